//! Tests of the map against exact references: batch moments in f64, brute-force k-NN, a
//! `HashMap` model of the index and of the eviction, and long drives in a fixed pool.
extern crate std;
use std::collections::HashMap;
use std::vec;
use std::vec::Vec;

use super::index::{index_find, index_insert, index_remove_at};
use super::knn::NEIGHBOURS;
use super::voxel::round_sat;
use super::*;

use crate::surfel::{Moments, Shape, SurfelCriteria, SurfelReject};
use crate::testutil::SplitMix as Rng;

fn storage(cap: usize) -> (Vec<Voxel>, Vec<IndexSlot>) {
    (vec![Voxel::EMPTY; cap], vec![IndexSlot::EMPTY; (2 * cap).next_power_of_two()])
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    normalised(v).unwrap()
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn angle_deg(a: [f64; 3], b: [f64; 3]) -> f64 {
    let c = surfel::dot3(unit(a), unit(b)).clamp(-1.0, 1.0);
    libm::acos(c).to_degrees()
}

fn p32(p: [f64; 3]) -> [f32; 3] {
    to32(p)
}

fn mp(p: [f64; 3], n: Option<[f64; 3]>) -> MapPoint {
    MapPoint { xyz: p32(p), normal: n.map(to32) }
}

/// A point of the plane through `c` with normal `n`, uniform over the plane's cut through
/// the voxel of edge `s` centred at `c` (rejection sampling), plus `noise` (std) along `n`.
fn plane_point(rng: &mut Rng, c: [f64; 3], n: [f64; 3], s: f64, noise: f64) -> [f64; 3] {
    let t = if n[0].abs() < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
    let u = unit(cross(n, t));
    let v = cross(n, u);
    loop {
        let a = rng.uniform(-s, s);
        let b = rng.uniform(-s, s);
        let w = noise * rng.gauss();
        let p = [
            c[0] + a * u[0] + b * v[0] + w * n[0],
            c[1] + a * u[1] + b * v[1] + w * n[1],
            c[2] + a * u[2] + b * v[2] + w * n[2],
        ];
        if (0..3).all(|i| (p[i] - c[i]).abs() < 0.5 * s - 1e-4) {
            return p;
        }
    }
}

/// A normal within about `deg` degrees of `n`.
fn jitter(rng: &mut Rng, n: [f64; 3], deg: f64) -> [f64; 3] {
    let r = deg.to_radians();
    unit([n[0] + r * rng.gauss() * 0.5, n[1] + r * rng.gauss() * 0.5, n[2] + r * rng.gauss() * 0.5])
}

/// The f64 batch moments of the points with key `k`.
fn batch(map: &VoxelMap, pts: &[[f32; 3]], k: [i32; 3]) -> Moments {
    let mut m = Moments::new(to64(map.centre(k)));
    for p in pts {
        if map.key_of(*p) == Some(k) {
            m.add(to64(*p));
        }
    }
    m
}

#[test]
fn voxel_layout_is_small_and_empty_is_zero() {
    assert_eq!(VOXEL_BYTES, 192);
    assert_eq!(core::mem::align_of::<Voxel>(), 64);
    assert_eq!(core::mem::offset_of!(Voxel, last_seen), 64, "line 0 holds the lookup and k-NN data");
    assert_eq!(core::mem::size_of::<IndexSlot>(), 8);
    assert_eq!(Voxel::EMPTY, Voxel::default());
    assert_eq!(IndexSlot::EMPTY.0, 0);
    // Every field of EMPTY is an integer 0 or +0.0 and the layout has no implicit padding
    // (the fields, spares included, add up to the size), so its bytes are all zero: a
    // static pool goes to .bss.
    assert_eq!(core::mem::offset_of!(Voxel, rep_normals), 128, "line 1 holds what insertion writes");
    assert_eq!(core::mem::offset_of!(Voxel, _spare2) + 16, VOXEL_BYTES);
    let e = Voxel::EMPTY;
    assert!(e.sum.iter().chain(&e.sum_sq).chain(&e.ring_sum).all(|x| x.to_bits() == 0));
    static STORAGE: MapStorage<4, 8> = MapStorage::new();
    assert!(STORAGE.pool.iter().all(|v| *v == Voxel::EMPTY));
    let mut s = MapStorage::<4, 8>::new();
    assert_eq!(s.map(MapConfig::VLP32C).unwrap().capacity(), 4);
}

#[test]
fn construction_checks_storage_and_config() {
    let (mut pool, mut index) = storage(8);
    assert_eq!(VoxelMap::new(&mut pool[..0], &mut index, MapConfig::VLP32C).err(), Some(MapError::PoolEmpty));
    assert_eq!(
        VoxelMap::new(&mut pool, &mut index[..12], MapConfig::VLP32C).err(),
        Some(MapError::IndexNotPowerOfTwo)
    );
    assert_eq!(
        VoxelMap::new(&mut pool, &mut index[..8], MapConfig::VLP32C).err(),
        Some(MapError::IndexTooSmall { needed: 16 })
    );
    let bad: [(MapConfig, &str); 7] = [
        (MapConfig { voxel_size: 0.0, ..MapConfig::VLP32C }, "voxel_size"),
        (MapConfig { voxel_size: f32::NAN, ..MapConfig::VLP32C }, "voxel_size"),
        (MapConfig { eta: 2, ..MapConfig::VLP32C }, "eta"),
        (MapConfig { saturate_at: 24, ..MapConfig::VLP32C }, "saturate_at"),
        (MapConfig { max_normal_angle_deg: 91.0, ..MapConfig::VLP32C }, "max_normal_angle_deg"),
        (MapConfig { evict_radius: f32::INFINITY, ..MapConfig::VLP32C }, "evict_radius"),
        (MapConfig { min_ring_coherence: 1.5, ..MapConfig::VLP32C }, "min_ring_coherence"),
    ];
    for (cfg, field) in bad {
        assert_eq!(VoxelMap::new(&mut pool, &mut index, cfg).err(), Some(MapError::InvalidConfig { field }));
    }
    let map = VoxelMap::new(&mut pool, &mut index, MapConfig::OS1_16).unwrap();
    assert_eq!((map.len(), map.capacity(), map.config().voxel_size), (0, 8, 0.5));
}

#[test]
fn bad_input_is_counted_or_refused_never_panics() {
    let (mut pool, mut index) = storage(64);
    let mut map = VoxelMap::new(&mut pool, &mut index, MapConfig::VLP32C).unwrap();
    let pts = [
        MapPoint { xyz: [f32::NAN, 0.0, 0.0], normal: None },
        MapPoint { xyz: [1e9, 0.0, 0.0], normal: None },
        MapPoint { xyz: [f32::INFINITY, 0.0, 0.0], normal: None },
        // Just beyond the eviction radius: not inserted (counted).
        MapPoint { xyz: [MapConfig::VLP32C.evict_radius + 1.0, 0.0, 0.0], normal: None },
        MapPoint { xyz: [1.0, 1.0, 1.0], normal: Some([0.0, 0.0, 0.0]) },
        MapPoint { xyz: [1.0, 1.0, 1.0], normal: Some([f32::NAN, 0.0, 1.0]) },
        MapPoint { xyz: [1.0, 1.0, 1.0], normal: Some([0.0, 0.0, 3.0]) },
        MapPoint { xyz: [1.0, 1.0, 1.0], normal: Some([0.0, 0.0, 1.2]) },
    ];
    let st = map.insert_slice(&pts, [0.0; 3], 5).unwrap();
    assert_eq!(st.points, 8);
    assert_eq!(st.dropped_invalid, 3);
    assert_eq!(st.dropped_far, 1);
    assert_eq!(st.bad_normals, 3);
    assert_eq!((st.inserted, st.new_voxels), (4, 1));
    let info = map.voxel(map.find([1.0, 1.0, 1.0]).unwrap()).unwrap();
    assert_eq!((info.count, info.normal_count), (4, 1));
    assert_eq!(info.normal, Some([0.0, 0.0, 1.0]));
    assert_eq!(map.insert_slice(&pts, [f32::NAN, 0.0, 0.0], 6), Err(InsertError::SensorNotFinite));
    assert_eq!(map.insert_slice(&pts, [0.0; 3], 4), Err(InsertError::StampWentBackwards { last: 5, got: 4 }));
    assert!(map.insert_slice(&pts, [0.0; 3], 5).is_ok()); // equal stamps are fine
    // Queries with bad input find nothing.
    let mut out = Neighbours::new();
    assert_eq!(map.knn([f32::NAN, 0.0, 0.0], &KnnQuery::new(5, 0.4), &mut out), 0);
    assert_eq!(map.knn([1.0, 1.0, 1.0], &KnnQuery::new(5, f32::NAN), &mut out), 0);
    assert_eq!(map.knn([1.0, 1.0, 1.0], &KnnQuery::new(0, 0.4), &mut out), 0);
    assert_eq!(map.knn([1.0, 1.0, 1.0], &KnnQuery::new(100, 0.4), &mut out), 1); // k clamped
    assert_eq!(map.voxel(VoxelHandle(5)), None);
    assert_eq!(map.small_surfel(VoxelHandle(9)), Err(SurfelReject::InvalidHandle));
    assert_eq!(map.large_surfel(&[VoxelHandle(9)]), Err(SurfelReject::InvalidHandle));
}

#[test]
fn incremental_statistics_equal_batch_in_any_insert_order() {
    // No voxel is fixed here (eta 1000), so every point reaches the sums.
    let cfg = MapConfig { eta: 1000, saturate_at: 2000, ..MapConfig::VLP32C };
    let mut rng = Rng(5);
    // A box of exactly 3 x 3 x 2 voxels: x in [100.0, 101.2), y in [-50.8, -49.6), z in [2.0, 2.8).
    let pts: Vec<MapPoint> = (0..900)
        .map(|i| {
            let p = [rng.uniform(100.01, 101.19), rng.uniform(-50.79, -49.61), rng.uniform(2.01, 2.79)];
            let n = if i % 3 == 0 { None } else { Some(jitter(&mut rng, [0.0, 0.3, 1.0], 20.0)) };
            mp(p, n)
        })
        .collect();
    let xyz: Vec<[f32; 3]> = pts.iter().map(|p| p.xyz).collect();
    let mut orders: Vec<Vec<usize>> = vec![(0..900).collect(), (0..900).rev().collect()];
    let mut shuffled: Vec<usize> = (0..900).collect();
    for i in (1..900).rev() {
        shuffled.swap(i, (rng.next_u64() % (i as u64 + 1)) as usize);
    }
    orders.push(shuffled);
    let mut results: Vec<Vec<([i32; 3], Moments, u32)>> = Vec::new();
    for order in &orders {
        let (mut pool, mut index) = storage(256);
        let mut map = VoxelMap::new(&mut pool, &mut index, cfg).unwrap();
        // In batches of 37 with increasing stamps.
        for (stamp, chunk) in order.chunks(37).enumerate() {
            let st = map.insert(chunk.iter().map(|&i| pts[i]), [100.0, -50.0, 2.0], stamp as u32).unwrap();
            assert_eq!(st.accumulated as usize, chunk.len());
        }
        let mut per_voxel = Vec::new();
        for (h, info) in map.voxels() {
            let got = map.voxel_moments(h).unwrap();
            let want = batch(&map, &xyz, info.key);
            assert_eq!(got.n, want.n);
            assert_eq!(info.count, want.n);
            let (gm, wm) = (got.mean().unwrap(), want.mean().unwrap());
            let (gc, wc) = (got.covariance(), want.covariance());
            for a in 0..3 {
                assert!((gm[a] - wm[a]).abs() < 2e-6, "mean {gm:?} vs {wm:?}");
            }
            for i in 0..6 {
                assert!((gc[i] - wc[i]).abs() < 2e-6, "cov {gc:?} vs {wc:?}");
            }
            // The ring normal is the exact mean of the normals given.
            let mut ns = [0.0f64; 3];
            let mut nc = 0;
            for p in &pts {
                if let (Some(n), true) = (p.normal, map.key_of(p.xyz) == Some(info.key)) {
                    let n = unit(to64(n));
                    ns = [ns[0] + n[0], ns[1] + n[1], ns[2] + n[2]];
                    nc += 1;
                }
            }
            assert_eq!(info.normal_count, nc);
            assert!(angle_deg(to64(info.normal.unwrap()), ns) < 0.01);
            per_voxel.push((info.key, got, info.count));
        }
        per_voxel.sort_by_key(|x| x.0);
        assert_eq!(per_voxel.len(), 3 * 3 * 2);
        results.push(per_voxel);
    }
    // Different orders: the same voxels, the same counts, sums equal to f32 rounding.
    for r in &results[1..] {
        for (a, b) in r.iter().zip(&results[0]) {
            assert_eq!((a.0, a.2), (b.0, b.2));
            let (ca, cb) = (a.1.covariance(), b.1.covariance());
            for i in 0..6 {
                assert!((ca[i] - cb[i]).abs() < 2e-6);
            }
        }
    }
}

/// Inserts `pts` one per stamp (as downsampled scans would), returning the final state and
/// the state after each point.
fn feed(map: &mut VoxelMap, pts: &[MapPoint], stamp0: u32) -> Vec<VoxelState> {
    let mut states = Vec::new();
    for (i, p) in pts.iter().enumerate() {
        map.insert_slice(core::slice::from_ref(p), [0.0, 0.0, 1.5], stamp0 + i as u32).unwrap();
        states.push(map.voxel(map.find(p.xyz).unwrap()).unwrap().state);
    }
    states
}

#[test]
fn planes_converge_corners_poles_and_clouds_saturate() {
    let (mut pool, mut index) = storage(256);
    let mut map = VoxelMap::new(&mut pool, &mut index, MapConfig::VLP32C).unwrap();
    let s = 0.4;
    let mut rng = Rng(9);
    let n = unit([0.2, -0.3, 1.0]);
    let centre = |i: i32| [(i as f64 + 0.5) * s + 4.0, 0.5 * s + 2.8, 0.5 * s];
    let mut stamp = 0;
    let mut run = |map: &mut VoxelMap, pts: Vec<MapPoint>| {
        let states = feed(map, &pts, stamp);
        stamp += pts.len() as u32;
        states
    };
    // 1. A plane with 2 mm noise and ring normals within ~3 degrees: converges at eta = 25.
    let c = centre(0);
    let pts: Vec<MapPoint> =
        (0..50).map(|_| mp(plane_point(&mut rng, c, n, s, 0.002), Some(jitter(&mut rng, n, 3.0)))).collect();
    let states = run(&mut map, pts.clone());
    assert!(states[..24].iter().all(|s| *s == VoxelState::Accumulating));
    assert!(states[24..].iter().all(|s| *s == VoxelState::Converged));
    let h = map.find(pts[0].xyz).unwrap();
    let info = map.voxel(h).unwrap();
    assert_eq!(info.count, 25); // fixed at convergence
    let sf = map.small_surfel(h).unwrap();
    assert!(angle_deg(to64(sf.normal), n) < 1.0, "{:?}", sf.normal);
    assert!(sf.eigenvalues[0] < 1e-5 && sf.eigenvalues[1] > 100.0 * sf.eigenvalues[0]);
    // The voxel normal of a converged voxel: the average of ring normal and e_d.
    assert!(angle_deg(to64(info.normal.unwrap()), n) < 2.0);

    // 2. The same plane, ring normals 35 degrees off: never converges, saturates at 2 eta.
    let c = centre(2);
    let tilted = unit([n[0] + 0.7, n[1], n[2]]);
    assert!((angle_deg(tilted, n) - 35.0).abs() < 5.0);
    let pts: Vec<MapPoint> =
        (0..60).map(|_| mp(plane_point(&mut rng, c, n, s, 0.002), Some(tilted))).collect();
    let states = run(&mut map, pts.clone());
    assert!(states[..49].iter().all(|s| *s == VoxelState::Accumulating));
    assert!(states[49..].iter().all(|s| *s == VoxelState::Saturated));
    let h = map.find(pts[0].xyz).unwrap();
    assert_eq!(map.voxel(h).unwrap().count, 50);
    assert_eq!(map.small_surfel(h), Err(SurfelReject::NotConverged));
    // ... although the distribution itself is a surfel: convergence needs the ring normal.
    let shape = Shape::of_covariance(&map.voxel_moments(h).unwrap().covariance());
    assert_eq!(map.config().criteria.check(&shape), Ok(()));

    // 3. No normals at all: saturates. 4. Incoherent normals (+n / -n alternating): saturates.
    // 5. Normals all flipped (-n): converges, with e_d oriented along them.
    for (case, want) in [(3, VoxelState::Saturated), (4, VoxelState::Saturated), (5, VoxelState::Converged)] {
        let c = centre(2 * case);
        let pts: Vec<MapPoint> = (0..50)
            .map(|i| {
                let p = plane_point(&mut rng, c, n, s, 0.002);
                let nn = match case {
                    3 => None,
                    4 if i % 2 == 0 => Some(n),
                    4 => Some([-n[0], -n[1], -n[2]]),
                    _ => Some([-n[0], -n[1], -n[2]]),
                };
                mp(p, nn)
            })
            .collect();
        let states = run(&mut map, pts.clone());
        assert_eq!(*states.last().unwrap(), want, "case {case}");
        if want == VoxelState::Converged {
            let sf = map.small_surfel_at(pts[0].xyz).unwrap();
            assert!(angle_deg(to64(sf.normal), [-n[0], -n[1], -n[2]]) < 1.0);
        }
    }

    // 6. A corner: two perpendicular planes through the voxel centre.
    let c = centre(12);
    let m = unit([1.0, 0.0, 0.2]);
    let pts: Vec<MapPoint> = (0..50)
        .map(|i| {
            let nn = if i % 2 == 0 { n } else { m };
            mp(plane_point(&mut rng, c, nn, s, 0.002), Some(nn))
        })
        .collect();
    let states = run(&mut map, pts.clone());
    assert_eq!(*states.last().unwrap(), VoxelState::Saturated);
    let shape = Shape::of_covariance(&map.voxel_moments(map.find(pts[0].xyz).unwrap()).unwrap().covariance());
    assert!(map.config().criteria.check(&shape).is_err());

    // 7. A pole: a vertical cylinder of radius 5 cm, radial normals.
    let c = centre(14);
    let pts: Vec<MapPoint> = (0..50)
        .map(|_| {
            let a = rng.uniform(0.0, core::f64::consts::TAU);
            let (sa, ca) = (libm::sin(a), libm::cos(a));
            let z = rng.uniform(-0.19, 0.19);
            mp([c[0] + 0.05 * ca, c[1] + 0.05 * sa, c[2] + z], Some([ca, sa, 0.0]))
        })
        .collect();
    let states = run(&mut map, pts.clone());
    assert_eq!(*states.last().unwrap(), VoxelState::Saturated);
    let shape = Shape::of_covariance(&map.voxel_moments(map.find(pts[0].xyz).unwrap()).unwrap().covariance());
    assert_eq!(map.config().criteria.check(&shape), Err(SurfelReject::NotPlanar));

    // 8. A random cloud filling the voxel (vegetation).
    let c = centre(16);
    let pts: Vec<MapPoint> = (0..50)
        .map(|_| {
            let p = [
                c[0] + rng.uniform(-0.19, 0.19),
                c[1] + rng.uniform(-0.19, 0.19),
                c[2] + rng.uniform(-0.19, 0.19),
            ];
            mp(p, Some(jitter(&mut rng, [0.0, 0.0, 1.0], 60.0)))
        })
        .collect();
    let states = run(&mut map, pts.clone());
    assert_eq!(*states.last().unwrap(), VoxelState::Saturated);

    // 9. A plane with 3 cm noise (too thick for gamma > 100): saturates.
    let c = centre(18);
    let pts: Vec<MapPoint> = (0..50).map(|_| mp(plane_point(&mut rng, c, n, s, 0.03), Some(n))).collect();
    let states = run(&mut map, pts.clone());
    assert_eq!(*states.last().unwrap(), VoxelState::Saturated);
    let shape = Shape::of_covariance(&map.voxel_moments(map.find(pts[0].xyz).unwrap()).unwrap().covariance());
    assert_eq!(map.config().criteria.check(&shape), Err(SurfelReject::NotThin));
}

#[test]
fn fixed_voxels_keep_their_distribution_but_refresh_stamp_and_representatives() {
    let (mut pool, mut index) = storage(16);
    let mut map = VoxelMap::new(&mut pool, &mut index, MapConfig::VLP32C).unwrap();
    let mut rng = Rng(21);
    let c = [2.2, 2.2, 0.2];
    let n = [0.0, 0.0, 1.0];
    let pts: Vec<MapPoint> = (0..25).map(|_| mp(plane_point(&mut rng, c, n, 0.4, 0.0), Some(n))).collect();
    feed(&mut map, &pts, 0);
    let h = map.find(pts[0].xyz).unwrap();
    let before = map.voxel_moments(h).unwrap();
    let info = map.voxel(h).unwrap();
    assert_eq!(info.state, VoxelState::Converged);
    // The plane z = 0.2 runs through the centre: its points have z offset 0 and fill the
    // upper four octants (offset >= 0); two points below fill two of the lower ones.
    let extra = [mp([2.3, 2.3, 0.1], Some(n)), mp([2.1, 2.1, 0.1], Some(n))];
    let reps_before = map.pool[h.index()].occupied;
    let st = map.insert_slice(&extra, [0.0; 3], 100).unwrap();
    assert_eq!((st.inserted, st.accumulated), (2, 0));
    assert_eq!(map.voxel_moments(h).unwrap(), before);
    let after = map.voxel(h).unwrap();
    assert_eq!((after.count, after.last_seen, after.state), (25, 100, VoxelState::Converged));
    assert_eq!(map.pool[h.index()].occupied.count_ones(), reps_before.count_ones() + 2);
}

#[test]
fn far_from_origin_voxel_sums_hold_where_world_frame_f32_sums_fail() {
    let (mut pool, mut index) = storage(16);
    let mut map = VoxelMap::new(&mut pool, &mut index, MapConfig::VLP32C).unwrap();
    let mut rng = Rng(33);
    // A tilted plane 10 km from the origin; the sensor nearby.
    let c = [10_000.2, -10_000.2, 30.2];
    let n = unit([0.3, 0.1, 1.0]);
    let pts: Vec<MapPoint> = (0..25).map(|_| mp(plane_point(&mut rng, c, n, 0.4, 0.001), Some(n))).collect();
    for (i, p) in pts.iter().enumerate() {
        map.insert_slice(core::slice::from_ref(p), [10_000.0, -10_000.0, 31.0], i as u32).unwrap();
    }
    let sf = map.small_surfel_at(pts[0].xyz).unwrap();
    assert!(angle_deg(to64(sf.normal), n) < 1.0, "normal {:?}", sf.normal);
    let want = Moments::from_points(c, &pts.iter().map(|p| to64(p.xyz)).collect::<Vec<_>>());
    let wm = want.mean().unwrap();
    for a in 0..3 {
        assert!((f64::from(sf.mean[a]) - wm[a]).abs() < 2e-3);
    }
    // The reference's scheme: world-frame f32 sums of p and p pᵀ, covariance S/n - mean meanᵀ.
    let mut s = [0.0f32; 6];
    let mut sum = [0.0f32; 3];
    for p in &pts {
        let x = p.xyz;
        sum = [sum[0] + x[0], sum[1] + x[1], sum[2] + x[2]];
        let o = [x[0] * x[0], x[0] * x[1], x[0] * x[2], x[1] * x[1], x[1] * x[2], x[2] * x[2]];
        for i in 0..6 {
            s[i] += o[i];
        }
    }
    let k = pts.len() as f32;
    let m = [sum[0] / k, sum[1] / k, sum[2] / k];
    let mm = [m[0] * m[0], m[0] * m[1], m[0] * m[2], m[1] * m[1], m[1] * m[2], m[2] * m[2]];
    let naive: surfel::Sym3 = core::array::from_fn(|i| f64::from(s[i] / k - mm[i]));
    let shape = Shape::of_covariance(&naive);
    let normal_err = angle_deg(shape.normal(), n).min(180.0 - angle_deg(shape.normal(), n));
    // Points inside a 0.4 m cube have no variance above 3 * 0.2^2 = 0.12 m²; the naive
    // covariance is off by orders of magnitude (12.5 m² here) and its normal is garbage.
    assert!(shape.eigenvalues[2] > 0.12, "world-frame f32 sums unexpectedly fine: {shape:?}");
    assert!(
        SurfelCriteria::DEFAULT.check(&shape).is_err() || normal_err > 10.0,
        "world-frame f32 sums unexpectedly fine: {shape:?}"
    );
}

/// Fills a grid of `nx x ny` voxels (keys `k0 + (i, j, 0)`) with points of planes with
/// normal `normal` through the voxel centres (raised by `lift(i, j)` metres): one point per
/// voxel per scan, `per_voxel` scans stamped from `stamp0`. Points are stratified over a
/// 5 x 5 grid of the patch (scan `t` takes cell `t mod 25`, as a moving sensor spreads its
/// samples) so 25 points cover the patch evenly: with 25 uniform random points a flat
/// square fails `rho > 0.6` 7 % of the time. Returns every point inserted.
#[allow(clippy::too_many_arguments)]
fn plane_grid(
    map: &mut VoxelMap,
    rng: &mut Rng,
    k0: [i32; 3],
    nx: i32,
    ny: i32,
    per_voxel: usize,
    normal: [f64; 3],
    lift: impl Fn(i32, i32) -> f64,
    stamp0: u32,
) -> Vec<[f32; 3]> {
    let s = f64::from(map.config().voxel_size);
    let t = if normal[0].abs() < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
    let u = unit(cross(normal, t));
    let v = cross(normal, u);
    let half = 0.35 * s; // the patch stays inside the voxel however it is rotated
    let mut all = Vec::new();
    for scan in 0..per_voxel {
        let cell = (stamp0 as usize + scan) % 25;
        let mut batch = Vec::new();
        for i in 0..nx {
            for j in 0..ny {
                let c = [
                    (f64::from(k0[0] + i) + 0.5) * s,
                    (f64::from(k0[1] + j) + 0.5) * s,
                    (f64::from(k0[2]) + 0.5) * s + lift(i, j),
                ];
                let a = half * (2.0 * ((cell % 5) as f64 + rng.uniform(0.0, 1.0)) / 5.0 - 1.0);
                let b = half * (2.0 * ((cell / 5) as f64 + rng.uniform(0.0, 1.0)) / 5.0 - 1.0);
                let w = 0.001 * rng.gauss();
                let p: [f64; 3] = core::array::from_fn(|x| c[x] + a * u[x] + b * v[x] + w * normal[x]);
                let k = [k0[0] + i, k0[1] + j, k0[2] + libm::floor(lift(i, j) / s + 0.5) as i32];
                assert_eq!(map.key_of(p32(p)), Some(k), "test point left its voxel");
                batch.push(mp(p, Some(jitter(rng, normal, 2.0))));
            }
        }
        let sensor = p32([(f64::from(k0[0]) + 0.5) * s, (f64::from(k0[1]) + 0.5) * s, 2.0]);
        map.insert_slice(&batch, sensor, stamp0 + scan as u32).unwrap();
        all.extend(batch.iter().map(|p| p.xyz));
    }
    all
}

fn handles(map: &VoxelMap, k0: [i32; 3], nx: i32, ny: i32) -> Vec<VoxelHandle> {
    let mut out = Vec::new();
    for i in 0..nx {
        for j in 0..ny {
            out.push(map.find_key([k0[0] + i, k0[1] + j, k0[2]]).unwrap());
        }
    }
    out
}

#[test]
fn large_surfel_equals_the_union_and_rejects_non_coplanar_neighbourhoods() {
    let (mut pool, mut index) = storage(256);
    // Voxels 10 km apart stay in the map: no distance eviction here.
    let cfg = MapConfig { evict_radius: 1e5, ..MapConfig::VLP32C };
    let mut map = VoxelMap::new(&mut pool, &mut index, cfg).unwrap();
    let mut rng = Rng(77);
    // A horizontal floor of 3 x 3 voxels, 25 points each: all converge, all points counted.
    // Near the origin and 10 km out.
    for (k0, stamp0) in [([10, 10, 0], 0), ([25_000, -25_000, 10], 50)] {
        let n = [0.0, 0.0, 1.0];
        let pts = plane_grid(&mut map, &mut rng, k0, 3, 3, 25, n, |_, _| 0.0, stamp0);
        let hs = handles(&map, k0, 3, 3);
        assert!(hs.iter().all(|h| map.voxel(*h).unwrap().state == VoxelState::Converged));
        let ls = map.large_surfel(&hs).unwrap();
        let want = Moments::from_points(to64(pts[0]), &pts.iter().map(|p| to64(*p)).collect::<Vec<_>>());
        let wshape = Shape::of_covariance(&want.covariance());
        assert_eq!((ls.count, ls.voxels), (225, 9));
        let wm = want.mean().unwrap();
        for a in 0..3 {
            // f32 output; 10 km out the f32 mean itself is quantised to 1 mm.
            assert!((f64::from(ls.mean[a]) - wm[a]).abs() < 1e-3, "{:?} vs {wm:?}", ls.mean);
            assert!((f64::from(ls.eigenvalues[a]) - wshape.eigenvalues[a]).abs() < 1e-6);
        }
        assert!(angle_deg(to64(ls.normal), n) < 0.5, "{:?}", ls.normal); // oriented with the ring normals
        // The merged covariance equals the union's entry by entry (f32 sums: 1e-6 m²).
        let mut merged = Moments::new(to64(pts[0]));
        for h in &hs {
            merged.merge(&map.voxel_moments(*h).unwrap());
        }
        let (mc, wc) = (merged.covariance(), want.covariance());
        for i in 0..6 {
            assert!((mc[i] - wc[i]).abs() < 1e-6, "{mc:?} vs {wc:?}");
        }
        // Duplicates count once.
        let mut dup = hs.clone();
        dup.extend_from_slice(&hs[..4]);
        assert_eq!(map.large_surfel(&dup), Ok(ls));
    }
    let hs = handles(&map, [10, 10, 0], 3, 3);
    // Too few points (2 voxels x 25 < 63) and too few voxels.
    assert_eq!(map.large_surfel(&hs[..2]), Err(SurfelReject::TooFewPoints));
    assert_eq!(map.large_surfel(&hs[..1]), Err(SurfelReject::TooFewVoxels));
    assert_eq!(map.large_surfel(&[]), Err(SurfelReject::TooFewVoxels));

    // A crease: a floor beside a wall (vertical plane) is no surfel.
    let kf = [40, 10, 0];
    plane_grid(&mut map, &mut rng, kf, 2, 3, 25, [0.0, 0.0, 1.0], |_, _| 0.0, 100);
    let kw = [42, 10, 1];
    plane_grid(&mut map, &mut rng, kw, 1, 3, 25, [1.0, 0.0, 0.0], |_, _| 0.0, 200);
    let mut mix = handles(&map, kf, 2, 3);
    mix.extend(handles(&map, kw, 1, 3));
    let r = map.large_surfel(&mix);
    assert!(matches!(r, Err(SurfelReject::NotPlanar | SurfelReject::NotThin)), "{r:?}");

    // A step: one column of the 3 x 3 floor raised by 18 cm (same voxel layer). The merged
    // plane tilts to follow the step and is too thick for gamma > 100.
    let ks = [60, 10, 0];
    plane_grid(
        &mut map,
        &mut rng,
        ks,
        3,
        3,
        25,
        [0.0, 0.0, 1.0],
        |i, _| if i == 2 { 0.18 } else { 0.0 },
        300,
    );
    let hs = handles(&map, ks, 3, 3);
    assert_eq!(map.large_surfel(&hs), Err(SurfelReject::NotThin));
    // Without the criteria, the mean-distance test decides: the column means lie about
    // 6 cm from the tilted plane, so it fails at 5 cm and passes at the default 15 cm.
    map.cfg.large.apply_criteria = false;
    map.cfg.large.max_mean_distance = 0.05;
    assert_eq!(map.large_surfel(&hs), Err(SurfelReject::OffPlane));
    map.cfg.large.max_mean_distance = 0.15;
    assert!(map.large_surfel(&hs).is_ok());
    // A 12 cm step is NOT rejected by the default criteria (gamma ~ 126, the plane tilts
    // 8 degrees to follow it): a limit of the paper's test worth knowing downstream.
    map.cfg.large = LargeSurfelConfig::DEFAULT;
    let ks = [70, 10, 0];
    plane_grid(
        &mut map,
        &mut rng,
        ks,
        3,
        3,
        25,
        [0.0, 0.0, 1.0],
        |i, _| if i == 2 { 0.12 } else { 0.0 },
        400,
    );
    let ls = map.large_surfel(&handles(&map, ks, 3, 3)).unwrap();
    assert!(angle_deg(to64(ls.normal), [0.0, 0.0, 1.0]) > 5.0);

    // Voxels below eta do not take part.
    let kl = [80, 10, 0];
    plane_grid(&mut map, &mut rng, kl, 3, 3, 10, [0.0, 0.0, 1.0], |_, _| 0.0, 500);
    let mut with_small = handles(&map, [10, 10, 0], 3, 3);
    with_small.extend(handles(&map, kl, 3, 3));
    assert_eq!(map.large_surfel(&with_small).unwrap().voxels, 9);
    assert_eq!(map.large_surfel(&handles(&map, kl, 3, 3)), Err(SurfelReject::TooFewVoxels));
}

#[test]
fn small_surfel_only_for_converged_voxels() {
    let (mut pool, mut index) = storage(64);
    let mut map = VoxelMap::new(&mut pool, &mut index, MapConfig::VLP32C).unwrap();
    let mut rng = Rng(3);
    plane_grid(&mut map, &mut rng, [0, 0, 0], 1, 1, 24, [0.0, 0.0, 1.0], |_, _| 0.0, 0);
    let p = [0.2, 0.2, 0.2];
    assert_eq!(map.small_surfel_at(p), Err(SurfelReject::NotConverged));
    assert_eq!(map.small_surfel_at([5.0, 5.0, 5.0]), Err(SurfelReject::InvalidHandle));
    plane_grid(&mut map, &mut rng, [0, 0, 0], 1, 1, 1, [0.0, 0.0, 1.0], |_, _| 0.0, 24);
    let sf = map.small_surfel_at(p).unwrap();
    assert_eq!(sf.count, 25);
    assert!((sf.mean[2] - 0.2).abs() < 2e-3);
    assert!(sf.normal[2] > 0.999);
    assert_eq!(sf.voxel, map.find(p).unwrap());
}

/// Brute-force k-NN over every representative point of the map (`block_only`: of the
/// query's 27 voxels; `octant`: of its 8 octant voxels).
fn brute_knn(
    map: &VoxelMap,
    q: [f32; 3],
    k: usize,
    max_dist: f32,
    one_per_voxel: bool,
    block_only: bool,
    octant: bool,
) -> Vec<(f64, VoxelHandle, [f32; 3])> {
    let qk = map.key_of(q).unwrap();
    let c = map.centre(qk);
    let side: [i32; 3] = core::array::from_fn(|a| if q[a] < c[a] { -1 } else { 1 });
    let mut all: Vec<(f64, VoxelHandle, [f32; 3])> = Vec::new();
    map.for_each_point(|h, p, _| {
        let key = map.voxel(h).unwrap().key;
        if block_only && (0..3).any(|a| (key[a] - qk[a]).abs() > 1) {
            return;
        }
        if octant && (0..3).any(|a| key[a] != qk[a] && key[a] != qk[a] + side[a]) {
            return;
        }
        let d = surfel::sub3(to64(p), to64(q));
        let d2 = surfel::dot3(d, d);
        if d2 <= f64::from(max_dist) * f64::from(max_dist) {
            all.push((d2, h, p));
        }
    });
    all.sort_by(|a, b| a.0.partial_cmp(&b.0).unwrap());
    if one_per_voxel {
        let mut seen = Vec::new();
        all.retain(|x| {
            if seen.contains(&x.1) {
                false
            } else {
                seen.push(x.1);
                true
            }
        });
    }
    all.truncate(k);
    all
}

#[test]
fn knn_equals_brute_force_on_random_data() {
    let (mut pool, mut index) = storage(2048);
    let mut map = VoxelMap::new(&mut pool, &mut index, MapConfig::VLP32C).unwrap();
    let mut rng = Rng(123);
    // Random points in a 3 x 3 x 2 m box, clustered unevenly (some voxels dense, some sparse,
    // many empty), with and without normals, inserted in 20 scans.
    for scan in 0..20u32 {
        let batch: Vec<MapPoint> = (0..400)
            .map(|i| {
                let p = if i % 2 == 0 {
                    [rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5), rng.uniform(0.0, 2.0)]
                } else {
                    [rng.uniform(-0.3, 0.5), rng.uniform(0.1, 0.9), rng.uniform(0.5, 0.7)]
                };
                mp(p, if i % 4 == 0 { None } else { Some(jitter(&mut rng, [0.0, 0.0, 1.0], 30.0)) })
            })
            .collect();
        map.insert_slice(&batch, [0.0, 0.0, 1.0], scan).unwrap();
    }
    assert!(map.point_count() > 1500, "{}", map.point_count());
    let mut out = Neighbours::new();
    let mut checked = 0;
    let (mut block_answers, mut block_differs) = (0, 0);
    for qi in 0..400 {
        let q = p32([rng.uniform(-1.7, 1.7), rng.uniform(-1.7, 1.7), rng.uniform(-0.2, 2.2)]);
        for (k, max_dist, one, block_only, reach) in [
            (5, 0.4, false, false, KnnReach::Neighbourhood),
            (1, 0.4, false, false, KnnReach::Neighbourhood),
            (8, 0.3, false, false, KnnReach::Neighbourhood),
            (5, 0.4, true, false, KnnReach::Neighbourhood),
            (8, 0.25, true, false, KnnReach::Neighbourhood),
            // Beyond one voxel: exact within the 27-voxel block.
            (5, 1.0, false, true, KnnReach::Neighbourhood),
            (5, 1.0, true, true, KnnReach::Neighbourhood),
            // The octant's 8 voxels when they hold k, else the 27.
            (5, 1.0, false, true, KnnReach::Block),
            (5, 1.0, true, true, KnnReach::Block),
            (8, 0.3, false, false, KnnReach::Block),
            (1, 0.4, false, false, KnnReach::Block),
        ] {
            let query = KnnQuery { k, max_dist, one_per_voxel: one, reach };
            let n = map.knn(q, &query, &mut out);
            let mut want = brute_knn(&map, q, k, max_dist, one, block_only, false);
            if reach == KnnReach::Block {
                let oct = brute_knn(&map, q, k, max_dist, one, block_only, true);
                if oct.len() == k {
                    block_answers += 1;
                    block_differs += usize::from(oct != want);
                    want = oct;
                }
            }
            assert_eq!(n, want.len(), "query {qi} {q:?} k {k} r {max_dist} one {one} {reach:?}");
            assert_eq!(out.len(), n);
            for (i, (got, w)) in out.as_slice().iter().zip(&want).enumerate() {
                assert!((f64::from(got.dist2) - w.0).abs() < 1e-5, "query {qi} #{i}: {got:?} vs {w:?}");
                // The point is a real map point of the voxel named, at the distance given.
                let d = surfel::sub3(to64(got.point), to64(q));
                assert!((surfel::dot3(d, d) - f64::from(got.dist2)).abs() < 1e-5);
                assert_eq!(map.key_of(got.point), Some(map.voxel(got.voxel).unwrap().key));
                if i > 0 {
                    assert!(got.dist2 >= out.as_slice()[i - 1].dist2);
                }
            }
            if one {
                let vs = out.voxels();
                for i in 0..n {
                    assert!(!vs[..i].contains(&vs[i]), "voxel repeated");
                }
            }
            checked += n;
        }
    }
    assert!(checked > 5000, "too few neighbours exercised: {checked}");
    // Both branches of the block reach ran, and it does differ from the exact search.
    // (1,172 of the 1,600 from the octant, 100 of them not the exact answer.)
    assert!(
        block_answers > 900 && block_answers < 1500 && block_differs > 50,
        "{block_answers} {block_differs}"
    );
    // knn_many gives exactly what knn gives, query by query (groups of 8 and a remainder).
    let queries: Vec<[f32; 3]> = (0..203)
        .map(|_| p32([rng.uniform(-1.7, 1.7), rng.uniform(-1.7, 1.7), rng.uniform(-0.2, 2.2)]))
        .collect();
    for query in [
        KnnQuery::new(5, 0.4),
        KnnQuery { k: 8, max_dist: 1.0, one_per_voxel: true, reach: KnnReach::Neighbourhood },
        KnnQuery::new(5, 1.0).with_reach(KnnReach::Block),
    ] {
        let mut many = vec![Neighbours::new(); queries.len() + 3];
        let total = map.knn_many(&queries, &query, &mut many);
        let mut sum = 0;
        for (q, m) in queries.iter().zip(&many) {
            sum += map.knn(*q, &query, &mut out);
            assert_eq!(m.as_slice(), out.as_slice());
        }
        assert_eq!(total, sum);
        assert!(many[queries.len()..].iter().all(|m| m.is_empty()));
    }
}

