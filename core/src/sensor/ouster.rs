//! Ouster OS0/OS1/OS2 lidar and IMU packets (UDP ports 7502 and 7503).
//!
//! Lidar packets hold `columns_per_packet` measurement columns (16 in every firmware so far).
//! Layouts (little-endian), from the Ouster sensor documentation ("Lidar Data Format"):
//!
//! ```text
//! LEGACY:   no packet header; column = ts u64 | measurement_id u16 | frame_id u16 | encoder u32
//!           | H x 12-byte pixels (range: low 20 bits of a u32; reflectivity u16; signal u16;
//!           near-ir u16; unused u16) | status u32 (0xFFFFFFFF = valid)
//! v2 profiles: 32-byte packet header (packet type u16, frame id u16, init id u24, serial u40, ...)
//!           | columns: ts u64 | measurement_id u16 | status u16 (bit 0 = valid) | H pixels
//!           | 32-byte packet footer
//!   RNG19_RFL8_SIG16_NIR16        12-byte pixels: range = low 19 bits of a u32 (mm); reflectivity u8 at +4
//!   RNG19_RFL8_SIG16_NIR16_DUAL   16-byte pixels: range 19 bits, reflectivity u8 at +3; range2 19 bits
//!                                  of the u32 at +4, reflectivity2 u8 at +7
//!   RNG15_RFL8_NIR8               4-byte pixels: range = low 15 bits x 8 mm; reflectivity u8 at +2
//!   FUSA_RNG15_RFL8_NIR8_DUAL     8-byte pixels: as RNG15 twice (range2 at +4); the packet header
//!                                  holds the frame id as a u32 at bytes 4..8
//! ```
//!
//! Geometry (Ouster's `make_xyz_lut`): pixel (beam `u`, measurement id `m`) with range `r` mm is
//! `T_lidar_to_sensor * (d * (r - n) + o)` with encoder angle `E = 2 pi (1 - m / W)`, beam
//! azimuth `A = -azimuth_u`, altitude `P`:
//! `d = (cos(E+A) cos P, sin(E+A) cos P, sin P)`, `n` the beam-origin distance
//! `|(bx, bz)|` of `beam_to_lidar_transform` (`lidar_origin_to_beam_origin_mm` in older
//! metadata), `o = (bx cos E, bx sin E, bz)`. Points come out in the sensor frame, metres.
//!
//! Destaggering: column `(m + pixel_shift_by_row[u]) mod W` of the range image holds pixel
//! `(u, m)`; that is each point's `col`, and [`Decoder::layout`] gives every row the azimuth of
//! its column 0 so that `layout.direction(row, col)` is the beam's direction.

use crate::imu::ImuSample;
use crate::range_image::{LayoutError, RangeImageLayout};
use crate::scan_assembly::{PacketMeta, PacketSeq, RawPoint};

/// Most beams (pixels per column).
pub const MAX_BEAMS: usize = 128;
/// Most columns per frame.
pub const MAX_COLUMNS: usize = 2048;
/// Length of a legacy IMU packet.
pub const IMU_PACKET_LEN: usize = 48;
/// Standard gravity, m/s^2 per g (the IMU reports g).
pub const STANDARD_GRAVITY: f32 = 9.80665;

/// Lidar UDP profiles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Profile {
    /// Firmware 1.x/2.x default: 12-byte pixels, no packet header.
    Legacy,
    /// `RNG19_RFL8_SIG16_NIR16`: single return, 12-byte pixels.
    Single,
    /// `RNG19_RFL8_SIG16_NIR16_DUAL`: two returns, 16-byte pixels.
    Dual,
    /// `RNG15_RFL8_NIR8`: low bandwidth, 4-byte pixels, 8 mm range steps.
    LowBandwidth,
    /// `FUSA_RNG15_RFL8_NIR8_DUAL`: two low-bandwidth returns, 8-byte pixels, u32 frame id.
    FusaDualLowBandwidth,
}

impl Profile {
    /// The profile of a metadata name (`udp_profile_lidar`).
    pub fn from_name(name: &str) -> Option<Self> {
        Some(match name {
            "LEGACY" => Self::Legacy,
            "RNG19_RFL8_SIG16_NIR16" => Self::Single,
            "RNG19_RFL8_SIG16_NIR16_DUAL" => Self::Dual,
            "RNG15_RFL8_NIR8" => Self::LowBandwidth,
            "FUSA_RNG15_RFL8_NIR8_DUAL" => Self::FusaDualLowBandwidth,
            _ => return None,
        })
    }

    /// Bytes per pixel.
    pub const fn pixel_bytes(self) -> usize {
        match self {
            Self::Legacy | Self::Single => 12,
            Self::Dual => 16,
            Self::LowBandwidth => 4,
            Self::FusaDualLowBandwidth => 8,
        }
    }

    /// Whether pixels carry a second return.
    pub const fn is_dual(self) -> bool {
        matches!(self, Self::Dual | Self::FusaDualLowBandwidth)
    }

    const fn packet_header(self) -> usize {
        if matches!(self, Self::Legacy) { 0 } else { 32 }
    }

    const fn column_header(self) -> usize {
        if matches!(self, Self::Legacy) { 16 } else { 12 }
    }

    const fn column_footer(self) -> usize {
        if matches!(self, Self::Legacy) { 4 } else { 0 }
    }

