//! A ROS 1 bag read without its index, as `rosbag reindex` would: the records are walked from
//! the bag header on (format 2.0: `header_len, header, data_len, data`, the header a list of
//! `len, name=value` fields with `op` the record type). Chunks (op 5; none, bz2 or lz4) hold
//! connection (op 7) and message data (op 2) records; connection records outside chunks (the
//! index section) are taken too; index data (op 4) and chunk info (op 6) records are skipped.
//!
//! A recorder that was stopped abruptly leaves no index (index_pos 0); a copy cut short loses
//! it. Everything before the first record whose framing is broken (a length past the end of
//! the file, a header that does not parse) is read; the walk stops there. A chunk whose framing
//! is whole but whose contents are damaged is reported; its messages before the damage are
//! kept and the walk goes on.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};

const OP_MSG_DATA: u8 = 0x02;
const OP_BAG_HEADER: u8 = 0x03;
const OP_CHUNK: u8 = 0x05;
const OP_CONNECTION: u8 = 0x07;
/// Record headers are a few hundred bytes; a longer one is damage, not data.
const MAX_HEADER: usize = 1 << 20;
/// A chunk is at most this big decompressed (`rosbag record` closes them at 768 KiB); a bigger
/// size field is damage, and would otherwise be allocated.
const MAX_CHUNK: usize = 1 << 29;

/// One record: its op, header fields and data.
struct Record {
    op: u8,
    fields: Vec<(Vec<u8>, Vec<u8>)>,
    data: Vec<u8>,
}

impl Record {
    fn field(&self, name: &[u8]) -> Option<&[u8]> {
        self.fields.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_slice())
    }
}

/// Splits `len, name=value` fields; `None` if they do not parse.
fn parse_fields(h: &[u8]) -> Option<Vec<(Vec<u8>, Vec<u8>)>> {
    let mut fields = Vec::new();
    let mut rest = h;
    while !rest.is_empty() {
        let n = u32::from_le_bytes(rest.get(..4)?.try_into().ok()?) as usize;
        let f = rest.get(4..4usize.checked_add(n)?)?;
        let eq = f.iter().position(|&b| b == b'=')?;
        fields.push((f[..eq].to_vec(), f[eq + 1..].to_vec()));
        rest = &rest[4 + n..];
    }
    Some(fields)
}

/// A record header's fields: (name, value) pairs.
type Fields = Vec<(Vec<u8>, Vec<u8>)>;

/// Splits a record header into fields; `None` if it does not parse or has no one-byte `op`.
fn parse_header(h: &[u8]) -> Option<(u8, Fields)> {
    let fields = parse_fields(h)?;
    let op = match fields.iter().find(|(n, _)| n == b"op") {
        Some((_, v)) if v.len() == 1 => v[0],
        _ => return None,
    };
    Some((op, fields))
}

fn u32_of(v: Option<&[u8]>) -> Option<u32> {
    Some(u32::from_le_bytes(v?.try_into().ok()?))
}

/// A ROS time field (sec, nsec) in ns.
fn time_of(v: Option<&[u8]>) -> Option<u64> {
    let v = v?;
    let s = u32::from_le_bytes(v.get(..4)?.try_into().ok()?) as u64;
    let ns = u32::from_le_bytes(v.get(4..8)?.try_into().ok()?) as u64;
    Some(s * 1_000_000_000 + ns)
}

/// Reads the record at the reader's position; `Err` says why its framing is broken.
fn read_record(r: &mut impl Read, remaining: u64) -> Result<(Record, u64), String> {
    let mut b4 = [0u8; 4];
    let take = |r: &mut dyn Read, n: u64, what: &str, used: u64| -> Result<Vec<u8>, String> {
        if used.saturating_add(n) > remaining {
            return Err(format!("{what} runs past the end of the file"));
        }
        let mut v = vec![0u8; n as usize];
        r.read_exact(&mut v).map_err(|e| format!("{what}: {e}"))?;
        Ok(v)
    };
    if remaining < 4 {
        return Err("the file ends inside a record".into());
    }
    r.read_exact(&mut b4).map_err(|e| format!("record length: {e}"))?;
    let hlen = u32::from_le_bytes(b4) as u64;
    if hlen as usize > MAX_HEADER {
        return Err(format!("a record header of {hlen} bytes"));
    }
    let header = take(r, hlen, "a record header", 4)?;
    let (op, fields) = parse_header(&header).ok_or("a record header that does not parse")?;
    let d = take(r, 4, "a record", 4 + hlen)?;
    let dlen = u32::from_le_bytes([d[0], d[1], d[2], d[3]]) as u64;
    let data = take(r, dlen, "a record's data", 8 + hlen)?;
    Ok((Record { op, fields, data }, 8 + hlen + dlen))
}

/// A connection: id, topic, message type.
pub(super) type Conn = (u32, String, String);

/// The records of a chunk's (decompressed) data: connections and messages (connection, record
/// time, bytes) up to the first damaged record, and what that damage is.
pub(super) struct ChunkContents {
    pub conns: Vec<Conn>,
    pub messages: Vec<(u32, u64, Vec<u8>)>,
    pub damage: Option<String>,
}

fn connection(r: &Record) -> Option<Conn> {
    let id = u32_of(r.field(b"conn"))?;
    let data_fields = parse_fields(&r.data)?;
    let get = |n: &[u8]| data_fields.iter().find(|(k, _)| k == n).map(|(_, v)| v.clone());
    let topic = r.field(b"topic").map(<[u8]>::to_vec).or_else(|| get(b"topic"))?;
    let ty = get(b"type")?;
    Some((id, String::from_utf8(topic).ok()?, String::from_utf8(ty).ok()?))
}

