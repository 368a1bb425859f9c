//! Standing still: when the platform stands, say so to the filter (zero-velocity and
//! zero-rate updates).
//!
//! At a stand the scans alone cannot tell a small velocity from none where the scene leaves a
//! direction unobserved (a corridor's axis, an open field's plane): the filter's velocity and
//! the accelerometer bias along it are then set by chance, and the drift that follows is paid
//! for when the platform moves on. A vehicle waiting at a junction, or the stand at the start
//! before a drive, is exactly where the IMU knows better: the velocity is zero, and the gyro's
//! mean is its bias.
//!
//! The IMU alone cannot tell a stand from a steady straight run (neither accelerates nor
//! turns; a simulator has no vibration), so a stand needs both:
//! - the IMU quiet over the scan's interval: the samples' per-axis standard deviations of
//!   rate and specific force below [`StandstillConfig::max_gyro_std`] and `max_acc_std`, the mean
//!   rate (less the filter's gyro bias) below `max_rate`, and the mean specific force, turned
//!   into the world by the filter's attitude, within `max_acc_error` of gravity (the
//!   acceleration: a magnitude test alone would pass a gentle horizontal acceleration, which
//!   changes `|f|` by only `a²/2g`, and pin the velocity of a vehicle pulling away);
//! - the filter's own velocity after the scan's update zero within four of its standard
//!   deviations and below `max_speed` (the LiDAR sees no motion), and likewise the mean rate
//!   its bias (a slow turn, a hover's slow yaw, is not a bias).
//!
//! Both must hold for `min_duration_s` in a row (a handheld sensor passes through zero
//! velocity when it turns back, for an instant only).
//!
//! Then [`crate::eskf::Eskf::zero_velocity`] and [`crate::eskf::Eskf::zero_rate`] run once per
//! scan, after its update.

use nalgebra::Vector3;

use crate::eskf::{Eskf, idx};
use crate::imu::ImuSample;

/// When the platform counts as standing, and how firmly the updates pin it.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StandstillConfig {
    /// Run the zero-velocity and zero-rate updates at all (on by default since 2026-12-07:
    /// with the block k-NN they halve the corridor's drift along its axis; see
    /// `docs/estimation.md` for what they give on the simulated scenarios).
    pub enabled: bool,
    /// Largest per-axis standard deviation of the rate over a scan's samples, rad/s.
    pub max_gyro_std: f64,
    /// Largest per-axis standard deviation of the specific force, m/s².
    pub max_acc_std: f64,
    /// Largest mean rate less the gyro bias, rad/s.
    pub max_rate: f64,
    /// Largest acceleration in the world (the mean specific force less the accelerometer
    /// bias, turned by the attitude, plus gravity), m/s².
    pub max_acc_error: f64,
    /// Largest speed of the filter after the scan's update, m/s.
    pub max_speed: f64,
    /// Standing this long in a row before the updates start, seconds.
    pub min_duration_s: f64,
    /// Standard deviation of the zero-velocity measurement, m/s.
    pub velocity_std: f64,
    /// Standard deviation of the zero-rate measurement beyond the mean's own noise, rad/s.
    pub rate_std: f64,
    /// Fewest samples in a scan's interval to judge it.
    pub min_samples: u32,
}

impl StandstillConfig {
    /// The defaults documented on each field.
    pub const DEFAULT: Self = Self {
        enabled: true,
        max_gyro_std: 0.02,
        max_acc_std: 0.3,
        max_rate: 0.02,
        max_acc_error: 0.05,
        max_speed: 0.1,
        min_duration_s: 0.5,
        velocity_std: 0.005,
        rate_std: 1e-4,
        min_samples: 5,
    };
}

impl Default for StandstillConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Sums of one interval's IMU samples.
#[derive(Clone, Copy, Debug, Default)]
pub struct ImuWindow {
    n: u32,
    gyro: [f64; 3],
    gyro2: [f64; 3],
    acc: [f64; 3],
    acc2: [f64; 3],
}

impl ImuWindow {
    /// Forgets every sample.
    pub fn clear(&mut self) {
        *self = Self::default();
    }

