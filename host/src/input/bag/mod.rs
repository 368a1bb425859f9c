//! ROS bags in, a time-ordered stream of [`BagEvent`]s out.
//!
//! Formats: ROS 1 bags (`.bag`, uncompressed, bz2 or lz4 chunks; the format of M2DGR and NTU
//! VIRAL), ROS 2 bags in sqlite3 (`.db3` or a rosbag2 directory) and MCAP (`.mcap`, CDR or ROS 1
//! messages). Messages: `sensor_msgs/PointCloud2` (Velodyne and Ouster driver fields, or any
//! field table, see [`cloud`]), `sensor_msgs/Imu`, `velodyne_msgs/VelodyneScan` (raw 1206-byte
//! packets), Ouster `PacketMsg` (raw lidar and IMU packets) and the Ouster driver's metadata
//! string.
//!
//! ```no_run
//! use loglio_host::input::bag::{BagEvent, BagOptions, BagReader};
//! use loglio_host::config::{Config, Preset};
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let cfg = Config::preset(Preset::Vlp16);
//! let mut bag = BagReader::open("run.bag".as_ref(), BagOptions::from_config(&cfg)?)?;
//! for item in &mut bag {
//!     match item?.event {
//!         BagEvent::Scan(scan) => { /* scan.stamp_ns, scan.points */ }
//!         BagEvent::Imu(sample) => { /* loglio_core::imu::ImuSample */ }
//!         BagEvent::LidarPacket(p) => { /* raw bytes for the core's decoders */ }
//!         BagEvent::OusterMetadata(json) => { /* the sensor's metadata */ }
//!     }
//! }
//! println!("{}", bag.stats());
//! # Ok(()) }
//! ```
//!
//! **Topics** are chosen by message type unless named ([`BagOptions::lidar_topic`],
//! [`BagOptions::imu_topic`]): the one PointCloud2 topic, else the one VelodyneScan topic, else
//! the Ouster packet topics; the one Imu topic (or the Ouster IMU packets). Several candidates,
//! a named topic that is missing or of the wrong type, or no LiDAR (or IMU, when required)
//! topic at all: one error line that lists the bag's topics.
//!
//! **Order**: events come in the order of the bags' record (receive) times. Messages are
//! held for [`BagOptions::reorder_window_ns`] to sort small disorder; a message older than one
//! already delivered is dropped and counted ([`BagStats::late`]). A record time more than
//! [`JUMP_NS`] past the window's newest is held back until [`JUMP_CONFIRM`] messages in a row
//! agree on the jump (a gap in the recording); a corrupt time, which the next messages do not
//! follow, is dropped and counted ([`BagStats::out_of_sequence`]). Taken at its word, one such
//! time would end the sorting for the rest of the bag, and its slightly disordered messages
//! would be dropped as late (24 of 52 in the test). The window's newest time starts from the
//! median of the first [`JUMP_CONFIRM`] messages, which are all delivered (a corrupt time among
//! them comes first or last).
//!
//! **Stamps**: with `use_record_time` off (`time.lidar_time_source = "packet"`) events carry the
//! messages' own stamps: a scan's start is its header stamp plus its earliest point time (see
//! [`cloud`]); IMU samples their header stamps; Velodyne packets their packet stamps; Ouster
//! packets (which have no stamp in the message) the record time. With it on (`"capture"`)
//! every event carries the record time (for a cloud: the record time minus its last point's
//! time, i.e. the record time taken as the scan end). Time offsets are not applied here
//! (`time_align.rs` does that).
//!
//! **Bad input**: a damaged file gives what it still holds. A ROS 1 bag that was never closed,
//! was cut short or has a corrupt index is read by walking its records up to the damage (as
//! `rosbag reindex` would); a rosbag2 database with damaged pages gives its rows before the
//! damage; each with one warning saying how much was recovered ([`BagStats::unindexed`],
//! [`BagStats::truncated_files`]). A file that is no bag, or a cut MCAP: one error line (the
//! good messages before the damage come first where the format allows). A corrupt ROS 1 chunk
//! is skipped and counted; a malformed message is dropped and counted; each with one warning. Clouds without ring or time fields fall back to geometry
//! with one warning per topic.

pub mod cloud;
mod mcap_src;
pub mod msg;
mod ros1;
mod ros1_scan;
pub mod ros1_writer;
mod ros2_sqlite;

use std::collections::{BinaryHeap, HashSet};
use std::fmt;
use std::path::{Path, PathBuf};

use loglio_core::imu::ImuSample;
use loglio_core::scan::ScanPoint;

use self::cloud::{CloudOptions, cloud_to_scan};
use self::msg::{Encoding, Imu, PointCloud2, VelodyneScan, decode_packet_msg, decode_string};
use crate::config::{Config, ConfigError, LidarTimeSource};
use crate::diag::warn;

/// A bag could not be read: one line naming the file and the problem.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BagError(pub String);

impl fmt::Display for BagError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for BagError {}

/// Storage format of a bag.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BagFormat {
    /// ROS 1 bag, format 2.0.
    Ros1,
    /// rosbag2 sqlite3 (`.db3`).
    Ros2Sqlite,
    /// MCAP.
    Mcap,
}

impl fmt::Display for BagFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            BagFormat::Ros1 => "ROS 1 bag",
            BagFormat::Ros2Sqlite => "rosbag2 sqlite3",
            BagFormat::Mcap => "MCAP",
        })
    }
}

