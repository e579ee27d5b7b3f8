//! Using a trained GL-DoT: load weights and complete crops in a few steps. [`GlDotCompleter`]
//! is the pipeline's learned [`deocc_completion::Completer`].

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use crate::config::GlDotConfig;
use crate::encode::{
    condition_tensor, residual_prior, COND_CHANNELS, DEPTH_SCALE, PRIOR_LOGIT, TARGET_CHANNELS,
};
use crate::flow::euler_sample;
use crate::init::randn;
use crate::model::{mix_views, GlDot};
use crate::train::{Result, TrainConfig, TrainError};
use rand::SeedableRng;

/// Margin of the free-space constraint, in relative depth (crop widths).
pub const FREE_SPACE_MARGIN: f32 = 0.05;

/// Crops wider than this at the object's depth are declined by default: at 64 pixels a crop of
/// furniture has 3+ cm pixels and the model's relative-depth error becomes decimetres (measured:
/// mean errors 0.1-0.6 m on shelves and segments of them, against 1-3 cm on table-top objects).
pub const DEFAULT_MAX_CROP_WIDTH_M: f32 = 0.6;

/// A loaded model ready to sample.
pub struct GlDotCompleter {
    pub model: GlDot,
    pub timestep_shift: f32,
    /// A pixel is in the amodal mask when the mask channel (in [-1, 1]) is above this.
    pub mask_threshold: f32,
    /// The threshold for crops that carry the other views' observations (at least one point);
    /// `None` = `mask_threshold` ([`crate::train::TrainConfig::mask_threshold_seen_elsewhere`]).
    /// Applied by [`GlDotCompleter::finish`].
    pub mask_threshold_seen_elsewhere: Option<f32>,
    /// Free-space constraint: a hidden pixel can belong to the object only where the observed
    /// scene is in front of the object's predicted near side (plus [`FREE_SPACE_MARGIN`]); where
    /// the scene is seen behind it, the object would have been seen. Uses the condition's
    /// scene-depth channel (index 5).
    pub free_space: bool,
    /// Samples averaged per completion (each `steps` steps from its own noise; every second one
    /// on the mirrored crop, mirrored back): the mask channel's average is a less noisy score
    /// than one sample's. 1 = a single sample.
    pub samples: usize,
    /// Keep every pixel of the geometric prior (condition channel 6) in the amodal mask whatever
    /// the mask channel says there; the model only adds pixels. On validation pairs the models'
    /// removals of prior pixels were wrong two times in three (`mask_decisions` example).
    pub keep_prior: bool,
    /// Crops wider than this (metres, at the object's depth) are declined and go to the next
    /// completer of the chain ([`DEFAULT_MAX_CROP_WIDTH_M`]).
    pub max_crop_width_m: f32,
    /// With a mean head: colour and depth from the mean head at the first step (one forward
    /// pass; the default), or, off, from the flow's sample after all steps.
    pub reads_mean: bool,
    pub device: Device,
}

/// One completed crop.
#[derive(Debug, Clone)]
pub struct Completion {
    /// (R*R*3) RGB of the whole object on white.
    pub rgb: Vec<u8>,
    /// (R*R) amodal mask: the mask channel above the completer's threshold, or visible.
    pub amodal: Vec<bool>,
    /// (R*R) the mask channel itself, in [-1, 1] roughly (for choosing the threshold); -inf where
    /// the free-space constraint rules the object out.
    pub mask_score: Vec<f32>,
    /// (R*R) relative depth of the near side (the training pairs' units), meaningful inside `amodal`.
    pub depth_rel: Vec<f32>,
    /// (R*R) relative depth of the far side (the object's back).
    pub back_depth_rel: Vec<f32>,
    /// The error head's expected absolute error of `depth_rel` and `back_depth_rel` (relative
    /// depth), for models with one read through the mean head.
    pub expected_error: Option<deocc_completion::ExpectedDepthError>,
}

