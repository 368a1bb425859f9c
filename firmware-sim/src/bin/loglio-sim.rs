//! `loglio-sim`: the simulated device side of loglio.
//!
//! ```text
//! loglio-sim file --scenario vehicle --sensor vlp32c --seed 1 --out out/vehicle
//! loglio-sim live --scenario corridor --sensor os1-64 --rate 1
//! loglio-sim bench --sensor vlp32c --seconds 30
//! loglio-sim replay --scenario handheld --sensor os1-16 --duration 3.5 --out replay.bin
//! ```

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::{Args, Parser, Subcommand};
use loglio_firmware_sim::imu_chip::Odr;
use loglio_firmware_sim::lidar::ouster::{LidarMode, Profile};
use loglio_firmware_sim::lidar::{ReturnMode, SensorModel};
use loglio_firmware_sim::raycast::Ray;
use loglio_firmware_sim::rng::SplitMix64;
use loglio_firmware_sim::scenario::{Event, LidarConfig, Scenario, ScenarioConfig, ScenarioKind};
use loglio_firmware_sim::{files, live_sensors};

/// Simulated LiDAR + IMU with exact ground truth, emitting the sensors' real wire formats.
#[derive(Debug, Parser)]
#[command(name = "loglio-sim", version, about)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Write a scenario to files: lidar.pcap, imu.bin, imu.csv, groundtruth.tum, scenario.json.
    File {
        #[command(flatten)]
        sc: ScenarioArgs,
        /// Output directory.
        #[arg(long, default_value = "out/sim")]
        out: PathBuf,
    },
    /// Stream a scenario live: LiDAR to UDP on loopback, IMU frames to a pseudo-terminal.
    Live {
        #[command(flatten)]
        sc: ScenarioArgs,
        /// Speed-up over real time (0 = as fast as possible).
        #[arg(long, default_value_t = 1.0)]
        rate: f64,
        /// Also create this symlink to the pseudo-terminal.
        #[arg(long)]
        pty_link: Option<PathBuf>,
        /// Added to every UDP destination port.
        #[arg(long, default_value_t = 0)]
        port_offset: u16,
    },
    /// Write a scenario as a replay recording for the Cortex-M firmware `loglio-fw` (IMU
    /// samples and scans in time order; format: `loglio_firmware_sim::firmware_recording`).
    Replay {
        #[command(flatten)]
        sc: ScenarioArgs,
        /// Output file.
        #[arg(long, default_value = "out/replay.bin")]
        out: PathBuf,
    },
    /// Measure ray-casting throughput and sequence generation time.
    Bench {
        #[command(flatten)]
        sc: ScenarioArgs,
        /// Seconds of data to generate.
        #[arg(long, default_value_t = 30.0)]
        seconds: f64,
    },
}

#[derive(Clone, Debug, Args)]
struct ScenarioArgs {
    /// vehicle, handheld, corridor, drone, rotation or traffic.
    #[arg(long, default_value = "vehicle")]
    scenario: String,
    /// Leave the scenario's moving actors out (traffic: the same drive in an empty street).
    #[arg(long)]
    no_actors: bool,
    /// vlp16, vlp32c, hdl32e, os1-16, os1-64 or os1-128.
    #[arg(long, default_value = "vlp32c")]
    sensor: String,
    /// Seed of the world and of every noise.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Seconds to simulate (default: the scenario's, 30-40 s).
    #[arg(long)]
    duration: Option<f64>,
    /// Velodyne rotation rate, rpm.
    #[arg(long)]
    rpm: Option<f64>,
    /// Velodyne return mode: strongest, last or dual.
    #[arg(long)]
    return_mode: Option<String>,
    /// Ouster lidar mode (512x10, 1024x10, 2048x10, 512x20, 1024x20).
    #[arg(long)]
    lidar_mode: Option<String>,
    /// Ouster UDP profile: legacy or rng19.
    #[arg(long)]
    profile: Option<String>,
    /// IMU rate, Hz (100, 200, 500 or 1000).
    #[arg(long)]
    imu_rate: Option<u32>,
    /// Generate without IMU noise and bias (quantisation remains).
    #[arg(long)]
    no_imu_noise: bool,
    /// Worker threads for scan generation (0: all cores).
    #[arg(long, default_value_t = 0)]
    threads: usize,
}

