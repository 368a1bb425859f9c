//! The `loglio` command.
//!
//! Every failure prints one line, `error: ...`, on stderr and exits non-zero (1 for errors, 2
//! for command-line mistakes, 101 for an internal error); non-fatal problems print
//! `warning: ...` lines (see `loglio_host::diag`). A panic hook turns a bug into one line too,
//! whatever `RUST_BACKTRACE` says.

use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand, ValueEnum};
#[cfg(feature = "sim")]
use loglio_host::config::KnnReach;
use loglio_host::config::{AssociationMode, Config, Preset};
use loglio_host::diag::one_line;
use loglio_host::eval::{self, Alignment, DeltaUnit, EvalOptions, Format};
use loglio_host::output;

/// LiDAR-inertial odometry for spinning LiDARs (LOG-LIO).
#[derive(Debug, Parser)]
#[command(name = "loglio", version, about, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// The subcommands. `live`, `replay`, `bag`, `sim`, `demo` and `bench` (they run the odometry)
/// and `normals` (Ring FALS) are added by their modules; `sim`, `demo` and `bench` only with the
/// default feature `sim` (the simulator).
#[derive(Debug, Subcommand)]
enum Command {
    /// Print a sensor preset's commented configuration template, or check a configuration file.
    Config(ConfigArgs),
    /// ATE and RPE of an estimated trajectory against a ground truth (evo-compatible).
    Eval(EvalArgs),
    /// List a ROS bag's topics and what loglio reads from it; with --read, decode it all.
    BagInfo(BagInfoArgs),
    /// Ring FALS normals of a real capture (the bundled Ouster OS-1-32 frame by default): valid
    /// normals, time per scan, agreement with kNN-PCA on planar points.
    Normals(loglio_host::cmd::normals::NormalsArgs),
    /// Run live: LiDAR packets over UDP, the IMU from a serial port or the Ouster's IMU packets;
    /// a status line each second; Ctrl-C stops and writes every output (as replay).
    Live(LiveArgs),
    /// Replay a pcap (Velodyne or Ouster) with the IMU from a CSV file, a serial capture or the
    /// Ouster's IMU packets; writes the trajectory, map, per-scan CSV and plots.
    Replay(ReplayArgs),
    #[cfg(feature = "sim")]
    /// Will this computer keep up? Per-stage times and the real-time margin of a sensor preset on
    /// a simulated drive, with the plain (FAST-LIO2-like) association as the baseline.
    Bench(BenchArgs),
    /// Run the odometry over a ROS bag: ROS 1 (.bag), rosbag2 (directory, .db3) or MCAP, with
    /// PointCloud2 (Velodyne or Ouster driver) or raw Velodyne/Ouster packets, and sensor_msgs/Imu.
    Bag(BagArgs),
    /// Run live on ROS 2 topics over DDS (no ROS installation; the domain from ROS_DOMAIN_ID):
    /// sensor_msgs/PointCloud2 (Velodyne or Ouster driver) and sensor_msgs/Imu, the extrinsic
    /// from /tf_static; the status line, stops and outputs of `live`.
    Ros2(Ros2Args),
    #[cfg(feature = "sim")]
    /// Run a simulated scenario (firmware-sim) end to end and report the ATE against its ground truth.
    Sim(SimArgs),
    #[cfg(feature = "sim")]
    /// The built-in demo: 25 s of a simulated VLP-32C on a car in a town, no files needed; prints
    /// the ATE against ground truth and writes the outputs into ./loglio-demo/.
    Demo(DemoArgs),
}

