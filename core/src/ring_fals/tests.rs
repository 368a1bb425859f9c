//! Tests of Ring FALS: the arithmetic helpers against libm and every vectorised stage against a
//! scalar reference, bit for bit; the selection networks are tested in `tests/networks.rs`.
use super::median::round_small;
use super::reference::{SPANS_PLANE, TRIM_LINES, solve_trimmed};
use super::solve::{LANES, TRIM, log2_approx, rsqrt, rsqrt_norm, solve_group_masked, solve_row_full};
use super::trimmed::solve_trimmed_lanes;
use super::*;
use crate::range_image::RangeImageLayout;
extern crate std;

mod networks;

#[test]
fn round_small_rounds_to_nearest() {
    for &x in &[0.0f32, 0.49, 0.5, 0.51, 1.5, 2.5, -0.5, -0.51, -1.5, 31999.6, -31999.6, 32000.0, -32000.0] {
        assert_eq!(round_small(x), libm::rintf(x) as i32, "{x}");
    }
    let mut x = -32000.0f32;
    while x <= 32000.0 {
        assert_eq!(round_small(x), libm::rintf(x) as i32, "{x}");
        x += 0.173;
    }
}

#[test]
fn rsqrt_is_accurate() {
    // Three Newton steps (inverse ranges) and two (normalisation).
    for (f, bound) in [(rsqrt as fn(f32) -> f32, 2e-7), (rsqrt_norm, 5e-6)] {
        let mut x = 1e-6f32;
        while x < 1e8 {
            let want = 1.0 / libm::sqrt(x as f64);
            let got = f(x) as f64;
            assert!(((got - want) / want).abs() < bound, "x {x}: {got} vs {want}");
            x *= 1.013;
        }
    }
}

#[test]
fn log2_approx_is_accurate() {
    let mut x = 1e-5f32;
    while x < 1e3 {
        let e = (log2_approx(x) as f64 - libm::log2(x as f64)).abs();
        assert!(e < 2.2e-4, "x {x}: error {e}");
        x *= 1.0071;
    }
}

#[test]
fn spans_plane_table() {
    let bit = |dr: i32, dc: i32| 1usize << ((dr + 1) * 3 + dc + 1);
    assert!(!SPANS_PLANE[bit(0, -1) | bit(0, 1)]);
    assert!(!SPANS_PLANE[bit(-1, -1) | bit(1, 1)]);
    assert!(!SPANS_PLANE[bit(-1, 0) | bit(1, 0) | bit(0, 0)]);
    assert!(SPANS_PLANE[bit(0, 1) | bit(-1, 0)]);
    assert!(SPANS_PLANE[bit(-1, -1) | bit(1, 1) | bit(0, 1)]);
}

#[test]
fn config_validation() {
    assert_eq!(RingFalsConfig::DEFAULT.validate(), Ok(()));
    let bad = |f: fn(&mut RingFalsConfig)| {
        let mut c = RingFalsConfig::DEFAULT;
        f(&mut c);
        c.validate()
    };
    assert_eq!(bad(|c| c.min_range = f32::NAN), Err(ConfigError::MinRange));
    assert_eq!(bad(|c| c.min_range = 0.0), Err(ConfigError::MinRange));
    assert_eq!(bad(|c| c.max_range = 0.1), Err(ConfigError::MaxRange));
    assert_eq!(bad(|c| c.max_range = f32::INFINITY), Err(ConfigError::MaxRange));
    assert_eq!(bad(|c| c.fit_tolerance_rel = 0.0), Err(ConfigError::FitToleranceRel));
    assert_eq!(bad(|c| c.max_incidence_deg = 90.0), Err(ConfigError::MaxIncidence));
    assert_eq!(bad(|c| c.range_jump_abs = -1.0), Err(ConfigError::RangeJumpAbs));
    assert_eq!(bad(|c| c.min_points = 2), Err(ConfigError::MinPoints));
    assert_eq!(bad(|c| c.min_conditioning = 0.0), Err(ConfigError::MinConditioning));
    assert_eq!(bad(|c| c.median_min_valid = 0), Err(ConfigError::MedianMinValid));
    for stride in [0, 3, 8] {
        let mut c = RingFalsConfig::DEFAULT;
        c.column_stride = stride;
        assert_eq!(c.validate(), Err(ConfigError::ColumnStride), "stride {stride}");
    }
}

