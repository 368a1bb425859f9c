//! The host side of the odometry: from the TOML [`Config`] to a running core [`Odometry`], fed
//! with time-ordered IMU samples and scans, writing every output.
//!
//! - [`odometry_config`] maps the host configuration onto the core's [`OdometryConfig`] (the
//!   table in `config.rs`'s module docs).
//! - [`with_engine`] allocates the core's storage once, on the heap, sized for the sensor, and
//!   lends an [`Engine`] (the odometry behind a trait object) to a closure.
//! - [`Runner`] orders the inputs (every IMU sample up to a scan's end is pushed before the scan
//!   is processed), times each scan with a std clock and writes the [`Outputs`].
//!
//! # Storage
//!
//! The core's [`OdometryStorage`] is generic over its capacities, so the host compiles a few
//! size classes and picks the smallest that fits (see [`StorageClass`]): up to 32 rows and the
//! pixels of 32 x 2048 (so 32 x 2170 for an HDL-32E at 10 Hz takes the next class, 16 x 3600
//! does not) and 131,072 points per scan, or the pixels of 128 x 2048 and 524,288 points
//! (dual-return OS1-128); a voxel pool of 2^18 voxels (52 MiB with its index) or, when
//! `mapping.map_capacity` asks for more, 2^20 (218 MiB). The storage is tens to hundreds of
//! MiB, far beyond a thread's stack, so it is never built on the main thread's stack: a
//! short-lived thread whose stack is sized to hold the value several times over runs
//! `Box::new(OdometryStorage::new())` (see [`boxed_storage`]). This needs no `unsafe`: the
//! storage is *not* all-zero bytes (the ring table's default settings and an `Option<u64>` in
//! the IMU queue), so a zeroed allocation (`Box::new_zeroed`, `alloc_zeroed`) would not be
//! sound without relying on unspecified layouts, and a `static` would put the non-zero value in
//! `.data`, i.e. in the binary. Every page is written once at start-up, so the
//! memory is committed before the first scan and nothing is allocated or faulted in later by the
//! core.

use std::collections::VecDeque;
use std::fmt;
use std::io;
use std::path::{Path, PathBuf};
use std::time::Instant;

use loglio_core::association::AssociationConfig;
use loglio_core::downsample::DownsampleConfig;
use loglio_core::eskf::{Eskf, EskfConfig, Predicted};
use loglio_core::imu::{ImuInitConfig, ImuNoise, ImuPush, ImuSample};
use loglio_core::odometry::{
    AssociationMode as CoreMode, Clock, Odometry, OdometryConfig, OdometryError, OdometryStorage,
};
use loglio_core::output::{ScanResult, StageTimes, Status};
use loglio_core::range_image::{MAX_COLS, MAX_ROWS, RangeImageLayout};
use loglio_core::ring_fals::storage_pixels;
use loglio_core::scan::{ScanPoint, ScanView};
use loglio_core::voxel_map::KnnReach;
use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::config::{AssociationMode, Config, ConfigError, KnnSearch, SensorFamily};
use crate::eval::{self, EvalOptions, EvalReport, Trajectory};
use crate::output::{self, MapPoint, PcdEncoding, ScanCsvWriter, ScanRecord, ScanStatus, TumWriter};
use crate::sink::{LiveStatus, PoseSample, ScanOutput, SinkEvent, SinkStats, Sinks};

/// A pipeline error: one line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PipelineError(pub String);

impl fmt::Display for PipelineError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for PipelineError {}

impl From<ConfigError> for PipelineError {
    fn from(e: ConfigError) -> Self {
        PipelineError(e.0)
    }
}

impl From<io::Error> for PipelineError {
    fn from(e: io::Error) -> Self {
        PipelineError(e.to_string())
    }
}

/// The host's clock for the core's per-stage times: monotonic nanoseconds since its creation,
/// or the calling thread's CPU time (see [`StdClock::thread_cpu`]).
#[derive(Clone, Copy, Debug)]
pub struct StdClock {
    origin: Instant,
    thread_cpu: bool,
}

