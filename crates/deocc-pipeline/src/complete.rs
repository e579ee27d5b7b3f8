//! Stage: completion. Each selected (instance, view) is cropped at the resolution of the first
//! completer of the chain that does not decline it ([`CompleterChain::route`]); each completer
//! then completes its crops in batches, every crop conditioned on the same instance's other crops
//! it holds (cross-view conditioning with weight `rho`). With the mirror check on
//! ([`PipelineOptions::gate_max_depth_spread_m`]) every crop is also completed mirrored left to
//! right, in the same call, and the two answers' depths are compared pixel by pixel
//! ([`DepthSpread`]): where a completer's answer depends on which way the crop faces, it does
//! not know the depth there.

use std::collections::BTreeMap;

use deocc_completion::crop::mirror;
use deocc_completion::{
    CompleterChain, CompletionOptions, CropCompletion, CropCondition, CropRequest,
};
use deocc_io::scene::SceneInput;

use crate::crops::{instance_pixels, make_crop, seen_elsewhere, CropWindow};
use crate::stats::InstanceStats;
use crate::{PipelineError, PipelineOptions};

/// A crop and what completed it.
pub struct CompletedCrop {
    pub window: CropWindow,
    pub condition: CropCondition,
    pub completion: CropCompletion,
    /// Index of the completer in the chain.
    pub completer: usize,
    /// How far the completion of the mirrored crop (mirrored back) is from this one, per pixel;
    /// `None` when the mirror check is off.
    pub spread: Option<DepthSpread>,
    /// (r*r) relative depth where the other frames observed the object's back along each
    /// pixel's ray ([`crate::crops::Elsewhere::back`]), infinite where they did not.
    pub seen_behind: Option<Vec<f32>>,
}

/// Per-pixel disagreement (relative depth, the crop's units) between a completion and the
/// completion of the mirrored crop, mirrored back.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthSpread {
    /// (r*r) |near - near'|.
    pub near: Vec<f32>,
    /// (r*r) |far - far'|.
    pub far: Vec<f32>,
}

impl DepthSpread {
    /// The spread of `a` and `b_mirrored` (the completion of the mirrored crop, still mirrored).
    pub fn between(a: &CropCompletion, b_mirrored: &CropCompletion, r: usize) -> Self {
        let diff = |x: &[f32], y: &[f32]| -> Vec<f32> {
            x.iter()
                .zip(mirror(y, r, 1))
                .map(|(&p, q)| (p - q).abs())
                .collect()
        };
        Self {
            near: diff(&a.depth, &b_mirrored.depth),
            far: diff(&a.back_depth, &b_mirrored.back_depth),
        }
    }
}

/// A crop that every completer declined, with their reasons.
#[derive(Debug, Clone)]
pub struct DeclinedCrop {
    pub instance_id: u16,
    pub view: usize,
    pub reasons: Vec<String>,
}

/// Crops to complete: for each selected (instance, view), the crop of the first link of the
/// chain that takes it (its index), with what the other views saw of the instance in front of
/// and behind it; and the crops no link takes.
type Crops = (
    Vec<(usize, CropWindow, CropCondition)>,
    Vec<Option<Vec<f32>>>,
    Vec<DeclinedCrop>,
);

fn build_crops(
    scene: &SceneInput,
    stats: &[BTreeMap<u16, InstanceStats>],
    selected: &BTreeMap<u16, Vec<usize>>,
    chain: &CompleterChain,
    opts: &PipelineOptions,
) -> Crops {
    let mut jobs: Vec<(usize, CropWindow, CropCondition)> = Vec::new();
    let mut behind: Vec<Option<Vec<f32>>> = Vec::new();
    let mut declined = Vec::new();
    let pixels = if opts.use_other_views && scene.frames.len() > 1 {
        instance_pixels(&scene.frames)
    } else {
        Vec::new()
    };
    for (&id, views) in selected {
        for &v in views {
            let Some(st) = stats[v].get(&id) else {
                continue;
            };
            let frame = &scene.frames[v];
            // `route` stops at the first link that takes the crop, so the last window built is
            // the one of the crop it returns.
            let mut built: Option<CropWindow> = None;
            let routed = chain.route(|res| {
                let (window, cond) = make_crop(frame, v, id, st, res)?;
                built = Some(window);
                Some(cond)
            });
            match routed {
                Ok((k, cond)) => {
                    let Some(window) = built.take() else { continue };
                    let elsewhere = seen_elsewhere(
                        &scene.frames,
                        &pixels,
                        &window,
                        opts.skip_observed_far_side,
                    );
                    let cond = match elsewhere.front {
                        Some(seen) => cond.with_seen_elsewhere(seen),
                        None => cond,
                    };
                    jobs.push((k, window, cond));
                    behind.push(elsewhere.back);
                }
                Err(reasons) => {
                    // Not even a crop at any resolution: too little of it is visible.
                    if built.is_some() {
                        declined.push(DeclinedCrop {
                            instance_id: id,
                            view: v,
                            reasons,
                        });
                    }
                }
            }
        }
    }
    (jobs, behind, declined)
}

