//! Stage: depth clean-up, the depth front end. Runs on every frame before anything uses its
//! depth (registration, segmentation, the run), in units of the frame's own noise
//! ([`DepthNoise::estimate`], `sigma(z) = a + b z^2`):
//!
//! 1. **Outliers and flying pixels** go: a pixel that continues none of its four sides' surfaces
//!    (each side's two pixels extrapolated to it, within `agree_sigmas * sigma * sqrt(6)` plus
//!    0.6% of the depth for curvature) lies
//!    on no surface: a time-of-flight pixel mixing the two sides of an edge, a speckle. A pixel
//!    on a steep but smooth slope continues its sides and stays.
//! 2. **Specks** go: pieces of connected depth (neighbours within `connect_sigmas * sigma`)
//!    smaller than `min_region_px`.
//! 3. **Smoothing without crossing edges**: each pixel becomes the value at its centre of the
//!    least-squares plane through its `(2 radius + 1)^2` window's pixels within
//!    `smooth_sigmas * sigma` of it (the mean where they span no plane). Not the mean: where the
//!    range test cuts a window on one side (a can's flank near its silhouette) the mean slides
//!    the pixel along the slope, and a can of 3.4 cm radius was fitted 4-15 mm too wide on
//!    pickup-v1 under the structured-light model; the plane leaves 0.5-1.5 mm on three of the
//!    four scenes looked at (`cargo run -p deocc-eval --example target_points`). 4 sigma: chosen on
//!    bench-v1 tuning views under the structured-light model, 2.5 / 4 / 6 / 10 tried). Disparity steps and
//!    axial noise average out on a surface; a depth edge (many sigma) is not crossed.
//!
//! On noise-free depth (the estimate at its floor, 0.5 mm) the stage changes almost nothing:
//! smoothing within 2 mm of a pixel keeps every edge the renderer drew.

use deocc_geometry::noise::DepthNoise;
use deocc_geometry::DepthMap;
use serde::{Deserialize, Serialize};

use crate::PipelineError;

/// The stage's settings.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct DepthCleanOptions {
    /// Run the stage at all.
    pub enabled: bool,
    pub agree_sigmas: f32,
    pub connect_sigmas: f32,
    pub min_region_px: usize,
    pub smooth_sigmas: f32,
    pub radius: usize,
}

impl Default for DepthCleanOptions {
    fn default() -> Self {
        Self {
            enabled: true,
            agree_sigmas: 3.0,
            connect_sigmas: 4.0,
            min_region_px: 12,
            smooth_sigmas: 4.0,
            radius: 3,
        }
    }
}

impl DepthCleanOptions {
    pub fn validate(&self) -> Result<(), PipelineError> {
        let bad = |field: &'static str, msg: String| PipelineError::Option { field, msg };
        for (field, v) in [
            ("depth_clean.agree_sigmas", self.agree_sigmas),
            ("depth_clean.connect_sigmas", self.connect_sigmas),
            ("depth_clean.smooth_sigmas", self.smooth_sigmas),
        ] {
            if !(0.5..=50.0).contains(&v) {
                return Err(bad(field, format!("{v} is outside [0.5, 50]")));
            }
        }
        if self.min_region_px > 10_000 {
            return Err(bad(
                "depth_clean.min_region_px",
                format!("{} is over 10000", self.min_region_px),
            ));
        }
        if self.radius > 8 {
            return Err(bad(
                "depth_clean.radius",
                format!("{} is over 8 pixels", self.radius),
            ));
        }
        Ok(())
    }
}

/// What the stage did to one frame.
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct DepthCleanRecord {
    /// The frame's noise before and after (`sigma(z) = a + b z^2`).
    pub noise: DepthNoise,
    pub noise_after: DepthNoise,
    pub sigma_at_2m_mm: f32,
    pub sigma_at_2m_after_mm: f32,
    pub outliers_removed: usize,
    pub specks_removed: usize,
    pub pixels_smoothed: usize,
}

