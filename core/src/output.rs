//! What the odometry reports for each scan: the pose at scan end with its covariance, velocity,
//! biases and gravity, a [`Status`], per-stage times and the association counts.
//!
//! The core has no clock: [`StageTimes`] are slots the caller fills (nanoseconds from its own
//! clock around each stage call). [`AssociationCounts`] are filled by the association.

use nalgebra::{Matrix6, UnitQuaternion, Vector3};

use crate::eskf::{Eskf, PropagationFlags, UpdateOutcome, UpdateResult};
use crate::imu::WaitReason;

/// The odometry's state of health for one scan.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Status {
    /// Updated by the scan, every pose direction observed.
    Ok,
    /// Updated by the scan, but some pose directions were unobservable and left to the IMU.
    Degraded {
        /// Pose axes affected (bit 0-2: position x, y, z; bit 3-5: rotation about IMU x, y, z),
        /// see [`crate::eskf::Degeneracy::axes`].
        axes: u8,
        /// Number of degenerate directions.
        count: u8,
    },
    /// Updated by the scan after a pause of one of the sensors that the filter bridged (the
    /// IMU alone through a LiDAR gap, constant velocity through an IMU gap): the pose is
    /// usable, with the bridge's larger covariance.
    Bridged(BridgeReason),
    /// The scans no longer agree with the map (see [`crate::odometry::IntegrityConfig`]): the
    /// pose is not to be trusted. The update is discarded and the map takes no scans
    /// meanwhile, so it stays clean for the re-localisation; if the agreement does not
    /// return, the odometry starts over.
    Lost {
        /// The last scan's share of matching points, percent.
        inliers_pct: u8,
    },
    /// Propagated by the IMU only; the covariance grows.
    ImuOnly(ImuOnlyReason),
    /// Waiting for the IMU initialisation.
    Initialising(WaitReason),
    /// The filter lost track and starts over.
    Reinitialising(ReinitReason),
}

/// Why a scan did not update the state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ImuOnlyReason {
    /// Too few correspondences (the count of the first iteration).
    TooFewCorrespondences {
        /// Accepted measurements.
        found: u32,
    },
    /// The scan had no usable points.
    EmptyScan,
    /// The first scan after (re)initialisation builds the map.
    BuildingMap,
    /// The update produced non-finite numbers and was discarded.
    NumericalFailure,
    /// The scan disagreed with the map at the predicted pose (the integrity check): its update
    /// was discarded and the map did not take it; three in a row are [`Status::Lost`].
    DisagreesWithMap {
        /// The share of its points near the map that matched, percent.
        inliers_pct: u8,
    },
}

/// Which sensor paused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum BridgeReason {
    /// No IMU samples for longer than `eskf.bridge_after_s`: the motion the last scans measured, held.
    ImuGap,
    /// No scan for longer than [`crate::odometry::LIDAR_GAP_S`]: the IMU alone.
    LidarGap,
}

/// Why the filter re-initialises.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ReinitReason {
    /// The IMU time jumped forward beyond `max_hold_s`.
    ImuJump,
    /// The state became non-finite.
    NonFinite,
    /// Lost for longer than `integrity.restart_after` scans.
    Lost,
}

impl Status {
    /// The status an update and the propagation flags of its scan imply: a jump means
    /// re-initialising; otherwise the update outcome and its degeneracy decide.
    pub fn from_update(update: &UpdateResult, flags: PropagationFlags) -> Status {
        if flags.has(PropagationFlags::JUMP) {
            return Status::Reinitialising(ReinitReason::ImuJump);
        }
        match update.outcome {
            UpdateOutcome::Updated if update.degeneracy.count > 0 => {
                Status::Degraded { axes: update.degeneracy.axes, count: update.degeneracy.count }
            }
            UpdateOutcome::Updated => Status::Ok,
            UpdateOutcome::TooFewMeasurements => {
                Status::ImuOnly(ImuOnlyReason::TooFewCorrespondences { found: update.measurements[0] })
            }
            UpdateOutcome::NumericalFailure => Status::ImuOnly(ImuOnlyReason::NumericalFailure),
        }
    }
}

