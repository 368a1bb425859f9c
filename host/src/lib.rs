//! loglio-host: the std shell around `loglio-core`. It feeds the core from live sensors, pcap
//! files and ROS bags, and writes trajectories, maps and plots.

// Sensor ingestion (issue 3): pcap replay, live UDP and serial, IMU CSV, metadata and
// calibration files, LiDAR/IMU time alignment.
pub mod imu_csv;
pub mod ouster_meta;
pub mod pcap;
pub mod serial;
pub mod time_align;
pub mod udp;
pub mod velodyne_calib;