impl StdClock {
    /// A wall clock starting now.
    pub fn new() -> Self {
        Self { origin: Instant::now(), thread_cpu: false }
    }

    /// The CPU time of the thread that reads it: the odometry's own time per scan even when
    /// other busy threads (the simulator's) share the cores, where the wall clock would count
    /// their turns too.
    pub fn thread_cpu() -> Self {
        Self { origin: Instant::now(), thread_cpu: true }
    }
}

impl Default for StdClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for StdClock {
    fn now_ns(&mut self) -> u64 {
        if self.thread_cpu {
            let t = rustix::time::clock_gettime(rustix::time::ClockId::ThreadCPUTime);
            return (t.tv_sec as u64).saturating_mul(1_000_000_000).saturating_add(t.tv_nsec as u64);
        }
        self.origin.elapsed().as_nanos() as u64
    }
}

/// The core association mode of a configuration's `mapping.association`.
pub fn core_mode(m: AssociationMode) -> CoreMode {
    match m {
        AssociationMode::Full => CoreMode::Full,
        AssociationMode::PlaneOnly => CoreMode::PlaneOnly,
        AssociationMode::Plain => CoreMode::Plain,
    }
}

/// The sensor's range-image layout for a configuration: the Velodyne calibration file or the
/// Ouster metadata when the configuration names one, the preset's nominal beams otherwise.
pub fn config_layout(cfg: &Config) -> Result<RangeImageLayout, PipelineError> {
    let cols = cfg.sensor.columns as usize;
    if let Some(path) = &cfg.sensor.calibration {
        let calib = crate::input::velodyne_calib::load(path).map_err(|e| PipelineError(e.to_string()))?;
        return calib
            .layout(cols)
            .map_err(|e| PipelineError(format!("velodyne calibration {}: layout: {e:?}", path.display())));
    }
    if let Some(path) = &cfg.sensor.ouster_metadata {
        let meta = crate::input::ouster_meta::load(path).map_err(|e| PipelineError(e.to_string()))?;
        return ouster_layout(&meta.intrinsics);
    }
    Ok(cfg.nominal_layout()?)
}

/// The range-image layout the core's Ouster decoder produces for these intrinsics.
pub fn ouster_layout(
    intr: &loglio_core::sensor::ouster::OusterIntrinsics,
) -> Result<RangeImageLayout, PipelineError> {
    let dec = loglio_core::sensor::ouster::Decoder::new(intr)
        .map_err(|e| PipelineError(format!("ouster metadata: {e}")))?;
    Ok(dec.layout().clone())
}

/// The core configuration of a host configuration with the sensor's `layout`.
pub fn odometry_config(cfg: &Config, layout: RangeImageLayout) -> Result<OdometryConfig, PipelineError> {
    cfg.validate()?;
    let ouster = cfg.preset.family() == SensorFamily::Ouster;
    // The core's preset of the sensor family (association, filter and map settings the
    // configuration does not expose), then every value the configuration sets.
    let base = if ouster { OdometryConfig::os1_16(layout) } else { OdometryConfig::vlp32c(layout) };
    let mut map = base.map;
    map.voxel_size = cfg.mapping.voxel_size as f32;
    let eskf = EskfConfig {
        noise: ImuNoise {
            gyro: cfg.imu.gyro_noise,
            acc: cfg.imu.acc_noise,
            gyro_bias_walk: cfg.imu.gyro_bias_walk,
            acc_bias_walk: cfg.imu.acc_bias_walk,
        },
        max_iterations: cfg.filter.max_iterations as usize,
        ..base.eskf
    };
    let init = ImuInitConfig { gravity: cfg.imu.gravity, ..base.init };
    let [w, x, y, z] = cfg.extrinsics.quaternion_wxyz();
    let t = cfg.extrinsics.translation();
    Ok(OdometryConfig {
        mode: core_mode(cfg.mapping.association),
        downsample: DownsampleConfig { voxel: cfg.mapping.scan_voxel_size as f32, ..base.downsample },
        map,
        eskf,
        init,
        ext_rot: UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        ext_pos: Vector3::new(t[0], t[1], t[2]),
        blind: cfg.sensor.blind as f32,
        max_range: cfg.sensor.max_range as f32,
        association: AssociationConfig {
            max_points: u32::try_from(cfg.mapping.max_points).unwrap_or(u32::MAX),
            knn_reach: match cfg.mapping.knn_search {
                KnnSearch::Exact => KnnReach::Neighbourhood,
                KnnSearch::Block => KnnReach::Block,
            },
            ..base.association
        },
        ..base
    })
}

