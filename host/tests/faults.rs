//! The fault-tolerance table (the open fault-tolerance issue): every timing and data fault of the
//! issue, injected deterministically (`loglio_firmware_sim::fault`) into the simulator's files
//! for a handheld VLP-16 and a vehicle VLP-32C, replayed with `loglio replay PCAP --imu CSV`.
//!
//! Each row must: exit 0 without a panic, name the fault in a warning, flag a scan (not `ok`)
//! while the fault matters where the row says so, and keep the whole run's ATE within
//! `max_ate_ratio` of the clean run's. Rows that do not meet that yet are in [`KNOWN_FAILING`]
//! with the reason; the test fails when a listed row passes (strike it from the list) or an
//! unlisted row fails. `cargo test -p loglio-host --test faults -- --nocapture` prints the table.

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use loglio_firmware_sim::fault::{Fault, FaultInjector, ImuSensor, foreign_scenario, write_faulted};
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::scenario::{Scenario, ScenarioConfig, ScenarioKind};
use loglio_firmware_sim::stream::{Wire, WireEvent, WireStream};

mod common;
use common::{extrinsic_config, number_after};

/// Simulated seconds per scenario (2 s at rest, then the motion); faults start at 4 s.
const SECONDS: f64 = 12.0;
/// The injector's seed.
const SEED: u64 = 0xFA_0175;
/// A run that takes longer is killed and fails the row (a flood once made 9,545 scans).
const RUN_LIMIT: Duration = Duration::from_secs(120);

/// Rows that do not meet the criteria yet, `scenario/fault` and why (ratios to the clean
/// ATE, 0.0035 m handheld, 0.0071 m vehicle). None since 2026-11-27: the last, the handheld
/// 2 s IMU gap (4.3x), is 1.8x with the bridge holding the last scans' motion.
const KNOWN_FAILING: &[(&str, &str)] = &[];

/// One row of the table.
struct Row {
    name: &'static str,
    faults: Vec<Fault>,
    /// The whole run's ATE over the clean run's, at most.
    max_ate_ratio: f64,
    /// A warning must contain one of these (case-insensitive).
    warning_contains: &'static [&'static str],
    /// Some scan in `flag_window_s` (s after the start) must not be `ok`.
    must_flag: bool,
    flag_window_s: (f64, f64),
}

fn rows() -> Vec<Row> {
    let gap = |name, secs: f64| Row {
        name,
        faults: vec![Fault::LidarGap { from_s: 4.0, to_s: 4.0 + secs }],
        max_ate_ratio: 3.0,
        warning_contains: &["gap"],
        must_flag: true,
        flag_window_s: (4.0, 4.0 + secs + 0.5),
    };
    let single = |name, fault, words| Row {
        name,
        faults: vec![fault],
        max_ate_ratio: 1.05,
        warning_contains: words,
        must_flag: false,
        flag_window_s: (0.0, 0.0),
    };
    vec![
        gap("lidar-gap-1s", 1.0),
        gap("lidar-gap-2s", 2.0),
        gap("lidar-gap-3s", 3.0),
        gap("lidar-gap-5s", 5.0),
        single("lidar-stamp+60s", Fault::LidarStamp { at_s: 6.0, shift_s: 60.0 }, &["stamp"]),
        Row {
            name: "foreign-packets-3s",
            faults: vec![Fault::Foreign { from_s: 5.0, to_s: 8.0 }],
            max_ate_ratio: 3.0,
            warning_contains: &["foreign", "other sensor", "model"],
            // The other sensor's packets are dropped before the scan assembly (counted, said):
            // no scan is hurt, so none has to be flagged; it "matters" only if they get in.
            must_flag: false,
            flag_window_s: (5.0, 8.5),
        },
        Row {
            name: "pcap-bitflips-1e-4",
            faults: vec![Fault::FlipBits { from_s: 0.0, to_s: SECONDS, rate: 1e-4 }],
            max_ate_ratio: 3.0,
            warning_contains: &["corrupt", "invalid", "malformed", "decode"],
            must_flag: false,
            flag_window_s: (0.0, 0.0),
        },
        single(
            "imu-acc-spike-1000",
            Fault::ImuSpike { at_s: 6.0, sensor: ImuSensor::Acc, value: 1000.0 },
            &["spike", "outlier"],
        ),
        single(
            "imu-gyro-spike-1000",
            Fault::ImuSpike { at_s: 6.0, sensor: ImuSensor::Gyro, value: 1000.0 },
            &["spike", "outlier"],
        ),
        Row {
            name: "imu-gap-2s",
            faults: vec![Fault::ImuGap { from_s: 5.0, to_s: 7.0 }],
            max_ate_ratio: 3.0,
            warning_contains: &["gap"],
            must_flag: true,
            flag_window_s: (5.0, 7.5),
        },
        Row {
            name: "imu-gap-200ms",
            faults: vec![Fault::ImuGap { from_s: 5.0, to_s: 5.2 }],
            max_ate_ratio: 3.0,
            warning_contains: &["gap"],
            must_flag: false,
            flag_window_s: (0.0, 0.0),
        },
        single("imu-nan-row", Fault::ImuNan { at_s: 6.0 }, &["nan", "non-finite"]),
        single("imu-duplicated-row", Fault::ImuDuplicate { at_s: 6.0 }, &["duplicate", "repeated"]),
        single("imu-swapped-rows", Fault::ImuSwap { at_s: 6.0 }, &["order"]),
        single("imu-stamp+60s", Fault::ImuStamp { at_s: 6.0, shift_s: 60.0 }, &["stamp"]),
    ]
}

