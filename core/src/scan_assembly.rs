//! Scan assembly: packets of points in, whole revolutions out.
//!
//! A decoder (`sensor::velodyne`, `sensor::ouster`) turns one packet into [`RawPoint`]s, each
//! with its firing's offset from the packet time and its firing's *sweep angle* (the encoder
//! angle, clockwise from the sensor's forward axis, as a fraction of a turn). The
//! [`ScanAssembler`] places them in scans that start where the sweep crosses a configurable cut
//! angle, stamps every point with its time since the scan start and keeps its range-image
//! row and column.
//!
//! Packets carry a sequence counter (the Velodyne microsecond clock, the Ouster frame and
//! measurement ids), so the assembler detects and counts
//! - duplicated packets (the same counter again): dropped;
//! - out-of-order packets (a counter a little behind the last one): dropped, because their
//!   points would land in a scan already stamped, or in the past of the current one;
//! - missing packets (a gap of more than one step): counted; the scan keeps the points it has
//!   and is marked incomplete;
//! - a jump of more than [`AssemblerConfig::reset_gap_packets`] either way (a sensor restart, a
//!   replay loop): the current scan is delivered as incomplete and assembly starts afresh.
//!
//! None of these can corrupt a scan: every delivered scan holds points of one revolution, in
//! time order, with `t >= 0`, and says whether it is complete.
//!
//! Memory: the caller lends the assembler two point slices (the scan being built and the last
//! completed one), smoltcp style: `static` arrays on firmware, two `vec![ScanPoint::default(); n]`
//! on the host (24 bytes a point: 2 x 300 000 points = 14.4 MB). A scan longer than its slice
//! keeps the first points and counts the rest in [`ScanInfo::overflow`].

use crate::scan::{ScanPoint, ScanView};

/// A point as a decoder delivers it, before it is placed in a scan.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct RawPoint {
    /// Position in the sensor frame, metres.
    pub xyz: [f32; 3],
    /// Firing time after the packet's time, nanoseconds.
    pub dt_ns: u32,
    /// Sweep angle of the firing: clockwise from forward, 2^32 = one turn.
    pub sweep: u32,
    /// Range-image row (0 = highest beam).
    pub row: u16,
    /// Range-image column.
    pub col: u16,
    /// Intensity / reflectivity.
    pub intensity: u16,
    /// 0 for the strongest (or only) return, 1 for a second return.
    pub ret: u8,
}

/// A packet's place in the sensor's sequence.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PacketSeq {
    /// The sensor's counter for this packet (Velodyne: microseconds past the hour; Ouster:
    /// frame id x columns per frame + first measurement id).
    pub counter: u64,
    /// The counter wraps modulo this (0: never).
    pub modulus: u64,
    /// Expected increase from one packet to the next.
    pub step: f32,
}

/// What the assembler needs to know about a packet besides its points.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PacketMeta {
    /// Absolute time of the packet's reference firing, nanoseconds (resolved by the host from
    /// the sensor clock or the capture time).
    pub time_ns: u64,
    /// Sequence information.
    pub seq: PacketSeq,
}

/// Settings of a [`ScanAssembler`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct AssemblerConfig {
    /// Scans start where the sweep angle crosses this (2^32 = one turn, clockwise from forward).
    pub cut_sweep: u32,
    /// A sequence jump of more than this many packets (forward or back) restarts assembly.
    pub reset_gap_packets: u32,
}

impl AssemblerConfig {
    /// Cut at `deg` degrees clockwise from the sensor's forward (+x) axis; restart after a gap
    /// of 40 packets (about half a revolution of a VLP-16 at 10 Hz).
    pub fn cut_at_degrees(deg: f32) -> Self {
        Self { cut_sweep: sweep_of_degrees(deg), reset_gap_packets: 40 }
    }
}

impl Default for AssemblerConfig {
    fn default() -> Self {
        Self::cut_at_degrees(0.0)
    }
}

/// Sweep angle (2^32 = one turn) of a clockwise angle in degrees, any multiple of 360.
pub fn sweep_of_degrees(deg: f32) -> u32 {
    let turns = deg as f64 / 360.0;
    let frac = turns - libm::floor(turns);
    let v = libm::round(frac * 4_294_967_296.0);
    if v >= 4_294_967_296.0 { 0 } else { v as u32 }
}

