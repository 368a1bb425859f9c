//! Raw sensor packets (pcap replay, live UDP, bag packets) to scans and IMU samples: the core's
//! Velodyne or Ouster decoder, the host's time alignment and the core's scan assembly.

use loglio_core::imu::ImuSample;
use loglio_core::range_image::RangeImageLayout;
use loglio_core::scan::ScanPoint;
use loglio_core::scan_assembly::{AssemblerConfig, AssemblyStats, ScanAssembler};
use loglio_core::sensor::ouster::{self, OusterIntrinsics};
use loglio_core::sensor::velodyne::{self, Model};
use loglio_core::sensor::velodyne_position::{PositionPacket, PositionRepr};

use crate::config::{Config, LidarTimeSource, Preset, SensorFamily};
use crate::error::PipelineError;
use crate::input::time_align::{self, TimeAlignConfig, VelodyneClock};
use crate::run::runner::OwnedScan;

/// Velodyne position packets' UDP port.
pub const VELODYNE_POSITION_PORT: u16 = 8308;

/// The decoder of one sensor.
#[derive(Debug)]
#[allow(clippy::large_enum_variant)] // one per run
pub enum SensorDecoder {
    /// A Velodyne and its hour-resolving clock.
    Velodyne {
        /// The decoder.
        dec: velodyne::Decoder,
        /// Microseconds past the hour to absolute time.
        clock: VelodyneClock,
    },
    /// An Ouster.
    Ouster(ouster::Decoder),
}

impl SensorDecoder {
    /// The decoder for a configuration; Ouster sensors need their intrinsics (metadata).
    pub fn new(cfg: &Config, ouster_intr: Option<&OusterIntrinsics>) -> Result<Self, PipelineError> {
        match cfg.preset.family() {
            SensorFamily::Velodyne => {
                let model = match cfg.preset {
                    Preset::Vlp16 => Model::Vlp16,
                    Preset::Vlp32c => Model::Vlp32c,
                    _ => Model::Hdl32e,
                };
                let mut vc = velodyne::Config::new(model);
                vc.columns = cfg.sensor.columns.min(u16::MAX as u32) as u16;
                vc.max_range = vc.max_range.max(cfg.sensor.max_range as f32);
                let dec = match &cfg.sensor.calibration {
                    Some(p) => {
                        let calib = crate::input::velodyne_calib::load(p)
                            .map_err(|e| PipelineError(e.to_string()))?;
                        velodyne::Decoder::with_calibration(vc, calib)
                    }
                    None => velodyne::Decoder::new(vc),
                }
                .map_err(|e| PipelineError(format!("velodyne decoder: {e}")))?;
                Ok(SensorDecoder::Velodyne { dec, clock: VelodyneClock::new() })
            }
            SensorFamily::Ouster => {
                let intr = ouster_intr.ok_or_else(|| {
                    PipelineError(format!(
                        "preset {} reads Ouster packets, which need the sensor's metadata: set sensor.ouster_metadata or pass --metadata FILE",
                        cfg.preset
                    ))
                })?;
                let dec =
                    ouster::Decoder::new(intr).map_err(|e| PipelineError(format!("ouster metadata: {e}")))?;
                Ok(SensorDecoder::Ouster(dec))
            }
        }
    }

    /// The range-image layout of the decoded points.
    pub fn layout(&self) -> RangeImageLayout {
        match self {
            SensorDecoder::Velodyne { dec, .. } => dec.layout().clone(),
            SensorDecoder::Ouster(dec) => dec.layout().clone(),
        }
    }

    /// Most points one revolution can hold (both returns), for the assembly buffers.
    pub fn max_points(&self) -> usize {
        let l = self.layout();
        let per_turn = l.rows() * l.cols();
        2 * per_turn + per_turn / 4
    }
}

/// What a packet produced.
#[derive(Debug, Clone, PartialEq)]
pub enum Decoded {
    /// A completed scan.
    Scan(OwnedScan),
    /// An IMU sample (Ouster IMU packet).
    Imu(ImuSample),
}

