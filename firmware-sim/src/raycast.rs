//! Exact ray casting against analytic primitives, accelerated by a uniform 2D grid.
//!
//! Primitives: boxes rotated about z (buildings, walls, cars, kerbs, floors), vertical
//! cylinders (poles, trunks, columns), porous spheres (tree crowns) and a triangulated
//! heightfield (the ground). Every intersection is solved in closed form in f64.
//!
//! Acceleration: the xy plane is cut into square cells; each cell lists the primitives that
//! overlap it and keeps the z range of those primitives and of the ground under it. A ray walks
//! the cells in order (Amanatides-Woo DDA) and tests a cell's primitives only when its own z
//! range inside the cell overlaps theirs, so rays above the rooftops or between buildings skip
//! almost everything. The ground is walked on its own finer grid, again only where the ray's
//! height can meet it. The walk stops at the first cell that ends beyond the nearest hit.
//!
//! Tree crowns let some rays through: along a crown chord the ray meets a leaf after an
//! exponentially distributed depth (Beer-Lambert with the crown's leaf density), drawn from a
//! hash of the world seed, the ray key and the crown (see [`crate::rng`]), so every ray's fate
//! is deterministic and independent of casting order. A leaf either blocks the beam or, with a
//! hashed fraction of its energy, gives a partial return and lets the rest through (the first
//! return of a dual-return sensor).

use crate::rng;

/// A ray: origin and unit direction, world frame, metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Origin.
    pub o: [f64; 3],
    /// Unit direction.
    pub d: [f64; 3],
}

/// A surface hit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the ray, metres.
    pub t: f64,
    /// Unit surface normal facing the ray's origin.
    pub n: [f64; 3],
    /// The surface's reflectivity, Velodyne/Ouster scale (0-100 diffuse, 101-255 retroreflective).
    pub refl: u8,
    /// For a leaf: the fraction of the beam's energy it returned (1 for solid surfaces).
    pub fraction: f32,
    /// Index of the primitive hit (`u32::MAX` for the ground).
    pub prim: u32,
}

/// What a ray sees: the surface that stops it, and possibly a leaf it passed through first.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayResult {
    /// The surface that stopped the beam, if any within range.
    pub hit: Option<Hit>,
    /// A leaf in front of `hit` that reflected part of the beam and let the rest through.
    pub partial: Option<Hit>,
}

/// The shape of a primitive.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// A box rotated by `yaw` about z: centre, half extents (in the box's own axes).
    Box {
        /// Centre.
        c: [f64; 3],
        /// Half extents.
        h: [f64; 3],
        /// cos(yaw)
        cos: f64,
        /// sin(yaw)
        sin: f64,
    },
    /// A vertical cylinder with a flat top and bottom.
    Cylinder {
        /// Axis position (x, y).
        c: [f64; 2],
        /// Radius.
        r: f64,
        /// Bottom height.
        z0: f64,
        /// Top height.
        z1: f64,
    },
    /// A porous sphere (tree crown) with a leaf density (expected leaf hits per metre).
    Crown {
        /// Centre.
        c: [f64; 3],
        /// Radius.
        r: f64,
        /// Leaf density, 1/m.
        density: f64,
    },
}

impl Shape {
    /// A box of size `size` (full extents) centred at `c`, rotated by `yaw` radians about z.
    pub fn boxed(c: [f64; 3], size: [f64; 3], yaw: f64) -> Shape {
        Shape::Box {
            c,
            h: [size[0] * 0.5, size[1] * 0.5, size[2] * 0.5],
            cos: libm::cos(yaw),
            sin: libm::sin(yaw),
        }
    }

    /// Axis-aligned bounds (min, max) of the shape.
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        match *self {
            Shape::Box { c, h, cos, sin } => {
                let ex = h[0] * cos.abs() + h[1] * sin.abs();
                let ey = h[0] * sin.abs() + h[1] * cos.abs();
                ([c[0] - ex, c[1] - ey, c[2] - h[2]], [c[0] + ex, c[1] + ey, c[2] + h[2]])
            }
            Shape::Cylinder { c, r, z0, z1 } => ([c[0] - r, c[1] - r, z0], [c[0] + r, c[1] + r, z1]),
            Shape::Crown { c, r, .. } => ([c[0] - r, c[1] - r, c[2] - r], [c[0] + r, c[1] + r, c[2] + r]),
        }
    }

    /// Whether the shape's footprint touches the axis-aligned square [c0, c0 + size] (with a
    /// millimetre of slack), by separating axes for boxes and nearest-point distance for round
    /// shapes.
    pub fn touches_square(&self, c0: [f64; 2], size: f64) -> bool {
        let eps = 1e-3;
        let h = size * 0.5;
        let sc = [c0[0] + h, c0[1] + h];
        match *self {
            Shape::Box { c, h: bh, cos, sin } => {
                let d = [c[0] - sc[0], c[1] - sc[1]];
                // Axes of the square (x, y) and of the box.
                let ex = bh[0] * cos.abs() + bh[1] * sin.abs();
                let ey = bh[0] * sin.abs() + bh[1] * cos.abs();
                if d[0].abs() > h + ex + eps || d[1].abs() > h + ey + eps {
                    return false;
                }
                for ax in [[cos, sin], [-sin, cos]] {
                    let r_sq = h * (ax[0].abs() + ax[1].abs());
                    let r_box = if ax == [cos, sin] { bh[0] } else { bh[1] };
                    if (d[0] * ax[0] + d[1] * ax[1]).abs() > r_sq + r_box + eps {
                        return false;
                    }
                }
                true
            }
            Shape::Cylinder { c: [x, y], r, .. } | Shape::Crown { c: [x, y, _], r, .. } => {
                let c = [x, y];
                let qx = (c[0] - sc[0]).abs() - h;
                let qy = (c[1] - sc[1]).abs() - h;
                let (qx, qy) = (qx.max(0.0), qy.max(0.0));
                qx * qx + qy * qy <= (r + eps) * (r + eps)
            }
        }
    }

    /// Distance in the xy plane from a point to the shape's footprint (0 inside).
    pub fn xy_distance(&self, p: [f64; 2]) -> f64 {
        match *self {
            Shape::Box { c, h, cos, sin } => {
                let (dx, dy) = (p[0] - c[0], p[1] - c[1]);
                let (lx, ly) = (cos * dx + sin * dy, -sin * dx + cos * dy);
                let qx = (lx.abs() - h[0]).max(0.0);
                let qy = (ly.abs() - h[1]).max(0.0);
                libm::sqrt(qx * qx + qy * qy)
            }
            Shape::Cylinder { c, r, .. } => 0.0f64.max(libm::hypot(p[0] - c[0], p[1] - c[1]) - r),
            Shape::Crown { c, r, .. } => 0.0f64.max(libm::hypot(p[0] - c[0], p[1] - c[1]) - r),
        }
    }
}

