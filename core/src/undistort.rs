//! Backward propagation (undistortion): every point of a scan, and its normal, moved to the
//! LiDAR frame at the scan-end time, using the IMU poses the filter passed through during the
//! scan.
//!
//! The odometry records the filter's state at every IMU sample of the scan in an
//! [`ImuTrajectory`] (fixed capacity, caller-owned):
//!
//! ```text
//! traj.clear(scan.start_ns);
//! traj.push(eskf.time_ns(), eskf.state());        // the state at the previous scan end
//! for each IMU sample s with s.t_ns <= scan_end_ns:
//!     eskf.predict(&s);  traj.push(eskf.time_ns(), eskf.state());
//! eskf.predict_to(scan_end_ns);  traj.push(eskf.time_ns(), eskf.state());
//! traj.undistort(eskf.state(), points, Some(normals));
//! ```
//!
//! Between two knots the pose is interpolated with the rate the filter integrated over that
//! segment (`R(τ) = R_k Exp(ω τ)`, `ω = Log(R_kᵀ R_k+1)/Δt`) and a cubic Hermite curve through the
//! knots' positions and velocities (exact at both knots). Outside the knots the motion is
//! extrapolated at constant velocity and rate (counted). A point at time `t` with LiDAR-frame
//! position `p` becomes `R_ILᵀ (R_eᵀ (R(t) (R_IL p + t_IL) + p(t) - p_e) - t_IL)`, its normal
//! `R_ILᵀ R_eᵀ R(t) R_IL n`, where `e` is the end state (the same as the reference's backward
//! propagation, plus the normals, as LOG-LIO does). The transform is computed exactly at the
//! ends of pieces of 2^-14 s (61 µs) and taken linear in time between them, within 1e-9 of the
//! exact one; four points at a time go through it on vector lanes. The odometry turns the
//! normals by a table of that rotation at 257 times over the scan, each normal taking the
//! nearest ([`NormalRotations`]): as close as the normals need, and it spares the thread that
//! estimates them a transform per firing time.
//!
//! When more knots arrive than fit, the last knot is replaced (the last two segments merge into
//! one, counted), so the buffer always ends at the newest pose; size it for the IMU rate (e.g.
//! 64 knots for a 400 Hz IMU and 10 Hz scans).

use nalgebra::{Matrix3, Vector3};

use crate::eskf::State;
use crate::parallel::Parallel;
use crate::scan::ScanPoint;
use crate::so3;
use wide::{CmpNe, f32x4, f64x4};

type M3 = Matrix3<f64>;
type V3 = Vector3<f64>;

/// Points per piece of a parallel undistortion (at least; the pieces start on multiples).
const UNDISTORT_PIECE: usize = 1024;

/// One recorded IMU pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Knot {
    /// Seconds since the scan start (negative before it).
    pub t: f64,
    /// World from IMU.
    pub rot: M3,
    /// IMU position in the world.
    pub pos: V3,
    /// IMU velocity in the world.
    pub vel: V3,
    /// Body rate over the segment that ends at this knot (zero for the first knot).
    pub omega: V3,
}

/// What [`ImuTrajectory::push`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum KnotPush {
    /// Stored.
    Stored,
    /// The buffer was full: it replaced the last knot (counted).
    Merged,
    /// Not later than the last knot (or non-finite): ignored (counted).
    Ignored,
}

/// Why undistortion could not run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum UndistortError {
    /// No knot was recorded.
    NoPoses,
    /// The normals slice is not as long as the points slice.
    LengthMismatch,
    /// A time range that is not finite (NaN or infinite).
    NonFiniteTime,
}

impl core::fmt::Display for UndistortError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::NoPoses => f.write_str("no IMU poses recorded for the scan"),
            Self::LengthMismatch => f.write_str("normals and points differ in length"),
            Self::NonFiniteTime => f.write_str("the time range is not finite"),
        }
    }
}

impl core::error::Error for UndistortError {}

/// Counters of one [`ImuTrajectory::undistort`] call.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct UndistortStats {
    /// Points moved.
    pub moved: u32,
    /// Points outside the recorded time span (extrapolated at constant velocity and rate).
    pub extrapolated: u32,
    /// Points left unchanged: non-finite position or time.
    pub invalid: u32,
    /// Exact transforms computed: the ends of the pieces that the points' times fall in.
    pub transforms: u32,
}

/// The IMU poses of one scan: fixed capacity `N` (at least 2), caller-owned, `const`-constructible.
#[derive(Debug)]
pub struct ImuTrajectory<const N: usize> {
    start_ns: u64,
    knots: heapless::Vec<Knot, N>,
    merged: u32,
    ignored: u32,
}

impl<const N: usize> Default for ImuTrajectory<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> ImuTrajectory<N> {
    /// An empty trajectory.
    pub const fn new() -> Self {
        Self { start_ns: 0, knots: heapless::Vec::new(), merged: 0, ignored: 0 }
    }

    /// Empties it for a scan starting at `scan_start_ns`.
    pub fn clear(&mut self, scan_start_ns: u64) {
        self.start_ns = scan_start_ns;
        self.knots.clear();
        self.merged = 0;
        self.ignored = 0;
    }

    /// The recorded knots.
    pub fn knots(&self) -> &[Knot] {
        &self.knots
    }

    /// Knots merged because the buffer was full (since [`Self::clear`]).
    pub fn merged(&self) -> u32 {
        self.merged
    }

    /// Knots ignored (not later than the last, or non-finite) since [`Self::clear`].
    pub fn ignored(&self) -> u32 {
        self.ignored
    }

    /// Records the filter state `x` at absolute time `t_ns`.
    pub fn push(&mut self, t_ns: u64, x: &State) -> KnotPush {
        let t = (t_ns as i128 - self.start_ns as i128) as f64 * 1e-9;
        let mut k = Knot {
            t,
            rot: x.rot.to_rotation_matrix().into_inner(),
            pos: x.pos,
            vel: x.vel,
            omega: V3::zeros(),
        };
        if !x.is_finite() || self.knots.last().is_some_and(|l| t <= l.t) {
            self.ignored = self.ignored.saturating_add(1);
            return KnotPush::Ignored;
        }
        let full = self.knots.len() == N;
        if full {
            self.knots.pop();
            self.merged = self.merged.saturating_add(1);
        }
        if let Some(prev) = self.knots.last() {
            k.omega = so3::log(&(prev.rot.transpose() * k.rot)) / (t - prev.t);
        }
        match self.knots.push(k) {
            Ok(()) if !full => KnotPush::Stored,
            Ok(()) => KnotPush::Merged,
            // Only with N == 0: nothing can be stored.
            Err(_) => KnotPush::Ignored,
        }
    }

    /// A trajectory of two knots: this one's first and the state `x` at `t_ns` (e.g. the
    /// updated scan end). Between them the pose moves at the constant rate and on the Hermite
    /// curve of those two states: the motion a scan update found, in place of what was
    /// recorded (through an IMU gap, a bridge that holds the last scans' motion).
    pub fn span_to(&self, t_ns: u64, x: &State) -> ImuTrajectory<2> {
        let mut out = ImuTrajectory::<2>::new();
        out.start_ns = self.start_ns;
        let Some(&k) = self.knots.first() else {
            out.push(t_ns, x);
            return out;
        };
        // Cannot fail: the capacity is 2 and the buffer is empty.
        let _ = out.knots.push(Knot { omega: V3::zeros(), ..k });
        out.push(t_ns, x);
        // A straight line between the two positions (the states' velocities are not used).
        if let [a, b] = &mut out.knots[..] {
            let v = (b.pos - a.pos) / (b.t - a.t);
            a.vel = v;
            b.vel = v;
        }
        out
    }

