//! `loglio sim` and `loglio demo`: a firmware-sim scenario run end to end in this process
//! (scenario → scans and IMU samples in the core's types → odometry → outputs), evaluated
//! against the scenario's exact ground truth (the IMU frame at each scan end).

use std::path::PathBuf;
use std::time::Instant;

use loglio_firmware_sim::imu_chip::{AccelFs, GyroFs};
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Event, Scenario, ScenarioConfig, ScenarioKind};
use nalgebra::Isometry3;

use crate::config::{AssociationMode, Config, ImuSource, KnnReach, Preset};
use crate::error::PipelineError;
use crate::eval::{self, Trajectory};
use crate::output::Progress;
use crate::run::engine::StorageClass;
use crate::run::runner::{self, OwnedScan, RunStats, Runner};
use crate::run::{self, RunOptions};
use crate::sink::files::{self, EstPose, Finished, OutputOptions};

/// The moving actors' ground truth beside the ego's (`loglio sim --out`, traffic scenario).
pub const ACTORS_CSV: &str = "actors.csv";

/// What to simulate and where to write.
#[derive(Clone, Debug)]
pub struct SimOptions {
    /// The scenario.
    pub kind: ScenarioKind,
    /// The simulated LiDAR.
    pub sensor: SensorModel,
    /// Seed of the world and every noise.
    pub seed: u64,
    /// Length, seconds (`None`: the scenario's default).
    pub duration_s: Option<f64>,
    /// Association mode (`None`: the preset's).
    pub mode: Option<AssociationMode>,
    /// Measurement budget (`mapping.max_points`; 0: every downsampled point; `None`: the
    /// configuration's).
    pub max_points: Option<u64>,
    /// The association's k-NN (`mapping.knn_search`).
    pub knn_search: KnnReach,
    /// Output directory (`None`: write nothing).
    pub out: Option<PathBuf>,
    /// Leave the scenario's moving actors out (the traffic scenario's drive in an empty street).
    pub no_actors: bool,
    /// Zero-velocity and zero-rate updates at stands (`filter.standstill`).
    pub standstill: bool,
    /// Keep what the scans see through in the map (`mapping.clear_free_space = false`).
    pub keep_free_space: bool,
    /// Keep `lidar_imu_offset_s` as it is (`time.estimate_offset = false`).
    pub fixed_offset: bool,
    /// The simulated IMU's clock ahead of the LiDAR's by this, ns (a sensor-realism switch).
    pub imu_clock_offset_ns: i64,
    /// The other sensor-realism switches.
    pub realism: Realism,
    /// `time.lidar_imu_offset`, s: what the run adds to the IMU stamps.
    pub lidar_imu_offset_s: f64,
    /// Show a progress bar (on a terminal).
    pub progress: bool,
    /// Pace the run by the simulated time at this speed-up (`None`: as fast as possible).
    pub realtime: Option<f64>,
    /// The live outputs.
    pub sinks: crate::sink::SinkArgs,
    /// Leave the simulated IMU out: LiDAR-only (constant-velocity model).
    pub no_imu: bool,
}

/// The outcome of a simulated run.
#[derive(Debug)]
pub struct SimReport {
    /// Counts and times.
    pub stats: RunStats,
    /// Files, map, evaluation.
    pub finished: Finished,
    /// Simulated seconds.
    pub sim_s: f64,
    /// Wall-clock seconds of the whole run (simulation included).
    pub wall_s: f64,
    /// The scan period, seconds.
    pub scan_period_s: f64,
    /// The storage class used.
    pub class: StorageClass,
    /// Drift per distance, on drives of at least [`DRIFT_MIN_PATH_M`].
    pub drift: Option<Drift>,
}

/// Below this ground-truth path length no drift per 100 m is given, metres.
pub const DRIFT_MIN_PATH_M: f64 = 300.0;

/// Drift per distance: the relative translation error over every 100 m stretch of the ground
/// truth's path (evo's RPE, `--delta 100 --delta_unit m --all_pairs`, pairs from the truth).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Drift {
    /// Ground-truth path length, metres.
    pub path_m: f64,
    /// Stretches of 100 m (overlapping, one from each pose).
    pub pairs: usize,
    /// Mean error over a stretch, metres (per 100 m, so also per cent).
    pub mean_m: f64,
    /// Largest error over a stretch, metres.
    pub max_m: f64,
    /// Mean rotation error over a stretch, degrees.
    pub rot_mean_deg: f64,
}