/// A primitive: a shape and its reflectivity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prim {
    /// Geometry.
    pub shape: Shape,
    /// Reflectivity (0-100 diffuse, 101-255 retroreflective).
    pub refl: u8,
}

/// A ground heightfield: vertex heights on a regular grid, each cell split into two triangles
/// along its (i, j)-(i+1, j+1) diagonal.
#[derive(Clone, Debug)]
pub struct Heightfield {
    x0: f64,
    y0: f64,
    step: f64,
    inv_step: f64,
    nx: usize,
    ny: usize,
    /// (nx + 1) * (ny + 1) vertex heights, row-major in y.
    z: Vec<f64>,
    /// Per cell (nx * ny): min and max of its four vertices.
    cell_range: Vec<[f32; 2]>,
    refl: u8,
}

impl Heightfield {
    /// Samples `height` on a grid of `nx` x `ny` cells of `step` metres starting at (x0, y0).
    pub fn new(
        x0: f64,
        y0: f64,
        step: f64,
        nx: usize,
        ny: usize,
        refl: u8,
        height: impl Fn(f64, f64) -> f64,
    ) -> Self {
        let mut z = Vec::with_capacity((nx + 1) * (ny + 1));
        for j in 0..=ny {
            for i in 0..=nx {
                z.push(height(x0 + i as f64 * step, y0 + j as f64 * step));
            }
        }
        let mut cell_range = Vec::with_capacity(nx * ny);
        for j in 0..ny {
            for i in 0..nx {
                let v = [
                    z[j * (nx + 1) + i],
                    z[j * (nx + 1) + i + 1],
                    z[(j + 1) * (nx + 1) + i],
                    z[(j + 1) * (nx + 1) + i + 1],
                ];
                let lo = v.iter().cloned().fold(f64::INFINITY, f64::min);
                let hi = v.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                // Rounded outwards so the f32 range always contains the f64 triangles.
                cell_range.push([next_down(lo as f32), next_up(hi as f32)]);
            }
        }
        Self { x0, y0, step, inv_step: 1.0 / step, nx, ny, z, cell_range, refl }
    }

    /// Height of the triangulated surface at (x, y), if inside.
    pub fn height_at(&self, x: f64, y: f64) -> Option<f64> {
        let fx = (x - self.x0) * self.inv_step;
        let fy = (y - self.y0) * self.inv_step;
        if !(fx >= 0.0 && fy >= 0.0 && fx <= self.nx as f64 && fy <= self.ny as f64) {
            return None;
        }
        let i = (fx as usize).min(self.nx - 1);
        let j = (fy as usize).min(self.ny - 1);
        let (u, v) = (fx - i as f64, fy - j as f64);
        let [z00, z10, z01, z11] = self.corners(i, j);
        Some(if u >= v {
            z00 + (z10 - z00) * u + (z11 - z10) * v
        } else {
            z00 + (z11 - z01) * u + (z01 - z00) * v
        })
    }

    #[inline]
    fn corners(&self, i: usize, j: usize) -> [f64; 4] {
        let w = self.nx + 1;
        let k = j * w + i;
        [self.z[k], self.z[k + 1], self.z[k + w], self.z[k + w + 1]]
    }

    /// Min and max height over the cells overlapping the xy box [lo, hi].
    fn range_over(&self, lo: [f64; 2], hi: [f64; 2]) -> Option<[f32; 2]> {
        let i0 = (((lo[0] - self.x0) * self.inv_step).floor().max(0.0) as usize).min(self.nx);
        let j0 = (((lo[1] - self.y0) * self.inv_step).floor().max(0.0) as usize).min(self.ny);
        let i1 = (((hi[0] - self.x0) * self.inv_step).ceil().max(0.0) as usize).min(self.nx);
        let j1 = (((hi[1] - self.y0) * self.inv_step).ceil().max(0.0) as usize).min(self.ny);
        let mut r: Option<[f32; 2]> = None;
        for j in j0..j1 {
            for i in i0..i1 {
                let c = self.cell_range[j * self.nx + i];
                r = Some(match r {
                    None => c,
                    Some(a) => [a[0].min(c[0]), a[1].max(c[1])],
                });
            }
        }
        r
    }

