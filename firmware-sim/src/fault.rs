//! A deterministic fault injector for the test suite (in the spirit of smoltcp's
//! `phy::FaultInjector`): it wraps any stream of wire events (the simulator's [`WireStream`], a
//! replayed capture, a live feed) and drops, bursts, duplicates, reorders, corrupts, restamps
//! and injects LiDAR packets, and spikes, gaps, NaNs, duplicates, swaps and restamps IMU
//! samples. Every decision comes from the seed, so the same seed and faults give the same bytes.
//!
//! LiDAR faults act on UDP datagrams; IMU faults on the IMU board's serial frames (one frame per
//! serial event, as [`WireStream`] sends them). Fault times are seconds after the injector's
//! `t0_ns` (normally the scenario's start).

use std::collections::VecDeque;
use std::fmt::Write as _;
use std::io::BufWriter;
use std::iter::Peekable;
use std::path::Path;

use loglio_core::sensor::imu_frame::{self, FRAME_MAX, ImuFrame};

use crate::files::{self, Summary};
use crate::lidar::{SensorModel, ouster, velodyne};
use crate::pcap_out::PcapWriter;
use crate::rng::SplitMix64;
use crate::scenario::{Scenario, ScenarioConfig};
use crate::stream::{Wire, WireEvent, WireStream, decode_serial};

/// Which IMU sensor a spike hits.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImuSensor {
    /// The accelerometer (m/s^2).
    Acc,
    /// The gyroscope (rad/s).
    Gyro,
}

/// One fault. Windows are `[from_s, to_s)` after `t0`; one-shot faults hit the first matching
/// item at or after `at_s`.
#[derive(Clone, Debug, PartialEq)]
pub enum Fault {
    /// Every UDP datagram in the window is lost (a LiDAR outage).
    LidarGap { from_s: f64, to_s: f64 },
    /// In the window, each UDP datagram starts a burst of `len` lost datagrams with probability
    /// `p`.
    BurstDrop { from_s: f64, to_s: f64, p: f64, len: u32 },
    /// In the window, each UDP datagram is sent twice with probability `p`.
    Duplicate { from_s: f64, to_s: f64, p: f64 },
    /// In the window, each UDP datagram is swapped with the next one with probability `p` (the
    /// capture times stay in order, the contents change places).
    Reorder { from_s: f64, to_s: f64, p: f64 },
    /// In the window, each UDP payload byte has one bit flipped with probability `rate`
    /// (after the UDP checksum: corruption the network did not catch).
    FlipBits { from_s: f64, to_s: f64, rate: f64 },
    /// The first LiDAR data packet at or after `at_s` is stamped `shift_s` late: both its
    /// capture time and the sensor's own timestamp in the payload.
    LidarStamp { at_s: f64, shift_s: f64 },
    /// Another sensor's datagrams (from [`FaultInjector::with_foreign`]) interleaved in the
    /// window, on their own ports (a VLP-32C and a VLP-16 share 2368).
    Foreign { from_s: f64, to_s: f64 },
    /// One IMU sample at or after `at_s` reads `value` on the x axis of `sensor`.
    ImuSpike { at_s: f64, sensor: ImuSensor, value: f32 },
    /// Every IMU sample in the window is lost.
    ImuGap { from_s: f64, to_s: f64 },
    /// One IMU sample at or after `at_s` reads NaN on every axis.
    ImuNan { at_s: f64 },
    /// One IMU sample at or after `at_s` is sent twice.
    ImuDuplicate { at_s: f64 },
    /// The IMU sample at or after `at_s` and the next one change places.
    ImuSwap { at_s: f64 },
    /// One IMU sample at or after `at_s` carries a stamp `shift_s` late.
    ImuStamp { at_s: f64, shift_s: f64 },
}

/// What the injector did, for exact assertions.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FaultStats {
    /// UDP datagrams lost (gaps and bursts).
    pub udp_dropped: u64,
    /// UDP datagrams sent twice.
    pub udp_duplicated: u64,
    /// UDP datagram pairs swapped.
    pub udp_swapped: u64,
    /// Payload bytes with a bit flipped.
    pub bytes_flipped: u64,
    /// LiDAR packets restamped.
    pub lidar_restamped: u64,
    /// Foreign datagrams injected.
    pub foreign: u64,
    /// IMU samples lost.
    pub imu_dropped: u64,
    /// IMU samples spiked.
    pub imu_spiked: u64,
    /// IMU samples made NaN.
    pub imu_nan: u64,
    /// IMU samples sent twice.
    pub imu_duplicated: u64,
    /// IMU sample pairs swapped.
    pub imu_swapped: u64,
    /// IMU samples restamped.
    pub imu_restamped: u64,
}

