//! [`Runner`] orders the inputs (every IMU sample up to a scan's end is pushed before the scan
//! is processed), times each scan with a std clock and writes the [`Outputs`].

use std::collections::VecDeque;
use std::fmt;
use std::io;
use std::time::Instant;

use loglio_core::eskf::{Eskf, Predicted, PropagationFlags};
use loglio_core::imu::{ImuDrop, ImuPush, ImuSample};
use loglio_core::output::{ScanResult, StageTimes, Status};
use loglio_core::scan::{ScanPoint, ScanView};

use crate::error::PipelineError;
use crate::output::ScanStatus;
use crate::run::engine::{Engine, StdClock};
use crate::sink::files::{Finished, Outputs};
use crate::sink::{LiveStatus, PoseSample, ScanOutput, SinkEvent, SinkStats, Sinks};

/// A scan the host holds until the IMU covers it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OwnedScan {
    /// Absolute start, ns.
    pub start_ns: u64,
    /// The points (`t` seconds since `start_ns`).
    pub points: Vec<ScanPoint>,
}

impl OwnedScan {
    /// The scan end: the latest point time (the start when empty), as the core computes it.
    pub fn end_ns(&self) -> u64 {
        let t_max = self.points.iter().filter(|p| p.t.is_finite()).fold(0.0f32, |m, p| m.max(p.t));
        self.start_ns.saturating_add((t_max as f64 * 1e9) as u64)
    }
}

/// The host's view of a scan's status.
pub fn scan_status(s: &Status) -> ScanStatus {
    match s {
        Status::Ok => ScanStatus::Ok,
        Status::Degraded { .. } => ScanStatus::Degraded,
        Status::ImuOnly(_) => ScanStatus::ImuOnly,
        Status::Initialising(_) => ScanStatus::Initialising,
        Status::Reinitialising(_) => ScanStatus::Reinitialising,
        Status::Bridged(_) => ScanStatus::Bridged,
        Status::Lost { .. } => ScanStatus::Lost,
    }
}

/// Counts and times of a run.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunStats {
    /// Scans processed.
    pub scans: u64,
    /// Scans per status: initialising, ok, degraded, imu-only, re-initialising, bridged, lost.
    pub status: [u64; 7],
    /// IMU samples received (before the core's checks).
    pub imu_in: u64,
    /// IMU samples the core refused (out of order, duplicate, non-finite).
    pub imu_dropped: u64,
    /// IMU samples discarded because they were more than a second older than the first scan.
    pub imu_stale: u64,
    /// Scans processed before the IMU reached their end (the IMU stream lagged or ended).
    pub scans_without_imu: u64,
    /// Scans whose points exceeded the storage (the excess was cut).
    pub scans_truncated: u64,
    /// First and last LiDAR scan end, ns.
    pub lidar_span: Option<(u64, u64)>,
    /// First and last IMU time (after the offset), ns.
    pub imu_span: Option<(u64, u64)>,
    /// Sum of the per-stage times, ns.
    pub stage_sum: StageTimes,
    /// Wall time per scan in the core, ns.
    pub scan_ns: Vec<u64>,
    /// The live outputs' counts (filled at the end of the run).
    pub sinks: Vec<SinkStats>,
    /// Timing faults and IMU outliers met.
    pub faults: FaultCounts,
    /// Scans at a stand, which gave zero-velocity updates.
    pub standstill: u64,
    /// Map voxels removed because a scan saw through them (moving objects' trails).
    pub cleared_voxels: u64,
    /// Points left out of the association and the map as moving.
    pub moving_points: u64,
    /// Scans predicted without IMU (LiDAR-only, constant-velocity model).
    pub lidar_only_scans: u64,
    /// The IMU–LiDAR time offset the core estimated (on top of `time.lidar_imu_offset`).
    pub time_offset: loglio_core::time_offset::TimeOffsetEstimate,
    /// The map at the end: its use of the fixed pool and what was evicted on the way.
    pub map: MapUse,
}

/// The voxel map's use of its fixed pool at the end of a run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MapUse {
    /// Voxels in the map.
    pub voxels: usize,
    /// The pool's capacity, voxels (fixed at the start; the map never grows past it).
    pub capacity: usize,
    /// Created, evicted (far from the sensor, from the full pool), dropped, cleared.
    pub counters: loglio_core::voxel_map::MapCounters,
}