    /// Nearest ground hit with t in [ta, tb].
    fn cast(&self, ray: &Ray, ta: f64, tb: f64) -> Option<Hit> {
        let [ox, oy, oz] = ray.o;
        let [dx, dy, dz] = ray.d;
        // Clip to the heightfield's xy extent.
        let (mut t0, mut t1) = (ta, tb);
        let ext = [
            (self.x0, self.x0 + self.nx as f64 * self.step, ox, dx),
            (self.y0, self.y0 + self.ny as f64 * self.step, oy, dy),
        ];
        for (lo, hi, o, d) in ext {
            if d == 0.0 {
                if o < lo || o > hi {
                    return None;
                }
            } else {
                let inv = 1.0 / d;
                let (a, b) = ((lo - o) * inv, (hi - o) * inv);
                t0 = t0.max(a.min(b));
                t1 = t1.min(a.max(b));
            }
        }
        if t0 > t1 {
            return None;
        }
        // Local grid coordinates along the ray.
        let gx = |t: f64| (ox + dx * t - self.x0) * self.inv_step;
        let gy = |t: f64| (oy + dy * t - self.y0) * self.inv_step;
        let (sx, sy) = (gx(t0), gy(t0));
        let mut i = (sx.floor().max(0.0) as usize).min(self.nx - 1) as isize;
        let mut j = (sy.floor().max(0.0) as usize).min(self.ny - 1) as isize;
        let (step_i, step_j) = (if dx > 0.0 { 1 } else { -1 }, if dy > 0.0 { 1 } else { -1 });
        let dtx = if dx != 0.0 { (self.step / dx).abs() } else { f64::INFINITY };
        let dty = if dy != 0.0 { (self.step / dy).abs() } else { f64::INFINITY };
        let bx = |i: isize| self.x0 + (i + if dx > 0.0 { 1 } else { 0 }) as f64 * self.step;
        let by = |j: isize| self.y0 + (j + if dy > 0.0 { 1 } else { 0 }) as f64 * self.step;
        let mut tnx = if dx != 0.0 { (bx(i) - ox) / dx } else { f64::INFINITY };
        let mut tny = if dy != 0.0 { (by(j) - oy) / dy } else { f64::INFINITY };
        let mut t_enter = t0;
        loop {
            let t_exit = tnx.min(tny).min(t1);
            let r = self.cell_range[j as usize * self.nx + i as usize];
            let (za, zb) = (oz + dz * t_enter, oz + dz * t_exit);
            let (zl, zh) = if za < zb { (za, zb) } else { (zb, za) };
            if zl <= r[1] as f64
                && zh >= r[0] as f64
                && let Some(h) = self.cell_hit(ray, i as usize, j as usize, t_enter, t_exit)
            {
                return Some(h);
            }
            if t_exit >= t1 {
                return None;
            }
            // Going up above the highest ground, or starting below it, never meets it later.
            t_enter = t_exit;
            if tnx < tny {
                i += step_i;
                tnx += dtx;
                if i < 0 || i >= self.nx as isize {
                    return None;
                }
            } else {
                j += step_j;
                tny += dty;
                if j < 0 || j >= self.ny as isize {
                    return None;
                }
            }
        }
    }

    /// Intersection with the two triangles of cell (i, j) within [ta, tb].
    #[inline]
    fn cell_hit(&self, ray: &Ray, i: usize, j: usize, ta: f64, tb: f64) -> Option<Hit> {
        let [z00, z10, z01, z11] = self.corners(i, j);
        let cx = self.x0 + i as f64 * self.step;
        let cy = self.y0 + j as f64 * self.step;
        let s = self.inv_step;
        // Ray in cell units: u = (x - cx)/step, v = (y - cy)/step.
        let (u0, v0, z0) = ((ray.o[0] - cx) * s, (ray.o[1] - cy) * s, ray.o[2]);
        let (du, dv, dz) = (ray.d[0] * s, ray.d[1] * s, ray.d[2]);
        let mut best: Option<(f64, [f64; 3])> = None;
        // Triangle A (u >= v): z = z00 + a u + b v; triangle B (v > u).
        for (a, b, upper) in [(z10 - z00, z11 - z10, false), (z11 - z01, z01 - z00, true)] {
            // z0 + dz t = z00 + a (u0 + du t) + b (v0 + dv t)
            let den = dz - a * du - b * dv;
            if den == 0.0 {
                continue;
            }
            let t = (z00 + a * u0 + b * v0 - z0) / den;
            if t < ta - 1e-9 || t > tb + 1e-9 || best.is_some_and(|(bt, _)| bt <= t) {
                continue;
            }
            let (u, v) = (u0 + du * t, v0 + dv * t);
            let inside = if upper { v > u } else { u >= v };
            if !inside || u < -1e-9 || v < -1e-9 || u > 1.0 + 1e-9 || v > 1.0 + 1e-9 {
                continue;
            }
            // Normal of z - a u - b v = 0 in world units: (-a/step, -b/step, 1).
            let n = normalize([-a * s, -b * s, 1.0]);
            best = Some((t, n));
        }
        best.map(|(t, n)| Hit { t, n: face(n, ray.d), refl: self.refl, fraction: 1.0, prim: u32::MAX })
    }
}

#[inline]
fn next_up(x: f32) -> f32 {
    x + x.abs() * 1e-6 + 1e-6
}

