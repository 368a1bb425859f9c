//! Tests of the distributions: incremental sums equal batch moments in any order, planes
//! converge, corners, poles and clouds saturate, and fixed voxels stay fixed.

use super::*;

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