#[test]
fn knn_normals_plane_fit_and_large_surfel_work_together() {
    let (mut pool, mut index) = storage(64);
    let mut map = VoxelMap::new(&mut pool, &mut index, MapConfig::VLP32C).unwrap();
    let mut rng = Rng(8);
    // One voxel holding a tilted plane through its centre.
    let n = unit([0.1, 0.2, 1.0]);
    plane_grid(&mut map, &mut rng, [0, 0, 0], 1, 1, 25, n, |_, _| 0.0, 0);
    let mut out = Neighbours::new();
    let q = [0.2, 0.2, 0.2];
    let found = map.knn(q, &KnnQuery::new(5, 0.4), &mut out);
    assert!(found >= 4, "{found}");
    for nb in out.as_slice() {
        // i8-quantised normals: within 0.5 degrees of the input (itself jittered ~2 degrees).
        assert!(angle_deg(to64(nb.normal().unwrap()), n) < 6.0);
    }
    let plane = out.fit_plane(0.1).unwrap();
    let err = angle_deg(to64(plane.normal), n);
    assert!(err.min(180.0 - err) < 1.0, "{err}");
    // A floor of 3 x 3 voxels: 5-NN one per voxel name 5 distinct voxels whose merge is a
    // large surfel.
    plane_grid(&mut map, &mut rng, [5, 0, 0], 3, 3, 25, [0.0, 0.0, 1.0], |_, _| 0.0, 100);
    let q = [2.6, 0.6, 0.21];
    let query = KnnQuery { k: 5, max_dist: 0.4, one_per_voxel: true, reach: KnnReach::Neighbourhood };
    assert_eq!(map.knn(q, &query, &mut out), 5);
    let ls = map.large_surfel(&out.voxels()[..out.len()]).unwrap();
    assert_eq!((ls.voxels, ls.count), (5, 125));
    assert!(ls.normal[2] > 0.999);
}

