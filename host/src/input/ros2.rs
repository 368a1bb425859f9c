//! ROS 2 topics in, live, over DDS (RTPS) with no ROS installation: `sensor_msgs/PointCloud2`
//! and `sensor_msgs/Imu` subscribed as a ROS 2 node would, and the latched `/tf_static`.
//!
//! The readers take each message's serialised bytes (the CDR payload with its encapsulation
//! header, as a rosbag2 file stores it), and the bag decoders read them
//! ([`crate::input::bag::msg`]): the same field tables (Velodyne and Ouster driver layouts) and
//! the same conversion as `loglio bag`.
//!
//! Names and QoS: a ROS 2 topic `/velodyne_points` is the DDS topic `rt/velodyne_points` of type
//! `sensor_msgs::msg::dds_::PointCloud2_`. The LiDAR and IMU readers are reliable, volatile,
//! keep last [`CLOUD_DEPTH`] and [`IMU_DEPTH`]: they match reliable publishers (rclcpp's
//! default profile, the Velodyne driver's) and repair lost fragments of large clouds; a
//! best-effort publisher (rclcpp's sensor-data profile, ouster-ros's default) needs best-effort
//! readers ([`Ros2InputOptions::best_effort`]), since DDS does not match a reliable reader with
//! a best-effort writer. `/tf_static` is read reliable and transient local, as tf2's static
//! listener does, so a broadcaster that started earlier is heard.
//!
//! Discovery is the one of `--ros2` ([`crate::sink::ros2`]): SPDP multicast, and unicast to
//! `127.0.0.1` for same-host peers without multicast.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use rustdds::no_key::{DataReader, Decode, DefaultDecoder, DeserializerAdapter};
use rustdds::policy::{Durability, History, Reliability};
use rustdds::{
    DomainParticipant, DomainParticipantBuilder, QosPolicies, QosPolicyBuilder, RepresentationIdentifier,
    TopicKind,
};

use crate::error::PipelineError;
use crate::input::bag::msg::{self, Encoding, Imu, PointCloud2};

/// Clouds a reader keeps before they are taken.
pub const CLOUD_DEPTH: i32 = 10;
/// IMU messages a reader keeps before they are taken (1 s of a 1 kHz IMU).
pub const IMU_DEPTH: i32 = 1000;
/// How long the reading thread sleeps when no reader had anything.
const IDLE: Duration = Duration::from_millis(1);

/// A message's bytes as a rosbag2 file stores them: the CDR encapsulation header, then the
/// payload.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RawCdr(pub Vec<u8>);

/// The payload was in an encoding other than plain CDR.
#[derive(Debug)]
pub struct NotCdr;

impl std::fmt::Display for NotCdr {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("not plain CDR")
    }
}

impl std::error::Error for NotCdr {}

/// rustdds's adapter that keeps the bytes (no serde types: the bag decoders read them).
#[derive(Debug)]
pub struct RawCdrAdapter;

/// The decoder of [`RawCdrAdapter`].
#[derive(Clone, Copy, Debug)]
pub struct RawCdrDecoder;

impl DeserializerAdapter<RawCdr> for RawCdrAdapter {
    type Error = NotCdr;
    type Decoded = RawCdr;

    fn supported_encodings() -> &'static [RepresentationIdentifier] {
        &[RepresentationIdentifier::CDR_LE, RepresentationIdentifier::CDR_BE]
    }

    fn transform_decoded(decoded: RawCdr) -> RawCdr {
        decoded
    }
}

impl DefaultDecoder<RawCdr> for RawCdrAdapter {
    type Decoder = RawCdrDecoder;
    const DECODER: RawCdrDecoder = RawCdrDecoder;
}

impl<'de> Decode<'de, RawCdr> for RawCdrDecoder {
    type Error = NotCdr;

    fn decode_bytes(self, input: &'de [u8], encoding: RepresentationIdentifier) -> Result<RawCdr, NotCdr> {
        let head: [u8; 4] = if encoding == RepresentationIdentifier::CDR_LE {
            [0, 1, 0, 0]
        } else if encoding == RepresentationIdentifier::CDR_BE {
            [0, 0, 0, 0]
        } else {
            return Err(NotCdr);
        };
        let mut v = Vec::with_capacity(input.len() + 4);
        v.extend_from_slice(&head);
        v.extend_from_slice(input);
        Ok(RawCdr(v))
    }
}

