//! Clearing: voxels that a scan sees through (the space is empty now) leave the map; the free
//! space test itself is [`crate::free_space`]. Each call judges a fixed number of voxels round
//! robin, so the cost per scan stays fixed and a ghost goes within a few scans of being seen
//! through.

use super::voxel::rep;
use super::{OCTANTS, VoxelMap, d2f};
use crate::free_space::Verdict;

impl VoxelMap<'_> {
    /// Judges `budget` voxels round robin and removes each one within `reach` of `sensor` (world
    /// frame, metres) whose centre `judge(centre, slack)` finds seen through with the voxel's
    /// half diagonal as slack, and of whose representatives `judge(point, 0)` finds at least two
    /// (or all, if fewer) seen through and none seen. Returns how many were removed.
    pub fn clear_seen_through(
        &mut self,
        sensor: [f32; 3],
        reach: f32,
        budget: usize,
        mut judge: impl FnMut([f32; 3], f32) -> Verdict,
    ) -> u32 {
        let reach = reach + self.cfg.voxel_size;
        let reach2 = reach * reach;
        let slack = 0.87 * self.cfg.voxel_size;
        let mut removed = 0u32;
        for _ in 0..budget.min(self.len) {
            if self.clear_cursor >= self.len {
                self.clear_cursor = 0;
            }
            let i = self.clear_cursor;
            if self.seen_through(i, sensor, reach2, slack, &mut judge) {
                // The last voxel moves into the hole and is judged next.
                self.remove_slot(i);
                removed += 1;
            } else {
                self.clear_cursor += 1;
            }
        }
        self.counters.cleared += u64::from(removed);
        removed
    }

    fn seen_through(
        &self,
        i: usize,
        sensor: [f32; 3],
        reach2: f32,
        slack: f32,
        judge: &mut impl FnMut([f32; 3], f32) -> Verdict,
    ) -> bool {
        let v = &self.pool[i];
        let c = self.centre(v.key);
        // A voxel the last scan put points in is where a surface was 0.1 s ago: judged later.
        if v.last_seen == self.stamp || d2f(c, sensor) > reach2 || judge(c, slack) != Verdict::SeenThrough {
            return false;
        }
        let (mut through, mut occupied) = (0u32, 0u32);
        for o in 0..OCTANTS {
            if v.occupied & (1 << o) == 0 {
                continue;
            }
            occupied += 1;
            match judge(self.rep_point(c, rep(v, o)), 0.0) {
                Verdict::SeenThrough => through += 1,
                Verdict::Seen => return false,
                Verdict::Unknown => {}
            }
        }
        through > 0 && through >= occupied.min(2)
    }
}
