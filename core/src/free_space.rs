//! Free space: what a scan sees through is empty, so what is there now moved in, and what the
//! map holds there is gone.
//!
//! A car, a bus or a pedestrian that moves leaves its surfaces in the voxel map (a "ghost
//! trail"): the map only ever adds, and a moving box's points then pull the association of later
//! scans. A LiDAR return says more than where a surface is: the beam crossed empty space on its
//! way there. Each scan's returns go into a coarse range image (the nearest return per cell),
//! and two tests use it:
//! - **the map's ghosts**: after the update, the map's representatives near the sensor are put in
//!   the scan's image, and a voxel whose representatives lie well in front of what the beams
//!   around them hit is removed ([`crate::voxel_map::VoxelMap::clear_seen_through`]);
//! - **moving points**: a point of this scan that lies where the beams of a reference scan went
//!   through has moved in; it is kept out of the association and the map. References are
//!   renewed every `reference_every_s` and the older of the last two is used, `reference_every_s`
//!   to twice that old. An object moving with the sensor (a bus overtaking at 1.5 m/s more)
//!   shifts only centimetres between two scans, hence an old reference; and the newest one alone
//!   is as young as one scan right after its renewal, when a bus closing in at 1.5 m/s from 40 m
//!   (a margin of 1.2 m) has not yet left the space it held then. With the older reference the
//!   traffic scenario's map held 0.71 / 1.22 / 1.06 % of its points where the actors drove
//!   (seeds 1-3) instead of 0.92 / 1.89 / 1.60 %.
//!
//! The test is conservative, because a wrong removal costs a static surface:
//! - the image holds the *nearest* return of each cell (row by elevation x 1 degree of azimuth,
//!   both from the point's direction in the scan-end frame, never the beam's nominal row, which
//!   is rows off wherever the platform pitched during the scan), and a point counts as seen
//!   through only if its own cell and at least `min_beyond` of the 3 x 3 cells around it saw
//!   farther by the margin, and none of them saw it (a return within the margin) or anything in
//!   front of it (an edge, an occluder);
//! - the margin grows with range (the beam's footprint and the pose's error);
//! - a ground point between two beams is never seen through: the beam below hits the ground
//!   nearer (grazing surfaces are safe by the same rule);
//! - only points within [`FreeSpaceConfig::max_range`] are judged;
//! - a cell no return of the scan fell in at all (marked from every return before the
//!   downsampling, [`FreeSpaceImage::mark_returns`]) is *open*: its beams went through to the sky
//!   or past the sensor's reach. For the map's ghosts an open cell counts as a return beyond,
//!   but only for a point on its own row's beam (within [`ON_BEAM_RAD`]): between two beams
//!   farther apart both may miss a thin object (a sign, a branch, a roof's edge). Every open
//!   cell says nothing for the moving points (judged against an older scan from elsewhere: with
//!   open cells there the static vehicle and rotation scenarios, seed 1, had 14,344 and 36,221
//!   points left out as moving instead of 3,434 and 11);
//! - the marks also note each cell's nearest return of all, not only of the downsampled points
//!   [`FreeSpaceImage::fill`] gets: one point per 0.4 m voxel can miss the nearest part of a
//!   cell's surface (a facade seen at a grazing angle spans metres of range in a 1-degree
//!   cell), and a point of a later scan there then lay in front of what the cell saw, a false
//!   alarm (on the traffic drive, seed 1, 309,495 points were left out as moving, 215,597 of
//!   them outside every actor's box, against 187,554 and 86,513 with the nearest of all
//!   returns). Without the marks a cell with returns but no representative says nothing.
//!
//! The images live in the caller's storage (`N` cells of 2 bytes, at most the range image's
//! pixels); each scan judges a fixed share of the map's voxels round robin, so a ghost is gone
//! within a few scans of the sensor seeing through it while the cost stays fixed.

// `!(x > t)` rejects NaN as well as small values, on purpose.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use crate::range_image::RangeImageLayout;
use crate::scan::ScanPoint;

/// Elevation bins of the row lookup table.
const ELEV_BINS: usize = 1024;
/// No row for this elevation (the table holds row + 1, so that empty storage is all zeros and a
/// `static` of it lands in `.bss`).
const NO_ROW: u8 = 0;

