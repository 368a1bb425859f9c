//! Rotations and the gravity sphere: SO(3) and S2 in f64, as the error-state filter needs them.
//!
//! - SO(3): [`hat`], [`exp`] / [`exp_quat`] (Rodrigues), [`log`] / [`log_quat`], the right
//!   Jacobian [`right_jacobian`] and its inverse [`right_jacobian_inv`]. Every function is
//!   small-angle safe: below [`SERIES_ANGLE`] the trigonometric ratios are replaced by their
//!   Taylor series (truncation error below 1e-18), so there is no 0/0 and no cancellation.
//!   [`exp`]'s ratios use longer series up to 0.5 rad (eight terms, below 5e-20), `sin` beyond.
//! - S2: [`S2`], a vector of fixed length (gravity) with a 2-DOF tangent space,
//!   boxplus `g ⊞ d = Exp(B(g) d) g` and boxminus its inverse.
//!
//! Perturbations are on the right everywhere (`R ⊞ φ = R Exp(φ)`), as in FAST-LIO2, so rotation
//! errors live in the body frame.

use nalgebra::{Matrix3, Matrix3x2, Rotation3, UnitQuaternion, Vector2, Vector3};

/// Below this angle (rad) the trigonometric ratios use their Taylor series.
pub const SERIES_ANGLE: f64 = 1e-3;
/// Below this angle (rad) [`exp`]'s ratios come from longer series (polynomials) instead of
/// `sin`.
const POLY_ANGLE: f64 = 0.5;
/// `sin θ / θ = Σ (-1)^k θ^2k / (2k + 1)!`, k = 0..8.
const SIN_C: [f64; 8] = [
    1.0,
    -1.0 / 6.0,
    1.0 / 120.0,
    -1.0 / 5040.0,
    1.0 / 362_880.0,
    -1.0 / 39_916_800.0,
    1.0 / 6_227_020_800.0,
    -1.0 / 1_307_674_368_000.0,
];
/// `(1 - cos θ) / θ² = Σ (-1)^k θ^2k / (2k + 2)!`, k = 0..8.
const COS_C: [f64; 8] = [
    0.5,
    -1.0 / 24.0,
    1.0 / 720.0,
    -1.0 / 40_320.0,
    1.0 / 3_628_800.0,
    -1.0 / 479_001_600.0,
    1.0 / 87_178_291_200.0,
    -1.0 / 20_922_789_888_000.0,
];

/// The skew-symmetric matrix of `v`: `hat(v) w = v × w`.
#[inline]
pub fn hat(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// `sin θ / θ` and `(1 - cos θ) / θ²` for `θ = |φ|`, small-angle safe.
#[inline]
pub(crate) fn rodrigues_coeffs(theta: f64) -> (f64, f64) {
    if theta < SERIES_ANGLE {
        let t2 = theta * theta;
        (1.0 - t2 / 6.0 + t2 * t2 / 120.0, 0.5 - t2 / 24.0 + t2 * t2 / 720.0)
    } else if theta < POLY_ANGLE {
        // Eight terms of each series (the next is below 5e-20 at 0.5 rad): the undistortion
        // asks for a transform per distinct point time, and two `sin` calls were a quarter of
        // its time. Estrin's scheme: three dependent multiply-adds instead of Horner's seven
        // (the transforms wait on this chain).
        let x = theta * theta;
        let (x2, x4) = (x * x, x * x * (x * x));
        let estrin = |c: &[f64; 8]| {
            let q0 = (c[0] + c[1] * x) + (c[2] + c[3] * x) * x2;
            let q1 = (c[4] + c[5] * x) + (c[6] + c[7] * x) * x2;
            q0 + q1 * x4
        };
        (estrin(&SIN_C), estrin(&COS_C))
    } else {
        // (1 - cos θ) = 2 sin²(θ/2): no cancellation for small θ.
        let s_half = libm::sin(0.5 * theta) / (0.5 * theta);
        (libm::sin(theta) / theta, 0.5 * s_half * s_half)
    }
}

/// The rotation matrix `Exp(φ)` of a rotation vector (axis times angle, rad).
#[inline]
pub fn exp(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let (a, b) = rodrigues_coeffs(theta);
    let k = hat(phi);
    Matrix3::identity() + k * a + k * k * b
}

/// The unit quaternion `Exp(φ)` of a rotation vector.
#[inline]
pub fn exp_quat(phi: &Vector3<f64>) -> UnitQuaternion<f64> {
    let theta = phi.norm();
    let half = 0.5 * theta;
    // sin(θ/2) / θ
    let s = if theta < SERIES_ANGLE {
        let t2 = theta * theta;
        0.5 * (1.0 - t2 / 24.0 + t2 * t2 / 1920.0)
    } else {
        libm::sin(half) / theta
    };
    let q = nalgebra::Quaternion::new(libm::cos(half), phi.x * s, phi.y * s, phi.z * s);
    // Already unit to rounding; renormalise so repeated products do not drift.
    UnitQuaternion::new_normalize(q)
}

/// The rotation vector `Log(q)` in `[0, π]` (the quaternion's sign is chosen so that `w ≥ 0`).
#[inline]
pub fn log_quat(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    let q = q.as_ref();
    let (w, v) = if q.w < 0.0 { (-q.w, -q.imag()) } else { (q.w, q.imag()) };
    let n = v.norm();
    if n < 1e-12 {
        // θ = 2 atan(n / w) ≈ 2 n / w; error O(n³).
        v * (2.0 / w)
    } else {
        v * (2.0 * libm::atan2(n, w) / n)
    }
}

/// The rotation vector `Log(R)` of a rotation matrix (robust near 0 and near π: it goes through
/// the quaternion).
#[inline]
pub fn log(r: &Matrix3<f64>) -> Vector3<f64> {
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(*r));
    log_quat(&q)
}

