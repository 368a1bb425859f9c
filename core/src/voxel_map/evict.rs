//! Bounded memory: the distance sweep, the batch eviction of a full pool (farthest, then least
//! recently used) and the swap-remove that keeps the pool dense; only insertion calls it.

use super::index::{IndexSlot, hash_key, index_find_slot, index_remove_at};
use super::voxel::Voxel;
use super::{InsertStats, VoxelMap, d2f};

/// Distance buckets of the full-pool eviction per `evict_radius`.
pub(super) const DIST_BUCKETS_PER_RADIUS: f32 = 192.0;

impl VoxelMap<'_> {
    /// Removes the voxel at pool position `slot`: deletes its index entry and moves the last live
    /// voxel into its place.
    pub(super) fn remove_slot(&mut self, slot: usize) {
        let k = self.pool[slot].key;
        if let Some(pos) = index_find_slot(self.index, self.mask, hash_key(k), slot as u32) {
            index_remove_at(self.index, self.mask, pos);
        }
        let last = self.len - 1;
        if slot != last {
            let moved = self.pool[last];
            let hm = hash_key(moved.key);
            if let Some(pos) = index_find_slot(self.index, self.mask, hm, last as u32) {
                self.index[pos] = IndexSlot::new(hm, slot as u32);
            }
            self.pool[slot] = moved;
        }
        self.pool[last] = Voxel::EMPTY;
        self.len = last;
    }

    /// The distance sweep: checks `sweep_per_insert` slots from the cursor.
    pub(super) fn sweep(&mut self, sensor: [f32; 3], st: &mut InsertStats) {
        let budget = (self.cfg.sweep_per_insert as usize).min(self.len);
        for _ in 0..budget {
            if self.len == 0 {
                break;
            }
            if self.cursor >= self.len {
                self.cursor = 0;
            }
            let c = self.centre(self.pool[self.cursor].key);
            if d2f(c, sensor) > self.d.evict_r2 {
                self.remove_slot(self.cursor);
                st.evicted_far += 1;
                self.counters.evicted_far += 1;
            } else {
                self.cursor += 1;
            }
        }
    }

    #[inline]
    pub(super) fn dist_bucket(&self, v: &Voxel, sensor: [f32; 3]) -> usize {
        let d = crate::math::sqrtf(d2f(self.centre(v.key), sensor)) * self.d.bucket_scale;
        if d < 255.0 { d as usize } else { 255 }
    }

    #[inline]
    fn age_bucket(&self, v: &Voxel) -> usize {
        (self.stamp.saturating_sub(v.last_seen)).min(255) as usize
    }

    /// Evicts a batch from a full pool (module docs). Returns how many were evicted.
    pub(super) fn make_room(&mut self, sensor: [f32; 3]) -> usize {
        let cap = self.pool.len();
        let batch = match self.cfg.evict_batch {
            0 => (cap / 16).max(1),
            b => (b as usize).clamp(1, cap),
        };
        // Pass 1: distance histogram of the evictable voxels.
        let mut hist = [0u32; 256];
        let mut evictable = 0usize;
        for v in &self.pool[..self.len] {
            if v.last_seen != self.stamp {
                hist[self.dist_bucket(v, sensor)] += 1;
                evictable += 1;
            }
        }
        if evictable == 0 {
            return 0;
        }
        let target = batch.min(evictable);
        let mut above = 0usize;
        let mut b_thr = 0usize;
        for b in (0..256).rev() {
            if above + hist[b] as usize >= target {
                b_thr = b;
                break;
            }
            above += hist[b] as usize;
        }
        let mut need_b = target - above;
        // Pass 2: age histogram inside the threshold bucket (LRU tie-break).
        let mut a_thr = 0usize;
        let mut need_a = 0usize;
        let all_of_b = need_b >= hist[b_thr] as usize;
        if !all_of_b {
            let mut ages = [0u32; 256];
            for v in &self.pool[..self.len] {
                if v.last_seen != self.stamp && self.dist_bucket(v, sensor) == b_thr {
                    ages[self.age_bucket(v)] += 1;
                }
            }
            let mut older = 0usize;
            for a in (0..256).rev() {
                if older + ages[a] as usize >= need_b {
                    a_thr = a;
                    need_a = need_b - older;
                    break;
                }
                older += ages[a] as usize;
            }
        }
        // Pass 3: evict.
        let mut evicted = 0usize;
        let mut i = 0usize;
        while i < self.len && evicted < target {
            let v = &self.pool[i];
            let mut go = false;
            if v.last_seen != self.stamp {
                let b = self.dist_bucket(v, sensor);
                if b > b_thr {
                    go = true;
                } else if b == b_thr && need_b > 0 {
                    if all_of_b {
                        go = true;
                    } else {
                        let a = self.age_bucket(v);
                        if a > a_thr {
                            go = true;
                        } else if a == a_thr && need_a > 0 {
                            need_a -= 1;
                            go = true;
                        }
                    }
                    if go {
                        need_b -= 1;
                    }
                }
            }
            if go {
                self.remove_slot(i);
                evicted += 1;
            } else {
                i += 1;
            }
        }
        self.counters.evicted_full += evicted as u64;
        debug!("voxel map full: evicted {} voxels (distance bucket >= {})", evicted, b_thr);
        evicted
    }
}
