//! The `loglio` configuration: a TOML file that names a sensor preset and overrides any of its
//! values, validated with messages that name the bad key and its allowed range.
//!
//! ```toml
//! preset = "vlp32c"
//! [mapping]
//! voxel_size = 0.4
//! [extrinsics]
//! translation = [0.27255, -0.00053, 0.17954]
//! ```
//!
//! `loglio config --preset NAME` prints [`template`]: every key with a comment saying what it
//! is, its unit and its range, set to the preset's value; it parses back to [`Config::preset`].
//!
//! # How this maps onto the core (`run::engine::odometry_config`)
//!
//! [`Config`] is a plain host struct on purpose; the core's config structs are built from it.
//! Every key, its range, unit, defaults and where it goes in the core are listed once, in the
//! key table below (`SPECS`, `SECTIONS`), from which the template, the validation and
//! `docs/configuration.md` ([`reference_markdown`], `loglio config --reference`) are generated.

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use loglio_core::range_image::RangeImageLayout;
use serde::{Deserialize, Serialize};

/// A configuration error: one line that names the bad key and what is allowed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConfigError(pub String);

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for ConfigError {}

macro_rules! bail {
    ($($t:tt)*) => { return Err(ConfigError(format!("config: {}", format_args!($($t)*)))) };
}

/// A supported sensor: sets the default of every configuration key.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Preset {
    /// Velodyne VLP-16 (Puck).
    #[serde(rename = "vlp16")]
    Vlp16,
    /// Velodyne VLP-32C (Ultra Puck).
    #[serde(rename = "vlp32c")]
    Vlp32c,
    /// Velodyne HDL-32E.
    #[serde(rename = "hdl32e")]
    Hdl32e,
    /// Ouster OS1, 16 beams.
    #[serde(rename = "os1-16")]
    Os1_16,
    /// Ouster OS1, 32 beams.
    #[serde(rename = "os1-32")]
    Os1_32,
    /// Ouster OS1, 64 beams.
    #[serde(rename = "os1-64")]
    Os1_64,
    /// Ouster OS1, 128 beams.
    #[serde(rename = "os1-128")]
    Os1_128,
}

/// Sensor family, which decides packet formats and the order of `ring` in point clouds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SensorFamily {
    /// Velodyne: `ring` 0 is the lowest beam.
    Velodyne,
    /// Ouster: `ring` 0 is the highest beam.
    Ouster,
}

impl Preset {
    /// Every preset, in the order the documentation lists them.
    pub const ALL: [Preset; 7] = [
        Preset::Vlp16,
        Preset::Vlp32c,
        Preset::Hdl32e,
        Preset::Os1_16,
        Preset::Os1_32,
        Preset::Os1_64,
        Preset::Os1_128,
    ];

    /// The name used in files and on the command line (`vlp16`, `os1-64`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Preset::Vlp16 => "vlp16",
            Preset::Vlp32c => "vlp32c",
            Preset::Hdl32e => "hdl32e",
            Preset::Os1_16 => "os1-16",
            Preset::Os1_32 => "os1-32",
            Preset::Os1_64 => "os1-64",
            Preset::Os1_128 => "os1-128",
        }
    }

    /// The known names joined by ", " (for error messages).
    pub fn known() -> String {
        Self::ALL.iter().map(|p| p.name()).collect::<Vec<_>>().join(", ")
    }

    /// A one-line description.
    pub fn description(self) -> &'static str {
        match self {
            Preset::Vlp16 => "Velodyne VLP-16, 16 beams over +-15 deg",
            Preset::Vlp32c => "Velodyne VLP-32C, 32 beams over -25..+15 deg",
            Preset::Hdl32e => "Velodyne HDL-32E, 32 beams over -30.67..+10.67 deg",
            Preset::Os1_16 => "Ouster OS1-16",
            Preset::Os1_32 => "Ouster OS1-32",
            Preset::Os1_64 => "Ouster OS1-64",
            Preset::Os1_128 => "Ouster OS1-128",
        }
    }

    /// Velodyne or Ouster.
    pub fn family(self) -> SensorFamily {
        match self {
            Preset::Vlp16 | Preset::Vlp32c | Preset::Hdl32e => SensorFamily::Velodyne,
            _ => SensorFamily::Ouster,
        }
    }

    /// Number of beams (range-image rows).
    pub fn rows(self) -> usize {
        match self {
            Preset::Vlp16 | Preset::Os1_16 => 16,
            Preset::Vlp32c | Preset::Hdl32e | Preset::Os1_32 => 32,
            Preset::Os1_64 => 64,
            Preset::Os1_128 => 128,
        }
    }

    /// Nominal beam elevations in degrees, row 0 the highest (datasheet values; Velodyne's
    /// agree with the factory calibration files of the VLP-16, VLP-32C and HDL-32E). Ouster
    /// beams are taken as evenly spread over the OS1's +-21.2 deg; the real table comes from
    /// the sensor's metadata.
    pub fn nominal_elevations_deg(self) -> Vec<f64> {
        let mut asc: Vec<f64> = match self {
            Preset::Vlp16 => (0..16).map(|i| -15.0 + 2.0 * i as f64).collect(),
            Preset::Vlp32c => vec![
                -25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0,
                -2.667, -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333,
                1.667, 2.333, 3.333, 4.667, 7.0, 10.333, 15.0,
            ],
            Preset::Hdl32e => (0..32).map(|i| -30.67 + (41.34 / 31.0) * i as f64).collect(),
            _ => {
                let n = self.rows();
                (0..n).map(|i| -21.2 + 42.4 * i as f64 / (n - 1) as f64).collect()
            }
        };
        asc.reverse();
        asc
    }

    /// The nominal range-image layout with `columns` columns (clockwise, as both families
    /// spin), every beam at azimuth offset 0.
    pub fn nominal_layout(self, columns: usize) -> Result<RangeImageLayout, ConfigError> {
        let el: Vec<f32> = self.nominal_elevations_deg().iter().map(|d| d.to_radians() as f32).collect();
        RangeImageLayout::from_elevations(&el, columns, true)
            .map_err(|e| ConfigError(format!("config: sensor.columns = {columns}: {e}")))
    }
}

impl FromStr for Preset {
    type Err = ConfigError;
    fn from_str(s: &str) -> Result<Self, ConfigError> {
        Self::ALL.iter().copied().find(|p| p.name().eq_ignore_ascii_case(s)).ok_or_else(|| {
            ConfigError(format!("config: unknown preset \"{s}\" (known: {})", Preset::known()))
        })
    }
}

impl fmt::Display for Preset {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Where the IMU samples come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ImuSource {
    /// loglio's serial IMU frames on `imu.serial_device`.
    Serial,
    /// The Ouster's own IMU packets (UDP `network.imu_port`, or in the pcap/bag).
    Ouster,
    /// A CSV file `t,gx,gy,gz,ax,ay,az` (replays only).
    Csv,
    /// An autopilot's `HIGHRES_IMU`, `SCALED_IMU` or `RAW_IMU` over MAVLink on UDP
    /// `network.mavlink_imu_port` (live only).
    Mavlink,
    /// No IMU: LiDAR-only odometry with a constant-velocity model (the core's
    /// `MotionModel::LIDAR_ONLY`; the world is the first scan's frame, not gravity-aligned).
    None,
}

/// What the serial IMU speaks (`imu.protocol`, `loglio live --imu-protocol`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum ImuProtocol {
    /// loglio's IMU frames (COBS + postcard + CRC-32); their time is used as it is.
    #[default]
    Loglio,
    /// Xsens MTi binary output (MTData2: Acceleration, RateOfTurn, SampleTimeFine).
    Xsens,
    /// VectorNav binary output (Common group: TimeStartup, AngularRate, Accel).
    Vectornav,
}

impl ImuProtocol {
    /// The name users type.
    pub fn name(self) -> &'static str {
        match self {
            Self::Loglio => "loglio",
            Self::Xsens => "xsens",
            Self::Vectornav => "vectornav",
        }
    }

    /// Whether the device stamps samples on its own clock (time since its power-on), which the
    /// host puts onto its own clock ([`crate::input::time_align::DeviceClock`]).
    pub fn own_clock(self) -> bool {
        !matches!(self, Self::Loglio)
    }
}