/// The odometry behind a trait object, whatever its storage size class.
pub trait Engine {
    /// Queues one IMU sample (see [`Odometry::push_imu`]).
    fn push_imu(&mut self, s: ImuSample) -> ImuPush;
    /// Processes one scan, timing the stages with `clock`.
    fn process_scan(&mut self, scan: ScanView<'_>, clock: &mut StdClock) -> ScanResult;
    /// Voxels in the map.
    fn map_voxels(&self) -> usize;
    /// Appends the map's points (world frame) with their normals where known.
    fn map_points(&self, out: &mut Vec<MapPoint>);
    /// Most points a scan may hold (more are cut off by the core).
    fn max_points(&self) -> usize;
    /// Bytes of the storage behind it.
    fn storage_bytes(&self) -> usize;
    /// The filter after the last scan (None before the initialisation): the live outputs
    /// propagate a copy of it with the IMU samples between scans.
    fn filter(&self) -> Option<loglio_core::eskf::Eskf>;
    /// Appends the last scan's points (undistorted, downsampled) in the world frame.
    fn scan_cloud(&self, out: &mut Vec<[f32; 3]>);
    /// Re-initialisations so far.
    fn resets(&self) -> u32;
}

struct CoreEngine<'a, const PIX: usize, const PTS: usize, const DS: usize> {
    odo: Odometry<'a, PIX, PTS, DS>,
    bytes: usize,
}

impl<const PIX: usize, const PTS: usize, const DS: usize> Engine for CoreEngine<'_, PIX, PTS, DS> {
    fn push_imu(&mut self, s: ImuSample) -> ImuPush {
        self.odo.push_imu(s)
    }
    fn process_scan(&mut self, scan: ScanView<'_>, clock: &mut StdClock) -> ScanResult {
        self.odo.process_scan_timed(scan, clock)
    }
    fn map_voxels(&self) -> usize {
        self.odo.map().len()
    }
    fn map_points(&self, out: &mut Vec<MapPoint>) {
        self.odo.map().for_each_point(|_, xyz, normal| out.push(MapPoint { xyz, normal }));
    }
    fn max_points(&self) -> usize {
        PTS
    }
    fn storage_bytes(&self) -> usize {
        self.bytes
    }
    fn filter(&self) -> Option<loglio_core::eskf::Eskf> {
        self.odo.filter().cloned()
    }
    fn scan_cloud(&self, out: &mut Vec<[f32; 3]>) {
        let Some(f) = self.odo.filter() else { return };
        let (r, t) = f.state().lidar_pose();
        let r = r.to_rotation_matrix().into_inner();
        out.extend(self.odo.scan_points().iter().map(|p| {
            let q = r * Vector3::new(f64::from(p.xyz[0]), f64::from(p.xyz[1]), f64::from(p.xyz[2])) + t;
            [q.x as f32, q.y as f32, q.z as f32]
        }));
    }
    fn resets(&self) -> u32 {
        self.odo.stats().reinitialisations
    }
}

/// The compiled storage size classes (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StorageClass {
    /// Up to 32 rows and the pixels of 32 x 2048, 131,072 points and a 2^18-voxel pool.
    Small,
    /// Up to 32 rows and the pixels of 32 x 2048, 131,072 points and a 2^20-voxel pool.
    SmallBigMap,
    /// Up to the pixels of 128 x 2048, 524,288 points and a 2^18-voxel pool.
    Large,
    /// Up to the pixels of 128 x 2048, 524,288 points and a 2^20-voxel pool.
    LargeBigMap,
}

