//! `loglio replay`: a pcap (Velodyne or Ouster) plus the IMU from a CSV file, a serial capture
//! (loglio's COBS frames) or the Ouster IMU packets in the same pcap, as fast as possible or in
//! real time, with a progress bar; writes every output.

use std::collections::VecDeque;
use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};
use std::time::Instant;

use loglio_core::imu::ImuSample;

use crate::config::{ImuSource, SensorFamily};
use crate::diag::warn;
use crate::error::PipelineError;
use crate::input::lidar_stream::{self, Decoded, LidarStream};
use crate::input::pace::Pacer;
use crate::input::serial::ImuFrameReader;
use crate::output::Progress;
use crate::run::runner::RunStats;
use crate::run::setup::{DataExtrinsic, PacketSetup, RunSetup};
use crate::run::{Event, RunOptions, Source};
use crate::sink::files::Finished;

/// Where the replay's IMU comes from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ImuInput {
    /// A CSV file `t,gx,gy,gz,ax,ay,az`.
    Csv(PathBuf),
    /// A capture of loglio's serial IMU frames.
    Serial(PathBuf),
    /// The Ouster IMU packets in the pcap.
    OusterPackets,
    /// No IMU: LiDAR-only, a constant-velocity model (`imu.source = "none"`).
    None,
}

impl ImuInput {
    /// The IMU input of a file: CSV if it starts like the CSV header, serial frames otherwise.
    pub fn detect(path: &Path) -> Result<ImuInput, PipelineError> {
        let mut head = [0u8; 64];
        let n = {
            use std::io::Read;
            let mut f = File::open(path).map_err(|e| PipelineError(format!("{}: {e}", path.display())))?;
            f.read(&mut head).map_err(|e| PipelineError(format!("{}: {e}", path.display())))?
        };
        let text = String::from_utf8_lossy(&head[..n]);
        let csvish = text.trim_start().starts_with("t,") || text.trim_start().starts_with('#');
        Ok(if csvish || path.extension().is_some_and(|e| e == "csv") {
            ImuInput::Csv(path.to_path_buf())
        } else {
            ImuInput::Serial(path.to_path_buf())
        })
    }
}

/// A replay's settings.
#[derive(Clone, Debug)]
pub struct ReplayOptions {
    /// The pcap.
    pub pcap: PathBuf,
    /// The IMU (`None`: the configuration's `imu.source`: Ouster packets or `imu.csv_path`).
    pub imu: Option<ImuInput>,
    /// Pace by the capture times (`rate` x real time).
    pub realtime: Option<f64>,
    /// The shared run settings.
    pub setup: RunSetup,
    /// Show the progress bar.
    pub progress: bool,
}

/// A finished replay.
#[derive(Debug)]
pub struct ReplayReport {
    /// Counts and times.
    pub stats: RunStats,
    /// What was written and the evaluation.
    pub finished: Finished,
    /// Packet counts.
    pub stream: lidar_stream::StreamStats,
    /// Whether the Ouster's IMU packets were the IMU (else they were counted and left out).
    pub imu_packets_used: bool,
    /// Where the extrinsic came from (a summary line), unless nothing gave one.
    pub extrinsic: Option<String>,
    /// The scan period, s.
    pub scan_period_s: f64,
    /// Wall time, s.
    pub wall_s: f64,
}

enum ImuFeed {
    Samples(std::vec::IntoIter<ImuSample>),
    Serial(Box<ImuFrameReader<BufReader<File>>>),
    None,
}

impl ImuFeed {
    fn next(&mut self) -> Result<Option<ImuSample>, PipelineError> {
        match self {
            ImuFeed::Samples(it) => Ok(it.next()),
            ImuFeed::Serial(r) => r
                .next_frame()
                .map(|f| f.map(|f| f.sample()))
                .map_err(|e| PipelineError(format!("IMU capture: {e}"))),
            ImuFeed::None => Ok(None),
        }
    }
}

