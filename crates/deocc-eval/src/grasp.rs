//! `deocc eval grasp`: grasps planned on each cloud of pickup-v1, scored on the ground truth.
//!
//! Every scene is rendered, run through the pipeline once per completer (ground-truth instance
//! maps, so the target's id is known), and the antipodal planner plans on the target's points of
//! each cloud: `observed` (the sensor's points), each completer's completed cloud, and
//! `ground_truth` (dense surface samples of the objects and the table: the upper bound). Each
//! plan's top 50 grasps are scored by [`deocc_robot::grasp_eval`] against the ground truth. Scenes
//! are split by the target's visible fraction in the view: heavy below 50%.
//!
//! The figures are an analytic stand-in for robot trials (graspnetAPI's protocol on our own
//! ground truth), not a reproduction of a robot's pick-up rate.

use std::time::Instant;

use deocc_completion::CompleterChain;
use deocc_robot::grasp_eval::{affordance_iou, precision, GraspOutcome, GroundTruthScene};
use deocc_robot::{AntipodalPlanner, GraspOptions, GraspPlanner, PlanStats};
use nalgebra::Point3;
use serde::Serialize;

use crate::stats::{compare, estimate, Comparison, Estimate};
use crate::EvalError;

/// Ground-truth surface samples per square metre (about 3 mm apart).
pub const GT_DENSITY: f32 = 100_000.0;
/// Ground-truth points a grasp must hold between its jaws.
pub const MIN_POINTS: usize = 10;
/// Affordance regions: ground-truth points this close to a contact (metres).
pub const AFFORDANCE_RADIUS_M: f32 = 0.01;
/// The friction at which the true graspable region is built.
pub const AFFORDANCE_MU: f32 = 0.8;
/// Heavy occlusion: the target's visible fraction below this.
pub const HEAVY_BELOW: f64 = 0.5;
/// The visibility bins of the report: (name, from, below).
pub const VISIBILITY_BINS: [(&str, f64, f64); 3] = [
    ("under 25% visible", 0.0, 0.25),
    ("25-50% visible", 0.25, 0.5),
    ("over 50% visible", 0.5, 1.01),
];

/// One cloud of one scene.
#[derive(Debug, Clone, Serialize)]
pub struct SceneGrasps {
    pub seed: u64,
    pub target: u16,
    pub target_category: String,
    pub visible_fraction: f64,
    pub target_points: usize,
    pub grasps: usize,
    pub top1_at_04: bool,
    pub top1_at_08: bool,
    pub ap: f64,
    pub ap_04: f64,
    pub ap_08: f64,
    /// NaN when neither region exists.
    pub affordance_iou: f64,
    pub collisions: usize,
    /// Of the collisions, those with the target itself (its hidden part where the cloud had
    /// none), and with the table.
    pub collisions_with_target: usize,
    pub collisions_with_table: usize,
    pub empty: usize,
    /// The revolve stage replaced the target's completion by a surface of revolution
    /// (`deocc_pipeline::revolve`; false for the observed and ground-truth clouds).
    pub target_revolved: bool,
    /// What the cuboid stage made of the target: "fit", or why it was turned down (empty where
    /// the stage did not look at it: the revolve stage took it, or the observed and ground-truth
    /// clouds).
    pub target_cuboid: String,
    /// What the revolve stage made of the target: "fit", or why it kept the completion (empty
    /// for the observed and ground-truth clouds, or where the target was not completed).
    pub target_revolve: String,
    /// Why the planner turned its candidates down (all zero when the target had too few points
    /// to plan on).
    pub plan_stats: PlanStats,
    /// Planning and evaluation of this cloud.
    pub seconds: f64,
}

/// One cloud kind over a subset of scenes.
#[derive(Debug, Clone, Serialize)]
pub struct Subset {
    pub scenes: usize,
    pub top1_at_04: Estimate,
    pub top1_at_08: Estimate,
    pub ap: Estimate,
    pub ap_04: Estimate,
    pub ap_08: Estimate,
    pub affordance_iou: Estimate,
}

