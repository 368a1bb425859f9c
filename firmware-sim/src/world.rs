//! Procedural, seeded worlds: an outdoor town, an indoor hall and a long corridor.
//!
//! - **Town** (vehicle and drone scenarios): rolling ground with grades up to ~9 % (see
//!   [`Terrain::town`]), a road looping through it (the vehicle trajectory's path) with raised
//!   sidewalks whose edges are 15 cm kerbs, buildings of 6-30 m with a ring of 25-40 m towers
//!   around the drone's courtyard, garden walls, street poles with retroreflective signs, trees
//!   whose crowns let some rays through, and parked cars (two boxes each).
//! - **Hall** (handheld walk and fast rotation): a 60 m x 36 m x 8 m hall with pilasters along
//!   the walls, a grid of columns, roof beams, shelving racks, crates, a partition wall and a
//!   mezzanine on legs.
//! - **Corridor**: a 610 m corridor with a constant 2.4 m x 3.0 m cross-section and smooth walls,
//!   floor and ceiling; nothing along it tells a scan matcher where along the axis it is. Its end
//!   walls are more than 200 m (the longest sensor range) from every point of the drive.
//!
//! Everything is drawn from [`SplitMix64`] streams of the seed; objects never come closer to the
//! trajectories than a clearance (the vehicle's road, the walker's loop), and the same seed
//! always builds the same world.

use crate::raycast::{Heightfield, Prim, Scene, Shape};
use crate::rng::SplitMix64;
use crate::terrain::Terrain;
use crate::trajectory::{DRONE_START, ROTATION_SPOT, Trajectory};

/// Which world.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SceneKind {
    /// The outdoor town.
    Town,
    /// The indoor hall.
    Hall,
    /// The long featureless corridor.
    Corridor,
    /// The town's kind of streets along the long drive's 3.1 km loop, over a square of
    /// 2 x [`LONG_HALF`] metres (buildings only within [`LONG_BAND`] of the road).
    LongLoop,
}

/// Corridor geometry: half width, height and x extent (metres).
pub const CORRIDOR_HALF_WIDTH: f64 = 1.2;
/// Corridor ceiling height.
pub const CORRIDOR_HEIGHT_M: f64 = 3.0;
/// Corridor x extent (start, end).
pub const CORRIDOR_X: [f64; 2] = [-220.0, 390.0];
/// Hall interior half extents (x, y) and height.
pub const HALL: [f64; 3] = [30.0, 18.0, 8.0];
/// Half size of the town's square (metres around the origin).
pub const TOWN_HALF: f64 = 180.0;
/// Half size of the long drive's square (metres around the origin).
pub const LONG_HALF: f64 = 530.0;
/// Along the long loop, nothing is built farther than this from the road (metres): beyond it a
/// 100 m LiDAR sees little, and the world stays small.
pub const LONG_BAND: f64 = 70.0;
/// Road half width in the town (the sidewalk kerbs start here).
pub const ROAD_HALF_WIDTH: f64 = 4.0;

/// A built world: its geometry and how it was made.
#[derive(Clone, Debug)]
pub struct World {
    /// Which world.
    pub kind: SceneKind,
    /// The seed it was built from.
    pub seed: u64,
    /// The ground function (flat indoors).
    pub terrain: Terrain,
    /// The geometry with its acceleration grid.
    pub scene: Scene,
}

/// Samples (x, y, yaw) along a trajectory every `dt` seconds over [0, `until`].
fn path_samples(traj: &Trajectory, until: f64, dt: f64) -> Vec<[f64; 3]> {
    let n = (until / dt) as usize;
    (0..=n)
        .map(|i| {
            let k = traj.eval(i as f64 * dt);
            let f = k.rotation * nalgebra::Vector3::x();
            [k.position.x, k.position.y, libm::atan2(f.y, f.x)]
        })
        .collect()
}

/// Smallest xy distance from a shape's footprint to any path sample.
pub fn clearance(shape: &Shape, path: &[[f64; 3]]) -> f64 {
    path.iter().map(|p| shape.xy_distance([p[0], p[1]])).fold(f64::INFINITY, f64::min)
}

