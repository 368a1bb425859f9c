//! The IMU–LiDAR time offset, estimated online from the scans' warp.
//!
//! An IMU stamped tens of milliseconds off the LiDAR's clock (a driver's latency, a separate
//! clock) bends every scan: the undistortion moves each point by the motion the IMU says
//! happened between the point's time and the scan end, and with the wrong offset that is the
//! motion of another stretch of time. On the handheld drive a 20 ms offset triples the ATE.
//!
//! What a wrong offset does *between* scans cannot tell it: the filter follows its IMU
//! prediction and the map is built from the same bent scans, so the scan-end rotations agree
//! with the shifted gyro (tried first: a 20 ms offset read as 5 to 9 ms). What it does *within*
//! a scan can. Delaying the IMU's motion by `dδ` moves a point measured at `t` (end frame,
//! position `p`) by
//!
//! `dp/dδ = (ω(T) - ω(t)) × p + ω(t) × c(t)`,  `c(t) = -v (T - t)`
//!
//! (`ω` the LiDAR's rate, `v` its velocity, `T` the scan end; a constant rate moves nothing).
//! Each matched point's plane residual then has a known derivative in `dδ` besides its pose
//! Jacobian `[q × n, n]`. After the update, the scan's 7x7 normal equations (pose and `dδ`) are
//! reduced to `dδ` alone (the Schur complement: whatever a rigid pose can explain is not
//! taken as offset), giving this scan's offset and its information. Scans accumulate, older
//! ones fading by `forget` per scan; the information-weighted mean is the estimate, and its
//! standard deviation widens where the scans scatter more than their information says (the
//! reduced chi-square: a wrong extrinsic, a moving scene). The odometry applies it to every IMU
//! stamp once `min_scans` gave it, its standard deviation is below `max_std_s` and it differs
//! from the one applied by more than two of them (and `hysteresis_s`). Without angular acceleration
//! there is no warp, no information and no change.

use nalgebra::{Matrix6, SMatrix, SVector, Vector3, Vector6};

use crate::association::{Correspondence, Kind};
use crate::eskf::State;
use crate::scan::ScanPoint;
use crate::undistort::ImuTrajectory;

/// The estimation's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TimeOffsetConfig {
    /// Estimate and apply the offset.
    pub enabled: bool,
    /// The largest offset applied, s (either sign).
    pub max_offset_s: f32,
    /// What the accumulated evidence keeps of itself per scan (1: never forget).
    pub forget: f32,
    /// The estimate is applied once its standard deviation is below this, s.
    pub max_std_s: f32,
    /// ... and this many scans (as kept by `forget`) gave it.
    pub min_scans: u16,
    /// An estimate this close to the applied one, s, or within two standard deviations of it,
    /// changes nothing.
    pub hysteresis_s: f32,
    /// The residuals' variance the information is counted with, m^2.
    pub residual_variance: f32,
}

impl TimeOffsetConfig {
    /// On: up to ±50 ms, a memory of about 100 scans, applied after 10 scans at a standard
    /// deviation under 2 ms and a change of more than two of them (and 0.05 ms).
    pub const DEFAULT: TimeOffsetConfig = TimeOffsetConfig {
        enabled: true,
        max_offset_s: 0.05,
        forget: 0.99,
        max_std_s: 0.002,
        min_scans: 10,
        hysteresis_s: 0.00005,
        residual_variance: 0.001,
    };

    /// Whether the settings can be used.
    pub fn validate(&self) -> Result<(), &'static str> {
        if !(self.max_offset_s.is_finite() && self.max_offset_s > 0.0 && self.max_offset_s <= 1.0) {
            return Err("time offset: max_offset_s must be in (0, 1] s");
        }
        if !(self.forget > 0.0 && self.forget <= 1.0) {
            return Err("time offset: forget must be in (0, 1]");
        }
        if !(self.max_std_s.is_finite() && self.max_std_s > 0.0) {
            return Err("time offset: max_std_s must be positive");
        }
        if !(self.hysteresis_s.is_finite() && self.hysteresis_s >= 0.0) {
            return Err("time offset: hysteresis_s must be finite and not negative");
        }
        if !(self.residual_variance.is_finite() && self.residual_variance > 0.0) {
            return Err("time offset: residual_variance must be positive");
        }
        Ok(())
    }
}

