//! Velodyne VLP-16, VLP-32C and HDL-32E firmware: data packets (UDP 2368) and position
//! packets (UDP 8308), written from the vendors' user manuals.
//!
//! Data packet (1206-byte UDP payload): 12 data blocks of 100 bytes, each `0xFF 0xEE`, the
//! azimuth (u16 LE, hundredths of a degree, clockwise) and 32 data points of (distance u16 LE,
//! calibrated reflectivity u8); then a u32 LE timestamp (microseconds past the top of the hour,
//! the time of the packet's first firing) and two factory bytes: the return mode (0x37
//! strongest, 0x38 last, 0x39 dual) and the product id (0x22 VLP-16, 0x28 VLP-32C, 0x21
//! HDL-32E). A distance of 0 means no return.
//!
//! Firing timing (the manuals' timing tables, reproduced by [`Velodyne::firing_offset_ns`]):
//! - VLP-16: 16 lasers fire 2.304 us apart, then recharge: one firing sequence per 55.296 us;
//!   each data block holds two sequences (channels 0-15 and 16-31); 24 sequences per packet.
//!   Distance unit 2 mm. Each laser has a vertical offset (manual table 9-1) applied to z.
//! - VLP-32C: 32 lasers fire in pairs (0+1, 2+3, ...) 2.304 us apart, one sequence per 55.296 us,
//!   one sequence per block; each laser has an azimuth offset of +-1.4 or +-4.2 degrees
//!   (manual table 9-6; added to the block azimuth). Distance unit 4 mm (a 2 mm unit could not
//!   encode the sensor's 200 m range in 16 bits; calibration files say 0.004 too).
//! - HDL-32E: 32 lasers fire 1.152 us apart, one sequence per 46.08 us, one per block; 2 mm.
//! - Every laser's beam starts at a vertical offset from the sensor origin: VLP-16 manual table
//!   9-1; VLP-32C 42.4 mm x tan(-elevation); HDL-32E the envelope drawing's values (the same
//!   tables as the core's built-in calibrations, so the host needs no calibration file).
//! - Dual return: block pairs (0|1, 2|3, ...) share one firing and azimuth; even blocks carry
//!   the last echo, odd blocks the strongest (the second strongest when the strongest is the
//!   last); with a single echo both blocks carry it. A packet then spans half the firings.
//!
//! Geometry: a laser's direction in the sensor frame at time t has elevation w and clockwise
//! azimuth a = head(t) + delta; x = r cos(w) cos(a), y = -r cos(w) sin(a), z = r sin(w) (+ the
//! laser's vertical offset). The head turns at a constant rate from `phase_deg` at the start.
//! The block azimuth is the head azimuth at the block's first firing, rounded to 0.01 degree.

use super::{Echo, EchoSource, Echoes, Firing, RangeModel, ReturnMode, SensorModel};

/// UDP payload size of a data packet.
pub const DATA_PACKET_LEN: usize = 1206;
/// UDP payload size of a position packet.
pub const POSITION_PACKET_LEN: usize = 512;
/// UDP destination port of data packets.
pub const DATA_PORT: u16 = 2368;
/// UDP destination port of position packets.
pub const POSITION_PORT: u16 = 8308;
/// Data points per packet (12 blocks x 32).
pub const POINTS_PER_PACKET: usize = 384;
/// Data packets per position packet ("about 14 to 1", VLP-16 manual 9.3.3).
pub const DATA_PER_POSITION: u64 = 14;

const VLP16_ELEVATION: [f64; 16] =
    [-15.0, 1.0, -13.0, 3.0, -11.0, 5.0, -9.0, 7.0, -7.0, 9.0, -5.0, 11.0, -3.0, 13.0, -1.0, 15.0];
/// VLP-16 vertical offsets of the lasers, millimetres (manual table 9-1).
const VLP16_VERTICAL_MM: [f64; 16] =
    [11.2, -0.7, 9.7, -2.2, 8.1, -3.7, 6.6, -5.1, 5.1, -6.6, 3.7, -8.1, 2.2, -9.7, 0.7, -11.2];