/// Whether two footprints (as boxes) overlap, with a margin, by separating axes.
pub fn footprints_overlap(a: &Shape, b: &Shape, margin: f64) -> bool {
    let rect = |s: &Shape| -> ([f64; 2], [f64; 2], f64, f64) {
        match *s {
            Shape::Box { c, h, cos, sin } => ([c[0], c[1]], [h[0] + margin, h[1] + margin], cos, sin),
            Shape::Cylinder { c, r, .. } => (c, [r + margin, r + margin], 1.0, 0.0),
            Shape::Crown { c, r, .. } => ([c[0], c[1]], [r + margin, r + margin], 1.0, 0.0),
        }
    };
    let (ca, ha, cosa, sina) = rect(a);
    let (cb, hb, cosb, sinb) = rect(b);
    let axes = [[cosa, sina], [-sina, cosa], [cosb, sinb], [-sinb, cosb]];
    let d = [cb[0] - ca[0], cb[1] - ca[1]];
    for ax in axes {
        let proj = |h: [f64; 2], cos: f64, sin: f64| {
            h[0] * (cos * ax[0] + sin * ax[1]).abs() + h[1] * (-sin * ax[0] + cos * ax[1]).abs()
        };
        let dist = (d[0] * ax[0] + d[1] * ax[1]).abs();
        if dist > proj(ha, cosa, sina) + proj(hb, cosb, sinb) {
            return false;
        }
    }
    true
}

struct Builder {
    prims: Vec<Prim>,
    rng: SplitMix64,
}

impl Builder {
    fn push(&mut self, shape: Shape, refl: u8) {
        self.prims.push(Prim { shape, refl });
    }
}

impl World {
    /// Builds a world from its seed. Nothing is placed in the way of the trajectories that move
    /// through it (the town keeps clear of the vehicle's road and the drone's courtyard, the hall
    /// of the walking loop and the rotation spot).
    pub fn build(kind: SceneKind, seed: u64) -> World {
        match kind {
            SceneKind::Town => town(seed),
            SceneKind::Hall => hall(seed),
            SceneKind::Corridor => corridor(seed),
            SceneKind::LongLoop => long_loop(seed),
        }
    }

    /// Ground height under (x, y) (the terrain function; 0 indoors).
    pub fn ground_height(&self, x: f64, y: f64) -> f64 {
        self.terrain.height(x, y)
    }
}

fn town(seed: u64) -> World {
    let (prims, terrain) = town_prims(seed);
    town_scene(prims, terrain, seed, TOWN_HALF, SceneKind::Town)
}

fn long_loop(seed: u64) -> World {
    let terrain = Terrain::town();
    let road =
        path_samples(&Trajectory::Long { terrain: terrain.clone() }, crate::trajectory::LONG_LAP_S, 0.125);
    let streets = Streets { half: LONG_HALF, band: LONG_BAND, court: None, walls: 1400 };
    let prims = street_prims(seed, &terrain, &road, &streets);
    town_scene(prims, terrain, seed, LONG_HALF, SceneKind::LongLoop)
}

impl World {
    /// The town of `seed` without the primitives `remove` selects (the traffic scenario clears
    /// a cross street and the actors' way); everything else is the same town.
    pub fn town_without(seed: u64, remove: impl Fn(&Prim) -> bool) -> World {
        let (mut prims, terrain) = town_prims(seed);
        prims.retain(|p| !remove(p));
        town_scene(prims, terrain, seed, TOWN_HALF, SceneKind::Town)
    }
}

fn town_scene(prims: Vec<Prim>, terrain: Terrain, seed: u64, half: f64, kind: SceneKind) -> World {
    let g = Heightfield::new(-half, -half, 1.0, (2.0 * half) as usize, (2.0 * half) as usize, 18, |x, y| {
        terrain.height(x, y)
    });
    let scene = Scene::new(prims, Some(g), seed, [-half, -half], [half, half], 4.0);
    World { kind, seed, terrain, scene }
}

fn town_prims(seed: u64) -> (Vec<Prim>, Terrain) {
    let terrain = Terrain::town();
    let road = path_samples(&Trajectory::Vehicle { terrain: terrain.clone() }, 95.0, 0.25);
    let streets = Streets { half: TOWN_HALF, band: f64::INFINITY, court: Some(DRONE_START), walls: 160 };
    let prims = street_prims(seed, &terrain, &road, &streets);
    (prims, terrain)
}

