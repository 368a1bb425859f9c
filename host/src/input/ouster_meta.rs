//! Ouster sensor metadata JSON (the file `ouster-cli` / the SDK / ouster_ros save) into the
//! core's [`OusterIntrinsics`].
//!
//! Both layouts are read:
//! - legacy (firmware 1.x/2.x, SDK < 0.5): flat keys `beam_altitude_angles`,
//!   `beam_azimuth_angles`, `lidar_mode`, `data_format {...}`, `lidar_origin_to_beam_origin_mm`,
//!   `lidar_to_sensor_transform`, `imu_to_sensor_transform`;
//! - current (firmware 2.x/3.x): sections `beam_intrinsics`, `lidar_intrinsics`,
//!   `imu_intrinsics`, `lidar_data_format`, `config_params`, `sensor_info`.
//!
//! What a file leaves out gets the SDK's defaults: 16 columns per packet, pixels per column =
//! number of beams, the LEGACY profile, the OS1 beam-origin distance 12.163 mm, the default
//! transforms, and the first-generation destaggering shifts (3, 2, 1, 0) x (columns / 170.67).

use loglio_core::sensor::ouster::{MAX_BEAMS, OusterIntrinsics, Profile};
use serde_json::Value;
use std::path::Path;

/// A metadata problem, naming the field.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MetaError {
    /// The JSON field (or "file").
    pub field: String,
    /// What is wrong with it.
    pub problem: String,
}

impl std::fmt::Display for MetaError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ouster metadata: {}: {}", self.field, self.problem)
    }
}

impl std::error::Error for MetaError {}

fn err(field: &str, problem: impl Into<String>) -> MetaError {
    MetaError { field: field.to_string(), problem: problem.into() }
}

/// Everything loglio takes from the metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct OusterMetadata {
    /// The core's intrinsics.
    pub intrinsics: OusterIntrinsics,
    /// Product line, e.g. "OS-1-128", if given.
    pub prod_line: Option<String>,
    /// Serial number, if given.
    pub serial: Option<String>,
    /// Firmware revision, if given.
    pub firmware: Option<String>,
    /// Lidar UDP port (default 7502).
    pub udp_port_lidar: u16,
    /// IMU UDP port (default 7503).
    pub udp_port_imu: u16,
    /// Timestamp mode (`TIME_FROM_INTERNAL_OSC`, `TIME_FROM_PTP_1588`, ...), if given.
    pub timestamp_mode: Option<String>,
}

impl OusterMetadata {
    /// The LiDAR-IMU extrinsic when the Ouster's own IMU is used: the pose, in the IMU frame,
    /// of the frame the decoded points are in, `(translation m, quaternion w x y z)`.
    ///
    /// The core's decoder applies `lidar_to_sensor_transform` already (its points are the SDK's
    /// XYZ, in the sensor frame), so the extrinsic is `imu_to_sensor⁻¹` alone:
    /// `p_imu = R_isᵀ (p_sensor - t_is)`, i.e. `R = R_isᵀ`, `t = -R_isᵀ t_is` (mm to m). For
    /// points in the lidar frame it would be `imu_to_sensor⁻¹ · lidar_to_sensor`.
    pub fn imu_extrinsic(&self) -> ([f64; 3], [f64; 4]) {
        use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
        let m = &self.intrinsics.imu_to_sensor;
        let at = |i: usize, j: usize| m[4 * i + j] as f64;
        let r_is = Matrix3::from_fn(at);
        let t_is = Vector3::new(at(0, 3), at(1, 3), at(2, 3)) * 1e-3;
        // The metadata's rotation is printed to a few digits: the nearest rotation.
        let r = Rotation3::from_matrix_eps(&r_is.transpose(), 1e-12, 100, Rotation3::identity());
        let t = -(r * t_is);
        let q = UnitQuaternion::from_rotation_matrix(&r);
        let q = if q.w < 0.0 { -q.into_inner() } else { q.into_inner() };
        ([t.x, t.y, t.z], [q.w, q.i, q.j, q.k])
    }
}

/// Reads a metadata file.
pub fn load(path: impl AsRef<Path>) -> Result<OusterMetadata, MetaError> {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path).map_err(|e| err("file", format!("{}: {e}", path.display())))?;
    parse(&text)
}

/// Finds `key` at the top level or in one of the known sections.
fn find<'a>(root: &'a Value, key: &str) -> Option<&'a Value> {
    if let Some(v) = root.get(key) {
        return Some(v);
    }
    for section in [
        "beam_intrinsics",
        "lidar_intrinsics",
        "imu_intrinsics",
        "lidar_data_format",
        "data_format",
        "config_params",
        "sensor_info",
    ] {
        if let Some(v) = root.get(section).and_then(|s| s.get(key)) {
            return Some(v);
        }
    }
    None
}

