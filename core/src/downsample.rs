//! Voxel downsampling of a scan that keeps averaged normals (paper section IV-A).
//!
//! Points are binned into cubic voxels of side `voxel` (keys `floor(p / voxel)`) in a
//! fixed-capacity open-addressing hash grid ([`VoxelDownsampler`], caller-owned,
//! `const`-constructible; once a scan is binned it is emptied by clearing only the slots used).
//! Each voxel outputs one point: **the input point nearest to the voxel's centroid**, not the
//! centroid itself. A real point keeps a coherent time (which undistortion needs), pixel and
//! intensity, and it lies on the measured surface, where a centroid of points on a corner or a
//! curved surface would not. Ties go to the earliest point.
//!
//! The voxel's normal is the mean of its points' valid normals ([`normal_is_valid`]: finite and
//! roughly unit length; invalid ones do not contribute), renormalised. If the mean's length (the
//! mean resultant length, 1 when all agree) is below `min_normal_agreement`, the normals disagree
//! (an edge, or noise) and the voxel gets [`INVALID_NORMAL`]. Normals are assumed consistently
//! oriented (towards the sensor, as the visibility check needs), so opposite normals cancel and
//! count as disagreement.
//!
//! The output is written in place: the first `kept` entries of the slices, **in the Morton
//! (Z-order) of the voxel keys** (10 bits per axis, keys offset by 512 so that the order wraps
//! only 512 voxels from the origin; deterministic). Nearby output points are thus close
//! together in memory order, which is what the association and the map insertion want: their
//! map lookups for consecutive points then hit the voxels and index lines the previous ones
//! brought into the caches (in the scan's column order they jump across the scene; in Morton
//! order the association of a VLP-32C vehicle scan takes 11 % less time, the map insertion 8 %,
//! medians of five alternated `loglio bench` runs).
//! The points are first compacted in the order the voxels were first seen (safe in place: a
//! voxel's chosen point never comes before the voxel's position in that order), then permuted
//! in place by a radix sort of the keys' Morton codes.

// Parallel xyz arrays read clearest as indexed loops.
#![allow(clippy::needless_range_loop)]

use crate::parallel::Parallel;
use crate::scan::ScanPoint;

/// The normal written where there is none.
pub const INVALID_NORMAL: [f32; 3] = [0.0; 3];

/// Whether `n` is a usable normal: finite, with a length between 0.5 and 1.5.
#[inline]
pub fn normal_is_valid(n: &[f32; 3]) -> bool {
    let l2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2];
    l2.is_finite() && l2 > 0.25 && l2 < 2.25
}

/// Settings of the downsampling.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DownsampleConfig {
    /// Voxel side, m.
    pub voxel: f32,
    /// Smallest mean resultant length of a voxel's normals that still gives it a normal
    /// (0.9 lets the normals spread by about 25 deg on average).
    pub min_normal_agreement: f32,
}

impl Default for DownsampleConfig {
    fn default() -> Self {
        Self { voxel: 0.4, min_normal_agreement: 0.9 }
    }
}

/// Why downsampling could not run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DownsampleError {
    /// The capacity `N` is not a power of two.
    Capacity,
    /// The voxel size is not a positive finite number.
    VoxelSize,
    /// The normals slice is not as long as the points slice.
    LengthMismatch,
}

impl core::fmt::Display for DownsampleError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::Capacity => "downsampler capacity must be a power of two",
            Self::VoxelSize => "voxel size must be positive and finite",
            Self::LengthMismatch => "normals and points differ in length",
        })
    }
}

impl core::error::Error for DownsampleError {}

/// Counters of one downsampling.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DownsampleStats {
    /// Points written (one per voxel).
    pub kept: u32,
    /// Input points dropped: non-finite, or too far for an `i32` voxel key.
    pub dropped_invalid: u32,
    /// Input points dropped because their voxel did not fit (more than `3N/4` voxels).
    pub dropped_overflow: u32,
    /// Output voxels without a valid normal (no valid input normal, or disagreement).
    pub normals_invalid: u32,
    /// ... of which because the normals disagreed.
    pub normals_disagree: u32,
}

/// The accumulators of one voxel, kept dense in first-seen order (the index points here), so
/// that a scan's voxels occupy a few hundred kilobytes instead of being spread over the table.
#[derive(Clone, Copy, Debug)]
struct Cell {
    key: [i32; 3],
    count: u32,
    /// Sum of positions relative to the voxel's corner (small numbers: f32 is enough); after
    /// the first pass their mean, the centroid.
    sum: [f32; 3],
    nsum: [f32; 3],
    ncount: u32,
    best: u32,
    best_d2: f32,
    /// The cell's position in the index, to clear it after the scan.
    pos: u32,
}

impl Cell {
    /// Adds `n` to the voxel's normal sum if it is a usable normal.
    #[inline(always)]
    fn add_normal(&mut self, n: &[f32; 3]) {
        if normal_is_valid(n) {
            self.ncount += 1;
            for a in 0..3 {
                self.nsum[a] += n[a];
            }
        }
    }

    const EMPTY: Cell = Cell {
        key: [0; 3],
        count: 0,
        sum: [0.0; 3],
        nsum: [0.0; 3],
        ncount: 0,
        best: 0,
        best_d2: 0.0,
        pos: 0,
    };
}

/// A voxel's unit mean normal as the output takes it (`agreement`:
/// [`DownsampleConfig::min_normal_agreement`]), or [`INVALID_NORMAL`] counted in `stats`.
#[inline(always)]
fn mean_normal(c: &Cell, agreement: f32, stats: &mut DownsampleStats) -> [f32; 3] {
    if c.ncount == 0 {
        stats.normals_invalid += 1;
        return INVALID_NORMAL;
    }
    let m = c.nsum.map(|v| v / c.ncount as f32);
    let len = crate::math::sqrtf(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]);
    let agree = len >= agreement && len > 0.0; // false for NaN
    if !agree {
        stats.normals_invalid += 1;
        stats.normals_disagree += 1;
        INVALID_NORMAL
    } else {
        m.map(|v| v / len)
    }
}

