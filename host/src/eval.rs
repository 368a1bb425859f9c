//! Trajectory evaluation: absolute (APE/ATE) and relative (RPE) pose errors against a ground
//! truth, with the definitions of evo (M. Grupp, <https://github.com/MichaelGrupp/evo>) so that
//! the numbers agree with `evo_ape`/`evo_rpe` to 1e-6 (tested on evo's KITTI-00 pair).
//!
//! Definitions (f64 throughout; `inv(T)` is `[R^T | -R^T t]`, as evo computes it):
//! - **Association**: each stamp of the shorter trajectory is paired with the nearest stamp of
//!   the other (the earlier one on a tie) when they differ by at most `max_diff` seconds, after
//!   adding `offset` to the estimate's stamps (evo's `--t_max_diff`, `--t_offset`). KITTI files
//!   without times pair by index.
//! - **Alignment** (optional) of the estimate onto the ground truth by Umeyama's least squares
//!   on the positions: SE(3) (`R`, `t`) or Sim(3) (`R`, `t`, scale `s`); the estimate's poses
//!   become `p' = s R p + t`, `R' = R R_i`.
//! - **APE**: translation error `|p_est - p_gt|`; rotation error the angle of `R_gt^T R_est`.
//! - **RPE** over pose pairs (i, j): `E = inv(inv(Q_i) Q_j) inv(P_i) P_j` (Q ground truth, P
//!   the aligned estimate); translation error `|t_E|`, rotation error the angle of `R_E`. The
//!   pairs are chosen on the (aligned) estimate's poses, as evo does by default, or on the ground
//!   truth's with `pairs_from_gt` (evo's `--pairs_from_reference`).
//!   Pairs with a delta in frames are (i, i + d) for every i (`all_pairs`) or (0, d), (d, 2d), ...
//!   With a delta in metres of path length: `all_pairs` pairs each i with
//!   the first j > i whose path distance from i is nearest to delta, kept if within 10 % of
//!   delta; otherwise consecutive poses are taken whenever the path since the last one reaches
//!   delta.
//! - **Angles** are taken after projecting the rotation onto SO(3) (polar decomposition, as
//!   scipy does for the slightly non-orthogonal matrices of text files), as
//!   `atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2)`, which is accurate for tiny angles.
//! - **Statistics**: rmse, mean, median (mean of the two middle values for an even count), std
//!   (population), min, max, sse.

use std::fmt;
use std::path::Path;

use nalgebra::{Matrix3, Vector3};

/// An evaluation error (bad file, nothing to compare).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct EvalError(pub String);

impl fmt::Display for EvalError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for EvalError {}

macro_rules! bail {
    ($($t:tt)*) => { return Err(EvalError(format!($($t)*))) };
}

/// One pose: rotation and position (f64).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Rotation, body to world (as read: not re-orthogonalised).
    pub r: Matrix3<f64>,
    /// Position, metres.
    pub t: Vector3<f64>,
}

impl Pose {
    /// `inv(self) * other` with the transpose as inverse (evo's `relative_se3`).
    pub fn between(&self, other: &Pose) -> Pose {
        let rt = self.r.transpose();
        Pose { r: rt * other.r, t: rt * other.t - rt * self.t }
    }
}

/// A trajectory: stamps (seconds) and poses, or poses only (KITTI without times).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trajectory {
    /// Stamps in seconds, increasing; `None` for KITTI files read without a times file.
    pub stamps: Option<Vec<f64>>,
    /// The poses.
    pub poses: Vec<Pose>,
}

impl Trajectory {
    /// Number of poses.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// Whether there are no poses.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    fn subset(&self, idx: &[usize]) -> Trajectory {
        Trajectory {
            stamps: self.stamps.as_ref().map(|s| idx.iter().map(|&i| s[i]).collect()),
            poses: idx.iter().map(|&i| self.poses[i]).collect(),
        }
    }
}

/// File formats `loglio eval` reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    /// `t tx ty tz qx qy qz qw` per line.
    Tum,
    /// 12 numbers per line: the row-major 3x4 `[R | t]`.
    Kitti,
}

fn numbers(line: &str) -> impl Iterator<Item = &str> {
    line.split(|c: char| c.is_whitespace() || c == ',').filter(|s| !s.is_empty())
}

fn parse_numbers(
    line: &str,
    name: &str,
    lineno: usize,
    want: usize,
    what: &str,
    other: Option<(usize, &str)>,
) -> Result<Vec<f64>, EvalError> {
    let fields: Vec<&str> = numbers(line).collect();
    if fields.len() != want {
        // The count of the other format: say which one it looks like.
        let hint = match other {
            Some((n, which)) if n == fields.len() => format!("; this looks like {which}"),
            _ => String::new(),
        };
        bail!("{name} line {lineno}: expected {want} numbers ({what}), found {}{hint}", fields.len());
    }
    fields
        .iter()
        .map(|s| match s.parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            Ok(_) => Err(EvalError(format!("{name} line {lineno}: `{s}` is not a finite number"))),
            Err(_) => Err(EvalError(format!("{name} line {lineno}: `{s}` is not a number"))),
        })
        .collect()
}

fn check_increasing(stamps: &[f64], lines: &[usize], name: &str) -> Result<(), EvalError> {
    for k in 1..stamps.len() {
        if stamps[k] <= stamps[k - 1] {
            bail!(
                "{name} line {}: timestamp {} does not increase (previous {})",
                lines[k],
                stamps[k],
                stamps[k - 1]
            );
        }
    }
    Ok(())
}

