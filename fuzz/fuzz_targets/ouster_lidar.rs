//! Ouster lidar packets: the first byte picks the profile and the shape (beams, columns per
//! packet), the rest is the packet; a packet of the right size is also made from the input by
//! padding, so the column and pixel code is reached.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_core::sensor::ouster::{Decoder, OusterIntrinsics, Profile};

fuzz_target!(|data: &[u8]| {
    let Some((&sel, packet)) = data.split_first() else { return };
    let profile = [
        Profile::Legacy,
        Profile::Single,
        Profile::Dual,
        Profile::LowBandwidth,
        Profile::FusaDualLowBandwidth,
    ][sel as usize % 5];
    let beams = [8u16, 16, 32, 64, 128][(sel as usize / 5) % 5];
    let cols = [512u16, 1024, 2048][(sel as usize / 25) % 3];
    let mut intr = OusterIntrinsics::new(profile, beams, cols, 10);
    intr.columns_per_packet = if sel & 0x80 != 0 { 4 } else { 16 };
    for u in 0..beams as usize {
        intr.beam_altitude_deg[u] = 20.0 - u as f32 * 0.3;
        intr.beam_azimuth_deg[u] = [4.2, 1.4, -1.4, -4.2][u % 4];
        intr.pixel_shift_by_row[u] = [12, 4, -4, -12][u % 4];
    }
    let mut dec = Decoder::new(&intr).unwrap();
    let want = intr.lidar_packet_bytes();
    let mut padded = packet.to_vec();
    padded.resize(want, 0);
    for bytes in [packet, &padded[..]] {
        if let Ok((p, repr)) = dec.parse(bytes) {
            let _ = dec.sequence(&repr);
            dec.points(&p, |q| {
                assert!(q.xyz.iter().all(|v| v.is_finite()));
                assert!(q.row < beams && q.col < cols);
            });
        }
    }
});