const SMALL_PIX: usize = storage_pixels(32, 2048);
const LARGE_PIX: usize = storage_pixels(128, 2048);
const SMALL_PTS: usize = 1 << 17;
const LARGE_PTS: usize = 1 << 19;
const SMALL_DS: usize = 1 << 16;
const LARGE_DS: usize = 1 << 17;
const POOL: usize = 1 << 18;
const BIG_POOL: usize = 1 << 20;

type SmallStorage = OdometryStorage<SMALL_PIX, SMALL_PTS, SMALL_DS, POOL, { 2 * POOL }>;
type SmallBigMapStorage = OdometryStorage<SMALL_PIX, SMALL_PTS, SMALL_DS, BIG_POOL, { 2 * BIG_POOL }>;
type LargeStorage = OdometryStorage<LARGE_PIX, LARGE_PTS, LARGE_DS, POOL, { 2 * POOL }>;
type LargeBigMapStorage = OdometryStorage<LARGE_PIX, LARGE_PTS, LARGE_DS, BIG_POOL, { 2 * BIG_POOL }>;

impl StorageClass {
    /// The smallest class for a layout of `rows` x `cols` and a map of `map_capacity` voxels.
    /// A class holds a number of pixels (with Ring FALS's border), not a fixed width: an
    /// HDL-32E at 10 Hz (32 x 2170) or a VLP-16 at 5 Hz (16 x 3616 -> 3600) fits as well as a
    /// 32 x 2048 image.
    pub fn choose(rows: usize, cols: usize, map_capacity: u64) -> Result<StorageClass, PipelineError> {
        let pixels = storage_pixels(rows, cols);
        if rows > MAX_ROWS || cols > MAX_COLS || pixels > LARGE_PIX {
            return Err(PipelineError(format!(
                "a {rows} x {cols} range image is larger than the largest supported ({LARGE_PIX} pixels with \
                 the border, e.g. 128 x 2048; at most {MAX_ROWS} rows and {MAX_COLS} columns)"
            )));
        }
        // More than 32 rows: the large class as well, for its points (dual returns).
        let large = rows > 32 || pixels > SMALL_PIX;
        let big_map = map_capacity > POOL as u64;
        if map_capacity > BIG_POOL as u64 {
            crate::diag::warn(format!(
                "mapping.map_capacity = {map_capacity} is more than the largest compiled pool; using {BIG_POOL} voxels"
            ));
        }
        Ok(match (large, big_map) {
            (false, false) => StorageClass::Small,
            (false, true) => StorageClass::SmallBigMap,
            (true, false) => StorageClass::Large,
            (true, true) => StorageClass::LargeBigMap,
        })
    }

    /// Bytes of the storage of this class.
    pub fn bytes(self) -> usize {
        match self {
            StorageClass::Small => SmallStorage::bytes(),
            StorageClass::SmallBigMap => SmallBigMapStorage::bytes(),
            StorageClass::Large => LargeStorage::bytes(),
            StorageClass::LargeBigMap => LargeBigMapStorage::bytes(),
        }
    }

    /// Voxels of the map pool.
    pub fn pool_voxels(self) -> usize {
        match self {
            StorageClass::Small | StorageClass::Large => POOL,
            _ => BIG_POOL,
        }
    }
}

/// `Box::new(make())` on a thread whose stack can hold the value several times over, so that
/// the value never lands on a small stack (see the module docs). Twice was not always enough:
/// how many temporaries of the value a build keeps depends on its inlining (a profile-guided
/// build with one codegen unit overflowed). The reservation is address space only: the pages
/// the construction does not touch are never committed.
pub fn boxed_storage<T: Send + 'static>(make: fn() -> T) -> Result<Box<T>, PipelineError> {
    let size = std::mem::size_of::<T>();
    let stack = size.saturating_mul(4).saturating_add(16 << 20);
    let handle = std::thread::Builder::new()
        .name("loglio-alloc".into())
        .stack_size(stack)
        .spawn(move || Box::new(make()))
        .map_err(|e| PipelineError(format!("cannot allocate the odometry's {} MiB: {e}", size >> 20)))?;
    handle.join().map_err(|_| PipelineError(format!("cannot allocate the odometry's {} MiB", size >> 20)))
}

