//! Resumable rectified-flow training of GL-DoT.
//!
//! A run directory holds everything needed to resume or to use the model:
//! ```text
//! run/
//!   train.json          TrainConfig (model config and seed included), written first
//!   model.safetensors   current weights
//!   ema.safetensors     exponential moving average of the weights (used for inference)
//!   optimizer.safetensors  AdamW moments
//!   state.json          step and last loss (written last: a checkpoint is complete when it is)
//!   loss.csv            step, loss, learning rate, gradient norm
//! ```

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::config::GlDotConfig;
use crate::data::PairData;
use crate::flow::{interpolate, sample_timesteps, velocity_target};
use crate::init::{randn, SeededInit};
use crate::model::{mix_views, GlDot};

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("{path}: {msg}")]
    File { path: PathBuf, msg: String },
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    #[error("{0}")]
    Config(String),
}

pub type Result<T, E = TrainError> = std::result::Result<T, E>;

fn file_err(path: &Path, e: impl std::fmt::Display) -> TrainError {
    TrainError::File {
        path: path.to_path_buf(),
        msg: e.to_string(),
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    pub model: GlDotConfig,
    pub seed: u64,
    pub batch_size: usize,
    pub steps: usize,
    pub learning_rate: f64,
    pub warmup_steps: usize,
    pub weight_decay: f64,
    pub grad_clip: f64,
    pub ema_decay: f64,
    /// Timestep shift, the same in training and sampling.
    pub timestep_shift: f32,
    /// Probability that a sample is conditioned on another view too (with rho ~ U(0, 1)).
    pub cross_view_probability: f64,
    pub checkpoint_every: usize,
    /// Per-target-channel weights of the flow loss (RGB, mask, near depth, far depth), normalised
    /// to mean 1; empty = uniform. The mask is what the amodal IoU and the fusion use, and it is one
    /// channel of six, so weighting it up spends the model's capacity where it is measured.
    pub channel_loss_weights: Vec<f32>,
    /// Inference, not training: the mask channel's threshold for "inside" (in [-1, 1]; 0 is the
    /// middle). Chosen on validation pairs after training (`deocc eval amodal --split val
    /// --mask-thresholds ...`) and shipped with the weights in train.json.
    pub mask_threshold: f32,
    /// Inference, not training: the threshold for crops that carry the other views' reprojected
    /// observations (at least one point kept, [`deocc_completion::CropCondition::seen_elsewhere`]);
    /// `None` = `mask_threshold`. Those points anchor the outline, and the pixels the model adds
    /// beside them are wrong more often than in a one-view crop: chosen on validation pairs like
    /// `mask_threshold` (`deocc eval amodal --split val --mask-thresholds-seen-elsewhere ...`).
    pub mask_threshold_seen_elsewhere: Option<f32>,
    /// Inference, not training: samples averaged per completion ([`crate::infer::GlDotCompleter`]'s
    /// `samples`), chosen on validation pairs like the threshold and shipped with it.
    pub inference_samples: usize,
    /// Inference, not training: keep the geometric prior's pixels in the amodal mask
    /// ([`crate::infer::GlDotCompleter`]'s `keep_prior`), chosen on validation pairs.
    pub mask_keeps_prior: bool,
    /// Weight of the mask head's loss against the flow loss (models with `mask_head`).
    pub mask_loss_weight: f32,
    /// Fraction of each batch drawn at t = 1 and trained on the mask head (models with
    /// `mask_head`), in (0, 1].
    pub mask_head_noise_fraction: f64,
    /// Weight of the mean head's L1 loss against the flow loss (models with `mean_head`).
    pub mean_loss_weight: f32,
    /// Weight of the error head's Laplace likelihood against the flow loss (models with
    /// `error_head`).
    pub error_loss_weight: f32,
    /// Inference, not training: with a mean head, colour and depth are the mean head's, read at
    /// the first step (one forward pass); off, they are the flow's sample after all steps.
    pub inference_reads_mean: bool,
    /// The share of training conditions that carry the other views' reprojected observations
    /// (where the pairs have them); the others train the one-view case. 0 by default: the
    /// shipped weights were trained without them, and the README's training chain reproduces
    /// those.
    pub other_views_observed: f32,
    /// Metric depth loss (0 = off): with a width `w` in metres, the mean head's near- and
    /// far-side depth loss weighs each pair by its crop's width over `w`, clamped to [1,
    /// [`MAX_METRIC_DEPTH_WEIGHT`]]. Depth is learned relative to the crop's width, but the
    /// fusion's errors are in metres: a wide crop (a chair, a table) turns the same relative
    /// error into several times the centimetres of a bottle's.
    pub depth_loss_metric_width_m: f32,
    /// The mean head's far side weighs 1 at visible pixels too, not [`MEAN_VISIBLE_WEIGHT`]:
    /// an object's back is hidden wherever its front is visible, and those pixels place most of
    /// the fused far side.
    pub far_side_full_weight: bool,
}

/// The largest weight [`TrainConfig::depth_loss_metric_width_m`] gives a pair: about the
/// pipeline's widest learned crop (0.6 m) over a 0.25 m reference, so that furniture crops the
/// pipeline hands to the rules do not take over the loss.
pub const MAX_METRIC_DEPTH_WEIGHT: f32 = 2.5;

/// A pair's weight in the mean head's depth loss for a crop `crop_width_m` wide (NaN: unknown,
/// weight 1) with reference width `reference_m` (0 = off, weight 1).
pub fn metric_depth_weight(crop_width_m: f32, reference_m: f32) -> f32 {
    if reference_m > 0.0 && crop_width_m.is_finite() {
        (crop_width_m / reference_m).clamp(1.0, MAX_METRIC_DEPTH_WEIGHT)
    } else {
        1.0
    }
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            model: GlDotConfig::small(),
            seed: 0,
            batch_size: 16,
            steps: 20_000,
            learning_rate: 5e-4,
            warmup_steps: 300,
            weight_decay: 0.01,
            grad_clip: 1.0,
            ema_decay: 0.999,
            timestep_shift: 1.0,
            cross_view_probability: 0.5,
            checkpoint_every: 200,
            channel_loss_weights: Vec::new(),
            mask_threshold: 0.0,
            mask_threshold_seen_elsewhere: None,
            inference_samples: 1,
            mask_keeps_prior: false,
            mask_loss_weight: 1.0,
            mask_head_noise_fraction: 0.5,
            mean_loss_weight: 1.0,
            error_loss_weight: 1.0,
            inference_reads_mean: true,
            other_views_observed: 0.0,
            depth_loss_metric_width_m: 0.0,
            far_side_full_weight: false,
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, Default)]
pub struct TrainState {
    pub step: usize,
    pub last_loss: f32,
}

