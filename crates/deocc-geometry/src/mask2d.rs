//! Binary masks on a square grid (row-major, `r x r`): IoU, the convex hull and an ellipse fit,
//! used by the amodal baselines and by the geometric priors the completion model is conditioned on.

use nalgebra::{Matrix3, Vector3};

/// Intersection over union; 1 when both are empty.
pub fn iou(a: &[bool], b: &[bool]) -> f64 {
    let (mut inter, mut union) = (0usize, 0usize);
    for (&x, &y) in a.iter().zip(b) {
        inter += (x && y) as usize;
        union += (x || y) as usize;
    }
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}

/// The convex hull of a mask's pixels (corners of every pixel, so a single pixel stays itself),
/// rasterised back on the same `r x r` grid by pixel centres.
pub fn convex_hull_mask(mask: &[bool], r: usize) -> Vec<bool> {
    let mut pts: Vec<(i64, i64)> = Vec::new();
    for (i, &m) in mask.iter().enumerate() {
        if m {
            let (u, v) = ((i % r) as i64, (i / r) as i64);
            pts.extend([(u, v), (u + 1, v), (u, v + 1), (u + 1, v + 1)]);
        }
    }
    let hull = monotone_chain(pts);
    if hull.len() < 3 {
        return mask.to_vec();
    }
    (0..r * r)
        .map(|i| {
            let (x, y) = ((i % r) as f64 + 0.5, (i / r) as f64 + 0.5);
            // Counter-clockwise hull: inside when left of (or on) every edge.
            hull.iter().zip(hull.iter().cycle().skip(1)).all(|(a, b)| {
                let (ax, ay, bx, by) = (a.0 as f64, a.1 as f64, b.0 as f64, b.1 as f64);
                (bx - ax) * (y - ay) - (by - ay) * (x - ax) >= 0.0
            })
        })
        .collect()
}

/// A conic `a x^2 + b xy + c y^2 + d x + e y + f = 0`, coefficients `[a, b, c, d, e, f]`.
pub type Conic = [f64; 6];

/// The value of a conic's polynomial at `(x, y)`: zero on the curve, one sign inside an ellipse
/// and the other outside.
pub fn conic_value(q: &Conic, x: f64, y: f64) -> f64 {
    q[0] * x * x + q[1] * x * y + q[2] * y * y + q[3] * x + q[4] * y + q[5]
}

/// Least-squares ellipse through 2-D points: Fitzgibbon's direct fit (the algebraic distance
/// minimised under `4ac - b^2 = 1`, which admits only ellipses) in Halir and Flusser's
/// numerically stable form, reduced to a 3x3 eigenproblem. `None` with fewer than 5 points or a
/// degenerate configuration (collinear points). Scale the points to about unit size first.
pub fn fit_ellipse(points: &[(f64, f64)]) -> Option<Conic> {
    if points.len() < 5 {
        return None;
    }
    // Scatter matrices of the quadratic part [x^2, xy, y^2] and the linear part [x, y, 1].
    let (mut s1, mut s2, mut s3) = (Matrix3::zeros(), Matrix3::zeros(), Matrix3::zeros());
    for &(x, y) in points {
        let d1 = Vector3::new(x * x, x * y, y * y);
        let d2 = Vector3::new(x, y, 1.0);
        s1 += d1 * d1.transpose();
        s2 += d1 * d2.transpose();
        s3 += d2 * d2.transpose();
    }
    // The linear part is solved for in closed form: a2 = t a1.
    let t = -s3.try_inverse()? * s2.transpose();
    let m = s1 + s2 * t;
    // Premultiply by the inverse of the constraint matrix [[0, 0, 2], [0, -1, 0], [2, 0, 0]].
    let m = Matrix3::from_rows(&[
        (m.row(2) / 2.0).into_owned(),
        (-m.row(1)).into_owned(),
        (m.row(0) / 2.0).into_owned(),
    ]);
    let scale = m.abs().max().max(f64::MIN_POSITIVE);
    m.complex_eigenvalues()
        .iter()
        .filter(|l| l.im.abs() <= 1e-9 * scale)
        .filter_map(|l| null_vector(&(m - Matrix3::identity() * l.re)))
        .find(|a1| 4.0 * a1[0] * a1[2] - a1[1] * a1[1] > 0.0)
        .map(|a1| {
            let a2 = t * a1;
            [a1[0], a1[1], a1[2], a2[0], a2[1], a2[2]]
        })
}

