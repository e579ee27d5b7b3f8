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
    /// Per-object 3-D figures on bench-v1 with the default segmenter: each object's hidden
    /// surface covered by its own points, a row per completer (none, rules, gldot, gldot,rules),
    /// and the share of generated points on a true surface.
    Objects(ObjectsArgs),
    /// Grasping on pickup-v1 or pickup-v2 (`--preset`): antipodal grasps planned on the
    /// observed cloud, each completer's cloud and the ground truth, scored analytically on the
    /// ground truth (top-1 success at mu 0.4 / 0.8, AP, affordance IoU), light and heavy
    /// occlusion, by target kind and visibility, with the planner's reasons per scene; bootstrap
    /// intervals.
    Grasp(crate::robot_eval::GraspArgs),
    /// Placing on place-v1: placement maps of an 8 x 8 x 12 cm object from the observed cloud
    /// (unseen space free, and occupied), each completer's cloud and the ground truth; IoU,
    /// false-placeable rate and placement success with bootstrap intervals.
    Place(crate::robot_eval::PlaceArgs),
    /// Depth filling on bench-v1 rendered with the sensor model (no depth at grazing angles) and
    /// one object's depth dropped per view: each depth source fills the holes, scored against
    /// the noise-free depth (share filled, within 2 cm, relative error) with bootstrap intervals;
    /// rows: the interpolation, a perfect relative-depth model (the bound), and
    /// --depth-model if given.
    Depth(DepthArgs),
}

#[derive(Args)]
pub struct DepthArgs {
    #[arg(long, default_value = "bench/depth.json")]
    json: PathBuf,
    /// Number of bench-v1 scenes (the first N of its 50).
    #[arg(long, default_value_t = 50)]
    scenes: usize,
    /// Views per scene (the first N of its 10).
    #[arg(long, default_value_t = 3)]
    views: usize,
    /// Score bench-v1-like scenes of other seeds (9,050,000 on), not the test scenes: where the
    /// interpolation's settings are chosen.
    #[arg(long)]
    tuning: bool,
    /// Depth Anything V2 weights (safetensors, the original checkpoint's layout), scored as a
    /// row of its own.
    #[arg(long, value_name = "FILE")]
    depth_model: Option<PathBuf>,
    /// Write, for each of the first N scenes, a picture of its first view: RGB, the sensor's
    /// depth, each source's filled depth and the true depth (DIR/depth-SEED.png).
    #[arg(long, value_name = "DIR")]
    pictures: Option<PathBuf>,
    /// How many scenes get a picture with --pictures.
    #[arg(long, default_value_t = 6, requires = "pictures")]
    picture_scenes: usize,
}

fn depth(a: DepthArgs) -> Result<()> {
    if a.scenes == 0 || a.views == 0 {
        bail!("--scenes and --views must be at least 1");
    }
    let model = match &a.depth_model {
        Some(p) => Some(
            deocc_model::depth_anything::DepthAnything::load(p, &candle_core::Device::Cpu)
                .context("--depth-model")?,
        ),
        None => None,
    };
    let sources: Vec<(&str, &dyn deocc_pipeline::depth::DepthSource)> = model
        .iter()
        .map(|m| {
            (
                deocc_pipeline::depth::DepthSource::name(m),
                m as &dyn deocc_pipeline::depth::DepthSource,
            )
        })
        .collect();
    let n = if a.tuning {
        a.scenes
    } else {
        a.scenes.min(deocc_synth::dataset::bench_v1().seeds.len())
    };
    let writer = crate::report::PictureWriter::new(a.pictures.as_deref(), "depth")?;
    let mut write = |seed, img| writer.as_ref().map_or(Ok(()), |w| w.write(seed, img));
    let picture = writer.is_some().then_some((
        a.picture_scenes,
        &mut write as deocc_eval::place::PictureSink<'_>,
    ));
    let pb = crate::progress::bar(n as u64, "scenes");
    let report = deocc_eval::depth_fill::depth_fill_benchmark(
        &sources,
        n,
        a.views,
        a.tuning,
        picture,
        &mut || pb.inc(1),
    )?;
    pb.finish_and_clear();
    for row in &report.rows {
        for h in &row.holes {
            println!(
                "{:>28} {:>15}: filled {:.3} [{:.3}, {:.3}], within 2 cm {:.3} [{:.3}, {:.3}], abs rel {:.4} ({} px)",
                row.source,
                h.kind,
                h.filled.mean,
                h.filled.ci95[0],
                h.filled.ci95[1],
                h.within_2cm.mean,
                h.within_2cm.ci95[0],
                h.within_2cm.ci95[1],
                h.abs_rel.mean,
                h.hole_pixels
            );
        }
    }
    crate::report::write_report(&a.json, &report)?;
    Ok(())
}

