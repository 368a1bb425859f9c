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
//! - [`OdometryConfig::vlp32c`] and [`OdometryConfig::os1_16`] are the paper's two setups; set
//!   the extrinsic ([`OdometryConfig::with_extrinsic`]) and the IMU noise (`eskf.noise`) of the
//!   actual rig.
//! - Without an IMU, [`OdometryConfig::motion`] = [`MotionModel::LIDAR_ONLY`] predicts each
//!   scan at the constant velocity of the last two (LiDAR-only, [`crate::motion_model`]): no
//!   IMU samples are needed, the first scan's frame is the world, and every result's
//!   propagation flags carry [`PropagationFlags::LIDAR_ONLY`].
//!
//! # One scan
//!
//! 1. Ring FALS estimates the normals of the first `PTS` points (the rest are counted in
//!    [`OdometryStats::points_overflow`]) on the raw scan, read in place, before undistortion,
//!    from the range image (skipped in [`AssociationMode::Plain`]).
//! 2. Points with a non-finite position or time, a time outside `[0, MAX_SCAN_SPAN_S]`, or a
//!    range outside `[blind, max_range]` are dropped (counted); the others are copied into the
//!    storage (their normals join them in step 3). The scan end is the latest kept point time.
//! 3. The IMU samples up to the scan end propagate the filter (or feed its initialisation); the
//!    state after every sample is a knot of the scan's [`ImuTrajectory`]; the filter is then
//!    propagated to the scan end, and every point is moved to the LiDAR frame at the scan end
//!    (backward propagation). Ring FALS (step 1) runs here, on two threads where the caller
//!    lends them beside the downsampling's search for the voxels of the moved points; the
//!    normals are then rotated as their points were.
//! 4. Voxel downsampling keeps one point per voxel with the averaged normal, in the Morton
//!    order of the voxels (nearby points together: the association's and the map's lookups
//!    then find the caches warm).
//! 5. The first scan after initialisation only builds the map. Later scans run the iterated
//!    update ([`Eskf::update`]) with the association of [`crate::association`]; the filter
//!    handles degenerate directions (the status says [`Status::Degraded`]). Under the
//!    measurement budget (`association.max_points`, 5,000 by default) at most that many
//!    downsampled points, evenly spread over their (Morton) order, are associated and
//!    measured, each standing for its share of the rest ([`crate::selection`]): the
//!    association's cost is per point, and a dense scan gives more constraints than the update
//!    needs (the reference subsamples every 4th raw point for the same reason).
//! 6. The scan goes into the voxel map at the updated pose (also when it had too few
//!    correspondences: the map must grow into new space).
//!
//! # Faults
//! - **IMU gaps** (spacing above `eskf.max_gap_s`): bridged holding the last sample, with
//!   inflated process noise (flagged `GAP` in [`ScanResult::propagation`]); while scans keep
//!   coming each bridges its own interval and corrects the state, however long the gap.
//!   Beyond `eskf.bridge_after_s` the bridge holds the rate and velocity between the last two
//!   updated scan ends (the LiDAR's own constant-velocity model, as LiDAR-only odometries
//!   predict), which also undistorts the bridged scan; after its update the scan is
//!   undistorted again with the motion that update found (the previous scan end to this one,
//!   constant rate, straight line) and updated again from the same prediction, twice.
//! - **IMU outliers** (beyond the full scale, lone spikes, lone stamps far ahead): dropped by
//!   [`crate::imu_guard`] before the queue.
//! - **Forward jumps** (the filter's time stepping by more than `eskf.max_hold_s`): re-seeded at the sample after the
//!   jump: the position moves on at the last velocity, the attitude at the last rate, and the
//!   position, velocity and attitude uncertainties grow by the "rough start" sigmas of
//!   `eskf.initial` (position by `rough_vel` times the gap), so the next scan can re-localise
//!   in the map. The scan reports [`Status::Reinitialising`].
//! - **Reversals**: single samples earlier than the last are dropped by the queue (counted in
//!   its stats). A clock that went back for good (more than [`CLOCK_RESET_SAMPLES`] samples in a
//!   row earlier than the last by over `max_hold_s`) restarts the odometry: queue, filter and map
//!   are cleared and the IMU initialisation runs again.
//! - **Too few correspondences** (fewer than `eskf.min_measurements`): the scan is IMU-only, the
//!   covariance keeps growing, the status says [`Status::ImuOnly`].
//! - **Empty scans** (nothing left after step 2 or 4): IMU-only, [`ImuOnlyReason::EmptyScan`].
//! - **A non-finite state** (absurd IMU values): full restart, [`ReinitReason::NonFinite`].
//!
//! Nothing here allocates, reads a clock (the caller may lend one) or panics on any input.

use nalgebra::{Matrix3, UnitQuaternion, Vector3};

// Re-exported: the odometry's paths to these stay valid.
pub use crate::association::AssociationMode;
pub use crate::clock::{Clock, NoClock};

use crate::association::{AssociationConfig, Correspondence, KNN_CHUNK, KnnScratch, ScanAssociation};
use crate::downsample::{DownsampleConfig, INVALID_NORMAL, VoxelDownsampler, normal_is_valid};
use crate::eskf::{Eskf, EskfConfig, Predicted, PropagationFlags, UpdateOutcome, UpdateResult, idx};
use crate::free_space::{FreeSpaceConfig, FreeSpaceImage, Verdict};
use crate::imu::{
    ImuDrop, ImuInitConfig, ImuInitializer, ImuPush, ImuQueue, ImuSample, InitStatus, WaitReason,
};
use crate::imu_guard::{ImuGuard, ImuGuardConfig};
use crate::motion_model::{ConstantVelocity, MotionModel};
use crate::moving_objects::MovingObjects;
use crate::output::{
    AssociationCounts, BridgeReason, ImuOnlyReason, Integrity, PoseEstimate, ReinitReason, ScanResult,
    StageTimes, Status,
};
use crate::parallel::{Arrangement, Parallel, Sequential};
use crate::range_image::RangeImageLayout;
use crate::relocalise::{self, Relocalisation, RelocaliseConfig};
use crate::ring_fals::{PointNormal, RingFals, RingFalsConfig, RingTable, TableError, storage_pixels};
use crate::scan::{ScanPoint, ScanView};
use crate::so3;
use crate::standstill::{ImuWindow, StandstillConfig};
use crate::time_offset::{self, TimeOffset, TimeOffsetConfig, TimeOffsetEstimate};
use crate::undistort::{ImuTrajectory, NormalRotations};
use crate::voxel_map::{
    MapConfig, MapError, MapPoint, MapStorage, Neighbours, PRESET_INDEX_SLOTS, PRESET_POOL_VOXELS, Suspects,
    VoxelMap,
};

/// IMU samples queued between two scans (200 Hz x 1 s, or 1 kHz x 0.25 s).
pub const IMU_QUEUE: usize = 256;
/// IMU knots kept for the undistortion of one scan.
pub const TRAJECTORY_KNOTS: usize = 64;

/// Through an IMU gap (a bridged scan), how many times the scan is undistorted again with the
/// motion its update found and updated again. Each pass halves the error of the bridge's
/// prediction but weighs the previous scan end's error more (the undistortion starts there):
/// 2 passes on the 2 s gap of the handheld walk 2.1x the clean ATE, 1 pass 3.1x, 3 passes
/// 17x (the scan ends' errors alternate and grow).
const BRIDGE_REUNDISTORT_PASSES: usize = 2;
/// Scans after a gap of either sensor that re-localise without the integrity check.
pub const RECOVERY_SCANS: u32 = 5;
/// A scan ending this long after the previous one follows a LiDAR gap (reported as
/// [`Status::Bridged`]), s.
pub const LIDAR_GAP_S: f64 = 0.5;
/// Points later than this after the scan start are dropped (a scan lasts 0.1 s at 10 Hz), s.
pub const MAX_SCAN_SPAN_S: f32 = 1.0;
/// Consecutive samples that went back in time by more than `max_hold_s` before the odometry
/// takes it as a clock reset and restarts.
pub const CLOCK_RESET_SAMPLES: u32 = 10;

/// The per-scan integrity check, at the predicted pose (the update's first association, before
/// the update pulls the pose towards the scan): the normalised innovation (`Σ r²/R` per
/// accepted residual) against its running mean, and of the measured points that found map
/// surfaces near them, the share that matched against its running mean. A wrong estimate or
/// scan (a bad stamp, another world's data, a divergence) puts the points beside the surfaces:
/// the innovation jumps (50-120 against 0.2-0.3 on the handheld walk with another world's
/// scans; at most 6.3x its mean on the clean scenarios) or the share collapses, while the
/// status would still say `ok`. Points with no map near them (new space) do not count, so
/// driving into the unknown is not "lost". Only where the map usually matches well (the mean
/// share at least `min_mean`): in open sky the share sinks slowly to a few percent on sparse,
/// far surfaces and the innovation of a few dozen residuals swings, and neither says anything.
/// A scan whose update ends agreeing (the last association's share and innovation back within
/// the bounds: a prediction that drifted, e.g. through a gap) is not low.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct IntegrityConfig {
    /// A scan whose share is below this ...
    pub min_share: f32,
    /// ... and below this fraction of the running mean of the agreeing scans' shares ...
    pub drop_ratio: f32,
    /// A scan whose normalised innovation is above this multiple of the agreeing scans'
    /// running mean ...
    pub nis_ratio: f32,
    /// ... and above this is "low" too ...
    pub nis_floor: f32,
    /// ... both only while the mean share is at least this (where the map usually matches
    /// well) ...
    pub min_mean: f32,
    /// ... with at least this many points near the map is "low".
    pub min_near: u32,
    /// This many low scans in a row: [`Status::Lost`] (0 disables the check).
    pub lost_scans: u32,
    /// Lost for this many scans more: the odometry starts over (0: never).
    pub restart_after: u32,
    /// The search in the map after a LiDAR gap and while lost ([`crate::relocalise`]).
    pub relocalise: RelocaliseConfig,
}