    /// Bytes of one column with `h` pixels.
    pub const fn column_bytes(self, h: usize) -> usize {
        self.column_header() + h * self.pixel_bytes() + self.column_footer()
    }

    /// Bytes of a lidar packet.
    pub const fn packet_bytes(self, h: usize, columns_per_packet: usize) -> usize {
        2 * self.packet_header() + columns_per_packet * self.column_bytes(h)
    }

    /// Frame ids wrap modulo this.
    pub const fn frame_id_modulus(self) -> u64 {
        if matches!(self, Self::FusaDualLowBandwidth) { 1 << 32 } else { 1 << 16 }
    }
}

/// Why intrinsics were rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum IntrinsicsError {
    /// Pixels per column not in 1..=128, or the angle arrays do not match it.
    Beams,
    /// Columns per frame not in 8..=2048, or columns per packet not in 1..=columns per frame.
    Columns,
    /// A value is not finite (angle, shift, transform).
    NotFinite,
    /// The packet would exceed 65535 bytes.
    PacketTooLarge,
}

impl core::fmt::Display for IntrinsicsError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Beams => "ouster intrinsics: pixels per column must be 1..=128 and match the beam angles",
            Self::Columns => {
                "ouster intrinsics: columns per frame must be 8..=2048 and columns per packet fit in it"
            }
            Self::NotFinite => "ouster intrinsics: a beam angle, shift or transform is not finite",
            Self::PacketTooLarge => "ouster intrinsics: lidar packet would exceed 65535 bytes",
        })
    }
}

impl core::error::Error for IntrinsicsError {}

/// A sensor's intrinsics, as the host reads them from the metadata JSON. Fixed-size arrays, no
/// allocation; about 3 KB.
#[derive(Clone, Debug, PartialEq)]
pub struct OusterIntrinsics {
    /// Lidar UDP profile.
    pub profile: Profile,
    /// Beams (pixels per column).
    pub pixels_per_column: u16,
    /// Columns per frame (512, 1024, 2048).
    pub columns_per_frame: u16,
    /// Columns per packet (16).
    pub columns_per_packet: u16,
    /// Frames per second (10 or 20).
    pub frequency_hz: u16,
    /// Beam altitude angles, degrees, per beam (packet order).
    pub beam_altitude_deg: [f32; MAX_BEAMS],
    /// Beam azimuth offsets, degrees, per beam.
    pub beam_azimuth_deg: [f32; MAX_BEAMS],
    /// Destaggering shift per beam, columns.
    pub pixel_shift_by_row: [i16; MAX_BEAMS],
    /// Beam origin relative to the lidar origin, mm: the x and z of
    /// `beam_to_lidar_transform` (older metadata: `lidar_origin_to_beam_origin_mm`, z = 0).
    pub beam_origin_mm: [f32; 2],
    /// `lidar_to_sensor_transform`, 4x4 row-major, translation in mm.
    pub lidar_to_sensor: [f32; 16],
    /// `imu_to_sensor_transform`, 4x4 row-major, translation in mm.
    pub imu_to_sensor: [f32; 16],
}

/// The default `lidar_to_sensor_transform` (OS1: 180 deg about z, 36.18 mm up), which Ouster's
/// SDK assumes when the metadata has none.
pub const DEFAULT_LIDAR_TO_SENSOR: [f32; 16] =
    [-1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 36.18, 0.0, 0.0, 0.0, 1.0];
/// The default `imu_to_sensor_transform`.
pub const DEFAULT_IMU_TO_SENSOR: [f32; 16] =
    [1.0, 0.0, 0.0, 6.253, 0.0, 1.0, 0.0, -11.775, 0.0, 0.0, 1.0, 7.645, 0.0, 0.0, 0.0, 1.0];
/// The default beam-origin distance (first-generation OS1), mm.
pub const DEFAULT_BEAM_ORIGIN_MM: f32 = 12.163;

impl OusterIntrinsics {
    /// Intrinsics for `profile`, `beams` x `columns`, at `frequency_hz`, with zero angles and
    /// shifts and the SDK's default transforms; fill the arrays, then [`Self::validate`].
    pub const fn new(profile: Profile, beams: u16, columns: u16, frequency_hz: u16) -> Self {
        Self {
            profile,
            pixels_per_column: beams,
            columns_per_frame: columns,
            columns_per_packet: 16,
            frequency_hz,
            beam_altitude_deg: [0.0; MAX_BEAMS],
            beam_azimuth_deg: [0.0; MAX_BEAMS],
            pixel_shift_by_row: [0; MAX_BEAMS],
            beam_origin_mm: [DEFAULT_BEAM_ORIGIN_MM, 0.0],
            lidar_to_sensor: DEFAULT_LIDAR_TO_SENSOR,
            imu_to_sensor: DEFAULT_IMU_TO_SENSOR,
        }
    }