/// Counts of the packets seen.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StreamStats {
    /// LiDAR data packets decoded.
    pub lidar_packets: u64,
    /// Packets the decoder refused (wrong size, bad header).
    pub bad_packets: u64,
    /// Packets the assembler refused (out of order, duplicate).
    pub rejected_packets: u64,
    /// IMU packets decoded.
    pub imu_packets: u64,
    /// IMU packets refused.
    pub bad_imu_packets: u64,
    /// Packets nothing decodes: datagrams on ports nothing listens to, Ouster IMU packets for a
    /// Velodyne.
    pub other_ports: u64,
    /// Incomplete scans (the first and last partial turns, packet gaps).
    pub incomplete_scans: u64,
}

/// What a packet is, as its source tells it: a UDP port for sockets and pcaps, the message
/// type for a bag (so no source has to pretend to be another).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PacketKind {
    /// LiDAR data (Velodyne data packet, Ouster lidar packet).
    Lidar,
    /// An Ouster IMU packet.
    OusterImu,
    /// A Velodyne position (GPS/PPS) packet, for the clock.
    VelodynePosition,
}

/// Packets in, scans and IMU samples out.
pub struct LidarStream<'a> {
    dec: SensorDecoder,
    asm: ScanAssembler<'a>,
    time: TimeAlignConfig,
    /// The LiDAR data and Ouster IMU ports (`None`: the source tells each packet's kind).
    ports: Option<(u16, u16)>,
    /// Counts.
    pub stats: StreamStats,
}

impl std::fmt::Debug for LidarStream<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LidarStream").field("stats", &self.stats).finish_non_exhaustive()
    }
}

/// Two assembly buffers for a decoder.
pub fn buffers(dec: &SensorDecoder) -> (Vec<ScanPoint>, Vec<ScanPoint>) {
    let n = dec.max_points();
    (vec![ScanPoint::default(); n], vec![ScanPoint::default(); n])
}

impl<'a> LidarStream<'a> {
    /// A stream over `dec` with the assembly buffers `a`, `b` (see [`buffers`]); packets on
    /// `lidar_port` are LiDAR data, on `imu_port` Ouster IMU packets (Velodyne position packets
    /// come on 8308).
    pub fn new(
        cfg: &Config,
        dec: SensorDecoder,
        a: &'a mut [ScanPoint],
        b: &'a mut [ScanPoint],
        lidar_port: u16,
        imu_port: u16,
    ) -> Self {
        LidarStream { ports: Some((lidar_port, imu_port)), ..Self::of_kinds(cfg, dec, a, b) }
    }

    /// A stream over `dec` for a source that tells each packet's kind (a bag): see
    /// [`LidarStream::packet_of_kind`].
    pub fn of_kinds(
        cfg: &Config,
        dec: SensorDecoder,
        a: &'a mut [ScanPoint],
        b: &'a mut [ScanPoint],
    ) -> Self {
        let source = match cfg.time.lidar_time_source {
            LidarTimeSource::Packet => time_align::LidarTimeSource::Sensor,
            LidarTimeSource::Capture => time_align::LidarTimeSource::Capture,
        };
        LidarStream {
            dec,
            asm: ScanAssembler::new(AssemblerConfig::cut_at_degrees(0.0), a, b),
            time: TimeAlignConfig { source, offset_ns: 0 },
            ports: None,
            stats: StreamStats::default(),
        }
    }

    /// The decoder.
    pub fn decoder(&self) -> &SensorDecoder {
        &self.dec
    }

    /// The assembler's counts.
    pub fn assembly_stats(&self) -> AssemblyStats {
        self.asm.stats
    }

    fn take_scan(&mut self, complete: bool) -> Option<Decoded> {
        if !complete {
            self.stats.incomplete_scans += 1;
        }
        let view = self.asm.scan();
        if view.points.is_empty() {
            return None;
        }
        Some(Decoded::Scan(OwnedScan { start_ns: view.start_ns, points: view.points.to_vec() }))
    }

