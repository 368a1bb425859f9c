//! `loglio replay`: a pcap (Velodyne or Ouster) plus the IMU from a CSV file, a serial capture
//! (loglio's COBS frames) or the Ouster IMU packets in the same pcap, as fast as possible or in
//! real time, with a progress bar; writes every output.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use loglio_core::imu::ImuSample;
use loglio_core::odometry::OdometryConfig;

use crate::config::{AssociationMode, Config, ImuSource, Preset, SensorFamily};
use crate::diag::warn;
use crate::eval::{self, Format};
use crate::input::lidar_stream::{self, Decoded, LidarStream, SensorDecoder};
use crate::input::serial::ImuFrameReader;
use crate::output::Progress;
use crate::pipeline::{
    self, Finished, OutputOptions, Outputs, PipelineError, RunStats, Runner, StorageClass,
};

/// What the run commands share: the configuration, the outputs and the evaluation.
#[derive(Clone, Debug, Default)]
pub struct RunSetup {
    /// Configuration file.
    pub config: Option<PathBuf>,
    /// Preset (when no file).
    pub preset: Option<String>,
    /// Association mode override.
    pub mode: Option<AssociationMode>,
    /// Ouster metadata (overrides the configuration's).
    pub metadata: Option<PathBuf>,
    /// Velodyne calibration (overrides the configuration's).
    pub calibration: Option<PathBuf>,
    /// Output directory.
    pub out: Option<PathBuf>,
    /// Ground truth (TUM).
    pub gt: Option<PathBuf>,
    /// Skip the map and the plots.
    pub no_map: bool,
    /// The live outputs.
    pub sinks: crate::sink::SinkArgs,
}

impl RunSetup {
    /// The configuration: the file, else the preset (default vlp16), with the overrides.
    pub fn load_config(&self) -> Result<Config, PipelineError> {
        let mut cfg = match (&self.config, &self.preset) {
            (Some(p), _) => Config::load(p)?,
            (None, Some(name)) => Config::preset(
                name.parse::<Preset>()
                    .map_err(|e| PipelineError(e.0.trim_start_matches("config: ").to_string()))?,
            ),
            (None, None) => Config::preset(Preset::Vlp16),
        };
        if let Some(m) = self.mode {
            cfg.mapping.association = m;
        }
        if let Some(m) = &self.metadata {
            cfg.sensor.ouster_metadata = Some(m.clone());
        }
        if let Some(c) = &self.calibration {
            cfg.sensor.calibration = Some(c.clone());
        }
        cfg.validate()?;
        Ok(cfg)
    }

    /// Output options (the ground truth read here).
    pub fn outputs(&self) -> Result<OutputOptions, PipelineError> {
        let gt = match &self.gt {
            Some(p) => {
                Some(eval::read_trajectory(p, Format::Tum, None).map_err(|e| PipelineError(e.to_string()))?)
            }
            None => None,
        };
        let write = self.out.is_some();
        Ok(OutputOptions {
            dir: self.out.clone(),
            gt,
            map: write && !self.no_map,
            plots: write && !self.no_map,
        })
    }
}

/// What a run over raw sensor packets (a pcap, live UDP) needs besides the configuration: the
/// decoder, the ports and the odometry's configuration and storage class.
#[derive(Debug)]
pub struct PacketSetup {
    /// The sensor's decoder (with the Ouster metadata or Velodyne calibration of the
    /// configuration).
    pub dec: SensorDecoder,
    /// The LiDAR data port: the Ouster metadata's, else `network.lidar_port`.
    pub lidar_port: u16,
    /// The Ouster IMU port: the Ouster metadata's, else `network.imu_port`.
    pub imu_port: u16,
    /// The storage class for the decoder's range image and `mapping.map_capacity`.
    pub class: StorageClass,
    /// The core odometry's configuration.
    pub core: OdometryConfig,
}

