//! Scenario-level tests of the simulator (loglio-firmware-sim): determinism of every output,
//! packets against an independent decoder written from the vendors' formulas, direct scans
//! against the world, the IMU against strapdown integration, and live mode end to end.

use std::collections::HashMap;
use std::path::PathBuf;

use loglio_core::range_image::RangeImageLayout;
use loglio_firmware_sim::imu_chip::ChipNoise;
use loglio_firmware_sim::lidar::SensorModel;
use loglio_firmware_sim::lidar::ouster::{self, LidarMode, Profile};
use loglio_firmware_sim::lidar::scanner::Firmware;
use loglio_firmware_sim::lidar::velodyne;
use loglio_firmware_sim::raycast::{Ray, Shape};
use loglio_firmware_sim::scenario::{Event, LidarConfig, Scenario, ScenarioConfig, ScenarioKind};
use loglio_firmware_sim::stream::{Wire, WireStream, decode_serial, ouster_packet, velodyne_packet};
use loglio_firmware_sim::trajectory::{GRAVITY, Kinematics, Trajectory};
use loglio_firmware_sim::{files, tum};
use nalgebra::{Point3, UnitQuaternion, Vector3};

fn short(kind: ScenarioKind, sensor: SensorModel, seed: u64, secs: f64) -> Scenario {
    let mut c = ScenarioConfig::new(kind, sensor, seed);
    c.duration_s = secs;
    Scenario::from_config(c).unwrap()
}

fn tmp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("loglio-sim-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn read_all(dir: &std::path::Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .map(|p| (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read(&p).unwrap()))
        .collect();
    v.sort();
    v
}

#[test]
fn same_seed_same_bytes_different_seed_different_bytes() {
    for sensor in [SensorModel::Vlp16, SensorModel::Os1_16] {
        let outs: Vec<_> = [(11, "a"), (11, "b"), (12, "c")]
            .iter()
            .map(|(seed, tag)| {
                let dir = tmp_dir(&format!("{}-{tag}", sensor.name()));
                let sc = short(ScenarioKind::Vehicle, sensor, *seed, 1.2);
                let sum = files::write_all(&sc, &dir).unwrap();
                assert!(sum.datagrams > 100 && sum.imu_frames == 240, "{sum:?}");
                let files = read_all(&dir);
                std::fs::remove_dir_all(&dir).unwrap();
                files
            })
            .collect();
        let names: Vec<&str> = outs[0].iter().map(|(n, _)| n.as_str()).collect();
        for want in ["groundtruth.tum", "imu.bin", "imu.csv", "lidar.pcap", "scenario.json"] {
            assert!(names.contains(&want), "{names:?}");
        }
        assert_eq!(outs[0], outs[1], "{sensor:?}: same seed must give identical bytes");
        for ((n, a), (_, c)) in outs[0].iter().zip(&outs[2]) {
            if n.ends_with(".pcap") || n == "imu.bin" || n == "imu.csv" {
                assert_ne!(a, c, "{sensor:?}: {n} must change with the seed");
            }
        }
    }
}

/// VLP-32C elevations, degrees (manual table 9-6).
const VLP32C_EL: [f64; 32] = [
    -25., -1., -1.667, -15.639, -11.31, 0., -0.667, -8.843, -7.254, 0.333, -0.333, -6.148, -5.333, 1.333,
    0.667, -4., -4.667, 1.667, 1., -3.667, -3.333, 3.333, 2.333, -2.667, -3., 7., 4.667, -2.333, -2., 15.,
    10.333, -1.333,
];

