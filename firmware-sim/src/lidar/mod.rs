//! Simulated spinning LiDARs: the sensors' firmware, emitting their real UDP packet formats.
//!
//! The firmware of each sensor (`velodyne`, `ouster`) knows its model's beams, firing timing and
//! packet layout. It decides *when* each laser fires and *where* it points (in the sensor frame,
//! at the true firing time) and asks an [`EchoSource`] what that laser sees. On the host the
//! source is the ray-cast world seen from the moving trajectory ([`scanner`]), so motion distorts
//! scans exactly as on a real vehicle; a test can plug in any other source.
//!
//! The firmware modules are `no_std` and allocation-free: packets and their ground truth are
//! written into caller-provided buffers.
//!
//! Frames: the sensor frame is x forward, y left, z up (the ROS convention the decoders use).
//! Velodyne azimuths are clockwise from +x, in hundredths of a degree on the wire.

pub mod ouster;
#[cfg(not(target_os = "none"))]
pub mod scanner;
pub mod velodyne;

/// One laser firing: when, which beam, and the ray in the sensor frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Firing {
    /// Absolute firing time, nanoseconds.
    pub t_ns: u64,
    /// A key unique to this firing (for the counter-based random numbers of its echo).
    pub key: u64,
    /// Laser id (Velodyne) or beam index (Ouster).
    pub beam: u16,
    /// Where the beam leaves the sensor, sensor frame, metres.
    pub origin: [f64; 3],
    /// Unit direction of the beam, sensor frame.
    pub dir: [f64; 3],
}

/// One echo of a firing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Echo {
    /// Measured distance from the beam origin, metres (noise included, not yet quantised).
    pub range: f64,
    /// Calibrated reflectivity the sensor reports (0-100 diffuse, 101-255 retroreflective).
    pub reflectivity: u8,
    /// Relative return strength (for choosing the strongest of two echoes, and signal counts).
    pub strength: f32,
}

/// What one firing returned: at most a partial (nearer) echo and the final echo.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Echoes {
    /// A nearer, partial echo (a leaf the beam partly went through).
    pub first: Option<Echo>,
    /// The echo of the surface that stopped the beam.
    pub last: Option<Echo>,
}

impl Echoes {
    /// The strongest echo (ties go to the last).
    pub fn strongest(&self) -> Option<Echo> {
        match (self.first, self.last) {
            (Some(f), Some(l)) => Some(if f.strength > l.strength { f } else { l }),
            (f, l) => l.or(f),
        }
    }

    /// The last echo (the first one if the beam was stopped by nothing else).
    pub fn last_echo(&self) -> Option<Echo> {
        self.last.or(self.first)
    }

    /// The echo a dual-return sensor pairs with the last one: the strongest, or the second
    /// strongest when the strongest is the last; the last itself when there is only one.
    pub fn dual_partner(&self) -> Option<Echo> {
        match (self.first, self.last) {
            (Some(f), Some(_)) => Some(f),
            (f, l) => l.or(f),
        }
    }
}

/// What the firmware asks about each firing.
pub trait EchoSource {
    /// Called once before the firings of a firing sequence (Velodyne) or column (Ouster) that
    /// starts at `t_ns`, so a source can prepare per-sequence state (the sensor pose).
    fn begin_sequence(&mut self, t_ns: u64);
    /// The echoes of one firing.
    fn measure(&mut self, f: &Firing) -> Echoes;
}

/// Which echoes a sensor reports.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ReturnMode {
    /// The strongest echo (Velodyne factory byte 0x37).
    Strongest,
    /// The last echo (0x38).
    Last,
    /// Both: last and strongest/second strongest (0x39).
    Dual,
}

/// The sensors the simulator models.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SensorModel {
    /// Velodyne VLP-16 (Puck).
    Vlp16,
    /// Velodyne VLP-32C (Ultra Puck).
    Vlp32c,
    /// Velodyne HDL-32E.
    Hdl32e,
    /// Ouster OS1-16.
    Os1_16,
    /// Ouster OS1-64.
    Os1_64,
    /// Ouster OS1-128 (45 degree field of view).
    Os1_128,
}

impl SensorModel {
    /// Every model.
    pub const ALL: [SensorModel; 6] =
        [Self::Vlp16, Self::Vlp32c, Self::Hdl32e, Self::Os1_16, Self::Os1_64, Self::Os1_128];

    /// Whether this is a Velodyne sensor.
    pub fn is_velodyne(&self) -> bool {
        matches!(self, Self::Vlp16 | Self::Vlp32c | Self::Hdl32e)
    }

    /// Number of beams.
    pub fn beams(&self) -> usize {
        match self {
            Self::Vlp16 | Self::Os1_16 => 16,
            Self::Vlp32c | Self::Hdl32e => 32,
            Self::Os1_64 => 64,
            Self::Os1_128 => 128,
        }
    }

    /// A short lower-case name (`vlp16`, `vlp32c`, `hdl32e`, `os1-16`, `os1-64`, `os1-128`).
    pub fn name(&self) -> &'static str {
        match self {
            Self::Vlp16 => "vlp16",
            Self::Vlp32c => "vlp32c",
            Self::Hdl32e => "hdl32e",
            Self::Os1_16 => "os1-16",
            Self::Os1_64 => "os1-64",
            Self::Os1_128 => "os1-128",
        }
    }

    /// Parses [`Self::name`].
    pub fn from_name(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|m| m.name().eq_ignore_ascii_case(s))
    }
}

/// Range noise, dropouts and limits of a simulated LiDAR.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RangeModel {
    /// Standard deviation of the range noise, metres.
    pub sigma: f64,
    /// Probability that any firing returns nothing (random dropout).
    pub dropout: f64,
    /// Nearest measurable range, metres.
    pub min_range: f64,
    /// Farthest measurable range (for a 100 % diffuse target), metres.
    pub max_range: f64,
}