    /// The inverse of [`Self::undistort`] with the same `end`: `points` (and `normals`) in the
    /// LiDAR frame at the end state back to the LiDAR frame at their own times, so that another
    /// trajectory can undistort them again. Invalid points and normals are left as they are.
    pub fn redistort(
        &self,
        end: &State,
        points: &mut [ScanPoint],
        normals: Option<&mut [[f32; 3]]>,
    ) -> Result<UndistortStats, UndistortError> {
        self.transform::<true, true, _>(end, points, normals, None)
    }

    /// The pose model that holds at `t`: `(valid from, valid to, reference knot a, rate ω,
    /// end knot b)`. Between knots `a` and `b`: `R = a.rot Exp(ω τ)` with `ω = b.omega` and a
    /// Hermite position; before the first knot (or with one knot) back along the first
    /// segment's rate, after the last along its rate, both at constant velocity (`b` is `None`).
    /// `None` without knots, and for a NaN `t` (it lies in no segment).
    fn locate(&self, t: f64) -> Option<(f64, f64, Knot, V3, Option<Knot>)> {
        if t.is_nan() {
            return None;
        }
        let ks = &self.knots[..];
        let first = *ks.first()?;
        let last = ks[ks.len() - 1];
        Some(if ks.len() == 1 || t < first.t {
            let hi = if ks.len() == 1 { f64::INFINITY } else { first.t };
            (f64::NEG_INFINITY, hi, first, ks.get(1).map_or(V3::zeros(), |k| k.omega), None)
        } else if t >= last.t {
            (last.t, f64::INFINITY, last, last.omega, None)
        } else {
            // ks[i-1].t <= t < ks[i].t
            let i = ks.partition_point(|k| k.t <= t);
            (ks[i - 1].t, ks[i].t, ks[i - 1], ks[i].omega, Some(ks[i]))
        })
    }

    /// The interpolated IMU pose (world from IMU) at `t` seconds since the scan start, and
    /// whether it was extrapolated; `None` without knots or for a NaN `t`.
    pub fn pose_at(&self, t: f64) -> Option<(M3, V3, bool)> {
        let (_, _, a, omega, end) = self.locate(t)?;
        let tau = t - a.t;
        let rot = a.rot * so3::exp(&(omega * tau));
        let Some(b) = end else {
            return Some((rot, a.pos + a.vel * tau, tau != 0.0));
        };
        let w = hermite_weights(tau, b.t - a.t);
        Some((rot, a.pos * w[0] + a.vel * w[1] + b.pos * w[2] + b.vel * w[3], false))
    }

    /// The interpolated IMU position, velocity (world) and body rate at `t` seconds since the
    /// scan start (the velocity linear between knots; the rate the segment's).
    pub fn kinematics_at(&self, t: f64) -> Option<(V3, V3, V3)> {
        let (_, _, a, omega, end) = self.locate(t)?;
        let tau = t - a.t;
        let Some(b) = end else {
            return Some((a.pos + a.vel * tau, a.vel, omega));
        };
        let h = b.t - a.t;
        let w = hermite_weights(tau, h);
        let pos = a.pos * w[0] + a.vel * w[1] + b.pos * w[2] + b.vel * w[3];
        Some((pos, a.vel + (b.vel - a.vel) * (tau / h), omega))
    }

    /// The pose model that holds at time `t` ([`Self::locate`]) folded with the end state and
    /// the extrinsic, so that a time inside it costs two coefficients instead of matrix
    /// products. `None` without knots.
    fn segment(&self, t: f64, f: &Frame) -> Option<Segment> {
        let (lo, hi, a, omega, hermite) = self.locate(t)?;
        // R(τ) = a.rot Exp(ω τ) = a.rot (I + c1(θ) τ W + c2(θ) τ² W²), W = hat(ω).
        let w = so3::hat(&omega);
        let nr = f.n * a.rot;
        let (nrw, nrw2) = (nr * w, nr * w * w);
        let np = match hermite {
            Some(b) => [f.n * a.pos, f.n * a.vel, f.n * b.pos, f.n * b.vel],
            None => [f.n * a.pos, f.n * a.vel, V3::zeros(), V3::zeros()],
        };
        Some(Segment {
            lo,
            hi,
            t0: a.t,
            h: hermite.map(|b| b.t - a.t),
            rate: omega.norm(),
            m: [nr * f.r_il, nrw * f.r_il, nrw2 * f.r_il],
            g: [nr * f.t_il + f.c0, nrw * f.t_il, nrw2 * f.t_il],
            np,
        })
    }

    /// [`Self::undistort`] with the points split over `parallel`'s threads: every point and
    /// normal the same as on one thread (the counts of transforms computed may differ where a
    /// firing is split between two pieces).
    pub fn undistort_with(
        &self,
        end: &State,
        points: &mut [ScanPoint],
        normals: Option<&mut [[f32; 3]]>,
        parallel: &dyn Parallel,
    ) -> Result<UndistortStats, UndistortError> {
        let n = points.len();
        if parallel.width() <= 1 || n < 2 * UNDISTORT_PIECE {
            return self.undistort(end, points, normals);
        }
        if normals.as_ref().is_some_and(|nr| nr.len() != n) {
            return Err(UndistortError::LengthMismatch);
        }
        let mut results = [Ok(UndistortStats::default()); crate::parallel::MAX_WIDTH];
        let pieces = crate::parallel::map_pieces2(
            parallel,
            points,
            normals,
            UNDISTORT_PIECE,
            &mut results,
            |_, p, nrm, out| *out = self.undistort(end, p, nrm),
        );
        let mut stats = UndistortStats::default();
        for r in &results[..pieces] {
            let s = (*r)?;
            stats.moved += s.moved;
            stats.extrapolated += s.extrapolated;
            stats.invalid += s.invalid;
            stats.transforms += s.transforms;
        }
        Ok(stats)
    }

    /// Moves `points` (and `normals`, if given: the same length, rotation only; invalid normals,
    /// i.e. non-finite or zero, are left as they are) in place to the LiDAR frame at the end
    /// state `end` (the filter state at the scan end), using each point's `t`.
    ///
    /// The transform of a time is that of [`Self::pose_at`] composed with the end state and
    /// the extrinsic, evaluated through the time's `Segment` (the same formula regrouped:
    /// results agree to rounding).
    pub fn undistort(
        &self,
        end: &State,
        points: &mut [ScanPoint],
        normals: Option<&mut [[f32; 3]]>,
    ) -> Result<UndistortStats, UndistortError> {
        self.transform::<false, true, _>(end, points, normals, None)
    }

    /// [`Self::undistort`] with the normals turned by `table` ([`NormalRotations::rotate`], the
    /// same bits) in the same pass: one thread's form of what the odometry runs as two jobs.
    pub fn undistort_rotating(
        &self,
        end: &State,
        points: &mut [ScanPoint],
        normals: &mut [[f32; 3]],
        table: &NormalRotations,
    ) -> Result<UndistortStats, UndistortError> {
        self.transform::<false, true, _>(end, points, Some(normals), Some(table))
    }

    /// The normals' half of [`Self::undistort`]: `normals` rotated as it rotates them, from
    /// the points' times (only their times and finiteness are read; points already undistorted
    /// keep their times, so the rotations are the same, bit for bit). The odometry moves every
    /// point first, then rotates the normals after Ring FALS, on the thread that estimated them,
    /// while another finds the downsampling's voxels among the same points.
    pub fn undistort_normals(
        &self,
        end: &State,
        points: &[ScanPoint],
        normals: &mut [[f32; 3]],
    ) -> Result<UndistortStats, UndistortError> {
        self.transform::<false, false, _>(end, points, Some(normals), None)
    }

