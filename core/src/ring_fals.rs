//! # Ring FALS: a surface normal for every LiDAR return, from the range image
//!
//! LOG-LIO's first contribution (Huang et al., RA-L 2023, section "Ring FALS Normal Estimator"),
//! after FALS (Badino et al., ICRA 2011).
//!
//! ## The idea
//!
//! A point is `p = r v`: its range `r` along the unit ray `v` of its pixel. A plane that misses
//! the sensor is `n . p = 1` (with `n` the unit normal divided by the plane's distance), so every
//! point of a pixel window `W` gives one linear equation `v . n = 1/r`. Least squares gives
//!
//! ```text
//!     n = M^-1 b,    M = sum_W v v^T,    b = sum_W v / r
//! ```
//!
//! `M` depends only on the rays, so it is computed once per sensor ([`RingTable`]); each scan
//! only needs `b`, a weighted sum of the nine ranges of a 3x3 window. The result points away
//! from the sensor; it is flipped to point toward it, smoothed by a 5x5 median and normalised.
//!
//! ## What loglio does differently from the reference (LOG-LIO's public C++ code)
//!
//! - **No recording is needed.** [`RingTable::build`] takes the sensor's beam intrinsics, a
//!   [`RangeImageLayout`]. For sensors without known intrinsics, [`RingLearner`] learns the
//!   layout from observed points.
//! - **Well-conditioned f32.** The nine rays are nearly parallel (`det M ~ 1e-7`): solved in
//!   the global frame, f32 loses most of the normal's tangential part. loglio solves in the
//!   centre pixel's local frame, `x` along the ray, `y` along the azimuth tangent, `z` along the
//!   elevation tangent, with the tangent coordinates divided by the angular step. The 3x3
//!   system then has entries of order 1 (`M' ~ diag(9, 6, 6)` for a full window) and both `M'`
//!   and `b'` are formed without cancellation. A spinning LiDAR is symmetric under rotation
//!   about its axis, so these coefficients depend on the row only: the table is a few kB per
//!   row instead of a 3x3 matrix per pixel. The test `precision_of_candidate_formulations`
//!   (tests/ring_fals_synthetic.rs) shows the choice: the naive f32 solve is off by degrees at
//!   60 m while this one matches the f64 solve.
//! - **Gap-aware.** A neighbour is *absent* when it has no return or its range jumps from the
//!   centre's by more than a plane at [`RingFalsConfig::max_incidence_deg`] could explain, plus
//!   [`RingFalsConfig::range_jump_abs`] for noise. A full window uses the table's `M'^-1`; an
//!   incomplete one is solved from the neighbours actually present (its own `M'` and `b'`),
//!   provided there are at least [`RingFalsConfig::min_points`] points, they are not all on one
//!   line of the image, and the system is well conditioned. The reference instead treats a
//!   missing neighbour as a point at infinity, which biases the normal toward the missing rays.
//! - **Every window must fit its plane.** After the solve, the squared range residuals of the
//!   window's points must stay within a tolerance ([`RingFalsConfig::fit_tolerance_rel`]); a
//!   window with some points off the plane (a bad return, an occluding edge, a step or crease
//!   along the scan lines, a pole in front of a wall where rows are degrees apart) is solved
//!   again without its worst point, else without each of its four edge lines (a row or column
//!   of three), taking the plane that fits best; clutter that no such plane fits is invalid.
//! - **Invalid is explicit.** A pixel that cannot give a reliable normal has a zero normal and
//!   a cleared validity flag, never NaN; its point is kept.
//! - **The median uses valid pixels only** (per channel, 5x5, columns wrapped, rows cut at the
//!   image border); the reference lets its `FLT_MAX` "no data" sentinels into its median, which
//!   turns some normals near holes into bogus ones such as (1, 0, 0). It also leaves
//!   out pixels of another surface (the range gate again), so a pole's edge normals are not bent
//!   toward the wall behind it. A valid pixel with fewer than
//!   [`RingFalsConfig::median_min_valid`] such pixels in its window keeps its own normal.
//! - **The 0/360 degree seam is no edge**: columns wrap (the reference mirrors its windows at the
//!   seam instead, and drops the returns just below 360 degrees).
//! - Zero, too short, too long and non-finite ranges are filtered. When several points hit a
//!   pixel the nearest wins (deterministic for any point order) and the others are counted.
//!
//! [`RangeImageLayout`]: crate::range_image::RangeImageLayout
//!
//! ## Using it
//!
//! ```
//! use loglio_core::range_image::RangeImageLayout;
//! use loglio_core::ring_fals::{PointNormal, RingFals, RingFalsConfig, RingTable, storage_pixels};
//! use loglio_core::scan::ScanPoint;
//!
//! // A 16-beam sensor, 1024 columns (in firmware both would be `static`s).
//! let elevations: [f32; 16] = core::array::from_fn(|i| (15.0 - 2.0 * i as f32).to_radians());
//! let layout = RangeImageLayout::from_elevations(&elevations, 1024, true).unwrap();
//! let mut table = RingTable::new();
//! table.build(&layout, &RingFalsConfig::DEFAULT).unwrap();
//! let mut fals = Box::new(RingFals::<{ storage_pixels(16, 1024) }>::new());
//!
//! let points: [ScanPoint; 0] = [];
//! let mut normals = [PointNormal::INVALID; 0];
//! let stats = fals.estimate(&table, &points, &mut normals).unwrap();
//! assert_eq!(stats.valid_points, 0);
//! ```
//!
//! ## Memory and time
//!
//! [`RingFals`] holds the per-scan images (35 bytes per padded pixel, plus a 187 kB row scratch:
//! 2.5 MB for 32 x 1800, 9.7 MB for 128 x 2048) and [`RingTable`] the per-row coefficients
//! (88 kB); both have `const fn new()`, and the storage's is all zero, so a `static` of it
//! costs no flash. Nothing
//! allocates, nothing reads a clock; the same input gives bit-identical output on every target
//! (per scan only `+ - * /`, comparisons, integer operations and, for a point that shares its
//! pixel, the correctly rounded `libm::sqrtf`; no FMA contraction, no reassociation). The inner loops are written over planar buffers without branches so that they
//! auto-vectorise (SSE2 on x86-64, NEON on aarch64, AVX2 where the build enables it); the median
//! runs on normals quantised to 1/32000 (0.002 degrees), 16 columns at a time in 16-bit lanes (8
//! on arm64, one NEON register), with selection networks. Where every window of a group lies on
//! one surface and lacks at most twelve pixels, the windows share their columns sorted once per
//! row (127 min/max per channel for up to four missing, 156 for more); elsewhere each window's
//! left-out pixels become -inf/+inf sentinels of a full 25-value network (190). All give the
//! exact lower median of the pixels kept.

