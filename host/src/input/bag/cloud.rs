//! `sensor_msgs/PointCloud2` to [`ScanPoint`]s, through the message's own field table: any field
//! order, datatype, `point_step`, row padding and byte order.
//!
//! - **Position**: `x`, `y`, `z` (any numeric type), LiDAR frame, metres. Non-finite points (in
//!   `f32`, as the scan stores them), points at the origin (no return, as Ouster's organised
//!   clouds hold them) and points whose time field is not finite are skipped and counted.
//! - **Intensity**: `intensity` (Velodyne, Ouster) or else `reflectivity`, rounded and clamped to
//!   `u16`.
//! - **Row** from `ring`: Velodyne drivers number rings from the lowest beam, so
//!   `row = rows - 1 - ring`; Ouster drivers from the highest, so `row = ring` (row 0 is the
//!   highest beam, see [`RangeImageLayout`]). A cloud without `ring` gets the row of the beam
//!   nearest to each point's elevation ([`RangeImageLayout::row_of_elevation`]).
//! - **Column** from the azimuth `atan2(y, x)` with [`RangeImageLayout::column_of`].
//! - **Time**: `t` (Ouster, integer nanoseconds), `time` (Velodyne, float seconds) or
//!   `timestamp` (float seconds or integer nanoseconds, absolute or relative). Floats are taken
//!   as seconds and integers as nanoseconds; a value above 1e8 s is absolute. The scan starts
//!   at its earliest point: relative times are added to the header stamp (negative ones too, as
//!   drivers that stamp the last packet write them). If a time span is longer than two
//!   revolutions, milli-, micro- and nanosecond readings are tried in turn (with a warning).
//!   A cloud without a usable time field gets times from azimuth: the sensor turns clockwise at
//!   `scan_rate_hz` from the first point's azimuth.

use std::f64::consts::TAU;

use loglio_core::range_image::RangeImageLayout;
use loglio_core::scan::{NO_PIXEL, ScanPoint};

use super::msg::{PointCloud2, datatype};
use crate::config::{Config, SensorFamily};

/// How `ring` numbers beams.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RingOrder {
    /// Ring 0 is the lowest beam (Velodyne drivers).
    LowestFirst,
    /// Ring 0 is the highest beam (Ouster drivers).
    HighestFirst,
}

impl From<SensorFamily> for RingOrder {
    fn from(f: SensorFamily) -> Self {
        match f {
            SensorFamily::Velodyne => RingOrder::LowestFirst,
            SensorFamily::Ouster => RingOrder::HighestFirst,
        }
    }
}

/// How a cloud becomes scan points.
#[derive(Clone, Debug, PartialEq)]
pub struct CloudOptions {
    /// The range-image layout (rows must cover the cloud's rings).
    pub layout: RangeImageLayout,
    /// How the cloud's `ring` numbers beams.
    pub ring_order: RingOrder,
    /// Revolutions per second (for times from azimuth and the plausibility of time fields).
    pub scan_rate_hz: f64,
}

impl CloudOptions {
    /// The nominal layout, ring order and scan rate of a configuration.
    pub fn from_config(cfg: &Config) -> Result<Self, crate::config::ConfigError> {
        Ok(CloudOptions {
            layout: cfg.nominal_layout()?,
            ring_order: cfg.preset.family().into(),
            scan_rate_hz: cfg.sensor.scan_rate_hz,
        })
    }
}

/// Which fallbacks a cloud needed (so the caller can warn once per topic).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CloudNotes {
    /// No `ring` field: rows from elevation.
    pub rows_from_elevation: bool,
    /// No usable time field: times from azimuth.
    pub times_from_azimuth: bool,
    /// The time field was read in another unit than its type suggests (the unit's name).
    pub time_unit: Option<&'static str>,
    /// Why the time field was not used (if it exists but was unusable).
    pub time_field_problem: Option<&'static str>,
    /// Points whose ring is past the layout's rows (kept without a pixel).
    pub ring_out_of_range: u32,
}

