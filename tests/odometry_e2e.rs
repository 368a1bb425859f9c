//! End to end on the simulator's standard scenarios (issue 7): each scenario is generated once
//! and fed to the three association modes in lockstep. On every well-posed scenario (vehicle,
//! handheld, drone, fast rotation) the ATE (RMSE after SE(3) alignment with the exact ground truth) of
//! the full mode must stay within 0.10 m and beat plane-only.
//!
//! The corridor is degenerate along its axis: there the axis must be reported, the error along
//! it stay within what IMU integration alone gives on the same data, and the other directions
//! be held to centimetres.
//!
//! Every scenario runs for at least 30 s (the minimum; the standard lengths are 40 s and
//! 30 s), seed fixed, nothing tuned per scenario: the configuration is the sensor's preset with
//! the rig's extrinsic and the IMU's noise figures (`config_for`).

use std::sync::{Mutex, MutexGuard};

use loglio_core::eskf::PropagationFlags;
use loglio_core::odometry::{AssociationMode, Odometry, Vlp32cStorage};
use loglio_core::output::Status;
use loglio_core::scan::{ScanPoint, ScanView};
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Event, Scenario, ScenarioConfig, ScenarioKind};
use loglio_tests::odom::{StdClock, Trace, config_for, free_set, run_lockstep, summary};
use nalgebra::{Isometry3, Vector3};

const MODES: [AssociationMode; 3] =
    [AssociationMode::Full, AssociationMode::PlaneOnly, AssociationMode::Plain];

/// Two sets of one storage per odometry, in statics (60 MB each: never on the stack): two of
/// this binary's tests run at once (cargo's two test threads on a 2-core machine; with one set
/// they ran one after the other on one core, 400 s), a third waits for a free set.
static SETS: [Mutex<[Vlp32cStorage; 3]>; 2] = [const { Mutex::new([const { Vlp32cStorage::new() }; 3]) }; 2];

/// A free set of storages, held until the guard drops.
fn stores() -> MutexGuard<'static, [Vlp32cStorage; 3]> {
    free_set(&SETS)
}

fn scenario(kind: ScenarioKind, secs: f64) -> Scenario {
    let mut c = ScenarioConfig::new(kind, SensorModel::Vlp32c, 7);
    c.duration_s = secs;
    Scenario::from_config(c).unwrap()
}

/// Runs `modes` on `sc` in lockstep. The worlds of these scenarios stand still: the free-space
/// tests (moving points, map voxels seen through) find almost nothing in them.
fn run(stores: &mut [Vlp32cStorage], sc: &Scenario, modes: &[AssociationMode]) -> Vec<Trace> {
    let mut odos: Vec<Odometry<'_, _, _, _>> =
        stores.iter_mut().zip(modes).map(|(g, &mode)| g.odometry(&config_for(sc, mode)).unwrap()).collect();
    let traces = run_lockstep(sc, &mut odos, |e| vec![e]);
    for (tr, mode) in traces.iter().zip(modes) {
        println!("{}", summary(sc.config().kind.name(), *mode, tr));
    }
    let kept: u64 = traces[0].results.iter().map(|r| u64::from(r.points[1])).sum();
    let st = odos[0].stats();
    println!(
        "{:?}: {} moving points of {kept}, {} map voxels seen through",
        sc.config().kind,
        st.moving,
        st.cleared
    );
    assert!(st.moving * 1000 <= kept, "static world: {} of {kept} points judged moving", st.moving);
    assert!(st.cleared <= 1000, "static world: {} map voxels seen through", st.cleared);
    traces
}

/// The well-posed scenarios: full within 0.10 m, better than plane-only, no re-initialisation,
/// and nearly every scan updated by the LiDAR.
fn well_posed(kind: ScenarioKind) {
    well_posed_over(kind, &[7]);
}