// Index loops over planar buffers are what auto-vectorises; `!(a <= b)` is deliberate
// wherever a NaN must count as failing the test.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]

use crate::range_image::MAX_COLS;
use crate::scan::ScanPoint;

mod config;
mod learner;
mod median;
mod networks;
mod solve;
mod table;
mod trimmed;

pub use self::config::{ConfigError, RingFalsConfig};
pub use self::learner::{LearnError, LearnedRow, RingLearner};
use self::table::CENTRE;
pub use self::table::{RingTable, TableError};

// ---------------------------------------------------------------------------------------------
// Per-scan storage and estimation
// ---------------------------------------------------------------------------------------------

/// Border around the image in the storage: two rows above and below (never data, so windows
/// near the top and bottom rows are simply incomplete) and two columns left and right (copies
/// of the opposite edge, so windows wrap around the 0/360 degree seam).
const PAD: usize = 2;
/// Columns of the row scratch.
const SCRATCH_COLS: usize = MAX_COLS + 2 * PAD;
/// Quantisation of unit-normal components for the median: 1/32000, about 0.002 degrees.
const QSCALE: f32 = 32000.0;
/// Median value of an invalid pixel (above every quantised component).
const QINVALID: i16 = i16::MAX;
/// Range keys: 2048 per octave of range (0.034 % resolution); 1/range from 1e-5 to 8 fits.
const KEY_SCALE: f32 = 2048.0;
/// Key of a pixel without a return: far from every real key.
const KEY_EMPTY: i16 = i16::MIN;

