//! `deocc eval`: figures on held-out data, written to a JSON report.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use deocc_eval::amodal::{evaluate_amodal, AmodalEvalOptions};
use deocc_model::data::{shards, PairData};
use deocc_synth::pairs::{split_scene_pairs, PairConfig, PairSet, Split};

#[derive(Subcommand)]
pub enum EvalCommand {
    /// 2-D amodal completion on held-out test pairs: mIoU per step count and baselines, occlusion
    /// levels, held-out shapes, cross-view gain, hidden-part depth error, completions per second.
    Amodal(AmodalArgs),
    /// 3-D reconstruction on bench-v1 test scenes: visible-only against + de-occlusion, after ICP
    /// to the ground truth; Chamfer, accuracy, completeness (whole and hidden region), objects/s.
    Reconstruction(ReconstructionArgs),
    /// Perception on bench-v1 scenes: occlusion detection precision/recall/F1 (ground-truth
    /// masks) and cross-view grouping ARI (adaptive tau against fixed ones).
    Perception(PerceptionArgs),
}

#[derive(Args)]
pub struct PerceptionArgs {
    #[arg(long, default_value = "bench/perception.json")]
    json: PathBuf,
    /// Number of bench-v1 scenes (the first N of its 50).
    #[arg(long, default_value_t = 50)]
    scenes: usize,
    /// Number of chairs-v1 scenes (hollow-back chairs, the named failure case; 0 skips them).
    #[arg(long, default_value_t = 10)]
    failure_scenes: usize,
}

/// The named failure case on its own scenes (`chairs-v1`: hollow-back chairs).
#[derive(serde::Serialize)]
struct FailureCaseFigures {
    benchmark: String,
    scenes: usize,
    /// Grouping of chair masks (ground-truth masks), adaptive tau and the fixed 5 cm one.
    grouping_ari_chairs: f64,
    grouping_ari_chairs_fixed_0_05: f64,
    /// Default segmenter: mIoU of chairs and of every object.
    segmenter_miou_chairs: f64,
    segmenter_miou: f64,
}

#[derive(serde::Serialize)]
struct PerceptionReport {
    benchmark: String,
    scenes: usize,
    occlusion_precision: f64,
    occlusion_recall: f64,
    occlusion_f1: f64,
    occlusion_counts: deocc_eval::perception::DetectionCounts,
    /// Grouping with the adaptive threshold (the default).
    grouping_ari: f64,
    grouping_ari_chairs: f64,
    grouping_ablation: Vec<deocc_eval::perception::GroupingFigures>,
    /// Default RGB-D segmenter: mean IoU of ground-truth object instances (>= 50 px, room
    /// structure excluded) with their best segment, and occlusion detection on its masks.
    segmenter_miou: f64,
    /// The same including floor and walls (split by whatever stands on them).
    segmenter_miou_with_structure: f64,
    segmenter_occlusion_precision: f64,
    segmenter_occlusion_recall: f64,
    segmenter_occlusion_f1: f64,
    segmenter_views_per_second: f64,
    /// Segmenter mIoU per category (floor and walls included).
    segmenter_miou_by_category: std::collections::BTreeMap<String, f64>,
    hollow_back_chairs: Option<FailureCaseFigures>,
}

