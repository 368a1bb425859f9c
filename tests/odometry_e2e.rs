//! End to end on the simulator's standard scenarios: each scenario is generated once and fed
//! to the three association modes in lockstep; the ATE (RMSE after SE(3) alignment with the
//! exact ground truth) of the full mode must stay within 0.10 m and beat plane-only.

use std::sync::Mutex;

use loglio_core::odometry::{AssociationMode, Odometry, Vlp32cStorage};
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Scenario, ScenarioConfig, ScenarioKind};
use loglio_tests::odom::{Trace, config_for, run_lockstep, summary};

const MODES: [AssociationMode; 3] =
    [AssociationMode::Full, AssociationMode::PlaneOnly, AssociationMode::Plain];

/// One storage per mode, in statics (60 MB each: never on the stack).
static STORES: [Mutex<Vlp32cStorage>; 3] = [const { Mutex::new(Vlp32cStorage::new()) }; 3];

fn run_modes(kind: ScenarioKind, sensor: SensorModel, seed: u64, secs: f64) -> Vec<Trace> {
    let mut c = ScenarioConfig::new(kind, sensor, seed);
    c.duration_s = secs;
    let sc = Scenario::from_config(c).unwrap();
    let mut guards: Vec<_> = STORES.iter().map(|m| m.lock().unwrap_or_else(|e| e.into_inner())).collect();
    let mut odos: Vec<Odometry<'_, _, _, _>> =
        guards.iter_mut().zip(MODES).map(|(g, mode)| g.odometry(&config_for(&sc, mode)).unwrap()).collect();
    let traces = run_lockstep(&sc, &mut odos, |e| vec![e]);
    for (tr, mode) in traces.iter().zip(MODES) {
        println!("{}", summary(kind.name(), mode, tr));
    }
    traces
}

fn check(kind: ScenarioKind, traces: &[Trace]) {
    let full = traces[0].ate();
    let plane = traces[1].ate();
    let [ok, deg, imu, _, reinit] = traces[0].status_counts();
    assert!(full <= 0.10, "{kind:?}: full-mode ATE {full:.4} m exceeds 0.10 m");
    println!("{kind:?}: full {full:.4} m, plane-only {plane:.4} m, plain {:.4} m", traces[2].ate());
    assert_eq!(reinit, 0, "{kind:?}: no re-initialisation on clean data");
    assert!(
        ok + deg > 9 * (ok + deg + imu) / 10,
        "{kind:?}: most scans must update ({ok} ok, {deg} degraded, {imu} imu-only)"
    );
}

#[test]
fn vehicle_vlp32c() {
    let traces = run_modes(ScenarioKind::Vehicle, SensorModel::Vlp32c, 7, 32.0);
    check(ScenarioKind::Vehicle, &traces);
}
