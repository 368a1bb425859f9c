//! Scenarios: a world, a trajectory, a LiDAR and an IMU board, with exact ground truth.
//!
//! A [`Scenario`] yields, in time order, the IMU samples (exactly the values the IMU board
//! sends in its serial frames) and the LiDAR scans in the core's format ([`ScanPoint`]s in the
//! LiDAR frame at each point's firing time, with `t` since the scan start and the range-image
//! `row`/`col` of [`Scenario::layout`]). The same scenario also produces the real wire formats
//! (see [`crate::stream`]); both come from the same firings, so a scan and the decoded packets
//! of the same seed carry the same points.
//!
//! ```no_run
//! use loglio_firmware_sim::scenario::{Event, Scenario, ScenarioKind};
//! use loglio_firmware_sim::lidar::SensorModel;
//!
//! let sc = Scenario::new(ScenarioKind::Vehicle, SensorModel::Vlp32c, 42);
//! let t_imu_lidar = sc.extrinsic(); // LiDAR pose in the IMU frame (non-zero by default)
//! let layout = sc.layout();         // RangeImageLayout of the scans' row/col
//! for ev in sc.events() {
//!     match ev {
//!         Event::Imu(s) => { /* s.t_ns, s.gyro (rad/s), s.acc (m/s^2) */ }
//!         Event::Scan(scan) => {
//!             let truth = sc.pose_at(scan.end_ns); // T_world_imu at the scan end
//!             let _ = (scan.points.len(), truth);
//!         }
//!     }
//! }
//! ```

use loglio_core::imu::ImuSample;
use loglio_core::range_image::RangeImageLayout;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use crate::actors::{ActorPose, Actors};
use crate::imu_board::{BoardConfig, Discard, ImuBoard};
use crate::imu_chip::{ChipNoise, I2C_ADDRESS, Icm42688, MockI2c};
use crate::lidar::ouster::{Ouster, OusterConfig};
use crate::lidar::scanner::{DirectScanner, Firmware, SimScan, WorldEchoes};
use crate::lidar::velodyne::{Velodyne, VelodyneConfig};
use crate::lidar::{RangeModel, SensorModel};
use crate::terrain::Terrain;
use crate::traffic::Traffic;
use crate::trajectory::{DRONE_START, Kinematics, Trajectory};
use crate::world::{SceneKind, World};

/// 2024-05-01 12:10:00 UTC, the default time origin (Unix ns).
pub const DEFAULT_START_UNIX_NS: u64 = 1_714_565_400_000_000_000;

/// The standard scenarios.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ScenarioKind {
    /// A car driving a loop through the town (up to ~10 m/s, turns, slopes).
    Vehicle,
    /// A person walking through the indoor hall holding the sensor (gait motion).
    Handheld,
    /// A robot driving 40 s down a long featureless corridor (degenerate along its axis).
    Corridor,
    /// A drone climbing from a courtyard among buildings into open sky.
    Drone,
    /// Fast handheld rotation (up to ~180 deg/s) in the hall.
    FastRotation,
    /// The vehicle's car in the town among moving vehicles and pedestrians, with a stop at a
    /// junction (see [`crate::traffic`]).
    Traffic,
    /// A car driving 3.2 km at 12.5 m/s on average (up to 20 m/s) around a 3.1 km loop with bends, once round and on
    /// past its start, through streets like the town's: the map's memory bound and the drift
    /// per distance.
    Long,
}

impl ScenarioKind {
    /// Every scenario.
    pub const ALL: [ScenarioKind; 7] = [
        Self::Vehicle,
        Self::Handheld,
        Self::Corridor,
        Self::Drone,
        Self::FastRotation,
        Self::Traffic,
        Self::Long,
    ];

    /// The world it happens in.
    pub fn scene(&self) -> SceneKind {
        match self {
            Self::Vehicle | Self::Drone | Self::Traffic => SceneKind::Town,
            Self::Handheld | Self::FastRotation => SceneKind::Hall,
            Self::Corridor => SceneKind::Corridor,
            Self::Long => SceneKind::LongLoop,
        }
    }

