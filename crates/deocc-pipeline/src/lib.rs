//! # deocc-pipeline
//!
//! The de-occlusion pipeline as plain functions over plain data, one stage per file. The stages,
//! in order, with their files and functions, are one list: [`stages::STAGES`] (ARCHITECTURE.md's
//! table is generated from it and checked by a test).
//!
//! [`run`] composes them on a loaded scene whose frames all have instance maps. The parts users
//! swap are traits: the completer chain ([`deocc_completion::Completer`]: GL-DoT, the rules
//! completer, or your own), the segmenter ([`segment::Segmenter`]) and the depth source
//! ([`depth::DepthSource`]). This crate does not
//! depend on the benchmark renderer or on the ML stack: the learned completer is handed in.

pub mod burst;
pub mod carve;
pub mod complete;
pub mod crops;
pub mod cuboid;
pub mod depth;
pub mod depth_clean;
pub mod error;
pub mod front;
pub mod fuse;
pub mod gate;
pub mod ground_truth;
pub mod instances;
pub mod mask_holes;
pub mod mask_rims;
pub mod matching;
pub mod occlusion;
pub mod options;
pub mod options_help;
pub mod output;
pub mod pictures;
pub mod planes;
pub mod reconstruct;
pub mod record;
pub mod recording;
pub mod registration;
pub mod render;
pub mod report;
pub mod report_html;
pub mod revolve;
pub mod segment;
pub mod stages;
pub mod stats;
pub mod support;
pub mod views;

use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;

use deocc_completion::rules::RulesCompleter;
use deocc_completion::{Completer, CompleterChain, Provenance};
use deocc_geometry::voxel::fuse_generated;
use deocc_geometry::PointCloud;

pub use deocc_io::scene::{read_scene, Frame, SceneInput};
pub use error::PipelineError;
pub use options::PipelineOptions;
pub use report::{CompletionRecord, InstanceReport, RunReport, StageTimings};

use crate::occlusion::{analyse_view_with, MaskOcclusion, OcclusionOptions};

/// What a run produces.
pub struct PipelineOutput {
    pub observed: PointCloud,
    pub completed: PointCloud,
    pub report: RunReport,
}

/// Registration facts a caller hands to [`run`] for its report (empty for posed input).
pub type Registration = Vec<registration::FrameRegistration>;

