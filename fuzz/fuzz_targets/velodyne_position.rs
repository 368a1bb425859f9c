//! Velodyne position packets and NMEA RMC sentences.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_core::sensor::velodyne_position::{Gprmc, PositionPacket, PositionRepr};

fuzz_target!(|data: &[u8]| {
    if let Ok(rmc) = Gprmc::parse(data) {
        let _ = rmc.unix_seconds();
        let _ = rmc.hour_start_ns();
    }
    if let Ok(p) = PositionPacket::new_checked(data) {
        let r = PositionRepr::parse(&p);
        if let Some(rmc) = r.rmc {
            assert!(rmc.hour < 24 && rmc.month >= 1 && rmc.month <= 12);
        }
    }
    // Also as the NMEA field of a full-size packet.
    let mut buf = [0u8; 512];
    let n = data.len().min(128);
    buf[206..206 + n].copy_from_slice(&data[..n]);
    let p = PositionPacket::new_checked(&buf[..]).unwrap();
    let _ = PositionRepr::parse(&p);
});
