//! Clearing: voxels that a scan sees through (the space is empty now) leave the map; the free
//! space test itself is [`crate::free_space`]. Each call judges a fixed number of voxels round
//! robin, so the cost per scan stays fixed; a voxel seen through goes on a short list of suspects
//! that the next scan judges again, and goes only if that scan sees through it too (one scan can
//! be wrong, a moving object's trail stays empty).

use super::voxel::rep;
use super::{OCTANTS, VoxelMap, d2f};
use crate::free_space::Verdict;
use crate::parallel::{self, Parallel, Sequential};

/// Voxels a scan found seen through, judged again by the next ([`VoxelMap::clear_seen_through`]);
/// caller-owned, all zeros when empty.
#[derive(Clone, Debug)]
pub struct Suspects<const N: usize> {
    keys: [[i32; 3]; N],
    len: usize,
}

impl<const N: usize> Default for Suspects<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> Suspects<N> {
    /// No suspects.
    pub const fn new() -> Self {
        Self { keys: [[0; 3]; N], len: 0 }
    }

    /// Forgets them (a restart).
    pub fn clear(&mut self) {
        self.len = 0;
    }

    /// How many wait for the next judgement.
    pub fn len(&self) -> usize {
        self.len
    }

    /// None wait.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl VoxelMap<'_> {
    /// Judges last call's `suspects` again and removes those seen through again, then judges
    /// `budget` voxels round robin and makes suspects of those seen through. A voxel within
    /// `reach` of `sensor` (world frame, metres) is seen through when `judge(centre, slack)`
    /// says so with the voxel's half diagonal as slack, and `judge(point, 0)` of at least two (or
    /// all, if fewer) of its representatives, none seen. Returns how many were removed.
    pub fn clear_seen_through<const N: usize>(
        &mut self,
        sensor: [f32; 3],
        reach: f32,
        budget: usize,
        suspects: &mut Suspects<N>,
        judge: impl Fn([f32; 3], f32) -> Verdict + Sync,
    ) -> u32 {
        self.clear_seen_through_with(sensor, reach, budget, suspects, judge, &Sequential, &mut [])
    }

    /// [`Self::clear_seen_through`] with the round robin's judgements (read-only, one voxel at
    /// a time) split over `parallel`'s threads, each piece noting its verdicts in its own part
    /// of `scratch` (one entry per voxel judged; a longer budget goes in rounds of
    /// `scratch.len()`, an empty scratch in rounds of 64). The suspects are then taken in
    /// order, so the result is the same, bit for bit, for any width.
    #[allow(clippy::too_many_arguments)]
    pub fn clear_seen_through_with<const N: usize>(
        &mut self,
        sensor: [f32; 3],
        reach: f32,
        budget: usize,
        suspects: &mut Suspects<N>,
        judge: impl Fn([f32; 3], f32) -> Verdict + Sync,
        parallel: &dyn Parallel,
        scratch: &mut [u32],
    ) -> u32 {
        let reach = reach + self.cfg.voxel_size;
        let reach2 = reach * reach;
        let slack = 0.87 * self.cfg.voxel_size;
        let mut removed = 0u32;
        // The suspects: gone if this scan sees through them too.
        let n = core::mem::take(&mut suspects.len);
        for k in 0..n {
            let key = suspects.keys[k];
            let Some(i) = self.find_slot(key) else { continue };
            if self.seen_through(i as usize, sensor, reach2, slack, &judge) == Some(true) {
                self.remove_slot(i as usize);
                removed += 1;
            }
        }
        // Round robin: new suspects, judged in rounds of at most `scratch.len()` voxels.
        let mut local = [0u32; 64];
        let scratch = if scratch.is_empty() { &mut local[..] } else { scratch };
        let total = budget.min(self.len);
        let mut done = 0;
        while done < total {
            if self.clear_cursor >= self.len {
                self.clear_cursor = 0;
            }
            let start = self.clear_cursor;
            // A round, up to the pool's end (the next one starts at 0).
            let len = (total - done).min(scratch.len()).min(self.len - start);
            let verdicts = &mut scratch[..len];
            let map = &*self;
            parallel::map_indexed(parallel, verdicts, |k| {
                u32::from(map.seen_through(start + k, sensor, reach2, slack, &judge) == Some(true))
            });
            for (k, &v) in verdicts.iter().enumerate() {
                if v != 0 && suspects.len < N {
                    suspects.keys[suspects.len] = self.pool[start + k].key;
                    suspects.len += 1;
                }
            }
            self.clear_cursor = start + len;
            done += len;
        }
        self.counters.cleared += u64::from(removed);
        removed
    }

    /// Whether the scan sees through voxel `i` (`Some(false)`: it sees it; `None`: it cannot
    /// tell).
    fn seen_through(
        &self,
        i: usize,
        sensor: [f32; 3],
        reach2: f32,
        slack: f32,
        judge: &impl Fn([f32; 3], f32) -> Verdict,
    ) -> Option<bool> {
        let v = &self.pool[i];
        let c = self.centre(v.key);
        // A voxel the last scan put points in is where a surface was 0.1 s ago: judged later.
        if v.last_seen == self.stamp || d2f(c, sensor) > reach2 {
            return None;
        }
        match judge(c, slack) {
            Verdict::SeenThrough => {}
            Verdict::Seen => return Some(false),
            Verdict::Unknown => return None,
        }
        let (mut through, mut occupied) = (0u32, 0u32);
        for o in 0..OCTANTS {
            if v.occupied & (1 << o) == 0 {
                continue;
            }
            occupied += 1;
            match judge(self.rep_point(c, rep(v, o)), 0.0) {
                Verdict::SeenThrough => through += 1,
                Verdict::Seen => return Some(false),
                Verdict::Unknown => {}
            }
        }
        (through > 0 && through >= occupied.min(2)).then_some(true)
    }
}
