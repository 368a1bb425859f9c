//! Moving objects: a scan's moving points grown into the objects they belong to.
//!
//! The moving-point test of [`crate::free_space`] flags a point where the beams of an older scan
//! went through. On an object that moves with the sensor (a bus overtaking slowly) only the part
//! that moved into free space is flagged: the rest of it lies where the object itself stood in
//! the older scan. That rest then enters the map, and the object hides its own trail from every
//! later scan, so the map never sees through it again.
//!
//! An object is connected: the flagged points' coarse cells ([`GrowConfig::cell`] metres, in the
//! scan's frame) are grown through the 26 neighbouring cells that hold points of the scan, and
//! the points of the grown cells are moving too. Three rules keep the growth on the object:
//! - ground-like points (a normal within about 37 degrees of the vertical: roads, floors,
//!   roofs) hold no cell, so that no growth runs along the ground from one object to the next;
//! - the growth stops [`GrowConfig::depth`] cells from the nearest flagged cell;
//! - a connected set of flagged cells must hold [`GrowConfig::min_seeds`] of them (a single
//!   flagged cell on a wall is a false alarm, not an object), and a set that reaches more than
//!   [`GrowConfig::max_grown_per_seed`] unflagged cells per flagged one is a static structure the
//!   object touches (a wall): nothing of it grows.
//!
//! An object is also followed from scan to scan. An object that moves with the sensor may have
//! no flagged point at all in some scans (a bus a few metres ahead at the car's own speed, with
//! nothing behind it to see through): each scan leaves the world cells of its objects, and a
//! point of the next scan in one of them is a seed too. Two rules keep that from turning a false
//! alarm into a standing one:
//! - carried cells count only for a *confirmed* object: one that had at least
//!   [`GrowConfig::track_flagged`] flagged cells in [`GrowConfig::track_hits`] scans, the last of
//!   them at most [`GrowConfig::track_scans`] scans ago (a false alarm on a static structure
//!   flags a cell or two, rarely twice); before that they only link one object's scans;
//! - a point the older scan saw where it is now (a beam hit it: [`SEEN`]) is static and carries
//!   nothing, and carried cells do not widen the growth's bound (only flagged cells do).
//!
//! A wrongly grown point costs only its own scan (it is left out of the association and the map
//! for that scan); the map's contents are never removed here. The cells live in the caller's
//! storage (`N` slots, a power of two, at least 4/3 of the points judged; the tracks in 4,096
//! more), so the cost is fixed.

use crate::math::floor_i32;
use crate::scan::ScanPoint;

/// Settings of the growth.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct GrowConfig {
    /// Grow at all (with the free-space moving points).
    pub enabled: bool,
    /// Cell size, metres.
    pub cell: f32,
    /// Most cells from the nearest flagged cell.
    pub depth: u8,
    /// Fewest flagged cells in a connected set for it to grow.
    pub min_seeds: u16,
    /// Most unflagged cells a set may reach per flagged cell (plus [`Self::slack`]).
    pub max_grown_per_seed: f32,
    /// Unflagged cells a set may always reach.
    pub slack: u16,
    /// A point whose unit normal has at least this component along the vertical is ground-like.
    pub ground_cos: f32,
    /// Scans an object stays moving without a flagged point of its own: the world cells of a
    /// scan's objects seed the next scan's growth (0: off).
    pub track_scans: u8,
    /// Scans with flagged cells an object needs before it is carried without one.
    pub track_hits: u8,
    /// Cells a carried object without flagged cells may grow by.
    pub track_slack: u16,
    /// Flagged cells a set needs for its scan to count as one of its object's hits.
    pub track_flagged: u16,
}

impl GrowConfig {
    /// The defaults: 1 m cells, 8 cells deep, 2 flagged cells, 4 grown per flagged cell plus 32
    /// (on the traffic scenario, seed 1: map points where actors drove 2.62 % without the
    /// growth, 1.86 % with it; docs/voxel-map.md). Objects are tracked for 40 scans after 2 hits
    /// of 8 flagged cells, and grow by 32 cells without flagged ones (seeds 1-3 of the traffic:
    /// trails 0.48 / 0.82 / 0.74 % instead of 0.71 / 1.22 / 1.06 %; hits of 4 cells left out
    /// 0.125 % of the static vehicle drive's points, over the 0.1 % bound, 8 cells 0.071 %).
    pub const DEFAULT: Self = Self {
        enabled: true,
        cell: 1.0,
        depth: 8,
        min_seeds: 2,
        max_grown_per_seed: 4.0,
        slack: 32,
        ground_cos: 0.8,
        track_scans: 40,
        track_hits: 2,
        track_slack: 32,
        track_flagged: 8,
    };
}