/// Velodyne data points decoded with the user manuals' formulas: block azimuth plus the
/// precision-azimuth interpolation by firing time, the laser's azimuth offset, elevation and
/// vertical offset, and the timing table. Returns (t_ns, laser, xyz).
fn decode_velodyne(model: SensorModel, pkt: &[u8], next_block_az: Option<u16>) -> Vec<(u64, u8, [f64; 3])> {
    let (el, azoff, vert, unit): (Vec<f64>, Vec<f64>, Vec<f64>, f64) = match model {
        SensorModel::Vlp16 => (
            vec![-15., 1., -13., 3., -11., 5., -9., 7., -7., 9., -5., 11., -3., 13., -1., 15.],
            vec![0.0; 16],
            vec![11.2, -0.7, 9.7, -2.2, 8.1, -3.7, 6.6, -5.1, 5.1, -6.6, 3.7, -8.1, 2.2, -9.7, 0.7, -11.2],
            0.002,
        ),
        SensorModel::Vlp32c => (
            VLP32C_EL.to_vec(),
            vec![
                1.4, -4.2, 1.4, -1.4, 1.4, -1.4, 4.2, -1.4, 1.4, -4.2, 1.4, -1.4, 4.2, -1.4, 4.2, -1.4, 1.4,
                -4.2, 1.4, -4.2, 4.2, -1.4, 1.4, -1.4, 1.4, -1.4, 1.4, -4.2, 4.2, -1.4, 1.4, -1.4,
            ],
            // Beam origins 42.4 mm x tan(-elevation) above the sensor origin (the focal distance;
            // the built-in tables round these to 1 um, well inside the tolerance below).
            VLP32C_EL.iter().map(|e| 42.4 * (-e).to_radians().tan()).collect(),
            0.004,
        ),
        _ => unreachable!(),
    };
    assert_eq!(pkt.len(), 1206);
    let ts = u32::from_le_bytes(pkt[1200..1204].try_into().unwrap()) as u64;
    let az = |b: usize| u16::from_le_bytes([pkt[b * 100 + 2], pkt[b * 100 + 3]]) as f64 / 100.0;
    let mut out = Vec::new();
    for b in 0..12 {
        // Azimuth change per block, from the next block (or the previous one for the last).
        let next = if b < 11 {
            az(b + 1)
        } else {
            next_block_az.map(|a| a as f64 / 100.0).unwrap_or(2.0 * az(11) - az(10))
        };
        let gap = (next - az(b)).rem_euclid(360.0);
        for ch in 0..32 {
            let p = b * 100 + 4 + ch * 3;
            let raw = u16::from_le_bytes([pkt[p], pkt[p + 1]]);
            if raw == 0 {
                continue;
            }
            let (laser, t_off_us, frac) = match model {
                SensorModel::Vlp16 => {
                    let (seq, l) = (ch / 16, ch % 16);
                    let off = 55.296 * (2 * b + seq) as f64 + 2.304 * l as f64;
                    (l, off, (55.296 * seq as f64 + 2.304 * l as f64) / (2.0 * 55.296))
                }
                _ => {
                    let off = 55.296 * b as f64 + 2.304 * (ch / 2) as f64;
                    (ch, off, 2.304 * (ch / 2) as f64 / 55.296)
                }
            };
            let a = (az(b) + gap * frac + azoff[laser]).to_radians();
            let w = el[laser].to_radians();
            let r = raw as f64 * unit;
            let xyz = [r * w.cos() * a.cos(), -r * w.cos() * a.sin(), r * w.sin() + vert[laser] * 1e-3];
            out.push(((ts as f64 * 1000.0 + t_off_us * 1000.0).round() as u64, laser as u8, xyz));
        }
    }
    out
}

#[test]
fn velodyne_packets_decode_to_their_truth_and_match_direct_scans() {
    for sensor in [SensorModel::Vlp16, SensorModel::Vlp32c] {
        let sc = short(ScenarioKind::Vehicle, sensor, 3, 3.0);
        let Firmware::Velodyne(v) = sc.firmware() else { unreachable!() };
        let mut src = sc.echo_source();
        // Packets around t = 2.5 s (moving): decode every one and compare with its truth.
        let k0 = (2.5e9 / v.packet_time_ns(1).saturating_sub(v.packet_time_ns(0)) as f64) as u64;
        let mut by_firing: HashMap<(u64, u8), [f64; 3]> = HashMap::new();
        let mut worst: f64 = 0.0;
        for k in k0..k0 + 80 {
            let (pkt, truth) = velodyne_packet(v, k, &mut src);
            let (next, _) = velodyne_packet(v, k + 1, &mut sc.echo_source());
            let next_az = u16::from_le_bytes([next[2], next[3]]);
            let dec = decode_velodyne(sensor, &pkt, Some(next_az));
            assert_eq!(dec.len(), truth.len());
            let hour_base = v.packet_time_ns(k) / 3_600_000_000_000 * 3_600_000_000_000;
            for (d, t) in dec.iter().zip(&truth) {
                assert_eq!(d.1, t.laser);
                // Timing table: within the 1 us resolution of the packet timestamp.
                let t_dec = hour_base + d.0;
                assert!(t.t_ns.abs_diff(t_dec) < 1_000, "{} vs {}", t.t_ns, t_dec);
                let r = (t.xyz[0].powi(2) + t.xyz[1].powi(2) + t.xyz[2].powi(2)).sqrt();
                let e =
                    ((d.2[0] - t.xyz[0]).powi(2) + (d.2[1] - t.xyz[1]).powi(2) + (d.2[2] - t.xyz[2]).powi(2))
                        .sqrt();
                // Resolution: the 0.01 degree azimuth of the blocks (interpolation adds nothing
                // at a constant spin), i.e. r * 0.01 deg, plus rounding.
                assert!(e <= r * 0.0101f64.to_radians() + 1e-6, "{sensor:?} error {e} at range {r}");
                worst = worst.max(e / r);
                by_firing.insert((t.t_ns, t.laser), t.xyz);
            }
        }
        assert!(worst > 0.0);
        // The direct scan of the same revolution carries the same points (f32).
        let j = (v.packet_time_ns(k0 + 10) - sc.start_ns()) / 100_000_000;
        let scan = sc.scan(j);
        let rows = loglio_firmware_sim::lidar::scanner::velodyne_rows(v);
        let mut matched = 0;
        for p in &scan.points {
            let t_ns = scan.start_ns + (p.t as f64 * 1e9).round() as u64;
            let laser = rows.iter().position(|&r| r == p.row).unwrap() as u8;
            // Firing times are exact ns; p.t is f32 seconds (< 10 ns error over 0.1 s).
            let hit = (t_ns.saturating_sub(16)..t_ns + 16).find_map(|t| by_firing.get(&(t, laser)));
            if let Some(xyz) = hit {
                for i in 0..3 {
                    assert!((p.xyz[i] as f64 - xyz[i]).abs() < 2e-5, "{sensor:?} {:?} vs {xyz:?}", p.xyz);
                }
                matched += 1;
            }
        }
        assert!(matched > 5_000, "{sensor:?}: only {matched} direct points matched packet truth");
    }
}