/// Runs a replay.
pub fn run(opt: &ReplayOptions) -> Result<ReplayReport, PipelineError> {
    let wall = Instant::now();
    let mut cfg = opt.setup.load_config()?;
    let data = DataExtrinsic::of_ouster_metadata(&cfg)?;
    let extrinsic = opt.setup.resolve_extrinsic(&mut cfg, data)?;
    let imu = match (&opt.imu, cfg.imu.source) {
        (Some(i), _) => i.clone(),
        (None, ImuSource::Ouster) => ImuInput::OusterPackets,
        (None, ImuSource::Csv) => ImuInput::Csv(cfg.imu.csv_path.clone().unwrap_or_default()),
        (None, ImuSource::Mavlink) => {
            return Err(PipelineError(
                "imu.source = \"mavlink\" is for live runs; the replay needs --imu FILE (an IMU CSV or a serial capture) or the Ouster's IMU packets (--ouster-imu)"
                    .into(),
            ));
        }
        (None, ImuSource::None) => ImuInput::None,
        (None, ImuSource::Serial) => {
            warn(
                "no IMU for the replay (--imu FILE, --ouster-imu): LiDAR-only (no IMU), a constant-velocity model; the world is the first scan's frame",
            );
            ImuInput::None
        }
    };
    if imu == ImuInput::None {
        cfg.imu.source = ImuSource::None;
    }
    let imu_packets_used = imu == ImuInput::OusterPackets;
    if imu_packets_used && cfg.preset.family() != SensorFamily::Ouster {
        return Err(PipelineError(format!(
            "--ouster-imu needs an Ouster preset (os1-*), not {}",
            cfg.preset
        )));
    }
    let PacketSetup { dec, lidar_port, imu_port, .. } = PacketSetup::new(&cfg)?;
    let feed = match &imu {
        ImuInput::Csv(p) => ImuFeed::Samples(
            crate::input::imu_csv::load(p).map_err(|e| PipelineError(e.to_string()))?.into_iter(),
        ),
        ImuInput::Serial(p) => {
            let f = File::open(p).map_err(|e| PipelineError(format!("{}: {e}", p.display())))?;
            ImuFeed::Serial(Box::new(ImuFrameReader::new(BufReader::new(f))))
        }
        ImuInput::OusterPackets | ImuInput::None => ImuFeed::None,
    };
    let reader = crate::input::pcap::PcapReader::open(&opt.pcap)
        .map_err(|e| PipelineError(format!("{}: {e}", opt.pcap.display())))?;
    let total = std::fs::metadata(&opt.pcap).map(|m| m.len()).unwrap_or(0);
    let progress = if opt.progress { Progress::new(total, "", true) } else { Progress::hidden() };
    let layout = dec.layout();
    let (mut a, mut b) = lidar_stream::buffers(&dec);
    let stream = LidarStream::new(&cfg, dec, &mut a, &mut b, lidar_port, imu_port);
    let mut src = PcapSource {
        reader,
        stream,
        feed,
        next_imu: None,
        started: false,
        imu_packets_used,
        offset_ns: (cfg.time.lidar_imu_offset * 1e9) as i64,
        pacer: opt.realtime.map(Pacer::new),
        progress: &progress,
        total,
        bytes: 0,
        ready: VecDeque::new(),
        scans: 0,
        done: false,
        pcap: &opt.pcap,
    };
    if imu != ImuInput::None {
        extrinsic.warn_if_missing();
    }
    let (stop, _signals) = crate::run::Signals::stop_flag();
    let opts = RunOptions {
        outputs: opt.setup.outputs()?,
        sinks: opt.setup.sinks.build(),
        stop: Some(stop),
        ..RunOptions::default()
    };
    let res = crate::run::drive(&cfg, layout, &mut src, opts)?;
    let (reader, stream) = (src.reader, src.stream);
    progress.finish();
    let ps = reader.stats;
    if ps.corrupt_records > 0 || ps.truncated_at_eof {
        warn(format!(
            "{}: {} corrupt records skipped{}",
            opt.pcap.display(),
            ps.corrupt_records,
            if ps.truncated_at_eof { ", truncated at the end" } else { "" }
        ));
    }
    if stream.stats.bad_packets > 0 {
        warn(format!("{} LiDAR packets could not be decoded and were dropped", stream.stats.bad_packets));
    }
    for w in stream.warnings() {
        warn(w);
    }
    let (stats, finished) = res;
    Ok(ReplayReport {
        stats,
        finished,
        stream: stream.stats,
        imu_packets_used,
        extrinsic: extrinsic.line().map(str::to_string),
        scan_period_s: 1.0 / cfg.sensor.scan_rate_hz,
        wall_s: wall.elapsed().as_secs_f64(),
    })
}
/// The replay as a source: the pcap's packets decoded into scans (and the Ouster's IMU
/// packets), with the file IMU interleaved up to a little past each scan's end.
struct PcapSource<'a, 'b> {
    reader: crate::input::pcap::PcapReader<BufReader<File>>,
    stream: LidarStream<'b>,
    feed: ImuFeed,
    next_imu: Option<ImuSample>,
    started: bool,
    imu_packets_used: bool,
    offset_ns: i64,
    pacer: Option<Pacer>,
    progress: &'a Progress,
    total: u64,
    bytes: u64,
    ready: VecDeque<Event>,
    scans: u64,
    done: bool,
    pcap: &'a Path,
}

