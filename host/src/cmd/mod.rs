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

use crate::error::PipelineError;

/// When a live run stops and what it watches while it runs: the settings `live` and `ros2`
/// share (the CLI's `--seconds`, `--lidar-timeout`, `--imu-timeout`, `--quiet`), in one place so
/// that the two commands cannot drift apart.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Watch {
    /// Stop after this many seconds (from the moment reception starts).
    pub seconds: Option<f64>,
    /// Fail when no LiDAR data (packets, clouds) arrives within this many seconds of the start;
    /// warn when it stops for as long later.
    pub lidar_timeout_s: f64,
    /// Warn when no IMU sample arrives for this many seconds.
    pub imu_timeout_s: f64,
    /// Print the status line once a second.
    pub status: bool,
}

impl Default for Watch {
    /// No time limit, 10 s for the LiDAR, 3 s for the IMU, a status line.
    fn default() -> Self {
        Watch { seconds: None, lidar_timeout_s: 10.0, imu_timeout_s: 3.0, status: true }
    }
}

impl Watch {
    /// Checks the time limit and the LiDAR timeout (both commands check them the same way, with
    /// the CLI's option names in the message).
    pub fn check(&self) -> Result<(), PipelineError> {
        if !(self.lidar_timeout_s > 0.0 && self.lidar_timeout_s.is_finite()) {
            return Err(PipelineError(format!(
                "--lidar-timeout must be a positive number of seconds, not {}",
                self.lidar_timeout_s
            )));
        }
        if let Some(s) = self.seconds
            && !(s > 0.0 && s.is_finite())
        {
            return Err(PipelineError(format!("--seconds must be a positive number, not {s}")));
        }
        Ok(())
    }
}