fn run_class<const PIX: usize, const PTS: usize, const DS: usize, const V: usize, const I: usize, R>(
    cfg: &OdometryConfig,
    f: impl FnOnce(&mut dyn Engine) -> R,
) -> Result<R, PipelineError> {
    let mut storage = boxed_storage(OdometryStorage::<PIX, PTS, DS, V, I>::new)?;
    let bytes = OdometryStorage::<PIX, PTS, DS, V, I>::bytes();
    let odo = storage.odometry(cfg).map_err(odometry_error)?;
    let mut engine = CoreEngine { odo, bytes };
    Ok(f(&mut engine))
}

fn odometry_error(e: OdometryError) -> PipelineError {
    PipelineError(format!("odometry: {e}"))
}

/// Builds the odometry for `cfg` over storage of `class` (allocated here, freed on return) and
/// runs `f` with it.
pub fn with_engine<R>(
    cfg: &OdometryConfig,
    class: StorageClass,
    f: impl FnOnce(&mut dyn Engine) -> R,
) -> Result<R, PipelineError> {
    match class {
        StorageClass::Small => run_class::<SMALL_PIX, SMALL_PTS, SMALL_DS, POOL, { 2 * POOL }, R>(cfg, f),
        StorageClass::SmallBigMap => {
            run_class::<SMALL_PIX, SMALL_PTS, SMALL_DS, BIG_POOL, { 2 * BIG_POOL }, R>(cfg, f)
        }
        StorageClass::Large => run_class::<LARGE_PIX, LARGE_PTS, LARGE_DS, POOL, { 2 * POOL }, R>(cfg, f),
        StorageClass::LargeBigMap => {
            run_class::<LARGE_PIX, LARGE_PTS, LARGE_DS, BIG_POOL, { 2 * BIG_POOL }, R>(cfg, f)
        }
    }
}

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
    }
}

/// Where and what to write.
#[derive(Clone, Debug, Default)]
pub struct OutputOptions {
    /// The output directory (`None`: write nothing).
    pub dir: Option<PathBuf>,
    /// A ground truth to evaluate against (ATE, error plot).
    pub gt: Option<Trajectory>,
    /// Write the map (PLY and PCD).
    pub map: bool,
    /// Write the plots (PNG and SVG).
    pub plots: bool,
}

/// One pose of the estimated trajectory.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EstPose {
    /// Scan end, ns.
    pub t_ns: u64,
    /// IMU position in the world, m.
    pub p: [f64; 3],
    /// IMU orientation in the world (w, x, y, z).
    pub q_wxyz: [f64; 4],
}

/// The streaming outputs: trajectory (TUM) and per-scan CSV, written as scans come; map, plots
/// and evaluation at [`Outputs::finish`]. [`Outputs::flush`] makes the files whole at any time.
#[derive(Debug)]
pub struct Outputs {
    opt: OutputOptions,
    tum: Option<TumWriter>,
    csv: Option<ScanCsvWriter>,
    /// Every pose written (for the plots and the evaluation).
    pub poses: Vec<EstPose>,
}

/// What [`Outputs::finish`] produced.
#[derive(Clone, Debug, Default)]
pub struct Finished {
    /// Files written.
    pub files: Vec<PathBuf>,
    /// The evaluation against the ground truth, if one was given.
    pub eval: Option<EvalReport>,
    /// Map points written.
    pub map_points: usize,
}

