//! `loglio normals`: Ring FALS on a real capture (by default the bundled Ouster OS-1-32-G frame
//! decoded by the vendor SDK, `tests/data/ouster-sdk`), timed, and compared with kNN-PCA normals
//! on the planar parts of the scene.
//!
//! The input is the vendor SDK's reference decode: the sensor metadata JSON and the frame's
//! `xyz_m.f32le.bin` (rows x columns x 3 float32 metres in the sensor frame, staggered columns).
//! [`load_ouster_reference`] turns it into what the core expects: points in the LiDAR frame with
//! their range-image row (beam, 0 = highest) and destaggered column, and the matching
//! [`RangeImageLayout`] built from the beam intrinsics.

use std::path::PathBuf;
use std::sync::Mutex;
use std::time::Instant;

use anyhow::{Context, anyhow, bail, ensure};
use loglio_core::range_image::RangeImageLayout;
use loglio_core::ring_fals::{
    PointNormal, RingFals, RingFals128x2048, RingFalsConfig, RingFalsStats, RingTable,
};
use loglio_core::scan::ScanPoint;
use serde_json::Value;

use crate::knn_pca::{PcaNormal, knn_pca_normals};

/// The bundled capture's name, metadata and xyz decode.
pub const BUNDLED_NAME: &str = "OS-1-32-G_v2.1.1_1024x10 frame 0 (ouster-sdk test capture)";
/// Metadata of the bundled capture.
pub const BUNDLED_METADATA: &str =
    include_str!("../../../tests/data/ouster-sdk/OS-1-32-G_v2.1.1_1024x10.json");
/// The SDK's xyz decode of the bundled capture.
pub const BUNDLED_XYZ: &[u8] = include_bytes!(
    "../../../tests/data/ouster-sdk/ref-ouster-sdk/OS-1-32-G_v2.1.1_1024x10.frame0.xyz_m.f32le.bin"
);

/// `loglio normals` arguments.
#[derive(Debug, clap::Args)]
pub struct NormalsArgs {
    /// Ouster sensor metadata JSON (default: the bundled OS-1-32-G capture).
    #[arg(long, requires = "xyz")]
    pub metadata: Option<PathBuf>,
    /// The SDK's xyz decode of one frame: rows x columns x 3 float32 little-endian metres, sensor
    /// frame, staggered columns.
    #[arg(long, requires = "metadata")]
    pub xyz: Option<PathBuf>,
    /// Neighbours of the kNN-PCA comparison.
    #[arg(long, default_value_t = 10)]
    pub k: usize,
    /// A point is planar for the comparison when PCA's smallest eigenvalue is at most this
    /// fraction of the middle one...
    #[arg(long, default_value_t = PLANARITY)]
    pub planarity: f64,
    /// ... and the middle one at least this fraction of the largest.
    #[arg(long, default_value_t = SPREAD)]
    pub spread: f64,
    /// Timed repetitions of Ring FALS (the median is printed).
    #[arg(long, default_value_t = 50)]
    pub repeat: usize,
}

/// Default planarity ratio of the comparison.
pub const PLANARITY: f64 = 0.01;
/// Default two-direction spread of the comparison.
pub const SPREAD: f64 = 0.1;

/// One frame of an Ouster capture, ready for the core.
#[derive(Debug, Clone)]
pub struct OusterFrame {
    /// The range-image layout from the beam intrinsics (LiDAR frame, destaggered columns).
    pub layout: RangeImageLayout,
    /// Every pixel's point (also those without a return, at the origin), in the LiDAR frame, in
    /// the file's order (row-major over beams and measurement ids).
    pub points: Vec<ScanPoint>,
}

/// A number or list from the metadata, in the legacy flat layout or the v2 nested one.
fn field<'a>(meta: &'a Value, paths: &[&[&str]]) -> Option<&'a Value> {
    paths.iter().find_map(|p| p.iter().try_fold(meta, |v, k| v.get(k)))
}