impl IntegrityConfig {
    /// The defaults (see the field docs and `tests/odometry_faults.rs`).
    pub const DEFAULT: IntegrityConfig = IntegrityConfig {
        min_share: 0.2,
        drop_ratio: 0.35,
        nis_ratio: 10.0,
        nis_floor: 4.0,
        min_mean: 0.5,
        min_near: 100,
        lost_scans: 3,
        restart_after: 50,
        relocalise: RelocaliseConfig::DEFAULT,
    };
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
    /// The association (checks, hierarchy, residual test, noise).
    pub association: AssociationConfig,
    /// The filter (noise, iterations, degeneracy, extrinsic estimation).
    pub eskf: EskfConfig,
    /// IMU initialisation.
    pub init: ImuInitConfig,
    /// IMU outlier rejection (full scale, spikes, stamps far ahead).
    pub imu_guard: ImuGuardConfig,
    /// The per-scan agreement with the map that decides `lost`.
    pub integrity: IntegrityConfig,
    /// Zero-velocity and zero-rate updates while the platform stands still.
    pub standstill: StandstillConfig,
    /// Removal of map voxels each scan sees through (moving objects' ghost trails).
    pub free_space: FreeSpaceConfig,
    /// The IMU–LiDAR time offset, estimated online ([`crate::time_offset`]).
    pub time_offset: TimeOffsetConfig,
    /// IMU from LiDAR rotation.
    pub ext_rot: UnitQuaternion<f64>,
    /// LiDAR origin in the IMU frame, m.
    pub ext_pos: Vector3<f64>,
    /// What predicts the pose between scans: the IMU, or without one a constant velocity
    /// ([`crate::motion_model`]).
    pub motion: MotionModel,
    /// Points nearer than this are ignored (the vehicle itself), m.
    pub blind: f32,
    /// Points farther than this are ignored, m.
    pub max_range: f32,
}

impl OdometryConfig {
    /// Velodyne VLP-32C (the paper's M2DGR setup): 0.4 m voxels for the scan and the map, 150 m
    /// range, full LOG-LIO association, identity extrinsic (set the rig's).
    pub fn vlp32c(layout: RangeImageLayout) -> Self {
        Self {
            mode: AssociationMode::Full,
            layout,
            ring_fals: RingFalsConfig::DEFAULT,
            downsample: DownsampleConfig { voxel: 0.4, ..DownsampleConfig::default() },
            map: MapConfig::VLP32C,
            association: AssociationConfig::DEFAULT,
            eskf: EskfConfig { min_measurements: 20, ..EskfConfig::default() },
            init: ImuInitConfig::default(),
            imu_guard: ImuGuardConfig::DEFAULT,
            integrity: IntegrityConfig::DEFAULT,
            standstill: StandstillConfig::DEFAULT,
            free_space: FreeSpaceConfig::DEFAULT,
            time_offset: TimeOffsetConfig::DEFAULT,
            ext_rot: UnitQuaternion::identity(),
            ext_pos: Vector3::zeros(),
            motion: MotionModel::Imu,
            blind: 0.5,
            max_range: 150.0,
        }
    }

    /// Ouster OS1-16 (the paper's NTU VIRAL setup): 0.5 m voxels, 100 m range.
    pub fn os1_16(layout: RangeImageLayout) -> Self {
        Self {
            downsample: DownsampleConfig { voxel: 0.5, ..DownsampleConfig::default() },
            map: MapConfig::OS1_16,
            max_range: 100.0,
            ..Self::vlp32c(layout)
        }
    }

    /// The same settings with the LiDAR-IMU extrinsic (IMU from LiDAR: `p_I = rot p_L + pos`).
    pub fn with_extrinsic(mut self, rot: UnitQuaternion<f64>, pos: Vector3<f64>) -> Self {
        self.ext_rot = rot;
        self.ext_pos = pos;
        self
    }

    /// The same settings with another motion model ([`MotionModel::LIDAR_ONLY`]: no IMU).
    pub fn with_motion(mut self, motion: MotionModel) -> Self {
        self.motion = motion;
        self
    }

    /// The same settings in another association mode.
    pub fn with_mode(mut self, mode: AssociationMode) -> Self {
        self.mode = mode;
        self
    }
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
/// pixels (see [`storage_pixels`]), `PTS` points per scan, `DS` downsampling slots (a power of
/// two; at most `3 DS / 4` voxels per scan).
pub struct ScanStorage<const PIX: usize, const PTS: usize, const DS: usize> {
    ring: RingFals<PIX>,
    table: RingTable,
    downsampler: VoxelDownsampler<DS>,
    points: [ScanPoint; PTS],
    normals: [PointNormal; PTS],
    normals3: [[f32; 3]; PTS],
    /// Each point's downsampling voxel (the downsampler's scratch).
    cell_of: [u32; PTS],
    imu: ImuQueue<IMU_QUEUE>,
    trajectory: ImuTrajectory<TRAJECTORY_KNOTS>,
    /// The normals' rotations of this scan ([`crate::undistort::NormalRotations`]).
    rotations: NormalRotations,
    corr: [Correspondence; DS],
    /// Three free-space images ([`crate::free_space`]), named by `free_turn`: this scan's nearest
    /// returns per coarse cell; the previous reference's ([`PrevScan`]: where its beams went
    /// through, something that is there now moved in); the one before it (`Odometry::old_scan`,
    /// `reference_every_s` to twice that old). A renewal rotates the names, not the images.
    frees: [FreeSpaceImage<PIX>; 3],
    /// Which of `frees` is this scan's, the previous reference's and the older one's
    /// ([`free_slot`]); zero at first, as every field, so that the storage is all zeros and a
    /// `static` of it takes no flash.
    free_turn: usize,
    /// Map voxels the last scan saw through, for this one to judge again.
    suspects: Suspects<SUSPECTS>,
    /// The scan's coarse cells, to grow moving points into their objects.
    objects: MovingObjects<DS>,
    queries: [[f32; 3]; KNN_CHUNK],
    neighbours: [Neighbours; KNN_CHUNK],
}

impl<const PIX: usize, const PTS: usize, const DS: usize> core::fmt::Debug for ScanStorage<PIX, PTS, DS> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("ScanStorage").field("pixels", &PIX).field("points", &PTS).field("slots", &DS).finish()
    }
}

impl<const PIX: usize, const PTS: usize, const DS: usize> Default for ScanStorage<PIX, PTS, DS> {
    fn default() -> Self {
        Self::new()
    }
}

/// A scan whose prediction held the last IMU sample longer than this (a 100 Hz IMU's period)
/// tells nothing of the time offset, ns.
const OFFSET_MAX_HOLD_NS: u64 = 10_000_000;

/// Map voxels one scan may find seen through for the next to judge again (24 KiB).
const SUSPECTS: usize = 2048;

/// The previous scan's pose (sensor from world rotation, sensor origin) and end time, for the
/// moving points of the next ([`crate::free_space`]).
#[derive(Clone, Copy, Debug)]
struct PrevScan {
    end_ns: u64,
    rot_t: Matrix3<f64>,
    origin: Vector3<f64>,
}

/// The caller's threads and their k-NN scratch ([`Odometry::set_parallel`]).
type ParallelSlot<'a> = Option<(&'a dyn Parallel, &'a mut [KnnScratch])>;

/// The image of `role` (0: this scan's, 1: the previous reference's, 2: the older one's) at
/// `turn`: each renewal advances the turn by one, so this scan's image becomes the previous
/// reference's, that one the older's, and the older's is written over by the next scan.
const fn free_slot(turn: usize, role: usize) -> usize {
    (turn + 3 - role) % 3
}

/// The two-thread stage's arrangements and the first in use, without and with a waiting
/// insertion: without one the normals' compaction and rotation start in pieces of their own
/// (Ring FALS's job is the longer there: a replay's scans 1-6 % shorter on the Intel Xeon,
/// 2026-12-07), with one in Ring FALS's job.
const STAGE_ARRANGEMENTS: [Arrangement; 2] = [Arrangement::with_arms(4, 2), Arrangement::with_arms(4, 0)];

/// A scan's map insertion waiting in the caller's buffer ([`Odometry::set_deferred_map`]).
#[derive(Clone, Copy, Debug)]
struct PendingInsert {
    origin: [f32; 3],
    stamp: u32,
    /// The first `points` of the buffer.
    points: usize,
}

/// A scan's clearing of the map, waiting with its insertion ([`Odometry::set_deferred_map`]):
/// what the free-space image `image` (of that scan, kept until then) sees through leaves the
/// map before the scan's points go in, as it did at once.
#[derive(Clone, Copy, Debug)]
struct PendingClear {
    /// The sensor's origin (world) and the world-to-sensor rotation.
    origin: [f32; 3],
    rt: [[f32; 3]; 3],
    /// Voxels judged ([`VoxelMap::clear_seen_through`]).
    budget: usize,
    /// The index in `frees` of the scan's image.
    image: usize,
}

/// The clearing `c` of the map, its judgements in pieces on `par`'s threads (the voxels'
/// scratch, `cell_of`, is free whenever it runs).
fn run_clear<const PIX: usize>(
    c: PendingClear,
    map: &mut VoxelMap<'_>,
    (frees, sus, cell_of): (&[FreeSpaceImage<PIX>], &mut Suspects<SUSPECTS>, &mut [u32]),
    fsc: &FreeSpaceConfig,
    par: &dyn Parallel,
    stats: &mut OdometryStats,
) {
    let Some(free) = frees.get(c.image) else { return };
    let (rt, origin) = (c.rt, c.origin);
    let judge = |q: [f32; 3], slack| {
        let d = [q[0] - origin[0], q[1] - origin[1], q[2] - origin[2]];
        let l: [f32; 3] = core::array::from_fn(|i| rt[i][0] * d[0] + rt[i][1] * d[1] + rt[i][2] * d[2]);
        free.verdict_with_slack(l, slack, fsc)
    };
    let cleared = map.clear_seen_through_with(origin, fsc.max_range, c.budget, sus, judge, par, cell_of);
    stats.cleared = stats.cleared.saturating_add(u64::from(cleared));
}

/// Inserts the waiting points, if any (the same call as an insertion without waiting).
fn insert_pending(map: &mut VoxelMap<'_>, pending: &mut Option<PendingInsert>, buf: Option<&[MapPoint]>) {
    if let (Some(p), Some(buf)) = (pending.take(), buf) {
        // Cannot fail: as at the insertion (a finite origin, stamps only increasing).
        let _ = map.insert_slice(&buf[..p.points], p.origin, p.stamp);
    }
}

