//! What the commands that run the odometry share: the configuration and outputs they were
//! asked for ([`RunSetup`]) and, over raw packets, the decoder, ports and odometry
//! configuration ([`PacketSetup`]).

use std::path::PathBuf;

use loglio_core::odometry::OdometryConfig;

use crate::config::{AssociationMode, Config, Preset};
use crate::error::PipelineError;
use crate::eval::{self, Format};
use crate::input::lidar_stream::SensorDecoder;
use crate::run::engine::{self, StorageClass};
use crate::sink::files::OutputOptions;

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
        let core = engine::odometry_config(cfg, layout)?;
        Ok(PacketSetup { dec, lidar_port, imu_port, class, core })
    }
}
