//! IMU measurements: the sample type, the noise model, the ingest queue with its rules for bad
//! timestamps, and the initialisation (gravity direction, gyro bias, accelerometer units).
//!
//! # Timestamp rules (one place, each tested)
//!
//! | case | where | rule |
//! |---|---|---|
//! | non-finite gyro or acc | [`ImuQueue::push`], [`ImuInitializer::push`], `Eskf::predict` | dropped, counted |
//! | `t` earlier than the last accepted sample (reversal) | queue, initialiser | dropped, counted |
//! | `t` equal to the last accepted sample (duplicate) | queue, initialiser | dropped, counted |
//! | queue full | queue | the oldest sample is overwritten, counted |
//! | spacing above `max_gap_s` | `Eskf::predict` | the interval is integrated holding the previous sample (no midpoint with the far sample), the process noise is inflated by `gap_inflation`, flagged `GAP` |
//! | the filter's time stepping by more than `max_hold_s` (a forward jump) | `Eskf::predict`, `Eskf::predict_to` | not integrated: the state keeps its values, its time moves to the sample, flagged `JUMP`; the odometry re-initialises |
//! | spacing above `max_gap_s` during initialisation | initialiser | the window restarts, counted |
//!
//! # Initialisation
//!
//! The world frame is gravity-aligned (z up) with the initial yaw 0, unlike the reference whose
//! world is the first IMU frame. [`ImuInitializer`] keeps running sums over a tumbling window (no
//! sample storage) and decides, once the window spans `window_s`:
//!
//! 1. units: the mean specific-force magnitude must be within `max_acc_magnitude_error` of
//!    gravity in m/s^2, or of 1 in units of g (then every accelerometer sample is scaled by
//!    [`STANDARD_GRAVITY`]); otherwise `Waiting(AccelMagnitude)`;
//! 2. stationary start: the per-axis standard deviations of gyro and acc below `max_gyro_std` and
//!    `max_acc_std` and the mean rate below `max_gyro_bias`: the gyro bias is the mean rate, roll
//!    and pitch come from the mean specific force, and the part of its magnitude that differs from
//!    gravity becomes the initial accelerometer bias along the vertical;
//! 3. moving start (if `allow_moving_start`): not stationary, but the mean specific force agrees
//!    with gravity within `rough_acc_tolerance` and the RMS rate is below `rough_max_gyro_rms`:
//!    a rough start with zero gyro bias and larger initial uncertainties (`rough == true`);
//! 4. otherwise `Waiting(Moving | Rotating)` and the window restarts.

use nalgebra::{UnitQuaternion, Vector3};

/// One IMU sample in the IMU frame, as every source (serial frames, Ouster IMU packets, CSV)
/// delivers it to the core.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImuSample {
    /// Absolute time, nanoseconds, on the same clock as the scans' `start_ns`.
    pub t_ns: u64,
    /// Angular rate, rad/s.
    pub gyro: [f32; 3],
    /// Specific force, m/s^2 (IMUs that report in g are detected at initialisation).
    pub acc: [f32; 3],
}

impl ImuSample {
    /// Whether every component is finite.
    pub fn is_finite(&self) -> bool {
        self.gyro.iter().chain(self.acc.iter()).all(|v| v.is_finite())
    }

    /// The angular rate as an f64 vector.
    #[inline]
    pub fn gyro_vec(&self) -> Vector3<f64> {
        Vector3::new(self.gyro[0] as f64, self.gyro[1] as f64, self.gyro[2] as f64)
    }

    /// The specific force as an f64 vector (in the sensor's units).
    #[inline]
    pub fn acc_vec(&self) -> Vector3<f64> {
        Vector3::new(self.acc[0] as f64, self.acc[1] as f64, self.acc[2] as f64)
    }
}

/// 1 g in m/s^2 (the unit of IMUs that report in g).
pub const STANDARD_GRAVITY: f64 = 9.80665;

