//! Recorded sequences for the core running as firmware: a compact binary file of IMU samples and
//! scans that the host writes from a scenario and the Cortex-M firmware (`loglio-fw`) reads
//! through semihosting, the odometry configuration both sides run, and the pose lines both sides
//! print so that their outputs compare as text.
//!
//! ## File format (version 1, every number little-endian)
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 8 | magic `LGLIOREP` |
//! | 8 | 2 | version, `1` |
//! | 10 | 2 | range-image rows `R` (1..=128) |
//! | 12 | 2 | range-image columns (8..=3600) |
//! | 14 | 1 | flags: bit 0 = columns advance clockwise; other bits 0 |
//! | 15 | 1 | reserved, 0 |
//! | 16 | 32 | IMU-from-LiDAR rotation, unit quaternion `w, x, y, z`, f64 |
//! | 48 | 24 | LiDAR origin in the IMU frame `x, y, z`, m, f64 |
//! | 72 | 8 R | per row: elevation, azimuth of column 0 (radians, f32, f32) |
//!
//! Then records, each a tag byte and its body, in the order the odometry consumes them (every
//! IMU sample up to a scan's end before that scan):
//!
//! | tag | body | size |
//! |---|---|---|
//! | `0x01` IMU sample | `t_ns` u64, gyro xyz f32 (rad/s), acc xyz f32 (m/s^2) | 32 |
//! | `0x02` scan | `start_ns` u64, point count `n` u32, then `n` points | 12 + 24 n |
//! | `0x00` end | nothing; must be the last byte | 0 |
//!
//! A point is the core's [`ScanPoint`]: x, y, z, t (f32), row, col, intensity (u16), return
//! index (u8), flags (u8): 24 bytes.
//!
//! The reader ([`Reader`]) works on any [`embedded_io::Read`] and never panics on bad input: a
//! wrong magic or version, an invalid layout or extrinsic, an unknown tag, a scan larger than the
//! caller's buffer or a truncated file is a [`ReplayError`]. The writer ([`Writer`],
//! [`record_scenario`]) is host-only.

use core::fmt;

use loglio_core::imu::ImuSample;
use loglio_core::odometry::{OdometryConfig, OdometryStorage};
use loglio_core::output::{ScanResult, Status};
use loglio_core::range_image::{LayoutError, MAX_ROWS, RangeImageLayout};
use loglio_core::ring_fals::storage_pixels;
use loglio_core::scan::ScanPoint;
use nalgebra::{Quaternion, UnitQuaternion, Vector3};

/// File magic.
pub const MAGIC: [u8; 8] = *b"LGLIOREP";
/// Format version.
pub const VERSION: u16 = 1;
/// Header bytes before the per-row table.
pub const HEADER_FIXED: usize = 72;
/// Bytes of one point.
pub const POINT_BYTES: usize = 24;
/// Record tag: end of file.
pub const TAG_END: u8 = 0x00;
/// Record tag: one IMU sample.
pub const TAG_IMU: u8 = 0x01;
/// Record tag: one scan.
pub const TAG_SCAN: u8 = 0x02;

// ---- The firmware configuration (shared by the firmware and the host test) ------------------

/// Range-image rows of the firmware configuration (a 16-beam LiDAR).
///
/// The firmware configuration is sized for QEMU's mps2-an386 (Cortex-M4F, 16 MiB of RAM): the
/// storage below is about 8.7 MiB, the rest is the scan buffer, code data and the stack.
pub const FW_ROWS: usize = 16;
/// Range-image columns of the firmware configuration: Ouster OS1-16 in its 512 x 10 mode (8,192
/// points per scan). The 1024 x 10 mode also runs (and fits the RAM with `FW_COLS = 1024`) but
/// needs 1.4 times the instructions per scan (the 512 x 10 budget: docs/firmware.md).
pub const FW_COLS: usize = 512;
/// Points per scan the firmware keeps (a full 16 x 512 frame).
pub const FW_POINTS: usize = FW_ROWS * FW_COLS;
/// Downsampling slots (power of two; at most 3/4 of them are used per scan).
pub const FW_DOWNSAMPLE_SLOTS: usize = 8192;
/// Voxels in the map pool: 2^15 x 192 bytes = 6 MiB (the host presets use 2^18 = 48 MiB).
pub const FW_POOL_VOXELS: usize = 1 << 15;
/// Map index slots (a power of two, at least twice the pool): 2^16 x 8 bytes = 512 KiB.
pub const FW_INDEX_SLOTS: usize = 1 << 16;
/// Map eviction radius of the firmware configuration, m: the ground disc inside it
/// (`pi R^2 / L^2` = 20,000 voxels at 0.5 m) fills well under the pool.
pub const FW_EVICT_RADIUS: f32 = 40.0;