    /// Default length, seconds (2 s at rest included).
    pub fn default_duration_s(&self) -> f64 {
        match self {
            Self::FastRotation => 30.0,
            Self::Traffic => crate::traffic::DURATION_S,
            Self::Long => crate::trajectory::LONG_DURATION_S,
            _ => 40.0,
        }
    }

    /// Name for the command line (`vehicle`, `handheld`, `corridor`, `drone`, `rotation`,
    /// `traffic`, `long`).
    pub fn name(&self) -> &'static str {
        match self {
            Self::Vehicle => "vehicle",
            Self::Handheld => "handheld",
            Self::Corridor => "corridor",
            Self::Drone => "drone",
            Self::FastRotation => "rotation",
            Self::Traffic => "traffic",
            Self::Long => "long",
        }
    }

    /// Parses [`Self::name`].
    pub fn from_name(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name().eq_ignore_ascii_case(s))
    }
}

/// The LiDAR's configuration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LidarConfig {
    /// A Velodyne.
    Velodyne(VelodyneConfig),
    /// An Ouster.
    Ouster(OusterConfig),
}

impl LidarConfig {
    /// The model's defaults.
    pub fn default_for(model: SensorModel) -> Self {
        if model.is_velodyne() {
            Self::Velodyne(VelodyneConfig::default_for(model))
        } else {
            Self::Ouster(OusterConfig::default_for(model))
        }
    }

    /// The model.
    pub fn model(&self) -> SensorModel {
        match self {
            Self::Velodyne(c) => c.model,
            Self::Ouster(c) => c.model,
        }
    }

    /// The same LiDAR at `hz` scans per second: a Velodyne at `60 hz` rpm (5 to 20 Hz), an
    /// Ouster in the mode of its columns at 10 or 20 Hz (2048 columns only at 10 Hz).
    pub fn with_scan_rate_hz(self, hz: u32) -> Result<Self, &'static str> {
        use crate::lidar::ouster::LidarMode as M;
        match self {
            Self::Velodyne(mut c) => {
                if !(5..=20).contains(&hz) {
                    return Err("a Velodyne turns at 5 to 20 Hz (300-1200 rpm)");
                }
                c.rpm = 60.0 * f64::from(hz);
                Ok(Self::Velodyne(c))
            }
            Self::Ouster(mut c) => {
                c.mode = match (c.mode.columns(), hz) {
                    (512, 10) => M::M512x10,
                    (512, 20) => M::M512x20,
                    (1024, 10) => M::M1024x10,
                    (1024, 20) => M::M1024x20,
                    (2048, 10) => M::M2048x10,
                    _ => return Err("an Ouster scans at 10 or 20 Hz (2048 columns at 10 Hz only)"),
                };
                Ok(Self::Ouster(c))
            }
        }
    }

    /// Scans per second.
    pub fn scan_rate_hz(&self) -> f64 {
        match self {
            Self::Velodyne(c) => c.rpm / 60.0,
            Self::Ouster(c) => c.mode.rate_hz() as f64,
        }
    }

    /// The range model.
    pub fn range_mut(&mut self) -> &mut RangeModel {
        match self {
            Self::Velodyne(c) => &mut c.range,
            Self::Ouster(c) => &mut c.range,
        }
    }
}

/// Everything that defines a scenario.
#[derive(Clone, Debug, PartialEq)]
pub struct ScenarioConfig {
    /// Which scenario.
    pub kind: ScenarioKind,
    /// The seed of the world and of every noise.
    pub seed: u64,
    /// Length, seconds.
    pub duration_s: f64,
    /// Unix time of t = 0, ns.
    pub start_unix_ns: u64,
    /// The LiDAR.
    pub lidar: LidarConfig,
    /// Pose of the LiDAR (its output frame) in the IMU frame.
    pub extrinsic: Isometry3<f64>,
    /// IMU noise figures.
    pub imu_noise: ChipNoise,
    /// IMU board settings (full scales, rate).
    pub imu_board: BoardConfig,
    /// Time of the first IMU sample after t = 0, ns (so samples do not coincide with firings).
    pub imu_phase_ns: u64,
    /// Worker threads for scan generation (the output does not depend on it).
    pub threads: usize,
    /// The scenario's moving actors (the traffic scenario's; false: the same drive through the
    /// same world with nobody else on the road).
    pub actors: bool,
    /// The IMU board's clock minus the true time (the LiDAR's clock), ns: its samples are
    /// stamped this much later (earlier when negative) than they were taken, as an IMU on a
    /// clock of its own. 0: one clock.
    pub imu_clock_offset_ns: i64,
}

