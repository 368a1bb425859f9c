//! Re-localisation in the map: after a LiDAR gap, or while the scans disagree with the map
//! (`lost`), the prediction may be off by more than the association can pull in (its
//! correspondences are found within a voxel or two). A coarse-to-fine search over position
//! offsets, as wide as the position covariance, finds where a sample of the scan's points fits
//! the map best, and the update starts from there instead of re-initialising into a new world.
//!
//! Translation only: roll and pitch stay observable through gravity during a gap, and the yaw
//! a calibrated gyro loses in seconds is well under what the update pulls in.
//!
//! - Coarse: offsets on a grid of the map's voxel size (or coarser, at most `max_steps` each
//!   way) over the window; a candidate scores the sample points that fall into occupied voxels
//!   (tolerant of offsets up to about a voxel).
//! - Fine: three levels of 3 x 3 x 3 offsets at a half, a quarter and an eighth of the coarse
//!   step around the best, scoring the points within `plane_dist` of their voxel's plane (its
//!   mean and voxel normal).
//!
//! The best offset is taken only if it fits clearly more points than the prediction
//! (`min_gain`), so a prediction that is right stays where it is. The cost is bounded by
//! `sample_points` times the candidates (at most `(2 * max_steps + 1)^2 * 3 + 78`); it runs only
//! on the scans named above. No clock, no allocation.

use nalgebra::{Matrix3, Vector3};

use crate::scan::ScanPoint;
use crate::voxel_map::VoxelMap;

/// When and how widely to search.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct RelocaliseConfig {
    /// Search on the first scan after a LiDAR gap longer than this, s (and on every `lost`
    /// scan). Non-positive or non-finite: never.
    pub after_gap_s: f64,
    /// How far dead reckoning drifts through a LiDAR gap of `T` s: an acceleration error of
    /// this standard deviation, m/s^2 (a tilt of 0.3 degrees), makes the position variance at
    /// least `(a T^2 / 2)^2` (the IMU noise alone grows it far too little: 0.023 m after 8 s on
    /// the handheld walk, which had drifted 1.3 m).
    pub dead_reckoning_acc_std: f64,
    /// The window is 3 standard deviations of the position, at most this, m.
    pub max_window_m: f32,
    /// The coarse grid has at most this many steps each way (horizontal).
    pub max_steps: u32,
    /// Points of the scan that score a candidate (evenly spread; at most twice this).
    pub sample_points: u32,
    /// A point fits a plane within this distance, m.
    pub plane_dist: f32,
    /// The best offset must fit at least this factor more points than the prediction ...
    pub min_gain: f32,
    /// ... and at least this share of the sample (a scan of another world fits nowhere).
    pub min_fit: f32,
}

impl RelocaliseConfig {
    /// The defaults (see the field docs and `tests/odometry_faults.rs`).
    pub const DEFAULT: RelocaliseConfig = RelocaliseConfig {
        after_gap_s: 1.0,
        dead_reckoning_acc_std: 0.05,
        max_window_m: 6.0,
        max_steps: 10,
        sample_points: 256,
        plane_dist: 0.1,
        min_gain: 1.15,
        min_fit: 0.25,
    };
}

impl Default for RelocaliseConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// What one search found.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Relocalisation {
    /// The offset to add to the predicted position (zero if none was better), m, world frame.
    pub offset: [f32; 3],
    /// Sample points that fit a plane at the prediction.
    pub score_before: u32,
    /// ... and at the offset found.
    pub score_after: u32,
    /// Candidates scored.
    pub candidates: u32,
    /// The half-width of the window searched, m.
    pub window_m: f32,
    /// Whether the offset was taken.
    pub moved: bool,
}

/// The sample points in the world at the predicted LiDAR pose (rotation `r_wl`, origin `t_wl`).
struct Sample<'p> {
    points: &'p [ScanPoint],
    stride: usize,
    r: Matrix3<f32>,
    t: Vector3<f32>,
}

