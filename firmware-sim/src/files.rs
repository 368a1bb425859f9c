//! File mode: a scenario written to a directory.
//!
//! | file | content |
//! |---|---|
//! | `lidar.pcap` | every LiDAR UDP datagram (Ethernet/IPv4/UDP, classic libpcap, us timestamps) |
//! | `imu.bin` | the IMU board's raw serial bytes (loglio IMU frames) |
//! | `imu.csv` | `t,gx,gy,gz,ax,ay,az`: Unix seconds, rad/s, m/s^2 (the frames' values) |
//! | `groundtruth.tum` | the IMU frame's exact pose at every IMU sample (TUM) |
//! | `lidar_groundtruth.tum` | the LiDAR frame's exact pose at the same times |
//! | `scenario.json` | what was simulated: scenario, seed, sensor, extrinsic, IMU figures |
//! | `ouster_metadata.json` | (Ouster only) the sensor metadata a decoder needs |
//! | `actors.csv` | (scenarios with moving actors: `traffic`) every actor's box at 10 Hz |
//!
//! The same configuration always writes the same bytes.

use std::fmt::Write as _;
use std::io::{BufWriter, Write};
use std::path::Path;

use loglio_core::sensor::imu_frame::ImuFrame;
use serde_json::json;

use crate::lidar::ouster::{self, Ouster};
use crate::lidar::scanner::Firmware;
use crate::lidar::velodyne;
use crate::pcap_out::{Endpoint, PcapWriter};
use crate::scenario::{LidarConfig, Scenario, ScenarioKind};
use crate::stream::{Wire, WireStream, decode_serial};
use crate::tum;

/// What file mode wrote.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Summary {
    /// UDP datagrams in the pcap.
    pub datagrams: u64,
    /// IMU frames.
    pub imu_frames: u64,
    /// Bytes of the serial dump.
    pub serial_bytes: u64,
}

/// Writes every output of `sc` into `dir` (created if needed).
pub fn write_all(sc: &Scenario, dir: &Path) -> anyhow::Result<Summary> {
    std::fs::create_dir_all(dir)?;
    let ep = endpoint(sc);
    let mut pcap = PcapWriter::new(BufWriter::new(std::fs::File::create(dir.join("lidar.pcap"))?))?;
    let mut serial = Vec::new();
    let mut sum = Summary::default();
    for ev in WireStream::new(sc) {
        match ev.wire {
            Wire::Udp { port, payload } => {
                pcap.write_udp(ev.t_ns, &ep, port, port, &payload)?;
                sum.datagrams += 1;
            }
            Wire::Serial(bytes) => serial.extend_from_slice(&bytes),
        }
    }
    pcap.finish()?;
    std::fs::write(dir.join("imu.bin"), &serial)?;
    sum.serial_bytes = serial.len() as u64;
    let frames = decode_serial(&serial);
    sum.imu_frames = frames.len() as u64;
    std::fs::write(dir.join("imu.csv"), imu_csv(&frames))?;
    let times: Vec<u64> = frames.iter().map(|f| f.t_ns).collect();
    write_truth_and_meta(sc, &times, dir)?;
    if !sc.actors().is_empty() {
        sc.write_actors_csv(&dir.join("actors.csv"), 10.0)?;
    }
    Ok(sum)
}

/// The network address the scenario's sensor sends from.
pub fn endpoint(sc: &Scenario) -> Endpoint {
    if sc.config().lidar.model().is_velodyne() { Endpoint::VELODYNE } else { Endpoint::OUSTER }
}

/// The `imu.csv` text of `frames` (a non-finite value is written `nan` or `inf`).
pub fn imu_csv(frames: &[ImuFrame]) -> String {
    let num = |v: f32| if v.is_nan() { "nan".to_string() } else { format!("{v:e}") };
    let mut csv = String::from("t,gx,gy,gz,ax,ay,az\n");
    for f in frames {
        let _ = writeln!(
            csv,
            "{}.{:09},{},{},{},{},{},{}",
            f.t_ns / 1_000_000_000,
            f.t_ns % 1_000_000_000,
            num(f.gyro[0]),
            num(f.gyro[1]),
            num(f.gyro[2]),
            num(f.acc[0]),
            num(f.acc[1]),
            num(f.acc[2])
        );
    }
    csv
}

/// Writes the ground truth at `times` (`groundtruth.tum`, `lidar_groundtruth.tum`),
/// `scenario.json` and, for an Ouster, `ouster_metadata.json`.
pub fn write_truth_and_meta(sc: &Scenario, times: &[u64], dir: &Path) -> anyhow::Result<()> {
    std::fs::write(dir.join("groundtruth.tum"), tum::trajectory(times.iter().copied(), |t| sc.pose_at(t)))?;
    std::fs::write(
        dir.join("lidar_groundtruth.tum"),
        tum::trajectory(times.iter().copied(), |t| sc.lidar_pose_at(t)),
    )?;
    let mut f = BufWriter::new(std::fs::File::create(dir.join("scenario.json"))?);
    serde_json::to_writer_pretty(&mut f, &scenario_json(sc))?;
    f.flush()?;
    if let Firmware::Ouster(o) = sc.firmware() {
        let mut f = BufWriter::new(std::fs::File::create(dir.join("ouster_metadata.json"))?);
        serde_json::to_writer_pretty(&mut f, &ouster_metadata(o))?;
        f.flush()?;
    }
    Ok(())
}

