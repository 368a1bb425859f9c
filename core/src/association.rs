//! Data association (paper section IV-B): which map element each scan point is measured
//! against, and the scalar residuals the iterated update consumes.
//!
//! For every downsampled scan point `p` (LiDAR frame at the scan end, with its Ring FALS normal
//! `n_r` when it has one), at the filter's current iterate:
//!
//! 1. **Initial correspondence.** `p` goes to the world (`p_W`, `n_W`); the `k` nearest map
//!    points within `max_dist` come from [`VoxelMap::knn_many`] (batched: the queries of a chunk
//!    of points go to the map together so their cache misses overlap); `knn_reach` picks the
//!    point's octant block first ([`KnnReach::Block`], default) or exact within the 27 voxels
//!    around the point. Fewer than `min_neighbours`: no correspondence (`no_neighbours`).
//! 2. **Visibility check** (modes `Full`, `PlaneOnly`). A map point whose normal `m` (oriented
//!    towards the sensor that saw it) makes more than 90 degrees with the ray from `p_W` to the
//!    LiDAR origin, `m · (o_W - p_W) <= 0`, is on the back of a surface the LiDAR cannot see
//!    from here (the double-side issue of thin walls): it is removed from the neighbours. The
//!    ray starts at the LiDAR origin, not at the IMU as in the reference.
//!    Map points without a normal carry no evidence and stay. If fewer than `min_neighbours`
//!    remain, the point is rejected (`rejected_visibility`).
//! 3. **Consistency check** (modes `Full`, `PlaneOnly`). The mean angle between `n_W` and the
//!    remaining neighbours' normals must be at most `max_mean_angle_deg` (60 degrees, the paper's
//!    `alpha`), else the point is rejected (`rejected_consistency`). A query without a valid
//!    normal skips this check (in the reference such points never give a residual: a non-finite
//!    normal drops the point, a zero one fails the angle test; here they can still give a
//!    point-to-plane residual, which the plane-fit and residual tests guard).
//! 4. **Hierarchy** (mode `Full`): the large-scale surfel merged from the remaining neighbours'
//!    voxels ([`VoxelMap::large_surfel`]: Eq. (5) with true counts, the surfel criteria and the
//!    0.15 m mean-to-plane test), else the small-scale surfel of the voxel holding `p_W` if that
//!    voxel has converged ([`VoxelMap::small_surfel_at`]) and `p_W` is within
//!    `small_surfel_max_residual` of it, else the point-to-plane fallback. `PlaneOnly` (the
//!    paper's LOG-C) and `Plain` go straight to point-to-plane: a plane fitted to the remaining
//!    neighbours, accepted only if every one lies within `plane_max_dist` of it (`no_plane`
//!    otherwise). With a normal to compare (modes `Full`, `PlaneOnly`: the point's own, else
//!    its neighbours' mean) the fitted normal must be within `plane_max_normal_angle_deg` of
//!    it, and where the neighbours lie along a line (one scan ring: their middle eigenvalue
//!    under `plane_line_spread` of the largest), which fixes no normal about it, a fit more
//!    than `plane_line_angle_deg` off takes that normal instead.
//! 5. **Residual test.** With `r` the signed distance of `p_W` from the chosen element and `|p|`
//!    the point's range, the residual is kept if `residual_gate · r² < |p|` (the reference's
//!    `1 - 0.9 |r| / sqrt(|p|) > 0.9`, i.e. `81 r² < |p|`), else `rejected_residual`.
//!
//! `Plain` (FAST-LIO2-like) uses no normals and no checks: steps 1, point-to-plane, 5.
//!
//! The measurement is `r = n · p_W + d` with its Jacobian row from
//! [`PointToPlane::row`]; surfel and plane residuals have their own noise variance
//! (`surfel_variance`, `plane_variance`; the reference uses 0.001 m² for every residual).
//!
//! ## Iterations
//! [`ScanAssociation`] implements [`Measurements`]. The search (steps 1-5) runs at the first
//! iteration and again whenever the iterate has moved more than `research_pos` /
//! `research_rot` since the last search; in between, the stored correspondences (world planes)
//! are re-linearised at the new iterate, which costs a few products per point.
//!
//! ## Speed
//! A search goes through the points in chunks of [`KNN_CHUNK`]: their k-NN queries go to the
//! map together, then steps 2-4 run per point up to the large surfel's eigen-analysis or the
//! point-to-plane fit. The chunk's large surfels are analysed [`PLANE_LANES`] at a time
//! ([`surfel::eigen_normals_lanes`]), those without one go on to the small surfel, and the
//! plane fits run [`PLANE_LANES`] at a time ([`surfel::fit_plane_lanes`]); both give the same
//! results as one at a time, with the chains of square roots and divisions overlapping. Then
//! step 5. Each linearisation sums the rows in eight fixed pieces of the points, each from zero,
//! merged in order: on the caller's threads the pieces run side by side, and the information is
//! the same, bit for bit, on any number of threads (an ordered reduction).
//!
//! Everything here is allocation-free: the caller lends the correspondence buffer and the k-NN
//! chunk buffers.

// `!(a <= b)` deliberately rejects NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use nalgebra::{Matrix3, Vector3};

type M3 = Matrix3<f64>;

use crate::clock::Clock;
use crate::downsample::normal_is_valid;
use crate::eskf::{InfoAccumulator, Measurements, PointToPlane, State};
use crate::output::AssociationCounts;
use crate::parallel::{self, Parallel};
use crate::scan::ScanPoint;
use crate::surfel::{self, PLANE_LANES, SurfelReject};
use crate::voxel_map::{
    KNN_MAX, KnnQuery, KnnReach, LargeMerge, LargeSurfel, Neighbours, VoxelHandle, VoxelMap,
};

/// Which association the update uses (the paper's ablation). The one definition: the host's
/// config key `mapping.association` and its `--mode` take it as is (`full`, `plane-only`,
/// `plain`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum AssociationMode {
    /// LOG-LIO: visibility and consistency checks, then large surfel, small surfel,
    /// point-to-plane.
    #[default]
    #[cfg_attr(
        feature = "clap",
        value(help = "LOG-LIO: surfels and point-to-plane behind the normal checks")
    )]
    Full,
    /// The paper's LOG-C: the checks and point-to-plane only (no surfels).
    #[cfg_attr(feature = "clap", value(help = "LOG-C: point-to-plane behind the normal checks"))]
    PlaneOnly,
    /// No normals and no checks: point-to-plane as FAST-LIO2 does it.
    #[cfg_attr(feature = "clap", value(help = "FAST-LIO2-like point-to-plane, no normals"))]
    Plain,
}

type V3 = Vector3<f64>;

/// The measurement budget's default ([`AssociationConfig::max_points`]): downsampled points
/// measured per scan. A VLP-32C street scan has about 18,000, a VLP-16 or OS1-16 one 5,000 to
/// 7,000 ([`crate::selection`]). With the Cauchy kernel ([`AssociationConfig::robust_sigmas`])
/// 3,000 gave the simulated drives' errors of 5,000, but on the drone full mode then no longer
/// beat plane-only (docs/estimation.md).
pub const DEFAULT_MAX_POINTS: u32 = 5000;

/// Points whose k-NN queries go to the map together ([`VoxelMap::knn_many`]).
pub const KNN_CHUNK: usize = 64;