/// Cleans `depth` in place (see the module docs) and says what it did.
pub fn clean_depth(depth: &mut DepthMap, opts: &DepthCleanOptions) -> DepthCleanRecord {
    let noise = DepthNoise::estimate(depth);
    let mut rec = DepthCleanRecord {
        noise,
        sigma_at_2m_mm: noise.sigma(2.0) * 1000.0,
        ..Default::default()
    };
    if !opts.enabled {
        rec.noise_after = noise;
        rec.sigma_at_2m_after_mm = rec.sigma_at_2m_mm;
        return rec;
    }
    let (w, h) = (depth.width() as usize, depth.height() as usize);
    let mut d = depth.data().to_vec();
    rec.outliers_removed = remove_outliers(&mut d, w, h, &noise, opts.agree_sigmas);
    rec.specks_removed = remove_specks(&mut d, w, h, &noise, opts);
    rec.pixels_smoothed = smooth(&mut d, w, h, &noise, opts);
    // Values stay finite and non-negative: every step writes depths it read, zero, or means of
    // them.
    *depth = DepthMap::new(depth.width(), depth.height(), d).unwrap_or_else(|_| depth.clone());
    rec.noise_after = DepthNoise::estimate(depth);
    rec.sigma_at_2m_after_mm = rec.noise_after.sigma(2.0) * 1000.0;
    rec
}

/// The extrapolation tolerance's part for curved surfaces, relative to depth (a cylinder seen
/// near its silhouette bends by millimetres over two pixels).
const CURVATURE_REL: f32 = 0.006;

/// Step 1, twice: a run of two mixed pixels along an edge can vouch for each other once.
fn remove_outliers(d: &mut [f32], w: usize, h: usize, noise: &DepthNoise, k: f32) -> usize {
    let first = outlier_pass(d, w, h, noise, k);
    first + outlier_pass(d, w, h, noise, k)
}

/// Pixels that continue none of their sides' surfaces.
fn outlier_pass(d: &mut [f32], w: usize, h: usize, noise: &DepthNoise, k: f32) -> usize {
    let src = d.to_vec();
    let at = |u: i64, v: i64| -> f32 {
        if u < 0 || v < 0 || u >= w as i64 || v >= h as i64 {
            0.0
        } else {
            src[v as usize * w + u as usize]
        }
    };
    let mut removed = 0;
    for v in 0..h as i64 {
        for u in 0..w as i64 {
            let z = at(u, v);
            if z <= 0.0 {
                continue;
            }
            // The noise of the extrapolation, and the curvature a smooth surface's silhouette
            // has over two pixels.
            let tol = k * noise.sigma(z) * 6f32.sqrt() + CURVATURE_REL * z;
            let (mut sides, mut agree) = (0, false);
            for (du, dv) in [(-1, 0), (1, 0), (0, -1), (0, 1)] {
                let (z1, z2) = (at(u + du, v + dv), at(u + 2 * du, v + 2 * dv));
                if z1 <= 0.0 || z2 <= 0.0 {
                    continue;
                }
                sides += 1;
                if (2.0 * z1 - z2 - z).abs() <= tol {
                    agree = true;
                    break;
                }
            }
            // Judged only with two sides to judge by (a pixel at a hole's rim keeps its place).
            if sides >= 2 && !agree {
                d[(v as usize) * w + u as usize] = 0.0;
                removed += 1;
            }
        }
    }
    removed
}

/// The 4-neighbours of pixel `i` in a `w x h` grid, row-major.
pub(crate) fn neighbours4(i: usize, w: usize, h: usize) -> impl Iterator<Item = usize> {
    let (u, v) = (i % w, i / w);
    [
        (u > 0).then(|| i - 1),
        (u + 1 < w).then(|| i + 1),
        (v > 0).then(|| i - w),
        (v + 1 < h).then(|| i + w),
    ]
    .into_iter()
    .flatten()
}

/// Step 2: connected pieces smaller than `min_region_px`.
fn remove_specks(
    d: &mut [f32],
    w: usize,
    h: usize,
    noise: &DepthNoise,
    opts: &DepthCleanOptions,
) -> usize {
    if opts.min_region_px == 0 {
        return 0;
    }
    let n = w * h;
    let mut label = vec![u32::MAX; n];
    let mut removed = 0;
    let mut stack = Vec::new();
    let mut members = Vec::new();
    for start in 0..n {
        if d[start] <= 0.0 || label[start] != u32::MAX {
            continue;
        }
        label[start] = start as u32;
        stack.push(start);
        members.clear();
        while let Some(i) = stack.pop() {
            members.push(i);
            let z = d[i];
            let tol = opts.connect_sigmas * noise.sigma(z) + 0.02 * z;
            for j in neighbours4(i, w, h) {
                if d[j] > 0.0 && label[j] == u32::MAX && (d[j] - z).abs() <= tol {
                    label[j] = start as u32;
                    stack.push(j);
                }
            }
        }
        if members.len() < opts.min_region_px {
            for &i in &members {
                d[i] = 0.0;
            }
            removed += members.len();
        }
    }
    removed
}

