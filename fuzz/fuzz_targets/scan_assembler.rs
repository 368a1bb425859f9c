//! The scan assembler fed arbitrary packets: the input is cut into (8-byte time step, 1206-byte
//! Velodyne packet) records; every packet the decoder accepts goes to the assembler, whose
//! every delivered scan must hold in-capacity, finite points with t >= 0.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_core::scan::ScanPoint;
use loglio_core::scan_assembly::{AssemblerConfig, ScanAssembler};
use loglio_core::sensor::velodyne::{Config, Decoder, Model};

fuzz_target!(|data: &[u8]| {
    let Some((&sel, data)) = data.split_first() else { return };
    let mut dec =
        Decoder::new(Config::new([Model::Vlp16, Model::Vlp32c, Model::Hdl32e][sel as usize % 3])).unwrap();
    let mut cfg = AssemblerConfig::cut_at_degrees(sel as f32 * 1.5);
    cfg.reset_gap_packets = 1 + (sel as u32 >> 3);
    let (mut a, mut b) = ([ScanPoint::default(); 512], [ScanPoint::default(); 512]);
    let mut asm = ScanAssembler::new(cfg, &mut a, &mut b);
    let mut time = 0u64;
    for rec in data.chunks(8 + 1206) {
        if rec.len() < 8 {
            break;
        }
        time = time.wrapping_add(u64::from_le_bytes(rec[..8].try_into().unwrap()) >> 40);
        let mut packet = [0u8; 1206];
        let n = (rec.len() - 8).min(1206);
        packet[..n].copy_from_slice(&rec[8..8 + n]);
        // Give half the packets valid block flags so that they get past the checks.
        if rec[0] & 1 == 0 {
            for i in 0..12 {
                packet[i * 100] = 0xFF;
                packet[i * 100 + 1] = 0xEE;
                let az = u16::from_le_bytes([packet[i * 100 + 2], packet[i * 100 + 3]]) % 36_001;
                packet[i * 100 + 2..i * 100 + 4].copy_from_slice(&az.to_le_bytes());
            }
        }
        let Ok((p, repr)) = dec.parse(&packet) else { continue };
        let meta = dec.meta(&repr, time);
        if let Ok(Some(info)) = asm.push_packet(meta, |sink| dec.points(&p, sink)) {
            let scan = asm.scan();
            assert_eq!(scan.points.len(), info.points as usize);
            assert!(scan.points.len() <= 512);
            assert!(
                scan.points
                    .iter()
                    .all(|q| q.t >= 0.0 && q.t.is_finite() && q.xyz.iter().all(|v| v.is_finite()))
            );
        }
    }
    if let Some(info) = asm.flush() {
        assert_eq!(asm.scan().points.len(), info.points as usize);
    }
});
