//! The VectorNav binary output byte stream: `vectornav::Decoder::feed` with chunk sizes taken
//! from the input; every sample is finite.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_core::sensor::vectornav::{Decoder, MAX_MESSAGE, crc16, parse_message};

fuzz_target!(|data: &[u8]| {
    let Some((&chunk, mut rest)) = data.split_first() else { return };
    let chunk = (chunk as usize % 64) + 1;
    // The message parser alone, on the raw input: an accepted message checks to CRC 0.
    if let Ok((o, n)) = parse_message(rest) {
        assert!(n <= rest.len() && n <= MAX_MESSAGE);
        assert_eq!(crc16(&rest[1..n]), 0);
        assert!(o.gyro.into_iter().flatten().chain(o.acc.into_iter().flatten()).all(|v| v.is_finite()));
    }
    let mut dec = Decoder::new();
    let mut samples = 0u64;
    while !rest.is_empty() {
        let n = chunk.min(rest.len());
        let mut c = &rest[..n];
        loop {
            let (used, s) = dec.feed(c);
            assert!(used <= c.len());
            c = &c[used..];
            match s {
                Some(s) => {
                    assert!(s.gyro.iter().chain(s.acc.iter()).all(|v| v.is_finite()));
                    samples += 1;
                }
                None => {
                    assert!(c.is_empty(), "no sample and bytes left unconsumed");
                    break;
                }
            }
        }
        rest = &rest[n..];
    }
    assert_eq!(dec.stats.samples, samples);
    assert!(dec.stats.dropped_bytes <= data.len() as u64);
});