/// Continuous-time IMU noise densities, in datasheet units. The filter discretises them
/// physically: over an interval `dt` a white-noise density `σ` adds `σ² dt` to the variance of
/// its integral (see `eskf`). (The reference instead takes per-sample variances from its yaml and
/// scales them by `dt²`; a datasheet density `σ` corresponds to a per-sample variance of
/// `σ² / dt_sample`.)
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImuNoise {
    /// Gyro white noise (angle random walk), rad/s/√Hz.
    pub gyro: f64,
    /// Accelerometer white noise (velocity random walk), m/s^2/√Hz.
    pub acc: f64,
    /// Gyro bias random walk, rad/s^2/√Hz.
    pub gyro_bias_walk: f64,
    /// Accelerometer bias random walk, m/s^3/√Hz.
    pub acc_bias_walk: f64,
}

impl Default for ImuNoise {
    /// About ten times the datasheet densities of an industrial MEMS IMU (the margin covers
    /// vibration and unmodelled scale and misalignment errors).
    fn default() -> Self {
        Self { gyro: 2e-3, acc: 2e-2, gyro_bias_walk: 2e-5, acc_bias_walk: 5e-4 }
    }
}

// ---------------------------------------------------------------------------------------------
// Ingest queue
// ---------------------------------------------------------------------------------------------

/// Why a sample was not queued.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ImuDrop {
    /// Earlier than the last accepted sample.
    Reversed,
    /// The same time as the last accepted sample.
    Duplicate,
    /// A gyro or accelerometer component is NaN or infinite.
    NonFinite,
    /// A component beyond the sensor's full scale ([`crate::imu_guard`]).
    BeyondFullScale,
    /// Put before samples already queued when the estimated time offset moved back
    /// ([`crate::time_offset`]).
    Realigned,
}

/// What [`ImuQueue::push`] did with a sample.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ImuPush {
    /// Queued.
    Accepted,
    /// Queued; the queue was full, so its oldest sample was overwritten (counted).
    AcceptedOverwritingOldest,
    /// Not queued (counted).
    Dropped(ImuDrop),
    /// Held by the outlier guard until the next sample decides (then queued or dropped, and
    /// counted in [`crate::imu_guard::ImuGuardStats`]).
    Held,
}

/// Counters of an [`ImuQueue`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImuQueueStats {
    /// Samples queued.
    pub accepted: u32,
    /// Dropped: earlier than the last accepted sample.
    pub reversed: u32,
    /// Dropped: same time as the last accepted sample.
    pub duplicate: u32,
    /// Dropped: non-finite values.
    pub non_finite: u32,
    /// Oldest samples overwritten because the queue was full.
    pub overwritten: u32,
}

/// A fixed-capacity FIFO of IMU samples in strictly increasing time order: reversed,
/// duplicate and non-finite samples are dropped and counted at the door, so the consumer (the
/// filter) only sees increasing times. `const`-constructible, so it can be a `static`.
#[derive(Debug)]
pub struct ImuQueue<const N: usize> {
    buf: heapless::Deque<ImuSample, N>,
    last_t_ns: Option<u64>,
    stats: ImuQueueStats,
}

impl<const N: usize> Default for ImuQueue<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> ImuQueue<N> {
    /// An empty queue.
    pub const fn new() -> Self {
        Self {
            buf: heapless::Deque::new(),
            last_t_ns: None,
            stats: ImuQueueStats { accepted: 0, reversed: 0, duplicate: 0, non_finite: 0, overwritten: 0 },
        }
    }

    /// Applies the ingest rules (module docs) and queues the sample if it passes.
    pub fn push(&mut self, s: ImuSample) -> ImuPush {
        if !s.is_finite() {
            self.stats.non_finite = self.stats.non_finite.saturating_add(1);
            return ImuPush::Dropped(ImuDrop::NonFinite);
        }
        if let Some(last) = self.last_t_ns {
            if s.t_ns < last {
                self.stats.reversed = self.stats.reversed.saturating_add(1);
                return ImuPush::Dropped(ImuDrop::Reversed);
            }
            if s.t_ns == last {
                self.stats.duplicate = self.stats.duplicate.saturating_add(1);
                return ImuPush::Dropped(ImuDrop::Duplicate);
            }
        }
        self.last_t_ns = Some(s.t_ns);
        self.stats.accepted = self.stats.accepted.saturating_add(1);
        if self.buf.is_full() {
            self.buf.pop_front();
            self.stats.overwritten = self.stats.overwritten.saturating_add(1);
            // Cannot fail: one slot was just freed.
            let _ = self.buf.push_back(s);
            return ImuPush::AcceptedOverwritingOldest;
        }
        let _ = self.buf.push_back(s);
        ImuPush::Accepted
    }

