//! Velodyne VLP-16, VLP-32C and HDL-32E data packets (1206-byte UDP payloads, port 2368).
//!
//! Wire format (all models, little-endian), from the Velodyne user manuals:
//!
//! ```text
//! 12 blocks x 100 bytes:  flag 0xFFEE (u16 = 0xEEFF) | azimuth u16 (0.01 deg) | 32 x (distance u16, intensity u8)
//! 1200..1204  timestamp: microseconds past the top of the hour (time of the first firing of block 0)
//! 1204        return mode: 0x37 strongest, 0x38 last, 0x39 dual
//! 1205        product id:  0x21 HDL-32E, 0x22 VLP-16, 0x24 VLP-16 Hi-Res, 0x28 VLP-32C
//! ```
//!
//! A VLP-16 block holds two firing sequences of 16 lasers; VLP-32C and HDL-32E blocks hold one
//! sequence of 32. In dual-return mode blocks come in pairs with equal azimuths: the even block
//! holds the last returns, the odd block the strongest.
//!
//! Decoding follows the manuals and the ROS `velodyne_pointcloud` driver conventions, so that the
//! points agree with `velodyne_decoder` (the reference decodes in `tests/data`) to well under a
//! millimetre:
//! - each firing's azimuth is the block azimuth plus the packet's mean rotation rate times the
//!   firing's time offset, rounded to the sensor's 0.01 degree resolution (in `f32`, exactly as the
//!   ROS driver does);
//! - a laser's calibrated elevation `v`, azimuth correction `r` and vertical offset `o` give
//!   `x = d cos v cos(a - r)`, `y = -d cos v sin(a - r)`, `z = d sin v + o` (ROS frame: x forward,
//!   y left, z up; the Velodyne azimuth `a` turns clockwise);
//! - each point's time is its firing time from the manuals' timing tables.
//!
//! The configured model always wins over the product-id byte: two real VLP-16 captures report
//! 0x21 (HDL-32E). A mismatch is counted in [`DecoderStats::model_mismatch`] and logged once.

use crate::range_image::{LayoutError, RangeImageLayout};
use crate::scan_assembly::{PacketMeta, PacketSeq, RawPoint};

/// Length of a data packet's UDP payload.
pub const DATA_PACKET_LEN: usize = 1206;
/// Data blocks per packet.
pub const BLOCKS: usize = 12;
/// Measurements per block.
pub const CHANNELS: usize = 32;
/// The block flag as read little-endian (bytes 0xFF 0xEE on the wire).
pub const BLOCK_FLAG: u16 = 0xEEFF;
/// UDP port of data packets.
pub const DATA_PORT: u16 = 2368;
/// Microseconds per hour: the packet timestamp wraps here.
pub const MICROS_PER_HOUR: u64 = 3_600_000_000;

/// Field ranges of a data packet.
pub mod field {
    use core::ops::Range;
    /// Bytes of one data block.
    pub const BLOCK_LEN: usize = 100;
    /// Block `i`.
    pub const fn block(i: usize) -> Range<usize> {
        i * BLOCK_LEN..(i + 1) * BLOCK_LEN
    }
    /// Flag within a block.
    pub const FLAG: Range<usize> = 0..2;
    /// Azimuth within a block, hundredths of a degree.
    pub const AZIMUTH: Range<usize> = 2..4;
    /// Measurement `j` within a block: distance u16, intensity u8.
    pub const fn channel(j: usize) -> Range<usize> {
        4 + 3 * j..7 + 3 * j
    }
    /// Microseconds past the hour.
    pub const TIMESTAMP: Range<usize> = 1200..1204;
    /// Return mode byte.
    pub const RETURN_MODE: usize = 1204;
    /// Product id byte.
    pub const PRODUCT_ID: usize = 1205;
}

/// Why a data packet was rejected. The whole packet is dropped (and counted by the caller).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Error {
    /// Shorter than [`DATA_PACKET_LEN`].
    Truncated,
    /// Longer than [`DATA_PACKET_LEN`].
    TooLong,
    /// A block does not start with 0xFFEE (garbage, or not a data packet).
    BadBlockFlag,
    /// A block azimuth is more than 36000 (360 deg).
    BadAzimuth,
}

impl core::fmt::Display for Error {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Truncated => "velodyne data packet shorter than 1206 bytes",
            Self::TooLong => "velodyne data packet longer than 1206 bytes",
            Self::BadBlockFlag => "velodyne data block without the 0xFFEE flag",
            Self::BadAzimuth => "velodyne block azimuth out of range (> 360 deg)",
        })
    }
}

impl core::error::Error for Error {}

/// Sensor models this decoder knows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Model {
    /// VLP-16 (Puck), 16 lasers, +-15 deg.
    Vlp16,
    /// VLP-32C (Ultra Puck), 32 lasers, -25..+15 deg.
    Vlp32c,
    /// HDL-32E, 32 lasers, -30.67..+10.67 deg.
    Hdl32e,
}

impl Model {
    /// The product id byte this model writes at offset 1205.
    pub const fn product_id(self) -> u8 {
        match self {
            Self::Vlp16 => 0x22,
            Self::Vlp32c => 0x28,
            Self::Hdl32e => 0x21,
        }
    }

    /// The model a product id byte names, if it is one of ours.
    pub const fn from_product_id(id: u8) -> Option<Self> {
        match id {
            0x22 => Some(Self::Vlp16),
            0x28 => Some(Self::Vlp32c),
            0x21 => Some(Self::Hdl32e),
            _ => None,
        }
    }

    /// Number of lasers (range-image rows).
    pub const fn lasers(self) -> usize {
        match self {
            Self::Vlp16 => 16,
            _ => 32,
        }
    }

