//! The sources: everything that brings sensor data into a run (files, sockets, serial ports,
//! bags), decodes it and hands the run loop time-ordered IMU samples and whole scans.

pub mod bag;
pub mod device_imu;
pub mod extrinsic_file;
pub mod imu_csv;
pub mod lidar_stream;
pub mod mavlink_imu;
pub mod ouster_meta;
pub mod pace;
pub mod pcap;
pub mod ros2;
pub mod serial;
pub mod time_align;
pub mod udp;
pub mod velodyne_calib;