const VLP32C_ELEVATION: [f64; 32] = [
    -25.0, -1.0, -1.667, -15.639, -11.31, 0.0, -0.667, -8.843, -7.254, 0.333, -0.333, -6.148, -5.333, 1.333,
    0.667, -4.0, -4.667, 1.667, 1.0, -3.667, -3.333, 3.333, 2.333, -2.667, -3.0, 7.0, 4.667, -2.333, -2.0,
    15.0, 10.333, -1.333,
];
/// VLP-32C azimuth offsets, degrees clockwise, added to the block azimuth (manual table 9-6).
const VLP32C_AZIMUTH: [f64; 32] = [
    1.4, -4.2, 1.4, -1.4, 1.4, -1.4, 4.2, -1.4, 1.4, -4.2, 1.4, -1.4, 4.2, -1.4, 4.2, -1.4, 1.4, -4.2, 1.4,
    -4.2, 4.2, -1.4, 1.4, -1.4, 1.4, -1.4, 1.4, -4.2, 4.2, -1.4, 1.4, -1.4,
];
/// VLP-32C vertical offsets of the beam origins, millimetres: the 42.4 mm focal distance times
/// tan(-elevation) (the manual documents no per-laser offsets; `velodyne_decoder` and the core's
/// built-in table use the same derivation, so a host decoding without a calibration file gets
/// the simulated points back).
const VLP32C_VERTICAL_MM: [f64; 32] = [
    19.771, 0.740, 1.234, 11.869, 8.480, 0.0, 0.494, 6.596, 5.397, -0.246, 0.246, 4.567, 3.958, -0.987,
    -0.494, 2.965, 3.461, -1.234, -0.740, 2.717, 2.469, -2.469, -1.727, 1.975, 2.222, -5.206, -3.461, 1.727,
    1.481, -11.361, -7.731, 0.987,
];
const HDL32E_ELEVATION: [f64; 32] = [
    -30.67, -9.33, -29.33, -8.0, -28.0, -6.67, -26.67, -5.33, -25.33, -4.0, -24.0, -2.67, -22.67, -1.33,
    -21.33, 0.0, -20.0, 1.33, -18.67, 2.67, -17.33, 4.0, -16.0, 5.33, -14.67, 6.67, -13.33, 8.0, -12.0, 9.33,
    -10.67, 10.67,
];
/// HDL-32E vertical offsets of the laser origins, millimetres (envelope drawing 86-0106 rev B,
/// as the core's built-in table).
const HDL32E_VERTICAL_MM: [f64; 32] = [
    17.17, 4.76, 16.27, 4.07, 15.4, 3.38, 14.54, 2.7, 13.71, 2.02, 12.89, 1.35, 12.09, 0.67, 11.31, 0.0,
    10.54, -0.67, 9.78, -1.35, 9.04, -2.02, 8.3, -2.7, 7.58, -3.38, 6.86, -4.07, 6.15, -4.76, 5.45, -5.45,
];

/// Why a Velodyne configuration was rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConfigError {
    /// The model is not a Velodyne.
    NotVelodyne,
    /// The rotation rate is outside 300-1200 rpm.
    BadRpm,
}

impl core::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::NotVelodyne => "not a Velodyne model",
            Self::BadRpm => "rotation rate must be 300..=1200 rpm",
        })
    }
}

impl core::error::Error for ConfigError {}

/// A Velodyne sensor's configuration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VelodyneConfig {
    /// VLP-16, VLP-32C or HDL-32E.
    pub model: SensorModel,
    /// Rotation rate, revolutions per minute (300-1200).
    pub rpm: f64,
    /// Which echoes are reported.
    pub return_mode: ReturnMode,
    /// Head azimuth at the sensor's time origin, degrees clockwise.
    pub phase_deg: f64,
    /// Noise, dropouts and range limits.
    pub range: RangeModel,
}

impl VelodyneConfig {
    /// The model's defaults: 600 rpm, strongest return, its datasheet range and noise.
    pub fn default_for(model: SensorModel) -> Self {
        let range = match model {
            SensorModel::Vlp32c => {
                RangeModel { sigma: 0.012, dropout: 0.002, min_range: 0.5, max_range: 200.0 }
            }
            SensorModel::Hdl32e => {
                RangeModel { sigma: 0.01, dropout: 0.002, min_range: 1.0, max_range: 100.0 }
            }
            _ => RangeModel { sigma: 0.012, dropout: 0.002, min_range: 0.5, max_range: 100.0 },
        };
        Self { model, rpm: 600.0, return_mode: ReturnMode::Strongest, phase_deg: 180.0, range }
    }
}