/// A point in no voxel (dropped), in the scratch of [`VoxelDownsampler::downsample_with_scratch`].
const NO_CELL: u32 = u32::MAX;

/// Rows of the per-row lookup cache (a point's row modulo this).
const RECENT: usize = 128;

/// The hash grid: `N` index slots (a power of two), at most `3N/4` voxels per scan. 68 bytes
/// per slot.
///
/// The index (4 bytes per slot: the dense cell + 1, 0 when empty) is cleared after every scan
/// by visiting only the slots the scan used. A point usually falls in the voxel of the previous
/// point of its beam (consecutive columns are centimetres apart), so a per-row cache of the
/// last voxel found skips most hash lookups; it is only a hint, checked by key.
#[derive(Debug)]
pub struct VoxelDownsampler<const N: usize> {
    index: [u32; N],
    cells: [Cell; N],
    recent: [([i32; 3], u32); RECENT],
    /// The output order (the radix sort's buffer; the index is its other one).
    perm: [u32; N],
    /// The cells' Morton codes, read in the radix sort's random order (dense: the cells
    /// themselves are 56 bytes apart).
    codes: [u32; N],
    /// Between the stages ([`Self::bin_with_scratch`], [`Self::finish`]): the cells in use
    /// and the counters so far.
    used: usize,
    staged: DownsampleStats,
}

impl<const N: usize> Default for VoxelDownsampler<N> {
    fn default() -> Self {
        Self::new()
    }
}

/// Points whose keys [`keys8`] finds at once.
const KEY_LANES: usize = 8;

/// Largest `|coordinate / voxel|` with a key: within i32 (2^31 voxels of 0.1 m is 2e8 m,
/// beyond any scan).
const KEY_BOUND: f32 = 2.0e9;

/// The voxel keys of up to eight points (`VoxelDownsampler::key`'s, bit for bit) and which of
/// them have one: the products, bounds and truncations on vector lanes where one point at a
/// time took three conversions and three branches.
#[inline(always)]
fn keys8(points: &[ScanPoint], inv: f32) -> ([[i32; KEY_LANES]; 3], [bool; KEY_LANES]) {
    let mut v = [[0.0f32; KEY_LANES]; 3];
    for (l, p) in points.iter().take(KEY_LANES).enumerate() {
        for a in 0..3 {
            v[a][l] = p.xyz[a] * inv;
        }
    }
    let mut ok = [true; KEY_LANES];
    let mut k = [[0i32; KEY_LANES]; 3];
    for a in 0..3 {
        // `key`'s test (false for NaN and the infinities); lanes that fail it are not used.
        for l in 0..KEY_LANES {
            ok[l] &= v[a][l].abs() < KEY_BOUND;
        }
        k[a] = crate::math::floor_i32x8(v[a]);
    }
    (k, ok)
}

/// The index slot of a voxel key: the hash of its 2x2x2 block times 8 plus its place in the
/// block, so that neighbouring voxels (the next beam of a column, the next column of a beam)
/// have their index entries in one cache line.
#[inline]
fn hash(k: &[i32; 3]) -> u32 {
    let b = [(k[0] >> 1) as u32, (k[1] >> 1) as u32, (k[2] >> 1) as u32];
    let mut h =
        b[0].wrapping_mul(0x9E37_79B1) ^ b[1].wrapping_mul(0x85EB_CA77) ^ b[2].wrapping_mul(0xC2B2_AE3D);
    h ^= h >> 15;
    h = h.wrapping_mul(0x2C1B_3C6D);
    h ^= h >> 12;
    h << 3 | ((k[0] & 1) | (k[1] & 1) << 1 | (k[2] & 1) << 2) as u32
}

impl<const N: usize> VoxelDownsampler<N> {
    /// An empty grid (all zero bytes, so that a `static` lives in .bss).
    pub const fn new() -> Self {
        Self {
            index: [0; N],
            cells: [Cell::EMPTY; N],
            recent: [([0; 3], 0); RECENT],
            perm: [0; N],
            codes: [0; N],
            used: 0,
            staged: DownsampleStats {
                kept: 0,
                dropped_invalid: 0,
                dropped_overflow: 0,
                normals_invalid: 0,
                normals_disagree: 0,
            },
        }
    }

    /// Most voxels one scan may produce.
    pub const fn max_voxels() -> usize {
        N - N / 4
    }

    #[inline]
    fn key(p: &[f32; 3], inv: f32) -> Option<[i32; 3]> {
        let mut k = [0i32; 3];
        for a in 0..3 {
            let v = p[a] * inv;
            // Finite and within [`KEY_BOUND`].
            if !v.is_finite() || v.abs() >= KEY_BOUND {
                return None;
            }
            k[a] = crate::math::floor_i32(v);
        }
        Some(k)
    }

    /// The dense cell of `key`: `Ok(cell)` if present, `Err(pos)` with the empty index slot to
    /// insert at. The per-row cache `row` is consulted first and updated.
    #[inline]
    fn find(&mut self, key: &[i32; 3], row: u16) -> Result<usize, usize> {
        let r = usize::from(row) % RECENT;
        let (k, c) = self.recent[r];
        if c != 0 && k == *key {
            return Ok(c as usize - 1);
        }
        let mask = N - 1;
        let mut i = hash(key) as usize & mask;
        loop {
            let e = self.index[i];
            if e == 0 {
                return Err(i);
            }
            let c = e as usize - 1;
            if self.cells[c].key == *key {
                self.recent[r] = (*key, e);
                return Ok(c);
            }
            i = (i + 1) & mask;
        }
    }

