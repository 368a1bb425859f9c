//! Which downsampled points are measured (issue 29: compute only what is measured).
//!
//! The association costs the same for every point it measures, and a dense scan gives more
//! constraints than the update needs: under the measurement budget (`association.max_points`,
//! 5,000 by default) an even spread of the downsampled points is measured, `floor(j n / budget)`
//! for `j < budget` over their (Morton) order, as the reference subsamples every 4th raw point.
//! Every point still goes to the map.
//!
//! Each measured point then stands for `n / budget` points: the association divides its
//! residuals' variance by that ([`crate::association::ScanAssociation::standing_for`]), so the
//! scan's information, and with it the balance between the scan and the IMU's prediction, is
//! what all the points would give. Without that the budget costs accuracy: on the simulated
//! vehicle drive (seeds 1-4) 9,000 of about 17,900 points gave 1.13x the ATE of all of them;
//! weighted, 9,000 gave 0.99x, 6,000 1.01x and 5,000 0.97x (`docs/estimation.md`, 2026-11-28).
//!
//! Measured and not kept: choosing by leverage first (the points that hold most of the
//! information along the pose's weakest directions, then an even fill) gave no lower ATE than
//! the even spread at 9,000 points (vehicle 1.00x, traffic 1.04x) and cost 0.4 ms a scan.

use crate::scan::ScanPoint;

/// Moves an even selection of at most `budget` of `points` (and their normals) to the front,
/// in their order, and returns how many: all of them when `budget` is 0 or not smaller. Element
/// `floor(j n / budget)` goes to position `j`; those positions increase strictly, so each swap
/// takes a point not yet moved.
pub fn select_even(points: &mut [ScanPoint], normals: &mut [[f32; 3]], budget: u32) -> usize {
    let n = points.len().min(normals.len());
    let b = budget as usize;
    if b == 0 || b >= n {
        return n;
    }
    for j in 0..b {
        let src = (j as u64 * n as u64 / b as u64) as usize;
        points.swap(j, src);
        normals.swap(j, src);
    }
    b
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The even budget takes `floor(j n / b)` for `j < b` (evenly spread, in order), moves them
    /// to the front with their normals, and loses no point: the rest still go to the map.
    #[test]
    fn the_even_budget_selects_evenly_and_keeps_every_point() {
        for (n, b) in [(10usize, 3u32), (1000, 333), (1001, 1000), (7, 7), (7, 9), (5, 0), (0, 4), (4, 1)] {
            let mut pts: [ScanPoint; 1001] = [ScanPoint::default(); 1001];
            let mut nrm = [[0.0f32; 3]; 1001];
            for i in 0..n {
                pts[i].t = i as f32;
                nrm[i] = [i as f32, 0.0, 1.0];
            }
            let m = select_even(&mut pts[..n], &mut nrm[..n], b);
            let want = if b == 0 || b as usize >= n { n } else { b as usize };
            assert_eq!(m, want, "n {n} b {b}");
            for j in 0..m {
                let src = if m == n { j } else { j * n / m };
                assert_eq!(pts[j].t, src as f32, "n {n} b {b} j {j}");
                assert_eq!(nrm[j][0], src as f32);
            }
            // A permutation: every input point is still there, each with its own normal.
            let mut seen = [false; 1001];
            for i in 0..n {
                let k = pts[i].t as usize;
                assert!(!seen[k]);
                seen[k] = true;
                assert_eq!(nrm[i][0], pts[i].t);
            }
        }
    }
}
