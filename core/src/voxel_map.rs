//! The map: a fixed pool of voxels, each keeping the distribution of the points that fell into
//! it, found through an open-addressing hash index (paper sections III-C, IV-D; reference notes
//! B). Memory is the caller's and bounded; nothing here allocates, grows or panics.
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
//! - the true point count (separate from the state: the reference's `-9999` "converged" marker
//!   corrupted merged surfels, reference notes C.2);
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
//! ## The state machine (paper section IV-A; reference notes B.2)
//! `Accumulating` voxels add every point to their sums. The distribution is evaluated every
//! `eta` points (and at `saturate_at`): the voxel becomes `Converged` when it is a surfel
//! ([`SurfelCriteria`]: `rho > 0.6`, `gamma > 100` by default) **and** its mean ring normal agrees
//! with the smallest-eigenvalue eigenvector within `max_normal_angle_deg` (20 degrees, the
//! paper's test; in the reference code the angle does not gate convergence). Otherwise, once
//! `saturate_at` (= 2 `eta`) points are in, it becomes `Saturated`. Converged and saturated
//! voxels no longer change their distribution, count or ring normal.
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

mod config;
mod distribution;
mod evict;
mod index;
mod knn;
mod surfels;
mod voxel;

pub use self::config::{LargeSurfelConfig, MapConfig, MapError};
pub use self::distribution::{VoxelInfo, VoxelState};
use self::evict::DIST_BUCKETS_PER_RADIUS;
pub use self::index::IndexSlot;
use self::index::{hash_key, index_find, index_first_with_hash, index_insert};
pub use self::knn::{KnnQuery, KnnReach, Neighbour, Neighbours};
pub use self::surfels::{LargeMerge, LargeSurfel, SmallSurfel};
pub use self::voxel::{MapStorage, Voxel};
use self::voxel::{QUANT, STATE_ACCUMULATING, STATE_CONVERGED, STATE_SATURATED, update_rep};

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

/// Points looked up together by [`VoxelMap::insert`].
const CHUNK: usize = 32;
const NO_HINT: u32 = u32::MAX;

/// Errors of [`VoxelMap::insert`]; nothing is inserted when one is returned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum InsertError {
    /// The sensor position has a NaN or infinite coordinate.
    SensorNotFinite,
    /// The stamp is smaller than the previous call's (stamps must not decrease).
    StampWentBackwards {
        /// The previous stamp.
        last: u32,
        /// The stamp passed.
        got: u32,
    },
}

impl core::fmt::Display for InsertError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::SensorNotFinite => f.write_str("sensor position is not finite"),
            Self::StampWentBackwards { last, got } => {
                write!(f, "map stamp went backwards ({got} after {last})")
            }
        }
    }
}

impl core::error::Error for InsertError {}

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

/// A point to insert: world frame, with its Ring FALS normal if it has one.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MapPoint {
    /// World-frame position, metres.
    pub xyz: [f32; 3],
    /// World-frame normal, oriented towards the sensor. Normals that are not finite or whose
    /// length is outside `[0.5, 1.5]` count as missing ([`InsertStats::bad_normals`]); the rest
    /// are normalised.
    pub normal: Option<[f32; 3]>,
}

