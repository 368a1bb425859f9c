//! Point distributions, their shape, surfels and plane fits (paper sections III-C and III-D).
//!
//! - [`Moments`]: the sums `P = Σ p` and `S = Σ p pᵀ` of a point set about an origin, with the
//!   paper's Eq. (4) (`M = S - P Pᵀ / n`) and Eq. (5) merge. Kept in `f64` about an origin near
//!   the points, so nothing cancels catastrophically far from the world origin.
//! - [`Shape`]: the eigen-analysis of a 3x3 symmetric covariance (cyclic Jacobi in `f64`,
//!   [`eigen_sym3`]), with the paper's planarity `rho` and ratio `gamma` (Eq. 6).
//! - [`SurfelCriteria`]: the surfel test, with defaults that can actually be met (see below).
//! - [`fit_plane`]: the point-to-plane fallback's plane through k neighbours, with the
//!   reference's acceptance test (every neighbour within 0.1 m).
//!
//! ## Eigenvalue naming
//! As in the paper, `λ1 ≤ λ2 ≤ λ3` ([`Shape::eigenvalues`] is ascending) and the surfel normal
//! `e_d` is the eigenvector of `λ1`. Eigenvalues are those of the covariance `M / n` (metres²);
//! `rho` and `gamma` do not depend on that scale.
//!
//! ## Why the planarity default is 0.6, not the paper's 1.0
//! `rho = 2 (λ2 - λ1) / (λ1 + λ2 + λ3)` is at most 1 for a covariance (λ1 ≥ 0 and λ2 ≤ λ3), and
//! equals 1 only for a perfectly flat, perfectly round patch, so the paper's `rho > 1.0` is never
//! met (nor is the reference code's own default, 1.0). The reference's configs use 0.6, and so does
//! [`SurfelCriteria::DEFAULT`]. For a flat patch (`λ1 ≈ 0`) `rho > 0.6` means `λ2 / λ3 > 3/7`,
//! i.e. the patch's in-plane extents differ by less than a factor `sqrt(7/3) ≈ 1.53`: it keeps a
//! plane cut through a voxel and rejects a strip (a single scan ring across the voxel, an edge).
//! `gamma = λ2 / λ1 > 100` means the thickness (std) is under a tenth of the smaller in-plane
//! extent (std): about 1.2 cm in a 0.4 m voxel filled edge to edge.
// `!(x > t)` rejects NaN as well as small values, on purpose; indexed loops over the three
// axes read like the maths.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

/// The upper triangle of a symmetric 3x3 matrix: `[xx, xy, xz, yy, yz, zz]`.
pub type Sym3 = [f64; 6];

/// Sums of a point set about an `origin`: `n`, `P = Σ (p - o)` and `S = Σ (p - o)(p - o)ᵀ`.
///
/// The origin is a bookkeeping choice: [`Self::scatter`], [`Self::covariance`] and the world mean
/// do not depend on it, but keeping it near the points keeps the sums small and the subtraction
/// in Eq. (4) well conditioned.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Moments {
    /// Number of points.
    pub n: u32,
    /// The origin the sums are taken about (world frame, metres).
    pub origin: [f64; 3],
    /// `Σ (p - origin)`.
    pub sum: [f64; 3],
    /// `Σ (p - origin)(p - origin)ᵀ`, upper triangle ([`Sym3`] order).
    pub sum_sq: Sym3,
}

impl Moments {
    /// No points yet, sums about `origin`.
    pub const fn new(origin: [f64; 3]) -> Self {
        Self { n: 0, origin, sum: [0.0; 3], sum_sq: [0.0; 6] }
    }

    /// The sums of `points` about `origin`, added one by one.
    pub fn from_points(origin: [f64; 3], points: &[[f64; 3]]) -> Self {
        let mut m = Self::new(origin);
        for p in points {
            m.add(*p);
        }
        m
    }

    /// Adds one point (world frame).
    pub fn add(&mut self, p: [f64; 3]) {
        let d = sub3(p, self.origin);
        self.n = self.n.saturating_add(1);
        for a in 0..3 {
            self.sum[a] += d[a];
        }
        add_outer(&mut self.sum_sq, d, d, 1.0);
    }

    /// The same sums about another origin (exact up to rounding):
    /// with `t = old - new`, `P' = P + n t` and `S' = S + P tᵀ + t Pᵀ + n t tᵀ`.
    pub fn about(&self, origin: [f64; 3]) -> Self {
        let t = sub3(self.origin, origin);
        let n = f64::from(self.n);
        let mut out = *self;
        out.origin = origin;
        for a in 0..3 {
            out.sum[a] += n * t[a];
        }
        add_outer(&mut out.sum_sq, self.sum, t, 1.0);
        add_outer(&mut out.sum_sq, t, self.sum, 1.0);
        add_outer(&mut out.sum_sq, t, t, n);
        out
    }

    /// The paper's Eq. (5): adds another set's sums (taken about any origin) to these, so the
    /// result is the distribution of the union. Counts add exactly (true counts, no flags).
    pub fn merge(&mut self, other: &Moments) {
        let o = if other.origin == self.origin { *other } else { other.about(self.origin) };
        self.n = self.n.saturating_add(o.n);
        for a in 0..3 {
            self.sum[a] += o.sum[a];
        }
        for i in 0..6 {
            self.sum_sq[i] += o.sum_sq[i];
        }
    }

    /// The mean in the world frame; `None` without points.
    pub fn mean(&self) -> Option<[f64; 3]> {
        if self.n == 0 {
            return None;
        }
        let n = f64::from(self.n);
        Some([
            self.origin[0] + self.sum[0] / n,
            self.origin[1] + self.sum[1] / n,
            self.origin[2] + self.sum[2] / n,
        ])
    }

    /// The paper's Eq. (4): `M = S - P Pᵀ / n` (the scatter matrix, metres²); zero without points.
    pub fn scatter(&self) -> Sym3 {
        if self.n == 0 {
            return [0.0; 6];
        }
        let mut m = self.sum_sq;
        add_outer(&mut m, self.sum, self.sum, -1.0 / f64::from(self.n));
        m
    }

    /// The covariance `M / n` (metres²); zero without points.
    pub fn covariance(&self) -> Sym3 {
        if self.n == 0 {
            return [0.0; 6];
        }
        let mut m = self.scatter();
        let inv = 1.0 / f64::from(self.n);
        for v in &mut m {
            *v *= inv;
        }
        m
    }
}

/// Eigen-analysis of a covariance: ascending eigenvalues and their unit eigenvectors.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Shape {
    /// `λ1 ≤ λ2 ≤ λ3` (the paper's naming), clamped at 0 (a covariance has none below).
    pub eigenvalues: [f64; 3],
    /// `eigenvectors[i]` is the unit eigenvector of `eigenvalues[i]`; `eigenvectors[0]` is the
    /// surfel normal `e_d`. Signs are arbitrary but deterministic.
    pub eigenvectors: [[f64; 3]; 3],
}

/// `rho = 2 (λ2 - λ1) / (λ1 + λ2 + λ3)` of ascending eigenvalues (0 for a zero matrix).
#[inline]
fn planarity_of([l1, l2, l3]: [f64; 3]) -> f64 {
    let s = l1 + l2 + l3;
    if s > 0.0 { 2.0 * (l2 - l1) / s } else { 0.0 }
}

impl Shape {
    /// The eigen-analysis of a covariance (or scatter) matrix.
    ///
    /// The closed form ([`eigen_sym3_closed`]) where the three eigenvalues are well apart (every
    /// plane and line the map sees), Jacobi ([`eigen_sym3`]) otherwise.
    pub fn of_covariance(c: &Sym3) -> Self {
        let (mut values, vectors) = eigen_sym3_closed(c).unwrap_or_else(|| eigen_sym3(c));
        for v in &mut values {
            if *v < 0.0 {
                *v = 0.0;
            }
        }
        Self { eigenvalues: values, eigenvectors: vectors }
    }

    /// The eigenvector of the smallest eigenvalue (`e_d`, the plane normal).
    pub fn normal(&self) -> [f64; 3] {
        self.eigenvectors[0]
    }