/// The drift per 100 m of `est` against `gt`, when the truth's path is long enough.
pub fn drift_per_100m(gt: &Trajectory, est: &Trajectory) -> Option<Drift> {
    let path_m: f64 = gt.poses.windows(2).map(|w| (w[1].t - w[0].t).norm()).sum();
    if path_m < DRIFT_MIN_PATH_M {
        return None;
    }
    let opt = eval::EvalOptions {
        max_diff: 0.002,
        rpe_delta: 100.0,
        rpe_unit: eval::DeltaUnit::Metres,
        all_pairs: true,
        pairs_from_gt: true,
        ..Default::default()
    };
    let r = eval::evaluate(gt, est, &opt).ok()?;
    (r.rpe_trans.n > 0).then_some(Drift {
        path_m,
        pairs: r.rpe_trans.n,
        mean_m: r.rpe_trans.mean,
        max_m: r.rpe_trans.max,
        rot_mean_deg: r.rpe_rot_deg.mean,
    })
}

impl SimReport {
    /// ATE (SE(3)-aligned translation RMSE), metres, if evaluated.
    pub fn ate_m(&self) -> Option<f64> {
        self.finished.eval.as_ref().map(|r| r.ape_trans.rmse)
    }
}

/// The host preset of a simulated sensor.
pub fn preset_of(sensor: SensorModel) -> Preset {
    match sensor {
        SensorModel::Vlp16 => Preset::Vlp16,
        SensorModel::Vlp32c => Preset::Vlp32c,
        SensorModel::Hdl32e => Preset::Hdl32e,
        SensorModel::Os1_16 => Preset::Os1_16,
        SensorModel::Os1_64 => Preset::Os1_64,
        SensorModel::Os1_128 => Preset::Os1_128,
    }
}

/// The simulated sensor of a host preset, if firmware-sim has it.
pub fn sensor_of(preset: Preset) -> Option<SensorModel> {
    Some(match preset {
        Preset::Vlp16 => SensorModel::Vlp16,
        Preset::Vlp32c => SensorModel::Vlp32c,
        Preset::Hdl32e => SensorModel::Hdl32e,
        Preset::Os1_16 => SensorModel::Os1_16,
        Preset::Os1_64 => SensorModel::Os1_64,
        Preset::Os1_128 => SensorModel::Os1_128,
        Preset::Os1_32 => return None,
    })
}

/// The configuration a scenario runs with: the preset's, with the scenario's true extrinsic and
/// the simulated IMU's noise densities and gravity (what a real user takes from the calibration
/// and the IMU's datasheet, and what the peers and the end-to-end tests get), and the given
/// association mode.
pub fn scenario_config(sc: &Scenario, preset: Preset, mode: Option<AssociationMode>) -> Config {
    let mut cfg = Config::preset(preset);
    let ext: Isometry3<f64> = sc.extrinsic();
    let q = ext.rotation.quaternion();
    cfg.extrinsics.translation = [ext.translation.x, ext.translation.y, ext.translation.z];
    cfg.extrinsics.rotation_rpy_deg = None;
    cfg.extrinsics.rotation_quat_wxyz = Some([q.w, q.i, q.j, q.k]);
    cfg.sensor.columns = sc.layout().cols() as u32;
    let n = sc.config().imu_noise.density;
    cfg.imu.gyro_noise = n.gyro;
    cfg.imu.acc_noise = n.acc;
    cfg.imu.gyro_bias_walk = n.gyro_bias_walk;
    cfg.imu.acc_bias_walk = n.acc_bias_walk;
    cfg.imu.gravity = loglio_firmware_sim::trajectory::GRAVITY;
    if let Some(m) = mode {
        cfg.mapping.association = m;
    }
    // The simulated world is bounded; the preset's pool is ample.
    cfg.mapping.map_capacity = 1 << 18;
    cfg
}

/// Sensor-realism switches of a simulated run beside the clock offset (`None`: the
/// scenario's own).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Realism {
    /// Scans per second (10 or 20; a Velodyne 5 to 20).
    pub scan_rate_hz: Option<u32>,
    /// The IMU chip's gyroscope full scale, deg/s (125, 250, 500, 1000, 2000): it saturates
    /// there.
    pub gyro_full_scale_dps: Option<u32>,
    /// The IMU chip's accelerometer full scale, g (2, 4, 8, 16).
    pub acc_full_scale_g: Option<u32>,
}

