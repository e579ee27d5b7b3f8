//! A depth map's noise, estimated from the map itself: `sigma(z) = a + b z^2` metres.
//!
//! Every depth sensor's error grows with distance: axial noise of structured light and stereo
//! grows with z^2 (Nguyen, Izadi and Lovell 2012), and so do their disparity steps (a step is
//! `z^2 / (f b steps)`); time of flight's grows slowly. [`DepthNoise::estimate`] fits the model
//! to the frame: it fits a plane to each 5 x 5 window on a sparse grid, takes the residual RMS
//! of the windows, keeps per depth bin a low quantile of them (flat patches, not edges), and fits
//! `a + b z^2` to the bins. Tolerances downstream are then multiples of `sigma(z)` instead of
//! fixed millimetres, so one setting holds on a renderer's exact depth and on a Kinect's.

use serde::{Deserialize, Serialize};

use crate::depth::DepthMap;

/// `sigma(z) = max(floor_m, a_m + b_per_m * z^2)`, metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DepthNoise {
    pub a_m: f32,
    pub b_per_m: f32,
}

/// The least sigma any estimate gives: a depth PNG stores millimetres (rounding: 0.29 mm).
pub const SIGMA_FLOOR_M: f32 = 0.0005;

impl Default for DepthNoise {
    /// Noise-free depth in millimetre PNGs.
    fn default() -> Self {
        Self {
            a_m: SIGMA_FLOOR_M,
            b_per_m: 0.0,
        }
    }
}

impl DepthNoise {
    pub fn sigma(&self, z: f32) -> f32 {
        (self.a_m + self.b_per_m * z * z).max(SIGMA_FLOOR_M)
    }

    /// Estimates the noise of `depth` (see the module docs). With too few flat windows (fewer
    /// than three depth bins of 30), the default (noise-free) model.
    pub fn estimate(depth: &DepthMap) -> Self {
        let (w, h) = (depth.width() as usize, depth.height() as usize);
        let d = depth.data();
        const R: usize = 2;
        const STRIDE: usize = 4;
        const BIN_M: f32 = 0.25;
        let mut samples: Vec<(f32, f32)> = Vec::new();
        let mut v = R;
        while v + R < h {
            let mut u = R;
            while u + R < w {
                if let Some(s) = window_residual(d, w, u, v, R) {
                    samples.push(s);
                }
                u += STRIDE;
            }
            v += STRIDE;
        }
        // Per depth bin, a low quantile of the residuals: flat windows; edges and creases give
        // the large ones.
        let mut bins: std::collections::BTreeMap<i32, Vec<f32>> = Default::default();
        for (z, r) in samples {
            bins.entry((z / BIN_M) as i32).or_default().push(r);
        }
        let points: Vec<(f32, f32, f32)> = bins
            .into_iter()
            .filter(|(_, rs)| rs.len() >= 30)
            .map(|(k, mut rs)| {
                let q = rs.len() * 3 / 10;
                let (_, r, _) = rs.select_nth_unstable_by(q, f32::total_cmp);
                // The RMS of 22 residual degrees of freedom: its 30th percentile is about 0.92
                // of sigma.
                let z = (k as f32 + 0.5) * BIN_M;
                (z, *r * 1.08, rs.len() as f32)
            })
            .collect();
        if points.len() < 3 {
            return Self::default();
        }
        fit(&points)
    }
}

/// Weighted least squares of `sigma = a + b z^2` over `(z, sigma, weight)`, both terms kept
/// non-negative.
fn fit(points: &[(f32, f32, f32)]) -> DepthNoise {
    let (mut s_w, mut s_x, mut s_xx, mut s_y, mut s_xy) = (0f64, 0f64, 0f64, 0f64, 0f64);
    for &(z, y, wt) in points {
        let (x, y, wt) = (f64::from(z * z), f64::from(y), f64::from(wt));
        s_w += wt;
        s_x += wt * x;
        s_xx += wt * x * x;
        s_y += wt * y;
        s_xy += wt * x * y;
    }
    let det = s_w * s_xx - s_x * s_x;
    let (mut a, mut b) = if det.abs() > 1e-12 {
        (
            (s_y * s_xx - s_x * s_xy) / det,
            (s_w * s_xy - s_x * s_y) / det,
        )
    } else {
        (s_y / s_w, 0.0)
    };
    if b < 0.0 {
        (a, b) = (s_y / s_w, 0.0);
    } else if a < 0.0 {
        (a, b) = (0.0, s_xy / s_xx.max(1e-12));
    }
    DepthNoise {
        a_m: a as f32,
        b_per_m: b as f32,
    }
}

