//! `--ros2` against an independent DDS implementation: a Cyclone DDS (Python) subscriber
//! declares the ROS 2 topics and types loglio should publish, then `loglio sim --ros2` runs;
//! what it received is compared with the run's trajectory.tum and scans.csv.
//!
//! Discovery uses loopback unicast only (Cyclone's `Peers` list is 127.0.0.1; loglio sends
//! its SPDP to the well-known localhost ports too), so no multicast is needed on `lo`. Each test
//! has its own `ROS_DOMAIN_ID` (from the process id) so parallel runs do not see each other.
//! Needs the peers' Python (`LOGLIO_PYTHON`, see [`common::peer_python`]).

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::Mutex;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;

/// The simulator runs are real time on a small machine: one at a time.
static SERIAL: Mutex<()> = Mutex::new(());

/// The Cyclone DDS subscriber: every message of the five topics, summarised as JSON on stdout
/// when stdin closes. With `die-after-first` it exits at the first odometry instead.
const SUBSCRIBER: &str = r#"import json, math, os, sys, threading, time
from dataclasses import dataclass
from cyclonedds.domain import DomainParticipant
from cyclonedds.topic import Topic
from cyclonedds.sub import DataReader
from cyclonedds.core import Qos, Policy
from cyclonedds.idl import IdlStruct
from cyclonedds.util import duration
from cyclonedds.idl.types import int32, uint32, uint8, float64, sequence, array

{ROS2_TYPES}def reliable(depth, latched=False):
    p = [Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)), Policy.History.KeepLast(depth)]
    if latched:
        p.append(Policy.Durability.TransientLocal)
    return Qos(*p)

dp = DomainParticipant(int(sys.argv[1]))
t0 = time.monotonic()
topics = {}
def reader(name, ty, depth=1000, latched=False):
    if name not in topics:
        topics[name] = Topic(dp, name, ty)
    return DataReader(dp, topics[name], qos=reliable(depth, latched))
r_odom = reader("rt/loglio/odometry", Odometry)
r_imu = reader("rt/loglio/odometry_imu", Odometry, 10000)
r_tf = reader("rt/tf", TFMessage)
r_cloud = reader("rt/loglio/cloud", PointCloud2)
r_map = reader("rt/loglio/map", PointCloud2, 10, True)
late_map = None
out = {"odom": [], "imu": [], "tf": [], "cloud": [], "map": [], "late_map": []}
first_t = None

def take(r, n, ty):
    # Skips the no-data samples (a writer that leaves).
    return [m for m in r.take(n) if isinstance(m, ty)]

def stamp(h):
    return [h.stamp.sec, h.stamp.nanosec]

def odo(m):
    p, q = m.pose.pose.position, m.pose.pose.orientation
    return {"stamp": stamp(m.header), "frame": m.header.frame_id, "child": m.child_frame_id,
            "p": [p.x, p.y, p.z], "q": [q.x, q.y, q.z, q.w], "pcov": list(m.pose.covariance),
            "tcov": list(m.twist.covariance),
            "v": [m.twist.twist.linear.x, m.twist.twist.linear.y, m.twist.twist.linear.z]}

def cloud(m):
    import struct
    n = len(m.data) // 12 if m.point_step == 12 else 0
    pts = struct.unpack("<%df" % (3 * n), bytes(m.data[:12 * n])) if n else ()
    finite = all(math.isfinite(v) for v in pts)
    norms = [math.sqrt(pts[i] ** 2 + pts[i + 1] ** 2 + pts[i + 2] ** 2) for i in range(0, len(pts), 3)]
    return {"stamp": stamp(m.header), "frame": m.header.frame_id, "height": m.height, "width": m.width,
            "fields": [[f.name, f.offset, f.datatype, f.count] for f in m.fields],
            "is_bigendian": m.is_bigendian, "point_step": m.point_step, "row_step": m.row_step,
            "len": len(m.data), "is_dense": m.is_dense, "finite": finite,
            "max_norm": max(norms) if norms else 0.0}