#[test]
fn ouster_packets_decode_to_their_truth() {
    for (sensor, profile) in
        [(SensorModel::Os1_64, Profile::Legacy), (SensorModel::Os1_16, Profile::Rng19Rfl8Sig16Nir16)]
    {
        let mut c = ScenarioConfig::new(ScenarioKind::Handheld, sensor, 5);
        c.duration_s = 3.0;
        if let LidarConfig::Ouster(o) = &mut c.lidar {
            o.profile = profile;
            o.mode = LidarMode::M1024x10;
        }
        let sc = Scenario::from_config(c).unwrap();
        let Firmware::Ouster(o) = sc.firmware() else { unreachable!() };
        let mut src = sc.echo_source();
        let legacy = profile == Profile::Legacy;
        let h = o.beams();
        let mut n = 0;
        for k in 1600..1664 {
            let (pkt, truth) = ouster_packet(o, k, &mut src);
            assert_eq!(pkt.len(), o.packet_len());
            let (col_len, mut off, px0) =
                if legacy { (16 + 12 * h + 4, 0, 16) } else { (12 + 12 * h, 32, 12) };
            let mut ti = 0;
            for _ in 0..16 {
                let col = &pkt[off..off + col_len];
                let m = u16::from_le_bytes([col[8], col[9]]) as f64;
                for b in 0..h {
                    let px = &col[px0 + 12 * b..];
                    let mask = if legacy { 0xF_FFFF } else { 0x7_FFFF };
                    let r_mm = u32::from_le_bytes(px[0..4].try_into().unwrap()) & mask;
                    if r_mm == 0 {
                        continue;
                    }
                    // Ouster's documented xyz formula, then the lidar-to-sensor transform.
                    let te = std::f64::consts::TAU * (1.0 - m / 1024.0);
                    let ta = -o.azimuth_deg(b).to_radians();
                    let ph = o.altitude_deg(b).to_radians();
                    let (r, nn) = (r_mm as f64 * 1e-3, ouster::BEAM_ORIGIN_M);
                    let x = (r - nn) * (te + ta).cos() * ph.cos() + nn * te.cos();
                    let y = (r - nn) * (te + ta).sin() * ph.cos() + nn * te.sin();
                    let z = (r - nn) * ph.sin();
                    let p = [-x, -y, z + ouster::LIDAR_TO_SENSOR_Z];
                    let t = truth[ti];
                    ti += 1;
                    let e = (0..3).map(|i| (p[i] - t.xyz[i]).powi(2)).sum::<f64>().sqrt();
                    assert!(e < 1e-9, "{sensor:?} {e}");
                    let ex = (0..3).map(|i| (p[i] - t.xyz_exact[i]).powi(2)).sum::<f64>().sqrt();
                    assert!(ex <= 0.0005 + 1e-9, "quantisation {ex}");
                    n += 1;
                }
                off += col_len;
            }
            assert_eq!(ti, truth.len());
        }
        assert!(n > 16 * 64 * h / 2, "{n}");
    }
}