fn numbers(root: &Value, key: &str) -> Result<Option<Vec<f64>>, MetaError> {
    let Some(v) = find(root, key) else { return Ok(None) };
    let arr = v.as_array().ok_or_else(|| err(key, "expected an array of numbers"))?;
    arr.iter()
        .enumerate()
        .map(|(i, x)| {
            x.as_f64()
                .filter(|f| f.is_finite())
                .ok_or_else(|| err(key, format!("element {i} is not a finite number")))
        })
        .collect::<Result<Vec<_>, _>>()
        .map(Some)
}

fn number(root: &Value, key: &str) -> Result<Option<f64>, MetaError> {
    match find(root, key) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => {
            v.as_f64().filter(|f| f.is_finite()).map(Some).ok_or_else(|| err(key, "expected a finite number"))
        }
    }
}

fn string(root: &Value, key: &str) -> Option<String> {
    find(root, key).and_then(|v| match v {
        Value::String(s) if !s.is_empty() => Some(s.clone()),
        Value::Number(n) => Some(n.to_string()),
        _ => None,
    })
}

fn matrix(root: &Value, key: &str) -> Result<Option<[f32; 16]>, MetaError> {
    let Some(v) = numbers(root, key)? else { return Ok(None) };
    if v.len() != 16 {
        return Err(err(key, format!("expected 16 numbers (4x4 row-major), found {}", v.len())));
    }
    let mut m = [0f32; 16];
    for (d, s) in m.iter_mut().zip(&v) {
        *d = *s as f32;
    }
    Ok(Some(m))
}