    /// Firing sequences per block (VLP-16 packs two sequences of 16 lasers in a block).
    pub const fn sequences_per_block(self) -> usize {
        match self {
            Self::Vlp16 => 2,
            _ => 1,
        }
    }

    /// Duration of one firing sequence (all lasers once, with recharge), nanoseconds (exact).
    pub const fn firing_cycle_ns(self) -> u32 {
        match self {
            Self::Vlp16 | Self::Vlp32c => 55_296,
            Self::Hdl32e => 46_080,
        }
    }

    /// Nominal time between data packets, nanoseconds: 12 blocks, halved in dual-return mode.
    pub const fn packet_period_ns(self, dual: bool) -> u32 {
        let firings = BLOCKS * self.sequences_per_block() / if dual { 2 } else { 1 };
        firings as u32 * self.firing_cycle_ns()
    }

    /// Firing time of measurement `channel` of block `block` after the packet timestamp, seconds
    /// (the manuals' timing tables; in dual mode block pairs share a time, pass `block / 2`).
    pub fn timing_offset_s(self, block: usize, channel: usize) -> f64 {
        match self {
            // 1.152 us per firing, 32 firings + recharge = 46.08 us per block.
            Self::Hdl32e => 46.080e-6 * block as f64 + 1.152e-6 * channel as f64,
            // Two sequences per block; 2.304 us per laser, 55.296 us per sequence.
            Self::Vlp16 => 55.296e-6 * (2 * block + channel / 16) as f64 + 2.304e-6 * (channel % 16) as f64,
            // Lasers fire in pairs: 16 firings of 2.304 us per 55.296 us sequence.
            Self::Vlp32c => 55.296e-6 * block as f64 + 2.304e-6 * (channel / 2) as f64,
        }
    }

    /// Range-image columns for a rotation rate: one column per firing sequence, rounded.
    pub fn columns_for_rpm(self, rpm: f32) -> usize {
        let deg_per_firing = rpm as f64 * 6.0 * self.firing_cycle_ns() as f64 * 1e-9;
        if deg_per_firing.is_nan() || deg_per_firing <= 0.0 {
            return 1800;
        }
        let cols = libm::round(360.0 / deg_per_firing);
        (cols as usize).clamp(8, crate::range_image::MAX_COLS)
    }
}

/// Return mode from byte 1204.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ReturnMode {
    /// 0x37: the strongest return of each firing.
    Strongest,
    /// 0x38: the last return of each firing.
    Last,
    /// 0x39: both; block pairs (last, strongest).
    Dual,
    /// Any other byte (old HDL-32E firmware writes 0): decoded as single return.
    Unspecified(u8),
}

impl ReturnMode {
    /// Decodes byte 1204.
    pub const fn from_byte(b: u8) -> Self {
        match b {
            0x37 => Self::Strongest,
            0x38 => Self::Last,
            0x39 => Self::Dual,
            other => Self::Unspecified(other),
        }
    }

    /// Whether block pairs carry two returns.
    pub const fn is_dual(self) -> bool {
        matches!(self, Self::Dual)
    }
}

/// A zero-copy view of a data packet whose length and block flags have been checked, so no
/// accessor can panic.
#[derive(Debug, Clone, Copy)]
pub struct Packet<T: AsRef<[u8]>> {
    buffer: T,
}

impl<T: AsRef<[u8]>> Packet<T> {
    /// Wraps a buffer without checks; accessors may panic on a short buffer.
    pub const fn new_unchecked(buffer: T) -> Self {
        Self { buffer }
    }

    /// Wraps a buffer after [`Self::check`].
    pub fn new_checked(buffer: T) -> Result<Self, Error> {
        let p = Self::new_unchecked(buffer);
        p.check()?;
        Ok(p)
    }

    /// Checks the length, every block flag and every block azimuth.
    pub fn check(&self) -> Result<(), Error> {
        let b = self.buffer.as_ref();
        if b.len() < DATA_PACKET_LEN {
            return Err(Error::Truncated);
        }
        if b.len() > DATA_PACKET_LEN {
            return Err(Error::TooLong);
        }
        for i in 0..BLOCKS {
            if self.block_flag(i) != BLOCK_FLAG {
                return Err(Error::BadBlockFlag);
            }
            // Real sensors send exactly 36000 now and then (= 0 deg); more is garbage.
            if self.azimuth(i) > 36_000 {
                return Err(Error::BadAzimuth);
            }
        }
        Ok(())
    }

    /// The underlying buffer.
    pub fn into_inner(self) -> T {
        self.buffer
    }

    fn u16_at(&self, at: usize) -> u16 {
        let b = self.buffer.as_ref();
        u16::from_le_bytes([b[at], b[at + 1]])
    }

    /// Flag of block `i` (read little-endian).
    pub fn block_flag(&self, i: usize) -> u16 {
        self.u16_at(field::block(i).start + field::FLAG.start)
    }

    /// Azimuth of block `i`, hundredths of a degree, clockwise from forward.
    pub fn azimuth(&self, i: usize) -> u16 {
        self.u16_at(field::block(i).start + field::AZIMUTH.start)
    }

    /// Raw distance (in units of the calibration's resolution) and intensity of measurement `j`
    /// of block `i`; distance 0 means no return.
    pub fn measurement(&self, i: usize, j: usize) -> (u16, u8) {
        let at = field::block(i).start + field::channel(j).start;
        (self.u16_at(at), self.buffer.as_ref()[at + 2])
    }

    /// Microseconds past the top of the hour of the first firing.
    pub fn timestamp_us(&self) -> u32 {
        let b = self.buffer.as_ref();
        let r = field::TIMESTAMP;
        u32::from_le_bytes([b[r.start], b[r.start + 1], b[r.start + 2], b[r.start + 3]])
    }

