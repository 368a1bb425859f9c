//! VectorNav (VN-100, VN-200, VN-300) binary output messages from a serial line.
//!
//! Layout, from the VectorNav user manuals ("Binary Output" / "Binary Group" sections):
//!
//! ```text
//! SYNC 0xFA | GROUPS u8 | one FIELDS u16 per bit set in GROUPS, little-endian, in bit order
//!           | PAYLOAD: the fields of each group, groups in bit order, fields in bit order,
//!             little-endian | CRC u16 big-endian
//! CRC-16-CCITT (polynomial 0x1021, initial value 0, as XModem) over GROUPS .. PAYLOAD;
//! over GROUPS .. CRC it is 0.
//! ```
//!
//! The payload carries no lengths: a receiver must know every selected field's size to find the
//! next field and the CRC. The sizes of the Common (group bit 0), Time (bit 1) and IMU (bit 2)
//! groups are tabled here; a message selecting a field of another group (GPS, Attitude, INS,
//! GPS2: their sizes differ between products and firmware) is rejected as
//! [`MessageError::Unsupported`], so a misconfigured output is a count that says so, never a
//! misread. Used: TimeStartup (u64 ns since power-on), AngularRate (3 x f32, rad/s, compensated,
//! body frame) and Accel (3 x f32, m/s^2, compensated specific force, body frame: a level
//! sensor at rest reads z = -9.8 with the body z axis down), from the Common group or the
//! Time/IMU groups; the uncompensated IMU outputs when the compensated ones are absent.
//!
//! [`Decoder`] takes the byte stream in any chunking; a candidate that fails its CRC gives up
//! only its sync byte, the search going on from the next 0xFA already read.

use super::sync_buf::{self, Framed, SyncBuf};

/// First byte of every binary message.
pub const SYNC: u8 = 0xFA;
/// Field sizes of the Common group, by field bit: TimeStartup, TimeGps, TimeSyncIn,
/// YawPitchRoll, Quaternion, AngularRate, Position, Velocity, Accel, Imu, MagPres, DeltaTheta,
/// InsStatus, SyncInCnt, TimeGpsPps; bit 15 is not a field.
pub const COMMON_SIZES: [u8; 16] = [8, 8, 8, 12, 16, 12, 24, 12, 12, 24, 20, 28, 2, 4, 8, 0];
/// Field sizes of the Time group: TimeStartup, TimeGps, GpsTow, GpsWeek, TimeSyncIn,
/// TimeGpsPps, TimeUTC, SyncInCnt, SyncOutCnt, TimeStatus.
pub const TIME_SIZES: [u8; 16] = [8, 8, 8, 2, 8, 8, 8, 4, 4, 1, 0, 0, 0, 0, 0, 0];
/// Field sizes of the IMU group: ImuStatus, UncompMag, UncompAccel, UncompGyro, Temp, Pres,
/// DeltaTheta, DeltaVel, Mag, Accel, AngularRate.
pub const IMU_SIZES: [u8; 16] = [2, 12, 12, 12, 4, 4, 16, 12, 12, 12, 12, 0, 0, 0, 0, 0];
/// Largest message with the tabled groups: sync, groups, 3 field words, every field, CRC.
pub const MAX_MESSAGE: usize = 512;

/// Common group fields used.
const COMMON_TIME_STARTUP: usize = 0;
const COMMON_ANGULAR_RATE: usize = 5;
const COMMON_ACCEL: usize = 8;
const COMMON_IMU: usize = 9;
/// Time group field used.
const TIME_TIME_STARTUP: usize = 0;
/// IMU group fields used.
const IMU_UNCOMP_ACCEL: usize = 2;
const IMU_UNCOMP_GYRO: usize = 3;
const IMU_ACCEL: usize = 9;
const IMU_ANGULAR_RATE: usize = 10;

/// CRC-16-CCITT as VectorNav uses it (XModem: polynomial 0x1021, initial value 0, no reflection,
/// no final xor).
pub fn crc16(data: &[u8]) -> u16 {
    let mut crc = 0u16;
    for &b in data {
        crc ^= (b as u16) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 { (crc << 1) ^ 0x1021 } else { crc << 1 };
        }
    }
    crc
}

