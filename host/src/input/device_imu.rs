//! IMU samples from a serial byte stream in any protocol `loglio live` reads
//! ([`ImuProtocol`]): loglio's own frames, Xsens MTData2, VectorNav binary output. The core's
//! streaming decoders do the framing and count what they drop; this reader adds the reads, the
//! arrival time of each sample (this computer's clock, taken when the bytes that completed it
//! were read) and the device time in nanoseconds (an Xsens's 32-bit SampleTimeFine unwrapped).

use std::io::{self, Read};

use loglio_core::sensor::{imu_frame, vectornav, xsens};

pub use crate::config::ImuProtocol;
use crate::input::udp::host_time_ns;

/// One sample as the device sent it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeviceSample {
    /// The device's time of the sample, ns: for loglio's frames already the LiDAR's clock; for
    /// Xsens and VectorNav time since the device's power-on. `None` when the device was not
    /// configured to send it.
    pub device_ns: Option<u64>,
    /// Angular rate, rad/s.
    pub gyro: [f32; 3],
    /// Specific force, m/s^2.
    pub acc: [f32; 3],
    /// This computer's time when the bytes that completed the sample were read, ns since 1970.
    pub arrival_ns: u64,
}

/// What the decoder accepted and dropped, the same for every protocol.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StreamCounts {
    /// Samples delivered.
    pub samples: u64,
    /// Samples missing by the sequence numbers (loglio's seq, Xsens PacketCounter).
    pub lost: u64,
    /// Messages or frames refused: failed checks, unreadable data, messages without both an
    /// angular rate and an acceleration, unsupported VectorNav groups.
    pub rejected: u64,
    /// Bytes that were not part of a good message or frame.
    pub dropped_bytes: u64,
}

/// Unwraps Xsens SampleTimeFine (u32 ticks of 100 us, wrapping after 4.97 days).
#[derive(Clone, Copy, Debug, Default)]
struct TickUnwrap {
    last: Option<u32>,
    wraps: u64,
}

impl TickUnwrap {
    fn ns(&mut self, ticks: u32) -> u64 {
        if let Some(last) = self.last
            && ticks < last
            && last - ticks > 1 << 31
        {
            self.wraps += 1;
        }
        self.last = Some(ticks);
        ((self.wraps << 32) + ticks as u64) * xsens::NS_PER_TICK
    }
}

#[derive(Debug)]
enum Dec {
    Loglio(imu_frame::FrameDecoder),
    Xsens(Box<xsens::Decoder>, TickUnwrap),
    VectorNav(Box<vectornav::Decoder>),
}

/// Decodes IMU samples of one protocol from a byte stream.
#[derive(Debug)]
pub struct DeviceImuReader<R: Read> {
    src: R,
    protocol: ImuProtocol,
    dec: Dec,
    buf: Box<[u8; 4096]>,
    start: usize,
    end: usize,
    eof: bool,
    read_ns: u64,
}

impl<R: Read> DeviceImuReader<R> {
    /// Wraps a byte stream carrying `protocol`.
    pub fn new(src: R, protocol: ImuProtocol) -> Self {
        let dec = match protocol {
            ImuProtocol::Loglio => Dec::Loglio(imu_frame::FrameDecoder::new()),
            ImuProtocol::Xsens => Dec::Xsens(Box::new(xsens::Decoder::new()), TickUnwrap::default()),
            ImuProtocol::Vectornav => Dec::VectorNav(Box::new(vectornav::Decoder::new())),
        };
        Self { src, protocol, dec, buf: Box::new([0; 4096]), start: 0, end: 0, eof: false, read_ns: 0 }
    }

    /// The protocol read.
    pub fn protocol(&self) -> ImuProtocol {
        self.protocol
    }

    /// What the decoder accepted and dropped so far.
    pub fn counts(&self) -> StreamCounts {
        match &self.dec {
            Dec::Loglio(d) => {
                let s = d.stats;
                StreamCounts {
                    samples: s.frames,
                    lost: s.seq_gaps,
                    rejected: s.too_long + s.cobs + s.crc + s.payload,
                    dropped_bytes: s.dropped_bytes,
                }
            }
            Dec::Xsens(d, _) => {
                let s = d.stats;
                StreamCounts {
                    samples: s.samples,
                    lost: s.counter_gaps,
                    rejected: s.checksum + s.too_long + s.bad_data + s.incomplete,
                    dropped_bytes: s.dropped_bytes,
                }
            }
            Dec::VectorNav(d) => {
                let s = d.stats;
                StreamCounts {
                    samples: s.samples,
                    lost: 0,
                    rejected: s.crc + s.unsupported + s.incomplete,
                    dropped_bytes: s.dropped_bytes,
                }
            }
        }
    }

    /// VectorNav messages refused because they select groups whose sizes are not known (a
    /// device configured with GPS, Attitude or INS outputs); 0 for the other protocols.
    pub fn unsupported_messages(&self) -> u64 {
        match &self.dec {
            Dec::VectorNav(d) => d.stats.unsupported,
            _ => 0,
        }
    }

    fn feed(&mut self) -> Option<DeviceSample> {
        let input = &self.buf[self.start..self.end];
        let (n, s) = match &mut self.dec {
            Dec::Loglio(d) => {
                let (n, f) = d.feed(input);
                (n, f.map(|f| (Some(f.t_ns), f.gyro, f.acc)))
            }
            Dec::Xsens(d, unwrap) => {
                let (n, s) = d.feed(input);
                (n, s.map(|s| (s.time_fine.map(|t| unwrap.ns(t)), s.gyro, s.acc)))
            }
            Dec::VectorNav(d) => {
                let (n, s) = d.feed(input);
                (n, s.map(|s| (s.time_startup_ns, s.gyro, s.acc)))
            }
        };
        self.start += n;
        s.map(|(device_ns, gyro, acc)| DeviceSample { device_ns, gyro, acc, arrival_ns: self.read_ns })
    }