fn numbers(v: &Value, what: &str) -> anyhow::Result<Vec<f64>> {
    v.as_array()
        .ok_or_else(|| anyhow!("metadata: {what} is not a list"))?
        .iter()
        .map(|x| x.as_f64().ok_or_else(|| anyhow!("metadata: {what} holds a non-number")))
        .collect()
}

/// Reads the SDK's reference decode of one frame (see the module docs).
pub fn load_ouster_reference(metadata: &str, xyz: &[u8]) -> anyhow::Result<OusterFrame> {
    let meta: Value = serde_json::from_str(metadata).context("metadata is not JSON")?;
    let alt = numbers(
        field(&meta, &[&["beam_altitude_angles"], &["beam_intrinsics", "beam_altitude_angles"]])
            .ok_or_else(|| anyhow!("metadata: no beam_altitude_angles"))?,
        "beam_altitude_angles",
    )?;
    let az = numbers(
        field(&meta, &[&["beam_azimuth_angles"], &["beam_intrinsics", "beam_azimuth_angles"]])
            .ok_or_else(|| anyhow!("metadata: no beam_azimuth_angles"))?,
        "beam_azimuth_angles",
    )?;
    let rows = alt.len();
    ensure!(rows > 0 && az.len() == rows, "metadata: {} altitudes but {} azimuths", rows, az.len());
    let cols =
        field(&meta, &[&["data_format", "columns_per_frame"], &["lidar_data_format", "columns_per_frame"]])
            .and_then(Value::as_u64)
            .ok_or_else(|| anyhow!("metadata: no columns_per_frame"))? as usize;
    ensure!(cols > 0, "metadata: zero columns");
    let deg = |d: f64| d.to_radians();
    // Destagger shift per row: the metadata's, or from the beam azimuths (the shift that brings
    // every beam to the azimuth of the beam most to the right).
    let shift: Vec<i64> = match field(
        &meta,
        &[&["data_format", "pixel_shift_by_row"], &["lidar_data_format", "pixel_shift_by_row"]],
    ) {
        Some(v) => numbers(v, "pixel_shift_by_row")?.iter().map(|&s| s as i64).collect(),
        None => {
            let min = az.iter().cloned().fold(f64::INFINITY, f64::min);
            az.iter().map(|&a| ((a - min) * cols as f64 / 360.0).round() as i64).collect()
        }
    };
    ensure!(shift.len() == rows, "metadata: pixel_shift_by_row has {} entries for {rows} rows", shift.len());
    let t = numbers(
        field(&meta, &[&["lidar_to_sensor_transform"], &["lidar_intrinsics", "lidar_to_sensor_transform"]])
            .ok_or_else(|| anyhow!("metadata: no lidar_to_sensor_transform"))?,
        "lidar_to_sensor_transform",
    )?;
    ensure!(t.len() == 16, "metadata: lidar_to_sensor_transform must have 16 numbers");

    // The layout: pixel (row, destaggered col) has measurement id m = col - shift, and looks at
    // azimuth 2 pi (1 - m / cols) - beam_azimuth, i.e. azimuth0 = 2 pi shift / cols - beam_azimuth
    // with columns advancing clockwise.
    let mut layout = RangeImageLayout::new(rows, cols, true).map_err(|e| anyhow!("layout: {e}"))?;
    for r in 0..rows {
        let az0 = std::f64::consts::TAU * shift[r] as f64 / cols as f64 - deg(az[r]);
        layout.set_row(r, deg(alt[r]) as f32, az0 as f32).map_err(|e| anyhow!("layout row {r}: {e}"))?;
    }

    ensure!(
        xyz.len() == rows * cols * 12,
        "xyz file has {} bytes, expected {rows} x {cols} x 3 x 4",
        xyz.len()
    );
    // Sensor frame -> LiDAR frame: p_l = R^T (p_s - t), translation in millimetres.
    let rot = [[t[0], t[1], t[2]], [t[4], t[5], t[6]], [t[8], t[9], t[10]]];
    let tr = [t[3] / 1000.0, t[7] / 1000.0, t[11] / 1000.0];
    let frame_s = field(&meta, &[&["lidar_mode"], &["config_params", "lidar_mode"]])
        .and_then(Value::as_str)
        .and_then(|m| m.split('x').nth(1))
        .and_then(|hz| hz.parse::<f64>().ok())
        .map_or(0.1, |hz| 1.0 / hz);
    let mut points = Vec::with_capacity(rows * cols);
    for (i, c) in xyz.chunks_exact(12).enumerate() {
        let (r, m) = (i / cols, i % cols);
        let s: [f64; 3] =
            std::array::from_fn(|k| f32::from_le_bytes(c[4 * k..4 * k + 4].try_into().unwrap()) as f64);
        let d = [s[0] - tr[0], s[1] - tr[1], s[2] - tr[2]];
        let p: [f32; 3] =
            std::array::from_fn(|k| (rot[0][k] * d[0] + rot[1][k] * d[1] + rot[2][k] * d[2]) as f32);
        // A pixel without a return decodes to the sensor origin: keep it at the LiDAR origin.
        let p = if s == [0.0; 3] { [0.0; 3] } else { p };
        let col = (m as i64 + shift[r]).rem_euclid(cols as i64) as u16;
        points.push(ScanPoint {
            xyz: p,
            t: (m as f64 / cols as f64 * frame_s) as f32,
            row: r as u16,
            col,
            ..Default::default()
        });
    }
    Ok(OusterFrame { layout, points })
}

