//! Sinks: where each scan's result goes while the odometry runs (the robot's ROS 2 stack, an
//! autopilot over MAVLink, Foxglove, a program embedding loglio).
//!
//! The odometry never waits for a sink. Each sink runs on its own thread behind a bounded
//! [`SinkQueue`]; [`Sinks::send`] only ever tries to enqueue. When a queue is full, a waiting
//! high-rate pose ([`SinkEvent::ImuPose`]) is evicted first (a newer one follows within a
//! millisecond); only when none waits is the new event dropped. Every drop and every error is
//! counted per sink and shown in the live status line and the run's summary; the first error
//! of a sink is also printed as one `warning:` line.
//!
//! What a sink receives is owned and cheap to clone: the pose as plain arrays, the scan's
//! points and the map behind `Arc`s (computed once, only when some sink [`Wants`] them).

use std::collections::VecDeque;
use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

pub mod args;
pub mod callback;
pub mod files;
pub mod foxglove;
pub mod mavlink;
pub mod mcap;
pub mod ros2;

pub use args::SinkArgs;
pub use callback::{CallbackSink, ChannelSink};

/// The odometry's health as the live outputs carry it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LiveStatus {
    /// Waiting for the IMU initialisation: the pose is a placeholder.
    Initialising,
    /// Tracking, every direction observed.
    Ok,
    /// Tracking, with the pose axes in `axes` (bits 0-2 position x, y, z; 3-5 rotation about
    /// the IMU's x, y, z) left to the IMU.
    Degraded {
        /// The degenerate axes.
        axes: u8,
    },
    /// Tracking again after a pause of the IMU (`imu_gap`) or of the LiDAR that the filter
    /// bridged: usable, with a larger covariance.
    Bridged {
        /// Whether the IMU paused (else the LiDAR).
        imu_gap: bool,
    },
    /// The scan did not update the state: IMU propagation only.
    ImuOnly,
    /// The filter lost track and starts over (a new world frame: `resets` counts them).
    Lost,
}

impl LiveStatus {
    /// The status of a core result.
    pub fn of(s: &loglio_core::output::Status) -> LiveStatus {
        use loglio_core::output::Status;
        match s {
            Status::Ok => LiveStatus::Ok,
            Status::Degraded { axes, .. } => LiveStatus::Degraded { axes: *axes },
            Status::ImuOnly(_) => LiveStatus::ImuOnly,
            Status::Initialising(_) => LiveStatus::Initialising,
            Status::Reinitialising(_) | Status::Lost { .. } => LiveStatus::Lost,
            Status::Bridged(r) => {
                LiveStatus::Bridged { imu_gap: matches!(r, loglio_core::output::BridgeReason::ImuGap) }
            }
        }
    }

    /// A 0-100 quality (MAVLink's `quality`): 100 ok, 50 degraded, 20 IMU only, 0 otherwise.
    pub fn quality(self) -> u8 {
        match self {
            LiveStatus::Ok => 100,
            LiveStatus::Degraded { .. } | LiveStatus::Bridged { .. } => 50,
            LiveStatus::ImuOnly => 20,
            LiveStatus::Initialising | LiveStatus::Lost => 0,
        }
    }

    /// Whether the pose is usable at all (initialised and not lost).
    pub fn is_tracking(self) -> bool {
        !matches!(self, LiveStatus::Initialising | LiveStatus::Lost)
    }
}

impl fmt::Display for LiveStatus {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LiveStatus::Initialising => f.write_str("initialising"),
            LiveStatus::Ok => f.write_str("ok"),
            LiveStatus::Degraded { axes } => {
                f.write_str("degraded (")?;
                let names = ["x", "y", "z", "roll", "pitch", "yaw"];
                let mut first = true;
                for (k, n) in names.iter().enumerate() {
                    if axes & (1 << k) != 0 {
                        if !first {
                            f.write_str(",")?;
                        }
                        f.write_str(n)?;
                        first = false;
                    }
                }
                f.write_str(")")
            }
            LiveStatus::Bridged { imu_gap: true } => f.write_str("bridged (IMU gap)"),
            LiveStatus::Bridged { imu_gap: false } => f.write_str("bridged (LiDAR gap)"),
            LiveStatus::ImuOnly => f.write_str("imu-only"),
            LiveStatus::Lost => f.write_str("lost"),
        }
    }
}