/// The right Jacobian of SO(3): `Exp(φ + δ) ≈ Exp(φ) Exp(Jr(φ) δ)`.
pub fn right_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let (_, b) = rodrigues_coeffs(theta);
    // (θ - sin θ) / θ³
    let c = if theta < SERIES_ANGLE {
        let t2 = theta * theta;
        1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    } else {
        (theta - libm::sin(theta)) / (theta * theta * theta)
    };
    let k = hat(phi);
    Matrix3::identity() - k * b + k * k * c
}

/// The inverse of [`right_jacobian`] (defined for `|φ| < 2π`).
pub fn right_jacobian_inv(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    // 1/θ² - (1 + cos θ) / (2 θ sin θ)
    let c = if theta < SERIES_ANGLE {
        let t2 = theta * theta;
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0
    } else {
        1.0 / (theta * theta) - (1.0 + libm::cos(theta)) / (2.0 * theta * libm::sin(theta))
    };
    let k = hat(phi);
    Matrix3::identity() + k * 0.5 + k * k * c
}

/// A vector of fixed length on the sphere (the gravity vector of the filter): 2 degrees of
/// freedom, tangent basis [`S2::basis`], `g ⊞ d = Exp(B(g) d) g`.
///
/// The tangent basis is the image of the world x and y axes under the smallest rotation that
/// takes `-z` to the direction of `g`. It is smooth everywhere except at `+z` (gravity pointing
/// up), which a gravity-aligned world frame never comes near: gravity starts at exactly `-z`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct S2 {
    v: Vector3<f64>,
}

impl S2 {
    /// `v` scaled to `length`. A zero or non-finite `v` gives `-z · length`.
    pub fn new(v: &Vector3<f64>, length: f64) -> Self {
        let n = v.norm();
        if n > 0.0 && n.is_finite() {
            Self { v: v * (length / n) }
        } else {
            Self { v: Vector3::new(0.0, 0.0, -length) }
        }
    }

    /// The vector.
    #[inline]
    pub fn vec(&self) -> Vector3<f64> {
        self.v
    }

    /// The fixed length.
    #[inline]
    pub fn length(&self) -> f64 {
        self.v.norm()
    }

    /// The orthonormal tangent basis `B(g)` (3x2, columns orthogonal to `g`).
    pub fn basis(&self) -> Matrix3x2<f64> {
        let u = self.v / self.v.norm();
        let d = 1.0 - u.z;
        if d < 1e-12 {
            // g points straight up: any orthonormal tangent pair will do (never reached in use).
            return Matrix3x2::new(1.0, 0.0, 0.0, -1.0, 0.0, 0.0);
        }
        let k = 1.0 / d;
        Matrix3x2::new(1.0 - k * u.x * u.x, -k * u.x * u.y, -k * u.x * u.y, 1.0 - k * u.y * u.y, u.x, u.y)
    }

