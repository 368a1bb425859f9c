//! Each voxel's distribution (paper IV-A): its sums as `f64` moments, the evaluation every `eta`
//! points that converges or saturates it, read access; the paper's state machine, on its own.

use super::voxel::{STATE_ACCUMULATING, STATE_CONVERGED, STATE_SATURATED, Voxel};
use super::{VoxelHandle, VoxelMap, normalised, to32, to64};
use crate::surfel::{self, Moments, Shape};

/// The state of a voxel's distribution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum VoxelState {
    /// Still adding points.
    Accumulating,
    /// A surfel whose ring normal agreed with `e_d`: fixed.
    Converged,
    /// Reached `saturate_at` points without converging: fixed.
    Saturated,
}

/// Read access to one voxel (visibility and consistency checks).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VoxelInfo {
    /// Integer voxel coordinates, `floor(p / voxel_size)`.
    pub key: [i32; 3],
    /// The distribution's state.
    pub state: VoxelState,
    /// Points in the distribution (true count).
    pub count: u32,
    /// How many of them brought a usable normal.
    pub normal_count: u32,
    /// Stamp of the last insert that touched the voxel.
    pub last_seen: u32,
    /// Mean of the distribution, world frame.
    pub mean: [f32; 3],
    /// The voxel normal for visibility and consistency checks: for a converged voxel the
    /// normalised average of the mean ring normal and `e_d` (the paper's "replaced by the average
    /// of their values"), otherwise the mean ring normal; `None` without usable normals.
    pub normal: Option<[f32; 3]>,
}

impl VoxelMap<'_> {
    /// A voxel's sums as `f64` moments about its centre.
    pub(super) fn moments(&self, v: &Voxel) -> Moments {
        Moments {
            n: u32::from(v.count),
            origin: to64(self.centre(v.key)),
            sum: to64(v.sum),
            sum_sq: [
                f64::from(v.sum_sq[0]),
                f64::from(v.sum_sq[1]),
                f64::from(v.sum_sq[2]),
                f64::from(v.sum_sq[3]),
                f64::from(v.sum_sq[4]),
                f64::from(v.sum_sq[5]),
            ],
        }
    }

    /// The distribution of a voxel as `f64` moments (about its centre).
    pub fn voxel_moments(&self, h: VoxelHandle) -> Option<Moments> {
        self.live(h).map(|v| self.moments(v))
    }

    fn ring_dir(v: &Voxel) -> Option<([f64; 3], f64)> {
        if v.normal_count == 0 {
            return None;
        }
        let s = to64(v.ring_sum);
        let len = crate::math::sqrt(surfel::dot3(s, s)) / f64::from(v.normal_count);
        normalised(s).map(|d| (d, len))
    }

    /// Read access to a voxel (mean, voxel normal, state, counts).
    pub fn voxel(&self, h: VoxelHandle) -> Option<VoxelInfo> {
        let v = self.live(h)?;
        let m = self.moments(v);
        let mean = to32(m.mean().unwrap_or(m.origin));
        let ring = Self::ring_dir(v);
        let normal = match (v.state, ring) {
            (STATE_CONVERGED, Some((r, _))) => {
                let e = to64(v.normal);
                normalised([r[0] + e[0], r[1] + e[1], r[2] + e[2]]).map(to32)
            }
            (_, Some((r, _))) => Some(to32(r)),
            _ => None,
        };
        Some(VoxelInfo {
            key: v.key,
            state: state_of(v.state),
            count: u32::from(v.count),
            normal_count: u32::from(v.normal_count),
            last_seen: v.last_seen,
            mean,
            normal,
        })
    }

    /// Every live voxel with its handle, in pool order.
    pub fn voxels(&self) -> impl Iterator<Item = (VoxelHandle, VoxelInfo)> + '_ {
        (0..self.len as u32).filter_map(|i| self.voxel(VoxelHandle(i)).map(|v| (VoxelHandle(i), v)))
    }

    /// Eigen-analysis of an accumulating voxel; updates its state. `to_sensor` orients `e_d`
    /// when there is no ring normal.
    pub(super) fn evaluate(&mut self, slot: usize, to_sensor: [f32; 3]) -> u8 {
        let v = self.pool[slot];
        let m = self.moments(&v);
        let shape = Shape::of_covariance(&m.covariance());
        let mut e = shape.normal();
        let ring = Self::ring_dir(&v);
        let reference = match ring {
            Some((r, _)) => r,
            None => to64(to_sensor),
        };
        if surfel::dot3(e, reference) < 0.0 {
            e = [-e[0], -e[1], -e[2]];
        }
        let surfel_ok = self.cfg.criteria.check(&shape).is_ok();
        let agrees = match ring {
            Some((r, len)) => {
                len >= f64::from(self.cfg.min_ring_coherence)
                    && surfel::dot3(e, r) >= f64::from(self.d.cos_max_angle)
            }
            None => false,
        };
        let state = if surfel_ok && agrees {
            STATE_CONVERGED
        } else if v.count >= self.cfg.saturate_at {
            STATE_SATURATED
        } else {
            STATE_ACCUMULATING
        };
        let w = &mut self.pool[slot];
        w.normal = to32(e);
        w.eigenvalues = to32(shape.eigenvalues);
        w.state = state;
        state
    }
}

fn state_of(s: u8) -> VoxelState {
    match s {
        STATE_CONVERGED => VoxelState::Converged,
        STATE_SATURATED => VoxelState::Saturated,
        _ => VoxelState::Accumulating,
    }
}