/// What a caller sees of a run as it goes, and how it stops one: [`run_observed`] calls
/// [`Observer::stage`] as each stage begins; `false` stops the run at that point with
/// [`PipelineError::Cancelled`] (everything it held is freed on the way out).
pub trait Observer: Sync {
    /// `stage` is about to begin; `fraction` of the run's usual time is done.
    fn stage(&self, stage: &'static str, fraction: f32) -> bool;
}

/// An observer that sees nothing and never stops a run.
pub struct Unobserved;

impl Observer for Unobserved {
    fn stage(&self, _: &'static str, _: f32) -> bool {
        true
    }
}

pub(crate) fn enter(observer: &dyn Observer, stage: &'static str) -> Result<(), PipelineError> {
    if observer.stage(stage, stages::progress(stage)) {
        Ok(())
    } else {
        Err(PipelineError::Cancelled { stage })
    }
}

/// The whole pipeline on a loaded scene whose frames all have instance maps
/// ([`instances::ensure_instances`] gives them one), completing with `chain`.
pub fn run(
    scene: &SceneInput,
    chain: &CompleterChain,
    opts: &PipelineOptions,
    registration: &Registration,
) -> Result<PipelineOutput, PipelineError> {
    run_observed(scene, chain, opts, registration, &Unobserved)
}

/// A scene made in memory (a service request, numpy arrays), end to end: unposed frames are
/// registered, frames without an instance map (every frame with `segment`) are segmented with
/// `segmenter`, then [`run_observed`].
pub fn run_in_memory(
    mut scene: SceneInput,
    chain: &CompleterChain,
    opts: &PipelineOptions,
    segmenter: &dyn segment::Segmenter,
    segment: bool,
    observer: &dyn Observer,
) -> Result<PipelineOutput, PipelineError> {
    let prepared = front::prepare_observed(&mut scene, opts, None, segmenter, segment, observer)?;
    run_prepared(&scene, chain, opts, prepared, observer)
}

/// [`run_observed`] on a scene the front half made ready ([`front::prepare`]); the report
/// carries what the front half did (its depth fills first, then the run's own).
pub fn run_prepared(
    scene: &SceneInput,
    chain: &CompleterChain,
    opts: &PipelineOptions,
    prepared: front::Prepared,
    observer: &dyn Observer,
) -> Result<PipelineOutput, PipelineError> {
    let mut out = run_observed(scene, chain, opts, &prepared.registration, observer)?;
    let own = std::mem::take(&mut out.report.depth_fill);
    out.report.depth_fill = prepared.depth_fill.into_iter().chain(own).collect();
    out.report.depth_clean = prepared.depth_clean;
    out.report.burst = prepared.burst;
    out.report.mask_rims = prepared.mask_rims;
    out.report.mask_holes = prepared.mask_holes;
    Ok(out)
}

/// [`run`], telling `observer` of each stage; it may stop the run between stages. The stages, in
/// order, each one function in the file named for it: depth filling (`depth.rs`, when the
/// options ask), reconstruction, occlusion and the instances to complete, view selection,
/// completion, the plane fill, fusion of the completions, the support, revolve and cuboid
/// stages, carving, fusion into the cloud, and the report.
pub fn run_observed(
    scene: &SceneInput,
    chain: &CompleterChain,
    opts: &PipelineOptions,
    registration: &Registration,
    observer: &dyn Observer,
) -> Result<PipelineOutput, PipelineError> {
    opts.validate()?;
    opts.check_links(chain)?;
    let t_all = Instant::now();
    let mut timings = StageTimings::default();
    let (filled, depth_fill) = fill_depth_first(scene, opts)?;
    let scene = filled.as_ref().unwrap_or(scene);
    check_input(scene, opts)?;
    enter(observer, "reconstruct")?;
    let t = Instant::now();
    let observed = reconstruct::reconstruct(scene, opts.observed_voxel_m)?;
    timings.reconstruct_s = t.elapsed().as_secs_f64();
    enter(observer, "occlusion")?;
    let t = Instant::now();
    let (occlusion, found, popts, to_complete) = occlusion_and_targets(scene, opts);
    timings.occlusion_s = t.elapsed().as_secs_f64();
    enter(observer, "select_views")?;
    let t = Instant::now();
    let stats: Vec<_> = scene.frames.iter().map(stats::view_stats).collect();
    let selected = views::select_all(scene, &stats, &to_complete, opts);
    timings.select_views_s = t.elapsed().as_secs_f64();
    enter(observer, "complete")?;
    let t = Instant::now();
    let (completed_crops, declined) =
        complete::complete_instances(scene, &stats, &selected, chain, opts, observer)?;
    timings.complete_s = t.elapsed().as_secs_f64();
    enter(observer, "fuse")?;
    // The plane fill first: the support and revolve stages stand objects on it; it joins last.
    let t = Instant::now();
    let fill = planes::plane_fill(scene, opts.complete_planes, found.as_ref(), &popts);
    timings.planes_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (generated, records) = fuse_completions(scene, chain, opts, &completed_crops, &declined);
    let run = (scene, opts, registration);
    let shaped = shape_stages(run, &observed, &fill, &selected, &records, generated);
    let (generated, points_carved) = carve_stage(shaped.generated, found.as_ref(), scene, opts);
    let completed = fuse_generated(&observed, &generated, opts.fusion_voxel_m)?;
    timings.fuse_s = t.elapsed().as_secs_f64();
    enter(observer, "planes")?;
    let t = Instant::now();
    let completed = join_plane_fill(completed, &fill, opts)?;
    timings.planes_s += t.elapsed().as_secs_f64();
    enter(observer, "report")?;
    timings.total_s = t_all.elapsed().as_secs_f64();

    let mut report = make_report(
        scene,
        chain,
        opts,
        occlusion,
        &selected,
        records,
        &observed,
        &completed,
        points_carved,
        declined.len(),
        timings,
        registration,
        &shaped.revolved,
        &shaped.boxed,
    );
    report.depth_fill = depth_fill;
    Ok(PipelineOutput {
        observed,
        completed,
        report,
    })
}

/// Every frame has an instance map (given, or made by `instances::ensure_instances`), and every
/// camera lies within the options' scene radius.
fn check_input(scene: &SceneInput, opts: &PipelineOptions) -> Result<(), PipelineError> {
    if scene.frames.iter().any(|f| f.instances.is_none()) {
        return Err(PipelineError::input(
            scene.dir.join("instances"),
            "every frame needs an instance map (instances/NAME.png), or call \
             instances::ensure_instances() to segment it",
        ));
    }
    check_scene_extent(scene, opts.max_scene_radius_m)
}

/// The revolve stage's limit on the share of a fitted solid the views see through: correct
/// fits 0-3% (pickup-v1 clean, pickup-v2 under the structured-light model), flasks fitted with
/// one circle 11-25%.
const REVOLVE_MAX_SEEN_THROUGH: f32 = 0.06;

/// Outline rays a revolved fit needs before the outline refits it (`revolve_outline`): a few
/// image rows on either side.
const REVOLVE_MIN_OUTLINE_RAYS: usize = 6;

/// Stage 6: the plane fill joins the cloud (when the options ask), after every other stage has
/// used it.
fn join_plane_fill(
    completed: PointCloud,
    fill: &PointCloud,
    opts: &PipelineOptions,
) -> Result<PointCloud, PipelineError> {
    if !opts.complete_planes {
        return Ok(completed);
    }
    Ok(fuse_generated(&completed, fill, opts.fusion_voxel_m)?)
}

/// Stage 0: the depth the sensor did not measure, filled first when the options ask for it (on
/// a copy: the caller's frames stay as they were read).
fn fill_depth_first(
    scene: &SceneInput,
    opts: &PipelineOptions,
) -> Result<(Option<SceneInput>, Vec<depth::DepthFillReport>), PipelineError> {
    if opts.fill_depth_max_gap_px == 0 {
        return Ok((None, Vec::new()));
    }
    let mut s = scene.clone();
    let source = depth::InterpolatedDepth {
        max_gap_px: opts.fill_depth_max_gap_px,
        ..Default::default()
    };
    let report = depth::fill_scene_depth(&mut s, &source, &depth::DepthFillOptions::default())?;
    Ok((Some(s), report))
}

/// What the occlusion stage hands on: each view's masks with their occlusion, the scene's
/// planes (when a later stage needs them) and their options, and the instances to complete with
/// their candidate views.
type Targets = (
    Vec<Vec<MaskOcclusion>>,
    Option<planes::ScenePlanes>,
    planes::PlaneOptions,
    BTreeMap<u16, Vec<(usize, usize)>>,
);

/// Stage 2: occlusion per view, and which instances to complete. Instances lying in the scene's
/// bounding planes (the floor, the walls, and the pieces a segmenter cut them into) are not
/// completed: the plane fill is their completion.
fn occlusion_and_targets(scene: &SceneInput, opts: &PipelineOptions) -> Targets {
    let oopts = OcclusionOptions {
        max_band_across_rows_px: opts.occlusion_max_band_across_rows_px,
    };
    let occlusion: Vec<Vec<MaskOcclusion>> = scene
        .frames
        .iter()
        .map(|f| {
            f.instances
                .as_ref()
                .map(|m| analyse_view_with(m, &f.depth, &oopts))
                .unwrap_or_default()
        })
        .collect();
    let popts = planes::PlaneOptions {
        min_rectangularity: opts.plane_min_rectangularity,
        fill_unmeasured: opts.plane_fill_unmeasured,
        mask_window_px: if opts.plane_fill_unmeasured {
            planes::PlaneOptions::default().mask_window_px
        } else {
            0
        },
        up: opts.up,
        ..planes::PlaneOptions::default()
    };
    let found = (opts.skip_plane_pieces || opts.complete_planes)
        .then(|| planes::ScenePlanes::find(scene, &popts));
    let mut not_completed = scene.structure_ids.clone();
    if let (true, Some(found)) = (opts.skip_plane_pieces, &found) {
        let pieces = planes::plane_pieces(found, &popts, opts.plane_piece_min_fraction);
        tracing::debug!("plane pieces, not completed: {pieces:?}");
        not_completed.extend(pieces);
    }
    let to_complete =
        occlusion::instances_to_complete(&occlusion, &not_completed, opts.complete_unoccluded);
    (occlusion, found, popts, to_complete)
}

/// Stage 5a: each completed crop fused into generated points at the observed scale, with the
/// settings of the completer that made it, the rules' fallback where the model expected to be
/// off, and the quality gate; a record for every crop, declined ones included.
fn fuse_completions(
    scene: &SceneInput,
    chain: &CompleterChain,
    opts: &PipelineOptions,
    completed_crops: &[complete::CompletedCrop],
    declined: &[complete::DeclinedCrop],
) -> (PointCloud, Vec<CompletionRecord>) {
    let mut generated = PointCloud::default();
    let mut records = Vec::new();
    let projectors: Vec<_> = scene.frames.iter().map(|f| f.camera.projector()).collect();
    for c in completed_crops {
        let link = &chain.links()[c.completer];
        let policy = opts.fuse_policy(link.name(), chain.policy(c.completer));
        let (mut cloud, mut rec, left_out) = fuse::fuse_completion_detailed(
            &c.window,
            &c.condition.visible,
            &c.completion,
            &scene.frames[c.window.view],
            link.name(),
            link.provenance(),
            &fuse::FuseOptions {
                spread: c.spread.as_ref().map(|spread| fuse::SpreadLimit {
                    spread,
                    max_m: opts.gate_max_depth_spread_m,
                }),
                median_px: policy.depth_median_for(c.window.metric_scale_m),
                max_thickness_m: policy.max_thickness_m,
                max_thickness_per_width: policy.max_thickness_per_width,
                seen_elsewhere: c.condition.seen_elsewhere.as_ref().map(|s| &s.depth[..]),
                // Only made when `skip_observed_far_side` is set (complete.rs).
                seen_behind: c.seen_behind.as_deref(),
                min_revealed_confidence: policy.min_revealed_confidence,
                max_expected_error_m: policy.max_expected_error_m,
                stated_error_m: policy.stated_error_m,
                only: None,
            },
        );
        // The pixels the model expected too far off, completed by the rules instead.
        let fallback =
            (policy.uncertain_to_rules && rec.accepted && left_out.count() > 0).then(|| {
                let rules = RulesCompleter {
                    resolution: c.window.resolution,
                    ..Default::default()
                };
                let rules_policy = opts.fuse_policy(rules.name(), rules.fuse_policy());
                fuse::fuse_completion(
                    &c.window,
                    &c.condition.visible,
                    &rules.complete_one(&c.condition),
                    &scene.frames[c.window.view],
                    "rules (where the model expected to be off)",
                    Provenance::Rules,
                    &fuse::FuseOptions {
                        max_thickness_m: rules_policy.max_thickness_m,
                        max_thickness_per_width: rules_policy.max_thickness_per_width,
                        seen_elsewhere: c.condition.seen_elsewhere.as_ref().map(|s| &s.depth[..]),
                        seen_behind: c.seen_behind.as_deref(),
                        only: Some(&left_out),
                        stated_error_m: rules_policy.stated_error_m,
                        ..Default::default()
                    },
                )
            });
        if rec.accepted {
            let v = gate::gate_completion(
                &cloud,
                scene,
                &projectors,
                opts.gate_min_mean_confidence,
                opts.gate_max_seen_through_fraction,
            );
            rec.mean_confidence = Some(v.mean_confidence);
            rec.seen_through_fraction = Some(v.seen_through_fraction);
            if let Some(why) = v.rejected {
                rec.accepted = false;
                rec.gated = true;
                rec.reason = format!("quality gate: {why}");
                rec.new_points = 0;
                cloud = PointCloud::default();
            }
        }
        generated.append(&cloud);
        let keep_fallback = rec.accepted;
        records.push(rec);
        if let Some((extra, extra_rec)) = fallback.filter(|_| keep_fallback) {
            if extra_rec.accepted {
                generated.append(&extra);
            }
            records.push(extra_rec);
        }
    }
    for d in declined {
        records.push(CompletionRecord::pending(
            d.instance_id,
            d.view,
            "none",
            format!("declined: {}", d.reasons.join("; ")),
        ));
    }
    (generated, records)
}

/// What the support, revolve and cuboid stages made.
struct Shaped {
    generated: PointCloud,
    revolved: Vec<revolve::RevolveRecord>,
    boxed: Vec<cuboid::CuboidRecord>,
}

/// Stages 5b-d (posed scenes, z up): hidden bottoms extended to the support below, upright
/// solids of revolution and boxes fitted in place of their completions, standing on what the
/// views and the plane fill show.
fn shape_stages(
    (scene, opts, registration): (&SceneInput, &PipelineOptions, &Registration),
    observed: &PointCloud,
    fill: &PointCloud,
    selected: &BTreeMap<u16, Vec<usize>>,
    records: &[CompletionRecord],
    mut generated: PointCloud,
) -> Shaped {
    if opts.extend_to_support && scene.posed && registration.is_empty() {
        let ids: BTreeSet<u16> = selected.keys().copied().collect();
        let mut both = observed.clone();
        both.append(&generated);
        both.append(fill);
        let extension = support::extend_to_support(
            &both,
            &ids,
            &support::SupportOptions {
                up: opts.up.into(),
                ..Default::default()
            },
        );
        generated.append(&extension.with_confidence(deocc_geometry::cloud::FILL_CONFIDENCE));
    }
    // The revolve and cuboid stages stand objects on what the views and the planes' fill show.
    let upright = scene.posed && registration.is_empty();
    let ground = if upright && (opts.revolve_upright || opts.cuboid_upright) {
        support::Ground::new(observed, fill, opts.up.into())
    } else {
        None
    };
    // Only what a completer of the chain completed: an empty chain means no completion.
    let mut ids: BTreeSet<u16> = records
        .iter()
        .filter(|r| r.accepted)
        .map(|r| r.instance_id)
        .collect();
    let mut revolved = Vec::new();
    if let Some(ground) = ground.as_ref().filter(|_| opts.revolve_upright) {
        let projectors: Vec<_> = scene.frames.iter().map(|f| f.camera.projector()).collect();
        let seen_through = |pts: &[nalgebra::Point3<f32>]| {
            let n = pts
                .iter()
                .filter(|p| carve::evidence(p, scene, &projectors) == carve::Evidence::SeenThrough)
                .count();
            n as f32 / pts.len().max(1) as f32
        };
        let cameras: Vec<_> = scene.frames.iter().map(|f| f.camera.center()).collect();
        let outline = |id: u16| revolve::outline_rays(&scene.frames, id);
        (generated, revolved) = revolve::revolve_instances(
            observed,
            &generated,
            ground,
            &ids,
            (
                &cameras,
                Some(&seen_through),
                opts.revolve_outline
                    .then_some(&outline as revolve::Outline<'_>),
            ),
            &revolve::RevolveOptions {
                // With the views' check the normals may be noisier than a fit alone may trust
                // (a sensor's normals on a bottle's side); chosen on pickup-v2's tuning scenes
                // under the structured-light model, pickup-v1's tuning scenes unchanged
                // (docs/decisions.md, "Expected errors in the cloud").
                max_seen_through_fraction: REVOLVE_MAX_SEEN_THROUGH,
                max_median_angle_deg: 12.0,
                max_p80_angle_deg: 24.0,
                rim_inset_m: opts.observed_voxel_m as f32 / 4.0,
                // A rim through voxel centroids wanders by up to half a voxel; 0.8 voxel here
                // and the side's 2 mm were chosen on pickup-v1's tuning seeds
                // (`deocc eval grasp --tuning`).
                max_top_residual_m: (0.8 * opts.observed_voxel_m as f32).max(0.002),
                min_outline_rays: REVOLVE_MIN_OUTLINE_RAYS,
                min_arc_deg: opts.revolve_min_arc_deg,
                max_rms_m: opts.revolve_max_residual_m,
                max_rms_fraction: opts.revolve_max_residual_fraction,
                ..Default::default()
            },
        );
    }
    let mut boxed = Vec::new();
    if let Some(ground) = ground.as_ref().filter(|_| opts.cuboid_upright) {
        // What the revolve stage took is done.
        ids.retain(|&id| {
            !revolved
                .iter()
                .any(|r| r.instance_id == id && r.fit.is_some())
        });
        (generated, boxed) = cuboid::cuboid_instances(
            observed,
            &generated,
            ground,
            &ids,
            &cuboid::CuboidOptions::default(),
        );
    }
    Shaped {
        generated,
        revolved,
        boxed,
    }
}

/// Stage 5e: generated points under the floor or behind a wall, and (when the options ask)
/// where a view saw through them, left out; how many went.
fn carve_stage(
    mut generated: PointCloud,
    found: Option<&planes::ScenePlanes>,
    scene: &SceneInput,
    opts: &PipelineOptions,
) -> (PointCloud, usize) {
    let mut points_carved = 0;
    if let (true, Some(found)) = (opts.carve_outside_bounding_planes_m > 0.0, found) {
        (generated, points_carved) = planes::keep_inside(
            &generated,
            &found.bounding,
            opts.carve_outside_bounding_planes_m,
        );
    }
    if opts.carve_generated {
        let carved;
        (generated, carved) = carve::keep_hidden(&generated, scene);
        points_carved += carved;
    }
    (generated, points_carved)
}

/// Every camera within `radius_m` of the cameras' median position, or an error naming the frame.
pub fn check_scene_extent(scene: &SceneInput, radius_m: f32) -> Result<(), PipelineError> {
    let centres: Vec<nalgebra::Point3<f32>> =
        scene.frames.iter().map(|f| f.camera.center()).collect();
    let median = |axis: usize| {
        let mut v: Vec<f32> = centres.iter().map(|c| c[axis]).collect();
        v.sort_by(f32::total_cmp);
        v.get(v.len() / 2).copied().unwrap_or(0.0)
    };
    let m = nalgebra::Point3::new(median(0), median(1), median(2));
    for (f, c) in scene.frames.iter().zip(&centres) {
        let d = (c - m).norm();
        if d.is_nan() || d > radius_m {
            return Err(PipelineError::input(
                scene.dir.join("cameras.json"),
                format!(
                    "frame {}: its camera is {d:.1} m from the other cameras' median position \
                     (more than max_scene_radius_m = {radius_m} m); is its pose right?",
                    f.name
                ),
            ));
        }
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn make_report(
    scene: &SceneInput,
    chain: &CompleterChain,
    opts: &PipelineOptions,
    occlusion: Vec<Vec<MaskOcclusion>>,
    selected: &BTreeMap<u16, Vec<usize>>,
    records: Vec<CompletionRecord>,
    observed: &PointCloud,
    completed: &PointCloud,
    points_carved: usize,
    crops_declined: usize,
    timings: StageTimings,
    registration: &Registration,
    revolved: &[revolve::RevolveRecord],
    boxed: &[cuboid::CuboidRecord],
) -> RunReport {
    let codes = completed.generated.as_deref().unwrap_or(&[]);
    let ids = completed.instance.as_deref().unwrap_or(&[]);
    let occluded_in = |id: u16| -> Vec<usize> {
        occlusion
            .iter()
            .enumerate()
            .filter(|(_, masks)| {
                masks
                    .iter()
                    .any(|m| m.instance_id == id && m.is_occluded() && !m.truncated)
            })
            .map(|(v, _)| v)
            .collect()
    };
    let instances: Vec<InstanceReport> = selected
        .iter()
        .map(|(&id, views)| InstanceReport {
            instance_id: id,
            occluded_in_views: occluded_in(id),
            selected_views: views.clone(),
            generated_points: codes
                .iter()
                .zip(ids)
                .filter(|(&g, &i)| g > 0 && i == id as u32)
                .count(),
            revolve: revolved.iter().find(|r| r.instance_id == id).cloned(),
            cuboid: boxed.iter().find(|r| r.instance_id == id).cloned(),
        })
        .collect();
    let objects_completed = records
        .iter()
        .filter(|r| r.accepted)
        .map(|r| r.instance_id)
        .collect::<BTreeSet<_>>()
        .len();
    let count = |p: Provenance| codes.iter().filter(|&&g| g == p.code()).count();
    let completions_gated = records.iter().filter(|r| r.gated).count();
    let points_spread_dropped = records.iter().map(|r| r.spread_dropped).sum();
    let points_uncertain_dropped = records.iter().map(|r| r.uncertain_dropped).sum();
    let points_far_side_observed = records.iter().map(|r| r.far_side_observed).sum();
    RunReport {
        frames: scene.frames.len(),
        options: opts.clone(),
        completers: chain.describe(),
        occlusion,
        instances,
        completions: records,
        objects_completed,
        objects_per_second: objects_completed as f64 / timings.total_s.max(1e-9),
        points_observed: observed.len(),
        points_generated: codes.iter().filter(|&&g| g > 0).count(),
        points_model: count(Provenance::Model),
        points_rules: count(Provenance::Rules),
        points_plane_fill: count(Provenance::PlaneFill),
        points_carved,
        crops_declined,
        completions_gated,
        points_spread_dropped,
        points_uncertain_dropped,
        points_far_side_observed,
        timings,
        poses: if registration.is_empty() {
            "given"
        } else {
            "icp"
        },
        registration: registration.clone(),
        peak_rss_mib: report::peak_rss_mib(),
        depth_fill: Vec::new(),
        depth_clean: Vec::new(),
        mask_rims: Vec::new(),
        mask_holes: Vec::new(),
        burst: Default::default(),
    }
}