impl ScenarioConfig {
    /// The defaults of a scenario: its standard duration, the sensor's defaults, the
    /// ICM-42688-P at 200 Hz, and a LiDAR mounted 0.1 m from the IMU with a small rotation.
    pub fn new(kind: ScenarioKind, sensor: SensorModel, seed: u64) -> Self {
        Self {
            kind,
            seed,
            duration_s: kind.default_duration_s(),
            start_unix_ns: DEFAULT_START_UNIX_NS,
            lidar: LidarConfig::default_for(sensor),
            extrinsic: default_extrinsic(),
            imu_noise: ChipNoise::icm42688p(),
            imu_board: BoardConfig::default(),
            imu_phase_ns: 1_250_000,
            threads: std::thread::available_parallelism().map_or(1, |n| n.get().min(4)),
            actors: true,
            imu_clock_offset_ns: 0,
        }
    }
}

/// The default LiDAR-in-IMU pose: translation (0.08, -0.04, 0.05) m (0.10 m), rotation
/// roll 0.5, pitch -1.0, yaw 2.0 degrees.
pub fn default_extrinsic() -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.08, -0.04, 0.05),
        UnitQuaternion::from_euler_angles(0.5f64.to_radians(), -1.0f64.to_radians(), 2.0f64.to_radians()),
    )
}

/// Why a scenario could not be built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScenarioError {
    /// The LiDAR configuration is invalid (model mismatch or rotation rate).
    Lidar,
    /// Duration not in (0, 600] s.
    Duration,
}

impl core::fmt::Display for ScenarioError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Lidar => "invalid LiDAR configuration",
            Self::Duration => "duration must be in (0, 600] seconds",
        })
    }
}

impl std::error::Error for ScenarioError {}

/// One item of a scenario, in time order.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// An IMU sample (the IMU board's frame, as the host decodes it).
    Imu(ImuSample),
    /// A complete LiDAR scan (delivered after its last firing).
    Scan(SimScan),
}

impl Event {
    /// The event's time: the IMU sample time or the scan's last firing, ns.
    pub fn t_ns(&self) -> u64 {
        match self {
            Event::Imu(s) => s.t_ns,
            Event::Scan(s) => s.end_ns,
        }
    }
}

/// A scenario, ready to generate.
#[derive(Clone, Debug)]
pub struct Scenario {
    cfg: ScenarioConfig,
    world: World,
    traj: Trajectory,
    firmware: Firmware,
    layout: RangeImageLayout,
    actors: Actors,
}

impl Scenario {
    /// A standard scenario with every default (see [`ScenarioConfig::new`]).
    pub fn new(kind: ScenarioKind, sensor: SensorModel, seed: u64) -> Scenario {
        Self::from_config(ScenarioConfig::new(kind, sensor, seed)).expect("default configurations are valid")
    }

