//! The map: a fixed pool of voxels, each keeping the distribution of the points that fell into
//! it, found through an open-addressing hash index (paper sections III-C, IV-D). Memory is the
//! caller's and bounded; nothing here allocates, grows or panics.
//!
//! ## Storage
//! The caller provides the voxel pool (`&mut [Voxel]`, [`Voxel::EMPTY`] is all-zero bytes so a
//! firmware `static` lands in `.bss`) and the hash index (`&mut [IndexSlot]`, a power of two at
//! least twice the pool, so the load factor never exceeds 1/2). [`MapStorage`] bundles both as
//! const-generic arrays with a `const fn new()`. A [`Voxel`] is [`VOXEL_BYTES`] = 192 bytes (three
//! cache lines; the first holds all a lookup or k-NN query reads), an index slot 8; per voxel of
//! capacity that is 208 bytes with the index at twice the pool.
//!
//! Live voxels occupy `pool[..len]` densely: removing one moves the last into its place
//! (swap-remove), so sweeps read memory sequentially and no free list is needed. A
//! [`VoxelHandle`] is a pool position: valid until the next call that mutates the map.
//!
//! ## Per voxel
//! - the true point count (separate from the state: the reference marks a converged voxel with a
//!   count of `-9999` and then weighs it as 9999 points in a merged surfel, whose normal turns
//!   toward the world origin);
//! - `Σ d` and `Σ d dᵀ` in `f32` with `d = p - c`, `c` the voxel centre. Offsets are at most half a
//!   voxel, so the sums stay small and Eq. (4) does not cancel catastrophically anywhere in the
//!   world (a test shows world-frame `f32` sums failing 10 km out where these pass);
//! - the ring normal: the sum of the incoming Ring FALS normals (oriented towards the sensor by
//!   the caller) and how many points had one (`normal_count`, separate from the count);
//! - up to 8 representative points with their normals for nearest-neighbour search: **one per
//!   octant** of the voxel. A point goes to its octant's slot; an occupied slot keeps whichever
//!   point lies closer to the octant centre (ties keep the old one). Representatives are thus a
//!   2x finer downsampling grid (the ikd-tree's rule, "closest to the box centre", one level
//!   down): every point ever inserted has a representative in its own octant, within
//!   `sqrt(3)/2` voxel of it, and they stay spread across the voxel. Positions are stored as
//!   `i16` offsets from the centre (resolution `voxel_size / 32768`, 12 µm at 0.4 m) and normals
//!   as `i8` triples (direction error under 0.5 degrees). Representatives keep updating after the
//!   distribution is fixed (an `O(1)` compare per point); the distribution does not;
//! - the state ([`VoxelState`]) and the stamp of the last scan that touched it (LRU).
//!
//! ## The state machine (paper section IV-A)
//! `Accumulating` voxels add every point to their sums. The distribution is evaluated every
//! `eta` points (and at `saturate_at`): the voxel becomes `Converged` when it is a surfel
//! ([`SurfelCriteria`]: `rho > 0.6`, `gamma > 100` by default) **and** its mean ring normal agrees
//! with the smallest-eigenvalue eigenvector within `max_normal_angle_deg` (20 degrees, the
//! paper's test; in the reference code the angle does not gate convergence). Otherwise, once
//! `saturate_at` (= 2 `eta`) points are in, it becomes `Saturated`. Converged and saturated
//! voxels no longer change their distribution, count or ring normal.
//!
//! [`SurfelCriteria`]: surfel::SurfelCriteria
//!
//! ## Bounded memory
//! - Points farther than `evict_radius` from the sensor are not inserted (counted).
//! - Each [`VoxelMap::insert`] first sweeps `sweep_per_insert` pool slots from a cursor that
//!   wraps around the pool, evicting voxels farther than `evict_radius` from the sensor, so the
//!   whole pool is checked every `capacity / sweep_per_insert` scans at a fixed cost per scan.
//! - When a new voxel is needed and the pool is full, a batch of `evict_batch` voxels is evicted
//!   at once (three sequential passes over the pool, amortised over the batch): the farthest from
//!   the sensor first (distance in buckets of `evict_radius / 192`), least recently used first
//!   within the threshold bucket, pool order last. Voxels touched by the current stamp are never
//!   evicted; when nothing else is left, the new voxel's point is dropped (counted).
//! - The index uses linear probing with backward-shift deletion (no tombstones), so lookups stay
//!   short after any number of evictions; every probe loop is bounded by the index length.
//!
//! ## Queries (all `&self`, allocation-free, deterministic)
//! - [`VoxelMap::knn`] / [`VoxelMap::knn_many`]: the k (<= [`KNN_MAX`]) nearest representatives
//!   within a distance, from the query's voxel and its 26 neighbours, with their normals and
//!   voxel handles, nearest first; optionally one per voxel (k distinct voxels, as the
//!   reference's one-point-per-voxel ikd-tree gives). Exact against brute force for
//!   `max_dist <= voxel_size`. [`KnnReach::Block`] searches the query's 2x2x2 octant block
//!   first and the rest only if the block holds fewer than k (faster, approximate).
//! - [`VoxelMap::large_surfel`]: distinct voxels merged by Eq. (5) with true counts, accepted
//!   by the surfel criteria and the 0.15 m mean-to-plane test.
//! - [`VoxelMap::small_surfel`] / [`VoxelMap::small_surfel_at`]: a converged voxel's surfel.
//! - [`Neighbours::fit_plane`] ([`surfel::fit_plane`]): the point-to-plane fallback.
//! - [`VoxelMap::voxel`], [`VoxelMap::find`]: mean, voxel normal, state and counts.
//!
//! ## Speed
//! Insertion and queries are bound by memory latency (a voxel and its index entry are two
//! cache misses), so: a voxel's first cache line holds everything a lookup or a k-NN reads;
//! the hash keeps the 8 voxels of each 2x2x2 block in adjacent index slots (one index line
//! serves a neighbourhood); and [`VoxelMap::insert`] and [`VoxelMap::knn_many`] run software
//! pipelines that fetch the index lines, then the voxels, of the next points while the current
//! ones are processed (prefetch hints on x86; elsewhere the same code without hints). The k-NN
//! search itself avoids unpredictable jumps: the query's 27 box distances are computed at once
//! in its search order, the 19 boxes outside its octant are picked by one pass of compares, and
//! the candidate list is a sorted array of `distance << 32 | position` keys kept by min/max
//! over the whole array (vector code) instead of an insertion loop.
// `!(x > t)` rejects NaN as well as small values, on purpose; indexed loops over the three
// axes read like the maths.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

