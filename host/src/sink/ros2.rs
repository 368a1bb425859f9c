//! `--ros2`: every pose, scan and map published over DDS (RTPS) the way a ROS 2 node would,
//! so a robot's ROS 2 stack subscribes to loglio with no ROS installed on loglio's side.
//!
//! Topics (under `--ros2-namespace`, default `/loglio`; DDS names get ROS 2's `rt` prefix and
//! types their `dds_` names, e.g. `rt/loglio/odometry`, `nav_msgs::msg::dds_::Odometry_`):
//!
//! | topic | type | when | QoS |
//! |---|---|---|---|
//! | `odometry` | `nav_msgs/Odometry` | each scan | reliable, volatile, keep last 10 |
//! | `odometry_imu` | `nav_msgs/Odometry` | each IMU sample between scans | reliable, volatile, keep last 10 |
//! | `/tf` | `tf2_msgs/TFMessage` | each scan | reliable, volatile, keep last 100 |
//! | `cloud` | `sensor_msgs/PointCloud2` | each scan | reliable, volatile, keep last 5 |
//! | `map` | `sensor_msgs/PointCloud2` | every `--map-every` s | reliable, transient local, keep last 1 |
//!
//! QoS: rclcpp's default profile is reliable, volatile, keep last 10, and a reliable writer
//! serves both reliable and best-effort (sensor-data profile) readers, while a best-effort one
//! would not match rclcpp's default subscriptions: every topic is reliable. `/tf` keeps 100
//! as tf2_ros's broadcaster does; the cloud keeps 5 as the sensor-data profile does; the map is
//! transient local (a latched topic: a late subscriber gets the last map; rviz's "Transient
//! Local" durability). A write waits at most [`MAX_BLOCKING`] for a slow reader's
//! acknowledgements, then the sample is counted as an error: a reader that vanishes costs at
//! most that per event until its lease expires, and never blocks the odometry (the sink has
//! its own thread and queue).
//!
//! Discovery is plain RTPS: SPDP multicast on the ROS 2 ports of `ROS_DOMAIN_ID` (default 0)
//! on every interface, and also SPDP unicast to `127.0.0.1` at the well-known ports of
//! participant indices 0-11, so same-host nodes find loglio even where no interface has
//! multicast (a Cyclone DDS node then needs `127.0.0.1` among its `Discovery/Peers`; with a
//! multicast interface Cyclone's defaults work as they are). Tested against Cyclone DDS.

use std::time::{Duration, Instant};

use nalgebra::{Matrix3, Matrix6, Quaternion as NQuat, UnitQuaternion};
use rustdds::no_key::DataWriter;
use rustdds::policy::{Durability, History, Reliability};
use rustdds::{DomainParticipant, DomainParticipantBuilder, QosPolicies, QosPolicyBuilder, TopicKind};

use super::{PoseSample, ScanOutput, Sink, SinkError, SinkEvent, Wants};

pub mod msg;

use msg::{
    Cov6, Header, Odometry, PointCloud2, Pose, PoseWithCovariance, Quaternion, TfMessage, Time, Transform,
    TransformStamped, Twist, TwistWithCovariance,
};

/// The longest a write waits for a reliable reader's acknowledgements (rclcpp's default is
/// 100 ms too).
pub const MAX_BLOCKING: Duration = Duration::from_millis(100);

/// How long the end of a run waits for the readers to acknowledge what was written.
const FINISH_ACK_WAIT: Duration = Duration::from_secs(2);

/// Variance of the published angular rate, (rad/s)^2: the rate is the last gyro sample less
/// the estimated bias, so its error is the gyro's white noise, about 0.01 rad/s for MEMS IMUs.
pub const GYRO_RATE_VARIANCE: f64 = 1e-4;

/// What `--ros2` publishes and under which names.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Ros2Options {
    /// The DDS domain (`ROS_DOMAIN_ID`).
    pub domain: u16,
    /// Namespace of the topics (`/loglio`); `/tf` is global.
    pub namespace: String,
    /// The world frame (`odom`).
    pub frame_id: String,
    /// The body frame (`base_link`).
    pub child_frame_id: String,
}