#[inline]
fn next_down(x: f32) -> f32 {
    x - x.abs() * 1e-6 - 1e-6
}

#[inline]
fn normalize(v: [f64; 3]) -> [f64; 3] {
    let n = 1.0 / libm::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    [v[0] * n, v[1] * n, v[2] * n]
}

/// Flips `n` to face against `d`.
#[inline]
fn face(n: [f64; 3], d: [f64; 3]) -> [f64; 3] {
    if n[0] * d[0] + n[1] * d[1] + n[2] * d[2] > 0.0 { [-n[0], -n[1], -n[2]] } else { n }
}

/// One grid cell.
#[derive(Clone, Copy, Debug)]
struct Cell {
    /// z range of its primitives (empty cells: [inf, -inf]).
    obj: [f32; 2],
    /// z range of the ground under it (no ground: [inf, -inf]).
    gnd: [f32; 2],
    /// Its items: `items[start..end]`.
    start: u32,
    end: u32,
}

/// A primitive listed in a cell, with its z range for a quick reject.
#[derive(Clone, Copy, Debug)]
struct Item {
    prim: u32,
    z: [f32; 2],
}

/// A primitive whose bounds cover more cells than this is tested once per ray instead.
const GLOBAL_CELLS: usize = 64;

/// The geometry of a world: primitives, optional ground, and the acceleration grid.
#[derive(Clone, Debug)]
pub struct Scene {
    prims: Vec<Prim>,
    ground: Option<Heightfield>,
    seed: u64,
    // Grid.
    gx0: f64,
    gy0: f64,
    cell: f64,
    nx: usize,
    ny: usize,
    /// Per cell, packed in one cache line: the z ranges and the item slice.
    cells: Vec<Cell>,
    items: Vec<Item>,
    /// Primitives covering many cells (floors, ceilings, long walls): tested once per ray,
    /// before the walk, so that their hit bounds it.
    global: Vec<u32>,
    zmin: f64,
    zmax: f64,
}

impl Scene {
    /// Builds the grid over the xy box [lo, hi] with square cells of `cell` metres.
    pub fn new(
        prims: Vec<Prim>,
        ground: Option<Heightfield>,
        seed: u64,
        lo: [f64; 2],
        hi: [f64; 2],
        cell: f64,
    ) -> Self {
        let nx = (((hi[0] - lo[0]) / cell).ceil() as usize).max(1);
        let ny = (((hi[1] - lo[1]) / cell).ceil() as usize).max(1);
        let mut lists: Vec<Vec<Item>> = vec![Vec::new(); nx * ny];
        let mut obj_z = vec![[f32::INFINITY, f32::NEG_INFINITY]; nx * ny];
        let (mut zmin, mut zmax) = (f64::INFINITY, f64::NEG_INFINITY);
        let mut global = Vec::new();
        for (k, p) in prims.iter().enumerate() {
            let (bl, bh) = p.shape.bounds();
            zmin = zmin.min(bl[2]);
            zmax = zmax.max(bh[2]);
            let ci = |x: f64, n: usize| (((x - lo[0]) / cell).floor().max(0.0) as usize).min(n - 1);
            let cj = |y: f64, n: usize| (((y - lo[1]) / cell).floor().max(0.0) as usize).min(n - 1);
            let covered = (cj(bh[1], ny) - cj(bl[1], ny) + 1) * (ci(bh[0], nx) - ci(bl[0], nx) + 1);
            if covered > GLOBAL_CELLS {
                global.push(k as u32);
                continue;
            }
            for j in cj(bl[1], ny)..=cj(bh[1], ny) {
                for i in ci(bl[0], nx)..=ci(bh[0], nx) {
                    // Skip cells the footprint does not touch (rotated boxes, round shapes).
                    let c0 = [lo[0] + i as f64 * cell, lo[1] + j as f64 * cell];
                    if !p.shape.touches_square(c0, cell) {
                        continue;
                    }
                    lists[j * nx + i]
                        .push(Item { prim: k as u32, z: [next_down(bl[2] as f32), next_up(bh[2] as f32)] });
                    let z = &mut obj_z[j * nx + i];
                    z[0] = z[0].min(next_down(bl[2] as f32));
                    z[1] = z[1].max(next_up(bh[2] as f32));
                }
            }
        }
        let mut gnd_z = vec![[f32::INFINITY, f32::NEG_INFINITY]; nx * ny];
        if let Some(g) = &ground {
            for j in 0..ny {
                for i in 0..nx {
                    let a = [lo[0] + i as f64 * cell, lo[1] + j as f64 * cell];
                    if let Some(r) = g.range_over(a, [a[0] + cell, a[1] + cell]) {
                        gnd_z[j * nx + i] = r;
                        zmin = zmin.min(r[0] as f64);
                        zmax = zmax.max(r[1] as f64);
                    }
                }
            }
        }
        let mut cells = Vec::with_capacity(nx * ny);
        let mut items = Vec::new();
        for (c, l) in lists.iter().enumerate() {
            let start = items.len() as u32;
            items.extend_from_slice(l);
            cells.push(Cell { obj: obj_z[c], gnd: gnd_z[c], start, end: items.len() as u32 });
        }
        Self { prims, ground, seed, gx0: lo[0], gy0: lo[1], cell, nx, ny, cells, items, global, zmin, zmax }
    }

    /// The primitives.
    pub fn prims(&self) -> &[Prim] {
        &self.prims
    }

