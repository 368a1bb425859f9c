//! `loglio ros2` against an independent DDS publisher: a Cyclone DDS (Python) node declares
//! `sensor_msgs/PointCloud2`, `sensor_msgs/Imu` and `tf2_msgs/TFMessage` with its own IDL types
//! and publishes a simulated drive in real time: Velodyne driver clouds (`x, y, z, intensity`
//! float32, `ring` uint16, `time` float32 seconds after the header stamp) on
//! `/velodyne_points`, the IMU on `/imu/data`, and the rig's extrinsic on `/tf_static`
//! (transient local, as tf2's static broadcaster publishes it). loglio runs on the topics until
//! SIGTERM; every scan published must be processed and the trajectory must track the
//! simulator's ground truth with the extrinsic taken from `/tf_static`.
//!
//! The numbers come from the simulator (this test writes them into a plain file: per scan its
//! stamp and its points, per IMU sample its time and readings); the publisher builds the
//! messages itself. Discovery and domains as in `ros2.rs` (loopback unicast, a domain per
//! process). Needs the peers' Python (`LOGLIO_PYTHON`, see [`common::peer_python`]).

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Instant;

use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Event, Scenario, ScenarioConfig, ScenarioKind};

mod common;

/// The publisher: reads `drive.bin` and publishes it paced by its times (`rate` x real time),
/// once every writer has matched a reader. Prints `published <scans> <imu>` at the end.
const PUBLISHER: &str = r#"import struct, sys, time
from dataclasses import dataclass
from cyclonedds.domain import DomainParticipant
from cyclonedds.topic import Topic
from cyclonedds.pub import DataWriter
from cyclonedds.core import Qos, Policy
from cyclonedds.idl import IdlStruct
from cyclonedds.util import duration
from cyclonedds.idl.types import int32, uint32, uint8, uint16, float32, float64, sequence, array

@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32

@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str

@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64
    y: float64
    z: float64

@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64
    y: float64
    z: float64
    w: float64

@dataclass
class Imu(IdlStruct, typename="sensor_msgs::msg::dds_::Imu_"):
    header: Header
    orientation: Quaternion
    orientation_covariance: array[float64, 9]
    angular_velocity: Vector3
    angular_velocity_covariance: array[float64, 9]
    linear_acceleration: Vector3
    linear_acceleration_covariance: array[float64, 9]

@dataclass
class PointField(IdlStruct, typename="sensor_msgs::msg::dds_::PointField_"):
    name: str
    offset: uint32
    datatype: uint8
    count: uint32

@dataclass
class PointCloud2(IdlStruct, typename="sensor_msgs::msg::dds_::PointCloud2_"):
    header: Header
    height: uint32
    width: uint32
    fields: sequence[PointField]
    is_bigendian: bool
    point_step: uint32
    row_step: uint32
    data: sequence[uint8]
    is_dense: bool

@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3
    rotation: Quaternion

@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header
    child_frame_id: str
    transform: Transform

@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: sequence[TransformStamped]

def qos(depth, latched=False):
    p = [Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)), Policy.History.KeepLast(depth)]
    if latched:
        p.append(Policy.Durability.TransientLocal)
    return Qos(*p)

domain, path, rate = int(sys.argv[1]), sys.argv[2], float(sys.argv[3])
tf_t = [float(v) for v in sys.argv[4].split(",")]  # tx ty tz qx qy qz qw
dp = DomainParticipant(domain)
w_cloud = DataWriter(dp, Topic(dp, "rt/velodyne_points", PointCloud2), qos=qos(10))
w_imu = DataWriter(dp, Topic(dp, "rt/imu/data", Imu), qos=qos(1000))
w_tf = DataWriter(dp, Topic(dp, "rt/tf_static", TFMessage), qos=qos(1, True))

