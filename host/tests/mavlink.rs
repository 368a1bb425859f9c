//! The MAVLink output against an independent decoder: pymavlink (its generated `common`
//! dialect checks every frame's CRC with CRC_EXTRA and unpacks the fields by its own layout).

mod common;

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Instant;

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use serde_json::Value;

/// With `udp`, binds UDP port 0 on 127.0.0.1 and prints the port; with `pty`, opens a
/// pseudo-terminal and prints the path of its serial end. Then decodes every datagram or byte
/// with pymavlink until the file `done` appears and 0.5 s pass without data (60 s at most), and
/// writes every message (NaN as null) and what it could not decode to `msgs.json`.
const LISTENER: &str = r#"
import json, math, os, select, socket, sys, time
from pymavlink.dialects.v20 import common as mavlink
d, mode = sys.argv[1], sys.argv[2]
if mode == "udp":
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(0.1)
    print(s.getsockname()[1], flush=True)
    def recv():
        try:
            return s.recv(65536)
        except socket.timeout:
            return None
else:
    master, slave = os.openpty()
    print(os.ttyname(slave), flush=True)
    def recv():
        r, _, _ = select.select([master], [], [], 0.1)
        return os.read(master, 65536) if r else None
mav = mavlink.MAVLink(None)
mav.robust_parsing = True
out, bad, datagrams = [], [], 0
start = time.monotonic(); last = start
def clean(v):
    if isinstance(v, float) and math.isnan(v): return None
    if isinstance(v, list): return [clean(x) for x in v]
    return v
while time.monotonic() - start < 60:
    data = recv()
    if data is None:
        if os.path.exists(os.path.join(d, "done")) and time.monotonic() - last > 0.5:
            break
        continue
    now = time.monotonic(); last = now; datagrams += 1
    for m in mav.parse_buffer(data) or []:
        if m.get_type() == "BAD_DATA":
            bad.append(repr(m)); continue
        f = {k: clean(v) for k, v in m.to_dict().items()}
        f.update(_wall=now - start, _seq=m.get_seq(), _sys=m.get_srcSystem(), _comp=m.get_srcComponent(),
                 _len=len(m.get_msgbuf()))
        out.append(f)
json.dump({"msgs": out, "bad": bad, "datagrams": datagrams}, open(os.path.join(d, "msgs.json"), "w"))
"#;

struct Listener {
    child: Child,
    /// The UDP port, or the serial device's path.
    addr: String,
    dir: std::path::PathBuf,
}

impl Listener {
    fn start(python: &Path, dir: &Path, mode: &str) -> Listener {
        let script = dir.join("listen.py");
        std::fs::write(&script, LISTENER).unwrap();
        let mut child = Command::new(python)
            .arg(&script)
            .arg(dir)
            .arg(mode)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start the pymavlink listener");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        assert!(!line.trim().is_empty(), "the listener did not start");
        Listener { child, addr: line.trim().to_string(), dir: dir.to_path_buf() }
    }

    /// Tells the listener the sender is done and returns what it decoded.
    fn finish(mut self) -> Value {
        std::fs::write(self.dir.join("done"), "").unwrap();
        let st = self.child.wait().unwrap();
        assert!(st.success(), "listener failed: {st}");
        serde_json::from_str(&std::fs::read_to_string(self.dir.join("msgs.json")).unwrap()).unwrap()
    }
}

/// TUM poses: (time in ns, exactly as written; position; quaternion w, x, y, z).
fn read_tum(path: &Path) -> Vec<(u64, [f64; 3], [f64; 4])> {
    let text = std::fs::read_to_string(path).unwrap();
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            let (s, frac) = f[0].split_once('.').unwrap_or((f[0], "0"));
            let frac = format!("{frac:0<9}");
            let t = s.parse::<u64>().unwrap() * 1_000_000_000 + frac[..9].parse::<u64>().unwrap();
            let v: Vec<f64> = f[1..8].iter().map(|x| x.parse().unwrap()).collect();
            (t, [v[0], v[1], v[2]], [v[6], v[3], v[4], v[5]])
        })
        .collect()
}

