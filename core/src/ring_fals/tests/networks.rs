//! Tests of the selection networks: each as data on every 0/1 input (the 0-1 principle), and
//! its straight-line lane code against sorting.
use crate::ring_fals::median::{Lane, QLANES};
use crate::ring_fals::networks::{
    Cx, MEDIAN25, RANKS25_PRESORTED, RANKS25_PRESORTED_WIDE, median25, ranks25_presorted,
    ranks25_presorted_wide, sort5,
};

/// Runs a network on 64 bit-sliced 0/1 inputs at once (min = AND, max = OR).
fn run_bits(net: &[(u8, u8, Cx)], v: &mut [u64; 25]) {
    for &(a, b, k) in net {
        let (x, y) = (v[a as usize], v[b as usize]);
        match k {
            Cx::B => {
                v[a as usize] = x & y;
                v[b as usize] = x | y;
            }
            Cx::L => v[a as usize] = x & y,
            Cx::H => v[b as usize] = x | y,
        }
    }
}

/// 0-1 principle: a comparator network selects the median of every input iff it does for
/// every 0/1 input. All 2^25 inputs, 64 per word.
#[test]
fn median25_is_exact_for_all_zero_one_inputs() {
    let (net, out) = (MEDIAN25.0, MEDIAN25.1[0]);
    for hi in 0u64..(1 << 19) {
        let mut v = [0u64; 25];
        for (i, w) in v.iter_mut().enumerate() {
            *w = if i < 6 {
                // Bits 0..6 of the input vary along the 64 lanes.
                let mut m = 0u64;
                for lane in 0..64u64 {
                    if lane >> i & 1 == 1 {
                        m |= 1 << lane;
                    }
                }
                m
            } else if hi >> (i - 6) & 1 == 1 {
                u64::MAX
            } else {
                0
            };
        }
        let ones: [u32; 64] =
            core::array::from_fn(|lane| (0..25).filter(|&i| v[i] >> lane & 1 == 1).count() as u32);
        run_bits(net, &mut v);
        for (lane, &n1) in ones.iter().enumerate() {
            // The median (13th smallest) is 1 iff at least 13 ones.
            assert_eq!(v[out] >> lane & 1 == 1, n1 >= 13, "input {hi:x}/{lane}");
        }
    }
}

/// The presorted networks on every 0/1 input whose five columns are sorted (6^5 of them).
#[test]
fn ranks25_presorted_is_exact_for_sorted_columns() {
    for (net, outs) in [RANKS25_PRESORTED, RANKS25_PRESORTED_WIDE] {
        check_presorted(net, outs);
    }
}

fn check_presorted(net: &[(u8, u8, Cx)], outs: &[usize]) {
    let first = 13 - outs.len();
    for code in 0..6u32.pow(5) {
        let mut v = [0u64; 25];
        let mut ones = 0;
        let mut c = code;
        for col in 0..5 {
            let k = (c % 6) as usize;
            c /= 6;
            for rank in 5 - k..5 {
                v[5 * col + rank] = 1;
            }
            ones += k;
        }
        run_bits(net, &mut v);
        for (k, &out) in outs.iter().enumerate() {
            // Rank r = first + k (from 0) is 1 iff at least 25 - r ones.
            let r = first + k;
            assert_eq!(v[out] == 1, ones >= 25 - r, "code {code}, rank {r}");
        }
    }
}

#[test]
fn sort5_sorts_everything() {
    for bits in 0..32u32 {
        let mut v: [i16; 5] = core::array::from_fn(|i| (bits >> i & 1) as i16);
        sort5(&mut v);
        assert!(v.windows(2).all(|w| w[0] <= w[1]), "{bits:b}");
    }
}

#[test]
fn straight_line_networks_match_their_data() {
    // Pseudo-random lanes; the straight-line code must give the true median.
    let mut s = 0x1234_5678_9abc_def0u64;
    for _ in 0..200 {
        let mut v = [[0i16; QLANES]; 25];
        for x in v.iter_mut().flatten() {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            *x = (s % 2001) as i16 - 1000;
        }
        let sorted: [[i16; 25]; QLANES] = core::array::from_fn(|l| {
            let mut c: [i16; 25] = core::array::from_fn(|i| v[i][l]);
            c.sort();
            c
        });
        let rank = |k: usize| -> Lane { core::array::from_fn(|l| sorted[l][k]) };
        assert_eq!(median25(&v), [rank(12)]);
        // Presorted: sort each column of five first.
        let mut p = v;
        for l in 0..QLANES {
            for col in 0..5 {
                let mut c: [i16; 5] = core::array::from_fn(|k| p[5 * col + k][l]);
                c.sort();
                for k in 0..5 {
                    p[5 * col + k][l] = c[k];
                }
            }
        }
        assert_eq!(ranks25_presorted(&p), [rank(10), rank(11), rank(12)]);
        assert_eq!(ranks25_presorted_wide(&p), core::array::from_fn(|k| rank(6 + k)));
    }
}
