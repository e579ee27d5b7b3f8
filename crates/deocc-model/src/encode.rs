//! GL-DoT's channel encoding, written once: the training pairs ([`crate::data`]) and inference
//! ([`crate::infer`]) both turn plain [`CropCondition`]s into tensors here.
//!
//! Condition channels (channels last, [`COND_CHANNELS`]):
//! 0-2 crop RGB `v / 127.5 - 1` (-1 outside the image), 3 visible mask `+-1`, 4 visible relative
//! depth x [`DEPTH_SCALE`] (0 elsewhere), 5 scene relative depth x [`DEPTH_SCALE`] (clamped to
//! [-1, 1] before scaling, 0 where unmeasured), 6 the geometric prior of the model's
//! [`MaskPrior`] `+-1`, 7-9 the nearest visible colour, 10 the rules completer's near side (the
//! visible depth, and the plane through it elsewhere) and 11 its far side (symmetric inside the
//! prior, the near side outside it), relative depth x [`DEPTH_SCALE`]: the residual base of
//! `base: rules` models
//! ([`crate::config::ResidualBase`]). Models read the first `cond_channels` of them, so weights
//! trained before a channel was added keep working.
//!
//! Target channels ([`TARGET_CHANNELS`]): RGB `v / 127.5 - 1`, amodal mask `2 m - 1`, near-side and
//! far-side relative depth x [`DEPTH_SCALE`].

use candle_core::{Device, Result, Tensor};
use deocc_completion::rules::{nearest_visible_colour, RulesCompleter};
use deocc_completion::{CropCondition, MaskPrior};

use crate::config::ResidualBase;

/// Relative depth is (d - median visible) / crop width: about +-0.5; doubled to fill [-1, 1].
pub const DEPTH_SCALE: f32 = 2.0;
pub const TARGET_CHANNELS: usize = 6;
pub const COND_CHANNELS: usize = 12;

/// The mask head's logit on a prior pixel with a zero head (minus this off the prior): the
/// prior at probability 0.88.
pub const PRIOR_LOGIT: f32 = 2.0;

/// Writes one crop's condition channels into `out` (r*r*[`COND_CHANNELS`]), channel 6 carrying
/// the prior of kind `prior`.
pub fn write_condition(c: &CropCondition, prior: MaskPrior, out: &mut [f32]) {
    let prior_mask = c.prior_of(prior);
    for (k, o) in out.chunks_exact_mut(COND_CHANNELS).enumerate() {
        for (o, &v) in o[..3].iter_mut().zip(&c.rgb[3 * k..3 * k + 3]) {
            *o = v as f32 / 127.5 - 1.0;
        }
        o[3] = if c.visible[k] { 1.0 } else { -1.0 };
        o[4] = if c.visible[k] {
            c.visible_depth[k] * DEPTH_SCALE
        } else {
            0.0
        };
        o[5] = c.scene_depth[k] * DEPTH_SCALE;
        o[6] = if prior_mask[k] { 1.0 } else { -1.0 };
    }
    // The rules base (channels 7-11) over the whole crop: the nearest visible colour and the
    // plane near side everywhere, the symmetric far side inside the default prior and the near
    // side outside it. A completer's mask may reach beyond the prior; its colour and depth start
    // from the rules there too.
    let rules = RulesCompleter {
        resolution: c.resolution,
        ..RulesCompleter::default()
    }
    .complete_one(c);
    let seen = c.observed();
    let fill = nearest_visible_colour(&seen.rgb, &seen.mask, c.resolution);
    for (k, o) in out.chunks_exact_mut(COND_CHANNELS).enumerate() {
        for (o, &v) in o[7..10].iter_mut().zip(&fill[3 * k..3 * k + 3]) {
            *o = v as f32 / 127.5 - 1.0;
        }
        o[10] = rules.depth[k] * DEPTH_SCALE;
        o[11] = if rules.amodal[k] {
            rules.back_depth[k]
        } else {
            rules.depth[k]
        } * DEPTH_SCALE;
    }
}

/// For `base: rules` training targets: outside the object the colour and depth targets are the
/// base itself (the residual is zero there: nothing outside the object is ever used), so the
/// model spends nothing on painting the background. `target` (r*r*[`TARGET_CHANNELS`]) and
/// `cond` (r*r*[`COND_CHANNELS`]) of one sample.
pub fn base_outside_object(target: &mut [f32], cond: &[f32]) {
    for (t, c) in target
        .chunks_exact_mut(TARGET_CHANNELS)
        .zip(cond.chunks_exact(COND_CHANNELS))
    {
        if t[3] <= 0.0 {
            t[..3].copy_from_slice(&c[7..10]);
            t[4] = c[10];
            t[5] = c[11];
        }
    }
}

