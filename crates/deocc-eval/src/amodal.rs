//! 2-D amodal completion on held-out pairs: the figures of `deocc eval amodal`.
//!
//! Every pair of the split is completed once by GL-DoT (at `main_steps`) and once by the rules
//! completer, and scored against the renderer's ground truth. Every model figure stands beside the
//! strongest non-learned baseline on the same pairs (the geometric prior for the silhouette, the
//! nearest visible colour, the plane through the visible near side, the symmetric far side), as
//! a paired difference with a 95% interval from a bootstrap over objects (the views of one object
//! are resampled together).

use std::collections::BTreeMap;
use std::time::Instant;

use candle_core::Tensor;
use deocc_completion::rules::{nearest_seed, nearest_visible_colour, RulesCompleter};
use deocc_completion::{CropCompletion, CropCondition};
use deocc_geometry::mask2d::{convex_hull_mask, iou};
use deocc_geometry::robust::{huber_affine_fit, HuberOptions};
use deocc_model::data::PairData;
use deocc_model::infer::{Completion, GlDotCompleter};
use deocc_pipeline::fuse::median_within;
use deocc_pipeline::options::depth_median_radius;
use deocc_synth::shapes::Category;
use serde::Serialize;

use crate::stats::{compare, mean, roc_auc, Comparison};
use crate::EvalError;

#[derive(Debug, Clone)]
pub struct AmodalEvalOptions {
    /// Pairs evaluated: the first N of the split; `None` = all.
    pub pairs: Option<usize>,
    /// The step count of every figure but the step sweep.
    pub main_steps: usize,
    /// Step counts of the sweep (four against fifty), on the first `sweep_pairs` pairs.
    pub sweep_steps: Vec<usize>,
    pub sweep_pairs: usize,
    pub rho: f32,
    pub batch: usize,
    pub seed: u64,
    /// Mask thresholds to report the model's main-steps mIoU at (choosing the shipped one on val;
    /// crops carrying other views' points keep the model's seen-elsewhere threshold if it has one).
    pub mask_thresholds: Vec<f32>,
    /// Thresholds of the crops carrying other views' points to report the mIoU at, the other
    /// crops at the model's threshold (choosing `mask_threshold_seen_elsewhere` on val).
    pub mask_thresholds_seen_elsewhere: Vec<f32>,
    pub bootstrap_resamples: usize,
    /// Skip the cross-view run (half the time).
    pub skip_cross_view: bool,
    /// Median filter radius (pixels; 0 = off) of the model's near and far depth over its amodal
    /// mask before scoring, as the pipeline's `completers.gldot.depth_median_px` does before fusion.
    pub depth_median_px: usize,
    /// The filter applies only to pairs whose crop is no wider than this (metres; 0 = every
    /// pair), as the pipeline's `completers.gldot.depth_median_max_crop_m`: the pairs must carry
    /// their crop width (`crop_width_m`, stored since it was added).
    pub depth_median_max_crop_m: f32,
}

impl Default for AmodalEvalOptions {
    fn default() -> Self {
        Self {
            pairs: None,
            main_steps: 4,
            sweep_steps: vec![1, 4, 50],
            sweep_pairs: 300,
            rho: 0.5,
            batch: 16,
            seed: 0,
            mask_thresholds: Vec::new(),
            mask_thresholds_seen_elsewhere: Vec::new(),
            bootstrap_resamples: 1000,
            skip_cross_view: false,
            depth_median_px: 0,
            depth_median_max_crop_m: 0.0,
        }
    }
}

/// A group of pairs: the model's and the prior's mIoU with the paired interval.
#[derive(Debug, Clone, Serialize)]
pub struct GroupRow {
    pub pairs: usize,
    pub miou_model: f64,
    pub miou_prior: f64,
    pub miou_hull: f64,
    pub model_minus_prior: Comparison,
}

#[derive(Debug, Clone, Serialize)]
pub struct ChairLegs {
    /// The paper's Table 4 rule: chairs whose amodal box's bottom 40% is at least 30% hidden.
    pub pairs: usize,
    pub miou: Comparison,
    /// IoU inside the bottom 40% of the amodal box (the legs).
    pub bottom_region_iou: Comparison,
}

#[derive(Debug, Clone, Serialize)]
pub struct Calibration {
    /// Probability-weighted mean gap between the predicted probability and the share of object
    /// pixels, over ten equal bins.
    pub expected_calibration_error: f64,
    pub bins: Vec<CalibrationBin>,
}

#[derive(Debug, Clone, Serialize)]
pub struct CalibrationBin {
    pub probability_up_to: f64,
    pub pixels: usize,
    pub mean_probability: f64,
    pub object_fraction: f64,
}

