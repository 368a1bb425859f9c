//! Criterion bench `voxel_map`: inserting a VLP-32C scan, and 5-NN queries against a kd-tree.
//!
//! The data is a synthetic street (ground, building facades, poles, trees, parked cars) seen by
//! a simulated VLP-32C (32 beams at the sensor's published elevations x 1800 azimuths = 57,600
//! rays, 1 cm range noise, normals within a few degrees of the surface normal, oriented towards
//! the sensor as Ring FALS gives them), downsampled on the 0.4 m map grid (centroid and averaged
//! normal per voxel), all generated deterministically here.
//!
//! - `insert_scan/vlp32c_0.4m`: one downsampled scan inserted into the map holding the previous
//!   scans of a 60-scan drive (1 m apart); each iteration inserts the next scan, the map is
//!   cleared (untimed) when the drive starts over. The figure is the mean per scan over the
//!   drive, creations, updates, evaluations and eviction sweeps included.
//! - `knn5_10k/*`: 10,000 queries (a scan from a pose 5 cm and 0.5 degrees off, in scan order)
//!   for their 5 nearest points within 0.4 m, against a map of at least 1,000,000 points built
//!   by driving the street: `VoxelMap::knn` one query at a time, `VoxelMap::knn_many` (the same
//!   results, pipelined; and as the association asks, 1 m bound in chunks of 64), and kiddo's immutable and mutable kd-trees holding exactly the map's
//!   points, built outside the timed part; results are checked equal to kiddo's before timing.
//! - `surfel/*`: the large surfel of each query's 5 nearest voxels, the plane fit of their 5
//!   nearest points (one at a time and `PLANE_LANES` at a time), and one 3x3 eigen-analysis.
//! - `downsample/vlp32c_0.4m/*`: the odometry's [`VoxelDownsampler`] on one raw scan (57,600
//!   returns with their normals, in the sensor's column order): `warm` with everything in the
//!   caches, `cold` after 64 MiB of other data went through them (as the map does between scans
//!   in the odometry). The scan is restored outside the timed part.

#[path = "../../host/src/machine.rs"]
mod machine;

use std::collections::HashMap;
use std::hint::black_box;
use std::num::NonZero;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use kiddo::kd_tree::KdTree;
use kiddo::leaf_strategies::VecOfArrays;
use kiddo::{Eytzinger, ImmutableKdTree, SquaredEuclidean};
use loglio_core::downsample::{DownsampleConfig, VoxelDownsampler};
use loglio_core::scan::ScanPoint;
use loglio_core::voxel_map::{IndexSlot, KnnQuery, MapConfig, MapPoint, Neighbours, Voxel, VoxelMap};

/// VLP-32C beam elevations, degrees (from the sensor's manual).
const VLP32C_ELEVATIONS: [f64; 32] = [
    -25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0, -2.667,
    -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333, 1.667, 2.333, 3.333,
    4.667, 7.0, 10.333, 15.0,
];
const COLUMNS: usize = 1800;
const MAX_RANGE: f64 = 100.0;
const SENSOR_HEIGHT: f64 = 1.8;