impl PcapSource<'_, '_> {
    /// Queues what a decoded packet gives.
    fn take(&mut self, d: Decoded) -> Result<(), PipelineError> {
        match d {
            // The sensor's own IMU only when it is the one chosen: with an IMU file, a second
            // IMU (another frame, another clock) must not be mixed into the file's samples.
            Decoded::Imu(s) if self.imu_packets_used => self.ready.push_back(Event::Imu(s)),
            Decoded::Imu(_) => {}
            Decoded::Scan(scan) => {
                // The file IMU up to a little past this scan's end first.
                let until = scan.end_ns().saturating_add(200_000_000);
                while let Some(s) = self.next_imu {
                    if s.t_ns.saturating_add_signed(self.offset_ns) > until {
                        break;
                    }
                    self.ready.push_back(Event::Imu(s));
                    self.next_imu = self.feed.next()?;
                }
                self.scans += 1;
                self.ready.push_back(Event::Scan { scan, arrival_ns: 0 });
            }
        }
        Ok(())
    }

    /// The end of the pcap: the assembler's last scans, then the rest of the file IMU.
    fn finish(&mut self) -> Result<(), PipelineError> {
        while let Some(d) = self.stream.flush() {
            self.take(d)?;
        }
        while let Some(s) = self.next_imu {
            self.ready.push_back(Event::Imu(s));
            self.next_imu = self.feed.next()?;
        }
        self.done = true;
        Ok(())
    }
}

impl Source for PcapSource<'_, '_> {
    fn next_event(&mut self) -> Result<Option<Event>, PipelineError> {
        if !self.started {
            self.started = true;
            self.next_imu = self.feed.next()?;
        }
        loop {
            if let Some(e) = self.ready.pop_front() {
                return Ok(Some(e));
            }
            if self.done {
                return Ok(None);
            }
            let udp = match self.reader.next_udp() {
                Ok(Some(u)) => u,
                Ok(None) => {
                    self.finish()?;
                    continue;
                }
                Err(e) => {
                    // The packets before the damage are used; none at all is an error.
                    if self.scans == 0 {
                        return Err(PipelineError(format!("{}: {e}", self.pcap.display())));
                    }
                    warn(format!("{}: {e}; replayed the packets before it", self.pcap.display()));
                    self.finish()?;
                    continue;
                }
            };
            self.bytes += udp.payload.len() as u64 + 58;
            self.progress.set_position(self.bytes.min(self.total));
            if let Some(wait) = self.pacer.as_mut().and_then(|p| p.wait(udp.ts_ns, Instant::now())) {
                std::thread::sleep(wait);
            }
            if let Some(d) = self.stream.packet(udp.dst_port, udp.payload, udp.ts_ns) {
                self.take(d)?;
            }
        }
    }
}