    /// Planarity `rho = 2 (λ2 - λ1) / (λ1 + λ2 + λ3)`, in `[0, 1]`; 0 for a single point.
    pub fn planarity(&self) -> f64 {
        planarity_of(self.eigenvalues)
    }

    /// `gamma = λ2 / λ1`; `+inf` for a perfectly flat set (`λ1 = 0 < λ2`), 0 when `λ2 = 0`.
    pub fn gamma(&self) -> f64 {
        let [l1, l2, _] = self.eigenvalues;
        if l2 <= 0.0 {
            0.0
        } else if l1 <= 0.0 {
            f64::INFINITY
        } else {
            l2 / l1
        }
    }
}

/// Why a distribution (or a plane fit) is not accepted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SurfelReject {
    /// Fewer points than required.
    TooFewPoints,
    /// Fewer distinct voxels took part than required (large surfel).
    TooFewVoxels,
    /// More distinct voxels were passed than [`crate::voxel_map::MERGE_MAX`].
    TooManyVoxels,
    /// A voxel handle does not name a voxel of the map.
    InvalidHandle,
    /// All points (nearly) coincide or lie on a line: no plane is defined.
    Degenerate,
    /// Planarity `rho` not above the threshold.
    NotPlanar,
    /// `gamma = λ2 / λ1` not above the threshold.
    NotThin,
    /// A voxel mean (large surfel) or a neighbour (plane fit) lies too far from the plane.
    OffPlane,
    /// The voxel has not converged (small surfel).
    NotConverged,
}

impl core::fmt::Display for SurfelReject {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::TooFewPoints => "too few points",
            Self::TooFewVoxels => "too few voxels",
            Self::TooManyVoxels => "too many voxels to merge",
            Self::InvalidHandle => "invalid voxel handle",
            Self::Degenerate => "degenerate distribution (point or line)",
            Self::NotPlanar => "planarity below threshold",
            Self::NotThin => "lambda2/lambda1 below threshold",
            Self::OffPlane => "a member lies too far from the plane",
            Self::NotConverged => "voxel not converged",
        })
    }
}

impl core::error::Error for SurfelReject {}

/// The surfel test of the paper's section III-D: `rho > planarity_min` and `gamma > gamma_min`.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct SurfelCriteria {
    /// Planarity threshold (strictly greater passes). Default 0.6: the reference configs' value;
    /// the paper's 1.0 cannot be met (module docs).
    pub planarity_min: f32,
    /// `λ2 / λ1` threshold (strictly greater passes). Default 100 (paper and reference).
    pub gamma_min: f32,
}

impl SurfelCriteria {
    /// `rho > 0.6`, `gamma > 100`.
    pub const DEFAULT: Self = Self { planarity_min: 0.6, gamma_min: 100.0 };

    /// `Ok` if `shape` is a surfel. Degenerate shapes (no extent in two directions) fail first.
    /// NaN anywhere fails.
    pub fn check(&self, shape: &Shape) -> Result<(), SurfelReject> {
        self.check_eigenvalues(shape.eigenvalues)
    }

    /// [`Self::check`] from the ascending eigenvalues alone (all it reads).
    pub fn check_eigenvalues(&self, eigenvalues: [f64; 3]) -> Result<(), SurfelReject> {
        let [l1, l2, l3] = eigenvalues;
        if !(l3 > 0.0 && l2 > 1e-12 * l3) {
            return Err(SurfelReject::Degenerate);
        }
        if !(planarity_of(eigenvalues) > f64::from(self.planarity_min)) {
            return Err(SurfelReject::NotPlanar);
        }
        // gamma > gamma_min, written without the division (l1 may be 0).
        if !(l2 > f64::from(self.gamma_min) * l1) {
            return Err(SurfelReject::NotThin);
        }
        Ok(())
    }
}

impl Default for SurfelCriteria {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Eigen-decomposition of a symmetric 3x3 matrix by cyclic Jacobi rotations in `f64`.
///
/// Returns the eigenvalues ascending and `vectors[i]`, the unit eigenvector of `values[i]`.
/// Jacobi is unconditionally stable and gives small eigenvalues to high *relative* accuracy when
/// the matrix is well scaled, which is what the `gamma = λ2 / λ1` test needs; it converges
/// quadratically (3x3: a handful of sweeps; capped at 32). Non-finite input gives NaN values
/// (every criterion then fails).
pub fn eigen_sym3(m: &Sym3) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut a = [[m[0], m[1], m[2]], [m[1], m[3], m[4]], [m[2], m[4], m[5]]];
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    if m.iter().any(|x| !x.is_finite()) {
        return ([f64::NAN; 3], v);
    }
    for _sweep in 0..32 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        let diag = a[0][0].abs() + a[1][1].abs() + a[2][2].abs();
        if off == 0.0 || off <= 1e-20 * diag {
            break;
        }
        for (p, q) in [(0usize, 1usize), (0, 2), (1, 2)] {
            jacobi_rotate(&mut a, &mut v, p, q);
        }
    }
    let mut values = [a[0][0], a[1][1], a[2][2]];
    let mut vectors = [[v[0][0], v[1][0], v[2][0]], [v[0][1], v[1][1], v[2][1]], [v[0][2], v[1][2], v[2][2]]];
    // Sort ascending (3 elements: a fixed network of compare-and-swap, deterministic).
    for (i, j) in [(0usize, 1usize), (1, 2), (0, 1)] {
        if values[j] < values[i] {
            values.swap(i, j);
            vectors.swap(i, j);
        }
    }
    for vec in &mut vectors {
        let n = crate::math::sqrt(dot3(*vec, *vec));
        if n > 0.0 {
            for x in vec.iter_mut() {
                *x /= n;
            }
        }
    }
    (values, vectors)
}

/// Eigen-decomposition of a symmetric 3x3 matrix in closed form; `None` (the caller falls back
/// to [`eigen_sym3`]) for a matrix within 1e-6 of a multiple of the identity or not finite.
///
/// The trigonometric solution of the characteristic cubic gives the eigenvalues; the one
/// farthest from the other two (the smallest of a flat surfel, the largest of a line) is
/// accurate, the close pair only to about `sqrt(eps)` of the spread. So only the isolated
/// eigenvector is taken from the cubic (the longest cross product of two rows of `A - λ I`,
/// whose rows span the plane orthogonal to it), its eigenvalue refined as the Rayleigh
/// quotient, and the pair solved exactly as the 2x2 problem in the orthogonal plane (one
/// Jacobi rotation). Accuracy as Jacobi's: vectors to about `1e-16 spread / gap`. No
/// iteration and no trigonometry (see `cos_third_acos`): a handful of square roots and
/// divisions.
pub fn eigen_sym3_closed(m: &Sym3) -> Option<([f64; 3], [[f64; 3]; 3])> {
    let [a00, a01, a02, a11, a12, a22] = *m;
    let q = (a00 + a11 + a22) / 3.0;
    let (b00, b11, b22) = (a00 - q, a11 - q, a22 - q);
    let p2 = b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12);
    if !(p2 > 0.0 && p2 < 1e300) {
        return None; // a multiple of the identity, or not finite
    }
    let p = crate::math::sqrt(p2 / 6.0);
    let inv = 1.0 / p;
    let (c00, c01, c02, c11, c12, c22) = (b00 * inv, a01 * inv, a02 * inv, b11 * inv, a12 * inv, b22 * inv);
    // The spread l3 - l1 is between 3 p and 2 sqrt(3) p, and |l1| + |l3| at most 2 |q| + 4 p.
    if !(3.0 * p > 1e-6 * (2.0 * q.abs() + 4.0 * p)) {
        return None;
    }
    let det = c00 * (c11 * c22 - c12 * c12) - c01 * (c01 * c22 - c12 * c02) + c02 * (c01 * c12 - c11 * c02);
    // The eigenvalues of (A - q I) / p are 2 cos(phi + 2 k pi / 3), cos(3 phi) = det / 2. The
    // largest is isolated when det > 0 (phi < pi / 6), the smallest otherwise; it is
    // q +- 2 p cos(acos(|det| / 2) / 3).
    let x = (0.5 * det).clamp(-1.0, 1.0);
    let low_isolated = x <= 0.0;
    let c = cos_third_acos(x.abs());
    let v = null_vector(m, if low_isolated { q - 2.0 * p * c } else { q + 2.0 * p * c })?;
    let av = sym_mul(m, v);
    let lv = dot3(v, av);
    // An orthonormal basis (u, w) of the plane orthogonal to v, and A restricted to it.
    let u = unit3(cross3(v, least_axis(v)))?;
    let w = cross3(v, u);
    let (au, aw) = (sym_mul(m, u), sym_mul(m, w));
    let (a, b, c) = (dot3(u, au), dot3(u, aw), dot3(w, aw));
    // One Jacobi rotation diagonalises it (see `jacobi_rotate`).
    let t = if b == 0.0 { 0.0 } else { rotation_tan(c - a, 2.0 * b) };
    let cs = 1.0 / crate::math::sqrt(t * t + 1.0);
    let (values, vectors, ordered) = assemble((lv, v), low_isolated, [a, b, c], t, cs, u, w);
    ordered.then_some((values, vectors))
}

