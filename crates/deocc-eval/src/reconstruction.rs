//! 3-D figures of a reconstruction against a benchmark scene's dense ground truth.

use serde::Serialize;

pub use deocc_pipeline::ground_truth::{
    align_to_ground_truth, evaluate_run, figures, gain, in_frustum, read_ground_truth,
    EvalGroundTruth, MethodFigures, RunEvaluation,
};

/// One row of the results table: a method's figures averaged over scenes.
#[derive(Debug, Clone, Serialize)]
pub struct TableRow {
    pub method: String,
    pub scenes: usize,
    pub accuracy_mean: f64,
    pub completeness_mean: f64,
    pub chamfer: f64,
    pub fscore: f64,
    pub completeness_hidden_mean: f64,
    pub recall_hidden: f64,
}

pub fn average_row(method: &str, figs: &[MethodFigures]) -> TableRow {
    let n = figs.len().max(1) as f64;
    let avg = |f: &dyn Fn(&MethodFigures) -> f64| figs.iter().map(f).sum::<f64>() / n;
    TableRow {
        method: method.into(),
        scenes: figs.len(),
        accuracy_mean: avg(&|m| m.whole_scene.accuracy_mean),
        completeness_mean: avg(&|m| m.whole_scene.completeness_mean),
        chamfer: avg(&|m| m.whole_scene.chamfer),
        fscore: avg(&|m| m.whole_scene.fscore),
        completeness_hidden_mean: avg(&|m| m.hidden_region.completeness_mean),
        recall_hidden: avg(&|m| m.hidden_region.recall),
    }
}

/// `deocc eval reconstruction`: bench-v1 scenes, visible-only against de-occlusion with the
/// ground-truth masks and with the default segmenter, and the segmenter's run without the plane
/// fill (what the object completions alone add).
#[derive(Debug, Clone, Serialize)]
pub struct ReconstructionReport {
    pub benchmark: String,
    pub scenes: usize,
    pub completers: String,
    pub rows: Vec<TableRow>,
    pub completeness_gain_whole_scene: f64,
    pub completeness_gain_hidden_region: f64,
    pub accuracy_change: f64,
    pub chamfer_gain: f64,
    pub completeness_gain_whole_scene_segmenter: f64,
    pub completeness_gain_hidden_region_segmenter: f64,
    pub accuracy_change_segmenter: f64,
    /// The same gains without the plane fill: what the completer alone adds.
    pub completeness_gain_whole_scene_segmenter_objects_only: f64,
    pub completeness_gain_hidden_region_segmenter_objects_only: f64,
    pub objects_completed: usize,
    pub objects_per_second: f64,
    /// Wall seconds a scene takes from its frames to the completed cloud, the front half (depth
    /// front end, and with the segmenter its segmentation) included: mean and largest, with the
    /// given masks and with the default segmenter. What issue 46 compares across sensors.
    pub seconds_per_scene: TimeSummary,
    pub seconds_per_scene_segmenter: TimeSummary,
    /// The machine and its load when the run began (timings from a loaded machine are not a
    /// quiet machine's).
    pub machine: crate::bench::timing::Machine,
    pub mean_stage_seconds: deocc_pipeline::StageTimings,
}

/// Mean and largest of a set of timings, seconds.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct TimeSummary {
    pub mean: f64,
    pub max: f64,
}

impl TimeSummary {
    pub fn of(seconds: &[f64]) -> Self {
        if seconds.is_empty() {
            return Self::default();
        }
        Self {
            mean: seconds.iter().sum::<f64>() / seconds.len() as f64,
            max: seconds.iter().copied().fold(f64::MIN, f64::max),
        }
    }
}

