//! A ROS 1 bag (format 2.0) writer: chunks (uncompressed by default, or bz2 / lz4 like
//! `rosbag record --bz2/--lz4`), each followed by its index data records, then the index section (every connection record and a chunk info record per chunk),
//! and the bag header rewritten with the index position at [`Ros1BagWriter::finish`]. The
//! result is read by `rosbag` (ROS 1), the `rosbag` crate and Python `rosbags`.
//!
//! It writes any message type given its name, MD5 sum, full definition and serialised bytes
//! ([`Ros1BagWriter::add_connection`]); [`super::msg`] has the types and serialisers of
//! `sensor_msgs/PointCloud2`, `sensor_msgs/Imu`, `velodyne_msgs/VelodyneScan`,
//! `ouster_ros/PacketMsg` and `std_msgs/String`. This is how loglio hands simulated sequences
//! to other odometries.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{self, BufWriter, Seek, SeekFrom, Write};
use std::path::Path;

use super::msg::{Encoding, Imu, MessageType, PointCloud2};

const MAGIC: &[u8] = b"#ROSBAG V2.0\n";
/// The bag header record is padded to this many bytes so that it can be rewritten in place.
const HEADER_RECORD_LEN: usize = 4096;
const OP_MSG_DATA: u8 = 0x02;
const OP_BAG_HEADER: u8 = 0x03;
const OP_INDEX_DATA: u8 = 0x04;
const OP_CHUNK: u8 = 0x05;
const OP_CHUNK_INFO: u8 = 0x06;
const OP_CONNECTION: u8 = 0x07;

/// Chunk compression.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum ChunkCompression {
    /// Stored as is.
    #[default]
    None,
    /// bzip2 (`rosbag record --bz2`).
    Bz2,
    /// LZ4 frames (`rosbag record --lz4`).
    Lz4,
}

/// A connection (topic + type) of the bag being written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct ConnId(u32);

#[derive(Debug)]
struct Conn {
    header: Vec<u8>,
    data: Vec<u8>,
    written: bool,
}

#[derive(Debug)]
struct ChunkInfo {
    pos: u64,
    start: u64,
    end: u64,
    counts: BTreeMap<u32, u32>,
}

/// Writes a ROS 1 bag.
#[derive(Debug)]
pub struct Ros1BagWriter<W: Write + Seek> {
    w: W,
    start: u64,
    pos: u64,
    conns: Vec<Conn>,
    chunk: Vec<u8>,
    chunk_index: BTreeMap<u32, Vec<(u64, u32)>>,
    chunk_span: Option<(u64, u64)>,
    chunks: Vec<ChunkInfo>,
    threshold: usize,
    compression: ChunkCompression,
    messages: u64,
}

fn field(out: &mut Vec<u8>, name: &str, value: &[u8]) {
    out.extend_from_slice(&((name.len() + 1 + value.len()) as u32).to_le_bytes());
    out.extend_from_slice(name.as_bytes());
    out.push(b'=');
    out.extend_from_slice(value);
}

fn time_bytes(ns: u64) -> [u8; 8] {
    let mut b = [0u8; 8];
    b[..4].copy_from_slice(&((ns / 1_000_000_000) as u32).to_le_bytes());
    b[4..].copy_from_slice(&((ns % 1_000_000_000) as u32).to_le_bytes());
    b
}

fn record(out: &mut Vec<u8>, header: &[u8], data: &[u8]) {
    out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    out.extend_from_slice(header);
    out.extend_from_slice(&(data.len() as u32).to_le_bytes());
    out.extend_from_slice(data);
}

impl Ros1BagWriter<BufWriter<File>> {
    /// Creates (truncates) a bag file.
    pub fn create(path: &Path) -> io::Result<Self> {
        let f = File::create(path).map_err(|e| crate::output::with_path(e, path))?;
        Self::new(BufWriter::new(f))
    }
}

impl<W: Write + Seek> Ros1BagWriter<W> {
    /// Starts a bag on `w` (at its current position, normally 0).
    pub fn new(mut w: W) -> io::Result<Self> {
        let start = w.stream_position()?;
        let mut s = Ros1BagWriter {
            w,
            start,
            pos: start,
            conns: Vec::new(),
            chunk: Vec::new(),
            chunk_index: BTreeMap::new(),
            chunk_span: None,
            chunks: Vec::new(),
            threshold: 768 * 1024,
            compression: ChunkCompression::None,
            messages: 0,
        };
        s.put(MAGIC)?;
        let h = s.header_record(0)?;
        s.put(&h)?;
        Ok(s)
    }

