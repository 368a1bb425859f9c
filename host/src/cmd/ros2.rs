//! `loglio ros2`: the odometry live on ROS 2 topics, over DDS with no ROS installation
//! ([`crate::input::ros2`]): a `sensor_msgs/PointCloud2` topic (Velodyne and Ouster driver
//! layouts, or any cloud, converted as `loglio bag` converts them) and a `sensor_msgs/Imu` topic,
//! with the outputs, status line, stops and drop counts of `loglio live`.
//!
//! # Threads and queues
//!
//! ```text
//! DDS readers (cloud, IMU, /tf_static) ── reading thread: CDR decoding, cloud to scan,
//!                                          try_send ──[IMU samples + scans, bounded]──> odometry
//! ```
//!
//! - The reading thread never waits on the odometry: a scan beyond
//!   [`live::MAX_QUEUED_SCANS`] waiting, or any message that finds the queue full, is dropped
//!   and counted (before the odometry starts, scans wait without that limit).
//! - Before the run starts, the first cloud (and IMU message) are awaited: their `frame_id`s and
//!   the latched `/tf_static` give the LiDAR-IMU extrinsic when the command line and the
//!   configuration give none (precedence: `--extrinsic` > the configuration's > `/tf_static` >
//!   the preset's > identity with a warning). `/tf_static` is waited for at most [`TF_WAIT`]
//!   once both frames are known.
//! - The odometry runs on the calling thread through [`Runner`]: a scan waits for the IMU to
//!   cover it at most [`live::IMU_WAIT`], as in `live`.
//! - Stamps: with `time.lidar_time_source = "packet"` (the default) the messages' header stamps
//!   (a cloud's start is its header stamp plus its earliest point time); with `"capture"` the
//!   time each message was taken on this computer (a cloud's as its end).
//! - Once a second a status line; Ctrl-C, SIGTERM or `--seconds` stop the reading, the queued
//!   scans are processed and every output is written.

use std::collections::HashSet;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::mpsc::{self, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::cmd::Watch;
use crate::cmd::live::{self, Msg, ScanTimes, Stall, StatusLine, StopReason, pose_phrase, since};
use crate::config::{ImuSource, LidarTimeSource};
use crate::diag::warn;
use crate::error::PipelineError;
use crate::input::bag::cloud::{CloudOptions, cloud_to_scan, note_warnings};
use crate::input::bag::{StaticFrames, add_static, chain, imu_sample};
use crate::input::ros2::{Received, Ros2InputOptions, Ros2Message, Ros2Subscriber};
use crate::run::engine::{self, StorageClass};
use crate::run::runner::{OwnedScan, RunStats, Runner};
use crate::run::setup::{DataExtrinsic, RunSetup};
use crate::sink::files::{self, Finished};

/// How long `/tf_static` is waited for once the LiDAR and IMU frames are known.
pub const TF_WAIT: Duration = Duration::from_secs(2);

/// A ROS 2 run's settings.
#[derive(Clone, Debug)]
pub struct Ros2RunOptions {
    /// Configuration, outputs, ground truth.
    pub setup: RunSetup,
    /// The `sensor_msgs/PointCloud2` topic.
    pub lidar_topic: String,
    /// The `sensor_msgs/Imu` topic (`None`: LiDAR-only, a constant-velocity model).
    pub imu_topic: Option<String>,
    /// The DDS domain (`None`: `ROS_DOMAIN_ID`, default 0).
    pub domain: Option<u16>,
    /// Best-effort readers (for best-effort publishers).
    pub best_effort: bool,
    /// When to stop (`seconds` from the moment the readers start), the timeouts (`lidar_timeout_s`:
    /// no cloud), the status line.
    pub watch: Watch,
    /// Handle SIGINT and SIGTERM.
    pub handle_signals: bool,
}

impl Ros2RunOptions {
    /// Defaults for `setup` and the LiDAR topic: the IMU on `/imu/data`, `ROS_DOMAIN_ID`, no
    /// time limit.
    pub fn new(setup: RunSetup, lidar_topic: &str) -> Self {
        Ros2RunOptions {
            setup,
            lidar_topic: lidar_topic.into(),
            imu_topic: Some("/imu/data".into()),
            domain: None,
            best_effort: false,
            watch: Watch::default(),
            handle_signals: true,
        }
    }
}

/// Counts of a ROS 2 run.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Ros2Counts {
    /// Clouds received.
    pub clouds: u64,
    /// IMU messages received.
    pub imu_messages: u64,
    /// `/tf_static` messages received.
    pub tf_messages: u64,
    /// Messages that could not be decoded or converted (dropped).
    pub malformed: u64,
    /// Points skipped in the clouds (non-finite, no return).
    pub skipped_points: u64,
    /// IMU samples that found the queue full, or that the odometry refused.
    pub imu_drops: u64,
    /// Scans dropped because the odometry did not keep up.
    pub scan_drops: u64,
    /// Mean latency, receipt of a cloud to its result, s.
    pub latency_mean_s: f64,
    /// Largest latency, s.
    pub latency_max_s: f64,
}