/// Timing faults and IMU outliers a run met (each also said as a `warning:`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FaultCounts {
    /// Pauses of the LiDAR longer than 0.5 s, and the longest, s.
    pub lidar_gaps: u64,
    /// The longest LiDAR gap, s.
    pub lidar_gap_max_s: f64,
    /// Pauses of the IMU longer than 0.2 s.
    pub imu_gaps: u64,
    /// The longest IMU gap, s.
    pub imu_gap_max_s: f64,
    /// IMU samples stamped far after their neighbours, dropped.
    pub imu_stamp_jumps: u64,
    /// Scans stamped far after their neighbours (not confirmed by the next), dropped.
    pub scan_stamp_jumps: u64,
    /// The core's IMU outlier guard.
    pub imu_guard: loglio_core::imu_guard::ImuGuardStats,
    /// Re-localisations in the map that moved the prediction (after LiDAR gaps, while lost).
    pub relocalisations: u32,
}

impl FaultCounts {
    /// The end-of-run warnings: one per kind met.
    pub fn warnings(&self) -> Vec<String> {
        let g = &self.imu_guard;
        let mut w = Vec::new();
        if g.beyond_full_scale > 0 {
            w.push(format!(
                "{} IMU samples beyond the sensor's full scale were dropped as outliers",
                g.beyond_full_scale
            ));
        }
        if g.spikes > 0 {
            w.push(format!("{} lone IMU spikes (outliers) were dropped", g.spikes));
        }
        if g.stamp_jumps > 0 {
            w.push(format!(
                "{} IMU samples with a stamp far after their neighbours were dropped",
                g.stamp_jumps
            ));
        }
        if self.scan_stamp_jumps > 0 {
            w.push(format!(
                "{} LiDAR scans with a stamp far after their neighbours were dropped",
                self.scan_stamp_jumps
            ));
        }
        if g.saturated > 0 {
            w.push(format!("{} IMU samples at the sensor's full scale: the IMU saturated", g.saturated));
        }
        if self.relocalisations > 0 {
            w.push(format!(
                "re-localised in the map {} times (the prediction was off after a LiDAR gap or while lost)",
                self.relocalisations
            ));
        }
        w
    }

    /// One summary phrase (empty when nothing happened).
    pub fn phrase(&self) -> String {
        let mut p = Vec::new();
        if self.lidar_gaps > 0 {
            p.push(format!("{} LiDAR gaps (longest {:.2} s)", self.lidar_gaps, self.lidar_gap_max_s));
        }
        if self.imu_gaps > 0 {
            p.push(format!("{} IMU gaps (longest {:.2} s)", self.imu_gaps, self.imu_gap_max_s));
        }
        let g = &self.imu_guard;
        let stamps = self.imu_stamp_jumps + u64::from(g.stamp_jumps);
        if stamps > 0 {
            p.push(format!("{stamps} IMU samples with wrong stamps dropped"));
        }
        if self.scan_stamp_jumps > 0 {
            p.push(format!("{} scans with wrong stamps dropped", self.scan_stamp_jumps));
        }
        if g.beyond_full_scale + g.spikes > 0 {
            p.push(format!("{} IMU outliers dropped", g.beyond_full_scale + g.spikes));
        }
        if g.saturated > 0 {
            p.push(format!("{} saturated IMU samples", g.saturated));
        }
        if self.relocalisations > 0 {
            p.push(format!("{} re-localisations", self.relocalisations));
        }
        p.join(", ")
    }
}

/// One item stamped far after the latest, held until the next item confirms the stamp (it
/// comes later still: a real pause) or refutes it (it comes earlier: a wrong stamp), so that
/// one bad stamp neither stalls what follows nor is believed.
struct Hold<T> {
    item: Option<(u64, T)>,
}

impl<T> Default for Hold<T> {
    fn default() -> Self {
        Self { item: None }
    }
}

impl<T> Hold<T> {
    /// The held item against the next stamp `next_ns`: `Ok` to take it, `Err` a wrong stamp.
    fn settle(&mut self, next_ns: u64) -> Option<Result<T, T>> {
        self.item.take().map(|(t, item)| if next_ns < t { Err(item) } else { Ok(item) })
    }

    /// Holds `item` (stamped `t_ns`) if it is more than `limit_ns` after `latest_ns`; else
    /// gives it back to be taken now.
    fn offer(&mut self, latest_ns: Option<u64>, limit_ns: u64, t_ns: u64, item: T) -> Option<T> {
        if latest_ns.is_some_and(|l| t_ns > l.saturating_add(limit_ns)) {
            self.item = Some((t_ns, item));
            None
        } else {
            Some(item)
        }
    }

    /// What is held, whatever comes next (the end of the run).
    fn take(&mut self) -> Option<T> {
        self.item.take().map(|(_, item)| item)
    }
}