impl ScenarioArgs {
    fn build(&self) -> anyhow::Result<Scenario> {
        let kind = ScenarioKind::from_name(&self.scenario)
            .with_context(|| format!("unknown scenario {:?}", self.scenario))?;
        let sensor = SensorModel::from_name(&self.sensor)
            .with_context(|| format!("unknown sensor {:?}", self.sensor))?;
        let mut cfg = ScenarioConfig::new(kind, sensor, self.seed);
        if let Some(d) = self.duration {
            cfg.duration_s = d;
        }
        cfg.actors = !self.no_actors;
        match &mut cfg.lidar {
            LidarConfig::Velodyne(v) => {
                if let Some(r) = self.rpm {
                    v.rpm = r;
                }
                if let Some(m) = &self.return_mode {
                    v.return_mode = match m.as_str() {
                        "strongest" => ReturnMode::Strongest,
                        "last" => ReturnMode::Last,
                        "dual" => ReturnMode::Dual,
                        _ => bail!("unknown return mode {m:?}"),
                    };
                }
            }
            LidarConfig::Ouster(o) => {
                if let Some(m) = &self.lidar_mode {
                    o.mode = [
                        LidarMode::M512x10,
                        LidarMode::M512x20,
                        LidarMode::M1024x10,
                        LidarMode::M1024x20,
                        LidarMode::M2048x10,
                    ]
                    .into_iter()
                    .find(|x| x.name() == m)
                    .with_context(|| format!("unknown lidar mode {m:?}"))?;
                }
                if let Some(p) = &self.profile {
                    o.profile = match p.as_str() {
                        "legacy" => Profile::Legacy,
                        "rng19" => Profile::Rng19Rfl8Sig16Nir16,
                        _ => bail!("unknown profile {p:?}"),
                    };
                }
            }
        }
        if let Some(hz) = self.imu_rate {
            cfg.imu_board.odr = Odr::from_hz(hz).with_context(|| format!("unsupported IMU rate {hz} Hz"))?;
        }
        if self.no_imu_noise {
            cfg.imu_noise = loglio_firmware_sim::imu_chip::ChipNoise::none();
        }
        cfg.threads = if self.threads == 0 {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        } else {
            self.threads
        };
        Scenario::from_config(cfg).map_err(|e| anyhow::anyhow!("{e}"))
    }
}

/// CPU time of the whole process (all threads), seconds.
fn process_cpu_s() -> f64 {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::ProcessCPUTime);
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

