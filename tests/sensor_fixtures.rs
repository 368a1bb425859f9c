//! Fixture helpers shared by the sensor tests (included with `#[path]` by each test target).
#![allow(dead_code)]

use loglio_host::input::pcap::PcapReader;
use std::path::PathBuf;

/// `tests/data/<rel>`.
pub fn data(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data").join(rel)
}

/// The bytes of an xz-compressed fixture.
pub fn xz(rel: &str) -> Vec<u8> {
    let path = data(rel);
    let packed = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut out = Vec::new();
    lzma_rs::xz_decompress(&mut &packed[..], &mut out)
        .unwrap_or_else(|e| panic!("{}: {e:?}", path.display()));
    out
}

/// A UDP datagram of a capture.
#[derive(Clone, Debug)]
pub struct Datagram {
    pub ts_ns: u64,
    pub dst_port: u16,
    pub payload: Vec<u8>,
}

/// Every UDP datagram of a pcap (bytes), in file order.
pub fn datagrams(pcap: &[u8]) -> Vec<Datagram> {
    let mut r = PcapReader::from_bytes(pcap).expect("pcap header");
    let mut out = Vec::new();
    while let Some(p) = r.next_udp().expect("pcap records") {
        out.push(Datagram { ts_ns: p.ts_ns, dst_port: p.dst_port, payload: p.payload.to_vec() });
    }
    assert_eq!(r.stats.malformed + r.stats.corrupt_records, 0, "{:?}", r.stats);
    out
}

/// The datagrams of an xz-compressed capture.
pub fn capture(rel: &str) -> Vec<Datagram> {
    datagrams(&xz(rel))
}

/// Columns of little-endian i32 values.
pub fn i32_col(b: &[u8], n: usize, k: usize) -> Vec<i32> {
    b[k * 4 * n..(k + 1) * 4 * n].chunks_exact(4).map(|c| i32::from_le_bytes(c.try_into().unwrap())).collect()
}

/// A compact velodyne_decoder reference frame (see tests/data/make_compact_refs.py).
pub struct VelodyneRef {
    pub xyz: Vec<[f64; 3]>,
    pub t_ns: Vec<i32>,
    pub ring: Vec<u8>,
    pub return_type: Vec<u8>,
}

pub fn velodyne_ref(rel: &str, n: usize) -> VelodyneRef {
    let b = xz(rel);
    assert_eq!(b.len(), n * 18, "{rel}");
    let (x, y, z, t) = (i32_col(&b, n, 0), i32_col(&b, n, 1), i32_col(&b, n, 2), i32_col(&b, n, 3));
    VelodyneRef {
        xyz: (0..n).map(|i| [x[i] as f64 * 1e-4, y[i] as f64 * 1e-4, z[i] as f64 * 1e-4]).collect(),
        t_ns: t,
        ring: b[16 * n..17 * n].to_vec(),
        return_type: b[17 * n..18 * n].to_vec(),
    }
}

/// A compact ouster-sdk reference frame: xyz of the valid pixels in staggered row-major order.
pub fn ouster_ref(rel: &str, n: usize) -> Vec<[f64; 3]> {
    let b = xz(rel);
    assert_eq!(b.len(), n * 12, "{rel}");
    let (x, y, z) = (i32_col(&b, n, 0), i32_col(&b, n, 1), i32_col(&b, n, 2));
    (0..n).map(|i| [x[i] as f64 * 1e-4, y[i] as f64 * 1e-4, z[i] as f64 * 1e-4]).collect()
}

/// A reference description file (`*.vref.json` / `*.oref.json`).
pub fn json(rel: &str) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(data(rel)).unwrap()).unwrap()
}

/// Angle between two vectors, radians.
pub fn angle(a: [f64; 3], b: [f64; 3]) -> f64 {
    let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let c = [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt().atan2(dot)
}

pub fn norm(a: [f64; 3]) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}
