//! One module per subcommand that runs the odometry: its arguments in, a source and sinks out,
//! then the run loop.

pub mod bag;
pub mod bench;
pub mod live;
pub mod normals;
pub mod replay;
pub mod sim;