    /// The ground, if any.
    pub fn ground(&self) -> Option<&Heightfield> {
        self.ground.as_ref()
    }

    /// Casts a ray up to `t_max` metres. `key` identifies the ray (for leaf pass-through).
    pub fn cast(&self, ray: &Ray, t_max: f64, key: u64) -> RayResult {
        let [ox, oy, oz] = ray.o;
        let [dx, dy, dz] = ray.d;
        let mut res = RayResult::default();
        // Clip to the grid box in xy and to the scene's z range.
        let (mut t0, mut t1) = (0.0f64, t_max);
        let ext = [
            (self.gx0, self.gx0 + self.nx as f64 * self.cell, ox, dx),
            (self.gy0, self.gy0 + self.ny as f64 * self.cell, oy, dy),
            (self.zmin, self.zmax, oz, dz),
        ];
        for (lo, hi, o, d) in ext {
            if d == 0.0 {
                if o < lo || o > hi {
                    return res;
                }
            } else {
                let inv = 1.0 / d;
                let (a, b) = ((lo - o) * inv, (hi - o) * inv);
                t0 = t0.max(a.min(b));
                t1 = t1.min(a.max(b));
            }
        }
        if t0 > t1 {
            return res;
        }
        let fx = (ox + dx * t0 - self.gx0) / self.cell;
        let fy = (oy + dy * t0 - self.gy0) / self.cell;
        let mut i = (fx.floor().max(0.0) as usize).min(self.nx - 1) as isize;
        let mut j = (fy.floor().max(0.0) as usize).min(self.ny - 1) as isize;
        let (step_i, step_j) = (if dx > 0.0 { 1 } else { -1 }, if dy > 0.0 { 1 } else { -1 });
        let dtx = if dx != 0.0 { (self.cell / dx).abs() } else { f64::INFINITY };
        let dty = if dy != 0.0 { (self.cell / dy).abs() } else { f64::INFINITY };
        let bx = self.gx0 + (i + if dx > 0.0 { 1 } else { 0 }) as f64 * self.cell;
        let by = self.gy0 + (j + if dy > 0.0 { 1 } else { 0 }) as f64 * self.cell;
        let mut tnx = if dx != 0.0 { (bx - ox) / dx } else { f64::INFINITY };
        let mut tny = if dy != 0.0 { (by - oy) / dy } else { f64::INFINITY };
        let mut t_enter = t0;
        let mut best = t1;
        let inv = inverse(ray.d);
        for &k in &self.global {
            self.test_prim(k, ray, &inv, 0.0, &mut best, &mut res, key);
        }
        // Primitives already tested by this ray (they span several cells).
        let mut mailbox = [u32::MAX; 8];
        let mut mb = 0usize;
        loop {
            let c = j as usize * self.nx + i as usize;
            let t_exit = tnx.min(tny).min(t1);
            let (za, zb) = (oz + dz * t_enter, oz + dz * t_exit.min(best));
            let (zl, zh) = if za < zb { (za, zb) } else { (zb, za) };
            let cell = self.cells[c];
            if zl <= cell.obj[1] as f64 && zh >= cell.obj[0] as f64 {
                for it in &self.items[cell.start as usize..cell.end as usize] {
                    let k = it.prim;
                    if zl > it.z[1] as f64 || zh < it.z[0] as f64 || mailbox.contains(&k) {
                        continue;
                    }
                    mailbox[mb & 7] = k;
                    mb += 1;
                    self.test_prim(k, ray, &inv, 0.0, &mut best, &mut res, key);
                }
            }
            let g = cell.gnd;
            if zl <= g[1] as f64
                && zh >= g[0] as f64
                && let Some(ground) = &self.ground
                && let Some(h) = ground.cast(ray, t_enter, t_exit.min(best))
                && h.t < best
            {
                best = h.t;
                res.hit = Some(h);
            }
            if best <= t_exit || t_exit >= t1 {
                break;
            }
            t_enter = t_exit;
            if tnx < tny {
                i += step_i;
                tnx += dtx;
                if i < 0 || i >= self.nx as isize {
                    break;
                }
            } else {
                j += step_j;
                tny += dty;
                if j < 0 || j >= self.ny as isize {
                    break;
                }
            }
        }
        if let (Some(p), Some(h)) = (res.partial, res.hit)
            && p.t >= h.t
        {
            res.partial = None;
        }
        res
    }

    /// The same answer as [`Self::cast`] without the grid: every primitive and the whole ground
    /// are tested. The reference for the grid's correctness tests and speed-up figure.
    pub fn cast_brute(&self, ray: &Ray, t_max: f64, key: u64) -> RayResult {
        let mut res = RayResult::default();
        let mut best = t_max;
        let inv = inverse(ray.d);
        for k in 0..self.prims.len() as u32 {
            self.test_prim(k, ray, &inv, 0.0, &mut best, &mut res, key);
        }
        if let Some(g) = &self.ground
            && let Some(h) = g.cast(ray, 0.0, best)
            && h.t < best
        {
            res.hit = Some(h);
        }
        if let (Some(p), Some(h)) = (res.partial, res.hit)
            && p.t >= h.t
        {
            res.partial = None;
        }
        res
    }