impl PacketSetup {
    /// The decoder, ports and odometry configuration of `cfg`.
    pub fn new(cfg: &Config) -> Result<PacketSetup, PipelineError> {
        let meta = match &cfg.sensor.ouster_metadata {
            Some(p) => Some(crate::input::ouster_meta::load(p).map_err(|e| PipelineError(e.to_string()))?),
            None => None,
        };
        let dec = SensorDecoder::new(cfg, meta.as_ref().map(|m| &m.intrinsics))?;
        let (lidar_port, imu_port) = match &meta {
            Some(m) => (m.udp_port_lidar, m.udp_port_imu),
            None => (cfg.network.lidar_port, cfg.network.imu_port),
        };
        let layout = dec.layout();
        let class = StorageClass::choose(layout.rows(), layout.cols(), cfg.mapping.map_capacity)?;
        let core = pipeline::odometry_config(cfg, layout)?;
        Ok(PacketSetup { dec, lidar_port, imu_port, class, core })
    }
}

/// Where the replay's IMU comes from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ImuInput {
    /// A CSV file `t,gx,gy,gz,ax,ay,az`.
    Csv(PathBuf),
    /// A capture of loglio's serial IMU frames.
    Serial(PathBuf),
    /// The Ouster IMU packets in the pcap.
    OusterPackets,
}

impl ImuInput {
    /// The IMU input of a file: CSV if it starts like the CSV header, serial frames otherwise.
    pub fn detect(path: &Path) -> Result<ImuInput, PipelineError> {
        let mut head = [0u8; 64];
        let n = {
            use std::io::Read;
            let mut f = File::open(path).map_err(|e| PipelineError(format!("{}: {e}", path.display())))?;
            f.read(&mut head).map_err(|e| PipelineError(format!("{}: {e}", path.display())))?
        };
        let text = String::from_utf8_lossy(&head[..n]);
        let csvish = text.trim_start().starts_with("t,") || text.trim_start().starts_with('#');
        Ok(if csvish || path.extension().is_some_and(|e| e == "csv") {
            ImuInput::Csv(path.to_path_buf())
        } else {
            ImuInput::Serial(path.to_path_buf())
        })
    }
}

/// A replay's settings.
#[derive(Clone, Debug)]
pub struct ReplayOptions {
    /// The pcap.
    pub pcap: PathBuf,
    /// The IMU (`None`: the configuration's `imu.source`: Ouster packets or `imu.csv_path`).
    pub imu: Option<ImuInput>,
    /// Pace by the capture times (`rate` x real time).
    pub realtime: Option<f64>,
    /// The shared run settings.
    pub setup: RunSetup,
    /// Show the progress bar.
    pub progress: bool,
}

/// A finished replay.
#[derive(Debug)]
pub struct ReplayReport {
    /// Counts and times.
    pub stats: RunStats,
    /// What was written and the evaluation.
    pub finished: Finished,
    /// Packet counts.
    pub stream: lidar_stream::StreamStats,
    /// Whether the Ouster's IMU packets were the IMU (else they were counted and left out).
    pub imu_packets_used: bool,
    /// The scan period, s.
    pub scan_period_s: f64,
    /// Wall time, s.
    pub wall_s: f64,
}

enum ImuFeed {
    Samples(std::vec::IntoIter<ImuSample>),
    Serial(Box<ImuFrameReader<BufReader<File>>>),
    None,
}

impl ImuFeed {
    fn next(&mut self) -> Result<Option<ImuSample>, PipelineError> {
        match self {
            ImuFeed::Samples(it) => Ok(it.next()),
            ImuFeed::Serial(r) => r
                .next_frame()
                .map(|f| f.map(|f| f.sample()))
                .map_err(|e| PipelineError(format!("IMU capture: {e}"))),
            ImuFeed::None => Ok(None),
        }
    }
}