fn f(m: &Value, k: &str) -> f64 {
    m[k].as_f64().unwrap_or_else(|| panic!("{k} of {m}"))
}

fn fa(m: &Value, k: &str) -> Vec<f64> {
    m[k].as_array().unwrap().iter().map(|v| v.as_f64().unwrap_or(f64::NAN)).collect()
}

#[test]
fn every_scan_pose_and_the_imu_rate_reach_pymavlink() {
    let Some(python) = common::peer_python("mavlink end to end") else { return };
    let dir = common::scratch("mavlink", "e2e");
    let out = dir.join("out");
    let lis = Listener::start(&python, &dir, "udp");
    let url = format!("udp:127.0.0.1:{}", lis.addr);
    let t0 = Instant::now();
    let run = common::loglio_command(&[
        "sim",
        "--scenario",
        "handheld",
        "--sensor",
        "os1-16",
        "--seconds",
        "6",
        "--out",
        out.to_str().unwrap(),
        "--realtime",
        "--rate",
        "2",
        "--mavlink",
        &url,
    ])
    .output()
    .unwrap();
    let wall = t0.elapsed().as_secs_f64();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(!stderr.contains("warning:") && !stderr.contains("panicked"), "{stderr}");
    let got = lis.finish();
    assert_eq!(got["bad"].as_array().unwrap().len(), 0, "frames pymavlink rejected: {}", got["bad"]);
    let msgs = got["msgs"].as_array().unwrap();

    // HEARTBEAT: about one per wall second (the run is paced at twice real time), as a component.
    let hb: Vec<&Value> = msgs.iter().filter(|m| m["mavpackettype"] == "HEARTBEAT").collect();
    assert!((hb.len() as f64 - wall).abs() <= 1.5, "{} heartbeats in {wall:.1} s", hb.len());
    for h in &hb {
        assert_eq!((f(h, "type"), f(h, "autopilot"), f(h, "mavlink_version")), (18.0, 8.0, 3.0), "{h}");
    }
    assert!(hb.iter().any(|h| f(h, "system_status") == 4.0 || f(h, "system_status") == 1.0));

    let odo: Vec<&Value> = msgs.iter().filter(|m| m["mavpackettype"] == "ODOMETRY").collect();
    assert_eq!(hb.len() + odo.len(), msgs.len(), "only HEARTBEAT and ODOMETRY");
    for m in msgs {
        assert_eq!((f(m, "_sys"), f(m, "_comp")), (1.0, 197.0));
    }
    // Every frame arrived, in order: the sequence counts up by one (mod 256).
    for w in msgs.windows(2) {
        assert_eq!((f(&w[0], "_seq") as u32 + 1) % 256, f(&w[1], "_seq") as u32, "a frame went missing");
    }
    let mut by_time: BTreeMap<u64, Vec<&Value>> = BTreeMap::new();
    for m in &odo {
        assert_eq!((f(m, "frame_id"), f(m, "child_frame_id"), f(m, "estimator_type")), (20.0, 12.0, 7.0));
        assert_eq!(f(m, "reset_counter"), 0.0);
        by_time.entry(m["time_usec"].as_u64().unwrap()).or_default().push(m);
    }

    // Every scan pose of the trajectory, converted back from FRD, equals the TUM's.
    let tum = read_tum(&out.join("trajectory.tum"));
    assert!(tum.len() >= 45, "{} poses", tum.len());
    let (mut worst_p, mut worst_q) = (0.0f64, 0.0f64);
    for (t, p, q) in &tum {
        let cands = by_time.get(&(t / 1000)).unwrap_or_else(|| panic!("no ODOMETRY at {t} ns"));
        let err = |m: &Value| {
            let back_p = [f(m, "x"), -f(m, "y"), -f(m, "z")];
            let mq = fa(m, "q");
            let back_q = [mq[0], mq[1], -mq[2], -mq[3]];
            let dp = (0..3).map(|i| (back_p[i] - p[i]).abs()).fold(0.0, f64::max);
            let dq = |s: f64| (0..4).map(|i| (s * back_q[i] - q[i]).abs()).fold(0.0, f64::max);
            (dp, dq(1.0).min(dq(-1.0)))
        };
        let m = *cands.iter().min_by(|a, b| err(a).0.total_cmp(&err(b).0)).unwrap();
        let (dp, dq) = err(m);
        worst_p = worst_p.max(dp);
        worst_q = worst_q.max(dq);
        assert!(dp < 1e-4 && dq < 1e-5, "pose at {t}: {dp} m, {dq} off: {m}");
        let qual = f(m, "quality");
        assert!(qual > 0.0 && qual <= 100.0, "quality {qual}");
        let cov = fa(m, "pose_covariance");
        // Variances (x, y, z, roll, pitch, yaw on the diagonal) finite and non-negative.
        for k in [0, 6, 11, 15, 18, 20] {
            assert!(cov[k].is_finite() && cov[k] >= 0.0, "{cov:?}");
        }
        let vcov = fa(m, "velocity_covariance");
        assert!(vcov[0].is_finite() && vcov[0] >= 0.0 && vcov[15].is_nan(), "{vcov:?}");
    }

    // Velocity and body rates, turned back from FRD, agree with the trajectory's finite
    // differences (central, over two scans): the frames of the twist are right.
    let (mut worst_v, mut worst_w) = (0.0f64, 0.0f64);
    for k in 1..tum.len() - 1 {
        let (t0, p0, q0) = tum[k - 1];
        let t1 = tum[k].0;
        let (t2, p2, _) = tum[k + 1];
        if t2 - t0 > 250_000_000 {
            continue;
        }
        let Some(m) = by_time.get(&(t1 / 1000)).and_then(|c| c.first()) else { continue };
        let quat = |q: [f64; 4]| UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]));
        let flip = |v: Vector3<f64>| Vector3::new(v.x, -v.y, -v.z);
        let mq = fa(m, "q");
        let r_frd = quat([mq[0], mq[1], mq[2], mq[3]]);
        let v_body = Vector3::new(f(m, "vx"), f(m, "vy"), f(m, "vz"));
        let v_world = flip(r_frd * v_body);
        let v_fd = (Vector3::from(p2) - Vector3::from(p0)) / ((t2 - t0) as f64 * 1e-9);
        worst_v = worst_v.max((v_world - v_fd).norm() / (0.05 + 0.1 * v_fd.norm()));
        let w_body = flip(Vector3::new(f(m, "rollspeed"), f(m, "pitchspeed"), f(m, "yawspeed")));
        let w_fd = (quat(q0).inverse() * quat(tum[k + 1].2)).scaled_axis() / ((t2 - t0) as f64 * 1e-9);
        worst_w = worst_w.max((w_body - w_fd).norm() / (0.05 + 0.2 * w_fd.norm()));
    }
    assert!(
        worst_v < 1.0 && worst_w < 1.0,
        "twist off: velocity {worst_v:.2}, rates {worst_w:.2} of the tolerance"
    );

    // Between scans, IMU poses: with the scans, about the requested 50 Hz of data time (none
    // in the first gap, before two scans gave the interval).
    let scan_us: Vec<u64> = tum.iter().map(|(t, ..)| t / 1000).collect();
    let first = scan_us[0];
    let last = *scan_us.last().unwrap();
    let imu = odo
        .iter()
        .filter(|m| {
            let t = m["time_usec"].as_u64().unwrap();
            t > first && t <= last && scan_us.binary_search(&t).is_err()
        })
        .count();
    let rate = imu as f64 / ((last - first) as f64 * 1e-6);
    let per_gap: Vec<usize> = scan_us
        .windows(2)
        .map(|w| odo.iter().filter(|m| (w[0] + 1..w[1]).contains(&m["time_usec"].as_u64().unwrap())).count())
        .collect();
    let backwards = odo
        .windows(2)
        .filter(|w| w[1]["time_usec"].as_u64().unwrap() <= w[0]["time_usec"].as_u64().unwrap())
        .count();
    eprintln!(
        "mavlink e2e: {} datagrams, {} HEARTBEAT, {} ODOMETRY ({} scan poses, IMU poses {rate:.1} Hz of data \
         time, {:?} per scan gap), {backwards} time steps not forward; worst |dp| {worst_p:.2e} m, |dq| \
         {worst_q:.2e}; twist {worst_v:.2} / {worst_w:.2} of the tolerance; loglio wall {wall:.2} s",
        got["datagrams"],
        hb.len(),
        odo.len(),
        tum.len(),
        per_gap.iter().skip(1).min().zip(per_gap.iter().max()),
    );
    assert!((35.0..=45.0).contains(&rate), "IMU-pose rate {rate:.1} Hz (plus 10 Hz of scans)");
    assert!(per_gap[1..].iter().all(|&n| (3..=4).contains(&n)), "IMU poses per 100 ms scan gap: {per_gap:?}");
    // Time only moves forward: an autopilot drops a pose not newer than the last.
    assert_eq!(backwards, 0);
}