    /// Return mode.
    pub fn return_mode(&self) -> ReturnMode {
        ReturnMode::from_byte(self.buffer.as_ref()[field::RETURN_MODE])
    }

    /// Product id byte.
    pub fn product_id(&self) -> u8 {
        self.buffer.as_ref()[field::PRODUCT_ID]
    }
}

/// The header facts of a data packet.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PacketRepr {
    /// Microseconds past the top of the hour (first firing of the packet).
    pub timestamp_us: u32,
    /// Return mode.
    pub return_mode: ReturnMode,
    /// Product id byte as sent (may disagree with the configured model).
    pub product_id: u8,
    /// Azimuth of block 0, hundredths of a degree.
    pub first_azimuth: u16,
    /// Azimuth of block 11, hundredths of a degree.
    pub last_azimuth: u16,
}

impl PacketRepr {
    /// Parses the header facts of a checked packet.
    pub fn parse<T: AsRef<[u8]>>(p: &Packet<T>) -> Self {
        Self {
            timestamp_us: p.timestamp_us(),
            return_mode: p.return_mode(),
            product_id: p.product_id(),
            first_azimuth: p.azimuth(0),
            last_azimuth: p.azimuth(BLOCKS - 1),
        }
    }
}

/// How a laser's vertical (and horizontal) offset enters the point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum OffsetModel {
    /// Velodyne manuals: the vertical offset is added to z (`z = d sin v + o`).
    ZTranslation,
    /// ROS `velodyne_pointcloud` "advanced" calibration (db.xml / yaml files): the beam starts
    /// at the offsets, `xy = d cos v - o sin v`, `z = d sin v + o cos v`, plus the horizontal
    /// offset across the beam.
    RosAdvanced,
}

/// One laser's calibration, in the ROS calibration-file sense.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LaserCalibration {
    /// Elevation (`vert_correction`), radians, up positive.
    pub elevation: f32,
    /// Azimuth correction (`rot_correction`), radians, subtracted from the firing azimuth.
    pub azimuth: f32,
    /// Vertical offset (`vert_offset_correction`), metres.
    pub vert_offset: f32,
    /// Horizontal offset (`horiz_offset_correction`), metres (only with [`OffsetModel::RosAdvanced`]).
    pub horiz_offset: f32,
    /// Distance correction added to every range (`dist_correction`), metres.
    pub dist_correction: f32,
}

/// Most lasers a calibration holds.
pub const MAX_LASERS: usize = 32;

/// Why a calibration was rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CalibrationError {
    /// Laser count is neither 16 nor 32, or does not fit the model.
    LaserCount,
    /// A value is not finite, or an angle is beyond +-90 deg.
    BadValue,
    /// The distance resolution is not a positive finite number.
    BadResolution,
}

impl core::fmt::Display for CalibrationError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::LaserCount => "velodyne calibration: laser count does not fit the model (16 or 32)",
            Self::BadValue => "velodyne calibration: a correction is not finite or out of range",
            Self::BadResolution => "velodyne calibration: distance resolution must be positive",
        })
    }
}

impl core::error::Error for CalibrationError {}

/// A sensor's calibration: the built-in tables ([`Self::default_for`]) or one the host filled
/// from a ROS velodyne calibration yaml ([`Self::new`] + [`Self::set_laser`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    lasers: [LaserCalibration; MAX_LASERS],
    num_lasers: u8,
    /// Metres per raw distance unit.
    pub distance_resolution: f32,
    /// How offsets enter the points.
    pub offset_model: OffsetModel,
}

const fn deg(d: f32) -> f32 {
    d * (core::f32::consts::PI / 180.0)
}

/// Builds a laser table from (elevation deg, azimuth deg, vertical offset mm) rows.
const fn table<const L: usize>(rows: [(f32, f32, f32); L]) -> [LaserCalibration; MAX_LASERS] {
    let mut out = [LaserCalibration {
        elevation: 0.0,
        azimuth: 0.0,
        vert_offset: 0.0,
        horiz_offset: 0.0,
        dist_correction: 0.0,
    }; MAX_LASERS];
    let mut i = 0;
    while i < L {
        out[i].elevation = deg(rows[i].0);
        out[i].azimuth = deg(rows[i].1);
        out[i].vert_offset = rows[i].2 * 1e-3;
        i += 1;
    }
    out
}

/// VLP-16 (manual 63-9243 rev E, table 9-1): elevation, azimuth correction 0, and the vertical
/// offsets of the laser origins, mm (the manual's values, +-0.05 mm of 41.91 mm x tan(-v)).
pub const VLP16_TABLE: [(f32, f32, f32); 16] = [
    (-15.0, 0.0, 11.2),
    (1.0, 0.0, -0.7),
    (-13.0, 0.0, 9.7),
    (3.0, 0.0, -2.2),
    (-11.0, 0.0, 8.1),
    (5.0, 0.0, -3.7),
    (-9.0, 0.0, 6.6),
    (7.0, 0.0, -5.1),
    (-7.0, 0.0, 5.1),
    (9.0, 0.0, -6.6),
    (-5.0, 0.0, 3.7),
    (11.0, 0.0, -8.1),
    (-3.0, 0.0, 2.2),
    (13.0, 0.0, -9.7),
    (-1.0, 0.0, 0.7),
    (15.0, 0.0, -11.2),
];