/// Builds the scenario of `opt`.
pub fn scenario(opt: &SimOptions) -> Result<Scenario, PipelineError> {
    let mut sc_cfg = ScenarioConfig::new(opt.kind, opt.sensor, opt.seed);
    if let Some(d) = opt.duration_s {
        sc_cfg.duration_s = d;
    }
    sc_cfg.actors = !opt.no_actors;
    sc_cfg.imu_clock_offset_ns = opt.imu_clock_offset_ns;
    let r = opt.realism;
    if let Some(hz) = r.scan_rate_hz {
        sc_cfg.lidar =
            sc_cfg.lidar.with_scan_rate_hz(hz).map_err(|e| PipelineError(format!("--scan-rate-hz: {e}")))?;
    }
    if let Some(dps) = r.gyro_full_scale_dps {
        sc_cfg.imu_board.gyro_fs = GyroFs::from_dps(dps).ok_or_else(|| {
            PipelineError(format!("--imu-gyro-full-scale: 125, 250, 500, 1000 or 2000 deg/s, not {dps}"))
        })?;
    }
    if let Some(g) = r.acc_full_scale_g {
        sc_cfg.imu_board.accel_fs = AccelFs::from_g(g)
            .ok_or_else(|| PipelineError(format!("--imu-acc-full-scale: 2, 4, 8 or 16 g, not {g}")))?;
    }
    Scenario::from_config(sc_cfg).map_err(|e| PipelineError(format!("scenario: {e}")))
}

/// The ground truth (IMU frame in the world) at the estimate's stamps.
pub fn ground_truth(sc: &Scenario, poses: &[EstPose]) -> Vec<EstPose> {
    poses
        .iter()
        .map(|p| {
            let g = sc.pose_at(p.t_ns);
            let q = g.rotation.quaternion();
            EstPose {
                t_ns: p.t_ns,
                p: [g.translation.x, g.translation.y, g.translation.z],
                q_wxyz: [q.w, q.i, q.j, q.k],
            }
        })
        .collect()
}

fn to_trajectory(poses: &[EstPose]) -> Trajectory {
    let text: String = poses
        .iter()
        .map(|p| {
            format!(
                "{} {} {} {} {} {} {} {}\n",
                crate::output::format_stamp_ns(p.t_ns),
                p.p[0],
                p.p[1],
                p.p[2],
                p.q_wxyz[1],
                p.q_wxyz[2],
                p.q_wxyz[3],
                p.q_wxyz[0]
            )
        })
        .collect();
    // Our own output: parsing cannot fail on finite numbers.
    eval::parse_tum(&text, "ground truth")
        .unwrap_or(Trajectory { stamps: Some(Vec::new()), poses: Vec::new() })
}

