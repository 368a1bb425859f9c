//! loglio-firmware-sim: a deterministic simulated world, vehicle motion and sensors (Velodyne,
//! Ouster, an IMU board) that emit the real wire formats with exact ground truth, and the core
//! built as Cortex-M firmware.
#![cfg_attr(target_os = "none", no_std)]