    /// Downsamples in place (module docs): on return the first `kept` points (and normals) are
    /// the output.
    pub fn downsample(
        &mut self,
        cfg: &DownsampleConfig,
        points: &mut [ScanPoint],
        normals: Option<&mut [[f32; 3]]>,
    ) -> Result<DownsampleStats, DownsampleError> {
        self.run(cfg, points, normals, None)
    }

    /// [`Self::downsample`] with a caller's scratch of at least `points.len()` entries
    /// (else [`DownsampleError::LengthMismatch`]): the first pass notes each point's voxel
    /// there, so the second (the point nearest to each centroid) neither recomputes keys nor
    /// searches the grid again. The output is the same, bit for bit.
    pub fn downsample_with_scratch(
        &mut self,
        cfg: &DownsampleConfig,
        points: &mut [ScanPoint],
        normals: Option<&mut [[f32; 3]]>,
        scratch: &mut [u32],
    ) -> Result<DownsampleStats, DownsampleError> {
        if scratch.len() < points.len() {
            return Err(DownsampleError::LengthMismatch);
        }
        self.run(cfg, points, normals, Some(&mut scratch[..points.len()]))
    }

    /// [`Self::downsample_with_scratch`] in three stages, so that the voxels can be found
    /// while the normals are still being estimated (on another thread): this one bins the
    /// points and picks each voxel's point, noting each point's voxel in `scratch` (at least
    /// `points.len()` entries); [`Self::add_normals`] then sums the normals, and
    /// [`Self::finish`] writes the output. The same output, bit for bit, as one call.
    pub fn bin_with_scratch(
        &mut self,
        cfg: &DownsampleConfig,
        points: &[ScanPoint],
        scratch: &mut [u32],
    ) -> Result<(), DownsampleError> {
        if scratch.len() < points.len() {
            return Err(DownsampleError::LengthMismatch);
        }
        self.bin(cfg, points, None, Some(&mut scratch[..points.len()]))
    }

    /// Adds each point's valid normal to its voxel, in the points' order (the sums of one
    /// call). `normals` and `scratch` are those of the points given to
    /// [`Self::bin_with_scratch`].
    pub fn add_normals(&mut self, normals: &[[f32; 3]], scratch: &[u32]) {
        let used = self.used;
        for (n, &cell) in normals.iter().zip(scratch.iter()) {
            if let Some(c) = self.cells[..used].get_mut(cell as usize) {
                c.add_normal(n);
            }
        }
    }

    /// [`Self::add_normals`] on `parallel`'s threads: each takes a range of the voxels and
    /// reads every point, adding only its voxels' normals, so each voxel's sum is still taken
    /// in the points' order (the same bits as one thread).
    pub fn add_normals_with(&mut self, normals: &[[f32; 3]], scratch: &[u32], parallel: &dyn Parallel) {
        let used = self.used;
        let width = parallel.width();
        if width <= 1 || used < 2 * 64 {
            return self.add_normals(normals, scratch);
        }
        // One run per piece: the runs are as long as the pieces' alignment.
        let run = used.div_ceil(width).next_multiple_of(64);
        crate::parallel::map_chunks(parallel, &mut self.cells[..used], run, |first, cells| {
            for (n, &cell) in normals.iter().zip(scratch.iter()) {
                // Points of no voxel (`NO_CELL`) and of other pieces' voxels fall outside.
                if let Some(c) = cells.get_mut((cell as usize).wrapping_sub(first)) {
                    c.add_normal(n);
                }
            }
        });
    }

    fn run(
        &mut self,
        cfg: &DownsampleConfig,
        points: &mut [ScanPoint],
        normals: Option<&mut [[f32; 3]]>,
        cell_of: Option<&mut [u32]>,
    ) -> Result<DownsampleStats, DownsampleError> {
        self.bin(cfg, points, normals.as_deref(), cell_of)?;
        Ok(self.finish(cfg, points, normals))
    }

