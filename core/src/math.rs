//! Square roots that compile to the target's own instruction in its own encoding, and a cache
//! warm-up read (`read_in`).
//!
//! `libm::sqrt` on x86 is inline assembly with the legacy SSE encoding (`sqrtsd`). In a build
//! for a CPU with AVX (`-C target-cpu=native`, see `.cargo/config.toml`) the code around it is
//! VEX-encoded, and every switch between the two encodings stalls while the upper register
//! halves are dirty: the 3x3 eigen-solver of the surfels ran 6x slower (2.4 us against 0.41
//! us per call). The intrinsic takes the encoding of the build. Both are IEEE square roots,
//! correctly rounded, so every result is bit for bit the same as `libm`'s.

/// `floor(v)` as an integer for finite `|v| < 2^31` (callers check a smaller bound): the
/// truncation, minus one for negative non-integers. Equal to `libm::floorf` there (an `f32` of
/// magnitude 2^23 or more is an integer, so the truncation is exact) and cheaper on targets
/// without a rounding instruction in their baseline (x86-64 before SSE4.1, Cortex-M4F).
#[inline(always)]
pub(crate) fn floor_i32(v: f32) -> i32 {
    let t = v as i32;
    if (t as f32) > v { t - 1 } else { t }
}

/// `floor(v)`, bit for bit `libm::floor`'s (signed zeros, infinities and NaN included), by a
/// truncation to `i64`: `libm`'s is a call into a software routine on every target (no
/// rounding instruction in x86-64's baseline; on arm64 `libm` does not use `frintm`), and the
/// scan assembly takes two per return (1.7 M of 131.7 M arm64 instructions per VLP-32C scan).
#[inline(always)]
pub(crate) fn floor_f64(v: f64) -> f64 {
    // From 2^52 on every f64 is an integer; zeros keep their sign; NaN is returned as is.
    if v.is_nan() || libm::fabs(v) >= 4_503_599_627_370_496.0 || v == 0.0 {
        return v;
    }
    let t = v as i64 as f64;
    if t > v { t - 1.0 } else { t }
}

/// Correctly rounded square root of an `f64`.
#[inline(always)]
pub fn sqrt(x: f64) -> f64 {
    #[cfg(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "sse2"))]
    {
        use safe_arch::{get_f64_from_m128d_s, set_m128d_s, sqrt_m128d};
        get_f64_from_m128d_s(sqrt_m128d(set_m128d_s(x)))
    }
    #[cfg(not(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "sse2")))]
    {
        libm::sqrt(x)
    }
}

/// Correctly rounded square root of an `f32`.
#[inline(always)]
pub fn sqrtf(x: f32) -> f32 {
    #[cfg(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "sse"))]
    {
        use safe_arch::{get_f32_from_m128_s, set_m128_s, sqrt_m128_s};
        let v = set_m128_s(x);
        get_f32_from_m128_s(sqrt_m128_s(v))
    }
    #[cfg(not(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "sse")))]
    {
        libm::sqrtf(x)
    }
}

/// Correctly rounded square roots of four `f64`: one vector instruction where the build has AVX,
/// four [`sqrt`] otherwise (the same bits either way).
#[inline(always)]
pub fn sqrt4(x: [f64; 4]) -> [f64; 4] {
    #[cfg(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "avx"))]
    {
        safe_arch::sqrt_m256d(safe_arch::m256d::from_array(x)).to_array()
    }
    #[cfg(not(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "avx")))]
    {
        x.map(sqrt)
    }
}

/// Correctly rounded square roots of eight `f32`: one vector instruction where the build has
/// AVX, eight [`sqrtf`] otherwise (the same bits either way).
#[inline(always)]
pub fn sqrtf8(x: [f32; 8]) -> [f32; 8] {
    #[cfg(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "avx"))]
    {
        safe_arch::sqrt_m256(safe_arch::m256::from_array(x)).to_array()
    }
    #[cfg(not(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "avx")))]
    {
        x.map(sqrtf)
    }
}

