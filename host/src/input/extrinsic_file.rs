//! The LiDAR-IMU extrinsic from a FAST-LIO / LOG-LIO configuration file (`--extrinsic FILE`,
//! `extrinsics.file`).
//!
//! Those files are YAML with the extrinsic in the `mapping:` section:
//!
//! ```yaml
//! mapping:
//!     extrinsic_est_en:  false      # true: estimate it online
//!     extrinsic_T: [ 0, 0, 0.28]
//!     extrinsic_R: [ 1, 0, 0,
//!                    0, 1, 0,
//!                    0, 0, 1]
//! ```
//!
//! `extrinsic_T` is the LiDAR origin in the IMU frame (metres) and `extrinsic_R` the LiDAR's
//! rotation in the IMU frame, row-major: FAST-LIO's `Lidar_T_wrt_IMU` and `Lidar_R_wrt_IMU`,
//! `p_imu = R * p_lidar + T`, loglio's convention too. The file is read with a YAML parser, so
//! comments, other keys and sections, flow sequences over several lines, block sequences and a
//! ROS 2 parameter file's nesting (`/**: ros__parameters: mapping:`) are all accepted. The keys
//! are taken from a `mapping` section at any depth; without one, from wherever they are if
//! they are there once. The rotation must be orthonormal with determinant +1 within 1e-3 (the
//! printed digits of a real calibration); it is then re-orthonormalised to the nearest rotation.

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Rotation3, UnitQuaternion};
use yaml_rust2::{Yaml, YamlLoader};

/// How far `R^T R` may be from the identity, and `det R` from 1.
pub const ROTATION_TOLERANCE: f64 = 1e-3;

/// The largest translation accepted, metres per axis (as `extrinsics.translation`).
pub const MAX_TRANSLATION_M: f64 = 10.0;

/// A problem with an extrinsic file: one line naming the file and, where there is one, the
/// line of the key.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ExtrinsicFileError(pub String);

impl std::fmt::Display for ExtrinsicFileError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for ExtrinsicFileError {}

/// The extrinsic read from a file: the LiDAR's pose in the IMU frame.
#[derive(Clone, Debug, PartialEq)]
pub struct FileExtrinsic {
    /// The file it came from.
    pub path: PathBuf,
    /// `extrinsic_T`, metres.
    pub translation: [f64; 3],
    /// `extrinsic_R`, re-orthonormalised, as a unit quaternion (w, x, y, z).
    pub quat_wxyz: [f64; 4],
    /// The largest entry of `R^T R - I` and `|det R - 1|` of the rotation as written.
    pub orthonormality_error: f64,
}

/// Reads the extrinsic of a FAST-LIO / LOG-LIO YAML file.
pub fn load(path: impl AsRef<Path>) -> Result<FileExtrinsic, ExtrinsicFileError> {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path)
        .map_err(|e| ExtrinsicFileError(format!("extrinsic file {}: {e}", path.display())))?;
    parse(&text, path)
}

/// The 1-based line of the first `key:` outside a comment, if any.
fn key_line(text: &str, key: &str) -> Option<usize> {
    text.lines()
        .position(|l| {
            let code = l.split('#').next().unwrap_or("");
            code.trim_start().trim_start_matches("- ").strip_prefix(key).is_some_and(|rest| {
                let rest = rest.trim_start();
                rest.starts_with(':') || rest.starts_with("\":") || rest.starts_with("':")
            }) || code.contains(&format!("\"{key}\":"))
        })
        .map(|i| i + 1)
}

/// Every value of `key` in a hash, with whether it sits under a `mapping` key, depth first.
fn find_all<'a>(node: &'a Yaml, key: &str, in_mapping: bool, out: &mut Vec<(&'a Yaml, bool)>) {
    match node {
        Yaml::Hash(h) => {
            for (k, v) in h {
                let name = k.as_str().unwrap_or("");
                if name == key {
                    out.push((v, in_mapping));
                }
                find_all(v, key, in_mapping || name == "mapping", out);
            }
        }
        Yaml::Array(a) => {
            for v in a {
                find_all(v, key, in_mapping, out);
            }
        }
        _ => {}
    }
}