#[derive(Debug, Clone, Serialize)]
pub struct GraspRow {
    pub cloud: String,
    pub all: Subset,
    pub light: Subset,
    pub heavy: Subset,
    /// By the target's category (pickup-v2: bottle, faceted_bottle, flask, can, mug, box).
    pub by_target: std::collections::BTreeMap<String, Subset>,
    /// By the target's visible share of its silhouette: under 25%, 25-50%, over 50%.
    pub by_visibility: Vec<(String, Subset)>,
    /// This row's top-1 success at mu 0.4 over the ground-truth cloud's (all scenes).
    pub top1_at_04_over_ground_truth: f64,
    /// Top-1 success at mu 0.4 against the observed cloud, paired over scenes.
    pub top1_at_04_vs_observed: Comparison,
    pub top1_at_04_vs_observed_heavy: Comparison,
    /// This row's top-1 success at mu 0.4 over the ground-truth cloud's (heavy scenes).
    pub top1_at_04_over_ground_truth_heavy: f64,
    /// Scenes whose target the revolve stage completed (all, heavy).
    pub target_revolved: [usize; 2],
    pub mean_seconds_per_scene: f64,
    pub max_seconds_per_scene: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct GraspReport {
    pub benchmark: String,
    pub scenes: usize,
    pub heavy_scenes: usize,
    pub planner: String,
    pub options: GraspOptions,
    pub rows: Vec<GraspRow>,
    pub per_scene: Vec<(String, Vec<SceneGrasps>)>,
}

/// Plans on `cloud` (positions and instance ids) for `target` and scores against `gt`.
#[allow(clippy::too_many_arguments)]
pub fn score_cloud(
    table: Option<u32>,
    planner: &AntipodalPlanner,
    options: &GraspOptions,
    scene_points: &[Point3<f32>],
    instance: &[u32],
    errors: Option<&[f32]>,
    target: u32,
    gt: &GroundTruthScene,
    true_contacts: Option<&[[f32; 3]]>,
    target_gt: &[Point3<f32>],
) -> Result<(SceneGrasps, Vec<[f32; 3]>), EvalError> {
    let t = Instant::now();
    let target_points: Vec<Point3<f32>> = scene_points
        .iter()
        .zip(instance)
        .filter(|(_, &i)| i == target)
        .map(|(p, _)| *p)
        .collect();
    let target_errors: Option<Vec<f32>> = errors.map(|e| {
        e.iter()
            .zip(instance)
            .filter(|(_, &i)| i == target)
            .map(|(e, _)| *e)
            .collect()
    });
    let (grasps, plan_stats) = if target_points.len() >= 2 * options.min_jaw_points {
        planner
            .plan_with_errors(
                scene_points,
                errors,
                &target_points,
                target_errors.as_deref(),
            )
            .map_err(|e| EvalError::Data(e.to_string()))?
    } else {
        (Vec::new(), PlanStats::default())
    };
    let outcomes: Vec<GraspOutcome> = grasps
        .iter()
        .map(|g| gt.evaluate(g, target, &options.gripper, MIN_POINTS))
        .collect();
    let p = precision(&outcomes, options.top_k);
    let holding: Vec<[f32; 3]> = outcomes
        .iter()
        .filter_map(|o| match o {
            GraspOutcome::Closure { mu, contacts } if *mu <= AFFORDANCE_MU + 1e-6 => {
                Some(contacts.to_vec())
            }
            _ => None,
        })
        .flatten()
        .collect();
    let planned: Vec<[f32; 3]> = grasps.iter().flat_map(|g| g.contacts).collect();
    let truth = true_contacts.unwrap_or(&holding);
    let iou = affordance_iou(target_gt, truth, &planned, AFFORDANCE_RADIUS_M)
        .map_err(|e| EvalError::Data(e.to_string()))?
        .unwrap_or(f64::NAN);
    Ok((
        SceneGrasps {
            seed: 0,
            target: target as u16,
            target_category: String::new(),
            visible_fraction: f64::NAN,
            target_points: target_points.len(),
            grasps: grasps.len(),
            top1_at_04: p.top1_at_04,
            top1_at_08: p.top1_at_08,
            ap: p.ap,
            ap_04: p.ap_04,
            ap_08: p.ap_08,
            affordance_iou: iou,
            collisions: outcomes
                .iter()
                .filter(|o| matches!(o, GraspOutcome::Collision { .. }))
                .count(),
            collisions_with_target: outcomes
                .iter()
                .filter(|o| matches!(o, GraspOutcome::Collision { with } if *with == target))
                .count(),
            collisions_with_table: outcomes
                .iter()
                .filter(|o| matches!(o, GraspOutcome::Collision { with } if Some(*with) == table))
                .count(),
            empty: outcomes
                .iter()
                .filter(|o| matches!(o, GraspOutcome::Empty))
                .count(),
            target_revolved: false,
            target_cuboid: String::new(),
            target_revolve: String::new(),
            plan_stats,
            seconds: t.elapsed().as_secs_f64(),
        },
        holding,
    ))
}

fn subset(rows: &[&SceneGrasps]) -> Subset {
    let f = |g: &dyn Fn(&SceneGrasps) -> f64, seed: u64| {
        estimate(&rows.iter().map(|r| g(r)).collect::<Vec<_>>(), 1000, seed)
    };
    Subset {
        scenes: rows.len(),
        top1_at_04: f(&|r| r.top1_at_04 as u8 as f64, 1),
        top1_at_08: f(&|r| r.top1_at_08 as u8 as f64, 2),
        ap: f(&|r| r.ap, 3),
        ap_04: f(&|r| r.ap_04, 4),
        ap_08: f(&|r| r.ap_08, 5),
        affordance_iou: f(&|r| r.affordance_iou, 6),
    }
}

/// `deocc eval grasp` on the first `scenes` of `preset` (pickup-v1, or its tuning seeds) with each
/// named chain.
pub fn grasp_benchmark(
    chains: &[crate::ChainRow],
    opts: &deocc_pipeline::PipelineOptions,
    options: &GraspOptions,
    preset: &deocc_synth::dataset::Preset,
    scenes: usize,
    tick: &mut dyn FnMut(),
) -> Result<GraspReport, EvalError> {
    options
        .validate()
        .map_err(|e| EvalError::Data(e.to_string()))?;
    let n = scenes.min(preset.seeds.len());
    let planner = AntipodalPlanner {
        options: options.clone(),
    };
    let mut names: Vec<String> = vec!["observed".into()];
    names.extend(chains.iter().map(|c| c.name.clone()));
    names.push("ground_truth".into());
    let mut per: Vec<Vec<SceneGrasps>> = vec![Vec::new(); names.len()];
    for &seed in &preset.seeds[..n] {
        let rendered = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        let target = rendered
            .scene
            .target
            .ok_or_else(|| EvalError::Data(format!("pickup seed {seed}: no target")))?;
        let category = rendered
            .scene
            .objects
            .iter()
            .find(|o| o.instance_id == target)
            .map(|o| o.category.name().to_string())
            .unwrap_or_default();
        let visible = rendered.views[0]
            .visibility
            .iter()
            .find(|v| v.instance_id == target)
            .map(|v| 1.0 - v.occlusion() as f64)
            .unwrap_or(0.0);
        let gt_cloud =
            deocc_synth::ground_truth::object_surfaces(&rendered.scene, GT_DENSITY, seed);
        let gt_normals = gt_cloud.normals.clone().unwrap_or_default();
        let gt_ids = gt_cloud.instance.clone().unwrap_or_default();
        let gt = GroundTruthScene::new(&gt_cloud.positions, &gt_normals, &gt_ids)
            .map_err(|e| EvalError::Data(e.to_string()))?;
        let target_gt = gt.target_points(target as u32);
        // The upper bound first: its holding grasps define the true graspable region.
        let table = rendered.scene.table.map(|t| t.instance_id as u32);
        let (mut gt_row, true_contacts) = score_cloud(
            table,
            &planner,
            options,
            &gt_cloud.positions,
            &gt_ids,
            None,
            target as u32,
            &gt,
            None,
            &target_gt,
        )?;
        let input = rendered.scene_input();
        // The occluder's far side matters to a gripper reaching behind it: complete every
        // object, occluded or not.
        let for_grasping = |o: &deocc_pipeline::PipelineOptions| deocc_pipeline::PipelineOptions {
            complete_unoccluded: true,
            ..o.clone()
        };
        let mut rows = Vec::new();
        let empty = CompleterChain::default();
        for (k, (chain, row_opts)) in std::iter::once((&empty, opts))
            .chain(chains.iter().map(|c| (&c.chain, c.options_or(opts))))
            .enumerate()
        {
            let out = crate::run_as_product(&input, chain, &for_grasping(row_opts))?;
            let cloud = if k == 0 {
                &out.observed
            } else {
                &out.completed
            };
            let ids = cloud.instance.clone().ok_or_else(|| {
                EvalError::Data("the pipeline's cloud has no instance ids".into())
            })?;
            // The planner's envelope: the stated error of each generated point.
            let fitted = out.report.fitted_instances();
            let errors = deocc_robot::grasp::envelope_errors(
                cloud.generated.as_deref(),
                cloud.expected_error.as_deref(),
                Some(&ids),
                &fitted,
                options,
            );
            let (mut row, _) = score_cloud(
                table,
                &planner,
                options,
                &cloud.positions,
                &ids,
                errors.as_deref(),
                target as u32,
                &gt,
                Some(&true_contacts),
                &target_gt,
            )?;
            if k > 0 {
                // What a shape stage made of the target: "fit", or why not.
                let said = |fit: bool, reason: &str| {
                    if fit {
                        "fit".to_string()
                    } else {
                        reason.to_string()
                    }
                };
                let target_report = out
                    .report
                    .instances
                    .iter()
                    .find(|i| i.instance_id == target);
                row.target_revolve = target_report
                    .and_then(|i| i.revolve.as_ref())
                    .map(|r| said(r.fit.is_some(), &r.reason))
                    .unwrap_or_default();
                row.target_cuboid = target_report
                    .and_then(|i| i.cuboid.as_ref())
                    .map(|c| said(c.fit.is_some(), &c.reason))
                    .unwrap_or_default();
                row.target_revolved = row.target_revolve == "fit";
            }
            rows.push(row);
        }
        rows.push({
            // The ground truth against its own region.
            gt_row.affordance_iou = if true_contacts.is_empty() {
                f64::NAN
            } else {
                gt_row.affordance_iou
            };
            gt_row
        });
        for (k, mut row) in rows.into_iter().enumerate() {
            row.seed = seed;
            row.target_category = category.clone();
            row.visible_fraction = visible;
            per[k].push(row);
        }
        tick();
    }
    let gt_k = names.len() - 1;
    let heavy_of = |r: &SceneGrasps| r.visible_fraction < HEAVY_BELOW;
    let rows = names
        .iter()
        .enumerate()
        .map(|(k, name)| {
            let all: Vec<&SceneGrasps> = per[k].iter().collect();
            let light: Vec<&SceneGrasps> = per[k].iter().filter(|r| !heavy_of(r)).collect();
            let heavy: Vec<&SceneGrasps> = per[k].iter().filter(|r| heavy_of(r)).collect();
            let top1 = |rs: &[SceneGrasps], keep: &dyn Fn(&SceneGrasps) -> bool| -> Vec<f64> {
                rs.iter()
                    .filter(|r| keep(r))
                    .map(|r| r.top1_at_04 as u8 as f64)
                    .collect()
            };
            let vs = |keep: &dyn Fn(&SceneGrasps) -> bool| {
                let a = top1(&per[k], keep);
                let b = top1(&per[0], keep);
                let c: Vec<u32> = (0..a.len() as u32).collect();
                compare(&a, &b, &c, 1000, 11)
            };
            let mut by_target = std::collections::BTreeMap::new();
            let mut categories: Vec<&str> =
                per[k].iter().map(|r| r.target_category.as_str()).collect();
            categories.sort_unstable();
            categories.dedup();
            for c in categories {
                let rs: Vec<&SceneGrasps> =
                    per[k].iter().filter(|r| r.target_category == c).collect();
                by_target.insert(c.to_string(), subset(&rs));
            }
            let by_visibility = VISIBILITY_BINS
                .iter()
                .map(|&(name, lo, hi)| {
                    let rs: Vec<&SceneGrasps> = per[k]
                        .iter()
                        .filter(|r| r.visible_fraction >= lo && r.visible_fraction < hi)
                        .collect();
                    (name.to_string(), subset(&rs))
                })
                .collect();
            let rate = crate::stats::mean(top1(&per[k], &|_| true));
            let gt_rate = crate::stats::mean(top1(&per[gt_k], &|_| true));
            let heavy_rate = crate::stats::mean(top1(&per[k], &heavy_of));
            let gt_heavy = crate::stats::mean(top1(&per[gt_k], &heavy_of));
            let secs: Vec<f64> = per[k].iter().map(|r| r.seconds).collect();
            GraspRow {
                cloud: name.clone(),
                all: subset(&all),
                light: subset(&light),
                heavy: subset(&heavy),
                by_target,
                by_visibility,
                top1_at_04_over_ground_truth: rate / gt_rate,
                top1_at_04_vs_observed: vs(&|_| true),
                top1_at_04_vs_observed_heavy: vs(&heavy_of),
                top1_at_04_over_ground_truth_heavy: heavy_rate / gt_heavy,
                target_revolved: [
                    all.iter().filter(|r| r.target_revolved).count(),
                    heavy.iter().filter(|r| r.target_revolved).count(),
                ],
                mean_seconds_per_scene: crate::stats::mean(secs.iter().copied()),
                max_seconds_per_scene: secs.iter().copied().fold(0.0, f64::max),
            }
        })
        .collect();
    Ok(GraspReport {
        benchmark: preset.name.clone(),
        scenes: n,
        heavy_scenes: per[0].iter().filter(|r| heavy_of(r)).count(),
        planner: planner.name().to_string(),
        options: options.clone(),
        rows,
        per_scene: names.into_iter().zip(per).collect(),
    })
}