    /// Adds one sample (non-finite ones are left out).
    pub fn push(&mut self, s: &ImuSample) {
        if !s.is_finite() {
            return;
        }
        self.n = self.n.saturating_add(1);
        for k in 0..3 {
            let (g, a) = (f64::from(s.gyro[k]), f64::from(s.acc[k]));
            self.gyro[k] += g;
            self.gyro2[k] += g * g;
            self.acc[k] += a;
            self.acc2[k] += a * a;
        }
    }

    /// Samples added.
    pub fn len(&self) -> u32 {
        self.n
    }

    /// Whether no sample was added.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The mean rate, rad/s.
    pub fn mean_gyro(&self) -> Vector3<f64> {
        let n = f64::from(self.n.max(1));
        Vector3::new(self.gyro[0] / n, self.gyro[1] / n, self.gyro[2] / n)
    }

    /// The mean specific force (unscaled), m/s² or g.
    pub fn mean_acc(&self) -> Vector3<f64> {
        let n = f64::from(self.n.max(1));
        Vector3::new(self.acc[0] / n, self.acc[1] / n, self.acc[2] / n)
    }

    fn max_std(sum: &[f64; 3], sum2: &[f64; 3], n: f64, scale: f64) -> f64 {
        (0..3)
            .map(|k| {
                let m = sum[k] / n;
                crate::math::sqrt(((sum2[k] / n - m * m) * scale * scale).max(0.0))
            })
            .fold(0.0f64, f64::max)
    }

    /// Whether the platform stands (module docs) by these samples and the filter `f` after
    /// the scan's update: the IMU quiet, the mean rate its bias and the velocity zero within
    /// four standard deviations of what the filter and the samples know (and within the
    /// absolute bounds), the world acceleration nil.
    pub fn stands(&self, cfg: &StandstillConfig, f: &Eskf) -> bool {
        if self.n < cfg.min_samples.max(2) {
            return false;
        }
        let (x, p) = (f.state(), f.covariance());
        let n = f64::from(self.n);
        let scale = f.acc_scale();
        let gyro_std = Self::max_std(&self.gyro, &self.gyro2, n, 1.0);
        let acc_std = Self::max_std(&self.acc, &self.acc2, n, scale);
        if gyro_std > cfg.max_gyro_std || acc_std > cfg.max_acc_std {
            return false;
        }
        let rate = self.mean_gyro() - x.bg;
        let mean_var = gyro_std * gyro_std / n + cfg.rate_std * cfg.rate_std;
        let rate_ok = (0..3).all(|k| rate[k] * rate[k] <= 16.0 * (mean_var + p[(idx::BG + k, idx::BG + k)]));
        let vel_ok = (0..3).all(|k| {
            x.vel[k] * x.vel[k]
                <= 16.0 * (p[(idx::VEL + k, idx::VEL + k)] + cfg.velocity_std * cfg.velocity_std)
        });
        let acc = x.rot * (self.mean_acc() * scale - x.ba) + x.grav.vec();
        rate_ok
            && vel_ok
            && rate.norm() <= cfg.max_rate
            && x.vel.norm() <= cfg.max_speed
            && acc.norm() <= cfg.max_acc_error
    }