/// One pose as it leaves the process: the IMU (`base_link`) in the odometry's world frame
/// (`odom`: gravity-aligned, z up, the start's yaw), ROS conventions (ENU-like, FLU body).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseSample {
    /// Time, ns (the LiDAR's clock: the scan end for a scan's pose).
    pub t_ns: u64,
    /// Position in the world, m.
    pub position: [f64; 3],
    /// World from body rotation (w, x, y, z).
    pub q_wxyz: [f64; 4],
    /// Velocity in the world frame, m/s.
    pub velocity_world: [f64; 3],
    /// Velocity in the body frame, m/s (what ROS's `twist` and MAVLink's body velocity carry).
    pub velocity_body: [f64; 3],
    /// Angular velocity in the body frame (the last gyro sample less the bias), rad/s.
    pub angular_velocity_body: [f64; 3],
    /// Covariance of (position in the world, m; rotation error in the body frame, rad),
    /// row-major 6 x 6.
    pub pose_covariance: [[f64; 6]; 6],
    /// Covariance of the body-frame velocity, row-major 3 x 3 ((m/s)^2).
    pub velocity_covariance: [[f64; 3]; 3],
    /// Health.
    pub status: LiveStatus,
    /// Jumps of the estimate so far: re-initialisations (each starts a new world frame) and
    /// re-localisations in the map (the position moved to where the scan fits).
    pub resets: u32,
}

impl PoseSample {
    /// The pose of a filter state, with `status`, `resets` and the body rate `omega_body`.
    pub fn from_filter(
        f: &loglio_core::eskf::Eskf,
        status: LiveStatus,
        resets: u32,
        omega_body: [f64; 3],
    ) -> PoseSample {
        use loglio_core::eskf::idx;
        let x = f.state();
        let p = f.covariance();
        let q = x.rot.quaternion();
        let r = x.rot.to_rotation_matrix().into_inner();
        let v_body = r.transpose() * x.vel;
        let mut pose_covariance = [[0.0; 6]; 6];
        for (i, row) in pose_covariance.iter_mut().enumerate() {
            for (j, c) in row.iter_mut().enumerate() {
                *c = p[(idx::POS + i, idx::POS + j)];
            }
        }
        // Velocity's covariance is the world frame's; the body's is R^T P R.
        let pv = p.fixed_view::<3, 3>(idx::VEL, idx::VEL).into_owned();
        let pb = r.transpose() * pv * r;
        let mut velocity_covariance = [[0.0; 3]; 3];
        for (i, row) in velocity_covariance.iter_mut().enumerate() {
            for (j, c) in row.iter_mut().enumerate() {
                *c = pb[(i, j)];
            }
        }
        PoseSample {
            t_ns: f.time_ns(),
            position: [x.pos.x, x.pos.y, x.pos.z],
            q_wxyz: [q.w, q.i, q.j, q.k],
            velocity_world: [x.vel.x, x.vel.y, x.vel.z],
            velocity_body: [v_body.x, v_body.y, v_body.z],
            angular_velocity_body: omega_body,
            pose_covariance,
            velocity_covariance,
            status,
            resets,
        }
    }

    /// A placeholder pose at `t_ns` (before the initialisation): identity, zero covariance.
    pub fn placeholder(t_ns: u64, status: LiveStatus, resets: u32) -> PoseSample {
        PoseSample {
            t_ns,
            position: [0.0; 3],
            q_wxyz: [1.0, 0.0, 0.0, 0.0],
            velocity_world: [0.0; 3],
            velocity_body: [0.0; 3],
            angular_velocity_body: [0.0; 3],
            pose_covariance: [[0.0; 6]; 6],
            velocity_covariance: [[0.0; 3]; 3],
            status,
            resets,
        }
    }
}

/// A map point as the live outputs carry it (world frame).
pub type MapPoint = crate::output::MapPoint;

/// One scan's result as the sinks see it.
#[derive(Clone, Debug)]
pub struct ScanOutput {
    /// Index of the scan in the run (0-based).
    pub index: u64,
    /// Scan start, ns.
    pub scan_start_ns: u64,
    /// The pose at the scan end.
    pub pose: PoseSample,
    /// The odometry's time for this scan, ms.
    pub process_ms: f64,
    /// Voxels in the map.
    pub map_voxels: usize,
    /// Points in the scan, and after downsampling.
    pub points: [u32; 2],
    /// The undistorted, downsampled scan in the world (`odom`) frame, when a sink wants it.
    pub cloud: Option<Arc<Vec<[f32; 3]>>>,
    /// The whole map in the world frame, every [`SinkOptions::map_every_s`], when a sink
    /// wants it.
    pub map: Option<Arc<Vec<MapPoint>>>,
    /// When the scan's last data arrived (live: the last packet's receive time) on the run's
    /// monotonic clock, ns; 0 when unknown (files).
    pub arrival_ns: u64,
    /// When the pose was ready, on the same clock as `arrival_ns`.
    pub ready_ns: u64,
}