/// Runs a short sim with `--mavlink url`; returns (exit code, stderr, TUM poses written).
fn run_with(url: &str, name: &str) -> (Option<i32>, String, usize) {
    let out = common::scratch("mavlink", name);
    let o = common::loglio_command(&[
        "sim",
        "--scenario",
        "handheld",
        "--sensor",
        "os1-16",
        "--seconds",
        "3",
        "--out",
        out.to_str().unwrap(),
        "--mavlink",
        url,
    ])
    .output()
    .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!stderr.contains("panicked"), "{stderr}");
    let tum = std::fs::read_to_string(out.join("trajectory.tum"))
        .map(|t| t.lines().filter(|l| !l.starts_with('#')).count());
    (o.status.code(), stderr, tum.unwrap_or(0))
}

#[test]
fn unreachable_or_malformed_addresses_never_stop_the_odometry() {
    // Nothing listens on the port: the kernel's ICMP "port unreachable" fails the sends.
    let free = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let port = free.local_addr().unwrap().port();
    drop(free);
    let t0 = Instant::now();
    let (code, stderr, poses) = run_with(&format!("udp:127.0.0.1:{port}"), "refused");
    let warnings: Vec<&str> = stderr.lines().filter(|l| l.starts_with("warning:")).collect();
    assert_eq!(code, Some(0), "{stderr}");
    assert_eq!(warnings.len(), 1, "{stderr}");
    assert!(warnings[0].contains("mavlink udp:127.0.0.1") && warnings[0].contains("refused"), "{stderr}");
    // A complete trajectory: 3 s at 10 Hz, less the initialisation.
    assert!(poses >= 18, "{poses} poses; {stderr}");
    let refused_s = t0.elapsed().as_secs_f64();

    // An address with no route (TEST-NET-1) either fails at the start or sends into the void:
    // at most one warning, the odometry complete either way.
    let (code, stderr, poses2) = run_with("udp:192.0.2.1:14550", "unroutable");
    assert_eq!(code, Some(0), "{stderr}");
    assert!(stderr.lines().filter(|l| l.starts_with("warning:")).count() <= 1, "{stderr}");
    assert_eq!(poses2, poses, "{stderr}");

    // Malformed URLs: one `error:` line and exit 2, before anything runs.
    for bad in ["udp:127.0.0.1", "tcp:127.0.0.1:5", "udp:host:notaport", "serial:/dev/ttyX:fast"] {
        let (code, stderr, _) = run_with(bad, "malformed");
        assert_eq!(code, Some(2), "{bad}: {stderr}");
        assert_eq!(stderr.trim().lines().count(), 1, "{bad}: {stderr}");
        assert!(stderr.starts_with("error:") && stderr.contains("--mavlink"), "{bad}: {stderr}");
    }
    // A serial port that does not exist: a warning at the start, the run goes on.
    let (code, stderr, poses3) = run_with("serial:/dev/loglio-no-such-tty:921600", "noserial");
    assert_eq!(code, Some(0), "{stderr}");
    assert_eq!(stderr.lines().filter(|l| l.starts_with("warning:")).count(), 1, "{stderr}");
    assert!(stderr.contains("mavlink serial:/dev/loglio-no-such-tty:921600"), "{stderr}");
    assert_eq!(poses3, poses, "{stderr}");
    eprintln!("mavlink faults: the refused run took {refused_s:.2} s; {poses} poses each");
}