    /// Passes 1 and 2: the voxels, their sums (normals too where given) and nearest points.
    fn bin(
        &mut self,
        cfg: &DownsampleConfig,
        points: &[ScanPoint],
        normals: Option<&[[f32; 3]]>,
        mut cell_of: Option<&mut [u32]>,
    ) -> Result<(), DownsampleError> {
        self.used = 0;
        if !N.is_power_of_two() || N < 4 {
            return Err(DownsampleError::Capacity);
        }
        let positive = cfg.voxel > 0.0; // false for NaN
        if !positive || !cfg.voxel.is_finite() {
            return Err(DownsampleError::VoxelSize);
        }
        if normals.as_ref().is_some_and(|n| n.len() != points.len()) {
            return Err(DownsampleError::LengthMismatch);
        }
        let inv = 1.0 / cfg.voxel;
        let mut stats = DownsampleStats::default();
        let mut used = 0usize;
        let max = Self::max_voxels();

        // The index is all but empty between scans and the map's work evicts it from the
        // caches: read in order, it comes back in a stream, where the scan's lookups would
        // fetch its lines one random miss at a time.
        crate::math::read_in(&self.index);

        // Pass 1: accumulate.
        self.recent = [([0; 3], 0); RECENT];
        // The keys of eight points at a time, on vector lanes ([`keys8`]).
        for (i0, block) in (0..).step_by(KEY_LANES).zip(points.chunks(KEY_LANES)) {
            let (keys, ok) = keys8(block, inv);
            for (l, p) in block.iter().enumerate() {
                let i = i0 + l;
                if let Some(co) = cell_of.as_deref_mut() {
                    co[i] = NO_CELL;
                }
                if !ok[l] {
                    stats.dropped_invalid += 1;
                    continue;
                }
                let key = [keys[0][l], keys[1][l], keys[2][l]];
                let cell = match self.find(&key, p.row) {
                    Ok(c) => c,
                    Err(pos) => {
                        if used >= max {
                            stats.dropped_overflow += 1;
                            continue;
                        }
                        self.cells[used] =
                            Cell { key, best_d2: f32::INFINITY, pos: pos as u32, ..Cell::EMPTY };
                        self.index[pos] = used as u32 + 1;
                        self.recent[usize::from(p.row) % RECENT] = (key, used as u32 + 1);
                        used += 1;
                        used - 1
                    }
                };
                if let Some(co) = cell_of.as_deref_mut() {
                    co[i] = cell as u32;
                }
                let c = &mut self.cells[cell];
                c.count += 1;
                for a in 0..3 {
                    c.sum[a] += p.xyz[a] - key[a] as f32 * cfg.voxel;
                }
                if let Some(ns) = normals {
                    c.add_normal(&ns[i]);
                }
            }
        }

        // Pass 2: the point nearest to each centroid (each cell's sum becomes its centroid,
        // relative to the corner, once: not one division per point).
        for c in self.cells[..used].iter_mut() {
            for a in 0..3 {
                c.sum[a] /= c.count as f32;
            }
        }
        let nearest = |c: &mut Cell, p: &ScanPoint, i: usize| {
            let mut d2 = 0.0;
            for a in 0..3 {
                let centroid = c.sum[a];
                let d = (p.xyz[a] - c.key[a] as f32 * cfg.voxel) - centroid;
                d2 += d * d;
            }
            if d2 < c.best_d2 {
                c.best_d2 = d2;
                c.best = i as u32;
            }
        };
        if let Some(co) = cell_of.as_deref() {
            for (i, (p, &cell)) in points.iter().zip(co.iter()).enumerate() {
                if let Some(c) = self.cells[..used].get_mut(cell as usize) {
                    nearest(c, p, i);
                }
            }
        } else {
            self.recent = [([0; 3], 0); RECENT];
            for (i, p) in points.iter().enumerate() {
                let Some(key) = Self::key(&p.xyz, inv) else { continue };
                let Ok(cell) = self.find(&key, p.row) else { continue };
                nearest(&mut self.cells[cell], p, i);
            }
        }

        // The grid is emptied for the next scan and the output order found here, not in
        // [`Self::finish`]: neither needs the normals, so with the stages on two threads this
        // runs beside the normals' estimation.
        for k in 0..used {
            let c = &self.cells[k];
            self.index[c.pos as usize] = 0;
            self.codes[k] = morton30(c.key);
        }
        self.morton_sort(used);
        self.used = used;
        self.staged = stats;
        Ok(())
    }

    /// The last stage ([`Self::bin_with_scratch`]): writes the first `kept` points (and
    /// normals, with the sums [`Self::add_normals`] made) in the voxels' Morton order, which
    /// the binning found as it emptied the grid for the next scan. `points` are those binned.
    pub fn finish(
        &mut self,
        cfg: &DownsampleConfig,
        points: &mut [ScanPoint],
        mut normals: Option<&mut [[f32; 3]]>,
    ) -> DownsampleStats {
        let (used, mut stats) = (core::mem::take(&mut self.used), self.staged);
        if normals.as_ref().is_some_and(|n| n.len() < used) || points.len() < used {
            // Not the points binned: nothing is written (the grid is empty already).
            return DownsampleStats { kept: 0, ..stats };
        }
        // Output, compacted in first-seen order, then permuted into the Morton order the
        // binning found.
        for k in 0..used {
            let c = self.cells[k];
            points[k] = points[c.best as usize];
            if let Some(ns) = normals.as_deref_mut() {
                ns[k] = mean_normal(&c, cfg.min_normal_agreement, &mut stats);
            }
        }
        stats.kept = used as u32;
        self.morton_permute(used, points, normals);
        stats
    }

    /// [`Self::finish`] out of place and in pieces on `parallel`'s threads: `out` gets the
    /// first `kept` points in the same Morton order (each piece gathers its own range of it
    /// from `points`, the points binned, which stay as they are), `normals` the same normals
    /// as [`Self::finish`] writes. The same bits; a one-thread gather and permutation in place
    /// become a gather the threads share. `out` shorter than the voxels: nothing is written
    /// (as [`Self::finish`] with the wrong points).
    pub fn finish_into(
        &mut self,
        cfg: &DownsampleConfig,
        points: &[ScanPoint],
        out: &mut [ScanPoint],
        normals: Option<&mut [[f32; 3]]>,
        parallel: &dyn Parallel,
    ) -> DownsampleStats {
        let (used, mut stats) = (core::mem::take(&mut self.used), self.staged);
        if normals.as_ref().is_some_and(|n| n.len() < used) || out.len() < used || points.len() < used {
            return DownsampleStats { kept: 0, ..stats };
        }
        let agreement = cfg.min_normal_agreement;
        let (cells, perm) = (&self.cells, &self.perm);
        let mut counts = [DownsampleStats::default(); crate::parallel::MAX_WIDTH];
        let normals = normals.map(|n| &mut n[..used]);
        crate::parallel::map_pieces2(
            parallel,
            &mut out[..used],
            normals,
            64,
            &mut counts,
            |first, piece, ns, count| {
                let mut ns = ns;
                for (j, o) in piece.iter_mut().enumerate() {
                    let c = &cells[perm[first + j] as usize];
                    *o = points[c.best as usize];
                    if let Some(ns) = ns.as_deref_mut() {
                        ns[j] = mean_normal(c, agreement, count);
                    }
                }
            },
        );
        for c in &counts {
            stats.normals_invalid += c.normals_invalid;
            stats.normals_disagree += c.normals_disagree;
        }
        stats.kept = used as u32;
        stats
    }