/// What one replay gave.
#[derive(Debug, Default)]
struct Outcome {
    exit_ok: bool,
    panicked: bool,
    timed_out: bool,
    ate: Option<f64>,
    summary: String,
    warnings: Vec<String>,
    /// (end time after the start, status) per scan.
    scans: Vec<(f64, String)>,
    stderr_tail: String,
}

fn run_replay(dir: &Path, out: &Path, cfg: &Path) -> Outcome {
    let p = |f: &str| dir.join(f).to_str().unwrap().to_string();
    let (pcap, imu, gt) = (p("lidar.pcap"), p("imu.csv"), p("groundtruth.tum"));
    let args = [
        "replay",
        &pcap,
        "--imu",
        &imu,
        "--config",
        cfg.to_str().unwrap(),
        "--gt",
        &gt,
        "--out",
        out.to_str().unwrap(),
    ];
    let mut child = common::loglio_command(&args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run loglio: {e}"));
    // Read both pipes on threads so a chatty run cannot block on a full pipe.
    let read = |mut r: Box<dyn std::io::Read + Send>| {
        std::thread::spawn(move || {
            let mut s = String::new();
            let _ = r.read_to_string(&mut s);
            s
        })
    };
    let so = read(Box::new(child.stdout.take().unwrap()));
    let se = read(Box::new(child.stderr.take().unwrap()));
    let start = Instant::now();
    let mut timed_out = false;
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break Some(s);
        }
        if start.elapsed() > RUN_LIMIT {
            let _ = child.kill();
            let _ = child.wait();
            timed_out = true;
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let (stdout, stderr) = (so.join().unwrap(), se.join().unwrap());
    let all = format!("{stdout}\n{stderr}");
    let summary = stdout
        .find(" scans (")
        .map(|i| {
            let close = i + stdout[i..].find(')').unwrap_or(0);
            let open = stdout[..i].rfind(|c: char| !c.is_ascii_digit()).map_or(0, |j| j + 1);
            stdout[open..=close].to_string()
        })
        .unwrap_or_default();
    // The full-precision ATE from eval.json (stdout prints 3 decimals: 0.004 against 0.003
    // would read as 1.33x); stdout's as a fallback.
    let ate = std::fs::read_to_string(out.join("eval.json"))
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v["ape_trans_m"]["rmse"].as_f64())
        .or_else(|| stdout.contains("rmse").then(|| number_after(&stdout, "rmse")))
        .filter(|a| a.is_finite());
    let warnings = stderr.lines().filter(|l| l.starts_with("warning:")).map(str::to_string).collect();
    Outcome {
        exit_ok: status.is_some_and(|s| s.success()),
        panicked: all.contains("panicked")
            || all.contains("internal error")
            || all.contains("stack backtrace"),
        timed_out,
        ate,
        summary,
        warnings,
        scans: scan_statuses(&out.join("scans.csv")),
        stderr_tail: stderr.lines().rev().take(3).collect::<Vec<_>>().join(" | "),
    }
}