/// Pixel states.
const EMPTY: u8 = 0;
/// Valid, from the full window.
const FULL: u8 = 1;
/// Has a return; the full window was not usable: the gap-aware path decides.
const PARTIAL: u8 = 2;
/// Valid, from the gap-aware path.
const GAP: u8 = 3;
/// Has a return but no reliable normal.
const INVALID: u8 = 4;
/// Owner of a pixel without a valid normal once [`RingFals::write_points`] has run (point
/// indices stay below it: `project` refuses more than `u32::MAX` points).
const NO_OWNER: u32 = u32::MAX;

/// Whether a pixel of state `s` has a normal.
#[inline(always)]
fn has_normal(s: u8) -> bool {
    (s == FULL) | (s == GAP)
}

/// Padded pixel count that a [`RingFals`] needs for a `rows` x `cols` layout: use it as the
/// const parameter, e.g. `RingFals<{ storage_pixels(32, 1800) }>`.
pub const fn storage_pixels(rows: usize, cols: usize) -> usize {
    (rows + 2 * PAD) * (cols + 2 * PAD)
}

/// Storage for the largest supported layouts: 128 x 2048 (Ouster OS-x-128).
pub type RingFals128x2048 = RingFals<{ storage_pixels(128, 2048) }>;
/// Storage for a 64 x 2048 layout.
pub type RingFals64x2048 = RingFals<{ storage_pixels(64, 2048) }>;
/// Storage for a 32 x 1800 layout (VLP-32C at 10 Hz).
pub type RingFals32x1800 = RingFals<{ storage_pixels(32, 1800) }>;
/// Storage for a 16 x 1024 layout (OS1-16).
pub type RingFals16x1024 = RingFals<{ storage_pixels(16, 1024) }>;

/// The normal of one point: unit length and facing the sensor when `valid`, all zero otherwise.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(C)]
pub struct PointNormal {
    /// Unit normal in the LiDAR frame, pointing toward the sensor; zero when not valid.
    pub normal: [f32; 3],
    /// Whether `normal` is a reliable estimate.
    pub valid: bool,
}

impl PointNormal {
    /// No normal.
    pub const INVALID: Self = Self { normal: [0.0; 3], valid: false };

    /// The normal if valid.
    #[inline]
    pub fn get(&self) -> Option<[f32; 3]> {
        if self.valid { Some(self.normal) } else { None }
    }
}

/// Why [`RingFals::estimate`] refused a scan (nothing was computed).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum EstimateError {
    /// The table has not been built.
    NoTable,
    /// The storage holds fewer pixels than the table's layout needs.
    Capacity {
        /// [`storage_pixels`] of the layout.
        needed: u32,
        /// The storage's const parameter.
        capacity: u32,
    },
    /// `out` must hold exactly one entry per point.
    OutputLength,
    /// More than `u32::MAX` points.
    TooManyPoints,
}

impl core::fmt::Display for EstimateError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::NoTable => f.write_str("ring_fals: the table is not built"),
            Self::Capacity { needed, capacity } => {
                write!(f, "ring_fals: layout needs {needed} storage pixels, storage has {capacity}")
            }
            Self::OutputLength => f.write_str("ring_fals: output slice length differs from the point count"),
            Self::TooManyPoints => f.write_str("ring_fals: more than u32::MAX points"),
        }
    }
}

impl core::error::Error for EstimateError {}

/// What happened to one scan.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct RingFalsStats {
    /// Points in the scan.
    pub points: u32,
    /// Points that own a pixel (the nearest return of the pixel).
    pub projected: u32,
    /// Points that hit a pixel another point also hit (all but the nearest of each pixel).
    pub collisions: u32,
    /// Points without a pixel (`NO_PIXEL`, or row/column outside the layout).
    pub no_pixel: u32,
    /// Points of the columns between the image's ([`RingFalsConfig::column_stride`] above 1):
    /// not projected; they share their pixel's normal on the same surface.
    pub off_stride: u32,
    /// Points dropped for their range: non-finite, below `min_range` or above `max_range`.
    pub rejected_range: u32,
    /// Pixels with a valid normal.
    pub valid_pixels: u32,
    /// Pixels with a return but no reliable normal.
    pub invalid_pixels: u32,
    /// Valid pixels solved from an incomplete window (gap-aware path).
    pub gap_solves: u32,
    /// Pixels whose window had a point off the fitted plane (a step, a crease, an occluding
    /// edge) and went through the trimmed solve (valid or not).
    pub trimmed_solves: u32,
    /// Valid pixels that kept their own normal because their median window was too sparse or
    /// the median was degenerate.
    pub median_kept_own: u32,
    /// Points given a valid normal (owners and colliding points within the range gate).
    pub valid_points: u32,
}

