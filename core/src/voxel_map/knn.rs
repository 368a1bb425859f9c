//! The k-NN search over the representatives of a query's 27 voxels (search order, sorted
//! candidates, a batched pipeline that overlaps cache misses); separate as it only reads the map.

use super::index::{block_hash, index_first_with_hash, sub_block};
use super::voxel::{rep, rep_d2, rep_normal};
use super::{KNN_MAX, NO_HINT, OCTANTS, VoxelHandle, VoxelMap, prefetch};
use crate::surfel::{self, SurfelReject};

/// Which voxels a k-NN query searches. The one definition: the host's config key
/// `mapping.knn_search` and its `--knn-search` take it as is (`exact`, `block`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum KnnReach {
    /// The query's voxel and its 26 neighbours: the exact k-NN within them (see
    /// [`VoxelMap::knn`]).
    #[cfg_attr(feature = "clap", value(help = "The exact k nearest within the 27 voxels around each point"))]
    Exact,
    /// The query's octant block first: its voxel and the 7 on its side of each face (the 2x2x2
    /// voxels around the query's nearest voxel corner). Every point within half a voxel of the
    /// query lies there. If the block holds `k` points within `max_dist`, they are the answer
    /// (the exact k-NN of the block); else the other 19 voxels are searched as for
    /// `Exact`. An approximation in the spirit of Faster-LIO's iVox: a neighbour it
    /// misses is at least half a voxel away, outside the block, and the plane then fitted is
    /// more local. On the simulated VLP-32C vehicle drive it skips 5.2 of the 12.8 boxes a
    /// query visits, and the association takes 0.9x the time. The odometry's default since the
    /// standstill updates hold the stand at the start (`AssociationConfig::knn_reach`).
    #[default]
    #[cfg_attr(feature = "clap", value(help = "The point's 2x2x2 octant block first: faster, approximate"))]
    Block,
}

/// Parameters of a k-NN query.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct KnnQuery {
    /// How many neighbours (at most [`KNN_MAX`]). Default 5.
    pub k: usize,
    /// Only points within this distance, metres. Default: the voxel size (see [`VoxelMap::knn`]).
    pub max_dist: f32,
    /// Take at most one point (its nearest representative) per voxel, so the k results name k
    /// distinct voxels, as the reference's ikd-tree (one point per voxel) gives. Default false.
    pub one_per_voxel: bool,
    /// Which voxels are searched. Default [`KnnReach::Exact`] (exact).
    pub reach: KnnReach,
}

impl KnnQuery {
    /// `k` neighbours within `max_dist`, any number per voxel, exact within the 27 voxels.
    pub const fn new(k: usize, max_dist: f32) -> Self {
        Self { k, max_dist, one_per_voxel: false, reach: KnnReach::Exact }
    }

    /// The same query with another reach.
    pub const fn with_reach(self, reach: KnnReach) -> Self {
        Self { reach, ..self }
    }
}

/// One neighbour found by [`VoxelMap::knn`].
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Neighbour {
    /// The map point, world frame.
    pub point: [f32; 3],
    /// Squared distance from the query, metres².
    pub dist2: f32,
    /// The voxel holding it.
    pub voxel: VoxelHandle,
    /// Its normal, quantised (see [`Self::normal`]).
    normal_q: [i8; 3],
}

impl Neighbour {
    const NONE: Neighbour =
        Neighbour { point: [0.0; 3], dist2: 0.0, voxel: VoxelHandle(0), normal_q: [0; 3] };

    /// The point's normal (unit, within 0.5 degrees of the one inserted), if it had one.
    /// Computed on demand: the reference's association never reads per-point normals.
    /// Inlined: out of line (another codegen unit) the association called it through the GOT
    /// and read its result back from memory, a stall per neighbour.
    #[inline]
    pub fn normal(&self) -> Option<[f32; 3]> {
        rep_normal(self.normal_q)
    }
}

/// Result buffer of [`VoxelMap::knn`]: up to [`KNN_MAX`] neighbours sorted by distance.
#[derive(Clone, Copy, Debug)]
pub struct Neighbours {
    items: [Neighbour; KNN_MAX],
    len: usize,
}