impl GlDotCompleter {
    /// From a weights file (safetensors, f32 or f16) and the `train.json` or model config beside it.
    pub fn load(
        weights: &Path,
        config: &GlDotConfig,
        timestep_shift: f32,
        device: &Device,
    ) -> Result<Self> {
        // The header first: a file that is not weights is refused before it is read.
        deocc_io::weights::check_safetensors(weights, crate::depth_anything::MAX_WEIGHTS_BYTES)
            .map_err(|e| TrainError::File {
                path: weights.to_path_buf(),
                msg: e.to_string(),
            })?;
        let tensors =
            candle_core::safetensors::load(weights, device).map_err(|e| TrainError::File {
                path: weights.to_path_buf(),
                msg: e.to_string(),
            })?;
        Self::from_tensors(tensors, config, timestep_shift, device).map_err(|e| TrainError::File {
            path: weights.to_path_buf(),
            msg: e.to_string(),
        })
    }

    /// From loaded tensors (any float type).
    pub fn from_tensors(
        tensors: HashMap<String, Tensor>,
        config: &GlDotConfig,
        timestep_shift: f32,
        device: &Device,
    ) -> Result<Self> {
        let tensors: HashMap<String, Tensor> = tensors
            .into_iter()
            .map(|(k, v)| Ok((k, v.to_dtype(DType::F32)?)))
            .collect::<candle_core::Result<_>>()?;
        let sorted: std::collections::BTreeMap<String, Tensor> = tensors
            .iter()
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect();
        if let Some(bad) = crate::train::check_finite(&sorted)? {
            return Err(TrainError::Config(format!(
                "tensor {bad} has non-finite values (NaN or infinite): the weights are broken"
            )));
        }
        let vb = VarBuilder::from_tensors(tensors, DType::F32, device);
        let model = GlDot::new(config, vb).map_err(|e| {
            TrainError::Config(format!("weights do not fit the model configuration: {e}"))
        })?;
        Ok(Self {
            model,
            timestep_shift,
            mask_threshold: 0.0,
            mask_threshold_seen_elsewhere: None,
            free_space: true,
            samples: 1,
            keep_prior: false,
            max_crop_width_m: DEFAULT_MAX_CROP_WIDTH_M,
            reads_mean: true,
            device: device.clone(),
        })
    }

    /// Applies the inference fields of a training config (mask rule, samples).
    fn with_inference_config(mut self, cfg: &TrainConfig) -> Self {
        self.mask_threshold = cfg.mask_threshold;
        self.mask_threshold_seen_elsewhere = cfg.mask_threshold_seen_elsewhere;
        self.samples = cfg.inference_samples.max(1);
        self.keep_prior = cfg.mask_keeps_prior;
        self.reads_mean = cfg.inference_reads_mean;
        self
    }

    /// From a run directory (EMA weights) or a folder holding `model.safetensors` + `train.json`.
    pub fn from_dir(dir: &Path, device: &Device) -> Result<Self> {
        let cfg = TrainConfig::read(&dir.join("train.json"))?;
        let weights = if dir.join("ema.safetensors").exists() {
            dir.join("ema.safetensors")
        } else {
            dir.join("model.safetensors")
        };
        Ok(
            Self::load(&weights, &cfg.model, cfg.timestep_shift, device)?
                .with_inference_config(&cfg),
        )
    }

    /// From a `train.json` text and safetensors bytes (the weights built into the binary).
    pub fn from_bytes(train_json: &str, safetensors: &[u8], device: &Device) -> Result<Self> {
        let cfg = TrainConfig::from_json(train_json)
            .map_err(|e| TrainError::Config(format!("built-in train.json: {e}")))?;
        let tensors = candle_core::safetensors::load_buffer(safetensors, device)?;
        Ok(
            Self::from_tensors(tensors, &cfg.model, cfg.timestep_shift, device)?
                .with_inference_config(&cfg),
        )
    }