/// Caller-owned working memory of Ring FALS for layouts of up to `P` padded pixels (see
/// [`storage_pixels`] and the aliases such as [`RingFals32x1800`]).
///
/// Holds the per-scan images (range, inverse range, owner point, normals, median planes, pixel
/// state) and a row scratch. One `RingFals` serves any table that fits; switching tables costs
/// one re-initialisation.
#[derive(Debug)]
pub struct RingFals<const P: usize> {
    rows: usize,
    cols: usize,
    stride: usize,
    stats: RingFalsStats,
    /// Squared range per pixel; 0 = no return.
    range2: [f32; P],
    /// 1 / range per pixel; 0 = no return.
    inv: [f32; P],
    /// Index of the point that owns the pixel (valid where `range2 > 0`).
    owner: [u32; P],
    /// Normal per pixel, planar; zero where not valid.
    nx: [f32; P],
    ny: [f32; P],
    nz: [f32; P],
    /// Quantised normal per pixel for the median; [`QINVALID`] where not valid.
    qx: [i16; P],
    qy: [i16; P],
    qz: [i16; P],
    /// -1 where the pixel is not valid, 0 where valid.
    qinv: [i16; P],
    /// Range key per pixel for the median's same-surface test: `KEY_SCALE log2(1/range)`;
    /// [`KEY_EMPTY`] where there is no return.
    key: [i16; P],
    state: [u8; P],
    /// Per row: the five values of each column's 5-row strip, sorted; [channel * 5 + rank].
    strips: [[i16; SCRATCH_COLS]; 15],
    /// Per row: minus the number of invalid pixels in each column's 5-row strip.
    strip_inv: [i16; SCRATCH_COLS],
    /// The largest and smallest range key of the valid pixels among each pixel and its two
    /// neighbours either side (`i16::MIN` / `i16::MAX` where none), for the five padded rows
    /// of the current windows (padded row `pr` in slot `pr % 5`).
    row_kmax: [[i16; SCRATCH_COLS]; 5],
    row_kmin: [[i16; SCRATCH_COLS]; 5],
}

impl<const P: usize> Default for RingFals<P> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const P: usize> RingFals<P> {
    /// Empty storage; `const` so that it can be a `static`.
    pub const fn new() -> Self {
        Self {
            rows: 0,
            cols: 0,
            stride: 0,
            stats: RingFalsStats {
                points: 0,
                projected: 0,
                collisions: 0,
                off_stride: 0,
                no_pixel: 0,
                rejected_range: 0,
                valid_pixels: 0,
                invalid_pixels: 0,
                gap_solves: 0,
                trimmed_solves: 0,
                median_kept_own: 0,
                valid_points: 0,
            },
            range2: [0.0; P],
            inv: [0.0; P],
            owner: [0; P],
            nx: [0.0; P],
            ny: [0.0; P],
            nz: [0.0; P],
            // All zero, so that a `static` lives in .bss; `bind` sets the invalid markers.
            qx: [0; P],
            qy: [0; P],
            qz: [0; P],
            qinv: [0; P],
            key: [0; P],
            state: [EMPTY; P],
            strips: [[0; SCRATCH_COLS]; 15],
            strip_inv: [0; SCRATCH_COLS],
            row_kmax: [[0; SCRATCH_COLS]; 5],
            row_kmin: [[0; SCRATCH_COLS]; 5],
        }
    }

    /// Statistics of the last scan.
    pub fn stats(&self) -> RingFalsStats {
        self.stats
    }

