//! The `loglio` binary: every failure is one `error: ...` line on stderr with a non-zero exit,
//! never a panic message or a backtrace (whatever RUST_BACKTRACE says); successes print what
//! they should.

use std::path::Path;
use std::process::Output;

use loglio_host::config::{Config, Preset};

mod common;

fn loglio(args: &[&str]) -> Output {
    loglio_env(args, &[])
}

/// Runs the binary ([`common::loglio_command`]: through `LOGLIO_TEST_RUNNER` when set) with
/// `env` added.
fn loglio_env(args: &[&str], env: &[(&str, &str)]) -> Output {
    let bin = env!("CARGO_BIN_EXE_loglio");
    let mut c = common::loglio_command(args);
    for (k, v) in env {
        c.env(k, v);
    }
    match c.output() {
        Ok(o) => o,
        Err(e) if e.raw_os_error() == Some(8) => {
            panic!(
                "cannot execute {bin} on this machine ({e}); set LOGLIO_TEST_RUNNER to the target's runner, e.g. \"qemu-aarch64 -L /usr/aarch64-linux-gnu\""
            )
        }
        Err(e) => panic!("cannot run {bin}: {e}"),
    }
}

/// Asserts a failure with exactly this one stderr line and exit code.
fn fails(out: &Output, code: i32, line: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(code), "stderr: {err}");
    assert_eq!(err, format!("{line}\n"));
    assert!(!err.contains("panicked") && !err.contains("stack backtrace"));
}

/// Asserts a failure whose one stderr line starts with `prefix`.
fn fails_with(out: &Output, code: i32, prefix: &str) -> String {
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert_eq!(out.status.code(), Some(code), "stderr: {err}");
    assert_eq!(err.lines().count(), 1, "one line: {err}");
    assert!(err.starts_with(prefix), "{err}");
    assert!(!err.contains("panicked") && !err.contains("stack backtrace"));
    err
}

