//! Velodyne position packets (512-byte UDP payloads, port 8308): the sensor's microsecond
//! clock, the PPS status and the NMEA `$GPRMC` sentence from a GPS receiver.
//!
//! Layout (VLP-16 / VLP-32C manuals; the HDL-32E uses the same offsets for the fields below and
//! has IMU data in the first bytes):
//!
//! ```text
//! 198..202  microseconds past the top of the hour (u32 LE)
//! 202       PPS status: 0 absent, 1 synchronising, 2 locked, 3 error (0 on HDL-32E)
//! 206..334  NMEA sentence, ASCII, NUL padded ($GPRMC,hhmmss,A,lat,N,lon,W,knots,course,ddmmyy,...)
//! ```
//!
//! The GPRMC date and hour resolve the packet timestamps (microseconds past the hour) to
//! absolute UTC time; see `time_align` in loglio-host.

/// Length of a position packet.
pub const POSITION_PACKET_LEN: usize = 512;
/// UDP port of position packets.
pub const POSITION_PORT: u16 = 8308;

/// Field ranges.
pub mod field {
    use core::ops::Range;
    /// Microseconds past the hour.
    pub const TIMESTAMP: Range<usize> = 198..202;
    /// PPS status byte.
    pub const PPS_STATUS: usize = 202;
    /// NMEA sentence.
    pub const NMEA: Range<usize> = 206..334;
}

/// Why a position packet or its sentence was rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Error {
    /// Shorter than 512 bytes.
    Truncated,
    /// Longer than 512 bytes.
    TooLong,
    /// No NMEA sentence in the packet.
    NoSentence,
    /// The sentence is not an RMC sentence.
    NotRmc,
    /// A field is missing or malformed.
    BadField,
    /// The `*hh` checksum does not match.
    Checksum,
}

impl core::fmt::Display for Error {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Truncated => "velodyne position packet shorter than 512 bytes",
            Self::TooLong => "velodyne position packet longer than 512 bytes",
            Self::NoSentence => "velodyne position packet has no NMEA sentence",
            Self::NotRmc => "NMEA sentence is not $GPRMC/$GNRMC",
            Self::BadField => "NMEA RMC sentence has a missing or malformed field",
            Self::Checksum => "NMEA checksum mismatch",
        })
    }
}

impl core::error::Error for Error {}

/// PPS (pulse per second) synchronisation status.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PpsStatus {
    /// No PPS detected.
    Absent,
    /// Synchronising to PPS.
    Synchronizing,
    /// PPS locked.
    Locked,
    /// PPS error.
    Error,
    /// Any other byte.
    Unknown(u8),
}

impl PpsStatus {
    /// Decodes byte 202.
    pub const fn from_byte(b: u8) -> Self {
        match b {
            0 => Self::Absent,
            1 => Self::Synchronizing,
            2 => Self::Locked,
            3 => Self::Error,
            o => Self::Unknown(o),
        }
    }
}

/// A checked view of a position packet.
#[derive(Debug, Clone, Copy)]
pub struct PositionPacket<T: AsRef<[u8]>> {
    buffer: T,
}

impl<T: AsRef<[u8]>> PositionPacket<T> {
    /// Wraps a buffer of exactly 512 bytes.
    pub fn new_checked(buffer: T) -> Result<Self, Error> {
        let n = buffer.as_ref().len();
        if n < POSITION_PACKET_LEN {
            return Err(Error::Truncated);
        }
        if n > POSITION_PACKET_LEN {
            return Err(Error::TooLong);
        }
        Ok(Self { buffer })
    }

    /// Microseconds past the top of the hour.
    pub fn timestamp_us(&self) -> u32 {
        let b = self.buffer.as_ref();
        u32::from_le_bytes([b[198], b[199], b[200], b[201]])
    }

    /// PPS status.
    pub fn pps_status(&self) -> PpsStatus {
        PpsStatus::from_byte(self.buffer.as_ref()[field::PPS_STATUS])
    }