impl fmt::Display for ImuProtocol {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Which clock stamps the LiDAR points.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LidarTimeSource {
    /// The sensor's own timestamp in each packet (PTP/GPS-synchronised or free-running).
    Packet,
    /// The host's receive time (live) or the capture time (pcap, bag record time).
    Capture,
}

// The core's settings, with the spellings users type (`full`, `plane-only`, `plain`; `exact`,
// `block`): one definition each.
pub use loglio_core::association::AssociationMode;
pub use loglio_core::voxel_map::KnnReach;

/// `[sensor]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorConfig {
    /// Range-image columns per revolution.
    pub columns: u32,
    /// Revolutions per second.
    pub scan_rate_hz: f64,
    /// Points closer than this are ignored, metres.
    pub blind: f64,
    /// Points farther than this are ignored, metres.
    pub max_range: f64,
    /// Velodyne calibration file (ROS velodyne YAML).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<PathBuf>,
    /// Ouster metadata JSON.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ouster_metadata: Option<PathBuf>,
}

/// `[network]` (live UDP).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetworkConfig {
    /// Local address to bind the UDP sockets to.
    pub bind: String,
    /// UDP port of the LiDAR data packets.
    pub lidar_port: u16,
    /// UDP port of the Ouster IMU packets.
    pub imu_port: u16,
    /// UDP port of the MAVLink IMU messages (`imu.source = "mavlink"`).
    #[serde(default = "default_mavlink_imu_port")]
    pub mavlink_imu_port: u16,
}

fn default_mavlink_imu_port() -> u16 {
    14550
}

/// `[imu]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImuConfig {
    /// Where samples come from.
    pub source: ImuSource,
    /// Serial device of the IMU.
    pub serial_device: String,
    /// What the serial IMU speaks.
    #[serde(default)]
    pub protocol: ImuProtocol,
    /// Serial baud rate.
    pub baud: u32,
    /// IMU CSV file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub csv_path: Option<PathBuf>,
    /// MAVLink `RAW_IMU` accelerometer scale, m/s^2 per count.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raw_imu_acc_scale: Option<f64>,
    /// MAVLink `RAW_IMU` gyroscope scale, rad/s per count.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raw_imu_gyro_scale: Option<f64>,
    /// Gyroscope white noise density, rad/s/sqrt(Hz).
    pub gyro_noise: f64,
    /// Accelerometer white noise density, m/s^2/sqrt(Hz).
    pub acc_noise: f64,
    /// Gyroscope bias random walk, rad/s^2/sqrt(Hz).
    pub gyro_bias_walk: f64,
    /// Accelerometer bias random walk, m/s^3/sqrt(Hz).
    pub acc_bias_walk: f64,
    /// Local gravity magnitude, m/s^2.
    pub gravity: f64,
    /// The gyroscope's full scale, deg/s: samples at it are counted as saturated, beyond it
    /// dropped.
    pub gyro_full_scale: f64,
    /// The accelerometer's full scale, g.
    pub acc_full_scale: f64,
}

/// `[extrinsics]`: the LiDAR frame in the IMU frame, `p_imu = R * p_lidar + t`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Extrinsics {
    /// t, metres.
    pub translation: [f64; 3],
    /// R as roll, pitch, yaw in degrees (R = Rz(yaw) Ry(pitch) Rx(roll)).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotation_rpy_deg: Option<[f64; 3]>,
    /// R as a unit quaternion w, x, y, z.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotation_quat_wxyz: Option<[f64; 4]>,
    /// A FAST-LIO / LOG-LIO YAML file with `extrinsic_T` and `extrinsic_R` instead (relative
    /// paths are taken from the configuration file's folder by [`Config::load`]); read by
    /// `run::setup::RunSetup::resolve_extrinsic`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<PathBuf>,
}

impl Extrinsics {
    /// The translation t, metres.
    pub fn translation(&self) -> [f64; 3] {
        self.translation
    }

    /// The rotation as a unit quaternion (w, x, y, z); identity if neither form is set.
    pub fn quaternion_wxyz(&self) -> [f64; 4] {
        if let Some(q) = self.rotation_quat_wxyz {
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            return [q[0] / n, q[1] / n, q[2] / n, q[3] / n];
        }
        let [r, p, y] = self.rotation_rpy_deg.unwrap_or([0.0; 3]).map(f64::to_radians);
        let (sr, cr) = (r / 2.0).sin_cos();
        let (sp, cp) = (p / 2.0).sin_cos();
        let (sy, cy) = (y / 2.0).sin_cos();
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    }

    /// The rotation matrix R (row-major).
    pub fn rotation_matrix(&self) -> [[f64; 3]; 3] {
        quat_to_matrix(self.quaternion_wxyz())
    }
}

/// Rotation matrix of a unit quaternion (w, x, y, z).
pub fn quat_to_matrix([w, x, y, z]: [f64; 4]) -> [[f64; 3]; 3] {
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// `[time]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TimeConfig {
    /// LiDAR clock minus IMU clock, seconds: IMU stamps are moved onto the LiDAR clock by adding it.
    pub lidar_imu_offset: f64,
    /// Added to a scan's stamp to get its start, seconds (-0.1 when a 10 Hz driver stamps scan ends).
    pub scan_stamp_offset: f64,
    /// Which clock stamps the LiDAR points.
    pub lidar_time_source: LidarTimeSource,
    /// Estimate what `lidar_imu_offset` leaves of the offset from the scans and apply it.
    pub estimate_offset: bool,
}

/// `[mapping]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MappingConfig {
    /// Voxel edge of the map, metres.
    pub voxel_size: f64,
    /// Leaf size of the scan downsampling, metres.
    pub scan_voxel_size: f64,
    /// Most voxels the map holds (the preallocated pool).
    pub map_capacity: u64,
    /// Most downsampled points measured per scan (0: all; default 5,000).
    pub max_points: u64,
    /// Association mode.
    pub association: AssociationMode,
    /// Nearest-neighbour search of the association.
    #[serde(default)]
    pub knn_search: KnnReach,
    /// Remove the map voxels each scan sees through (moving objects' ghost trails).
    #[serde(default = "yes")]
    pub clear_free_space: bool,
    /// Every how many range-image columns Ring FALS estimates normals (1, 2 or 4).
    #[serde(default = "one")]
    pub normals_column_stride: u8,
    /// Point-to-plane fits along a line take the point's normal below this spread (0: off).
    #[serde(default)]
    pub plane_line_spread: f64,
}

fn yes() -> bool {
    true
}

fn one() -> u8 {
    1
}

/// `[filter]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FilterConfig {
    /// Most iterated-update passes per scan.
    pub max_iterations: u32,
    /// Zero-velocity and zero-rate updates while the platform stands still.
    #[serde(default = "standstill_default")]
    pub standstill: bool,
    /// The residuals' Cauchy kernel, in standard deviations of their noise (0: plain least
    /// squares).
    #[serde(default = "three")]
    pub robust_sigmas: f64,
}

/// The core's default (`StandstillConfig::DEFAULT`): the one place it is decided.
fn standstill_default() -> bool {
    loglio_core::standstill::StandstillConfig::DEFAULT.enabled
}

fn three() -> f64 {
    3.0
}

/// `[compute]`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ComputeConfig {
    /// Threads for the association's searches; 0: the available cores, at most
    /// [`loglio_core::parallel::MAX_WIDTH`]. The results do not depend on it.
    #[serde(default)]
    pub threads: u32,
}

impl ComputeConfig {
    /// The threads to use: the setting, or the available cores, within 1..=MAX_WIDTH.
    pub fn resolved_threads(&self) -> usize {
        let n = match self.threads {
            0 => std::thread::available_parallelism().map_or(1, |n| n.get()),
            n => n as usize,
        };
        n.clamp(1, loglio_core::parallel::MAX_WIDTH)
    }
}

/// The whole configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// The sensor preset the values started from.
    pub preset: Preset,
    /// `[sensor]`.
    pub sensor: SensorConfig,
    /// `[network]`.
    pub network: NetworkConfig,
    /// `[imu]`.
    pub imu: ImuConfig,
    /// `[extrinsics]`.
    pub extrinsics: Extrinsics,
    /// `[time]`.
    pub time: TimeConfig,
    /// `[mapping]`.
    pub mapping: MappingConfig,
    /// `[filter]`.
    pub filter: FilterConfig,
    /// `[compute]`.
    #[serde(default)]
    pub compute: ComputeConfig,
}

/// What a key holds, for checking and for the template's comments.
#[derive(Clone, Copy, Debug)]
enum Kind {
    Bool,
    Float { min: f64, max: f64 },
    Int { min: i64, max: i64 },
    Str,
    Path,
    Enum(&'static [&'static str]),
    Floats { len: usize, min: f64, max: f64 },
}

/// One documented key.
#[derive(Clone, Copy, Debug)]
struct Spec {
    key: &'static str,
    kind: Kind,
    unit: &'static str,
    doc: &'static str,
    /// Optional keys may be absent; the template shows them commented out with this example.
    example: Option<&'static str>,
}

const fn spec(key: &'static str, kind: Kind, unit: &'static str, doc: &'static str) -> Spec {
    Spec { key, kind, unit, doc, example: None }
}