use crate::surfel;

mod clear;
mod config;
mod distribution;
mod evict;
mod index;
mod insert;
mod knn;
mod surfels;
mod voxel;

pub use self::clear::Suspects;
pub use self::config::{LargeSurfelConfig, MapConfig, MapError};
pub use self::distribution::{VoxelInfo, VoxelState};
use self::evict::DIST_BUCKETS_PER_RADIUS;
pub use self::index::IndexSlot;
use self::index::{hash_key, index_find};
pub use self::insert::{InsertError, InsertStats, MapPoint};
pub use self::knn::{KnnQuery, KnnReach, Neighbour, Neighbours};
pub use self::surfels::{LargeMerge, LargeSurfel, SmallSurfel};
use self::voxel::QUANT;
pub use self::voxel::{MapStorage, Voxel};

/// Representative points per voxel (one per octant).
pub const OCTANTS: usize = 8;
/// The largest `k` a k-NN query returns.
pub const KNN_MAX: usize = 8;
/// The most distinct voxels one large-surfel merge takes.
pub const MERGE_MAX: usize = 27;
/// Size of one [`Voxel`] in bytes.
pub const VOXEL_BYTES: usize = core::mem::size_of::<Voxel>();
/// Pool capacity suggested for the presets ([`MapConfig::VLP32C`], [`MapConfig::OS1_16`]):
/// 2^18 voxels (48 MiB at 192 bytes), about twice the ground disc inside the eviction radius
/// (`π R² / L²` ≈ 126,000 voxels for both), leaving room for walls and vegetation.
pub const PRESET_POOL_VOXELS: usize = 1 << 18;
/// Index slots for [`PRESET_POOL_VOXELS`] (2^19, 4 MiB).
pub const PRESET_INDEX_SLOTS: usize = 1 << 19;

