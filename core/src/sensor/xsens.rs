//! Xsens MTi binary output (MTData2 messages) from a serial line.
//!
//! Layout, from Xsens' "MT Low Level Communication Protocol Documentation" (the Xbus message and
//! the MTData2 message):
//!
//! ```text
//! message:  PREAMBLE 0xFA | BID u8 (0xFF: from the device) | MID u8 | LEN u8 | DATA[LEN] | CHECKSUM u8
//! extended: PREAMBLE 0xFA | BID | MID | 0xFF | LEN u16 big-endian | DATA[LEN] | CHECKSUM
//!           checksum: BID + MID + LEN byte(s) + DATA + CHECKSUM = 0 (mod 256)
//! MTData2 (MID 0x36): DATA = packets, each  data id u16 BE | size u8 | value[size] (big-endian)
//!   data id 0xGGTF: group and type in the upper 12 bits, F the format nibble:
//!     bits 0-1 precision: 00 float32, 01 fixed point 12.20 (i32 / 2^20),
//!                         10 fixed point 16.32 (6 bytes: u32 fraction, then i16 integer part),
//!                         11 float64
//!     bits 2-3 coordinate system (ENU, NED, NWU) of the navigation outputs
//!   0x1020 PacketCounter u16      0x1060 SampleTimeFine u32 (10 kHz ticks since power-on)
//!   0x402x Acceleration 3 x m/s^2 0x802x RateOfTurn 3 x rad/s
//! ```
//!
//! Acceleration and rate of turn are the calibrated inertial data in the sensor frame (the
//! coordinate bits concern orientation, velocity and free acceleration), which is what an
//! odometry wants: the specific force including gravity and the body rate. Every other data
//! packet (orientation, DeltaV/DeltaQ, status, ...) is skipped by its size and counted.
//!
//! [`Decoder`] takes the serial byte stream in any chunking: bytes before a preamble are noise,
//! and a message that fails its checksum gives up only its preamble byte, the search going on
//! from the next 0xFA in the bytes already read, so a good message right after a corrupted one
//! (or after a stray 0xFA) is kept.

use super::sync_buf::{self, Framed, SyncBuf};

/// First byte of every message.
pub const PREAMBLE: u8 = 0xFA;
/// Bus identifier of the messages a device sends.
pub const BID_MASTER: u8 = 0xFF;
/// Message identifier of MTData2.
pub const MID_MTDATA2: u8 = 0x36;
/// Largest data field accepted. The protocol's extended length allows 65535, but Xsens devices
/// send at most 2048 bytes of data; a larger length is noise that happened to look like a header.
pub const MAX_DATA: usize = 2048;
/// Largest message: extended header (6 bytes), data, checksum.
pub const MAX_MESSAGE: usize = 6 + MAX_DATA + 1;
/// SampleTimeFine ticks per second.
pub const TICKS_PER_SECOND: u64 = 10_000;
/// Nanoseconds per SampleTimeFine tick.
pub const NS_PER_TICK: u64 = 1_000_000_000 / TICKS_PER_SECOND;

/// Data ids (format nibble 0).
pub const XDI_PACKET_COUNTER: u16 = 0x1020;
/// SampleTimeFine.
pub const XDI_SAMPLE_TIME_FINE: u16 = 0x1060;
/// Acceleration (calibrated, sensor frame).
pub const XDI_ACCELERATION: u16 = 0x4020;
/// Rate of turn (calibrated, sensor frame).
pub const XDI_RATE_OF_TURN: u16 = 0x8020;

/// Why bytes starting with a preamble are not a message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum MessageError {
    /// Fewer bytes than the header's length says: wait for more.
    Incomplete,
    /// The first byte is not the preamble.
    NoPreamble,
    /// The length exceeds [`MAX_DATA`].
    TooLong,
    /// The checksum does not add up: the bytes were corrupted (or were never a message).
    Checksum,
}

