//! Deterministic randomness for the simulator, with no global state.
//!
//! Two kinds are used:
//! - **Counter-based hashes** ([`hash3`], [`unit`], [`gauss`]): the random numbers of one LiDAR
//!   ray (range noise, dropout, leaf pass-through) are a pure function of the seed, the ray's key
//!   and a stream number. A ray's outcome therefore does not depend on the order in which rays
//!   are cast, on threads, or on whether packets or direct scans are generated: the same seed
//!   gives the same points everywhere.
//! - **A sequential generator** ([`SplitMix64`]) for processes with memory, such as an IMU's
//!   bias random walk, where each draw follows the previous one.
//!
//! Everything is integer arithmetic plus `libm`, so results are bit-identical on every target.

/// The 64-bit finaliser of SplitMix64 (Steele, Lea, Flood 2014): a bijective avalanche mixer.
#[inline]
pub const fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Hash of a seed and two words (e.g. a ray key and a stream id).
#[inline]
pub const fn hash3(seed: u64, a: u64, b: u64) -> u64 {
    let h = mix64(seed ^ 0x9E37_79B9_7F4A_7C15);
    let h = mix64(h ^ a.wrapping_mul(0xD6E8_FEB8_6659_FD93));
    mix64(h ^ b.wrapping_add(0x2545_F491_4F6C_DD1D))
}

