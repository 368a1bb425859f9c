//! Helpers of the odometry tests: the configuration for a simulated scenario (its true extrinsic
//! and its IMU's noise figures, nothing tuned per scenario), a lockstep runner that feeds one
//! event stream to several odometries (so a scenario is generated once for every mode), and the
//! absolute trajectory error after SE(3) alignment.

use std::sync::{Mutex, MutexGuard, TryLockError};
use std::time::{Duration, Instant};

use loglio_core::odometry::{AssociationMode, Clock, Odometry, OdometryConfig};
use loglio_core::output::{ScanResult, Status};
use loglio_core::scan::ScanView;
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Event, Scenario};
use nalgebra::{Isometry3, Matrix3, Vector3};

/// The odometry configuration for a scenario: the sensor's preset, the scenario's true
/// extrinsic and the simulated IMU's noise densities.
pub fn config_for(sc: &Scenario, mode: AssociationMode) -> OdometryConfig {
    let layout = sc.layout().clone();
    let base = match sc.config().lidar.model() {
        SensorModel::Os1_16 | SensorModel::Os1_64 => OdometryConfig::os1_16(layout),
        _ => OdometryConfig::vlp32c(layout),
    };
    let e = sc.extrinsic();
    let mut cfg = base.with_extrinsic(e.rotation, e.translation.vector).with_mode(mode);
    cfg.eskf.noise = sc.config().imu_noise.density;
    cfg
}

/// A monotonic clock for stage times.
#[derive(Debug)]
pub struct StdClock(Instant);

impl Default for StdClock {
    fn default() -> Self {
        Self(Instant::now())
    }
}

impl Clock for StdClock {
    fn now_ns(&mut self) -> u64 {
        self.0.elapsed().as_nanos() as u64
    }
}

/// One odometry's results on a scenario, with the true IMU pose at each result's time.
#[derive(Debug, Default)]
pub struct Trace {
    /// Per scan.
    pub results: Vec<ScanResult>,
    /// The true IMU pose (world from IMU) at `results[i].pose.t_ns`.
    pub truth: Vec<Isometry3<f64>>,
}

impl Trace {
    /// Estimated and true positions of the scans that have an estimate (initialised).
    pub fn positions(&self) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
        let mut est = Vec::new();
        let mut gt = Vec::new();
        for (r, t) in self.results.iter().zip(&self.truth) {
            if matches!(r.status, Status::Initialising(_)) {
                continue;
            }
            est.push(r.pose.position);
            gt.push(t.translation.vector);
        }
        (est, gt)
    }

    /// ATE RMSE after SE(3) alignment, metres.
    pub fn ate(&self) -> f64 {
        let (est, gt) = self.positions();
        ate_rmse(&est, &gt)
    }

    /// How many scans had each status kind: (ok, degraded, imu-only, initialising, reinit).
    pub fn status_counts(&self) -> [usize; 5] {
        let mut c = [0; 5];
        for r in &self.results {
            let i = match r.status {
                Status::Ok => 0,
                // Updated by the scan after a bridged sensor pause.
                Status::Degraded { .. } | Status::Bridged(_) => 1,
                Status::ImuOnly(_) => 2,
                Status::Initialising(_) => 3,
                Status::Reinitialising(_) | Status::Lost { .. } => 4,
            };
            c[i] += 1;
        }
        c
    }
}

/// Feeds every event of `sc` to every odometry (IMU samples to all, then each scan to each in
/// turn) and returns their traces. `filter` may drop or alter events (fault injection): it gets
/// each event and returns the events to deliver.
pub fn run_lockstep<const PIX: usize, const PTS: usize, const DS: usize>(
    sc: &Scenario,
    odos: &mut [Odometry<'_, PIX, PTS, DS>],
    mut inject: impl FnMut(Event) -> Vec<Event>,
) -> Vec<Trace> {
    let mut traces: Vec<Trace> = odos.iter().map(|_| Trace::default()).collect();
    let mut clock = StdClock::default();
    for ev in sc.events() {
        for ev in inject(ev) {
            match ev {
                Event::Imu(s) => {
                    for o in odos.iter_mut() {
                        o.push_imu(s);
                    }
                }
                Event::Scan(scan) => {
                    let view = ScanView { start_ns: scan.start_ns, points: &scan.points };
                    for (o, tr) in odos.iter_mut().zip(traces.iter_mut()) {
                        let r = o.process_scan_timed(view, &mut clock);
                        tr.truth.push(sc.pose_at(r.pose.t_ns));
                        tr.results.push(r);
                    }
                }
            }
        }
    }
    traces
}

/// The rigid transform (R, t) minimising `Σ |R est_i + t - gt_i|²` (Umeyama without scale).
pub fn align(est: &[Vector3<f64>], gt: &[Vector3<f64>]) -> (Matrix3<f64>, Vector3<f64>) {
    let n = est.len().min(gt.len()).max(1) as f64;
    let me = est.iter().sum::<Vector3<f64>>() / n;
    let mg = gt.iter().sum::<Vector3<f64>>() / n;
    let mut c = Matrix3::zeros();
    for (e, g) in est.iter().zip(gt) {
        c += (g - mg) * (e - me).transpose();
    }
    let svd = c.svd(true, true);
    let (u, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
    let mut s = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        s[(2, 2)] = -1.0;
    }
    let r = u * s * vt;
    (r, mg - r * me)
}

/// ATE RMSE after [`align`], metres (`NaN` for no poses).
pub fn ate_rmse(est: &[Vector3<f64>], gt: &[Vector3<f64>]) -> f64 {
    if est.is_empty() {
        return f64::NAN;
    }
    let (r, t) = align(est, gt);
    let se: f64 = est.iter().zip(gt).map(|(e, g)| (r * e + t - g).norm_squared()).sum();
    (se / est.len() as f64).sqrt()
}

/// Prints a one-line summary of a trace (for the test logs and docs/figures.md).
pub fn summary(name: &str, mode: AssociationMode, tr: &Trace) -> String {
    let [ok, deg, imu, init, reinit] = tr.status_counts();
    let acc: u64 = tr.results.iter().map(|r| u64::from(r.associations.accepted())).sum();
    let large: u64 = tr.results.iter().map(|r| u64::from(r.associations.large_surfel)).sum();
    let small: u64 = tr.results.iter().map(|r| u64::from(r.associations.small_surfel)).sum();
    let n = tr.results.len().max(1) as f64;
    let ms = tr.results.iter().map(|r| r.times.total_ns as f64).sum::<f64>() / n * 1e-6;
    format!(
        "{name} {mode:?}: ATE {:.4} m over {} scans (ok {ok}, degraded {deg}, imu-only {imu}, init {init}, \
         reinit {reinit}); residuals/scan {:.0} (large {:.0}, small {:.0}); {ms:.2} ms/scan",
        tr.ate(),
        tr.results.len(),
        acc as f64 / n,
        large as f64 / n,
        small as f64 / n,
    )
}

/// The first free one of `sets` (storages in statics, one set per test running at once), held
/// until the guard drops; waits while every set is taken. A poisoned set (a test that failed
/// with it) is handed out as it is: each odometry discards its storage's contents.
pub fn free_set<T>(sets: &'static [Mutex<T>]) -> MutexGuard<'static, T> {
    loop {
        for set in sets {
            match set.try_lock() {
                Ok(g) => return g,
                Err(TryLockError::Poisoned(e)) => return e.into_inner(),
                Err(TryLockError::WouldBlock) => {}
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}