/// Voxel coordinates beyond this (in voxels, per axis) are out of range: the point is dropped.
/// 2^22 voxels is 1,677 km at 0.4 m; it keeps `key + 0.5` exact in `f32`.
const KEY_LIMIT: f32 = 4_194_304.0;

const NO_HINT: u32 = u32::MAX;

/// A voxel's position in the pool. Valid until the next call that mutates the map.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct VoxelHandle(pub u32);

impl VoxelHandle {
    /// The pool position.
    pub fn index(self) -> usize {
        self.0 as usize
    }
}

/// Values derived from the config once.
#[derive(Clone, Copy, Debug)]
struct Derived {
    inv_size: f32,
    half: f32,
    quant: f32,
    dequant: f32,
    cos_max_angle: f32,
    evict_r2: f32,
    bucket_scale: f32,
    /// Slack for box-distance pruning (points may sit a rounding error outside their box).
    slack: f32,
}

/// Counters over the map's life.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MapCounters {
    /// Voxels created.
    pub created: u64,
    /// Voxels evicted by the distance sweep.
    pub evicted_far: u64,
    /// Voxels evicted from a full pool.
    pub evicted_full: u64,
    /// Points dropped because the pool was full.
    pub dropped_full: u64,
    /// Voxels removed because a scan saw through them ([`VoxelMap::clear_seen_through`]).
    pub cleared: u64,
}

/// The voxel map over caller-owned storage. See the module documentation.
#[derive(Debug)]
pub struct VoxelMap<'a> {
    pool: &'a mut [Voxel],
    index: &'a mut [IndexSlot],
    len: usize,
    mask: usize,
    cfg: MapConfig,
    d: Derived,
    cursor: usize,
    /// Where [`VoxelMap::clear_seen_through`] goes on.
    clear_cursor: usize,
    stamp: u32,
    has_stamp: bool,
    counters: MapCounters,
}

// ---- Small vector helpers ----------------------------------------------------------------------

#[inline]
fn d2f(a: [f32; 3], b: [f32; 3]) -> f32 {
    let (x, y, z) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    x * x + y * y + z * z
}

#[inline]
fn to64(a: [f32; 3]) -> [f64; 3] {
    [f64::from(a[0]), f64::from(a[1]), f64::from(a[2])]
}

#[inline]
fn to32(a: [f64; 3]) -> [f32; 3] {
    [a[0] as f32, a[1] as f32, a[2] as f32]
}

fn normalised(v: [f64; 3]) -> Option<[f64; 3]> {
    let n = crate::math::sqrt(surfel::dot3(v, v));
    if n > 0.0 && n.is_finite() { Some([v[0] / n, v[1] / n, v[2] / n]) } else { None }
}

impl<'a> VoxelMap<'a> {
    /// A map over caller-provided storage. `index.len()` must be a power of two and at least
    /// `2 * pool.len()`. The index is cleared (`O(index.len())`); the pool's contents are
    /// ignored (slots are overwritten when used).
    pub fn new(
        pool: &'a mut [Voxel],
        index: &'a mut [IndexSlot],
        config: MapConfig,
    ) -> Result<Self, MapError> {
        config.validate()?;
        if pool.is_empty() {
            return Err(MapError::PoolEmpty);
        }
        if pool.len() as u64 >= u64::from(u32::MAX) {
            return Err(MapError::PoolTooLarge);
        }
        if !index.len().is_power_of_two() {
            return Err(MapError::IndexNotPowerOfTwo);
        }
        let needed = pool.len().saturating_mul(2);
        if index.len() < needed {
            return Err(MapError::IndexTooSmall { needed });
        }
        index.fill(IndexSlot::EMPTY);
        let mask = index.len() - 1;
        let d = Self::derive(&config);
        Ok(Self {
            pool,
            index,
            len: 0,
            mask,
            cfg: config,
            d,
            cursor: 0,
            clear_cursor: 0,
            stamp: 0,
            has_stamp: false,
            counters: MapCounters::default(),
        })
    }