    /// One sample of the whole target (B, R, R, 6), the residual prior added back.
    fn sample_x0(
        &self,
        cond: &Tensor,
        other_views: &[Vec<Tensor>],
        rho: f32,
        steps: usize,
        seed: u64,
    ) -> Result<Tensor> {
        let (b, r, _, _) = cond.dims4()?;
        let own = self.model.encode(cond)?;
        let tokens = if other_views.iter().any(|v| !v.is_empty()) && rho > 0.0 {
            let mut means = Vec::with_capacity(b);
            let mut rhos = Vec::with_capacity(b);
            for k in 0..b {
                let views = other_views.get(k).filter(|v| !v.is_empty());
                match views {
                    Some(v) => {
                        let t = self.model.encode(&Tensor::cat(v, 0)?)?; // (V, M, D)
                        means.push(t.mean_keepdim(0)?);
                        rhos.push(rho);
                    }
                    None => {
                        means.push(own.narrow(0, k, 1)?);
                        rhos.push(0.0);
                    }
                }
            }
            mix_views(
                &own,
                &Tensor::cat(&means, 0)?,
                &Tensor::from_vec(rhos, b, &self.device)?,
            )?
        } else {
            own
        };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let noise = randn((b, r, r, TARGET_CHANNELS), &mut rng, &self.device)?;
        let cfg = &self.model.config;
        if cfg.mean_head && self.reads_mean {
            // One forward pass at t = 1: the mask head and the mean head, as they were trained.
            let tc = cfg.target_channels;
            let tt = Tensor::full(1f32, b, &self.device)?;
            let out = self.model.forward(&noise, &tt, cond, &tokens)?;
            let head = out.narrow(3, tc, 1)?;
            let mean = out.narrow(3, tc + 1, crate::config::MEAN_CHANNELS)?;
            let residual = Tensor::cat(
                &[
                    &mean.narrow(3, 0, 3)?,
                    &head.zeros_like()?,
                    &mean.narrow(3, 3, 2)?,
                ],
                3,
            )?;
            let x0 = (residual + residual_prior(cond, cfg.mask_prior, cfg.base)?)?;
            let logit = (head + (cond.narrow(3, 6, 1)? * f64::from(PRIOR_LOGIT))?)?;
            if cfg.error_head {
                // The error head's log scale (its exp is taken per pixel after averaging).
                let log_error = (out.narrow(
                    3,
                    tc + 1 + crate::config::MEAN_CHANNELS,
                    crate::config::ERROR_CHANNELS,
                )? + f64::from(crate::config::ERROR_LOG_OFFSET))?;
                return Ok(Tensor::cat(&[&x0, &logit, &log_error], 3)?);
            }
            return Ok(Tensor::cat(&[&x0, &logit], 3)?);
        }
        // The mask head is read at the first step (t = 1, pure noise), as it was trained.
        let mut head: Option<Tensor> = None;
        let x0 = euler_sample(&noise, steps, self.timestep_shift, |x, t| {
            let tt = Tensor::full(t, b, &self.device)?;
            let out = self.model.forward(x, &tt, cond, &tokens)?;
            if !cfg.mask_head {
                return Ok(out);
            }
            if head.is_none() {
                head = Some(out.narrow(3, cfg.target_channels, 1)?);
            }
            out.narrow(3, 0, cfg.target_channels)
        })?;
        let x0 = if cfg.residual {
            (x0 + residual_prior(cond, cfg.mask_prior, cfg.base)?)?
        } else {
            x0
        };
        match head {
            Some(h) => {
                let logit = (h + (cond.narrow(3, 6, 1)? * f64::from(PRIOR_LOGIT))?)?;
                Ok(Tensor::cat(&[&x0, &logit], 3)?)
            }
            None => Ok(x0),
        }
    }

    /// The completer's mask rule for one pixel at a given threshold: visible pixels are in, prior
    /// pixels (condition channel 6) too when the prior is kept, and others when their mask score
    /// is above the threshold.
    pub fn in_mask(&self, score: f32, visible: bool, prior: bool, threshold: f32) -> bool {
        visible || (self.keep_prior && prior) || score > threshold
    }

    pub fn resolution(&self) -> usize {
        self.model.config.resolution
    }

    /// The mask threshold for one crop: [`GlDotCompleter::mask_threshold_seen_elsewhere`] where
    /// the condition carries at least one point another view observed, else `mask_threshold`.
    pub fn threshold_for(&self, c: &deocc_completion::CropCondition) -> f32 {
        match self.mask_threshold_seen_elsewhere {
            Some(th) if has_seen_elsewhere(c) => th,
            _ => self.mask_threshold,
        }
    }

