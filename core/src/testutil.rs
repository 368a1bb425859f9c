//! Test helpers (compiled for tests only): a seeded PRNG, an analytic trajectory with exact
//! derivatives, IMU samples synthesised from it, and a [`Parallel`](crate::parallel::Parallel)
//! on scoped threads.
#![allow(dead_code)] // helpers shared by several test modules; not every build uses each one

use nalgebra::{Matrix3, UnitQuaternion, Vector3};

use crate::imu::ImuSample;

/// Gravity magnitude used by the synthetic worlds, m/s^2.
pub const G: f64 = 9.81;

/// SplitMix64 with Box-Muller normals: small, seeded, deterministic.
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
    spare: Option<f64>,
}

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self { state: seed, spare: None }
    }

    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in (0, 1).
    pub fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    /// Standard normal.
    pub fn gauss(&mut self) -> f64 {
        if let Some(s) = self.spare.take() {
            return s;
        }
        let u1 = self.uniform();
        let u2 = self.uniform();
        let r = libm::sqrt(-2.0 * libm::log(u1));
        let a = 2.0 * core::f64::consts::PI * u2;
        self.spare = Some(r * libm::sin(a));
        r * libm::cos(a)
    }

    pub fn gauss3(&mut self) -> Vector3<f64> {
        Vector3::new(self.gauss(), self.gauss(), self.gauss())
    }
}

/// SplitMix64 with ranges and a sum-of-12 normal: the map and surfel tests' data generator
/// (their fixtures were drawn with it; keep the sequence).
pub struct SplitMix(pub u64);

impl SplitMix {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [lo, hi).
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }

    /// Sum of 12 uniforms: close enough to a unit normal for test noise.
    pub fn gauss(&mut self) -> f64 {
        (0..12).map(|_| self.uniform(0.0, 1.0)).sum::<f64>() - 6.0
    }
}

/// The exact state of the IMU at one instant.
#[derive(Clone, Copy, Debug)]
pub struct Motion {
    /// World from IMU.
    pub rot: Matrix3<f64>,
    pub pos: Vector3<f64>,
    pub vel: Vector3<f64>,
    /// World acceleration (not specific force).
    pub acc: Vector3<f64>,
    /// Body-frame angular rate.
    pub omega: Vector3<f64>,
}

impl Motion {
    /// The noise-free IMU reading (specific force in the body frame, g = -9.81 z).
    pub fn imu(&self, t_ns: u64) -> ImuSample {
        let f = self.rot.transpose() * (self.acc + Vector3::new(0.0, 0.0, G));
        ImuSample {
            t_ns,
            gyro: [self.omega.x as f32, self.omega.y as f32, self.omega.z as f32],
            acc: [f.x as f32, f.y as f32, f.z as f32],
        }
    }

    pub fn quat(&self) -> UnitQuaternion<f64> {
        UnitQuaternion::from_matrix(&self.rot)
    }
}

/// A helix about world z with a heading that follows the tangent plus a wobble, and roll and
/// pitch oscillations: every derivative in closed form.
#[derive(Clone, Copy, Debug)]
pub struct Helix {
    pub radius: f64,
    /// Angular rate around the helix axis, rad/s.
    pub rate: f64,
    /// Climb rate, m/s.
    pub climb: f64,
    /// Vertical oscillation amplitude (m) and frequency (rad/s).
    pub heave: (f64, f64),
    /// (amplitude rad, frequency rad/s) of roll, pitch and the yaw wobble.
    pub roll: (f64, f64),
    pub pitch: (f64, f64),
    pub yaw: (f64, f64),
}

impl Helix {
    /// A brisk handheld-like motion: 5 m radius, 0.4 rad/s around, 0.1 m/s climb, roll and pitch
    /// of ±0.2 rad, rates up to ~1 rad/s.
    pub fn standard() -> Self {
        Self {
            radius: 5.0,
            rate: 0.4,
            climb: 0.1,
            heave: (0.2, 1.3),
            roll: (0.2, 1.7),
            pitch: (0.15, 2.3),
            yaw: (0.25, 1.1),
        }
    }

    pub fn at(&self, t: f64) -> Motion {
        let (s, c) = (libm::sin, libm::cos);
        let w = self.rate;
        let r = self.radius;
        let (ha, hf) = self.heave;
        let pos = Vector3::new(r * c(w * t), r * s(w * t), self.climb * t + ha * s(hf * t));
        let vel = Vector3::new(-r * w * s(w * t), r * w * c(w * t), self.climb + ha * hf * c(hf * t));
        let acc = Vector3::new(-r * w * w * c(w * t), -r * w * w * s(w * t), -ha * hf * hf * s(hf * t));

        let (ra, rf) = self.roll;
        let (pa, pf) = self.pitch;
        let (ya, yf) = self.yaw;
        let phi = ra * s(rf * t + 0.5);
        let theta = pa * s(pf * t);
        let psi = w * t + core::f64::consts::FRAC_PI_2 + ya * s(yf * t);
        let dphi = ra * rf * c(rf * t + 0.5);
        let dtheta = pa * pf * c(pf * t);
        let dpsi = w + ya * yf * c(yf * t);
        let omega = Vector3::new(
            dphi - dpsi * s(theta),
            dtheta * c(phi) + dpsi * c(theta) * s(phi),
            -dtheta * s(phi) + dpsi * c(theta) * c(phi),
        );
        let rot = UnitQuaternion::from_euler_angles(phi, theta, psi).to_rotation_matrix().into_inner();
        Motion { rot, pos, vel, acc, omega }
    }
}