const fn opt(key: &'static str, kind: Kind, unit: &'static str, doc: &'static str, ex: &'static str) -> Spec {
    Spec { key, kind, unit, doc, example: Some(ex) }
}

/// Every key of the file, in template order. Single source of the ranges, units and docs.
static SPECS: &[Spec] = &[
    spec(
        "sensor.columns",
        Kind::Int { min: 8, max: 3600 },
        "columns",
        "Range-image columns per revolution: 360 deg / column width for Velodyne (1800 = 0.2 deg); the lidar mode's columns for Ouster (512, 1024 or 2048).",
    ),
    spec(
        "sensor.scan_rate_hz",
        Kind::Float { min: 5.0, max: 20.0 },
        "Hz",
        "Revolutions per second (Velodyne RPM / 60; Ouster 10 or 20).",
    ),
    spec(
        "sensor.blind",
        Kind::Float { min: 0.0, max: 50.0 },
        "m",
        "Points closer than this to the LiDAR are ignored (the robot itself, rain, dust). The reference used 2 m where the platform is in view.",
    ),
    spec(
        "sensor.max_range",
        Kind::Float { min: 1.0, max: 500.0 },
        "m",
        "Points farther than this are ignored.",
    ),
    opt(
        "sensor.calibration",
        Kind::Path,
        "path",
        "Velodyne calibration file (ROS velodyne YAML) with the beam table; without it the datasheet angles are used.",
        "\"VLP16.yaml\"",
    ),
    opt(
        "sensor.ouster_metadata",
        Kind::Path,
        "path",
        "Ouster sensor metadata JSON (beam angles, lidar mode, IMU transform); needed for raw Ouster packets.",
        "\"os1.json\"",
    ),
    spec("network.bind", Kind::Str, "IP address", "Local address the UDP sockets bind to (live only)."),
    spec(
        "network.lidar_port",
        Kind::Int { min: 1, max: 65535 },
        "UDP port",
        "Port of the LiDAR data packets (Velodyne 2368, Ouster 7502).",
    ),
    spec(
        "network.imu_port",
        Kind::Int { min: 1, max: 65535 },
        "UDP port",
        "Port of the Ouster IMU packets (7503); unused for Velodyne.",
    ),
    spec(
        "network.mavlink_imu_port",
        Kind::Int { min: 1, max: 65535 },
        "UDP port",
        "Port the autopilot sends its MAVLink IMU messages to (imu.source = \"mavlink\").",
    ),
    spec(
        "imu.source",
        Kind::Enum(&["serial", "ouster", "csv", "mavlink", "none"]),
        "",
        "Where IMU samples come from: serial = the IMU on imu.serial_device (imu.protocol); ouster = the Ouster's own IMU packets; csv = imu.csv_path (replays); mavlink = an autopilot's HIGHRES_IMU, SCALED_IMU or RAW_IMU on UDP network.mavlink_imu_port (live); none = no IMU: LiDAR-only odometry with a constant-velocity model (the world is the first scan's frame).",
    ),
    spec(
        "imu.serial_device",
        Kind::Str,
        "device path",
        "Serial device of the IMU (imu.source = \"serial\").",
    ),
    spec(
        "imu.protocol",
        Kind::Enum(&["loglio", "xsens", "vectornav"]),
        "",
        "What the serial IMU speaks: loglio = loglio's IMU frames (their time is used as it is); xsens = Xsens MTData2 (Acceleration, RateOfTurn, SampleTimeFine); vectornav = VectorNav binary output (TimeStartup, AngularRate, Accel). The Xsens and VectorNav times are put onto this computer's clock (see docs/sensors.md).",
    ),
    spec("imu.baud", Kind::Int { min: 1200, max: 12_000_000 }, "baud", "Serial baud rate."),
    opt(
        "imu.csv_path",
        Kind::Path,
        "path",
        "IMU CSV with the header t,gx,gy,gz,ax,ay,az (s, rad/s, m/s^2); for imu.source = \"csv\".",
        "\"imu.csv\"",
    ),
    opt(
        "imu.raw_imu_acc_scale",
        Kind::Float { min: 1e-9, max: 1.0 },
        "m/s^2 per count",
        "MAVLink RAW_IMU accelerometer scale: full scale / 32768 for raw counts (e.g. 16 g: 0.0047884), 0.00980665 for ArduPilot's (milli-g). Without both scales RAW_IMU is ignored.",
        "0.00980665",
    ),
    opt(
        "imu.raw_imu_gyro_scale",
        Kind::Float { min: 1e-9, max: 1.0 },
        "rad/s per count",
        "MAVLink RAW_IMU gyroscope scale: full scale / 32768 for raw counts (e.g. 2000 deg/s: 0.0010653), 0.001 for ArduPilot's (mrad/s).",
        "0.001",
    ),
    spec(
        "imu.gyro_noise",
        Kind::Float { min: 1e-6, max: 1.0 },
        "rad/s/sqrt(Hz)",
        "Gyroscope white noise density (tuned for LIO, larger than a datasheet's).",
    ),
    spec(
        "imu.acc_noise",
        Kind::Float { min: 1e-5, max: 10.0 },
        "m/s^2/sqrt(Hz)",
        "Accelerometer white noise density.",
    ),
    spec(
        "imu.gyro_bias_walk",
        Kind::Float { min: 1e-9, max: 1.0 },
        "rad/s^2/sqrt(Hz)",
        "Gyroscope bias random walk.",
    ),
    spec(
        "imu.acc_bias_walk",
        Kind::Float { min: 1e-8, max: 10.0 },
        "m/s^3/sqrt(Hz)",
        "Accelerometer bias random walk.",
    ),
    spec("imu.gravity", Kind::Float { min: 9.7, max: 9.9 }, "m/s^2", "Local gravity magnitude."),
    spec(
        "imu.gyro_full_scale",
        Kind::Float { min: 100.0, max: 10000.0 },
        "deg/s",
        "The gyroscope's full scale (its configured range, e.g. 250, 500, 1000, 2000): samples within 2 % of it are counted as saturated, and on a saturated axis the filter takes the rate the last scans measured where it is larger and trusts its attitude less; beyond it a sample is dropped.",
    ),
    spec(
        "imu.acc_full_scale",
        Kind::Float { min: 1.0, max: 100.0 },
        "g",
        "The accelerometer's full scale (e.g. 2, 4, 8, 16): samples within 2 % of it are counted as saturated, beyond it dropped.",
    ),
    spec(
        "extrinsics.translation",
        Kind::Floats { len: 3, min: -10.0, max: 10.0 },
        "m",
        "LiDAR origin in the IMU frame, x y z: p_imu = R * p_lidar + translation.",
    ),
    opt(
        "extrinsics.rotation_rpy_deg",
        Kind::Floats { len: 3, min: -360.0, max: 360.0 },
        "deg",
        "R as roll, pitch, yaw (R = Rz(yaw) Ry(pitch) Rx(roll)). Set this or rotation_quat_wxyz, not both; neither means identity.",
        "[0.0, 0.0, 0.0]",
    ),
    opt(
        "extrinsics.rotation_quat_wxyz",
        Kind::Floats { len: 4, min: -1.0, max: 1.0 },
        "unit quaternion",
        "R as a unit quaternion w, x, y, z. Set this or rotation_rpy_deg, not both.",
        "[1.0, 0.0, 0.0, 0.0]",
    ),
    opt(
        "extrinsics.file",
        Kind::Path,
        "path",
        "A FAST-LIO / LOG-LIO YAML file whose mapping section gives extrinsic_T [x, y, z] and extrinsic_R [9 numbers, row-major]: the LiDAR's pose in the IMU frame. A relative path is from this file's folder. Set this or translation and a rotation, not both; --extrinsic FILE overrides it.",
        "\"fast_lio.yaml\"",
    ),
    spec(
        "time.lidar_imu_offset",
        Kind::Float { min: -4e9, max: 4e9 },
        "s",
        "LiDAR clock minus IMU clock: IMU stamps are moved onto the LiDAR clock by adding it (any size: an IMU counting from its power-on beside a LiDAR on GPS time is 1.7e9 s behind; `loglio replay` names the offset that lines up streams that do not overlap).",
    ),
    spec(
        "time.estimate_offset",
        Kind::Bool,
        "",
        "Estimate what lidar_imu_offset leaves of the IMU-LiDAR clock offset (up to ±50 ms) from how it bends the scans, and apply it to the IMU stamps (see docs/estimation.md).",
    ),
    spec(
        "time.scan_stamp_offset",
        Kind::Float { min: -1.0, max: 1.0 },
        "s",
        "Added to each scan's stamp to get its start (-0.1 for a 10 Hz driver that stamps the scan end).",
    ),
    spec(
        "time.lidar_time_source",
        Kind::Enum(&["packet", "capture"]),
        "",
        "packet = the sensor's own timestamps (PTP/GPS or free-running); capture = the host's receive or capture time.",
    ),
    spec(
        "mapping.voxel_size",
        Kind::Float { min: 0.05, max: 5.0 },
        "m",
        "Voxel edge of the map (the paper: 0.4 for VLP-32C, 0.5 for OS1-16).",
    ),
    spec(
        "mapping.scan_voxel_size",
        Kind::Float { min: 0.05, max: 5.0 },
        "m",
        "Leaf size of the scan downsampling.",
    ),
    spec(
        "mapping.map_capacity",
        Kind::Int { min: 1024, max: 100_000_000 },
        "voxels",
        "Most voxels the map holds; the pool is allocated once at start-up (memory = capacity x bytes per voxel, see docs/voxel-map.md).",
    ),
    spec(
        "mapping.max_points",
        Kind::Int { min: 0, max: 10_000_000 },
        "points",
        "Measurement budget: at most this many downsampled points per scan are associated and measured, evenly spread over the scan, each standing for its share of the rest (0 = all; default 5000). The map still receives every point. Bounds the association's time on dense sensors (see docs/estimation.md).",
    ),
    spec(
        "mapping.association",
        Kind::Enum(&["full", "plane-only", "plain"]),
        "",
        "full = LOG-LIO (large surfel, small surfel, point-to-plane, with visibility and consistency checks); plane-only = LOG-C; plain = no normals, no checks (FAST-LIO2-like).",
    ),
    spec(
        "mapping.knn_search",
        Kind::Enum(&["exact", "block"]),
        "",
        "block = the point's 2x2x2 octant block first (the default: 0.9x the association's time, the same errors on well-structured scenes, and with the standstill updates half the drift along a featureless corridor's axis); exact = the k nearest map points within the 27 voxels around each point (see docs/estimation.md).",
    ),
    spec(
        "mapping.clear_free_space",
        Kind::Bool,
        "",
        "Remove the map voxels that a scan sees through (the beams around them hit farther): the ghost trails moving cars and people leave (see docs/estimation.md).",
    ),
    spec(
        "mapping.normals_column_stride",
        Kind::Int { min: 1, max: 4 },
        "columns",
        "Every how many range-image columns Ring FALS estimates normals: 1, 2 or 4. With 2 the other columns' returns take the normal of their kept neighbour on the same surface (every return is still measured and mapped): the normals take 0.6x the time, a VLP-32C scan about 0.9x, for about 1.1x the error on the simulated drives (see docs/ring-fals.md).",
    ),
    spec(
        "mapping.plane_line_spread",
        Kind::Float { min: 0.0, max: 1.0 },
        "",
        "Point-to-plane fits whose neighbours lie along a line (one scan ring: their middle eigenvalue under this share of the largest) fix no normal about it; where such a fit's normal is 5 to 30 degrees from the point's own (without one, its neighbours' mean), that one is taken. 0 = off (the default): 0.03 gives 0.86x the ATE on the simulated vehicle and 0.82x among traffic, 1.06x on the drone, but a VLP-16 walk after a 5 s LiDAR gap 1.6x (see docs/estimation.md).",
    ),
    spec(
        "filter.max_iterations",
        Kind::Int { min: 1, max: 20 },
        "passes",
        "Most iterated-update passes per scan.",
    ),
    spec(
        "filter.standstill",
        Kind::Bool,
        "",
        "Zero-velocity and zero-rate updates while the platform stands still (the IMU quiet, the scans see no motion), against drift at a stand where the scene leaves a direction unobserved: the stand at the start then sets the accelerometer bias instead of the scans; on by default (see docs/estimation.md).",
    ),
    spec(
        "filter.robust_sigmas",
        Kind::Float { min: 0.0, max: 100.0 },
        "sigmas",
        "The update's Cauchy kernel: at every iteration each point's residual r is weighted by 1 / (1 + r^2 / (c^2 v)), v its noise variance and c this value, so that a point a moving object or a wrong match puts 30 cm off its plane keeps a tenth of its weight while one within the noise keeps nearly all of it; 0 = plain least squares, as the reference (see docs/estimation.md).",
    ),
    spec(
        "compute.threads",
        Kind::Int { min: 0, max: 8 },
        "threads",
        "Threads for the association (0 = the available cores, at most 8); the results are the same for any number.",
    ),
];