/// What a topic carries, by message type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TopicKind {
    /// `sensor_msgs/PointCloud2`.
    PointCloud2,
    /// `sensor_msgs/Imu`.
    Imu,
    /// `velodyne_msgs/VelodyneScan`.
    VelodyneScan,
    /// Ouster `PacketMsg` (lidar or IMU packets).
    OusterPacket,
    /// `std_msgs/String` (the Ouster driver's metadata).
    Text,
    /// `tf2_msgs/TFMessage` (`/tf_static`: the sensors' frames).
    Tf,
    /// Anything else.
    Other,
}

/// A topic of the bag.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TopicInfo {
    /// Topic name.
    pub name: String,
    /// Message type, ROS 1 style (`sensor_msgs/PointCloud2`, also for ROS 2 bags).
    pub msg_type: String,
    /// Wire encoding, `None` if loglio cannot decode it.
    pub encoding: Option<Encoding>,
    /// Number of messages, when the bag says.
    pub count: Option<u64>,
}

impl TopicInfo {
    fn new(name: &str, msg_type: &str, enc: Encoding, count: Option<u64>) -> Self {
        TopicInfo {
            name: name.to_string(),
            msg_type: msg_type.replace("/msg/", "/"),
            encoding: Some(enc),
            count,
        }
    }

    /// The kind of the topic's messages.
    pub fn kind(&self) -> TopicKind {
        if self.encoding.is_none() {
            return TopicKind::Other;
        }
        let (pkg, name) = self.msg_type.split_once('/').unwrap_or(("", &self.msg_type));
        match (pkg, name) {
            ("sensor_msgs", "PointCloud2") => TopicKind::PointCloud2,
            ("sensor_msgs", "Imu") => TopicKind::Imu,
            ("velodyne_msgs", "VelodyneScan") => TopicKind::VelodyneScan,
            (p, "PacketMsg") if p.contains("ouster") => TopicKind::OusterPacket,
            ("std_msgs", "String") => TopicKind::Text,
            ("tf2_msgs", "TFMessage") | ("tf", "tfMessage") => TopicKind::Tf,
            _ => TopicKind::Other,
        }
    }
}

/// A message as stored.
#[derive(Debug)]
pub(crate) struct RawMsg {
    record_ns: u64,
    topic: usize,
    data: Vec<u8>,
}

/// What a storage reader yields.
#[derive(Debug)]
pub(crate) enum RawEvent {
    Msg(RawMsg),
    /// A damaged stretch was skipped (reading goes on).
    Skipped(String),
    /// A file is read without its index (`unindexed`) or only up to damage (`truncated`):
    /// said once, as `why`, before the messages that remain (or after them, when the damage
    /// is only found on the way).
    Recovered {
        why: String,
        unindexed: bool,
        truncated: bool,
    },
}

/// A storage reader: raw messages of the selected topics in storage order.
pub(crate) trait RawSource {
    fn select(&mut self, topics: &[usize]);
    fn next_raw(&mut self) -> Option<Result<RawEvent, BagError>>;
}

/// How far (ns) past the reorder window's newest record time a message may be before its time
/// is doubted (see the module docs, "Order").
pub const JUMP_NS: u64 = 10_000_000_000;
/// How many messages in a row must agree on a jump in record time before it is taken.
pub const JUMP_CONFIRM: usize = 3;

/// How to read a bag.
#[derive(Clone, Debug, PartialEq)]
pub struct BagOptions {
    /// The LiDAR topic; found by type if `None`.
    pub lidar_topic: Option<String>,
    /// The IMU topic; found by type if `None`.
    pub imu_topic: Option<String>,
    /// Whether a bag without an IMU topic is an error.
    pub require_imu: bool,
    /// How clouds become scans.
    pub cloud: CloudOptions,
    /// Stamp events with the record time instead of the messages' own stamps.
    pub use_record_time: bool,
    /// How long messages are held to sort them by record time, ns.
    pub reorder_window_ns: u64,
}

impl BagOptions {
    /// Options for a configuration (its nominal layout, ring order, scan rate and LiDAR time
    /// source); topics found by type; IMU required.
    pub fn from_config(cfg: &Config) -> Result<Self, ConfigError> {
        Ok(BagOptions {
            lidar_topic: None,
            imu_topic: None,
            require_imu: true,
            cloud: CloudOptions::from_config(cfg)?,
            use_record_time: cfg.time.lidar_time_source == LidarTimeSource::Capture,
            reorder_window_ns: 1_000_000_000,
        })
    }
}

/// Kind of a raw LiDAR-side packet.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PacketKind {
    /// A 1206-byte Velodyne data packet.
    Velodyne,
    /// An Ouster lidar packet.
    OusterLidar,
    /// An Ouster IMU packet (48 bytes).
    OusterImu,
}

/// A LiDAR scan from a point cloud.
#[derive(Clone, Debug, PartialEq)]
pub struct Scan {
    /// Absolute time of the scan start, ns (see the module docs for the clock).
    pub stamp_ns: u64,
    /// Points in the LiDAR frame, `t` seconds since `stamp_ns`, pixel from the layout.
    pub points: Vec<ScanPoint>,
    /// Points skipped (non-finite, or no return).
    pub skipped: u32,
}

/// A raw sensor packet.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LidarPacket {
    /// Stamp, ns (see the module docs).
    pub stamp_ns: u64,
    /// What the bytes are.
    pub kind: PacketKind,
    /// The packet payload.
    pub bytes: Vec<u8>,
}

/// One event of a bag.
#[derive(Clone, Debug, PartialEq)]
pub enum BagEvent {
    /// A point cloud as a scan.
    Scan(Scan),
    /// An IMU sample.
    Imu(ImuSample),
    /// A raw LiDAR (or Ouster IMU) packet, for the core's decoders.
    LidarPacket(LidarPacket),
    /// The Ouster driver's sensor metadata (JSON).
    OusterMetadata(String),
}

