//! Tests of the k-NN search against brute force over every representative, for both reaches,
//! with and without one point per voxel.

use super::*;

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
            (5, 0.4, false, false, KnnReach::Exact),
            (1, 0.4, false, false, KnnReach::Exact),
            (8, 0.3, false, false, KnnReach::Exact),
            (5, 0.4, true, false, KnnReach::Exact),
            (8, 0.25, true, false, KnnReach::Exact),
            // Beyond one voxel: exact within the 27-voxel block.
            (5, 1.0, false, true, KnnReach::Exact),
            (5, 1.0, true, true, KnnReach::Exact),
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
        KnnQuery { k: 8, max_dist: 1.0, one_per_voxel: true, reach: KnnReach::Exact },
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