    /// Removes and returns the oldest sample if its time is at most `t_ns`.
    pub fn pop_until(&mut self, t_ns: u64) -> Option<ImuSample> {
        match self.buf.front() {
            Some(s) if s.t_ns <= t_ns => self.buf.pop_front(),
            _ => None,
        }
    }

    /// The oldest queued sample.
    pub fn front(&self) -> Option<&ImuSample> {
        self.buf.front()
    }

    /// Time of the newest accepted sample (also after it was popped).
    pub fn last_time_ns(&self) -> Option<u64> {
        self.last_t_ns
    }

    /// Number of queued samples.
    pub fn len(&self) -> usize {
        self.buf.len()
    }

    /// Whether nothing is queued.
    pub fn is_empty(&self) -> bool {
        self.buf.is_empty()
    }

    /// Capacity `N`.
    pub const fn capacity(&self) -> usize {
        N
    }

    /// The counters.
    pub fn stats(&self) -> ImuQueueStats {
        self.stats
    }

    /// Empties the queue and forgets the last time (after a re-initialisation); keeps counters.
    pub fn clear(&mut self) {
        self.buf.clear();
        self.last_t_ns = None;
    }
}

// ---------------------------------------------------------------------------------------------
// Initialisation
// ---------------------------------------------------------------------------------------------

/// Settings of [`ImuInitializer`].
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImuInitConfig {
    /// Local gravity magnitude, m/s^2 (the length of the filter's gravity vector).
    pub gravity: f64,
    /// The window must span at least this long, seconds.
    pub window_s: f64,
    /// ... and hold at least this many samples.
    pub min_samples: u32,
    /// A spacing above this restarts the window, seconds.
    pub max_gap_s: f64,
    /// Largest allowed difference between the mean specific-force magnitude and gravity (in
    /// m/s^2, after unit detection).
    pub max_acc_magnitude_error: f64,
    /// Stationary: largest per-axis gyro standard deviation, rad/s.
    pub max_gyro_std: f64,
    /// Stationary: largest per-axis accelerometer standard deviation, m/s^2.
    pub max_acc_std: f64,
    /// Stationary: largest mean rate that is still taken for a gyro bias, rad/s.
    pub max_gyro_bias: f64,
    /// Accept a rough start while moving (rules in the module docs).
    pub allow_moving_start: bool,
    /// Moving start: largest difference between the mean specific-force magnitude and gravity.
    pub rough_acc_tolerance: f64,
    /// Moving start: largest RMS rate, rad/s.
    pub rough_max_gyro_rms: f64,
}

impl Default for ImuInitConfig {
    fn default() -> Self {
        Self {
            gravity: 9.81,
            window_s: 1.0,
            min_samples: 20,
            max_gap_s: 0.1,
            max_acc_magnitude_error: 1.0,
            max_gyro_std: 0.02,
            max_acc_std: 0.3,
            max_gyro_bias: 0.05,
            allow_moving_start: true,
            rough_acc_tolerance: 0.3,
            rough_max_gyro_rms: 0.1,
        }
    }
}

/// Why the initialiser is still waiting.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum WaitReason {
    /// The window is not long enough yet.
    Collecting {
        /// Samples in the window.
        samples: u32,
        /// Time the window spans, seconds.
        span_s: f32,
    },
    /// The mean specific force is neither gravity in m/s^2 nor 1 g.
    AccelMagnitude {
        /// Its magnitude, in the sensor's units.
        mean_norm: f32,
    },
    /// The IMU moves too much for a stationary start and not smoothly enough for a rough one.
    Moving {
        /// Largest per-axis gyro standard deviation, rad/s.
        gyro_std: f32,
        /// Largest per-axis accelerometer standard deviation, m/s^2.
        acc_std: f32,
    },
    /// Steady but turning: the mean rate is too large for a gyro bias.
    Rotating {
        /// Magnitude of the mean rate, rad/s.
        mean_rate: f32,
    },
}