/// The ground truth of one encoded data point.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TruthPoint {
    /// Data block (0-11).
    pub block: u8,
    /// Channel within the block (0-31).
    pub channel: u8,
    /// Laser id.
    pub laser: u8,
    /// 0 for the block's echo in single mode or the last echo in dual mode (even block),
    /// 1 for the strongest/second-strongest echo of dual mode (odd block).
    pub slot: u8,
    /// Exact firing time, absolute nanoseconds.
    pub t_ns: u64,
    /// Distance on the wire, in the model's distance units.
    pub raw_distance: u16,
    /// Calibrated reflectivity on the wire.
    pub reflectivity: u8,
    /// Exact clockwise azimuth of the beam at its firing time, degrees in [0, 360).
    pub azimuth_deg: f64,
    /// Elevation of the laser, degrees.
    pub elevation_deg: f64,
    /// The point an exact decoder gets: the quantised distance along the exact beam, plus the
    /// laser's vertical offset; sensor frame at the firing time, metres.
    pub xyz: [f64; 3],
    /// The same with the unquantised (noisy) distance.
    pub xyz_exact: [f64; 3],
}

/// The firmware of one Velodyne sensor.
#[derive(Clone, Debug)]
pub struct Velodyne {
    cfg: VelodyneConfig,
    start_ns: u64,
    lasers: usize,
    elevation: [f64; 32],
    azimuth_offset: [f64; 32],
    vertical: [f64; 32],
    cos_el: [f64; 32],
    sin_el: [f64; 32],
    /// cos/sin of each laser's azimuth lead over its sequence's start: head turn during its
    /// firing offset plus its azimuth offset.
    cos_lead: [f64; 32],
    sin_lead: [f64; 32],
}

impl Velodyne {
    /// The firmware of a sensor whose time origin (head at `phase_deg`) is `start_ns`.
    pub fn new(cfg: VelodyneConfig, start_ns: u64) -> Result<Self, ConfigError> {
        if !cfg.model.is_velodyne() {
            return Err(ConfigError::NotVelodyne);
        }
        if !(300.0..=1200.0).contains(&cfg.rpm) {
            return Err(ConfigError::BadRpm);
        }
        let mut v = Self {
            cfg,
            start_ns,
            lasers: cfg.model.beams(),
            elevation: [0.0; 32],
            azimuth_offset: [0.0; 32],
            vertical: [0.0; 32],
            cos_el: [0.0; 32],
            sin_el: [0.0; 32],
            cos_lead: [0.0; 32],
            sin_lead: [0.0; 32],
        };
        for l in 0..v.lasers {
            let (el, az, vo) = match cfg.model {
                SensorModel::Vlp16 => (VLP16_ELEVATION[l], 0.0, VLP16_VERTICAL_MM[l] * 1e-3),
                SensorModel::Vlp32c => (VLP32C_ELEVATION[l], VLP32C_AZIMUTH[l], VLP32C_VERTICAL_MM[l] * 1e-3),
                _ => (HDL32E_ELEVATION[l], 0.0, HDL32E_VERTICAL_MM[l] * 1e-3),
            };
            v.elevation[l] = el;
            v.azimuth_offset[l] = az;
            v.vertical[l] = vo;
            v.cos_el[l] = libm::cos(el.to_radians());
            v.sin_el[l] = libm::sin(el.to_radians());
            let lead = (6.0 * cfg.rpm * v.firing_offset_ns(l) as f64 * 1e-9 + az).to_radians();
            v.cos_lead[l] = libm::cos(lead);
            v.sin_lead[l] = libm::sin(lead);
        }
        Ok(v)
    }

    /// The configuration.
    pub fn config(&self) -> &VelodyneConfig {
        &self.cfg
    }

    /// The sensor's time origin, ns.
    pub fn start_ns(&self) -> u64 {
        self.start_ns
    }

    /// Number of lasers.
    pub fn lasers(&self) -> usize {
        self.lasers
    }

    /// Elevation of a laser, degrees.
    pub fn elevation_deg(&self, laser: usize) -> f64 {
        self.elevation[laser]
    }

    /// Azimuth offset of a laser, degrees clockwise (VLP-32C; 0 otherwise).
    pub fn azimuth_offset_deg(&self, laser: usize) -> f64 {
        self.azimuth_offset[laser]
    }

    /// Vertical offset of a laser's origin, metres.
    pub fn vertical_offset_m(&self, laser: usize) -> f64 {
        self.vertical[laser]
    }

    /// Distance unit on the wire, metres.
    pub fn distance_unit(&self) -> f64 {
        match self.cfg.model {
            SensorModel::Vlp32c => 0.004,
            _ => 0.002,
        }
    }