/// AdamW with moments we can save.
pub struct AdamW {
    pub m: BTreeMap<String, Tensor>,
    pub v: BTreeMap<String, Tensor>,
    beta1: f64,
    beta2: f64,
    eps: f64,
}

impl AdamW {
    pub fn new(vars: &BTreeMap<String, Var>) -> candle_core::Result<Self> {
        let zeros = |v: &Var| v.as_tensor().zeros_like();
        Ok(Self {
            m: vars
                .iter()
                .map(|(k, v)| Ok((k.clone(), zeros(v)?)))
                .collect::<candle_core::Result<_>>()?,
            v: vars
                .iter()
                .map(|(k, v)| Ok((k.clone(), zeros(v)?)))
                .collect::<candle_core::Result<_>>()?,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        })
    }

    /// One update with gradients already scaled (clipped); `step` counts from 1.
    pub fn step(
        &mut self,
        vars: &BTreeMap<String, Var>,
        grads: &BTreeMap<String, Tensor>,
        step: usize,
        lr: f64,
        wd: f64,
    ) -> candle_core::Result<()> {
        self.step_scaled(vars, grads, 1.0, step, lr, wd)
    }

    /// One update with the gradients multiplied by `grad_scale` (gradient clipping) first.
    ///
    /// On the CPU each parameter is updated in one pass over plain slices: the composed version
    /// ran about fourteen candle ops per parameter tensor (two thousand small ops per step for
    /// this model, each allocating a tensor of the parameter's size). Other devices use the
    /// composed ops.
    pub fn step_scaled(
        &mut self,
        vars: &BTreeMap<String, Var>,
        grads: &BTreeMap<String, Tensor>,
        grad_scale: f64,
        step: usize,
        lr: f64,
        wd: f64,
    ) -> candle_core::Result<()> {
        let (b1, b2) = (self.beta1, self.beta2);
        let c1 = 1.0 - b1.powi(step as i32);
        let c2 = 1.0 - b2.powi(step as i32);
        for (name, var) in vars {
            let Some(g) = grads.get(name) else { continue };
            let missing = || candle_core::Error::msg(format!("no moment for {name}"));
            let m = self.m.get_mut(name).ok_or_else(missing)?;
            let v = self.v.get_mut(name).ok_or_else(missing)?;
            // Decoupled weight decay on matrices only (not biases, norms or tables).
            let decay = if var.rank() >= 2 && !name.contains("table") {
                wd
            } else {
                0.0
            };
            let w = var.as_tensor();
            if w.device().is_cpu() && w.dtype() == DType::F32 {
                let shape = w.shape().clone();
                let g = flat_f32(g)?;
                let (mut mv, mut vv, mut wv) = (flat_f32(m)?, flat_f32(v)?, flat_f32(w)?);
                let (b1, b2, eps) = (b1 as f32, b2 as f32, self.eps as f32);
                let (inv_c1, inv_c2) = (1.0 / c1 as f32, 1.0 / c2 as f32);
                let (keep, step_size, gs) =
                    ((1.0 - lr * decay) as f32, lr as f32, grad_scale as f32);
                for (((gi, mi), vi), wi) in g.iter().zip(&mut mv).zip(&mut vv).zip(&mut wv) {
                    let gi = gi * gs;
                    *mi = b1 * *mi + (1.0 - b1) * gi;
                    *vi = b2 * *vi + (1.0 - b2) * gi * gi;
                    let update = (*mi * inv_c1) / ((*vi * inv_c2).sqrt() + eps);
                    *wi = *wi * keep - step_size * update;
                }
                let dev = w.device().clone();
                *m = Tensor::from_vec(mv, shape.clone(), &dev)?;
                *v = Tensor::from_vec(vv, shape.clone(), &dev)?;
                var.set(&Tensor::from_vec(wv, shape, &dev)?)?;
            } else {
                let g = (g * grad_scale)?;
                // detach(): optimizer state must not record an op graph, or every step would
                // keep the previous step's tensors alive (a leak of one model copy per step).
                *m = ((&*m * b1)? + (&g * (1.0 - b1))?)?.detach();
                *v = ((&*v * b2)? + (g.sqr()? * (1.0 - b2))?)?.detach();
                let update = ((&*m / c1)? / ((&*v / c2)?.sqrt()? + self.eps)?)?;
                let new = ((w * (1.0 - lr * decay))? - (update * lr)?)?.detach();
                var.set(&new)?;
            }
        }
        Ok(())
    }
}

/// A tensor's values as one f32 vector (a copy; row-major).
fn flat_f32(t: &Tensor) -> candle_core::Result<Vec<f32>> {
    t.flatten_all()?.to_dtype(DType::F32)?.to_vec1::<f32>()
}

/// Learning rate with linear warm-up then cosine decay to 10%.
pub fn learning_rate(cfg: &TrainConfig, step: usize) -> f64 {
    if step < cfg.warmup_steps {
        return cfg.learning_rate * (step + 1) as f64 / cfg.warmup_steps as f64;
    }
    let t = (step - cfg.warmup_steps) as f64
        / (cfg.steps.saturating_sub(cfg.warmup_steps)).max(1) as f64;
    cfg.learning_rate * (0.1 + 0.9 * 0.5 * (1.0 + (std::f64::consts::PI * t.min(1.0)).cos()))
}