impl core::fmt::Display for MessageError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Incomplete => "Xsens message incomplete",
            Self::NoPreamble => "Xsens message does not start with the preamble 0xFA",
            Self::TooLong => "Xsens message longer than 2048 data bytes",
            Self::Checksum => "Xsens message checksum mismatch",
        })
    }
}

impl core::error::Error for MessageError {}

/// Why an MTData2 message's data could not be read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DataError {
    /// A data packet's header or value runs past the end of the message.
    Truncated,
    /// A known data packet has a size its format does not have.
    BadSize,
    /// A value is NaN or infinite.
    NotFinite,
}

impl core::fmt::Display for DataError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Truncated => "MTData2 data packet runs past the end of the message",
            Self::BadSize => "MTData2 data packet has the wrong size for its data id",
            Self::NotFinite => "MTData2 value is not finite",
        })
    }
}

impl core::error::Error for DataError {}

/// One Xbus message, borrowed from the bytes it was parsed from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Message<'a> {
    /// Bus identifier (0xFF from a device).
    pub bid: u8,
    /// Message identifier.
    pub mid: u8,
    /// The data field.
    pub data: &'a [u8],
}

/// Parses the message at the start of `bytes`: the message and its length on the wire.
pub fn parse_message(bytes: &[u8]) -> Result<(Message<'_>, usize), MessageError> {
    let (&first, _) = bytes.split_first().ok_or(MessageError::Incomplete)?;
    if first != PREAMBLE {
        return Err(MessageError::NoPreamble);
    }
    let (header, len) = match bytes.get(3) {
        None => return Err(MessageError::Incomplete),
        Some(0xFF) => match bytes.get(4..6) {
            None => return Err(MessageError::Incomplete),
            Some(l) => (6, u16::from_be_bytes([l[0], l[1]]) as usize),
        },
        Some(&l) => (4, l as usize),
    };
    if len > MAX_DATA {
        return Err(MessageError::TooLong);
    }
    let total = header + len + 1;
    let msg = bytes.get(..total).ok_or(MessageError::Incomplete)?;
    if msg[1..].iter().fold(0u8, |s, &b| s.wrapping_add(b)) != 0 {
        return Err(MessageError::Checksum);
    }
    Ok((Message { bid: msg[1], mid: msg[2], data: &msg[header..total - 1] }, total))
}

/// The checksum byte that makes `bid`, `mid`, the length byte(s) and `data` add up to 0.
pub fn checksum(after_preamble: &[u8]) -> u8 {
    after_preamble.iter().fold(0u8, |s, &b| s.wrapping_sub(b))
}

/// What an MTData2 message says that LIO uses.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MtData2 {
    /// PacketCounter: +1 per message (wrapping); a gap means messages were lost.
    pub counter: Option<u16>,
    /// SampleTimeFine: ticks of 100 us since power-on (wraps after 4.97 days).
    pub time_fine: Option<u32>,
    /// Acceleration (specific force), m/s^2.
    pub acc: Option<[f32; 3]>,
    /// Rate of turn, rad/s.
    pub gyro: Option<[f32; 3]>,
    /// Data packets skipped (other data, DeltaV/DeltaQ, status, ...).
    pub unknown: u16,
}

/// A 3-vector in the precision `format & 3` selects.
fn vec3(format: u16, v: &[u8]) -> Result<[f32; 3], DataError> {
    let be4 = |b: &[u8]| [b[0], b[1], b[2], b[3]];
    let width = match format & 3 {
        0 | 1 => 4,
        2 => 6,
        _ => 8,
    };
    if v.len() != 3 * width {
        return Err(DataError::BadSize);
    }
    let mut out = [0f32; 3];
    for (o, b) in out.iter_mut().zip(v.chunks_exact(width)) {
        *o = match format & 3 {
            0 => f32::from_be_bytes(be4(b)),
            1 => (i32::from_be_bytes(be4(b)) as f64 / (1u64 << 20) as f64) as f32,
            2 => {
                // 16.32 fixed point: the fraction (u32) first, then the signed integer part (i16).
                let frac = u32::from_be_bytes(be4(b)) as i64;
                let int = i16::from_be_bytes([b[4], b[5]]) as i64;
                (((int << 32) | frac) as f64 / (1u64 << 32) as f64) as f32
            }
            _ => f64::from_be_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32,
        };
    }
    if out.iter().all(|x| x.is_finite()) { Ok(out) } else { Err(DataError::NotFinite) }
}