#[cfg(feature = "sim")]
#[derive(Debug, Args)]
struct SimArgs {
    /// Scenario: vehicle, handheld, corridor, drone, rotation, traffic, long (3.2 km, 262 s).
    #[arg(long, default_value = "vehicle", value_name = "NAME")]
    scenario: String,
    /// Leave the scenario's moving actors out (traffic: the same drive in an empty street).
    #[arg(long)]
    no_actors: bool,
    /// Simulated LiDAR: vlp16, vlp32c, hdl32e, os1-16, os1-64, os1-128.
    #[arg(long, default_value = "vlp32c", value_name = "NAME")]
    sensor: String,
    /// Seed of the world and every noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Length in seconds (default: the scenario's, 30-60 s; long 262 s).
    #[arg(long, value_name = "S")]
    seconds: Option<f64>,
    /// Association mode.
    #[arg(long, value_enum)]
    mode: Option<AssociationMode>,
    /// Measurement budget (`mapping.max_points`): at most N downsampled points measured per
    /// scan; 0 = all [default: the configuration's, 5000]
    #[arg(long, value_name = "N")]
    max_points: Option<u64>,
    /// The association's k-NN (`mapping.knn_search`).
    #[arg(long, value_enum, default_value = "block")]
    knn_search: KnnReach,
    /// Output directory (trajectory, ground truth, map, per-scan CSV, plots); nothing is written
    /// without it.
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Leave the simulated IMU out: LiDAR-only odometry with a constant-velocity model (the
    /// world is the first scan's frame).
    #[arg(long)]
    no_imu: bool,
    /// No zero-velocity and zero-rate updates while the platform stands (`filter.standstill =
    /// false`; they are on by default).
    #[arg(long)]
    no_standstill: bool,
    /// The standstill updates, as by default (kept so that older command lines still run).
    #[arg(long, hide = true, conflicts_with = "no_standstill")]
    standstill: bool,
    /// Keep in the map what the scans see through (`mapping.clear_free_space = false`): the
    /// moving actors' ghost trails stay.
    #[arg(long)]
    keep_free_space: bool,
    /// Keep `--lidar-imu-offset` as it is (`time.estimate_offset = false`): no online estimate
    /// of the IMU-LiDAR time offset.
    #[arg(long)]
    fixed_offset: bool,
    /// The simulated IMU's clock runs this far ahead of the LiDAR's, ms (a sensor-realism
    /// switch: its samples are stamped late).
    #[arg(long, default_value_t = 0.0, value_name = "MS", allow_negative_numbers = true)]
    imu_clock_offset_ms: f64,
    /// Scans per second (a sensor-realism switch): 10 or 20 (a Velodyne 5 to 20; an Ouster
    /// keeps its columns).
    #[arg(long, value_name = "HZ")]
    scan_rate_hz: Option<u32>,
    /// The simulated IMU's gyroscope full scale, deg/s (a sensor-realism switch: 125, 250,
    /// 500, 1000 or 2000; default 500). Faster rotation saturates there.
    #[arg(long, value_name = "DPS")]
    imu_gyro_full_scale: Option<u32>,
    /// The simulated IMU's accelerometer full scale, g (2, 4, 8 or 16; default 4).
    #[arg(long, value_name = "G")]
    imu_acc_full_scale: Option<u32>,
    /// `time.lidar_imu_offset`: seconds added to the IMU stamps (e.g. -0.02 for
    /// --imu-clock-offset-ms 20).
    #[arg(long, default_value_t = 0.0, value_name = "S", allow_negative_numbers = true)]
    lidar_imu_offset: f64,
    /// Pace the run by the simulated time (real time), e.g. to watch it live in Foxglove.
    #[arg(long)]
    realtime: bool,
    /// Speed-up over real time with --realtime.
    #[arg(long, default_value_t = 1.0, requires = "realtime")]
    rate: f64,
    #[command(flatten)]
    outputs: loglio_host::sink::SinkArgs,
}

/// What the commands that run the odometry share.
#[derive(Debug, Args)]
struct RunArgs {
    /// Configuration file (see `loglio config --preset NAME`).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Sensor preset when no configuration file is given: vlp16, vlp32c, hdl32e, os1-16, os1-32,
    /// os1-64, os1-128.
    #[arg(long, value_name = "NAME", conflicts_with = "config")]
    preset: Option<String>,
    /// Association mode (overrides the configuration's).
    #[arg(long, value_enum)]
    mode: Option<AssociationMode>,
    /// Ouster metadata JSON (overrides sensor.ouster_metadata).
    #[arg(long, value_name = "FILE")]
    metadata: Option<PathBuf>,
    /// Velodyne calibration yaml (overrides sensor.calibration).
    #[arg(long, value_name = "FILE")]
    calibration: Option<PathBuf>,
    /// LiDAR-IMU extrinsic from a FAST-LIO / LOG-LIO YAML (`mapping:` `extrinsic_T`,
    /// `extrinsic_R`: the LiDAR's pose in the IMU frame); overrides the configuration's
    /// [extrinsics] and what the data gives (a bag's /tf_static, the Ouster metadata).
    #[arg(long, value_name = "FILE.yaml")]
    extrinsic: Option<PathBuf>,
    /// Output directory (trajectory.tum, scans.csv, map.ply, map.pcd, plots).
    #[arg(long, value_name = "DIR", default_value = "loglio-out")]
    out: PathBuf,
    /// Ground truth (TUM): the ATE and the error plot.
    #[arg(long, value_name = "FILE.tum")]
    gt: Option<PathBuf>,
    /// Do not write the map and the plots.
    #[arg(long)]
    no_map: bool,
    #[command(flatten)]
    outputs: loglio_host::sink::SinkArgs,
}

impl RunArgs {
    fn setup(&self) -> loglio_host::run::setup::RunSetup {
        loglio_host::run::setup::RunSetup {
            config: self.config.clone(),
            preset: self.preset.clone(),
            mode: self.mode,
            metadata: self.metadata.clone(),
            calibration: self.calibration.clone(),
            extrinsic: self.extrinsic.clone(),
            out: Some(self.out.clone()),
            gt: self.gt.clone(),
            no_map: self.no_map,
            sinks: self.outputs.clone(),
        }
    }
}

#[derive(Debug, Args)]
struct ReplayArgs {
    /// The capture (classic libpcap).
    pcap: PathBuf,
    /// IMU file: a CSV `t,gx,gy,gz,ax,ay,az` or a capture of loglio's serial IMU frames
    /// (detected from the contents).
    #[arg(long, value_name = "FILE", conflicts_with = "ouster_imu")]
    imu: Option<PathBuf>,
    /// Take the IMU from the Ouster IMU packets in the pcap.
    #[arg(long)]
    ouster_imu: bool,
    /// Pace the replay by the capture times (real time). A step back in capture time, or one of
    /// more than 1 s ahead (a pause in the capture, a damaged record), is not waited out: the
    /// pacing restarts from that packet.
    #[arg(long)]
    realtime: bool,
    /// Speed-up over real time with --realtime.
    #[arg(long, default_value_t = 1.0, requires = "realtime")]
    rate: f64,
    #[command(flatten)]
    run: RunArgs,
}

/// When a live run stops, and what it watches while it runs (`live`, `ros2`).
#[derive(Debug, Args)]
struct WatchArgs {
    /// Stop after this many seconds (as Ctrl-C does).
    #[arg(long, value_name = "S")]
    seconds: Option<f64>,
    /// Fail when no LiDAR data (packets, clouds) arrives within this many seconds of the start.
    #[arg(long, value_name = "S", default_value_t = 10.0)]
    lidar_timeout: f64,
    /// Warn when no IMU sample arrives for this many seconds.
    #[arg(long, value_name = "S", default_value_t = 3.0)]
    imu_timeout: f64,
    /// No status line.
    #[arg(long)]
    quiet: bool,
}

impl TryFrom<&WatchArgs> for loglio_host::cmd::Watch {
    type Error = anyhow::Error;

