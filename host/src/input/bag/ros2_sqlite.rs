//! ROS 2 bags in the sqlite3 storage (rosbag2 `.db3`, one file per split), through rusqlite
//! with its bundled SQLite. Messages are read in (timestamp, id) order, a page at a time.
//!
//! rosbag2 indexes `messages` by timestamp (`timestamp_idx`), and each page is then one short
//! index walk. Files without that index (older rosbag2 releases, hand-made or converted bags)
//! would make every page a scan and sort of the whole table: quadratic, 34.5 s for 100,000
//! messages and about 20 minutes for a 10-minute bag with a 1 kHz IMU. For those the message
//! ids are sorted once, in one query (8 bytes per message of the selected topics), and the pages
//! are read by id, which is the table's primary key.
//!
//! A database with damaged pages (a disk error, a copy cut short) gives its rows up to the
//! first error, then one warning naming how many rows were read; the next split is read on.

use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};

use rusqlite::{Connection, OpenFlags};

use super::{BagError, RawEvent, RawMsg, RawSource, TopicInfo};
use crate::input::bag::msg::Encoding;

const PAGE: usize = 64;

fn open_db(path: &Path) -> Result<Connection, BagError> {
    let name = path.display();
    let db =
        Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX)
            .map_err(|e| BagError(format!("{name}: cannot open as a rosbag2 sqlite3 database: {e}")))?;
    let tables = |db: &Connection| -> rusqlite::Result<i64> {
        db.query_row(
            "SELECT COUNT(*) FROM sqlite_master WHERE type = 'table' AND name IN ('topics', 'messages')",
            [],
            |r| r.get(0),
        )
    };
    // SQLite refuses a file shorter than its header says (a copy cut short) unless the schema
    // is marked writable; the connection is read-only, so this only lets the pages that are
    // there be read (as the sqlite3 shell's `.recover` does).
    let has_tables: i64 = tables(&db)
        .or_else(|_| {
            db.pragma_update(None, "writable_schema", true)?;
            tables(&db)
        })
        .map_err(|e| BagError(format!("{name}: not a readable sqlite3 database ({e})")))?;
    if has_tables != 2 {
        return Err(BagError(format!("{name}: not a rosbag2 database (no topics and messages tables)")));
    }
    Ok(db)
}

fn sql_err(path: &Path, e: rusqlite::Error) -> BagError {
    BagError(format!(
        "{}: corrupt rosbag2 database: {}",
        path.display(),
        crate::diag::one_line(&e.to_string())
    ))
}

/// One or more `.db3` files of a rosbag2 bag.
pub(super) struct SqliteSource {
    files: Vec<PathBuf>,
    /// Per file: rosbag2 topic id -> topic index.
    ids: Vec<HashMap<i64, usize>>,
    selected: Vec<usize>,
    file: usize,
    db: Option<Connection>,
    last: (i64, i64),
    /// For a file without a timestamp index: the ids of its selected messages in (timestamp,
    /// id) order, and how many of them have been read.
    order: Option<(Vec<i64>, usize)>,
    /// Damage met while listing the ids of a file without a timestamp index: said once the
    /// ids before it are read.
    order_damage: Option<BagError>,
    /// Rows of the selected topics read from the current file.
    rows: u64,
    /// A warning for the file just left at damage, said once its rows are delivered.
    recovered: Option<String>,
    queue: VecDeque<RawMsg>,
}

/// Messages per topic id.
fn message_counts(db: &Connection) -> Result<Vec<(i64, i64)>, rusqlite::Error> {
    let mut st = db.prepare("SELECT topic_id, COUNT(*) FROM messages GROUP BY topic_id")?;
    let rows = st.query_map([], |r| Ok((r.get::<_, i64>(0)?, r.get::<_, i64>(1)?)))?;
    rows.collect()
}

/// Whether `messages` has an index that starts with its `timestamp` column.
fn has_timestamp_index(db: &Connection) -> Result<bool, rusqlite::Error> {
    db.query_row(
        "SELECT COUNT(*) FROM pragma_index_list('messages') AS l, pragma_index_info(l.name) AS i \
         WHERE i.seqno = 0 AND i.name = 'timestamp'",
        [],
        |r| r.get::<_, i64>(0),
    )
    .map(|n| n > 0)
}

