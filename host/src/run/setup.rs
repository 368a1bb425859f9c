//! What the commands that run the odometry share: the configuration and outputs they were
//! asked for ([`RunSetup`]) and, over raw packets, the decoder, ports and odometry
//! configuration ([`PacketSetup`]).

use std::path::PathBuf;

use loglio_core::odometry::OdometryConfig;

use crate::config::{AssociationMode, Config, Preset, SensorFamily};
use crate::error::PipelineError;
use crate::eval::{self, Format};
use crate::input::extrinsic_file;
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
    /// The LiDAR-IMU extrinsic from a FAST-LIO / LOG-LIO YAML file (overrides the
    /// configuration's and the data's).
    pub extrinsic: Option<PathBuf>,
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
    /// ([`Self::extrinsic_missing`]).
    pub fn warn_missing_extrinsic(&self, cfg: &Config) {
        if let Some(why) = self.extrinsic_missing(cfg) {
            crate::diag::warn(why);
        }
    }

    /// Sets `cfg`'s LiDAR-IMU extrinsic from its source of highest precedence and says which:
    /// `--extrinsic FILE`; the configuration's `extrinsics.file`; the configuration's
    /// `[extrinsics]` numbers; what the data gives (`data`: a bag's `/tf_static`, an Ouster
    /// metadata's IMU transform); the Ouster presets' internal IMU; else the identity, with the
    /// warning of [`Self::extrinsic_missing`]. The commands resolve it before they build the
    /// odometry; once their inputs are open, before the run, they warn if it is missing
    /// ([`ExtrinsicNote::warn_if_missing`]) and otherwise say where it came from in one line
    /// ([`ExtrinsicNote::line`]: `replay` and `bag` in their summary, `live` in its start-up
    /// line).
    pub fn resolve_extrinsic(
        &self,
        cfg: &mut Config,
        data: Option<DataExtrinsic>,
    ) -> Result<ExtrinsicNote, PipelineError> {
        let set = |cfg: &mut Config, t: [f64; 3], q: [f64; 4]| {
            cfg.extrinsics.translation = t;
            cfg.extrinsics.rotation_rpy_deg = None;
            cfg.extrinsics.rotation_quat_wxyz = Some(q);
        };
        let read = |p: &PathBuf| extrinsic_file::load(p).map_err(|e| PipelineError(e.to_string()));
        let from = if let Some(p) = &self.extrinsic {
            let e = read(p)?;
            set(cfg, e.translation, e.quat_wxyz);
            format!("--extrinsic {}", p.display())
        } else if let Some(p) = cfg.extrinsics.file.clone() {
            let e = read(&p)?;
            set(cfg, e.translation, e.quat_wxyz);
            format!("extrinsics.file {}", p.display())
        } else if let Some(why) = self.extrinsic_missing(cfg) {
            match data {
                Some(d) => {
                    set(cfg, d.translation, d.quat_wxyz);
                    d.what
                }
                None => return Ok(ExtrinsicNote::Missing(why)),
            }
        } else if let Some(p) = self.config.as_ref().filter(|p| config_has_extrinsics(p)) {
            format!("[extrinsics] of {}", p.display())
        } else if let Some(d) = data {
            set(cfg, d.translation, d.quat_wxyz);
            d.what
        } else {
            format!("preset {} (the Ouster's internal IMU)", cfg.preset)
        };
        let t = cfg.extrinsics.translation();
        let q = cfg.extrinsics.quaternion_wxyz();
        Ok(ExtrinsicNote::From(format!(
            "extrinsic from {from}: t = [{:.4}, {:.4}, {:.4}] m, q wxyz = [{:.4}, {:.4}, {:.4}, {:.4}]",
            t[0], t[1], t[2], q[0], q[1], q[2], q[3]
        )))
    }

    /// Whether an extrinsic the data gives would be used ([`Self::resolve_extrinsic`]): no
    /// `--extrinsic`, no `extrinsics.file` and no `[extrinsics]` in the configuration file (a
    /// live source waits for its `/tf_static` only then).
    pub fn data_extrinsic_used(&self, cfg: &Config) -> bool {
        self.extrinsic.is_none()
            && cfg.extrinsics.file.is_none()
            && !self.config.as_ref().is_some_and(|p| config_has_extrinsics(p))
    }

    /// Why the LiDAR-IMU extrinsic would be the identity, if it would: no `--extrinsic`, no
    /// `[extrinsics]` in the configuration file and a preset without one (the Velodyne presets:
    /// their IMU is external; the Ouster presets carry the internal IMU's). The data may still
    /// give one: [`Self::resolve_extrinsic`] takes it then (the bag looks for its `/tf_static`
    /// only when this says none is given).
    pub fn extrinsic_missing(&self, cfg: &Config) -> Option<String> {
        if cfg.preset.family() != SensorFamily::Velodyne || self.extrinsic.is_some() {
            return None;
        }
        let where_ = match &self.config {
            Some(p) if config_has_extrinsics(p) => return None,
            Some(p) => format!("{} has no [extrinsics]", p.display()),
            None => "no configuration file".to_string(),
        };
        Some(format!(
            "no LiDAR-IMU extrinsic given ({where_}, preset {} has none, the data none): the LiDAR is taken to sit at the IMU, unrotated; give it with --extrinsic FILE (a FAST-LIO / LOG-LIO YAML) or as [extrinsics] translation and rotation_rpy_deg (or rotation_quat_wxyz) in the configuration file (--config)",
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

/// Whether the configuration file at `p` gives an extrinsic: an `[extrinsics]` section with a
/// key in it (unreadable: no; its errors are [`RunSetup::load_config`]'s).
fn config_has_extrinsics(p: &std::path::Path) -> bool {
    std::fs::read_to_string(p)
        .ok()
        .and_then(|text| text.parse::<toml::Table>().ok())
        .and_then(|table| table.get("extrinsics").and_then(|e| e.as_table()).map(|e| !e.is_empty()))
        .unwrap_or(false)
}

/// An extrinsic the data gives: a bag's `/tf_static`, an Ouster metadata's IMU transform.
#[derive(Clone, Debug, PartialEq)]
pub struct DataExtrinsic {
    /// Where it came from, for the info line (`/tf_static (velodyne in imu_link)`).
    pub what: String,
    /// The LiDAR origin in the IMU frame, m.
    pub translation: [f64; 3],
    /// The LiDAR's rotation in the IMU frame, unit quaternion (w, x, y, z).
    pub quat_wxyz: [f64; 4],
}

impl DataExtrinsic {
    /// The Ouster's own IMU, from the metadata of `cfg.sensor.ouster_metadata` if it names one.
    pub fn of_ouster_metadata(cfg: &Config) -> Result<Option<DataExtrinsic>, PipelineError> {
        match &cfg.sensor.ouster_metadata {
            Some(p) => {
                let m = crate::input::ouster_meta::load(p).map_err(|e| PipelineError(e.to_string()))?;
                Ok(Some(Self::of_metadata(&m, &p.display().to_string())))
            }
            None => Ok(None),
        }
    }

    /// The Ouster's own IMU from parsed metadata (`source` names the file or topic).
    pub fn of_metadata(m: &crate::input::ouster_meta::OusterMetadata, source: &str) -> DataExtrinsic {
        let (translation, quat_wxyz) = m.imu_extrinsic();
        DataExtrinsic {
            what: format!("the Ouster metadata {source} (imu_to_sensor_transform)"),
            translation,
            quat_wxyz,
        }
    }
}

/// Where the extrinsic came from, to be said once the inputs are open.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ExtrinsicNote {
    /// `extrinsic from SOURCE: t = [...] m, q wxyz = [...]`.
    From(String),
    /// Nothing gave one: the warning of [`RunSetup::extrinsic_missing`].
    Missing(String),
}

impl ExtrinsicNote {
    /// The warning, when nothing gave an extrinsic.
    pub fn warn_if_missing(&self) {
        if let ExtrinsicNote::Missing(why) = self {
            crate::diag::warn(why);
        }
    }

    /// `extrinsic from SOURCE: t = [...] m, q wxyz = [...]`, when something gave one.
    pub fn line(&self) -> Option<&str> {
        match self {
            ExtrinsicNote::From(line) => Some(line),
            ExtrinsicNote::Missing(_) => None,
        }
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

    /// The fresh directory of [`config_file`] `name`.
    fn config_dir(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("loglio-setup-{}-{name}", std::process::id()))
    }

    /// A configuration file in a fresh directory (removed by [`remove_config_dirs`]).
    fn config_file(name: &str, text: &str) -> PathBuf {
        let dir = config_dir(name);
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("config.toml");
        std::fs::write(&p, text).unwrap();
        p
    }

    /// Removes the directories of [`config_file`] once a test is through with them.
    fn remove_config_dirs(names: &[&str]) {
        for n in names {
            let _ = std::fs::remove_dir_all(config_dir(n));
        }
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
                "warning: no LiDAR-IMU extrinsic given (no configuration file, preset vlp32c has none, the data none): the LiDAR is taken to sit at the IMU, unrotated; give it with --extrinsic FILE (a FAST-LIO / LOG-LIO YAML) or as [extrinsics] translation and rotation_rpy_deg (or rotation_quat_wxyz) in the configuration file (--config)"
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
        // A file made by `loglio config --preset vlp16` and not filled in: still missing (the
        // template writes the identity commented out); an empty [extrinsics] too.
        let tpl = config_file("template", &crate::config::template(crate::config::Preset::Vlp16));
        let setup = RunSetup { config: Some(tpl.clone()), ..RunSetup::default() };
        let cfg = setup.load_config().unwrap();
        assert!(setup.extrinsic_missing(&cfg).is_some());
        let empty = config_file("empty", "preset = \"vlp16\"\n[extrinsics]\n");
        let setup = RunSetup { config: Some(empty), ..RunSetup::default() };
        let cfg = setup.load_config().unwrap();
        assert!(setup.extrinsic_missing(&cfg).is_some());
        // An Ouster preset carries its internal IMU's extrinsic.
        let setup = RunSetup { preset: Some("os1-64".into()), ..RunSetup::default() };
        let cfg = setup.load_config().unwrap();
        assert_eq!(setup.extrinsic_missing(&cfg), None);
        assert_eq!(cfg.extrinsics.translation(), [-0.006253, 0.011775, -0.007645]);
        remove_config_dirs(&["bare", "given", "template", "empty"]);
    }

    /// The extrinsic's sources, highest first: `--extrinsic FILE`, `extrinsics.file` (beside
    /// the configuration), the configuration's numbers, the data, the Ouster preset, nothing.
    #[test]
    fn the_extrinsic_comes_from_the_source_of_highest_precedence() {
        let fixture = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/data/fast-lio/velodyne.yaml");
        let yaml = std::fs::read_to_string(fixture).unwrap();
        let numbers =
            config_file("numbers", "preset = \"vlp32c\"\n[extrinsics]\ntranslation = [0.1, 0.2, 0.3]\n");
        let with_file = config_file("file", "preset = \"vlp32c\"\n[extrinsics]\nfile = \"fast_lio.yaml\"\n");
        let beside = with_file.parent().unwrap().join("fast_lio.yaml");
        std::fs::write(&beside, &yaml).unwrap();
        let data = || {
            Some(DataExtrinsic {
                what: "/tf_static (velodyne in imu_link)".into(),
                translation: [0.5, 0.0, 0.0],
                quat_wxyz: [1.0, 0.0, 0.0, 0.0],
            })
        };
        let resolve = |setup: &RunSetup, data: Option<DataExtrinsic>| {
            let mut cfg = setup.load_config().unwrap();
            let note = setup.resolve_extrinsic(&mut cfg, data).unwrap();
            (cfg, note)
        };
        let from = |note: &ExtrinsicNote| match note {
            ExtrinsicNote::From(line) => line.clone(),
            ExtrinsicNote::Missing(why) => panic!("missing: {why}"),
        };
        // The command line over the configuration's numbers and the data.
        let setup = RunSetup {
            config: Some(numbers.clone()),
            extrinsic: Some(fixture.into()),
            ..RunSetup::default()
        };
        let (cfg, note) = resolve(&setup, data());
        assert_eq!(
            from(&note),
            format!(
                "extrinsic from --extrinsic {fixture}: t = [-0.0500, 0.0000, 0.2800] m, q wxyz = [0.7071, 0.0000, 0.0000, 0.7071]"
            )
        );
        assert_eq!(cfg.extrinsics.translation(), [-0.05, 0.0, 0.28]);
        // The odometry gets it: the core's configuration holds the file's rotation.
        let r = cfg.extrinsics.rotation_matrix();
        assert!((r[0][1] + 1.0).abs() < 1e-12 && (r[1][0] - 1.0).abs() < 1e-12, "{r:?}");
        // extrinsics.file, found beside the configuration, over the data.
        let setup = RunSetup { config: Some(with_file.clone()), ..RunSetup::default() };
        let (cfg, note) = resolve(&setup, data());
        assert!(
            from(&note)
                .starts_with(&format!("extrinsic from extrinsics.file {}: t = [-0.0500,", beside.display()))
        );
        assert_eq!(cfg.extrinsics.translation(), [-0.05, 0.0, 0.28]);
        // The configuration's numbers over the data.
        let setup = RunSetup { config: Some(numbers.clone()), ..RunSetup::default() };
        let (cfg, note) = resolve(&setup, data());
        assert!(from(&note).starts_with(&format!(
            "extrinsic from [extrinsics] of {}: t = [0.1000, 0.2000, 0.3000] m",
            numbers.display()
        )));
        assert_eq!(cfg.extrinsics.translation(), [0.1, 0.2, 0.3]);
        // The data when the configuration has none; nothing: the warning.
        let setup = RunSetup { preset: Some("vlp32c".into()), ..RunSetup::default() };
        let (cfg, note) = resolve(&setup, data());
        assert!(
            from(&note).starts_with(
                "extrinsic from /tf_static (velodyne in imu_link): t = [0.5000, 0.0000, 0.0000] m"
            )
        );
        assert_eq!(cfg.extrinsics.translation(), [0.5, 0.0, 0.0]);
        let (_, note) = resolve(&setup, None);
        assert!(
            matches!(&note, ExtrinsicNote::Missing(w) if w.starts_with("no LiDAR-IMU extrinsic given (no configuration file"))
        );
        // An Ouster: its metadata's IMU over the preset's; the preset's without metadata.
        let meta =
            concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/data/ouster-sdk/OS-2-128-U1_v2.3.0_1024x10.json");
        let setup =
            RunSetup { preset: Some("os1-128".into()), metadata: Some(meta.into()), ..RunSetup::default() };
        let mut cfg = setup.load_config().unwrap();
        let data = DataExtrinsic::of_ouster_metadata(&cfg).unwrap();
        let note = setup.resolve_extrinsic(&mut cfg, data).unwrap();
        assert_eq!(
            from(&note),
            format!(
                "extrinsic from the Ouster metadata {meta} (imu_to_sensor_transform): t = [-0.0063, 0.0118, -0.0116] m, q wxyz = [1.0000, 0.0000, 0.0000, 0.0000]"
            )
        );
        let setup = RunSetup { preset: Some("os1-128".into()), ..RunSetup::default() };
        let (_, note) = resolve(&setup, None);
        assert!(from(&note).starts_with(
            "extrinsic from preset os1-128 (the Ouster's internal IMU): t = [-0.0063, 0.0118, -0.0076] m"
        ));
        // A bad file is an error naming it.
        let bad = with_file.parent().unwrap().join("bad.yaml");
        std::fs::write(&bad, "mapping:\n  extrinsic_T: [0, 0, 0]\n").unwrap();
        let setup =
            RunSetup { preset: Some("vlp32c".into()), extrinsic: Some(bad.clone()), ..RunSetup::default() };
        let mut cfg = setup.load_config().unwrap();
        let e = setup.resolve_extrinsic(&mut cfg, None).unwrap_err().0;
        assert!(e.starts_with(&format!("extrinsic file {}: no extrinsic_R", bad.display())), "{e}");
        remove_config_dirs(&["numbers", "file"]);
    }
}