    /// Takes one UDP payload received on `port` at `capture_ns`.
    pub fn packet(&mut self, port: u16, payload: &[u8], capture_ns: u64) -> Option<Decoded> {
        match self.port_kind(port) {
            Some(kind) => self.packet_of_kind(kind, payload, capture_ns),
            None => {
                self.stats.other_ports += 1;
                None
            }
        }
    }

    /// What a datagram on `port` is: the LiDAR port's data first, the IMU port only for an
    /// Ouster, then Velodyne position packets (8308).
    fn port_kind(&self, port: u16) -> Option<PacketKind> {
        match self.ports {
            Some((lidar, _)) if port == lidar => Some(PacketKind::Lidar),
            Some((_, imu)) if port == imu && matches!(self.dec, SensorDecoder::Ouster(_)) => {
                Some(PacketKind::OusterImu)
            }
            _ if port == VELODYNE_POSITION_PORT => Some(PacketKind::VelodynePosition),
            _ => None,
        }
    }

    /// Takes one packet of `kind` received at `capture_ns`; one this decoder cannot use (an
    /// Ouster IMU packet for a Velodyne) counts as [`StreamStats::other_ports`].
    pub fn packet_of_kind(&mut self, kind: PacketKind, payload: &[u8], capture_ns: u64) -> Option<Decoded> {
        let time = self.time;
        if kind == PacketKind::Lidar {
            let done = match &mut self.dec {
                SensorDecoder::Velodyne { dec, clock } => {
                    let Ok((pkt, repr)) = dec.parse(payload) else {
                        self.stats.bad_packets += 1;
                        return None;
                    };
                    self.stats.lidar_packets += 1;
                    let t = time_align::packet_time_ns(
                        &time,
                        clock.resolve(repr.timestamp_us, capture_ns),
                        capture_ns,
                    );
                    let meta = dec.meta(&repr, t);
                    self.asm.push_packet(meta, |sink| dec.points(&pkt, sink))
                }
                SensorDecoder::Ouster(dec) => {
                    let Ok((pkt, repr)) = dec.parse(payload) else {
                        self.stats.bad_packets += 1;
                        return None;
                    };
                    self.stats.lidar_packets += 1;
                    if repr.valid_columns == 0 {
                        return None;
                    }
                    let t = time_align::packet_time_ns(&time, repr.timestamp_ns, capture_ns);
                    let meta = dec.meta(&repr, t);
                    self.asm.push_packet(meta, |sink| dec.points(&pkt, sink))
                }
            };
            match done {
                Ok(Some(info)) => self.take_scan(info.complete),
                Ok(None) => None,
                Err(_) => {
                    self.stats.rejected_packets += 1;
                    None
                }
            }
        } else if kind == PacketKind::OusterImu && matches!(self.dec, SensorDecoder::Ouster(_)) {
            let SensorDecoder::Ouster(dec) = &mut self.dec else { return None };
            match dec.imu(payload).ok().and_then(|r| r.sample(0)) {
                Some(mut s) => {
                    self.stats.imu_packets += 1;
                    if time.source == time_align::LidarTimeSource::Capture {
                        s.t_ns = capture_ns;
                    }
                    Some(Decoded::Imu(s))
                }
                None => {
                    self.stats.bad_imu_packets += 1;
                    None
                }
            }
        } else if kind == PacketKind::VelodynePosition {
            if let SensorDecoder::Velodyne { clock, .. } = &mut self.dec
                && let Ok(p) = PositionPacket::new_checked(payload)
            {
                clock.observe_position(&PositionRepr::parse(&p));
            }
            None
        } else {
            self.stats.other_ports += 1;
            None
        }
    }

    /// The scan being built, when the input ends.
    pub fn flush(&mut self) -> Option<Decoded> {
        let info = self.asm.flush()?;
        self.take_scan(info.complete)
    }
}