    /// The product id factory byte.
    pub fn product_id(&self) -> u8 {
        match self.cfg.model {
            SensorModel::Vlp16 => 0x22,
            SensorModel::Vlp32c => 0x28,
            _ => 0x21,
        }
    }

    /// The return-mode factory byte.
    pub fn return_mode_byte(&self) -> u8 {
        match self.cfg.return_mode {
            ReturnMode::Strongest => 0x37,
            ReturnMode::Last => 0x38,
            ReturnMode::Dual => 0x39,
        }
    }

    /// Duration of one firing sequence (all lasers fire once), ns.
    pub fn sequence_ns(&self) -> u64 {
        match self.cfg.model {
            SensorModel::Hdl32e => 46_080,
            _ => 55_296,
        }
    }

    /// Firing sequences per data block (2 for the VLP-16, else 1).
    pub fn sequences_per_block(&self) -> u64 {
        if self.cfg.model == SensorModel::Vlp16 { 2 } else { 1 }
    }

    /// Firing sequences per data packet.
    pub fn sequences_per_packet(&self) -> u64 {
        let blocks = if self.cfg.return_mode == ReturnMode::Dual { 6 } else { 12 };
        blocks * self.sequences_per_block()
    }

    /// Time of a laser's firing after the start of its sequence, ns (the manuals' tables).
    pub fn firing_offset_ns(&self, laser: usize) -> u64 {
        match self.cfg.model {
            SensorModel::Vlp16 => laser as u64 * 2_304,
            SensorModel::Vlp32c => (laser as u64 / 2) * 2_304,
            _ => laser as u64 * 1_152,
        }
    }

    /// Start time of firing sequence `n`, ns.
    pub fn sequence_time_ns(&self, n: u64) -> u64 {
        self.start_ns + n * self.sequence_ns()
    }

    /// Firing sequences per revolution (not an integer in general).
    pub fn sequences_per_revolution(&self) -> f64 {
        60.0e9 / self.cfg.rpm / self.sequence_ns() as f64
    }

    /// Unwrapped head azimuth at `t_ns`, degrees clockwise.
    pub fn head_azimuth_deg(&self, t_ns: u64) -> f64 {
        let dt = t_ns.saturating_sub(self.start_ns) as f64 * 1e-9;
        self.cfg.phase_deg + 6.0 * self.cfg.rpm * dt
    }

    /// Range-image columns per revolution for the direct-scan layout: 1800 (VLP) or 2160 (HDL)
    /// at 600 rpm, scaled with the rotation rate.
    pub fn columns(&self) -> usize {
        let base = if self.cfg.model == SensorModel::Hdl32e { 2160.0 } else { 1800.0 };
        (libm::round(base * 600.0 / self.cfg.rpm) as usize).clamp(8, 3600)
    }

    /// The firing of `laser` in sequence `n`, with its ray in the sensor frame.
    pub fn firing(&self, n: u64, laser: usize) -> Firing {
        let a = self.head_azimuth_deg(self.sequence_time_ns(n)).to_radians();
        self.firing_at(n, laser, libm::cos(a), libm::sin(a))
    }

    /// All firings of sequence `n` (the first [`Self::lasers`] entries of `out`).
    pub fn sequence_firings(&self, n: u64, out: &mut [Firing; 32]) {
        let a = self.head_azimuth_deg(self.sequence_time_ns(n)).to_radians();
        let (ca, sa) = (libm::cos(a), libm::sin(a));
        for (l, f) in out.iter_mut().enumerate().take(self.lasers) {
            *f = self.firing_at(n, l, ca, sa);
        }
    }

    /// The firing of `laser` in sequence `n` given cos/sin of the sequence's head azimuth.
    #[inline]
    fn firing_at(&self, n: u64, laser: usize, ca: f64, sa: f64) -> Firing {
        let t_ns = self.sequence_time_ns(n) + self.firing_offset_ns(laser);
        // Clockwise azimuth of the beam: head + lead; rotate (cos, sin) by the lead.
        let (cl, sl) = (self.cos_lead[laser], self.sin_lead[laser]);
        let (c, s) = (ca * cl - sa * sl, sa * cl + ca * sl);
        let (ce, se) = (self.cos_el[laser], self.sin_el[laser]);
        Firing {
            t_ns,
            key: (n << 8) | laser as u64,
            beam: laser as u16,
            origin: [0.0, 0.0, self.vertical[laser]],
            dir: [ce * c, -ce * s, se],
        }
    }

