//! The core as Cortex-M firmware: the poses `loglio-fw` computes under QEMU (mps2-an386,
//! Cortex-M4F) are bit-identical to the host's on the same recording.
//!
//! 1. Records 3 s of the handheld scenario with an OS1-16 in 512 x 10 mode (the 2 s rest for
//!    the IMU initialisation included) in the replay format.
//! 2. Runs the firmware configuration over it on the host (same reader, same storage type).
//! 3. Builds `loglio-fw` for `thumbv7em-none-eabihf` (profile `firmware`), runs it under
//!    `qemu-system-arm -M mps2-an386 -icount shift=0 -semihosting`, and compares every pose line
//!    (the f64 bits in hex) with the host's.
//!
//! If `qemu-system-arm` or the Rust target is missing the firmware part prints a loud SKIPPED
//! notice and passes, unless `LOGLIO_REQUIRE_QEMU=1` (set by `.ci/run` after installing them).
//! The instruction counts per scan (SysTick under `-icount`) are printed (`--nocapture`).

use std::io::Read as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use loglio_core::output::Status;
use loglio_core::scan::{ScanPoint, ScanView};
use loglio_firmware_sim::firmware_recording::{self, FW_POINTS, FirmwareStorage, Reader, Record};
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::lidar::ouster::LidarMode;
use loglio_firmware_sim::scenario::{LidarConfig, Scenario, ScenarioConfig, ScenarioKind};

const TARGET: &str = "thumbv7em-none-eabihf";
/// SysTick ticks per instruction under `-icount shift=0` on mps2-an386: 1 ns per instruction,
/// SysTick on the 25 MHz core clock.
const INSNS_PER_TICK: u64 = 40;

/// The host's odometry memory: the firmware's storage type, in `.bss` here too.
static HOST: Mutex<FirmwareStorage> = Mutex::new(FirmwareStorage::new());

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

fn record(path: &Path) -> (Scenario, firmware_recording::RecordingStats) {
    let mut cfg = ScenarioConfig::new(ScenarioKind::Handheld, SensorModel::Os1_16, 11);
    cfg.duration_s = 3.0;
    if let LidarConfig::Ouster(o) = &mut cfg.lidar {
        o.mode = LidarMode::M512x10;
    }
    let sc = Scenario::from_config(cfg).unwrap();
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let (_, stats) = firmware_recording::record_scenario(&sc, file).unwrap();
    (sc, stats)
}

struct HostRun {
    lines: Vec<String>,
    /// (scan end ns, position) of every scan after initialisation.
    positions: Vec<(u64, [f64; 3])>,
    statuses: Vec<Status>,
}

fn run_host(bytes: &[u8]) -> HostRun {
    let (mut reader, header) = Reader::new(bytes).unwrap();
    let cfg = firmware_recording::firmware_config(&header);
    let mut storage = HOST.lock().unwrap();
    let mut odo = storage.odometry(&cfg).unwrap();
    let mut points = vec![ScanPoint::default(); FW_POINTS];
    let mut run = HostRun { lines: Vec::new(), positions: Vec::new(), statuses: Vec::new() };
    loop {
        match reader.next_record(&mut points).unwrap() {
            Record::Imu(s) => {
                odo.push_imu(s);
            }
            Record::Scan { start_ns, points: n } => {
                let r = odo.process_scan(ScanView { start_ns, points: &points[..n] });
                let mut line = String::new();
                firmware_recording::write_pose_line(&mut line, run.lines.len() as u32, &r).unwrap();
                run.lines.push(line);
                if !matches!(r.status, Status::Initialising(_)) {
                    let p = r.pose.position;
                    run.positions.push((r.pose.t_ns, [p.x, p.y, p.z]));
                }
                run.statuses.push(r.status);
            }
            Record::End => break,
        }
    }
    run
}

/// Prints an unmissable notice, or fails if QEMU is required.
fn skip(why: &str) {
    if std::env::var("LOGLIO_REQUIRE_QEMU").is_ok_and(|v| v == "1") {
        panic!("LOGLIO_REQUIRE_QEMU=1 but {why}");
    }
    eprintln!("\n!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!");
    eprintln!("!!! SKIPPED: firmware under QEMU: {why}");
    eprintln!("!!! (the host half of this test ran; set LOGLIO_REQUIRE_QEMU=1 to make this an error)");
    eprintln!("!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!!\n");
}