/// One `[section]` of the file.
struct Section {
    name: &'static str,
    /// The template's heading comment.
    what: &'static str,
    /// Where its keys go in the code, for the reference page.
    code: &'static str,
}

/// Where `preset` goes in the code, for the reference page.
const PRESET_CODE: &str = "The preset and `sensor.columns` give the range-image layout (`RangeImageLayout`): rows and \
     nominal elevations from the preset, or the real beam table from `sensor.calibration` (Velodyne, \
     `velodyne_calib.rs`) or `sensor.ouster_metadata` (`ouster_meta.rs`); Ring FALS builds its table from \
     that layout.";

/// The sections of the file, in template order.
const SECTIONS: [Section; 8] = [
    Section {
        name: "sensor",
        what: "The LiDAR.",
        code: "`blind` and `max_range` are the odometry's range gate on incoming points (metres from the \
               LiDAR origin); `scan_rate_hz` gives scan assembly its expected scan period and the \
               time-from-azimuth fallback; `columns`, `calibration` and `ouster_metadata` make the \
               range-image layout (see `preset`).",
    },
    Section { name: "network", what: "Live UDP input.", code: "The host's live input (`udp.rs`)." },
    Section {
        name: "imu",
        what: "The IMU: source and noise model.",
        code: "`source`, `serial_device`, `protocol`, `baud` and `csv_path` are the host's inputs (`serial.rs`, \
               `device_imu.rs`, `imu_csv.rs`). `gyro_noise` and `acc_noise` are the ESKF's process noise as white noise \
               densities: the discrete variance per IMU step of length dt is `density^2 / dt` (rates) or \
               `density^2 * dt` (integrated angle and velocity); the bias walks add the variance \
               `density^2 * dt` per step; `gravity` is the magnitude of the gravity-aligned world frame.",
    },
    Section {
        name: "extrinsics",
        what: "The LiDAR frame in the IMU frame.",
        code: "The fixed LiDAR-in-IMU transform of the odometry, `p_imu = R * p_lidar + t` \
               (`Extrinsics::rotation_matrix`, `Extrinsics::translation`). Where it comes from, highest \
               precedence first: `--extrinsic FILE`, then this section (`file`, or `translation` and a rotation), \
               then the data (a bag's `/tf_static`, an Ouster metadata's `imu_to_sensor_transform`), \
               then the Ouster presets' internal IMU, else the identity with a warning \
               (`run::setup::RunSetup::resolve_extrinsic`; `extrinsic_file.rs`).",
    },
    Section {
        name: "time",
        what: "Clocks and time offsets.",
        code: "`time_align.rs`: IMU stamps on the LiDAR clock are `t_imu + lidar_imu_offset`; a scan starts \
               at its stamp plus `scan_stamp_offset`; `lidar_time_source` picks the packet's own time or \
               the capture time.",
    },
    Section {
        name: "mapping",
        what: "The voxel map and data association.",
        code: "`voxel_size` is the voxel map's voxel edge (the paper's map resolution), `scan_voxel_size` \
               the scan downsampling's leaf size, `map_capacity` the voxel pool's capacity (the hash index \
               is sized from it), `max_points` the association's measurement budget, `association` its \
               mode (`AssociationMode`), `knn_search` its k-NN (`KnnReach`) and `normals_column_stride` \
               Ring FALS's image (`RingFalsConfig::column_stride`).",
    },
    Section {
        name: "filter",
        what: "The iterated error-state Kalman filter.",
        code: "`max_iterations` is the iterated ESKF's maximum number of passes per scan, `standstill` \
               `OdometryConfig::standstill`, `robust_sigmas` the association's \
               `AssociationConfig::robust_sigmas` (applied as each pass linearises the residuals).",
    },
    Section {
        name: "compute",
        what: "How the work uses this computer.",
        code: "The association's threads (`loglio_core::parallel`).",
    },
];

fn find_spec(key: &str) -> Option<&'static Spec> {
    SPECS.iter().find(|s| s.key == key)
}

fn kind_range_text(kind: Kind, unit: &str) -> String {
    let unit_sfx = if unit.is_empty() { String::new() } else { format!(" {unit}") };
    match kind {
        Kind::Float { min, max } => format!("{}..={}{unit_sfx}", fmt_num(min), fmt_num(max)),
        Kind::Int { min, max } => format!("{min}..={max}{unit_sfx}"),
        Kind::Str | Kind::Path => unit.to_string(),
        Kind::Bool => "true or false".to_string(),
        Kind::Enum(list) => format!("one of: {}", list.join(", ")),
        Kind::Floats { len, min, max } => {
            format!("{len} numbers, each {}..={}{unit_sfx}", fmt_num(min), fmt_num(max))
        }
    }
}