/// The estimate at one instant (the scan end).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseEstimate {
    /// Time, ns.
    pub t_ns: u64,
    /// World from IMU (the world is gravity-aligned, z up, yaw 0 at start).
    pub rotation: UnitQuaternion<f64>,
    /// IMU position in the world, m.
    pub position: Vector3<f64>,
    /// Covariance of (position error in the world, m; rotation error in the IMU frame, rad:
    /// `R_true = R Exp(δθ)`).
    pub covariance: Matrix6<f64>,
    /// Velocity in the world, m/s.
    pub velocity: Vector3<f64>,
    /// Gyro bias, rad/s.
    pub gyro_bias: Vector3<f64>,
    /// Accelerometer bias, m/s^2.
    pub acc_bias: Vector3<f64>,
    /// Gravity in the world, m/s^2.
    pub gravity: Vector3<f64>,
    /// IMU from LiDAR rotation (estimated if the filter estimates the extrinsic).
    pub ext_rot: UnitQuaternion<f64>,
    /// LiDAR origin in the IMU frame, m.
    pub ext_pos: Vector3<f64>,
}

impl PoseEstimate {
    /// The identity pose at `t_ns` with zero covariance (before initialisation).
    pub fn identity(t_ns: u64) -> Self {
        Self {
            t_ns,
            rotation: UnitQuaternion::identity(),
            position: Vector3::zeros(),
            covariance: Matrix6::zeros(),
            velocity: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
            acc_bias: Vector3::zeros(),
            gravity: Vector3::zeros(),
            ext_rot: UnitQuaternion::identity(),
            ext_pos: Vector3::zeros(),
        }
    }

    /// The filter's current estimate.
    pub fn from_filter(f: &Eskf) -> Self {
        let x = f.state();
        Self {
            t_ns: f.time_ns(),
            rotation: x.rot,
            position: x.pos,
            covariance: f.covariance().fixed_view::<6, 6>(0, 0).into_owned(),
            velocity: x.vel,
            gyro_bias: x.bg,
            acc_bias: x.ba,
            gravity: x.grav.vec(),
            ext_rot: x.ext_rot,
            ext_pos: x.ext_pos,
        }
    }

    /// World from LiDAR.
    pub fn lidar_pose(&self) -> (UnitQuaternion<f64>, Vector3<f64>) {
        (self.rotation * self.ext_rot, self.rotation * self.ext_pos + self.position)
    }
}

/// Per-stage wall times of one scan, nanoseconds, filled by the caller (0 = not measured).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StageTimes {
    /// Ring FALS normals. Where the caller gives two threads or more: with the normals'
    /// compaction and rotation, and the downsampling's voxel binning beside them (the two jobs'
    /// time together).
    pub normals_ns: u64,
    /// Copying the points in, the IMU propagation and the undistortion of every point (of its
    /// normal too on one thread); where the last scan's map clearing waited for this scan (a
    /// deferred insertion not flushed between scans), that clearing too.
    pub undistort_ns: u64,
    /// The rest of the voxel downsampling (on one thread with the voxel binning): the voxels'
    /// mean normals and the output.
    pub downsample_ns: u64,
    /// Association (all iterations).
    pub association_ns: u64,
    /// Filter update (all iterations, without association), with the moving points' verdicts
    /// and the measured points' selection.
    pub update_ns: u64,
    /// The map: its free-space clearing and the insertion (each only where it does not wait:
    /// `Odometry::set_deferred_map`).
    pub map_ns: u64,
    /// The whole scan.
    pub total_ns: u64,
}

/// Association outcomes of one scan (of the last iteration), filled by the association.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct AssociationCounts {
    /// Point-to-large-surfel residuals.
    pub large_surfel: u32,
    /// Point-to-small-surfel residuals.
    pub small_surfel: u32,
    /// Point-to-plane residuals.
    pub plane: u32,
    /// Rejected by the visibility check.
    pub rejected_visibility: u32,
    /// Rejected by the normal-consistency check.
    pub rejected_consistency: u32,
    /// Rejected by the residual test.
    pub rejected_residual: u32,
    /// No neighbours in the map.
    pub no_neighbours: u32,
    /// No surfel, and the neighbours were not coplanar (the plane fit failed).
    pub no_plane: u32,
}

impl AssociationCounts {
    /// The counts of two sets of points together.
    pub fn plus(&self, o: &AssociationCounts) -> AssociationCounts {
        AssociationCounts {
            large_surfel: self.large_surfel + o.large_surfel,
            small_surfel: self.small_surfel + o.small_surfel,
            plane: self.plane + o.plane,
            rejected_visibility: self.rejected_visibility + o.rejected_visibility,
            rejected_consistency: self.rejected_consistency + o.rejected_consistency,
            rejected_residual: self.rejected_residual + o.rejected_residual,
            no_neighbours: self.no_neighbours + o.no_neighbours,
            no_plane: self.no_plane + o.no_plane,
        }
    }