/// A finished ROS 2 run.
#[derive(Debug)]
pub struct Ros2Report {
    /// The odometry's counts and times.
    pub stats: RunStats,
    /// What was written and the evaluation.
    pub finished: Finished,
    /// Reception and drop counts.
    pub counts: Ros2Counts,
    /// Why it stopped.
    pub stopped_by: StopReason,
    /// `LiDAR /velodyne_points, IMU /imu/data, domain 0`.
    pub topics: String,
    /// Where the extrinsic came from (a summary line), unless nothing gave one.
    pub extrinsic: Option<String>,
    /// The scan period, s.
    pub scan_period_s: f64,
    /// Wall time, s.
    pub wall_s: f64,
}

/// What the reading thread counts and learns.
#[derive(Debug, Default)]
struct Shared {
    clouds: AtomicU64,
    imu_messages: AtomicU64,
    tf_messages: AtomicU64,
    malformed: AtomicU64,
    skipped_points: AtomicU64,
    imu_queue_drops: AtomicU64,
    scan_drops: AtomicU64,
    scans_queued: AtomicUsize,
    /// ns since the start of the last cloud and IMU message (0: none yet).
    last_cloud_ns: AtomicU64,
    last_imu_ns: AtomicU64,
    /// The odometry runs: the scan queue's limit applies.
    started: AtomicBool,
    frames: Mutex<Frames>,
}

/// The frames of the first messages and the static transforms.
#[derive(Debug, Default)]
struct Frames {
    lidar: Option<String>,
    imu: Option<String>,
    tf: StaticFrames,
}

/// The reading thread's conversion: messages to scans and samples, sent without waiting.
struct Convert {
    cloud: CloudOptions,
    capture_stamps: bool,
    scan_offset_ns: i64,
    lidar_topic: String,
    imu_topic: String,
    warned: HashSet<String>,
    tx: SyncSender<Msg>,
    shared: Arc<Shared>,
    t0: Instant,
}

impl Convert {
    fn warn_once(&mut self, key: String, text: impl FnOnce() -> String) {
        if self.warned.insert(key) {
            warn(text());
        }
    }

    fn malformed(&mut self, topic: &str, why: &str) {
        self.shared.malformed.fetch_add(1, Relaxed);
        self.warn_once(format!("malformed {topic}"), || {
            format!("{topic}: a message could not be read ({why}); dropped (later ones are counted)")
        });
    }

