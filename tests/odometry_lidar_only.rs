//! LiDAR-only mode (issue 30): the simulator's scenarios without their IMU, the core's
//! constant-velocity model ([`MotionModel::LIDAR_ONLY`]) beside the LiDAR-inertial odometry on
//! the same scans (seed 7, VLP-32C, full association, nothing tuned).
//!
//! Every scan must say it was predicted without IMU, none may re-initialise, nearly all must
//! be updated by the scan, and the ATE and the rotation error (after SE(3) alignment) must stay
//! within absolute bounds and within a multiple of the LiDAR-inertial ATE. The bounds sit a
//! few times above what was measured (the test prints both): a broken prediction, a lost
//! undistortion or a frame mix-up gives metres, not centimetres.

use std::sync::{Mutex, MutexGuard};

use loglio_core::eskf::PropagationFlags;
use loglio_core::motion_model::MotionModel;
use loglio_core::odometry::{AssociationMode, Vlp32cStorage};
use loglio_core::output::Status;
use loglio_core::scan::ScanView;
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Event, Scenario, ScenarioConfig, ScenarioKind};
use loglio_tests::odom::{StdClock, Trace, align, config_for, free_set, summary};
use nalgebra::Vector3;

/// One storage per odometry (LiDAR-inertial, LiDAR-only), in statics (never on the stack); one
/// set per test, so that the two tests run side by side on cargo's two test threads.
static SETS: [Mutex<[Vlp32cStorage; 2]>; 2] = [const { Mutex::new([const { Vlp32cStorage::new() }; 2]) }; 2];

/// A free set of storages, held until the guard drops.
fn stores() -> MutexGuard<'static, [Vlp32cStorage; 2]> {
    free_set(&SETS)
}

/// The scenario run with and without IMU: (LiDAR-inertial, LiDAR-only) traces.
fn run(kind: ScenarioKind) -> (Trace, Trace) {
    let mut c = ScenarioConfig::new(kind, SensorModel::Vlp32c, 7);
    c.duration_s = kind.default_duration_s();
    let sc = Scenario::from_config(c).unwrap();
    let mut set = stores();
    let lio_cfg = config_for(&sc, AssociationMode::Full);
    let lo_cfg = config_for(&sc, AssociationMode::Full).with_motion(MotionModel::LIDAR_ONLY);
    let [a, b] = &mut *set;
    let mut lio = a.odometry(&lio_cfg).unwrap();
    let mut lo = b.odometry(&lo_cfg).unwrap();
    let (mut t_lio, mut t_lo) = (Trace::default(), Trace::default());
    let mut clock = StdClock::default();
    for ev in sc.events() {
        match ev {
            // Only the LiDAR-inertial odometry sees the IMU.
            Event::Imu(s) => {
                lio.push_imu(s);
            }
            Event::Scan(scan) => {
                let view = ScanView { start_ns: scan.start_ns, points: &scan.points };
                for (o, tr) in [(&mut lio, &mut t_lio), (&mut lo, &mut t_lo)] {
                    let r = o.process_scan_timed(view, &mut clock);
                    tr.truth.push(sc.pose_at(r.pose.t_ns));
                    tr.results.push(r);
                }
            }
        }
    }
    println!("{}", summary(kind.name(), AssociationMode::Full, &t_lio));
    println!("{} (LiDAR-only)", summary(kind.name(), AssociationMode::Full, &t_lo));
    (t_lio, t_lo)
}