impl<const PIX: usize, const PTS: usize, const DS: usize> ScanStorage<PIX, PTS, DS> {
    /// The measurements of the first `measured` points (of `still` points the budget chose
    /// from) against `map`, split over `parallel`'s threads where given.
    fn association<'x, 'm, C: Clock>(
        &'x mut self,
        map: &'x VoxelMap<'m>,
        cfg: &'x OdometryConfig,
        (measured, still): (usize, usize),
        parallel: &'x mut ParallelSlot<'_>,
        clock: &'x mut C,
    ) -> ScanAssociation<'x, 'm, C> {
        let assoc = ScanAssociation::new(
            map,
            &cfg.association,
            cfg.mode,
            &self.points[..measured],
            &self.normals3[..measured],
            &mut self.corr[..],
            &mut self.queries,
            &mut self.neighbours,
            clock,
        );
        // Under a budget each measured point stands for its share of the rest.
        let assoc = if measured > 0 && still > measured {
            assoc.standing_for(still as f64 / measured as f64)
        } else {
            assoc
        };
        match parallel {
            Some((p, scratch)) => assoc.with_parallel(*p, scratch),
            None => assoc,
        }
    }

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
            cell_of: [0; PTS],
            imu: ImuQueue::new(),
            trajectory: ImuTrajectory::new(),
            rotations: NormalRotations::new(),
            corr: [Correspondence::NONE; DS],
            frees: [FreeSpaceImage::new(), FreeSpaceImage::new(), FreeSpaceImage::new()],
            free_turn: 0,
            suspects: Suspects::new(),
            objects: MovingObjects::new(),
            queries: [[0.0; 3]; KNN_CHUNK],
            neighbours: [Neighbours::new(); KNN_CHUNK],
        }
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

impl<const PIX: usize, const PTS: usize, const DS: usize, const V: usize, const I: usize> core::fmt::Debug
    for OdometryStorage<PIX, PTS, DS, V, I>
{
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("OdometryStorage").field("scan", &self.scan).field("voxels", &V).finish()
    }
}

impl<const PIX: usize, const PTS: usize, const DS: usize, const V: usize, const I: usize> Default
    for OdometryStorage<PIX, PTS, DS, V, I>
{
    fn default() -> Self {
        Self::new()
    }
}

impl<const PIX: usize, const PTS: usize, const DS: usize, const V: usize, const I: usize>
    OdometryStorage<PIX, PTS, DS, V, I>
{
    /// Empty storage.
    pub const fn new() -> Self {
        Self { scan: ScanStorage::new(), map: MapStorage::new() }
    }

    /// Bytes this storage takes (docs/voxel-map.md states the default pool's).
    pub const fn bytes() -> usize {
        core::mem::size_of::<Self>()
    }

    /// An odometry over this storage (the previous contents are discarded).
    pub fn odometry(&mut self, cfg: &OdometryConfig) -> Result<Odometry<'_, PIX, PTS, DS>, OdometryError> {
        Odometry::new(&mut self.scan, &mut self.map, cfg)
    }
}

/// Storage for a Velodyne VLP-32C (32 x 1800, 57,600 points per scan) with the preset map pool.
pub type Vlp32cStorage =
    OdometryStorage<{ storage_pixels(32, 1800) }, 65536, 32768, PRESET_POOL_VOXELS, PRESET_INDEX_SLOTS>;
/// Storage for an Ouster OS1-16 (16 x 1024) with the preset map pool.
pub type Os1_16Storage =
    OdometryStorage<{ storage_pixels(16, 1024) }, 16384, 16384, PRESET_POOL_VOXELS, PRESET_INDEX_SLOTS>;

/// Counters over the odometry's life (and of the last scan).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct OdometryStats {
    /// Scans processed.
    pub scans: u32,
    /// Points beyond the storage's `PTS` (not processed), all scans.
    pub points_overflow: u64,
    /// Points dropped for a non-finite or out-of-range position or time, all scans.
    pub points_invalid: u64,
    /// Points beyond `PTS` in the last scan.
    pub last_overflow: u32,
    /// Points dropped as invalid in the last scan.
    pub last_invalid: u32,
    /// Re-seeds after an IMU jump and full restarts.
    pub reinitialisations: u32,
    /// Scans that did not update the state (after initialisation, map building excluded).
    pub imu_only: u32,
    /// Scans with degenerate directions.
    pub degraded: u32,
    /// Samples that went back in time by more than `max_hold_s` in a row (clock reset watch).
    pub reversed_run: u32,
    /// Scans reported [`Status::Lost`].
    pub lost: u32,
    /// Re-localisations that moved the prediction ([`crate::relocalise`]).
    pub relocalisations: u32,
    /// Scans that stood still and gave zero-velocity updates ([`crate::standstill`]).
    pub standstill: u32,
    /// Map voxels removed because a scan saw through them ([`crate::free_space`]).
    pub cleared: u64,
    /// Points kept out of the association and the map because the previous scan saw through
    /// where they are (moving objects; [`crate::free_space`]).
    pub moving: u64,
    /// IMU samples dropped because the estimated time offset moved back and put them before
    /// samples already queued ([`crate::time_offset`]).
    pub realigned: u32,
}

/// The LiDAR-inertial odometry over caller-owned storage.
pub struct Odometry<'a, const PIX: usize, const PTS: usize, const DS: usize> {
    cfg: OdometryConfig,
    scan: &'a mut ScanStorage<PIX, PTS, DS>,
    map: VoxelMap<'a>,
    initializer: ImuInitializer,
    filter: Option<Eskf>,
    wait: WaitReason,
    stamp: u32,
    restart_pending: bool,
    stats: OdometryStats,
    /// Points of the last scan after undistortion and downsampling (the front of `scan.points`).
    last_kept: usize,
    guard: ImuGuard,
    /// A jump happened in [`Self::propagate_imu`]: the next scan reports it.
    jumped: bool,
    /// The end of the last scan processed after the initialisation.
    last_scan_end_ns: Option<u64>,
    /// The last scan end's time, attitude and position (for the motion a bridge holds).
    last_end: Option<(u64, UnitQuaternion<f64>, Vector3<f64>)>,
    /// The last re-localisation search (whether or not it moved the prediction).
    last_relocalisation: Option<Relocalisation>,
    /// The previous reference's pose, when its image is in `scan.frees[free_slot(scan.free_turn, 1)]`.
    prev_scan: Option<PrevScan>,
    /// The reference before it, when its image is in `scan.frees[free_slot(scan.free_turn, 2)]`: the moving points are
    /// judged against it, so that an object approaching slowly has moved by its speed times at
    /// least `reference_every_s` (the newer reference is one scan to that old).
    old_scan: Option<PrevScan>,
    /// The caller's threads and their k-NN scratch ([`Odometry::set_parallel`]).
    parallel: ParallelSlot<'a>,
    /// The caller's buffer for a scan's map points whose insertion waits for the next scan
    /// ([`Odometry::set_deferred_map`]).
    deferred: Option<&'a mut [MapPoint]>,
    /// The caller's buffer the downsampling's kept points are gathered into on the threads
    /// ([`Odometry::set_gather_buffer`]).
    gather: Option<&'a mut [ScanPoint]>,
    /// The insertion waiting in `deferred`, if any.
    pending: Option<PendingInsert>,
    /// The clearing that goes before it, if any.
    pending_clear: Option<PendingClear>,
    /// Running means of the agreeing scans' shares of matching points and innovations.
    share_mean: Option<f32>,
    nis_mean: Option<f32>,
    /// Low scans in a row.
    low_run: u32,
    /// Scans left that re-localise after a gap, not judged by the integrity check.
    recovering: u32,
    /// The IMU samples of the scan being processed (for the standstill test).
    window: ImuWindow,
    /// How long the platform has stood still in a row, seconds.
    still_s: f64,
    /// The IMU–LiDAR time offset's estimation; its applied offset shifts every IMU stamp.
    offset: TimeOffset,
    /// After the applied offset moved back: IMU samples up to this stamp are dropped.
    realign_until_ns: Option<u64>,
    /// How the jobs of Ring FALS's stage go together on two threads, without and with a
    /// waiting map insertion.
    balance: [Arrangement; 2],
}