/// What one [`VoxelMap::insert`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct InsertStats {
    /// Points offered.
    pub points: u32,
    /// Points that reached a voxel (including voxels whose distribution is fixed).
    pub inserted: u32,
    /// Points added to a distribution (their voxel was accumulating).
    pub accumulated: u32,
    /// Voxels created.
    pub new_voxels: u32,
    /// Voxels evicted by the distance sweep.
    pub evicted_far: u32,
    /// Voxels evicted to make room in a full pool.
    pub evicted_full: u32,
    /// Points dropped: pool full and nothing evictable (all touched by this stamp).
    pub dropped_full: u32,
    /// Points dropped: a coordinate not finite or out of range.
    pub dropped_invalid: u32,
    /// Points dropped: farther than `evict_radius` from the sensor.
    pub dropped_far: u32,
    /// Normals given but unusable (treated as missing).
    pub bad_normals: u32,
    /// Voxels that converged.
    pub converged: u32,
    /// Voxels that saturated.
    pub saturated: u32,
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
            k[a] = floor_i32(v);
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

    // ---- Insertion ------------------------------------------------------------------------------

    /// Inserts one scan's points (world frame, downsampled on the voxel grid) seen from `sensor`
    /// (world frame), stamped `stamp` (e.g. the scan index; must not decrease between calls,
    /// equal stamps are fine). First sweeps part of the pool for voxels beyond `evict_radius`
    /// (module docs), then inserts the points in order. Allocation-free, `O(points +
    /// sweep_per_insert)` plus, when the pool is full, an `O(capacity)` eviction per
    /// `evict_batch` new voxels.
    pub fn insert<I>(&mut self, points: I, sensor: [f32; 3], stamp: u32) -> Result<InsertStats, InsertError>
    where
        I: IntoIterator<Item = MapPoint>,
    {
        if sensor.iter().any(|x| !x.is_finite()) {
            return Err(InsertError::SensorNotFinite);
        }
        if self.has_stamp && stamp < self.stamp {
            return Err(InsertError::StampWentBackwards { last: self.stamp, got: stamp });
        }
        self.stamp = stamp;
        self.has_stamp = true;
        let mut st = InsertStats::default();
        self.sweep(sensor, &mut st);
        let mut full_failed = false;
        // A software pipeline over chunks of CHUNK points (insertion is bound by memory
        // latency): while chunk g - 2 is inserted, the voxels of chunk g - 1 (whose index
        // entries have arrived) and the index lines of chunk g are being fetched. The slots
        // found are hints only, checked again at insertion (an eviction may have moved voxels).
        let mut it = points.into_iter();
        let mut pts = [[MapPoint::default(); CHUNK]; 3];
        let mut keys = [[None; CHUNK]; 3];
        let mut hashes = [[NO_HINT; CHUNK]; 3];
        let mut hints = [[NO_HINT; CHUNK]; 3];
        let mut lens = [0usize; 3];
        let mut chunks = usize::MAX; // known once the input runs out
        let mut g = 0usize;
        loop {
            if g < chunks {
                let r = g % 3;
                let mut n = 0;
                while n < CHUNK {
                    let Some(p) = it.next() else { break };
                    pts[r][n] = p;
                    let k = self.key_of(p.xyz);
                    let h = k.map_or(0, hash_key);
                    if k.is_some() {
                        prefetch(&self.index[h as usize & self.mask]);
                    }
                    keys[r][n] = k;
                    hashes[r][n] = h;
                    n += 1;
                }
                lens[r] = n;
                if n < CHUNK {
                    chunks = if n > 0 { g + 1 } else { g };
                }
            }
            if g >= 1 && g - 1 < chunks {
                let r = (g - 1) % 3;
                for i in 0..lens[r] {
                    let h = hashes[r][i];
                    let slot = match keys[r][i] {
                        Some(_) => index_first_with_hash(self.index, self.mask, h),
                        None => None,
                    };
                    hints[r][i] = slot.unwrap_or(NO_HINT);
                    if let Some(s) = slot {
                        let v = &self.pool[s as usize];
                        prefetch(v); // line 0: key, state, representatives
                        prefetch(&v.last_seen); // line 1: the sums
                        prefetch(&v.rep_normals); // line 2: the representatives' normals
                    }
                }
            }
            if g >= 2 && g - 2 < chunks {
                let r = (g - 2) % 3;
                for i in 0..lens[r] {
                    st.points = st.points.saturating_add(1);
                    let key = keys[r][i].map(|k| (k, hashes[r][i]));
                    self.insert_one(pts[r][i], key, hints[r][i], sensor, &mut st, &mut full_failed);
                }
            }
            if g >= 2 && g > chunks {
                break;
            }
            g += 1;
        }
        if st.dropped_full > 0 {
            warn!("voxel map full: {} points dropped", st.dropped_full);
        }
        Ok(st)
    }

    /// [`Self::insert`] for a slice.
    pub fn insert_slice(
        &mut self,
        points: &[MapPoint],
        sensor: [f32; 3],
        stamp: u32,
    ) -> Result<InsertStats, InsertError> {
        self.insert(points.iter().copied(), sensor, stamp)
    }

    /// Inserts one point; `key` is its voxel key and the key's hash (`None`: out of range).
    fn insert_one(
        &mut self,
        p: MapPoint,
        key: Option<([i32; 3], u32)>,
        hint: u32,
        sensor: [f32; 3],
        st: &mut InsertStats,
        full_failed: &mut bool,
    ) {
        let Some((k, h)) = key else {
            st.dropped_invalid += 1;
            return;
        };
        if d2f(p.xyz, sensor) > self.d.evict_r2 {
            st.dropped_far += 1;
            return;
        }
        let normal = match p.normal {
            None => None,
            Some(n) => {
                let l2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2];
                if (1.0 - 1e-5..=1.0 + 1e-5).contains(&l2) {
                    Some(n) // already unit (the usual case): no square root
                } else if l2.is_finite() && (0.25..=2.25).contains(&l2) {
                    let inv = 1.0 / crate::math::sqrtf(l2);
                    Some([n[0] * inv, n[1] * inv, n[2] * inv])
                } else {
                    st.bad_normals += 1;
                    None
                }
            }
        };
        // Keys of live voxels are unique, so a live slot holding `k` is the voxel.
        let slot = if (hint as usize) < self.len && self.pool[hint as usize].key == k {
            Some(hint)
        } else {
            let pool = &*self.pool;
            index_find(self.index, self.mask, h, |s| pool[s as usize].key == k).map(|(_, s)| s)
        };
        let slot = match slot {
            Some(s) => s as usize,
            None => {
                if self.len == self.pool.len() {
                    if !*full_failed {
                        let n = self.make_room(sensor);
                        st.evicted_full += n as u32;
                        if n == 0 {
                            *full_failed = true;
                        }
                    }
                    if self.len == self.pool.len() {
                        st.dropped_full += 1;
                        self.counters.dropped_full += 1;
                        return;
                    }
                }
                let s = self.len;
                if !index_insert(self.index, self.mask, h, s as u32) {
                    // Unreachable while index.len() >= 2 * pool.len(); counted, never a panic.
                    st.dropped_full += 1;
                    self.counters.dropped_full += 1;
                    return;
                }
                self.pool[s] =
                    Voxel { key: k, state: STATE_ACCUMULATING, until_eval: self.cfg.eta, ..Voxel::EMPTY };
                self.len += 1;
                st.new_voxels += 1;
                self.counters.created += 1;
                s
            }
        };
        st.inserted += 1;
        let c = self.centre(k);
        let off = [p.xyz[0] - c[0], p.xyz[1] - c[1], p.xyz[2] - c[2]];
        let d = self.d;
        let cfg = self.cfg;
        let stamp = self.stamp;
        let v = &mut self.pool[slot];
        v.last_seen = stamp;
        update_rep(v, off, normal, &d);
        if v.state != STATE_ACCUMULATING {
            return;
        }
        st.accumulated += 1;
        v.count += 1;
        for a in 0..3 {
            v.sum[a] += off[a];
        }
        v.sum_sq[0] += off[0] * off[0];
        v.sum_sq[1] += off[0] * off[1];
        v.sum_sq[2] += off[0] * off[2];
        v.sum_sq[3] += off[1] * off[1];
        v.sum_sq[4] += off[1] * off[2];
        v.sum_sq[5] += off[2] * off[2];
        if let Some(n) = normal {
            v.normal_count += 1;
            for a in 0..3 {
                v.ring_sum[a] += n[a];
            }
        }
        v.until_eval = v.until_eval.saturating_sub(1);
        if v.until_eval == 0 || v.count >= cfg.saturate_at {
            v.until_eval = cfg.eta;
            let to_c = [sensor[0] - c[0], sensor[1] - c[1], sensor[2] - c[2]];
            match self.evaluate(slot, to_c) {
                STATE_CONVERGED => st.converged += 1,
                STATE_SATURATED => st.saturated += 1,
                _ => {}
            }
        }
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

/// `floor(v)` for `|v| < 2^31` (callers check a smaller bound): truncation, minus one for
/// negative non-integers. Exact, and cheaper than `libm::floorf` on targets without a rounding
/// instruction in their baseline (x86-64 before SSE4.1, Cortex-M4F).
#[inline]
fn floor_i32(v: f32) -> i32 {
    let t = v as i32;
    if (t as f32) > v { t - 1 } else { t }
}

#[cfg(test)]
mod tests;
