//! The per-scan pipeline (paper section IV): IMU initialisation and propagation, Ring FALS
//! normals, undistortion, downsampling, association and the iterated update, then the map
//! insertion.
//!
//! **Public contract** (host, firmware and tests code against it; keep it stable):
//! - [`OdometryStorage`] owns every buffer (`const fn new()`, all-zero: a `static` lands in
//!   `.bss`); [`OdometryStorage::odometry`] lends them to an [`Odometry`].
//! - [`Odometry::push_imu`] queues IMU samples (in time order; bad ones are counted and dropped).
//! - [`Odometry::process_scan`] takes one scan (its points carry `t` from `start_ns`, and their
//!   range-image pixel) after the IMU samples up to the scan end were pushed, and returns a
//!   [`ScanResult`]. [`Odometry::process_scan_timed`] does the same with a caller clock for the
//!   per-stage times (the core has no clock).
//! - [`AssociationMode`] selects `full` (LOG-LIO), `plane-only` (LOG-C) or `plain` (FAST-LIO2-like)
//!   at run time.

// SKELETON: the stages after propagation land with the association (issue 7); remove this then.
#![allow(dead_code, missing_debug_implementations)]

use nalgebra::{UnitQuaternion, Vector3};

use crate::downsample::{DownsampleConfig, VoxelDownsampler};
use crate::eskf::{Eskf, EskfConfig, UpdateResult};
use crate::imu::{ImuInitConfig, ImuInitializer, ImuPush, ImuQueue, ImuSample, InitStatus, WaitReason};
use crate::output::{AssociationCounts, ImuOnlyReason, PoseEstimate, ScanResult, StageTimes, Status};
use crate::range_image::RangeImageLayout;
use crate::ring_fals::{PointNormal, RingFals, RingFalsConfig, RingTable, TableError, storage_pixels};
use crate::scan::{ScanPoint, ScanView};
use crate::undistort::ImuTrajectory;
use crate::voxel_map::{MapConfig, MapError, MapStorage, PRESET_INDEX_SLOTS, PRESET_POOL_VOXELS, VoxelMap};

/// IMU samples queued between two scans (200 Hz x 1 s, or 1 kHz x 0.25 s).
pub const IMU_QUEUE: usize = 256;
/// IMU knots kept for the undistortion of one scan.
pub const TRAJECTORY_KNOTS: usize = 64;

/// Which association the update uses (the paper's ablation).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum AssociationMode {
    /// LOG-LIO: visibility and consistency checks, then large surfel, small surfel,
    /// point-to-plane.
    #[default]
    Full,
    /// The paper's LOG-C: the checks and point-to-plane only (no surfels).
    PlaneOnly,
    /// No normals and no checks: point-to-plane as FAST-LIO2 does it.
    Plain,
}

/// Everything the pipeline needs to know. Presets for the two paper setups:
/// [`OdometryConfig::vlp32c`] and [`OdometryConfig::os1_16`].
#[derive(Clone, Debug, PartialEq)]
pub struct OdometryConfig {
    /// Association mode.
    pub mode: AssociationMode,
    /// The sensor's range image (rows, columns, beam angles) for the Ring FALS table.
    pub layout: RangeImageLayout,
    /// Ring FALS settings.
    pub ring_fals: RingFalsConfig,
    /// Scan downsampling (voxel edge; the map's voxel edge is the paper's choice).
    pub downsample: DownsampleConfig,
    /// The voxel map.
    pub map: MapConfig,
    /// The filter (noise, iterations, degeneracy, extrinsic estimation).
    pub eskf: EskfConfig,
    /// IMU initialisation.
    pub init: ImuInitConfig,
    /// IMU from LiDAR rotation.
    pub ext_rot: UnitQuaternion<f64>,
    /// LiDAR origin in the IMU frame, m.
    pub ext_pos: Vector3<f64>,
    /// Points nearer than this are ignored (the vehicle itself), m.
    pub blind: f32,
    /// Points farther than this are ignored, m.
    pub max_range: f32,
}

/// Why an [`Odometry`] cannot be built.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum OdometryError {
    /// The layout does not fit the storage or the Ring FALS settings are invalid.
    RingTable(TableError),
    /// The map settings are invalid or the map storage is unusable.
    Map(MapError),
    /// A setting is out of range (its name).
    InvalidConfig(&'static str),
}