impl Outputs {
    /// Opens the streaming files in `opt.dir` (created if missing).
    pub fn new(opt: OutputOptions) -> Result<Outputs, PipelineError> {
        let (tum, csv) = match &opt.dir {
            Some(d) => (
                Some(TumWriter::create(&d.join("trajectory.tum"))?),
                Some(ScanCsvWriter::create(&d.join("scans.csv"))?),
            ),
            None => (None, None),
        };
        Ok(Outputs { opt, tum, csv, poses: Vec::new() })
    }

    /// Records one scan's result.
    pub fn record(
        &mut self,
        index: u64,
        res: &ScanResult,
        process_ms: f64,
        map_voxels: usize,
    ) -> io::Result<()> {
        let pose = &res.pose;
        let initialising = matches!(res.status, Status::Initialising(_));
        let q = pose.rotation.quaternion();
        let e = EstPose {
            t_ns: pose.t_ns,
            p: [pose.position.x, pose.position.y, pose.position.z],
            q_wxyz: [q.w, q.i, q.j, q.k],
        };
        // Before the IMU initialisation the pose is a placeholder: not part of the trajectory.
        if !initialising {
            self.poses.push(e);
            if let Some(t) = &mut self.tum {
                t.write(e.t_ns, e.p, e.q_wxyz)?;
            }
        }
        if let Some(c) = &mut self.csv {
            let a = &res.associations;
            c.write(&ScanRecord {
                index,
                start_ns: res.scan_start_ns,
                end_ns: pose.t_ns,
                points_in: res.points[0],
                points_used: res.points[1],
                large_surfel: a.large_surfel,
                small_surfel: a.small_surfel,
                point_to_plane: a.plane,
                unmatched: res.points[1].saturating_sub(a.accepted()),
                iterations: res.update.iterations as u32,
                status: scan_status(&res.status),
                process_ms,
                map_voxels: map_voxels as u64,
            })?;
        }
        // Whole lines on disk after every scan: a crash or a power cut loses nothing estimated.
        self.flush()
    }

    /// Sets the ground truth to evaluate against at [`Self::finish`].
    pub fn set_ground_truth(&mut self, gt: Option<Trajectory>) {
        self.opt.gt = gt;
    }

    /// Flushes the streaming files (Ctrl-C).
    pub fn flush(&mut self) -> io::Result<()> {
        if let Some(t) = &mut self.tum {
            t.flush()?;
        }
        if let Some(c) = &mut self.csv {
            c.flush()?;
        }
        Ok(())
    }