fn sorted_vars(varmap: &VarMap) -> BTreeMap<String, Var> {
    varmap
        .data()
        .lock()
        .map(|d| d.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
        .unwrap_or_default()
}

fn save_tensors(path: &Path, tensors: &BTreeMap<String, Tensor>) -> Result<()> {
    let tmp = path.with_extension("safetensors.tmp");
    let map: std::collections::HashMap<&str, Tensor> = tensors
        .iter()
        .map(|(k, v)| (k.as_str(), v.clone()))
        .collect();
    candle_core::safetensors::save(&map, &tmp).map_err(|e| file_err(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| file_err(path, e))
}

fn load_tensors(path: &Path, device: &Device) -> Result<BTreeMap<String, Tensor>> {
    Ok(candle_core::safetensors::load(path, device)
        .map_err(|e| file_err(path, e))?
        .into_iter()
        .collect())
}

fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let tmp = path.with_extension("json.tmp");
    let text = serde_json::to_string_pretty(value).map_err(|e| file_err(path, e))?;
    std::fs::write(&tmp, text + "\n").map_err(|e| file_err(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| file_err(path, e))
}

pub fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| file_err(path, e))?;
    serde_json::from_str(&text).map_err(|e| file_err(path, e))
}

impl TrainConfig {
    /// Parses a `train.json`: the model configuration must be there (a `{}` is not a preset),
    /// unknown fields are refused, and every value is range-checked ([`TrainConfig::validate`]).
    pub fn from_json(text: &str) -> std::result::Result<Self, String> {
        let value: serde_json::Value = serde_json::from_str(text).map_err(|e| e.to_string())?;
        if value.get("model").is_none() {
            return Err("no \"model\" configuration".into());
        }
        let cfg: Self = serde_json::from_value(value).map_err(|e| e.to_string())?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Reads and checks a `train.json`, naming the file in errors.
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| file_err(path, e))?;
        Self::from_json(&text).map_err(|e| file_err(path, e))
    }

    /// Checks every field's range (the model's shape arithmetic included).
    pub fn validate(&self) -> std::result::Result<(), String> {
        self.model.validate()?;
        let positive = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(format!("{name} = {v} must be positive and finite"))
            }
        };
        if self.batch_size == 0 || self.batch_size > 4096 {
            return Err(format!(
                "batch_size = {} is outside 1..=4096",
                self.batch_size
            ));
        }
        if self.steps == 0 {
            return Err("steps must be at least 1".into());
        }
        if self.checkpoint_every == 0 {
            return Err("checkpoint_every must be at least 1".into());
        }
        positive("learning_rate", self.learning_rate)?;
        positive("grad_clip", self.grad_clip)?;
        positive("timestep_shift", f64::from(self.timestep_shift))?;
        if !(self.weight_decay.is_finite() && (0.0..1.0).contains(&self.weight_decay)) {
            return Err(format!(
                "weight_decay = {} is outside [0, 1)",
                self.weight_decay
            ));
        }
        if !(0.0..1.0).contains(&self.ema_decay) {
            return Err(format!("ema_decay = {} is outside [0, 1)", self.ema_decay));
        }
        if !(0.0..=1.0).contains(&self.cross_view_probability) {
            return Err(format!(
                "cross_view_probability = {} is outside [0, 1]",
                self.cross_view_probability
            ));
        }
        if !(self.mask_head_noise_fraction > 0.0 && self.mask_head_noise_fraction <= 1.0) {
            return Err(format!(
                "mask_head_noise_fraction = {} is outside (0, 1]",
                self.mask_head_noise_fraction
            ));
        }
        if !(self.mask_loss_weight.is_finite() && self.mask_loss_weight >= 0.0) {
            return Err(format!(
                "mask_loss_weight = {} must be finite and non-negative",
                self.mask_loss_weight
            ));
        }
        if !(0.0..=1.0).contains(&self.other_views_observed) {
            return Err(format!(
                "other_views_observed = {} is outside [0, 1]",
                self.other_views_observed
            ));
        }
        if !(self.mean_loss_weight.is_finite() && self.mean_loss_weight >= 0.0) {
            return Err(format!(
                "mean_loss_weight = {} must be finite and non-negative",
                self.mean_loss_weight
            ));
        }
        if !(self.depth_loss_metric_width_m.is_finite() && self.depth_loss_metric_width_m >= 0.0) {
            return Err(format!(
                "depth_loss_metric_width_m = {} must be finite and non-negative (0 = off)",
                self.depth_loss_metric_width_m
            ));
        }
        if !(self.error_loss_weight.is_finite() && self.error_loss_weight >= 0.0) {
            return Err(format!(
                "error_loss_weight = {} must be finite and non-negative",
                self.error_loss_weight
            ));
        }
        let range = if self.model.mask_head {
            0.0..=1.0
        } else {
            -1e3..=1e3
        };
        for (name, th) in [
            ("mask_threshold", Some(self.mask_threshold)),
            (
                "mask_threshold_seen_elsewhere",
                self.mask_threshold_seen_elsewhere,
            ),
        ] {
            if let Some(th) = th.filter(|th| !range.contains(th)) {
                return Err(format!(
                    "{name} = {th} is outside [{}, {}]",
                    range.start(),
                    range.end()
                ));
            }
        }
        if !(1..=16).contains(&self.inference_samples) {
            return Err(format!(
                "inference_samples = {} is outside 1..=16",
                self.inference_samples
            ));
        }
        Ok(())
    }
}

/// Every tensor finite, or an error naming the first that is not.
pub fn check_finite(tensors: &BTreeMap<String, Tensor>) -> candle_core::Result<Option<String>> {
    for (name, t) in tensors {
        let v = t.flatten_all()?.to_dtype(DType::F32)?.to_vec1::<f32>()?;
        if v.iter().any(|x| !x.is_finite()) {
            return Ok(Some(name.clone()));
        }
    }
    Ok(None)
}

/// The rectified-flow loss of one batch of `b` random samples of the model's shapes (t = 0.5,
/// condition tokens mixed from two encodings with rho = 0.5): the step `deocc bench model` times
/// against PyTorch and the `train_steps` profiling example runs, one definition for both.
pub fn random_batch_loss(
    model: &GlDot,
    b: usize,
    rng: &mut impl Rng,
    device: &Device,
) -> candle_core::Result<Tensor> {
    let cfg = &model.config;
    let (r, tc, cc) = (cfg.resolution, cfg.target_channels, cfg.cond_channels);
    let x0 = randn((b, r, r, tc), rng, device)?;
    let cond = randn((b, r, r, cc), rng, device)?;
    let toks = model.encode(&Tensor::cat(&[&cond, &cond], 0)?)?;
    let half = Tensor::full(0.5f32, b, device)?;
    let c = mix_views(&toks.narrow(0, 0, b)?, &toks.narrow(0, b, b)?, &half)?;
    let eps = randn((b, r, r, tc), rng, device)?;
    let xt = interpolate(&x0, &eps, &half)?;
    (model.forward(&xt, &half, &cond, &c)?.narrow(3, 0, tc)? - velocity_target(&x0, &eps)?)?
        .sqr()?
        .mean_all()
}