    /// Checks sizes and values so that no decoder accessor can fail.
    pub fn validate(&self) -> Result<(), IntrinsicsError> {
        let h = self.pixels_per_column as usize;
        let w = self.columns_per_frame as usize;
        let cpp = self.columns_per_packet as usize;
        if h == 0 || h > MAX_BEAMS {
            return Err(IntrinsicsError::Beams);
        }
        if !(8..=MAX_COLUMNS).contains(&w) || cpp == 0 || cpp > w {
            return Err(IntrinsicsError::Columns);
        }
        if self.profile.packet_bytes(h, cpp) > 65_535 {
            return Err(IntrinsicsError::PacketTooLarge);
        }
        let finite =
            self.beam_altitude_deg[..h].iter().chain(&self.beam_azimuth_deg[..h]).all(|v| v.is_finite())
                && self
                    .beam_origin_mm
                    .iter()
                    .chain(&self.lidar_to_sensor)
                    .chain(&self.imu_to_sensor)
                    .all(|v| v.is_finite())
                && self.pixel_shift_by_row[..h].iter().all(|s| (s.unsigned_abs() as usize) < 4 * MAX_COLUMNS);
        if !finite || self.frequency_hz == 0 {
            return Err(IntrinsicsError::NotFinite);
        }
        Ok(())
    }

    /// Bytes of a lidar packet.
    pub fn lidar_packet_bytes(&self) -> usize {
        self.profile.packet_bytes(self.pixels_per_column as usize, self.columns_per_packet as usize)
    }

    /// Nanoseconds between two columns.
    pub fn column_period_ns(&self) -> f64 {
        1e9 / (self.frequency_hz as f64 * self.columns_per_frame as f64)
    }
}

/// Why a lidar or IMU packet was rejected (the whole packet; counted by the decoder).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Error {
    /// Shorter than the profile's packet size.
    Truncated,
    /// Longer than the profile's packet size.
    TooLong,
    /// A column's measurement id is not below the columns per frame.
    BadMeasurementId,
}

impl core::fmt::Display for Error {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Truncated => "ouster packet shorter than its profile's size",
            Self::TooLong => "ouster packet longer than its profile's size",
            Self::BadMeasurementId => "ouster column measurement id beyond the columns per frame",
        })
    }
}

impl core::error::Error for Error {}

/// A zero-copy view of a lidar packet of a known format whose length and measurement ids have
/// been checked, so no accessor can panic.
#[derive(Debug, Clone, Copy)]
pub struct LidarPacket<T: AsRef<[u8]>> {
    buffer: T,
    profile: Profile,
    h: usize,
    cpp: usize,
}

impl<T: AsRef<[u8]>> LidarPacket<T> {
    /// Wraps a buffer after checking its length against the intrinsics and every column's
    /// measurement id.
    pub fn new_checked(buffer: T, intr: &OusterIntrinsics) -> Result<Self, Error> {
        let p = Self {
            buffer,
            profile: intr.profile,
            h: intr.pixels_per_column as usize,
            cpp: intr.columns_per_packet as usize,
        };
        let want = p.profile.packet_bytes(p.h, p.cpp);
        let len = p.buffer.as_ref().len();
        if len < want {
            return Err(Error::Truncated);
        }
        if len > want {
            return Err(Error::TooLong);
        }
        for c in 0..p.cpp {
            if p.measurement_id(c) as usize >= intr.columns_per_frame as usize {
                return Err(Error::BadMeasurementId);
            }
        }
        Ok(p)
    }

    fn bytes(&self) -> &[u8] {
        self.buffer.as_ref()
    }

    fn u16_at(&self, at: usize) -> u16 {
        let b = self.bytes();
        u16::from_le_bytes([b[at], b[at + 1]])
    }

    fn u32_at(&self, at: usize) -> u32 {
        let b = self.bytes();
        u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
    }

    fn column_at(&self, c: usize) -> usize {
        self.profile.packet_header() + c * self.profile.column_bytes(self.h)
    }

    /// Columns in the packet.
    pub fn columns(&self) -> usize {
        self.cpp
    }

    /// Frame id (legacy: from the first column).
    pub fn frame_id(&self) -> u32 {
        match self.profile {
            Profile::Legacy => self.u16_at(10) as u32,
            Profile::FusaDualLowBandwidth => self.u32_at(4),
            _ => self.u16_at(2) as u32,
        }
    }

    /// Column `c`'s timestamp, ns.
    pub fn timestamp(&self, c: usize) -> u64 {
        let at = self.column_at(c);
        let b = self.bytes();
        let mut w = [0u8; 8];
        w.copy_from_slice(&b[at..at + 8]);
        u64::from_le_bytes(w)
    }

    /// Column `c`'s measurement id (its index in the frame).
    pub fn measurement_id(&self, c: usize) -> u16 {
        self.u16_at(self.column_at(c) + 8)
    }

    /// Whether column `c` holds valid data.
    pub fn column_valid(&self, c: usize) -> bool {
        let at = self.column_at(c);
        match self.profile {
            Profile::Legacy => self.u32_at(at + self.profile.column_bytes(self.h) - 4) == 0xFFFF_FFFF,
            _ => self.u16_at(at + 10) & 1 == 1,
        }
    }