/// A float as TOML and the messages write it: always with a '.' or an exponent.
fn fmt_num(v: f64) -> String {
    let s = if v != 0.0 && (v.abs() < 1e-3 || v.abs() >= 1e6) { format!("{v:e}") } else { format!("{v}") };
    if v.is_finite() && !s.contains(['.', 'e']) { format!("{s}.0") } else { s }
}

fn type_name(v: &toml::Value) -> &'static str {
    match v {
        toml::Value::String(_) => "a string",
        toml::Value::Integer(_) => "an integer",
        toml::Value::Float(_) => "a number",
        toml::Value::Boolean(_) => "a boolean",
        toml::Value::Datetime(_) => "a date",
        toml::Value::Array(_) => "an array",
        toml::Value::Table(_) => "a table",
    }
}

fn value_text(v: &toml::Value) -> String {
    match v {
        toml::Value::Float(f) => fmt_num(*f),
        other => other.to_string(),
    }
}

/// Checks (and normalises: integers become floats where a float is wanted) one value.
fn check_value(spec: &Spec, v: &toml::Value) -> Result<toml::Value, ConfigError> {
    let key = spec.key;
    let range = kind_range_text(spec.kind, spec.unit);
    let as_f64 = |v: &toml::Value| match v {
        toml::Value::Float(f) => Some(*f),
        toml::Value::Integer(i) => Some(*i as f64),
        _ => None,
    };
    match spec.kind {
        Kind::Bool => {
            let toml::Value::Boolean(_) = v else {
                bail!("{key} must be true or false, found {}", type_name(v))
            };
            Ok(v.clone())
        }
        Kind::Float { min, max } => {
            let Some(f) = as_f64(v) else { bail!("{key} must be a number, found {}", type_name(v)) };
            if !(min..=max).contains(&f) {
                bail!("{key} = {} is out of range ({range})", fmt_num(f));
            }
            Ok(toml::Value::Float(f))
        }
        Kind::Int { min, max } => {
            let toml::Value::Integer(i) = v else {
                bail!("{key} must be an integer, found {}", type_name(v))
            };
            if !(min..=max).contains(i) {
                bail!("{key} = {i} is out of range ({range})");
            }
            Ok(v.clone())
        }
        Kind::Str | Kind::Path => {
            let toml::Value::String(s) = v else { bail!("{key} must be a string, found {}", type_name(v)) };
            if s.is_empty() {
                bail!("{key} must not be empty");
            }
            Ok(v.clone())
        }
        Kind::Enum(list) => {
            let toml::Value::String(s) = v else { bail!("{key} must be a string, found {}", type_name(v)) };
            if !list.contains(&s.as_str()) {
                bail!("{key} = \"{s}\" is not {range}");
            }
            Ok(v.clone())
        }
        Kind::Floats { len, min, max } => {
            let toml::Value::Array(a) = v else {
                bail!("{key} must be an array of {len} numbers, found {}", type_name(v))
            };
            if a.len() != len {
                bail!("{key} must be an array of {len} numbers, found {}", a.len());
            }
            let mut out = Vec::with_capacity(len);
            for (i, e) in a.iter().enumerate() {
                let Some(f) = as_f64(e) else { bail!("{key}[{i}] must be a number, found {}", type_name(e)) };
                if !(min..=max).contains(&f) {
                    bail!("{key}[{i}] = {} is out of range ({range})", fmt_num(f));
                }
                out.push(toml::Value::Float(f));
            }
            Ok(toml::Value::Array(out))
        }
    }
}

fn section_keys(section: &str) -> String {
    SPECS
        .iter()
        .filter_map(|s| s.key.strip_prefix(section).and_then(|r| r.strip_prefix('.')))
        .collect::<Vec<_>>()
        .join(", ")
}

fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.matches('\n').count() + 1;
    let col = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    (line, col)
}

impl Config {
    /// The configuration of a preset, with no overrides.
    pub fn preset(preset: Preset) -> Config {
        let ouster = preset.family() == SensorFamily::Ouster;
        let (voxel, max_range) = match preset {
            Preset::Vlp16 => (0.5, 100.0),
            Preset::Vlp32c => (0.4, 200.0),
            Preset::Hdl32e => (0.4, 100.0),
            _ => (0.5, 120.0),
        };
        Config {
            preset,
            sensor: SensorConfig {
                columns: if ouster { 1024 } else { 1800 },
                scan_rate_hz: 10.0,
                blind: 1.0,
                max_range,
                calibration: None,
                ouster_metadata: None,
            },
            network: NetworkConfig {
                bind: "0.0.0.0".into(),
                lidar_port: if ouster { 7502 } else { 2368 },
                imu_port: 7503,
                mavlink_imu_port: 14550,
            },
            imu: ImuConfig {
                source: if ouster { ImuSource::Ouster } else { ImuSource::Serial },
                serial_device: "/dev/ttyUSB0".into(),
                protocol: ImuProtocol::Loglio,
                baud: 921_600,
                csv_path: None,
                raw_imu_acc_scale: None,
                raw_imu_gyro_scale: None,
                // LIO-tuned densities (equivalent to the reference's per-step covariances at
                // 200 Hz, see docs): far above an IMU datasheet's, which ignore vibration.
                gyro_noise: 5e-3,
                acc_noise: 2e-2,
                gyro_bias_walk: 1e-4,
                acc_bias_walk: 6e-4,
                gravity: 9.81,
                gyro_full_scale: 2000.0,
                acc_full_scale: 16.0,
            },
            extrinsics: Extrinsics {
                // Ouster: points in the sensor frame (the SDK's XYZ) and the internal IMU at
                // imu_to_sensor_transform = (6.253, -11.775, 7.645) mm in every OS1 metadata
                // file we have. Velodyne with an external IMU: measure yours.
                translation: if ouster { [-0.006253, 0.011775, -0.007645] } else { [0.0; 3] },
                rotation_rpy_deg: Some([0.0; 3]),
                rotation_quat_wxyz: None,
                file: None,
            },
            time: TimeConfig {
                lidar_imu_offset: 0.0,
                scan_stamp_offset: 0.0,
                lidar_time_source: LidarTimeSource::Packet,
                estimate_offset: true,
            },
            mapping: MappingConfig {
                voxel_size: voxel,
                scan_voxel_size: voxel,
                map_capacity: 1_000_000,
                max_points: u64::from(loglio_core::association::DEFAULT_MAX_POINTS),
                association: AssociationMode::Full,
                knn_search: loglio_core::association::AssociationConfig::DEFAULT.knn_reach,
                clear_free_space: true,
                normals_column_stride: 1,
                plane_line_spread: 0.0,
            },
            filter: FilterConfig { max_iterations: 4, standstill: standstill_default(), robust_sigmas: 3.0 },
            compute: ComputeConfig::default(),
        }
    }