impl Default for TimeOffsetConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// One scan's normal equations in its LiDAR pose (rotation and translation, world frame) and
/// the offset's change `dδ`: `Σ [J s]ᵀ [J s]` and `Σ [J s]ᵀ r`.
#[derive(Clone, Copy, Debug, Default)]
pub struct Warp {
    /// The upper triangle of `Σ [J s]ᵀ [J s]`, row by row.
    h: [f64; 28],
    g: [f64; 7],
    n: u32,
}

impl Warp {
    /// No residual yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds one matched point: `q` its world position less the LiDAR origin, `n` and `d` the
    /// plane (`n·(q + o) + d` the residual, `o` the origin), `w` its derivative in the offset
    /// (`dp/dδ`, world frame).
    pub fn add(
        &mut self,
        q: &Vector3<f64>,
        origin: &Vector3<f64>,
        n: &Vector3<f64>,
        d: f64,
        w: &Vector3<f64>,
    ) {
        let r = n.dot(&(q + origin)) + d;
        let qn = q.cross(n);
        let row = [qn.x, qn.y, qn.z, n.x, n.y, n.z, n.dot(w)];
        let mut k = 0;
        for i in 0..7 {
            for j in i..7 {
                self.h[k] += row[i] * row[j];
                k += 1;
            }
            self.g[i] += row[i] * r;
        }
        self.n += 1;
    }

    /// Points added.
    pub fn len(&self) -> u32 {
        self.n
    }

    /// Whether none was added.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The offset's change this scan asks for and its information (unit residual variance),
    /// with the pose free; `None` when the pose is not pinned down.
    pub fn offset_change(&self) -> Option<(f64, f64)> {
        let mut full = SMatrix::<f64, 7, 7>::zeros();
        let mut k = 0;
        for i in 0..7 {
            for j in i..7 {
                full[(i, j)] = self.h[k];
                full[(j, i)] = self.h[k];
                k += 1;
            }
        }
        let (h, g) = (full, SVector::<f64, 7>::from_column_slice(&self.g));
        let hpp: Matrix6<f64> = h.fixed_view::<6, 6>(0, 0).into();
        let hps: Vector6<f64> = h.fixed_view::<6, 1>(0, 6).into();
        let gp: Vector6<f64> = g.fixed_rows::<6>(0).into();
        let chol = hpp.cholesky()?;
        let x = chol.solve(&hps);
        let info = h[(6, 6)] - hps.dot(&x);
        let gs = g[6] - x.dot(&gp);
        (info > 0.0 && info.is_finite() && gs.is_finite()).then(|| (-gs / info, info))
    }
}

/// The warp of one scan after its update: `points` (LiDAR frame at the scan end, undistorted
/// along `traj` at the applied offset) with their correspondences `corr`, the filter `x` at
/// the scan end, `end_t` seconds after the scan start. Empty without a trajectory.
pub fn scan_warp<const K: usize>(
    points: &[ScanPoint],
    corr: &[Correspondence],
    x: &State,
    traj: &ImuTrajectory<K>,
    end_t: f64,
) -> Warp {
    let mut warp = Warp::new();
    let Some((p_end, v_end, w_end)) = traj.kinematics_at(end_t) else { return warp };
    // The motion at the scan's times, tabulated (the points come in no time order; a search
    // of the knots per point cost more than the rest).
    let step = end_t.max(1e-6) / TABLE as f64;
    let mut table = [(Vector3::zeros(), Vector3::zeros(), Vector3::zeros()); TABLE + 1];
    for (i, k) in table.iter_mut().enumerate() {
        *k = traj.kinematics_at(i as f64 * step).unwrap_or((p_end, v_end, w_end));
    }
    let at = |t: f64| {
        let x = (t / step).clamp(0.0, TABLE as f64);
        let i = (x as usize).min(TABLE - 1);
        let f = x - i as f64;
        let (a, b) = (&table[i], &table[i + 1]);
        (a.0 + (b.0 - a.0) * f, a.1 + (b.1 - a.1) * f, a.2 + (b.2 - a.2) * f)
    };
    let r_il = x.ext_rot.to_rotation_matrix().into_inner();
    let r = x.rot.to_rotation_matrix().into_inner();
    let r_wl = r * r_il;
    let origin = r * x.ext_pos + x.pos;
    let rt = r.transpose();
    // Every matched point: with every third only, the vehicle's 20 ms read as 17.9 ms.
    for (p, c) in points.iter().zip(corr) {
        if c.kind == Kind::None {
            continue;
        }
        let (p_t, v_t, w_t) = at(f64::from(p.t));
        let p_l = Vector3::new(f64::from(p.xyz[0]), f64::from(p.xyz[1]), f64::from(p.xyz[2]));
        let p_i = r_il * p_l + x.ext_pos;
        // The point's move for a later IMU, in the IMU frame at the scan end.
        let dp = (w_end - w_t).cross(&p_i) + w_t.cross(&(rt * (p_t - p_end))) + rt * (v_end - v_t);
        let n = Vector3::new(f64::from(c.normal[0]), f64::from(c.normal[1]), f64::from(c.normal[2]));
        warp.add(&(r_wl * p_l), &origin, &n, c.d, &(r * dp));
    }
    warp
}

