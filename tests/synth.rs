//! Synthetic LiDAR scans with exact ground truth: the pixel rays of a [`RangeImageLayout`]
//! ray-cast against planes and vertical cylinders, with optional Gaussian range noise from a
//! seeded generator written here (so results never change with a dependency's version).
//!
//! Used by the Ring FALS tests and by the `ring_fals` benchmark (which includes this file by
//! path: it depends on nothing but `loglio_core` and std).
#![allow(dead_code)]

use loglio_core::range_image::RangeImageLayout;
use loglio_core::scan::ScanPoint;

/// SplitMix64: small, fast, and fixed forever.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    /// A generator from a seed.
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Standard normal (Box-Muller).
    pub fn gauss(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// VLP-32C beam elevations, degrees, highest first (row 0 = highest).
pub const VLP32C_ELEVATIONS_DEG: [f64; 32] = [
    15.0, 10.333, 7.0, 4.667, 3.333, 2.333, 1.667, 1.333, 1.0, 0.667, 0.333, 0.0, -0.333, -0.667, -1.0,
    -1.333, -1.667, -2.0, -2.333, -2.667, -3.0, -3.333, -3.667, -4.0, -4.667, -5.333, -6.148, -7.254, -8.843,
    -11.31, -15.639, -25.0,
];

/// A VLP-32C at 10 Hz: 32 x 1800, columns clockwise.
pub fn vlp32c_layout() -> RangeImageLayout {
    let el: Vec<f32> = VLP32C_ELEVATIONS_DEG.iter().map(|d| d.to_radians() as f32).collect();
    RangeImageLayout::from_elevations(&el, 1800, true).unwrap()
}

/// An OS1-16-like sensor: 16 beams evenly over +-16.6 degrees, 1024 columns clockwise.
pub fn os1_16_layout() -> RangeImageLayout {
    let el: Vec<f32> = (0..16).map(|i| (16.6 - 33.2 * i as f64 / 15.0).to_radians() as f32).collect();
    RangeImageLayout::from_elevations(&el, 1024, true).unwrap()
}

/// A surface of the synthetic world.
#[derive(Clone, Copy, Debug)]
pub enum Shape {
    /// Points `p` with `n . p = d` (`n` unit) inside the box `lo..=hi`.
    Plane { n: [f64; 3], d: f64, lo: [f64; 3], hi: [f64; 3] },
    /// Vertical cylinder around the axis through (x, y), `z` from `z[0]` to `z[1]`.
    Cylinder { axis: [f64; 2], radius: f64, z: [f64; 2] },
}

const EVERYWHERE: ([f64; 3], [f64; 3]) = ([-1e9; 3], [1e9; 3]);

impl Shape {
    /// An unbounded plane with unit normal `n` through the point `p`.
    pub fn plane(n: [f64; 3], p: [f64; 3]) -> Self {
        let n = unit(n);
        Shape::Plane { n, d: dot(n, p), lo: EVERYWHERE.0, hi: EVERYWHERE.1 }
    }

    /// Nearest hit along the unit ray `v` from the origin: distance and unit normal facing the
    /// origin.
    pub fn cast(&self, v: [f64; 3]) -> Option<(f64, [f64; 3])> {
        match *self {
            Shape::Plane { n, d, lo, hi } => {
                let nv = dot(n, v);
                if nv.abs() < 1e-12 {
                    return None;
                }
                let t = d / nv;
                let p = scale(v, t);
                let inside = (0..3).all(|i| p[i] >= lo[i] && p[i] <= hi[i]);
                if t > 0.0 && inside { Some((t, if nv > 0.0 { scale(n, -1.0) } else { n })) } else { None }
            }
            Shape::Cylinder { axis, radius, z } => {
                // |(t v_xy) - axis|^2 = radius^2
                let (a, b) = (v[0] * v[0] + v[1] * v[1], -2.0 * (v[0] * axis[0] + v[1] * axis[1]));
                let c = axis[0] * axis[0] + axis[1] * axis[1] - radius * radius;
                let disc = b * b - 4.0 * a * c;
                if a < 1e-12 || disc < 0.0 {
                    return None;
                }
                let t = (-b - disc.sqrt()) / (2.0 * a);
                let p = scale(v, t);
                if t <= 0.0 || p[2] < z[0] || p[2] > z[1] {
                    return None;
                }
                Some((t, unit([p[0] - axis[0], p[1] - axis[1], 0.0])))
            }
        }
    }
}

/// One rendered scan: a point per pixel that saw a surface, with the exact normal.
#[derive(Clone, Debug, Default)]
pub struct Render {
    /// The points, row-major over the image.
    pub points: Vec<ScanPoint>,
    /// Exact unit normal of each point's surface at the hit, facing the sensor.
    pub truth: Vec<[f64; 3]>,
    /// Index of the shape each point hit.
    pub shape: Vec<usize>,
    /// Exact (noise-free) range of each point.
    pub range: Vec<f64>,
}

/// The benches' VLP-32C street scan: 1 cm of range noise, 2 % of the returns missing, in
/// firing order (column by column), as a spinning sensor sends it.
pub fn vlp32c_street_in_firing_order() -> Vec<ScanPoint> {
    let layout = vlp32c_layout();
    let mut drop = Rng::new(7 ^ 0xd0);
    let keep: Vec<bool> = (0..layout.pixels()).map(|_| drop.uniform() > 0.02).collect();
    let cols = layout.cols();
    let mut points =
        render(&layout, &street_scene(), 0.01, &mut Rng::new(7), |r, c| keep[r * cols + c]).points;
    points.sort_by_key(|p| (p.col, p.row));
    points
}

/// Ray-casts every pixel of `layout`; `sigma` is the range noise (metres); pixels for which
/// `keep(row, col)` is false get no point (missing returns).
pub fn render(
    layout: &RangeImageLayout,
    shapes: &[Shape],
    sigma: f64,
    rng: &mut Rng,
    keep: impl Fn(usize, usize) -> bool,
) -> Render {
    let mut out = Render::default();
    for row in 0..layout.rows() {
        for col in 0..layout.cols() {
            let v = layout.direction(row, col);
            let hit = shapes
                .iter()
                .enumerate()
                .filter_map(|(i, s)| s.cast(v).map(|(t, n)| (t, n, i)))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            let Some((t, n, i)) = hit else { continue };
            if !(0.5..=200.0).contains(&t) || !keep(row, col) {
                continue;
            }
            let r = t + sigma * rng.gauss();
            let p = scale(v, r);
            out.points.push(ScanPoint {
                xyz: [p[0] as f32, p[1] as f32, p[2] as f32],
                row: row as u16,
                col: col as u16,
                ..Default::default()
            });
            out.truth.push(n);
            out.shape.push(i);
            out.range.push(t);
        }
    }
    out
}

/// Angle in degrees between a computed and a true normal.
pub fn angle_deg(a: [f32; 3], b: [f64; 3]) -> f64 {
    let a = [a[0] as f64, a[1] as f64, a[2] as f64];
    let c = dot(a, b) / (dot(a, a).sqrt() * dot(b, b).sqrt());
    c.clamp(-1.0, 1.0).acos().to_degrees()
}

/// Median of a non-empty list (the upper median for even lengths).
pub fn median(v: &[f64]) -> f64 {
    assert!(!v.is_empty(), "median of nothing");
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Unit vector at azimuth `az` and elevation `el` (radians).
pub fn ray(az: f64, el: f64) -> [f64; 3] {
    [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()]
}

pub fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}

pub fn unit(a: [f64; 3]) -> [f64; 3] {
    scale(a, 1.0 / dot(a, a).sqrt())
}

pub fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

/// A plane seen along the ray at azimuth `az`, elevation `el`, at range `range`, whose normal is
/// tilted by `incidence` (radians) from the reversed ray, toward `tilt_dir` (radians: 0 tilts in
/// azimuth, pi/2 in elevation).
pub fn plane_at(az: f64, el: f64, range: f64, incidence: f64, tilt_dir: f64) -> (Shape, [f64; 3]) {
    let v = ray(az, el);
    let t_az = [-az.sin(), az.cos(), 0.0];
    let t_el = cross(v, t_az);
    let t = unit([
        tilt_dir.cos() * t_az[0] + tilt_dir.sin() * t_el[0],
        tilt_dir.cos() * t_az[1] + tilt_dir.sin() * t_el[1],
        tilt_dir.cos() * t_az[2] + tilt_dir.sin() * t_el[2],
    ]);
    let n = unit([
        -v[0] * incidence.cos() + t[0] * incidence.sin(),
        -v[1] * incidence.cos() + t[1] * incidence.sin(),
        -v[2] * incidence.cos() + t[2] * incidence.sin(),
    ]);
    (Shape::plane(n, scale(v, range)), n)
}

/// A street-like scene for benchmarks: ground 1.8 m below, walls both sides and ahead, poles, a
/// box-like car; every pixel above the horizon that misses everything has no return.
pub fn street_scene() -> Vec<Shape> {
    let mut s = vec![
        Shape::plane([0.0, 0.0, 1.0], [0.0, 0.0, -1.8]),
        Shape::Plane { n: [0.0, 1.0, 0.0], d: 8.0, lo: [-60.0, -1e9, -5.0], hi: [60.0, 1e9, 12.0] },
        Shape::Plane { n: [0.0, 1.0, 0.0], d: -6.0, lo: [-60.0, -1e9, -5.0], hi: [60.0, 1e9, 9.0] },
        Shape::Plane { n: [1.0, 0.0, 0.0], d: 45.0, lo: [-1e9, -6.0, -5.0], hi: [1e9, 8.0, 20.0] },
        Shape::Plane { n: [1.0, 0.0, 0.0], d: 4.0, lo: [-1e9, -3.5, -1.8], hi: [1e9, -1.7, -0.3] },
        Shape::Plane { n: [0.0, 1.0, 0.0], d: -1.7, lo: [4.0, -1e9, -1.8], hi: [8.5, 1e9, -0.3] },
    ];
    for i in 0..12 {
        let x = -30.0 + 6.0 * i as f64;
        s.push(Shape::Cylinder { axis: [x, 5.0], radius: 0.15, z: [-1.8, 4.0] });
    }
    s
}