/// All the odometry memory of the firmware configuration (it lives in a `static`, in `.bss`).
pub type FirmwareStorage = OdometryStorage<
    { storage_pixels(FW_ROWS, FW_COLS) },
    FW_POINTS,
    FW_DOWNSAMPLE_SLOTS,
    FW_POOL_VOXELS,
    FW_INDEX_SLOTS,
>;

/// The odometry configuration of the firmware replay, from a recording's header: the OS1-16
/// preset ([`OdometryConfig::os1_16`], the paper's NTU VIRAL setup) with the recording's extrinsic
/// and the reduced map above (eviction radius and range [`FW_EVICT_RADIUS`]).
pub fn firmware_config(header: &Header) -> OdometryConfig {
    let mut cfg =
        OdometryConfig::os1_16(header.layout.clone()).with_extrinsic(header.ext_rot, header.ext_pos);
    cfg.map.evict_radius = FW_EVICT_RADIUS;
    cfg.max_range = FW_EVICT_RADIUS;
    cfg
}

// ---- Pose lines --------------------------------------------------------------------------------

/// A short name of a status (the pose line's second field).
pub fn status_name(s: &Status) -> &'static str {
    match s {
        Status::Ok => "ok",
        Status::Degraded { .. } => "degraded",
        Status::Bridged(_) => "bridged",
        Status::Lost { .. } => "lost",
        Status::ImuOnly(_) => "imu-only",
        Status::Initialising(_) => "initialising",
        Status::Reinitialising(_) => "reinitialising",
    }
}

/// Writes one scan's result as one line (no newline): `pose <scan> <status> <t_ns> <points>
/// <downsampled>` followed by the f64 bit patterns, as 16 hex digits each, of the rotation
/// (w, x, y, z), position, velocity, gyro bias, accelerometer bias, gravity and the diagonal of
/// the pose covariance. Equal lines mean bit-identical estimates.
pub fn write_pose_line<W: fmt::Write>(w: &mut W, scan: u32, r: &ScanResult) -> fmt::Result {
    let p = &r.pose;
    write!(w, "pose {scan} {} {} {} {}", status_name(&r.status), p.t_ns, r.points[0], r.points[1])?;
    let q = p.rotation.quaternion();
    let mut put = |v: f64| write!(w, " {:016x}", v.to_bits());
    for v in [q.w, q.i, q.j, q.k] {
        put(v)?;
    }
    for vec in [&p.position, &p.velocity, &p.gyro_bias, &p.acc_bias, &p.gravity] {
        for v in vec.iter() {
            put(*v)?;
        }
    }
    for k in 0..6 {
        put(p.covariance[(k, k)])?;
    }
    Ok(())
}

// ---- Reader ------------------------------------------------------------------------------------

/// A recording's header: what the odometry configuration needs from the sensor.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    /// The LiDAR's range image.
    pub layout: RangeImageLayout,
    /// IMU-from-LiDAR rotation.
    pub ext_rot: UnitQuaternion<f64>,
    /// LiDAR origin in the IMU frame, m.
    pub ext_pos: Vector3<f64>,
}

/// One record.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Record {
    /// An IMU sample.
    Imu(ImuSample),
    /// A scan: its start time and the number of points written to the caller's buffer.
    Scan {
        /// Scan start, ns.
        start_ns: u64,
        /// Points in the buffer.
        points: usize,
    },
    /// The end of the recording.
    End,
}

