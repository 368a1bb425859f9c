//! The trimmed solve, branch-free over 8 pixels: windows with points off the plane solved again
//! without their worst point or an edge line; separate as the solve's longest lane code.

use super::RingFalsConfig;
use super::solve::{FIT_K, LANES, PRE, on_surface, to_global};
use super::table::{CENTRE, RowCoeffs, adjugate_f32};

/// [`solve_trimmed`] for up to [`LANES`] pixels of one row at once (lanes with `active` unset
/// are ignored), branch-free across lanes so that it vectorises: every lane solves the same
/// candidates with its own mask of points, until every lane has its verdict. `pre` is
/// [`solve_group_masked`]'s solution of the same windows ([`PRE`]). The arithmetic is
/// [`solve_trimmed`]'s, term by term in the same order, so the results are the same bits.
/// Returns the normals and which lanes have one.
///
/// [`solve_trimmed`]: super::reference::solve_trimmed
/// [`solve_group_masked`]: super::solve::solve_group_masked
#[inline(always)]
pub(super) fn solve_trimmed_lanes(
    rc: &RowCoeffs,
    cfg: &RingFalsConfig,
    w9: &[[f32; LANES]; 9],
    ca: &[f32; LANES],
    sa: &[f32; LANES],
    active: &[bool; LANES],
    pre: &[[f32; LANES]; PRE],
) -> ([[f32; LANES]; 3], [bool; LANES]) {
    let wc = w9[CENTRE];
    let t: [f32; LANES] = core::array::from_fn(|l| cfg.range_jump_abs * wc[l]);
    let tol: [f32; LANES] = core::array::from_fn(|l| wc[l] * (cfg.fit_tolerance_rel + t[l]));
    let mut mask = [0u32; LANES];
    for k in 0..9 {
        if rc.exists & (1 << k) == 0 {
            continue;
        }
        let w = &w9[k];
        for l in 0..LANES {
            let present = on_surface(w[l], wc[l], rc.gate[k] + t[l]);
            mask[l] |= u32::from(present) << k;
        }
    }
    let mut done: [bool; LANES] = core::array::from_fn(|l| !active[l] | !(wc[l] > 0.0));
    let mut valid = [false; LANES];
    let mut out = [[0.0f32; LANES]; 3];
    // The right-hand side's terms u_i w of every window point, the same in every pass.
    let mut uw = [[[0.0f32; LANES]; 3]; 9];
    for k in 0..9 {
        for i in 0..3 {
            let u = rc.u[i][k];
            for l in 0..LANES {
                uw[k][i][l] = u * w9[k][l];
            }
        }
    }
    // The masked solve's plane of every point present (`pre`), and the point farthest off it
    // (first of equals in window order, as the scalar loop keeps it).
    let mut worst_e = [0.0f32; LANES];
    let mut worst_k = [u32::MAX; LANES];
    for k in 0..9 {
        if k == CENTRE {
            continue;
        }
        let u = [rc.u[0][k], rc.u[1][k], rc.u[2][k]];
        for l in 0..LANES {
            let present = (mask[l] >> k) & 1 != 0;
            let e = (u[0] * pre[0][l] + u[1] * pre[1][l] + u[2] * pre[2][l] - w9[k][l]).abs();
            // A blend by bit masks: as a select, it compiled to masked stores that the next
            // k's loads waited on (no store forwarding from a masked store).
            let take = u32::from(present & !(e <= worst_e[l])).wrapping_neg();
            worst_e[l] = f32::from_bits((e.to_bits() & take) | (worst_e[l].to_bits() & !take));
            worst_k[l] = (k as u32 & take) | (worst_k[l] & !take);
        }
    }
    for l in 0..LANES {
        let sound = (pre[3][l] != 0.0) & mask_spans_plane(mask[l], cfg.min_points);
        // Unsound with every point: no fewer will do.
        done[l] |= !sound;
    }
    if done.iter().all(|&d| d) {
        return (out, valid);
    }
    let cand = Candidate { rc, cfg, w9, uw: &uw, tol: &tol, ca, sa };
    let mut best = [f32::INFINITY; LANES];
    // Without the worst point: any fit is taken (`best` is still infinite).
    let single: [u32; LANES] = core::array::from_fn(|l| mask[l] & !(1u32 << (worst_k[l] & 15)));
    let eligible: [bool; LANES] = core::array::from_fn(|l| !done[l] & (worst_k[l] != u32::MAX));
    cand.solve::<0>(&single, &eligible, &mut best, &mut valid, &mut out);
    for l in 0..LANES {
        done[l] |= valid[l];
    }
    if done.iter().all(|&d| d) {
        return (out, valid);
    }
    // The four lines, each left out in turn (its points never enter the sums): the best fit.
    let eligible = done.map(|d| !d);
    cand.solve::<LINE_TOP>(&mask, &eligible, &mut best, &mut valid, &mut out);
    cand.solve::<LINE_BOTTOM>(&mask, &eligible, &mut best, &mut valid, &mut out);
    cand.solve::<LINE_LEFT>(&mask, &eligible, &mut best, &mut valid, &mut out);
    cand.solve::<LINE_RIGHT>(&mask, &eligible, &mut best, &mut valid, &mut out);
    (out, valid)
}