    fn put(&mut self, b: &[u8]) -> io::Result<()> {
        self.w.write_all(b)?;
        self.pos += b.len() as u64;
        Ok(())
    }

    fn header_record(&self, index_pos: u64) -> io::Result<Vec<u8>> {
        let mut h = Vec::new();
        field(&mut h, "index_pos", &index_pos.to_le_bytes());
        field(&mut h, "conn_count", &(self.conns.len() as u32).to_le_bytes());
        field(&mut h, "chunk_count", &(self.chunks.len() as u32).to_le_bytes());
        field(&mut h, "op", &[OP_BAG_HEADER]);
        let pad = HEADER_RECORD_LEN
            .checked_sub(8 + h.len())
            .ok_or_else(|| io::Error::other("bag header record does not fit its 4096 bytes"))?;
        let mut out = Vec::with_capacity(HEADER_RECORD_LEN);
        record(&mut out, &h, &vec![b' '; pad]);
        Ok(out)
    }

    /// Chunks are closed once their data exceeds this many bytes (default 768 KiB, as `rosbag
    /// record`).
    pub fn set_chunk_threshold(&mut self, bytes: usize) {
        self.threshold = bytes.max(1);
    }

    /// Compression of the chunks closed from now on.
    pub fn set_compression(&mut self, c: ChunkCompression) {
        self.compression = c;
    }