/// Checks the linear-probing invariants: every entry is reachable from its home bucket
/// without crossing an empty slot, entries name distinct live slots whose keys hash to the
/// entry's hash, and there is exactly one entry per live voxel.
fn check_index(map: &VoxelMap) {
    let mask = map.mask;
    let mut seen = vec![false; map.len];
    let mut entries = 0;
    for pos in 0..map.index.len() {
        let e = map.index[pos];
        if e.is_empty() {
            continue;
        }
        entries += 1;
        let slot = e.slot() as usize;
        assert!(slot < map.len, "entry names a dead slot");
        assert!(!seen[slot], "two entries for one slot");
        seen[slot] = true;
        assert_eq!(hash_key(map.pool[slot].key), e.hash());
        let mut p = e.hash() as usize & mask;
        while p != pos {
            assert!(!map.index[p].is_empty(), "hole between home and entry");
            p = (p + 1) & mask;
        }
    }
    assert_eq!(entries, map.len);
}

const COLLIDING: [u32; 12] = [14, 15, 15, 0, 14, 1, 15, 0, 14, 2, 3, 15];

proptest::proptest! {
    /// The raw index against a HashMap, with hashes chosen to collide (equal full hashes,
    /// equal buckets, clusters wrapping around the end of a 16-slot table).
    #[test]
    fn index_with_colliding_hashes_matches_a_hashmap(
        ops in proptest::collection::vec((0u8..3, 0u32..12), 1..300)
    ) {
        let mut index = [IndexSlot::EMPTY; 16];
        let mask = 15;
        let mut model: std::collections::HashMap<u32, usize> = std::collections::HashMap::new();
        for (op, id) in ops {
            let h = COLLIDING[id as usize];
            let found = index_find(&index, mask, h, |s| s == id);
            proptest::prop_assert_eq!(found.is_some(), model.contains_key(&id));
            match op {
                0 if found.is_none() && model.len() < 8 => {
                    proptest::prop_assert!(index_insert(&mut index, mask, h, id));
                    model.insert(id, 0);
                }
                1 => {
                    if let Some((pos, _)) = found {
                        index_remove_at(&mut index, mask, pos);
                        model.remove(&id);
                    }
                }
                _ => {}
            }
            // Every id: found iff in the model; the cluster invariant holds.
            for other in 0..12u32 {
                let f = index_find(&index, mask, COLLIDING[other as usize], |s| s == other);
                proptest::prop_assert_eq!(f.map(|x| x.1), model.get(&other).map(|_| other));
            }
            for pos in 0..16 {
                let e = index[pos];
                if e.is_empty() { continue; }
                let mut p = e.hash() as usize & mask;
                while p != pos {
                    proptest::prop_assert!(!index[p].is_empty());
                    p = (p + 1) & mask;
                }
            }
            proptest::prop_assert_eq!(index.iter().filter(|e| !e.is_empty()).count(), model.len());
        }
    }

    /// The map against a model (key -> count) through inserts into a 16-voxel pool with
    /// full-pool evictions: counts exact, nothing lost but the evicted voxel, and the evicted
    /// voxel is always the farthest (then least recently used) one.
    #[test]
    fn map_insert_lookup_evict_matches_a_model(
        ops in proptest::collection::vec(((-4i32..4, -4i32..4, -1i32..2), (-3i32..4, -3i32..4)), 1..250)
    ) {
        let cfg = MapConfig {
            eta: 1000,
            saturate_at: 2000,
            evict_radius: 4.0,
            sweep_per_insert: 0,
            evict_batch: 1,
            ..MapConfig::VLP32C
        };
        let (mut pool, mut index) = storage(16);
        let mut map = VoxelMap::new(&mut pool, &mut index, cfg).unwrap();
        let mut model: std::collections::HashMap<[i32; 3], u32> = std::collections::HashMap::new();
        for (stamp, (k, sxy)) in ops.into_iter().enumerate() {
            let stamp = stamp as u32 + 1;
            let key = [k.0, k.1, k.2];
            let p = [(k.0 as f32 + 0.3) * 0.4, (k.1 as f32 + 0.6) * 0.4, (k.2 as f32 + 0.5) * 0.4];
            let sensor = [sxy.0 as f32 * 0.5, sxy.1 as f32 * 0.5, 0.0];
            // Priorities before the insert: (distance bucket, age) of every voxel.
            let prio: std::collections::HashMap<[i32; 3], (usize, u32)> = map
                .voxels()
                .map(|(h, v)| {
                    let vx = &map.pool[h.index()];
                    (v.key, (map.dist_bucket(vx, sensor), stamp - v.last_seen))
                })
                .collect();
            let st = map.insert_slice(&[MapPoint { xyz: p, normal: None }], sensor, stamp).unwrap();
            if st.dropped_far == 1 {
                proptest::prop_assert!(d2f(p, sensor) > 16.0);
            } else {
                proptest::prop_assert_eq!(st.inserted, 1);
                if st.evicted_full == 1 {
                    let gone: Vec<[i32; 3]> =
                        model.keys().copied().filter(|k| map.find_key(*k).is_none()).collect();
                    proptest::prop_assert_eq!(gone.len(), 1);
                    let worst = prio.values().max().unwrap();
                    proptest::prop_assert_eq!(prio[&gone[0]], *worst);
                    model.remove(&gone[0]);
                } else {
                    proptest::prop_assert_eq!(st.evicted_full, 0);
                }
                *model.entry(key).or_insert(0) += 1;
            }
            proptest::prop_assert!(map.len() <= 16);
            proptest::prop_assert_eq!(map.len(), model.len());
            for (k, c) in &model {
                let h = map.find_key(*k);
                proptest::prop_assert!(h.is_some());
                let v = map.voxel(h.unwrap()).unwrap();
                proptest::prop_assert_eq!((v.key, v.count), (*k, *c));
            }
            check_index(&map);
        }
    }
}