/// The result of a successful initialisation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuInit {
    /// Time of the last sample of the window; the filter starts here.
    pub t_ns: u64,
    /// The last sample of the window, unscaled (the filter's first held input).
    pub last_sample: ImuSample,
    /// World-from-IMU rotation: roll and pitch from gravity, yaw 0.
    pub rotation: UnitQuaternion<f64>,
    /// Gyro bias, rad/s.
    pub gyro_bias: Vector3<f64>,
    /// Accelerometer bias, m/s^2 (along the vertical only: the magnitude mismatch).
    pub acc_bias: Vector3<f64>,
    /// Factor applied to every accelerometer sample: 1, or [`STANDARD_GRAVITY`] for g units.
    pub acc_scale: f64,
    /// Gravity magnitude, m/s^2.
    pub gravity: f64,
    /// A moving start: biases and attitude are rough.
    pub rough: bool,
    /// Samples in the window.
    pub samples: u32,
    /// Largest per-axis gyro standard deviation in the window, rad/s.
    pub gyro_std: f64,
    /// Largest per-axis accelerometer standard deviation in the window (scaled), m/s^2.
    pub acc_std: f64,
    /// RMS rate in the window, rad/s.
    pub gyro_rms: f64,
}

/// The initialiser's answer to each sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum InitStatus {
    /// Not initialised yet, and why.
    Waiting(WaitReason),
    /// Initialised.
    Ready(ImuInit),
}

/// Counters of an [`ImuInitializer`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct InitStats {
    /// Samples dropped: earlier than or equal to the previous one.
    pub out_of_order: u32,
    /// Samples dropped: non-finite.
    pub non_finite: u32,
    /// Windows restarted after a gap.
    pub gap_restarts: u32,
    /// Windows rejected (motion or magnitude).
    pub rejected_windows: u32,
}

/// Running sums over a window, shifted by the first sample for numerical stability.
#[derive(Clone, Copy, Debug, Default)]
struct Sums {
    n: u32,
    t0: u64,
    shift_g: Vector3<f64>,
    shift_a: Vector3<f64>,
    sg: Vector3<f64>,
    sa: Vector3<f64>,
    sgg: Vector3<f64>,
    saa: Vector3<f64>,
    /// Σ |ω|² (unshifted) for the RMS rate.
    sw2: f64,
}

/// IMU initialisation from a window of samples (rules in the module docs). Holds no samples:
/// only running sums.
#[derive(Clone, Copy, Debug)]
pub struct ImuInitializer {
    cfg: ImuInitConfig,
    sums: Sums,
    last: Option<ImuSample>,
    stats: InitStats,
}

impl ImuInitializer {
    /// A fresh initialiser.
    pub fn new(cfg: ImuInitConfig) -> Self {
        Self { cfg, sums: Sums::default(), last: None, stats: InitStats::default() }
    }

    /// The counters.
    pub fn stats(&self) -> InitStats {
        self.stats
    }

    /// Forgets the window (keeps counters).
    pub fn reset(&mut self) {
        self.sums = Sums::default();
        self.last = None;
    }

    fn restart_window(&mut self) {
        self.sums = Sums::default();
    }

    /// Feeds one sample.
    pub fn push(&mut self, s: &ImuSample) -> InitStatus {
        if !s.is_finite() {
            self.stats.non_finite = self.stats.non_finite.saturating_add(1);
            return InitStatus::Waiting(self.collecting());
        }
        if let Some(last) = self.last {
            if s.t_ns <= last.t_ns {
                self.stats.out_of_order = self.stats.out_of_order.saturating_add(1);
                return InitStatus::Waiting(self.collecting());
            }
            if (s.t_ns - last.t_ns) as f64 * 1e-9 > self.cfg.max_gap_s {
                self.stats.gap_restarts = self.stats.gap_restarts.saturating_add(1);
                self.restart_window();
            }
        }
        self.last = Some(*s);
        let g = s.gyro_vec();
        let a = s.acc_vec();
        let w = &mut self.sums;
        if w.n == 0 {
            w.t0 = s.t_ns;
            w.shift_g = g;
            w.shift_a = a;
        }
        w.n += 1;
        let dg = g - w.shift_g;
        let da = a - w.shift_a;
        w.sg += dg;
        w.sa += da;
        w.sgg += dg.component_mul(&dg);
        w.saa += da.component_mul(&da);
        w.sw2 += g.norm_squared();

        let span_s = (s.t_ns - w.t0) as f64 * 1e-9;
        if w.n < self.cfg.min_samples.max(2) || span_s < self.cfg.window_s {
            return InitStatus::Waiting(self.collecting());
        }
        let out = self.evaluate(s);
        if let InitStatus::Waiting(_) = out {
            self.stats.rejected_windows = self.stats.rejected_windows.saturating_add(1);
            self.restart_window();
        }
        out
    }

