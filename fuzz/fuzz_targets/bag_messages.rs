//! The bag message decoders (PointCloud2, Imu, VelodyneScan, PacketMsg, String; ROS 1 and CDR)
//! and the cloud conversion behind them, fed two ways: serialised bytes as a bag holds them,
//! and clouds built around the input from a fuzzed field table (the drivers' field names at any
//! offset, datatype and count, any point and row step, either byte order), which reach the
//! conversion's time-unit and ring logic far more often than decoded bytes do.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_core::scan::NO_PIXEL;
use loglio_host::input::bag::cloud::{CloudOptions, CloudScan, cloud_to_scan};
use loglio_host::input::bag::msg::{
    Encoding, Imu, PointCloud2, PointField, VelodyneScan, decode_packet_msg, decode_string,
};
use loglio_host::config::{Config, Preset};

const PRESETS: [Preset; 4] = [Preset::Vlp16, Preset::Vlp32c, Preset::Os1_16, Preset::Os1_64];
const NAMES: [&str; 11] =
    ["x", "y", "z", "intensity", "reflectivity", "ring", "t", "time", "timestamp", "range", ""];

/// What every converted scan must satisfy.
fn check(c: &PointCloud2, s: &CloudScan, opt: &CloudOptions) {
    let total = c.width as usize * c.height as usize;
    assert_eq!(s.points.len() + s.skipped as usize, total);
    let (rows, cols) = (opt.layout.rows(), opt.layout.cols());
    for p in &s.points {
        assert!(p.xyz.iter().all(|v| v.is_finite()), "{p:?}");
        assert!(p.t.is_finite() && p.t >= 0.0, "{p:?}");
        if p.row == NO_PIXEL {
            assert_eq!(p.col, NO_PIXEL);
        } else {
            assert!(usize::from(p.row) < rows && usize::from(p.col) < cols, "{p:?}");
        }
    }
}

/// A cloud from the input: a field table, steps and flags, then the point bytes.
fn built(d: &[u8]) -> Option<PointCloud2> {
    let (&nf, d) = d.split_first()?;
    let nf = usize::from(nf % 8);
    if d.len() < nf * 4 + 8 {
        return None;
    }
    let (table, d) = d.split_at(nf * 4);
    let fields = table
        .chunks(4)
        .map(|f| PointField {
            name: NAMES[usize::from(f[0]) % NAMES.len()].to_string(),
            offset: u32::from(f[1]),
            datatype: f[2] % 10, // 0 and 9 are not ROS datatypes
            count: u32::from(f[3] % 3),
        })
        .collect();
    let (head, data) = d.split_at(8);
    let point_step = u32::from(head[0]);
    let width = u32::from(u16::from_le_bytes([head[1], head[2]]) % 4096);
    let height = u32::from(head[3] % 8);
    let row_step = width * point_step + u32::from(head[4] % 16);
    let stamp_ns = u64::from(u32::from_le_bytes([head[5], head[6], head[7], 0])) * 1_000_000_000;
    Some(PointCloud2 {
        stamp_ns,
        frame_id: String::new(),
        height,
        width,
        fields,
        is_bigendian: head[4] & 0x80 != 0,
        point_step,
        row_step,
        data: data.to_vec(),
        is_dense: false,
    })
}

fuzz_target!(|data: &[u8]| {
    let Some((&sel, rest)) = data.split_first() else { return };
    let enc = if sel & 1 == 0 { Encoding::Ros1 } else { Encoding::Cdr };
    let preset = PRESETS[usize::from(sel >> 1) % PRESETS.len()];
    let Ok(opt) = CloudOptions::from_config(&Config::preset(preset)) else { return };
    match (sel >> 3) % 6 {
        0 => {
            if let Ok(c) = PointCloud2::decode(rest, enc) {
                // What was decoded encodes back to a message that decodes the same.
                assert_eq!(PointCloud2::decode(&c.encode(enc), enc).as_ref(), Ok(&c));
                if let Ok(s) = cloud_to_scan(&c, &opt) {
                    check(&c, &s, &opt);
                }
            }
        }
        1 => {
            if let Some(c) = built(rest)
                && let Ok(s) = cloud_to_scan(&c, &opt)
            {
                check(&c, &s, &opt);
            }
        }
        2 => {
            let _ = Imu::decode(rest, enc);
        }
        3 => {
            if let Ok(v) = VelodyneScan::decode(rest, enc) {
                assert!(v.packets.iter().all(|(_, p)| p.len() == 1206));
                assert_eq!(VelodyneScan::decode(&v.encode(enc), enc).as_ref(), Ok(&v));
            }
        }
        4 => {
            if let Ok(p) = decode_packet_msg(rest, enc) {
                assert!(p.len() <= rest.len());
            }
        }
        _ => {
            let _ = decode_string(rest, enc);
        }
    }
});
