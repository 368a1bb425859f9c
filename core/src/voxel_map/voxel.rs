//! One voxel of the pool: its 192-byte layout, the caller's storage and the octant
//! representatives (quantised offsets and normals); the layout every other part's speed rests on.

use super::{Derived, IndexSlot, MapConfig, MapError, OCTANTS, VoxelHandle, VoxelMap, d2f};

/// Quantisation of representative offsets: `q = offset * QUANT / voxel_size`.
pub(super) const QUANT: f32 = 32768.0;

pub(super) const STATE_FREE: u8 = 0;
pub(super) const STATE_ACCUMULATING: u8 = 1;
pub(super) const STATE_CONVERGED: u8 = 2;
pub(super) const STATE_SATURATED: u8 = 3;

/// One voxel of the pool: 192 bytes, aligned to a 64-byte cache line, no implicit padding;
/// [`Voxel::EMPTY`] is all zeros.
///
/// The first cache line holds everything a lookup and a k-NN query read (key, state, count,
/// occupancy and the representative points), so a query touches one line per voxel.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(C, align(64))]
pub struct Voxel {
    // Line 0 (64 bytes): lookups and k-NN.
    pub(super) key: [i32; 3],
    pub(super) state: u8,
    pub(super) occupied: u8,
    pub(super) count: u16,
    /// Representative offsets, axis-major (`reps[axis][octant]`) so the 8 distances of a
    /// voxel compute as vectors.
    pub(super) reps: [[i16; OCTANTS]; 3],
    // Line 1 (64 bytes): what every insertion into an accumulating voxel writes.
    pub(super) last_seen: u32,
    pub(super) normal_count: u16,
    /// Points until the next evaluation (counts down from `eta`).
    pub(super) until_eval: u16,
    pub(super) sum: [f32; 3],
    pub(super) sum_sq: [f32; 6],
    pub(super) ring_sum: [f32; 3],
    pub(super) _spare1: [u32; 2],
    // Line 2 (64 bytes): written when a representative changes or the voxel is evaluated.
    pub(super) rep_normals: [[i8; 3]; OCTANTS],
    /// `e_d` of the latest evaluation, oriented with the ring normal (or towards the sensor).
    pub(super) normal: [f32; 3],
    /// Ascending covariance eigenvalues of the latest evaluation.
    pub(super) eigenvalues: [f32; 3],
    pub(super) _spare2: [u32; 4],
}

impl Voxel {
    /// An unused slot (all-zero bytes).
    pub const EMPTY: Voxel = Voxel {
        key: [0; 3],
        state: STATE_FREE,
        occupied: 0,
        count: 0,
        reps: [[0; OCTANTS]; 3],
        last_seen: 0,
        normal_count: 0,
        until_eval: 0,
        sum: [0.0; 3],
        sum_sq: [0.0; 6],
        ring_sum: [0.0; 3],
        _spare1: [0; 2],
        rep_normals: [[0; 3]; OCTANTS],
        normal: [0.0; 3],
        eigenvalues: [0.0; 3],
        _spare2: [0; 4],
    };
}

impl Default for Voxel {
    fn default() -> Self {
        Self::EMPTY
    }
}

/// Caller-owned storage for a map of `V` voxels with an index of `I` slots (a power of two,
/// `I >= 2 V`); `const fn new()` so it can be a `static` (all zeros: `.bss`).
#[derive(Debug)]
pub struct MapStorage<const V: usize, const I: usize> {
    /// The voxel pool.
    pub pool: [Voxel; V],
    /// The hash index.
    pub index: [IndexSlot; I],
}

impl<const V: usize, const I: usize> MapStorage<V, I> {
    /// Empty storage.
    pub const fn new() -> Self {
        Self { pool: [Voxel::EMPTY; V], index: [IndexSlot::EMPTY; I] }
    }

    /// A map over this storage (see [`VoxelMap::new`]).
    pub fn map(&mut self, config: MapConfig) -> Result<VoxelMap<'_>, MapError> {
        VoxelMap::new(&mut self.pool, &mut self.index, config)
    }
}

impl<const V: usize, const I: usize> Default for MapStorage<V, I> {
    fn default() -> Self {
        Self::new()
    }
}