die_after_first = len(sys.argv) > 2 and sys.argv[2] == "die-after-first"
print("ready", flush=True)
stop = threading.Event()
threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
last = False
while not last:
    last = stop.is_set()
    got = False
    for m in take(r_odom, 100, Odometry):
        got = True
        if first_t is None:
            first_t = time.monotonic() - t0
        out["odom"].append(odo(m))
        if die_after_first:
            # A subscriber that vanishes without leaving the domain.
            print("dying", flush=True)
            os._exit(0)
    for m in take(r_imu, 1000, Odometry):
        got = True
        out["imu"].append({"stamp": stamp(m.header), "frame": m.header.frame_id, "child": m.child_frame_id})
    for m in take(r_tf, 100, TFMessage):
        got = True
        for t in m.transforms:
            tr, q = t.transform.translation, t.transform.rotation
            out["tf"].append({"stamp": stamp(t.header), "frame": t.header.frame_id, "child": t.child_frame_id,
                              "p": [tr.x, tr.y, tr.z], "q": [q.x, q.y, q.z, q.w]})
    for m in take(r_cloud, 100, PointCloud2):
        got = True
        out["cloud"].append(cloud(m))
    for m in take(r_map, 10, PointCloud2):
        got = True
        out["map"].append(cloud(m))
        if late_map is None:
            # A subscriber that joins after the map was sent gets it (transient local).
            late_map = reader("rt/loglio/map", PointCloud2, 1, True)
    if late_map is not None:
        for m in take(late_map, 10, PointCloud2):
            out["late_map"].append(cloud(m))
    if not got and not last:
        time.sleep(0.005)
out["first_odom_s"] = first_t
print(json.dumps(out), flush=True)
"#;

/// Skips (with the reason on stdout) under an emulating runner: the emulated odometry cannot
/// keep up with `--realtime`, and the timing bounds would not hold.
fn skip_under_runner(test: &str) -> bool {
    if let Some(r) = common::runner() {
        println!("{test}: skipped under LOGLIO_TEST_RUNNER ({r}): the emulated run cannot keep real time");
        return true;
    }
    false
}

fn domain(salt: u32) -> String {
    (1 + (std::process::id() * 3 + salt) % 200).to_string()
}

/// A started subscriber, ready (its readers created).
struct Subscriber {
    child: Child,
    lines: mpsc::Receiver<String>,
    _reader: std::thread::JoinHandle<()>,
}

impl Subscriber {
    fn start(python: &Path, dir: &Path, domain: &str, mode: &str) -> Subscriber {
        let script = dir.join("sub.py");
        std::fs::write(&script, common::with_ros2_types(SUBSCRIBER)).unwrap();
        let xml = dir.join("cyclonedds.xml");
        std::fs::write(&xml, common::CYCLONE_XML).unwrap();
        let mut child = Command::new(python)
            .arg(&script)
            .arg(domain)
            .arg(mode)
            .env("CYCLONEDDS_URI", format!("file://{}", xml.display()))
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot run {}: {e}", python.display()));
        let out: ChildStdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        let reader = std::thread::spawn(move || {
            for l in BufReader::new(out).lines().map_while(Result::ok) {
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        let s = Subscriber { child, lines, _reader: reader };
        assert_eq!(s.line(Duration::from_secs(20)).as_deref(), Some("ready"), "the subscriber did not start");
        s
    }

    fn line(&self, timeout: Duration) -> Option<String> {
        self.lines.recv_timeout(timeout).ok()
    }

    /// Closes its stdin and returns what it received.
    fn finish(mut self) -> Value {
        drop(self.child.stdin.take());
        let line = self.line(Duration::from_secs(20)).expect("the subscriber said nothing");
        let _ = self.child.wait();
        serde_json::from_str(&line).unwrap_or_else(|e| panic!("subscriber output {e}: {line:.200}"))
    }
}

impl Drop for Subscriber {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn sim(dir: &Path, domain: &str, extra: &[&str]) -> std::process::Output {
    let out = dir.join("out");
    let mut args =
        vec!["sim", "--scenario", "handheld", "--sensor", "os1-16", "--seconds", "6", "--seed", "5"];
    args.extend(["--out", out.to_str().unwrap(), "--ros2", "--realtime", "--rate", "2"]);
    args.extend(extra);
    common::loglio_command(&args).env("ROS_DOMAIN_ID", domain).output().unwrap()
}

/// (sec, nanosec) of a `sec.nnnnnnnnn` stamp.
fn stamp_of(s: &str) -> (i64, i64) {
    let (a, b) = s.split_once('.').unwrap();
    (a.parse().unwrap(), b.parse().unwrap())
}

fn stamp_json(v: &Value) -> (i64, i64) {
    (v[0].as_i64().unwrap(), v[1].as_i64().unwrap())
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

fn close(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-9 * (1.0 + y.abs()))
}

#[test]
fn ros2_topics_reach_a_cyclone_dds_subscriber() {
    let Some(python) = common::peer_python("ros2_topics_reach_a_cyclone_dds_subscriber") else { return };
    if skip_under_runner("ros2_topics_reach_a_cyclone_dds_subscriber") {
        return;
    }
    let _g = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let dir = common::scratch("ros2", "topics");
    let domain = domain(0);
    let sub = Subscriber::start(&python, &dir, &domain, "all");
    let t = Instant::now();
    let out = sim(&dir, &domain, &["--map-every", "2"]);
    let run_s = t.elapsed().as_secs_f64();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(!err.contains("warning") && !err.contains("panicked"), "{err}");
    let got = sub.finish();

    // The trajectory: stamp -> (position, orientation x y z w).
    let tum = std::fs::read_to_string(dir.join("out/trajectory.tum")).unwrap();
    let traj: HashMap<(i64, i64), Vec<f64>> = tum
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            (stamp_of(f[0]), f[1..8].iter().map(|v| v.parse().unwrap()).collect())
        })
        .collect();
    let scans = std::fs::read_to_string(dir.join("out/scans.csv")).unwrap();
    let used: HashMap<(i64, i64), u64> = scans
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (stamp_of(f[2]), f[4].parse().unwrap())
        })
        .collect();
    assert!(traj.len() >= 50, "{} poses in trajectory.tum", traj.len());

