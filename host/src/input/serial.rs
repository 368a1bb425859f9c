//! loglio's serial IMU frames from a UART (the serialport crate, default features off so the
//! host cross-builds for aarch64 without libudev), or from any byte stream (a file, a pipe, a
//! test buffer). Noise and partial frames between good frames cost only themselves: the core's
//! [`FrameDecoder`] resynchronises at the next delimiter and counts what it dropped.

use loglio_core::sensor::imu_frame::{DecoderStats, FrameDecoder, ImuFrame};
use std::io::{self, Read};
use std::time::Duration;

/// Opens a serial port at `baud`, 8N1, with a read timeout.
pub fn open(
    path: &str,
    baud: u32,
    timeout: Duration,
) -> Result<Box<dyn serialport::SerialPort>, serialport::Error> {
    serialport::new(path, baud)
        .data_bits(serialport::DataBits::Eight)
        .parity(serialport::Parity::None)
        .stop_bits(serialport::StopBits::One)
        .flow_control(serialport::FlowControl::None)
        .timeout(timeout)
        .open()
}

/// Serial ports the system lists (by sysfs; no libudev).
pub fn ports() -> Vec<String> {
    serialport::available_ports().map(|v| v.into_iter().map(|p| p.port_name).collect()).unwrap_or_default()
}

/// Decodes IMU frames from a byte stream.
#[derive(Debug)]
pub struct ImuFrameReader<R: Read> {
    src: R,
    dec: FrameDecoder,
    buf: Box<[u8; 4096]>,
    start: usize,
    end: usize,
    eof: bool,
}

impl<R: Read> ImuFrameReader<R> {
    /// Wraps a byte stream.
    pub fn new(src: R) -> Self {
        Self { src, dec: FrameDecoder::new(), buf: Box::new([0; 4096]), start: 0, end: 0, eof: false }
    }

    /// What the decoder accepted and dropped so far.
    pub fn stats(&self) -> DecoderStats {
        self.dec.stats
    }

    /// The next good frame; `Ok(None)` at the end of the stream. A read timeout of a serial
    /// port comes back as an `io::ErrorKind::TimedOut` error: call again to keep waiting.
    pub fn next_frame(&mut self) -> io::Result<Option<ImuFrame>> {
        loop {
            while self.start < self.end {
                let (n, frame) = self.dec.feed(&self.buf[self.start..self.end]);
                self.start += n;
                if let Some(f) = frame {
                    return Ok(Some(f));
                }
            }
            if self.eof {
                return Ok(None);
            }
            self.start = 0;
            self.end = 0;
            match self.src.read(&mut self.buf[..]) {
                Ok(0) => self.eof = true,
                Ok(n) => self.end = n,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
    }
}

impl<R: Read> Iterator for ImuFrameReader<R> {
    type Item = io::Result<ImuFrame>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_frame().transpose()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use loglio_core::sensor::imu_frame::{FRAME_MAX, encode};

    /// A reader that hands out at most `k` bytes per read and times out once in a while.
    struct Dribble {
        data: Vec<u8>,
        at: usize,
        k: usize,
        calls: usize,
    }

    impl Read for Dribble {
        fn read(&mut self, out: &mut [u8]) -> io::Result<usize> {
            self.calls += 1;
            if self.calls.is_multiple_of(5) {
                return Err(io::Error::new(io::ErrorKind::TimedOut, "no data yet"));
            }
            let n = self.k.min(out.len()).min(self.data.len() - self.at);
            out[..n].copy_from_slice(&self.data[self.at..self.at + n]);
            self.at += n;
            Ok(n)
        }
    }

    #[test]
    fn frames_survive_noise_chunking_and_timeouts() {
        let mut stream = vec![0x55, 0x13, 0x00, 0xFF];
        let mut buf = [0u8; FRAME_MAX];
        for seq in 0..50u32 {
            let f = ImuFrame {
                seq,
                t_ns: 1_000 + seq as u64 * 5_000_000,
                gyro: [0.1, 0.2, 0.3],
                acc: [0.0, 0.0, 9.81],
            };
            let n = encode(&f, &mut buf).unwrap();
            if seq == 20 {
                stream.extend_from_slice(&buf[..n - 5]); // cut short, no delimiter
                stream.extend_from_slice(&[0x77; 9]);
                stream.push(0);
                continue;
            }
            stream.extend_from_slice(&buf[..n]);
            if seq % 7 == 0 {
                stream.extend_from_slice(&[0xEE, 0x01, 0x00]); // line noise with a stray delimiter
            }
        }
        let mut r = ImuFrameReader::new(Dribble { data: stream, at: 0, k: 3, calls: 0 });
        let mut seqs = Vec::new();
        let mut timeouts = 0;
        loop {
            match r.next_frame() {
                Ok(Some(f)) => seqs.push(f.seq),
                Ok(None) => break,
                Err(e) if e.kind() == io::ErrorKind::TimedOut => timeouts += 1,
                Err(e) => panic!("{e}"),
            }
        }
        let want: Vec<u32> = (0..50).filter(|s| *s != 20).collect();
        assert_eq!(seqs, want);
        assert!(timeouts > 0);
        let st = r.stats();
        assert_eq!(st.frames, 49);
        assert_eq!(st.seq_gaps, 1);
        assert!(st.dropped_bytes > 0);
    }
}
