//! Ouster IMU packets.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_core::sensor::ouster::ImuRepr;

fuzz_target!(|data: &[u8]| {
    if let Ok(r) = ImuRepr::parse(data) {
        if let Some(s) = r.sample(i64::from(data[0]) - 128) {
            assert!(s.acc.iter().chain(s.gyro.iter()).all(|v| v.is_finite()));
        }
    }
});