    /// A scenario from a full configuration.
    pub fn from_config(cfg: ScenarioConfig) -> Result<Scenario, ScenarioError> {
        if !(cfg.duration_s > 0.0 && cfg.duration_s <= 600.0) {
            return Err(ScenarioError::Duration);
        }
        let (world, actors) = if cfg.kind == ScenarioKind::Traffic {
            let traffic = Traffic::new(&Terrain::town());
            let world = traffic.world(cfg.seed);
            (world, if cfg.actors { traffic.actors } else { Actors::default() })
        } else {
            (World::build(cfg.kind.scene(), cfg.seed), Actors::default())
        };
        let traj = match cfg.kind {
            ScenarioKind::Vehicle => Trajectory::Vehicle { terrain: world.terrain.clone() },
            ScenarioKind::Handheld => Trajectory::Handheld,
            ScenarioKind::Corridor => Trajectory::Corridor,
            ScenarioKind::Drone => {
                Trajectory::Drone { ground_z: world.ground_height(DRONE_START[0], DRONE_START[1]) }
            }
            ScenarioKind::FastRotation => Trajectory::FastRotation,
            ScenarioKind::Traffic => Trajectory::Traffic { terrain: world.terrain.clone() },
            ScenarioKind::Long => Trajectory::Long { terrain: world.terrain.clone() },
        };
        let firmware = match cfg.lidar {
            LidarConfig::Velodyne(c) => {
                Firmware::Velodyne(Velodyne::new(c, cfg.start_unix_ns).map_err(|_| ScenarioError::Lidar)?)
            }
            LidarConfig::Ouster(c) => {
                Firmware::Ouster(Ouster::new(c, cfg.start_unix_ns).map_err(|_| ScenarioError::Lidar)?)
            }
        };
        let layout = firmware.layout();
        Ok(Scenario { cfg, world, traj, firmware, layout, actors })
    }

    /// The configuration.
    pub fn config(&self) -> &ScenarioConfig {
        &self.cfg
    }

    /// The world.
    pub fn world(&self) -> &World {
        &self.world
    }

    /// The moving actors (empty but in the traffic scenario).
    pub fn actors(&self) -> &Actors {
        &self.actors
    }

    /// Where every actor is at an absolute time.
    pub fn actors_at(&self, t_ns: u64) -> Vec<ActorPose> {
        self.actors.at(self.seconds(t_ns))
    }

    /// The id of an actor whose box contains a world point at an absolute time.
    pub fn inside_actor(&self, p: [f64; 3], t_ns: u64) -> Option<u32> {
        self.actors.inside(p, self.seconds(t_ns))
    }

    /// The id of an actor whose swept volume over [t0_ns, t1_ns] contains a world point (for the
    /// share of map points left behind by moving objects).
    pub fn inside_actor_swept(&self, p: [f64; 3], t0_ns: u64, t1_ns: u64) -> Option<u32> {
        self.actors.inside_swept(p, self.seconds(t0_ns), self.seconds(t1_ns))
    }

    /// Writes the actors' ground truth at `hz` over the scenario as CSV (see
    /// [`Actors::write_csv`]).
    pub fn write_actors_csv(&self, path: &std::path::Path, hz: f64) -> std::io::Result<()> {
        let f = std::io::BufWriter::new(std::fs::File::create(path)?);
        self.actors.write_csv(f, self.cfg.start_unix_ns, 0.0, self.cfg.duration_s, hz)
    }

    /// The trajectory of the IMU frame (time in seconds since [`Self::start_ns`]).
    pub fn trajectory(&self) -> &Trajectory {
        &self.traj
    }

    /// The LiDAR firmware.
    pub fn firmware(&self) -> &Firmware {
        &self.firmware
    }

    /// The range-image layout of the scans' `row`/`col`.
    pub fn layout(&self) -> &RangeImageLayout {
        &self.layout
    }

    /// Pose of the LiDAR frame in the IMU frame (T_imu_lidar).
    pub fn extrinsic(&self) -> Isometry3<f64> {
        self.cfg.extrinsic
    }

    /// Absolute time of t = 0, ns.
    pub fn start_ns(&self) -> u64 {
        self.cfg.start_unix_ns
    }

    /// Absolute end time, ns.
    pub fn end_ns(&self) -> u64 {
        self.cfg.start_unix_ns + (self.cfg.duration_s * 1e9) as u64
    }

    /// Seconds since the start of an absolute time.
    pub fn seconds(&self, t_ns: u64) -> f64 {
        (t_ns as i128 - self.cfg.start_unix_ns as i128) as f64 * 1e-9
    }

    /// Exact kinematics of the IMU frame at an absolute time: pose, velocity, acceleration,
    /// body rates; [`Kinematics::specific_force`] gives the ideal accelerometer reading.
    pub fn kinematics_at(&self, t_ns: u64) -> Kinematics {
        self.traj.eval(self.seconds(t_ns).max(0.0))
    }