#[test]
fn table_rejects_degenerate_layouts() {
    let mut t = RingTable::new();
    let one = RangeImageLayout::from_elevations(&[0.0], 64, true).unwrap();
    assert_eq!(t.build(&one, &RingFalsConfig::DEFAULT), Err(TableError::TooFewRows));
    let narrow = RangeImageLayout::from_elevations(&[0.1, 0.0], 15, true).unwrap();
    assert_eq!(t.build(&narrow, &RingFalsConfig::DEFAULT), Err(TableError::TooFewCols));
    let flat = RangeImageLayout::from_elevations(&[0.1, 0.1, 0.1], 64, true).unwrap();
    assert_eq!(t.build(&flat, &RingFalsConfig::DEFAULT), Err(TableError::FlatRow { row: 0 }));
    let mut cfg = RingFalsConfig::DEFAULT;
    cfg.min_points = 10;
    let ok = RangeImageLayout::from_elevations(&[0.1, 0.0], 64, true).unwrap();
    assert_eq!(t.build(&ok, &cfg), Err(TableError::Config(ConfigError::MinPoints)));
    assert_eq!(t.rows(), 0);
    assert_eq!(t.build(&ok, &RingFalsConfig::DEFAULT), Ok(()));
    assert_eq!(t.rows(), 2);
    let strided = |s| RingFalsConfig { column_stride: s, ..RingFalsConfig::DEFAULT };
    assert_eq!(t.build(&ok, &strided(4)), Ok(()));
    assert_eq!((t.cols(), t.layout_cols()), (16, 64));
    let odd = RangeImageLayout::from_elevations(&[0.1, 0.0], 66, true).unwrap();
    assert_eq!(t.build(&odd, &strided(4)), Err(TableError::ColumnStride));
    assert_eq!(
        t.build(&ok, &RingFalsConfig { column_stride: 8, ..RingFalsConfig::DEFAULT }),
        Err(TableError::Config(ConfigError::ColumnStride))
    );
    let narrow = RangeImageLayout::from_elevations(&[0.1, 0.0], 60, true).unwrap();
    assert_eq!(t.build(&narrow, &strided(4)), Err(TableError::TooFewCols));
}