    /// The NMEA sentence bytes (up to the first NUL), or empty.
    pub fn nmea(&self) -> &[u8] {
        let s = &self.buffer.as_ref()[field::NMEA];
        let end = s.iter().position(|&c| c == 0).unwrap_or(s.len());
        &s[..end]
    }
}

/// The parsed facts of a position packet.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PositionRepr {
    /// Microseconds past the hour.
    pub timestamp_us: u32,
    /// PPS status.
    pub pps: PpsStatus,
    /// The RMC sentence, if there is a valid one.
    pub rmc: Option<Gprmc>,
}

impl PositionRepr {
    /// Parses a checked packet; a missing or malformed sentence leaves `rmc` empty.
    pub fn parse<T: AsRef<[u8]>>(p: &PositionPacket<T>) -> Self {
        Self { timestamp_us: p.timestamp_us(), pps: p.pps_status(), rmc: Gprmc::parse(p.nmea()).ok() }
    }
}

/// An NMEA RMC sentence (recommended minimum GNSS data).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Gprmc {
    /// UTC hour, minute.
    pub hour: u8,
    /// Minute.
    pub minute: u8,
    /// Second.
    pub second: u8,
    /// Milliseconds (from a fractional seconds field).
    pub millis: u16,
    /// 'A' (active, valid fix) or 'V' (void).
    pub valid: bool,
    /// Latitude, degrees, north positive (NaN if empty).
    pub latitude_deg: f64,
    /// Longitude, degrees, east positive (NaN if empty).
    pub longitude_deg: f64,
    /// Speed over ground, knots (NaN if empty).
    pub speed_knots: f32,
    /// Course over ground, degrees (NaN if empty).
    pub course_deg: f32,
    /// Day of month.
    pub day: u8,
    /// Month.
    pub month: u8,
    /// Full year (two-digit years are 2000-2079 / 1980-1999).
    pub year: u16,
}

impl Gprmc {
    /// Parses `$GPRMC` (or `$GNRMC`, `$GLRMC`, ...); verifies the checksum when present.
    pub fn parse(s: &[u8]) -> Result<Self, Error> {
        let s = trim(s);
        if s.is_empty() {
            return Err(Error::NoSentence);
        }
        if s.len() < 6 || s[0] != b'$' || &s[3..6] != b"RMC" {
            return Err(Error::NotRmc);
        }
        let body_end = s.iter().position(|&c| c == b'*').unwrap_or(s.len());
        if body_end < s.len() {
            let hex = &s[body_end + 1..];
            if hex.len() < 2 {
                return Err(Error::BadField);
            }
            let want = hex_byte(hex[0], hex[1]).ok_or(Error::BadField)?;
            let got = s[1..body_end].iter().fold(0u8, |a, &c| a ^ c);
            if want != got {
                return Err(Error::Checksum);
            }
        }
        let mut fields = s[..body_end].split(|&c| c == b',');
        let _talker = fields.next();
        let time = fields.next().ok_or(Error::BadField)?;
        let status = fields.next().ok_or(Error::BadField)?;
        let lat = fields.next().ok_or(Error::BadField)?;
        let ns = fields.next().ok_or(Error::BadField)?;
        let lon = fields.next().ok_or(Error::BadField)?;
        let ew = fields.next().ok_or(Error::BadField)?;
        let speed = fields.next().ok_or(Error::BadField)?;
        let course = fields.next().ok_or(Error::BadField)?;
        let date = fields.next().ok_or(Error::BadField)?;
        if time.len() < 6 || date.len() != 6 {
            return Err(Error::BadField);
        }
        let hour = two_digits(&time[0..2])?;
        let minute = two_digits(&time[2..4])?;
        let second = two_digits(&time[4..6])?;
        let millis = if time.len() > 7 && time[6] == b'.' {
            let frac = parse_f64(&time[6..]).ok_or(Error::BadField)?;
            (frac * 1000.0).clamp(0.0, 999.0) as u16
        } else if time.len() == 6 {
            0
        } else {
            return Err(Error::BadField);
        };
        let day = two_digits(&date[0..2])?;
        let month = two_digits(&date[2..4])?;
        let yy = two_digits(&date[4..6])? as u16;
        if hour > 23 || minute > 59 || second > 60 || !(1..=31).contains(&day) || !(1..=12).contains(&month) {
            return Err(Error::BadField);
        }
        let year = if yy < 80 { 2000 + yy } else { 1900 + yy };
        let latitude_deg = match (degrees_minutes(lat, 2), ns) {
            (Some(v), b"N") => v,
            (Some(v), b"S") => -v,
            (None, _) if lat.is_empty() => f64::NAN,
            _ => return Err(Error::BadField),
        };
        let longitude_deg = match (degrees_minutes(lon, 3), ew) {
            (Some(v), b"E") => v,
            (Some(v), b"W") => -v,
            (None, _) if lon.is_empty() => f64::NAN,
            _ => return Err(Error::BadField),
        };
        let opt = |f: &[u8]| if f.is_empty() { Some(f64::NAN) } else { parse_f64(f) };
        Ok(Self {
            hour,
            minute,
            second,
            millis,
            valid: status == b"A",
            latitude_deg,
            longitude_deg,
            speed_knots: opt(speed).ok_or(Error::BadField)? as f32,
            course_deg: opt(course).ok_or(Error::BadField)? as f32,
            day,
            month,
            year,
        })
    }