/// An IMU sample this far after the last one is held until the next confirms it, ns.
pub const IMU_FORWARD_NS: u64 = 500_000_000;
/// An IMU pause longer than this is a gap (said and counted), ns.
pub const IMU_GAP_NS: u64 = 200_000_000;
/// A LiDAR pause longer than this is a gap (said and counted), ns.
pub const LIDAR_GAP_NS: u64 = 500_000_000;
/// With no scan waiting, IMU samples older than the newest by this are integrated without one.
pub const PROPAGATE_LAG_NS: u64 = 1_000_000_000;

impl RunStats {
    /// Mean time per scan, seconds.
    pub fn mean_scan_s(&self) -> f64 {
        if self.scan_ns.is_empty() {
            return 0.0;
        }
        self.scan_ns.iter().sum::<u64>() as f64 * 1e-9 / self.scan_ns.len() as f64
    }

    /// Median time per scan, seconds.
    pub fn median_scan_s(&self) -> f64 {
        let mut v = self.scan_ns.clone();
        if v.is_empty() {
            return 0.0;
        }
        v.sort_unstable();
        v[v.len() / 2] as f64 * 1e-9
    }

    /// Checks that the streams overlapped: a one-line error otherwise.
    pub fn check_overlap(&self) -> Result<(), PipelineError> {
        match (self.lidar_span, self.imu_span) {
            (None, _) => Err(PipelineError("no LiDAR scans in the input".into())),
            (Some(_), _) if self.lidar_only_scans > 0 => Ok(()),
            (Some(_), None) => Err(PipelineError("no IMU samples in the input".into())),
            (Some(l), Some(i)) => {
                crate::input::time_align::check_overlap(l, i).map_err(|e| PipelineError(e.to_string()))?;
                Ok(())
            }
        }
    }
}

fn widen(span: &mut Option<(u64, u64)>, t: u64) {
    *span = Some(span.map_or((t, t), |(a, b)| (a.min(t), b.max(t))));
}

/// A callback after each processed scan: its result, the counts so far and the `arrival` the
/// scan was given to [`Runner::scan`] with (live: when its last packet was received).
pub type ScanCallback<'e> = Box<dyn FnMut(&ScanResult, &RunStats, u64) + 'e>;

/// Most scans held while waiting for the IMU before one is processed without it.
pub const MAX_PENDING_SCANS: usize = 8;

/// Feeds the odometry in the right order and writes the outputs.
///
/// IMU samples and scans may arrive interleaved in any order the sources produce; a scan is
/// processed once an IMU sample at or after its end has arrived (every sample up to its end is
/// pushed first), when [`MAX_PENDING_SCANS`] are waiting, when the caller says the wait is over
/// ([`Runner::process_ready`] with `force`), or at [`Runner::finish`].
pub struct Runner<'e> {
    engine: &'e mut dyn Engine,
    clock: StdClock,
    imu_offset_ns: i64,
    imu: VecDeque<ImuSample>,
    last_imu_ns: Option<u64>,
    /// Waiting scans: each with its arrival and its end (found once: a fold over the points).
    scans: VecDeque<(OwnedScan, u64, u64)>,
    spare: Vec<Vec<ScanPoint>>,
    /// The outputs.
    pub outputs: Outputs,
    /// Counts and times.
    pub stats: RunStats,
    /// Called after each processed scan with its result.
    pub on_scan: Option<ScanCallback<'e>>,
    /// Whether a scan's waiting map insertion ([`Engine::flush_map`]) runs as soon as no scan
    /// waits (the default: a live run inserts between scans, after the pose is out). Off, it
    /// runs inside the next scan's processing, where `loglio bench` times it.
    pub flush_map_when_idle: bool,
    /// The live outputs (ROS 2, MAVLink, Foxglove, an embedding program's), each behind its
    /// own bounded queue: offered every scan's result and, between scans, the IMU-propagated
    /// pose; they never hold the odometry up.
    pub sinks: Sinks,
    /// The latest scan's pose (the status line's).
    pub latest: Option<PoseSample>,
    /// A copy of the filter after the latest scan, propagated with each later IMU sample for
    /// the high-rate pose.
    predictor: Option<Eskf>,
    map_sent_ns: Option<u64>,
    origin: Instant,
    /// An IMU sample stamped far after the last one, held until the next confirms it.
    held_far: Hold<ImuSample>,
    /// A scan far after the latest, held until the next confirms it.
    held_scan: Hold<(OwnedScan, u64)>,
    /// The latest scan start (LiDAR gaps).
    last_scan_start_ns: Option<u64>,
    /// No IMU (LiDAR-only): every scan is processed as it comes.
    lidar_only: bool,
}