#[test]
fn serial_output_reaches_pymavlink_through_a_pty() {
    let Some(python) = common::peer_python("mavlink serial") else { return };
    let dir = common::scratch("mavlink", "pty");
    let lis = Listener::start(&python, &dir, "pty");
    let out = dir.join("out");
    let url = format!("serial:{}:921600", lis.addr);
    let args = ["sim", "--scenario", "handheld", "--sensor", "os1-16", "--seconds", "3", "--out"];
    let run = common::loglio_command(&args)
        .arg(&out)
        .args(["--mavlink", &url, "--mavlink-sysid", "42"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success() && !stderr.contains("warning:"), "{stderr}");
    let got = lis.finish();
    assert_eq!(got["bad"].as_array().unwrap().len(), 0, "bytes pymavlink rejected: {}", got["bad"]);
    let msgs = got["msgs"].as_array().unwrap();
    let times: std::collections::BTreeSet<u64> = msgs
        .iter()
        .filter(|m| m["mavpackettype"] == "ODOMETRY")
        .map(|m| m["time_usec"].as_u64().unwrap())
        .collect();
    let tum = read_tum(&out.join("trajectory.tum"));
    assert!(tum.len() >= 18);
    assert!(tum.iter().all(|(t, ..)| times.contains(&(t / 1000))), "a scan pose is missing");
    // The IMU poses too: four between scans after the first two.
    assert_eq!(times.len(), tum.len() + 4 * (tum.len() - 2), "{times:?}");
    assert!(msgs.iter().any(|m| m["mavpackettype"] == "HEARTBEAT"));
    assert!(msgs.iter().all(|m| (f(m, "_sys"), f(m, "_comp")) == (42.0, 197.0)), "--mavlink-sysid 42");
    eprintln!("mavlink serial: {} messages over the pty for {} scan poses", msgs.len(), tum.len());
}

/// Encodes IMU messages with pymavlink and prints each frame as a hex line: RAW_IMU (MAVLink 2,
/// signed), SCALED_IMU (MAVLink 1), a HEARTBEAT, HIGHRES_IMU (MAVLink 2; zeros at its end, which
/// MAVLink 2 truncates).
const IMU_ENCODER: &str = r#"
from pymavlink.dialects.v20 import common as m2
from pymavlink.dialects.v10 import common as m1
class Sink:
    def write(self, b): pass
signed = m2.MAVLink(Sink(), srcSystem=1, srcComponent=1)
signed.signing.secret_key = bytes(range(32))
signed.signing.link_id = 1
signed.signing.sign_outgoing = True
v2 = m2.MAVLink(Sink(), srcSystem=1, srcComponent=1)
v1 = m1.MAVLink(Sink(), srcSystem=1, srcComponent=1)
frames = [
    signed.raw_imu_encode(5_000_000, 10, -20, -1000, 100, -200, 300, 1, 2, 3).pack(signed),
    v1.scaled_imu_encode(4000, 10, -20, -1000, 100, -200, 300, 1, 2, 3).pack(v1),
    v2.heartbeat_encode(18, 8, 0, 0, 4).pack(v2),
    v2.highres_imu_encode(1234567890123, 0.5, -0.25, 9.75, 0.125, 0.0, -1.0, 0, 0, 0, 0, 0, 0, 0, 0).pack(v2),
]
for f in frames:
    print(bytes(f).hex())
"#;

/// The MAVLink IMU input against pymavlink's frames: every kind decodes to the values sent, in
/// SI units, through both protocol versions, a signature and MAVLink 2's truncation.
#[test]
fn imu_messages_from_pymavlink_decode_exactly() {
    use loglio_host::input::mavlink_imu::{ImuMessage, MavlinkImuDecoder, RawScale};
    let Some(python) = common::peer_python("mavlink IMU in") else { return };
    let out = Command::new(python).arg("-c").arg(IMU_ENCODER).output().expect("run pymavlink");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let frames: Vec<Vec<u8>> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| (0..l.len()).step_by(2).map(|i| u8::from_str_radix(&l[i..i + 2], 16).unwrap()).collect())
        .collect();
    assert_eq!(frames.len(), 4);
    assert_eq!(frames[1][0], 0xFE, "SCALED_IMU in MAVLink 1");
    assert_eq!(frames[0][2] & 1, 1, "RAW_IMU signed");
    // ArduPilot's RAW_IMU units (milli-g, mrad/s) as the configured scales.
    let mut dec = MavlinkImuDecoder::new(Some(RawScale { acc: 0.009_806_65, gyro: 0.001 }));
    let mut got = Vec::new();
    // Each frame a datagram, then all of them in one datagram (the best kind stays HIGHRES_IMU).
    for f in &frames {
        dec.datagram(f, |s| got.push(s));
    }
    assert_eq!(got.len(), 3, "{:?}", dec.stats);
    let g = 9.806_65f32;
    assert_eq!(got[0].message, ImuMessage::RawImu);
    assert_eq!(got[0].device_ns, 5_000_000_000);
    assert_eq!(got[0].acc, [10.0 * 0.009_806_65, -20.0 * 0.009_806_65, -1000.0 * 0.009_806_65]);
    assert_eq!(got[0].gyro, [0.1, -0.2, 0.3].map(|v: f32| (v * 1000.0).round() * 0.001));
    assert_eq!(got[1].message, ImuMessage::ScaledImu);
    assert_eq!(got[1].device_ns, 4_000_000_000);
    assert_eq!(got[1].acc, [10.0, -20.0, -1000.0].map(|v: f32| v * 1e-3 * g));
    assert_eq!(got[1].gyro, [100.0, -200.0, 300.0].map(|v: f32| v * 1e-3));
    assert_eq!(got[2].message, ImuMessage::HighresImu);
    assert_eq!(got[2].device_ns, 1_234_567_890_123_000);
    assert_eq!((got[2].acc, got[2].gyro), ([0.5, -0.25, 9.75], [0.125, 0.0, -1.0]));
    assert_eq!(dec.stats.other_messages, 1);
    assert_eq!((dec.stats.crc, dec.stats.dropped_bytes), (0, 0));
    let all: Vec<u8> = frames.concat();
    let mut n = 0;
    dec.datagram(&all, |s| {
        assert_eq!(s.message, ImuMessage::HighresImu);
        n += 1;
    });
    assert_eq!((n, dec.stats.ignored), (1, 2));
    // Without the scales RAW_IMU is ignored, not misread.
    let mut dec = MavlinkImuDecoder::new(None);
    dec.datagram(&frames[0], |_| panic!("RAW_IMU without scales"));
    assert_eq!(dec.stats.ignored, 1);
}