/// Parses metadata JSON text.
pub fn parse(text: &str) -> Result<OusterMetadata, MetaError> {
    let root: Value = serde_json::from_str(text).map_err(|e| err("file", format!("not valid JSON: {e}")))?;
    if !root.is_object() {
        return Err(err("file", "the top level is not a JSON object"));
    }
    let alt =
        numbers(&root, "beam_altitude_angles")?.ok_or_else(|| err("beam_altitude_angles", "missing"))?;
    let az = numbers(&root, "beam_azimuth_angles")?.ok_or_else(|| err("beam_azimuth_angles", "missing"))?;
    if alt.len() != az.len() {
        return Err(err(
            "beam_azimuth_angles",
            format!("{} values but {} altitude angles", az.len(), alt.len()),
        ));
    }
    if alt.is_empty() || alt.len() > MAX_BEAMS {
        return Err(err("beam_altitude_angles", format!("{} beams (1..={MAX_BEAMS} supported)", alt.len())));
    }
    let mode = string(&root, "lidar_mode").ok_or_else(|| err("lidar_mode", "missing (e.g. \"1024x10\")"))?;
    let (mode_cols, freq) = mode
        .split_once('x')
        .and_then(|(c, f)| Some((c.parse::<u16>().ok()?, f.parse::<u16>().ok()?)))
        .ok_or_else(|| err("lidar_mode", format!("{mode:?} is not of the form <columns>x<Hz>")))?;
    let cols = match number(&root, "columns_per_frame")? {
        Some(c) => c as u16,
        None => mode_cols,
    };
    let h = match number(&root, "pixels_per_column")? {
        Some(p) => p as usize,
        None => alt.len(),
    };
    if h != alt.len() {
        return Err(err("pixels_per_column", format!("{h} but {} beam angles", alt.len())));
    }
    let profile = match string(&root, "udp_profile_lidar") {
        None => Profile::Legacy,
        Some(name) => Profile::from_name(&name).ok_or_else(|| {
            err(
                "udp_profile_lidar",
                format!("{name:?} is not supported (LEGACY, RNG19_RFL8_SIG16_NIR16[_DUAL], RNG15_RFL8_NIR8, FUSA_RNG15_RFL8_NIR8_DUAL)"),
            )
        })?,
    };
    let mut intr = OusterIntrinsics::new(profile, h as u16, cols, freq);
    if let Some(cpp) = number(&root, "columns_per_packet")? {
        intr.columns_per_packet = cpp as u16;
    }
    for u in 0..h {
        intr.beam_altitude_deg[u] = alt[u] as f32;
        intr.beam_azimuth_deg[u] = az[u] as f32;
    }
    match numbers(&root, "pixel_shift_by_row")? {
        Some(shift) => {
            if shift.len() != h {
                return Err(err("pixel_shift_by_row", format!("{} values for {h} beams", shift.len())));
            }
            for (d, s) in intr.pixel_shift_by_row.iter_mut().zip(&shift) {
                if s.fract() != 0.0 || s.abs() > 8192.0 {
                    return Err(err("pixel_shift_by_row", format!("{s} is not a small integer")));
                }
                *d = *s as i16;
            }
        }
        None => {
            let base = (cols as i32 * 6 / 1024) as i16;
            for (u, d) in intr.pixel_shift_by_row.iter_mut().enumerate().take(h) {
                *d = (3 - (u % 4) as i16) * base;
            }
        }
    }
    if let Some(m) = matrix(&root, "beam_to_lidar_transform")? {
        intr.beam_origin_mm = [m[3], m[11]];
    } else if let Some(n) = number(&root, "lidar_origin_to_beam_origin_mm")? {
        intr.beam_origin_mm = [n as f32, 0.0];
    }
    if let Some(m) = matrix(&root, "lidar_to_sensor_transform")? {
        intr.lidar_to_sensor = m;
    }
    if let Some(m) = matrix(&root, "imu_to_sensor_transform")? {
        intr.imu_to_sensor = m;
    }
    intr.validate().map_err(|e| err("file", e.to_string()))?;
    let port = |key: &str, default: u16| -> Result<u16, MetaError> {
        match number(&root, key)? {
            None => Ok(default),
            Some(p) if (0.0..=65535.0).contains(&p) && p != 0.0 => Ok(p as u16),
            Some(p) => Err(err(key, format!("{p} is not a UDP port"))),
        }
    };
    Ok(OusterMetadata {
        intrinsics: intr,
        prod_line: string(&root, "prod_line"),
        serial: string(&root, "prod_sn"),
        firmware: string(&root, "build_rev").or_else(|| string(&root, "fw_rev")),
        udp_port_lidar: port("udp_port_lidar", 7502)?,
        udp_port_imu: port("udp_port_imu", 7503)?,
        timestamp_mode: string(&root, "timestamp_mode"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const LEGACY: &str = r#"{
        "beam_altitude_angles": [10.0, 3.5, -3.5, -10.0],
        "beam_azimuth_angles": [3.1, 1.0, -1.0, -3.1],
        "lidar_mode": "512x20",
        "lidar_origin_to_beam_origin_mm": 15.806,
        "data_format": {"pixels_per_column": 4, "columns_per_packet": 16, "pixel_shift_by_row": [9, 6, 3, 0],
                        "udp_profile_lidar": "RNG19_RFL8_SIG16_NIR16"},
        "prod_line": "OS-1-4-test", "udp_port_lidar": 7777
    }"#;

    #[test]
    fn legacy_layout() {
        let m = parse(LEGACY).unwrap();
        let i = &m.intrinsics;
        assert_eq!(i.profile, Profile::Single);
        assert_eq!((i.pixels_per_column, i.columns_per_frame, i.frequency_hz), (4, 512, 20));
        assert_eq!(i.pixel_shift_by_row[..4], [9, 6, 3, 0]);
        assert_eq!(i.beam_origin_mm, [15.806, 0.0]);
        assert_eq!(i.lidar_to_sensor[11], 36.18, "default transform");
        assert_eq!(m.prod_line.as_deref(), Some("OS-1-4-test"));
        assert_eq!((m.udp_port_lidar, m.udp_port_imu), (7777, 7503));
    }

    #[test]
    fn current_layout() {
        let text = r#"{
            "beam_intrinsics": {"beam_altitude_angles": [1.0, -1.0], "beam_azimuth_angles": [0.5, -0.5],
                                "beam_to_lidar_transform": [1,0,0,16.7, 0,1,0,0, 0,0,1,2.5, 0,0,0,1]},
            "lidar_intrinsics": {"lidar_to_sensor_transform": [-1,0,0,0, 0,-1,0,0, 0,0,1,38.195, 0,0,0,1]},
            "lidar_data_format": {"columns_per_frame": 1024, "columns_per_packet": 16, "pixels_per_column": 2,
                                  "pixel_shift_by_row": [12, -12], "udp_profile_lidar": "FUSA_RNG15_RFL8_NIR8_DUAL"},
            "config_params": {"lidar_mode": "1024x10", "udp_port_imu": 7504, "timestamp_mode": "TIME_FROM_PTP_1588"},
            "sensor_info": {"prod_line": "OS-1-128", "build_rev": "v3.1.0"}
        }"#;
        let m = parse(text).unwrap();
        let i = &m.intrinsics;
        assert_eq!(i.profile, Profile::FusaDualLowBandwidth);
        assert_eq!(i.beam_origin_mm, [16.7, 2.5]);
        assert_eq!(i.lidar_to_sensor[11], 38.195);
        assert_eq!(i.pixel_shift_by_row[..2], [12, -12]);
        assert_eq!(m.udp_port_imu, 7504);
        assert_eq!(m.firmware.as_deref(), Some("v3.1.0"));
        assert_eq!(m.timestamp_mode.as_deref(), Some("TIME_FROM_PTP_1588"));
    }

    #[test]
    fn minimal_file_gets_sdk_defaults() {
        let alt: Vec<String> = (0..64).map(|i| format!("{}", 16.0 - i as f64 * 0.5)).collect();
        let text = format!(
            r#"{{"beam_altitude_angles": [{0}], "beam_azimuth_angles": [{0}], "lidar_mode": "1024x10"}}"#,
            alt.join(",")
        );
        let i = parse(&text).unwrap().intrinsics;
        assert_eq!(i.profile, Profile::Legacy);
        assert_eq!(i.pixel_shift_by_row[..8], [18, 12, 6, 0, 18, 12, 6, 0]);
        assert_eq!(i.beam_origin_mm, [12.163, 0.0]);
        assert_eq!(i.columns_per_packet, 16);
    }

    /// The extrinsic of the Ouster's own IMU, from the repository's real OS-2-128 metadata
    /// (`imu_to_sensor_transform` = identity rotation, (6.253, -11.775, 11.645) mm; the OS1's
    /// is 7.645 mm in z, which the os1-* presets carry), checked against the hand computation
    /// `t = -t_is / 1000`, and a turned IMU against `R = R_isᵀ`, `t = -R_isᵀ t_is`.
    #[test]
    fn the_imu_extrinsic_is_the_inverse_of_imu_to_sensor() {
        let path =
            concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/data/ouster-sdk/OS-2-128-U1_v2.3.0_1024x10.json");
        let m = load(path).unwrap();
        let (t, q) = m.imu_extrinsic();
        let want = [-0.006253, 0.011775, -0.011645];
        for (a, b) in t.iter().zip(want) {
            assert!((a - b).abs() < 1e-8, "{t:?}");
        }
        assert_eq!(q, [1.0, 0.0, 0.0, 0.0]);
        // An IMU turned 90 deg about z in the sensor frame, at (10, 20, 30) mm:
        // R_is = [[0,-1,0],[1,0,0],[0,0,1]], so R = R_isᵀ (-90 deg about z) and
        // t = -R_isᵀ (0.01, 0.02, 0.03) = -(0.02, -0.01, 0.03).
        let mut m = m;
        m.intrinsics.imu_to_sensor =
            [0.0, -1.0, 0.0, 10.0, 1.0, 0.0, 0.0, 20.0, 0.0, 0.0, 1.0, 30.0, 0.0, 0.0, 0.0, 1.0];
        let (t, q) = m.imu_extrinsic();
        for (a, b) in t.iter().zip([-0.02, 0.01, -0.03]) {
            assert!((a - b).abs() < 1e-9, "{t:?}");
        }
        let h = std::f64::consts::FRAC_1_SQRT_2;
        for (a, b) in q.iter().zip([h, 0.0, 0.0, -h]) {
            assert!((a - b).abs() < 1e-9, "{q:?}");
        }
    }

    #[test]
    fn errors_name_the_field() {
        let cases = [
            ("not json", "file"),
            ("[1,2]", "file"),
            (r#"{"beam_azimuth_angles": [1], "lidar_mode": "1024x10"}"#, "beam_altitude_angles"),
            (
                r#"{"beam_altitude_angles": [1,2], "beam_azimuth_angles": [1], "lidar_mode": "1024x10"}"#,
                "beam_azimuth_angles",
            ),
            (
                r#"{"beam_altitude_angles": [1], "beam_azimuth_angles": [1], "lidar_mode": "fast"}"#,
                "lidar_mode",
            ),
            (
                r#"{"beam_altitude_angles": [1], "beam_azimuth_angles": ["x"], "lidar_mode": "1024x10"}"#,
                "beam_azimuth_angles",
            ),
            (
                r#"{"beam_altitude_angles": [1], "beam_azimuth_angles": [1], "lidar_mode": "1024x10", "udp_profile_lidar": "NEW_ONE"}"#,
                "udp_profile_lidar",
            ),
            (
                r#"{"beam_altitude_angles": [1], "beam_azimuth_angles": [1], "lidar_mode": "1024x10", "lidar_to_sensor_transform": [1,2]}"#,
                "lidar_to_sensor_transform",
            ),
            (r#"{"beam_altitude_angles": [1], "beam_azimuth_angles": [1], "lidar_mode": "9999x10"}"#, "file"),
        ];
        for (text, field) in cases {
            let e = parse(text).unwrap_err();
            assert_eq!(e.field, field, "{text}: {e}");
            assert!(e.to_string().starts_with("ouster metadata: "));
        }
    }
}