impl Sample<'_> {
    fn world(&self) -> impl Iterator<Item = Vector3<f32>> + '_ {
        self.points.iter().step_by(self.stride).filter(|p| p.xyz.iter().all(|v| v.is_finite())).map(|p| {
            let [x, y, z] = p.xyz;
            self.r * Vector3::new(x, y, z) + self.t
        })
    }

    /// Points that fall into an occupied voxel at offset `o`.
    fn occupancy(&self, map: &VoxelMap<'_>, o: &Vector3<f32>) -> u32 {
        self.world().filter(|q| map.find(arr(&(q + o))).is_some()).count() as u32
    }

    /// Points within `d` of their voxel's plane (its mean and normal) at offset `o`.
    fn planes(&self, map: &VoxelMap<'_>, o: &Vector3<f32>, d: f32) -> u32 {
        self.world()
            .filter(|q| {
                let q = q + o;
                let v = map.find(arr(&q)).and_then(|h| map.voxel(h));
                v.is_some_and(|v| {
                    v.normal.is_some_and(|n| Vector3::from(n).dot(&(q - Vector3::from(v.mean))).abs() < d)
                })
            })
            .count() as u32
    }
}

fn arr(v: &Vector3<f32>) -> [f32; 3] {
    [v.x, v.y, v.z]
}

