//! Whole ROS 1 bag files through `BagReader`: a bag written by loglio's own writer from the
//! input (clouds in the Velodyne or Ouster driver layout, IMU messages, VelodyneScan and
//! Ouster packet messages, metadata strings, or raw bytes under any of those types; chunk size
//! and compression from the input), then damaged as the input says (bytes flipped, the file
//! cut short), so the fuzzer reaches every record type behind the magic and the index. Also
//! rosbag2 sqlite3 files built from the input (with and without the timestamp index, rows in
//! any time order, unknown topic ids, negative timestamps), damaged the same way, and the
//! input as a file of its own, as `.bag`, `.mcap` and `.db3`. The reader may refuse a file or
//! drop messages; it must not panic, and what it delivers must be well formed and in
//! record-time order.
#![no_main]
use std::io::Cursor;
use std::path::PathBuf;

use libfuzzer_sys::fuzz_target;
use loglio_fuzz::Input;
use loglio_host::input::bag::cloud::build::{OUSTER, VELODYNE, cloud};
use loglio_host::input::bag::msg::{self, Encoding, Imu, MessageType, VelodyneScan};
use loglio_host::input::bag::ros1_writer::{ChunkCompression, Ros1BagWriter};
use loglio_host::input::bag::{BagEvent, BagOptions, BagReader};
use loglio_host::config::{Config, Preset};

/// The message types loglio reads and a topic for each, for both kinds of bag.
const KINDS: [(&MessageType, &str); 5] = [
    (&msg::POINTCLOUD2, "/points"),
    (&msg::IMU, "/imu"),
    (&msg::VELODYNE_SCAN, "/velodyne_packets"),
    (&msg::OUSTER_PACKET, "/os_node/lidar_packets"),
    (&msg::STRING, "/os_node/metadata"),
];

/// A bag from the input, or `None` if the writer refuses it.
fn write_bag(inp: &mut Input<'_>) -> Option<Vec<u8>> {
    let mut w = Ros1BagWriter::new(Cursor::new(Vec::new())).ok()?;
    w.set_chunk_threshold(usize::from(inp.u16()) * 16);
    w.set_compression(match inp.u8() % 3 {
        0 => ChunkCompression::None,
        1 => ChunkCompression::Bz2,
        _ => ChunkCompression::Lz4,
    });
    // Which topics the bag has (the reader picks its LiDAR topic by type, clouds first).
    let mask = match inp.u8() % 32 {
        0 => 31,
        m => m,
    };
    let conns: Vec<_> = KINDS
        .iter()
        .enumerate()
        .filter(|(i, _)| mask >> i & 1 == 1)
        .map(|(_, (t, topic))| w.add_typed_connection(topic, t))
        .collect::<Result<_, _>>()
        .ok()?;
    let mut t_ns = 1_700_000_000_000_000_000u64;
    for _ in 0..usize::from(inp.u8() % 24) {
        let kind = inp.u8();
        t_ns = t_ns.saturating_add(u64::from(inp.u16()) * 100_000);
        let conn = conns[usize::from(kind) % conns.len()];
        let data = message(inp, kind, t_ns, Encoding::Ros1);
        w.write(conn, t_ns, &data).ok()?;
    }
    let mut bytes = w.finish().ok()?.into_inner();
    damage(inp, &mut bytes);
    Some(bytes)
}

/// Damage as the input says: bytes flipped, then perhaps the file cut short.
fn damage(inp: &mut Input<'_>, bytes: &mut Vec<u8>) {
    for _ in 0..usize::from(inp.u8() % 8) {
        let pos = usize::from(inp.u16()) * 4 + usize::from(inp.u8());
        let x = inp.u8();
        if let Some(b) = bytes.get_mut(pos) {
            *b ^= x;
        }
    }
    if inp.u8() & 1 == 1 {
        let cut = usize::from(inp.u16()) * 8;
        bytes.truncate(cut);
    }
}