/// How [`street_prims`] builds around a road.
struct Streets {
    /// Half size of the square the buildings' grid covers, metres.
    half: f64,
    /// No building farther than this from the road, metres.
    band: f64,
    /// The drone's courtyard (cleared and ringed by towers), if any.
    court: Option<[f64; 2]>,
    /// How many garden walls are tried.
    walls: usize,
}

/// The town's streets along `road` (samples of x, y, heading): kerbs, street furniture, parked
/// cars, buildings and garden walls.
fn street_prims(seed: u64, terrain: &Terrain, road: &[[f64; 3]], streets: &Streets) -> Vec<Prim> {
    let mut b = Builder { prims: Vec::new(), rng: SplitMix64::new(seed, 1) };
    let ground_range = |s: &Shape| -> (f64, f64) {
        let (lo, hi) = s.bounds();
        let mut r = (f64::INFINITY, f64::NEG_INFINITY);
        for (x, y) in [
            (lo[0], lo[1]),
            (hi[0], lo[1]),
            (lo[0], hi[1]),
            (hi[0], hi[1]),
            ((lo[0] + hi[0]) * 0.5, (lo[1] + hi[1]) * 0.5),
        ] {
            let z = terrain.height(x, y);
            r = (r.0.min(z), r.1.max(z));
        }
        r
    };
    // Sidewalks (kerbs), every ~5 m of road on both sides.
    let mut arc = 0.0;
    let mut last = road[0];
    for p in road {
        arc += libm::hypot(p[0] - last[0], p[1] - last[1]);
        last = *p;
        if arc < 5.0 {
            continue;
        }
        arc = 0.0;
        for side in [-1.0, 1.0] {
            let (c, s) = (libm::cos(p[2]), libm::sin(p[2]));
            let off = side * (ROAD_HALF_WIDTH + 1.5);
            let (x, y) = (p[0] - s * off, p[1] + c * off);
            let foot = Shape::boxed([x, y, 0.0], [5.4, 3.0, 1.0], p[2]);
            if clearance(&foot, road) < ROAD_HALF_WIDTH - 0.4 {
                continue;
            }
            let (g0, g1) = ground_range(&foot);
            let (bot, top) = (g0 - 0.5, g1 + 0.15);
            b.push(Shape::boxed([x, y, (bot + top) * 0.5], [5.4, 3.0, top - bot], p[2]), 35);
        }
    }
    // Street furniture along the road: poles with signs, trees, parked cars.
    let mut placed: Vec<Shape> = Vec::new();
    let mut last = road[0];
    let mut next_pole = 12.0;
    let mut next_tree = 6.0;
    let mut next_car = 3.0;
    let mut dist = 0.0;
    for p in road {
        let step = libm::hypot(p[0] - last[0], p[1] - last[1]);
        dist += step;
        last = *p;
        let (c, s) = (libm::cos(p[2]), libm::sin(p[2]));
        let at = |off: f64| (p[0] - s * off, p[1] + c * off);
        if dist >= next_pole {
            next_pole = dist + 22.0 + 6.0 * b.rng.unit();
            let side = if b.rng.unit() < 0.5 { -1.0 } else { 1.0 };
            let (x, y) = at(side * 6.4);
            let cyl = Shape::Cylinder { c: [x, y], r: 0.12, z0: 0.0, z1: 1.0 };
            if clearance(&cyl, road) > ROAD_HALF_WIDTH + 1.0 {
                let g = terrain.height(x, y);
                let h = 6.0 + 2.0 * b.rng.unit();
                b.push(Shape::Cylinder { c: [x, y], r: 0.12, z0: g - 0.5, z1: g + h }, 30);
                // A lamp arm over the road.
                let (ax, ay) = at(side * 5.4);
                b.push(Shape::boxed([ax, ay, g + h - 0.1], [0.15, 2.0, 0.15], p[2]), 40);
                if b.rng.unit() < 0.6 {
                    // A retroreflective sign facing the traffic.
                    let (sx, sy) = at(side * 6.4 - side * 0.2);
                    b.push(Shape::boxed([sx, sy, g + 2.6], [0.05, 0.6, 0.6], p[2]), 200);
                }
                placed.push(cyl);
            }
        }
        if dist >= next_tree {
            next_tree = dist + 11.0 + 8.0 * b.rng.unit();
            let side = if b.rng.unit() < 0.5 { -1.0 } else { 1.0 };
            let (x, y) = at(side * (8.0 + 1.5 * b.rng.unit()));
            let trunk_r = 0.15 + 0.1 * b.rng.unit();
            let cyl = Shape::Cylinder { c: [x, y], r: trunk_r, z0: 0.0, z1: 1.0 };
            if clearance(&cyl, road) > ROAD_HALF_WIDTH + 2.5 {
                let g = terrain.height(x, y);
                let h = 2.8 + 1.5 * b.rng.unit();
                let r = 1.8 + 1.4 * b.rng.unit();
                let density = 0.25 + 0.3 * b.rng.unit();
                b.push(Shape::Cylinder { c: [x, y], r: trunk_r, z0: g - 0.5, z1: g + h + 0.5 * r }, 22);
                b.push(Shape::Crown { c: [x, y, g + h + 0.7 * r], r, density }, 28);
                placed.push(Shape::Cylinder { c: [x, y], r: 0.5 * r, z0: 0.0, z1: 1.0 });
            }
        }
        if dist >= next_car {
            next_car = dist + 6.5 + 4.0 * b.rng.unit();
            if b.rng.unit() < 0.55 {
                let side = if b.rng.unit() < 0.7 { -1.0 } else { 1.0 };
                let (x, y) = at(side * 3.15);
                let yaw = p[2] + 0.04 * (b.rng.unit() - 0.5);
                let body = Shape::boxed([x, y, 0.0], [4.4, 1.8, 1.0], yaw);
                if clearance(&body, road) > 2.1 && !placed.iter().any(|q| footprints_overlap(&body, q, 0.5)) {
                    let g = terrain.height(x, y);
                    let paint = 30 + (b.rng.unit() * 60.0) as u8;
                    b.push(Shape::boxed([x, y, g + 0.65], [4.4, 1.8, 0.7], yaw), paint);
                    let back = 0.3 * (b.rng.unit() - 0.5);
                    b.push(
                        Shape::boxed(
                            [x + back * libm::cos(yaw), y + back * libm::sin(yaw), g + 1.25],
                            [2.4, 1.6, 0.5],
                            yaw,
                        ),
                        12,
                    );
                    placed.push(body);
                }
            }
        }
    }
    // The drone's courtyard: a clear disc ringed by towers.
    let court_clear = 13.0;
    let mut buildings: Vec<Shape> = Vec::new();
    let n_towers = 7;
    if let Some(court) = streets.court {
        for k in 0..n_towers {
            let a = k as f64 * core::f64::consts::TAU / n_towers as f64 + 0.3 * b.rng.unit();
            let depth = 10.0 + 6.0 * b.rng.unit();
            let width = 9.0 + 5.0 * b.rng.unit();
            let r = court_clear + depth * 0.5 + 1.0;
            let (x, y) = (court[0] + r * libm::cos(a), court[1] + r * libm::sin(a));
            let foot = Shape::boxed([x, y, 0.0], [depth, width, 1.0], a);
            if clearance(&foot, road) < 9.0 || buildings.iter().any(|q| footprints_overlap(&foot, q, 1.0)) {
                continue;
            }
            let (g0, g1) = ground_range(&foot);
            let h = 25.0 + 15.0 * b.rng.unit();
            let refl = 55 + (b.rng.unit() * 25.0) as u8;
            b.push(
                Shape::boxed([x, y, (g0 - 0.5 + g1 + h) * 0.5], [depth, width, g1 + h - g0 + 0.5], a),
                refl,
            );
            buildings.push(foot);
        }
    }
    // Buildings on a jittered grid over the town, aligned with the nearest street.
    let spacing = 23.0;
    let half = streets.half;
    let clear_of_court =
        |foot: &Shape, margin: f64| streets.court.is_none_or(|c| foot.xy_distance(c) > margin);
    let n = (2.0 * half / spacing) as i32;
    for gj in 0..n {
        for gi in 0..n {
            let x = -half + (gi as f64 + 0.2 + 0.6 * b.rng.unit()) * spacing;
            let y = -half + (gj as f64 + 0.2 + 0.6 * b.rng.unit()) * spacing;
            if streets.band.is_finite()
                && clearance(&Shape::boxed([x, y, 0.0], [1.0; 3], 0.0), road) > streets.band
            {
                continue;
            }
            let (sx, sy) = (9.0 + 12.0 * b.rng.unit(), 9.0 + 12.0 * b.rng.unit());
            let height = 6.0 + 24.0 * b.rng.unit() * b.rng.unit() + 3.0 * b.rng.unit();
            let near = road.iter().min_by(|a, c| {
                libm::hypot(a[0] - x, a[1] - y)
                    .partial_cmp(&libm::hypot(c[0] - x, c[1] - y))
                    .unwrap_or(core::cmp::Ordering::Equal)
            });
            let yaw = match near {
                Some(p) if libm::hypot(p[0] - x, p[1] - y) < 45.0 => p[2],
                _ => b.rng.range(0.0, core::f64::consts::PI),
            };
            let refl = 45 + (b.rng.unit() * 40.0) as u8;
            let mut size = [sx, sy];
            let mut ok = false;
            for _ in 0..4 {
                let foot = Shape::boxed([x, y, 0.0], [size[0], size[1], 1.0], yaw);
                if clearance(&foot, road) >= 9.0
                    && clear_of_court(&foot, court_clear + 3.0)
                    && !buildings.iter().any(|q| footprints_overlap(&foot, q, 1.5))
                {
                    ok = true;
                    break;
                }
                size = [size[0] * 0.75, size[1] * 0.75];
            }
            if !ok || size[0] < 5.0 || size[1] < 5.0 {
                continue;
            }
            let foot = Shape::boxed([x, y, 0.0], [size[0], size[1], 1.0], yaw);
            let (g0, g1) = ground_range(&foot);
            b.push(
                Shape::boxed(
                    [x, y, (g0 - 0.5 + g1 + height) * 0.5],
                    [size[0], size[1], g1 + height - g0 + 0.5],
                    yaw,
                ),
                refl,
            );
            // Some buildings have a rooftop structure.
            if b.rng.unit() < 0.4 {
                let rs = [size[0] * 0.3, size[1] * 0.3, 2.5];
                b.push(Shape::boxed([x, y, g1 + height + 1.25], rs, yaw), 40);
            }
            buildings.push(foot);
        }
    }
    // Garden walls between buildings and the road.
    for _ in 0..streets.walls {
        let x = b.rng.range(-half, half);
        let y = b.rng.range(-half, half);
        let len = 6.0 + 12.0 * b.rng.unit();
        let yaw = b.rng.range(0.0, core::f64::consts::PI);
        let foot = Shape::boxed([x, y, 0.0], [len, 0.25, 1.0], yaw);
        let cl = clearance(&foot, road);
        if !(7.0..20.0).contains(&cl)
            || !clear_of_court(&foot, court_clear + 1.0)
            || buildings.iter().any(|q| footprints_overlap(&foot, q, 0.5))
        {
            continue;
        }
        let (g0, g1) = ground_range(&foot);
        let h = 1.2 + 1.2 * b.rng.unit();
        b.push(Shape::boxed([x, y, (g0 - 0.5 + g1 + h) * 0.5], [len, 0.25, g1 + h - g0 + 0.5], yaw), 40);
        buildings.push(foot);
    }
    b.prims
}