impl MtData2 {
    /// Reads the data packets of an MTData2 message's data field.
    pub fn parse(mut data: &[u8]) -> Result<Self, DataError> {
        let mut m = MtData2::default();
        while !data.is_empty() {
            let [h, l, size, ..] = *data else { return Err(DataError::Truncated) };
            let id = u16::from_be_bytes([h, l]);
            let value = data.get(3..3 + size as usize).ok_or(DataError::Truncated)?;
            data = &data[3 + size as usize..];
            match id & 0xFFF0 {
                XDI_PACKET_COUNTER => {
                    let [a, b] = *value else { return Err(DataError::BadSize) };
                    m.counter = Some(u16::from_be_bytes([a, b]));
                }
                XDI_SAMPLE_TIME_FINE => {
                    let [a, b, c, d] = *value else { return Err(DataError::BadSize) };
                    m.time_fine = Some(u32::from_be_bytes([a, b, c, d]));
                }
                XDI_ACCELERATION => m.acc = Some(vec3(id, value)?),
                XDI_RATE_OF_TURN => m.gyro = Some(vec3(id, value)?),
                _ => m.unknown = m.unknown.saturating_add(1),
            }
        }
        Ok(m)
    }
}

/// One inertial sample of an MTData2 message that has both acceleration and rate of turn.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct XsensSample {
    /// PacketCounter, when configured.
    pub counter: Option<u16>,
    /// SampleTimeFine (100 us ticks), when configured.
    pub time_fine: Option<u32>,
    /// Rate of turn, rad/s.
    pub gyro: [f32; 3],
    /// Acceleration, m/s^2.
    pub acc: [f32; 3],
}

/// Counts of what a [`Decoder`] accepted and dropped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct XsensStats {
    /// Samples delivered.
    pub samples: u64,
    /// Candidate messages whose checksum failed.
    pub checksum: u64,
    /// Candidate messages with a length beyond [`MAX_DATA`].
    pub too_long: u64,
    /// MTData2 messages whose data packets are broken ([`DataError`]).
    pub bad_data: u64,
    /// MTData2 messages without acceleration or without rate of turn.
    pub incomplete: u64,
    /// Good messages that are not MTData2 (acknowledgements, errors, wake-up).
    pub other_messages: u64,
    /// Data packets skipped as not used.
    pub unknown_items: u64,
    /// Messages missing according to the PacketCounter.
    pub counter_gaps: u64,
    /// Bytes that were not part of a good message.
    pub dropped_bytes: u64,
}

/// A streaming decoder: feed it the serial bytes in any chunking and it yields samples.
#[derive(Debug)]
pub struct Decoder {
    buf: SyncBuf<MAX_MESSAGE>,
    last_counter: Option<u16>,
    /// What was accepted and dropped so far.
    pub stats: XsensStats,
}

impl Framed for Decoder {
    type Sample = XsensSample;

    fn push(&mut self, b: u8) -> bool {
        self.buf.push(b)
    }

    fn poll(&mut self) -> Option<XsensSample> {
        self.decide()
    }

    fn give_up_candidate(&mut self) {
        self.stats.dropped_bytes += self.buf.skip_to_sync(PREAMBLE, 1) as u64;
    }
}

impl Default for Decoder {
    fn default() -> Self {
        Self::new()
    }
}

impl Decoder {
    /// A decoder waiting for the first preamble.
    pub const fn new() -> Self {
        Self {
            buf: SyncBuf::new(),
            last_counter: None,
            stats: XsensStats {
                samples: 0,
                checksum: 0,
                too_long: 0,
                bad_data: 0,
                incomplete: 0,
                other_messages: 0,
                unknown_items: 0,
                counter_gaps: 0,
                dropped_bytes: 0,
            },
        }
    }