#[test]
fn full_pool_evicts_farthest_then_least_recently_used_and_never_the_current_scan() {
    let cfg = MapConfig { evict_radius: 50.0, sweep_per_insert: 0, evict_batch: 1, ..MapConfig::VLP32C };
    let (mut pool, mut index) = storage(8);
    let mut map = VoxelMap::new(&mut pool, &mut index, cfg).unwrap();
    let at = |x: f32, y: f32| MapPoint { xyz: [x, y, 0.1], normal: None };
    // One scan with 12 voxels for 8 slots: the first 8 are kept, 4 points dropped (nothing
    // of this scan may be evicted to make room for the rest of it).
    let scan: Vec<MapPoint> = (0..12).map(|i| at(1.1 + i as f32, 0.1)).collect();
    let st = map.insert_slice(&scan, [0.0; 3], 1).unwrap();
    assert_eq!((st.new_voxels, st.dropped_full, st.evicted_full), (8, 4, 0));
    assert_eq!(map.len(), 8);
    for (i, p) in scan.iter().enumerate() {
        assert_eq!(map.find(p.xyz).is_some(), i < 8);
    }
    // Next scan, sensor at the origin: two new voxels evict the two farthest (x = 8.1, 7.1).
    let st = map.insert_slice(&[at(-1.1, 0.1), at(-2.1, 0.1)], [0.0; 3], 2).unwrap();
    assert_eq!((st.new_voxels, st.evicted_full, st.dropped_full), (2, 2, 0));
    assert!(map.find([8.1, 0.1, 0.1]).is_none() && map.find([7.1, 0.1, 0.1]).is_none());
    assert!(map.find([6.1, 0.1, 0.1]).is_some());
    // Distance comes before recency: x = 6.1, refreshed just now, is still the farthest and
    // goes first.
    map.insert_slice(&[at(6.1, 0.1)], [0.0; 3], 3).unwrap();
    map.insert_slice(&[at(0.1, 3.1)], [0.0; 3], 4).unwrap();
    assert!(map.find([6.1, 0.1, 0.1]).is_none(), "farthest goes first even if recent");
    assert!(map.find([5.1, 0.1, 0.1]).is_some());
    // Two voxels at exactly the same distance (mirror images), different ages.
    let (mut pool, mut index) = storage(4);
    let mut map = VoxelMap::new(&mut pool, &mut index, cfg).unwrap();
    map.insert_slice(&[at(3.1, 0.1)], [0.0; 3], 1).unwrap(); // older
    map.insert_slice(&[at(-3.1, 0.1)], [0.0; 3], 2).unwrap();
    map.insert_slice(&[at(0.1, 0.1)], [0.0; 3], 3).unwrap();
    map.insert_slice(&[at(0.5, 0.1)], [0.0; 3], 4).unwrap();
    assert_eq!(map.len(), 4);
    map.insert_slice(&[at(0.1, 1.1)], [0.0; 3], 5).unwrap();
    assert!(map.find([3.1, 0.1, 0.1]).is_none(), "older of two equidistant voxels evicted");
    assert!(map.find([-3.1, 0.1, 0.1]).is_some());
    // Batches: evict_batch 3 frees three at once, then the next two creations need none.
    let cfg3 = MapConfig { evict_batch: 3, ..cfg };
    let (mut pool, mut index) = storage(6);
    let mut map = VoxelMap::new(&mut pool, &mut index, cfg3).unwrap();
    let six: Vec<MapPoint> = (0..6).map(|i| at(1.1 + i as f32, 0.1)).collect();
    map.insert_slice(&six, [0.0; 3], 1).unwrap();
    let st = map.insert_slice(&[at(0.1, 1.1), at(0.1, 2.1), at(0.1, 3.1)], [0.0; 3], 2).unwrap();
    assert_eq!((st.evicted_full, st.new_voxels), (3, 3));
    assert_eq!(map.counters().evicted_full, 3);
    check_index(&map);
}

