//! The live outputs' command-line options, shared by `live`, `replay`, `bag`, `sim` and `demo`.

use clap::Args;

use super::mavlink::{
    MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY, MavlinkOptions, MavlinkSink, MavlinkUrl, serial_too_slow,
};
use super::{SinkOptions, Sinks};

/// Live outputs: where each pose, scan and map goes while the odometry runs.
#[derive(Clone, Debug, Default, Args)]
#[command(next_help_heading = "Live outputs")]
pub struct SinkArgs {
    /// Events each live output may hold before it drops (and counts) what it cannot send in time.
    #[arg(long, value_name = "N", default_value_t = 256, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
    pub sink_queue: u64,
    /// Seconds between two maps sent to the live outputs that carry one.
    #[arg(long, value_name = "S", default_value_t = 5.0)]
    pub map_every: f64,
    /// MAVLink 2 output (HEARTBEAT and ODOMETRY, for PX4/ArduPilot external vision):
    /// udp:HOST:PORT (or udpout:HOST:PORT) or serial:/dev/PATH:BAUD.
    #[arg(long, value_name = "URL")]
    pub mavlink: Option<MavlinkUrl>,
    /// ODOMETRY messages per second: every scan's pose, and the IMU-propagated pose between
    /// scans up to this rate; at or below the scan rate (or 0) the scans' poses only.
    #[arg(long, value_name = "HZ", default_value_t = 50.0, value_parser = parse_rate)]
    pub mavlink_rate: f64,
    /// MAVLink system id (the autopilot's, for a companion computer on the vehicle).
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=255))]
    pub mavlink_sysid: u8,
    /// MAVLink component id (default MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY).
    #[arg(long, value_name = "N", default_value_t = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY, value_parser = clap::value_parser!(u8).range(1..=255))]
    pub mavlink_compid: u8,
    /// Serve the live output to Foxglove on HOST:PORT (Foxglove WebSocket, e.g. 0.0.0.0:8765).
    #[arg(long, value_name = "HOST:PORT")]
    pub foxglove: Option<String>,
    /// Record the Foxglove output's channels to an MCAP file.
    #[arg(long, value_name = "FILE")]
    pub mcap: Option<std::path::PathBuf>,
    /// Publish over ROS 2 (DDS; no ROS installation needed): odometry, IMU-rate odometry, /tf,
    /// the scan and the map. The domain is ROS_DOMAIN_ID's (default 0).
    #[arg(long)]
    pub ros2: bool,
    /// Namespace of the --ros2 topics (/tf is always global).
    #[arg(long, value_name = "NS", default_value = "/loglio")]
    pub ros2_namespace: String,
    /// The --ros2 world frame (the odometry's header and the parent in /tf).
    #[arg(long, value_name = "FRAME", default_value = "odom")]
    pub ros2_frame_id: String,
    /// The --ros2 body frame (the odometry's child frame, the IMU).
    #[arg(long, value_name = "FRAME", default_value = "base_link")]
    pub ros2_child_frame_id: String,
}

/// A rate in Hz: finite, 0 to 1000.
fn parse_rate(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(r) if r.is_finite() && (0.0..=1000.0).contains(&r) => Ok(r),
        _ => Err(format!("'{s}' is not a rate from 0 to 1000 Hz")),
    }
}

impl SinkArgs {
    /// The sinks these options name, each started on its own thread. One that cannot start (a
    /// port in use, an unreachable address) is left out with one `warning:` line: the run and
    /// the other outputs go on.
    pub fn build(&self) -> Sinks {
        let opt = SinkOptions {
            queue: usize::try_from(self.sink_queue).unwrap_or(usize::MAX),
            map_every_s: if self.map_every.is_finite() { self.map_every.max(0.0) } else { 5.0 },
            ..SinkOptions::default()
        };
        let mut sinks = Sinks::new(opt);
        if let Some(url) = &self.mavlink {
            let opt = MavlinkOptions {
                url: url.clone(),
                rate_hz: self.mavlink_rate,
                sysid: self.mavlink_sysid,
                compid: self.mavlink_compid,
            };
            let sink = MavlinkSink::new(opt).map(|s| Box::new(s) as Box<dyn super::Sink>);
            let slow = match (&sink, url) {
                (Ok(_), MavlinkUrl::Serial { baud, .. }) => serial_too_slow(*baud, self.mavlink_rate),
                _ => None,
            };
            if let Some(w) = slow {
                crate::diag::warn(format!("mavlink {url}: {w}"));
            }
            add(&mut sinks, &format!("mavlink {url}"), sink);
        }
        if let Some(a) = &self.foxglove {
            let s = super::foxglove::FoxgloveSink::start(a).map(|s| Box::new(s) as Box<dyn super::Sink>);
            add(&mut sinks, "--foxglove", s);
        }
        if let Some(p) = &self.mcap {
            let s = super::mcap::McapSink::create(p).map(|s| Box::new(s) as Box<dyn super::Sink>);
            add(&mut sinks, "--mcap", s);
        }
        if self.ros2 {
            add(&mut sinks, "--ros2", self.ros2_sink());
        }
        sinks
    }

    fn ros2_sink(&self) -> Result<Box<dyn super::Sink>, super::SinkError> {
        let domain = super::ros2::domain_from_env(std::env::var("ROS_DOMAIN_ID").ok().as_deref())?;
        let opt = super::ros2::Ros2Options {
            domain,
            namespace: self.ros2_namespace.clone(),
            frame_id: self.ros2_frame_id.clone(),
            child_frame_id: self.ros2_child_frame_id.clone(),
        };
        Ok(Box::new(super::ros2::Ros2Sink::start(opt)?))
    }
}

/// Adds `sink` (or says in one warning why it could not start).
fn add(sinks: &mut Sinks, what: &str, sink: Result<Box<dyn super::Sink>, super::SinkError>) {
    match sink.and_then(|s| sinks.add(s)) {
        Ok(()) => {}
        Err(e) => crate::diag::warn(format!("{what}: {e}; this output is off for the run")),
    }
}
