//! Stage 2, each pixel's normal from its 3x3 window: full windows a row at a time, incomplete
//! ones 8 at a time through the masked least squares; separate from the storage it fills.

use super::median::round_small;
use super::table::{CENTRE, RingTable, RowCoeffs, adjugate_f32};
use super::trimmed::solve_trimmed_lanes;
use super::{
    EMPTY, FULL, GAP, INVALID, KEY_EMPTY, KEY_SCALE, PAD, PARTIAL, RingFals, RingFalsConfig, has_normal,
    wrap_row,
};

/// Lanes of the gap-aware solve (f32): 8 neighbouring columns.
pub(super) const LANES: usize = 8;
/// What the masked solve hands the trimmed solve per window: the solution over every point
/// present (3 values, the same bits as solving it again) and 1.0 where its system passed the
/// determinant and conditioning tests (else 0.0).
pub(super) const PRE: usize = 4;

/// Pixels of one row waiting for the lane-parallel masked or trimmed solve: their windows'
/// inverse ranges and azimuths (and, for the trimmed solve, [`PRE`]).
#[derive(Clone, Copy, Debug)]
struct WindowBatch {
    len: usize,
    px: [usize; LANES],
    w9: [[f32; LANES]; 9],
    ca: [f32; LANES],
    sa: [f32; LANES],
    pre: [[f32; LANES]; PRE],
}

impl WindowBatch {
    const EMPTY: Self = Self {
        len: 0,
        px: [0; LANES],
        w9: [[0.0; LANES]; 9],
        ca: [0.0; LANES],
        sa: [0.0; LANES],
        pre: [[0.0; LANES]; PRE],
    };

    /// Adds pixel `px` with its window's inverse ranges and azimuth; whether the batch is full.
    #[inline(always)]
    fn push(&mut self, px: usize, w9: [f32; 9], (ca, sa): (f32, f32)) -> bool {
        let j = self.len;
        self.px[j] = px;
        for k in 0..9 {
            self.w9[k][j] = w9[k];
        }
        (self.ca[j], self.sa[j]) = (ca, sa);
        self.len += 1;
        self.len == LANES
    }
}

/// Two window batches filled in turn. A batch that fills is solved only when the other one
/// fills too: a batch solved at once loads, as vectors, the values its last pixel stored one by
/// one a moment before, and those loads wait until the stores reach the cache (a store is not
/// forwarded into a wider load); a batch older by one fill has long reached it.
#[derive(Clone, Copy, Debug)]
struct BatchPair {
    b: [WindowBatch; 2],
    cur: usize,
}

impl BatchPair {
    const EMPTY: Self = Self { b: [WindowBatch::EMPTY; 2], cur: 0 };

    /// Adds a pixel. When that fills the current batch, the other one becomes current and is
    /// returned if it holds the previous full batch, to be solved (and emptied) at once.
    #[inline(always)]
    fn push(&mut self, px: usize, w9: [f32; 9], cs: (f32, f32)) -> Option<&mut WindowBatch> {
        self.push_pre(px, w9, cs, None)
    }

    /// [`Self::push`] with the masked solve's [`PRE`] values of the pixel.
    #[inline(always)]
    fn push_pre(
        &mut self,
        px: usize,
        w9: [f32; 9],
        cs: (f32, f32),
        pre: Option<[f32; PRE]>,
    ) -> Option<&mut WindowBatch> {
        if let Some(v) = pre {
            let b = &mut self.b[self.cur];
            for i in 0..PRE {
                b.pre[i][b.len] = v[i];
            }
        }
        if self.b[self.cur].push(px, w9, cs) {
            self.cur ^= 1;
            let other = &mut self.b[self.cur];
            if other.len > 0 {
                return Some(other);
            }
        }
        None
    }

    /// The batch to solve at the end of a row, older first; `None` when both are empty.
    fn pending(&mut self) -> Option<&mut WindowBatch> {
        let older = self.cur ^ 1;
        if self.b[older].len > 0 {
            Some(&mut self.b[older])
        } else if self.b[self.cur].len > 0 {
            Some(&mut self.b[self.cur])
        } else {
            None
        }
    }
}