/// Parses a TUM trajectory (`#` comments and blank lines allowed; spaces or commas).
pub fn parse_tum(text: &str, name: &str) -> Result<Trajectory, EvalError> {
    let mut stamps = Vec::new();
    let mut poses = Vec::new();
    let mut lines = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v = parse_numbers(
            line,
            name,
            i + 1,
            8,
            "t tx ty tz qx qy qz qw",
            Some((12, "a KITTI pose file (row-major 3x4 [R|t]): use `--format kitti`")),
        )?;
        let (x, y, z, w) = (v[4], v[5], v[6], v[7]);
        let n = (x * x + y * y + z * z + w * w).sqrt();
        if (n - 1.0).abs() > 1e-2 {
            bail!(
                "{name} line {}: quaternion norm {n:.4} is not 1 (TUM order is t tx ty tz qx qy qz qw)",
                i + 1
            );
        }
        let q = [w / n, x / n, y / n, z / n];
        let m = crate::config::quat_to_matrix(q);
        stamps.push(v[0]);
        lines.push(i + 1);
        poses.push(Pose { r: Matrix3::from_fn(|r, c| m[r][c]), t: Vector3::new(v[1], v[2], v[3]) });
    }
    if poses.is_empty() {
        bail!("{name}: no poses (TUM format: t tx ty tz qx qy qz qw per line)");
    }
    check_increasing(&stamps, &lines, name)?;
    Ok(Trajectory { stamps: Some(stamps), poses })
}

/// Parses a KITTI pose file, with the stamps of a KITTI times file (one number per line) if given.
pub fn parse_kitti(text: &str, name: &str, times: Option<(&str, &str)>) -> Result<Trajectory, EvalError> {
    let mut poses = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v = parse_numbers(
            line,
            name,
            i + 1,
            12,
            "row-major 3x4 [R|t]",
            Some((8, "a TUM trajectory (t tx ty tz qx qy qz qw): use `--format tum`")),
        )?;
        let r = Matrix3::new(v[0], v[1], v[2], v[4], v[5], v[6], v[8], v[9], v[10]);
        // As lenient as the TUM quaternion-norm check: the rotation errors and the alignment
        // assume a rotation (a zero or scaled block gave NaN errors, or a panic in the SVD).
        let off = (r.transpose() * r - Matrix3::identity()).abs().max();
        if !(off <= 1e-2 && r.determinant() > 0.0) {
            bail!(
                "{name} line {}: the 3x3 block is not a rotation (|R^T R - I| = {off:.3e}, det {:.3}; KITTI rows are r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz)",
                i + 1,
                r.determinant()
            );
        }
        poses.push(Pose { r, t: Vector3::new(v[3], v[7], v[11]) });
    }
    if poses.is_empty() {
        bail!("{name}: no poses (KITTI format: 12 numbers per line)");
    }
    let stamps = match times {
        None => None,
        Some((ttext, tname)) => {
            let mut s = Vec::new();
            let mut lines = Vec::new();
            for (i, line) in ttext.lines().enumerate() {
                let line = line.trim();
                if line.is_empty() || line.starts_with('#') {
                    continue;
                }
                s.push(parse_numbers(line, tname, i + 1, 1, "a time in seconds", None)?[0]);
                lines.push(i + 1);
            }
            if s.len() != poses.len() {
                bail!("{tname}: {} times for the {} poses of {name}", s.len(), poses.len());
            }
            check_increasing(&s, &lines, tname)?;
            Some(s)
        }
    };
    Ok(Trajectory { stamps, poses })
}

fn read_text(path: &Path) -> Result<String, EvalError> {
    std::fs::read_to_string(path).map_err(|e| EvalError(format!("cannot read {}: {e}", path.display())))
}

/// Reads a trajectory file; `times` only for KITTI.
pub fn read_trajectory(path: &Path, format: Format, times: Option<&Path>) -> Result<Trajectory, EvalError> {
    let text = read_text(path)?;
    let name = path.display().to_string();
    match format {
        Format::Tum => {
            if times.is_some() {
                bail!("a times file is only for KITTI pose files; TUM files carry their stamps");
            }
            parse_tum(&text, &name)
        }
        Format::Kitti => match times {
            None => parse_kitti(&text, &name, None),
            Some(tp) => {
                let ttext = read_text(tp)?;
                parse_kitti(&text, &name, Some((&ttext, &tp.display().to_string())))
            }
        },
    }
}

fn nearest(sorted: &[f64], x: f64) -> usize {
    let k = sorted.partition_point(|&s| s < x);
    if k == 0 {
        return 0;
    }
    if k == sorted.len() {
        return k - 1;
    }
    // The earlier index wins a tie, as numpy's argmin does.
    if (sorted[k - 1] - x).abs() <= (sorted[k] - x).abs() { k - 1 } else { k }
}

/// Pairs the poses of `gt` and `est` by time (see the module docs). Returns the two matched
/// trajectories, equally long.
pub fn associate(
    gt: &Trajectory,
    est: &Trajectory,
    max_diff: f64,
    offset: f64,
) -> Result<(Trajectory, Trajectory), EvalError> {
    match (&gt.stamps, &est.stamps) {
        (None, None) => {
            if gt.len() != est.len() {
                bail!(
                    "the ground truth has {} poses and the estimate {}; without stamps (KITTI without times files) they pair by index",
                    gt.len(),
                    est.len()
                );
            }
            Ok((gt.clone(), est.clone()))
        }
        (Some(g), Some(e)) => {
            let e_off: Vec<f64> = e.iter().map(|t| t + offset).collect();
            let (mut gi, mut ei) = (Vec::new(), Vec::new());
            if e.len() > g.len() {
                for (i, &t) in g.iter().enumerate() {
                    let j = nearest(&e_off, t);
                    if (e_off[j] - t).abs() <= max_diff {
                        gi.push(i);
                        ei.push(j);
                    }
                }
            } else {
                for (j, &t) in e_off.iter().enumerate() {
                    let i = nearest(g, t);
                    if (g[i] - t).abs() <= max_diff {
                        gi.push(i);
                        ei.push(j);
                    }
                }
            }
            if gi.is_empty() {
                bail!(
                    "no matching timestamps within {max_diff} s: ground truth spans {:.3}..{:.3} s, estimate {:.3}..{:.3} s (after offset {offset} s)",
                    g[0],
                    g[g.len() - 1],
                    e_off[0],
                    e_off[e_off.len() - 1]
                );
            }
            Ok((gt.subset(&gi), est.subset(&ei)))
        }
        _ => {
            bail!("one trajectory has stamps and the other none: give a KITTI times file for both or neither")
        }
    }
}