impl<const PIX: usize, const PTS: usize, const DS: usize> core::fmt::Debug for Odometry<'_, PIX, PTS, DS> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("Odometry")
            .field("mode", &self.cfg.mode)
            .field("initialised", &self.filter.is_some())
            .field("map_voxels", &self.map.len())
            .field("stats", &self.stats)
            .finish()
    }
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
        if !(cfg.downsample.voxel.is_finite() && cfg.downsample.voxel > 0.0) {
            return Err(OdometryError::InvalidConfig("downsample.voxel"));
        }
        if !DS.is_power_of_two() || DS < 4 {
            return Err(OdometryError::InvalidConfig("storage: DS must be a power of two"));
        }
        cfg.association.validate().map_err(OdometryError::InvalidConfig)?;
        if !cfg.imu_guard.is_valid() {
            return Err(OdometryError::InvalidConfig("imu_guard"));
        }
        cfg.time_offset.validate().map_err(OdometryError::InvalidConfig)?;
        let ext_ok =
            cfg.ext_rot.coords.iter().all(|v| v.is_finite()) && cfg.ext_pos.iter().all(|v| v.is_finite());
        if !ext_ok {
            return Err(OdometryError::InvalidConfig("extrinsic"));
        }
        scan.table.build(&cfg.layout, &cfg.ring_fals).map_err(OdometryError::RingTable)?;
        // A layout the image cannot hold judges nothing: the map then keeps everything.
        for free in &mut scan.frees {
            let _ = free.set_layout(&cfg.layout, cfg.free_space.columns);
        }
        scan.imu.clear();
        let map = map.map(cfg.map).map_err(OdometryError::Map)?;
        Ok(Self {
            cfg: OdometryConfig {
                // The filter knows where the gyro clips (the guard's full scale).
                eskf: EskfConfig { gyro_full_scale: f64::from(cfg.imu_guard.gyro_full_scale), ..cfg.eskf },
                ..cfg.clone()
            },
            scan,
            map,
            initializer: ImuInitializer::new(cfg.init),
            filter: None,
            wait: WaitReason::Collecting { samples: 0, span_s: 0.0 },
            stamp: 0,
            restart_pending: false,
            stats: OdometryStats::default(),
            last_kept: 0,
            guard: ImuGuard::new(cfg.imu_guard),
            jumped: false,
            last_scan_end_ns: None,
            last_end: None,
            last_relocalisation: None,
            prev_scan: None,
            old_scan: None,
            parallel: None,
            deferred: None,
            gather: None,
            pending: None,
            pending_clear: None,
            share_mean: None,
            nis_mean: None,
            low_run: 0,
            recovering: 0,
            window: ImuWindow::default(),
            still_s: 0.0,
            offset: TimeOffset::new(cfg.time_offset),
            realign_until_ns: None,
            balance: STAGE_ARRANGEMENTS,
        })
    }

    /// The settings.
    pub fn config(&self) -> &OdometryConfig {
        &self.cfg
    }

    /// The map; without the last scan's points while their insertion waits
    /// ([`Self::set_deferred_map`]; [`Self::flush_map`] puts them in).
    pub fn map(&self) -> &VoxelMap<'a> {
        &self.map
    }

    /// The filter, once initialised.
    pub fn filter(&self) -> Option<&Eskf> {
        self.filter.as_ref()
    }

    /// The IMU–LiDAR time offset: what is applied to the IMU stamps and what the scans say.
    pub fn time_offset(&self) -> TimeOffsetEstimate {
        TimeOffsetEstimate { realigned: self.stats.realigned, ..self.offset.estimate() }
    }

    /// Counters.
    pub fn stats(&self) -> OdometryStats {
        self.stats
    }

    /// The IMU queue's counters (accepted, reversed, duplicate, non-finite, overwritten).
    pub fn imu_stats(&self) -> crate::imu::ImuQueueStats {
        self.scan.imu.stats()
    }

    /// The last scan's points: undistorted to the LiDAR frame at the scan end and downsampled
    /// (empty when the scan did not reach the map). The points judged moving are among them,
    /// last: the map left them out, but a robot's obstacle view needs them. Live outputs
    /// publish them; world frame = the result's [`PoseEstimate::lidar_pose`] applied to them.
    pub fn scan_points(&self) -> &[ScanPoint] {
        &self.scan.points[..self.last_kept]
    }

    /// Switches the association mode from the next scan on.
    pub fn set_mode(&mut self, mode: AssociationMode) {
        self.cfg.mode = mode;
    }

    /// Takes one IMU sample: the outlier guard first ([`crate::imu_guard`]; a suspect sample
    /// is `Held` until the next one decides), then the queue (time order; dropped ones are
    /// counted in the queue's stats).
    pub fn push_imu(&mut self, s: ImuSample) -> ImuPush {
        // The estimated time offset moves the sample onto the LiDAR's clock.
        let shift = self.offset.applied_ns();
        let s = ImuSample { t_ns: s.t_ns.saturating_add_signed(shift), ..s };
        if let Some(until) = self.realign_until_ns {
            if s.t_ns <= until {
                self.stats.realigned = self.stats.realigned.saturating_add(1);
                return ImuPush::Dropped(ImuDrop::Realigned);
            }
            self.realign_until_ns = None;
        }
        let before = self.guard.stats().beyond_full_scale;
        let mut result = ImuPush::Held;
        for r in self.guard.push(s) {
            let pushed = self.queue_imu(r);
            if r == s {
                result = pushed;
            }
        }
        if self.guard.stats().beyond_full_scale != before {
            return ImuPush::Dropped(ImuDrop::BeyondFullScale);
        }
        result
    }

    /// Integrates the queued IMU samples up to `until_ns` into the filter (or the
    /// initialisation) without a scan: through a LiDAR gap the IMU carries the state, with its
    /// honest covariance growth, instead of the samples piling up and being lost. Call it only
    /// for samples before the start of any scan still to come (their knots undistort it).
    /// Returns the samples consumed.
    pub fn propagate_imu(&mut self, until_ns: u64) -> u32 {
        let mut n = 0u32;
        while let Some(s) = self.scan.imu.pop_until(until_ns) {
            n = n.saturating_add(1);
            if self.cfg.motion.is_lidar_only() {
                continue;
            }
            match &mut self.filter {
                Some(f) => {
                    let before = f.time_ns();
                    if let Predicted::Jump { .. } = f.predict(&s) {
                        reseed_after_jump(f, before);
                        self.stats.reinitialisations = self.stats.reinitialisations.saturating_add(1);
                        self.jumped = true;
                    }
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
        n
    }

    /// Splits the association's searches over the caller's threads (`parallel`, with one
    /// k-NN scratch per thread beyond the first): the results are bit-identical to one
    /// thread's, so this is a speed setting only. Without it everything runs on the calling
    /// thread.
    pub fn set_parallel(&mut self, parallel: &'a dyn Parallel, scratch: &'a mut [KnnScratch]) {
        self.parallel = Some((parallel, scratch));
    }

    /// With [`Self::set_parallel`]'s threads, lets a scan's map insertion wait in `buffer` (at
    /// least `DS` points; a smaller one defers only scans that fit) until the next scan, whose
    /// Ring FALS and voxel search it then runs beside: the pose is returned before the insertion,
    /// and the insertion takes no time of its own. The free-space clearing that goes before it
    /// waits too (for the caller's [`Self::flush_map`] between scans, else the next scan's
    /// start, before that scan's marks write over its image). The map and every result are the
    /// same, bit for bit; only [`Self::map`] may lag one scan until [`Self::flush_map`].
    pub fn set_deferred_map(&mut self, buffer: &'a mut [MapPoint]) {
        self.flush_map();
        self.deferred = Some(buffer);
    }

    /// With [`Self::set_parallel`]'s threads, lets the downsampling gather its kept points into
    /// `buffer` (at least [`VoxelDownsampler::max_voxels`] of the storage's `DS`, else unused)
    /// in pieces on the threads, then copy them back, instead of moving them into place on one
    /// thread. The same bits.
    pub fn set_gather_buffer(&mut self, buffer: &'a mut [ScanPoint]) {
        self.gather = Some(buffer);
    }

    /// The last scan's clearing of the map, if it waits: before anything else reads the map or
    /// the next scan's marks write over its free-space image.
    fn clear_pending(&mut self) {
        let Some(c) = self.pending_clear.take() else { return };
        let par = match &self.parallel {
            Some((p, _)) => *p,
            None => &Sequential,
        };
        let st = &mut *self.scan;
        let scratch = (&st.frees[..], &mut st.suspects, &mut st.cell_of[..]);
        run_clear(c, &mut self.map, scratch, &self.cfg.free_space, par, &mut self.stats);
    }

    /// Inserts the last scan's points if their insertion is waiting ([`Self::set_deferred_map`]),
    /// so that [`Self::map`] holds every scan processed.
    pub fn flush_map(&mut self) {
        self.clear_pending();
        insert_pending(&mut self.map, &mut self.pending, self.deferred.as_deref());
    }

    /// The last re-localisation search ([`crate::relocalise`]), whether or not it moved the
    /// prediction; `None` before the first.
    pub fn last_relocalisation(&self) -> Option<Relocalisation> {
        self.last_relocalisation
    }

    /// The outlier guard's counts.
    pub fn imu_guard_stats(&self) -> crate::imu_guard::ImuGuardStats {
        self.guard.stats()
    }

    fn queue_imu(&mut self, s: ImuSample) -> ImuPush {
        let r = self.scan.imu.push(s);
        let hold_ns = (self.cfg.eskf.max_hold_s.max(0.0) * 1e9) as u64;
        let far_back = matches!(r, ImuPush::Dropped(ImuDrop::Reversed))
            && self.scan.imu.last_time_ns().is_some_and(|last| s.t_ns.saturating_add(hold_ns) < last);
        if far_back {
            self.stats.reversed_run = self.stats.reversed_run.saturating_add(1);
            if self.stats.reversed_run >= CLOCK_RESET_SAMPLES {
                // The IMU clock went back for good: start over on the new clock.
                self.scan.imu.clear();
                self.guard.reset();
                self.restart_pending = true;
                self.stats.reversed_run = 0;
                return self.scan.imu.push(s);
            }
        } else if !matches!(r, ImuPush::Dropped(_)) {
            self.stats.reversed_run = 0;
        }
        r
    }

    /// Processes one scan without stage timing.
    pub fn process_scan(&mut self, scan: ScanView<'_>) -> ScanResult {
        self.process_scan_timed(scan, &mut NoClock)
    }

    /// Forgets the filter and the map; the IMU initialisation starts again.
    fn restart(&mut self) {
        // What came before still goes in first (the map's counters stay those of one thread).
        self.flush_map();
        self.filter = None;
        self.initializer.reset();
        self.map.clear();
        self.wait = WaitReason::Collecting { samples: 0, span_s: 0.0 };
        self.last_scan_end_ns = None;
        self.last_end = None;
        self.prev_scan = None;
        self.old_scan = None;
        self.scan.suspects.clear();
        self.scan.objects.forget_tracks();
        self.share_mean = None;
        self.nis_mean = None;
        self.low_run = 0;
        self.still_s = 0.0;
        self.stats.reinitialisations = self.stats.reinitialisations.saturating_add(1);
    }

    /// Processes one scan; `clock` is read around each stage for [`StageTimes`].
    pub fn process_scan_timed(&mut self, scan: ScanView<'_>, clock: &mut impl Clock) -> ScanResult {
        let t0 = clock.now_ns();
        let mut times = StageTimes::default();
        self.last_kept = 0;
        self.stats.scans = self.stats.scans.saturating_add(1);
        let mut reinit: Option<ReinitReason> = None;
        if core::mem::take(&mut self.jumped) {
            reinit = Some(ReinitReason::ImuJump);
        }
        if self.restart_pending {
            self.restart_pending = false;
            self.restart();
            reinit = Some(ReinitReason::ImuJump);
        }
        let use_normals = self.cfg.mode != AssociationMode::Plain;
        // A waiting insertion goes in beside Ring FALS and the voxel search (step 3) where
        // there is a second thread; else now.
        let par_width = self.parallel.as_ref().map_or(1, |(p, _)| p.width());
        if !(par_width > 1 && self.filter.is_some()) {
            self.flush_map();
        } else {
            // Its clearing goes first, on the threads.
            self.clear_pending();
        }

        // 1. Copy the valid points into the storage (their normals come in step 3).
        let n_in = scan.points.len();
        let n = n_in.min(PTS);
        let overflow = (n_in - n).min(u32::MAX as usize) as u32;
        let st = &mut *self.scan;
        let input = &scan.points[..n];
        let (blind2, max2) = (self.cfg.blind * self.cfg.blind, self.cfg.max_range * self.cfg.max_range);
        let valid = |p: &ScanPoint| {
            let [x, y, z] = p.xyz;
            let r2 = x * x + y * y + z * z;
            r2.is_finite() && r2 >= blind2 && r2 <= max2 && p.t >= 0.0 && p.t <= MAX_SCAN_SPAN_S
        };
        let mut m = 0usize;
        let mut t_max = 0.0f32;
        // The valid points before the input's middle: where the second half's normals go
        // when their compaction runs in two pieces (step 3).
        let n_half = n / 2;
        let mut m_half = 0usize;
        for (i, &p) in input.iter().enumerate() {
            if i == n_half {
                m_half = m;
            }
            if !valid(&p) {
                continue;
            }
            st.points[m] = p;
            if p.t > t_max {
                t_max = p.t;
            }
            m += 1;
        }
        let invalid = (n - m) as u32;
        self.stats.last_overflow = overflow;
        self.stats.last_invalid = invalid;
        self.stats.points_overflow = self.stats.points_overflow.saturating_add(u64::from(overflow));
        self.stats.points_invalid = self.stats.points_invalid.saturating_add(u64::from(invalid));
        let end_ns = scan.start_ns.saturating_add((f64::from(t_max) * 1e9) as u64);
        let npoints = [n_in.min(u32::MAX as usize) as u32, 0];

        // 3. Propagate (or initialise) through the IMU samples up to the scan end.
        let mut flags = PropagationFlags::default();
        st.trajectory.clear(scan.start_ns);
        if let Some(f) = &self.filter {
            st.trajectory.push(f.time_ns(), f.state());
        }
        self.window.clear();
        if let MotionModel::ConstantVelocity(cv) = self.cfg.motion {
            predict_without_imu(&mut self.filter, st, &self.cfg, cv, scan.start_ns, end_ns);
            flags.0 |= PropagationFlags::LIDAR_ONLY;
        }
        while let Some(s) = st.imu.pop_until(end_ns) {
            self.window.push(&s);
            match &mut self.filter {
                Some(f) => {
                    let before = f.time_ns();
                    if let Predicted::Jump { .. } = f.predict(&s) {
                        flags.0 |= f.take_flags().0;
                        reseed_after_jump(f, before);
                        st.trajectory.clear(scan.start_ns);
                        reinit = Some(ReinitReason::ImuJump);
                        self.stats.reinitialisations = self.stats.reinitialisations.saturating_add(1);
                    }
                    st.trajectory.push(f.time_ns(), f.state());
                }
                None => match self.initializer.push(&s) {
                    InitStatus::Ready(init) => {
                        let f = Eskf::new(self.cfg.eskf, &init, self.cfg.ext_rot, self.cfg.ext_pos);
                        st.trajectory.clear(scan.start_ns);
                        st.trajectory.push(f.time_ns(), f.state());
                        self.filter = Some(f);
                    }
                    InitStatus::Waiting(w) => self.wait = w,
                },
            }
        }
        let Some(f) = self.filter.as_mut() else {
            times.total_ns = clock.now_ns().saturating_sub(t0);
            let status = match reinit {
                Some(r) => Status::Reinitialising(r),
                None => Status::Initialising(self.wait),
            };
            return ScanResult {
                scan_start_ns: scan.start_ns,
                pose: PoseEstimate::identity(end_ns),
                status,
                times,
                associations: AssociationCounts::default(),
                update: UpdateResult::default(),
                propagation: flags,
                points: npoints,
                integrity: Integrity::default(),
            };
        };
        let before = f.time_ns();
        if let Predicted::Jump { .. } = f.predict_to(end_ns) {
            flags.0 |= f.take_flags().0;
            reseed_after_jump(f, before);
            st.trajectory.clear(scan.start_ns);
            reinit = Some(ReinitReason::ImuJump);
            self.stats.reinitialisations = self.stats.reinitialisations.saturating_add(1);
        }
        st.trajectory.push(f.time_ns(), f.state());
        flags.0 |= f.take_flags().0;
        if !f.state().is_finite() || !f.covariance().iter().all(|v| v.is_finite()) {
            self.restart();
            times.total_ns = clock.now_ns().saturating_sub(t0);
            return ScanResult {
                scan_start_ns: scan.start_ns,
                pose: PoseEstimate::identity(end_ns),
                status: Status::Reinitialising(ReinitReason::NonFinite),
                times,
                associations: AssociationCounts::default(),
                update: UpdateResult::default(),
                propagation: flags,
                points: npoints,
                integrity: Integrity::default(),
            };
        }
        // Through a LiDAR gap the IMU alone carried the state: its position variance grows with
        // what dead reckoning really drifts, and the first scan after it searches the map that
        // wide. (Widening the velocity too made the gaps of 2 and 5 s worse: 1.3x and 1.6x the
        // clean ATE against 1.1x and 1.4x.)
        let rc = self.cfg.integrity.relocalise;
        let gap_s = self.last_scan_end_ns.map_or(0.0, |t| end_ns.saturating_sub(t) as f64 * 1e-9);
        let after_long_gap = rc.after_gap_s > 0.0 && gap_s > rc.after_gap_s;
        if after_long_gap && reinit.is_none() {
            let a = rc.dead_reckoning_acc_std;
            let d = 0.5 * a * gap_s * gap_s;
            f.widen_position(d * d);
        }
        // 3. Every point to the LiDAR frame at the scan end (backward propagation), with its
        // Ring FALS normal (on the raw scan, the caller's points); then the downsampling's voxels.
        // With a second thread the normals are estimated beside the voxels' search (neither
        // needs the other): the points are moved first and the normals rotated after. The normals
        // turn by the table of [`crate::undistort::NormalRotations`] (its rotation nearest each
        // point's time, to 0.4 mrad of the exact one), on one thread in the points' own pass:
        // the same bits either way.
        let t_p = clock.now_ns();
        let ds_cfg = self.cfg.downsample;
        let par = match &self.parallel {
            Some((p, _)) if p.width() > 1 => Some(*p),
            _ => None,
        };
        let overlap = use_normals && par.is_some();
        if use_normals && !overlap {
            ring_fals(&mut st.ring, &st.table, input, &mut st.normals[..n]);
        }
        let t_n0 = clock.now_ns();
        if !overlap {
            fill_normals(use_normals, input, &st.normals[..n], &mut st.normals3[..m], valid);
        }
        // The normals turn with the table's rotations (on any number of threads the same).
        let rotations = use_normals
            && m > 0
            && st.trajectory.normal_rotations(f.state(), 0.0, t_max, &mut st.rotations).is_ok();
        let rotations = rotations.then_some(&st.rotations);
        if m > 0 {
            // Cannot fail: the trajectory holds the end knot.
            let (pts, nrm) = (&mut st.points[..m], &mut st.normals3[..m]);
            let _ = match (par, &rotations) {
                (Some(p), _) => st.trajectory.undistort_with(f.state(), pts, None, p),
                (None, Some(rot)) => st.trajectory.undistort_rotating(f.state(), pts, nrm, rot),
                (None, None) => st.trajectory.undistort(f.state(), pts, None),
            };
        }
        let t_u = clock.now_ns();
        let mut binned = false;
        let t_r = if overlap {
            // One job estimates, compacts and rotates the normals; the other bins the points
            // (both only read them).
            let (ring, table, normals) = (&mut st.ring, &st.table, &mut st.normals[..n]);
            let (nrm3, rot) = (&mut st.normals3[..m], &rotations);
            let pts = &st.points[..m];
            // On two threads, how the stage's jobs go together ([`Arrangement`], four ways: bit 0
            // where the free-space marks go, bit 1 whether the normals' compaction and rotation
            // follow in two pieces of their own).
            let deferred = self.pending.is_some();
            let arm = par.filter(|p| p.width() == 2).map(|_| self.balance[usize::from(deferred)].pick());
            let tail_after = arm.is_some_and(|a| a & 2 != 0);
            let mut job_normals = || {
                ring_fals(ring, table, input, normals);
                if !tail_after {
                    fill_turned(input, normals, pts, nrm3, *rot, valid);
                }
            };
            let (ds, cells, free) =
                (&mut st.downsampler, &mut st.cell_of[..m], &mut st.frees[free_slot(st.free_turn, 0)]);
            let bin = &mut binned;
            // Which cells of the free-space image no return fell in (every point, before the
            // downsampling keeps one a voxel): the map's clearing reads them as gone through.
            let mark = self.cfg.free_space.enabled;
            let mut job_voxels = || {
                *bin = m > 0 && ds.bin_with_scratch(&ds_cfg, pts, cells).is_ok();
            };
            let mut job_mark = || {
                if mark {
                    free.mark_returns(pts);
                }
            };
            // The last scan's map insertion, where it waits: it writes the map only, which
            // nothing of this scan reads before the association.
            let (map, pending, buf) = (&mut self.map, &mut self.pending, self.deferred.as_deref());
            let mut job_map = || insert_pending(map, pending, buf);
            // With three threads or more each job runs on its own. On two, the free-space
            // marks go with the normals or with the voxel search, and the normals' compaction
            // and rotation stay in Ring FALS's job or follow it in two pieces, whichever made
            // the stage shorter lately ([`Arrangement`]; the same results every way). On the
            // simulated street drive the insertion makes the voxels' job the longer (Intel Xeon,
            // 2026-12-07: 2.39 against 2.34 ms with the marks), in the rotation and corridor
            // scenes Ring FALS's (1.62 against 2.24, 0.89 against 1.83); without an insertion
            // waiting (a replay, a live run) Ring FALS's everywhere.
            if let Some(p) = par {
                if deferred && p.width() >= 3 {
                    p.run(&mut [&mut job_normals, &mut job_voxels, &mut job_map, &mut job_mark]);
                } else if p.width() >= 3 {
                    p.run(&mut [&mut job_normals, &mut job_voxels, &mut job_mark]);
                } else {
                    let a = arm.unwrap_or(0);
                    let marks_with_normals = (a & 1 == 0) == deferred;
                    let (mut mark_a, mut mark_b) = if marks_with_normals {
                        (None, Some(&mut job_mark))
                    } else {
                        (Some(&mut job_mark), None)
                    };
                    let mut first = || {
                        job_voxels();
                        job_map();
                        if let Some(m) = mark_a.as_mut() {
                            m();
                        }
                    };
                    let mut second = || {
                        job_normals();
                        if let Some(m) = mark_b.as_mut() {
                            m();
                        }
                    };
                    // The calling thread takes the job it took before the marks moved.
                    if deferred {
                        p.run(&mut [&mut first, &mut second]);
                    } else {
                        p.run(&mut [&mut second, &mut first]);
                    }
                }
            }
            // The normals' compaction and rotation in two pieces: each half of the caller's
            // points into its own part of the compacted normals (step 1 counted the valid points
            // of the first half).
            if let (true, Some(p)) = (tail_after, par) {
                let (in_a, in_b) = input.split_at(n_half);
                let (nr_a, nr_b) = normals.split_at(n_half);
                let (out_a, out_b) = nrm3.split_at_mut(m_half);
                let (pt_a, pt_b) = pts.split_at(m_half);
                let mut tail_a = || fill_turned(in_a, nr_a, pt_a, out_a, *rot, valid);
                let mut tail_b = || fill_turned(in_b, nr_b, pt_b, out_b, *rot, valid);
                p.run(&mut [&mut tail_a, &mut tail_b]);
            }
            let t_n = clock.now_ns();
            if let Some(a) = arm {
                self.balance[usize::from(deferred)].record(a, t_n.saturating_sub(t_u));
            }
            times.normals_ns = t_n.saturating_sub(t_u);
            times.undistort_ns = (t_p.saturating_sub(t0)).saturating_add(t_u.saturating_sub(t_n0));
            t_n
        } else {
            let (ds, cells, pts) = (&mut st.downsampler, &mut st.cell_of[..m], &st.points[..m]);
            let (free, mark, bin) =
                (&mut st.frees[free_slot(st.free_turn, 0)], self.cfg.free_space.enabled, &mut binned);
            let mut job_voxels = || {
                *bin = m > 0 && ds.bin_with_scratch(&ds_cfg, pts, cells).is_ok();
                if mark {
                    free.mark_returns(pts);
                }
            };
            match par {
                // Plain mode: the last scan's insertion beside the voxel search.
                Some(p) if self.pending.is_some() => {
                    let (map, pending, buf) = (&mut self.map, &mut self.pending, self.deferred.as_deref());
                    let mut job_map = || insert_pending(map, pending, buf);
                    p.run(&mut [&mut job_voxels, &mut job_map]);
                }
                _ => job_voxels(),
            }
            times.normals_ns = t_n0.saturating_sub(t_p);
            times.undistort_ns = t_p.saturating_sub(t0).saturating_add(t_u.saturating_sub(t_n0));
            t_u
        };

        // 4. The downsampling's output: one point per voxel with the mean normal.
        let kept = if binned {
            if use_normals {
                st.downsampler.add_normals_with(
                    &st.normals3[..m],
                    &st.cell_of[..m],
                    par.unwrap_or(&Sequential),
                );
            }
            let room = VoxelDownsampler::<DS>::max_voxels();
            match (par, self.gather.as_deref_mut()) {
                // Gathered in pieces, then back into the points (the same bits as in place).
                (Some(p), Some(buf)) if buf.len() >= room => {
                    let (pts, nrm) = (&st.points[..m], Some(&mut st.normals3[..m]));
                    let kept = st.downsampler.finish_into(&ds_cfg, pts, buf, nrm, p).kept as usize;
                    let buf = &*buf;
                    crate::parallel::map_chunks(p, &mut st.points[..kept], 64, |first, run| {
                        run.copy_from_slice(&buf[first..first + run.len()]);
                    });
                    kept
                }
                _ => {
                    st.downsampler.finish(&ds_cfg, &mut st.points[..m], Some(&mut st.normals3[..m])).kept
                        as usize
                }
            }
        } else {
            0
        };
        let t3 = clock.now_ns();
        times.downsample_ns = t3.saturating_sub(t_r);
        let npoints = [npoints[0], kept as u32];

        // 4b. Moving points: where the previous scan's beams went through, something moved in.
        // They go to the end of the kept points, out of the association and the map.
        let mut moving = 0usize;
        let fs = self.cfg.free_space;
        let ref_max_ns = (2.0 * f64::from(fs.reference_every_s) * 1e9) as u64 + 150_000_000;
        let stale = |p: Option<PrevScan>, max_ns: u64| {
            reinit.is_some() || p.is_some_and(|p| end_ns <= p.end_ns || end_ns - p.end_ns > max_ns)
        };
        if stale(self.prev_scan, ref_max_ns) {
            self.prev_scan = None;
        }
        // The older one's bound is one scan (0.1 s) longer: each renewal may come a scan after
        // `reference_every_s`, so the older reference can be that much older than the newer's bound.
        if stale(self.old_scan, ref_max_ns + 100_000_000) {
            self.old_scan = None;
        }
        // Against the older reference (`reference_every_s` to twice that old), where there is one:
        // it saw where a slowly approaching object was far enough away.
        let reference = match self.old_scan {
            Some(o) => Some((o, &st.frees[free_slot(st.free_turn, 2)])),
            None => self.prev_scan.map(|p| (p, &st.frees[free_slot(st.free_turn, 1)])),
        };
        if let Some((prev, img)) = reference
            && kept > 0
            && fs.enabled
            && fs.moving_points
        {
            let x = f.state();
            let r = x.rot.to_rotation_matrix().into_inner();
            let r_wl = r * x.ext_rot.to_rotation_matrix().into_inner();
            let p_wl = r * x.ext_pos + x.pos;
            // This scan's sensor frame to the reference's.
            let m = prev.rot_t * r_wl;
            let b = prev.rot_t * (p_wl - prev.origin);
            let m: [[f32; 3]; 3] = core::array::from_fn(|i| core::array::from_fn(|j| m[(i, j)] as f32));
            let b = [b.x as f32, b.y as f32, b.z as f32];
            let fs = &self.cfg.free_space;
            // Each point's verdict (in pieces on the caller's threads), then the partition.
            let (pts, flags) = (&st.points[..kept], &mut st.cell_of[..kept]);
            // A point's verdict in `cell_of`: seen through (moving), seen, or neither.
            const MOVED: u32 = 1;
            // Eight points at a time: the image finds their cells on vector lanes.
            let moved = |first: usize, out: &mut [u32]| {
                let to_ref = |q: &ScanPoint| {
                    let p = &q.xyz;
                    core::array::from_fn(|i| m[i][0] * p[0] + m[i][1] * p[1] + m[i][2] * p[2] + b[i])
                };
                let v = crate::free_space::lanes(pts[first..first + out.len()].iter().map(to_ref));
                let verdicts = img.verdicts8(&v, fs);
                for (slot, verdict) in out.iter_mut().zip(verdicts) {
                    // The reference saw it there: static, no tracked object's.
                    *slot = match verdict {
                        Verdict::SeenThrough => MOVED,
                        Verdict::Seen => crate::moving_objects::SEEN,
                        Verdict::Unknown => 0,
                    };
                }
            };
            crate::parallel::map_chunks(par.unwrap_or(&Sequential), flags, crate::free_space::LANES, moved);
            let (mut i, mut end) = (0usize, kept);
            while i < end {
                if st.cell_of[i] == MOVED {
                    end -= 1;
                    st.points.swap(i, end);
                    st.normals3.swap(i, end);
                    st.cell_of.swap(i, end);
                } else {
                    i += 1;
                }
            }
            moving = kept - end;
            // The rest of the objects those points belong to ([`crate::moving_objects`]).
            let grow = &self.cfg.free_space.grow;
            if grow.enabled && (moving > 0 || st.objects.tracking()) {
                let to_world: [[f32; 4]; 3] = core::array::from_fn(|i| {
                    [r_wl[(i, 0)] as f32, r_wl[(i, 1)] as f32, r_wl[(i, 2)] as f32, p_wl[i] as f32]
                });
                moving += st.objects.grow(
                    &mut st.points[..kept],
                    &mut st.normals3[..kept],
                    end,
                    grow,
                    &to_world,
                    &mut st.cell_of[..kept],
                );
            }
            self.stats.moving = self.stats.moving.saturating_add(moving as u64);
        } else {
            // Tracks are in scans: a scan without the test breaks them.
            st.objects.forget_tracks();
        }
        let still = kept - moving;

        // 5. Association and update.
        let building = self.map.is_empty();
        let mut update = UpdateResult::default();
        let mut counts = AssociationCounts::default();
        let mut first = AssociationCounts::default();
        let mut measured_n = 0u32;
        let ic = self.cfg.integrity;
        // Without IMU every scan is predicted as a bridged one is (the LiDAR's own motion).
        let bridged = flags.has(PropagationFlags::BRIDGE) || flags.has(PropagationFlags::LIDAR_ONLY);
        let mut measured = 0;
        if kept > 0 && !building {
            // The measured points first; the map still gets them all (step 6).
            measured = crate::selection::select_even(
                &mut st.points[..still],
                &mut st.normals3[..still],
                self.cfg.association.max_points,
            );
            // After a long LiDAR gap or while lost: re-localise in the map first.
            let lost_now = ic.lost_scans > 0 && self.low_run >= ic.lost_scans;
            if (after_long_gap || lost_now) && reinit.is_none() && measured > 0 {
                let x = f.state();
                let r = x.rot.to_rotation_matrix().into_inner();
                let r_wl = r * x.ext_rot.to_rotation_matrix().into_inner();
                let t_wl = r * x.ext_pos + x.pos;
                let p = f.covariance();
                let var = (0..3).map(|k| p[(idx::POS + k, idx::POS + k)]).fold(0.0f64, f64::max);
                let window = (3.0 * crate::math::sqrt(var)) as f32;
                let window = window.max(2.0 * self.cfg.map.voxel_size);
                let found = relocalise::search(&rc, &self.map, &st.points[..measured], &r_wl, &t_wl, window);
                if found.moved {
                    let o = found.offset;
                    f.shift_position(&Vector3::new(f64::from(o[0]), f64::from(o[1]), f64::from(o[2])));
                    self.stats.relocalisations = self.stats.relocalisations.saturating_add(1);
                }
                self.last_relocalisation = Some(found);
            }
        }
        // The prediction, kept to fall back on when the scan disagrees with the map.
        let prior = (ic.lost_scans > 0 && kept > 0 && !building).then(|| f.clone());
        if kept > 0 && !building {
            let mut assoc =
                st.association(&self.map, &self.cfg, (measured, still), &mut self.parallel, clock);
            let bridge_prior = bridged.then(|| f.clone());
            update = f.update(&mut assoc);
            counts = assoc.counts();
            first = assoc.first_counts();
            measured_n = measured as u32;
            times.association_ns = assoc.elapsed_ns();
            // Through an IMU gap the bridge holds the last scans' motion: the update's motion
            // from the previous scan end to this one undistorts the scan again, and the update
            // runs again from the same prediction (the LiDAR's own constant-velocity model).
            if let Some(prior) = bridge_prior {
                // The undistortion the points are in: its trajectory (`None`: the scan's) and end.
                let mut last: Option<ImuTrajectory<2>> = None;
                let mut last_end = *prior.state();
                for _ in 0..BRIDGE_REUNDISTORT_PASSES {
                    if update.outcome != UpdateOutcome::Updated {
                        break;
                    }
                    let span = st.trajectory.span_to(end_ns, f.state());
                    let (pts, nrm) = (&mut st.points[..kept], &mut st.normals3[..kept]);
                    // Cannot fail: both trajectories hold knots and the slices have equal lengths.
                    let _ = match &last {
                        Some(l) => l.redistort(&last_end, pts, Some(&mut *nrm)),
                        None => st.trajectory.redistort(&last_end, pts, Some(&mut *nrm)),
                    };
                    let _ = span.undistort(f.state(), pts, Some(nrm));
                    last_end = *f.state();
                    last = Some(span);
                    *f = prior.clone();
                    let mut assoc =
                        st.association(&self.map, &self.cfg, (measured, still), &mut self.parallel, clock);
                    update = f.update(&mut assoc);
                    counts = assoc.counts();
                    times.association_ns = times.association_ns.saturating_add(assoc.elapsed_ns());
                }
            }
        }
        let t4 = clock.now_ns();
        times.update_ns = t4.saturating_sub(t3).saturating_sub(times.association_ns);

        // Integrity: of the points with map surfaces near them at the predicted pose, the share
        // that matched.
        let near = first
            .accepted()
            .saturating_add(first.rejected_residual)
            .saturating_add(first.no_plane)
            .saturating_add(first.rejected_consistency);
        let mut integrity = Integrity { near, measured: measured_n, share_pct: 100, nis: 0.0, low: false };
        // Per point and in the residuals' own variance (a budget's points weigh more).
        let per_point = if measured > 0 && still > measured { measured as f64 / still as f64 } else { 1.0 };
        if update.measurements[0] > 0 {
            integrity.nis =
                (per_point * update.weighted_sq_residual[0] / f64::from(update.measurements[0])) as f32;
        }
        // After a pause of either sensor the prediction is known to be off: the first scans
        // re-localise and are not judged (nor feed the means).
        let after_gap = flags.has(PropagationFlags::BRIDGE)
            || self.last_scan_end_ns.is_some_and(|t| end_ns.saturating_sub(t) as f64 * 1e-9 > LIDAR_GAP_S);
        if after_gap {
            self.recovering = RECOVERY_SCANS;
        }
        let recovering = self.recovering > 0;
        self.recovering = self.recovering.saturating_sub(1);
        if kept > 0 && !building && near > 0 && !recovering {
            let share = first.accepted() as f32 / near as f32;
            integrity.share_pct = (share * 100.0) as u8;
            // The bounds, where the map usually matches well (none yet: nothing is low).
            let bounds = match (self.share_mean, self.nis_mean) {
                (Some(s), Some(n)) if s >= ic.min_mean && near >= ic.min_near => {
                    Some((ic.min_share.min(ic.drop_ratio * s), ic.nis_floor.max(ic.nis_ratio * n)))
                }
                _ => None,
            };
            let disagrees = |share: f32, nis: f32| bounds.is_some_and(|(s, n)| share < s || nis > n);
            // The update's last association and innovation, for a prediction that drifted.
            let last =
                counts.accepted().saturating_add(counts.rejected_residual).saturating_add(counts.no_plane);
            let last = last.saturating_add(counts.rejected_consistency);
            let it = usize::from(update.iterations.max(1)) - 1;
            let nis_last = if update.measurements[it] > 0 {
                (per_point * update.weighted_sq_residual[1] / f64::from(update.measurements[it])) as f32
            } else {
                f32::INFINITY
            };
            let share_last = if last > 0 { counts.accepted() as f32 / last as f32 } else { 0.0 };
            integrity.low = disagrees(share, integrity.nis)
                && (update.outcome != UpdateOutcome::Updated || disagrees(share_last, nis_last));
            if integrity.low {
                self.low_run = self.low_run.saturating_add(1);
                // Not believed: the prediction stands (an update towards a scan that does not
                // fit the map drags the pose away, and the next scans then "fit").
                if let Some(p) = &prior
                    && ic.lost_scans > 0
                {
                    *f = p.clone();
                    update.outcome = UpdateOutcome::TooFewMeasurements;
                }
            } else {
                self.low_run = 0;
                self.share_mean = Some(self.share_mean.map_or(share, |m| 0.9 * m + 0.1 * share));
                if update.measurements[0] > 0 {
                    let n = integrity.nis;
                    self.nis_mean = Some(self.nis_mean.map_or(n, |m| 0.9 * m + 0.1 * n));
                }
            }
        }
        let lost = ic.lost_scans > 0 && self.low_run >= ic.lost_scans;
        let low = ic.lost_scans > 0 && self.low_run > 0;

        // Standing still: zero velocity and the gyro's mean as its bias.
        let dt = self.last_scan_end_ns.map_or(0.0, |t| end_ns.saturating_sub(t) as f64 * 1e-9);
        let sc = self.cfg.standstill;
        let stands = sc.enabled
            && reinit.is_none()
            && !bridged
            && !low
            && kept > 0
            && !building
            && update.measurements[0] > 0
            && update.outcome == UpdateOutcome::Updated
            && dt <= LIDAR_GAP_S
            && self.window.stands(&sc, f);
        self.still_s = if stands { self.still_s + dt } else { 0.0 };
        if stands && self.still_s >= sc.min_duration_s {
            let v = f.zero_velocity(sc.velocity_std * sc.velocity_std);
            let r = f.zero_rate(&self.window.mean_gyro(), self.window.rate_variance(&sc));
            if v || r {
                flags.0 |= PropagationFlags::STILL;
                self.stats.standstill = self.stats.standstill.saturating_add(1);
            }
        }

        // How the scan is bent tells the IMU–LiDAR time offset (well-posed scans only). Only a
        // scan the IMU covers to within a sample period: one predicted further past the last
        // sample (a live source whose IMU lags) is bent by the extrapolation, not by the
        // offset. With a second thread the warp's sums run beside the free-space image's fill
        // (step 6); nothing there changes what they read.
        let covered = st.imu.last_time_ns().is_some_and(|t| t.saturating_add(OFFSET_MAX_HOLD_NS) >= end_ns);
        let judged = covered
            && reinit.is_none()
            && !bridged
            && !low
            && !recovering
            && !building
            && kept > 0
            && update.outcome == UpdateOutcome::Updated
            && update.degeneracy.count == 0;
        let want_warp = judged && self.cfg.time_offset.enabled && !self.cfg.motion.is_lidar_only();
        let (end_t, x_end) = (f64::from(t_max), *f.state());
        let warp_of = move |pts: &[ScanPoint], corr: &[Correspondence], traj: &ImuTrajectory<_>| {
            time_offset::scan_warp(&pts[..measured], &corr[..measured], &x_end, traj, end_t)
        };
        let mut warp: Option<time_offset::Warp> = None;

        // 6. Map insertion at the updated pose (not while the scans disagree with the map: it
        // stays clean for the re-localisation).
        if kept > 0 && update.outcome != UpdateOutcome::NumericalFailure && !low {
            self.last_kept = kept;
            // The insertion (and the clearing before it) waits for the next scan or the caller's
            // flush where there is a second thread and room.
            let defer = par.is_some() && self.deferred.as_ref().is_some_and(|b| b.len() >= still);
            let x = f.state();
            let r = x.rot.to_rotation_matrix().into_inner();
            let r_wl: Matrix3<f64> = r * x.ext_rot.to_rotation_matrix().into_inner();
            let p_wl = r * x.ext_pos + x.pos;
            let origin = [p_wl.x as f32, p_wl.y as f32, p_wl.z as f32];
            let pts = st.points[..still].iter().zip(st.normals3[..still].iter()).map(|(p, n)| {
                let q =
                    r_wl * Vector3::new(f64::from(p.xyz[0]), f64::from(p.xyz[1]), f64::from(p.xyz[2])) + p_wl;
                let normal = if normal_is_valid(n) {
                    let w = r_wl * Vector3::new(f64::from(n[0]), f64::from(n[1]), f64::from(n[2]));
                    Some([w.x as f32, w.y as f32, w.z as f32])
                } else {
                    None
                };
                MapPoint { xyz: [q.x as f32, q.y as f32, q.z as f32], normal }
            });
            // Before the scan goes in: what it sees through leaves the map.
            // Judged only from a scan whose pose the map pins down in every direction.
            let well_posed = update.outcome == UpdateOutcome::Updated && update.degeneracy.count == 0;
            if !well_posed {
                self.prev_scan = None;
                self.old_scan = None;
            }
            if fs.enabled && !building && well_posed {
                let (frees, slot, pts_k) = (&mut st.frees, free_slot(st.free_turn, 0), &st.points[..kept]);
                match par {
                    Some(p) if want_warp => {
                        let (w, corr, traj) = (&mut warp, &st.corr, &st.trajectory);
                        let (pts, wo) = (&st.points, &warp_of);
                        p.run(&mut [&mut || frees[slot].fill(pts_k), &mut || *w = Some(wo(pts, corr, traj))]);
                    }
                    _ => frees[slot].fill(pts_k),
                }
                // World to sensor in f32: the map's points are f32, the margins decimetres.
                let rt: [[f32; 3]; 3] =
                    core::array::from_fn(|i| core::array::from_fn(|j| r_wl[(j, i)] as f32));
                // Every voxel at least every 4 scans on a small map; a fixed cost on a large one.
                let budget = (fs.voxels_per_scan as usize).min(self.map.len().div_ceil(4));
                // The clearing waits with the insertion where that waits (the pose goes out
                // first), else runs now: its judgements in pieces on the caller's threads (the
                // voxels' scratch is free by now).
                let clear = PendingClear { origin, rt, budget, image: free_slot(st.free_turn, 0) };
                if defer {
                    self.pending_clear = Some(clear);
                } else {
                    let (p, fsc) = (par.unwrap_or(&Sequential), &self.cfg.free_space);
                    let scratch = (&st.frees[..], &mut st.suspects, &mut st.cell_of[..]);
                    run_clear(clear, &mut self.map, scratch, fsc, p, &mut self.stats);
                }
                // The reference image and pose for the next scans' moving points, renewed every
                // `reference_every_s`.
                let renew_ns = (f64::from(fs.reference_every_s) * 1e9) as u64;
                if self.prev_scan.is_none_or(|p| end_ns.saturating_sub(p.end_ns) >= renew_ns) {
                    // This scan's image becomes the newer reference, the newer the older, and the
                    // older one is written over by the next scan.
                    st.free_turn = (st.free_turn + 1) % 3;
                    self.old_scan = self.prev_scan;
                    self.prev_scan = Some(PrevScan { end_ns, rot_t: r_wl.transpose(), origin: p_wl });
                }
            }
            self.stamp = self.stamp.saturating_add(1);
            match self.deferred.as_deref_mut() {
                // With a second thread, the insertion waits for the next scan's normals stage.
                Some(buf) if defer => {
                    for (slot, p) in buf.iter_mut().zip(pts) {
                        *slot = p;
                    }
                    self.pending = Some(PendingInsert { origin, stamp: self.stamp, points: still });
                }
                // Cannot fail: the origin is finite (the state is) and stamps only increase.
                _ => {
                    let _ = self.map.insert(pts, origin, self.stamp);
                }
            }
        }
        let t5 = clock.now_ns();
        times.map_ns = t5.saturating_sub(t4);

        let lidar_gap = self
            .last_scan_end_ns
            .replace(end_ns)
            .is_some_and(|t| end_ns.saturating_sub(t) as f64 * 1e-9 > LIDAR_GAP_S);
        let status = if let Some(r) = reinit {
            Status::Reinitialising(r)
        } else if lost {
            Status::Lost { inliers_pct: integrity.share_pct }
        } else if kept == 0 {
            Status::ImuOnly(ImuOnlyReason::EmptyScan)
        } else if building {
            Status::ImuOnly(ImuOnlyReason::BuildingMap)
        } else if low {
            Status::ImuOnly(ImuOnlyReason::DisagreesWithMap { inliers_pct: integrity.share_pct })
        } else {
            match Status::from_update(&update, flags) {
                Status::Ok if lidar_gap => Status::Bridged(BridgeReason::LidarGap),
                Status::Ok if flags.has(PropagationFlags::BRIDGE) => Status::Bridged(BridgeReason::ImuGap),
                s => s,
            }
        };
        match status {
            Status::ImuOnly(ImuOnlyReason::BuildingMap) => {}
            Status::ImuOnly(_) => self.stats.imu_only = self.stats.imu_only.saturating_add(1),
            Status::Degraded { .. } => self.stats.degraded = self.stats.degraded.saturating_add(1),
            Status::Lost { .. } => self.stats.lost = self.stats.lost.saturating_add(1),
            _ => {}
        }
        let pose = PoseEstimate::from_filter(f);
        let x = f.state();
        // The time offset's warp (step 6 took it where it ran beside the fill).
        let warp = warp.or_else(|| want_warp.then(|| warp_of(&st.points, &st.corr, &st.trajectory)));
        if let Some(warp) = warp
            && self.offset.scan(&warp).is_some()
        {
            // Samples that the new offset puts before the ones queued are dropped until it
            // catches up (only when it moved back).
            self.realign_until_ns = st.imu.last_time_ns();
        }
        // The motion from the last scan end to this one: what an IMU gap is bridged with.
        if let Some((t, rot, pos)) = self.last_end.replace((end_ns, x.rot, x.pos))
            && end_ns > t
            && (end_ns - t) as f64 * 1e-9 <= LIDAR_GAP_S
            && reinit.is_none()
            && update.outcome == UpdateOutcome::Updated
            && !low
        {
            let dt = (end_ns - t) as f64 * 1e-9;
            let rate = crate::so3::log(&(rot.inverse() * x.rot).to_rotation_matrix().into_inner()) / dt;
            f.set_bridge_motion(rate, (x.pos - pos) / dt);
        }
        let mut status = status;
        if lost && ic.restart_after > 0 && self.low_run >= ic.lost_scans.saturating_add(ic.restart_after) {
            // The agreement never came back: start over in a new world frame.
            self.restart();
            status = Status::Reinitialising(ReinitReason::Lost);
        }
        times.total_ns = clock.now_ns().saturating_sub(t0);
        ScanResult {
            scan_start_ns: scan.start_ns,
            pose,
            status,
            times,
            associations: counts,
            update,
            propagation: flags,
            points: npoints,
            integrity,
        }
    }
}

/// [`fill_normals`] of the caller's `input`, then each turned by `rot` as its (moved) point in
/// `pts` gives it: the normals' part of Ring FALS's job, whole or in pieces.
fn fill_turned(
    input: &[ScanPoint],
    normals: &[PointNormal],
    pts: &[ScanPoint],
    out: &mut [[f32; 3]],
    rot: Option<&NormalRotations>,
    valid: impl Fn(&ScanPoint) -> bool,
) {
    fill_normals(true, input, normals, out, valid);
    if let Some(r) = rot {
        r.rotate(pts, out);
    }
}

/// The valid points' normals (`valid`, as step 1 kept the points) compacted into `out`, or
/// none at all without normals. `out` holds as many as `valid` keeps of `input`.
fn fill_normals(
    use_normals: bool,
    input: &[ScanPoint],
    normals: &[PointNormal],
    out: &mut [[f32; 3]],
    valid: impl Fn(&ScanPoint) -> bool,
) {
    if !use_normals {
        out.fill(INVALID_NORMAL);
        return;
    }
    if out.len() == input.len() && normals.len() == input.len() {
        // Every point was kept (as `out` holds as many as `valid` kept): nothing to test.
        for (o, nr) in out.iter_mut().zip(normals) {
            *o = nr.get().unwrap_or(INVALID_NORMAL);
        }
        return;
    }
    let mut k = 0usize;
    for (p, nr) in input.iter().zip(normals.iter()) {
        if valid(p)
            && let Some(o) = out.get_mut(k)
        {
            *o = nr.get().unwrap_or(INVALID_NORMAL);
            k += 1;
        }
    }
}

/// Ring FALS normals of `input` into `out`; all invalid if the table or storage refuses the
/// scan.
fn ring_fals<const PIX: usize>(
    ring: &mut RingFals<PIX>,
    table: &RingTable,
    input: &[ScanPoint],
    out: &mut [PointNormal],
) {
    if ring.estimate(table, input, out).is_err() {
        out.fill(PointNormal::INVALID);
    }
}

/// The LiDAR-only prediction of a scan ending at `end_ns` ([`crate::motion_model`]): IMU
/// samples queued anyway are discarded; the first scan starts the filter at the identity (at
/// its end: one knot, no motion); every later one is propagated at the held rate and velocity,
/// the scan's trajectory holding the knot before (with that velocity) and the end.
fn predict_without_imu<const PIX: usize, const PTS: usize, const DS: usize>(
    filter: &mut Option<Eskf>,
    st: &mut ScanStorage<PIX, PTS, DS>,
    cfg: &OdometryConfig,
    cv: ConstantVelocity,
    start_ns: u64,
    end_ns: u64,
) {
    while st.imu.pop_until(end_ns).is_some() {}
    st.trajectory.clear(start_ns);
    match filter {
        None => {
            let f = Eskf::without_imu(cfg.eskf, end_ns, cfg.init.gravity, cfg.ext_rot, cfg.ext_pos);
            st.trajectory.push(f.time_ns(), f.state());
            *filter = Some(f);
        }
        Some(f) => {
            f.hold_velocity();
            st.trajectory.push(f.time_ns(), f.state());
            f.predict_constant_velocity(end_ns, cv.acc_std, cv.gyro_std);
            st.trajectory.push(f.time_ns(), f.state());
        }
    }
}

/// Re-seeds the filter after an IMU jump that moved its time from `before_ns` without
/// integrating (module docs): constant velocity and rate over the skipped time, larger
/// position, velocity and attitude uncertainties.
fn reseed_after_jump(f: &mut Eskf, before_ns: u64) {
    let cfg = *f.config();
    let s = cfg.initial;
    let mut x = *f.state();
    let mut p = *f.covariance();
    let gap = (f.time_ns().saturating_sub(before_ns) as f64 * 1e-9).min(10.0);
    x.pos += x.vel * gap;
    if let Some(h) = f.held_sample() {
        let w = (h.gyro_vec() - x.bg) * gap;
        if w.iter().all(|v| v.is_finite()) {
            x.rot *= so3::exp_quat(&w);
        }
    }
    let dp = s.rough_vel * gap;
    for k in 0..3 {
        p[(idx::POS + k, idx::POS + k)] += dp * dp;
        p[(idx::VEL + k, idx::VEL + k)] += s.rough_vel * s.rough_vel;
        p[(idx::ROT + k, idx::ROT + k)] += s.rough_tilt * s.rough_tilt;
    }
    *f = Eskf::from_state(cfg, x, p, f.time_ns(), f.held_sample().copied(), f.acc_scale());
}
