//! IMU measurements. (Initialisation and propagation join this module with the odometry.)

/// One IMU sample in the IMU frame, as every source (serial frames, Ouster IMU packets, CSV)
/// delivers it to the core.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ImuSample {
    /// Absolute time, nanoseconds, on the same clock as the scans' `start_ns`.
    pub t_ns: u64,
    /// Angular rate, rad/s.
    pub gyro: [f32; 3],
    /// Specific force, m/s^2 (IMUs that report in g are detected at initialisation).
    pub acc: [f32; 3],
}