impl Default for GrowConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

const EMPTY: u64 = 0;
const NONE: u32 = u32::MAX;

/// A cell's state.
const STATIC: u8 = 0;
const SEED: u8 = 1;
/// Reached from a seed set that may grow.
const GROWN: u8 = 2;
/// A seed carried from the last scans' objects: this plus the scans since the object had a
/// flagged point of its own.
const CARRIED: u8 = 64;
/// Not in a tracked object.
const UNTRACKED: u8 = u8::MAX;

/// The cells of one scan, in the caller's storage (`N` a power of two).
pub struct MovingObjects<const N: usize> {
    keys: [u64; N],
    state: [u8; N],
    /// BFS depth of each cell reached (u8::MAX: not yet).
    depth: [u8; N],
    /// The slots in use (to clear them) and the BFS queue.
    used: [u32; N],
    queue: [u32; N],
    /// Each cell's object age (scans since a flagged point), [`UNTRACKED`] if in none.
    age: [u8; N],
    /// Each cell's object's hits (scans with flagged cells).
    hits: [u8; N],
    /// The last scan's objects: world cells and their ages (an open-addressing table of
    /// `TRACKS` slots, its used slots listed to clear them).
    tracks: [u64; TRACKS],
    track_age: [u8; TRACKS],
    track_hits: [u8; TRACKS],
    track_used: [u16; TRACKS],
    track_n: usize,
}

/// World cells the objects of one scan may leave for the next (a quarter stays free).
const TRACKS: usize = 4096;

impl<const N: usize> core::fmt::Debug for MovingObjects<N> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("MovingObjects").field("slots", &N).finish()
    }
}

impl<const N: usize> Default for MovingObjects<N> {
    fn default() -> Self {
        Self::new()
    }
}

/// A cell's key: the three cell indices packed, never [`EMPTY`].
fn key(c: [i32; 3]) -> u64 {
    let f = |v: i32| u64::from((v as u32).wrapping_add(1 << 20) & 0x1f_ffff);
    (f(c[0]) | (f(c[1]) << 21) | (f(c[2]) << 42)) | (1 << 63)
}

fn hash(k: u64) -> usize {
    (k.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 40) as usize
}

/// Where `k` is in an open-addressing `table` (a power of two long) (`Ok`), or the empty slot
/// where it would go (`Err(Some)`; `Err(None)`: the table is full).
fn probe(table: &[u64], k: u64) -> Result<usize, Option<usize>> {
    let mask = table.len().wrapping_sub(1);
    let mut i = hash(k) & mask;
    for _ in 0..table.len() {
        if table[i] == k {
            return Ok(i);
        }
        if table[i] == EMPTY {
            return Err(Some(i));
        }
        i = (i + 1) & mask;
    }
    Err(None)
}

impl<const N: usize> MovingObjects<N> {
    /// Empty storage.
    pub const fn new() -> Self {
        Self {
            keys: [EMPTY; N],
            state: [0; N],
            depth: [0; N],
            used: [0; N],
            queue: [0; N],
            age: [0; N],
            hits: [0; N],
            tracks: [EMPTY; TRACKS],
            track_age: [0; TRACKS],
            track_hits: [0; TRACKS],
            track_used: [0; TRACKS],
            track_n: 0,
        }
    }

    /// Whether the last scan left objects to track.
    pub fn tracking(&self) -> bool {
        self.track_n > 0
    }

    /// Forgets the tracked objects (a scan without the moving-point test, a restart).
    pub fn forget_tracks(&mut self) {
        for u in 0..self.track_n {
            self.tracks[usize::from(self.track_used[u])] = EMPTY;
        }
        self.track_n = 0;
    }

    /// The slot of `k`, if present.
    fn find(&self, k: u64) -> Option<usize> {
        probe(&self.keys, k).ok()
    }

