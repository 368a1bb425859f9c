//! `loglio bag`: the odometry over a ROS bag (ROS 1, rosbag2 sqlite3, MCAP) through
//! [`crate::input::bag::BagReader`]: `sensor_msgs/PointCloud2` from the Velodyne or Ouster drivers (or
//! any cloud: clouds without ring or time fields get them from geometry, with one warning),
//! raw `velodyne_msgs/VelodyneScan` or Ouster packets (decoded by the core), and
//! `sensor_msgs/Imu` or the Ouster IMU packets. Topics are found by type unless named.

use std::path::PathBuf;
use std::time::Instant;

use loglio_core::scan::ScanPoint;

use crate::config::SensorFamily;
use crate::diag::warn;
use crate::error::PipelineError;
use crate::input::bag::{BagEvent, BagOptions, BagReader, PacketKind, TopicKind};
use crate::input::lidar_stream::{self, Decoded, LidarStream, SensorDecoder};
use crate::output::Progress;
use crate::run::engine::{self, StorageClass};
use crate::run::runner::{OwnedScan, RunStats, Runner};
use crate::run::setup::RunSetup;
use crate::sink::files::{Finished, Outputs};

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
        Ok(o)
    };
    let mut reader = BagReader::open(&opt.bag, bag_opts()?).map_err(|e| PipelineError(e.to_string()))?;
    let sel = reader.selection().clone();
    let topics = format!("LiDAR {}, IMU {}", sel.lidar.0, sel.imu.as_deref().unwrap_or("none"));
    // Packets need a decoder: Velodyne from the configuration, Ouster from its metadata (the
    // configuration's, or the bag's metadata topic, read in a first pass).
    let packets = matches!(sel.lidar.1, TopicKind::VelodyneScan | TopicKind::OusterPacket);
    let mut meta = match &cfg.sensor.ouster_metadata {
        Some(p) => Some(crate::input::ouster_meta::load(p).map_err(|e| PipelineError(e.to_string()))?),
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
                    meta = Some(
                        crate::input::ouster_meta::parse(&json).map_err(|e| PipelineError(e.to_string()))?,
                    );
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
    let dec =
        if packets { Some(SensorDecoder::new(&cfg, meta.as_ref().map(|m| &m.intrinsics))?) } else { None };
    let layout = match &dec {
        Some(d) => d.layout(),
        None => engine::config_layout(&cfg)?,
    };
    if let Some(m) = &meta {
        cfg.sensor.columns = m.intrinsics.columns_per_frame as u32;
    }
    let class = StorageClass::choose(layout.rows(), layout.cols(), cfg.mapping.map_capacity)?;
    let core = engine::odometry_config(&cfg, layout)?;
    let n = dec.as_ref().map_or(0, |d| d.max_points());
    let (mut a, mut b) = (vec![ScanPoint::default(); n], vec![ScanPoint::default(); n]);
    let mut stream = dec.map(|d| LidarStream::of_kinds(&cfg, d, &mut a, &mut b));
    let outputs = Outputs::new(opt.setup.outputs()?)?;
    let progress = if opt.progress {
        Progress::new(reader.total_messages().unwrap_or(0), "messages", false)
    } else {
        Progress::hidden()
    };
    let scan_offset_ns = (cfg.time.scan_stamp_offset * 1e9).round() as i64;
    let (stats, finished) = engine::with_engine(&core, class, |engine| -> Result<_, PipelineError> {
        let mut runner = Runner::new(engine, outputs, cfg.time.lidar_imu_offset);
        runner.sinks = opt.setup.sinks.build();
        let mut read_error = None;
        let mut pacer = opt.realtime.map(crate::input::pace::Pacer::new);
        let (stop, _signals) = crate::run::Signals::stop_flag();
        while let Some(item) = reader.next() {
            if stop.load(std::sync::atomic::Ordering::Relaxed) {
                warn("stopped by a signal; writing what was estimated");
                break;
            }
            let item = match item {
                Ok(i) => i,
                Err(e) => {
                    read_error = Some(e.to_string());
                    break;
                }
            };
            if let Some(p) = &mut pacer {
                p.wait_for(item.record_ns);
            }
            match item.event {
                BagEvent::Scan(sc) => runner.scan(
                    OwnedScan {
                        start_ns: sc.stamp_ns.saturating_add_signed(scan_offset_ns),
                        points: sc.points,
                    },
                    0,
                )?,
                BagEvent::Imu(s) => runner.imu(s)?,
                BagEvent::LidarPacket(p) => {
                    let Some(st) = stream.as_mut() else { continue };
                    let kind = match p.kind {
                        PacketKind::Velodyne | PacketKind::OusterLidar => lidar_stream::PacketKind::Lidar,
                        PacketKind::OusterImu => lidar_stream::PacketKind::OusterImu,
                    };
                    match st.packet_of_kind(kind, &p.bytes, p.stamp_ns) {
                        Some(Decoded::Scan(s)) => runner.scan(s, 0)?,
                        Some(Decoded::Imu(s)) => runner.imu(s)?,
                        None => {}
                    }
                }
                BagEvent::OusterMetadata(_) => {}
            }
            progress.set_position(reader.stats().messages);
        }
        if let Some(st) = stream.as_mut() {
            while let Some(d) = st.flush() {
                match d {
                    Decoded::Scan(s) => runner.scan(s, 0)?,
                    Decoded::Imu(s) => runner.imu(s)?,
                }
            }
            for w in st.warnings() {
                warn(w);
            }
        }
        if let Some(e) = read_error {
            if runner.stats.scans == 0 && runner.pending() == 0 {
                return Err(PipelineError(e));
            }
            warn(format!("{e}; ran the messages before it"));
        }
        runner.finish()
    })??;
    progress.finish();
    Ok(BagRunReport {
        stats,
        finished,
        bag_stats: reader.stats().to_string(),
        topics,
        scan_period_s: 1.0 / cfg.sensor.scan_rate_hz,
        wall_s: wall.elapsed().as_secs_f64(),
    })
}
