//! Second-order forward-mode automatic differentiation ("jets").
//!
//! A [`Jet`] carries a value and its first and second derivatives with respect to time. The
//! trajectories are written once as closed-form expressions over jets, and the arithmetic below
//! applies the chain and product rules exactly, so velocity, acceleration, angular rate and
//! angular acceleration are exact to rounding: there is no finite differencing anywhere.

use core::ops::{Add, Div, Mul, Neg, Sub};

/// A value with its first and second time derivatives.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Jet {
    /// f(t)
    pub v: f64,
    /// f'(t)
    pub d1: f64,
    /// f''(t)
    pub d2: f64,
}

impl Jet {
    /// A constant (zero derivatives).
    #[inline]
    pub const fn c(v: f64) -> Self {
        Self { v, d1: 0.0, d2: 0.0 }
    }

    /// The independent variable t itself.
    #[inline]
    pub const fn var(t: f64) -> Self {
        Self { v: t, d1: 1.0, d2: 0.0 }
    }

    /// Applies a scalar function f with derivatives (f(v), f'(v), f''(v)).
    #[inline]
    fn chain(self, f: f64, df: f64, ddf: f64) -> Self {
        Self { v: f, d1: df * self.d1, d2: ddf * self.d1 * self.d1 + df * self.d2 }
    }

    /// sin
    #[inline]
    pub fn sin(self) -> Self {
        let (s, c) = (libm::sin(self.v), libm::cos(self.v));
        self.chain(s, c, -s)
    }

    /// cos
    #[inline]
    pub fn cos(self) -> Self {
        let (s, c) = (libm::sin(self.v), libm::cos(self.v));
        self.chain(c, -s, -c)
    }

    /// sqrt (for positive values)
    #[inline]
    pub fn sqrt(self) -> Self {
        let r = libm::sqrt(self.v);
        self.chain(r, 0.5 / r, -0.25 / (r * self.v))
    }

    /// atan
    #[inline]
    pub fn atan(self) -> Self {
        let d = 1.0 / (1.0 + self.v * self.v);
        self.chain(libm::atan(self.v), d, -2.0 * self.v * d * d)
    }

    /// atan2(self, x), the angle of the vector (x, self).
    #[inline]
    pub fn atan2(self, x: Jet) -> Self {
        let y = self;
        let r2 = x * x + y * y;
        // d(atan2) = (x dy - y dx) / r^2; differentiate that quotient once more.
        let num = x * Jet { v: y.d1, d1: y.d2, d2: 0.0 } - y * Jet { v: x.d1, d1: x.d2, d2: 0.0 };
        let rate = num / r2;
        Self { v: libm::atan2(y.v, x.v), d1: rate.v, d2: rate.d1 }
    }

    /// Multiplies by a constant.
    #[inline]
    pub fn scale(self, k: f64) -> Self {
        Self { v: self.v * k, d1: self.d1 * k, d2: self.d2 * k }
    }

    /// The jet of f'(t) (value f', derivative f''), for quantities whose rate must itself be
    /// differentiated once; its second derivative is unknown and set to 0.
    #[inline]
    pub fn rate(self) -> Self {
        Self { v: self.d1, d1: self.d2, d2: 0.0 }
    }
}

impl Add for Jet {
    type Output = Jet;
    #[inline]
    fn add(self, o: Jet) -> Jet {
        Jet { v: self.v + o.v, d1: self.d1 + o.d1, d2: self.d2 + o.d2 }
    }
}

impl Sub for Jet {
    type Output = Jet;
    #[inline]
    fn sub(self, o: Jet) -> Jet {
        Jet { v: self.v - o.v, d1: self.d1 - o.d1, d2: self.d2 - o.d2 }
    }
}

impl Neg for Jet {
    type Output = Jet;
    #[inline]
    fn neg(self) -> Jet {
        Jet { v: -self.v, d1: -self.d1, d2: -self.d2 }
    }
}

impl Mul for Jet {
    type Output = Jet;
    #[inline]
    fn mul(self, o: Jet) -> Jet {
        Jet {
            v: self.v * o.v,
            d1: self.d1 * o.v + self.v * o.d1,
            d2: self.d2 * o.v + 2.0 * self.d1 * o.d1 + self.v * o.d2,
        }
    }
}

