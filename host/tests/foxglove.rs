//! The Foxglove output (`--foxglove HOST:PORT`) and its recording (`--mcap FILE`), checked
//! against independent implementations: a Python `websockets` client speaking
//! `foxglove.websocket.v1` and the Python `mcap` reader (`LOGLIO_PYTHON`, see
//! `common::peer_python`). The poses they decode must equal `trajectory.tum`.

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;
use common::{loglio_command, peer_python, runner, scratch};

/// The Foxglove client: connects (retrying until the server is up), reads serverInfo and
/// advertise, subscribes to every channel and counts and decodes what comes until the server
/// closes. `stall` mode: a raw socket with a tiny receive buffer that subscribes and never
/// reads again. Prints one JSON object.
const CLIENT_PY: &str = r#"
import asyncio, base64, json, socket, struct, sys, time, os
mode, host, port = sys.argv[1], sys.argv[2], int(sys.argv[3])
SUB = "foxglove.websocket.v1"

def stall():
    deadline = time.time() + 20
    while True:
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        try:
            s.connect((host, port)); break
        except OSError:
            s.close()
            if time.time() > deadline: raise
            time.sleep(0.05)
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall(("GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               "Sec-WebSocket-Key: %s\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: %s\r\n\r\n" % (key, SUB)).encode())
    buf = b""
    while b"\r\n\r\n" not in buf:
        buf += s.recv(1)
    assert b" 101 " in buf.split(b"\r\n")[0], buf
    def read_exact(n):
        d = b""
        while len(d) < n:
            c = s.recv(n - len(d))
            if not c: raise EOFError
            d += c
        return d
    def frame():
        b0, b1 = read_exact(2)
        n = b1 & 127
        if n == 126: n = struct.unpack(">H", read_exact(2))[0]
        elif n == 127: n = struct.unpack(">Q", read_exact(8))[0]
        return read_exact(n)
    info = json.loads(frame()); adv = json.loads(frame())
    assert info["op"] == "serverInfo" and adv["op"] == "advertise"
    sub = json.dumps({"op": "subscribe", "subscriptions": [{"id": c["id"], "channelId": c["id"]} for c in adv["channels"]]}).encode()
    mask = os.urandom(4)
    head = bytes([0x81, 0x80 | 126]) + struct.pack(">H", len(sub)) if len(sub) >= 126 else bytes([0x81, 0x80 | len(sub)])
    s.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(sub)))
    print(json.dumps({"stalled": True, "channels": len(adv["channels"])}), flush=True)
    time.sleep(float(sys.argv[4]))

async def read():
    import websockets
    deadline = time.time() + 20
    while True:
        try:
            ws = await websockets.connect("ws://%s:%d" % (host, port), subprotocols=[SUB], max_size=None, ping_interval=None)
            break
        except (OSError, websockets.exceptions.InvalidHandshake):
            if time.time() > deadline: raise
            await asyncio.sleep(0.05)
    info = json.loads(await ws.recv()); adv = json.loads(await ws.recv())
    chans = {c["id"]: c for c in adv["channels"]}
    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 100 + i, "channelId": i} for i in chans]}))
    topic = {100 + i: c["topic"] for i, c in chans.items()}
    r = {"subprotocol": ws.subprotocol, "info": info, "channels": list(chans.values()), "counts": {},
         "poses": [], "scan_points": [], "map_points": [], "path_len": [], "stamp_mismatch": 0, "last_status": None}
    try:
        while True:
            m = await ws.recv()
            if isinstance(m, str): continue
            assert m[0] == 1
            sub, ts = struct.unpack_from("<IQ", m, 1)
            t = topic[sub]; p = json.loads(m[13:])
            r["counts"][t] = r["counts"].get(t, 0) + 1
            st = (p["transforms"][0] if t == "/tf" else p)["timestamp"]
            if st["sec"] * 10**9 + st["nsec"] != ts: r["stamp_mismatch"] += 1
            if t == "/loglio/pose":
                q = p["pose"]; a, o = q["position"], q["orientation"]
                r["poses"].append([ts, a["x"], a["y"], a["z"], o["x"], o["y"], o["z"], o["w"]])
            elif t in ("/loglio/scan", "/loglio/map"):
                n = len(base64.b64decode(p["data"])) // p["point_stride"]
                r["scan_points" if t == "/loglio/scan" else "map_points"].append(n)
                assert p["frame_id"] == "odom" and [f["name"] for f in p["fields"]] == ["x", "y", "z"]
            elif t == "/loglio/path":
                r["path_len"].append(len(p["poses"]))
            elif t == "/loglio/status":
                r["last_status"] = p
    except websockets.exceptions.ConnectionClosed:
        pass
    print(json.dumps(r), flush=True)