impl fmt::Debug for Runner<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Runner").field("stats", &self.stats).finish_non_exhaustive()
    }
}

impl<'e> Runner<'e> {
    /// A runner over `engine`; IMU stamps are moved onto the LiDAR clock by `imu_offset_s`
    /// (`time.lidar_imu_offset`).
    pub fn new(engine: &'e mut dyn Engine, outputs: Outputs, imu_offset_s: f64) -> Self {
        Runner {
            engine,
            clock: StdClock::new(),
            imu_offset_ns: (imu_offset_s * 1e9).round() as i64,
            imu: VecDeque::new(),
            last_imu_ns: None,
            scans: VecDeque::new(),
            spare: Vec::new(),
            outputs,
            stats: RunStats::default(),
            on_scan: None,
            flush_map_when_idle: true,
            sinks: Sinks::default(),
            latest: None,
            predictor: None,
            map_sent_ns: None,
            origin: Instant::now(),
            held_far: Hold::default(),
            held_scan: Hold::default(),
            last_scan_start_ns: None,
            lidar_only: false,
        }
    }

    /// LiDAR-only (the core's constant-velocity model, `imu.source = "none"`): scans wait for
    /// no IMU.
    pub fn set_lidar_only(&mut self, on: bool) {
        self.lidar_only = on;
    }

    /// Times the odometry by this thread's CPU time ([`StdClock::thread_cpu`]).
    pub fn use_thread_cpu_clock(&mut self) {
        self.clock = StdClock::thread_cpu();
    }

    /// Sets the monotonic clock origin of the `arrival` times given to [`Self::scan`] (a live
    /// source's start), so that the sinks' latency (`ready_ns - arrival_ns`) is on one clock.
    pub fn set_origin(&mut self, origin: Instant) {
        self.origin = origin;
    }

    fn now_ns(&self) -> u64 {
        self.origin.elapsed().as_nanos().min(u128::from(u64::MAX)) as u64
    }

    /// Propagates the live predictor with one IMU sample and offers the pose to the sinks.
    fn propagate_live(&mut self, s: &ImuSample) {
        let Some(f) = &mut self.predictor else { return };
        if s.t_ns <= f.time_ns() {
            return;
        }
        if let Predicted::Jump { .. } = f.predict(s) {
            // A jump re-seeds the filter on the next scan: no pose until then.
            self.predictor = None;
            return;
        }
        let Some(latest) = &self.latest else { return };
        let bg = f.state().bg;
        let omega = [f64::from(s.gyro[0]) - bg.x, f64::from(s.gyro[1]) - bg.y, f64::from(s.gyro[2]) - bg.z];
        let pose = PoseSample::from_filter(f, latest.status, latest.resets, omega);
        self.sinks.send(SinkEvent::ImuPose(pose));
    }

    /// Offers a processed scan to the sinks and restarts the high-rate predictor from it.
    fn publish(&mut self, index: u64, res: &ScanResult, arrival: u64) {
        let status = LiveStatus::of(&res.status);
        let resets = self.engine.resets();
        let filter = self.engine.filter();
        let pose = match (&filter, status) {
            (Some(f), s) if s != LiveStatus::Initialising => {
                let omega = f.held_sample().map_or([0.0; 3], |h| {
                    let bg = f.state().bg;
                    [f64::from(h.gyro[0]) - bg.x, f64::from(h.gyro[1]) - bg.y, f64::from(h.gyro[2]) - bg.z]
                });
                PoseSample::from_filter(f, status, resets, omega)
            }
            _ => PoseSample::placeholder(res.pose.t_ns, status, resets),
        };
        self.latest = Some(pose);
        if self.sinks.is_empty() {
            return;
        }
        let wants = self.sinks.wants();
        let cloud = (wants.cloud && status.is_tracking()).then(|| {
            let mut v = Vec::new();
            self.engine.scan_cloud(&mut v);
            std::sync::Arc::new(v)
        });
        let every_ns = (self.sinks.opt.map_every_s.max(0.0) * 1e9) as u64;
        let map_due = wants.map
            && status.is_tracking()
            && self.map_sent_ns.is_none_or(|t| res.pose.t_ns.saturating_sub(t) >= every_ns);
        let map = map_due.then(|| {
            self.map_sent_ns = Some(res.pose.t_ns);
            let mut v = Vec::new();
            self.engine.flush_map();
            self.engine.map_points(&mut v);
            std::sync::Arc::new(v)
        });
        let out = ScanOutput {
            index,
            scan_start_ns: res.scan_start_ns,
            pose,
            process_ms: res.times.total_ns as f64 * 1e-6,
            map_voxels: self.engine.map_voxels(),
            points: res.points,
            cloud,
            map,
            arrival_ns: arrival,
            ready_ns: self.now_ns(),
        };
        self.sinks.send(SinkEvent::Scan(std::sync::Arc::new(out)));
        self.predictor = if wants.imu_pose && status.is_tracking() { filter } else { None };
        if let Some(f) = &mut self.predictor {
            // The samples already received beyond the scan's end.
            for s in self.imu.iter() {
                if s.t_ns > f.time_ns() && matches!(f.predict(s), Predicted::Jump { .. }) {
                    self.predictor = None;
                    break;
                }
            }
        }
    }