/// The warnings a cloud's notes call for on `topic`, as (key, text): the caller says each key
/// once per run (the notes repeat on every cloud of a driver).
pub fn note_warnings(topic: &str, n: &CloudNotes, opt: &CloudOptions) -> Vec<(String, String)> {
    let mut out = Vec::new();
    if n.rows_from_elevation {
        out.push((
            format!("ring {topic}"),
            format!("{topic}: clouds have no `ring` field; rows are computed from each point's elevation (nearest beam of the layout)"),
        ));
    }
    if n.times_from_azimuth {
        let why = n.time_field_problem.map_or("no time field (t, time or timestamp)".to_string(), |p| {
            format!("its time field is unusable ({p})")
        });
        let hz = opt.scan_rate_hz;
        out.push((
            format!("time {topic}"),
            format!("{topic}: clouds have {why}; point times are computed from azimuth at {hz} Hz"),
        ));
    }
    if let Some(unit) = n.time_unit {
        out.push((
            format!("unit {topic}"),
            format!("{topic}: the point time field reads as {unit} (taken so)"),
        ));
    }
    if n.ring_out_of_range > 0 {
        let rows = opt.layout.rows();
        out.push((
            format!("rings {topic}"),
            format!(
                "{topic}: rings past the layout's {rows} rows (kept without a pixel); check the sensor preset"
            ),
        ));
    }
    out
}

/// A converted scan.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CloudScan {
    /// Absolute time of the scan start (its earliest point), ns.
    pub start_ns: u64,
    /// The points, in the cloud's order.
    pub points: Vec<ScanPoint>,
    /// Non-finite points and no-return points (at the origin), skipped.
    pub skipped: u32,
    /// Fallbacks used.
    pub notes: CloudNotes,
}

#[derive(Clone, Copy, Debug)]
struct Field {
    offset: usize,
    dt: u8,
}

fn find(c: &PointCloud2, name: &str) -> Result<Option<Field>, String> {
    let Some(f) = c.fields.iter().find(|f| f.name == name) else { return Ok(None) };
    let Some(size) = datatype::size(f.datatype) else {
        return Err(format!("field `{name}` has unknown datatype {}", f.datatype));
    };
    if f.offset as usize + size > c.point_step as usize {
        return Err(format!(
            "field `{name}` (offset {}, {size} bytes) overruns point_step {}",
            f.offset, c.point_step
        ));
    }
    Ok(Some(Field { offset: f.offset as usize, dt: f.datatype }))
}

fn read(p: &[u8], f: Field, be: bool) -> f64 {
    macro_rules! get {
        ($t:ty, $n:expr) => {{
            let mut b = [0u8; $n];
            b.copy_from_slice(&p[f.offset..f.offset + $n]);
            if be { <$t>::from_be_bytes(b) as f64 } else { <$t>::from_le_bytes(b) as f64 }
        }};
    }
    match f.dt {
        datatype::INT8 => p[f.offset] as i8 as f64,
        datatype::UINT8 => p[f.offset] as f64,
        datatype::INT16 => get!(i16, 2),
        datatype::UINT16 => get!(u16, 2),
        datatype::INT32 => get!(i32, 4),
        datatype::UINT32 => get!(u32, 4),
        datatype::FLOAT32 => get!(f32, 4),
        _ => get!(f64, 8),
    }
}

fn is_float(dt: u8) -> bool {
    dt == datatype::FLOAT32 || dt == datatype::FLOAT64
}