impl core::fmt::Display for OdometryError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::RingTable(e) => write!(f, "ring table: {e}"),
            Self::Map(e) => write!(f, "voxel map: {e}"),
            Self::InvalidConfig(k) => write!(f, "invalid odometry setting `{k}`"),
        }
    }
}

impl core::error::Error for OdometryError {}

/// The buffers of one scan and the pipeline's stages, sized at compile time: `PIX` range-image
/// pixels (see [`storage_pixels`]), `PTS` points per scan, `DS` downsampling slots.
pub struct ScanStorage<const PIX: usize, const PTS: usize, const DS: usize> {
    ring: RingFals<PIX>,
    table: RingTable,
    downsampler: VoxelDownsampler<DS>,
    points: [ScanPoint; PTS],
    normals: [PointNormal; PTS],
    normals3: [[f32; 3]; PTS],
    imu: ImuQueue<IMU_QUEUE>,
    trajectory: ImuTrajectory<TRAJECTORY_KNOTS>,
}

impl<const PIX: usize, const PTS: usize, const DS: usize> ScanStorage<PIX, PTS, DS> {
    /// Empty storage.
    pub const fn new() -> Self {
        Self {
            ring: RingFals::new(),
            table: RingTable::new(),
            downsampler: VoxelDownsampler::new(),
            points: [ScanPoint { xyz: [0.0; 3], t: 0.0, row: 0, col: 0, intensity: 0, ret: 0, flags: 0 };
                PTS],
            normals: [PointNormal::INVALID; PTS],
            normals3: [[0.0; 3]; PTS],
            imu: ImuQueue::new(),
            trajectory: ImuTrajectory::new(),
        }
    }
}

impl<const PIX: usize, const PTS: usize, const DS: usize> Default for ScanStorage<PIX, PTS, DS> {
    fn default() -> Self {
        Self::new()
    }
}

/// All the memory of the odometry: the scan buffers and the voxel map (`V` voxels, `I` index
/// slots). `const fn new()`; put it in a `static` (firmware) or a `Box` (host).
pub struct OdometryStorage<
    const PIX: usize,
    const PTS: usize,
    const DS: usize,
    const V: usize,
    const I: usize,
> {
    scan: ScanStorage<PIX, PTS, DS>,
    map: MapStorage<V, I>,
}

impl<const PIX: usize, const PTS: usize, const DS: usize, const V: usize, const I: usize>
    OdometryStorage<PIX, PTS, DS, V, I>
{
    /// Empty storage.
    pub const fn new() -> Self {
        Self { scan: ScanStorage::new(), map: MapStorage::new() }
    }

    /// Bytes this storage takes (what the README states per preset).
    pub const fn bytes() -> usize {
        core::mem::size_of::<Self>()
    }

    /// An odometry over this storage (the previous contents are discarded).
    pub fn odometry(&mut self, cfg: &OdometryConfig) -> Result<Odometry<'_, PIX, PTS, DS>, OdometryError> {
        Odometry::new(&mut self.scan, &mut self.map, cfg)
    }
}

impl<const PIX: usize, const PTS: usize, const DS: usize, const V: usize, const I: usize> Default
    for OdometryStorage<PIX, PTS, DS, V, I>
{
    fn default() -> Self {
        Self::new()
    }
}

/// Storage for a Velodyne VLP-32C (32 x 1800, 57,600 points per scan) with the preset map pool.
pub type Vlp32cStorage =
    OdometryStorage<{ storage_pixels(32, 1800) }, 65536, 32768, PRESET_POOL_VOXELS, PRESET_INDEX_SLOTS>;
/// Storage for an Ouster OS1-16 (16 x 1024) with the preset map pool.
pub type Os1_16Storage =
    OdometryStorage<{ storage_pixels(16, 1024) }, 16384, 16384, PRESET_POOL_VOXELS, PRESET_INDEX_SLOTS>;

/// The LiDAR-inertial odometry over caller-owned storage.
pub struct Odometry<'a, const PIX: usize, const PTS: usize, const DS: usize> {
    cfg: OdometryConfig,
    scan: &'a mut ScanStorage<PIX, PTS, DS>,
    map: VoxelMap<'a>,
    initializer: ImuInitializer,
    filter: Option<Eskf>,
    wait: WaitReason,
    scans: u32,
}