/// Settings of the free-space clearing.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FreeSpaceConfig {
    /// Remove seen-through voxels and leave moving points out (on by default).
    pub enabled: bool,
    /// Leave moving points out of the association and the map (with `enabled`).
    pub moving_points: bool,
    /// Representatives farther from the sensor than this (metres) are not judged.
    pub max_range: f32,
    /// A return must lie this far (metres) beyond a representative, plus `margin_per_m` times
    /// its range, to see through it.
    pub margin: f32,
    /// The margin's growth with range (metres per metre).
    pub margin_per_m: f32,
    /// Map voxels judged each scan, round robin.
    pub voxels_per_scan: u32,
    /// Azimuth cells of the image per revolution (fewer if the storage is smaller), equal in the
    /// diamond angle (0.7 to 1.4 degrees each for 360).
    pub columns: u16,
    /// Cells of the 3 x 3 neighbourhood that must see beyond a representative (a return
    /// beyond it, or, for the map's ghosts on the point's own beam, no return at all; cells
    /// with returns but no representative say nothing).
    pub min_beyond: u8,
    /// References for the moving points are renewed this often (seconds), and the older of the
    /// last two is used (this to twice this old): an object moving with the sensor shifts too
    /// little between two scans.
    pub reference_every_s: f32,
    /// Moving points grown into the rest of their objects ([`crate::moving_objects`]).
    pub grow: crate::moving_objects::GrowConfig,
}

impl FreeSpaceConfig {
    /// The defaults: 60 m, 0.4 m + 2 %, 65536 voxels per scan (24576 left a third more of the
    /// traffic's trails), 1-degree cells, 8 of 9 cells beyond (6 or 7 removed static voxels:
    /// 1,457 on the handheld scenario against 19), a reference every second, moving points grown
    /// into their objects.
    pub const DEFAULT: Self = Self {
        enabled: true,
        moving_points: true,
        max_range: 60.0,
        margin: 0.4,
        margin_per_m: 0.02,
        voxels_per_scan: 65536,
        columns: 360,
        min_beyond: 8,
        reference_every_s: 1.0,
        grow: crate::moving_objects::GrowConfig::DEFAULT,
    };
    /// Off: the map keeps everything it was given.
    pub const OFF: Self = Self { enabled: false, ..Self::DEFAULT };
}

impl Default for FreeSpaceConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// What a scan says about a point of the map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// The beams around it hit farther: the space is empty now.
    SeenThrough,
    /// A beam hit it (within the margin).
    Seen,
    /// Out of reach, out of the field of view, occluded or not enough returns around it.
    Unknown,
}

/// The azimuth as a "diamond angle" in [0, 4): monotonic in the true angle (0 at +x, 1 at +y,
/// 2 at -x, 3 at -y) with one division and no arctangent. Cells of equal diamond width are 0.7
/// to 1.4 times their mean angle, the same cells for the scan and for the map's points.
#[inline]
fn diamond(x: f32, y: f32) -> f32 {
    let d = if y >= 0.0 {
        if x >= 0.0 {
            let s = x + y;
            if s > 0.0 { y / s } else { 0.0 }
        } else {
            1.0 - x / (y - x)
        }
    } else if x < 0.0 {
        2.0 - y / (-x - y)
    } else {
        3.0 + x / (x - y)
    };
    if (0.0..4.0).contains(&d) { d } else { 0.0 }
}

/// [`diamond`] without a jump: the quadrant's base plus the share of `|y|` (first and third
/// quadrants) or `|x|` (second and fourth) in `|x| + |y|`. The same value, bit for bit, but
/// for the sign of a zero, which no cell tells apart; so it runs on vector lanes.
#[inline(always)]
fn diamond_lanes(x: f32, y: f32) -> f32 {
    let (ax, ay) = (libm::fabsf(x), libm::fabsf(y));
    let (up, right) = (y >= 0.0, x >= 0.0);
    let base = match (up, right) {
        (true, true) => 0.0,
        (true, false) => 1.0,
        (false, false) => 2.0,
        (false, true) => 3.0,
    };
    let s = ax + ay;
    let q = (if up == right { ay } else { ax }) / s;
    let d = base + if s > 0.0 { q } else { 0.0 };
    if (0.0..4.0).contains(&d) { d } else { 0.0 }
}

/// Points whose cells are found together ([`FreeSpaceImage::cells8`]): their arithmetic is
/// one 8-lane vector of `f32` per step where the build has AVX.
pub(crate) const LANES: usize = 8;

/// No cell: the point is outside the beams or has no range.
const NO_CELL: u32 = u32::MAX;

/// The cells of [`LANES`] points ([`FreeSpaceImage::cells8_parts`]).
struct CellLanes {
    /// The row, -1 for none.
    row: [i32; LANES],
    col: [i32; LANES],
    /// The squared range, m², and the range.
    r2: [f32; LANES],
    r: [f32; LANES],
    /// The elevation bin ([`ELEV_BINS`] for none).
    bin: [i32; LANES],
}