    /// The options as the commands take them, the IMU timeout checked (the run checks the rest).
    fn try_from(a: &WatchArgs) -> anyhow::Result<Self> {
        if !(a.imu_timeout > 0.0 && a.imu_timeout.is_finite()) {
            bail!("--imu-timeout must be a positive number of seconds, not {}", a.imu_timeout);
        }
        Ok(loglio_host::cmd::Watch {
            seconds: a.seconds,
            lidar_timeout_s: a.lidar_timeout,
            imu_timeout_s: a.imu_timeout,
            status: !a.quiet,
        })
    }
}

#[derive(Debug, Args)]
struct LiveArgs {
    /// The IMU's serial device: a UART, a USB serial adapter, a pseudo-terminal or a FIFO
    /// (default: the configuration's imu.serial_device).
    #[arg(long, value_name = "PATH", conflicts_with = "ouster_imu")]
    imu_serial: Option<PathBuf>,
    /// What the serial IMU speaks (overrides imu.protocol): loglio's IMU frames, Xsens MTData2
    /// or VectorNav binary output.
    #[arg(long, value_enum, value_name = "PROTOCOL", conflicts_with = "ouster_imu")]
    imu_protocol: Option<loglio_host::config::ImuProtocol>,
    /// Serial baud rate (overrides imu.baud).
    #[arg(long, value_name = "BAUD", value_parser = clap::value_parser!(u32).range(1200..=12_000_000))]
    baud: Option<u32>,
    /// Take the IMU from the Ouster's IMU packets (UDP --imu-port).
    #[arg(long)]
    ouster_imu: bool,
    /// Take the IMU from an autopilot's MAVLink HIGHRES_IMU, SCALED_IMU or RAW_IMU messages
    /// sent to this UDP port (as imu.source = "mavlink" with network.mavlink_imu_port).
    #[arg(long, value_name = "PORT", conflicts_with_all = ["imu_serial", "ouster_imu", "imu_protocol"])]
    imu_mavlink_udp: Option<u16>,
    /// No IMU: LiDAR-only odometry with a constant-velocity model (imu.source = "none"; the
    /// world is the first scan's frame).
    #[arg(long, conflicts_with_all = ["imu_serial", "ouster_imu", "imu_mavlink_udp"])]
    no_imu: bool,
    /// Local IP address to listen on (overrides network.bind, default 0.0.0.0).
    #[arg(long, value_name = "IP")]
    bind: Option<std::net::IpAddr>,
    /// LiDAR data port (default: the Ouster metadata's, else network.lidar_port: 2368
    /// Velodyne, 7502 Ouster).
    #[arg(long, value_name = "PORT")]
    lidar_port: Option<u16>,
    /// Ouster IMU port with --ouster-imu (default: the metadata's, else network.imu_port, 7503).
    #[arg(long, value_name = "PORT")]
    imu_port: Option<u16>,
    /// Velodyne position packet port (the GPS time).
    #[arg(long, value_name = "PORT", default_value_t = 8308)]
    position_port: u16,
    #[command(flatten)]
    watch: WatchArgs,
    #[command(flatten)]
    run: RunArgs,
}

#[cfg(feature = "sim")]
#[derive(Debug, Args)]
struct BenchArgs {
    /// Sensor preset: vlp16, vlp32c, hdl32e, os1-16, os1-64, os1-128.
    #[arg(long, default_value = "vlp32c", value_name = "NAME")]
    preset: String,
    /// Seconds of simulated data (2 s at rest are not timed).
    #[arg(long, default_value_t = 12.0, value_name = "S")]
    seconds: f64,
    /// Measurement budget (`mapping.max_points`): at most N downsampled points measured per
    /// scan, in both modes; 0 = all [default: the configuration's, 5000]
    #[arg(long, value_name = "N")]
    max_points: Option<u64>,
    /// The association's k-NN (`mapping.knn_search`), in both modes.
    #[arg(long, value_enum, default_value = "block")]
    knn_search: KnnReach,
    /// Threads for the association (`compute.threads`), in both modes; 0 = the available
    /// cores (at most 8).
    #[arg(long, default_value_t = 0, value_name = "N")]
    threads: usize,
    /// Simulated scenario: vehicle, handheld, corridor, drone, rotation, traffic, long (default: vehicle for
    /// Velodyne presets, handheld for Ouster).
    #[arg(long, value_name = "NAME")]
    scenario: Option<String>,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Args)]