/// VLP-32C (manual 63-9325 rev B, table "VLP-32C laser angles"): elevation, azimuth offset, and
/// the vertical offset of the beam origin, mm, derived from the 42.4 mm focal distance as
/// 42.4 x tan(-elevation) (the manual documents no per-laser offsets; `velodyne_decoder` uses
/// the same derivation).
pub const VLP32C_TABLE: [(f32, f32, f32); 32] = [
    (-25.0, -1.4, 19.771),
    (-1.0, 4.2, 0.740),
    (-1.667, -1.4, 1.234),
    (-15.639, 1.4, 11.869),
    (-11.31, -1.4, 8.480),
    (0.0, 1.4, 0.0),
    (-0.667, -4.2, 0.494),
    (-8.843, 1.4, 6.596),
    (-7.254, -1.4, 5.397),
    (0.333, 4.2, -0.246),
    (-0.333, -1.4, 0.246),
    (-6.148, 1.4, 4.567),
    (-5.333, -4.2, 3.958),
    (1.333, 1.4, -0.987),
    (0.667, -4.2, -0.494),
    (-4.0, 1.4, 2.965),
    (-4.667, -1.4, 3.461),
    (1.667, 4.2, -1.234),
    (1.0, -1.4, -0.740),
    (-3.667, 4.2, 2.717),
    (-3.333, -4.2, 2.469),
    (3.333, 1.4, -2.469),
    (2.333, -1.4, -1.727),
    (-2.667, 1.4, 1.975),
    (-3.0, -1.4, 2.222),
    (7.0, 1.4, -5.206),
    (4.667, -1.4, -3.461),
    (-2.333, 4.2, 1.727),
    (-2.0, -4.2, 1.481),
    (15.0, 1.4, -11.361),
    (10.333, -1.4, -7.731),
    (-1.333, 1.4, 0.987),
];

/// HDL-32E (manual 63-9113, and the envelope drawing 86-0106 rev B for the vertical offsets of
/// the laser origins, mm).
pub const HDL32E_TABLE: [(f32, f32, f32); 32] = [
    (-30.67, 0.0, 17.17),
    (-9.33, 0.0, 4.76),
    (-29.33, 0.0, 16.27),
    (-8.0, 0.0, 4.07),
    (-28.0, 0.0, 15.4),
    (-6.67, 0.0, 3.38),
    (-26.67, 0.0, 14.54),
    (-5.33, 0.0, 2.7),
    (-25.33, 0.0, 13.71),
    (-4.0, 0.0, 2.02),
    (-24.0, 0.0, 12.89),
    (-2.67, 0.0, 1.35),
    (-22.67, 0.0, 12.09),
    (-1.33, 0.0, 0.67),
    (-21.33, 0.0, 11.31),
    (0.0, 0.0, 0.0),
    (-20.0, 0.0, 10.54),
    (1.33, 0.0, -0.67),
    (-18.67, 0.0, 9.78),
    (2.67, 0.0, -1.35),
    (-17.33, 0.0, 9.04),
    (4.0, 0.0, -2.02),
    (-16.0, 0.0, 8.3),
    (5.33, 0.0, -2.7),
    (-14.67, 0.0, 7.58),
    (6.67, 0.0, -3.38),
    (-13.33, 0.0, 6.86),
    (8.0, 0.0, -4.07),
    (-12.0, 0.0, 6.15),
    (9.33, 0.0, -4.76),
    (-10.67, 0.0, 5.45),
    (10.67, 0.0, -5.45),
];

impl Calibration {
    /// An all-zero calibration of `num_lasers` lasers; fill it with [`Self::set_laser`].
    pub fn new(
        num_lasers: usize,
        distance_resolution: f32,
        offset_model: OffsetModel,
    ) -> Result<Self, CalibrationError> {
        if num_lasers != 16 && num_lasers != 32 {
            return Err(CalibrationError::LaserCount);
        }
        if !(distance_resolution > 0.0 && distance_resolution.is_finite()) {
            return Err(CalibrationError::BadResolution);
        }
        Ok(Self {
            lasers: [LaserCalibration::default(); MAX_LASERS],
            num_lasers: num_lasers as u8,
            distance_resolution,
            offset_model,
        })
    }

    /// The built-in calibration of a model (tables above; distance resolution 2 mm, 4 mm for
    /// the VLP-32C).
    pub const fn default_for(model: Model) -> Self {
        match model {
            Model::Vlp16 => Self {
                lasers: table(VLP16_TABLE),
                num_lasers: 16,
                distance_resolution: 0.002,
                offset_model: OffsetModel::ZTranslation,
            },
            Model::Vlp32c => Self {
                lasers: table(VLP32C_TABLE),
                num_lasers: 32,
                distance_resolution: 0.004,
                offset_model: OffsetModel::ZTranslation,
            },
            Model::Hdl32e => Self {
                lasers: table(HDL32E_TABLE),
                num_lasers: 32,
                distance_resolution: 0.002,
                offset_model: OffsetModel::ZTranslation,
            },
        }
    }

    /// Sets laser `i` (the laser's index in the packet, the calibration file's `laser_id`).
    pub fn set_laser(&mut self, i: usize, laser: LaserCalibration) -> Result<(), CalibrationError> {
        if i >= self.num_lasers as usize {
            return Err(CalibrationError::LaserCount);
        }
        let half_pi = core::f32::consts::FRAC_PI_2;
        let finite =
            [laser.elevation, laser.azimuth, laser.vert_offset, laser.horiz_offset, laser.dist_correction]
                .iter()
                .all(|v| v.is_finite());
        if !finite || libm::fabsf(laser.elevation) > half_pi || libm::fabsf(laser.azimuth) > half_pi {
            return Err(CalibrationError::BadValue);
        }
        self.lasers[i] = laser;
        Ok(())
    }

    /// Number of lasers.
    pub fn num_lasers(&self) -> usize {
        self.num_lasers as usize
    }