    /// The output order (`perm`) of the first `used` cells: the Morton order of their keys
    /// (`codes[..used]`, noted by the binning), by an LSD radix sort of the 30-bit codes (three
    /// 10-bit digits, stable) between `perm` and the index (empty before and afterwards).
    #[inline(never)]
    fn morton_sort(&mut self, used: usize) {
        if used < 2 {
            return;
        }
        let codes = &self.codes[..used];
        // The three digits' histograms in one pass, then each turned into bucket starts.
        let mut hists = [[0u32; 1024]; 3];
        for &c in codes.iter() {
            for (pass, h) in hists.iter_mut().enumerate() {
                h[(c >> (10 * pass)) as usize & 1023] += 1;
            }
        }
        for h in hists.iter_mut() {
            let mut start = 0u32;
            for b in h.iter_mut() {
                let n = *b;
                *b = start;
                start += n;
            }
        }
        // Pass 0 reads the cells in their order; passes 1 and 2 go perm -> index -> perm.
        for (pass, hist) in hists.iter_mut().enumerate() {
            let shift = 10 * pass;
            let (src, dst): (Option<&[u32]>, &mut [u32]) = match pass {
                0 => (None, &mut self.perm[..used]),
                1 => (Some(&self.perm[..used]), &mut self.index[..used]),
                _ => (Some(&self.index[..used]), &mut self.perm[..used]),
            };
            for i in 0..used {
                let k = src.map_or(i as u32, |s| s[i]);
                let d = (codes[k as usize] >> shift) as usize & 1023;
                dst[hist[d] as usize] = k;
                hist[d] += 1;
            }
        }
        self.index[..used].fill(0);
    }

    /// Permutes the first `used` points (and normals), compacted in the cells' order, into the
    /// order [`Self::morton_sort`] left in `perm`, in place cycle by cycle.
    fn morton_permute(
        &mut self,
        used: usize,
        points: &mut [ScanPoint],
        mut normals: Option<&mut [[f32; 3]]>,
    ) {
        if used < 2 {
            return;
        }
        // Output position j takes the point at perm[j]; the top bit marks positions done.
        const DONE: u32 = 1 << 31;
        for s in 0..used {
            if self.perm[s] & DONE != 0 {
                continue;
            }
            let (tp, tn) = (points[s], normals.as_deref().map(|n| n[s]));
            let mut cur = s;
            loop {
                let next = (self.perm[cur] & !DONE) as usize;
                self.perm[cur] |= DONE;
                if next == s {
                    points[cur] = tp;
                    if let (Some(ns), Some(t)) = (normals.as_deref_mut(), tn) {
                        ns[cur] = t;
                    }
                    break;
                }
                points[cur] = points[next];
                if let Some(ns) = normals.as_deref_mut() {
                    ns[cur] = ns[next];
                }
                cur = next;
            }
        }
    }
}