/// A similarity transform `p -> s R p + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity {
    /// Rotation.
    pub r: Matrix3<f64>,
    /// Translation, metres.
    pub t: Vector3<f64>,
    /// Scale (1 for SE(3)).
    pub s: f64,
}

impl Similarity {
    /// The identity.
    pub fn identity() -> Self {
        Similarity { r: Matrix3::identity(), t: Vector3::zeros(), s: 1.0 }
    }

    /// Applies the transform to a pose (the estimate's frame onto the ground truth's).
    pub fn apply(&self, p: &Pose) -> Pose {
        Pose { r: self.r * p.r, t: self.r * (p.t * self.s) + self.t }
    }
}

/// Umeyama's least-squares similarity taking the points `x` onto `y` (scale 1 unless `with_scale`).
pub fn umeyama(x: &[Vector3<f64>], y: &[Vector3<f64>], with_scale: bool) -> Result<Similarity, EvalError> {
    if x.len() != y.len() || x.is_empty() {
        bail!("alignment needs two equally long, non-empty point sets");
    }
    let n = x.len() as f64;
    let mean = |v: &[Vector3<f64>]| v.iter().fold(Vector3::zeros(), |a, b| a + b) / n;
    let (mx, my) = (mean(x), mean(y));
    let sigma_x = x.iter().map(|p| (p - mx).norm_squared()).sum::<f64>() / n;
    let mut cov = Matrix3::zeros();
    for (a, b) in x.iter().zip(y) {
        cov += (b - my) * (a - mx).transpose();
    }
    cov /= n;
    if !(sigma_x.is_finite() && cov.iter().all(|v| v.is_finite())) {
        // Coordinates near f64's limit: the SVD would see NaN (and nalgebra panics sorting it).
        bail!("alignment failed: the positions are too large to align (their covariance overflows)");
    }
    let mut svd = cov.svd(true, true);
    svd.sort_by_singular_values();
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else { bail!("alignment failed: SVD did not converge") };
    let d = svd.singular_values;
    if d.iter().filter(|&&s| s > f64::EPSILON).count() < 2 {
        bail!("alignment is degenerate: the matched positions lie on a point or a line ({} poses)", x.len());
    }
    let mut s_diag = Vector3::new(1.0, 1.0, 1.0);
    if u.determinant() * v_t.determinant() < 0.0 {
        s_diag[2] = -1.0;
    }
    let r = u * Matrix3::from_diagonal(&s_diag) * v_t;
    let s = if with_scale { d.component_mul(&s_diag).sum() / sigma_x } else { 1.0 };
    let t = my - r * mx * s;
    Ok(Similarity { r, t, s })
}

/// Rotation angle in radians of a (near-)rotation matrix, after projecting it onto SO(3).
pub fn rotation_angle(m: &Matrix3<f64>) -> f64 {
    let svd = m.svd(true, true);
    let r = match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) => u * v_t,
        _ => *m,
    };
    let w = Vector3::new(r[(2, 1)] - r[(1, 2)], r[(0, 2)] - r[(2, 0)], r[(1, 0)] - r[(0, 1)]);
    let c = (r.trace() - 1.0) / 2.0;
    (w.norm() / 2.0).atan2(c)
}

/// Summary statistics of an error series.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Stats {
    /// Root mean square.
    pub rmse: f64,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub median: f64,
    /// Population standard deviation.
    pub std: f64,
    /// Smallest.
    pub min: f64,
    /// Largest.
    pub max: f64,
    /// Sum of squares.
    pub sse: f64,
    /// Number of values.
    pub n: usize,
}

impl Stats {
    /// The statistics of `v` (all zero for an empty slice).
    pub fn of(v: &[f64]) -> Stats {
        if v.is_empty() {
            return Stats::default();
        }
        let n = v.len() as f64;
        let sse: f64 = v.iter().map(|e| e * e).sum();
        let mean = v.iter().sum::<f64>() / n;
        let var = v.iter().map(|e| (e - mean) * (e - mean)).sum::<f64>() / n;
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        let k = s.len();
        let median = if k % 2 == 1 { s[k / 2] } else { (s[k / 2 - 1] + s[k / 2]) / 2.0 };
        Stats { rmse: (sse / n).sqrt(), mean, median, std: var.sqrt(), min: s[0], max: s[k - 1], sse, n: k }
    }

    fn json(&self) -> String {
        format!(
            "{{\"rmse\": {:e}, \"mean\": {:e}, \"median\": {:e}, \"std\": {:e}, \"min\": {:e}, \"max\": {:e}, \"sse\": {:e}, \"n\": {}}}",
            self.rmse, self.mean, self.median, self.std, self.min, self.max, self.sse, self.n
        )
    }
}

/// How the estimate is aligned to the ground truth before the errors are computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Alignment {
    /// None: both trajectories must share a frame.
    None,
    /// Rotation and translation (evo `-a`).
    Se3,
    /// Rotation, translation and scale (evo `-as`), for monocular estimates.
    Sim3,
}

/// The unit of the RPE delta.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DeltaUnit {
    /// Poses (frames).
    Frames,
    /// Metres of path length along the ground truth.
    Metres,
}