    fn collecting(&self) -> WaitReason {
        let span = match self.last {
            Some(l) if self.sums.n > 0 => (l.t_ns - self.sums.t0) as f64 * 1e-9,
            _ => 0.0,
        };
        WaitReason::Collecting { samples: self.sums.n, span_s: span as f32 }
    }

    fn evaluate(&self, last: &ImuSample) -> InitStatus {
        let c = &self.cfg;
        let w = &self.sums;
        let n = w.n as f64;
        let mean_g = w.shift_g + w.sg / n;
        let mean_a_raw = w.shift_a + w.sa / n;
        let var = |s: &Vector3<f64>, ss: &Vector3<f64>| {
            let m = s / n;
            (ss / n - m.component_mul(&m)).map(|v| v.max(0.0))
        };
        let std_g = crate::math::sqrt(var(&w.sg, &w.sgg).max());
        let std_a_raw = crate::math::sqrt(var(&w.sa, &w.saa).max());
        let gyro_rms = crate::math::sqrt(w.sw2 / n);

        // 1. Units.
        let norm_raw = mean_a_raw.norm();
        let acc_scale = if (norm_raw - c.gravity).abs() <= c.max_acc_magnitude_error {
            1.0
        } else if (norm_raw * STANDARD_GRAVITY - c.gravity).abs() <= c.max_acc_magnitude_error {
            STANDARD_GRAVITY
        } else {
            return InitStatus::Waiting(WaitReason::AccelMagnitude { mean_norm: norm_raw as f32 });
        };
        let mean_a = mean_a_raw * acc_scale;
        let std_a = std_a_raw * acc_scale;
        let norm = mean_a.norm();
        let up = mean_a / norm;

        let stationary = std_g <= c.max_gyro_std && std_a <= c.max_acc_std;
        let (rough, gyro_bias, acc_bias) = if stationary && mean_g.norm() <= c.max_gyro_bias {
            (false, mean_g, up * (norm - c.gravity))
        } else if c.allow_moving_start
            && (norm - c.gravity).abs() <= c.rough_acc_tolerance
            && gyro_rms <= c.rough_max_gyro_rms
        {
            (true, Vector3::zeros(), Vector3::zeros())
        } else if stationary {
            return InitStatus::Waiting(WaitReason::Rotating { mean_rate: mean_g.norm() as f32 });
        } else {
            return InitStatus::Waiting(WaitReason::Moving { gyro_std: std_g as f32, acc_std: std_a as f32 });
        };

        InitStatus::Ready(ImuInit {
            t_ns: last.t_ns,
            last_sample: *last,
            rotation: gravity_aligned_rotation(&up),
            gyro_bias,
            acc_bias,
            acc_scale,
            gravity: c.gravity,
            rough,
            samples: w.n,
            gyro_std: std_g,
            acc_std: std_a,
            gyro_rms,
        })
    }
}