impl Neighbours {
    /// Empty.
    pub const fn new() -> Self {
        Self { items: [Neighbour::NONE; KNN_MAX], len: 0 }
    }
    /// The neighbours, nearest first.
    #[inline]
    pub fn as_slice(&self) -> &[Neighbour] {
        &self.items[..self.len]
    }
    /// How many were found.
    #[inline]
    pub fn len(&self) -> usize {
        self.len
    }
    /// Whether none was found.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
    /// The neighbours' points, for [`surfel::fit_plane`]; the array is filled up to `len()`.
    pub fn points(&self) -> [[f32; 3]; KNN_MAX] {
        let mut out = [[0.0; 3]; KNN_MAX];
        for (o, n) in out.iter_mut().zip(self.as_slice()) {
            *o = n.point;
        }
        out
    }
    /// The neighbours' voxel handles, for [`VoxelMap::large_surfel`]; filled up to `len()`.
    pub fn voxels(&self) -> [VoxelHandle; KNN_MAX] {
        let mut out = [VoxelHandle(0); KNN_MAX];
        for (o, n) in out.iter_mut().zip(self.as_slice()) {
            *o = n.voxel;
        }
        out
    }
    /// The point-to-plane fallback: a plane through the neighbours, accepted only if every one
    /// lies within `max_dist` of it (reference: 0.1 m). See [`surfel::fit_plane`].
    pub fn fit_plane(&self, max_dist: f32) -> Result<surfel::Plane, SurfelReject> {
        let pts = self.points();
        surfel::fit_plane(&pts[..self.len], max_dist)
    }
}

impl Default for Neighbours {
    fn default() -> Self {
        Self::new()
    }
}

/// The query's octant: its own box, then the face, edge and corner neighbours on its side
/// (multiplied per axis by the side, -1 or +1).
const NEAR_ORDER: [[i32; 3]; 8] =
    [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1], [1, 1, 1]];

/// The order a k-NN search visits the 27 boxes, in "side" coordinates (per axis, +1 is the
/// neighbour on the query's side of its voxel centre, -1 the one on the other side): the
/// octant's 8 boxes ([`NEAR_ORDER`]), then the other 19 in [`NEIGHBOURS`] order (faces, edges,
/// corners). A query's offsets are these times its side per axis.
const SEARCH_ORDER: [[i32; 3]; 27] = search_order();

const fn search_order() -> [[i32; 3]; 27] {
    let mut out = [[0i32; 3]; 27];
    let mut n = 0;
    while n < 8 {
        out[n] = NEAR_ORDER[n];
        n += 1;
    }
    let mut j = 0;
    while j < 27 {
        let off = NEIGHBOURS[j];
        if off[0] < 0 || off[1] < 0 || off[2] < 0 {
            out[n] = off;
            n += 1;
        }
        j += 1;
    }
    out
}

/// [`SEARCH_ORDER`] per axis as indices into `[other side, own, query's side]`.
const SEARCH_IDX: [[usize; 27]; 3] = {
    let mut out = [[0usize; 27]; 3];
    let mut i = 0;
    while i < 27 {
        let mut a = 0;
        while a < 3 {
            out[a][i] = (SEARCH_ORDER[i][a] + 1) as usize;
            a += 1;
        }
        i += 1;
    }
    out
};

/// The 27 voxel offsets of a neighbourhood, the centre first, then faces, edges and corners.
pub(super) const NEIGHBOURS: [[i32; 3]; 27] = neighbour_order();

const fn neighbour_order() -> [[i32; 3]; 27] {
    let mut out = [[0i32; 3]; 27];
    let mut n = 0;
    let mut ring = 0;
    while ring <= 3 {
        let mut i = 0i32;
        while i < 27 {
            let d = [i / 9 - 1, (i / 3) % 3 - 1, i % 3 - 1];
            let m = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            if m == ring {
                out[n] = d;
                n += 1;
            }
            i += 1;
        }
        ring += 1;
    }
    out
}

