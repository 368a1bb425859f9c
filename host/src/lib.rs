//! loglio-host: the std shell around `loglio-core`. It feeds the core from live sensors, pcap
//! files and ROS bags, and writes trajectories, maps and plots.

pub mod imu_csv;
pub mod knn_pca;
pub mod normals;
pub mod ouster_meta;
pub mod pcap;
pub mod serial;
pub mod time_align;
pub mod udp;
pub mod velodyne_calib;
