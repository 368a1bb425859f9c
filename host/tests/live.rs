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
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::Mutex;
use std::sync::mpsc::{self, Receiver};
use std::time::{Duration, Instant};

use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::lidar::scanner::Firmware;
use loglio_firmware_sim::live::{LiveConfig, LiveStats};
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

fn scratch(name: &str) -> PathBuf {
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
        let mut child = loglio_cmd(args)
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
    loglio_firmware_sim::live::run(sc, &cfg, |pty| on_ready(pty.path.to_str().unwrap())).unwrap()
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
struct SimRun {
    _one: std::sync::MutexGuard<'static, ()>,
    dir: PathBuf,
    sc: Scenario,
    offset: u16,
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
        Some(SimRun { _one, dir, sc, offset })
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
        let mut c = LiveChild::spawn(&args);
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
    // Whole outputs: the scans of 3.5 s or less, one pose per scan after the initialisation.
    let (poses, scans, _) = check_outputs(&out);
    assert!((5..=36).contains(&scans) && poses > 0, "{scans} scans, {poses} poses: {text}");
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
    let pty = match loglio_firmware_sim::live::Pty::open() {
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
    let Some(run) = SimRun::start("live_without_imu_data_warns_and_fails_clearly", "no-imu", 3.0) else {
        return;
    };
    // An IMU device that stays silent: a pseudo-terminal nobody writes.
    let silent = loglio_firmware_sim::live::Pty::open().unwrap();
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