    /// The lasers, in packet order.
    pub fn lasers(&self) -> &[LaserCalibration] {
        &self.lasers[..self.num_lasers as usize]
    }

    /// Range-image row of each laser: lasers sorted by elevation, row 0 the highest (ties keep
    /// packet order).
    pub fn rows(&self) -> [u16; MAX_LASERS] {
        let n = self.num_lasers();
        let mut rows = [0u16; MAX_LASERS];
        for (i, row) in rows.iter_mut().enumerate().take(n) {
            let e = self.lasers[i].elevation;
            let higher = (0..n)
                .filter(|&k| {
                    let ek = self.lasers[k].elevation;
                    ek > e || (ek == e && k < i)
                })
                .count();
            *row = higher as u16;
        }
        rows
    }

    /// The range-image layout of this calibration with `cols` columns: rows by elevation (row 0
    /// highest), column 0 at azimuth 0 (forward), columns clockwise like the sensor spins.
    pub fn layout(&self, cols: usize) -> Result<RangeImageLayout, LayoutError> {
        let mut l = RangeImageLayout::new(self.num_lasers(), cols, true)?;
        let rows = self.rows();
        for (i, laser) in self.lasers().iter().enumerate() {
            l.set_row(rows[i] as usize, laser.elevation, 0.0)?;
        }
        Ok(l)
    }
}

/// sin of k hundredths of a degree, k = 0..=9000, rounded to f32 (a quarter wave; the other
/// quadrants follow by symmetry). 36 KB of read-only data.
static SIN_QUARTER: [f32; 9001] = {
    let mut t = [0.0f32; 9001];
    let mut k = 0;
    while k <= 9000 {
        t[k] = const_sin(k as f64 * (core::f64::consts::PI / 18_000.0)) as f32;
        k += 1;
    }
    t
};

/// Taylor series of sin on [0, pi/2], accurate to f64 rounding (for the const table above).
const fn const_sin(x: f64) -> f64 {
    let x2 = x * x;
    let mut term = x;
    let mut sum = x;
    let mut n = 1;
    while n < 15 {
        term = -term * x2 / ((2 * n) as f64 * (2 * n + 1) as f64);
        sum += term;
        n += 1;
    }
    sum
}

/// (sin, cos) of `a` hundredths of a degree, a < 36000.
#[inline]
fn sin_cos_centideg(a: u32) -> (f32, f32) {
    let q = a / 9000;
    let r = (a % 9000) as usize;
    let (s, c) = (SIN_QUARTER[r], SIN_QUARTER[9000 - r]);
    match q {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    }
}

/// Decoder settings.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Config {
    /// The sensor model; wins over the packet's product-id byte.
    pub model: Model,
    /// Points nearer than this are dropped, metres (after the distance correction).
    pub min_range: f32,
    /// Points farther than this are dropped, metres.
    pub max_range: f32,
    /// Range-image columns per revolution ([`Model::columns_for_rpm`]).
    pub columns: u16,
}

impl Config {
    /// Defaults for a model at 600 rpm: 0.1..200 m (as `velodyne_decoder`).
    pub fn new(model: Model) -> Self {
        Self { model, min_range: 0.1, max_range: 200.0, columns: model.columns_for_rpm(600.0) as u16 }
    }
}

/// Counts of what a [`Decoder`] saw.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DecoderStats {
    /// Packets decoded.
    pub packets: u64,
    /// Packets rejected by [`Packet::check`].
    pub bad_packets: u64,
    /// Packets whose product id disagrees with the configured model (decoded as configured).
    pub model_mismatch: u64,
    /// Points delivered.
    pub points: u64,
    /// Returns dropped by the range limits.
    pub out_of_range: u64,
}

#[derive(Clone, Copy, Debug, Default)]
struct LaserCache {
    cos_v: f32,
    sin_v: f32,
    cos_r: f32,
    sin_r: f32,
    rot: f32,
    vert_offset: f32,
    horiz_offset: f32,
    dist_correction: f32,
    row: u16,
}

/// Decodes data packets of one sensor into points. Holds only fixed-size tables (about 4 KB).
#[derive(Clone, Debug)]
pub struct Decoder {
    config: Config,
    calib: Calibration,
    lasers: [LaserCache; MAX_LASERS],
    /// Firing time of (block, channel) after the packet time, seconds, as f32 (as the ROS
    /// driver computes it: it sets the azimuth interpolation).
    timing_s: [[f32; CHANNELS]; BLOCKS],
    /// The same, nanoseconds, rounded from the exact values.
    timing_ns: [[u32; CHANNELS]; BLOCKS],
    layout: RangeImageLayout,
    warned_mismatch: bool,
    /// What was decoded and dropped.
    pub stats: DecoderStats,
}

impl Decoder {
    /// A decoder with the model's built-in calibration.
    pub fn new(config: Config) -> Result<Self, CalibrationError> {
        Self::with_calibration(config, Calibration::default_for(config.model))
    }