/// The mask head's classification loss: binary cross-entropy plus Dice over the candidate
/// pixels (not visible, the scene observed in front of the object's median depth: where a hidden
/// part can be), the logit being `head + PRIOR_LOGIT * prior`. `head` (B, R, R, 1), `cond` (B, R,
/// R, [`crate::encode::COND_CHANNELS`]), `target` (B, R, R, 6) with the amodal mask in channel 3.
/// Both terms in stable forms (softplus), so saturated logits give finite gradients.
pub fn mask_head_loss(
    head: &Tensor,
    cond: &Tensor,
    target: &Tensor,
) -> candle_core::Result<Tensor> {
    let (b, r, _, _) = head.dims4()?;
    let n = r * r;
    let cc = cond.dim(3)?;
    let cond_host = cond.flatten_all()?.to_vec1::<f32>()?;
    let target_host = target.narrow(3, 3, 1)?.flatten_all()?.to_vec1::<f32>()?;
    let region: Vec<f32> = (0..b * n)
        .map(|i| {
            let c = &cond_host[i * cc..(i + 1) * cc];
            (c[3] <= 0.0 && c[5] < 0.0) as u8 as f32
        })
        .collect();
    let y: Vec<f32> = target_host
        .iter()
        .map(|&m| (m > 0.0) as u8 as f32)
        .collect();
    let shape = (b, r, r, 1);
    let dev = head.device();
    let region = Tensor::from_vec(region, shape, dev)?;
    let y = Tensor::from_vec(y, shape, dev)?;
    let logit = (head + (cond.narrow(3, 6, 1)? * f64::from(crate::encode::PRIOR_LOGIT))?)?;
    // log(1 + exp(-|l|)), and softplus(-l) = relu(-l) + that: -log(sigmoid(l)).
    let log1p_exp = (logit.abs()?.neg()?.exp()? + 1.0)?.log()?;
    let bce = ((logit.relu()? - (&logit * &y)?)? + &log1p_exp)?;
    let count = region.sum_all()?.to_scalar::<f32>()?.max(1.0);
    let bce = ((bce * &region)?.sum_all()? / f64::from(count))?;
    let p = (logit.neg()?.relu()? + &log1p_exp)?.neg()?.exp()?;
    let (p, y) = ((p * &region)?, (y * &region)?);
    let inter = (&p * &y)?.sum((1, 2, 3))?;
    let sums = (p.sum((1, 2, 3))? + y.sum((1, 2, 3))?)?;
    let dice = (((inter * 2.0)? + 1.0)? / (sums + 1.0)?)?;
    let dice = (dice.neg()? + 1.0)?.mean_all()?;
    bce + dice
}

/// Weight of a visible pixel in the mean head's loss (a hidden pixel weighs 1): the visible
/// part's colour and near side are observed, and the figures are measured on the hidden part.
pub const MEAN_VISIBLE_WEIGHT: f32 = 0.25;

/// The mean head's loss: the L1 distance of its colour and depth residuals (B, R, R,
/// [`crate::config::MEAN_CHANNELS`]) to the target's (`residual`, the target less the base, (B, R,
/// R, 6)) over the object's pixels (the target mask, channel 3 of `target`), hidden pixels
/// weighing 1 and visible ones [`MEAN_VISIBLE_WEIGHT`] (the visible mask, channel 3 of `cond`).
/// L1, so the head estimates the median, which mean absolute errors reward.
///
/// `weights` sets what the defaults leave as above: per-pair depth weights
/// ([`metric_depth_weight`]) and the visible pixels' weight on the far side.
pub fn mean_head_loss(
    mean: &Tensor,
    residual: &Tensor,
    target: &Tensor,
    cond: &Tensor,
    weights: &MeanLossWeights<'_>,
) -> candle_core::Result<Tensor> {
    let want = Tensor::cat(&[residual.narrow(3, 0, 3)?, residual.narrow(3, 4, 2)?], 3)?;
    let (w, total) = object_pixel_weights(target, cond)?;
    let total = total.max(1.0) * crate::config::MEAN_CHANNELS as f32;
    let raw = (mean - want)?.abs()?;
    let err = if weights.far_visible == MEAN_VISIBLE_WEIGHT {
        raw.broadcast_mul(&w)?
    } else {
        // The far side is hidden at visible pixels too: no view shows an object's back.
        let visible = cond.narrow(3, 3, 1)?.gt(0f32)?.to_dtype(w.dtype())?;
        let w_far = (&w + (visible * f64::from(weights.far_visible - MEAN_VISIBLE_WEIGHT))?)?;
        let c = crate::config::MEAN_CHANNELS;
        Tensor::cat(
            &[
                raw.narrow(3, 0, c - 1)?.broadcast_mul(&w)?,
                raw.narrow(3, c - 1, 1)?.broadcast_mul(&w_far)?,
            ],
            3,
        )?
    };
    let err = match weights.depth {
        Some(dw) => {
            let c = crate::config::MEAN_CHANNELS;
            let per_channel: Vec<f32> = dw
                .iter()
                .flat_map(|&d| (0..c).map(move |ch| if ch >= 3 { d } else { 1.0 }))
                .collect();
            let per_channel = Tensor::from_vec(per_channel, (dw.len(), 1, 1, c), mean.device())?;
            err.broadcast_mul(&per_channel)?
        }
        None => err,
    };
    err.sum_all()? / f64::from(total)
}

/// What the mean head's loss weighs besides the object's pixels ([`mean_head_loss`]).
#[derive(Debug, Clone, Copy)]
pub struct MeanLossWeights<'a> {
    /// Per pair: multiplies its near- and far-side depth terms (`None`: 1).
    pub depth: Option<&'a [f32]>,
    /// A visible pixel's weight on the far side ([`MEAN_VISIBLE_WEIGHT`] by default, as on the
    /// other channels).
    pub far_visible: f32,
}