/// An event after the faults, with the IMU frame a serial event carries (decoded, faults
/// applied: a NaN frame is still here though a receiver's decoder refuses it).
#[derive(Clone, Debug, PartialEq)]
pub struct FaultedEvent {
    /// The event on the wire.
    pub event: WireEvent,
    /// The IMU frame of a serial event.
    pub frame: Option<ImuFrame>,
}

#[derive(Clone, Debug, Default)]
struct State {
    done: bool,
    burst_left: u32,
    /// Bytes still to pass before the next bit flip.
    skip: Option<u64>,
}

type Foreign<'a> = Peekable<Box<dyn Iterator<Item = WireEvent> + 'a>>;

/// Applies [`Fault`]s to a stream of wire events.
pub struct FaultInjector<'a, I: Iterator<Item = WireEvent>> {
    inner: Peekable<I>,
    foreign: Option<Foreign<'a>>,
    t0_ns: u64,
    faults: Vec<(Fault, State, SplitMix64)>,
    out: VecDeque<FaultedEvent>,
    popped: u64,
    /// Absolute index in `out` of a UDP datagram waiting for its swap partner.
    held_udp: Option<u64>,
    /// Absolute index in `out` of an IMU frame waiting for its swap partner.
    held_imu: Option<u64>,
    imu_times: Vec<u64>,
    /// What was done so far.
    pub stats: FaultStats,
}

impl<I: Iterator<Item = WireEvent>> core::fmt::Debug for FaultInjector<'_, I> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("FaultInjector")
            .field("t0_ns", &self.t0_ns)
            .field("faults", &self.faults.iter().map(|(f, ..)| f).collect::<Vec<_>>())
            .field("stats", &self.stats)
            .finish_non_exhaustive()
    }
}

fn ns(s: f64) -> u64 {
    (s.max(0.0) * 1e9) as u64
}

fn in_window(rel: u64, from_s: f64, to_s: f64) -> bool {
    (ns(from_s)..ns(to_s)).contains(&rel)
}

/// Bytes to pass before the next flip at `rate` (geometric).
fn geometric(rng: &mut SplitMix64, rate: f64) -> u64 {
    if rate >= 1.0 {
        return 0;
    }
    if rate <= 0.0 {
        return u64::MAX;
    }
    let u = 1.0 - rng.unit(); // (0, 1]
    let k = libm::log(u) / libm::log1p(-rate);
    if k >= 1e18 { u64::MAX } else { k as u64 }
}

/// Shifts the sensor timestamp(s) inside a LiDAR data payload by `shift_ns`; false when the
/// payload is not a known data packet.
pub fn shift_payload_stamp(port: u16, payload: &mut [u8], shift_ns: i64) -> bool {
    if port == velodyne::DATA_PORT && payload.len() == velodyne::DATA_PACKET_LEN {
        // u32 LE microseconds past the top of the hour, at 1200.
        let old = u32::from_le_bytes([payload[1200], payload[1201], payload[1202], payload[1203]]);
        let new = (old as i64 + shift_ns / 1_000).rem_euclid(3_600_000_000) as u32;
        payload[1200..1204].copy_from_slice(&new.to_le_bytes());
        return true;
    }
    if port != ouster::LIDAR_PORT {
        return false;
    }
    // Find the beam count from the length: LEGACY 16 (20 + 12 H), RNG19 64 + 16 (12 + 12 H).
    let n = ouster::COLUMNS_PER_PACKET;
    let len = payload.len();
    let legacy = len.is_multiple_of(n) && (len / n).checked_sub(20).is_some_and(|r| r.is_multiple_of(12));
    let rng19 = len.checked_sub(64).is_some_and(|m| {
        m.is_multiple_of(n) && (m / n).checked_sub(12).is_some_and(|r| r.is_multiple_of(12))
    });
    let (col_len, first) = match (legacy, rng19) {
        (true, _) => (len / n, 0),
        (false, true) => ((len - 64) / n, 32),
        _ => return false,
    };
    for c in 0..n {
        let at = first + c * col_len;
        let old = u64::from_le_bytes(payload[at..at + 8].try_into().unwrap_or([0; 8]));
        payload[at..at + 8].copy_from_slice(&old.saturating_add_signed(shift_ns).to_le_bytes());
    }
    true
}

fn is_lidar_data(port: u16) -> bool {
    port == velodyne::DATA_PORT || port == ouster::LIDAR_PORT
}