    /// Quantises a range to the wire's distance units (0 = no return).
    pub fn quantise(&self, range: f64) -> u16 {
        let raw = libm::round(range / self.distance_unit());
        if !(1.0..=65535.0).contains(&raw) { 0 } else { raw as u16 }
    }

    /// Encodes data packet `k` (covering sequences `k * sequences_per_packet()` onwards) into
    /// `out`, asking `src` for every firing's echoes, and writes the ground truth of every
    /// non-zero data point into `truth`; returns how many truth points were written.
    pub fn data_packet<S: EchoSource>(
        &self,
        k: u64,
        src: &mut S,
        out: &mut [u8; DATA_PACKET_LEN],
        truth: &mut [TruthPoint; POINTS_PER_PACKET],
    ) -> usize {
        out.fill(0);
        let spb = self.sequences_per_block();
        let dual = self.cfg.return_mode == ReturnMode::Dual;
        let first_seq = k * self.sequences_per_packet();
        let mut nt = 0usize;
        let mut echoes = [Echoes::default(); 64];
        let blocks_per_firing = if dual { 2 } else { 1 };
        for fb in 0..(12 / blocks_per_firing) {
            // The firing block fb covers sequences first_seq + fb*spb .. + spb.
            let seq0 = first_seq + fb as u64 * spb;
            let mut firings = [Firing { t_ns: 0, key: 0, beam: 0, origin: [0.0; 3], dir: [0.0; 3] }; 32];
            for s in 0..spb {
                src.begin_sequence(self.sequence_time_ns(seq0 + s));
                let mut seq = [Firing { t_ns: 0, key: 0, beam: 0, origin: [0.0; 3], dir: [0.0; 3] }; 32];
                self.sequence_firings(seq0 + s, &mut seq);
                for (l, f) in seq.iter().enumerate().take(self.lasers) {
                    let ch = s as usize * self.lasers + l;
                    firings[ch] = *f;
                    echoes[ch] = src.measure(f);
                }
            }
            let az = self.head_azimuth_deg(self.sequence_time_ns(seq0));
            let az_raw = (libm::round(az * 100.0) as i64).rem_euclid(36_000) as u16;
            for slot in 0..blocks_per_firing {
                let b = fb * blocks_per_firing + slot;
                let base = b * 100;
                out[base] = 0xFF;
                out[base + 1] = 0xEE;
                out[base + 2..base + 4].copy_from_slice(&az_raw.to_le_bytes());
                for (ch, f) in firings.iter().enumerate().take(32) {
                    let e = echoes[ch];
                    let echo = match (self.cfg.return_mode, slot) {
                        (ReturnMode::Strongest, _) => e.strongest(),
                        (ReturnMode::Last, _) | (ReturnMode::Dual, 0) => e.last_echo(),
                        (ReturnMode::Dual, _) => e.dual_partner(),
                    };
                    let Some(Echo { range, reflectivity, .. }) = echo else { continue };
                    let raw = self.quantise(range);
                    if raw == 0 {
                        continue;
                    }
                    let p = base + 4 + ch * 3;
                    out[p..p + 2].copy_from_slice(&raw.to_le_bytes());
                    out[p + 2] = reflectivity;
                    let laser = f.beam as usize;
                    let q = raw as f64 * self.distance_unit();
                    let at = |r: f64| {
                        [f.origin[0] + r * f.dir[0], f.origin[1] + r * f.dir[1], f.origin[2] + r * f.dir[2]]
                    };
                    let az_f = wrap360(self.head_azimuth_deg(f.t_ns) + self.azimuth_offset[laser]);
                    truth[nt] = TruthPoint {
                        block: b as u8,
                        channel: ch as u8,
                        laser: laser as u8,
                        slot: slot as u8,
                        t_ns: f.t_ns,
                        raw_distance: raw,
                        reflectivity,
                        azimuth_deg: az_f,
                        elevation_deg: self.elevation[laser],
                        xyz: at(q),
                        xyz_exact: at(range),
                    };
                    nt += 1;
                }
            }
        }
        let ts = self.timestamp_us(self.sequence_time_ns(first_seq));
        out[1200..1204].copy_from_slice(&ts.to_le_bytes());
        out[1204] = self.return_mode_byte();
        out[1205] = self.product_id();
        nt
    }

    /// Microseconds past the top of the hour of an absolute (Unix, UTC) time.
    pub fn timestamp_us(&self, t_ns: u64) -> u32 {
        ((t_ns / 1_000) % 3_600_000_000) as u32
    }

