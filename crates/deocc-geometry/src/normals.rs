//! Surface normals by principal component analysis of the k nearest neighbours.

use nalgebra::{Matrix3, Point3, Vector3};
use rayon::prelude::*;

use crate::error::Result;
use crate::knn::KdIndex;

/// Unit normals of every point from the PCA of its `k` nearest neighbours (the point included), as
/// Open3D's `estimate_normals(KDTreeSearchParamKNN(k))` does. The sign is arbitrary; use
/// [`orient_towards`] to make them face a viewpoint. Points whose neighbourhood is degenerate get
/// the zero vector.
pub fn estimate_normals(points: &[Point3<f32>], k: usize) -> Result<Vec<Vector3<f32>>> {
    let index = KdIndex::build(points)?;
    Ok(estimate_normals_with_index(points, &index, k))
}

/// [`estimate_normals`] with a k-d tree the caller already has over `points`.
pub fn estimate_normals_with_index(
    points: &[Point3<f32>],
    index: &KdIndex,
    k: usize,
) -> Vec<Vector3<f32>> {
    points
        .par_iter()
        .with_min_len(256)
        .map(|p| {
            let nbs = index.k_nearest(p, k);
            if nbs.len() < 3 {
                return Vector3::zeros();
            }
            // Centre on the query point before accumulating: keeps f64 sums well conditioned far
            // from the origin.
            let origin = p.coords.cast::<f64>();
            let mut sum = Vector3::<f64>::zeros();
            let mut outer = Matrix3::<f64>::zeros();
            for nb in &nbs {
                let q = points[nb.index as usize].coords.cast::<f64>() - origin;
                sum += q;
                outer += q * q.transpose();
            }
            let n = nbs.len() as f64;
            let mean = sum / n;
            let cov = outer / n - mean * mean.transpose();
            smallest_eigenvector(&cov).cast::<f32>()
        })
        .collect()
}

/// Flips each normal so that it points towards `viewpoint`.
pub fn orient_towards(
    points: &[Point3<f32>],
    normals: &mut [Vector3<f32>],
    viewpoint: &Point3<f32>,
) {
    for (p, n) in points.iter().zip(normals.iter_mut()) {
        if n.dot(&(viewpoint - p)) < 0.0 {
            *n = -*n;
        }
    }
}

/// Unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix, in closed form
/// (trigonometric eigenvalues, then the largest cross product of two rows of A - lambda I); about
/// 10x faster than an iterative solver and accurate to ~1e-7 for covariance matrices.
pub fn smallest_eigenvector(a: &Matrix3<f64>) -> Vector3<f64> {
    let max = a.abs().max();
    if max <= 0.0 || !max.is_finite() {
        return Vector3::zeros();
    }
    let a = a / max;
    let p1 = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
    let q = a.trace() / 3.0;
    let lambda_min = if p1 <= 1e-20 {
        a[(0, 0)].min(a[(1, 1)]).min(a[(2, 2)])
    } else {
        let p2 =
            (a[(0, 0)] - q).powi(2) + (a[(1, 1)] - q).powi(2) + (a[(2, 2)] - q).powi(2) + 2.0 * p1;
        let p = (p2 / 6.0).sqrt();
        let b = (a - Matrix3::identity() * q) / p;
        let r = (b.determinant() / 2.0).clamp(-1.0, 1.0);
        let phi = r.acos() / 3.0;
        // Eigenvalues are q + 2p cos(phi + 2k pi / 3); k = 1 gives the smallest.
        q + 2.0 * p * (phi + 2.0 * std::f64::consts::PI / 3.0).cos()
    };
    let m = a - Matrix3::identity() * lambda_min;
    let (r0, r1, r2) = (
        m.row(0).transpose(),
        m.row(1).transpose(),
        m.row(2).transpose(),
    );
    let candidates = [r0.cross(&r1), r0.cross(&r2), r1.cross(&r2)];
    let best = candidates
        .iter()
        .max_by(|x, y| x.norm_squared().total_cmp(&y.norm_squared()))
        .copied()
        .unwrap_or_default();
    let norm = best.norm();
    if norm > 1e-12 {
        best / norm
    } else {
        // Two or three equal smallest eigenvalues (a line or a blob): fall back to the general
        // solver, which handles repeated eigenvalues.
        let eig = a.symmetric_eigen();
        let i = eig.eigenvalues.imin();
        eig.eigenvectors.column(i).into_owned()
    }
}