struct Rng(u64);
impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn gauss(&mut self) -> f64 {
        let (u, v) = (self.uniform().max(1e-300), self.uniform());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

#[derive(Clone, Copy)]
enum Prim {
    /// Axis-aligned box: min, max.
    Box([f64; 3], [f64; 3]),
    /// Vertical cylinder: centre x, y, radius, z range.
    Cylinder(f64, f64, f64, f64, f64),
    /// Sphere: centre, radius.
    Sphere([f64; 3], f64),
}

impl Prim {
    /// Horizontal bounding circle (centre, radius) for culling.
    fn bound(&self) -> ([f64; 2], f64) {
        match *self {
            Prim::Box(a, b) => {
                let c = [(a[0] + b[0]) / 2.0, (a[1] + b[1]) / 2.0];
                (c, ((b[0] - a[0]).hypot(b[1] - a[1])) / 2.0)
            }
            Prim::Cylinder(x, y, r, _, _) => ([x, y], r),
            Prim::Sphere(c, r) => ([c[0], c[1]], r),
        }
    }

    /// Nearest hit distance along the unit ray and the surface normal there.
    fn hit(&self, o: [f64; 3], d: [f64; 3]) -> Option<(f64, [f64; 3])> {
        match *self {
            Prim::Box(lo, hi) => {
                let (mut t0, mut t1, mut axis) = (0.0f64, f64::INFINITY, 0usize);
                for a in 0..3 {
                    if d[a].abs() < 1e-12 {
                        if o[a] < lo[a] || o[a] > hi[a] {
                            return None;
                        }
                        continue;
                    }
                    let (mut ta, mut tb) = ((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]);
                    if ta > tb {
                        std::mem::swap(&mut ta, &mut tb);
                    }
                    if ta > t0 {
                        t0 = ta;
                        axis = a;
                    }
                    t1 = t1.min(tb);
                    if t0 > t1 {
                        return None;
                    }
                }
                let mut n = [0.0; 3];
                n[axis] = -d[axis].signum();
                (t0 > 0.0).then_some((t0, n))
            }
            Prim::Cylinder(cx, cy, r, z0, z1) => {
                let (ox, oy) = (o[0] - cx, o[1] - cy);
                let a = d[0] * d[0] + d[1] * d[1];
                if a < 1e-12 {
                    return None;
                }
                let b = ox * d[0] + oy * d[1];
                let c = ox * ox + oy * oy - r * r;
                let disc = b * b - a * c;
                if disc < 0.0 {
                    return None;
                }
                let t = (-b - disc.sqrt()) / a;
                let z = o[2] + t * d[2];
                if t <= 0.0 || z < z0 || z > z1 {
                    return None;
                }
                let (hx, hy) = (ox + t * d[0], oy + t * d[1]);
                Some((t, [hx / r, hy / r, 0.0]))
            }
            Prim::Sphere(c, r) => {
                let oc = [o[0] - c[0], o[1] - c[1], o[2] - c[2]];
                let b = oc[0] * d[0] + oc[1] * d[1] + oc[2] * d[2];
                let cc = oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2] - r * r;
                let disc = b * b - cc;
                if disc < 0.0 {
                    return None;
                }
                let t = -b - disc.sqrt();
                if t <= 0.0 {
                    return None;
                }
                let h = [oc[0] + t * d[0], oc[1] + t * d[1], oc[2] + t * d[2]];
                Some((t, [h[0] / r, h[1] / r, h[2] / r]))
            }
        }
    }
}

/// A street along +x from -60 m to 560 m.
fn street() -> Vec<Prim> {
    let mut rng = Rng(2024);
    let mut p = Vec::new();
    let mut x = -60.0;
    while x < 560.0 {
        for side in [-1.0, 1.0] {
            let h = 8.0 + 12.0 * rng.uniform();
            let depth = 8.0 + 6.0 * rng.uniform();
            let (y0, y1) = if side > 0.0 { (11.0, 11.0 + depth) } else { (-11.0 - depth, -11.0) };
            p.push(Prim::Box([x, y0, 0.0], [x + 22.0 + 4.0 * rng.uniform(), y1, h]));
        }
        x += 30.0;
    }
    let mut x = -55.0;
    while x < 560.0 {
        for side in [-1.0, 1.0] {
            p.push(Prim::Cylinder(x, 7.5 * side, 0.12, 0.0, 6.0)); // pole
            let tx = x + 5.0;
            p.push(Prim::Cylinder(tx, 8.5 * side, 0.2, 0.0, 3.0)); // trunk
            p.push(Prim::Sphere([tx, 8.5 * side, 4.5], 1.8 + 0.6 * rng.uniform())); // crown
            if rng.uniform() < 0.6 {
                let cx = x + 1.0 + 3.0 * rng.uniform();
                let cy = 5.0 * side;
                p.push(Prim::Box([cx, cy - 0.9, 0.0], [cx + 4.5, cy + 0.9, 1.5])); // car
            }
        }
        x += 10.0;
    }
    p
}

