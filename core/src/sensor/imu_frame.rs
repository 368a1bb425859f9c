//! loglio's compact serial IMU frame, as the IMU board firmware sends it over a UART.
//!
//! Wire format of one frame:
//!
//! ```text
//! COBS( postcard(ImuFrame) ++ crc32_le(postcard bytes) ) 0x00
//! ```
//!
//! postcard keeps the payload small (varint integers, ~35 bytes), COBS makes 0x00 a frame
//! delimiter that never occurs inside a frame, so a receiver that starts mid-stream or loses
//! bytes resynchronises at the next 0x00, and the CRC-32 (IEEE) rejects frames that line noise
//! corrupted. [`FrameDecoder`] takes a byte stream in arbitrary chunks and yields good frames,
//! counting every byte run it had to drop.

use serde::{Deserialize, Serialize};

use crate::imu::ImuSample;

/// One IMU sample with its sequence number, as sent by the IMU board.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize, postcard::experimental::max_size::MaxSize,
)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImuFrame {
    /// Incremented by one per sample (wrapping); a gap means frames were lost.
    pub seq: u32,
    /// Sample time on the board's clock, nanoseconds.
    pub t_ns: u64,
    /// Angular rate, rad/s.
    pub gyro: [f32; 3],
    /// Specific force, m/s^2.
    pub acc: [f32; 3],
}

impl ImuFrame {
    /// The sample this frame carries.
    pub fn sample(&self) -> ImuSample {
        ImuSample { t_ns: self.t_ns, gyro: self.gyro, acc: self.acc }
    }
}

use postcard::experimental::max_size::MaxSize;

/// Largest postcard encoding of an [`ImuFrame`].
pub const PAYLOAD_MAX: usize = ImuFrame::POSTCARD_MAX_SIZE;
/// Largest unencoded frame body: payload plus CRC.
const BODY_MAX: usize = PAYLOAD_MAX + 4;
/// Largest frame on the wire, delimiter included (COBS adds one byte per 254 and one more).
pub const FRAME_MAX: usize = BODY_MAX + BODY_MAX.div_ceil(254) + 1 + 1;

/// Why a frame could not be encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum EncodeError {
    /// The output buffer is shorter than [`FRAME_MAX`] requires for this frame.
    BufferTooSmall,
}

impl core::fmt::Display for EncodeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("output buffer too small for an IMU frame")
    }
}

impl core::error::Error for EncodeError {}

/// Why a delimited byte run was not a frame. Every variant is counted by [`FrameDecoder`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DecodeError {
    /// More bytes than any frame has before a delimiter (noise, or a lost delimiter).
    TooLong,
    /// The COBS encoding is broken.
    Cobs,
    /// The CRC does not match: the bytes were corrupted.
    Crc,
    /// The CRC matched but the payload is not an `ImuFrame` (wrong version or garbage).
    Payload,
}

impl core::fmt::Display for DecodeError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::TooLong => "IMU frame too long (missing delimiter)",
            Self::Cobs => "IMU frame has a broken COBS encoding",
            Self::Crc => "IMU frame CRC mismatch",
            Self::Payload => "IMU frame payload is not a valid sample",
        })
    }
}

impl core::error::Error for DecodeError {}

/// CRC-32 (IEEE 802.3, reflected, polynomial 0xEDB88320), as zlib computes it.
pub fn crc32(data: &[u8]) -> u32 {
    const TABLE: [u32; 256] = {
        let mut t = [0u32; 256];
        let mut i = 0;
        while i < 256 {
            let mut c = i as u32;
            let mut k = 0;
            while k < 8 {
                c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
                k += 1;
            }
            t[i] = c;
            i += 1;
        }
        t
    };
    let mut crc = 0xFFFF_FFFFu32;
    for &b in data {
        crc = TABLE[((crc ^ b as u32) & 0xFF) as usize] ^ (crc >> 8);
    }
    !crc
}

