//! Everything a scenario's devices put on the wire, in time order: the LiDAR's UDP packets
//! (Velodyne data and position packets; Ouster lidar and IMU packets) and the IMU board's
//! serial bytes. File mode writes this stream to a pcap and a serial dump; live mode sends it to
//! UDP ports and a pseudo-terminal.
//!
//! Send times: a LiDAR packet leaves after its last firing; a Velodyne position packet follows
//! every 14th data packet; the Ouster sends an IMU packet every 10 ms; the IMU board writes a
//! frame at each sample.

use loglio_core::sensor::imu_frame::ImuFrame;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

use crate::imu_chip::{AccelFs, GyroFs, Icm42688, Odr, reg};
use crate::lidar::ouster::{self, IMU_IN_SENSOR};
use crate::lidar::scanner::{Firmware, WorldEchoes};
use crate::lidar::velodyne::{self, DATA_PER_POSITION, Velodyne};
// Re-exported: `stream::velodyne_packet` and `stream::ouster_packet` stay valid.
pub use crate::packet::{ouster_packet, velodyne_packet};
use crate::scenario::{ImuStream, Scenario};
use crate::trajectory::GRAVITY;

/// What goes on the wire.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Wire {
    /// A UDP datagram to a destination port.
    Udp {
        /// Destination port (2368, 8308, 7502, 7503).
        port: u16,
        /// The payload.
        payload: Vec<u8>,
    },
    /// Bytes on the IMU board's serial line.
    Serial(Vec<u8>),
}

/// One item on the wire and when it is sent.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WireEvent {
    /// Send time, absolute ns.
    pub t_ns: u64,
    /// What is sent.
    pub wire: Wire,
}

/// Origin of the simulated GNSS fix for Velodyne position packets (degrees).
pub const GNSS_ORIGIN: [f64; 2] = [48.137_4, 11.575_5];

/// Latitude/longitude of a local east-north position near [`GNSS_ORIGIN`].
pub fn lat_lon(east: f64, north: f64) -> (f64, f64) {
    let m_per_deg = 111_320.0;
    let lat = GNSS_ORIGIN[0] + north / m_per_deg;
    let lon = GNSS_ORIGIN[1] + east / (m_per_deg * libm::cos(GNSS_ORIGIN[0].to_radians()));
    (lat, lon)
}

/// The wire stream of a scenario.
#[derive(Debug)]
pub struct WireStream<'a> {
    sc: &'a Scenario,
    src: WorldEchoes<'a>,
    imu: ImuStream<Vec<u8>>,
    next_packet: u64,
    ouster_imu: Option<(Icm42688, u64)>,
    pending: Vec<WireEvent>,
    /// Data packets sent.
    pub lidar_packets: u64,
    /// IMU frames sent.
    pub imu_frames: u64,
}

impl<'a> WireStream<'a> {
    /// The stream of scenario `sc`.
    pub fn new(sc: &'a Scenario) -> Self {
        let ouster_imu = match sc.firmware() {
            Firmware::Ouster(_) => {
                let mut chip = Icm42688::new(sc.config().imu_noise, sc.config().seed ^ 0x0057_E21A);
                chip.write_reg(reg::GYRO_CONFIG0, (GyroFs::Dps500 as u8) << 5 | Odr::Hz100 as u8);
                chip.write_reg(reg::ACCEL_CONFIG0, (AccelFs::G4 as u8) << 5 | Odr::Hz100 as u8);
                chip.write_reg(reg::PWR_MGMT0, 0x0F);
                Some((chip, 0))
            }
            Firmware::Velodyne(_) => None,
        };
        Self {
            sc,
            src: sc.echo_source(),
            imu: ImuStream::new(sc, Vec::new()),
            next_packet: 0,
            ouster_imu,
            pending: Vec::new(),
            lidar_packets: 0,
            imu_frames: 0,
        }
    }

    fn packet_time(&self, k: u64) -> u64 {
        match self.sc.firmware() {
            Firmware::Velodyne(v) => {
                let last = (k + 1) * v.sequences_per_packet() - 1;
                v.sequence_time_ns(last) + v.firing_offset_ns(v.lasers() - 1)
            }
            Firmware::Ouster(o) => o.column_time_ns((k + 1) * ouster::COLUMNS_PER_PACKET as u64 - 1),
        }
    }

    fn ouster_imu_time(&self, k: u64) -> u64 {
        self.sc.start_ns() + 3_000_000 + k * 10_000_000
    }

    fn lidar_events(&mut self) -> Vec<WireEvent> {
        let k = self.next_packet;
        self.next_packet += 1;
        self.lidar_packets += 1;
        let t = self.packet_time(k);
        let sc = self.sc;
        match sc.firmware() {
            Firmware::Velodyne(v) => {
                let mut out = vec![WireEvent {
                    t_ns: t,
                    wire: Wire::Udp {
                        port: velodyne::DATA_PORT,
                        payload: velodyne_packet(v, k, &mut self.src).0,
                    },
                }];
                if k % DATA_PER_POSITION == DATA_PER_POSITION - 1 {
                    out.push(WireEvent {
                        t_ns: t,
                        wire: Wire::Udp {
                            port: velodyne::POSITION_PORT,
                            payload: self.position_packet(v, t),
                        },
                    });
                }
                out
            }
            Firmware::Ouster(o) => {
                vec![WireEvent {
                    t_ns: t,
                    wire: Wire::Udp {
                        port: ouster::LIDAR_PORT,
                        payload: ouster_packet(o, k, &mut self.src).0,
                    },
                }]
            }
        }
    }