/// What travels through a sink's queue. The pose is held by value: an allocation per IMU
/// sample would cost more than the queue's few hundred bytes per slot.
#[derive(Clone, Debug)]
#[allow(clippy::large_enum_variant)]
pub enum SinkEvent {
    /// A scan's result.
    Scan(Arc<ScanOutput>),
    /// The IMU-propagated pose between scans (from the latest scan's update).
    ImuPose(PoseSample),
}

/// What a sink needs computed for it (nothing is computed that no sink needs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Wants {
    /// The scan's points in the world frame.
    pub cloud: bool,
    /// The map, every few seconds.
    pub map: bool,
    /// The high-rate IMU-propagated pose.
    pub imu_pose: bool,
}

impl Wants {
    fn or(self, o: Wants) -> Wants {
        Wants { cloud: self.cloud || o.cloud, map: self.map || o.map, imu_pose: self.imu_pose || o.imu_pose }
    }
}

/// A sink's failure: one line, said once as a `warning:` and then counted.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SinkError(pub String);

impl fmt::Display for SinkError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for SinkError {}

impl From<std::io::Error> for SinkError {
    fn from(e: std::io::Error) -> Self {
        SinkError(e.to_string())
    }
}

/// A consumer of the odometry's results. It runs on its own thread: it may block on its own
/// output (a socket, a file) without slowing the odometry, which only drops what the queue
/// cannot hold.
pub trait Sink: Send {
    /// A short name for the status line and warnings (`ros2`, `mavlink udp:...`).
    fn name(&self) -> String;
    /// What it needs computed.
    fn wants(&self) -> Wants;
    /// Handles one event. An error is counted (and the first one printed); the sink keeps
    /// receiving.
    fn handle(&mut self, ev: &SinkEvent) -> Result<(), SinkError>;
    /// Called once after the last event (flush, close).
    fn finish(&mut self) -> Result<(), SinkError> {
        Ok(())
    }
    /// Called right after [`Sink::handle`] of a scan: when its pose left, `None` if it was not
    /// sent. The default (now) suits sinks whose `handle` ends with the send; a sink that
    /// sends more after the pose, or skips some, says so (the wire latency is the pose's).
    fn pose_sent(&mut self) -> Option<Instant> {
        Some(Instant::now())
    }
}

/// One sink's latency from a scan's last packet to its pose sent, beside the processing time
/// of the same scans (µs, live only). Bounded: past [`WireLatency::CAP`] scans a reservoir
/// keeps a uniform sample, so hours of running cost 256 KiB per sink.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct WireLatency {
    /// Scans measured.
    pub scans: u64,
    latency_us: Vec<u32>,
    process_us: Vec<u32>,
    rng: u64,
}

impl WireLatency {
    /// Samples kept.
    pub const CAP: usize = 1 << 15;

    /// Records one scan: its latency and processing time, ns.
    pub fn record(&mut self, latency_ns: u64, process_ns: u64) {
        let us = |ns: u64| u32::try_from(ns / 1000).unwrap_or(u32::MAX);
        self.scans += 1;
        let slot = if self.latency_us.len() < Self::CAP {
            self.latency_us.push(0);
            self.process_us.push(0);
            self.latency_us.len() - 1
        } else {
            // xorshift64: a uniform enough index for Algorithm R, without a dependency.
            let mut x = if self.rng == 0 { 0x9E37_79B9_7F4A_7C15 } else { self.rng };
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            self.rng = x;
            let j = x % self.scans;
            match usize::try_from(j) {
                Ok(j) if j < Self::CAP => j,
                _ => return,
            }
        };
        self.latency_us[slot] = us(latency_ns);
        self.process_us[slot] = us(process_ns);
    }

    /// Median and p99 of the latency, ms; `None` before any scan.
    pub fn latency_ms(&self) -> Option<[f64; 2]> {
        quantiles_ms(&self.latency_us)
    }

    /// Median and p99 of the processing time of the same scans, ms.
    pub fn process_ms(&self) -> Option<[f64; 2]> {
        quantiles_ms(&self.process_us)
    }

