//! The small (one converged voxel) and large (neighbouring voxels merged by Eq. (5)) surfels of
//! paper IV-B3; separate because they only read the distributions, for the association.

use super::voxel::STATE_CONVERGED;
use super::{MERGE_MAX, VoxelHandle, VoxelMap, to32, to64};
use crate::surfel::{self, Moments, Shape, SurfelReject};

/// The surfel of one converged voxel.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct SmallSurfel {
    /// The voxel.
    pub voxel: VoxelHandle,
    /// Mean of its points, world frame.
    pub mean: [f32; 3],
    /// `e_d`, oriented with the voxel's ring normal.
    pub normal: [f32; 3],
    /// Ascending covariance eigenvalues, metres².
    pub eigenvalues: [f32; 3],
    /// Points in the distribution.
    pub count: u32,
}

/// A large-scale surfel: distinct voxels' distributions merged by Eq. (5).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LargeSurfel {
    /// Mean of the union, world frame.
    pub mean: [f32; 3],
    /// `e_d` of the union, oriented with the sum of the voxels' ring normals (or, without any,
    /// as the eigen solver returned it).
    pub normal: [f32; 3],
    /// Ascending covariance eigenvalues of the union, metres².
    pub eigenvalues: [f32; 3],
    /// Total point count (true counts).
    pub count: u32,
    /// Distinct voxels merged.
    pub voxels: u32,
}

/// A large surfel's merged distribution before its eigen-analysis
/// ([`VoxelMap::large_surfel_merge`]).
#[derive(Clone, Copy, Debug)]
pub struct LargeMerge {
    distinct: [VoxelHandle; MERGE_MAX],
    nd: u8,
    merged: Moments,
    ring: [f64; 3],
}

impl LargeMerge {
    /// No voxels (a placeholder for buffers; [`VoxelMap::large_surfel_finish`] refuses it).
    pub const EMPTY: Self =
        Self { distinct: [VoxelHandle(0); MERGE_MAX], nd: 0, merged: Moments::new([0.0; 3]), ring: [0.0; 3] };

    /// The merged covariance, for the eigen-analysis.
    pub fn covariance(&self) -> surfel::Sym3 {
        self.merged.covariance()
    }
}

impl VoxelMap<'_> {
    /// The small-scale surfel of a voxel: only if it has converged.
    pub fn small_surfel(&self, h: VoxelHandle) -> Result<SmallSurfel, SurfelReject> {
        let v = self.live(h).ok_or(SurfelReject::InvalidHandle)?;
        if v.state != STATE_CONVERGED {
            return Err(SurfelReject::NotConverged);
        }
        let m = self.moments(v);
        Ok(SmallSurfel {
            voxel: h,
            mean: to32(m.mean().unwrap_or(m.origin)),
            normal: v.normal,
            eigenvalues: v.eigenvalues,
            count: u32::from(v.count),
        })
    }

    /// The small-scale surfel of the voxel holding world point `p` (paper IV-B3: "the voxel
    /// where the point is located, which must already be fixed"): only if it has converged.
    pub fn small_surfel_at(&self, p: [f32; 3]) -> Result<SmallSurfel, SurfelReject> {
        let h = self.find(p).ok_or(SurfelReject::InvalidHandle)?;
        self.small_surfel(h)
    }

    /// The large-scale surfel of some voxels (typically the k-NN's, [`Neighbours::voxels`]): each
    /// distinct voxel with at least `eta` points is merged once, by Eq. (5) with its true count
    /// (converged, saturated and accumulating alike). Accepted if the union has
    /// `large.min_points` points from `large.min_voxels` voxels, meets the surfel criteria
    /// (`large.apply_criteria`), and every merged voxel's mean lies within
    /// `large.max_mean_distance` of the merged plane.
    ///
    /// [`Neighbours::voxels`]: super::Neighbours::voxels
    pub fn large_surfel(&self, voxels: &[VoxelHandle]) -> Result<LargeSurfel, SurfelReject> {
        let m = self.large_surfel_merge(voxels)?;
        let shape = Shape::of_covariance(&m.covariance());
        self.large_surfel_finish(&m, shape.eigenvalues, shape.normal())
    }

    /// [`Self::large_surfel`] up to its eigen-analysis: the distinct voxels merged, or why
    /// there is no surfel yet. The association analyses several merges at once
    /// ([`surfel::eigen_normals_lanes`]) and then calls [`Self::large_surfel_finish`].
    pub fn large_surfel_merge(&self, voxels: &[VoxelHandle]) -> Result<LargeMerge, SurfelReject> {
        let mut distinct = [VoxelHandle(0); MERGE_MAX];
        let mut nd = 0usize;
        for &h in voxels {
            if self.live(h).is_none() {
                return Err(SurfelReject::InvalidHandle);
            }
            if distinct[..nd].contains(&h) {
                continue;
            }
            if self.pool[h.index()].count < self.cfg.eta {
                continue;
            }
            if nd == MERGE_MAX {
                return Err(SurfelReject::TooManyVoxels);
            }
            distinct[nd] = h;
            nd += 1;
        }
        let lc = &self.cfg.large;
        if nd == 0 || nd < usize::from(lc.min_voxels) {
            return Err(SurfelReject::TooFewVoxels);
        }
        let first = &self.pool[distinct[0].index()];
        let mut merged = Moments::new(to64(self.centre(first.key)));
        let mut ring = [0.0f64; 3];
        for h in &distinct[..nd] {
            let v = &self.pool[h.index()];
            merged.merge(&self.moments(v));
            for a in 0..3 {
                ring[a] += f64::from(v.ring_sum[a]);
            }
        }
        if merged.n < lc.min_points {
            return Err(SurfelReject::TooFewPoints);
        }
        Ok(LargeMerge { distinct, nd: nd as u8, merged, ring })
    }

    /// The rest of [`Self::large_surfel`], given the eigenvalues (ascending, clamped at 0) and
    /// the normal of `m`'s covariance, as [`Shape::of_covariance`] gives them.
    pub fn large_surfel_finish(
        &self,
        m: &LargeMerge,
        eigenvalues: [f64; 3],
        normal: [f64; 3],
    ) -> Result<LargeSurfel, SurfelReject> {
        let lc = &self.cfg.large;
        let distinct = &m.distinct[..usize::from(m.nd)];
        if distinct.is_empty() {
            return Err(SurfelReject::TooFewVoxels);
        }
        let [l1, _, l3] = eigenvalues;
        if !(l3 > 0.0) || l3 == l1 {
            return Err(SurfelReject::Degenerate);
        }
        if lc.apply_criteria {
            self.cfg.criteria.check_eigenvalues(eigenvalues)?;
        }
        let mut nrm = normal;
        if surfel::dot3(nrm, m.ring) < 0.0 {
            nrm = [-nrm[0], -nrm[1], -nrm[2]];
        }
        let mean = m.merged.mean().unwrap_or(m.merged.origin);
        for h in distinct {
            let mv = self.moments(&self.pool[h.index()]);
            let mi = mv.mean().unwrap_or(mv.origin);
            let dist = surfel::dot3(nrm, surfel::sub3(mi, mean)).abs();
            if !(dist <= f64::from(lc.max_mean_distance)) {
                return Err(SurfelReject::OffPlane);
            }
        }
        Ok(LargeSurfel {
            mean: to32(mean),
            normal: to32(nrm),
            eigenvalues: to32(eigenvalues),
            count: m.merged.n,
            voxels: u32::from(m.nd),
        })
    }
}