    /// (range mm, reflectivity) of the first return and, for dual profiles, of the second.
    pub fn pixel(&self, c: usize, beam: usize) -> ([u32; 2], [u16; 2]) {
        let at = self.column_at(c) + self.profile.column_header() + beam * self.profile.pixel_bytes();
        let b = self.bytes();
        match self.profile {
            Profile::Legacy => ([self.u32_at(at) & 0xF_FFFF, 0], [self.u16_at(at + 4), 0]),
            Profile::Single => ([self.u32_at(at) & 0x7_FFFF, 0], [b[at + 4] as u16, 0]),
            Profile::Dual => (
                [self.u32_at(at) & 0x7_FFFF, self.u32_at(at + 4) & 0x7_FFFF],
                [b[at + 3] as u16, b[at + 7] as u16],
            ),
            Profile::LowBandwidth => ([(self.u16_at(at) as u32 & 0x7FFF) << 3, 0], [b[at + 2] as u16, 0]),
            Profile::FusaDualLowBandwidth => (
                [(self.u16_at(at) as u32 & 0x7FFF) << 3, (self.u16_at(at + 4) as u32 & 0x7FFF) << 3],
                [b[at + 2] as u16, b[at + 6] as u16],
            ),
        }
    }
}

/// Header facts of a lidar packet.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LidarRepr {
    /// Frame id.
    pub frame_id: u32,
    /// Measurement id of the first column.
    pub first_measurement_id: u16,
    /// Timestamp of the first valid column, ns (0 if none is valid).
    pub timestamp_ns: u64,
    /// Valid columns.
    pub valid_columns: u16,
}

impl LidarRepr {
    /// Parses the header facts of a checked packet.
    pub fn parse<T: AsRef<[u8]>>(p: &LidarPacket<T>) -> Self {
        let mut ts = 0;
        let mut valid = 0u16;
        for c in 0..p.columns() {
            if p.column_valid(c) {
                if valid == 0 {
                    ts = p.timestamp(c);
                }
                valid += 1;
            }
        }
        Self {
            frame_id: p.frame_id(),
            first_measurement_id: p.measurement_id(0),
            timestamp_ns: ts,
            valid_columns: valid,
        }
    }
}

/// Counts of what a [`Decoder`] saw.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DecoderStats {
    /// Lidar packets decoded.
    pub packets: u64,
    /// Lidar packets rejected.
    pub bad_packets: u64,
    /// Columns skipped because their status says invalid.
    pub invalid_columns: u64,
    /// Columns whose timestamp runs backwards within a packet (their points get offset 0).
    pub bad_timestamps: u64,
    /// Points delivered.
    pub points: u64,
    /// IMU packets decoded.
    pub imu_packets: u64,
    /// IMU packets rejected.
    pub bad_imu_packets: u64,
}

#[derive(Clone, Copy, Debug, Default)]
struct Beam {
    cos_p: f32,
    sin_p: f32,
    cos_a: f32,
    sin_a: f32,
    shift: i32,
    row: u16,
    /// Sensor-frame direction = `ce * dir_c + se * dir_s + dir_0` (m per mm of range), with
    /// (ce, se) the encoder angle's cosine and sine: the rotation folded in once.
    dir_c: [f32; 3],
    dir_s: [f32; 3],
    dir_0: [f32; 3],
}

/// Decodes lidar packets of one sensor. About 21 KB of fixed tables.
#[derive(Clone, Debug)]
pub struct Decoder {
    intr: OusterIntrinsics,
    beams: [Beam; MAX_BEAMS],
    /// cos, sin of the encoder angle of each measurement id.
    encoder: [[f32; 2]; MAX_COLUMNS],
    rot: [[f32; 3]; 3],
    beam_dist_mm: f32,
    /// Sensor-frame beam-origin offset = `ce * off_c + se * off_s + off_0`, metres.
    off_c: [f32; 3],
    off_s: [f32; 3],
    off_0: [f32; 3],
    yaw_sweep: u32,
    layout: RangeImageLayout,
    /// What was decoded and dropped.
    pub stats: DecoderStats,
}