    /// Estimates the normal of every point of a scan.
    ///
    /// `points` use the table's layout for their `row`/`col`; `out[i]` receives the normal of
    /// `points[i]` (invalid for points without a pixel, with a filtered range, or whose pixel
    /// has no reliable normal; a point that lost its pixel to a nearer one shares that pixel's
    /// normal if its range is within the pixel's range gate). Runs the four stages in order:
    /// [`Self::project`], [`Self::solve`], [`Self::smooth`], [`Self::write_points`].
    pub fn estimate(
        &mut self,
        table: &RingTable,
        points: &[ScanPoint],
        out: &mut [PointNormal],
    ) -> Result<RingFalsStats, EstimateError> {
        if out.len() != points.len() {
            return Err(EstimateError::OutputLength);
        }
        self.project(table, points)?;
        self.solve(table);
        self.smooth(table);
        self.write_points(table, points, out);
        Ok(self.stats)
    }

    /// Stage 1: checks the sizes and projects the points into the range image (nearest return
    /// per pixel). Also binds the storage to the table's size.
    pub fn project(&mut self, table: &RingTable, points: &[ScanPoint]) -> Result<(), EstimateError> {
        let (rows, cols) = (table.rows(), table.cols());
        if rows == 0 {
            return Err(EstimateError::NoTable);
        }
        let needed = storage_pixels(rows, cols);
        if needed > P {
            return Err(EstimateError::Capacity { needed: needed as u32, capacity: P as u32 });
        }
        if points.len() > u32::MAX as usize {
            return Err(EstimateError::TooManyPoints);
        }
        if rows != self.rows || cols != self.cols {
            self.bind(rows, cols);
        }
        let stride = self.stride;
        self.stats = RingFalsStats { points: points.len() as u32, ..RingFalsStats::default() };

        // Clear the image rows (the pad rows stay empty forever).
        self.range2[PAD * stride..(PAD + rows) * stride].fill(0.0);
        // The owner image is written in the points' order, column by column, a stream per row:
        // more streams than the hardware prefetchers follow. Where the storage left the caches
        // between scans (the odometry's map work evicts it), it is read in order first.
        crate::math::read_in(&self.owner[PAD * stride..(PAD + rows) * stride]);

        let cfg = table.config;
        let (min2, max2) = (cfg.min_range * cfg.min_range, cfg.max_range * cfg.max_range);
        // Two counters only: with four, one lived on the stack, and its store and reload were a
        // chain through every iteration. Projected pixels are counted after the loop.
        let (mut no_pixel, mut rejected) = (0u32, 0u32);
        let ix = table.pixel_index(stride);
        let (shift, off) = (u32::from(table.col_shift), (1usize << table.col_shift) - 1);
        let layout_cols = cols << shift;
        let mut off_stride = 0u32;
        for (i, p) in points.iter().enumerate() {
            let (row, col) = (p.row as usize, p.col as usize);
            if row >= rows || col >= layout_cols {
                no_pixel += 1;
                continue;
            }
            // A column between the image's: its normal comes from its pixel (`write_points`).
            if col & off != 0 {
                off_stride += 1;
                continue;
            }
            let [x, y, z] = p.xyz;
            let r2 = x * x + y * y + z * z;
            // Written so that NaN fails: a non-finite point is rejected, never projected.
            if !(r2 >= min2 && r2 <= max2) {
                rejected += 1;
                continue;
            }
            let px = ix.px(row, col >> shift);
            let old = self.range2[px];
            if old == 0.0 || r2 < old {
                self.range2[px] = r2;
                self.owner[px] = i as u32;
            }
        }
        let image = &self.range2[PAD * stride..(PAD + rows) * stride];
        let projected = image.iter().fold(0u32, |n, &r2| n + u32::from(r2 > 0.0));
        self.stats.no_pixel = no_pixel;
        self.stats.rejected_range = rejected;
        self.stats.projected = projected;
        self.stats.off_stride = off_stride;
        self.stats.collisions = points.len() as u32 - no_pixel - rejected - projected - off_stride;
        Ok(())
    }