    /// The next sample; `Ok(None)` at the end of the stream. A read timeout of a serial port
    /// comes back as an `io::ErrorKind::TimedOut` error: call again to keep waiting.
    pub fn next_sample(&mut self) -> io::Result<Option<DeviceSample>> {
        loop {
            // A decoder may hold a complete sample without consuming input (its own buffer).
            loop {
                if let Some(s) = self.feed() {
                    return Ok(Some(s));
                }
                if self.start >= self.end {
                    break;
                }
            }
            if self.eof {
                return Ok(None);
            }
            self.start = 0;
            self.end = 0;
            match self.src.read(&mut self.buf[..]) {
                Ok(0) => self.eof = true,
                Ok(n) => {
                    self.end = n;
                    self.read_ns = host_time_ns();
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An Xsens MTData2 message (float32 acceleration and rate of turn, counter, time), written
    /// from the documented layout independently of the core's parser.
    fn xsens_msg(counter: u16, ticks: u32, acc: [f32; 3], gyro: [f32; 3]) -> Vec<u8> {
        let mut d = vec![0x10, 0x20, 2];
        d.extend(counter.to_be_bytes());
        d.extend([0x10, 0x60, 4]);
        d.extend(ticks.to_be_bytes());
        d.extend([0x40, 0x20, 12]);
        d.extend(acc.iter().flat_map(|x| x.to_be_bytes()));
        d.extend([0x80, 0x20, 12]);
        d.extend(gyro.iter().flat_map(|x| x.to_be_bytes()));
        let mut m = vec![0xFA, 0xFF, 0x36, d.len() as u8];
        m.extend(d);
        let sum = m[1..].iter().fold(0u8, |s, &b| s.wrapping_add(b));
        m.push(sum.wrapping_neg());
        m
    }

    #[test]
    fn xsens_time_unwraps_and_noise_is_counted() {
        let mut stream = vec![0x01, 0xFA, 0x02];
        // Across the 32-bit wrap of SampleTimeFine.
        let ticks = [u32::MAX - 20, u32::MAX - 5, 10, 25];
        for (k, t) in ticks.iter().enumerate() {
            stream.extend(xsens_msg(k as u16, *t, [0.0, 0.0, 9.81], [0.0, 0.0, 0.1 * k as f32]));
            if k == 1 {
                stream.extend([0xFA, 0xFF, 0x36, 0x03, 0x00]); // a broken message
            }
        }
        let mut r = DeviceImuReader::new(&stream[..], ImuProtocol::Xsens);
        let mut got = Vec::new();
        while let Some(s) = r.next_sample().unwrap() {
            got.push(s);
        }
        let ns: Vec<u64> = got.iter().map(|s| s.device_ns.unwrap()).collect();
        let base = (u32::MAX as u64 - 20) * 100_000;
        assert_eq!(ns, [base, base + 1_500_000, base + 3_100_000, base + 4_600_000]);
        assert_eq!(got[3].gyro, [0.0, 0.0, 0.3]);
        assert!(got.iter().all(|s| s.arrival_ns > 0));
        let c = r.counts();
        assert_eq!((c.samples, c.lost, c.dropped_bytes), (4, 0, 3 + 5));
        assert!(c.rejected >= 1);
    }

    #[test]
    fn vectornav_and_loglio_times_pass_through() {
        // VectorNav: Common group TimeStartup, AngularRate, Accel; the CRC big-endian.
        let mut m = vec![0xFA, 0x01, 0x21, 0x01];
        m.extend(7_000_000_123u64.to_le_bytes());
        m.extend([0.5f32, 0.0, -0.5].iter().flat_map(|x| x.to_le_bytes()));
        m.extend([0.0f32, 0.0, -9.81].iter().flat_map(|x| x.to_le_bytes()));
        let crc = vectornav::crc16(&m[1..]);
        m.extend(crc.to_be_bytes());
        let stream = [&b"$VNYMR,0*00\r\n"[..], &m, &m[..10]].concat();
        let mut r = DeviceImuReader::new(&stream[..], ImuProtocol::Vectornav);
        let s = r.next_sample().unwrap().unwrap();
        assert_eq!((s.device_ns, s.gyro, s.acc), (Some(7_000_000_123), [0.5, 0.0, -0.5], [0.0, 0.0, -9.81]));
        assert_eq!(r.next_sample().unwrap(), None);
        assert_eq!((r.counts().samples, r.counts().dropped_bytes), (1, 13));
        // loglio's frame: its time is the LiDAR clock's, as it is.
        let f = imu_frame::ImuFrame { seq: 3, t_ns: 42, gyro: [1.0; 3], acc: [2.0; 3] };
        let mut buf = [0u8; imu_frame::FRAME_MAX];
        let n = imu_frame::encode(&f, &mut buf).unwrap();
        let mut r = DeviceImuReader::new(&buf[..n], ImuProtocol::Loglio);
        let s = r.next_sample().unwrap().unwrap();
        assert_eq!((s.device_ns, s.gyro, s.acc), (Some(42), [1.0; 3], [2.0; 3]));
    }
}
