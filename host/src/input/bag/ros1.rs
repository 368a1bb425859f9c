//! ROS 1 bags (format 2.0) through the `rosbag` crate, which reads uncompressed, bz2 and lz4
//! chunks.
//!
//! The bag header is checked here first, because the crate slices the file at the header's
//! `index_pos` without checking it. A bag that was never closed (index_pos 0), that was cut
//! short (index_pos past the end) or whose index is corrupt is read without the index by
//! walking its records ([`super::ros1_scan`], as `rosbag reindex` would), with one warning
//! saying so and how much was recovered. Chunks are read one by one (at the positions of the
//! index's chunk info records, or where the walk found them), so a corrupt chunk is reported
//! and skipped and the chunks around it are still read.

use std::collections::{HashMap, VecDeque};
use std::io::Read;
use std::path::Path;

use rosbag::record_types::Compression;
use rosbag::{ChunkRecord, IndexRecord, MessageRecord, RosBag};

use super::{BagError, RawEvent, RawMsg, RawSource, TopicInfo, ros1_scan};
use crate::input::bag::msg::Encoding;

pub(super) const MAGIC: &[u8] = b"#ROSBAG V2.0\n";

/// Checks the magic and the bag header record, and returns the file's length and `index_pos`,
/// or why the index cannot be used.
fn check_header(path: &Path, name: &str) -> Result<(u64, Result<u64, String>), BagError> {
    let mut f = std::fs::File::open(path).map_err(|e| BagError(format!("cannot open {name}: {e}")))?;
    let len = f.metadata().map_err(|e| BagError(format!("cannot read {name}: {e}")))?.len();
    let mut head = vec![0u8; 8192.min(len as usize)];
    f.read_exact(&mut head).map_err(|e| BagError(format!("cannot read {name}: {e}")))?;
    if !head.starts_with(MAGIC) {
        if head.starts_with(b"#ROSBAG V") {
            return Err(BagError(format!("{name}: unsupported ROS bag version (only 2.0 is read)")));
        }
        return Err(BagError(format!("{name}: not a ROS 1 bag (no #ROSBAG V2.0 header)")));
    }
    let truncated = || BagError(format!("{name}: truncated: the file ends inside the bag header"));
    let u32_at = |at: usize| -> Result<usize, BagError> {
        head.get(at..at + 4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
            .ok_or_else(truncated)
    };
    let hlen = u32_at(MAGIC.len())?;
    let hstart = MAGIC.len() + 4;
    let header = head.get(hstart..hstart + hlen).ok_or_else(truncated)?;
    let dlen = u32_at(hstart + hlen)?;
    let data_end = (hstart + hlen + 4 + dlen) as u64;
    let mut index_pos = None;
    let mut rest = header;
    while rest.len() >= 4 {
        let n = u32::from_le_bytes([rest[0], rest[1], rest[2], rest[3]]) as usize;
        let Some(f) = rest.get(4..4 + n) else { break };
        if let Some(v) = f.strip_prefix(b"index_pos=")
            && v.len() == 8
        {
            index_pos = Some(u64::from_le_bytes(v.try_into().unwrap_or([0; 8])));
        }
        rest = &rest[4 + n..];
    }
    let Some(index_pos) = index_pos else {
        return Err(BagError(format!("{name}: corrupt bag header (no index_pos)")));
    };
    if index_pos == 0 {
        return Ok((len, Err("the bag was not closed (no index: the recorder was stopped abruptly)".into())));
    }
    if index_pos < data_end || index_pos > len {
        return Ok((
            len,
            Err(format!(
                "cut short or corrupt (its index starts at byte {index_pos} but the file has {len} bytes)"
            )),
        ));
    }
    Ok((len, Ok(index_pos)))
}

/// Seconds with milliseconds, for messages.
fn secs(ns: u64) -> String {
    format!("{}.{:03}", ns / 1_000_000_000, ns % 1_000_000_000 / 1_000_000)
}

/// Where the chunks are read from.
enum Reader {
    /// Through the index, by the `rosbag` crate.
    Indexed(RosBag),
    /// Found by walking the records.
    Scanned { file: std::fs::File, len: u64 },
}

struct Chunk {
    pos: u64,
    /// Found damaged by the walk: read (to report it) even if none of its messages is selected.
    damaged: bool,
    /// Messages of the selected connections in this chunk.
    selected: u64,
}

/// A ROS 1 bag.
pub(super) struct Ros1Source {
    reader: Reader,
    /// For a bag read without its index: the warning, said before the first message, and
    /// whether the walk stopped at damage.
    recovered: Option<(String, bool)>,
    chunks: Vec<Chunk>,
    /// Per chunk: (connection, messages), from its chunk info record or from the walk.
    chunk_entries: Vec<Vec<(u32, u32)>>,
    next_chunk: usize,
    /// Connection id -> topic index.
    conn_topic: HashMap<u32, usize>,
    /// Connection ids read (all of them until [`RawSource::select`]).
    selected: HashMap<u32, usize>,
    queue: VecDeque<RawMsg>,
}

impl Ros1Source {
    pub(super) fn open(path: &Path) -> Result<(Self, Vec<TopicInfo>), BagError> {
        let name = path.display().to_string();
        let (len, index) = check_header(path, &name)?;
        match index {
            Ok(_) => match Self::open_indexed(path) {
                Ok(x) => Ok(x),
                Err(why) => Self::open_scanned(path, &name, len, &format!("corrupt index ({why})")),
            },
            Err(why) => Self::open_scanned(path, &name, len, &why),
        }
    }

    fn new(
        reader: Reader,
        conn_topic: HashMap<u32, usize>,
        chunk_infos: Vec<(u64, Vec<(u32, u32)>)>,
    ) -> Self {
        Ros1Source {
            reader,
            recovered: None,
            chunks: chunk_infos
                .iter()
                .map(|(pos, _)| Chunk { pos: *pos, damaged: false, selected: 0 })
                .collect(),
            chunk_entries: chunk_infos.into_iter().map(|(_, e)| e).collect(),
            next_chunk: 0,
            conn_topic,
            selected: HashMap::new(),
            queue: VecDeque::new(),
        }
    }

    /// Opens through the index; `Err` says why the index cannot be used.
    fn open_indexed(path: &Path) -> Result<(Self, Vec<TopicInfo>), String> {
        let bag = RosBag::new(path).map_err(|e| e.to_string())?;
        let mut topics: Vec<TopicInfo> = Vec::new();
        let mut conn_topic = HashMap::new();
        let mut chunk_infos: Vec<(u64, Vec<(u32, u32)>)> = Vec::new();
        for rec in bag.index_records() {
            match rec.map_err(|e| rosbag_msg(&e))? {
                IndexRecord::Connection(c) => {
                    conn_topic.insert(c.id, topic_index(&mut topics, c.topic, c.tp));
                }
                IndexRecord::ChunkInfo(ci) => {
                    chunk_infos.push((ci.chunk_pos, ci.entries().map(|e| (e.conn_id, e.count)).collect()));
                }
                IndexRecord::IndexData(_) => {}
            }
        }
        if chunk_infos.len() != bag.get_chunk_count() as usize {
            return Err(format!(
                "{} chunk info records for {} chunks",
                chunk_infos.len(),
                bag.get_chunk_count()
            ));
        }
        chunk_infos.sort_by_key(|c| c.0);
        count_messages(&mut topics, &conn_topic, &chunk_infos);
        Ok((Self::new(Reader::Indexed(bag), conn_topic, chunk_infos), topics))
    }

    /// Opens by walking the records; `why` says why the index is not used.
    fn open_scanned(
        path: &Path,
        name: &str,
        len: u64,
        why: &str,
    ) -> Result<(Self, Vec<TopicInfo>), BagError> {
        let file = std::fs::File::open(path).map_err(|e| BagError(format!("cannot open {name}: {e}")))?;
        let s = ros1_scan::scan(&file, len).map_err(|e| BagError(format!("cannot read {name}: {e}")))?;
        let stop = s
            .stopped
            .as_ref()
            .map(|(pos, e)| format!("; the records end at byte {pos} of {len} ({e}), the rest is lost"));
        if s.chunks.is_empty() {
            return Err(BagError(format!(
                "{name}: {why}, and no chunk could be read without it{}",
                stop.unwrap_or_default()
            )));
        }
        let mut topics: Vec<TopicInfo> = Vec::new();
        let mut conn_topic = HashMap::new();
        for (id, (topic, ty)) in &s.conns {
            conn_topic.insert(*id, topic_index(&mut topics, topic, ty));
        }
        count_messages(&mut topics, &conn_topic, &s.chunks);
        let span =
            s.span.map_or(String::new(), |(a, b)| format!(", record times {} to {} s", secs(a), secs(b)));
        let warning = format!(
            "{name}: {why}; read without the index, as `rosbag reindex` would: {} messages recovered from {} chunks{span}{}",
            s.messages,
            s.chunks.len(),
            stop.clone().unwrap_or_default()
        );
        let mut src = Self::new(Reader::Scanned { file, len }, conn_topic, s.chunks);
        for c in &mut src.chunks {
            c.damaged = s.damaged.contains(&c.pos);
        }
        src.recovered = Some((warning, stop.is_some()));
        Ok((src, topics))
    }

    fn load_chunk(&mut self, k: usize) -> Result<(), BagError> {
        let pos = self.chunks[k].pos;
        let bag = match &mut self.reader {
            Reader::Indexed(bag) => bag,
            Reader::Scanned { file, len } => {
                let c = ros1_scan::read_chunk(file, *len, pos)
                    .map_err(|e| BagError(format!("chunk at byte {pos}: {e}")))?;
                for (conn, time, data) in c.messages {
                    if let Some(&topic) = self.selected.get(&conn) {
                        self.queue.push_back(RawMsg { record_ns: time, topic, data });
                    }
                }
                return match c.damage {
                    Some(e) => Err(BagError(format!("chunk at byte {pos}: {e}"))),
                    None => Ok(()),
                };
            }
        };
        let mut it = bag.chunk_records();
        it.seek(pos).map_err(|e| BagError(format!("chunk at byte {pos}: {}", rosbag_msg(&e))))?;
        let chunk = match it.next() {
            Some(Ok(ChunkRecord::Chunk(c))) => c,
            Some(Ok(ChunkRecord::IndexData(_))) => {
                return Err(BagError(format!("the index points at byte {pos}, which is not a chunk")));
            }
            Some(Err(e)) => return Err(BagError(format!("chunk at byte {pos}: {}", rosbag_msg(&e)))),
            None => return Err(BagError(format!("the index points at byte {pos}, past the chunks"))),
        };
        let compression = match chunk.compression {
            Compression::None => "",
            Compression::Bzip2 => " (bz2)",
            Compression::Lz4 => " (lz4)",
            _ => " (unknown compression)",
        };
        for m in chunk.messages() {
            match m {
                Ok(MessageRecord::MessageData(d)) => {
                    if let Some(&topic) = self.selected.get(&d.conn_id) {
                        self.queue.push_back(RawMsg { record_ns: d.time, topic, data: d.data.to_vec() });
                    }
                }
                Ok(MessageRecord::Connection(_)) => {}
                Err(e) => {
                    return Err(BagError(format!(
                        "chunk{compression} at byte {pos}: {} after {} messages",
                        rosbag_msg(&e),
                        self.queue.len()
                    )));
                }
            }
        }
        Ok(())
    }
}

/// The index of `topic` in `topics`, added if new.
fn topic_index(topics: &mut Vec<TopicInfo>, topic: &str, ty: &str) -> usize {
    match topics.iter().position(|t| t.name == topic) {
        Some(i) => i,
        None => {
            topics.push(TopicInfo::new(topic, ty, Encoding::Ros1, Some(0)));
            topics.len() - 1
        }
    }
}

/// Adds the chunks' message counts to the topics.
fn count_messages(
    topics: &mut [TopicInfo],
    conn_topic: &HashMap<u32, usize>,
    chunks: &[(u64, Vec<(u32, u32)>)],
) {
    for (_, entries) in chunks {
        for (conn, n) in entries {
            if let Some(t) = conn_topic.get(conn).and_then(|&i| topics.get_mut(i)) {
                t.count = Some(t.count.unwrap_or(0) + *n as u64);
            }
        }
    }
}

fn rosbag_msg(e: &rosbag::Error) -> String {
    e.to_string().trim_start_matches("rosbag::Error: ").to_string()
}

impl RawSource for Ros1Source {
    fn select(&mut self, topics: &[usize]) {
        self.selected =
            self.conn_topic.iter().filter(|(_, t)| topics.contains(t)).map(|(&c, &t)| (c, t)).collect();
        for (k, c) in self.chunks.iter_mut().enumerate() {
            c.selected = self.chunk_entries[k]
                .iter()
                .filter(|(conn, _)| self.selected.contains_key(conn))
                .map(|(_, n)| *n as u64)
                .sum();
        }
    }

    fn next_raw(&mut self) -> Option<Result<RawEvent, BagError>> {
        if let Some((why, truncated)) = self.recovered.take() {
            return Some(Ok(RawEvent::Recovered { why, unindexed: true, truncated }));
        }
        loop {
            if let Some(m) = self.queue.pop_front() {
                return Some(Ok(RawEvent::Msg(m)));
            }
            let k = self.next_chunk;
            if k >= self.chunks.len() {
                return None;
            }
            self.next_chunk += 1;
            if self.chunks[k].selected == 0 && !self.chunks[k].damaged {
                continue;
            }
            if let Err(e) = self.load_chunk(k) {
                // The messages decoded before the damage are kept (queued); the rest of this
                // chunk is skipped and the next chunk is read.
                return Some(Ok(RawEvent::Skipped(format!("corrupt {}", e.0))));
            }
        }
    }
}