    /// Stage 4: the normal of every point, from its pixel. `points` are those of the last
    /// [`Self::project`] (as [`Self::estimate`] passes them); other points get meaningless
    /// normals, never a panic.
    pub fn write_points(&mut self, table: &RingTable, points: &[ScanPoint], out: &mut [PointNormal]) {
        let (rows, cols) = (self.rows, self.cols);
        if rows == 0 || table.rows() != rows || table.cols() != cols || out.len() != points.len() {
            out.fill(PointNormal::INVALID);
            return;
        }
        let st = self.stats;
        self.stats.valid_points =
            if st.collisions == 0 && st.off_stride == 0 && st.points as usize == points.len() {
                self.write_by_pixel(out)
            } else {
                self.write_by_point(table, points, out)
            };
    }

    /// [`Self::write_points`] when every point with a pixel owns it (no collisions): each
    /// pixel's normal goes to its owner, the image read in order instead of four planes read in
    /// the points' order (a third faster on the bench scans). A point without a pixel (none,
    /// or a filtered range) is invalid. Returns the valid points.
    fn write_by_pixel(&self, out: &mut [PointNormal]) -> u32 {
        let (rows, cols, stride) = (self.rows, self.cols, self.stride);
        let st = self.stats;
        if st.no_pixel > 0 || st.rejected_range > 0 {
            out.fill(PointNormal::INVALID);
        }
        let (mut valid_points, mut lost) = (0u32, 0u32);
        for r in PAD..PAD + rows {
            let i = r * stride + PAD..r * stride + PAD + cols;
            let (state, owner) = (&self.state[i.clone()], &self.owner[i.clone()]);
            let (nx, ny, nz) = (&self.nx[i.clone()], &self.ny[i.clone()], &self.nz[i]);
            for j in 0..cols {
                let s = state[j];
                if s == EMPTY {
                    continue;
                }
                let valid = has_normal(s);
                // Invalid pixels hold zero normals already; the mask makes sure of it without a
                // second store path.
                let keep = u32::from(valid).wrapping_neg();
                let normal = [nx[j], ny[j], nz[j]].map(|v| f32::from_bits(v.to_bits() & keep));
                // The owner was projected from these points; `get_mut` only keeps a caller who
                // passed other points from a panic.
                match out.get_mut(owner[j] as usize) {
                    Some(o) => *o = PointNormal { normal, valid },
                    None => lost += u32::from(valid),
                }
            }
            valid_points += state.iter().fold(0u32, |n, &s| n + u32::from(has_normal(s)));
        }
        valid_points -= lost;
        valid_points
    }

    /// [`Self::write_points`] point by point: a point that lost its pixel to a nearer one
    /// shares the pixel's normal if it lies on the same surface. Returns the valid points.
    fn write_by_point(&mut self, table: &RingTable, points: &[ScanPoint], out: &mut [PointNormal]) -> u32 {
        let (rows, cols, stride) = (self.rows, self.cols, self.stride);
        let mut valid_points = 0u32;
        let cfg = table.config;
        let (min2, max2) = (cfg.min_range * cfg.min_range, cfg.max_range * cfg.max_range);
        // Pixels without a normal get the owner no point has, so that the loop below tells
        // "owned and valid" by one load and compare instead of two (the state's load and test
        // were 40 % of its samples).
        for r in PAD..PAD + rows {
            let i = r * stride + PAD..r * stride + PAD + cols;
            for (o, &s) in self.owner[i.clone()].iter_mut().zip(&self.state[i]) {
                *o = if has_normal(s) { *o } else { NO_OWNER };
            }
        }
        let ix = table.pixel_index(stride);
        let shift = u32::from(table.col_shift);
        let layout_cols = cols << shift;
        for (i, (p, o)) in points.iter().zip(out.iter_mut()).enumerate() {
            let (row, col) = (p.row as usize, p.col as usize);
            if row >= rows || col >= layout_cols {
                *o = PointNormal::INVALID;
                continue;
            }
            let px = ix.px(row, col >> shift);
            // The pixel's owner was projected this scan (a pixel with a return was written),
            // so it passed the range filter already.
            let owner = self.owner[px];
            if owner != i as u32 {
                if owner == NO_OWNER {
                    *o = PointNormal::INVALID;
                    continue;
                }
                let [x, y, z] = p.xyz;
                let r2 = x * x + y * y + z * z;
                // A point that lost its pixel to a nearer one, or lies between the image's
                // columns, shares the pixel's normal only if it lies on the same surface: within
                // the gate to a same-row neighbour (one image column, at least as far).
                let (ri, rp) = (crate::math::sqrtf(r2), crate::math::sqrtf(self.range2[px]));
                let g = table.row[row].gate[CENTRE + 1];
                if !((r2 >= min2) & (r2 <= max2) & (ri - rp <= g * rp + cfg.range_jump_abs)) {
                    *o = PointNormal::INVALID;
                    continue;
                }
            }
            *o = PointNormal { normal: [self.nx[px], self.ny[px], self.nz[px]], valid: true };
            valid_points += 1;
        }
        valid_points
    }