impl SqliteSource {
    pub(super) fn open(files: Vec<PathBuf>) -> Result<(Self, Vec<TopicInfo>), BagError> {
        let mut topics: Vec<TopicInfo> = Vec::new();
        let mut ids = Vec::new();
        for f in &files {
            let db = open_db(f)?;
            let mut map = HashMap::new();
            let mut st = db
                .prepare("SELECT id, name, type, serialization_format FROM topics")
                .map_err(|e| sql_err(f, e))?;
            let rows = st
                .query_map([], |r| {
                    Ok((
                        r.get::<_, i64>(0)?,
                        r.get::<_, String>(1)?,
                        r.get::<_, String>(2)?,
                        r.get::<_, String>(3)?,
                    ))
                })
                .map_err(|e| sql_err(f, e))?;
            for row in rows {
                let (id, name, ty, ser) = row.map_err(|e| sql_err(f, e))?;
                let enc = (ser == "cdr").then_some(Encoding::Cdr);
                let idx = match topics.iter().position(|t| t.name == name) {
                    Some(i) => i,
                    None => {
                        let mut t = TopicInfo::new(&name, &ty, Encoding::Cdr, Some(0));
                        t.encoding = enc;
                        topics.push(t);
                        topics.len() - 1
                    }
                };
                map.insert(id, idx);
            }
            // The counts walk the whole table: damaged pages leave them unknown (the rows
            // before the damage are still read).
            match message_counts(&db) {
                Ok(counts) => {
                    for (id, n) in counts {
                        if let Some(t) = map.get(&id).and_then(|&i| topics.get_mut(i)) {
                            t.count = t.count.map(|c| c + n.max(0) as u64);
                        }
                    }
                }
                Err(_) => {
                    for &i in map.values() {
                        topics[i].count = None;
                    }
                }
            }
            ids.push(map);
        }
        let src = SqliteSource {
            files,
            ids,
            selected: Vec::new(),
            file: 0,
            db: None,
            last: (i64::MIN, i64::MIN),
            order: None,
            order_damage: None,
            rows: 0,
            recovered: None,
            queue: VecDeque::new(),
        };
        Ok((src, topics))
    }

