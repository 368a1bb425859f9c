//! The lookup table of one sensor layout ([`RingTable`]): per row, the window geometry and its
//! inverse matrix in the scaled local frame; built once in f64, only read per scan.

use super::median::QLANES;
use super::{ConfigError, KEY_SCALE, PAD, RingFalsConfig};
use crate::range_image::{MAX_COLS, MAX_ROWS, RangeImageLayout};

/// The fewest columns a layout may have: the most lanes of the median on any target.
const MIN_COLS: usize = 16;
const _: () = assert!(QLANES <= MIN_COLS);

/// Why a [`RingTable`] could not be built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TableError {
    /// A configuration value is out of range.
    Config(ConfigError),
    /// The layout has fewer than 2 rows: one row of returns cannot define a plane.
    TooFewRows,
    /// The layout has fewer than 16 columns (the median works on up to 16 columns at a time),
    /// after the column stride.
    TooFewCols,
    /// The layout's columns are not a multiple of the configuration's `column_stride`.
    ColumnStride,
    /// A row's neighbouring rows lie at (almost) its own elevation, so its window has no
    /// vertical extent.
    FlatRow {
        /// The row.
        row: u16,
    },
}

impl core::fmt::Display for TableError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Config(e) => write!(f, "{e}"),
            Self::TooFewRows => f.write_str("ring_fals: the layout needs at least 2 rows"),
            Self::TooFewCols => f.write_str("ring_fals: the layout needs at least 16 columns"),
            Self::ColumnStride => {
                f.write_str("ring_fals: the layout's columns must be a multiple of column_stride")
            }
            Self::FlatRow { row } => write!(f, "ring_fals: row {row} has no vertical extent"),
        }
    }
}

impl core::error::Error for TableError {}

impl From<ConfigError> for TableError {
    fn from(e: ConfigError) -> Self {
        Self::Config(e)
    }
}

/// Window index of neighbour (dr, dc), both in -1..=1: `k = 3 (dr + 1) + (dc + 1)`; 4 is the
/// centre.
pub(super) const CENTRE: usize = 4;

/// Per-row coefficients: everything about a pixel's window that does not depend on its column.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct RowCoeffs {
    /// Scaled local coordinates of the nine window rays: `u[0][k]` along the centre ray,
    /// `u[1][k]` along the azimuth tangent divided by the column step, `u[2][k]` along the
    /// elevation tangent divided by the row step. Zero for neighbours outside the image.
    pub(super) u: [[f32; 9]; 3],
    /// Products `u_k u_k^T` (00, 01, 02, 11, 12, 22) of every window ray, to build `M'` of an
    /// incomplete window as a masked sum.
    pub(super) uu: [[f32; 9]; 6],
    /// Relative range-jump gate per neighbour (see [`RingFalsConfig::max_incidence_deg`]);
    /// +inf for neighbours outside the image.
    pub(super) gate: [f32; 9],
    /// Bit k set when neighbour k is inside the image (rows do not wrap).
    pub(super) exists: u16,
    /// The same gate for the 5x5 median window (index 5 (dr + 2) + (dc + 2)), as a bound on
    /// the difference of the pixels' range keys (`KEY_SCALE log2(1 + gate)`): a pixel of the
    /// window takes part in the median only if it is on the centre's surface. 0 for rows
    /// outside the image.
    pub(super) gate5: [i16; 25],
    /// Per window row, the smallest of `gate5` over its pixels (centre excluded; 0 for rows
    /// outside the image): a window row whose keys all lie within it of the centre's key needs
    /// no per-pixel gate.
    pub(super) gate5_min: [i16; 5],
    /// Inverse of `M'` for the nominal window (every neighbour inside the image present),
    /// symmetric: 00, 01, 02, 11, 12, 22.
    pub(super) minv: [f32; 6],
    /// Whether the nominal window passed the conditioning check.
    pub(super) nominal_ok: bool,
    /// cos and sin of the row's elevation.
    pub(super) ce: f32,
    pub(super) se: f32,
    /// cos and sin of the azimuth of the row's internal column 0.
    pub(super) ca0: f32,
    pub(super) sa0: f32,
    /// 1 / column step and 1 / row step (radians), to undo the scaling of the local frame.
    pub(super) inv_dh: f32,
    pub(super) inv_dv: f32,
}