/// Times of a scan at which its motion is tabulated for the warp, less one.
const TABLE: usize = 64;

/// What the estimation knows.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct TimeOffsetEstimate {
    /// The offset added to the IMU stamps now, s (on top of the caller's).
    pub applied_s: f64,
    /// The same, exactly, ns (what the stamps are moved by).
    pub applied_ns: i64,
    /// The scans' estimate, s, once any scan gave information.
    pub estimate_s: Option<f64>,
    /// Its standard deviation, s.
    pub std_s: f64,
    /// Scans that gave information.
    pub scans: u32,
    /// Times the applied offset changed.
    pub changes: u32,
    /// IMU samples dropped because a change put them before samples already queued (filled in
    /// by the odometry, which owns the queue).
    pub realigned: u32,
}

/// The estimation's state (a few numbers).
#[derive(Clone, Debug)]
pub struct TimeOffset {
    cfg: TimeOffsetConfig,
    /// Σ information, 1/s².
    info: f64,
    /// Σ information × the scans' offsets, 1/s.
    weighted: f64,
    /// Σ information × the scans' offsets squared (unitless).
    weighted_sq: f64,
    /// Scans, each kept as the information is.
    count: f64,
    applied_ns: i64,
    state: TimeOffsetEstimate,
}

impl TimeOffset {
    /// Nothing known; no offset applied.
    pub fn new(cfg: TimeOffsetConfig) -> Self {
        Self {
            cfg,
            info: 0.0,
            weighted: 0.0,
            weighted_sq: 0.0,
            count: 0.0,
            applied_ns: 0,
            state: TimeOffsetEstimate::default(),
        }
    }

    /// The offset to add to every IMU stamp, ns.
    pub fn applied_ns(&self) -> i64 {
        self.applied_ns
    }

    /// What the estimation knows.
    pub fn estimate(&self) -> TimeOffsetEstimate {
        self.state
    }

