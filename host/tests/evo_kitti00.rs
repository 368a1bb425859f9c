//! `loglio eval` against evo 1.38.1 on evo's KITTI-00 pair (ground truth and an ORB-SLAM2
//! estimate, 4,541 poses): every statistic must agree to 1e-6. The reference numbers are in
//! `tests/data/trajectories-kitti00-evo/SOURCE.md` (the six-decimal ones shipped with the data,
//! and the full-precision ones computed here with evo).

use std::path::PathBuf;

use loglio_host::eval::{
    Alignment, DeltaUnit, EvalOptions, Format, Stats, Trajectory, evaluate, read_trajectory,
};

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/data/trajectories-kitti00-evo").join(name)
}

fn load() -> (Trajectory, Trajectory) {
    let gt = read_trajectory(&data("KITTI_00_gt.txt"), Format::Kitti, None).unwrap();
    let est = read_trajectory(&data("KITTI_00_ORB.txt"), Format::Kitti, None).unwrap();
    (gt, est)
}

/// rmse, mean, median, std, min, max, n from evo.
type Ref = [f64; 7];

fn check(what: &str, got: &Stats, want: Ref) {
    let g = [got.rmse, got.mean, got.median, got.std, got.min, got.max, got.n as f64];
    let names = ["rmse", "mean", "median", "std", "min", "max", "n"];
    for k in 0..7 {
        let d = (g[k] - want[k]).abs();
        println!("{what:<34} {:<6} loglio {:<22} evo {:<22} |diff| {d:.1e}", names[k], g[k], want[k]);
        assert!(d <= 1e-6, "{what} {}: loglio {} vs evo {}", names[k], g[k], want[k]);
    }
}

fn opts(align: Alignment, delta: f64, unit: DeltaUnit, all_pairs: bool) -> EvalOptions {
    EvalOptions { align, rpe_delta: delta, rpe_unit: unit, all_pairs, ..Default::default() }
}

#[test]
fn ape_matches_evo() {
    let (gt, est) = load();
    let none = evaluate(&gt, &est, &opts(Alignment::None, 1.0, DeltaUnit::Frames, false)).unwrap();
    check(
        "APE trans, no alignment",
        &none.ape_trans,
        [
            7.790288882656827,
            7.01175040166684,
            6.801631674560281,
            3.3946954473076767,
            4.000000055511189e-09,
            13.45850880738189,
            4541.0,
        ],
    );
    // The numbers shipped with the data (six decimals).
    for (g, w) in
        [(none.ape_trans.rmse, 7.790289), (none.ape_trans.mean, 7.011750), (none.ape_trans.max, 13.458509)]
    {
        assert!((g - w).abs() <= 1e-6, "{g} vs {w}");
    }
    let se3 = evaluate(&gt, &est, &opts(Alignment::Se3, 1.0, DeltaUnit::Frames, false)).unwrap();
    check(
        "APE trans, SE(3)",
        &se3.ape_trans,
        [
            1.3034497145650337,
            1.1569971285389835,
            1.0656247695557912,
            0.600282269396835,
            0.06931322021482282,
            3.587949120678975,
            4541.0,
        ],
    );
    let s = &se3.ape_trans;
    for (g, w) in [
        (s.rmse, 1.303450),
        (s.mean, 1.156997),
        (s.median, 1.065625),
        (s.std, 0.600282),
        (s.min, 0.069313),
        (s.max, 3.587949),
    ] {
        assert!((g - w).abs() <= 1e-6, "{g} vs {w}");
    }
    check(
        "APE rot (deg), SE(3)",
        &se3.ape_rot_deg,
        [
            0.7563005166348642,
            0.6165164105423996,
            0.52789136412974,
            0.4380616246535158,
            0.11281953643426093,
            6.752584453656365,
            4541.0,
        ],
    );
    let sim3 = evaluate(&gt, &est, &opts(Alignment::Sim3, 1.0, DeltaUnit::Frames, false)).unwrap();
    check(
        "APE trans, Sim(3)",
        &sim3.ape_trans,
        [
            0.9377090736114023,
            0.8726926319693107,
            0.8446910134864141,
            0.34308290082665355,
            0.17951466687998655,
            2.693499863613383,
            4541.0,
        ],
    );
}