/// One VLP-32C scan from `pos` (yaw `yaw`), world frame, with noisy oriented normals.
fn scan(scene: &[Prim], pos: [f64; 3], yaw: f64, seed: u64) -> Vec<([f64; 3], [f64; 3])> {
    let mut rng = Rng(seed);
    let near: Vec<Prim> = scene
        .iter()
        .copied()
        .filter(|p| {
            let (c, r) = p.bound();
            (c[0] - pos[0]).hypot(c[1] - pos[1]) - r < MAX_RANGE
        })
        .collect();
    let mut out = Vec::with_capacity(COLUMNS * 32);
    for col in 0..COLUMNS {
        let az = yaw + std::f64::consts::TAU * col as f64 / COLUMNS as f64;
        let (sa, ca) = az.sin_cos();
        for el in VLP32C_ELEVATIONS {
            let (se, ce) = el.to_radians().sin_cos();
            let d = [ce * ca, ce * sa, se];
            let mut best: Option<(f64, [f64; 3])> = None;
            if d[2] < 0.0 {
                best = Some((-pos[2] / d[2], [0.0, 0.0, 1.0])); // ground
            }
            for p in &near {
                if let Some((t, n)) = p.hit(pos, d)
                    && best.is_none_or(|b| t < b.0)
                {
                    best = Some((t, n));
                }
            }
            let Some((t, n)) = best else { continue };
            if !(1.0..MAX_RANGE).contains(&t) {
                continue;
            }
            let r = t + 0.01 * rng.gauss();
            let p = [pos[0] + r * d[0], pos[1] + r * d[1], pos[2] + r * d[2]];
            // A Ring FALS-like normal: a few degrees of noise, facing the sensor.
            let mut nn = [n[0] + 0.04 * rng.gauss(), n[1] + 0.04 * rng.gauss(), n[2] + 0.04 * rng.gauss()];
            if nn[0] * d[0] + nn[1] * d[1] + nn[2] * d[2] > 0.0 {
                nn = [-nn[0], -nn[1], -nn[2]];
            }
            let l = (nn[0] * nn[0] + nn[1] * nn[1] + nn[2] * nn[2]).sqrt();
            out.push((p, [nn[0] / l, nn[1] / l, nn[2] / l]));
        }
    }
    out
}

/// Voxel-grid downsampling on the map grid: centroid and normalised mean normal per voxel, in
/// order of first appearance.
fn downsample(points: &[([f64; 3], [f64; 3])], size: f64) -> Vec<MapPoint> {
    let mut cells: HashMap<[i64; 3], usize> = HashMap::new();
    let mut acc: Vec<([f64; 3], [f64; 3], f64)> = Vec::new();
    for (p, n) in points {
        let k = [(p[0] / size).floor() as i64, (p[1] / size).floor() as i64, (p[2] / size).floor() as i64];
        let i = *cells.entry(k).or_insert_with(|| {
            acc.push(([0.0; 3], [0.0; 3], 0.0));
            acc.len() - 1
        });
        let a = &mut acc[i];
        for j in 0..3 {
            a.0[j] += p[j];
            a.1[j] += n[j];
        }
        a.2 += 1.0;
    }
    acc.iter()
        .map(|(s, n, c)| {
            let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            MapPoint {
                xyz: [(s[0] / c) as f32, (s[1] / c) as f32, (s[2] / c) as f32],
                normal: (l > 1e-6).then(|| [(n[0] / l) as f32, (n[1] / l) as f32, (n[2] / l) as f32]),
            }
        })
        .collect()
}

fn storage(voxels: usize) -> (Vec<Voxel>, Vec<IndexSlot>) {
    (vec![Voxel::EMPTY; voxels], vec![IndexSlot::EMPTY; (2 * voxels).next_power_of_two()])
}

