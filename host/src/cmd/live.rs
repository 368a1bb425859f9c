//! `loglio live`: LiDAR packets over UDP, the IMU from a serial port (loglio's IMU frames) or
//! from the Ouster's IMU packets, through the odometry as they arrive, with the same outputs as
//! `loglio replay`.
//!
//! # Threads and queues
//!
//! ```text
//! UDP LiDAR port ──┐  receive threads: recv, stamp,      decode thread: decoder,
//! UDP 8308 / 7503 ─┴─ try_send ──[datagrams, bounded]──> time alignment, scan assembly ─┐
//! serial IMU ──────── IMU thread: frame decoding, try_send ─────────────────────────────┤
//!                                                                                       v
//!                          the calling thread: odometry + outputs <──[IMU samples + scans, bounded]
//! ```
//!
//! - A receive thread never waits on the rest: it hands each datagram on with `try_send`, and a
//!   datagram that finds the queue full is dropped and counted (*socket queue* drops). The
//!   kernel's receive buffer in front of it ([`crate::input::udp`], `SO_RCVBUF`) absorbs bursts while
//!   the thread is descheduled.
//! - The decode thread turns datagrams into scans ([`LidarStream`], as the replay does) and
//!   Ouster IMU packets into samples. Undecodable and out-of-order packets are *decoder* drops.
//!   At most [`MAX_QUEUED_SCANS`] scans wait for the odometry; a scan beyond that is dropped
//!   and counted (*scans* drops: the odometry does not keep up).
//! - The IMU thread reads the serial device (a UART, a USB adapter, a pseudo-terminal, or a
//!   FIFO) and decodes the frames; frames missing by their sequence numbers and samples that
//!   find the queue full are *IMU* drops.
//! - The odometry runs on the calling thread through [`Runner`]: every IMU sample up to a
//!   scan's end is pushed before the scan; a scan the IMU has not covered after
//!   [`IMU_WAIT`] is processed anyway (counted as a scan without IMU).
//! - Once a second a status line goes to stderr: scan rate, packets/s, latency (from the
//!   receipt of the packet that completed a scan to its result), real-time margin (scan period
//!   / processing time) and the drop counts.
//! - Ctrl-C (SIGINT) or SIGTERM, or `--seconds`: the receive threads stop, the queues are
//!   drained, the complete scans are processed (the turn being assembled is not), and every
//!   output is written. A second Ctrl-C exits at once (status 1).
//! - A Velodyne's packets carry microseconds past the hour: with `time.lidar_time_source =
//!   "packet"` the hour comes from the GPS time of the position packets (port 8308). Data
//!   packets that arrive before the first position packet with a GPS time (at most
//!   [`GPS_WAIT`]) are skipped, so that no scan mixes two clocks.

use std::cell::RefCell;
use std::fs::File;
use std::io::{self, Read};
use std::net::{IpAddr, SocketAddr};
use std::path::{Path, PathBuf};
use std::rc::Rc;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use loglio_core::imu::ImuSample;

use crate::cmd::Watch;
use crate::config::{Config, ImuSource, LidarTimeSource, SensorFamily};
use crate::diag::warn;
use crate::error::PipelineError;
use crate::input::device_imu::{DeviceImuReader, ImuProtocol};
use crate::input::lidar_stream::{self, Decoded, LidarStream, SensorDecoder, VELODYNE_POSITION_PORT};
use crate::input::mavlink_imu::{MavlinkImuDecoder, RawScale};
use crate::input::time_align::{ClockEstimate, DeviceClock};
use crate::input::udp::{self, UdpSource};
use crate::run::engine;
use crate::run::runner::{OwnedScan, RunStats, Runner};
use crate::run::setup::{DataExtrinsic, PacketSetup, RunSetup};
use crate::sink::files::{self, Finished};
use std::sync::Mutex;

/// Datagrams waiting for the decode thread (about 1.4 s of a VLP-32C, 3 s of an OS1-128).
pub const DATAGRAM_QUEUE: usize = 2048;
/// IMU samples and scans waiting for the odometry (8 s of a 1 kHz IMU).
pub const ODOMETRY_QUEUE: usize = 8192;
/// Most scans waiting for the odometry; more are dropped.
pub const MAX_QUEUED_SCANS: usize = 4;
/// How long a scan waits for the IMU to reach its end before it is processed without.
pub const IMU_WAIT: Duration = Duration::from_millis(500);
/// How long Velodyne data packets are skipped while waiting for a GPS time.
pub const GPS_WAIT: Duration = Duration::from_millis(1500);
/// The receive threads' read timeout (how soon they notice a stop).
const POLL: Duration = Duration::from_millis(100);

/// Where the IMU comes from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum LiveImu {
    /// The configuration's `imu.source`: `serial` (`imu.serial_device` at `imu.baud`) or
    /// `ouster`.
    Config,
    /// loglio's serial IMU frames from this device: a UART, a USB serial adapter, a
    /// pseudo-terminal, or a FIFO another program writes.
    Serial(PathBuf),
    /// The Ouster's IMU packets (UDP, `network.imu_port` or the metadata's).
    OusterPackets,
    /// An autopilot's MAVLink `HIGHRES_IMU`, `SCALED_IMU` or `RAW_IMU` on this UDP port.
    Mavlink(u16),
    /// No IMU: LiDAR-only, a constant-velocity model (`imu.source = "none"`, `--no-imu`).
    None,
}

/// A live run's settings.
#[derive(Clone, Debug)]
pub struct LiveOptions {
    /// Configuration, outputs, ground truth.
    pub setup: RunSetup,
    /// The IMU.
    pub imu: LiveImu,
    /// Serial baud rate (overrides `imu.baud`).
    pub baud: Option<u32>,
    /// What the serial IMU speaks (overrides `imu.protocol`).
    pub imu_protocol: Option<ImuProtocol>,
    /// Local address to listen on (overrides `network.bind`).
    pub bind: Option<IpAddr>,
    /// LiDAR data port (overrides the metadata's and `network.lidar_port`).
    pub lidar_port: Option<u16>,
    /// Ouster IMU port (overrides the metadata's and `network.imu_port`).
    pub imu_port: Option<u16>,
    /// Velodyne position packet port (GPS time).
    pub position_port: u16,
    /// When to stop (`seconds` from the moment reception starts), the timeouts
    /// (`lidar_timeout_s`: no LiDAR packet), the status line.
    pub watch: Watch,
    /// Handle SIGINT and SIGTERM (the command does; a library caller may not want to).
    pub handle_signals: bool,
}