/// Why a recording cannot be read.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ReplayError<E> {
    /// The underlying reader failed.
    Io(E),
    /// The file ends inside the header or a record (or has no end record).
    Truncated,
    /// Not a recording (the magic is wrong).
    BadMagic,
    /// A version this reader does not know.
    Version(u16),
    /// Unknown header flags or a non-zero reserved byte (flags, reserved).
    Flags(u8, u8),
    /// The range-image layout in the header is invalid.
    Layout(LayoutError),
    /// The extrinsic is not finite or the quaternion is far from unit length.
    Extrinsic,
    /// An unknown record tag.
    Tag(u8),
    /// A scan holds more points than the caller's buffer.
    TooManyPoints {
        /// Points in the scan.
        count: u32,
        /// The buffer's capacity.
        capacity: usize,
    },
    /// Bytes after the end record.
    TrailingData,
}

impl<E: fmt::Debug> fmt::Display for ReplayError<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io(e) => write!(f, "read error: {e:?}"),
            Self::Truncated => f.write_str("recording is truncated"),
            Self::BadMagic => f.write_str("not a loglio recording (bad magic)"),
            Self::Version(v) => write!(f, "recording version {v} is not supported (expected {VERSION})"),
            Self::Flags(fl, r) => write!(f, "unknown header flags 0x{fl:02x} / reserved byte 0x{r:02x}"),
            Self::Layout(e) => write!(f, "invalid range-image layout: {e}"),
            Self::Extrinsic => f.write_str("invalid extrinsic (not finite or not a unit quaternion)"),
            Self::Tag(t) => write!(f, "unknown record tag 0x{t:02x}"),
            Self::TooManyPoints { count, capacity } => {
                write!(f, "scan of {count} points exceeds the buffer of {capacity}")
            }
            Self::TrailingData => f.write_str("data after the end record"),
        }
    }
}

impl<E: fmt::Debug> core::error::Error for ReplayError<E> {}

/// Reads a recording record by record from any [`embedded_io::Read`].
#[derive(Debug)]
pub struct Reader<R> {
    r: R,
    ended: bool,
}

fn le_u16(b: &[u8], o: usize) -> u16 {
    u16::from_le_bytes([b[o], b[o + 1]])
}
fn le_u32(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
}
fn le_u64(b: &[u8], o: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[o..o + 8]);
    u64::from_le_bytes(a)
}
fn le_f32(b: &[u8], o: usize) -> f32 {
    f32::from_bits(le_u32(b, o))
}
fn le_f64(b: &[u8], o: usize) -> f64 {
    f64::from_bits(le_u64(b, o))
}

/// Decodes one point (`b` holds at least [`POINT_BYTES`]).
fn decode_point(b: &[u8]) -> ScanPoint {
    ScanPoint {
        xyz: [le_f32(b, 0), le_f32(b, 4), le_f32(b, 8)],
        t: le_f32(b, 12),
        row: le_u16(b, 16),
        col: le_u16(b, 18),
        intensity: le_u16(b, 20),
        ret: b[22],
        flags: b[23],
    }
}

impl<R: embedded_io::Read> Reader<R> {
    /// Reads and checks the header.
    pub fn new(mut r: R) -> Result<(Self, Header), ReplayError<R::Error>> {
        let mut h = [0u8; HEADER_FIXED];
        read_exact(&mut r, &mut h)?;
        if h[0..8] != MAGIC {
            return Err(ReplayError::BadMagic);
        }
        let version = le_u16(&h, 8);
        if version != VERSION {
            return Err(ReplayError::Version(version));
        }
        let rows = le_u16(&h, 10) as usize;
        let cols = le_u16(&h, 12) as usize;
        let flags = h[14];
        if flags & !1 != 0 || h[15] != 0 {
            return Err(ReplayError::Flags(flags, h[15]));
        }
        let mut layout = RangeImageLayout::new(rows, cols, flags & 1 != 0).map_err(ReplayError::Layout)?;
        let q = Quaternion::new(le_f64(&h, 16), le_f64(&h, 24), le_f64(&h, 32), le_f64(&h, 40));
        let ext_pos = Vector3::new(le_f64(&h, 48), le_f64(&h, 56), le_f64(&h, 64));
        let qn = q.norm();
        if !(q.coords.iter().all(|v| v.is_finite())
            && ext_pos.iter().all(|v| v.is_finite())
            && libm::fabs(qn - 1.0) < 1e-6)
        {
            return Err(ReplayError::Extrinsic);
        }
        // Only `rows <= MAX_ROWS` reach here (checked by the layout).
        let mut row_buf = [0u8; 8 * MAX_ROWS];
        let row_bytes = &mut row_buf[..8 * rows];
        read_exact(&mut r, row_bytes)?;
        for row in 0..rows {
            layout
                .set_row(row, le_f32(row_bytes, 8 * row), le_f32(row_bytes, 8 * row + 4))
                .map_err(ReplayError::Layout)?;
        }
        let header = Header { layout, ext_rot: UnitQuaternion::new_unchecked(q), ext_pos };
        Ok((Self { r, ended: false }, header))
    }

