//! Configuration files (TOML) as a user writes them: any text through `Config::from_toml_str`;
//! an accepted one on through what every command does next (the nominal layout, the core's
//! configuration, the storage class), and back out as the commented TOML `loglio config`
//! prints, which must read back to the same configuration.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_host::config::Config;
use loglio_host::run::engine::{StorageClass, odometry_config};

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let Ok(cfg) = Config::from_toml_str(text) else { return };
    let back = Config::from_toml_str(&cfg.to_commented_toml()).expect("printed configuration reads back");
    assert_eq!(back, cfg);
    let Ok(layout) = cfg.nominal_layout() else { return };
    let (rows, cols) = (layout.rows(), layout.cols());
    if let Ok(core) = odometry_config(&cfg, layout) {
        assert!(core.map.voxel_size.is_finite() && core.map.voxel_size > 0.0);
    }
    let _ = StorageClass::choose(rows, cols, cfg.mapping.map_capacity);
});