impl<'a, const PIX: usize, const PTS: usize, const DS: usize> Odometry<'a, PIX, PTS, DS> {
    /// Builds the ring table from `cfg.layout` and an empty map.
    pub fn new<const V: usize, const I: usize>(
        scan: &'a mut ScanStorage<PIX, PTS, DS>,
        map: &'a mut MapStorage<V, I>,
        cfg: &OdometryConfig,
    ) -> Result<Self, OdometryError> {
        if !(cfg.blind.is_finite() && cfg.blind >= 0.0) {
            return Err(OdometryError::InvalidConfig("blind"));
        }
        if !(cfg.max_range.is_finite() && cfg.max_range > cfg.blind) {
            return Err(OdometryError::InvalidConfig("max_range"));
        }
        scan.table.build(&cfg.layout, &cfg.ring_fals).map_err(OdometryError::RingTable)?;
        scan.imu.clear();
        let map = map.map(cfg.map).map_err(OdometryError::Map)?;
        Ok(Self {
            cfg: cfg.clone(),
            scan,
            map,
            initializer: ImuInitializer::new(cfg.init),
            filter: None,
            wait: WaitReason::Collecting { samples: 0, span_s: 0.0 },
            scans: 0,
        })
    }

    /// The settings.
    pub fn config(&self) -> &OdometryConfig {
        &self.cfg
    }

    /// The map.
    pub fn map(&self) -> &VoxelMap<'a> {
        &self.map
    }

    /// The filter, once initialised.
    pub fn filter(&self) -> Option<&Eskf> {
        self.filter.as_ref()
    }

    /// Queues one IMU sample (time order; dropped ones are counted in the queue's stats).
    pub fn push_imu(&mut self, s: ImuSample) -> ImuPush {
        self.scan.imu.push(s)
    }

    /// Processes one scan without stage timing.
    pub fn process_scan(&mut self, scan: ScanView<'_>) -> ScanResult {
        self.process_scan_timed(scan, &mut NoClock)
    }

    /// Processes one scan; `clock` is read around each stage for [`StageTimes`].
    pub fn process_scan_timed(&mut self, scan: ScanView<'_>, clock: &mut impl Clock) -> ScanResult {
        let t0 = clock.now_ns();
        let end_ns = scan_end_ns(&scan);
        let mut times = StageTimes::default();
        // Propagate (or initialise) through the IMU samples up to the scan end.
        while let Some(s) = self.scan.imu.pop_until(end_ns) {
            match &mut self.filter {
                Some(f) => {
                    let _ = f.predict(&s);
                }
                None => match self.initializer.push(&s) {
                    InitStatus::Ready(init) => {
                        self.filter =
                            Some(Eskf::new(self.cfg.eskf, &init, self.cfg.ext_rot, self.cfg.ext_pos));
                    }
                    InitStatus::Waiting(w) => self.wait = w,
                },
            }
        }
        self.scans = self.scans.wrapping_add(1);
        let n = scan.points.len().min(PTS) as u32;
        let (pose, status, propagation) = match &mut self.filter {
            None => (PoseEstimate::identity(end_ns), Status::Initialising(self.wait), Default::default()),
            Some(f) => {
                let _ = f.predict_to(end_ns);
                let flags = f.take_flags();
                (PoseEstimate::from_filter(f), Status::ImuOnly(ImuOnlyReason::BuildingMap), flags)
            }
        };
        times.total_ns = clock.now_ns().saturating_sub(t0);
        ScanResult {
            scan_start_ns: scan.start_ns,
            pose,
            status,
            times,
            associations: AssociationCounts::default(),
            update: UpdateResult::default(),
            propagation,
            points: [n, 0],
        }
    }
}

/// The scan end: the latest point time (the start for an empty scan).
fn scan_end_ns(scan: &ScanView<'_>) -> u64 {
    let mut t_max = 0.0f32;
    for p in scan.points {
        if p.t.is_finite() && p.t > t_max {
            t_max = p.t;
        }
    }
    scan.start_ns.saturating_add((t_max as f64 * 1e9) as u64)
}

/// A monotonic clock the caller lends for stage timing (the core has none).
pub trait Clock {
    /// Now, nanoseconds (any origin).
    fn now_ns(&mut self) -> u64;
}

/// A clock that always reads 0 (no timing).
pub struct NoClock;

impl Clock for NoClock {
    fn now_ns(&mut self) -> u64 {
        0
    }
}
