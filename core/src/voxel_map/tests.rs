//! Tests of the map against exact references, one file per part of the map in `tests/`; here
//! the helpers they share and the tests of the layout, the construction and bad input.
extern crate std;
use std::collections::HashMap;
use std::vec;
use std::vec::Vec;

use super::voxel::round_sat;
use super::*;
use crate::math::floor_i32;

use crate::surfel::{Moments, Shape, SurfelCriteria, SurfelReject};
use crate::testutil::SplitMix as Rng;

mod distribution;
mod evict;
mod index;
mod knn;
mod surfels;

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