    /// Fills `out`, the table of [`NormalRotations`] for points timed `t_lo..=t_hi` (seconds
    /// since the scan start) undistorted to the end state `end`: the rotation each knot time's
    /// transform gives (as [`Self::undistort`] computes it), rounded to f32. A bound that is
    /// not finite is [`UndistortError::NonFiniteTime`] (`out` is left as it was).
    pub fn normal_rotations(
        &self,
        end: &State,
        t_lo: f32,
        t_hi: f32,
        out: &mut NormalRotations,
    ) -> Result<(), UndistortError> {
        if self.knots.is_empty() {
            return Err(UndistortError::NoPoses);
        }
        if !(t_lo.is_finite() && t_hi.is_finite()) {
            return Err(UndistortError::NonFiniteTime);
        }
        let frame = Self::frame(end);
        let span = if t_hi > t_lo { t_hi - t_lo } else { 0.0 };
        let step = span / NORMAL_ROTATION_STEPS as f32;
        out.t0 = t_lo;
        out.inv_step = if step > 0.0 { 1.0 / step } else { 0.0 };
        let mut seg: Option<Segment> = None;
        for (k, r) in out.rot.iter_mut().enumerate() {
            let t = f64::from(t_lo) + f64::from(step) * k as f64;
            let sg = match seg {
                Some(s) if s.lo <= t && t < s.hi => s,
                // Cannot fail: knots is not empty.
                _ => *seg.insert(self.segment(t, &frame).ok_or(UndistortError::NoPoses)?),
            };
            let a = sg.rotation(t);
            *r = core::array::from_fn(|j| a[(j / 3, j % 3)] as f32);
        }
        Ok(())
    }

    /// The end state's frame of an undistortion.
    fn frame(end: &State) -> Frame {
        let r_e_t = end.rot.to_rotation_matrix().into_inner().transpose();
        let r_il = end.ext_rot.to_rotation_matrix().into_inner();
        let r_il_t = r_il.transpose();
        let n = r_il_t * r_e_t;
        Frame { n, r_il, t_il: end.ext_pos, c0: -(n * end.pos) - r_il_t * end.ext_pos }
    }

    /// [`Self::undistort`], or with `INVERSE` [`Self::redistort`] (each point's transform
    /// `q = A p + b` applied backwards, `p = Aᵀ (q - b)`: the exact inverse of the same
    /// transform); without `MOVE` only the normals ([`Self::undistort_normals`]).
    fn transform<const INVERSE: bool, const MOVE: bool, P: Points>(
        &self,
        end: &State,
        mut points: P,
        mut normals: Option<&mut [[f32; 3]]>,
        table: Option<&NormalRotations>,
    ) -> Result<UndistortStats, UndistortError> {
        if self.knots.is_empty() {
            return Err(UndistortError::NoPoses);
        }
        if normals.as_ref().is_some_and(|n| n.len() != points.as_ref().len()) {
            return Err(UndistortError::LengthMismatch);
        }
        let frame = Self::frame(end);
        let mut stats = UndistortStats::default();
        let mut seg = Segment::NONE;
        let mut ends = PieceEnds::new();
        let n = points.as_ref().len();
        let mut i = 0;
        while i < n {
            // Four points at a time where they can go together: moved forwards, their normals
            // (if any) turned by the table.
            if MOVE && !INVERSE && i + LANES <= n && (normals.is_none() || table.is_some()) {
                let block: Option<[ScanPoint; LANES]> = points.as_ref()[i..i + LANES].try_into().ok();
                if let Some((block, out)) =
                    block.and_then(|b| Some((b, lanes(&b, &seg, &mut ends, &mut stats)?)))
                {
                    for (l, xyz) in out.iter().enumerate() {
                        points.set_xyz(i + l, *xyz);
                    }
                    if let (Some(ns), Some(tb)) = (normals.as_deref_mut(), table) {
                        tb.rotate4(core::array::from_fn(|l| block[l].t), &mut ns[i..i + LANES]);
                    }
                    i += LANES;
                    continue;
                }
            }
            let pt = points.as_ref()[i];
            let [x, y, z] = pt.xyz;
            if !(x.is_finite() && y.is_finite() && z.is_finite() && pt.t.is_finite()) {
                stats.invalid += 1;
                i += 1;
                continue;
            }
            let t = pt.t as f64;
            if !(seg.lo <= t && t < seg.hi) {
                // Cannot fail: knots is not empty.
                seg = self.segment(t, &frame).ok_or(UndistortError::NoPoses)?;
                ends = PieceEnds::new();
            }
            let tau = t - seg.t0;
            if seg.h.is_none() && tau != 0.0 {
                stats.extrapolated += 1;
            }
            let exact_normal = normals.is_some() && table.is_none();
            let (a, b) = if INVERSE || exact_normal {
                ends.transform(&seg, tau, &mut stats)
            } else {
                (M3::zeros(), V3::zeros())
            };
            if MOVE {
                let q = [x as f64, y as f64, z as f64];
                let p = if INVERSE {
                    let p = a.transpose() * (V3::from(q) - b);
                    [p.x as f32, p.y as f32, p.z as f32]
                } else {
                    ends.forward(&seg, tau, q, &mut stats)
                };
                points.set_xyz(i, p);
                stats.moved += 1;
            }
            if let (Some(ns), Some(tb)) = (normals.as_deref_mut(), table) {
                tb.rotate_one(pt.t, &mut ns[i]);
            } else if let Some(ns) = normals.as_deref_mut() {
                let n = &mut ns[i];
                if crate::downsample::normal_is_valid(n) {
                    let v = V3::new(n[0] as f64, n[1] as f64, n[2] as f64);
                    let m = if INVERSE { a.transpose() * v } else { a * v };
                    *n = [m.x as f32, m.y as f32, m.z as f32];
                }
            }
            i += 1;
        }
        Ok(stats)
    }
}

/// Intervals of a [`NormalRotations`] table over a scan.
pub const NORMAL_ROTATION_STEPS: usize = 256;

/// The undistortion's rotation of the normals (`R_ILᵀ R_eᵀ R(t) R_IL`) at
/// [`NORMAL_ROTATION_STEPS`]` + 1` even times over a scan; a normal takes the nearest. A normal
/// needs its firing's rotation only to well below its own noise (Ring FALS normals scatter by
/// about 1e-2 rad) and the map's quantisation (half a degree): half a step of a 0.1 s scan
/// turning at 2 rad/s is 0.4 mrad. The table spares the normals' thread a transform for each
/// of the ~28,700 distinct firing times of a VLP-32C scan, and a normal costs a look-up and a
/// product (four at a time where they share a rotation). The same table on one thread and on
/// many: the normals are the same, bit for bit.
/// Caller-owned (9 KiB): it lives in the odometry's storage.
#[derive(Clone, Debug)]
pub struct NormalRotations {
    t0: f32,
    inv_step: f32,
    /// Row-major rotations at the knots.
    rot: [[f32; 9]; NORMAL_ROTATION_STEPS + 1],
}

impl Default for NormalRotations {
    fn default() -> Self {
        Self::new()
    }
}

impl NormalRotations {
    /// An empty table, all zero bytes (so that the odometry's storage in a `static` stays in
    /// .bss): [`ImuTrajectory::normal_rotations`] fills it before a scan's normals turn.
    pub const fn new() -> Self {
        Self { t0: 0.0, inv_step: 0.0, rot: [[0.0; 9]; NORMAL_ROTATION_STEPS + 1] }
    }

    /// Rotates each valid normal (finite, not zero: [`crate::downsample::normal_is_valid`])
    /// by the table's rotation nearest its point's time; normals of points without a finite
    /// position or time are left as they are, as [`ImuTrajectory::undistort`] leaves them.
    pub fn rotate(&self, points: &[ScanPoint], normals: &mut [[f32; 3]]) {
        let finite = |p: &ScanPoint| p.xyz.iter().all(|v| v.is_finite()) && p.t.is_finite();
        let mut pc = points.chunks_exact(LANES);
        let mut nc = normals.chunks_exact_mut(LANES);
        for (p, n) in (&mut pc).zip(&mut nc) {
            if p.iter().all(finite) {
                self.rotate4(core::array::from_fn(|l| p[l].t), n);
            } else {
                for (p, n) in p.iter().zip(n.iter_mut()) {
                    if finite(p) {
                        self.rotate_one(p.t, n);
                    }
                }
            }
        }
        for (p, n) in pc.remainder().iter().zip(nc.into_remainder().iter_mut()) {
            if finite(p) {
                self.rotate_one(p.t, n);
            }
        }
    }

