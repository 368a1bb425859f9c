//! ROS bag reading: real bags from the Ouster SDK (ROS 1) and Autoware Nebula (rosbag2 sqlite3),
//! and bags written here (ROS 1 with loglio's writer, MCAP with the `mcap` crate, rosbag2
//! sqlite3 with rusqlite) holding PointCloud2 (Velodyne and Ouster driver fields, and clouds
//! without ring or time) and Imu. Then every kind of bad input.

use std::collections::BTreeMap;
use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
mod common;

use loglio_core::scan::NO_PIXEL;
use loglio_host::config::{Config, Preset};
use loglio_host::diag;
use loglio_host::input::bag::cloud::build::{self, FieldSpec};
use loglio_host::input::bag::msg::{self, Encoding, IMU, Imu, MessageType, POINTCLOUD2, PointCloud2, STRING};
use loglio_host::input::bag::ros1_writer::{ChunkCompression, Ros1BagWriter};
use loglio_host::input::bag::{
    BagError, BagEvent, BagFormat, BagItem, BagOptions, BagReader, BagStats, PacketKind, TopicKind,
};

fn tmp(name: &str) -> common::Scratch {
    common::scratch("bags", name)
}

fn data(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/data").join(rel)
}

fn opts(p: Preset) -> BagOptions {
    BagOptions::from_config(&Config::preset(p)).unwrap()
}

struct Run {
    items: Vec<BagItem>,
    end: Result<(), BagError>,
    stats: BagStats,
    warnings: Vec<String>,
}

fn read_all(path: &Path, opt: BagOptions) -> Result<Run, BagError> {
    let (r, warnings) = diag::capture(|| -> Result<_, BagError> {
        let mut bag = BagReader::open(path, opt)?;
        let mut items = Vec::new();
        let mut end = Ok(());
        for it in &mut bag {
            match it {
                Ok(i) => items.push(i),
                Err(e) => {
                    end = Err(e);
                    break;
                }
            }
        }
        Ok((items, end, *bag.stats()))
    });
    let (items, end, stats) = r?;
    Ok(Run { items, end, stats, warnings })
}

fn open_err(path: &Path, opt: BagOptions) -> String {
    let e = BagReader::open(path, opt).unwrap_err().0;
    assert!(!e.contains('\n'), "one line: {e}");
    e
}

// ---------------------------------------------------------------------------------------------
// Real bags.

#[test]
fn ouster_ros1_bag_gives_packets_imu_packets_and_metadata() {
    let path = data("ouster-sdk/512x10_raw.bag");
    let bag = BagReader::open(&path, opts(Preset::Os1_64)).unwrap();
    assert_eq!(bag.format(), BagFormat::Ros1);
    let sel = bag.selection().clone();
    assert_eq!(sel.lidar, ("/os_node0/lidar_packets".to_string(), TopicKind::OusterPacket));
    assert_eq!(sel.imu.as_deref(), Some("/os_node0/imu_packets"));
    assert_eq!(sel.metadata.as_deref(), Some("/os_node0/metadata"));
    assert_eq!(bag.total_messages(), Some(43));
    let run = read_all(&path, opts(Preset::Os1_64)).unwrap();
    run.end.unwrap();
    assert!(run.warnings.is_empty(), "{:?}", run.warnings);
    let (mut lidar, mut imu, mut meta) = (Vec::new(), Vec::new(), Vec::new());
    for it in &run.items {
        match &it.event {
            BagEvent::LidarPacket(p) if p.kind == PacketKind::OusterLidar => {
                lidar.push((it.record_ns, p.clone()))
            }
            BagEvent::LidarPacket(p) if p.kind == PacketKind::OusterImu => {
                imu.push((it.record_ns, p.clone()))
            }
            BagEvent::OusterMetadata(s) => meta.push(s.clone()),
            other => panic!("unexpected {other:?}"),
        }
    }
    assert_eq!((lidar.len(), imu.len(), meta.len()), (32, 10, 1));
    assert!(lidar.iter().all(|(_, p)| p.bytes.len() == 8448));
    assert!(imu.iter().all(|(_, p)| p.bytes.len() == 48));
    // Values read with Python rosbags (tests/data/ouster-sdk/SOURCE.md).
    assert_eq!(lidar[0].0, 1_723_828_414_279_578_824);
    assert_eq!(lidar[0].1.stamp_ns, 1_723_828_414_279_578_824, "Ouster packets carry the record time");
    assert_eq!(lidar[0].1.bytes[..8], [0x01, 0x00, 0x06, 0x07, 0xc3, 0x7b, 0x92, 0x09]);
    assert_eq!(imu[0].0, 1_723_828_414_280_472_589);
    assert_eq!(imu[0].1.bytes[..8], [0x10, 0x4d, 0x88, 0xcc, 0x43, 0x00, 0x00, 0x00]);
    assert_eq!(lidar[31].0, 1_723_828_414_376_097_122);
    let json: serde_json::Value = serde_json::from_str(&meta[0]).unwrap();
    assert!(json.to_string().contains("512x10"), "the metadata names the lidar mode");
    assert!(run.items.windows(2).all(|w| w[0].record_ns <= w[1].record_ns));
    assert_eq!(run.stats.messages, 43);
    assert_eq!(run.stats.packets, 42);
}

fn check_nebula(
    rel: &str,
    file: &str,
    msgs: u64,
    packets: usize,
    first: (u64, [u8; 8]),
    last: (u64, [u8; 6]),
) {
    let mut o = opts(Preset::Vlp32c);
    o.require_imu = false;
    for path in [data(rel), data(rel).join(file)] {
        let run = read_all(&path, o.clone()).unwrap();
        run.end.unwrap();
        assert!(run.warnings.is_empty(), "{:?}", run.warnings);
        assert_eq!(run.stats.messages, msgs);
        let p: Vec<_> = run
            .items
            .iter()
            .map(|i| match &i.event {
                BagEvent::LidarPacket(p) => p.clone(),
                other => panic!("unexpected {other:?}"),
            })
            .collect();
        assert_eq!(p.len(), packets);
        assert!(p.iter().all(|p| p.kind == PacketKind::Velodyne && p.bytes.len() == 1206));
        assert_eq!((p[0].stamp_ns, &p[0].bytes[..8]), (first.0, &first.1[..]));
        let l = &p[packets - 1];
        assert_eq!((l.stamp_ns, &l.bytes[1200..]), (last.0, &last.1[..]));
    }
}

#[test]
fn nebula_rosbag2_sqlite_bags_give_velodyne_packets() {
    // Reference values read with Python rosbags (tests/data/velodyne-nebula/SOURCE.md).
    check_nebula(
        "velodyne-nebula/vlp16_dual_rosbag2/1673400471837873222",
        "1673400471837873222_0.db3",
        4,
        603,
        (1_673_400_471_737_763_166, [0xff, 0xee, 0x42, 0x00, 0x00, 0x00, 0x04, 0xdd]),
        (1_673_400_472_137_216_567, [0xae, 0xc9, 0x66, 0x08, 0x39, 0x22]),
    );
    check_nebula(
        "velodyne-nebula/vlp32c_rosbag2/1713492677464078412",
        "1713492677464078412_0.db3",
        5,
        379,
        (1_713_492_677_327_771_785, [0xff, 0xee, 0x9f, 0x69, 0xbd, 0x00, 0x0b, 0xd1]),
        (1_713_492_677_827_134_284, [0x3f, 0xa9, 0x51, 0x25, 0x37, 0x28]),
    );
}

// ---------------------------------------------------------------------------------------------
// Synthetic sequences.

const T0: u64 = 1_700_000_000_000_000_000;

/// Expected per point: xyz, row, t.
type Expect = Vec<([f32; 3], u16, f32)>;

/// A VLP-16 scan k (Velodyne driver fields; ring 0 lowest; `time` relative to the header stamp,
/// which marks the scan end as stock drivers do).
fn vlp16_scan(k: usize, fields: &[FieldSpec]) -> (PointCloud2, Expect) {
    let el = Preset::Vlp16.nominal_elevations_deg();
    let cols = 360;
    let stamp = T0 + (k as u64 + 1) * 100_000_000;
    let mut pts = Vec::new();
    for c in 0..cols {
        for ring in 0..16usize {
            let az = -(c as f64) * std::f64::consts::TAU / cols as f64 + 0.3;
            let e = el[15 - ring].to_radians();
            let r = 5.0 + (c % 7) as f64 + 0.01 * k as f64;
            let t = c as f64 / cols as f64 * 0.1 - 0.1;
            pts.push((r * e.cos() * az.cos(), r * e.cos() * az.sin(), r * e.sin(), ring, t));
        }
    }
    let cloud =
        build::cloud(stamp, "velodyne", fields, 1, pts.len() as u32, Some(32), false, |i, f| match f {
            "x" => pts[i].0,
            "y" => pts[i].1,
            "z" => pts[i].2,
            "intensity" => (i % 200) as f64,
            "ring" => pts[i].3 as f64,
            _ => pts[i].4,
        });
    let exp = pts
        .iter()
        .map(|p| ([p.0 as f32, p.1 as f32, p.2 as f32], 15 - p.3 as u16, (p.4 + 0.1) as f32))
        .collect();
    (cloud, exp)
}