/// Parses the text of an extrinsic file; `path` names it in errors.
pub fn parse(text: &str, path: &Path) -> Result<FileExtrinsic, ExtrinsicFileError> {
    let file = path.display().to_string();
    let docs = YamlLoader::load_from_str(text)
        .map_err(|e| ExtrinsicFileError(format!("extrinsic file {file}: not valid YAML: {e}")))?;
    let at = |key: &str| match key_line(text, key) {
        Some(l) => format!("extrinsic file {file}: line {l}: {key}"),
        None => format!("extrinsic file {file}: {key}"),
    };
    let numbers = |key: &str, n: usize, what: &str| -> Result<Vec<f64>, ExtrinsicFileError> {
        let mut found = Vec::new();
        for doc in &docs {
            find_all(doc, key, false, &mut found);
        }
        let in_mapping: Vec<&Yaml> = found.iter().filter(|(_, m)| *m).map(|(v, _)| *v).collect();
        let candidates =
            if in_mapping.is_empty() { found.iter().map(|(v, _)| *v).collect() } else { in_mapping };
        let value = match candidates.as_slice() {
            [] => {
                return Err(ExtrinsicFileError(format!(
                    "extrinsic file {file}: no {key} (FAST-LIO's `mapping:` section holds `{key}: {what}`)"
                )));
            }
            [one] => *one,
            more => {
                return Err(ExtrinsicFileError(format!(
                    "{} is given {} times; keep one (in the `mapping:` section)",
                    at(key),
                    more.len()
                )));
            }
        };
        let Yaml::Array(items) = value else {
            return Err(ExtrinsicFileError(format!("{} must be a list of {n} numbers, {what}", at(key))));
        };
        if items.len() != n {
            return Err(ExtrinsicFileError(format!(
                "{} has {} numbers; it must have {n}, {what}",
                at(key),
                items.len()
            )));
        }
        items
            .iter()
            .enumerate()
            .map(|(i, v)| {
                let x = match v {
                    Yaml::Real(_) => v.as_f64(),
                    Yaml::Integer(i) => Some(*i as f64),
                    _ => None,
                };
                x.filter(|x| x.is_finite()).ok_or_else(|| {
                    ExtrinsicFileError(format!("{}[{i}] is not a finite number ({v:?})", at(key)))
                })
            })
            .collect()
    };
    let t = numbers("extrinsic_T", 3, "x, y, z in metres")?;
    let r = numbers("extrinsic_R", 9, "the 3x3 rotation row-major")?;
    if let Some((i, v)) = t.iter().enumerate().find(|(_, v)| v.abs() > MAX_TRANSLATION_M) {
        return Err(ExtrinsicFileError(format!(
            "{}[{i}] = {v} m is out of range (-{MAX_TRANSLATION_M}..={MAX_TRANSLATION_M} m)",
            at("extrinsic_T")
        )));
    }
    let m = Matrix3::from_row_slice(&r);
    let ortho = (m.transpose() * m - Matrix3::identity()).abs().max();
    let det = m.determinant();
    let error = ortho.max((det - 1.0).abs());
    if error > ROTATION_TOLERANCE {
        return Err(ExtrinsicFileError(format!(
            "{} is not a rotation: R^T R differs from the identity by {ortho:.2e} and det R = {det:.6} \
             (both must be within {ROTATION_TOLERANCE:e}; a det of -1 is a reflection, a transposed or \
             mistyped matrix); it is the LiDAR's rotation in the IMU frame, row-major",
            at("extrinsic_R")
        )));
    }
    // The nearest rotation (the digits printed by a calibration tool are not exactly one).
    let rot = Rotation3::from_matrix_eps(&m, 1e-12, 100, Rotation3::identity());
    let q = UnitQuaternion::from_rotation_matrix(&rot);
    let q = if q.w < 0.0 { -q.into_inner() } else { q.into_inner() };
    Ok(FileExtrinsic {
        path: path.to_path_buf(),
        translation: [t[0], t[1], t[2]],
        quat_wxyz: [q.w, q.i, q.j, q.k],
        orthonormality_error: error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A configuration in the layout of FAST-LIO's `config/velodyne.yaml` (comments, other
    /// sections, a multi-line flow sequence), with a LiDAR turned 90 deg about z and mounted
    /// 0.28 m above and 5 cm behind the IMU.
    const FAST_LIO_VELODYNE: &str = include_str!("../../../tests/data/fast-lio/velodyne.yaml");

    fn parse_str(text: &str) -> Result<FileExtrinsic, ExtrinsicFileError> {
        parse(text, Path::new("velodyne.yaml"))
    }

    #[test]
    fn a_fast_lio_file_gives_the_lidar_pose_in_the_imu_frame() {
        let e = parse_str(FAST_LIO_VELODYNE).unwrap();
        assert_eq!(e.translation, [-0.05, 0.0, 0.28]);
        // 90 deg about z: w = x... = cos 45, z = sin 45.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let want = [h, 0.0, 0.0, h];
        for (a, b) in e.quat_wxyz.iter().zip(want) {
            assert!((a - b).abs() < 1e-12, "{:?}", e.quat_wxyz);
        }
        assert_eq!(e.orthonormality_error, 0.0);
    }

    #[test]
    fn other_yaml_forms_are_read() {
        // A ROS 2 parameter file, block sequences, another section with the same key names.
        let text = "\
/**:
    ros__parameters:
        preprocess:
            extrinsic_T: [9.0, 9.0, 9.0]   # not the mapping's: ignored
        mapping:
            extrinsic_T:
              - 0.1
              - -0.2
              - 0.3
            extrinsic_R: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
";
        let e = parse_str(text).unwrap();
        assert_eq!(e.translation, [0.1, -0.2, 0.3]);
        assert_eq!(e.quat_wxyz, [1.0, 0.0, 0.0, 0.0]);
        // No `mapping:` at all: the keys where they are, once.
        let e = parse_str("extrinsic_T: [1, 2, 3]\nextrinsic_R: [1,0,0, 0,1,0, 0,0,1]\n").unwrap();
        assert_eq!(e.translation, [1.0, 2.0, 3.0]);
    }

    #[test]
    fn a_slightly_off_rotation_is_reorthonormalised() {
        // Printed digits a little off: R^T R is 4.4e-4 from the identity.
        let text = "mapping:\n  extrinsic_T: [0, 0, 0]\n  extrinsic_R: [1.0002, -0.0063, 0.0,\n    0.0063, 0.9999, 0.0,\n    0.0, 0.0, 1.0]\n";
        let e = parse_str(text).unwrap();
        assert!(e.orthonormality_error > 1e-5 && e.orthonormality_error < 1e-3, "{}", e.orthonormality_error);
        let n: f64 = e.quat_wxyz.iter().map(|v| v * v).sum();
        assert!((n - 1.0).abs() < 1e-12);
        // About 0.0063 rad about z.
        assert!((2.0 * e.quat_wxyz[3] - 0.0063).abs() < 1e-4, "{:?}", e.quat_wxyz);
    }

    #[test]
    fn bad_files_are_one_line_naming_the_file_and_line() {
        let bad_rotation = "mapping:\n    extrinsic_T: [0, 0, 0]\n    extrinsic_R: [1, 0, 0,\n                  0, 1, 0,\n                  0, 0, -1]   # a reflection\n";
        let e = parse_str(bad_rotation).unwrap_err().0;
        assert!(
            e.starts_with("extrinsic file velodyne.yaml: line 3: extrinsic_R is not a rotation: "),
            "{e}"
        );
        assert!(e.contains("det R = -1.000000"), "{e}");
        let scaled =
            "mapping:\n    extrinsic_T: [0, 0, 0]\n    extrinsic_R: [1.01, 0, 0, 0, 1, 0, 0, 0, 1]\n";
        assert!(parse_str(scaled).unwrap_err().0.contains("line 3: extrinsic_R is not a rotation"));
        let e = parse_str("mapping:\n    extrinsic_R: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n").unwrap_err().0;
        assert_eq!(
            e,
            "extrinsic file velodyne.yaml: no extrinsic_T (FAST-LIO's `mapping:` section holds `extrinsic_T: x, y, z in metres`)"
        );
        let e =
            parse_str("mapping:\n    extrinsic_T: [0, 0]\n    extrinsic_R: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n")
                .unwrap_err()
                .0;
        assert_eq!(
            e,
            "extrinsic file velodyne.yaml: line 2: extrinsic_T has 2 numbers; it must have 3, x, y, z in metres"
        );
        let e = parse_str(
            "mapping:\n    extrinsic_T: [0, .nan, 0]\n    extrinsic_R: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n",
        )
        .unwrap_err()
        .0;
        assert!(
            e.starts_with("extrinsic file velodyne.yaml: line 2: extrinsic_T[1] is not a finite number"),
            "{e}"
        );
        let e = parse_str("mapping:\n    extrinsic_T: [0, 0, 0]\n    extrinsic_R: 1\n").unwrap_err().0;
        assert!(
            e.starts_with("extrinsic file velodyne.yaml: line 3: extrinsic_R must be a list of 9 numbers"),
            "{e}"
        );
        let e = parse_str("mapping:\n  extrinsic_T: [0, 0, 0]\n  extrinsic_T: [1, 0, 0]\n");
        assert!(e.is_err());
        let e = parse_str("mapping: [\n").unwrap_err().0;
        assert!(e.starts_with("extrinsic file velodyne.yaml: not valid YAML: "), "{e}");
        assert!(!e.contains('\n'));
        let e = load("/nonexistent/velodyne.yaml").unwrap_err().0;
        assert!(e.starts_with("extrinsic file /nonexistent/velodyne.yaml: "), "{e}");
    }
}