/// An event with its record time.
#[derive(Clone, Debug, PartialEq)]
pub struct BagItem {
    /// When the bag recorded the message, ns.
    pub record_ns: u64,
    /// The event.
    pub event: BagEvent,
}

/// Counts of what a reader delivered and dropped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BagStats {
    /// Messages read from the selected topics.
    pub messages: u64,
    /// Scans delivered.
    pub scans: u64,
    /// IMU samples delivered.
    pub imu: u64,
    /// Packets delivered.
    pub packets: u64,
    /// Malformed messages dropped.
    pub malformed: u64,
    /// Damaged stretches (ROS 1 chunks) skipped.
    pub skipped_chunks: u64,
    /// Messages dropped because they arrived after later ones had been delivered.
    pub late: u64,
    /// Messages dropped because their record time jumped far ahead of the others' and the
    /// next messages did not follow (corrupt times).
    pub out_of_sequence: u64,
    /// Points skipped in clouds (non-finite or no return).
    pub skipped_points: u64,
    /// Whether a ROS 1 bag was read without its index (never closed, cut short, or a corrupt
    /// index), by walking its records.
    pub unindexed: bool,
    /// Files read only up to damage (cut short, or damaged pages); what follows is lost.
    pub truncated_files: u64,
}

impl fmt::Display for BagStats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} messages: {} scans, {} IMU samples, {} packets; dropped {} malformed, {} late, {} out of sequence, {} corrupt chunks; {} points without a return skipped",
            self.messages,
            self.scans,
            self.imu,
            self.packets,
            self.malformed,
            self.late,
            self.out_of_sequence,
            self.skipped_chunks,
            self.skipped_points
        )?;
        if self.unindexed {
            f.write_str("; read without its index")?;
        }
        if self.truncated_files > 0 {
            write!(f, "; {} file(s) read only up to damage, the rest lost", self.truncated_files)?;
        }
        Ok(())
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Role {
    Lidar(TopicKind),
    Imu(TopicKind),
    Metadata,
}

/// The topics a reader uses.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Selection {
    /// The LiDAR topic (or the Ouster lidar packet topic) and its kind.
    pub lidar: (String, TopicKind),
    /// The IMU topic (or the Ouster IMU packet topic), if any.
    pub imu: Option<String>,
    /// The Ouster metadata topic, if any.
    pub metadata: Option<String>,
}

struct Pending {
    record_ns: u64,
    seq: u64,
    item: BagItem,
}

impl PartialEq for Pending {
    fn eq(&self, o: &Self) -> bool {
        (self.record_ns, self.seq) == (o.record_ns, o.seq)
    }
}
impl Eq for Pending {}
impl PartialOrd for Pending {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Pending {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        // Min-heap on (record time, arrival).
        (o.record_ns, o.seq).cmp(&(self.record_ns, self.seq))
    }
}

/// Reads a bag as a stream of [`BagItem`]s (an iterator of `Result`s; after an error it ends).
pub struct BagReader {
    name: String,
    format: BagFormat,
    topics: Vec<TopicInfo>,
    roles: Vec<Option<Role>>,
    selection: Selection,
    source: Box<dyn RawSource>,
    opt: BagOptions,
    heap: BinaryHeap<Pending>,
    seq: u64,
    /// The newest record time taken, once a message has been.
    max_seen: Option<u64>,
    /// Messages whose record time jumped past `max_seen`, held until the jump is confirmed.
    jumped: Vec<RawMsg>,
    last_emitted: Option<u64>,
    source_done: bool,
    pending_error: Option<BagError>,
    finished: bool,
    stats: BagStats,
    warned: HashSet<String>,
    total: Option<u64>,
    /// Decompressed storage files (removed on drop: declared last, after the source that
    /// reads them).
    _decompressed: Option<Decompressed>,
}

impl fmt::Debug for BagReader {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("BagReader")
            .field("name", &self.name)
            .field("format", &self.format)
            .field("selection", &self.selection)
            .finish_non_exhaustive()
    }
}

fn ext(p: &Path) -> String {
    p.file_name().and_then(|n| n.to_str()).unwrap_or("").to_ascii_lowercase()
}

/// Storage files decompressed from a rosbag2's file compression (`.db3.zstd`, `.mcap.zstd`)
/// into a temporary directory, removed when the bag is closed.
#[derive(Debug)]
struct Decompressed(PathBuf);