/// Crops and completes every selected (instance, view); returns the completions in (instance,
/// selected view) order and the crops no completer took.
pub fn complete_instances(
    scene: &SceneInput,
    stats: &[BTreeMap<u16, InstanceStats>],
    selected: &BTreeMap<u16, Vec<usize>>,
    chain: &CompleterChain,
    opts: &PipelineOptions,
    observer: &dyn crate::Observer,
) -> Result<(Vec<CompletedCrop>, Vec<DeclinedCrop>), PipelineError> {
    let (jobs, behind, declined) = build_crops(scene, stats, selected, chain, opts);
    let sampling = CompletionOptions {
        steps: opts.steps,
        rho: opts.rho,
        seed: opts.seed,
    };
    let mirror_check = opts.gate_max_depth_spread_m > 0.0;
    let mut completions: Vec<Option<CropCompletion>> = vec![None; jobs.len()];
    let mut spreads: Vec<Option<DepthSpread>> = vec![None; jobs.len()];
    for (k, link) in chain.links().iter().enumerate() {
        let mine: Vec<usize> = (0..jobs.len()).filter(|&j| jobs[j].0 == k).collect();
        for chunk in mine.chunks(opts.batch.max(1)) {
            // The longest stage: a cancelled or timed-out run stops between batches, not only
            // when the stage is over.
            let from = crate::stages::progress("complete");
            let to = crate::stages::progress("fuse");
            let done_share = chunk[0] as f32 / jobs.len().max(1) as f32;
            if !observer.stage("complete", from + (to - from) * done_share) {
                return Err(PipelineError::Cancelled { stage: "complete" });
            }
            let others: Vec<Vec<&CropCondition>> = chunk
                .iter()
                .map(|&j| {
                    mine.iter()
                        .filter(|&&o| {
                            jobs[o].1.instance_id == jobs[j].1.instance_id
                                && jobs[o].1.view != jobs[j].1.view
                        })
                        .map(|&o| &jobs[o].2)
                        .collect()
                })
                .collect();
            // The mirrored crops (and their other views, mirrored) ride in the same call.
            let (mirrored, mirrored_others): (Vec<CropCondition>, Vec<Vec<CropCondition>>) =
                if mirror_check {
                    chunk
                        .iter()
                        .zip(&others)
                        .map(|(&j, o)| {
                            (
                                jobs[j].2.mirrored(),
                                o.iter().map(|c| c.mirrored()).collect(),
                            )
                        })
                        .unzip()
                } else {
                    (Vec::new(), Vec::new())
                };
            let mirrored_refs: Vec<Vec<&CropCondition>> =
                mirrored_others.iter().map(|o| o.iter().collect()).collect();
            let requests: Vec<CropRequest<'_>> = chunk
                .iter()
                .zip(&others)
                .map(|(&j, o)| CropRequest {
                    condition: &jobs[j].2,
                    other_views: o,
                })
                .chain(
                    mirrored
                        .iter()
                        .zip(&mirrored_refs)
                        .map(|(c, o)| CropRequest {
                            condition: c,
                            other_views: o,
                        }),
                )
                .collect();
            let mut done = link.complete(&requests, &sampling)?;
            if done.len() != requests.len() {
                return Err(deocc_completion::CompletionError::Failed {
                    completer: link.name().into(),
                    msg: format!("{} completions for {} crops", done.len(), requests.len()),
                }
                .into());
            }
            let flipped = done.split_off(chunk.len());
            for (i, (&j, c)) in chunk.iter().zip(done).enumerate() {
                if let Some(m) = flipped.get(i) {
                    spreads[j] = Some(DepthSpread::between(&c, m, jobs[j].2.resolution));
                }
                completions[j] = Some(c);
            }
        }
    }
    let completed = jobs
        .into_iter()
        .zip(completions)
        .zip(spreads)
        .zip(behind)
        .filter_map(
            |((((completer, window, condition), completion), spread), seen_behind)| {
                Some(CompletedCrop {
                    window,
                    condition,
                    completion: completion?,
                    completer,
                    spread,
                    seen_behind,
                })
            },
        )
        .collect();
    Ok((completed, declined))
}
