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
    /// LiDAR packets of another sensor model than the stream's (Velodyne product id, Ouster
    /// packet layout): dropped, never assembled.
    pub foreign: u64,
    /// What the first foreign packet was, for the warning.
    pub foreign_kind: Option<ForeignKind>,
    /// LiDAR packets whose time jumped away from their neighbours' and which the packets after
    /// them did not confirm: dropped.
    pub stamp_jumps: u64,
    /// The first dropped packet's jump (ns, signed), for the warning.
    pub stamp_jump_ns: i64,
    /// Jumps in LiDAR time that the following packets confirmed (a pause in the stream, a clock
    /// step): taken.
    pub time_steps: u64,
    /// The largest confirmed jump (ns, signed).
    pub time_step_ns: i64,
}

/// A LiDAR packet of another sensor than the configured one.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ForeignKind {
    /// A Velodyne packet with this product id (byte 1205); the stream's id beside it.
    Velodyne {
        /// The foreign packet's product id.
        product_id: u8,
        /// The stream's product id.
        stream_id: u8,
    },
    /// An Ouster lidar packet of this size, which another beam count or profile writes.
    Ouster {
        /// Its length, bytes.
        len: usize,
        /// Beams of the layout it matches.
        beams: usize,
    },
}

/// The Velodyne model a product id names, for messages.
pub fn velodyne_product_name(id: u8) -> &'static str {
    match id {
        0x21 => "HDL-32E",
        0x22 => "VLP-16",
        0x24 => "VLP-16 Hi-Res",
        0x28 => "VLP-32C",
        _ => "unknown model",
    }
}