impl Default for MeanLossWeights<'_> {
    fn default() -> Self {
        Self {
            depth: None,
            far_visible: MEAN_VISIBLE_WEIGHT,
        }
    }
}

/// The mean and error heads' per-pixel weights (hidden pixels of the object 1, visible ones
/// [`MEAN_VISIBLE_WEIGHT`], others 0) and their sum.
fn object_pixel_weights(target: &Tensor, cond: &Tensor) -> candle_core::Result<(Tensor, f32)> {
    let (b, r, _, _) = target.dims4()?;
    let object = target.narrow(3, 3, 1)?.flatten_all()?.to_vec1::<f32>()?;
    let visible = cond.narrow(3, 3, 1)?.flatten_all()?.to_vec1::<f32>()?;
    let w: Vec<f32> = object
        .iter()
        .zip(&visible)
        .map(|(&m, &v)| match (m > 0.0, v > 0.0) {
            (false, _) => 0.0,
            (true, true) => MEAN_VISIBLE_WEIGHT,
            (true, false) => 1.0,
        })
        .collect();
    let total = w.iter().sum::<f32>();
    Ok((Tensor::from_vec(w, (b, r, r, 1), target.device())?, total))
}

/// The error head's loss: the Laplace negative log-likelihood `e / s + ln s` of the mean head's
/// absolute depth error `e` (near and far side, relative depth), with `s = exp(head +
/// ERROR_LOG_OFFSET)` the head's expected absolute error, over the object's pixels weighted as
/// the mean head's loss. The mean is held fixed (`mean` should come detached): the head learns
/// how far off the mean is. Minimised at `s = E[e]` per pixel. `head` (B, R, R, 2), `mean` (B,
/// R, R, [`crate::config::MEAN_CHANNELS`]), `residual` (B, R, R, 6) the target less the base.
pub fn error_head_loss(
    head: &Tensor,
    mean: &Tensor,
    residual: &Tensor,
    target: &Tensor,
    cond: &Tensor,
) -> candle_core::Result<Tensor> {
    let scale = f64::from(crate::encode::DEPTH_SCALE);
    let err = ((mean.narrow(3, 3, 2)? - residual.narrow(3, 4, 2)?)?.abs()? / scale)?;
    // The log scale, clamped so that exp(-log s) stays finite while the head is far off.
    let log_s = (head + f64::from(crate::config::ERROR_LOG_OFFSET))?.clamp(-12f32, 4f32)?;
    let nll = ((err * log_s.neg()?.exp()?)? + &log_s)?;
    let (w, total) = object_pixel_weights(target, cond)?;
    let total = total.max(1.0) * crate::config::ERROR_CHANNELS as f32;
    nll.broadcast_mul(&w)?.sum_all()? / f64::from(total)
}

/// A training run in memory.
pub struct Trainer {
    pub config: TrainConfig,
    pub model: GlDot,
    pub varmap: VarMap,
    vars: BTreeMap<String, Var>,
    ema: BTreeMap<String, Tensor>,
    opt: AdamW,
    pub state: TrainState,
    device: Device,
}

/// What one step did.
#[derive(Debug, Clone, Copy)]
pub struct StepReport {
    pub step: usize,
    pub loss: f32,
    pub learning_rate: f64,
    pub grad_norm: f32,
}

impl Trainer {
    pub fn new(config: TrainConfig, device: &Device) -> Result<Self> {
        config.model.validate().map_err(TrainError::Config)?;
        let w = &config.channel_loss_weights;
        if !w.is_empty()
            && (w.len() != config.model.target_channels
                || w.iter().any(|x| !x.is_finite() || *x < 0.0)
                || w.iter().sum::<f32>() <= 0.0)
        {
            return Err(TrainError::Config(format!(
                "channel_loss_weights {w:?}: need {} non-negative weights, not all zero",
                config.model.target_channels
            )));
        }
        let varmap = VarMap::new();
        let vb = VarBuilder::from_backend(
            Box::new(SeededInit::new(varmap.clone(), config.seed)),
            DType::F32,
            device.clone(),
        );
        let model = GlDot::new(&config.model, vb)?;
        let vars = sorted_vars(&varmap);
        let ema = vars
            .iter()
            .map(|(k, v)| Ok((k.clone(), v.as_tensor().copy()?)))
            .collect::<candle_core::Result<_>>()?;
        let opt = AdamW::new(&vars)?;
        Ok(Self {
            config,
            model,
            varmap,
            vars,
            ema,
            opt,
            state: TrainState::default(),
            device: device.clone(),
        })
    }