/// (end_s, status) of every row of `scans.csv`, the times made relative to the first scan's
/// start.
fn scan_statuses(p: &Path) -> Vec<(f64, String)> {
    let Ok(text) = std::fs::read_to_string(p) else { return Vec::new() };
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let col = |n: &str| head.iter().position(|h| *h == n);
    let (Some(ce), Some(cs)) = (col("end_s"), col("status")) else { return Vec::new() };
    lines
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            Some((f.get(ce)?.parse().ok()?, f.get(cs)?.to_string()))
        })
        .collect()
}

/// A scenario's clean wire stream, kept in memory so every row faults the same bytes.
struct Clean {
    name: &'static str,
    sc: Scenario,
    events: Vec<WireEvent>,
    cfg: PathBuf,
    dir: common::Scratch,
    ate: f64,
    t0_s: f64,
}

fn clean(name: &'static str, kind: ScenarioKind, sensor: SensorModel) -> Clean {
    let dir = common::scratch("faults", name);
    let mut c = ScenarioConfig::new(kind, sensor, 5);
    c.duration_s = SECONDS;
    let sc = Scenario::from_config(c).unwrap();
    let events: Vec<WireEvent> = WireStream::new(&sc).collect();
    let cfg = dir.join("config.toml");
    std::fs::write(&cfg, extrinsic_config(sensor.name(), &sc.extrinsic())).unwrap();
    let files = dir.join("clean");
    write_faulted(&sc, FaultInjector::new(events.iter().cloned(), sc.start_ns(), SEED, &[]), &files).unwrap();
    let o = run_replay(&files, &dir.join("out-clean"), &cfg);
    assert!(o.exit_ok && !o.panicked, "clean {name}: {o:?}");
    let ate = o.ate.unwrap_or_else(|| panic!("clean {name}: no ATE: {o:?}"));
    assert!(ate < 0.1, "clean {name}: ATE {ate} m: {o:?}");
    let t0_s = sc.start_ns() as f64 * 1e-9;
    eprintln!("clean {name}: ATE {ate:.4} m, {}", o.summary);
    Clean { name, sc, events, cfg, dir, ate, t0_s }
}

/// The verdict on one row.
struct Verdict {
    row: String,
    ate: Option<f64>,
    ratio: Option<f64>,
    exit_ok: bool,
    no_panic: bool,
    warned: bool,
    must_flag: bool,
    flagged: bool,
    ate_ok: bool,
    summary: String,
    warnings: String,
}

impl Verdict {
    fn pass(&self) -> bool {
        self.exit_ok && self.no_panic && self.warned && self.flagged && self.ate_ok
    }
}

fn run_row(c: &Clean, row: &Row) -> Verdict {
    let files = c.dir.join(row.name);
    let mut foreign = Vec::new();
    for f in &row.faults {
        if let Fault::Foreign { from_s, to_s } = *f {
            let fs = foreign_scenario(&c.sc, from_s, to_s).unwrap();
            foreign.extend(WireStream::new(&fs).filter(|e| matches!(e.wire, Wire::Udp { .. })));
        }
    }
    let inj = FaultInjector::new(c.events.iter().cloned(), c.sc.start_ns(), SEED, &row.faults)
        .with_foreign(foreign.into_iter());
    let (_, stats) = write_faulted(&c.sc, inj, &files).unwrap();
    assert_ne!(stats, Default::default(), "{}: the fault did nothing", row.name);
    let o = run_replay(&files, &c.dir.join(format!("out-{}", row.name)), &c.cfg);
    let warned = o.warnings.iter().any(|w| {
        let w = w.to_lowercase();
        row.warning_contains.iter().any(|k| w.contains(k))
    });
    let (a, b) = row.flag_window_s;
    let flagged = !row.must_flag
        || o.scans.iter().any(|(t, s)| {
            // scans.csv times: absolute or after the start, whichever they are.
            let t = if *t > 1e8 { t - c.t0_s } else { *t };
            (a..=b).contains(&t) && s != "ok"
        });
    let ratio = o.ate.map(|x| x / c.ate);
    let mut warnings: Vec<String> =
        o.warnings.iter().map(|w| w.trim_start_matches("warning: ").to_string()).collect();
    warnings.dedup();
    let mut w = warnings.join(" / ");
    if w.chars().count() > 160 {
        w = format!("{}...", w.chars().take(160).collect::<String>());
    }
    if !o.exit_ok {
        w = format!(
            "[exit: {}] {w}",
            if o.timed_out { "timed out".to_string() } else { o.stderr_tail.clone() }
        );
    }
    Verdict {
        row: format!("{}/{}", c.name, row.name),
        ate: o.ate,
        ratio,
        exit_ok: o.exit_ok,
        no_panic: !o.panicked,
        warned,
        must_flag: row.must_flag,
        flagged,
        ate_ok: ratio.is_some_and(|r| r <= row.max_ate_ratio),
        summary: o.summary,
        warnings: w,
    }
}