/// What to subscribe to.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Ros2InputOptions {
    /// The DDS domain (`ROS_DOMAIN_ID`).
    pub domain: u16,
    /// The `sensor_msgs/PointCloud2` topic (`/velodyne_points`).
    pub lidar_topic: String,
    /// The `sensor_msgs/Imu` topic (`None`: no IMU).
    pub imu_topic: Option<String>,
    /// Read `/tf_static`.
    pub tf_static: bool,
    /// Best-effort LiDAR and IMU readers (for best-effort publishers).
    pub best_effort: bool,
}

/// One received message, decoded.
#[derive(Clone, Debug, PartialEq)]
pub enum Ros2Message {
    /// A cloud of the LiDAR topic.
    Cloud(PointCloud2),
    /// A sample of the IMU topic, with its `frame_id`.
    Imu(Imu, String),
    /// The transforms of a `/tf_static` message.
    TfStatic(Vec<msg::Transform>),
    /// A message of `topic` that could not be decoded (dropped).
    Malformed {
        /// The ROS 2 topic.
        topic: String,
        /// Why.
        why: String,
    },
}

/// A received message with its arrival time.
#[derive(Clone, Debug, PartialEq)]
pub struct Received {
    /// The message.
    pub msg: Ros2Message,
    /// When it was taken from the reader, ns since 1970 on this computer's clock.
    pub capture_ns: u64,
}

/// Checks a ROS 2 topic name (`/a/b`, or relative `a/b`, taken under `/`) and returns its DDS
/// name (`rt/a/b`).
pub fn dds_topic(flag: &str, topic: &str) -> Result<String, PipelineError> {
    let t = topic.trim_start_matches('/');
    let ok = !t.is_empty()
        && !t.ends_with('/')
        && t.split('/').all(|tok| {
            !tok.is_empty()
                && tok.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
                && !tok.starts_with(|c: char| c.is_ascii_digit())
        });
    if !ok {
        return Err(PipelineError(format!(
            "{flag} {topic:?} is not a ROS 2 topic name (tokens of letters, digits and '_', separated by '/')"
        )));
    }
    Ok(format!("rt/{t}"))
}

fn qos(depth: i32, reliable: bool, latched: bool) -> QosPolicies {
    let reliability = if reliable {
        Reliability::Reliable { max_blocking_time: rustdds::Duration::from_millis(100) }
    } else {
        Reliability::BestEffort
    };
    QosPolicyBuilder::new()
        .reliability(reliability)
        .history(History::KeepLast { depth })
        .durability(if latched { Durability::TransientLocal } else { Durability::Volatile })
        .build()
}

type Reader = DataReader<RawCdr, RawCdrAdapter>;

/// The subscriptions, read by a thread of their own until [`Ros2Subscriber::stop`] (or drop).
pub struct Ros2Subscriber {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for Ros2Subscriber {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ros2Subscriber").finish_non_exhaustive()
    }
}

fn now_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos() as u64)
}