    /// Time of the first firing of data packet `k`, ns.
    pub fn packet_time_ns(&self, k: u64) -> u64 {
        self.sequence_time_ns(k * self.sequences_per_packet())
    }

    /// Writes a position packet for time `t_ns` carrying an NMEA sentence (the latest GPRMC).
    pub fn position_packet(&self, t_ns: u64, nmea: &[u8], out: &mut [u8; POSITION_PACKET_LEN]) {
        out.fill(0);
        out[198..202].copy_from_slice(&self.timestamp_us(t_ns).to_le_bytes());
        out[202] = 2; // PPS locked
        let n = nmea.len().min(POSITION_PACKET_LEN - 206);
        out[206..206 + n].copy_from_slice(&nmea[..n]);
    }
}

/// An angle in degrees wrapped into [0, 360) (no_std: no `f64::rem_euclid`).
pub fn wrap360(x: f64) -> f64 {
    let w = x - 360.0 * libm::floor(x / 360.0);
    if w >= 360.0 { 0.0 } else { w }
}

/// A small `core::fmt::Write` into a byte slice (no heap).
struct SliceWriter<'a> {
    buf: &'a mut [u8],
    len: usize,
}

impl core::fmt::Write for SliceWriter<'_> {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        let b = s.as_bytes();
        let end = self.len + b.len();
        if end > self.buf.len() {
            return Err(core::fmt::Error);
        }
        self.buf[self.len..end].copy_from_slice(b);
        self.len = end;
        Ok(())
    }
}

/// Civil date (year, month, day) of a day count since 1970-01-01 (H. Hinnant's algorithm).
pub fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let y = yoe + era * 400;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    (if m <= 2 { y + 1 } else { y }, m, d)
}

