//! Stage 3, the 5x5 median over the valid pixels on the centre's surface, 16 columns at a time
//! (8 on arm64: `QLANES`); separate from the solve because it works on quantised lanes through
//! the selection networks.

use super::networks::{median25, ranks25_presorted, ranks25_presorted_wide, sort5};
use super::solve::rsqrt_norm;
use super::table::RingTable;
use super::{
    EMPTY, FULL, GAP, KEY_SCALE, PAD, QINVALID, QSCALE, RingFals, has_normal, pad_sentinel, wrap_row,
};

/// Lanes of the median (i16): 16 neighbouring columns, two SSE2 registers or one AVX2 register
/// per operation; on arm64 8, one NEON register, so that a window's 25 values fit in its 32
/// registers.
#[cfg(not(target_arch = "aarch64"))]
pub(super) const QLANES: usize = 16;
#[cfg(target_arch = "aarch64")]
pub(super) const QLANES: usize = 8;
/// One vector of quantised normal components.
pub(super) type Lane = [i16; QLANES];
/// `wide`'s vector of `QLANES` i16, through which the networks' comparators go.
#[cfg(not(target_arch = "aarch64"))]
pub(super) type WideLane = wide::i16x16;
#[cfg(target_arch = "aarch64")]
pub(super) type WideLane = wide::i16x8;

impl<const P: usize> RingFals<P> {
    /// Stage 3: the 5x5 median over valid pixels (per channel, columns wrapped, rows cut at the
    /// border) and normalisation. Skipped when the table's config disables the median.
    pub fn smooth(&mut self, table: &RingTable) {
        let (rows, cols, stride) = (self.rows, self.cols, self.stride);
        if rows == 0 || table.rows() != rows || table.cols() != cols || !table.config.median {
            return;
        }
        // Quantised planes of the image rows, then their wrapped pad columns.
        for r in PAD..PAD + rows {
            let s = r * stride..(r + 1) * stride;
            quantise_row(
                &self.nx[s.clone()],
                &self.ny[s.clone()],
                &self.nz[s.clone()],
                &self.state[s.clone()],
                &mut self.qx[s.clone()],
                &mut self.qy[s.clone()],
                &mut self.qz[s.clone()],
                &mut self.qinv[s.clone()],
            );
            wrap_row(&mut self.qx[s.clone()], cols);
            wrap_row(&mut self.qy[s.clone()], cols);
            wrap_row(&mut self.qz[s.clone()], cols);
            wrap_row(&mut self.qinv[s], cols);
        }

        let min_valid = table.config.median_min_valid as i16;
        let mut kept_own = 0u32;
        for r in 0..rows {
            // Column strips of rows r-2..=r+2 (padded rows r..=r+4): sorted values and counts.
            let top = r * stride;
            {
                let planes = [&self.qx, &self.qy, &self.qz];
                for (ch, q) in planes.iter().enumerate() {
                    let s: [&[i16]; 5] = core::array::from_fn(|i| &q[top + i * stride..][..stride]);
                    let (a, rest) = self.strips[ch * 5..ch * 5 + 5].split_at_mut(1);
                    let (b, rest) = rest.split_at_mut(1);
                    let (c, rest) = rest.split_at_mut(1);
                    let (d, e) = rest.split_at_mut(1);
                    sort_strips(
                        s,
                        [
                            &mut a[0][..stride],
                            &mut b[0][..stride],
                            &mut c[0][..stride],
                            &mut d[0][..stride],
                            &mut e[0][..stride],
                        ],
                    );
                }
                let s: [&[i16]; 5] = core::array::from_fn(|i| &self.qinv[top + i * stride..][..stride]);
                let dst = &mut self.strip_inv[..stride];
                for (j, d) in dst.iter_mut().enumerate() {
                    *d = s[0][j] + s[1][j] + s[2][j] + s[3][j] + s[4][j];
                }
                // Key ranges of the padded rows r..r + 5: all five for the first row, then the
                // one that enters.
                for pr in if r == 0 { 0..5 } else { r + 4..r + 5 } {
                    let i = pr * stride..(pr + 1) * stride;
                    key_range_row(
                        &self.key[i.clone()],
                        &self.qinv[i],
                        &mut self.row_kmax[pr % 5][..stride],
                        &mut self.row_kmin[pr % 5][..stride],
                    );
                }
            }

            let base = (r + PAD) * stride + PAD;
            // -inf pad pixels in the window of an even and of an odd image column c: the window
            // covers padded rows r..r + 5 and padded columns c..c + 5.
            let neg = |c: usize| {
                let pads = (r..r + 5).filter(|&pr| pr < PAD || pr >= rows + PAD);
                pads.map(|pr| (c..c + 5).filter(|&pc| pad_sentinel(pr, pc) == i16::MIN).count() as i16).sum()
            };
            let (neg_even, neg_odd) = (neg(0), neg(1));
            // Groups of `QLANES` columns; the last group is moved left to end at the last column
            // and skips the lanes the previous group already did.
            let mut c0 = 0;
            while c0 < cols {
                let c0_eff = c0.min(cols - QLANES);
                kept_own +=
                    self.median_group(table, r, base, c0_eff, c0 - c0_eff, min_valid, (neg_even, neg_odd));
                c0 += QLANES;
            }
        }
        self.stats.median_kept_own = kept_own;
    }