fn bench_insert(c: &mut Criterion) {
    let scene = street();
    let cfg = MapConfig::VLP32C;
    let drive: Vec<(Vec<MapPoint>, [f32; 3])> = (0..60)
        .map(|i| {
            let pos = [i as f64, 0.3 * (i as f64 * 0.1).sin(), SENSOR_HEIGHT];
            let raw = scan(&scene, pos, 0.01 * i as f64, i as u64);
            let ds = downsample(&raw, f64::from(cfg.voxel_size));
            (ds, [pos[0] as f32, pos[1] as f32, pos[2] as f32])
        })
        .collect();
    let raw0 = scan(&scene, [0.0, 0.0, SENSOR_HEIGHT], 0.0, 0).len();
    let mean_pts = drive.iter().map(|d| d.0.len()).sum::<usize>() / drive.len();
    let (mut pool, mut index) = storage(loglio_core::voxel_map::PRESET_POOL_VOXELS);
    let mut map = VoxelMap::new(&mut pool, &mut index, cfg).unwrap();
    // One untimed pass: report what the drive does to the map.
    for (i, (pts, sensor)) in drive.iter().enumerate() {
        map.insert_slice(pts, *sensor, i as u32).unwrap();
    }
    eprintln!(
        "insert: {raw0} returns per scan, {mean_pts} points per downsampled scan (mean), {} voxels after \
         {} scans, {} KiB per voxel pool of {}",
        map.len(),
        drive.len(),
        loglio_core::voxel_map::VOXEL_BYTES * map.capacity() / 1024,
        map.capacity()
    );
    map.clear();
    let mut next = 0usize;
    c.bench_function("insert_scan/vlp32c_0.4m", |b| {
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                if next == drive.len() {
                    next = 0;
                    map.clear();
                }
                let (pts, sensor) = &drive[next];
                let t = Instant::now();
                let st = map.insert_slice(black_box(pts), *sensor, next as u32).unwrap();
                total += t.elapsed();
                black_box(st);
                next += 1;
            }
            total
        })
    });
}

/// kiddo's mutable kd-tree with 64-point buckets.
type MutableKd = KdTree<f32, u32, Eytzinger, VecOfArrays<f32, u32, 3, 64>, 3, 64>;