    /// Four normals (of points with finite times `t`) on vector lanes where they take the
    /// same rotation, as they mostly do: the same operations, so the same bits, as
    /// [`Self::rotate_one`] gives each.
    #[inline(always)]
    fn rotate4(&self, t: [f32; LANES], n: &mut [[f32; 3]]) {
        let at =
            |t: f32| ((t - self.t0) * self.inv_step + 0.5).clamp(0.0, NORMAL_ROTATION_STEPS as f32) as usize;
        let k: [usize; LANES] = core::array::from_fn(|l| at(t[l]));
        let (Some(r), true, true) = (self.rot.get(k[0]), k.iter().all(|&v| v == k[0]), n.len() == LANES)
        else {
            for (t, n) in t.iter().zip(n.iter_mut()) {
                self.rotate_one(*t, n);
            }
            return;
        };
        let v: [f32x4; 3] =
            core::array::from_fn(|a| f32x4::from(core::array::from_fn::<f32, LANES, _>(|l| n[l][a])));
        let o: [[f32; LANES]; 3] = core::array::from_fn(|i| {
            let s = |j: usize| f32x4::splat(r[3 * i + j]);
            (s(0) * v[0] + s(1) * v[1] + s(2) * v[2]).to_array()
        });
        for (l, n) in n.iter_mut().enumerate() {
            if crate::downsample::normal_is_valid(n) {
                *n = [o[0][l], o[1][l], o[2][l]];
            }
        }
    }

    /// One normal at time `t` (finite; valid normals only).
    #[inline(always)]
    fn rotate_one(&self, t: f32, n: &mut [f32; 3]) {
        if !crate::downsample::normal_is_valid(n) {
            return;
        }
        // The nearest knot; times outside the scan take the first or the last.
        let u = (t - self.t0) * self.inv_step + 0.5;
        let r = &self.rot[u.clamp(0.0, NORMAL_ROTATION_STEPS as f32) as usize];
        let v = *n;
        *n = core::array::from_fn(|i| r[3 * i] * v[0] + r[3 * i + 1] * v[1] + r[3 * i + 2] * v[2]);
    }
}

/// The points a transform reads (and, moving them, writes).
trait Points: AsRef<[ScanPoint]> {
    fn set_xyz(&mut self, i: usize, xyz: [f32; 3]);
}

impl Points for &mut [ScanPoint] {
    #[inline(always)]
    fn set_xyz(&mut self, i: usize, xyz: [f32; 3]) {
        self[i].xyz = xyz;
    }
}

/// Read only: for the normals alone.
impl Points for &[ScanPoint] {
    #[inline(always)]
    fn set_xyz(&mut self, _: usize, _: [f32; 3]) {}
}

/// Cubic Hermite weights of `(a.pos, a.vel, b.pos, b.vel)` at `tau` into a segment of length
/// `h`.
#[inline]
fn hermite_weights(tau: f64, h: f64) -> [f64; 4] {
    let s = tau / h;
    let (s2, s3) = (s * s, s * s * s);
    [2.0 * s3 - 3.0 * s2 + 1.0, h * (s3 - 2.0 * s2 + s), 3.0 * s2 - 2.0 * s3, h * (s3 - s2)]
}

/// The end state and extrinsic of an undistortion: `n = R_ILᵀ R_eᵀ` and
/// `c0 = -n p_e - R_ILᵀ t_IL`, so that a world point `w` is `n w + c0` in the end LiDAR frame.
struct Frame {
    n: M3,
    r_il: M3,
    t_il: V3,
    c0: V3,
}

/// One pose model of [`ImuTrajectory::undistort`], valid for `lo <= t < hi`: the transform of a
/// point at `τ = t - t0` is `A = m0 + s1 m1 + s2 m2`, `b = g0 + s1 g1 + s2 g2 + Σ w_k np_k` with
/// `s1 = c1(θ) τ`, `s2 = c2(θ) τ²` (Rodrigues, `θ = rate |τ|`) and `w` the Hermite weights
/// (step `h`) or `(1, τ, 0, 0)` outside the knots.
#[derive(Clone, Copy)]
struct Segment {
    lo: f64,
    hi: f64,
    t0: f64,
    h: Option<f64>,
    rate: f64,
    m: [M3; 3],
    g: [V3; 3],
    np: [V3; 4],
}

impl Segment {
    /// No segment: it holds no time.
    const NONE: Self = Self {
        lo: f64::NAN,
        hi: f64::NAN,
        t0: 0.0,
        h: None,
        rate: 0.0,
        m: [M3::new(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0); 3],
        g: [V3::new(0.0, 0.0, 0.0); 3],
        np: [V3::new(0.0, 0.0, 0.0); 4],
    };

    /// The rotation `A` of the exact transform at `t` ([`Self::exact`]'s).
    fn rotation(&self, t: f64) -> M3 {
        self.exact(t - self.t0).0
    }

    /// The exact transform `(A, b)` at `tau` seconds from the segment's knot: the rotation
    /// from the segment's rate, the position Hermite on the segment (constant velocity outside
    /// the knots).
    fn exact(&self, tau: f64) -> (M3, V3) {
        let (c1, c2) = so3::rodrigues_coeffs(self.rate * tau.abs());
        let (s1, s2) = (c1 * tau, c2 * tau * tau);
        let a = self.m[0] + self.m[1] * s1 + self.m[2] * s2;
        let wts = match self.h {
            Some(h) => hermite_weights(tau, h),
            None => [1.0, tau, 0.0, 0.0],
        };
        let b = self.g[0]
            + self.g[1] * s1
            + self.g[2] * s2
            + self.np[0] * wts[0]
            + self.np[1] * wts[1]
            + self.np[2] * wts[2]
            + self.np[3] * wts[3];
        (a, b)
    }
}

/// Pieces of a second over which a point's transform is interpolated (2^14: 61 µs, a little
/// over one VLP-32C firing cycle of 55.3 µs).
const PIECES_PER_S: f64 = 16_384.0;

/// Points moved together on vector lanes.
const LANES: usize = 4;

/// The exact transforms at the ends of the pieces of one segment that the points' times fall
/// in, each computed once. Between its ends a point moves by `e_k q + w (d q)`, `d = e_k+1 - e_k`,
/// `w = u - k` (`u` its time in pieces): the transform linear in time. A VLP-32C scan has about
/// 28,700 distinct firing times and 1,650 pieces; the exact transform of each firing time
/// (Rodrigues coefficients, a Hermite curve, two sums of matrices, and the jump to it) was about
/// 60 % of the undistortion of its points. The straight line is off by an eighth of the piece
/// squared times the motion's second derivative: at 4 rad/s by 7e-9 rad (0.7 µm at 100 m, a
/// tenth of an f32's step there), at 20 m/s² by 1e-8 m. A piece lies within its segment (where
/// the rate and the curve change), and a point's transform is a function of its time alone: the
/// same bits on vector lanes or alone, on one thread or in pieces on many.
struct PieceEnds {
    /// The piece index of each slot (NaN: empty), slot `k mod 4`.
    k: [f64; 4],
    /// `A` row-major, then `b`: twelve coefficients.
    e: [[f64; 12]; 4],
}

impl PieceEnds {
    fn new() -> Self {
        Self { k: [f64::NAN; 4], e: [[0.0; 12]; 4] }
    }

