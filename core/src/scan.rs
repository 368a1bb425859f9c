//! A LiDAR scan as the rest of the core sees it: points in the LiDAR frame, each with its time
//! offset from the scan start and its pixel in the sensor's range image.
//!
//! The decoders (`sensor`) produce [`ScanPoint`]s; Ring FALS reads their pixels; the odometry
//! reads their times to undistort them. Storage is caller-owned: a [`ScanBuffer`] is a fixed
//! array that can live in a `static`.

/// Marks a point that has no pixel in the range image (it keeps its place in the scan and is
/// still used for mapping, it only gets no Ring FALS normal).
pub const NO_PIXEL: u16 = u16::MAX;

/// One LiDAR return. 24 bytes, `Copy`, no padding surprises.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(C)]
pub struct ScanPoint {
    /// Position in the LiDAR frame (x forward, y left, z up), metres.
    pub xyz: [f32; 3],
    /// Seconds since the scan's start time ([`ScanBuffer::start_ns`]), at least 0.
    pub t: f32,
    /// Range-image row: the beam, ordered by elevation with row 0 the highest; [`NO_PIXEL`] if none.
    pub row: u16,
    /// Range-image column (see [`crate::range_image::RangeImageLayout`]); [`NO_PIXEL`] if none.
    pub col: u16,
    /// Intensity or reflectivity as the sensor reports it.
    pub intensity: u16,
    /// Return index: 0 for the strongest (or only) return, 1 for the second of a dual return.
    pub ret: u8,
    /// Reserved for per-point flags; 0 today.
    pub flags: u8,
}

impl ScanPoint {
    /// Distance from the LiDAR origin, metres.
    #[inline]
    pub fn range(&self) -> f32 {
        let [x, y, z] = self.xyz;
        crate::math::sqrtf(x * x + y * y + z * z)
    }

    /// Whether the point has a range-image pixel.
    #[inline]
    pub fn has_pixel(&self) -> bool {
        self.row != NO_PIXEL && self.col != NO_PIXEL
    }
}

/// A borrowed scan: the points and the absolute time of the scan start.
#[derive(Clone, Copy, Debug)]
pub struct ScanView<'a> {
    /// Absolute time of the scan start, nanoseconds (the sensor's or the host's clock, as chosen
    /// by the caller; the core only takes differences).
    pub start_ns: u64,
    /// The points, in the order the sensor produced them.
    pub points: &'a [ScanPoint],
}

/// Error returned when a fixed-capacity buffer is full. The point is counted, not stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct CapacityError;

impl core::fmt::Display for CapacityError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("scan buffer is full")
    }
}

impl core::error::Error for CapacityError {}

/// Caller-owned storage for one scan of at most `N` points.
#[derive(Debug)]
pub struct ScanBuffer<const N: usize> {
    /// Absolute time of the scan start, nanoseconds.
    pub start_ns: u64,
    /// Points that did not fit and were dropped (counted, never silently lost).
    pub overflow: u32,
    points: heapless::Vec<ScanPoint, N>,
}

impl<const N: usize> Default for ScanBuffer<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> ScanBuffer<N> {
    /// An empty buffer; `const` so it can be a `static`.
    pub const fn new() -> Self {
        Self { start_ns: 0, overflow: 0, points: heapless::Vec::new() }
    }

    /// Empties the buffer and sets the start time of the next scan.
    pub fn clear(&mut self, start_ns: u64) {
        self.points.clear();
        self.overflow = 0;
        self.start_ns = start_ns;
    }

    /// Appends a point; when full the point is counted in [`Self::overflow`] and dropped.
    pub fn push(&mut self, p: ScanPoint) -> Result<(), CapacityError> {
        self.points.push(p).map_err(|_| {
            self.overflow = self.overflow.saturating_add(1);
            CapacityError
        })
    }

    /// The points stored so far.
    pub fn points(&self) -> &[ScanPoint] {
        &self.points
    }

    /// Mutable access to the stored points (e.g. to undistort them in place).
    pub fn points_mut(&mut self) -> &mut [ScanPoint] {
        &mut self.points
    }

    /// Number of points stored.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Whether no point is stored.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Capacity `N`.
    pub const fn capacity(&self) -> usize {
        N
    }

    /// A borrowed view of the scan.
    pub fn view(&self) -> ScanView<'_> {
        ScanView { start_ns: self.start_ns, points: &self.points }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_is_24_bytes() {
        assert_eq!(core::mem::size_of::<ScanPoint>(), 24);
    }

    #[test]
    fn overflow_is_counted_and_earlier_points_kept() {
        let mut b = ScanBuffer::<2>::new();
        b.clear(5);
        let p = ScanPoint { xyz: [3.0, 4.0, 0.0], ..Default::default() };
        assert!(b.push(p).is_ok());
        assert!(b.push(p).is_ok());
        assert_eq!(b.push(p), Err(CapacityError));
        assert_eq!(b.len(), 2);
        assert_eq!(b.overflow, 1);
        assert_eq!(b.points()[0].range(), 5.0);
        assert_eq!(b.view().start_ns, 5);
    }
}