impl LiveOptions {
    /// Defaults for `setup`: the configuration's IMU, ports and address, no time limit.
    pub fn new(setup: RunSetup) -> Self {
        LiveOptions {
            setup,
            imu: LiveImu::Config,
            baud: None,
            imu_protocol: None,
            bind: None,
            lidar_port: None,
            imu_port: None,
            position_port: VELODYNE_POSITION_PORT,
            watch: Watch::default(),
            handle_signals: true,
        }
    }
}

/// Why the run stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StopReason {
    /// Ctrl-C or SIGTERM.
    Signal,
    /// `--seconds` passed.
    Seconds,
}

/// Counts of a live run (the status line's and the summary's).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LiveCounts {
    /// Datagrams received on every socket.
    pub datagrams: u64,
    /// Datagrams dropped because the decode thread's queue was full.
    pub socket_drops: u64,
    /// LiDAR data packets decoded.
    pub lidar_packets: u64,
    /// Packets the decoder or the scan assembly refused (bad size or header, out of order,
    /// duplicate).
    pub decoder_drops: u64,
    /// Packets missing from the sequence (lost before this program: network, kernel buffer).
    pub missing_packets: u64,
    /// Velodyne data packets skipped while waiting for the GPS time.
    pub gps_wait_packets: u64,
    /// IMU samples received (serial frames or Ouster IMU packets).
    pub imu_samples: u64,
    /// IMU samples lost: frames missing by their sequence numbers, samples that found the
    /// queue full, samples the odometry refused.
    pub imu_drops: u64,
    /// Bytes of the serial line that were not part of a good frame (noise, partial frames).
    pub imu_noise_bytes: u64,
    /// Serial IMU messages refused (failed checks, unreadable or incomplete data).
    pub imu_rejected: u64,
    /// Complete scans dropped because the odometry did not keep up.
    pub scan_drops: u64,
    /// Mean latency, receipt of a scan's last packet to its result, seconds.
    pub latency_mean_s: f64,
    /// Largest latency, seconds.
    pub latency_max_s: f64,
}

/// A finished live run.
#[derive(Debug)]
pub struct LiveReport {
    /// The odometry's counts and times.
    pub stats: RunStats,
    /// What was written and the evaluation.
    pub finished: Finished,
    /// Reception, decoding and drop counts.
    pub counts: LiveCounts,
    /// Why it stopped.
    pub stopped_by: StopReason,
    /// The scan period, s.
    pub scan_period_s: f64,
    /// Wall time, s.
    pub wall_s: f64,
    /// Latency from a scan's last packet to its result, beside its processing time.
    pub result_latency: crate::sink::WireLatency,
    /// The IMU input with its decoding counts in the summary: `serial IMU (xsens)`,
    /// `MAVLink IMU (HIGHRES_IMU)`; `None` for the Ouster's IMU packets.
    pub imu_input: Option<String>,
    /// The device clock against this computer's (Xsens, VectorNav with their time configured).
    pub imu_clock: Option<ClockEstimate>,
}

/// What the threads count (read by the status line).
#[derive(Debug, Default)]
struct Counters {
    datagrams: AtomicU64,
    lidar_datagrams: AtomicU64,
    /// ns since the start of the last LiDAR datagram (0: none yet).
    last_lidar_ns: AtomicU64,
    socket_drops: AtomicU64,
    lidar_packets: AtomicU64,
    decoder_drops: AtomicU64,
    missing_packets: AtomicU64,
    gps_wait: AtomicU64,
    imu_samples: AtomicU64,
    last_imu_ns: AtomicU64,
    imu_queue_drops: AtomicU64,
    imu_seq_gaps: AtomicU64,
    imu_noise_bytes: AtomicU64,
    imu_rejected: AtomicU64,
    /// VectorNav messages refused for their output groups.
    imu_unsupported: AtomicU64,
    /// The serial IMU's device clock estimate.
    imu_clock: Mutex<Option<ClockEstimate>>,
    /// MAVLink IMU messages not used (a worse kind than the one used, RAW_IMU without scales).
    imu_ignored: AtomicU64,
    /// The MAVLink IMU message used.
    imu_kind: Mutex<Option<&'static str>>,
    scans_queued: AtomicUsize,
    scan_drops: AtomicU64,
}

/// A received datagram.
struct Datagram {
    /// The port the decoder knows it by (see [`LidarStream::packet`]).
    port: u16,
    data: Vec<u8>,
    /// Host wall-clock receive time, ns since 1970 (capture time).
    capture_ns: u64,
    /// Monotonic receive time, ns since the start.
    at_ns: u64,
}

/// What the odometry thread receives.
pub(crate) enum Msg {
    Imu(ImuSample),
    Scan { scan: OwnedScan, arrival_ns: u64 },
}

pub(crate) fn since(t0: Instant) -> u64 {
    t0.elapsed().as_nanos().max(1) as u64
}

/// An open IMU byte stream.
enum ImuPort {
    /// A serial port (read timeouts let the thread notice a stop).
    Serial(Box<dyn serialport::SerialPort>),
    /// A FIFO (blocking reads; the thread is left behind at the stop).
    Fifo(File),
}

/// Opens the IMU device: a serial port or pseudo-terminal through serialport, a FIFO as a file.
fn open_imu(path: &Path, baud: u32) -> Result<ImuPort, PipelineError> {
    let shown = path.display();
    let meta = std::fs::metadata(path).map_err(|e| {
        let ports = crate::input::serial::ports();
        let listed = if ports.is_empty() {
            "no serial ports found on this computer".to_string()
        } else {
            format!("serial ports here: {}", ports.join(", "))
        };
        PipelineError(format!("IMU serial device {shown}: {} ({listed})", io_reason(&e)))
    })?;
    use std::os::unix::fs::FileTypeExt;
    let ft = meta.file_type();
    if ft.is_fifo() {
        let f =
            File::open(path).map_err(|e| PipelineError(format!("IMU FIFO {shown}: {}", io_reason(&e))))?;
        return Ok(ImuPort::Fifo(f));
    }
    if ft.is_file() || ft.is_dir() {
        return Err(PipelineError(format!(
            "IMU serial device {shown} is a {}, not a serial port (a capture of IMU frames is replayed with `loglio replay --imu FILE`)",
            if ft.is_dir() { "directory" } else { "regular file" }
        )));
    }
    let path_str = path.to_string_lossy();
    crate::input::serial::open(&path_str, baud, POLL).map(ImuPort::Serial).map_err(|e| {
        PipelineError(format!("IMU serial device {shown}: {}", crate::diag::one_line(&e.to_string())))
    })
}