/// The median depth and residual RMS of a plane `z = c0 + c1 du + c2 dv` fitted to the `(2r+1)^2`
/// window around (u, v); `None` with fewer than 80% of its pixels measured.
fn window_residual(d: &[f32], w: usize, u: usize, v: usize, r: usize) -> Option<(f32, f32)> {
    let mut pts = [(0f32, 0f32, 0f32); 49];
    let mut n = 0;
    let r_i = r as i64;
    for dv in -r_i..=r_i {
        for du in -r_i..=r_i {
            let z = d[(v as i64 + dv) as usize * w + (u as i64 + du) as usize];
            if z > 0.0 {
                pts[n] = (du as f32, dv as f32, z);
                n += 1;
            }
        }
    }
    let side = 2 * r + 1;
    if n * 5 < side * side * 4 {
        return None;
    }
    let pts = &pts[..n];
    let mean_z = pts.iter().map(|p| p.2).sum::<f32>() / n as f32;
    // Binned by the median: a window across an edge lies at one surface's depth, not between.
    let mut zs: Vec<f32> = pts.iter().map(|p| p.2).collect();
    let mid = zs.len() / 2;
    let (_, median_z, _) = zs.select_nth_unstable_by(mid, f32::total_cmp);
    let median_z = *median_z;
    // Normal equations of the plane fit, centred.
    let (mut suu, mut svv, mut suv, mut suz, mut svz, mut su, mut sv) =
        (0f32, 0f32, 0f32, 0f32, 0f32, 0f32, 0f32);
    for &(x, y, _) in pts {
        su += x;
        sv += y;
    }
    let (mu, mv) = (su / n as f32, sv / n as f32);
    for &(x, y, z) in pts {
        let (x, y, z) = (x - mu, y - mv, z - mean_z);
        suu += x * x;
        svv += y * y;
        suv += x * y;
        suz += x * z;
        svz += y * z;
    }
    let det = suu * svv - suv * suv;
    if det.abs() < 1e-6 {
        return None;
    }
    let c1 = (suz * svv - svz * suv) / det;
    let c2 = (svz * suu - suz * suv) / det;
    let ss: f32 = pts
        .iter()
        .map(|&(x, y, z)| {
            let e = (z - mean_z) - c1 * (x - mu) - c2 * (y - mv);
            e * e
        })
        .sum();
    Some((median_z, (ss / (n as f32 - 3.0)).sqrt()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A tilted plane from 1 to 4 m across the image, with Gaussian noise of `model`.
    fn noisy_ramp(model: DepthNoise, seed: u64) -> DepthMap {
        let (w, h) = (320u32, 240u32);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let data = (0..w * h)
            .map(|i| {
                let z = 1.0 + 3.0 * (i % w) as f32 / w as f32 + 0.2 * (i / w) as f32 / h as f32;
                let (a, b): (f32, f32) = (rng.random_range(1e-7..1.0), rng.random_range(0.0..1.0));
                let g = (-2.0 * a.ln()).sqrt() * (std::f32::consts::TAU * b).cos();
                z + g * model.sigma(z)
            })
            .collect();
        DepthMap::new(w, h, data).unwrap()
    }

    #[test]
    fn the_estimate_recovers_the_noise_it_was_given() {
        for truth in [
            DepthNoise {
                a_m: 0.0012,
                b_per_m: 0.0019,
            },
            DepthNoise {
                a_m: 0.001,
                b_per_m: 0.0,
            },
            DepthNoise {
                a_m: 0.0,
                b_per_m: 0.004,
            },
        ] {
            let est = DepthNoise::estimate(&noisy_ramp(truth, 1));
            for z in [1.5f32, 2.5, 3.5] {
                let (s, t) = (est.sigma(z), truth.sigma(z));
                assert!((s / t - 1.0).abs() < 0.2, "{truth:?} at {z} m: {s} vs {t}");
            }
        }
    }

    #[test]
    fn noise_free_depth_gives_the_floor_and_edges_do_not_raise_it() {
        // Two flat planes at 1 and 3 m meeting in a vertical edge.
        let (w, h) = (200u32, 150u32);
        let data = (0..w * h)
            .map(|i| if i % w < 100 { 1.0 } else { 3.0 })
            .collect();
        let est = DepthNoise::estimate(&DepthMap::new(w, h, data).unwrap());
        assert!(est.sigma(2.0) <= SIGMA_FLOOR_M * 1.01, "{est:?}");
        // Too little depth: the default.
        assert_eq!(
            DepthNoise::estimate(&DepthMap::zeros(50, 50)),
            DepthNoise::default()
        );
    }
}