/// COBS-encodes `src` into `dst` (no delimiter); returns the encoded length.
fn cobs_encode(src: &[u8], dst: &mut [u8]) -> Option<usize> {
    let mut code_at = 0usize;
    let mut out = 1usize;
    let mut code = 1u8;
    for &b in src {
        if b == 0 {
            *dst.get_mut(code_at)? = code;
            code_at = out;
            out += 1;
            code = 1;
        } else {
            *dst.get_mut(out)? = b;
            out += 1;
            code += 1;
            if code == 0xFF {
                *dst.get_mut(code_at)? = code;
                code_at = out;
                out += 1;
                code = 1;
            }
        }
    }
    *dst.get_mut(code_at)? = code;
    Some(out)
}

/// COBS-decodes `buf` in place (no delimiter inside); returns the decoded length.
fn cobs_decode_in_place(buf: &mut [u8]) -> Option<usize> {
    let (mut read, mut write) = (0usize, 0usize);
    while read < buf.len() {
        let code = buf[read];
        if code == 0 {
            return None;
        }
        read += 1;
        let end = read + code as usize - 1;
        if end > buf.len() {
            return None;
        }
        while read < end {
            let b = buf[read];
            if b == 0 {
                return None;
            }
            buf[write] = b;
            write += 1;
            read += 1;
        }
        if code != 0xFF && read < buf.len() {
            buf[write] = 0;
            write += 1;
        }
    }
    Some(write)
}

/// Encodes one frame, delimiter included, into `out`; returns the bytes written.
pub fn encode(frame: &ImuFrame, out: &mut [u8]) -> Result<usize, EncodeError> {
    let mut body = [0u8; BODY_MAX];
    let n = postcard::to_slice(frame, &mut body).map_err(|_| EncodeError::BufferTooSmall)?.len();
    let crc = crc32(&body[..n]).to_le_bytes();
    body[n..n + 4].copy_from_slice(&crc);
    let len = cobs_encode(&body[..n + 4], out).ok_or(EncodeError::BufferTooSmall)?;
    *out.get_mut(len).ok_or(EncodeError::BufferTooSmall)? = 0;
    Ok(len + 1)
}

/// Decodes the bytes between two delimiters (the delimiter itself excluded), in place.
pub fn decode_in_place(encoded: &mut [u8]) -> Result<ImuFrame, DecodeError> {
    if encoded.len() > FRAME_MAX - 1 {
        return Err(DecodeError::TooLong);
    }
    let n = cobs_decode_in_place(encoded).ok_or(DecodeError::Cobs)?;
    if n < 5 {
        return Err(DecodeError::Crc);
    }
    let (payload, crc) = encoded[..n].split_at(n - 4);
    if crc32(payload).to_le_bytes() != crc {
        return Err(DecodeError::Crc);
    }
    match postcard::from_bytes::<ImuFrame>(payload) {
        Ok(f) if f.gyro.iter().chain(f.acc.iter()).all(|v| v.is_finite()) => Ok(f),
        _ => Err(DecodeError::Payload),
    }
}

/// Counts of what a [`FrameDecoder`] accepted and dropped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DecoderStats {
    /// Good frames delivered.
    pub frames: u64,
    /// Delimited runs dropped, by reason.
    pub too_long: u64,
    /// Broken COBS encodings.
    pub cobs: u64,
    /// CRC mismatches.
    pub crc: u64,
    /// Undecodable payloads.
    pub payload: u64,
    /// Frames missing according to the sequence numbers.
    pub seq_gaps: u64,
    /// Bytes thrown away with dropped runs (noise, partial frames).
    pub dropped_bytes: u64,
}

/// A streaming decoder: feed it bytes as they arrive, in any chunking, and it yields frames.
/// A corrupted or partial frame costs only itself: the next delimiter resynchronises, and when
/// noise was glued to the front of a good frame (no delimiter between them) the frame is still
/// recovered, because the decoder keeps the last [`FRAME_MAX`] bytes of a run and tries its
/// suffixes, each guarded by the CRC.
#[derive(Debug)]
pub struct FrameDecoder {
    /// Ring of the last bytes of the current run.
    ring: [u8; FRAME_MAX],
    /// Bytes in the current run (may exceed the ring; the oldest are then gone).
    run: usize,
    last_seq: Option<u32>,
    /// What was accepted and dropped so far.
    pub stats: DecoderStats,
}

