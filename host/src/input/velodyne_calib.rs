//! ROS `velodyne_pointcloud` calibration yaml (`VLP16db.yaml`, `VeloView-VLP-32C.yaml`, the
//! Nebula `*.calib.yaml` files, files made by `gen_calibration.py` from a db.xml) into the core's
//! [`Calibration`].
//!
//! Format: `lasers:` a list of maps with `laser_id`, `rot_correction`, `vert_correction`
//! (radians), `vert_offset_correction`, `horiz_offset_correction`, `dist_correction` (metres),
//! optionally `num_lasers` and `distance_resolution` (metres, default 0.002). The offsets are
//! applied as the ROS driver does ([`OffsetModel::RosAdvanced`]). The HDL-64E two-point distance
//! corrections (`dist_correction_x/_y`) and the intensity focal parameters are not used: a file
//! that sets them non-zero is read with a warning.

use loglio_core::sensor::velodyne::{Calibration, LaserCalibration, OffsetModel};
use std::path::Path;
use yaml_rust2::{Yaml, YamlLoader};

/// A calibration-file problem.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CalibError(pub String);

impl std::fmt::Display for CalibError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "velodyne calibration: {}", self.0)
    }
}

impl std::error::Error for CalibError {}

/// Reads a calibration file.
pub fn load(path: impl AsRef<Path>) -> Result<Calibration, CalibError> {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path).map_err(|e| CalibError(format!("{}: {e}", path.display())))?;
    parse(&text)
}

fn num(v: &Yaml) -> Option<f64> {
    match v {
        Yaml::Real(_) => v.as_f64(),
        Yaml::Integer(i) => Some(*i as f64),
        _ => None,
    }
}

/// Parses calibration yaml text.
pub fn parse(text: &str) -> Result<Calibration, CalibError> {
    let docs = YamlLoader::load_from_str(text).map_err(|e| CalibError(format!("not valid yaml: {e}")))?;
    let doc = docs.first().ok_or_else(|| CalibError("empty file".into()))?;
    let lasers = doc["lasers"].as_vec().ok_or_else(|| CalibError("no `lasers:` list".into()))?;
    let n = match &doc["num_lasers"] {
        Yaml::BadValue => lasers.len(),
        v => num(v).ok_or_else(|| CalibError("num_lasers is not a number".into()))? as usize,
    };
    if n != lasers.len() {
        return Err(CalibError(format!("num_lasers is {n} but {} lasers are listed", lasers.len())));
    }
    let res = match &doc["distance_resolution"] {
        Yaml::BadValue => 0.002,
        v => num(v).ok_or_else(|| CalibError("distance_resolution is not a number".into()))?,
    };
    let mut calib = Calibration::new(n, res as f32, OffsetModel::RosAdvanced)
        .map_err(|e| CalibError(format!("{e} ({n} lasers, resolution {res})")))?;
    let mut seen = vec![false; n];
    let mut unsupported = false;
    for (k, l) in lasers.iter().enumerate() {
        let field = |name: &str, default: Option<f64>| -> Result<f64, CalibError> {
            match &l[name] {
                Yaml::BadValue => {
                    default.ok_or_else(|| CalibError(format!("laser entry {k}: `{name}` missing")))
                }
                v => num(v).ok_or_else(|| CalibError(format!("laser entry {k}: `{name}` is not a number"))),
            }
        };
        let id = field("laser_id", None)?;
        if id < 0.0 || id.fract() != 0.0 || id as usize >= n {
            return Err(CalibError(format!("laser entry {k}: laser_id {id} is not in 0..{n}")));
        }
        let id = id as usize;
        if std::mem::replace(&mut seen[id], true) {
            return Err(CalibError(format!("laser_id {id} is listed twice")));
        }
        let laser = LaserCalibration {
            elevation: field("vert_correction", None)? as f32,
            azimuth: field("rot_correction", Some(0.0))? as f32,
            vert_offset: field("vert_offset_correction", Some(0.0))? as f32,
            horiz_offset: field("horiz_offset_correction", Some(0.0))? as f32,
            dist_correction: field("dist_correction", Some(0.0))? as f32,
        };
        let dc = laser.dist_correction as f64;
        if field("dist_correction_x", Some(dc))? != dc || field("dist_correction_y", Some(dc))? != dc {
            unsupported = true;
        }
        calib.set_laser(id, laser).map_err(|e| CalibError(format!("laser_id {id}: {e}")))?;
    }
    if unsupported {
        log::warn!("velodyne calibration: two-point distance corrections (HDL-64E) are not applied");
    }
    Ok(calib)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flow_and_block_styles() {
        let flow = "lasers:\n  - {dist_correction: 0.0, laser_id: 1, rot_correction: -0.02, vert_correction: 0.1, vert_offset_correction: 0.01}\n  - {laser_id: 0, vert_correction: -0.2}\n";
        let text = flow.replace("lasers:\n", "").repeat(8);
        let c = parse(&format!("lasers:\n{text}num_lasers: 16\ndistance_resolution: 0.002\n"));
        // 16 entries but ids 0 and 1 repeated: an error naming the duplicate.
        assert!(c.unwrap_err().to_string().contains("listed twice"));
        let mut entries = String::new();
        for i in 0..16 {
            entries.push_str(&format!(
                "  - laser_id: {i}\n    rot_correction: 0.0\n    vert_correction: {}\n    vert_offset_correction: 0.0112\n",
                -0.26 + i as f64 * 0.03
            ));
        }
        let c = parse(&format!("lasers:\n{entries}num_lasers: 16\n")).unwrap();
        assert_eq!(c.num_lasers(), 16);
        assert_eq!(c.offset_model, OffsetModel::RosAdvanced);
        assert!((c.lasers()[3].elevation - (-0.26 + 0.09) as f32).abs() < 1e-7);
        assert_eq!(c.lasers()[0].vert_offset, 0.0112);
        assert_eq!(c.distance_resolution, 0.002);
    }

    #[test]
    fn errors_are_clear() {
        assert!(parse("").unwrap_err().to_string().contains("empty"));
        assert!(parse("foo: 1").unwrap_err().to_string().contains("lasers"));
        let sixteen = |last: &str| {
            let mut s = String::from("lasers:\n");
            for i in 0..15 {
                s.push_str(&format!("  - {{laser_id: {i}, vert_correction: 0.01}}\n"));
            }
            s.push_str(&format!("  - {last}\n"));
            s
        };
        let e = parse(&sixteen("{laser_id: 15}")).unwrap_err().to_string();
        assert!(e.contains("laser entry 15: `vert_correction` missing"), "{e}");
        let e = parse(&sixteen("{laser_id: x, vert_correction: 0}")).unwrap_err().to_string();
        assert!(e.contains("`laser_id` is not a number"), "{e}");
        let e = parse(&sixteen("{laser_id: 16, vert_correction: 0}")).unwrap_err().to_string();
        assert!(e.contains("not in 0..16"), "{e}");
        let e = parse(&sixteen("{laser_id: 15, vert_correction: 2.0}")).unwrap_err().to_string();
        assert!(e.contains("laser_id 15"), "{e}");
        assert!(
            parse("lasers: [{laser_id: 0, vert_correction: 0}]")
                .unwrap_err()
                .to_string()
                .contains("1 lasers")
        );
        assert!(parse("lasers: [{: ").unwrap_err().to_string().contains("yaml"));
    }
}