/// A completed scan's facts; its points are in [`ScanAssembler::scan`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ScanInfo {
    /// Running number of delivered scans, from 0.
    pub index: u64,
    /// Absolute time of the first point, ns (the scan's `start_ns`).
    pub start_ns: u64,
    /// Absolute time of the last point, ns.
    pub end_ns: u64,
    /// Points stored.
    pub points: u32,
    /// Points dropped because the buffer was full.
    pub overflow: u32,
    /// Packets that contributed.
    pub packets: u32,
    /// Packets the sequence says are missing from this scan.
    pub missing_packets: u32,
    /// The scan began at the cut, ended at the cut, and no packet is missing.
    pub complete: bool,
}

/// Why a packet was refused (it is counted; nothing else changes).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PacketRejected {
    /// The same sequence counter as the previous packet.
    Duplicate,
    /// A counter behind the previous packet's (but within the reset gap).
    OutOfOrder,
}

impl core::fmt::Display for PacketRejected {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Duplicate => "duplicated lidar packet dropped",
            Self::OutOfOrder => "out-of-order lidar packet dropped",
        })
    }
}

impl core::error::Error for PacketRejected {}

/// Counts over the assembler's life.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct AssemblyStats {
    /// Packets accepted.
    pub packets: u64,
    /// Duplicated packets dropped.
    pub duplicates: u64,
    /// Out-of-order packets dropped.
    pub out_of_order: u64,
    /// Packets missing according to the sequence.
    pub missing_packets: u64,
    /// Sequence jumps that restarted assembly.
    pub resets: u64,
    /// Scans delivered.
    pub scans: u64,
    /// Of them, incomplete.
    pub incomplete_scans: u64,
    /// Scans with no points, or shorter than a packet after a restart: not delivered.
    pub discarded_scans: u64,
    /// Points dropped because a scan buffer was full.
    pub overflow_points: u64,
    /// Points whose absolute time was before their scan's start (capture-time jitter); their
    /// `t` is clamped to 0.
    pub time_regressions: u64,
}

#[derive(Clone, Copy, Debug, Default)]
struct Building {
    packets: u32,
    missing: u32,
    started_at_cut: bool,
    start_ns: Option<u64>,
    end_ns: u64,
}

#[derive(Debug)]
struct Buf<'a> {
    pts: &'a mut [ScanPoint],
    len: usize,
    start_ns: u64,
    overflow: u32,
}

impl Buf<'_> {
    fn clear(&mut self, start_ns: u64) {
        self.len = 0;
        self.overflow = 0;
        self.start_ns = start_ns;
    }

    fn push(&mut self, p: ScanPoint) -> bool {
        match self.pts.get_mut(self.len) {
            Some(slot) => {
                *slot = p;
                self.len += 1;
                true
            }
            None => {
                self.overflow = self.overflow.saturating_add(1);
                false
            }
        }
    }
}

/// Builds scans from packets into two caller-lent point slices.
#[derive(Debug)]
pub struct ScanAssembler<'a> {
    config: AssemblerConfig,
    bufs: [Buf<'a>; 2],
    building: usize,
    cur: Building,
    last_seq: Option<PacketSeq>,
    prev_rel: Option<u32>,
    /// Set when a scan completed during the current packet.
    pending: Option<ScanInfo>,
    /// Points of the current packet placed in the scan being built.
    packet_points: u32,
    last_completed: Option<ScanInfo>,
    /// What was accepted, dropped and delivered.
    pub stats: AssemblyStats,
}

const HALF_TURN: u32 = 1 << 31;

impl<'a> ScanAssembler<'a> {
    /// An empty assembler building scans in `a` and `b` (each holds one scan: size them for the
    /// most points a revolution can have).
    pub fn new(config: AssemblerConfig, a: &'a mut [ScanPoint], b: &'a mut [ScanPoint]) -> Self {
        Self {
            config,
            bufs: [
                Buf { pts: a, len: 0, start_ns: 0, overflow: 0 },
                Buf { pts: b, len: 0, start_ns: 0, overflow: 0 },
            ],
            building: 0,
            cur: Building { packets: 0, missing: 0, started_at_cut: false, start_ns: None, end_ns: 0 },
            last_seq: None,
            prev_rel: None,
            pending: None,
            packet_points: 0,
            last_completed: None,
            stats: AssemblyStats {
                packets: 0,
                duplicates: 0,
                out_of_order: 0,
                missing_packets: 0,
                resets: 0,
                scans: 0,
                incomplete_scans: 0,
                discarded_scans: 0,
                overflow_points: 0,
                time_regressions: 0,
            },
        }
    }

    /// The settings.
    pub fn config(&self) -> &AssemblerConfig {
        &self.config
    }