/// A uniform number in [0, 1) from the top 53 bits of a hash.
#[inline]
pub fn to_unit(h: u64) -> f64 {
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// A uniform number in [0, 1) for (seed, a, b).
#[inline]
pub fn unit(seed: u64, a: u64, b: u64) -> f64 {
    to_unit(hash3(seed, a, b))
}

/// A standard normal number for (seed, a, b), by Box-Muller on two uniforms taken from one
/// 64-bit hash and a second, independent one.
#[inline]
pub fn gauss(seed: u64, a: u64, b: u64) -> f64 {
    let h1 = hash3(seed, a, b);
    let h2 = mix64(h1 ^ 0x6A09_E667_F3BC_C909);
    box_muller(h1, h2)
}

/// A standard normal number from one uniform in (0, 1), by inverting the normal distribution
/// function (P. J. Acklam's rational approximation, relative error below 1.2e-9). Cheaper
/// than Box-Muller: no logarithm or cosine except in the 5 % tails.
#[inline]
#[allow(clippy::excessive_precision)] // the published coefficients, verbatim
pub fn normal_quantile(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969683028665376e+01,
        2.209460984245205e+02,
        -2.759285104469687e+02,
        1.383577518672690e+02,
        -3.066479806614716e+01,
        2.506628277459239e+00,
    ];
    const B: [f64; 5] = [
        -5.447609879822406e+01,
        1.615858368580409e+02,
        -1.556989798598866e+02,
        6.680131188771972e+01,
        -1.328068155288572e+01,
    ];
    const C: [f64; 6] = [
        -7.784894002430293e-03,
        -3.223964580411365e-01,
        -2.400758277161838e+00,
        -2.549732539343734e+00,
        4.374664141464968e+00,
        2.938163982698783e+00,
    ];
    const D: [f64; 4] =
        [7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00, 3.754408661907416e+00];
    const LOW: f64 = 0.02425;
    let tail = |q: f64| {
        let q = libm::sqrt(-2.0 * libm::log(q));
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    if p < LOW {
        tail(p)
    } else if p > 1.0 - LOW {
        -tail(1.0 - p)
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

/// A standard normal number from a 64-bit hash (via [`normal_quantile`]).
#[inline]
pub fn gauss_from(h: u64) -> f64 {
    // p in (0, 1): never 0 or 1.
    let p = ((h >> 11) as f64 + 0.5) * (1.0 / (1u64 << 53) as f64);
    normal_quantile(p)
}

/// Box-Muller transform of two 64-bit words into one standard normal number.
#[inline]
fn box_muller(h1: u64, h2: u64) -> f64 {
    // u1 in (0, 1]: never 0, so the logarithm is finite.
    let u1 = ((h1 >> 11) + 1) as f64 * (1.0 / (1u64 << 53) as f64);
    let u2 = to_unit(h2);
    libm::sqrt(-2.0 * libm::log(u1)) * libm::cos(core::f64::consts::TAU * u2)
}

/// SplitMix64: a small, fast, full-period sequential generator (the state is a Weyl sequence
/// passed through [`mix64`]).
#[derive(Clone, Debug)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    /// A generator for a seed and a stream id (different streams are independent).
    pub const fn new(seed: u64, stream: u64) -> Self {
        Self { state: hash3(seed, stream, 0x5EED) }
    }

    /// The next 64-bit word.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix64(self.state)
    }

    /// A uniform number in [0, 1).
    #[inline]
    pub fn unit(&mut self) -> f64 {
        to_unit(self.next_u64())
    }

    /// A uniform number in [lo, hi).
    #[inline]
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// A standard normal number.
    #[inline]
    pub fn gauss(&mut self) -> f64 {
        let a = self.next_u64();
        let b = self.next_u64();
        box_muller(a, b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hashes_are_deterministic_and_distinct() {
        assert_eq!(hash3(1, 2, 3), hash3(1, 2, 3));
        assert_ne!(hash3(1, 2, 3), hash3(2, 2, 3));
        assert_ne!(hash3(1, 2, 3), hash3(1, 3, 3));
        assert_ne!(hash3(1, 2, 3), hash3(1, 2, 4));
        // SplitMix64 reference value (first output for state 0 after one increment).
        assert_eq!(mix64(0x9E37_79B9_7F4A_7C15), 0xE220_A839_7B1D_CDAF);
    }

    #[test]
    fn uniform_and_normal_moments() {
        let n = 200_000u64;
        let (mut s, mut s2, mut g, mut g2, mut g4) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for i in 0..n {
            let u = unit(7, i, 0);
            assert!((0.0..1.0).contains(&u));
            s += u;
            s2 += u * u;
            let x = gauss(7, i, 1);
            g += x;
            g2 += x * x;
            g4 += x * x * x * x;
        }
        let nf = n as f64;
        // Standard errors: mean 0.00065, var ~0.0002; normal mean 0.0022, var 0.0032, 4th moment ~0.02.
        assert!((s / nf - 0.5).abs() < 0.004);
        assert!((s2 / nf - 1.0 / 3.0).abs() < 0.004);
        assert!((g / nf).abs() < 0.012);
        assert!((g2 / nf - 1.0).abs() < 0.02);
        assert!((g4 / nf - 3.0).abs() < 0.12);
        let (mut q, mut q2, mut q4) = (0.0, 0.0, 0.0);
        for i in 0..n {
            let x = gauss_from(hash3(5, i, 2));
            q += x;
            q2 += x * x;
            q4 += x * x * x * x;
        }
        assert!((q / nf).abs() < 0.012);
        assert!((q2 / nf - 1.0).abs() < 0.02);
        assert!((q4 / nf - 3.0).abs() < 0.12);
        // Quantiles: Phi^-1(0.975) = 1.959964, Phi^-1(0.001) = -3.090232.
        assert!((normal_quantile(0.975) - 1.959_963_985).abs() < 1e-8);
        assert!((normal_quantile(0.001) + 3.090_232_306).abs() < 1e-8);
        assert!((normal_quantile(0.5)).abs() < 1e-15);
        let mut r = SplitMix64::new(3, 4);
        let (mut m, mut v) = (0.0, 0.0);
        for _ in 0..n {
            let x = r.gauss();
            m += x;
            v += x * x;
        }
        assert!((m / nf).abs() < 0.012);
        assert!((v / nf - 1.0).abs() < 0.02);
    }
}