/// The lane-parallel trimmed solve gives the scalar reference's results, bit for bit, on
/// windows of planes with outliers, holes and far points, in rows with and without
/// neighbours above or below, with lanes in every position of a batch.
#[test]
fn trimmed_lanes_equal_the_scalar_solve() {
    let els: [f32; 16] = core::array::from_fn(|i| (15.0 - 2.0 * i as f32).to_radians());
    let layout = RangeImageLayout::from_elevations(&els, 1024, true).unwrap();
    let mut table = RingTable::new();
    let cfg = RingFalsConfig::DEFAULT;
    table.build(&layout, &cfg).unwrap();
    let mut rng = crate::testutil::Rng::new(11);
    let (mut valid, mut none) = (0, 0);
    for case in 0..20_000 {
        let row = [0usize, 1, 7, 14, 15][case % 5];
        let rc = &table.row[row];
        let active: [bool; LANES] = core::array::from_fn(|_| rng.uniform() < 0.8);
        let mut w9 = [[0.0f32; LANES]; 9];
        let (mut ca, mut sa) = ([0.0f32; LANES], [0.0f32; LANES]);
        for l in 0..LANES {
            let r0 = 2.0 + 40.0 * rng.uniform();
            // A plane's inverse ranges vary smoothly over the window; a few points are off it,
            // and in a third of the windows one edge line is on another surface (a step).
            let (gx, gy) = (0.05 * (rng.uniform() - 0.5), 0.05 * (rng.uniform() - 0.5));
            let step = if rng.uniform() < 0.33 { TRIM_LINES[(rng.uniform() * 4.0) as usize % 4] } else { 0 };
            let step_to = 0.85 + 0.1 * rng.uniform();
            for k in 0..9 {
                let (dr, dc) = ((k / 3) as f64 - 1.0, (k % 3) as f64 - 1.0);
                let mut r = r0 * (1.0 + gx * dc + gy * dr) + 0.01 * rng.gauss();
                if step & (1 << k) != 0 {
                    r *= step_to;
                }
                let u = rng.uniform();
                if u < 0.12 {
                    r *= 0.6 + 0.8 * rng.uniform(); // another surface
                } else if u < 0.16 {
                    r = 0.0; // no return
                }
                w9[k][l] = if r > 0.0 { (1.0 / r) as f32 } else { 0.0 };
            }
            let a = core::f64::consts::TAU * rng.uniform();
            (ca[l], sa[l]) = (libm::cos(a) as f32, libm::sin(a) as f32);
        }
        let (_, _, pre) = solve_group_masked(rc, &cfg, &w9, &ca, &sa);
        let (n, ok) = solve_trimmed_lanes(rc, &cfg, &w9, &ca, &sa, &active, &pre);
        for l in 0..LANES {
            if !active[l] {
                continue;
            }
            let w: [f32; 9] = core::array::from_fn(|k| w9[k][l]);
            let want = solve_trimmed(rc, &cfg, w, ca[l], sa[l]);
            let got = ok[l].then(|| [n[0][l], n[1][l], n[2][l]]);
            assert_eq!(
                got.map(|v| v.map(f32::to_bits)),
                want.map(|v| v.map(f32::to_bits)),
                "row {row}, {w:?}"
            );
            if want.is_some() { valid += 1 } else { none += 1 }
        }
    }
    // Both outcomes are well represented.
    assert!(valid > 10_000 && none > 10_000, "{valid} valid, {none} none");
}

/// A 16 x 1020 scan (a column count no multiple of the lane widths) of a room 8 m across,
/// 1.5 m above its floor: 1 cm noise, 3 % dropouts, `outliers` of the returns cut to 70 %;
/// `pole(c)` is the range of a pole in column c (infinite where none).
fn room_scan(seed: u64, pole: impl Fn(usize) -> f64, outliers: f64) -> (RingTable, std::vec::Vec<ScanPoint>) {
    let els: [f32; 16] = core::array::from_fn(|i| (15.0 - 2.0 * i as f32).to_radians());
    let layout = RangeImageLayout::from_elevations(&els, 1020, true).unwrap();
    let mut table = RingTable::new();
    table.build(&layout, &RingFalsConfig::DEFAULT).unwrap();
    let mut rng = crate::testutil::Rng::new(seed);
    let mut points = std::vec::Vec::new();
    for r in 0..16 {
        for c in 0..1020 {
            if rng.uniform() < 0.03 {
                continue;
            }
            let d = layout.direction(r, c);
            let wall = 8.0 / d[0].abs().max(d[1].abs()).max(1e-6);
            let floor = if d[2] < 0.0 { 1.5 / -d[2] } else { f64::INFINITY };
            let mut range = wall.min(floor).min(pole(c)) + 0.01 * rng.gauss();
            if rng.uniform() < outliers {
                range *= 0.7;
            }
            let p = [d[0] * range, d[1] * range, d[2] * range].map(|v| v as f32);
            points.push(ScanPoint { xyz: p, row: r as u16, col: c as u16, ..Default::default() });
        }
    }
    (table, points)
}

