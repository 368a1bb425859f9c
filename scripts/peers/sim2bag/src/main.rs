//! `sim2bag`: writes loglio's simulated scenarios as ROS 1 bags for other odometries.
//!
//! For each scenario, into `OUT/<scenario>/`:
//!
//! | file | content |
//! |---|---|
//! | `<scenario>.bag` | `/points` (`sensor_msgs/PointCloud2`, frame `velodyne`) and `/imu` (`sensor_msgs/Imu`, frame `imu_link`) |
//! | `groundtruth.tum` | exact pose of the IMU frame (T_world_imu) at every IMU sample and at every scan's start, middle and end |
//! | `lidar_groundtruth.tum` | exact pose of the LiDAR frame (T_world_lidar) at the same times |
//! | `scans.csv` | `index,start_ns,end_ns,points` per scan |
//! | `scenario.json` | what `loglio-sim file` writes (extrinsic, IMU noise figures, ...) plus a `bag` section (topics, frames, fields, conventions) |
//!
//! The clouds are what a Velodyne driver publishes (velodyne_pointcloud's layout): one
//! unorganised row (`height` 1) of the returned points in firing order, fields `x y z
//! intensity` (f32), `ring` (u16, 0 = lowest beam) and `time` (f32, seconds since the header
//! stamp), 32 bytes per point. The header stamp is the scan's first firing; the bag's record
//! time is its last firing (when a driver could publish it). Points are in the LiDAR frame at
//! their own firing time (motion distortion as on a real sensor).
//!
//! ```text
//! sim2bag --out /work/peers-data/bags                       # the five standard scenarios, VLP-32C, seed 1
//! sim2bag --out DIR --scenario vehicle --seed 7 --duration 30
//! ```

use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Event, Scenario, ScenarioConfig, ScenarioKind};
use loglio_firmware_sim::{files, tum};
use loglio_host::input::bag::msg::{self, Imu};
use loglio_host::input::bag::ros1_writer::Ros1BagWriter;
use serde_json::json;

/// Writes simulated scenarios as ROS 1 bags (PointCloud2 + Imu) with exact ground truth.
#[derive(Debug, Parser)]
#[command(name = "sim2bag", about)]
struct Cli {
    /// Output directory (one folder per scenario is created in it).
    #[arg(long)]
    out: PathBuf,
    /// Scenarios (vehicle, handheld, corridor, drone, rotation, traffic, long); default: the five
    /// static 30-40 s ones (not traffic, not long).
    #[arg(long)]
    scenario: Vec<String>,
    /// LiDAR model: vlp16, vlp32c or hdl32e (Velodyne layout clouds).
    #[arg(long, default_value = "vlp32c")]
    sensor: String,
    /// Seed of the world and of every noise (loglio-sim's default: 1).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Seconds to simulate (default: the scenario's: 30-40 s, traffic 60 s, long 262 s).
    #[arg(long)]
    duration: Option<f64>,
    /// Threads for scan generation (the output does not depend on it).
    #[arg(long, default_value_t = 2)]
    threads: usize,
}