    /// The slot of the exact transform at the start of piece `k` (an integer) of `sg`.
    #[inline]
    fn slot(&mut self, sg: &Segment, k: f64, stats: &mut UndistortStats) -> usize {
        let s = (k as i64 & 3) as usize;
        if self.k[s] != k {
            // `k` is an integer: its time is an exact multiple of the piece.
            let (a, b) = sg.exact(k / PIECES_PER_S);
            self.e[s] = core::array::from_fn(|c| if c < 9 { a[(c / 3, c % 3)] } else { b[c - 9] });
            self.k[s] = k;
            stats.transforms += 1;
        }
        s
    }

    /// The ends of the piece that `tau` seconds from `sg`'s knot fall in, and the fraction `w`
    /// of the piece: `(e_k, e_k+1 - e_k, w)`.
    #[inline]
    fn piece(&mut self, sg: &Segment, tau: f64, stats: &mut UndistortStats) -> ([f64; 12], [f64; 12], f64) {
        let u = tau * PIECES_PER_S;
        let k = crate::math::floor_f64(u);
        let s0 = self.slot(sg, k, stats);
        let s1 = self.slot(sg, k + 1.0, stats);
        let (e0, e1) = (self.e[s0], self.e[s1]);
        (e0, core::array::from_fn(|j| e1[j] - e0[j]), u - k)
    }

    /// The transform `(A, b)` at `tau` seconds from `sg`'s knot, for the normals and the
    /// inverse: `e + d w`, each coefficient.
    #[inline]
    fn transform(&mut self, sg: &Segment, tau: f64, stats: &mut UndistortStats) -> (M3, V3) {
        let (e, d, w) = self.piece(sg, tau, stats);
        let c: [f64; 12] = core::array::from_fn(|j| e[j] + d[j] * w);
        (M3::new(c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8]), V3::new(c[9], c[10], c[11]))
    }

    /// A point `q` at `tau` seconds from `sg`'s knot, moved forwards: `e q + w (d q)`, each
    /// row's products summed in order, then its translation (the same operations as [`lanes`]').
    #[inline]
    fn forward(&mut self, sg: &Segment, tau: f64, q: [f64; 3], stats: &mut UndistortStats) -> [f32; 3] {
        let (e, d, w) = self.piece(sg, tau, stats);
        let row =
            |c: &[f64; 12], r: usize| c[3 * r] * q[0] + c[3 * r + 1] * q[1] + c[3 * r + 2] * q[2] + c[9 + r];
        core::array::from_fn(|r| (row(&e, r) + w * row(&d, r)) as f32)
    }
}