fn hall(seed: u64) -> World {
    let mut b = Builder { prims: Vec::new(), rng: SplitMix64::new(seed, 2) };
    let [hx, hy, hz] = HALL;
    let mut keep = path_samples(&Trajectory::Handheld, 90.0, 0.1);
    keep.extend(path_samples(&Trajectory::FastRotation, 60.0, 0.1));
    keep.push([ROTATION_SPOT[0], ROTATION_SPOT[1], 0.0]);
    let t = 0.3;
    // Shell: floor, ceiling, walls.
    b.push(Shape::boxed([0.0, 0.0, -t * 0.5], [2.0 * hx + 2.0 * t, 2.0 * hy + 2.0 * t, t], 0.0), 30);
    b.push(Shape::boxed([0.0, 0.0, hz + t * 0.5], [2.0 * hx + 2.0 * t, 2.0 * hy + 2.0 * t, t], 0.0), 45);
    for s in [-1.0, 1.0] {
        b.push(Shape::boxed([s * (hx + t * 0.5), 0.0, hz * 0.5], [t, 2.0 * hy, hz], 0.0), 55);
        b.push(Shape::boxed([0.0, s * (hy + t * 0.5), hz * 0.5], [2.0 * hx, t, hz], 0.0), 55);
    }
    // Pilasters along the walls every 6 m, a door recess pattern broken by a hashed skip.
    let mut x = -hx + 3.0;
    while x < hx - 1.0 {
        for s in [-1.0, 1.0] {
            if b.rng.unit() < 0.85 {
                b.push(Shape::boxed([x, s * (hy - 0.2), hz * 0.5], [0.5, 0.4, hz], 0.0), 60);
            }
        }
        x += 6.0;
    }
    let mut y = -hy + 3.0;
    while y < hy - 1.0 {
        for s in [-1.0, 1.0] {
            if b.rng.unit() < 0.85 {
                b.push(Shape::boxed([s * (hx - 0.2), y, hz * 0.5], [0.4, 0.5, hz], 0.0), 60);
            }
        }
        y += 6.0;
    }
    // Roof beams across the hall.
    let mut x = -hx + 5.0;
    while x < hx {
        b.push(Shape::boxed([x, 0.0, hz - 0.35], [0.3, 2.0 * hy, 0.7], 0.0), 50);
        x += 6.0;
    }
    let mut placed: Vec<Shape> = Vec::new();
    // Columns on a 10 m x 9 m grid, except in the walkers' way.
    for ix in -2..=2 {
        for iy in -1..=1 {
            let c = [ix as f64 * 10.0 + 1.0, iy as f64 * 9.0];
            let s = Shape::Cylinder { c, r: 0.3, z0: 0.0, z1: hz };
            if clearance(&s, &keep) > 1.0 {
                b.push(s, 50);
                placed.push(s);
            }
        }
    }
    // Racks, crates, a partition wall and a mezzanine.
    let mut tries = 0;
    let mut racks = 0;
    while racks < 12 && tries < 400 {
        tries += 1;
        let len = 4.0 + 5.0 * b.rng.unit();
        let yaw = if b.rng.unit() < 0.5 { 0.0 } else { core::f64::consts::FRAC_PI_2 };
        let (x, y) = (b.rng.range(-hx + 3.0, hx - 3.0), b.rng.range(-hy + 3.0, hy - 3.0));
        let h = 2.0 + 2.5 * b.rng.unit();
        let s = Shape::boxed([x, y, h * 0.5], [len, 1.0, h], yaw);
        if clearance(&s, &keep) > 1.2 && !placed.iter().any(|q| footprints_overlap(&s, q, 0.8)) {
            let refl = 40 + (b.rng.unit() * 30.0) as u8;
            b.push(s, refl);
            placed.push(s);
            racks += 1;
        }
    }
    let mut crates = 0;
    tries = 0;
    while crates < 30 && tries < 600 {
        tries += 1;
        let (sx, sy, sz) = (0.6 + 0.9 * b.rng.unit(), 0.6 + 0.9 * b.rng.unit(), 0.3 + 1.3 * b.rng.unit());
        let (x, y) = (b.rng.range(-hx + 1.0, hx - 1.0), b.rng.range(-hy + 1.0, hy - 1.0));
        let s = Shape::boxed([x, y, sz * 0.5], [sx, sy, sz], b.rng.range(0.0, core::f64::consts::PI));
        if clearance(&s, &keep) > 0.8 && !placed.iter().any(|q| footprints_overlap(&s, q, 0.2)) {
            let refl = 20 + (b.rng.unit() * 60.0) as u8;
            b.push(s, refl);
            placed.push(s);
            crates += 1;
        }
    }
    for _ in 0..50 {
        let (x, y) = (b.rng.range(-hx + 6.0, hx - 6.0), b.rng.range(-hy + 4.0, hy - 4.0));
        let s = Shape::boxed([x, y, 1.5], [10.0, 0.2, 3.0], if b.rng.unit() < 0.5 { 0.0 } else { 1.2 });
        if clearance(&s, &keep) > 1.5 && !placed.iter().any(|q| footprints_overlap(&s, q, 1.0)) {
            b.push(s, 65);
            placed.push(s);
            break;
        }
    }
    for _ in 0..50 {
        let (x, y) = (b.rng.range(-hx + 6.0, hx - 6.0), b.rng.range(-hy + 5.0, hy - 5.0));
        let foot = Shape::boxed([x, y, 0.0], [10.0, 7.0, 1.0], 0.0);
        if clearance(&foot, &keep) > 1.5 && !placed.iter().any(|q| footprints_overlap(&foot, q, 0.5)) {
            b.push(Shape::boxed([x, y, 3.15], [10.0, 7.0, 0.3], 0.0), 45);
            for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
                b.push(Shape::Cylinder { c: [x + sx * 4.7, y + sy * 3.2], r: 0.12, z0: 0.0, z1: 3.0 }, 50);
            }
            placed.push(foot);
            break;
        }
    }
    let scene = Scene::new(b.prims, None, seed, [-hx - 1.0, -hy - 1.0], [hx + 1.0, hy + 1.0], 2.0);
    World { kind: SceneKind::Hall, seed, terrain: Terrain::flat(0.0), scene }
}