/// Up to [`LANES`] points' coordinates by axis, the lanes past the points zero (no cell).
#[inline(always)]
pub(crate) fn lanes(points: impl Iterator<Item = [f32; 3]>) -> [[f32; LANES]; 3] {
    let mut v = [[0.0; LANES]; 3];
    for (l, p) in points.take(LANES).enumerate() {
        for a in 0..3 {
            v[a][l] = p[a];
        }
    }
    v
}

/// The scan's nearest return per (beam row, azimuth cell), in centimetres (0: none), in the
/// caller's storage.
pub struct FreeSpaceImage<const N: usize> {
    range_cm: [u16; N],
    rows: u16,
    cols: u16,
    elev_row: [u8; ELEV_BINS],
    /// Bit per elevation bin: within [`ON_BEAM_RAD`] of its row's beam.
    on_beam: [u8; ELEV_BINS / 8],
    elev_lo: f32,
    elev_scale: f32,
    col_scale: f32,
    /// [`Self::mark_returns`] ran since the last [`Self::fill`].
    marked: bool,
}

/// A cell no return of the scan fell in: the beams went through (as a return beyond every
/// reach).
const OPEN: u16 = u16::MAX;

/// A range in the image's units (centimetres, 1 to 65,534: never 0 nor [`OPEN`]); one lane of
/// [`FreeSpaceImage::ranges_cm8`], which the image uses.
#[cfg(test)]
fn range_cm(r: f32) -> u16 {
    (r * 100.0).clamp(1.0, 65534.0) as u16
}

/// A direction this close to a beam's elevation lies on the beam (its divergence and the
/// pose's error): an open cell says the beam went through it. Between two beams farther
/// apart (the upper rows of a VLP-32C are 1-5 degrees apart) an open cell says nothing: a thin
/// object there (a sign, a branch, a roof's edge) is missed by both.
const ON_BEAM_RAD: f32 = 0.2 * core::f32::consts::PI / 180.0;

impl<const N: usize> core::fmt::Debug for FreeSpaceImage<N> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("FreeSpaceImage").field("rows", &self.rows).field("cols", &self.cols).finish()
    }
}

impl<const N: usize> Default for FreeSpaceImage<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> FreeSpaceImage<N> {
    /// Empty storage (no layout: every verdict is [`Verdict::Unknown`]).
    pub const fn new() -> Self {
        Self {
            range_cm: [0; N],
            rows: 0,
            cols: 0,
            elev_row: [NO_ROW; ELEV_BINS],
            on_beam: [0; ELEV_BINS / 8],
            elev_lo: 0.0,
            elev_scale: 0.0,
            col_scale: 0.0,
            marked: false,
        }
    }

    /// Sets the beams from `layout` and the azimuth cells (`columns`, fewer where `N` is
    /// smaller). Returns false (and judges nothing) for a layout of more than 254 rows or
    /// fewer than 8 cells per row.
    pub fn set_layout(&mut self, layout: &RangeImageLayout, columns: u16) -> bool {
        self.rows = 0;
        self.cols = 0;
        let rows = layout.rows();
        if rows == 0 || rows >= usize::from(u8::MAX) {
            return false;
        }
        let cols = usize::from(columns).min(N / rows);
        if cols < 8 {
            return false;
        }
        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
        for r in 0..rows {
            lo = lo.min(layout.elevation(r));
            hi = hi.max(layout.elevation(r));
        }
        // Half a typical beam spacing beyond the outer beams still belongs to them.
        let pad = if rows > 1 { 0.5 * (hi - lo) / (rows - 1) as f32 } else { 0.01 };
        let pad = pad.clamp(0.002, 0.05);
        // Bins of the elevation's sine (a point's is z / r: no arcsine per point).
        let (lo, hi) = (libm::sinf((lo - pad).max(-1.5)), libm::sinf((hi + pad).min(1.5)));
        self.elev_lo = lo;
        self.elev_scale = ELEV_BINS as f32 / (hi - lo).max(1e-3);
        self.on_beam = [0; ELEV_BINS / 8];
        for (b, slot) in self.elev_row.iter_mut().enumerate() {
            let e = libm::asinf((lo + (b as f32 + 0.5) / self.elev_scale).clamp(-1.0, 1.0));
            let mut best = (NO_ROW, f32::INFINITY);
            for r in 0..rows {
                let d = libm::fabsf(layout.elevation(r) - e);
                if d < best.1 {
                    best = (r as u8 + 1, d);
                }
            }
            *slot = best.0;
            if best.1 <= ON_BEAM_RAD {
                self.on_beam[b / 8] |= 1 << (b % 8);
            }
        }
        self.rows = rows as u16;
        self.cols = cols as u16;
        self.col_scale = cols as f32 / 4.0;
        true
    }