impl<const P: usize> RingFals<P> {
    /// Stage 2: per pixel, the Ring FALS normal from its 3x3 window (full windows vectorised,
    /// incomplete ones through the gap-aware solve), oriented toward the sensor and normalised.
    pub fn solve(&mut self, table: &RingTable) {
        let (rows, cols, stride) = (self.rows, self.cols, self.stride);
        if rows == 0 || table.rows() != rows || table.cols() != cols {
            return;
        }
        // Inverse range of every image row, then wrap its pad columns.
        for r in PAD..PAD + rows {
            let src = &self.range2[r * stride..(r + 1) * stride];
            let dst = &mut self.inv[r * stride..(r + 1) * stride];
            for (d, &s) in dst.iter_mut().zip(src) {
                *d = if s > 0.0 { rsqrt(s) } else { 0.0 };
            }
            wrap_row(&mut self.inv[r * stride..(r + 1) * stride], cols);
            let (w, key) =
                (&self.inv[r * stride..(r + 1) * stride], &mut self.key[r * stride..(r + 1) * stride]);
            for (k, &w) in key.iter_mut().zip(w) {
                // Within +-32000 for any range the config allows; clamped all the same.
                let key = round_small((log2_approx(w) * KEY_SCALE).clamp(-32000.0, 32000.0));
                *k = if w > 0.0 { key as i16 } else { KEY_EMPTY };
            }
        }

        let abs = table.config.range_jump_abs;
        let rel = table.config.fit_tolerance_rel;
        let mut gap_solves = 0u32;
        let mut trimmed = 0u32;
        let mut valid = 0u32;
        let mut invalid = 0u32;
        let mut partial = BatchPair::EMPTY;
        let mut trim = BatchPair::EMPTY;
        for r in 0..rows {
            let rc = &table.row[r];
            let base = (r + PAD) * stride + PAD;
            {
                let up = &self.inv[base - stride - 1..][..cols + 2];
                let mid = &self.inv[base - 1..][..cols + 2];
                let dn = &self.inv[base + stride - 1..][..cols + 2];
                let cs = (&table.col_cos[..cols], &table.col_sin[..cols]);
                let nx = &mut self.nx[base..][..cols];
                let ny = &mut self.ny[base..][..cols];
                let nz = &mut self.nz[base..][..cols];
                let state = &mut self.state[base..][..cols];
                solve_row_full(rc, abs, rel, up, mid, dn, cs, nx, ny, nz, state);
            }
            // Incomplete windows, gathered LANES at a time: the masked least squares over the
            // neighbours present; windows that still fail the plane-fit check go to the
            // trimmed solve, gathered LANES at a time as well.
            // They are found by the set bits of a mask per 64 columns: a test per pixel would
            // be a mispredicted jump at every one of them.
            for c0 in (0..cols).step_by(64) {
                let st = &self.state[base + c0..base + cols.min(c0 + 64)];
                let mut bits =
                    st.iter().enumerate().fold(0u64, |m, (i, &s)| m | (u64::from(s == PARTIAL) << i));
                while bits != 0 {
                    let c = c0 + bits.trailing_zeros() as usize;
                    bits &= bits - 1;
                    let px = base + c;
                    let w9 = core::array::from_fn(|k| self.inv[px + (k / 3) * stride + (k % 3) - stride - 1]);
                    if let Some(full) = partial.push(px, w9, table.azimuth_cs(r, c)) {
                        trimmed += self.finish_partial(rc, &table.config, full, &mut trim);
                    }
                }
            }
            while let Some(b) = partial.pending() {
                trimmed += self.finish_partial(rc, &table.config, b, &mut trim);
            }
            while let Some(b) = trim.pending() {
                self.finish_trimmed(rc, &table.config, b);
            }
            for &st in &self.state[base..base + cols] {
                valid += u32::from(has_normal(st));
                gap_solves += u32::from(st == GAP);
                invalid += u32::from(st == INVALID);
            }
        }
        self.stats.gap_solves = gap_solves;
        self.stats.trimmed_solves = trimmed;
        self.stats.valid_pixels = valid;
        self.stats.invalid_pixels = invalid;
    }