    /// Finishes a completion of crop `c` as the pipeline's completer does: the mask at the
    /// crop's threshold ([`GlDotCompleter::threshold_for`]; [`GlDotCompleter::complete`] applies
    /// `mask_threshold` to every crop), then the other views' observations win
    /// ([`Completion::keep_seen_elsewhere`]).
    pub fn finish(&self, comp: &mut Completion, c: &deocc_completion::CropCondition) {
        let th = self.threshold_for(c);
        if th != self.mask_threshold {
            // The prior the condition tensor carried (channel 6), read only when it is kept.
            let prior = if self.keep_prior {
                c.prior_of(self.model.config.mask_prior)
            } else {
                vec![false; c.pixels()]
            };
            for (k, a) in comp.amodal.iter_mut().enumerate() {
                *a = self.in_mask(comp.mask_score[k], c.visible[k], prior[k], th);
            }
        }
        comp.keep_seen_elsewhere(c);
    }

    /// Completes a batch. `cond` (B, R, R, 7) as built by [`crate::encode::condition_tensor`];
    /// `other_views[k]` are condition images of other views of sample k's object, mixed in with
    /// weight `rho`. Deterministic given `seed`.
    pub fn complete(
        &self,
        cond: &Tensor,
        other_views: &[Vec<Tensor>],
        rho: f32,
        steps: usize,
        seed: u64,
    ) -> Result<Vec<Completion>> {
        self.complete_with(cond, other_views, rho, steps, seed, self.free_space)
    }

