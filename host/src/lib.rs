//! loglio-host: the std shell around `loglio-core`. Data goes one way: sources ([`input`]) →
//! one run loop ([`run`]) → sinks ([`sink`]); each subcommand ([`cmd`]) wires them.
//!
//! | module | why |
//! |---|---|
//! | [`input`] | sources: pcap, UDP, serial and CSV IMU, ROS bags; packets decoded and assembled into scans |
//! | [`run`] | the one loop, also the library API ([`run::drive`]): storage, core odometry, input ordering |
//! | [`sink`] | outputs of a run: the files, and live ROS 2 / MAVLink / Foxglove / callback, never blocking |
//! | [`cmd`] | one module per subcommand: arguments in, a source and sinks out, then the run loop |
//! | [`error`] | the host's one-line error |
//! | [`config`] | the TOML configuration: presets, overrides, validation, the commented template |
//! | [`output`] | format writers: TUM, PLY/PCD, per-scan CSV, PNG/SVG plots, progress bar |
//! | [`eval`] | ATE/RPE against a ground truth, evo-compatible |
//! | [`diag`] | one-line `warning: ...` diagnostics |
//! | [`machine`] | which CPU this is (for `bench`) |
//! | [`knn_pca`] | kNN-PCA normals, the reference `normals` compares Ring FALS with |

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