impl<'a, I: Iterator<Item = WireEvent>> FaultInjector<'a, I> {
    /// Applies `faults` to `inner`; fault times are seconds after `t0_ns`; `seed` drives every
    /// random choice (each fault has its own stream, so adding one leaves the others' alone).
    pub fn new(inner: I, t0_ns: u64, seed: u64, faults: &[Fault]) -> Self {
        let faults = faults
            .iter()
            .enumerate()
            .map(|(i, f)| (f.clone(), State::default(), SplitMix64::new(seed, 0xFA17_0000 + i as u64)))
            .collect();
        Self {
            inner: inner.peekable(),
            foreign: None,
            t0_ns,
            faults,
            out: VecDeque::new(),
            popped: 0,
            held_udp: None,
            held_imu: None,
            imu_times: Vec::new(),
            stats: FaultStats::default(),
        }
    }

    /// The datagrams a [`Fault::Foreign`] injects (serial events in it are ignored).
    pub fn with_foreign(mut self, foreign: impl Iterator<Item = WireEvent> + 'a) -> Self {
        let b: Box<dyn Iterator<Item = WireEvent> + 'a> = Box::new(foreign);
        self.foreign = Some(b.peekable());
        self
    }

    /// The send times of every IMU frame that came in, before the faults (the ground truth's
    /// times).
    pub fn input_imu_times(&self) -> &[u64] {
        &self.imu_times
    }

    /// The faulted stream as plain wire events.
    pub fn events(self) -> impl Iterator<Item = WireEvent> + 'a
    where
        I: 'a,
    {
        self.map(|f| f.event)
    }

    fn push(&mut self, e: FaultedEvent) -> u64 {
        self.out.push_back(e);
        self.popped + self.out.len() as u64 - 1
    }

    fn slot(&mut self, abs: u64) -> &mut FaultedEvent {
        let i = (abs - self.popped) as usize;
        &mut self.out[i]
    }

    /// The foreign datagram to send next, if it comes before the inner stream's next event.
    fn next_foreign(&mut self) -> Option<WireEvent> {
        let fg = self.foreign.as_mut()?;
        let windows = self.faults.iter().filter_map(|(f, ..)| match f {
            Fault::Foreign { from_s, to_s } => Some((*from_s, *to_s)),
            _ => None,
        });
        let last = windows.clone().map(|w| ns(w.1)).max()?;
        let t_inner = self.inner.peek().map_or(u64::MAX, |e| e.t_ns);
        loop {
            let e = fg.peek()?;
            let rel = e.t_ns.saturating_sub(self.t0_ns);
            if rel >= last {
                self.foreign = None;
                return None;
            }
            if e.t_ns > t_inner {
                return None;
            }
            let e = fg.next()?;
            if matches!(e.wire, Wire::Udp { .. }) && windows.clone().any(|w| in_window(rel, w.0, w.1)) {
                return Some(e);
            }
        }
    }

    fn udp(&mut self, mut e: WireEvent) {
        let rel = e.t_ns.saturating_sub(self.t0_ns);
        let Wire::Udp { port, payload } = &mut e.wire else { return };
        let port = *port;
        let mut dup = false;
        let mut swap = false;
        let mut drop = false;
        for (f, st, rng) in &mut self.faults {
            match *f {
                Fault::LidarGap { from_s, to_s } if in_window(rel, from_s, to_s) => drop = true,
                Fault::BurstDrop { from_s, to_s, p, len } if in_window(rel, from_s, to_s) => {
                    if st.burst_left == 0 && rng.unit() < p {
                        st.burst_left = len;
                    }
                    if st.burst_left > 0 {
                        st.burst_left -= 1;
                        drop = true;
                    }
                }
                Fault::Duplicate { from_s, to_s, p } if in_window(rel, from_s, to_s) => {
                    dup |= rng.unit() < p;
                }
                Fault::Reorder { from_s, to_s, p } if in_window(rel, from_s, to_s) => {
                    swap |= rng.unit() < p;
                }
                Fault::FlipBits { from_s, to_s, rate } if in_window(rel, from_s, to_s) => {
                    let mut pos = *st.skip.get_or_insert_with(|| geometric(rng, rate));
                    while let Some(b) = usize::try_from(pos).ok().and_then(|i| payload.get_mut(i)) {
                        *b ^= 1 << (rng.next_u64() % 8);
                        self.stats.bytes_flipped += 1;
                        pos = pos.saturating_add(1).saturating_add(geometric(rng, rate));
                    }
                    st.skip = Some(pos - payload.len() as u64);
                }
                Fault::LidarStamp { at_s, shift_s } if !st.done && rel >= ns(at_s) && is_lidar_data(port) => {
                    st.done = true;
                    let shift = (shift_s * 1e9) as i64;
                    shift_payload_stamp(port, payload, shift);
                    e.t_ns = e.t_ns.saturating_add_signed(shift);
                    self.stats.lidar_restamped += 1;
                }
                _ => {}
            }
        }
        if drop {
            self.stats.udp_dropped += 1;
            return;
        }
        let frame = FaultedEvent { event: e, frame: None };
        if let Some(h) = self.held_udp.take() {
            // Swap the contents, keep the capture times in order.
            let held = self.slot(h);
            let mut mine = frame;
            core::mem::swap(&mut held.event.wire, &mut mine.event.wire);
            self.stats.udp_swapped += 1;
            self.push(mine);
            return;
        }
        if dup {
            self.stats.udp_duplicated += 1;
            self.push(frame.clone());
        }
        let at = self.push(frame);
        if swap {
            self.held_udp = Some(at);
        }
    }