    /// One scan's warp (built at the applied offset). Returns the new offset to apply to the
    /// IMU stamps, ns, when it changes.
    pub fn scan(&mut self, warp: &Warp) -> Option<i64> {
        if !self.cfg.enabled {
            return None;
        }
        let forget = f64::from(self.cfg.forget);
        self.info *= forget;
        self.weighted *= forget;
        self.weighted_sq *= forget;
        self.count *= forget;
        let applied = self.applied_ns as f64 * 1e-9;
        if let Some((change, info)) = warp.offset_change() {
            // A change beyond the search range is no evidence (an outlier scan).
            let max = f64::from(self.cfg.max_offset_s);
            if (applied + change).abs() <= 2.0 * max {
                let info = info / f64::from(self.cfg.residual_variance);
                let offset = applied + change;
                self.info += info;
                self.weighted += info * offset;
                self.weighted_sq += info * offset * offset;
                self.count += 1.0;
                self.state.scans = self.state.scans.saturating_add(1);
            }
        }
        if self.info <= 0.0 {
            return None;
        }
        let est = self.weighted / self.info;
        // The scans' scatter about the mean against what their information promises (the
        // reduced chi-square): where the warp model does not hold (a wrong extrinsic, a
        // scene that moves), they disagree, and the standard deviation widens with them.
        let spread = (self.weighted_sq - self.weighted * est).max(0.0);
        let chi2 = spread / (self.count - 1.0).max(1.0);
        let std = crate::math::sqrt(chi2.max(1.0) / self.info);
        self.state.estimate_s = Some(est);
        self.state.std_s = std;
        if self.count < f64::from(self.cfg.min_scans)
            || std > f64::from(self.cfg.max_std_s)
            || (est - applied).abs() <= f64::from(self.cfg.hysteresis_s).max(2.0 * std)
        {
            return None;
        }
        let max = f64::from(self.cfg.max_offset_s);
        self.applied_ns = libm::round(est.clamp(-max, max) * 1e9) as i64;
        self.state.applied_s = self.applied_ns as f64 * 1e-9;
        self.state.applied_ns = self.applied_ns;
        self.state.changes = self.state.changes.saturating_add(1);
        Some(self.applied_ns)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    /// Planes around the origin: a room's walls, floor and ceiling.
    const PLANES: [([f64; 3], f64); 6] = [
        ([1.0, 0.0, 0.0], -6.0),
        ([-1.0, 0.0, 0.0], -5.0),
        ([0.0, 1.0, 0.0], -7.0),
        ([0.0, -1.0, 0.0], -4.0),
        ([0.0, 0.0, 1.0], 1.5),
        ([0.0, 0.0, -1.0], -2.5),
    ];

    /// A scan of the room from a sensor at `origin` whose orientation at time `t` (from the scan
    /// end, negative before) is `rot(t)`, undistorted with the orientation `est(t)`: each
    /// point's warp derivative is computed from the rates `est_rate(t)`; returns the warp.
    fn scan(
        rot: impl Fn(f64) -> UnitQuaternion<f64>,
        est: impl Fn(f64) -> UnitQuaternion<f64>,
        est_rate: impl Fn(f64) -> Vector3<f64>,
        end_rot: UnitQuaternion<f64>,
    ) -> Warp {
        let mut w = Warp::new();
        let origin = Vector3::new(0.3, -0.2, 0.1);
        for k in 0..3000 {
            let t = -0.1 + 0.1 * f64::from(k) / 3000.0;
            // A direction per point, spread over the sphere.
            let (az, el) = (f64::from(k) * 2.399_963, (f64::from(k * 7 % 3000) / 3000.0 - 0.5) * 2.4);
            let dir_s = Vector3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
            let dir_w = rot(t) * dir_s;
            // The nearest plane hit.
            let mut best: Option<(f64, usize)> = None;
            for (i, (n, d)) in PLANES.iter().enumerate() {
                let n = Vector3::from(*n);
                let den = n.dot(&dir_w);
                if den.abs() < 1e-6 {
                    continue;
                }
                let range = -(n.dot(&origin) + d) / den;
                if range > 0.1 && best.is_none_or(|(r, _)| range < r) {
                    best = Some((range, i));
                }
            }
            let Some((range, i)) = best else { continue };
            let p_s = dir_s * range;
            // Undistorted into the end frame with the estimated motion.
            let p_e = est(0.0).inverse() * est(t) * p_s;
            let q = end_rot * p_e;
            let wd = (est_rate(0.0) - est_rate(t)).cross(&p_e);
            let (n, d) = PLANES[i];
            w.add(&q, &origin, &Vector3::from(n), d, &(end_rot * wd));
        }
        w
    }

    /// Rates with angular acceleration on every axis, rad/s at `t` (s).
    fn rate(t: f64) -> Vector3<f64> {
        Vector3::new(0.8 * (3.3 * t).sin(), 0.5 * (4.1 * t + 1.0).sin(), 1.1 * (2.7 * t).cos())
    }

    /// The orientation reached at [`rate`] from identity at `t0`, tabulated every 0.1 ms up
    /// to `t0 + span`.
    struct Motion {
        t0: f64,
        q: heapless::Vec<UnitQuaternion<f64>, 4100>,
    }

    const STEP: f64 = 1e-4;

    impl Motion {
        fn new(t0: f64, span: f64) -> Self {
            let mut q = heapless::Vec::new();
            let mut last = UnitQuaternion::identity();
            q.push(last).unwrap();
            for i in 0..(span / STEP).ceil() as usize {
                last *= crate::so3::exp_quat(&(rate(t0 + (i as f64 + 0.5) * STEP) * STEP));
                q.push(last).unwrap();
            }
            Self { t0, q }
        }

        fn at(&self, t: f64) -> UnitQuaternion<f64> {
            let x = (t - self.t0) / STEP;
            let i = (x.floor().max(0.0) as usize).min(self.q.len() - 1);
            let h = t - self.t0 - i as f64 * STEP;
            self.q[i] * crate::so3::exp_quat(&(rate(t - 0.5 * h) * h))
        }
    }

    /// A scan ending at `end` of an IMU `late` seconds late, undistorted with it.
    fn late_scan(end: f64, late: f64) -> Warp {
        let m = Motion::new(end - 0.3, 0.4);
        scan(|t| m.at(end + t), |t| m.at(end + t - late), |t| rate(end + t - late), m.at(end))
    }

    #[test]
    fn one_scan_tells_how_late_its_imu_was() {
        for (end, late) in [(1.0, 0.020), (2.3, -0.012), (3.1, 0.0)] {
            let (change, info) = late_scan(end, late).offset_change().expect("a warp");
            assert!(info > 0.0);
            // The IMU's motion must be moved `late` earlier: the change is -late.
            assert!((change + late).abs() < 0.0015, "late {late}: change {change}");
        }
    }

    #[test]
    fn scans_accumulate_and_the_offset_is_applied_once_certain() {
        let mut est = TimeOffset::new(TimeOffsetConfig::DEFAULT);
        let late = 0.020;
        let mut applied = 0.0;
        let mut first_change = None;
        for k in 0..40 {
            let end = 0.5 + 0.1 * f64::from(k);
            if let Some(ns) = est.scan(&late_scan(end, late + applied)) {
                applied = ns as f64 * 1e-9;
                first_change.get_or_insert(k);
            }
        }
        let e = est.estimate();
        assert!((e.applied_s + late).abs() < 0.0005, "{e:?}");
        assert_eq!(e.applied_ns, est.applied_ns());
        assert_eq!(e.applied_s, e.applied_ns as f64 * 1e-9);
        assert!(e.changes >= 1 && e.scans == 40, "{e:?}");
        // Not from the first scan: only once the standard deviation allows.
        assert!(first_change.is_some_and(|k| k > 0), "{first_change:?}");
        assert!(e.std_s < 0.002, "{e:?}");
    }

    #[test]
    fn a_constant_rate_gives_no_information() {
        let mut w = Warp::new();
        assert!(w.is_empty());
        // A constant rate: the warp derivatives are zero.
        let o = Vector3::zeros();
        for k in 0..500 {
            let p = Vector3::new(5.0, f64::from(k) * 0.01 - 2.5, f64::from(k % 7) * 0.3 - 1.0);
            w.add(&p, &o, &Vector3::x(), -5.0, &Vector3::zeros());
            w.add(&Vector3::new(p.y, 6.0, p.z), &o, &Vector3::y(), -6.0, &Vector3::zeros());
            w.add(&Vector3::new(p.y, p.z * 2.0, -1.5), &o, &(-Vector3::z()), -1.5, &Vector3::zeros());
        }
        assert_eq!((w.len(), w.is_empty()), (1500, false));
        assert_eq!(w.offset_change(), None);
        let mut est = TimeOffset::new(TimeOffsetConfig::DEFAULT);
        assert_eq!(est.scan(&w), None);
        assert_eq!(est.applied_ns(), 0);
    }

    #[test]
    fn settings_are_checked() {
        assert!(TimeOffsetConfig::DEFAULT.validate().is_ok());
        let bad = [
            TimeOffsetConfig { max_offset_s: 0.0, ..TimeOffsetConfig::DEFAULT },
            TimeOffsetConfig { forget: 0.0, ..TimeOffsetConfig::DEFAULT },
            TimeOffsetConfig { max_std_s: 0.0, ..TimeOffsetConfig::DEFAULT },
            TimeOffsetConfig { hysteresis_s: f32::NAN, ..TimeOffsetConfig::DEFAULT },
            TimeOffsetConfig { residual_variance: -1.0, ..TimeOffsetConfig::DEFAULT },
        ];
        for b in bad {
            assert!(b.validate().is_err(), "{b:?}");
        }
    }
}