    /// Ground-truth pose of the IMU in the world (T_world_imu) at an absolute time.
    pub fn pose_at(&self, t_ns: u64) -> Isometry3<f64> {
        self.kinematics_at(t_ns).pose()
    }

    /// Ground-truth pose of the LiDAR in the world (T_world_lidar) at an absolute time.
    pub fn lidar_pose_at(&self, t_ns: u64) -> Isometry3<f64> {
        self.pose_at(t_ns) * self.cfg.extrinsic
    }

    /// An echo source for this scenario's LiDAR (what the firmware asks on the host).
    pub fn echo_source(&self) -> WorldEchoes<'_> {
        let range = match &self.cfg.lidar {
            LidarConfig::Velodyne(c) => c.range,
            LidarConfig::Ouster(c) => c.range,
        };
        WorldEchoes::new(
            &self.world.scene,
            &self.traj,
            self.cfg.extrinsic,
            self.cfg.start_unix_ns,
            self.cfg.seed ^ 0x11DA_2000,
            range,
        )
        .with_actors(&self.actors)
    }

    /// A direct scanner over this scenario's LiDAR.
    pub fn scanner(&self) -> DirectScanner {
        let mut s = DirectScanner::new(self.firmware.clone());
        s.threads = self.cfg.threads;
        s
    }

    /// Velodyne data packet `k` (1206-byte UDP payload) with the ground truth of every
    /// non-zero data point it encodes (sensor-frame xyz at the firing time, firing time, laser);
    /// `None` for an Ouster scenario. For decoder round-trip tests.
    pub fn velodyne_packet(&self, k: u64) -> Option<(Vec<u8>, Vec<crate::lidar::velodyne::TruthPoint>)> {
        match &self.firmware {
            Firmware::Velodyne(v) => Some(crate::packet::velodyne_packet(v, k, &mut self.echo_source())),
            Firmware::Ouster(_) => None,
        }
    }

    /// Ouster lidar packet `k` with the ground truth of every non-zero pixel; `None` for a
    /// Velodyne scenario.
    pub fn ouster_packet(&self, k: u64) -> Option<(Vec<u8>, Vec<crate::lidar::ouster::OusterTruth>)> {
        match &self.firmware {
            Firmware::Ouster(o) => Some(crate::packet::ouster_packet(o, k, &mut self.echo_source())),
            Firmware::Velodyne(_) => None,
        }
    }

    /// Scan `j` (revolution or frame `j` since the start).
    pub fn scan(&self, j: u64) -> SimScan {
        self.scanner().scan(j, || self.echo_source())
    }

    /// The IMU samples in time order.
    pub fn imu_samples(&self) -> ImuStream<Discard> {
        ImuStream::new(self, Discard)
    }

    /// Every event (IMU samples and scans) in time order.
    ///
    /// Scans are generated ahead on a background thread (at most two waiting), so that their
    /// generation overlaps whatever the caller does with the previous ones; the events are the
    /// same as without it (every ray is a pure function of the seed).
    pub fn events(&self) -> Events<'_> {
        let scanner = self.scanner();
        let (tx, rx) = std::sync::mpsc::sync_channel(2);
        let owned = std::sync::Arc::new(self.clone());
        let worker = std::thread::Builder::new()
            .name("loglio-sim-scans".into())
            .spawn(move || {
                let mut scanner = owned.scanner();
                while scanner.scan_end_ns(scanner.next_index()) <= owned.end_ns() {
                    let scan = scanner.next(|| owned.echo_source());
                    if tx.send(scan).is_err() {
                        break; // the consumer is gone
                    }
                }
            })
            .ok();
        let rx = worker.as_ref().map(|_| rx);
        Events {
            sc: self,
            imu: self.imu_samples(),
            pending: None,
            scanner,
            scan_end: None,
            imu_done: false,
            rx,
            _worker: worker,
        }
    }
}

/// The IMU board running along the trajectory; yields samples and writes frames to `W`.
#[derive(Debug)]
pub struct ImuStream<W: embedded_io::Write> {
    traj: Trajectory,
    start_ns: u64,
    phase_ns: u64,
    period_ns: u64,
    end_ns: u64,
    k: u64,
    board: ImuBoard<MockI2c, W>,
    clock_offset_ns: i64,
}