/// Checks that the points of a direct scan, put in the world with the LiDAR's true pose at
/// their firing times, lie on the surfaces that noise-free rays find there. Rays grazing an
/// edge may switch surface with the tiny direction change of noise and beam offsets, so up to
/// 1 % may miss; the median error must be at the noise level.
fn points_lie_on_the_world(sc: &Scenario, j: u64, max_err: f64) -> usize {
    let scan = sc.scan(j);
    let scene = &sc.world().scene;
    let mut checked = 0;
    let mut errs = Vec::new();
    for (i, p) in scan.points.iter().enumerate().step_by(7) {
        let t_ns = scan.start_ns + (p.t as f64 * 1e9).round() as u64;
        let pose = sc.lidar_pose_at(t_ns);
        let w = pose * Point3::new(p.xyz[0] as f64, p.xyz[1] as f64, p.xyz[2] as f64);
        let o = pose.translation.vector;
        let d = (w.coords - o).normalize();
        let Some(h) = scene.cast(&Ray { o: [o.x, o.y, o.z], d: [d.x, d.y, d.z] }, 300.0, i as u64).hit else {
            continue;
        };
        let r = (w.coords - o).norm();
        // Crowns are porous and their leaves are drawn per firing: skip rays through crowns.
        let ray = Ray { o: [o.x, o.y, o.z], d: [d.x, d.y, d.z] };
        let through_crown = scene.prims().iter().any(|p| match p.shape {
            Shape::Crown { c, r: cr, .. } => {
                loglio_firmware_sim::raycast::ray_sphere(&ray, c, cr).is_some_and(|(a, _)| a < h.t + 0.1)
            }
            _ => false,
        });
        if through_crown {
            continue;
        }
        errs.push((h.t - r).abs());
        checked += 1;
    }
    errs.sort_by(f64::total_cmp);
    let bad = errs.iter().filter(|&&e| e > max_err).count();
    assert!(bad * 100 <= errs.len(), "scan {j}: {bad} of {} points off the surfaces", errs.len());
    assert!(errs[errs.len() / 2] < 0.02, "scan {j}: median error {}", errs[errs.len() / 2]);
    checked
}

#[test]
fn direct_scans_are_motion_distorted_like_the_real_sensor() {
    // Range noise 1.2 cm (5 sigma = 6 cm) plus the VLP-16 beam offsets and quantisation; a
    // scan put in the world with one pose per scan instead of per firing misses by metres.
    let sc = short(ScenarioKind::Vehicle, SensorModel::Vlp16, 9, 4.0);
    assert!(points_lie_on_the_world(&sc, 30, 0.08) > 1_500);
    let sc = short(ScenarioKind::FastRotation, SensorModel::Os1_64, 9, 4.0);
    assert!(points_lie_on_the_world(&sc, 35, 0.08) > 1_500);
    // Counter-check: the same points with the scan-start pose for all are far off somewhere.
    let scan = sc.scan(35);
    let pose0 = sc.lidar_pose_at(scan.start_ns);
    let last = scan.points.last().unwrap();
    let t_last = scan.start_ns + (last.t as f64 * 1e9) as u64;
    let p = Point3::new(last.xyz[0] as f64, last.xyz[1] as f64, last.xyz[2] as f64);
    assert!((pose0 * p - sc.lidar_pose_at(t_last) * p).norm() > 0.1);
}

