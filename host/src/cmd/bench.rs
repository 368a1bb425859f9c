//! `loglio bench`: will this computer keep up? The per-stage times of the odometry and the
//! real-time margin (scan period / mean time per scan) for a sensor preset, on a simulated
//! drive of that sensor (firmware-sim), with a baseline measured in the same run: the same
//! scans through the `plain` association (FAST-LIO2-like point-to-plane, no normals).
//!
//! The scans and IMU samples are generated first and held in memory, so only the odometry is
//! timed (with the host's monotonic clock through the core's `process_scan_timed`). Scans
//! processed before the IMU initialisation are not counted.

use std::time::Instant;

use loglio_core::imu::ImuSample;
use loglio_firmware_sim::scenario::{Event, ScenarioKind};
use serde_json::json;

use crate::cmd::sim::{self, SimOptions};
use crate::config::{AssociationMode, KnnReach, Preset};
use crate::error::PipelineError;
use crate::machine;
use crate::output::Progress;
use crate::run::engine::{self, StorageClass};
use crate::run::runner::{OwnedScan, Runner};
use crate::sink::files::{OutputOptions, Outputs};

/// Times of one configuration.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ModeTimes {
    /// The association mode.
    pub mode: String,
    /// Scans timed (after the initialisation).
    pub scans: usize,
    /// Mean per stage, ms: normals, undistort, downsample, association, update, map.
    pub stages_ms: [f64; 6],
    /// Mean, median and 95th percentile of the whole scan, ms.
    pub total_ms: [f64; 3],
    /// Scan period / mean time per scan.
    pub margin: f64,
}

/// The stage names, in [`ModeTimes::stages_ms`] order.
pub const STAGES: [&str; 6] = ["normals", "undistort", "downsample", "association", "update", "map"];

/// A bench result.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BenchReport {
    /// Preset.
    pub preset: String,
    /// The simulated scenario.
    pub scenario: String,
    /// The measurement budget both modes ran with (0: none).
    pub max_points: u64,
    /// The k-NN both modes ran with.
    pub knn_search: KnnReach,
    /// Threads of the association, both modes (`--threads`).
    pub threads: usize,
    /// Simulated seconds.
    pub seconds: f64,
    /// Points per scan (mean).
    pub points_per_scan: f64,
    /// Scan period, s.
    pub scan_period_s: f64,
    /// The configured mode (the preset's: full).
    pub main: ModeTimes,
    /// The baseline (plain).
    pub baseline: ModeTimes,
    /// Seconds spent generating the data (not timed).
    pub generate_s: f64,
}

fn time_mode(
    data: &[Event2],
    sc: &loglio_firmware_sim::scenario::Scenario,
    preset: Preset,
    mode: AssociationMode,
    (max_points, knn_search, threads): (Option<u64>, KnnReach, usize),
    scan_period_s: f64,
) -> Result<ModeTimes, PipelineError> {
    let mut cfg = sim::scenario_config(sc, preset, Some(mode));
    if let Some(m) = max_points {
        cfg.mapping.max_points = m;
    }
    cfg.mapping.knn_search = knn_search;
    let layout = sc.layout().clone();
    let class = StorageClass::choose(layout.rows(), layout.cols(), cfg.mapping.map_capacity)?;
    let core = engine::odometry_config(&cfg, layout)?;
    let per_scan = engine::with_engine(
        &core,
        class,
        threads,
        |engine| -> Result<Vec<(u64, [u64; 6])>, PipelineError> {
            let mut runner = Runner::new(engine, Outputs::new(OutputOptions::default())?, 0.0);
            // Every insertion inside a timed scan: with a second thread the next scan's.
            runner.flush_map_when_idle = false;
            let timed = std::rc::Rc::new(std::cell::RefCell::new(Vec::new()));
            let sink = timed.clone();
            runner.on_scan = Some(Box::new(move |res, _, _| {
                if !matches!(res.status, loglio_core::output::Status::Initialising(_)) {
                    let t = &res.times;
                    sink.borrow_mut().push((
                        t.total_ns,
                        [
                            t.normals_ns,
                            t.undistort_ns,
                            t.downsample_ns,
                            t.association_ns,
                            t.update_ns,
                            t.map_ns,
                        ],
                    ));
                }
            }));
            for ev in data {
                match ev {
                    Event2::Imu(s) => runner.imu(*s)?,
                    Event2::Scan(s) => runner.scan(s.clone(), 0)?,
                }
            }
            runner.process_ready(true, None)?;
            drop(runner);
            Ok(timed.take())
        },
    )??;
    let n = per_scan.len().max(1) as f64;
    let mut stages_ms = [0.0; 6];
    for (_, st) in &per_scan {
        for (acc, v) in stages_ms.iter_mut().zip(st) {
            *acc += *v as f64 * 1e-6 / n;
        }
    }
    let mut totals: Vec<f64> = per_scan.iter().map(|(t, _)| *t as f64 * 1e-6).collect();
    totals.sort_by(f64::total_cmp);
    let pick =
        |q: f64| totals.get(((totals.len() as f64 - 1.0) * q).round() as usize).copied().unwrap_or(0.0);
    let mean = totals.iter().sum::<f64>() / n;
    Ok(ModeTimes {
        mode: match mode {
            AssociationMode::Full => "full",
            AssociationMode::PlaneOnly => "plane-only",
            AssociationMode::Plain => "plain",
        }
        .into(),
        scans: per_scan.len(),
        stages_ms,
        total_ms: [mean, pick(0.5), pick(0.95)],
        margin: if mean > 0.0 { scan_period_s * 1e3 / mean } else { f64::INFINITY },
    })
}