fn target_installed() -> bool {
    let rustc = std::env::var("RUSTC").unwrap_or_else(|_| "rustc".into());
    let Ok(out) = Command::new(rustc).args(["--print", "sysroot"]).output() else { return false };
    let sysroot = String::from_utf8_lossy(&out.stdout).trim().to_string();
    Path::new(&sysroot).join("lib/rustlib").join(TARGET).join("lib").is_dir()
}

fn qemu_available() -> bool {
    Command::new("qemu-system-arm")
        .arg("--version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok()
}

/// Builds the firmware; returns the ELF path.
fn build_firmware() -> PathBuf {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let t0 = Instant::now();
    let out = Command::new(cargo)
        .current_dir(workspace())
        .args(["build", "-p", "loglio-firmware-sim", "--bin", "loglio-fw", "--profile", "firmware"])
        .args(["--target", TARGET, "--message-format", "json-render-diagnostics"])
        .stderr(Stdio::inherit())
        .output()
        .expect("cargo runs");
    assert!(out.status.success(), "firmware build failed");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let exe = stdout
        .lines()
        .filter(|l| l.contains("\"reason\":\"compiler-artifact\"") && l.contains("\"loglio-fw\""))
        .find_map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).ok()?;
            v["executable"].as_str().map(PathBuf::from)
        })
        .expect("cargo reports the firmware executable");
    eprintln!("firmware built in {:.1} s: {}", t0.elapsed().as_secs_f64(), exe.display());
    exe
}

