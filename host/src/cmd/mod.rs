//! One module per subcommand that runs the odometry: its arguments in, a source and sinks out,
//! then the run loop. `sim` and `bench` need the simulator (feature `sim`).

pub mod bag;
#[cfg(feature = "sim")]
pub mod bench;
pub mod live;
pub mod normals;
pub mod replay;
pub mod ros2;
#[cfg(feature = "sim")]
pub mod sim;