    /// Reads and validates a configuration file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| ConfigError(format!("config: cannot read {}: {e}", path.display())))?;
        let mut cfg = Self::from_toml_str(&text).map_err(|e| {
            // Name the file in syntax errors only; key errors already name the key.
            if e.0.starts_with("config: line ") {
                ConfigError(e.0.replacen("config: ", &format!("config: {}: ", path.display()), 1))
            } else {
                e
            }
        })?;
        // extrinsics.file is the configuration's companion: found beside it, wherever the
        // command runs (a service's working folder is not the configuration's).
        if let Some(f) = &cfg.extrinsics.file
            && f.is_relative()
            && let Some(dir) = path.parent()
        {
            cfg.extrinsics.file = Some(dir.join(f));
        }
        Ok(cfg)
    }

    /// Parses and validates a configuration from TOML text.
    pub fn from_toml_str(text: &str) -> Result<Config, ConfigError> {
        let user: toml::Table = text.parse().map_err(|e: toml::de::Error| {
            let msg = crate::diag::one_line(e.message());
            match e.span() {
                Some(span) => {
                    let (l, c) = line_col(text, span.start);
                    ConfigError(format!("config: line {l}, column {c}: {msg}"))
                }
                None => ConfigError(format!("config: {msg}")),
            }
        })?;
        let preset = match user.get("preset") {
            None => bail!("missing key preset (one of: {})", Preset::known()),
            Some(toml::Value::String(s)) => s.parse::<Preset>()?,
            Some(v) => bail!("preset must be a string, found {}", type_name(v)),
        };
        let base = Config::preset(preset);
        let mut merged =
            toml::Table::try_from(&base).map_err(|e| ConfigError(format!("config: internal: {e}")))?;
        for (section, value) in &user {
            if section == "preset" {
                continue;
            }
            if !SECTIONS.iter().any(|s| s.name == section) {
                let known: Vec<&str> = SECTIONS.iter().map(|s| s.name).collect();
                bail!("unknown key {section} (top-level keys: preset, {})", known.join(", "));
            }
            let toml::Value::Table(entries) = value else {
                bail!("{section} must be a table ([{section}]), found {}", type_name(value));
            };
            let target = merged
                .entry(section.clone())
                .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                .as_table_mut()
                .ok_or_else(|| ConfigError(format!("config: internal: {section} is not a table")))?;
            if section == "extrinsics"
                && entries.contains_key("file")
                && let Some(k) = ["translation", "rotation_rpy_deg", "rotation_quat_wxyz"]
                    .iter()
                    .find(|k| entries.contains_key(**k))
            {
                bail!("set extrinsics.file or extrinsics.{k} (and the rest of the section), not both");
            }
            // One rotation form replaces the other unless the file sets both.
            for (a, b) in
                [("rotation_quat_wxyz", "rotation_rpy_deg"), ("rotation_rpy_deg", "rotation_quat_wxyz")]
            {
                if section == "extrinsics" && entries.contains_key(a) && !entries.contains_key(b) {
                    target.remove(b);
                }
            }
            for (key, v) in entries {
                let full = format!("{section}.{key}");
                let Some(spec) = find_spec(&full) else {
                    bail!("unknown key {full} (keys of [{section}]: {})", section_keys(section));
                };
                target.insert(key.clone(), check_value(spec, v)?);
            }
        }
        let cfg: Config = toml::Value::Table(merged).try_into().map_err(|e: toml::de::Error| {
            ConfigError(format!("config: {}", crate::diag::one_line(e.message())))
        })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks every value against its range and the keys against each other.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let table = toml::Table::try_from(self).map_err(|e| ConfigError(format!("config: internal: {e}")))?;
        for spec in SPECS {
            let (section, key) = spec.key.split_once('.').unwrap_or(("", spec.key));
            match table.get(section).and_then(|s| s.get(key)) {
                Some(v) => {
                    check_value(spec, v)?;
                }
                None if spec.example.is_some() => {}
                None => bail!("missing key {}", spec.key),
            }
        }
        let ouster = self.preset.family() == SensorFamily::Ouster;
        let p = self.preset;
        if ouster && ![512, 1024, 2048].contains(&self.sensor.columns) {
            bail!(
                "sensor.columns = {} is not an Ouster lidar mode's width (512, 1024 or 2048) for preset {p}",
                self.sensor.columns
            );
        }
        if ouster && ![10.0, 20.0].contains(&self.sensor.scan_rate_hz) {
            bail!(
                "sensor.scan_rate_hz = {} is not an Ouster rate (10 or 20) for preset {p}",
                fmt_num(self.sensor.scan_rate_hz)
            );
        }
        if self.mapping.normals_column_stride == 3 {
            bail!("mapping.normals_column_stride = 3: it must be 1, 2 or 4");
        }
        if let s @ 2.. = self.mapping.normals_column_stride
            && !self.sensor.columns.is_multiple_of(u32::from(s))
        {
            bail!(
                "mapping.normals_column_stride = {s} does not divide sensor.columns = {}",
                self.sensor.columns
            );
        }
        if self.sensor.blind >= self.sensor.max_range {
            bail!(
                "sensor.blind = {} must be less than sensor.max_range = {} (m)",
                fmt_num(self.sensor.blind),
                fmt_num(self.sensor.max_range)
            );
        }
        if ouster && self.sensor.calibration.is_some() {
            bail!(
                "sensor.calibration is a Velodyne calibration file; preset {p} is an Ouster (use sensor.ouster_metadata)"
            );
        }
        if !ouster && self.sensor.ouster_metadata.is_some() {
            bail!(
                "sensor.ouster_metadata is for Ouster presets; preset {p} is a Velodyne (use sensor.calibration)"
            );
        }
        if self.network.bind.parse::<std::net::IpAddr>().is_err() {
            bail!("network.bind = \"{}\" is not an IP address (e.g. 0.0.0.0)", self.network.bind);
        }
        match self.imu.source {
            ImuSource::Ouster if !ouster => {
                bail!("imu.source = \"ouster\" needs an Ouster preset (os1-*), not {p}")
            }
            ImuSource::Csv if self.imu.csv_path.is_none() => bail!("imu.source = \"csv\" needs imu.csv_path"),
            _ => {}
        }
        if self.imu.raw_imu_acc_scale.is_some() != self.imu.raw_imu_gyro_scale.is_some() {
            bail!("imu.raw_imu_acc_scale and imu.raw_imu_gyro_scale are set together (RAW_IMU needs both)");
        }
        let e = &self.extrinsics;
        if e.rotation_quat_wxyz.is_some() && e.rotation_rpy_deg.is_some() {
            bail!("set extrinsics.rotation_quat_wxyz or extrinsics.rotation_rpy_deg, not both");
        }
        if let Some(q) = e.rotation_quat_wxyz {
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            if (n - 1.0).abs() > 1e-3 {
                bail!(
                    "extrinsics.rotation_quat_wxyz has norm {n:.6}; it must be a unit quaternion (w, x, y, z)"
                );
            }
        }
        Ok(())
    }

    /// The nominal range-image layout of this configuration (preset beams, `sensor.columns`).
    pub fn nominal_layout(&self) -> Result<RangeImageLayout, ConfigError> {
        self.preset.nominal_layout(self.sensor.columns as usize)
    }

    /// This configuration as a commented TOML file (see [`template`]).
    pub fn to_commented_toml(&self) -> String {
        let table = toml::Table::try_from(self).unwrap_or_default();
        let mut out = String::new();
        out.push_str(&format!(
            "# loglio configuration, preset {}: {}.\n\
             # Written by `loglio config --preset {}`. Every key except `preset` is optional: a key you\n\
             # delete takes the preset's value. Check a file with `loglio config --check FILE`.\n\
             # Units: metres, seconds, radians unless the comment says otherwise.\n\n",
            self.preset,
            self.preset.description(),
            self.preset
        ));
        push_comment(
            &mut out,
            &format!(
                "The sensor model; it sets the default of every key below. One of: {}.",
                Preset::known()
            ),
        );
        out.push_str(&format!("preset = \"{}\"\n", self.preset));
        // A Velodyne preset knows no extrinsic (the IMU is the rig's): its identity is written
        // commented out, so that a file made from the template without the rig's numbers still
        // gets the run's warning that the extrinsic is missing.
        let placeholder =
            |section: &str| section == "extrinsics" && self.preset.family() == SensorFamily::Velodyne;
        for Section { name: section, what, .. } in SECTIONS {
            out.push_str(&format!("\n# {what}\n[{section}]\n"));
            if placeholder(section) {
                push_comment(
                    &mut out,
                    "Give the rig's LiDAR-IMU extrinsic here (or extrinsics.file, a FAST-LIO YAML): the preset has none.",
                );
            }
            for spec in section_specs(section) {
                let key = &spec.key[section.len() + 1..];
                let range = kind_range_text(spec.kind, spec.unit);
                let value = table.get(section).and_then(|t| t.get(key));
                let tail = match (value, spec.example) {
                    (None, Some(_)) => format!(" [{range}; unset by default]"),
                    _ => format!(" [{range}]"),
                };
                push_comment(&mut out, &format!("{}{tail}", spec.doc));
                match (value, spec.example) {
                    (Some(v), _) if placeholder(section) => {
                        out.push_str(&format!("# {key} = {}\n", value_text(v)))
                    }
                    (Some(v), _) => out.push_str(&format!("{key} = {}\n", value_text(v))),
                    (None, Some(ex)) => out.push_str(&format!("# {key} = {ex}\n")),
                    (None, None) => {}
                }
            }
        }
        out
    }
}

fn push_comment(out: &mut String, text: &str) {
    let mut line = String::from("#");
    for word in text.split_whitespace() {
        if line.len() + 1 + word.len() > 100 && line.len() > 1 {
            out.push_str(&line);
            out.push('\n');
            line = String::from("#");
        }
        line.push(' ');
        line.push_str(word);
    }
    out.push_str(&line);
    out.push('\n');
}

/// The commented template of a preset, as printed by `loglio config --preset NAME`.
pub fn template(preset: Preset) -> String {
    Config::preset(preset).to_commented_toml()
}

/// The keys of `[section]`, in template order.
fn section_specs(section: &str) -> impl Iterator<Item = &'static Spec> + '_ {
    SPECS.iter().filter(move |s| s.key.split_once('.').is_some_and(|(sec, _)| sec == section))
}