    #[inline]
    #[allow(clippy::too_many_arguments)]
    fn test_prim(
        &self,
        k: u32,
        ray: &Ray,
        inv: &[f64; 3],
        tmin: f64,
        best: &mut f64,
        res: &mut RayResult,
        key: u64,
    ) {
        let p = &self.prims[k as usize];
        match p.shape {
            Shape::Box { c, h, cos, sin } => {
                if let Some((t, n)) = ray_box_inv(ray, inv, c, h, cos, sin, tmin, *best) {
                    *best = t;
                    res.hit = Some(Hit { t, n: face(n, ray.d), refl: p.refl, fraction: 1.0, prim: k });
                }
            }
            Shape::Cylinder { c, r, z0, z1 } => {
                if let Some((t, n)) = ray_cylinder(ray, c, r, z0, z1, tmin, *best) {
                    *best = t;
                    res.hit = Some(Hit { t, n: face(n, ray.d), refl: p.refl, fraction: 1.0, prim: k });
                }
            }
            Shape::Crown { c, r, density } => {
                let Some((ta, tb)) = ray_sphere(ray, c, r) else { return };
                let ta = ta.max(tmin);
                if ta >= tb || ta >= *best {
                    return;
                }
                // Depth to the first leaf: exponential with rate `density`, by inversion.
                let u = rng::unit(self.seed, key, 0x1EAF_0000 ^ k as u64);
                let depth = -libm::log(1.0 - u) / density;
                let t = ta + depth;
                if t >= tb || t >= *best {
                    return;
                }
                let q = rng::unit(self.seed, key, 0x1EAF_1000 ^ k as u64);
                // A leaf normal: the crown's outward normal tilted by a hashed amount.
                let jit = rng::unit(self.seed, key, 0x1EAF_2000 ^ k as u64) - 0.5;
                let pnt = [
                    ray.o[0] + ray.d[0] * t - c[0],
                    ray.o[1] + ray.d[1] * t - c[1],
                    ray.o[2] + ray.d[2] * t - c[2] + jit * r,
                ];
                let n = face(normalize(pnt), ray.d);
                if q < 0.4 {
                    // The leaf covers the whole footprint: the beam stops here.
                    *best = t;
                    res.hit = Some(Hit { t, n, refl: p.refl, fraction: 1.0, prim: k });
                } else {
                    // Part of the beam returns, the rest goes on: keep the nearest such leaf.
                    let fraction = (0.15 + 0.6 * (1.0 - q)) as f32;
                    if res.partial.is_none_or(|h| t < h.t) {
                        res.partial = Some(Hit { t, n, refl: p.refl, fraction, prim: k });
                    }
                }
            }
        }
    }
}

/// Ray against a z-rotated box; (t, normal) of the entry point with t in (tmin, tmax).
#[inline]
pub fn ray_box(
    ray: &Ray,
    c: [f64; 3],
    h: [f64; 3],
    cos: f64,
    sin: f64,
    tmin: f64,
    tmax: f64,
) -> Option<(f64, [f64; 3])> {
    ray_box_inv(ray, &inverse(ray.d), c, h, cos, sin, tmin, tmax)
}

/// Component-wise 1/d (infinite for zero components).
#[inline]
fn inverse(d: [f64; 3]) -> [f64; 3] {
    [1.0 / d[0], 1.0 / d[1], 1.0 / d[2]]
}

/// One slab of a box: updates the entry/exit distances; false if the ray misses.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn slab(o: f64, d: f64, inv: f64, h: f64, a: usize, tn: &mut f64, tf: &mut f64, axis: &mut usize) -> bool {
    if d == 0.0 {
        return o >= -h && o <= h;
    }
    let (t1, t2) = ((-h - o) * inv, (h - o) * inv);
    let (lo, hi) = if t1 < t2 { (t1, t2) } else { (t2, t1) };
    if lo > *tn {
        *tn = lo;
        *axis = a;
    }
    *tf = tf.min(hi);
    *tn <= *tf
}

/// [`ray_box`] with the ray's inverse direction precomputed (the z slab and axis-aligned
/// boxes need no division).
#[inline]
#[allow(clippy::too_many_arguments)]
fn ray_box_inv(
    ray: &Ray,
    inv: &[f64; 3],
    c: [f64; 3],
    h: [f64; 3],
    cos: f64,
    sin: f64,
    tmin: f64,
    tmax: f64,
) -> Option<(f64, [f64; 3])> {
    let (px, py, pz) = (ray.o[0] - c[0], ray.o[1] - c[1], ray.o[2] - c[2]);
    let mut tn = f64::NEG_INFINITY;
    let mut tf = tmax;
    let mut axis = 2usize;
    // The z slab first: it is unrotated and rejects most boxes above or below the ray.
    if !slab(pz, ray.d[2], inv[2], h[2], 2, &mut tn, &mut tf, &mut axis) {
        return None;
    }
    let (d0, d1) = if sin == 0.0 && cos == 1.0 {
        if !slab(px, ray.d[0], inv[0], h[0], 0, &mut tn, &mut tf, &mut axis)
            || !slab(py, ray.d[1], inv[1], h[1], 1, &mut tn, &mut tf, &mut axis)
        {
            return None;
        }
        (ray.d[0], ray.d[1])
    } else {
        let o = [cos * px + sin * py, -sin * px + cos * py];
        let d = [cos * ray.d[0] + sin * ray.d[1], -sin * ray.d[0] + cos * ray.d[1]];
        if !slab(o[0], d[0], 1.0 / d[0], h[0], 0, &mut tn, &mut tf, &mut axis)
            || !slab(o[1], d[1], 1.0 / d[1], h[1], 1, &mut tn, &mut tf, &mut axis)
        {
            return None;
        }
        (d[0], d[1])
    };
    // Origin inside the box (tn < tmin): a sensor inside a solid sees nothing of it.
    if tn <= tmin || tn >= tmax {
        return None;
    }
    let da = [d0, d1, ray.d[2]][axis];
    let s = if da > 0.0 { -1.0 } else { 1.0 };
    let n = match axis {
        0 => [s * cos, s * sin, 0.0],
        1 => [-s * sin, s * cos, 0.0],
        _ => [0.0, 0.0, s],
    };
    Some((tn, n))
}