    /// Accepted residuals.
    pub fn accepted(&self) -> u32 {
        self.large_surfel + self.small_surfel + self.plane
    }
}

/// Everything the odometry reports for one scan.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScanResult {
    /// Scan start, ns.
    pub scan_start_ns: u64,
    /// The estimate at scan end.
    pub pose: PoseEstimate,
    /// Health.
    pub status: Status,
    /// Stage times (caller-filled).
    pub times: StageTimes,
    /// Association counts.
    pub associations: AssociationCounts,
    /// The update's result (iterations, per-iteration counts, degeneracy).
    pub update: UpdateResult,
    /// Propagation flags raised during the scan.
    pub propagation: PropagationFlags,
    /// Points in the scan, and after downsampling.
    pub points: [u32; 2],
    /// The scan's agreement with the map at the predicted pose.
    pub integrity: Integrity,
}

/// A scan's agreement with the map, measured at the predicted pose (the update's first
/// association, before the update pulls the pose towards the scan).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Integrity {
    /// Measured points with map surfaces near them (accepted, or rejected by the residual, the
    /// normal consistency or the plane fit).
    pub near: u32,
    /// Measured points, all.
    pub measured: u32,
    /// Of the `near` points, the share accepted, percent (100 when not measured).
    pub share_pct: u8,
    /// The first iteration's normalised innovation, `Σ r²/R` per accepted residual.
    pub nis: f32,
    /// Whether the scan counted as disagreeing with the map.
    pub low: bool,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eskf::{Degeneracy, UpdateResult};

    #[test]
    fn status_follows_the_update_and_the_flags() {
        let mut u = UpdateResult::default();
        assert_eq!(Status::from_update(&u, PropagationFlags::default()), Status::Ok);
        u.degeneracy = Degeneracy { count: 1, axes: 1, ..Default::default() };
        assert_eq!(
            Status::from_update(&u, PropagationFlags(PropagationFlags::GAP)),
            Status::Degraded { axes: 1, count: 1 }
        );
        u.outcome = UpdateOutcome::TooFewMeasurements;
        u.measurements[0] = 3;
        assert_eq!(
            Status::from_update(&u, PropagationFlags::default()),
            Status::ImuOnly(ImuOnlyReason::TooFewCorrespondences { found: 3 })
        );
        u.outcome = UpdateOutcome::NumericalFailure;
        assert_eq!(
            Status::from_update(&u, PropagationFlags::default()),
            Status::ImuOnly(ImuOnlyReason::NumericalFailure)
        );
        assert_eq!(
            Status::from_update(&u, PropagationFlags(PropagationFlags::JUMP)),
            Status::Reinitialising(ReinitReason::ImuJump)
        );
        let c = AssociationCounts { large_surfel: 1, small_surfel: 2, plane: 3, ..Default::default() };
        assert_eq!(c.accepted(), 6);
    }
}

#[cfg(test)]
mod footprint {
    extern crate std;
    use core::mem::size_of;

    use crate::downsample::VoxelDownsampler;
    use crate::eskf::{Eskf, InfoAccumulator};
    use crate::imu::{ImuInitializer, ImuQueue};
    use crate::undistort::ImuTrajectory;

    /// The fixed memory of the estimation stages (docs/estimation.md states these figures).
    #[test]
    fn memory_footprint_is_fixed() {
        let sizes = [
            ("Eskf", size_of::<Eskf>()),
            ("InfoAccumulator", size_of::<InfoAccumulator>()),
            ("ImuInitializer", size_of::<ImuInitializer>()),
            ("ImuQueue<256>", size_of::<ImuQueue<256>>()),
            ("ImuTrajectory<64>", size_of::<ImuTrajectory<64>>()),
            ("VoxelDownsampler<32768>", size_of::<VoxelDownsampler<32768>>()),
        ];
        for (n, s) in sizes {
            std::println!("{n}: {s} bytes");
        }
        assert!(size_of::<Eskf>() < 5 * 1024);
        // 68 bytes per slot (plus a 2 KiB row cache and the counters between the stages), 152
        // per knot.
        assert!(size_of::<VoxelDownsampler<32768>>() <= 32768 * 68 + 2048 + 64);
        assert!(size_of::<ImuTrajectory<64>>() <= 64 * 152 + 32);
    }
}