impl<W: embedded_io::Write> ImuStream<W> {
    /// The board of scenario `sc`, writing its serial frames into `serial`.
    pub fn new(sc: &Scenario, serial: W) -> Self {
        let chip = Icm42688::new(sc.cfg.imu_noise, sc.cfg.seed ^ 0x1A0_B0A2D);
        let mut board = ImuBoard::new(MockI2c::new(chip, I2C_ADDRESS), serial, I2C_ADDRESS);
        // The mock chip always answers with its identity; configuration cannot fail.
        let _ = board.init(sc.cfg.imu_board);
        let period_ns = 1_000_000_000 / sc.cfg.imu_board.odr.hz() as u64;
        Self {
            traj: sc.traj.clone(),
            start_ns: sc.start_ns(),
            phase_ns: sc.cfg.imu_phase_ns % period_ns,
            period_ns,
            end_ns: sc.end_ns(),
            k: 0,
            board,
            clock_offset_ns: sc.cfg.imu_clock_offset_ns,
        }
    }

    /// Time of the next sample, if within the scenario.
    pub fn peek_time(&self) -> Option<u64> {
        let t = self.start_ns + self.phase_ns + self.k * self.period_ns;
        (t <= self.end_ns).then_some(t)
    }

    /// The board's serial sink.
    pub fn serial(&mut self) -> &mut W {
        self.board.serial()
    }

    /// The chip's current biases (gyro rad/s, accel m/s^2), for tests.
    pub fn biases(&mut self) -> ([f64; 3], [f64; 3]) {
        self.board.bus_mut().chip().biases()
    }
}

impl<W: embedded_io::Write> Iterator for ImuStream<W> {
    type Item = ImuSample;

    fn next(&mut self) -> Option<ImuSample> {
        let t_ns = self.peek_time()?;
        self.k += 1;
        let kin = self.traj.eval((t_ns - self.start_ns) as f64 * 1e-9);
        let w = kin.angular_velocity;
        let f: Vector3<f64> = kin.specific_force();
        self.board.bus_mut().chip_mut().sample([w.x, w.y, w.z], [f.x, f.y, f.z]);
        // The chip was just given a sample and the sink accepts everything: the handler can only
        // fail on a serial error, which ends the stream. The board latches its own clock.
        let t_board = t_ns.saturating_add_signed(self.clock_offset_ns);
        self.board.on_data_ready(t_board).ok().map(|fr| fr.sample())
    }
}

/// The time-ordered events of a scenario.
#[derive(Debug)]
pub struct Events<'a> {
    sc: &'a Scenario,
    imu: ImuStream<Discard>,
    pending: Option<ImuSample>,
    /// Knows the scans' times (and generates them itself if no thread could be started).
    scanner: DirectScanner,
    scan_end: Option<u64>,
    imu_done: bool,
    rx: Option<std::sync::mpsc::Receiver<SimScan>>,
    _worker: Option<std::thread::JoinHandle<()>>,
}