def stamp(ns):
    return Time(sec=ns // 1000000000, nanosec=ns % 1000000000)

# The static transform first, as a robot's launch file does: the LiDAR's pose in the IMU frame.
w_tf.write(TFMessage(transforms=[TransformStamped(
    header=Header(stamp=stamp(0), frame_id="imu_link"), child_frame_id="velodyne",
    transform=Transform(translation=Vector3(*tf_t[:3]), rotation=Quaternion(*tf_t[3:])))]))

deadline = time.monotonic() + 20
while (not w_cloud.get_matched_subscriptions() or not w_imu.get_matched_subscriptions()) and time.monotonic() < deadline:
    time.sleep(0.01)
print("matched", flush=True)
# The Velodyne driver's point layout, declared here: 22 bytes a point.
FIELDS = [PointField(name="x", offset=0, datatype=7, count=1), PointField(name="y", offset=4, datatype=7, count=1),
          PointField(name="z", offset=8, datatype=7, count=1), PointField(name="intensity", offset=12, datatype=7, count=1),
          PointField(name="ring", offset=16, datatype=4, count=1), PointField(name="time", offset=18, datatype=7, count=1)]
STEP = 22
ZERO9 = [0.0] * 9
scans = imus = 0
t_first = wall0 = None
with open(path, "rb") as f:
    while True:
        kind = f.read(1)
        if not kind:
            break
        if kind == b"I":
            t, gx, gy, gz, ax, ay, az = struct.unpack("<Q6d", f.read(56))
            due = t
        else:
            t, end, n = struct.unpack("<QQI", f.read(20))
            points = f.read(n * STEP)
            due = end
        if t_first is None:
            t_first, wall0 = due, time.monotonic()
        wait = wall0 + (due - t_first) * 1e-9 / rate - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        if kind == b"I":
            w_imu.write(Imu(header=Header(stamp=stamp(t), frame_id="imu_link"),
                            orientation=Quaternion(0.0, 0.0, 0.0, 1.0), orientation_covariance=[-1.0] + ZERO9[1:],
                            angular_velocity=Vector3(gx, gy, gz), angular_velocity_covariance=ZERO9,
                            linear_acceleration=Vector3(ax, ay, az), linear_acceleration_covariance=ZERO9))
            imus += 1
        else:
            w_cloud.write(PointCloud2(header=Header(stamp=stamp(t), frame_id="velodyne"), height=1, width=n,
                                      fields=FIELDS, is_bigendian=False, point_step=STEP, row_step=STEP * n,
                                      data=points, is_dense=True))
            scans += 1
# Reliable writers: what was written reaches the reader before the node leaves.
time.sleep(1.0)
print("published %d %d" % (scans, imus), flush=True)
"#;

/// Writes `drive.bin` (the publisher's numbers) and `gt.tum` of a VLP-32C vehicle drive;
/// returns (scans, IMU samples, the `/tf_static` argument).
fn write_drive(dir: &Path, seconds: f64) -> (usize, usize, String) {
    let mut c = ScenarioConfig::new(ScenarioKind::Vehicle, SensorModel::Vlp32c, 2);
    c.duration_s = seconds;
    let sc = Scenario::from_config(c).unwrap();
    let rows = sc.layout().rows() as u16;
    let (mut bin, mut gt) = (Vec::new(), String::new());
    let (mut scans, mut imus) = (0, 0);
    for ev in sc.events() {
        match ev {
            Event::Imu(s) => {
                bin.push(b'I');
                bin.extend_from_slice(&s.t_ns.to_le_bytes());
                for v in s.gyro.iter().chain(&s.acc) {
                    bin.extend_from_slice(&f64::from(*v).to_le_bytes());
                }
                imus += 1;
            }
            Event::Scan(s) => {
                bin.push(b'S');
                bin.extend_from_slice(&s.start_ns.to_le_bytes());
                bin.extend_from_slice(&s.end_ns.to_le_bytes());
                bin.extend_from_slice(&(s.points.len() as u32).to_le_bytes());
                for p in &s.points {
                    for v in [p.xyz[0], p.xyz[1], p.xyz[2], p.intensity as f32] {
                        bin.extend_from_slice(&v.to_le_bytes());
                    }
                    // The Velodyne driver's ring 0 is the lowest beam; row 0 is the highest.
                    bin.extend_from_slice(&(rows - 1 - p.row).to_le_bytes());
                    bin.extend_from_slice(&p.t.to_le_bytes());
                }
                scans += 1;
                let g = sc.pose_at(s.end_ns);
                let q = g.rotation.quaternion();
                gt.push_str(&format!(
                    "{}.{:09} {} {} {} {} {} {} {}\n",
                    s.end_ns / 1_000_000_000,
                    s.end_ns % 1_000_000_000,
                    g.translation.x,
                    g.translation.y,
                    g.translation.z,
                    q.i,
                    q.j,
                    q.k,
                    q.w
                ));
            }
        }
    }
    std::fs::write(dir.join("drive.bin"), bin).unwrap();
    std::fs::write(dir.join("gt.tum"), gt).unwrap();
    let e = sc.extrinsic();
    let q = e.rotation.quaternion();
    let tf = [e.translation.x, e.translation.y, e.translation.z, q.i, q.j, q.k, q.w]
        .map(|v| format!("{v:.17}"))
        .join(",");
    (scans, imus, tf)
}

/// Kills the loglio run if the test fails before it stopped it.
struct KillOnDrop(Option<u32>);

impl Drop for KillOnDrop {
    fn drop(&mut self) {
        if let Some(pid) = self.0 {
            let _ = Command::new("kill").arg("-KILL").arg(pid.to_string()).status();
        }
    }
}

fn domain() -> String {
    (1 + (std::process::id() * 3 + 7) % 200).to_string()
}

#[test]
fn ros2_topics_from_a_cyclone_dds_publisher_drive_the_odometry() {
    let test = "ros2_topics_from_a_cyclone_dds_publisher_drive_the_odometry";
    let Some(python) = common::peer_python(test) else { return };
    if let Some(r) = common::runner() {
        println!("{test}: skipped under LOGLIO_TEST_RUNNER ({r}): the emulated run cannot keep real time");
        return;
    }
    let wall = Instant::now();
    let dir = common::scratch("ros2in", "drive");
    let (scans, imus, tf) = write_drive(&dir, 6.0);
    let domain = domain();
    let p = |f: &str| dir.join(f).to_str().unwrap().to_string();
    std::fs::write(dir.join("pub.py"), PUBLISHER).unwrap();
    std::fs::write(dir.join("cyclonedds.xml"), common::CYCLONE_XML).unwrap();

    // loglio first (it waits for the first cloud), then the publisher.
    let loglio = common::loglio_command(&[
        "ros2",
        "--lidar-topic",
        "/velodyne_points",
        "--imu-topic",
        "/imu/data",
        "--preset",
        "vlp32c",
        "--gt",
        &p("gt.tum"),
        "--out",
        &p("out"),
        "--lidar-timeout",
        "30",
        "--seconds",
        "40",
    ])
    .env("ROS_DOMAIN_ID", &domain)
    .stdout(Stdio::piped())
    .stderr(Stdio::piped())
    .spawn()
    .unwrap();
    let mut guard = KillOnDrop(Some(loglio.id()));
    let mut publisher = Command::new(&python)
        .arg(p("pub.py"))
        .arg(&domain)
        .arg(p("drive.bin"))
        .arg("1.0")
        .arg(&tf)
        .env("CYCLONEDDS_URI", format!("file://{}", p("cyclonedds.xml")))
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run {}: {e}", python.display()));
    let lines: Vec<String> =
        BufReader::new(publisher.stdout.take().unwrap()).lines().map_while(Result::ok).collect();
    let published_at = wall.elapsed().as_secs_f64();
    assert!(publisher.wait().unwrap().success(), "the publisher failed: {lines:?}");
    assert_eq!(lines.first().map(String::as_str), Some("matched"), "{lines:?}");
    assert_eq!(lines.last(), Some(&format!("published {scans} {imus}")), "{lines:?}");
    // Everything was sent (the publisher waited for the acknowledgements): SIGTERM, as a robot's
    // launch system stops a node; the run writes its outputs.
    let killed = Command::new("kill").arg("-TERM").arg(loglio.id().to_string()).status().unwrap();
    assert!(killed.success());
    let out = loglio.wait_with_output().unwrap();
    guard.0 = None;
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    let wall_s = wall.elapsed().as_secs_f64();
    assert!(out.status.success(), "{err}\n{text}");
    assert!(!err.contains("panicked"), "{err}");
    let ate = common::number_after(&text, "rmse");
    println!(
        "ros2 input: {scans} scans and {imus} IMU samples published in {published_at:.1} s, ATE {ate:.4} m, test {wall_s:.1} s\n{text}\n{err}"
    );
    assert!(
        text.starts_with(&format!(
            "ros2: LiDAR /velodyne_points, IMU /imu/data, domain {domain}; stopped by a signal; {scans} clouds, {imus} IMU messages, 1 /tf_static messages; drops: malformed 0, IMU 0, scans 0\n"
        )),
        "{text}"
    );
    // The scenario's true extrinsic, from /tf_static (no configuration, no --extrinsic).
    assert!(
        text.contains("\nextrinsic from /tf_static (velodyne in imu_link): t = [0.0800, -0.0400, 0.0500] m, q wxyz = [0.9998, 0.0045, -0.0086, 0.0175]\n"),
        "{text}"
    );
    assert!(!err.contains("no LiDAR-IMU extrinsic"), "{err}");
    // Every scan published was processed.
    assert!(text.contains(&format!("\n{scans} scans (")), "{text}");
    // Measured 2026-11-27: 0.008 m (`loglio sim` on the same drive, without the clouds' float32
    // times and the messages: 0.004 m); the extrinsic is too small to move the ATE (identity:
    // 0.009 m), so the line above checks that it was used.
    assert!(ate < 0.02, "ATE {ate} m: {text}");
    let tum = std::fs::read_to_string(dir.join("out/trajectory.tum")).unwrap();
    assert!(tum.lines().filter(|l| !l.starts_with('#')).count() >= scans / 2, "{tum}");
    assert!(wall_s < 60.0, "the test took {wall_s:.1} s");
    let _ = std::fs::remove_dir_all(&dir);
}
