//! `deocc run`: the pipeline on a scene folder (or a built-in example), its output folder written
//! atomically by the pipeline's output stage.

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};
use clap::Args;
use deocc_pipeline::depth::DepthSource;
use deocc_pipeline::output::{write_output, Staging};
use deocc_pipeline::segment::ConvexitySegmenter;
use deocc_pipeline::PipelineOptions;

use crate::completers::CompleterArgs;
use crate::depth::DepthArgs;

#[derive(Args)]
pub struct RunArgs {
    /// Scene folder (rgb/, depth/, cameras.json, optional instances/), TUM RGB-D sequence
    /// folder (rgb.txt, depth.txt, groundtruth.txt), MCAP recording (.mcap) or MRPT rawlog of
    /// RGB-D observations (.rawlog).
    input: Option<PathBuf>,
    #[command(flatten)]
    input_args: crate::input::InputArgs,
    /// Output folder (replaced if it holds a previous run's output).
    #[arg(long)]
    out: PathBuf,
    /// Run on the built-in example: bench-v1 scene 0 (ten views and its ground truth).
    #[arg(long)]
    example: bool,
    #[command(flatten)]
    completers: CompleterArgs,
    #[command(flatten)]
    depth: DepthArgs,
    /// Pipeline options from a JSON file (any field of the run report's `options`); the flags
    /// below override it.
    #[arg(long)]
    options: Option<PathBuf>,
    /// Denoising steps (1-1000).
    #[arg(long)]
    steps: Option<usize>,
    /// Weight of the other views in the conditioning, in [0, 1] (0 = single view).
    #[arg(long)]
    rho: Option<f32>,
    /// Ignore given instance maps and segment with the default RGB-D segmenter (frames without an
    /// instance map are always segmented).
    #[arg(long)]
    segment: bool,
    /// Also write OUT/recording.mcap: cameras, images, depth, instances and the cloud by
    /// provenance, in Foxglove's schemas (open it in Foxglove Studio).
    #[arg(long)]
    mcap: bool,
}

/// How [`run_scene`] reads and what it writes besides the output: segment even frames with
/// instance maps, write `recording.mcap`, and how to read recordings and sequences.
#[derive(Default)]
pub struct RunHow {
    pub segment: bool,
    pub mcap: bool,
    pub input: deocc_pipeline::recording::RecordingOptions,
}

/// What [`run_scene`] made: the pipeline's result, the evaluation against the scene's ground
/// truth (if it has one), and the output folder.
pub struct SceneRun {
    pub result: deocc_pipeline::PipelineOutput,
    pub evaluation: Option<deocc_pipeline::ground_truth::RunEvaluation>,
    pub out: PathBuf,
}