    /// The engine.
    pub fn engine(&self) -> &dyn Engine {
        &*self.engine
    }

    /// A cleared point buffer to fill for [`Self::scan`] (recycled from processed scans).
    pub fn buffer(&mut self) -> Vec<ScanPoint> {
        let mut v = self.spare.pop().unwrap_or_default();
        v.clear();
        v
    }

    /// Takes one IMU sample (sensor clock; the offset is applied here). A sample stamped more
    /// than [`IMU_FORWARD_NS`] after the last one is held until the next sample confirms it (a
    /// real gap) or comes before it (a wrong stamp: dropped and counted), so that one bad stamp
    /// neither stalls the samples behind it nor makes every scan look covered.
    pub fn imu(&mut self, mut s: ImuSample) -> Result<(), PipelineError> {
        s.t_ns = s.t_ns.saturating_add_signed(self.imu_offset_ns);
        self.stats.imu_in += 1;
        match self.held_far.settle(s.t_ns) {
            Some(Ok(h)) => self.accept_imu(h)?,
            Some(Err(h)) => {
                self.stats.faults.imu_stamp_jumps += 1;
                if self.stats.faults.imu_stamp_jumps <= 3 {
                    crate::diag::warn(format!(
                        "an IMU sample stamped {:.3} s after its neighbours was dropped (a wrong stamp; counted)",
                        (h.t_ns - self.last_imu_ns.unwrap_or(h.t_ns)) as f64 * 1e-9
                    ));
                }
            }
            None => {}
        }
        match self.held_far.offer(self.last_imu_ns, IMU_FORWARD_NS, s.t_ns, s) {
            Some(s) => self.accept_imu(s),
            None => Ok(()),
        }
    }

    fn accept_imu(&mut self, s: ImuSample) -> Result<(), PipelineError> {
        if let Some(last) = self.last_imu_ns
            && s.t_ns > last
        {
            let gap_ns = s.t_ns - last;
            if gap_ns > IMU_GAP_NS {
                let f = &mut self.stats.faults;
                f.imu_gaps += 1;
                f.imu_gap_max_s = f.imu_gap_max_s.max(gap_ns as f64 * 1e-9);
                if f.imu_gaps <= 3 {
                    crate::diag::warn(format!(
                        "IMU gap of {:.2} s: the scans carried the pose at constant velocity (bridged)",
                        gap_ns as f64 * 1e-9
                    ));
                }
            }
        }
        widen(&mut self.stats.imu_span, s.t_ns);
        self.last_imu_ns = Some(self.last_imu_ns.map_or(s.t_ns, |t| t.max(s.t_ns)));
        self.imu.push_back(s);
        if self.predictor.is_some() {
            self.propagate_live(&s);
        }
        // No scan waiting and more than a second of samples: the IMU carries the state
        // through the LiDAR's silence (samples older than any scan still to come).
        if self.scans.is_empty()
            && let (Some(first), Some(newest)) = (self.imu.front(), self.last_imu_ns)
            && newest.saturating_sub(first.t_ns) > 2 * PROPAGATE_LAG_NS
        {
            let until = newest - PROPAGATE_LAG_NS;
            while let Some(s) = self.imu.front() {
                if s.t_ns > until {
                    break;
                }
                let s = *s;
                self.imu.pop_front();
                if !pushed_ok(self.engine.push_imu(s)) {
                    self.stats.imu_dropped += 1;
                }
            }
            self.engine.propagate_imu(until);
        }
        self.process_ready(false, None)
    }

