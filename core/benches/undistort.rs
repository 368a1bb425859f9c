//! The undistortion of one 32 x 1800 (VLP-32C) street scan (55,000 returns in firing order, 16
//! firing times per 55.3 µs column, as the sensor fires its 32 lasers in pairs) to the scan end,
//! on a trajectory of 41 knots (a 400 Hz IMU) turning at 1.5 rad/s and driving at 10 m/s,
//! single-threaded: the points alone (`points`) and the points with their normals turned by the
//! odometry's table in the same pass (`rotating`).
//!
//! `cargo bench -p loglio-core --bench undistort`

use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use loglio_core::eskf::State;
use loglio_core::scan::ScanPoint;
use loglio_core::so3::S2;
use loglio_core::undistort::{ImuTrajectory, NormalRotations};
use nalgebra::{UnitQuaternion, Vector3};

#[path = "../../tests/synth.rs"]
mod synth;

/// VLP-32C timing: a column every 55.296 µs, a firing of two lasers every 2.304 µs.
const COLUMN_S: f32 = 55.296e-6;
const FIRING_S: f32 = 2.304e-6;

fn state_at(t: f64) -> State {
    let (rate, speed) = (1.5, 10.0);
    let yaw = rate * t;
    State {
        rot: UnitQuaternion::from_euler_angles(0.01 * t, 0.0, yaw),
        pos: Vector3::new(speed * t, 0.3 * t * t, 0.0),
        ext_rot: UnitQuaternion::from_euler_angles(0.0, 0.0, core::f64::consts::PI),
        ext_pos: Vector3::new(0.1, 0.0, 0.2),
        vel: Vector3::new(speed, 0.6 * t, 0.0),
        bg: Vector3::zeros(),
        ba: Vector3::zeros(),
        grav: S2::new(&Vector3::new(0.0, 0.0, -1.0), 9.81),
    }
}

fn bench(c: &mut Criterion) {
    let mut points: Vec<ScanPoint> = synth::vlp32c_street_in_firing_order();
    for p in &mut points {
        p.t = p.col as f32 * COLUMN_S + (p.row / 2) as f32 * FIRING_S;
    }
    let normals: Vec<[f32; 3]> = points.iter().map(|p| [p.xyz[1], -p.xyz[0], 0.3]).collect();
    let normals: Vec<[f32; 3]> = normals
        .iter()
        .map(|n| {
            let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            [n[0] / l, n[1] / l, n[2] / l]
        })
        .collect();
    let start_ns = 5_000_000_000u64;
    let mut traj = ImuTrajectory::<64>::new();
    traj.clear(start_ns);
    let knot_ns = 2_500_000u64;
    for k in 0..=40u64 {
        let t_ns = k * knot_ns;
        traj.push(start_ns + t_ns, &state_at(t_ns as f64 * 1e-9));
    }
    let end = state_at(0.1);
    let t_max = points.iter().map(|p| p.t).fold(0.0f32, f32::max);
    let mut table = NormalRotations::new();
    traj.normal_rotations(&end, 0.0, t_max, &mut table).unwrap();
    let (mut out, mut nout) = (points.clone(), normals.clone());
    let st = traj.undistort(&end, &mut out, None).unwrap();
    let mut times: Vec<u32> = points.iter().map(|p| p.t.to_bits()).collect();
    times.dedup();
    println!(
        "undistort: {} points, {} firing times, {} exact transforms, {} knots",
        points.len(),
        times.len(),
        st.transforms,
        traj.knots().len()
    );

    let mut g = c.benchmark_group("undistort/32x1800");
    g.sample_size(40).measurement_time(Duration::from_secs(4)).warm_up_time(Duration::from_secs(1));
    g.bench_function("points", |b| {
        b.iter(|| {
            out.copy_from_slice(&points);
            traj.undistort(&end, std::hint::black_box(&mut out), None).unwrap()
        })
    });
    g.bench_function("rotating", |b| {
        b.iter(|| {
            out.copy_from_slice(&points);
            nout.copy_from_slice(&normals);
            traj.undistort_rotating(&end, std::hint::black_box(&mut out), &mut nout, &table).unwrap()
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