#[derive(Clone, Debug)]
enum Event2 {
    Imu(ImuSample),
    Scan(OwnedScan),
}

/// Runs the bench for `preset` over `seconds` of a simulated scenario (`None`: the vehicle
/// drive for Velodyne presets, the handheld walk for Ouster), both modes with the measurement
/// budget `max_points` (0: every downsampled point; `None`: the configuration's), the k-NN `knn_search` and `threads`
/// (0: the available cores) for the association.
#[allow(clippy::too_many_arguments)]
pub fn run(
    preset: Preset,
    scenario: Option<ScenarioKind>,
    seconds: f64,
    max_points: Option<u64>,
    knn_search: KnnReach,
    threads: usize,
    progress: bool,
) -> Result<BenchReport, PipelineError> {
    let threads = crate::config::ComputeConfig { threads: threads as u32 }.resolved_threads();
    let sensor = sim::sensor_of(preset).ok_or_else(|| {
        PipelineError(format!(
            "the simulator has no {preset} model; bench one of vlp16, vlp32c, hdl32e, os1-16, os1-64, os1-128 (the per-point cost scales with the points per scan)"
        ))
    })?;
    let kind = scenario.unwrap_or(if preset.family() == crate::config::SensorFamily::Ouster {
        ScenarioKind::Handheld
    } else {
        ScenarioKind::Vehicle
    });
    let opt = SimOptions {
        kind,
        sensor,
        seed: 1,
        duration_s: Some(seconds),
        mode: None,
        max_points,
        knn_search,
        out: None,
        no_actors: false,
        progress: false,
        realtime: None,
        sinks: crate::sink::SinkArgs::default(),
        no_imu: false,
        standstill: loglio_core::standstill::StandstillConfig::DEFAULT.enabled,
        keep_free_space: false,
        fixed_offset: false,
        imu_clock_offset_ns: 0,
        realism: Default::default(),
        lidar_imu_offset_s: 0.0,
    };
    let sc = sim::scenario(&opt)?;
    let t0 = Instant::now();
    let bar = if progress {
        Progress::new((seconds * 10.0) as u64, "scans generated", false)
    } else {
        Progress::hidden()
    };
    let mut data = Vec::new();
    let (mut points, mut scans) = (0usize, 0usize);
    for ev in sc.events() {
        match ev {
            Event::Imu(s) => data.push(Event2::Imu(s)),
            Event::Scan(s) => {
                points += s.points.len();
                scans += 1;
                bar.inc(1);
                data.push(Event2::Scan(OwnedScan { start_ns: s.start_ns, points: s.points }));
            }
        }
    }
    bar.finish();
    let generate_s = t0.elapsed().as_secs_f64();
    let scan_period_s = 1.0 / crate::config::Config::preset(preset).sensor.scan_rate_hz;
    let knn = (max_points, knn_search, threads);
    let main = time_mode(&data, &sc, preset, AssociationMode::Full, knn, scan_period_s)?;
    let baseline = time_mode(&data, &sc, preset, AssociationMode::Plain, knn, scan_period_s)?;
    Ok(BenchReport {
        preset: preset.name().into(),
        scenario: kind.name().into(),
        max_points: max_points.unwrap_or_else(|| crate::config::Config::preset(preset).mapping.max_points),
        knn_search,
        threads,
        seconds,
        points_per_scan: points as f64 / scans.max(1) as f64,
        scan_period_s,
        main,
        baseline,
        generate_s,
    })
}

