//! ROS 2 bags in the sqlite3 storage (rosbag2 `.db3`, one file per split), through rusqlite
//! with its bundled SQLite. Messages are read in (timestamp, id) order, a page at a time.

use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};

use rusqlite::{Connection, OpenFlags};

use super::{BagError, RawEvent, RawMsg, RawSource, TopicInfo};
use crate::bag::msg::Encoding;

const PAGE: usize = 64;

fn open_db(path: &Path) -> Result<Connection, BagError> {
    let name = path.display();
    let db =
        Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX)
            .map_err(|e| BagError(format!("{name}: cannot open as a rosbag2 sqlite3 database: {e}")))?;
    let has_tables: i64 = db
        .query_row(
            "SELECT COUNT(*) FROM sqlite_master WHERE type = 'table' AND name IN ('topics', 'messages')",
            [],
            |r| r.get(0),
        )
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
    queue: VecDeque<RawMsg>,
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
            let mut st = db
                .prepare("SELECT topic_id, COUNT(*) FROM messages GROUP BY topic_id")
                .map_err(|e| sql_err(f, e))?;
            let rows = st
                .query_map([], |r| Ok((r.get::<_, i64>(0)?, r.get::<_, i64>(1)?)))
                .map_err(|e| sql_err(f, e))?;
            for row in rows {
                let (id, n) = row.map_err(|e| sql_err(f, e))?;
                if let Some(t) = map.get(&id).and_then(|&i| topics.get_mut(i)) {
                    t.count = Some(t.count.unwrap_or(0) + n.max(0) as u64);
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
            queue: VecDeque::new(),
        };
        Ok((src, topics))
    }

    /// Reads the next page of the current file; `false` when the file has no more.
    fn page(&mut self) -> Result<bool, BagError> {
        let path = &self.files[self.file];
        if self.db.is_none() {
            self.db = Some(open_db(path)?);
            self.last = (i64::MIN, i64::MIN);
        }
        let ids: Vec<String> = self.ids[self.file]
            .iter()
            .filter(|(_, t)| self.selected.contains(t))
            .map(|(id, _)| id.to_string())
            .collect();
        if ids.is_empty() {
            return Ok(false);
        }
        let Some(db) = self.db.as_ref() else { return Ok(false) };
        let sql = format!(
            "SELECT id, topic_id, timestamp, data FROM messages WHERE topic_id IN ({}) \
             AND (timestamp > ?1 OR (timestamp = ?1 AND id > ?2)) ORDER BY timestamp, id LIMIT {PAGE}",
            ids.join(",")
        );
        let mut st = db.prepare_cached(&sql).map_err(|e| sql_err(path, e))?;
        let rows = st
            .query_map([self.last.0, self.last.1], |r| {
                Ok((r.get::<_, i64>(0)?, r.get::<_, i64>(1)?, r.get::<_, i64>(2)?, r.get::<_, Vec<u8>>(3)?))
            })
            .map_err(|e| sql_err(path, e))?;
        let mut n = 0;
        for row in rows {
            let (id, topic_id, ts, data) = row.map_err(|e| sql_err(path, e))?;
            self.last = (ts, id);
            n += 1;
            if ts < 0 {
                return Err(BagError(format!(
                    "{}: corrupt rosbag2 database: negative timestamp {ts}",
                    path.display()
                )));
            }
            if let Some(&topic) = self.ids[self.file].get(&topic_id) {
                self.queue.push_back(RawMsg { record_ns: ts as u64, topic, data });
            }
        }
        Ok(n > 0)
    }
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
                    self.file = self.files.len();
                    return Some(Err(e));
                }
            }
        }
    }
}