#[test]
fn distance_sweep_evicts_voxels_behind_a_moving_sensor_at_a_bounded_rate() {
    let cfg = MapConfig { evict_radius: 5.0, sweep_per_insert: 8, ..MapConfig::VLP32C };
    let (mut pool, mut index) = storage(64);
    let mut map = VoxelMap::new(&mut pool, &mut index, cfg).unwrap();
    let pts: Vec<MapPoint> = (0..40)
        .map(|i| MapPoint {
            xyz: [(i % 8) as f32 * 0.4 + 0.1, (i / 8) as f32 * 0.4 + 0.1, 0.1],
            normal: None,
        })
        .collect();
    map.insert_slice(&pts, [0.0; 3], 1).unwrap();
    assert_eq!(map.len(), 40);
    // The sensor stays: nothing is evicted.
    let st = map.insert_slice(&[], [0.0; 3], 2).unwrap();
    assert_eq!(st.evicted_far, 0);
    // The sensor leaves: at most 8 slots are checked per call, so the 40 (plus the new
    // voxel near the sensor, which is checked and kept) are swept within ceil(41 / 8) = 6
    // calls; the voxel near the new position stays.
    let near = MapPoint { xyz: [100.1, 0.1, 0.1], normal: None };
    let mut total = 0;
    let mut calls = 0;
    while map.len() > 1 {
        let st = map.insert_slice(&[near], [100.0, 0.0, 0.0], 3 + calls).unwrap();
        assert!(st.evicted_far <= 8);
        total += st.evicted_far;
        calls += 1;
        check_index(&map);
        assert!(calls <= 6, "sweep too slow");
    }
    assert_eq!(total, 40);
    assert_eq!(map.voxel(map.find(near.xyz).unwrap()).unwrap().count, calls);
    assert_eq!(map.counters().evicted_far, 40);
    // Points beyond the radius are not inserted.
    let st = map.insert_slice(&pts, [100.0, 0.0, 0.0], 20).unwrap();
    assert_eq!((st.dropped_far, st.inserted), (40, 0));
}