impl Div for Jet {
    type Output = Jet;
    #[inline]
    fn div(self, o: Jet) -> Jet {
        let inv = 1.0 / o.v;
        let q = self.v * inv;
        let d1 = (self.d1 - q * o.d1) * inv;
        let d2 = (self.d2 - 2.0 * d1 * o.d1 - q * o.d2) * inv;
        Jet { v: q, d1, d2 }
    }
}

impl Add<f64> for Jet {
    type Output = Jet;
    #[inline]
    fn add(self, k: f64) -> Jet {
        Jet { v: self.v + k, ..self }
    }
}

impl Sub<f64> for Jet {
    type Output = Jet;
    #[inline]
    fn sub(self, k: f64) -> Jet {
        Jet { v: self.v - k, ..self }
    }
}

impl Mul<f64> for Jet {
    type Output = Jet;
    #[inline]
    fn mul(self, k: f64) -> Jet {
        self.scale(k)
    }
}

/// The quintic smoothstep s(u) = 6u^5 - 15u^4 + 10u^3 on [0, 1], 0 before and 1 after: its
/// first and second derivatives vanish at both ends, so blends with it keep acceleration
/// continuous.
#[inline]
pub fn smoothstep(u: Jet) -> Jet {
    if u.v <= 0.0 {
        return Jet::c(0.0);
    }
    if u.v >= 1.0 {
        return Jet::c(1.0);
    }
    let x = u.v;
    let s = x * x * x * (10.0 + x * (-15.0 + 6.0 * x));
    let ds = 30.0 * x * x * (1.0 - x) * (1.0 - x);
    let dds = 60.0 * x * (1.0 - x) * (1.0 - 2.0 * x);
    u.chain(s, ds, dds)
}

/// The integral of [`smoothstep`] from 0 to u: u^6 - 3u^5 + 2.5u^4 on [0, 1], continued
/// linearly (slope 1) after 1. A speed that ramps up with a smoothstep gives this distance.
#[inline]
pub fn smoothstep_integral(u: Jet) -> Jet {
    if u.v <= 0.0 {
        return Jet::c(0.0);
    }
    if u.v >= 1.0 {
        return u - 0.5;
    }
    let x = u.v;
    let f = x * x * x * x * (2.5 + x * (-3.0 + x));
    let df = x * x * x * (10.0 + x * (-15.0 + 6.0 * x));
    let ddf = 30.0 * x * x * (1.0 - x) * (1.0 - x);
    u.chain(f, df, ddf)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Checks a jet function against central finite differences of its value.
    fn check(f: impl Fn(Jet) -> Jet, t: f64) {
        let h = 1e-4;
        let j = f(Jet::var(t));
        let (fp, fm, f0) = (f(Jet::var(t + h)).v, f(Jet::var(t - h)).v, j.v);
        let d1 = (fp - fm) / (2.0 * h);
        let d2 = (fp - 2.0 * f0 + fm) / (h * h);
        let s = 1.0 + j.d1.abs() + j.d2.abs();
        assert!((j.d1 - d1).abs() < 1e-7 * s, "d1 {} vs {} at {t}", j.d1, d1);
        assert!((j.d2 - d2).abs() < 2e-4 * s, "d2 {} vs {} at {t}", j.d2, d2);
    }

    #[test]
    fn derivatives_match_finite_differences() {
        for t in [-1.3, 0.2, 0.5, 0.77, 2.0] {
            check(|x| (x * 1.7).sin() * x.cos() + x * x * 0.3, t);
            check(|x| (x * x + 2.0).sqrt() / (x.cos() + 3.0), t);
            check(|x| (x * 0.5).atan(), t);
            check(|x| (x.sin() + 0.1).atan2(x.cos() * 2.0 + 0.3), t);
            check(|x| smoothstep((x + 1.5) * 0.3), t);
            check(|x| smoothstep_integral((x + 1.5) * 0.3), t);
        }
        // Smoothstep ends: value, slope and curvature are continuous at 0 and 1.
        assert_eq!(smoothstep(Jet::var(0.0)), Jet::c(0.0));
        let e = smoothstep(Jet::var(1.0 - 1e-9));
        assert!((e.v - 1.0).abs() < 1e-12 && e.d1.abs() < 1e-12 && e.d2.abs() < 1e-6);
        let i = smoothstep_integral(Jet::var(1.0 - 1e-12));
        assert!((i.v - 0.5).abs() < 1e-10 && (i.d1 - 1.0).abs() < 1e-10);
    }
}