#[test]
fn scan_rows_and_columns_follow_the_layout() {
    for sensor in SensorModel::ALL {
        let sc = short(ScenarioKind::Handheld, sensor, 2, 1.0);
        let layout: &RangeImageLayout = sc.layout();
        let scan = sc.scan(3);
        assert!(!scan.points.is_empty());
        let step = std::f64::consts::TAU / layout.cols() as f64;
        for p in scan.points.iter().step_by(13) {
            let (row, col) = (p.row as usize, p.col as usize);
            assert!(row < layout.rows() && col < layout.cols());
            let d = layout.direction(row, col);
            let n = (p.xyz[0] as f64).hypot(p.xyz[1] as f64);
            let az_p = (p.xyz[1] as f64).atan2(p.xyz[0] as f64);
            let az_l = d[1].atan2(d[0]);
            let daz =
                (az_p - az_l + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
            // Half a column, plus for Ouster the 15.8 mm beam-origin offset seen from the point.
            let slack =
                if sensor.is_velodyne() { 0.5 * step + 1e-4 } else { 0.5 * step + 0.017 / n.max(0.3) };
            assert!(daz.abs() <= slack, "{sensor:?} row {row} col {col}: {daz}");
            let el_p = (p.xyz[2] as f64 - if sensor.is_velodyne() { 0.0 } else { ouster::LIDAR_TO_SENSOR_Z })
                .atan2(n);
            assert!(
                (el_p - layout.elevation(row) as f64).abs() < 0.02 + 0.012 / n.max(0.3),
                "{sensor:?} row {row}"
            );
        }
        // Rows are ordered by elevation, highest first.
        for r in 1..layout.rows() {
            assert!(layout.elevation(r) < layout.elevation(r - 1));
        }
    }
}

/// Strapdown integration (RK4 on attitude, velocity and position) of angular rate and specific
/// force given as functions of time.
fn strapdown(
    k0: &Kinematics,
    t1: f64,
    h: f64,
    imu: impl Fn(f64) -> (Vector3<f64>, Vector3<f64>),
) -> (UnitQuaternion<f64>, Vector3<f64>, Vector3<f64>) {
    let g = Vector3::new(0.0, 0.0, -GRAVITY);
    let mut q = UnitQuaternion::from_rotation_matrix(&k0.rotation);
    let (mut v, mut p) = (k0.velocity, k0.position);
    let t0 = k0.t;
    let deriv = |q: &nalgebra::Quaternion<f64>, v: &Vector3<f64>, t: f64| {
        let (w, f) = imu(t);
        let qd = q * nalgebra::Quaternion::from_parts(0.0, w) * 0.5;
        let r = UnitQuaternion::new_normalize(*q);
        (qd, r * f + g, *v)
    };
    let steps = ((t1 - t0) / h).round() as u64;
    for k in 0..steps {
        let t = t0 + k as f64 * h;
        let q0 = *q.quaternion();
        let (k1q, k1v, k1p) = deriv(&q0, &v, t);
        let (k2q, k2v, k2p) = deriv(&(q0 + k1q * (h / 2.0)), &(v + k1v * (h / 2.0)), t + h / 2.0);
        let (k3q, k3v, k3p) = deriv(&(q0 + k2q * (h / 2.0)), &(v + k2v * (h / 2.0)), t + h / 2.0);
        let (k4q, k4v, k4p) = deriv(&(q0 + k3q * h), &(v + k3v * h), t + h);
        q = UnitQuaternion::new_normalize(q0 + (k1q + k2q * 2.0 + k3q * 2.0 + k4q) * (h / 6.0));
        p += (k1p + k2p * 2.0 + k3p * 2.0 + k4p) * (h / 6.0);
        v += (k1v + k2v * 2.0 + k3v * 2.0 + k4v) * (h / 6.0);
    }
    (q, v, p)
}

#[test]
fn noise_free_imu_integrates_back_to_the_trajectory() {
    for traj in [
        Trajectory::Vehicle { terrain: loglio_firmware_sim::terrain::Terrain::town() },
        Trajectory::Handheld,
        Trajectory::Corridor,
        Trajectory::Drone { ground_z: 0.7 },
        Trajectory::FastRotation,
    ] {
        // 400 Hz samples (RK4 steps of 5 ms use the 2.5 ms midpoints) over 30 s.
        let k0 = traj.eval(0.0);
        let (q, v, p) = strapdown(&k0, 30.0, 0.005, |t| {
            let k = traj.eval(t);
            (k.angular_velocity, k.specific_force())
        });
        let k1 = traj.eval(30.0);
        let path: f64 = (0..3000)
            .map(|i| (traj.eval(0.01 * (i + 1) as f64).position - traj.eval(0.01 * i as f64).position).norm())
            .sum();
        let ep = (p - k1.position).norm();
        let ev = (v - k1.velocity).norm();
        let eq = q.angle_to(&UnitQuaternion::from_rotation_matrix(&k1.rotation));
        assert!(ep < 1e-6 * path.max(1.0), "{traj:?}: position error {ep} over {path} m");
        assert!(ev < 1e-6 * 10.0, "{traj:?}: velocity error {ev}");
        assert!(eq < 1e-7, "{traj:?}: attitude error {eq}");
    }
}

/// The board's samples of a vehicle scenario as a zero-order-hold function of time.
fn held_samples(
    seed: u64,
    noise: ChipNoise,
    t_end: f64,
) -> (Scenario, impl Fn(f64) -> (Vector3<f64>, Vector3<f64>)) {
    let mut c = ScenarioConfig::new(ScenarioKind::Vehicle, SensorModel::Vlp16, seed);
    c.duration_s = t_end + 0.01;
    c.imu_phase_ns = 0;
    c.imu_noise = noise;
    let sc = Scenario::from_config(c).unwrap();
    let samples: Vec<_> = sc.imu_samples().collect();
    let f = move |t: f64| {
        let x = samples[(((t / 0.005) + 1e-9).floor() as usize).min(samples.len() - 1)];
        (
            Vector3::new(x.gyro[0] as f64, x.gyro[1] as f64, x.gyro[2] as f64),
            Vector3::new(x.acc[0] as f64, x.acc[1] as f64, x.acc[2] as f64),
        )
    };
    (sc, f)
}

#[test]
fn noisy_imu_drifts_within_the_datasheet_bound() {
    // Integrate the board's samples for T = 4 s from rest, with and without noise. The
    // noise-free run has only quantisation and sample-and-hold error; the difference between
    // the runs is the noise's doing and must stay within 5 sigma of what the figures imply:
    // attitude sigma^2 = (b_g T)^2 + N_g^2 T + s_g^2 T^3 / 3 per axis; velocity: the
    // accelerometer's equivalent terms plus gravity acting through the tilt error.
    let n = ChipNoise::icm42688p();
    let (t, dt) = (4.0, 0.005);
    let var_th = (n.gyro_bias_init * t).powi(2)
        + n.density.gyro.powi(2) * t
        + n.density.gyro_bias_walk.powi(2) * t.powi(3) / 3.0;
    let var_v = (n.accel_bias_init * t).powi(2)
        + n.density.acc.powi(2) * t
        + n.density.acc_bias_walk.powi(2) * t.powi(3) / 3.0
        + GRAVITY.powi(2)
            * ((n.gyro_bias_init * t * t / 2.0).powi(2) + n.density.gyro.powi(2) * t.powi(3) / 3.0);
    // Quantisation differs between the runs: +-0.5 LSB per sample, at most 1 LSB * T.
    let (qg, qa) = (500.0f64.to_radians() / 32768.0, 4.0 * GRAVITY / 32768.0);
    let (bound_th, bound_v) =
        (5.0 * var_th.sqrt() + qg * t, 5.0 * var_v.sqrt() + qa * t + GRAVITY * qg * t * t / 2.0);
    let mut max_ratio: f64 = 0.0;
    for seed in 0..6u64 {
        let (sc, noisy) = held_samples(100 + seed, n, t);
        let (_, clean) = held_samples(100 + seed, ChipNoise::none(), t);
        let k0 = sc.trajectory().eval(0.0);
        let (qn, vn, _) = strapdown(&k0, t, dt, noisy);
        let (qc, vc, _) = strapdown(&k0, t, dt, clean);
        let k1 = sc.trajectory().eval(t);
        // Noise-free: only hold and quantisation error.
        assert!(qc.angle_to(&UnitQuaternion::from_rotation_matrix(&k1.rotation)) < 2e-3);
        assert!((vc - k1.velocity).norm() < 0.05, "{}", (vc - k1.velocity).norm());
        let (eq, ev) = (qn.angle_to(&qc), (vn - vc).norm());
        assert!(
            eq < bound_th && ev < bound_v,
            "seed {seed}: attitude {eq} (bound {bound_th}), velocity {ev} (bound {bound_v})"
        );
        max_ratio = max_ratio.max(eq / bound_th).max(ev / bound_v);
    }
    // The bound is not vacuous: the errors reach a sizeable part of it.
    assert!(max_ratio > 0.05, "{max_ratio}");
}

#[test]
fn imu_stream_and_frames_agree_and_ground_truth_is_tum() {
    let sc = short(ScenarioKind::FastRotation, SensorModel::Os1_16, 4, 1.0);
    let direct: Vec<_> = sc.imu_samples().collect();
    assert_eq!(direct.len(), 200);
    let mut serial = Vec::new();
    let mut ouster_imu = 0;
    for ev in WireStream::new(&sc) {
        match ev.wire {
            Wire::Serial(b) => serial.extend(b),
            Wire::Udp { port, payload } if port == ouster::IMU_PORT => {
                assert_eq!(payload.len(), 48);
                // Ouster IMU packet in g and deg/s at the Ouster IMU: check against the truth.
                let t = u64::from_le_bytes(payload[8..16].try_into().unwrap());
                let f = |i: usize| f32::from_le_bytes(payload[i..i + 4].try_into().unwrap()) as f64;
                let acc = Vector3::new(f(24), f(28), f(32)) * GRAVITY;
                let gyro = Vector3::new(f(36), f(40), f(44)).map(f64::to_radians);
                let k = sc.kinematics_at(t);
                let t_io = sc.extrinsic()
                    * nalgebra::Isometry3::translation(
                        ouster::IMU_IN_SENSOR[0],
                        ouster::IMU_IN_SENSOR[1],
                        ouster::IMU_IN_SENSOR[2],
                    );
                let ka = k.attached(&t_io);
                assert!((gyro - ka.angular_velocity).norm() < 0.02, "{gyro} vs {}", ka.angular_velocity);
                assert!((acc - ka.specific_force()).norm() < 0.3, "{acc} vs {}", ka.specific_force());
                ouster_imu += 1;
            }
            _ => {}
        }
    }
    assert!((99..=100).contains(&ouster_imu), "{ouster_imu}");
    let frames = decode_serial(&serial);
    assert_eq!(frames.iter().map(|f| f.sample()).collect::<Vec<_>>(), direct);
    // Ground truth lines parse back to the exact poses.
    let gt = tum::trajectory(direct.iter().map(|s| s.t_ns), |t| sc.pose_at(t));
    for (l, s) in gt.lines().skip(1).zip(&direct) {
        let (t, p) = tum::parse_line(l).unwrap();
        assert_eq!(t, s.t_ns);
        assert!((p.translation.vector - sc.pose_at(t).translation.vector).norm() < 1e-8);
    }
}

#[test]
fn corridor_scans_see_only_the_parallel_walls() {
    use loglio_firmware_sim::world::{CORRIDOR_HALF_WIDTH, CORRIDOR_HEIGHT_M};
    let sc = short(ScenarioKind::Corridor, SensorModel::Vlp32c, 1, 40.0);
    for j in [5u64, 200, 390] {
        let scan = sc.scan(j);
        assert!(scan.points.len() > 40_000);
        for p in scan.points.iter().step_by(11) {
            let t_ns = scan.start_ns + (p.t as f64 * 1e9).round() as u64;
            let w = sc.lidar_pose_at(t_ns) * Point3::new(p.xyz[0] as f64, p.xyz[1] as f64, p.xyz[2] as f64);
            let on_wall = (w.y.abs() - CORRIDOR_HALF_WIDTH).abs() < 0.1;
            let on_floor_or_ceiling = w.z.abs() < 0.1 || (w.z - CORRIDOR_HEIGHT_M).abs() < 0.1;
            assert!(on_wall || on_floor_or_ceiling, "scan {j}: point off the corridor's walls at {w:?}");
        }
    }
}

#[test]
fn events_interleave_imu_and_scans_with_ground_truth() {
    let sc = short(ScenarioKind::Drone, SensorModel::Vlp16, 8, 2.5);
    let (mut imu, mut scans, mut last) = (0, 0, 0);
    for ev in sc.events() {
        assert!(ev.t_ns() >= last);
        last = ev.t_ns();
        match ev {
            Event::Imu(s) => {
                // At rest (first 2 s) the accelerometer reads gravity within noise and bias.
                if s.t_ns < sc.start_ns() + 1_900_000_000 {
                    let a = (s.acc[0].powi(2) + s.acc[1].powi(2) + s.acc[2].powi(2)).sqrt() as f64;
                    assert!((a - GRAVITY).abs() < 0.3, "{a}");
                }
                imu += 1;
            }
            Event::Scan(s) => {
                assert_eq!(s.index, scans);
                scans += 1;
            }
        }
    }
    assert_eq!((imu, scans), (500, 24));
}

#[test]
fn live_mode_sends_udp_and_serial() {
    use std::net::UdpSocket;
    let sc = short(ScenarioKind::Handheld, SensorModel::Vlp16, 1, 0.5);
    let expect_data = WireStream::new(&sc)
        .filter(|e| matches!(e.wire, Wire::Udp { port: velodyne::DATA_PORT, .. }))
        .count();
    // Free loopback ports: other tests (or other engineers' runs) may hold some.
    let (offset, data, _pos) = (0..200u16)
        .find_map(|i| {
            let offset = 20_000 + ((std::process::id() as u16 % 97) * 200 + i * 7) % 20_000;
            let d = UdpSocket::bind(("127.0.0.1", velodyne::DATA_PORT + offset)).ok()?;
            let p = UdpSocket::bind(("127.0.0.1", velodyne::POSITION_PORT + offset)).ok()?;
            Some((offset, d, p))
        })
        .expect("no free loopback ports");
    data.set_read_timeout(Some(std::time::Duration::from_millis(500))).unwrap();
    let cfg = loglio_firmware_sim::live_sensors::LiveConfig {
        host: std::net::Ipv4Addr::LOCALHOST,
        rate: 1.0,
        pty_link: None,
        port_offset: offset,
    };
    let (tx, rx) = std::sync::mpsc::channel();
    let (n, stats, bytes) = std::thread::scope(|s| {
        let h = s.spawn(|| {
            loglio_firmware_sim::live_sensors::run(&sc, &cfg, |pty| tx.send(pty.path.clone()).unwrap())
        });
        let path = rx.recv().unwrap();
        let serial = std::fs::File::open(&path).unwrap();
        let reader = s.spawn(move || {
            use std::io::Read;
            let (mut bytes, mut buf, mut f) = (Vec::new(), [0u8; 4096], serial);
            let t = std::time::Instant::now();
            while t.elapsed() < std::time::Duration::from_secs(3) && decode_serial(&bytes).len() < 100 {
                match f.read(&mut buf) {
                    Ok(0) | Err(_) => break,
                    Ok(n) => bytes.extend_from_slice(&buf[..n]),
                }
            }
            bytes
        });
        let mut n = 0;
        let mut b = [0u8; 2000];
        while let Ok((len, _)) = data.recv_from(&mut b) {
            assert_eq!(len, 1206);
            n += 1;
        }
        (n, h.join().unwrap().unwrap(), reader.join().unwrap())
    });
    // Loopback UDP in real time: nothing should be lost; allow a little for a busy machine.
    assert!(expect_data > 300 && n * 10 >= expect_data * 9, "{n} of {expect_data} data packets");
    assert_eq!(stats.datagrams as usize, expect_data + expect_data / 14);
    let frames = decode_serial(&bytes);
    assert!(frames.len() + stats.imu_dropped as usize >= 99, "{} frames, {stats:?}", frames.len());
    let direct: Vec<_> = sc.imu_samples().collect();
    for f in &frames {
        assert_eq!(f.sample(), direct[f.seq as usize]);
    }
}

/// Scan `j` of `sc` with each point in the world at its firing time, pushed `nudge` metres
/// further along its beam (so a point on a surface lies just inside the solid), with its time.
fn world_points(sc: &Scenario, j: u64, nudge: f64) -> Vec<([f64; 3], u64)> {
    let scan = sc.scan(j);
    scan.points
        .iter()
        .map(|p| {
            let t_ns = scan.start_ns + (p.t as f64 * 1e9).round() as u64;
            let pose = sc.lidar_pose_at(t_ns);
            let w = pose * Point3::new(p.xyz[0] as f64, p.xyz[1] as f64, p.xyz[2] as f64);
            let d = (w.coords - pose.translation.vector).normalize();
            let q = w.coords + d * nudge;
            ([q.x, q.y, q.z], t_ns)
        })
        .collect()
}

fn noise_free_traffic(actors: bool) -> Scenario {
    let mut c = ScenarioConfig::new(ScenarioKind::Traffic, SensorModel::Vlp32c, 5);
    c.lidar.range_mut().sigma = 0.0;
    c.actors = actors;
    Scenario::from_config(c).unwrap()
}

/// The traffic scenario: its scans see the actors where they are at each firing's time (the
/// truck ahead and oncoming cars early on, the cross traffic and pedestrians at the stop, the bus
/// alongside later), the same drive without actors sees none of them, and the ego car stands
/// exactly still at the junction.
#[test]
fn traffic_scans_see_the_moving_actors_and_the_car_waits_at_the_junction() {
    let sc = noise_free_traffic(true);
    let bare = noise_free_traffic(false);
    assert_eq!(sc.config().duration_s, 60.0);
    assert_eq!(ScenarioKind::from_name("traffic"), Some(ScenarioKind::Traffic));
    assert_eq!(sc.actors().list().len(), 13);
    assert!(bare.actors().is_empty());
    assert_eq!(sc.world().scene.prims(), bare.world().scene.prims(), "the same world either way");
    // 10 scans/s: scan j spans [j/10, (j+1)/10) s.
    for (j, min_ids) in [(50u64, 2usize), (240, 3), (500, 1)] {
        let pts = world_points(&sc, j, 0.02);
        let mut per_actor: HashMap<u32, usize> = HashMap::new();
        for (p, t) in &pts {
            if let Some(id) = sc.inside_actor(*p, *t) {
                *per_actor.entry(id).or_default() += 1;
            }
        }
        let on_actors: usize = per_actor.values().sum();
        assert!(on_actors > 500, "scan {j}: {on_actors} points on actors {per_actor:?}");
        assert!(per_actor.len() >= min_ids, "scan {j}: {per_actor:?}");
        // Without the actors, the same rays reach the world behind them: no point in a box but
        // the ground under them (boxes stand on the ground's height at their centre).
        let pts0 = world_points(&bare, j, 0.02);
        let above_ground = |p: &[f64; 3]| p[2] > bare.world().ground_height(p[0], p[1]) + 0.25;
        let in0 = pts0.iter().filter(|(p, t)| above_ground(p) && sc.inside_actor(*p, *t).is_some()).count();
        assert!(in0 * 50 < on_actors, "scan {j}: {in0} points inside boxes without actors");
        // A point on an actor lies in the volume the actor swept over its scan.
        let scan_t = (sc.start_ns() + j * 100_000_000, sc.start_ns() + (j + 1) * 100_000_000 + 1_000_000);
        let (p, t) = pts.iter().find(|(p, t)| sc.inside_actor(*p, *t).is_some()).unwrap();
        let id = sc.inside_actor(*p, *t);
        assert_eq!(sc.inside_actor_swept(*p, scan_t.0, scan_t.1), id);
    }
    // At 4 s (scan 40) the truck drives 14 m ahead (centre to centre): its back is hit.
    let pts = world_points(&sc, 40, 0.02);
    let truck = pts.iter().filter(|(p, t)| sc.inside_actor(*p, *t) == Some(0)).count();
    assert!(truck > 200, "{truck}");
    // The stop: exactly still from 20 s to 29 s (inside the rounding of the boundaries).
    let k0 = sc.kinematics_at(sc.start_ns() + 20_001_000_000);
    for i in 0..=899u64 {
        let k = sc.kinematics_at(sc.start_ns() + 20_001_000_000 + i * 10_000_000);
        assert_eq!(k.position, k0.position);
        assert_eq!(k.velocity, Vector3::zeros());
        assert_eq!(k.angular_velocity, Vector3::zeros());
    }
    assert!(sc.kinematics_at(sc.start_ns() + 10_000_000_000).velocity.norm() > 3.0);
    assert!(sc.kinematics_at(sc.start_ns() + 40_000_000_000).velocity.norm() > 3.0);
    // Where the actors are is ground truth at any time.
    let at = sc.actors_at(sc.start_ns() + 25_000_000_000);
    assert!(at.iter().any(|a| a.kind == loglio_firmware_sim::actors::ActorKind::Pedestrian));
    assert!(at.iter().all(|a| a.size == a.kind.size()));
}