/// The bundled capture.
pub fn bundled() -> OusterFrame {
    load_ouster_reference(BUNDLED_METADATA, BUNDLED_XYZ).expect("the bundled capture loads")
}

/// How Ring FALS agrees with kNN-PCA on the planar points of a scan.
#[derive(Debug, Clone, PartialEq)]
pub struct Agreement {
    /// Points with a return (both estimators had a chance).
    pub points: usize,
    /// Of those, planar by PCA's eigenvalues.
    pub planar: usize,
    /// Of the planar ones, with a valid Ring FALS normal (the compared set).
    pub compared: usize,
    /// Median and 90th percentile of the angle between the two normals, degrees.
    pub median_deg: f64,
    /// 90th percentile, degrees.
    pub p90_deg: f64,
}

/// Compares Ring FALS normals with PCA normals on the points PCA finds planar (see
/// [`PcaNormal::is_planar`]).
pub fn agreement(
    points: &[ScanPoint],
    ours: &[PointNormal],
    pca: &[Option<PcaNormal>],
    planarity: f64,
    spread: f64,
) -> Agreement {
    let mut angles = Vec::new();
    let (mut n, mut planar) = (0, 0);
    for i in 0..points.len() {
        let Some(p) = pca[i] else { continue };
        n += 1;
        if !p.is_planar(planarity, spread) {
            continue;
        }
        planar += 1;
        if let Some(v) = ours[i].get() {
            let c = v[0] as f64 * p.normal[0] + v[1] as f64 * p.normal[1] + v[2] as f64 * p.normal[2];
            angles.push(c.clamp(-1.0, 1.0).acos().to_degrees());
        }
    }
    angles.sort_by(f64::total_cmp);
    let q =
        |f: f64| if angles.is_empty() { f64::NAN } else { angles[((angles.len() - 1) as f64 * f) as usize] };
    Agreement { points: n, planar, compared: angles.len(), median_deg: q(0.5), p90_deg: q(0.9) }
}

/// Storage for up to 128 x 2048, in a static so that its 9 MB never touch the stack.
static FALS: Mutex<RingFals128x2048> = Mutex::new(RingFals::new());

/// Ring FALS and kNN-PCA normals of one frame.
#[derive(Debug, Clone)]
pub struct Estimates {
    /// Ring FALS normal of every point.
    pub normals: Vec<PointNormal>,
    /// Ring FALS statistics.
    pub stats: RingFalsStats,
    /// Ring FALS time per scan, milliseconds (median of the repetitions).
    pub ms: f64,
    /// kNN-PCA normal of every point with a return.
    pub pca: Vec<Option<PcaNormal>>,
    /// kNN-PCA time (tree build included), milliseconds, one run.
    pub pca_ms: f64,
}