impl Default for Ros2Options {
    fn default() -> Self {
        Ros2Options {
            domain: 0,
            namespace: "/loglio".into(),
            frame_id: "odom".into(),
            child_frame_id: "base_link".into(),
        }
    }
}

/// The domain of `ROS_DOMAIN_ID` (unset or blank: 0), as ROS 2 reads it.
pub fn domain_from_env(v: Option<&str>) -> Result<u16, SinkError> {
    match v.map(str::trim).filter(|v| !v.is_empty()) {
        None => Ok(0),
        // RTPS's port mapping leaves room for domains 0-232.
        Some(v) => match v.parse::<u16>() {
            Ok(d) if d <= 232 => Ok(d),
            _ => Err(SinkError(format!("ROS_DOMAIN_ID={v:?} is not a domain id (0-232)"))),
        },
    }
}

/// Checks a ROS 2 namespace (`/a/b`: tokens of letters, digits and `_`, not starting with a
/// digit) and returns it without a trailing `/` (`/` alone gives the empty prefix).
pub fn check_namespace(ns: &str) -> Result<String, SinkError> {
    let bad = |why: &str| Err(SinkError(format!("--ros2-namespace {ns:?}: {why}")));
    let Some(rest) = ns.strip_prefix('/') else { return bad("must start with '/'") };
    let rest = rest.strip_suffix('/').unwrap_or(rest);
    if rest.is_empty() {
        return Ok(String::new());
    }
    for tok in rest.split('/') {
        let ok = !tok.is_empty()
            && tok.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
            && !tok.starts_with(|c: char| c.is_ascii_digit());
        if !ok {
            return bad("tokens are letters, digits and '_', not starting with a digit");
        }
    }
    Ok(format!("/{rest}"))
}

/// Checks a frame id (non-empty, no whitespace; tf2 wants no leading '/').
pub fn check_frame(flag: &str, f: &str) -> Result<(), SinkError> {
    if f.is_empty() || f.chars().any(char::is_whitespace) || f.starts_with('/') {
        return Err(SinkError(format!(
            "{flag} {f:?}: a frame id is non-empty, without spaces or a leading '/'"
        )));
    }
    Ok(())
}

/// The ROS 2 odometry message of `p` (ROS's pose covariance order: position, then rotation
/// about the world's axes; the twist in the body frame).
pub fn odometry(p: &PoseSample, frame_id: &str, child_frame_id: &str) -> Odometry {
    Odometry {
        header: Header { stamp: Time::from_ns(p.t_ns), frame_id: frame_id.into() },
        child_frame_id: child_frame_id.into(),
        pose: PoseWithCovariance {
            pose: Pose { position: p.position.into(), orientation: Quaternion::from_wxyz(p.q_wxyz) },
            covariance: pose_covariance_world(p),
        },
        twist: TwistWithCovariance {
            twist: Twist { linear: p.velocity_body.into(), angular: p.angular_velocity_body.into() },
            covariance: twist_covariance(p),
        },
    }
}

/// The pose covariance with the rotation error turned from the body frame (the filter's) into
/// the world frame (ROS's "rotation about X, Y, Z" of the pose's frame): J P J^T, J = diag(I, R).
fn pose_covariance_world(p: &PoseSample) -> Cov6 {
    let q = UnitQuaternion::from_quaternion(NQuat::new(p.q_wxyz[0], p.q_wxyz[1], p.q_wxyz[2], p.q_wxyz[3]));
    let r = q.to_rotation_matrix().into_inner();
    let mut j = Matrix6::<f64>::identity();
    j.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    let m = Matrix6::from_fn(|i, k| p.pose_covariance[i][k]);
    let w = j * m * j.transpose();
    let mut out = [0.0; 36];
    for i in 0..6 {
        for k in 0..6 {
            // Symmetric by construction; averaging removes rounding asymmetry.
            out[i * 6 + k] = 0.5 * (w[(i, k)] + w[(k, i)]);
        }
    }
    Cov6(out)
}