impl Drop for Decompressed {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Decompresses `files` (zstd frames) into a new temporary directory, each under its name
/// less `.zstd`.
fn decompress(name: &str, files: &[PathBuf]) -> Result<(Decompressed, Vec<PathBuf>), BagError> {
    static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let dir = std::env::temp_dir().join(format!("loglio-bag-{}-{n}", std::process::id()));
    std::fs::create_dir_all(&dir)
        .map_err(|e| BagError(format!("{name}: cannot make {} to decompress into: {e}", dir.display())))?;
    let guard = Decompressed(dir.clone());
    let mut out = Vec::new();
    for f in files {
        let file_name = f.file_name().and_then(|n| n.to_str()).unwrap_or("bag");
        let plain = dir.join(file_name.strip_suffix(".zstd").unwrap_or(file_name));
        let src =
            std::fs::File::open(f).map_err(|e| BagError(format!("cannot open {}: {e}", f.display())))?;
        let dst = std::fs::File::create(&plain)
            .map_err(|e| BagError(format!("{name}: cannot write {}: {e}", plain.display())))?;
        zstd::stream::copy_decode(std::io::BufReader::new(src), std::io::BufWriter::new(dst)).map_err(
            |e| {
                BagError(format!(
                    "{}: a zstd-compressed file (rosbag2 file compression) that does not decompress: {}",
                    f.display(),
                    crate::diag::one_line(&e.to_string())
                ))
            },
        )?;
        out.push(plain);
    }
    Ok((guard, out))
}

/// Finds the format and the storage files of a path (a file, or a rosbag2 directory);
/// compressed storage files are decompressed into a temporary directory first.
fn detect(path: &Path) -> Result<(BagFormat, Vec<PathBuf>, Option<Decompressed>), BagError> {
    let name = path.display();
    let meta = std::fs::metadata(path).map_err(|e| BagError(format!("cannot open {name}: {e}")))?;
    if meta.is_dir() {
        let yaml = std::fs::read_to_string(path.join("metadata.yaml")).unwrap_or_default();
        let value = |key: &str| {
            yaml.lines().find_map(|l| {
                let v = l.trim().strip_prefix(key)?.strip_prefix(':')?;
                Some(v.trim().trim_matches('"').trim_matches('\'').to_string())
            })
        };
        let format = value("compression_format").unwrap_or_default();
        let mode = value("compression_mode").unwrap_or_default().to_ascii_lowercase();
        // zstd per message is decompressed as the rows are read, zstd files before reading.
        let readable = format.is_empty() || format == "zstd";
        if !readable {
            let how = if mode == "message" { "message" } else { "file" };
            return Err(BagError(format!(
                "{name}: this rosbag2 is {format}-compressed ({how} compression), which loglio does not read; \
                 decompress it first (`ros2 bag convert` to an uncompressed bag)"
            )));
        }
        let mut files: Vec<PathBuf> = std::fs::read_dir(path)
            .map_err(|e| BagError(format!("cannot read {name}: {e}")))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file())
            .collect();
        // Splits are NAME_0, NAME_1, ...: sort by the number after the last '_'.
        let split_no = |p: &PathBuf| -> (u64, String) {
            let stem = p.file_stem().and_then(|s| s.to_str()).unwrap_or("").to_string();
            (stem.rsplit('_').next().and_then(|n| n.parse().ok()).unwrap_or(0), stem)
        };
        files.sort_by_key(split_no);
        let zstd: Vec<PathBuf> = files
            .iter()
            .filter(|p| ext(p).ends_with(".db3.zstd") || ext(p).ends_with(".mcap.zstd"))
            .cloned()
            .collect();
        let mut temp = None;
        if !zstd.is_empty() {
            // File compression: every storage file is one zstd stream.
            let (guard, plain) = decompress(&name.to_string(), &zstd)?;
            files.retain(|p| !zstd.contains(p));
            files.extend(plain);
            files.sort_by_key(split_no);
            temp = Some(guard);
        }
        let db3: Vec<PathBuf> = files.iter().filter(|p| ext(p).ends_with(".db3")).cloned().collect();
        let mcap: Vec<PathBuf> = files.iter().filter(|p| ext(p).ends_with(".mcap")).cloned().collect();
        return match (db3.is_empty(), mcap.len()) {
            (false, 0) => Ok((BagFormat::Ros2Sqlite, db3, temp)),
            (true, n) if n >= 1 => Ok((BagFormat::Mcap, mcap, temp)),
            (false, _) => Err(BagError(format!("{name}: holds both .db3 and .mcap files; pass one file"))),
            _ => Err(BagError(format!("{name}: no .db3 or .mcap files (not a rosbag2 directory)"))),
        };
    }
    let mut head = [0u8; 16];
    let n = {
        use std::io::Read;
        let mut f = std::fs::File::open(path).map_err(|e| BagError(format!("cannot open {name}: {e}")))?;
        let mut n = 0;
        while n < head.len() {
            match f.read(&mut head[n..]) {
                Ok(0) => break,
                Ok(k) => n += k,
                Err(e) => return Err(BagError(format!("cannot read {name}: {e}"))),
            }
        }
        n
    };
    let head = &head[..n];
    if head.starts_with(b"#ROSBAG") {
        Ok((BagFormat::Ros1, vec![path.to_path_buf()], None))
    } else if head.starts_with(b"\x89MCAP") {
        Ok((BagFormat::Mcap, vec![path.to_path_buf()], None))
    } else if head.starts_with(b"SQLite format 3\0") {
        Ok((BagFormat::Ros2Sqlite, vec![path.to_path_buf()], None))
    } else if head.starts_with(&ros2_sqlite::ZSTD_MAGIC) {
        // One storage file of a rosbag2 with file compression: decompressed, then read as
        // what it holds (a zstd stream of anything else is no bag).
        let (guard, plain) = decompress(&name.to_string(), &[path.to_path_buf()])?;
        match detect(&plain[0]) {
            Ok((format, files, _)) if format != BagFormat::Ros1 => Ok((format, files, Some(guard))),
            _ => Err(BagError(format!(
                "{name}: a zstd-compressed file that holds no rosbag2 storage file (sqlite3 or MCAP)"
            ))),
        }
    } else if n == 0 {
        Err(BagError(format!("{name}: empty file, not a bag")))
    } else {
        Err(BagError(format!("{name}: not a ROS bag (neither a ROS 1 bag, a rosbag2 sqlite3 file nor MCAP)")))
    }
}

/// How many messages [`BagReader::static_extrinsic`] reads at most.
pub const TF_SEARCH_MESSAGES: usize = 100_000;
/// How many messages after the last `/tf_static` one [`BagReader::static_extrinsic`] reads
/// once both frames are known and still not connected.
pub const TF_SETTLE: usize = 1_000;