impl VoxelMap<'_> {
    /// The `k` nearest map points to `q` within `max_dist`, nearest first, written to `out`;
    /// returns how many were found.
    ///
    /// The search covers the query's voxel and its 26 neighbours, nearest boxes first, skipping
    /// boxes farther than the current k-th distance. Every map point within `voxel_size` of the
    /// query lies in those 27 voxels, so with `max_dist <= voxel_size` the result is the exact
    /// k-NN of the whole map (up to rounding at voxel faces); with a larger `max_dist` it is the
    /// exact k-NN among the 27 voxels. Ties keep the first found (deterministic). A non-finite
    /// query finds nothing.
    pub fn knn(&self, q: [f32; 3], query: &KnnQuery, out: &mut Neighbours) -> usize {
        out.len = 0;
        let Some((k, bound2)) = Self::knn_params(query) else { return 0 };
        let Some(mut pre) = self.prepare(q) else { return 0 };
        // The query's own box and the 7 others on its side of each face (its octant) hold the
        // nearest points almost always: their index entries are probed together, so their
        // cache misses overlap (queries are bound by memory latency). The other boxes are
        // probed only if the search gets to them.
        for i in 0..OCTANTS {
            if pre.bd[i] <= bound2 {
                self.probe(&mut pre, i);
            }
        }
        self.finish_knn(&mut pre, q, query, k, bound2, out)
    }

    /// [`Self::knn`] for many queries: `out[i]` receives the neighbours of `queries[i]` (for
    /// `i < min(queries.len(), out.len())`); returns the total found. The results are exactly
    /// those of [`Self::knn`] called on each query in turn, obtained faster: queries go in
    /// groups of 8, and all the index lines, then all the voxels, of a group's neighbourhoods
    /// are read before any member is searched, so the cache misses overlap instead of being paid
    /// one after another. Give nearby queries together (the odometry's downsampled points come in
    /// the Morton order of their voxels).
    pub fn knn_many(&self, queries: &[[f32; 3]], query: &KnnQuery, out: &mut [Neighbours]) -> usize {
        let m = queries.len().min(out.len());
        for o in out[..m].iter_mut() {
            o.len = 0;
        }
        let Some((k, bound2)) = Self::knn_params(query) else { return 0 };
        // A software pipeline over groups of KNN_GROUP queries: while group g is searched, the
        // voxels of group g + 1 (whose index entries arrived meanwhile) and the index lines of
        // group g + 2 are being fetched.
        let groups = m.div_ceil(KNN_GROUP);
        let mut ring = [[None; KNN_GROUP]; 3];
        let mut total = 0;
        for g in 0..groups + 2 {
            // Stage 1, group g: keys, block hashes, prefetch of the blocks' home index lines.
            if g < groups {
                let slot = &mut ring[g % 3];
                for (i, pre) in slot.iter_mut().enumerate() {
                    let qi = g * KNN_GROUP + i;
                    *pre = if qi < m { self.prepare(queries[qi]) } else { None };
                    if let Some(p) = pre {
                        for bh in p.bh {
                            prefetch(&self.index[(bh << 3) as usize & self.mask]);
                        }
                    }
                }
            }
            // Stage 2, group g - 1: probe the octants, prefetch their voxels.
            if g >= 1 && g - 1 < groups {
                for p in ring[(g - 1) % 3].iter_mut().flatten() {
                    for i in 0..OCTANTS {
                        if p.bd[i] <= bound2 {
                            let slot = self.probe(p, i);
                            if slot != NO_HINT {
                                let v = &self.pool[slot as usize];
                                prefetch(v); // line 0: key and representatives
                                prefetch(&v.last_seen); // line 1: the sums (large surfels)
                                prefetch(&v.rep_normals); // line 2: their normals
                            }
                        }
                    }
                }
            }
            // Stage 3, group g - 2: the searches.
            if g >= 2 {
                let gg = g - 2;
                for (i, pre) in ring[gg % 3].iter_mut().enumerate() {
                    let qi = gg * KNN_GROUP + i;
                    if let Some(p) = pre {
                        total += self.finish_knn(p, queries[qi], query, k, bound2, &mut out[qi]);
                    }
                }
            }
        }
        total
    }

    /// `(k, max_dist²)`, or `None` if the query asks for nothing.
    fn knn_params(query: &KnnQuery) -> Option<(usize, f32)> {
        let k = query.k.min(KNN_MAX);
        if k == 0 || !(query.max_dist >= 0.0) {
            return None;
        }
        Some((k, query.max_dist * query.max_dist))
    }

    /// The query's voxel, the distances to its neighbouring boxes and the hashes of the 8
    /// blocks (2x2x2 voxels) the neighbourhood spans; no box probed yet. `None` out of range.
    #[inline]
    pub(super) fn prepare(&self, q: [f32; 3]) -> Option<Prepared> {
        let key = self.key_of(q)?;
        let c0 = self.centre(key);
        let mut gap2 = [[0.0f32; 3]; 3];
        for a in 0..3 {
            let rel = q[a] - c0[a];
            let lo = (rel + self.d.half - self.d.slack).max(0.0);
            let hi = (self.d.half - rel - self.d.slack).max(0.0);
            gap2[a] = [lo * lo, 0.0, hi * hi];
        }
        let side = [
            if q[0] < c0[0] { -1 } else { 1 },
            if q[1] < c0[1] { -1 } else { 1 },
            if q[2] < c0[2] { -1 } else { 1 },
        ];
        // keys k-1 .. k+1 span exactly two blocks per axis: (k-1)>>1 and the next.
        let b0 = [(key[0] - 1) >> 1, (key[1] - 1) >> 1, (key[2] - 1) >> 1];
        let mut bh = [0u32; 8];
        for (i, h) in bh.iter_mut().enumerate() {
            let i = i as i32;
            *h = block_hash([b0[0] + (i & 1), b0[1] + (i >> 1 & 1), b0[2] + (i >> 2)]);
        }
        // Squared box distances in the search order, summed per axis in a fixed order (x, then
        // y, then z); per axis [other side, own, query's side].
        let g: [[f32; 3]; 3] = core::array::from_fn(|a| {
            let [lo, mid, hi] = gap2[a];
            if side[a] > 0 { [lo, mid, hi] } else { [hi, mid, lo] }
        });
        let bd: [f32; 27] = core::array::from_fn(|i| {
            g[0][SEARCH_IDX[0][i]] + g[1][SEARCH_IDX[1][i]] + g[2][SEARCH_IDX[2][i]]
        });
        Some(Prepared { key, b0, bd, side, bh, slots: [UNPROBED; 27] })
    }

    /// The slot of the first index entry with the hash of the `i`-th box of the query's search
    /// order (not key-checked), or `NO_HINT`; remembered in `pre`.
    #[inline]
    fn probe(&self, pre: &mut Prepared, i: usize) -> u32 {
        if pre.slots[i] == UNPROBED {
            let h = pre.hash(pre.offset(i));
            pre.slots[i] = index_first_with_hash(self.index, self.mask, h).unwrap_or(NO_HINT);
        }
        pre.slots[i]
    }

    /// The search proper: the octant's boxes, then the other 19, each only if not already
    /// farther than the k-th distance found (with [`KnnReach::Block`], only if the octant's
    /// boxes gave fewer than `k`); then the neighbours' points and normals.
    fn finish_knn(
        &self,
        pre: &mut Prepared,
        q: [f32; 3],
        query: &KnnQuery,
        k: usize,
        bound2: f32,
        out: &mut Neighbours,
    ) -> usize {
        let one_per_voxel = query.one_per_voxel;
        let mut cand = Candidates::EMPTY;
        // The voxel slot of each box searched, by search order.
        let mut found = [0u32; 27];
        // The octant's boxes, each unless it is out of bound or beyond the k-th candidate.
        for i in 0..OCTANTS {
            let bd2 = pre.bd[i];
            if (bd2 <= bound2) & (bd2 < cand.dist(k - 1)) {
                self.visit(pre, i, q, one_per_voxel, &mut cand, &mut found, k, bound2);
            }
        }
        // The other 19: those that may still hold a candidate, found with one pass of compares
        // and visited in order (the k-th distance only shrinks, so each is checked again).
        // The block reach stops here when the octant gave k (all within the bound, so finite).
        let kth = cand.dist(k - 1);
        let block_done = query.reach == KnnReach::Block && kth < f32::INFINITY;
        let kth = if block_done { 0.0 } else { kth };
        let mut rest = 0u32;
        for i in OCTANTS..27 {
            let bd2 = pre.bd[i];
            rest |= u32::from((bd2 <= bound2) & (bd2 < kth)) << i;
        }
        while rest != 0 {
            let i = rest.trailing_zeros() as usize;
            rest &= rest - 1;
            if pre.bd[i] < cand.dist(k - 1) {
                self.visit(pre, i, q, one_per_voxel, &mut cand, &mut found, k, bound2);
            }
        }
        let mut n = 0;
        for i in 0..k {
            let d2 = cand.dist(i);
            if d2 == f32::INFINITY {
                break;
            }
            let (bi, o) = cand.box_octant(i);
            let slot = found[bi];
            let v = &self.pool[slot as usize];
            let c = self.centre(v.key);
            out.items[i] = Neighbour {
                point: self.rep_point(c, rep(v, o)),
                normal_q: v.rep_normals[o],
                dist2: d2,
                voxel: VoxelHandle(slot),
            };
            n += 1;
        }
        out.len = n;
        n
    }

    /// Searches the `i`-th box of the query's order: finds its voxel (recorded in `found`) and
    /// adds its representatives to the candidates.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn visit(
        &self,
        pre: &mut Prepared,
        i: usize,
        q: [f32; 3],
        one_per_voxel: bool,
        cand: &mut Candidates,
        found: &mut [u32; 27],
        k: usize,
        bound2: f32,
    ) {
        let slot = self.probe(pre, i);
        if slot == NO_HINT {
            return;
        }
        let off = pre.offset(i);
        let nk = [pre.key[0] + off[0], pre.key[1] + off[1], pre.key[2] + off[2]];
        let slot = if self.pool[slot as usize].key == nk {
            slot
        } else {
            // Another key with the same 32-bit hash came first: look it up properly.
            match self.find_slot(nk) {
                Some(s2) => s2,
                None => return,
            }
        };
        found[i] = slot;
        self.scan_voxel(slot, nk, q, one_per_voxel, cand, (i as u32) << 3, k, bound2);
    }

    /// Adds the representatives of the voxel at `slot` (key `nk`) to the candidates, tagged
    /// `tag | octant`.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn scan_voxel(
        &self,
        slot: u32,
        nk: [i32; 3],
        q: [f32; 3],
        one_per_voxel: bool,
        cand: &mut Candidates,
        tag: u32,
        k: usize,
        bound2: f32,
    ) {
        let v = &self.pool[slot as usize];
        let c = self.centre(nk);
        let d2s = rep_d2(v, [q[0] - c[0], q[1] - c[1], q[2] - c[2]], self.d.dequant);
        let mut bits = v.occupied;
        if one_per_voxel {
            let mut best = (f32::INFINITY, 0u32);
            while bits != 0 {
                let o = bits.trailing_zeros();
                bits &= bits - 1;
                if d2s[o as usize] < best.0 {
                    best = (d2s[o as usize], o);
                }
            }
            // Written so that NaN is refused.
            if (best.0 <= bound2) & (best.0 < cand.dist(k - 1)) {
                cand.push(best.0, tag | best.1);
            }
            return;
        }
        // Only representatives within the bound and nearer than the k-th candidate go on (one
        // vector compare); some of them may fall beyond the k-th as the list shrinks, which the
        // insertion handles (they land after the first k entries).
        let kth = cand.dist(k - 1);
        let mut pass = 0u8;
        for o in 0..OCTANTS {
            pass |= u8::from((d2s[o] < kth) & (d2s[o] <= bound2)) << o;
        }
        bits &= pass;
        while bits != 0 {
            let o = bits.trailing_zeros();
            bits &= bits - 1;
            cand.push(d2s[o as usize], tag | o);
        }
    }
}

