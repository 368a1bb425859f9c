//! Round trips between the simulator (loglio-firmware-sim) and the core's decoders: what the
//! host decodes from the simulated packets and frames equals the simulated ground truth within
//! the formats' resolution (issue 5, "Round trips").
//!
//! The decoders are built exactly as the host builds them: Velodyne with the model's built-in
//! calibration (`Decoder::new(Config::new(model))`, no calibration file), the packet clock
//! resolved by `loglio_host::input::time_align::VelodyneClock`; Ouster from the metadata JSON the
//! simulator writes, parsed by `loglio_host::input::ouster_meta`. Whole scans go through the core's
//! `ScanAssembler`.
//!
//! Resolutions the bounds are computed from:
//! - Velodyne distance unit `u` (2 mm, VLP-32C 4 mm): the decoded range is within `u / 2` of the
//!   unquantised range, and equals the quantised one up to f32 rounding.
//! - Velodyne azimuth: blocks carry 0.01 degree; the decoder interpolates each firing's azimuth
//!   from the packet's first and last block azimuths and rounds it to 0.01 degree again (as the
//!   ROS driver does). Per firing that is at most half a unit (block rounding) + half a unit
//!   (firing rounding) + the interpolated rate's error (one unit over the packet's span, times
//!   the firing's share of it: at most 1/11 of a span, 1/5 in dual mode), plus f32 rounding of an
//!   azimuth near 36000 hundredths (2^-8 hundredths).
//! - Velodyne firing times: the packet timestamp is whole microseconds (truncated), the timing
//!   tables are whole nanoseconds: decoded = true - (true packet time mod 1 us).
//! - Ouster: 1 mm range (the decoded point equals the simulator's quantised point up to f32
//!   rounding, and is within 0.5 mm of the unquantised one along the beam); column timestamps
//!   are exact nanoseconds.
//! - IMU frames carry the board's f32 values bit for bit; Ouster IMU packets carry f32 g and
//!   deg/s, the chip's LSBs being the resolution against the true kinematics.

use std::collections::HashMap;