#[derive(Args)]
pub struct ObjectsArgs {
    #[arg(long, default_value = "bench/objects.json")]
    json: PathBuf,
    /// GL-DoT model folder; default: the built-in model.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Number of bench-v1 scenes (the first N of its 50).
    #[arg(long, default_value_t = 50)]
    scenes: usize,
    /// Score bench-v1-like scenes of other seeds (9,050,000 on), not the test scenes: where
    /// limits such as the quality gate's are chosen.
    #[arg(long)]
    tuning: bool,
    /// Use the renderer's instance masks instead of the default segmenter: what the completers
    /// score when segmentation is right.
    #[arg(long)]
    ground_truth_masks: bool,
    #[command(flatten)]
    pipeline: crate::completers::PipelineArgs,
    #[command(flatten)]
    sensor: crate::sensor::SensorArgs,
}

fn objects(a: ObjectsArgs) -> Result<()> {
    let chains =
        crate::completers::named_chains(a.weights.as_deref(), &["rules", "gldot", "gldot,rules"])?;
    let opts = a.pipeline.options()?;
    let mut preset = deocc_synth::dataset::bench_v1();
    a.sensor.apply(&mut preset)?;
    if a.tuning {
        preset.name = format!("{} tuning scenes", preset.name);
        preset.seeds = (9_050_000..9_050_000 + a.scenes as u64).collect();
    }
    let n = a.scenes.min(preset.seeds.len());
    let pb = crate::progress::bar(n as u64, "scenes");
    let report = deocc_eval::objects::object_benchmark(
        &chains,
        &opts,
        &preset,
        n,
        a.ground_truth_masks,
        &mut || pb.inc(1),
    )?;
    pb.finish_and_clear();
    crate::report::write_report(&a.json, &report)?;
    Ok(())
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
    #[command(flatten)]
    sensor: crate::sensor::SensorArgs,
    /// Segment the rendered depth as it is, without the pipeline's depth front end.
    #[arg(long)]
    no_depth_clean: bool,
    /// Score bench-v1-like scenes of other seeds (9,050,000 on), not the test scenes: where the
    /// front end's and the segmenter's settings are chosen.
    #[arg(long)]
    tuning: bool,
    /// The depth front end's settings are the options file's `depth_clean`.
    #[command(flatten)]
    pipeline: crate::completers::PipelineArgs,
    #[command(flatten)]
    segmenter: SegmenterStudyArgs,
}

/// A study of the default segmenter's settings (the pipeline runs it with its defaults).
#[derive(Args)]
pub struct SegmenterStudyArgs {
    /// Label pixels without depth by colour up to this cost (`ConvexitySegmenter::hole_max_cost`;
    /// 0, the default, leaves them unlabelled; 10 is the value tuned for masks).
    #[arg(long, default_value_t = 0.0)]
    hole_colour_cost: f32,
}

impl SegmenterStudyArgs {
    fn segmenter(&self) -> Result<deocc_pipeline::segment::ConvexitySegmenter> {
        if !(self.hole_colour_cost >= 0.0 && self.hole_colour_cost.is_finite()) {
            bail!(
                "--hole-colour-cost {}: must be a finite cost >= 0",
                self.hole_colour_cost
            );
        }
        Ok(deocc_pipeline::segment::ConvexitySegmenter {
            hole_max_cost: self.hole_colour_cost,
            ..Default::default()
        })
    }
}

