//! The configuration onto a running core [`Odometry`]:
//!
//! - [`odometry_config`] maps the host configuration onto the core's [`OdometryConfig`] (key by
//!   key in docs/configuration.md, generated from `config.rs`'s key table).
//! - [`with_engine`] allocates the core's storage once, on the heap, sized for the sensor, and
//!   lends an [`Engine`] (the odometry behind a trait object) to a closure.
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

use std::time::Instant;

use loglio_core::association::{AssociationConfig, KnnScratch};
use loglio_core::downsample::DownsampleConfig;
use loglio_core::eskf::EskfConfig;
use loglio_core::free_space::FreeSpaceConfig;
use loglio_core::imu::{ImuInitConfig, ImuNoise, ImuPush, ImuSample};
use loglio_core::imu_guard::ImuGuardConfig;
use loglio_core::motion_model::MotionModel;
use loglio_core::odometry::{Clock, Odometry, OdometryConfig, OdometryError, OdometryStorage};
use loglio_core::output::ScanResult;
use loglio_core::parallel::Parallel;
use loglio_core::range_image::{MAX_COLS, MAX_ROWS, RangeImageLayout};
use loglio_core::ring_fals::RingFalsConfig;
use loglio_core::ring_fals::storage_pixels;
use loglio_core::scan::ScanView;
use loglio_core::standstill::StandstillConfig;
use loglio_core::time_offset::TimeOffsetConfig;
use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::config::{Config, ImuSource, SensorFamily};
use crate::error::PipelineError;
use crate::output::MapPoint;

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
    // 0 keeps the preset's stride (by the layout's columns).
    let ring_fals = RingFalsConfig { column_stride: cfg.mapping.normals_column_stride, ..base.ring_fals };
    let [w, x, y, z] = cfg.extrinsics.quaternion_wxyz();
    let t = cfg.extrinsics.translation();
    Ok(OdometryConfig {
        mode: cfg.mapping.association,
        downsample: DownsampleConfig { voxel: cfg.mapping.scan_voxel_size as f32, ..base.downsample },
        map,
        eskf,
        init,
        ext_rot: UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        ext_pos: Vector3::new(t[0], t[1], t[2]),
        motion: if cfg.imu.source == ImuSource::None { MotionModel::LIDAR_ONLY } else { MotionModel::Imu },
        blind: cfg.sensor.blind as f32,
        max_range: cfg.sensor.max_range as f32,
        association: AssociationConfig {
            max_points: u32::try_from(cfg.mapping.max_points).unwrap_or(u32::MAX),
            knn_reach: cfg.mapping.knn_search,
            robust_sigmas: cfg.filter.robust_sigmas,
            plane_line_spread: cfg.mapping.plane_line_spread as f32,
            ..base.association
        },
        standstill: StandstillConfig { enabled: cfg.filter.standstill, ..base.standstill },
        free_space: FreeSpaceConfig { enabled: cfg.mapping.clear_free_space, ..base.free_space },
        time_offset: TimeOffsetConfig { enabled: cfg.time.estimate_offset, ..base.time_offset },
        imu_guard: ImuGuardConfig {
            gyro_full_scale: cfg.imu.gyro_full_scale.to_radians() as f32,
            acc_full_scale: (cfg.imu.acc_full_scale * 9.80665) as f32,
            ..base.imu_guard
        },
        ring_fals,
        ..base
    })
}