/// Four points moved forwards on vector lanes, where all are finite, in `sg` and in two
/// neighbouring pieces at most, the first's the lower (else `None`, and each goes alone): the
/// same operations, so the same bits, as [`PieceEnds::forward`] gives each.
#[inline]
fn lanes(
    block: &[ScanPoint; LANES],
    sg: &Segment,
    ends: &mut PieceEnds,
    stats: &mut UndistortStats,
) -> Option<[[f32; 3]; LANES]> {
    let mut ok = true;
    for p in block {
        let t = p.t as f64;
        // An infinite time can lie in the segment before the first knot (no lower end).
        ok &= p.xyz[0].is_finite() & p.xyz[1].is_finite() & p.xyz[2].is_finite() & p.t.is_finite();
        ok &= (sg.lo <= t) & (t < sg.hi);
    }
    if !ok {
        return None;
    }
    // Plain loops, not `array::from_fn`: its closures stay calls on arm64 where the crate's
    // codegen units fall unluckily (a change elsewhere in the crate is enough).
    let (mut t, mut q) = ([0.0f64; LANES], [[0.0f64; LANES]; 3]);
    for (l, p) in block.iter().enumerate() {
        t[l] = p.t as f64;
        for (qa, x) in q.iter_mut().zip(p.xyz) {
            qa[l] = x as f64;
        }
    }
    let tau = f64x4::from(t) - f64x4::splat(sg.t0);
    let u = tau * f64x4::splat(PIECES_PER_S);
    let k = u.floor();
    let ka = k.to_array();
    let k0 = ka[0];
    if ka.iter().any(|&v| v != k0 && v != k0 + 1.0) {
        return None;
    }
    let two = ka.iter().any(|&v| v != k0);
    let s0 = ends.slot(sg, k0, stats);
    let s1 = ends.slot(sg, k0 + 1.0, stats);
    let s2 = if two { ends.slot(sg, k0 + 2.0, stats) } else { s1 };
    let (e0, e1, e2) = (ends.e[s0], ends.e[s1], ends.e[s2]);
    let w = u - k;
    let q = [f64x4::from(q[0]), f64x4::from(q[1]), f64x4::from(q[2])];
    // `e q + w (d q)` on the lanes of one piece.
    let moved = |e: &[f64; 12], e1: &[f64; 12]| -> [f64x4; 3] {
        let mut d = [0.0f64; 12];
        for ((d, a), b) in d.iter_mut().zip(e).zip(e1) {
            *d = b - a;
        }
        let row = |c: &[f64; 12], r: usize| {
            let s = |j: usize| f64x4::splat(c[j]);
            s(3 * r) * q[0] + s(3 * r + 1) * q[1] + s(3 * r + 2) * q[2] + s(9 + r)
        };
        [row(e, 0) + w * row(&d, 0), row(e, 1) + w * row(&d, 1), row(e, 2) + w * row(&d, 2)]
    };
    let mut p = moved(&e0, &e1);
    if two {
        let hi = k.cmp_ne(f64x4::splat(k0));
        let p1 = moved(&e1, &e2);
        p = [hi.blend(p1[0], p[0]), hi.blend(p1[1], p[1]), hi.blend(p1[2], p[2])];
    }
    let mut out = [[0.0f32; 3]; LANES];
    for (r, v) in p.iter().enumerate() {
        for (l, x) in v.to_array().iter().enumerate() {
            out[l][r] = *x as f32;
        }
    }
    if sg.h.is_none() {
        stats.extrapolated += tau.to_array().iter().filter(|&&v| v != 0.0).count() as u32;
    }
    stats.moved += LANES as u32;
    Some(out)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec::Vec;

    use nalgebra::UnitQuaternion;

    use super::*;
    use crate::eskf::{Eskf, EskfConfig, StateCov};
    use crate::so3::S2;
    use crate::testutil::{G, Helix};

    const T0: u64 = 7_000_000_000;

    /// Two threads' pieces, run one after the other in reverse.
    struct Two;
    impl Parallel for Two {
        fn width(&self) -> usize {
            2
        }
        fn run(&self, jobs: &mut [crate::parallel::Job<'_>]) {
            for j in jobs.iter_mut().rev() {
                j();
            }
        }
    }
    const SCAN: f64 = 0.1;

    fn ext() -> (UnitQuaternion<f64>, V3) {
        (UnitQuaternion::from_euler_angles(0.02, -0.01, core::f64::consts::PI), V3::new(0.1, -0.05, 0.15))
    }

    fn state_at(h: &Helix, t: f64) -> State {
        let m = h.at(t);
        let (er, ep) = ext();
        State {
            rot: m.quat(),
            pos: m.pos,
            ext_rot: er,
            ext_pos: ep,
            vel: m.vel,
            bg: V3::zeros(),
            ba: V3::zeros(),
            grav: S2::new(&V3::new(0.0, 0.0, -G), G),
        }
    }

    /// Box room planes (inward normals n, offsets d: n·q + d = 0 inside-facing).
    fn room() -> [(V3, f64); 6] {
        [
            (V3::x(), 12.0),
            (-V3::x(), 12.0),
            (V3::y(), 10.0),
            (-V3::y(), 10.0),
            (V3::z(), 4.0),
            (-V3::z(), 6.0),
        ]
    }

    /// A 16-beam LiDAR spinning once per scan on the helix: points and normals in the LiDAR frame
    /// at their own firing times, and the index of the plane each hit.
    fn scan(h: &Helix, t_start: f64) -> (Vec<ScanPoint>, Vec<[f32; 3]>, Vec<usize>) {
        let (mut pts, mut ns, mut ids) = (Vec::new(), Vec::new(), Vec::new());
        let cols = 900;
        for c in 0..cols {
            let ts = SCAN * c as f64 / cols as f64;
            let x = state_at(h, t_start + ts);
            let (q_wl, t_wl) = x.lidar_pose();
            let az = 2.0 * core::f64::consts::PI * c as f64 / cols as f64;
            for r in 0..16 {
                let el = (-15.0 + 2.0 * r as f64).to_radians();
                let d_l = V3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                let d_w = q_wl * d_l;
                let (mut best, mut id) = (f64::INFINITY, 0);
                for (k, (n, d)) in room().iter().enumerate() {
                    let den = n.dot(&d_w);
                    if den < -1e-9 {
                        let s = -(n.dot(&t_wl) + d) / den;
                        if s > 0.0 && s < best {
                            best = s;
                            id = k;
                        }
                    }
                }
                let p = d_l * best;
                let n_l = q_wl.inverse() * room()[id].0;
                pts.push(ScanPoint {
                    xyz: [p.x as f32, p.y as f32, p.z as f32],
                    t: ts as f32,
                    row: r,
                    col: c as u16,
                    ..Default::default()
                });
                ns.push([n_l.x as f32, n_l.y as f32, n_l.z as f32]);
                ids.push(id);
            }
        }
        (pts, ns, ids)
    }

    /// Runs the filter through the scan with noise-free 200 Hz IMU samples, recording the knots.
    fn propagate(h: &Helix, t_start: f64, traj: &mut ImuTrajectory<64>) -> Eskf {
        let start_ns = T0;
        let dt_ns = 5_000_000u64;
        // The previous scan ended at t_start; the held sample is the one at or before it.
        let held = h.at(t_start).imu(start_ns);
        let mut f = Eskf::from_state(
            EskfConfig::default(),
            state_at(h, t_start),
            StateCov::zeros(),
            start_ns,
            Some(held),
            1.0,
        );
        traj.clear(start_ns);
        assert_eq!(traj.push(f.time_ns(), f.state()), KnotPush::Stored);
        let end_ns = start_ns + (SCAN * 1e9) as u64;
        let mut k = 1;
        while start_ns + k * dt_ns <= end_ns {
            let t_ns = start_ns + k * dt_ns;
            f.predict(&h.at(t_start + (t_ns - start_ns) as f64 * 1e-9).imu(t_ns));
            traj.push(f.time_ns(), f.state());
            k += 1;
        }
        f.predict_to(end_ns);
        traj.push(f.time_ns(), f.state());
        f
    }

    /// Residuals of points against the planes expressed in the true scan-end LiDAR frame, and the
    /// largest angle between the normals and the true plane normals.
    fn check(h: &Helix, t_end: f64, pts: &[ScanPoint], ns: &[[f32; 3]], ids: &[usize]) -> (f64, f64) {
        let (q, t) = state_at(h, t_end).lidar_pose();
        let (mut worst_d, mut worst_a) = (0.0f64, 0.0f64);
        for ((p, n), &id) in pts.iter().zip(ns).zip(ids) {
            let (nw, d) = room()[id];
            let ne = q.inverse() * nw;
            let de = nw.dot(&t) + d;
            let pv = V3::new(p.xyz[0] as f64, p.xyz[1] as f64, p.xyz[2] as f64);
            worst_d = worst_d.max((ne.dot(&pv) + de).abs());
            let nv = V3::new(n[0] as f64, n[1] as f64, n[2] as f64);
            worst_a = worst_a.max(nv.angle(&ne));
        }
        (worst_d, worst_a)
    }

    /// Points generated on known planes while the sensor moves along the helix (2 m/s, up to
    /// ~1 rad/s; a non-trivial extrinsic): after undistortion with the IMU-propagated poses they
    /// lie on the planes in the true scan-end frame. Measured: 25 µm worst residual over 14,400
    /// points at up to 16 m, normals within 1.9e-6 rad; without undistortion 0.32 m and
    /// 0.032 rad. Bounds: 4x and 5x the measured values.
    #[test]
    fn undistorted_points_and_normals_lie_on_their_planes_at_scan_end() {
        let h = Helix::standard();
        let t_start = 3.0;
        let (mut pts, mut ns, ids) = scan(&h, t_start);
        let (raw_d, raw_a) = check(&h, t_start + SCAN, &pts, &ns, &ids);
        let mut traj = ImuTrajectory::<64>::new();
        let f = propagate(&h, t_start, &mut traj);
        assert_eq!(traj.knots().len(), 21);
        let st = traj.undistort(f.state(), &mut pts, Some(&mut ns)).unwrap();
        let (d, a) = check(&h, t_start + SCAN, &pts, &ns, &ids);
        std::println!("undistort: raw {raw_d:.3} m / {raw_a:.4} rad -> {d:.2e} m / {a:.2e} rad; {st:?}");
        assert!(raw_d > 0.2 && raw_a > 0.02, "the test must have distortion to remove");
        assert!(d < 1e-4, "{d}");
        assert!(a < 1e-5, "{a}");
        assert_eq!(st.moved, 14_400);
        // One exact transform per end of a piece the 900 firing times fall in: 0.1 s of 2^-14 s
        // pieces (0..=1638), 1640 ends.
        assert_eq!(st.transforms, 1640);
        assert_eq!(st.invalid, 0);
    }

    /// The odometry's two steps (points first, while Ring FALS runs; normals after) give the
    /// points and normals of one call, bit for bit, also in pieces on threads.
    #[test]
    fn points_then_normals_equal_both_at_once() {
        let h = Helix::standard();
        let t_start = 3.0;
        let (pts, ns, _) = scan(&h, t_start);
        let mut traj = ImuTrajectory::<64>::new();
        let f = propagate(&h, t_start, &mut traj);
        let (mut p1, mut n1) = (pts.clone(), ns.clone());
        traj.undistort(f.state(), &mut p1, Some(&mut n1)).unwrap();
        for par in [None, Some(&Two as &dyn Parallel)] {
            let (mut p2, mut n2) = (pts.clone(), ns.clone());
            match par {
                None => {
                    traj.undistort(f.state(), &mut p2, None).unwrap();
                    let st = traj.undistort_normals(f.state(), &p2, &mut n2).unwrap();
                    assert_eq!(st.moved, 0);
                }
                Some(p) => {
                    traj.undistort_with(f.state(), &mut p2, None, p).unwrap();
                    traj.undistort_normals(f.state(), &p2, &mut n2).unwrap();
                }
            }
            assert_eq!(p1, p2);
            assert_eq!(n1, n2);
            assert_ne!(ns, n2, "the normals were rotated");
        }
    }

    /// The normals' table: within 0.3 mrad of the exact rotation on the helix, against the room's true normals as
    /// good as the exact undistortion, and the same bits alone ([`NormalRotations::rotate`])
    /// and in the points' pass ([`ImuTrajectory::undistort_rotating`]).
    #[test]
    fn the_normals_table_rotates_as_the_exact_transform_does() {
        let h = Helix::standard();
        let t_start = 3.0;
        let (pts, ns, ids) = scan(&h, t_start);
        let mut traj = ImuTrajectory::<64>::new();
        let f = propagate(&h, t_start, &mut traj);
        let t_max = pts.iter().map(|p| p.t).fold(0.0f32, f32::max);
        let mut table = NormalRotations::new();
        traj.normal_rotations(f.state(), 0.0, t_max, &mut table).unwrap();
        let (mut p1, mut n1) = (pts.clone(), ns.clone());
        traj.undistort(f.state(), &mut p1, Some(&mut n1)).unwrap();
        let (mut p2, mut n2) = (pts.clone(), ns.clone());
        traj.undistort(f.state(), &mut p2, None).unwrap();
        table.rotate(&p2, &mut n2);
        let (mut p3, mut n3) = (pts.clone(), ns.clone());
        traj.undistort_rotating(f.state(), &mut p3, &mut n3, &table).unwrap();
        assert_eq!(p1, p2);
        assert_eq!(p2, p3);
        assert_eq!(n2, n3, "the same bits in the points' pass");
        // Four at a time on lanes, or one at a time, the same bits.
        let mut n4 = ns.clone();
        for i in 0..n4.len() {
            table.rotate(&p2[i..i + 1], &mut n4[i..i + 1]);
        }
        assert_eq!(n2, n4, "the same bits one at a time");
        let mut worst = 0.0f64;
        for (a, b) in n1.iter().zip(&n2) {
            let (a, b) = (
                V3::new(a[0].into(), a[1].into(), a[2].into()),
                V3::new(b[0].into(), b[1].into(), b[2].into()),
            );
            worst = worst.max(a.angle(&b)).max((b.norm() - 1.0).abs());
        }
        // The helix turns at about 1.1 rad/s: half a step of 0.1 s / 256 is 0.2 mrad.
        assert!(worst < 3e-4, "{worst}");
        let (_, exact) = check(&h, t_start + SCAN, &p1, &n1, &ids);
        let (_, tabled) = check(&h, t_start + SCAN, &p2, &n2, &ids);
        assert!(tabled < exact + 3e-4, "{tabled} against {exact}");
        assert_ne!(ns, n2, "the normals were rotated");
        // Invalid normals stay as they are; a scan of one time takes the first rotation.
        let mut zero = [[0.0f32; 3]; 2];
        table.rotate(&p2[..2], &mut zero);
        assert_eq!(zero, [[0.0; 3]; 2]);
        let mut flat = NormalRotations::new();
        traj.normal_rotations(f.state(), 0.05, 0.05, &mut flat).unwrap();
        let mut one = [ns[0]];
        flat.rotate(&p2[..1], &mut one);
        assert!(one[0].iter().all(|v| v.is_finite()));
        // Bounds that are not finite are an error, not a panic, and leave the table as it was.
        let before = (flat.t0, flat.inv_step, flat.rot);
        for (lo, hi) in [(0.0, f32::NAN), (f32::NAN, 0.1), (f32::NEG_INFINITY, 0.1), (0.0, f32::INFINITY)] {
            assert_eq!(
                traj.normal_rotations(f.state(), lo, hi, &mut flat),
                Err(UndistortError::NonFiniteTime)
            );
            assert_eq!((flat.t0, flat.inv_step, flat.rot), before);
        }
        assert_eq!(traj.pose_at(f64::NAN), None);
        assert!(traj.pose_at(f64::INFINITY).is_some_and(|(_, _, extrapolated)| extrapolated));
    }

    /// The segment evaluation is the documented formula with `pose_at`, regrouped: on times
    /// before, between and after the knots (in scan order and shuffled) the two agree to f32
    /// rounding, and extrapolated times are counted alike.
    #[test]
    fn segments_equal_the_pose_at_formula() {
        let h = Helix::standard();
        let t_start = 3.0;
        let mut traj = ImuTrajectory::<64>::new();
        let f = propagate(&h, t_start, &mut traj);
        let x = f.state();
        let mut rng = crate::testutil::Rng::new(3);
        let mut pts: Vec<ScanPoint> = (0..4000)
            .map(|i| ScanPoint {
                xyz: [(rng.uniform() * 40.0 - 20.0) as f32, (rng.uniform() * 40.0 - 20.0) as f32, 1.5],
                // -10 ms .. 110 ms: before the first knot, on the knots and after the last.
                t: if i % 7 == 0 { (i / 7) as f32 * 0.005 } else { (rng.uniform() * 0.12 - 0.01) as f32 },
                ..Default::default()
            })
            .collect();
        let orig = pts.clone();
        let st = traj.undistort(x, &mut pts, None).unwrap();
        let r_e_t = x.rot.to_rotation_matrix().into_inner().transpose();
        let r_il = x.ext_rot.to_rotation_matrix().into_inner();
        let mut extrapolated = 0;
        for (p, o) in pts.iter().zip(&orig) {
            let (r_t, p_t, extra) = traj.pose_at(o.t as f64).unwrap();
            extrapolated += u32::from(extra);
            let q = V3::new(o.xyz[0] as f64, o.xyz[1] as f64, o.xyz[2] as f64);
            let want = r_il.transpose() * (r_e_t * (r_t * (r_il * q + x.ext_pos) + p_t - x.pos) - x.ext_pos);
            for a in 0..3 {
                assert!((p.xyz[a] as f64 - want[a]).abs() < 1e-5, "t {}: {:?} vs {want:?}", o.t, p.xyz);
            }
        }
        assert_eq!(st.extrapolated, extrapolated);
        assert!(extrapolated > 100 && extrapolated < 4000);
    }

    /// Each point's transform is a function of its time alone: a scan moved at once (four
    /// points at a time on vector lanes where they can go together: a firing order with 16
    /// times per 55 µs column, then blocks across two pieces, across knots, out of order,
    /// with invalid points and times outside the knots) equals each point moved alone, bit
    /// for bit, points and table-turned normals alike, and in pieces on threads.
    #[test]
    fn points_moved_together_equal_points_moved_alone() {
        let h = Helix::standard();
        let mut traj = ImuTrajectory::<64>::new();
        let f = propagate(&h, 3.0, &mut traj);
        let x = f.state();
        let mut rng = crate::testutil::Rng::new(11);
        let mut pts: Vec<ScanPoint> = Vec::new();
        for c in 0..2000u32 {
            for r in 0..8u32 {
                let t = match c {
                    // Out of order, and outside the knots.
                    0..100 => (rng.uniform() * 0.14 - 0.02) as f32,
                    _ => (c as f64 * 55.296e-6 + (r / 2) as f64 * 2.304e-6) as f32,
                };
                let mut p = ScanPoint {
                    xyz: [(rng.uniform() * 80.0 - 40.0) as f32, (rng.uniform() * 80.0 - 40.0) as f32, 1.5],
                    t,
                    ..Default::default()
                };
                if rng.uniform() < 0.01 {
                    p.xyz[1] = f32::NAN;
                }
                // Infinite times among those before the first knot, whose segment has no
                // lower end.
                if c < 100 && rng.uniform() < 0.05 {
                    p.t = if r % 2 == 0 { f32::NEG_INFINITY } else { f32::INFINITY };
                }
                pts.push(p);
            }
        }
        // A whole block of infinite times right after a point before the first knot: the
        // extrapolation's segment there has no lower end.
        for t in [-0.015, f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY, -0.015]
        {
            pts.push(ScanPoint { xyz: [3.0, 4.0, 1.5], t, ..Default::default() });
        }
        let normals: Vec<[f32; 3]> =
            (0..pts.len()).map(|i| if i % 13 == 0 { [0.0; 3] } else { [0.6, 0.0, 0.8] }).collect();
        let t_max = pts.iter().map(|p| p.t).filter(|t| t.is_finite()).fold(0.0f32, f32::max);
        let mut table = NormalRotations::new();
        traj.normal_rotations(x, 0.0, t_max, &mut table).unwrap();
        let (mut p1, mut n1) = (pts.clone(), normals.clone());
        let st = traj.undistort_rotating(x, &mut p1, &mut n1, &table).unwrap();
        let (mut p2, mut n2) = (pts.clone(), normals.clone());
        for i in 0..pts.len() {
            traj.undistort_rotating(x, &mut p2[i..i + 1], &mut n2[i..i + 1], &table).unwrap();
        }
        let bits = |v: &[ScanPoint]| v.iter().map(|p| p.xyz.map(f32::to_bits)).collect::<Vec<_>>();
        assert_eq!(bits(&p1), bits(&p2));
        assert_eq!(n1, n2);
        let mut p3 = pts.clone();
        traj.undistort_with(x, &mut p3, None, &Two).unwrap();
        assert_eq!(bits(&p1), bits(&p3));
        let mut n3 = normals.clone();
        table.rotate(&p3, &mut n3);
        assert_eq!(n1, n3);
        assert_eq!(st.invalid as usize, pts.iter().filter(|p| p.xyz[1].is_nan() || !p.t.is_finite()).count());
        assert_eq!(st.moved + st.invalid, pts.len() as u32);
        assert!(st.extrapolated > 0);
    }

    /// The interpolated transform is the exact one to well below an f32's step: on the helix
    /// (1.1 rad/s, a non-trivial extrinsic) over every 7 µs of a scan and outside its knots,
    /// the rotation within 1e-9 (the straight line's bound is 6e-10) and the translation within
    /// 1e-8 m of the segment's exact transform.
    #[test]
    fn the_pieces_interpolate_the_exact_transform() {
        let h = Helix::standard();
        let mut traj = ImuTrajectory::<64>::new();
        let f = propagate(&h, 3.0, &mut traj);
        let frame = ImuTrajectory::<64>::frame(f.state());
        let mut stats = UndistortStats::default();
        let (mut worst_a, mut worst_b) = (0.0f64, 0.0f64);
        for i in 0..17_000 {
            let t = -0.01 + i as f64 * 7e-6;
            let sg = traj.segment(t, &frame).unwrap();
            let mut ends = PieceEnds::new();
            let (a, b) = ends.transform(&sg, t - sg.t0, &mut stats);
            let (ea, eb) = sg.exact(t - sg.t0);
            worst_a = worst_a.max((a - ea).abs().max());
            worst_b = worst_b.max((b - eb).abs().max());
        }
        std::println!("pieces: rotation {worst_a:.1e}, translation {worst_b:.1e} m");
        assert!(worst_a < 1e-9, "{worst_a}");
        assert!(worst_b < 1e-8, "{worst_b}");
        assert!(worst_a > 0.0, "the test must interpolate");
    }

    #[test]
    fn interpolation_is_exact_at_knots_and_extrapolates_outside() {
        let h = Helix::standard();
        let mut traj = ImuTrajectory::<64>::new();
        propagate(&h, 1.0, &mut traj);
        for k in traj.knots() {
            let (r, p, extra) = traj.pose_at(k.t).unwrap();
            assert!(!extra);
            assert!((r - k.rot).amax() < 1e-14 && (p - k.pos).amax() < 1e-12);
        }
        let (_, _, extra) = traj.pose_at(-0.01).unwrap();
        assert!(extra);
        let (_, p, extra) = traj.pose_at(SCAN + 0.01).unwrap();
        assert!(extra);
        let last = traj.knots().last().unwrap();
        assert!((p - (last.pos + last.vel * 0.01)).norm() < 1e-12);
    }

    #[test]
    fn full_buffer_merges_the_last_segment_and_bad_knots_are_ignored() {
        let h = Helix::standard();
        let mut traj = ImuTrajectory::<4>::new();
        traj.clear(T0);
        let mut results = Vec::new();
        for k in 0..6u64 {
            results.push(traj.push(T0 + k * 5_000_000, &state_at(&h, k as f64 * 0.005)));
        }
        assert_eq!(results[..4], [KnotPush::Stored; 4]);
        assert_eq!(results[4..], [KnotPush::Merged; 2]);
        assert_eq!(traj.merged(), 2);
        // The buffer ends at the newest pose, and the merged segment is consistent with it.
        let last = traj.knots()[3];
        assert!((last.t - 0.025).abs() < 1e-12);
        let (r, _, _) = traj.pose_at(0.025 - 1e-12).unwrap();
        assert!((r - last.rot).amax() < 1e-9);
        // Older, equal and non-finite knots are ignored.
        assert_eq!(traj.push(T0 + 25_000_000, &state_at(&h, 0.0)), KnotPush::Ignored);
        let mut bad = state_at(&h, 0.03);
        bad.pos.x = f64::NAN;
        assert_eq!(traj.push(T0 + 30_000_000, &bad), KnotPush::Ignored);
        assert_eq!(traj.ignored(), 2);
    }

    #[test]
    fn redistort_inverts_undistort_and_span_to_interpolates_between_its_two_knots() {
        let h = Helix::standard();
        let mut traj = ImuTrajectory::<64>::new();
        let end = *propagate(&h, 1.0, &mut traj).state();
        let mut pts: Vec<ScanPoint> = (0..200)
            .map(|i| {
                let a = i as f32 * 0.1;
                ScanPoint {
                    xyz: [5.0 * a.cos(), 4.0 * a.sin(), 1.0 + 0.01 * i as f32],
                    t: i as f32 * 0.0005,
                    ..Default::default()
                }
            })
            .collect();
        let mut ns: Vec<[f32; 3]> =
            (0..200).map(|i| if i % 2 == 0 { [0.0, 0.6, 0.8] } else { [0.0; 3] }).collect();
        let (p0, n0) = (pts.clone(), ns.clone());
        traj.undistort(&end, &mut pts, Some(&mut ns)).unwrap();
        assert!(pts.iter().zip(&p0).any(|(a, b)| (a.xyz[0] - b.xyz[0]).abs() > 1e-3));
        let st = traj.redistort(&end, &mut pts, Some(&mut ns)).unwrap();
        assert_eq!(st.moved, 200);
        for ((a, b), (m, n)) in pts.iter().zip(&p0).zip(ns.iter().zip(&n0)) {
            assert!((0..3).all(|k| (a.xyz[k] - b.xyz[k]).abs() < 1e-5 && (m[k] - n[k]).abs() < 1e-5));
        }
        // Two knots: the first one's pose and the end state's, a straight line between.
        let span = traj.span_to(T0 + (SCAN * 1e9) as u64, &end);
        assert_eq!(span.knots().len(), 2);
        let (a, b) = (span.knots()[0], span.knots()[1]);
        assert_eq!((a.rot, a.pos), (traj.knots()[0].rot, traj.knots()[0].pos));
        assert!((b.pos - end.pos).norm() < 1e-12);
        let (_, p, extra) = span.pose_at(0.5 * (a.t + b.t)).unwrap();
        assert!(!extra && (p - 0.5 * (a.pos + b.pos)).norm() < 1e-12);
    }

    #[test]
    fn bad_points_are_counted_and_left_alone_and_errors_are_reported() {
        let h = Helix::standard();
        let x = state_at(&h, 0.0);
        let mut traj = ImuTrajectory::<8>::new();
        traj.clear(T0);
        let mut pts = [ScanPoint { xyz: [1.0, 2.0, 3.0], t: 0.0, ..Default::default() }; 3];
        pts[1].t = f32::NAN;
        pts[2].xyz[0] = f32::INFINITY;
        assert_eq!(traj.undistort(&x, &mut pts, None), Err(UndistortError::NoPoses));
        traj.push(T0, &x);
        let mut ns = [[0.0f32; 3]; 2];
        assert_eq!(traj.undistort(&x, &mut pts, Some(&mut ns)), Err(UndistortError::LengthMismatch));
        let mut ns = [[0.0, 0.0, 1.0], [0.0; 3], [f32::NAN; 3]];
        let before = pts;
        let st = traj.undistort(&x, &mut pts, Some(&mut ns)).unwrap();
        assert_eq!((st.moved, st.invalid), (1, 2));
        assert_eq!(pts[1].xyz, before[1].xyz);
        assert_eq!(pts[2].xyz, before[2].xyz);
        // A single knot at the end state: the identity.
        assert!((pts[0].xyz[0] - 1.0).abs() < 1e-6 && (pts[0].xyz[2] - 3.0).abs() < 1e-6);
        assert!((ns[0][2] - 1.0).abs() < 1e-6);
        assert_eq!(ns[1], [0.0; 3]);
        assert!(ns[2][0].is_nan());
    }
}