fn perception(a: PerceptionArgs) -> Result<()> {
    let total = a.scenes.min(deocc_synth::dataset::bench_v1().seeds.len())
        + a.failure_scenes
            .min(deocc_synth::dataset::chairs_v1().seeds.len());
    let pb = crate::progress::bar(total as u64, "scenes");
    let sensor = a.sensor.kind_without_burst("deocc eval perception")?;
    let opts = a.pipeline.options()?;
    let mut clean = opts.depth_clean.clone();
    clean.enabled &= !a.no_depth_clean;
    let report = deocc_eval::perception::perception_benchmark(
        a.scenes,
        a.failure_scenes,
        sensor,
        &clean,
        &a.segmenter.segmenter()?,
        &deocc_pipeline::occlusion::OcclusionOptions {
            max_band_across_rows_px: opts.occlusion_max_band_across_rows_px,
        },
        a.tuning,
        &mut || pb.inc(1),
    )?;
    pb.finish_and_clear();
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
    #[command(flatten)]
    pipeline: crate::completers::PipelineArgs,
    #[command(flatten)]
    sensor: crate::sensor::SensorArgs,
    #[command(flatten)]
    segmenter: SegmenterStudyArgs,
}

fn reconstruction(a: ReconstructionArgs) -> Result<()> {
    let chain = crate::completers::chain(&a.completers)?;
    let opts = a.pipeline.options()?;
    let n = a.scenes.min(deocc_synth::dataset::bench_v1().seeds.len());
    let pb = crate::progress::bar(n as u64, "scenes");
    let sensor = a.sensor.kind_without_burst("deocc eval reconstruction")?;
    let report = deocc_eval::reconstruction::reconstruction_benchmark(
        &chain,
        &opts,
        n,
        sensor,
        &a.segmenter.segmenter()?,
        &mut || pb.inc(1),
    )?;
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
    /// Also report the mIoU with the crops that carry other views' points at these thresholds
    /// (the others at the model's), comma-separated: chooses the shipped
    /// `mask_threshold_seen_elsewhere` on val.
    #[arg(long, value_delimiter = ',')]
    mask_thresholds_seen_elsewhere: Vec<f32>,
    /// Override the model's mask threshold (from its train.json) for every figure.
    #[arg(long, allow_hyphen_values = true)]
    mask_threshold: Option<f32>,
    /// Override the threshold of crops carrying other views' points (from its train.json):
    /// a number, or `none` (the plain threshold everywhere), as `deocc export` takes it.
    #[arg(long)]
    mask_threshold_seen_elsewhere: Option<String>,
    /// Override the samples averaged per completion (from its train.json; 1 if absent).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=16))]
    samples: Option<u32>,
    /// Override whether the geometric prior's pixels are always kept (from its train.json).
    #[arg(long)]
    keep_prior: Option<bool>,
    /// With a mean head: take colour and depth from the flow's sample after --main-steps steps
    /// instead of the mean head (for comparing the two).
    #[arg(long)]
    sample_flow: bool,
    /// Skip the cross-view run (about half the time).
    #[arg(long)]
    no_cross_view: bool,
    /// Leave out what the other views observed of each object (reprojected into the crop, as
    /// the pipeline does with several frames) from every completer's input: one view's answer.
    #[arg(long)]
    no_seen_elsewhere: bool,
    /// Median filter radius (pixels) of the model's depth over its amodal mask before scoring
    /// (the pipeline's `completers.gldot.depth_median_px`; default: the pipeline's); 0 = off.
    #[arg(long, value_parser = clap::value_parser!(u32).range(0..=16))]
    median_px: Option<u32>,
    /// The filter applies to pairs whose crop is no wider than this, metres (the pipeline's
    /// `completers.gldot.depth_median_max_crop_m`; default: the pipeline's); 0 = every pair.
    #[arg(long)]
    median_max_crop_m: Option<f32>,
    /// Bootstrap resamples of every interval.
    #[arg(long, default_value_t = 1000)]
    bootstrap: usize,
    /// The sensor of the test pairs rendered on the fly (pairs from --data carry their own).
    #[command(flatten)]
    sensor: crate::sensor::SensorArgs,
}