/// Runs a scenario end to end.
pub fn run(opt: &SimOptions) -> Result<SimReport, PipelineError> {
    let wall = Instant::now();
    let sc = scenario(opt)?;
    let mut cfg = scenario_config(&sc, preset_of(opt.sensor), opt.mode);
    if let Some(m) = opt.max_points {
        cfg.mapping.max_points = m;
    }
    cfg.mapping.knn_search = opt.knn_search;
    cfg.filter.standstill = opt.standstill;
    cfg.mapping.clear_free_space = !opt.keep_free_space;
    cfg.time.estimate_offset = !opt.fixed_offset;
    // What the chip is configured to is what its user knows: its rate and its full scales.
    cfg.sensor.scan_rate_hz = sc.config().lidar.scan_rate_hz();
    cfg.imu.gyro_full_scale = f64::from(sc.config().imu_board.gyro_fs.dps());
    cfg.imu.acc_full_scale = f64::from(sc.config().imu_board.accel_fs.g());
    cfg.time.lidar_imu_offset = opt.lidar_imu_offset_s;
    if opt.no_imu {
        cfg.imu.source = ImuSource::None;
    }
    let layout = sc.layout().clone();
    let class = StorageClass::choose(layout.rows(), layout.cols(), cfg.mapping.map_capacity)?;
    let scan_period_s = 1.0 / cfg.sensor.scan_rate_hz;
    let sim_s = sc.config().duration_s;
    let progress = if opt.progress {
        Progress::new((sim_s * 1000.0) as u64, "ms simulated", false)
    } else {
        Progress::hidden()
    };
    let mut pace = opt.realtime.map(crate::input::pace::Pacer::new);
    let no_imu = opt.no_imu;
    let mut events = sc.events().filter(|ev| !(no_imu && matches!(ev, Event::Imu(_)))).map(|ev| match ev {
        Event::Imu(s) => {
            if let Some(p) = &mut pace {
                p.wait_for(s.t_ns);
            }
            run::Event::Imu(s)
        }
        Event::Scan(s) => {
            if let Some(p) = &mut pace {
                p.wait_for(s.end_ns);
            }
            progress.set_position((sc.seconds(s.end_ns).max(0.0) * 1000.0) as u64);
            run::Event::Scan { scan: OwnedScan { start_ns: s.start_ns, points: s.points }, arrival_ns: 0 }
        }
    });
    let (stop, _signals) = run::Signals::stop_flag();
    let drift = std::cell::Cell::new(None);
    let opts = RunOptions {
        outputs: OutputOptions {
            dir: opt.out.clone(),
            gt: None,
            map: opt.out.is_some(),
            plots: opt.out.is_some(),
        },
        sinks: opt.sinks.build(),
        stop: Some(stop),
        // The simulator's threads generate the next scans beside the odometry: its own time
        // per scan is its thread's CPU time.
        cpu_clock: true,
        before_finish: Some(Box::new(|runner: &mut Runner<'_>| {
            let gt = ground_truth(&sc, &runner.outputs.poses);
            if let Some(dir) = &opt.out {
                files::write_tum(&dir.join("groundtruth.tum"), &gt)?;
                if !sc.actors().is_empty() {
                    sc.write_actors_csv(&dir.join(ACTORS_CSV), 10.0)
                        .map_err(|e| PipelineError(format!("{}: {e}", dir.join(ACTORS_CSV).display())))?;
                }
            }
            let gt = to_trajectory(&gt);
            drift.set(drift_per_100m(&gt, &to_trajectory(&runner.outputs.poses)));
            runner.outputs.set_ground_truth(Some(gt));
            Ok(())
        })),
    };
    let (stats, finished) = run::drive(&cfg, layout, &mut events, opts)?;
    progress.finish();
    let mut finished = finished;
    if let Some(dir) = &opt.out {
        finished.files.push(dir.join("groundtruth.tum"));
        if !sc.actors().is_empty() {
            finished.files.push(dir.join(ACTORS_CSV));
        }
    }
    Ok(SimReport {
        stats,
        finished,
        sim_s,
        wall_s: wall.elapsed().as_secs_f64(),
        scan_period_s,
        class,
        drift: drift.get(),
    })
}