fn mode_json(m: &ModeTimes) -> serde_json::Value {
    let stages: serde_json::Map<String, serde_json::Value> =
        STAGES.iter().zip(m.stages_ms).map(|(k, v)| (k.to_string(), json!(v))).collect();
    json!({
        "mode": m.mode,
        "scans": m.scans,
        "stage_mean_ms": stages,
        "scan_ms": { "mean": m.total_ms[0], "median": m.total_ms[1], "p95": m.total_ms[2] },
        "realtime_margin": if m.margin.is_finite() { json!(m.margin) } else { json!(null) },
    })
}

impl BenchReport {
    /// Machine-readable.
    pub fn to_json(&self) -> String {
        let cpu = std::thread::available_parallelism().map_or(1, |n| n.get());
        let v = json!({
            "preset": self.preset,
            "scenario": self.scenario,
            "max_points": self.max_points,
            "knn_search": self.knn_search,
            "association_threads": self.threads,
            "simulated_seconds": self.seconds,
            "points_per_scan": self.points_per_scan,
            "scan_period_ms": self.scan_period_s * 1e3,
            "main": mode_json(&self.main),
            "baseline": mode_json(&self.baseline),
            "main_over_baseline": if self.baseline.total_ms[0] > 0.0 { json!(self.main.total_ms[0] / self.baseline.total_ms[0]) } else { json!(null) },
            "keeps_up": self.main.margin >= 1.0,
            "machine": {
                "os": std::env::consts::OS,
                "arch": std::env::consts::ARCH,
                "threads": cpu,
                "cpu": machine::cpu_model(),
                "built_for": machine::vector_features(),
            },
        });
        serde_json::to_string_pretty(&v).unwrap_or_default()
    }

    /// Human-readable.
    pub fn to_text(&self) -> String {
        let mut s = format!(
            "bench {}: {} s of the simulated {} scenario, {:.0} points per scan, scan period {:.0} ms ({} {} threads; the association on {})\n",
            self.preset,
            self.seconds,
            self.scenario,
            self.points_per_scan,
            self.scan_period_s * 1e3,
            std::env::consts::ARCH,
            std::thread::available_parallelism().map_or(1, |n| n.get()),
            self.threads,
        );
        s.push_str(&machine::describe());
        s.push('\n');
        if self.max_points > 0 {
            s.push_str(&format!(
                "measurement budget: at most {} points measured per scan\n",
                self.max_points
            ));
        }
        if self.knn_search == KnnReach::Exact {
            s.push_str("k-NN: exact within the 27 voxels (--knn-search exact)\n");
        }
        s.push_str(&format!("{:<12} {:>10} {:>10}\n", "stage [ms]", self.main.mode, self.baseline.mode));
        for (i, name) in STAGES.iter().enumerate() {
            s.push_str(&format!(
                "{:<12} {:>10.2} {:>10.2}\n",
                name, self.main.stages_ms[i], self.baseline.stages_ms[i]
            ));
        }
        for (i, name) in ["scan mean", "scan median", "scan p95"].iter().enumerate() {
            s.push_str(&format!(
                "{:<12} {:>10.2} {:>10.2}\n",
                name, self.main.total_ms[i], self.baseline.total_ms[i]
            ));
        }
        s.push_str(&format!("{:<12} {:>9.1}x {:>9.1}x\n", "margin", self.main.margin, self.baseline.margin));
        let ratio = if self.baseline.total_ms[0] > 0.0 {
            self.main.total_ms[0] / self.baseline.total_ms[0]
        } else {
            f64::NAN
        };
        s.push_str(&format!(
            "{}: this computer {} in real time ({:.1}x margin; {} takes {:.2}x the time of {})\n",
            self.preset,
            if self.main.margin >= 1.0 { "keeps up" } else { "does NOT keep up" },
            self.main.margin,
            self.main.mode,
            ratio,
            self.baseline.mode
        ));
        s
    }
}