    /// `median 21.3 ms, p99 25.0 ms (processing of the same 57 scans: median 20.1 ms, p99
    /// 24.0 ms)`; `None` before any scan.
    pub fn phrase(&self) -> Option<String> {
        let [lm, lp] = self.latency_ms()?;
        let [pm, pp] = self.process_ms()?;
        Some(format!(
            "median {lm:.1} ms, p99 {lp:.1} ms (processing of the same {} scans: median {pm:.1} ms, p99 {pp:.1} ms)",
            self.scans
        ))
    }
}

/// Median and p99 (nearest rank) of µs values, in ms.
fn quantiles_ms(v: &[u32]) -> Option<[f64; 2]> {
    let mut s = v.to_vec();
    s.sort_unstable();
    let at = |q: f64| {
        let rank = (q * s.len() as f64).ceil() as usize;
        s.get(rank.max(1) - 1).map(|&x| f64::from(x) * 1e-3)
    };
    Some([at(0.5)?, at(0.99)?])
}

/// Counts of one sink.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct SinkStats {
    /// The sink's name.
    pub name: String,
    /// Events enqueued.
    pub queued: u64,
    /// Events handled.
    pub handled: u64,
    /// Scan events dropped because the queue was full.
    pub dropped_scans: u64,
    /// High-rate poses dropped (evicted or refused) because the queue was full.
    pub dropped_poses: u64,
    /// Events whose handling failed.
    pub errors: u64,
    /// The first error, if any.
    pub first_error: Option<String>,
    /// Latency from a scan's last packet to its pose sent (live runs only).
    pub wire: WireLatency,
}

impl SinkStats {
    /// Every event the sink did not get out: drops and errors.
    pub fn lost(&self) -> u64 {
        self.dropped_scans + self.dropped_poses + self.errors
    }
}

struct Shared {
    q: Mutex<QueueState>,
    cv: Condvar,
    handled: AtomicU64,
    errors: AtomicU64,
    first_error: Mutex<Option<String>>,
    /// The live run's clock origin (`arrival_ns` counts from it); unset: no latency.
    origin: OnceLock<Instant>,
    wire: Mutex<WireLatency>,
}

struct QueueState {
    events: VecDeque<SinkEvent>,
    closed: bool,
    busy: bool,
}

/// A sink on its own thread behind a bounded queue.
pub struct SinkQueue {
    name: String,
    wants: Wants,
    capacity: usize,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
    queued: u64,
    dropped_scans: u64,
    dropped_poses: u64,
}

impl fmt::Debug for SinkQueue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SinkQueue").field("name", &self.name).field("capacity", &self.capacity).finish()
    }
}

impl SinkQueue {
    /// Starts `sink` on a thread of its own with a queue of `capacity` events (at least 1).
    pub fn start(mut sink: Box<dyn Sink>, capacity: usize) -> Result<SinkQueue, SinkError> {
        let name = sink.name();
        let wants = sink.wants();
        let shared = Arc::new(Shared {
            q: Mutex::new(QueueState { events: VecDeque::new(), closed: false, busy: false }),
            cv: Condvar::new(),
            handled: AtomicU64::new(0),
            errors: AtomicU64::new(0),
            first_error: Mutex::new(None),
            origin: OnceLock::new(),
            wire: Mutex::new(WireLatency::default()),
        });
        let sh = Arc::clone(&shared);
        let label = name.clone();
        let thread = std::thread::Builder::new()
            .name(format!("loglio-sink-{}", name.split_whitespace().next().unwrap_or("sink")))
            .spawn(move || {
                let fail = |e: SinkError| {
                    sh.errors.fetch_add(1, Ordering::Relaxed);
                    let mut first = sh.first_error.lock().unwrap_or_else(|p| p.into_inner());
                    if first.is_none() {
                        crate::diag::warn(format!("{label}: {e} (further errors are counted)"));
                        *first = Some(e.0);
                    }
                };
                loop {
                    let ev = {
                        let mut q = sh.q.lock().unwrap_or_else(|p| p.into_inner());
                        q.busy = false;
                        loop {
                            if let Some(ev) = q.events.pop_front() {
                                q.busy = true;
                                break Some(ev);
                            }
                            if q.closed {
                                break None;
                            }
                            sh.cv.notify_all();
                            q = sh.cv.wait(q).unwrap_or_else(|p| p.into_inner());
                        }
                    };
                    let Some(ev) = ev else { break };
                    let r = sink.handle(&ev);
                    if let SinkEvent::Scan(s) = &ev {
                        let sent = sink.pose_sent();
                        if let (true, Some(sent), Some(origin)) = (r.is_ok(), sent, sh.origin.get())
                            && s.arrival_ns > 0
                        {
                            let sent_ns = u64::try_from(sent.saturating_duration_since(*origin).as_nanos())
                                .unwrap_or(u64::MAX);
                            let process_ns = (s.process_ms.max(0.0) * 1e6) as u64;
                            sh.wire
                                .lock()
                                .unwrap_or_else(|p| p.into_inner())
                                .record(sent_ns.saturating_sub(s.arrival_ns), process_ns);
                        }
                    }
                    if let Err(e) = r {
                        fail(e);
                    }
                    sh.handled.fetch_add(1, Ordering::Relaxed);
                }
                if let Err(e) = sink.finish() {
                    fail(e);
                }
                let mut q = sh.q.lock().unwrap_or_else(|p| p.into_inner());
                q.busy = false;
                sh.cv.notify_all();
            })
            .map_err(|e| SinkError(format!("{name}: cannot start its thread: {e}")))?;
        Ok(SinkQueue {
            name,
            wants,
            capacity: capacity.max(1),
            shared,
            thread: Some(thread),
            queued: 0,
            dropped_scans: 0,
            dropped_poses: 0,
        })
    }