    /// The last completed scan (valid until the next call that completes one).
    pub fn scan(&self) -> ScanView<'_> {
        let b = &self.bufs[1 - self.building];
        ScanView { start_ns: b.start_ns, points: &b.pts[..b.len] }
    }

    /// The last completed scan's points, mutable (to undistort them in place).
    pub fn scan_mut(&mut self) -> &mut [ScanPoint] {
        let b = &mut self.bufs[1 - self.building];
        &mut b.pts[..b.len]
    }

    /// Facts of the last completed scan, if any.
    pub fn last_scan_info(&self) -> Option<ScanInfo> {
        self.last_completed
    }

    /// Points in the scan being built.
    pub fn building_len(&self) -> usize {
        self.bufs[self.building].len
    }

    /// Feeds one packet: `meta` first, then its points through the sink `emit` is given.
    /// Returns the scan this packet completed, if any (its points: [`Self::scan`]).
    ///
    /// ```
    /// # use loglio_core::scan_assembly::*;
    /// # use loglio_core::scan::ScanPoint;
    /// let (mut a, mut b) = ([ScanPoint::default(); 64], [ScanPoint::default(); 64]);
    /// let mut asm = ScanAssembler::new(AssemblerConfig::cut_at_degrees(0.0), &mut a, &mut b);
    /// let meta = PacketMeta { time_ns: 1_000, seq: PacketSeq { counter: 0, modulus: 0, step: 1.0 } };
    /// let done = asm.push_packet(meta, |sink| sink(RawPoint { sweep: 1 << 30, ..Default::default() }));
    /// assert_eq!(done, Ok(None));
    /// assert_eq!(asm.building_len(), 1);
    /// ```
    pub fn push_packet<F>(&mut self, meta: PacketMeta, emit: F) -> Result<Option<ScanInfo>, PacketRejected>
    where
        F: FnOnce(&mut dyn FnMut(RawPoint)),
    {
        self.pending = None;
        self.check_sequence(&meta.seq)?;
        self.stats.packets += 1;
        self.cur.packets += 1;
        self.packet_points = 0;
        {
            let mut sink = |p: RawPoint| self.push_point(meta.time_ns, p);
            emit(&mut sink);
        }
        Ok(self.pending.take())
    }

    /// Ends the stream: delivers the scan being built (incomplete: it never reached the cut).
    pub fn flush(&mut self) -> Option<ScanInfo> {
        self.pending = None;
        self.finish(false);
        self.last_seq = None;
        self.prev_rel = None;
        self.pending.take()
    }

    fn check_sequence(&mut self, seq: &PacketSeq) -> Result<(), PacketRejected> {
        let Some(last) = self.last_seq else {
            self.last_seq = Some(*seq);
            return Ok(());
        };
        let delta = signed_delta(seq.counter, last.counter, seq.modulus);
        let step = if seq.step > 0.0 { seq.step as f64 } else { 1.0 };
        let packets = libm::round(delta as f64 / step);
        let limit = self.config.reset_gap_packets as f64;
        if packets.abs() > limit {
            // A restart of the sensor or of the stream: start afresh.
            self.stats.resets += 1;
            warn!("lidar packet sequence jumped by {} packets: restarting scan assembly", packets);
            self.finish(false);
            self.prev_rel = None;
            self.last_seq = Some(*seq);
            return Ok(());
        }
        if delta == 0 {
            self.stats.duplicates += 1;
            return Err(PacketRejected::Duplicate);
        }
        if delta < 0 {
            self.stats.out_of_order += 1;
            return Err(PacketRejected::OutOfOrder);
        }
        if packets >= 2.0 {
            let missing = (packets - 1.0) as u32;
            self.stats.missing_packets += missing as u64;
            self.cur.missing = self.cur.missing.saturating_add(missing);
        }
        self.last_seq = Some(*seq);
        Ok(())
    }

    fn push_point(&mut self, packet_ns: u64, p: RawPoint) {
        let rel = p.sweep.wrapping_sub(self.config.cut_sweep);
        if let Some(prev) = self.prev_rel
            && rel < prev
            && prev - rel > HALF_TURN
        {
            self.finish(true);
            self.cur.started_at_cut = true;
        }
        self.prev_rel = Some(rel);
        let abs = packet_ns.saturating_add(p.dt_ns as u64);
        let buf = &mut self.bufs[self.building];
        let start = match self.cur.start_ns {
            Some(s) => s,
            None => {
                buf.clear(abs);
                self.cur.start_ns = Some(abs);
                abs
            }
        };
        let t = if abs >= start {
            (abs - start) as f64 * 1e-9
        } else {
            self.stats.time_regressions += 1;
            0.0
        };
        self.cur.end_ns = self.cur.end_ns.max(abs);
        let sp = ScanPoint {
            xyz: p.xyz,
            t: t as f32,
            row: p.row,
            col: p.col,
            intensity: p.intensity,
            ret: p.ret,
            flags: 0,
        };
        if !buf.push(sp) {
            self.stats.overflow_points += 1;
        }
        self.packet_points += 1;
    }

    /// Closes the scan being built. `at_cut`: it ended because the sweep crossed the cut.
    fn finish(&mut self, at_cut: bool) {
        let cur = core::mem::take(&mut self.cur);
        let buf = &self.bufs[self.building];
        if cur.start_ns.is_none() || buf.len == 0 || self.pending.is_some() {
            // Nothing in it, or a second scan within one packet (after a restart): too short.
            if cur.start_ns.is_some() || cur.packets > 0 {
                self.stats.discarded_scans += 1;
            }
            self.bufs[self.building].clear(0);
            return;
        }
        let complete = at_cut && cur.started_at_cut && cur.missing == 0;
        // The packet that crossed the cut belongs to this scan only if some of its points did.
        let packets =
            if at_cut && self.packet_points == 0 { cur.packets.saturating_sub(1) } else { cur.packets };
        let info = ScanInfo {
            index: self.stats.scans,
            start_ns: buf.start_ns,
            end_ns: cur.end_ns,
            points: buf.len as u32,
            overflow: buf.overflow,
            packets,
            missing_packets: cur.missing,
            complete,
        };
        self.stats.scans += 1;
        if !complete {
            self.stats.incomplete_scans += 1;
        }
        self.building = 1 - self.building;
        self.bufs[self.building].clear(0);
        // The packet that crossed the cut also starts the next scan.
        self.cur.packets = if at_cut { 1 } else { 0 };
        self.packet_points = 0;
        self.pending = Some(info);
        self.last_completed = Some(info);
    }
}

