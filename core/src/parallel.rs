//! Work in independent ranges, run by the caller's threads.
//!
//! The core owns no threads and allocates nothing: where a stage splits into independent
//! pieces (the association's search, point by point; the Ring FALS normals beside the
//! downsampling's voxel binning), it builds one job per piece over
//! disjoint slices and hands them to a [`Parallel`] the caller supplies (the host's thread pool;
//! [`Sequential`] runs them one after another). Each piece writes only its own slots and the
//! results are combined in piece order, so the output is bit-identical for any width.

/// One job: runs once, on any thread.
pub type Job<'a> = &'a mut (dyn FnMut() + Send);

/// Runs independent jobs, e.g. on a pool of threads.
pub trait Parallel: Sync {
    /// How many jobs it runs at once; the core splits work into at most this many pieces
    /// (1: no split).
    fn width(&self) -> usize;
    /// Runs every job exactly once and returns when all have finished.
    fn run(&self, jobs: &mut [Job<'_>]);
}

/// Runs the jobs one after another on the calling thread.
#[derive(Clone, Copy, Debug, Default)]
pub struct Sequential;

impl Parallel for Sequential {
    fn width(&self) -> usize {
        1
    }
    fn run(&self, jobs: &mut [Job<'_>]) {
        for j in jobs.iter_mut() {
            j();
        }
    }
}

/// The most pieces a stage is split into.
pub const MAX_WIDTH: usize = 8;

/// `n` items in `pieces` contiguous ranges whose starts are multiples of `align` (so that the
/// pieces' inner chunking matches the sequential one), the first ones longer; empty ranges are
/// left out. Returns the ends of the ranges.
pub fn split(n: usize, pieces: usize, align: usize) -> heapless::Vec<usize, MAX_WIDTH> {
    let mut ends = heapless::Vec::new();
    let align = align.max(1);
    let blocks = n.div_ceil(align);
    let pieces = pieces.clamp(1, MAX_WIDTH).min(blocks.max(1));
    let mut done = 0;
    for p in 0..pieces {
        let take = blocks / pieces + usize::from(p < blocks % pieces);
        done = (done + take * align).min(n);
        if ends.last() != Some(&done) {
            // Cannot fail: at most MAX_WIDTH pieces.
            let _ = ends.push(done);
        }
    }
    ends
}

/// Fills `out[k] = f(k)` for every `k`, in pieces on `parallel`'s threads (each piece writes
/// only its own slots; starts aligned to 64 entries): the same as one loop for any width.
pub fn map_indexed<U: Send>(parallel: &dyn Parallel, out: &mut [U], f: impl Fn(usize) -> U + Sync) {
    map_chunks(parallel, out, 64, |k, run| {
        for (i, v) in run.iter_mut().enumerate() {
            *v = f(k + i);
        }
    });
}

/// [`map_indexed`] by runs of `chunk` slots (for work on vector lanes): `f(first, run)` fills
/// `out[first..first + run.len()]`, every run `chunk` long but the last. Pieces start on runs'
/// starts, so the runs are the same as one loop's for any width.
pub fn map_chunks<U: Send>(
    parallel: &dyn Parallel,
    out: &mut [U],
    chunk: usize,
    f: impl Fn(usize, &mut [U]) + Sync,
) {
    let chunk = chunk.max(1);
    let ends = split(out.len(), parallel.width(), 64usize.next_multiple_of(chunk));
    let f = &f;
    let mut rest = out;
    let mut closures = heapless::Vec::<_, MAX_WIDTH>::new();
    let mut from = 0;
    for &end in &ends {
        let (piece, r) = core::mem::take(&mut rest).split_at_mut(end - from);
        rest = r;
        let first = from;
        // Cannot fail: at most MAX_WIDTH pieces.
        let _ = closures.push(move || {
            for (k, run) in piece.chunks_mut(chunk).enumerate() {
                f(first + k * chunk, run);
            }
        });
        from = end;
    }
    let mut jobs = heapless::Vec::<Job<'_>, MAX_WIDTH>::new();
    for c in closures.iter_mut() {
        let _ = jobs.push(c);
    }
    parallel.run(&mut jobs);
}

/// Splits `a` (and `b`, the same length, where given) into the pieces of
/// [`split`]`(a.len(), width, align)` and runs `f(first, piece_of_a, piece_of_b, slot)` for each
/// on `parallel`'s threads, each with its own slot of `slots` (the pieces in order). Returns the
/// number of pieces. `b` shorter than `a`: its pieces are cut to what it holds.
pub fn map_pieces2<A: Send, B: Send, R: Send>(
    parallel: &dyn Parallel,
    a: &mut [A],
    b: Option<&mut [B]>,
    align: usize,
    slots: &mut [R; MAX_WIDTH],
    f: impl Fn(usize, &mut [A], Option<&mut [B]>, &mut R) + Sync,
) -> usize {
    let ends = split(a.len(), parallel.width(), align);
    let f = &f;
    let (mut rest_a, mut rest_b) = (a, b);
    let mut closures = heapless::Vec::<_, MAX_WIDTH>::new();
    let mut start = 0;
    for (&end, slot) in ends.iter().zip(slots.iter_mut()) {
        let (piece_a, r) = core::mem::take(&mut rest_a).split_at_mut(end - start);
        rest_a = r;
        let mut piece_b = rest_b.take().map(|all| {
            let (x, y) = all.split_at_mut((end - start).min(all.len()));
            rest_b = Some(y);
            x
        });
        let first = start;
        // Cannot fail: at most MAX_WIDTH pieces.
        let _ = closures.push(move || f(first, &mut *piece_a, piece_b.as_deref_mut(), &mut *slot));
        start = end;
    }
    let mut jobs = heapless::Vec::<Job<'_>, MAX_WIDTH>::new();
    for c in closures.iter_mut() {
        let _ = jobs.push(c);
    }
    parallel.run(&mut jobs);
    ends.len()
}

/// Scans between two tries of an arrangement not in use ([`Arrangement`]).
pub const ARRANGEMENT_EXPLORE: u16 = 16;

/// The most arrangements an [`Arrangement`] chooses among.
pub const ARRANGEMENT_MAX: usize = 4;

/// Which of a few arrangements of a stage's jobs runs: the same jobs, each writing only its
/// own data, put together differently on the threads (so the results are the same bits every
/// way; only the time differs). Which one is shortest depends on the scene and the machine: on
/// a street the map insertion makes the voxel search's job the longer one, indoors Ring FALS's.
///
/// The choice follows the stage's time as the caller's clock gives it. One arrangement is in
/// use, with a running mean of its last scans' times (half the weight to each new one: it
/// follows the scene). Every [`ARRANGEMENT_EXPLORE`] scans one of the others runs once (each in
/// turn), and it takes over if it was shorter than that mean by more than
/// [`ARRANGEMENT_MARGIN`]: a comparison with the scans just before, of about the same scene (a
/// mean kept for an arrangement not in use would be of scans long past). Without a clock
/// (every time 0) the first arrangement in use stays.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Arrangement {
    arms: u8,
    current: u8,
    /// The arrangement tried last (the next try is the one after it, skipping `current`).
    tried: u8,
    mean_ns: u64,
    since: u16,
}

impl Default for Arrangement {
    fn default() -> Self {
        Self::new()
    }
}

/// How much shorter (a fraction) another arrangement's try must be to take over.
pub const ARRANGEMENT_MARGIN: f32 = 0.03;

impl Arrangement {
    /// Two arrangements, no times yet: the first in use.
    pub const fn new() -> Self {
        Self::with_arms(2, 0)
    }

    /// `arms` arrangements (2 to [`ARRANGEMENT_MAX`]), `first` in use until a try beats it.
    pub const fn with_arms(arms: usize, first: usize) -> Self {
        let arms = if arms < 2 {
            2
        } else if arms > ARRANGEMENT_MAX {
            ARRANGEMENT_MAX
        } else {
            arms
        };
        let first = if first < arms { first } else { 0 };
        Self { arms: arms as u8, current: first as u8, tried: first as u8, mean_ns: 0, since: 0 }
    }

    /// The arrangement for the next stage: `0..arms`.
    pub fn pick(&mut self) -> usize {
        let current = usize::from(self.current);
        if self.mean_ns == 0 {
            return current;
        }
        self.since = self.since.saturating_add(1);
        if self.since >= ARRANGEMENT_EXPLORE {
            self.since = 0;
            let arms = usize::from(self.arms);
            let mut next = (usize::from(self.tried) + 1) % arms;
            if next == current {
                next = (next + 1) % arms;
            }
            self.tried = next as u8;
            return next;
        }
        current
    }

    /// The stage's time with arrangement `arm`, the one [`Self::pick`] gave (0 = no clock:
    /// ignored). An arrangement other than the one in use is only ever a try.
    pub fn record(&mut self, arm: usize, ns: u64) {
        if ns == 0 || arm >= usize::from(self.arms) {
            return;
        }
        if arm == usize::from(self.current) {
            self.mean_ns = if self.mean_ns == 0 { ns } else { (self.mean_ns + ns) / 2 };
        } else if (ns as f32) < self.mean_ns as f32 * (1.0 - ARRANGEMENT_MARGIN) {
            self.current = arm as u8;
            self.mean_ns = ns;
        }
    }

    /// The arrangement in use.
    pub fn current(&self) -> usize {
        usize::from(self.current)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::testutil::Threads;

    #[test]
    fn splits_cover_everything_on_aligned_starts() {
        for n in [0usize, 1, 63, 64, 65, 500, 4096, 10_000] {
            for pieces in 1..=MAX_WIDTH + 2 {
                let ends = split(n, pieces, 64);
                assert!(ends.len() <= pieces.min(MAX_WIDTH), "{n} {pieces} {ends:?}");
                assert_eq!(ends.last().copied().unwrap_or(0), n, "{n} {pieces} {ends:?}");
                let mut start = 0;
                for &e in &ends {
                    assert!(e > start || n == 0, "{n} {pieces} {ends:?}");
                    assert_eq!(start % 64, 0, "{n} {pieces} {ends:?}");
                    start = e;
                }
            }
        }
    }

    #[test]
    fn map_indexed_equals_one_loop_for_any_width() {
        for n in [0usize, 1, 64, 65, 1000] {
            let want: std::vec::Vec<u64> =
                (0..n).map(|k| (k as u64).wrapping_mul(0x9E37_79B9) >> 3).collect();
            for w in 1..=MAX_WIDTH + 1 {
                let mut got = std::vec![0u64; n];
                map_indexed(&Threads(w), &mut got, |k| (k as u64).wrapping_mul(0x9E37_79B9) >> 3);
                assert_eq!(got, want, "n {n} width {w}");
            }
        }
    }

    #[test]
    fn map_chunks_equals_one_loop_for_any_width() {
        for n in [0usize, 1, 8, 63, 64, 65, 1000] {
            for chunk in [1usize, 8, 48] {
                // Each slot: its index and its run's start, which must be a multiple of `chunk`.
                let want: std::vec::Vec<(usize, usize)> = (0..n).map(|k| (k, k - k % chunk)).collect();
                for w in 1..=MAX_WIDTH + 1 {
                    let mut got = std::vec![(0usize, 0usize); n];
                    map_chunks(&Threads(w), &mut got, chunk, |first, run| {
                        assert!(run.len() == chunk || first + run.len() == n);
                        for (l, v) in run.iter_mut().enumerate() {
                            *v = (first + l, first);
                        }
                    });
                    assert_eq!(got, want, "n {n} chunk {chunk} width {w}");
                }
            }
        }
    }

    /// The arrangement in use runs, the other once every `ARRANGEMENT_EXPLORE` scans, taking
    /// over when it is shorter by more than the margin; without a clock always the first.
    #[test]
    fn the_shorter_arrangement_runs_and_the_other_is_tried_now_and_then() {
        let mut none = Arrangement::new();
        for _ in 0..100 {
            let a = none.pick();
            assert_eq!(a, 0);
            none.record(a, 0);
        }
        let explore = usize::from(ARRANGEMENT_EXPLORE);
        let run = |arr: &mut Arrangement, cost: [u64; 2], scans: usize| {
            let mut runs = [0u32; 2];
            for _ in 0..scans {
                let a = arr.pick();
                runs[a] += 1;
                arr.record(a, cost[a]);
            }
            runs
        };
        // Arrangement 1 takes 3 ms, 0 takes 5 ms: 1 takes over at the first try and keeps it,
        // 0 tried once in every ARRANGEMENT_EXPLORE scans.
        let mut arr = Arrangement::new();
        let runs = run(&mut arr, [5_000_000, 3_000_000], 10 * explore);
        assert_eq!(arr.current(), 1);
        // The first ARRANGEMENT_EXPLORE scans before the first try, then one try in each
        // ARRANGEMENT_EXPLORE of the other 9 * ARRANGEMENT_EXPLORE scans (but the first).
        assert_eq!(runs, [explore as u32 + 8, 9 * explore as u32 - 8], "{runs:?}");
        // The scene changes: 1 now takes 7 ms; 0 takes over at a try once the mean has
        // followed (within two tries).
        let runs = run(&mut arr, [5_000_000, 7_000_000], 2 * explore);
        assert_eq!(arr.current(), 0, "{runs:?}");
        // Within the margin (2 % shorter) nothing changes hands.
        let runs = run(&mut arr, [5_000_000, 4_900_000], 10 * explore);
        assert_eq!(arr.current(), 0);
        assert_eq!(runs[1], 10, "{runs:?}");
    }

    #[test]
    fn with_four_arrangements_each_other_is_tried_in_turn_and_the_shortest_stays() {
        let explore = usize::from(ARRANGEMENT_EXPLORE);
        let mut arr = Arrangement::with_arms(4, 2);
        assert_eq!(arr.pick(), 2, "no times yet: the first in use");
        let cost = [6_000_000u64, 5_000_000, 4_000_000, 3_000_000];
        let mut runs = [0u32; 4];
        arr.record(2, cost[2]);
        for _ in 0..12 * explore {
            let a = arr.pick();
            runs[a] += 1;
            arr.record(a, cost[a]);
        }
        // 3 is tried first after 2 (the next in turn) and takes over; then 0, 1 and 2 are
        // tried in turn, one scan in ARRANGEMENT_EXPLORE, and lose.
        assert_eq!(arr.current(), 3, "{runs:?}");
        assert_eq!(runs[0] + runs[1] + runs[2] + runs[3], 12 * explore as u32);
        assert_eq!(runs[0], 4, "{runs:?}");
        assert_eq!(runs[1], 4, "{runs:?}");
        assert!(runs[2] >= explore as u32 - 1 && runs[2] <= explore as u32 + 4, "{runs:?}");
        // Out-of-range arms and counts are clamped, never a panic.
        let mut odd = Arrangement::with_arms(9, 7);
        assert_eq!(odd.pick(), 0);
        odd.record(5, 1);
        assert_eq!(Arrangement::with_arms(1, 1).pick(), 1, "two arms at least");
    }

    #[test]
    fn sequential_runs_each_job_once() {
        let mut hits = [0u32; 3];
        {
            let (a, rest) = hits.split_at_mut(1);
            let (b, c) = rest.split_at_mut(1);
            let mut ja = || a[0] += 1;
            let mut jb = || b[0] += 1;
            let mut jc = || c[0] += 1;
            let mut jobs: [Job<'_>; 3] = [&mut ja, &mut jb, &mut jc];
            Sequential.run(&mut jobs);
        }
        assert_eq!(hits, [1, 1, 1]);
    }
}