/// The LiDAR frame in the IMU frame, from the bag's `/tf_static`.
#[derive(Clone, Debug, PartialEq)]
pub struct StaticExtrinsic {
    /// The LiDAR messages' `frame_id`.
    pub lidar_frame: String,
    /// The IMU messages' `frame_id`.
    pub imu_frame: String,
    /// `p_imu = imu_lidar * p_lidar`.
    pub imu_lidar: nalgebra::Isometry3<f64>,
}

/// Static transforms by child frame: (parent frame, the child's pose in the parent).
pub(crate) type StaticFrames = std::collections::HashMap<String, (String, nalgebra::Isometry3<f64>)>;

/// Adds a `/tf_static` message's transforms to `parents` (frame names without a leading `/`).
pub(crate) fn add_static(parents: &mut StaticFrames, ts: &[msg::Transform]) {
    for t in ts {
        let [x, y, z, w] = t.rotation_xyzw;
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
        let iso = nalgebra::Isometry3::from_parts(nalgebra::Translation3::from(t.translation), q);
        parents.insert(
            t.child.trim_start_matches('/').to_string(),
            (t.parent.trim_start_matches('/').to_string(), iso),
        );
    }
}

/// A `sensor_msgs/Imu` as a sample at `t_ns` (an error for non-finite rates or accelerations).
pub(crate) fn imu_sample(m: &Imu, t_ns: u64) -> Result<ImuSample, String> {
    let v: Vec<f64> = m.angular_velocity.iter().chain(&m.linear_acceleration).copied().collect();
    if v.iter().any(|x| !x.is_finite()) {
        return Err("non-finite angular velocity or acceleration".into());
    }
    let f = |a: [f64; 3]| a.map(|x| x as f32);
    Ok(ImuSample { t_ns, gyro: f(m.angular_velocity), acc: f(m.linear_acceleration) })
}

/// The pose of `child` in `parent` from static transforms (child -> (parent, pose in parent)):
/// both frames walked up to their roots, joined at the first frame they share.
pub(crate) fn chain(parents: &StaticFrames, parent: &str, child: &str) -> Option<nalgebra::Isometry3<f64>> {
    // Each frame's ancestors with the frame's pose in them, the frame itself first.
    let up = |f: &str| {
        let mut out = vec![(f.to_string(), nalgebra::Isometry3::identity())];
        while let Some((p, iso)) = parents.get(&out[out.len() - 1].0) {
            if out.len() > 64 || out.iter().any(|(n, _)| n == p) {
                break;
            }
            let pose = iso * out[out.len() - 1].1;
            out.push((p.clone(), pose));
        }
        out
    };
    let (a, b) = (up(parent), up(child));
    let (root_parent, root_child) =
        a.iter().find_map(|(n, pa)| b.iter().find(|(m, _)| m == n).map(|(_, pb)| (*pa, *pb)))?;
    Some(root_parent.inverse() * root_child)
}

fn list_topics(topics: &[TopicInfo]) -> String {
    if topics.is_empty() {
        return "no topics".into();
    }
    topics.iter().map(|t| format!("{} ({})", t.name, t.msg_type)).collect::<Vec<_>>().join(", ")
}

fn select(
    name: &str,
    topics: &[TopicInfo],
    opt: &BagOptions,
) -> Result<(Vec<Option<Role>>, Selection), BagError> {
    let all = || list_topics(topics);
    let find = |t: &str| topics.iter().position(|x| x.name == t);
    let mut roles = vec![None; topics.len()];
    let lidar_kinds = [TopicKind::PointCloud2, TopicKind::VelodyneScan, TopicKind::OusterPacket];
    let is_imu_packets =
        |t: &TopicInfo| t.kind() == TopicKind::OusterPacket && t.name.to_ascii_lowercase().contains("imu");
    let lidar = match &opt.lidar_topic {
        Some(t) => {
            let i =
                find(t).ok_or_else(|| BagError(format!("{name}: no topic {t}; the bag has {}", all())))?;
            let k = topics[i].kind();
            if !lidar_kinds.contains(&k) {
                return Err(BagError(format!(
                    "{name}: topic {t} is a {}, not a LiDAR message (sensor_msgs/PointCloud2, velodyne_msgs/VelodyneScan or Ouster PacketMsg)",
                    topics[i].msg_type
                )));
            }
            i
        }
        None => {
            let mut found = None;
            for kind in lidar_kinds {
                let c: Vec<usize> = (0..topics.len())
                    .filter(|&i| topics[i].kind() == kind && !is_imu_packets(&topics[i]))
                    .collect();
                match c.len() {
                    0 => continue,
                    1 => {
                        found = Some(c[0]);
                        break;
                    }
                    _ => {
                        let names: Vec<&str> = c.iter().map(|&i| topics[i].name.as_str()).collect();
                        return Err(BagError(format!(
                            "{name}: several LiDAR topics ({}); name one (lidar topic option)",
                            names.join(", ")
                        )));
                    }
                }
            }
            found.ok_or_else(|| {
                BagError(format!(
                    "{name}: no LiDAR topic (sensor_msgs/PointCloud2, velodyne_msgs/VelodyneScan or Ouster PacketMsg); the bag has {}",
                    all()
                ))
            })?
        }
    };
    let lidar_kind = topics[lidar].kind();
    roles[lidar] = Some(Role::Lidar(lidar_kind));
    let imu = match &opt.imu_topic {
        Some(t) => {
            let i =
                find(t).ok_or_else(|| BagError(format!("{name}: no topic {t}; the bag has {}", all())))?;
            let k = topics[i].kind();
            if k != TopicKind::Imu && k != TopicKind::OusterPacket {
                return Err(BagError(format!(
                    "{name}: topic {t} is a {}, not an IMU message (sensor_msgs/Imu or Ouster IMU PacketMsg)",
                    topics[i].msg_type
                )));
            }
            Some(i)
        }
        None => {
            let c: Vec<usize> = (0..topics.len()).filter(|&i| topics[i].kind() == TopicKind::Imu).collect();
            match c.len() {
                1 => Some(c[0]),
                0 => (0..topics.len())
                    .find(|&i| lidar_kind == TopicKind::OusterPacket && is_imu_packets(&topics[i])),
                _ => {
                    let names: Vec<&str> = c.iter().map(|&i| topics[i].name.as_str()).collect();
                    return Err(BagError(format!(
                        "{name}: several IMU topics ({}); name one (imu topic option)",
                        names.join(", ")
                    )));
                }
            }
        }
    };
    if let Some(i) = imu {
        if i == lidar {
            return Err(BagError(format!(
                "{name}: topic {} cannot be both the LiDAR and the IMU topic",
                topics[i].name
            )));
        }
        roles[i] = Some(Role::Imu(topics[i].kind()));
    } else if opt.require_imu {
        return Err(BagError(format!("{name}: no IMU topic (sensor_msgs/Imu); the bag has {}", all())));
    }
    let metadata = if lidar_kind == TopicKind::OusterPacket {
        (0..topics.len())
            .find(|&i| topics[i].kind() == TopicKind::Text && topics[i].name.contains("metadata"))
    } else {
        None
    };
    if let Some(i) = metadata {
        roles[i] = Some(Role::Metadata);
    }
    let sel = Selection {
        lidar: (topics[lidar].name.clone(), lidar_kind),
        imu: imu.map(|i| topics[i].name.clone()),
        metadata: metadata.map(|i| topics[i].name.clone()),
    };
    Ok((roles, sel))
}