    /// `false`: the odometry is gone.
    fn handle(&mut self, r: Received) -> bool {
        let at = since(self.t0);
        let sh = Arc::clone(&self.shared);
        match r.msg {
            Ros2Message::Cloud(c) => {
                sh.clouds.fetch_add(1, Relaxed);
                sh.last_cloud_ns.store(at, Relaxed);
                {
                    let mut f = sh.frames.lock().unwrap_or_else(|e| e.into_inner());
                    f.lidar.get_or_insert_with(|| c.frame_id.trim_start_matches('/').to_string());
                }
                let topic = self.lidar_topic.clone();
                let s = match cloud_to_scan(&c, &self.cloud) {
                    Ok(s) => s,
                    Err(why) => {
                        self.malformed(&topic, &why);
                        return true;
                    }
                };
                for (key, text) in note_warnings(&topic, &s.notes, &self.cloud) {
                    self.warn_once(key, || text);
                }
                sh.skipped_points.fetch_add(s.skipped as u64, Relaxed);
                let stamp = if self.capture_stamps {
                    let last = s.points.iter().map(|p| p.t).fold(0.0f32, f32::max);
                    r.capture_ns.saturating_sub((last as f64 * 1e9) as u64)
                } else {
                    s.start_ns
                };
                let scan = OwnedScan {
                    start_ns: stamp.saturating_add_signed(self.scan_offset_ns),
                    points: s.points,
                };
                if sh.started.load(Relaxed) && sh.scans_queued.load(Relaxed) >= live::MAX_QUEUED_SCANS {
                    sh.scan_drops.fetch_add(1, Relaxed);
                    return true;
                }
                sh.scans_queued.fetch_add(1, Relaxed);
                match self.tx.try_send(Msg::Scan { scan, arrival_ns: at }) {
                    Ok(()) => true,
                    Err(TrySendError::Full(_)) => {
                        sh.scans_queued.fetch_sub(1, Relaxed);
                        sh.scan_drops.fetch_add(1, Relaxed);
                        true
                    }
                    Err(TrySendError::Disconnected(_)) => false,
                }
            }
            Ros2Message::Imu(m, frame) => {
                sh.imu_messages.fetch_add(1, Relaxed);
                sh.last_imu_ns.store(at, Relaxed);
                {
                    let mut f = sh.frames.lock().unwrap_or_else(|e| e.into_inner());
                    f.imu.get_or_insert_with(|| frame.trim_start_matches('/').to_string());
                }
                let t = if self.capture_stamps { r.capture_ns } else { m.stamp_ns };
                match imu_sample(&m, t) {
                    Ok(s) => match self.tx.try_send(Msg::Imu(s)) {
                        Ok(()) => true,
                        Err(TrySendError::Full(_)) => {
                            sh.imu_queue_drops.fetch_add(1, Relaxed);
                            true
                        }
                        Err(TrySendError::Disconnected(_)) => false,
                    },
                    Err(why) => {
                        let topic = self.imu_topic.clone();
                        self.malformed(&topic, &why);
                        true
                    }
                }
            }
            Ros2Message::TfStatic(ts) => {
                sh.tf_messages.fetch_add(1, Relaxed);
                let mut f = sh.frames.lock().unwrap_or_else(|e| e.into_inner());
                add_static(&mut f.tf, &ts);
                true
            }
            Ros2Message::Malformed { topic, why } => {
                self.malformed(&topic, &why);
                true
            }
        }
    }
}