    /// Consumes bytes from `input` until a sample is complete. Returns the number of bytes
    /// consumed (possibly 0 when a sample was already buffered) and the sample, if any. Call
    /// it again with the rest of the input until everything is consumed and no sample comes.
    pub fn feed(&mut self, input: &[u8]) -> (usize, Option<XsensSample>) {
        sync_buf::feed(self, input)
    }

    /// Decides the buffered candidates until one needs more bytes or yields a sample.
    fn decide(&mut self) -> Option<XsensSample> {
        loop {
            self.stats.dropped_bytes += self.buf.skip_to_sync(PREAMBLE, 0) as u64;
            let (parsed, len) = match parse_message(self.buf.bytes()) {
                Err(MessageError::Incomplete) | Err(MessageError::NoPreamble) => return None,
                Err(e) => {
                    match e {
                        MessageError::TooLong => self.stats.too_long += 1,
                        _ => self.stats.checksum += 1,
                    }
                    self.give_up_candidate();
                    continue;
                }
                Ok((m, len)) if m.bid == BID_MASTER && m.mid == MID_MTDATA2 => {
                    (Some(MtData2::parse(m.data)), len)
                }
                Ok((_, len)) => (None, len),
            };
            self.buf.drop_front(len);
            match parsed {
                None => self.stats.other_messages += 1,
                Some(Err(e)) => {
                    debug!("xsens MTData2 dropped: {}", e);
                    self.stats.bad_data += 1;
                }
                Some(Ok(m)) => {
                    self.stats.unknown_items += m.unknown as u64;
                    if let Some(c) = m.counter {
                        if let Some(prev) = self.last_counter {
                            let gap = c.wrapping_sub(prev).wrapping_sub(1);
                            // A huge "gap" is a reordering or a device reset.
                            if gap != 0 && gap < 1 << 15 {
                                self.stats.counter_gaps += gap as u64;
                            }
                        }
                        self.last_counter = Some(c);
                    }
                    match (m.acc, m.gyro) {
                        (Some(acc), Some(gyro)) => {
                            self.stats.samples += 1;
                            return Some(XsensSample {
                                counter: m.counter,
                                time_fine: m.time_fine,
                                gyro,
                                acc,
                            });
                        }
                        _ => self.stats.incomplete += 1,
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec::Vec;

    use super::*;

    /// An MTData2 message with `packets` (id, value bytes), built by hand from the documented
    /// layout: the standard or the extended length, the checksum that makes the sum 0.
    fn message(mid: u8, packets: &[(u16, Vec<u8>)]) -> Vec<u8> {
        let mut data = Vec::new();
        for (id, v) in packets {
            data.extend_from_slice(&id.to_be_bytes());
            data.push(v.len() as u8);
            data.extend_from_slice(v);
        }
        let mut m = std::vec![PREAMBLE, BID_MASTER, mid];
        if data.len() < 0xFF {
            m.push(data.len() as u8);
        } else {
            m.push(0xFF);
            m.extend_from_slice(&(data.len() as u16).to_be_bytes());
        }
        m.extend_from_slice(&data);
        let cs = checksum(&m[1..]);
        m.push(cs);
        m
    }

    fn f32s(v: [f32; 3]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_be_bytes()).collect()
    }

    fn f64s(v: [f64; 3]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_be_bytes()).collect()
    }

    fn imu_message(counter: u16, fine: u32, acc: [f32; 3], gyro: [f32; 3]) -> Vec<u8> {
        message(
            MID_MTDATA2,
            &[
                (XDI_PACKET_COUNTER, counter.to_be_bytes().to_vec()),
                (XDI_SAMPLE_TIME_FINE, fine.to_be_bytes().to_vec()),
                (XDI_ACCELERATION, f32s(acc)),
                (XDI_RATE_OF_TURN, f32s(gyro)),
            ],
        )
    }

    fn decode_all(dec: &mut Decoder, mut bytes: &[u8], out: &mut Vec<XsensSample>) {
        loop {
            let (n, s) = dec.feed(bytes);
            bytes = &bytes[n..];
            match s {
                Some(s) => out.push(s),
                None if bytes.is_empty() => return,
                None => {}
            }
        }
    }

    #[test]
    fn checksum_of_the_documented_config_messages() {
        // GoToConfig and GoToMeasurement as the protocol documentation lists them.
        for m in [[0xFA, 0xFF, 0x30, 0x00, 0xD1], [0xFA, 0xFF, 0x10, 0x00, 0xF1]] {
            let (msg, n) = parse_message(&m).unwrap();
            assert_eq!((msg.bid, msg.mid, msg.data.len(), n), (0xFF, m[2], 0, 5));
            assert_eq!(checksum(&m[1..4]), m[4]);
        }
        assert_eq!(parse_message(&[0xFA, 0xFF, 0x30, 0x00, 0xD2]), Err(MessageError::Checksum));
        assert_eq!(parse_message(&[0xFA, 0xFF, 0x30]), Err(MessageError::Incomplete));
        assert_eq!(parse_message(&[0xFB]), Err(MessageError::NoPreamble));
        assert_eq!(parse_message(&[0xFA, 0xFF, 0x36, 0xFF, 0x08, 0x01]), Err(MessageError::TooLong));
    }

    #[test]
    fn float32_message_decodes_exactly() {
        // Bytes written out: counter 0x1234, time 123456789 ticks, acc (0.5, -1.25, 9.75),
        // gyro (0.125, 0, -2.5).
        let m = imu_message(0x1234, 123_456_789, [0.5, -1.25, 9.75], [0.125, 0.0, -2.5]);
        assert_eq!(&m[..4], &[0xFA, 0xFF, 0x36, 5 + 7 + 15 + 15]);
        assert_eq!(&m[4..9], &[0x10, 0x20, 0x02, 0x12, 0x34]);
        assert_eq!(&m[9..16], &[0x10, 0x60, 0x04, 0x07, 0x5B, 0xCD, 0x15]);
        assert_eq!(&m[16..22], &[0x40, 0x20, 0x0C, 0x3F, 0x00, 0x00]); // 0.5f32 = 0x3F000000
        let (msg, n) = parse_message(&m).unwrap();
        assert_eq!(n, m.len());
        let d = MtData2::parse(msg.data).unwrap();
        assert_eq!(d.counter, Some(0x1234));
        assert_eq!(d.time_fine, Some(123_456_789));
        assert_eq!(d.acc, Some([0.5, -1.25, 9.75]));
        assert_eq!(d.gyro, Some([0.125, 0.0, -2.5]));
        assert_eq!(d.unknown, 0);
    }

    #[test]
    fn float64_and_fixed_point_formats() {
        let acc = [0.5f64, -1.25, 9.806_65];
        let fp1220 = |x: f64| ((x * (1u64 << 20) as f64).round() as i32).to_be_bytes();
        let fp1632 = |x: f64| {
            let v = (x * (1u64 << 32) as f64).round() as i64;
            let mut b = (v as u32).to_be_bytes().to_vec();
            b.extend_from_slice(&((v >> 32) as i16).to_be_bytes());
            b
        };
        for (fmt, bytes) in [
            (3u16, f64s(acc)),
            (1, acc.iter().flat_map(|&x| fp1220(x)).collect()),
            (2, acc.iter().flat_map(|&x| fp1632(x)).collect()),
        ] {
            let m = message(
                MID_MTDATA2,
                &[(XDI_ACCELERATION | fmt, bytes.clone()), (XDI_RATE_OF_TURN | fmt, bytes)],
            );
            let d = MtData2::parse(parse_message(&m).unwrap().0.data).unwrap();
            let want = acc.map(|x| x as f32);
            let got = d.acc.unwrap();
            // float64 converts exactly to the nearest f32; 12.20 is within 2^-21.
            let tol = if fmt == 1 { 1e-6 } else { 0.0 };
            for (g, w) in got.iter().zip(want) {
                assert!((g - w).abs() <= tol, "format {fmt}: {got:?}");
            }
            assert_eq!(d.gyro, d.acc);
        }
        // -1.5 in 16.32: integer part -2, fraction 0.5.
        let m = message(
            MID_MTDATA2,
            &[
                (XDI_ACCELERATION | 2, [0x80, 0, 0, 0, 0xFF, 0xFE].repeat(3)),
                (XDI_RATE_OF_TURN, f32s([0.0; 3])),
            ],
        );
        assert_eq!(MtData2::parse(parse_message(&m).unwrap().0.data).unwrap().acc, Some([-1.5; 3]));
        // The coordinate bits (ENU/NED/NWU) do not change the sensor-frame inertial data.
        let m = message(MID_MTDATA2, &[(XDI_ACCELERATION | 0x4, f32s([1.0, 2.0, 3.0]))]);
        assert_eq!(MtData2::parse(parse_message(&m).unwrap().0.data).unwrap().acc, Some([1.0, 2.0, 3.0]));
    }

    #[test]
    fn broken_data_packets_are_clear_errors() {
        let data = |p: &[(u16, Vec<u8>)]| {
            let m = message(MID_MTDATA2, p);
            MtData2::parse(parse_message(&m).unwrap().0.data)
        };
        assert_eq!(data(&[(XDI_ACCELERATION, std::vec![0; 11])]), Err(DataError::BadSize));
        assert_eq!(data(&[(XDI_ACCELERATION | 3, std::vec![0; 12])]), Err(DataError::BadSize));
        assert_eq!(data(&[(XDI_PACKET_COUNTER, std::vec![0; 4])]), Err(DataError::BadSize));
        assert_eq!(data(&[(XDI_RATE_OF_TURN, f32s([0.0, f32::NAN, 0.0]))]), Err(DataError::NotFinite));
        assert_eq!(MtData2::parse(&[0x40, 0x20]), Err(DataError::Truncated));
        assert_eq!(MtData2::parse(&[0x40, 0x20, 0x0C, 0, 0]), Err(DataError::Truncated));
        // Unknown ids (orientation quaternion, DeltaV, status word) are skipped by their size.
        let d = data(&[
            (0x2010, std::vec![0; 16]),
            (0x4010, std::vec![0; 12]),
            (0xE020, std::vec![0; 4]),
            (XDI_RATE_OF_TURN, f32s([1.0; 3])),
        ])
        .unwrap();
        assert_eq!((d.unknown, d.gyro, d.acc), (3, Some([1.0; 3]), None));
    }

    #[test]
    fn extended_length_message() {
        // Enough skipped data (orientation matrices) to need the 2-byte length.
        let mut packets: Vec<(u16, Vec<u8>)> = (0..8).map(|_| (0x2020u16, std::vec![0x11; 36])).collect();
        packets.push((XDI_ACCELERATION, f32s([1.0, 2.0, 3.0])));
        packets.push((XDI_RATE_OF_TURN, f32s([4.0, 5.0, 6.0])));
        let m = message(MID_MTDATA2, &packets);
        assert_eq!(m[3], 0xFF);
        assert_eq!(u16::from_be_bytes([m[4], m[5]]) as usize, m.len() - 7);
        let mut dec = Decoder::new();
        let mut got = Vec::new();
        decode_all(&mut dec, &m, &mut got);
        assert_eq!(got.len(), 1);
        assert_eq!((got[0].acc, got[0].gyro), ([1.0, 2.0, 3.0], [4.0, 5.0, 6.0]));
        assert_eq!(dec.stats.unknown_items, 8);
    }

    #[test]
    fn stream_with_noise_resynchronises_and_counts() {
        let sample = |k: u16| (k, k as u32 * 25, [0.01 * k as f32, 0.0, 9.81], [0.0, -0.001 * k as f32, 0.5]);
        let mut stream = std::vec![0x00, 0x13, 0xFA, 0x42]; // noise, with a stray preamble
        let mut noise = 4;
        for k in 0..40u16 {
            let (c, t, a, g) = sample(k);
            let mut m = imu_message(c, t, a, g);
            match k {
                5 => {
                    // Noise that looks like the start of a long message right before a good one.
                    stream.extend_from_slice(&[0xFA, 0xFF, 0x36, 0x40]);
                    noise += 4;
                }
                9 => m[12] ^= 0x10, // corrupted: checksum fails, counter gap of 1
                13 => {
                    stream.extend_from_slice(&m[..20]); // cut short: its tail never comes
                    noise += 20;
                    continue;
                }
                // A wake-up message: good, not MTData2, not noise.
                17 => stream.extend_from_slice(&message(0x3E, &[])),
                _ => {}
            }
            if k == 9 {
                noise += m.len();
            }
            stream.extend_from_slice(&m);
        }
        stream.extend_from_slice(&message(MID_MTDATA2, &[(XDI_ACCELERATION, f32s([0.0; 3]))]));
        for chunk in [1usize, 3, 64, 4096] {
            let mut dec = Decoder::new();
            let mut got = Vec::new();
            for c in stream.chunks(chunk) {
                decode_all(&mut dec, c, &mut got);
            }
            let counters: Vec<u16> = got.iter().map(|s| s.counter.unwrap()).collect();
            let want: Vec<u16> = (0..40).filter(|k| *k != 9 && *k != 13).collect();
            assert_eq!(counters, want, "chunk {chunk}");
            for s in &got {
                let (c, t, a, g) = sample(s.counter.unwrap());
                assert_eq!((s.counter, s.time_fine, s.acc, s.gyro), (Some(c), Some(t), a, g));
            }
            let st = dec.stats;
            assert_eq!(st.samples, 38);
            assert_eq!(st.counter_gaps, 2);
            assert_eq!(st.other_messages, 1);
            assert_eq!(st.incomplete, 1);
            assert!(st.checksum >= 2, "{st:?}");
            assert_eq!(st.dropped_bytes, noise as u64, "{st:?}");
        }
    }

    proptest::proptest! {
        /// Any bytes in any chunking: no panic, every sample finite, no byte counted twice.
        #[test]
        fn arbitrary_bytes_are_safe(bytes in proptest::collection::vec(proptest::prelude::any::<u8>(), 0..3000), chunk in 1usize..80) {
            let mut dec = Decoder::new();
            let mut got = Vec::new();
            for c in bytes.chunks(chunk) {
                decode_all(&mut dec, c, &mut got);
            }
            proptest::prop_assert!(got.iter().all(|s| s.acc.iter().chain(s.gyro.iter()).all(|v| v.is_finite())));
            proptest::prop_assert!(dec.stats.dropped_bytes <= bytes.len() as u64);
            proptest::prop_assert_eq!(dec.stats.samples, got.len() as u64);
        }

        /// Good messages with noise (without the preamble) before each: every message is
        /// recovered in order and exactly the noise is counted as dropped.
        #[test]
        fn messages_behind_noise_are_all_recovered(
            noise in proptest::collection::vec(proptest::collection::vec(0u8..0xFA, 0..40), 1..30),
            chunk in 1usize..80,
        ) {
            let mut stream = Vec::new();
            for (k, n) in noise.iter().enumerate() {
                stream.extend_from_slice(n);
                stream.extend(imu_message(k as u16, k as u32 * 50, [k as f32, 0.0, 9.81], [0.0, 0.5, k as f32]));
            }
            let mut dec = Decoder::new();
            let mut got = Vec::new();
            for c in stream.chunks(chunk) {
                decode_all(&mut dec, c, &mut got);
            }
            let counters: Vec<u16> = got.iter().map(|s| s.counter.unwrap_or(u16::MAX)).collect();
            proptest::prop_assert_eq!(counters, (0..noise.len() as u16).collect::<Vec<_>>());
            let noise_bytes: usize = noise.iter().map(Vec::len).sum();
            proptest::prop_assert_eq!(dec.stats.dropped_bytes, noise_bytes as u64);
        }
    }
}