    /// Runs the masked solve on the gathered incomplete windows of one row: writes the normals
    /// and states of those it decides and moves those to be trimmed into `trim` (solving the
    /// full batch `trim` hands back). Empties the batch; returns how many went to the trimmed
    /// solve.
    fn finish_partial(
        &mut self,
        rc: &RowCoeffs,
        cfg: &RingFalsConfig,
        batch: &mut WindowBatch,
        trim: &mut BatchPair,
    ) -> u32 {
        if batch.len == 0 {
            return 0;
        }
        let (n, verdict, pre) = solve_group_masked(rc, cfg, &batch.w9, &batch.ca, &batch.sa);
        let mut trimmed = 0;
        for l in 0..batch.len {
            let px = batch.px[l];
            match verdict[l] {
                GAP => {
                    self.nx[px] = n[0][l];
                    self.ny[px] = n[1][l];
                    self.nz[px] = n[2][l];
                    self.state[px] = GAP;
                }
                TRIM => {
                    trimmed += 1;
                    let w9 = core::array::from_fn(|k| batch.w9[k][l]);
                    let p = core::array::from_fn(|i| pre[i][l]);
                    if let Some(full) = trim.push_pre(px, w9, (batch.ca[l], batch.sa[l]), Some(p)) {
                        self.finish_trimmed(rc, cfg, full);
                    }
                }
                _ => {
                    self.nx[px] = 0.0;
                    self.ny[px] = 0.0;
                    self.nz[px] = 0.0;
                    self.state[px] = INVALID;
                }
            }
        }
        batch.len = 0;
        trimmed
    }

    /// Runs the trimmed solve on the gathered pixels of one row and writes their normals and
    /// states; empties the batch.
    fn finish_trimmed(&mut self, rc: &RowCoeffs, cfg: &RingFalsConfig, batch: &mut WindowBatch) {
        if batch.len == 0 {
            return;
        }
        let active: [bool; LANES] = core::array::from_fn(|l| l < batch.len);
        let (n, valid) = solve_trimmed_lanes(rc, cfg, &batch.w9, &batch.ca, &batch.sa, &active, &batch.pre);
        for l in 0..batch.len {
            let px = batch.px[l];
            self.nx[px] = n[0][l];
            self.ny[px] = n[1][l];
            self.nz[px] = n[2][l];
            self.state[px] = if valid[l] { GAP } else { INVALID };
        }
        batch.len = 0;
    }
}

/// log2(x) for finite x > 0 from the float's exponent and a quartic in its mantissa (error
/// below 2.1e-4), in f32 arithmetic only so that it vectorises.
#[inline(always)]
pub(super) fn log2_approx(x: f32) -> f32 {
    let bits = x.to_bits();
    let e = ((bits >> 23) & 0xff) as i32 - 127;
    let f = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    let p = -2.496_773_8 + f * (4.028_373 + f * (-2.081_060_2 + f * (0.628_815_7 + f * -0.079_150_37)));
    e as f32 + p
}

/// 1/sqrt(x) for x > 0 in f32 arithmetic only (so that it vectorises and gives the same bits on
/// every target): [`rsqrt_norm`] refined by a third Newton step, relative error below 2e-7.
#[inline(always)]
pub(super) fn rsqrt(x: f32) -> f32 {
    let y = rsqrt_norm(x);
    y * (1.5 - 0.5 * x * y * y)
}

/// 1/sqrt(x) for normalising a vector: a bit-level first guess refined by two Newton steps,
/// relative error below 5e-6 (the median quantises normals to 3e-5). [`rsqrt`]'s third step
/// would be a quarter of the full-window solve's arithmetic.
#[inline(always)]
pub(super) fn rsqrt_norm(x: f32) -> f32 {
    let y = f32::from_bits(0x5f37_5a86u32.wrapping_sub(x.to_bits() >> 1));
    let h = 0.5 * x;
    let y = y * (1.5 - h * y * y);
    y * (1.5 - h * y * y)
}

