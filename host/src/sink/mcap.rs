//! `--mcap FILE`: records the Foxglove output's channels (same topics, JSON messages and
//! schemas as [`super::foxglove`]) to an MCAP file, to open in Foxglove afterwards.
//!
//! Chunks are closed and flushed about once a second of data, so a run killed without its end
//! (the summary and index written by [`Sink::finish`]) still leaves every closed chunk readable
//! by streaming readers. LZ4 chunks: cheap on a robot's CPU.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use ::mcap::records::MessageHeader;
use ::mcap::{Compression, WriteOptions, Writer};

use super::foxglove::{CHANNELS, Encoder, EncoderOptions};
use super::{Sink, SinkError, SinkEvent, Wants};

/// Data time between two chunk flushes, ns.
const FLUSH_EVERY_NS: u64 = 1_000_000_000;

/// The `--mcap` sink.
pub struct McapSink {
    path: PathBuf,
    writer: Option<Writer<BufWriter<File>>>,
    channel_ids: Vec<u16>,
    seq: u32,
    enc: Encoder,
    flushed_ns: Option<u64>,
}

impl std::fmt::Debug for McapSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("McapSink").field("path", &self.path).field("seq", &self.seq).finish()
    }
}

impl McapSink {
    /// Creates `path` and writes the header, schemas and channels.
    pub fn create(path: &Path) -> Result<McapSink, SinkError> {
        let err = |e: &dyn std::fmt::Display| SinkError(format!("cannot write {}: {e}", path.display()));
        let f = File::create(path).map_err(|e| err(&e))?;
        let opts =
            WriteOptions::new().compression(Some(Compression::Lz4)).profile("loglio").library("loglio");
        let mut w = Writer::with_options(BufWriter::new(f), opts).map_err(|e| err(&e))?;
        let mut channel_ids = Vec::with_capacity(CHANNELS.len());
        for c in &CHANNELS {
            let schema = c.channel.schema().to_string();
            let sid = w.add_schema(c.schema_name, "jsonschema", schema.as_bytes()).map_err(|e| err(&e))?;
            channel_ids.push(w.add_channel(sid, c.topic, "json", &BTreeMap::new()).map_err(|e| err(&e))?);
        }
        w.flush().map_err(|e| err(&e))?;
        Ok(McapSink {
            path: path.to_path_buf(),
            writer: Some(w),
            channel_ids,
            seq: 0,
            enc: Encoder::new(EncoderOptions::default()),
            flushed_ns: None,
        })
    }

    fn err(&self, e: impl std::fmt::Display) -> SinkError {
        SinkError(format!("cannot write {}: {e}", self.path.display()))
    }
}

impl Sink for McapSink {
    fn name(&self) -> String {
        format!("mcap {}", self.path.display())
    }

    fn wants(&self) -> Wants {
        Wants { cloud: true, map: true, imu_pose: true }
    }

    fn handle(&mut self, ev: &SinkEvent) -> Result<(), SinkError> {
        let msgs = self.enc.encode(ev, 0);
        let Some(w) = &mut self.writer else { return Ok(()) };
        let mut res = Ok(());
        let mut last_t = None;
        for m in msgs {
            self.seq = self.seq.wrapping_add(1);
            let h = MessageHeader {
                channel_id: self.channel_ids[m.channel.index()],
                sequence: self.seq,
                log_time: m.t_ns,
                publish_time: m.t_ns,
            };
            if let Err(e) = w.write_to_known_channel(&h, &m.data) {
                res = Err(e);
            }
            last_t = Some(m.t_ns);
        }
        if let Some(t) = last_t
            && self.flushed_ns.is_none_or(|f| t >= f.saturating_add(FLUSH_EVERY_NS))
        {
            self.flushed_ns = Some(t);
            if let Err(e) = w.flush() {
                res = Err(e);
            }
        }
        res.map_err(|e| self.err(e))
    }

    fn finish(&mut self) -> Result<(), SinkError> {
        match self.writer.take() {
            Some(mut w) => w.finish().map(|_| ()).map_err(|e| self.err(e)),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unwritable_path_is_one_error_line() {
        let e = McapSink::create(Path::new("/nonexistent-dir/x/run.mcap")).err().unwrap();
        assert!(e.0.starts_with("cannot write /nonexistent-dir/x/run.mcap"), "{e}");
        assert!(!e.0.contains('\n'));
    }
}