    /// The next record; a scan's points go to `points[..n]`. After [`Record::End`] it keeps
    /// returning `End`.
    pub fn next_record(&mut self, points: &mut [ScanPoint]) -> Result<Record, ReplayError<R::Error>> {
        if self.ended {
            return Ok(Record::End);
        }
        let mut tag = [0u8; 1];
        read_exact(&mut self.r, &mut tag)?;
        match tag[0] {
            TAG_END => {
                self.ended = true;
                // Nothing may follow the end record.
                match self.r.read(&mut tag) {
                    Ok(0) => Ok(Record::End),
                    Ok(_) => Err(ReplayError::TrailingData),
                    Err(e) => Err(ReplayError::Io(e)),
                }
            }
            TAG_IMU => {
                let mut b = [0u8; 32];
                read_exact(&mut self.r, &mut b)?;
                Ok(Record::Imu(ImuSample {
                    t_ns: le_u64(&b, 0),
                    gyro: [le_f32(&b, 8), le_f32(&b, 12), le_f32(&b, 16)],
                    acc: [le_f32(&b, 20), le_f32(&b, 24), le_f32(&b, 28)],
                }))
            }
            TAG_SCAN => {
                let mut b = [0u8; 12];
                read_exact(&mut self.r, &mut b)?;
                let start_ns = le_u64(&b, 0);
                let count = le_u32(&b, 8);
                if count as usize > points.len() {
                    return Err(ReplayError::TooManyPoints { count, capacity: points.len() });
                }
                // Points in chunks: one read call per 170 points.
                let mut chunk = [0u8; 170 * POINT_BYTES];
                let n = count as usize;
                let mut done = 0;
                while done < n {
                    let k = (n - done).min(170);
                    let bytes = &mut chunk[..k * POINT_BYTES];
                    read_exact(&mut self.r, bytes)?;
                    for (i, pb) in bytes.chunks_exact(POINT_BYTES).enumerate() {
                        points[done + i] = decode_point(pb);
                    }
                    done += k;
                }
                Ok(Record::Scan { start_ns, points: n })
            }
            t => Err(ReplayError::Tag(t)),
        }
    }
}

fn read_exact<R: embedded_io::Read>(r: &mut R, buf: &mut [u8]) -> Result<(), ReplayError<R::Error>> {
    r.read_exact(buf).map_err(|e| match e {
        embedded_io::ReadExactError::UnexpectedEof => ReplayError::Truncated,
        embedded_io::ReadExactError::Other(e) => ReplayError::Io(e),
    })
}

// ---- Writer (host) ---------------------------------------------------------------------------

#[cfg(not(target_os = "none"))]
pub use writer::{RecordingStats, Writer, record_scenario};

#[cfg(not(target_os = "none"))]
mod writer {
    use std::io::{self, Write};

    use loglio_core::imu::ImuSample;
    use loglio_core::range_image::RangeImageLayout;
    use loglio_core::scan::ScanPoint;
    use nalgebra::{UnitQuaternion, Vector3};

    use super::{HEADER_FIXED, MAGIC, POINT_BYTES, TAG_END, TAG_IMU, TAG_SCAN, VERSION};
    use crate::scenario::{Event, Scenario};

    /// Writes a recording (see the module docs for the format).
    #[derive(Debug)]
    pub struct Writer<W: Write> {
        w: W,
    }