/// Association settings (defaults: the paper's and the reference's values).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct AssociationConfig {
    /// Neighbours searched per point (at most [`KNN_MAX`]). Default 5 (the reference's
    /// `NUM_MATCH_POINTS`).
    pub k: u8,
    /// Fewest neighbours (after the visibility check) a point needs, at least 3. Default 4.
    pub min_neighbours: u8,
    /// Neighbours farther than this are not used, metres. Default 1.0 (the k-NN is exact
    /// within the voxel size and searches the 27 voxels around the point beyond it).
    pub max_dist: f32,
    /// Consistency check: largest mean angle between the point's normal and its neighbours'
    /// normals, degrees. Default 60 (the paper's `alpha`).
    pub max_mean_angle_deg: f32,
    /// Point-to-plane: every neighbour must lie within this of the fitted plane, metres.
    /// Default 0.1 (the reference's `esti_plane`).
    pub plane_max_dist: f32,
    /// Point-to-plane (modes `Full`, `PlaneOnly`): the fitted plane's normal must lie within
    /// this of the point's own normal (its Ring FALS normal; without one, the mean of the
    /// neighbours' normals), degrees; 180 disables the test. Default 30. Neighbours from one
    /// scan ring fit a plane *across* the surface they lie on (a ring crossing a corridor is a
    /// U in one cross-section, accepted by the distance test with a normal along the axis):
    /// such planes pin the estimate to the ring pattern the map was built from.
    pub plane_max_normal_angle_deg: f32,
    /// Point-to-plane: neighbours that lie along a line (their middle eigenvalue under this
    /// share of the largest, [`surfel::Plane::spread`]) fix no normal about it, only the line;
    /// where their fit's normal leaves the one `plane_max_normal_angle_deg` compares it with
    /// by more than `plane_line_angle_deg`, that normal is taken instead (the plane through
    /// the line that the surface around the point has). 0 disables it. Default 0 (off: 0.03
    /// gives 0.86x the ATE on the simulated vehicle, but sets a VLP-16 walk back after a 5 s
    /// LiDAR gap by 1.6x).
    pub plane_line_spread: f32,
    /// The angle beyond which a line-like fit's normal gives way to the point's, degrees.
    /// Default 5.
    pub plane_line_angle_deg: f32,
    /// Small surfel: the point must lie within this of it, metres. Default 0.2 (reference).
    pub small_surfel_max_residual: f32,
    /// Residual test: keep a residual `r` of a point at range `|p|` if `gate · r² < |p|`.
    /// Default 81 (the reference's `s > 0.9`).
    pub residual_gate: f32,
    /// Noise variance of a point-to-surfel residual, m². Default 0.001.
    pub surfel_variance: f64,
    /// Noise variance of a point-to-plane residual, m². Default 0.001.
    pub plane_variance: f64,
    /// Measurement budget: at most this many downsampled points (evenly spread over their
    /// order, the voxels' Morton order) are associated and measured, each standing for its
    /// share of the rest ([`crate::selection`]); the map still receives them all. 0: no limit.
    /// Default [`DEFAULT_MAX_POINTS`].
    pub max_points: u32,
    /// Search again when the iterate's position moved more than this since the last search, m.
    pub research_pos: f64,
    /// ... or its rotation by more than this, rad.
    pub research_rot: f64,
    /// Which map voxels the k-NN searches. Default [`KnnReach::Block`] (the point's octant
    /// block first): 0.9x the association's time of [`KnnReach::Exact`] on the simulated
    /// VLP-32C drive with the same errors on well-posed scenes. Its more local neighbours once
    /// let the scans drag the vehicle along a featureless corridor's axis (26.9 m over 151 m
    /// against 5.9 m exact; IMU alone 8.6 m): the scans set the accelerometer bias along the
    /// axis during the stand at the start. With the standstill updates on (the default since
    /// 2026-12-07, [`crate::standstill`]) the stand holds it, and the worst error along the
    /// axis is 2.6 m with the block search against 5.3 m exact (docs/estimation.md).
    pub knn_reach: KnnReach,
    /// The Cauchy kernel's scale, in standard deviations of the residual's noise: at every
    /// iteration each residual `r` (of variance `v`) is weighted by `1 / (1 + r² / (c² v))`,
    /// `c` this value (iteratively reweighted least squares). A point within the noise keeps
    /// nearly all its weight (0.9 at one standard deviation, 3 cm with the default variances);
    /// one that the residual test lets through 30 cm off its plane (a moving object's point no
    /// free-space test caught, a wrong correspondence) keeps a tenth. 0 disables it (plain
    /// least squares, as the reference). Default 3.
    pub robust_sigmas: f64,
}

impl AssociationConfig {
    /// The defaults documented on each field.
    pub const DEFAULT: Self = Self {
        k: 5,
        min_neighbours: 4,
        max_dist: 1.0,
        max_mean_angle_deg: 60.0,
        plane_max_dist: 0.1,
        plane_max_normal_angle_deg: 30.0,
        plane_line_spread: 0.0,
        plane_line_angle_deg: 5.0,
        small_surfel_max_residual: 0.2,
        residual_gate: 81.0,
        surfel_variance: 0.001,
        plane_variance: 0.001,
        max_points: DEFAULT_MAX_POINTS,
        research_pos: 0.05,
        research_rot: 0.005,
        knn_reach: KnnReach::Block,
        robust_sigmas: 3.0,
    };

    /// Whether every setting is usable (the name of the first that is not).
    pub fn validate(&self) -> Result<(), &'static str> {
        if self.k < 3 || usize::from(self.k) > KNN_MAX {
            return Err("association.k");
        }
        if self.min_neighbours < 3 || self.min_neighbours > self.k {
            return Err("association.min_neighbours");
        }
        if !(self.max_dist > 0.0 && self.max_dist.is_finite()) {
            return Err("association.max_dist");
        }
        if !(self.max_mean_angle_deg >= 0.0 && self.max_mean_angle_deg <= 180.0) {
            return Err("association.max_mean_angle_deg");
        }
        if !(self.plane_max_dist > 0.0 && self.plane_max_dist.is_finite()) {
            return Err("association.plane_max_dist");
        }
        if !(self.plane_max_normal_angle_deg >= 0.0 && self.plane_max_normal_angle_deg <= 180.0) {
            return Err("association.plane_max_normal_angle_deg");
        }
        if !(self.plane_line_spread >= 0.0 && self.plane_line_spread <= 1.0) {
            return Err("association.plane_line_spread");
        }
        if !(self.plane_line_angle_deg >= 0.0 && self.plane_line_angle_deg <= 90.0) {
            return Err("association.plane_line_angle_deg");
        }
        if !(self.small_surfel_max_residual >= 0.0 && self.small_surfel_max_residual.is_finite()) {
            return Err("association.small_surfel_max_residual");
        }
        if !(self.residual_gate >= 0.0 && self.residual_gate.is_finite()) {
            return Err("association.residual_gate");
        }
        if !(self.surfel_variance > 0.0 && self.surfel_variance.is_finite()) {
            return Err("association.surfel_variance");
        }
        if !(self.plane_variance > 0.0 && self.plane_variance.is_finite()) {
            return Err("association.plane_variance");
        }
        if !(self.robust_sigmas >= 0.0 && self.robust_sigmas.is_finite()) {
            return Err("association.robust_sigmas");
        }
        if !(self.research_pos >= 0.0 && self.research_rot >= 0.0) {
            return Err("association.research");
        }
        Ok(())
    }
}

