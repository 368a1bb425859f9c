//! The pcap reader (global and record headers, link layers, IPv4 reassembly, UDP).
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_host::input::pcap::PcapReader;

fuzz_target!(|data: &[u8]| {
    let Ok(mut r) = PcapReader::from_bytes(data) else { return };
    let mut n = 0u64;
    while let Ok(Some(p)) = r.next_udp() {
        assert!(p.payload.len() <= 65_535);
        n += 1;
    }
    assert_eq!(r.stats.udp, n);
});