/// Step 3: the mean of each window's pixels near the centre's depth (integral images would not
/// know the range test; the window is small).
fn smooth(
    d: &mut [f32],
    w: usize,
    h: usize,
    noise: &DepthNoise,
    opts: &DepthCleanOptions,
) -> usize {
    let r = opts.radius as i64;
    if r == 0 {
        return 0;
    }
    let src = d.to_vec();
    let mut changed = 0;
    for v in 0..h as i64 {
        for u in 0..w as i64 {
            let i = v as usize * w + u as usize;
            let z = src[i];
            if z <= 0.0 {
                continue;
            }
            let tol = opts.smooth_sigmas * noise.sigma(z);
            // Sums for the least-squares plane z = a + b du + c dv over the window's pixels
            // near z, in offsets from the centre.
            let mut s = [0f64; 9]; // n, su, sv, suu, suv, svv, sz, suz, svz
            for y in (v - r).max(0)..=(v + r).min(h as i64 - 1) {
                let row = y as usize * w;
                let dv = (y - v) as f64;
                for x in (u - r).max(0)..=(u + r).min(w as i64 - 1) {
                    let zz = src[row + x as usize];
                    if zz > 0.0 && (zz - z).abs() <= tol {
                        let (du, zz) = ((x - u) as f64, f64::from(zz));
                        s[0] += 1.0;
                        s[1] += du;
                        s[2] += dv;
                        s[3] += du * du;
                        s[4] += du * dv;
                        s[5] += dv * dv;
                        s[6] += zz;
                        s[7] += du * zz;
                        s[8] += dv * zz;
                    }
                }
            }
            let value = plane_at_centre(&s).unwrap_or((s[6] / s[0]) as f32);
            if value != z && value > 0.0 && value.is_finite() {
                d[i] = value;
                changed += 1;
            }
        }
    }
    changed
}