/// Converts one cloud. An error means the message is malformed (it is dropped whole).
pub fn cloud_to_scan(c: &PointCloud2, opt: &CloudOptions) -> Result<CloudScan, String> {
    let step = c.point_step as usize;
    let (w, h) = (c.width as usize, c.height as usize);
    if step == 0 && w * h > 0 {
        return Err("point_step is 0".into());
    }
    if w.saturating_mul(step) > c.row_step as usize {
        return Err(format!("row_step {} is shorter than width {w} x point_step {step}", c.row_step));
    }
    let need = (c.row_step as usize).saturating_mul(h);
    if c.data.len() < need {
        return Err(format!(
            "data holds {} bytes, row_step x height needs {need} (truncated cloud)",
            c.data.len()
        ));
    }
    let (Some(fx), Some(fy), Some(fz)) = (find(c, "x")?, find(c, "y")?, find(c, "z")?) else {
        return Err("no x, y, z fields".into());
    };
    let f_int = match find(c, "intensity")? {
        Some(f) => Some(f),
        None => find(c, "reflectivity")?,
    };
    let f_ring = find(c, "ring")?;
    let f_time = match find(c, "t")? {
        Some(f) => Some(f),
        None => match find(c, "time")? {
            Some(f) => Some(f),
            None => find(c, "timestamp")?,
        },
    };
    let be = c.is_bigendian;
    let layout = &opt.layout;
    let rows = layout.rows();
    let mut notes = CloudNotes { rows_from_elevation: f_ring.is_none(), ..Default::default() };
    let mut points = Vec::with_capacity(w * h);
    let mut raw_t = Vec::with_capacity(if f_time.is_some() { w * h } else { 0 });
    let mut azimuths = Vec::with_capacity(w * h);
    let mut skipped = 0u32;
    for r in 0..h {
        let row_bytes = &c.data[r * c.row_step as usize..];
        for i in 0..w {
            let p = &row_bytes[i * step..(i + 1) * step];
            let (x, y, z) = (read(p, fx, be), read(p, fy, be), read(p, fz, be));
            // Finite as the f32 the scan stores: a float64 field past f32's range would become
            // an infinite point.
            let xyz = [x as f32, y as f32, z as f32];
            // A point whose time is not a number is as broken as one without a position.
            let raw_time = f_time.map(|f| read(p, f, be));
            if !xyz.iter().all(|v| v.is_finite())
                || x * x + y * y + z * z < 1e-6
                || raw_time.is_some_and(|t| !t.is_finite())
            {
                skipped += 1;
                continue;
            }
            let az = y.atan2(x);
            let row = match f_ring {
                Some(f) => {
                    let ring = read(p, f, be);
                    if ring >= 0.0 && (ring as usize) < rows {
                        let ring = ring as usize;
                        Some(match opt.ring_order {
                            RingOrder::LowestFirst => rows - 1 - ring,
                            RingOrder::HighestFirst => ring,
                        })
                    } else {
                        notes.ring_out_of_range += 1;
                        None
                    }
                }
                None => {
                    let el = z.atan2((x * x + y * y).sqrt()) as f32;
                    layout.row_of_elevation(el).map(usize::from)
                }
            };
            let (row, col) = match row {
                Some(r) => (r as u16, layout.column_of(r, az)),
                None => (NO_PIXEL, NO_PIXEL),
            };
            let intensity = f_int.map_or(0.0, |f| read(p, f, be));
            let intensity =
                if intensity.is_finite() { intensity.round().clamp(0.0, 65535.0) as u16 } else { 0 };
            if let Some(t) = raw_time {
                raw_t.push(t);
            }
            azimuths.push(az);
            points.push(ScanPoint { xyz, t: 0.0, row, col, intensity, ret: 0, flags: 0 });
        }
    }
    let period = 1.0 / opt.scan_rate_hz.max(1e-3);
    // Times from the field, if it is usable.
    let mut start_ns = c.stamp_ns;
    let mut times: Option<Vec<f64>> = None;
    if let (Some(f), false) = (f_time, raw_t.is_empty()) {
        let (lo, hi) = raw_t.iter().fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        // Natural unit: seconds for floats, nanoseconds for integers; then the others.
        let candidates: &[(f64, Option<&'static str>)] = if is_float(f.dt) {
            &[
                (1.0, None),
                (1e-3, Some("milliseconds")),
                (1e-6, Some("microseconds")),
                (1e-9, Some("nanoseconds")),
            ]
        } else {
            &[(1e-9, None), (1e-6, Some("microseconds")), (1e-3, Some("milliseconds"))]
        };
        // Every value is finite (points with another are skipped above).
        if hi == lo && points.len() > 1 {
            notes.time_field_problem = Some("all values equal");
        } else if let Some(&(scale, name)) = candidates.iter().find(|(s, _)| (hi - lo) * s <= 2.0 * period) {
            notes.time_unit = name;
            let lo_s = lo * scale;
            let absolute = lo_s.abs() > 1e8;
            start_ns = if absolute {
                // Whole seconds and the fraction apart: f64 nanoseconds since 1970 would lose
                // hundreds of them.
                let secs = lo_s.floor();
                (secs as u64)
                    .saturating_mul(1_000_000_000)
                    .saturating_add(((lo_s - secs) * 1e9).round() as u64)
            } else {
                let off = (lo_s * 1e9).round() as i128;
                (c.stamp_ns as i128 + off).clamp(0, u64::MAX as i128) as u64
            };
            times = Some(raw_t.iter().map(|v| (v - lo) * scale).collect());
        } else {
            notes.time_field_problem = Some("its span is longer than two revolutions in any unit");
        }
    }
    match times {
        Some(t) => {
            for (p, t) in points.iter_mut().zip(t) {
                p.t = t as f32;
            }
        }
        None => {
            notes.times_from_azimuth = true;
            times_from_azimuth(&mut points, &azimuths, period);
        }
    }
    Ok(CloudScan { start_ns, points, skipped, notes })
}

/// Point times from azimuth: the sensor turns clockwise, once per `period`, starting at the
/// first point's azimuth. The angle turned is unwrapped along the point order, so a point a
/// little before the start (a beam with an azimuth offset) is at time 0, not at the end, and a
/// sweep that overlaps its start runs past `period`. Clouds stored beam by beam (organised
/// clouds, or ring-major lists: rows change at under a quarter of the points) start over at
/// each new row;
/// clouds in firing order unwrap continuously.
fn times_from_azimuth(points: &mut [ScanPoint], azimuths: &[f64], period: f64) {
    let Some(&a0) = azimuths.first() else { return };
    let rows_of = |p: &ScanPoint| (p.row != NO_PIXEL).then_some(p.row);
    let with_row: Vec<u16> = points.iter().filter_map(rows_of).collect();
    let changes = with_row.windows(2).filter(|w| w[0] != w[1]).count();
    // Firing order changes row at nearly every point; beam by beam once per beam.
    let beam_by_beam = changes * 4 <= with_row.len();
    let mut prev = 0.0f64;
    let mut row = None;
    for (p, az) in points.iter_mut().zip(azimuths) {
        if beam_by_beam && rows_of(p).is_some() && rows_of(p) != row {
            row = rows_of(p);
            prev = 0.0;
        }
        // Clockwise: the azimuth decreases with time.
        let raw = (a0 - az).rem_euclid(TAU);
        let turned = [raw - TAU, raw, raw + TAU]
            .into_iter()
            .min_by(|a, b| (a - prev).abs().total_cmp(&(b - prev).abs()))
            .unwrap_or(raw);
        prev = turned;
        p.t = (turned.max(0.0) / TAU * period) as f32;
    }
}

/// Helpers to build clouds (tests, simulated sequences for peer odometries).
pub mod build {
    use super::super::msg::{PointCloud2, PointField, datatype};

    /// One field of a cloud to build: name, datatype, and the value of a point.
    #[derive(Clone, Copy, Debug)]
    pub struct FieldSpec {
        /// Field name.
        pub name: &'static str,
        /// One of [`datatype`].
        pub datatype: u8,
    }

    /// The Velodyne driver's layout: x y z intensity (f32), ring (u16), time (f32 s), 22 bytes
    /// padded to 32 as velodyne_pointcloud does.
    pub const VELODYNE: &[FieldSpec] = &[
        FieldSpec { name: "x", datatype: datatype::FLOAT32 },
        FieldSpec { name: "y", datatype: datatype::FLOAT32 },
        FieldSpec { name: "z", datatype: datatype::FLOAT32 },
        FieldSpec { name: "intensity", datatype: datatype::FLOAT32 },
        FieldSpec { name: "ring", datatype: datatype::UINT16 },
        FieldSpec { name: "time", datatype: datatype::FLOAT32 },
    ];

    /// The Ouster driver's layout: x y z intensity (f32), t (u32 ns), reflectivity (u16),
    /// ring (u8), ambient (u16), range (u32).
    pub const OUSTER: &[FieldSpec] = &[
        FieldSpec { name: "x", datatype: datatype::FLOAT32 },
        FieldSpec { name: "y", datatype: datatype::FLOAT32 },
        FieldSpec { name: "z", datatype: datatype::FLOAT32 },
        FieldSpec { name: "intensity", datatype: datatype::FLOAT32 },
        FieldSpec { name: "t", datatype: datatype::UINT32 },
        FieldSpec { name: "reflectivity", datatype: datatype::UINT16 },
        FieldSpec { name: "ring", datatype: datatype::UINT8 },
        FieldSpec { name: "ambient", datatype: datatype::UINT16 },
        FieldSpec { name: "range", datatype: datatype::UINT32 },
    ];

    /// x, y, z only (f32).
    pub const XYZ: &[FieldSpec] = &[
        FieldSpec { name: "x", datatype: datatype::FLOAT32 },
        FieldSpec { name: "y", datatype: datatype::FLOAT32 },
        FieldSpec { name: "z", datatype: datatype::FLOAT32 },
    ];

    fn put(out: &mut [u8], dt: u8, v: f64, be: bool) {
        macro_rules! w {
            ($t:ty) => {{
                let x = v as $t;
                let b = if be { x.to_be_bytes() } else { x.to_le_bytes() };
                out[..b.len()].copy_from_slice(&b);
            }};
        }
        match dt {
            datatype::INT8 => w!(i8),
            datatype::UINT8 => w!(u8),
            datatype::INT16 => w!(i16),
            datatype::UINT16 => w!(u16),
            datatype::INT32 => w!(i32),
            datatype::UINT32 => w!(u32),
            datatype::FLOAT32 => w!(f32),
            _ => w!(f64),
        }
    }

    /// Builds a cloud of `height` x `width` points with the given fields packed in order (each
    /// at its natural size, the point padded to `point_step` if larger), from `value(point,
    /// field name)`.
    #[allow(clippy::too_many_arguments)] // a flat builder reads best at the call sites
    pub fn cloud(
        stamp_ns: u64,
        frame_id: &str,
        fields: &[FieldSpec],
        height: u32,
        width: u32,
        point_step: Option<u32>,
        big_endian: bool,
        mut value: impl FnMut(usize, &str) -> f64,
    ) -> PointCloud2 {
        let mut table = Vec::new();
        let mut off = 0u32;
        for f in fields {
            table.push(PointField { name: f.name.into(), offset: off, datatype: f.datatype, count: 1 });
            off += datatype::size(f.datatype).unwrap_or(1) as u32;
        }
        let step = point_step.unwrap_or(off).max(off);
        let n = (height * width) as usize;
        let mut data = vec![0u8; n * step as usize];
        for i in 0..n {
            for (f, t) in fields.iter().zip(&table) {
                let at = i * step as usize + t.offset as usize;
                put(&mut data[at..], f.datatype, value(i, f.name), big_endian);
            }
        }
        PointCloud2 {
            stamp_ns,
            frame_id: frame_id.into(),
            height,
            width,
            fields: table,
            is_bigendian: big_endian,
            point_step: step,
            row_step: step * width,
            data,
            is_dense: true,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::build::{OUSTER, VELODYNE, XYZ, cloud};
    use super::*;
    use crate::config::Preset;

    fn opts(p: Preset) -> CloudOptions {
        CloudOptions::from_config(&Config::preset(p)).unwrap()
    }

    /// A VLP-16-like scan: 16 rings x 90 azimuth steps clockwise from +x, 10 m range, times
    /// over 0.1 s.
    fn velodyne_points() -> Vec<(f64, f64, f64, u16, f64)> {
        let el = Preset::Vlp16.nominal_elevations_deg();
        let mut v = Vec::new();
        for k in 0..90 {
            let az = -(k as f64) * 4.0f64.to_radians();
            for ring in 0..16u16 {
                // ring 0 lowest: row 15.
                let e = el[15 - ring as usize].to_radians();
                let t = k as f64 / 90.0 * 0.1 - 0.05;
                v.push((10.0 * e.cos() * az.cos(), 10.0 * e.cos() * az.sin(), 10.0 * e.sin(), ring, t));
            }
        }
        v
    }

    #[test]
    fn velodyne_fields_give_rows_columns_and_times() {
        let pts = velodyne_points();
        let c =
            cloud(
                1_000_000_000,
                "velodyne",
                VELODYNE,
                1,
                pts.len() as u32,
                Some(32),
                false,
                |i, f| match f {
                    "x" => pts[i].0,
                    "y" => pts[i].1,
                    "z" => pts[i].2,
                    "intensity" => 17.4,
                    "ring" => pts[i].3 as f64,
                    _ => pts[i].4,
                },
            );
        let s = cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap();
        assert_eq!(s.points.len(), pts.len());
        // Negative relative times: the scan starts 50 ms (as an f32) before the header stamp.
        assert_eq!(s.start_ns as i64, 1_000_000_000 + (f64::from(-0.05f32) * 1e9).round() as i64);
        assert_eq!(s.notes, CloudNotes::default());
        for (p, q) in s.points.iter().zip(&pts) {
            assert_eq!(p.row, 15 - q.3);
            assert!((p.t as f64 - (q.4 + 0.05)).abs() < 1e-6);
            assert_eq!(p.intensity, 17);
        }
        // 1800 columns clockwise: 4 degrees = 20 columns per step.
        assert_eq!(s.points[16].col, 20);
        assert_eq!(s.points[16 * 45].col, 900);
    }

    #[test]
    fn ouster_fields_and_organised_no_return_points() {
        // 16 rows x 64 columns, ring 0 at the top, t in ns, a no-return point (zeros) per row.
        let el = Preset::Os1_16.nominal_elevations_deg();
        let (rows, cols) = (16usize, 64usize);
        let c = cloud(5_000_000_000, "os_sensor", OUSTER, rows as u32, cols as u32, None, false, |i, f| {
            let (r, k) = (i / cols, i % cols);
            let az = -(k as f64) * TAU / cols as f64;
            let e = el[r].to_radians();
            let rng = if k == 7 { 0.0 } else { 20.0 };
            match f {
                "x" => rng * e.cos() * az.cos(),
                "y" => rng * e.cos() * az.sin(),
                "z" => rng * e.sin(),
                "intensity" => 100.0,
                "t" => (k as f64) * 1_562_500.0,
                "reflectivity" => 5.0,
                "ring" => r as f64,
                _ => 0.0,
            }
        });
        let mut o = opts(Preset::Os1_16);
        o.layout = Preset::Os1_16.nominal_layout(64).unwrap();
        let s = cloud_to_scan(&c, &o).unwrap();
        assert_eq!(s.skipped, 16);
        assert_eq!(s.points.len(), 16 * 63);
        assert_eq!(s.start_ns, 5_000_000_000);
        let p = s.points[63 + 8]; // row 1, column 9 (column 7 skipped)
        assert_eq!((p.row, p.col), (1, 9));
        assert!((p.t - 9.0 * 0.0015625).abs() < 1e-7);
    }

    #[test]
    fn missing_ring_and_time_fall_back_to_geometry() {
        let pts = velodyne_points();
        let c = cloud(2_000_000_000, "velodyne", XYZ, 1, pts.len() as u32, None, true, |i, f| match f {
            "x" => pts[i].0,
            "y" => pts[i].1,
            _ => pts[i].2,
        });
        let s = cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap();
        assert!(s.notes.rows_from_elevation && s.notes.times_from_azimuth);
        assert_eq!(s.start_ns, 2_000_000_000);
        for (p, q) in s.points.iter().zip(&pts) {
            assert_eq!(p.row, 15 - q.3, "row from elevation");
            // Azimuth time: 4 degrees per step at 10 Hz.
            assert!((p.t as f64 - (q.4 + 0.05)).abs() < 1e-6, "{} vs {}", p.t, q.4 + 0.05);
        }
    }

    #[test]
    fn time_units_are_detected_and_absolute_stamps_used() {
        let pts = velodyne_points();
        // Microseconds in a float field (as some drivers write): detected, noted.
        let c = cloud(1_000_000_000, "v", VELODYNE, 1, pts.len() as u32, None, false, |i, f| match f {
            "x" => pts[i].0,
            "y" => pts[i].1,
            "z" => pts[i].2,
            "ring" => pts[i].3 as f64,
            "time" => (pts[i].4 + 0.05) * 1e6,
            _ => 0.0,
        });
        let s = cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap();
        assert_eq!(s.notes.time_unit, Some("microseconds"));
        assert!((s.points.last().unwrap().t - 89.0 / 900.0).abs() < 1e-6);
        // Absolute float seconds in `timestamp` (f64).
        let fields =
            [XYZ[0], XYZ[1], XYZ[2], build::FieldSpec { name: "timestamp", datatype: datatype::FLOAT64 }];
        let c = cloud(7, "v", &fields, 1, 3, None, false, |i, f| match f {
            "timestamp" => 1_700_000_000.25 + i as f64 * 0.01,
            "x" => 1.0,
            _ => 0.5,
        });
        let s = cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap();
        assert_eq!(s.start_ns, 1_700_000_000_250_000_000);
        assert!((s.points[2].t - 0.02).abs() < 1e-6);
        // All-zero times fall back to azimuth.
        let c = cloud(7, "v", VELODYNE, 1, 3, None, false, |i, f| match f {
            "x" => 1.0,
            "y" => i as f64,
            _ => 0.0,
        });
        let s = cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap();
        assert!(s.notes.times_from_azimuth);
        assert_eq!(s.notes.time_field_problem, Some("all values equal"));
    }

    /// Found by the `bag_messages` and `bag_file` fuzz targets: a float64 coordinate past f32's
    /// range became an infinite point, and one point's NaN time (the time span is taken over
    /// the others) a NaN point time. Both points are now skipped and counted; the rest of the
    /// cloud is kept with the times of its own field.
    #[test]
    fn points_out_of_f32_range_or_with_a_nan_time_are_skipped() {
        let fields = [
            build::FieldSpec { name: "x", datatype: datatype::FLOAT64 },
            build::FieldSpec { name: "y", datatype: datatype::FLOAT64 },
            build::FieldSpec { name: "z", datatype: datatype::FLOAT64 },
            build::FieldSpec { name: "time", datatype: datatype::FLOAT32 },
        ];
        let c = cloud(7, "v", &fields, 1, 5, None, false, |i, f| match (i, f) {
            (1, "z") => -1e39,
            (3, "time") => f64::NAN,
            (_, "time") => i as f64 * 0.01,
            (_, "x") => 2.0,
            (_, "y") => i as f64,
            _ => 0.5,
        });
        let s = cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap();
        assert_eq!(s.skipped, 2);
        assert_eq!(s.points.len(), 3);
        assert!(!s.notes.times_from_azimuth);
        for (p, (y, t)) in s.points.iter().zip([(0.0, 0.0), (2.0, 0.02), (4.0, 0.04)]) {
            assert!(p.xyz.iter().all(|v| v.is_finite()), "{p:?}");
            assert_eq!(p.xyz[1], y);
            assert!((p.t - t).abs() < 1e-6, "{p:?}");
        }
    }

    #[test]
    fn malformed_clouds_are_errors() {
        let good = cloud(0, "v", XYZ, 1, 4, None, false, |_, _| 1.0);
        let mut c = good.clone();
        c.data.truncate(40);
        assert_eq!(
            cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap_err(),
            "data holds 40 bytes, row_step x height needs 48 (truncated cloud)"
        );
        let mut c = good.clone();
        c.fields[2].offset = 10;
        assert_eq!(
            cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap_err(),
            "field `z` (offset 10, 4 bytes) overruns point_step 12"
        );
        let mut c = good.clone();
        c.fields.pop();
        assert_eq!(cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap_err(), "no x, y, z fields");
        let mut c = good.clone();
        c.row_step = 8;
        assert_eq!(
            cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap_err(),
            "row_step 8 is shorter than width 4 x point_step 12"
        );
        let mut c = good;
        c.fields[0].datatype = 9;
        assert_eq!(cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap_err(), "field `x` has unknown datatype 9");
    }

    #[test]
    fn azimuth_times_unwrap_beam_offsets_and_overlap() {
        let deg = |d: f64| d.to_radians();
        let mk = |az: &[f64], rows: &[u16]| -> Vec<ScanPoint> {
            az.iter().zip(rows).map(|(_, &r)| ScanPoint { row: r, ..Default::default() }).collect()
        };
        // Firing order (rows change every point): the second beam fires 2 degrees before the
        // first's azimuth (counter-clockwise of it), the sweep ends 1 degree past its start.
        let az = [deg(10.0), deg(12.0), deg(-80.0), deg(-170.0), deg(100.0), deg(11.0), deg(9.0)];
        let rows = [0, 1, 0, 1, 0, 1, 0];
        let mut p = mk(&az, &rows);
        times_from_azimuth(&mut p, &az, 0.1);
        let t: Vec<f64> = p.iter().map(|p| p.t as f64).collect();
        let want = [0.0, 0.0, 0.025, 0.05, 0.075, 359.0 / 3600.0, 361.0 / 3600.0];
        for (a, b) in t.iter().zip(want) {
            assert!((a - b).abs() < 1e-6, "{t:?}");
        }
        // Beam by beam (two rows, each a full sweep): each row starts over.
        let az =
            [deg(10.0), deg(-80.0), deg(-170.0), deg(100.0), deg(12.0), deg(-80.0), deg(-170.0), deg(100.0)];
        let rows = [0, 0, 0, 0, 1, 1, 1, 1];
        let mut p = mk(&az, &rows);
        times_from_azimuth(&mut p, &az, 0.1);
        let t: Vec<f64> = p.iter().map(|p| p.t as f64).collect();
        let want = [0.0, 0.025, 0.05, 0.075, 0.0, 0.025, 0.05, 0.075];
        for (a, b) in t.iter().zip(want) {
            assert!((a - b).abs() < 1e-6, "{t:?}");
        }
    }

    #[test]
    fn rings_past_the_layout_keep_the_point_without_a_pixel() {
        let c = cloud(0, "v", VELODYNE, 1, 2, None, false, |i, f| match f {
            "x" => 5.0,
            "ring" => [3.0, 40.0][i],
            "time" => i as f64 * 0.01,
            _ => 0.0,
        });
        let s = cloud_to_scan(&c, &opts(Preset::Vlp16)).unwrap();
        assert_eq!(s.notes.ring_out_of_range, 1);
        assert_eq!((s.points[1].row, s.points[1].col), (NO_PIXEL, NO_PIXEL));
        assert_eq!(s.points[0].row, 12);
    }
}
