//! Pacing a source by its data's times, for a replay in real time (or `rate` times it).

use std::time::{Duration, Instant};

/// Paces a replay at `rate` times real time by the packets' capture times.
///
/// A capture time that steps back, or more than [`Pacer::MAX_STEP_NS`] past the previous one
/// (a pause in the capture, or a damaged record), starts the pacing afresh from that packet
/// instead of waiting out the step: one record stamped days ahead stalled the replay for days.
#[derive(Debug)]
pub struct Pacer {
    rate: f64,
    /// Capture time and wall time of the packet the pacing counts from.
    anchor: Option<(u64, Instant)>,
    prev_ns: u64,
}

impl Pacer {
    const MAX_STEP_NS: u64 = 1_000_000_000;

    /// Pacing at `rate` times real time.
    pub fn new(rate: f64) -> Self {
        Pacer { rate, anchor: None, prev_ns: 0 }
    }

    /// Sleeps until data stamped `ts_ns` is due. Stamps a little behind the latest (the
    /// interleaved IMU samples and scans of one source) count as the latest, not as a step back.
    pub fn wait_for(&mut self, ts_ns: u64) {
        let ts = if ts_ns < self.prev_ns && self.prev_ns - ts_ns < Self::MAX_STEP_NS {
            self.prev_ns
        } else {
            ts_ns
        };
        if let Some(d) = self.wait(ts, Instant::now()) {
            std::thread::sleep(d);
        }
    }

    /// How long to sleep (from `now`) before the packet captured at `ts_ns` is due.
    pub(crate) fn wait(&mut self, ts_ns: u64, now: Instant) -> Option<Duration> {
        let step_ok = ts_ns >= self.prev_ns && ts_ns - self.prev_ns <= Self::MAX_STEP_NS;
        self.prev_ns = ts_ns;
        let (t0, w0) = match self.anchor {
            Some(a) if step_ok => a,
            _ => {
                self.anchor = Some((ts_ns, now));
                return None;
            }
        };
        // A tiny rate asks for a very long wait, not a panic on overflow.
        let due =
            Duration::try_from_secs_f64((ts_ns - t0) as f64 * 1e-9 / self.rate).unwrap_or(Duration::MAX);
        due.checked_sub(now.saturating_duration_since(w0)).filter(|d| !d.is_zero())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Wall times are given, not read: the pacing's arithmetic, not the machine's clock.
    #[test]
    fn pacing_follows_capture_times_and_restarts_at_steps() {
        let w = Instant::now();
        let ms = Duration::from_millis;
        let mut p = Pacer::new(2.0);
        let t0 = 1_700_000_000_000_000_000u64;
        assert_eq!(p.wait(t0, w), None);
        // 100 ms of capture at twice real time: due 50 ms after the first packet.
        assert_eq!(p.wait(t0 + 100_000_000, w + ms(10)), Some(ms(40)));
        // Late already: no wait.
        assert_eq!(p.wait(t0 + 200_000_000, w + ms(120)), None);
        // A record stamped ten days ahead: no ten-day sleep, the pacing restarts from it...
        let far = t0 + 864_000_000_000_000;
        assert_eq!(p.wait(far, w + ms(130)), None);
        // ...and again from the next good packet, which steps back.
        assert_eq!(p.wait(t0 + 300_000_000, w + ms(131)), None);
        assert_eq!(p.wait(t0 + 400_000_000, w + ms(141)), Some(ms(40)));
        // A pause of 5 s in the capture is not replayed either.
        assert_eq!(p.wait(t0 + 5_400_000_000, w + ms(200)), None);
        assert_eq!(p.wait(t0 + 5_420_000_000, w + ms(200)), Some(ms(10)));
        // The smallest rate the command accepts: a very long wait, no overflow.
        let mut slow = Pacer::new(f64::MIN_POSITIVE);
        assert_eq!(slow.wait(t0, w), None);
        assert_eq!(slow.wait(t0 + 1, w), Some(Duration::MAX));
    }
}
