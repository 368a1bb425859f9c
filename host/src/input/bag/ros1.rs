//! ROS 1 bags (format 2.0) through the `rosbag` crate, which reads uncompressed, bz2 and lz4
//! chunks.
//!
//! The bag header is checked here first, because the crate slices the file at the header's
//! `index_pos` without checking it: a bag that was never closed (index_pos 0) or that was cut
//! short gets a clear error (and the advice to run `rosbag reindex`) instead of a panic. Chunks
//! are then read one by one at the positions of the index's chunk info records, so a corrupt
//! chunk is reported and skipped and the chunks around it are still read.

use std::collections::{HashMap, VecDeque};
use std::io::Read;
use std::path::Path;

use rosbag::record_types::Compression;
use rosbag::{ChunkRecord, IndexRecord, MessageRecord, RosBag};

use super::{BagError, RawEvent, RawMsg, RawSource, TopicInfo};
use crate::input::bag::msg::Encoding;

const MAGIC: &[u8] = b"#ROSBAG V2.0\n";

/// Checks the magic and the bag header record, and returns `index_pos`.
fn check_header(path: &Path, name: &str) -> Result<u64, BagError> {
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
        return Err(BagError(format!(
            "{name}: the bag was not closed (no index; the recorder was stopped abruptly); run `rosbag reindex` on it"
        )));
    }
    if index_pos < data_end || index_pos > len {
        return Err(BagError(format!(
            "{name}: truncated or corrupt: its index starts at byte {index_pos} but the file has {len} bytes; run `rosbag reindex` on it"
        )));
    }
    Ok(index_pos)
}

struct Chunk {
    pos: u64,
    /// Messages of the selected connections in this chunk.
    selected: u64,
}

/// A ROS 1 bag.
pub(super) struct Ros1Source {
    bag: RosBag,
    chunks: Vec<Chunk>,
    /// Per chunk: (connection, messages) from its chunk info record.
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
        check_header(path, &name)?;
        let bag = RosBag::new(path).map_err(|e| BagError(format!("{name}: {e}")))?;
        let mut topics: Vec<TopicInfo> = Vec::new();
        let mut conn_topic = HashMap::new();
        let mut chunk_infos: Vec<(u64, Vec<(u32, u32)>)> = Vec::new();
        for rec in bag.index_records() {
            let rec = rec.map_err(|e| {
                BagError(format!("{name}: corrupt index ({}); run `rosbag reindex` on it", rosbag_msg(&e)))
            })?;
            match rec {
                IndexRecord::Connection(c) => {
                    let idx = match topics.iter().position(|t| t.name == c.topic) {
                        Some(i) => i,
                        None => {
                            topics.push(TopicInfo::new(c.topic, c.tp, Encoding::Ros1, Some(0)));
                            topics.len() - 1
                        }
                    };
                    conn_topic.insert(c.id, idx);
                }
                IndexRecord::ChunkInfo(ci) => {
                    chunk_infos.push((ci.chunk_pos, ci.entries().map(|e| (e.conn_id, e.count)).collect()));
                }
                IndexRecord::IndexData(_) => {}
            }
        }
        if chunk_infos.len() != bag.get_chunk_count() as usize {
            return Err(BagError(format!(
                "{name}: corrupt index: {} chunk info records for {} chunks; run `rosbag reindex` on it",
                chunk_infos.len(),
                bag.get_chunk_count()
            )));
        }
        chunk_infos.sort_by_key(|c| c.0);
        for (_, entries) in &chunk_infos {
            for (conn, n) in entries {
                if let Some(t) = conn_topic.get(conn).and_then(|&i| topics.get_mut(i)) {
                    t.count = Some(t.count.unwrap_or(0) + *n as u64);
                }
            }
        }
        let src = Ros1Source {
            bag,
            chunks: chunk_infos.iter().map(|(pos, _)| Chunk { pos: *pos, selected: 0 }).collect(),
            chunk_entries: chunk_infos.into_iter().map(|(_, e)| e).collect(),
            next_chunk: 0,
            conn_topic,
            selected: HashMap::new(),
            queue: VecDeque::new(),
        };
        Ok((src, topics))
    }

    fn load_chunk(&mut self, k: usize) -> Result<(), BagError> {
        let pos = self.chunks[k].pos;
        let mut it = self.bag.chunk_records();
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
        loop {
            if let Some(m) = self.queue.pop_front() {
                return Some(Ok(RawEvent::Msg(m)));
            }
            let k = self.next_chunk;
            if k >= self.chunks.len() {
                return None;
            }
            self.next_chunk += 1;
            if self.chunks[k].selected == 0 {
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