/// [`well_posed`] on each of `seeds`, full against plane-only by their mean ATE. The seeds run
/// side by side, each on a free set of storages.
fn well_posed_over(kind: ScenarioKind, seeds: &[u64]) {
    let ates: Vec<(f64, f64)> = std::thread::scope(|s| {
        let runs: Vec<_> = seeds.iter().map(|&seed| s.spawn(move || well_posed_seed(kind, seed))).collect();
        runs.into_iter().map(|r| r.join().unwrap_or_else(|e| std::panic::resume_unwind(e))).collect()
    });
    let n = seeds.len() as f64;
    let full = ates.iter().map(|a| a.0).sum::<f64>() / n;
    let plane = ates.iter().map(|a| a.1).sum::<f64>() / n;
    assert!(
        full < plane,
        "{kind:?}: full {full:.4} m must beat plane-only {plane:.4} m (mean over {seeds:?})"
    );
}

/// One seed of [`well_posed_over`]: its checks, and the ATE of full and plane-only.
fn well_posed_seed(kind: ScenarioKind, seed: u64) -> (f64, f64) {
    let mut c = ScenarioConfig::new(kind, SensorModel::Vlp32c, seed);
    c.duration_s = kind.default_duration_s();
    let sc = Scenario::from_config(c).unwrap();
    let traces = run(&mut stores()[..], &sc, &MODES);
    let (full, plane, plain) = (traces[0].ate(), traces[1].ate(), traces[2].ate());
    println!("{kind:?} seed {seed}: ATE full {full:.4} m, plane-only {plane:.4} m, plain {plain:.4} m");
    let [ok, deg, imu, _, reinit] = traces[0].status_counts();
    assert!(full.is_finite() && full <= 0.10, "{kind:?}: full-mode ATE {full:.4} m exceeds 0.10 m");
    assert_eq!(reinit, 0, "{kind:?}: no re-initialisation on clean data");
    assert!(
        ok + deg > 9 * (ok + deg + imu) / 10,
        "{kind:?}: most scans must update ({ok} ok, {deg} degraded, {imu} imu-only)"
    );
    (full, plane)
}

/// Zero-velocity updates only where the platform truly stands (its true speed under 1 cm/s
/// and turn rate under 0.1 deg/s around the scan end), and at the stand before the run.
fn standstill_only_at_stands(sc: &Scenario, tr: &Trace) {
    let mut still = 0;
    for r in &tr.results {
        if !r.propagation.has(PropagationFlags::STILL) {
            continue;
        }
        let t = r.pose.t_ns;
        let (a, b) = (sc.pose_at(t.saturating_sub(50_000_000)), sc.pose_at(t + 50_000_000));
        let speed = (b.translation.vector - a.translation.vector).norm() / 0.1;
        let rate = (a.rotation.inverse() * b.rotation).angle() / 0.1;
        assert!(
            speed < 0.01 && rate < 0.1f64.to_radians(),
            "standing at {t} ns? {speed:.4} m/s, {rate:.5} rad/s"
        );
        still += 1;
    }
    println!("{}: {still} scans standing still", sc.config().kind.name());
    assert!(still > 0, "the stand at the start gives zero-velocity updates");
}

/// With the standstill updates on (`filter.standstill`, the default): they run at the stand
/// before the drive and never while the vehicle drives or the sensor spins in place, and the
/// errors stay those of the well-posed runs.
#[test]
fn standstill_updates_only_where_the_platform_stands() {
    let mut set = stores();
    for kind in [ScenarioKind::Vehicle, ScenarioKind::FastRotation] {
        let sc = scenario(kind, kind.default_duration_s());
        let guard = &mut set[0];
        let mut cfg = config_for(&sc, AssociationMode::Full);
        cfg.standstill.enabled = true;
        let mut odos = [guard.odometry(&cfg).unwrap()];
        let traces = run_lockstep(&sc, &mut odos, |e| vec![e]);
        println!("{} (standstill on)", summary(kind.name(), AssociationMode::Full, &traces[0]));
        let ate = traces[0].ate();
        assert!(ate.is_finite() && ate <= 0.10, "{kind:?}: ATE {ate:.4} m with the standstill updates");
        standstill_only_at_stands(&sc, &traces[0]);
    }
}

/// Full against plane-only by the mean of three seeds, as on the drone: on seed 7 alone they are
/// within what a handful of points changes (`loglio sim`, seed 7, at `1ef3c66`: full 5.31-5.72 mm
/// over the measurement budgets 4990-5010, plane-only 5.43 mm).
#[test]
fn vehicle_vlp32c() {
    well_posed_over(ScenarioKind::Vehicle, &[7, 1, 2]);
}

