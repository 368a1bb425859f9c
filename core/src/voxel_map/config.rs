//! The map's settings (every threshold, the two sensor presets) and its construction errors:
//! plain values, apart from the map because they are checked once, when a map is made.

use crate::surfel::SurfelCriteria;

/// Large-surfel settings (paper section IV-B3; the thresholds are the reference code's).
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LargeSurfelConfig {
    /// Minimum total (true) point count of the merged voxels. Default 63: the reference's
    /// `N >= eta * 5 * 0.5 = 62.5` for eta 25.
    pub min_points: u32,
    /// Minimum number of distinct voxels merged. Default 2 (one voxel is a small surfel).
    pub min_voxels: u8,
    /// Every merged voxel's mean must lie within this of the merged plane, metres. Default 0.15.
    pub max_mean_distance: f32,
    /// Apply the surfel criteria to the merged distribution (the paper does; the reference code
    /// computes rho and gamma there but never tests them). Default true.
    pub apply_criteria: bool,
}

impl LargeSurfelConfig {
    /// The defaults documented on each field.
    pub const DEFAULT: Self =
        Self { min_points: 63, min_voxels: 2, max_mean_distance: 0.15, apply_criteria: true };
}

/// Map settings. Every threshold is here; [`MapConfig::VLP32C`] and [`MapConfig::OS1_16`] are the
/// paper's two setups.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MapConfig {
    /// Voxel edge, metres: 0.4 (VLP-32C, M2DGR) or 0.5 (OS1-16, NTU VIRAL). The scan should be
    /// downsampled on the same grid so each voxel gets at most one point per scan (paper V-A).
    pub voxel_size: f32,
    /// `eta`: the distribution is evaluated every `eta` points (default 25, the paper's value;
    /// at least 3).
    pub eta: u16,
    /// A voxel that has not converged is fixed (saturated) at this many points. Default 50
    /// (`2 eta`, the paper's rule). At least `eta`.
    pub saturate_at: u16,
    /// Surfel test for a voxel and for a merged (large) surfel.
    pub criteria: SurfelCriteria,
    /// Convergence also needs the mean ring normal within this angle of `e_d`, degrees.
    /// Default 20 (the paper's value).
    pub max_normal_angle_deg: f32,
    /// The mean ring normal is used only if the incoming normals agree: the length of their
    /// mean (1 when all are equal, near 0 when they point every way) must reach this. Default
    /// 0.5.
    pub min_ring_coherence: f32,
    /// Voxels farther than this from the sensor are evicted, and points farther are not
    /// inserted, metres. Default 80 (VLP-32C) / 100 (OS1-16).
    pub evict_radius: f32,
    /// Pool slots the eviction sweep checks per insert call. Default 4096: the whole of a 2^18
    /// pool every 64 scans (6.4 s at 10 Hz) for about 30 µs per scan; voxels left behind
    /// meanwhile are also the first to go when the pool runs full.
    pub sweep_per_insert: u32,
    /// Voxels evicted at once when the pool is full; 0 means `capacity / 16`. Default 0.
    pub evict_batch: u32,
    /// Large-surfel settings.
    pub large: LargeSurfelConfig,
}

impl MapConfig {
    /// Velodyne VLP-32C (M2DGR): 0.4 m voxels, 150 m eviction radius (the sensor reaches 200 m;
    /// a drone 70 m up sees the ground only beyond 150 m, rooftops from 100 m on).
    pub const VLP32C: Self = Self {
        voxel_size: 0.4,
        eta: 25,
        saturate_at: 50,
        criteria: SurfelCriteria::DEFAULT,
        max_normal_angle_deg: 20.0,
        min_ring_coherence: 0.5,
        evict_radius: 150.0,
        sweep_per_insert: 4096,
        evict_batch: 0,
        large: LargeSurfelConfig::DEFAULT,
    };

    /// Ouster OS1-16 (NTU VIRAL): 0.5 m voxels, 100 m eviction radius.
    pub const OS1_16: Self = Self { voxel_size: 0.5, evict_radius: 100.0, ..Self::VLP32C };

    pub(super) fn validate(&self) -> Result<(), MapError> {
        let bad = |field| Err(MapError::InvalidConfig { field });
        if !(self.voxel_size.is_finite() && self.voxel_size >= 1e-3) {
            return bad("voxel_size");
        }
        if self.eta < 3 {
            return bad("eta");
        }
        if self.saturate_at < self.eta {
            return bad("saturate_at");
        }
        let c = &self.criteria;
        if !(c.planarity_min.is_finite() && c.gamma_min.is_finite() && c.gamma_min >= 0.0) {
            return bad("criteria");
        }
        if !(self.max_normal_angle_deg >= 0.0 && self.max_normal_angle_deg <= 90.0) {
            return bad("max_normal_angle_deg");
        }
        if !(self.min_ring_coherence >= 0.0 && self.min_ring_coherence <= 1.0) {
            return bad("min_ring_coherence");
        }
        if !(self.evict_radius.is_finite() && self.evict_radius > 0.0) {
            return bad("evict_radius");
        }
        if !(self.large.max_mean_distance >= 0.0 && self.large.max_mean_distance.is_finite()) {
            return bad("large.max_mean_distance");
        }
        Ok(())
    }
}

impl Default for MapConfig {
    fn default() -> Self {
        Self::VLP32C
    }
}

/// Construction errors.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum MapError {
    /// The pool has no slot.
    PoolEmpty,
    /// The pool has more than `u32::MAX - 1` slots.
    PoolTooLarge,
    /// The index length is not a power of two.
    IndexNotPowerOfTwo,
    /// The index must have at least `needed` slots (twice the pool, bounding the load at 1/2).
    IndexTooSmall {
        /// Slots needed.
        needed: usize,
    },
    /// A configuration value is out of range.
    InvalidConfig {
        /// The offending field.
        field: &'static str,
    },
}

impl core::fmt::Display for MapError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::PoolEmpty => f.write_str("voxel pool is empty"),
            Self::PoolTooLarge => f.write_str("voxel pool exceeds u32::MAX - 1 slots"),
            Self::IndexNotPowerOfTwo => f.write_str("hash index length is not a power of two"),
            Self::IndexTooSmall { needed } => {
                write!(f, "hash index needs at least {needed} slots (twice the pool)")
            }
            Self::InvalidConfig { field } => write!(f, "invalid map config: {field}"),
        }
    }
}

impl core::error::Error for MapError {}