/// A whole object as a training target: what the renderer knows and no sensor sees.
#[derive(Debug, Clone, Copy)]
pub struct TargetView<'a> {
    /// (r*r*3) the object alone on white.
    pub rgb: &'a [u8],
    /// (r*r) its amodal mask, 0/1.
    pub amodal: &'a [u8],
    /// (r*r) near-side relative depth.
    pub depth: &'a [f32],
    /// (r*r) far-side relative depth.
    pub back_depth: &'a [f32],
}

/// Writes one target's channels into `out` (r*r*[`TARGET_CHANNELS`]); with `mirror` the target is
/// mirrored left to right (as [`CropCondition::mirrored`] mirrors its condition).
pub fn write_target(t: &TargetView<'_>, r: usize, mirror: bool, out: &mut [f32]) {
    for v in 0..r {
        for u in 0..r {
            let p = v * r + if mirror { r - 1 - u } else { u };
            let o = &mut out[(v * r + u) * TARGET_CHANNELS..(v * r + u + 1) * TARGET_CHANNELS];
            for (o, &v) in o[..3].iter_mut().zip(&t.rgb[3 * p..3 * p + 3]) {
                *o = v as f32 / 127.5 - 1.0;
            }
            o[3] = 2.0 * t.amodal[p] as f32 - 1.0;
            o[4] = t.depth[p] * DEPTH_SCALE;
            o[5] = t.back_depth[p] * DEPTH_SCALE;
        }
    }
}

/// Stacks crops' conditions into a (B, R, R, [`COND_CHANNELS`]) tensor.
pub fn condition_tensor(
    crops: &[&CropCondition],
    prior: MaskPrior,
    device: &Device,
) -> Result<Tensor> {
    let r = crops.first().map(|c| c.resolution).unwrap_or(0);
    if let Some(c) = crops.iter().find(|c| c.resolution != r) {
        candle_core::bail!(
            "crops of one batch must share a resolution: {r} and {}",
            c.resolution
        );
    }
    let n = r * r;
    let mut data = vec![0f32; crops.len() * n * COND_CHANNELS];
    for (c, out) in crops.iter().zip(data.chunks_exact_mut(n * COND_CHANNELS)) {
        write_condition(c, prior, out);
    }
    Tensor::from_vec(data, (crops.len(), r, r, COND_CHANNELS), device)
}

/// The residual base of a condition batch (B, R, R, [`COND_CHANNELS`]) in target channels (B, R, R,
/// 6): what the model's output is with a zero residual.
///
/// - [`ResidualBase::Visible`]: the crop's RGB on the visible pixels and white elsewhere, the
///   mask of `mask_prior` (the visible mask, channel 3, or the geometric prior, channel 6), and
///   the visible depth for both the near and the far side: the "amodal = visible" answer, exact
///   on every pixel an occluder does not hide.
/// - [`ResidualBase::Rules`]: the rules completion of channels 7-11 and the prior mask.
pub fn residual_prior(cond: &Tensor, mask_prior: MaskPrior, base: ResidualBase) -> Result<Tensor> {
    let mask = match mask_prior {
        MaskPrior::Visible => cond.narrow(3, 3, 1)?,
        MaskPrior::HullInFront | MaskPrior::EllipseInFront | MaskPrior::EllipseOrBoxInFront => {
            cond.narrow(3, 6, 1)?
        }
    };
    match base {
        ResidualBase::Visible => {
            let rgb = cond.narrow(3, 0, 3)?;
            let vis_mask = cond.narrow(3, 3, 1)?;
            let depth = cond.narrow(3, 4, 1)?;
            let vis = ((&vis_mask + 1.0)? * 0.5)?; // {0, 1}
            let white = (vis.neg()? + 1.0)?;
            let prior_rgb = rgb.broadcast_mul(&vis)?.broadcast_add(&white)?;
            let prior_depth = depth.mul(&vis)?;
            Tensor::cat(&[&prior_rgb, &mask, &prior_depth, &prior_depth], 3)
        }
        ResidualBase::Rules => Tensor::cat(
            &[
                &cond.narrow(3, 7, 3)?,
                &mask,
                &cond.narrow(3, 10, 1)?,
                &cond.narrow(3, 11, 1)?,
            ],
            3,
        ),
    }
}