impl Ros2Subscriber {
    /// Joins the domain, creates the readers and starts the thread that hands every message to
    /// `handle` (on that thread, in the order taken; `false` from `handle` ends the thread).
    pub fn start(
        opt: &Ros2InputOptions,
        mut handle: impl FnMut(Received) -> bool + Send + 'static,
    ) -> Result<Ros2Subscriber, PipelineError> {
        let lidar = dds_topic("--lidar-topic", &opt.lidar_topic)?;
        let imu = opt.imu_topic.as_deref().map(|t| dds_topic("--imu-topic", t)).transpose()?;
        let dds = |what: &str, e: &dyn std::fmt::Display| PipelineError(format!("DDS {what}: {e}"));
        let participant: DomainParticipant = DomainParticipantBuilder::new(opt.domain)
            .build()
            .map_err(|e| dds(&format!("cannot join domain {}", opt.domain), &e))?;
        let reliable = !opt.best_effort;
        let subscriber =
            participant.create_subscriber(&qos(10, reliable, false)).map_err(|e| dds("subscriber", &e))?;
        let reader = |name: &str, ty: &str, q: QosPolicies| -> Result<Reader, PipelineError> {
            let t = participant
                .create_topic(name.into(), ty.into(), &q, TopicKind::NoKey)
                .map_err(|e| dds(&format!("topic {name}"), &e))?;
            subscriber
                .create_datareader_no_key::<RawCdr, RawCdrAdapter>(&t, Some(q))
                .map_err(|e| dds(&format!("reader of {name}"), &e))
        };
        let mut readers: Vec<(Reader, String, Kind)> = Vec::new();
        readers.push((
            reader(&lidar, "sensor_msgs::msg::dds_::PointCloud2_", qos(CLOUD_DEPTH, reliable, false))?,
            opt.lidar_topic.clone(),
            Kind::Cloud,
        ));
        if let (Some(name), Some(topic)) = (&imu, &opt.imu_topic) {
            readers.push((
                reader(name, "sensor_msgs::msg::dds_::Imu_", qos(IMU_DEPTH, reliable, false))?,
                topic.clone(),
                Kind::Imu,
            ));
        }
        if opt.tf_static {
            readers.push((
                reader("rt/tf_static", "tf2_msgs::msg::dds_::TFMessage_", qos(100, true, true))?,
                "/tf_static".into(),
                Kind::Tf,
            ));
        }
        let stop = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&stop);
        let thread = std::thread::Builder::new()
            .name("loglio-ros2-in".into())
            .spawn(move || {
                // Dropped last: the readers need it.
                let _participant = participant;
                let _subscriber = subscriber;
                while !flag.load(Relaxed) {
                    let mut got = false;
                    for (r, topic, kind) in readers.iter_mut() {
                        // At most a burst per reader per round, so one topic cannot starve another.
                        for _ in 0..256 {
                            let msg = match r.take_next_sample() {
                                Ok(Some(s)) => kind.decode(&s.into_value().0, topic),
                                Ok(None) => break,
                                Err(e) => Ros2Message::Malformed { topic: topic.clone(), why: e.to_string() },
                            };
                            got = true;
                            if !handle(Received { msg, capture_ns: now_ns() }) {
                                return;
                            }
                        }
                    }
                    if !got {
                        std::thread::sleep(IDLE);
                    }
                }
            })
            .map_err(|e| PipelineError(format!("cannot start a thread: {e}")))?;
        Ok(Ros2Subscriber { stop, thread: Some(thread) })
    }

    /// Stops the thread and leaves the domain.
    pub fn stop(&mut self) {
        self.stop.store(true, Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for Ros2Subscriber {
    fn drop(&mut self) {
        self.stop();
    }
}

#[derive(Clone, Copy, Debug)]
enum Kind {
    Cloud,
    Imu,
    Tf,
}

impl Kind {
    fn decode(self, bytes: &[u8], topic: &str) -> Ros2Message {
        let r = match self {
            Kind::Cloud => PointCloud2::decode(bytes, Encoding::Cdr).map(Ros2Message::Cloud),
            Kind::Imu => Imu::decode(bytes, Encoding::Cdr).and_then(|m| {
                let (_, frame) = msg::Reader::new(bytes, Encoding::Cdr)?.header()?;
                Ok(Ros2Message::Imu(m, frame))
            }),
            Kind::Tf => msg::decode_tf(bytes, Encoding::Cdr).map(Ros2Message::TfStatic),
        };
        r.unwrap_or_else(|e| Ros2Message::Malformed { topic: topic.to_string(), why: e.0 })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topic_names_get_the_rt_prefix() {
        assert_eq!(dds_topic("--lidar-topic", "/velodyne_points").unwrap(), "rt/velodyne_points");
        assert_eq!(dds_topic("--imu-topic", "imu/data").unwrap(), "rt/imu/data");
        for bad in ["", "/", "/a//b", "/a b", "/1abc", "/a/"] {
            let e = dds_topic("--lidar-topic", bad).unwrap_err();
            assert!(e.0.starts_with("--lidar-topic "), "{e}");
        }
    }

    #[test]
    fn raw_payloads_get_their_encapsulation_header_back() {
        let m = Imu {
            stamp_ns: 1_700_000_000_123_456_789,
            orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
            angular_velocity: [0.1, -0.2, 0.3],
            linear_acceleration: [0.0, 0.5, 9.81],
        };
        let bytes = m.encode("imu_link", Encoding::Cdr);
        let raw = RawCdrDecoder.decode_bytes(&bytes[4..], RepresentationIdentifier::CDR_LE).unwrap();
        assert_eq!(raw.0, bytes);
        assert_eq!(Imu::decode(&raw.0, Encoding::Cdr).unwrap(), m);
        assert!(RawCdrDecoder.decode_bytes(&bytes[4..], RepresentationIdentifier::PL_CDR_LE).is_err());
    }
}
