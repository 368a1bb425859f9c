//! The estimator's settings and their validation, each threshold with its documented range;
//! separate because they are plain values that the table and every stage read.

/// Settings of the estimator. [`RingFalsConfig::DEFAULT`] suits Velodyne and Ouster sensors.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct RingFalsConfig {
    /// Returns closer than this (metres) are dropped: zero ranges, Ouster's few-centimetre
    /// "no return" points, the sensor's own housing. At least 0.01 m. Default 0.3 m.
    pub min_range: f32,
    /// Returns farther than this (metres) are dropped. At most 10 km. Default 1000 m.
    pub max_range: f32,
    /// Largest incidence angle (between ray and surface normal, degrees) of a surface whose
    /// neighbouring returns still count as one surface. A neighbour at angle `theta` from the
    /// centre ray is absent when `|r_n - r_c| > r_c * (cos(a)/cos(a + theta) - 1) + range_jump_abs`,
    /// the largest range change a plane at incidence `a` can produce. With the default 80
    /// degrees that is 2-4 % between columns of 1024-1800 column sensors and 28 % between the
    /// 2.2 degree rows of an OS1-16: a fixed relative threshold would either cut the ground
    /// seen at grazing angles or merge a person standing 30 cm in front of a wall.
    pub max_incidence_deg: f32,
    /// Absolute part of the range-jump gate (metres), for range noise. Default 0.05 m, five
    /// standard deviations of a typical 1 cm range noise.
    pub range_jump_abs: f32,
    /// Relative part of the plane-fit check: after the solve, the window's points must lie on
    /// the fitted plane: the squares of their range residuals (along their rays) may sum to at
    /// most `4 (range_jump_abs + fit_tolerance_rel r)^2` (noise up to 0.8 of that tolerance per
    /// point passes, one point off by more than 2.2 times it fails). A window that fails is
    /// solved again without its worst point, else without each of its edge lines (top or
    /// bottom row, left or right column), taking the plane that fits its remaining points best;
    /// if none fits, the pixel is invalid.
    /// This is what separates a pole from the wall behind it where the rows are degrees apart
    /// (the top and bottom beams of a VLP-32C) and the range gate alone must admit large
    /// jumps. In [0.002, 1] (the full-window test sums squared inverse ranges in f32, whose
    /// rounding is 1e-6 of the sum: a smaller tolerance would send every far window to the
    /// slower gap-aware path). Default 0.01.
    pub fit_tolerance_rel: f32,
    /// Fewest window points (the centre included) an incomplete window may be solved from,
    /// 3..=9. Default 4: one more than a plane needs, so one bad range cannot fully decide it.
    pub min_points: u8,
    /// Smallest accepted conditioning `27 det(M') / trace(M')^3` of an incomplete window's
    /// scaled 3x3 system (1 for an isotropic system, 0 for a singular one; a full window has
    /// about 0.94, a 2x2 corner window 0.21, three points in an L 0.22), in (0, 1). Default
    /// 0.02: only near-collinear windows, which pass the image-line test only because of
    /// irregular beam spacing, are rejected.
    pub min_conditioning: f32,
    /// Whether to apply the 5x5 median. Default true.
    pub median: bool,
    /// A valid pixel whose 5x5 window holds fewer valid pixels than this (itself included)
    /// keeps its own normal instead of the median: with so few neighbours the median is not a
    /// robust estimate. 1..=25, default 5.
    pub median_min_valid: u8,
    /// Every how many of the layout's columns the normals' image keeps: 1 (every column), 2 or
    /// 4. With 2 the image has half the columns (0.4 degrees apart on a 1800-column Velodyne):
    /// only the returns of every second column are projected, the solve and the median run on
    /// half the pixels, and every other return takes its pixel's normal when it lies on the same
    /// surface (the range gate of a neighbouring column). A trade of accuracy for time, not the
    /// default: on the simulated VLP-32C drives the normals' stage took 0.61x the time and the
    /// whole scan about 0.9x, but the vehicle's ATE grew 1.10x over six seeds
    /// (docs/ring-fals.md). The layout's columns must be a multiple of it. Default 1.
    pub column_stride: u8,
}

impl RingFalsConfig {
    /// The defaults described on each field.
    pub const DEFAULT: Self = Self {
        min_range: 0.3,
        max_range: 1000.0,
        max_incidence_deg: 80.0,
        range_jump_abs: 0.05,
        fit_tolerance_rel: 0.01,
        min_points: 4,
        min_conditioning: 0.02,
        median: true,
        median_min_valid: 5,
        column_stride: 1,
    };

    /// Checks every field against its documented range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let ok = |c: bool, e: ConfigError| if c { Ok(()) } else { Err(e) };
        ok(self.min_range >= 0.01 && self.min_range < 1.0e4, ConfigError::MinRange)?;
        ok(self.max_range > self.min_range && self.max_range <= 1.0e4, ConfigError::MaxRange)?;
        ok(self.max_incidence_deg > 0.0 && self.max_incidence_deg <= 89.0, ConfigError::MaxIncidence)?;
        ok(self.range_jump_abs.is_finite() && self.range_jump_abs >= 0.0, ConfigError::RangeJumpAbs)?;
        ok((0.002..=1.0).contains(&self.fit_tolerance_rel), ConfigError::FitToleranceRel)?;
        ok((3..=9).contains(&self.min_points), ConfigError::MinPoints)?;
        ok(self.min_conditioning > 0.0 && self.min_conditioning < 1.0, ConfigError::MinConditioning)?;
        ok((1..=25).contains(&self.median_min_valid), ConfigError::MedianMinValid)?;
        ok(matches!(self.column_stride, 1 | 2 | 4), ConfigError::ColumnStride)
    }
}

impl Default for RingFalsConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Which [`RingFalsConfig`] field is out of range.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ConfigError {
    /// `min_range` must be at least 0.01 m (a zero range marks an empty pixel).
    MinRange,
    /// `max_range` must be greater than `min_range` and at most 10 km.
    MaxRange,
    /// `max_incidence_deg` must be in (0, 89].
    MaxIncidence,
    /// `range_jump_abs` must be finite and at least 0.
    RangeJumpAbs,
    /// `fit_tolerance_rel` must be in [0.002, 1].
    FitToleranceRel,
    /// `min_points` must be in 3..=9.
    MinPoints,
    /// `min_conditioning` must be in (0, 1).
    MinConditioning,
    /// `median_min_valid` must be in 1..=25.
    MedianMinValid,
    /// `column_stride` must be 1, 2 or 4.
    ColumnStride,
}

impl core::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::MinRange => "ring_fals: min_range must be in [0.01, 1e4) m",
            Self::MaxRange => "ring_fals: max_range must be in (min_range, 1e4] m",
            Self::MaxIncidence => "ring_fals: max_incidence_deg must be in (0, 89]",
            Self::RangeJumpAbs => "ring_fals: range_jump_abs must be finite and >= 0",
            Self::FitToleranceRel => "ring_fals: fit_tolerance_rel must be in [0.002, 1]",
            Self::MinPoints => "ring_fals: min_points must be in 3..=9",
            Self::MinConditioning => "ring_fals: min_conditioning must be in (0, 1)",
            Self::MedianMinValid => "ring_fals: median_min_valid must be in 1..=25",
            Self::ColumnStride => "ring_fals: column_stride must be 1, 2 or 4",
        })
    }
}

impl core::error::Error for ConfigError {}
