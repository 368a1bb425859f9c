//! MCAP files (ROS 2's default storage since Iron; also ROS 1 messages), streamed with the
//! `mcap` crate's reader (zstd and lz4 chunks). Topics and counts come from the summary
//! section; a file without one (cut short while recording) is scanned once for its channels,
//! and the messages before the damage are still read before the error.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, Read, Seek};
use std::path::{Path, PathBuf};

use mcap::sans_io::summary_reader::{SummaryReadEvent, SummaryReader};

use super::{BagError, RawEvent, RawMsg, RawSource, TopicInfo};
use crate::input::bag::msg::Encoding;

fn encoding(message_encoding: &str) -> Option<Encoding> {
    match message_encoding {
        "cdr" => Some(Encoding::Cdr),
        "ros1" => Some(Encoding::Ros1),
        _ => None,
    }
}

fn mcap_err(name: &str, e: impl std::fmt::Display) -> BagError {
    BagError(format!("{name}: corrupt or truncated MCAP: {}", crate::diag::one_line(&e.to_string())))
}

fn summary(path: &Path) -> Option<mcap::Summary> {
    let mut file = File::open(path).ok()?;
    let mut reader = SummaryReader::new();
    while let Some(event) = reader.next_event() {
        match event.ok()? {
            SummaryReadEvent::ReadRequest(need) => {
                let n = file.read(reader.insert(need)).ok()?;
                reader.notify_read(n);
            }
            SummaryReadEvent::SeekRequest(to) => {
                let pos = file.seek(to).ok()?;
                reader.notify_seeked(pos);
            }
        }
    }
    reader.finish()
}

/// An MCAP file.
pub(super) struct McapSource {
    name: String,
    path: PathBuf,
    reader: Option<mcap::io::MessageReader<BufReader<File>>>,
    topic_of: HashMap<String, usize>,
    selected: Vec<usize>,
    read: u64,
}

impl McapSource {
    pub(super) fn open(path: &Path) -> Result<(Self, Vec<TopicInfo>), BagError> {
        let name = path.display().to_string();
        let mut topics: Vec<TopicInfo> = Vec::new();
        let add =
            |topic: &str, ty: &str, enc: Option<Encoding>, n: Option<u64>, topics: &mut Vec<TopicInfo>| {
                match topics.iter_mut().find(|t| t.name == topic) {
                    Some(t) => t.count = t.count.zip(n).map(|(a, b)| a + b),
                    None => {
                        let mut t = TopicInfo::new(topic, ty, Encoding::Cdr, n);
                        t.encoding = enc;
                        topics.push(t);
                    }
                }
            };
        match summary(path) {
            Some(s) if !s.channels.is_empty() => {
                let counts = s.stats.as_ref().map(|st| st.channel_message_counts.clone());
                let mut chans: Vec<_> = s.channels.values().collect();
                chans.sort_by_key(|c| c.id);
                for c in chans {
                    let ty = c.schema.as_ref().map_or("", |s| s.name.as_str());
                    let n = counts.as_ref().map(|m| m.get(&c.id).copied().unwrap_or(0));
                    add(&c.topic, ty, encoding(&c.message_encoding), n, &mut topics);
                }
            }
            _ => {
                // No summary: one pass over the file for the channels (errors are reported by
                // the reading pass, after the good messages).
                let f = File::open(path).map_err(|e| BagError(format!("cannot open {name}: {e}")))?;
                let mut seen: HashMap<String, u64> = HashMap::new();
                for m in mcap::io::MessageReader::new(BufReader::new(f)) {
                    let Ok(m) = m else { break };
                    let c = &m.channel;
                    if !seen.contains_key(&c.topic) {
                        let ty = c.schema.as_ref().map_or("", |s| s.name.as_str());
                        add(&c.topic, ty, encoding(&c.message_encoding), None, &mut topics);
                    }
                    *seen.entry(c.topic.clone()).or_default() += 1;
                }
                for t in &mut topics {
                    t.count = seen.get(&t.name).copied();
                }
            }
        }
        let topic_of = topics.iter().enumerate().map(|(i, t)| (t.name.clone(), i)).collect();
        Ok((
            McapSource {
                name,
                path: path.to_path_buf(),
                reader: None,
                topic_of,
                selected: Vec::new(),
                read: 0,
            },
            topics,
        ))
    }
}

impl RawSource for McapSource {
    fn select(&mut self, topics: &[usize]) {
        self.selected = topics.to_vec();
    }

    fn next_raw(&mut self) -> Option<Result<RawEvent, BagError>> {
        if self.reader.is_none() {
            let f = match File::open(&self.path) {
                Ok(f) => f,
                Err(e) => return Some(Err(BagError(format!("cannot open {}: {e}", self.name)))),
            };
            self.reader = Some(mcap::io::MessageReader::new(BufReader::new(f)));
        }
        let reader = self.reader.as_mut()?;
        loop {
            match reader.next()? {
                Ok(m) => {
                    self.read += 1;
                    let Some(&topic) = self.topic_of.get(&m.channel.topic) else { continue };
                    if self.selected.contains(&topic) {
                        return Some(Ok(RawEvent::Msg(RawMsg {
                            record_ns: m.log_time,
                            topic,
                            data: m.data.into_owned(),
                        })));
                    }
                }
                Err(e) => {
                    return Some(Err(mcap_err(
                        &self.name,
                        format_args!("{e} (after {} messages)", self.read),
                    )));
                }
            }
        }
    }
}

/// A rosbag2 recorded into several MCAP files (`NAME_0.mcap`, `NAME_1.mcap`, ... split by size
/// or duration), read one after the other as one bag: topics merged by name (counts added),
/// each file's messages with the merged topic numbers.
pub(super) struct McapSplits {
    /// Each file's source and, per its own topic number, the merged one.
    parts: Vec<(McapSource, Vec<usize>)>,
    current: usize,
}

impl McapSplits {
    pub(super) fn open(paths: &[PathBuf]) -> Result<(Self, Vec<TopicInfo>), BagError> {
        let mut topics: Vec<TopicInfo> = Vec::new();
        let mut parts = Vec::with_capacity(paths.len());
        for p in paths {
            let (src, local) = McapSource::open(p)?;
            let map = local
                .into_iter()
                .map(|t| match topics.iter().position(|g| g.name == t.name) {
                    Some(i) => {
                        topics[i].count = topics[i].count.zip(t.count).map(|(a, b)| a + b);
                        i
                    }
                    None => {
                        topics.push(t);
                        topics.len() - 1
                    }
                })
                .collect();
            parts.push((src, map));
        }
        Ok((McapSplits { parts, current: 0 }, topics))
    }
}

impl RawSource for McapSplits {
    fn select(&mut self, topics: &[usize]) {
        for (src, map) in &mut self.parts {
            let local: Vec<usize> = (0..map.len()).filter(|&i| topics.contains(&map[i])).collect();
            src.select(&local);
        }
    }

    fn next_raw(&mut self) -> Option<Result<RawEvent, BagError>> {
        while let Some((src, map)) = self.parts.get_mut(self.current) {
            match src.next_raw() {
                Some(Ok(RawEvent::Msg(mut m))) => {
                    m.topic = map[m.topic];
                    return Some(Ok(RawEvent::Msg(m)));
                }
                Some(other) => return Some(other),
                None => self.current += 1,
            }
        }
        None
    }
}
