//! An autopilot's IMU over MAVLink (UDP datagrams): `HIGHRES_IMU` (id 105: m/s^2, rad/s),
//! `SCALED_IMU` (id 26: mG, mrad/s) and `RAW_IMU` (id 27: sensor counts, read only with the
//! scales of the configuration). The framing and the CRC are the ones of loglio's MAVLink
//! output ([`crate::sink::mavlink`]): MAVLink 2 frames (a signature, when flagged, skipped
//! unchecked) and MAVLink 1 frames, several to a datagram, every CRC checked with the message's
//! CRC_EXTRA, payloads truncated by MAVLink 2 zero-extended. Layouts from common.xml, fields in
//! wire order (largest type first):
//!
//! ```text
//! HIGHRES_IMU 105, CRC_EXTRA 93:  time_usec u64 | xacc yacc zacc xgyro ygyro zgyro
//!                                 xmag ymag zmag abs_pressure diff_pressure pressure_alt
//!                                 temperature f32 | fields_updated u16 | (ext) id u8
//! SCALED_IMU   26, CRC_EXTRA 170: time_boot_ms u32 | xacc yacc zacc xgyro ygyro zgyro
//!                                 xmag ymag zmag i16 | (ext) temperature i16
//! RAW_IMU      27, CRC_EXTRA 144: time_usec u64 | xacc yacc zacc xgyro ygyro zgyro
//!                                 xmag ymag zmag i16 | (ext) id u8, temperature i16
//! ```
//!
//! An autopilot often sends more than one of them (ArduPilot: `RAW_IMU` and `SCALED_IMU2`;
//! PX4: `HIGHRES_IMU`): the best kind seen so far is used (`HIGHRES_IMU` over `SCALED_IMU`
//! over `RAW_IMU`) and the others are counted as ignored, so no sample is taken twice.

use crate::sink::mavlink::{crc_accumulate, crc16};

/// `HIGHRES_IMU` id.
pub const HIGHRES_IMU_ID: u32 = 105;
/// `SCALED_IMU` id.
pub const SCALED_IMU_ID: u32 = 26;
/// `RAW_IMU` id.
pub const RAW_IMU_ID: u32 = 27;
const HIGHRES_IMU_CRC_EXTRA: u8 = 93;
const SCALED_IMU_CRC_EXTRA: u8 = 170;
const RAW_IMU_CRC_EXTRA: u8 = 144;
/// Standard gravity, m/s^2 per g (`SCALED_IMU` gives mG).
const G: f32 = 9.80665;

/// The IMU messages read, best first.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum ImuMessage {
    /// `RAW_IMU`: counts times the configured scales.
    RawImu,
    /// `SCALED_IMU`: mG and mrad/s.
    ScaledImu,
    /// `HIGHRES_IMU`: m/s^2 and rad/s.
    HighresImu,
}

impl ImuMessage {
    /// The message's name in common.xml.
    pub fn name(self) -> &'static str {
        match self {
            Self::RawImu => "RAW_IMU",
            Self::ScaledImu => "SCALED_IMU",
            Self::HighresImu => "HIGHRES_IMU",
        }
    }
}

/// `RAW_IMU`'s counts to SI units (the sensor's scale: its full-scale range over 32768).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RawScale {
    /// m/s^2 per count.
    pub acc: f32,
    /// rad/s per count.
    pub gyro: f32,
}

/// One IMU sample of a MAVLink message.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MavlinkImuSample {
    /// Which message it came from.
    pub message: ImuMessage,
    /// The autopilot's time of the sample, ns (since its boot, or the UNIX epoch when it has a
    /// GPS time; `SCALED_IMU`'s milliseconds since boot wrap after 49.7 days).
    pub device_ns: u64,
    /// Angular rate, rad/s.
    pub gyro: [f32; 3],
    /// Specific force, m/s^2.
    pub acc: [f32; 3],
}

/// What the decoder saw.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MavlinkImuStats {
    /// Samples delivered.
    pub samples: u64,
    /// Good frames of other messages (heartbeats, attitude, ...).
    pub other_messages: u64,
    /// IMU messages of a kind worse than the best seen, or `RAW_IMU` without scales.
    pub ignored: u64,
    /// Frames whose CRC failed (or whose message id is an IMU's with a wrong CRC_EXTRA).
    pub crc: u64,
    /// IMU messages with a non-finite value.
    pub bad_values: u64,
    /// Bytes of the datagrams that were not part of a good frame.
    pub dropped_bytes: u64,
}