/// The end of [`eigen_sym3_closed`] (and of its lanes): the pair's rotation by `t` (cosine
/// `cs`) in the basis `(u, w)` of A restricted to `[a, b, c]`, and the three eigenpairs in
/// ascending order with the isolated one `(lv, v)` first or last, and whether they are in
/// order (rounding may leave the isolated value a hair past its neighbour).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn assemble(
    (lv, v): (f64, [f64; 3]),
    low_isolated: bool,
    [a, b, c]: [f64; 3],
    t: f64,
    cs: f64,
    u: [f64; 3],
    w: [f64; 3],
) -> ([f64; 3], [[f64; 3]; 3], bool) {
    let sn = t * cs;
    let (la, lb) = (a - t * b, c + t * b);
    let xa = [cs * u[0] - sn * w[0], cs * u[1] - sn * w[1], cs * u[2] - sn * w[2]];
    let xb = [sn * u[0] + cs * w[0], sn * u[1] + cs * w[1], sn * u[2] + cs * w[2]];
    let (pair_lo, pair_hi) = if la <= lb { ((la, xa), (lb, xb)) } else { ((lb, xb), (la, xa)) };
    let [(v1, e1), (v2, e2), (v3, e3)] =
        if low_isolated { [(lv, v), pair_lo, pair_hi] } else { [pair_lo, pair_hi, (lv, v)] };
    ([v1, v2, v3], [e1, e2, e3], v1 <= v2 && v2 <= v3)
}

/// `cos(acos(y) / 3)` for `y` in [0, 1] (in [cos(30 deg), 1]; smooth there): a degree-7
/// polynomial (error below 1.5e-8) refined by one Newton step on `4 c^3 - 3 c = y`, which
/// leaves it within 5e-16. The trigonometric form costs an `acos` and a `cos`.
#[inline]
fn cos_third_acos(y: f64) -> f64 {
    const P: [f64; 8] = [
        0.866_025_418_487_860_6,
        0.166_665_004_910_188_6,
        -0.048_077_599_969_208_67,
        0.024_396_834_548_788_833,
        -0.014_308_110_684_524_656,
        0.007_698_013_997_092_669,
        -0.002_951_174_269_594_082_7,
        0.000_551_623_982_633_952_6,
    ];
    let mut c = P[7];
    for k in (0..7).rev() {
        c = c * y + P[k];
    }
    let f = (4.0 * c * c - 3.0) * c - y;
    c - f / (12.0 * c * c - 3.0)
}

#[inline]
fn sym_mul(m: &Sym3, v: [f64; 3]) -> [f64; 3] {
    [
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[1] * v[0] + m[3] * v[1] + m[4] * v[2],
        m[2] * v[0] + m[4] * v[1] + m[5] * v[2],
    ]
}

/// The unit vector spanning the null space of `A - λ I` (rank 2): the longest cross product of
/// two of its rows.
fn null_vector(m: &Sym3, l: f64) -> Option<[f64; 3]> {
    unit3(longest_row_cross(m, l).0)
}

/// The longest cross product of two rows of `A - λ I` and its squared length (before
/// [`unit3`], which the lanes take in a batch).
#[inline(always)]
fn longest_row_cross(m: &Sym3, l: f64) -> ([f64; 3], f64) {
    let r0 = [m[0] - l, m[1], m[2]];
    let r1 = [m[1], m[3] - l, m[4]];
    let r2 = [m[2], m[4], m[5] - l];
    let (x01, x02, x12) = (cross3(r0, r1), cross3(r0, r2), cross3(r1, r2));
    let (n01, n02, n12) = (dot3(x01, x01), dot3(x02, x02), dot3(x12, x12));
    if n01 >= n02 && n01 >= n12 {
        (x01, n01)
    } else if n02 >= n12 {
        (x02, n02)
    } else {
        (x12, n12)
    }
}

/// The coordinate axis along which `v` is shortest (the first of equals): crossed with `v`, it
/// gives a vector orthogonal to `v` far from zero.
#[inline]
fn least_axis(v: [f64; 3]) -> [f64; 3] {
    if v[0].abs() <= v[1].abs() && v[0].abs() <= v[2].abs() {
        [1.0, 0.0, 0.0]
    } else if v[1].abs() <= v[2].abs() {
        [0.0, 1.0, 0.0]
    } else {
        [0.0, 0.0, 1.0]
    }
}

#[inline]
fn cross3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

#[inline]
fn unit3(v: [f64; 3]) -> Option<[f64; 3]> {
    let n2 = dot3(v, v);
    if !(n2 > 0.0 && n2.is_finite()) {
        return None;
    }
    let s = 1.0 / crate::math::sqrt(n2);
    Some([v[0] * s, v[1] * s, v[2] * s])
}

/// One Jacobi rotation zeroing `a[p][q]`; `v` accumulates the rotations (columns = eigenvectors).
///
/// An element too small to change either diagonal entry in f64 (`100 |apq|` vanishes beside
/// both) is set to zero without a rotation: the diagonal is already exact to rounding, and the
/// sweeps that would only polish such elements (each rotation a chain of two square roots and
/// two divisions) are skipped.
fn jacobi_rotate(a: &mut [[f64; 3]; 3], v: &mut [[f64; 3]; 3], p: usize, q: usize) {
    let apq = a[p][q];
    if apq == 0.0 {
        return;
    }
    let g = 100.0 * apq.abs();
    if a[p][p].abs() + g == a[p][p].abs() && a[q][q].abs() + g == a[q][q].abs() {
        a[p][q] = 0.0;
        a[q][p] = 0.0;
        return;
    }
    let t = rotation_tan(a[q][q] - a[p][p], 2.0 * apq);
    let c = 1.0 / crate::math::sqrt(t * t + 1.0);
    let s = t * c;
    a[p][p] -= t * apq;
    a[q][q] += t * apq;
    a[p][q] = 0.0;
    a[q][p] = 0.0;
    let r = 3 - p - q;
    let (arp, arq) = (a[r][p], a[r][q]);
    a[r][p] = c * arp - s * arq;
    a[p][r] = a[r][p];
    a[r][q] = s * arp + c * arq;
    a[q][r] = a[r][q];
    for row in v.iter_mut() {
        let (vp, vq) = (row[p], row[q]);
        row[p] = c * vp - s * vq;
        row[q] = s * vp + c * vq;
    }
}

/// `tan` of the Jacobi rotation that zeroes the off-diagonal element of `[[a, e/2], [e/2, a+d]]`
/// (`e != 0`): the smaller root of `t² + 2 t theta - 1 = 0`, `theta = d / e`, written without
/// the division as `sign(d) e / (|d| + sqrt(d² + e²))`; through `theta` only where the squares
/// could overflow.
fn rotation_tan(d: f64, e: f64) -> f64 {
    if d.abs() > 1e150 || e.abs() > 1e150 {
        let theta = d / e;
        if theta.abs() > 1e150 {
            0.5 / theta
        } else {
            let s = if theta >= 0.0 { 1.0 } else { -1.0 };
            s / (theta.abs() + crate::math::sqrt(theta * theta + 1.0))
        }
    } else {
        let s = if d >= 0.0 { 1.0 } else { -1.0 };
        s * e / (d.abs() + crate::math::sqrt(d * d + e * e))
    }
}

