//! Decoding throughput on one core, for real packet streams from tests/data:
//! - VLP-32C: 379 packets (tests/data/velodyne-nebula/vlp32c_nebula_1713492677), strongest return;
//!   real time is one packet per 663.552 us (1507.1 packets/s).
//! - OS1-128: 192 packets, RNG15_RFL8_NIR8, 1024x10 (tests/data/ouster-sdk/
//!   OS-1-128_v2.3.0_1024x10_lb_n3); real time is 640 packets/s.
//!
//! Each stream is measured three ways: `checksum` (a pass summing every byte: the memory-read
//! baseline of the same run), `decode` (checks + points), `decode+assemble` (the points placed in
//! scans by the assembler). Throughput is reported in packets; multiply by the points per packet
//! printed at start-up for points/s, divide by the real-time rate above for "x real time".

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use loglio_core::scan::ScanPoint;
use loglio_core::scan_assembly::{AssemblerConfig, ScanAssembler};
use loglio_core::sensor::{ouster, velodyne};
use std::hint::black_box;

fn fixture(rel: &str) -> Vec<u8> {
    let path = format!("{}/../tests/data/{rel}", env!("CARGO_MANIFEST_DIR"));
    let packed = std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let mut out = Vec::new();
    lzma_rs::xz_decompress(&mut &packed[..], &mut out).unwrap();
    out
}

/// UDP payloads to `port` of a classic little-endian Ethernet/IPv4 pcap without fragments.
fn udp(pcap: &[u8], port: u16) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let mut at = 24;
    while at + 16 <= pcap.len() {
        let incl = u32::from_le_bytes(pcap[at + 8..at + 12].try_into().unwrap()) as usize;
        let f = &pcap[at + 16..at + 16 + incl];
        at += 16 + incl;
        let ihl = (f[14] & 15) as usize * 4;
        let u = 14 + ihl;
        if f[23] == 17 && u16::from_be_bytes([f[u + 2], f[u + 3]]) == port {
            let len = u16::from_be_bytes([f[u + 4], f[u + 5]]) as usize;
            out.push(f[u + 8..u + len].to_vec());
        }
    }
    out
}

fn checksum(packets: &[Vec<u8>]) -> u64 {
    packets.iter().map(|p| p.iter().map(|&b| b as u64).sum::<u64>()).sum()
}

fn vlp32c(c: &mut Criterion) {
    let packets = udp(&fixture("velodyne-nebula/vlp32c_nebula_1713492677.pcap.xz"), 2368);
    let mut dec = velodyne::Decoder::new(velodyne::Config::new(velodyne::Model::Vlp32c)).unwrap();
    let mut n = 0u64;
    for p in &packets {
        let (pk, _) = dec.parse(p).unwrap();
        dec.points(&pk, |_| n += 1);
    }
    eprintln!(
        "VLP-32C: {} packets, {:.1} points/packet; real time 1507.1 packets/s",
        packets.len(),
        n as f64 / packets.len() as f64
    );
    let mut g = c.benchmark_group("vlp32c");
    g.throughput(Throughput::Elements(packets.len() as u64));
    g.bench_function("checksum", |b| b.iter(|| black_box(checksum(black_box(&packets)))));
    g.bench_function("decode", |b| {
        b.iter(|| {
            let mut acc = 0f32;
            for p in &packets {
                let (pk, _) = dec.parse(black_box(p)).unwrap();
                dec.points(&pk, |q| acc += q.xyz[0]);
            }
            black_box(acc)
        })
    });
    let (mut a, mut bb) = (vec![ScanPoint::default(); 60_000], vec![ScanPoint::default(); 60_000]);
    let mut asm = ScanAssembler::new(AssemblerConfig::cut_at_degrees(0.0), &mut a, &mut bb);
    let mut t = 0u64;
    g.bench_function("decode+assemble", |b| {
        b.iter(|| {
            for p in &packets {
                let (pk, repr) = dec.parse(black_box(p)).unwrap();
                t += 663_552;
                let meta = dec.meta(&repr, t);
                // Consecutive iterations replay the same packets: make the sequence continue.
                let meta = loglio_core::scan_assembly::PacketMeta {
                    seq: loglio_core::scan_assembly::PacketSeq { counter: t / 1000, modulus: 0, ..meta.seq },
                    ..meta
                };
                black_box(asm.push_packet(meta, |sink| dec.points(&pk, sink)).ok());
            }
        })
    });
    g.finish();
}

fn os1_128(c: &mut Criterion) {
    let pcap = fixture("ouster-sdk/OS-1-128_v2.3.0_1024x10_lb_n3.pcap.xz");
    let packets = udp(&pcap, 7502);
    let mut intr = ouster::OusterIntrinsics::new(ouster::Profile::LowBandwidth, 128, 1024, 10);
    // OS-1-128 angles are irrelevant to speed; a plausible spread.
    for u in 0..128 {
        intr.beam_altitude_deg[u] = 21.0 - u as f32 * 0.33;
        intr.beam_azimuth_deg[u] = [4.2, 1.4, -1.4, -4.2][u % 4];
        intr.pixel_shift_by_row[u] = [24, 16, 8, 0][u % 4];
    }
    intr.beam_origin_mm = [15.806, 0.0];
    let mut dec = ouster::Decoder::new(&intr).unwrap();
    let mut n = 0u64;
    for p in &packets {
        let (pk, _) = dec.parse(p).unwrap();
        dec.points(&pk, |_| n += 1);
    }
    eprintln!(
        "OS1-128: {} packets, {:.1} points/packet; real time 640 packets/s",
        packets.len(),
        n as f64 / packets.len() as f64
    );
    let mut g = c.benchmark_group("os1_128");
    g.throughput(Throughput::Elements(packets.len() as u64));
    g.bench_function("checksum", |b| b.iter(|| black_box(checksum(black_box(&packets)))));
    g.bench_function("decode", |b| {
        b.iter(|| {
            let mut acc = 0f32;
            for p in &packets {
                let (pk, _) = dec.parse(black_box(p)).unwrap();
                dec.points(&pk, |q| acc += q.xyz[0]);
            }
            black_box(acc)
        })
    });
    let (mut a, mut bb) = (vec![ScanPoint::default(); 140_000], vec![ScanPoint::default(); 140_000]);
    let mut asm = ScanAssembler::new(AssemblerConfig::cut_at_degrees(0.0), &mut a, &mut bb);
    let mut k = 0u64;
    g.bench_function("decode+assemble", |b| {
        b.iter(|| {
            for p in &packets {
                let (pk, repr) = dec.parse(black_box(p)).unwrap();
                k += 16;
                let meta = dec.meta(&repr, k / 16 * 1_562_500);
                let meta = loglio_core::scan_assembly::PacketMeta {
                    seq: loglio_core::scan_assembly::PacketSeq { counter: k, modulus: 0, ..meta.seq },
                    ..meta
                };
                black_box(asm.push_packet(meta, |sink| dec.points(&pk, sink)).ok());
            }
        })
    });
    g.finish();
}

criterion_group!(benches, vlp32c, os1_128);
criterion_main!(benches);