/// Runs the firmware under QEMU with a wall-clock limit; returns (exit code, stdout, stderr).
fn run_qemu(elf: &Path, recording: &Path, limit: Duration) -> (Option<i32>, String, String) {
    let mut child = Command::new("qemu-system-arm")
        .args(["-M", "mps2-an386", "-cpu", "cortex-m4", "-nographic", "-monitor", "none", "-serial", "none"])
        .args(["-icount", "shift=0", "-semihosting-config", "enable=on,target=native", "-kernel"])
        .arg(elf)
        .arg("-append")
        .arg(recording)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("qemu starts");
    let mut stdout = child.stdout.take().unwrap();
    let mut stderr = child.stderr.take().unwrap();
    let out_thread = std::thread::spawn(move || {
        let mut s = String::new();
        stdout.read_to_string(&mut s).map(|_| s).unwrap_or_default()
    });
    let err_thread = std::thread::spawn(move || {
        let mut s = String::new();
        stderr.read_to_string(&mut s).map(|_| s).unwrap_or_default()
    });
    let t0 = Instant::now();
    let code = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st.code();
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("QEMU ran past {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    eprintln!("QEMU ran {:.1} s", t0.elapsed().as_secs_f64());
    (code, out_thread.join().unwrap(), err_thread.join().unwrap())
}

#[test]
fn firmware_poses_are_bit_identical_to_the_host() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR"));
    let recording = dir.join(format!("loglio-fw-replay-{}.bin", std::process::id()));
    let t0 = Instant::now();
    let (sc, stats) = record(&recording);
    eprintln!(
        "recorded {} scans ({} points, largest {}), {} IMU samples in {:.1} s",
        stats.scans,
        stats.points,
        stats.max_points,
        stats.imu,
        t0.elapsed().as_secs_f64()
    );
    assert!(stats.max_points <= FW_POINTS);
    let bytes = std::fs::read(&recording).unwrap();

    // The host run.
    let host = run_host(&bytes);
    assert_eq!(host.lines.len(), stats.scans);
    assert!(stats.scans >= 28, "{} scans", stats.scans);
    // The filter initialises during the 2 s rest, and the estimate follows the walk: the
    // distance travelled since initialisation matches the ground truth's.
    let first =
        host.statuses.iter().position(|s| !matches!(s, Status::Initialising(_))).expect("initialised");
    assert!(first <= 20, "initialised only at scan {first}");
    let (t_a, p_a) = host.positions[0];
    let (t_b, p_b) = *host.positions.last().unwrap();
    let est = ((p_b[0] - p_a[0]).powi(2) + (p_b[1] - p_a[1]).powi(2) + (p_b[2] - p_a[2]).powi(2)).sqrt();
    let gt = (sc.pose_at(t_b).translation.vector - sc.pose_at(t_a).translation.vector).norm();
    eprintln!("distance since initialisation: estimate {est:.3} m, ground truth {gt:.3} m");
    assert!(gt > 0.1, "the sequence must move ({gt} m)");
    assert!((est - gt).abs() < 0.05 + 0.1 * gt, "estimate {est} m vs ground truth {gt} m");

    // The firmware run.
    if !qemu_available() {
        skip("qemu-system-arm is not installed (Debian: apt-get install qemu-system-arm)");
        return;
    }
    if !target_installed() {
        skip(
            "the Rust target thumbv7em-none-eabihf is not installed (rustup target add thumbv7em-none-eabihf)",
        );
        return;
    }
    let elf = build_firmware();
    let (code, out, err) = run_qemu(&elf, &recording, Duration::from_secs(300));
    let _ = std::fs::remove_file(&recording);
    assert_eq!(code, Some(0), "firmware failed (exit {code:?})\nstdout:\n{out}\nstderr:\n{err}");
    let fw_lines: Vec<&str> = out.lines().filter(|l| l.starts_with("pose ")).collect();
    assert_eq!(fw_lines.len(), host.lines.len(), "scan count differs\nfirmware output:\n{out}");
    for (i, (fw, h)) in fw_lines.iter().zip(&host.lines).enumerate() {
        assert_eq!(*fw, h.as_str(), "scan {i}: firmware and host poses differ");
    }
    let done = out.lines().find(|l| l.starts_with("done ")).expect("done line");
    assert!(done.starts_with(&format!("done scans={} imu={}", stats.scans, stats.imu)), "{done}");

    // Instruction budget per scan (deterministic under -icount).
    let mut insns: Vec<(usize, u64)> = out
        .lines()
        .filter_map(|l| {
            let mut it = l.strip_prefix("ticks ")?.split(' ');
            let scan: usize = it.next()?.parse().ok()?;
            let ticks: u64 = it.next()?.parse().ok()?;
            Some((scan, ticks * INSNS_PER_TICK))
        })
        .collect();
    assert_eq!(insns.len(), stats.scans);
    let tracking: Vec<u64> = insns.iter().filter(|(s, _)| *s > first).map(|&(_, n)| n).collect();
    insns.sort_by_key(|&(_, n)| n);
    let mut sorted = tracking.clone();
    sorted.sort_unstable();
    if let (Some(&max), false) = (sorted.last(), sorted.is_empty()) {
        let median = sorted[sorted.len() / 2];
        eprintln!(
            "instructions per scan after initialisation (Cortex-M4F, {} scans): median {median}, max {max} \
             (= {:.1} ms / {:.1} ms at 480 MHz and 1 instruction per cycle)",
            sorted.len(),
            median as f64 / 480e3,
            max as f64 / 480e3
        );
    }
    eprintln!("{}", out.lines().next().unwrap_or(""));
    // The comparison covers scans the LiDAR update corrected, not only IMU propagation.
    let updated = host.statuses.iter().filter(|s| matches!(s, Status::Ok | Status::Degraded { .. })).count();
    eprintln!("scans updated by the LiDAR: {updated} of {}", host.statuses.len());
    assert!(updated >= 10, "only {updated} scans were updated by the LiDAR");
}

/// The static pool is checked against `memory.x` by the linker: with a map pool of 2^17 voxels
/// (24 MiB, feature `oversized-pool`) the firmware does not link.
#[test]
fn an_oversized_pool_fails_the_link() {
    if !target_installed() {
        skip(
            "the Rust target thumbv7em-none-eabihf is not installed (rustup target add thumbv7em-none-eabihf)",
        );
        return;
    }
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .current_dir(workspace())
        .args(["build", "-p", "loglio-firmware-sim", "--bin", "loglio-fw", "--profile", "firmware"])
        .args(["--target", TARGET, "--features", "oversized-pool"])
        .output()
        .expect("cargo runs");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "an oversized pool linked");
    assert!(
        stderr.contains("will not fit in region 'RAM'"),
        "the link must fail on the RAM region:\n{stderr}"
    );
}
