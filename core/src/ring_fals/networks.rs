//! The sorting and selection networks of the median, each as data and as straight-line lane code;
//! separate so that the tests check the data exhaustively (0-1 principle) apart from its use.

use super::median::{Lane, WideLane};

/// Optimal 9-comparator sorting network for 5 values.
#[inline(always)]
pub(super) fn sort5(v: &mut [i16; 5]) {
    macro_rules! s {
        ($a:expr, $b:expr) => {{
            let (x, y) = (v[$a], v[$b]);
            v[$a] = x.min(y);
            v[$b] = x.max(y);
        }};
    }
    s!(0, 1);
    s!(3, 4);
    s!(2, 4);
    s!(2, 3);
    s!(0, 3);
    s!(0, 2);
    s!(1, 4);
    s!(1, 3);
    s!(1, 2);
}

/// Which outputs of a comparator are used: both, only the minimum (`L`), only the maximum (`H`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[allow(dead_code)]
pub(super) enum Cx {
    B,
    L,
    H,
}

// The comparators' `QLANES`-lane minimum and maximum through `wide`: one or two vector
// instructions on every target. Written per lane they were left to LLVM's vectoriser, which in
// an arm64 build of `82166eb` (a change elsewhere in the crate) left the whole median network
// of the general path on scalar registers: `median_group` 13.1 -> 28.8 M instructions a scan.
#[inline(always)]
fn lmin(a: Lane, b: Lane) -> Lane {
    WideLane::new(a).min(WideLane::new(b)).to_array()
}

#[inline(always)]
fn lmax(a: Lane, b: Lane) -> Lane {
    WideLane::new(a).max(WideLane::new(b)).to_array()
}