/// The full-window solve of one image row, vectorisable: writes the oriented unit normal and
/// FULL for pixels whose complete window passed the gates, zero and PARTIAL for pixels with a
/// return whose window is incomplete, zero and EMPTY for pixels without a return.
#[allow(clippy::too_many_arguments)]
#[inline(never)]
pub(super) fn solve_row_full(
    rc: &RowCoeffs,
    abs: f32,
    rel: f32,
    up: &[f32],
    mid: &[f32],
    dn: &[f32],
    cs: (&[f32], &[f32]),
    nx: &mut [f32],
    ny: &mut [f32],
    nz: &mut [f32],
    state: &mut [u8],
) {
    let n = nx.len();
    let (up, mid, dn) = (&up[..n + 2], &mid[..n + 2], &dn[..n + 2]);
    let (col_cos, col_sin) = (&cs.0[..n], &cs.1[..n]);
    let (ny, nz, state) = (&mut ny[..n], &mut nz[..n], &mut state[..n]);
    let [u0, u1, u2] = rc.u;
    let mi = rc.minv;
    let nominal = rc.nominal_ok;
    for j in 0..n {
        let w = [up[j], up[j + 1], up[j + 2], mid[j], mid[j + 1], mid[j + 2], dn[j], dn[j + 1], dn[j + 2]];
        let wc = w[CENTRE];
        let mut b = [0.0f32; 3];
        let mut ww = 0.0f32;
        for k in 0..9 {
            b[0] += u0[k] * w[k];
            b[1] += u1[k] * w[k];
            b[2] += u2[k] * w[k];
            ww += w[k] * w[k];
        }
        let m0 = mi[0] * b[0] + mi[1] * b[1] + mi[2] * b[2];
        let m1 = mi[1] * b[0] + mi[3] * b[1] + mi[4] * b[2];
        let m2 = mi[2] * b[0] + mi[4] * b[1] + mi[5] * b[2];
        // Plane-fit check (see FIT_K): the sum of squared residuals of the nine equations,
        // sum w^2 - m . b'. A neighbour without a return (w = 0, a point at infinity) fails it,
        // so does one on another surface; neighbours outside the image (u = 0, w = 0) do not
        // count.
        let tol = wc * (rel + abs * wc);
        let ssr = ww - (m0 * b[0] + m1 * b[1] + m2 * b[2]);
        let mut ok = wc > 0.0 && ssr <= FIT_K * tol * tol;
        let (cc, sc) = (col_cos[j], col_sin[j]);
        let (ca, sa) = (rc.ca0 * cc - rc.sa0 * sc, rc.sa0 * cc + rc.ca0 * sc);
        let (v, o) = to_global(rc, m0, m1, m2, ca, sa);
        ok &= nominal & o;
        nx[j] = if ok { v[0] } else { 0.0 };
        ny[j] = if ok { v[1] } else { 0.0 };
        nz[j] = if ok { v[2] } else { 0.0 };
        state[j] = if ok {
            FULL
        } else if wc > 0.0 {
            PARTIAL
        } else {
            EMPTY
        };
    }
}

/// From the scaled local solution (m0 along the ray, m1 and m2 the scaled tangent parts) to the
/// unit normal in the LiDAR frame, pointing toward the sensor. The second value is false when
/// the solution is unusable (not finite, zero, or its plane equation does not face the sensor:
/// `n . p = 1` requires m0 > 0).
#[inline(always)]
pub(super) fn to_global(rc: &RowCoeffs, m0: f32, m1: f32, m2: f32, ca: f32, sa: f32) -> ([f32; 3], bool) {
    let t1 = m1 * rc.inv_dh;
    let t2 = m2 * rc.inv_dv;
    let h = m0 * rc.ce - t2 * rc.se;
    let x = ca * h - sa * t1;
    let y = sa * h + ca * t1;
    let z = m0 * rc.se + t2 * rc.ce;
    let n2 = x * x + y * y + z * z;
    // FALS normals point away from the sensor (m0 > 0): flip them toward it.
    let s = -rsqrt_norm(n2);
    let ok = (m0 > 0.0) & (n2 > 1e-30) & (n2 < 1e30);
    ([x * s, y * s, z * s], ok)
}

/// The plane-fit check: a window's squared residuals (in inverse range) may sum to at most
/// `FIT_K tol^2`, `tol = wc (fit_tolerance_rel + range_jump_abs wc)` being the inverse-range form
/// of `fit_tolerance_rel r + range_jump_abs`. Range noise of `s` per point passes while its
/// expected sum `6 s^2` stays below that (`s` up to 0.8 `tol`); a single point off the plane by
/// more than about 2.2 `tol` fails it, wherever the noise.
pub(super) const FIT_K: f32 = 4.0;