fn failure_case(scenes: usize) -> Result<FailureCaseFigures> {
    use deocc_eval::perception::{grouping, segmenter_figures, DetectionCounts, SegmenterIous};
    use deocc_pipeline::matching::Threshold;
    let mut preset = deocc_synth::dataset::chairs_v1();
    preset.config.gt_points_per_m2 = 10.0;
    let n = scenes.min(preset.seeds.len());
    let segmenter = deocc_pipeline::segment::ConvexitySegmenter::default();
    let mut ious = SegmenterIous::default();
    let mut counts = DetectionCounts::default();
    let (mut adaptive, mut fixed, mut k) = (0.0, 0.0, 0usize);
    let pb = crate::progress::bar(n as u64, "chairs-v1 scenes");
    for &seed in &preset.seeds[..n] {
        let r = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        segmenter_figures(&r, &segmenter, &mut counts, &mut ious);
        if let (Some(a), Some(f)) = (
            grouping(&r, Threshold::Adaptive).1,
            grouping(&r, Threshold::Fixed(0.05)).1,
        ) {
            adaptive += a;
            fixed += f;
            k += 1;
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    Ok(FailureCaseFigures {
        benchmark: preset.name,
        scenes: n,
        grouping_ari_chairs: adaptive / k.max(1) as f64,
        grouping_ari_chairs_fixed_0_05: fixed / k.max(1) as f64,
        segmenter_miou_chairs: ious
            .per_category()
            .get("chair")
            .copied()
            .unwrap_or(f64::NAN),
        segmenter_miou: ious.miou_objects(),
    })
}

fn perception(a: PerceptionArgs) -> Result<()> {
    use deocc_eval::perception::{grouping, occlusion_counts, DetectionCounts, GroupingFigures};
    use deocc_pipeline::matching::Threshold;
    let mut preset = deocc_synth::dataset::bench_v1();
    preset.config.gt_points_per_m2 = 10.0; // ground truth is not used here
    let n = a.scenes.min(preset.seeds.len());
    let thresholds = [
        ("adaptive".to_string(), Threshold::Adaptive),
        ("fixed 0.05 m".into(), Threshold::Fixed(0.05)),
        ("fixed 0.15 m".into(), Threshold::Fixed(0.15)),
        ("fixed 0.50 m".into(), Threshold::Fixed(0.5)),
    ];
    let mut counts = DetectionCounts::default();
    let mut seg_counts = DetectionCounts::default();
    let segmenter = deocc_pipeline::segment::ConvexitySegmenter::default();
    let mut seg_ious = deocc_eval::perception::SegmenterIous::default();
    let (mut seg_time, mut seg_views) = (0.0f64, 0usize);
    let mut sums = vec![(0.0f64, 0.0f64, 0usize, 0.0f64); thresholds.len()];
    let pb = crate::progress::bar(n as u64, "scenes");
    for &seed in &preset.seeds[..n] {
        let r = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        occlusion_counts(&r, &mut counts);
        let t0 = std::time::Instant::now();
        deocc_eval::perception::segmenter_figures(&r, &segmenter, &mut seg_counts, &mut seg_ious);
        seg_time += t0.elapsed().as_secs_f64();
        seg_views += r.views.len();
        for (k, (_, t)) in thresholds.iter().enumerate() {
            let (ari, chairs, tau) = grouping(&r, *t);
            sums[k].0 += ari;
            if let Some(c) = chairs {
                sums[k].1 += c;
                sums[k].2 += 1;
            }
            sums[k].3 += tau as f64;
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    let ablation: Vec<GroupingFigures> = thresholds
        .iter()
        .zip(&sums)
        .map(|((name, _), s)| GroupingFigures {
            threshold: name.clone(),
            ari_mean: s.0 / n as f64,
            ari_chairs_mean: s.1 / s.2.max(1) as f64,
            tau_mean_m: s.3 / n as f64,
        })
        .collect();
    let report = PerceptionReport {
        benchmark: preset.name.clone(),
        scenes: n,
        occlusion_precision: counts.precision(),
        occlusion_recall: counts.recall(),
        occlusion_f1: counts.f1(),
        occlusion_counts: counts,
        grouping_ari: ablation[0].ari_mean,
        grouping_ari_chairs: ablation[0].ari_chairs_mean,
        grouping_ablation: ablation,
        segmenter_miou: seg_ious.miou_objects(),
        segmenter_miou_with_structure: seg_ious.miou_all(),
        segmenter_occlusion_precision: seg_counts.precision(),
        segmenter_occlusion_recall: seg_counts.recall(),
        segmenter_occlusion_f1: seg_counts.f1(),
        // Includes the occlusion analysis and scoring: a lower bound on the segmenter alone.
        segmenter_views_per_second: seg_views as f64 / seg_time.max(1e-9),
        segmenter_miou_by_category: seg_ious.per_category(),
        hollow_back_chairs: (a.failure_scenes > 0)
            .then(|| failure_case(a.failure_scenes))
            .transpose()?,
    };
    crate::report::write_report(&a.json, &report)?;
    Ok(())
}

#[derive(Args)]
pub struct ReconstructionArgs {
    #[arg(long, default_value = "bench/reconstruction.json")]
    json: PathBuf,
    #[command(flatten)]
    completers: crate::completers::CompleterArgs,
    /// Number of bench-v1 scenes (the first N of its 50).
    #[arg(long, default_value_t = 50)]
    scenes: usize,
    #[arg(long, default_value_t = 4)]
    steps: usize,
}

fn reconstruction(a: ReconstructionArgs) -> Result<()> {
    let chain = crate::completers::chain(&a.completers)?;
    let opts = deocc_pipeline::PipelineOptions {
        steps: a.steps,
        ..Default::default()
    };
    opts.validate()?;
    let n = a.scenes.min(deocc_synth::dataset::bench_v1().seeds.len());
    let pb = crate::progress::bar(n as u64, "scenes");
    let report =
        deocc_eval::reconstruction::reconstruction_benchmark(&chain, &opts, n, &mut || pb.inc(1))?;
    pb.finish_and_clear();
    crate::report::write_report(&a.json, &report)?;
    Ok(())
}

#[derive(Args)]
pub struct AmodalArgs {
    #[arg(long, default_value = "bench/amodal.json")]
    json: PathBuf,
    /// GL-DoT model folder (train.json + ema.safetensors or model.safetensors). Default: the
    /// shipped model built into this binary.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Folder with {split}-*.safetensors shards; without it, test pairs are rendered on the fly
    /// from the first 120 test scenes (the same pairs `deocc synth pairs --split test --scenes
    /// 120` writes).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Evaluate only the first N pairs (default: the whole split).
    #[arg(long)]
    pairs: Option<usize>,
    /// The step count of every figure but the step sweep.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u32).range(1..=1000))]
    main_steps: u32,
    /// Step counts of the sweep, comma-separated (run on the first --sweep-pairs pairs).
    #[arg(long, default_value = "1,4,50", value_delimiter = ',')]
    sweep_steps: Vec<usize>,
    #[arg(long, default_value_t = 300)]
    sweep_pairs: usize,
    /// Which shards of --data to use: test (held-out, the reported figures) or val (for choosing
    /// the mask threshold).
    #[arg(long, default_value = "test")]
    split: String,
    /// Also report the main-steps mIoU at these mask thresholds, comma-separated (a probability
    /// for models with a mask head, the mask channel in [-1, 1] otherwise).
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    mask_thresholds: Vec<f32>,
    /// Override the model's mask threshold (from its train.json) for every figure.
    #[arg(long, allow_hyphen_values = true)]
    mask_threshold: Option<f32>,
    /// Override the samples averaged per completion (from its train.json; 1 if absent).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=16))]
    samples: Option<u32>,
    /// Override whether the geometric prior's pixels are always kept (from its train.json).
    #[arg(long)]
    keep_prior: Option<bool>,
    /// Skip the cross-view run (about half the time).
    #[arg(long)]
    no_cross_view: bool,
    /// Bootstrap resamples of every interval.
    #[arg(long, default_value_t = 1000)]
    bootstrap: usize,
}

pub fn run(cmd: EvalCommand) -> Result<()> {
    match cmd {
        EvalCommand::Amodal(a) => amodal(a),
        EvalCommand::Reconstruction(a) => reconstruction(a),
        EvalCommand::Perception(a) => perception(a),
    }
}

/// Evaluation pairs: from a split's shards if given, else rendered from the test split's first
/// `scenes` scenes.
fn test_pairs(data: Option<&PathBuf>, split: &str, scenes: u64) -> Result<PairData> {
    if let Some(dir) = data {
        let files = shards(dir, split)
            .with_context(|| format!("{}: cannot list {split} pairs", dir.display()))?;
        if files.is_empty() {
            bail!(
                "{}: no {split}-*.safetensors shards (make them with `deocc synth pairs --split {split} --out {}`)",
                dir.display(),
                dir.display()
            );
        }
        return Ok(PairData::load(&files)?);
    }
    let mut set = PairSet::default();
    for scene in 0..scenes {
        set.extend(&split_scene_pairs(
            Split::Test,
            scene,
            &PairConfig::default(),
        )?);
    }
    Ok(PairData::new(set))
}

fn amodal(a: AmodalArgs) -> Result<()> {
    if a.split != "test" && a.split != "val" {
        bail!("--split must be test or val, not '{}'", a.split);
    }
    if a.split == "val" && a.data.is_none() {
        bail!("--split val needs --data (a folder with val-*.safetensors shards)");
    }
    let mut completer = crate::completers::load_gldot(a.weights.as_deref())?;
    if let Some(th) = a.mask_threshold {
        completer.mask_threshold = th;
    }
    if let Some(n) = a.samples {
        completer.samples = n as usize;
    }
    if let Some(keep) = a.keep_prior {
        completer.keep_prior = keep;
    }
    let data = test_pairs(a.data.as_ref(), &a.split, 120)?
        .with_mask_prior(completer.model.config.mask_prior);
    if data.resolution() != completer.resolution() {
        bail!(
            "{} pairs are {0}x{0} but the model expects {1}x{1}",
            data.resolution(),
            completer.resolution(),
        );
    }
    if a.bootstrap == 0 {
        bail!("--bootstrap must be at least 1");
    }
    let opts = AmodalEvalOptions {
        pairs: a.pairs,
        main_steps: a.main_steps as usize,
        sweep_steps: a.sweep_steps.clone(),
        sweep_pairs: a.sweep_pairs,
        mask_thresholds: a.mask_thresholds.clone(),
        bootstrap_resamples: a.bootstrap,
        skip_cross_view: a.no_cross_view,
        ..AmodalEvalOptions::default()
    };
    let n = opts.pairs.unwrap_or(data.len()).min(data.len());
    let multi = if a.no_cross_view { 0 } else { n };
    let sweep: usize = opts
        .sweep_steps
        .iter()
        .filter(|&&s| s != opts.main_steps)
        .count()
        * opts.sweep_pairs.min(n);
    eprintln!("evaluating {n} {} pairs", a.split);
    let pb = crate::progress::bar((n + multi + sweep) as u64, "completions");
    let report = evaluate_amodal(&completer, &data, &a.split, &opts, &mut |k| {
        pb.inc(k as u64)
    })?;
    pb.finish_and_clear();
    crate::report::write_report(&a.json, &report)?;
    Ok(())
}
