//! Instance segmentation behind a trait. Two implementations: masks given with the input, and a
//! default RGB-D segmenter that needs no weights.
//!
//! The default segmenter grows regions over the pixel grid by local convexity (the criterion of
//! LCCP, Stein et al. 2014, applied to neighbouring pixels): two neighbouring pixels belong to the
//! same segment when their depths are continuous and the surface between them is flat or convex
//! (normals turning away from each other, as on the edge of a box). Depth jumps separate objects
//! from what is behind them; concave creases separate an object from the table it stands on, a
//! table from the floor, the floor from the walls. Support planes therefore come out as segments of
//! their own. Known weakness, measured by `deocc eval perception`: parts joined by concave creases
//! (chair legs under a seat) come out as separate segments.

use deocc_geometry::camera::Camera;
use deocc_geometry::DepthMap;
use deocc_io::images::InstanceMap;
use nalgebra::{Point3, Vector3};

/// Something that turns an RGB-D frame into an instance map (ids local to the frame).
pub trait Segmenter: Send + Sync {
    fn segment(&self, depth: &DepthMap, camera: &Camera) -> InstanceMap;
}

/// The default RGB-D segmenter (see the module docs). Concave bends gentler than `smooth_deg`
/// count as curvature (the inside of a bowl), not as a crease.
#[derive(Debug, Clone)]
pub struct ConvexitySegmenter {
    /// Depth continuity: neighbours closer than `abs + rel * z` in depth are continuous.
    pub depth_abs_m: f32,
    pub depth_rel: f32,
    /// Normals are estimated from neighbours this many pixels away (noise against detail).
    pub normal_step: usize,
    /// Tolerance of the concavity test, `(n_i - n_j) . (p_i - p_j) >= -tol * |p_i - p_j|`: absorbs
    /// normal noise on flat surfaces; a crease smoothed over a few pixels still fails it.
    pub concave_tolerance: f32,
    /// Concave bends gentler than this (degrees, between the normals `crease_reach` pixels either
    /// side) are curvature, not a crease between two objects.
    pub smooth_deg: f32,
    /// Creases are judged from normals this many pixels away on either side.
    pub crease_reach: usize,
    /// Segments smaller than this (pixels) are dropped (id 0).
    pub min_segment_px: usize,
}

impl Default for ConvexitySegmenter {
    fn default() -> Self {
        Self {
            depth_abs_m: 0.01,
            depth_rel: 0.02,
            normal_step: 2,
            concave_tolerance: 0.15,
            smooth_deg: 12.0,
            crease_reach: 3,
            min_segment_px: 80,
        }
    }
}

fn find(parent: &mut [u32], i: u32) -> u32 {
    let mut r = i;
    while parent[r as usize] != r {
        r = parent[r as usize];
    }
    let mut i = i;
    while parent[i as usize] != r {
        let next = parent[i as usize];
        parent[i as usize] = r;
        i = next;
    }
    r
}

impl ConvexitySegmenter {
    /// Camera-frame points and unit normals (zero where unknown).
    fn geometry(&self, depth: &DepthMap, camera: &Camera) -> (Vec<Point3<f32>>, Vec<Vector3<f32>>) {
        let (w, h) = (depth.width() as usize, depth.height() as usize);
        let k = &camera.intrinsics;
        let d = depth.data();
        let pts: Vec<Point3<f32>> = (0..w * h)
            .map(|i| k.unproject((i % w) as f32 + 0.5, (i / w) as f32 + 0.5, d[i]))
            .collect();
        let s = self.normal_step;
        let mut normals = vec![Vector3::zeros(); w * h];
        for v in s..h.saturating_sub(s) {
            for u in s..w.saturating_sub(s) {
                let i = v * w + u;
                let (l, r, t, b) = (i - s, i + s, i - s * w, i + s * w);
                if [i, l, r, t, b].iter().any(|&j| d[j] <= 0.0) {
                    continue;
                }
                let n = (pts[r] - pts[l]).cross(&(pts[b] - pts[t]));
                if let Some(n) = n.try_normalize(1e-12) {
                    // Face the camera.
                    normals[i] = if n.dot(&pts[i].coords) > 0.0 { -n } else { n };
                }
            }
        }
        (pts, normals)
    }
}