if mode == "stall": stall()
else: asyncio.run(read())
"#;

/// Reads the MCAP file with the Python `mcap` reader: schemas, channels, the summary's counts
/// and every message's count and pose.
const MCAP_PY: &str = r#"
import json, sys
from mcap.reader import make_reader
with open(sys.argv[1], "rb") as f:
    rd = make_reader(f)
    summ = rd.get_summary()
    r = {"channels": {c.topic: [c.message_encoding, summ.schemas[c.schema_id].name, summ.schemas[c.schema_id].encoding]
                      for c in summ.channels.values()},
         "stats": {summ.channels[k].topic: v for k, v in summ.statistics.channel_message_counts.items()},
         "counts": {}, "poses": [], "scan_points": [], "map_points": [], "stamp_mismatch": 0}
    for schema, ch, msg in rd.iter_messages(log_time_order=False):
        t = ch.topic; p = json.loads(msg.data)
        r["counts"][t] = r["counts"].get(t, 0) + 1
        st = (p["transforms"][0] if t == "/tf" else p)["timestamp"]
        if st["sec"] * 10**9 + st["nsec"] != msg.log_time: r["stamp_mismatch"] += 1
        if t == "/loglio/pose":
            a, o = p["pose"]["position"], p["pose"]["orientation"]
            r["poses"].append([msg.log_time, a["x"], a["y"], a["z"], o["x"], o["y"], o["z"], o["w"]])
        elif t in ("/loglio/scan", "/loglio/map"):
            import base64
            r["scan_points" if t == "/loglio/scan" else "map_points"].append(len(base64.b64decode(p["data"])) // p["point_stride"])
print(json.dumps(r))
"#;

const TOPICS: [&str; 7] = [
    "/loglio/pose",
    "/loglio/pose_imu",
    "/loglio/path",
    "/loglio/scan",
    "/loglio/map",
    "/tf",
    "/loglio/status",
];

/// Skips under an emulating runner (the real-time runs cannot keep up there).
fn skip_under_runner(test: &str) -> bool {
    if let Some(r) = runner() {
        println!("{test}: skipped under LOGLIO_TEST_RUNNER ({r}): the emulated odometry is not real time");
        return true;
    }
    false
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

fn write_script(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// `trajectory.tum` as (t_ns, x, y, z, qx, qy, qz, qw).
fn tum(dir: &Path) -> Vec<(u64, [f64; 7])> {
    std::fs::read_to_string(dir.join("trajectory.tum"))
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            let (s, ns) = f[0].split_once('.').unwrap();
            let t = s.parse::<u64>().unwrap() * 1_000_000_000 + ns.parse::<u64>().unwrap();
            let mut v = [0.0; 7];
            for (k, x) in v.iter_mut().enumerate() {
                *x = f[k + 1].parse().unwrap();
            }
            (t, v)
        })
        .collect()
}

/// Scans after the initialisation in `scans.csv` (what the trajectory must hold).
fn tracked_scans(dir: &Path) -> usize {
    std::fs::read_to_string(dir.join("scans.csv"))
        .unwrap()
        .lines()
        .skip(1)
        .filter(|l| l.split(',').nth(10).is_some_and(|s| s != "initialising"))
        .count()
}

/// Checks each decoded pose against the trajectory at the same stamp; returns how many matched.
fn check_poses(poses: &Value, tum: &[(u64, [f64; 7])]) -> usize {
    let by_t: HashMap<u64, [f64; 7]> = tum.iter().copied().collect();
    let poses = poses.as_array().unwrap();
    for p in poses {
        let t = p[0].as_u64().unwrap();
        let want = by_t.get(&t).unwrap_or_else(|| panic!("pose at {t} ns is not in trajectory.tum"));
        for k in 0..7 {
            let got = p[k + 1].as_f64().unwrap();
            assert!((got - want[k]).abs() <= 1e-9, "pose at {t} ns, component {k}: {got} vs {}", want[k]);
        }
    }
    poses.len()
}

fn count(r: &Value, topic: &str) -> u64 {
    r["counts"][topic].as_u64().unwrap_or(0)
}

/// `loglio sim` (handheld, os1-16) with `extra` options, spawned with its output piped.
fn spawn_sim(out: &Path, seconds: &str, extra: &[&str]) -> Child {
    let mut args = vec![
        "sim",
        "--scenario",
        "handheld",
        "--sensor",
        "os1-16",
        "--seconds",
        seconds,
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    loglio_command(&args).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().expect("cannot run loglio")
}

/// Waits for `child` (at most `limit`), killing it past the limit.
fn wait(mut child: Child, limit: Duration, what: &str) -> Output {
    let start = Instant::now();
    loop {
        if child.try_wait().unwrap().is_some() {
            return child.wait_with_output().unwrap();
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let o = child.wait_with_output().unwrap();
            panic!(
                "{what} still running after {limit:?}\nstdout: {}\nstderr: {}",
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn client(py: &Path, script: &Path, mode: &str, port: u16, extra: &[&str]) -> Child {
    Command::new(py)
        .arg(script)
        .args([mode, "127.0.0.1", &port.to_string()])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("cannot run the Python client")
}

fn json_of(o: &Output, what: &str) -> Value {
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{what} failed: {}\n{text}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_str(text.lines().last().unwrap_or("")).unwrap_or_else(|e| panic!("{what}: {e}: {text}"))
}

fn ok_run(o: &Output) -> String {
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "loglio failed: {}\n{err}", String::from_utf8_lossy(&o.stdout));
    assert!(!err.contains("panicked"), "{err}");
    err
}

#[test]
fn foxglove_client_sees_every_channel_and_the_trajectory() {
    let Some(py) = peer_python("foxglove_client_sees_every_channel_and_the_trajectory") else { return };
    if skip_under_runner("foxglove_client_sees_every_channel_and_the_trajectory") {
        return;
    }
    let dir = scratch("foxglove", "client");
    let script = write_script(&dir, "client.py", CLIENT_PY);
    let port = free_port();
    let addr = format!("127.0.0.1:{port}");
    let out = dir.join("out");
    let sim = spawn_sim(&out, "6", &["--foxglove", &addr, "--map-every", "2", "--realtime", "--rate", "2"]);
    let cl = client(&py, &script, "read", port, &[]);
    let run = wait(sim, Duration::from_secs(60), "loglio sim");
    let err = ok_run(&run);
    assert!(err.contains(&format!("foxglove: serving ws://{addr}")), "{err}");
    let r = json_of(&wait(cl, Duration::from_secs(20), "the client"), "the client");

    assert_eq!(r["subprotocol"], "foxglove.websocket.v1");
    assert_eq!(r["info"]["op"], "serverInfo");
    let chans: HashMap<String, (String, String, String)> = r["channels"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let s = |k: &str| c[k].as_str().unwrap().to_string();
            (s("topic"), (s("encoding"), s("schemaName"), s("schemaEncoding")))
        })
        .collect();
    for t in TOPICS {
        assert!(chans.contains_key(t), "{t} not advertised: {chans:?}");
        assert_eq!(chans[t].0, "json");
        assert_eq!(chans[t].2, "jsonschema");
    }
    assert_eq!(chans["/loglio/pose"].1, "foxglove.PoseInFrame");
    assert_eq!(chans["/loglio/path"].1, "foxglove.PosesInFrame");
    assert_eq!(chans["/loglio/scan"].1, "foxglove.PointCloud");
    assert_eq!(chans["/tf"].1, "foxglove.FrameTransforms");

    let traj = tum(&out);
    let poses = check_poses(&r["poses"], &traj);
    let counts: Vec<(&str, u64)> = TOPICS.iter().map(|t| (*t, count(&r, t))).collect();
    println!("client: {counts:?}; trajectory {} poses; status {}", traj.len(), r["last_status"]);
    // The client connects within a fraction of a second; the first second is the initialisation.
    assert!(traj.len() >= 40, "trajectory of {} poses", traj.len());
    assert!(poses as f64 >= 0.8 * traj.len() as f64, "{poses} poses of {}", traj.len());
    assert_eq!(count(&r, "/loglio/scan"), poses as u64);
    assert!(count(&r, "/loglio/pose_imu") >= 3 * poses as u64, "{counts:?}");
    assert!(count(&r, "/loglio/pose_imu") <= 6 * poses as u64, "50 Hz against 10 Hz scans: {counts:?}");
    assert_eq!(count(&r, "/tf"), poses as u64 + count(&r, "/loglio/pose_imu"));
    assert!(count(&r, "/loglio/status") >= poses as u64);
    assert!((3..=7).contains(&count(&r, "/loglio/path")), "about 1 Hz over 5 s: {counts:?}");
    assert!(count(&r, "/loglio/map") >= 2, "{counts:?}");
    assert!(
        r["scan_points"].as_array().unwrap().iter().all(|n| n.as_u64().unwrap() >= 100),
        "{}",
        r["scan_points"]
    );
    assert!(
        r["map_points"].as_array().unwrap().iter().all(|n| n.as_u64().unwrap() >= 1000),
        "{}",
        r["map_points"]
    );
    let path = r["path_len"].as_array().unwrap();
    assert!(path.last().unwrap().as_u64().unwrap() >= 30, "{path:?}");
    assert_eq!(r["stamp_mismatch"], 0);
    let st = &r["last_status"];
    assert_eq!(st["tracking"], true);
    assert!(st["map_voxels"].as_u64().unwrap() > 0 && st["process_ms"].as_f64().unwrap() > 0.0, "{st}");
}

#[test]
fn mcap_recording_holds_every_channel_and_the_whole_trajectory() {
    let Some(py) = peer_python("mcap_recording_holds_every_channel_and_the_whole_trajectory") else { return };
    let dir = scratch("foxglove", "mcap");
    let script = write_script(&dir, "read_mcap.py", MCAP_PY);
    let out = dir.join("out");
    let file = dir.join("run.mcap");
    let sim = spawn_sim(&out, "6", &["--mcap", file.to_str().unwrap(), "--map-every", "2"]);
    let err = ok_run(&wait(sim, Duration::from_secs(120), "loglio sim"));
    assert!(!err.contains("warning"), "{err}");
    let o = Command::new(&py).arg(&script).arg(&file).output().unwrap();
    let r = json_of(&o, "the mcap reader");

    let chans = r["channels"].as_object().unwrap();
    for t in TOPICS {
        let c = chans.get(t).unwrap_or_else(|| panic!("{t} not in the file: {chans:?}"));
        assert_eq!(c[0], "json");
        assert_eq!(c[2], "jsonschema");
    }
    assert_eq!(chans["/loglio/map"][1], "foxglove.PointCloud");
    assert_eq!(chans["/loglio/pose_imu"][1], "foxglove.PoseInFrame");
    // The summary's statistics (written at the end) agree with the messages read.
    for t in TOPICS {
        assert_eq!(r["stats"][t], r["counts"][t], "{t}: summary vs messages");
    }
    let traj = tum(&out);
    assert_eq!(traj.len(), tracked_scans(&out));
    let poses = check_poses(&r["poses"], &traj);
    assert_eq!(poses, traj.len(), "every pose of the trajectory is recorded");
    let counts: Vec<(&str, u64)> = TOPICS.iter().map(|t| (*t, count(&r, t))).collect();
    println!("mcap: {counts:?}; trajectory {} poses", traj.len());
    assert_eq!(count(&r, "/loglio/scan"), poses as u64);
    assert!(count(&r, "/loglio/pose_imu") >= 3 * poses as u64, "{counts:?}");
    assert_eq!(count(&r, "/tf"), poses as u64 + count(&r, "/loglio/pose_imu"));
    assert!(count(&r, "/loglio/status") > poses as u64, "initialising scans have a status too");
    assert!(count(&r, "/loglio/map") >= 2 && count(&r, "/loglio/path") >= 4, "{counts:?}");
    assert!(r["map_points"].as_array().unwrap().iter().all(|n| n.as_u64().unwrap() >= 1000));
    assert_eq!(r["stamp_mismatch"], 0);
}

#[test]
fn a_client_that_never_reads_blocks_nothing_and_its_drops_are_counted() {
    let Some(py) = peer_python("a_client_that_never_reads_blocks_nothing_and_its_drops_are_counted") else {
        return;
    };
    if skip_under_runner("a_client_that_never_reads_blocks_nothing_and_its_drops_are_counted") {
        return;
    }
    let dir = scratch("foxglove", "stall");
    let script = write_script(&dir, "client.py", CLIENT_PY);
    let port = free_port();
    let addr = format!("127.0.0.1:{port}");
    let out = dir.join("out");
    let start = Instant::now();
    let sim = spawn_sim(&out, "10", &["--foxglove", &addr, "--realtime", "--rate", "4"]);
    // One client that subscribes and then never reads, and one that reads.
    let mut stalled = client(&py, &script, "stall", port, &["60"]);
    let reader = client(&py, &script, "read", port, &[]);
    let mut line = String::new();
    BufReader::new(stalled.stdout.as_mut().unwrap()).read_line(&mut line).unwrap();
    assert!(line.contains("\"stalled\": true"), "the stalling client did not subscribe: {line}");
    let run = wait(sim, Duration::from_secs(60), "loglio sim");
    let wall = start.elapsed();
    let err = ok_run(&run);
    let _ = stalled.kill();
    let _ = stalled.wait();
    let r = json_of(&wait(reader, Duration::from_secs(20), "the reading client"), "the reading client");

    // The run was paced by the data (10 s at 4x), not held up by the client.
    assert!(wall < Duration::from_secs(20), "{wall:?}");
    let traj = tum(&out);
    assert_eq!(traj.len(), tracked_scans(&out), "the trajectory is complete");
    assert!(traj.len() >= 70, "{}", traj.len());
    // The other client got its poses.
    let poses = check_poses(&r["poses"], &traj);
    assert!(poses as f64 >= 0.8 * traj.len() as f64, "{poses} of {}", traj.len());
    // The slow client's drops: one warning at the end and in the status channel.
    let drops = err
        .lines()
        .find(|l| l.contains("messages dropped for slow clients"))
        .unwrap_or_else(|| panic!("no drop warning: {err}"));
    let n: u64 = drops
        .split(": ")
        .nth(2)
        .and_then(|s| s.split_whitespace().next())
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    println!("stall: {drops}; the reader got {poses} poses of {}; wall {wall:?}", traj.len());
    assert!(n > 0, "{drops}");
    assert!(r["last_status"]["dropped"].as_u64().unwrap() > 0, "{}", r["last_status"]);
}

#[test]
fn a_port_in_use_or_an_unwritable_file_is_one_warning_and_the_run_goes_on() {
    let dir = scratch("foxglove", "bad");
    let held = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = held.local_addr().unwrap().to_string();
    let out = dir.join("out");
    let sim = spawn_sim(&out, "2", &["--foxglove", &addr, "--mcap", "/nonexistent-loglio-dir/run.mcap"]);
    let err = ok_run(&wait(sim, Duration::from_secs(60), "loglio sim"));
    let fox: Vec<&str> = err.lines().filter(|l| l.contains("--foxglove")).collect();
    let mcap: Vec<&str> = err.lines().filter(|l| l.contains("--mcap")).collect();
    assert_eq!(fox.len(), 1, "{err}");
    assert_eq!(mcap.len(), 1, "{err}");
    assert!(fox[0].starts_with("warning: --foxglove: cannot listen on") && fox[0].contains(&addr), "{err}");
    assert!(mcap[0].starts_with("warning: --mcap: cannot write /nonexistent-loglio-dir/run.mcap"), "{err}");
    assert!(!tum(&out).is_empty());
    drop(held);
}

/// Reads a recording without its end (a killed run) with the streaming reader, up to where it
/// breaks off.
const MCAP_STREAM_PY: &str = r#"
import json, sys
from mcap.stream_reader import StreamReader
from mcap.records import Channel, Message
chans, poses, n, end = {}, [], 0, "complete"
try:
    for rec in StreamReader(open(sys.argv[1], "rb"), skip_magic=False).records:
        if isinstance(rec, Channel): chans[rec.id] = rec.topic
        elif isinstance(rec, Message):
            n += 1
            if chans.get(rec.channel_id) == "/loglio/pose":
                p = json.loads(rec.data); a, o = p["pose"]["position"], p["pose"]["orientation"]
                poses.append([rec.log_time, a["x"], a["y"], a["z"], o["x"], o["y"], o["z"], o["w"]])
except Exception as e:
    end = type(e).__name__
print(json.dumps({"messages": n, "poses": poses, "end": end}))
"#;

#[test]
fn a_killed_run_leaves_its_recording_readable_up_to_the_last_second() {
    let Some(py) = peer_python("a_killed_run_leaves_its_recording_readable_up_to_the_last_second") else {
        return;
    };
    if skip_under_runner("a_killed_run_leaves_its_recording_readable_up_to_the_last_second") {
        return;
    }
    let dir = scratch("foxglove", "killed");
    let script = write_script(&dir, "stream_mcap.py", MCAP_STREAM_PY);
    let out = dir.join("out");
    let file = dir.join("run.mcap");
    let mut sim = spawn_sim(&out, "20", &["--mcap", file.to_str().unwrap(), "--realtime", "--rate", "2"]);
    // 4 s of data after the initialisation, then killed (no end, no summary).
    let start = Instant::now();
    let lines = || std::fs::read_to_string(out.join("trajectory.tum")).map_or(0, |t| t.lines().count());
    while lines() < 40 {
        assert!(start.elapsed() < Duration::from_secs(30), "no progress");
        assert!(sim.try_wait().unwrap().is_none(), "the run ended early");
        std::thread::sleep(Duration::from_millis(50));
    }
    sim.kill().unwrap();
    let _ = sim.wait();
    let r = json_of(&Command::new(&py).arg(&script).arg(&file).output().unwrap(), "the stream reader");
    let traj = tum(&out);
    let poses = check_poses(&r["poses"], &traj);
    println!(
        "killed: {} messages, {poses} poses of {} readable; the stream ends with {}",
        r["messages"],
        traj.len(),
        r["end"]
    );
    // Chunks are closed about every second of data: at most ~1 s (10 poses) is lost.
    assert!(poses + 12 >= traj.len(), "{poses} of {}", traj.len());
    assert!(r["messages"].as_u64().unwrap() > 300);
}
