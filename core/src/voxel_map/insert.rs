//! Insertion of a scan: lookups pipelined ahead of use, new voxels (room made in a full pool),
//! each point added to its voxel; separate because it is the only writer of points.

use super::index::{hash_key, index_find, index_first_with_hash, index_insert};
use super::voxel::{STATE_ACCUMULATING, STATE_CONVERGED, STATE_SATURATED, Voxel, update_rep};
use super::{NO_HINT, VoxelMap, d2f, prefetch};

/// Points looked up together by [`VoxelMap::insert`].
const CHUNK: usize = 32;

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

impl VoxelMap<'_> {
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