/// A deterministic number in [0, 1) from integers.
fn hash01(a: i64, b: i64, c: i64) -> f64 {
    let mut r =
        Rng((a as u64).wrapping_mul(0x9E37_79B9) ^ (b as u64).wrapping_mul(0x85EB_CA6B) ^ (c as u64) << 40);
    r.uniform(0.0, 1.0)
}

/// The sensor position (2-D) at scan `t`: 2 km along +x, a 270 degree left turn of radius
/// 30 m, then 200 m along -y, crossing the first leg (whose voxels were evicted long ago).
fn trajectory(t: usize) -> [f64; 2] {
    let arc = 141; // 30 m * 3 pi / 2
    if t <= 2000 {
        [t as f64, 0.0]
    } else if t <= 2000 + arc {
        let a = -core::f64::consts::FRAC_PI_2 + (t - 2000) as f64 / 30.0;
        [2000.0 + 30.0 * libm::cos(a), 30.0 + 30.0 * libm::sin(a)]
    } else {
        let end = -core::f64::consts::FRAC_PI_2 + arc as f64 / 30.0;
        let p = [2000.0 + 30.0 * libm::cos(end), 30.0 + 30.0 * libm::sin(end)];
        [p[0], p[1] - (t - 2000 - arc) as f64]
    }
}