/// Runs a replay.
pub fn run(opt: &ReplayOptions) -> Result<ReplayReport, PipelineError> {
    let wall = Instant::now();
    let cfg = opt.setup.load_config()?;
    let imu = match (&opt.imu, cfg.imu.source) {
        (Some(i), _) => i.clone(),
        (None, ImuSource::Ouster) => ImuInput::OusterPackets,
        (None, ImuSource::Csv) => ImuInput::Csv(cfg.imu.csv_path.clone().unwrap_or_default()),
        (None, ImuSource::Serial) => {
            return Err(PipelineError(
                "no IMU for the replay: pass --imu FILE (an IMU CSV or a serial capture), or use an Ouster's IMU packets (--ouster-imu)"
                    .into(),
            ));
        }
    };
    let imu_packets_used = imu == ImuInput::OusterPackets;
    if imu_packets_used && cfg.preset.family() != SensorFamily::Ouster {
        return Err(PipelineError(format!(
            "--ouster-imu needs an Ouster preset (os1-*), not {}",
            cfg.preset
        )));
    }
    let PacketSetup { dec, lidar_port, imu_port, class, core } = PacketSetup::new(&cfg)?;
    let mut feed = match &imu {
        ImuInput::Csv(p) => ImuFeed::Samples(
            crate::input::imu_csv::load(p).map_err(|e| PipelineError(e.to_string()))?.into_iter(),
        ),
        ImuInput::Serial(p) => {
            let f = File::open(p).map_err(|e| PipelineError(format!("{}: {e}", p.display())))?;
            ImuFeed::Serial(Box::new(ImuFrameReader::new(BufReader::new(f))))
        }
        ImuInput::OusterPackets => ImuFeed::None,
    };
    let mut reader = crate::input::pcap::PcapReader::open(&opt.pcap)
        .map_err(|e| PipelineError(format!("{}: {e}", opt.pcap.display())))?;
    let total = std::fs::metadata(&opt.pcap).map(|m| m.len()).unwrap_or(0);
    let progress = if opt.progress { Progress::new(total, "", true) } else { Progress::hidden() };
    let outputs = Outputs::new(opt.setup.outputs()?)?;
    let (a_len, _) = (dec.max_points(), ());
    let mut a = vec![loglio_core::scan::ScanPoint::default(); a_len];
    let mut b = vec![loglio_core::scan::ScanPoint::default(); a_len];
    let mut stream = LidarStream::new(&cfg, dec, &mut a, &mut b, lidar_port, imu_port);
    let offset_ns = (cfg.time.lidar_imu_offset * 1e9) as i64;
    let res = pipeline::with_engine(&core, class, |engine| -> Result<_, PipelineError> {
        let mut runner = Runner::new(engine, outputs, cfg.time.lidar_imu_offset);
        runner.sinks = opt.setup.sinks.build();
        let mut next_imu = feed.next()?;
        let mut bytes = 0u64;
        let mut pacer = opt.realtime.map(Pacer::new);
        let mut read_error = None;
        let (stop, _signals) = crate::run::Signals::stop_flag();
        loop {
            if stop.load(std::sync::atomic::Ordering::Relaxed) {
                warn("stopped by a signal; writing what was estimated");
                break;
            }
            let udp = match reader.next_udp() {
                Ok(Some(u)) => u,
                Ok(None) => break,
                Err(e) => {
                    read_error = Some(e.to_string());
                    break;
                }
            };
            bytes += udp.payload.len() as u64 + 58;
            progress.set_position(bytes.min(total));
            if let Some(wait) = pacer.as_mut().and_then(|p| p.wait(udp.ts_ns, Instant::now())) {
                std::thread::sleep(wait);
            }
            let (port, payload, ts) = (udp.dst_port, udp.payload, udp.ts_ns);
            match stream.packet(port, payload, ts) {
                // The sensor's own IMU only when it is the one chosen: with an IMU file, a second
                // IMU (another frame, another clock) must not be mixed into the file's samples.
                Some(Decoded::Imu(s)) if imu_packets_used => runner.imu(s)?,
                Some(Decoded::Imu(_)) => {}
                Some(Decoded::Scan(scan)) => {
                    // The file IMU up to a little past this scan's end first.
                    let until = scan.end_ns().saturating_add(200_000_000);
                    while let Some(s) = next_imu {
                        if s.t_ns.saturating_add_signed(offset_ns) > until {
                            break;
                        }
                        runner.imu(s)?;
                        next_imu = feed.next()?;
                    }
                    runner.scan(scan, 0)?;
                }
                None => {}
            }
        }
        if let Some(Decoded::Scan(scan)) = stream.flush() {
            runner.scan(scan, 0)?;
        }
        while let Some(s) = next_imu {
            runner.imu(s)?;
            next_imu = feed.next()?;
        }
        if let Some(e) = read_error {
            if runner.stats.scans == 0 && runner.pending() == 0 {
                return Err(PipelineError(format!("{}: {e}", opt.pcap.display())));
            }
            warn(format!("{}: {e}; replayed the packets before it", opt.pcap.display()));
        }
        let fin = runner.finish()?;
        Ok(fin)
    })??;
    progress.finish();
    let ps = reader.stats;
    if ps.corrupt_records > 0 || ps.truncated_at_eof {
        warn(format!(
            "{}: {} corrupt records skipped{}",
            opt.pcap.display(),
            ps.corrupt_records,
            if ps.truncated_at_eof { ", truncated at the end" } else { "" }
        ));
    }
    if stream.stats.bad_packets > 0 {
        warn(format!("{} LiDAR packets could not be decoded and were dropped", stream.stats.bad_packets));
    }
    let (stats, finished) = res;
    Ok(ReplayReport {
        stats,
        finished,
        stream: stream.stats,
        imu_packets_used,
        scan_period_s: 1.0 / cfg.sensor.scan_rate_hz,
        wall_s: wall.elapsed().as_secs_f64(),
    })
}