/// A table cell: no line breaks, no column separators.
fn cell(text: &str) -> String {
    text.split_whitespace().collect::<Vec<_>>().join(" ").replace('|', "\\|")
}

/// The defaults of one key over the presets: one value, or each value with its presets.
fn defaults_text(spec: &Spec, presets: &[(Preset, toml::Table)]) -> String {
    let (section, key) = spec.key.split_once('.').unwrap_or(("", spec.key));
    let mut groups: Vec<(Option<String>, Vec<&str>)> = Vec::new();
    for (p, table) in presets {
        let v = table.get(section).and_then(|t| t.get(key)).map(value_text);
        match groups.iter_mut().find(|(g, _)| *g == v) {
            Some((_, names)) => names.push(p.name()),
            None => groups.push((v, vec![p.name()])),
        }
    }
    let show = |v: &Option<String>| match (v, spec.example) {
        (Some(v), _) => format!("`{v}`"),
        (None, Some(ex)) => format!("unset (e.g. `{ex}`)"),
        (None, None) => "unset".to_string(),
    };
    match groups.as_slice() {
        [(v, _)] => show(v),
        _ => groups
            .iter()
            .map(|(v, names)| format!("{}: {}", show(v), names.join(", ")))
            .collect::<Vec<_>>()
            .join("; "),
    }
}

