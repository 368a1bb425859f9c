//! loglio-host: the std shell around `loglio-core`. It feeds the core from live sensors, pcap
//! files and ROS bags, and writes trajectories, maps and plots.

pub mod knn_pca;
pub mod normals;