/// CPU time of the calling thread, seconds.
fn thread_cpu_s() -> f64 {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::ThreadCPUTime);
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.cmd {
        Cmd::File { sc, out } => {
            let s = sc.build()?;
            let t = Instant::now();
            let sum = files::write_all(&s, &out)?;
            println!(
                "wrote {} ({} UDP datagrams, {} IMU frames, {} serial bytes) in {:.2} s",
                out.display(),
                sum.datagrams,
                sum.imu_frames,
                sum.serial_bytes,
                t.elapsed().as_secs_f64()
            );
        }
        Cmd::Replay { sc, out } => {
            let s = sc.build()?;
            if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            }
            let file = std::fs::File::create(&out).with_context(|| format!("creating {}", out.display()))?;
            let (_, st) =
                loglio_firmware_sim::firmware_recording::record_scenario(&s, std::io::BufWriter::new(file))
                    .with_context(|| format!("writing {}", out.display()))?;
            println!(
                "wrote {}: {} scans ({} points, largest {}), {} IMU samples",
                out.display(),
                st.scans,
                st.points,
                st.max_points,
                st.imu
            );
        }
        Cmd::Live { sc, rate, pty_link, port_offset } => {
            let s = sc.build()?;
            let cfg =
                live_sensors::LiveConfig { host: std::net::Ipv4Addr::LOCALHOST, rate, pty_link, port_offset };
            let stats = live_sensors::run(&s, &cfg, |pty| {
                println!("IMU serial: {}", pty.path.display());
                println!("LiDAR UDP: 127.0.0.1 (ports +{port_offset}); ctrl-c to stop");
            })?;
            println!("{stats:?}");
        }
        Cmd::Bench { mut sc, seconds } => {
            // Single thread: rays per CPU second of the casting thread.
            sc.threads = 1;
            sc.duration = Some(seconds);
            let s = sc.build()?;
            let scanner = s.scanner();
            let (c0, w0) = (thread_cpu_s(), Instant::now());
            let total = (seconds * 10.0) as u64;
            let n = total.clamp(1, 50);
            let (mut points, mut rays) = (0usize, 0u64);
            for i in 0..n {
                let j = i * (total / n).max(1);
                points += scanner.scan(j, || s.echo_source()).points.len();
                rays += scanner.rays_in_scan(j);
            }
            let (cpu, wall) = (thread_cpu_s() - c0, w0.elapsed().as_secs_f64());
            println!(
                "cast: {:.2} M rays per CPU-second ({:.2} M rays/s wall), {n} scans, {:.0} points/scan",
                rays as f64 / cpu / 1e6,
                rays as f64 / wall / 1e6,
                points as f64 / n as f64
            );
            if !s.actors().is_empty() {
                // The same scans without the actors, in the same run.
                let mut bare = ScenarioArgs { no_actors: true, ..sc.clone() };
                bare.threads = 1;
                let s0 = bare.build()?;
                let c0 = thread_cpu_s();
                let mut points0 = 0usize;
                for i in 0..n {
                    let j = i * (total / n).max(1);
                    points0 += scanner.scan(j, || s0.echo_source()).points.len();
                }
                let cpu0 = thread_cpu_s() - c0;
                println!(
                    "cast without the {} actors: {:.2} M rays per CPU-second, {:.0} points/scan (with them: {:.1} % slower)",
                    s.actors().list().len(),
                    rays as f64 / cpu0 / 1e6,
                    points0 as f64 / n as f64,
                    (cpu / cpu0 - 1.0) * 100.0
                );
            }
            // Baseline in the same run: the same random rays cast with and without the grid.
            let rays_b: Vec<Ray> = {
                let mut rng = SplitMix64::new(7, 7);
                (0..20_000)
                    .map(|_| {
                        let p =
                            s.trajectory().eval(rng.range(0.0, seconds)).attached(&s.extrinsic()).position;
                        let (az, el) = (rng.range(-3.2, 3.2), rng.range(-0.44, 0.27));
                        Ray { o: [p.x, p.y, p.z], d: [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()] }
                    })
                    .collect()
            };
            let scene = &s.world().scene;
            let time = |f: &dyn Fn(&Ray, u64) -> bool| {
                let c0 = thread_cpu_s();
                let hits = rays_b.iter().enumerate().filter(|(i, r)| f(r, *i as u64)).count();
                (thread_cpu_s() - c0, hits)
            };
            let (tg, hg) = time(&|r, k| scene.cast(r, 200.0, k).hit.is_some());
            let (tb, hb) = time(&|r, k| scene.cast_brute(r, 200.0, k).hit.is_some());
            assert_eq!(hg, hb);
            println!(
                "grid vs brute force ({} primitives): {:.2} vs {:.3} M rays per CPU-second, speed-up {:.0}x",
                scene.prims().len(),
                rays_b.len() as f64 / tg / 1e6,
                rays_b.len() as f64 / tb / 1e6,
                tb / tg
            );
            // The whole sequence through the Scenario API, with all cores.
            let mut sc2 = sc;
            sc2.threads = 0;
            let s = sc2.build()?;
            let (t, c0) = (Instant::now(), process_cpu_s());
            let (mut scans, mut imu) = (0, 0);
            for ev in s.events() {
                match ev {
                    Event::Imu(_) => imu += 1,
                    Event::Scan(_) => scans += 1,
                }
            }
            println!(
                "sequence: {:.0} s of {} ({scans} scans, {imu} IMU samples) generated in {:.2} s wall, {:.2} s CPU, with {} threads",
                seconds,
                s.config().lidar.model().name(),
                t.elapsed().as_secs_f64(),
                process_cpu_s() - c0,
                s.config().threads
            );
        }
    }
    Ok(())
}