/// `a - b` modulo `m` as a signed number in (-m/2, m/2] (plain wrapping i64 difference when
/// `m` is 0).
fn signed_delta(a: u64, b: u64, m: u64) -> i64 {
    if m == 0 {
        return a.wrapping_sub(b) as i64;
    }
    let d = (a % m + m - b % m) % m;
    if d > m / 2 { d as i64 - m as i64 } else { d as i64 }
}

#[cfg(test)]
mod tests {
    use super::*;
    extern crate std;
    use std::vec::Vec;

    const STEP: u64 = 10;

    /// A synthetic sensor: `per_packet` firings per packet, `per_turn` firings per turn, one
    /// point per firing; packet k starts at firing k * per_packet.
    fn feed(asm: &mut ScanAssembler<'_>, k: u64, out: &mut Vec<ScanInfo>) -> Result<(), PacketRejected> {
        let per_packet = 8u64;
        let per_turn = 96u64;
        let meta = PacketMeta {
            time_ns: 1_000_000 + k * per_packet * 1000,
            seq: PacketSeq { counter: k * STEP, modulus: 0, step: STEP as f32 },
        };
        let r = asm.push_packet(meta, |sink| {
            for f in 0..per_packet {
                let firing = k * per_packet + f;
                let sweep = (((firing % per_turn) << 32) / per_turn) as u32;
                sink(RawPoint {
                    sweep,
                    dt_ns: f as u32 * 1000,
                    row: 0,
                    col: (firing % per_turn) as u16,
                    ..Default::default()
                });
            }
        })?;
        out.extend(r);
        Ok(())
    }

    #[test]
    fn cuts_at_the_configured_angle_with_monotonic_times() {
        let (mut a, mut b) = ([ScanPoint::default(); 256], [ScanPoint::default(); 256]);
        let mut asm = ScanAssembler::new(AssemblerConfig::cut_at_degrees(90.0), &mut a, &mut b);
        let mut out = Vec::new();
        for k in 0..40 {
            feed(&mut asm, k, &mut out).unwrap();
        }
        // 40 packets x 8 = 320 firings; cuts at firings 24, 120, 216 and 312 (90 deg of each
        // 96-firing turn).
        assert_eq!(out.len(), 4);
        assert!(!out[0].complete, "first scan started mid-turn");
        assert_eq!(out[0].points, 24);
        assert!(out[1].complete && out[2].complete && out[3].complete);
        assert_eq!(out[1].points, 96);
        assert_eq!(out[1].start_ns, 1_000_000 + 24 * 1000);
        assert_eq!(asm.scan().points.len(), 96);
        let pts = asm.scan().points;
        assert_eq!(pts[0].col, 24);
        assert!(pts.windows(2).all(|w| w[1].t >= w[0].t) && pts[0].t == 0.0);
        assert!((pts[95].t - 95e-6).abs() < 1e-9);
        let tail = asm.flush().unwrap();
        assert!(!tail.complete);
        assert_eq!(tail.points, 320 - 312);
        assert_eq!(asm.stats.scans, 5);
        assert_eq!(asm.stats.incomplete_scans, 2);
    }