fn corridor(seed: u64) -> World {
    let mut b = Builder { prims: Vec::new(), rng: SplitMix64::new(seed, 3) };
    let [x0, x1] = CORRIDOR_X;
    let (len, cx) = (x1 - x0, 0.5 * (x0 + x1));
    let (w, h, t) = (CORRIDOR_HALF_WIDTH, CORRIDOR_HEIGHT_M, 0.3);
    b.push(Shape::boxed([cx, 0.0, -t * 0.5], [len, 2.0 * (w + t), t], 0.0), 25);
    b.push(Shape::boxed([cx, 0.0, h + t * 0.5], [len, 2.0 * (w + t), t], 0.0), 60);
    b.push(Shape::boxed([cx, w + t * 0.5, h * 0.5], [len, t, h], 0.0), 45);
    b.push(Shape::boxed([cx, -w - t * 0.5, h * 0.5], [len, t, h], 0.0), 45);
    b.push(Shape::boxed([x0 - t * 0.5, 0.0, h * 0.5], [t, 2.0 * w, h], 0.0), 45);
    b.push(Shape::boxed([x1 + t * 0.5, 0.0, h * 0.5], [t, 2.0 * w, h], 0.0), 45);
    let scene = Scene::new(b.prims, None, seed, [x0 - 2.0, -w - 2.0], [x1 + 2.0, w + 2.0], 4.0);
    World { kind: SceneKind::Corridor, seed, terrain: Terrain::flat(0.0), scene }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raycast::Ray;

    #[test]
    fn same_seed_same_world_and_trajectories_stay_clear() {
        for kind in [SceneKind::Town, SceneKind::Hall, SceneKind::Corridor] {
            let a = World::build(kind, 5);
            let b = World::build(kind, 5);
            assert_eq!(a.scene.prims(), b.scene.prims());
            if kind != SceneKind::Corridor {
                let c = World::build(kind, 6);
                assert_ne!(a.scene.prims(), c.scene.prims(), "{kind:?}");
            }
        }
        let town = World::build(SceneKind::Town, 5);
        assert!(town.scene.prims().len() > 300, "{}", town.scene.prims().len());
        let crowns = town.scene.prims().iter().filter(|p| matches!(p.shape, Shape::Crown { .. })).count();
        assert!(crowns > 10);
        // Nothing within 2 m of the vehicle's IMU footprint (cars park at 2.1 m+ from the centre line)
        // and above the road surface: cast from each path point straight up must be clear of
        // everything but lamp arms and crowns above 4 m.
        let traj = Trajectory::Vehicle { terrain: Terrain::town() };
        for i in 0..900 {
            let k = traj.eval(i as f64 * 0.1);
            let p = k.position;
            let r = town.scene.cast(&Ray { o: [p.x, p.y, p.z], d: [0.0, 0.0, 1.0] }, 3.0, i);
            assert!(r.hit.is_none(), "obstacle above the road at {p:?}: {r:?}");
            let down =
                town.scene.cast(&Ray { o: [p.x, p.y, p.z], d: [0.0, 0.0, -1.0] }, 10.0, i).hit.unwrap();
            assert!((down.t - 1.75).abs() < 0.01, "IMU height above the road {}", down.t);
        }
    }

    #[test]
    fn long_loop_is_built_along_its_whole_road_and_leaves_it_clear() {
        let a = World::build(SceneKind::LongLoop, 5);
        assert_eq!(a.kind, SceneKind::LongLoop);
        assert_eq!(a.scene.prims(), World::build(SceneKind::LongLoop, 5).scene.prims());
        let prims = a.scene.prims();
        assert!(prims.len() > 2000, "{}", prims.len());
        let traj = Trajectory::Long { terrain: Terrain::town() };
        let lap = crate::trajectory::LONG_LAP_S;
        // Along the whole loop: the road is clear above and the ground 1.75 m below, and within
        // 40 m on either side stand walls a LiDAR can hold on to (a horizontal ray hits within
        // 60 m one way or the other).
        let mut walled = 0;
        let n = 600;
        for i in 0..n {
            let k = traj.eval(lap * i as f64 / n as f64);
            let p = k.position;
            let key = i as u64;
            let r = a.scene.cast(&Ray { o: [p.x, p.y, p.z], d: [0.0, 0.0, 1.0] }, 3.0, key);
            assert!(r.hit.is_none(), "obstacle above the road at {p:?}: {r:?}");
            let down = a.scene.cast(&Ray { o: [p.x, p.y, p.z], d: [0.0, 0.0, -1.0] }, 10.0, key).hit.unwrap();
            assert!((down.t - 1.75).abs() < 0.01, "IMU height above the road {}", down.t);
            let left = k.rotation * nalgebra::Vector3::y();
            let side = |s: f64| {
                let d = [s * left.x, s * left.y, 0.0];
                a.scene.cast(&Ray { o: [p.x, p.y, p.z + 1.0], d }, 60.0, key).hit.is_some()
            };
            walled += usize::from(side(1.0) || side(-1.0));
        }
        assert!(walled * 10 > n * 8, "{walled} of {n} stretches see a wall beside the road");
    }

    #[test]
    fn grid_casting_equals_brute_force() {
        // Random rays from around the trajectories: the grid must return exactly what testing
        // every primitive returns (hit distance, primitive, partial leaf).
        for (kind, traj) in [
            (SceneKind::Town, Trajectory::Vehicle { terrain: Terrain::town() }),
            (SceneKind::Town, Trajectory::Drone { ground_z: 0.0 }),
            (SceneKind::Hall, Trajectory::Handheld),
            (SceneKind::Corridor, Trajectory::Corridor),
            (SceneKind::LongLoop, Trajectory::Long { terrain: Terrain::town() }),
        ] {
            let w = World::build(kind, 21);
            let mut rng = SplitMix64::new(4, 4);
            let mut hits = 0;
            for i in 0..3000u64 {
                let p = traj.eval(rng.range(0.0, 40.0)).position;
                let (az, el) = (rng.range(-3.2, 3.2), rng.range(-0.6, 0.4));
                let d = [libm::cos(el) * libm::cos(az), libm::cos(el) * libm::sin(az), libm::sin(el)];
                let r = Ray { o: [p.x, p.y, p.z], d };
                let a = w.scene.cast(&r, 150.0, i);
                let b = w.scene.cast_brute(&r, 150.0, i);
                assert_eq!(a, b, "{kind:?} ray {i}: {r:?}");
                hits += a.hit.is_some() as u32;
            }
            assert!(hits > 1000, "{kind:?}: {hits}");
        }
    }

    #[test]
    fn corridor_has_constant_cross_section() {
        let w = World::build(SceneKind::Corridor, 1);
        for x in [-150.0, 0.0, 77.7, 300.0] {
            for (d, t) in [
                ([0.0, 1.0, 0.0], CORRIDOR_HALF_WIDTH),
                ([0.0, -1.0, 0.0], CORRIDOR_HALF_WIDTH),
                ([0.0, 0.0, 1.0], 2.0),
                ([0.0, 0.0, -1.0], 1.0),
            ] {
                let h = w.scene.cast(&Ray { o: [x, 0.0, 1.0], d }, 100.0, 0).hit.unwrap();
                assert!((h.t - t).abs() < 1e-12);
            }
        }
    }
}