fn decompress(r: &Record) -> Result<Vec<u8>, String> {
    let size = u32_of(r.field(b"size")).ok_or("a chunk without a size")? as usize;
    if size > MAX_CHUNK {
        return Err(format!("a chunk size of {size} bytes"));
    }
    let mut out = Vec::with_capacity(size.min(64 << 20));
    let limit = size as u64 + 1;
    match r.field(b"compression") {
        Some(b"none") => out.extend_from_slice(&r.data),
        Some(b"bz2") => {
            bzip2::read::BzDecoder::new(r.data.as_slice())
                .take(limit)
                .read_to_end(&mut out)
                .map_err(|e| format!("bz2: {e}"))?;
        }
        Some(b"lz4") => {
            lz4::Decoder::new(r.data.as_slice())
                .map_err(|e| format!("lz4: {e}"))?
                .take(limit)
                .read_to_end(&mut out)
                .map_err(|e| format!("lz4: {e}"))?;
        }
        Some(c) => return Err(format!("unknown compression `{}`", String::from_utf8_lossy(c))),
        None => return Err("a chunk without a compression field".into()),
    }
    if out.len() != size {
        return Err(format!("{} bytes decompressed, the chunk says {size}", out.len()));
    }
    Ok(out)
}

fn chunk_contents(r: &Record) -> ChunkContents {
    let mut c = ChunkContents { conns: Vec::new(), messages: Vec::new(), damage: None };
    let data = match decompress(r) {
        Ok(d) => d,
        Err(e) => {
            c.damage = Some(e);
            return c;
        }
    };
    let mut rest: &[u8] = &data;
    while !rest.is_empty() {
        let remaining = rest.len() as u64;
        let (rec, _) = match read_record(&mut rest, remaining) {
            Ok(x) => x,
            Err(e) => {
                c.damage = Some(format!("{e} after {} messages", c.messages.len()));
                break;
            }
        };
        match rec.op {
            OP_MSG_DATA => match (u32_of(rec.field(b"conn")), time_of(rec.field(b"time"))) {
                (Some(conn), Some(t)) => c.messages.push((conn, t, rec.data)),
                _ => {
                    c.damage = Some(format!(
                        "a message record without conn or time after {} messages",
                        c.messages.len()
                    ));
                    break;
                }
            },
            OP_CONNECTION => match connection(&rec) {
                Some(conn) => c.conns.push(conn),
                None => {
                    c.damage = Some("a connection record that does not parse".into());
                    break;
                }
            },
            _ => {}
        }
    }
    c
}

/// What the walk found.
pub(super) struct Scan {
    /// Connections by id.
    pub conns: BTreeMap<u32, (String, String)>,
    /// Chunks: position and per connection message counts.
    pub chunks: Vec<(u64, Vec<(u32, u32)>)>,
    /// Positions of chunks whose contents are damaged (their messages before the damage are
    /// counted in `chunks`).
    pub damaged: Vec<u64>,
    /// Messages in the chunks (all connections).
    pub messages: u64,
    /// Record times of the first and last messages (in file order, the earliest and latest).
    pub span: Option<(u64, u64)>,
    /// Where the walk stopped before the end of the file, and why.
    pub stopped: Option<(u64, String)>,
}

/// Walks the records of a bag from its start.
pub(super) fn scan(file: &File, len: u64) -> Result<Scan, String> {
    let mut r = BufReader::with_capacity(1 << 20, file);
    r.seek(SeekFrom::Start(super::ros1::MAGIC.len() as u64)).map_err(|e| e.to_string())?;
    let mut pos = super::ros1::MAGIC.len() as u64;
    let mut s = Scan {
        conns: BTreeMap::new(),
        chunks: Vec::new(),
        messages: 0,
        span: None,
        stopped: None,
        damaged: Vec::new(),
    };
    while pos < len {
        let (rec, used) = match read_record(&mut r, len - pos) {
            Ok(x) => x,
            Err(e) => {
                s.stopped = Some((pos, e));
                break;
            }
        };
        match rec.op {
            OP_CHUNK => {
                let c = chunk_contents(&rec);
                for (id, topic, ty) in c.conns {
                    s.conns.entry(id).or_insert((topic, ty));
                }
                let mut counts: BTreeMap<u32, u32> = BTreeMap::new();
                for (conn, t, _) in &c.messages {
                    *counts.entry(*conn).or_default() += 1;
                    s.span = Some(s.span.map_or((*t, *t), |(a, b)| (a.min(*t), b.max(*t))));
                }
                s.messages += c.messages.len() as u64;
                s.chunks.push((pos, counts.into_iter().collect()));
                if c.damage.is_some() {
                    s.damaged.push(pos);
                }
            }
            OP_CONNECTION => {
                if let Some((id, topic, ty)) = connection(&rec) {
                    s.conns.entry(id).or_insert((topic, ty));
                }
            }
            OP_BAG_HEADER if pos != super::ros1::MAGIC.len() as u64 => {
                s.stopped = Some((pos, "a second bag header".into()));
                break;
            }
            _ => {}
        }
        pos += used;
    }
    Ok(s)
}

/// Reads the chunk at `pos` (found by [`scan`]).
pub(super) fn read_chunk(file: &mut File, len: u64, pos: u64) -> Result<ChunkContents, String> {
    file.seek(SeekFrom::Start(pos)).map_err(|e| e.to_string())?;
    let mut r = BufReader::with_capacity(1 << 16, file);
    let (rec, _) = read_record(&mut r, len.saturating_sub(pos))?;
    if rec.op != OP_CHUNK {
        return Err("not a chunk".into());
    }
    Ok(chunk_contents(&rec))
}