#[test]
fn handheld_indoors() {
    well_posed(ScenarioKind::Handheld);
}

/// The drone climbs 70 m out of a courtyard among 25-40 m towers: near the top only rooftops
/// (from ~100 m) and the ground (beyond ~150 m, the VLP-32C looks at most 25 deg down) are in
/// range, so the scans thin out from ~50,000 returns to a few hundred. There one seed's full
/// against plane-only is within what a handful of points changes (four variants of the
/// free-space tests that touched 16-26 points of 1.6 million gave full 0.0218-0.0240 m and
/// plane-only 0.0234-0.0262 m on seed 7), so the modes are compared by their mean over three
/// seeds.
#[test]
fn drone_into_open_sky() {
    well_posed_over(ScenarioKind::Drone, &[7, 1, 2]);
}

#[test]
fn fast_rotation() {
    well_posed(ScenarioKind::FastRotation);
}

/// The estimate expressed in the truth's frame, anchored at the first initialised pose (no
/// alignment: drift along the corridor must show, not be fitted away).
fn anchored_errors(tr: &Trace) -> Vec<(u64, Vector3<f64>)> {
    let mut anchor: Option<Isometry3<f64>> = None;
    let mut out = Vec::new();
    for (r, t) in tr.results.iter().zip(&tr.truth) {
        if matches!(r.status, Status::Initialising(_)) {
            continue;
        }
        let est = Isometry3::from_parts(r.pose.position.into(), r.pose.rotation);
        let a = *anchor.get_or_insert(t * est.inverse());
        out.push((r.pose.t_ns, (a * est).translation.vector - t.translation.vector));
    }
    out
}

/// Worst anchored errors (along the corridor, across it, vertical) of the LIO and of an IMU-only
/// run on the same data, and the LIO's status counts.
fn corridor_errors() -> ([f64; 3], [f64; 3], [usize; 5]) {
    let mut set = stores();
    let kind = ScenarioKind::Corridor;
    let sc = scenario(kind, kind.default_duration_s());
    // The scenario is generated once: the LIO gets every event; beside it the same filter
    // gets the same IMU samples and every scan emptied (its IMU-only propagation).
    let (mut lio, mut imu_only) = (Trace::default(), Trace::default());
    {
        let cfg = config_for(&sc, AssociationMode::Full);
        let [a, b, _] = &mut *set;
        let mut odos = [a.odometry(&cfg).unwrap(), b.odometry(&cfg).unwrap()];
        let mut clock = StdClock::default();
        for ev in sc.events() {
            match ev {
                Event::Imu(s) => odos.iter_mut().for_each(|o| {
                    o.push_imu(s);
                }),
                Event::Scan(scan) => {
                    let inputs: [(&mut Trace, &[ScanPoint]); 2] =
                        [(&mut lio, &scan.points), (&mut imu_only, &[])];
                    for (o, (tr, points)) in odos.iter_mut().zip(inputs) {
                        let r =
                            o.process_scan_timed(ScanView { start_ns: scan.start_ns, points }, &mut clock);
                        tr.truth.push(sc.pose_at(r.pose.t_ns));
                        tr.results.push(r);
                    }
                }
            }
        }
    }
    println!("{}", summary(kind.name(), AssociationMode::Full, &lio));
    println!("{} (IMU only)", summary(kind.name(), AssociationMode::Full, &imu_only));

    let counts = lio.status_counts();
    println!("corridor: (ok, degraded, imu-only, init, reinit) = {counts:?}");

    // The corridor's axis: the direction of travel, start to end.
    let p0 = sc.pose_at(lio.results[0].pose.t_ns).translation.vector;
    let p1 = sc.pose_at(lio.results.last().unwrap().pose.t_ns).translation.vector;
    let axis = Vector3::new(p1.x - p0.x, p1.y - p0.y, 0.0).normalize();
    let side = Vector3::z().cross(&axis);

    let e_lio = anchored_errors(&lio);
    let e_imu = anchored_errors(&imu_only);
    let worst_of = |e: &[(u64, Vector3<f64>)]| {
        let mut w = [0.0f64; 3];
        for (_, a) in e {
            for (k, d) in [axis, side, Vector3::z()].iter().enumerate() {
                w[k] = w[k].max(a.dot(d).abs());
            }
        }
        w
    };
    let (worst, worst_imu) = (worst_of(&e_lio), worst_of(&e_imu));
    let last = e_lio.last().unwrap().1;
    println!(
        "corridor: worst error along / across / vertical: LIO {:.3} / {:.3} / {:.3} m, IMU only {:.3} / {:.3} / {:.3} m; \
         final along-axis {:.3} m over {:.0} m",
        worst[0],
        worst[1],
        worst[2],
        worst_imu[0],
        worst_imu[1],
        worst_imu[2],
        last.dot(&axis),
        (p1 - p0).norm()
    );
    (worst, worst_imu, counts)
}

