//! The commands that run the odometry: `demo`, `sim`, `bench`, `replay`, `bag`: what they
//! print and write, their accuracy against exact ground truth, and their one-line errors.
//!
//! The accuracy assertions need the real odometry (issue 7, branch `odom`, merged here): with
//! the propagation-only skeleton no scan is ever `ok` and the map stays empty.

use std::path::Path;
use std::process::Output;

mod common;
use common::{extrinsic_config, number_after};

fn loglio(args: &[&str]) -> Output {
    common::loglio_command(args).output().unwrap_or_else(|e| panic!("cannot run loglio: {e}"))
}

fn stdout(out: &Output) -> String {
    assert!(out.status.success(), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout.clone()).unwrap()
}

/// Asserts a failure whose one stderr line starts with `prefix`.
fn fails_with(out: &Output, prefix: &str) -> String {
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(!out.status.success(), "should fail: {err}");
    assert_eq!(err.lines().count(), 1, "one line: {err}");
    assert!(err.starts_with(prefix), "{err}");
    assert!(!err.contains("panicked") && !err.contains("stack backtrace"));
    err
}

fn scratch(name: &str) -> common::Scratch {
    common::scratch("run", name)
}

/// The count of scans with `status` in the summary's "N scans (a ok, b imu-only, ...)".
/// Under an emulating runner (CI's aarch64 job under qemu-user) the long simulated runs take
/// minutes each; they are said skipped (the short `sim` tests still run there).
fn emulated(test: &str, what: &str) -> bool {
    match common::runner() {
        Some(r) => {
            println!("{test}: skipped under LOGLIO_TEST_RUNNER ({r}): {what}; run natively");
            true
        }
        None => false,
    }
}

fn status_count(text: &str, status: &str) -> u64 {
    let open = text.find(" scans (").expect("scan summary") + " scans (".len();
    let close = open + text[open..].find(')').unwrap();
    text[open..close]
        .split(", ")
        .filter_map(|part| part.split_once(' '))
        .find(|(_, s)| *s == status)
        .map_or(0, |(n, _)| n.parse().unwrap())
}

fn tum_poses(p: &Path) -> Vec<[f64; 8]> {
    std::fs::read_to_string(p)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            v.try_into().unwrap()
        })
        .collect()
}

fn ply_vertices(p: &Path) -> usize {
    let bytes = std::fs::read(p).unwrap();
    let head = String::from_utf8_lossy(&bytes[..bytes.len().min(400)]).to_string();
    number_after(&head, "element vertex") as usize
}

