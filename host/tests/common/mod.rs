//! Helpers every test of the `loglio` binary needs (each test file is its own crate, so each
//! compiles this module and uses a part of it).
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

use nalgebra::Isometry3;

/// The runner of a cross build's binary, from `LOGLIO_TEST_RUNNER` (e.g. `qemu-aarch64 -L
/// /usr/aarch64-linux-gnu`: the tests run under qemu-user, and the kernel cannot exec the
/// foreign binary they spawn without binfmt_misc); `None` when unset or blank.
pub fn runner() -> Option<String> {
    std::env::var("LOGLIO_TEST_RUNNER").ok().filter(|r| !r.trim().is_empty())
}

/// The `loglio` binary with `args`, through [`runner`] when set; backtraces on (a panic would
/// show), the binary's internal test-panic hook off.
pub fn loglio_command(args: &[&str]) -> Command {
    let bin = env!("CARGO_BIN_EXE_loglio");
    let mut c = match runner() {
        Some(r) => {
            let mut parts = r.split_whitespace();
            let mut c = Command::new(parts.next().unwrap_or_default());
            c.args(parts).arg(bin);
            c
        }
        None => Command::new(bin),
    };
    c.args(args).env("RUST_BACKTRACE", "full").env_remove("LOGLIO_TEST_INTERNAL_PANIC");
    c
}

/// A fresh folder `loglio-{group}-{name}-{pid}` in the temporary directory, removed with its
/// contents when the returned guard drops (a test's outputs run to hundreds of megabytes: maps,
/// recordings). It is kept, and its path printed, when the test fails, or for every test with
/// `LOGLIO_KEEP_TEST_FILES` set.
pub fn scratch(group: &str, name: &str) -> Scratch {
    let d = std::env::temp_dir().join(format!("loglio-{group}-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    Scratch(d)
}

/// A test's scratch folder ([`scratch`]); derefs to its path.
#[derive(Debug)]
pub struct Scratch(PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("test files kept in {}", self.0.display());
        } else if std::env::var_os("LOGLIO_KEEP_TEST_FILES").is_none() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for Scratch {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

/// The number that follows `key` in `text` (a trailing `,` or `;` removed).
pub fn number_after(text: &str, key: &str) -> f64 {
    let i = text.find(key).unwrap_or_else(|| panic!("no {key:?} in {text}"));
    text[i + key.len()..].split_whitespace().next().unwrap().trim_end_matches([',', ';']).parse().unwrap()
}

/// A configuration file: `preset` with the rig's extrinsic (the LiDAR's pose in the IMU frame).
pub fn extrinsic_config(preset: &str, e: &Isometry3<f64>) -> String {
    let q = e.rotation.quaternion();
    format!(
        "preset = \"{preset}\"\n[extrinsics]\ntranslation = [{}, {}, {}]\nrotation_quat_wxyz = [{}, {}, {}, {}]\n",
        e.translation.x, e.translation.y, e.translation.z, q.w, q.i, q.j, q.k
    )
}

/// The Python with the live outputs' independent peers (pymavlink, cyclonedds, websockets,
/// mcap), from `LOGLIO_PYTHON` (set by `scripts/test-all` after installing them into
/// `target/pyenv`). Without it a test prints a loud SKIPPED and passes, unless
/// `LOGLIO_REQUIRE_PEERS=1`, when it fails.
pub fn peer_python(test: &str) -> Option<PathBuf> {
    let p = std::env::var_os("LOGLIO_PYTHON").map(PathBuf::from).filter(|p| p.exists());
    if p.is_none() {
        let why = "LOGLIO_PYTHON is not set to a Python with the peers (scripts/test-all installs them)";
        if std::env::var("LOGLIO_REQUIRE_PEERS").is_ok_and(|v| v == "1") {
            panic!("LOGLIO_REQUIRE_PEERS=1 but {why}");
        }
        eprintln!("\n!!! SKIPPED {test}: {why}\n");
    }
    p
}

/// The ROS 2 message types as Cyclone DDS's Python IDL classes (`nav_msgs::msg::dds_::Odometry_`
/// and what it holds), for the test subscribers of `ros2.rs` and `live.rs`: a script template's
/// `{ROS2_TYPES}` is replaced by them ([`with_ros2_types`]).
pub const ROS2_TYPES: &str = r#"@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32

@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str

@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64
    y: float64
    z: float64

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
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion

@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose
    covariance: array[float64, 36]

@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3
    angular: Vector3

@dataclass
class TwistWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):
    twist: Twist
    covariance: array[float64, 36]

@dataclass
class Odometry(IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):
    header: Header
    child_frame_id: str
    pose: PoseWithCovariance
    twist: TwistWithCovariance

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

"#;

/// `script` with `{ROS2_TYPES}` replaced by [`ROS2_TYPES`].
pub fn with_ros2_types(script: &str) -> String {
    script.replace("{ROS2_TYPES}", ROS2_TYPES)
}

/// Cyclone DDS on loopback only, unicast to 127.0.0.1 (no multicast needed in a sandbox).
pub const CYCLONE_XML: &str = r#"<CycloneDDS><Domain id="any"><General><Interfaces><NetworkInterface name="lo"/></Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery><Peers><Peer address="127.0.0.1"/></Peers><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>20</MaxAutoParticipantIndex></Discovery></Domain></CycloneDDS>"#;