    /// The variance of the mean rate as a bias measurement: the samples' spread over their
    /// count, with `cfg.rate_std` for what the mean does not see (vibration, the earth's rate).
    pub fn rate_variance(&self, cfg: &StandstillConfig) -> f64 {
        let n = f64::from(self.n.max(2));
        let spread = Self::max_std(&self.gyro, &self.gyro2, n, 1.0);
        spread * spread / n + cfg.rate_std * cfg.rate_std
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::UnitQuaternion;

    use super::*;
    use crate::eskf::{EskfConfig, State, StateCov};
    use crate::so3::S2;

    fn sample(t: u64, gyro: [f32; 3], acc: [f32; 3]) -> ImuSample {
        ImuSample { t_ns: t, gyro, acc }
    }

    fn level(bg: Vector3<f64>) -> Eskf {
        level_at(bg, UnitQuaternion::identity(), 1.0)
    }

    fn level_at(bg: Vector3<f64>, rot: UnitQuaternion<f64>, scale: f64) -> Eskf {
        let x = State {
            rot: UnitQuaternion::identity(),
            pos: Vector3::zeros(),
            ext_rot: UnitQuaternion::identity(),
            ext_pos: Vector3::zeros(),
            vel: Vector3::zeros(),
            bg,
            ba: Vector3::zeros(),
            grav: S2::new(&Vector3::new(0.0, 0.0, -9.81), 9.81),
        };
        let mut p = StateCov::zeros();
        for k in 0..3 {
            p[(idx::BG + k, idx::BG + k)] = 1e-8;
            p[(idx::VEL + k, idx::VEL + k)] = 1e-4;
        }
        let mut x = x;
        x.rot = rot;
        Eskf::from_state(EskfConfig::default(), x, p, 0, None, scale)
    }

    fn steady(gyro: [f32; 3], acc: [f32; 3]) -> ImuWindow {
        let mut w = ImuWindow::default();
        for i in 0..20u64 {
            w.push(&sample(i, gyro, acc));
        }
        w
    }

    #[test]
    fn a_quiet_imu_is_quiet_and_motion_is_not() {
        let cfg = StandstillConfig::default();
        let bg = Vector3::new(0.001, -0.002, 0.0005);
        let x = level(bg);
        let mut w = ImuWindow::default();
        for i in 0..20u64 {
            let e = if i % 2 == 0 { 0.004f32 } else { -0.004 };
            w.push(&sample(i, [0.001 + e, -0.002 - e, 0.0005], [e * 5.0, -e * 5.0, 9.81 + e * 5.0]));
        }
        assert_eq!(w.len(), 20);
        assert!(w.stands(&cfg, &x));
        assert!((w.mean_gyro() - bg).norm() < 1e-7);
        // In g units with the initialiser's scale.
        let x0 = level(Vector3::zeros());
        let g = steady([0.0; 3], [0.0, 0.0, 1.0]);
        assert!(g.stands(&cfg, &level_at(Vector3::zeros(), UnitQuaternion::identity(), 9.81)));
        assert!(!g.stands(&cfg, &x0), "1 g read as 1 m/s² is not gravity");
        // Tilted by 10 degrees, the attitude knows it: still quiet.
        let tilted = level_at(Vector3::zeros(), UnitQuaternion::from_euler_angles(0.1745, 0.0, 0.0), 1.0);
        let f = tilted.state().rot.inverse() * Vector3::new(0.0, 0.0, 9.81);
        assert!(steady([0.0; 3], [f.x as f32, f.y as f32, f.z as f32]).stands(&cfg, &tilted));
        // A hover's slow yaw (0.005 rad/s, within the absolute bound) is not the gyro's bias.
        assert!(!steady([0.0, 0.0, 0.005], [0.0, 0.0, 9.81]).stands(&cfg, &x0));
        // Drifting at 0.05 m/s with the velocity known to 0.01 m/s is not standing.
        let mut drifting = level(Vector3::zeros());
        let mut xd = *drifting.state();
        xd.vel = Vector3::new(0.05, 0.0, 0.0);
        drifting = Eskf::from_state(EskfConfig::default(), xd, *drifting.covariance(), 0, None, 1.0);
        assert!(!steady([0.0; 3], [0.0, 0.0, 9.81]).stands(&cfg, &drifting));

        // Turning slowly on the spot: the mean rate gives it away.
        assert!(!steady([0.0, 0.0, 0.05], [0.0, 0.0, 9.81]).stands(&cfg, &x0));
        // Braking.
        assert!(!steady([0.0; 3], [-2.0, 0.0, 9.81]).stands(&cfg, &x0));
        // Pulling away gently: |f| changes by 2 mm/s² only, the world acceleration by 0.2 m/s².
        let gentle = steady([0.0; 3], [0.2, 0.0, 9.81]);
        assert!((gentle.mean_acc().norm() - 9.81).abs() < 0.003);
        assert!(!gentle.stands(&cfg, &x0));
        // Shaking: the spread.
        let mut shake = ImuWindow::default();
        for i in 0..20u64 {
            let e = if i % 2 == 0 { 1.0f32 } else { -1.0 };
            shake.push(&sample(i, [0.0; 3], [e, 0.0, 9.81]));
        }
        assert!(!shake.stands(&cfg, &x0));
        // Too few samples to judge.
        let mut few = ImuWindow::default();
        few.push(&sample(0, [0.0; 3], [0.0, 0.0, 9.81]));
        assert!(!few.stands(&cfg, &x0));
        // Non-finite samples are left out.
        few.push(&sample(1, [f32::NAN, 0.0, 0.0], [0.0, 0.0, 9.81]));
        assert_eq!(few.len(), 1);
    }
}