    /// The slot of `k`, inserted (as `STATIC`) if absent; `None` when the table is three
    /// quarters full (a quarter stays free so that every probe ends soon).
    fn insert(&mut self, k: u64, used: &mut usize) -> Option<usize> {
        match probe(&self.keys, k) {
            Ok(i) => Some(i),
            Err(Some(i)) if *used * 4 < N * 3 => {
                self.keys[i] = k;
                self.state[i] = STATIC;
                self.depth[i] = u8::MAX;
                self.age[i] = UNTRACKED;
                self.hits[i] = 0;
                self.used[*used] = i as u32;
                *used += 1;
                Some(i)
            }
            Err(_) => None,
        }
    }

    /// Grows the moving points `points[still..kept]` into the still points `points[..still]`
    /// of the same objects (see the module docs). The grown points are moved to the end of
    /// `points[..still]` (with their `normals`, same order of operations as the caller's
    /// partition); returns how many. `to_world` is the points' pose in the world (rotation
    /// rows, translation last: the world's vertical for the ground test, the tracked objects'
    /// cells); `cell_of` is scratch of at least `kept` entries.
    ///
    /// The world cells of this scan's objects are kept for the next call, where a still point
    /// in one of them (and not marked [`SEEN`] in `cell_of` on entry) is a seed of a confirmed
    /// object (module docs). Only the cells themselves carry on, not their neighbours.
    pub fn grow(
        &mut self,
        points: &mut [ScanPoint],
        normals: &mut [[f32; 3]],
        still: usize,
        cfg: &GrowConfig,
        to_world: &[[f32; 4]; 3],
        cell_of: &mut [u32],
    ) -> usize {
        let kept = points.len().min(normals.len()).min(cell_of.len());
        let bad_cell = cfg.cell.is_nan() || cfg.cell <= 0.0;
        if !cfg.enabled || N == 0 || !N.is_power_of_two() || still > kept || bad_cell {
            self.forget_tracks();
            return 0;
        }
        let inv = 1.0 / cfg.cell;
        // The world's vertical in the points' frame: the rotation's last row.
        let up = [to_world[2][0], to_world[2][1], to_world[2][2]];
        let world_key = |p: &[f32; 3]| {
            let w: [f32; 3] = core::array::from_fn(|a| {
                let r = &to_world[a];
                (r[0] * p[0] + r[1] * p[1] + r[2] * p[2] + r[3]) * inv
            });
            key(w.map(floor_i32))
        };
        let cell = |i: usize| {
            let n = normals[i];
            let vertical = (n[0] * up[0] + n[1] * up[1] + n[2] * up[2]).abs();
            let unit = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2] - 1.0).abs() < 0.1;
            let p = points[i].xyz;
            (!(unit && vertical >= cfg.ground_cos))
                .then(|| [p[0] * inv, p[1] * inv, p[2] * inv].map(floor_i32))
        };
        // 0. Fewer flagged cells than a set needs (a few false alarms, the usual case): nothing
        // can grow, and the scan's other points need no cells.
        let mut seeds = heapless::Vec::<[i32; 3], SEED_CHECK>::new();
        for i in still..kept {
            if let Some(c) = cell(i)
                && !seeds.contains(&c)
                && seeds.push(c).is_err()
            {
                break;
            }
        }
        let carry = cfg.track_scans > 0 && self.track_n > 0;
        if seeds.len() < SEED_CHECK && seeds.len() < usize::from(cfg.min_seeds) && !carry {
            self.forget_tracks();
            return 0;
        }
        let mut used = 0usize;
        // 1. Cells of every point that is not ground-like; flagged points make seeds, and so do
        // points in the last scan's objects' world cells.
        for (i, co) in cell_of[..kept].iter_mut().enumerate() {
            let seen = *co == SEEN;
            *co = NONE;
            let Some(c) = cell(i) else { continue };
            if let Some(s) = self.insert(key(c), &mut used) {
                *co = s as u32;
                if i >= still {
                    self.state[s] = SEED;
                } else if carry
                    && !seen
                    && self.state[s] != SEED
                    && let Ok(t) = probe(&self.tracks, world_key(&points[i].xyz))
                {
                    let a = CARRIED.saturating_add(self.track_age[t]);
                    if self.state[s] == STATIC || a < self.state[s] {
                        self.state[s] = a;
                    }
                    self.hits[s] = self.hits[s].max(self.track_hits[t]);
                }
            }
        }
        self.forget_tracks();
        let is_seed = |st: u8| st == SEED || st >= CARRIED;
        // 2. Each connected set of seeds, breadth first through the occupied cells.
        let mut any = false;
        for u in 0..used {
            let s0 = self.used[u] as usize;
            if !is_seed(self.state[s0]) || self.depth[s0] != u8::MAX {
                continue;
            }
            // First the seeds of this set (depth 0), then the cells around them.
            let (mut head, mut tail) = (0usize, 0usize);
            self.depth[s0] = 0;
            self.queue[tail] = s0 as u32;
            tail += 1;
            let (mut seeds, mut reached) = (0u32, 0u32);
            // The set's age: 0 with a flagged cell, else one more than its youngest carried one;
            // its hits: the scans its object had flagged cells in.
            let (mut youngest, mut hits, mut flagged, mut linked) = (u8::MAX, 0u8, 0u32, 0u32);
            while head < tail {
                let s = self.queue[head] as usize;
                head += 1;
                if is_seed(self.state[s]) {
                    seeds += 1;
                    if self.state[s] == SEED {
                        flagged += 1;
                        youngest = 0;
                    } else {
                        linked += 1;
                        youngest = youngest.min((self.state[s] - CARRIED).saturating_add(1));
                        hits = hits.max(self.hits[s]);
                    }
                } else {
                    reached += 1;
                }
                let d = self.depth[s];
                let c = unkey(self.keys[s]);
                for dz in -1..=1 {
                    for dy in -1..=1 {
                        for dx in -1..=1 {
                            if dx == 0 && dy == 0 && dz == 0 {
                                continue;
                            }
                            let Some(t) = self.find(key([c[0] + dx, c[1] + dy, c[2] + dz])) else {
                                continue;
                            };
                            if self.depth[t] != u8::MAX {
                                continue;
                            }
                            // Seeds join at depth 0 (the set is all the flagged cells it
                            // touches); other cells one deeper, up to the limit.
                            let nd = if is_seed(self.state[t]) { 0 } else { d.saturating_add(1) };
                            if nd > cfg.depth {
                                continue;
                            }
                            self.depth[t] = nd;
                            if tail < N {
                                self.queue[tail] = t as u32;
                                tail += 1;
                            }
                        }
                    }
                }
            }
            // Carried cells count (as seeds, and move) only for a confirmed object: one with
            // [`GrowConfig::track_hits`] scans of many flagged cells (a false alarm on a static
            // structure flags a few) and one not too long ago. Otherwise they only link the
            // scans of one object, so that it can be confirmed. Only flagged cells widen the
            // growth's bound, so that a carried set cannot grow by its own growth.
            let confirmed = hits >= cfg.track_hits && youngest <= cfg.track_scans;
            let hits = hits.saturating_add(u8::from(flagged >= u32::from(cfg.track_flagged)));
            let live =
                flagged >= u32::from(cfg.min_seeds) || (confirmed && seeds >= u32::from(cfg.min_seeds));
            let slack = if flagged > 0 { cfg.slack } else { cfg.track_slack };
            let cap = cfg.max_grown_per_seed * flagged as f32 + f32::from(slack);
            // Unconfirmed carried cells are the object's own cells the growth reaches.
            let reached = if confirmed { reached } else { reached + linked };
            let grows = live && (reached as f32) <= cap;
            let tracked = if live && cfg.track_scans > 0 { youngest } else { UNTRACKED };
            for q in 0..tail {
                let s = self.queue[q] as usize;
                let st = self.state[s];
                self.hits[s] = hits;
                if st == SEED {
                    self.age[s] = tracked;
                } else if st >= CARRIED {
                    // A carried seed moves with its set (else it is a still point again).
                    let moves = live && confirmed || grows;
                    self.state[s] = if moves { GROWN } else { STATIC };
                    self.age[s] = tracked;
                    any |= moves;
                } else {
                    if grows {
                        self.state[s] = GROWN;
                        self.age[s] = tracked;
                        any = true;
                    }
                    // Open again for the next set, which must count what it reaches too.
                    self.depth[s] = u8::MAX;
                }
            }
        }
        // 3. The still points of grown cells move to the end of the still ones.
        let mut end = still;
        if any {
            let mut i = 0;
            while i < end {
                let s = cell_of[i];
                if s != NONE && self.state[s as usize] == GROWN {
                    end -= 1;
                    points.swap(i, end);
                    normals.swap(i, end);
                    cell_of.swap(i, end);
                } else {
                    i += 1;
                }
            }
        }
        // 4. The objects' world cells for the next scan (the moving points: flagged and grown),
        // then clear the slots used.
        if cfg.track_scans > 0 {
            for i in end..kept {
                let s = cell_of[i];
                if s == NONE || self.age[s as usize] == UNTRACKED {
                    continue;
                }
                let (a, h, k) = (self.age[s as usize], self.hits[s as usize], world_key(&points[i].xyz));
                match probe(&self.tracks, k) {
                    Ok(t) => {
                        self.track_age[t] = self.track_age[t].min(a);
                        self.track_hits[t] = self.track_hits[t].max(h);
                    }
                    Err(Some(t)) if self.track_n * 4 < TRACKS * 3 => {
                        self.tracks[t] = k;
                        self.track_age[t] = a;
                        self.track_hits[t] = h;
                        self.track_used[self.track_n] = t as u16;
                        self.track_n += 1;
                    }
                    Err(_) => {}
                }
            }
        }
        for u in 0..used {
            self.keys[self.used[u] as usize] = EMPTY;
        }
        still - end
    }
}