#[test]
fn demo_writes_every_output_and_tracks_the_ground_truth() {
    let dir = scratch("demo");
    let out = loglio(&["demo", "--seconds", "6", "--out", dir.to_str().unwrap()]);
    let text = stdout(&out);
    // 6 s at 10 Hz: 60 scans; the IMU initialises within the 2 s at rest.
    assert!(text.contains("scenario vehicle (6 s, vlp32c, seed 1): 60 scans"), "{text}");
    let ate = number_after(&text, "rmse");
    assert!(ate.is_finite() && ate <= 0.10, "ATE {ate} m: {text}");
    for f in [
        "trajectory.tum",
        "groundtruth.tum",
        "scans.csv",
        "map.ply",
        "map.pcd",
        "trajectory.png",
        "trajectory.svg",
        "error.png",
        "error.svg",
        "eval.json",
    ] {
        let p = dir.join(f);
        assert!(p.metadata().is_ok_and(|m| m.len() > 0), "{} missing or empty", p.display());
    }
    // The trajectory: one pose per scan after the initialisation, at the scan ends, 0.1 s apart.
    let est = tum_poses(&dir.join("trajectory.tum"));
    let gt = tum_poses(&dir.join("groundtruth.tum"));
    assert_eq!(est.len(), gt.len());
    assert!(est.len() >= 48, "{} poses", est.len());
    for w in est.windows(2) {
        assert!((w[1][0] - w[0][0] - 0.1).abs() < 2e-3, "stamps {} {}", w[0][0], w[1][0]);
    }
    // Position error without alignment: the world frames agree up to yaw at start (both
    // gravity-aligned, both start at the IMU's rest pose), so the first pose matches closely
    // and the car's drive (tens of metres) is followed.
    let travelled =
        ((gt.last().unwrap()[1] - gt[0][1]).powi(2) + (gt.last().unwrap()[2] - gt[0][2]).powi(2)).sqrt();
    assert!(travelled > 5.0, "the car moved {travelled} m");
    // The per-scan CSV: a header and one row per scan; after the initialisation the scans
    // update the state (status ok or degraded), not the IMU alone.
    let csv = std::fs::read_to_string(dir.join("scans.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().skip(1).collect();
    assert_eq!(rows.len(), 60);
    let tracked = rows.iter().filter(|r| r.contains(",ok,") || r.contains(",degraded,")).count();
    assert!(tracked >= 45, "{tracked} of 60 scans updated by the LiDAR");
    // The map holds the town's surfaces seen over 6 s.
    assert!(ply_vertices(&dir.join("map.ply")) > 5_000);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Runs `loglio sim` for `seconds` (seed 3) and checks its summary: `scans` scans, an ATE of at
/// most `max_ate` m and at least `min_tracked` scans updated by the LiDAR.
fn sim_tracks(scenario: &str, sensor: &str, seconds: u32, scans: usize, max_ate: f64, min_tracked: u64) {
    let secs = seconds.to_string();
    let out = loglio(&["sim", "--scenario", scenario, "--sensor", sensor, "--seconds", &secs, "--seed", "3"]);
    let text = stdout(&out);
    assert!(
        text.contains(&format!("scenario {scenario} ({seconds} s, {sensor}, seed 3): {scans} scans")),
        "{text}"
    );
    let ate = number_after(&text, "rmse");
    assert!(ate <= max_ate, "ATE {ate} m: {text}");
    let tracked = status_count(&text, "ok") + status_count(&text, "degraded");
    assert!(tracked >= min_tracked, "scans updated by the LiDAR: {text}");
}

#[test]
fn sim_handheld_ouster_accuracy() {
    sim_tracks("handheld", "os1-16", 6, 60, 0.10, 45);
}

/// The OS1-128 (131,072 pixels a scan at 1024 x 10) runs on the class for 128 rows. Measured
/// (seed 1): handheld 20 s ATE 0.002 m. 4 s here (2 of them at rest), short enough for qemu-user.
#[test]
fn sim_os1_128_tracks() {
    sim_tracks("handheld", "os1-128", 4, 40, 0.01, 25);
}

/// The HDL-32E at 10 Hz has 2,170 columns, more than the 2,048 the host once allowed: it runs
/// on the next storage class. 4 s (2 s of them at rest): short enough for the aarch64 run
/// under qemu-user.
#[test]
fn sim_hdl32e_runs_on_a_wider_image() {
    sim_tracks("vehicle", "hdl32e", 4, 39, 0.02, 25);
}

/// `loglio sim --scenario traffic --out` writes the actors' ground truth beside the ego's;
/// `--no-actors` runs the same drive without them and writes none.
#[test]
fn sim_traffic_writes_the_actors_ground_truth() {
    for bare in [false, true] {
        let dir = scratch(if bare { "traffic-bare" } else { "traffic" });
        let d = dir.to_str().unwrap();
        let mut args = vec!["sim", "--scenario", "traffic", "--seconds", "4", "--out", d];
        if bare {
            args.push("--no-actors");
        }
        let text = stdout(&loglio(&args));
        assert!(text.contains("scenario traffic (4 s, vlp32c, seed 1)"), "{text}");
        assert!(number_after(&text, "rmse") < 0.02, "{text}");
        assert!(dir.join("groundtruth.tum").exists());
        let csv = dir.join("actors.csv");
        assert_eq!(csv.exists(), !bare, "{text}");
        if bare {
            continue;
        }
        assert!(text.contains("actors.csv"), "{text}");
        let csv = std::fs::read_to_string(&csv).unwrap();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(lines[0], "t_ns,t_s,id,kind,x,y,z,yaw,length,width,height,vx,vy,vz");
        // 41 stamps at 10 Hz; in the first 4 s exist the truck, two oncoming cars and five
        // pedestrians.
        assert_eq!(lines.len(), 1 + 41 * 8);
        assert!(lines[1].starts_with("1714565400000000000,0.000,0,truck,"), "{}", lines[1]);
        assert!(lines.last().unwrap().starts_with("1714565404000000000,4.000,12,pedestrian,"));
    }
}

/// An IMU on a clock of its own, 20 ms ahead of the LiDAR's (a sensor-realism switch of the
/// simulator): kept as stamped (`--fixed-offset`), the error grows; `time.lidar_imu_offset =
/// -0.02` (here `--lidar-imu-offset`) puts the stamps back exactly, and the trajectory is the
/// one-clock run's, bit for bit.
#[test]
fn sim_imu_clock_offset_and_its_compensation() {
    let run = |name: &str, extra: &[&str]| {
        let dir = scratch(name);
        let d = dir.to_str().unwrap().to_string();
        let mut args = vec!["sim", "--scenario", "vehicle", "--seconds", "10", "--out", &d];
        args.extend_from_slice(extra);
        let text = stdout(&loglio(&args));
        (number_after(&text, "rmse"), std::fs::read_to_string(dir.join("trajectory.tum")).unwrap())
    };
    let (one_clock, tum) = run("clock-one", &[]);
    let (late, _) = run("clock-late", &["--imu-clock-offset-ms", "20", "--fixed-offset"]);
    let (fixed, tum_fixed) =
        run("clock-fixed", &["--imu-clock-offset-ms", "20", "--lidar-imu-offset", "-0.02"]);
    assert_eq!(tum, tum_fixed, "the compensated run is the one-clock run");
    assert_eq!(fixed, one_clock);
    assert!(late > 1.3 * one_clock, "20 ms off: {late} m against {one_clock} m");
    fails_with(
        &loglio(&["sim", "--imu-clock-offset-ms", "5000"]),
        "error: --imu-clock-offset-ms must be within",
    );
}

/// The same 20 ms with nothing said about it: the scans' warp tells the offset
/// (`time.estimate_offset`, on by default), it is applied to the IMU stamps, and the error is
/// near the one-clock run's: only the first scans, before the estimate is certain, are bent.
/// Measured (handheld, 20 s, 2026-11-28, under the measurement budget): -19.82 ms applied; ATE
/// 3.94 mm against 3.04 mm on one clock (1.30x) and 7.81 mm with the offset kept (1.98x the
/// estimated). The bounds hold the spread over seeds: seeds 2 and 3 give 1.47x / 1.15x one clock
/// and 1.94x / 2.42x below the offset kept. The ATEs are read from `eval.json` (the
/// summary's three decimals of a metre cannot tell 1.15x from 1.3x at 3 mm).
#[test]
fn sim_imu_clock_offset_is_estimated_from_the_scans() {
    if emulated("sim_imu_clock_offset_is_estimated_from_the_scans", "three 20 s runs") {
        return;
    }
    let dir = scratch("offset-estimated");
    let run = |extra: &[&str]| {
        let mut args =
            vec!["sim", "--scenario", "handheld", "--seconds", "20", "--out", dir.to_str().unwrap()];
        args.extend_from_slice(extra);
        let text = stdout(&loglio(&args));
        let eval = std::fs::read_to_string(dir.join("eval.json")).unwrap();
        let v: serde_json::Value = serde_json::from_str(&eval).unwrap();
        (text, v["ape_trans_m"]["rmse"].as_f64().unwrap())
    };
    let (_, one_clock) = run(&[]);
    let (_, kept) = run(&["--imu-clock-offset-ms", "20", "--fixed-offset"]);
    let (text, estimated) = run(&["--imu-clock-offset-ms", "20"]);
    let line = text.lines().find(|l| l.starts_with("IMU–LiDAR time offset:")).expect(&text);
    let applied: f64 = line
        .split("; ")
        .nth(1)
        .and_then(|p| p.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{line}"));
    assert!((applied + 20.0).abs() < 1.0, "{line}");
    // Moving the stamps 20 ms earlier puts the next few samples before queued ones: said.
    let dropped = number_after(line, "applied to the IMU stamps (");
    assert!((1.0..=8.0).contains(&dropped), "{line}");
    assert!(
        line.ends_with("IMU samples dropped: a change put them before samples already queued)"),
        "{line}"
    );
    assert!(kept > 2.0 * one_clock, "20 ms kept: {kept} m against {one_clock} m");
    assert!(estimated < 1.6 * one_clock, "estimated: {estimated} m against {one_clock} m\n{text}");
    assert!(1.7 * estimated < kept, "estimated: {estimated} m against {kept} m kept\n{text}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Sensor-realism switches: a gyro that clips at 125 deg/s while the platform spins at up to
/// 180 deg/s (a third of the samples at the full scale), and scans at 20 Hz. The clipped
/// samples are counted and said; the filter takes the scans' own rate on the clipped axes and
/// trusts its attitude less, so that the run stays tracked. Measured (seed 1): fast rotation
/// clipped 0.014 m over 20 s (over 30 s 0.014 m, where the filter that did not know the full
/// scale lost 50 scans and ended at 1.63 m; 0.003 m unclipped); vehicle at 20 Hz 0.003 m over
/// 400 scans (0.004 m at 10 Hz).
#[test]
fn sim_saturated_gyro_and_20_hz_scans() {
    if emulated("sim_saturated_gyro_and_20_hz_scans", "two 20 s runs") {
        return;
    }
    let run = |extra: &[&str]| {
        let mut args = vec!["sim", "--seconds", "20"];
        args.extend_from_slice(extra);
        stdout(&loglio(&args))
    };
    let text = run(&["--scenario", "rotation", "--imu-gyro-full-scale", "125"]);
    let saturated = number_after(&text, "faults: ");
    assert!(saturated > 1000.0, "{text}");
    assert!(text.contains(" saturated IMU samples"), "{text}");
    assert!(!text.contains(" lost") && !text.contains("re-initialising"), "{text}");
    let ate = number_after(&text, "rmse");
    assert!(ate < 0.03, "clipped gyro: ATE {ate} m\n{text}");

    let text = run(&["--scenario", "vehicle", "--scan-rate-hz", "20"]);
    assert!(text.contains("(20 s, vlp32c, seed 1): 400 scans ("), "{text}");
    assert!(text.contains("(scan period 50 ms / mean)"), "{text}");
    let ate = number_after(&text, "rmse");
    assert!(ate < 0.006, "20 Hz: ATE {ate} m\n{text}");

    fails_with(&loglio(&["sim", "--imu-gyro-full-scale", "300"]), "error: --imu-gyro-full-scale: 125, 250");
    fails_with(
        &loglio(&["sim", "--scan-rate-hz", "40"]),
        "error: --scan-rate-hz: a Velodyne turns at 5 to 20 Hz",
    );
    fails_with(
        &loglio(&["sim", "--sensor", "os1-16", "--scan-rate-hz", "15"]),
        "error: --scan-rate-hz: an Ouster scans at 10 or 20 Hz",
    );
}

/// The `long` drive (3.2 km around a 3.1 km loop, back past its start) holds the map inside
/// its fixed pool by evicting what is far behind, keeps its time per scan, and drifts little per
/// 100 m. Measured (seed 1, 2026-11-28): 2,619 scans, ATE 0.044 m, drift 0.011 m per 100 m (max
/// 0.125 m), 3.39 M voxels created of which 3.02 M evicted far and 131,072 from the full pool,
/// 239,353 of 262,144 held at the end; 15.1 then 14.9 ms per scan. Not under qemu-user (2,619
/// emulated scans).
#[test]
fn sim_long_drive_stays_in_its_pool_and_drifts_little() {
    if let Some(r) = common::runner() {
        println!(
            "sim_long_drive_stays_in_its_pool_and_drifts_little: skipped under LOGLIO_TEST_RUNNER ({r}): 2,619 emulated scans; run natively"
        );
        return;
    }
    let text = stdout(&loglio(&["sim", "--scenario", "long"]));
    assert!(text.contains("scenario long (262 s, vlp32c, seed 1): 2619 scans ("), "{text}");
    let tracked = status_count(&text, "ok") + status_count(&text, "degraded");
    assert!(tracked >= 2600, "{text}");
    assert!(!text.contains(" lost") && !text.contains("re-initialising"), "{text}");
    let ate = number_after(&text, "rmse");
    assert!(ate < 0.1, "ATE {ate} m\n{text}");
    let driven = number_after(&text, "drift per 100 m of the ");
    assert!((3150.0..3300.0).contains(&driven), "{text}");
    let drift = number_after(&text, " m driven: ");
    assert!(drift < 0.03, "drift {drift} m per 100 m\n{text}");
    // The map: never more than its pool, and it had to evict to get there.
    let voxels = number_after(&text, "map: ");
    let pool = number_after(&text, "voxels of a fixed pool of ");
    assert!(voxels <= pool && voxels > 0.5 * pool, "{text}");
    let far = number_after(&text, " created, ");
    assert!(far > pool, "the drive must evict what it left behind: {text}");
    assert!(!text.contains("points dropped with the pool full"), "{text}");
    assert!(text.contains("time per scan over the run: "), "{text}");
}

#[test]
fn sim_and_demo_bad_arguments_are_one_line() {
    fails_with(&loglio(&["sim", "--scenario", "moon"]), "error: unknown scenario \"moon\" (known: vehicle,");
    fails_with(&loglio(&["sim", "--sensor", "os2-128"]), "error: unknown simulated sensor \"os2-128\"");
    fails_with(&loglio(&["sim", "--seconds", "0"]), "error: --seconds must be in (0, 600]");
    fails_with(&loglio(&["demo", "--seconds", "1"]), "error: --seconds must be in (2.5, 600]");
    // An output directory that cannot be created: one line naming it.
    let dir = scratch("demo-bad-out");
    let file = dir.join("a-file");
    std::fs::write(&file, b"x").unwrap();
    let err = fails_with(
        &loglio(&["demo", "--seconds", "3", "--out", file.join("sub").to_str().unwrap()]),
        "error: ",
    );
    assert!(err.contains("a-file"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A short simulated drive written as files (pcap, IMU CSV and serial capture, ground
/// truth) and a configuration with the simulator's extrinsic.
fn sim_files(name: &str, sensor: loglio_firmware_sim::lidar::SensorModel, seconds: f64) -> common::Scratch {
    use loglio_firmware_sim::scenario::{Scenario, ScenarioConfig, ScenarioKind};
    let dir = scratch(name);
    let mut c = ScenarioConfig::new(ScenarioKind::Vehicle, sensor, 5);
    c.duration_s = seconds;
    let sc = Scenario::from_config(c).unwrap();
    loglio_firmware_sim::files::write_all(&sc, &dir.join("sim")).unwrap();
    std::fs::write(dir.join("config.toml"), extrinsic_config(sensor.name(), &sc.extrinsic())).unwrap();
    dir
}

#[test]
fn replay_pcap_with_imu_csv_or_serial_capture() {
    // A VLP-32C: on the simulated VLP-16 drives the odometry itself (direct scans, no packets)
    // does not hold yet (ATE 0.56-0.67 m, reported to issue 7), so it cannot test the replay.
    let dir = sim_files("replay", loglio_firmware_sim::lidar::SensorModel::Vlp32c, 4.0);
    let p = |f: &str| dir.join(f).to_str().unwrap().to_string();
    let (mut trajectories, mut tracked) = (Vec::new(), Vec::new());
    for imu in ["sim/imu.csv", "sim/imu.bin"] {
        let out = dir.join(format!("out-{}", imu.replace(['/', '.'], "-")));
        let text = stdout(&loglio(&[
            "replay",
            &p("sim/lidar.pcap"),
            "--imu",
            &p(imu),
            "--config",
            &p("config.toml"),
            "--gt",
            &p("sim/groundtruth.tum"),
            "--out",
            out.to_str().unwrap(),
        ]));
        // 4 s at 10 Hz: 40 whole turns plus the partial first and last ones.
        let scans = number_after(&text, "LiDAR packets\n") as u64;
        assert!((40..=41).contains(&scans), "{text}");
        let ate = number_after(&text, "rmse");
        assert!(ate <= 0.10, "ATE {ate} m: {text}");
        tracked.push((status_count(&text, "ok") + status_count(&text, "degraded"), text.clone()));
        for f in
            ["trajectory.tum", "scans.csv", "map.ply", "map.pcd", "trajectory.png", "error.svg", "eval.json"]
        {
            assert!(out.join(f).metadata().is_ok_and(|m| m.len() > 0), "{f} missing: {text}");
        }
        trajectories.push(std::fs::read_to_string(out.join("trajectory.tum")).unwrap());
    }
    // The CSV holds the serial frames' values: both IMU inputs give the same trajectory.
    assert_eq!(trajectories[0], trajectories[1]);
    // After the initialisation the scans update the state (needs the odometry of issue 7).
    for (n, text) in tracked {
        assert!(n >= 25, "scans updated by the LiDAR: {text}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The extrinsic from a FAST-LIO / LOG-LIO YAML (`--extrinsic FILE`): the run says so and
/// tracks exactly as with the same extrinsic in the configuration; without any (the identity,
/// with a warning) the trajectory moves by centimetres and the ATE grows.
#[test]
fn replay_takes_the_extrinsic_from_a_fast_lio_yaml() {
    use loglio_firmware_sim::lidar::SensorModel;
    let dir = sim_files("replay-extrinsic", SensorModel::Vlp32c, 4.0);
    let p = |f: &str| dir.join(f).to_str().unwrap().to_string();
    // The scenario's true extrinsic, as FAST-LIO's config/velodyne.yaml writes it.
    let mut c = loglio_firmware_sim::scenario::ScenarioConfig::new(
        loglio_firmware_sim::scenario::ScenarioKind::Vehicle,
        SensorModel::Vlp32c,
        5,
    );
    c.duration_s = 4.0;
    let e = loglio_firmware_sim::scenario::Scenario::from_config(c).unwrap().extrinsic();
    let r = e.rotation.to_rotation_matrix();
    let m = r.matrix();
    let t = e.translation.vector;
    std::fs::write(
        dir.join("velodyne.yaml"),
        format!(
            "common:\n    lid_topic:  \"/velodyne_points\"   # the driver's topic\n\nmapping:\n    extrinsic_est_en:  false\n    \
             extrinsic_T: [ {}, {}, {}]\n    extrinsic_R: [ {}, {}, {},\n                   {}, {}, {},\n                   {}, {}, {}]\n",
            t.x, t.y, t.z, m[(0, 0)], m[(0, 1)], m[(0, 2)], m[(1, 0)], m[(1, 1)], m[(1, 2)], m[(2, 0)], m[(2, 1)], m[(2, 2)]
        ),
    )
    .unwrap();
    let run = |how: &[&str], out: &str| {
        let (pcap, imu, gt, out) = (p("sim/lidar.pcap"), p("sim/imu.csv"), p("sim/groundtruth.tum"), p(out));
        let mut args = vec!["replay", pcap.as_str(), "--imu", &imu, "--gt", &gt, "--out", &out, "--no-map"];
        args.extend_from_slice(how);
        let o = loglio(&args);
        (stdout(&o), String::from_utf8_lossy(&o.stderr).to_string())
    };
    let yaml = p("velodyne.yaml");
    let (from_file, err) = run(&["--preset", "vlp32c", "--extrinsic", &yaml], "out-file");
    assert!(err.is_empty(), "{err}");
    let first = from_file.lines().next().unwrap();
    assert!(first.starts_with(&format!("extrinsic from --extrinsic {yaml}: t = [0.0800, -0.0400, 0.0500] m, q wxyz = [0.9998, 0.0045, -0.0086, 0.0175]")), "{from_file}");
    let config = p("config.toml");
    let (from_config, _) = run(&["--config", &config], "out-config");
    assert!(
        from_config.starts_with(&format!(
            "extrinsic from [extrinsics] of {config}: t = [0.0800, -0.0400, 0.0500] m"
        )),
        "{from_config}"
    );
    let (identity, err) = run(&["--preset", "vlp32c"], "out-identity");
    assert!(err.starts_with("warning: no LiDAR-IMU extrinsic given"), "{err}");
    assert!(!identity.contains("extrinsic from"), "{identity}");
    // The file's extrinsic is the configuration's: the same trajectory, to rounding. The
    // identity puts the IMU ~10 cm off the LiDAR: the IMU frame's trajectory moves by cm
    // (4.4 cm; the SE(3)-aligned ATE grows less, 1.52 to 1.69 mm, in these 4 s).
    let positions = |out: &str| -> Vec<[f64; 3]> {
        tum_poses(&dir.join(out).join("trajectory.tum")).iter().map(|p| [p[1], p[2], p[3]]).collect()
    };
    let most_apart = |a: &[[f64; 3]], b: &[[f64; 3]]| {
        assert_eq!(a.len(), b.len());
        a.iter().zip(b).flat_map(|(x, y)| (0..3).map(move |k| (x[k] - y[k]).abs())).fold(0.0, f64::max)
    };
    let (file, config, none) = (positions("out-file"), positions("out-config"), positions("out-identity"));
    assert!(most_apart(&file, &config) < 1e-9, "{} m", most_apart(&file, &config));
    assert!(most_apart(&file, &none) > 0.01, "{} m", most_apart(&file, &none));
    let ate = |out: &str| {
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join(out).join("eval.json")).unwrap()).unwrap();
        v["ape_trans_m"]["rmse"].as_f64().unwrap()
    };
    let (ate_file, ate_config, ate_none) = (ate("out-file"), ate("out-config"), ate("out-identity"));
    assert!((ate_file - ate_config).abs() < 1e-9, "file {ate_file} m, configuration {ate_config} m");
    assert!(ate_file <= 0.01 && ate_none > ate_file, "file {ate_file} m, identity {ate_none} m");
    let _ = std::fs::remove_dir_all(&dir);
}

/// An Ouster pcap holds the sensor's own IMU packets as well. With `--ouster-imu` they are the
/// IMU; with `--imu FILE` the file is, and the packets are counted but not mixed into it (they
/// were: 1,200 samples from two IMUs, 404 of them dropped as out of order).
#[test]
fn replay_ouster_takes_one_imu() {
    let dir = sim_files("replay-ouster", loglio_firmware_sim::lidar::SensorModel::Os1_16, 4.0);
    let p = |f: &str| dir.join(f).to_str().unwrap().to_string();
    let run = |imu: &[&str]| {
        let out = p(&format!("out{}", imu.len()));
        let (pcap, meta) = (p("sim/lidar.pcap"), p("sim/ouster_metadata.json"));
        let (cfg, gt) = (p("config.toml"), p("sim/groundtruth.tum"));
        let mut args = vec!["replay", pcap.as_str()];
        args.extend_from_slice(imu);
        args.extend_from_slice(&["--metadata", &meta, "--config", &cfg, "--gt", &gt, "--out", &out]);
        stdout(&loglio(&args))
    };
    let packets = run(&["--ouster-imu"]);
    assert!(packets.contains("2560 LiDAR packets, 400 IMU packets\n"), "{packets}");
    assert!(packets.contains("41 scans") && packets.contains(", 400 IMU samples;"), "{packets}");
    let csv = p("sim/imu.csv");
    let file = run(&["--imu", &csv]);
    assert!(
        file.contains("2560 LiDAR packets, 400 IMU packets (not used: the IMU comes from a file)\n"),
        "{file}"
    );
    assert!(file.contains(", 800 IMU samples;") && !file.contains("dropped"), "{file}");
    for text in [&packets, &file] {
        let ate = number_after(text, "rmse");
        assert!(ate <= 0.10, "ATE {ate} m: {text}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Without an IMU a pcap replays LiDAR-only (constant-velocity model) with one warning instead
/// of an error, and `sim --no-imu` leaves the simulated IMU out; both say so in the summary and
/// track the ground truth.
#[test]
fn replay_and_sim_without_imu_run_lidar_only() {
    let dir = sim_files("replay-no-imu", loglio_firmware_sim::lidar::SensorModel::Vlp32c, 4.0);
    let p = |f: &str| dir.join(f).to_str().unwrap().to_string();
    let out = loglio(&[
        "replay",
        &p("sim/lidar.pcap"),
        "--config",
        &p("config.toml"),
        "--gt",
        &p("sim/groundtruth.tum"),
        "--out",
        &p("out"),
    ]);
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert_eq!(err.lines().count(), 1, "one warning: {err}");
    assert!(
        err.starts_with("warning: no IMU for the replay (--imu FILE, --ouster-imu): LiDAR-only (no IMU)"),
        "{err}"
    );
    let text = stdout(&out);
    assert!(
        text.starts_with("LiDAR-only (no IMU): constant-velocity model\n")
            || text.contains("\nLiDAR-only (no IMU): constant-velocity model\n"),
        "{text}"
    );
    assert!(text.contains(", 0 IMU samples"), "{text}");
    let ate = number_after(&text, "rmse");
    assert!(ate <= 0.10, "ATE {ate} m: {text}");
    assert!(status_count(&text, "ok") + status_count(&text, "degraded") >= 35, "{text}");
    let eval = std::fs::read_to_string(dir.join("out/eval.json")).unwrap();
    assert!(eval.starts_with("{\"motion_model\": \"lidar-only (no IMU): constant velocity\", "), "{eval}");
    let _ = std::fs::remove_dir_all(&dir);

    let dir = scratch("sim-no-imu");
    let o = dir.to_str().unwrap();
    let text = stdout(&loglio(&[
        "sim",
        "--scenario",
        "handheld",
        "--sensor",
        "os1-16",
        "--seconds",
        "8",
        "--no-imu",
        "--out",
        o,
    ]));
    assert!(text.starts_with("LiDAR-only (no IMU): constant-velocity model\n"), "{text}");
    assert!(text.contains(", 0 IMU samples\n"), "{text}");
    assert_eq!(status_count(&text, "initialising") + status_count(&text, "re-initialising"), 0, "{text}");
    let ate = number_after(&text, "rmse");
    assert!(ate <= 0.05, "ATE {ate} m: {text}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn replay_bad_input_is_one_line() {
    let dir = sim_files("replay-bad", loglio_firmware_sim::lidar::SensorModel::Vlp16, 3.0);
    let p = |f: &str| dir.join(f).to_str().unwrap().to_string();
    let out = p("out");
    // Unknown preset.
    let e =
        fails_with(&loglio(&["replay", &p("sim/lidar.pcap"), "--preset", "vlp64", "--out", &out]), "error: ");
    assert!(e.contains("unknown preset \"vlp64\" (known: vlp16,"), "{e}");
    // Not a pcap.
    let e = fails_with(
        &loglio(&[
            "replay",
            &p("config.toml"),
            "--imu",
            &p("sim/imu.csv"),
            "--config",
            &p("config.toml"),
            "--out",
            &out,
        ]),
        "error: ",
    );
    assert!(e.contains("config.toml"), "{e}");
    // A truncated pcap: the packets before the cut are replayed, with one warning.
    let bytes = std::fs::read(dir.join("sim/lidar.pcap")).unwrap();
    std::fs::write(dir.join("cut.pcap"), &bytes[..bytes.len() * 2 / 3 + 7]).unwrap();
    let o = loglio(&[
        "replay",
        &p("cut.pcap"),
        "--imu",
        &p("sim/imu.csv"),
        "--config",
        &p("config.toml"),
        "--out",
        &out,
    ]);
    let text = stdout(&o);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.lines().all(|l| l.starts_with("warning: ")) && err.contains("truncated"), "{err}");
    let scans = number_after(&text, "LiDAR packets\n");
    assert!((18.0..=21.0).contains(&scans), "{text}");
    // IMU and LiDAR that do not overlap: the IMU 1000 s later.
    let csv = std::fs::read_to_string(dir.join("sim/imu.csv")).unwrap();
    let shifted: String = csv
        .lines()
        .map(|l| match l.split_once(',') {
            Some((t, rest)) if t.parse::<f64>().is_ok() => {
                format!("{:.9},{rest}\n", t.parse::<f64>().unwrap() + 1000.0)
            }
            _ => format!("{l}\n"),
        })
        .collect();
    std::fs::write(dir.join("late.csv"), shifted).unwrap();
    let e = fails_with(
        &loglio(&[
            "replay",
            &p("sim/lidar.pcap"),
            "--imu",
            &p("late.csv"),
            "--config",
            &p("config.toml"),
            "--out",
            &out,
        ]),
        "error: LiDAR and IMU streams do not overlap in time",
    );
    assert!(e.contains("offset of"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bench_json_parses_and_is_consistent() {
    let text = stdout(&loglio(&["bench", "--preset", "os1-16", "--seconds", "3", "--json"]));
    let v: serde_json::Value = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{e}: {text}"));
    assert_eq!(v["preset"], "os1-16");
    assert_eq!(v["scenario"], "handheld"); // the Ouster presets' default
    assert_eq!(v["scan_period_ms"], 100.0);
    assert_eq!(v["knn_search"], "block");
    assert!(v["points_per_scan"].as_f64().unwrap() > 5_000.0, "{text}");
    for (key, mode) in [("main", "full"), ("baseline", "plain")] {
        let m = &v[key];
        assert_eq!(m["mode"], mode);
        // 3 s at 10 Hz, the first ~1 s spent initialising: 15-25 timed scans.
        let scans = m["scans"].as_u64().unwrap();
        assert!((15..=25).contains(&scans), "{text}");
        let mean = m["scan_ms"]["mean"].as_f64().unwrap();
        let median = m["scan_ms"]["median"].as_f64().unwrap();
        let p95 = m["scan_ms"]["p95"].as_f64().unwrap();
        assert!(mean > 0.0 && median > 0.0 && p95 >= median, "{text}");
        // The stages are parts of the scan's time.
        let stages: f64 = m["stage_mean_ms"].as_object().unwrap().values().map(|x| x.as_f64().unwrap()).sum();
        assert_eq!(m["stage_mean_ms"].as_object().unwrap().len(), 6);
        assert!(stages <= mean * 1.0001, "stages {stages} ms > scan {mean} ms");
        let margin = m["realtime_margin"].as_f64().unwrap();
        assert!((margin - 100.0 / mean).abs() <= 1e-9 * margin, "{text}");
    }
    let ratio = v["main_over_baseline"].as_f64().unwrap();
    let means = [&v["main"], &v["baseline"]].map(|m| m["scan_ms"]["mean"].as_f64().unwrap());
    assert!((ratio - means[0] / means[1]).abs() < 1e-9 * ratio);
    assert_eq!(v["keeps_up"], v["main"]["realtime_margin"].as_f64().unwrap() >= 1.0);
    // The human form names the scenario, the k-NN when not the default and the verdict.
    let text = stdout(&loglio(&[
        "bench",
        "--preset",
        "vlp16",
        "--seconds",
        "3",
        "--scenario",
        "rotation",
        "--knn-search",
        "exact",
    ]));
    assert!(text.contains("simulated rotation scenario"), "{text}");
    assert!(text.contains("k-NN: exact within the 27 voxels"), "{text}");
    assert!(text.contains("this computer keeps up") || text.contains("does NOT keep up"), "{text}");
    assert!(text.contains("margin"), "{text}");
}

#[test]
fn bench_bad_presets_are_one_line() {
    fails_with(&loglio(&["bench", "--preset", "vlp64"]), "error: unknown preset \"vlp64\" (known: vlp16,");
    fails_with(&loglio(&["bench", "--preset", "os1-32"]), "error: the simulator has no os1-32 model");
    fails_with(&loglio(&["bench", "--seconds", "1"]), "error: --seconds must be in [3, 120]");
    fails_with(
        &loglio(&["bench", "--scenario", "moon"]),
        "error: unknown scenario \"moon\" (known: vehicle,",
    );
}