fn imu_at(t_ns: u64) -> Imu {
    let s = (t_ns - T0) as f64 * 1e-9;
    Imu {
        stamp_ns: t_ns,
        orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
        angular_velocity: [0.1 * s, -0.02, 0.3],
        linear_acceleration: [0.5, s.sin(), 9.81],
    }
}

/// (record time, topic, type, serialised message).
type Msg = (u64, &'static str, MessageType, Vec<u8>);

/// 3 scans and 200 Hz IMU, in record order.
fn sequence(enc: Encoding, fields: &[FieldSpec]) -> (Vec<Msg>, Vec<Expect>) {
    let mut out = Vec::new();
    let mut exp = Vec::new();
    for k in 0..3usize {
        for j in 1..=20u64 {
            let t = T0 + k as u64 * 100_000_000 + j * 5_000_000;
            out.push((t + 100_000, "/imu/data", IMU, imu_at(t).encode("imu_link", enc)));
        }
        let (c, e) = vlp16_scan(k, fields);
        out.push((c.stamp_ns + 8_000_000, "/velodyne_points", POINTCLOUD2, c.encode(enc)));
        exp.push(e);
    }
    (out, exp)
}

/// `msgs` with each pair of neighbours swapped: out of record-time order by a few ms, as bags
/// of several recording threads, or converters, write them.
fn pairs_swapped(msgs: &[Msg]) -> Vec<Msg> {
    let mut rows = msgs.to_vec();
    for pair in rows.chunks_mut(2) {
        pair.reverse();
    }
    rows
}

fn write_ros1(
    path: &Path,
    msgs: &[(u64, &str, MessageType, Vec<u8>)],
    threshold: usize,
    comp: ChunkCompression,
) {
    let mut w = Ros1BagWriter::create(path).unwrap();
    w.set_chunk_threshold(threshold);
    w.set_compression(comp);
    let mut conns = BTreeMap::new();
    for (t, topic, ty, bytes) in msgs {
        let c = match conns.get(topic) {
            Some(c) => *c,
            None => {
                let c = w.add_typed_connection(topic, ty).unwrap();
                conns.insert(*topic, c);
                c
            }
        };
        w.write(c, *t, bytes).unwrap();
    }
    w.finish().unwrap();
}

fn write_mcap(path: &Path, msgs: &[(u64, &str, MessageType, Vec<u8>)]) {
    let f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut w = mcap::WriteOptions::new().profile("ros2").create(f).unwrap();
    let mut chans = BTreeMap::new();
    for (seq, (t, topic, ty, bytes)) in msgs.iter().enumerate() {
        let ch = match chans.get(topic) {
            Some(c) => *c,
            None => {
                let s =
                    w.add_schema(&msg::ros2_name(ty), "ros2msg", msg::ros2_schema(ty).as_bytes()).unwrap();
                let c = w.add_channel(s, topic, "cdr", &BTreeMap::new()).unwrap();
                chans.insert(*topic, c);
                c
            }
        };
        let h = mcap::records::MessageHeader {
            channel_id: ch,
            sequence: seq as u32,
            log_time: *t,
            publish_time: *t,
        };
        w.write_to_known_channel(&h, bytes).unwrap();
    }
    w.finish().unwrap();
}

const ROSBAG2_SCHEMA: &str = "CREATE TABLE schema(schema_version INTEGER PRIMARY KEY,ros_distro TEXT NOT NULL);
CREATE TABLE metadata(id INTEGER PRIMARY KEY,metadata_version INTEGER NOT NULL,metadata TEXT NOT NULL);
CREATE TABLE topics(id INTEGER PRIMARY KEY,name TEXT NOT NULL,type TEXT NOT NULL,serialization_format TEXT NOT NULL,offered_qos_profiles TEXT NOT NULL);
CREATE TABLE messages(id INTEGER PRIMARY KEY,topic_id INTEGER NOT NULL,timestamp INTEGER NOT NULL, data BLOB NOT NULL);
CREATE INDEX timestamp_idx ON messages (timestamp ASC);
INSERT INTO schema VALUES (3, 'humble');";

/// Writes a rosbag2 sqlite3 file; `id_base` makes topic ids differ between splits.
fn write_db3(path: &Path, msgs: &[(u64, &str, MessageType, Vec<u8>)], id_base: i64) {
    write_db3_index(path, msgs, id_base, true);
}

/// [`write_db3`], with or without rosbag2's index of the messages' timestamps.
fn write_db3_index(path: &Path, msgs: &[(u64, &str, MessageType, Vec<u8>)], id_base: i64, index: bool) {
    let db = rusqlite::Connection::open(path).unwrap();
    let schema = if index {
        ROSBAG2_SCHEMA.to_string()
    } else {
        ROSBAG2_SCHEMA.replace("CREATE INDEX timestamp_idx ON messages (timestamp ASC);\n", "")
    };
    assert_eq!(schema.contains("CREATE INDEX"), index);
    db.execute_batch(&schema).unwrap();
    // One transaction: one sync for the file, not one per row.
    db.execute_batch("BEGIN").unwrap();
    let mut ids = BTreeMap::new();
    for (t, topic, ty, bytes) in msgs {
        let id = match ids.get(topic) {
            Some(i) => *i,
            None => {
                let id = id_base + ids.len() as i64;
                db.execute(
                    "INSERT INTO topics VALUES (?1, ?2, ?3, 'cdr', '')",
                    rusqlite::params![id, topic, msg::ros2_name(ty)],
                )
                .unwrap();
                ids.insert(*topic, id);
                id
            }
        };
        db.execute(
            "INSERT INTO messages (topic_id, timestamp, data) VALUES (?1, ?2, ?3)",
            rusqlite::params![id, *t as i64, bytes],
        )
        .unwrap();
    }
    db.execute_batch("COMMIT").unwrap();
}

/// Checks the events of [`sequence`] against what was written.
fn check_sequence(run: &Run, exp: &[Expect]) {
    run.end.as_ref().unwrap();
    let scans: Vec<_> = run
        .items
        .iter()
        .filter_map(|i| if let BagEvent::Scan(s) = &i.event { Some(s) } else { None })
        .collect();
    let imu: Vec<_> = run
        .items
        .iter()
        .filter_map(|i| if let BagEvent::Imu(s) = &i.event { Some(*s) } else { None })
        .collect();
    assert_eq!(scans.len(), 3);
    assert_eq!(imu.len(), 60);
    assert!(run.items.windows(2).all(|w| w[0].record_ns <= w[1].record_ns), "time-ordered");
    for (k, (s, e)) in scans.iter().zip(exp).enumerate() {
        // The header stamps the scan end; the earliest point is 100 ms before it (-0.1 s as an
        // f32 `time` field).
        let first = (f64::from(-0.1f32) * 1e9).round() as i64;
        assert_eq!(s.stamp_ns as i64, (T0 + (k as u64 + 1) * 100_000_000) as i64 + first);
        assert_eq!(s.points.len(), e.len());
        for (p, (xyz, row, t)) in s.points.iter().zip(e) {
            assert_eq!(p.xyz, *xyz);
            assert_eq!(p.row, *row);
            assert!((p.t - t).abs() < 1e-6, "{} vs {t}", p.t);
            assert_ne!(p.col, NO_PIXEL);
        }
        // 360 azimuth steps clockwise from 0.3 rad on 1800 columns: 5 columns per step.
        let c0 = s.points[0].col as i64;
        assert_eq!((s.points[16].col as i64 - c0).rem_euclid(1800), 5);
    }
    let first = imu[0];
    assert_eq!(first.t_ns, T0 + 5_000_000);
    let want = imu_at(T0 + 5_000_000);
    assert_eq!(first.gyro, want.angular_velocity.map(|v| v as f32));
    assert_eq!(first.acc, want.linear_acceleration.map(|v| v as f32));
}

#[test]
fn ros1_velodyne_clouds_and_imu_round_trip_through_the_writer() {
    let dir = tmp("ros1-velodyne");
    let (msgs, exp) = sequence(Encoding::Ros1, build::VELODYNE);
    for (name, comp) in
        [("none", ChunkCompression::None), ("bz2", ChunkCompression::Bz2), ("lz4", ChunkCompression::Lz4)]
    {
        let path = dir.join(format!("{name}.bag"));
        // A small chunk threshold: several chunks, each cloud in its own.
        write_ros1(&path, &msgs, 64 * 1024, comp);
        let bag = BagReader::open(&path, opts(Preset::Vlp16)).unwrap();
        assert_eq!(bag.selection().lidar, ("/velodyne_points".to_string(), TopicKind::PointCloud2));
        assert_eq!(bag.selection().imu.as_deref(), Some("/imu/data"));
        assert_eq!(bag.total_messages(), Some(63));
        let run = read_all(&path, opts(Preset::Vlp16)).unwrap();
        assert!(run.warnings.is_empty(), "{name}: {:?}", run.warnings);
        check_sequence(&run, &exp);
    }
}

#[test]
fn ros1_ouster_organised_clouds() {
    let dir = tmp("ros1-ouster");
    let path = dir.join("os.bag");
    let (rows, cols) = (16usize, 512usize);
    let el = Preset::Os1_16.nominal_elevations_deg();
    let cloud =
        build::cloud(T0, "os_sensor", build::OUSTER, rows as u32, cols as u32, Some(48), false, |i, f| {
            let (r, c) = (i / cols, i % cols);
            let az = -(c as f64 + 0.5) * std::f64::consts::TAU / cols as f64;
            let e = el[r].to_radians();
            let rng = if (r + c) % 50 == 0 { 0.0 } else { 12.0 };
            match f {
                "x" => rng * e.cos() * az.cos(),
                "y" => rng * e.cos() * az.sin(),
                "z" => rng * e.sin(),
                "intensity" => 300.0,
                "t" => c as f64 * 195_312.5,
                "reflectivity" => 7.0,
                "ring" => r as f64,
                _ => 0.0,
            }
        });
    let mut w = Ros1BagWriter::create(&path).unwrap();
    let c = w.add_typed_connection("/os_cloud_node/points", &POINTCLOUD2).unwrap();
    let i = w.add_typed_connection("/os_cloud_node/imu", &IMU).unwrap();
    w.write_imu(i, T0, &imu_at(T0), "os_imu").unwrap();
    w.write_point_cloud2(c, T0 + 100_000_000, &cloud).unwrap();
    w.finish().unwrap();
    let mut cfg = Config::preset(Preset::Os1_16);
    cfg.sensor.columns = 512;
    let run = read_all(&path, BagOptions::from_config(&cfg).unwrap()).unwrap();
    run.end.unwrap();
    assert!(run.warnings.is_empty(), "{:?}", run.warnings);
    let BagEvent::Scan(s) = &run.items[1].event else { panic!() };
    let no_return = (0..rows * cols).filter(|k| (k / cols + k % cols) % 50 == 0).count();
    assert_eq!(s.skipped as usize, no_return);
    assert_eq!(s.points.len(), rows * cols - no_return);
    assert_eq!(s.stamp_ns, T0);
    // Ring 0 is the top row; columns follow the organised index; t from ns.
    let p = s.points.iter().find(|p| p.row == 3 && p.col == 100).unwrap();
    assert!((p.t - 100.0 * 195_312.5e-9).abs() < 1e-7);
    assert_eq!(p.intensity, 300);
    assert!(s.points.iter().all(|p| p.row < 16 && p.col < 512));
}

#[test]
fn clouds_without_ring_or_time_fall_back_to_geometry_with_one_warning_each() {
    let dir = tmp("ros1-xyz");
    let path = dir.join("xyz.bag");
    let (msgs, exp) = sequence(Encoding::Ros1, build::XYZ);
    write_ros1(&path, &msgs, 768 * 1024, ChunkCompression::None);
    let run = read_all(&path, opts(Preset::Vlp16)).unwrap();
    run.end.as_ref().unwrap();
    assert_eq!(
        run.warnings,
        vec![
            "warning: /velodyne_points: clouds have no `ring` field; rows are computed from each point's elevation (nearest beam of the layout)".to_string(),
            "warning: /velodyne_points: clouds have no time field (t, time or timestamp); point times are computed from azimuth at 10 Hz".to_string(),
        ]
    );
    let scans: Vec<_> = run
        .items
        .iter()
        .filter_map(|i| if let BagEvent::Scan(s) = &i.event { Some(s) } else { None })
        .collect();
    assert_eq!(scans.len(), 3);
    for (s, e) in scans.iter().zip(&exp) {
        // Without times the header stamp is the scan start.
        for (p, (_, row, t)) in s.points.iter().zip(e) {
            assert_eq!(p.row, *row, "row from elevation");
            assert!((p.t - t).abs() < 1e-6, "time from azimuth");
        }
    }
}

#[test]
fn mcap_cdr_round_trip() {
    let dir = tmp("mcap");
    let path = dir.join("seq.mcap");
    let (msgs, exp) = sequence(Encoding::Cdr, build::VELODYNE);
    write_mcap(&path, &msgs);
    let bag = BagReader::open(&path, opts(Preset::Vlp16)).unwrap();
    assert_eq!(bag.format(), BagFormat::Mcap);
    assert_eq!(bag.total_messages(), Some(63));
    let run = read_all(&path, opts(Preset::Vlp16)).unwrap();
    assert!(run.warnings.is_empty(), "{:?}", run.warnings);
    check_sequence(&run, &exp);
}

#[test]
fn rosbag2_sqlite_round_trip_across_splits() {
    let dir = tmp("db3");
    let bagdir = dir.join("run");
    std::fs::create_dir_all(&bagdir).unwrap();
    let (msgs, exp) = sequence(Encoding::Cdr, build::VELODYNE);
    let half = msgs.len() / 2;
    write_db3(&bagdir.join("run_0.db3"), &msgs[..half], 1);
    write_db3(&bagdir.join("run_1.db3"), &msgs[half..], 7);
    let bag = BagReader::open(&bagdir, opts(Preset::Vlp16)).unwrap();
    assert_eq!(bag.format(), BagFormat::Ros2Sqlite);
    assert_eq!(bag.total_messages(), Some(63));
    let run = read_all(&bagdir, opts(Preset::Vlp16)).unwrap();
    assert!(run.warnings.is_empty(), "{:?}", run.warnings);
    check_sequence(&run, &exp);
}

/// A rosbag2 recorded into several MCAP files (split by size or duration): read as one bag,
/// in split order, the topics merged; also when each split is zstd-compressed.
#[test]
fn rosbag2_mcap_splits_are_one_bag() {
    let dir = tmp("mcap-splits");
    let (msgs, exp) = sequence(Encoding::Cdr, build::VELODYNE);
    let third = msgs.len() / 3;
    let bagdir = dir.join("run");
    std::fs::create_dir_all(&bagdir).unwrap();
    // Written out of name order: the split number decides (run_10 after run_2).
    write_mcap(&bagdir.join("run_10.mcap"), &msgs[2 * third..]);
    write_mcap(&bagdir.join("run_0.mcap"), &msgs[..third]);
    write_mcap(&bagdir.join("run_2.mcap"), &msgs[third..2 * third]);
    let bag = BagReader::open(&bagdir, opts(Preset::Vlp16)).unwrap();
    assert_eq!(bag.format(), BagFormat::Mcap);
    assert_eq!(bag.total_messages(), Some(63));
    drop(bag);
    let run = read_all(&bagdir, opts(Preset::Vlp16)).unwrap();
    assert!(run.warnings.is_empty(), "{:?}", run.warnings);
    check_sequence(&run, &exp);
    // The same splits with file compression.
    for k in [0, 2, 10] {
        let plain = bagdir.join(format!("run_{k}.mcap"));
        let data = std::fs::read(&plain).unwrap();
        std::fs::write(
            bagdir.join(format!("run_{k}.mcap.zstd")),
            zstd::stream::encode_all(data.as_slice(), 3).unwrap(),
        )
        .unwrap();
        std::fs::remove_file(&plain).unwrap();
    }
    let run = read_all(&bagdir, opts(Preset::Vlp16)).unwrap();
    check_sequence(&run, &exp);
}

/// rosbag2's file compression (`compression_mode: FILE`): every storage file one zstd stream,
/// split or not, sqlite3 or MCAP, given as the directory or as one `.zstd` file. Read as the
/// uncompressed bag is, from a temporary copy that is removed when the bag is closed.
#[test]
fn rosbag2_file_compression_is_read() {
    let dir = tmp("db3-zstd");
    let (msgs, exp) = sequence(Encoding::Cdr, build::VELODYNE);
    let half = msgs.len() / 2;
    let compress = |plain: &Path, to: &Path| {
        let data = std::fs::read(plain).unwrap();
        std::fs::write(to, zstd::stream::encode_all(data.as_slice(), 3).unwrap()).unwrap();
        std::fs::remove_file(plain).unwrap();
    };
    let bagdir = dir.join("run");
    std::fs::create_dir_all(&bagdir).unwrap();
    std::fs::write(
        bagdir.join("metadata.yaml"),
        "rosbag2_bagfile_information:\n  compression_format: zstd\n  compression_mode: FILE\n",
    )
    .unwrap();
    for (k, part, base) in [(0, &msgs[..half], 1), (1, &msgs[half..], 7)] {
        let plain = bagdir.join(format!("run_{k}.db3"));
        write_db3(&plain, part, base);
        compress(&plain, &bagdir.join(format!("run_{k}.db3.zstd")));
    }
    let temp_dirs = || {
        let prefix = format!("loglio-bag-{}-", std::process::id());
        std::fs::read_dir(std::env::temp_dir())
            .unwrap()
            .filter_map(|e| e.ok())
            .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
            .count()
    };
    {
        let bag = BagReader::open(&bagdir, opts(Preset::Vlp16)).unwrap();
        assert_eq!(bag.format(), BagFormat::Ros2Sqlite);
        assert_eq!(bag.total_messages(), Some(63));
        assert!(temp_dirs() >= 1, "decompressed into a temporary directory");
    }
    let run = read_all(&bagdir, opts(Preset::Vlp16)).unwrap();
    assert!(run.warnings.is_empty(), "{:?}", run.warnings);
    check_sequence(&run, &exp);
    // One storage file given alone, and an MCAP one.
    let run = read_all(&bagdir.join("run_0.db3.zstd"), opts(Preset::Vlp16)).unwrap();
    assert!(run.end.is_ok());
    assert_eq!(run.stats.messages, half as u64);
    let mcap = dir.join("all.mcap");
    write_mcap(&mcap, &msgs);
    compress(&mcap, &dir.join("all.mcap.zstd"));
    let bag = BagReader::open(&dir.join("all.mcap.zstd"), opts(Preset::Vlp16)).unwrap();
    assert_eq!(bag.format(), BagFormat::Mcap);
    drop(bag);
    let run = read_all(&dir.join("all.mcap.zstd"), opts(Preset::Vlp16)).unwrap();
    check_sequence(&run, &exp);
}

/// `/tf_static` gives the LiDAR frame in the IMU frame: through a common parent (`base_link`),
/// directly, or inverted; in ROS 1 and CDR bags. p_imu = R * p_lidar + t, values by hand.
#[test]
fn static_transforms_give_the_lidar_in_the_imu_frame() {
    use loglio_host::input::bag::msg::{TF_MESSAGE, Transform, encode_tf};
    let dir = tmp("tf-static");
    let tf = |parent: &str, child: &str, t: [f64; 3], q: [f64; 4]| Transform {
        parent: parent.into(),
        child: child.into(),
        translation: t,
        rotation_xyzw: q,
    };
    let s = std::f64::consts::FRAC_1_SQRT_2;
    let yaw90 = [0.0, 0.0, s, s];
    let cases = [
        (
            "common-parent",
            vec![
                tf("base_link", "imu_link", [0.1, 0.0, 0.2], [0.0, 0.0, 0.0, 1.0]),
                tf("/base_link", "velodyne", [0.3, 0.05, 0.5], yaw90),
            ],
            [0.2, 0.05, 0.3],
        ),
        ("direct", vec![tf("imu_link", "velodyne", [0.2, 0.05, 0.3], yaw90)], [0.2, 0.05, 0.3]),
        // velodyne -> imu_link: the IMU at (-0.05, 0.2, -0.3) in the LiDAR frame, yawed -90.
        (
            "inverse",
            vec![tf("velodyne", "imu_link", [-0.05, 0.2, -0.3], [0.0, 0.0, -s, s])],
            [0.2, 0.05, 0.3],
        ),
    ];
    for (name, transforms, t) in cases {
        for enc in [Encoding::Ros1, Encoding::Cdr] {
            let (mut msgs, _) = sequence(enc, build::VELODYNE);
            msgs.insert(0, (T0, "/tf_static", TF_MESSAGE, encode_tf(&transforms, enc)));
            let path =
                dir.join(format!("{name}-{enc:?}.{}", if enc == Encoding::Ros1 { "bag" } else { "mcap" }));
            if enc == Encoding::Ros1 {
                write_ros1(&path, &msgs, 4096, ChunkCompression::None);
            } else {
                write_mcap(&path, &msgs);
            }
            let e = BagReader::static_extrinsic(&path, &opts(Preset::Vlp16)).unwrap().unwrap();
            assert_eq!((e.lidar_frame.as_str(), e.imu_frame.as_str()), ("velodyne", "imu_link"), "{name}");
            let got = e.imu_lidar.translation.vector;
            for k in 0..3 {
                assert!((got[k] - t[k]).abs() < 1e-12, "{name} {enc:?}: {got:?}");
            }
            // R is a yaw of 90 degrees: the LiDAR's x is the IMU's y.
            let x = e.imu_lidar.rotation * nalgebra::Vector3::x();
            assert!((x - nalgebra::Vector3::y()).norm() < 1e-12, "{name} {enc:?}: {x:?}");
            // The run itself reads the bag as before (the /tf_static topic is not a role).
            let run = read_all(&path, opts(Preset::Vlp16)).unwrap();
            assert!(run.warnings.is_empty(), "{:?}", run.warnings);
            assert_eq!(run.items.len(), 63);
        }
    }
    // No /tf_static, or frames it does not connect: none.
    let (msgs, _) = sequence(Encoding::Ros1, build::VELODYNE);
    let plain = dir.join("plain.bag");
    write_ros1(&plain, &msgs, 4096, ChunkCompression::None);
    assert_eq!(BagReader::static_extrinsic(&plain, &opts(Preset::Vlp16)).unwrap(), None);
    let mut msgs = msgs;
    msgs.insert(
        0,
        (
            T0,
            "/tf_static",
            TF_MESSAGE,
            encode_tf(&[tf("map", "velodyne", [1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])], Encoding::Ros1),
        ),
    );
    let apart = dir.join("apart.bag");
    write_ros1(&apart, &msgs, 4096, ChunkCompression::None);
    assert_eq!(BagReader::static_extrinsic(&apart, &opts(Preset::Vlp16)).unwrap(), None);
    // /tf_static is latched: reading stops TF_SETTLE messages after the last one once both
    // frames are known. A connecting transform 900 messages after the first is found; one
    // 1,200 after is not looked for.
    assert_eq!(loglio_host::input::bag::TF_SETTLE, 1_000);
    let link = encode_tf(&[tf("map", "imu_link", [0.0; 3], [0.0, 0.0, 0.0, 1.0])], Encoding::Ros1);
    for (at, found) in [(900, true), (1_200, false)] {
        let mut msgs = long_sequence(60);
        msgs.insert(
            0,
            (
                T0,
                "/tf_static",
                TF_MESSAGE,
                encode_tf(&[tf("map", "velodyne", [1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])], Encoding::Ros1),
            ),
        );
        msgs.insert(at, (msgs[at - 1].0, "/tf_static", TF_MESSAGE, link.clone()));
        let path = dir.join(format!("late-{at}.bag"));
        write_ros1(&path, &msgs, 4096, ChunkCompression::None);
        let e = BagReader::static_extrinsic(&path, &opts(Preset::Vlp16)).unwrap();
        assert_eq!(e.is_some(), found, "{at}");
        if let Some(e) = e {
            assert_eq!(e.imu_lidar.translation.vector, nalgebra::Vector3::new(1.0, 0.0, 0.0));
        }
    }
}

/// rosbag2's message compression (`compression_mode: message`): each row is one zstd frame
/// (28 b5 2f fd), decompressed as it is read: the same scans and IMU samples as the plain bag,
/// from the file alone and from its directory with the metadata. A row that does not
/// decompress is said as such.
#[test]
fn rosbag2_sqlite_with_zstd_message_compression_reads_the_messages() {
    let dir = tmp("db3-zstd-msg");
    let bagdir = dir.join("run");
    std::fs::create_dir_all(&bagdir).unwrap();
    let (msgs, exp) = sequence(Encoding::Cdr, build::VELODYNE);
    let packed: Vec<_> = msgs
        .iter()
        .map(|(t, topic, ty, b)| (*t, *topic, *ty, zstd::encode_all(b.as_slice(), 3).unwrap()))
        .collect();
    assert!(packed.iter().all(|m| m.3.starts_with(&[0x28, 0xb5, 0x2f, 0xfd])));
    assert!(packed.iter().zip(&msgs).all(|(p, m)| p.3 != m.3));
    let db = bagdir.join("run_0.db3");
    write_db3(&db, &packed, 1);
    std::fs::write(
        bagdir.join("metadata.yaml"),
        "rosbag2_bagfile_information:\n  compression_format: zstd\n  compression_mode: MESSAGE\n",
    )
    .unwrap();
    for path in [&db, &bagdir] {
        let run = read_all(path, opts(Preset::Vlp16)).unwrap();
        assert!(run.warnings.is_empty(), "{:?}", run.warnings);
        check_sequence(&run, &exp);
    }
    // A row with the magic and garbage after it.
    let mut bad = packed.clone();
    bad[0].3 = vec![0x28, 0xb5, 0x2f, 0xfd, 1, 2, 3];
    let bad_db = dir.join("bad.db3");
    write_db3(&bad_db, &bad, 1);
    let run = read_all(&bad_db, opts(Preset::Vlp16)).unwrap();
    let said = format!("{}\n{:?}", run.warnings.join("\n"), run.end);
    assert!(
        said.contains(&format!(
            "{}: this rosbag2 is zstd-compressed (message compression) and message 1 does not decompress: ",
            bad_db.display()
        )),
        "{said}"
    );
}

/// Older rosbag2 releases and converted bags have no timestamp index: the reader then sorts the
/// message ids once instead of sorting the whole table for every page (quadratic: 34.5 s for
/// 100,000 messages). Same items in the same order, ties in record time by id.
#[test]
fn rosbag2_sqlite_without_a_timestamp_index_reads_in_time_order() {
    let dir = tmp("db3-noindex");
    let (msgs, exp) = sequence(Encoding::Cdr, build::VELODYNE);
    // Rows written in another order than their record times, across more than one page; no
    // reorder window, so the reader's own order is what comes out (a message older than one
    // delivered would be dropped).
    let rows = pairs_swapped(&msgs);
    let mut o = opts(Preset::Vlp16);
    o.reorder_window_ns = 0;
    let (plain, indexed) = (dir.join("plain.db3"), dir.join("indexed.db3"));
    write_db3_index(&plain, &rows, 1, false);
    write_db3_index(&indexed, &rows, 1, true);
    let run = read_all(&plain, o.clone()).unwrap();
    assert!(run.warnings.is_empty(), "{:?}", run.warnings);
    assert_eq!(run.stats.late, 0);
    check_sequence(&run, &exp);
    assert_eq!(run.items, read_all(&indexed, o.clone()).unwrap().items);
    // Equal record times: the row written first comes first, with the index or without.
    let mut ties = rows.clone();
    for r in ties.iter_mut().filter(|r| r.1 == "/imu/data") {
        r.0 = T0 + (r.0 - T0) / 20_000_000 * 20_000_000;
    }
    write_db3_index(&dir.join("ties.db3"), &ties, 1, false);
    write_db3_index(&dir.join("ties-indexed.db3"), &ties, 1, true);
    let a = read_all(&dir.join("ties.db3"), o.clone()).unwrap();
    let b = read_all(&dir.join("ties-indexed.db3"), o).unwrap();
    a.end.as_ref().unwrap();
    assert_eq!((a.items.len(), a.stats.late), (63, 0));
    assert!(a.items.windows(2).any(|w| w[0].record_ns == w[1].record_ns), "ties present");
    assert_eq!(a.items, b.items);
}

#[test]
fn record_time_stamps_when_the_capture_clock_is_chosen() {
    let dir = tmp("capture");
    let path = dir.join("c.bag");
    let (msgs, _) = sequence(Encoding::Ros1, build::VELODYNE);
    write_ros1(&path, &msgs, 768 * 1024, ChunkCompression::None);
    let mut o = opts(Preset::Vlp16);
    o.use_record_time = true;
    let run = read_all(&path, o).unwrap();
    for it in &run.items {
        match &it.event {
            BagEvent::Imu(s) => assert_eq!(s.t_ns, it.record_ns),
            BagEvent::Scan(s) => {
                let last = s.points.iter().map(|p| p.t).fold(0.0f32, f32::max);
                assert_eq!(s.stamp_ns, it.record_ns - (last as f64 * 1e9) as u64);
            }
            _ => unreachable!(),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Bad input.

fn small_bag(dir: &Path, name: &str, threshold: usize) -> (PathBuf, Vec<Msg>) {
    let path = dir.join(name);
    let (msgs, _) = sequence(Encoding::Ros1, build::VELODYNE);
    write_ros1(&path, &msgs, threshold, ChunkCompression::None);
    (path, msgs)
}

/// `scans` scans and 200 Hz IMU, in record order (20 IMU messages per scan).
fn long_sequence(scans: usize) -> Vec<Msg> {
    let mut out = Vec::new();
    for k in 0..scans {
        for j in 1..=20u64 {
            let t = T0 + k as u64 * 100_000_000 + j * 5_000_000;
            out.push((t + 100_000, "/imu/data", IMU, imu_at(t).encode("imu_link", Encoding::Ros1)));
        }
        let (c, _) = vlp16_scan(k, build::VELODYNE);
        out.push((c.stamp_ns + 8_000_000, "/velodyne_points", POINTCLOUD2, c.encode(Encoding::Ros1)));
    }
    out
}

/// The chunk records of a bag file, found by walking its records independently of the
/// reader: (start, end, messages), the messages counted from the index data records that
/// follow each chunk.
fn chunk_layout(bytes: &[u8]) -> Vec<(usize, usize, u64)> {
    let u32_at = |p: usize| u32::from_le_bytes(bytes[p..p + 4].try_into().unwrap()) as usize;
    let mut p = 13;
    let mut chunks: Vec<(usize, usize, u64)> = Vec::new();
    while p + 4 <= bytes.len() {
        let hl = u32_at(p);
        if p + 8 + hl > bytes.len() {
            break;
        }
        let header = &bytes[p + 4..p + 4 + hl];
        let dl = u32_at(p + 4 + hl);
        let end = p + 8 + hl + dl;
        if header.windows(4).any(|w| w == b"op=\x05") {
            chunks.push((p, end, 0));
        } else if header.windows(4).any(|w| w == b"op=\x04") {
            let at = header.windows(6).position(|w| w == b"count=").unwrap() + 6;
            chunks.last_mut().unwrap().2 += u32::from_le_bytes(header[at..at + 4].try_into().unwrap()) as u64;
        }
        p = end;
    }
    chunks
}

const INDEX_POS: std::ops::Range<usize> = 13 + 4 + 4 + 10..13 + 4 + 4 + 18;

#[test]
fn unindexed_and_cut_ros1_bags_give_the_messages_of_their_complete_chunks() {
    let dir = tmp("cut");
    let msgs = long_sequence(10);
    for (cname, comp) in
        [("none", ChunkCompression::None), ("bz2", ChunkCompression::Bz2), ("lz4", ChunkCompression::Lz4)]
    {
        let path = dir.join(format!("{cname}.bag"));
        // 4 KiB chunks: IMU-only chunks of about 12 messages and one chunk per cloud.
        write_ros1(&path, &msgs, 4096, comp);
        let bytes = std::fs::read(&path).unwrap();
        let full = read_all(&path, opts(Preset::Vlp16)).unwrap();
        full.end.as_ref().unwrap();
        assert!(full.warnings.is_empty(), "{:?}", full.warnings);
        assert_eq!(full.items.len(), 210);
        assert!(!full.stats.unindexed);
        let chunks = chunk_layout(&bytes);
        assert!(chunks.len() >= 20, "{cname}: {} chunks", chunks.len());
        assert_eq!(chunks.iter().map(|c| c.2).sum::<u64>(), 210);
        let index_pos = u64::from_le_bytes(bytes[INDEX_POS].try_into().unwrap());
        for percent in [50, 90] {
            let len = bytes.len() * percent / 100;
            let complete: Vec<_> = chunks.iter().filter(|c| c.1 <= len).collect();
            let want = complete.iter().map(|c| c.2).sum::<u64>() as usize;
            assert!(want > 10 && want < 210, "{cname} {percent} %: {want}");
            let cut = dir.join(format!("{cname}-{percent}.bag"));
            std::fs::write(&cut, &bytes[..len]).unwrap();
            let run = read_all(&cut, opts(Preset::Vlp16)).unwrap();
            run.end.as_ref().unwrap();
            assert_eq!(run.items.len(), want, "{cname} {percent} %");
            // The first `want` messages as written, in the order the complete bag gives them.
            let kept: std::collections::HashSet<u64> = msgs[..want].iter().map(|m| m.0).collect();
            let expect: Vec<&BagItem> = full.items.iter().filter(|i| kept.contains(&i.record_ns)).collect();
            assert_eq!(expect.len(), want);
            assert!(
                run.items.iter().zip(&expect).all(|(a, b)| a == *b),
                "{cname} {percent} %: the same messages, order and stamps"
            );
            let last = *kept.iter().max().unwrap();
            assert_eq!(run.warnings.len(), 1, "{:?}", run.warnings);
            let w = &run.warnings[0];
            assert!(
                w.starts_with(&format!(
                    "warning: {}: cut short or corrupt (its index starts at byte {index_pos} but the file has {len} bytes); read without the index, as `rosbag reindex` would: {want} messages recovered from {} chunks, record times 1700000000.005 to {}.{:03} s; the records end at byte {} of {len} (",
                    cut.display(),
                    complete.len(),
                    last / 1_000_000_000,
                    last % 1_000_000_000 / 1_000_000,
                    chunks.iter().find(|c| c.1 > len).unwrap().0,
                )),
                "{w}"
            );
            assert!(w.ends_with("), the rest is lost"), "{w}");
            assert!(run.stats.unindexed);
            assert_eq!(run.stats.truncated_files, 1);
            assert_eq!(run.stats.messages, want as u64);
            assert!(
                run.stats
                    .to_string()
                    .ends_with("; read without its index; 1 file(s) read only up to damage, the rest lost")
            );
        }
        // Never closed: index_pos 0, everything there.
        let open = dir.join(format!("{cname}-open.bag"));
        let mut b = bytes.clone();
        b[INDEX_POS].copy_from_slice(&0u64.to_le_bytes());
        std::fs::write(&open, &b).unwrap();
        let run = read_all(&open, opts(Preset::Vlp16)).unwrap();
        run.end.as_ref().unwrap();
        assert_eq!(run.items, full.items);
        assert_eq!(
            run.warnings,
            vec![format!(
                "warning: {}: the bag was not closed (no index: the recorder was stopped abruptly); read without the index, as `rosbag reindex` would: 210 messages recovered from {} chunks, record times 1700000000.005 to 1700000001.008 s",
                open.display(),
                chunks.len()
            )]
        );
        assert!(run.stats.unindexed);
        assert_eq!(run.stats.truncated_files, 0);
    }
}

#[test]
fn a_recorder_killed_mid_bag_and_damaged_indexes_are_read_by_walking_the_records() {
    let dir = tmp("killed");
    let msgs = long_sequence(4);
    // The writer dropped without `finish`: the closed chunks are on disk, the open one and the
    // index are not, and index_pos is 0, as a killed `rosbag record` leaves it.
    let killed = dir.join("killed.bag");
    let mut w = Ros1BagWriter::create(&killed).unwrap();
    w.set_chunk_threshold(4096);
    let imu = w.add_typed_connection("/imu/data", &IMU).unwrap();
    let pc = w.add_typed_connection("/velodyne_points", &POINTCLOUD2).unwrap();
    // All but the last cloud: the last IMU messages are in the open chunk, lost.
    for (t, topic, _, bytes) in &msgs[..83] {
        w.write(if *topic == "/imu/data" { imu } else { pc }, *t, bytes).unwrap();
    }
    drop(w);
    let bytes = std::fs::read(&killed).unwrap();
    let want = chunk_layout(&bytes).iter().map(|c| c.2).sum::<u64>() as usize;
    assert!(want > 40 && want < 83, "{want}");
    let run = read_all(&killed, opts(Preset::Vlp16)).unwrap();
    run.end.as_ref().unwrap();
    assert_eq!(run.items.len(), want);
    let full_path = dir.join("full.bag");
    write_ros1(&full_path, &msgs, 4096, ChunkCompression::None);
    let full = read_all(&full_path, opts(Preset::Vlp16)).unwrap();
    let kept: std::collections::HashSet<u64> = msgs[..want].iter().map(|m| m.0).collect();
    let expect: Vec<&BagItem> = full.items.iter().filter(|i| kept.contains(&i.record_ns)).collect();
    assert_eq!(expect.len(), want);
    assert!(run.items.iter().zip(&expect).all(|(a, b)| a == *b), "the same messages, order and stamps");
    assert_eq!(run.warnings.len(), 1);
    assert!(
        run.warnings[0].contains(&format!(
            "the bag was not closed (no index: the recorder was stopped abruptly); read without the index, as `rosbag reindex` would: {want} messages recovered"
        )),
        "{}",
        run.warnings[0]
    );
    // Cut inside the index section: the index is corrupt, every chunk is whole.
    let fb = std::fs::read(&full_path).unwrap();
    let idx = dir.join("index.bag");
    std::fs::write(&idx, &fb[..fb.len() - 10]).unwrap();
    let run = read_all(&idx, opts(Preset::Vlp16)).unwrap();
    run.end.as_ref().unwrap();
    assert_eq!(run.items, full.items);
    assert_eq!(run.warnings.len(), 1);
    assert!(
        run.warnings[0].starts_with(&format!("warning: {}: corrupt index (", idx.display())),
        "{}",
        run.warnings[0]
    );
    assert!(
        run.warnings[0].contains("read without the index, as `rosbag reindex` would: 84 messages recovered")
    );
    // Never closed and a chunk damaged inside: the chunk is reported and skipped, the walk
    // goes on past it.
    let layout = chunk_layout(&fb);
    let mut b = fb.clone();
    b[INDEX_POS].copy_from_slice(&0u64.to_le_bytes());
    let (start, _, lost) = layout[1];
    let hl = u32::from_le_bytes(b[start..start + 4].try_into().unwrap()) as usize;
    let first_inner = start + 8 + hl;
    b[first_inner..first_inner + 4].copy_from_slice(&0x7fff_ffffu32.to_le_bytes());
    let both = dir.join("both.bag");
    std::fs::write(&both, &b).unwrap();
    let run = read_all(&both, opts(Preset::Vlp16)).unwrap();
    run.end.as_ref().unwrap();
    assert!(lost > 0);
    assert_eq!(run.items.len(), 84 - lost as usize);
    assert_eq!(run.stats.skipped_chunks, 1);
    assert_eq!(run.warnings.len(), 2, "{:?}", run.warnings);
    assert!(run.warnings[0].contains(&format!(
        "{} messages recovered from {} chunks",
        84 - lost,
        layout.len()
    )));
    assert!(
        run.warnings[1].starts_with(&format!("warning: {}: corrupt chunk at byte {start}: ", both.display())),
        "{}",
        run.warnings[1]
    );
    // Cut inside the header, or inside the first chunk: nothing to read, one line.
    let tiny = dir.join("tiny.bag");
    std::fs::write(&tiny, &fb[..40]).unwrap();
    assert_eq!(
        open_err(&tiny, opts(Preset::Vlp16)),
        format!("{}: truncated: the file ends inside the bag header", tiny.display())
    );
    let first = chunk_layout(&fb)[0];
    let short = dir.join("short.bag");
    std::fs::write(&short, &fb[..first.1 - 1]).unwrap();
    assert_eq!(
        open_err(&short, opts(Preset::Vlp16)),
        format!(
            "{}: cut short or corrupt (its index starts at byte {} but the file has {} bytes), and no chunk could be read without it; the records end at byte {} of {} (a record's data runs past the end of the file), the rest is lost",
            short.display(),
            u64::from_le_bytes(fb[INDEX_POS].try_into().unwrap()),
            first.1 - 1,
            first.0,
            first.1 - 1
        )
    );
}

#[test]
fn a_corrupt_chunk_is_skipped_and_the_others_are_read() {
    let dir = tmp("corrupt-chunk");
    let (path, _) = small_bag(&dir, "b.bag", 64 * 1024);
    let mut bytes = std::fs::read(&path).unwrap();
    // Walk the records after the magic: (header_len, header, data_len, data); find the chunks.
    let u32_at = |b: &[u8], p: usize| u32::from_le_bytes(b[p..p + 4].try_into().unwrap()) as usize;
    let mut p = 13;
    let mut chunk_data = Vec::new();
    while p + 4 <= bytes.len() {
        let hl = u32_at(&bytes, p);
        let header = &bytes[p + 4..p + 4 + hl];
        let dl = u32_at(&bytes, p + 4 + hl);
        if header.windows(4).any(|w| w == b"op=\x05") {
            chunk_data.push(p + 8 + hl);
        }
        p += 8 + hl + dl;
    }
    assert!(chunk_data.len() >= 3, "{} chunks", chunk_data.len());
    // Damage the length of the first record inside the second chunk.
    let at = chunk_data[1];
    bytes[at..at + 4].copy_from_slice(&0x7fff_ffffu32.to_le_bytes());
    let bad = dir.join("bad.bag");
    std::fs::write(&bad, &bytes).unwrap();
    let run = read_all(&bad, opts(Preset::Vlp16)).unwrap();
    run.end.as_ref().unwrap();
    assert_eq!(run.stats.skipped_chunks, 1);
    assert_eq!(run.warnings.len(), 1, "{:?}", run.warnings);
    assert!(
        run.warnings[0].starts_with(&format!("warning: {}: corrupt chunk at byte ", bad.display())),
        "{}",
        run.warnings[0]
    );
    assert!(run.warnings[0].ends_with("; skipped it (later damage is counted)"));
    // Everything outside the damaged chunk is there.
    let good = read_all(&path, opts(Preset::Vlp16)).unwrap();
    assert!(run.items.len() < good.items.len());
    assert!(run.items.len() >= good.items.len() - 25, "{} of {}", run.items.len(), good.items.len());
}

#[test]
fn missing_ambiguous_and_mistyped_topics_are_one_line_errors() {
    let dir = tmp("topics");
    // Cloud only: no IMU.
    let (c, _) = vlp16_scan(0, build::VELODYNE);
    let path = dir.join("noimu.bag");
    write_ros1(
        &path,
        &[(T0, "/points", POINTCLOUD2, c.encode(Encoding::Ros1))],
        1 << 20,
        ChunkCompression::None,
    );
    assert_eq!(
        open_err(&path, opts(Preset::Vlp16)),
        format!(
            "{}: no IMU topic (sensor_msgs/Imu); the bag has /points (sensor_msgs/PointCloud2)",
            path.display()
        )
    );
    let mut o = opts(Preset::Vlp16);
    o.require_imu = false;
    assert!(BagReader::open(&path, o.clone()).is_ok());
    o.lidar_topic = Some("/velodyne_points".into());
    assert_eq!(
        open_err(&path, o.clone()),
        format!(
            "{}: no topic /velodyne_points; the bag has /points (sensor_msgs/PointCloud2)",
            path.display()
        )
    );
    // Two clouds and a string.
    let two = dir.join("two.bag");
    let b = c.encode(Encoding::Ros1);
    write_ros1(
        &two,
        &[
            (T0, "/a", POINTCLOUD2, b.clone()),
            (T0, "/b", POINTCLOUD2, b),
            (T0, "/imu", IMU, imu_at(T0).encode("i", Encoding::Ros1)),
            (T0, "/note", STRING, msg::encode_string("hello", Encoding::Ros1)),
        ],
        1 << 20,
        ChunkCompression::None,
    );
    assert_eq!(
        open_err(&two, opts(Preset::Vlp16)),
        format!("{}: several LiDAR topics (/a, /b); name one (lidar topic option)", two.display())
    );
    let mut o = opts(Preset::Vlp16);
    o.lidar_topic = Some("/note".into());
    assert_eq!(
        open_err(&two, o),
        format!(
            "{}: topic /note is a std_msgs/String, not a LiDAR message (sensor_msgs/PointCloud2, velodyne_msgs/VelodyneScan or Ouster PacketMsg)",
            two.display()
        )
    );
    let mut o = opts(Preset::Vlp16);
    o.lidar_topic = Some("/a".into());
    o.imu_topic = Some("/b".into());
    assert_eq!(
        open_err(&two, o),
        format!(
            "{}: topic /b is a sensor_msgs/PointCloud2, not an IMU message (sensor_msgs/Imu or Ouster IMU PacketMsg)",
            two.display()
        )
    );
    // IMU only.
    let imu_only = dir.join("imu.bag");
    write_ros1(
        &imu_only,
        &[(T0, "/imu", IMU, imu_at(T0).encode("i", Encoding::Ros1))],
        1 << 20,
        ChunkCompression::None,
    );
    assert_eq!(
        open_err(&imu_only, opts(Preset::Vlp16)),
        format!(
            "{}: no LiDAR topic (sensor_msgs/PointCloud2, velodyne_msgs/VelodyneScan or Ouster PacketMsg); the bag has /imu (sensor_msgs/Imu)",
            imu_only.display()
        )
    );
}

#[test]
fn malformed_messages_are_dropped_counted_and_warned_once() {
    let dir = tmp("malformed");
    let (mut msgs, _) = sequence(Encoding::Ros1, build::VELODYNE);
    // Cut the data of the first cloud short (the message itself stays well-formed ROS 1) and
    // truncate an IMU message.
    let k = msgs.iter().position(|m| m.1 == "/velodyne_points").unwrap();
    let mut c = PointCloud2::decode(&msgs[k].3, Encoding::Ros1).unwrap();
    c.data.truncate(1000);
    msgs[k].3 = c.encode(Encoding::Ros1);
    msgs[0].3.truncate(50);
    let path = dir.join("m.bag");
    write_ros1(&path, &msgs, 768 * 1024, ChunkCompression::None);
    let run = read_all(&path, opts(Preset::Vlp16)).unwrap();
    run.end.as_ref().unwrap();
    assert_eq!(run.stats.malformed, 2);
    assert_eq!(run.stats.scans, 2);
    assert_eq!(run.stats.imu, 59);
    assert_eq!(
        run.warnings,
        vec![
            "warning: /imu/data: dropped a malformed sensor_msgs/Imu message (message too short: Imu fields needs 8 more bytes, 2 left); later ones are counted".to_string(),
            "warning: /velodyne_points: dropped a malformed sensor_msgs/PointCloud2 message (data holds 1000 bytes, row_step x height needs 184320 (truncated cloud)); later ones are counted".to_string(),
        ]
    );
}

#[test]
fn late_messages_are_dropped_and_counted() {
    let dir = tmp("late");
    let (mut msgs, _) = sequence(Encoding::Ros1, build::VELODYNE);
    // One IMU sample recorded 3 s before the rest, written last: past the 1 s window.
    let mut m = msgs[5].clone();
    m.0 -= 3_000_000_000;
    msgs.push(m);
    let path = dir.join("l.bag");
    write_ros1(&path, &msgs, 768 * 1024, ChunkCompression::None);
    // Within the reorder window a message is sorted in; past it, dropped.
    let sorted = read_all(&path, opts(Preset::Vlp16)).unwrap();
    assert_eq!((sorted.stats.late, sorted.stats.imu), (0, 61));
    assert_eq!(sorted.items[0].record_ns, msgs[5].0 - 3_000_000_000);
    let mut o = opts(Preset::Vlp16);
    o.reorder_window_ns = 50_000_000;
    let run = read_all(&path, o).unwrap();
    assert_eq!(run.stats.late, 1);
    assert_eq!(run.stats.imu, 60);
    assert_eq!(run.warnings.len(), 1);
    assert!(run.warnings[0].contains("was dropped (later ones are counted)"));
}

/// One corrupt record time far ahead (here 11.6 days) must not end the sorting for the rest of
/// the bag: its slightly disordered messages were dropped as late (24 of the 52 after it). The
/// message is dropped and counted wherever it stands; a real gap, which the next messages
/// follow, is taken.
#[test]
fn a_corrupt_record_time_far_ahead_is_dropped_and_a_real_gap_is_taken() {
    let dir = tmp("future");
    let (msgs, _) = sequence(Encoding::Ros1, build::VELODYNE);
    let rows = pairs_swapped(&msgs);
    // The rows as a ROS 1 bag, read back.
    let run_of = |name: &str, rows: &[Msg]| {
        let path = dir.join(name);
        write_ros1(&path, rows, 768 * 1024, ChunkCompression::None);
        read_all(&path, opts(Preset::Vlp16)).unwrap()
    };
    for at in [10, 30, rows.len() - 1] {
        let mut bad = rows.clone();
        bad[at].0 += 1_000_000_000_000_000;
        let run = run_of(&format!("f{at}.bag"), &bad);
        run.end.as_ref().unwrap();
        assert_eq!((run.stats.late, run.stats.out_of_sequence), (0, 1), "at {at}");
        assert_eq!(run.items.len(), 62, "at {at}");
        assert!(run.items.windows(2).all(|w| w[0].record_ns <= w[1].record_ns), "at {at}");
        assert!(run.items.iter().all(|i| i.record_ns < T0 + 1_000_000_000), "at {at}");
        assert_eq!(run.warnings.len(), 1, "at {at}: {:?}", run.warnings);
        assert!(run.warnings[0].contains("a corrupt time"), "{}", run.warnings[0]);
        assert!(run.stats.to_string().contains("1 out of sequence"));
    }
    // Among the first messages, which set the window's clock by their median, a corrupt time
    // is delivered (last, in record-time order) and the sorting still works.
    let mut bad = rows.clone();
    bad[0].0 += 1_000_000_000_000_000;
    let run = run_of("first.bag", &bad);
    assert_eq!((run.stats.late, run.stats.out_of_sequence, run.items.len()), (0, 0, 63));
    assert!(run.items.windows(2).all(|w| w[0].record_ns <= w[1].record_ns));
    assert_eq!(run.items[62].record_ns, bad[0].0);
    // A first message well before the rest (a latched topic recorded before the sensor
    // started) is kept.
    let mut early = rows.clone();
    early[0].0 -= 20_000_000_000;
    let run = run_of("early.bag", &early);
    assert_eq!((run.stats.late, run.stats.out_of_sequence, run.items.len()), (0, 0, 63));
    assert_eq!(run.items[0].record_ns, early[0].0);
    // A gap of 100 s in the recording (the second half later), which the messages follow.
    let mut gap = rows.clone();
    for r in gap[30..].iter_mut() {
        r.0 += 100_000_000_000;
    }
    let run = run_of("gap.bag", &gap);
    run.end.as_ref().unwrap();
    assert!(run.warnings.is_empty(), "{:?}", run.warnings);
    assert_eq!((run.stats.late, run.stats.out_of_sequence, run.items.len()), (0, 0, 63));
    assert!(run.items.windows(2).all(|w| w[0].record_ns <= w[1].record_ns));
}

#[test]
fn truncated_mcap_delivers_the_good_messages_then_one_error() {
    let dir = tmp("mcap-cut");
    let path = dir.join("seq.mcap");
    let (msgs, _) = sequence(Encoding::Cdr, build::VELODYNE);
    write_mcap(&path, &msgs);
    let bytes = std::fs::read(&path).unwrap();
    let cut = dir.join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let run = read_all(&cut, opts(Preset::Vlp16)).unwrap();
    let e = run.end.unwrap_err().0;
    assert!(e.starts_with(&format!("{}: corrupt or truncated MCAP: ", cut.display())), "{e}");
    assert!(!e.contains('\n'));
    assert!(!run.items.is_empty() && run.items.len() < 63, "{}", run.items.len());
}

#[test]
fn not_bags_corrupt_databases_and_compressed_bags_are_one_line_errors() {
    let dir = tmp("notbags");
    let o = || opts(Preset::Vlp16);
    let text = dir.join("notes.txt");
    std::fs::write(&text, "hello, not a bag\n").unwrap();
    assert_eq!(
        open_err(&text, o()),
        format!("{}: not a ROS bag (neither a ROS 1 bag, a rosbag2 sqlite3 file nor MCAP)", text.display())
    );
    let empty = dir.join("empty.bag");
    std::fs::write(&empty, "").unwrap();
    assert_eq!(open_err(&empty, o()), format!("{}: empty file, not a bag", empty.display()));
    let missing = dir.join("missing.bag");
    assert!(open_err(&missing, o()).starts_with(&format!("cannot open {}: ", missing.display())));
    let v1 = dir.join("v1.bag");
    std::fs::write(&v1, "#ROSBAG V1.2\nxxxx").unwrap();
    assert_eq!(
        open_err(&v1, o()),
        format!("{}: unsupported ROS bag version (only 2.0 is read)", v1.display())
    );
    let z = dir.join("b.db3.zstd");
    std::fs::write(&z, [0x28, 0xb5, 0x2f, 0xfd, 0, 0]).unwrap();
    let e = open_err(&z, o());
    assert!(
        e.starts_with(&format!(
            "{}: a zstd-compressed file (rosbag2 file compression) that does not decompress: ",
            z.display()
        )),
        "{e}"
    );
    // A zstd stream of something else.
    let zt = dir.join("text.zstd");
    std::fs::write(&zt, zstd::stream::encode_all(&b"hello, not a bag"[..], 3).unwrap()).unwrap();
    assert_eq!(
        open_err(&zt, o()),
        format!(
            "{}: a zstd-compressed file that holds no rosbag2 storage file (sqlite3 or MCAP)",
            zt.display()
        )
    );
    // A rosbag2 directory that says it is compressed.
    let cdir = dir.join("compressed");
    std::fs::create_dir_all(&cdir).unwrap();
    std::fs::write(
        cdir.join("metadata.yaml"),
        "rosbag2_bagfile_information:\n  compression_format: zstd\n  compression_mode: FILE\n",
    )
    .unwrap();
    assert_eq!(
        open_err(&cdir, o()),
        format!("{}: no .db3 or .mcap files (not a rosbag2 directory)", cdir.display())
    );
    // A broken .db3.zstd file, without the metadata.
    std::fs::remove_file(cdir.join("metadata.yaml")).unwrap();
    let c0 = cdir.join("c_0.db3.zstd");
    std::fs::write(&c0, [0x28, 0xb5, 0x2f, 0xfd, 0, 0]).unwrap();
    let e = open_err(&cdir, o());
    assert!(
        e.starts_with(&format!(
            "{}: a zstd-compressed file (rosbag2 file compression) that does not decompress: ",
            c0.display()
        )),
        "{e}"
    );
    // Another compression format is named with the fix.
    std::fs::write(
        cdir.join("metadata.yaml"),
        "rosbag2_bagfile_information:\n  compression_format: lz4\n  compression_mode: FILE\n",
    )
    .unwrap();
    assert_eq!(
        open_err(&cdir, o()),
        format!(
            "{}: this rosbag2 is lz4-compressed (file compression), which loglio does not read; decompress it first (`ros2 bag convert` to an uncompressed bag)",
            cdir.display()
        )
    );
    let edir = dir.join("emptydir");
    std::fs::create_dir_all(&edir).unwrap();
    assert_eq!(
        open_err(&edir, o()),
        format!("{}: no .db3 or .mcap files (not a rosbag2 directory)", edir.display())
    );
    // A sqlite database that is not a rosbag2 one.
    let other = dir.join("other.db3");
    rusqlite::Connection::open(&other).unwrap().execute_batch("CREATE TABLE t(x INTEGER);").unwrap();
    assert_eq!(
        open_err(&other, o()),
        format!("{}: not a rosbag2 database (no topics and messages tables)", other.display())
    );
    // A real rosbag2 file with its pages damaged / cut short: the rows before the damage,
    // then one warning naming how many.
    let src = data("velodyne-nebula/vlp16_dual_rosbag2/1673400471837873222/1673400471837873222_0.db3");
    let bytes = std::fs::read(&src).unwrap();
    let mut o2 = o();
    o2.require_imu = false;
    let whole = read_all(&src, o2.clone()).unwrap();
    whole.end.as_ref().unwrap();
    for (name, damaged) in [
        ("cut.db3", bytes[..bytes.len() / 3].to_vec()),
        ("garbled.db3", {
            // Damage pages in the middle (message blobs and their overflow-page links).
            let mut b = bytes.clone();
            let mid = bytes.len() / 2 / 4096 * 4096;
            for x in &mut b[mid..mid + 8 * 4096] {
                *x = 0xa5;
            }
            b
        }),
    ] {
        let p = dir.join(name);
        std::fs::write(&p, &damaged).unwrap();
        let run = read_all(&p, o2.clone()).unwrap();
        run.end.as_ref().unwrap();
        assert!(run.items.len() < whole.items.len(), "{name}");
        assert!(
            run.items.iter().zip(&whole.items).all(|(a, b)| a == b),
            "{name}: the rows before the damage"
        );
        assert_eq!(run.warnings.len(), 1, "{name}: {:?}", run.warnings);
        let w = &run.warnings[0];
        assert!(w.starts_with(&format!("warning: {}: corrupt rosbag2 database: ", p.display())), "{w}");
        assert!(
            w.ends_with(&format!(
                "; the {} rows before the damage are read, the rest of the file is lost",
                run.stats.messages
            )),
            "{w}"
        );
        assert_eq!(run.stats.truncated_files, 1);
    }
}

/// Where `data` lies in `bytes`.
fn find(bytes: &[u8], data: &[u8]) -> Option<usize> {
    bytes.windows(data.len()).position(|w| w == data)
}

#[test]
fn a_damaged_rosbag2_database_gives_its_rows_before_the_damage() {
    let dir = tmp("db3-damaged");
    let (mut msgs, _) = sequence(Encoding::Cdr, build::VELODYNE);
    for j in 0..540u64 {
        let t = T0 + 300_000_000 + (j + 1) * 5_000_000;
        msgs.push((t + 100_000, "/imu/data", IMU, imu_at(t).encode("imu_link", Encoding::Cdr)));
    }
    for index in [false, true] {
        let path = dir.join(format!("index-{index}.db3"));
        write_db3_index(&path, &msgs, 1, index);
        let full = read_all(&path, opts(Preset::Vlp16)).unwrap();
        full.end.as_ref().unwrap();
        assert_eq!(full.items.len(), 603);
        let mut bytes = std::fs::read(&path).unwrap();
        // Overwrite the page holding message 400 (an IMU row; its table leaf page).
        let page = find(&bytes, &msgs[400].3).unwrap() / 4096 * 4096;
        // A leaf holds a run of rows; the reading stops at the first of them (rows are read
        // in id order, or in time order, which is the same for these).
        let on_page = |k: usize| find(&bytes[page..page + 4096], &msgs[k].3).is_some();
        let want = (300..=400).find(|&k| on_page(k)).unwrap();
        assert!(want > 300 && (want..=400).all(on_page), "{want}");
        bytes[page..page + 4096].fill(0xa5);
        let bad = dir.join(format!("bad-{index}.db3"));
        std::fs::write(&bad, &bytes).unwrap();
        let run = read_all(&bad, opts(Preset::Vlp16)).unwrap();
        run.end.as_ref().unwrap();
        assert_eq!(run.items.len(), want, "index {index}");
        let kept: std::collections::HashSet<u64> = msgs[..want].iter().map(|m| m.0).collect();
        let expect: Vec<&BagItem> = full.items.iter().filter(|i| kept.contains(&i.record_ns)).collect();
        assert!(run.items.iter().zip(&expect).all(|(a, b)| a == *b), "the same rows, order and stamps");
        assert_eq!(
            run.warnings,
            vec![format!(
                "warning: {}: corrupt rosbag2 database: database disk image is malformed; the {want} rows before the damage are read, the rest of the file is lost",
                bad.display()
            )]
        );
        assert_eq!(run.stats.truncated_files, 1);
        assert!(!run.stats.unindexed);
        // The bag's message count needs the whole table: unknown.
        assert_eq!(BagReader::open(&bad, opts(Preset::Vlp16)).unwrap().total_messages(), None);
    }
    // A file that is not sqlite at all, named .db3: one line.
    let junk = dir.join("junk.db3");
    std::fs::write(&junk, vec![0x5a; 8192]).unwrap();
    assert_eq!(
        open_err(&junk, opts(Preset::Vlp16)),
        format!("{}: not a ROS bag (neither a ROS 1 bag, a rosbag2 sqlite3 file nor MCAP)", junk.display())
    );
}

#[test]
fn the_writer_takes_any_message_type_and_rejects_bad_md5s() {
    let dir = tmp("writer");
    let path = dir.join("w.bag");
    let mut w = Ros1BagWriter::create(&path).unwrap();
    assert!(w.add_connection("/x", "my_msgs/Thing", "not-an-md5", "int32 a\n").is_err());
    let c = w.add_connection("/x", "my_msgs/Thing", "0123456789abcdef0123456789abcdef", "int32 a\n").unwrap();
    w.write(c, T0, &7i32.to_le_bytes()).unwrap();
    assert_eq!(w.messages(), 1);
    let mut f = w.finish().unwrap();
    // The writer leaves the file positioned at its end.
    assert_eq!(f.stream_position().unwrap(), std::fs::metadata(&path).unwrap().len());
    f.flush().unwrap();
    f.seek(SeekFrom::Start(0)).unwrap();
    // Read back with the `rosbag` crate directly.
    let bag = rosbag::RosBag::new(&path).unwrap();
    let mut got = Vec::new();
    for rec in bag.chunk_records() {
        if let rosbag::ChunkRecord::Chunk(ch) = rec.unwrap() {
            for m in ch.messages() {
                match m.unwrap() {
                    rosbag::MessageRecord::MessageData(d) => got.push((d.conn_id, d.time, d.data.to_vec())),
                    rosbag::MessageRecord::Connection(c) => {
                        assert_eq!(
                            (c.topic, c.tp, c.message_definition),
                            ("/x", "my_msgs/Thing", "int32 a\n")
                        );
                    }
                }
            }
        }
    }
    assert_eq!(got, vec![(0, T0, 7i32.to_le_bytes().to_vec())]);
}
