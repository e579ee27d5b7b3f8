//! Robust 1-D affine fit `y = alpha * x + beta` with the Huber loss, by iteratively reweighted least
//! squares. Used to put generated relative depth at the observed metric scale.

use serde::{Deserialize, Serialize};

use crate::error::{GeometryError, Result};

/// Settings of [`huber_affine_fit`].
#[derive(Debug, Clone, Copy)]
pub struct HuberOptions {
    /// Huber threshold in units of the robust residual scale (1.4826 * MAD). 1.345 gives 95%
    /// efficiency on Gaussian noise.
    pub k: f64,
    pub max_iterations: usize,
    /// Stop when alpha and beta move less than this.
    pub tolerance: f64,
}

impl Default for HuberOptions {
    fn default() -> Self {
        Self {
            k: 1.345,
            max_iterations: 100,
            tolerance: 1e-10,
        }
    }
}

/// The fitted line and how well it fits.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AffineFit {
    pub alpha: f64,
    pub beta: f64,
    /// Robust residual scale (1.4826 * median absolute residual).
    pub scale: f64,
    /// Fraction of samples whose residual is within the Huber threshold.
    pub inlier_fraction: f64,
    pub iterations: usize,
}

impl AffineFit {
    pub fn apply(&self, x: f64) -> f64 {
        self.alpha * x + self.beta
    }
}

/// Weighted least-squares line; `None` when x has no spread under the weights.
fn weighted_line(x: &[f64], y: &[f64], w: &[f64]) -> Option<(f64, f64)> {
    let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for i in 0..x.len() {
        sw += w[i];
        sx += w[i] * x[i];
        sy += w[i] * y[i];
    }
    if sw <= 0.0 {
        return None;
    }
    let (mx, my) = (sx / sw, sy / sw);
    let (mut sxx, mut sxy) = (0.0, 0.0);
    for i in 0..x.len() {
        let dx = x[i] - mx;
        sxx += w[i] * dx * dx;
        sxy += w[i] * dx * (y[i] - my);
    }
    if sxx <= 1e-18 * sw {
        return None;
    }
    let alpha = sxy / sxx;
    Some((alpha, my - alpha * mx))
}

/// The median of `v` (reordered; the upper one of an even count), NaN when `v` is empty.
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mid = v.len() / 2;
    v.select_nth_unstable_by(mid, f64::total_cmp);
    v[mid]
}

/// Ordinary least squares, for comparison with the robust fit.
pub fn least_squares_affine_fit(x: &[f32], y: &[f32]) -> Result<(f64, f64)> {
    let (x, y) = to_f64(x, y)?;
    weighted_line(&x, &y, &vec![1.0; x.len()])
        .ok_or_else(|| GeometryError::Degenerate("x has no spread".into()))
}

fn to_f64(x: &[f32], y: &[f32]) -> Result<(Vec<f64>, Vec<f64>)> {
    if x.len() != y.len() {
        return Err(GeometryError::SizeMismatch {
            what: "affine fit samples",
            expected: x.len(),
            got: y.len(),
        });
    }
    if x.len() < 2 {
        return Err(GeometryError::Degenerate(format!(
            "an affine fit needs at least 2 samples, got {}",
            x.len()
        )));
    }
    for (i, (a, b)) in x.iter().zip(y).enumerate() {
        if !(a.is_finite() && b.is_finite()) {
            return Err(GeometryError::NonFinite {
                what: "affine fit samples",
                index: i,
            });
        }
    }
    Ok((
        x.iter().map(|&v| v as f64).collect(),
        y.iter().map(|&v| v as f64).collect(),
    ))
}

/// Fits `y = alpha * x + beta` minimising the Huber loss of the residuals.
///
/// Starts from an L1 fit (IRLS with 1/|r| weights), which gross outliers cannot drag far, then
/// iterates Huber weights with the residual scale re-estimated from the MAD each round. Outliers
/// spread on both sides barely move the fit; one-sided outliers bias beta by at most about
/// `0.4 * k * scale`.
pub fn huber_affine_fit(x: &[f32], y: &[f32], options: &HuberOptions) -> Result<AffineFit> {
    let (x, y) = to_f64(x, y)?;
    let n = x.len();
    let mut w = vec![1.0; n];
    let (mut alpha, mut beta) = weighted_line(&x, &y, &w)
        .ok_or_else(|| GeometryError::Degenerate("x has no spread".into()))?;
    let mut residuals = vec![0.0; n];
    let update_residuals = |alpha: f64, beta: f64, r: &mut [f64]| {
        for i in 0..n {
            r[i] = y[i] - (alpha * x[i] + beta);
        }
    };
    // L1 start.
    for _ in 0..30 {
        update_residuals(alpha, beta, &mut residuals);
        for i in 0..n {
            w[i] = 1.0 / residuals[i].abs().max(1e-9);
        }
        let Some((a, b)) = weighted_line(&x, &y, &w) else {
            break;
        };
        let moved = (a - alpha).abs() + (b - beta).abs();
        (alpha, beta) = (a, b);
        if moved < options.tolerance {
            break;
        }
    }
    let mut iterations = 0;
    let mut scale = 0.0;
    for _ in 0..options.max_iterations {
        iterations += 1;
        update_residuals(alpha, beta, &mut residuals);
        let mut abs: Vec<f64> = residuals.iter().map(|r| r.abs()).collect();
        scale = (1.4826 * median(&mut abs)).max(1e-12);
        let delta = options.k * scale;
        for i in 0..n {
            let r = residuals[i].abs();
            w[i] = if r <= delta { 1.0 } else { delta / r };
        }
        let Some((a, b)) = weighted_line(&x, &y, &w) else {
            break;
        };
        let moved = (a - alpha).abs() + (b - beta).abs();
        (alpha, beta) = (a, b);
        if moved < options.tolerance {
            break;
        }
    }
    update_residuals(alpha, beta, &mut residuals);
    let delta = options.k * scale;
    let inliers = residuals.iter().filter(|r| r.abs() <= delta).count();
    Ok(AffineFit {
        alpha,
        beta,
        scale,
        inlier_fraction: inliers as f64 / n as f64,
        iterations,
    })
}
