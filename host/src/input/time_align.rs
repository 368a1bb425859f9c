//! LiDAR and IMU time alignment.
//!
//! The scan assembler needs each LiDAR packet's absolute time (ns) on the same clock as the
//! IMU samples. Two sources are offered ([`LidarTimeSource`]):
//! - `Sensor`: the packet's own timestamp. Velodyne packets carry microseconds past the top of
//!   the hour: [`VelodyneClock`] adds the hour, from the `$GPRMC` sentences of the position
//!   packets when a GPS is connected, otherwise from the host (capture) date and hour. Ouster
//!   packets carry nanoseconds (since boot with the internal oscillator, TAI/UTC with PTP or
//!   GPS), used as they are; Ouster IMU packets share that clock.
//!   Without GPS (no `$GPRMC`, PPS absent) a Velodyne's clock free-runs from power-on: its
//!   "hour" is arbitrary, the resolved time can be up to 30 min from the host's, and only time
//!   differences are meaningful. Use `Capture` (or an offset) there unless the IMU shares that
//!   clock.
//! - `Capture`: the host's receive time (or the pcap record time).
//!
//! Either way a configurable offset (ns, signed) is added, for an IMU on another clock.
//! [`check_overlap`] turns two streams that do not overlap in time into a clear error with the
//! offset that would line them up.

use loglio_core::sensor::velodyne::MICROS_PER_HOUR;
use loglio_core::sensor::velodyne_position::PositionRepr;

/// Where a LiDAR packet's time comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum LidarTimeSource {
    /// The sensor's packet timestamp, resolved to absolute time.
    #[default]
    Sensor,
    /// The host receive / pcap capture time.
    Capture,
}

impl std::str::FromStr for LidarTimeSource {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "sensor" | "packet" => Ok(Self::Sensor),
            "capture" | "host" => Ok(Self::Capture),
            _ => Err(format!("unknown LiDAR time source {s:?} (sensor or capture)")),
        }
    }
}

/// Time-alignment settings.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub struct TimeAlignConfig {
    /// The source of packet times.
    pub source: LidarTimeSource,
    /// Added to every LiDAR packet time, ns.
    pub offset_ns: i64,
}

const HOUR_NS: i64 = 3_600_000_000_000;

/// Resolves Velodyne microseconds-past-the-hour to absolute ns.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct VelodyneClock {
    /// Absolute time (ns) of a reference instant and its microseconds past the hour, from the
    /// last position packet with a valid date.
    gps_ref: Option<(i64, u32)>,
}

impl VelodyneClock {
    /// A clock with no GPS reference yet (capture time decides the hour).
    pub fn new() -> Self {
        Self::default()
    }

    /// Takes the date and hour from a position packet's `$GPRMC` (if it has one).
    pub fn observe_position(&mut self, pos: &PositionRepr) {
        let Some(rmc) = pos.rmc else { return };
        // The sentence's time and the packet's microsecond clock are within seconds of each
        // other; near the top of the hour they may sit on either side of it.
        let nmea_in_hour_ns =
            (rmc.minute as i64 * 60 + rmc.second as i64) * 1_000_000_000 + rmc.millis as i64 * 1_000_000;
        let mut hour = rmc.hour_start_ns();
        let toh_ns = pos.timestamp_us as i64 * 1000;
        if toh_ns - nmea_in_hour_ns > HOUR_NS / 2 {
            hour -= HOUR_NS;
        } else if nmea_in_hour_ns - toh_ns > HOUR_NS / 2 {
            hour += HOUR_NS;
        }
        self.gps_ref = Some((hour + toh_ns, pos.timestamp_us));
    }

    /// Whether a GPS date has been seen.
    pub fn has_gps(&self) -> bool {
        self.gps_ref.is_some()
    }

    /// Absolute ns of a packet timestamp (µs past the hour), choosing the hour nearest to the
    /// GPS reference, or else to the capture time.
    pub fn resolve(&self, toh_us: u32, capture_ns: u64) -> u64 {
        let toh_ns = (toh_us as u64 % MICROS_PER_HOUR) as i64 * 1000;
        let reference = match self.gps_ref {
            Some((abs, _)) => abs,
            None => capture_ns as i64,
        };
        let hour = reference.div_euclid(HOUR_NS) * HOUR_NS;
        let best = [hour - HOUR_NS, hour, hour + HOUR_NS]
            .into_iter()
            .map(|h| h + toh_ns)
            .min_by_key(|t| (t - reference).unsigned_abs())
            .unwrap_or(hour + toh_ns);
        best.max(0) as u64
    }
}

/// The absolute time of a LiDAR packet.
///
/// `sensor_ns`: the packet's own time already on an absolute scale (Ouster: the first valid
/// column's timestamp; Velodyne: [`VelodyneClock::resolve`]); `capture_ns`: the host receive or
/// pcap time.
pub fn packet_time_ns(cfg: &TimeAlignConfig, sensor_ns: u64, capture_ns: u64) -> u64 {
    let base = match cfg.source {
        LidarTimeSource::Sensor => sensor_ns,
        LidarTimeSource::Capture => capture_ns,
    };
    base.saturating_add_signed(cfg.offset_ns)
}