    /// Takes one scan. A scan starting more than [`LIDAR_GAP_NS`] after the latest start is
    /// held until the next scan confirms it (a real pause: it starts later still) or comes
    /// before it (a wrong stamp, e.g. one cloud's `header.stamp` a minute late: dropped and
    /// counted), as IMU samples are.
    pub fn scan(&mut self, scan: OwnedScan, arrival: u64) -> Result<(), PipelineError> {
        match self.held_scan.settle(scan.start_ns) {
            Some(Ok((h, ha))) => self.accept_scan(h, ha)?,
            Some(Err((h, _))) => {
                let f = &mut self.stats.faults;
                f.scan_stamp_jumps += 1;
                if f.scan_stamp_jumps <= 3 {
                    crate::diag::warn(format!(
                        "a LiDAR scan stamped {:.3} s after the scans around it was dropped (a wrong stamp; counted)",
                        h.start_ns.saturating_sub(self.last_scan_start_ns.unwrap_or(h.start_ns)) as f64
                            * 1e-9
                    ));
                }
            }
            None => {}
        }
        let start = scan.start_ns;
        match self.held_scan.offer(self.last_scan_start_ns, LIDAR_GAP_NS, start, (scan, arrival)) {
            Some((scan, arrival)) => self.accept_scan(scan, arrival),
            None => Ok(()),
        }
    }

    fn accept_scan(&mut self, scan: OwnedScan, arrival: u64) -> Result<(), PipelineError> {
        // A point time past a second into the scan is damage (a flipped bit), not a pause.
        let scan_end = scan.end_ns();
        let end = scan_end.min(scan.start_ns.saturating_add(1_000_000_000));
        // Gaps from start to start: the starts are packet stamps the stream checked.
        if let Some(last) = self.last_scan_start_ns
            && scan.start_ns > last
        {
            let gap_ns = scan.start_ns - last;
            if gap_ns > LIDAR_GAP_NS {
                let f = &mut self.stats.faults;
                f.lidar_gaps += 1;
                f.lidar_gap_max_s = f.lidar_gap_max_s.max(gap_ns as f64 * 1e-9);
                if f.lidar_gaps <= 3 {
                    crate::diag::warn(format!(
                        "LiDAR gap of {:.2} s: the IMU carried the pose (bridged)",
                        gap_ns as f64 * 1e-9
                    ));
                }
            }
        }
        self.last_scan_start_ns =
            Some(self.last_scan_start_ns.map_or(scan.start_ns, |t| t.max(scan.start_ns)));
        widen(&mut self.stats.lidar_span, end);
        self.scans.push_back((scan, arrival, scan_end));
        self.process_ready(false, None)
    }

    /// Scans waiting for the IMU.
    pub fn pending(&self) -> usize {
        self.scans.len()
    }

    /// Processes the waiting scans the IMU covers; with `force`, every waiting scan; with
    /// `older_than`, those that arrived before it (a caller's wall clock: the live wait bound).
    pub fn process_ready(&mut self, force: bool, older_than: Option<u64>) -> Result<(), PipelineError> {
        let mut processed = false;
        while let Some(&(_, arrival, scan_end)) = self.scans.front() {
            let end = self.imu_time(scan_end);
            let covered = self.lidar_only || self.last_imu_ns.is_some_and(|t| t >= end);
            let waited = older_than.is_some_and(|t| arrival <= t);
            if !(covered || force || waited || self.scans.len() > MAX_PENDING_SCANS) {
                break;
            }
            let Some((scan, arrival, scan_end)) = self.scans.pop_front() else { break };
            if !covered {
                self.stats.scans_without_imu += 1;
            }
            self.process(scan, arrival, scan_end)?;
            processed = true;
        }
        // The poses are out; with no scan waiting, the last one's map insertion (where it waits
        // for the next scan) runs now, in the time before the next scan.
        if processed && self.scans.is_empty() && self.flush_map_when_idle {
            self.engine.flush_map();
        }
        Ok(())
    }

    /// A LiDAR time on the IMU stamps' clock as they arrive here: the core moves them on by the
    /// time offset it estimated ([`loglio_core::time_offset`]), so a scan's end is covered by
    /// samples stamped that much later (or earlier).
    fn imu_time(&self, lidar_ns: u64) -> u64 {
        lidar_ns.saturating_add_signed(-self.engine.time_offset().applied_ns)
    }