/// Searches position offsets within `window_m` (half-width, m; clamped to the config's
/// maximum) for the LiDAR pose (`r_wl`, `t_wl`, world from LiDAR) at which `points` (LiDAR
/// frame, undistorted to the pose's time) fit `map` best.
pub fn search(
    cfg: &RelocaliseConfig,
    map: &VoxelMap<'_>,
    points: &[ScanPoint],
    r_wl: &Matrix3<f64>,
    t_wl: &Vector3<f64>,
    window_m: f32,
) -> Relocalisation {
    let mut out = Relocalisation::default();
    let n = points.len();
    let want = cfg.sample_points.max(1) as usize;
    if n == 0 || map.is_empty() || !window_m.is_finite() {
        return out;
    }
    let sample =
        Sample { points, stride: n.div_ceil(want).max(1), r: r_wl.cast::<f32>(), t: t_wl.cast::<f32>() };
    let voxel = map.config().voxel_size.max(1e-3);
    let window = window_m.clamp(0.0, cfg.max_window_m.max(0.0));
    out.window_m = window;
    let zero = Vector3::zeros();
    out.score_before = sample.planes(map, &zero, cfg.plane_dist);

    // Coarse: a grid of the voxel size over the window, coarser where the window needs more
    // than `max_steps` of them (z: one step each way, where the window allows).
    let step = voxel.max(window / cfg.max_steps.max(1) as f32);
    let steps = (libm::ceilf(window / step) as i32).clamp(0, cfg.max_steps as i32);
    let zsteps = i32::from(window >= step);
    let mut best = (sample.occupancy(map, &zero), zero);
    out.candidates = 1;
    for iz in -zsteps..=zsteps {
        for iy in -steps..=steps {
            for ix in -steps..=steps {
                if ix == 0 && iy == 0 && iz == 0 {
                    continue;
                }
                let o = Vector3::new(ix as f32, iy as f32, iz as f32) * step;
                let s = sample.occupancy(map, &o);
                out.candidates += 1;
                // Ties keep the smaller offset (the loop order visits larger ones later).
                if s > best.0 || (s == best.0 && o.norm() < best.1.norm()) {
                    best = (s, o);
                }
            }
        }
    }
    // Fine: planes, at a half, a quarter and an eighth of the coarse step around the best.
    let mut fine = (sample.planes(map, &best.1, cfg.plane_dist), best.1);
    for div in [2.0f32, 4.0, 8.0] {
        let step = step / div;
        let centre = fine.1;
        for iz in -1..=1 {
            for iy in -1..=1 {
                for ix in -1..=1 {
                    if ix == 0 && iy == 0 && iz == 0 {
                        continue;
                    }
                    let o = centre + Vector3::new(ix as f32, iy as f32, iz as f32) * step;
                    let s = sample.planes(map, &o, cfg.plane_dist);
                    out.candidates += 1;
                    if s > fine.0 {
                        fine = (s, o);
                    }
                }
            }
        }
    }
    out.score_after = fine.0;
    let sampled = sample.world().count() as f32;
    let s = fine.0 as f32;
    if fine.1 != zero && s >= cfg.min_gain * (out.score_before as f32) + 8.0 && s >= cfg.min_fit * sampled {
        out.offset = arr(&fine.1);
        out.moved = true;
    } else {
        out.score_after = out.score_before;
    }
    out
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::voxel_map::{MapConfig, MapPoint, MapStorage};

    /// A room 12 x 9 x 4 m (floor, ceiling, four walls) and a box in it, sampled every 0.1 m.
    fn room(mut f: impl FnMut([f32; 3], [f32; 3])) {
        let (lx, ly, lz) = (12.0f32, 9.0f32, 4.0f32);
        let step = 0.1f32;
        let (nx, ny, nz) = ((lx / step) as i32, (ly / step) as i32, (lz / step) as i32);
        for i in 0..=nx {
            for j in 0..=ny {
                let (x, y) = (i as f32 * step - 6.0, j as f32 * step - 4.5);
                f([x, y, -1.5], [0.0, 0.0, 1.0]);
                f([x, y, lz - 1.5], [0.0, 0.0, -1.0]);
            }
        }
        for i in 0..=nx {
            for k in 0..=nz {
                let (x, z) = (i as f32 * step - 6.0, k as f32 * step - 1.5);
                f([x, -4.5, z], [0.0, 1.0, 0.0]);
                f([x, 4.5, z], [0.0, -1.0, 0.0]);
            }
        }
        for j in 0..=ny {
            for k in 0..=nz {
                let (y, z) = (j as f32 * step - 4.5, k as f32 * step - 1.5);
                f([-6.0, y, z], [1.0, 0.0, 0.0]);
                f([6.0, y, z], [-1.0, 0.0, 0.0]);
            }
        }
        // A box 1 x 2 m in plan, 1.5 m high, off-centre: breaks the room's symmetry.
        for j in 0..=20 {
            for k in 0..=15 {
                let (y, z) = (1.0 + j as f32 * 0.1, k as f32 * 0.1 - 1.5);
                f([2.0, y, z], [-1.0, 0.0, 0.0]);
                f([3.0, y, z], [1.0, 0.0, 0.0]);
            }
        }
    }

    static STORE: std::sync::Mutex<MapStorage<4096, 65536>> = std::sync::Mutex::new(MapStorage::new());

    #[test]
    fn finds_a_metre_and_a_half_of_drift_and_keeps_a_right_prediction() {
        let mut store = STORE.lock().unwrap_or_else(|e| e.into_inner());
        let mut map = store.map(MapConfig::default()).unwrap();
        let mut pts = std::vec::Vec::new();
        room(|p, n| pts.push(MapPoint { xyz: p, normal: Some(n) }));
        for chunk in pts.chunks(4096) {
            map.insert(chunk.iter().copied(), [0.0, 0.0, 0.0], 1).unwrap();
        }
        // The scan: every 7th surface point seen from the sensor at (0.4, -0.3, 0), in its frame.
        let sensor = Vector3::new(0.4f32, -0.3, 0.0);
        let scan: std::vec::Vec<ScanPoint> = pts
            .iter()
            .step_by(7)
            .map(|p| {
                let q = Vector3::from(p.xyz) - sensor;
                ScanPoint { xyz: [q.x, q.y, q.z], ..ScanPoint::default() }
            })
            .collect();
        let cfg = RelocaliseConfig::DEFAULT;
        let r = Matrix3::identity();
        // Predicted 1.1 m and -0.7 m off (what 8 s of dead reckoning gave on the handheld walk).
        let predicted = sensor.cast::<f64>() + Vector3::new(1.1, -0.7, 0.05);
        let found = search(&cfg, &map, &scan, &r, &predicted, 2.0);
        assert!(found.moved, "{found:?}");
        let err = predicted.cast::<f32>() + Vector3::from(found.offset) - sensor;
        assert!(err.norm() < 0.15, "left {err:?} of 1.3 m: {found:?}");
        assert!(found.score_after as f32 > 1.8 * found.score_before as f32, "{found:?}");
        // Bounded: the coarse grid (21 x 21 x 3 at most) and the three fine levels.
        assert!(found.candidates <= 21 * 21 * 3 + 78, "{found:?}");

        // A right prediction stays.
        let stay = search(&cfg, &map, &scan, &r, &sensor.cast::<f64>(), 2.0);
        assert!(!stay.moved && stay.offset == [0.0; 3], "{stay:?}");
        // No window, no map, no points: nothing moves.
        assert!(!search(&cfg, &map, &[], &r, &predicted, 2.0).moved);
        assert!(!search(&cfg, &map, &scan, &r, &predicted, f32::NAN).moved);
    }
}