fn bench_knn(c: &mut Criterion) {
    let scene = street();
    let cfg = MapConfig { evict_radius: 10_000.0, ..MapConfig::VLP32C };
    let (mut pool, mut index) = storage(1 << 19);
    let mut map = VoxelMap::new(&mut pool, &mut index, cfg).unwrap();
    // Drive until the map holds a million points.
    let mut i = 0u32;
    while map.point_count() < 1_000_000 {
        let pos = [f64::from(i) * 1.5, 0.5 * (f64::from(i) * 0.05).sin(), SENSOR_HEIGHT];
        let raw = scan(&scene, pos, 0.02 * f64::from(i), 1000 + u64::from(i));
        let pts = downsample(&raw, f64::from(cfg.voxel_size));
        map.insert_slice(&pts, [pos[0] as f32, pos[1] as f32, pos[2] as f32], i).unwrap();
        i += 1;
        assert!(i < 2000, "map does not fill");
    }
    let mut points: Vec<[f32; 3]> = Vec::with_capacity(map.point_count());
    map.for_each_point(|_, p, _| points.push(p));
    // Queries: a scan from the middle of the drive, 5 cm and 0.5 degrees off, in scan order.
    let mid = f64::from(i) * 1.5 / 2.0;
    let raw = scan(&scene, [mid + 0.05, 0.03, SENSOR_HEIGHT], 0.5f64.to_radians(), 7);
    let stride = (raw.len() / 10_000).max(1);
    let queries: Vec<[f32; 3]> = raw
        .iter()
        .step_by(stride)
        .take(10_000)
        .map(|(p, _)| [p[0] as f32, p[1] as f32, p[2] as f32])
        .collect();
    assert_eq!(queries.len(), 10_000);
    let r = cfg.voxel_size;
    // kiddo's mutable tree with its default 32-point buckets refuses this map
    // (`UnsplittableBucket`: the upper half of a bucket shares one coordinate, which the map's
    // quantised points produce); with 64-point buckets it builds. Reported as skipped if not.
    let mut mutable: Option<MutableKd> = Some(MutableKd::default());
    for (j, p) in points.iter().enumerate() {
        if let Some(t) = mutable.as_mut()
            && let Err(e) = t.add(p, j as u32)
        {
            eprintln!("knn: kiddo mutable kd-tree cannot hold this map ({e}); its row is skipped");
            mutable = None;
        }
    }
    let immutable: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(&points).unwrap();
    eprintln!(
        "knn: map of {} points in {} voxels after {i} scans; kd-trees of {} points; 10,000 queries, k = 5, r = {r} m",
        points.len(),
        map.len(),
        points.len()
    );
    // Same answers: counts and distances.
    let five = NonZero::new(5usize).unwrap();
    let query = KnnQuery::new(5, r);
    let mut out = Neighbours::new();
    let mut found = 0usize;
    for q in &queries {
        let n = map.knn(*q, &query, &mut out);
        let kd = immutable.query(q).nearest_n::<SquaredEuclidean<f32>>(five).within(r * r).execute();
        assert_eq!(n, kd.len(), "query {q:?}");
        for (a, b) in out.as_slice().iter().zip(&kd) {
            assert!((a.dist2 - b.distance).abs() <= 1e-5 + 1e-5 * b.distance, "{a:?} vs {}", b.distance);
        }
        found += n;
    }
    eprintln!("knn: {found} neighbours found in all ({:.2} per query)", found as f64 / 1e4);
    let mut outs = vec![Neighbours::new(); queries.len()];
    assert_eq!(map.knn_many(&queries, &query, &mut outs), found);

    let mut g = c.benchmark_group("knn5_10k");
    g.bench_function("voxel_map", |b| {
        b.iter(|| {
            let mut s = 0usize;
            for q in &queries {
                s += map.knn(black_box(*q), &query, &mut out);
            }
            s
        })
    });
    g.bench_function("voxel_map_knn_many", |b| {
        b.iter(|| map.knn_many(black_box(&queries), &query, &mut outs))
    });
    // As the association asks: 1 m bound (beyond the voxel, so the other 19 boxes are searched
    // until 5 are found), chunks of `KNN_CHUNK` queries.
    let assoc = KnnQuery::new(5, 1.0);
    g.bench_function("voxel_map_knn_many_1m_chunks", |b| {
        b.iter(|| {
            let mut s = 0;
            for (q, o) in queries
                .chunks(loglio_core::association::KNN_CHUNK)
                .zip(outs.chunks_mut(loglio_core::association::KNN_CHUNK))
            {
                s += map.knn_many(black_box(q), &assoc, o);
            }
            s
        })
    });
    let one = KnnQuery { one_per_voxel: true, ..query };
    g.bench_function("voxel_map_knn_many_one_per_voxel", |b| {
        b.iter(|| map.knn_many(black_box(&queries), &one, &mut outs))
    });
    if let Some(mutable) = &mutable {
        g.bench_function("kiddo_mutable", |b| {
            b.iter(|| {
                let mut s = 0usize;
                for q in &queries {
                    s += mutable
                        .query(black_box(q))
                        .nearest_n::<SquaredEuclidean<f32>>(five)
                        .within(r * r)
                        .execute()
                        .len();
                }
                s
            })
        });
    }
    g.bench_function("kiddo_immutable", |b| {
        b.iter(|| {
            let mut s = 0usize;
            for q in &queries {
                s += immutable
                    .query(black_box(q))
                    .nearest_n::<SquaredEuclidean<f32>>(five)
                    .within(r * r)
                    .execute()
                    .len();
            }
            s
        })
    });
    g.finish();

    // What the association pays per point on top of the k-NN: the large surfel of the 5
    // distinct voxels nearest each query, and one 3x3 eigen-analysis of a surfel's covariance.
    let mut handles = Vec::with_capacity(queries.len());
    map.knn_many(&queries, &one, &mut outs);
    for o in &outs {
        handles.push(o.voxels());
    }
    let accepted = outs.iter().zip(&handles).filter(|(o, h)| map.large_surfel(&h[..o.len()]).is_ok()).count();
    eprintln!("surfel: {accepted} of 10,000 queries have a large surfel over their 5 nearest voxels");
    let mut g = c.benchmark_group("surfel");
    g.bench_function("large_surfel_10k", |b| {
        b.iter(|| {
            let mut s = 0usize;
            for (o, h) in outs.iter().zip(&handles) {
                s += usize::from(map.large_surfel(black_box(&h[..o.len()])).is_ok());
            }
            s
        })
    });
    // The point-to-plane fallback's fit of each query's 5 nearest points: one at a time, and
    // PLANE_LANES at a time as the association runs them (the same results).
    let mut near = vec![Neighbours::new(); queries.len()];
    map.knn_many(&queries, &query, &mut near);
    let sets: Vec<([[f32; 3]; 8], usize)> = near.iter().map(|o| (o.points(), o.len())).collect();
    let lanes = loglio_core::surfel::PLANE_LANES;
    g.bench_function("fit_plane_10k", |b| {
        b.iter(|| {
            let mut s = 0usize;
            for (p, n) in &sets {
                s += usize::from(loglio_core::surfel::fit_plane(black_box(&p[..*n]), 0.1).is_ok());
            }
            s
        })
    });
    g.bench_function("fit_plane_lanes_10k", |b| {
        b.iter(|| {
            let mut s = 0usize;
            for group in sets.chunks(lanes) {
                let mut pts = [[[0.0f32; 3]; 8]; loglio_core::surfel::PLANE_LANES];
                let mut len = [0usize; loglio_core::surfel::PLANE_LANES];
                for (l, (p, n)) in group.iter().enumerate() {
                    (pts[l], len[l]) = (*p, *n);
                }
                let r = loglio_core::surfel::fit_plane_lanes(black_box(&pts), len, 0.1);
                s += r[..group.len()].iter().filter(|r| r.is_ok()).count();
            }
            s
        })
    });
    let cov: loglio_core::surfel::Sym3 = [0.0133, 0.0004, 0.0002, 0.0121, 0.0003, 2e-6];
    // Jacobi (the fallback) and the closed form the surfels use (`Shape::of_covariance`).
    g.bench_function("eigen_sym3", |b| b.iter(|| loglio_core::surfel::eigen_sym3(black_box(&cov))));
    g.bench_function("eigen_sym3_closed", |b| {
        b.iter(|| loglio_core::surfel::eigen_sym3_closed(black_box(&cov)))
    });
    g.finish();
}