    /// Enqueues `ev` without waiting: when full, a waiting high-rate pose is evicted first,
    /// else `ev` is dropped. Returns whether `ev` was queued.
    pub fn try_send(&mut self, ev: SinkEvent) -> bool {
        let is_pose = matches!(ev, SinkEvent::ImuPose(_));
        if is_pose && !self.wants.imu_pose {
            return false;
        }
        let mut q = self.shared.q.lock().unwrap_or_else(|p| p.into_inner());
        if q.events.len() >= self.capacity {
            let oldest_pose = q.events.iter().position(|e| matches!(e, SinkEvent::ImuPose(_)));
            match oldest_pose {
                Some(i) => {
                    q.events.remove(i);
                    self.dropped_poses += 1;
                }
                None => {
                    if is_pose {
                        self.dropped_poses += 1;
                    } else {
                        self.dropped_scans += 1;
                    }
                    return false;
                }
            }
        }
        q.events.push_back(ev);
        self.queued += 1;
        drop(q);
        self.shared.cv.notify_all();
        true
    }

    /// Waits up to `timeout` until the queue is empty and the sink idle; whether it is.
    pub fn drain(&self, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        let mut q = self.shared.q.lock().unwrap_or_else(|p| p.into_inner());
        while !q.events.is_empty() || q.busy {
            let now = Instant::now();
            if now >= deadline {
                return false;
            }
            q = self.shared.cv.wait_timeout(q, deadline - now).unwrap_or_else(|p| p.into_inner()).0;
        }
        true
    }

    /// The counts so far.
    pub fn stats(&self) -> SinkStats {
        SinkStats {
            name: self.name.clone(),
            queued: self.queued,
            handled: self.shared.handled.load(Ordering::Relaxed),
            dropped_scans: self.dropped_scans,
            dropped_poses: self.dropped_poses,
            errors: self.shared.errors.load(Ordering::Relaxed),
            first_error: self.shared.first_error.lock().unwrap_or_else(|p| p.into_inner()).clone(),
            wire: self.shared.wire.lock().unwrap_or_else(|p| p.into_inner()).clone(),
        }
    }

    /// Sets the clock the scans' `arrival_ns` count from (once; later calls are ignored).
    pub fn set_origin(&self, origin: Instant) {
        let _ = self.shared.origin.set(origin);
    }

    /// Lets the sink take what is queued (up to `timeout`), finishes it and returns its counts.
    /// A sink still blocked after `timeout` is left behind (its thread ends with the process)
    /// with one warning; what it had not handled is counted as dropped.
    pub fn finish(mut self, timeout: Duration) -> SinkStats {
        let done = self.drain(timeout);
        {
            let mut q = self.shared.q.lock().unwrap_or_else(|p| p.into_inner());
            q.closed = true;
            if !done {
                for ev in q.events.drain(..) {
                    match ev {
                        SinkEvent::Scan(_) => self.dropped_scans += 1,
                        SinkEvent::ImuPose(_) => self.dropped_poses += 1,
                    }
                }
            }
        }
        self.shared.cv.notify_all();
        if let Some(t) = self.thread.take() {
            if done {
                let _ = t.join();
            } else {
                crate::diag::warn(format!(
                    "{}: still busy after {:.1} s at the end; left behind",
                    self.name,
                    timeout.as_secs_f64()
                ));
            }
        }
        self.stats()
    }
}