/// A plane through a handful of points: unit `normal` and a point `centroid` on it.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Plane {
    /// Unit normal (sign deterministic but arbitrary; flip it as the caller needs).
    pub normal: [f32; 3],
    /// The points' centroid, on the plane (world frame).
    pub centroid: [f32; 3],
    /// The largest |distance| of a fitted point from the plane, metres.
    pub max_residual: f32,
    /// The points' middle eigenvalue over their largest: near 0 when they lie along a line
    /// (one scan ring on the ground, a pole), about which the fitted normal is free to turn.
    pub spread: f32,
}

impl Plane {
    /// Signed distance of `p` from the plane, `n · (p - centroid)` (the paper's Eq. 9 residual),
    /// computed in `f64` so it stays exact far from the origin.
    pub fn signed_distance(&self, p: [f32; 3]) -> f32 {
        let mut s = 0.0f64;
        for a in 0..3 {
            s += f64::from(self.normal[a]) * (f64::from(p[a]) - f64::from(self.centroid[a]));
        }
        s as f32
    }
}

/// Fits a plane to `points` (the k nearest map points) and accepts it only if every point lies
/// within `max_dist` of it: the reference's point-to-plane acceptance (`esti_plane`, 0.1 m).
///
/// The fit is PCA in `f64` about the first point (the normal is the covariance's
/// smallest-eigenvalue eigenvector). The reference solves `A x = -1` instead, which breaks down
/// for planes through or near the world origin (`d → 0`, `|x| → ∞`) and weighs points
/// unevenly; PCA is the total-least-squares plane and is conditioned by the points' spread only.
/// Needs 3 points or more; collinear or coincident points are [`SurfelReject::Degenerate`].
pub fn fit_plane(points: &[[f32; 3]], max_dist: f32) -> Result<Plane, SurfelReject> {
    if points.len() < 3 {
        return Err(SurfelReject::TooFewPoints);
    }
    if points.iter().any(|p| p.iter().any(|x| !x.is_finite())) {
        return Err(SurfelReject::Degenerate);
    }
    let o = [f64::from(points[0][0]), f64::from(points[0][1]), f64::from(points[0][2])];
    let mut m = Moments::new(o);
    for p in points {
        m.add([f64::from(p[0]), f64::from(p[1]), f64::from(p[2])]);
    }
    let shape = Shape::of_covariance(&m.covariance());
    plane_verdict(points, o, m.sum, f64::from(m.n), shape.eigenvalues, shape.normal(), max_dist)
}

/// The end of [`fit_plane`] (and of its lanes), given the points' sums about `o` and the
/// clamped eigenvalues and normal of their covariance: the degeneracy and distance tests and
/// the plane.
#[inline(always)]
fn plane_verdict(
    points: &[[f32; 3]],
    o: [f64; 3],
    sum: [f64; 3],
    n_pts: f64,
    [_, l2, l3]: [f64; 3],
    n: [f64; 3],
    max_dist: f32,
) -> Result<Plane, SurfelReject> {
    // A line (or a point) has no unique plane: the middle eigenvalue must be a real extent.
    if !(l3 > 0.0 && l2 > 1e-8 * l3) {
        return Err(SurfelReject::Degenerate);
    }
    let c = [sum[0] / n_pts, sum[1] / n_pts, sum[2] / n_pts]; // relative to o
    let mut max_res = 0.0f64;
    for p in points {
        let d = [f64::from(p[0]) - o[0] - c[0], f64::from(p[1]) - o[1] - c[1], f64::from(p[2]) - o[2] - c[2]];
        let r = dot3(n, d).abs();
        if r > max_res {
            max_res = r;
        }
    }
    if !(max_res <= f64::from(max_dist)) {
        return Err(SurfelReject::OffPlane);
    }
    Ok(Plane {
        normal: [n[0] as f32, n[1] as f32, n[2] as f32],
        centroid: [(o[0] + c[0]) as f32, (o[1] + c[1]) as f32, (o[2] + c[2]) as f32],
        max_residual: max_res as f32,
        spread: (l2 / l3) as f32,
    })
}

/// Point sets [`fit_plane_lanes`] fits at once.
pub const PLANE_LANES: usize = 8;

type Lanes = [f64; PLANE_LANES];

/// [`crate::math::sqrt4`] over the lanes.
#[inline(always)]
fn sqrt_lanes(x: Lanes) -> Lanes {
    let mut out = x;
    for c in 0..PLANE_LANES / 4 {
        let v = crate::math::sqrt4([x[4 * c], x[4 * c + 1], x[4 * c + 2], x[4 * c + 3]]);
        out[4 * c..4 * c + 4].copy_from_slice(&v);
    }
    out
}

/// [`fit_plane`] of [`PLANE_LANES`] point sets at once (`pts[l][..len[l]]`); every lane's
/// result is the scalar function's, bit for bit.
///
/// The scalar fit is a chain of a dozen dependent square roots and divisions (about 100 ns):
/// here the lanes run the same operations side by side (vector code where the target has it),
/// so the chains overlap. Lanes the straight-line code cannot answer exactly (too few or
/// non-finite points, eigenvalues too close for the closed form, overflow-sized numbers) take
/// the scalar function.
pub fn fit_plane_lanes<const K: usize>(
    pts: &[[[f32; 3]; K]; PLANE_LANES],
    len: [usize; PLANE_LANES],
    max_dist: f32,
) -> [Result<Plane, SurfelReject>; PLANE_LANES] {
    const L: usize = PLANE_LANES;
    let mut scalar: [bool; L] = core::array::from_fn(|l| {
        len[l] < 3 || len[l] > K || pts[l][..len[l]].iter().any(|p| p.iter().any(|x| !x.is_finite()))
    });
    // Moments about the first point, as `Moments::add` sums them.
    let o: [Lanes; 3] = core::array::from_fn(|a| core::array::from_fn(|l| f64::from(pts[l][0][a])));
    let mut sum = [[0.0f64; L]; 3];
    let mut sq = [[0.0f64; L]; 6];
    for j in 0..K {
        for l in 0..L {
            let take = j < len[l];
            let d = [
                f64::from(pts[l][j][0]) - o[0][l],
                f64::from(pts[l][j][1]) - o[1][l],
                f64::from(pts[l][j][2]) - o[2][l],
            ];
            for a in 0..3 {
                sum[a][l] = if take { sum[a][l] + d[a] } else { sum[a][l] };
            }
            let outer = [
                1.0 * d[0] * d[0],
                1.0 * d[0] * d[1],
                1.0 * d[0] * d[2],
                1.0 * d[1] * d[1],
                1.0 * d[1] * d[2],
                1.0 * d[2] * d[2],
            ];
            for i in 0..6 {
                sq[i][l] = if take { sq[i][l] + outer[i] } else { sq[i][l] };
            }
        }
    }
    let n: Lanes = core::array::from_fn(|l| f64::from(len[l].min(K) as u32));
    // `Moments::covariance`: the scatter `S - P Pᵀ / n`, then divided by n.
    let mut cov = sq;
    for l in 0..L {
        let w = -1.0 / n[l];
        let s = [sum[0][l], sum[1][l], sum[2][l]];
        let outer = [
            w * s[0] * s[0],
            w * s[0] * s[1],
            w * s[0] * s[2],
            w * s[1] * s[1],
            w * s[1] * s[2],
            w * s[2] * s[2],
        ];
        let inv = 1.0 / n[l];
        for i in 0..6 {
            cov[i][l] = (cov[i][l] + outer[i]) * inv;
        }
    }
    let (values, normal, ok) = eigen_closed_lanes(&cov);
    let mut out = [Err(SurfelReject::Degenerate); L];
    for l in 0..L {
        scalar[l] |= !ok[l];
        if scalar[l] {
            out[l] = fit_plane(&pts[l][..len[l].min(K)], max_dist);
            continue;
        }
        // `Shape::of_covariance` clamps at 0.
        let values = [0, 1, 2].map(|i| if values[i][l] < 0.0 { 0.0 } else { values[i][l] });
        out[l] = plane_verdict(
            &pts[l][..len[l]],
            [o[0][l], o[1][l], o[2][l]],
            [sum[0][l], sum[1][l], sum[2][l]],
            n[l],
            values,
            [normal[0][l], normal[1][l], normal[2][l]],
            max_dist,
        );
    }
    out
}