/// One downsampled scan at scan `t`: a point in every ground voxel within 12 m (2-D) of the
/// sensor, and the surface points of poles (every 25 m along x at y = 6, 3 m tall) in range.
fn scene_scan(t: usize, s: f64) -> Vec<MapPoint> {
    let [sx, sy] = trajectory(t);
    let r = 12.0;
    let mut out = Vec::new();
    let (x0, x1) = (libm::floor((sx - r) / s) as i64, libm::ceil((sx + r) / s) as i64);
    let (y0, y1) = (libm::floor((sy - r) / s) as i64, libm::ceil((sy + r) / s) as i64);
    for ix in x0..=x1 {
        for iy in y0..=y1 {
            let (cx, cy) = ((ix as f64 + 0.5) * s, (iy as f64 + 0.5) * s);
            if (cx - sx) * (cx - sx) + (cy - sy) * (cy - sy) > r * r {
                continue;
            }
            let u = 0.05 + 0.9 * hash01(ix, iy, t as i64);
            let v = 0.05 + 0.9 * hash01(iy, ix, 3 * t as i64 + 1);
            let w = hash01(ix ^ iy, t as i64, 7) - 0.5;
            out.push(mp([(ix as f64 + u) * s, (iy as f64 + v) * s, 0.1 + 0.004 * w], Some([0.0, 0.0, 1.0])));
        }
    }
    let mut px = libm::floor((sx - r) / 25.0) * 25.0;
    while px <= sx + r {
        if (px - sx) * (px - sx) + (6.0 - sy) * (6.0 - sy) <= r * r {
            for j in 0..6 {
                let a = core::f64::consts::TAU * hash01(px as i64, j, t as i64);
                let (ca, sa) = (libm::cos(a), libm::sin(a));
                out.push(mp([px + 0.1 * ca, 6.0 + 0.1 * sa, 0.5 + 0.5 * j as f64], Some([ca, sa, 0.0])));
            }
        }
        px += 25.0;
    }
    out
}

#[test]
fn long_trajectory_keeps_the_sensor_neighbourhood_intact_in_a_fixed_pool() {
    // 0.5 m voxels, 30 m eviction radius. A pool of 3072 voxels cannot hold the voxels the
    // scans leave within 30 m of the sensor (about 3,600): it runs full and evicts the
    // farthest. A pool of 8192 can: the distance sweep alone keeps it bounded.
    let full = run_trajectory(3072);
    assert!(full.evicted_full > 0, "the pool never ran full: {full:?}");
    let swept = run_trajectory(8192);
    assert!(swept.evicted_far > 100_000 && swept.evicted_full == 0, "{swept:?}");
}