    /// The cell of a point in the sensor frame and its range, or `None` outside the beams.
    #[inline]
    fn cell(&self, p: [f32; 3]) -> Option<(usize, usize, f32, bool)> {
        let r = crate::math::sqrtf(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
        if !(r > 0.0) {
            return None;
        }
        let b = (p[2] / r - self.elev_lo) * self.elev_scale;
        if !(b >= 0.0 && b < ELEV_BINS as f32) {
            return None;
        }
        let b = b as usize;
        let row = self.elev_row[b];
        let on_beam = self.on_beam[b / 8] & (1 << (b % 8)) != 0;
        if row == NO_ROW {
            return None;
        }
        let row = row - 1;
        let c = (diamond(p[0], p[1]) * self.col_scale) as usize;
        let c = if c >= usize::from(self.cols) { 0 } else { c };
        Some((usize::from(row), c, r, on_beam))
    }

    /// [`Self::cell`] of [`LANES`] points at once (`v`: their coordinates by axis): each one's
    /// row (-1 where `cell` gives none), column, range and elevation bin, the same bit for bit.
    /// The arithmetic runs on all lanes together; only the table lookup is one lane at a time.
    #[inline(always)]
    fn cells8_parts(&self, v: &[[f32; LANES]; 3]) -> CellLanes {
        let [x, y, z] = v;
        let r2 = core::array::from_fn(|l| x[l] * x[l] + y[l] * y[l] + z[l] * z[l]);
        let r = crate::math::sqrtf8(r2);
        let cols = self.cols as i32;
        let (mut bin, mut col) = ([0.0f32; LANES], [0.0f32; LANES]);
        for l in 0..LANES {
            let b = (z[l] / r[l] - self.elev_lo) * self.elev_scale;
            let inside = r[l] > 0.0 && b >= 0.0 && b < ELEV_BINS as f32;
            bin[l] = if inside { b } else { ELEV_BINS as f32 };
            col[l] = diamond_lanes(x[l], y[l]) * self.col_scale;
        }
        // Both within `i32` (the bin below 1025, the column at most `cols`).
        let (bin, col) = (crate::math::trunc_i32x8(bin), crate::math::trunc_i32x8(col));
        let col = core::array::from_fn(|l| if col[l] >= cols { 0 } else { col[l] });
        let row = core::array::from_fn(|l| match self.elev_row.get(bin[l] as usize) {
            Some(&row) if row != NO_ROW => i32::from(row) - 1,
            _ => -1,
        });
        CellLanes { row, col, r2, r, bin }
    }

    /// [`Self::cells8_parts`] as each point's index in the image (`row * cols + col`,
    /// [`NO_CELL`] where `cell` gives none) and range.
    #[inline(always)]
    fn cells8(&self, v: &[[f32; LANES]; 3]) -> ([u32; LANES], [f32; LANES]) {
        let c = self.cells8_parts(v);
        let cols = self.cols as i32;
        let idx =
            core::array::from_fn(
                |l| if c.row[l] < 0 { NO_CELL } else { (c.row[l] * cols + c.col[l]) as u32 },
            );
        (idx, c.r)
    }

    /// [`range_cm`] of eight ranges (as `i32` on the way: a vector conversion). A range that is
    /// not a number gives 0 either way.
    #[inline(always)]
    fn ranges_cm8(r: &[f32; LANES]) -> [u16; LANES] {
        let cm = crate::math::trunc_i32x8(core::array::from_fn(|l| (r[l] * 100.0).clamp(1.0, 65534.0)));
        cm.map(|v| v as u16)
    }

    /// Marks the cells that none of `points` (every return of the scan, sensor frame) fell in
    /// as open, and notes the nearest return of each other cell, for the next [`Self::fill`].
    pub fn mark_returns(&mut self, points: &[ScanPoint]) {
        let cells = usize::from(self.rows) * usize::from(self.cols);
        self.range_cm[..cells].fill(OPEN);
        for chunk in points.chunks(LANES) {
            let (idx, r) = self.cells8(&lanes(chunk.iter().map(|p| p.xyz)));
            let cm = Self::ranges_cm8(&r);
            for l in 0..LANES {
                if let Some(slot) = self.range_cm.get_mut(idx[l] as usize) {
                    *slot = (*slot).min(cm[l]);
                }
            }
        }
        self.marked = cells > 0;
    }

    /// Fills the image from a scan's points (sensor frame).
    pub fn fill(&mut self, points: &[ScanPoint]) {
        let cells = usize::from(self.rows) * usize::from(self.cols);
        if !core::mem::take(&mut self.marked) {
            self.range_cm[..cells].fill(0);
        }
        if cells == 0 {
            return;
        }
        // By the direction in this frame, as the map's points are judged: a beam's own row is
        // off by rows wherever the platform pitched or rolled during the scan.
        for chunk in points.chunks(LANES) {
            let (idx, r) = self.cells8(&lanes(chunk.iter().map(|p| p.xyz)));
            let cm = Self::ranges_cm8(&r);
            for l in 0..LANES {
                if let Some(slot) = self.range_cm.get_mut(idx[l] as usize)
                    && (*slot == 0 || cm[l] < *slot)
                {
                    *slot = cm[l];
                }
            }
        }
    }

    /// What the filled image says about a point `p` in the sensor frame.
    pub fn verdict(&self, p: [f32; 3], cfg: &FreeSpaceConfig) -> Verdict {
        self.judge(p, 0.0, false, cfg)
    }

    /// [`Self::verdict`] for anything within `slack` metres of `p` (a voxel by its centre).
    pub fn verdict_with_slack(&self, p: [f32; 3], slack: f32, cfg: &FreeSpaceConfig) -> Verdict {
        self.judge(p, slack, true, cfg)
    }

    /// The verdicts of [`LANES`] points (`v`: their coordinates by axis, sensor frame), as
    /// [`Self::verdict`] gives them one by one, with the cells found on vector lanes.
    pub(crate) fn verdicts8(&self, v: &[[f32; LANES]; 3], cfg: &FreeSpaceConfig) -> [Verdict; LANES] {
        let c = self.cells8_parts(v);
        core::array::from_fn(|l| {
            if !self.in_reach(c.r2[l], cfg) || c.row[l] < 0 {
                return Verdict::Unknown;
            }
            let b = c.bin[l] as usize;
            let on_beam = self.on_beam[b / 8] & (1 << (b % 8)) != 0;
            self.judge_cell(c.row[l] as usize, c.col[l] as usize, c.r[l], on_beam, 0.0, false, cfg)
        })
    }

    /// Whether a point at squared range `r2` can be judged at all.
    #[inline(always)]
    fn in_reach(&self, r2: f32, cfg: &FreeSpaceConfig) -> bool {
        !(self.rows == 0 || !(r2 <= cfg.max_range * cfg.max_range) || r2 < 0.25)
    }

    #[inline]
    fn judge(&self, p: [f32; 3], slack: f32, open: bool, cfg: &FreeSpaceConfig) -> Verdict {
        // Out of reach first: the cell's arctangents cost more than the range.
        let r2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2];
        if !self.in_reach(r2, cfg) {
            return Verdict::Unknown;
        }
        let Some((row, col, r, on_beam)) = self.cell(p) else { return Verdict::Unknown };
        self.judge_cell(row, col, r, on_beam, slack, open, cfg)
    }