    /// The estimate as an evaluation trajectory.
    pub fn trajectory(&self) -> Trajectory {
        let mut stamps = Vec::with_capacity(self.poses.len());
        let mut poses = Vec::with_capacity(self.poses.len());
        for p in &self.poses {
            stamps.push(p.t_ns as f64 * 1e-9);
            let [w, x, y, z] = p.q_wxyz;
            let r = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))
                .to_rotation_matrix()
                .into_inner();
            poses.push(eval::Pose { r, t: Vector3::from(p.p) });
        }
        Trajectory { stamps: Some(stamps), poses }
    }

    /// Closes the streams and writes the map, the plots and the evaluation.
    pub fn finish(mut self, engine: &dyn Engine) -> Result<Finished, PipelineError> {
        let mut out = Finished::default();
        self.flush()?;
        if let Some(t) = self.tum.take() {
            t.finish()?;
        }
        if let Some(c) = self.csv.take() {
            c.finish()?;
        }
        if let Some(gt) = &self.opt.gt {
            let est = self.trajectory();
            if est.len() >= 3 {
                let opt = EvalOptions::default(); // evo's defaults: SE(3), 10 ms pairing
                match eval::evaluate(gt, &est, &opt) {
                    Ok(r) => out.eval = Some(r),
                    Err(e) => crate::diag::warn(format!("no evaluation against the ground truth: {e}")),
                }
            } else {
                crate::diag::warn("no evaluation against the ground truth: fewer than 3 poses");
            }
        }
        let Some(dir) = self.opt.dir.clone() else { return Ok(out) };
        out.files.push(dir.join("trajectory.tum"));
        out.files.push(dir.join("scans.csv"));
        if self.opt.map {
            let mut pts = Vec::new();
            engine.map_points(&mut pts);
            out.map_points = pts.len();
            let ply = dir.join("map.ply");
            output::write_ply_file(&ply, &pts, true)?;
            let pcd = dir.join("map.pcd");
            output::write_pcd_file(&pcd, &pts, true, PcdEncoding::Binary)?;
            out.files.extend([ply, pcd]);
        }
        if self.opt.plots {
            let est: Vec<[f64; 3]> = self.poses.iter().map(|p| p.p).collect();
            for ext in ["png", "svg"] {
                let p = dir.join(format!("trajectory.{ext}"));
                match &out.eval {
                    Some(r) => output::plot_trajectory_top_view(
                        &p,
                        "Trajectory, top view (SE(3)-aligned to the ground truth)",
                        "loglio",
                        &r.est_positions,
                        Some(&r.gt_positions),
                    ),
                    None => {
                        output::plot_trajectory_top_view(&p, "Trajectory, top view", "loglio", &est, None)
                    }
                }
                .map_err(|e| PipelineError(e.0))?;
                out.files.push(p);
                if let Some(r) = &out.eval {
                    let p = dir.join(format!("error.{ext}"));
                    let title = format!("APE translation (SE(3)-aligned), rmse {:.3} m", r.ape_trans.rmse);
                    output::plot_error_over_time(
                        &p,
                        &title,
                        "time since start [s]",
                        "error [m]",
                        &r.ape_series,
                    )
                    .map_err(|e| PipelineError(e.0))?;
                    out.files.push(p);
                }
            }
        }
        if let Some(r) = &out.eval {
            let p = dir.join("eval.json");
            std::fs::write(&p, r.to_json()).map_err(|e| PipelineError(format!("{}: {e}", p.display())))?;
            out.files.push(p);
        }
        Ok(out)
    }
}