/// Evaluation settings (defaults as evo's).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EvalOptions {
    /// Alignment of the estimate.
    pub align: Alignment,
    /// Largest stamp difference of an associated pair, seconds (evo's default 0.01).
    pub max_diff: f64,
    /// Added to the estimate's stamps before association, seconds.
    pub offset: f64,
    /// RPE delta.
    pub rpe_delta: f64,
    /// Unit of `rpe_delta`.
    pub rpe_unit: DeltaUnit,
    /// Every pair at the delta rather than consecutive ones.
    pub all_pairs: bool,
    /// Choose the RPE pairs on the ground truth instead of the estimate (evo's
    /// `--pairs_from_reference`; evo's default is the estimate).
    pub pairs_from_gt: bool,
}

impl Default for EvalOptions {
    fn default() -> Self {
        EvalOptions {
            align: Alignment::Se3,
            max_diff: 0.01,
            offset: 0.0,
            rpe_delta: 1.0,
            rpe_unit: DeltaUnit::Frames,
            all_pairs: false,
            pairs_from_gt: false,
        }
    }
}

/// The pose pairs (i, j) of the RPE, chosen on the given poses (see the module docs).
pub fn rpe_pairs(
    gt: &[Pose],
    delta: f64,
    unit: DeltaUnit,
    all_pairs: bool,
) -> Result<Vec<(usize, usize)>, EvalError> {
    let n = gt.len();
    match unit {
        DeltaUnit::Frames => {
            if delta < 1.0 || delta.fract() != 0.0 {
                bail!("RPE delta in frames must be a whole number >= 1, not {delta}");
            }
            let d = delta as usize;
            Ok(if all_pairs {
                (0..n.saturating_sub(d)).map(|i| (i, i + d)).collect()
            } else {
                let ids: Vec<usize> = (0..n).step_by(d).collect();
                ids.windows(2).map(|w| (w[0], w[1])).collect()
            })
        }
        DeltaUnit::Metres => {
            if !(delta > 0.0 && delta.is_finite()) {
                bail!("RPE delta in metres must be positive, not {delta}");
            }
            let step = |a: &Pose, b: &Pose| {
                let d = a.t - b.t;
                (d.x * d.x + d.y * d.y + d.z * d.z).sqrt()
            };
            if all_pairs {
                let mut dist = Vec::with_capacity(n);
                let mut acc = 0.0;
                dist.push(0.0);
                for k in 1..n {
                    acc += step(&gt[k - 1], &gt[k]);
                    dist.push(acc);
                }
                let tol = delta * 0.1;
                let mut pairs = Vec::new();
                for i in 0..n.saturating_sub(1) {
                    let from = |j: usize| (dist[j] - dist[i]) - delta;
                    // dist is non-decreasing: the nearest is the first j with from(j) >= 0 or
                    // the first index of the plateau just before it.
                    let k = i + 1 + dist[i + 1..].partition_point(|&dj| (dj - dist[i]) - delta < 0.0);
                    let mut best: Option<usize> = None;
                    if k > i + 1 {
                        let v = dist[k - 1];
                        best = Some(i + 1 + dist[i + 1..].partition_point(|&dj| dj < v));
                    }
                    if k < n && best.is_none_or(|b| from(k).abs() < from(b).abs()) {
                        best = Some(k);
                    }
                    if let Some(j) = best
                        && from(j).abs() <= tol
                    {
                        pairs.push((i, j));
                    }
                }
                Ok(pairs)
            } else {
                let mut ids = vec![0usize];
                let mut path = 0.0;
                for k in 1..n {
                    path += step(&gt[k], &gt[k - 1]);
                    if path >= delta {
                        ids.push(k);
                        path = 0.0;
                    }
                }
                Ok(ids.windows(2).map(|w| (w[0], w[1])).collect())
            }
        }
    }
}

/// Everything `loglio eval` reports.
#[derive(Clone, Debug, PartialEq)]
pub struct EvalReport {
    /// Options used.
    pub options: EvalOptions,
    /// Poses in each input, and matched pairs.
    pub gt_poses: usize,
    /// Poses of the estimate.
    pub est_poses: usize,
    /// Associated pairs.
    pub matched: usize,
    /// The alignment applied to the estimate.
    pub alignment: Similarity,
    /// APE translation, metres.
    pub ape_trans: Stats,
    /// APE rotation, degrees.
    pub ape_rot_deg: Stats,
    /// RPE translation, metres.
    pub rpe_trans: Stats,
    /// RPE rotation, degrees.
    pub rpe_rot_deg: Stats,
    /// Stamp (s, or index without stamps) and APE translation of every matched pose.
    pub ape_series: Vec<(f64, f64)>,
    /// Whether the series' first element is a stamp (false: a pose index).
    pub has_stamps: bool,
    /// Matched ground-truth positions.
    pub gt_positions: Vec<[f64; 3]>,
    /// Matched, aligned estimate positions.
    pub est_positions: Vec<[f64; 3]>,
    /// The positions lie nearly on a line (their second spread under
    /// [`LINE_SPREAD_RATIO`] of the first): the rotation about it was taken from the
    /// orientations, as positions alone leave it to noise.
    pub rotation_from_orientations: bool,
}

/// Below this ratio of the ground truth's second to first positional variance, the positions
/// are taken as a line (a straight drive): 1 cm of wander across 10 m of travel is 1e-6.
pub const LINE_SPREAD_RATIO: f64 = 1e-4;

/// The rotation that best takes the orientations `est` onto `gt` (chordal mean of
/// `R_gt R_estᵀ`, projected onto SO(3)).
fn orientation_alignment(gt: &[Pose], est: &[Pose]) -> Option<Matrix3<f64>> {
    let mut m = Matrix3::zeros();
    for (g, e) in gt.iter().zip(est) {
        m += g.r * e.r.transpose();
    }
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * v_t;
    r.iter().all(|v| v.is_finite()).then_some(r)
}