    impl<W: Write> Writer<W> {
        /// Writes the header.
        pub fn new(
            mut w: W,
            layout: &RangeImageLayout,
            ext_rot: &UnitQuaternion<f64>,
            ext_pos: &Vector3<f64>,
        ) -> io::Result<Self> {
            let mut h = Vec::with_capacity(HEADER_FIXED + 8 * layout.rows());
            h.extend_from_slice(&MAGIC);
            h.extend_from_slice(&VERSION.to_le_bytes());
            h.extend_from_slice(&(layout.rows() as u16).to_le_bytes());
            h.extend_from_slice(&(layout.cols() as u16).to_le_bytes());
            h.push(layout.clockwise() as u8);
            h.push(0);
            let q = ext_rot.quaternion();
            for v in [q.w, q.i, q.j, q.k, ext_pos.x, ext_pos.y, ext_pos.z] {
                h.extend_from_slice(&v.to_le_bytes());
            }
            debug_assert_eq!(h.len(), HEADER_FIXED);
            for row in 0..layout.rows() {
                h.extend_from_slice(&layout.elevation(row).to_le_bytes());
                h.extend_from_slice(&layout.azimuth0(row).to_le_bytes());
            }
            w.write_all(&h)?;
            Ok(Self { w })
        }

        /// Writes one IMU sample.
        pub fn imu(&mut self, s: &ImuSample) -> io::Result<()> {
            let mut b = [0u8; 33];
            b[0] = TAG_IMU;
            b[1..9].copy_from_slice(&s.t_ns.to_le_bytes());
            for (i, v) in s.gyro.iter().chain(s.acc.iter()).enumerate() {
                b[9 + 4 * i..13 + 4 * i].copy_from_slice(&v.to_le_bytes());
            }
            self.w.write_all(&b)
        }

        /// Writes one scan.
        pub fn scan(&mut self, start_ns: u64, points: &[ScanPoint]) -> io::Result<()> {
            let count = u32::try_from(points.len())
                .map_err(|_| io::Error::new(io::ErrorKind::InvalidInput, "scan too large"))?;
            let mut b = Vec::with_capacity(13 + POINT_BYTES * points.len());
            b.push(TAG_SCAN);
            b.extend_from_slice(&start_ns.to_le_bytes());
            b.extend_from_slice(&count.to_le_bytes());
            for p in points {
                for v in [p.xyz[0], p.xyz[1], p.xyz[2], p.t] {
                    b.extend_from_slice(&v.to_le_bytes());
                }
                for v in [p.row, p.col, p.intensity] {
                    b.extend_from_slice(&v.to_le_bytes());
                }
                b.push(p.ret);
                b.push(p.flags);
            }
            self.w.write_all(&b)
        }

        /// Writes the end record and returns the sink.
        pub fn finish(mut self) -> io::Result<W> {
            self.w.write_all(&[TAG_END])?;
            self.w.flush()?;
            Ok(self.w)
        }
    }

    /// What [`record_scenario`] wrote.
    #[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
    pub struct RecordingStats {
        /// IMU samples.
        pub imu: usize,
        /// Scans.
        pub scans: usize,
        /// Points in all scans.
        pub points: usize,
        /// The largest scan.
        pub max_points: usize,
    }