    /// Opens a run directory: resumes it if it has a checkpoint, else starts it with `config`.
    pub fn open(dir: &Path, config: TrainConfig, device: &Device) -> Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| file_err(dir, e))?;
        let state_path = dir.join("state.json");
        if !state_path.exists() {
            let t = Self::new(config, device)?;
            write_json(&dir.join("train.json"), &t.config)?;
            return Ok(t);
        }
        let mut saved = TrainConfig::read(&dir.join("train.json"))?;
        if saved.model != config.model {
            return Err(TrainError::Config(format!("{}: this run was started with another model configuration; use a new --run directory", dir.display())));
        }
        saved.steps = config.steps; // the only thing a resume may change: how far to go
        let mut t = Self::new(saved, device)?;
        let weights = load_tensors(&dir.join("model.safetensors"), device)?;
        for (name, var) in &t.vars {
            let w = weights.get(name).ok_or_else(|| {
                file_err(
                    &dir.join("model.safetensors"),
                    format!("missing tensor {name}"),
                )
            })?;
            var.set(w)?;
        }
        let ema_path = dir.join("ema.safetensors");
        t.ema = load_tensors(&ema_path, device)?;
        for (name, var) in &t.vars {
            match t.ema.get(name) {
                Some(e) if e.shape() == var.shape() => {}
                Some(e) => {
                    return Err(file_err(
                        &ema_path,
                        format!(
                            "tensor {name} has shape {:?}, the model needs {:?}",
                            e.shape(),
                            var.shape()
                        ),
                    ))
                }
                None => return Err(file_err(&ema_path, format!("missing tensor {name}"))),
            }
        }
        for (path, tensors) in [(&ema_path, &t.ema)] {
            if let Some(bad) = check_finite(tensors)? {
                return Err(file_err(
                    path,
                    format!("tensor {bad} has non-finite values"),
                ));
            }
        }
        let opt = load_tensors(&dir.join("optimizer.safetensors"), device)?;
        for name in t.vars.keys() {
            let get = |p: &str| {
                opt.get(&format!("{p}.{name}")).cloned().ok_or_else(|| {
                    file_err(
                        &dir.join("optimizer.safetensors"),
                        format!("missing moment {p}.{name}"),
                    )
                })
            };
            t.opt.m.insert(name.clone(), get("m")?);
            t.opt.v.insert(name.clone(), get("v")?);
        }
        t.state = read_json(&state_path)?;
        write_json(&dir.join("train.json"), &t.config)?;
        Ok(t)
    }

    /// Starts from given weights (e.g. the shipped f16 EMA weights) instead of the random
    /// initialisation: the way to continue when a run directory with optimizer state is not at hand.
    pub fn init_from(&mut self, weights: &Path) -> Result<()> {
        let tensors = load_tensors(weights, &self.device)?;
        for (name, var) in &self.vars {
            let w = tensors
                .get(name)
                .ok_or_else(|| file_err(weights, format!("missing tensor {name}")))?;
            let mut w = w.to_dtype(DType::F32)?;
            if w.shape() != var.shape() {
                if let Some(grown) = self.grow_input_channels(name, &w)? {
                    w = grown;
                } else if let Some(grown) = self.grow_output_channels(name, &w)? {
                    w = grown;
                }
            }
            if w.shape() != var.shape() {
                return Err(file_err(
                    weights,
                    format!(
                        "tensor {name} has shape {:?}, the model needs {:?}",
                        w.shape(),
                        var.shape()
                    ),
                ));
            }
            var.set(&w)?;
            self.ema.insert(name.clone(), w.copy()?.detach());
        }
        Ok(())
    }

    /// Warm start across an added condition channel: the two patch embeddings take
    /// (patch, patch, channels) inputs, channel fastest; weights of a model with fewer channels
    /// are copied in with zero columns for the new (last) channels, so the grown model computes
    /// exactly what the old one did until training teaches it to use them.
    fn grow_input_channels(&self, name: &str, w: &Tensor) -> Result<Option<Tensor>> {
        let m = &self.config.model;
        let (patch_area, new_channels) = match name {
            "x_embedder.weight" => (m.patch * m.patch, m.target_channels + m.cond_channels),
            "cond_encoder.embed.weight" => (m.cond_patch * m.cond_patch, m.cond_channels),
            _ => return Ok(None),
        };
        let (d, k) = w.dims2()?;
        if d != m.width || k % patch_area != 0 || k / patch_area >= new_channels {
            return Ok(None);
        }
        let old_channels = k / patch_area;
        Ok(Some(
            w.reshape((d, patch_area, old_channels))?
                .pad_with_zeros(2, 0, new_channels - old_channels)?
                .reshape((d, patch_area * new_channels))?,
        ))
    }

    /// Warm start across an added output channel (the mask head): the final layer's rows are
    /// (patch, patch, channels), channel fastest; a model with fewer output channels gets zero
    /// rows (weight) and zero entries (bias) for the new last channels, so the grown model's
    /// velocity is the old one's and its head starts at zero (the prior).
    fn grow_output_channels(&self, name: &str, w: &Tensor) -> Result<Option<Tensor>> {
        let m = &self.config.model;
        let area = m.patch * m.patch;
        let new_channels = m.out_channels();
        let rows = w.dim(0)?;
        if rows % area != 0 || rows / area >= new_channels {
            return Ok(None);
        }
        let old_channels = rows / area;
        let grown = match name {
            "final_layer.linear.weight" => {
                let (_, d) = w.dims2()?;
                w.reshape((area, old_channels, d))?
                    .pad_with_zeros(1, 0, new_channels - old_channels)?
                    .reshape((area * new_channels, d))?
            }
            "final_layer.linear.bias" => w
                .reshape((area, old_channels))?
                .pad_with_zeros(1, 0, new_channels - old_channels)?
                .reshape(area * new_channels)?,
            _ => return Ok(None),
        };
        Ok(Some(grown))
    }

    /// Saves a complete checkpoint; `state.json` goes last so a crash mid-way leaves the previous
    /// checkpoint valid... except for the weight files already replaced, which are then one step
    /// ahead of their state: harmless for training.
    pub fn checkpoint(&self, dir: &Path) -> Result<()> {
        let weights: BTreeMap<String, Tensor> = self
            .vars
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect();
        save_tensors(&dir.join("model.safetensors"), &weights)?;
        save_tensors(&dir.join("ema.safetensors"), &self.ema)?;
        let mut opt = BTreeMap::new();
        for (k, m) in &self.opt.m {
            opt.insert(format!("m.{k}"), m.clone());
        }
        for (k, v) in &self.opt.v {
            opt.insert(format!("v.{k}"), v.clone());
        }
        save_tensors(&dir.join("optimizer.safetensors"), &opt)?;
        write_json(&dir.join("state.json"), &self.state)
    }

    /// The training loss of a batch (used by training and by tests): the rectified-flow loss of
    /// the residual, plus, with a mask head, its classification loss
    /// ([`mask_head_loss`]) on the first `mask_head_noise_fraction` of the batch, whose samples are
    /// drawn at t = 1 (pure noise: the head sees only the condition, as at the sampler's first
    /// step, where inference reads it).
    pub fn loss(
        &self,
        data: &PairData,
        indices: &[usize],
        rng: &mut impl Rng,
    ) -> candle_core::Result<Tensor> {
        let cfg = &self.config;
        let m = &cfg.model;
        let b = indices.len();
        let flips: Vec<bool> = (0..b).map(|_| rng.random_bool(0.5)).collect();
        let (target, cond) = data.batch(indices, &flips, &self.device)?;
        let x0 = if m.residual {
            (&target - crate::encode::residual_prior(&cond, m.mask_prior, m.base)?)?
        } else {
            target.clone()
        };
        // Other views for cross-view conditioning (own view with rho = 0 when none is drawn).
        let mut others = Vec::with_capacity(b);
        let mut rho = Vec::with_capacity(b);
        for &i in indices {
            match data
                .random_other_view(i, rng)
                .filter(|_| rng.random_bool(cfg.cross_view_probability))
            {
                Some(j) => {
                    others.push(j);
                    rho.push(rng.random_range(0.0..1.0f32));
                }
                None => {
                    others.push(i);
                    rho.push(0.0);
                }
            }
        }
        let (_, cond_other) = data.batch(&others, &flips, &self.device)?;
        let tokens = self.model.encode(&Tensor::cat(&[&cond, &cond_other], 0)?)?;
        let own = tokens.narrow(0, 0, b)?;
        let other = tokens.narrow(0, b, b)?;
        let cond_tokens = mix_views(&own, &other, &Tensor::from_vec(rho, b, &self.device)?)?;
        let mut times = sample_timesteps(b, cfg.timestep_shift, rng);
        let head_samples = if m.mask_head {
            ((b as f64 * cfg.mask_head_noise_fraction).ceil() as usize).clamp(1, b)
        } else {
            0
        };
        times[..head_samples].fill(1.0);
        let t = Tensor::from_vec(times, b, &self.device)?;
        let eps = randn(x0.shape(), rng, &self.device)?;
        let x_t = interpolate(&x0, &eps, &t)?;
        let out = self.model.forward(&x_t, &t, &cond, &cond_tokens)?;
        let v = out.narrow(3, 0, m.target_channels)?;
        let err = (v - velocity_target(&x0, &eps)?)?.sqr()?;
        let w = &cfg.channel_loss_weights;
        let flow = if w.is_empty() {
            err.mean_all()?
        } else {
            let mean = w.iter().sum::<f32>() / w.len() as f32;
            let w: Vec<f32> = w.iter().map(|x| x / mean).collect();
            let w = Tensor::from_vec(w, (1, 1, 1, m.target_channels), &self.device)?;
            err.broadcast_mul(&w)?.mean_all()?
        };
        if head_samples == 0 {
            return Ok(flow);
        }
        let head = out
            .narrow(3, m.target_channels, 1)?
            .narrow(0, 0, head_samples)?;
        let mask = mask_head_loss(
            &head,
            &cond.narrow(0, 0, head_samples)?,
            &target.narrow(0, 0, head_samples)?,
        )?;
        let loss = (flow + (mask * f64::from(cfg.mask_loss_weight))?)?;
        if !m.mean_head {
            return Ok(loss);
        }
        let mean = out
            .narrow(3, m.target_channels + 1, crate::config::MEAN_CHANNELS)?
            .narrow(0, 0, head_samples)?;
        let residual = x0.narrow(0, 0, head_samples)?;
        let target = target.narrow(0, 0, head_samples)?;
        let cond = cond.narrow(0, 0, head_samples)?;
        let depth_weights = (cfg.depth_loss_metric_width_m > 0.0).then(|| {
            indices[..head_samples]
                .iter()
                .map(|&i| {
                    let width = data.set.crop_width_m.get(i).copied().unwrap_or(f32::NAN);
                    metric_depth_weight(width, cfg.depth_loss_metric_width_m)
                })
                .collect::<Vec<f32>>()
        });
        let l1 = mean_head_loss(
            &mean,
            &residual,
            &target,
            &cond,
            &MeanLossWeights {
                depth: depth_weights.as_deref(),
                far_visible: if cfg.far_side_full_weight {
                    1.0
                } else {
                    MEAN_VISIBLE_WEIGHT
                },
            },
        )?;
        let loss = (loss + (l1 * f64::from(cfg.mean_loss_weight))?)?;
        if !m.error_head {
            return Ok(loss);
        }
        let head = out
            .narrow(
                3,
                m.target_channels + 1 + crate::config::MEAN_CHANNELS,
                crate::config::ERROR_CHANNELS,
            )?
            .narrow(0, 0, head_samples)?;
        let nll = error_head_loss(&head, &mean.detach(), &residual, &target, &cond)?;
        loss + (nll * f64::from(cfg.error_loss_weight))?
    }

    /// One optimisation step on a random batch.
    pub fn step(&mut self, data: &PairData) -> Result<StepReport> {
        let step = self.state.step;
        let mut rng = ChaCha8Rng::seed_from_u64(
            self.config.seed ^ (step as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15),
        );
        let indices: Vec<usize> = (0..self.config.batch_size)
            .map(|_| rng.random_range(0..data.len()))
            .collect();
        let loss = self.loss(data, &indices, &mut rng)?;
        let grads = loss.backward()?;
        let mut g: BTreeMap<String, Tensor> = BTreeMap::new();
        let mut sq = 0f64;
        for (name, var) in &self.vars {
            if let Some(t) = grads.get(var) {
                // One pass on the host instead of three candle ops per parameter.
                sq += flat_f32(t)?
                    .iter()
                    .map(|&x| f64::from(x) * f64::from(x))
                    .sum::<f64>();
                g.insert(name.clone(), t.clone());
            }
        }
        let norm = sq.sqrt();
        if !norm.is_finite() {
            return Err(TrainError::Config(format!(
                "gradient norm is {norm} at step {step}: training diverged"
            )));
        }
        let scale = if norm > self.config.grad_clip {
            self.config.grad_clip / norm
        } else {
            1.0
        };
        let lr = learning_rate(&self.config, step);
        self.opt.step_scaled(
            &self.vars,
            &g,
            scale,
            step + 1,
            lr,
            self.config.weight_decay,
        )?;
        // EMA with a warm-up so early checkpoints are usable.
        let decay = self
            .config
            .ema_decay
            .min((1.0 + step as f64) / (10.0 + step as f64));
        for (name, var) in &self.vars {
            if let Some(e) = self.ema.get_mut(name) {
                let w = var.as_tensor();
                *e = if w.device().is_cpu() && w.dtype() == DType::F32 {
                    let (mut ev, wv) = (flat_f32(e)?, flat_f32(w)?);
                    let (d, rest) = (decay as f32, (1.0 - decay) as f32);
                    for (a, b) in ev.iter_mut().zip(&wv) {
                        *a = d * *a + rest * b;
                    }
                    Tensor::from_vec(ev, w.shape().clone(), w.device())?
                } else {
                    ((&*e * decay)? + (w * (1.0 - decay))?)?.detach()
                };
            }
        }
        let loss = loss.to_scalar::<f32>()?;
        self.state.step += 1;
        self.state.last_loss = loss;
        Ok(StepReport {
            step: self.state.step,
            loss,
            learning_rate: lr,
            grad_norm: norm as f32,
        })
    }

    /// Appends a line to the loss log.
    pub fn log(dir: &Path, r: &StepReport) -> Result<()> {
        let path = dir.join("loss.csv");
        let new = !path.exists();
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|e| file_err(&path, e))?;
        if new {
            writeln!(f, "step,loss,learning_rate,grad_norm").map_err(|e| file_err(&path, e))?;
        }
        writeln!(
            f,
            "{},{},{},{}",
            r.step, r.loss, r.learning_rate, r.grad_norm
        )
        .map_err(|e| file_err(&path, e))
    }

    pub fn ema_weights(&self) -> &BTreeMap<String, Tensor> {
        &self.ema
    }
}

