//! Tests of bounded memory: insertion and eviction against a model, the eviction order, the
//! distance sweep, and long drives through a fixed pool.

use super::*;

proptest::proptest! {
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