struct BagArgs {
    /// The bag: a ROS 1 bag, a rosbag2 directory, a .db3 or an .mcap file.
    bag: PathBuf,
    /// The LiDAR topic (found by message type if not given).
    #[arg(long, value_name = "TOPIC")]
    lidar_topic: Option<String>,
    /// The IMU topic (found by message type if not given).
    #[arg(long, value_name = "TOPIC")]
    imu_topic: Option<String>,
    /// Pace the run by the bag's record times (real time), e.g. to feed a robot stack or
    /// watch it in Foxglove.
    #[arg(long)]
    realtime: bool,
    /// Speed-up over real time with --realtime.
    #[arg(long, default_value_t = 1.0, requires = "realtime")]
    rate: f64,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Debug, Args)]
struct Ros2Args {
    /// The sensor_msgs/PointCloud2 topic (e.g. /velodyne_points, /ouster/points).
    #[arg(long, value_name = "TOPIC")]
    lidar_topic: String,
    /// The sensor_msgs/Imu topic.
    #[arg(long, value_name = "TOPIC", default_value = "/imu/data", conflicts_with = "no_imu")]
    imu_topic: String,
    /// No IMU: LiDAR-only odometry with a constant-velocity model.
    #[arg(long)]
    no_imu: bool,
    /// Best-effort readers, for publishers with the sensor-data QoS (e.g. ouster-ros's
    /// default); reliable readers (the default) do not match them.
    #[arg(long)]
    best_effort: bool,
    #[command(flatten)]
    watch: WatchArgs,
    #[command(flatten)]
    run: RunArgs,
}

#[cfg(feature = "sim")]
#[derive(Debug, Args)]
struct DemoArgs {
    /// Output directory.
    #[arg(long, default_value = "loglio-demo", value_name = "DIR")]
    out: PathBuf,
    /// Length in seconds.
    #[arg(long, default_value_t = 25.0, value_name = "S")]
    seconds: f64,
    /// Pace the run by the simulated time (real time), e.g. to watch it live in Foxglove.
    #[arg(long)]
    realtime: bool,
    /// Speed-up over real time with --realtime.
    #[arg(long, default_value_t = 1.0, requires = "realtime")]
    rate: f64,
    #[command(flatten)]
    outputs: loglio_host::sink::SinkArgs,
}