    fn position_packet(&self, v: &Velodyne, t_ns: u64) -> Vec<u8> {
        // The GNSS receiver sends GPRMC once per second; the packet echoes the latest.
        let sec = t_ns / 1_000_000_000;
        let k = self.sc.kinematics_at((sec * 1_000_000_000).max(self.sc.start_ns()));
        let (lat, lon) = lat_lon(k.position.x, k.position.y);
        let speed_kn = libm::hypot(k.velocity.x, k.velocity.y) / 0.514_444;
        let course = libm::atan2(k.velocity.x, k.velocity.y).to_degrees();
        let mut nmea = [0u8; 96];
        let n = velodyne::gprmc(sec, lat, lon, speed_kn, course, &mut nmea).unwrap_or(0);
        let mut p = [0u8; velodyne::POSITION_PACKET_LEN];
        v.position_packet(t_ns, &nmea[..n], &mut p);
        p.to_vec()
    }

    fn ouster_imu_event(&mut self) -> Option<WireEvent> {
        let (k, t) = {
            let (_, k) = self.ouster_imu.as_ref()?;
            (*k, self.ouster_imu_time(*k))
        };
        let sc = self.sc;
        let t_io = sc.extrinsic()
            * Isometry3::from_parts(
                Translation3::new(IMU_IN_SENSOR[0], IMU_IN_SENSOR[1], IMU_IN_SENSOR[2]),
                UnitQuaternion::identity(),
            );
        let kin = sc.kinematics_at(t).attached(&t_io);
        let (w, f) = (kin.angular_velocity, kin.specific_force());
        let (chip, next) = self.ouster_imu.as_mut()?;
        *next = k + 1;
        let (g, a) = chip.sample([w.x, w.y, w.z], [f.x, f.y, f.z]);
        let (gl, al) = (chip.gyro_lsb().to_degrees(), chip.accel_lsb() / GRAVITY);
        let acc_g = [(a[0] as f64 * al) as f32, (a[1] as f64 * al) as f32, (a[2] as f64 * al) as f32];
        let gyro_dps = [(g[0] as f64 * gl) as f32, (g[1] as f64 * gl) as f32, (g[2] as f64 * gl) as f32];
        let mut b = [0u8; ouster::IMU_PACKET_LEN];
        ouster::imu_packet(t + 20_000, t, t, acc_g, gyro_dps, &mut b);
        Some(WireEvent { t_ns: t + 20_000, wire: Wire::Udp { port: ouster::IMU_PORT, payload: b.to_vec() } })
    }

    /// The IMU frames sent so far are in the serial bytes; this is the last frame's sample.
    fn imu_event(&mut self) -> Option<WireEvent> {
        let t = self.imu.peek_time()?;
        self.imu.next()?;
        self.imu_frames += 1;
        let bytes = core::mem::take(self.imu.serial());
        Some(WireEvent { t_ns: t, wire: Wire::Serial(bytes) })
    }
}

impl Iterator for WireStream<'_> {
    type Item = WireEvent;

    fn next(&mut self) -> Option<WireEvent> {
        let end = self.sc.end_ns();
        loop {
            // The earliest pending event, if nothing else can come before it.
            let t_lidar = self.packet_time(self.next_packet);
            let t_imu = self.imu.peek_time().unwrap_or(u64::MAX);
            let t_oimu =
                self.ouster_imu.as_ref().map_or(u64::MAX, |(_, k)| self.ouster_imu_time(*k) + 20_000);
            let t_pending = self.pending.iter().map(|e| e.t_ns).min().unwrap_or(u64::MAX);
            let t_next = t_lidar.min(t_imu).min(t_oimu);
            if t_pending <= t_next {
                let i = self.pending.iter().position(|e| e.t_ns == t_pending)?;
                return Some(self.pending.remove(i));
            }
            if t_next > end {
                return None;
            }
            if t_imu == t_next {
                return self.imu_event();
            }
            if t_oimu == t_next {
                return self.ouster_imu_event();
            }
            let evs = self.lidar_events();
            self.pending.extend(evs);
        }
    }
}

/// Parses every IMU frame out of a serial byte stream (as the host would).
pub fn decode_serial(bytes: &[u8]) -> Vec<ImuFrame> {
    let mut dec = loglio_core::sensor::imu_frame::FrameDecoder::new();
    let mut out = Vec::new();
    let mut rest = bytes;
    while !rest.is_empty() {
        let (n, f) = dec.feed(rest);
        out.extend(f);
        rest = &rest[n..];
    }
    out
}
