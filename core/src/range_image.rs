//! Range-image geometry of a spinning LiDAR: which direction each pixel (row, column) looks in.
//!
//! Rows are beams ordered by elevation, row 0 the highest. Columns are azimuth bins of one
//! revolution. Each row has its own azimuth for column 0, because beams of one firing are
//! offset in azimuth (Ouster's per-beam azimuth angles after destaggering, for example).
//! Columns advance clockwise or counter-clockwise as the sensor spins; either way the column of
//! an azimuth is computed wrap-safe, so the bin straddling 0/360 degrees is never lost (LOG-LIO's
//! reference code rounds an azimuth within half a column below 360 degrees to a column past the
//! last and drops the point, so its column 0 holds only half a bin).
//!
//! The decoders build a [`RangeImageLayout`] from the sensor's own calibration, and Ring FALS
//! builds its lookup table from the same layout, so no recording has to be replayed to make a
//! table.

use core::f64::consts::TAU;

/// Most rows (beams) a layout can hold.
pub const MAX_ROWS: usize = 128;
/// Most columns a layout can hold (0.1 degree bins).
pub const MAX_COLS: usize = 3600;

/// Why a layout could not be built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LayoutError {
    /// Zero rows, or more than [`MAX_ROWS`].
    BadRows,
    /// Fewer than 8 columns, or more than [`MAX_COLS`].
    BadCols,
    /// A row index past the layout's rows.
    RowOutOfRange,
    /// An angle that is not finite.
    NotFinite,
}

impl core::fmt::Display for LayoutError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::BadRows => "range image rows must be 1..=128",
            Self::BadCols => "range image columns must be 8..=3600",
            Self::RowOutOfRange => "row index out of range",
            Self::NotFinite => "beam angle is not finite",
        })
    }
}

impl core::error::Error for LayoutError {}

/// The direction of every pixel of a spinning LiDAR's range image.
///
/// Pixel (row, col) looks along elevation `elevation[row]` and azimuth
/// `azimuth0[row] + s * col * 2*pi/cols`, with s = -1 when columns advance clockwise (seen from
/// above, as Velodyne azimuths and Ouster measurement ids do) and s = +1 otherwise. Azimuth is
/// counter-clockwise from +x, x forward, y left, z up.
#[derive(Clone, Debug, PartialEq)]
pub struct RangeImageLayout {
    rows: u16,
    cols: u16,
    clockwise: bool,
    elevation: [f32; MAX_ROWS],
    azimuth0: [f32; MAX_ROWS],
}

impl RangeImageLayout {
    /// A layout with no rows; `const` so that it can initialise a `static`.
    pub const fn empty() -> Self {
        Self { rows: 0, cols: 0, clockwise: true, elevation: [0.0; MAX_ROWS], azimuth0: [0.0; MAX_ROWS] }
    }

    /// A layout of `rows` x `cols` with every beam at elevation 0 and azimuth offset 0; set the
    /// beams with [`Self::set_row`].
    pub fn new(rows: usize, cols: usize, clockwise: bool) -> Result<Self, LayoutError> {
        if rows == 0 || rows > MAX_ROWS {
            return Err(LayoutError::BadRows);
        }
        if !(8..=MAX_COLS).contains(&cols) {
            return Err(LayoutError::BadCols);
        }
        Ok(Self { rows: rows as u16, cols: cols as u16, clockwise, ..Self::empty() })
    }

    /// A layout whose rows have the given elevations (radians, row 0 highest) and a common
    /// azimuth origin of 0.
    pub fn from_elevations(elevations: &[f32], cols: usize, clockwise: bool) -> Result<Self, LayoutError> {
        let mut l = Self::new(elevations.len(), cols, clockwise)?;
        for (row, &e) in elevations.iter().enumerate() {
            l.set_row(row, e, 0.0)?;
        }
        Ok(l)
    }

    /// Sets one beam: its elevation and the azimuth of its column 0, both radians.
    pub fn set_row(&mut self, row: usize, elevation: f32, azimuth0: f32) -> Result<(), LayoutError> {
        if row >= self.rows as usize {
            return Err(LayoutError::RowOutOfRange);
        }
        if !elevation.is_finite() || !azimuth0.is_finite() {
            return Err(LayoutError::NotFinite);
        }
        self.elevation[row] = elevation;
        self.azimuth0[row] = azimuth0;
        Ok(())
    }

    /// Number of rows (beams).
    #[inline]
    pub fn rows(&self) -> usize {
        self.rows as usize
    }

    /// Number of columns per revolution.
    #[inline]
    pub fn cols(&self) -> usize {
        self.cols as usize
    }

    /// Number of pixels, rows x cols.
    #[inline]
    pub fn pixels(&self) -> usize {
        self.rows() * self.cols()
    }

    /// Whether columns advance clockwise seen from above.
    #[inline]
    pub fn clockwise(&self) -> bool {
        self.clockwise
    }

    /// Elevation of a row's beam, radians.
    #[inline]
    pub fn elevation(&self, row: usize) -> f32 {
        self.elevation[row]
    }

