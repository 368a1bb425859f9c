//! The run loop as a library: a source of events in, the odometry, results out to the files
//! and the sinks. The commands are built on it, and a Rust program can embed loglio the same
//! way, with a source of its own and a [`crate::sink::ChannelSink`] or
//! [`crate::sink::CallbackSink`] receiving every scan's result:
//!
//! ```no_run
//! use loglio_core::imu::ImuSample;
//! use loglio_host::config::{Config, Preset};
//! use loglio_host::run::runner::OwnedScan;
//! use loglio_host::run::{self, Event, RunOptions};
//! use loglio_host::sink::files::OutputOptions;
//! use loglio_host::sink::{ChannelSink, SinkEvent, SinkOptions, Sinks, Wants};
//!
//! # fn my_imu_and_scans() -> Vec<Event> { Vec::new() }
//! let cfg = Config::preset(Preset::Vlp16);
//! // Every scan's result (and the IMU-rate pose) on a channel of our own.
//! let (sink, rx) = ChannelSink::new(Wants { imu_pose: true, ..Wants::default() }, 64);
//! let mut sinks = Sinks::new(SinkOptions::default());
//! sinks.add(Box::new(sink)).expect("a thread");
//! let consumer = std::thread::spawn(move || {
//!     for ev in rx {
//!         if let SinkEvent::Scan(s) = ev {
//!             println!("{} {:?} {}", s.pose.t_ns, s.pose.position, s.pose.status);
//!         }
//!     }
//! });
//! // Any iterator of events is a source (a driver's callback can feed a channel's iterator).
//! let mut events = my_imu_and_scans().into_iter();
//! let layout = loglio_host::run::engine::config_layout(&cfg)?;
//! let opts = RunOptions { sinks, ..RunOptions::default() };
//! let (stats, _files) = run::drive(&cfg, layout, &mut events, opts)?;
//! consumer.join().ok();
//! println!("{} scans", stats.scans);
//! # Ok::<(), loglio_host::error::PipelineError>(())
//! ```

pub mod engine;
pub mod pool;
pub mod runner;
pub mod setup;

use std::io;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use loglio_core::imu::ImuSample;
use loglio_core::range_image::RangeImageLayout;

use crate::config::Config;
use crate::error::PipelineError;
use crate::run::engine::StorageClass;
use crate::run::runner::{OwnedScan, RunStats, Runner};
use crate::sink::Sinks;
use crate::sink::files::{Finished, OutputOptions, Outputs};

/// What a source yields, in the order it has them.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// One IMU sample on the IMU's clock (the configuration's offset is applied by the run).
    Imu(ImuSample),
    /// One whole scan on the LiDAR's clock.
    Scan {
        /// The scan.
        scan: OwnedScan,
        /// When its last data arrived, ns on the run's clock (0: unknown, e.g. files).
        arrival_ns: u64,
    },
}

/// A source of events: anything that yields them until it ends or fails. Every iterator of
/// [`Event`]s is one.
pub trait Source {
    /// The next event; `Ok(None)` at the end.
    fn next_event(&mut self) -> Result<Option<Event>, PipelineError>;
}

impl<I: Iterator<Item = Event>> Source for I {
    fn next_event(&mut self) -> Result<Option<Event>, PipelineError> {
        Ok(self.next())
    }
}

/// Called with the runner after the last event, before the outputs are finished (a simulated
/// run sets its ground truth here).
pub type BeforeFinish<'a> = Box<dyn FnOnce(&mut Runner<'_>) -> Result<(), PipelineError> + 'a>;

/// How a run goes besides its configuration and source.
#[derive(Default)]
pub struct RunOptions<'a> {
    /// The files.
    pub outputs: OutputOptions,
    /// The live outputs.
    pub sinks: Sinks,
    /// Set (by a signal handler, another thread) to end the run as if the source had ended:
    /// everything is still written.
    pub stop: Option<Arc<AtomicBool>>,
    /// Time the odometry by its thread's CPU time instead of the wall clock (when other busy
    /// threads share the cores, e.g. the simulator's).
    pub cpu_clock: bool,
    /// See [`BeforeFinish`].
    pub before_finish: Option<BeforeFinish<'a>>,
}