/// A rosbag2 sqlite3 file at `path` from the input: rosbag2's schema with or without the
/// messages' timestamp index, topics of the message types loglio reads (or others, or another
/// serialisation format; ids from the input), messages on those topics or on unknown ids, at
/// any timestamp (negative ones included), then damaged. `None` if SQLite refuses the input.
fn write_db3(inp: &mut Input<'_>, path: &std::path::Path) -> Option<Vec<u8>> {
    let _ = std::fs::remove_file(path);
    {
        let db = rusqlite::Connection::open(path).ok()?;
        db.execute_batch(
            "CREATE TABLE schema(schema_version INTEGER PRIMARY KEY,ros_distro TEXT NOT NULL);
             CREATE TABLE metadata(id INTEGER PRIMARY KEY,metadata_version INTEGER NOT NULL,metadata TEXT NOT NULL);
             CREATE TABLE topics(id INTEGER PRIMARY KEY,name TEXT NOT NULL,type TEXT NOT NULL,serialization_format TEXT NOT NULL,offered_qos_profiles TEXT NOT NULL);
             CREATE TABLE messages(id INTEGER PRIMARY KEY,topic_id INTEGER NOT NULL,timestamp INTEGER NOT NULL, data BLOB NOT NULL);",
        )
        .ok()?;
        if inp.u8() & 1 == 0 {
            db.execute_batch("CREATE INDEX timestamp_idx ON messages (timestamp ASC);").ok()?;
        }
        // loglio's types and topics, and one of neither.
        let mut types: Vec<String> = KINDS.iter().map(|(t, _)| msg::ros2_name(t)).collect();
        types.push("sensor_msgs/msg/Image".to_string());
        let mut names: Vec<&str> = KINDS.iter().map(|(_, n)| *n).collect();
        names.push("/x");
        for _ in 0..1 + usize::from(inp.u8() % 5) {
            let (id, ty, name, ser) = (i64::from(inp.u8() % 8), inp.u8(), inp.u8(), inp.u8());
            let ser = if ser % 8 == 0 { "ros1" } else { "cdr" };
            let _ = db.execute(
                "INSERT INTO topics VALUES (?1, ?2, ?3, ?4, '')",
                rusqlite::params![
                    id,
                    names[usize::from(name) % names.len()],
                    &types[usize::from(ty) % types.len()],
                    ser
                ],
            );
        }
        let mut t = 1_700_000_000_000_000_000i64;
        for _ in 0..usize::from(inp.u8() % 24) {
            let kind = inp.u8();
            let topic = i64::from(inp.u8() % 9);
            // Mostly forward in time, sometimes back (rows need not be in time order), rarely
            // anywhere.
            let step = i64::from(inp.u16() as i16) * 100_000;
            t = if kind & 3 == 3 { i64::from(inp.u32() as i32) << 32 } else { t.saturating_add(step) };
            let data = message(inp, kind, t.max(0) as u64, Encoding::Cdr);
            let _ = db.execute(
                "INSERT INTO messages (topic_id, timestamp, data) VALUES (?1, ?2, ?3)",
                rusqlite::params![topic, t, data],
            );
        }
    }
    let mut bytes = std::fs::read(path).ok()?;
    damage(inp, &mut bytes);
    Some(bytes)
}

/// A message of the kind the input picks, stamped `t_ns`, in `enc`: a driver-layout cloud with
/// point values from the input, an IMU sample, a VelodyneScan, an Ouster packet, or raw bytes.
fn message(inp: &mut Input<'_>, kind: u8, t_ns: u64, enc: Encoding) -> Vec<u8> {
    match (kind >> 4) % 6 {
        0 => {
            // A driver-layout cloud with point values from the input.
            let (fields, n) = if kind & 8 == 0 { (VELODYNE, 6) } else { (OUSTER, 9) };
            let (h, wd) = (u32::from(inp.u8() % 4), u32::from(inp.u8() % 64));
            let vals: Vec<f32> = (0..(h * wd) as usize * n).map(|_| inp.f32()).collect();
            let c = cloud(t_ns, "lidar", fields, h, wd, None, kind & 4 != 0, |i, name| {
                let k = fields.iter().position(|f| f.name == name).unwrap_or(0);
                f64::from(vals.get(i * n + k).copied().unwrap_or(0.0))
            });
            c.encode(enc)
        }
        1 => {
            let v: Vec<f64> = (0..10).map(|_| f64::from(inp.f32())).collect();
            Imu {
                stamp_ns: t_ns,
                orientation_xyzw: [v[0], v[1], v[2], v[3]],
                angular_velocity: [v[4], v[5], v[6]],
                linear_acceleration: [v[7], v[8], v[9]],
            }
            .encode("imu", enc)
        }
        2 => {
            let n = usize::from(inp.u8() % 4);
            let packets = (0..n).map(|_| (t_ns, inp.bytes(1206).to_vec())).collect();
            VelodyneScan { stamp_ns: t_ns, packets }.encode(enc)
        }
        3 => {
            let n = usize::from(inp.u16() % 8192);
            msg::encode_packet_msg(inp.bytes(n), enc)
        }
        _ => {
            // Raw bytes under the connection's type.
            let n = usize::from(inp.u16() % 4096);
            inp.bytes(n).to_vec()
        }
    }
}

fn read(path: &PathBuf, preset: Preset) {
    let Ok(opt) = BagOptions::from_config(&Config::preset(preset)) else { return };
    let Ok(mut bag) = BagReader::open(path, opt) else { return };
    let mut last = 0;
    for item in (&mut bag).take(10_000) {
        let Ok(item) = item else { break };
        // Events come in record-time order, whatever the file's order and damage.
        assert!(item.record_ns >= last, "{} after {last}", item.record_ns);
        last = item.record_ns;
        if let BagEvent::Scan(s) = item.event {
            for p in &s.points {
                assert!(p.xyz.iter().all(|v| v.is_finite()) && p.t.is_finite(), "{p:?}");
            }
        }
    }
    let _ = bag.stats().to_string();
}

fuzz_target!(|data: &[u8]| {
    let mut inp = Input(data);
    let sel = inp.u8();
    let preset = [Preset::Vlp16, Preset::Vlp32c, Preset::Os1_16, Preset::Os1_64][usize::from(sel & 3)];
    let dir = std::env::temp_dir().join(format!("loglio-fuzz-bag-{}", std::process::id()));
    let _ = std::fs::create_dir_all(&dir);
    let (name, bytes) = match (sel >> 2) % 6 {
        0 => ("raw.bag", inp.0.to_vec()),
        1 => ("raw.mcap", inp.0.to_vec()),
        2 | 3 => match write_bag(&mut inp) {
            Some(b) => ("built.bag", b),
            None => return,
        },
        4 => ("raw.db3", inp.0.to_vec()),
        _ => match write_db3(&mut inp, &dir.join("scratch.db3")) {
            Some(b) => ("built.db3", b),
            None => return,
        },
    };
    let path = dir.join(name);
    if std::fs::write(&path, &bytes).is_ok() {
        read(&path, preset);
    }
});