    /// [`GlDotCompleter::complete`] with the free-space constraint on or off.
    pub fn complete_with(
        &self,
        cond: &Tensor,
        other_views: &[Vec<Tensor>],
        rho: f32,
        steps: usize,
        seed: u64,
        free_space: bool,
    ) -> Result<Vec<Completion>> {
        let (b, r, _, c) = cond.dims4()?;
        if c != COND_CHANNELS || r != self.resolution() {
            // Data carries COND_CHANNELS; the model reads the first `cond_channels` of them.
            return Err(TrainError::Config(format!(
                "condition must be (B, {r0}, {r0}, {COND_CHANNELS}), got {:?}",
                cond.dims(),
                r0 = self.resolution()
            )));
        }
        // Every sample in one batch (odd ones mirrored left to right, and mirrored back): one
        // forward pass of B x samples crops costs less than `samples` passes of B.
        let samples = self.samples.max(1);
        let flipped = if samples > 1 {
            let others = other_views
                .iter()
                .map(|v| {
                    v.iter()
                        .map(flip_width)
                        .collect::<candle_core::Result<Vec<_>>>()
                })
                .collect::<candle_core::Result<Vec<_>>>()?;
            Some((flip_width(cond)?, others))
        } else {
            None
        };
        let mut conds = Vec::with_capacity(samples);
        // Sample i's crop k reads the other views at i * B + k (none where `other_views` is
        // shorter than the batch).
        let mut others: Vec<Vec<Tensor>> = Vec::with_capacity(samples * b);
        for i in 0..samples {
            let (c, o) = match (&flipped, i % 2 == 1) {
                (Some((fc, fo)), true) => (fc, fo.as_slice()),
                _ => (cond, other_views),
            };
            conds.push(c.clone());
            others.extend((0..b).map(|k| o.get(k).cloned().unwrap_or_default()));
        }
        let all = self.sample_x0(&Tensor::cat(&conds, 0)?, &others, rho, steps, seed)?;
        let mut sum: Option<Tensor> = None;
        for i in 0..samples {
            let x = all.narrow(0, i * b, b)?;
            let x = if i % 2 == 1 { flip_width(&x)? } else { x };
            sum = Some(match sum {
                None => x,
                Some(acc) => (acc + x)?,
            });
        }
        let x0 = match sum {
            Some(acc) if samples > 1 => (acc / samples as f64)?,
            Some(acc) => acc,
            None => unreachable!("at least one sample is drawn"),
        };
        let data = x0.flatten_all()?.to_vec1::<f32>()?;
        let cond_data = cond.flatten_all()?.to_vec1::<f32>()?;
        let n = r * r;
        let oc = x0.dim(3)?;
        let head = self.model.config.mask_head;
        // The error head's two channels follow the mask logit when the mean head was read.
        let error_at =
            (self.model.config.error_head && self.reads_mean && oc >= TARGET_CHANNELS + 3)
                .then_some(TARGET_CHANNELS + 1);
        Ok((0..b)
            .map(|k| {
                let px = &data[k * n * oc..(k + 1) * n * oc];
                let cx = &cond_data[k * n * COND_CHANNELS..(k + 1) * n * COND_CHANNELS];
                let mask_score: Vec<f32> = px
                    .chunks_exact(oc)
                    .zip(cx.chunks_exact(COND_CHANNELS))
                    .map(|(p, c)| {
                        if head {
                            // The head's probability, on the pixels where a hidden part can be
                            // (the scene in front of the object's median depth).
                            let candidate = c[3] <= 0.0 && c[5] < 0.0;
                            if c[3] > 0.0 {
                                1.0
                            } else if free_space && !candidate {
                                f32::NEG_INFINITY
                            } else {
                                sigmoid(p[TARGET_CHANNELS])
                            }
                        } else {
                            let behind = c[5] > p[4] + FREE_SPACE_MARGIN * DEPTH_SCALE;
                            if free_space && c[3] <= 0.0 && behind {
                                f32::NEG_INFINITY
                            } else {
                                p[3]
                            }
                        }
                    })
                    .collect();
                Completion {
                    rgb: px
                        .chunks_exact(oc)
                        .flat_map(|p| {
                            (0..3)
                                .map(|c| ((p[c] + 1.0) * 127.5).round().clamp(0.0, 255.0) as u8)
                                .collect::<Vec<_>>()
                        })
                        .collect(),
                    // The amodal mask contains the visible mask by definition.
                    amodal: mask_score
                        .iter()
                        .zip(cx.chunks_exact(COND_CHANNELS))
                        .map(|(&m, c)| self.in_mask(m, c[3] > 0.0, c[6] > 0.0, self.mask_threshold))
                        .collect(),
                    mask_score,
                    depth_rel: px.chunks_exact(oc).map(|p| p[4] / DEPTH_SCALE).collect(),
                    back_depth_rel: px.chunks_exact(oc).map(|p| p[5] / DEPTH_SCALE).collect(),
                    expected_error: error_at.map(|e| deocc_completion::ExpectedDepthError {
                        near: px.chunks_exact(oc).map(|p| p[e].exp()).collect(),
                        far: px.chunks_exact(oc).map(|p| p[e + 1].exp()).collect(),
                    }),
                }
            })
            .collect())
    }
}