/// The eigenvalues and normal `e_d` that [`Shape::of_covariance`] gives, for [`PLANE_LANES`]
/// covariances at once (the first `used`; the others are not analysed): the closed form on
/// lanes, whose chains of square roots and divisions overlap, and the scalar analysis for the
/// lanes it cannot answer, so each result is the scalar one bit for bit.
pub fn eigen_normals_lanes(covs: &[Sym3; PLANE_LANES], used: usize) -> [([f64; 3], [f64; 3]); PLANE_LANES] {
    // Unused lanes get a matrix the closed form answers (no scalar fallback for them).
    const SPARE: Sym3 = [1.0, 0.0, 0.0, 2.0, 0.0, 3.0];
    let m: [Lanes; 6] =
        core::array::from_fn(|i| core::array::from_fn(|l| if l < used { covs[l][i] } else { SPARE[i] }));
    let (values, normal, ok) = eigen_closed_lanes(&m);
    core::array::from_fn(|l| {
        if l >= used {
            return ([0.0; 3], [0.0; 3]);
        }
        if !ok[l] {
            let s = Shape::of_covariance(&covs[l]);
            return (s.eigenvalues, s.normal());
        }
        // `Shape::of_covariance` clamps at 0.
        let v = [0, 1, 2].map(|i| if values[i][l] < 0.0 { 0.0 } else { values[i][l] });
        (v, [normal[0][l], normal[1][l], normal[2][l]])
    })
}

/// [`eigen_sym3_closed`] on lanes, operation for operation: the ascending eigenvalues, the
/// eigenvector of the smallest, and whether the lane's answer is the scalar one (false where
/// the scalar function returns `None` or takes a branch not written here).
fn eigen_closed_lanes(m: &[Lanes; 6]) -> ([Lanes; 3], [Lanes; 3], [bool; PLANE_LANES]) {
    const L: usize = PLANE_LANES;
    let [a00, a01, a02, a11, a12, a22] = *m;
    let mut ok = [true; L];
    let mut q = [0.0; L];
    let mut p2 = [0.0; L];
    let mut b = [[0.0; L]; 3];
    for l in 0..L {
        q[l] = (a00[l] + a11[l] + a22[l]) / 3.0;
        b[0][l] = a00[l] - q[l];
        b[1][l] = a11[l] - q[l];
        b[2][l] = a22[l] - q[l];
        p2[l] = b[0][l] * b[0][l]
            + b[1][l] * b[1][l]
            + b[2][l] * b[2][l]
            + 2.0 * (a01[l] * a01[l] + a02[l] * a02[l] + a12[l] * a12[l]);
        ok[l] &= p2[l] > 0.0 && p2[l] < 1e300;
    }
    let p = sqrt_lanes(p2.map(|v| v / 6.0));
    let mut low = [false; L];
    let mut liso = [0.0; L];
    for l in 0..L {
        let inv = 1.0 / p[l];
        let (c00, c01, c02, c11, c12, c22) =
            (b[0][l] * inv, a01[l] * inv, a02[l] * inv, b[1][l] * inv, a12[l] * inv, b[2][l] * inv);
        ok[l] &= 3.0 * p[l] > 1e-6 * (2.0 * q[l].abs() + 4.0 * p[l]);
        let det =
            c00 * (c11 * c22 - c12 * c12) - c01 * (c01 * c22 - c12 * c02) + c02 * (c01 * c12 - c11 * c02);
        let x = (0.5 * det).clamp(-1.0, 1.0);
        low[l] = x <= 0.0;
        let c = cos_third_acos(x.abs());
        liso[l] = if low[l] { q[l] - 2.0 * p[l] * c } else { q[l] + 2.0 * p[l] * c };
    }
    // `null_vector`: the longest cross product of two rows of A - λ I, made unit. Vectors are
    // kept per component over the lanes (`x[axis][lane]`), which is what vectorises.
    let row = |l: usize| [a00[l], a01[l], a02[l], a11[l], a12[l], a22[l]];
    let get = |x: &[Lanes; 3], l: usize| [x[0][l], x[1][l], x[2][l]];
    let put = |x: &mut [Lanes; 3], l: usize, y: [f64; 3]| (x[0][l], x[1][l], x[2][l]) = (y[0], y[1], y[2]);
    let mut best = [[0.0; L]; 3];
    let mut bn = [0.0; L];
    for l in 0..L {
        let (x, n2) = longest_row_cross(&row(l), liso[l]);
        put(&mut best, l, x);
        bn[l] = n2;
        ok[l] &= n2 > 0.0 && n2.is_finite();
    }
    let rs = sqrt_lanes(bn);
    let mut v = [[0.0; L]; 3];
    let mut u = [[0.0; L]; 3];
    let mut un = [0.0; L];
    for l in 0..L {
        let s = 1.0 / rs[l];
        let vl = get(&best, l).map(|x| x * s);
        let ul = cross3(vl, least_axis(vl));
        un[l] = dot3(ul, ul);
        ok[l] &= un[l] > 0.0 && un[l].is_finite();
        put(&mut v, l, vl);
        put(&mut u, l, ul);
    }
    // The plane orthogonal to v: its basis (u, w), A restricted to it ([a, b, c]), and the
    // rotation that diagonalises that (`rotation_tan(c - a, 2 b)`, its common branch).
    let ru = sqrt_lanes(un);
    let mut w = [[0.0; L]; 3];
    let mut abc = [[0.0; L]; 3];
    let mut dd = [0.0; L];
    for l in 0..L {
        let s = 1.0 / ru[l];
        let (ul, vl) = (get(&u, l).map(|x| x * s), get(&v, l));
        let wl = cross3(vl, ul);
        let (au, aw) = (sym_mul(&row(l), ul), sym_mul(&row(l), wl));
        let (a, b, c) = (dot3(ul, au), dot3(ul, aw), dot3(wl, aw));
        let (d, e) = (c - a, 2.0 * b);
        ok[l] &= !(d.abs() > 1e150 || e.abs() > 1e150);
        dd[l] = d * d + e * e;
        put(&mut u, l, ul);
        put(&mut w, l, wl);
        put(&mut abc, l, [a, b, c]);
    }
    let rd = sqrt_lanes(dd);
    let mut t = [0.0; L];
    for l in 0..L {
        let [a, b, c] = get(&abc, l);
        let (d, e) = (c - a, 2.0 * b);
        let sg = if d >= 0.0 { 1.0 } else { -1.0 };
        t[l] = if b == 0.0 { 0.0 } else { sg * e / (d.abs() + rd[l]) };
    }
    let rc = sqrt_lanes(t.map(|t| t * t + 1.0));
    let mut values = [[0.0; L]; 3];
    let mut normal = [[0.0; L]; 3];
    for l in 0..L {
        let vl = get(&v, l);
        let lv = dot3(vl, sym_mul(&row(l), vl));
        let (vals, vecs, ordered) =
            assemble((lv, vl), low[l], get(&abc, l), t[l], 1.0 / rc[l], get(&u, l), get(&w, l));
        ok[l] &= ordered;
        put(&mut values, l, vals);
        put(&mut normal, l, vecs[0]);
    }
    (values, normal, ok)
}