    /// A decoder with a calibration from a file (its laser count must match the model).
    pub fn with_calibration(config: Config, calib: Calibration) -> Result<Self, CalibrationError> {
        if calib.num_lasers() != config.model.lasers() {
            return Err(CalibrationError::LaserCount);
        }
        let rows = calib.rows();
        let mut lasers = [LaserCache::default(); MAX_LASERS];
        for (i, l) in calib.lasers().iter().enumerate() {
            lasers[i] = LaserCache {
                cos_v: libm::cosf(l.elevation),
                sin_v: libm::sinf(l.elevation),
                cos_r: libm::cosf(l.azimuth),
                sin_r: libm::sinf(l.azimuth),
                rot: l.azimuth,
                vert_offset: l.vert_offset,
                horiz_offset: l.horiz_offset,
                dist_correction: l.dist_correction,
                row: rows[i],
            };
        }
        let mut timing_s = [[0.0f32; CHANNELS]; BLOCKS];
        let mut timing_ns = [[0u32; CHANNELS]; BLOCKS];
        for (b, (ts, tn)) in timing_s.iter_mut().zip(timing_ns.iter_mut()).enumerate() {
            for c in 0..CHANNELS {
                let t = config.model.timing_offset_s(b, c);
                ts[c] = t as f32;
                tn[c] = libm::round(t * 1e9) as u32;
            }
        }
        let cols = (config.columns as usize).clamp(8, crate::range_image::MAX_COLS);
        let layout = calib.layout(cols).map_err(|_| CalibrationError::BadValue)?;
        Ok(Self {
            config,
            calib,
            lasers,
            timing_s,
            timing_ns,
            layout,
            warned_mismatch: false,
            stats: DecoderStats::default(),
        })
    }

    /// The settings.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// The calibration in use.
    pub fn calibration(&self) -> &Calibration {
        &self.calib
    }

    /// The range-image layout the points' rows and columns refer to.
    pub fn layout(&self) -> &RangeImageLayout {
        &self.layout
    }

    /// Checks a packet and reads its header; counts bad packets and product-id mismatches.
    pub fn parse<'a>(&mut self, bytes: &'a [u8]) -> Result<(Packet<&'a [u8]>, PacketRepr), Error> {
        let p = match Packet::new_checked(bytes) {
            Ok(p) => p,
            Err(e) => {
                self.stats.bad_packets += 1;
                return Err(e);
            }
        };
        let repr = PacketRepr::parse(&p);
        if repr.product_id != self.config.model.product_id() {
            self.stats.model_mismatch += 1;
            if !self.warned_mismatch {
                self.warned_mismatch = true;
                warn!(
                    "velodyne: packet product id {} disagrees with the configured model (id {}); decoding as configured",
                    repr.product_id,
                    self.config.model.product_id()
                );
            }
        }
        self.stats.packets += 1;
        Ok((p, repr))
    }

    /// Sequence information for scan assembly: the sensor's microsecond clock, which wraps every
    /// hour and advances by one packet period per packet.
    pub fn sequence(&self, repr: &PacketRepr) -> PacketSeq {
        PacketSeq {
            counter: repr.timestamp_us as u64,
            modulus: MICROS_PER_HOUR,
            step: self.config.model.packet_period_ns(repr.return_mode.is_dual()) as f32 * 1e-3,
        }
    }

    /// The packet's metadata for the scan assembler, given its absolute time (ns) as resolved
    /// by the host (see `time_align` in loglio-host).
    pub fn meta(&self, repr: &PacketRepr, packet_time_ns: u64) -> PacketMeta {
        PacketMeta { time_ns: packet_time_ns, seq: self.sequence(repr) }
    }

    /// Emits every point of a checked packet, in packet order (in dual mode per laser: the last
    /// return, then the strongest; one point when both are the same return).
    pub fn points<T: AsRef<[u8]>>(&mut self, p: &Packet<T>, mut emit: impl FnMut(RawPoint)) {
        let dual = p.return_mode().is_dual();
        let res = self.calib.distance_resolution;
        let az_first = p.azimuth(0) as i32;
        let az_last = p.azimuth(BLOCKS - 1) as i32;
        let az_diff = (az_last - az_first).rem_euclid(36_000) as f32;
        let duration =
            self.timing_s[if dual { (BLOCKS - 1) / 2 } else { BLOCKS - 1 }][0] - self.timing_s[0][0];
        let rate = az_diff / duration;
        let n = self.calib.num_lasers();
        let step = if dual { 2 } else { 1 };
        let mut points = 0u64;
        let mut out_of_range = 0u64;
        let mut b = 0;
        while b < BLOCKS {
            let tb = if dual { b / 2 } else { b };
            let t0 = self.timing_s[tb][0];
            let block_az = p.azimuth(b) as f32;
            for j in 0..CHANNELS {
                let (d_a, i_a) = p.measurement(b, j);
                let (d_b, i_b) = if dual { p.measurement(b + 1, j) } else { (0, 0) };
                if d_a == 0 && d_b == 0 {
                    continue;
                }
                let dt = self.timing_s[tb][j] - t0;
                let az = lround_azimuth(block_az + rate * dt);
                let laser = if n == 16 { j % 16 } else { j };
                let t_ns = self.timing_ns[tb][j];
                // (distance, intensity, return index); dual: last (block b) then strongest (b+1).
                let mut emit_one = |dist: u16, inten: u8, ret: u8| match self.point(laser, az, dist, res) {
                    Some(xyz) => {
                        points += 1;
                        let l = &self.lasers[laser];
                        let beam_az = -(az as f64 * (core::f64::consts::PI / 18_000.0) - l.rot as f64);
                        emit(RawPoint {
                            xyz,
                            dt_ns: t_ns,
                            sweep: sweep_of_centideg(az),
                            row: l.row,
                            col: self.layout.column_of(l.row as usize, beam_az),
                            intensity: inten as u16,
                            ret,
                        });
                    }
                    None => out_of_range += 1,
                };
                if !dual {
                    emit_one(d_a, i_a, 0);
                } else if d_a == d_b {
                    emit_one(d_b, i_b, 0);
                } else {
                    if d_a != 0 {
                        emit_one(d_a, i_a, 1);
                    }
                    if d_b != 0 {
                        emit_one(d_b, i_b, 0);
                    }
                }
            }
            b += step;
        }
        self.stats.points += points;
        self.stats.out_of_range += out_of_range;
    }

    /// The point of one return, or `None` outside the range limits.
    #[inline]
    fn point(&self, laser: usize, az: u32, raw: u16, res: f32) -> Option<[f32; 3]> {
        let l = &self.lasers[laser];
        let d = raw as f32 * res + l.dist_correction;
        if !(d >= self.config.min_range && d <= self.config.max_range) {
            return None;
        }
        let (sa, ca) = sin_cos_centideg(az);
        // cos(a - r), sin(a - r)
        let c = ca * l.cos_r + sa * l.sin_r;
        let s = sa * l.cos_r - ca * l.sin_r;
        Some(match self.calib.offset_model {
            OffsetModel::ZTranslation => {
                let xy = d * l.cos_v;
                [xy * c, -xy * s, d * l.sin_v + l.vert_offset]
            }
            OffsetModel::RosAdvanced => {
                let xy = d * l.cos_v - l.vert_offset * l.sin_v;
                let h = l.horiz_offset;
                [xy * c + h * s, -xy * s + h * c, d * l.sin_v + l.vert_offset * l.cos_v]
            }
        })
    }
}