impl std::fmt::Debug for RunOptions<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RunOptions")
            .field("outputs", &self.outputs)
            .field("sinks", &self.sinks)
            .field("cpu_clock", &self.cpu_clock)
            .finish_non_exhaustive()
    }
}

/// Runs the odometry of `cfg` over `layout`'s range image on every event of `source` (lent, so
/// that the caller can read the source's own counts afterwards): the
/// storage is allocated for the layout and the map capacity, the events are ordered for the
/// core, each result goes to the files and the sinks, and what is left is written at the end
/// (also after `stop`).
pub fn drive(
    cfg: &Config,
    layout: RangeImageLayout,
    source: &mut dyn Source,
    opts: RunOptions<'_>,
) -> Result<(RunStats, Finished), PipelineError> {
    let class = StorageClass::choose(layout.rows(), layout.cols(), cfg.mapping.map_capacity)?;
    let core = engine::odometry_config(cfg, layout)?;
    let outputs = Outputs::new(opts.outputs)?;
    let RunOptions { sinks, stop, cpu_clock, before_finish, .. } = opts;
    // Timed by the thread's CPU time, the other threads' share would go unseen: one thread.
    let threads = if cpu_clock { 1 } else { cfg.compute.resolved_threads() };
    engine::with_engine(&core, class, threads, |engine| {
        let mut runner = Runner::new(engine, outputs, cfg.time.lidar_imu_offset);
        runner.set_lidar_only(cfg.imu.source == crate::config::ImuSource::None);
        runner.sinks = sinks;
        if cpu_clock {
            runner.use_thread_cpu_clock();
        }
        while let Some(ev) = source.next_event()? {
            match ev {
                Event::Imu(s) => runner.imu(s)?,
                Event::Scan { scan, arrival_ns } => runner.scan(scan, arrival_ns)?,
            }
            if stop.as_ref().is_some_and(|s| s.load(Ordering::Relaxed)) {
                crate::diag::warn("stopped by a signal; writing what was estimated");
                break;
            }
        }
        runner.process_ready(true, None)?;
        if let Some(f) = before_finish {
            f(&mut runner)?;
        }
        runner.finish()
    })?
}

/// SIGINT and SIGTERM set a flag (the run ends and writes everything); a second one exits at
/// once. Unregistered on drop.
#[derive(Debug)]
pub struct Signals {
    ids: Vec<signal_hook::SigId>,
}

impl Signals {
    /// Registers the handlers that set `flag`.
    pub fn register(flag: &Arc<AtomicBool>) -> Result<Signals, PipelineError> {
        use signal_hook::consts::{SIGINT, SIGTERM};
        let mut ids = Vec::new();
        for sig in [SIGINT, SIGTERM] {
            let err = |e: io::Error| PipelineError(format!("cannot handle signal {sig}: {e}"));
            // Registered first, so it sees the flag as the previous signal left it.
            ids.push(
                signal_hook::flag::register_conditional_shutdown(sig, 1, Arc::clone(flag)).map_err(err)?,
            );
            ids.push(signal_hook::flag::register(sig, Arc::clone(flag)).map_err(err)?);
        }
        Ok(Signals { ids })
    }

    /// A fresh flag with the handlers registered (`None` with a warning when they cannot be:
    /// the run goes on without).
    pub fn stop_flag() -> (Arc<AtomicBool>, Option<Signals>) {
        let flag = Arc::new(AtomicBool::new(false));
        let s = match Signals::register(&flag) {
            Ok(s) => Some(s),
            Err(e) => {
                crate::diag::warn(format!("{e}; Ctrl-C will end the run without writing the outputs"));
                None
            }
        };
        (flag, s)
    }
}

impl Drop for Signals {
    fn drop(&mut self) {
        for id in self.ids.drain(..) {
            signal_hook::low_level::unregister(id);
        }
    }
}
