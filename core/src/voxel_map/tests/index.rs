//! Tests of the hash index: a `HashMap` model with colliding hashes, full 32-bit collisions
//! resolved by the key, and the block hashes from which the k-NN derives its neighbours' hashes.

use super::*;
use crate::voxel_map::index::{index_find, index_insert, index_remove_at};
use crate::voxel_map::knn::NEIGHBOURS;

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