    /// [`Self::judge`] once the point's cell is known.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn judge_cell(
        &self,
        row: usize,
        col: usize,
        r: f32,
        on_beam: bool,
        slack: f32,
        open: bool,
        cfg: &FreeSpaceConfig,
    ) -> Verdict {
        // Open cells (no return at all) count as beyond only for a point on its row's beam.
        let open = open && on_beam;
        let seen = |v: u16| if v == OPEN && !open { 0 } else { v };
        let (rows, cols) = (usize::from(self.rows), usize::from(self.cols));
        let own = seen(self.range_cm[row * cols + col]);
        let margin = cfg.margin + cfg.margin_per_m * r + slack;
        let (near, far) = (r - margin, r + margin);
        if own == 0 || f32::from(own) * 0.01 <= far {
            return if own != 0 && f32::from(own) * 0.01 >= near { Verdict::Seen } else { Verdict::Unknown };
        }
        let mut beyond = 0u8;
        let left = if col == 0 { cols - 1 } else { col - 1 };
        let right = if col + 1 == cols { 0 } else { col + 1 };
        for rr in row.saturating_sub(1)..(row + 2).min(rows) {
            for c in [left, col, right] {
                let v = seen(self.range_cm[rr * cols + c]);
                if v == 0 {
                    continue;
                }
                let d = f32::from(v) * 0.01;
                if d > far {
                    beyond += 1;
                } else if d >= near {
                    return Verdict::Seen;
                } else {
                    return Verdict::Unknown;
                }
            }
        }
        if beyond >= cfg.min_beyond { Verdict::SeenThrough } else { Verdict::Unknown }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 16 beams 2 degrees apart from -15 to +15 degrees, 1800 columns.
    fn layout() -> RangeImageLayout {
        let el: [f32; 16] = core::array::from_fn(|i| (15.0 - 2.0 * i as f32).to_radians());
        RangeImageLayout::from_elevations(&el, 1800, true).unwrap()
    }

    #[test]
    fn the_lanes_find_the_cells_one_point_at_a_time_finds() {
        // Every quadrant, the axes, signed zeros, and points off the beams or without a range.
        extern crate std;
        let mut pts = std::vec::Vec::new();
        for &x in &[-7.3f32, -1.0, -0.0, 0.0, 1e-30, 0.5, 3.0, 20.0] {
            for &y in &[-4.1f32, -1.0, -0.0, 0.0, 1e-30, 0.5, 3.0, 20.0] {
                for &z in &[-9.0f32, -0.4, 0.0, 0.2, 1.5, 40.0] {
                    pts.push([x, y, z]);
                }
            }
        }
        pts.push([f32::NAN, 1.0, 0.0]);
        pts.push([f32::INFINITY, 1.0, 0.0]);
        pts.extend(scene(20.0).iter().map(|p| p.xyz));
        let img = image(20.0);
        let cols = img.cols as usize;
        for chunk in pts.chunks(LANES) {
            let (idx, r) = img.cells8(&lanes(chunk.iter().copied()));
            for (l, p) in chunk.iter().enumerate() {
                // Not a number: no cell (below), whatever either diamond says.
                if !p[0].is_nan() {
                    let d = diamond_lanes(p[0], p[1]);
                    assert_eq!(libm::fabsf(d).to_bits(), libm::fabsf(diamond(p[0], p[1])).to_bits(), "{p:?}");
                }
                match img.cell(*p) {
                    Some((row, col, rr, _)) => {
                        assert_eq!(idx[l] as usize, row * cols + col, "{p:?}");
                        assert_eq!(r[l].to_bits(), rr.to_bits(), "{p:?}");
                        assert_eq!(FreeSpaceImage::<{ 16 * 1800 }>::ranges_cm8(&r)[l], range_cm(rr), "{p:?}");
                    }
                    None => assert_eq!(idx[l], NO_CELL, "{p:?}"),
                }
            }
        }
    }

    #[test]
    fn eight_verdicts_at_once_are_the_verdicts_one_by_one() {
        extern crate std;
        let img = image(20.0);
        let cfg = FreeSpaceConfig::DEFAULT;
        // The scene's returns, nearer by 5 % and by 30 % (some seen through), farther, and
        // out of reach or without a range.
        let mut probes: std::vec::Vec<[f32; 3]> = std::vec::Vec::new();
        for k in [0.7f32, 0.95, 1.0, 1.2] {
            probes.extend(scene(20.0).iter().map(|p| p.xyz.map(|v| v * k)));
        }
        probes.extend([
            [0.0; 3],
            [0.1, 0.1, 0.0],
            [500.0, 1.0, 1.0],
            [f32::NAN, 0.0, 0.0],
            [3.0, -4.0, -1.0],
        ]);
        let mut through = 0;
        for chunk in probes.chunks(LANES) {
            let v = img.verdicts8(&lanes(chunk.iter().copied()), &cfg);
            for (l, p) in chunk.iter().enumerate() {
                assert_eq!(v[l], img.verdict(*p, &cfg), "{p:?}");
                through += usize::from(v[l] == Verdict::SeenThrough);
            }
        }
        assert!(through > 1000, "{through}");
    }

    fn pt(xyz: [f32; 3], row: u16) -> ScanPoint {
        ScanPoint { xyz, t: 0.0, row, col: 0, intensity: 0, ret: 0, flags: 0 }
    }

    /// A sensor 1.8 m above a flat ground with a wall at x = 20 m: the returns of every beam
    /// over every azimuth cell in front (|azimuth| < 40 degrees).
    fn scene(wall_x: f32) -> [ScanPoint; 16 * 400] {
        let lay = layout();
        core::array::from_fn(|i| {
            let (row, k) = (i / 400, i % 400);
            let az = (-40.0 + 0.2 * k as f32).to_radians();
            let el = lay.elevation(row);
            let d = [libm::cosf(el) * libm::cosf(az), libm::cosf(el) * libm::sinf(az), libm::sinf(el)];
            let t_wall = wall_x / d[0];
            let t_ground = if d[2] < 0.0 { -1.8 / d[2] } else { f32::INFINITY };
            let t = t_wall.min(t_ground);
            // Every other point without its beam: the row comes from its elevation.
            let beam = if i % 2 == 0 { row as u16 } else { crate::scan::NO_PIXEL };
            pt([d[0] * t, d[1] * t, d[2] * t], beam)
        })
    }

    fn image(wall_x: f32) -> FreeSpaceImage<{ 16 * 1800 }> {
        let mut img = FreeSpaceImage::new();
        assert!(img.set_layout(&layout(), 360));
        img.fill(&scene(wall_x));
        img
    }

    #[test]
    fn a_point_in_front_of_the_wall_is_seen_through_and_the_wall_is_seen() {
        let img = image(20.0);
        let cfg = FreeSpaceConfig::DEFAULT;
        // 1 m above the ground, 8 m ahead: beams at that elevation reach the wall at 20 m.
        assert_eq!(img.verdict([8.0, 0.3, -0.8], &cfg), Verdict::SeenThrough);
        // On the wall itself.
        assert_eq!(img.verdict([20.0, 1.0, 0.5], &cfg), Verdict::Seen);
        // Behind the wall: occluded.
        assert_eq!(img.verdict([24.0, 1.0, 0.5], &cfg), Verdict::Unknown);
        // Beyond the judged range.
        assert_eq!(
            img.verdict([30.0, 0.0, 0.0], &FreeSpaceConfig { max_range: 25.0, ..cfg }),
            Verdict::Unknown
        );
        // Behind the sensor: no returns there.
        assert_eq!(img.verdict([-8.0, 0.0, 0.0], &cfg), Verdict::Unknown);
        // Above the highest beam.
        assert_eq!(img.verdict([5.0, 0.0, 4.0], &cfg), Verdict::Unknown);
    }

    #[test]
    fn ground_between_two_beams_is_never_seen_through() {
        let img = image(20.0);
        let cfg = FreeSpaceConfig::DEFAULT;
        // Every ground point from 3 to 19 m, in 5 cm steps, on and between the beams' rings.
        let mut x = 3.0f32;
        while x < 19.0 {
            for y in [-2.0f32, 0.0, 3.0] {
                assert_ne!(img.verdict([x, y, -1.8], &cfg), Verdict::SeenThrough, "ground at {x} {y}");
            }
            x += 0.05;
        }
    }

    #[test]
    fn a_wall_moved_back_leaves_its_old_place_seen_through() {
        // The map saw a wall at 12 m (a truck's back); it has moved on to 20 m.
        let img = image(20.0);
        let cfg = FreeSpaceConfig::DEFAULT;
        let mut through = 0;
        let mut n = 0;
        for k in 0..20 {
            for z in [-1.0f32, -0.5, 0.0, 0.5] {
                n += 1;
                if img.verdict([12.0, -1.0 + 0.1 * k as f32, z], &cfg) == Verdict::SeenThrough {
                    through += 1;
                }
            }
        }
        assert_eq!(through, n, "every point of the old wall is seen through");
    }

    /// Where no beam returned (above a wall 1.2 m over the sensor, at 20 m), the map's clearing
    /// reads the beam as gone through, on its own elevation only; the moving points' test and
    /// an image without the marks read nothing there.
    #[test]
    fn open_cells_see_through_on_the_beam_only_and_only_for_the_map() {
        extern crate std;
        use std::vec::Vec;
        let returns: Vec<ScanPoint> = scene(20.0).into_iter().filter(|p| p.xyz[2] <= 1.2).collect();
        let mut img: FreeSpaceImage<{ 16 * 1800 }> = FreeSpaceImage::new();
        assert!(img.set_layout(&layout(), 360));
        let mut plain: FreeSpaceImage<{ 16 * 1800 }> = FreeSpaceImage::new();
        assert!(plain.set_layout(&layout(), 360));
        img.mark_returns(&returns);
        img.fill(&returns);
        plain.fill(&returns);
        let cfg = FreeSpaceConfig::DEFAULT;
        let at = |el: f32, r: f32| {
            let e = el.to_radians();
            [r * libm::cosf(e), 0.0, r * libm::sinf(e)]
        };
        // On the 7-degree beam, 10 m out: the beams at 5, 7 and 9 degrees passed over the wall.
        assert_eq!(img.verdict_with_slack(at(7.0, 10.0), 0.0, &cfg), Verdict::SeenThrough);
        assert_eq!(img.verdict(at(7.0, 10.0), &cfg), Verdict::Unknown);
        assert_eq!(plain.verdict_with_slack(at(7.0, 10.0), 0.0, &cfg), Verdict::Unknown);
        // Between the 7 and 9-degree beams: both missed whatever is there.
        assert_eq!(img.verdict_with_slack(at(8.0, 10.0), 0.0, &cfg), Verdict::Unknown);
        // On the 3-degree beam: the wall behind (3 and 1 degrees) and open above (5 degrees).
        assert_eq!(img.verdict_with_slack(at(3.0, 10.0), 0.0, &cfg), Verdict::SeenThrough);
        assert_eq!(plain.verdict_with_slack(at(3.0, 10.0), 0.0, &cfg), Verdict::Unknown);
        // The wall itself is still seen, and nothing behind it is judged.
        assert_eq!(img.verdict_with_slack([20.0, 0.5, 0.5], 0.0, &cfg), Verdict::Seen);
        assert_eq!(img.verdict_with_slack([24.0, 0.5, 0.5], 0.0, &cfg), Verdict::Unknown);
        // The marks last one fill: the next fill without them reads open cells as nothing.
        img.fill(&returns);
        assert_eq!(img.verdict_with_slack(at(7.0, 10.0), 0.0, &cfg), Verdict::Unknown);
    }

    /// The marks note the nearest of every return: a post 10 m out that the downsampling kept
    /// no point of (its returns are in the marks only) still stands in its cells, and a point
    /// 15 m out behind it is not seen through, as it is against the wall's representatives
    /// alone. Beside the post both read the space before the wall as gone through.
    #[test]
    fn the_nearest_of_all_returns_counts_not_only_the_representatives() {
        extern crate std;
        use std::vec::Vec;
        let (lay, wall) = (layout(), scene(20.0));
        let ray = |row: usize, az_deg: f32, r: f32| {
            let (el, az) = (lay.elevation(row), az_deg.to_radians());
            [r * libm::cosf(el) * libm::cosf(az), r * libm::cosf(el) * libm::sinf(az), r * libm::sinf(el)]
        };
        let post = (4..10).flat_map(|row| (0..5).map(move |k| (row, 0.2 * k as f32)));
        let all: Vec<ScanPoint> =
            wall.iter().copied().chain(post.map(|(row, az)| pt(ray(row, az, 10.0), row as u16))).collect();
        let mut img: FreeSpaceImage<{ 16 * 1800 }> = FreeSpaceImage::new();
        let mut plain: FreeSpaceImage<{ 16 * 1800 }> = FreeSpaceImage::new();
        assert!(img.set_layout(&lay, 360) && plain.set_layout(&lay, 360));
        img.mark_returns(&all);
        img.fill(&wall);
        plain.fill(&wall);
        let cfg = FreeSpaceConfig::DEFAULT;
        let behind_post = ray(6, 0.5, 15.0);
        assert_eq!(plain.verdict(behind_post, &cfg), Verdict::SeenThrough);
        assert_ne!(img.verdict(behind_post, &cfg), Verdict::SeenThrough);
        assert_eq!(img.verdict(ray(6, -20.5, 15.0), &cfg), Verdict::SeenThrough);
        assert_eq!(plain.verdict(ray(6, -20.5, 15.0), &cfg), Verdict::SeenThrough);
    }

    #[test]
    fn the_diamond_angle_rises_with_the_azimuth_and_wraps_once() {
        let mut last = -1.0f32;
        for i in 0..3600 {
            let a = (i as f32 * 0.1).to_radians();
            let d = diamond(libm::cosf(a), libm::sinf(a));
            assert!((0.0..4.0).contains(&d) && d > last, "azimuth {} deg: {d} after {last}", i as f32 * 0.1);
            last = d;
        }
        for (x, y, d) in
            [(1.0, 0.0, 0.0), (0.0, 1.0, 1.0), (-1.0, 0.0, 2.0), (0.0, -1.0, 3.0), (1.0, 1.0, 0.5)]
        {
            assert!((diamond(x, y) - d).abs() < 1e-6, "({x}, {y})");
        }
        assert_eq!(diamond(0.0, 0.0), 0.0);
        assert_eq!(diamond(f32::NAN, 1.0), 0.0);
    }

    #[test]
    fn small_storage_shrinks_the_cells_and_no_layout_judges_nothing() {
        let mut img: FreeSpaceImage<{ 16 * 100 }> = FreeSpaceImage::new();
        assert_eq!(img.verdict([5.0, 0.0, 0.0], &FreeSpaceConfig::DEFAULT), Verdict::Unknown);
        assert!(img.set_layout(&layout(), 360));
        assert_eq!(img.cols, 100);
        let mut tiny: FreeSpaceImage<64> = FreeSpaceImage::new();
        assert!(!tiny.set_layout(&layout(), 360));
        tiny.fill(&[pt([1.0, 0.0, 0.0], 0)]);
        assert_eq!(tiny.verdict([0.5, 0.0, 0.0], &FreeSpaceConfig::DEFAULT), Verdict::Unknown);
    }
}
