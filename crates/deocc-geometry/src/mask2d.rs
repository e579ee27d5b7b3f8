//! Binary masks on a square grid (row-major, `r x r`): IoU and the convex hull, used by the
//! amodal baselines and by the geometric prior the completion model is conditioned on.

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