/// Drives the map along [`trajectory`] with a pool of `cap` voxels, checking after every
/// scan that no voxel within 20 m of the sensor was lost and that counts (every scan) and
/// distributions (every 100 scans) equal a reference built from the points inserted.
fn run_trajectory(cap: usize) -> MapCounters {
    let cfg = MapConfig { evict_radius: 30.0, sweep_per_insert: 512, ..MapConfig::OS1_16 };
    let s = f64::from(cfg.voxel_size);
    let (mut pool, mut index) = storage(cap);
    let mut map = VoxelMap::new(&mut pool, &mut index, cfg).unwrap();
    // The reference: per key, the points since the voxel was (re)created (the first 50 kept).
    struct Ref {
        count: u32,
        pts: Vec<[f64; 3]>,
    }
    let mut model: HashMap<[i32; 3], Ref> = HashMap::new();
    let intact_radius = 20.0; // every voxel within this of the sensor must survive
    let steps = 2000 + 141 + 200;
    let mut max_len = 0;
    for t in 0..=steps {
        let [sx, sy] = trajectory(t);
        let sensor = p32([sx, sy, 1.5]);
        let scan = scene_scan(t, s);
        let st = map.insert_slice(&scan, sensor, t as u32).unwrap();
        assert_eq!((st.dropped_full, st.dropped_invalid, st.dropped_far), (0, 0, 0), "scan {t}");
        assert_eq!(st.inserted as usize, scan.len());
        assert!(map.len() <= cap);
        max_len = max_len.max(map.len());
        // Voxels gone from the map must have been far from the sensor.
        model.retain(|k, _| {
            if map.find_key(*k).is_some() {
                return true;
            }
            let c = to64(map.centre(*k));
            let d = crate::math::sqrt(
                (c[0] - sx) * (c[0] - sx) + (c[1] - sy) * (c[1] - sy) + (c[2] - 1.5) * (c[2] - 1.5),
            );
            assert!(d > intact_radius, "scan {t}: voxel {k:?} {d:.1} m from the sensor was evicted");
            false
        });
        for p in &scan {
            let k = map.key_of(p.xyz).unwrap();
            let e = model.entry(k).or_insert(Ref { count: 0, pts: Vec::new() });
            e.count += 1;
            if e.pts.len() < 50 {
                e.pts.push(to64(p.xyz));
            }
        }
        // Every voxel the model knows: present, with the count its history implies.
        for (k, r) in &model {
            let h = map.find_key(*k).unwrap_or_else(|| panic!("scan {t}: voxel {k:?} lost"));
            let v = map.voxel(h).unwrap();
            match v.state {
                VoxelState::Accumulating => assert_eq!(v.count, r.count, "scan {t} {k:?}"),
                _ => assert!(v.count <= r.count && (v.count == 25 || v.count == 50), "scan {t} {k:?}"),
            }
        }
        // Now and then, the distributions themselves near the sensor.
        if t % 100 == 0 {
            let mut checked = 0;
            for (k, r) in &model {
                let c = to64(map.centre(*k));
                if (c[0] - sx).hypot(c[1] - sy) > intact_radius {
                    continue;
                }
                let h = map.find_key(*k).unwrap();
                let got = map.voxel_moments(h).unwrap();
                let want = Moments::from_points(c, &r.pts[..got.n as usize]);
                let (gm, wm) = (got.mean().unwrap(), want.mean().unwrap());
                let (gc, wc) = (got.covariance(), want.covariance());
                for a in 0..3 {
                    assert!((gm[a] - wm[a]).abs() < 1e-4, "scan {t} {k:?}: {gm:?} vs {wm:?}");
                }
                for i in 0..6 {
                    assert!((gc[i] - wc[i]).abs() < 1e-6, "scan {t} {k:?}: {gc:?} vs {wc:?}");
                }
                checked += 1;
            }
            assert!(checked > 1500, "scan {t}: only {checked} voxels near the sensor");
        }
        if t % 200 == 0 {
            check_index(&map);
        }
    }
    let c = map.counters();
    assert!(c.created > 10 * cap as u64, "the pool was not cycled: {c:?}");
    assert!(max_len <= cap);
    assert_eq!(c.dropped_full, 0);
    std::println!("trajectory with {cap} voxels: {c:?}, at most {max_len} live");
    c
}

#[test]
fn floor_and_round_helpers_match_libm() {
    let mut rng = Rng(4);
    for i in 0..100_000 {
        let v = match i % 4 {
            0 => rng.uniform(-4e6, 4e6) as f32,
            1 => rng.uniform(-3.0, 3.0) as f32,
            2 => (rng.next_u64() % 2001) as f32 * 0.5 - 500.0, // integers and halves
            _ => f32::from_bits(rng.next_u64() as u32 & 0x4A7F_FFFF), // any value below 2^22
        };
        assert_eq!(floor_i32(v), libm::floorf(v) as i32, "{v}");
        let r = round_sat(v, 32767.0);
        let c = v.clamp(-32767.0, 32767.0);
        assert!((r as f32 - c).abs() <= 0.5 + 2.0 * f32::EPSILON * c.abs(), "{v} {r}");
    }
    assert_eq!(floor_i32(-0.0), 0);
    assert_eq!(floor_i32(-1e-30), -1);
    assert_eq!(round_sat(1e9, 127.0), 127);
    assert_eq!(round_sat(-1e9, 127.0), -127);
    assert_eq!(round_sat(f32::NAN, 127.0), 0);
}

#[test]
fn full_32_bit_hash_collisions_are_resolved_by_the_key() {
    // Birthday search for two keys with the same 32-bit hash.
    let mut seen: HashMap<u32, [i32; 3]> = HashMap::new();
    let mut pair = None;
    'search: for x in -200..200 {
        for y in -200..200 {
            for z in -20..20 {
                let k = [x, y, z];
                if let Some(other) = seen.insert(hash_key(k), k) {
                    pair = Some((other, k));
                    break 'search;
                }
            }
        }
    }
    let (a, b) = pair.expect("no collision among 6.4 million keys");
    assert_ne!(a, b);
    assert_eq!(hash_key(a), hash_key(b));
    let cfg = MapConfig { evict_radius: 1e4, ..MapConfig::VLP32C };
    let (mut pool, mut index) = storage(8);
    let mut map = VoxelMap::new(&mut pool, &mut index, cfg).unwrap();
    let inside =
        |k: [i32; 3]| [(k[0] as f32 + 0.3) * 0.4, (k[1] as f32 + 0.6) * 0.4, (k[2] as f32 + 0.5) * 0.4];
    // `a` first, so a probe for `b`'s hash meets `a`'s entry before `b`'s.
    for (i, k) in [a, b].into_iter().enumerate() {
        map.insert_slice(&[MapPoint { xyz: inside(k), normal: None }], [0.0; 3], i as u32).unwrap();
    }
    assert_eq!(map.len(), 2);
    assert_eq!(map.voxel(map.find_key(a).unwrap()).unwrap().key, a);
    assert_eq!(map.voxel(map.find_key(b).unwrap()).unwrap().key, b);
    let mut out = Neighbours::new();
    assert_eq!(map.knn(inside(b), &KnnQuery::new(5, 0.4), &mut out), 1);
    assert_eq!(out.as_slice()[0].voxel, map.find_key(b).unwrap());
    // Removing `a` leaves `b` reachable.
    let sa = map.find_key(a).unwrap().index();
    map.remove_slot(sa);
    check_index(&map);
    assert!(map.find_key(a).is_none());
    assert_eq!(map.knn(inside(b), &KnnQuery::new(5, 0.4), &mut out), 1);
}

#[test]
fn block_hashes_derive_every_neighbour_hash() {
    let mut rng = Rng(17);
    for _ in 0..2000 {
        let q = p32([rng.uniform(-1e4, 1e4), rng.uniform(-1e4, 1e4), rng.uniform(-50.0, 50.0)]);
        let (mut pool, mut index) = storage(1);
        let map = VoxelMap::new(&mut pool, &mut index, MapConfig::VLP32C).unwrap();
        let pre = map.prepare(q).unwrap();
        for off in NEIGHBOURS {
            let k = pre.key;
            assert_eq!(pre.hash(off), hash_key([k[0] + off[0], k[1] + off[1], k[2] + off[2]]));
        }
    }
    // The 8 voxels of a block have consecutive home buckets.
    let base = hash_key([4, -6, 10]) & !7;
    for i in 0..8 {
        assert_eq!(hash_key([4 + (i & 1), -6 + (i >> 1 & 1), 10 + (i >> 2)]), base | i as u32);
    }
}
