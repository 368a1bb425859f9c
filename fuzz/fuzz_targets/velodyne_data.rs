//! Velodyne data packets: the first byte picks the model, the rest is the packet (any length).
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_core::sensor::velodyne::{Config, Decoder, Model};

fuzz_target!(|data: &[u8]| {
    let Some((&sel, packet)) = data.split_first() else { return };
    let model = [Model::Vlp16, Model::Vlp32c, Model::Hdl32e][sel as usize % 3];
    let mut cfg = Config::new(model);
    cfg.columns = 8 + (sel as u16 >> 2) * 14;
    let mut dec = Decoder::new(cfg).unwrap();
    let cols = dec.layout().cols() as u16;
    if let Ok((p, repr)) = dec.parse(packet) {
        let _ = dec.sequence(&repr);
        dec.points(&p, |q| {
            assert!(q.xyz.iter().all(|v| v.is_finite()));
            assert!((q.row as usize) < model.lasers());
            assert!(q.col < cols);
            assert!(q.ret <= 1);
        });
    }
});