/// Ten-bin reliability of probabilities `p` (scores outside [0, 1], such as the free-space
/// constraint's -inf, are clamped) against labels.
pub fn calibration(p: &[f32], labels: &[bool]) -> Calibration {
    let mut acc = vec![(0usize, 0f64, 0usize); 10];
    for (&s, &l) in p.iter().zip(labels) {
        let s = if s.is_nan() { 0.0 } else { s.clamp(0.0, 1.0) };
        let b = ((s * 10.0) as usize).min(9);
        acc[b].0 += 1;
        acc[b].1 += f64::from(s);
        acc[b].2 += l as usize;
    }
    let total = p.len().max(1) as f64;
    let bins: Vec<CalibrationBin> = acc
        .iter()
        .enumerate()
        .map(|(k, &(n, sum, pos))| CalibrationBin {
            probability_up_to: (k + 1) as f64 / 10.0,
            pixels: n,
            mean_probability: sum / n.max(1) as f64,
            object_fraction: pos as f64 / n.max(1) as f64,
        })
        .collect();
    let ece = bins
        .iter()
        .map(|b| b.pixels as f64 / total * (b.mean_probability - b.object_fraction).abs())
        .sum();
    Calibration {
        expected_calibration_error: ece,
        bins,
    }
}

/// Upper edges (crop widths) of the expected-error bins of [`ErrorHeadSide::bins`].
pub const ERROR_BINS: [f32; 6] = [0.01, 0.02, 0.03, 0.05, 0.08, f32::INFINITY];

/// An actual error above this (crop widths) is a "large" one for [`ErrorHeadSide::auc_large`].
pub const LARGE_ERROR: f32 = 0.05;

#[derive(Debug, Clone, Serialize)]
pub struct ErrorHeadFigures {
    pub near_hidden: ErrorHeadSide,
    pub far: ErrorHeadSide,
}