    fn process(&mut self, scan: OwnedScan, arrival: u64, scan_end: u64) -> Result<(), PipelineError> {
        let end = self.imu_time(scan_end);
        let stale_before = scan.start_ns.saturating_sub(1_000_000_000);
        // After the first scan, samples that old are the IMU through a LiDAR pause: integrated
        // without a scan (dropping them made the filter step over the pause: a re-initialising
        // scan after gaps of 1-2 s). Before it, they are the IMU's head start: dropped.
        let tracking = self.stats.status.iter().any(|&n| n > 0);
        while let Some(s) = self.imu.front() {
            if s.t_ns > end {
                break;
            }
            let s = *s;
            self.imu.pop_front();
            if s.t_ns < stale_before && !tracking {
                self.stats.imu_stale += 1;
                continue;
            }
            if !pushed_ok(self.engine.push_imu(s)) {
                self.stats.imu_dropped += 1;
            }
            if s.t_ns < stale_before {
                self.engine.propagate_imu(s.t_ns);
            }
        }
        if scan.points.len() > self.engine.max_points() {
            self.stats.scans_truncated += 1;
        }
        let res = self
            .engine
            .process_scan(ScanView { start_ns: scan.start_ns, points: &scan.points }, &mut self.clock);
        let st = &mut self.stats;
        st.status[match scan_status(&res.status) {
            ScanStatus::Initialising => 0,
            ScanStatus::Ok => 1,
            ScanStatus::Degraded => 2,
            ScanStatus::ImuOnly => 3,
            ScanStatus::Reinitialising => 4,
            ScanStatus::Bridged => 5,
            ScanStatus::Lost => 6,
        }] += 1;
        if res.propagation.has(loglio_core::eskf::PropagationFlags::STILL) {
            st.standstill += 1;
        }
        let t = &res.times;
        let s = &mut st.stage_sum;
        s.normals_ns += t.normals_ns;
        s.undistort_ns += t.undistort_ns;
        s.downsample_ns += t.downsample_ns;
        s.association_ns += t.association_ns;
        s.update_ns += t.update_ns;
        s.map_ns += t.map_ns;
        s.total_ns += t.total_ns;
        st.scan_ns.push(t.total_ns);
        if res.propagation.has(PropagationFlags::LIDAR_ONLY) {
            st.lidar_only_scans += 1;
        }
        let index = st.scans;
        st.scans += 1;
        self.outputs.record(index, &res, t.total_ns as f64 * 1e-6, self.engine.map_voxels())?;
        self.publish(index, &res, arrival);
        if let Some(cb) = &mut self.on_scan {
            cb(&res, &self.stats, arrival);
        }
        if self.spare.len() < 4 {
            self.spare.push(scan.points);
        }
        Ok(())
    }

    /// Processes what is left and writes the final outputs. Fails when the streams never
    /// overlapped (no IMU, no scans, or disjoint times).
    pub fn finish(mut self) -> Result<(RunStats, Finished), PipelineError> {
        if let Some(h) = self.held_far.take() {
            self.accept_imu(h)?;
        }
        if let Some((h, ha)) = self.held_scan.take() {
            self.accept_scan(h, ha)?;
        }
        self.process_ready(true, None)?;
        self.engine.flush_map();
        self.stats.faults.imu_guard = self.engine.imu_guard_stats();
        self.stats.faults.relocalisations = self.engine.relocalisations();
        (self.stats.cleared_voxels, self.stats.moving_points) = self.engine.free_space();
        self.stats.time_offset = self.engine.time_offset();
        let (counters, capacity) = self.engine.map_counters();
        self.stats.map = MapUse { voxels: self.engine.map_voxels(), capacity, counters };
        for w in self.stats.faults.warnings() {
            crate::diag::warn(w);
        }
        self.stats.sinks = self.sinks.finish();
        self.stats.check_overlap()?;
        let fin = self.outputs.finish(&*self.engine)?;
        Ok((self.stats, fin))
    }

    /// Flushes the streaming outputs (Ctrl-C).
    pub fn flush(&mut self) -> io::Result<()> {
        self.outputs.flush()
    }
}

/// Whether a pushed sample went in (or waits in the guard): a sample that the estimated time
/// offset put before those queued is no fault either.
fn pushed_ok(p: ImuPush) -> bool {
    matches!(p, ImuPush::Accepted | ImuPush::Held | ImuPush::Dropped(ImuDrop::Realigned))
}

/// A summary line of the status counts.
pub fn status_summary(st: &RunStats) -> String {
    let names = ["initialising", "ok", "degraded", "imu-only", "re-initialising", "bridged", "lost"];
    let mut parts: Vec<String> =
        names.iter().zip(st.status).filter(|(_, n)| *n > 0).map(|(name, n)| format!("{n} {name}")).collect();
    if st.standstill > 0 {
        parts.push(format!("{} standing still", st.standstill));
    }
    if st.moving_points > 0 || st.cleared_voxels > 0 {
        parts.push(format!(
            "{} moving points left out, {} map voxels seen through",
            st.moving_points, st.cleared_voxels
        ));
    }
    parts.join(", ")
}