    let odom = got["odom"].as_array().unwrap();
    let first_s = got["first_odom_s"].as_f64().unwrap_or(f64::NAN);
    println!(
        "ros2: {} of {} scan poses received, {} IMU-rate poses, {} tf, {} clouds, {} maps ({} late); first odometry {first_s:.2} s after the subscriber was ready, run {run_s:.1} s",
        odom.len(),
        traj.len(),
        got["imu"].as_array().unwrap().len(),
        got["tf"].as_array().unwrap().len(),
        got["cloud"].as_array().unwrap().len(),
        got["map"].as_array().unwrap().len(),
        got["late_map"].as_array().unwrap().len(),
    );
    assert!(odom.len() as f64 >= 0.9 * traj.len() as f64, "{} of {} poses", odom.len(), traj.len());
    assert!(odom.len() <= traj.len());
    let mut last = (0, 0);
    for m in odom {
        let s = stamp_json(&m["stamp"]);
        assert!(s > last, "stamps increase");
        last = s;
        let want = traj.get(&s).unwrap_or_else(|| panic!("odometry at {s:?} is not in trajectory.tum"));
        let mut pq = floats(&m["p"]);
        pq.extend(floats(&m["q"]));
        assert!(close(&pq, want), "{s:?}: {pq:?} vs {want:?}");
        assert_eq!((m["frame"].as_str(), m["child"].as_str()), (Some("odom"), Some("base_link")));
        let c = floats(&m["pcov"]);
        assert_eq!(c.len(), 36);
        assert!(c.iter().all(|v| v.is_finite()));
        assert!((0..6).all(|i| c[i * 7] > 0.0), "{c:?}");
        assert!(
            (0..6).all(
                |i| (0..6).all(|k| (c[i * 6 + k] - c[k * 6 + i]).abs() <= 1e-12 * c[i * 7].max(c[k * 7]))
            )
        );
        let t = floats(&m["tcov"]);
        assert!((0..6).all(|i| t[i * 7] > 0.0 && t[i * 7].is_finite()), "{t:?}");
        assert!(floats(&m["v"]).iter().all(|v| v.is_finite() && v.abs() < 10.0));
    }

    // /tf: the same poses, odom -> base_link.
    let tf = got["tf"].as_array().unwrap();
    assert_eq!(tf.len(), odom.len());
    for (t, o) in tf.iter().zip(odom) {
        assert_eq!(t["stamp"], o["stamp"]);
        assert_eq!((t["frame"].as_str(), t["child"].as_str()), (Some("odom"), Some("base_link")));
        assert!(close(&floats(&t["p"]), &floats(&o["p"])) && close(&floats(&t["q"]), &floats(&o["q"])));
    }