/// The summary of a run: scans, timing, margin, ATE and files.
pub fn summary(stats: &RunStats, fin: &Finished, scan_period_s: f64, wall_s: f64) -> String {
    let mean = stats.mean_scan_s();
    let mut s =
        format!("{} scans ({}), {} IMU samples", stats.scans, pipeline::status_summary(stats), stats.imu_in);
    if stats.imu_dropped + stats.imu_stale > 0 {
        s.push_str(&format!(" ({} dropped, {} older than their scan)", stats.imu_dropped, stats.imu_stale));
    }
    if stats.scans_without_imu > 0 {
        s.push_str(&format!("; {} scans without IMU up to their end", stats.scans_without_imu));
    }
    s.push('\n');
    s.push_str(&format!(
        "odometry: {:.1} ms per scan (mean), {:.1} ms (median); real-time margin {:.1}x (scan period {:.0} ms / mean)\n",
        mean * 1e3,
        stats.median_scan_s() * 1e3,
        if mean > 0.0 { scan_period_s / mean } else { f64::INFINITY },
        scan_period_s * 1e3
    ));
    if let Some(e) = &fin.eval {
        s.push_str(&format!(
            "ATE against ground truth (SE(3)-aligned, {} poses): rmse {:.3} m, max {:.3} m; rotation rmse {:.2} deg\n",
            e.matched, e.ape_trans.rmse, e.ape_trans.max, e.ape_rot_deg.rmse
        ));
    }
    s.push_str(&format!("wall time {wall_s:.1} s\n"));
    for line in crate::sink::sinks_summary(&stats.sinks) {
        s.push_str(&format!("live output {line}\n"));
    }
    if !fin.files.is_empty() {
        s.push_str("wrote:");
        for f in &fin.files {
            s.push_str(&format!(" {}", f.display()));
        }
        s.push('\n');
    }
    s
}

