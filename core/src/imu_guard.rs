//! IMU outlier rejection: one bad sample must not end a run.
//!
//! A single accelerometer sample of 1000 m/s^2 integrated for 5 ms moves the estimate by metres
//! and the scans cannot pull it back in time; a single sample stamped a minute ahead makes every
//! later sample look old. The guard sits in front of the filter's queue and drops, counting
//! each kind:
//!
//! | sample | rule |
//! |---|---|
//! | a component beyond the sensor's full scale (`acc_full_scale`, `gyro_full_scale`) | dropped (`beyond_full_scale`); within 2 % of it counts as `saturated` but passes |
//! | far from the last good sample (`acc_step`, `gyro_step`) | held; dropped as a `spike` if the next sample is back near the last good one, else both pass (a real step) |
//! | stamped more than `max_forward_s` after the last good sample | held; dropped as a `stamp_jump` if the next sample is earlier than it, else both pass (a real gap) |
//!
//! The hold costs one sample of delay for the rare suspect sample only; good samples pass at once.

use crate::imu::ImuSample;

/// The guard's limits (0 disables a rule). Full scales are in the sensor's own units (m/s^2,
/// or g for IMUs that report in g, see [`crate::imu`]) and rad/s.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImuGuardConfig {
    /// Accelerometer full scale per axis (16 g for most MEMS IMUs), m/s^2.
    pub acc_full_scale: f32,
    /// Gyro full scale per axis (2000 deg/s for most MEMS IMUs), rad/s.
    pub gyro_full_scale: f32,
    /// A change of the specific force from the last good sample that makes a sample suspect, m/s^2.
    pub acc_step: f32,
    /// A change of the rate from the last good sample that makes a sample suspect, rad/s.
    pub gyro_step: f32,
    /// A stamp this far after the last good sample is held until the next one confirms it, s.
    pub max_forward_s: f32,
}

impl ImuGuardConfig {
    /// 16 g, 2000 deg/s; a 10 g or 20 rad/s jump in one sample is suspect; stamps 0.5 s ahead
    /// are confirmed before use.
    pub const DEFAULT: ImuGuardConfig = ImuGuardConfig {
        acc_full_scale: 16.0 * 9.80665,
        gyro_full_scale: 34.906_586,
        acc_step: 98.0,
        gyro_step: 20.0,
        max_forward_s: 0.5,
    };
    /// No rule at all.
    pub const OFF: ImuGuardConfig = ImuGuardConfig {
        acc_full_scale: 0.0,
        gyro_full_scale: 0.0,
        acc_step: 0.0,
        gyro_step: 0.0,
        max_forward_s: 0.0,
    };

    /// Whether every limit is finite and not negative.
    pub fn is_valid(&self) -> bool {
        [self.acc_full_scale, self.gyro_full_scale, self.acc_step, self.gyro_step, self.max_forward_s]
            .iter()
            .all(|v| v.is_finite() && *v >= 0.0)
    }
}

impl Default for ImuGuardConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// What the guard dropped and flagged.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImuGuardStats {
    /// Dropped: a component beyond the full scale.
    pub beyond_full_scale: u32,
    /// Passed, but a component within 2 % of the full scale (the sensor saturates).
    pub saturated: u32,
    /// Dropped: a lone sample far from both its neighbours.
    pub spikes: u32,
    /// Dropped: a lone sample stamped far after its neighbours.
    pub stamp_jumps: u32,
}

impl ImuGuardStats {
    /// Every sample dropped.
    pub fn dropped(&self) -> u32 {
        self.beyond_full_scale.saturating_add(self.spikes).saturating_add(self.stamp_jumps)
    }
}

/// What one [`ImuGuard::push`] released, oldest first (0, 1 or 2 samples).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Released {
    samples: [Option<ImuSample>; 2],
}

impl Iterator for Released {
    type Item = ImuSample;
    fn next(&mut self) -> Option<ImuSample> {
        match self.samples[0].take() {
            Some(s) => Some(s),
            None => self.samples[1].take(),
        }
    }
}

impl Released {
    fn one(s: ImuSample) -> Self {
        Released { samples: [Some(s), None] }
    }
    fn two(a: ImuSample, b: ImuSample) -> Self {
        Released { samples: [Some(a), Some(b)] }
    }
}

/// Why a sample is suspect.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Suspicion {
    Step,
    Forward,
}

