//! Filter benchmarks: one IMU propagation step (state and 23 x 23 covariance) against a dense
//! `F P Fᵀ` baseline, and one update iteration with 5,000 point-to-plane measurements against
//! the accumulation alone.
//!
//! `cargo bench -p loglio-core --bench eskf`

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use loglio_core::eskf::{
    DIM, Eskf, EskfConfig, InfoAccumulator, Measurements, PointToPlane, State, StateCov, idx,
};
use loglio_core::imu::ImuSample;
use loglio_core::so3::S2;
use nalgebra::{UnitQuaternion, Vector3};

fn state() -> State {
    State {
        rot: UnitQuaternion::from_euler_angles(0.1, -0.2, 0.7),
        pos: Vector3::new(1.0, 2.0, 0.5),
        ext_rot: UnitQuaternion::identity(),
        ext_pos: Vector3::new(0.05, 0.0, 0.1),
        vel: Vector3::new(1.0, 0.5, 0.0),
        bg: Vector3::zeros(),
        ba: Vector3::zeros(),
        grav: S2::new(&Vector3::new(0.0, 0.0, -9.81), 9.81),
    }
}

fn cov() -> StateCov {
    // A dense, well-conditioned SPD matrix (what the filter carries after a few updates).
    let mut a = StateCov::zeros();
    let mut s = 1u64;
    for v in a.iter_mut() {
        s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        *v = ((s >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.01;
    }
    a * a.transpose() + StateCov::identity() * 1e-4
}

fn sample(t_ns: u64) -> ImuSample {
    ImuSample { t_ns, gyro: [0.01, -0.02, 0.3], acc: [0.2, -0.1, 9.8] }
}

/// 5,000 LiDAR-frame points on the planes of a box room, with their planes.
struct Room {
    points: Vec<(Vector3<f64>, Vector3<f64>, f64)>,
}

impl Room {
    fn new(x: &State) -> Self {
        let mut s = 7u64;
        let mut u = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let (lo, hi) = (Vector3::new(-8.0, -6.0, -1.5), Vector3::new(8.0, 6.0, 3.0));
        let mut points = Vec::new();
        for i in 0..5000 {
            let axis = i % 3;
            let side = if (i / 3) % 2 == 0 { lo[axis] } else { hi[axis] };
            let mut p = Vector3::zeros();
            for a in 0..3 {
                p[a] = lo[a] + (hi[a] - lo[a]) * u();
            }
            p[axis] = side;
            let mut n = Vector3::zeros();
            n[axis] = 1.0;
            let d = -side;
            // In the LiDAR frame of a pose 2 cm and 0.3 deg off `x`.
            let p_i = x.rot.inverse() * (p - x.pos - Vector3::new(0.02, -0.01, 0.01));
            points.push((x.ext_rot.inverse() * (p_i - x.ext_pos), n, d));
        }
        Self { points }
    }
}

impl Measurements for Room {
    fn linearize(&mut self, x: &State, _iteration: usize, acc: &mut InfoAccumulator) {
        let lin = PointToPlane::new(x);
        for (p, n, d) in &self.points {
            let (r, h) = lin.row(p, n, *d);
            acc.add(&h, r, 1e-3);
        }
    }
}

fn benches(c: &mut Criterion) {
    let mut g = c.benchmark_group("eskf");

    // --- propagation ---
    let mut f = Eskf::from_state(EskfConfig::default(), state(), cov(), 0, Some(sample(0)), 1.0);
    let mut t = 0u64;
    g.bench_function("propagate_step", |b| {
        b.iter(|| {
            t += 5_000_000;
            black_box(f.predict(black_box(&sample(t))))
        })
    });
    // Baseline: the dense covariance product a naive step would do.
    let p = cov();
    let mut fm = StateCov::identity();
    for i in 0..9 {
        for j in 0..DIM {
            fm[(i, j)] += 0.001 * ((i * 7 + j * 3) % 11) as f64;
        }
    }
    fm[(idx::VEL, idx::ROT)] = 0.05;
    g.bench_function("baseline_dense_fpft", |b| {
        b.iter(|| black_box(black_box(fm) * black_box(p) * fm.transpose()))
    });

    // --- update ---
    let x = state();
    let mut room = Room::new(&x);
    let lin = PointToPlane::new(&x);
    g.bench_function("accumulate_5000", |b| {
        b.iter(|| {
            let mut acc = InfoAccumulator::new(false);
            for (p, n, d) in &room.points {
                let (r, h) = lin.row(p, n, *d);
                acc.add(&h, r, 1e-3);
            }
            black_box(acc.information())
        })
    });
    g.bench_function("accumulate_5000_extrinsic", |b| {
        b.iter(|| {
            let mut acc = InfoAccumulator::new(true);
            for (p, n, d) in &room.points {
                let (r, h) = lin.row(p, n, *d);
                acc.add(&h, r, 1e-3);
            }
            black_box(acc.information())
        })
    });
    let cfg = EskfConfig { max_iterations: 1, ..Default::default() };
    let base = Eskf::from_state(cfg, x, cov(), 0, None, 1.0);
    g.bench_function("update_iteration_5000", |b| {
        b.iter(|| {
            let mut f = base.clone();
            black_box(f.update(&mut room))
        })
    });
    let mut small = Room { points: room.points[..50].to_vec() };
    g.bench_function("update_iteration_50", |b| {
        b.iter(|| {
            let mut f = base.clone();
            black_box(f.update(&mut small))
        })
    });
    g.finish();
}

criterion_group!(eskf, benches);
criterion_main!(eskf);
