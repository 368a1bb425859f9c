//! The scalar reference of the trimmed solve, one pixel at a time, for the tests only (the module
//! is `#[cfg(test)]`), out of the production files: `trimmed.rs` must give the same bits.

use super::RingFalsConfig;
use super::solve::{FIT_K, on_surface, to_global};
use super::table::{CENTRE, RowCoeffs, adjugate_f32};
use super::trimmed::{LINE_BOTTOM, LINE_LEFT, LINE_RIGHT, LINE_TOP};

/// Present-neighbour bit masks (bit k of the 3x3 window, centre excluded) whose offsets span
/// both image directions (not all on one line through the centre). The scalar reference's
/// table ([`solve_trimmed_lanes`] computes it).
///
/// [`solve_trimmed_lanes`]: super::trimmed::solve_trimmed_lanes
pub(super) const SPANS_PLANE: [bool; 512] = {
    let mut t = [false; 512];
    let mut mask = 0;
    while mask < 512 {
        let (mut srr, mut scc, mut src) = (0i32, 0i32, 0i32);
        let mut k = 0;
        while k < 9 {
            if mask & (1 << k) != 0 {
                let (dr, dc) = (k / 3 - 1, k % 3 - 1);
                srr += dr * dr;
                scc += dc * dc;
                src += dr * dc;
            }
            k += 1;
        }
        t[mask] = srr * scc - src * src > 0;
        mask += 1;
    }
    t
};

/// The trimmed solve of one pixel whose masked solve did not fit (the scalar reference of
/// [`solve_trimmed_lanes`], which runs it on a row's pixels in parallel). Some of the window's
/// points are off the plane of the rest: a bad return, an occluding edge, the far side of a
/// step or a crease. In order, the first that fits gives the normal:
///
/// 1. every point: the masked solve's plane, which did not fit; `None` if its system is unsound
///    (no fewer points will do);
/// 2. every point but the one farthest off that plane (a single bad return or edge point);
/// 3. the window without one of its edge lines ([`TRIM_LINES`]: top row, bottom row, left
///    column, right column, at most three points each), the one whose plane fits its points
///    best (smallest sum of squares; the first of equals in that order).
///
/// `None` when nothing fits (clutter without a plane). Dropping one worst point at a time, as
/// this did before step 3, cannot find a step along the scan lines: the first fit is pulled so
/// far toward the other surface's three points that good points look worst. That left 5 % of
/// a 16 x 1024 street scan's pixels without a normal (1 % now) and took four passes.
///
/// [`solve_trimmed_lanes`]: super::trimmed::solve_trimmed_lanes
pub(super) fn solve_trimmed(
    rc: &RowCoeffs,
    cfg: &RingFalsConfig,
    w: [f32; 9],
    ca: f32,
    sa: f32,
) -> Option<[f32; 3]> {
    let wc = w[CENTRE];
    if !(wc > 0.0) {
        return None;
    }
    let t = cfg.range_jump_abs * wc;
    let tol = wc * (cfg.fit_tolerance_rel + t);
    let mut mask = 0usize;
    for k in 0..9 {
        let present = rc.exists & (1 << k) != 0 && on_surface(w[k], wc, rc.gate[k] + t);
        if present {
            mask |= 1 << k;
        }
    }
    // The least squares over the points of `mask`: its solution and sum of squared residuals,
    // or `None` when the system is unsound.
    let fit = |mask: usize| -> Option<([f32; 3], f32)> {
        if (mask.count_ones() as u8) < cfg.min_points || !SPANS_PLANE[mask] {
            return None;
        }
        let mut m = [0.0f32; 6];
        let mut b = [0.0f32; 3];
        for k in 0..9 {
            if mask & (1 << k) != 0 {
                for i in 0..6 {
                    m[i] += rc.uu[i][k];
                }
                b[0] += rc.u[0][k] * w[k];
                b[1] += rc.u[1][k] * w[k];
                b[2] += rc.u[2][k] * w[k];
            }
        }
        let (adj, det) = adjugate_f32(&m);
        let tr = m[0] + m[3] + m[5];
        if !(det > 0.0 && 27.0 * det >= cfg.min_conditioning * tr * tr * tr) {
            return None;
        }
        let s = 1.0 / det;
        let sol = [
            (adj[0] * b[0] + adj[1] * b[1] + adj[2] * b[2]) * s,
            (adj[1] * b[0] + adj[3] * b[1] + adj[4] * b[2]) * s,
            (adj[2] * b[0] + adj[4] * b[1] + adj[5] * b[2]) * s,
        ];
        let mut ssr = 0.0f32;
        for k in 0..9 {
            if mask & (1 << k) != 0 {
                let e = (rc.u[0][k] * sol[0] + rc.u[1][k] * sol[1] + rc.u[2][k] * sol[2] - w[k]).abs();
                ssr += e * e;
            }
        }
        Some((sol, ssr))
    };
    let fits = |ssr: f32| ssr <= FIT_K * tol * tol;
    let normal = |sol: [f32; 3]| {
        let (n, ok) = to_global(rc, sol[0], sol[1], sol[2], ca, sa);
        ok.then_some(n)
    };
    // 1. Every point (the masked solve's plane).
    let (sol, _) = fit(mask)?;
    // 2. Without the point farthest off that plane.
    let mut worst = (0.0f32, usize::MAX);
    for k in 0..9 {
        if mask & (1 << k) == 0 || k == CENTRE {
            continue;
        }
        let e = (rc.u[0][k] * sol[0] + rc.u[1][k] * sol[1] + rc.u[2][k] * sol[2] - w[k]).abs();
        if !(e <= worst.0) {
            worst = (e, k);
        }
    }
    if worst.1 != usize::MAX
        && let Some((sol, ssr)) = fit(mask & !(1 << worst.1))
        && fits(ssr)
        && let Some(n) = normal(sol)
    {
        return Some(n);
    }
    // 3. Without one edge line: the best fit.
    let mut best: Option<(f32, [f32; 3])> = None;
    for line in TRIM_LINES {
        if let Some((sol, ssr)) = fit(mask & !(line as usize))
            && fits(ssr)
            && let Some(n) = normal(sol)
            && best.is_none_or(|(b, _)| ssr < b)
        {
            best = Some((ssr, n));
        }
    }
    best.map(|(_, n)| n)
}

/// [`solve_trimmed`]'s candidates, in order.
pub(super) const TRIM_LINES: [u32; 4] = [LINE_TOP, LINE_BOTTOM, LINE_LEFT, LINE_RIGHT];