/// Runs on the topics until a signal or `seconds`.
pub fn run(opt: &Ros2RunOptions) -> Result<Ros2Report, PipelineError> {
    let wall = Instant::now();
    let mut cfg = opt.setup.load_config()?;
    opt.watch.check()?;
    let domain = match opt.domain {
        Some(d) => d,
        None => crate::sink::ros2::domain_from_env(std::env::var("ROS_DOMAIN_ID").ok().as_deref())
            .map_err(|e| PipelineError(e.0))?,
    };
    // `--no-imu`, or `imu.source = "none"` in the configuration: LiDAR-only.
    let lidar_only = opt.imu_topic.is_none() || cfg.imu.source == ImuSource::None;
    if lidar_only {
        cfg.imu.source = ImuSource::None;
    }
    let imu_topic = opt.imu_topic.clone().filter(|_| !lidar_only);
    let want_tf = !lidar_only && opt.setup.data_extrinsic_used(&cfg);
    let cloud = CloudOptions::from_config(&cfg)?;
    let layout = engine::config_layout(&cfg)?;
    let stop_signal = Arc::new(AtomicBool::new(false));
    let _signals = if opt.handle_signals { Some(crate::run::Signals::register(&stop_signal)?) } else { None };

    let t0 = Instant::now();
    let shared = Arc::new(Shared::default());
    let (msg_tx, msg_rx) = mpsc::sync_channel::<Msg>(live::ODOMETRY_QUEUE);
    let mut conv = Convert {
        cloud,
        capture_stamps: cfg.time.lidar_time_source == LidarTimeSource::Capture,
        scan_offset_ns: (cfg.time.scan_stamp_offset * 1e9).round() as i64,
        lidar_topic: opt.lidar_topic.clone(),
        imu_topic: imu_topic.clone().unwrap_or_default(),
        warned: HashSet::new(),
        tx: msg_tx,
        shared: Arc::clone(&shared),
        t0,
    };
    let sub_opt = Ros2InputOptions {
        domain,
        lidar_topic: opt.lidar_topic.clone(),
        imu_topic: imu_topic.clone(),
        tf_static: want_tf,
        best_effort: opt.best_effort,
    };
    let mut sub = Ros2Subscriber::start(&sub_opt, move |r| conv.handle(r))?;
    let imu_name = imu_topic.clone().unwrap_or_else(|| "none".into());
    let topics = format!("LiDAR {}, IMU {imu_name}, domain {domain}", opt.lidar_topic);
    let qos_hint =
        if opt.best_effort { "" } else { "; a best-effort publisher (sensor-data QoS) needs --best-effort" };
    let imu_desc = match &imu_topic {
        Some(t) => format!("{t} (sensor_msgs/Imu)"),
        None => crate::run::runner::LIDAR_ONLY_MODEL.to_string(),
    };
    eprintln!(
        "loglio ros2: subscribed to {} (sensor_msgs/PointCloud2), {imu_desc}, on ROS_DOMAIN_ID {domain}; Ctrl-C to stop",
        opt.lidar_topic
    );

    // The first messages: their frames and /tf_static give the extrinsic.
    let lidar_timeout_ns = (opt.watch.lidar_timeout_s * 1e9) as u64;
    let mut both_at: Option<u64> = None;
    let data = loop {
        if stop_signal.load(Relaxed) {
            return Err(PipelineError(format!(
                "stopped by a signal before a cloud arrived on {}",
                opt.lidar_topic
            )));
        }
        let now = since(t0);
        {
            let f = shared.frames.lock().unwrap_or_else(|e| e.into_inner());
            if f.lidar.is_some() && !want_tf {
                break None;
            }
        }
        if shared.clouds.load(Relaxed) == 0 && now > lidar_timeout_ns {
            return Err(PipelineError(format!(
                "no sensor_msgs/PointCloud2 on {} within {} s (ROS_DOMAIN_ID {domain}): is the driver publishing there{qos_hint}?",
                opt.lidar_topic, opt.watch.lidar_timeout_s
            )));
        }
        if want_tf {
            let f = shared.frames.lock().unwrap_or_else(|e| e.into_inner());
            if let (Some(l), Some(i)) = (&f.lidar, &f.imu) {
                let at = *both_at.get_or_insert(now);
                if let Some(e) = chain(&f.tf, i, l) {
                    let t = e.translation.vector;
                    let q = e.rotation;
                    break Some(DataExtrinsic {
                        what: format!("/tf_static ({l} in {i})"),
                        translation: [t.x, t.y, t.z],
                        quat_wxyz: [q.w, q.i, q.j, q.k],
                    });
                }
                if now - at > TF_WAIT.as_nanos() as u64 {
                    break None;
                }
            } else if f.lidar.is_some() && now > lidar_timeout_ns {
                // No IMU message yet: the run says so; the extrinsic is not waited for longer.
                break None;
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let note = opt.setup.resolve_extrinsic(&mut cfg, data)?;
    if !lidar_only {
        note.warn_if_missing();
    }
    let extrinsic = note.line().map(str::to_string);
    let class = StorageClass::choose(layout.rows(), layout.cols(), cfg.mapping.map_capacity)?;
    let core = engine::odometry_config(&cfg, layout)?;
    let outputs = files::Outputs::new(opt.setup.outputs()?)?;
    let scan_period_s = 1.0 / cfg.sensor.scan_rate_hz;
    let res = engine::with_engine(&core, class, cfg.compute.resolved_threads(), |engine| {
        shared.started.store(true, Relaxed);
        let times = std::rc::Rc::new(std::cell::RefCell::new(ScanTimes::default()));
        let mut runner = Runner::new(engine, outputs, cfg.time.lidar_imu_offset);
        runner.set_lidar_only(lidar_only);
        runner.sinks = opt.setup.sinks.build();
        runner.set_origin(t0);
        runner.sinks.set_origin(t0);
        {
            let times = std::rc::Rc::clone(&times);
            runner.on_scan = Some(Box::new(move |res, _, arrival| {
                let latency = since(t0).saturating_sub(arrival);
                let mut t = times.borrow_mut();
                t.window.push((latency, res.times.total_ns));
                t.latency_sum_ns += latency;
                t.latency_max_ns = t.latency_max_ns.max(latency);
                t.result.record(latency, res.times.total_ns);
                t.scans += 1;
            }));
        }
        let status = StatusLine::new(opt.watch.status);
        let limit_ns = opt.watch.seconds.map(|s| (s * 1e9) as u64);
        let imu_timeout_ns = (opt.watch.imu_timeout_s * 1e9) as u64;
        let wait_ns = live::IMU_WAIT.as_nanos() as u64;
        let (mut lidar_stall, mut imu_stall) = (Stall::default(), Stall::default());
        let mut stopped: Option<StopReason> = None;
        let mut last_status = (since(t0), shared.imu_messages.load(Relaxed)); // (time, IMU messages)
        loop {
            match msg_rx.recv_timeout(Duration::from_millis(100)) {
                Ok(Msg::Imu(s)) => runner.imu(s)?,
                Ok(Msg::Scan { scan, arrival_ns }) => {
                    shared.scans_queued.fetch_sub(1, Relaxed);
                    runner.scan(scan, arrival_ns)?;
                }
                // The reading thread has stopped and its queue is drained.
                Err(RecvTimeoutError::Disconnected) => break,
                Err(RecvTimeoutError::Timeout) => {}
            }
            let now = since(t0);
            runner.process_ready(false, Some(now.saturating_sub(wait_ns)))?;
            if stopped.is_none() {
                let reason = if stop_signal.load(Relaxed) {
                    Some(StopReason::Signal)
                } else if limit_ns.is_some_and(|l| now >= l) {
                    Some(StopReason::Seconds)
                } else {
                    None
                };
                if let Some(r) = reason {
                    // Joins the reading thread: its end of the queue closes.
                    sub.stop();
                    stopped = Some(r);
                    continue;
                }
                let last_cloud = shared.last_cloud_ns.load(Relaxed);
                lidar_stall.check(now, last_cloud, lidar_timeout_ns, |s| {
                    format!("no clouds on {} for {s:.0} s; still listening", opt.lidar_topic)
                });
                if !lidar_only {
                    imu_stall.check(now, shared.last_imu_ns.load(Relaxed), imu_timeout_ns, |s| {
                        format!(
                            "no IMU messages on {imu_name} for {s:.0} s{qos_hint}; scans wait {:.1} s for it, then run without",
                            live::IMU_WAIT.as_secs_f64()
                        )
                    });
                }
            }
            if now.saturating_sub(last_status.0) >= 1_000_000_000 {
                let dt = (now - last_status.0) as f64 * 1e-9;
                let imu_msgs = shared.imu_messages.load(Relaxed);
                let line = {
                    let mut t = times.borrow_mut();
                    let counts = snapshot(&shared, &runner.stats, &t);
                    let mut line = format!(
                        "ros2: {}; {:.1} scans/s, {:.0} IMU/s, {}, {}",
                        pose_phrase(runner.latest.as_ref()),
                        t.window.len() as f64 / dt,
                        (imu_msgs - last_status.1) as f64 / dt,
                        live::timing_phrase(&t.window, scan_period_s),
                        drops(&counts)
                    );
                    if lidar_only {
                        line = line.replacen("ros2: ", "ros2: LiDAR-only (no IMU), ", 1);
                    }
                    if !runner.sinks.is_empty() {
                        line.push_str(&format!("; outputs: {}", runner.sinks.status_phrase()));
                    }
                    t.window.clear();
                    line
                };
                status.show(line);
                last_status = (now, imu_msgs);
            }
        }
        drop(status);
        let stopped_by = stopped.unwrap_or(StopReason::Signal);
        runner.process_ready(true, None)?;
        let counts = snapshot(&shared, &runner.stats, &times.borrow());
        if counts.clouds == 0 {
            return Err(PipelineError(format!("no clouds arrived on {} during the run", opt.lidar_topic)));
        }
        if runner.stats.imu_in == 0 && !lidar_only {
            return Err(PipelineError(format!(
                "no IMU data arrived on {imu_name} during the run ({} clouds){qos_hint}",
                counts.clouds
            )));
        }
        if runner.stats.scans == 0 {
            return Err(PipelineError(format!(
                "no scan was processed ({} clouds, {} malformed)",
                counts.clouds, counts.malformed
            )));
        }
        let (stats, finished) = runner.finish()?;
        Ok((stats, finished, counts, stopped_by))
    })??;
    let (stats, finished, counts, stopped_by) = res;
    Ok(Ros2Report {
        stats,
        finished,
        counts,
        stopped_by,
        topics,
        extrinsic,
        scan_period_s,
        wall_s: wall.elapsed().as_secs_f64(),
    })
}

fn snapshot(sh: &Shared, stats: &RunStats, t: &ScanTimes) -> Ros2Counts {
    Ros2Counts {
        clouds: sh.clouds.load(Relaxed),
        imu_messages: sh.imu_messages.load(Relaxed),
        tf_messages: sh.tf_messages.load(Relaxed),
        malformed: sh.malformed.load(Relaxed),
        skipped_points: sh.skipped_points.load(Relaxed),
        imu_drops: sh.imu_queue_drops.load(Relaxed) + stats.imu_dropped,
        scan_drops: sh.scan_drops.load(Relaxed),
        latency_mean_s: if t.scans > 0 { t.latency_sum_ns as f64 * 1e-9 / t.scans as f64 } else { 0.0 },
        latency_max_s: t.latency_max_ns as f64 * 1e-9,
    }
}

fn drops(c: &Ros2Counts) -> String {
    format!("drops: malformed {}, IMU {}, scans {}", c.malformed, c.imu_drops, c.scan_drops)
}

/// The summary of a ROS 2 run (stdout).
pub fn summary(r: &Ros2Report) -> String {
    let c = &r.counts;
    let mut s = format!(
        "ros2: {}; stopped by {}; {} clouds, {} IMU messages, {} /tf_static messages; {}\n",
        r.topics,
        match r.stopped_by {
            StopReason::Signal => "a signal",
            StopReason::Seconds => "--seconds",
        },
        c.clouds,
        c.imu_messages,
        c.tf_messages,
        drops(c)
    );
    if let Some(e) = &r.extrinsic {
        s.push_str(e);
        s.push('\n');
    }
    s.push_str(&format!(
        "latency (cloud received to its result): mean {:.0} ms, max {:.0} ms\n",
        c.latency_mean_s * 1e3,
        c.latency_max_s * 1e3
    ));
    s.push_str(&crate::run::runner::summary(&r.stats, &r.finished, r.scan_period_s, r.wall_s));
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{Config, Preset};
    use crate::input::bag::msg::{Imu, PointCloud2, PointField, Transform, datatype};

    /// A Velodyne driver cloud of three points, times 0, 0.05 and 0.1 s after the stamp.
    fn cloud(stamp_ns: u64) -> PointCloud2 {
        let f = |name: &str, offset, dt| PointField { name: name.into(), offset, datatype: dt, count: 1 };
        let mut data = Vec::new();
        for (i, t) in [0.0f32, 0.05, 0.1].iter().enumerate() {
            for v in [5.0f32, i as f32, 0.5, 10.0] {
                data.extend_from_slice(&v.to_le_bytes());
            }
            data.extend_from_slice(&7u16.to_le_bytes());
            data.extend_from_slice(&t.to_le_bytes());
        }
        PointCloud2 {
            stamp_ns,
            frame_id: "/velodyne".into(),
            height: 1,
            width: 3,
            fields: vec![
                f("x", 0, datatype::FLOAT32),
                f("y", 4, datatype::FLOAT32),
                f("z", 8, datatype::FLOAT32),
                f("intensity", 12, datatype::FLOAT32),
                f("ring", 16, datatype::UINT16),
                f("time", 18, datatype::FLOAT32),
            ],
            is_bigendian: false,
            point_step: 22,
            row_step: 66,
            data,
            is_dense: true,
        }
    }

    fn convert(capture: bool) -> (Convert, mpsc::Receiver<Msg>, Arc<Shared>) {
        let cfg = Config::preset(Preset::Vlp16);
        let (tx, rx) = mpsc::sync_channel(100);
        let shared = Arc::new(Shared::default());
        let c = Convert {
            cloud: CloudOptions::from_config(&cfg).unwrap(),
            capture_stamps: capture,
            scan_offset_ns: 0,
            lidar_topic: "/points".into(),
            imu_topic: "/imu".into(),
            warned: HashSet::new(),
            tx,
            shared: Arc::clone(&shared),
            t0: Instant::now(),
        };
        (c, rx, shared)
    }

    fn got(msg: Ros2Message, capture_ns: u64) -> Received {
        Received { msg, capture_ns }
    }

    #[test]
    fn clouds_and_imu_become_scans_and_samples_with_their_frames() {
        let (mut c, rx, sh) = convert(false);
        assert!(c.handle(got(Ros2Message::Cloud(cloud(1_000_000_000)), 9_000_000_000)));
        let imu = Imu {
            stamp_ns: 1_000_500_000,
            orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
            angular_velocity: [0.1, 0.0, 0.0],
            linear_acceleration: [0.0, 0.0, 9.8],
        };
        assert!(c.handle(got(Ros2Message::Imu(imu, "imu_link".into()), 9_000_000_000)));
        let tf = Transform {
            parent: "imu_link".into(),
            child: "velodyne".into(),
            translation: [0.1, 0.0, 0.0],
            rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
        };
        assert!(c.handle(got(Ros2Message::TfStatic(vec![tf]), 0)));
        // The header stamps: the scan starts at its earliest point.
        match rx.try_recv() {
            Ok(Msg::Scan { scan, .. }) => {
                assert_eq!(scan.start_ns, 1_000_000_000);
                assert_eq!(scan.points.len(), 3);
            }
            _ => panic!("no scan"),
        }
        match rx.try_recv() {
            Ok(Msg::Imu(s)) => assert_eq!((s.t_ns, s.acc[2]), (1_000_500_000, 9.8)),
            _ => panic!("no IMU sample"),
        }
        let f = sh.frames.lock().unwrap();
        assert_eq!((f.lidar.as_deref(), f.imu.as_deref()), (Some("velodyne"), Some("imu_link")));
        let e = chain(&f.tf, "imu_link", "velodyne").unwrap();
        assert!((e.translation.vector.x - 0.1).abs() < 1e-12);
        assert_eq!(
            (sh.clouds.load(Relaxed), sh.imu_messages.load(Relaxed), sh.tf_messages.load(Relaxed)),
            (1, 1, 1)
        );
    }

    #[test]
    fn capture_stamps_take_the_arrival_as_the_scan_end() {
        let (mut c, rx, _) = convert(true);
        assert!(c.handle(got(Ros2Message::Cloud(cloud(1_000_000_000)), 9_000_000_000)));
        match rx.try_recv() {
            Ok(Msg::Scan { scan, .. }) => {
                assert_eq!(scan.start_ns, 9_000_000_000 - (0.1f32 as f64 * 1e9) as u64)
            }
            _ => panic!("no scan"),
        }
    }

    #[test]
    fn scans_queue_freely_before_the_start_then_at_most_four_wait() {
        let (mut c, rx, sh) = convert(false);
        for i in 0..6 {
            assert!(c.handle(got(Ros2Message::Cloud(cloud(1_000_000_000 + i * 100_000_000)), 0)));
        }
        assert_eq!((sh.scans_queued.load(Relaxed), sh.scan_drops.load(Relaxed)), (6, 0));
        sh.started.store(true, Relaxed);
        assert!(c.handle(got(Ros2Message::Cloud(cloud(2_000_000_000)), 0)));
        assert_eq!(sh.scan_drops.load(Relaxed), 1);
        // Malformed messages are counted (one warning each topic), nothing is sent.
        let mut bad = cloud(3_000_000_000);
        bad.data.truncate(10);
        let bad_imu = Imu {
            stamp_ns: 1,
            orientation_xyzw: [0.0; 4],
            angular_velocity: [f64::NAN, 0.0, 0.0],
            linear_acceleration: [0.0; 3],
        };
        let ((), warnings) = crate::diag::capture(|| {
            assert!(c.handle(got(Ros2Message::Cloud(bad.clone()), 0)));
            assert!(c.handle(got(Ros2Message::Cloud(bad), 0)));
            assert!(c.handle(got(Ros2Message::Imu(bad_imu, "imu".into()), 0)));
        });
        assert_eq!(sh.malformed.load(Relaxed), 3);
        assert_eq!(warnings.len(), 2, "{warnings:?}");
        assert!(warnings[0].starts_with("warning: /points: a message could not be read ("), "{warnings:?}");
        assert!(warnings[1].starts_with("warning: /imu: a message could not be read ("), "{warnings:?}");
        assert_eq!(rx.try_iter().count(), 6);
        // The odometry gone: the reading thread ends.
        drop(rx);
        sh.scans_queued.store(0, Relaxed);
        assert!(!c.handle(got(Ros2Message::Cloud(cloud(4_000_000_000)), 0)));
    }
}