/// The body velocity's covariance and [`GYRO_RATE_VARIANCE`] on the angular rates.
fn twist_covariance(p: &PoseSample) -> Cov6 {
    let v = Matrix3::from_fn(|i, k| p.velocity_covariance[i][k]);
    let mut out = [0.0; 36];
    for i in 0..3 {
        for k in 0..3 {
            out[i * 6 + k] = v[(i, k)];
        }
        out[(i + 3) * 6 + i + 3] = GYRO_RATE_VARIANCE;
    }
    Cov6(out)
}

/// The `/tf` message of `p`: `frame_id` -> `child_frame_id`.
pub fn transform(p: &PoseSample, frame_id: &str, child_frame_id: &str) -> TfMessage {
    TfMessage {
        transforms: vec![TransformStamped {
            header: Header { stamp: Time::from_ns(p.t_ns), frame_id: frame_id.into() },
            child_frame_id: child_frame_id.into(),
            transform: Transform {
                translation: p.position.into(),
                rotation: Quaternion::from_wxyz(p.q_wxyz),
            },
        }],
    }
}

/// A reliable QoS with `depth` samples kept, latched (transient local) or not.
fn qos(depth: i32, latched: bool) -> QosPolicies {
    let blocking = rustdds::Duration::from_std(MAX_BLOCKING);
    QosPolicyBuilder::new()
        .reliability(Reliability::Reliable { max_blocking_time: blocking })
        .history(History::KeepLast { depth })
        .durability(if latched { Durability::TransientLocal } else { Durability::Volatile })
        .build()
}

/// The publisher of `--ros2`.
pub struct Ros2Sink {
    opt: Ros2Options,
    odom: DataWriter<Odometry>,
    odom_imu: DataWriter<Odometry>,
    tf: DataWriter<TfMessage>,
    cloud: DataWriter<PointCloud2>,
    map: DataWriter<PointCloud2>,
    /// When the latest scan's odometry was written (the cloud and the map follow it).
    pose_sent: Option<Instant>,
    // Dropped last: the writers need it.
    _participant: DomainParticipant,
}

impl std::fmt::Debug for Ros2Sink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ros2Sink").field("opt", &self.opt).finish()
    }
}

impl Ros2Sink {
    /// Joins the DDS domain and creates the writers (one line on failure: a port, a socket).
    pub fn start(opt: Ros2Options) -> Result<Ros2Sink, SinkError> {
        let namespace = check_namespace(&opt.namespace)?;
        check_frame("--ros2-frame-id", &opt.frame_id)?;
        check_frame("--ros2-child-frame-id", &opt.child_frame_id)?;
        let dds = |what: &str, e: &dyn std::fmt::Display| SinkError(format!("DDS {what}: {e}"));
        let participant = DomainParticipantBuilder::new(opt.domain)
            .build()
            .map_err(|e| dds(&format!("cannot join domain {}", opt.domain), &e))?;
        let publisher = participant.create_publisher(&qos(10, false)).map_err(|e| dds("publisher", &e))?;
        let topic = |name: &str, ty: &str, q: &QosPolicies| {
            participant
                .create_topic(name.into(), ty.into(), q, TopicKind::NoKey)
                .map_err(|e| dds(&format!("topic {name}"), &e))
        };
        const ODOM: &str = "nav_msgs::msg::dds_::Odometry_";
        const CLOUD: &str = "sensor_msgs::msg::dds_::PointCloud2_";
        let writer = |name: &str, ty: &str, q: QosPolicies| {
            let t = topic(name, ty, &q)?;
            Ok::<_, SinkError>((t, q))
        };
        let (t, q) = writer(&format!("rt{namespace}/odometry"), ODOM, qos(10, false))?;
        let odom = publisher.create_datawriter_no_key_cdr(&t, Some(q)).map_err(|e| dds("writer", &e))?;
        let (t, q) = writer(&format!("rt{namespace}/odometry_imu"), ODOM, qos(10, false))?;
        let odom_imu = publisher.create_datawriter_no_key_cdr(&t, Some(q)).map_err(|e| dds("writer", &e))?;
        let (t, q) = writer("rt/tf", "tf2_msgs::msg::dds_::TFMessage_", qos(100, false))?;
        let tf = publisher.create_datawriter_no_key_cdr(&t, Some(q)).map_err(|e| dds("writer", &e))?;
        let (t, q) = writer(&format!("rt{namespace}/cloud"), CLOUD, qos(5, false))?;
        let cloud = publisher.create_datawriter_no_key_cdr(&t, Some(q)).map_err(|e| dds("writer", &e))?;
        let (t, q) = writer(&format!("rt{namespace}/map"), CLOUD, qos(1, true))?;
        let map = publisher.create_datawriter_no_key_cdr(&t, Some(q)).map_err(|e| dds("writer", &e))?;
        Ok(Ros2Sink { opt, odom, odom_imu, tf, cloud, map, pose_sent: None, _participant: participant })
    }