    /// Reads the next page of the current file; `false` when the file has no more.
    fn page(&mut self) -> Result<bool, BagError> {
        let path = &self.files[self.file];
        let ids: Vec<String> = self.ids[self.file]
            .iter()
            .filter(|(_, t)| self.selected.contains(t))
            .map(|(id, _)| id.to_string())
            .collect();
        if ids.is_empty() {
            return Ok(false);
        }
        if self.db.is_none() {
            let db = open_db(path)?;
            self.last = (i64::MIN, i64::MIN);
            self.rows = 0;
            // Once per file: without the timestamp index, the ids in (timestamp, id) order,
            // listed in table order (up to any damage) and sorted here.
            self.order = if has_timestamp_index(&db).map_err(|e| sql_err(path, e))? {
                None
            } else {
                let sql = format!("SELECT timestamp, id FROM messages WHERE topic_id IN ({})", ids.join(","));
                let mut st = db.prepare(&sql).map_err(|e| sql_err(path, e))?;
                let mut order = Vec::new();
                for r in st
                    .query_map([], |r| Ok((r.get::<_, i64>(0)?, r.get::<_, i64>(1)?)))
                    .map_err(|e| sql_err(path, e))?
                {
                    match r {
                        Ok(x) => order.push(x),
                        Err(e) => {
                            self.order_damage = Some(sql_err(path, e));
                            break;
                        }
                    }
                }
                order.sort_unstable();
                Some((order.into_iter().map(|(_, id)| id).collect(), 0))
            };
            self.db = Some(db);
        }
        let Some(db) = self.db.as_ref() else { return Ok(false) };
        // Rows are queued as they come, so that those before an error are kept.
        let mut got = Vec::with_capacity(PAGE);
        let mut damage = None;
        if let Some((order, done)) = &mut self.order {
            // The next PAGE ids of the sorted list, by primary key.
            let next = &order[*done..order.len().min(*done + PAGE)];
            if next.is_empty() {
                return match self.order_damage.take() {
                    Some(e) => Err(e),
                    None => Ok(false),
                };
            }
            *done += next.len();
            let params: [i64; PAGE] = core::array::from_fn(|i| next.get(i).copied().unwrap_or(-1));
            let sql = format!(
                "SELECT id, topic_id, timestamp, data FROM messages WHERE id IN ({})",
                (1..=PAGE).map(|i| format!("?{i}")).collect::<Vec<_>>().join(",")
            );
            let mut st = db.prepare_cached(&sql).map_err(|e| sql_err(path, e))?;
            for r in st.query_map(rusqlite::params_from_iter(params), row).map_err(|e| sql_err(path, e))? {
                match r {
                    Ok(r) => got.push(r),
                    Err(e) => {
                        damage = Some(sql_err(path, e));
                        break;
                    }
                }
            }
            // Only the listed ids (the padding's -1 may be a real one), in the list's order.
            got.retain(|r| next.contains(&r.0));
            got.sort_by_key(|r| next.iter().position(|&id| id == r.0));
        } else {
            let sql = format!(
                "SELECT id, topic_id, timestamp, data FROM messages WHERE topic_id IN ({}) \
                 AND (timestamp > ?1 OR (timestamp = ?1 AND id > ?2)) ORDER BY timestamp, id LIMIT {PAGE}",
                ids.join(",")
            );
            let mut st = db.prepare_cached(&sql).map_err(|e| sql_err(path, e))?;
            for r in st.query_map([self.last.0, self.last.1], row).map_err(|e| sql_err(path, e))? {
                match r {
                    Ok(r) => got.push(r),
                    Err(e) => {
                        damage = Some(sql_err(path, e));
                        break;
                    }
                }
            }
            if got.is_empty() && damage.is_none() {
                return Ok(false);
            }
        }
        for (id, topic_id, ts, data) in got {
            self.last = (ts, id);
            if ts < 0 {
                return Err(BagError(format!(
                    "{}: corrupt rosbag2 database: negative timestamp {ts}",
                    path.display()
                )));
            }
            if let Some(&topic) = self.ids[self.file].get(&topic_id) {
                let data = decompress(path, id, data)?;
                self.rows += 1;
                self.queue.push_back(RawMsg { record_ns: ts as u64, topic, data });
            }
        }
        match damage {
            Some(e) => Err(e),
            None => Ok(true),
        }
    }
}

/// A zstd frame's first bytes.
pub(super) const ZSTD_MAGIC: [u8; 4] = [0x28, 0xb5, 0x2f, 0xfd];

/// A message as stored, or decompressed when rosbag2 compressed it (`compression_mode:
/// message`, each row one zstd frame; a CDR message starts with 0000 or 0001, never with the
/// magic).
fn decompress(path: &Path, id: i64, data: Vec<u8>) -> Result<Vec<u8>, BagError> {
    if !data.starts_with(&ZSTD_MAGIC) {
        return Ok(data);
    }
    zstd::stream::decode_all(data.as_slice()).map_err(|e| {
        BagError(format!(
            "{}: this rosbag2 is zstd-compressed (message compression) and message {id} does not decompress: {e}",
            path.display()
        ))
    })
}

/// One `messages` row: id, topic id, timestamp, data.
fn row(r: &rusqlite::Row<'_>) -> rusqlite::Result<(i64, i64, i64, Vec<u8>)> {
    Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?))
}

impl RawSource for SqliteSource {
    fn select(&mut self, topics: &[usize]) {
        self.selected = topics.to_vec();
    }

    fn next_raw(&mut self) -> Option<Result<RawEvent, BagError>> {
        loop {
            if let Some(m) = self.queue.pop_front() {
                return Some(Ok(RawEvent::Msg(m)));
            }
            if let Some(why) = self.recovered.take() {
                return Some(Ok(RawEvent::Recovered { why, unindexed: false, truncated: true }));
            }
            if self.file >= self.files.len() {
                return None;
            }
            match self.page() {
                Ok(true) => {}
                Ok(false) => {
                    self.file += 1;
                    self.db = None;
                }
                Err(e) => {
                    // The rows before the damage are queued; the rest of this file is lost,
                    // the next split is read.
                    self.recovered = Some(format!(
                        "{}; the {} rows before the damage are read, the rest of the file is lost",
                        e.0, self.rows
                    ));
                    self.file += 1;
                    self.db = None;
                    self.order_damage = None;
                }
            }
        }
    }
}