    fn serial(&mut self, e: WireEvent) {
        self.imu_times.push(e.t_ns);
        let Wire::Serial(bytes) = &e.wire else { return };
        let frames = decode_serial(bytes);
        let [mut fr] = frames[..] else {
            // Not exactly one frame: passed on untouched.
            self.push(FaultedEvent { event: e, frame: None });
            return;
        };
        let rel = e.t_ns.saturating_sub(self.t0_ns);
        let (mut changed, mut dup, mut swap) = (false, false, false);
        for (f, st, _) in &mut self.faults {
            match *f {
                Fault::ImuGap { from_s, to_s } if in_window(rel, from_s, to_s) => {
                    self.stats.imu_dropped += 1;
                    return;
                }
                Fault::ImuSpike { at_s, sensor, value } if !st.done && rel >= ns(at_s) => {
                    st.done = true;
                    match sensor {
                        ImuSensor::Acc => fr.acc[0] = value,
                        ImuSensor::Gyro => fr.gyro[0] = value,
                    }
                    changed = true;
                    self.stats.imu_spiked += 1;
                }
                Fault::ImuNan { at_s } if !st.done && rel >= ns(at_s) => {
                    st.done = true;
                    fr.acc = [f32::NAN; 3];
                    fr.gyro = [f32::NAN; 3];
                    changed = true;
                    self.stats.imu_nan += 1;
                }
                Fault::ImuStamp { at_s, shift_s } if !st.done && rel >= ns(at_s) => {
                    st.done = true;
                    fr.t_ns = fr.t_ns.saturating_add_signed((shift_s * 1e9) as i64);
                    changed = true;
                    self.stats.imu_restamped += 1;
                }
                Fault::ImuDuplicate { at_s } if !st.done && rel >= ns(at_s) => {
                    st.done = true;
                    dup = true;
                }
                Fault::ImuSwap { at_s } if !st.done && rel >= ns(at_s) => {
                    st.done = true;
                    swap = true;
                }
                _ => {}
            }
        }
        let wire = if changed {
            let mut buf = [0u8; FRAME_MAX];
            let n = imu_frame::encode(&fr, &mut buf).unwrap_or(0);
            Wire::Serial(buf[..n].to_vec())
        } else {
            e.wire
        };
        let item = FaultedEvent { event: WireEvent { t_ns: e.t_ns, wire }, frame: Some(fr) };
        if let Some(h) = self.held_imu.take() {
            let held = self.slot(h);
            let mut mine = item;
            core::mem::swap(&mut held.event.wire, &mut mine.event.wire);
            core::mem::swap(&mut held.frame, &mut mine.frame);
            self.stats.imu_swapped += 1;
            self.push(mine);
            return;
        }
        if dup {
            self.stats.imu_duplicated += 1;
            self.push(item.clone());
        }
        let at = self.push(item);
        if swap {
            self.held_imu = Some(at);
        }
    }

    fn front_ready(&self) -> bool {
        !self.out.is_empty() && self.held_udp != Some(self.popped) && self.held_imu != Some(self.popped)
    }
}

impl<I: Iterator<Item = WireEvent>> Iterator for FaultInjector<'_, I> {
    type Item = FaultedEvent;

    fn next(&mut self) -> Option<FaultedEvent> {
        loop {
            if self.front_ready() {
                self.popped += 1;
                return self.out.pop_front();
            }
            if let Some(f) = self.next_foreign() {
                self.stats.foreign += 1;
                self.push(FaultedEvent { event: f, frame: None });
                continue;
            }
            match self.inner.next() {
                Some(e @ WireEvent { wire: Wire::Udp { .. }, .. }) => self.udp(e),
                Some(e) => self.serial(e),
                None => {
                    // No partner comes: a held item goes as it is.
                    self.held_udp = None;
                    self.held_imu = None;
                    if self.out.is_empty() {
                        return None;
                    }
                }
            }
        }
    }
}