    fn header(&self, t_ns: u64) -> Header {
        Header { stamp: Time::from_ns(t_ns), frame_id: self.opt.frame_id.clone() }
    }

    fn scan(&mut self, s: &ScanOutput) -> Result<(), SinkError> {
        // Before the IMU initialisation the pose is a placeholder (trajectory.tum leaves it out too).
        if s.pose.status == super::LiveStatus::Initialising {
            return Ok(());
        }
        let (f, c) = (&self.opt.frame_id, &self.opt.child_frame_id);
        let mut first_err = None;
        let mut note = |what: &str, r: Result<(), String>| {
            if let Err(e) = r {
                first_err.get_or_insert_with(|| SinkError(format!("{what}: {e}")));
            }
        };
        let odom = self.odom.write(odometry(&s.pose, f, c), None).map_err(|e| e.to_string());
        self.pose_sent = odom.is_ok().then(Instant::now);
        note("odometry", odom);
        note("tf", self.tf.write(transform(&s.pose, f, c), None).map_err(|e| e.to_string()));
        if let Some(pts) = &s.cloud {
            let m = PointCloud2::xyz(self.header(s.pose.t_ns), pts.iter());
            note("cloud", self.cloud.write(m, None).map_err(|e| e.to_string()));
        }
        if let Some(map) = &s.map {
            let m = PointCloud2::xyz(self.header(s.pose.t_ns), map.iter().map(|p| &p.xyz));
            note("map", self.map.write(m, None).map_err(|e| e.to_string()));
        }
        first_err.map_or(Ok(()), Err)
    }
}

impl Sink for Ros2Sink {
    fn name(&self) -> String {
        format!("ros2 domain {}", self.opt.domain)
    }

    fn wants(&self) -> Wants {
        Wants { cloud: true, map: true, imu_pose: true }
    }

    fn handle(&mut self, ev: &SinkEvent) -> Result<(), SinkError> {
        match ev {
            SinkEvent::Scan(s) => self.scan(s),
            SinkEvent::ImuPose(p) => {
                let m = odometry(p, &self.opt.frame_id, &self.opt.child_frame_id);
                self.odom_imu.write(m, None).map_err(|e| SinkError(format!("odometry_imu: {e}")))
            }
        }
    }

    fn pose_sent(&mut self) -> Option<Instant> {
        self.pose_sent.take()
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        // Reliable readers get what was written before the participant leaves; one that does
        // not acknowledge within FINISH_ACK_WAIT (all writers together) is not waited for.
        let deadline = std::time::Instant::now() + FINISH_ACK_WAIT;
        let left = || deadline.saturating_duration_since(std::time::Instant::now());
        let _ = self.odom.wait_for_acknowledgments(left());
        let _ = self.odom_imu.wait_for_acknowledgments(left());
        let _ = self.tf.wait_for_acknowledgments(left());
        let _ = self.cloud.wait_for_acknowledgments(left());
        let _ = self.map.wait_for_acknowledgments(left());
        Ok(())
    }
}

#[cfg(test)]
mod tests;