/// Why bytes starting with a sync byte are not a usable message.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum MessageError {
    /// Fewer bytes than the header says: wait for more.
    Incomplete,
    /// The first byte is not the sync byte.
    NoSync,
    /// No group selected (not a binary output message).
    NoGroups,
    /// A group or field whose size is not tabled here (GPS, Attitude, INS, GPS2, or a reserved
    /// bit): the message cannot be measured.
    Unsupported,
    /// The CRC does not match: the bytes were corrupted (or were never a message).
    Crc,
}

impl core::fmt::Display for MessageError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Incomplete => "VectorNav message incomplete",
            Self::NoSync => "VectorNav message does not start with the sync byte 0xFA",
            Self::NoGroups => "VectorNav message selects no output group",
            Self::Unsupported => {
                "VectorNav message selects a GPS, Attitude or INS group field (only Common, Time and IMU are read)"
            }
            Self::Crc => "VectorNav message CRC mismatch",
        })
    }
}

impl core::error::Error for MessageError {}

/// What a binary output message says that LIO uses.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct BinaryOutput {
    /// TimeStartup: ns since power-on.
    pub time_startup_ns: Option<u64>,
    /// Angular rate, rad/s (compensated if sent, else uncompensated).
    pub gyro: Option<[f32; 3]>,
    /// Acceleration, m/s^2 (compensated if sent, else uncompensated).
    pub acc: Option<[f32; 3]>,
    /// Fields read past as not used.
    pub skipped: u16,
}

/// The size tables of the groups selected by `groups`, in order; `None` for an untabled group.
fn group_sizes(group_bit: usize) -> Option<&'static [u8; 16]> {
    match group_bit {
        0 => Some(&COMMON_SIZES),
        1 => Some(&TIME_SIZES),
        2 => Some(&IMU_SIZES),
        _ => None,
    }
}

fn le3(b: &[u8]) -> [f32; 3] {
    let f = |i: usize| f32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]]);
    [f(0), f(4), f(8)]
}

/// Parses the message at the start of `bytes`: what it says and its length on the wire. A
/// value that is not finite leaves its field `None` (the message is then incomplete).
pub fn parse_message(bytes: &[u8]) -> Result<(BinaryOutput, usize), MessageError> {
    let (&first, rest) = bytes.split_first().ok_or(MessageError::Incomplete)?;
    if first != SYNC {
        return Err(MessageError::NoSync);
    }
    let &groups = rest.first().ok_or(MessageError::Incomplete)?;
    if groups == 0 {
        return Err(MessageError::NoGroups);
    }
    // Measure: every selected group tabled, every selected field of known size.
    let n_groups = groups.count_ones() as usize;
    let header = 2 + 2 * n_groups;
    let words = bytes.get(2..header).ok_or(MessageError::Incomplete)?;
    let mut payload = 0usize;
    let mut word_of = [0u16; 8];
    let mut w = 0;
    for (g, slot) in word_of.iter_mut().enumerate() {
        if groups & (1 << g) == 0 {
            continue;
        }
        let fields = u16::from_le_bytes([words[2 * w], words[2 * w + 1]]);
        w += 1;
        let sizes = group_sizes(g).ok_or(MessageError::Unsupported)?;
        for (bit, &size) in sizes.iter().enumerate() {
            if fields & (1 << bit) != 0 {
                if size == 0 {
                    return Err(MessageError::Unsupported);
                }
                payload += size as usize;
            }
        }
        *slot = fields;
    }
    let total = header + payload + 2;
    let msg = bytes.get(..total).ok_or(MessageError::Incomplete)?;
    if crc16(&msg[1..]) != 0 {
        return Err(MessageError::Crc);
    }
    // Read: walk the fields in order.
    let mut out = BinaryOutput::default();
    let (mut uncomp_acc, mut uncomp_gyro) = (None, None);
    let mut at = header;
    for (g, &fields) in word_of.iter().enumerate().take(3) {
        let Some(sizes) = group_sizes(g) else { continue };
        for (bit, &size) in sizes.iter().enumerate() {
            if fields & (1 << bit) == 0 {
                continue;
            }
            let v = &msg[at..at + size as usize];
            at += size as usize;
            let finite = |x: [f32; 3]| x.iter().all(|v| v.is_finite()).then_some(x);
            match (g, bit) {
                (0, COMMON_TIME_STARTUP) | (1, TIME_TIME_STARTUP) => {
                    out.time_startup_ns =
                        Some(u64::from_le_bytes([v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7]]))
                }
                (0, COMMON_ANGULAR_RATE) | (2, IMU_ANGULAR_RATE) => out.gyro = finite(le3(v)),
                (0, COMMON_ACCEL) | (2, IMU_ACCEL) => out.acc = finite(le3(v)),
                // Common Imu: uncompensated accel, then uncompensated gyro.
                (0, COMMON_IMU) => {
                    uncomp_acc = finite(le3(v));
                    uncomp_gyro = finite(le3(&v[12..]));
                }
                (2, IMU_UNCOMP_ACCEL) => uncomp_acc = finite(le3(v)),
                (2, IMU_UNCOMP_GYRO) => uncomp_gyro = finite(le3(v)),
                _ => out.skipped = out.skipped.saturating_add(1),
            }
        }
    }
    out.acc = out.acc.or(uncomp_acc);
    out.gyro = out.gyro.or(uncomp_gyro);
    Ok((out, total))
}