/// Paces a replay at `rate` times real time by the packets' capture times.
///
/// A capture time that steps back, or more than [`Pacer::MAX_STEP_NS`] past the previous one
/// (a pause in the capture, or a damaged record), starts the pacing afresh from that packet
/// instead of waiting out the step: one record stamped days ahead stalled the replay for days.
#[derive(Debug)]
pub struct Pacer {
    rate: f64,
    /// Capture time and wall time of the packet the pacing counts from.
    anchor: Option<(u64, Instant)>,
    prev_ns: u64,
}

impl Pacer {
    const MAX_STEP_NS: u64 = 1_000_000_000;

    /// Pacing at `rate` times real time.
    pub fn new(rate: f64) -> Self {
        Pacer { rate, anchor: None, prev_ns: 0 }
    }

    /// Sleeps until data stamped `ts_ns` is due. Stamps a little behind the latest (the
    /// interleaved IMU samples and scans of one source) count as the latest, not as a step back.
    pub fn wait_for(&mut self, ts_ns: u64) {
        let ts = if ts_ns < self.prev_ns && self.prev_ns - ts_ns < Self::MAX_STEP_NS {
            self.prev_ns
        } else {
            ts_ns
        };
        if let Some(d) = self.wait(ts, Instant::now()) {
            std::thread::sleep(d);
        }
    }

    /// How long to sleep (from `now`) before the packet captured at `ts_ns` is due.
    fn wait(&mut self, ts_ns: u64, now: Instant) -> Option<Duration> {
        let step_ok = ts_ns >= self.prev_ns && ts_ns - self.prev_ns <= Self::MAX_STEP_NS;
        self.prev_ns = ts_ns;
        let (t0, w0) = match self.anchor {
            Some(a) if step_ok => a,
            _ => {
                self.anchor = Some((ts_ns, now));
                return None;
            }
        };
        // A tiny rate asks for a very long wait, not a panic on overflow.
        let due =
            Duration::try_from_secs_f64((ts_ns - t0) as f64 * 1e-9 / self.rate).unwrap_or(Duration::MAX);
        due.checked_sub(now.saturating_duration_since(w0)).filter(|d| !d.is_zero())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Wall times are given, not read: the pacing's arithmetic, not the machine's clock.
    #[test]
    fn pacing_follows_capture_times_and_restarts_at_steps() {
        let w = Instant::now();
        let ms = Duration::from_millis;
        let mut p = Pacer::new(2.0);
        let t0 = 1_700_000_000_000_000_000u64;
        assert_eq!(p.wait(t0, w), None);
        // 100 ms of capture at twice real time: due 50 ms after the first packet.
        assert_eq!(p.wait(t0 + 100_000_000, w + ms(10)), Some(ms(40)));
        // Late already: no wait.
        assert_eq!(p.wait(t0 + 200_000_000, w + ms(120)), None);
        // A record stamped ten days ahead: no ten-day sleep, the pacing restarts from it...
        let far = t0 + 864_000_000_000_000;
        assert_eq!(p.wait(far, w + ms(130)), None);
        // ...and again from the next good packet, which steps back.
        assert_eq!(p.wait(t0 + 300_000_000, w + ms(131)), None);
        assert_eq!(p.wait(t0 + 400_000_000, w + ms(141)), Some(ms(40)));
        // A pause of 5 s in the capture is not replayed either.
        assert_eq!(p.wait(t0 + 5_400_000_000, w + ms(200)), None);
        assert_eq!(p.wait(t0 + 5_420_000_000, w + ms(200)), Some(ms(10)));
        // The smallest rate the command accepts: a very long wait, no overflow.
        let mut slow = Pacer::new(f64::MIN_POSITIVE);
        assert_eq!(slow.wait(t0, w), None);
        assert_eq!(slow.wait(t0 + 1, w), Some(Duration::MAX));
    }
}