    /// Seconds since 1970-01-01 00:00 UTC of the sentence's time (whole seconds).
    pub fn unix_seconds(&self) -> i64 {
        days_from_civil(self.year as i64, self.month as i64, self.day as i64) * 86_400
            + self.hour as i64 * 3600
            + self.minute as i64 * 60
            + self.second as i64
    }

    /// Start of the sentence's UTC hour, ns since 1970.
    pub fn hour_start_ns(&self) -> i64 {
        (days_from_civil(self.year as i64, self.month as i64, self.day as i64) * 86_400
            + self.hour as i64 * 3600)
            * 1_000_000_000
    }
}

fn trim(s: &[u8]) -> &[u8] {
    let mut a = 0;
    let mut b = s.len();
    while a < b && s[a].is_ascii_whitespace() {
        a += 1;
    }
    while b > a && s[b - 1].is_ascii_whitespace() {
        b -= 1;
    }
    &s[a..b]
}

fn hex_byte(h: u8, l: u8) -> Option<u8> {
    let v = |c: u8| (c as char).to_digit(16).map(|d| d as u8);
    Some(v(h)? << 4 | v(l)?)
}

fn two_digits(s: &[u8]) -> Result<u8, Error> {
    match s {
        [a, b] if a.is_ascii_digit() && b.is_ascii_digit() => Ok((a - b'0') * 10 + (b - b'0')),
        _ => Err(Error::BadField),
    }
}

/// Parses a plain decimal number (digits, one optional '.', optional leading '-').
fn parse_f64(s: &[u8]) -> Option<f64> {
    let (neg, s) = match s.first() {
        Some(b'-') => (true, &s[1..]),
        _ => (false, s),
    };
    if s.is_empty() || s.len() > 24 {
        return None;
    }
    let mut int = 0f64;
    let mut frac = 0f64;
    let mut scale = 1f64;
    let mut seen_dot = false;
    let mut digits = 0;
    for &c in s {
        match c {
            b'0'..=b'9' => {
                digits += 1;
                if seen_dot {
                    scale *= 0.1;
                    frac += (c - b'0') as f64 * scale;
                } else {
                    int = int * 10.0 + (c - b'0') as f64;
                }
            }
            b'.' if !seen_dot => seen_dot = true,
            _ => return None,
        }
    }
    if digits == 0 {
        return None;
    }
    let v = int + frac;
    Some(if neg { -v } else { v })
}