/// In `cell_of` on entry: the reference saw this still point where it is now (it carries no
/// tracked object).
pub const SEEN: u32 = 2;

/// Distinct flagged cells counted before the growth (at most), to skip it when a set cannot
/// hold [`GrowConfig::min_seeds`] of them.
const SEED_CHECK: usize = 8;

/// The cell indices of a key.
fn unkey(k: u64) -> [i32; 3] {
    let f = |v: u64| ((v & 0x1f_ffff) as u32).wrapping_sub(1 << 20) as i32;
    [f(k), f(k >> 21), f(k >> 42)]
}

#[cfg(test)]
mod tests {
    use super::*;

    const ID: [[f32; 4]; 3] = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]];

    fn pt(x: f32, y: f32, z: f32) -> ScanPoint {
        ScanPoint { xyz: [x, y, z], t: 0.0, row: 0, col: 0, intensity: 0, ret: 0, flags: 0 }
    }

    #[test]
    fn keys_round_trip() {
        for c in [[0, 0, 0], [-1, 2, -3], [1 << 19, -(1 << 19), 77]] {
            assert_eq!(unkey(key(c)), c);
            assert_ne!(key(c), EMPTY);
        }
    }

    /// A 12 m "bus" side (x 0..12, y 3, z -1.5..1.5) whose front 8 m were flagged, beside a
    /// road (ground points), a long wall farther out (y 10) and a lone false alarm on it.
    fn scene() -> (heapless::Vec<ScanPoint, 2048>, heapless::Vec<[f32; 3], 2048>, usize, usize) {
        let mut still: heapless::Vec<(ScanPoint, [f32; 3]), 2048> = heapless::Vec::new();
        let mut moving: heapless::Vec<(ScanPoint, [f32; 3]), 2048> = heapless::Vec::new();
        let side = [0.0, -1.0, 0.0];
        for i in 0..24 {
            for k in 0..6 {
                let (x, z) = (0.5 * i as f32 + 0.25, -1.5 + 0.5 * k as f32 + 0.25);
                let p = (pt(x, 3.0, z), side);
                if x >= 4.0 { moving.push(p).unwrap() } else { still.push(p).unwrap() }
            }
        }
        // The road: ground points under and around everything (normals up).
        for i in -10..30 {
            for j in -2..14 {
                still.push((pt(0.5 * i as f32, 0.5 * j as f32, -1.8), [0.0, 0.0, 1.0])).unwrap();
            }
        }
        // The wall: 60 m long, 3 m high, at y = 10.
        for i in 0..120 {
            for k in 0..6 {
                still.push((pt(-20.0 + 0.5 * i as f32, 10.0, -1.5 + 0.5 * k as f32), side)).unwrap();
            }
        }
        // False alarms: two flagged points on the wall in one cell, and a patch of three
        // cells' worth (a set that reaches far more of the wall than it holds).
        moving.push((pt(20.1, 10.0, 0.2), side)).unwrap();
        moving.push((pt(20.3, 10.0, 0.4), side)).unwrap();
        for x in [30.5, 31.5, 32.5] {
            moving.push((pt(x, 10.0, 0.5), side)).unwrap();
        }
        let (n_still, n_moving) = (still.len(), moving.len());
        let mut pts = heapless::Vec::new();
        let mut nrm = heapless::Vec::new();
        for (p, n) in still.iter().chain(moving.iter()) {
            pts.push(*p).unwrap();
            nrm.push(*n).unwrap();
        }
        (pts, nrm, n_still, n_moving)
    }

    #[test]
    fn a_flagged_front_takes_the_rest_of_its_object_and_nothing_else() {
        let obj = &mut MovingObjects::<4096>::new();
        let (mut pts, mut nrm, still, _) = scene();
        let mut cell_of = [0u32; 2048];
        let grown = obj.grow(&mut pts, &mut nrm, still, &GrowConfig::DEFAULT, &ID, &mut cell_of);
        // The bus's unflagged 4 m (8 x 6 points) and nothing of the ground or the wall.
        assert_eq!(grown, 48);
        for p in &pts[still - grown..still] {
            assert!(p.xyz[1] == 3.0 && p.xyz[0] < 4.0, "{:?}", p.xyz);
        }
        for p in &pts[..still - grown] {
            assert!(p.xyz[1] != 3.0 || p.xyz[2] < -1.6, "{:?}", p.xyz);
        }
        // Again with the same storage: the same answer (the cells were cleared).
        let (mut pts2, mut nrm2, still2, _) = scene();
        let again = obj.grow(&mut pts2, &mut nrm2, still2, &GrowConfig::DEFAULT, &ID, &mut cell_of);
        assert_eq!(again, 48);
        // Off: nothing.
        let off = GrowConfig { enabled: false, ..GrowConfig::DEFAULT };
        let (mut pts3, mut nrm3, still3, _) = scene();
        assert_eq!(obj.grow(&mut pts3, &mut nrm3, still3, &off, &ID, &mut cell_of), 0);
        // Without the depth to reach the rear: only what lies within it (and the wall's patch,
        // which reaches less of the wall now, is small enough to grow: 3 seeds, 8 cells).
        let shallow = GrowConfig { depth: 1, ..GrowConfig::DEFAULT };
        let (mut pts4, mut nrm4, still4, _) = scene();
        let some = obj.grow(&mut pts4, &mut nrm4, still4, &shallow, &ID, &mut cell_of);
        let bus = pts4[still4 - some..still4].iter().filter(|p| p.xyz[1] == 3.0).count();
        assert_eq!(bus, 12, "the 1 m column behind the flagged front: 2 x 6 points");
    }

    /// A bus side 12 m long from `x0` (y 3) whose points from `flag_from` on are flagged, and
    /// a 60 m wall (y 10).
    fn bus(
        x0: f32,
        flag_from: f32,
    ) -> (heapless::Vec<ScanPoint, 2048>, heapless::Vec<[f32; 3], 2048>, [u32; 2048], usize) {
        let side = [0.0, -1.0, 0.0];
        let (mut still, mut moving) = (heapless::Vec::<_, 2048>::new(), heapless::Vec::<_, 2048>::new());
        for i in 0..24 {
            for k in 0..6 {
                let (x, z) = (x0 + 0.5 * i as f32 + 0.25, -1.5 + 0.5 * k as f32 + 0.25);
                let p = (pt(x, 3.0, z), side, 0);
                if x >= flag_from { moving.push(p).unwrap() } else { still.push(p).unwrap() }
            }
        }
        for i in 0..120 {
            for k in 0..6 {
                let p = (pt(-20.0 + 0.5 * i as f32, 10.0, -1.5 + 0.5 * k as f32), side, 0);
                still.push(p).unwrap();
            }
        }
        let n_still = still.len();
        let (mut pts, mut nrm, mut cell_of) = (heapless::Vec::new(), heapless::Vec::new(), [0u32; 2048]);
        for (i, (p, n, c)) in still.iter().chain(moving.iter()).enumerate() {
            pts.push(*p).unwrap();
            nrm.push(*n).unwrap();
            cell_of[i] = *c;
        }
        (pts, nrm, cell_of, n_still)
    }

    /// Moving points (grown and flagged) of one call on a [`bus`] scene: (on the bus, elsewhere).
    fn moving_after(
        obj: &mut MovingObjects<4096>,
        cfg: &GrowConfig,
        x0: f32,
        flag_from: f32,
    ) -> (usize, usize) {
        let (mut pts, mut nrm, mut cell_of, still) = bus(x0, flag_from);
        let grown = obj.grow(&mut pts, &mut nrm, still, cfg, &ID, &mut cell_of);
        let moving = &pts[still - grown..];
        let on_bus = moving.iter().filter(|p| p.xyz[1] == 3.0).count();
        (on_bus, moving.len() - on_bus)
    }

    #[test]
    fn a_confirmed_object_stays_moving_without_flagged_points_for_a_while() {
        let obj = &mut MovingObjects::<4096>::new();
        let cfg = GrowConfig { track_scans: 3, ..GrowConfig::DEFAULT };
        // Flagged in two scans (its front, as it moves 0.5 m a scan): confirmed.
        assert_eq!(moving_after(obj, &cfg, 0.0, 4.0), (144, 0));
        assert_eq!(moving_after(obj, &cfg, 0.5, 5.0), (144, 0));
        // Then nothing flagged: the whole bus still moves (its cells of the last scan carry, the
        // growth takes its new front), for `track_scans` scans; the wall never does.
        for k in 2..5 {
            assert_eq!(moving_after(obj, &cfg, 0.5 * k as f32, 100.0), (144, 0), "scan {k}");
        }
        assert_eq!(moving_after(obj, &cfg, 2.5, 100.0), (0, 0), "tracked too long");
        assert!(!obj.tracking());
        // Without the tracks (`track_scans` 0) the second scan's growth is the same, and the
        // unflagged scans move nothing.
        let off = GrowConfig { track_scans: 0, ..GrowConfig::DEFAULT };
        assert_eq!(moving_after(obj, &off, 0.0, 4.0), (144, 0));
        assert_eq!(moving_after(obj, &off, 0.5, 5.0), (144, 0));
        assert_eq!(moving_after(obj, &off, 1.0, 100.0), (0, 0));
    }

    #[test]
    fn a_false_alarm_or_a_seen_point_carries_nothing() {
        let obj = &mut MovingObjects::<4096>::new();
        let cfg = GrowConfig { track_scans: 40, ..GrowConfig::DEFAULT };
        // Flagged once only (one hit): the next scan without flags moves nothing.
        assert_eq!(moving_after(obj, &cfg, 0.0, 4.0), (144, 0));
        assert_eq!(moving_after(obj, &cfg, 0.0, 100.0), (0, 0));
        // Flagged in two scans, but in fewer cells than a hit needs (4 against 5): no hits.
        let few = GrowConfig { track_flagged: 5, ..cfg };
        assert!(moving_after(obj, &few, 0.0, 11.0).0 >= 12);
        assert!(moving_after(obj, &few, 0.0, 11.0).0 >= 12);
        assert_eq!(moving_after(obj, &few, 0.0, 100.0), (0, 0));
        // Confirmed, but the older scan saw every point where it is now: static after all.
        assert_eq!(moving_after(obj, &cfg, 0.0, 4.0), (144, 0));
        assert_eq!(moving_after(obj, &cfg, 0.0, 4.0), (144, 0));
        let (mut pts, mut nrm, mut cell_of, still) = bus(0.0, 100.0);
        for c in cell_of[..still].iter_mut() {
            *c = SEEN;
        }
        assert_eq!(obj.grow(&mut pts, &mut nrm, still, &cfg, &ID, &mut cell_of), 0);
    }

    #[test]
    fn storage_too_small_grows_nothing_wrongly() {
        let obj = &mut MovingObjects::<64>::new();
        let (mut pts, mut nrm, still, _) = scene();
        let mut cell_of = [0u32; 2048];
        let grown = obj.grow(&mut pts, &mut nrm, still, &GrowConfig::DEFAULT, &ID, &mut cell_of);
        // Some cells find no slot; whatever grows is still on the bus.
        for p in &pts[still - grown..still] {
            assert!(p.xyz[1] == 3.0, "{:?}", p.xyz);
        }
    }
}