    /// Median of the 16 pixels at image columns c0..c0+16 of one image row. `pad_neg` is the
    /// number of -inf pad pixels in the window of an even and of an odd column. Returns how many
    /// kept their own normal.
    #[allow(clippy::too_many_arguments)]
    fn median_group(
        &mut self,
        table: &RingTable,
        r: usize,
        base: usize,
        c0: usize,
        first_lane: usize,
        min_valid: i16,
        pad_neg: (i16, i16),
    ) -> u32 {
        let rc = &table.row[r];
        let stride = self.stride;
        let centre = base + c0;
        let st: [u8; QLANES] =
            core::array::from_fn(|l| if l < first_lane { EMPTY } else { self.state[centre + l] });
        if st.iter().all(|&s| s != FULL && s != GAP) {
            return 0;
        }
        // Which window pixels take part, per lane: a valid normal on the centre's surface (the
        // range gate of the solve for the pixel's angular distance, on range keys). Leaving out
        // the wall behind a pole keeps the pole's edge normals from being pulled toward the
        // wall's.
        let sc = c0 + PAD; // strip column of the lane's own column
        let kc = lane_load(&self.key[centre..]);
        // Absolute part of the gate: log2(1 + abs / r) <= abs / (r ln 2).
        let tc: Lane = core::array::from_fn(|l| {
            round_small(
                (self.inv[centre + l]
                    * (table.config.range_jump_abs * KEY_SCALE * core::f32::consts::LOG2_E))
                    .min(30000.0),
            ) as i16
        });
        // Per window: how many pixels have no valid normal (pad rows included), and whether
        // the valid pixels' keys lie, row by row, within the row's smallest gate of the centre's.
        let mut out: Lane = [0; QLANES];
        for dc in 0..5 {
            let inv = lane_load(&self.strip_inv[sc + dc - 2..]);
            for l in 0..QLANES {
                out[l] -= inv[l];
            }
        }
        let mut one_surface = [true; QLANES];
        for dr in 0..5 {
            let (hi, lo) = (
                lane_load(&self.row_kmax[(r + dr) % 5][sc..]),
                lane_load(&self.row_kmin[(r + dr) % 5][sc..]),
            );
            let g = rc.gate5_min[dr];
            for l in 0..QLANES {
                let d = hi[l].saturating_sub(kc[l]).max(kc[l].saturating_sub(lo[l]));
                one_surface[l] &= d.saturating_sub(tc[l]) <= g;
            }
        }
        // The shared-strip path needs, in every lane that uses its median, all valid pixels
        // within the row's smallest gate of the centre's key (then none is left out by the
        // gate), and the lower median of the valid pixels at rank 6 to 12 of all 25 values:
        // invalid pixels sort as +inf, and pad pixels as -inf and +inf in the numbers
        // `pad_neg` gives. Without pad rows that is up to 12 invalid pixels; ranks 10 to 12
        // (up to 4) take a smaller network.
        let mut rank: Lane = [0; QLANES];
        let mut general: Lane = [0; QLANES];
        let mut low: Lane = [0; QLANES];
        for l in 0..QLANES {
            let neg = if (c0 + l) & 1 == 0 { pad_neg.0 } else { pad_neg.1 };
            rank[l] = neg + ((24 - out[l]) >> 1);
            let used = has_normal(st[l]) & (25 - out[l] >= min_valid);
            general[l] = -((used & !(one_surface[l] & (6..=12).contains(&rank[l]))) as i16);
            low[l] = -((used & (rank[l] < 10)) as i16);
        }
        let mut med = [[0i16; QLANES]; 3];
        let mut neg_count: Lane = [0; QLANES];
        if general == [0; QLANES] {
            // The sorted column strips are shared between windows.
            neg_count = out.map(|o| -o);
            let narrow = low == [0; QLANES];
            for (ch, m) in med.iter_mut().enumerate() {
                let mut v = [[0i16; QLANES]; 25];
                for dc in 0..5 {
                    for k in 0..5 {
                        v[5 * dc + k] = lane_load(&self.strips[ch * 5 + k][sc + dc - 2..]);
                    }
                }
                *m = if narrow {
                    pick_rank(&ranks25_presorted(&v), 10, &rank)
                } else {
                    pick_rank(&ranks25_presorted_wide(&v), 6, &rank)
                };
            }
        } else {
            let mut masks = [[0i16; QLANES]; 25];
            for dr in 0..5 {
                let row0 = centre + dr * stride - 2 * stride - 2;
                for dc in 0..5 {
                    let j = 5 * dr + dc;
                    let inv = lane_load(&self.qinv[row0 + dc..]);
                    let kq = lane_load(&self.key[row0 + dc..]);
                    let g = rc.gate5[j];
                    masks[j] = core::array::from_fn(|l| {
                        let d = kc[l].saturating_sub(kq[l]);
                        let d = d.max(0i16.saturating_sub(d));
                        inv[l] | -((d.saturating_sub(tc[l]) > g) as i16)
                    });
                }
            }
            // Left-out pixels enter the network as alternately -inf and +inf sentinels (per
            // window, in scan order), so that the network's middle output is the median of the
            // pixels kept (the lower median for an even count): value `(x | m) ^ c` with the
            // mask m all ones and c = i16::MIN (giving +inf) or i16::MAX (giving -inf).
            let mut c = [[0i16; QLANES]; 25];
            let mut tog: Lane = [0; QLANES];
            for j in 0..25 {
                let m = masks[j];
                for l in 0..QLANES {
                    neg_count[l] += m[l];
                    tog[l] ^= m[l];
                    c[j][l] = m[l] & (i16::MIN ^ (tog[l] & m[l]));
                }
            }
            let planes = [&self.qx, &self.qy, &self.qz];
            for (ch, q) in planes.iter().enumerate() {
                let mut v = [[0i16; QLANES]; 25];
                for dr in 0..5 {
                    let row0 = centre + dr * stride - 2 * stride - 2;
                    for dc in 0..5 {
                        let j = 5 * dr + dc;
                        let x = lane_load(&q[row0 + dc..]);
                        for l in 0..QLANES {
                            v[j][l] = (x[l] | masks[j][l]) ^ c[j][l];
                        }
                    }
                }
                med[ch] = median25(&v)[0];
            }
        }

        // Back to unit vectors; fall back to the pixel's own normal when the window is too
        // sparse, the median is degenerate (|m| < 0.5) or it faces away from the sensor.
        // In f32 only, over fixed-size arrays, so that it vectorises (16 lanes of scalar code,
        // rsqrt's Newton steps included, were a quarter of this function's time).
        let (cos_c, sin_c) = (&table.col_cos[c0..c0 + QLANES], &table.col_sin[c0..c0 + QLANES]);
        let mut sound = [false; QLANES];
        let mut n = [[0.0f32; QLANES]; 3];
        for l in 0..QLANES {
            let m = [f32::from(med[0][l]), f32::from(med[1][l]), f32::from(med[2][l])];
            let n2 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2];
            let (cc, sc) = (cos_c[l], sin_c[l]);
            let (ca, sa) = (rc.ca0 * cc - rc.sa0 * sc, rc.sa0 * cc + rc.ca0 * sc);
            let facing = rc.ce * (ca * m[0] + sa * m[1]) + rc.se * m[2];
            sound[l] = (n2 >= 0.25 * QSCALE * QSCALE) & (facing < 0.0);
            let s = rsqrt_norm(n2);
            for ch in 0..3 {
                n[ch][l] = m[ch] * s;
            }
        }
        let mut use_med = [false; QLANES];
        for l in 0..QLANES {
            let valid = has_normal(st[l]);
            use_med[l] = valid & (25 + neg_count[l] >= min_valid) & sound[l];
        }
        // A blend by bit masks: a conditional store per lane compiled to jumps.
        let keep: [u32; QLANES] = core::array::from_fn(|l| u32::from(use_med[l]).wrapping_neg());
        let planes = [&mut self.nx, &mut self.ny, &mut self.nz];
        for (ch, plane) in planes.into_iter().enumerate() {
            let dst = &mut plane[centre..centre + QLANES];
            for l in 0..QLANES {
                dst[l] = f32::from_bits((n[ch][l].to_bits() & keep[l]) | (dst[l].to_bits() & !keep[l]));
            }
        }
        let valid = st.iter().filter(|&&s| has_normal(s)).count();
        (valid - use_med.iter().filter(|&&u| u).count()) as u32
    }
}