pub fn run(cmd: EvalCommand) -> Result<()> {
    match cmd {
        EvalCommand::Amodal(a) => amodal(a),
        EvalCommand::Reconstruction(a) => reconstruction(a),
        EvalCommand::Perception(a) => perception(a),
        EvalCommand::Objects(a) => objects(a),
        EvalCommand::Grasp(a) => crate::robot_eval::grasp(a),
        EvalCommand::Place(a) => crate::robot_eval::place(a),
        EvalCommand::Depth(a) => depth(a),
    }
}

/// Evaluation pairs: from a split's shards if given, else rendered from the test split's first
/// `scenes` scenes.
fn test_pairs(
    data: Option<&PathBuf>,
    split: &str,
    scenes: u64,
    sensor: deocc_synth::sensor::SensorKind,
) -> Result<PairData> {
    if let Some(dir) = data {
        if sensor != deocc_synth::sensor::SensorKind::Clean {
            bail!(
                "--sensor {} renders test pairs on the fly; pairs from --data carry the sensor \
                 they were made with (deocc synth pairs --sensor)",
                sensor.name()
            );
        }
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
            &PairConfig {
                sensor,
                ..PairConfig::default()
            },
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
    if let Some(th) = a.mask_threshold_seen_elsewhere.as_deref() {
        completer.mask_threshold_seen_elsewhere = crate::train::parse_optional_threshold(th)?;
    }
    if let Some(n) = a.samples {
        completer.samples = n as usize;
    }
    if let Some(keep) = a.keep_prior {
        completer.keep_prior = keep;
    }
    if a.sample_flow {
        completer.reads_mean = false;
    }
    let data = test_pairs(
        a.data.as_ref(),
        &a.split,
        120,
        a.sensor.kind_without_burst("deocc eval amodal")?,
    )?
    .with_mask_prior(completer.model.config.mask_prior)
    .with_seen_elsewhere(!a.no_seen_elsewhere);
    if !a.no_seen_elsewhere && !data.set.has_elsewhere() {
        eprintln!(
            "note: these pairs carry no other views' observations (made before they were \
             stored); make them again with `deocc synth pairs` to score what the pipeline does \
             with several frames"
        );
    }
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
    if let Some(w) = a.median_max_crop_m {
        if !(0.0..=10.0).contains(&w) {
            bail!("--median-max-crop-m {w} is outside [0, 10] m (0 = every pair)");
        }
    }
    // The depth figures are of what the pipeline fuses: its median filter by default.
    let learned = deocc_completion::FusePolicy::LEARNED;
    let opts = AmodalEvalOptions {
        pairs: a.pairs,
        main_steps: a.main_steps as usize,
        sweep_steps: a.sweep_steps.clone(),
        sweep_pairs: a.sweep_pairs,
        mask_thresholds: a.mask_thresholds.clone(),
        mask_thresholds_seen_elsewhere: a.mask_thresholds_seen_elsewhere.clone(),
        bootstrap_resamples: a.bootstrap,
        skip_cross_view: a.no_cross_view,
        depth_median_px: a.median_px.map_or(learned.depth_median_px, |r| r as usize),
        depth_median_max_crop_m: a
            .median_max_crop_m
            .unwrap_or(learned.depth_median_max_crop_m),
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
    // The run without the other views' observations, when the pairs carry them.
    let single = if data.set.has_elsewhere() && data.seen_elsewhere() {
        n
    } else {
        0
    };
    let pb = crate::progress::bar((n + multi + sweep + single) as u64, "completions");
    let report = evaluate_amodal(&completer, &data, &a.split, &opts, &mut |k| {
        pb.inc(k as u64)
    })?;
    pb.finish_and_clear();
    crate::report::write_report(&a.json, &report)?;
    Ok(())
}
