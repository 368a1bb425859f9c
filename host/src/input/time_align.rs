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

/// Puts the sample times of an IMU that stamps on its own clock (Xsens SampleTimeFine,
/// VectorNav TimeStartup: time since its power-on) onto this computer's clock, the clock of the
/// arrival times and of the LiDAR's capture times.
///
/// The arrival of a sample is its device time plus a fixed offset plus a transport delay that
/// is never negative and often large (USB polling, the serial driver, a busy thread). The
/// minimum of `arrival - device` over a window is therefore the offset plus the smallest
/// delay, and follows the offset with the least latency: one late sample cannot move it, and
/// the device's sample-to-sample spacing (its crystal) is kept. The minimum is taken over the
/// current and the previous window of [`DeviceClock::WINDOW_NS`] device time, so a drift
/// between the clocks is followed a window at a time; the drift itself is the slope of the
/// window minima over the run. A device time that steps back (the device restarted) starts the
/// estimate afresh. Mapped times only increase.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DeviceClock {
    /// The window being filled: its first device time and its minimum of arrival - device.
    cur: Option<(u64, i64)>,
    /// The last complete window's minimum.
    prev_min: Option<i64>,
    /// The first and the last complete window (first device time, minimum).
    first_window: Option<(u64, i64)>,
    last_window: Option<(u64, i64)>,
    last_device: Option<u64>,
    last_out: u64,
    /// Times the device time stepped back.
    pub resets: u64,
}

/// What a [`DeviceClock`] estimated.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClockEstimate {
    /// Arrival minus device time (the smallest over the last windows), ns.
    pub offset_ns: i64,
    /// Drift of arrival minus device time, parts per million of device time (positive: the
    /// device's clock runs slow against this computer's); `None` before two complete windows.
    pub drift_ppm: Option<f64>,
    /// Device time the drift was measured over, s.
    pub span_s: f64,
    /// Times the device time stepped back.
    pub resets: u64,
}

impl DeviceClock {
    /// The window of device time over which the minimum is taken.
    pub const WINDOW_NS: u64 = 1_000_000_000;

    /// A clock with no sample yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// This computer's time (ns) of a sample stamped `device_ns` that arrived at `arrival_ns`.
    pub fn map(&mut self, device_ns: u64, arrival_ns: u64) -> u64 {
        if self.last_device.is_some_and(|d| device_ns < d) {
            let resets = self.resets + 1;
            *self = Self { resets, ..Self::default() };
        }
        self.last_device = Some(device_ns);
        let d = (arrival_ns as i128 - device_ns as i128).clamp(i64::MIN as i128, i64::MAX as i128) as i64;
        self.cur = Some(match self.cur {
            Some((start, m)) if device_ns - start < Self::WINDOW_NS => (start, m.min(d)),
            Some((start, m)) => {
                self.prev_min = Some(m);
                self.first_window.get_or_insert((start, m));
                self.last_window = Some((start, m));
                (device_ns, d)
            }
            None => (device_ns, d),
        });
        let t = (device_ns as i128 + self.offset_ns().unwrap_or(d) as i128).clamp(0, u64::MAX as i128) as u64;
        let t = if self.last_out == 0 { t } else { t.max(self.last_out + 1) };
        self.last_out = t;
        t
    }

    /// The offset in use: the smallest arrival - device of this and the previous window.
    pub fn offset_ns(&self) -> Option<i64> {
        let cur = self.cur.map(|(_, m)| m);
        match (self.prev_min, cur) {
            (Some(p), Some(c)) => Some(p.min(c)),
            (p, c) => p.or(c),
        }
    }

    /// The estimate so far (`None` before the first sample).
    pub fn estimate(&self) -> Option<ClockEstimate> {
        let offset_ns = self.offset_ns()?;
        let (drift_ppm, span_s) = match (self.first_window, self.last_window) {
            (Some((t0, m0)), Some((t1, m1))) if t1 > t0 => {
                let span = (t1 - t0) as f64;
                (Some((m1 - m0) as f64 / span * 1e6), span * 1e-9)
            }
            _ => (None, 0.0),
        };
        Some(ClockEstimate { offset_ns, drift_ppm, span_s, resets: self.resets })
    }
}

impl std::fmt::Display for ClockEstimate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "arrival - device time {:.6} s", self.offset_ns as f64 * 1e-9)?;
        match self.drift_ppm {
            Some(p) => write!(f, ", drift {p:+.1} ppm over {:.0} s", self.span_s)?,
            None => f.write_str(", drift not measured (under 2 s)")?,
        }
        if self.resets > 0 {
            write!(f, ", device time restarted {} times", self.resets)?;
        }
        Ok(())
    }
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
    fn device_clock_follows_the_smallest_delay_and_measures_drift() {
        // A device at 400 Hz whose clock runs 50 ppm slow; arrivals 3 ms (one sample in 37)
        // to 10 ms after the sample, one in 7 a further 40 ms late (a busy host).
        let offset = 1_700_000_000_000_000_000i64;
        let mut c = DeviceClock::new();
        let mut max_err = 0i64;
        let mut last = 0u64;
        for k in 0..4000u64 {
            let dev = 5_000_000_000 + k * 2_500_000;
            let true_host = (dev as f64 * (1.0 + 50e-6)) as i64 + offset;
            let jitter = if k % 37 == 0 { 0 } else { 1_000_000 + (k * 7_919 % 6_000_000) as i64 };
            let delay = 3_000_000 + jitter + if k % 7 == 3 { 40_000_000 } else { 0 };
            let t = c.map(dev, (true_host + delay) as u64);
            assert!(t > last, "mapped times increase");
            last = t;
            if k > 400 {
                // After the first window: within the smallest delay (3 ms) plus a window of drift.
                max_err = max_err.max((t as i64 - true_host - 3_000_000).abs());
            }
        }
        assert!(max_err < 200_000, "{max_err} ns");
        let e = c.estimate().unwrap();
        let drift = e.drift_ppm.unwrap();
        assert!((drift - 50.0).abs() < 3.0, "{drift} ppm");
        assert!(e.to_string().starts_with("arrival - device time "), "{e}");
        // The device restarts: its time steps back and the estimate starts afresh.
        let t = c.map(1_000_000, 1_700_000_100_000_000_000);
        assert_eq!(t, 1_700_000_100_000_000_000);
        assert_eq!(c.estimate().unwrap().resets, 1);
        assert_eq!(c.estimate().unwrap().drift_ppm, None);
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
