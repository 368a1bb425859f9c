//! The text files a user hands loglio, followed as far as loglio takes them: Ouster sensor
//! metadata (JSON) into the Ouster decoder and its range-image layout; a Velodyne calibration
//! (the ROS drivers' YAML) into the Velodyne decoder and a layout of the input's column count;
//! each layout into a Ring FALS table; IMU CSV into samples. Any bytes: an error, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loglio_core::range_image::RangeImageLayout;
use loglio_core::ring_fals::{RingFalsConfig, RingTable};
use loglio_core::sensor::{ouster, velodyne};
use loglio_host::input::{imu_csv, ouster_meta, velodyne_calib};

fn table(layout: &RangeImageLayout) {
    let mut t = RingTable::new();
    if t.build(layout, &RingFalsConfig::DEFAULT).is_ok() {
        assert_eq!((t.rows(), t.cols()), (layout.rows(), layout.cols()));
    }
}

fuzz_target!(|data: &[u8]| {
    let Some((&sel, rest)) = data.split_first() else { return };
    match sel % 3 {
        0 => {
            if let Ok(s) = std::str::from_utf8(rest)
                && let Ok(meta) = ouster_meta::parse(s)
                && let Ok(dec) = ouster::Decoder::new(&meta.intrinsics)
            {
                table(dec.layout());
            }
        }
        1 => {
            let Ok(s) = std::str::from_utf8(rest) else { return };
            let Ok(calib) = velodyne_calib::parse(s) else { return };
            let cols = [8, 900, 1800, 2170, 3600, 3601, 0][usize::from(sel >> 2) % 7];
            if let Ok(layout) = calib.layout(cols) {
                table(&layout);
            }
            let model = [velodyne::Model::Vlp16, velodyne::Model::Vlp32c, velodyne::Model::Hdl32e]
                [usize::from(sel >> 5) % 3];
            if let Ok(dec) = velodyne::Decoder::with_calibration(velodyne::Config::new(model), calib) {
                table(dec.layout());
            }
        }
        _ => {
            if let Ok(samples) = imu_csv::parse(rest) {
                assert!(samples.iter().all(|s| s.is_finite()));
                assert!(samples.windows(2).all(|w| w[0].t_ns < w[1].t_ns));
            }
        }
    }
});