impl Default for AssociationConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Which map element a point is measured against.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Kind {
    /// No correspondence.
    #[default]
    None,
    /// A large-scale surfel (merged voxels).
    LargeSurfel,
    /// The small-scale surfel of the point's own voxel.
    SmallSurfel,
    /// A plane fitted to the nearest map points.
    Plane,
}

/// Why a point got no correspondence.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Reject {
    /// Fewer than `min_neighbours` map points near it.
    NoNeighbours,
    /// Too few visible neighbours.
    Visibility,
    /// The mean normal angle exceeds the limit.
    Consistency,
    /// No surfel, and the neighbours are not coplanar.
    NoPlane,
    /// The residual test failed.
    Residual,
}

/// One point's correspondence: the world plane `{q : normal · q + d = 0}` it is measured
/// against.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Correspondence {
    /// Unit normal, world frame.
    pub normal: [f32; 3],
    /// Offset, metres (`-normal · q0` for a point `q0` on the element).
    pub d: f64,
    /// The element's kind ([`Kind::None`]: no correspondence).
    pub kind: Kind,
}

impl Correspondence {
    /// No correspondence.
    pub const NONE: Self = Self { normal: [0.0; 3], d: 0.0, kind: Kind::None };

    fn through(normal: [f32; 3], q: [f32; 3], kind: Kind) -> Self {
        let d = -(f64::from(normal[0]) * f64::from(q[0])
            + f64::from(normal[1]) * f64::from(q[1])
            + f64::from(normal[2]) * f64::from(q[2]));
        Self { normal, d, kind }
    }

    /// Signed distance of world point `p` from the element.
    pub fn distance(&self, p: [f32; 3]) -> f64 {
        f64::from(self.normal[0]) * f64::from(p[0])
            + f64::from(self.normal[1]) * f64::from(p[1])
            + f64::from(self.normal[2]) * f64::from(p[2])
            + self.d
    }
}

/// Associates one point (steps 2-5 of the module docs) given its neighbours `nb` (step 1).
///
/// `p_w` is the point in the world, `n_w` its world normal (`None` or any invalid value: no
/// normal), `origin` the LiDAR origin in the world, `range` the point's range in the LiDAR frame.
#[allow(clippy::too_many_arguments)]
pub fn associate_point(
    map: &VoxelMap<'_>,
    cfg: &AssociationConfig,
    mode: AssociationMode,
    p_w: [f32; 3],
    n_w: Option<[f32; 3]>,
    origin: [f32; 3],
    range: f32,
    nb: &Neighbours,
) -> Result<Correspondence, Reject> {
    Associator::new(map, cfg, mode, origin).point(p_w, n_w, range, nb)
}

/// What every point of one search shares: the map, the settings and mode, the LiDAR origin,
/// and the cosines of the angle limits (computed once per search, not per point).
struct Associator<'a, 'm> {
    map: &'a VoxelMap<'m>,
    cfg: &'a AssociationConfig,
    mode: AssociationMode,
    origin: [f32; 3],
    /// `cos(max_mean_angle_deg)`.
    cos_mean_angle: f32,
    /// `cos(plane_max_normal_angle_deg)`.
    cos_plane_normal: f32,
    /// `cos(plane_line_angle_deg)`.
    cos_line_normal: f32,
}

impl<'a, 'm> Associator<'a, 'm> {
    fn new(
        map: &'a VoxelMap<'m>,
        cfg: &'a AssociationConfig,
        mode: AssociationMode,
        origin: [f32; 3],
    ) -> Self {
        Self {
            map,
            cfg,
            mode,
            origin,
            cos_mean_angle: libm::cosf(cfg.max_mean_angle_deg.to_radians()),
            cos_plane_normal: libm::cosf(cfg.plane_max_normal_angle_deg.to_radians()),
            cos_line_normal: libm::cosf(cfg.plane_line_angle_deg.to_radians()),
        }
    }

    /// [`associate_point`] for one point.
    #[inline]
    fn point(
        &self,
        p_w: [f32; 3],
        n_w: Option<[f32; 3]>,
        range: f32,
        nb: &Neighbours,
    ) -> Result<Correspondence, Reject> {
        let next = match self.head(p_w, n_w, range, nb)? {
            Head::Done(c) => Next::Done(c),
            Head::Plane(f) => Next::Plane(f),
            Head::Large(m, f) => {
                let shape = surfel::Shape::of_covariance(&m.covariance());
                self.large_or_next(self.map.large_surfel_finish(&m, shape.eigenvalues, shape.normal()), f)?
            }
        };
        match next {
            Next::Done(c) => Ok(c),
            Next::Plane(f) => self.tail(&f, surfel::fit_plane(&f.pts[..f.len], self.cfg.plane_max_dist)),
        }
    }

    /// Steps 2-4 up to the plane fit (and step 5 for a surfel): a correspondence or rejection,
    /// or the point-to-plane fit still to do (which [`ScanAssociation`] runs for several points
    /// at once).
    #[inline]
    fn head(
        &self,
        p_w: [f32; 3],
        n_w: Option<[f32; 3]>,
        range: f32,
        nb: &Neighbours,
    ) -> Result<Head, Reject> {
        let (map, cfg, mode, origin) = (self.map, self.cfg, self.mode, self.origin);
        let min_nb = usize::from(cfg.min_neighbours.max(3));
        if nb.len() < min_nb {
            return Err(Reject::NoNeighbours);
        }
        let mut pts = [[0.0f32; 3]; KNN_MAX];
        let mut voxels = [VoxelHandle(0); KNN_MAX];
        let mut m = 0usize;
        // The direction a fitted plane's normal must agree with (point-to-plane check).
        let mut expect: Option<[f32; 3]> = None;
        if mode == AssociationMode::Plain {
            for n in nb.as_slice() {
                pts[m] = n.point;
                voxels[m] = n.voxel;
                m += 1;
            }
        } else {
            let ray = [origin[0] - p_w[0], origin[1] - p_w[1], origin[2] - p_w[2]];
            let query_n = n_w.filter(normal_is_valid);
            let mut nb_sum = [0.0f32; 3];
            let mut angle_sum = 0.0f32;
            let mut angle_n = 0u32;
            let mut all_close = true; // every dot >= cos(max angle): the mean passes without acos
            let cos_max = self.cos_mean_angle;
            let mut dots = [0.0f32; KNN_MAX];
            for n in nb.as_slice() {
                if let Some(mn) = n.normal() {
                    if !(dot(mn, ray) > 0.0) {
                        continue; // behind the surface as seen from here
                    }
                    for a in 0..3 {
                        nb_sum[a] += mn[a];
                    }
                    if let Some(q) = query_n {
                        let c = dot(q, mn).clamp(-1.0, 1.0);
                        all_close &= c >= cos_max;
                        dots[angle_n as usize] = c;
                        angle_n += 1;
                    }
                }
                pts[m] = n.point;
                voxels[m] = n.voxel;
                m += 1;
            }
            if m < min_nb {
                return Err(Reject::Visibility);
            }
            expect = query_n.or_else(|| {
                let l = crate::math::sqrtf(dot(nb_sum, nb_sum));
                (l > 0.0).then(|| [nb_sum[0] / l, nb_sum[1] / l, nb_sum[2] / l])
            });
            if angle_n > 0 && !all_close {
                for c in &dots[..angle_n as usize] {
                    angle_sum += libm::acosf(*c);
                }
                if !(angle_sum / angle_n as f32 <= cfg.max_mean_angle_deg.to_radians()) {
                    return Err(Reject::Consistency);
                }
            }
        }
        let fit = PlaneFit { pts, len: m, expect, p_w, range };
        if mode == AssociationMode::Full {
            // The large surfel's eigen-analysis waits for the chunk's others
            // ([`ScanAssociation`] runs them [`PLANE_LANES`] at a time).
            if let Ok(merge) = map.large_surfel_merge(&voxels[..m]) {
                return Ok(Head::Large(merge, fit));
            }
            return self.after_large(fit).map(Head::from);
        }
        Ok(Head::Plane(fit))
    }