fn stdout(out: &Output) -> String {
    assert!(out.status.success(), "stderr: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout.clone()).unwrap()
}

fn scratch(name: &str) -> common::Scratch {
    common::scratch("cli", name)
}

fn data(rel: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/data").join(rel).display().to_string()
}

#[test]
fn config_template_prints_and_parses_back() {
    for p in Preset::ALL {
        let text = stdout(&loglio(&["config", "--preset", p.name()]));
        assert_eq!(Config::from_toml_str(&text).unwrap(), Config::preset(p));
    }
    let list = stdout(&loglio(&["config", "--list"]));
    assert_eq!(list.lines().count(), 7);
}

#[test]
fn config_errors_are_one_line() {
    fails(
        &loglio(&["config", "--preset", "vlp64"]),
        1,
        "error: unknown preset \"vlp64\" (known: vlp16, vlp32c, hdl32e, os1-16, os1-32, os1-64, os1-128)",
    );
    let d = scratch("config");
    let bad = d.join("bad.toml");
    std::fs::write(&bad, "preset = \"vlp32c\"\n[mapping]\nvoxel_size = -0.4\n").unwrap();
    fails(
        &loglio(&["config", "--check", bad.to_str().unwrap()]),
        1,
        "error: config: mapping.voxel_size = -0.4 is out of range (0.05..=5.0 m)",
    );
    std::fs::write(&bad, "preset = \"vlp32c\"\n[imu]\ngyro_nois = 0.1\n").unwrap();
    let e = fails_with(
        &loglio(&["config", "--check", bad.to_str().unwrap()]),
        1,
        "error: config: unknown key imu.gyro_nois (keys of [imu]: ",
    );
    assert!(e.contains("gyro_noise"));
    std::fs::write(&bad, "preset = \"vlp32c\"\n[imu\n").unwrap();
    fails_with(
        &loglio(&["config", "--check", bad.to_str().unwrap()]),
        1,
        &format!("error: config: {}: line 2, column", bad.display()),
    );
    fails_with(
        &loglio(&["config", "--check", "/nonexistent/x.toml"]),
        1,
        "error: config: cannot read /nonexistent/x.toml: ",
    );
    // A valid file prints the resolved configuration.
    let good = d.join("good.toml");
    std::fs::write(&good, "preset = \"os1-64\"\n[mapping]\nvoxel_size = 0.3\n").unwrap();
    let text = stdout(&loglio(&["config", "--check", good.to_str().unwrap()]));
    assert_eq!(Config::from_toml_str(&text).unwrap().mapping.voxel_size, 0.3);
    // extrinsics.file is read beside the configuration and checked.
    let with_file = d.join("with-file.toml");
    std::fs::write(&with_file, "preset = \"vlp32c\"\n[extrinsics]\nfile = \"velodyne.yaml\"\n").unwrap();
    fails_with(
        &loglio(&["config", "--check", with_file.to_str().unwrap()]),
        1,
        &format!("error: extrinsic file {}: ", d.join("velodyne.yaml").display()),
    );
    let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/data/fast-lio/velodyne.yaml");
    std::fs::copy(fixture, d.join("velodyne.yaml")).unwrap();
    let out = loglio(&["config", "--check", with_file.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(out.status.success(), "{err}");
    assert_eq!(
        err.trim_end(),
        format!(
            "{}: valid (preset vlp32c; extrinsic from {}: t = [-0.0500, 0.0000, 0.2800] m, q wxyz = [0.7071, 0.0000, 0.0000, 0.7071])",
            with_file.display(),
            d.join("velodyne.yaml").display()
        )
    );
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn usage_errors_are_one_line_with_exit_code_2() {
    fails(&loglio(&[]), 2, "error: no subcommand given; see 'loglio --help'");
    fails(&loglio(&["frobnicate"]), 2, "error: unrecognized subcommand 'frobnicate'; see 'loglio --help'");
    fails_with(&loglio(&["eval"]), 2, "error: the following required arguments were not provided:");
    fails_with(
        &loglio(&["eval", "a", "b", "--align", "affine"]),
        2,
        "error: invalid value 'affine' for '--align <ALIGN>'",
    );
    fails_with(&loglio(&["config"]), 2, "error: the following required arguments were not provided:");
    assert!(stdout(&loglio(&["--help"])).contains("eval"));
    assert!(stdout(&loglio(&["--version"])).starts_with("loglio "));
}

#[test]
fn eval_reports_and_plots_and_bad_files_are_one_line() {
    let d = scratch("eval");
    let gt = data("trajectories-kitti00-evo/KITTI_00_gt.txt");
    let est = data("trajectories-kitti00-evo/KITTI_00_ORB.txt");
    let prefix = d.join("k00");
    let out = stdout(&loglio(&[
        "eval",
        "--format",
        "kitti",
        &gt,
        &est,
        "--json",
        "--plot",
        prefix.to_str().unwrap(),
    ]));
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let rmse = v["ape_trans_m"]["rmse"].as_f64().unwrap();
    assert!((rmse - 1.3034497145650337).abs() < 1e-6, "{rmse}");
    assert_eq!(v["matched"], 4541);
    for f in ["k00_trajectory.png", "k00_trajectory.svg", "k00_ape.png", "k00_ape.svg"] {
        assert!(std::fs::metadata(d.join(f)).unwrap().len() > 1000, "{f}");
    }
    let table = stdout(&loglio(&["eval", "--format", "kitti", &gt, &est, "--align", "none"]));
    assert!(table.contains("APE translation (m)          7.790289"), "{table}");
    // The KITTI files without --format: the error says which flag reads them.
    fails(
        &loglio(&["eval", &gt, &est]),
        1,
        &format!(
            "error: {gt} line 1: expected 8 numbers (t tx ty tz qx qy qz qw), found 12; this looks like a KITTI pose file (row-major 3x4 [R|t]): use `--format kitti`"
        ),
    );
    // Bad TUM files.
    let bad = d.join("est.txt");
    std::fs::write(&bad, "0 1 2 3 0 0 0 1\n1 1 2 3 0 0 1\n").unwrap();
    let good = d.join("gt.txt");
    std::fs::write(&good, "0 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 1\n2 1 2 4 0 0 0 1\n").unwrap();
    let (g, b) = (good.to_str().unwrap(), bad.to_str().unwrap());
    fails(
        &loglio(&["eval", g, b]),
        1,
        &format!("error: {} line 2: expected 8 numbers (t tx ty tz qx qy qz qw), found 7", bad.display()),
    );
    std::fs::write(&bad, "5 1 2 3 0 0 0 1\n4 1 2 3 0 0 0 1\n").unwrap();
    fails(
        &loglio(&["eval", g, b]),
        1,
        &format!("error: {} line 2: timestamp 4 does not increase (previous 5)", bad.display()),
    );
    std::fs::write(&bad, "100 1 2 3 0 0 0 1\n101 1 2 3 0 0 0 1\n").unwrap();
    fails(
        &loglio(&["eval", g, b]),
        1,
        "error: no matching timestamps within 0.01 s: ground truth spans 0.000..2.000 s, estimate 100.000..101.000 s (after offset 0 s)",
    );
    std::fs::write(&bad, "0 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 1\n2 1 2 4 0 0 0 1\n").unwrap();
    // Positions on a line leave the rotation about it open: it comes from the orientations.
    let line = loglio(&["eval", g, b]);
    assert!(line.status.success(), "{}", String::from_utf8_lossy(&line.stderr));
    assert!(String::from_utf8_lossy(&line.stdout).contains("the positions lie on a line"));
    fails_with(&loglio(&["eval", g, "/nonexistent.txt"]), 1, "error: cannot read /nonexistent.txt: ");
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn bag_info_lists_topics_and_bad_bags_are_one_line() {
    let out =
        stdout(&loglio(&["bag-info", &data("ouster-sdk/512x10_raw.bag"), "--preset", "os1-64", "--read"]));
    assert!(out.contains("reads: LiDAR /os_node0/lidar_packets (Ouster packets), IMU /os_node0/imu_packets, metadata /os_node0/metadata"));
    assert!(out.contains("43 messages: 0 scans, 0 IMU samples, 42 packets"));
    let d = scratch("bags");
    let bytes = std::fs::read(data("ouster-sdk/512x10_raw.bag")).unwrap();
    let cut = d.join("cut.bag");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    fails_with(
        &loglio(&["bag-info", cut.to_str().unwrap()]),
        1,
        // Its one chunk is in the lost half: nothing can be recovered without the index.
        &format!("error: {}: cut short or corrupt (its index starts at byte", cut.display()),
    );
    fails(
        &loglio(&["bag-info", &data("ouster-sdk/512x10_raw.bag"), "--lidar-topic", "/points"]),
        1,
        &format!(
            "error: {}: no topic /points; the bag has /os_node0/imu_packets (ouster_ros/PacketMsg), /os_node0/lidar_packets (ouster_ros/PacketMsg), /os_node0/metadata (std_msgs/String)",
            data("ouster-sdk/512x10_raw.bag")
        ),
    );
    fails(
        &loglio(&["bag-info", &data("ouster-sdk/512x10_raw.bag"), "--preset", "os2"]),
        1,
        "error: unknown preset \"os2\" (known: vlp16, vlp32c, hdl32e, os1-16, os1-32, os1-64, os1-128)",
    );
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn a_bug_is_one_line_too() {
    let out = loglio_env(&["config", "--list"], &[("LOGLIO_TEST_INTERNAL_PANIC", "1")]);
    fails_with(&out, 101, "error: internal error: deliberate panic for the tests with a second line at ");
}