    /// The normal of pixel (row, col) of the last scan, in the caller's columns; `None` when the
    /// pixel has no valid normal, is outside the layout or lies between the image's columns.
    pub fn pixel_normal(&self, table: &RingTable, row: usize, col: usize) -> Option<[f32; 3]> {
        let col = self.image_col(table, row, col)?;
        let px = (row + PAD) * self.stride + table.internal_col(row, col) + PAD;
        match self.state[px] {
            FULL | GAP => Some([self.nx[px], self.ny[px], self.nz[px]]),
            _ => None,
        }
    }

    /// Whether pixel (row, col) of the last scan was solved from an incomplete window.
    pub fn pixel_is_gap_solve(&self, table: &RingTable, row: usize, col: usize) -> bool {
        let Some(col) = self.image_col(table, row, col) else { return false };
        let px = (row + PAD) * self.stride + table.internal_col(row, col) + PAD;
        self.state[px] == GAP
    }

    /// The image column of the caller's pixel (row, col): `None` outside the layout, for a
    /// column between the image's, or for a table this storage was not bound to.
    fn image_col(&self, table: &RingTable, row: usize, col: usize) -> Option<usize> {
        let shift = u32::from(table.col_shift);
        let bound = table.rows() == self.rows && table.cols() == self.cols;
        let on = row < self.rows && col < self.cols << shift && col & ((1 << shift) - 1) == 0;
        (bound && on).then_some(col >> shift)
    }

    /// Sets up the planes for a new size: every pixel empty, every median value invalid.
    fn bind(&mut self, rows: usize, cols: usize) {
        self.rows = rows;
        self.cols = cols;
        self.stride = cols + 2 * PAD;
        let n = storage_pixels(rows, cols);
        self.range2[..n].fill(0.0);
        self.inv[..n].fill(0.0);
        self.owner[..n].fill(0);
        self.nx[..n].fill(0.0);
        self.ny[..n].fill(0.0);
        self.nz[..n].fill(0.0);
        self.qx[..n].fill(QINVALID);
        self.qy[..n].fill(QINVALID);
        self.qz[..n].fill(QINVALID);
        self.qinv[..n].fill(-1);
        self.key[..n].fill(KEY_EMPTY);
        self.state[..n].fill(EMPTY);
        // The pad rows hold -inf and +inf alternately (see `smooth`).
        let stride = self.stride;
        for pr in [0, 1, rows + PAD, rows + PAD + 1] {
            for pc in 0..stride {
                let v = pad_sentinel(pr, pc);
                let i = pr * stride + pc;
                (self.qx[i], self.qy[i], self.qz[i]) = (v, v, v);
            }
        }
    }
}

/// Median value of a pad-row pixel at padded row `pr`, column `pc`: -inf and +inf alternately,
/// so that a window's pad pixels sit at both ends of its sorted values in known numbers.
const fn pad_sentinel(pr: usize, pc: usize) -> i16 {
    if (pr + pc) & 1 == 0 { i16::MIN } else { QINVALID }
}

/// Copies the two image columns at each end of a padded row into the opposite pad columns.
#[inline]
fn wrap_row<T: Copy>(row: &mut [T], cols: usize) {
    // Layout: [pad0 pad1 | c0 c1 ... c(cols-1) | pad2 pad3]
    row[0] = row[cols];
    row[1] = row[cols + 1];
    row[cols + PAD] = row[PAD];
    row[cols + PAD + 1] = row[PAD + 1];
}

#[cfg(test)]
mod reference;
#[cfg(test)]
mod tests;