/// Decodes MAVLink datagrams into IMU samples.
#[derive(Clone, Debug, Default)]
pub struct MavlinkImuDecoder {
    raw_scale: Option<RawScale>,
    best: Option<ImuMessage>,
    /// What was accepted and dropped so far.
    pub stats: MavlinkImuStats,
}

/// A frame found at the start of `d`: (message id, payload, length on the wire), or `None` when
/// there is no complete frame of either version there.
fn frame(d: &[u8]) -> Option<(u32, &[u8], usize, &[u8])> {
    match *d.first()? {
        0xFD => {
            let len = *d.get(1)? as usize;
            let signed = d.get(2)? & 1 != 0;
            let total = 10 + len + 2 + if signed { 13 } else { 0 };
            let f = d.get(..total)?;
            let id = u32::from_le_bytes([f[7], f[8], f[9], 0]);
            Some((id, &f[10..10 + len], total, &f[1..10 + len + 2]))
        }
        0xFE => {
            let len = *d.get(1)? as usize;
            let total = 6 + len + 2;
            let f = d.get(..total)?;
            Some((f[5] as u32, &f[6..6 + len], total, &f[1..6 + len + 2]))
        }
        _ => None,
    }
}

impl MavlinkImuDecoder {
    /// A decoder; `raw_scale` makes `RAW_IMU` readable.
    pub fn new(raw_scale: Option<RawScale>) -> Self {
        Self { raw_scale, ..Self::default() }
    }

    /// The best IMU message seen so far (the one used).
    pub fn message(&self) -> Option<ImuMessage> {
        self.best
    }

    /// Decodes every frame of one datagram; samples go to `out`.
    pub fn datagram(&mut self, mut d: &[u8], mut out: impl FnMut(MavlinkImuSample)) {
        while !d.is_empty() {
            let Some((id, payload, total, checked)) = frame(d) else {
                // Not a frame start, or a frame cut short: skip to the next start byte.
                let skip = d[1..].iter().position(|&b| b == 0xFD || b == 0xFE).map_or(d.len(), |i| i + 1);
                self.stats.dropped_bytes += skip as u64;
                d = &d[skip..];
                continue;
            };
            let extra = match id {
                HIGHRES_IMU_ID => Some(HIGHRES_IMU_CRC_EXTRA),
                SCALED_IMU_ID => Some(SCALED_IMU_CRC_EXTRA),
                RAW_IMU_ID => Some(RAW_IMU_CRC_EXTRA),
                _ => None,
            };
            let Some(extra) = extra else {
                // Another message: its CRC_EXTRA is not known here, so it is not checked.
                self.stats.other_messages += 1;
                d = &d[total..];
                continue;
            };
            let n = checked.len();
            let crc = crc_accumulate(extra, crc16(&checked[..n - 2]));
            if crc.to_le_bytes() != checked[n - 2..] {
                self.stats.crc += 1;
                self.stats.dropped_bytes += 1;
                d = &d[1..];
                continue;
            }
            d = &d[total..];
            if let Some(s) = self.imu_message(id, payload) {
                out(s);
            }
        }
    }