/// The world-from-IMU rotation with yaw 0 that turns the body-frame "up" direction `up` (the
/// specific force at rest, unit length) into world +z: `R = Ry(pitch) Rx(roll)` (ZYX Euler angles
/// with yaw 0).
pub fn gravity_aligned_rotation(up: &Vector3<f64>) -> UnitQuaternion<f64> {
    let roll = libm::atan2(up.y, up.z);
    let pitch = libm::atan2(-up.x, crate::math::sqrt(up.y * up.y + up.z * up.z));
    UnitQuaternion::from_euler_angles(roll, pitch, 0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testutil::Rng;

    fn sample(t_ns: u64, gyro: [f32; 3], acc: [f32; 3]) -> ImuSample {
        ImuSample { t_ns, gyro, acc }
    }

    #[test]
    fn queue_drops_reversed_duplicate_and_non_finite_and_counts_them() {
        let mut q = ImuQueue::<4>::new();
        let a = [0.0, 0.0, 9.81];
        assert_eq!(q.push(sample(100, [0.0; 3], a)), ImuPush::Accepted);
        assert_eq!(q.push(sample(100, [1.0; 3], a)), ImuPush::Dropped(ImuDrop::Duplicate));
        assert_eq!(q.push(sample(50, [0.0; 3], a)), ImuPush::Dropped(ImuDrop::Reversed));
        assert_eq!(q.push(sample(200, [f32::NAN, 0.0, 0.0], a)), ImuPush::Dropped(ImuDrop::NonFinite));
        assert_eq!(
            q.push(sample(300, [0.0; 3], [0.0, f32::INFINITY, 0.0])),
            ImuPush::Dropped(ImuDrop::NonFinite)
        );
        assert_eq!(q.push(sample(200, [0.0; 3], a)), ImuPush::Accepted);
        let st = q.stats();
        assert_eq!((st.accepted, st.duplicate, st.reversed, st.non_finite), (2, 1, 1, 2));
        assert_eq!(q.len(), 2);
        // The queue only ever holds increasing times.
        assert_eq!(q.pop_until(150).map(|s| s.t_ns), Some(100));
        assert_eq!(q.pop_until(150), None);
        assert_eq!(q.pop_until(200).map(|s| s.t_ns), Some(200));
        assert!(q.is_empty());
        // The last time is remembered after popping: an old sample is still a reversal.
        assert_eq!(q.push(sample(150, [0.0; 3], a)), ImuPush::Dropped(ImuDrop::Reversed));
    }

    #[test]
    fn queue_overwrites_oldest_when_full_and_counts() {
        let mut q = ImuQueue::<3>::new();
        for k in 1..=3u64 {
            assert_eq!(q.push(sample(k, [0.0; 3], [0.0; 3])), ImuPush::Accepted);
        }
        assert_eq!(q.push(sample(4, [0.0; 3], [0.0; 3])), ImuPush::AcceptedOverwritingOldest);
        assert_eq!(q.stats().overwritten, 1);
        assert_eq!(q.front().map(|s| s.t_ns), Some(2));
        assert_eq!(q.len(), 3);
        q.clear();
        assert!(q.is_empty());
        assert_eq!(q.last_time_ns(), None);
        assert_eq!(q.push(sample(1, [0.0; 3], [0.0; 3])), ImuPush::Accepted);
    }

    /// Stationary samples of an IMU tilted by (roll, pitch) with a gyro bias and white noise.
    #[allow(clippy::too_many_arguments)]
    fn stationary(
        rng: &mut Rng,
        n: usize,
        roll: f64,
        pitch: f64,
        bias: Vector3<f64>,
        sg: f64,
        sa: f64,
        unit: f64,
    ) -> impl Iterator<Item = ImuSample> + '_ {
        let r = UnitQuaternion::from_euler_angles(roll, pitch, 0.3); // yaw must not matter
        let f_body = r.inverse() * Vector3::new(0.0, 0.0, 9.81);
        (0..n).map(move |k| {
            let g = bias + Vector3::new(rng.gauss(), rng.gauss(), rng.gauss()) * sg;
            let a = (f_body + Vector3::new(rng.gauss(), rng.gauss(), rng.gauss()) * sa) / unit;
            ImuSample {
                t_ns: 1_000_000_000 + k as u64 * 5_000_000,
                gyro: [g.x as f32, g.y as f32, g.z as f32],
                acc: [a.x as f32, a.y as f32, a.z as f32],
            }
        })
    }

    fn run(init: &mut ImuInitializer, it: impl Iterator<Item = ImuSample>) -> Option<ImuInit> {
        for s in it {
            if let InitStatus::Ready(r) = init.push(&s) {
                return Some(r);
            }
        }
        None
    }

    #[test]
    fn stationary_start_recovers_gravity_and_gyro_bias_to_noise_precision() {
        let mut rng = Rng::new(7);
        let (roll, pitch) = (0.2, -0.35);
        let bias = Vector3::new(0.004, -0.007, 0.002);
        let (sg, sa) = (0.003, 0.05);
        let mut init = ImuInitializer::new(ImuInitConfig::default());
        let r = run(&mut init, stationary(&mut rng, 400, roll, pitch, bias, sg, sa, 1.0)).unwrap();
        assert!(!r.rough);
        assert_eq!(r.acc_scale, 1.0);
        // A 1.0 s window at 200 Hz: 201 samples.
        assert_eq!(r.samples, 201);
        let n = r.samples as f64;
        // Gyro bias: the mean of n samples of noise sg has σ = sg/√n = 2.1e-4; allow 4σ per axis.
        assert!((r.gyro_bias - bias).amax() < 4.0 * sg / n.sqrt(), "{:?}", r.gyro_bias - bias);
        // Gravity direction: σ of the tilt = sa/(g √n) = 3.6e-4 rad; allow 4σ (f32 samples add ~1e-7).
        let up_world =
            r.rotation * (UnitQuaternion::from_euler_angles(roll, pitch, 0.3).inverse() * Vector3::z());
        let tilt_err = up_world.angle(&Vector3::z());
        assert!(tilt_err < 4.0 * sa / (9.81 * n.sqrt()), "tilt error {tilt_err}");
        // Yaw is 0 by definition: the IMU x axis has no world-y component... after roll/pitch.
        let (_, _, yaw) = r.rotation.euler_angles();
        assert!(yaw.abs() < 1e-12);
        // The magnitude mismatch went into the vertical accelerometer bias: tiny here.
        assert!(r.acc_bias.norm() < 4.0 * sa / n.sqrt());
        assert!(r.gyro_std < 2.0 * sg && r.acc_std < 2.0 * sa);
    }

    #[test]
    fn g_unit_imu_is_detected_and_scaled() {
        let mut rng = Rng::new(9);
        let bias = Vector3::new(-0.003, 0.001, 0.005);
        let mut init = ImuInitializer::new(ImuInitConfig::default());
        let r = run(&mut init, stationary(&mut rng, 400, -0.1, 0.25, bias, 0.002, 0.02, STANDARD_GRAVITY))
            .unwrap();
        assert_eq!(r.acc_scale, STANDARD_GRAVITY);
        assert!(!r.rough);
        // The sensor reads 9.81/9.80665 g, which scales back to exactly 9.81 m/s^2: no vertical
        // bias beyond the noise of the mean (σ = 0.02/√201 = 1.4e-3; 4σ).
        assert!(r.acc_bias.norm() < 4.0 * 0.02 / (r.samples as f64).sqrt(), "{:?}", r.acc_bias);
        assert!((r.gyro_bias - bias).amax() < 4.0 * 0.002 / (r.samples as f64).sqrt());
        // Accelerometer std is reported in m/s^2 after scaling.
        assert!(r.acc_std > 0.5 * 0.02 && r.acc_std < 2.0 * 0.02, "{}", r.acc_std);
    }

    #[test]
    fn accel_bias_along_gravity_becomes_the_initial_vertical_bias() {
        let mut rng = Rng::new(10);
        let mut init = ImuInitializer::new(ImuInitConfig::default());
        // A sensor that reads 2% high: 9.81 * 1.02.
        let it = stationary(&mut rng, 400, 0.0, 0.0, Vector3::zeros(), 0.001, 0.01, 1.0 / 1.02);
        let r = run(&mut init, it).unwrap();
        assert!((r.acc_bias - Vector3::new(0.0, 0.0, 0.02 * 9.81)).norm() < 0.005, "{:?}", r.acc_bias);
    }

    #[test]
    fn wrong_magnitude_waits_with_the_reason() {
        let mut rng = Rng::new(11);
        let mut init = ImuInitializer::new(ImuInitConfig::default());
        let mut seen = None;
        // 9.81 / 3: neither m/s^2 nor g.
        for s in stationary(&mut rng, 300, 0.0, 0.0, Vector3::zeros(), 0.001, 0.01, 3.0) {
            match init.push(&s) {
                InitStatus::Waiting(WaitReason::AccelMagnitude { mean_norm }) => seen = Some(mean_norm),
                InitStatus::Waiting(WaitReason::Collecting { .. }) => {}
                other => panic!("{other:?}"),
            }
        }
        assert!((seen.unwrap() - 3.27).abs() < 0.01);
        // 1.5 s of samples: one full window evaluated and rejected, the next one collecting.
        assert_eq!(init.stats().rejected_windows, 1);
    }

    /// A strongly moving start: accelerations of several m/s^2 and rates of 1 rad/s.
    #[test]
    fn moving_start_reports_waiting_moving() {
        let mut init = ImuInitializer::new(ImuInitConfig::default());
        let mut reasons = [0u32; 2];
        for k in 0..1000u64 {
            let t = k as f64 * 0.005;
            let s = ImuSample {
                t_ns: k * 5_000_000,
                gyro: [(1.0 * libm::sin(3.0 * t)) as f32, 0.2, (0.8 * libm::cos(2.0 * t)) as f32],
                acc: [(3.0 * libm::sin(4.0 * t)) as f32, (2.0 * libm::cos(5.0 * t)) as f32, 9.81],
            };
            match init.push(&s) {
                InitStatus::Ready(r) => panic!("initialised while moving: {r:?}"),
                InitStatus::Waiting(WaitReason::Moving { gyro_std, acc_std }) => {
                    assert!(gyro_std > 0.02 && acc_std > 0.3);
                    reasons[0] += 1;
                }
                InitStatus::Waiting(WaitReason::Collecting { .. }) => reasons[1] += 1,
                InitStatus::Waiting(other) => panic!("{other:?}"),
            }
        }
        // 5 s of samples: one rejected window per second.
        assert_eq!(reasons[0], 4);
        assert_eq!(init.stats().rejected_windows, 4);
    }

    #[test]
    fn steady_rotation_is_not_taken_for_a_bias() {
        let mut init = ImuInitializer::new(ImuInitConfig { allow_moving_start: false, ..Default::default() });
        let mut got = None;
        for k in 0..300u64 {
            let s = sample(k * 5_000_000, [0.0, 0.0, 0.3], [0.0, 0.0, 9.81]);
            if let InitStatus::Waiting(WaitReason::Rotating { mean_rate }) = init.push(&s) {
                got = Some(mean_rate);
            }
        }
        assert!((got.unwrap() - 0.3).abs() < 1e-6);
    }

    #[test]
    fn vibrating_start_is_accepted_as_rough() {
        // Vibration: acc std 0.6 m/s^2 (too much for stationary), zero-mean, small rates.
        let mut rng = Rng::new(12);
        let mut init = ImuInitializer::new(ImuInitConfig::default());
        let r = run(
            &mut init,
            stationary(&mut rng, 400, 0.1, 0.05, Vector3::new(0.01, 0.0, 0.0), 0.03, 0.6, 1.0),
        )
        .unwrap();
        assert!(r.rough);
        assert_eq!(r.gyro_bias, Vector3::zeros());
        let up_world =
            r.rotation * (UnitQuaternion::from_euler_angles(0.1, 0.05, 0.3).inverse() * Vector3::z());
        // Rough, but still the right attitude to 0.6/(9.81 √201) ≈ 4.3e-3 rad (4σ).
        assert!(up_world.angle(&Vector3::z()) < 0.02);
    }

    #[test]
    fn initialiser_drops_bad_samples_and_restarts_after_gap() {
        let mut init = ImuInitializer::new(ImuInitConfig::default());
        let a = [0.0, 0.0, 9.81];
        init.push(&sample(1_000_000_000, [0.0; 3], a));
        init.push(&sample(1_000_000_000, [0.0; 3], a));
        init.push(&sample(900_000_000, [0.0; 3], a));
        init.push(&sample(1_005_000_000, [f32::NAN; 3], a));
        assert_eq!(init.stats().out_of_order, 2);
        assert_eq!(init.stats().non_finite, 1);
        // A 0.5 s gap restarts the window.
        init.push(&sample(1_500_000_000, [0.0; 3], a));
        assert_eq!(init.stats().gap_restarts, 1);
        match init.push(&sample(1_505_000_000, [0.0; 3], a)) {
            InitStatus::Waiting(WaitReason::Collecting { samples, span_s }) => {
                assert_eq!(samples, 2);
                assert!((span_s - 0.005).abs() < 1e-6);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn gravity_aligned_rotation_maps_up_to_z_with_zero_yaw() {
        for (r, p) in [(0.0, 0.0), (0.3, -0.2), (-1.2, 0.9), (2.5, 0.1)] {
            let truth = UnitQuaternion::from_euler_angles(r, p, 0.0);
            let up = truth.inverse() * Vector3::z();
            let est = gravity_aligned_rotation(&up);
            assert!(est.angle_to(&truth) < 1e-12, "{r} {p}");
        }
    }
}