/// Two streams that do not overlap in time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NoOverlap {
    /// First and last LiDAR time, ns.
    pub lidar: (u64, u64),
    /// First and last IMU time, ns.
    pub imu: (u64, u64),
}

impl NoOverlap {
    /// The offset (ns) that would move the LiDAR start onto the IMU start.
    pub fn suggested_offset_ns(&self) -> i64 {
        self.imu.0 as i64 - self.lidar.0 as i64
    }
}

impl std::fmt::Display for NoOverlap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s = |t: u64| t as f64 * 1e-9;
        write!(
            f,
            "LiDAR and IMU streams do not overlap in time: LiDAR covers {:.6} .. {:.6} s, IMU covers {:.6} .. {:.6} s \
             (gap {:.3} s). Check the LiDAR time source (sensor or capture) and the time offset; an offset of {} ns \
             would line up their starts",
            s(self.lidar.0),
            s(self.lidar.1),
            s(self.imu.0),
            s(self.imu.1),
            if self.lidar.0 > self.imu.1 {
                s(self.lidar.0) - s(self.imu.1)
            } else {
                s(self.imu.0) - s(self.lidar.1)
            },
            self.suggested_offset_ns()
        )
    }
}

impl std::error::Error for NoOverlap {}

/// The common time span of a LiDAR and an IMU stream (each `(first, last)` ns), or an error
/// that says how far apart they are.
pub fn check_overlap(lidar: (u64, u64), imu: (u64, u64)) -> Result<(u64, u64), NoOverlap> {
    let start = lidar.0.max(imu.0);
    let end = lidar.1.min(imu.1);
    if start <= end && lidar.0 <= lidar.1 && imu.0 <= imu.1 {
        Ok((start, end))
    } else {
        Err(NoOverlap { lidar, imu })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use loglio_core::sensor::velodyne_position::{Gprmc, PpsStatus};

    fn pos(toh_us: u32, sentence: &[u8]) -> PositionRepr {
        PositionRepr {
            timestamp_us: toh_us,
            pps: PpsStatus::Absent,
            rmc: Some(Gprmc::parse(sentence).unwrap()),
        }
    }

    #[test]
    fn velodyne_hour_from_gps_and_from_capture() {
        // Monterey: GPRMC 22:06:32 on 2012-12-11; packet clock 393.21 s past the hour.
        let mut c = VelodyneClock::new();
        let hour_22 = 1_355_263_200_000_000_000u64;
        // Without GPS: the capture time (22:06:34.2 by the host clock) picks the hour.
        assert_eq!(c.resolve(393_203_883, hour_22 + 394_200_000_000), hour_22 + 393_203_883_000);
        c.observe_position(&pos(
            393_210_381,
            b"$GPRMC,220632,A,3707.8324,N,12139.2864,W,000.0,144.7,111212,013.8,E,D*09",
        ));
        assert!(c.has_gps());
        // With GPS the capture time no longer matters.
        assert_eq!(c.resolve(393_203_883, 0), hour_22 + 393_203_883_000);
        // A packet stamped 1 ms past the hour, 6.5 minutes before the reference: hour 22.
        assert_eq!(c.resolve(1_000, 0), hour_22 + 1_000_000);
        // After a sentence at 22:59:58, 1 ms past the hour is in hour 23.
        c.observe_position(&pos(
            3_598_400_000,
            b"$GPRMC,225958,A,3707.8324,N,12139.2864,W,000.0,144.7,111212,,",
        ));
        assert_eq!(c.resolve(1_000, 0), hour_22 + 3_600_000_000_000 + 1_000_000);
        // Sentence 22:59:59 stamped 0.5 s after the hour by the sensor clock: hour 23.
        let mut c = VelodyneClock::new();
        c.observe_position(&pos(500_000, b"$GPRMC,225959,A,3707.8324,N,12139.2864,W,000.0,144.7,111212,,"));
        assert_eq!(c.resolve(600_000, 0), hour_22 + 3_600_000_000_000 + 600_000_000);
    }

    #[test]
    fn sources_and_offsets() {
        let mut cfg = TimeAlignConfig { source: LidarTimeSource::Sensor, offset_ns: -5 };
        assert_eq!(packet_time_ns(&cfg, 100, 900), 95);
        cfg.source = LidarTimeSource::Capture;
        assert_eq!(packet_time_ns(&cfg, 100, 900), 895);
        assert_eq!("capture".parse::<LidarTimeSource>(), Ok(LidarTimeSource::Capture));
        assert!("gps".parse::<LidarTimeSource>().is_err());
    }

    #[test]
    fn overlap_or_a_clear_error() {
        assert_eq!(check_overlap((10, 50), (0, 30)), Ok((10, 30)));
        let e = check_overlap(
            (278_211_490_950, 278_311_490_950),
            (1_620_852_160_626_132_000, 1_620_852_160_726_132_000),
        )
        .unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("do not overlap"), "{msg}");
        assert!(msg.contains("time source"), "{msg}");
        assert_eq!(e.suggested_offset_ns(), 1_620_852_160_626_132_000 - 278_211_490_950);
    }
}