fn bench_downsample(c: &mut Criterion) {
    let scene = street();
    let raw = scan(&scene, [0.0, 0.0, SENSOR_HEIGHT], 0.0, 7);
    let to32 = |v: [f64; 3]| v.map(|x| x as f32);
    let points: Vec<ScanPoint> = raw
        .iter()
        .enumerate()
        .map(|(i, (p, _))| ScanPoint {
            xyz: to32(*p),
            t: i as f32 * 1e-6,
            row: (i % 32) as u16,
            col: (i / 32) as u16,
            ..Default::default()
        })
        .collect();
    let normals: Vec<[f32; 3]> = raw.iter().map(|(_, n)| to32(*n)).collect();
    // The odometry's capacity (`OdometryStorage`'s `DS`) for this layout.
    let mut ds: Box<VoxelDownsampler<{ 1 << 16 }>> = Box::new(VoxelDownsampler::new());
    let cfg = DownsampleConfig::default();
    let (mut p, mut n, mut cell_of) = (points.clone(), normals.clone(), vec![0u32; points.len()]);
    let kept = ds.downsample_with_scratch(&cfg, &mut p, Some(&mut n), &mut cell_of).unwrap().kept;
    eprintln!("downsample: {} returns -> {kept} points", points.len());
    let mut sweep = vec![0u64; 8 << 20];
    let mut g = c.benchmark_group("downsample/vlp32c_0.4m");
    for cold in [false, true] {
        g.bench_function(if cold { "cold" } else { "warm" }, |b| {
            b.iter_custom(|iters| {
                let mut total = Duration::ZERO;
                for i in 0..iters {
                    p.copy_from_slice(&points);
                    n.copy_from_slice(&normals);
                    if cold {
                        for (j, w) in sweep.iter_mut().enumerate() {
                            *w = w.wrapping_add(j as u64 ^ i);
                        }
                        black_box(&sweep);
                    }
                    let t = Instant::now();
                    let st = ds.downsample_with_scratch(&cfg, black_box(&mut p), Some(&mut n), &mut cell_of);
                    total += t.elapsed();
                    black_box(st.unwrap());
                }
                total
            })
        });
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(Duration::from_secs(4)).warm_up_time(Duration::from_secs(1));
    targets = print_machine, bench_insert, bench_knn, bench_downsample
}

fn print_machine(_: &mut Criterion) {
    println!("{}", machine::describe());
}
criterion_main!(benches);