    /// Records every event of a scenario (IMU samples and scans, in time order).
    pub fn record_scenario<W: Write>(sc: &Scenario, w: W) -> io::Result<(W, RecordingStats)> {
        let ext = sc.extrinsic();
        let mut wr = Writer::new(w, sc.layout(), &ext.rotation, &ext.translation.vector)?;
        let mut st = RecordingStats::default();
        for ev in sc.events() {
            match ev {
                Event::Imu(s) => {
                    wr.imu(&s)?;
                    st.imu += 1;
                }
                Event::Scan(s) => {
                    wr.scan(s.start_ns, &s.points)?;
                    st.scans += 1;
                    st.points += s.points.len();
                    st.max_points = st.max_points.max(s.points.len());
                }
            }
        }
        Ok((wr.finish()?, st))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout() -> RangeImageLayout {
        let mut l = RangeImageLayout::new(2, 16, true).unwrap();
        l.set_row(0, 0.1, 0.01).unwrap();
        l.set_row(1, -0.1, -0.02).unwrap();
        l
    }

    fn point(i: u16) -> ScanPoint {
        ScanPoint {
            xyz: [1.0 + i as f32, -2.5, 0.125],
            t: 1e-4 * i as f32,
            row: i % 2,
            col: i,
            intensity: 7,
            ret: 1,
            flags: 3,
        }
    }

    fn recording() -> Vec<u8> {
        let rot = UnitQuaternion::from_euler_angles(0.01, -0.02, 0.03);
        let mut w = Writer::new(Vec::new(), &layout(), &rot, &Vector3::new(0.1, 0.2, -0.3)).unwrap();
        w.imu(&ImuSample { t_ns: 5, gyro: [0.1, 0.2, 0.3], acc: [0.0, 0.0, 9.81] }).unwrap();
        let pts: Vec<ScanPoint> = (0..400).map(point).collect();
        w.scan(1_000, &pts).unwrap();
        w.finish().unwrap()
    }

    #[test]
    fn round_trip() {
        let bytes = recording();
        assert_eq!(bytes.len(), HEADER_FIXED + 16 + 33 + 13 + 400 * POINT_BYTES + 1);
        let (mut r, h) = Reader::new(&bytes[..]).unwrap();
        assert_eq!(h.layout, layout());
        assert_eq!(h.ext_pos, Vector3::new(0.1, 0.2, -0.3));
        assert_eq!(h.ext_rot, UnitQuaternion::from_euler_angles(0.01, -0.02, 0.03));
        let mut buf = [ScanPoint::default(); 512];
        assert_eq!(
            r.next_record(&mut buf).unwrap(),
            Record::Imu(ImuSample { t_ns: 5, gyro: [0.1, 0.2, 0.3], acc: [0.0, 0.0, 9.81] })
        );
        assert_eq!(r.next_record(&mut buf).unwrap(), Record::Scan { start_ns: 1_000, points: 400 });
        for i in 0..400 {
            assert_eq!(buf[i as usize], point(i));
        }
        assert_eq!(r.next_record(&mut buf).unwrap(), Record::End);
        assert_eq!(r.next_record(&mut buf).unwrap(), Record::End);
    }

    #[test]
    fn bad_input_is_an_error_never_a_panic() {
        let good = recording();
        let mut buf = [ScanPoint::default(); 512];
        // Every truncation is `Truncated` (or, inside the header, possibly a layout error).
        for cut in 0..good.len() {
            let res = Reader::new(&good[..cut]).and_then(|(mut r, _)| {
                loop {
                    match r.next_record(&mut buf)? {
                        Record::End => break Ok(()),
                        _ => continue,
                    }
                }
            });
            assert_eq!(res, Err(ReplayError::Truncated), "cut at {cut}");
        }
        let mut bad = good.clone();
        bad[0] = b'X';
        assert_eq!(Reader::new(&bad[..]).unwrap_err(), ReplayError::BadMagic);
        let mut bad = good.clone();
        bad[8] = 2;
        assert_eq!(Reader::new(&bad[..]).unwrap_err(), ReplayError::Version(2));
        let mut bad = good.clone();
        bad[10] = 0;
        assert_eq!(Reader::new(&bad[..]).unwrap_err(), ReplayError::Layout(LayoutError::BadRows));
        let mut bad = good.clone();
        bad[16..24].copy_from_slice(&2.0f64.to_le_bytes());
        assert_eq!(Reader::new(&bad[..]).unwrap_err(), ReplayError::Extrinsic);
        let mut bad = good.clone();
        bad[HEADER_FIXED + 16] = 0x07;
        let (mut r, _) = Reader::new(&bad[..]).unwrap();
        assert_eq!(r.next_record(&mut buf), Err(ReplayError::Tag(7)));
        let (mut r, _) = Reader::new(&good[..]).unwrap();
        let mut small = [ScanPoint::default(); 100];
        r.next_record(&mut small).unwrap();
        assert_eq!(r.next_record(&mut small), Err(ReplayError::TooManyPoints { count: 400, capacity: 100 }));
        let mut bad = good.clone();
        bad.push(0);
        let (mut r, _) = Reader::new(&bad[..]).unwrap();
        r.next_record(&mut buf).unwrap();
        r.next_record(&mut buf).unwrap();
        assert_eq!(r.next_record(&mut buf), Err(ReplayError::TrailingData));
    }

    #[test]
    fn the_firmware_storage_fits_the_board() {
        // mps2-an386 has 16 MiB of RAM (memory.x); the pool must leave room for the stack and the
        // replay buffers. The linker enforces the hard limit; this keeps a margin.
        let bytes = FirmwareStorage::bytes() + FW_POINTS * core::mem::size_of::<ScanPoint>();
        assert!(bytes < 13 << 20, "{bytes} bytes");
    }
}