/// The value at the window's centre of the least-squares plane through a window's pixels, from
/// the sums `[n, su, sv, suu, suv, svv, sz, suz, svz]` (offsets from the centre). A plane, not
/// the mean: on a slope or a curved surface whose window the range test cuts on one side, the
/// mean moves the centre along the slope (a can's silhouette pushed back, its radius fitted
/// centimetres too large); the plane does not. `None` when the pixels do not span a plane
/// (under 6, or in a line).
fn plane_at_centre(s: &[f64; 9]) -> Option<f32> {
    if s[0] < 6.0 {
        return None;
    }
    let m = nalgebra::Matrix3::new(s[0], s[1], s[2], s[1], s[3], s[4], s[2], s[4], s[5]);
    let b = nalgebra::Vector3::new(s[6], s[7], s[8]);
    // A window in a line (one row of depth) has a singular system: fall back to the mean.
    if m.determinant().abs() < 1e-6 * s[0].powi(3) {
        return None;
    }
    let x = m.lu().solve(&b)?;
    Some(x[0] as f32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn gauss(rng: &mut impl Rng) -> f32 {
        let (a, b): (f32, f32) = (rng.random_range(1e-7..1.0), rng.random_range(0.0..1.0));
        (-2.0 * a.ln()).sqrt() * (std::f32::consts::TAU * b).cos()
    }

    /// A box face at 1.5 m (left) before a wall at 2.5 m (right), with Kinect-like noise,
    /// 1 cm disparity-like steps on the wall, a column of flying pixels at the edge and a few
    /// specks.
    fn scene(seed: u64) -> (DepthMap, Vec<f32>) {
        let (w, h) = (200usize, 150usize);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut truth = vec![0f32; w * h];
        let mut d = vec![0f32; w * h];
        for v in 0..h {
            for u in 0..w {
                let z = if u < 100 { 1.5 } else { 2.5 + 0.002 * v as f32 };
                truth[v * w + u] = z;
                let noisy = z + gauss(&mut rng) * (0.0012 + 0.0019 * (z - 0.4) * (z - 0.4));
                d[v * w + u] = if u >= 100 {
                    (noisy / 0.01).round() * 0.01
                } else {
                    noisy
                };
            }
            d[v * w + 100] = 2.0 + 0.1 * gauss(&mut rng).clamp(-3.0, 3.0);
        }
        for k in 0..5 {
            d[(20 + 25 * k) * w + 150] = 0.6;
        }
        (DepthMap::new(w as u32, h as u32, d).unwrap(), truth)
    }

    #[test]
    fn flying_pixels_and_specks_go_surfaces_smooth_and_the_edge_stays() {
        let (mut depth, truth) = scene(1);
        let before = depth.clone();
        let rec = clean_depth(&mut depth, &DepthCleanOptions::default());
        let (w, h) = (200usize, 150usize);
        let d = depth.data();
        // The flying column and the specks are gone.
        let flying_left = (2..h - 2)
            .filter(|&v| d[v * w + 100] > 0.0 && (d[v * w + 100] - truth[v * w + 100]).abs() > 0.05)
            .count();
        assert!(flying_left < 5, "{flying_left} flying pixels left");
        for k in 0..5 {
            assert_eq!(d[(20 + 25 * k) * w + 150], 0.0);
        }
        assert!(rec.outliers_removed + rec.specks_removed >= 100, "{rec:?}");
        // Surfaces are closer to the truth: the error inside each side falls by half.
        let err = |m: &[f32], cols: std::ops::Range<usize>| {
            let mut s = 0f64;
            let mut n = 0;
            for v in 5..h - 5 {
                for u in cols.clone() {
                    let i = v * w + u;
                    if m[i] > 0.0 {
                        s += f64::from((m[i] - truth[i]).powi(2));
                        n += 1;
                    }
                }
            }
            (s / n as f64).sqrt()
        };
        for cols in [5..95, 106..195] {
            let (a, b) = (err(before.data(), cols.clone()), err(d, cols.clone()));
            assert!(b < 0.5 * a, "{cols:?}: {a} -> {b}");
        }
        // No pixel of either side takes the other side's depth.
        for v in 0..h {
            for u in (0..98).chain(103..w) {
                let i = v * w + u;
                if d[i] > 0.0 {
                    assert!(
                        (d[i] - truth[i]).abs() < 0.1,
                        "({u}, {v}): {} vs {}",
                        d[i],
                        truth[i]
                    );
                }
            }
        }
        assert!(rec.sigma_at_2m_after_mm < rec.sigma_at_2m_mm);
    }

    /// A gentle slope (1 mm a pixel) ending at a depth edge: next to the edge the range test
    /// cuts the window on one side, and a mean would slide the pixel 1-2 mm along the slope; the
    /// plane keeps it where it is.
    #[test]
    fn a_slope_beside_an_edge_stays_on_the_slope() {
        let (w, h) = (60usize, 40usize);
        let d: Vec<f32> = (0..w * h)
            .map(|i| {
                let u = i % w;
                if u < 30 {
                    1.0 + 0.001 * u as f32
                } else {
                    2.0
                }
            })
            .collect();
        let mut depth = DepthMap::new(w as u32, h as u32, d.clone()).unwrap();
        clean_depth(&mut depth, &DepthCleanOptions::default());
        let worst = (0..w * h)
            .filter(|i| i % w < 30 && depth.data()[*i] > 0.0)
            .map(|i| (depth.data()[i] - d[i]).abs())
            .fold(0.0, f32::max);
        assert!(worst < 5e-5, "{worst} m off the slope");
        // The mean of the same window is off by more than a millimetre at the edge: the case
        // the plane exists for.
        let row: Vec<f32> = (23..30).map(|u| 1.0 + 0.001 * u as f32).collect();
        let mean = row.iter().sum::<f32>() / row.len() as f32;
        assert!((mean - 1.029).abs() > 0.001);
    }

    #[test]
    fn exact_depth_and_steep_slopes_are_left_alone() {
        // A floor seen at a grazing angle: depth rises 3 cm a row, exactly (millimetre PNG).
        let (w, h) = (120usize, 90usize);
        let d: Vec<f32> = (0..w * h)
            .map(|i| ((1.0 + 0.03 * (i / w) as f32) * 1000.0).round() / 1000.0)
            .collect();
        let mut depth = DepthMap::new(w as u32, h as u32, d.clone()).unwrap();
        let rec = clean_depth(&mut depth, &DepthCleanOptions::default());
        assert_eq!(rec.outliers_removed + rec.specks_removed, 0, "{rec:?}");
        let worst = depth
            .data()
            .iter()
            .zip(&d)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(worst < 0.001, "{worst}");
        // Off: nothing changes.
        let mut depth = DepthMap::new(w as u32, h as u32, d.clone()).unwrap();
        clean_depth(
            &mut depth,
            &DepthCleanOptions {
                enabled: false,
                ..Default::default()
            },
        );
        assert_eq!(depth.data(), &d[..]);
    }
}