impl Decoder {
    /// Builds the decoder's tables from validated intrinsics.
    pub fn new(intr: &OusterIntrinsics) -> Result<Self, IntrinsicsError> {
        intr.validate()?;
        let h = intr.pixels_per_column as usize;
        let w = intr.columns_per_frame as usize;
        let d2r = core::f64::consts::PI / 180.0;
        let t = &intr.lidar_to_sensor;
        let r64 = |i: usize, j: usize| t[4 * i + j] as f64;
        // R * v for a lidar-frame vector, scaled mm -> m.
        let rot_m = |v: [f64; 3]| -> [f32; 3] {
            core::array::from_fn(|i| ((r64(i, 0) * v[0] + r64(i, 1) * v[1] + r64(i, 2) * v[2]) * 1e-3) as f32)
        };
        // Rows: beams by altitude, highest first (ties keep beam order).
        let mut beams = [Beam::default(); MAX_BEAMS];
        for (u, beam) in beams.iter_mut().enumerate().take(h) {
            let alt = intr.beam_altitude_deg[u] as f64 * d2r;
            let az = -(intr.beam_azimuth_deg[u] as f64) * d2r;
            let higher = (0..h)
                .filter(|&k| {
                    let ak = intr.beam_altitude_deg[k];
                    ak > intr.beam_altitude_deg[u] || (ak == intr.beam_altitude_deg[u] && k < u)
                })
                .count();
            let (cp, sp, ca, sa) = (libm::cos(alt), libm::sin(alt), libm::cos(az), libm::sin(az));
            // d = (cos(E+A) cos P, sin(E+A) cos P, sin P)
            //   = cos E (cos A cos P, sin A cos P, 0) + sin E (-sin A cos P, cos A cos P, 0) + (0, 0, sin P)
            *beam = Beam {
                cos_p: cp as f32,
                sin_p: sp as f32,
                cos_a: ca as f32,
                sin_a: sa as f32,
                shift: (intr.pixel_shift_by_row[u] as i32).rem_euclid(w as i32),
                row: higher as u16,
                dir_c: rot_m([ca * cp, sa * cp, 0.0]),
                dir_s: rot_m([-sa * cp, ca * cp, 0.0]),
                dir_0: rot_m([0.0, 0.0, sp]),
            };
        }
        let mut encoder = [[0.0f32; 2]; MAX_COLUMNS];
        for (m, e) in encoder.iter_mut().enumerate().take(w) {
            let ang = core::f64::consts::TAU * (1.0 - m as f64 / w as f64);
            *e = [libm::cos(ang) as f32, libm::sin(ang) as f32];
        }
        let rot = [[t[0], t[1], t[2]], [t[4], t[5], t[6]], [t[8], t[9], t[10]]];
        let [bx, bz] = intr.beam_origin_mm;
        let beam_dist_mm = if bz != 0.0 { libm::sqrtf(bx * bx + bz * bz) } else { bx };
        // Offset o = (bx cos E, bx sin E, bz) in the lidar frame, then R o + t.
        let (bx64, bz64) = (bx as f64, bz as f64);
        let off_c = rot_m([bx64, 0.0, 0.0]);
        let off_s = rot_m([0.0, bx64, 0.0]);
        let oz = rot_m([0.0, 0.0, bz64]);
        let off_0: [f32; 3] = core::array::from_fn(|i| oz[i] + (t[4 * i + 3] as f64 * 1e-3) as f32);
        let yaw = libm::atan2(rot[1][0] as f64, rot[0][0] as f64);
        let yaw_turns = yaw / core::f64::consts::TAU;
        let yaw_sweep =
            (libm::round((yaw_turns - libm::floor(yaw_turns)) * 4_294_967_296.0) as u64 & 0xFFFF_FFFF) as u32;
        let mut dec = Self {
            intr: intr.clone(),
            beams,
            encoder,
            rot,
            beam_dist_mm,
            off_c,
            off_s,
            off_0,
            yaw_sweep,
            layout: RangeImageLayout::empty(),
            stats: DecoderStats::default(),
        };
        dec.layout = dec.build_layout().map_err(|_| IntrinsicsError::NotFinite)?;
        Ok(dec)
    }

    /// The intrinsics in use.
    pub fn intrinsics(&self) -> &OusterIntrinsics {
        &self.intr
    }

    /// The range-image layout of the points' rows and (destaggered) columns.
    pub fn layout(&self) -> &RangeImageLayout {
        &self.layout
    }

    /// Direction of pixel (beam, measurement id) in the sensor frame (unit vector).
    pub fn beam_direction(&self, beam: usize, mid: usize) -> [f32; 3] {
        let b = &self.beams[beam];
        let [ce, se] = self.encoder[mid];
        let c = ce * b.cos_a - se * b.sin_a;
        let s = se * b.cos_a + ce * b.sin_a;
        let d = [c * b.cos_p, s * b.cos_p, b.sin_p];
        self.rotate(d)
    }

    fn rotate(&self, v: [f32; 3]) -> [f32; 3] {
        let r = &self.rot;
        [
            r[0][0] * v[0] + r[0][1] * v[1] + r[0][2] * v[2],
            r[1][0] * v[0] + r[1][1] * v[1] + r[1][2] * v[2],
            r[2][0] * v[0] + r[2][1] * v[1] + r[2][2] * v[2],
        ]
    }

    fn build_layout(&self) -> Result<RangeImageLayout, LayoutError> {
        let h = self.intr.pixels_per_column as usize;
        let w = self.intr.columns_per_frame as usize;
        let mut l = RangeImageLayout::new(h, w, true)?;
        for u in 0..h {
            // Destaggered column 0 of beam u holds measurement id (-shift) mod W.
            let m0 = (-self.beams[u].shift).rem_euclid(w as i32) as usize;
            let d = self.beam_direction(u, m0);
            let el = libm::atan2f(d[2], libm::sqrtf(d[0] * d[0] + d[1] * d[1]));
            let az = libm::atan2f(d[1], d[0]);
            l.set_row(self.beams[u].row as usize, el, az)?;
        }
        Ok(l)
    }