/// Whether a crop carries at least one point another view observed.
pub fn has_seen_elsewhere(c: &deocc_completion::CropCondition) -> bool {
    c.seen_elsewhere
        .as_ref()
        .is_some_and(|s| s.depth.iter().any(|d| d.is_finite()))
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Mirrors images (B, H, W, C) left to right.
fn flip_width(x: &Tensor) -> candle_core::Result<Tensor> {
    let w = x.dim(2)?;
    let reversed: Vec<u32> = (0..w as u32).rev().collect();
    x.index_select(&Tensor::from_vec(reversed, w, x.device())?, 2)
}

impl deocc_completion::Completer for GlDotCompleter {
    fn name(&self) -> &str {
        "gldot"
    }
    /// A model with a mean head read at the first step (the shipped one) answers in one forward
    /// pass: its steps setting changes nothing.
    fn uses_steps(&self) -> bool {
        !(self.model.config.mean_head && self.reads_mean)
    }

    fn provenance(&self) -> deocc_completion::Provenance {
        deocc_completion::Provenance::Model
    }

    fn resolution(&self) -> usize {
        self.model.config.resolution
    }

    fn decline(&self, c: &deocc_completion::CropCondition) -> Option<String> {
        let w = c.crop_width_m?;
        (w > self.max_crop_width_m).then(|| {
            format!(
                "crop {w:.2} m wide, more than {:.2} m at {} px",
                self.max_crop_width_m,
                self.resolution()
            )
        })
    }

    fn complete(
        &self,
        batch: &[deocc_completion::CropRequest<'_>],
        opts: &deocc_completion::CompletionOptions,
    ) -> std::result::Result<Vec<deocc_completion::CropCompletion>, deocc_completion::CompletionError>
    {
        let fail = |e: &dyn std::fmt::Display| deocc_completion::CompletionError::Failed {
            completer: "gldot".into(),
            msg: e.to_string(),
        };
        if batch.is_empty() {
            return Ok(Vec::new());
        }
        if let Some(bad) = batch
            .iter()
            .find(|r| r.condition.resolution != self.resolution())
        {
            return Err(deocc_completion::CompletionError::Input {
                completer: "gldot".into(),
                msg: format!(
                    "crop of {} px, the model takes {} px",
                    bad.condition.resolution,
                    self.resolution()
                ),
            });
        }
        let prior = self.model.config.mask_prior;
        let conds: Vec<&deocc_completion::CropCondition> =
            batch.iter().map(|r| r.condition).collect();
        let cond = condition_tensor(&conds, prior, &self.device).map_err(|e| fail(&e))?;
        let others = batch
            .iter()
            .map(|r| {
                r.other_views
                    .iter()
                    .map(|o| condition_tensor(&[o], prior, &self.device))
                    .collect::<candle_core::Result<Vec<_>>>()
            })
            .collect::<candle_core::Result<Vec<_>>>()
            .map_err(|e| fail(&e))?;
        let done = self
            .complete(&cond, &others, opts.rho, opts.steps, opts.seed)
            .map_err(|e| fail(&e))?;
        Ok(done
            .into_iter()
            .zip(batch)
            .map(|(mut c, req)| {
                self.finish(&mut c, req.condition);
                c.into_crop_completion(&req.condition.visible, self.model.config.mask_head)
            })
            .collect())
    }
}

impl Completion {
    /// Where other views observed the object ([`CropCondition::seen_elsewhere`]), their
    /// observation wins over the generated one, as the visible pixels' does: the pixel is in the
    /// mask, with their colour and near-side depth (the far side stays generated).
    ///
    /// [`CropCondition::seen_elsewhere`]: deocc_completion::CropCondition::seen_elsewhere
    pub fn keep_seen_elsewhere(&mut self, c: &deocc_completion::CropCondition) {
        let Some(seen) = &c.seen_elsewhere else {
            return;
        };
        for (k, &d) in seen.depth.iter().enumerate() {
            if d.is_finite() && k < self.amodal.len() {
                self.amodal[k] = true;
                self.mask_score[k] = self.mask_score[k].max(1.0);
                self.depth_rel[k] = d;
                self.rgb[3 * k..3 * k + 3].copy_from_slice(&seen.rgb[3 * k..3 * k + 3]);
                if let Some(e) = self.expected_error.as_mut() {
                    e.near[k] = 0.0; // observed
                }
            }
        }
    }

    /// The plain-data completion of the pipeline's seam. A mask head's score is a probability;
    /// the flow model's mask channel is not, and `(score + 1) / 2` clamped to [0, 1] stands in
    /// for one (1 on visible pixels, 0 where the free-space constraint rules the object out).
    pub fn into_crop_completion(
        self,
        visible: &[bool],
        score_is_probability: bool,
    ) -> deocc_completion::CropCompletion {
        let mask_probability = self
            .mask_score
            .iter()
            .zip(visible)
            .map(|(&s, &v)| {
                if v {
                    1.0
                } else if score_is_probability {
                    s.clamp(0.0, 1.0)
                } else {
                    ((s + 1.0) / 2.0).clamp(0.0, 1.0)
                }
            })
            .collect();
        deocc_completion::CropCompletion {
            amodal: self.amodal,
            mask_probability,
            rgb: self.rgb,
            depth: self.depth_rel,
            back_depth: self.back_depth_rel,
            expected_error: self.expected_error,
        }
    }
}