/// What the time-offset estimation found and applies (a line), or nothing before its first
/// window.
pub fn time_offset_line(t: &loglio_core::time_offset::TimeOffsetEstimate) -> String {
    match t.estimate_s {
        Some(e) => {
            let mut s = format!(
                "IMU–LiDAR time offset: the scans' warp says {:+.2} ± {:.2} ms ({} scans); {:+.2} ms applied to the IMU stamps",
                e * 1e3,
                t.std_s * 1e3,
                t.scans,
                t.applied_s * 1e3
            );
            if t.realigned > 0 {
                s.push_str(&format!(
                    " ({} IMU samples dropped: a change put them before samples already queued)",
                    t.realigned
                ));
            }
            s.push('\n');
            s
        }
        None => String::new(),
    }
}

/// The map's use of its fixed pool (a line): voxels held of the capacity, and what was
/// evicted to stay inside it. Nothing before the map holds a voxel.
pub fn map_line(m: &MapUse) -> String {
    let c = &m.counters;
    if c.created == 0 || m.capacity == 0 {
        return String::new();
    }
    let mut s = format!(
        "map: {} voxels of a fixed pool of {} ({:.0} %); {} created, {} evicted far from the sensor, {} evicted from the full pool",
        m.voxels,
        m.capacity,
        100.0 * m.voxels as f64 / m.capacity as f64,
        c.created,
        c.evicted_far,
        c.evicted_full
    );
    if c.dropped_full > 0 {
        s.push_str(&format!(", {} points dropped with the pool full", c.dropped_full));
    }
    s.push('\n');
    s
}

/// Whether the time per scan grew over a long run (a line): the mean of the first and the last
/// quarter of the scans. Nothing under 400 scans.
pub fn scan_time_trend_line(st: &RunStats) -> String {
    let n = st.scan_ns.len();
    if n < 400 {
        return String::new();
    }
    let q = n / 4;
    let mean_ms = |v: &[u64]| v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64 * 1e-6;
    format!(
        "time per scan over the run: {:.1} ms (mean of the first quarter), {:.1} ms (last quarter)\n",
        mean_ms(&st.scan_ns[..q]),
        mean_ms(&st.scan_ns[n - q..])
    )
}

/// "LiDAR-only (no IMU): constant-velocity model" and a newline when the run had no IMU,
/// else nothing.
pub fn lidar_only_line(st: &RunStats) -> String {
    if st.lidar_only_scans > 0 { format!("{LIDAR_ONLY_MODEL}\n") } else { String::new() }
}

/// How the summaries and the live status name the LiDAR-only mode.
pub const LIDAR_ONLY_MODEL: &str = "LiDAR-only (no IMU): constant-velocity model";

/// The summary of a run: scans, timing, margin, ATE and files.
pub fn summary(stats: &RunStats, fin: &Finished, scan_period_s: f64, wall_s: f64) -> String {
    let mean = stats.mean_scan_s();
    let mut s = lidar_only_line(stats);
    s.push_str(&format!("{} scans ({}), {} IMU samples", stats.scans, status_summary(stats), stats.imu_in));
    if stats.imu_dropped + stats.imu_stale > 0 {
        s.push_str(&format!(" ({} dropped, {} older than their scan)", stats.imu_dropped, stats.imu_stale));
    }
    if stats.scans_without_imu > 0 {
        s.push_str(&format!("; {} scans without IMU up to their end", stats.scans_without_imu));
    }
    let faults = stats.faults.phrase();
    if !faults.is_empty() {
        s.push_str(&format!("; faults: {faults}"));
    }
    s.push('\n');
    s.push_str(&format!(
        "odometry: {:.1} ms per scan (mean), {:.1} ms (median); real-time margin {:.1}x (scan period {:.0} ms / mean)\n",
        mean * 1e3,
        stats.median_scan_s() * 1e3,
        if mean > 0.0 { scan_period_s / mean } else { f64::INFINITY },
        scan_period_s * 1e3
    ));
    s.push_str(&scan_time_trend_line(stats));
    s.push_str(&map_line(&stats.map));
    s.push_str(&time_offset_line(&stats.time_offset));
    if let Some(e) = &fin.eval {
        s.push_str(&format!(
            "ATE against ground truth (SE(3)-aligned, {} poses): rmse {:.3} m, max {:.3} m; rotation rmse {:.2} deg\n",
            e.matched, e.ape_trans.rmse, e.ape_trans.max, e.ape_rot_deg.rmse
        ));
    }
    s.push_str(&format!("wall time {wall_s:.1} s\n"));
    for line in crate::sink::sinks_summary(&stats.sinks) {
        s.push_str(&format!("live output {line}\n"));
    }
    if !fin.files.is_empty() {
        s.push_str("wrote:");
        for f in &fin.files {
            s.push_str(&format!(" {}", f.display()));
        }
        s.push('\n');
    }
    s
}
