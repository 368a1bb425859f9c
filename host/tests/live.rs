//! `loglio live` end to end: firmware-sim's live mode (the code behind `loglio-sim live`, run in
//! this process) streams a scenario's LiDAR packets to UDP on loopback and its IMU frames to a
//! pseudo-terminal in real time; the `loglio` binary listens on the port and reads the
//! pseudo-terminal. Checked: the exit status, every output and its completeness, the pose error
//! against the simulator's exact ground truth, the drop counts, Ctrl-C and `--seconds`, and the
//! one-line errors of bad input.
//!
//! The runs against the simulator need the odometry to keep up with a real-time stream, which
//! the emulated binary does not under qemu-user (`LOGLIO_TEST_RUNNER`, CI's aarch64 job): there
//! they are skipped with a printed reason; the bad-input tests run everywhere. No assertion
//! depends on timing: counts are compared with what was sent, with slack for a loaded machine.

use std::io::{BufRead, BufReader, Read};
use std::net::UdpSocket;
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::Mutex;
use std::sync::mpsc::{self, Receiver};
use std::time::{Duration, Instant};

use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::lidar::scanner::Firmware;
use loglio_firmware_sim::live_sensors::{LiveConfig, LiveStats};
use loglio_firmware_sim::scenario::{Scenario, ScenarioConfig, ScenarioKind};
use loglio_host::eval::{self, EvalOptions, Format};

/// The simulator runs are real time on a small machine: one at a time.
static SERIAL: Mutex<()> = Mutex::new(());

mod common;
use common::{extrinsic_config, loglio_command as loglio_cmd, number_after, runner};

/// Skips (with the reason on stdout) under an emulating runner.
fn skip_under_runner(test: &str) -> bool {
    if let Some(r) = runner() {
        println!(
            "{test}: skipped under LOGLIO_TEST_RUNNER ({r}): the emulated odometry cannot keep up with the simulator's real-time stream"
        );
        return true;
    }
    false
}

fn scratch(name: &str) -> common::Scratch {
    common::scratch("live", name)
}

/// A loopback port offset under which `ports` (the simulator's destination ports) are free.
fn free_offset(ports: &[u16]) -> u16 {
    (0..300u16)
        .find_map(|i| {
            let offset = 20_000 + ((std::process::id() as u16 % 89) * 211 + i * 13) % 25_000;
            let held: Option<Vec<UdpSocket>> =
                ports.iter().map(|p| UdpSocket::bind(("127.0.0.1", p + offset)).ok()).collect();
            held.map(|_| offset)
        })
        .expect("no free loopback ports")
}

/// A running `loglio live`: its stderr lines as they come, its stdout at the end.
struct LiveChild {
    child: Child,
    stderr: Receiver<String>,
    stderr_seen: Vec<String>,
    stdout: std::thread::JoinHandle<String>,
}

impl LiveChild {
    fn spawn(args: &[&str]) -> LiveChild {
        LiveChild::spawn_with(args, &[])
    }

