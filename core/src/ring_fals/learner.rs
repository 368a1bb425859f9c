//! Learning a [`RangeImageLayout`] from observed points, for sensors without known intrinsics;
//! separate because it is optional: the table is built from its layout as from a calibration.

use crate::range_image::{LayoutError, MAX_ROWS, RangeImageLayout};
use crate::scan::ScanPoint;

/// Why [`RingLearner::layout`] could not produce a layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LearnError {
    /// The learner was not [reset](RingLearner::reset) to a size.
    NotStarted,
    /// A row saw fewer points than required.
    Unobserved {
        /// The row.
        row: u16,
    },
    /// A row's azimuth offsets disagree (mean resultant length below 0.95: the points are not
    /// binned by a fixed column step, e.g. the column direction or count is wrong).
    Inconsistent {
        /// The row.
        row: u16,
    },
    /// The learned angles do not make a valid layout.
    Layout(LayoutError),
}

impl core::fmt::Display for LearnError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::NotStarted => f.write_str("ring_fals: learner not started"),
            Self::Unobserved { row } => write!(f, "ring_fals: row {row} has too few observed points"),
            Self::Inconsistent { row } => {
                write!(f, "ring_fals: row {row} azimuths do not follow the column step")
            }
            Self::Layout(e) => write!(f, "{e}"),
        }
    }
}

impl core::error::Error for LearnError {}

/// What the learner found for one row.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LearnedRow {
    /// Points accumulated.
    pub points: u32,
    /// Mean elevation, radians.
    pub elevation: f64,
    /// Standard deviation of the elevation, radians.
    pub elevation_std: f64,
    /// Circular mean of (point azimuth - column step * column): the azimuth of column 0, radians.
    pub azimuth0: f64,
    /// Mean resultant length of those azimuths (1 = all identical).
    pub azimuth_consistency: f64,
}

/// Learns a [`RangeImageLayout`] from observed points, for sensors whose beam intrinsics are
/// unknown: the running mean direction of the returns of every ring.
///
/// A spinning LiDAR's pixel (row, col) looks along its beam's elevation and along the beam's
/// azimuth offset plus `col` column steps, so the mean direction of every pixel follows from
/// two numbers per row. The learner therefore keeps running sums per row (elevation, and the
/// circular mean of azimuth minus column angle) over every observed point: a few hundred bytes
/// instead of a table per pixel, no holes where a pixel was never hit (the reference leaves
/// those with a zero matrix, so their normals come out NaN), and the table is then built from
/// the learned layout exactly as from a calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct RingLearner {
    rows: u16,
    cols: u16,
    clockwise: bool,
    /// Points skipped (no pixel, outside the size, range under 1 m or not finite).
    pub rejected: u32,
    n: [u32; MAX_ROWS],
    sum_el: [f64; MAX_ROWS],
    sum_el2: [f64; MAX_ROWS],
    sum_c: [f64; MAX_ROWS],
    sum_s: [f64; MAX_ROWS],
}

impl Default for RingLearner {
    fn default() -> Self {
        Self::new()
    }
}

impl RingLearner {
    /// Closest range the learner uses: nearer returns are dominated by the beam-origin offsets.
    pub const MIN_RANGE: f32 = 1.0;

    /// An unstarted learner; `const` so that it can be a `static`.
    pub const fn new() -> Self {
        Self {
            rows: 0,
            cols: 0,
            clockwise: true,
            rejected: 0,
            n: [0; MAX_ROWS],
            sum_el: [0.0; MAX_ROWS],
            sum_el2: [0.0; MAX_ROWS],
            sum_c: [0.0; MAX_ROWS],
            sum_s: [0.0; MAX_ROWS],
        }
    }

    /// Starts learning a layout of `rows` x `cols` whose columns advance clockwise (seen from
    /// above) or not; forgets everything seen before.
    pub fn reset(&mut self, rows: usize, cols: usize, clockwise: bool) -> Result<(), LayoutError> {
        RangeImageLayout::new(rows, cols, clockwise)?;
        *self = Self::new();
        self.rows = rows as u16;
        self.cols = cols as u16;
        self.clockwise = clockwise;
        Ok(())
    }

    /// Accumulates the points of one scan (their `row`/`col` and direction).
    pub fn observe(&mut self, points: &[ScanPoint]) {
        let step = core::f64::consts::TAU / self.cols.max(1) as f64 * if self.clockwise { -1.0 } else { 1.0 };
        for p in points {
            let (row, col) = (p.row as usize, p.col as usize);
            let r = p.range();
            if row >= self.rows as usize
                || col >= self.cols as usize
                || !(r >= Self::MIN_RANGE && r.is_finite())
            {
                self.rejected = self.rejected.saturating_add(1);
                continue;
            }
            let [x, y, z] = p.xyz.map(|v| v as f64);
            let el = libm::atan2(z, crate::math::sqrt(x * x + y * y));
            let d = libm::atan2(y, x) - step * col as f64;
            self.n[row] = self.n[row].saturating_add(1);
            self.sum_el[row] += el;
            self.sum_el2[row] += el * el;
            self.sum_c[row] += libm::cos(d);
            self.sum_s[row] += libm::sin(d);
        }
    }

    /// The learned numbers of one row, if it saw any point.
    pub fn row(&self, row: usize) -> Option<LearnedRow> {
        if row >= self.rows as usize || self.n[row] == 0 {
            return None;
        }
        let n = self.n[row] as f64;
        let el = self.sum_el[row] / n;
        let var = (self.sum_el2[row] / n - el * el).max(0.0);
        Some(LearnedRow {
            points: self.n[row],
            elevation: el,
            elevation_std: crate::math::sqrt(var),
            azimuth0: libm::atan2(self.sum_s[row], self.sum_c[row]),
            azimuth_consistency: libm::hypot(self.sum_s[row], self.sum_c[row]) / n,
        })
    }

    /// The learned layout; every row must have seen at least `min_points_per_row` points.
    pub fn layout(&self, min_points_per_row: u32) -> Result<RangeImageLayout, LearnError> {
        if self.rows == 0 {
            return Err(LearnError::NotStarted);
        }
        let mut l = RangeImageLayout::new(self.rows as usize, self.cols as usize, self.clockwise)
            .map_err(LearnError::Layout)?;
        for r in 0..self.rows as usize {
            let row = r as u16;
            let lr = self.row(r).ok_or(LearnError::Unobserved { row })?;
            if lr.points < min_points_per_row.max(1) {
                return Err(LearnError::Unobserved { row });
            }
            if lr.azimuth_consistency < 0.95 {
                return Err(LearnError::Inconsistent { row });
            }
            l.set_row(r, lr.elevation as f32, lr.azimuth0 as f32).map_err(LearnError::Layout)?;
        }
        Ok(l)
    }
}
