//! # loglio-core
//!
//! The LOG-LIO LiDAR-inertial odometry as a `#![no_std]` library with no allocator: every byte
//! of working memory is owned by the caller (storage structs with `const fn new()` that can live
//! in a `static`, or slices the caller provides), and nothing inside reads a clock or draws a
//! random number. Inputs are bytes and timestamps, outputs are values, so a run is deterministic
//! and its memory is fixed at start-up.
//!
//! One module per concept of the paper (Huang et al., "LOG-LIO", RA-L 2023):
//!
//! | concept | module |
//! |---|---|
//! | points of a scan, their time and pixel | [`scan`] |
//! | range-image geometry of a spinning LiDAR | [`range_image`] |
//! | Ring FALS normals | [`ring_fals`] |
//! | wire formats (Velodyne, Ouster, IMU frames) | [`sensor`] |
//! | packets to whole scans (cut angle, drops, duplicates) | [`scan_assembly`] |
//! | IMU samples, initialisation and propagation | [`imu`] |
//! | voxel map with incremental distributions | [`voxel_map`], [`surfel`] |
//! | data association | [`association`] |
//! | iterated error-state Kalman filter | [`eskf`] |
//! | the per-scan pipeline | [`odometry`] |
//! | the motion model between scans (IMU, or LiDAR-only constant velocity) | [`motion_model`] |
//! | IMU outliers (beyond full scale, spikes, wrong stamps) | [`imu_guard`] |
//! | re-localisation in the map after a LiDAR gap or when lost | [`relocalise`] |
//! | the caller's clock for stage timing | [`clock`] |
#![no_std]
#![cfg_attr(not(test), forbid(unsafe_code))]

// clap's derive names `::std` paths.
#[cfg(feature = "clap")]
extern crate std;

#[macro_use]
mod fmt;

pub mod association;
pub mod clock;
pub mod downsample;
pub mod eskf;
pub mod free_space;
pub mod imu;
pub mod imu_guard;
pub mod math;
pub mod motion_model;
pub mod moving_objects;
pub mod odometry;
pub mod output;
pub mod parallel;
pub mod range_image;
pub mod relocalise;
pub mod ring_fals;
pub mod scan;
pub mod scan_assembly;
pub mod selection;
pub mod sensor;
pub mod so3;
pub mod standstill;
pub mod surfel;
#[cfg(test)]
mod testutil;
pub mod time_offset;
pub mod undistort;
pub mod voxel_map;