impl VoxelMap<'_> {
    /// Calls `f(voxel, point, normal)` for every representative point of the map.
    pub fn for_each_point(&self, mut f: impl FnMut(VoxelHandle, [f32; 3], Option<[f32; 3]>)) {
        for (i, v) in self.pool[..self.len].iter().enumerate() {
            let c = self.centre(v.key);
            for o in 0..OCTANTS {
                if v.occupied & (1 << o) != 0 {
                    f(VoxelHandle(i as u32), self.rep_point(c, rep(v, o)), rep_normal(v.rep_normals[o]));
                }
            }
        }
    }

    #[inline]
    pub(super) fn rep_point(&self, c: [f32; 3], q: [i16; 3]) -> [f32; 3] {
        let s = self.d.dequant;
        [c[0] + f32::from(q[0]) * s, c[1] + f32::from(q[1]) * s, c[2] + f32::from(q[2]) * s]
    }
}

/// A representative's quantised offset.
#[inline]
pub(super) fn rep(v: &Voxel, o: usize) -> [i16; 3] {
    [v.reps[0][o], v.reps[1][o], v.reps[2][o]]
}

/// Squared distances from `rq` (relative to the voxel centre) to the voxel's 8 representative
/// slots (unoccupied ones too), as one vector computation. Out of line on purpose: inlined into
/// the k-NN, an AVX-512 build split the loop into masked loads, one of which reached into the
/// voxel's second cache line (a miss per voxel searched).
#[inline(never)]
pub(super) fn rep_d2(v: &Voxel, rq: [f32; 3], s: f32) -> [f32; OCTANTS] {
    let mut d2s = [0.0f32; OCTANTS];
    for o in 0..OCTANTS {
        let dx = rq[0] - f32::from(v.reps[0][o]) * s;
        let dy = rq[1] - f32::from(v.reps[1][o]) * s;
        let dz = rq[2] - f32::from(v.reps[2][o]) * s;
        d2s[o] = dx * dx + dy * dy + dz * dz;
    }
    d2s
}

/// A quantised normal as a unit vector; `None` for the "no normal" marker `[0, 0, 0]`.
#[inline]
pub(super) fn rep_normal(q: [i8; 3]) -> Option<[f32; 3]> {
    if q == [0, 0, 0] {
        return None;
    }
    let n = [f32::from(q[0]), f32::from(q[1]), f32::from(q[2])];
    let inv = 1.0 / crate::math::sqrtf(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    Some([n[0] * inv, n[1] * inv, n[2] * inv])
}

/// The octant rule for representatives (module docs).
#[inline]
pub(super) fn update_rep(v: &mut Voxel, off: [f32; 3], normal: Option<[f32; 3]>, d: &Derived) {
    let o = usize::from(off[0] >= 0.0) | usize::from(off[1] >= 0.0) << 1 | usize::from(off[2] >= 0.0) << 2;
    let quarter = 0.5 * d.half;
    let oc = [
        if off[0] >= 0.0 { quarter } else { -quarter },
        if off[1] >= 0.0 { quarter } else { -quarter },
        if off[2] >= 0.0 { quarter } else { -quarter },
    ];
    let bit = 1u8 << o;
    if v.occupied & bit != 0 {
        let r = rep(v, o);
        let old = [f32::from(r[0]) * d.dequant, f32::from(r[1]) * d.dequant, f32::from(r[2]) * d.dequant];
        if !(d2f(off, oc) < d2f(old, oc)) {
            return;
        }
    }
    let q = [quantise(off[0], d.quant), quantise(off[1], d.quant), quantise(off[2], d.quant)];
    v.occupied |= bit;
    for a in 0..3 {
        v.reps[a][o] = q[a];
    }
    v.rep_normals[o] = match normal {
        Some(n) => [quantise_unit(n[0]), quantise_unit(n[1]), quantise_unit(n[2])],
        None => [0, 0, 0],
    };
}

/// Rounds half away from zero (up to one unit in the last place at exact halves; either
/// neighbour is an equally good quantisation) and saturates to `±limit`.
#[inline]
pub(super) fn round_sat(x: f32, limit: f32) -> i32 {
    let x = x.clamp(-limit, limit);
    if x >= 0.0 { (x + 0.5) as i32 } else { (x - 0.5) as i32 }
}

#[inline]
fn quantise(x: f32, scale: f32) -> i16 {
    round_sat(x * scale, 32767.0) as i16
}

#[inline]
fn quantise_unit(x: f32) -> i8 {
    round_sat(x * 127.0, 127.0) as i8
}