/// 40 s down a corridor with no feature along its axis. The status must report the degenerate
/// axis, the filter must neither diverge nor restart, the walls, floor and ceiling must hold the
/// vehicle across the corridor and vertically (centimetres, where IMU-only drifts by metres),
/// and along the axis the error must stay within what IMU integration alone gives on the same
/// data (an IMU-only run, whose attitude the scans do not hold, is the bound), and within half
/// of it since the standstill updates hold the stand at the start (2026-12-07, seed 7: 2.65 m
/// against 8.57 m IMU-only; 5.30 m with the stand left to the scans and the exact k-NN). Before
/// the plane-normal check of the association (`plane_max_normal_angle_deg`) the scans pinned
/// the vehicle to the ring pattern of the map built at rest: 146 m behind after the 151 m drive.
#[test]
fn corridor_degenerate_axis_left_to_the_imu() {
    let (worst, worst_imu, [ok, deg, imu, _, reinit]) = corridor_errors();
    assert_eq!(reinit, 0, "no re-initialisation");
    assert!(
        deg > 8 * (ok + deg + imu) / 10,
        "the axis must be reported degenerate ({deg} of {})",
        ok + deg + imu
    );
    assert!(worst.iter().all(|w| w.is_finite()), "no divergence");
    assert!(worst[1] < 0.10 && worst[2] < 0.10, "across {:.3} m, vertical {:.3} m", worst[1], worst[2]);
    assert!(worst_imu[1] > worst[1], "the scans must beat the IMU across the corridor");
    assert!(
        worst[0] <= 0.5 * worst_imu[0],
        "along the axis: {:.3} m, IMU-only {:.3} m: the scans must not drag the vehicle, and the stand \
         must hold the accelerometer bias",
        worst[0],
        worst_imu[0]
    );
}

/// Map points more than 0.3 m above the ground, put in the simulator's world with the first
/// estimated and true poses: (inside the actors' swept volumes over the run, elsewhere).
fn map_points_in_and_out_of_the_traffic<const PIX: usize, const PTS: usize, const DS: usize>(
    sc: &Scenario,
    odo: &Odometry<'_, PIX, PTS, DS>,
    tr: &Trace,
) -> (usize, usize) {
    let i = tr.results.iter().position(|r| !matches!(r.status, Status::Initialising(_))).unwrap();
    let p = &tr.results[i].pose;
    let est = Isometry3::from_parts(p.position.into(), p.rotation);
    let t_w = tr.truth[i] * est.inverse();
    let (t0, t1) = (sc.start_ns(), sc.end_ns());
    let (mut inside, mut outside) = (0, 0);
    odo.map().for_each_point(|_, xyz, _| {
        let q = t_w * nalgebra::Point3::new(f64::from(xyz[0]), f64::from(xyz[1]), f64::from(xyz[2]));
        if q.z < sc.world().ground_height(q.x, q.y) + 0.3 {
            return;
        }
        if sc.inside_actor_swept([q.x, q.y, q.z], t0, t1).is_some() {
            inside += 1;
        } else {
            outside += 1;
        }
    });
    (inside, outside)
}