/// Runs the pipeline on the scene folder `input` (or the built-in example when `None`) and
/// writes its output folder `out` atomically: read, fill the depth the sensor did not measure
/// from `depth` when given (the options' interpolation runs inside the pipeline), register unposed frames, segment frames
/// without instance maps (all frames with `segment`), complete, evaluate against
/// `ground_truth.ply` if the scene has one, write, swap in.
pub fn run_scene(
    input: Option<&Path>,
    out: &Path,
    chain: &deocc_completion::CompleterChain,
    opts: &PipelineOptions,
    depth: Option<&dyn DepthSource>,
    how: &RunHow,
) -> Result<SceneRun> {
    let (segment, mcap, input_opts) = (how.segment, how.mcap, &how.input);
    let staging = Staging::begin(out, input)?;
    let (input_dir, reported_input) = match input {
        Some(p) => (p.to_path_buf(), p.to_path_buf()),
        None => {
            let dir = staging.dir().join("input");
            crate::example::write_example_scene(&dir)?;
            (dir, staging.out().join("input"))
        }
    };
    let mut scene = deocc_pipeline::recording::read_input(&input_dir, input_opts)?;
    // The recording holds the input as read (before the depth front end and segmentation), so
    // `deocc run recording.mcap` repeats this run.
    let as_read = mcap.then(|| scene.clone());
    let prepared = deocc_pipeline::front::prepare(
        &mut scene,
        opts,
        depth,
        &ConvexitySegmenter::default(),
        segment,
    )?;
    if prepared.segmented > 0 {
        eprintln!(
            "segmented the frames with the default RGB-D segmenter: {} instances across views",
            prepared.segmented
        );
    }
    let result =
        deocc_pipeline::run_prepared(&scene, chain, opts, prepared, &deocc_pipeline::Unobserved)?;
    crate::depth::print_depth_fill(&result.report.depth_fill);
    let gt_path = input_dir.join("ground_truth.ply");
    let evaluation = if gt_path.exists() {
        let (gt, seen) = deocc_pipeline::ground_truth::read_ground_truth(&gt_path)?;
        let cams: Vec<_> = scene.frames.iter().map(|f| f.camera).collect();
        Some(deocc_pipeline::ground_truth::evaluate_run(
            &gt,
            &seen,
            &cams,
            &result.observed,
            &result.completed,
        )?)
    } else {
        None
    };
    write_output(
        staging.dir(),
        &reported_input,
        &scene,
        &result,
        evaluation.as_ref(),
    )?;
    if mcap {
        let robot = scene.frames[0]
            .camera
            .world_from_camera
            .translation
            .vector
            .into();
        let annotations = crate::robot::recording_annotations(&result.completed, robot);
        deocc_pipeline::record::write_mcap(
            &staging.dir().join("recording.mcap"),
            as_read.as_ref().unwrap_or(&scene),
            &result.completed,
            Some(&annotations),
        )?;
    }
    let out = staging.commit()?;
    Ok(SceneRun {
        result,
        evaluation,
        out,
    })
}

pub fn run(a: RunArgs) -> Result<()> {
    let input = match (&a.input, a.example) {
        (Some(_), true) => bail!("give an INPUT folder or --example, not both"),
        (None, false) => {
            bail!("give an INPUT scene folder, or --example to run on a generated benchmark scene")
        }
        (Some(p), false) => Some(p.clone()),
        (None, true) => None,
    };
    let mut opts = match &a.options {
        Some(path) => PipelineOptions::from_json_file(path)?,
        None => PipelineOptions::default(),
    };
    if let Some(s) = a.steps {
        opts.steps = s;
    }
    if let Some(r) = a.rho {
        opts.rho = r;
    }
    opts.validate()
        .map_err(|e| anyhow::anyhow!("{e} (from --steps / --rho / --options)"))?;
    let chain = crate::completers::chain(&a.completers)?;
    if let Some(s) = a.steps {
        crate::completers::warn_unused_steps(&chain, s);
    }
    let depth = a.depth.model()?;
    a.depth.apply(&mut opts);
    let SceneRun {
        result,
        evaluation,
        out,
    } = run_scene(
        input.as_deref(),
        &a.out,
        &chain,
        &opts,
        depth.as_ref().map(|d| d as &dyn DepthSource),
        &RunHow {
            segment: a.segment,
            mcap: a.mcap,
            input: a.input_args.options()?,
        },
    )?;
    let r = &result.report;
    println!(
        "{} frames, {} instances completed by {} ({} with generated points, {:.2} objects/s), {} observed + {} generated points, {:.1} s",
        r.frames,
        r.instances.len(),
        r.completers,
        r.objects_completed,
        r.objects_per_second,
        r.points_observed,
        r.points_generated,
        r.timings.total_s
    );
    if let Some(e) = &evaluation {
        println!(
            "against ground truth: completeness {:.4} -> {:.4} m ({:+.1}%), hidden region {:.4} -> {:.4} m ({:+.1}%), accuracy {:.4} -> {:.4} m",
            e.visible_only.whole_scene.completeness_mean,
            e.with_deocclusion.whole_scene.completeness_mean,
            100.0 * e.completeness_gain_whole_scene,
            e.visible_only.hidden_region.completeness_mean,
            e.with_deocclusion.hidden_region.completeness_mean,
            100.0 * e.completeness_gain_hidden_region,
            e.visible_only.whole_scene.accuracy_mean,
            e.with_deocclusion.whole_scene.accuracy_mean,
        );
    }
    println!("wrote {}", out.display());
    Ok(())
}
