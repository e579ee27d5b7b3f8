//! Rectified flow: `x_t = (1 - t) x0 + t eps`, the model predicts `v = eps - x0`, trained with MSE
//! on logit-normal timesteps; sampled with Euler steps from t = 1 (noise) to t = 0 (data).

use candle_core::{Result, Tensor};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

/// SANA's timestep shift: `s t / (1 + (s - 1) t)`; 1.0 leaves t unchanged. The same shift must be
/// used in training and sampling.
pub fn shift_timestep(t: f32, shift: f32) -> f32 {
    shift * t / (1.0 + (shift - 1.0) * t)
}

/// Logit-normal(0, 1) timesteps, shifted.
pub fn sample_timesteps(n: usize, shift: f32, rng: &mut impl Rng) -> Vec<f32> {
    (0..n)
        .map(|_| {
            let z: f32 = StandardNormal.sample(rng);
            shift_timestep(1.0 / (1.0 + (-z).exp()), shift)
        })
        .collect()
}

/// `x_t = (1 - t) x0 + t eps` with per-sample `t` (B,).
pub fn interpolate(x0: &Tensor, eps: &Tensor, t: &Tensor) -> Result<Tensor> {
    let shape: Vec<usize> = std::iter::once(t.dim(0)?)
        .chain(std::iter::repeat_n(1, x0.rank() - 1))
        .collect();
    let t = t.reshape(shape)?;
    x0.broadcast_mul(&(t.neg()? + 1.0)?)?
        .broadcast_add(&eps.broadcast_mul(&t)?)
}

/// The velocity target `eps - x0`.
pub fn velocity_target(x0: &Tensor, eps: &Tensor) -> Result<Tensor> {
    eps - x0
}

/// The time grid of an N-step sampler: linspace(1, 0, N + 1), shifted.
pub fn time_grid(steps: usize, shift: f32) -> Vec<f32> {
    (0..=steps)
        .map(|i| shift_timestep(1.0 - i as f32 / steps as f32, shift))
        .collect()
}

/// Euler sampling: from `noise` at t = 1 to t = 0 in `steps` steps. `velocity(x, t)` is the model.
pub fn euler_sample(
    noise: &Tensor,
    steps: usize,
    shift: f32,
    mut velocity: impl FnMut(&Tensor, f32) -> Result<Tensor>,
) -> Result<Tensor> {
    let grid = time_grid(steps.max(1), shift);
    let mut x = noise.clone();
    for w in grid.windows(2) {
        let v = velocity(&x, w[0])?;
        x = (x + (v * (w[1] - w[0]) as f64)?)?;
    }
    Ok(x)
}