impl StreamStats {
    /// One `warning:` text per kind of drop counted here that the callers do not say otherwise
    /// (foreign packets, stamp jumps, confirmed time steps); `configured` names the sensor.
    pub fn warnings(&self, configured: &str) -> Vec<String> {
        let mut w = Vec::new();
        if self.foreign > 0 {
            let what = match self.foreign_kind {
                Some(ForeignKind::Velodyne { product_id, stream_id }) => format!(
                    " ({}, product id {product_id:#04x}; the stream's: {} {stream_id:#04x})",
                    velodyne_product_name(product_id),
                    velodyne_product_name(stream_id)
                ),
                Some(ForeignKind::Ouster { len, beams }) => {
                    format!(" ({len}-byte packets, the layout of a {beams}-beam Ouster)")
                }
                None => String::new(),
            };
            w.push(format!(
                "{} LiDAR packets of another sensor model{what} on the LiDAR port were dropped (configured: {configured})",
                self.foreign
            ));
        }
        if self.stamp_jumps > 0 {
            w.push(format!(
                "{} LiDAR packets with a wrong stamp (the first {:+.3} s from the packets around it) were dropped",
                self.stamp_jumps,
                self.stamp_jump_ns as f64 * 1e-9
            ));
        }
        if self.time_steps > 0 {
            w.push(format!(
                "{} gaps or clock steps in the LiDAR packet time (largest {:+.3} s), confirmed by the packets after each: taken as they are",
                self.time_steps,
                self.time_step_ns as f64 * 1e-9
            ));
        }
        w
    }
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

/// A jump in packet time (either way) beyond this holds the packet until the packets after it
/// confirm it: 150 to 300 Velodyne/Ouster packet periods, more than any capture jitter.
const STAMP_JUMP_NS: u64 = 200_000_000;
/// Packets after a jump that must agree with it before it is believed.
const STAMP_CONFIRM: usize = 3;
/// Consecutive packets of another known Velodyne product id after which that id becomes the
/// stream's (the first sensor went away): about a second of packets.
const RELOCK_PACKETS: u32 = 1000;

/// A LiDAR packet held until the packets after it confirm its time.
struct Held {
    payload: Vec<u8>,
    t_ns: u64,
}

/// Packets in, scans and IMU samples out.
pub struct LidarStream<'a> {
    dec: SensorDecoder,
    asm: ScanAssembler<'a>,
    time: TimeAlignConfig,
    /// The LiDAR data and Ouster IMU ports (`None`: the source tells each packet's kind).
    ports: Option<(u16, u16)>,
    /// The last assembled packet's time, ns.
    last_ns: Option<u64>,
    /// Packets after a time jump, waiting for confirmation.
    held: Vec<Held>,
    /// Outputs not yet returned (a confirmed jump releases several packets at once).
    ready: std::collections::VecDeque<Decoded>,
    /// The stream's Velodyne product id: the first known one seen.
    velodyne_id: Option<u8>,
    /// Foreign Velodyne packets since the last one with the stream's id.
    velodyne_other_run: u32,
    /// Whether foreign packets, wrong stamps and confirmed time steps were warned of (once each,
    /// at first sight: a live run has no end summary to wait for).
    warned: [bool; 3],
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
            last_ns: None,
            held: Vec::new(),
            ready: std::collections::VecDeque::new(),
            velodyne_id: None,
            velodyne_other_run: 0,
            warned: [false; 3],
            stats: StreamStats::default(),
        }
    }

    /// The decoder.
    pub fn decoder(&self) -> &SensorDecoder {
        &self.dec
    }

    /// The `warning:` texts of the drops counted in [`LidarStream::stats`] (see
    /// [`StreamStats::warnings`]), naming the configured sensor.
    pub fn warnings(&self) -> Vec<String> {
        self.stats.warnings(&self.configured())
    }

    /// The configured sensor, for messages.
    fn configured(&self) -> String {
        match &self.dec {
            SensorDecoder::Velodyne { dec, .. } => {
                velodyne_product_name(dec.config().model.product_id()).to_string()
            }
            SensorDecoder::Ouster(dec) => {
                let i = dec.intrinsics();
                format!("{}-beam Ouster, {:?} profile", i.pixels_per_column, i.profile)
            }
        }
    }

    /// Warns of the first drop or time step of a kind (0 foreign, 1 stamp, 2 time step).
    fn warn_first(&mut self, kind: usize) {
        if std::mem::replace(&mut self.warned[kind], true) {
            return;
        }
        let st = &self.stats;
        crate::diag::warn(match kind {
            0 => format!(
                "LiDAR packets of another sensor model{} on the LiDAR port: dropping them (configured: {}); the count comes at the end",
                match st.foreign_kind {
                    Some(ForeignKind::Velodyne { product_id, .. }) =>
                        format!(" ({}, product id {product_id:#04x})", velodyne_product_name(product_id)),
                    Some(ForeignKind::Ouster { len, beams }) =>
                        format!(" ({len}-byte packets of a {beams}-beam Ouster)"),
                    None => String::new(),
                },
                self.configured()
            ),
            1 => format!(
                "a LiDAR packet with a wrong stamp ({:+.3} s from the packets around it) was dropped; the count comes at the end",
                st.stamp_jump_ns as f64 * 1e-9
            ),
            _ if st.time_step_ns >= 0 => format!(
                "a gap of {:.3} s in the LiDAR packets (their time jumped forward; the packets after it confirm it)",
                st.time_step_ns as f64 * 1e-9
            ),
            _ => format!(
                "LiDAR packet time stepped back {:.3} s (the packets after it confirm it): a clock step",
                st.time_step_ns as f64 * -1e-9
            ),
        });
    }

    /// The assembler's counts.
    pub fn assembly_stats(&self) -> AssemblyStats {
        self.asm.stats
    }

    fn take_scan(&mut self, complete: bool) {
        if !complete {
            self.stats.incomplete_scans += 1;
        }
        let view = self.asm.scan();
        if !view.points.is_empty() {
            let scan = OwnedScan { start_ns: view.start_ns, points: view.points.to_vec() };
            self.ready.push_back(Decoded::Scan(scan));
        }
    }

    /// Takes one UDP payload received on `port` at `capture_ns`.
    pub fn packet(&mut self, port: u16, payload: &[u8], capture_ns: u64) -> Option<Decoded> {
        match self.port_kind(port) {
            Some(kind) => self.packet_of_kind(kind, payload, capture_ns),
            None => {
                self.stats.other_ports += 1;
                self.ready.pop_front()
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
        self.take(kind, payload, capture_ns);
        self.ready.pop_front()
    }

    fn take(&mut self, kind: PacketKind, payload: &[u8], capture_ns: u64) {
        let time = self.time;
        if kind == PacketKind::Lidar {
            if let Some(t) = self.admit(payload, capture_ns) {
                self.guard(payload, t);
            }
        } else if kind == PacketKind::OusterImu && matches!(self.dec, SensorDecoder::Ouster(_)) {
            let SensorDecoder::Ouster(dec) = &mut self.dec else { return };
            match dec.imu(payload).ok().and_then(|r| r.sample(0)) {
                Some(mut s) => {
                    self.stats.imu_packets += 1;
                    if time.source == time_align::LidarTimeSource::Capture {
                        s.t_ns = capture_ns;
                    }
                    self.ready.push_back(Decoded::Imu(s));
                }
                None => self.stats.bad_imu_packets += 1,
            }
        } else if kind == PacketKind::VelodynePosition {
            if let SensorDecoder::Velodyne { clock, .. } = &mut self.dec
                && let Ok(p) = PositionPacket::new_checked(payload)
            {
                clock.observe_position(&PositionRepr::parse(&p));
            }
        } else {
            self.stats.other_ports += 1;
        }
    }

    /// Whether a Velodyne packet's product id is another known model's than the stream's. The
    /// stream's is the first known id seen, not the configured model's: two real VLP-16
    /// captures report 0x21. Unknown ids are decoded as configured.
    fn velodyne_foreign(&mut self, id: u8) -> bool {
        if !matches!(id, 0x21 | 0x22 | 0x24 | 0x28) {
            return false;
        }
        match self.velodyne_id {
            None => self.velodyne_id = Some(id),
            Some(s) if s == id => self.velodyne_other_run = 0,
            Some(s) => {
                self.velodyne_other_run += 1;
                if self.velodyne_other_run <= RELOCK_PACKETS {
                    self.stats.foreign += 1;
                    self.stats
                        .foreign_kind
                        .get_or_insert(ForeignKind::Velodyne { product_id: id, stream_id: s });
                    self.warn_first(0);
                    return true;
                }
                self.velodyne_id = Some(id);
                self.velodyne_other_run = 0;
            }
        }
        false
    }

    /// Checks a LiDAR packet and gives its time; `None` for one that is malformed (counted in
    /// `bad_packets`), of another sensor (`foreign`) or without a valid column.
    fn admit(&mut self, payload: &[u8], capture_ns: u64) -> Option<u64> {
        let time = self.time;
        if matches!(self.dec, SensorDecoder::Velodyne { .. })
            && let Ok(p) = velodyne::Packet::new_checked(payload)
            && self.velodyne_foreign(p.product_id())
        {
            // Before the decoder sees it: a foreign packet is no model mismatch.
            return None;
        }
        match &mut self.dec {
            SensorDecoder::Velodyne { dec, clock } => {
                let Ok((_, repr)) = dec.parse(payload) else {
                    self.stats.bad_packets += 1;
                    return None;
                };
                self.stats.lidar_packets += 1;
                let sensor_ns = clock.resolve(repr.timestamp_us, capture_ns);
                Some(time_align::packet_time_ns(&time, sensor_ns, capture_ns))
            }
            SensorDecoder::Ouster(dec) => {
                let repr = match dec.parse(payload) {
                    Ok((_, repr)) => repr,
                    Err(ouster::Error::Truncated | ouster::Error::TooLong) => {
                        match ouster_layout_beams(payload.len(), dec.intrinsics()) {
                            Some(beams) => {
                                self.stats.foreign += 1;
                                self.stats
                                    .foreign_kind
                                    .get_or_insert(ForeignKind::Ouster { len: payload.len(), beams });
                                self.warn_first(0);
                            }
                            None => self.stats.bad_packets += 1,
                        }
                        return None;
                    }
                    Err(_) => {
                        self.stats.bad_packets += 1;
                        return None;
                    }
                };
                self.stats.lidar_packets += 1;
                if repr.valid_columns == 0 {
                    return None;
                }
                Some(time_align::packet_time_ns(&time, repr.timestamp_ns, capture_ns))
            }
        }
    }

    /// Time is checked before it is believed: a packet whose time jumps from the last
    /// assembled one's is held; the packets after it either confirm it (all are assembled) or
    /// go on from the old time (the held ones are dropped as wrong stamps).
    fn guard(&mut self, payload: &[u8], t_ns: u64) {
        let near = |a: u64, b: u64| a.abs_diff(b) <= STAMP_JUMP_NS;
        let Some(last) = self.last_ns else {
            self.assemble(payload, t_ns);
            return;
        };
        let hold = |held: &mut Vec<Held>| held.push(Held { payload: payload.to_vec(), t_ns });
        match self.held.last().map(|h| h.t_ns) {
            None if near(t_ns, last) => self.assemble(payload, t_ns),
            None => hold(&mut self.held),
            Some(_) if near(t_ns, last) => {
                self.drop_held(last);
                self.assemble(payload, t_ns);
            }
            Some(h) if near(t_ns, h) => {
                hold(&mut self.held);
                if self.held.len() > STAMP_CONFIRM {
                    let step = self.held[0].t_ns as i64 - last as i64;
                    self.stats.time_steps += 1;
                    if step.unsigned_abs() > self.stats.time_step_ns.unsigned_abs() {
                        self.stats.time_step_ns = step;
                    }
                    self.warn_first(2);
                    for h in std::mem::take(&mut self.held) {
                        self.assemble(&h.payload, h.t_ns);
                    }
                }
            }
            Some(_) => {
                self.drop_held(last);
                hold(&mut self.held);
            }
        }
    }

    /// Drops the held packets: wrong stamps.
    fn drop_held(&mut self, last: u64) {
        if let Some(h) = self.held.first()
            && self.stats.stamp_jumps == 0
        {
            self.stats.stamp_jump_ns = h.t_ns as i64 - last as i64;
        }
        if !self.held.is_empty() {
            self.stats.stamp_jumps += self.held.len() as u64;
            self.held.clear();
            self.warn_first(1);
        }
    }

    /// Puts an admitted packet's points in the scan being built.
    fn assemble(&mut self, payload: &[u8], t_ns: u64) {
        self.last_ns = Some(t_ns);
        let done = match &mut self.dec {
            SensorDecoder::Velodyne { dec, .. } => {
                let Ok(pkt) = velodyne::Packet::new_checked(payload) else { return };
                let meta = dec.meta(&velodyne::PacketRepr::parse(&pkt), t_ns);
                self.asm.push_packet(meta, |sink| dec.points(&pkt, sink))
            }
            SensorDecoder::Ouster(dec) => {
                let Ok(pkt) = ouster::LidarPacket::new_checked(payload, dec.intrinsics()) else { return };
                let meta = dec.meta(&ouster::LidarRepr::parse(&pkt), t_ns);
                self.asm.push_packet(meta, |sink| dec.points(&pkt, sink))
            }
        };
        match done {
            Ok(Some(info)) => self.take_scan(info.complete),
            Ok(None) => {}
            Err(_) => self.stats.rejected_packets += 1,
        }
    }

    /// The scans left when the input ends: call until `None`. Packets still held after a time
    /// jump were never confirmed: they are dropped as wrong stamps.
    pub fn flush(&mut self) -> Option<Decoded> {
        if let Some(last) = self.last_ns {
            self.drop_held(last);
        }
        if let Some(info) = self.asm.flush() {
            self.take_scan(info.complete);
        }
        self.ready.pop_front()
    }
}

/// The beam count of another Ouster's packet layout (any profile, beam count or columns per
/// packet) that is `len` bytes long.
fn ouster_layout_beams(len: usize, intr: &OusterIntrinsics) -> Option<usize> {
    use ouster::Profile::*;
    let cpps = [intr.columns_per_packet as usize, 8, 16];
    [Legacy, Single, Dual, LowBandwidth, FusaDualLowBandwidth].into_iter().find_map(|p| {
        [16, 32, 64, 128].into_iter().find(|&h| cpps.iter().any(|&c| p.packet_bytes(h, c) == len))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use loglio_core::sensor::velodyne::{BLOCK_FLAG, DATA_PACKET_LEN};

    /// An hour boundary, ns (so that stamps and capture times agree).
    const HOUR0_NS: u64 = 491_000 * 3_600_000_000_000;

    /// A single-return packet `k` of `model` whose sensor time is `t_ns` after `HOUR0_NS`:
    /// 75 VLP-16 packets a turn (150 for the 32-laser models), every return at 5 m.
    fn packet(model: Model, k: u64, t_ns: u64) -> (Vec<u8>, u64) {
        let step: u64 = if model == Model::Vlp16 { 40 } else { 20 };
        let mut b = vec![0u8; DATA_PACKET_LEN];
        for i in 0..12u64 {
            let o = i as usize * 100;
            b[o..o + 2].copy_from_slice(&BLOCK_FLAG.to_le_bytes());
            let az = ((k * 12 + i) * step % 36_000) as u16;
            b[o + 2..o + 4].copy_from_slice(&az.to_le_bytes());
            for j in 0..32 {
                let p = o + 4 + 3 * j;
                b[p..p + 2].copy_from_slice(&2500u16.to_le_bytes());
                b[p + 2] = j as u8;
            }
        }
        let toh_us = (t_ns / 1000 % velodyne::MICROS_PER_HOUR) as u32;
        b[1200..1204].copy_from_slice(&toh_us.to_le_bytes());
        b[1204] = 0x37;
        b[1205] = model.product_id();
        (b, HOUR0_NS + t_ns)
    }

    /// VLP-16 packet `k` at its nominal time after `start_ns`.
    fn vlp16(k: u64, start_ns: u64) -> (Vec<u8>, u64) {
        packet(Model::Vlp16, k, start_ns + k * 1_327_104)
    }

    /// Every output of `packets` (payload, capture time) through a VLP-16 stream, and its counts.
    fn run(preset: Preset, packets: &[(Vec<u8>, u64)]) -> (Vec<Decoded>, StreamStats, Vec<String>) {
        let cfg = Config::preset(preset);
        let dec = SensorDecoder::new(&cfg, None).unwrap();
        let (mut a, mut b) = buffers(&dec);
        let mut s = LidarStream::new(&cfg, dec, &mut a, &mut b, 2368, 7503);
        let mut out: Vec<Decoded> = packets.iter().filter_map(|(p, t)| s.packet(2368, p, *t)).collect();
        while let Some(d) = s.flush() {
            out.push(d);
        }
        (out, s.stats, s.warnings())
    }

    fn clean(n: u64) -> Vec<(Vec<u8>, u64)> {
        (0..n).map(|k| vlp16(k, 0)).collect()
    }

    #[test]
    fn lidar_stream_clean_is_untouched() {
        let (out, st, w) = run(Preset::Vlp16, &clean(600));
        assert_eq!(out.len(), 8, "600 packets from azimuth 0: 8 turns");
        assert_eq!((st.lidar_packets, st.foreign, st.stamp_jumps, st.time_steps), (600, 0, 0, 0));
        assert!(w.is_empty(), "{w:?}");
    }

    #[test]
    fn lidar_stream_drops_an_isolated_stamp_jump() {
        let good = clean(600);
        let (want, ..) = run(Preset::Vlp16, &good);
        // An extra copy of packet 300 stamped +60 s (in the payload and the capture time).
        let mut bad = good.clone();
        let (p, _) = vlp16(300, 60_000_000_000);
        bad.insert(301, (p, HOUR0_NS + 60_000_000_000 + 300 * 1_327_104));
        let (out, st, w) = run(Preset::Vlp16, &bad);
        assert_eq!((st.stamp_jumps, st.time_steps, st.rejected_packets), (1, 0, 0));
        assert_eq!(out, want, "the scans of the clean stream");
        assert_eq!(w.len(), 1);
        assert!(w[0].contains("1 LiDAR packets with a wrong stamp") && w[0].contains("+60.000 s"), "{w:?}");
        // The injector's way: packet 300 itself restamped (-60 s this time): as if it were lost.
        let mut lost = good.clone();
        lost[300] = vlp16(300, 3_600_000_000_000 - 60_000_000_000);
        lost[300].1 -= 3_600_000_000_000;
        let (out, st, _) = run(Preset::Vlp16, &lost);
        let mut without = good.clone();
        without.remove(300);
        assert_eq!((st.stamp_jumps, st.time_steps), (1, 0));
        assert_eq!(out, run(Preset::Vlp16, &without).0);
    }

    #[test]
    fn lidar_stream_takes_a_confirmed_pause_and_clock_step() {
        // The sensor pauses for 2 s after packet 299, then goes on.
        let pkts: Vec<_> = (0..600).map(|k| vlp16(k, if k < 300 { 0 } else { 2_000_000_000 })).collect();
        let (out, st, w) = run(Preset::Vlp16, &pkts);
        assert_eq!((st.stamp_jumps, st.time_steps, st.lidar_packets), (0, 1, 600));
        let points: usize =
            out.iter().map(|d| if let Decoded::Scan(s) = d { s.points.len() } else { 0 }).sum();
        let clean_points: usize = run(Preset::Vlp16, &clean(600))
            .0
            .iter()
            .map(|d| if let Decoded::Scan(s) = d { s.points.len() } else { 0 })
            .sum();
        assert_eq!(points, clean_points, "every packet assembled");
        assert!((st.time_step_ns - 2_000_000_000).abs() < 2_000_000, "{}", st.time_step_ns);
        assert!(w.len() == 1 && w[0].starts_with("1 gaps or clock steps"), "{w:?}");
        // A clock stepped 5 s back for good, and the last packets of a stream after a jump
        // (never confirmed: dropped at the end).
        let mut pkts: Vec<_> = (0..600).map(|k| vlp16(k, if k < 300 { 5_000_000_000 } else { 0 })).collect();
        pkts.push(vlp16(600, 9_000_000_000));
        pkts.push(vlp16(601, 9_000_000_000));
        let (_, st, _) = run(Preset::Vlp16, &pkts);
        assert_eq!((st.stamp_jumps, st.time_steps), (2, 1));
        assert!((st.time_step_ns + 5_000_000_000).abs() < 2_000_000, "{}", st.time_step_ns);
    }

    #[test]
    fn lidar_stream_hour_wrap_is_no_jump() {
        // 0.4 s before the top of the hour to 0.4 s after it.
        let pkts: Vec<_> = (0..600).map(|k| vlp16(k, 3_600_000_000_000 - 400_000_000)).collect();
        let (out, st, w) = run(Preset::Vlp16, &pkts);
        assert_eq!((st.stamp_jumps, st.time_steps, st.rejected_packets), (0, 0, 0));
        assert_eq!(out.len(), 8);
        assert!(w.is_empty(), "{w:?}");
    }

    #[test]
    fn lidar_stream_drops_foreign_velodyne_packets() {
        let good = clean(600);
        let (want, ..) = run(Preset::Vlp16, &good);
        // From packet 150 to 450 a VLP-32C sends two packets per VLP-16 packet, on the same clock.
        let mut mixed = Vec::new();
        let mut foreign = 0;
        for (k, p) in good.iter().enumerate() {
            mixed.push(p.clone());
            if (150..450).contains(&k) {
                for j in 0..2 {
                    let kf = 2 * k as u64 + j;
                    mixed.push(packet(Model::Vlp32c, kf, kf * 663_552 + 300_000));
                    foreign += 1;
                }
            }
        }
        let ((out, st, w), first) = crate::diag::capture(|| run(Preset::Vlp16, &mixed));
        assert_eq!(
            first,
            [
                "warning: LiDAR packets of another sensor model (VLP-32C, product id 0x28) on the LiDAR port: dropping them (configured: VLP-16); the count comes at the end"
            ],
            "warned once, at first sight"
        );
        assert_eq!((st.foreign, st.lidar_packets, st.stamp_jumps, st.bad_packets), (foreign, 600, 0, 0));
        assert_eq!(out, want, "the VLP-16 scans of the clean stream");
        assert_eq!(
            w,
            [
                "600 LiDAR packets of another sensor model (VLP-32C, product id 0x28; the stream's: VLP-16 0x22) on the LiDAR port were dropped (configured: VLP-16)"
            ]
        );
    }

    #[test]
    fn lidar_stream_keeps_a_mislabelled_vlp16() {
        // Real VLP-16s that report 0x21 (HDL-32E): their id is the stream's; VLP-16 ids beside
        // it are foreign.
        let relabel = |(mut p, t): (Vec<u8>, u64), id: u8| {
            p[1205] = id;
            (p, t)
        };
        let pkts: Vec<_> = clean(600).into_iter().map(|p| relabel(p, 0x21)).collect();
        let (want, st, w) = run(Preset::Vlp16, &pkts);
        assert_eq!((st.foreign, st.lidar_packets), (0, 600));
        assert!(w.is_empty(), "{w:?}");
        let mut mixed = pkts.clone();
        for k in 0..50u64 {
            mixed.insert(200 + 2 * k as usize, packet(Model::Vlp16, 1000 + k, (198 + k) * 1_327_104 + 1));
        }
        let (out, st, _) = run(Preset::Vlp16, &mixed);
        assert_eq!((st.foreign, st.lidar_packets), (50, 600));
        assert_eq!(out, want);
        // An unknown product id (a flipped bit) is decoded as configured.
        let odd: Vec<_> = clean(600)
            .into_iter()
            .enumerate()
            .map(|(k, p)| if k == 7 { relabel(p, 0x23) } else { p })
            .collect();
        let (_, st, _) = run(Preset::Vlp16, &odd);
        assert_eq!((st.foreign, st.lidar_packets), (0, 600));
    }

    #[test]
    fn lidar_stream_relocks_when_the_first_sensor_goes_away() {
        // The stream starts with a VLP-32C's packets, then only the VLP-16's come.
        let mut pkts: Vec<_> = (0..10).map(|k| packet(Model::Vlp32c, k, k * 663_552)).collect();
        pkts.extend((0..1500).map(|k| vlp16(k, 10_000_000)));
        let (_, st, _) = run(Preset::Vlp16, &pkts);
        assert_eq!(st.foreign, RELOCK_PACKETS as u64);
        assert_eq!(st.lidar_packets, 10 + 1500 - RELOCK_PACKETS as u64);
    }

    #[test]
    fn lidar_stream_ouster_layouts() {
        use loglio_core::sensor::ouster::Profile;
        let mut intr = test_intrinsics();
        intr.pixels_per_column = 16;
        let os64 = Profile::Legacy.packet_bytes(64, 16);
        assert_eq!(ouster_layout_beams(os64, &intr), Some(64));
        assert_eq!(ouster_layout_beams(Profile::Single.packet_bytes(32, 16), &intr), Some(32));
        assert_eq!(ouster_layout_beams(1000, &intr), None);
        let cfg = Config::preset(Preset::Os1_16);
        let dec = SensorDecoder::new(&cfg, Some(&intr)).unwrap();
        let (mut a, mut b) = buffers(&dec);
        let mut s = LidarStream::new(&cfg, dec, &mut a, &mut b, 7502, 7503);
        assert_eq!(s.packet(7502, &vec![0u8; os64], 1), None);
        assert_eq!(s.packet(7502, &[0u8; 1000], 1), None);
        assert_eq!((s.stats.foreign, s.stats.bad_packets, s.stats.lidar_packets), (1, 1, 0));
        let w = s.warnings();
        assert!(
            w.len() == 1 && w[0].contains("64-beam Ouster") && w[0].contains("configured: 16-beam"),
            "{w:?}"
        );
    }

    fn test_intrinsics() -> OusterIntrinsics {
        let mut alt = [0.0f32; ouster::MAX_BEAMS];
        for (i, a) in alt.iter_mut().enumerate() {
            *a = 16.0 - i as f32;
        }
        OusterIntrinsics {
            profile: ouster::Profile::Legacy,
            pixels_per_column: 16,
            columns_per_frame: 1024,
            columns_per_packet: 16,
            frequency_hz: 10,
            beam_altitude_deg: alt,
            beam_azimuth_deg: [0.0; ouster::MAX_BEAMS],
            pixel_shift_by_row: [0; ouster::MAX_BEAMS],
            beam_origin_mm: [15.0, 0.0],
            lidar_to_sensor: [
                1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 36.0, 0.0, 0.0, 0.0, 1.0,
            ],
            imu_to_sensor: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
        }
    }
}