/// Ray against a vertical capped cylinder.
#[inline]
pub fn ray_cylinder(
    ray: &Ray,
    c: [f64; 2],
    r: f64,
    z0: f64,
    z1: f64,
    tmin: f64,
    tmax: f64,
) -> Option<(f64, [f64; 3])> {
    let (px, py) = (ray.o[0] - c[0], ray.o[1] - c[1]);
    let (dx, dy, dz) = (ray.d[0], ray.d[1], ray.d[2]);
    let a = dx * dx + dy * dy;
    let mut best: Option<(f64, [f64; 3])> = None;
    if a > 0.0 {
        let b = px * dx + py * dy;
        let cc = px * px + py * py - r * r;
        let disc = b * b - a * cc;
        if disc < 0.0 {
            return None;
        }
        let t = (-b - libm::sqrt(disc)) / a;
        if t > tmin && t < tmax {
            let z = ray.o[2] + dz * t;
            if z >= z0 && z <= z1 {
                let inv = 1.0 / r;
                best = Some((t, [(px + dx * t) * inv, (py + dy * t) * inv, 0.0]));
            }
        }
    }
    // Caps.
    if dz != 0.0 {
        for (zc, nz) in [(z1, 1.0), (z0, -1.0)] {
            let t = (zc - ray.o[2]) / dz;
            if t > tmin && t < best.map_or(tmax, |b| b.0) {
                let (x, y) = (px + dx * t, py + dy * t);
                if x * x + y * y <= r * r {
                    best = Some((t, [0.0, 0.0, nz]));
                }
            }
        }
    }
    best
}