/// The reference of every key as Markdown, rendered from the key table (`SPECS`, `SECTIONS`):
/// the committed `docs/configuration.md`, printed by `loglio config --reference`.
pub fn reference_markdown() -> String {
    let presets: Vec<(Preset, toml::Table)> = Preset::ALL
        .iter()
        .map(|&p| (p, toml::Table::try_from(Config::preset(p)).expect("a preset serialises")))
        .collect();
    let mut out = String::new();
    out.push_str(
        "# Configuration reference\n\n\
         <!-- Generated from the key table in host/src/config.rs (SPECS, SECTIONS): edit it there and run\n\
         `loglio config --reference > docs/configuration.md`; a unit test fails while this file differs. -->\n\n\
         A configuration file is TOML: `preset = \"NAME\"` and any of the keys below, each overriding the\n\
         preset's value; a key left out takes the preset's value. `loglio config --preset NAME` prints\n\
         a preset's file with every key commented, `loglio config --check FILE` validates one, and the\n\
         commands that run the odometry read one with `--config FILE`. Units are metres, seconds and\n\
         radians unless the key says otherwise; a value outside its range is an error that names the\n\
         key and the range.\n\n\
         ## `preset`\n\n\
         The sensor model (required); it sets the default of every other key.\n\n\
         | preset | sensor |\n|---|---|\n",
    );
    for p in Preset::ALL {
        out.push_str(&format!("| `{}` | {} |\n", p.name(), cell(p.description())));
    }
    out.push_str(&format!("\n**In the code.** {}\n", cell(PRESET_CODE)));
    for Section { name: section, what, code } in SECTIONS {
        out.push_str(&format!("\n## `[{section}]`\n\n{what}\n\n"));
        out.push_str("| key | range | default | meaning |\n|---|---|---|---|\n");
        for spec in section_specs(section) {
            out.push_str(&format!(
                "| `{}` | {} | {} | {} |\n",
                spec.key,
                cell(&kind_range_text(spec.kind, spec.unit)),
                cell(&defaults_text(spec, &presets)),
                cell(spec.doc)
            ));
        }
        out.push_str(&format!("\n**In the code.** {}\n", cell(code)));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    fn err(text: &str) -> String {
        Config::from_toml_str(text).unwrap_err().0
    }

    #[test]
    fn every_preset_is_valid_and_its_template_parses_back() {
        for p in Preset::ALL {
            let cfg = Config::preset(p);
            cfg.validate().unwrap();
            let text = template(p);
            let back = Config::from_toml_str(&text).unwrap_or_else(|e| panic!("{p}: {e}\n{text}"));
            assert_eq!(back, cfg, "{p}");
            // Every key has a comment line right above it.
            let lines: Vec<&str> = text.lines().collect();
            for (i, l) in lines.iter().enumerate() {
                if !l.starts_with('#') && l.contains(" = ") {
                    assert!(lines[i - 1].starts_with('#'), "{p}: no comment above `{l}`");
                }
            }
            assert_eq!(p.nominal_elevations_deg().len(), p.rows());
            let layout = cfg.nominal_layout().unwrap();
            assert_eq!(layout.rows(), p.rows());
            assert!(layout.elevation(0) > layout.elevation(p.rows() - 1), "row 0 is the highest");
        }
    }

    #[test]
    fn template_lists_every_key() {
        let text = template(Preset::Vlp16);
        for spec in SPECS {
            let key = spec.key.split_once('.').unwrap().1;
            let set = text.lines().any(|l| l.starts_with(&format!("{key} = ")));
            let commented = text.lines().any(|l| l.starts_with(&format!("# {key} = ")));
            assert!(set || commented, "{} missing from the template", spec.key);
        }
    }

    /// Optional keys that no preset sets, so a serialised preset never has them.
    const UNSET_IN_EVERY_PRESET: [(&str, &str); 7] = [
        ("sensor.calibration", "without it the datasheet beam table is used"),
        ("sensor.ouster_metadata", "without it the nominal Ouster beam table is used"),
        ("imu.csv_path", "only imu.source = \"csv\" reads it"),
        ("imu.raw_imu_acc_scale", "only MAVLink RAW_IMU needs it"),
        ("imu.raw_imu_gyro_scale", "only MAVLink RAW_IMU needs it"),
        ("extrinsics.rotation_quat_wxyz", "the presets give the rotation as rotation_rpy_deg"),
        ("extrinsics.file", "the presets give the extrinsic as numbers"),
    ];

    /// The dotted keys of a serialised configuration (arrays are values, not tables).
    fn dotted_keys(cfg: &Config) -> BTreeSet<String> {
        fn walk(prefix: &str, table: &toml::Table, out: &mut BTreeSet<String>) {
            for (k, v) in table {
                let key = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                match v {
                    toml::Value::Table(t) => walk(&key, t, out),
                    _ => {
                        out.insert(key);
                    }
                }
            }
        }
        let mut out = BTreeSet::new();
        walk("", &toml::Table::try_from(cfg).unwrap(), &mut out);
        out
    }

    #[test]
    fn the_structs_and_the_key_table_agree() {
        let specs: BTreeSet<String> = SPECS.iter().map(|s| s.key.to_string()).collect();
        assert_eq!(specs.len(), SPECS.len(), "a key is twice in SPECS");
        let sections: Vec<&str> = SECTIONS.iter().map(|s| s.name).collect();
        let mut spec_sections: Vec<&str> = SPECS.iter().map(|s| s.key.split_once('.').unwrap().0).collect();
        spec_sections.dedup();
        assert_eq!(spec_sections, sections, "SPECS and SECTIONS list the sections in the same order");
        let mut set_by_presets = specs.clone();
        for (key, why) in UNSET_IN_EVERY_PRESET {
            let spec = find_spec(key).unwrap_or_else(|| panic!("{key} is not in SPECS"));
            assert!(spec.example.is_some(), "{key} is unset in every preset ({why}) but not optional");
            set_by_presets.remove(key);
        }
        let with_preset = |keys: &BTreeSet<String>| {
            let mut keys = keys.clone();
            keys.insert("preset".to_string());
            keys
        };
        // Every field of every preset has a spec, and every spec a field.
        for p in Preset::ALL {
            assert_eq!(
                dotted_keys(&Config::preset(p)),
                with_preset(&set_by_presets),
                "{p}: the serialised keys (left) against SPECS less UNSET_IN_EVERY_PRESET (right)"
            );
        }
        // The optional keys are fields too: set, they serialise, and then the keys are all of SPECS.
        let mut cfg = Config::preset(Preset::Vlp16);
        cfg.sensor.calibration = Some("VLP16.yaml".into());
        cfg.sensor.ouster_metadata = Some("os1.json".into());
        cfg.imu.csv_path = Some("imu.csv".into());
        cfg.imu.raw_imu_acc_scale = Some(0.00980665);
        cfg.imu.raw_imu_gyro_scale = Some(0.001);
        cfg.extrinsics.rotation_quat_wxyz = Some([1.0, 0.0, 0.0, 0.0]);
        cfg.extrinsics.file = Some("fast_lio.yaml".into());
        assert_eq!(
            dotted_keys(&cfg),
            with_preset(&specs),
            "the serialised keys (left) against SPECS (right)"
        );
    }

    #[test]
    fn the_reference_page_is_the_generated_one() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/configuration.md");
        let want = reference_markdown();
        if std::env::var_os("LOGLIO_BLESS").is_some() {
            std::fs::write(&path, &want).unwrap();
            return;
        }
        let have = std::fs::read_to_string(&path).unwrap_or_default();
        if have != want {
            let line = have.lines().zip(want.lines()).take_while(|(a, b)| a == b).count() + 1;
            panic!(
                "docs/configuration.md differs from the reference generated from SPECS and SECTIONS \
                 (first at line {line}); regenerate it with \
                 `cargo run -p loglio-host -- config --reference > docs/configuration.md` \
                 or `LOGLIO_BLESS=1 cargo test -p loglio-host --lib config`"
            );
        }
    }

    #[test]
    fn overrides_apply_over_the_preset() {
        let cfg = Config::from_toml_str(
            "preset = \"vlp32c\"\n[mapping]\nvoxel_size = 1\nassociation = \"plane-only\"\n\
             [extrinsics]\ntranslation = [0.27255, -0.00053, 0.17954]\nrotation_quat_wxyz = [0.0, 0.0, 0.0, 1.0]\n",
        )
        .unwrap();
        assert_eq!(cfg.mapping.voxel_size, 1.0);
        assert_eq!(cfg.mapping.scan_voxel_size, 0.4);
        assert_eq!(cfg.mapping.association, AssociationMode::PlaneOnly);
        assert_eq!(cfg.extrinsics.translation, [0.27255, -0.00053, 0.17954]);
        assert_eq!(cfg.extrinsics.rotation_rpy_deg, None, "the quaternion replaces the preset's rpy");
        let r = cfg.extrinsics.rotation_matrix();
        // 180 deg about z.
        let want = [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]];
        for i in 0..3 {
            for j in 0..3 {
                assert!((r[i][j] - want[i][j]).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn rpy_matches_the_zyx_convention() {
        let e = Extrinsics {
            translation: [0.0; 3],
            rotation_rpy_deg: Some([10.0, -20.0, 30.0]),
            rotation_quat_wxyz: None,
            file: None,
        };
        let r = e.rotation_matrix();
        let (a, b, c) = (10f64.to_radians(), (-20f64).to_radians(), 30f64.to_radians());
        let rx = [[1.0, 0.0, 0.0], [0.0, a.cos(), -a.sin()], [0.0, a.sin(), a.cos()]];
        let ry = [[b.cos(), 0.0, b.sin()], [0.0, 1.0, 0.0], [-b.sin(), 0.0, b.cos()]];
        let rz = [[c.cos(), -c.sin(), 0.0], [c.sin(), c.cos(), 0.0], [0.0, 0.0, 1.0]];
        let mul = |x: [[f64; 3]; 3], y: [[f64; 3]; 3]| {
            let mut m = [[0.0; 3]; 3];
            for i in 0..3 {
                for j in 0..3 {
                    m[i][j] = (0..3).map(|k| x[i][k] * y[k][j]).sum();
                }
            }
            m
        };
        let want = mul(rz, mul(ry, rx));
        for i in 0..3 {
            for j in 0..3 {
                assert!((r[i][j] - want[i][j]).abs() < 1e-12, "{i}{j}");
            }
        }
    }

    /// An IMU counting from its power-on beside a LiDAR on GPS time: decades apart.
    #[test]
    fn the_imu_offset_may_be_any_clock_difference() {
        let c = Config::from_toml_str("preset = \"vlp16\"\n[time]\nlidar_imu_offset = 1.7e9\n").unwrap();
        assert_eq!(c.time.lidar_imu_offset, 1.7e9);
        let c = Config::from_toml_str("preset = \"vlp16\"\n[time]\nlidar_imu_offset = -86400.25\n").unwrap();
        assert_eq!(c.time.lidar_imu_offset, -86400.25);
        assert!(
            err("preset = \"vlp16\"\n[time]\nlidar_imu_offset = 5e9\n").contains("time.lidar_imu_offset")
        );
    }

    #[test]
    fn bad_values_name_the_key_and_the_range() {
        assert_eq!(
            err("preset = \"vlp16\"\n[mapping]\nvoxel_size = -0.4\n"),
            "config: mapping.voxel_size = -0.4 is out of range (0.05..=5.0 m)"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[filter]\nmax_iterations = 0\n"),
            "config: filter.max_iterations = 0 is out of range (1..=20 passes)"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[mapping]\nassociation = \"fulll\"\n"),
            "config: mapping.association = \"fulll\" is not one of: full, plane-only, plain"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[mapping]\nvoxel_size = \"big\"\n"),
            "config: mapping.voxel_size must be a number, found a string"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[extrinsics]\ntranslation = [1.0, 2.0]\n"),
            "config: extrinsics.translation must be an array of 3 numbers, found 2"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[imu]\ngyro_noise = nan\n"),
            "config: imu.gyro_noise = NaN is out of range (1e-6..=1.0 rad/s/sqrt(Hz))"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[sensor]\nblind = 20.0\nmax_range = 10.0\n"),
            "config: sensor.blind = 20.0 must be less than sensor.max_range = 10.0 (m)"
        );
        assert_eq!(
            err("preset = \"os1-64\"\n[sensor]\ncolumns = 1800\n"),
            "config: sensor.columns = 1800 is not an Ouster lidar mode's width (512, 1024 or 2048) for preset os1-64"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[imu]\nsource = \"ouster\"\n"),
            "config: imu.source = \"ouster\" needs an Ouster preset (os1-*), not vlp16"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[imu]\nsource = \"csv\"\n"),
            "config: imu.source = \"csv\" needs imu.csv_path"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[extrinsics]\nrotation_quat_wxyz = [1.0, 1.0, 0.0, 0.0]\n"),
            "config: extrinsics.rotation_quat_wxyz has norm 1.414214; it must be a unit quaternion (w, x, y, z)"
        );
        assert_eq!(
            err(
                "preset = \"vlp16\"\n[extrinsics]\nrotation_quat_wxyz = [1.0, 0.0, 0.0, 0.0]\nrotation_rpy_deg = [0, 0, 0]\n"
            ),
            "config: set extrinsics.rotation_quat_wxyz or extrinsics.rotation_rpy_deg, not both"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[extrinsics]\nfile = \"f.yaml\"\ntranslation = [0.1, 0.0, 0.0]\n"),
            "config: set extrinsics.file or extrinsics.translation (and the rest of the section), not both"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[network]\nbind = \"localhost:80\"\n"),
            "config: network.bind = \"localhost:80\" is not an IP address (e.g. 0.0.0.0)"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[mapping]\nnormals_column_stride = 3\n"),
            "config: mapping.normals_column_stride = 3: it must be 1, 2 or 4"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[sensor]\ncolumns = 1802\n[mapping]\nnormals_column_stride = 4\n"),
            "config: mapping.normals_column_stride = 4 does not divide sensor.columns = 1802"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[mapping]\nnormals_column_stride = 0\n"),
            "config: mapping.normals_column_stride = 0 is out of range (1..=4 columns)"
        );
    }

    #[test]
    fn unknown_keys_and_presets_are_errors() {
        assert_eq!(
            err("preset = \"vlp16\"\n[mapping]\nvoxl_size = 0.4\n"),
            "config: unknown key mapping.voxl_size (keys of [mapping]: voxel_size, scan_voxel_size, map_capacity, max_points, association, knn_search, clear_free_space, normals_column_stride, plane_line_spread)"
        );
        assert_eq!(
            err("preset = \"vlp16\"\n[maping]\nvoxel_size = 0.4\n"),
            "config: unknown key maping (top-level keys: preset, sensor, network, imu, extrinsics, time, mapping, filter, compute)"
        );
        assert_eq!(
            err("preset = \"vlp64\"\n"),
            "config: unknown preset \"vlp64\" (known: vlp16, vlp32c, hdl32e, os1-16, os1-32, os1-64, os1-128)"
        );
        assert_eq!(
            err("[mapping]\nvoxel_size = 0.4\n"),
            "config: missing key preset (one of: vlp16, vlp32c, hdl32e, os1-16, os1-32, os1-64, os1-128)"
        );
        assert_eq!(
            err("preset = \"vlp16\"\nmapping = 3\n"),
            "config: mapping must be a table ([mapping]), found an integer"
        );
        let syntax = err("preset = \"vlp16\"\n[mapping\n");
        assert!(syntax.starts_with("config: line 2, column "), "{syntax}");
        assert!(!syntax.contains('\n'));
    }

    #[test]
    fn programmatic_configs_are_validated_too() {
        let mut cfg = Config::preset(Preset::Hdl32e);
        cfg.mapping.scan_voxel_size = 9.0;
        assert_eq!(
            cfg.validate().unwrap_err().0,
            "config: mapping.scan_voxel_size = 9.0 is out of range (0.05..=5.0 m)"
        );
    }
}