/// The write-back in pixel order (no collisions) gives every point what the point-by-point
/// one gives, with and without points that have no pixel or a filtered range.
#[test]
fn pixel_order_write_back_equals_point_order() {
    use std::boxed::Box;
    use std::vec;
    for extra in [false, true] {
        let (table, mut points) =
            room_scan(9, |c| if (300..304).contains(&c) { 3.0 } else { f64::INFINITY }, 0.02);
        if extra {
            for (i, p) in points.iter_mut().enumerate().filter(|(i, _)| i % 97 == 0) {
                if i % 2 == 0 {
                    p.xyz = [0.0; 3]; // a zero range: filtered
                } else {
                    p.row = crate::scan::NO_PIXEL;
                }
            }
        }
        let mut fals = Box::new(RingFals::<{ storage_pixels(16, 1020) }>::new());
        let mut by_pixel = vec![PointNormal { normal: [9.0; 3], valid: true }; points.len()];
        let stats = fals.estimate(&table, &points, &mut by_pixel).unwrap();
        assert_eq!(stats.collisions, 0);
        assert_eq!(stats.no_pixel + stats.rejected_range > 0, extra);
        let mut by_point = vec![PointNormal { normal: [9.0; 3], valid: true }; points.len()];
        let n = fals.write_by_point(&table, &points, &mut by_point);
        assert_eq!(n, stats.valid_points);
        assert!(n > 15_000 && (n as usize) < points.len(), "{n} of {}", points.len());
        for (i, (a, b)) in by_pixel.iter().zip(&by_point).enumerate() {
            assert_eq!(
                (a.valid, a.normal.map(f32::to_bits)),
                (b.valid, b.normal.map(f32::to_bits)),
                "point {i}"
            );
        }
    }
}

/// Every incomplete window goes through the masked solve once, and on to the trimmed solve
/// once at most, wherever it lies in the row (the column count here is no multiple of
/// LANES): the counts equal a pixel-by-pixel reference.
#[test]
fn each_incomplete_window_is_solved_once() {
    use std::boxed::Box;
    let cols = 1020;
    // A pole near the seam and a few outliers.
    let (table, points) =
        room_scan(5, |c| if c >= cols - 6 && c < cols - 2 { 3.0 } else { f64::INFINITY }, 0.01);
    let mut fals = Box::new(RingFals::<{ storage_pixels(16, 1020) }>::new());
    let mut out = std::vec![PointNormal::INVALID; points.len()];
    let stats = fals.estimate(&table, &points, &mut out).unwrap();
    // The reference: each pixel with a return, its full window alone, then the masked solve
    // alone (the image planes `inv` are what `solve` read).
    let (stride, cfg) = (fals.stride, table.config);
    let (mut partial, mut trimmed) = (0u32, 0u32);
    for r in 0..16 {
        let rc = &table.row[r];
        for c in 0..cols {
            let px = (r + PAD) * stride + PAD + c;
            let row = |dr: usize| &fals.inv[px + dr * stride - stride - 1..][..3];
            let (mut n3, mut st) = ([[0.0f32; 1]; 3], [EMPTY]);
            let [nx, ny, nz] = &mut n3;
            let cs = (&table.col_cos[c..c + 1], &table.col_sin[c..c + 1]);
            solve_row_full(
                rc,
                cfg.range_jump_abs,
                cfg.fit_tolerance_rel,
                row(0),
                row(1),
                row(2),
                cs,
                nx,
                ny,
                nz,
                &mut st,
            );
            if st[0] != PARTIAL {
                continue;
            }
            partial += 1;
            let w9: [[f32; LANES]; 9] =
                core::array::from_fn(|k| [fals.inv[px + (k / 3) * stride + (k % 3) - stride - 1]; LANES]);
            let (ca, sa) = table.azimuth_cs(r, c);
            let (_, verdict, _) = solve_group_masked(rc, &cfg, &w9, &[ca; LANES], &[sa; LANES]);
            trimmed += u32::from(verdict[0] == TRIM);
        }
    }
    assert!(
        trimmed > 20 && partial > trimmed,
        "{partial} partial, {trimmed} trimmed: the scene should exercise both"
    );
    assert_eq!(stats.trimmed_solves, trimmed);
    assert_eq!(stats.gap_solves + stats.invalid_pixels, partial, "{stats:?}");
}