impl Segmenter for ConvexitySegmenter {
    fn segment(&self, depth: &DepthMap, camera: &Camera) -> InstanceMap {
        let (w, h) = (depth.width() as usize, depth.height() as usize);
        let d = depth.data();
        let (pts, normals) = self.geometry(depth, camera);
        let mut parent: Vec<u32> = (0..(w * h) as u32).collect();
        let k = self.crease_reach;
        let cos_smooth = self.smooth_deg.to_radians().cos();
        // `step`: 1 for a horizontal neighbour pair, w for a vertical one.
        let connect = |i: usize, j: usize, step: usize| -> bool {
            let (zi, zj) = (d[i], d[j]);
            if zi <= 0.0 || zj <= 0.0 {
                return false;
            }
            if (zi - zj).abs() > self.depth_abs_m + self.depth_rel * zi.min(zj) {
                return false;
            }
            // Judge the crease between (i, j) from a little way off on either side: normals
            // estimated right at a crease blend both surfaces and hide it.
            let (a, b) = match (i.checked_sub(k * step), j + k * step) {
                (Some(a), b) if b < w * h && (step != 1 || (a / w == i / w && b / w == j / w)) => {
                    (a, b)
                }
                _ => (i, j),
            };
            let (na, nb) = (normals[a], normals[b]);
            if na == Vector3::zeros() || nb == Vector3::zeros() || d[a] <= 0.0 || d[b] <= 0.0 {
                // No normal (image border, next to missing depth): do not connect, or creases that
                // reach the border would leak through it.
                return false;
            }
            // Gently curved (the inside of a bowl), or flat or convex (normals not turning towards
            // each other across the crease): the same surface.
            if na.dot(&nb) >= cos_smooth {
                return true;
            }
            let dp = pts[a] - pts[b];
            (na - nb).dot(&dp) >= -self.concave_tolerance * dp.norm()
        };
        for v in 0..h {
            for u in 0..w {
                let i = v * w + u;
                for (j, step) in [
                    if u + 1 < w { Some((i + 1, 1)) } else { None },
                    if v + 1 < h { Some((i + w, w)) } else { None },
                ]
                .into_iter()
                .flatten()
                {
                    if connect(i, j, step) {
                        let (a, b) = (find(&mut parent, i as u32), find(&mut parent, j as u32));
                        if a != b {
                            parent[a as usize] = b;
                        }
                    }
                }
            }
        }
        let mut size = vec![0usize; w * h];
        let roots: Vec<u32> = (0..w * h).map(|i| find(&mut parent, i as u32)).collect();
        for (i, &r) in roots.iter().enumerate() {
            if d[i] > 0.0 {
                size[r as usize] += 1;
            }
        }
        let mut label = std::collections::HashMap::new();
        let ids = roots
            .iter()
            .enumerate()
            .map(|(i, &r)| {
                if d[i] <= 0.0 || size[r as usize] < self.min_segment_px {
                    return 0;
                }
                let next = label.len() + 1;
                (*label.entry(r).or_insert(next)).min(u16::MAX as usize) as u16
            })
            .collect();
        InstanceMap {
            width: w as u32,
            height: h as u32,
            ids,
        }
    }
}

/// Matches every ground-truth instance to its best-overlapping segment; returns the mean IoU over
/// ground-truth instances with at least `min_px` visible pixels.
pub fn matched_miou(
    predicted: &InstanceMap,
    truth: &InstanceMap,
    min_px: usize,
    skip: &[u16],
) -> Option<(f64, usize)> {
    use std::collections::HashMap;
    let mut inter: HashMap<(u16, u16), usize> = HashMap::new();
    let mut area_t: HashMap<u16, usize> = HashMap::new();
    let mut area_p: HashMap<u16, usize> = HashMap::new();
    for (&t, &p) in truth.ids.iter().zip(&predicted.ids) {
        if t != 0 {
            *area_t.entry(t).or_default() += 1;
        }
        if p != 0 {
            *area_p.entry(p).or_default() += 1;
        }
        if t != 0 && p != 0 {
            *inter.entry((t, p)).or_default() += 1;
        }
    }
    let ious: Vec<f64> = area_t
        .iter()
        .filter(|(t, &a)| a >= min_px && !skip.contains(t))
        .map(|(&t, &at)| {
            inter
                .iter()
                .filter(|((tt, _), _)| *tt == t)
                .map(|((_, p), &i)| i as f64 / (at + area_p[p] - i) as f64)
                .fold(0.0, f64::max)
        })
        .collect();
    (!ious.is_empty()).then(|| (ious.iter().sum::<f64>() / ious.len() as f64, ious.len()))
}