/// Per padded column `pc` of one padded row: the largest and smallest key of the valid pixels
/// (`qinv` 0) in columns pc-2..=pc+2, `i16::MIN` / `i16::MAX` where none (the two columns at
/// each end are left as they are).
fn key_range_row(key: &[i16], qinv: &[i16], kmax: &mut [i16], kmin: &mut [i16]) {
    let n = key.len();
    let (qinv, kmax, kmin) = (&qinv[..n], &mut kmax[..n], &mut kmin[..n]);
    let hi = |j: usize| (key[j] & !qinv[j]) | (qinv[j] & i16::MIN);
    let lo = |j: usize| (key[j] & !qinv[j]) | (qinv[j] & i16::MAX);
    for pc in 2..n - 2 {
        kmax[pc] = hi(pc - 2).max(hi(pc - 1)).max(hi(pc)).max(hi(pc + 1)).max(hi(pc + 2));
        kmin[pc] = lo(pc - 2).min(lo(pc - 1)).min(lo(pc)).min(lo(pc + 1)).min(lo(pc + 2));
    }
}

/// Quantises one padded row of normals for the median: valid pixels to 1/QSCALE, the rest to
/// the invalid sentinel with `qinv = -1`.
#[allow(clippy::too_many_arguments)]
fn quantise_row(
    nx: &[f32],
    ny: &[f32],
    nz: &[f32],
    state: &[u8],
    qx: &mut [i16],
    qy: &mut [i16],
    qz: &mut [i16],
    qinv: &mut [i16],
) {
    let n = nx.len();
    let (ny, nz, state) = (&ny[..n], &nz[..n], &state[..n]);
    let (qx, qy, qz, qinv) = (&mut qx[..n], &mut qy[..n], &mut qz[..n], &mut qinv[..n]);
    for j in 0..n {
        let v = state[j] == FULL || state[j] == GAP;
        // |n| <= 1, so the products lie in [-32000, 32000], well within `round_small`'s range.
        qx[j] = if v { round_small(nx[j] * QSCALE) as i16 } else { QINVALID };
        qy[j] = if v { round_small(ny[j] * QSCALE) as i16 } else { QINVALID };
        qz[j] = if v { round_small(nz[j] * QSCALE) as i16 } else { QINVALID };
        qinv[j] = if v { 0 } else { -1 };
    }
}