/// Defines a selection network both as data (for the exhaustive tests) and as straight-line code
/// (for speed): comparator (a, b, kind) leaves the minimum on wire a and the maximum on wire b;
/// the outputs are the listed wires.
macro_rules! median_network {
    ($(#[$m:meta])* $data:ident, $apply:ident, [$($out:expr),+]; $(($a:expr, $b:expr, $k:ident)),* $(,)?) => {
        $(#[$m])*
        #[allow(dead_code)]
        pub(super) const $data: (&[(u8, u8, Cx)], &[usize]) = (&[$(($a, $b, Cx::$k)),*], &[$($out),+]);

        // Inlined: out of line, the calls cost 20 % more of `smooth` here. The input is copied
        // into a local so that only constant indices touch it and it can live in registers.
        #[inline(always)]
        pub(super) fn $apply(v: &[Lane; 25]) -> [Lane; [$($out),+].len()] {
            let mut w = *v;
            let v = &mut w;
            $( median_network!(@cx v, $a, $b, $k); )*
            [$(v[$out]),+]
        }
    };
    (@cx $v:ident, $a:expr, $b:expr, B) => {{ let (x, y) = ($v[$a], $v[$b]); $v[$a] = lmin(x, y); $v[$b] = lmax(x, y); }};
    (@cx $v:ident, $a:expr, $b:expr, L) => {{ $v[$a] = lmin($v[$a], $v[$b]); }};
    (@cx $v:ident, $a:expr, $b:expr, H) => {{ $v[$b] = lmax($v[$a], $v[$b]); }};
}

median_network! {
    /// Median of 25 values: Batcher's odd-even merge sort for 32 inputs restricted to 25,
    /// pruned backwards from output 12, then stripped of every comparator whose removal the
    /// exhaustive 0-1 check allows (107 comparators, 190 min/max operations; pruning alone left
    /// 113 and 202).
    MEDIAN25, median25, [12];
    (0, 1, B), (2, 3, B), (4, 5, B), (6, 7, B), (8, 9, B), (10, 11, B), (12, 13, B), (14, 15, B),
    (16, 17, B), (18, 19, B), (20, 21, B), (22, 23, B), (0, 2, B), (1, 3, B), (4, 6, B), (5, 7, B),
    (8, 10, B), (9, 11, B), (12, 14, B), (13, 15, B), (16, 18, B), (17, 19, B), (20, 22, B),
    (21, 23, B), (1, 2, B), (5, 6, B), (9, 10, B), (13, 14, B), (17, 18, B), (21, 22, B),
    (0, 4, B), (1, 5, B), (2, 6, B), (3, 7, B), (8, 12, B), (9, 13, B), (10, 14, B), (11, 15, B),
    (16, 20, B), (17, 21, B), (18, 22, B), (19, 23, B), (2, 4, B), (3, 5, B), (10, 12, B),
    (11, 13, B), (18, 20, B), (19, 21, B), (1, 2, B), (3, 4, B), (5, 6, B), (9, 10, B),
    (11, 12, B), (13, 14, B), (17, 18, B), (19, 20, B), (21, 22, B), (0, 8, H), (1, 9, H),
    (2, 10, B), (3, 11, B), (4, 12, B), (5, 13, B), (6, 14, L), (7, 15, L), (16, 24, B), (4, 8, B),
    (5, 9, B), (6, 10, B), (7, 11, B), (20, 24, B), (2, 4, H), (3, 5, B), (6, 8, B), (7, 9, B),
    (10, 12, B), (11, 13, B), (18, 20, B), (22, 24, B), (3, 4, B), (5, 6, B), (7, 8, B),
    (9, 10, B), (11, 12, B), (17, 18, B), (19, 20, B), (21, 22, B), (23, 24, B), (3, 19, H),
    (4, 20, H), (5, 21, H), (6, 22, L), (7, 23, L), (8, 24, L), (8, 16, H), (9, 17, H),
    (10, 18, L), (11, 19, L), (12, 20, L), (13, 21, L), (6, 10, H), (7, 11, H), (12, 16, L),
    (13, 17, L), (10, 12, H), (11, 13, L), (11, 12, H)
}

median_network! {
    /// Ranks 10, 11 and 12 (from 0) of 25 values given as five sorted columns of five (wires
    /// 5c..5c+4 ascending): a full sort (the rows by five-sorters, then Batcher's network)
    /// pruned backwards from the three outputs, stripped of comparators whose order the sorted
    /// columns already fix and then of every comparator the exhaustive 0-1 check shows
    /// unneeded (75 comparators, 127 min/max operations).
    RANKS25_PRESORTED, ranks25_presorted, [10, 11, 12];
    (0, 5, B), (10, 15, B), (0, 10, H), (5, 15, B), (1, 6, B), (16, 21, B), (11, 21, B),
    (11, 16, B), (1, 16, H), (6, 21, B), (6, 16, B), (6, 11, B), (2, 7, B), (17, 22, B),
    (12, 22, B), (12, 17, B), (2, 17, B), (2, 12, B), (7, 22, L), (7, 17, B), (7, 12, B),
    (3, 8, B), (13, 23, B), (13, 18, B), (3, 13, B), (8, 23, L), (8, 18, B), (8, 13, B), (4, 9, B),
    (19, 24, B), (4, 19, B), (4, 14, B), (9, 24, L), (9, 19, L), (9, 14, B), (4, 5, B),
    (14, 15, L), (5, 7, B), (8, 10, B), (9, 11, B), (12, 14, B), (5, 6, B), (9, 10, B),
    (13, 14, B), (16, 20, B), (17, 21, L), (2, 4, H), (3, 5, H), (10, 12, B), (11, 13, B),
    (18, 20, L), (5, 6, B), (11, 12, B), (13, 14, L), (17, 18, B), (4, 8, H), (5, 9, H),
    (6, 10, B), (7, 11, B), (6, 8, H), (7, 9, B), (11, 13, L), (7, 8, B), (9, 10, B), (11, 12, B),
    (8, 16, H), (9, 17, B), (10, 18, L), (12, 16, L), (13, 17, L), (7, 9, H), (10, 12, B),
    (11, 13, L), (9, 10, H), (11, 12, B)
}

median_network! {
    /// Ranks 6 to 12 (from 0) of 25 values given as five sorted columns of five, for windows
    /// with up to 12 pixels left out as +inf: the rows by five-sorters and Batcher's network,
    /// pruned backwards from the seven outputs and stripped of every comparator the exhaustive
    /// 0-1 check on sorted columns shows unneeded (87 comparators, 156 min/max operations).
    RANKS25_PRESORTED_WIDE, ranks25_presorted_wide, [6, 7, 8, 9, 10, 11, 12];
    (10, 15, B), (0, 15, B), (0, 10, B), (5, 15, B), (5, 10, B), (1, 6, B), (16, 21, B),
    (11, 21, B), (11, 16, B), (1, 16, B), (1, 11, H), (6, 21, B), (6, 16, B), (6, 11, B),
    (2, 7, B), (17, 22, B), (12, 17, B), (2, 17, B), (2, 12, B), (7, 22, B), (7, 17, B),
    (7, 12, B), (3, 8, B), (18, 23, B), (13, 18, B), (3, 18, B), (8, 18, B), (8, 13, B), (4, 9, B),
    (19, 24, B), (14, 24, L), (4, 19, B), (9, 19, L), (4, 5, B), (14, 15, B), (22, 23, L),
    (0, 2, H), (5, 7, B), (8, 10, B), (9, 11, B), (12, 14, B), (5, 6, B), (9, 10, B), (13, 14, B),
    (21, 22, L), (3, 7, B), (11, 15, L), (16, 20, B), (17, 21, L), (2, 4, H), (3, 5, B),
    (10, 12, B), (11, 13, B), (18, 20, L), (3, 4, B), (5, 6, B), (9, 10, B), (11, 12, B),
    (13, 14, L), (17, 18, B), (4, 8, B), (5, 9, B), (6, 10, B), (7, 11, B), (6, 8, B), (7, 9, B),
    (10, 12, B), (11, 13, B), (5, 6, B), (7, 8, B), (9, 10, B), (11, 12, B), (8, 16, B),
    (9, 17, B), (10, 18, L), (4, 8, H), (12, 16, L), (13, 17, L), (3, 5, H), (6, 8, B), (7, 9, B),
    (10, 12, B), (11, 13, L), (5, 6, H), (7, 8, B), (9, 10, B), (11, 12, B)
}