    fn imu_message(&mut self, id: u32, payload: &[u8]) -> Option<MavlinkImuSample> {
        // MAVLink 2 drops trailing zero bytes: put them back.
        let mut p = [0u8; 64];
        let n = payload.len().min(p.len());
        p[..n].copy_from_slice(&payload[..n]);
        let u64_at = |i: usize| {
            u64::from_le_bytes([p[i], p[i + 1], p[i + 2], p[i + 3], p[i + 4], p[i + 5], p[i + 6], p[i + 7]])
        };
        let f32_at = |i: usize| f32::from_le_bytes([p[i], p[i + 1], p[i + 2], p[i + 3]]);
        let i16_at = |i: usize| i16::from_le_bytes([p[i], p[i + 1]]) as f32;
        let (message, device_ns, acc, gyro) = match id {
            HIGHRES_IMU_ID => (
                ImuMessage::HighresImu,
                u64_at(0).saturating_mul(1000),
                [f32_at(8), f32_at(12), f32_at(16)],
                [f32_at(20), f32_at(24), f32_at(28)],
            ),
            SCALED_IMU_ID => (
                ImuMessage::ScaledImu,
                u32::from_le_bytes([p[0], p[1], p[2], p[3]]) as u64 * 1_000_000,
                [i16_at(4), i16_at(6), i16_at(8)].map(|v| v * 1e-3 * G),
                [i16_at(10), i16_at(12), i16_at(14)].map(|v| v * 1e-3),
            ),
            _ => {
                let Some(s) = self.raw_scale else {
                    self.stats.ignored += 1;
                    return None;
                };
                (
                    ImuMessage::RawImu,
                    u64_at(0).saturating_mul(1000),
                    [i16_at(8), i16_at(10), i16_at(12)].map(|v| v * s.acc),
                    [i16_at(14), i16_at(16), i16_at(18)].map(|v| v * s.gyro),
                )
            }
        };
        if self.best.is_some_and(|b| message < b) {
            self.stats.ignored += 1;
            return None;
        }
        self.best = Some(message);
        if !acc.iter().chain(gyro.iter()).all(|v| v.is_finite()) {
            self.stats.bad_values += 1;
            return None;
        }
        self.stats.samples += 1;
        Some(MavlinkImuSample { message, device_ns, gyro, acc })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sink::mavlink::Encoder;

    fn highres(t_us: u64, acc: [f32; 3], gyro: [f32; 3]) -> Vec<u8> {
        let mut p = t_us.to_le_bytes().to_vec();
        for v in acc.iter().chain(gyro.iter()).chain([0.0f32; 7].iter()) {
            p.extend(v.to_le_bytes());
        }
        p.extend(0x3Fu16.to_le_bytes());
        p.push(0);
        p
    }

    #[test]
    fn frames_of_both_versions_and_every_kind() {
        let mut enc = Encoder::new(1, 1);
        let mut d = vec![0x55, 0xFD]; // noise, a start byte cut short
        let mut buf = [0u8; 300];
        let n = enc
            .frame(
                HIGHRES_IMU_ID,
                HIGHRES_IMU_CRC_EXTRA,
                &highres(1_500_000, [0.5, -0.25, 9.75], [0.125, 0.0, -1.0]),
                &mut buf,
            )
            .unwrap();
        d.extend_from_slice(&buf[..n]);
        // A heartbeat between them.
        let n = enc.frame(0, 50, &[0, 0, 0, 0, 18, 8, 0, 4, 3], &mut buf).unwrap();
        d.extend_from_slice(&buf[..n]);
        // A MAVLink 1 SCALED_IMU: 1000 mG down, 100 mrad/s about x.
        let mut p = 2_000u32.to_le_bytes().to_vec();
        for v in [0i16, 0, -1000, 100, 0, 0, 0, 0, 0] {
            p.extend(v.to_le_bytes());
        }
        let mut v1 = vec![0xFE, p.len() as u8, 0, 1, 1, SCALED_IMU_ID as u8];
        v1.extend(&p);
        let crc = crc_accumulate(SCALED_IMU_CRC_EXTRA, crc16(&v1[1..]));
        v1.extend(crc.to_le_bytes());
        d.extend(&v1);
        let mut dec = MavlinkImuDecoder::new(None);
        let mut got = Vec::new();
        dec.datagram(&d, |s| got.push(s));
        assert_eq!(got.len(), 1, "SCALED_IMU after HIGHRES_IMU is ignored: {got:?}");
        assert_eq!(got[0].device_ns, 1_500_000_000);
        assert_eq!((got[0].acc, got[0].gyro), ([0.5, -0.25, 9.75], [0.125, 0.0, -1.0]));
        assert_eq!(dec.stats.other_messages, 1);
        assert_eq!(dec.stats.ignored, 1);
        assert_eq!(dec.stats.dropped_bytes, 2);
        // Alone, the SCALED_IMU is read in SI units.
        let mut dec = MavlinkImuDecoder::new(None);
        let mut got = Vec::new();
        dec.datagram(&v1, |s| got.push(s));
        assert_eq!(got[0].device_ns, 2_000_000_000);
        assert_eq!((got[0].acc, got[0].gyro), ([0.0, 0.0, -9.80665], [0.1, 0.0, 0.0]));
        // A corrupted CRC.
        let mut bad = v1.clone();
        bad[8] ^= 1;
        dec.datagram(&bad, |_| panic!("corrupted"));
        assert_eq!(dec.stats.crc, 1);
    }
}