/// The sensor whose datagrams a [`Fault::Foreign`] brings: another model on the same kind of
/// port (VLP-32C for a VLP-16, and back).
pub fn foreign_model(m: SensorModel) -> SensorModel {
    match m {
        SensorModel::Vlp16 => SensorModel::Vlp32c,
        SensorModel::Vlp32c | SensorModel::Hdl32e => SensorModel::Vlp16,
        SensorModel::Os1_16 => SensorModel::Os1_64,
        SensorModel::Os1_64 | SensorModel::Os1_128 => SensorModel::Os1_16,
    }
}

/// A second sensor in `sc`'s world, running only over `[from_s, to_s)` of `sc` (so that only
/// the window is simulated): its wire stream feeds [`FaultInjector::with_foreign`].
pub fn foreign_scenario(sc: &Scenario, from_s: f64, to_s: f64) -> anyhow::Result<Scenario> {
    let c = sc.config();
    let mut f = ScenarioConfig::new(c.kind, foreign_model(c.lidar.model()), c.seed ^ 0xF0E1);
    f.start_unix_ns = c.start_unix_ns + ns(from_s);
    f.duration_s = to_s - from_s;
    f.threads = c.threads;
    Scenario::from_config(f).map_err(|e| anyhow::anyhow!("foreign scenario: {e:?}"))
}

/// Writes `sc`'s files (as [`files::write_all`]) from a faulted stream: `lidar.pcap`,
/// `imu.bin` and `imu.csv` carry the faults (a NaN sample is the row's `nan`), the ground truth
/// is the clean one at every input IMU time, and `faults.txt` lists the faults and what they
/// did.
pub fn write_faulted<I: Iterator<Item = WireEvent>>(
    sc: &Scenario,
    mut inj: FaultInjector<'_, I>,
    dir: &Path,
) -> anyhow::Result<(Summary, FaultStats)> {
    std::fs::create_dir_all(dir)?;
    let ep = files::endpoint(sc);
    let mut pcap = PcapWriter::new(BufWriter::new(std::fs::File::create(dir.join("lidar.pcap"))?))?;
    let (mut serial, mut frames) = (Vec::new(), Vec::new());
    let mut sum = Summary::default();
    for fe in &mut inj {
        match fe.event.wire {
            Wire::Udp { port, payload } => {
                pcap.write_udp(fe.event.t_ns, &ep, port, port, &payload)?;
                sum.datagrams += 1;
            }
            Wire::Serial(bytes) => {
                serial.extend_from_slice(&bytes);
                frames.extend(fe.frame);
            }
        }
    }
    pcap.finish()?;
    std::fs::write(dir.join("imu.bin"), &serial)?;
    sum.serial_bytes = serial.len() as u64;
    sum.imu_frames = frames.len() as u64;
    std::fs::write(dir.join("imu.csv"), files::imu_csv(&frames))?;
    files::write_truth_and_meta(sc, inj.input_imu_times(), dir)?;
    let mut log = String::new();
    for (f, ..) in &inj.faults {
        let _ = writeln!(log, "{f:?}");
    }
    let _ = writeln!(log, "{:?}", inj.stats);
    std::fs::write(dir.join("faults.txt"), log)?;
    Ok((sum, inj.stats))
}