/// The human summary of a simulated run.
pub fn summary(opt: &SimOptions, r: &SimReport) -> String {
    let st = &r.stats;
    let mut s = runner::lidar_only_line(st);
    s.push_str(&format!(
        "scenario {} ({} s, {}, seed {}): {} scans ({}), {} IMU samples\n",
        opt.kind.name(),
        r.sim_s,
        opt.sensor.name(),
        opt.seed,
        st.scans,
        runner::status_summary(st),
        st.imu_in
    ));
    let faults = st.faults.phrase();
    if !faults.is_empty() {
        s.push_str(&format!("faults: {faults}\n"));
    }
    let mean = st.mean_scan_s();
    s.push_str(&format!(
        "odometry: {:.1} ms per scan (mean), {:.1} ms (median), its thread's CPU time; real-time margin {:.1}x (scan period {:.0} ms / mean)\n",
        mean * 1e3,
        st.median_scan_s() * 1e3,
        if mean > 0.0 { r.scan_period_s / mean } else { f64::INFINITY },
        r.scan_period_s * 1e3
    ));
    s.push_str(&runner::scan_time_trend_line(st));
    s.push_str(&runner::map_line(&st.map));
    s.push_str(&runner::time_offset_line(&st.time_offset));
    match &r.finished.eval {
        Some(e) => s.push_str(&format!(
            "ATE against ground truth (SE(3)-aligned, {} poses): rmse {:.3} m, max {:.3} m; rotation rmse {:.2} deg\n",
            e.matched, e.ape_trans.rmse, e.ape_trans.max, e.ape_rot_deg.rmse
        )),
        None => s.push_str("ATE: not evaluated\n"),
    }
    if let Some(d) = &r.drift {
        s.push_str(&format!(
            "drift per 100 m of the {:.0} m driven: {:.3} m mean ({:.3} %), {:.3} m max, {:.3} deg mean rotation ({} stretches)\n",
            d.path_m,
            d.mean_m,
            d.mean_m,
            d.max_m,
            d.rot_mean_deg,
            d.pairs
        ));
    }
    s.push_str(&format!("wall time {:.1} s (simulation included)\n", r.wall_s));
    for line in crate::sink::sinks_summary(&st.sinks) {
        s.push_str(&format!("live output {line}\n"));
    }
    if !r.finished.files.is_empty() {
        s.push_str("wrote:");
        for f in &r.finished.files {
            s.push_str(&format!(" {}", f.display()));
        }
        s.push('\n');
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use loglio_core::imu::ImuNoise;

    /// `loglio sim`, `bench` and `demo` give the odometry what a user gives it for a real rig:
    /// the IMU's own noise densities and gravity (here the simulator's), not the preset's
    /// generic ones. With the preset's, the drone scenario drifted 4.7 m (0.026 m with these).
    #[test]
    fn scenario_config_takes_the_simulated_imu_noise_and_gravity() {
        let mut c = ScenarioConfig::new(ScenarioKind::Drone, SensorModel::Vlp32c, 3);
        c.duration_s = 1.0;
        c.imu_noise.density =
            ImuNoise { gyro: 1.25e-3, acc: 3.5e-2, gyro_bias_walk: 2.5e-5, acc_bias_walk: 4.5e-4 };
        let sc = Scenario::from_config(c).unwrap();
        let cfg = scenario_config(&sc, Preset::Vlp32c, Some(AssociationMode::Plain));
        assert_eq!(cfg.imu.gyro_noise, 1.25e-3);
        assert_eq!(cfg.imu.acc_noise, 3.5e-2);
        assert_eq!(cfg.imu.gyro_bias_walk, 2.5e-5);
        assert_eq!(cfg.imu.acc_bias_walk, 4.5e-4);
        assert_eq!(cfg.imu.gravity, loglio_firmware_sim::trajectory::GRAVITY);
        assert_eq!(cfg.mapping.association, AssociationMode::Plain);
        // ... and they reach the filter.
        let core = crate::run::engine::odometry_config(&cfg, sc.layout().clone()).unwrap();
        assert_eq!(core.eskf.noise.gyro, 1.25e-3);
        assert_eq!(core.eskf.noise.acc, 3.5e-2);
        assert_eq!(core.eskf.noise.gyro_bias_walk, 2.5e-5);
        assert_eq!(core.eskf.noise.acc_bias_walk, 4.5e-4);
        assert_eq!(core.init.gravity, loglio_firmware_sim::trajectory::GRAVITY);
        let t = sc.extrinsic().translation.vector;
        assert_eq!(cfg.extrinsics.translation, [t.x, t.y, t.z]);
        // The default measurement budget unless asked for; `mapping.max_points` reaches the
        // association.
        assert_eq!(core.association.max_points, loglio_core::association::DEFAULT_MAX_POINTS);
        let file = Config::from_toml_str("preset = \"vlp32c\"\n[mapping]\nmax_points = 5000\n").unwrap();
        let core = crate::run::engine::odometry_config(&file, sc.layout().clone()).unwrap();
        assert_eq!(core.association.max_points, 5000);
        let err = Config::from_toml_str("preset = \"vlp32c\"\n[mapping]\nmax_points = -1\n").unwrap_err();
        assert!(err.0.contains("mapping.max_points"), "{}", err.0);
        // The block k-NN and the standstill updates unless asked otherwise; the keys reach the
        // core.
        assert_eq!(core.association.knn_reach, KnnReach::Block);
        assert!(core.standstill.enabled);
        let file = Config::from_toml_str(
            "preset = \"vlp32c\"\n[mapping]\nknn_search = \"exact\"\n[filter]\nmax_iterations = 4\nstandstill = false\n",
        )
        .unwrap();
        assert_eq!(file.mapping.knn_search, KnnReach::Exact);
        let core = crate::run::engine::odometry_config(&file, sc.layout().clone()).unwrap();
        assert_eq!(core.association.knn_reach, KnnReach::Exact);
        assert!(!core.standstill.enabled);
        let err = Config::from_toml_str("preset = \"vlp32c\"\n[mapping]\nknn_search = \"kd\"\n").unwrap_err();
        assert_eq!(err.0, "config: mapping.knn_search = \"kd\" is not one of: exact, block");
    }
}