    /// Step 4 after the large surfel: its correspondence if `large` is one, else the small
    /// surfel, else the point-to-plane fit still to do.
    #[inline]
    fn large_or_next(&self, large: Result<LargeSurfel, SurfelReject>, f: PlaneFit) -> Result<Next, Reject> {
        match large {
            Ok(s) => {
                let c = Correspondence::through(s.normal, s.mean, Kind::LargeSurfel);
                self.residual_test(c, f.p_w, f.range).map(Next::Done)
            }
            Err(_) => self.after_large(f),
        }
    }

    /// Step 4 without a large surfel: the small surfel of the point's voxel, else the
    /// point-to-plane fit still to do.
    #[inline]
    fn after_large(&self, f: PlaneFit) -> Result<Next, Reject> {
        if let Ok(s) = self.map.small_surfel_at(f.p_w) {
            let c = Correspondence::through(s.normal, s.mean, Kind::SmallSurfel);
            if libm::fabs(c.distance(f.p_w)) <= f64::from(self.cfg.small_surfel_max_residual) {
                return self.residual_test(c, f.p_w, f.range).map(Next::Done);
            }
        }
        Ok(Next::Plane(f))
    }

    /// The point-to-plane fallback's verdict on `fit` (the plane of `f.pts`), then step 5.
    #[inline]
    fn tail(
        &self,
        f: &PlaneFit,
        fit: Result<surfel::Plane, surfel::SurfelReject>,
    ) -> Result<Correspondence, Reject> {
        let Ok(pl) = fit else { return Err(Reject::NoPlane) };
        let mut normal = pl.normal;
        if let Some(e) = f.expect {
            // Orientation-free: a plane's normal has no sign.
            let c = libm::fabsf(dot(e, pl.normal));
            if !(c >= self.cos_plane_normal) {
                return Err(Reject::NoPlane);
            }
            if pl.spread < self.cfg.plane_line_spread && !(c >= self.cos_line_normal) {
                // A line's fit: its normal is any about the line; the surface's is known.
                normal = e;
            }
        }
        self.residual_test(Correspondence::through(normal, pl.centroid, Kind::Plane), f.p_w, f.range)
    }

    /// Step 5.
    #[inline]
    fn residual_test(
        &self,
        corr: Correspondence,
        p_w: [f32; 3],
        range: f32,
    ) -> Result<Correspondence, Reject> {
        let r = corr.distance(p_w);
        if !(f64::from(self.cfg.residual_gate) * r * r < f64::from(range)) {
            return Err(Reject::Residual);
        }
        Ok(corr)
    }
}

/// Where [`Associator::head`] got to. Moved by value into the chunk's buffers (there is no
/// allocator to box the large variant in, and each lives for one point).
#[allow(clippy::large_enum_variant)]
enum Head {
    /// A surfel correspondence that passed the residual test.
    Done(Correspondence),
    /// The large surfel's eigen-analysis is next (then, without a surfel, the small surfel and
    /// the point-to-plane fallback).
    Large(LargeMerge, PlaneFit),
    /// The point-to-plane fallback is next.
    Plane(PlaneFit),
}

/// What is left after step 4's surfels.
enum Next {
    /// A surfel correspondence that passed the residual test.
    Done(Correspondence),
    /// The point-to-plane fallback is next.
    Plane(PlaneFit),
}

impl From<Next> for Head {
    fn from(n: Next) -> Self {
        match n {
            Next::Done(c) => Head::Done(c),
            Next::Plane(f) => Head::Plane(f),
        }
    }
}

/// A point waiting for its point-to-plane fit: the neighbours to fit, and what the verdict
/// needs.
#[derive(Clone, Copy)]
struct PlaneFit {
    pts: [[f32; 3]; KNN_MAX],
    len: usize,
    expect: Option<[f32; 3]>,
    p_w: [f32; 3],
    range: f32,
}

impl PlaneFit {
    const EMPTY: Self = Self { pts: [[0.0; 3]; KNN_MAX], len: 0, expect: None, p_w: [0.0; 3], range: 0.0 };
}

#[inline]
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
fn to32(v: &V3) -> [f32; 3] {
    [v.x as f32, v.y as f32, v.z as f32]
}

/// The measurements of one scan for [`crate::eskf::Eskf::update`]: the downsampled points
/// (LiDAR frame at the scan end) and their normals, associated with the map at each iterate.
pub struct ScanAssociation<'a, 'm, C: Clock> {
    map: &'a VoxelMap<'m>,
    cfg: &'a AssociationConfig,
    mode: AssociationMode,
    points: &'a [ScanPoint],
    normals: &'a [[f32; 3]],
    corr: &'a mut [Correspondence],
    queries: &'a mut [[f32; 3]; KNN_CHUNK],
    nbrs: &'a mut [Neighbours; KNN_CHUNK],
    counts: AssociationCounts,
    first: Option<AssociationCounts>,
    searched: Option<State>,
    searches: u32,
    stands_for: f64,
    clock: &'a mut C,
    elapsed_ns: u64,
    /// The caller's threads and one k-NN scratch per extra thread ([`Self::with_parallel`]).
    parallel: Option<(&'a dyn Parallel, &'a mut [KnnScratch])>,
}

impl<C: Clock> core::fmt::Debug for ScanAssociation<'_, '_, C> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("ScanAssociation")
            .field("mode", &self.mode)
            .field("points", &self.points.len())
            .field("counts", &self.counts)
            .field("searches", &self.searches)
            .finish()
    }
}