impl Iterator for Events<'_> {
    type Item = Event;

    fn next(&mut self) -> Option<Event> {
        if self.pending.is_none() && !self.imu_done {
            self.pending = self.imu.next();
            self.imu_done = self.pending.is_none();
        }
        let end = *self.scan_end.get_or_insert_with(|| self.scanner.scan_end_ns(self.scanner.next_index()));
        let scan_ok = end <= self.sc.end_ns();
        match self.pending {
            Some(s) if !scan_ok || s.t_ns <= end => {
                self.pending = None;
                Some(Event::Imu(s))
            }
            _ if scan_ok => {
                self.scan_end = None;
                let j = self.scanner.next_index();
                let prefetched = self.rx.as_ref().and_then(|rx| rx.recv().ok());
                let scan = match prefetched {
                    Some(s) => {
                        self.scanner.skip(1);
                        s
                    }
                    None => {
                        let sc = self.sc;
                        self.scanner.next(|| sc.echo_source())
                    }
                };
                debug_assert_eq!(scan.index, j);
                Some(Event::Scan(scan))
            }
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scans_do_not_depend_on_threads_or_prefetch() {
        let mut cfg = ScenarioConfig::new(ScenarioKind::FastRotation, SensorModel::Vlp32c, 3);
        cfg.duration_s = 2.6;
        cfg.threads = 1;
        let one = Scenario::from_config(cfg.clone()).unwrap();
        cfg.threads = 3;
        let three = Scenario::from_config(cfg).unwrap();
        assert_eq!(one.scan(24), three.scan(24));
        let ev: Vec<Event> = three.events().collect();
        let scans: Vec<&SimScan> =
            ev.iter().filter_map(|e| if let Event::Scan(s) = e { Some(s) } else { None }).collect();
        assert_eq!(scans.len(), 26);
        assert_eq!(*scans[24], one.scan(24));
    }

    #[test]
    fn traffic_scans_do_not_depend_on_threads_and_actors_change_only_their_rays() {
        let mut cfg = ScenarioConfig::new(ScenarioKind::Traffic, SensorModel::Vlp16, 3);
        cfg.threads = 1;
        let one = Scenario::from_config(cfg.clone()).unwrap();
        cfg.threads = 3;
        let three = Scenario::from_config(cfg.clone()).unwrap();
        cfg.actors = false;
        let bare = Scenario::from_config(cfg).unwrap();
        // Scan 240 (24 s): the car waits at the junction among cross traffic and pedestrians.
        let (a, b, c) = (one.scan(240), three.scan(240), bare.scan(240));
        assert_eq!(a, b);
        assert_ne!(a, c);
        // Same firings, same noise: the points of rays that meet no actor are identical.
        let key = |p: &loglio_core::scan::ScanPoint| (p.row, p.col, p.ret, p.t.to_bits());
        let bare_pts: std::collections::HashMap<_, _> = c.points.iter().map(|p| (key(p), *p)).collect();
        let same = a.points.iter().filter(|p| bare_pts.get(&key(p)) == Some(p)).count();
        assert!(same * 10 > a.points.len() * 9 && same < a.points.len(), "{same} of {}", a.points.len());
    }

    #[test]
    fn packet_helpers_match_the_sensor_kind() {
        let v = Scenario::new(ScenarioKind::Corridor, SensorModel::Vlp16, 1);
        let (bytes, truth) = v.velodyne_packet(3).unwrap();
        assert_eq!(bytes.len(), 1206);
        assert!(!truth.is_empty() && truth.iter().all(|t| t.raw_distance > 0));
        assert!(v.ouster_packet(3).is_none());
        let o = Scenario::new(ScenarioKind::Corridor, SensorModel::Os1_16, 1);
        let (bytes, truth) = o.ouster_packet(3).unwrap();
        assert_eq!(bytes.len(), 32 + 16 * (12 + 12 * 16) + 32);
        assert!(!truth.is_empty());
        assert!(o.velodyne_packet(3).is_none());
    }

    #[test]
    fn events_are_time_ordered_and_complete() {
        let mut cfg = ScenarioConfig::new(ScenarioKind::Handheld, SensorModel::Vlp16, 7);
        cfg.duration_s = 1.05;
        let sc = Scenario::from_config(cfg).unwrap();
        let mut last = 0;
        let (mut imu, mut scans) = (0, 0);
        for ev in sc.events() {
            assert!(ev.t_ns() >= last);
            last = ev.t_ns();
            match ev {
                Event::Imu(s) => {
                    assert!(s.t_ns >= sc.start_ns() && s.t_ns <= sc.end_ns());
                    imu += 1;
                }
                Event::Scan(s) => {
                    assert_eq!(s.index, scans);
                    assert!(s.points.len() > 20_000, "{}", s.points.len());
                    let span = (s.end_ns - s.start_ns) as f32 * 1e-9;
                    assert!(span > 0.0999 && span < 0.1001, "{span}");
                    assert!(s.points.iter().all(|p| p.t >= 0.0 && p.t <= span + 1e-6 && p.has_pixel()));
                    scans += 1;
                }
            }
        }
        assert_eq!(imu, 210);
        assert_eq!(scans, 10);
    }
}