    /// Declares a connection: a topic with its message type (`package/Name`), the type's MD5
    /// sum (32 hex digits) and full definition.
    pub fn add_connection(
        &mut self,
        topic: &str,
        msg_type: &str,
        md5sum: &str,
        definition: &str,
    ) -> io::Result<ConnId> {
        if md5sum.len() != 32 || !md5sum.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("md5sum `{md5sum}` is not 32 hex digits"),
            ));
        }
        let id = self.conns.len() as u32;
        let mut header = Vec::new();
        field(&mut header, "op", &[OP_CONNECTION]);
        field(&mut header, "conn", &id.to_le_bytes());
        field(&mut header, "topic", topic.as_bytes());
        let mut data = Vec::new();
        field(&mut data, "topic", topic.as_bytes());
        field(&mut data, "type", msg_type.as_bytes());
        field(&mut data, "md5sum", md5sum.to_ascii_lowercase().as_bytes());
        field(&mut data, "message_definition", definition.as_bytes());
        field(&mut data, "callerid", b"/loglio");
        field(&mut data, "latching", b"0");
        self.conns.push(Conn { header, data, written: false });
        Ok(ConnId(id))
    }

    /// [`Self::add_connection`] for one of the types in [`super::msg`].
    pub fn add_typed_connection(&mut self, topic: &str, t: &MessageType) -> io::Result<ConnId> {
        self.add_connection(topic, t.name, t.md5sum, t.definition)
    }

    /// Appends one message (ROS 1 serialised) received at `time_ns`.
    pub fn write(&mut self, conn: ConnId, time_ns: u64, data: &[u8]) -> io::Result<()> {
        if time_ns / 1_000_000_000 > u32::MAX as u64 {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "time past 2106 does not fit a ROS 1 time",
            ));
        }
        let c = self
            .conns
            .get_mut(conn.0 as usize)
            .ok_or_else(|| io::Error::new(io::ErrorKind::InvalidInput, "unknown connection"))?;
        if !c.written {
            c.written = true;
            let (h, d) = (c.header.clone(), c.data.clone());
            record(&mut self.chunk, &h, &d);
        }
        let offset = self.chunk.len() as u32;
        let mut h = Vec::new();
        field(&mut h, "op", &[OP_MSG_DATA]);
        field(&mut h, "conn", &conn.0.to_le_bytes());
        field(&mut h, "time", &time_bytes(time_ns));
        record(&mut self.chunk, &h, data);
        self.chunk_index.entry(conn.0).or_default().push((time_ns, offset));
        self.chunk_span = Some(match self.chunk_span {
            None => (time_ns, time_ns),
            Some((a, b)) => (a.min(time_ns), b.max(time_ns)),
        });
        self.messages += 1;
        if self.chunk.len() >= self.threshold {
            self.close_chunk()?;
        }
        Ok(())
    }

    /// Appends a `sensor_msgs/PointCloud2`.
    pub fn write_point_cloud2(&mut self, conn: ConnId, time_ns: u64, cloud: &PointCloud2) -> io::Result<()> {
        self.write(conn, time_ns, &cloud.encode(Encoding::Ros1))
    }

    /// Appends a `sensor_msgs/Imu`.
    pub fn write_imu(&mut self, conn: ConnId, time_ns: u64, imu: &Imu, frame_id: &str) -> io::Result<()> {
        self.write(conn, time_ns, &imu.encode(frame_id, Encoding::Ros1))
    }

    /// Messages written so far.
    pub fn messages(&self) -> u64 {
        self.messages
    }

    fn close_chunk(&mut self) -> io::Result<()> {
        let Some((start, end)) = self.chunk_span.take() else { return Ok(()) };
        let chunk_pos = self.pos;
        let mut h = Vec::new();
        field(&mut h, "op", &[OP_CHUNK]);
        let size = self.chunk.len() as u32;
        let (name, data): (&[u8], Vec<u8>) = match self.compression {
            ChunkCompression::None => (b"none", std::mem::take(&mut self.chunk)),
            ChunkCompression::Bz2 => {
                let mut enc = bzip2::write::BzEncoder::new(Vec::new(), bzip2::Compression::best());
                enc.write_all(&self.chunk)?;
                (b"bz2", enc.finish()?)
            }
            ChunkCompression::Lz4 => {
                let mut enc = lz4::EncoderBuilder::new().build(Vec::new())?;
                enc.write_all(&self.chunk)?;
                let (out, r) = enc.finish();
                r?;
                (b"lz4", out)
            }
        };
        field(&mut h, "compression", name);
        field(&mut h, "size", &size.to_le_bytes());
        let mut out = Vec::with_capacity(data.len() + 64);
        record(&mut out, &h, &data);
        let mut counts = BTreeMap::new();
        for (conn, entries) in std::mem::take(&mut self.chunk_index) {
            let mut h = Vec::new();
            field(&mut h, "op", &[OP_INDEX_DATA]);
            field(&mut h, "ver", &1u32.to_le_bytes());
            field(&mut h, "conn", &conn.to_le_bytes());
            field(&mut h, "count", &(entries.len() as u32).to_le_bytes());
            let mut d = Vec::with_capacity(entries.len() * 12);
            for (t, off) in &entries {
                d.extend_from_slice(&time_bytes(*t));
                d.extend_from_slice(&off.to_le_bytes());
            }
            record(&mut out, &h, &d);
            counts.insert(conn, entries.len() as u32);
        }
        self.chunk.clear();
        self.put(&out)?;
        self.chunks.push(ChunkInfo { pos: chunk_pos, start, end, counts });
        Ok(())
    }

    /// Pushes buffered bytes of closed chunks to the underlying writer (the open chunk stays in
    /// memory until it fills or [`Self::finish`]).
    pub fn flush(&mut self) -> io::Result<()> {
        self.w.flush()
    }

    /// Closes the last chunk, writes the index section, rewrites the bag header and returns
    /// the underlying writer.
    pub fn finish(mut self) -> io::Result<W> {
        self.close_chunk()?;
        let index_pos = self.pos;
        let mut out = Vec::new();
        for c in &self.conns {
            record(&mut out, &c.header, &c.data);
        }
        for ci in &self.chunks {
            let mut h = Vec::new();
            field(&mut h, "op", &[OP_CHUNK_INFO]);
            field(&mut h, "ver", &1u32.to_le_bytes());
            field(&mut h, "chunk_pos", &ci.pos.to_le_bytes());
            field(&mut h, "start_time", &time_bytes(ci.start));
            field(&mut h, "end_time", &time_bytes(ci.end));
            field(&mut h, "count", &(ci.counts.len() as u32).to_le_bytes());
            let mut d = Vec::new();
            for (conn, n) in &ci.counts {
                d.extend_from_slice(&conn.to_le_bytes());
                d.extend_from_slice(&n.to_le_bytes());
            }
            record(&mut out, &h, &d);
        }
        self.put(&out)?;
        let end = self.pos;
        let header = self.header_record(index_pos)?;
        self.w.seek(SeekFrom::Start(self.start + MAGIC.len() as u64))?;
        self.w.write_all(&header)?;
        self.w.seek(SeekFrom::Start(end))?;
        self.w.flush()?;
        Ok(self.w)
    }
}