/// A drive along world x at `speed` with a lateral and vertical sway and small roll, pitch and
/// yaw oscillations (yaw about 0: the vehicle faces +x): every derivative in closed form.
#[derive(Clone, Copy, Debug)]
pub struct Drive {
    pub speed: f64,
    /// (amplitude m, frequency rad/s) of the surge on top of the speed, the sway (y) and the heave (z).
    pub surge: (f64, f64),
    pub sway: (f64, f64),
    pub heave: (f64, f64),
    /// (amplitude rad, frequency rad/s) of roll, pitch and yaw.
    pub roll: (f64, f64),
    pub pitch: (f64, f64),
    pub yaw: (f64, f64),
}

impl Drive {
    /// 1.5 m/s down a corridor with a gentle sway.
    pub fn corridor() -> Self {
        Self {
            speed: 1.5,
            surge: (0.3, 0.4),
            sway: (0.2, 0.5),
            heave: (0.05, 1.1),
            roll: (0.03, 1.3),
            pitch: (0.04, 0.9),
            yaw: (0.08, 0.6),
        }
    }

    pub fn at(&self, t: f64) -> Motion {
        let (s, c) = (libm::sin, libm::cos);
        let osc = |(a, f): (f64, f64)| (a * s(f * t), a * f * c(f * t), -a * f * f * s(f * t));
        let (sx, vx, ax) = osc(self.surge);
        let (sy, vy, ay) = osc(self.sway);
        let (sz, vz, az) = osc(self.heave);
        let pos = Vector3::new(self.speed * t + sx, sy, sz);
        let vel = Vector3::new(self.speed + vx, vy, vz);
        let acc = Vector3::new(ax, ay, az);
        let (phi, dphi, _) = osc(self.roll);
        let (theta, dtheta, _) = osc(self.pitch);
        let (psi, dpsi, _) = osc(self.yaw);
        let omega = Vector3::new(
            dphi - dpsi * s(theta),
            dtheta * c(phi) + dpsi * c(theta) * s(phi),
            -dtheta * s(phi) + dpsi * c(theta) * c(phi),
        );
        let rot = UnitQuaternion::from_euler_angles(phi, theta, psi).to_rotation_matrix().into_inner();
        Motion { rot, pos, vel, acc, omega }
    }
}

/// IMU sample times: `t0_ns + k * dt_ns`.
pub fn sample_time(t0_ns: u64, dt_ns: u64, k: u64) -> u64 {
    t0_ns + k * dt_ns
}

/// Seconds between two absolute times.
pub fn secs(t_ns: u64, t0_ns: u64) -> f64 {
    (t_ns as i64 - t0_ns as i64) as f64 * 1e-9
}

/// Upper and lower bounds of the two-sided `z`-quantile interval of a chi-square with `k` degrees
/// of freedom (Wilson-Hilferty; accurate to a fraction of a percent for k > 30).
pub fn chi2_interval(k: f64, z: f64) -> (f64, f64) {
    let a = 2.0 / (9.0 * k);
    let f = |z: f64| k * libm::pow(1.0 - a + z * libm::sqrt(a), 3.0);
    (f(-z), f(z))
}

/// Runs the jobs on scoped threads (the host's way), to check that work split into pieces
/// gives the one-thread result.
pub struct Threads(pub usize);

impl crate::parallel::Parallel for Threads {
    fn width(&self) -> usize {
        self.0
    }
    fn run(&self, jobs: &mut [crate::parallel::Job<'_>]) {
        extern crate std;
        std::thread::scope(|s| {
            for j in jobs.iter_mut() {
                s.spawn(j);
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::so3;

    #[test]
    fn helix_derivatives_match_finite_differences() {
        let h = Helix::standard();
        for t in [0.0, 0.37, 2.9, 7.3] {
            let m = h.at(t);
            let e = 1e-5;
            let (a, b) = (h.at(t - e), h.at(t + e));
            let om = so3::log(&(a.rot.transpose() * b.rot)) / (2.0 * e);
            assert!((om - m.omega).norm() < 1e-8, "{t}: {om:?} vs {:?}", m.omega);
            assert!(((b.pos - a.pos) / (2.0 * e) - m.vel).norm() < 1e-8);
            assert!(((b.vel - a.vel) / (2.0 * e) - m.acc).norm() < 1e-8);
        }
    }

    #[test]
    fn drive_derivatives_match_finite_differences() {
        let d = Drive::corridor();
        for t in [0.0, 1.7, 13.2] {
            let m = d.at(t);
            let e = 1e-5;
            let (a, b) = (d.at(t - e), d.at(t + e));
            let om = so3::log(&(a.rot.transpose() * b.rot)) / (2.0 * e);
            assert!((om - m.omega).norm() < 1e-8);
            assert!(((b.pos - a.pos) / (2.0 * e) - m.vel).norm() < 1e-8);
            assert!(((b.vel - a.vel) / (2.0 * e) - m.acc).norm() < 1e-8);
        }
    }

    #[test]
    fn rng_normals_have_unit_variance() {
        let mut r = Rng::new(1);
        let n = 20000;
        let (mut s, mut ss) = (0.0, 0.0);
        for _ in 0..n {
            let x = r.gauss();
            s += x;
            ss += x * x;
        }
        assert!((s / n as f64).abs() < 0.03);
        assert!((ss / n as f64 - 1.0).abs() < 0.03);
    }

    #[test]
    fn chi2_interval_is_sane() {
        // chi2(100): 0.5% and 99.5% quantiles are 67.33 and 140.17.
        let (lo, hi) = chi2_interval(100.0, 2.5758);
        assert!((lo - 67.33).abs() < 0.3 && (hi - 140.17).abs() < 0.3, "{lo} {hi}");
    }
}