/// What [`solve_trimmed_lanes`]'s candidates share.
struct Candidate<'a> {
    rc: &'a RowCoeffs,
    cfg: &'a RingFalsConfig,
    w9: &'a [[f32; LANES]; 9],
    uw: &'a [[[f32; LANES]; 3]; 9],
    tol: &'a [f32; LANES],
    ca: &'a [f32; LANES],
    sa: &'a [f32; LANES],
}

impl Candidate<'_> {
    /// Solves every lane's window over the points of `mask` without those of `DROP` and keeps,
    /// in the `eligible` lanes, the normal of the best fit so far (`best`: its sum of squared
    /// residuals).
    #[inline(always)]
    fn solve<const DROP: u32>(
        &self,
        mask: &[u32; LANES],
        eligible: &[bool; LANES],
        best: &mut [f32; LANES],
        valid: &mut [bool; LANES],
        out: &mut [[f32; LANES]; 3],
    ) {
        let (rc, cfg) = (self.rc, self.cfg);
        let mask: [u32; LANES] = core::array::from_fn(|l| mask[l] & !DROP);
        let sys = lane_system::<DROP>(rc, cfg, self.uw, &mask);
        let ssr = lane_ssr::<DROP>(rc, self.w9, &mask, &sys.sol);
        for l in 0..LANES {
            let fits = ssr[l] <= FIT_K * self.tol[l] * self.tol[l];
            let (n, ok) = to_global(rc, sys.sol[0][l], sys.sol[1][l], sys.sol[2][l], self.ca[l], self.sa[l]);
            let take = eligible[l] & sys.sound[l] & fits & ok & (ssr[l] < best[l]);
            best[l] = if take { ssr[l] } else { best[l] };
            valid[l] |= take;
            for c in 0..3 {
                out[c][l] = if take { n[c] } else { out[c][l] };
            }
        }
    }
}

/// The window's edge lines, the points the trimmed solve's candidates leave out in turn: top
/// row, bottom row, left column, right column (bits k = 3 dr + dc of the 3x3 window).
pub(super) const LINE_TOP: u32 = 0b000_000_111;
pub(super) const LINE_BOTTOM: u32 = 0b111_000_000;
pub(super) const LINE_LEFT: u32 = 0b001_001_001;
pub(super) const LINE_RIGHT: u32 = 0b100_100_100;

/// Lane-parallel least-squares solutions over the points of a mask, and whether each lane's
/// system is sound.
struct LaneSystem {
    sol: [[f32; LANES]; 3],
    sound: [bool; LANES],
}