    // The scans: x, y, z float32, as many as the scan used, around the sensor.
    let clouds = got["cloud"].as_array().unwrap();
    assert!(clouds.len() as f64 >= 0.9 * traj.len() as f64, "{} clouds", clouds.len());
    let fields = serde_json::json!([["x", 0, 7, 1], ["y", 4, 7, 1], ["z", 8, 7, 1]]);
    for (i, c) in clouds.iter().chain(got["map"].as_array().unwrap()).enumerate() {
        let u = |k: &str| c[k].as_u64().unwrap();
        assert_eq!(c["frame"].as_str(), Some("odom"));
        assert_eq!(c["fields"], fields);
        assert_eq!((u("height"), u("point_step"), c["is_bigendian"].as_bool()), (1, 12, Some(false)));
        assert_eq!(u("row_step"), 12 * u("width"));
        assert_eq!(u("width") * u("height") * u("point_step"), u("len"));
        assert!(c["is_dense"].as_bool().unwrap() && c["finite"].as_bool().unwrap());
        assert!(u("width") > 100, "{c}");
        if i < clouds.len() {
            let s = stamp_json(&c["stamp"]);
            assert_eq!(Some(&u("width")), used.get(&s), "cloud at {s:?}: points vs scans.csv");
            assert!(c["max_norm"].as_f64().unwrap() < 200.0);
        }
    }
    // The map: every 2 s of the 6 s (after the initialisation), and latched for a late reader.
    let maps = got["map"].as_array().unwrap();
    assert!(maps.len() >= 2, "{} maps", maps.len());
    let late = got["late_map"].as_array().unwrap();
    assert!(!late.is_empty(), "a late subscriber got no map");
    assert!(maps.iter().any(|m| m["stamp"] == late[0]["stamp"] && m["width"] == late[0]["width"]));

    // The IMU-rate poses: many per scan, stamps between the scans'.
    let imu = got["imu"].as_array().unwrap();
    assert!(imu.len() >= 5 * odom.len(), "{} IMU-rate poses", imu.len());
    assert!(imu.iter().all(|m| m["frame"] == "odom" && m["child"] == "base_link"));
}

#[test]
fn ros2_subscriber_that_vanishes_does_not_stall_the_run() {
    let Some(python) = common::peer_python("ros2_subscriber_that_vanishes_does_not_stall_the_run") else {
        return;
    };
    if skip_under_runner("ros2_subscriber_that_vanishes_does_not_stall_the_run") {
        return;
    }
    let _g = SERIAL.lock().unwrap_or_else(|p| p.into_inner());
    let dir = common::scratch("ros2", "vanish");
    let domain = domain(1);
    let mut sub = Subscriber::start(&python, &dir, &domain, "die-after-first");
    let t = Instant::now();
    let out = sim(&dir, &domain, &["--ros2-namespace", "/loglio", "--ros2-frame-id", "odom"]);
    let run_s = t.elapsed().as_secs_f64();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && !err.contains("panicked"), "{err}");
    assert_eq!(sub.line(Duration::from_secs(1)).as_deref(), Some("dying"), "the subscriber got no odometry");
    let _ = sub.child.stdin.take().map(|mut s| s.write_all(b""));
    // 3 s of data at rate 2, the 2 s wait for acknowledgements at the end, start-up.
    assert!(run_s < 12.0, "the run took {run_s:.1} s");
    let tum = std::fs::read_to_string(dir.join("out/trajectory.tum")).unwrap();
    assert!(tum.lines().count() >= 50);
}

#[test]
fn ros2_bad_settings_warn_and_the_run_goes_on() {
    let dir = common::scratch("ros2", "bad");
    for (env, extra, says) in [
        (
            "7",
            vec!["--ros2-namespace", "loglio"],
            "warning: --ros2: --ros2-namespace \"loglio\": must start with '/'",
        ),
        (
            "7",
            vec!["--ros2-frame-id", "/odom"],
            "warning: --ros2: --ros2-frame-id \"/odom\": a frame id is non-empty",
        ),
        ("500", vec![], "warning: --ros2: ROS_DOMAIN_ID=\"500\" is not a domain id (0-232)"),
    ] {
        let out = dir.join("out");
        let mut args = vec!["sim", "--scenario", "handheld", "--sensor", "os1-16", "--seconds", "2"];
        args.extend(["--out", out.to_str().unwrap(), "--ros2"]);
        args.extend(extra);
        let o = common::loglio_command(&args).env("ROS_DOMAIN_ID", env).output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success(), "{err}");
        // (A 2 s run also warns that it is too short to evaluate.)
        let warnings: Vec<&str> = err.lines().filter(|l| l.contains("ros2")).collect();
        assert_eq!(warnings.len(), 1, "{err}");
        assert!(
            warnings[0].starts_with(says) && warnings[0].ends_with("this output is off for the run"),
            "{err}"
        );
    }
}