/// The 30-bit Morton code of a voxel key (10 bits per axis of `key + 512`, interleaved x, y,
/// z from the lowest bit).
#[inline(always)]
fn morton30(key: [i32; 3]) -> u32 {
    let spread = |v: i32| {
        let mut x = (v.wrapping_add(512) as u32) & 1023;
        x = (x | x << 16) & 0x0300_00ff;
        x = (x | x << 8) & 0x0300_f00f;
        x = (x | x << 4) & 0x030c_30c3;
        (x | x << 2) & 0x0924_9249
    };
    spread(key[0]) | spread(key[1]) << 1 | spread(key[2]) << 2
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec::Vec;

    use super::*;
    use crate::testutil::{Rng, Threads};

    fn pt(x: f32, y: f32, z: f32, t: f32) -> ScanPoint {
        ScanPoint { xyz: [x, y, z], t, ..Default::default() }
    }

    fn cfg(voxel: f32) -> DownsampleConfig {
        DownsampleConfig { voxel, ..Default::default() }
    }

    #[test]
    fn eight_keys_at_once_are_the_keys_of_one_point_at_a_time() {
        let edge = [
            0.0,
            -0.0,
            0.25,
            -0.25,
            1.0,
            -1.0,
            2.5,
            -2.5,
            0.099_999,
            -0.100_001,
            1.0e-30,
            -1.0e-30,
            1.999_999_9e9,
            -1.999_999_9e9,
            2.0e9,
            -2.0e9,
            3.0e9,
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            16_777_217.0,
            -16_777_217.0,
            8_388_607.5,
            -8_388_607.5,
        ];
        let mut rng = crate::testutil::SplitMix(3);
        let mut points: Vec<ScanPoint> = Vec::new();
        for (i, &e) in edge.iter().enumerate() {
            let o = edge[(i * 7 + 3) % edge.len()];
            points.push(pt(e, o, rng.uniform(-50.0, 50.0) as f32, 0.0));
            points.push(pt(rng.uniform(-50.0, 50.0) as f32, e, o, 0.0));
        }
        for _ in 0..200 {
            let v = |r: &mut crate::testutil::SplitMix| r.uniform(-300.0, 300.0) as f32;
            points.push(pt(v(&mut rng), v(&mut rng), v(&mut rng), 0.0));
        }
        for inv in [1.0 / 0.5, 1.0 / 0.1, 1.0, 3.0e-9] {
            // Blocks of every length, as a scan's last block is.
            for len in 1..=KEY_LANES {
                for block in points.chunks(len) {
                    let (keys, ok) = keys8(block, inv);
                    for (l, p) in block.iter().enumerate() {
                        let one = VoxelDownsampler::<64>::key(&p.xyz, inv);
                        assert_eq!(ok[l], one.is_some(), "{:?} at {inv}", p.xyz);
                        if let Some(k) = one {
                            assert_eq!([keys[0][l], keys[1][l], keys[2][l]], k, "{:?} at {inv}", p.xyz);
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn counts_order_and_nearest_to_centroid() {
        let mut rng = Rng::new(5);
        // Random points in [-1, 1)^3; voxel 0.5: up to 64 voxels.
        let mut pts: Vec<ScanPoint> = (0..3000)
            .map(|i| {
                let u = |r: &mut Rng| (r.uniform() * 2.0 - 1.0) as f32;
                pt(u(&mut rng), u(&mut rng), u(&mut rng), i as f32 * 1e-5)
            })
            .collect();
        let orig = pts.clone();
        let mut ds = std::boxed::Box::new(VoxelDownsampler::<256>::new());
        let st = ds.downsample(&cfg(0.5), &mut pts, None).unwrap();
        assert_eq!(st.kept, 64);
        assert_eq!(st.dropped_invalid + st.dropped_overflow, 0);
        // Brute force: per voxel (in the Morton order of the keys) the point nearest to the
        // centroid.
        let key = |p: &ScanPoint| p.xyz.map(|v| (v / 0.5).floor() as i32);
        let mut keys: Vec<[i32; 3]> = Vec::new();
        for p in &orig {
            if !keys.contains(&key(p)) {
                keys.push(key(p));
            }
        }
        keys.sort_by_key(|k| morton_reference(*k));
        for (k, kk) in keys.iter().enumerate() {
            let members: Vec<&ScanPoint> = orig.iter().filter(|p| key(p) == *kk).collect();
            let mut c = [0.0f64; 3];
            for m in &members {
                for a in 0..3 {
                    c[a] += m.xyz[a] as f64 / members.len() as f64;
                }
            }
            let d = |p: &ScanPoint| (0..3).map(|a| (p.xyz[a] as f64 - c[a]).powi(2)).sum::<f64>();
            let best = members.iter().min_by(|a, b| d(a).partial_cmp(&d(b)).unwrap()).unwrap();
            // f32 sums may pick a different point only when two are equally near (within 1e-9 m²).
            assert!(d(&pts[k]) - d(best) < 1e-9, "voxel {k}");
            assert_eq!(key(&pts[k]), *kk);
            // The point is an input point, with its own time.
            assert!(orig.iter().any(|o| o == &pts[k]));
        }
    }

    /// The Morton code bit by bit: bit b of axis a (of `key + 512`, 10 bits) at bit 3b + a.
    fn morton_reference(k: [i32; 3]) -> u64 {
        let mut c = 0u64;
        for b in 0..10 {
            for a in 0..3 {
                c |= ((((k[a] + 512) as u64) >> b) & 1) << (3 * b + a);
            }
        }
        c
    }

    #[test]
    fn output_is_in_morton_order_with_normals_alongside() {
        let mut rng = Rng::new(11);
        // Keys from -600 to 600 per axis (past the 10-bit wrap at -512 and 512), two points per
        // voxel, each with a normal that identifies it.
        let mut pts = Vec::new();
        let mut ns = Vec::new();
        for i in 0..2000 {
            let k = [0, 1, 2].map(|_| (rng.uniform() * 1200.0 - 600.0).floor() as f32);
            for j in 0..2 {
                let off = 0.25 + 0.5 * j as f32;
                pts.push(pt(k[0] + off, k[1] + off, k[2] + off, i as f32));
                let a = (2 * i + j) as f32 * 1e-3;
                ns.push([libm::cosf(a), libm::sinf(a), 0.0]);
            }
        }
        let (orig, orig_n) = (pts.clone(), ns.clone());
        let mut ds = std::boxed::Box::new(VoxelDownsampler::<8192>::new());
        let st = ds.downsample(&cfg(1.0), &mut pts, Some(&mut ns)).unwrap();
        assert_eq!(st.kept, 2000);
        let key = |p: &ScanPoint| p.xyz.map(|v| v.floor() as i32);
        let out = &pts[..2000];
        // Every voxel once, in Morton order of `key + 512` modulo 1024 (the wrap is part of
        // the order: keys 600 and -424 share a code, and ties keep the order first seen).
        let wrapped = |k: [i32; 3]| morton_reference(k.map(|v| (v + 512).rem_euclid(1024) - 512));
        for w in out.windows(2) {
            assert!(wrapped(key(&w[0])) <= wrapped(key(&w[1])));
        }
        let mut seen: Vec<[i32; 3]> = out.iter().map(key).collect();
        seen.sort();
        seen.dedup();
        assert_eq!(seen.len(), 2000);
        // Each output point is an input point, and its normal the mean of its voxel's two
        // (angles 2i and 2i + 1 milliradians: the mean at 2i + 0.5).
        for (p, n) in out.iter().zip(&ns[..2000]) {
            let i = orig.iter().position(|o| o == p).expect("an input point") / 2;
            let a = (2 * i) as f32 * 1e-3 + 0.5e-3;
            let d = (n[0] - libm::cosf(a)).abs() + (n[1] - libm::sinf(a)).abs() + n[2].abs();
            assert!(d < 2e-5, "{n:?} voxel {i}");
        }
        // The same input again gives the same bytes.
        let (mut p2, mut n2) = (orig.clone(), orig_n.clone());
        ds.downsample(&cfg(1.0), &mut p2, Some(&mut n2)).unwrap();
        assert_eq!(&p2[..2000], out);
    }

    /// The staged calls (bin, normals summed on threads by ranges of voxels, finish) write the
    /// bytes of one call, for any number of pieces, invalid points and normals and voxels whose
    /// normals disagree included.
    #[test]
    fn staged_with_threads_equals_one_call() {
        let mut rng = Rng::new(21);
        let (mut pts, mut ns) = (Vec::new(), Vec::new());
        for i in 0..6000 {
            let p = [0, 1, 2].map(|_| (rng.uniform() * 12.0 - 6.0) as f32);
            let mut q = pt(p[0], p[1], p[2], i as f32 * 1e-5);
            q.row = (i % 32) as u16;
            if i % 97 == 0 {
                q.xyz[1] = f32::NAN;
            }
            pts.push(q);
            let a = rng.uniform() as f32 * 0.6;
            // Some invalid, some turned over (voxels whose normals disagree).
            let z = if i % 5 == 0 { -libm::cosf(a) } else { libm::cosf(a) };
            ns.push(if i % 13 == 0 { [0.0; 3] } else { [libm::sinf(a), 0.0, z] });
        }
        let mut ds = std::boxed::Box::new(VoxelDownsampler::<16384>::new());
        let (mut p1, mut n1) = (pts.clone(), ns.clone());
        let one = ds.downsample(&cfg(0.5), &mut p1, Some(&mut n1)).unwrap();
        assert!(one.kept > 1000 && one.dropped_invalid > 0, "{one:?}");
        assert!(one.normals_disagree > 0 && one.normals_invalid > one.normals_disagree, "{one:?}");
        for width in [1, 2, 3, 8] {
            let (p2, mut n2, mut cells) = (pts.clone(), ns.clone(), std::vec![0u32; pts.len()]);
            ds.bin_with_scratch(&cfg(0.5), &p2, &mut cells).unwrap();
            ds.add_normals_with(&n2, &cells, &Threads(width));
            let mut p2 = p2;
            let st = ds.finish(&cfg(0.5), &mut p2, Some(&mut n2));
            assert_eq!(st, one, "width {width}");
            let k = one.kept as usize;
            assert_eq!(&p2[..k], &p1[..k], "width {width}");
            let bits = |n: &[[f32; 3]]| n.iter().flat_map(|v| v.map(f32::to_bits)).collect::<Vec<_>>();
            assert_eq!(bits(&n2[..k]), bits(&n1[..k]), "width {width}");
            // Gathered out of place in pieces: the same points, normals and counts.
            let (p3, mut n3) = (pts.clone(), ns.clone());
            ds.bin_with_scratch(&cfg(0.5), &p3, &mut cells).unwrap();
            ds.add_normals_with(&n3, &cells, &Threads(width));
            let mut out = std::vec![ScanPoint::default(); k];
            let st = ds.finish_into(&cfg(0.5), &p3, &mut out, Some(&mut n3), &Threads(width));
            assert_eq!(st, one, "width {width}, out of place");
            assert_eq!(&out[..], &p1[..k], "width {width}, out of place");
            assert_eq!(bits(&n3[..k]), bits(&n1[..k]), "width {width}, out of place");
        }
        // Too short a buffer: nothing written, nothing kept (never a panic).
        ds.bin_with_scratch(&cfg(0.5), &pts, &mut std::vec![0u32; pts.len()]).unwrap();
        let mut short = std::vec![ScanPoint::default(); 10];
        assert_eq!(ds.finish_into(&cfg(0.5), &pts, &mut short, None, &Threads(2)).kept, 0);
    }

    #[test]
    fn deterministic_across_runs_and_grids() {
        let mut rng = Rng::new(8);
        let pts: Vec<ScanPoint> = (0..5000)
            .map(|i| {
                pt(
                    (rng.uniform() * 20.0 - 10.0) as f32,
                    (rng.uniform() * 20.0) as f32,
                    rng.uniform() as f32,
                    i as f32,
                )
            })
            .collect();
        let ns: Vec<[f32; 3]> = (0..5000).map(|_| [0.0, 0.0, 1.0]).collect();
        let run = |ds: &mut VoxelDownsampler<4096>| {
            let (mut p, mut n) = (pts.clone(), ns.clone());
            let st = ds.downsample(&cfg(0.4), &mut p, Some(&mut n)).unwrap();
            p.truncate(st.kept as usize);
            n.truncate(st.kept as usize);
            (p, n, st)
        };
        let mut a = std::boxed::Box::new(VoxelDownsampler::<4096>::new());
        let mut b = std::boxed::Box::new(VoxelDownsampler::<4096>::new());
        let first = run(&mut a);
        // Same grid reused (emptied after each scan) and a fresh grid give identical output.
        assert_eq!(first, run(&mut a));
        assert_eq!(first, run(&mut b));
        assert!(first.2.kept > 1000);
        // With the scratch (no second search): the same output, bit for bit, also with
        // invalid points among the input; a short scratch is refused.
        let mut bad = pts.clone();
        bad[17].xyz[1] = f32::NAN;
        bad[4000].xyz = [f32::INFINITY; 3];
        for input in [pts.clone(), bad] {
            let (mut p1, mut n1) = (input.clone(), ns.clone());
            let s1 = a.downsample(&cfg(0.4), &mut p1, Some(&mut n1)).unwrap();
            let (mut p2, mut n2) = (input.clone(), ns.clone());
            let mut scratch = std::vec![0u32; input.len() + 3];
            let s2 = b.downsample_with_scratch(&cfg(0.4), &mut p2, Some(&mut n2), &mut scratch).unwrap();
            assert_eq!(s1, s2);
            let k = s1.kept as usize;
            assert_eq!(p1[..k], p2[..k]);
            assert_eq!(n1[..k], n2[..k]);
            // In stages (the voxels found before the normals are known): the same again, with
            // normals that differ from point to point (and some invalid).
            let mut rng = Rng::new(9);
            let varied: Vec<[f32; 3]> = (0..input.len())
                .map(|i| {
                    let (a, b) = ((rng.uniform() - 0.5) as f32, (rng.uniform() - 0.5) as f32);
                    let l = libm::sqrtf(a * a + b * b + 1.0);
                    if i % 13 == 0 { INVALID_NORMAL } else { [a / l, b / l, 1.0 / l] }
                })
                .collect();
            let (mut p3, mut n3) = (input.clone(), varied.clone());
            let s3 = a.downsample_with_scratch(&cfg(0.4), &mut p3, Some(&mut n3), &mut scratch).unwrap();
            let (mut p4, mut n4) = (input.clone(), varied.clone());
            b.bin_with_scratch(&cfg(0.4), &p4, &mut scratch).unwrap();
            b.add_normals(&n4, &scratch[..input.len()]);
            let s4 = b.finish(&cfg(0.4), &mut p4, Some(&mut n4));
            assert_eq!(s3, s4);
            let k = s3.kept as usize;
            assert_eq!(p3[..k], p4[..k]);
            assert_eq!(n3[..k], n4[..k]);
            assert!(s3.normals_invalid < s3.kept / 2, "{s3:?}");
        }
        let mut short = std::vec![0u32; pts.len() - 1];
        assert_eq!(
            b.downsample_with_scratch(&cfg(0.4), &mut pts.clone(), None, &mut short),
            Err(DownsampleError::LengthMismatch)
        );
    }

    #[test]
    fn normals_are_averaged_invalid_excluded_disagreement_flagged() {
        let s = libm::sinf(0.2);
        let c = libm::cosf(0.2);
        let mut pts = Vec::new();
        let mut ns = Vec::new();
        // Voxel A (x in [0, 1)): normals at +-0.2 rad about z-axis around +x, plus invalid ones.
        for (n, x) in [
            ([c, s, 0.0], 0.1),
            ([c, -s, 0.0], 0.2),
            ([0.0; 3], 0.3),
            ([f32::NAN, 0.0, 0.0], 0.4),
            ([5.0, 0.0, 0.0], 0.5),
        ] {
            pts.push(pt(x, 0.5, 0.5, x));
            ns.push(n);
        }
        // Voxel B (x in [1, 2)): opposite normals.
        for (n, x) in [([0.0, 0.0, 1.0], 1.1), ([0.0, 0.0, -1.0], 1.2)] {
            pts.push(pt(x, 0.5, 0.5, x));
            ns.push(n);
        }
        // Voxel C (x in [2, 3)): only invalid normals.
        pts.push(pt(2.5, 0.5, 0.5, 2.5));
        ns.push([0.0; 3]);
        let mut ds = VoxelDownsampler::<16>::new();
        let st = ds.downsample(&cfg(1.0), &mut pts, Some(&mut ns)).unwrap();
        assert_eq!(st.kept, 3);
        // A: the bisector, +x (the invalid normals did not pull it).
        assert!((ns[0][0] - 1.0).abs() < 1e-6 && ns[0][1].abs() < 1e-6, "{:?}", ns[0]);
        assert_eq!(ns[1], INVALID_NORMAL);
        assert_eq!(ns[2], INVALID_NORMAL);
        assert_eq!((st.normals_invalid, st.normals_disagree), (2, 1));
        // Times travel with the chosen points: A's centroid x is 0.3, so the 0.3 point is chosen.
        assert_eq!(pts[0].t, 0.3);
        assert!(pts[1].t == 1.1 || pts[1].t == 1.2);
        assert_eq!(pts[2].t, 2.5);
    }

    #[test]
    fn negative_coordinates_floor_and_bad_points_are_counted() {
        let mut pts = std::vec![
            pt(-0.1, 0.0, 0.0, 0.0),
            pt(0.1, 0.0, 0.0, 1.0),
            pt(f32::NAN, 0.0, 0.0, 2.0),
            pt(1e30, 0.0, 0.0, 3.0),
            pt(-0.2, 0.0, 0.0, 4.0),
        ];
        let mut ds = VoxelDownsampler::<16>::new();
        let st = ds.downsample(&cfg(1.0), &mut pts, None).unwrap();
        assert_eq!((st.kept, st.dropped_invalid), (2, 2));
        // -0.1 and -0.2 share voxel -1 (first seen), 0.1 is voxel 0.
        assert!(pts[0].xyz[0] < 0.0);
        assert_eq!(pts[1].xyz[0], 0.1);
    }

    #[test]
    fn overflow_is_counted_and_errors_reported() {
        let mut pts: Vec<ScanPoint> = (0..20).map(|i| pt(i as f32 + 0.5, 0.0, 0.0, 0.0)).collect();
        let mut ds = VoxelDownsampler::<16>::new();
        let st = ds.downsample(&cfg(1.0), &mut pts, None).unwrap();
        assert_eq!(st.kept, 12);
        assert_eq!(st.dropped_overflow, 8);
        assert_eq!(pts[11].xyz[0], 11.5);
        let mut bad = VoxelDownsampler::<12>::new();
        assert_eq!(bad.downsample(&cfg(1.0), &mut pts, None), Err(DownsampleError::Capacity));
        assert_eq!(ds.downsample(&cfg(0.0), &mut pts, None), Err(DownsampleError::VoxelSize));
        assert_eq!(ds.downsample(&cfg(f32::NAN), &mut pts, None), Err(DownsampleError::VoxelSize));
        let mut ns = [[0.0f32; 3]; 3];
        assert_eq!(ds.downsample(&cfg(1.0), &mut pts, Some(&mut ns)), Err(DownsampleError::LengthMismatch));
        // Empty input.
        assert_eq!(ds.downsample(&cfg(1.0), &mut [], None).unwrap().kept, 0);
    }
}