fn table(kind: ScenarioKind, sensor: SensorModel, name: &'static str) {
    let t = Instant::now();
    let c = clean(name, kind, sensor);
    let verdicts: Vec<Verdict> = rows().iter().map(|r| run_row(&c, r)).collect();
    let yn = |b: bool| if b { "yes" } else { "NO" };
    let mut s = format!(
        "\n{name}: clean ATE {:.4} m ({:.0} s)\n{:<40} {:>9} {:>8} {:>4} {:>5} {:>4} {:>4} {:>4}  statuses | warnings\n",
        c.ate,
        t.elapsed().as_secs_f64(),
        "row",
        "ATE m",
        "ratio",
        "exit",
        "panic",
        "warn",
        "flag",
        "ate"
    );
    for v in &verdicts {
        s += &format!(
            "{:<40} {:>9} {:>8} {:>4} {:>5} {:>4} {:>4} {:>4}  {} | {}\n",
            v.row,
            v.ate.map_or("-".into(), |a| format!("{a:.4}")),
            v.ratio.map_or("-".into(), |r| format!("{r:.2}")),
            yn(v.exit_ok),
            if v.no_panic { "no" } else { "YES" },
            yn(v.warned),
            if v.must_flag { yn(v.flagged) } else { "-" },
            yn(v.ate_ok),
            v.summary,
            v.warnings
        );
    }
    eprintln!("{s}");
    let mut wrong = Vec::new();
    for (r, _) in KNOWN_FAILING.iter().filter(|(r, _)| r.starts_with(&format!("{name}/"))) {
        if !verdicts.iter().any(|v| v.row == *r) {
            wrong.push(format!("{r} in KNOWN_FAILING is no row of the table"));
        }
    }
    for v in &verdicts {
        if !v.no_panic {
            wrong.push(format!("{} panicked: never allowed, listed or not", v.row));
        }
        let listed = KNOWN_FAILING.iter().find(|(r, _)| *r == v.row);
        match (v.pass(), listed) {
            (true, Some((r, why))) => {
                wrong.push(format!("{r} passes now: strike it from KNOWN_FAILING ({why})"))
            }
            (false, None) => wrong.push(format!("{} fails and is not in KNOWN_FAILING", v.row)),
            _ => {}
        }
    }
    let _ = std::fs::remove_dir_all(&c.dir);
    assert!(wrong.is_empty(), "{}\n{s}", wrong.join("\n"));
}

/// Under an emulating runner (the aarch64 build under qemu-user in CI) the 32 replays would
/// take most of an hour; the table runs natively, the cross build's other tests run there.
fn skipped_under_runner(test: &str) -> bool {
    if let Some(r) = common::runner() {
        println!("{test}: skipped under LOGLIO_TEST_RUNNER ({r}): 32 emulated replays; run natively");
        return true;
    }
    false
}

#[test]
fn faults_handheld_vlp16() {
    if skipped_under_runner("faults_handheld_vlp16") {
        return;
    }
    table(ScenarioKind::Handheld, SensorModel::Vlp16, "handheld-vlp16");
}

#[test]
fn faults_vehicle_vlp32c() {
    if skipped_under_runner("faults_vehicle_vlp32c") {
        return;
    }
    table(ScenarioKind::Vehicle, SensorModel::Vlp32c, "vehicle-vlp32c");
}