/// One inertial sample of a message that has both an angular rate and an acceleration.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VectorNavSample {
    /// TimeStartup (ns since power-on), when configured.
    pub time_startup_ns: Option<u64>,
    /// Angular rate, rad/s.
    pub gyro: [f32; 3],
    /// Acceleration, m/s^2.
    pub acc: [f32; 3],
}

/// Counts of what a [`Decoder`] accepted and dropped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VectorNavStats {
    /// Samples delivered.
    pub samples: u64,
    /// Candidate messages whose CRC failed.
    pub crc: u64,
    /// Candidate messages selecting groups or fields not tabled here ([`MessageError::Unsupported`]).
    pub unsupported: u64,
    /// Good messages without an angular rate or an acceleration (or with a non-finite one).
    pub incomplete: u64,
    /// Fields read past as not used.
    pub skipped_fields: u64,
    /// Bytes that were not part of a good message (noise, ASCII output, rejected messages).
    pub dropped_bytes: u64,
}

/// A streaming decoder: feed it the serial bytes in any chunking and it yields samples.
#[derive(Debug)]
pub struct Decoder {
    buf: SyncBuf<MAX_MESSAGE>,
    /// What was accepted and dropped so far.
    pub stats: VectorNavStats,
}

impl Framed for Decoder {
    type Sample = VectorNavSample;

    fn push(&mut self, b: u8) -> bool {
        self.buf.push(b)
    }

    fn poll(&mut self) -> Option<VectorNavSample> {
        self.decide()
    }

    fn give_up_candidate(&mut self) {
        self.stats.dropped_bytes += self.buf.skip_to_sync(SYNC, 1) as u64;
    }
}

impl Default for Decoder {
    fn default() -> Self {
        Self::new()
    }
}

impl Decoder {
    /// A decoder waiting for the first sync byte.
    pub const fn new() -> Self {
        Self {
            buf: SyncBuf::new(),
            stats: VectorNavStats {
                samples: 0,
                crc: 0,
                unsupported: 0,
                incomplete: 0,
                skipped_fields: 0,
                dropped_bytes: 0,
            },
        }
    }

    /// Consumes bytes from `input` until a sample is complete. Returns the number of bytes
    /// consumed (possibly 0 when a sample was already buffered) and the sample, if any. Call
    /// it again with the rest of the input until everything is consumed and no sample comes.
    pub fn feed(&mut self, input: &[u8]) -> (usize, Option<VectorNavSample>) {
        sync_buf::feed(self, input)
    }

