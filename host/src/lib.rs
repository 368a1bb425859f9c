//! loglio-host: the std shell around `loglio-core`. It feeds the core from live sensors, pcap
//! files and ROS bags, and writes trajectories, maps and plots.
//!
//! | module | what |
//! |---|---|
//! | [`bag`] | ROS 1 bags, rosbag2 sqlite3 and MCAP in, a time-ordered event stream out; a ROS 1 bag writer |
//! | [`bagrun`] | `loglio bag`: the odometry over a ROS 1 / rosbag2 / MCAP bag (clouds or packets) |
//! | [`bench`] | `loglio bench`: per-stage times and real-time margin of a preset, with a baseline |
//! | [`config`] | the TOML configuration: presets, overrides, validation, the commented template |
//! | [`diag`] | one-line `warning: ...` diagnostics |
//! | [`eval`] | ATE/RPE against a ground truth, evo-compatible |
//! | [`output`] | TUM trajectory, PLY/PCD map, per-scan CSV, PNG/SVG plots, progress bar |
//! | [`lidar_stream`] | raw Velodyne/Ouster packets to scans and IMU samples (decoders, time alignment, scan assembly) |
//! | [`live`] | `loglio live`: UDP LiDAR and serial or Ouster IMU on their own threads, bounded queues, status line, Ctrl-C |
//! | [`replay`] | `loglio replay`: pcap plus IMU CSV, serial capture or Ouster IMU packets |
//! | [`sim`] | `loglio sim` / `demo`: a firmware-sim scenario end to end, ATE against its ground truth |
//! | [`run`] | the run loop as a library: a source of events, the odometry, the files and the sinks; signals |
//! | [`sink`] | live outputs: each scan's result and the high-rate pose to ROS 2, MAVLink, Foxglove or a callback, never blocking |
//! | [`pipeline`] | the configuration onto the core odometry, its heap storage, input ordering and outputs |

pub mod cmd;
pub mod config;
pub mod diag;
pub mod error;
pub mod eval;
pub mod input;
pub mod knn_pca;
pub mod machine;
pub mod output;

pub mod run;
pub mod sink;
