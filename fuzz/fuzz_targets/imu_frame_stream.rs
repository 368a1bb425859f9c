//! The serial IMU frame stream: `FrameDecoder::feed` with chunk sizes taken from the input.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_core::sensor::imu_frame::FrameDecoder;

fuzz_target!(|data: &[u8]| {
    let Some((&chunk, mut rest)) = data.split_first() else { return };
    let chunk = (chunk as usize % 64) + 1;
    let mut dec = FrameDecoder::new();
    let mut frames = 0u64;
    while !rest.is_empty() {
        let n = chunk.min(rest.len());
        let mut c = &rest[..n];
        while !c.is_empty() {
            let (used, f) = dec.feed(c);
            assert!(used >= 1 && used <= c.len());
            if let Some(f) = f {
                assert!(f.gyro.iter().chain(f.acc.iter()).all(|v| v.is_finite()));
                frames += 1;
            }
            c = &c[used..];
        }
        rest = &rest[n..];
    }
    assert_eq!(dec.stats.frames, frames);
});