impl<'a, 'm, C: Clock> ScanAssociation<'a, 'm, C> {
    /// The measurements of `points` (with `normals`, the same length; [`crate::downsample::INVALID_NORMAL`]
    /// where none) against `map`. `corr` must hold at least `points.len()` entries (extra points
    /// are ignored); `queries` and `nbrs` are k-NN scratch; `clock` times the association.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        map: &'a VoxelMap<'m>,
        cfg: &'a AssociationConfig,
        mode: AssociationMode,
        points: &'a [ScanPoint],
        normals: &'a [[f32; 3]],
        corr: &'a mut [Correspondence],
        queries: &'a mut [[f32; 3]; KNN_CHUNK],
        nbrs: &'a mut [Neighbours; KNN_CHUNK],
        clock: &'a mut C,
    ) -> Self {
        let n = points.len().min(normals.len()).min(corr.len());
        Self {
            map,
            cfg,
            mode,
            points: &points[..n],
            normals: &normals[..n],
            corr,
            queries,
            nbrs,
            counts: AssociationCounts::default(),
            first: None,
            searched: None,
            searches: 0,
            stands_for: 1.0,
            clock,
            elapsed_ns: 0,
            parallel: None,
        }
    }

    /// Splits each search over `parallel`'s threads (at most one more than `scratch` holds);
    /// the correspondences and counts are the same as without.
    pub fn with_parallel(mut self, parallel: &'a dyn Parallel, scratch: &'a mut [KnnScratch]) -> Self {
        self.parallel = Some((parallel, scratch));
        self
    }

    /// Each point measured stands for `k >= 1` points of the scan (a measurement budget,
    /// [`crate::selection`]): its residual's variance is divided by `k`, so the scan weighs in
    /// the update as all its points would. 1 (the default) changes nothing.
    pub fn standing_for(mut self, k: f64) -> Self {
        if k.is_finite() && k >= 1.0 {
            self.stands_for = k;
        }
        self
    }

    /// The counts of the last search.
    pub fn counts(&self) -> AssociationCounts {
        self.counts
    }

    /// The counts of the first search (at the predicted pose, before the update moved it).
    pub fn first_counts(&self) -> AssociationCounts {
        self.first.unwrap_or(self.counts)
    }

    /// How many searches ran (the rest of the iterations reused the correspondences).
    pub fn searches(&self) -> u32 {
        self.searches
    }

    /// Time spent in [`Measurements::linearize`], ns (0 with a clock that reads 0).
    pub fn elapsed_ns(&self) -> u64 {
        self.elapsed_ns
    }

    /// The correspondences of the last search, one per point.
    pub fn correspondences(&self) -> &[Correspondence] {
        &self.corr[..self.points.len()]
    }

    fn needs_search(&self, x: &State) -> bool {
        match &self.searched {
            None => true,
            Some(s) => {
                let dp = (x.pos - s.pos).amax();
                let dr = (s.rot.inverse() * x.rot).angle();
                !(dp <= self.cfg.research_pos && dr <= self.cfg.research_rot)
            }
        }
    }

    fn search(&mut self, x: &State) {
        let r = x.rot.to_rotation_matrix().into_inner();
        let ctx = SearchCtx {
            h: PointToPlane::new(x),
            r_wl: r * x.ext_rot.to_rotation_matrix().into_inner(),
            query: KnnQuery::new(usize::from(self.cfg.k).min(KNN_MAX), self.cfg.max_dist)
                .with_reach(self.cfg.knn_reach),
            assoc: Associator::new(self.map, self.cfg, self.mode, to32(&(r * x.ext_pos + x.pos))),
            map: self.map,
            mode: self.mode,
            plane_max_dist: self.cfg.plane_max_dist,
        };
        let n = self.points.len();
        let width = match &self.parallel {
            Some((p, scratch)) => p.width().min(scratch.len() + 1),
            None => 1,
        };
        let counts = if width <= 1 || n < 2 * KNN_CHUNK {
            search_range(&ctx, self.points, self.normals, &mut self.corr[..n], self.queries, self.nbrs)
        } else {
            // Independent pieces on the caller's threads, each into its own slots; the counts
            // are summed in piece order (integers: the same for any width).
            let Some((par, scratch)) = &mut self.parallel else { unreachable!("width > 1") };
            let ends = parallel::split(n, width, KNN_CHUNK);
            let mut parts = [AssociationCounts::default(); parallel::MAX_WIDTH];
            {
                let mut corr = &mut self.corr[..n];
                let mut scratch = core::iter::once((&mut *self.queries, &mut *self.nbrs))
                    .chain(scratch.iter_mut().map(|s| (&mut s.queries, &mut s.nbrs)));
                let (points, normals, ctx) = (self.points, self.normals, &ctx);
                let mut closures = heapless::Vec::<_, { parallel::MAX_WIDTH }>::new();
                let mut start = 0;
                for (&end, out) in ends.iter().zip(parts.iter_mut()) {
                    let (c, rest) = core::mem::take(&mut corr).split_at_mut(end - start);
                    corr = rest;
                    let Some((q, nb)) = scratch.next() else { break };
                    let (pts, nrm) = (&points[start..end], &normals[start..end]);
                    // Cannot fail: at most MAX_WIDTH pieces.
                    let _ = closures.push(move || *out = search_range(ctx, pts, nrm, c, q, nb));
                    start = end;
                }
                let mut jobs = heapless::Vec::<parallel::Job<'_>, { parallel::MAX_WIDTH }>::new();
                for c in closures.iter_mut() {
                    let _ = jobs.push(c);
                }
                par.run(&mut jobs);
            }
            parts.iter().fold(AssociationCounts::default(), |a, b| a.plus(b))
        };
        self.counts = counts;
        if self.first.is_none() {
            self.first = Some(counts);
        }
        self.searched = Some(*x);
        self.searches += 1;
    }
}

/// One linearisation's rows and weights, shared by its pieces.
struct Weights {
    h: PointToPlane,
    surfel_var: f64,
    plane_var: f64,
    surfel_k: f64,
    plane_k: f64,
}

impl Weights {
    /// Adds the rows of `points` with their correspondences to `acc`.
    #[inline]
    fn add(&self, acc: &mut InfoAccumulator, points: &[ScanPoint], corr: &[Correspondence]) {
        for (p, c) in points.iter().zip(corr.iter()) {
            let (var, k) = match c.kind {
                Kind::None => continue,
                Kind::LargeSurfel | Kind::SmallSurfel => (self.surfel_var, self.surfel_k),
                Kind::Plane => (self.plane_var, self.plane_k),
            };
            let [px, py, pz] = p.xyz;
            let p_l = V3::new(f64::from(px), f64::from(py), f64::from(pz));
            let n = V3::new(f64::from(c.normal[0]), f64::from(c.normal[1]), f64::from(c.normal[2]));
            let (r, row) = self.h.row(&p_l, &n, c.d);
            // The weight divides the information: the variance grows by `1 + r² / (c² v)`.
            acc.add(&row, r, var * (1.0 + k * r * r));
        }
    }
}

/// The pieces `ends` of a linearisation on `par`'s threads (consecutive pieces per thread),
/// each into its own accumulator, merged into `acc` in piece order. Out of line: its
/// accumulators stay off the stack of the one-thread path (the firmware's).
#[inline(never)]
fn linearize_pieces(
    par: &dyn Parallel,
    w: &Weights,
    points: &[ScanPoint],
    corr: &[Correspondence],
    ends: &[usize],
    acc: &mut InfoAccumulator,
) {
    let mut parts: [InfoAccumulator; parallel::MAX_WIDTH] = core::array::from_fn(|_| acc.empty_like());
    let groups = parallel::split(ends.len(), par.width(), 1);
    {
        let mut rest = &mut parts[..ends.len()];
        let mut closures = heapless::Vec::<_, { parallel::MAX_WIDTH }>::new();
        let mut first = 0;
        for &last in &groups {
            let (mine, r) = core::mem::take(&mut rest).split_at_mut(last - first);
            rest = r;
            let pieces = first..last;
            let _ = closures.push(move || {
                for (part, k) in mine.iter_mut().zip(pieces.clone()) {
                    let start = if k == 0 { 0 } else { ends[k - 1] };
                    w.add(part, &points[start..ends[k]], &corr[start..ends[k]]);
                }
            });
            first = last;
        }
        let mut jobs = heapless::Vec::<parallel::Job<'_>, { parallel::MAX_WIDTH }>::new();
        for c in closures.iter_mut() {
            let _ = jobs.push(c);
        }
        par.run(&mut jobs);
    }
    for part in &parts[..ends.len()] {
        acc.merge(part);
    }
}