/// Whether the run directory `dir` holds a checkpoint at `steps` or beyond (a finished run; no
/// checkpoint: not started).
pub fn finished(dir: &Path, steps: usize) -> Result<bool> {
    let path = dir.join("state.json");
    if !path.exists() {
        return Ok(false);
    }
    let text = std::fs::read_to_string(&path).map_err(|e| file_err(&path, e))?;
    let state: TrainState = serde_json::from_str(&text).map_err(|e| file_err(&path, e))?;
    Ok(state.step >= steps)
}

/// A training run as `deocc train` makes it: where, with what, from which data.
#[derive(Debug, Clone)]
pub struct TrainRunOptions {
    /// Run directory: created if new, resumed if it holds a checkpoint.
    pub run: PathBuf,
    /// The configuration of a new run (a resumed run keeps its own; only `steps` may change).
    pub config: TrainConfig,
    /// Weights to start a new run from (a folder with `ema.safetensors`), grown by any channel
    /// the new configuration adds.
    pub init: Option<PathBuf>,
    /// Training-pair shards.
    pub shards: Vec<PathBuf>,
    /// At most this many pairs in memory: a seeded draw of shards, drawn again every
    /// `reshuffle_every` steps, so a set larger than memory is used whole over a run.
    pub resident_pairs: usize,
    pub reshuffle_every: usize,
}