/// The second to first positional variance of `p` (1: a blob, 0: a line or a point).
fn spread_ratio(p: &[Vector3<f64>]) -> f64 {
    let n = p.len().max(1) as f64;
    let m = p.iter().fold(Vector3::zeros(), |a, b| a + b) / n;
    let mut c = Matrix3::zeros();
    for q in p {
        c += (q - m) * (q - m).transpose();
    }
    let mut e: Vec<f64> = c.symmetric_eigenvalues().iter().copied().collect();
    e.sort_by(|a, b| b.total_cmp(a));
    if e[0] > 0.0 { e[1] / e[0] } else { 0.0 }
}

/// Evaluates `est` against `gt`.
pub fn evaluate(gt: &Trajectory, est: &Trajectory, opt: &EvalOptions) -> Result<EvalReport, EvalError> {
    let (g, e) = associate(gt, est, opt.max_diff, opt.offset)?;
    let mut rotation_from_orientations = false;
    let alignment = match opt.align {
        Alignment::None => Similarity::identity(),
        Alignment::Se3 | Alignment::Sim3 => {
            if g.len() < 3 {
                bail!("alignment needs at least 3 matched poses, found {}", g.len());
            }
            let x: Vec<_> = e.poses.iter().map(|p| p.t).collect();
            let y: Vec<_> = g.poses.iter().map(|p| p.t).collect();
            // Along a straight line the positions leave the rotation about it to their noise
            // (an 11.6 deg "rotation error" on a straight 4 s drive): take the rotation from the
            // orientations there, the translation (and scale) from the positions.
            let r_or =
                (spread_ratio(&y) < LINE_SPREAD_RATIO).then(|| orientation_alignment(&g.poses, &e.poses));
            match r_or.flatten() {
                Some(r) => {
                    rotation_from_orientations = true;
                    let n = x.len() as f64;
                    let (mx, my) = (x.iter().sum::<Vector3<f64>>() / n, y.iter().sum::<Vector3<f64>>() / n);
                    let s = if opt.align == Alignment::Sim3 {
                        let (mut num, mut den) = (0.0, 0.0);
                        for (a, b) in x.iter().zip(&y) {
                            num += (b - my).dot(&(r * (a - mx)));
                            den += (a - mx).norm_squared();
                        }
                        if den > 0.0 && num > 0.0 { num / den } else { 1.0 }
                    } else {
                        1.0
                    };
                    Similarity { r, t: my - r * mx * s, s }
                }
                None => umeyama(&x, &y, opt.align == Alignment::Sim3)?,
            }
        }
    };
    let est_al: Vec<Pose> = e.poses.iter().map(|p| alignment.apply(p)).collect();
    let ape_t: Vec<f64> = g.poses.iter().zip(&est_al).map(|(q, p)| (p.t - q.t).norm()).collect();
    let ape_r: Vec<f64> = g
        .poses
        .iter()
        .zip(&est_al)
        .map(|(q, p)| rotation_angle(&(q.r.transpose() * p.r)).to_degrees())
        .collect();
    let pair_poses = if opt.pairs_from_gt { &g.poses } else { &est_al };
    let pairs = rpe_pairs(pair_poses, opt.rpe_delta, opt.rpe_unit, opt.all_pairs)?;
    if pairs.is_empty() {
        let unit = if opt.rpe_unit == DeltaUnit::Frames { "frames" } else { "m" };
        bail!("RPE: no pose pair {} {unit} apart among the {} matched poses", opt.rpe_delta, g.len());
    }
    let (mut rpe_t, mut rpe_r) = (Vec::with_capacity(pairs.len()), Vec::with_capacity(pairs.len()));
    for &(i, j) in &pairs {
        let qe = g.poses[i].between(&g.poses[j]);
        let pe = est_al[i].between(&est_al[j]);
        let err = qe.between(&pe);
        rpe_t.push(err.t.norm());
        rpe_r.push(rotation_angle(&err.r).to_degrees());
    }
    // Positions near f64's limit overflow the error sums (inf, then NaN in the statistics and
    // in the JSON): refuse them as the alignment does.
    let stats = [&ape_t, &ape_r, &rpe_t, &rpe_r].map(|v| Stats::of(v));
    if !stats.iter().all(|s| s.sse.is_finite() && s.std.is_finite())
        || !est_al.iter().all(|p| p.t.iter().all(|v| v.is_finite()))
    {
        bail!("the errors overflow: the positions are too large to compare");
    }
    let [ape_trans, ape_rot_deg, rpe_trans, rpe_rot_deg] = stats;
    let times: Vec<f64> = match &g.stamps {
        Some(s) => s.clone(),
        None => (0..g.len()).map(|i| i as f64).collect(),
    };
    Ok(EvalReport {
        options: *opt,
        gt_poses: gt.len(),
        est_poses: est.len(),
        matched: g.len(),
        alignment,
        ape_trans,
        ape_rot_deg,
        rpe_trans,
        rpe_rot_deg,
        ape_series: times.into_iter().zip(ape_t).collect(),
        has_stamps: g.stamps.is_some(),
        gt_positions: g.poses.iter().map(|p| [p.t.x, p.t.y, p.t.z]).collect(),
        est_positions: est_al.iter().map(|p| [p.t.x, p.t.y, p.t.z]).collect(),
        rotation_from_orientations,
    })
}

impl EvalReport {
    /// The report as JSON (one object; numbers in full precision).
    pub fn to_json(&self) -> String {
        let o = &self.options;
        let a = &self.alignment;
        format!(
            "{{\"gt_poses\": {}, \"est_poses\": {}, \"matched\": {}, \"alignment\": {{\"mode\": \"{}\", \"scale\": {:e}, \"translation\": [{:e}, {:e}, {:e}], \"rotation_from\": \"{}\"}}, \
             \"rpe_delta\": {}, \"rpe_unit\": \"{}\", \"all_pairs\": {}, \"pairs_from_gt\": {}, \
             \"ape_trans_m\": {}, \"ape_rot_deg\": {}, \"rpe_trans_m\": {}, \"rpe_rot_deg\": {}}}",
            self.gt_poses,
            self.est_poses,
            self.matched,
            match o.align {
                Alignment::None => "none",
                Alignment::Se3 => "se3",
                Alignment::Sim3 => "sim3",
            },
            a.s,
            a.t.x,
            a.t.y,
            a.t.z,
            if self.rotation_from_orientations { "orientations" } else { "positions" },
            o.rpe_delta,
            if o.rpe_unit == DeltaUnit::Frames { "frames" } else { "m" },
            o.all_pairs,
            o.pairs_from_gt,
            self.ape_trans.json(),
            self.ape_rot_deg.json(),
            self.rpe_trans.json(),
            self.rpe_rot_deg.json()
        )
    }
}

