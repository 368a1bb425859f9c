//! The Xsens MTData2 byte stream: `xsens::Decoder::feed` with chunk sizes taken from the input.
//! Every byte is either in a delivered message or counted as dropped (the candidate still in the
//! decoder's buffer at the end aside), and every sample is finite.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_core::sensor::xsens::{Decoder, MAX_MESSAGE, MtData2, parse_message};

fuzz_target!(|data: &[u8]| {
    let Some((&chunk, mut rest)) = data.split_first() else { return };
    let chunk = (chunk as usize % 64) + 1;
    // The message parser alone, on the raw input.
    if let Ok((m, n)) = parse_message(rest) {
        assert!(n <= rest.len() && n <= MAX_MESSAGE && m.data.len() < n);
        let _ = MtData2::parse(m.data);
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