    fn decide(&mut self) -> Option<VectorNavSample> {
        loop {
            self.stats.dropped_bytes += self.buf.skip_to_sync(SYNC, 0) as u64;
            match parse_message(self.buf.bytes()) {
                Err(MessageError::Incomplete) | Err(MessageError::NoSync) => return None,
                Err(e) => {
                    match e {
                        MessageError::Unsupported => self.stats.unsupported += 1,
                        MessageError::Crc => self.stats.crc += 1,
                        _ => {} // a lone 0xFA followed by 0x00: noise
                    }
                    self.give_up_candidate();
                }
                Ok((m, len)) => {
                    self.buf.drop_front(len);
                    self.stats.skipped_fields += m.skipped as u64;
                    match (m.gyro, m.acc) {
                        (Some(gyro), Some(acc)) => {
                            self.stats.samples += 1;
                            return Some(VectorNavSample { time_startup_ns: m.time_startup_ns, gyro, acc });
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

    /// A message built by hand from the documented layout: `groups`, the field words, the
    /// payload bytes (already in field order), the CRC big-endian.
    fn message(groups: u8, words: &[u16], payload: &[u8]) -> Vec<u8> {
        let mut m = std::vec![SYNC, groups];
        for w in words {
            m.extend_from_slice(&w.to_le_bytes());
        }
        m.extend_from_slice(payload);
        let crc = crc16(&m[1..]);
        m.extend_from_slice(&crc.to_be_bytes());
        m
    }

    fn f32s(v: [f32; 3]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    /// Common group: TimeStartup, AngularRate, Accel (field bits 0, 5, 8).
    fn common(t_ns: u64, gyro: [f32; 3], acc: [f32; 3]) -> Vec<u8> {
        let mut p = t_ns.to_le_bytes().to_vec();
        p.extend(f32s(gyro));
        p.extend(f32s(acc));
        message(0x01, &[0x0121], &p)
    }

    #[test]
    fn crc16_known_answers() {
        // CRC-16/XMODEM check value.
        assert_eq!(crc16(b"123456789"), 0x31C3);
        assert_eq!(crc16(b""), 0);
        // A message with its CRC appended checks to 0.
        let mut m = b"123456789".to_vec();
        m.extend_from_slice(&0x31C3u16.to_be_bytes());
        assert_eq!(crc16(&m), 0);
    }

    #[test]
    fn common_group_message_decodes_exactly() {
        let m = common(1_234_567_890_123, [0.125, -0.5, 2.0], [0.25, 0.0, -9.75]);
        // FA | 01 | 21 01 | 8 + 12 + 12 payload | CRC.
        assert_eq!(&m[..4], &[0xFA, 0x01, 0x21, 0x01]);
        assert_eq!(m.len(), 4 + 32 + 2);
        assert_eq!(&m[4..12], &1_234_567_890_123u64.to_le_bytes());
        assert_eq!(&m[12..16], &[0x00, 0x00, 0x00, 0x3E]); // 0.125f32 little-endian
        let (o, n) = parse_message(&m).unwrap();
        assert_eq!(n, m.len());
        assert_eq!(o.time_startup_ns, Some(1_234_567_890_123));
        assert_eq!(o.gyro, Some([0.125, -0.5, 2.0]));
        assert_eq!(o.acc, Some([0.25, 0.0, -9.75]));
        assert_eq!(o.skipped, 0);
        let mut bad = m.clone();
        bad[20] ^= 1;
        assert_eq!(parse_message(&bad), Err(MessageError::Crc));
        assert_eq!(parse_message(&m[..m.len() - 1]), Err(MessageError::Incomplete));
    }

    #[test]
    fn other_fields_are_skipped_by_their_size() {
        // Common: TimeGps(8) YawPitchRoll(12) AngularRate(12) Accel(12) InsStatus(2);
        // Time: GpsWeek(2) TimeStatus(1); IMU: ImuStatus(2) Temp(4).
        let mut p = std::vec![0xAA; 8 + 12];
        p.extend(f32s([1.0, 2.0, 3.0]));
        p.extend(f32s([4.0, 5.0, 6.0]));
        p.extend([0xBB; 2 + 2 + 1 + 2 + 4]);
        let m = message(0x07, &[0x0002 | 0x0008 | 0x0020 | 0x0100 | 0x1000, 0x0008 | 0x0200, 0x0011], &p);
        let (o, _) = parse_message(&m).unwrap();
        assert_eq!(
            (o.gyro, o.acc, o.time_startup_ns, o.skipped),
            (Some([1.0, 2.0, 3.0]), Some([4.0, 5.0, 6.0]), None, 7)
        );
        // Time group TimeStartup, IMU group UncompAccel + UncompGyro: the uncompensated data.
        let mut p = 42u64.to_le_bytes().to_vec();
        p.extend(f32s([0.0, 0.0, -9.8]));
        p.extend(f32s([0.5, 0.0, 0.0]));
        let (o, _) = parse_message(&message(0x06, &[0x0001, 0x000C], &p)).unwrap();
        assert_eq!(
            (o.time_startup_ns, o.acc, o.gyro),
            (Some(42), Some([0.0, 0.0, -9.8]), Some([0.5, 0.0, 0.0]))
        );
    }

    #[test]
    fn untabled_groups_and_fields_are_rejected() {
        // GPS group; Attitude group; Common bit 15; Time bit 12.
        for (groups, words) in
            [(0x08u8, &[0x0001u16][..]), (0x11, &[0x0020, 0x0002]), (0x01, &[0x8000]), (0x02, &[0x1000])]
        {
            let m = message(groups, words, &[0; 40]);
            assert_eq!(parse_message(&m), Err(MessageError::Unsupported), "{groups:#x} {words:?}");
        }
        assert_eq!(parse_message(&[0xFA, 0x00]), Err(MessageError::NoGroups));
        assert_eq!(parse_message(&[0x55]), Err(MessageError::NoSync));
    }

    #[test]
    fn stream_with_noise_resynchronises_and_counts() {
        let sample =
            |k: u64| (k * 2_500_000, [0.01 * k as f32, 0.0, 0.1], [0.0, 0.2, -9.81 + 0.001 * k as f32]);
        let mut stream = b"$VNYMR,+010.0*5A\r\n".to_vec(); // ASCII output before the binary
        let mut noise = stream.len();
        for k in 0..40u64 {
            let (t, g, a) = sample(k);
            let mut m = common(t, g, a);
            match k {
                3 => {
                    stream.extend_from_slice(&[0xFA, 0x01, 0xFF]); // a header cut short
                    noise += 3;
                }
                8 => {
                    m[30] ^= 0x20; // corrupted: the CRC fails
                    noise += m.len();
                }
                12 => {
                    stream.extend_from_slice(&m[..10]); // cut short
                    noise += 10;
                    continue;
                }
                _ => {}
            }
            stream.extend_from_slice(&m);
        }
        // A good message without the acceleration.
        stream.extend_from_slice(&message(0x01, &[0x0020], &f32s([0.0; 3])));
        for chunk in [1usize, 5, 64, 4096] {
            let mut dec = Decoder::new();
            let mut got = Vec::new();
            for c in stream.chunks(chunk) {
                let mut rest = c;
                loop {
                    let (n, s) = dec.feed(rest);
                    rest = &rest[n..];
                    match s {
                        Some(s) => got.push(s),
                        None if rest.is_empty() => break,
                        None => {}
                    }
                }
            }
            let want: Vec<u64> = (0..40).filter(|k| *k != 8 && *k != 12).collect();
            let times: Vec<u64> = got.iter().map(|s| s.time_startup_ns.unwrap() / 2_500_000).collect();
            assert_eq!(times, want, "chunk {chunk}");
            for s in &got {
                let (t, g, a) = sample(s.time_startup_ns.unwrap() / 2_500_000);
                assert_eq!((s.time_startup_ns, s.gyro, s.acc), (Some(t), g, a));
            }
            assert_eq!(dec.stats.samples, 38);
            assert_eq!(dec.stats.incomplete, 1);
            assert!(dec.stats.crc >= 2, "{:?}", dec.stats);
            assert_eq!(dec.stats.dropped_bytes, noise as u64, "{:?}", dec.stats);
        }
    }

    fn decode_all(dec: &mut Decoder, mut bytes: &[u8], out: &mut Vec<VectorNavSample>) {
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

        /// Good messages with noise (without the sync byte) before each: every message is
        /// recovered in order and exactly the noise is counted as dropped.
        #[test]
        fn messages_behind_noise_are_all_recovered(
            noise in proptest::collection::vec(proptest::collection::vec(0u8..0xFA, 0..40), 1..30),
            chunk in 1usize..80,
        ) {
            let mut stream = Vec::new();
            for (k, n) in noise.iter().enumerate() {
                stream.extend_from_slice(n);
                stream.extend(common(k as u64 * 1000, [k as f32, 0.0, 0.1], [0.0, 0.5, k as f32]));
            }
            let mut dec = Decoder::new();
            let mut got = Vec::new();
            for c in stream.chunks(chunk) {
                decode_all(&mut dec, c, &mut got);
            }
            let times: Vec<u64> = got.iter().map(|s| s.time_startup_ns.unwrap_or(u64::MAX)).collect();
            proptest::prop_assert_eq!(times, (0..noise.len() as u64).map(|k| k * 1000).collect::<Vec<_>>());
            let noise_bytes: usize = noise.iter().map(Vec::len).sum();
            proptest::prop_assert_eq!(dec.stats.dropped_bytes, noise_bytes as u64);
        }
    }
}