/// NMEA `dddmm.mmmm` with `deg_digits` degree digits, as degrees.
fn degrees_minutes(s: &[u8], deg_digits: usize) -> Option<f64> {
    if s.len() <= deg_digits || !s[..deg_digits].iter().all(|c| c.is_ascii_digit()) {
        return None;
    }
    let d = parse_f64(&s[..deg_digits])?;
    let m = parse_f64(&s[deg_digits..])?;
    if m >= 60.0 {
        return None;
    }
    Some(d + m / 60.0)
}

/// Days from 1970-01-01 to a proleptic Gregorian date (H. Hinnant's algorithm).
pub fn days_from_civil(y: i64, m: i64, d: i64) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = if y >= 0 { y } else { y - 399 } / 400;
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + d - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

#[cfg(test)]
mod tests {
    use super::*;

    const MONTEREY: &[u8] = b"$GPRMC,220632,A,3707.8324,N,12139.2864,W,000.0,144.7,111212,013.8,E,D*09\r\n";

    #[test]
    fn parses_a_real_sentence() {
        let r = Gprmc::parse(MONTEREY).unwrap();
        assert_eq!((r.hour, r.minute, r.second, r.millis), (22, 6, 32, 0));
        assert!(r.valid);
        assert!((r.latitude_deg - (37.0 + 7.8324 / 60.0)).abs() < 1e-9);
        assert!((r.longitude_deg + (121.0 + 39.2864 / 60.0)).abs() < 1e-9);
        assert_eq!(r.speed_knots, 0.0);
        assert!((r.course_deg - 144.7).abs() < 1e-4);
        assert_eq!((r.day, r.month, r.year), (11, 12, 2012));
        // 2012-12-11 22:06:32 UTC = 1355263592.
        assert_eq!(r.unix_seconds(), 1_355_263_592);
        assert_eq!(r.hour_start_ns(), 1_355_263_200 * 1_000_000_000);
    }

    #[test]
    fn rejects_bad_sentences() {
        assert_eq!(Gprmc::parse(b""), Err(Error::NoSentence));
        assert_eq!(Gprmc::parse(b"$GPGGA,1,2,3"), Err(Error::NotRmc));
        let mut bad = MONTEREY.to_vec();
        bad[10] = b'7';
        assert_eq!(Gprmc::parse(&bad), Err(Error::Checksum));
        assert_eq!(Gprmc::parse(b"$GPRMC,2206,A"), Err(Error::BadField));
        assert_eq!(
            Gprmc::parse(b"$GPRMC,220632,A,3707.8324,N,12139.2864,W,0,0,321312"),
            Err(Error::BadField)
        );
        assert_eq!(
            Gprmc::parse(b"$GPRMC,220632,A,3707.8324,X,12139.2864,W,0,0,111212"),
            Err(Error::BadField)
        );
        // No fix: empty position fields are accepted as NaN.
        let v = Gprmc::parse(b"$GPRMC,000001.50,V,,,,,,,010120,,").unwrap();
        assert!(!v.valid && v.latitude_deg.is_nan());
        assert_eq!(v.millis, 500);
    }

    #[test]
    fn packet_fields() {
        let mut b = [0u8; POSITION_PACKET_LEN];
        b[198..202].copy_from_slice(&393_210_381u32.to_le_bytes());
        b[202] = 2;
        b[206..206 + MONTEREY.len()].copy_from_slice(MONTEREY);
        let p = PositionPacket::new_checked(&b[..]).unwrap();
        let r = PositionRepr::parse(&p);
        assert_eq!(r.timestamp_us, 393_210_381);
        assert_eq!(r.pps, PpsStatus::Locked);
        assert_eq!(r.rmc.unwrap().minute, 6);
        assert_eq!(PositionPacket::new_checked(&b[..511]).unwrap_err(), Error::Truncated);
        let big = [0u8; 600];
        assert_eq!(PositionPacket::new_checked(&big[..]).unwrap_err(), Error::TooLong);
        let empty = PositionPacket::new_checked(&big[..512]).unwrap();
        assert_eq!(PositionRepr::parse(&empty).rmc, None);
        assert_eq!(days_from_civil(1970, 1, 1), 0);
        assert_eq!(days_from_civil(2000, 3, 1), 11_017);
    }
}