/// What a search needs at one state, shared by the pieces.
struct SearchCtx<'a, 'm> {
    h: PointToPlane,
    r_wl: M3,
    query: KnnQuery,
    assoc: Associator<'a, 'm>,
    map: &'a VoxelMap<'m>,
    mode: AssociationMode,
    plane_max_dist: f32,
}

/// The k-NN scratch of one piece of a search run in parallel (the first piece uses the
/// association's own): caller-owned, one per extra thread.
#[derive(Clone, Copy, Debug)]
pub struct KnnScratch {
    /// Query points of a chunk.
    pub queries: [[f32; 3]; KNN_CHUNK],
    /// Their neighbours.
    pub nbrs: [Neighbours; KNN_CHUNK],
}

impl KnnScratch {
    /// Empty scratch.
    pub const fn new() -> Self {
        Self { queries: [[0.0; 3]; KNN_CHUNK], nbrs: [Neighbours::new(); KNN_CHUNK] }
    }
}

impl Default for KnnScratch {
    fn default() -> Self {
        Self::new()
    }
}

/// Associates `points` (with `normals`) into `corr` (the same length), [`KNN_CHUNK`] at a time.
fn search_range(
    ctx: &SearchCtx<'_, '_>,
    points: &[ScanPoint],
    normals: &[[f32; 3]],
    corr: &mut [Correspondence],
    queries: &mut [[f32; 3]; KNN_CHUNK],
    nbrs: &mut [Neighbours; KNN_CHUNK],
) -> AssociationCounts {
    let assoc = &ctx.assoc;
    let mut counts = AssociationCounts::default();
    let n = points.len().min(normals.len()).min(corr.len());
    let mut start = 0;
    let mut fits = [(0usize, PlaneFit::EMPTY); KNN_CHUNK];
    let mut larges = [(0usize, PlaneFit::EMPTY, LargeMerge::EMPTY); KNN_CHUNK];
    while start < n {
        let len = (n - start).min(KNN_CHUNK);
        for i in 0..len {
            let [px, py, pz] = points[start + i].xyz;
            queries[i] = to32(&ctx.h.to_world(&V3::new(f64::from(px), f64::from(py), f64::from(pz))));
        }
        ctx.map.knn_many(&queries[..len], &ctx.query, &mut nbrs[..len]);
        let (mut nfit, mut nlarge) = (0, 0);
        for i in 0..len {
            let j = start + i;
            let p = &points[j];
            let nl = normals[j];
            let n_w = if ctx.mode != AssociationMode::Plain && normal_is_valid(&nl) {
                Some(to32(&(ctx.r_wl * V3::new(f64::from(nl[0]), f64::from(nl[1]), f64::from(nl[2])))))
            } else {
                None
            };
            let res = match assoc.head(queries[i], n_w, p.range(), &nbrs[i]) {
                Ok(Head::Plane(f)) => {
                    // Later, with the chunk's other plane fits.
                    fits[nfit] = (j, f);
                    nfit += 1;
                    continue;
                }
                Ok(Head::Large(m, f)) => {
                    // Later, with the chunk's other large surfels.
                    larges[nlarge] = (j, f, m);
                    nlarge += 1;
                    continue;
                }
                Ok(Head::Done(c)) => Ok(c),
                Err(e) => Err(e),
            };
            corr[j] = count(&mut counts, res);
        }
        // The large surfels' eigen-analyses, PLANE_LANES at a time (the same results as
        // one at a time); those without a surfel go on to the small surfel and the fits.
        for group in larges[..nlarge].chunks(PLANE_LANES) {
            let mut covs = [[0.0f64; 6]; PLANE_LANES];
            for (c, (_, _, m)) in covs.iter_mut().zip(group) {
                *c = m.covariance();
            }
            let shapes = surfel::eigen_normals_lanes(&covs, group.len());
            for ((j, f, m), (values, normal)) in group.iter().zip(shapes) {
                match assoc.large_or_next(ctx.map.large_surfel_finish(m, values, normal), *f) {
                    Ok(Next::Plane(f)) => {
                        fits[nfit] = (*j, f);
                        nfit += 1;
                    }
                    Ok(Next::Done(c)) => corr[*j] = count(&mut counts, Ok(c)),
                    Err(e) => corr[*j] = count(&mut counts, Err(e)),
                }
            }
        }
        // The plane fits, PLANE_LANES at a time (their chains of square roots and
        // divisions overlap); the same results as one at a time.
        for group in fits[..nfit].chunks(PLANE_LANES) {
            let mut pts = [[[0.0f32; 3]; KNN_MAX]; PLANE_LANES];
            let mut lens = [0usize; PLANE_LANES];
            for (l, (_, f)) in group.iter().enumerate() {
                pts[l] = f.pts;
                lens[l] = f.len;
            }
            let planes = surfel::fit_plane_lanes(&pts, lens, ctx.plane_max_dist);
            for ((j, f), fit) in group.iter().zip(planes) {
                corr[*j] = count(&mut counts, assoc.tail(f, fit));
            }
        }
        start += len;
    }
    counts
}

/// Counts a point's association and gives its correspondence ([`Correspondence::NONE`] if
/// rejected).
fn count(counts: &mut AssociationCounts, res: Result<Correspondence, Reject>) -> Correspondence {
    match res {
        Ok(c) => {
            match c.kind {
                Kind::LargeSurfel => counts.large_surfel += 1,
                Kind::SmallSurfel => counts.small_surfel += 1,
                Kind::Plane | Kind::None => counts.plane += 1,
            }
            c
        }
        Err(e) => {
            match e {
                Reject::NoNeighbours => counts.no_neighbours += 1,
                Reject::Visibility => counts.rejected_visibility += 1,
                Reject::Consistency => counts.rejected_consistency += 1,
                Reject::NoPlane => counts.no_plane += 1,
                Reject::Residual => counts.rejected_residual += 1,
            }
            Correspondence::NONE
        }
    }
}

impl<C: Clock> Measurements for ScanAssociation<'_, '_, C> {
    fn linearize(&mut self, x: &State, _iteration: usize, acc: &mut InfoAccumulator) {
        let t0 = self.clock.now_ns();
        if self.needs_search(x) {
            self.search(x);
        }
        let h = PointToPlane::new(x);
        // Exact when a point stands for itself (`v / 1.0 == v`).
        let (surfel_var, plane_var) =
            (self.cfg.surfel_variance / self.stands_for, self.cfg.plane_variance / self.stands_for);
        // The Cauchy kernel's `1 / (c² s²)` per kind, `s` the residuals' scale in their own
        // (unscaled) variance's units: the noise's standard deviation, or the spread of this
        // iterate's residuals where that is wider (a prediction far off: every residual large).
        let c2 = self.cfg.robust_sigmas * self.cfg.robust_sigmas;
        let (surfel_k, plane_k) = if c2 > 0.0 {
            let spread = self.residual_spread(&h);
            (1.0 / (c2 * self.cfg.surfel_variance * spread), 1.0 / (c2 * self.cfg.plane_variance * spread))
        } else {
            (0.0, 0.0)
        };
        let w = Weights { h, surfel_var, plane_var, surfel_k, plane_k };
        let n = self.points.len().min(self.corr.len());
        let (points, corr) = (&self.points[..n], &self.corr[..n]);
        // Fixed pieces, each summed from zero and merged in order: the same bits for any
        // number of threads (an ordered reduction).
        let ends = parallel::split(n, parallel::MAX_WIDTH, KNN_CHUNK);
        match &self.parallel {
            Some((par, _)) if par.width() > 1 && ends.len() > 1 => {
                linearize_pieces(*par, &w, points, corr, &ends, acc);
            }
            _ => {
                let mut start = 0;
                for &end in &ends {
                    let mut part = acc.empty_like();
                    w.add(&mut part, &points[start..end], &corr[start..end]);
                    acc.merge(&part);
                    start = end;
                }
            }
        }
        self.elapsed_ns = self.elapsed_ns.saturating_add(self.clock.now_ns().saturating_sub(t0));
    }
}