#[derive(Debug, Clone, Serialize)]
pub struct ErrorHeadSide {
    pub pixels: usize,
    /// Mean expected and mean actual absolute error (crop widths).
    pub mean_expected: f64,
    pub mean_actual: f64,
    /// How well the expected error ranks the pixels whose actual error is above
    /// [`LARGE_ERROR`] (0.5 = not at all).
    pub auc_large: f64,
    pub bins: Vec<ErrorBin>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ErrorBin {
    /// Upper edge of the expected error (crop widths); `None` = no limit.
    pub expected_up_to: Option<f32>,
    pub pixels: usize,
    pub mean_expected: f64,
    pub mean_actual: f64,
    pub share_large: f64,
}

/// The error head's figures on (expected, actual) pixel errors.
pub fn error_head_side(pairs: &[(f32, f32)]) -> ErrorHeadSide {
    let mut acc = vec![(0usize, 0f64, 0f64, 0usize); ERROR_BINS.len()];
    for &(e, a) in pairs {
        let b = ERROR_BINS
            .iter()
            .position(|&hi| e <= hi)
            .unwrap_or(ERROR_BINS.len() - 1);
        acc[b].0 += 1;
        acc[b].1 += f64::from(e);
        acc[b].2 += f64::from(a);
        acc[b].3 += (a > LARGE_ERROR) as usize;
    }
    let n = pairs.len().max(1) as f64;
    let expected: Vec<f32> = pairs.iter().map(|p| p.0).collect();
    let large: Vec<bool> = pairs.iter().map(|p| p.1 > LARGE_ERROR).collect();
    ErrorHeadSide {
        pixels: pairs.len(),
        mean_expected: pairs.iter().map(|p| f64::from(p.0)).sum::<f64>() / n,
        mean_actual: pairs.iter().map(|p| f64::from(p.1)).sum::<f64>() / n,
        auc_large: crate::stats::roc_auc(&expected, &large),
        bins: ERROR_BINS
            .iter()
            .zip(&acc)
            .map(|(&hi, &(k, e, a, l))| ErrorBin {
                expected_up_to: hi.is_finite().then_some(hi),
                pixels: k,
                mean_expected: e / k.max(1) as f64,
                mean_actual: a / k.max(1) as f64,
                share_large: l as f64 / k.max(1) as f64,
            })
            .collect(),
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct CandidateAuc {
    /// Candidate pixels (not visible, the scene in front of the object): where a completer
    /// chooses.
    pub pixels: usize,
    pub object_fraction: f64,
    /// Ranked by the model's mask score.
    pub model: f64,
    /// Ranked by closeness to the geometric prior (inside it first, then by distance).
    pub distance_to_prior: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct DepthFigures {
    /// Near side on the hidden part (amodal minus visible), after each completer's Huber fit to
    /// the visible depth; crop widths. Baseline: the plane through the visible near side.
    pub near_hidden: Comparison,
    /// Far side over the whole amodal mask. Baseline: the symmetric far side.
    pub far: Comparison,
    pub near_hidden_bottles_vases: Comparison,
    pub far_bottles_vases: Comparison,
    /// Near (hidden part) and far side by category: which shapes the depth errors come from (a
    /// crop width is ~0.1-0.3 m for table-top objects and ~0.5-1.5 m for furniture).
    pub by_category: BTreeMap<String, CategoryDepth>,
}

#[derive(Debug, Clone, Serialize)]
pub struct CategoryDepth {
    pub near_hidden: Comparison,
    pub far: Comparison,
}

#[derive(Debug, Clone, Serialize)]
pub struct StepSweep {
    pub pairs: usize,
    pub miou_by_steps: BTreeMap<usize, f64>,
    /// The main step count against the largest of the sweep.
    pub main_vs_most: Option<Comparison>,
}

#[derive(Debug, Clone, Serialize)]
pub struct SpeedFigures {
    pub steps: usize,
    pub completions_per_second_batch_1: f64,
    pub completions_per_second_batch_8: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct ModelFacts {
    pub mask_head: bool,
    pub base: deocc_model::config::ResidualBase,
    pub mask_prior: deocc_completion::MaskPrior,
    pub mask_threshold: f32,
    /// The threshold of crops carrying other views' points (`None`: `mask_threshold`).
    pub mask_threshold_seen_elsewhere: Option<f32>,
    pub keep_prior: bool,
    pub samples_per_completion: usize,
    /// Colour and depth from the mean head (read at the first step) rather than the flow's sample.
    pub colour_depth_from_mean_head: bool,
    /// Median filter radius of the model's depth before scoring (0 = none).
    pub depth_median_px: usize,
    /// ... on crops no wider than this (metres; 0 = every crop).
    pub depth_median_max_crop_m: f32,
    /// Pairs whose depth was median-filtered.
    pub depth_median_pairs: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct AmodalReport {
    pub split: String,
    pub pairs: usize,
    pub objects: usize,
    pub resolution: usize,
    pub main_steps: usize,
    pub model: ModelFacts,
    pub miou_model: f64,
    pub miou_prior: f64,
    pub miou_rules: f64,
    pub miou_visible: f64,
    pub miou_convex_hull: f64,
    /// The model's mask against the geometric prior (= the rules completer's mask).
    pub mask_vs_prior: Comparison,
    pub by_occlusion: BTreeMap<String, GroupRow>,
    pub by_category: BTreeMap<String, GroupRow>,
    pub held_out_families: GroupRow,
    pub training_categories_above_40: GroupRow,
    pub chair_legs: ChairLegs,
    pub candidate_auc: CandidateAuc,
    /// Whether the mask probability on the candidate pixels means what it says (models with a
    /// mask head): the share of object pixels in each tenth of the probability, and the expected
    /// calibration error. The pipeline carries this probability to each generated point's
    /// confidence.
    pub candidate_calibration: Calibration,
    /// Whether the error head's expected depth error means what it says (models with one):
    /// hidden pixels' near side and the object's far side, after the Huber fit, binned by the
    /// expected error.
    pub error_head: Option<ErrorHeadFigures>,
    /// Hidden colour (mean absolute error per channel, 0-255) against the nearest visible colour.
    pub hidden_colour: Comparison,
    pub depth: DepthFigures,
    /// mIoU with cross-view conditioning (rho) against without, on pairs with other views.
    pub cross_view: Option<Comparison>,
    /// With the other views' observations reprojected into the crop (the pipeline's default with
    /// several frames) against without, on the pairs where some landed; `None` for pairs made
    /// without them or with them switched off.
    pub other_views_observed: Option<OtherViewsObserved>,
    pub steps: StepSweep,
    pub miou_by_mask_threshold: BTreeMap<String, f64>,
    /// mIoU with the crops carrying other views' points at each threshold of
    /// `mask_thresholds_seen_elsewhere`, the others at the model's.
    pub miou_by_seen_elsewhere_threshold: BTreeMap<String, f64>,
    pub speed: SpeedFigures,
}

/// What the other views' reprojected observations change: each figure with them (method)
/// against without (baseline), paired over the same pairs.
#[derive(Debug, Clone, Serialize)]
pub struct OtherViewsObserved {
    pub pairs: usize,
    pub miou_model: Comparison,
    pub miou_prior: Comparison,
    pub hidden_colour: Comparison,
    pub near_hidden: Comparison,
    pub far: Comparison,
    pub far_bottles_vases: Comparison,
}

/// What one pair scores.
#[derive(Debug, Clone, Default)]
struct PairScores {
    iou_model: f64,
    iou_prior: f64,
    iou_rules: f64,
    iou_visible: f64,
    iou_hull: f64,
    chair_legs: bool,
    bottom_model: f64,
    bottom_prior: f64,
    colour_model: f64,
    colour_rules: f64,
    near_model: f64,
    near_rules: f64,
    far_model: f64,
    far_rules: f64,
    /// (expected, actual) errors of the model's near side on hidden pixels and far side on the
    /// object's, where it has an error head.
    error_near: Vec<(f32, f32)>,
    error_far: Vec<(f32, f32)>,
}

/// One pair's scores (model and rules against the truth); the flag says whether the model's
/// depth was median-filtered.
fn score_pair(
    data: &PairData,
    i: usize,
    cond: &CropCondition,
    model: &Completion,
    rule: &CropCompletion,
    opts: &AmodalEvalOptions,
) -> (PairScores, bool) {
    let set = &data.set;
    let r = data.resolution();
    let truth: Vec<bool> = data.amodal_mask(i).iter().map(|&m| m > 0).collect();
    let vis = &cond.visible;
    let (region, legs) = bottom_region(&truth, vis, r);
    let visible_px: Vec<usize> = (0..r * r).filter(|&p| vis[p]).collect();
    let hidden: Vec<usize> = (0..r * r).filter(|&p| truth[p] && !vis[p]).collect();
    let amodal: Vec<usize> = (0..r * r).filter(|&p| truth[p]).collect();
    // The pipeline's rule (`FusePolicy::depth_median_for`).
    let radius = depth_median_radius(
        opts.depth_median_px,
        opts.depth_median_max_crop_m,
        set.crop_width_m[i],
    );
    let mut s = PairScores {
        iou_model: iou(&model.amodal, &truth),
        iou_prior: iou(&cond.prior, &truth),
        iou_rules: iou(&rule.amodal, &truth),
        iou_visible: iou(vis, &truth),
        iou_hull: iou(&convex_hull_mask(vis, r), &truth),
        chair_legs: legs && set.category[i] == Category::Chair as u8,
        bottom_model: masked_iou(&model.amodal, &truth, &region),
        bottom_prior: masked_iou(&cond.prior, &truth, &region),
        colour_model: f64::NAN,
        colour_rules: f64::NAN,
        near_model: f64::NAN,
        near_rules: f64::NAN,
        far_model: f64::NAN,
        far_rules: f64::NAN,
        error_near: Vec::new(),
        error_far: Vec::new(),
    };
    let whole_rgb = &set.whole_rgb[i * r * r * 3..(i + 1) * r * r * 3];
    if !hidden.is_empty() {
        s.colour_model = colour_error(&model.rgb, whole_rgb, &hidden);
        // The rules' colour over the whole crop (they paint it inside their mask only): the
        // nearest visible pixel's, or where other views saw the object, theirs.
        let seen = cond.observed();
        let fill = nearest_visible_colour(&seen.rgb, &seen.mask, r);
        s.colour_rules = colour_error(&fill, whole_rgb, &hidden);
    }
    if hidden.len() >= 5 && visible_px.len() >= 5 {
        let (obs, tn, tf) = (
            data.visible_depth(i),
            data.whole_depth(i),
            data.whole_back_depth(i),
        );
        let case = DepthCase {
            visible: &visible_px,
            hidden: &hidden,
            amodal: &amodal,
            obs,
            truth_near: tn,
            truth_far: tf,
        };
        let median = |d: &[f32]| median_within(d, &model.amodal, r, radius);
        if let (Some(m), Some(b)) = (
            depth_errors(
                &median(&model.depth_rel),
                &median(&model.back_depth_rel),
                &case,
            ),
            depth_errors(&rule.depth, &rule.back_depth, &case),
        ) {
            (s.near_model, s.far_model) = m;
            (s.near_rules, s.far_rules) = b;
        }
        if let Some(e) = &model.expected_error {
            let near = median(&model.depth_rel);
            let far = median(&model.back_depth_rel);
            if let Some((n, f)) = pixel_errors(&near, &far, &case) {
                s.error_near = case.hidden.iter().map(|&p| e.near[p]).zip(n).collect();
                s.error_far = case.amodal.iter().map(|&p| e.far[p]).zip(f).collect();
            }
        }
    }
    (s, radius > 0)
}

/// Completes `idx` with GL-DoT at `steps`, cross-view conditioned with `rho` on every other view
/// of the object in the split.
fn complete_model(
    c: &GlDotCompleter,
    data: &PairData,
    idx: &[usize],
    steps: usize,
    rho: f32,
    opts: &AmodalEvalOptions,
    tick: &mut dyn FnMut(usize),
) -> Result<Vec<Completion>, EvalError> {
    let mut out = Vec::with_capacity(idx.len());
    let dev = c.device.clone();
    for chunk in idx.chunks(opts.batch.max(1)) {
        let (_, cond) = data.batch(chunk, &vec![false; chunk.len()], &dev)?;
        let others: Vec<Vec<Tensor>> = if rho > 0.0 {
            chunk
                .iter()
                .map(|&i| {
                    data.other_views(i)
                        .iter()
                        .map(|&j| data.batch(&[j], &[false], &dev).map(|b| b.1))
                        .collect::<candle_core::Result<Vec<_>>>()
                })
                .collect::<candle_core::Result<_>>()?
        } else {
            Vec::new()
        };
        let mut done = c
            .complete(&cond, &others, rho, steps, opts.seed)
            .map_err(|e| EvalError::Model(e.to_string()))?;
        // As the pipeline's completer does: the crop's threshold, and other views'
        // observations win.
        for (comp, &i) in done.iter_mut().zip(chunk) {
            c.finish(comp, &data.condition(i));
        }
        out.extend(done);
        tick(chunk.len());
    }
    Ok(out)
}

/// Mean absolute error of the near side on `hidden` pixels and of the far side on `amodal`
/// pixels, after the Huber fit of `near` to the visible depth; `None` when it cannot be fitted.
/// One pair's pixels and true depth for [`depth_errors`].
struct DepthCase<'a> {
    visible: &'a [usize],
    hidden: &'a [usize],
    amodal: &'a [usize],
    obs: &'a [f32],
    truth_near: &'a [f32],
    truth_far: &'a [f32],
}

/// Per-pixel absolute errors of the near side on the hidden pixels and of the far side on the
/// amodal ones, after the Huber fit (as [`depth_errors`]).
fn pixel_errors(near: &[f32], far: &[f32], case: &DepthCase<'_>) -> Option<(Vec<f32>, Vec<f32>)> {
    let x: Vec<f32> = case.visible.iter().map(|&p| near[p]).collect();
    let y: Vec<f32> = case.visible.iter().map(|&p| case.obs[p]).collect();
    let fit = huber_affine_fit(&x, &y, &HuberOptions::default()).ok()?;
    let err = |d: &[f32], truth: &[f32], px: &[usize]| -> Vec<f32> {
        px.iter()
            .map(|&p| (fit.apply(d[p] as f64) - truth[p] as f64).abs() as f32)
            .collect()
    };
    Some((
        err(near, case.truth_near, case.hidden),
        err(far, case.truth_far, case.amodal),
    ))
}

fn depth_errors(near: &[f32], far: &[f32], case: &DepthCase<'_>) -> Option<(f64, f64)> {
    let DepthCase {
        visible,
        hidden,
        amodal,
        obs,
        truth_near,
        truth_far,
    } = case;
    let x: Vec<f32> = visible.iter().map(|&p| near[p]).collect();
    let y: Vec<f32> = visible.iter().map(|&p| obs[p]).collect();
    let fit = huber_affine_fit(&x, &y, &HuberOptions::default()).ok()?;
    let near_err = mean(
        hidden
            .iter()
            .map(|&p| (fit.apply(near[p] as f64) - truth_near[p] as f64).abs()),
    );
    let far_err = mean(
        amodal
            .iter()
            .map(|&p| (fit.apply(far[p] as f64) - truth_far[p] as f64).abs()),
    );
    Some((near_err, far_err))
}

fn colour_error(rgb: &[u8], truth: &[u8], hidden: &[usize]) -> f64 {
    mean(hidden.iter().map(|&p| {
        (0..3)
            .map(|c| (rgb[3 * p + c] as f64 - truth[3 * p + c] as f64).abs())
            .sum::<f64>()
            / 3.0
    }))
}

/// The chair-legs rule and the bottom region: rows in the bottom 40% of the amodal box, and
/// whether at least 30% of the object there is hidden.
fn bottom_region(truth: &[bool], visible: &[bool], r: usize) -> (Vec<bool>, bool) {
    let rows: Vec<usize> = (0..r)
        .filter(|&v| truth[v * r..(v + 1) * r].iter().any(|&t| t))
        .collect();
    let (Some(&v0), Some(&v1)) = (rows.first(), rows.last()) else {
        return (vec![false; r * r], false);
    };
    let start = v1 + 1 - ((v1 + 1 - v0) as f64 * 0.4).ceil() as usize;
    let region: Vec<bool> = (0..r * r).map(|p| p / r >= start).collect();
    let (mut object, mut hidden) = (0usize, 0usize);
    for p in (0..r * r).filter(|&p| region[p] && truth[p]) {
        object += 1;
        hidden += !visible[p] as usize;
    }
    let legs = object > 0 && hidden as f64 >= 0.3 * object as f64;
    (region, legs)
}

fn masked_iou(a: &[bool], b: &[bool], region: &[bool]) -> f64 {
    let a: Vec<bool> = a.iter().zip(region).map(|(&x, &r)| x && r).collect();
    let b: Vec<bool> = b.iter().zip(region).map(|(&x, &r)| x && r).collect();
    iou(&a, &b)
}

fn category_name(code: u8) -> String {
    Category::from_code(code)
        .map(|c| c.name().to_string())
        .unwrap_or_else(|| format!("category_{code}"))
}

/// Runs the whole evaluation on the first `opts.pairs` pairs of `data` (the `split` named in the
/// report). `tick` is told how many completions were made.
pub fn evaluate_amodal(
    c: &GlDotCompleter,
    data: &PairData,
    split: &str,
    opts: &AmodalEvalOptions,
    tick: &mut dyn FnMut(usize),
) -> Result<AmodalReport, EvalError> {
    let n = opts.pairs.unwrap_or(data.len()).min(data.len());
    if n == 0 {
        return Err(EvalError::Data("no pairs to evaluate".into()));
    }
    let idx: Vec<usize> = (0..n).collect();
    let r = data.resolution();
    let set = &data.set;
    let groups: Vec<u32> = idx.iter().map(|&i| set.group[i]).collect();
    let rules = RulesCompleter {
        resolution: r,
        ..RulesCompleter::default()
    };
    let conds: Vec<CropCondition> = idx.iter().map(|&i| data.condition(i)).collect();
    let rules_out: Vec<CropCompletion> = conds.iter().map(|c| rules.complete_one(c)).collect();
    let model_out = complete_model(c, data, &idx, opts.main_steps, 0.0, opts, tick)?;

    if opts.depth_median_px > 0
        && opts.depth_median_max_crop_m > 0.0
        && idx.iter().any(|&i| !set.crop_width_m[i].is_finite())
    {
        return Err(EvalError::Data(
            "the median filter's crop-width limit needs each pair's crop width, and these \
             pairs were made before it was stored (tensor 'crop_width_m'): make them again \
             with `deocc synth pairs`, or set the limit to 0"
                .into(),
        ));
    }
    let mut depth_median_pairs = 0;
    let mut scores = Vec::with_capacity(n);
    let (mut cand_scores, mut cand_dist, mut cand_labels) = (Vec::new(), Vec::new(), Vec::new());
    for (k, &i) in idx.iter().enumerate() {
        let cond = &conds[k];
        let vis = &cond.visible;
        let model = &model_out[k];
        let truth: Vec<bool> = data.amodal_mask(i).iter().map(|&m| m > 0).collect();
        let (s, filtered) = score_pair(data, i, cond, model, &rules_out[k], opts);
        depth_median_pairs += filtered as usize;
        // Candidate pixels: the model's score, and closeness to the prior.
        let nearest = nearest_seed(&cond.prior, r);
        for p in (0..r * r).filter(|&p| !vis[p] && cond.scene_depth[p] < 0.0) {
            cand_scores.push(model.mask_score[p]);
            let d = match nearest[p] {
                Some(q) => {
                    let (du, dv) = (
                        (p % r) as f32 - (q % r) as f32,
                        (p / r) as f32 - (q / r) as f32,
                    );
                    (du * du + dv * dv).sqrt()
                }
                None => r as f32,
            };
            cand_dist.push(-d);
            cand_labels.push(truth[p]);
        }
        scores.push(s);
    }

    let cmp = |m: &dyn Fn(&PairScores) -> f64,
               b: &dyn Fn(&PairScores) -> f64,
               keep: &dyn Fn(usize) -> bool,
               seed: u64| {
        let ks: Vec<usize> = (0..n).filter(|&k| keep(k)).collect();
        compare(
            &ks.iter().map(|&k| m(&scores[k])).collect::<Vec<_>>(),
            &ks.iter().map(|&k| b(&scores[k])).collect::<Vec<_>>(),
            &ks.iter().map(|&k| groups[k]).collect::<Vec<_>>(),
            opts.bootstrap_resamples,
            opts.seed ^ seed,
        )
    };
    let group = |keep: &dyn Fn(usize) -> bool, seed: u64| -> GroupRow {
        let ks: Vec<usize> = (0..n).filter(|&k| keep(k)).collect();
        GroupRow {
            pairs: ks.len(),
            miou_model: mean(ks.iter().map(|&k| scores[k].iou_model)),
            miou_prior: mean(ks.iter().map(|&k| scores[k].iou_prior)),
            miou_hull: mean(ks.iter().map(|&k| scores[k].iou_hull)),
            model_minus_prior: cmp(&|s| s.iou_model, &|s| s.iou_prior, keep, seed),
        }
    };
    let occ = |k: usize| set.occlusion[idx[k]] as f64;
    let mut by_occlusion = BTreeMap::new();
    for (name, lo, hi) in [
        ("0-10%", -1.0, 0.1),
        ("10-40%", 0.1, 0.4),
        ("40-70%", 0.4, 0.7),
        ("70-100%", 0.7, 2.0),
    ] {
        by_occlusion.insert(
            name.to_string(),
            group(&|k| occ(k) > lo && occ(k) <= hi, 11),
        );
    }
    let mut codes: Vec<u8> = idx.iter().map(|&i| set.category[i]).collect();
    codes.sort_unstable();
    codes.dedup();
    let by_category = codes
        .iter()
        .map(|&code| {
            (
                category_name(code),
                group(&|k| set.category[idx[k]] == code, 13),
            )
        })
        .collect();
    let held = |k: usize| set.held_out[idx[k]] > 0;
    let is_bottle_vase = |k: usize| {
        let cat = set.category[idx[k]];
        cat == Category::Bottle as u8 || cat == Category::Vase as u8
    };
    let all = |_k: usize| true;

    // The other views' observations: everything again without them.
    let other_views_observed = if data.set.has_elsewhere() && data.seen_elsewhere() {
        data.set_seen_elsewhere(false);
        let without = complete_model(c, data, &idx, opts.main_steps, 0.0, opts, tick);
        data.set_seen_elsewhere(true);
        let without = without?;
        let with: Vec<usize> = (0..n)
            .filter(|&k| conds[k].seen_elsewhere.is_some())
            .collect();
        let base: Vec<PairScores> = with
            .iter()
            .map(|&k| {
                let i = idx[k];
                let cond = data.condition_without_elsewhere(i);
                let rule = rules.complete_one(&cond);
                score_pair(data, i, &cond, &without[k], &rule, opts).0
            })
            .collect();
        let pair = |f: &dyn Fn(&PairScores) -> f64, keep: &dyn Fn(usize) -> bool, seed: u64| {
            let ks: Vec<usize> = (0..with.len()).filter(|&j| keep(with[j])).collect();
            compare(
                &ks.iter().map(|&j| f(&scores[with[j]])).collect::<Vec<_>>(),
                &ks.iter().map(|&j| f(&base[j])).collect::<Vec<_>>(),
                &ks.iter().map(|&j| groups[with[j]]).collect::<Vec<_>>(),
                opts.bootstrap_resamples,
                opts.seed ^ seed,
            )
        };
        Some(OtherViewsObserved {
            pairs: with.len(),
            miou_model: pair(&|s| s.iou_model, &all, 41),
            miou_prior: pair(&|s| s.iou_prior, &all, 43),
            hidden_colour: pair(&|s| s.colour_model, &all, 45),
            near_hidden: pair(&|s| s.near_model, &all, 47),
            far: pair(&|s| s.far_model, &all, 49),
            far_bottles_vases: pair(&|s| s.far_model, &is_bottle_vase, 51),
        })
    } else {
        None
    };

    // Cross-view: the pairs with other views of their object.
    let cross_view = if opts.skip_cross_view {
        None
    } else {
        let multi: Vec<usize> = (0..n)
            .filter(|&k| !data.other_views(idx[k]).is_empty())
            .collect();
        let sub: Vec<usize> = multi.iter().map(|&k| idx[k]).collect();
        let with_rho = complete_model(c, data, &sub, opts.main_steps, opts.rho, opts, tick)?;
        let truth_of =
            |i: usize| -> Vec<bool> { data.amodal_mask(i).iter().map(|&m| m > 0).collect() };
        let rho_iou: Vec<f64> = sub
            .iter()
            .zip(&with_rho)
            .map(|(&i, comp)| iou(&comp.amodal, &truth_of(i)))
            .collect();
        let base: Vec<f64> = multi.iter().map(|&k| scores[k].iou_model).collect();
        let cl: Vec<u32> = multi.iter().map(|&k| groups[k]).collect();
        Some(compare(
            &rho_iou,
            &base,
            &cl,
            opts.bootstrap_resamples,
            opts.seed ^ 17,
        ))
    };

    // Step sweep on the first pairs.
    let sweep_n = opts.sweep_pairs.min(n);
    let sweep_idx: Vec<usize> = (0..sweep_n).collect();
    let mut sweep: BTreeMap<usize, Vec<f64>> = BTreeMap::new();
    for &steps in &opts.sweep_steps {
        let ious: Vec<f64> = if steps == opts.main_steps {
            (0..sweep_n).map(|k| scores[k].iou_model).collect()
        } else {
            let comp = complete_model(c, data, &sweep_idx, steps, 0.0, opts, tick)?;
            comp.iter()
                .zip(&sweep_idx)
                .map(|(m, &i)| {
                    let truth: Vec<bool> = data.amodal_mask(i).iter().map(|&v| v > 0).collect();
                    iou(&m.amodal, &truth)
                })
                .collect()
        };
        sweep.insert(steps, ious);
    }
    let most = opts.sweep_steps.iter().copied().max();
    let main_vs_most = match (
        sweep.get(&opts.main_steps),
        most.and_then(|m| sweep.get(&m)),
    ) {
        (Some(a), Some(b)) if most != Some(opts.main_steps) => Some(compare(
            a,
            b,
            &groups[..sweep_n],
            opts.bootstrap_resamples,
            opts.seed ^ 19,
        )),
        _ => None,
    };
    let steps = StepSweep {
        pairs: sweep_n,
        miou_by_steps: sweep
            .iter()
            .map(|(&s, v)| (s, mean(v.iter().copied())))
            .collect(),
        main_vs_most,
    };

    // mIoU with one threshold for the crops without other views' points and one for those with.
    let seen: Vec<bool> = conds
        .iter()
        .map(deocc_model::infer::has_seen_elsewhere)
        .collect();
    let miou_at = |plain: f32, with_points: f32| {
        mean((0..n).map(|k| {
            let cond = &conds[k];
            let th = if seen[k] { with_points } else { plain };
            let pred: Vec<bool> = (0..r * r)
                .map(|p| {
                    c.in_mask(
                        model_out[k].mask_score[p],
                        cond.visible[p],
                        cond.prior[p],
                        th,
                    )
                })
                .collect();
            let truth: Vec<bool> = data.amodal_mask(idx[k]).iter().map(|&v| v > 0).collect();
            iou(&pred, &truth)
        }))
    };
    let miou_by_mask_threshold = opts
        .mask_thresholds
        .iter()
        .map(|&th| {
            let m = miou_at(th, c.mask_threshold_seen_elsewhere.unwrap_or(th));
            (format!("{th:.3}"), m)
        })
        .collect();
    let miou_by_seen_elsewhere_threshold = opts
        .mask_thresholds_seen_elsewhere
        .iter()
        .map(|&th| (format!("{th:.3}"), miou_at(c.mask_threshold, th)))
        .collect();

    // Speed at the main step count: one crop, then a batch of 8.
    let dev = c.device.clone();
    let (_, one) = data.batch(&[0], &[false], &dev)?;
    let eight_idx: Vec<usize> = (0..8).map(|k| k % data.len()).collect();
    let (_, eight) = data.batch(&eight_idx, &[false; 8], &dev)?;
    let time = |cond: &Tensor, reps: usize| -> Result<f64, EvalError> {
        let run = || {
            c.complete(cond, &[], 0.0, opts.main_steps, 0)
                .map_err(|e| EvalError::Model(e.to_string()))
        };
        run()?; // warm-up
        let t0 = Instant::now();
        for _ in 0..reps {
            run()?;
        }
        Ok(t0.elapsed().as_secs_f64() / reps as f64)
    };
    let speed = SpeedFigures {
        steps: opts.main_steps,
        completions_per_second_batch_1: 1.0 / time(&one, 5)?,
        completions_per_second_batch_8: 8.0 / time(&eight, 3)?,
    };

    let mut object_ids = groups.clone();
    object_ids.sort_unstable();
    object_ids.dedup();
    let auc_pixels = cand_labels.len();
    Ok(AmodalReport {
        split: split.to_string(),
        pairs: n,
        objects: object_ids.len(),
        resolution: r,
        main_steps: opts.main_steps,
        model: ModelFacts {
            mask_head: c.model.config.mask_head,
            base: c.model.config.base,
            mask_prior: c.model.config.mask_prior,
            mask_threshold: c.mask_threshold,
            mask_threshold_seen_elsewhere: c.mask_threshold_seen_elsewhere,
            keep_prior: c.keep_prior,
            samples_per_completion: c.samples,
            colour_depth_from_mean_head: c.model.config.mean_head && c.reads_mean,
            depth_median_px: opts.depth_median_px,
            depth_median_max_crop_m: opts.depth_median_max_crop_m,
            depth_median_pairs,
        },
        miou_model: mean(scores.iter().map(|s| s.iou_model)),
        miou_prior: mean(scores.iter().map(|s| s.iou_prior)),
        miou_rules: mean(scores.iter().map(|s| s.iou_rules)),
        miou_visible: mean(scores.iter().map(|s| s.iou_visible)),
        miou_convex_hull: mean(scores.iter().map(|s| s.iou_hull)),
        mask_vs_prior: cmp(&|s| s.iou_model, &|s| s.iou_prior, &all, 1),
        by_occlusion,
        by_category,
        held_out_families: group(&held, 3),
        training_categories_above_40: group(&|k| !held(k) && occ(k) > 0.4, 5),
        chair_legs: ChairLegs {
            pairs: scores.iter().filter(|s| s.chair_legs).count(),
            miou: cmp(
                &|s| s.iou_model,
                &|s| s.iou_prior,
                &|k| scores[k].chair_legs,
                7,
            ),
            bottom_region_iou: cmp(
                &|s| s.bottom_model,
                &|s| s.bottom_prior,
                &|k| scores[k].chair_legs,
                9,
            ),
        },
        candidate_auc: CandidateAuc {
            pixels: auc_pixels,
            object_fraction: cand_labels.iter().filter(|&&l| l).count() as f64
                / auc_pixels.max(1) as f64,
            model: roc_auc(&cand_scores, &cand_labels),
            distance_to_prior: roc_auc(&cand_dist, &cand_labels),
        },
        candidate_calibration: calibration(&cand_scores, &cand_labels),
        error_head: scores
            .iter()
            .any(|s| !s.error_far.is_empty())
            .then(|| ErrorHeadFigures {
                near_hidden: error_head_side(
                    &scores
                        .iter()
                        .flat_map(|s| s.error_near.iter().copied())
                        .collect::<Vec<_>>(),
                ),
                far: error_head_side(
                    &scores
                        .iter()
                        .flat_map(|s| s.error_far.iter().copied())
                        .collect::<Vec<_>>(),
                ),
            }),
        hidden_colour: cmp(&|s| s.colour_model, &|s| s.colour_rules, &all, 21),
        depth: DepthFigures {
            near_hidden: cmp(&|s| s.near_model, &|s| s.near_rules, &all, 23),
            far: cmp(&|s| s.far_model, &|s| s.far_rules, &all, 25),
            near_hidden_bottles_vases: cmp(
                &|s| s.near_model,
                &|s| s.near_rules,
                &is_bottle_vase,
                27,
            ),
            far_bottles_vases: cmp(&|s| s.far_model, &|s| s.far_rules, &is_bottle_vase, 29),
            by_category: codes
                .iter()
                .map(|&code| {
                    let of = |k: usize| set.category[idx[k]] == code;
                    (
                        category_name(code),
                        CategoryDepth {
                            near_hidden: cmp(&|s| s.near_model, &|s| s.near_rules, &of, 31),
                            far: cmp(&|s| s.far_model, &|s| s.far_rules, &of, 33),
                        },
                    )
                })
                .collect(),
        },
        cross_view,
        other_views_observed,
        steps,
        miou_by_mask_threshold,
        miou_by_seen_elsewhere_threshold,
        speed,
    })
}

#[cfg(test)]
mod tests {
    use super::{error_head_side, ERROR_BINS};

    /// Pixels land in the bin of their expected error, each bin's actual mean is its pixels',
    /// and an expected error that ranks the large actual errors first scores an AUC of 1
    /// (reversed, 0).
    #[test]
    fn error_head_figures_bin_by_the_expected_error() {
        let pairs = [(0.005, 0.004), (0.015, 0.01), (0.04, 0.06), (0.2, 0.3)];
        let f = error_head_side(&pairs);
        assert_eq!(f.pixels, 4);
        assert_eq!(f.bins.len(), ERROR_BINS.len());
        let counts: Vec<usize> = f.bins.iter().map(|b| b.pixels).collect();
        assert_eq!(counts, [1, 1, 0, 1, 0, 1]);
        assert!((f.bins[3].mean_actual - 0.06).abs() < 1e-6);
        assert_eq!(f.bins[3].share_large, 1.0);
        assert_eq!(f.bins[0].share_large, 0.0);
        assert!(f.bins[5].expected_up_to.is_none());
        assert!((f.mean_actual - (0.004 + 0.01 + 0.06 + 0.3) / 4.0).abs() < 1e-6);
        assert_eq!(f.auc_large, 1.0);
        let reversed: Vec<(f32, f32)> = pairs.iter().map(|&(e, a)| (1.0 - e, a)).collect();
        assert_eq!(error_head_side(&reversed).auc_large, 0.0);
    }
}