#[derive(Debug, Args)]
#[command(group = clap::ArgGroup::new("what").required(true).args(["preset", "check", "list", "reference"]))]
struct ConfigArgs {
    /// Print the commented template of this preset (vlp16, vlp32c, hdl32e, os1-16, os1-32,
    /// os1-64, os1-128); it parses back to the preset's values.
    #[arg(long, value_name = "NAME")]
    preset: Option<String>,
    /// Validate a configuration file and print the resolved configuration.
    #[arg(long, value_name = "FILE")]
    check: Option<PathBuf>,
    /// List the presets.
    #[arg(long)]
    list: bool,
    /// Print the reference of every key: range, unit, default per preset and meaning (Markdown,
    /// as docs/configuration.md).
    #[arg(long)]
    reference: bool,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum FormatArg {
    /// `t tx ty tz qx qy qz qw` per line.
    Tum,
    /// 12 numbers per line (row-major 3x4 [R|t]); stamps from --gt-times/--est-times.
    Kitti,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum AlignArg {
    /// No alignment.
    None,
    /// Rotation and translation (evo -a).
    Se3,
    /// Rotation, translation and scale (evo -as).
    Sim3,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum UnitArg {
    /// Poses.
    Frames,
    /// Metres of path length.
    M,
}

#[derive(Debug, Args)]
struct EvalArgs {
    /// Ground-truth trajectory.
    gt: PathBuf,
    /// Estimated trajectory (e.g. loglio's trajectory.tum).
    est: PathBuf,
    /// File format of both trajectories.
    #[arg(long, value_enum, default_value = "tum")]
    format: FormatArg,
    /// KITTI times file of the ground truth (one stamp in seconds per line).
    #[arg(long, value_name = "FILE")]
    gt_times: Option<PathBuf>,
    /// KITTI times file of the estimate.
    #[arg(long, value_name = "FILE")]
    est_times: Option<PathBuf>,
    /// Alignment of the estimate onto the ground truth before computing errors.
    #[arg(long, value_enum, default_value = "se3")]
    align: AlignArg,
    /// Largest stamp difference of an associated pose pair, seconds (evo --t_max_diff).
    #[arg(long, default_value_t = 0.01, value_name = "S")]
    t_max_diff: f64,
    /// Added to the estimate's stamps before association, seconds (evo --t_offset).
    #[arg(long, default_value_t = 0.0, value_name = "S", allow_negative_numbers = true)]
    t_offset: f64,
    /// RPE delta between the poses of a pair.
    #[arg(long, default_value_t = 1.0)]
    delta: f64,
    /// Unit of --delta.
    #[arg(long, value_enum, default_value = "frames")]
    delta_unit: UnitArg,
    /// RPE over every pair at the delta, not only consecutive ones (evo --all_pairs).
    #[arg(long)]
    all_pairs: bool,
    /// Choose the RPE pairs on the ground truth instead of the estimate (evo --pairs_from_reference).
    #[arg(long)]
    pairs_from_gt: bool,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
    /// Write plots PREFIX_trajectory.{png,svg} and PREFIX_ape.{png,svg}.
    #[arg(long, value_name = "PREFIX")]
    plot: Option<PathBuf>,
}

#[derive(Debug, Args)]
struct BagInfoArgs {
    /// A ROS 1 bag, a rosbag2 directory, a .db3 or an .mcap file.
    bag: PathBuf,
    /// Sensor preset (decides how clouds' rings map to rows).
    #[arg(long, default_value = "vlp16", value_name = "NAME")]
    preset: String,
    /// Configuration file (instead of --preset).
    #[arg(long, value_name = "FILE", conflicts_with = "preset")]
    config: Option<PathBuf>,
    /// The LiDAR topic (found by message type if not given).
    #[arg(long, value_name = "TOPIC")]
    lidar_topic: Option<String>,
    /// The IMU topic (found by message type if not given).
    #[arg(long, value_name = "TOPIC")]
    imu_topic: Option<String>,
    /// Decode every message of the chosen topics and print what came out.
    #[arg(long)]
    read: bool,
}

fn main() -> ExitCode {
    std::panic::set_hook(Box::new(|info| {
        let payload = info.payload();
        let msg = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown panic".into());
        let at = info.location().map(|l| format!(" at {}:{}", l.file(), l.line())).unwrap_or_default();
        eprintln!("error: internal error: {}{at} (a bug in loglio; please report it)", one_line(&msg));
    }));
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => return usage_error(e),
    };
    match std::panic::catch_unwind(|| run(cli)) {
        Ok(Ok(())) => ExitCode::SUCCESS,
        Ok(Err(e)) => {
            // A closed pipe (`loglio config --preset vlp16 | head`) is not a failure.
            if e.chain().any(|c| {
                c.downcast_ref::<io::Error>().is_some_and(|io| io.kind() == io::ErrorKind::BrokenPipe)
            }) {
                return ExitCode::SUCCESS;
            }
            eprintln!("error: {}", one_line(&format!("{e:#}")));
            ExitCode::FAILURE
        }
        Err(_) => ExitCode::from(101),
    }
}

/// Clap's own messages span several lines; keep help and version as they are and shorten the
/// rest to their first line.
fn usage_error(e: clap::Error) -> ExitCode {
    use clap::error::ErrorKind;
    match e.kind() {
        ErrorKind::DisplayHelp | ErrorKind::DisplayVersion => {
            let _ = e.print();
            ExitCode::SUCCESS
        }
        ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand | ErrorKind::MissingSubcommand => {
            eprintln!("error: no subcommand given; see 'loglio --help'");
            ExitCode::from(2)
        }
        _ => {
            let text = e.render().to_string();
            let first = text.lines().find(|l| !l.trim().is_empty()).unwrap_or("error: invalid command line");
            let first = first.strip_prefix("error: ").unwrap_or(first);
            eprintln!("error: {}; see 'loglio --help'", one_line(first));
            ExitCode::from(2)
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    // Exercises the panic hook in the CLI tests (a bug must still print one line).
    if std::env::var_os("LOGLIO_TEST_INTERNAL_PANIC").is_some() {
        panic!("deliberate panic for the tests\nwith a second line");
    }
    match cli.command {
        Command::Config(a) => config_cmd(a),
        Command::Eval(a) => eval_cmd(a),
        Command::BagInfo(a) => bag_info_cmd(a),
        Command::Normals(a) => loglio_host::cmd::normals::run(&a),
        Command::Live(a) => live_cmd(a),
        Command::Replay(a) => replay_cmd(a),
        Command::Bag(a) => bag_cmd(a),
        Command::Ros2(a) => ros2_cmd(a),
        #[cfg(feature = "sim")]
        Command::Sim(a) => sim_cmd(a),
        #[cfg(feature = "sim")]
        Command::Bench(a) => bench_cmd(a),
        #[cfg(feature = "sim")]
        Command::Demo(a) => demo_cmd(a),
    }
}

fn replay_cmd(a: ReplayArgs) -> anyhow::Result<()> {
    use loglio_host::cmd::replay::{ImuInput, ReplayOptions};
    check_rate(a.rate)?;
    let imu = match (&a.imu, a.ouster_imu) {
        (Some(p), _) => Some(ImuInput::detect(p)?),
        (None, true) => Some(ImuInput::OusterPackets),
        (None, false) => None,
    };
    let opt = ReplayOptions {
        pcap: a.pcap,
        imu,
        realtime: a.realtime.then_some(a.rate),
        setup: a.run.setup(),
        progress: true,
    };
    let r = loglio_host::cmd::replay::run(&opt)?;
    print(&format!(
        "{}{}: {} LiDAR packets{}\n{}",
        r.extrinsic.as_ref().map_or(String::new(), |e| format!("{e}\n")),
        opt.pcap.display(),
        r.stream.lidar_packets,
        if r.stream.imu_packets > 0 {
            let unused = if r.imu_packets_used { "" } else { " (not used: the IMU comes from a file)" };
            format!(", {} IMU packets{unused}", r.stream.imu_packets)
        } else {
            String::new()
        },
        loglio_host::run::runner::summary(&r.stats, &r.finished, r.scan_period_s, r.wall_s)
    ))
}

fn live_cmd(a: LiveArgs) -> anyhow::Result<()> {
    use loglio_host::cmd::Watch;
    use loglio_host::cmd::live::{LiveImu, LiveOptions};
    let watch = Watch::try_from(&a.watch)?;
    let mut opt = LiveOptions::new(a.run.setup());
    opt.imu = match (a.imu_serial, a.ouster_imu, a.imu_mavlink_udp, a.no_imu) {
        (_, _, _, true) => LiveImu::None,
        (Some(p), _, _, _) => LiveImu::Serial(p),
        (None, true, _, _) => LiveImu::OusterPackets,
        (None, false, Some(port), _) => LiveImu::Mavlink(port),
        (None, false, None, _) => LiveImu::Config,
    };
    opt.baud = a.baud;
    opt.imu_protocol = a.imu_protocol;
    opt.bind = a.bind;
    opt.lidar_port = a.lidar_port;
    opt.imu_port = a.imu_port;
    opt.position_port = a.position_port;
    opt.watch = watch;
    let r = loglio_host::cmd::live::run(&opt)?;
    print(&loglio_host::cmd::live::summary(&r))
}

#[cfg(feature = "sim")]
fn bench_cmd(a: BenchArgs) -> anyhow::Result<()> {
    let preset: Preset = a.preset.parse().map_err(|e: loglio_host::config::ConfigError| {
        anyhow::anyhow!("{}", e.0.trim_start_matches("config: "))
    })?;
    if !(a.seconds >= 3.0 && a.seconds <= 120.0) {
        bail!("--seconds must be in [3, 120], not {}", a.seconds);
    }
    let scenario = a.scenario.as_deref().map(scenario_kind).transpose()?;
    let r = loglio_host::cmd::bench::run(
        preset,
        scenario,
        a.seconds,
        a.max_points,
        a.knn_search,
        a.threads,
        !a.json,
    )?;
    print(&if a.json { r.to_json() } else { r.to_text() })
}

fn bag_cmd(a: BagArgs) -> anyhow::Result<()> {
    check_rate(a.rate)?;
    let opt = loglio_host::cmd::bag::BagRunOptions {
        bag: a.bag,
        lidar_topic: a.lidar_topic,
        imu_topic: a.imu_topic,
        setup: a.run.setup(),
        progress: !a.realtime,
        realtime: a.realtime.then_some(a.rate),
    };
    let r = loglio_host::cmd::bag::run(&opt)?;
    print(&format!(
        "{}: {}\n{}{}\n{}",
        opt.bag.display(),
        r.topics,
        r.extrinsic.as_ref().map_or(String::new(), |e| format!("{e}\n")),
        r.bag_stats,
        loglio_host::run::runner::summary(&r.stats, &r.finished, r.scan_period_s, r.wall_s)
    ))
}

fn ros2_cmd(a: Ros2Args) -> anyhow::Result<()> {
    use loglio_host::cmd::Watch;
    use loglio_host::cmd::ros2::{Ros2RunOptions, run, summary};
    let watch = Watch::try_from(&a.watch)?;
    let mut opt = Ros2RunOptions::new(a.run.setup(), &a.lidar_topic);
    opt.imu_topic = (!a.no_imu).then_some(a.imu_topic);
    opt.best_effort = a.best_effort;
    opt.watch = watch;
    print(&summary(&run(&opt)?))
}

#[cfg(feature = "sim")]
fn sim_run(opt: loglio_host::cmd::sim::SimOptions) -> anyhow::Result<()> {
    let report = loglio_host::cmd::sim::run(&opt)?;
    print(&loglio_host::cmd::sim::summary(&opt, &report))
}

#[cfg(feature = "sim")]
/// A simulator scenario by name, or an error that lists the known ones.
fn scenario_kind(name: &str) -> anyhow::Result<loglio_firmware_sim::scenario::ScenarioKind> {
    use loglio_firmware_sim::scenario::ScenarioKind;
    ScenarioKind::from_name(name).ok_or_else(|| {
        let known: Vec<&str> = ScenarioKind::ALL.iter().map(|k| k.name()).collect();
        anyhow::anyhow!("unknown scenario \"{name}\" (known: {})", known.join(", "))
    })
}

#[cfg(feature = "sim")]
fn sim_cmd(a: SimArgs) -> anyhow::Result<()> {
    check_rate(a.rate)?;
    use loglio_firmware_sim::lidar::SensorModel;
    let kind = scenario_kind(&a.scenario)?;
    let sensor =
        SensorModel::ALL.into_iter().find(|m| m.name().eq_ignore_ascii_case(&a.sensor)).ok_or_else(|| {
            let known: Vec<&str> = SensorModel::ALL.iter().map(|m| m.name()).collect();
            anyhow::anyhow!("unknown simulated sensor \"{}\" (known: {})", a.sensor, known.join(", "))
        })?;
    if let Some(s) = a.seconds
        && !(s > 0.0 && s <= 600.0)
    {
        bail!("--seconds must be in (0, 600], not {s}");
    }
    if a.imu_clock_offset_ms.is_nan() || a.imu_clock_offset_ms.abs() > 1000.0 {
        bail!("--imu-clock-offset-ms must be within ±1000 ms, not {}", a.imu_clock_offset_ms);
    }
    if a.lidar_imu_offset.is_nan() || a.lidar_imu_offset.abs() > 4e9 {
        bail!("--lidar-imu-offset must be within ±4e9 s, not {}", a.lidar_imu_offset);
    }
    sim_run(loglio_host::cmd::sim::SimOptions {
        kind,
        sensor,
        seed: a.seed,
        duration_s: a.seconds,
        mode: a.mode,
        max_points: a.max_points,
        knn_search: a.knn_search,
        out: a.out,
        no_actors: a.no_actors,
        progress: !a.realtime,
        realtime: a.realtime.then_some(a.rate),
        sinks: a.outputs,
        no_imu: a.no_imu,
        // `--standstill` (hidden) conflicts with `--no-standstill`: the default either way.
        standstill: !a.no_standstill,
        keep_free_space: a.keep_free_space,
        fixed_offset: a.fixed_offset,
        imu_clock_offset_ns: (a.imu_clock_offset_ms * 1e6).round() as i64,
        realism: loglio_host::cmd::sim::Realism {
            scan_rate_hz: a.scan_rate_hz,
            gyro_full_scale_dps: a.imu_gyro_full_scale,
            acc_full_scale_g: a.imu_acc_full_scale,
        },
        lidar_imu_offset_s: a.lidar_imu_offset,
    })
}

#[cfg(feature = "sim")]
fn demo_cmd(a: DemoArgs) -> anyhow::Result<()> {
    check_rate(a.rate)?;
    use loglio_firmware_sim::lidar::SensorModel;
    use loglio_firmware_sim::scenario::ScenarioKind;
    if !(a.seconds > 2.5 && a.seconds <= 600.0) {
        bail!("--seconds must be in (2.5, 600] (the scenario starts with 2 s at rest), not {}", a.seconds);
    }
    print(&format!(
        "loglio demo: {} s of a simulated Velodyne VLP-32C on a car driving through a town (firmware-sim, seed 1)",
        a.seconds
    ))?;
    sim_run(loglio_host::cmd::sim::SimOptions {
        kind: ScenarioKind::Vehicle,
        sensor: SensorModel::Vlp32c,
        seed: 1,
        duration_s: Some(a.seconds),
        mode: None,
        max_points: None,
        knn_search: KnnReach::default(),
        out: Some(a.out),
        no_actors: false,
        progress: !a.realtime,
        realtime: a.realtime.then_some(a.rate),
        sinks: a.outputs,
        no_imu: false,
        standstill: loglio_core::standstill::StandstillConfig::DEFAULT.enabled,
        keep_free_space: false,
        fixed_offset: false,
        imu_clock_offset_ns: 0,
        realism: Default::default(),
        lidar_imu_offset_s: 0.0,
    })
}

/// `--rate` of `--realtime`: a positive number.
fn check_rate(rate: f64) -> anyhow::Result<()> {
    if !(rate > 0.0 && rate.is_finite()) {
        bail!("--rate must be a positive number, not {rate}");
    }
    Ok(())
}

fn print(text: &str) -> anyhow::Result<()> {
    let mut out = io::stdout().lock();
    out.write_all(text.as_bytes())?;
    if !text.ends_with('\n') {
        out.write_all(b"\n")?;
    }
    out.flush()?;
    Ok(())
}

fn config_cmd(a: ConfigArgs) -> anyhow::Result<()> {
    if a.list {
        let mut s = String::new();
        for p in Preset::ALL {
            s.push_str(&format!("{:<8} {}\n", p.name(), p.description()));
        }
        return print(&s);
    }
    if a.reference {
        return print(&loglio_host::config::reference_markdown());
    }
    if let Some(name) = a.preset {
        let preset: Preset = name.parse().map_err(|e: loglio_host::config::ConfigError| {
            anyhow::anyhow!("{}", e.0.trim_start_matches("config: "))
        })?;
        return print(&loglio_host::config::template(preset));
    }
    if let Some(path) = a.check {
        let cfg = Config::load(&path)?;
        // extrinsics.file is read and checked too: a robot's first run should not find it bad.
        let extrinsic = match &cfg.extrinsics.file {
            Some(f) => {
                let e = loglio_host::input::extrinsic_file::load(f)?;
                let [x, y, z] = e.translation;
                let [w, i, j, k] = e.quat_wxyz;
                format!(
                    "; extrinsic from {}: t = [{x:.4}, {y:.4}, {z:.4}] m, q wxyz = [{w:.4}, {i:.4}, {j:.4}, {k:.4}]",
                    f.display()
                )
            }
            None => String::new(),
        };
        print(&cfg.to_commented_toml())?;
        eprintln!("{}: valid (preset {}{extrinsic})", path.display(), cfg.preset);
        return Ok(());
    }
    bail!("give --preset NAME, --check FILE, --list or --reference")
}

fn eval_cmd(a: EvalArgs) -> anyhow::Result<()> {
    let format = match a.format {
        FormatArg::Tum => Format::Tum,
        FormatArg::Kitti => Format::Kitti,
    };
    if !(a.t_max_diff >= 0.0 && a.t_max_diff.is_finite()) {
        bail!("--t-max-diff must be a non-negative number of seconds, not {}", a.t_max_diff);
    }
    let gt = eval::read_trajectory(&a.gt, format, a.gt_times.as_deref())?;
    let est = eval::read_trajectory(&a.est, format, a.est_times.as_deref())?;
    let opt = EvalOptions {
        align: match a.align {
            AlignArg::None => Alignment::None,
            AlignArg::Se3 => Alignment::Se3,
            AlignArg::Sim3 => Alignment::Sim3,
        },
        max_diff: a.t_max_diff,
        offset: a.t_offset,
        rpe_delta: a.delta,
        rpe_unit: match a.delta_unit {
            UnitArg::Frames => DeltaUnit::Frames,
            UnitArg::M => DeltaUnit::Metres,
        },
        all_pairs: a.all_pairs,
        pairs_from_gt: a.pairs_from_gt,
    };
    let report = eval::evaluate(&gt, &est, &opt)?;
    if let Some(prefix) = &a.plot {
        write_eval_plots(prefix, &report)?;
    }
    print(&if a.json { report.to_json() } else { report.to_string() })
}

fn bag_info_cmd(a: BagInfoArgs) -> anyhow::Result<()> {
    use loglio_host::input::bag::{BagEvent, BagOptions, BagReader, TopicKind};
    let cfg = match &a.config {
        Some(path) => Config::load(path)?,
        None => {
            let p: Preset = a.preset.parse().map_err(|e: loglio_host::config::ConfigError| {
                anyhow::anyhow!("{}", e.0.trim_start_matches("config: "))
            })?;
            Config::preset(p)
        }
    };
    let mut opt = BagOptions::from_config(&cfg)?;
    opt.lidar_topic = a.lidar_topic;
    opt.imu_topic = a.imu_topic;
    opt.require_imu = false;
    let mut bag = BagReader::open(&a.bag, opt)?;
    let mut s = format!("{}: {}, {} topics\n", a.bag.display(), bag.format(), bag.topics().len());
    for t in bag.topics() {
        let n = t.count.map_or("?".to_string(), |n| n.to_string());
        s.push_str(&format!("  {:<40} {:<36} {:>8}\n", t.name, t.msg_type, n));
    }
    let sel = bag.selection().clone();
    let kind = match sel.lidar.1 {
        TopicKind::PointCloud2 => "point clouds",
        TopicKind::VelodyneScan => "Velodyne packets",
        TopicKind::OusterPacket => "Ouster packets",
        _ => "?",
    };
    s.push_str(&format!(
        "reads: LiDAR {} ({kind}), IMU {}",
        sel.lidar.0,
        sel.imu.as_deref().unwrap_or("none")
    ));
    if let Some(m) = &sel.metadata {
        s.push_str(&format!(", metadata {m}"));
    }
    print(&s)?;
    if !a.read {
        return Ok(());
    }
    let progress = output::Progress::new(bag.total_messages().unwrap_or(0), "messages", false);
    let span = |v: &Option<(u64, u64)>| match v {
        Some((a, b)) => format!("{} .. {} s", output::format_stamp_ns(*a), output::format_stamp_ns(*b)),
        None => "-".to_string(),
    };
    let (mut scans, mut imu, mut packets) = (None::<(u64, u64)>, None::<(u64, u64)>, None::<(u64, u64)>);
    let (mut points, mut n_scans) = (0u64, 0u64);
    let widen =
        |r: &mut Option<(u64, u64)>, t: u64| *r = Some(r.map_or((t, t), |(a, b)| (a.min(t), b.max(t))));
    let mut result = Ok(());
    while let Some(item) = bag.next() {
        let item = match item {
            Ok(i) => i,
            Err(e) => {
                result = Err(e);
                break;
            }
        };
        progress.set_position(bag.stats().messages);
        match item.event {
            BagEvent::Scan(sc) => {
                widen(&mut scans, sc.stamp_ns);
                points += sc.points.len() as u64;
                n_scans += 1;
            }
            BagEvent::Imu(i) => widen(&mut imu, i.t_ns),
            BagEvent::LidarPacket(p) => widen(&mut packets, p.stamp_ns),
            BagEvent::OusterMetadata(_) => {}
        }
    }
    progress.finish();
    result?;
    let mut s = format!("{}\n", bag.stats());
    if n_scans > 0 {
        s.push_str(&format!(
            "scans: {}, {:.0} points each on average\n",
            span(&scans),
            points as f64 / n_scans as f64
        ));
    }
    s.push_str(&format!("IMU samples: {}\npackets: {}", span(&imu), span(&packets)));
    print(&s)
}

fn with_suffix(prefix: &Path, suffix: &str) -> PathBuf {
    let mut s = prefix.as_os_str().to_owned();
    s.push(suffix);
    PathBuf::from(s)
}

fn write_eval_plots(prefix: &Path, r: &eval::EvalReport) -> anyhow::Result<()> {
    let align = match r.options.align {
        Alignment::None => "not aligned",
        Alignment::Se3 => "SE(3)-aligned",
        Alignment::Sim3 => "Sim(3)-aligned",
    };
    for ext in ["png", "svg"] {
        let p = with_suffix(prefix, &format!("_trajectory.{ext}"));
        let title = format!("Trajectory, top view ({align})");
        output::plot_trajectory_top_view(&p, &title, "estimate", &r.est_positions, Some(&r.gt_positions))
            .with_context(|| "writing the trajectory plot")?;
        let p = with_suffix(prefix, &format!("_ape.{ext}"));
        let title = format!("APE translation ({align}), rmse {:.3} m", r.ape_trans.rmse);
        let x_desc = if r.has_stamps { "time since start [s]" } else { "pose index" };
        output::plot_error_over_time(&p, &title, x_desc, "error [m]", &r.ape_series)
            .with_context(|| "writing the error plot")?;
    }
    Ok(())
}
