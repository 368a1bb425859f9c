//! Wire formats: zero-copy views over the bytes sensors send, with checked lengths, and parsed
//! representations (after smoltcp's `wire` module).

pub mod imu_frame;
pub mod ouster;
mod sync_buf;
pub mod vectornav;
pub mod velodyne;
pub mod velodyne_position;
pub mod xsens;