    /// Azimuth of a row's column 0, radians.
    #[inline]
    pub fn azimuth0(&self, row: usize) -> f32 {
        self.azimuth0[row]
    }

    /// Signed azimuth step from one column to the next, radians.
    #[inline]
    pub fn column_step(&self) -> f64 {
        let s = TAU / self.cols as f64;
        if self.clockwise { -s } else { s }
    }

    /// Azimuth of pixel (row, col), radians, not wrapped.
    #[inline]
    pub fn azimuth(&self, row: usize, col: usize) -> f64 {
        self.azimuth0[row] as f64 + self.column_step() * col as f64
    }

    /// Unit direction of pixel (row, col) in the LiDAR frame.
    pub fn direction(&self, row: usize, col: usize) -> [f64; 3] {
        let el = self.elevation[row] as f64;
        let az = self.azimuth(row, col);
        let (se, ce) = (libm::sin(el), libm::cos(el));
        let (sa, ca) = (libm::sin(az), libm::cos(az));
        [ce * ca, ce * sa, se]
    }

    /// The column whose centre is nearest to `azimuth` (radians, any multiple of 2*pi) for the
    /// given row. Wrap-safe: angles just below 360 degrees land in column 0.
    pub fn column_of(&self, row: usize, azimuth: f64) -> u16 {
        let cols = self.cols as f64;
        let x = (azimuth - self.azimuth0[row] as f64) / self.column_step();
        let c = crate::math::floor_f64(x + 0.5);
        let c = c - cols * crate::math::floor_f64(c / cols);
        // `c` is in [0, cols]; rounding of the last expression can give exactly `cols`.
        let c = c as u32;
        if c >= self.cols as u32 { 0 } else { c as u16 }
    }

    /// The row whose elevation is nearest to `elevation` (radians), or `None` for an empty
    /// layout. For sensors whose decoder does not know the beam (a cloud without a ring field).
    pub fn row_of_elevation(&self, elevation: f32) -> Option<u16> {
        let mut best: Option<(u16, f32)> = None;
        for r in 0..self.rows() {
            let d = libm::fabsf(self.elevation[r] - elevation);
            if best.is_none_or(|(_, bd)| d < bd) {
                best = Some((r as u16, d));
            }
        }
        best.map(|(r, _)| r)
    }
}

impl Default for RangeImageLayout {
    fn default() -> Self {
        Self::empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn deg(d: f64) -> f64 {
        d.to_radians()
    }

    #[test]
    fn rejects_bad_sizes() {
        assert_eq!(RangeImageLayout::new(0, 1024, true), Err(LayoutError::BadRows));
        assert_eq!(RangeImageLayout::new(129, 1024, true), Err(LayoutError::BadRows));
        assert_eq!(RangeImageLayout::new(16, 4, true), Err(LayoutError::BadCols));
        assert_eq!(RangeImageLayout::new(16, 5000, true), Err(LayoutError::BadCols));
        let mut l = RangeImageLayout::new(2, 16, true).unwrap();
        assert_eq!(l.set_row(2, 0.0, 0.0), Err(LayoutError::RowOutOfRange));
        assert_eq!(l.set_row(0, f32::NAN, 0.0), Err(LayoutError::NotFinite));
    }

    #[test]
    fn column_wraps_at_360_degrees() {
        let l = RangeImageLayout::new(1, 1800, false).unwrap();
        // 0.2 degree bins: 359.95 degrees is nearer column 0 than column 1799.
        assert_eq!(l.column_of(0, deg(359.95)), 0);
        assert_eq!(l.column_of(0, deg(359.85)), 1799);
        assert_eq!(l.column_of(0, deg(-0.05)), 0);
        assert_eq!(l.column_of(0, deg(0.09)), 0);
        assert_eq!(l.column_of(0, deg(0.11)), 1);
        assert_eq!(l.column_of(0, deg(720.0 + 90.0)), 450);
    }

    #[test]
    fn clockwise_columns_and_row_offsets_round_trip() {
        let mut l = RangeImageLayout::new(2, 1024, true).unwrap();
        l.set_row(0, 0.1, 0.3).unwrap();
        l.set_row(1, -0.1, -0.2).unwrap();
        for row in 0..2 {
            for col in [0usize, 1, 511, 1023] {
                let d = l.direction(row, col);
                let az = libm::atan2(d[1], d[0]);
                assert_eq!(l.column_of(row, az) as usize, col, "row {row} col {col}");
                let n = d.iter().map(|v| v * v).sum::<f64>();
                assert!((n - 1.0).abs() < 1e-12);
            }
        }
        // Clockwise: column 1 is a small turn to the right of column 0.
        assert!(l.azimuth(0, 1) < l.azimuth(0, 0));
    }

    #[test]
    fn nearest_row_by_elevation() {
        let l = RangeImageLayout::from_elevations(&[0.2, 0.0, -0.2], 64, true).unwrap();
        assert_eq!(l.row_of_elevation(0.15), Some(0));
        assert_eq!(l.row_of_elevation(-0.05), Some(1));
        assert_eq!(l.row_of_elevation(-1.0), Some(2));
        assert_eq!(RangeImageLayout::empty().row_of_elevation(0.0), None);
    }
}