impl RowCoeffs {
    const ZERO: Self = Self {
        u: [[0.0; 9]; 3],
        uu: [[0.0; 9]; 6],
        gate: [0.0; 9],
        exists: 0,
        gate5: [0; 25],
        gate5_min: [0; 5],
        minv: [0.0; 6],
        nominal_ok: false,
        ce: 0.0,
        se: 0.0,
        ca0: 0.0,
        sa0: 0.0,
        inv_dh: 0.0,
        inv_dv: 0.0,
    };
}

/// The Ring FALS lookup table of one sensor layout, built from its beam intrinsics.
///
/// Holds, per row, the window geometry in the local frame of the row's pixels and its inverse
/// system matrix, plus per column the sine and cosine of the column's azimuth, and the
/// [`RingFalsConfig`] in use. Rows whose column 0 looks in a different azimuth than others
/// (staggered layouts, Velodyne laser azimuth offsets) are re-aligned internally by a whole
/// number of columns so that every window covers geometric neighbours; results are reported in
/// the caller's columns.
#[derive(Clone, Debug, PartialEq)]
pub struct RingTable {
    rows: u16,
    /// The image's columns: the layout's divided by the column stride.
    cols: u16,
    /// log2 of the column stride: caller column `c` is image column `c >> col_shift`, when
    /// its low bits are zero.
    pub(super) col_shift: u8,
    pub(super) config: RingFalsConfig,
    /// Internal column = (caller column + shift) mod cols.
    shift: [u16; MAX_ROWS],
    pub(super) row: [RowCoeffs; MAX_ROWS],
    /// cos and sin of `step * c`, the azimuth of internal column c relative to column 0.
    pub(super) col_cos: [f32; MAX_COLS],
    pub(super) col_sin: [f32; MAX_COLS],
}

impl Default for RingTable {
    fn default() -> Self {
        Self::new()
    }
}

impl RingTable {
    /// An empty table (no rows); `const` so that it can be a `static`. Build it with
    /// [`Self::build`].
    pub const fn new() -> Self {
        Self {
            rows: 0,
            cols: 0,
            col_shift: 0,
            // All zero (not a usable configuration: the table has no rows until `build`), so
            // that a `static` holding a table lives in .bss.
            config: RingFalsConfig {
                min_range: 0.0,
                max_range: 0.0,
                max_incidence_deg: 0.0,
                range_jump_abs: 0.0,
                fit_tolerance_rel: 0.0,
                min_points: 0,
                min_conditioning: 0.0,
                median: false,
                median_min_valid: 0,
                column_stride: 0,
            },
            shift: [0; MAX_ROWS],
            row: [RowCoeffs::ZERO; MAX_ROWS],
            col_cos: [0.0; MAX_COLS],
            col_sin: [0.0; MAX_COLS],
        }
    }

