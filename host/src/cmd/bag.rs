//! `loglio bag`: the odometry over a ROS bag (ROS 1, rosbag2 sqlite3, MCAP) through
//! [`crate::input::bag::BagReader`]: `sensor_msgs/PointCloud2` from the Velodyne or Ouster drivers (or
//! any cloud: clouds without ring or time fields get them from geometry, with one warning),
//! raw `velodyne_msgs/VelodyneScan` or Ouster packets (decoded by the core), and
//! `sensor_msgs/Imu` or the Ouster IMU packets. Topics are found by type unless named.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::time::Instant;

use loglio_core::scan::ScanPoint;

use crate::config::{ImuSource, SensorFamily};
use crate::diag::warn;
use crate::error::PipelineError;
use crate::input::bag::{BagEvent, BagOptions, BagReader, PacketKind, TopicKind};
use crate::input::lidar_stream::{self, Decoded, LidarStream, SensorDecoder};
use crate::output::Progress;
use crate::run::engine;
use crate::run::runner::{OwnedScan, RunStats};
use crate::run::setup::{DataExtrinsic, RunSetup};
use crate::run::{Event, RunOptions, Source};
use crate::sink::files::Finished;

/// A bag run's settings.
#[derive(Clone, Debug)]
pub struct BagRunOptions {
    /// The bag (file or rosbag2 directory).
    pub bag: PathBuf,
    /// LiDAR topic (found by type if `None`).
    pub lidar_topic: Option<String>,
    /// IMU topic (found by type if `None`).
    pub imu_topic: Option<String>,
    /// The shared run settings.
    pub setup: RunSetup,
    /// Show the progress bar.
    pub progress: bool,
    /// Pace by the bag's record times (`rate` x real time).
    pub realtime: Option<f64>,
}

/// A finished bag run.
#[derive(Debug)]
pub struct BagRunReport {
    /// Counts and times.
    pub stats: RunStats,
    /// Outputs and evaluation.
    pub finished: Finished,
    /// The reader's counts, as a line.
    pub bag_stats: String,
    /// The topics read.
    pub topics: String,
    /// Where the extrinsic came from (a summary line), unless nothing gave one.
    pub extrinsic: Option<String>,
    /// Scan period, s.
    pub scan_period_s: f64,
    /// Wall time, s.
    pub wall_s: f64,
}