/// Rotation error after the SE(3) alignment of the positions: (RMSE, max), degrees.
fn rotation_error_deg(tr: &Trace) -> (f64, f64) {
    let mut est = Vec::new();
    let mut gt = Vec::new();
    let mut pairs = Vec::new();
    for (r, t) in tr.results.iter().zip(&tr.truth) {
        if matches!(r.status, Status::Initialising(_)) {
            continue;
        }
        est.push(r.pose.position);
        gt.push(t.translation.vector);
        pairs.push((
            r.pose.rotation.to_rotation_matrix().into_inner(),
            t.rotation.to_rotation_matrix().into_inner(),
        ));
    }
    let (ra, _) = align(&est, &gt);
    let angles: Vec<f64> = pairs
        .iter()
        .map(|(re, rg)| {
            let d = rg.transpose() * ra * re;
            ((d.trace() - 1.0) * 0.5).clamp(-1.0, 1.0).acos().to_degrees()
        })
        .collect();
    let n = angles.len().max(1) as f64;
    let rmse = (angles.iter().map(|a| a * a).sum::<f64>() / n).sqrt();
    (rmse, angles.iter().copied().fold(0.0, f64::max))
}

/// The LiDAR-only checks: every scan flagged, no re-initialisation, nearly every scan updated,
/// ATE within `max_ate` m and `ratio` times the LiDAR-inertial ATE, rotation within `max_rot`
/// degrees (RMSE).
fn lidar_only(kind: ScenarioKind, max_ate: f64, ratio: f64, max_rot: f64) {
    let (lio, lo) = run(kind);
    let (ate_lio, ate_lo) = (lio.ate(), lo.ate());
    let (rot_rmse, rot_max) = rotation_error_deg(&lo);
    println!(
        "{kind:?}: ATE LiDAR-inertial {ate_lio:.4} m, LiDAR-only {ate_lo:.4} m ({:.1}x); LiDAR-only rotation rmse {rot_rmse:.3} deg, max {rot_max:.3} deg",
        ate_lo / ate_lio
    );
    assert!(
        lo.results.iter().all(|r| r.propagation.has(PropagationFlags::LIDAR_ONLY)),
        "{kind:?}: every LiDAR-only scan says so"
    );
    assert!(
        lio.results.iter().all(|r| !r.propagation.has(PropagationFlags::LIDAR_ONLY)),
        "{kind:?}: no LiDAR-inertial scan says LiDAR-only"
    );
    let [ok, deg, imu, init, reinit] = lo.status_counts();
    assert_eq!((init, reinit), (0, 0), "{kind:?}: no initialising or re-initialising scan without IMU");
    // The first scan builds the map.
    assert!(
        ok + deg + 2 >= lo.results.len(),
        "{kind:?}: every scan updated ({ok} ok, {deg} degraded, {imu} not)"
    );
    assert!(
        ate_lo.is_finite() && ate_lo <= max_ate,
        "{kind:?}: LiDAR-only ATE {ate_lo:.4} m above {max_ate} m"
    );
    assert!(
        ate_lo <= ratio * ate_lio,
        "{kind:?}: LiDAR-only ATE {ate_lo:.4} m above {ratio}x the LiDAR-inertial {ate_lio:.4} m"
    );
    assert!(rot_rmse <= max_rot, "{kind:?}: LiDAR-only rotation error {rot_rmse:.3} deg above {max_rot} deg");
    // The first scan's frame is the world: its pose is the identity.
    let first = &lo.results[0].pose;
    assert_eq!(first.position, Vector3::zeros());
    assert_eq!(first.rotation.angle(), 0.0);
}

#[test]
fn vehicle_without_imu() {
    lidar_only(ScenarioKind::Vehicle, BOUNDS[0].0, BOUNDS[0].1, BOUNDS[0].2);
}

#[test]
fn handheld_without_imu() {
    lidar_only(ScenarioKind::Handheld, BOUNDS[1].0, BOUNDS[1].1, BOUNDS[1].2);
}

/// (ATE m, multiple of the LiDAR-inertial ATE, rotation RMSE deg) for vehicle and handheld.
/// Measured (2026-11-27, AMD EPYC 2-core, the commit that added this test): vehicle 0.0075 m
/// against 0.0054 m LiDAR-inertial (1.4x), rotation 0.049 deg RMSE (0.165 max); handheld
/// 0.0156 m against 0.0030 m (5.1x), 0.415 deg (0.769 max).
const BOUNDS: [(f64, f64, f64); 2] = [(0.04, 5.0, 0.3), (0.05, 10.0, 1.5)];