/// A bag opened: its format, its message source, its topics and the temporary directory of
/// its decompressed files.
type Opened = (BagFormat, Box<dyn RawSource>, Vec<TopicInfo>, Option<Decompressed>);

/// Opens the bag at `path` (a file, or a rosbag2 directory).
fn open_source(path: &Path) -> Result<Opened, BagError> {
    let (format, files, temp) = detect(path)?;
    let (source, topics): (Box<dyn RawSource>, Vec<TopicInfo>) = match format {
        BagFormat::Ros1 => {
            let (s, t) = ros1::Ros1Source::open(&files[0])?;
            (Box::new(s), t)
        }
        BagFormat::Ros2Sqlite => {
            let (s, t) = ros2_sqlite::SqliteSource::open(files)?;
            (Box::new(s), t)
        }
        BagFormat::Mcap if files.len() > 1 => {
            let (s, t) = mcap_src::McapSplits::open(&files)?;
            (Box::new(s), t)
        }
        BagFormat::Mcap => {
            let (s, t) = mcap_src::McapSource::open(&files[0])?;
            (Box::new(s), t)
        }
    };
    Ok((format, source, topics, temp))
}

impl BagReader {
    /// Opens a bag (a file, or a rosbag2 directory), lists its topics and chooses the ones to
    /// read.
    pub fn open(path: &Path, opt: BagOptions) -> Result<BagReader, BagError> {
        let name = path.display().to_string();
        let (format, mut source, topics, temp) = open_source(path)?;
        let (roles, selection) = select(&name, &topics, &opt)?;
        let chosen: Vec<usize> = (0..topics.len()).filter(|&i| roles[i].is_some()).collect();
        source.select(&chosen);
        let total = chosen.iter().map(|&i| topics[i].count).sum::<Option<u64>>();
        Ok(BagReader {
            name,
            format,
            topics,
            roles,
            selection,
            source,
            opt,
            heap: BinaryHeap::new(),
            seq: 0,
            max_seen: None,
            jumped: Vec::new(),
            last_emitted: None,
            source_done: false,
            pending_error: None,
            finished: false,
            stats: BagStats::default(),
            warned: HashSet::new(),
            total,
            _decompressed: temp,
        })
    }