/// Solves each lane's window over the points of its mask (vector code over the lanes): the
/// points' count and spread over the image ([`mask_spans_plane`]), the system as masked
/// sums in window order, its adjugate and solution. Adding a product by 0.0 leaves a sum's bits
/// as they were, so these are the scalar loop's sums over the points present. (Written as an
/// add under a condition, the sums stopped vectorising: the solve took 35 % longer.)
/// The points of `DROP` (never in the mask) are skipped: adding nothing leaves the same bits as
/// adding their products by 0.0.
#[inline(always)]
fn lane_system<const DROP: u32>(
    rc: &RowCoeffs,
    cfg: &RingFalsConfig,
    uw: &[[[f32; LANES]; 3]; 9],
    mask: &[u32; LANES],
) -> LaneSystem {
    let spans: [bool; LANES] = core::array::from_fn(|l| mask_spans_plane(mask[l], cfg.min_points));
    let mut m = [[0.0f32; LANES]; 6];
    let mut b = [[0.0f32; LANES]; 3];
    for k in 0..9 {
        if DROP & (1 << k) != 0 {
            continue;
        }
        let p: [f32; LANES] = core::array::from_fn(|l| ((mask[l] >> k) & 1) as f32);
        for i in 0..6 {
            let uu = rc.uu[i][k];
            for l in 0..LANES {
                m[i][l] += p[l] * uu;
            }
        }
        for i in 0..3 {
            for l in 0..LANES {
                b[i][l] += p[l] * uw[k][i][l];
            }
        }
    }
    let mut sys = LaneSystem { sol: [[0.0; LANES]; 3], sound: [false; LANES] };
    for l in 0..LANES {
        let mm = [m[0][l], m[1][l], m[2][l], m[3][l], m[4][l], m[5][l]];
        let (a, det) = adjugate_f32(&mm);
        let tr = mm[0] + mm[3] + mm[5];
        sys.sound[l] = spans[l] & (det > 0.0) & (27.0 * det >= cfg.min_conditioning * tr * tr * tr);
        let s = 1.0 / det;
        let bb = [b[0][l], b[1][l], b[2][l]];
        sys.sol[0][l] = (a[0] * bb[0] + a[1] * bb[1] + a[2] * bb[2]) * s;
        sys.sol[1][l] = (a[1] * bb[0] + a[3] * bb[1] + a[4] * bb[2]) * s;
        sys.sol[2][l] = (a[2] * bb[0] + a[4] * bb[1] + a[5] * bb[2]) * s;
    }
    sys
}

/// The sum of squared residuals over each lane's mask (the points of `DROP` skipped).
#[inline(always)]
fn lane_ssr<const DROP: u32>(
    rc: &RowCoeffs,
    w9: &[[f32; LANES]; 9],
    mask: &[u32; LANES],
    sol: &[[f32; LANES]; 3],
) -> [f32; LANES] {
    let mut ssr = [0.0f32; LANES];
    for k in 0..9 {
        if DROP & (1 << k) != 0 {
            continue;
        }
        let u = [rc.u[0][k], rc.u[1][k], rc.u[2][k]];
        let w = &w9[k];
        for l in 0..LANES {
            let p = ((mask[l] >> k) & 1) as f32;
            let e = (u[0] * sol[0][l] + u[1] * sol[1][l] + u[2] * sol[2][l] - w[l]).abs();
            ssr[l] += p * (e * e);
        }
    }
    ssr
}

/// Whether the window points of `mask` are enough to solve from: at least `min_points`, and
/// spread over both image directions (the bit-count form of [`SPANS_PLANE`]).
///
/// [`SPANS_PLANE`]: super::reference::SPANS_PLANE
#[inline(always)]
fn mask_spans_plane(mask: u32, min_points: u8) -> bool {
    let bits = |m: u32| (mask & m).count_ones() as i32;
    let src = bits(DIAG_SAME) - bits(DIAG_OPPOSITE);
    (bits(0x1ff) >= i32::from(min_points)) & (bits(ROW_OFF) * bits(COL_OFF) - src * src > 0)
}

/// Window points off the centre row (dr != 0), off the centre column (dc != 0), and on the
/// diagonals where dr dc = 1 and -1: their bit counts in a mask of present points are the
/// sums of dr^2, dc^2 and dr dc that tell whether the points span a plane.
const ROW_OFF: u32 = 0b111_000_111;
const COL_OFF: u32 = 0b101_101_101;
const DIAG_SAME: u32 = (1 << 0) | (1 << 8);
const DIAG_OPPOSITE: u32 = (1 << 2) | (1 << 6);