/// Eight `f32` truncated towards zero to `i32`: one vector instruction where the build has AVX
/// (Rust's saturating `as` is one lane at a time there). The same as `x as i32` for every
/// value within `i32`; beyond it or for NaN the result is some `i32`, different by build.
#[inline(always)]
pub(crate) fn trunc_i32x8(x: [f32; 8]) -> [i32; 8] {
    #[cfg(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "avx"))]
    {
        let v = safe_arch::convert_truncate_to_i32_m256i_from_m256(safe_arch::m256::from_array(x));
        <[i32; 8]>::from(v)
    }
    #[cfg(not(all(any(target_arch = "x86", target_arch = "x86_64"), target_feature = "avx")))]
    {
        x.map(|v| v as i32)
    }
}

/// [`floor_i32`] of eight `f32` at once: [`trunc_i32x8`], minus one for negative
/// non-integers. Equal to `floor_i32` for finite `|v| < 2^31`; a lane beyond it (or NaN) gives
/// some `i32` (wrapping, never a panic) that the caller must not use.
#[inline(always)]
pub(crate) fn floor_i32x8(x: [f32; 8]) -> [i32; 8] {
    let t = trunc_i32x8(x);
    let mut k = [0i32; 8];
    for l in 0..8 {
        k[l] = if (t[l] as f32) > x[l] { t[l].wrapping_sub(1) } else { t[l] };
    }
    k
}

/// Reads one element per 64-byte cache line of `s`, in order, and nothing else. For a buffer
/// about to be used in random order after other work evicted it: a sequential read arrives as a
/// stream the hardware prefetchers follow, where the random accesses would each wait for
/// memory. No effect on results.
#[inline]
pub(crate) fn read_in<T: Copy>(s: &[T]) {
    let step = (64 / core::mem::size_of::<T>().max(1)).max(1);
    for x in s.iter().step_by(step) {
        core::hint::black_box(*x);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floor_is_libms_bit_for_bit() {
        extern crate std;
        let mut vals = std::vec![0.0f64, -0.0, 0.5, -0.5, 1.0, -1.0, 2.5, -2.5, 1e-300, -1e-300];
        vals.extend([0.999_999_999_999_999_9, -0.999_999_999_999_999_9]);
        vals.extend([4_503_599_627_370_495.5, -4_503_599_627_370_495.5]);
        vals.extend([4_503_599_627_370_496.0, -4_503_599_627_370_497.0, 1e300, -1e300, f64::MAX, f64::MIN]);
        vals.extend([f64::INFINITY, f64::NEG_INFINITY, f64::NAN, f64::MIN_POSITIVE, -f64::MIN_POSITIVE]);
        let mut x = 1.0e-20f64;
        while x < 1.0e20 {
            vals.extend([x, -x, x + 0.5, -x - 0.5, x * 1799.3, -x * 1799.3]);
            x *= 1.7;
        }
        for v in vals {
            assert_eq!(floor_f64(v).to_bits(), libm::floor(v).to_bits(), "{v:e}");
        }
    }

    #[test]
    fn same_bits_as_libm() {
        let mut x = 1.0e-310f64;
        while x < 1.0e300 {
            for y in [x, x * 1.000_000_1, x * 3.7] {
                assert_eq!(sqrt(y).to_bits(), libm::sqrt(y).to_bits(), "{y}");
                let f = y as f32;
                assert_eq!(sqrtf(f).to_bits(), libm::sqrtf(f).to_bits(), "{f}");
            }
            x *= 1.37;
        }
        let x8 = [0.0f32, 1.0, 2.0, 1e-38, 3.7e30, 1e-44, 0.25, 7.0];
        let v8 = sqrtf8(x8);
        for i in 0..8 {
            assert_eq!(v8[i].to_bits(), libm::sqrtf(x8[i]).to_bits(), "{}", x8[i]);
        }
        for x in [[0.0, 1.0, 2.0, 1e-300], [3.7e200, 1e-310, 0.25, 7.0]] {
            let v = sqrt4(x);
            for i in 0..4 {
                assert_eq!(v[i].to_bits(), libm::sqrt(x[i]).to_bits(), "{}", x[i]);
            }
        }
        assert!(sqrt(-1.0).is_nan() && sqrtf(-1.0).is_nan());
        assert_eq!(sqrt(0.0), 0.0);
        assert_eq!(sqrtf(f32::INFINITY), f32::INFINITY);
    }
}