/// An I/O error's reason without the "(os error N)" suffix.
fn io_reason(e: &io::Error) -> String {
    let s = e.to_string();
    match s.find(" (os error") {
        Some(i) => s[..i].to_string(),
        None => s,
    }
}

/// Binds one UDP socket with a clear error for a port in use.
fn bind_udp(addr: SocketAddr, what: &str) -> Result<UdpSource, PipelineError> {
    let sock = UdpSource::bind(addr, udp::DEFAULT_RCVBUF, POLL).map_err(|e| {
        if e.kind() == io::ErrorKind::AddrInUse {
            PipelineError(format!(
                "cannot listen for {what} on UDP {addr}: the port is already in use (another loglio, or a LiDAR driver, is listening there; stop it or pass another port)"
            ))
        } else if e.kind() == io::ErrorKind::AddrNotAvailable {
            PipelineError(format!(
                "cannot listen for {what} on UDP {addr}: {addr} is not an address of this computer (see --bind)"
            ))
        } else {
            PipelineError(format!("cannot listen for {what} on UDP {addr}: {}", io_reason(&e)))
        }
    })?;
    Ok(sock)
}

/// One socket's receive thread: never blocks on the rest of the program.
fn receive(
    sock: UdpSource,
    port: u16,
    lidar: bool,
    tx: SyncSender<Datagram>,
    c: Arc<Counters>,
    stop: Arc<AtomicBool>,
    t0: Instant,
) {
    let mut buf = vec![0u8; 65_536];
    let mut warned = false;
    while !stop.load(Relaxed) {
        match sock.recv(&mut buf) {
            Ok(Some((n, _, capture_ns))) => {
                let at_ns = since(t0);
                c.datagrams.fetch_add(1, Relaxed);
                if lidar {
                    c.lidar_datagrams.fetch_add(1, Relaxed);
                    c.last_lidar_ns.store(at_ns, Relaxed);
                }
                let d = Datagram { port, data: buf[..n].to_vec(), capture_ns, at_ns };
                match tx.try_send(d) {
                    Ok(()) => {}
                    Err(TrySendError::Full(_)) => {
                        c.socket_drops.fetch_add(1, Relaxed);
                    }
                    Err(TrySendError::Disconnected(_)) => break,
                }
            }
            Ok(None) => {}
            Err(e) => {
                if !warned {
                    warn(format!("UDP port {port}: {}; still listening", io_reason(&e)));
                    warned = true;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }
}

fn send_imu(tx: &SyncSender<Msg>, s: ImuSample, c: &Counters, t0: Instant) -> bool {
    c.imu_samples.fetch_add(1, Relaxed);
    c.last_imu_ns.store(since(t0), Relaxed);
    match tx.try_send(Msg::Imu(s)) {
        Ok(()) => true,
        Err(TrySendError::Full(_)) => {
            c.imu_queue_drops.fetch_add(1, Relaxed);
            true
        }
        Err(TrySendError::Disconnected(_)) => false,
    }
}

/// The serial IMU thread. loglio's frames carry the LiDAR's clock and are used as they are; an
/// Xsens's or a VectorNav's own time goes onto this computer's clock through a [`DeviceClock`]
/// (without a device time, the arrival time is used).
fn read_imu(
    port: ImuPort,
    path: PathBuf,
    protocol: ImuProtocol,
    tx: SyncSender<Msg>,
    c: Arc<Counters>,
    stop: Arc<AtomicBool>,
    t0: Instant,
) {
    let src: Box<dyn Read + Send> = match port {
        ImuPort::Serial(p) => Box::new(p),
        ImuPort::Fifo(f) => Box::new(f),
    };
    let mut r = DeviceImuReader::new(src, protocol);
    let mut clock = DeviceClock::new();
    let mut estimated_at = 0u64;
    while !stop.load(Relaxed) {
        let next = r.next_sample();
        let st = r.counts();
        c.imu_seq_gaps.store(st.lost, Relaxed);
        c.imu_noise_bytes.store(st.dropped_bytes, Relaxed);
        c.imu_rejected.store(st.rejected, Relaxed);
        c.imu_unsupported.store(r.unsupported_messages(), Relaxed);
        match next {
            Ok(Some(d)) => {
                let t_ns = match (protocol.own_clock(), d.device_ns) {
                    (false, Some(t)) => t,
                    (true, Some(t)) => clock.map(t, d.arrival_ns),
                    (_, None) => d.arrival_ns,
                };
                if protocol.own_clock() && d.device_ns.is_some() && st.samples >= estimated_at + 100 {
                    estimated_at = st.samples;
                    *c.imu_clock.lock().unwrap_or_else(|e| e.into_inner()) = clock.estimate();
                }
                if !send_imu(&tx, ImuSample { t_ns, gyro: d.gyro, acc: d.acc }, &c, t0) {
                    break;
                }
            }
            Ok(None) => {
                if !stop.load(Relaxed) {
                    warn(format!("IMU stream {} ended; no more IMU samples", path.display()));
                }
                break;
            }
            Err(e) if matches!(e.kind(), io::ErrorKind::TimedOut | io::ErrorKind::WouldBlock) => {}
            Err(e) => {
                if !stop.load(Relaxed) {
                    warn(format!(
                        "IMU serial device {}: {}; no more IMU samples",
                        path.display(),
                        io_reason(&e)
                    ));
                }
                break;
            }
        }
    }
    if protocol.own_clock() {
        *c.imu_clock.lock().unwrap_or_else(|e| e.into_inner()) = clock.estimate();
    }
}

/// The MAVLink IMU thread: datagrams to samples, the autopilot's time onto this computer's
/// clock through a [`DeviceClock`] (its `time_usec` is since boot, or since 1970 with a GPS).
fn read_mavlink(
    sock: UdpSource,
    raw_scale: Option<RawScale>,
    tx: SyncSender<Msg>,
    c: Arc<Counters>,
    stop: Arc<AtomicBool>,
    t0: Instant,
) {
    let mut dec = MavlinkImuDecoder::new(raw_scale);
    let mut clock = DeviceClock::new();
    let mut buf = vec![0u8; 65_536];
    let mut samples = Vec::new();
    let (mut warned, mut warned_raw, mut estimated_at) = (false, false, 0u64);
    'recv: while !stop.load(Relaxed) {
        match sock.recv(&mut buf) {
            Ok(Some((n, _, arrival_ns))) => {
                dec.datagram(&buf[..n], |s| samples.push(s));
                let st = dec.stats;
                c.imu_noise_bytes.store(st.dropped_bytes, Relaxed);
                c.imu_rejected.store(st.crc + st.bad_values, Relaxed);
                c.imu_ignored.store(st.ignored, Relaxed);
                *c.imu_kind.lock().unwrap_or_else(|e| e.into_inner()) = dec.message().map(|m| m.name());
                if raw_scale.is_none() && st.ignored > 0 && dec.message().is_none() && !warned_raw {
                    warn(
                        "MAVLink RAW_IMU arrives but imu.raw_imu_acc_scale and imu.raw_imu_gyro_scale are not set: it is ignored (stream HIGHRES_IMU or SCALED_IMU, or set the scales)",
                    );
                    warned_raw = true;
                }
                for s in samples.drain(..) {
                    let t_ns = clock.map(s.device_ns, arrival_ns);
                    if !send_imu(&tx, ImuSample { t_ns, gyro: s.gyro, acc: s.acc }, &c, t0) {
                        break 'recv;
                    }
                }
                if st.samples >= estimated_at + 100 {
                    estimated_at = st.samples;
                    *c.imu_clock.lock().unwrap_or_else(|e| e.into_inner()) = clock.estimate();
                }
            }
            Ok(None) => {}
            Err(e) => {
                if !warned {
                    warn(format!("MAVLink IMU port: {}; still listening", io_reason(&e)));
                    warned = true;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }
    *c.imu_clock.lock().unwrap_or_else(|e| e.into_inner()) = clock.estimate();
}

/// What the decode thread needs besides its queues.
struct DecodeSetup {
    cfg: Config,
    dec: SensorDecoder,
    lidar_port: u16,
    imu_port: u16,
    /// Skip Velodyne data packets until a GPS time is seen (at most [`GPS_WAIT`]).
    hold_for_gps: bool,
}

/// The decode thread: datagrams to scans and Ouster IMU samples.
fn decode(s: DecodeSetup, rx: Receiver<Datagram>, tx: SyncSender<Msg>, c: Arc<Counters>, t0: Instant) {
    let (mut a, mut b) = lidar_stream::buffers(&s.dec);
    let mut stream = LidarStream::new(&s.cfg, s.dec, &mut a, &mut b, s.lidar_port, s.imu_port);
    let mut first_data: Option<u64> = None;
    let mut gps_given_up = false;
    while let Ok(d) = rx.recv() {
        if s.hold_for_gps && d.port == s.lidar_port && !gps_given_up {
            let has_gps =
                matches!(stream.decoder(), SensorDecoder::Velodyne { clock, .. } if clock.has_gps());
            if !has_gps {
                let first = *first_data.get_or_insert(d.at_ns);
                if d.at_ns.saturating_sub(first) < GPS_WAIT.as_nanos() as u64 {
                    c.gps_wait.fetch_add(1, Relaxed);
                    continue;
                }
                gps_given_up = true;
                warn(format!(
                    "no GPS time in the Velodyne position packets within {:.1} s: packet hours come from this computer's clock (set time.lidar_time_source = \"capture\" unless the IMU shares the LiDAR's clock)",
                    GPS_WAIT.as_secs_f64()
                ));
            }
        }
        let out = stream.packet(d.port, &d.data, d.capture_ns);
        let st = stream.stats;
        c.lidar_packets.store(st.lidar_packets, Relaxed);
        c.decoder_drops.store(
            st.bad_packets + st.rejected_packets + st.bad_imu_packets + st.foreign + st.stamp_jumps,
            Relaxed,
        );
        c.missing_packets.store(stream.assembly_stats().missing_packets, Relaxed);
        match out {
            Some(Decoded::Scan(scan)) => {
                if c.scans_queued.load(Relaxed) >= MAX_QUEUED_SCANS {
                    c.scan_drops.fetch_add(1, Relaxed);
                    continue;
                }
                c.scans_queued.fetch_add(1, Relaxed);
                match tx.try_send(Msg::Scan { scan, arrival_ns: d.at_ns }) {
                    Ok(()) => {}
                    Err(TrySendError::Full(_)) => {
                        c.scans_queued.fetch_sub(1, Relaxed);
                        c.scan_drops.fetch_add(1, Relaxed);
                    }
                    Err(TrySendError::Disconnected(_)) => break,
                }
            }
            // (Sent in the guard; `false`: the odometry is gone.)
            Some(Decoded::Imu(sample)) if !send_imu(&tx, sample, &c, t0) => break,
            Some(Decoded::Imu(_)) | None => {}
        }
    }
    // The turn being assembled is incomplete: it is not processed. What was dropped is said.
    for w in stream.warnings() {
        warn(w);
    }
}

/// Sets the stop flag when dropped (every way out of the run stops the threads).
pub(crate) struct StopOnDrop(pub(crate) Arc<AtomicBool>);

impl Drop for StopOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Relaxed);
    }
}

/// The status line: redrawn in place on a terminal, one line a second otherwise.
pub(crate) struct StatusLine {
    bar: Option<indicatif::ProgressBar>,
    enabled: bool,
}

impl StatusLine {
    pub(crate) fn new(enabled: bool) -> StatusLine {
        use std::io::IsTerminal;
        let bar = (enabled && io::stderr().is_terminal()).then(|| {
            let bar = indicatif::ProgressBar::with_draw_target(
                None,
                indicatif::ProgressDrawTarget::stderr_with_hz(2),
            );
            if let Ok(style) = indicatif::ProgressStyle::with_template("{msg}") {
                bar.set_style(style);
            }
            crate::diag::set_progress_bar(Some(bar.clone()));
            bar
        });
        StatusLine { bar, enabled }
    }

    pub(crate) fn show(&self, line: String) {
        match &self.bar {
            Some(bar) => bar.set_message(line),
            None if self.enabled => eprintln!("{line}"),
            None => {}
        }
    }
}

impl Drop for StatusLine {
    fn drop(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish();
            crate::diag::set_progress_bar(None);
        }
    }
}

/// Per-scan figures of the odometry thread.
#[derive(Debug, Default)]
pub(crate) struct ScanTimes {
    /// (latency, processing) of each scan since the last status line, ns.
    pub(crate) window: Vec<(u64, u64)>,
    pub(crate) latency_sum_ns: u64,
    pub(crate) latency_max_ns: u64,
    pub(crate) scans: u64,
    /// Last packet to result of every scan, beside its processing time (the summary's).
    pub(crate) result: crate::sink::WireLatency,
}

/// A stall warning that is given once per silence.
#[derive(Debug, Default)]
pub(crate) struct Stall {
    warned: bool,
}

impl Stall {
    /// `last`: the last arrival, ns since the start (0: none yet); warns when it is older than
    /// `timeout`.
    pub(crate) fn check(&mut self, now: u64, last: u64, timeout: u64, what: impl FnOnce(f64) -> String) {
        let since_last = now.saturating_sub(last);
        if since_last > timeout {
            if !self.warned {
                warn(what(since_last as f64 * 1e-9));
                self.warned = true;
            }
        } else if last != 0 {
            self.warned = false;
        }
    }
}

/// Runs live until a signal or `seconds`.
pub fn run(opt: &LiveOptions) -> Result<LiveReport, PipelineError> {
    let wall = Instant::now();
    let mut cfg = opt.setup.load_config()?;
    let imu = match &opt.imu {
        LiveImu::Config => match cfg.imu.source {
            ImuSource::Serial => LiveImu::Serial(PathBuf::from(&cfg.imu.serial_device)),
            ImuSource::Ouster => LiveImu::OusterPackets,
            ImuSource::Mavlink => LiveImu::Mavlink(cfg.network.mavlink_imu_port),
            ImuSource::Csv => {
                return Err(PipelineError(
                    "imu.source = \"csv\" is for replays; live needs the IMU on a serial port (--imu-serial PATH) or an Ouster's IMU packets (--ouster-imu)"
                        .into(),
                ));
            }
            ImuSource::None => LiveImu::None,
        },
        other => other.clone(),
    };
    let lidar_only = imu == LiveImu::None;
    if lidar_only {
        cfg.imu.source = ImuSource::None;
    }
    let family = cfg.preset.family();
    if imu == LiveImu::OusterPackets && family != SensorFamily::Ouster {
        return Err(PipelineError(format!(
            "--ouster-imu needs an Ouster preset (os1-*), not {}",
            cfg.preset
        )));
    }
    if let Some(b) = opt.baud {
        cfg.imu.baud = b;
    }
    if let Some(p) = opt.imu_protocol {
        cfg.imu.protocol = p;
    }
    let imu_protocol = cfg.imu.protocol;
    opt.watch.check()?;
    let bind: IpAddr = match opt.bind {
        Some(a) => a,
        None => cfg.network.bind.parse().map_err(|_| {
            PipelineError(format!("network.bind = \"{}\" is not an IP address", cfg.network.bind))
        })?,
    };
    let data = DataExtrinsic::of_ouster_metadata(&cfg)?;
    let extrinsic = opt.setup.resolve_extrinsic(&mut cfg, data)?;
    let PacketSetup { dec, lidar_port, imu_port, class, core } = PacketSetup::new(&cfg)?;
    let lidar_port = opt.lidar_port.unwrap_or(lidar_port);
    let imu_port = opt.imu_port.unwrap_or(imu_port);

    // Sockets and the serial device first: their errors come before the allocation.
    let lidar_addr = SocketAddr::new(bind, lidar_port);
    let lidar_sock = bind_udp(lidar_addr, "LiDAR packets")?;
    // Linux reports twice the usable size (its bookkeeping included).
    let usable = lidar_sock.recv_buffer_size() / if cfg!(target_os = "linux") { 2 } else { 1 };
    if usable < udp::DEFAULT_RCVBUF {
        warn(format!(
            "UDP receive buffer is {} KiB, less than the {} MiB asked for: a burst while this computer is busy may be lost (raise it: sysctl -w net.core.rmem_max={})",
            usable >> 10,
            udp::DEFAULT_RCVBUF >> 20,
            udp::DEFAULT_RCVBUF
        ));
    }
    let mut sockets = vec![(lidar_sock, lidar_port, true)];
    let mut hold_for_gps = false;
    match family {
        SensorFamily::Velodyne if opt.position_port != lidar_port => {
            // The position packets carry the GPS time; without them the host clock gives the hour.
            match bind_udp(SocketAddr::new(bind, opt.position_port), "Velodyne position packets") {
                Ok(s) => {
                    sockets.push((s, VELODYNE_POSITION_PORT, false));
                    hold_for_gps = cfg.time.lidar_time_source == LidarTimeSource::Packet;
                }
                Err(e) => warn(format!("{e}; packet hours come from this computer's clock")),
            }
        }
        SensorFamily::Ouster if imu == LiveImu::OusterPackets => {
            sockets.push((bind_udp(SocketAddr::new(bind, imu_port), "Ouster IMU packets")?, imu_port, false));
        }
        _ => {}
    }
    let serial = match &imu {
        LiveImu::Serial(p) => Some((open_imu(p, cfg.imu.baud)?, p.clone())),
        _ => None,
    };
    let mavlink = match imu {
        LiveImu::Mavlink(port) => {
            Some((bind_udp(SocketAddr::new(bind, port), "MAVLink IMU messages")?, port))
        }
        _ => None,
    };
    if !lidar_only {
        extrinsic.warn_if_missing();
    }
    let extrinsic_desc = extrinsic.line().map_or(String::new(), |l| format!("; {l}"));
    let raw_scale = match (cfg.imu.raw_imu_acc_scale, cfg.imu.raw_imu_gyro_scale) {
        (Some(acc), Some(gyro)) => Some(RawScale { acc: acc as f32, gyro: gyro as f32 }),
        _ => None,
    };
    let own_clock = if mavlink.is_some() {
        Some("MAVLink".to_string())
    } else {
        (serial.is_some() && imu_protocol.own_clock()).then(|| imu_protocol.to_string())
    };
    if let Some(what) = own_clock
        && cfg.time.lidar_time_source == LidarTimeSource::Packet
    {
        warn(format!(
            "the {what} IMU's time is put onto this computer's clock, the LiDAR's packet times are the sensor's own: set time.lidar_time_source = \"capture\" unless the LiDAR is synchronised to this computer (PTP)"
        ));
    }
    let imu_desc = match &serial {
        Some((ImuPort::Serial(_), p)) => {
            format!("{imu_protocol} IMU from {} at {} baud", p.display(), cfg.imu.baud)
        }
        Some((ImuPort::Fifo(_), p)) => format!("{imu_protocol} IMU from the FIFO {}", p.display()),
        None if lidar_only => crate::run::runner::LIDAR_ONLY_MODEL.to_string(),
        None => match &mavlink {
            Some((_, port)) => {
                format!("IMU from MAVLink (HIGHRES_IMU, SCALED_IMU or RAW_IMU) on UDP {bind}:{port}")
            }
            None => format!("IMU from the Ouster's packets on UDP {imu_port}"),
        },
    };
    let imu_source_name = match (&serial, &mavlink) {
        (Some((_, p)), _) => p.display().to_string(),
        (None, Some((_, port))) => format!("the MAVLink IMU messages (UDP {bind}:{port})"),
        (None, None) => format!("the Ouster IMU packets (UDP {bind}:{imu_port})"),
    };

    let outputs = files::Outputs::new(opt.setup.outputs()?)?;
    let stop_signal = Arc::new(AtomicBool::new(false));
    let _signals = if opt.handle_signals { Some(crate::run::Signals::register(&stop_signal)?) } else { None };
    let scan_period_s = 1.0 / cfg.sensor.scan_rate_hz;
    let preset = cfg.preset;
    let imu_label = match &imu {
        LiveImu::OusterPackets | LiveImu::None => None,
        LiveImu::Mavlink(_) => Some("MAVLink IMU".to_string()),
        _ => Some(format!("serial IMU ({imu_protocol})")),
    };
    let decode_setup = DecodeSetup { cfg: cfg.clone(), dec, lidar_port, imu_port, hold_for_gps };

    let res = engine::with_engine(
        &core,
        class,
        cfg.compute.resolved_threads(),
        move |engine| -> Result<_, PipelineError> {
            let t0 = Instant::now();
            let counters = Arc::new(Counters::default());
            let stop_rx = Arc::new(AtomicBool::new(false));
            let _stop_guard = StopOnDrop(Arc::clone(&stop_rx));
            let (dg_tx, dg_rx) = mpsc::sync_channel::<Datagram>(DATAGRAM_QUEUE);
            let (msg_tx, msg_rx) = mpsc::sync_channel::<Msg>(ODOMETRY_QUEUE);
            let spawn_err = |e: io::Error| PipelineError(format!("cannot start a thread: {e}"));
            let mut receivers: Vec<JoinHandle<()>> = Vec::new();
            for (sock, port, lidar) in sockets {
                let (tx, c, stop) = (dg_tx.clone(), Arc::clone(&counters), Arc::clone(&stop_rx));
                receivers.push(
                    std::thread::Builder::new()
                        .name(format!("loglio-udp-{port}"))
                        .spawn(move || receive(sock, port, lidar, tx, c, stop, t0))
                        .map_err(spawn_err)?,
                );
            }
            drop(dg_tx);
            let decoder = {
                let (tx, c) = (msg_tx.clone(), Arc::clone(&counters));
                std::thread::Builder::new()
                    .name("loglio-decode".into())
                    .spawn(move || decode(decode_setup, dg_rx, tx, c, t0))
                    .map_err(spawn_err)?
            };
            let imu_thread = match serial {
                Some((port, path)) => {
                    let (tx, c, stop) = (msg_tx.clone(), Arc::clone(&counters), Arc::clone(&stop_rx));
                    Some(
                        std::thread::Builder::new()
                            .name("loglio-imu".into())
                            .spawn(move || read_imu(port, path, imu_protocol, tx, c, stop, t0))
                            .map_err(spawn_err)?,
                    )
                }
                None => match mavlink {
                    Some((sock, _)) => {
                        let (tx, c, stop) = (msg_tx.clone(), Arc::clone(&counters), Arc::clone(&stop_rx));
                        Some(
                            std::thread::Builder::new()
                                .name("loglio-mavlink-imu".into())
                                .spawn(move || read_mavlink(sock, raw_scale, tx, c, stop, t0))
                                .map_err(spawn_err)?,
                        )
                    }
                    None => None,
                },
            };
            drop(msg_tx);
            eprintln!(
                "loglio live: listening for {preset} LiDAR packets on UDP {lidar_addr}, {imu_desc}{extrinsic_desc}; Ctrl-C to stop"
            );

            let times = Rc::new(RefCell::new(ScanTimes::default()));
            let mut runner = Runner::new(engine, outputs, cfg.time.lidar_imu_offset);
            runner.set_lidar_only(lidar_only);
            runner.sinks = opt.setup.sinks.build();
            runner.set_origin(t0);
            runner.sinks.set_origin(t0);
            {
                let times = Rc::clone(&times);
                runner.on_scan = Some(Box::new(move |res, _, arrival| {
                    let latency = since(t0).saturating_sub(arrival);
                    let mut t = times.borrow_mut();
                    t.window.push((latency, res.times.total_ns));
                    t.latency_sum_ns += latency;
                    t.latency_max_ns = t.latency_max_ns.max(latency);
                    t.result.record(latency, res.times.total_ns);
                    t.scans += 1;
                }));
            }
            let status = StatusLine::new(opt.watch.status);
            let limit_ns = opt.watch.seconds.map(|s| (s * 1e9) as u64);
            let lidar_timeout_ns = (opt.watch.lidar_timeout_s * 1e9) as u64;
            let imu_timeout_ns = (opt.watch.imu_timeout_s * 1e9) as u64;
            let wait_ns = IMU_WAIT.as_nanos() as u64;
            let (mut lidar_stall, mut imu_stall) = (Stall::default(), Stall::default());
            let mut stopped: Option<(StopReason, u64)> = None;
            let mut last_status = (0u64, 0u64); // (time, datagrams)
            let c = &*counters;
            loop {
                let timeout =
                    if stopped.is_some() { Duration::from_millis(50) } else { Duration::from_millis(100) };
                match msg_rx.recv_timeout(timeout) {
                    Ok(Msg::Imu(s)) => runner.imu(s)?,
                    Ok(Msg::Scan { scan, arrival_ns }) => {
                        c.scans_queued.fetch_sub(1, Relaxed);
                        runner.scan(scan, arrival_ns)?;
                    }
                    Err(RecvTimeoutError::Disconnected) => break,
                    Err(RecvTimeoutError::Timeout) => {
                        if let Some((_, at)) = stopped {
                            // A FIFO's reader may sit in a blocking read: do not wait for it long.
                            let imu_done = imu_thread.as_ref().is_none_or(|h| h.is_finished())
                                || since(t0).saturating_sub(at) > 1_000_000_000;
                            if decoder.is_finished() && imu_done {
                                break;
                            }
                        }
                    }
                }
                let now = since(t0);
                runner.process_ready(false, Some(now.saturating_sub(wait_ns)))?;
                if stopped.is_none() {
                    let reason = if stop_signal.load(Relaxed) {
                        Some(StopReason::Signal)
                    } else if limit_ns.is_some_and(|l| now >= l) {
                        Some(StopReason::Seconds)
                    } else {
                        None
                    };
                    if let Some(r) = reason {
                        stop_rx.store(true, Relaxed);
                        stopped = Some((r, now));
                        continue;
                    }
                    let last_lidar = c.last_lidar_ns.load(Relaxed);
                    if last_lidar == 0 && now > lidar_timeout_ns {
                        return Err(PipelineError(format!(
                            "no LiDAR packets on UDP {lidar_addr} within {} s: is the sensor on, and sending to this computer's address and port {lidar_port} (its destination IP, the firewall)?",
                            opt.watch.lidar_timeout_s
                        )));
                    }
                    if last_lidar != 0 && c.lidar_packets.load(Relaxed) == 0 && now > lidar_timeout_ns {
                        return Err(PipelineError(format!(
                            "{} datagrams arrived on UDP {lidar_addr} but none is a {preset} data packet: wrong --preset, --metadata or --lidar-port?",
                            c.lidar_datagrams.load(Relaxed)
                        )));
                    }
                    lidar_stall.check(now, last_lidar, lidar_timeout_ns, |s| {
                        format!("no LiDAR packets on UDP {lidar_addr} for {s:.0} s; still listening")
                    });
                    if last_lidar != 0 && !lidar_only {
                        let noise = c.imu_noise_bytes.load(Relaxed);
                        imu_stall.check(now, c.last_imu_ns.load(Relaxed), imu_timeout_ns, |s| {
                        let unsupported = c.imu_unsupported.load(Relaxed);
                        if c.imu_samples.load(Relaxed) == 0 && unsupported > 0 {
                            format!(
                                "{unsupported} VectorNav messages from {imu_source_name} in {s:.0} s select GPS, Attitude or INS outputs, which loglio cannot measure: configure a binary output of the Common (or Time and IMU) group only"
                            )
                        } else if c.imu_samples.load(Relaxed) == 0 && noise > 0 && matches!(imu, LiveImu::Mavlink(_)) {
                            format!(
                                "{noise} bytes from {imu_source_name} in {s:.0} s but no MAVLink IMU message decodes: does the sender speak MAVLink and stream HIGHRES_IMU, SCALED_IMU or RAW_IMU?"
                            )
                        } else if c.imu_samples.load(Relaxed) == 0 && noise > 0 {
                            format!(
                                "{noise} bytes from {imu_source_name} in {s:.0} s but no IMU {} decodes: wrong --baud, or {}?",
                                if imu_protocol.own_clock() { "message" } else { "frame" },
                                match imu_protocol {
                                    ImuProtocol::Loglio => "not loglio's IMU board (--imu-protocol)".to_string(),
                                    p => format!("not {p} binary output with acceleration and angular rate (--imu-protocol)"),
                                }
                            )
                        } else {
                            format!(
                                "no IMU data from {imu_source_name} for {s:.0} s; scans wait {:.1} s for it, then run without",
                                IMU_WAIT.as_secs_f64()
                            )
                        }
                    });
                    }
                }
                if now.saturating_sub(last_status.0) >= 1_000_000_000 {
                    let dt = (now - last_status.0) as f64 * 1e-9;
                    let datagrams = c.datagrams.load(Relaxed);
                    let line = {
                        let mut t = times.borrow_mut();
                        let n = t.window.len();
                        let mut line = status_line(
                            n as f64 / dt,
                            (datagrams - last_status.1) as f64 / dt,
                            &t.window,
                            scan_period_s,
                            &snapshot(c, &runner.stats, &t),
                        );
                        // "live: <status and pose>; <rates, latency, drops>": the status first.
                        let rest = line.strip_prefix("live: ").unwrap_or(&line).to_string();
                        line = format!("live: {}; {rest}", pose_phrase(runner.latest.as_ref()));
                        if lidar_only {
                            line = line.replacen("live: ", "live: LiDAR-only (no IMU), ", 1);
                        }
                        if !runner.sinks.is_empty() {
                            line.push_str(&format!("; outputs: {}", runner.sinks.status_phrase()));
                        }
                        t.window.clear();
                        line
                    };
                    status.show(line);
                    last_status = (now, datagrams);
                }
            }
            drop(status);
            for h in receivers {
                let _ = h.join();
            }
            let _ = decoder.join();
            let stopped_by = stopped.map_or(StopReason::Signal, |(r, _)| r);
            runner.process_ready(true, None)?;
            let counts = snapshot(c, &runner.stats, &times.borrow());
            if counts.lidar_packets == 0 {
                return Err(PipelineError(format!(
                    "no LiDAR packets arrived on UDP {lidar_addr} during the run ({} datagrams)",
                    counts.datagrams
                )));
            }
            if runner.stats.imu_in == 0 && !lidar_only {
                return Err(PipelineError(format!(
                    "no IMU data arrived from {imu_source_name} during the run ({} LiDAR packets, {} scans): check the device{}",
                    counts.lidar_packets,
                    runner.stats.scans,
                    if imu == LiveImu::OusterPackets {
                        "'s IMU port".to_string()
                    } else if matches!(imu, LiveImu::Mavlink(_)) {
                        format!(
                            ": the autopilot must stream HIGHRES_IMU, SCALED_IMU or RAW_IMU to this port{}",
                            if c.imu_ignored.load(Relaxed) > 0 {
                                " (RAW_IMU arrived: it needs imu.raw_imu_acc_scale and imu.raw_imu_gyro_scale)"
                            } else {
                                ""
                            }
                        )
                    } else if imu_protocol == ImuProtocol::Loglio {
                        ", its --baud and the IMU board".to_string()
                    } else {
                        format!(
                            ", its --baud and that it sends {imu_protocol} binary output with acceleration and angular rate"
                        )
                    }
                )));
            }
            if runner.stats.scans == 0 {
                return Err(PipelineError(format!(
                    "no complete LiDAR scan in {:.1} s ({} packets decoded)",
                    since(t0) as f64 * 1e-9,
                    counts.lidar_packets
                )));
            }
            let (stats, finished) = runner.finish()?;
            let result_latency = std::mem::take(&mut times.borrow_mut().result);
            let clock = *c.imu_clock.lock().unwrap_or_else(|e| e.into_inner());
            let imu_label = imu_label.map(|l| match *c.imu_kind.lock().unwrap_or_else(|e| e.into_inner()) {
                Some(kind) => format!("{l} ({kind})"),
                None => l,
            });
            Ok((stats, finished, counts, stopped_by, result_latency, clock, imu_label))
        },
    )??;
    let (stats, finished, counts, stopped_by, result_latency, imu_clock, imu_input) = res;
    Ok(LiveReport {
        stats,
        finished,
        counts,
        stopped_by,
        scan_period_s,
        wall_s: wall.elapsed().as_secs_f64(),
        result_latency,
        imu_input,
        imu_clock,
    })
}

fn snapshot(c: &Counters, stats: &RunStats, t: &ScanTimes) -> LiveCounts {
    LiveCounts {
        datagrams: c.datagrams.load(Relaxed),
        socket_drops: c.socket_drops.load(Relaxed),
        lidar_packets: c.lidar_packets.load(Relaxed),
        decoder_drops: c.decoder_drops.load(Relaxed),
        missing_packets: c.missing_packets.load(Relaxed),
        gps_wait_packets: c.gps_wait.load(Relaxed),
        imu_samples: c.imu_samples.load(Relaxed),
        imu_drops: c.imu_seq_gaps.load(Relaxed) + c.imu_queue_drops.load(Relaxed) + stats.imu_dropped,
        imu_noise_bytes: c.imu_noise_bytes.load(Relaxed),
        imu_rejected: c.imu_rejected.load(Relaxed),
        scan_drops: c.scan_drops.load(Relaxed),
        latency_mean_s: if t.scans > 0 { t.latency_sum_ns as f64 * 1e-9 / t.scans as f64 } else { 0.0 },
        latency_max_s: t.latency_max_ns as f64 * 1e-9,
    }
}

fn drops(c: &LiveCounts) -> String {
    format!(
        "drops: socket queue {}, decoder {}, IMU {}, scans {}",
        c.socket_drops, c.decoder_drops, c.imu_drops, c.scan_drops
    )
}

/// The status line: rates over the last interval, latency and margin of its scans, drops so far.
fn status_line(
    scan_hz: f64,
    pkt_hz: f64,
    window: &[(u64, u64)],
    scan_period_s: f64,
    c: &LiveCounts,
) -> String {
    let timing = timing_phrase(window, scan_period_s);
    format!("live: {scan_hz:.1} scans/s, {pkt_hz:.0} packets/s, {timing}, {}", drops(c))
}

/// `latency 50 ms, margin 4.0x` of the scans of a status interval: (latency, processing) ns.
pub(crate) fn timing_phrase(window: &[(u64, u64)], scan_period_s: f64) -> String {
    let n = window.len().max(1) as f64;
    let (lat, proc_) = window.iter().fold((0u64, 0u64), |(a, b), (l, p)| (a + l, b + p));
    let (lat_ms, proc_s) = (lat as f64 * 1e-6 / n, proc_ as f64 * 1e-9 / n);
    if window.is_empty() {
        "latency -, margin -".to_string()
    } else {
        format!("latency {lat_ms:.0} ms, margin {:.1}x", scan_period_s / proc_s.max(1e-9))
    }
}

/// The latest pose and the status for the status line: `ok, at (12.3, -4.0, 0.5) m, yaw 35 deg`.
pub(crate) fn pose_phrase(p: Option<&crate::sink::PoseSample>) -> String {
    let Some(p) = p else { return "no scan yet".into() };
    if !p.status.is_tracking() {
        return p.status.to_string();
    }
    let [w, x, y, z] = p.q_wxyz;
    let yaw = (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z)).to_degrees();
    let [px, py, pz] = p.position;
    format!("{}, at ({px:.1}, {py:.1}, {pz:.1}) m, yaw {yaw:.0} deg", p.status)
}