/// Ray against a sphere: the entry and exit distances (entry may be negative inside).
#[inline]
pub fn ray_sphere(ray: &Ray, c: [f64; 3], r: f64) -> Option<(f64, f64)> {
    let p = [ray.o[0] - c[0], ray.o[1] - c[1], ray.o[2] - c[2]];
    let b = p[0] * ray.d[0] + p[1] * ray.d[1] + p[2] * ray.d[2];
    let cc = p[0] * p[0] + p[1] * p[1] + p[2] * p[2] - r * r;
    let disc = b * b - cc;
    if disc <= 0.0 {
        return None;
    }
    let s = libm::sqrt(disc);
    let (ta, tb) = (-b - s, -b + s);
    if tb <= 0.0 { None } else { Some((ta, tb)) }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray(o: [f64; 3], d: [f64; 3]) -> Ray {
        Ray { o, d: normalize(d) }
    }

    fn scene(prims: Vec<Prim>, ground: Option<Heightfield>) -> Scene {
        Scene::new(prims, ground, 1, [-50.0, -50.0], [50.0, 50.0], 4.0)
    }

    #[test]
    fn box_hit_at_analytic_range_and_normal() {
        // A 45-degree rotated box whose face is 10 m away along the diagonal.
        let yaw = core::f64::consts::FRAC_PI_4;
        let c =
            [10.0 * libm::cos(yaw) + 1.0 * libm::cos(yaw), 10.0 * libm::sin(yaw) + 1.0 * libm::sin(yaw), 2.0];
        let s = scene(vec![Prim { shape: Shape::boxed(c, [2.0, 6.0, 4.0], yaw), refl: 40 }], None);
        let r = s.cast(&ray([0.0, 0.0, 2.0], [1.0, 1.0, 0.0]), 100.0, 0);
        let h = r.hit.unwrap();
        assert!((h.t - 10.0).abs() < 1e-12, "{}", h.t);
        let n = [-libm::cos(yaw), -libm::sin(yaw), 0.0];
        assert!((0..3).all(|a| (h.n[a] - n[a]).abs() < 1e-12));
        assert_eq!(h.refl, 40);
        // Grazing over the top misses; a ray pointing away misses.
        assert!(s.cast(&ray([0.0, 0.0, 4.01], [1.0, 1.0, 0.0]), 100.0, 0).hit.is_none());
        assert!(s.cast(&ray([0.0, 0.0, 2.0], [-1.0, -1.0, 0.0]), 100.0, 0).hit.is_none());
        // Out of range.
        assert!(s.cast(&ray([0.0, 0.0, 2.0], [1.0, 1.0, 0.0]), 9.9, 0).hit.is_none());
    }

    #[test]
    fn cylinder_hit_at_analytic_range() {
        let s = scene(
            vec![Prim { shape: Shape::Cylinder { c: [20.0, 5.0], r: 0.5, z0: 0.0, z1: 8.0 }, refl: 20 }],
            None,
        );
        // From the origin at elevation e towards the axis: the side is hit at (d - r)/cos(e).
        let e: f64 = 0.1;
        let d = libm::hypot(20.0, 5.0);
        let dir = [20.0 / d * libm::cos(e), 5.0 / d * libm::cos(e), libm::sin(e)];
        let h = s.cast(&ray([0.0, 0.0, 1.0], dir), 100.0, 0).hit.unwrap();
        assert!((h.t - (d - 0.5) / libm::cos(e)).abs() < 1e-12);
        assert!((h.n[0] + 20.0 / d).abs() < 1e-9 && h.n[2] == 0.0);
        // Off-axis by 0.3 m laterally: the chord geometry, 20 m ahead along x.
        let h = s.cast(&ray([0.0, 5.3, 3.0], [1.0, 0.0, 0.0]), 100.0, 0).hit.unwrap();
        assert!((h.t - (20.0 - libm::sqrt(0.25 - 0.09))).abs() < 1e-12);
        // Top cap from above.
        let h = s.cast(&ray([20.1, 5.0, 20.0], [0.0, 0.0, -1.0]), 100.0, 0).hit.unwrap();
        assert!((h.t - 12.0).abs() < 1e-12 && h.n == [0.0, 0.0, 1.0]);
    }

    #[test]
    fn ground_plane_and_tilted_ground_hit_exactly() {
        // A plane z = 0.1 x - 0.05 y + 1 sampled on the heightfield is represented exactly.
        let g = Heightfield::new(-40.0, -40.0, 1.0, 80, 80, 15, |x, y| 0.1 * x - 0.05 * y + 1.0);
        let s = scene(vec![], Some(g));
        for (o, d) in [
            ([0.3, 0.7, 5.0], [1.0, 0.2, -0.3]),
            ([-10.0, 3.0, 2.5], [-0.3, -1.0, -0.05]),
            ([1.0, 1.0, 9.0], [0.0, 0.0, -1.0]),
        ] {
            let r = ray(o, d);
            let h = s.cast(&r, 200.0, 0).hit.unwrap();
            // Analytic: oz + t dz = 0.1 (ox + t dx) - 0.05 (oy + t dy) + 1.
            let t = (0.1 * r.o[0] - 0.05 * r.o[1] + 1.0 - r.o[2]) / (r.d[2] - 0.1 * r.d[0] + 0.05 * r.d[1]);
            assert!((h.t - t).abs() < 1e-9, "{} vs {t}", h.t);
            let n = normalize([-0.1, 0.05, 1.0]);
            assert!((0..3).all(|a| (h.n[a] - n[a]).abs() < 1e-12));
        }
        // Looking up never hits the ground.
        assert!(s.cast(&ray([0.0, 0.0, 5.0], [1.0, 0.0, 0.2]), 200.0, 0).hit.is_none());
    }

    #[test]
    fn nearest_of_several_and_crowns_let_some_rays_through() {
        let wall = Prim { shape: Shape::boxed([30.0, 0.0, 5.0], [1.0, 40.0, 10.0], 0.0), refl: 50 };
        let crown = Prim { shape: Shape::Crown { c: [15.0, 0.0, 3.0], r: 2.0, density: 0.4 }, refl: 25 };
        let s = scene(vec![wall, crown], None);
        let (mut stopped, mut partial, mut through) = (0, 0, 0);
        let n = 4000;
        for key in 0..n {
            let r = s.cast(&ray([0.0, 0.0, 3.0], [1.0, 0.0, 0.0]), 100.0, key);
            let h = r.hit.unwrap();
            if h.prim == 1 {
                assert!(h.t >= 13.0 && h.t <= 17.0);
                stopped += 1;
            } else {
                assert!((h.t - 29.5).abs() < 1e-12, "{h:?}");
                through += 1;
                if let Some(p) = r.partial {
                    assert!(p.t >= 13.0 && p.t <= 17.0 && p.fraction < 1.0);
                    partial += 1;
                }
            }
            // Deterministic per key.
            assert_eq!(r, s.cast(&ray([0.0, 0.0, 3.0], [1.0, 0.0, 0.0]), 100.0, key));
        }
        // A 4 m chord at 0.4 leaves/m: P(leaf) = 1 - exp(-1.6) = 0.80; 40 % of leaves stop the beam.
        let p_leaf = 1.0 - libm::exp(-1.6);
        let exp_stop = n as f64 * p_leaf * 0.4;
        let exp_partial = n as f64 * p_leaf * 0.6;
        assert!((stopped as f64 - exp_stop).abs() < 5.0 * libm::sqrt(exp_stop), "{stopped} vs {exp_stop}");
        assert!(
            (partial as f64 - exp_partial).abs() < 5.0 * libm::sqrt(exp_partial),
            "{partial} vs {exp_partial}"
        );
        assert_eq!(stopped + through, n as usize);
    }

    #[test]
    fn grid_traversal_finds_hits_in_far_cells_in_every_direction() {
        // A ring of poles at 30 m; rays in 360 directions each hit the analytic range.
        let mut prims = Vec::new();
        for k in 0..36 {
            let a = k as f64 * 10.0f64.to_radians();
            prims.push(Prim {
                shape: Shape::Cylinder {
                    c: [30.0 * libm::cos(a), 30.0 * libm::sin(a)],
                    r: 1.0,
                    z0: -5.0,
                    z1: 5.0,
                },
                refl: 10,
            });
        }
        let s = scene(prims, None);
        for k in 0..36 {
            let a = k as f64 * 10.0f64.to_radians();
            let h = s.cast(&ray([0.0, 0.0, 0.0], [libm::cos(a), libm::sin(a), 0.0]), 100.0, 0).hit.unwrap();
            assert!((h.t - 29.0).abs() < 1e-12 && h.prim == k, "{k} {h:?}");
        }
    }
}