    /// Builds the table for `layout` with `config` (computed in f64, stored in f32). Fails for a
    /// bad configuration, a layout of fewer than 2 rows or a row without vertical extent; the
    /// table is left empty then.
    pub fn build(&mut self, layout: &RangeImageLayout, config: &RingFalsConfig) -> Result<(), TableError> {
        self.rows = 0;
        self.cols = 0;
        config.validate()?;
        let (rows, stride) = (layout.rows(), usize::from(config.column_stride));
        if rows < 2 {
            return Err(TableError::TooFewRows);
        }
        if !layout.cols().is_multiple_of(stride) {
            return Err(TableError::ColumnStride);
        }
        let cols = layout.cols() / stride;
        // 16 on every target (at least the median's lanes), so that a layout works everywhere.
        if cols < MIN_COLS {
            return Err(TableError::TooFewCols);
        }
        let step = layout.column_step() * stride as f64;
        let dh = libm::fabs(step);
        let alpha = (config.max_incidence_deg as f64).to_radians();

        // Re-align rows whose azimuth origin differs from row 0's by whole columns.
        let mut az0 = [0.0f64; MAX_ROWS];
        let ref_az = layout.azimuth0(0) as f64;
        for r in 0..rows {
            let a = layout.azimuth0(r) as f64;
            let d = wrap_pi(a - ref_az) / step;
            let s = libm::round(d);
            let s_mod = s - cols as f64 * libm::floor(s / cols as f64);
            self.shift[r] = (s_mod as u32 % cols as u32) as u16;
            az0[r] = a - s * step;
        }

        for c in 0..cols {
            let a = step * c as f64;
            self.col_cos[c] = libm::cos(a) as f32;
            self.col_sin[c] = libm::sin(a) as f32;
        }

        for r in 0..rows {
            let el = layout.elevation(r) as f64;
            let (se, ce) = (libm::sin(el), libm::cos(el));
            // Row step: mean distance in elevation to the rows present above and below.
            let mut dv_sum = 0.0;
            let mut dv_n = 0.0;
            for rn in [r.wrapping_sub(1), r + 1] {
                if rn < rows {
                    dv_sum += libm::fabs(layout.elevation(rn) as f64 - el);
                    dv_n += 1.0;
                }
            }
            let dv = dv_sum / dv_n;
            if !(dv > 1e-5) {
                return Err(TableError::FlatRow { row: r as u16 });
            }

            let mut rc = RowCoeffs::ZERO;
            let mut m = [0.0f64; 6];
            for k in 0..9 {
                let (dr, dc) = (k as isize / 3 - 1, k as isize % 3 - 1);
                let rn = r as isize + dr;
                if rn < 0 || rn >= rows as isize {
                    rc.gate[k] = f32::INFINITY;
                    continue;
                }
                let rn = rn as usize;
                rc.exists |= 1 << k;
                // The neighbour's ray in the frame where the centre pixel looks at azimuth 0.
                let eln = layout.elevation(rn) as f64;
                let (sen, cen) = (libm::sin(eln), libm::cos(eln));
                let da = az0[rn] - az0[r] + dc as f64 * step;
                let (sd, cd) = (libm::sin(da), libm::cos(da));
                let v = [cen * cd, cen * sd, sen];
                let a = ce * v[0] + se * v[2];
                let x = v[1] / dh;
                let y = (-se * v[0] + ce * v[2]) / dv;
                rc.u[0][k] = a as f32;
                rc.u[1][k] = x as f32;
                rc.u[2][k] = y as f32;
                let p = [a * a, a * x, a * y, x * x, x * y, y * y];
                for i in 0..6 {
                    m[i] += p[i];
                    rc.uu[i][k] = p[i] as f32;
                }
                rc.gate[k] =
                    if k == CENTRE { 0.0 } else { incidence_gate(alpha, libm::acos(a.clamp(-1.0, 1.0))) };
            }
            // Gates of the 5x5 median window.
            let ray = |rr: usize, dc: f64| {
                let e = layout.elevation(rr) as f64;
                let a = az0[rr] + dc * step;
                [libm::cos(e) * libm::cos(a), libm::cos(e) * libm::sin(a), libm::sin(e)]
            };
            let vc = ray(r, 0.0);
            for j in 0..25 {
                let (dr, dc) = (j as isize / 5 - 2, j as isize % 5 - 2);
                let rn = r as isize + dr;
                if rn < 0 || rn >= rows as isize {
                    continue;
                }
                let vn = ray(rn as usize, dc as f64);
                let ca = vc[0] * vn[0] + vc[1] * vn[1] + vc[2] * vn[2];
                let g =
                    if j == 12 { 0.0 } else { incidence_gate(alpha, libm::acos(ca.clamp(-1.0, 1.0))) as f64 };
                rc.gate5[j] = (KEY_SCALE as f64 * libm::log2(1.0 + g)).min(30000.0) as i16;
            }
            rc.gate5_min = core::array::from_fn(|dr| {
                (5 * dr..5 * dr + 5).filter(|&j| j != 12).map(|j| rc.gate5[j]).min().unwrap_or(0)
            });
            let (adj, det) = adjugate_f64(&m);
            let tr = m[0] + m[3] + m[5];
            rc.nominal_ok = det > 0.0 && 27.0 * det >= config.min_conditioning as f64 * tr * tr * tr;
            if rc.nominal_ok {
                for i in 0..6 {
                    rc.minv[i] = (adj[i] / det) as f32;
                }
            }
            rc.ce = ce as f32;
            rc.se = se as f32;
            rc.ca0 = libm::cos(az0[r]) as f32;
            rc.sa0 = libm::sin(az0[r]) as f32;
            rc.inv_dh = (1.0 / dh) as f32;
            rc.inv_dv = (1.0 / dv) as f32;
            self.row[r] = rc;
        }
        self.config = *config;
        self.rows = rows as u16;
        self.cols = cols as u16;
        self.col_shift = stride.trailing_zeros() as u8;
        Ok(())
    }

    /// Rows of the layout (0 until built).
    pub fn rows(&self) -> usize {
        self.rows as usize
    }