impl Default for FrameDecoder {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameDecoder {
    /// A decoder waiting for the first delimiter-terminated frame.
    pub const fn new() -> Self {
        Self {
            ring: [0; FRAME_MAX],
            run: 0,
            last_seq: None,
            stats: DecoderStats {
                frames: 0,
                too_long: 0,
                cobs: 0,
                crc: 0,
                payload: 0,
                seq_gaps: 0,
                dropped_bytes: 0,
            },
        }
    }

    /// Consumes bytes from `input` up to and including the first frame delimiter. Returns the
    /// number of bytes consumed and, if they completed a good frame, the frame. Call it again
    /// with the rest of the input until everything is consumed.
    pub fn feed(&mut self, input: &[u8]) -> (usize, Option<ImuFrame>) {
        for (i, &b) in input.iter().enumerate() {
            if b != 0 {
                self.ring[self.run % FRAME_MAX] = b;
                self.run += 1;
                continue;
            }
            let run = core::mem::take(&mut self.run);
            if run == 0 {
                continue; // back-to-back delimiters are harmless
            }
            if let Some(frame) = self.finish_run(run) {
                return (i + 1, Some(frame));
            }
        }
        (input.len(), None)
    }

    /// Decodes a delimited run of `run` bytes whose last `min(run, FRAME_MAX)` are in the ring.
    fn finish_run(&mut self, run: usize) -> Option<ImuFrame> {
        let kept = run.min(FRAME_MAX);
        let mut linear = [0u8; FRAME_MAX];
        for (k, slot) in linear[..kept].iter_mut().enumerate() {
            *slot = self.ring[(run - kept + k) % FRAME_MAX];
        }
        // The whole run first (the common case), then ever shorter suffixes.
        let first_err = if run > kept {
            DecodeError::TooLong
        } else {
            let mut tmp = linear;
            match decode_in_place(&mut tmp[..kept]) {
                Ok(frame) => return Some(self.accept(frame, 0)),
                Err(e) => e,
            }
        };
        for start in 1..kept.saturating_sub(5) {
            let mut tmp = linear;
            if let Ok(frame) = decode_in_place(&mut tmp[start..kept]) {
                return Some(self.accept(frame, run - kept + start));
            }
        }
        self.stats.dropped_bytes += run as u64;
        match first_err {
            DecodeError::TooLong => self.stats.too_long += 1,
            DecodeError::Cobs => self.stats.cobs += 1,
            DecodeError::Crc => self.stats.crc += 1,
            DecodeError::Payload => self.stats.payload += 1,
        }
        debug!("imu frame dropped: {}", first_err);
        None
    }