/// Runs [`ReconstructionReport`] on the first `scenes` of bench-v1; `tick` is called after each.
/// The segmenter rows use `segmenter` (the default one unless a study changes it).
pub fn reconstruction_benchmark(
    chain: &deocc_completion::CompleterChain,
    opts: &deocc_pipeline::PipelineOptions,
    scenes: usize,
    sensor: deocc_synth::sensor::SensorKind,
    segmenter: &deocc_pipeline::segment::ConvexitySegmenter,
    tick: &mut dyn FnMut(),
) -> Result<ReconstructionReport, crate::EvalError> {
    let mut preset = deocc_synth::dataset::bench_v1();
    crate::with_sensor(&mut preset, sensor);
    let n = scenes.min(preset.seeds.len());
    let (mut vis_figs, mut deo_figs, mut seg_figs) = (Vec::new(), Vec::new(), Vec::new());
    let mut seg_objects_figs = Vec::new();
    let (mut objects, mut total_s) = (0usize, 0f64);
    let mut stages = deocc_pipeline::StageTimings::default();
    let machine = crate::bench::timing::Machine::now();
    let (mut wall, mut wall_seg) = (Vec::new(), Vec::new());
    for &seed in &preset.seeds[..n] {
        let rendered = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        let scene = rendered.scene_input();
        // The product's front half (the depth front end on every frame) before each run.
        let mut scene = scene;
        let unlabelled_input = crate::scenes::unlabelled(scene.clone());
        let started = std::time::Instant::now();
        let prepared = deocc_pipeline::front::prepare(&mut scene, opts, None, segmenter, false)?;
        let out = deocc_pipeline::run_prepared(
            &scene,
            chain,
            opts,
            prepared,
            &deocc_pipeline::Unobserved,
        )?;
        wall.push(started.elapsed().as_secs_f64());
        let cams: Vec<_> = scene.frames.iter().map(|f| f.camera).collect();
        let gt = in_frustum(
            &rendered.ground_truth.cloud,
            &rendered.ground_truth.seen,
            &cams,
        );
        vis_figs.push(figures(&align_to_ground_truth(&out.observed, &gt)?, &gt)?);
        deo_figs.push(figures(&align_to_ground_truth(&out.completed, &gt)?, &gt)?);
        // The same scene with the default segmenter instead of the ground-truth masks.
        let mut unlabelled = unlabelled_input;
        let started = std::time::Instant::now();
        let prepared =
            deocc_pipeline::front::prepare(&mut unlabelled, opts, None, segmenter, true)?;
        let seg_out = deocc_pipeline::run_prepared(
            &unlabelled,
            chain,
            opts,
            prepared,
            &deocc_pipeline::Unobserved,
        )?;
        wall_seg.push(started.elapsed().as_secs_f64());
        seg_figs.push(figures(
            &align_to_ground_truth(&seg_out.completed, &gt)?,
            &gt,
        )?);
        // What the completer alone adds: the same cloud without the plane fill.
        let plane = deocc_geometry::Provenance::PlaneFill.code();
        let objects_only = {
            let g = seg_out.completed.generated.as_deref().unwrap_or(&[]);
            seg_out
                .completed
                .filter(|i| g.get(i).copied().unwrap_or(0) != plane)
        };
        seg_objects_figs.push(figures(&align_to_ground_truth(&objects_only, &gt)?, &gt)?);
        objects += out.report.objects_completed;
        total_s += out.report.timings.total_s;
        stages.add_scaled(&out.report.timings, 1.0 / n as f64);
        tick();
    }
    let vis = average_row("visible-only", &vis_figs);
    let deo = average_row("+ de-occlusion (ground-truth masks)", &deo_figs);
    let seg = average_row("+ de-occlusion (default segmenter)", &seg_figs);
    let seg_objects = average_row(
        "+ de-occlusion, objects only, no plane fill (default segmenter)",
        &seg_objects_figs,
    );
    Ok(ReconstructionReport {
        benchmark: preset.name.clone(),
        scenes: n,
        completers: chain.describe(),
        completeness_gain_whole_scene: gain(vis.completeness_mean, deo.completeness_mean),
        completeness_gain_hidden_region: gain(
            vis.completeness_hidden_mean,
            deo.completeness_hidden_mean,
        ),
        accuracy_change: deo.accuracy_mean / vis.accuracy_mean - 1.0,
        chamfer_gain: gain(vis.chamfer, deo.chamfer),
        completeness_gain_whole_scene_segmenter: gain(vis.completeness_mean, seg.completeness_mean),
        completeness_gain_hidden_region_segmenter: gain(
            vis.completeness_hidden_mean,
            seg.completeness_hidden_mean,
        ),
        accuracy_change_segmenter: seg.accuracy_mean / vis.accuracy_mean - 1.0,
        completeness_gain_hidden_region_segmenter_objects_only: gain(
            vis.completeness_hidden_mean,
            seg_objects.completeness_hidden_mean,
        ),
        completeness_gain_whole_scene_segmenter_objects_only: gain(
            vis.completeness_mean,
            seg_objects.completeness_mean,
        ),
        rows: vec![vis, deo, seg, seg_objects],
        objects_completed: objects,
        objects_per_second: objects as f64 / total_s.max(1e-9),
        seconds_per_scene: TimeSummary::of(&wall),
        seconds_per_scene_segmenter: TimeSummary::of(&wall_seg),
        machine,
        mean_stage_seconds: stages,
    })
}