/// The guard (see the module docs). `const`-constructible.
#[derive(Clone, Copy, Debug)]
pub struct ImuGuard {
    cfg: ImuGuardConfig,
    last: Option<ImuSample>,
    held: Option<(ImuSample, Suspicion)>,
    stats: ImuGuardStats,
}

fn max_abs_diff(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    (0..3).map(|k| (a[k] - b[k]).abs()).fold(0.0, f32::max)
}

fn max_abs(a: &[f32; 3]) -> f32 {
    a.iter().map(|v| v.abs()).fold(0.0, f32::max)
}

impl ImuGuard {
    /// A guard with `cfg`.
    pub const fn new(cfg: ImuGuardConfig) -> Self {
        ImuGuard {
            cfg,
            last: None,
            held: None,
            stats: ImuGuardStats { beyond_full_scale: 0, saturated: 0, spikes: 0, stamp_jumps: 0 },
        }
    }

    /// The counts so far.
    pub fn stats(&self) -> ImuGuardStats {
        self.stats
    }

    /// Forgets the last good sample and any held one (a restart on a new clock).
    pub fn reset(&mut self) {
        self.last = None;
        self.held = None;
    }

    /// Whether `s` is far from `near` by the step limits.
    fn stepped(&self, near: &ImuSample, s: &ImuSample) -> bool {
        let c = &self.cfg;
        (c.acc_step > 0.0 && max_abs_diff(&near.acc, &s.acc) > c.acc_step)
            || (c.gyro_step > 0.0 && max_abs_diff(&near.gyro, &s.gyro) > c.gyro_step)
    }

    fn forward(&self, near: &ImuSample, s: &ImuSample) -> bool {
        self.cfg.max_forward_s > 0.0
            && s.t_ns > near.t_ns
            && (s.t_ns - near.t_ns) as f64 * 1e-9 > f64::from(self.cfg.max_forward_s)
    }

    /// Takes one sample; returns the samples that may go on to the filter, oldest first.
    /// Non-finite values and time order are the queue's business ([`crate::imu::ImuQueue`]).
    pub fn push(&mut self, s: ImuSample) -> Released {
        let c = self.cfg;
        if !s.is_finite() {
            return Released::one(s);
        }
        let (a, g) = (max_abs(&s.acc), max_abs(&s.gyro));
        if (c.acc_full_scale > 0.0 && a > c.acc_full_scale)
            || (c.gyro_full_scale > 0.0 && g > c.gyro_full_scale)
        {
            self.stats.beyond_full_scale = self.stats.beyond_full_scale.saturating_add(1);
            return Released::default();
        }
        if (c.acc_full_scale > 0.0 && a >= 0.98 * c.acc_full_scale)
            || (c.gyro_full_scale > 0.0 && g >= 0.98 * c.gyro_full_scale)
        {
            self.stats.saturated = self.stats.saturated.saturating_add(1);
        }
        if let Some((h, why)) = self.held.take() {
            let last = self.last;
            let back = match (why, &last) {
                // A spike: the next sample is back near the last good one.
                (Suspicion::Step, Some(l)) => !self.stepped(l, &s) && self.stepped(&h, &s),
                // A wrong stamp: the next sample comes before the held one.
                (Suspicion::Forward, _) => s.t_ns < h.t_ns,
                (Suspicion::Step, None) => false,
            };
            if back {
                match why {
                    Suspicion::Step => self.stats.spikes = self.stats.spikes.saturating_add(1),
                    Suspicion::Forward => self.stats.stamp_jumps = self.stats.stamp_jumps.saturating_add(1),
                }
                return self.judge(s);
            }
            // Confirmed: the held sample was real; the new one is judged against it.
            self.last = Some(h);
            let mut out = self.judge(s);
            return match out.samples[0].take() {
                Some(n) => Released::two(h, n),
                None => Released::one(h),
            };
        }
        self.judge(s)
    }

