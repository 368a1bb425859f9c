//! loglio-firmware-sim: a deterministic simulated world, vehicle motion and sensors (Velodyne,
//! Ouster, an IMU board) that emit the real wire formats with exact ground truth, and the core
//! built as Cortex-M firmware (`bin/loglio-fw.rs`, fed by [`firmware_recording`]).
//!
//! Modules that would run on a device (the IMU chip model and board firmware, the packet
//! emitters, trajectories, randomness) are `no_std` and allocation-free; the world, the ray
//! caster, scenarios (the traffic scenario's moving actors included), files and live streaming
//! need `std` and are gated on a hosted target.
#![cfg_attr(target_os = "none", no_std)]

#[cfg(not(target_os = "none"))]
pub mod actors;
#[cfg(not(target_os = "none"))]
pub mod fault;
#[cfg(not(target_os = "none"))]
pub mod files;
pub mod firmware_recording;
pub mod imu_board;
pub mod imu_chip;
pub mod jet;
pub mod lidar;
#[cfg(not(target_os = "none"))]
pub mod live_sensors;
#[cfg(not(target_os = "none"))]
mod packet;
#[cfg(not(target_os = "none"))]
pub mod pcap_out;
#[cfg(not(target_os = "none"))]
pub mod raycast;
pub mod rng;
#[cfg(not(target_os = "none"))]
pub mod scenario;
#[cfg(not(target_os = "none"))]
pub mod stream;
pub mod terrain;
#[cfg(not(target_os = "none"))]
pub mod traffic;
pub mod trajectory;
#[cfg(not(target_os = "none"))]
pub mod tum;
#[cfg(not(target_os = "none"))]
pub mod world;