/// Options of the sinks as a whole.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SinkOptions {
    /// Events each sink's queue holds.
    pub queue: usize,
    /// Seconds between two maps sent to the sinks that want it (of the data's time).
    pub map_every_s: f64,
    /// How long the end of a run waits for the sinks to send what they hold, s.
    pub finish_timeout_s: f64,
}

impl Default for SinkOptions {
    fn default() -> Self {
        SinkOptions { queue: 256, map_every_s: 5.0, finish_timeout_s: 5.0 }
    }
}

/// Every sink of a run.
#[derive(Debug, Default)]
pub struct Sinks {
    queues: Vec<SinkQueue>,
    /// Options.
    pub opt: SinkOptions,
    finished: Vec<SinkStats>,
    origin: Option<Instant>,
}

impl Sinks {
    /// No sinks.
    pub fn new(opt: SinkOptions) -> Sinks {
        Sinks { queues: Vec::new(), opt, finished: Vec::new(), origin: None }
    }

    /// Adds a sink on its own thread.
    pub fn add(&mut self, sink: Box<dyn Sink>) -> Result<(), SinkError> {
        let q = SinkQueue::start(sink, self.opt.queue)?;
        if let Some(o) = self.origin {
            q.set_origin(o);
        }
        self.queues.push(q);
        Ok(())
    }

    /// Sets the live run's monotonic clock origin (the one `ScanOutput::arrival_ns` counts
    /// from) so that each sink measures its wire latency on that clock; without it none is.
    pub fn set_origin(&mut self, origin: Instant) {
        self.origin = Some(origin);
        for q in &self.queues {
            q.set_origin(origin);
        }
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.queues.is_empty()
    }

    /// What any sink wants.
    pub fn wants(&self) -> Wants {
        self.queues.iter().fold(Wants::default(), |w, q| w.or(q.wants))
    }

    /// Offers `ev` to every sink (never waits).
    pub fn send(&mut self, ev: SinkEvent) {
        if let Some((last, rest)) = self.queues.split_last_mut() {
            for q in rest {
                q.try_send(ev.clone());
            }
            last.try_send(ev);
        }
    }

    /// Waits up to `timeout` until every sink has handled what it was given (tests, the end).
    pub fn drain(&self, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        self.queues.iter().all(|q| q.drain(deadline.saturating_duration_since(Instant::now())))
    }

    /// The counts so far (finished sinks included).
    pub fn stats(&self) -> Vec<SinkStats> {
        self.finished.iter().cloned().chain(self.queues.iter().map(SinkQueue::stats)).collect()
    }

    /// Finishes every sink (each given what is left of the finish timeout) and returns the counts.
    pub fn finish(&mut self) -> Vec<SinkStats> {
        let deadline = Instant::now() + Duration::from_secs_f64(self.opt.finish_timeout_s.max(0.0));
        for q in self.queues.drain(..) {
            let left = deadline.saturating_duration_since(Instant::now());
            self.finished.push(q.finish(left));
        }
        self.finished.clone()
    }

    /// One short phrase for the status line: `ros2 0 lost, mavlink 3 lost` (empty without sinks).
    pub fn status_phrase(&self) -> String {
        sinks_phrase(&self.stats())
    }
}

/// `name N lost` for each sink, comma-separated.
pub fn sinks_phrase(stats: &[SinkStats]) -> String {
    stats
        .iter()
        .map(|s| {
            let name = s.name.split_whitespace().next().unwrap_or("");
            format!("{name} {} lost", s.lost())
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// The summary's lines on the sinks: what each got out, dropped and failed.
pub fn sinks_summary(stats: &[SinkStats]) -> Vec<String> {
    stats
        .iter()
        .map(|s| {
            let mut line = format!(
                "{}: {} events sent, {} scans and {} poses dropped (queue full), {} errors",
                s.name,
                s.handled.saturating_sub(s.errors),
                s.dropped_scans,
                s.dropped_poses,
                s.errors
            );
            if let Some(e) = &s.first_error {
                line.push_str(&format!(" (first: {e})"));
            }
            if let Some(w) = s.wire.phrase() {
                line.push_str(&format!("; pose latency from the scan's last packet: {w}"));
            }
            line
        })
        .collect()
}

#[cfg(test)]
mod tests;
