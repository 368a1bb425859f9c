//! What predicts the pose from one scan to the next: the IMU (LiDAR-inertial, the default) or,
//! for a LiDAR without IMU, a constant velocity (LiDAR-only, as KISS-ICP predicts).
//!
//! **LiDAR-only** ([`MotionModel::ConstantVelocity`]):
//! - The world frame is the body frame (the IMU frame of the extrinsic; with the identity
//!   extrinsic the LiDAR's) at the first scan's end: that scan's pose is the identity and it
//!   only builds the map. Gravity is unknown, so the world is *not* gravity-aligned, and
//!   neither gravity nor the IMU biases nor the extrinsic are estimated.
//! - Every later scan is predicted with the rate and velocity between the last two updated
//!   scan ends (at rest before the second): the IMU-gap bridge's machinery
//!   ([`crate::eskf::Eskf::set_bridge_motion`]). That motion (constant rate, straight line)
//!   undistorts the scan; after the update the scan is undistorted again with the motion the
//!   update found and updated again from the same prediction, as a bridged scan is.
//! - The prediction's process noise is white acceleration and white rate ([`ConstantVelocity`]),
//!   large enough that the update, not the prior, decides the pose: over a 0.1 s scan the
//!   defaults grow the position sigma by 3.7 cm, the velocity's by 0.63 m/s and the attitude's by
//!   0.32 rad, against a scan update's few millimetres and few 1e-4 rad. The prediction is
//!   only the start of the iterated update and the association's search.
//! - The association, the update, the Ring FALS normals and the map are those of the
//!   LiDAR-inertial mode. Directions the scans do not constrain (a corridor's axis) get no
//!   correction and move on at the held velocity: without the IMU nothing bounds their drift.
//! - Every scan's [`crate::eskf::PropagationFlags`] carries `LIDAR_ONLY`; IMU samples pushed
//!   anyway are discarded.

/// The noise of the LiDAR-only constant-velocity prediction.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ConstantVelocity {
    /// White acceleration, per world axis, m/s^2/√Hz.
    pub acc_std: f64,
    /// White body rate, per axis, rad/s/√Hz.
    pub gyro_std: f64,
}

impl ConstantVelocity {
    /// The IMU-gap bridge's values (`EskfConfig::bridge_acc_std`, `bridge_gyro_std`): a walking
    /// or driving platform's changes of speed and turn rate within a scan or two (module docs).
    /// The prior hardly matters: 1 and 0.3 gave the same ATE to 1 % (docs/estimation.md).
    pub const DEFAULT: ConstantVelocity = ConstantVelocity { acc_std: 2.0, gyro_std: 1.0 };
}

/// What predicts the pose between scans.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum MotionModel {
    /// The IMU samples (LiDAR-inertial; the default).
    Imu,
    /// No IMU: a constant velocity (LiDAR-only; module docs).
    ConstantVelocity(ConstantVelocity),
}

impl MotionModel {
    /// LiDAR-only with the default noise.
    pub const LIDAR_ONLY: MotionModel = MotionModel::ConstantVelocity(ConstantVelocity::DEFAULT);

    /// Whether this is the LiDAR-only model.
    pub fn is_lidar_only(&self) -> bool {
        matches!(self, MotionModel::ConstantVelocity(_))
    }
}
