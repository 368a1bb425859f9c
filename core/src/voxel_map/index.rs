//! The hash index from voxel keys to pool positions (linear probing, backward-shift deletion, a
//! hash that keeps each 2x2x2 block in one cache line); separate because it sees only keys.

/// One slot of the hash index: the key's 32-bit hash and the pool position + 1 (0 = empty).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(transparent)]
pub struct IndexSlot(pub(super) u64);

impl IndexSlot {
    /// An empty slot (all-zero bytes).
    pub const EMPTY: IndexSlot = IndexSlot(0);

    #[inline]
    pub(super) fn new(hash: u32, slot: u32) -> Self {
        Self((u64::from(hash) << 32) | u64::from(slot + 1))
    }
    #[inline]
    pub(super) fn is_empty(self) -> bool {
        self.0 == 0
    }
    #[inline]
    pub(super) fn hash(self) -> u32 {
        (self.0 >> 32) as u32
    }
    #[inline]
    pub(super) fn slot(self) -> u32 {
        (self.0 as u32).wrapping_sub(1)
    }
}

/// 32-bit hash of a voxel key; the index bucket is its low bits.
///
/// The voxel's 2x2x2 block (`key >> 1`) is hashed (multiply-xor, then a 64-bit finaliser) into
/// the upper 29 bits and the voxel's position in the block fills the low 3, so the 8 voxels of a
/// block have consecutive home buckets: their index entries share one cache line, and a query,
/// which reads a voxel and its neighbours, touches a few index lines instead of one per voxel.
#[inline]
pub(super) fn hash_key(k: [i32; 3]) -> u32 {
    block_hash([k[0] >> 1, k[1] >> 1, k[2] >> 1]) << 3 | sub_block(k)
}

/// The 29-bit hash of a 2x2x2 block of voxels.
#[inline]
pub(super) fn block_hash(b: [i32; 3]) -> u32 {
    let h = u64::from(b[0] as u32).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ u64::from(b[1] as u32).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ u64::from(b[2] as u32).wrapping_mul(0x1656_67B1_9E37_79F9);
    let h = (h ^ (h >> 31)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    (h >> 35) as u32
}

/// A voxel's position in its 2x2x2 block, 0..8.
#[inline]
pub(super) fn sub_block(k: [i32; 3]) -> u32 {
    ((k[0] & 1) | (k[1] & 1) << 1 | (k[2] & 1) << 2) as u32
}

// ---- The open-addressing index (linear probing, backward-shift deletion) ----------------------

/// Finds the index position of the entry for a key with hash `h`; `is_key(slot)` confirms a
/// candidate. Stops at the first empty slot, and after `index.len()` probes at the latest.
#[inline]
pub(super) fn index_find(
    index: &[IndexSlot],
    mask: usize,
    h: u32,
    mut is_key: impl FnMut(u32) -> bool,
) -> Option<(usize, u32)> {
    let mut pos = h as usize & mask;
    for _ in 0..index.len() {
        let e = index[pos];
        if e.is_empty() {
            return None;
        }
        if e.hash() == h && is_key(e.slot()) {
            return Some((pos, e.slot()));
        }
        pos = (pos + 1) & mask;
    }
    None
}

/// The slot of the first entry with hash `h` (no key check, so no pool access: the caller
/// checks the key and falls back to [`index_find`] on the rare 32-bit hash collision).
#[inline]
pub(super) fn index_first_with_hash(index: &[IndexSlot], mask: usize, h: u32) -> Option<u32> {
    let mut pos = h as usize & mask;
    for _ in 0..index.len() {
        let e = index[pos];
        if e.is_empty() {
            return None;
        }
        if e.hash() == h {
            return Some(e.slot());
        }
        pos = (pos + 1) & mask;
    }
    None
}

/// Finds the index position that holds `slot` for a key with hash `h`.
#[inline]
pub(super) fn index_find_slot(index: &[IndexSlot], mask: usize, h: u32, slot: u32) -> Option<usize> {
    index_find(index, mask, h, |s| s == slot).map(|(pos, _)| pos)
}

/// Inserts an entry (the key must not be present). `false` if the index is full (cannot happen
/// while the load is at most 1/2).
#[inline]
pub(super) fn index_insert(index: &mut [IndexSlot], mask: usize, h: u32, slot: u32) -> bool {
    let mut pos = h as usize & mask;
    for _ in 0..index.len() {
        if index[pos].is_empty() {
            index[pos] = IndexSlot::new(h, slot);
            return true;
        }
        pos = (pos + 1) & mask;
    }
    false
}

/// Removes the entry at `pos` and shifts the following cluster back so no lookup needs a
/// tombstone: an entry moves into the hole if its home bucket is not cyclically inside
/// `(hole, entry]`.
pub(super) fn index_remove_at(index: &mut [IndexSlot], mask: usize, mut hole: usize) {
    index[hole] = IndexSlot::EMPTY;
    let mut j = hole;
    for _ in 0..index.len() {
        j = (j + 1) & mask;
        let e = index[j];
        if e.is_empty() {
            return;
        }
        let home = e.hash() as usize & mask;
        // Distance from home to j and from hole to j, cyclically.
        let d_home = j.wrapping_sub(home) & mask;
        let d_hole = j.wrapping_sub(hole) & mask;
        if d_home >= d_hole {
            index[hole] = e;
            index[j] = IndexSlot::EMPTY;
            hole = j;
        }
    }
}