    fn derive(c: &MapConfig) -> Derived {
        let s = c.voxel_size;
        Derived {
            inv_size: 1.0 / s,
            half: 0.5 * s,
            quant: QUANT / s,
            dequant: s / QUANT,
            cos_max_angle: libm::cosf(c.max_normal_angle_deg.to_radians()),
            evict_r2: c.evict_radius * c.evict_radius,
            bucket_scale: DIST_BUCKETS_PER_RADIUS / c.evict_radius,
            slack: s * 1e-3,
        }
    }

    /// Removes every voxel (keeps the storage and config; resets the stamp).
    pub fn clear(&mut self) {
        self.index.fill(IndexSlot::EMPTY);
        self.len = 0;
        self.cursor = 0;
        self.clear_cursor = 0;
        self.has_stamp = false;
        self.stamp = 0;
    }

    /// The configuration.
    pub fn config(&self) -> &MapConfig {
        &self.cfg
    }

    /// Live voxels.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether the map holds no voxel.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Pool capacity (voxels).
    pub fn capacity(&self) -> usize {
        self.pool.len()
    }

    /// Lifetime counters.
    pub fn counters(&self) -> MapCounters {
        self.counters
    }

    /// Representative points held by the map (`O(len)`).
    pub fn point_count(&self) -> usize {
        self.pool[..self.len].iter().map(|v| v.occupied.count_ones() as usize).sum()
    }

    /// The voxel key of a world point, `floor(p / voxel_size)`; `None` if a coordinate is not
    /// finite or out of range (more than 2^22 voxels from the origin).
    #[inline]
    pub fn key_of(&self, p: [f32; 3]) -> Option<[i32; 3]> {
        let mut k = [0i32; 3];
        for a in 0..3 {
            let v = p[a] * self.d.inv_size;
            if !(libm::fabsf(v) < KEY_LIMIT) {
                return None;
            }
            k[a] = crate::math::floor_i32(v);
        }
        Some(k)
    }

    /// The centre of a voxel, world frame (the origin of its sums and representatives).
    #[inline]
    pub fn centre(&self, k: [i32; 3]) -> [f32; 3] {
        let s = self.cfg.voxel_size;
        [(k[0] as f32 + 0.5) * s, (k[1] as f32 + 0.5) * s, (k[2] as f32 + 0.5) * s]
    }

    #[inline]
    fn find_slot(&self, k: [i32; 3]) -> Option<u32> {
        let pool = &*self.pool;
        index_find(self.index, self.mask, hash_key(k), |s| pool[s as usize].key == k).map(|(_, s)| s)
    }

    /// The voxel with integer coordinates `key`.
    pub fn find_key(&self, key: [i32; 3]) -> Option<VoxelHandle> {
        self.find_slot(key).map(VoxelHandle)
    }

    /// The voxel holding world point `p`.
    pub fn find(&self, p: [f32; 3]) -> Option<VoxelHandle> {
        self.key_of(p).and_then(|k| self.find_key(k))
    }

    #[inline]
    fn live(&self, h: VoxelHandle) -> Option<&Voxel> {
        if h.index() < self.len { Some(&self.pool[h.index()]) } else { None }
    }
}

/// A cache prefetch hint (no effect on results; a no-op where the target has none in stable
/// Rust without `unsafe`).
#[inline(always)]
fn prefetch<T>(r: &T) {
    #[cfg(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "sse"))]
    safe_arch::prefetch_t0(r);
    #[cfg(not(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "sse")))]
    let _ = r;
}

#[cfg(test)]
mod tests;