/// Queries prepared together by [`VoxelMap::knn_many`].
const KNN_GROUP: usize = 8;

/// Slot not probed yet.
const UNPROBED: u32 = u32::MAX - 1;

/// A k-NN query's voxel, box distances, block hashes and probed index slots.
#[derive(Clone, Copy, Debug)]
pub(super) struct Prepared {
    pub(super) key: [i32; 3],
    /// The lowest of the two blocks the neighbourhood spans per axis.
    b0: [i32; 3],
    /// Squared distance from the query to each neighbouring box, in the search order
    /// ([`SEARCH_ORDER`]).
    bd: [f32; 27],
    /// The query's side of its voxel centre per axis (-1 or +1).
    side: [i32; 3],
    /// Hashes of the 8 blocks, index `dx | dy << 1 | dz << 2` for block `b0 + (dx, dy, dz)`.
    bh: [u32; 8],
    /// Per box of the search order: `UNPROBED`, `NO_HINT` (absent) or the slot of the first
    /// index entry with the box's hash.
    slots: [u32; 27],
}

impl Prepared {
    /// The offset of the `i`-th box of the search order.
    #[inline]
    fn offset(&self, i: usize) -> [i32; 3] {
        let o = SEARCH_ORDER[i];
        [o[0] * self.side[0], o[1] * self.side[1], o[2] * self.side[2]]
    }

