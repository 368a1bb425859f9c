//! What the commands that run the odometry share: the configuration and outputs they were
//! asked for ([`RunSetup`]) and, over raw packets, the decoder, ports and odometry
//! configuration ([`PacketSetup`]).

use std::path::PathBuf;

use loglio_core::odometry::OdometryConfig;

use crate::config::{AssociationMode, Config, Preset, SensorFamily};
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

    /// Says in one warning that the LiDAR-IMU extrinsic is identity because nothing gave one
    /// ([`Self::extrinsic_missing`]); the commands call it once their inputs are open, before
    /// the run.
    pub fn warn_missing_extrinsic(&self, cfg: &Config) {
        if let Some(why) = self.extrinsic_missing(cfg) {
            crate::diag::warn(why);
        }
    }

    /// Why the LiDAR-IMU extrinsic is identity because nothing gave one, if it is: no
    /// `[extrinsics]` in the configuration file and a preset without one (the Velodyne presets:
    /// their IMU is external; the Ouster presets carry the internal IMU's). Nothing in the
    /// data gives one today.
    pub fn extrinsic_missing(&self, cfg: &Config) -> Option<String> {
        if cfg.preset.family() != SensorFamily::Velodyne {
            return None;
        }
        let where_ = match &self.config {
            Some(p) => {
                let text = std::fs::read_to_string(p).ok()?;
                let table: toml::Table = text.parse().ok()?;
                if table.contains_key("extrinsics") {
                    return None;
                }
                format!("{} has no [extrinsics]", p.display())
            }
            None => "no configuration file".to_string(),
        };
        Some(format!(
            "no LiDAR-IMU extrinsic given ({where_}, preset {} has none, the data none): the LiDAR is taken to sit at the IMU, unrotated; give it as [extrinsics] translation and rotation_rpy_deg (or rotation_quat_wxyz) in the configuration file (--config)",
            cfg.preset
        ))
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A configuration file in a fresh directory.
    fn config_file(name: &str, text: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("loglio-setup-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("config.toml");
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn a_missing_extrinsic_is_said_once_naming_how_to_give_it() {
        // A Velodyne preset without a file: one warning, from `warn_missing_extrinsic` only.
        let setup = RunSetup { preset: Some("vlp32c".into()), ..RunSetup::default() };
        let (cfg, loaded) = crate::diag::capture(|| setup.load_config().unwrap());
        assert!(loaded.is_empty(), "{loaded:?}");
        let ((), said) = crate::diag::capture(|| setup.warn_missing_extrinsic(&cfg));
        assert_eq!(
            said,
            vec![
                "warning: no LiDAR-IMU extrinsic given (no configuration file, preset vlp32c has none, the data none): the LiDAR is taken to sit at the IMU, unrotated; give it as [extrinsics] translation and rotation_rpy_deg (or rotation_quat_wxyz) in the configuration file (--config)"
                    .to_string()
            ]
        );
        // The extrinsic it warns about is the identity.
        assert_eq!(cfg.extrinsics.translation(), [0.0; 3]);
        assert_eq!(cfg.extrinsics.quaternion_wxyz(), [1.0, 0.0, 0.0, 0.0]);
        // A file without [extrinsics] is named.
        let bare = config_file("bare", "preset = \"vlp16\"\n[mapping]\nmax_points = 5000\n");
        let setup = RunSetup { config: Some(bare.clone()), ..RunSetup::default() };
        let cfg = setup.load_config().unwrap();
        let why = setup.extrinsic_missing(&cfg).unwrap();
        assert!(
            why.starts_with(&format!(
                "no LiDAR-IMU extrinsic given ({} has no [extrinsics], preset vlp16 has none, the data none)",
                bare.display()
            )),
            "{why}"
        );
        // An [extrinsics] section, even the identity written out, is a given extrinsic.
        let given = config_file("given", "preset = \"vlp16\"\n[extrinsics]\ntranslation = [0.0, 0.0, 0.0]\n");
        let setup = RunSetup { config: Some(given), ..RunSetup::default() };
        let cfg = setup.load_config().unwrap();
        let ((), said) = crate::diag::capture(|| setup.warn_missing_extrinsic(&cfg));
        assert!(said.is_empty(), "{said:?}");
        // An Ouster preset carries its internal IMU's extrinsic.
        let setup = RunSetup { preset: Some("os1-64".into()), ..RunSetup::default() };
        let cfg = setup.load_config().unwrap();
        assert_eq!(setup.extrinsic_missing(&cfg), None);
        assert_eq!(cfg.extrinsics.translation(), [-0.006253, 0.011775, -0.007645]);
    }
}