/// A unit vector spanning the null space of a rank-2 3x3 matrix: the longest cross product of
/// two of its rows.
fn null_vector(a: &Matrix3<f64>) -> Option<Vector3<f64>> {
    let rows = [
        a.row(0).transpose(),
        a.row(1).transpose(),
        a.row(2).transpose(),
    ];
    [(0, 1), (0, 2), (1, 2)]
        .iter()
        .map(|&(i, j)| rows[i].cross(&rows[j]))
        .max_by(|p, q| p.norm_squared().total_cmp(&q.norm_squared()))
        .filter(|v| v.norm_squared() > 0.0)
        .map(|v| v.normalize())
}

/// Andrew's monotone chain; counter-clockwise, no repeated end point.
fn monotone_chain(mut p: Vec<(i64, i64)>) -> Vec<(i64, i64)> {
    p.sort_unstable();
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let cross = |o: (i64, i64), a: (i64, i64), b: (i64, i64)| {
        (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0)
    };
    let mut lower: Vec<(i64, i64)> = Vec::new();
    for &q in &p {
        while lower.len() >= 2 && cross(lower[lower.len() - 2], lower[lower.len() - 1], q) <= 0 {
            lower.pop();
        }
        lower.push(q);
    }
    let mut upper: Vec<(i64, i64)> = Vec::new();
    for &q in p.iter().rev() {
        while upper.len() >= 2 && cross(upper[upper.len() - 2], upper[upper.len() - 1], q) <= 0 {
            upper.pop();
        }
        upper.push(q);
    }
    lower.pop();
    upper.pop();
    lower.extend(upper);
    lower
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn iou_of_known_masks() {
        assert_eq!(
            iou(&[true, true, false, false], &[true, false, true, false]),
            1.0 / 3.0
        );
        assert_eq!(iou(&[false; 4], &[false; 4]), 1.0);
    }

    #[test]
    fn ellipse_fit_recovers_a_known_ellipse_from_an_arc() {
        // An axis-aligned ellipse centred at (0.5, 0.4), semi-axes 0.3 and 0.15, rotated by 0.6
        // rad; only half of it is sampled, as the unoccluded part of a contour would be.
        let (cx, cy, ra, rb, th) = (0.5f64, 0.4f64, 0.3f64, 0.15f64, 0.6f64);
        let at = |s: f64| {
            let (x, y) = (ra * s.cos(), rb * s.sin());
            (
                cx + x * th.cos() - y * th.sin(),
                cy + x * th.sin() + y * th.cos(),
            )
        };
        let arc: Vec<(f64, f64)> = (0..40).map(|k| at(k as f64 * 0.08)).collect();
        let q = fit_ellipse(&arc).expect("an arc of an ellipse fits");
        let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        // Points of the other half are on the fitted curve; the centre is inside, far points out.
        for k in 0..20 {
            let (x, y) = at(3.5 + k as f64 * 0.1);
            assert!(
                conic_value(&q, x, y).abs() / norm < 1e-9,
                "off the curve at {k}"
            );
        }
        let inside = conic_value(&q, cx, cy).signum();
        assert_eq!(conic_value(&q, cx + 0.5, cy).signum(), -inside);
        assert_eq!(conic_value(&q, cx, cy - 0.3).signum(), -inside);
        assert!(4.0 * q[0] * q[2] - q[1] * q[1] > 0.0, "an ellipse");
    }

    #[test]
    fn ellipse_fit_refuses_too_few_or_collinear_points() {
        assert!(fit_ellipse(&[(0.0, 0.0), (1.0, 1.0), (2.0, 0.0), (1.0, -1.0)]).is_none());
        let line: Vec<(f64, f64)> = (0..10).map(|k| (k as f64 * 0.1, k as f64 * 0.05)).collect();
        assert!(fit_ellipse(&line).is_none());
    }

    #[test]
    fn hull_fills_an_l_shape_to_its_triangle_closure() {
        let r = 8;
        // An L: the left column and the bottom row.
        let mask: Vec<bool> = (0..r * r).map(|i| i % r == 0 || i / r == r - 1).collect();
        let hull = convex_hull_mask(&mask, r);
        for i in 0..r * r {
            if mask[i] {
                assert!(hull[i], "hull must contain the mask");
            }
        }
        let (u, v) = (i64::from(1u8), 6i64);
        assert!(
            hull[(v as usize) * r + u as usize],
            "inside the L's triangle"
        );
        assert!(!hull[r - 1], "the far corner is outside the triangle");
        let area = hull.iter().filter(|&&b| b).count();
        assert!(area > mask.iter().filter(|&&b| b).count() && area < r * r);
    }
}