/// The odometry behind a trait object, whatever its storage size class.
pub trait Engine {
    /// Queues one IMU sample (see [`Odometry::push_imu`]).
    fn push_imu(&mut self, s: ImuSample) -> ImuPush;
    /// Processes one scan, timing the stages with `clock`.
    fn process_scan(&mut self, scan: ScanView<'_>, clock: &mut StdClock) -> ScanResult;
    /// Inserts a scan's map points whose insertion waits for the next scan
    /// ([`Odometry::set_deferred_map`]): the map accessors below then hold every scan.
    fn flush_map(&mut self);
    /// Voxels in the map (before the last scan's points while their insertion waits).
    fn map_voxels(&self) -> usize;
    /// The map's life counters (voxels created and evicted, points dropped) and its pool's
    /// capacity in voxels.
    fn map_counters(&self) -> (loglio_core::voxel_map::MapCounters, usize);
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
    /// Jumps of the estimate so far: re-initialisations and re-localisations (MAVLink's
    /// `reset_counter`).
    fn resets(&self) -> u32;
    /// Integrates the queued IMU samples up to `until_ns` without a scan (a LiDAR gap; see
    /// [`Odometry::propagate_imu`]).
    fn propagate_imu(&mut self, until_ns: u64) -> u32;
    /// What the core's IMU outlier guard dropped and flagged.
    fn imu_guard_stats(&self) -> loglio_core::imu_guard::ImuGuardStats;
    /// Re-localisations in the map that moved the prediction (after LiDAR gaps, while lost).
    fn relocalisations(&self) -> u32;
    /// Map voxels removed because a scan saw through them, and points left out as moving
    /// ([`loglio_core::free_space`]).
    fn free_space(&self) -> (u64, u64);
    /// The IMU–LiDAR time offset the core estimated and applies ([`loglio_core::time_offset`]).
    fn time_offset(&self) -> loglio_core::time_offset::TimeOffsetEstimate;
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
    fn flush_map(&mut self) {
        self.odo.flush_map();
    }
    fn map_voxels(&self) -> usize {
        self.odo.map().len()
    }
    fn map_counters(&self) -> (loglio_core::voxel_map::MapCounters, usize) {
        (self.odo.map().counters(), self.odo.map().capacity())
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
        let s = self.odo.stats();
        s.reinitialisations.saturating_add(s.relocalisations)
    }
    fn propagate_imu(&mut self, until_ns: u64) -> u32 {
        self.odo.propagate_imu(until_ns)
    }
    fn imu_guard_stats(&self) -> loglio_core::imu_guard::ImuGuardStats {
        self.odo.imu_guard_stats()
    }
    fn relocalisations(&self) -> u32 {
        self.odo.stats().relocalisations
    }
    fn free_space(&self) -> (u64, u64) {
        let s = self.odo.stats();
        (s.cleared, s.moving)
    }
    fn time_offset(&self) -> loglio_core::time_offset::TimeOffsetEstimate {
        self.odo.time_offset()
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
    threads: usize,
    f: impl FnOnce(&mut dyn Engine) -> R,
) -> Result<R, PipelineError> {
    let mut storage = boxed_storage(OdometryStorage::<PIX, PTS, DS, V, I>::new)?;
    let bytes = OdometryStorage::<PIX, PTS, DS, V, I>::bytes();
    let pool = super::pool::Pool::new(threads);
    let mut scratch = vec![KnnScratch::new(); pool.width().saturating_sub(1)];
    // A scan's map insertion waits here for the next scan's Ring FALS, beside it.
    let mut deferred =
        vec![loglio_core::voxel_map::MapPoint::default(); if pool.width() > 1 { DS } else { 0 }];
    // The downsampling's kept points are gathered here in pieces on the threads.
    let mut gather = vec![loglio_core::scan::ScanPoint::default(); if pool.width() > 1 { DS } else { 0 }];
    let bytes = bytes + std::mem::size_of_val(deferred.as_slice()) + std::mem::size_of_val(gather.as_slice());
    let mut odo = storage.odometry(cfg).map_err(odometry_error)?;
    if pool.width() > 1 {
        odo.set_parallel(&pool, &mut scratch);
        odo.set_deferred_map(&mut deferred);
        odo.set_gather_buffer(&mut gather);
    }
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
    threads: usize,
    f: impl FnOnce(&mut dyn Engine) -> R,
) -> Result<R, PipelineError> {
    let t = threads;
    match class {
        StorageClass::Small => run_class::<SMALL_PIX, SMALL_PTS, SMALL_DS, POOL, { 2 * POOL }, R>(cfg, t, f),
        StorageClass::SmallBigMap => {
            run_class::<SMALL_PIX, SMALL_PTS, SMALL_DS, BIG_POOL, { 2 * BIG_POOL }, R>(cfg, t, f)
        }
        StorageClass::Large => run_class::<LARGE_PIX, LARGE_PTS, LARGE_DS, POOL, { 2 * POOL }, R>(cfg, t, f),
        StorageClass::LargeBigMap => {
            run_class::<LARGE_PIX, LARGE_PTS, LARGE_DS, BIG_POOL, { 2 * BIG_POOL }, R>(cfg, t, f)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The line-fit key reaches the association: off by default, on where set.
    #[test]
    fn plane_line_spread_reaches_the_association() {
        let text = "preset = \"vlp32c\"\n";
        let layout = |c: &Config| c.nominal_layout().unwrap();
        let off = Config::from_toml_str(text).unwrap();
        assert_eq!(odometry_config(&off, layout(&off)).unwrap().association.plane_line_spread, 0.0);
        let on = Config::from_toml_str(&format!("{text}[mapping]\nplane_line_spread = 0.03\n")).unwrap();
        assert_eq!(odometry_config(&on, layout(&on)).unwrap().association.plane_line_spread, 0.03);
        let bad = Config::from_toml_str(&format!("{text}[mapping]\nplane_line_spread = 2.0\n"));
        assert!(bad.is_err_and(|e| e.0.contains("mapping.plane_line_spread")));
    }

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