/// Moving traffic costs at most a fifth of the error of the same drive in an empty street
/// (issue 31): the full 60 s of `traffic`, seeds 1-3, with the actors and without. What is left
/// of the ratio is the static world the actors hide, not their points: a perfect removal (the
/// simulator's rays return nothing where they meet an actor) gave the same ratio over ten seeds
/// (1.16 against loglio's 1.17, three seeds over 1.2 each way; docs/voxel-map.md), so the ratio
/// is asserted on the seeds' mean, and per seed only against a gross failure.
#[test]
fn traffic_costs_at_most_a_fifth_of_the_empty_streets_error() {
    let mut set = stores();
    let mut ratios = Vec::new();
    for seed in [1, 2, 3] {
        let mut ates = [0.0f64; 2];
        for (i, actors) in [true, false].into_iter().enumerate() {
            let mut c = ScenarioConfig::new(ScenarioKind::Traffic, SensorModel::Vlp32c, seed);
            c.actors = actors;
            let sc = Scenario::from_config(c).unwrap();
            let mut odos = [set[i].odometry(&config_for(&sc, AssociationMode::Full)).unwrap()];
            let traces = run_lockstep(&sc, &mut odos, |e| vec![e]);
            ates[i] = traces[0].ate();
        }
        let ratio = ates[0] / ates[1];
        println!(
            "traffic seed {seed}: ATE {:.4} m with actors, {:.4} m without: {ratio:.3}x",
            ates[0], ates[1]
        );
        assert!(ates[0] < 0.01 && ratio < 1.5, "seed {seed}: {:.4} m against {:.4} m", ates[0], ates[1]);
        ratios.push(ratio);
    }
    let mean = ratios.iter().sum::<f64>() / ratios.len() as f64;
    println!("traffic against the empty street: mean ratio {mean:.3}");
    assert!(mean <= 1.2, "mean ratio {mean:.3} over seeds 1-3 ({ratios:?})");
}

/// Moving actors leave no ghost trails: the first 35 s of `traffic` (the truck ahead pulling
/// away, oncoming cars, the wait at the junction with cross traffic and pedestrians) run with the
/// free-space tests (the map clears what the scans see through, moving points are left out) and
/// without. Most of the points left where the actors drove go, the static world stays, and the
/// trajectory is as good.
#[test]
fn moving_actors_leave_no_ghost_trails_in_the_map() {
    let mut set = stores();
    let mut c = ScenarioConfig::new(ScenarioKind::Traffic, SensorModel::Vlp32c, 1);
    c.duration_s = 35.0;
    let sc = Scenario::from_config(c).unwrap();
    let clear = config_for(&sc, AssociationMode::Full);
    let mut keep = clear.clone();
    keep.free_space.enabled = false;
    let mut odos: Vec<Odometry<'_, _, _, _>> =
        set.iter_mut().zip([&clear, &keep]).map(|(g, cfg)| g.odometry(cfg).unwrap()).collect();
    let traces = run_lockstep(&sc, &mut odos, |e| vec![e]);
    let (ghosts, statics) = map_points_in_and_out_of_the_traffic(&sc, &odos[0], &traces[0]);
    let (ghosts_kept, statics_kept) = map_points_in_and_out_of_the_traffic(&sc, &odos[1], &traces[1]);
    let (ate, ate_kept) = (traces[0].ate(), traces[1].ate());
    let (cleared, moving) = (odos[0].stats().cleared, odos[0].stats().moving);
    println!(
        "traffic 35 s: {moving} moving points left out, {cleared} voxels cleared; map points in the actors' swept volumes {ghosts} (kept: \
         {ghosts_kept}), elsewhere {statics} (kept: {statics_kept}); ATE {ate:.4} m (kept: {ate_kept:.4} m)"
    );
    assert_eq!((odos[1].stats().cleared, odos[1].stats().moving), (0, 0));
    assert!(cleared > 0 && moving > 0);
    assert!(ghosts_kept > 1000, "the actors leave trails without clearing: {ghosts_kept}");
    assert!(2 * ghosts <= ghosts_kept, "at least half the trail points go: {ghosts} of {ghosts_kept}");
    assert!(
        statics as f64 >= 0.97 * statics_kept as f64,
        "the static world stays: {statics} of {statics_kept}"
    );
    assert!(ate <= 1.1 * ate_kept && ate < 0.02, "ATE {ate:.4} m with clearing, {ate_kept:.4} m without");
}