/// Counts and times of a run.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunStats {
    /// Scans processed.
    pub scans: u64,
    /// Scans per status: initialising, ok, degraded, imu-only, re-initialising.
    pub status: [u64; 5],
    /// IMU samples received (before the core's checks).
    pub imu_in: u64,
    /// IMU samples the core refused (out of order, duplicate, non-finite).
    pub imu_dropped: u64,
    /// IMU samples discarded because they were more than a second older than the next scan.
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
}

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
    scans: VecDeque<(OwnedScan, u64)>,
    spare: Vec<Vec<ScanPoint>>,
    /// The outputs.
    pub outputs: Outputs,
    /// Counts and times.
    pub stats: RunStats,
    /// Called after each processed scan with its result.
    pub on_scan: Option<ScanCallback<'e>>,
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
            sinks: Sinks::default(),
            latest: None,
            predictor: None,
            map_sent_ns: None,
            origin: Instant::now(),
        }
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

    /// Takes one IMU sample (sensor clock; the offset is applied here).
    pub fn imu(&mut self, mut s: ImuSample) -> Result<(), PipelineError> {
        s.t_ns = s.t_ns.saturating_add_signed(self.imu_offset_ns);
        self.stats.imu_in += 1;
        widen(&mut self.stats.imu_span, s.t_ns);
        self.last_imu_ns = Some(self.last_imu_ns.map_or(s.t_ns, |t| t.max(s.t_ns)));
        self.imu.push_back(s);
        if self.predictor.is_some() {
            self.propagate_live(&s);
        }
        // With no scan waiting, keep about 5 s (1 kHz) of samples for the first one.
        if self.scans.is_empty() && self.imu.len() > 5000 {
            self.imu.pop_front();
            self.stats.imu_stale += 1;
        }
        self.process_ready(false, None)
    }

    /// Takes one scan.
    pub fn scan(&mut self, scan: OwnedScan, arrival: u64) -> Result<(), PipelineError> {
        widen(&mut self.stats.lidar_span, scan.end_ns());
        self.scans.push_back((scan, arrival));
        self.process_ready(false, None)
    }

    /// Scans waiting for the IMU.
    pub fn pending(&self) -> usize {
        self.scans.len()
    }

    /// Processes the waiting scans the IMU covers; with `force`, every waiting scan; with
    /// `older_than`, those that arrived before it (a caller's wall clock: the live wait bound).
    pub fn process_ready(&mut self, force: bool, older_than: Option<u64>) -> Result<(), PipelineError> {
        while let Some((front, arrival)) = self.scans.front() {
            let end = front.end_ns();
            let covered = self.last_imu_ns.is_some_and(|t| t >= end);
            let waited = older_than.is_some_and(|t| *arrival <= t);
            if !(covered || force || waited || self.scans.len() > MAX_PENDING_SCANS) {
                break;
            }
            let Some((scan, arrival)) = self.scans.pop_front() else { break };
            if !covered {
                self.stats.scans_without_imu += 1;
            }
            self.process(scan, arrival)?;
        }
        Ok(())
    }

    fn process(&mut self, scan: OwnedScan, arrival: u64) -> Result<(), PipelineError> {
        let end = scan.end_ns();
        let stale_before = scan.start_ns.saturating_sub(1_000_000_000);
        while let Some(s) = self.imu.front() {
            if s.t_ns > end {
                break;
            }
            let s = *s;
            self.imu.pop_front();
            if s.t_ns < stale_before {
                self.stats.imu_stale += 1;
                continue;
            }
            if !matches!(self.engine.push_imu(s), ImuPush::Accepted) {
                self.stats.imu_dropped += 1;
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
        }] += 1;
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
        self.process_ready(true, None)?;
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

/// Writes a trajectory as TUM (for the ground truth of simulated runs).
pub fn write_tum(path: &Path, poses: &[EstPose]) -> Result<(), PipelineError> {
    let mut w = TumWriter::create(path)?;
    for p in poses {
        w.write(p.t_ns, p.p, p.q_wxyz)?;
    }
    w.finish()?;
    Ok(())
}

/// A summary line of the status counts.
pub fn status_summary(st: &RunStats) -> String {
    let names = ["initialising", "ok", "degraded", "imu-only", "re-initialising"];
    let parts: Vec<String> =
        names.iter().zip(st.status).filter(|(_, n)| *n > 0).map(|(name, n)| format!("{n} {name}")).collect();
    parts.join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Classes by pixels: every layout the core accepts and a class can hold gets one (the
    /// HDL-32E at 10 Hz, 32 x 2170, was refused as wider than 2048), the rest a one-line error.
    #[test]
    fn storage_class_is_chosen_by_pixels() {
        let small = POOL as u64;
        assert_eq!(StorageClass::choose(32, 1800, small), Ok(StorageClass::Small));
        assert_eq!(StorageClass::choose(32, 2048, small), Ok(StorageClass::Small));
        assert_eq!(StorageClass::choose(16, 3600, small), Ok(StorageClass::Small));
        assert_eq!(StorageClass::choose(32, 2170, small), Ok(StorageClass::Large));
        assert_eq!(StorageClass::choose(32, 2170, 2 * small), Ok(StorageClass::LargeBigMap));
        assert_eq!(StorageClass::choose(32, 3600, small), Ok(StorageClass::Large));
        assert_eq!(StorageClass::choose(64, 1024, small), Ok(StorageClass::Large));
        assert_eq!(StorageClass::choose(128, 2048, small), Ok(StorageClass::Large));
        assert_eq!(StorageClass::choose(16, 1024, 2 * small), Ok(StorageClass::SmallBigMap));
        for (rows, cols) in [(128, 2100), (64, 3601), (129, 1024)] {
            let e = StorageClass::choose(rows, cols, small).unwrap_err().0;
            assert!(e.starts_with(&format!("a {rows} x {cols} range image is larger than")), "{e}");
            assert!(!e.contains('\n'));
        }
        // What a class holds, the core's check agrees with.
        assert!(storage_pixels(32, 2170) <= LARGE_PIX && storage_pixels(32, 2170) > SMALL_PIX);
    }
}