    /// Passes `s` or holds it as suspect against the last good sample.
    fn judge(&mut self, s: ImuSample) -> Released {
        match self.last {
            Some(l) if self.forward(&l, &s) => {
                self.held = Some((s, Suspicion::Forward));
                Released::default()
            }
            Some(l) if s.t_ns > l.t_ns && self.stepped(&l, &s) => {
                self.held = Some((s, Suspicion::Step));
                Released::default()
            }
            _ => {
                if self.last.is_none_or(|l| s.t_ns > l.t_ns) {
                    self.last = Some(s);
                }
                Released::one(s)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec::Vec;

    use super::*;

    fn s(t_ms: u64, ax: f32, gz: f32) -> ImuSample {
        ImuSample { t_ns: t_ms * 1_000_000, gyro: [0.0, 0.0, gz], acc: [ax, 0.0, 9.81] }
    }

    fn run(g: &mut ImuGuard, xs: &[ImuSample]) -> Vec<u64> {
        xs.iter().flat_map(|x| g.push(*x)).map(|x| x.t_ns / 1_000_000).collect()
    }

    #[test]
    fn beyond_full_scale_is_dropped_and_near_it_is_flagged() {
        let mut g = ImuGuard::new(ImuGuardConfig::DEFAULT);
        let out = run(&mut g, &[s(0, 0.0, 0.0), s(5, 1000.0, 0.0), s(10, 0.0, 1000.0), s(15, 0.0, 0.0)]);
        assert_eq!(out, [0, 15]);
        assert_eq!(g.stats().beyond_full_scale, 2);
        // 15.8 g passes (a hard landing), flagged as saturated; so is 1990 deg/s.
        let out = run(&mut g, &[s(20, 155.0, 0.0), s(25, 155.0, 34.8), s(30, 150.0, 34.0)]);
        assert_eq!(out, [20, 25, 30]);
        assert_eq!(g.stats().saturated, 2);
        assert_eq!(g.stats().dropped(), 2);
    }

    #[test]
    fn a_lone_spike_within_full_scale_is_dropped_a_real_step_passes() {
        let mut g = ImuGuard::new(ImuGuardConfig::DEFAULT);
        // 120 m/s^2 for one sample amid 0: a spike.
        let out = run(&mut g, &[s(0, 0.0, 0.0), s(5, 120.0, 0.0), s(10, 1.0, 0.0), s(15, 1.0, 0.0)]);
        assert_eq!(out, [0, 10, 15]);
        assert_eq!(g.stats().spikes, 1);
        // A gyro spike the same way.
        let out = run(&mut g, &[s(20, 1.0, 25.0), s(25, 1.0, 0.1)]);
        assert_eq!(out, [25]);
        assert_eq!(g.stats().spikes, 2);
        // A step that stays (an impact, a spin-up): both pass, a sample late.
        let out = run(&mut g, &[s(30, 1.0, 21.0), s(35, 1.0, 21.5), s(40, 1.0, 21.0)]);
        assert_eq!(out, [30, 35, 40]);
        assert_eq!(g.stats().spikes, 2);
    }

    #[test]
    fn a_stamp_far_ahead_is_dropped_a_real_gap_passes() {
        let mut g = ImuGuard::new(ImuGuardConfig::DEFAULT);
        // One sample stamped a minute ahead amid 200 Hz samples.
        let out = run(&mut g, &[s(0, 0.0, 0.0), s(60_005, 0.0, 0.0), s(10, 0.0, 0.0), s(15, 0.0, 0.0)]);
        assert_eq!(out, [0, 10, 15]);
        assert_eq!(g.stats().stamp_jumps, 1);
        // A real 2 s gap: the samples after it continue from its time.
        let out = run(&mut g, &[s(2015, 0.0, 0.0), s(2020, 0.0, 0.0)]);
        assert_eq!(out, [2015, 2020]);
        assert_eq!(g.stats().stamp_jumps, 1);
    }

    #[test]
    fn off_passes_everything_and_bad_limits_are_invalid() {
        let mut g = ImuGuard::new(ImuGuardConfig::OFF);
        let out = run(&mut g, &[s(0, 0.0, 0.0), s(5, 1e6, 1e6), s(60_000, 0.0, 0.0), s(10, 0.0, 0.0)]);
        assert_eq!(out, [0, 5, 60_000, 10]);
        assert_eq!(g.stats(), ImuGuardStats::default());
        assert!(ImuGuardConfig::DEFAULT.is_valid());
        assert!(!ImuGuardConfig { acc_step: f32::NAN, ..ImuGuardConfig::DEFAULT }.is_valid());
        assert!(!ImuGuardConfig { gyro_full_scale: -1.0, ..ImuGuardConfig::DEFAULT }.is_valid());
    }
}