/// `x` rounded to the nearest integer (ties to even) for finite `|x| < 2^22`: adding 1.5 * 2^23
/// leaves the integer in the low mantissa bits. Float and integer arithmetic only, so a loop of
/// it vectorises, which a float-to-integer `as` (saturating, NaN to 0) does not.
#[inline(always)]
pub(super) fn round_small(x: f32) -> i32 {
    const MAGIC: f32 = 12_582_912.0;
    (x + MAGIC).to_bits() as i32 - MAGIC.to_bits() as i32
}

/// Sorts every column's 5-row strip: `s[i][j]` is row i of column j, `d[k][j]` receives the
/// k-th smallest of column j.
#[inline(never)]
fn sort_strips(s: [&[i16]; 5], d: [&mut [i16]; 5]) {
    let n = d[0].len();
    let s: [&[i16]; 5] = core::array::from_fn(|i| &s[i][..n]);
    let [d0, d1, d2, d3, d4] = d;
    let (d1, d2, d3, d4) = (&mut d1[..n], &mut d2[..n], &mut d3[..n], &mut d4[..n]);
    for j in 0..n {
        let mut v = [s[0][j], s[1][j], s[2][j], s[3][j], s[4][j]];
        sort5(&mut v);
        d0[j] = v[0];
        d1[j] = v[1];
        d2[j] = v[2];
        d3[j] = v[3];
        d4[j] = v[4];
    }
}

/// Per lane, the value of rank `rank[l]` from `ranks` (ranks `first`, `first + 1`, ...); 0 in
/// lanes whose rank is not among them (lanes that do not use their median).
#[inline(always)]
fn pick_rank(ranks: &[Lane], first: i16, rank: &Lane) -> Lane {
    let mut m: Lane = [0; QLANES];
    for (k, rk) in ranks.iter().enumerate() {
        for l in 0..QLANES {
            m[l] |= rk[l] & -i16::from(rank[l] == first + k as i16);
        }
    }
    m
}

#[inline(always)]
fn lane_load(s: &[i16]) -> Lane {
    let s = &s[..QLANES];
    core::array::from_fn(|l| s[l])
}