    /// Checks a lidar packet and reads its header (counts rejects).
    pub fn parse<'a>(&mut self, bytes: &'a [u8]) -> Result<(LidarPacket<&'a [u8]>, LidarRepr), Error> {
        match LidarPacket::new_checked(bytes, &self.intr) {
            Ok(p) => {
                self.stats.packets += 1;
                let r = LidarRepr::parse(&p);
                Ok((p, r))
            }
            Err(e) => {
                self.stats.bad_packets += 1;
                Err(e)
            }
        }
    }

    /// Sequence information for scan assembly: frame id x W + first measurement id.
    pub fn sequence(&self, repr: &LidarRepr) -> PacketSeq {
        let w = self.intr.columns_per_frame as u64;
        PacketSeq {
            counter: repr.frame_id as u64 * w + repr.first_measurement_id as u64,
            modulus: self.intr.profile.frame_id_modulus() * w,
            step: self.intr.columns_per_packet as f32,
        }
    }

    /// The packet's metadata for the scan assembler, given the absolute time (ns) of its first
    /// valid column as resolved by the host.
    pub fn meta(&self, repr: &LidarRepr, packet_time_ns: u64) -> PacketMeta {
        PacketMeta { time_ns: packet_time_ns, seq: self.sequence(repr) }
    }

    /// Sweep angle of a measurement id (clockwise from the sensor's forward axis).
    pub fn sweep_of(&self, mid: usize) -> u32 {
        let w = self.intr.columns_per_frame as u64;
        ((((mid as u64) << 32) / w) as u32).wrapping_sub(self.yaw_sweep)
    }

    /// Emits every return of the valid columns of a checked packet, column by column, beam by
    /// beam (first return, then the second for dual profiles). Times are relative to the
    /// first valid column ([`LidarRepr::timestamp_ns`]).
    pub fn points<T: AsRef<[u8]>>(&mut self, p: &LidarPacket<T>, mut emit: impl FnMut(RawPoint)) {
        let h = self.intr.pixels_per_column as usize;
        let w = self.intr.columns_per_frame as i32;
        let dual = self.intr.profile.is_dual();
        let mut t_ref: Option<u64> = None;
        let mut last_ts = 0u64;
        let mut points = 0u64;
        for c in 0..p.columns() {
            if !p.column_valid(c) {
                self.stats.invalid_columns += 1;
                continue;
            }
            let ts = p.timestamp(c);
            let base = *t_ref.get_or_insert(ts);
            let dt = if ts >= base && ts >= last_ts {
                (ts - base).min(u32::MAX as u64) as u32
            } else {
                self.stats.bad_timestamps += 1;
                0
            };
            last_ts = last_ts.max(ts);
            let mid = p.measurement_id(c) as usize;
            let sweep = self.sweep_of(mid);
            let [ce, se] = self.encoder[mid];
            let off: [f32; 3] =
                core::array::from_fn(|i| ce * self.off_c[i] + se * self.off_s[i] + self.off_0[i]);
            let n = self.beam_dist_mm;
            for u in 0..h {
                let (ranges, refl) = p.pixel(c, u);
                if ranges == [0, 0] {
                    continue;
                }
                let b = &self.beams[u];
                // `shift` is kept in 0..W, so one fold suffices.
                let mut col = mid as i32 + b.shift;
                if col >= w {
                    col -= w;
                }
                let col = col as u16;
                let d: [f32; 3] = core::array::from_fn(|i| ce * b.dir_c[i] + se * b.dir_s[i] + b.dir_0[i]);
                for (k, &r) in ranges.iter().enumerate().take(if dual { 2 } else { 1 }) {
                    if r == 0 {
                        continue;
                    }
                    points += 1;
                    let rr = r as f32 - n;
                    emit(RawPoint {
                        xyz: [d[0] * rr + off[0], d[1] * rr + off[1], d[2] * rr + off[2]],
                        dt_ns: dt,
                        sweep,
                        row: b.row,
                        col,
                        intensity: refl[k],
                        ret: k as u8,
                    });
                }
            }
        }
        self.stats.points += points;
    }

    /// Decodes an IMU packet (counted).
    pub fn imu(&mut self, bytes: &[u8]) -> Result<ImuRepr, Error> {
        match ImuRepr::parse(bytes) {
            Ok(r) => {
                self.stats.imu_packets += 1;
                Ok(r)
            }
            Err(e) => {
                self.stats.bad_imu_packets += 1;
                Err(e)
            }
        }
    }
}

/// A legacy-profile IMU packet (48 bytes): three u64 timestamps (system, accelerometer,
/// gyroscope; ns, the lidar's clock), acceleration in g and angular rate in deg/s, all in the
/// IMU frame (`imu_to_sensor_transform` maps it to the sensor frame).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImuRepr {
    /// System timestamp, ns.
    pub sys_ts_ns: u64,
    /// Accelerometer read time, ns.
    pub accel_ts_ns: u64,
    /// Gyroscope read time, ns.
    pub gyro_ts_ns: u64,
    /// Linear acceleration, g.
    pub accel_g: [f32; 3],
    /// Angular velocity, deg/s.
    pub gyro_dps: [f32; 3],
}