    /// Columns of the normals' image: the layout's divided by the column stride (0 until
    /// built).
    pub fn cols(&self) -> usize {
        self.cols as usize
    }

    /// Columns of the layout, as the points number them (0 until built).
    pub fn layout_cols(&self) -> usize {
        (self.cols as usize) << self.col_shift
    }

    /// The configuration the table was built with (all zero before the first build).
    pub fn config(&self) -> &RingFalsConfig {
        &self.config
    }

    /// Internal (re-aligned) column of the caller's pixel (row, col); both must be in range.
    #[inline]
    pub(super) fn internal_col(&self, row: usize, col: usize) -> usize {
        let c = col + self.shift[row] as usize;
        if c >= self.cols as usize { c - self.cols as usize } else { c }
    }

    /// The padded-image index of every caller pixel, as a table per row for the per-point
    /// loops (see [`PixelIndex`]).
    pub(super) fn pixel_index(&self, stride: usize) -> PixelIndex {
        let cols = usize::from(self.cols);
        let mut ix = PixelIndex { base: [0; MAX_ROWS], wrap_at: [0; MAX_ROWS], cols };
        for r in 0..usize::from(self.rows) {
            let shift = usize::from(self.shift[r]);
            ix.base[r] = (r + PAD) * stride + PAD + shift;
            ix.wrap_at[r] = cols - shift;
        }
        ix
    }

    /// Unit ray (cos az, sin az) of the internal pixel (row, internal col), as the solve uses it.
    #[inline]
    pub(super) fn azimuth_cs(&self, row: usize, icol: usize) -> (f32, f32) {
        let rc = &self.row[row];
        let (cc, sc) = (self.col_cos[icol], self.col_sin[icol]);
        (rc.ca0 * cc - rc.sa0 * sc, rc.sa0 * cc + rc.ca0 * sc)
    }
}

/// Per row of a table: where its caller column 0 lies in the padded image, and the caller
/// column from which the internal columns wrap around. One load and a compare per point instead
/// of [`RingTable::internal_col`]'s multiply and its bounds checks: the projection and the
/// write-back are short loops over every point.
pub(super) struct PixelIndex {
    base: [usize; MAX_ROWS],
    wrap_at: [usize; MAX_ROWS],
    cols: usize,
}

const _: () = assert!(MAX_ROWS.is_power_of_two());

impl PixelIndex {
    /// Padded-image index of caller pixel (row, col), for `row < rows` and `col < cols`.
    #[inline(always)]
    pub(super) fn px(&self, row: usize, col: usize) -> usize {
        // `row` is below the table's rows, so the mask changes nothing but proves the index.
        let r = row & (MAX_ROWS - 1);
        self.base[r] + col - if col >= self.wrap_at[r] { self.cols } else { 0 }
    }
}

/// Largest relative range change between two rays `theta` apart on a plane seen at incidence
/// `alpha` or less: `cos(alpha) / cos(alpha + theta) - 1` (capped at 1000 near grazing).
fn incidence_gate(alpha: f64, theta: f64) -> f32 {
    let far = alpha + theta;
    if far >= core::f64::consts::FRAC_PI_2 - 1e-3 {
        1.0e3
    } else {
        (libm::cos(alpha) / libm::cos(far) - 1.0) as f32
    }
}

/// Wraps an angle to (-pi, pi].
fn wrap_pi(a: f64) -> f64 {
    let t = core::f64::consts::TAU;
    a - t * libm::floor((a + core::f64::consts::PI) / t)
}

/// Adjugate and determinant of a symmetric 3x3 matrix stored as 00, 01, 02, 11, 12, 22.
fn adjugate_f64(m: &[f64; 6]) -> ([f64; 6], f64) {
    let [a, b, c, d, e, f] = *m;
    let adj = [d * f - e * e, c * e - b * f, b * e - c * d, a * f - c * c, b * c - a * e, a * d - b * b];
    let det = a * adj[0] + b * adj[1] + c * adj[2];
    (adj, det)
}

/// The same in f32, for the per-scan gap-aware solve.
#[inline]
pub(super) fn adjugate_f32(m: &[f32; 6]) -> ([f32; 6], f32) {
    let [a, b, c, d, e, f] = *m;
    let adj = [d * f - e * e, c * e - b * f, b * e - c * d, a * f - c * c, b * c - a * e, a * d - b * b];
    let det = a * adj[0] + b * adj[1] + c * adj[2];
    (adj, det)
}