/// The summary of a live run (stdout).
pub fn summary(r: &LiveReport) -> String {
    let c = &r.counts;
    let mut s = format!(
        "live: stopped by {}; {} datagrams, {} LiDAR packets decoded, {} IMU samples; {}",
        match r.stopped_by {
            StopReason::Signal => "a signal",
            StopReason::Seconds => "--seconds",
        },
        c.datagrams,
        c.lidar_packets,
        c.imu_samples,
        drops(c)
    );
    if c.missing_packets > 0 {
        s.push_str(&format!("; {} packets missing from the sequence", c.missing_packets));
    }
    if c.gps_wait_packets > 0 {
        s.push_str(&format!("; {} packets before the first GPS time skipped", c.gps_wait_packets));
    }
    s.push('\n');
    if let Some(p) = &r.imu_input {
        s.push_str(&format!(
            "{p}: {} bytes not IMU data, {} messages refused",
            c.imu_noise_bytes, c.imu_rejected
        ));
        if let Some(e) = &r.imu_clock {
            s.push_str(&format!("; device clock: {e}"));
        }
        s.push('\n');
    }
    s.push_str(&format!(
        "latency (last packet of a scan to its result): mean {:.0} ms, max {:.0} ms\n",
        c.latency_mean_s * 1e3,
        c.latency_max_s * 1e3
    ));
    // The figures beside the processing time of the same scans: what a sink adds on top.
    let from = "latency from the last packet of a scan";
    if let Some(p) = r.result_latency.phrase() {
        s.push_str(&format!("{from} to its result: {p}\n"));
    }
    for st in &r.stats.sinks {
        if let Some(p) = st.wire.phrase() {
            s.push_str(&format!("{from} to its pose sent by {}: {p}\n", st.name));
        }
    }
    s.push_str(&crate::run::runner::summary(&r.stats, &r.finished, r.scan_period_s, r.wall_s));
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_line_reads_well() {
        let c = LiveCounts { socket_drops: 2, scan_drops: 1, ..Default::default() };
        let l = status_line(10.0, 1508.4, &[(40_000_000, 20_000_000), (60_000_000, 30_000_000)], 0.1, &c);
        assert_eq!(
            l,
            "live: 10.0 scans/s, 1508 packets/s, latency 50 ms, margin 4.0x, drops: socket queue 2, decoder 0, IMU 0, scans 1"
        );
        assert!(status_line(0.0, 0.0, &[], 0.1, &c).contains("latency -, margin -"));
    }

    #[test]
    fn pose_phrase_names_status_position_and_yaw() {
        use crate::sink::{LiveStatus, PoseSample};
        assert_eq!(pose_phrase(None), "no scan yet");
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let mut p = PoseSample::placeholder(0, LiveStatus::Degraded { axes: 1 }, 0);
        p.position = [12.34, -4.0, 0.46];
        p.q_wxyz = [h, 0.0, 0.0, h];
        assert_eq!(pose_phrase(Some(&p)), "degraded (x), at (12.3, -4.0, 0.5) m, yaw 90 deg");
        p.status = LiveStatus::Lost;
        assert_eq!(pose_phrase(Some(&p)), "lost");
    }

    #[test]
    fn stall_warns_once_per_silence() {
        let ((), w) = crate::diag::capture(|| {
            let mut s = Stall::default();
            let msg = |x: f64| format!("silent {x:.0} s");
            s.check(500, 0, 1000, msg); // not yet
            s.check(2000, 0, 1000, msg); // warns
            s.check(3000, 0, 1000, msg); // already warned
            s.check(3500, 3400, 1000, msg); // data again: re-armed
            s.check(5000, 3400, 1000, msg); // warns again
        });
        assert_eq!(w.len(), 2, "{w:?}");
    }
}