    /// `g ⊞ d = Exp(B(g) d) g`.
    pub fn boxplus(&self, d: &Vector2<f64>) -> Self {
        let phi = self.basis() * d;
        let len = self.length();
        // Renormalise to the exact length so that repeated updates do not drift.
        Self::new(&(exp(&phi) * self.v), len)
    }

    /// `self ⊟ other`: the tangent vector `d` at `other` with `other ⊞ d = self`.
    pub fn boxminus(&self, other: &S2) -> Vector2<f64> {
        let a = self.v / self.v.norm();
        let b = other.v / other.v.norm();
        let axis = b.cross(&a);
        let s = axis.norm();
        let c = b.dot(&a);
        let phi = if s < 1e-15 {
            if c > 0.0 {
                return Vector2::zeros();
            }
            // Antiparallel: any tangent direction; take the first basis vector.
            other.basis().column(0) * core::f64::consts::PI
        } else {
            axis * (libm::atan2(s, c) / s)
        };
        other.basis().transpose() * phi
    }

    /// The derivative of `(g ⊞ d)` by `d` at `d = 0`: `-hat(g) B(g)`.
    pub fn dvec_dtangent(&self) -> Matrix3x2<f64> {
        -hat(&self.v) * self.basis()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vecs() -> [Vector3<f64>; 9] {
        [
            Vector3::zeros(),
            Vector3::new(1e-12, -2e-12, 3e-13),
            Vector3::new(1e-5, 2e-6, -3e-5),
            Vector3::new(4e-4, -3e-4, 1e-4),
            Vector3::new(0.3, -0.2, 0.1),
            Vector3::new(-1.0, 0.5, 2.0),
            Vector3::new(0.0, 0.0, 3.0),
            Vector3::new(core::f64::consts::PI - 1e-3, 0.0, 0.0),
            Vector3::new(1.0, 1.0, 1.0).normalize() * (core::f64::consts::PI - 1e-4),
        ]
    }

    /// The series agree with the trigonometric form to rounding over their whole range (both lie
    /// within 1.7e-16 of the exact ratios, checked in 50-digit arithmetic when this was written:
    /// Estrin 1.6e-16 / 0.8e-16, `sin` 1.6e-16 / 1.7e-16).
    #[test]
    fn rodrigues_series_match_sin() {
        for i in 0..=50_000 {
            let t = i as f64 * (0.6 / 50_000.0);
            let (a, b) = rodrigues_coeffs(t);
            if t < 1e-6 {
                continue;
            }
            let h = libm::sin(0.5 * t) / (0.5 * t);
            let (wa, wb) = (libm::sin(t) / t, 0.5 * h * h);
            assert!((a - wa).abs() <= 4e-16 && (b - wb).abs() <= 4e-16, "{t}: {a} {wa} {b} {wb}");
        }
    }

    #[test]
    fn exp_is_orthonormal_and_matches_quaternion() {
        for phi in vecs() {
            let r = exp(&phi);
            assert!((r.transpose() * r - Matrix3::identity()).norm() < 1e-14, "{phi:?}");
            assert!((r.determinant() - 1.0).abs() < 1e-14);
            let rq = exp_quat(&phi).to_rotation_matrix().into_inner();
            assert!((r - rq).norm() < 1e-14, "{phi:?}");
        }
    }

    #[test]
    fn exp_matches_nalgebra_axis_angle() {
        for phi in vecs().iter().skip(4) {
            let expect = Rotation3::from_scaled_axis(*phi).into_inner();
            assert!((exp(phi) - expect).norm() < 1e-14);
        }
    }

    #[test]
    fn log_inverts_exp_including_small_and_near_pi() {
        for phi in vecs() {
            let back = log(&exp(&phi));
            assert!((back - phi).norm() < 1e-12 * (1.0 + phi.norm()), "{phi:?} -> {back:?}");
            let backq = log_quat(&exp_quat(&phi));
            assert!((backq - phi).norm() < 1e-12 * (1.0 + phi.norm()), "{phi:?} -> {backq:?}");
        }
        // Tiny angles keep their relative precision.
        let tiny = Vector3::new(3e-10, -1e-10, 2e-10);
        assert!((log(&exp(&tiny)) - tiny).norm() < 1e-22);
    }

    #[test]
    fn hat_is_the_cross_product() {
        let a = Vector3::new(0.3, -1.2, 2.0);
        let b = Vector3::new(-0.7, 0.1, 0.4);
        assert!((hat(&a) * b - a.cross(&b)).norm() < 1e-15);
    }

    #[test]
    fn right_jacobian_first_order_property_and_inverse() {
        let deltas = [Vector3::new(1e-6, 0.0, 0.0), Vector3::new(0.0, -2e-6, 1e-6)];
        for phi in vecs().iter().take(7) {
            let jr = right_jacobian(phi);
            let jri = right_jacobian_inv(phi);
            assert!((jr * jri - Matrix3::identity()).norm() < 1e-12, "{phi:?}");
            for d in deltas {
                // Exp(φ + δ) vs Exp(φ) Exp(Jr δ): equal to second order in δ.
                let lhs = exp(&(phi + d));
                let rhs = exp(phi) * exp(&(jr * d));
                assert!((lhs - rhs).norm() < 1e-11, "{phi:?}");
                // Log(Exp(φ) Exp(δ)) ≈ φ + Jr⁻¹ δ.
                let l = log(&(exp(phi) * exp(&d)));
                assert!((l - (phi + jri * d)).norm() < 1e-11, "{phi:?}");
            }
        }
    }

    #[test]
    fn series_and_closed_forms_agree_at_the_switch() {
        let below = Vector3::new(SERIES_ANGLE * (1.0 - 1e-9), 0.0, 0.0);
        let above = Vector3::new(SERIES_ANGLE * (1.0 + 1e-9), 0.0, 0.0);
        assert!((exp(&below) - exp(&above)).norm() < 1e-11);
        assert!((right_jacobian(&below) - right_jacobian(&above)).norm() < 1e-11);
        assert!((right_jacobian_inv(&below) - right_jacobian_inv(&above)).norm() < 1e-11);
        assert!((exp_quat(&below).coords - exp_quat(&above).coords).norm() < 1e-11);
    }

    #[test]
    fn s2_basis_is_orthonormal_and_tangent() {
        let dirs = [
            Vector3::new(0.0, 0.0, -1.0),
            Vector3::new(0.1, -0.2, -1.0),
            Vector3::new(1.0, 0.0, 0.0),
            Vector3::new(0.3, 0.9, 0.2),
            Vector3::new(0.0, 0.0, 1.0),
        ];
        for d in dirs {
            let g = S2::new(&d, 9.81);
            assert!((g.length() - 9.81).abs() < 1e-12);
            let b = g.basis();
            assert!((b.transpose() * b - nalgebra::Matrix2::identity()).norm() < 1e-12, "{d:?}");
            assert!((b.transpose() * g.vec()).norm() < 1e-12, "{d:?}");
        }
        // Nominal gravity: the basis is the world x and y axes.
        let g = S2::new(&Vector3::new(0.0, 0.0, -1.0), 9.81);
        assert_eq!(g.basis(), Matrix3x2::new(1.0, 0.0, 0.0, 1.0, 0.0, 0.0));
    }

    #[test]
    fn s2_boxplus_boxminus_round_trip_and_length() {
        let g = S2::new(&Vector3::new(0.05, -0.02, -1.0), 9.81);
        for d in [Vector2::new(0.0, 0.0), Vector2::new(1e-7, -3e-7), Vector2::new(0.2, -0.1)] {
            let h = g.boxplus(&d);
            assert!((h.length() - 9.81).abs() < 1e-12);
            assert!((h.boxminus(&g) - d).norm() < 1e-12, "{d:?}");
        }
        assert_eq!(g.boxminus(&g), Vector2::zeros());
    }

    #[test]
    fn s2_derivative_matches_finite_difference() {
        let g = S2::new(&Vector3::new(0.05, -0.02, -1.0), 9.81);
        let j = g.dvec_dtangent();
        let eps = 1e-6;
        for k in 0..2 {
            let mut d = Vector2::zeros();
            d[k] = eps;
            let num = (g.boxplus(&d).vec() - g.boxplus(&(-d)).vec()) / (2.0 * eps);
            assert!((num - j.column(k)).norm() < 1e-8, "{k}");
        }
    }
}