impl<C: Clock> ScanAssociation<'_, '_, C> {
    /// How much wider than their noise this iterate's residuals spread, squared (at least 1):
    /// the median absolute residual over its Gaussian value (0.6745 standard deviations), from a
    /// histogram of `|r| / sigma` in quarters of a standard deviation. At a good prediction it
    /// is 1 (the kernel acts on the outliers); where the prediction is off by more than the
    /// noise (a clipped gyro, a bridged gap) it widens the kernel with the residuals, so the
    /// update still moves the state by the whole scan instead of weighing most of it down.
    fn residual_spread(&self, h: &PointToPlane) -> f64 {
        const BINS: usize = 64;
        let mut hist = [0u32; BINS];
        let mut n = 0u32;
        let (surfel_sd, plane_sd) =
            (crate::math::sqrt(self.cfg.surfel_variance), crate::math::sqrt(self.cfg.plane_variance));
        for (p, c) in self.points.iter().zip(self.corr.iter()) {
            let sd = match c.kind {
                Kind::None => continue,
                Kind::LargeSurfel | Kind::SmallSurfel => surfel_sd,
                Kind::Plane => plane_sd,
            };
            let [px, py, pz] = p.xyz;
            let p_l = V3::new(f64::from(px), f64::from(py), f64::from(pz));
            let nv = V3::new(f64::from(c.normal[0]), f64::from(c.normal[1]), f64::from(c.normal[2]));
            let u = libm::fabs(h.residual(&p_l, &nv, c.d)) / sd * 4.0;
            // NaN and beyond the last bin land in the last bin.
            let b = if u < (BINS - 1) as f64 { u as usize } else { BINS - 1 };
            hist[b] += 1;
            n += 1;
        }
        if n == 0 {
            return 1.0;
        }
        let (half, mut seen) = (n.div_ceil(2), 0u32);
        let mut median = BINS - 1;
        for (b, &k) in hist.iter().enumerate() {
            seen += k;
            if seen >= half {
                median = b;
                break;
            }
        }
        let s = (median as f64 + 0.5) * 0.25 / 0.6745;
        (s * s).max(1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::voxel_map::{MapConfig, MapPoint, MapStorage};
    extern crate std;

    /// One scan ring crossing a corridor 5 m ahead: a U of points at x = 5 (floor at z = -1,
    /// walls at y = ±1.2), as a map built while standing still holds it.
    fn ring_cross_section(map: &mut VoxelMap<'_>) {
        let mut pts = [MapPoint { xyz: [0.0; 3], normal: None }; 64];
        let mut n = 0;
        for i in 0..24 {
            let y = -1.15 + 0.1 * i as f32;
            pts[n] = MapPoint { xyz: [5.0, y, -1.0], normal: Some([0.0, 0.0, 1.0]) };
            n += 1;
        }
        for i in 0..20 {
            let z = -0.95 + 0.1 * i as f32;
            pts[n] = MapPoint { xyz: [5.0, -1.2, z], normal: Some([0.0, 1.0, 0.0]) };
            pts[n + 1] = MapPoint { xyz: [5.0, 1.2, z], normal: Some([0.0, -1.0, 0.0]) };
            n += 2;
        }
        map.insert(pts[..n].iter().copied(), [0.0; 3], 1).unwrap();
    }

    /// The Cauchy kernel (`robust_sigmas`): a residual `r` enters with its variance times
    /// `1 + r² / (c² v)`. A floor 1.5 m below the LiDAR, 100 scan points on it and 20 of an
    /// object 0.25 m above it (well inside the residual test at 8-12 m): without the kernel
    /// each of the 20 weighs as a floor point; with c = 3 one weighs 1 / 7.9 of it.
    #[test]
    fn the_cauchy_kernel_weighs_points_off_their_plane_down() {
        use crate::clock::NoClock;
        use crate::eskf::{InfoAccumulator, State};
        use crate::so3::S2;
        use nalgebra::UnitQuaternion;
        let mut storage = MapStorage::<8192, 16384>::new();
        let mut map = storage.map(MapConfig::VLP32C).unwrap();
        let mut floor = std::vec::Vec::new();
        for i in 0..100 {
            for j in 0..60 {
                let (x, y) = (5.0 + 0.08 * i as f32, -2.4 + 0.08 * j as f32);
                floor.push(MapPoint { xyz: [x, y, -1.5], normal: Some([0.0, 0.0, 1.0]) });
            }
        }
        map.insert(floor.iter().copied(), [0.0; 3], 1).unwrap();
        let mut points = std::vec::Vec::new();
        for k in 0..120 {
            let (x, y) = (8.0 + 0.03 * (k % 60) as f32, -1.0 + 0.035 * (k / 2) as f32);
            let z = if k < 100 { -1.5 } else { -1.25 };
            points.push(ScanPoint { xyz: [x, y, z], ..ScanPoint::default() });
        }
        let normals = std::vec![[0.0f32, 0.0, 1.0]; points.len()];
        let x = State {
            rot: UnitQuaternion::identity(),
            pos: V3::zeros(),
            ext_rot: UnitQuaternion::identity(),
            ext_pos: V3::zeros(),
            vel: V3::zeros(),
            bg: V3::zeros(),
            ba: V3::zeros(),
            grav: S2::new(&V3::new(0.0, 0.0, -1.0), 9.81),
        };
        let info = |sigmas: f64| {
            let cfg = AssociationConfig { robust_sigmas: sigmas, ..AssociationConfig::DEFAULT };
            let mut corr = std::vec![Correspondence::NONE; points.len()];
            let (mut queries, mut nbrs) = ([[0.0f32; 3]; KNN_CHUNK], [Neighbours::new(); KNN_CHUNK]);
            let mut clock = NoClock;
            let mut assoc = ScanAssociation::new(
                &map,
                &cfg,
                AssociationMode::PlaneOnly,
                &points,
                &normals,
                &mut corr,
                &mut queries,
                &mut nbrs,
                &mut clock,
            );
            let mut acc = InfoAccumulator::new(false);
            assoc.linearize(&x, 0, &mut acc);
            assert_eq!(assoc.counts().accepted(), 120, "{:?}", assoc.counts());
            (acc.information()[(2, 2)], acc.weighted_sq_residual())
        };
        let v = AssociationConfig::DEFAULT.plane_variance;
        let ((plain_zz, plain_chi2), (robust_zz, robust_chi2)) = (info(0.0), info(3.0));
        let w = 1.0 / (1.0 + 0.0625 / (9.0 * v));
        let close = |a: f64, b: f64| (a / b - 1.0).abs() < 1e-3;
        assert!(close(plain_zz, 120.0 / v), "{plain_zz}");
        assert!(close(robust_zz, (100.0 + 20.0 * w) / v), "{robust_zz}");
        assert!(close(plain_chi2, 20.0 * 0.0625 / v), "{plain_chi2}");
        assert!(close(robust_chi2, 20.0 * 0.0625 * w / v), "{robust_chi2}");
    }

    #[test]
    fn a_plane_across_the_surface_is_refused_when_normals_are_known() {
        let mut storage = MapStorage::<1024, 2048>::new();
        let mut map = storage.map(MapConfig::VLP32C).unwrap();
        ring_cross_section(&mut map);
        let cfg = AssociationConfig::DEFAULT;
        // A floor point near the corner, a little ahead of the ring the map holds.
        let p = [5.05f32, -1.0, -1.0];
        let range = crate::math::sqrtf(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
        let mut nb = Neighbours::new();
        assert!(map.knn(p, &KnnQuery::new(5, 1.0), &mut nb) >= 4);

        // Without normals (FAST-LIO2-like) the U of floor and wall points fits the plane x = 5:
        // a residual along the corridor's axis that the scene does not have.
        let plain =
            associate_point(&map, &cfg, AssociationMode::Plain, p, None, [0.0; 3], range, &nb).unwrap();
        assert!(plain.normal[0].abs() > 0.9, "{:?}", plain.normal);

        // With the point's own normal (the floor's) that plane is refused ...
        let r = associate_point(
            &map,
            &cfg,
            AssociationMode::PlaneOnly,
            p,
            Some([0.0, 0.0, 1.0]),
            [0.0; 3],
            range,
            &nb,
        );
        assert_eq!(r, Err(Reject::NoPlane));
        // ... also without it (the neighbours' mean normal) ...
        let r = associate_point(&map, &cfg, AssociationMode::PlaneOnly, p, None, [0.0; 3], range, &nb);
        assert_eq!(r, Err(Reject::NoPlane));
        // ... and accepted when the check is switched off.
        let off = AssociationConfig { plane_max_normal_angle_deg: 180.0, ..cfg };
        let r = associate_point(
            &map,
            &off,
            AssociationMode::PlaneOnly,
            p,
            Some([0.0, 0.0, 1.0]),
            [0.0; 3],
            range,
            &nb,
        );
        assert!(r.is_ok_and(|c| c.normal[0].abs() > 0.9), "{r:?}");
    }

    #[test]
    fn a_line_of_neighbours_takes_the_points_normal() {
        // One scan ring on the floor z = -1: a line along y with a few mm of noise across it,
        // none in the direction `tilt` degrees from the vertical about the line, so that its
        // best "plane" is tilted by that much. The point's own normal is the floor's.
        let fit = |tilt: f32, cfg: &AssociationConfig, mode| {
            let mut storage = MapStorage::<1024, 2048>::new();
            let mut map = storage.map(MapConfig::VLP32C).unwrap();
            let (s, c) = (libm::sinf(tilt.to_radians()), libm::cosf(tilt.to_radians()));
            let wide = [c, 0.0, -s];
            let mut pts = [MapPoint { xyz: [0.0; 3], normal: None }; 21];
            for (i, q) in pts.iter_mut().enumerate() {
                let a = 0.003 * (2.0 * (i % 2) as f32 - 1.0);
                let xyz = [5.0 + a * wide[0], -1.0 + 0.1 * i as f32, -1.0 + a * wide[2]];
                *q = MapPoint { xyz, normal: Some([0.0, 0.0, 1.0]) };
            }
            map.insert(pts.iter().copied(), [0.0; 3], 1).unwrap();
            let p = [5.0f32, 0.05, -0.98];
            let range = crate::math::sqrtf(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
            let mut nb = Neighbours::new();
            assert!(map.knn(p, &KnnQuery::new(5, 1.0), &mut nb) >= 4);
            associate_point(&map, cfg, mode, p, Some([0.0, 0.0, 1.0]), [0.0; 3], range, &nb)
                .map(|c| (c.kind, c.normal.map(|v| v.abs()), c.distance(p).abs()))
        };
        let (on, off) = (
            AssociationConfig { plane_line_spread: 0.03, ..AssociationConfig::DEFAULT },
            AssociationConfig::DEFAULT,
        );
        let plane = AssociationMode::PlaneOnly;

        // 15 degrees off: the fit alone tilts the floor about the ring ...
        let (_, n, _) = fit(15.0, &off, plane).unwrap();
        assert!((n[0] - 0.259).abs() < 0.01 && (n[2] - 0.966).abs() < 0.01, "{n:?}");
        let (_, n, _) = fit(15.0, &on, AssociationMode::Plain).unwrap();
        assert!((n[0] - 0.259).abs() < 0.01, "{n:?}");
        // ... and as a line it is the floor through the ring.
        let (kind, n, d) = fit(15.0, &on, plane).unwrap();
        assert_eq!((kind, n), (Kind::Plane, [0.0, 0.0, 1.0]));
        assert!((d - 0.02).abs() < 0.002, "{d}");
        // Within 5 degrees the fit's own normal stays.
        let (_, n, _) = fit(3.0, &on, plane).unwrap();
        assert!((n[0] - 0.052).abs() < 0.005, "{n:?}");
        // Beyond the plane check's 30 degrees it is refused, line or not.
        assert_eq!(fit(60.0, &on, plane), Err(Reject::NoPlane));
        assert_eq!(fit(60.0, &off, plane), Err(Reject::NoPlane));
        let bad = AssociationConfig { plane_line_spread: 1.5, ..AssociationConfig::DEFAULT };
        assert_eq!(bad.validate(), Err("association.plane_line_spread"));
    }

    #[test]
    fn a_plane_along_the_surface_is_kept() {
        let mut storage = MapStorage::<1024, 2048>::new();
        let mut map = storage.map(MapConfig::VLP32C).unwrap();
        // A floor patch seen by several rings.
        let mut pts = [MapPoint { xyz: [0.0; 3], normal: None }; 100];
        for (i, q) in pts.iter_mut().enumerate() {
            let (x, y) = (4.0 + 0.1 * (i / 10) as f32, -0.5 + 0.1 * (i % 10) as f32);
            *q = MapPoint { xyz: [x, y, -1.0 + 0.002 * ((i * 7) % 5) as f32], normal: Some([0.0, 0.0, 1.0]) };
        }
        map.insert(pts.iter().copied(), [0.0; 3], 1).unwrap();
        let cfg = AssociationConfig::DEFAULT;
        let p = [4.45f32, 0.0, -0.98];
        let range = crate::math::sqrtf(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
        let mut nb = Neighbours::new();
        assert!(map.knn(p, &KnnQuery::new(5, 1.0), &mut nb) >= 4);
        let c = associate_point(
            &map,
            &cfg,
            AssociationMode::PlaneOnly,
            p,
            Some([0.05, 0.0, 0.998]),
            [0.0; 3],
            range,
            &nb,
        )
        .unwrap();
        assert_eq!(c.kind, Kind::Plane);
        assert!(c.normal[2].abs() > 0.99, "{:?}", c.normal);
        assert!(
            (c.distance(p) - 0.02).abs() < 0.01 || (c.distance(p) + 0.02).abs() < 0.01,
            "{}",
            c.distance(p)
        );
    }
}