    #[test]
    fn duplicates_out_of_order_and_gaps_are_counted_not_corrupting() {
        let (mut a, mut b) = ([ScanPoint::default(); 256], [ScanPoint::default(); 256]);
        let mut asm = ScanAssembler::new(AssemblerConfig::cut_at_degrees(0.0), &mut a, &mut b);
        let mut out = Vec::new();
        let order = [
            0u64, 1, 2, 2, 3, 5, 4, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24,
            25, 26,
        ];
        let mut rejected = Vec::new();
        for &k in &order {
            if let Err(e) = feed(&mut asm, k, &mut out) {
                rejected.push((k, e));
            }
        }
        assert_eq!(rejected, [(2, PacketRejected::Duplicate), (4, PacketRejected::OutOfOrder)]);
        assert_eq!(asm.stats.duplicates, 1);
        assert_eq!(asm.stats.out_of_order, 1);
        assert_eq!(asm.stats.missing_packets, 1);
        // Packets 0..11 are the first turn (cut at 0 => scan 0 started at the cut? no: the first
        // scan starts with the stream, so it is incomplete), 12..23 the second.
        assert_eq!(out.len(), 2);
        assert_eq!(out[0].missing_packets, 1);
        assert!(!out[0].complete);
        assert_eq!(out[0].points, 11 * 8);
        assert!(out[1].complete);
        assert_eq!(out[1].points, 96);
        let pts = asm.scan().points;
        assert!(pts.windows(2).all(|w| w[1].t >= w[0].t));
    }

    #[test]
    fn big_jumps_restart_and_overflow_is_counted() {
        let mut cfg = AssemblerConfig::cut_at_degrees(0.0);
        cfg.reset_gap_packets = 5;
        let (mut a, mut b) = ([ScanPoint::default(); 256], [ScanPoint::default(); 256]);
        let mut asm = ScanAssembler::new(cfg, &mut a, &mut b);
        let mut out = Vec::new();
        for k in 0..30 {
            feed(&mut asm, k, &mut out).unwrap();
        }
        // The sensor restarts: counter back to 0.
        for k in 0..30 {
            feed(&mut asm, k, &mut out).unwrap();
        }
        assert_eq!(asm.stats.resets, 1);
        assert_eq!(asm.stats.duplicates + asm.stats.out_of_order, 0);
        // Scans: [0,12) incomplete, [12,24) complete, [24,30) cut by the restart (incomplete),
        // then [0,12) incomplete (no cut before it), [12,24) complete.
        assert_eq!(out.len(), 5);
        assert_eq!(out.iter().filter(|s| s.complete).count(), 2);

        let (mut a, mut b) = ([ScanPoint::default(); 10], [ScanPoint::default(); 10]);
        let mut small = ScanAssembler::new(AssemblerConfig::cut_at_degrees(0.0), &mut a, &mut b);
        let meta = PacketMeta { time_ns: 0, seq: PacketSeq { counter: 0, modulus: 0, step: 1.0 } };
        small
            .push_packet(meta, |sink| {
                for i in 0..15 {
                    sink(RawPoint { sweep: i, ..Default::default() });
                }
            })
            .unwrap();
        assert_eq!(small.building_len(), 10);
        assert_eq!(small.stats.overflow_points, 5);
        let info = small.flush().unwrap();
        assert_eq!(info.overflow, 5);
    }

    #[test]
    fn wrapping_counters() {
        assert_eq!(signed_delta(5, 3_599_999_990, 3_600_000_000), 15);
        assert_eq!(signed_delta(3_599_999_990, 5, 3_600_000_000), -15);
        assert_eq!(signed_delta(7, 7, 0), 0);
        assert_eq!(signed_delta(3, 7, 0), -4);
        assert_eq!(sweep_of_degrees(90.0), 1 << 30);
        assert_eq!(sweep_of_degrees(-90.0), 3 << 30);
        assert_eq!(sweep_of_degrees(360.0), 0);
    }
}