#[test]
fn rpe_matches_evo() {
    let (gt, est) = load();
    let f1 = evaluate(&gt, &est, &opts(Alignment::None, 1.0, DeltaUnit::Frames, false)).unwrap();
    check(
        "RPE trans, 1 frame",
        &f1.rpe_trans,
        [
            0.02812037701739386,
            0.019301310981393958,
            0.01470904343858892,
            0.020450305572286533,
            0.00031240026309761656,
            0.30271249059536337,
            4540.0,
        ],
    );
    for (g, w) in [(f1.rpe_trans.rmse, 0.028120), (f1.rpe_trans.mean, 0.019301), (f1.rpe_trans.max, 0.302712)]
    {
        assert!((g - w).abs() <= 1e-6, "{g} vs {w}");
    }
    check(
        "RPE rot (deg), 1 frame",
        &f1.rpe_rot_deg,
        [
            0.11497352125979224,
            0.05958345492311408,
            0.04107440527533871,
            0.09832966231153815,
            0.002243553775880668,
            2.196615406942415,
            4540.0,
        ],
    );
    let m100 = evaluate(&gt, &est, &opts(Alignment::None, 100.0, DeltaUnit::Metres, true)).unwrap();
    check(
        "RPE trans, 100 m all pairs",
        &m100.rpe_trans,
        [
            1.2548299616430865,
            1.0146945009089312,
            0.9003863828486766,
            0.7382366168528658,
            0.1254677848316807,
            11.815064774902076,
            4457.0,
        ],
    );
    for (g, w) in
        [(m100.rpe_trans.rmse, 1.254830), (m100.rpe_trans.mean, 1.014695), (m100.rpe_trans.max, 11.815065)]
    {
        assert!((g - w).abs() <= 1e-6, "{g} vs {w}");
    }
    check(
        "RPE rot (deg), 100 m all pairs",
        &m100.rpe_rot_deg,
        [
            0.8969429007336782,
            0.6300025341098227,
            0.5346641377203215,
            0.638438230521753,
            0.00526233036143914,
            7.228795125910481,
            4457.0,
        ],
    );
    // Pairs chosen on the ground truth instead (evo --pairs_from_reference).
    let m100r = evaluate(
        &gt,
        &est,
        &EvalOptions { pairs_from_gt: true, ..opts(Alignment::None, 100.0, DeltaUnit::Metres, true) },
    )
    .unwrap();
    check(
        "RPE trans, 100 m all pairs, on gt",
        &m100r.rpe_trans,
        [
            1.2509260050965094,
            1.0106943684497247,
            0.8994733465261422,
            0.7370975266616517,
            0.1254677848316807,
            11.83379107372921,
            4458.0,
        ],
    );
    let m100c = evaluate(&gt, &est, &opts(Alignment::None, 100.0, DeltaUnit::Metres, false)).unwrap();
    check(
        "RPE trans, 100 m consecutive",
        &m100c.rpe_trans,
        [
            1.1939759245846355,
            1.054477825715355,
            0.9214941902754695,
            0.5600491260258809,
            0.27590912938463125,
            2.959637959978665,
            36.0,
        ],
    );
    let f10 = evaluate(&gt, &est, &opts(Alignment::None, 10.0, DeltaUnit::Frames, true)).unwrap();
    check(
        "RPE trans, 10 frames all pairs",
        &f10.rpe_trans,
        [
            0.18934823038597612,
            0.13978226849548528,
            0.11321949169175895,
            0.12772497705835284,
            0.004600557887213407,
            1.5153832705472317,
            4531.0,
        ],
    );
}

#[test]
fn kitti_with_times_files_associates_by_time() {
    let times = data("KITTI_00_gt_times.txt");
    let gt = read_trajectory(&data("KITTI_00_gt.txt"), Format::Kitti, Some(&times)).unwrap();
    let est = read_trajectory(&data("KITTI_00_ORB.txt"), Format::Kitti, Some(&times)).unwrap();
    let rep = evaluate(&gt, &est, &EvalOptions::default()).unwrap();
    assert_eq!(rep.matched, 4541);
    assert!((rep.ape_trans.rmse - 1.3034497145650337).abs() <= 1e-6);
}