/// `lround(x + 36000) % 36000` in f32, as the ROS driver quantises interpolated azimuths.
#[inline]
fn lround_azimuth(x: f32) -> u32 {
    let v = x + 36_000.0;
    if !(0.0..1.0e7).contains(&v) {
        return 0;
    }
    let i = v as u32;
    let frac = v - i as f32;
    let r = if frac >= 0.5 { i + 1 } else { i };
    r % 36_000
}

/// Sweep angle (fraction of a turn, 2^32 = 360 deg, clockwise from forward) of an azimuth in
/// hundredths of a degree.
#[inline]
pub fn sweep_of_centideg(az: u32) -> u32 {
    (((az as u64) << 32) / 36_000) as u32
}

#[cfg(test)]
mod tests {
    use super::*;
    extern crate std;
    use std::vec::Vec;

    /// A synthetic single-return packet: every block at `az0 + 20 * i`, every channel at
    /// distance `dist` raw units.
    pub(crate) fn packet(model: Model, az0: u16, dist: u16, mode: u8) -> [u8; DATA_PACKET_LEN] {
        let mut b = [0u8; DATA_PACKET_LEN];
        for i in 0..BLOCKS {
            let o = i * 100;
            b[o..o + 2].copy_from_slice(&BLOCK_FLAG.to_le_bytes());
            let az = if mode == 0x39 { az0 + 20 * (i as u16 / 2) } else { az0 + 20 * i as u16 };
            b[o + 2..o + 4].copy_from_slice(&(az % 36000).to_le_bytes());
            for j in 0..CHANNELS {
                let p = o + 4 + 3 * j;
                b[p..p + 2].copy_from_slice(&dist.to_le_bytes());
                b[p + 2] = j as u8;
            }
        }
        b[1200..1204].copy_from_slice(&123_456u32.to_le_bytes());
        b[1204] = mode;
        b[1205] = model.product_id();
        b
    }

    #[test]
    fn sin_table_matches_libm() {
        for a in (0..36_000).step_by(7) {
            let (s, c) = sin_cos_centideg(a);
            let r = a as f64 * core::f64::consts::PI / 18_000.0;
            assert!((s as f64 - libm::sin(r)).abs() < 1e-7, "{a}");
            assert!((c as f64 - libm::cos(r)).abs() < 1e-7, "{a}");
        }
    }

    #[test]
    fn timing_tables_follow_the_manuals() {
        // VLP-16: block 1, channel 17 = third sequence, laser 1: 3 x 55.296 + 2.304 us.
        assert!((Model::Vlp16.timing_offset_s(1, 17) - (3.0 * 55.296e-6 + 2.304e-6)).abs() < 1e-12);
        // VLP-32C: lasers fire in pairs.
        assert_eq!(Model::Vlp32c.timing_offset_s(2, 6), Model::Vlp32c.timing_offset_s(2, 7));
        // HDL-32E: 1.152 us per laser, 46.08 us per block.
        assert!((Model::Hdl32e.timing_offset_s(11, 31) - (11.0 * 46.08e-6 + 31.0 * 1.152e-6)).abs() < 1e-12);
        assert_eq!(Model::Vlp16.packet_period_ns(false), 1_327_104);
        assert_eq!(Model::Vlp32c.packet_period_ns(false), 663_552);
        assert_eq!(Model::Hdl32e.packet_period_ns(false), 552_960);
        assert_eq!(Model::Vlp16.packet_period_ns(true), 663_552);
        assert_eq!(Model::Vlp16.columns_for_rpm(600.0), 1808);
    }

    #[test]
    fn rejects_wrong_sizes_and_garbage() {
        let good = packet(Model::Vlp16, 100, 500, 0x37);
        assert!(Packet::new_checked(&good[..]).is_ok());
        assert_eq!(Packet::new_checked(&good[..1205]).unwrap_err(), Error::Truncated);
        assert_eq!(Packet::new_checked(&[][..]).unwrap_err(), Error::Truncated);
        let mut long = [0u8; 1300];
        long[..DATA_PACKET_LEN].copy_from_slice(&good);
        assert_eq!(Packet::new_checked(&long[..]).unwrap_err(), Error::TooLong);
        let mut bad = good;
        bad[500] = 0x12; // inside block 5's flag
        assert_eq!(Packet::new_checked(&bad[..]).unwrap_err(), Error::BadBlockFlag);
        let mut bad = good;
        bad[302..304].copy_from_slice(&36_001u16.to_le_bytes());
        assert_eq!(Packet::new_checked(&bad[..]).unwrap_err(), Error::BadAzimuth);
        // Exactly 360 deg happens on real sensors: accepted as 0.
        let mut edge = good;
        edge[302..304].copy_from_slice(&36_000u16.to_le_bytes());
        assert!(Packet::new_checked(&edge[..]).is_ok());
        let garbage = [0xA5u8; DATA_PACKET_LEN];
        assert_eq!(Packet::new_checked(&garbage[..]).unwrap_err(), Error::BadBlockFlag);
        let mut dec = Decoder::new(Config::new(Model::Vlp16)).unwrap();
        assert!(dec.parse(&garbage).is_err());
        assert!(dec.parse(&good).is_ok());
        assert_eq!(dec.stats.bad_packets, 1);
        assert_eq!(dec.stats.packets, 1);
    }