impl ImuRepr {
    /// Parses an IMU packet; exactly [`IMU_PACKET_LEN`] bytes.
    pub fn parse(b: &[u8]) -> Result<Self, Error> {
        if b.len() < IMU_PACKET_LEN {
            return Err(Error::Truncated);
        }
        if b.len() > IMU_PACKET_LEN {
            return Err(Error::TooLong);
        }
        let u64_at = |at: usize| {
            let mut w = [0u8; 8];
            w.copy_from_slice(&b[at..at + 8]);
            u64::from_le_bytes(w)
        };
        let f32_at = |at: usize| f32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]]);
        Ok(Self {
            sys_ts_ns: u64_at(0),
            accel_ts_ns: u64_at(8),
            gyro_ts_ns: u64_at(16),
            accel_g: [f32_at(24), f32_at(28), f32_at(32)],
            gyro_dps: [f32_at(36), f32_at(40), f32_at(44)],
        })
    }

    /// The sample in SI units, stamped with the gyroscope time plus `offset_ns` (the host's
    /// time alignment), or `None` when a value is not finite.
    pub fn sample(&self, offset_ns: i64) -> Option<ImuSample> {
        let d2r = core::f32::consts::PI / 180.0;
        let acc = self.accel_g.map(|a| a * STANDARD_GRAVITY);
        let gyro = self.gyro_dps.map(|g| g * d2r);
        if !acc.iter().chain(gyro.iter()).all(|v| v.is_finite()) {
            return None;
        }
        Some(ImuSample { t_ns: self.gyro_ts_ns.saturating_add_signed(offset_ns), gyro, acc })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    extern crate std;
    use std::vec;
    use std::vec::Vec;

    fn intr(profile: Profile) -> OusterIntrinsics {
        let mut i = OusterIntrinsics::new(profile, 4, 64, 10);
        i.beam_altitude_deg[..4].copy_from_slice(&[10.0, 3.0, -3.0, -10.0]);
        i.beam_azimuth_deg[..4].copy_from_slice(&[3.0, 1.0, -1.0, -3.0]);
        i.pixel_shift_by_row[..4].copy_from_slice(&[3, 1, -1, -3]);
        i.beam_origin_mm = [15.806, 0.0];
        i
    }

    /// A packet of `profile` with columns m0.. and range `1000 * (beam + 1)` mm everywhere.
    fn packet(i: &OusterIntrinsics, frame: u32, m0: u16) -> Vec<u8> {
        let p = i.profile;
        let h = i.pixels_per_column as usize;
        let mut b = vec![0u8; i.lidar_packet_bytes()];
        match p {
            Profile::Legacy => {}
            Profile::FusaDualLowBandwidth => b[4..8].copy_from_slice(&frame.to_le_bytes()),
            _ => b[2..4].copy_from_slice(&(frame as u16).to_le_bytes()),
        }
        for c in 0..i.columns_per_packet as usize {
            let at = p.packet_header() + c * p.column_bytes(h);
            b[at..at + 8].copy_from_slice(&(1_000_000u64 + c as u64 * 1_562_500).to_le_bytes());
            b[at + 8..at + 10].copy_from_slice(&(m0 + c as u16).to_le_bytes());
            if p == Profile::Legacy {
                b[at + 10..at + 12].copy_from_slice(&(frame as u16).to_le_bytes());
                let end = at + p.column_bytes(h);
                b[end - 4..end].copy_from_slice(&u32::MAX.to_le_bytes());
            } else {
                b[at + 10] = 1;
            }
            for u in 0..h {
                let px = at + p.column_header() + u * p.pixel_bytes();
                let r = 1000 * (u as u32 + 1);
                match p {
                    Profile::Legacy | Profile::Single => b[px..px + 4].copy_from_slice(&r.to_le_bytes()),
                    Profile::Dual => {
                        b[px..px + 4].copy_from_slice(&r.to_le_bytes());
                        b[px + 4..px + 8].copy_from_slice(&(r + 5000).to_le_bytes());
                    }
                    Profile::LowBandwidth => b[px..px + 2].copy_from_slice(&((r >> 3) as u16).to_le_bytes()),
                    Profile::FusaDualLowBandwidth => {
                        b[px..px + 2].copy_from_slice(&((r >> 3) as u16).to_le_bytes());
                        b[px + 4..px + 6].copy_from_slice(&(((r + 5000) >> 3) as u16).to_le_bytes());
                    }
                }
            }
        }
        b
    }

    #[test]
    fn packet_sizes_match_the_sdk() {
        assert_eq!(Profile::Legacy.packet_bytes(64, 16), 12_608);
        assert_eq!(Profile::Legacy.packet_bytes(32, 16), 6_464);
        assert_eq!(Profile::Single.packet_bytes(128, 16), 24_832);
        assert_eq!(Profile::LowBandwidth.packet_bytes(128, 16), 8_448);
        assert_eq!(Profile::Dual.packet_bytes(32, 16), 8_448);
        assert_eq!(Profile::FusaDualLowBandwidth.packet_bytes(128, 16), 16_640);
    }

    #[test]
    fn every_profile_decodes_ranges_and_geometry() {
        for profile in [
            Profile::Legacy,
            Profile::Single,
            Profile::Dual,
            Profile::LowBandwidth,
            Profile::FusaDualLowBandwidth,
        ] {
            let i = intr(profile);
            let mut dec = Decoder::new(&i).unwrap();
            let bytes = packet(&i, 7, 16);
            let (p, repr) = dec.parse(&bytes).unwrap();
            assert_eq!(repr.frame_id, 7, "{profile:?}");
            assert_eq!(repr.first_measurement_id, 16);
            assert_eq!(repr.valid_columns, 16);
            let mut pts = Vec::new();
            dec.points(&p, |q| pts.push(q));
            let per_col = if profile.is_dual() { 8 } else { 4 };
            assert_eq!(pts.len(), 16 * per_col, "{profile:?}");
            // Column 0 (mid 16), beam 1 (3 deg up), first return 2 m.
            let q = pts.iter().find(|q| q.row == 1 && q.ret == 0).unwrap();
            let range = 2000.0f32;
            let dir = dec.beam_direction(1, 16);
            // xyz = R (d (r - n) + o) + t; |xyz - t - R o| = r - n along d.
            let n = 15.806f32;
            let e = core::f32::consts::TAU * (1.0 - 16.0 / 64.0);
            let o = [libm::cosf(e) * n, libm::sinf(e) * n, 0.0];
            let ro = [-o[0], -o[1], o[2]];
            for k in 0..3 {
                let expect = (dir[k] * (range - n) + ro[k] + [0.0, 0.0, 36.18][k]) * 1e-3;
                assert!((q.xyz[k] - expect).abs() < 1e-5, "{profile:?} {k}: {} vs {expect}", q.xyz[k]);
            }
            assert_eq!(q.col, 17, "destaggered: mid 16 + shift 1");
            assert_eq!(q.dt_ns, 0);
            assert_eq!(pts.last().unwrap().dt_ns, 15 * 1_562_500);
            if profile.is_dual() {
                let q2 = pts.iter().find(|q| q.row == 1 && q.ret == 1).unwrap();
                let r2 = libm::sqrtf(q2.xyz.iter().map(|v| v * v).sum());
                assert!((r2 - 7.0).abs() < 0.06, "{r2}");
            }
            let seq = dec.sequence(&repr);
            assert_eq!(seq.counter, 7 * 64 + 16);
        }
    }

    #[test]
    fn bad_packets_are_rejected_and_invalid_columns_skipped() {
        let i = intr(Profile::Single);
        let mut dec = Decoder::new(&i).unwrap();
        let mut bytes = packet(&i, 1, 0);
        assert_eq!(dec.parse(&bytes[..bytes.len() - 1]).unwrap_err(), Error::Truncated);
        let mut long = bytes.clone();
        long.push(0);
        assert_eq!(dec.parse(&long).unwrap_err(), Error::TooLong);
        let at = 32 + 3 * Profile::Single.column_bytes(4) + 8;
        bytes[at..at + 2].copy_from_slice(&64u16.to_le_bytes());
        assert_eq!(dec.parse(&bytes).unwrap_err(), Error::BadMeasurementId);
        assert_eq!(dec.stats.bad_packets, 3);
        let mut bytes = packet(&i, 1, 0);
        bytes[32 + 2 * Profile::Single.column_bytes(4) + 10] = 0; // column 2 invalid
        let (p, repr) = dec.parse(&bytes).unwrap();
        assert_eq!(repr.valid_columns, 15);
        let mut n = 0;
        dec.points(&p, |_| n += 1);
        assert_eq!(n, 15 * 4);
        assert_eq!(dec.stats.invalid_columns, 1);
    }

    #[test]
    fn layout_directions_match_beams_after_destaggering() {
        let i = intr(Profile::Legacy);
        let dec = Decoder::new(&i).unwrap();
        let l = dec.layout();
        for u in 0..4 {
            for mid in [0usize, 5, 63] {
                let col = (mid as i32 + i.pixel_shift_by_row[u] as i32).rem_euclid(64) as usize;
                let a = l.direction(dec.beams[u].row as usize, col);
                let b = dec.beam_direction(u, mid);
                let dot: f64 = (0..3).map(|k| a[k] * b[k] as f64).sum();
                let cross = [
                    a[1] * b[2] as f64 - a[2] * b[1] as f64,
                    a[2] * b[0] as f64 - a[0] * b[2] as f64,
                    a[0] * b[1] as f64 - a[1] * b[0] as f64,
                ];
                let angle = libm::atan2(libm::sqrt(cross.iter().map(|c| c * c).sum()), dot);
                assert!(angle < 2e-6, "beam {u} mid {mid}: {angle}");
            }
        }
        // The sweep runs clockwise: with the default 180 deg yaw, mid 0 looks backwards.
        assert_eq!(dec.sweep_of(0), 1 << 31);
        assert_eq!(dec.sweep_of(16), (1u32 << 31) + (1 << 30));
    }

    #[test]
    fn intrinsics_validation() {
        let mut i = intr(Profile::Single);
        i.pixels_per_column = 0;
        assert_eq!(Decoder::new(&i).unwrap_err(), IntrinsicsError::Beams);
        let mut i = intr(Profile::Single);
        i.columns_per_frame = 4096;
        assert_eq!(i.validate(), Err(IntrinsicsError::Columns));
        let mut i = intr(Profile::Single);
        i.beam_altitude_deg[2] = f32::INFINITY;
        assert_eq!(i.validate(), Err(IntrinsicsError::NotFinite));
        let mut i = intr(Profile::Dual);
        i.pixels_per_column = 128;
        i.columns_per_packet = 64;
        assert_eq!(i.validate(), Err(IntrinsicsError::PacketTooLarge));
    }

    #[test]
    fn imu_packets() {
        let mut b = [0u8; IMU_PACKET_LEN];
        b[16..24].copy_from_slice(&5_000u64.to_le_bytes());
        b[32..36].copy_from_slice(&1.0f32.to_le_bytes());
        b[36..40].copy_from_slice(&90.0f32.to_le_bytes());
        let r = ImuRepr::parse(&b).unwrap();
        let s = r.sample(-1_000).unwrap();
        assert_eq!(s.t_ns, 4_000);
        assert!((s.acc[2] - 9.80665).abs() < 1e-6);
        assert!((s.gyro[0] - core::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert_eq!(ImuRepr::parse(&b[..47]).unwrap_err(), Error::Truncated);
        b[24..28].copy_from_slice(&f32::NAN.to_le_bytes());
        assert_eq!(ImuRepr::parse(&b).unwrap().sample(0), None);
    }
}