#[inline]
pub(crate) fn sub3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
pub(crate) fn dot3(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `m += w · a bᵀ` (upper triangle; for `a ≠ b` the caller adds `b aᵀ` too to stay symmetric).
#[inline]
fn add_outer(m: &mut Sym3, a: [f64; 3], b: [f64; 3], w: f64) {
    m[0] += w * a[0] * b[0];
    m[1] += w * a[0] * b[1];
    m[2] += w * a[0] * b[2];
    m[3] += w * a[1] * b[1];
    m[4] += w * a[1] * b[2];
    m[5] += w * a[2] * b[2];
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec::Vec;

    use super::*;

    use crate::testutil::SplitMix as Rng;

    /// `R diag(e) Rᵀ` for a random rotation `R`.
    fn rotated(rng: &mut Rng, e: [f64; 3]) -> Sym3 {
        let q = nalgebra::UnitQuaternion::from_euler_angles(
            rng.uniform(-3.0, 3.0),
            rng.uniform(-1.5, 1.5),
            rng.uniform(-3.0, 3.0),
        );
        let r = q.to_rotation_matrix().into_inner();
        let a =
            r * nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::new(e[0], e[1], e[2])) * r.transpose();
        [a[(0, 0)], a[(0, 1)], a[(0, 2)], a[(1, 1)], a[(1, 2)], a[(2, 2)]]
    }

    /// Checks `A v = λ v`, orthonormality and ascending order to `tol * scale`.
    fn check_eigen(m: &Sym3, tol: f64) -> ([f64; 3], [[f64; 3]; 3]) {
        let (vals, vecs) = eigen_sym3(m);
        let scale = m.iter().fold(0.0f64, |a, x| a.max(x.abs())).max(f64::MIN_POSITIVE);
        assert!(vals[0] <= vals[1] && vals[1] <= vals[2], "{vals:?}");
        for i in 0..3 {
            let av = sym_mul(m, vecs[i]);
            for a in 0..3 {
                assert!((av[a] - vals[i] * vecs[i][a]).abs() <= tol * scale, "{m:?} {i}");
            }
            for j in 0..3 {
                let d = dot3(vecs[i], vecs[j]);
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((d - want).abs() < 1e-12, "not orthonormal: {d}");
            }
        }
        (vals, vecs)
    }

    #[test]
    fn jacobi_matches_nalgebra_on_random_symmetric_matrices() {
        let mut rng = Rng(1);
        for case in 0..2000 {
            // Random eigenvalues spanning many magnitudes (including near-degenerate and
            // repeated ones), random rotation.
            let e = match case % 4 {
                0 => [rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)],
                1 => [1e-9 * rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0)],
                2 => [0.3, 0.3, rng.uniform(0.0, 1.0)],
                _ => [rng.uniform(0.0, 1e-6), 1e-3, 1e3],
            };
            let m = rotated(&mut rng, e);
            let (vals, _) = check_eigen(&m, 1e-13);
            let mut want = e;
            want.sort_by(|x, y| x.partial_cmp(y).unwrap());
            let scale = e.iter().fold(0.0f64, |s, x| s.max(x.abs()));
            let na = nalgebra::Matrix3::new(m[0], m[1], m[2], m[1], m[3], m[4], m[2], m[4], m[5])
                .symmetric_eigen();
            let mut nv = [na.eigenvalues[0], na.eigenvalues[1], na.eigenvalues[2]];
            nv.sort_by(|x, y| x.partial_cmp(y).unwrap());
            for i in 0..3 {
                assert!((vals[i] - want[i]).abs() <= 1e-13 * scale, "case {case}: {vals:?} vs {want:?}");
                assert!((vals[i] - nv[i]).abs() <= 1e-13 * scale, "case {case}: {vals:?} vs nalgebra {nv:?}");
            }
        }
    }

    /// The closed form agrees with Jacobi: eigenvalues to 1e-12 of the spread (the smallest of
    /// a flat surfel to 1e-9 relative or 1e-15 of the largest, far below what gamma needs), each vector to `1e-13 spread / gap`
    /// rad; it answers for everything but near-multiples of the identity.
    #[test]
    fn cos_third_acos_matches_the_trigonometric_form() {
        for i in 0..=100_000 {
            let y = i as f64 / 100_000.0;
            let want = libm::cos(libm::acos(y) / 3.0);
            assert!((cos_third_acos(y) - want).abs() <= 1e-15, "{y}: {} vs {want}", cos_third_acos(y));
        }
    }

    #[test]
    fn closed_form_matches_jacobi() {
        let mut rng = Rng(7);
        let mut answered = 0;
        for case in 0..20000 {
            let e = match case % 5 {
                0 => [rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)],
                // Surfels as the map sees them: a thin direction 1e-2..1e-7 of the others.
                1 => {
                    let l = rng.uniform(0.001, 0.04);
                    [l * libm::pow(10.0, rng.uniform(-7.0, -2.0)), l * rng.uniform(0.05, 1.0), l]
                }
                2 => [0.3, 0.3, rng.uniform(0.0, 1.0)],
                3 => [rng.uniform(0.0, 1e-6), 1e-3, 1e3],
                _ => [0.0, rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0)],
            };
            let m = rotated(&mut rng, e);
            let (jv, jvec) = eigen_sym3(&m);
            let spread = jv[2] - jv[0];
            let Some((cv, cvec)) = eigen_sym3_closed(&m) else {
                assert!(spread <= 2e-6 * (jv[0].abs() + jv[2].abs()), "case {case}: declined {jv:?}");
                continue;
            };
            answered += 1;
            let scale = spread.max(jv[2].abs());
            for i in 0..3 {
                assert!((cv[i] - jv[i]).abs() <= 1e-12 * scale, "case {case}: {cv:?} vs {jv:?}");
                let gap =
                    (0..3).filter(|&j| j != i).map(|j| (jv[j] - jv[i]).abs()).fold(f64::INFINITY, f64::min);
                let x = cross3(cvec[i], jvec[i]);
                let sin = crate::math::sqrt(dot3(x, x));
                assert!(sin <= 1e-13 * scale / gap, "case {case}: vector {i} off by {sin:e} rad; {e:?}");
                for j in 0..3 {
                    let d = dot3(cvec[i], cvec[j]);
                    assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
                }
            }
            if case % 5 == 1 {
                // Relative to itself down to rounding of the largest (eps = 2.2e-16).
                let tol = 1e-9 * jv[0] + 1e-15 * jv[2];
                assert!((cv[0] - jv[0]).abs() <= tol, "case {case}: smallest {} vs {}", cv[0], jv[0]);
            }
        }
        assert!(answered > 19000, "{answered}");
    }

    #[test]
    fn jacobi_edge_cases() {
        // Zero, diagonal (already converged), permuted diagonal, rank one, huge and tiny scales.
        let (v, _) = check_eigen(&[0.0; 6], 0.0);
        assert_eq!(v, [0.0; 3]);
        let (v, vecs) = check_eigen(&[3.0, 0.0, 0.0, 1.0, 0.0, 2.0], 0.0);
        assert_eq!(v, [1.0, 2.0, 3.0]);
        assert_eq!(vecs[0], [0.0, 1.0, 0.0]);
        let (v, vecs) = check_eigen(&[1.0, 1.0, 1.0, 1.0, 1.0, 1.0], 1e-15);
        assert!(v[0].abs() < 1e-15 && v[1].abs() < 1e-15 && (v[2] - 3.0).abs() < 1e-14);
        let s = 1.0 / crate::math::sqrt(3.0);
        assert!((dot3(vecs[2], [s, s, s]).abs() - 1.0).abs() < 1e-14);
        check_eigen(&[1e150, 1e149, 0.0, 1e150, 0.0, 1e140], 1e-13);
        check_eigen(&[1e-150, 1e-151, 0.0, 1e-150, 0.0, 1e-160], 1e-13);
        let (v, _) = eigen_sym3(&[f64::NAN, 0.0, 0.0, 1.0, 0.0, 1.0]);
        assert!(v.iter().all(|x| x.is_nan()));
        // NaN fails every criterion.
        let shape = Shape { eigenvalues: v, eigenvectors: [[0.0; 3]; 3] };
        assert!(SurfelCriteria::DEFAULT.check(&shape).is_err());
    }

    #[test]
    fn merge_equals_batch_for_any_split_and_origins() {
        let mut rng = Rng(7);
        let pts: Vec<[f64; 3]> = (0..300)
            .map(|_| {
                [1000.0 + rng.uniform(-2.0, 2.0), -500.0 + rng.uniform(-1.0, 1.0), rng.uniform(0.0, 0.1)]
            })
            .collect();
        let batch = Moments::from_points([1000.0, -500.0, 0.0], &pts);
        for split in [0usize, 1, 17, 150, 299, 300] {
            let mut a = Moments::from_points([999.0, -499.0, 0.5], &pts[..split]);
            let b = Moments::from_points([1001.5, -500.2, -3.0], &pts[split..]);
            a.merge(&b);
            assert_eq!(a.n, 300);
            let (ma, mb) = (a.mean().unwrap(), batch.mean().unwrap());
            let (ca, cb) = (a.covariance(), batch.covariance());
            for i in 0..3 {
                assert!((ma[i] - mb[i]).abs() < 1e-10);
            }
            for i in 0..6 {
                assert!((ca[i] - cb[i]).abs() < 1e-11, "split {split}: {ca:?} vs {cb:?}");
            }
        }
        // The direct covariance, from the mean.
        let mean = batch.mean().unwrap();
        let mut direct = [0.0f64; 6];
        for p in &pts {
            let d = sub3(*p, mean);
            add_outer(&mut direct, d, d, 1.0 / 300.0);
        }
        let c = batch.covariance();
        for i in 0..6 {
            assert!((c[i] - direct[i]).abs() < 1e-12);
        }
        // `about` round trip and empty sets.
        let back = batch.about([0.0; 3]).about(batch.origin);
        for i in 0..6 {
            assert!((back.sum_sq[i] - batch.sum_sq[i]).abs() < 1e-6 * batch.sum_sq[i].abs().max(1.0));
        }
        let mut e = Moments::new([5.0; 3]);
        assert_eq!(e.mean(), None);
        assert_eq!(e.covariance(), [0.0; 6]);
        e.merge(&batch);
        assert_eq!(e.n, 300);
    }

    /// Points on a grid in the plane spanned by `u`, `v` through `c`, plus `noise` along `n`.
    fn patch(
        c: [f64; 3],
        u: [f64; 3],
        v: [f64; 3],
        n: [f64; 3],
        half: (f64, f64),
        noise: f64,
    ) -> Vec<[f64; 3]> {
        let mut rng = Rng(3);
        let mut out = Vec::new();
        for i in 0..10 {
            for j in 0..10 {
                let a = half.0 * (i as f64 / 4.5 - 1.0);
                let b = half.1 * (j as f64 / 4.5 - 1.0);
                let w = noise * rng.uniform(-1.0, 1.0);
                out.push([
                    c[0] + a * u[0] + b * v[0] + w * n[0],
                    c[1] + a * u[1] + b * v[1] + w * n[1],
                    c[2] + a * u[2] + b * v[2] + w * n[2],
                ]);
            }
        }
        out
    }

    #[test]
    fn planarity_and_gamma_follow_the_paper_definitions() {
        let shape = Shape::of_covariance(&[4.0, 0.0, 0.0, 1.0, 0.0, 0.01]);
        assert_eq!(shape.eigenvalues, [0.01, 1.0, 4.0]);
        assert!((shape.planarity() - 2.0 * (1.0 - 0.01) / 5.01).abs() < 1e-15);
        assert!((shape.gamma() - 100.0).abs() < 1e-12);
        assert_eq!(shape.normal().map(f64::abs), [0.0, 0.0, 1.0]);
        // rho never exceeds 1 for a covariance: the paper's "rho > 1.0" is unreachable.
        let mut rng = Rng(11);
        for _ in 0..1000 {
            let e = [rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0)];
            let s = Shape::of_covariance(&[e[0], 0.0, 0.0, e[1], 0.0, e[2]]);
            assert!(s.planarity() <= 1.0 + 1e-15);
        }
        // A flat square patch: rho = 1 exactly, gamma infinite.
        let s = [0.0, 0.0, 1.0];
        let flat = Moments::from_points(
            [0.0; 3],
            &patch([0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], s, (0.2, 0.2), 0.0),
        );
        let shape = Shape::of_covariance(&flat.covariance());
        assert!((shape.planarity() - 1.0).abs() < 1e-12);
        assert_eq!(shape.gamma(), f64::INFINITY);
        assert_eq!(SurfelCriteria::DEFAULT.check(&shape), Ok(()));
    }

    #[test]
    fn surfel_criteria_decisions() {
        let c = SurfelCriteria::DEFAULT;
        let (x, y, z) = ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]);
        let shape =
            |pts: &[[f64; 3]]| Shape::of_covariance(&Moments::from_points([0.0; 3], pts).covariance());
        // Square patch with 2 mm noise: a surfel (gamma ~ 0.0133 / 1.3e-6).
        assert_eq!(c.check(&shape(&patch([0.0; 3], x, y, z, (0.2, 0.2), 0.002))), Ok(()));
        // 3 cm of noise on a 0.4 m patch: too thick (gamma ~ 0.0137 / 3e-4 = 45).
        assert_eq!(c.check(&shape(&patch([0.0; 3], x, y, z, (0.2, 0.2), 0.03))), Err(SurfelReject::NotThin));
        // A strip 0.4 x 0.1: lambda2 / lambda3 = 1/16, rho = 2/17 < 0.6.
        assert_eq!(
            c.check(&shape(&patch([0.0; 3], x, y, z, (0.2, 0.05), 0.0))),
            Err(SurfelReject::NotPlanar)
        );
        // Aspect 1.4 (rho = 2/(1+1.96) = 0.68) passes, aspect 1.7 (rho = 0.51) fails: the
        // documented bound sqrt(7/3) = 1.53.
        assert_eq!(c.check(&shape(&patch([0.0; 3], x, y, z, (0.2, 0.2 / 1.4), 0.0))), Ok(()));
        assert_eq!(
            c.check(&shape(&patch([0.0; 3], x, y, z, (0.2, 0.2 / 1.7), 0.0))),
            Err(SurfelReject::NotPlanar)
        );
        // A line and a single point are degenerate.
        let line: Vec<[f64; 3]> = (0..10).map(|i| [i as f64 * 0.01, 0.0, 0.0]).collect();
        assert_eq!(c.check(&shape(&line)), Err(SurfelReject::Degenerate));
        assert_eq!(c.check(&shape(&[[1.0, 2.0, 3.0]; 5])), Err(SurfelReject::Degenerate));
    }

    /// The lanes give the scalar fit's results bit for bit, on the sets the association sees
    /// (4 to 8 neighbours on a noisy plane, anywhere in the world) and on those the scalar fit
    /// refuses or that leave the closed form: lines, coincident points, near-isotropic clouds,
    /// non-finite coordinates, too few points.
    #[test]
    fn plane_fit_lanes_equal_the_scalar_fit() {
        fn same(a: &Result<Plane, SurfelReject>, b: &Result<Plane, SurfelReject>) -> bool {
            match (a, b) {
                (Ok(x), Ok(y)) => {
                    let bits =
                        |p: &Plane| [p.normal, p.centroid, [p.max_residual; 3]].map(|v| v.map(f32::to_bits));
                    bits(x) == bits(y)
                }
                (Err(x), Err(y)) => x == y,
                _ => false,
            }
        }
        let mut rng = Rng(11);
        let mut kinds = [0usize; 4]; // ok, off plane, degenerate, other
        for case in 0..4000 {
            let mut pts = [[[0.0f32; 3]; 8]; PLANE_LANES];
            let mut len = [0usize; PLANE_LANES];
            for l in 0..PLANE_LANES {
                len[l] = 3 + (rng.next_u64() % 6) as usize;
                let far = if case % 3 == 0 { 1000.0 } else { 20.0 };
                let c = [rng.uniform(-far, far), rng.uniform(-far, far), rng.uniform(-5.0, 5.0)];
                let (u, v) = (
                    [1.0, rng.uniform(-1.0, 1.0), rng.uniform(-0.3, 0.3)],
                    [rng.uniform(-0.3, 0.3), 1.0, rng.uniform(-1.0, 1.0)],
                );
                let noise = [0.0, 0.005, 0.05, 0.3][(rng.next_u64() % 4) as usize];
                let style = rng.next_u64() % 10;
                for j in 0..8 {
                    let (s, t) = (rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5));
                    let p: [f64; 3] = core::array::from_fn(|a| match style {
                        0 => c[a] + s * u[a],               // a line
                        1 => c[a],                          // one point, repeated
                        2 => c[a] + rng.uniform(-0.3, 0.3), // a blob
                        _ => c[a] + s * u[a] + t * v[a] + noise * rng.gauss(),
                    });
                    pts[l][j] = p.map(|x| x as f32);
                }
                if style == 3 && case % 7 == 0 {
                    pts[l][(rng.next_u64() % len[l] as u64) as usize][1] = f32::NAN;
                }
                if style == 4 && case % 5 == 0 {
                    len[l] = (rng.next_u64() % 3) as usize;
                }
            }
            let lanes = fit_plane_lanes(&pts, len, 0.1);
            for l in 0..PLANE_LANES {
                let want = fit_plane(&pts[l][..len[l]], 0.1);
                assert!(same(&lanes[l], &want), "case {case} lane {l}: {:?} vs {want:?}", lanes[l]);
                kinds[match want {
                    Ok(_) => 0,
                    Err(SurfelReject::OffPlane) => 1,
                    Err(SurfelReject::Degenerate) => 2,
                    Err(_) => 3,
                }] += 1;
            }
        }
        // Every outcome is exercised.
        assert!(kinds.iter().all(|&k| k > 200), "{kinds:?}");
        // The lanes answer surfel-like covariances themselves (no fallback), as the closed form.
        for _ in 0..500 {
            let covs: [Sym3; PLANE_LANES] = core::array::from_fn(|_| {
                let l = rng.uniform(0.001, 0.04);
                let e = [l * libm::pow(10.0, rng.uniform(-7.0, -1.0)), l * rng.uniform(0.05, 1.0), l];
                rotated(&mut rng, e)
            });
            let m: [Lanes; 6] = core::array::from_fn(|i| core::array::from_fn(|l| covs[l][i]));
            let (values, normal, ok) = eigen_closed_lanes(&m);
            for l in 0..PLANE_LANES {
                let (cv, cvec) = eigen_sym3_closed(&covs[l]).unwrap();
                assert!(ok[l]);
                for i in 0..3 {
                    assert_eq!(values[i][l].to_bits(), cv[i].to_bits());
                    assert_eq!(normal[i][l].to_bits(), cvec[0][i].to_bits());
                }
            }
        }
    }

    /// `eigen_normals_lanes` (the association's large surfels, eight at a time) gives what
    /// `Shape::of_covariance` gives, bit for bit: surfel-like covariances (the lanes answer),
    /// and ones the closed form refuses (a multiple of the identity, two equal eigenvalues,
    /// zero, non-finite), which take the scalar path; partly used groups too.
    #[test]
    fn eigen_normals_lanes_equal_the_scalar_shape() {
        let mut rng = Rng(0x5eed_1a7e);
        let odd: [Sym3; 5] = [
            [2.0, 0.0, 0.0, 2.0, 0.0, 2.0],
            [1.0, 0.0, 0.0, 1.0, 0.0, 3.0],
            [0.0; 6],
            [f64::NAN, 0.0, 0.0, 1.0, 0.0, 1.0],
            [1e-30, 0.0, 0.0, 1e-30, 0.0, 2e-30],
        ];
        let (mut lanes_answered, mut fallbacks) = (0, 0);
        for case in 0..2000 {
            let covs: [Sym3; PLANE_LANES] = core::array::from_fn(|_| {
                if rng.uniform(0.0, 1.0) < 0.1 {
                    return odd[(rng.uniform(0.0, 5.0) as usize).min(4)];
                }
                let l = rng.uniform(0.001, 0.04);
                let e = [l * libm::pow(10.0, rng.uniform(-7.0, -1.0)), l * rng.uniform(0.05, 1.0), l];
                rotated(&mut rng, e)
            });
            let used = 1 + case % PLANE_LANES;
            let got = eigen_normals_lanes(&covs, used);
            for l in 0..used {
                let want = Shape::of_covariance(&covs[l]);
                let same = (0..3).all(|i| {
                    got[l].0[i].to_bits() == want.eigenvalues[i].to_bits()
                        && got[l].1[i].to_bits() == want.normal()[i].to_bits()
                });
                assert!(same, "case {case} lane {l}: {:?} vs {want:?}", got[l]);
                if eigen_sym3_closed(&covs[l]).is_some() {
                    lanes_answered += 1;
                } else {
                    fallbacks += 1;
                }
            }
        }
        assert!(lanes_answered > 5000 && fallbacks > 300, "{lanes_answered} {fallbacks}");
    }

    #[test]
    fn plane_fit_recovers_known_planes_and_applies_the_reference_acceptance() {
        let planes: [([f64; 3], [f64; 3]); 4] = [
            ([0.0, 0.0, 0.0], [0.0, 0.0, 1.0]), // through the origin: A x = -1 has no solution
            ([0.0, 0.0, 0.0], [0.6, 0.0, 0.8]),
            ([12.0, -3.0, 1.5], [0.36, 0.48, 0.8]),
            ([10_000.0, 10_000.0, 20.0], [1.0, 0.0, 0.0]), // 14 km out
        ];
        for (c, n) in planes {
            // Two in-plane directions.
            let t = if n[0].abs() < 0.9 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
            let u = normalised_cross(n, t);
            let v = normalised_cross(n, u);
            let pts: Vec<[f32; 3]> = [(0.0, 0.0), (0.1, 0.05), (-0.2, 0.1), (0.05, -0.3), (0.15, 0.2)]
                .iter()
                .map(|&(a, b)| {
                    let p =
                        [c[0] + a * u[0] + b * v[0], c[1] + a * u[1] + b * v[1], c[2] + a * u[2] + b * v[2]];
                    [p[0] as f32, p[1] as f32, p[2] as f32]
                })
                .collect();
            let plane = fit_plane(&pts, 0.1).unwrap();
            let nn = [f64::from(plane.normal[0]), f64::from(plane.normal[1]), f64::from(plane.normal[2])];
            // f32 inputs: at 14 km they are quantised to ~1 mm, over a 0.5 m spread.
            let tol = if c[0] > 1000.0 { 5e-3 } else { 1e-6 };
            // sin(angle) = |nn x n| / |nn|.
            let x = cross3(nn, n);
            let sin = crate::math::sqrt(dot3(x, x)) / crate::math::sqrt(dot3(nn, nn));
            assert!(sin < tol, "normal {nn:?} vs {n:?}: sin {sin}");
            assert!(plane.max_residual < if c[0] > 1000.0 { 2e-3 } else { 1e-6 });
            assert!(plane.signed_distance([c[0] as f32, c[1] as f32, c[2] as f32]).abs() < 2e-3);
            // One neighbour 0.12 m off the plane: rejected at 0.1 m.
            let mut off = pts.clone();
            for a in 0..3 {
                off[4][a] += (0.3 * n[a]) as f32;
            }
            assert_eq!(fit_plane(&off, 0.1), Err(SurfelReject::OffPlane));
        }
        let line: Vec<[f32; 3]> = (0..5).map(|i| [i as f32 * 0.1, 1.0, 2.0]).collect();
        assert_eq!(fit_plane(&line, 0.1), Err(SurfelReject::Degenerate));
        assert_eq!(fit_plane(&line[..2], 0.1), Err(SurfelReject::TooFewPoints));
        assert_eq!(
            fit_plane(&[[0.0; 3], [1.0, 0.0, 0.0], [f32::NAN, 1.0, 0.0]], 0.1),
            Err(SurfelReject::Degenerate)
        );
    }

    fn normalised_cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
        let c = cross3(a, b);
        let n = crate::math::sqrt(dot3(c, c));
        [c[0] / n, c[1] / n, c[2] / n]
    }
}