/// The vectorised median equals a pixel-by-pixel reference: per channel, the lower median
/// of the window pixels that are valid and pass the same-surface gate, then the same
/// fallback and normalisation. Poles in front of walls make the gate leave pixels out.
#[test]
fn median_equals_the_scalar_reference() {
    use std::{boxed::Box, vec::Vec};
    let cols = 1020;
    // Poles 3-9 pixels wide every 60 columns, at 2-5 m; one across the seam.
    let pole = |c: usize| if (c + 3) % 60 < 3 + c % 7 { 2.0 + (c / 60 % 4) as f64 } else { f64::INFINITY };
    let (table, points) = room_scan(11, pole, 0.0);
    let mut fals = Box::new(RingFals::<{ storage_pixels(16, 1020) }>::new());
    fals.project(&table, &points).unwrap();
    fals.solve(&table);
    let (nx0, ny0, nz0) = (fals.nx.to_vec(), fals.ny.to_vec(), fals.nz.to_vec());
    fals.smooth(&table);
    let (stride, cfg) = (fals.stride, table.config);
    let (mut checked, mut gated, mut kept_own) = (0, 0, 0u32);
    for r in 0..16 {
        let rc = &table.row[r];
        for c in 0..cols {
            let px = (r + PAD) * stride + PAD + c;
            if fals.state[px] != FULL && fals.state[px] != GAP {
                continue;
            }
            let kc = fals.key[px];
            let tc = round_small(
                (fals.inv[px] * (cfg.range_jump_abs * KEY_SCALE * core::f32::consts::LOG2_E)).min(30000.0),
            ) as i16;
            let mut vals: [Vec<i16>; 3] = Default::default();
            for j in 0..25 {
                let q = px + (j / 5) * stride + j % 5 - 2 * stride - 2;
                let d = kc.saturating_sub(fals.key[q]);
                let d = d.max(0i16.saturating_sub(d));
                if fals.qinv[q] != 0 {
                    continue;
                }
                if d.saturating_sub(tc) > rc.gate5[j] {
                    gated += 1;
                    continue;
                }
                for (ch, q3) in [&fals.qx, &fals.qy, &fals.qz].into_iter().enumerate() {
                    vals[ch].push(q3[q]);
                }
            }
            let n = vals[0].len();
            let own = [nx0[px], ny0[px], nz0[px]];
            let mut want = own;
            if n >= usize::from(cfg.median_min_valid) {
                let m = vals.map(|mut v| {
                    v.sort_unstable();
                    f32::from(v[(n - 1) / 2])
                });
                let n2 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2];
                let (cc, sc) = (table.col_cos[c], table.col_sin[c]);
                let (ca, sa) = (rc.ca0 * cc - rc.sa0 * sc, rc.sa0 * cc + rc.ca0 * sc);
                let facing = rc.ce * (ca * m[0] + sa * m[1]) + rc.se * m[2];
                if n2 >= 0.25 * QSCALE * QSCALE && facing < 0.0 {
                    let s = rsqrt_norm(n2);
                    want = m.map(|v| v * s);
                }
            }
            kept_own += u32::from(want == own);
            let got = [fals.nx[px], fals.ny[px], fals.nz[px]];
            assert_eq!(got.map(f32::to_bits), want.map(f32::to_bits), "pixel ({r}, {c}): {n} kept");
            checked += 1;
        }
    }
    assert!(
        checked > 12000 && gated > 500,
        "{checked} pixels, {gated} gated: the scene should exercise the gate"
    );
    assert_eq!(fals.stats.median_kept_own, kept_own);
}

#[test]
fn full_window_system_is_well_conditioned_in_the_local_frame() {
    // VLP-32C-like central rows, 1800 columns: det(M) of the global-frame system is ~1e-7;
    // the scaled local system is close to diag(9, 6, 6).
    let els: [f32; 3] = [0.01, 0.0, -0.01];
    let l = RangeImageLayout::from_elevations(&els, 1800, true).unwrap();
    let mut t = RingTable::new();
    t.build(&l, &RingFalsConfig::DEFAULT).unwrap();
    let rc = &t.row[1];
    assert!(rc.nominal_ok);
    let mut m = [0.0f64; 6];
    for k in 0..9 {
        let u = [rc.u[0][k] as f64, rc.u[1][k] as f64, rc.u[2][k] as f64];
        m[0] += u[0] * u[0];
        m[3] += u[1] * u[1];
        m[5] += u[2] * u[2];
    }
    assert!((m[0] - 9.0).abs() < 1e-3 && (m[3] - 6.0).abs() < 1e-3 && (m[5] - 6.0).abs() < 0.1, "{m:?}");
}