/// [`write_faulted`] for scenario `sc` itself, with a foreign sensor simulated for each
/// [`Fault::Foreign`] window.
pub fn write_all_faulted(
    sc: &Scenario,
    faults: &[Fault],
    seed: u64,
    dir: &Path,
) -> anyhow::Result<(Summary, FaultStats)> {
    let mut foreign = Vec::new();
    for f in faults {
        if let Fault::Foreign { from_s, to_s } = *f {
            let fs = foreign_scenario(sc, from_s, to_s)?;
            foreign.extend(WireStream::new(&fs).filter(|e| matches!(e.wire, Wire::Udp { .. })));
        }
    }
    foreign.sort_by_key(|e| e.t_ns);
    let inj = FaultInjector::new(WireStream::new(sc), sc.start_ns(), seed, faults)
        .with_foreign(foreign.into_iter());
    write_faulted(sc, inj, dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    const T0: u64 = 1_000_000_000_000;
    const MS: u64 = 1_000_000;

    fn imu_event(k: u64) -> WireEvent {
        let fr =
            ImuFrame { seq: k as u32, t_ns: T0 + k * 5 * MS, gyro: [0.1, 0.2, 0.3], acc: [0.0, 0.0, 9.81] };
        let mut buf = [0u8; FRAME_MAX];
        let n = imu_frame::encode(&fr, &mut buf).unwrap();
        WireEvent { t_ns: fr.t_ns, wire: Wire::Serial(buf[..n].to_vec()) }
    }

    /// 1 s: a VLP data packet every 10 ms (k in the first payload bytes, the stamp at 1200) and
    /// an IMU frame every 5 ms.
    fn stream() -> Vec<WireEvent> {
        let mut v = Vec::new();
        for k in 0..200u64 {
            v.push(imu_event(k));
            if k % 2 == 1 {
                let mut p = vec![0u8; velodyne::DATA_PACKET_LEN];
                p[..8].copy_from_slice(&(k / 2).to_le_bytes());
                p[1200..1204].copy_from_slice(&((k * 5_000) as u32).to_le_bytes());
                v.push(WireEvent {
                    t_ns: T0 + k * 5 * MS,
                    wire: Wire::Udp { port: velodyne::DATA_PORT, payload: p },
                });
            }
        }
        v
    }

    fn run(faults: &[Fault]) -> (Vec<FaultedEvent>, FaultStats) {
        let mut inj = FaultInjector::new(stream().into_iter(), T0, 7, faults);
        let out: Vec<_> = (&mut inj).collect();
        (out, inj.stats)
    }

    fn udp_ids(out: &[FaultedEvent]) -> Vec<u64> {
        out.iter()
            .filter_map(|f| match &f.event.wire {
                Wire::Udp { payload, .. } => Some(u64::from_le_bytes(payload[..8].try_into().unwrap())),
                _ => None,
            })
            .collect()
    }

    fn imu_frames(out: &[FaultedEvent]) -> Vec<ImuFrame> {
        out.iter().filter_map(|f| f.frame).collect()
    }

    #[test]
    fn no_fault_is_the_identity() {
        let (out, stats) = run(&[]);
        assert_eq!(out.iter().map(|f| f.event.clone()).collect::<Vec<_>>(), stream());
        assert_eq!(stats, FaultStats::default());
        assert_eq!(imu_frames(&out).len(), 200);
    }

    #[test]
    fn lidar_gap_drops_the_window() {
        // Packets at 5, 15, ... ms: [0.2, 0.5) holds 30 of them.
        let (out, stats) = run(&[Fault::LidarGap { from_s: 0.2, to_s: 0.5 }]);
        assert_eq!(stats.udp_dropped, 30);
        let ids = udp_ids(&out);
        assert_eq!(ids.len(), 70);
        assert!(!ids.iter().any(|k| (20..50).contains(k)));
        assert_eq!(imu_frames(&out).len(), 200);
    }

    #[test]
    fn bursts_drop_runs_of_len() {
        let (out, stats) = run(&[Fault::BurstDrop { from_s: 0.0, to_s: 1.0, p: 1.0, len: 3 }]);
        assert_eq!((stats.udp_dropped, udp_ids(&out).len()), (100, 0));
        let (out, stats) = run(&[Fault::BurstDrop { from_s: 0.0, to_s: 1.0, p: 0.1, len: 4 }]);
        assert_eq!(stats.udp_dropped as usize + udp_ids(&out).len(), 100);
        assert!((10..=80).contains(&stats.udp_dropped), "{stats:?}");
    }

    #[test]
    fn duplicates_send_twice() {
        let (out, stats) = run(&[Fault::Duplicate { from_s: 0.0, to_s: 0.1, p: 1.0 }]);
        assert_eq!(stats.udp_duplicated, 10);
        let ids = udp_ids(&out);
        assert_eq!(ids.len(), 110);
        assert_eq!(&ids[..4], &[0, 0, 1, 1]);
    }

    #[test]
    fn reorder_swaps_contents_and_keeps_times_in_order() {
        let (out, stats) = run(&[Fault::Reorder { from_s: 0.0, to_s: 0.04, p: 1.0 }]);
        // Packets 0..3 are in the window: 0 waits for 1, 2 for 3.
        assert_eq!(stats.udp_swapped, 2);
        assert_eq!(&udp_ids(&out)[..6], &[1, 0, 3, 2, 4, 5]);
        assert!(out.windows(2).all(|w| w[0].event.t_ns <= w[1].event.t_ns));
        assert_eq!(out.len(), 300);
    }

    #[test]
    fn flips_bits_at_the_rate() {
        let (out, stats) = run(&[Fault::FlipBits { from_s: 0.0, to_s: 1.0, rate: 1.0 }]);
        assert_eq!(stats.bytes_flipped, 100 * velodyne::DATA_PACKET_LEN as u64);
        let clean = stream();
        let (a, b) = (&out[2].event.wire, &clean[2].wire);
        let (Wire::Udp { payload: a, .. }, Wire::Udp { payload: b, .. }) = (a, b) else { panic!() };
        assert!(a.iter().zip(b).all(|(x, y)| (x ^ y).count_ones() == 1));
        // 1e-2 of 120,600 bytes: about 1,206.
        let (_, stats) = run(&[Fault::FlipBits { from_s: 0.0, to_s: 1.0, rate: 1e-2 }]);
        assert!((1_000..1_400).contains(&stats.bytes_flipped), "{stats:?}");
    }

    #[test]
    fn restamps_one_packet_and_its_payload() {
        let (out, stats) = run(&[Fault::LidarStamp { at_s: 0.5, shift_s: 60.0 }]);
        assert_eq!(stats.lidar_restamped, 1);
        let hit: Vec<_> = out.iter().filter(|f| f.event.t_ns > T0 + 2_000 * MS).collect();
        assert_eq!(hit.len(), 1);
        assert_eq!(hit[0].event.t_ns, T0 + 505 * MS + 60_000 * MS);
        let Wire::Udp { payload, .. } = &hit[0].event.wire else { panic!() };
        assert_eq!(u32::from_le_bytes(payload[1200..1204].try_into().unwrap()), 505_000 + 60_000_000);
        assert_eq!(u64::from_le_bytes(payload[..8].try_into().unwrap()), 50);
    }

    #[test]
    fn velodyne_stamp_wraps_at_the_hour() {
        let mut p = vec![0u8; velodyne::DATA_PACKET_LEN];
        p[1200..1204].copy_from_slice(&3_599_000_000u32.to_le_bytes());
        assert!(shift_payload_stamp(velodyne::DATA_PORT, &mut p, 60_000_000_000));
        assert_eq!(u32::from_le_bytes(p[1200..1204].try_into().unwrap()), 59_000_000);
        assert!(!shift_payload_stamp(velodyne::POSITION_PORT, &mut p, 1));
    }

    #[test]
    fn ouster_stamps_shift_in_every_column() {
        for (beams, legacy) in [(16usize, true), (64, true), (16, false), (64, false)] {
            let (col, first) = if legacy { (20 + 12 * beams, 0) } else { (12 + 12 * beams, 32) };
            let len = first + 16 * col + if legacy { 0 } else { 32 };
            let mut p = vec![0u8; len];
            for c in 0..16 {
                p[first + c * col..first + c * col + 8].copy_from_slice(&(1000 + c as u64).to_le_bytes());
            }
            assert!(shift_payload_stamp(ouster::LIDAR_PORT, &mut p, 5), "{beams} {legacy}");
            for c in 0..16 {
                let at = first + c * col;
                assert_eq!(u64::from_le_bytes(p[at..at + 8].try_into().unwrap()), 1005 + c as u64);
            }
        }
    }

    #[test]
    fn foreign_datagrams_only_in_the_window() {
        let foreign: Vec<WireEvent> = (0..100u64)
            .flat_map(|k| {
                [
                    WireEvent {
                        t_ns: T0 + k * 10 * MS + 1,
                        wire: Wire::Udp { port: 2368, payload: vec![0xAB; 1206] },
                    },
                    imu_event(k),
                ]
            })
            .collect();
        let mut inj =
            FaultInjector::new(stream().into_iter(), T0, 1, &[Fault::Foreign { from_s: 0.3, to_s: 0.6 }])
                .with_foreign(foreign.into_iter());
        let out: Vec<_> = (&mut inj).collect();
        assert_eq!(inj.stats.foreign, 30);
        let n = out
            .iter()
            .filter(|f| matches!(&f.event.wire, Wire::Udp { payload, .. } if payload[0] == 0xAB))
            .count();
        assert_eq!(n, 30);
        assert_eq!(out.len(), 330);
        assert!(out.windows(2).all(|w| w[0].event.t_ns <= w[1].event.t_ns));
    }

    #[test]
    fn imu_gap_spike_nan_and_stamp() {
        let (out, stats) = run(&[
            Fault::ImuGap { from_s: 0.1, to_s: 0.2 },
            Fault::ImuSpike { at_s: 0.5, sensor: ImuSensor::Acc, value: 1000.0 },
            Fault::ImuSpike { at_s: 0.6, sensor: ImuSensor::Gyro, value: 1000.0 },
            Fault::ImuNan { at_s: 0.7 },
            Fault::ImuStamp { at_s: 0.8, shift_s: 60.0 },
        ]);
        assert_eq!((stats.imu_dropped, stats.imu_spiked, stats.imu_nan, stats.imu_restamped), (20, 2, 1, 1));
        let fr = imu_frames(&out);
        assert_eq!(fr.len(), 180);
        assert_eq!(fr.iter().filter(|f| f.acc[0] == 1000.0).count(), 1);
        assert_eq!(fr.iter().filter(|f| f.gyro[0] == 1000.0).count(), 1);
        assert_eq!(fr.iter().filter(|f| f.acc[0].is_nan()).count(), 1);
        assert_eq!(fr.iter().filter(|f| f.t_ns == T0 + 160 * 5 * MS + 60_000 * MS).count(), 1);
        // The serial bytes carry the faulted frames; a receiver refuses the NaN one.
        let bytes: Vec<u8> = out
            .iter()
            .filter_map(|f| match &f.event.wire {
                Wire::Serial(b) => Some(b.clone()),
                _ => None,
            })
            .flatten()
            .collect();
        let decoded = decode_serial(&bytes);
        assert_eq!(decoded.len(), 179);
        assert_eq!(decoded.iter().filter(|f| f.acc[0] == 1000.0).count(), 1);
    }

    #[test]
    fn imu_duplicate_and_swap() {
        let (out, stats) = run(&[Fault::ImuDuplicate { at_s: 0.1 }, Fault::ImuSwap { at_s: 0.5 }]);
        assert_eq!((stats.imu_duplicated, stats.imu_swapped), (1, 1));
        let seqs: Vec<u32> = imu_frames(&out).iter().map(|f| f.seq).collect();
        assert_eq!(seqs.len(), 201);
        assert_eq!(&seqs[19..23], &[19, 20, 20, 21]);
        assert_eq!(&seqs[100..104], &[99, 101, 100, 102]);
        assert!(out.windows(2).all(|w| w[0].event.t_ns <= w[1].event.t_ns));
    }

    /// Files from a real scenario: no fault writes what `write_all` writes; the same seed and
    /// faults write the same bytes; another seed does not.
    #[test]
    fn files_are_deterministic() {
        use crate::scenario::ScenarioKind;
        let mut c = ScenarioConfig::new(ScenarioKind::Vehicle, SensorModel::Vlp16, 3);
        c.duration_s = 0.6;
        let sc = Scenario::from_config(c).unwrap();
        let base = std::env::temp_dir().join(format!("loglio-fault-files-{}", std::process::id()));
        let faults = [
            Fault::FlipBits { from_s: 0.0, to_s: 0.6, rate: 1e-3 },
            Fault::LidarStamp { at_s: 0.3, shift_s: 60.0 },
            Fault::Foreign { from_s: 0.2, to_s: 0.4 },
            Fault::ImuNan { at_s: 0.25 },
        ];
        let names =
            ["lidar.pcap", "imu.bin", "imu.csv", "groundtruth.tum", "lidar_groundtruth.tum", "scenario.json"];
        let read = |d: &str| names.map(|n| std::fs::read(base.join(d).join(n)).unwrap());
        crate::files::write_all(&sc, &base.join("clean")).unwrap();
        write_all_faulted(&sc, &[], 1, &base.join("none")).unwrap();
        assert_eq!(read("clean"), read("none"));
        let (_, s1) = write_all_faulted(&sc, &faults, 1, &base.join("a")).unwrap();
        let (_, s2) = write_all_faulted(&sc, &faults, 1, &base.join("b")).unwrap();
        write_all_faulted(&sc, &faults, 2, &base.join("c")).unwrap();
        assert_eq!(s1, s2);
        assert!(
            s1.foreign > 0 && s1.bytes_flipped > 0 && s1.lidar_restamped == 1 && s1.imu_nan == 1,
            "{s1:?}"
        );
        let (a, b, c) = (read("a"), read("b"), read("c"));
        assert_eq!(a, b);
        assert_ne!(a[0], c[0]);
        let csv = String::from_utf8(a[2].clone()).unwrap();
        assert_eq!(csv.lines().filter(|l| l.ends_with(",nan,nan,nan,nan,nan,nan")).count(), 1);
        let _ = std::fs::remove_dir_all(&base);
    }

    #[test]
    fn same_seed_same_stream() {
        let faults = [
            Fault::BurstDrop { from_s: 0.0, to_s: 1.0, p: 0.05, len: 3 },
            Fault::FlipBits { from_s: 0.0, to_s: 1.0, rate: 1e-3 },
            Fault::Reorder { from_s: 0.0, to_s: 1.0, p: 0.1 },
        ];
        assert_eq!(run(&faults), run(&faults));
        let other: Vec<_> = FaultInjector::new(stream().into_iter(), T0, 8, &faults).collect();
        assert_ne!(run(&faults).0, other);
    }
}