    /// The LiDAR frame in the IMU frame from the bag's `/tf_static`: the frames are the
    /// `frame_id`s of the first LiDAR and IMU messages, the transform the chain of static
    /// transforms between them (direct, inverse, or through a common parent such as
    /// `base_link`). Reads until all three are known, at most [`TF_SEARCH_MESSAGES`] messages
    /// ([`TF_SETTLE`] after the last `/tf_static` one once both frames are known);
    /// `None` when the bag has no `/tf_static`, the LiDAR has no header (Ouster packets) or
    /// the frames are not connected.
    pub fn static_extrinsic(path: &Path, opt: &BagOptions) -> Result<Option<StaticExtrinsic>, BagError> {
        let name = path.display().to_string();
        let (_, mut source, topics, _decompressed) = open_source(path)?;
        let Some(tf) = topics.iter().position(|t| t.name == "/tf_static" && t.kind() == TopicKind::Tf) else {
            return Ok(None);
        };
        let (roles, _) = select(&name, &topics, opt)?;
        let lidar = roles.iter().position(|r| matches!(r, Some(Role::Lidar(_))));
        let imu = roles.iter().position(|r| matches!(r, Some(Role::Imu(_))));
        let (Some(lidar), Some(imu)) = (lidar, imu) else { return Ok(None) };
        if !matches!(topics[lidar].kind(), TopicKind::PointCloud2 | TopicKind::VelodyneScan) {
            return Ok(None);
        }
        source.select(&[lidar, imu, tf]);
        let frame = |data: &[u8], enc: Encoding| -> Option<String> {
            let (_, f) = msg::Reader::new(data, enc).ok()?.header().ok()?;
            Some(f.trim_start_matches('/').to_string())
        };
        let (mut lidar_frame, mut imu_frame) = (None, None);
        let mut parents = StaticFrames::new();
        // /tf_static is latched: recorded once per publisher, at the start. Reading stops
        // TF_SETTLE messages after the last one once both frames are known.
        let mut since_tf: Option<usize> = None;
        for _ in 0..TF_SEARCH_MESSAGES {
            if lidar_frame.is_some() && imu_frame.is_some() && since_tf.is_some_and(|n| n > TF_SETTLE) {
                break;
            }
            let Some(ev) = source.next_raw() else { break };
            let RawEvent::Msg(m) = ev? else { continue };
            since_tf = since_tf.map(|n| n + 1);
            if m.topic == tf {
                since_tf = Some(0);
            }
            let Some(enc) = topics[m.topic].encoding else { continue };
            if m.topic == lidar && lidar_frame.is_none() {
                lidar_frame = frame(&m.data, enc);
            } else if m.topic == imu && imu_frame.is_none() {
                imu_frame = frame(&m.data, enc);
            } else if m.topic == tf
                && let Ok(ts) = msg::decode_tf(&m.data, enc)
            {
                add_static(&mut parents, &ts);
            }
            if let (Some(l), Some(i)) = (&lidar_frame, &imu_frame)
                && let Some(e) = chain(&parents, i, l)
            {
                return Ok(Some(StaticExtrinsic {
                    lidar_frame: l.clone(),
                    imu_frame: i.clone(),
                    imu_lidar: e,
                }));
            }
        }
        Ok(None)
    }

    /// The storage format.
    pub fn format(&self) -> BagFormat {
        self.format
    }

    /// Every topic of the bag.
    pub fn topics(&self) -> &[TopicInfo] {
        &self.topics
    }

    /// The topics being read.
    pub fn selection(&self) -> &Selection {
        &self.selection
    }

    /// Messages of the selected topics in the bag, when the bag says (for a progress bar).
    pub fn total_messages(&self) -> Option<u64> {
        self.total
    }

    /// What has been delivered and dropped so far.
    pub fn stats(&self) -> &BagStats {
        &self.stats
    }

    fn warn_once(&mut self, key: &str, msg: impl FnOnce() -> String) {
        if self.warned.insert(key.to_string()) {
            warn(msg());
        }
    }

    fn decode(&mut self, raw: &RawMsg) -> Result<Vec<BagEvent>, String> {
        let topic = &self.topics[raw.topic];
        let enc = topic.encoding.ok_or("unsupported encoding")?;
        let name = topic.name.clone();
        let rec = self.opt.use_record_time;
        let e = |m: msg::MsgError| m.0;
        Ok(match self.roles[raw.topic] {
            None => vec![],
            Some(Role::Lidar(TopicKind::PointCloud2)) => {
                let c = PointCloud2::decode(&raw.data, enc).map_err(e)?;
                let s = cloud_to_scan(&c, &self.opt.cloud)?;
                for (key, text) in cloud::note_warnings(&name, &s.notes, &self.opt.cloud) {
                    self.warn_once(&key, || text);
                }
                self.stats.skipped_points += s.skipped as u64;
                let stamp_ns = if rec {
                    let last = s.points.iter().map(|p| p.t).fold(0.0f32, f32::max);
                    raw.record_ns.saturating_sub((last as f64 * 1e9) as u64)
                } else {
                    s.start_ns
                };
                vec![BagEvent::Scan(Scan { stamp_ns, points: s.points, skipped: s.skipped })]
            }
            Some(Role::Lidar(TopicKind::VelodyneScan)) => {
                let s = VelodyneScan::decode(&raw.data, enc).map_err(e)?;
                s.packets
                    .into_iter()
                    .map(|(t, bytes)| {
                        BagEvent::LidarPacket(LidarPacket {
                            stamp_ns: if rec { raw.record_ns } else { t },
                            kind: PacketKind::Velodyne,
                            bytes,
                        })
                    })
                    .collect()
            }
            Some(Role::Lidar(_)) => {
                let bytes = decode_packet_msg(&raw.data, enc).map_err(e)?;
                vec![BagEvent::LidarPacket(LidarPacket {
                    stamp_ns: raw.record_ns,
                    kind: PacketKind::OusterLidar,
                    bytes,
                })]
            }
            Some(Role::Imu(TopicKind::Imu)) => {
                let m = Imu::decode(&raw.data, enc).map_err(e)?;
                vec![BagEvent::Imu(imu_sample(&m, if rec { raw.record_ns } else { m.stamp_ns })?)]
            }
            Some(Role::Imu(_)) => {
                let bytes = decode_packet_msg(&raw.data, enc).map_err(e)?;
                vec![BagEvent::LidarPacket(LidarPacket {
                    stamp_ns: raw.record_ns,
                    kind: PacketKind::OusterImu,
                    bytes,
                })]
            }
            Some(Role::Metadata) => vec![BagEvent::OusterMetadata(decode_string(&raw.data, enc).map_err(e)?)],
        })
    }