/// Ring FALS (timed over `repeat` runs) and kNN-PCA normals of a frame.
pub fn estimate(frame: &OusterFrame, k: usize, repeat: usize) -> anyhow::Result<Estimates> {
    let mut table = RingTable::new();
    table.build(&frame.layout, &RingFalsConfig::DEFAULT).map_err(|e| anyhow!("{e}"))?;
    let mut fals = FALS.lock().map_err(|_| anyhow!("storage lock poisoned"))?;
    let mut out = vec![PointNormal::INVALID; frame.points.len()];
    let mut times = Vec::new();
    let mut stats = RingFalsStats::default();
    for _ in 0..repeat.max(1) {
        let t0 = Instant::now();
        stats = fals.estimate(&table, &frame.points, &mut out).map_err(|e| anyhow!("{e}"))?;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    // PCA on the points with a return (the others sit at the origin).
    let with_return: Vec<usize> =
        (0..frame.points.len()).filter(|&i| frame.points[i].range() > 0.3).collect();
    let xyz: Vec<[f32; 3]> = with_return.iter().map(|&i| frame.points[i].xyz).collect();
    let t0 = Instant::now();
    let pca_sub = knn_pca_normals(&xyz, k).map_err(|e| anyhow!(e))?;
    let pca_ms = t0.elapsed().as_secs_f64() * 1e3;
    let mut pca = vec![None; frame.points.len()];
    for (j, &i) in with_return.iter().enumerate() {
        pca[i] = pca_sub[j];
    }
    Ok(Estimates { normals: out, stats, ms: times[times.len() / 2], pca, pca_ms })
}

/// `loglio normals`.
pub fn run(args: &NormalsArgs) -> anyhow::Result<()> {
    let (name, frame) = match (&args.metadata, &args.xyz) {
        (Some(m), Some(x)) => {
            let meta = std::fs::read_to_string(m).with_context(|| format!("reading {}", m.display()))?;
            let xyz = std::fs::read(x).with_context(|| format!("reading {}", x.display()))?;
            (x.display().to_string(), load_ouster_reference(&meta, &xyz)?)
        }
        (None, None) => (BUNDLED_NAME.to_string(), bundled()),
        _ => bail!("give both --metadata and --xyz, or neither"),
    };
    let Estimates { normals: out, stats: st, ms, pca, pca_ms } = estimate(&frame, args.k, args.repeat)?;
    let ag = agreement(&frame.points, &out, &pca, args.planarity, args.spread);
    let l = &frame.layout;
    println!("Ring FALS normals of {name}");
    println!("  layout        {} rows x {} columns ({} pixels)", l.rows(), l.cols(), l.pixels());
    println!(
        "  points        {} ({} with a pixel and a usable range, {} filtered ranges, {} without pixel)",
        st.points, st.projected, st.rejected_range, st.no_pixel
    );
    println!(
        "  valid normals {} of {} returns ({:.1} %); {} from incomplete windows, {} trimmed; {} pixels invalid",
        st.valid_points,
        st.projected,
        100.0 * st.valid_points as f64 / st.projected.max(1) as f64,
        st.gap_solves,
        st.trimmed_solves,
        st.invalid_pixels
    );
    println!("  time          {ms:.2} ms per scan (median of {} runs, one thread)", args.repeat.max(1));
    println!(
        "  kNN-PCA       k = {}: {pca_ms:.1} ms ({:.0}x the Ring FALS time)",
        args.k,
        pca_ms / ms.max(1e-9)
    );
    println!(
        "  agreement     {} planar points (lambda_min <= {} lambda_mid, lambda_mid >= {} lambda_max) with both normals: median {:.2} deg, 90 % within {:.2} deg",
        ag.compared, args.planarity, args.spread, ag.median_deg, ag.p90_deg
    );
    println!(
        "                (k = 10 PCA is itself noisy on a 32-beam scan: try --k 60 for a steadier reference)"
    );
    Ok(())
}