const LIDAR_TOPIC: &str = "/points";
const IMU_TOPIC: &str = "/imu";
const LIDAR_FRAME: &str = "velodyne";
const IMU_FRAME: &str = "imu_link";

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let sensor = SensorModel::from_name(&cli.sensor).with_context(|| format!("unknown sensor {:?}", cli.sensor))?;
    anyhow::ensure!(sensor.is_velodyne(), "only Velodyne models are exported (Velodyne cloud layout)");
    let kinds: Vec<ScenarioKind> = if cli.scenario.is_empty() {
        ScenarioKind::ALL
            .into_iter()
            .filter(|k| !matches!(k, ScenarioKind::Traffic | ScenarioKind::Long))
            .collect()
    } else {
        cli.scenario
            .iter()
            .map(|s| ScenarioKind::from_name(s).with_context(|| format!("unknown scenario {s:?}")))
            .collect::<anyhow::Result<_>>()?
    };
    for kind in kinds {
        let mut cfg = ScenarioConfig::new(kind, sensor, cli.seed);
        if let Some(d) = cli.duration {
            cfg.duration_s = d;
        }
        cfg.threads = cli.threads.max(1);
        let sc = Scenario::from_config(cfg).map_err(|e| anyhow::anyhow!("{e}"))?;
        let dir = cli.out.join(kind.name());
        let t = Instant::now();
        let (scans, imu) = export(&sc, &dir)?;
        println!(
            "{}: {scans} scans, {imu} IMU samples -> {} ({:.1} s)",
            kind.name(),
            dir.display(),
            t.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

/// Writes one scenario; returns (scans, IMU samples).
fn export(sc: &Scenario, dir: &Path) -> anyhow::Result<(u64, u64)> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let name = sc.config().kind.name();
    let bag_path = dir.join(format!("{name}.bag"));
    let mut bag = Ros1BagWriter::create(&bag_path)?;
    let c_imu = bag.add_typed_connection(IMU_TOPIC, &msg::IMU)?;
    let c_pts = bag.add_typed_connection(LIDAR_TOPIC, &msg::POINTCLOUD2)?;
    let rows = sc.layout().rows();
    let mut gt_times = BTreeSet::new();
    let mut scans_csv = String::from("index,start_ns,end_ns,points\n");
    let (mut n_scans, mut n_imu, mut max_t) = (0u64, 0u64, 0f32);
    for ev in sc.events() {
        match ev {
            Event::Imu(s) => {
                let m = Imu {
                    stamp_ns: s.t_ns,
                    orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
                    angular_velocity: s.gyro.map(f64::from),
                    linear_acceleration: s.acc.map(f64::from),
                };
                bag.write_imu(c_imu, s.t_ns, &m, IMU_FRAME)?;
                gt_times.insert(s.t_ns);
                n_imu += 1;
            }
            Event::Scan(scan) => {
                let pts = &scan.points;
                let cloud = msg::PointCloud2 {
                    is_dense: true,
                    ..loglio_host::input::bag::cloud::build::cloud(
                        scan.start_ns,
                        LIDAR_FRAME,
                        loglio_host::input::bag::cloud::build::VELODYNE,
                        1,
                        pts.len() as u32,
                        Some(32),
                        false,
                        |i, field| {
                            let p = &pts[i];
                            match field {
                                "x" => f64::from(p.xyz[0]),
                                "y" => f64::from(p.xyz[1]),
                                "z" => f64::from(p.xyz[2]),
                                "intensity" => f64::from(p.intensity),
                                // Velodyne drivers number rings from the lowest beam up; the
                                // sim's rows count from the highest.
                                "ring" => (rows - 1).saturating_sub(usize::from(p.row)) as f64,
                                _ => f64::from(p.t),
                            }
                        },
                    )
                };
                max_t = pts.iter().fold(max_t, |m, p| m.max(p.t));
                bag.write_point_cloud2(c_pts, scan.end_ns, &cloud)?;
                let _ = writeln!(scans_csv, "{},{},{},{}", scan.index, scan.start_ns, scan.end_ns, pts.len());
                gt_times.extend([scan.start_ns, scan.start_ns + (scan.end_ns - scan.start_ns) / 2, scan.end_ns]);
                n_scans += 1;
            }
        }
    }
    bag.finish()?;
    std::fs::write(dir.join("scans.csv"), scans_csv)?;
    std::fs::write(dir.join("groundtruth.tum"), tum::trajectory(gt_times.iter().copied(), |t| sc.pose_at(t)))?;
    std::fs::write(
        dir.join("lidar_groundtruth.tum"),
        tum::trajectory(gt_times.iter().copied(), |t| sc.lidar_pose_at(t)),
    )?;
    let mut info = files::scenario_json(sc);
    info["bag"] = json!({
        "file": bag_path.file_name().map(|f| f.to_string_lossy().into_owned()),
        "lidar_topic": LIDAR_TOPIC,
        "imu_topic": IMU_TOPIC,
        "lidar_frame": LIDAR_FRAME,
        "imu_frame": IMU_FRAME,
        "scans": n_scans,
        "imu_samples": n_imu,
        "rows": rows,
        "columns": sc.layout().cols(),
        "max_point_time_s": max_t,
        "point_fields": "x y z intensity (float32), ring (uint16, 0 = lowest beam), time (float32, s since the header stamp); point_step 32",
        "stamps": "cloud header stamp = first firing of the scan; bag record time = last firing; IMU header stamp = sample time",
        "imu_orientation": "not provided (orientation_covariance[0] = -1)",
        "groundtruth": "groundtruth.tum: T_world_imu at every IMU sample and every scan's start, middle and end; lidar_groundtruth.tum: T_world_lidar at the same times",
    });
    std::fs::write(dir.join("scenario.json"), serde_json::to_string_pretty(&info)?)?;
    Ok((n_scans, n_imu))
}