    fn push(&mut self, raw: RawMsg) {
        self.stats.messages += 1;
        if self.last_emitted.is_some_and(|last| raw.record_ns < last) {
            self.stats.late += 1;
            let topic = self.topics[raw.topic].name.clone();
            let window = self.opt.reorder_window_ns as f64 * 1e-9;
            self.warn_once("late", || {
                format!("{topic}: a message recorded more than {window} s before one already delivered was dropped (later ones are counted)")
            });
            return;
        }
        let Some(newest) = self.max_seen else {
            // The first JUMP_CONFIRM messages are all taken, but the newest time starts from
            // their median, so that one corrupt time among them cannot set it (nor can a
            // message dropped here be missed: an Ouster bag's one metadata message may stand
            // well before its packets).
            self.jumped.push(raw);
            if self.jumped.len() >= JUMP_CONFIRM {
                self.take_first();
            }
            return;
        };
        // A message far ahead of the rest is held until JUMP_CONFIRM messages in a row, each
        // within JUMP_NS of the one before, agree on its time.
        if raw.record_ns > newest.saturating_add(self.opt.reorder_window_ns).saturating_add(JUMP_NS) {
            if self.jumped.last().is_some_and(|m| m.record_ns.abs_diff(raw.record_ns) > JUMP_NS) {
                self.drop_jumped(Some(raw.record_ns));
            }
            self.jumped.push(raw);
            if self.jumped.len() >= JUMP_CONFIRM {
                self.take_held();
            }
            return;
        }
        // A message in the usual range: whatever jumped before it had a corrupt time.
        self.drop_jumped(Some(raw.record_ns));
        self.take(raw);
    }

    /// Drops the held messages whose time was not confirmed, counted; `next` is the record
    /// time of the message that did not follow them, if any.
    fn drop_jumped(&mut self, next: Option<u64>) {
        let Some(m) = self.jumped.first() else { return };
        let Some(other) = next.or(self.max_seen) else { return };
        let (topic, off) = (self.topics[m.topic].name.clone(), m.record_ns as f64 - other as f64);
        self.stats.out_of_sequence += self.jumped.len() as u64;
        self.warn_once("out of sequence", || {
            format!(
                "{topic}: dropped a message recorded {:+.3} s from the others, which the next messages do not follow (a corrupt time; later ones are counted)",
                off * 1e-9
            )
        });
        self.jumped.clear();
    }

    /// Takes the first messages held, with the newest time at their median.
    fn take_first(&mut self) {
        let mut t: Vec<u64> = self.jumped.iter().map(|m| m.record_ns).collect();
        t.sort_unstable();
        let median = t[t.len() / 2];
        self.take_held();
        self.max_seen = Some(median);
    }

    /// Takes every held message.
    fn take_held(&mut self) {
        for m in std::mem::take(&mut self.jumped) {
            self.take(m);
        }
    }

    /// At the end of the source: the first messages of a bag shorter than JUMP_CONFIRM are
    /// taken; messages that jumped from the rest are dropped.
    fn flush_jumped(&mut self) {
        if self.max_seen.is_none() && !self.jumped.is_empty() {
            self.take_first();
        }
        self.drop_jumped(None);
    }

    /// Takes a message in: its record time is the newest if it is, and its events wait in the
    /// reorder heap.
    fn take(&mut self, raw: RawMsg) {
        self.max_seen = Some(self.max_seen.map_or(raw.record_ns, |m| m.max(raw.record_ns)));
        match self.decode(&raw) {
            Ok(events) => {
                for event in events {
                    match &event {
                        BagEvent::Scan(_) => self.stats.scans += 1,
                        BagEvent::Imu(_) => self.stats.imu += 1,
                        BagEvent::LidarPacket(_) => self.stats.packets += 1,
                        BagEvent::OusterMetadata(_) => {}
                    }
                    self.seq += 1;
                    self.heap.push(Pending {
                        record_ns: raw.record_ns,
                        seq: self.seq,
                        item: BagItem { record_ns: raw.record_ns, event },
                    });
                }
            }
            Err(why) => {
                self.stats.malformed += 1;
                let t = &self.topics[raw.topic];
                let (topic, ty) = (t.name.clone(), t.msg_type.clone());
                self.warn_once(&format!("malformed {topic}"), || {
                    format!("{topic}: dropped a malformed {ty} message ({why}); later ones are counted")
                });
            }
        }
    }
}

impl Iterator for BagReader {
    type Item = Result<BagItem, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if self.finished {
                return None;
            }
            if let Some(top) = self.heap.peek()
                && (self.source_done
                    || self
                        .max_seen
                        .is_some_and(|m| top.record_ns.saturating_add(self.opt.reorder_window_ns) <= m))
                && let Some(p) = self.heap.pop()
            {
                self.last_emitted = Some(p.record_ns);
                return Some(Ok(p.item));
            }
            if self.source_done {
                self.finished = true;
                return self.pending_error.take().map(Err);
            }
            match self.source.next_raw() {
                None => {
                    self.source_done = true;
                    self.flush_jumped();
                }
                Some(Err(e)) => {
                    self.source_done = true;
                    self.flush_jumped();
                    self.pending_error = Some(e);
                }
                Some(Ok(RawEvent::Skipped(why))) => {
                    self.stats.skipped_chunks += 1;
                    let name = self.name.clone();
                    self.warn_once("skipped", || {
                        format!("{name}: {why}; skipped it (later damage is counted)")
                    });
                }
                Some(Ok(RawEvent::Recovered { why, unindexed, truncated })) => {
                    self.stats.unindexed |= unindexed;
                    self.stats.truncated_files += u64::from(truncated);
                    warn(why);
                }
                Some(Ok(RawEvent::Msg(raw))) => self.push(raw),
            }
        }
    }
}
