//! The classic normal estimator, for comparison with Ring FALS: the k nearest neighbours of each
//! point (a kiddo k-d tree), their covariance, and the eigenvector of its smallest eigenvalue.
//!
//! Used by `loglio normals`, the real-capture test and the `ring_fals` benchmark (which includes
//! this file by path, so it depends on nothing but kiddo and nalgebra).

use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Matrix3, SymmetricEigen, Vector3};

/// A PCA normal and the covariance eigenvalues it came from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PcaNormal {
    /// Unit normal, oriented toward the sensor at the origin (`n . p < 0`).
    pub normal: [f64; 3],
    /// Covariance eigenvalues, ascending (m^2).
    pub eigenvalues: [f64; 3],
}

impl PcaNormal {
    /// Planarity test: the smallest eigenvalue is at most `ratio` times the middle one (flat)
    /// and the middle one at least `spread` times the largest (spread in two directions: ten
    /// points along one scan line look flat to PCA, but their smallest-eigenvalue direction is
    /// only the direction across the line).
    pub fn is_planar(&self, ratio: f64, spread: f64) -> bool {
        let [l0, l1, l2] = self.eigenvalues;
        l1 > 0.0 && l2 > 0.0 && l0 <= ratio * l1 && l1 >= spread * l2
    }
}

/// kNN-PCA normals of `points` (the neighbourhood includes the point itself). `None` for points
/// that are not finite or whose neighbourhood is degenerate. Fails only if the tree cannot be
/// built.
pub fn knn_pca_normals(points: &[[f32; 3]], k: usize) -> Result<Vec<Option<PcaNormal>>, String> {
    let k = NonZeroUsize::new(k.max(3)).ok_or("k must be at least 3")?;
    // The tree needs finite coordinates: keep an index map of the finite points.
    let finite: Vec<usize> = (0..points.len()).filter(|&i| points[i].iter().all(|v| v.is_finite())).collect();
    let coords: Vec<[f32; 3]> = finite.iter().map(|&i| points[i]).collect();
    let mut out = vec![None; points.len()];
    if coords.len() < k.get() {
        return Ok(out);
    }
    let tree: ImmutableKdTree<f32, 3> =
        ImmutableKdTree::new_from_slice(&coords).map_err(|e| format!("kd-tree: {e:?}"))?;
    for (j, &i) in finite.iter().enumerate() {
        let q = coords[j];
        let nn = tree.query(&q).nearest_n::<SquaredEuclidean<f32>>(k).execute();
        out[i] = pca(nn.iter().map(|r| coords[r.item as usize]), q);
    }
    Ok(out)
}

/// PCA normal of a neighbourhood, oriented toward the origin as seen from `at`.
pub fn pca(neigh: impl Iterator<Item = [f32; 3]>, at: [f32; 3]) -> Option<PcaNormal> {
    let pts: Vec<Vector3<f64>> = neigh.map(|p| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)).collect();
    if pts.len() < 3 {
        return None;
    }
    let mean = pts.iter().sum::<Vector3<f64>>() / pts.len() as f64;
    let mut cov = Matrix3::zeros();
    for p in &pts {
        let d = p - mean;
        cov += d * d.transpose();
    }
    cov /= pts.len() as f64;
    let eig = SymmetricEigen::new(cov);
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let mut n: Vector3<f64> = eig.eigenvectors.column(idx[0]).into();
    let norm = n.norm();
    if norm.is_nan() || norm <= 0.5 {
        return None;
    }
    n /= norm;
    let a = Vector3::new(at[0] as f64, at[1] as f64, at[2] as f64);
    if n.dot(&a) > 0.0 {
        n = -n;
    }
    Some(PcaNormal { normal: [n.x, n.y, n.z], eigenvalues: idx.map(|i| eig.eigenvalues[i]) })
}