/// The shards resident in draw `epoch`: a seeded shuffle, taken until `budget` pairs (each
/// shard's size from `sizes`; at least one shard).
pub fn resident_shards(sizes: &[usize], budget: usize, seed: u64, epoch: u64) -> Vec<usize> {
    let mut order: Vec<usize> = (0..sizes.len()).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ epoch.wrapping_mul(0x2545_f491_4f6c_dd1d));
    for i in (1..order.len()).rev() {
        order.swap(i, rng.random_range(0..=i));
    }
    let mut taken = Vec::new();
    let mut total = 0usize;
    for k in order {
        if !taken.is_empty() && total + sizes[k] > budget {
            continue;
        }
        total += sizes[k];
        taken.push(k);
    }
    taken.sort_unstable();
    taken
}

/// Pairs in each shard (reads the safetensors header only).
fn shard_sizes(shards: &[PathBuf]) -> Result<Vec<usize>> {
    shards
        .iter()
        .map(|p| deocc_io::pairs::count_pairs(p).map_err(|e| file_err(p, e)))
        .collect()
}

/// Trains a run to `config.steps` (resuming it if it has a checkpoint), checkpointing every
/// `checkpoint_every` steps and at the end; `on_step` sees every step (progress, logging).
pub fn train_run(
    opts: &TrainRunOptions,
    device: &Device,
    on_step: &mut dyn FnMut(&Trainer, &StepReport),
) -> Result<TrainState> {
    if opts.shards.is_empty() {
        return Err(TrainError::Config("no training-pair shards".into()));
    }
    if opts.reshuffle_every == 0 || opts.resident_pairs == 0 {
        return Err(TrainError::Config(
            "resident_pairs and reshuffle_every must be positive".into(),
        ));
    }
    let mut trainer = Trainer::open(&opts.run, opts.config.clone(), device)?;
    if let Some(init) = &opts.init {
        if trainer.state.step > 0 {
            return Err(TrainError::Config(format!(
                "--init starts a new run, but {} already holds step {}",
                opts.run.display(),
                trainer.state.step
            )));
        }
        trainer.init_from(&init.join("ema.safetensors"))?;
    }
    let sizes = shard_sizes(&opts.shards)?;
    let prior = trainer.config.model.mask_prior;
    let base = trainer.config.model.base;
    let observed = trainer.config.other_views_observed;
    let load = |epoch: u64| -> Result<PairData> {
        let pick = resident_shards(&sizes, opts.resident_pairs, trainer_seed(opts), epoch);
        let files: Vec<&PathBuf> = pick.iter().map(|&k| &opts.shards[k]).collect();
        let data = PairData::load(&files)
            .map_err(|e| TrainError::Config(e.to_string()))?
            .with_mask_prior(prior)
            .with_base(base)
            .with_seen_elsewhere_share(observed);
        Ok(data)
    };
    let every = opts.reshuffle_every;
    let mut epoch = (trainer.state.step / every) as u64;
    let mut data = load(epoch)?;
    if data.resolution() != trainer.config.model.resolution {
        return Err(TrainError::Config(format!(
            "pairs are {0}x{0} but the model takes {1}x{1}",
            data.resolution(),
            trainer.config.model.resolution
        )));
    }
    let total = trainer.config.steps;
    while trainer.state.step < total {
        if (trainer.state.step / every) as u64 != epoch {
            epoch = (trainer.state.step / every) as u64;
            data = load(epoch)?;
        }
        let r = trainer.step(&data)?;
        Trainer::log(&opts.run, &r)?;
        on_step(&trainer, &r);
        if r.step % trainer.config.checkpoint_every.max(1) == 0 {
            trainer.checkpoint(&opts.run)?;
        }
    }
    trainer.checkpoint(&opts.run)?;
    Ok(trainer.state.clone())
}

fn trainer_seed(opts: &TrainRunOptions) -> u64 {
    opts.config.seed
}