    /// `hash_key(key + off)`, from the block hashes.
    #[inline]
    pub(super) fn hash(&self, off: [i32; 3]) -> u32 {
        let nk = [self.key[0] + off[0], self.key[1] + off[1], self.key[2] + off[2]];
        let b = [(nk[0] >> 1) - self.b0[0], (nk[1] >> 1) - self.b0[1], (nk[2] >> 1) - self.b0[2]];
        self.bh[(b[0] | b[1] << 1 | b[2] << 2) as usize] << 3 | sub_block(nk)
    }
}

/// The k-NN candidates, kept sorted without branches (so that a query's candidates cost no
/// mispredicted jumps): each is a key `distance bits << 32 | box << 3 | octant` (non-negative
/// floats order as their bits; `box` is the position in the search order, so the low bits also
/// put the earlier found of equal distances first). Unused entries are `EMPTY_KEY` (+inf).
#[derive(Clone, Copy, Debug)]
struct Candidates {
    keys: [u64; KNN_MAX],
}

/// An unused candidate entry: distance +inf, after every real candidate.
const EMPTY_KEY: u64 = (0x7f80_0000u64 << 32) | 0xffff_ffff;

impl Candidates {
    const EMPTY: Self = Self { keys: [EMPTY_KEY; KNN_MAX] };

    /// Distance of entry `i` (+inf if unused).
    #[inline(always)]
    fn dist(&self, i: usize) -> f32 {
        f32::from_bits((self.keys[i] >> 32) as u32)
    }

    /// The search-order box and the octant of entry `i`.
    #[inline(always)]
    fn box_octant(&self, i: usize) -> (usize, usize) {
        let t = self.keys[i] as usize;
        ((t >> 3) & 31, t & 7)
    }

    /// Inserts a candidate (`tag`: box << 3 | octant); it lands after every entry not farther.
    /// The caller has checked it against the bound.
    #[inline(always)]
    fn push(&mut self, d: f32, tag: u32) {
        let key = (u64::from(d.to_bits()) << 32) | u64::from(tag);
        // Sorted insertion as min/max over whole arrays (vector code): entry i becomes
        // min(old i, max(old i - 1, key)).
        let old = self.keys;
        let mut prev = [0u64; KNN_MAX];
        prev[1..].copy_from_slice(&old[..KNN_MAX - 1]);
        for i in 0..KNN_MAX {
            self.keys[i] = old[i].min(prev[i].max(key));
        }
    }
}