    fn accept(&mut self, frame: ImuFrame, dropped: usize) -> ImuFrame {
        self.stats.dropped_bytes += dropped as u64;
        if let Some(prev) = self.last_seq {
            let gap = frame.seq.wrapping_sub(prev).wrapping_sub(1);
            // A huge "gap" is a reordering or a board reset, not billions of lost frames.
            if gap != 0 && gap < 1 << 31 {
                self.stats.seq_gaps += gap as u64;
            }
        }
        self.last_seq = Some(frame.seq);
        self.stats.frames += 1;
        frame
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec::Vec;

    use super::*;

    fn frame(seq: u32) -> ImuFrame {
        ImuFrame {
            seq,
            t_ns: 1_700_000_000_000_000_000 + seq as u64 * 2_500_000,
            gyro: [0.01 * seq as f32, -0.02, 0.0],
            acc: [0.1, 0.0, 9.81],
        }
    }

    fn decode_all(dec: &mut FrameDecoder, mut bytes: &[u8], out: &mut Vec<ImuFrame>) {
        while !bytes.is_empty() {
            let (n, f) = dec.feed(bytes);
            out.extend(f);
            bytes = &bytes[n..];
        }
    }

    #[test]
    fn crc32_matches_zlib() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn cobs_round_trip_with_zero_runs() {
        for src in [&[][..], &[0][..], &[0, 0, 1, 0][..], &[1; 300][..], &[7, 0, 0, 0, 255, 0][..]] {
            let mut enc = [0u8; 400];
            let n = cobs_encode(src, &mut enc).unwrap();
            assert!(!enc[..n].contains(&0));
            let d = cobs_decode_in_place(&mut enc[..n]).unwrap();
            assert_eq!(&enc[..d], src);
        }
    }

    #[test]
    fn encode_decode_round_trip() {
        let mut buf = [0u8; FRAME_MAX];
        let f = frame(42);
        let n = encode(&f, &mut buf).unwrap();
        assert!(n <= FRAME_MAX);
        assert_eq!(buf[n - 1], 0);
        assert!(!buf[..n - 1].contains(&0));
        assert_eq!(decode_in_place(&mut buf[..n - 1]), Ok(f));
        assert_eq!(encode(&f, &mut buf[..5]), Err(EncodeError::BufferTooSmall));
    }

    #[test]
    fn stream_with_noise_and_partial_frames_keeps_every_good_frame() {
        let mut stream = Vec::new();
        let mut buf = [0u8; FRAME_MAX];
        // Start mid-frame: the tail of a frame without its head.
        let n = encode(&frame(0), &mut buf).unwrap();
        stream.extend_from_slice(&buf[n / 2..n]);
        for seq in 1..=20u32 {
            let n = encode(&frame(seq), &mut buf).unwrap();
            match seq {
                5 => stream.extend_from_slice(&[0x13, 0x37, 0x42]), // noise then a good frame
                9 => {
                    // Corrupt one byte: the CRC rejects it.
                    buf[3] ^= 0x40;
                    if buf[3] == 0 {
                        buf[3] = 1;
                    }
                }
                13 => {
                    stream.extend_from_slice(&buf[..n / 2]); // a truncated frame, then its delimiter lost
                    stream.extend_from_slice(&[0xAB; 100]); // noise longer than a frame
                    stream.push(0);
                    continue;
                }
                _ => {}
            }
            stream.extend_from_slice(&buf[..n]);
        }
        for chunk in [1usize, 7, 64, 4096] {
            let mut dec = FrameDecoder::new();
            let mut got = Vec::new();
            for c in stream.chunks(chunk) {
                decode_all(&mut dec, c, &mut got);
            }
            let seqs: Vec<u32> = got.iter().map(|f| f.seq).collect();
            let want: Vec<u32> = (1..=20).filter(|s| *s != 9 && *s != 13).collect();
            assert_eq!(seqs, want, "chunk {chunk}");
            assert_eq!(got[0], frame(1));
            assert_eq!(dec.stats.frames, 18);
            assert_eq!(dec.stats.seq_gaps, 2);
            // The head-less first frame and the corrupted frame 9 fail their checks; the
            // truncated frame 13 with 100 noise bytes after it is too long.
            assert_eq!(dec.stats.crc + dec.stats.cobs + dec.stats.payload, 2, "{:?}", dec.stats);
            assert_eq!(dec.stats.too_long, 1);
            // 3 noise bytes before frame 5 were dropped, frame 5 itself recovered.
            assert!(dec.stats.dropped_bytes > 100 + 3);
        }
    }

    #[test]
    fn non_finite_payload_is_rejected() {
        let mut f = frame(1);
        f.acc[2] = f32::NAN;
        let mut buf = [0u8; FRAME_MAX];
        let n = encode(&f, &mut buf).unwrap();
        assert_eq!(decode_in_place(&mut buf[..n - 1]), Err(DecodeError::Payload));
    }
}