/// Whether a window neighbour with inverse range `w` takes part in the centre's solve: it has
/// a return and its range is within the gate (`gate`: the relative part for its angular
/// distance plus the absolute part) of the centre's (inverse range `wc`). Written so that NaN
/// fails.
#[inline(always)]
pub(super) fn on_surface(w: f32, wc: f32, gate: f32) -> bool {
    (w > 0.0) & ((wc - w).abs() <= w * gate)
}

/// Verdict of the masked solve: the system is sound but some points are off the plane (the
/// trimmed solve is next).
pub(super) const TRIM: u8 = 5;

/// The gap-aware solve of 8 neighbouring pixels at once (branch-free, so it vectorises): the
/// least squares over each window's present neighbours (a return, within the range gate), `M'`
/// and `b'` as masked sums. Per lane: GAP with the normal when the plane fits every point,
/// TRIM when the system is sound but some point is off the plane, INVALID when too few points
/// are present or the system is ill-conditioned (which includes all points on one image line).
/// Also returns the solutions for the trimmed solve ([`PRE`]).
#[inline(always)]
pub(super) fn solve_group_masked(
    rc: &RowCoeffs,
    cfg: &RingFalsConfig,
    w9: &[[f32; LANES]; 9],
    ca: &[f32; LANES],
    sa: &[f32; LANES],
) -> ([[f32; LANES]; 3], [u8; LANES], [[f32; LANES]; PRE]) {
    let wc = w9[CENTRE];
    let t: [f32; LANES] = core::array::from_fn(|l| cfg.range_jump_abs * wc[l]);
    let mut m = [[0.0f32; LANES]; 6];
    let mut b = [[0.0f32; LANES]; 3];
    let mut ww = [0.0f32; LANES];
    let mut count = [0.0f32; LANES];
    for k in 0..9 {
        if (rc.exists >> k) & 1 == 0 {
            continue;
        }
        let g = rc.gate[k];
        let uu: [f32; 6] = core::array::from_fn(|i| rc.uu[i][k]);
        let u = [rc.u[0][k], rc.u[1][k], rc.u[2][k]];
        let w = &w9[k];
        for l in 0..LANES {
            let present = on_surface(w[l], wc[l], g + t[l]);
            let p = if present { 1.0f32 } else { 0.0 };
            let pw = p * w[l];
            for i in 0..6 {
                m[i][l] += p * uu[i];
            }
            b[0][l] += pw * u[0];
            b[1][l] += pw * u[1];
            b[2][l] += pw * u[2];
            ww[l] += pw * w[l];
            count[l] += p;
        }
    }
    let mut out = [[0.0f32; LANES]; 3];
    let mut verdict = [INVALID; LANES];
    let mut pre = [[0.0f32; LANES]; PRE];
    for l in 0..LANES {
        let mm = [m[0][l], m[1][l], m[2][l], m[3][l], m[4][l], m[5][l]];
        let bb = [b[0][l], b[1][l], b[2][l]];
        let (adj, det) = adjugate_f32(&mm);
        let tr = mm[0] + mm[3] + mm[5];
        let system = (det > 0.0) & (27.0 * det >= cfg.min_conditioning * tr * tr * tr);
        let sound = (wc[l] > 0.0) & (count[l] >= cfg.min_points as f32) & system;
        let s = 1.0 / det;
        let m0 = (adj[0] * bb[0] + adj[1] * bb[1] + adj[2] * bb[2]) * s;
        let m1 = (adj[1] * bb[0] + adj[3] * bb[1] + adj[4] * bb[2]) * s;
        let m2 = (adj[2] * bb[0] + adj[4] * bb[1] + adj[5] * bb[2]) * s;
        (pre[0][l], pre[1][l], pre[2][l]) = (m0, m1, m2);
        pre[3][l] = if system { 1.0 } else { 0.0 };
        let tol = wc[l] * (cfg.fit_tolerance_rel + t[l]);
        let fits = ww[l] - (m0 * bb[0] + m1 * bb[1] + m2 * bb[2]) <= FIT_K * tol * tol;
        let (v, ok) = to_global(rc, m0, m1, m2, ca[l], sa[l]);
        verdict[l] = if sound & fits & ok {
            GAP
        } else if sound {
            TRIM
        } else {
            INVALID
        };
        out[0][l] = v[0];
        out[1][l] = v[1];
        out[2][l] = v[2];
    }
    (out, verdict, pre)
}