/// Runs the odometry over a bag.
pub fn run(opt: &BagRunOptions) -> Result<BagRunReport, PipelineError> {
    let wall = Instant::now();
    let mut cfg = opt.setup.load_config()?;
    let bag_opts = || -> Result<BagOptions, PipelineError> {
        let mut o = BagOptions::from_config(&cfg)?;
        o.lidar_topic = opt.lidar_topic.clone();
        o.imu_topic = opt.imu_topic.clone();
        o.require_imu = false;
        Ok(o)
    };
    let mut reader = BagReader::open(&opt.bag, bag_opts()?).map_err(|e| PipelineError(e.to_string()))?;
    let lidar_only = reader.selection().imu.is_none();
    if lidar_only && cfg.imu.source != ImuSource::None {
        warn(format!(
            "{}: no IMU topic (sensor_msgs/Imu): LiDAR-only (no IMU), a constant-velocity model; the world is the first scan's frame",
            opt.bag.display()
        ));
    }
    // No extrinsic from the configuration: the bag's /tf_static, if it connects the frames.
    let from_tf = match opt.setup.extrinsic_missing(&cfg) {
        Some(_) if !lidar_only => {
            BagReader::static_extrinsic(&opt.bag, &bag_opts()?).map_err(|e| PipelineError(e.to_string()))?
        }
        _ => None,
    };
    let sel = reader.selection().clone();
    let topics = format!("LiDAR {}, IMU {}", sel.lidar.0, sel.imu.as_deref().unwrap_or("none"));
    // Packets need a decoder: Velodyne from the configuration, Ouster from its metadata (the
    // configuration's, or the bag's metadata topic, read in a first pass).
    let packets = matches!(sel.lidar.1, TopicKind::VelodyneScan | TopicKind::OusterPacket);
    let mut meta = match &cfg.sensor.ouster_metadata {
        Some(p) => Some((
            crate::input::ouster_meta::load(p).map_err(|e| PipelineError(e.to_string()))?,
            p.display().to_string(),
        )),
        None => None,
    };
    if sel.lidar.1 == TopicKind::OusterPacket {
        if cfg.preset.family() != SensorFamily::Ouster {
            return Err(PipelineError(format!(
                "the bag holds Ouster packets; choose an Ouster preset (os1-*), not {}",
                cfg.preset
            )));
        }
        if meta.is_none() {
            let mut first =
                BagReader::open(&opt.bag, bag_opts()?).map_err(|e| PipelineError(e.to_string()))?;
            for item in first.by_ref().take(100_000) {
                if let Ok(crate::input::bag::BagItem { event: BagEvent::OusterMetadata(json), .. }) = item {
                    meta = Some((
                        crate::input::ouster_meta::parse(&json).map_err(|e| PipelineError(e.to_string()))?,
                        "of the bag's metadata topic".to_string(),
                    ));
                    break;
                }
            }
            if meta.is_none() {
                return Err(PipelineError(
                    "the bag holds Ouster packets but no metadata topic; pass --metadata FILE".into(),
                ));
            }
        }
    }
    if sel.lidar.1 == TopicKind::VelodyneScan && cfg.preset.family() != SensorFamily::Velodyne {
        return Err(PipelineError(format!(
            "the bag holds Velodyne packets; choose a Velodyne preset (vlp16, vlp32c, hdl32e), not {}",
            cfg.preset
        )));
    }
    let dec = if packets {
        Some(SensorDecoder::new(&cfg, meta.as_ref().map(|(m, _)| &m.intrinsics))?)
    } else {
        None
    };
    let layout = match &dec {
        Some(d) => d.layout(),
        None => engine::config_layout(&cfg)?,
    };
    if let Some((m, _)) = &meta {
        cfg.sensor.columns = m.intrinsics.columns_per_frame as u32;
    }
    // What the data gives: the bag's /tf_static, else the Ouster metadata's IMU transform.
    let data = match (from_tf, &meta) {
        (Some(e), _) => {
            let t = e.imu_lidar.translation.vector;
            let q = e.imu_lidar.rotation;
            Some(DataExtrinsic {
                what: format!("/tf_static ({} in {})", e.lidar_frame, e.imu_frame),
                translation: [t.x, t.y, t.z],
                quat_wxyz: [q.w, q.i, q.j, q.k],
            })
        }
        (None, Some((m, source))) => Some(DataExtrinsic::of_metadata(m, source)),
        (None, None) => None,
    };
    let note = opt.setup.resolve_extrinsic(&mut cfg, data)?;
    if !lidar_only {
        note.warn_if_missing();
    }
    let extrinsic = note.line().map(str::to_string);
    let n = dec.as_ref().map_or(0, |d| d.max_points());
    let (mut a, mut b) = (vec![ScanPoint::default(); n], vec![ScanPoint::default(); n]);
    let stream = dec.map(|d| LidarStream::of_kinds(&cfg, d, &mut a, &mut b));
    let progress = if opt.progress {
        Progress::new(reader.total_messages().unwrap_or(0), "messages", false)
    } else {
        Progress::hidden()
    };
    let mut src = BagSource {
        reader: &mut reader,
        stream,
        scan_offset_ns: (cfg.time.scan_stamp_offset * 1e9).round() as i64,
        pacer: opt.realtime.map(crate::input::pace::Pacer::new),
        progress: &progress,
        ready: VecDeque::new(),
        scans: 0,
        done: false,
    };
    if lidar_only {
        cfg.imu.source = ImuSource::None;
    }
    let (stop, _signals) = crate::run::Signals::stop_flag();
    let opts = RunOptions {
        outputs: opt.setup.outputs()?,
        sinks: opt.setup.sinks.build(),
        stop: Some(stop),
        ..RunOptions::default()
    };
    let (stats, finished) = crate::run::drive(&cfg, layout, &mut src, opts)?;
    if let Some(st) = &src.stream {
        for w in st.warnings() {
            warn(w);
        }
    }
    progress.finish();
    Ok(BagRunReport {
        stats,
        finished,
        bag_stats: reader.stats().to_string(),
        topics,
        extrinsic,
        scan_period_s: 1.0 / cfg.sensor.scan_rate_hz,
        wall_s: wall.elapsed().as_secs_f64(),
    })
}
/// The bag as a source: clouds and IMU messages as they are, packets through the decoder and
/// the scan assembly (told each packet's kind).
struct BagSource<'a, 'b> {
    reader: &'a mut BagReader,
    stream: Option<LidarStream<'b>>,
    scan_offset_ns: i64,
    pacer: Option<crate::input::pace::Pacer>,
    progress: &'a Progress,
    ready: VecDeque<Event>,
    scans: u64,
    done: bool,
}

impl BagSource<'_, '_> {
    fn take(&mut self, d: Decoded) {
        match d {
            Decoded::Scan(scan) => {
                self.scans += 1;
                self.ready.push_back(Event::Scan { scan, arrival_ns: 0 });
            }
            Decoded::Imu(s) => self.ready.push_back(Event::Imu(s)),
        }
    }

    /// The end of the bag: the assembler's last scans.
    fn finish(&mut self) {
        while let Some(d) = self.stream.as_mut().and_then(LidarStream::flush) {
            self.take(d);
        }
        self.done = true;
    }
}

impl Source for BagSource<'_, '_> {
    fn next_event(&mut self) -> Result<Option<Event>, PipelineError> {
        loop {
            if let Some(e) = self.ready.pop_front() {
                return Ok(Some(e));
            }
            if self.done {
                return Ok(None);
            }
            let item = match self.reader.next() {
                None => {
                    self.finish();
                    continue;
                }
                Some(Ok(i)) => i,
                Some(Err(e)) => {
                    // The messages before the damage are used; none at all is an error.
                    if self.scans == 0 {
                        return Err(PipelineError(e.to_string()));
                    }
                    warn(format!("{e}; ran the messages before it"));
                    self.finish();
                    continue;
                }
            };
            if let Some(p) = &mut self.pacer {
                p.wait_for(item.record_ns);
            }
            match item.event {
                BagEvent::Scan(sc) => self.take(Decoded::Scan(OwnedScan {
                    start_ns: sc.stamp_ns.saturating_add_signed(self.scan_offset_ns),
                    points: sc.points,
                })),
                BagEvent::Imu(s) => self.ready.push_back(Event::Imu(s)),
                BagEvent::LidarPacket(p) => {
                    let Some(st) = self.stream.as_mut() else { continue };
                    let kind = match p.kind {
                        PacketKind::Velodyne | PacketKind::OusterLidar => lidar_stream::PacketKind::Lidar,
                        PacketKind::OusterImu => lidar_stream::PacketKind::OusterImu,
                    };
                    if let Some(d) = st.packet_of_kind(kind, &p.bytes, p.stamp_ns) {
                        self.take(d);
                    }
                }
                BagEvent::OusterMetadata(_) => {}
            }
            self.progress.set_position(self.reader.stats().messages);
        }
    }
}
