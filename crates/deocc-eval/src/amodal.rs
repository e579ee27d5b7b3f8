//! 2-D amodal completion on held-out pairs: the figures of `deocc eval amodal`.

use std::collections::BTreeMap;
use std::time::Instant;

use candle_core::Tensor;
use deocc_geometry::robust::{huber_affine_fit, HuberOptions};
use deocc_model::data::PairData;
use deocc_model::infer::{Completion, GlDotCompleter};
use serde::Serialize;

use crate::masks::{convex_hull_mask, iou};

#[derive(Debug, Clone)]
pub struct AmodalEvalOptions {
    /// Pairs evaluated (the first N of the test set).
    pub pairs: usize,
    pub steps: Vec<usize>,
    /// The step count of the per-level, cross-view and depth figures.
    pub main_steps: usize,
    pub rho: f32,
    pub batch: usize,
    pub seed: u64,
    /// Mask thresholds to report the main-steps mIoU at (the completer's own is always used for
    /// every other figure).
    pub mask_thresholds: Vec<f32>,
}

impl Default for AmodalEvalOptions {
    fn default() -> Self {
        Self {
            pairs: 120,
            steps: vec![1, 2, 4, 8, 50],
            main_steps: 4,
            rho: 0.5,
            batch: 16,
            seed: 0,
            mask_thresholds: Vec::new(),
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct GroupFigures {
    pub pairs: usize,
    pub miou_model: f64,
    pub miou_visible: f64,
    pub miou_convex_hull: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct CrossViewFigures {
    pub pairs: usize,
    pub miou_rho_0: f64,
    pub miou_rho: f64,
    pub rho: f32,
    pub gain: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct DepthFigures {
    pub pairs: usize,
    /// Mean absolute error of relative depth on the hidden part (amodal minus visible) after the
    /// Huber fit of the prediction to the visible depth. Units: crop widths.
    pub mae_hidden_model: f64,
    /// The same with the hidden part filled with the median visible depth.
    pub mae_hidden_median_baseline: f64,
    /// Mean absolute error of the far side's relative depth (the object's back) over the whole
    /// amodal mask, after the same fit.
    pub mae_back_model: f64,
    /// The same for a zero-thickness baseline (back = observed near side on visible pixels,
    /// median visible depth elsewhere).
    pub mae_back_thin_baseline: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct SpeedFigures {
    pub steps: usize,
    pub completions_per_second_batch_1: f64,
    pub completions_per_second_batch_8: f64,
    pub threads: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct AmodalReport {
    pub pairs: usize,
    pub resolution: usize,
    /// mIoU of the predicted amodal mask per number of sampling steps.
    pub miou_by_steps: BTreeMap<usize, f64>,
    pub miou_baseline_visible: f64,
    pub miou_baseline_convex_hull: f64,
    /// The convex hull kept only where the observed scene is in front of the object (where it is
    /// behind, the object would be seen): a free-space-aware geometric baseline.
    pub miou_baseline_convex_hull_in_front: f64,
    /// The ellipse prior ([`deocc_model::data::ellipse_prior`]), also without a model.
    pub miou_baseline_ellipse_in_front: f64,
    /// The geometric prior the model was trained on (its condition channel 6), without a model:
    /// the figure the model's mask has to beat to be worth its cost.
    pub mask_prior: deocc_model::config::MaskPrior,
    pub miou_baseline_model_prior: f64,
    /// The model's mask (main steps) united with that baseline.
    pub miou_model_or_hull_in_front: f64,
    /// Whether the completer applied its free-space constraint, and the main-steps mIoU with it
    /// switched off (the model's raw mask).
    pub free_space_constraint: bool,
    pub miou_main_steps_without_free_space: f64,
    pub main_steps: usize,
    /// The completer's mask threshold, and the main-steps mIoU at other thresholds.
    pub mask_threshold: f32,
    /// Samples averaged per completion (every figure above).
    pub samples_per_completion: usize,
    /// Whether the completer keeps every prior pixel (the model only adds).
    pub keep_prior: bool,
    pub miou_by_mask_threshold: BTreeMap<String, f64>,
    /// Figures at `main_steps`, by occlusion level (light: 10-40% hidden, heavy: over 40%).
    pub light: GroupFigures,
    pub heavy: GroupFigures,
    pub held_out_shapes: GroupFigures,
    pub cross_view: CrossViewFigures,
    pub depth: DepthFigures,
    pub speed: SpeedFigures,
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

fn complete_all(
    c: &GlDotCompleter,
    data: &PairData,
    idx: &[usize],
    steps: usize,
    rho: f32,
    opts: &AmodalEvalOptions,
    free_space: bool,
) -> candle_core::Result<Vec<Completion>> {
    let mut out = Vec::with_capacity(idx.len());
    let dev = c.device.clone();
    for chunk in idx.chunks(opts.batch.max(1)) {
        let flips = vec![false; chunk.len()];
        let (_, cond) = data.batch(chunk, &flips, &dev)?;
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
        out.extend(
            c.complete_with(&cond, &others, rho, steps, opts.seed, free_space)
                .map_err(|e| candle_core::Error::msg(e.to_string()))?,
        );
    }
    Ok(out)
}

fn mask_of(m: &[u8]) -> Vec<bool> {
    m.iter().map(|&v| v > 0).collect()
}

/// Runs the whole evaluation.
pub fn evaluate_amodal(
    c: &GlDotCompleter,
    data: &PairData,
    opts: &AmodalEvalOptions,
) -> candle_core::Result<AmodalReport> {
    let n = opts.pairs.min(data.len());
    let idx: Vec<usize> = (0..n).collect();
    let r = data.resolution();
    let truth: Vec<Vec<bool>> = idx.iter().map(|&i| mask_of(data.amodal_mask(i))).collect();
    let visible: Vec<Vec<bool>> = idx.iter().map(|&i| mask_of(data.visible_mask(i))).collect();
    let iou_visible: Vec<f64> = (0..n).map(|k| iou(&visible[k], &truth[k])).collect();
    let hulls: Vec<Vec<bool>> = (0..n).map(|k| convex_hull_mask(&visible[k], r)).collect();
    let iou_hull: Vec<f64> = (0..n).map(|k| iou(&hulls[k], &truth[k])).collect();
    let hull_in_front: Vec<Vec<bool>> = idx.iter().map(|&i| data.hull_prior(i)).collect();
    let ellipse_in_front: Vec<Vec<bool>> = idx.iter().map(|&i| data.ellipse_prior(i)).collect();
    let model_prior: Vec<Vec<bool>> = idx.iter().map(|&i| data.condition_prior(i)).collect();

    let mut miou_by_steps = BTreeMap::new();
    let mut main: Option<(Vec<f64>, Vec<Completion>)> = None;
    for &s in &opts.steps {
        let comp = complete_all(c, data, &idx, s, 0.0, opts, c.free_space)?;
        let ious: Vec<f64> = (0..n).map(|k| iou(&comp[k].amodal, &truth[k])).collect();
        miou_by_steps.insert(s, mean(ious.iter().copied()));
        if s == opts.main_steps {
            main = Some((ious, comp));
        }
    }
    let (main_iou, main_comp) = match main {
        Some(m) => m,
        None => {
            let comp = complete_all(c, data, &idx, opts.main_steps, 0.0, opts, c.free_space)?;
            (
                (0..n).map(|k| iou(&comp[k].amodal, &truth[k])).collect(),
                comp,
            )
        }
    };
    // The same completions without the free-space constraint (same seed, same noise).
    let miou_main_steps_without_free_space = {
        let comp = complete_all(c, data, &idx, opts.main_steps, 0.0, opts, false)?;
        mean((0..n).map(|k| iou(&comp[k].amodal, &truth[k])))
    };
    let miou_by_mask_threshold = opts
        .mask_thresholds
        .iter()
        .map(|&th| {
            let m = mean((0..n).map(|k| {
                let pred: Vec<bool> = (0..r * r)
                    .map(|p| {
                        let score = main_comp[k].mask_score[p];
                        c.in_mask(score, visible[k][p], model_prior[k][p], th)
                    })
                    .collect();
                iou(&pred, &truth[k])
            }));
            (format!("{th:.2}"), m)
        })
        .collect();
    let group = |keep: &dyn Fn(usize) -> bool| -> GroupFigures {
        let ks: Vec<usize> = (0..n).filter(|&k| keep(idx[k])).collect();
        GroupFigures {
            pairs: ks.len(),
            miou_model: mean(ks.iter().map(|&k| main_iou[k])),
            miou_visible: mean(ks.iter().map(|&k| iou_visible[k])),
            miou_convex_hull: mean(ks.iter().map(|&k| iou_hull[k])),
        }
    };
    let occ = &data.set.occlusion;
    let light = group(&|i| occ[i] >= 0.1 && occ[i] <= 0.4);
    let heavy = group(&|i| occ[i] > 0.4);
    let held_out_shapes = group(&|i| data.set.held_out[i] > 0);

    // Cross-view: the pairs that have other views of their object.
    let multi: Vec<usize> = idx
        .iter()
        .copied()
        .filter(|&i| !data.other_views(i).is_empty())
        .collect();
    let with_rho = complete_all(
        c,
        data,
        &multi,
        opts.main_steps,
        opts.rho,
        opts,
        c.free_space,
    )?;
    let pos: BTreeMap<usize, usize> = idx.iter().enumerate().map(|(k, &i)| (i, k)).collect();
    let miou_rho = mean(
        multi
            .iter()
            .zip(&with_rho)
            .map(|(&i, comp)| iou(&comp.amodal, &truth[pos[&i]])),
    );
    let miou_rho_0 = mean(multi.iter().map(|&i| main_iou[pos[&i]]));
    let cross_view = CrossViewFigures {
        pairs: multi.len(),
        miou_rho_0,
        miou_rho,
        rho: opts.rho,
        gain: miou_rho - miou_rho_0,
    };

    // Depth on the hidden part after the Huber fit on the visible part.
    let (mut model_err, mut base_err, mut used) = (Vec::new(), Vec::new(), 0usize);
    let (mut back_err, mut back_base_err) = (Vec::new(), Vec::new());
    for (k, &i) in idx.iter().enumerate() {
        let (vis, amo) = (&visible[k], &truth[k]);
        let hidden: Vec<usize> = (0..r * r).filter(|&p| amo[p] && !vis[p]).collect();
        let shown: Vec<usize> = (0..r * r).filter(|&p| vis[p]).collect();
        if hidden.len() < 5 || shown.len() < 5 {
            continue;
        }
        let pred = &main_comp[k].depth_rel;
        let gt = data.whole_depth(i);
        let obs = data.visible_depth(i);
        let x: Vec<f32> = shown.iter().map(|&p| pred[p]).collect();
        let y: Vec<f32> = shown.iter().map(|&p| obs[p]).collect();
        let Ok(fit) = huber_affine_fit(&x, &y, &HuberOptions::default()) else {
            continue;
        };
        let mut sorted = y.clone();
        sorted.sort_by(f32::total_cmp);
        let med = sorted[sorted.len() / 2] as f64;
        model_err.push(mean(
            hidden
                .iter()
                .map(|&p| (fit.apply(pred[p] as f64) - gt[p] as f64).abs()),
        ));
        base_err.push(mean(hidden.iter().map(|&p| (med - gt[p] as f64).abs())));
        let back_pred = &main_comp[k].back_depth_rel;
        let back_gt = data.whole_back_depth(i);
        let amodal_px: Vec<usize> = (0..r * r).filter(|&p| amo[p]).collect();
        back_err.push(mean(
            amodal_px
                .iter()
                .map(|&p| (fit.apply(back_pred[p] as f64) - back_gt[p] as f64).abs()),
        ));
        back_base_err.push(mean(amodal_px.iter().map(|&p| {
            let thin = if vis[p] { obs[p] as f64 } else { med };
            (thin - back_gt[p] as f64).abs()
        })));
        used += 1;
    }
    let depth = DepthFigures {
        pairs: used,
        mae_hidden_model: mean(model_err.into_iter()),
        mae_hidden_median_baseline: mean(base_err.into_iter()),
        mae_back_model: mean(back_err.into_iter()),
        mae_back_thin_baseline: mean(back_base_err.into_iter()),
    };

    // Speed at the main step count: one crop, then a batch of 8.
    let dev = c.device.clone();
    let (_, one) = data.batch(&[0], &[false], &dev)?;
    let eight_idx: Vec<usize> = (0..8).map(|k| k % data.len()).collect();
    let (_, eight) = data.batch(&eight_idx, &[false; 8], &dev)?;
    let time = |cond: &Tensor, reps: usize| -> candle_core::Result<f64> {
        c.complete(cond, &[], 0.0, opts.main_steps, 0)
            .map_err(|e| candle_core::Error::msg(e.to_string()))?; // warm-up
        let t0 = Instant::now();
        for _ in 0..reps {
            c.complete(cond, &[], 0.0, opts.main_steps, 0)
                .map_err(|e| candle_core::Error::msg(e.to_string()))?;
        }
        Ok(t0.elapsed().as_secs_f64() / reps as f64)
    };
    let t1 = time(&one, 5)?;
    let t8 = time(&eight, 3)?;
    let speed = SpeedFigures {
        steps: opts.main_steps,
        completions_per_second_batch_1: 1.0 / t1,
        completions_per_second_batch_8: 8.0 / t8,
        threads: rayon::current_num_threads(),
    };

    Ok(AmodalReport {
        pairs: n,
        resolution: r,
        miou_by_steps,
        miou_baseline_visible: mean(iou_visible.iter().copied()),
        miou_baseline_convex_hull: mean(iou_hull.iter().copied()),
        free_space_constraint: c.free_space,
        miou_main_steps_without_free_space,
        miou_baseline_convex_hull_in_front: mean((0..n).map(|k| iou(&hull_in_front[k], &truth[k]))),
        miou_baseline_ellipse_in_front: mean((0..n).map(|k| iou(&ellipse_in_front[k], &truth[k]))),
        mask_prior: c.model.config.mask_prior,
        miou_baseline_model_prior: mean((0..n).map(|k| iou(&model_prior[k], &truth[k]))),
        miou_model_or_hull_in_front: mean((0..n).map(|k| {
            let united: Vec<bool> = main_comp[k]
                .amodal
                .iter()
                .zip(&hull_in_front[k])
                .map(|(&a, &b)| a || b)
                .collect();
            iou(&united, &truth[k])
        })),
        main_steps: opts.main_steps,
        mask_threshold: c.mask_threshold,
        samples_per_completion: c.samples,
        keep_prior: c.keep_prior,
        miou_by_mask_threshold,
        light,
        heavy,
        held_out_shapes,
        cross_view,
        depth,
        speed,
    })
}
