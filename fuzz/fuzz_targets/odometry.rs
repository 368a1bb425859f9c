//! The whole core odometry under faults: a well-formed stream (a 16 x 128 LiDAR in a box-shaped
//! room whose floor height the input picks, 10 Hz scans, a 200 Hz IMU at rest with gravity, slowly turning and moving when the
//! input says) that the input damages event by event: IMU samples with any values, time jumps
//! and reversals, dropped samples, scan points with any values, truncated or empty scans, scan
//! starts that jump. Every result must be well formed: a finite pose, velocity, biases and
//! covariance, whatever the status. The storage is the caller's (one static, reused).
#![no_main]
use std::sync::Mutex;

use libfuzzer_sys::fuzz_target;
use loglio_core::imu::ImuSample;
use loglio_core::odometry::{OdometryConfig, OdometryStorage};
use loglio_core::range_image::RangeImageLayout;
use loglio_core::ring_fals::storage_pixels;
use loglio_core::scan::{ScanPoint, ScanView};
use loglio_fuzz::Input;

const ROWS: usize = 16;
const COLS: usize = 128;
type Storage = OdometryStorage<{ storage_pixels(ROWS, COLS) }, 4096, 4096, 8192, 16384>;

static STORAGE: Mutex<Option<Box<Storage>>> = Mutex::new(None);

/// Range from `o` along `d` to the walls of a 10 x 8 m room, floor at `floor` (below -1.5 the
/// beams, +-15 degrees, no longer reach it: z is then unobservable, which the status must say).
fn room_range(d: [f32; 3], o: [f32; 3], floor: f32) -> f32 {
    let (lo, hi) = ([-5.0f32, -4.0, floor], [5.0f32, 4.0, 1.2]);
    let mut t = f32::INFINITY;
    for a in 0..3 {
        if d[a] > 1e-6 {
            t = t.min((hi[a] - o[a]) / d[a]);
        } else if d[a] < -1e-6 {
            t = t.min((lo[a] - o[a]) / d[a]);
        }
    }
    t
}

fuzz_target!(|data: &[u8]| {
    let mut inp = Input(data);
    let mut guard = STORAGE.lock().unwrap_or_else(|e| e.into_inner());
    let storage = guard.get_or_insert_with(|| Box::new(Storage::new()));
    let elev: Vec<f32> = (0..ROWS).map(|r| (15.0 - 2.0 * r as f32).to_radians()).collect();
    let layout = RangeImageLayout::from_elevations(&elev, COLS, true).expect("layout");
    let cfg = OdometryConfig::os1_16(layout);
    let mut odo = storage.odometry(&cfg).expect("config");
    // Motion the input picks: a yaw rate and a forward speed (small: the room is small).
    let yaw_rate = f32::from(inp.u8() as i8) * 0.002;
    let speed = f32::from(inp.u8() % 16) * 0.02;
    let floor = -1.0 - f32::from(inp.u8() % 4) * 0.3;
    let mut t_ns: u64 = 1_000_000_000;
    let mut points = vec![ScanPoint::default(); ROWS * COLS];
    for scan_no in 0..usize::from(inp.u8() % 24) {
        // 20 IMU samples up to this scan's end.
        for _ in 0..20 {
            t_ns += 5_000_000;
            let mut s = ImuSample { t_ns, gyro: [0.0, 0.0, yaw_rate], acc: [0.0, 0.0, 9.81] };
            match inp.u8() {
                250 => s.gyro[usize::from(inp.u8() % 3)] = inp.f32(),
                251 => s.acc[usize::from(inp.u8() % 3)] = inp.f32(),
                252 => s.t_ns = s.t_ns.wrapping_add(u64::from(inp.u32()) * 1000),
                253 => s.t_ns = s.t_ns.saturating_sub(u64::from(inp.u32())),
                254 => continue,
                _ => {}
            }
            let _ = odo.push_imu(s);
        }
        // The scan: the room from the pose the motion gives (yaw and x), points over 100 ms.
        let secs = scan_no as f32 * 0.1;
        let (yaw, x) = (yaw_rate * secs, (speed * secs).min(3.0));
        let mut n = 0;
        for c in 0..COLS {
            let az = -(c as f32) / COLS as f32 * std::f32::consts::TAU;
            for (r, &e) in elev.iter().enumerate() {
                let dl = [e.cos() * az.cos(), e.cos() * az.sin(), e.sin()];
                let (cy, sy) = (yaw.cos(), yaw.sin());
                let dw = [cy * dl[0] - sy * dl[1], sy * dl[0] + cy * dl[1], dl[2]];
                let range = room_range(dw, [x, 0.0, 0.0], floor);
                points[n] = ScanPoint {
                    xyz: [dl[0] * range, dl[1] * range, dl[2] * range],
                    t: c as f32 / COLS as f32 * 0.1,
                    row: r as u16,
                    col: c as u16,
                    intensity: 100,
                    ret: 0,
                    flags: 0,
                };
                n += 1;
            }
        }
        let mut start_ns = t_ns - 100_000_000;
        // Damage to the scan, as many times as the input says.
        for _ in 0..usize::from(inp.u8() % 8) {
            match inp.u8() % 6 {
                0 => {
                    let i = usize::from(inp.u8()) * 8 % n.max(1);
                    points[i].xyz[usize::from(inp.u8() % 3)] = inp.f32();
                }
                1 => {
                    let i = usize::from(inp.u8()) * 8 % n.max(1);
                    points[i].t = inp.f32();
                }
                2 => {
                    let i = usize::from(inp.u8()) * 8 % n.max(1);
                    points[i].row = u16::from(inp.u8());
                    points[i].col = u16::from(inp.u8()) * 2;
                }
                3 => n = n * usize::from(inp.u8()) / 256,
                4 => start_ns = start_ns.wrapping_add(u64::from(inp.u32()) * 1000),
                _ => start_ns = start_ns.saturating_sub(u64::from(inp.u32()) * 1000),
            }
        }
        let r = odo.process_scan(ScanView { start_ns, points: &points[..n] });
        if std::env::var_os("LOGLIO_FUZZ_SHOW").is_some() {
            eprintln!("scan {scan_no}: {:?} {:?} position {:?}", r.status, r.associations, r.pose.position);
        }
        let p = &r.pose;
        assert!(p.position.iter().all(|v| v.is_finite()), "{r:?}");
        assert!(p.rotation.coords.iter().all(|v| v.is_finite()), "{r:?}");
        assert!(
            p.velocity.iter().chain(p.gyro_bias.iter()).chain(p.acc_bias.iter()).all(|v| v.is_finite()),
            "{r:?}"
        );
        assert!(p.covariance.iter().all(|v| v.is_finite()), "{r:?}");
    }
});