    /// With `env` set (e.g. `ROS_DOMAIN_ID`).
    fn spawn_with(args: &[&str], env: &[(&str, &str)]) -> LiveChild {
        let mut child = loglio_cmd(args)
            .envs(env.iter().copied())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run loglio: {e}"));
        let (tx, rx) = mpsc::channel();
        let err = child.stderr.take().unwrap();
        std::thread::spawn(move || {
            for line in BufReader::new(err).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut out = child.stdout.take().unwrap();
        let stdout = std::thread::spawn(move || {
            let mut s = String::new();
            let _ = out.read_to_string(&mut s);
            s
        });
        LiveChild { child, stderr: rx, stderr_seen: Vec::new(), stdout }
    }

    /// Waits for the "listening" line (allocation and start-up on a loaded machine: generous).
    fn wait_ready(&mut self) {
        let deadline = Instant::now() + Duration::from_secs(120);
        while Instant::now() < deadline {
            match self.stderr.recv_timeout(Duration::from_millis(200)) {
                Ok(line) => {
                    let ready = line.starts_with("loglio live: listening");
                    self.stderr_seen.push(line);
                    if ready {
                        return;
                    }
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    if let Ok(Some(st)) = self.child.try_wait() {
                        panic!("loglio live exited ({st}) before listening: {:?}", self.drain_stderr());
                    }
                }
                Err(mpsc::RecvTimeoutError::Disconnected) => {
                    panic!("loglio live closed stderr before listening: {:?}", self.stderr_seen)
                }
            }
        }
        let _ = self.child.kill();
        panic!("loglio live not listening after 120 s: {:?}", self.stderr_seen);
    }

    fn drain_stderr(&mut self) -> Vec<String> {
        while let Ok(l) = self.stderr.recv_timeout(Duration::from_millis(100)) {
            self.stderr_seen.push(l);
        }
        self.stderr_seen.clone()
    }

    fn interrupt(&self) {
        let st = Command::new("kill").args(["-INT", &self.child.id().to_string()]).status().unwrap();
        assert!(st.success());
    }

    /// Waits for the exit (at most 120 s): status, stdout, stderr lines.
    fn finish(mut self) -> (ExitStatus, String, Vec<String>) {
        let deadline = Instant::now() + Duration::from_secs(120);
        let status = loop {
            if let Some(st) = self.child.try_wait().unwrap() {
                break st;
            }
            if Instant::now() > deadline {
                let _ = self.child.kill();
                panic!("loglio live did not exit within 120 s: {:?}", self.drain_stderr());
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        let err = self.drain_stderr();
        (status, self.stdout.join().unwrap(), err)
    }
}

/// A handheld OS1-16 scenario (2 s at rest, then motion), its metadata, configuration (the
/// simulator's extrinsic) and ground truth (the IMU frame at 200 Hz) in `dir`.
fn scenario(dir: &Path, seconds: f64) -> Scenario {
    let mut c = ScenarioConfig::new(ScenarioKind::Handheld, SensorModel::Os1_16, 3);
    c.duration_s = seconds;
    let sc = Scenario::from_config(c).unwrap();
    let Firmware::Ouster(o) = sc.firmware() else { unreachable!("an Ouster scenario") };
    std::fs::write(
        dir.join("meta.json"),
        serde_json::to_string(&loglio_firmware_sim::files::ouster_metadata(o)).unwrap(),
    )
    .unwrap();
    std::fs::write(dir.join("config.toml"), extrinsic_config("os1-16", &sc.extrinsic())).unwrap();
    let times = (sc.start_ns()..=sc.end_ns()).step_by(5_000_000);
    std::fs::write(dir.join("gt.tum"), loglio_firmware_sim::tum::trajectory(times, |t| sc.pose_at(t)))
        .unwrap();
    sc
}

/// Streams `sc` live to loopback (+`offset`); `on_ready` gets the pseudo-terminal's path
/// before the first byte is sent.
fn stream(sc: &Scenario, offset: u16, on_ready: impl FnOnce(&str)) -> LiveStats {
    let cfg =
        LiveConfig { host: std::net::Ipv4Addr::LOCALHOST, rate: 1.0, pty_link: None, port_offset: offset };
    loglio_firmware_sim::live_sensors::run(sc, &cfg, |pty| on_ready(pty.path.to_str().unwrap())).unwrap()
}

/// The counts after `key` in the summary's "drops: socket queue A, decoder B, IMU C, scans D".
fn drops(text: &str) -> [u64; 4] {
    let i = text.find("drops: ").unwrap_or_else(|| panic!("no drops in {text}")) + "drops: ".len();
    let line = text[i..].lines().next().unwrap();
    let mut v = [0u64; 4];
    for (slot, key) in v.iter_mut().zip(["socket queue ", "decoder ", "IMU ", "scans "]) {
        let j = line.find(key).unwrap_or_else(|| panic!("no {key:?} in {line}")) + key.len();
        *slot = line[j..].split(|c: char| !c.is_ascii_digit()).next().unwrap().parse().unwrap();
    }
    v
}

/// Checks that the streaming outputs are whole: every TUM line has 8 finite numbers, one per
/// scan past the IMU initialisation, and the CSV has one full row per scan. Returns (poses,
/// scans, scans tracked by the LiDAR).
fn check_outputs(out: &Path) -> (usize, usize, usize) {
    let tum = std::fs::read_to_string(out.join("trajectory.tum")).unwrap();
    let poses: Vec<&str> = tum.lines().filter(|l| !l.starts_with('#') && !l.trim().is_empty()).collect();
    for l in &poses {
        let v: Vec<f64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
        assert!(v.len() == 8 && v.iter().all(|x| x.is_finite()), "TUM line {l:?}");
    }
    let csv = std::fs::read_to_string(out.join("scans.csv")).unwrap();
    assert!(csv.ends_with('\n'), "scans.csv cut short");
    let mut lines = csv.lines();
    let columns = lines.next().expect("scans.csv header").split(',').count();
    let rows: Vec<&str> = lines.collect();
    for r in &rows {
        assert_eq!(r.split(',').count(), columns, "row {r:?}");
    }
    let initialising = rows.iter().filter(|r| r.contains(",initialising,")).count();
    let tracked = rows.iter().filter(|r| r.contains(",ok,") || r.contains(",degraded,")).count();
    assert_eq!(poses.len(), rows.len() - initialising, "one pose per scan after the initialisation");
    for f in ["map.ply", "map.pcd", "trajectory.png", "trajectory.svg"] {
        assert!(out.join(f).metadata().is_ok_and(|m| m.len() > 0), "{f} missing");
    }
    (poses.len(), rows.len(), tracked)
}

/// A run against the simulator: the one-at-a-time lock, a scratch folder holding the
/// scenario's files ([`scenario`]), loopback ports for the simulator to send to, and the
/// arguments every such `loglio live` gets.
/// Fields drop in their order: the scratch folder goes before the lock is released, so that
/// the next run never has its new folder removed by this one's guard.
struct SimRun {
    dir: common::Scratch,
    sc: Scenario,
    offset: u16,
    _one: std::sync::MutexGuard<'static, ()>,
}

impl SimRun {
    /// `seconds` of the scenario in the scratch folder `name`; `None` (the reason printed)
    /// under an emulating runner.
    fn start(test: &str, name: &str, seconds: f64) -> Option<SimRun> {
        if skip_under_runner(test) {
            return None;
        }
        let _one = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
        let dir = scratch(name);
        let sc = scenario(&dir, seconds);
        let offset = free_offset(&[7502, 7503]);
        Some(SimRun { dir, sc, offset, _one })
    }

    /// A file of the scratch folder.
    fn path(&self, f: &str) -> String {
        self.dir.join(f).to_str().unwrap().to_string()
    }

    /// The loopback port the simulator sends the Ouster's `base` port to.
    fn port(&self, base: u16) -> String {
        (base + self.offset).to_string()
    }

    /// Starts `loglio live` on the scenario's configuration, metadata and LiDAR port with
    /// `extra`, and waits until it listens.
    fn spawn_live(&self, extra: &[&str]) -> LiveChild {
        self.spawn_live_with(extra, &[])
    }

    /// [`Self::spawn_live`] with `env` set.
    fn spawn_live_with(&self, extra: &[&str], env: &[(&str, &str)]) -> LiveChild {
        let (config, meta, lidar_port) = (self.path("config.toml"), self.path("meta.json"), self.port(7502));
        let mut args = vec![
            "live",
            "--config",
            &config,
            "--metadata",
            &meta,
            "--bind",
            "127.0.0.1",
            "--lidar-port",
            &lidar_port,
        ];
        args.extend_from_slice(extra);
        let mut c = LiveChild::spawn_with(&args, env);
        c.wait_ready();
        c
    }

    /// Streams the scenario live; `loglio live` is started (by `start`, given the
    /// pseudo-terminal's path) before the first byte is sent.
    fn stream(&self, start: impl FnOnce(&str) -> LiveChild) -> (LiveStats, LiveChild) {
        let mut child = None;
        let sent = stream(&self.sc, self.offset, |pty| child = Some(start(pty)));
        (sent, child.unwrap())
    }
}

#[test]
fn live_tracks_the_simulator_and_ctrl_c_writes_every_output() {
    let Some(run) = SimRun::start("live_tracks_the_simulator_and_ctrl_c_writes_every_output", "e2e", 6.0)
    else {
        return;
    };
    let (sc, dir, out) = (&run.sc, &run.dir, run.dir.join("out"));
    let (sent, child) = run.stream(|pty| {
        run.spawn_live(&["--imu-serial", pty, "--gt", &run.path("gt.tum"), "--out", out.to_str().unwrap()])
    });
    // Everything is sent and the pseudo-terminal drained; Ctrl-C stops, drains and writes.
    std::thread::sleep(Duration::from_millis(300));
    child.interrupt();
    let (status, text, err) = child.finish();
    assert!(status.success(), "{status}: {err:?}\n{text}");
    assert!(text.contains("live: stopped by a signal"), "{text}");
    assert!(!err.iter().any(|l| l.contains("panicked") || l.contains("error:")), "{err:?}");
    // Status lines came (once a second) with the drop counts.
    assert!(err.iter().any(|l| l.starts_with("live: ") && l.contains("drops: socket queue")), "{err:?}");
    // The status and the latest pose lead the line.
    assert!(err.iter().any(|l| l.starts_with("live: ok, at (") && l.contains(" m, yaw ")), "{err:?}");

    // Counts against what the simulator sent: every data packet decoded, no IMU frame lost.
    // The simulator also sends the Ouster's IMU packets, 100 a second, to a port nobody
    // listens to here.
    let lidar_sent = sent.datagrams - (sc.end_ns() - sc.start_ns()) / 10_000_000;
    let decoded = number_after(&text, "datagrams, ") as u64;
    let imu = number_after(&text, "decoded, ") as u64;
    let [socket, decoder, imu_drops, scan_drops] = drops(&text);
    assert_eq!((socket, decoder), (0, 0), "{text}");
    assert!(imu_drops <= sent.imu_frames / 100 + sent.imu_dropped, "{text}\n{sent:?}");
    assert!(imu + imu_drops >= sent.imu_frames - sent.imu_dropped, "{text}\n{sent:?}");
    // Loopback loses nothing unless this machine starves the receive thread for longer than
    // the kernel buffer lasts: allow a little.
    assert!(decoded * 100 >= lidar_sent * 97 && decoded <= lidar_sent + 1, "{text}\n{sent:?}");
    // Scans dropped only if this machine could not keep up: allow a few, not many.
    assert!(scan_drops <= 5, "{text}");

    // Outputs: whole, one pose per scan after the initialisation; 6 s at 10 Hz is 59 whole
    // turns, of which a loaded machine may drop a few.
    let (poses, scans, tracked) = check_outputs(&out);
    assert!(scans as u64 + scan_drops >= 55 && scans <= 60, "{scans} scans: {text}");
    assert!(tracked >= 30, "{tracked} scans updated by the LiDAR: {text}");
    for f in ["error.png", "error.svg", "eval.json"] {
        assert!(out.join(f).metadata().is_ok_and(|m| m.len() > 0), "{f} missing");
    }
    // The pose error against the simulator's exact ground truth (the IMU frame).
    let gt = eval::read_trajectory(&dir.join("gt.tum"), Format::Tum, None).unwrap();
    let est = eval::read_trajectory(&out.join("trajectory.tum"), Format::Tum, None).unwrap();
    let opt = EvalOptions::default(); // evo's defaults: SE(3), 10 ms pairing
    let r = eval::evaluate(&gt, &est, &opt).unwrap();
    assert_eq!(r.matched, poses, "every pose matched a ground-truth stamp");
    assert!(r.ape_trans.rmse <= 0.10, "ATE {} m: {text}", r.ape_trans.rmse);
    assert!((number_after(&text, "rmse") - r.ape_trans.rmse).abs() < 1e-3, "{text}");
    println!("live e2e: {text}");
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn live_stops_after_seconds_with_the_ouster_imu() {
    let Some(run) = SimRun::start("live_stops_after_seconds_with_the_ouster_imu", "seconds", 4.5) else {
        return;
    };
    let out = run.dir.join("out");
    // The simulator streams 4.5 s; loglio stops on its own 3.5 s after it starts listening.
    let (_, child) = run.stream(|_pty| {
        run.spawn_live(&[
            "--ouster-imu",
            "--imu-port",
            &run.port(7503),
            "--seconds",
            "3.5",
            "--out",
            out.to_str().unwrap(),
        ])
    });
    let (status, text, err) = child.finish();
    assert!(status.success(), "{status}: {err:?}\n{text}");
    assert!(text.contains("live: stopped by --seconds"), "{text}");
    assert!(!err.iter().any(|l| l.contains("panicked") || l.contains("error:")), "{err:?}");
    // The Ouster's IMU packets (100 Hz) were the IMU.
    let imu = number_after(&text, "decoded, ");
    assert!(imu >= 100.0, "{text}");
    let [socket, decoder, imu_drops, _] = drops(&text);
    assert_eq!((socket, decoder, imu_drops), (0, 0, 0), "{text}");
    // The Ouster's IMU is on the LiDAR's clock: no offset is applied.
    if let Some(l) = text.lines().find(|l| l.starts_with("IMU–LiDAR time offset:")) {
        println!("ouster imu: {l}");
        assert!(l.ends_with("; +0.00 ms applied to the IMU stamps"), "{text}");
    }
    // Whole outputs: the scans of 3.5 s or less, one pose per scan after the initialisation.
    let (poses, scans, _) = check_outputs(&out);
    assert!((5..=36).contains(&scans) && poses > 0, "{scans} scans, {poses} poses: {text}");
    let _ = std::fs::remove_dir_all(&run.dir);
}

/// Without an IMU (`--no-imu`) live runs LiDAR-only: no IMU warning or error, the summary
/// and the status line say LiDAR-only, and the scans are tracked.
#[test]
fn live_without_imu_runs_lidar_only() {
    let Some(run) = SimRun::start("live_without_imu_runs_lidar_only", "no-imu", 4.5) else {
        return;
    };
    let out = run.dir.join("out");
    let (_, child) =
        run.stream(|_pty| run.spawn_live(&["--no-imu", "--seconds", "3.5", "--out", out.to_str().unwrap()]));
    let (status, text, err) = child.finish();
    assert!(status.success(), "{status}: {err:?}\n{text}");
    assert!(text.contains("LiDAR-only (no IMU): constant-velocity model\n"), "{text}");
    assert!(text.contains(", 0 IMU samples"), "{text}");
    assert!(
        !err.iter().any(|l| l.contains("panicked") || l.contains("error:") || l.contains("IMU data")),
        "{err:?}"
    );
    assert!(err.iter().any(|l| l.contains("live: LiDAR-only (no IMU), ")), "status line: {err:?}");
    let (poses, scans, tracked) = check_outputs(&out);
    assert!(
        (5..=36).contains(&scans) && poses == scans && tracked + 2 >= scans,
        "{scans} scans, {poses} poses, {tracked} tracked: {text}"
    );
    let _ = std::fs::remove_dir_all(&run.dir);
}

/// Runs `loglio live` to its end (bad input: it must not wait long).
fn live_output(args: &[&str]) -> (ExitStatus, String, Vec<String>) {
    let c = LiveChild::spawn(args);
    c.finish()
}

/// A failure whose last stderr line starts with `prefix`; every other line is the start-up
/// line or a warning; no panic.
fn fails_with(r: &(ExitStatus, String, Vec<String>), prefix: &str) -> String {
    let (status, _, err) = r;
    assert!(!status.success(), "should fail: {err:?}");
    assert_eq!(status.code(), Some(1), "{err:?}");
    let last = err.last().cloned().unwrap_or_default();
    assert!(last.starts_with(prefix), "{err:?}");
    assert_eq!(err.iter().filter(|l| l.starts_with("error:")).count(), 1, "{err:?}");
    for l in err {
        assert!(
            l.starts_with("error: ") || l.starts_with("warning: ") || l.starts_with("loglio live: listening"),
            "{err:?}"
        );
        assert!(!l.contains("panicked") && !l.contains("backtrace"), "{err:?}");
    }
    last
}

#[test]
fn live_bad_input_is_one_clear_line() {
    let held = UdpSocket::bind("127.0.0.1:0").unwrap();
    let busy = held.local_addr().unwrap().port().to_string();
    let free = {
        let s = UdpSocket::bind("127.0.0.1:0").unwrap();
        s.local_addr().unwrap().port().to_string()
    };
    let dir = scratch("bad");
    let base = ["live", "--preset", "vlp16", "--bind", "127.0.0.1", "--out"];
    let out = dir.join("out");
    let with = |extra: &[&str]| {
        let mut v: Vec<&str> = base.to_vec();
        v.push(out.to_str().unwrap());
        v.extend_from_slice(extra);
        live_output(&v)
    };
    // A port another program listens on.
    let e = fails_with(
        &with(&["--lidar-port", &busy, "--imu-serial", "/dev/null"]),
        &format!(
            "error: cannot listen for LiDAR packets on UDP 127.0.0.1:{busy}: the port is already in use"
        ),
    );
    assert!(e.contains("another loglio"), "{e}");
    // A serial device that does not exist: named, with the ports this computer has.
    let e = fails_with(
        &with(&["--lidar-port", &free, "--imu-serial", "/dev/loglio-no-such-tty"]),
        "error: IMU serial device /dev/loglio-no-such-tty: No such file or directory (",
    );
    assert!(e.contains("serial ports"), "{e}");
    // A capture file instead of a device.
    let capture = dir.join("imu.bin");
    std::fs::write(&capture, [0u8; 16]).unwrap();
    fails_with(
        &with(&["--lidar-port", &free, "--imu-serial", capture.to_str().unwrap()]),
        &format!("error: IMU serial device {} is a regular file, not a serial port", capture.display()),
    );
    // The Ouster's IMU with a Velodyne; an address that is not this computer's.
    fails_with(&with(&["--ouster-imu"]), "error: --ouster-imu needs an Ouster preset (os1-*), not vlp16");
    fails_with(
        &live_output(&["live", "--preset", "vlp16", "--bind", "192.0.2.1", "--lidar-port", &free]),
        "error: cannot listen for LiDAR packets on UDP 192.0.2.1:",
    );
    // An Ouster without its metadata.
    fails_with(
        &live_output(&["live", "--preset", "os1-16", "--ouster-imu"]),
        "error: preset os1-16 reads Ouster packets, which need the sensor's metadata",
    );
    // Nothing arrives on the LiDAR port: a clear error after --lidar-timeout.
    let pty = match loglio_firmware_sim::live_sensors::Pty::open() {
        Ok(p) => p,
        // qemu-user does not emulate the pseudo-terminal ioctls the test process needs.
        Err(e) if runner().is_some() => {
            println!(
                "live_bad_input_is_one_clear_line: the LiDAR-timeout part skipped under LOGLIO_TEST_RUNNER: {e}"
            );
            drop(held);
            let _ = std::fs::remove_dir_all(&dir);
            return;
        }
        Err(e) => panic!("pseudo-terminal: {e}"),
    };
    let r = with(&[
        "--lidar-port",
        &free,
        "--imu-serial",
        pty.path.to_str().unwrap(),
        "--lidar-timeout",
        "1",
        "--quiet",
    ]);
    let e = fails_with(&r, &format!("error: no LiDAR packets on UDP 127.0.0.1:{free} within 1 s"));
    assert!(e.contains("destination IP"), "{e}");
    // Stopped (--seconds, as by Ctrl-C) before anything arrived.
    let r = with(&["--lidar-port", &free, "--imu-serial", pty.path.to_str().unwrap(), "--seconds", "0.5"]);
    fails_with(&r, &format!("error: no LiDAR packets arrived on UDP 127.0.0.1:{free} during the run"));
    drop(held);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn live_without_imu_data_warns_and_fails_clearly() {
    let Some(run) = SimRun::start("live_without_imu_data_warns_and_fails_clearly", "no-imu-data", 3.0) else {
        return;
    };
    // An IMU device that stays silent: a pseudo-terminal nobody writes.
    let silent = loglio_firmware_sim::live_sensors::Pty::open().unwrap();
    let silent_path = silent.path.to_str().unwrap().to_string();
    let out = run.dir.join("out");
    let (_, child) = run.stream(|_pty| {
        run.spawn_live(&[
            "--imu-serial",
            &silent_path,
            "--imu-timeout",
            "1",
            "--seconds",
            "2.5",
            "--quiet",
            "--out",
            out.to_str().unwrap(),
        ])
    });
    let r = child.finish();
    let e = fails_with(&r, &format!("error: no IMU data arrived from {silent_path} during the run"));
    assert!(e.contains("--baud"), "{e}");
    assert!(
        r.2.iter().any(|l| l.starts_with(&format!("warning: no IMU data from {silent_path} for "))),
        "{:?}",
        r.2
    );
    let _ = std::fs::remove_dir_all(&run.dir);
}

/// A Cyclone DDS subscriber to `rt/loglio/odometry` (the types as in `tests/ros2.rs`, where
/// they are checked field by field): prints `ready`, then, when stdin closes, the number of
/// odometry messages received.
const ODOM_SUBSCRIBER: &str = r#"import sys, threading, time
from dataclasses import dataclass
from cyclonedds.domain import DomainParticipant
from cyclonedds.topic import Topic
from cyclonedds.sub import DataReader
from cyclonedds.core import Qos, Policy
from cyclonedds.idl import IdlStruct
from cyclonedds.util import duration
from cyclonedds.idl.types import int32, uint32, uint8, float64, sequence, array

{ROS2_TYPES}dp = DomainParticipant(int(sys.argv[1]))
qos = Qos(Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)), Policy.History.KeepLast(1000))
r = DataReader(dp, Topic(dp, "rt/loglio/odometry", Odometry), qos=qos)
print("ready", flush=True)
stop = threading.Event()
threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
n, last = 0, False
while not last:
    last = stop.is_set()
    got = [m for m in r.take(100) if isinstance(m, Odometry)]
    n += len(got)
    if not got and not last:
        time.sleep(0.005)
print(n, flush=True)
"#;

/// A pymavlink listener on a UDP port of 127.0.0.1 (printed first): once the file `done`
/// appears and 0.5 s pass quietly, prints `ODOMETRY-count bad-frame-count`.
const MAVLINK_LISTENER: &str = r#"import os, socket, sys, time
from pymavlink.dialects.v20 import common as mavlink
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", 0))
s.settimeout(0.1)
print(s.getsockname()[1], flush=True)
mav = mavlink.MAVLink(None)
mav.robust_parsing = True
odo, bad = 0, 0
start = time.monotonic(); last = start
while time.monotonic() - start < 120:
    try:
        data = s.recv(65536)
    except socket.timeout:
        if os.path.exists(sys.argv[1]) and time.monotonic() - last > 0.5:
            break
        continue
    last = time.monotonic()
    for m in mav.parse_buffer(data) or []:
        t = m.get_type()
        odo += t == "ODOMETRY"
        bad += t == "BAD_DATA"
print(odo, bad, flush=True)
"#;

/// A peer process: its stdout lines as they come; killed when dropped.
struct Peer {
    child: Child,
    lines: Receiver<String>,
}

impl Peer {
    fn start(mut cmd: Command) -> Peer {
        let mut child = cmd
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start a peer: {e}"));
        let out = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for l in BufReader::new(out).lines().map_while(Result::ok) {
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        Peer { child, lines }
    }

    fn line(&self, what: &str) -> String {
        self.lines.recv_timeout(Duration::from_secs(30)).unwrap_or_else(|_| panic!("{what}: no answer"))
    }

    /// Closes its stdin; its last line.
    fn finish(mut self, what: &str) -> String {
        drop(self.child.stdin.take());
        self.line(what)
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `(median, p99)` of the latency and of the processing in a summary line ending in
/// `median A ms, p99 B ms (processing of the same N scans: median C ms, p99 D ms)`.
fn latency_figures(line: &str) -> ([f64; 2], [f64; 2]) {
    let med = number_after(line, "median ");
    let p99 = number_after(line, "p99 ");
    let rest = &line[line.find("processing").unwrap_or_else(|| panic!("no processing in {line}"))..];
    ([med, p99], [number_after(rest, "median "), number_after(rest, "p99 ")])
}

/// Every live output on at once at real time: `--ros2` (a Cyclone DDS subscriber), `--mavlink`
/// (pymavlink), `--foxglove` (no client), `--mcap`. No scan dropped, no sink losing anything,
/// the trajectory whole, and the latency from a scan's last packet to its pose on the wire
/// measured and printed beside the processing time of the same scans. Only a generous sanity
/// bound is asserted on it (docs/performance-log.md carries the figures).
#[test]
fn live_with_every_output_drops_nothing_and_reports_the_wire_latency() {
    let test = "live_with_every_output_drops_nothing_and_reports_the_wire_latency";
    let Some(python) = common::peer_python(test) else { return };
    let Some(run) = SimRun::start(test, "all-sinks", 6.0) else { return };
    let out = run.dir.join("out");
    let domain = (1 + (std::process::id() * 3 + 101) % 200).to_string();
    let xml = run.dir.join("cyclonedds.xml");
    std::fs::write(&xml, common::CYCLONE_XML).unwrap();
    std::fs::write(run.dir.join("sub.py"), common::with_ros2_types(ODOM_SUBSCRIBER)).unwrap();
    std::fs::write(run.dir.join("mav.py"), MAVLINK_LISTENER).unwrap();
    let mut cmd = Command::new(&python);
    cmd.arg(run.dir.join("sub.py")).arg(&domain).env("CYCLONEDDS_URI", format!("file://{}", xml.display()));
    let sub = Peer::start(cmd);
    assert_eq!(sub.line("the DDS subscriber"), "ready");
    let done = run.dir.join("mav-done");
    let mut cmd = Command::new(&python);
    cmd.arg(run.dir.join("mav.py")).arg(&done);
    let mav = Peer::start(cmd);
    let mav_url = format!("udp:127.0.0.1:{}", mav.line("the pymavlink listener"));
    let fox = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        format!("127.0.0.1:{}", l.local_addr().unwrap().port())
    };
    let mcap = run.path("run.mcap");

    let (sent, child) = run.stream(|pty| {
        run.spawn_live_with(
            &[
                "--imu-serial",
                pty,
                "--out",
                out.to_str().unwrap(),
                "--ros2",
                "--mavlink",
                &mav_url,
                "--foxglove",
                &fox,
                "--mcap",
                &mcap,
            ],
            &[("ROS_DOMAIN_ID", &domain)],
        )
    });
    std::thread::sleep(Duration::from_millis(300));
    child.interrupt();
    let (status, text, err) = child.finish();
    std::fs::write(&done, "").unwrap();
    let ros2_odom: usize = sub.finish("the DDS subscriber").trim().parse().unwrap();
    let mav_line = mav.finish("the pymavlink listener");
    let [mav_odom, mav_bad]: [usize; 2] = mav_line
        .split_whitespace()
        .map(|x| x.parse().unwrap())
        .collect::<Vec<_>>()
        .try_into()
        .unwrap_or_else(|_| panic!("listener said {mav_line:?}"));

    assert!(status.success(), "{status}: {err:?}\n{text}");
    assert!(!err.iter().any(|l| l.contains("panicked") || l.contains("error:")), "{err:?}");
    // No sink warned (the kernel's receive-buffer limit is this machine's, not a sink's).
    let warned = |l: &&String| l.starts_with("warning:") && !l.starts_with("warning: UDP receive buffer");
    assert!(!err.iter().any(|l| warned(&l)), "{err:?}");
    // No scan dropped anywhere: not by the socket, the decoder nor the odometry's queue.
    let [socket, decoder, _, scan_drops] = drops(&text);
    assert_eq!((socket, decoder, scan_drops), (0, 0, 0), "{text}\n{sent:?}");
    // Every sink lost nothing: the summary's lines, and the last status line's `0 lost`s.
    for name in ["ros2 ", "mavlink udp:", "foxglove ", "mcap "] {
        let line = text
            .lines()
            .find(|l| l.strip_prefix("live output ").is_some_and(|l| l.starts_with(name)))
            .unwrap_or_else(|| panic!("no {name}: {text}"));
        assert!(line.contains(" 0 scans and 0 poses dropped (queue full), 0 errors"), "{line}");
    }
    let last_status =
        err.iter().rev().find(|l| l.contains("; outputs: ")).unwrap_or_else(|| panic!("{err:?}"));
    let outputs = &last_status[last_status.find("; outputs: ").unwrap() + 11..];
    assert_eq!(outputs.split(", ").filter(|p| p.ends_with(" 0 lost")).count(), 4, "{last_status}");
    // The trajectory whole: one pose per scan after the initialisation, all 59 scans.
    let (poses, scans, tracked) = check_outputs(&out);
    assert!((57..=60).contains(&scans) && tracked >= 30, "{scans} scans, {tracked} tracked: {text}");
    // The poses reached the peers: pymavlink every scan pose (and IMU-rate ones), the DDS
    // subscriber those after its discovery (a volatile reader misses what came before).
    assert_eq!(mav_bad, 0, "{mav_line}");
    assert!(mav_odom >= poses, "{mav_odom} ODOMETRY for {poses} poses");
    assert!(ros2_odom * 2 >= poses && ros2_odom <= poses, "{ros2_odom} odometry for {poses} poses");
    assert!(std::fs::read(&mcap).is_ok_and(|b| b.starts_with(b"\x89MCAP0\r\n") && b.len() > 1000), "{mcap}");

    // The figures: last packet to the result, and to the pose on the wire per sink.
    let mut figures = Vec::new();
    for key in ["to its result: ", "to its pose sent by ros2", "to its pose sent by mavlink"] {
        let line = text.lines().find(|l| l.contains(key)).unwrap_or_else(|| panic!("no {key:?}: {text}"));
        let ([med, p99], [pmed, pp99]) = latency_figures(line);
        assert!(med > 0.0 && med <= p99 && pmed <= pp99, "{line}");
        // A sanity bound only; the target (processing + 1 ms at the median) is a figure.
        assert!(med < 200.0, "{line}");
        figures.push(format!(
            "{}: latency median {med:.1} ms, p99 {p99:.1} ms; processing median {pmed:.1} ms, p99 {pp99:.1} ms",
            key.trim_end_matches(": ")
        ));
    }
    println!("live all outputs: {}", figures.join(" | "));
    println!("live all outputs, summary:\n{text}");
    let _ = std::fs::remove_dir_all(&run.dir);
}

/// The fault injector around the live sources: the simulator's UDP packets and serial IMU
/// frames pass `loglio_firmware_sim::fault::FaultInjector` on their way to `loglio live`
/// (a LiDAR outage, an IMU spike, a packet stamped a minute late, another Ouster model's
/// packets on the port, an IMU pause, flipped bits). The run must go on through all of them,
/// name each in a warning, flag the scans after the outage, and keep the clean run's bound on
/// the ATE.
#[test]
fn live_survives_the_fault_injector() {
    use loglio_firmware_sim::fault::{Fault, FaultInjector, ImuSensor, foreign_scenario};
    use loglio_firmware_sim::stream::{Wire, WireStream};
    let Some(run) = SimRun::start("live_survives_the_fault_injector", "faults", 12.0) else {
        return;
    };
    let (sc, dir, out) = (&run.sc, &run.dir, run.dir.join("out"));
    let faults = [
        Fault::LidarGap { from_s: 4.0, to_s: 5.5 },
        Fault::ImuSpike { at_s: 6.5, sensor: ImuSensor::Acc, value: 1000.0 },
        Fault::LidarStamp { at_s: 7.0, shift_s: 60.0 },
        Fault::Foreign { from_s: 8.0, to_s: 9.0 },
        Fault::ImuGap { from_s: 9.5, to_s: 10.0 },
        Fault::FlipBits { from_s: 10.5, to_s: 11.0, rate: 1e-4 },
    ];
    let fs = foreign_scenario(sc, 8.0, 9.0).unwrap();
    let foreign: Vec<_> = WireStream::new(&fs).filter(|e| matches!(e.wire, Wire::Udp { .. })).collect();
    let events = FaultInjector::new(WireStream::new(sc), sc.start_ns(), 0x11FE, &faults)
        .with_foreign(foreign.into_iter())
        .events();
    let cfg = LiveConfig {
        host: std::net::Ipv4Addr::LOCALHOST,
        rate: 1.0,
        pty_link: None,
        port_offset: run.offset,
    };
    let mut child = None;
    loglio_firmware_sim::live_sensors::run_events(events, sc.start_ns(), &cfg, |pty| {
        let pty = pty.path.to_str().unwrap();
        child = Some(run.spawn_live(&[
            "--imu-serial",
            pty,
            "--gt",
            &run.path("gt.tum"),
            "--out",
            out.to_str().unwrap(),
        ]))
    })
    .unwrap();
    let child = child.unwrap();
    std::thread::sleep(Duration::from_millis(300));
    child.interrupt();
    let (status, text, err) = child.finish();
    assert!(status.success(), "{status}: {err:?}\n{text}");
    assert!(!err.iter().any(|l| l.contains("panicked") || l.contains("error:")), "{err:?}");
    let said = |words: &[&str]| {
        err.iter().chain(text.lines().map(str::to_string).collect::<Vec<_>>().iter()).any(|l| {
            let l = l.to_lowercase();
            l.contains("warning") && words.iter().any(|w| l.contains(w))
        })
    };
    for (fault, words) in [
        ("LiDAR gap", &["lidar gap", "no lidar", "lidar paused"][..]),
        ("IMU spike", &["outlier", "spike", "full scale"][..]),
        ("wrong packet stamp", &["stamp"][..]),
        ("foreign packets", &["foreign", "other sensor", "model", "layout"][..]),
        ("IMU gap", &["imu gap"][..]),
    ] {
        assert!(said(words), "no warning names the {fault}:\n{err:#?}\n{text}");
    }
    let (poses, scans, tracked) = check_outputs(&out);
    assert!(tracked >= 60, "{tracked} of {scans} scans updated by the LiDAR: {text}");
    // The first scan after the outage says so.
    let csv = std::fs::read_to_string(out.join("scans.csv")).unwrap();
    assert!(csv.contains(",bridged,"), "no scan flagged after the LiDAR gap: {text}");
    // The IMU carried the state through the 1.5 s outage: no re-initialisation (before
    // 2026-11-27 the runner dropped the samples over a second old and the filter stepped over
    // the pause: ATE 0.060 m, rotation 8.4 deg); one gap said (a flipped bit in a point time
    // once made a second one).
    assert!(!csv.contains(",re-initialising,"), "re-initialised: {text}");
    assert!(text.contains("faults: 1 LiDAR gaps"), "{text}");
    let gt = eval::read_trajectory(&dir.join("gt.tum"), Format::Tum, None).unwrap();
    let est = eval::read_trajectory(&out.join("trajectory.tum"), Format::Tum, None).unwrap();
    let r = eval::evaluate(&gt, &est, &EvalOptions::default()).unwrap();
    assert_eq!(r.matched, poses, "every pose matched a ground-truth stamp");
    // 0.009 m measured (2026-11-27); the clean live run's bound is 0.10 m (timing on a loaded
    // machine).
    assert!(r.ape_trans.rmse <= 0.03, "ATE {} m: {text}", r.ape_trans.rmse);
    println!("live with faults: ATE {:.4} m, {scans} scans\n{text}\n{}", r.ape_trans.rmse, err.join("\n"));
    let _ = std::fs::remove_dir_all(dir);
}

/// An Xsens MTData2 message (PacketCounter, SampleTimeFine, float32 Acceleration and
/// RateOfTurn), written from Xsens' "MT Low Level Communication Protocol Documentation"
/// independently of the core's parser: FA FF 36 LEN, the data packets (id u16 BE, size u8,
/// big-endian values), and the checksum that makes the bytes after the preamble sum to 0.
fn xsens_message(counter: u16, ticks: u32, acc: [f32; 3], gyro: [f32; 3]) -> Vec<u8> {
    let mut d = vec![0x10, 0x20, 2];
    d.extend(counter.to_be_bytes());
    d.extend([0x10, 0x60, 4]);
    d.extend(ticks.to_be_bytes());
    d.extend([0x40, 0x20, 12]);
    d.extend(acc.iter().flat_map(|x| x.to_be_bytes()));
    d.extend([0x80, 0x20, 12]);
    d.extend(gyro.iter().flat_map(|x| x.to_be_bytes()));
    let mut m = vec![0xFA, 0xFF, 0x36, d.len() as u8];
    m.extend(d);
    let sum = m[1..].iter().fold(0u8, |s, &b| s.wrapping_add(b));
    m.push(sum.wrapping_neg());
    m
}

/// An Xsens on the serial line instead of loglio's IMU board: the simulator's IMU samples (the
/// scenario's motion) re-sent as MTData2 messages stamped with a device clock that started at
/// an arbitrary time, with line noise before some messages and some messages corrupted. The
/// LiDAR is taken on this computer's clock (`lidar_time_source = "capture"`), the Xsens's time
/// goes onto it through the device-clock estimate. Checked: every good message arrives as a
/// sample, the noise bytes and the corrupted messages are counted (not fatal), the clock
/// offset is reported, and the trajectory matches the simulator's ground truth once the
/// simulator's clock is put onto this computer's (the start of the paced stream).
#[test]
fn live_reads_an_xsens_with_noise_on_the_line() {
    use loglio_core::sensor::imu_frame;
    use loglio_firmware_sim::stream::{Wire, WireEvent, WireStream};
    let Some(run) = SimRun::start("live_reads_an_xsens_with_noise_on_the_line", "xsens", 6.0) else {
        return;
    };
    let (sc, dir, out) = (&run.sc, &run.dir, run.dir.join("out"));
    let mut config = std::fs::read_to_string(dir.join("config.toml")).unwrap();
    config.push_str("[time]\nlidar_time_source = \"capture\"\n");
    std::fs::write(dir.join("config.toml"), config).unwrap();
    // The device was powered on 1234.5 s before the scenario starts.
    let power_on = sc.start_ns() - 1_234_500_000_000;
    let (mut noise, mut corrupted, mut messages) = (0u64, 0u64, 0u64);
    let events: Vec<WireEvent> = WireStream::new(sc)
        .map(|ev| {
            let (t_ns, mut frame) = match ev {
                WireEvent { t_ns, wire: Wire::Serial(frame) } => (t_ns, frame),
                other => return other,
            };
            let n = frame.len();
            let f = imu_frame::decode_in_place(&mut frame[..n - 1]).expect("the simulator's frame");
            let ticks = ((f.t_ns - power_on) / 100_000) as u32;
            let mut bytes = Vec::new();
            if f.seq % 50 == 7 {
                bytes.extend([0x00, 0xFA, 0x13, 0x37, 0xFA]); // noise with stray preambles
                noise += 5;
            }
            let mut m = xsens_message(f.seq as u16, ticks, f.acc, f.gyro);
            if f.seq % 97 == 30 {
                m[20] ^= 0x04; // a flipped bit: the checksum fails
                noise += m.len() as u64;
                corrupted += 1;
            } else {
                messages += 1;
            }
            bytes.extend(m);
            WireEvent { t_ns, wire: Wire::Serial(bytes) }
        })
        .collect();
    let cfg = LiveConfig {
        host: std::net::Ipv4Addr::LOCALHOST,
        rate: 1.0,
        pty_link: None,
        port_offset: run.offset,
    };
    let mut child = None;
    let mut stream_start_ns = 0u64;
    let sent =
        loglio_firmware_sim::live_sensors::run_events(events.into_iter(), sc.start_ns(), &cfg, |pty| {
            let pty = pty.path.to_str().unwrap();
            child = Some(run.spawn_live(&[
                "--imu-serial",
                pty,
                "--imu-protocol",
                "xsens",
                "--out",
                out.to_str().unwrap(),
            ]));
            // The stream is paced from here: the simulator's start is now on this computer's clock.
            stream_start_ns = loglio_host::input::udp::host_time_ns();
        })
        .unwrap();
    let child = child.unwrap();
    std::thread::sleep(Duration::from_millis(300));
    child.interrupt();
    let (status, text, err) = child.finish();
    assert!(status.success(), "{status}: {err:?}\n{text}");
    assert!(!err.iter().any(|l| l.contains("panicked") || l.contains("error:")), "{err:?}");
    assert!(err.iter().any(|l| l.contains("listening") && l.contains("xsens IMU from")), "{err:?}");

    // Every good message is a sample; the corrupted ones are IMU drops (PacketCounter gaps).
    let samples = number_after(&text, "decoded, ") as u64;
    let [_, _, imu_drops, _] = drops(&text);
    let lost_on_the_line = sent.imu_dropped;
    assert!(samples + lost_on_the_line >= messages && samples <= messages, "{text}\n{sent:?}");
    assert!(imu_drops >= corrupted, "{text}");
    // The noise and the corrupted messages are counted to the byte (when the line lost nothing).
    let line =
        text.lines().find(|l| l.starts_with("serial IMU (xsens): ")).unwrap_or_else(|| panic!("{text}"));
    let counted = number_after(line, "serial IMU (xsens): ") as u64;
    // Refused: the corrupted messages and the false starts at the stray preambles in the noise.
    let refused = number_after(line, "bytes not IMU data, ") as u64;
    assert!(refused >= corrupted, "{line}");
    if lost_on_the_line == 0 {
        assert_eq!(counted, noise, "{line}");
    } else {
        assert!(counted > 0, "{line}");
    }
    // The device clock: 1234.5 s since power-on at the start, against this computer's clock.
    let offset_s = number_after(line, "arrival - device time ");
    let want_s = (stream_start_ns - (sc.start_ns() - power_on)) as f64 * 1e-9;
    assert!((offset_s - want_s).abs() < 0.05, "offset {offset_s} s, expected about {want_s} s: {line}");
    assert!(line.contains("ppm over "), "{line}");

    // The trajectory against the ground truth, the simulator's clock moved onto this
    // computer's: the Xsens samples carried the scenario's motion.
    let (poses, scans, tracked) = check_outputs(&out);
    assert!(tracked >= 30, "{tracked} of {scans} scans updated by the LiDAR: {text}");
    let gt = eval::read_trajectory(&dir.join("gt.tum"), Format::Tum, None).unwrap();
    let est = eval::read_trajectory(&out.join("trajectory.tum"), Format::Tum, None).unwrap();
    let opt = EvalOptions {
        offset: -((stream_start_ns - sc.start_ns()) as f64 * 1e-9),
        max_diff: 0.02,
        ..EvalOptions::default()
    };
    let r = eval::evaluate(&gt, &est, &opt).unwrap();
    assert!(r.matched * 10 >= poses * 9, "{} of {poses} poses matched: {text}", r.matched);
    assert!(r.ape_trans.rmse <= 0.10, "ATE {} m: {text}", r.ape_trans.rmse);
    println!("live xsens: ATE {:.4} m, {scans} scans\n{text}", r.ape_trans.rmse);
    let _ = std::fs::remove_dir_all(dir);
}

/// An autopilot's IMU over MAVLink: the simulator's IMU samples re-sent as `HIGHRES_IMU`
/// datagrams (loglio's own MAVLink framing; pymavlink's frames are checked field by field in
/// `tests/mavlink.rs`) stamped with the autopilot's time since boot, with heartbeats and
/// junk datagrams between them. Checked: every sample arrives, the junk is counted, the clock
/// offset is reported, and the trajectory matches the ground truth on this computer's clock.
#[test]
fn live_reads_a_mavlink_imu_over_udp() {
    use loglio_core::sensor::imu_frame;
    use loglio_firmware_sim::stream::{Wire, WireEvent, WireStream};
    use loglio_host::sink::mavlink::Encoder;
    let Some(run) = SimRun::start("live_reads_a_mavlink_imu_over_udp", "mavlink-imu", 6.0) else {
        return;
    };
    let (sc, dir, out) = (&run.sc, &run.dir, run.dir.join("out"));
    let mut config = std::fs::read_to_string(dir.join("config.toml")).unwrap();
    config.push_str("[time]\nlidar_time_source = \"capture\"\n");
    std::fs::write(dir.join("config.toml"), config).unwrap();
    let boot = sc.start_ns() - 77_000_000_000; // the autopilot booted 77 s before
    let mav_port = 14_550u16;
    let mut enc = Encoder::new(1, 1);
    let (mut junk, mut messages) = (0u64, 0u64);
    let mut events = Vec::new();
    for ev in WireStream::new(sc) {
        let (t_ns, mut frame) = match ev {
            WireEvent { t_ns, wire: Wire::Serial(frame) } => (t_ns, frame),
            other => {
                events.push(other);
                continue;
            }
        };
        let n = frame.len();
        let f = imu_frame::decode_in_place(&mut frame[..n - 1]).expect("the simulator's frame");
        // HIGHRES_IMU (id 105, CRC_EXTRA 93): time_usec, acc, gyro, mag, pressures, temperature,
        // fields_updated, id.
        let mut p = ((f.t_ns - boot) / 1000).to_le_bytes().to_vec();
        for v in f.acc.iter().chain(f.gyro.iter()).chain([0.0f32; 7].iter()) {
            p.extend(v.to_le_bytes());
        }
        p.extend(0x3Fu16.to_le_bytes());
        p.push(0);
        let mut buf = [0u8; 300];
        let len = enc.frame(105, 93, &p, &mut buf).unwrap();
        events.push(WireEvent { t_ns, wire: Wire::Udp { port: mav_port, payload: buf[..len].to_vec() } });
        messages += 1;
        if f.seq % 50 == 7 {
            events.push(WireEvent { t_ns, wire: Wire::Udp { port: mav_port, payload: vec![0x13, 0x37] } });
            junk += 2;
            let len = enc.frame(0, 50, &[0, 0, 0, 0, 2, 3, 0, 4, 3], &mut buf).unwrap(); // a heartbeat
            events.push(WireEvent { t_ns, wire: Wire::Udp { port: mav_port, payload: buf[..len].to_vec() } });
        }
    }
    let cfg = LiveConfig {
        host: std::net::Ipv4Addr::LOCALHOST,
        rate: 1.0,
        pty_link: None,
        port_offset: run.offset,
    };
    let mut child = None;
    let mut stream_start_ns = 0u64;
    let listen = (mav_port + run.offset).to_string();
    loglio_firmware_sim::live_sensors::run_events(events.into_iter(), sc.start_ns(), &cfg, |_pty| {
        child = Some(run.spawn_live(&["--imu-mavlink-udp", &listen, "--out", out.to_str().unwrap()]));
        stream_start_ns = loglio_host::input::udp::host_time_ns();
    })
    .unwrap();
    let child = child.unwrap();
    std::thread::sleep(Duration::from_millis(300));
    child.interrupt();
    let (status, text, err) = child.finish();
    assert!(status.success(), "{status}: {err:?}\n{text}");
    assert!(!err.iter().any(|l| l.contains("panicked") || l.contains("error:")), "{err:?}");
    // Loopback loses nothing unless this machine starves the receiving thread: a little slack.
    let samples = number_after(&text, "decoded, ") as u64;
    assert!(samples * 100 >= messages * 97 && samples <= messages, "{samples} of {messages}: {text}");
    let line = text
        .lines()
        .find(|l| l.starts_with("MAVLink IMU (HIGHRES_IMU): "))
        .unwrap_or_else(|| panic!("{text}"));
    assert_eq!(number_after(line, "MAVLink IMU (HIGHRES_IMU): ") as u64, junk, "{line}");
    let offset_s = number_after(line, "arrival - device time ");
    let want_s = (stream_start_ns - (sc.start_ns() - boot)) as f64 * 1e-9;
    assert!((offset_s - want_s).abs() < 0.05, "offset {offset_s} s, expected about {want_s} s: {line}");
    let (poses, scans, tracked) = check_outputs(&out);
    assert!(tracked >= 30, "{tracked} of {scans} scans updated by the LiDAR: {text}");
    let gt = eval::read_trajectory(&dir.join("gt.tum"), Format::Tum, None).unwrap();
    let est = eval::read_trajectory(&out.join("trajectory.tum"), Format::Tum, None).unwrap();
    let opt = EvalOptions {
        offset: -((stream_start_ns - sc.start_ns()) as f64 * 1e-9),
        max_diff: 0.02,
        ..EvalOptions::default()
    };
    let r = eval::evaluate(&gt, &est, &opt).unwrap();
    assert!(r.matched * 10 >= poses * 9, "{} of {poses} poses matched: {text}", r.matched);
    assert!(r.ape_trans.rmse <= 0.10, "ATE {} m: {text}", r.ape_trans.rmse);
    println!("live mavlink IMU: ATE {:.4} m, {scans} scans\n{text}", r.ape_trans.rmse);
    let _ = std::fs::remove_dir_all(dir);
}