/// Writes a `$GPRMC` sentence (with checksum and CR LF) for a Unix time (whole seconds are
/// used), a position in degrees, a speed over ground in knots and a course in degrees.
/// Returns the length, or `None` if `out` is too short (82 bytes always suffice).
pub fn gprmc(
    unix_s: u64,
    lat_deg: f64,
    lon_deg: f64,
    speed_kn: f64,
    course_deg: f64,
    out: &mut [u8],
) -> Option<usize> {
    use core::fmt::Write;
    let days = (unix_s / 86_400) as i64;
    let sod = unix_s % 86_400;
    let (y, mo, d) = civil_from_days(days);
    let (lat_h, lat) = if lat_deg < 0.0 { ('S', -lat_deg) } else { ('N', lat_deg) };
    let (lon_h, lon) = if lon_deg < 0.0 { ('W', -lon_deg) } else { ('E', lon_deg) };
    let (lat_d, lon_d) = (libm::floor(lat), libm::floor(lon));
    let mut w = SliceWriter { buf: out, len: 0 };
    write!(
        w,
        "$GPRMC,{:02}{:02}{:02},A,{:02}{:07.4},{},{:03}{:07.4},{},{:05.1},{:05.1},{:02}{:02}{:02},,,A",
        sod / 3600,
        (sod / 60) % 60,
        sod % 60,
        lat_d as u32,
        (lat - lat_d) * 60.0,
        lat_h,
        lon_d as u32,
        (lon - lon_d) * 60.0,
        lon_h,
        speed_kn.clamp(0.0, 999.9),
        wrap360(course_deg),
        d,
        mo,
        y.rem_euclid(100)
    )
    .ok()?;
    let cs = w.buf[1..w.len].iter().fold(0u8, |a, b| a ^ b);
    write!(w, "*{cs:02X}\r\n").ok()?;
    Some(w.len)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A source that sees a cylinder wall of radius 10 m around the sensor (range 10 m at any
    /// elevation if measured horizontally) and records the calls.
    struct Wall {
        sequences: u32,
    }

    impl EchoSource for Wall {
        fn begin_sequence(&mut self, _t_ns: u64) {
            self.sequences += 1;
        }
        fn measure(&mut self, f: &Firing) -> Echoes {
            let horiz = libm::hypot(f.dir[0], f.dir[1]);
            // Every 7th firing is a dropout; laser 3 sees a partial echo in front.
            if f.key.is_multiple_of(7) {
                return Echoes::default();
            }
            let last = Echo { range: 10.0 / horiz, reflectivity: 40, strength: 1.0 };
            let first = (f.beam == 3).then_some(Echo { range: 4.0, reflectivity: 10, strength: 2.0 });
            Echoes { first, last: Some(last) }
        }
    }

    fn vel(model: SensorModel, mode: ReturnMode) -> Velodyne {
        let mut c = VelodyneConfig::default_for(model);
        c.return_mode = mode;
        Velodyne::new(c, 1_714_565_400_000_000_000).unwrap()
    }

    #[test]
    fn packet_structure_and_timing_tables() {
        for model in [SensorModel::Vlp16, SensorModel::Vlp32c, SensorModel::Hdl32e] {
            for mode in [ReturnMode::Strongest, ReturnMode::Last, ReturnMode::Dual] {
                let v = vel(model, mode);
                let mut src = Wall { sequences: 0 };
                let mut buf = [0u8; DATA_PACKET_LEN];
                let mut truth = [TruthPoint::default(); POINTS_PER_PACKET];
                let mut last_az: Option<i32> = None;
                for k in 0..30u64 {
                    let n = v.data_packet(k, &mut src, &mut buf, &mut truth);
                    assert!(n > 300, "{model:?} {mode:?} {n}");
                    for b in 0..12 {
                        assert_eq!(&buf[b * 100..b * 100 + 2], &[0xFF, 0xEE]);
                    }
                    assert_eq!(buf[1204], v.return_mode_byte());
                    assert_eq!(buf[1205], v.product_id());
                    let ts = u32::from_le_bytes(buf[1200..1204].try_into().unwrap());
                    assert_eq!(ts, v.timestamp_us(v.packet_time_ns(k)));
                    // Azimuths never decrease within a revolution (the step is ~0.2-0.4 degree).
                    for b in 0..12 {
                        let az = u16::from_le_bytes([buf[b * 100 + 2], buf[b * 100 + 3]]) as i32;
                        assert!(az < 36_000);
                        if let Some(prev) = last_az {
                            let step = (az - prev).rem_euclid(36_000);
                            let dual_pair = mode == ReturnMode::Dual && b % 2 == 1;
                            if dual_pair {
                                assert_eq!(step, 0);
                            } else {
                                let expect = v.sequences_per_block() as f64
                                    * v.sequence_ns() as f64
                                    * 1e-9
                                    * 6.0
                                    * v.config().rpm
                                    * 100.0;
                                assert!(
                                    (step as f64 - expect).abs() <= 1.0,
                                    "{model:?} step {step} vs {expect}"
                                );
                            }
                        }
                        last_az = Some(az);
                    }
                    for t in &truth[..n] {
                        // Timing table: block/channel -> offset from the packet timestamp.
                        let b = t.block as u64;
                        let fb = if mode == ReturnMode::Dual { b / 2 } else { b };
                        let ch = t.channel as u64;
                        let expect = match model {
                            SensorModel::Vlp16 => 55_296 * (2 * fb + ch / 16) + 2_304 * (ch % 16),
                            SensorModel::Vlp32c => 55_296 * fb + 2_304 * (ch / 2),
                            _ => 46_080 * fb + 1_152 * ch,
                        };
                        assert_eq!(t.t_ns - v.packet_time_ns(k), expect, "{model:?} b{b} ch{ch}");
                        let laser = if model == SensorModel::Vlp16 { ch % 16 } else { ch };
                        assert_eq!(t.laser as u64, laser);
                        // Bytes on the wire match the truth.
                        let p = t.block as usize * 100 + 4 + ch as usize * 3;
                        assert_eq!(u16::from_le_bytes([buf[p], buf[p + 1]]), t.raw_distance);
                        assert_eq!(buf[p + 2], t.reflectivity);
                        // Quantised point within half a distance unit of the exact one.
                        let d = (0..3).map(|i| (t.xyz[i] - t.xyz_exact[i]).powi(2)).sum::<f64>().sqrt();
                        assert!(d <= v.distance_unit() * 0.5 + 1e-12);
                        // The wall is 10 m away horizontally (laser 3 may report the leaf).
                        let h = libm::hypot(t.xyz_exact[0], t.xyz_exact[1]);
                        assert!(
                            (h - 10.0).abs() < 1e-9
                                || (t.laser == 3
                                    && (h - 4.0 * libm::cos(t.elevation_deg.to_radians())).abs() < 1e-9)
                        );
                    }
                    // Single modes: one truth point per non-dropped firing.
                    if mode != ReturnMode::Dual {
                        assert_eq!(
                            n,
                            (0..12 * 32)
                                .filter(|c| buf[(c / 32) * 100 + 4 + (c % 32) * 3] != 0
                                    || buf[(c / 32) * 100 + 5 + (c % 32) * 3] != 0)
                                .count()
                        );
                    }
                }
                assert_eq!(src.sequences as u64, 30 * v.sequences_per_packet());
            }
        }
    }

    #[test]
    fn echo_selection_by_mode() {
        // Laser 3 sees a strong leaf at 4 m in front of the wall: strongest picks the leaf, last
        // the wall, dual the wall (even block) and the leaf (odd block).
        for mode in [ReturnMode::Strongest, ReturnMode::Last, ReturnMode::Dual] {
            let v = vel(SensorModel::Hdl32e, mode);
            let mut buf = [0u8; DATA_PACKET_LEN];
            let mut truth = [TruthPoint::default(); POINTS_PER_PACKET];
            let n = v.data_packet(1, &mut Wall { sequences: 0 }, &mut buf, &mut truth);
            let mut seen = 0;
            for t in truth[..n].iter().filter(|t| t.laser == 3) {
                // Range from the beam's origin (the laser's vertical offset above the sensor's).
                let o = [0.0, 0.0, v.vertical_offset_m(t.laser as usize)];
                let r = (0..3).map(|i| (t.xyz_exact[i] - o[i]).powi(2)).sum::<f64>().sqrt();
                let wall = 10.0 / libm::cos(t.elevation_deg.to_radians());
                let want = match (mode, t.slot) {
                    (ReturnMode::Strongest, _) | (ReturnMode::Dual, 1) => 4.0,
                    _ => wall,
                };
                assert!((r - want).abs() < 1e-9, "{mode:?} slot {} r {r}", t.slot);
                seen += 1;
            }
            assert!(seen >= 10);
        }
    }

    #[test]
    fn timestamps_wrap_at_the_top_of_the_hour() {
        // Start 50 ms before 13:00:00 UTC: packet timestamps run up to 3,599,9xx,xxx us and
        // restart from 0 at the hour, each the packet's first firing time modulo one hour.
        let cfg = VelodyneConfig::default_for(SensorModel::Vlp16);
        let v = Velodyne::new(cfg, 1_714_568_400_000_000_000 - 50_000_000).unwrap();
        let mut buf = [0u8; DATA_PACKET_LEN];
        let mut truth = [TruthPoint::default(); POINTS_PER_PACKET];
        let mut wrapped = false;
        let mut prev = 0u32;
        for k in 0..80 {
            v.data_packet(k, &mut Wall { sequences: 0 }, &mut buf, &mut truth);
            let ts = u32::from_le_bytes(buf[1200..1204].try_into().unwrap());
            assert!(ts < 3_600_000_000);
            assert_eq!(ts as u64, (v.packet_time_ns(k) / 1000) % 3_600_000_000);
            if k > 0 && ts < prev {
                wrapped = true;
                assert!(prev > 3_599_900_000 && ts < 2_000);
            }
            prev = ts;
        }
        assert!(wrapped);
    }

    #[test]
    fn gprmc_sentence_and_position_packet() {
        // 2024-05-01 12:10:07 UTC.
        let mut s = [0u8; 100];
        let n = gprmc(1_714_565_407, 48.1374, -11.5755, 12.34, 271.0, &mut s).unwrap();
        let txt = core::str::from_utf8(&s[..n]).unwrap();
        assert!(txt.starts_with("$GPRMC,121007,A,4808.2440,N,01134.5300,W,012.3,271.0,010524,,,A*"), "{txt}");
        assert!(txt.ends_with("\r\n"));
        let cs = u8::from_str_radix(&txt[n - 4..n - 2], 16).unwrap();
        assert_eq!(cs, txt.as_bytes()[1..n - 5].iter().fold(0, |a, b| a ^ b));
        assert_eq!(civil_from_days(0), (1970, 1, 1));
        assert_eq!(civil_from_days(19_844), (2024, 5, 1));
        assert_eq!(civil_from_days(-1), (1969, 12, 31));
        let v = vel(SensorModel::Vlp16, ReturnMode::Strongest);
        let mut p = [0u8; POSITION_PACKET_LEN];
        v.position_packet(1_714_565_407_123_456_789, &s[..n], &mut p);
        assert_eq!(u32::from_le_bytes(p[198..202].try_into().unwrap()), 607_123_456);
        assert_eq!(p[202], 2);
        assert_eq!(&p[206..206 + n], &s[..n]);
        assert!(p[206 + n..].iter().all(|&b| b == 0));
    }
}