impl fmt::Display for EvalReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let o = &self.options;
        let align = match o.align {
            Alignment::None => "none".to_string(),
            Alignment::Se3 => "SE(3) Umeyama".to_string(),
            Alignment::Sim3 => format!("Sim(3) Umeyama, scale {:.6}", self.alignment.s),
        };
        writeln!(
            f,
            "matched {} of {} estimated / {} ground-truth poses; alignment: {align}",
            self.matched, self.est_poses, self.gt_poses
        )?;
        if self.rotation_from_orientations {
            writeln!(
                f,
                "note: the positions lie on a line, which leaves the rotation about it open: the alignment's rotation is taken from the orientations"
            )?;
        }
        let unit = if o.rpe_unit == DeltaUnit::Frames { "frames" } else { "m" };
        let pairs = if o.all_pairs { ", all pairs" } else { "" };
        writeln!(
            f,
            "{:<26} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10} {:>7}",
            "", "rmse", "mean", "median", "std", "min", "max", "n"
        )?;
        let rows = [
            ("APE translation (m)", &self.ape_trans),
            ("APE rotation (deg)", &self.ape_rot_deg),
            ("RPE translation (m)", &self.rpe_trans),
            ("RPE rotation (deg)", &self.rpe_rot_deg),
        ];
        for (name, s) in rows {
            writeln!(
                f,
                "{name:<26} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>7}",
                s.rmse, s.mean, s.median, s.std, s.min, s.max, s.n
            )?;
        }
        let on = if o.pairs_from_gt { "ground truth" } else { "estimate" };
        write!(f, "RPE pose pairs: delta {} ({unit}){pairs}, chosen on the {on}", o.rpe_delta)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rz(a: f64) -> Matrix3<f64> {
        Matrix3::new(a.cos(), -a.sin(), 0.0, a.sin(), a.cos(), 0.0, 0.0, 0.0, 1.0)
    }

    fn helix(n: usize) -> Trajectory {
        let poses = (0..n)
            .map(|i| {
                let a = i as f64 * 0.1;
                Pose { r: rz(a), t: Vector3::new(5.0 * a.cos(), 5.0 * a.sin(), 0.2 * a) }
            })
            .collect();
        Trajectory { stamps: Some((0..n).map(|i| 100.0 + i as f64 * 0.1).collect()), poses }
    }

    #[test]
    fn umeyama_recovers_an_exact_similarity() {
        let gt = helix(50);
        let true_t = Similarity {
            r: rz(0.7) * Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.6, -0.8, 0.0, 0.8, 0.6),
            t: Vector3::new(3.0, -2.0, 1.0),
            s: 2.5,
        };
        // est = inverse of true_t applied to gt, so aligning est gives back gt.
        let inv_r = true_t.r.transpose();
        let est: Vec<Vector3<f64>> = gt.poses.iter().map(|p| inv_r * (p.t - true_t.t) / true_t.s).collect();
        let y: Vec<_> = gt.poses.iter().map(|p| p.t).collect();
        let sim = umeyama(&est, &y, true).unwrap();
        assert!((sim.s - 2.5).abs() < 1e-12);
        assert!((sim.r - true_t.r).norm() < 1e-12);
        assert!((sim.t - true_t.t).norm() < 1e-10);
        let line: Vec<Vector3<f64>> = (0..10).map(|i| Vector3::new(i as f64, 0.0, 0.0)).collect();
        assert!(umeyama(&line, &line, false).unwrap_err().0.contains("degenerate"));
    }

    #[test]
    fn identical_trajectories_have_zero_error_and_offset_ones_are_aligned_away() {
        let gt = helix(80);
        let mut est = gt.clone();
        let shift = Similarity { r: rz(1.0), t: Vector3::new(10.0, 0.0, -3.0), s: 1.0 };
        est.poses = est.poses.iter().map(|p| shift.apply(p)).collect();
        let rep = evaluate(&gt, &est, &EvalOptions::default()).unwrap();
        assert_eq!(rep.matched, 80);
        assert!(rep.ape_trans.max < 1e-9, "{:?}", rep.ape_trans);
        assert!(rep.ape_rot_deg.max < 1e-6);
        assert!(rep.rpe_trans.max < 1e-9);
        let none =
            evaluate(&gt, &est, &EvalOptions { align: Alignment::None, ..Default::default() }).unwrap();
        assert!(none.ape_trans.min > 1.0);
        // RPE is blind to a global rigid transform.
        assert!(none.rpe_trans.max < 1e-9);
        assert!(none.rpe_rot_deg.max < 1e-6);
    }

    #[test]
    fn known_constant_error() {
        // The estimate is the ground truth shifted by 0.3 m along its body x axis: APE without
        // alignment is exactly 0.3 everywhere.
        let gt = helix(40);
        let mut est = gt.clone();
        for p in &mut est.poses {
            p.t += p.r * Vector3::new(0.3, 0.0, 0.0);
        }
        let rep = evaluate(&gt, &est, &EvalOptions { align: Alignment::None, ..Default::default() }).unwrap();
        assert!((rep.ape_trans.rmse - 0.3).abs() < 1e-12);
        assert!((rep.ape_trans.std).abs() < 1e-9);
        assert_eq!(rep.ape_trans.n, 40);
    }

    #[test]
    fn stats_match_hand_values() {
        let s = Stats::of(&[1.0, 2.0, 3.0, 4.0]);
        assert_eq!(s.mean, 2.5);
        assert_eq!(s.median, 2.5);
        assert_eq!(s.sse, 30.0);
        assert!((s.rmse - 7.5f64.sqrt()).abs() < 1e-15);
        assert!((s.std - 1.25f64.sqrt()).abs() < 1e-15);
        assert_eq!((s.min, s.max, s.n), (1.0, 4.0, 4));
        assert_eq!(Stats::of(&[3.0, 1.0, 2.0]).median, 2.0);
    }

    #[test]
    fn rotation_angle_is_accurate_for_tiny_and_large_angles() {
        for a in [1e-9, 1e-5, 0.3, 3.0, std::f64::consts::PI - 1e-6] {
            assert!((rotation_angle(&rz(a)) - a).abs() < 1e-12, "{a}");
        }
        // A slightly non-orthogonal matrix (7-digit text) still gives the angle of its nearest rotation.
        let mut m = rz(1e-4);
        m[(0, 0)] += 1e-7;
        m[(1, 1)] += 1e-7;
        assert!((rotation_angle(&m) - 1e-4).abs() < 1e-11);
    }

    #[test]
    fn association_follows_evo() {
        let g = Trajectory { stamps: Some(vec![0.0, 1.0, 2.0, 3.0]), poses: helix(4).poses };
        let e = Trajectory { stamps: Some(vec![0.004, 1.02, 2.009]), poses: helix(3).poses };
        let (gm, em) = associate(&g, &e, 0.01, 0.0).unwrap();
        assert_eq!(gm.stamps.unwrap(), vec![0.0, 2.0]);
        assert_eq!(em.stamps.unwrap(), vec![0.004, 2.009]);
        let (gm, _) = associate(&g, &e, 0.01, -0.02).unwrap();
        assert_eq!(gm.stamps.unwrap(), vec![1.0]);
        let err = associate(&g, &Trajectory { stamps: Some(vec![50.0]), poses: helix(1).poses }, 0.01, 0.0)
            .unwrap_err();
        assert_eq!(
            err.0,
            "no matching timestamps within 0.01 s: ground truth spans 0.000..3.000 s, estimate 50.000..50.000 s (after offset 0 s)"
        );
    }

    fn brute_pairs(gt: &[Pose], delta: f64) -> Vec<(usize, usize)> {
        let mut d = vec![0.0];
        for k in 1..gt.len() {
            let v = gt[k - 1].t - gt[k].t;
            let last = d[k - 1];
            d.push(last + (v.x * v.x + v.y * v.y + v.z * v.z).sqrt());
        }
        let mut out = Vec::new();
        for i in 0..gt.len() - 1 {
            let mut best = i + 1;
            for j in i + 1..gt.len() {
                if ((d[j] - d[i]) - delta).abs() < ((d[best] - d[i]) - delta).abs() {
                    best = j;
                }
            }
            if ((d[best] - d[i]) - delta).abs() <= delta * 0.1 {
                out.push((i, best));
            }
        }
        out
    }

    #[test]
    fn metre_pairs_match_a_brute_force_search_with_stops() {
        // A path with stops (repeated positions make plateaus of the path length).
        let mut poses = Vec::new();
        let mut x = 0.0;
        for k in 0..300 {
            if k % 7 != 3 && k % 11 != 5 {
                x += 0.37 + 0.2 * ((k as f64) * 0.9).sin().abs();
            }
            poses.push(Pose { r: Matrix3::identity(), t: Vector3::new(x, 0.0, 0.0) });
        }
        for delta in [0.5, 1.0, 3.3, 10.0, 55.0] {
            assert_eq!(
                rpe_pairs(&poses, delta, DeltaUnit::Metres, true).unwrap(),
                brute_pairs(&poses, delta),
                "{delta}"
            );
        }
        let consecutive = rpe_pairs(&poses, 10.0, DeltaUnit::Metres, false).unwrap();
        assert!(consecutive.windows(2).all(|w| w[0].1 == w[1].0));
        assert_eq!(rpe_pairs(&poses, 3.0, DeltaUnit::Frames, false).unwrap()[..2], [(0, 3), (3, 6)]);
        assert_eq!(rpe_pairs(&poses, 3.0, DeltaUnit::Frames, true).unwrap().len(), 297);
    }

    #[test]
    fn bad_tum_files_give_one_line_errors() {
        let e = |t: &str| parse_tum(t, "est.txt").unwrap_err().0;
        assert_eq!(
            e("0 1 2 3 0 0 0 1\n1 1 2 3 0 0 1\n"),
            "est.txt line 2: expected 8 numbers (t tx ty tz qx qy qz qw), found 7"
        );
        assert_eq!(e("# header\n0 1 2 x 0 0 0 1\n"), "est.txt line 2: `x` is not a number");
        // A KITTI file read as TUM, and a TUM file read as KITTI, say which flag reads them.
        assert_eq!(
            e("1 0 0 0.5 0 1 0 0 0 0 1 0\n"),
            "est.txt line 1: expected 8 numbers (t tx ty tz qx qy qz qw), found 12; this looks like a KITTI pose file (row-major 3x4 [R|t]): use `--format kitti`"
        );
        assert_eq!(
            parse_kitti("0 1 2 3 0 0 0 1\n", "gt.txt", None).unwrap_err().0,
            "gt.txt line 1: expected 12 numbers (row-major 3x4 [R|t]), found 8; this looks like a TUM trajectory (t tx ty tz qx qy qz qw): use `--format tum`"
        );
        assert_eq!(
            parse_kitti("0 1 2 3 0 0 0\n", "gt.txt", None).unwrap_err().0,
            "gt.txt line 1: expected 12 numbers (row-major 3x4 [R|t]), found 7"
        );
        // The right flag reads the same KITTI line: identity rotation, t = (0.5, 0, 0).
        let k = parse_kitti("1 0 0 0.5 0 1 0 0 0 0 1 0\n", "est.txt", None).unwrap();
        assert_eq!(k.poses[0].t, Vector3::new(0.5, 0.0, 0.0));
        assert_eq!(k.poses[0].r, Matrix3::identity());
        assert_eq!(e("0 1 2 nan 0 0 0 1\n"), "est.txt line 1: `nan` is not a finite number");
        assert_eq!(
            e("1 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n"),
            "est.txt line 2: timestamp 0.5 does not increase (previous 1)"
        );
        assert_eq!(
            e("0 0 0 0 1 0 0 1\n"),
            "est.txt line 1: quaternion norm 1.4142 is not 1 (TUM order is t tx ty tz qx qy qz qw)"
        );
        assert_eq!(e("# nothing\n\n"), "est.txt: no poses (TUM format: t tx ty tz qx qy qz qw per line)");
        let ok = parse_tum("0,1,2,3,0,0,0,1\n", "x").unwrap();
        assert_eq!(ok.poses[0].t, Vector3::new(1.0, 2.0, 3.0));
        let k = parse_kitti("1 0 0 1 0 1 0 2 0 0 1 3\n", "gt.txt", Some(("0.1\n0.2\n", "times.txt")))
            .unwrap_err();
        assert_eq!(k.0, "times.txt: 2 times for the 1 poses of gt.txt");
    }

    /// Positions near f64's limit gave a NaN covariance, on which nalgebra's SVD sort panicked
    /// (found by the `eval_trajectories` fuzz target); a KITTI block that is no rotation gave
    /// NaN rotation errors (found reading the code around it). Both are now one-line errors.
    #[test]
    fn kitti_blocks_that_are_no_rotation_and_overflowing_positions_are_errors() {
        let e = |t: &str| parse_kitti(t, "gt.txt", None).unwrap_err().0;
        assert!(
            e("1 0 0 1 0 1 0 2 0 0 1 3
0 0 0 1 0 0 0 2 0 0 0 3
")
            .starts_with("gt.txt line 2: the 3x3 block is not a rotation (|R^T R - I| = 1.000e0, det 0.000;")
        );
        // A reflection is orthonormal but not a rotation.
        assert!(
            e("-1 0 0 1 0 1 0 2 0 0 1 3
")
            .starts_with("gt.txt line 1: the 3x3 block is not a rotation")
        );
        // A slightly non-orthonormal block (rounded output) is accepted.
        assert!(
            parse_kitti(
                "1.001 0 0 1 0 0.999 0 2 0 0 1 3
",
                "gt.txt",
                None
            )
            .is_ok()
        );

        let gt = helix(50);
        let mut est = gt.clone();
        est.poses[7].t.x = 4.4e300;
        for align in [Alignment::Se3, Alignment::None] {
            let opt = EvalOptions { align, ..EvalOptions::default() };
            let err = evaluate(&gt, &est, &opt).unwrap_err().0;
            assert!(
                err == "alignment failed: the positions are too large to align (their covariance overflows)"
                    || err == "the errors overflow: the positions are too large to compare",
                "{err}"
            );
        }
    }

    /// A straight 4 s drive: the positions leave the rotation about the line to their noise
    /// (millimetres across 10 m), so Umeyama's rotation about it is noise, and with it the APE
    /// rotation. The orientations fix it.
    #[test]
    fn a_straight_drive_takes_its_rotation_from_the_orientations() {
        let n = 40;
        let wobble = |i: usize, k: u64| {
            // splitmix64 of (i, k)
            let mut h = (i as u64 * 16 + k).wrapping_add(0x9e37_79b9_7f4a_7c15);
            h = (h ^ (h >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            h = (h ^ (h >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            h ^= h >> 31;
            (h % 2001) as f64 / 1000.0 - 1.0
        };
        let stamps: Vec<f64> = (0..n).map(|i| i as f64 * 0.1).collect();
        let gt = Trajectory {
            stamps: Some(stamps.clone()),
            poses: (0..n)
                .map(|i| Pose {
                    r: rz(0.001 * wobble(i, 1)),
                    t: Vector3::new(0.25 * i as f64, 0.0005 * wobble(i, 5), 0.0005 * wobble(i, 6)),
                })
                .collect(),
        };
        // The estimate: the same orientations; its positions wander across the line on their
        // own (up to 2 mm), not with the ground truth's wander.
        let est = Trajectory {
            stamps: Some(stamps),
            poses: gt
                .poses
                .iter()
                .enumerate()
                .map(|(i, p)| Pose {
                    r: p.r,
                    t: Vector3::new(p.t.x, 0.0, 0.0)
                        + 0.002 * Vector3::new(wobble(i, 2), wobble(i, 3), wobble(i, 4)),
                })
                .collect(),
        };
        let x: Vec<_> = est.poses.iter().map(|p| p.t).collect();
        let y: Vec<_> = gt.poses.iter().map(|p| p.t).collect();
        let by_positions = umeyama(&x, &y, false).unwrap();
        let roll = rotation_angle(&by_positions.r).to_degrees();
        assert!(roll > 5.0, "positions alone: noise decides the roll ({roll:.3} deg)");
        let r = evaluate(&gt, &est, &EvalOptions::default()).unwrap();
        assert!(r.rotation_from_orientations);
        assert!(r.ape_rot_deg.max < 1e-9, "{:?}", r.ape_rot_deg);
        assert!(r.ape_trans.max < 0.004, "{:?}", r.ape_trans);
        assert!(r.to_json().contains("\"rotation_from\": \"orientations\""));
        assert!(r.to_string().contains("the positions lie on a line"));
        // A helix is no line: the positions decide, as before.
        let h = helix(50);
        let rh = evaluate(&h, &h, &EvalOptions::default()).unwrap();
        assert!(!rh.rotation_from_orientations);
    }
}