use loglio_core::scan::ScanPoint;
use loglio_core::scan_assembly::{AssemblerConfig, PacketMeta, RawPoint, ScanAssembler, ScanInfo};
use loglio_core::sensor::imu_frame::FrameDecoder;
use loglio_core::sensor::ouster as core_ouster;
use loglio_core::sensor::velodyne::{Config, Decoder, Model};
use loglio_firmware_sim::imu_chip::{ChipNoise, accel_lsb, gyro_lsb};
use loglio_firmware_sim::lidar::ouster::{IMU_IN_SENSOR, LidarMode, Ouster, OusterTruth, Profile};
use loglio_firmware_sim::lidar::scanner::{Firmware, velodyne_rows};
use loglio_firmware_sim::lidar::velodyne::{TruthPoint, Velodyne, wrap360};
use loglio_firmware_sim::lidar::{ReturnMode, SensorModel};
use loglio_firmware_sim::scenario::{ImuStream, LidarConfig, Scenario, ScenarioConfig, ScenarioKind};
use loglio_firmware_sim::stream::{Wire, WireStream};
use loglio_host::input::ouster_meta;
use loglio_host::input::time_align::VelodyneClock;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// f32 rounding of a decoded coordinate chain (a handful of f32 operations on values up to
/// `r`): relative 2^-24 per operation, with margin.
fn f32_eps(r: f64) -> f64 {
    8.0 * r * f64::from(f32::EPSILON) / 2.0 + 1e-6
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn f64s(v: [f32; 3]) -> [f64; 3] {
    v.map(f64::from)
}

/// Signed difference of two angles, radians, in (-pi, pi].
fn ang_diff(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(std::f64::consts::TAU);
    if d > std::f64::consts::PI { d - std::f64::consts::TAU } else { d }
}

/// One decoded point beside its ground truth, in stream order.
#[derive(Clone, Copy, Debug)]
struct Pair {
    raw: RawPoint,
    /// Absolute decoded firing time, ns.
    t_dec: u64,
    /// Absolute true firing time, ns.
    t_true: u64,
    /// Unwrapped sweep of the firing in turns since the sensor's origin (exact), for checking
    /// where scans are cut.
    turns: f64,
}

/// Feeds the pairs' packets to a scan assembler (cut at 0 degrees) and checks every complete
/// scan against the stream: it is a contiguous run of the decoded points, each stamped with its
/// time since the scan start (within `t_tol_ns` of the true time), and it starts and ends where
/// the exact sweep crosses the cut, up to `cut_tol_turns` of ambiguity. Returns the number of
/// complete scans.
fn check_scans(
    packets: &[(PacketMeta, std::ops::Range<usize>)],
    pairs: &[Pair],
    t_tol_ns: u64,
    cut_tol_turns: f64,
    name: &str,
) -> usize {
    let (mut a, mut b) = (vec![ScanPoint::default(); 200_000], vec![ScanPoint::default(); 200_000]);
    let mut asm = ScanAssembler::new(AssemblerConfig::cut_at_degrees(0.0), &mut a, &mut b);
    let mut scans: Vec<(ScanInfo, Vec<ScanPoint>)> = Vec::new();
    for (meta, range) in packets {
        let done = asm
            .push_packet(*meta, |sink| {
                for p in &pairs[range.clone()] {
                    sink(p.raw);
                }
            })
            .unwrap();
        if let Some(info) = done {
            scans.push((info, asm.scan().points.to_vec()));
        }
    }
    assert_eq!(asm.stats.missing_packets + asm.stats.duplicates + asm.stats.out_of_order, 0, "{name}");
    assert_eq!(asm.stats.overflow_points + asm.stats.time_regressions, 0, "{name}");
    let mut complete = 0;
    for (info, pts) in scans.iter().filter(|(i, _)| i.complete) {
        complete += 1;
        assert_eq!(info.points as usize, pts.len(), "{name}");
        assert_eq!(info.overflow, 0);
        // The scan's first point is the first decoded point fired at its start time.
        let s = pairs.iter().position(|p| p.t_dec == info.start_ns).expect("scan start in the stream");
        let n = pts.len();
        assert!(s > 0 && s + n < pairs.len(), "{name}: scan at the edge of the stream");
        for (p, q) in pts.iter().zip(&pairs[s..s + n]) {
            assert_eq!(p.xyz, q.raw.xyz, "{name}");
            assert_eq!(
                (p.row, p.col, p.intensity, p.ret),
                (q.raw.row, q.raw.col, q.raw.intensity, q.raw.ret)
            );
            let t_true = (q.t_true - info.start_ns) as f64 * 1e-9;
            // f32 seconds over 0.1 s: 7.5 ns rounding.
            assert!(
                (p.t as f64 - t_true).abs() <= t_tol_ns as f64 * 1e-9 + 1e-8,
                "{name}: t {} vs {t_true}",
                p.t
            );
        }
        assert_eq!(info.end_ns, pairs[s + n - 1].t_dec);
        // Exactly one revolution: the points inside lie between the two cut crossings, the
        // points just outside lie beyond them (each up to the azimuth resolution).
        let m = (pairs[s].turns + 0.5).floor();
        assert!(
            pairs[s..s + n].iter().all(|p| p.turns >= m - cut_tol_turns && p.turns < m + 1.0 + cut_tol_turns)
        );
        assert!(pairs[s - 1].turns < m + cut_tol_turns, "{name}: a point before the scan is after the cut");
        assert!(
            pairs[s + n].turns >= m + 1.0 - cut_tol_turns,
            "{name}: a point after the scan is before the cut"
        );
        let lo = pairs
            .iter()
            .filter(|p| p.turns >= m + cut_tol_turns && p.turns < m + 1.0 - cut_tol_turns)
            .count();
        let hi = pairs
            .iter()
            .filter(|p| p.turns >= m - cut_tol_turns && p.turns < m + 1.0 + cut_tol_turns)
            .count();
        assert!(lo <= n && n <= hi, "{name}: {n} points, {lo}..={hi} expected");
    }
    complete
}

/// Worst errors seen in a round trip.
#[derive(Debug, Default)]
struct Worst {
    /// |decoded - quantised truth|, metres.
    xyz: f64,
    /// Range error against the unquantised truth, metres.
    range_exact: f64,
    /// Firing time error, ns.
    t_ns: u64,
    /// Velodyne: the xyz error seen from the laser, degrees (the azimuth quantisation).
    angle_deg: f64,
    points: usize,
}

fn velodyne_scenario(sensor: SensorModel, mode: ReturnMode, seed: u64) -> Scenario {
    let mut c = ScenarioConfig::new(ScenarioKind::Vehicle, sensor, seed);
    c.duration_s = 1.0;
    if let LidarConfig::Velodyne(v) = &mut c.lidar {
        v.return_mode = mode;
    }
    Scenario::from_config(c).unwrap()
}

/// The truth points of a packet in the decoder's emission order, each with the return index
/// the decoder gives it; equal dual returns merge into one point (the odd block's).
fn velodyne_expected(truth: &[TruthPoint], dual: bool) -> Vec<(TruthPoint, u8)> {
    if !dual {
        return truth.iter().map(|t| (*t, 0)).collect();
    }
    let by_key: HashMap<(u8, u8, u8), TruthPoint> =
        truth.iter().map(|t| ((t.block / 2, t.channel, t.slot), *t)).collect();
    let mut out = Vec::new();
    for pair in 0..6u8 {
        for ch in 0..32u8 {
            let last = by_key.get(&(pair, ch, 0));
            let other = by_key.get(&(pair, ch, 1));
            match (last, other) {
                (Some(l), Some(o)) if l.raw_distance == o.raw_distance => out.push((*o, 0)),
                (l, o) => {
                    out.extend(l.map(|l| (*l, 1)));
                    out.extend(o.map(|o| (*o, 0)));
                }
            }
        }
    }
    out
}

/// Decodes `packets` Velodyne packets from the first with the host's decoder and clock, checks
/// every point against its truth, then assembles whole scans.
fn velodyne_round_trip(sensor: SensorModel, model: Model, mode: ReturnMode, packets: u64) -> Worst {
    let name = format!("{sensor:?} {mode:?}");
    let sc = velodyne_scenario(sensor, mode, 7);
    let Firmware::Velodyne(v) = sc.firmware() else { unreachable!() };
    let v: &Velodyne = v;
    let dual = mode == ReturnMode::Dual;
    let mut dec = Decoder::new(Config::new(model)).unwrap();
    let unit = v.distance_unit();
    assert_eq!(unit as f32, dec.calibration().distance_resolution, "{name}: distance unit");
    // Rows: the sim's layout rows (by elevation, highest first) are the decoder's.
    let sim_rows = velodyne_rows(v);
    assert_eq!(&sim_rows[..v.lasers()], &dec.calibration().rows()[..v.lasers()], "{name}");
    let layout = dec.layout().clone();
    let step = layout.column_step().abs();
    // Azimuth resolution of a decoded firing, degrees (see the module documentation).
    let span_blocks: f64 = if dual { 5.0 } else { 11.0 };
    let az_tol_deg = 0.01 * (0.5 + 0.5 + 1.0 / span_blocks + 1.0 / 256.0);
    let az_tol = az_tol_deg.to_radians();
    let clock = VelodyneClock::new();
    let mut worst = Worst::default();
    let mut pairs: Vec<Pair> = Vec::new();
    let mut metas = Vec::new();
    let mut merged = 0;
    for k in 0..packets {
        let (bytes, truth) = sc.velodyne_packet(k).unwrap();
        let (p, repr) = dec.parse(&bytes).unwrap();
        // Sent after its last firing; the capture time only picks the hour.
        let packet_ns = clock.resolve(repr.timestamp_us, v.packet_time_ns(k + 1));
        let mut raws = Vec::new();
        dec.points(&p, |r| raws.push(r));
        let expected = velodyne_expected(&truth, dual);
        merged += truth.len() - expected.len();
        // Exact counts: every truth point is decoded once (equal dual returns once).
        assert_eq!(raws.len(), expected.len(), "{name} packet {k}");
        let first = pairs.len();
        for (r, (t, ret)) in raws.iter().zip(&expected) {
            let laser = t.laser as usize;
            assert_eq!(r.ret, *ret, "{name}");
            assert_eq!(r.intensity, t.reflectivity as u16);
            let xyz = f64s(r.xyz);
            let range = norm(t.xyz);
            let e = norm(sub(xyz, t.xyz));
            // The beam's horizontal reach: the lever arm of an azimuth error.
            let reach = (t.xyz[0] * t.xyz[0] + t.xyz[1] * t.xyz[1]).sqrt();
            assert!(e <= reach * az_tol + f32_eps(range), "{name}: error {e} m at range {range} m");
            // Along the beam: the decoded distance is the wire's distance (f32), within half a
            // unit of the unquantised one.
            let origin = [0.0, 0.0, v.vertical_offset_m(laser)];
            let d_dec = norm(sub(xyz, origin));
            assert!((d_dec - t.raw_distance as f64 * unit).abs() <= f32_eps(range), "{name}");
            let d_exact = norm(sub(t.xyz_exact, origin));
            assert!((d_dec - d_exact).abs() <= unit / 2.0 + f32_eps(range), "{name}: {d_dec} vs {d_exact}");
            // Firing time: the timestamp's microsecond truncation only.
            let t_dec = packet_ns + r.dt_ns as u64;
            assert!(t_dec <= t.t_ns && t.t_ns - t_dec < 1_000, "{name}: t {t_dec} vs {}", t.t_ns);
            assert_eq!(t.t_ns - t_dec, v.packet_time_ns(k) % 1_000);
            // Pixel: the laser's row; the column whose centre is nearest to the beam's true
            // azimuth, up to the azimuth resolution.
            assert_eq!(r.row, sim_rows[laser]);
            let az_true = -t.azimuth_deg.to_radians();
            let off = ang_diff(layout.azimuth(r.row as usize, r.col as usize), az_true).abs();
            assert!(off <= 0.5 * step + az_tol, "{name}: column {} is {off} rad off", r.col);
            worst.xyz = worst.xyz.max(e);
            worst.angle_deg = worst.angle_deg.max((e / reach).to_degrees());
            worst.range_exact = worst.range_exact.max((d_dec - d_exact).abs());
            worst.t_ns = worst.t_ns.max(t.t_ns - t_dec);
            worst.points += 1;
            // Sweep of the firing (the head, without the VLP-32C's per-laser offsets).
            let turns = v.head_azimuth_deg(t.t_ns) / 360.0;
            assert!(
                (wrap360(v.head_azimuth_deg(t.t_ns) + v.azimuth_offset_deg(laser)) - t.azimuth_deg).abs()
                    < 1e-6
            );
            pairs.push(Pair { raw: *r, t_dec, t_true: t.t_ns, turns });
        }
        metas.push((dec.meta(&repr, packet_ns), first..pairs.len()));
    }
    assert_eq!(dec.stats.bad_packets + dec.stats.model_mismatch + dec.stats.out_of_range, 0, "{name}");
    if dual {
        assert!(merged > 0 && merged < pairs.len(), "{name}: {merged} merged dual returns");
    }
    let complete = check_scans(&metas, &pairs, 1_000, az_tol_deg / 360.0, &name);
    assert!(complete >= 2, "{name}: {complete} complete scans");
    eprintln!("{name}: {worst:?}, {complete} complete scans");
    worst
}

fn packets_for_revolutions(sensor: SensorModel, mode: ReturnMode, revs: f64) -> u64 {
    let model = match sensor {
        SensorModel::Vlp16 => Model::Vlp16,
        SensorModel::Vlp32c => Model::Vlp32c,
        _ => Model::Hdl32e,
    };
    (revs * 0.1e9 / model.packet_period_ns(mode == ReturnMode::Dual) as f64).ceil() as u64
}

#[test]
fn velodyne_packets_round_trip_through_the_core_decoder_and_assembler() {
    for (sensor, model, mode) in [
        (SensorModel::Vlp16, Model::Vlp16, ReturnMode::Strongest),
        (SensorModel::Vlp16, Model::Vlp16, ReturnMode::Dual),
        (SensorModel::Vlp32c, Model::Vlp32c, ReturnMode::Last),
        (SensorModel::Vlp32c, Model::Vlp32c, ReturnMode::Dual),
        (SensorModel::Hdl32e, Model::Hdl32e, ReturnMode::Strongest),
    ] {
        let w = velodyne_round_trip(sensor, model, mode, packets_for_revolutions(sensor, mode, 3.2));
        assert!(w.points > 40_000, "{sensor:?}: {} points", w.points);
        // Some error must be seen (the azimuth is quantised), or the comparison is vacuous.
        assert!(w.xyz > 0.0 && w.range_exact > 0.0 && w.t_ns > 0);
    }
}

fn ouster_scenario(sensor: SensorModel, profile: Profile, mode: LidarMode, seed: u64) -> Scenario {
    let mut c = ScenarioConfig::new(ScenarioKind::Handheld, sensor, seed);
    c.duration_s = 1.0;
    if let LidarConfig::Ouster(o) = &mut c.lidar {
        o.profile = profile;
        o.mode = mode;
    }
    Scenario::from_config(c).unwrap()
}

/// The core's decoder built the way the host builds it: from the metadata JSON the simulator
/// writes, parsed by the host.
fn host_ouster_decoder(o: &Ouster) -> core_ouster::Decoder {
    let json = serde_json::to_string(&loglio_firmware_sim::files::ouster_metadata(o)).unwrap();
    let meta = ouster_meta::parse(&json).unwrap();
    core_ouster::Decoder::new(&meta.intrinsics).unwrap()
}

fn ouster_round_trip(sensor: SensorModel, profile: Profile, mode: LidarMode, frames: u64) -> Worst {
    let name = format!("{sensor:?} {profile:?} {mode:?}");
    let sc = ouster_scenario(sensor, profile, mode, 5);
    let Firmware::Ouster(o) = sc.firmware() else { unreachable!() };
    let mut dec = host_ouster_decoder(o);
    let layout = dec.layout().clone();
    let (h, w) = (o.beams(), o.columns());
    assert_eq!((layout.rows(), layout.cols()), (h, w), "{name}");
    let step = layout.column_step().abs();
    // Rows: beams by altitude, highest first (the sim's beams are in that order already).
    for b in 0..h {
        assert!((layout.elevation(b) as f64 - o.altitude_deg(b).to_radians()).abs() < 1e-6, "{name} row {b}");
    }
    // Destaggered: the pixels of one column look the same way in every row, up to the
    // rounding of each row's shift to a whole column.
    for c in [0, w / 3, w - 1] {
        let a0 = layout.azimuth(0, c);
        for r in 0..h {
            assert!(ang_diff(layout.azimuth(r, c), a0).abs() <= step + 1e-6, "{name}: row {r} column {c}");
        }
    }
    let mut worst = Worst::default();
    let mut pairs = Vec::new();
    let mut metas = Vec::new();
    let per_frame = (w / 16) as u64;
    for k in 0..frames * per_frame {
        let (bytes, truth): (Vec<u8>, Vec<OusterTruth>) = sc.ouster_packet(k).unwrap();
        let (p, repr) = dec.parse(&bytes).unwrap();
        assert_eq!(repr.valid_columns, 16);
        assert_eq!(repr.frame_id as u64, k / per_frame);
        let mut raws = Vec::new();
        dec.points(&p, |r| raws.push(r));
        assert_eq!(raws.len(), truth.len(), "{name} packet {k}");
        let first = pairs.len();
        for (r, t) in raws.iter().zip(&truth) {
            let xyz = f64s(r.xyz);
            let range = norm(t.xyz);
            let e = norm(sub(xyz, t.xyz));
            assert!(e <= f32_eps(range), "{name}: error {e} m at {range} m");
            let ex = norm(sub(xyz, t.xyz_exact));
            assert!(ex <= 0.0005 + f32_eps(range), "{name}: {ex} m from the unquantised point");
            let t_dec = repr.timestamp_ns + r.dt_ns as u64;
            assert_eq!(t_dec, t.t_ns, "{name}");
            assert_eq!(r.intensity, t.reflectivity as u16);
            assert_eq!(r.ret, 0);
            // Pixel: the beam's row, the destaggered column whose direction is the beam's.
            assert_eq!(r.row, t.beam);
            let g = k * 16 + (t.measurement_id as u64 % 16);
            assert_eq!(g % w as u64, t.measurement_id as u64);
            let d = o.firing(g, t.beam as usize).dir;
            let off = ang_diff(layout.azimuth(r.row as usize, r.col as usize), d[1].atan2(d[0])).abs();
            assert!(off <= 1e-5, "{name}: column {} is {off} rad off the beam", r.col);
            worst.xyz = worst.xyz.max(e);
            worst.range_exact = worst.range_exact.max(ex);
            worst.points += 1;
            // Sweep: clockwise from the sensor's forward axis; the lidar frame is turned half a
            // turn, so measurement id W/2 looks forward.
            let turns = g as f64 / w as f64 - 0.5;
            pairs.push(Pair { raw: *r, t_dec, t_true: t.t_ns, turns });
        }
        metas.push((dec.meta(&repr, repr.timestamp_ns), first..pairs.len()));
    }
    assert_eq!(dec.stats.bad_packets + dec.stats.invalid_columns + dec.stats.bad_timestamps, 0);
    // Columns are exact: no cut ambiguity beyond f64 rounding.
    let complete = check_scans(&metas, &pairs, 0, 1e-9, &name);
    assert!(complete as u64 >= frames - 1, "{name}: {complete} complete scans");
    eprintln!("{name}: {worst:?}, {complete} complete scans");
    worst
}

#[test]
fn ouster_packets_round_trip_through_the_core_decoder_and_assembler() {
    for (sensor, profile, mode, frames) in [
        (SensorModel::Os1_16, Profile::Legacy, LidarMode::M1024x10, 3),
        (SensorModel::Os1_16, Profile::Rng19Rfl8Sig16Nir16, LidarMode::M512x20, 3),
        (SensorModel::Os1_64, Profile::Legacy, LidarMode::M1024x10, 3),
        (SensorModel::Os1_64, Profile::Rng19Rfl8Sig16Nir16, LidarMode::M2048x10, 3),
        (SensorModel::Os1_128, Profile::Legacy, LidarMode::M1024x10, 2),
        (SensorModel::Os1_128, Profile::Rng19Rfl8Sig16Nir16, LidarMode::M512x20, 3),
    ] {
        let w = ouster_round_trip(sensor, profile, mode, frames);
        assert!(w.points > 20_000, "{sensor:?}: {} points", w.points);
        assert!(w.range_exact > 0.0);
    }
}

/// The IMU board's serial frames, fed to the core's frame decoder in awkward chunks, give back
/// every frame the board sent, bit for bit; with a perfect chip they are the true kinematics
/// within the chip's LSB.
#[test]
fn imu_serial_frames_round_trip_through_the_core_frame_decoder() {
    // 2 s at rest, then 4 s of fast handheld rotation.
    let mut c = ScenarioConfig::new(ScenarioKind::FastRotation, SensorModel::Vlp16, 3);
    c.duration_s = 6.0;
    c.imu_noise = ChipNoise::none();
    let sc = Scenario::from_config(c).unwrap();
    let mut stream = ImuStream::new(&sc, Vec::<u8>::new());
    let sent: Vec<_> = stream.by_ref().collect();
    let bytes = std::mem::take(stream.serial());
    // One sample per 5 ms from the board's phase to the end, both included.
    let period = 1_000_000_000 / sc.config().imu_board.odr.hz() as u64;
    let phase = sc.config().imu_phase_ns % period;
    assert_eq!(sent.len() as u64, (sc.end_ns() - sc.start_ns() - phase) / period + 1);
    assert!(sent.len() >= 1200);
    let mut dec = FrameDecoder::new();
    let mut got = Vec::new();
    // Chunks of 1, 2, ..., 17 bytes, as a UART driver might hand them over.
    let (mut at, mut chunk) = (0, 1);
    while at < bytes.len() {
        let mut rest = &bytes[at..(at + chunk).min(bytes.len())];
        at += rest.len();
        while !rest.is_empty() {
            let (n, f) = dec.feed(rest);
            got.extend(f);
            rest = &rest[n..];
        }
        chunk = chunk % 17 + 1;
    }
    assert_eq!(got.len(), sent.len());
    assert_eq!(dec.stats.frames as usize, sent.len());
    assert_eq!(
        dec.stats.crc + dec.stats.cobs + dec.stats.payload + dec.stats.seq_gaps + dec.stats.too_long,
        0
    );
    let cfg = sc.config().imu_board;
    let (glsb, alsb) = (gyro_lsb(cfg.gyro_fs as u8), accel_lsb(cfg.accel_fs as u8));
    let (mut worst_g, mut worst_a) = (0.0f64, 0.0f64);
    for (i, (f, s)) in got.iter().zip(&sent).enumerate() {
        assert_eq!(f.seq as usize, i);
        assert_eq!(f.sample(), *s, "frame {i}");
        let k = sc.kinematics_at(f.t_ns);
        let (wv, fv) = (k.angular_velocity, k.specific_force());
        for j in 0..3 {
            let eg = (f.gyro[j] as f64 - wv[j]).abs();
            let ea = (f.acc[j] as f64 - fv[j]).abs();
            // Half an LSB, plus the f32 product of the count and the f32 scale.
            assert!(eg <= 0.5 * glsb + 1e-6 * wv[j].abs() + 1e-9, "gyro {eg} rad/s");
            assert!(ea <= 0.5 * alsb + 1e-6 * fv[j].abs() + 1e-9, "acc {ea} m/s^2");
            worst_g = worst_g.max(eg / glsb);
            worst_a = worst_a.max(ea / alsb);
        }
    }
    // Fast rotation reaches 2 rad/s within 4 s: the values are far from trivial.
    let peak = got.iter().map(|f| f.gyro.iter().fold(0.0f32, |m, g| m.max(g.abs()))).fold(0.0, f32::max);
    assert!(peak > 2.0, "peak rate {peak} rad/s");
    eprintln!("IMU frames: worst gyro {worst_g:.3} LSB, worst acc {worst_a:.3} LSB");
}

/// The Ouster's IMU packets decoded by the core are the IMU's true kinematics (a perfect chip)
/// within the chip's LSB, stamped with the exact sample time.
#[test]
fn ouster_imu_packets_round_trip_through_the_core_decoder() {
    let mut c = ScenarioConfig::new(ScenarioKind::FastRotation, SensorModel::Os1_16, 4);
    c.duration_s = 2.6;
    c.imu_noise = ChipNoise::none();
    if let LidarConfig::Ouster(o) = &mut c.lidar {
        o.mode = LidarMode::M512x10;
    }
    let sc = Scenario::from_config(c).unwrap();
    let Firmware::Ouster(o) = sc.firmware() else { unreachable!() };
    let mut dec = host_ouster_decoder(o);
    // The chip in the Ouster runs at +-500 deg/s and +-4 g (see `stream`).
    let (glsb, alsb) = (gyro_lsb(2), accel_lsb(2));
    let t_io = sc.extrinsic()
        * Isometry3::from_parts(
            Translation3::new(IMU_IN_SENSOR[0], IMU_IN_SENSOR[1], IMU_IN_SENSOR[2]),
            UnitQuaternion::identity(),
        );
    let mut n = 0u64;
    let (mut worst_g, mut worst_a) = (0.0f64, 0.0f64);
    let mut last_t = 0;
    for ev in WireStream::new(&sc) {
        let Wire::Udp { port: 7503, payload } = ev.wire else { continue };
        let imu = dec.imu(&payload).unwrap();
        let s = imu.sample(0).unwrap();
        // 100 Hz from 3 ms after the start; sent 20 us after sampling.
        assert_eq!(s.t_ns, sc.start_ns() + 3_000_000 + n * 10_000_000);
        assert_eq!(imu.sys_ts_ns, s.t_ns + 20_000);
        assert_eq!(ev.t_ns, imu.sys_ts_ns);
        assert!(s.t_ns > last_t);
        last_t = s.t_ns;
        let k = sc.kinematics_at(s.t_ns).attached(&t_io);
        let (wv, fv) = (k.angular_velocity, k.specific_force());
        for j in 0..3 {
            // The packet carries f32 deg/s and g; the core converts with f32 factors.
            let eg = (s.gyro[j] as f64 - wv[j]).abs();
            let ea = (s.acc[j] as f64 - fv[j]).abs();
            assert!(eg <= 0.5 * glsb + 1e-6 * wv[j].abs() + 1e-7, "gyro {eg} rad/s at {}", s.t_ns);
            assert!(ea <= 0.5 * alsb + 1e-6 * fv[j].abs() + 1e-6, "acc {ea} m/s^2 at {}", s.t_ns);
            worst_g = worst_g.max(eg / glsb);
            worst_a = worst_a.max(ea / alsb);
        }
        n += 1;
    }
    assert_eq!(n, 260, "2.6 s at 100 Hz");
    assert_eq!(dec.stats.imu_packets, n);
    assert_eq!(dec.stats.bad_imu_packets, 0);
    eprintln!("Ouster IMU: worst gyro {worst_g:.3} LSB, worst acc {worst_a:.3} LSB");
}