    #[test]
    fn geometry_of_a_known_return() {
        // VLP-16 laser 0 (-15 deg, offset 11.2 mm) at 10 m, block azimuth 90 deg.
        let mut dec = Decoder::new(Config::new(Model::Vlp16)).unwrap();
        let bytes = packet(Model::Vlp16, 9000, 5000, 0x37);
        let (p, _) = dec.parse(&bytes).unwrap();
        let mut pts = Vec::new();
        dec.points(&p, |q| pts.push(q));
        assert_eq!(pts.len(), 12 * 32);
        let q = pts[0];
        let v = -15f64.to_radians();
        // Azimuth 90 deg clockwise = to the right: -y.
        assert!((q.xyz[0] as f64).abs() < 1e-4);
        assert!((q.xyz[1] as f64 + 10.0 * v.cos()).abs() < 1e-4);
        assert!((q.xyz[2] as f64 - (10.0 * v.sin() + 0.0112)).abs() < 1e-4);
        assert_eq!(q.row, 15, "laser 0 is the lowest of 16");
        assert_eq!(q.dt_ns, 0);
        // Second sequence of block 0: 55.296 us later.
        assert_eq!(pts[16].dt_ns, 55_296);
        assert_eq!(pts[16].row, 15);
        assert_eq!(pts[1].row, 7, "laser 1 is +1 deg: 8th from the top");
        // Column of forward-right 90 deg with 1808 clockwise columns: 452.
        assert_eq!(q.col, 452);
    }

    #[test]
    fn dual_returns_keep_distinct_and_merge_equal() {
        let mut dec = Decoder::new(Config::new(Model::Vlp16)).unwrap();
        let mut bytes = packet(Model::Vlp16, 0, 1000, 0x39);
        // Block 0 (last returns): channel 0 farther; channel 1 no last return.
        bytes[4..6].copy_from_slice(&2000u16.to_le_bytes());
        bytes[7..9].copy_from_slice(&0u16.to_le_bytes());
        let (p, _) = dec.parse(&bytes).unwrap();
        let mut pts = Vec::new();
        dec.points(&p, |q| pts.push(q));
        // 6 pairs x 32 channels, one extra point for channel 0 of pair 0.
        assert_eq!(pts.len(), 6 * 32 + 1);
        assert_eq!(pts[0].ret, 1, "last return first");
        assert!((pts[0].xyz[0] - 4.0 * libm::cosf(deg(-15.0))).abs() < 1e-4);
        assert_eq!(pts[1].ret, 0);
        assert!((pts[1].xyz[0] - 2.0 * libm::cosf(deg(-15.0))).abs() < 1e-4);
        assert_eq!(pts[2].ret, 0, "strongest only");
        assert_eq!(pts[3].ret, 0, "both the same: one point");
    }

    #[test]
    fn configured_model_wins_over_product_id() {
        let mut dec = Decoder::new(Config::new(Model::Vlp16)).unwrap();
        let mut bytes = packet(Model::Vlp16, 0, 1000, 0x37);
        bytes[1205] = 0x21;
        for _ in 0..3 {
            let (p, repr) = dec.parse(&bytes).unwrap();
            assert_eq!(repr.product_id, 0x21);
            let mut n = 0;
            dec.points(&p, |q| {
                assert!(q.row < 16);
                n += 1
            });
            assert_eq!(n, 384);
        }
        assert_eq!(dec.stats.model_mismatch, 3);
    }

    #[test]
    fn range_limits_are_counted() {
        let mut cfg = Config::new(Model::Hdl32e);
        cfg.max_range = 1.0;
        let mut dec = Decoder::new(cfg).unwrap();
        let bytes = packet(Model::Hdl32e, 0, 1000, 0x37); // 2 m
        let (p, _) = dec.parse(&bytes).unwrap();
        let mut n = 0;
        dec.points(&p, |_| n += 1);
        assert_eq!(n, 0);
        assert_eq!(dec.stats.out_of_range, 384);
    }

    #[test]
    fn calibration_validation() {
        assert_eq!(
            Calibration::new(12, 0.002, OffsetModel::RosAdvanced).unwrap_err(),
            CalibrationError::LaserCount
        );
        assert_eq!(
            Calibration::new(16, 0.0, OffsetModel::RosAdvanced).unwrap_err(),
            CalibrationError::BadResolution
        );
        let mut c = Calibration::new(16, 0.002, OffsetModel::RosAdvanced).unwrap();
        let bad = LaserCalibration { elevation: f32::NAN, ..Default::default() };
        assert_eq!(c.set_laser(0, bad), Err(CalibrationError::BadValue));
        assert_eq!(c.set_laser(16, LaserCalibration::default()), Err(CalibrationError::LaserCount));
        assert_eq!(
            Decoder::with_calibration(Config::new(Model::Vlp32c), c).unwrap_err(),
            CalibrationError::LaserCount
        );
        let rows = Calibration::default_for(Model::Vlp32c).rows();
        assert_eq!(rows[29], 0, "+15 deg is the top row");
        assert_eq!(rows[0], 31, "-25 deg is the bottom row");
    }
}