/// A description of the scenario for the host and for people.
pub fn scenario_json(sc: &Scenario) -> serde_json::Value {
    let c = sc.config();
    let e = c.extrinsic;
    let q = e.rotation.coords;
    let n = c.imu_noise;
    let lidar = match &c.lidar {
        LidarConfig::Velodyne(v) => json!({
            "vendor": "velodyne",
            "model": v.model.name(),
            "rpm": v.rpm,
            "return_mode": format!("{:?}", v.return_mode).to_lowercase(),
            "data_port": velodyne::DATA_PORT,
            "position_port": velodyne::POSITION_PORT,
            "range_sigma_m": v.range.sigma,
            "max_range_m": v.range.max_range,
        }),
        LidarConfig::Ouster(o) => json!({
            "vendor": "ouster",
            "model": o.model.name(),
            "lidar_mode": o.mode.name(),
            "udp_profile_lidar": o.profile.name(),
            "lidar_port": ouster::LIDAR_PORT,
            "imu_port": ouster::IMU_PORT,
            "range_sigma_m": o.range.sigma,
            "max_range_m": o.range.max_range,
        }),
    };
    let mut v = json!({
        "scenario": c.kind.name(),
        "seed": c.seed,
        "duration_s": c.duration_s,
        "start_unix_ns": c.start_unix_ns,
        "world_frame": "gravity-aligned, z up; ground truth is the IMU frame (x forward, y left, z up)",
        "gravity_m_s2": crate::trajectory::GRAVITY,
        "lidar": lidar,
        "extrinsic_imu_lidar": {
            "comment": "pose of the LiDAR frame in the IMU frame: p_imu = R p_lidar + t",
            "translation_m": [e.translation.x, e.translation.y, e.translation.z],
            "quaternion_xyzw": [q[0], q[1], q[2], q[3]],
        },
        "imu": {
            "chip": "TDK InvenSense ICM-42688-P (simulated)",
            "rate_hz": c.imu_board.odr.hz(),
            "gyro_full_scale": format!("{:?}", c.imu_board.gyro_fs),
            "accel_full_scale": format!("{:?}", c.imu_board.accel_fs),
            "gyro_noise_density_rad_s_sqrt_hz": n.density.gyro,
            "accel_noise_density_m_s2_sqrt_hz": n.density.acc,
            "gyro_bias_random_walk_rad_s2_sqrt_hz": n.density.gyro_bias_walk,
            "accel_bias_random_walk_m_s3_sqrt_hz": n.density.acc_bias_walk,
            "serial_frame": "loglio_core::sensor::imu_frame (postcard + CRC-32 + COBS)",
        },
    });
    if c.kind == ScenarioKind::Traffic {
        // Only here: the static scenarios' descriptions stay as they were.
        v["actors"] = json!({
            "count": sc.actors().list().len(),
            "ground_truth": if sc.actors().is_empty() { "none (--no-actors)" } else { "actors.csv" },
        });
    }
    v
}

/// Ouster sensor metadata (firmware 2.x style, flat keys) describing the simulated unit.
pub fn ouster_metadata(o: &Ouster) -> serde_json::Value {
    let c = o.config();
    let w = o.columns();
    let h = o.beams();
    let alt: Vec<f64> = (0..h).map(|b| o.altitude_deg(b)).collect();
    let az: Vec<f64> = (0..h).map(|b| o.azimuth_deg(b)).collect();
    let min_az = az.iter().cloned().fold(f64::INFINITY, f64::min);
    let shift: Vec<i64> = az.iter().map(|a| libm::round((a - min_az) * w as f64 / 360.0) as i64).collect();
    let i = ouster::IMU_IN_SENSOR;
    json!({
        "prod_line": match c.model {
            crate::lidar::SensorModel::Os1_16 => "OS-1-16",
            crate::lidar::SensorModel::Os1_128 => "OS-1-128",
            _ => "OS-1-64",
        },
        "prod_sn": c.serial.to_string(),
        "build_rev": "v2.3.0",
        "status": "RUNNING",
        "initialization_id": c.init_id,
        "json_calibration_version": 4,
        "lidar_mode": c.mode.name(),
        "beam_altitude_angles": alt,
        "beam_azimuth_angles": az,
        "lidar_origin_to_beam_origin_mm": ouster::BEAM_ORIGIN_M * 1000.0,
        "lidar_to_sensor_transform": [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, ouster::LIDAR_TO_SENSOR_Z * 1000.0, 0, 0, 0, 1],
        "imu_to_sensor_transform": [1, 0, 0, i[0] * 1000.0, 0, 1, 0, i[1] * 1000.0, 0, 0, 1, i[2] * 1000.0, 0, 0, 0, 1],
        "data_format": {
            "pixels_per_column": h,
            "columns_per_packet": ouster::COLUMNS_PER_PACKET,
            "columns_per_frame": w,
            "column_window": [0, w - 1],
            "pixel_shift_by_row": shift,
            "udp_profile_lidar": c.profile.name(),
            "udp_profile_imu": "LEGACY",
        },
        "udp_port_lidar": ouster::LIDAR_PORT,
        "udp_port_imu": ouster::IMU_PORT,
    })
}
