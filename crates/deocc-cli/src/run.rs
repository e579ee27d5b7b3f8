//! `deocc run`: the pipeline on a scene folder (or a built-in example), all outputs written
//! atomically: into a staging folder first, renamed into place only when everything succeeded.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use deocc_eval::reconstruction::{figures, in_frustum, MethodFigures};
use deocc_io::ply::{read_ply, write_point_cloud};
use deocc_io::PlyEncoding;
use deocc_model::infer::Completer;
use deocc_pipeline::input::read_scene;
use deocc_pipeline::render::{side_by_side, splat};
use deocc_pipeline::{run as run_pipeline, PipelineOptions};
use nalgebra::{Point3, Vector3};
use serde::Serialize;

#[derive(Args)]
pub struct RunArgs {
    /// Scene folder: rgb/, depth/ (16-bit mm), cameras.json, instances/ (u16 ids).
    input: Option<PathBuf>,
    /// Output folder (replaced if it holds a previous run's output).
    #[arg(long)]
    out: PathBuf,
    /// Make a benchmark scene (bench-v1 scene 0) and run on it.
    #[arg(long)]
    example: bool,
    /// Model folder (train.json + weights).
    #[arg(long, default_value = "weights/gldot-small")]
    weights: PathBuf,
    /// Denoising steps.
    #[arg(long, default_value_t = 4)]
    steps: usize,
    /// Ignore given instance maps and segment with the default RGB-D segmenter (frames without an
    /// instance map are always segmented).
    #[arg(long)]
    segment: bool,
    /// Weight of the other views in the conditioning (0 = single view).
    #[arg(long, default_value_t = 0.5)]
    rho: f32,
}

#[derive(Serialize)]
struct Evaluation {
    ground_truth_points_in_frustum: usize,
    visible_only: MethodFigures,
    with_deocclusion: MethodFigures,
    completeness_gain_whole_scene: f64,
    completeness_gain_hidden_region: f64,
    accuracy_change: f64,
}

pub fn run(a: RunArgs) -> Result<()> {
    let input_given = match (&a.input, a.example) {
        (Some(_), true) => bail!("give an INPUT folder or --example, not both"),
        (None, false) => {
            bail!("give an INPUT scene folder, or --example to run on a generated benchmark scene")
        }
        (Some(p), false) => Some(p.clone()),
        (None, true) => None,
    };
    if a.out.exists()
        && a.out
            .read_dir()
            .map(|mut d| d.next().is_some())
            .unwrap_or(true)
        && !a.out.join("report.json").exists()
    {
        bail!(
            "{}: exists and is not a previous deocc run output; choose an empty or new folder",
            a.out.display()
        );
    }
    let completer = Completer::from_dir(&a.weights, &candle_core::Device::Cpu)
        .with_context(|| format!("loading the model from {}", a.weights.display()))?;
    let staging = staging_dir(&a.out)?;
    let result = (|| -> Result<()> {
        let input = match input_given {
            Some(p) => p,
            None => {
                let p = deocc_synth::dataset::bench_v1();
                let dir = staging.join("input");
                let rendered = deocc_synth::dataset::render_full_scene(&p.config, p.seeds[0])?;
                deocc_synth::dataset::write_scene(&dir, &p.config, &rendered)?;
                dir
            }
        };
        run_into(&input, &staging, &completer, &a)
    })();
    match result {
        Ok(()) => {
            if a.out.exists() {
                std::fs::remove_dir_all(&a.out).with_context(|| {
                    format!("{}: cannot replace the previous output", a.out.display())
                })?;
            }
            std::fs::rename(&staging, &a.out).with_context(|| {
                format!("{}: cannot move the output into place", a.out.display())
            })?;
            println!("wrote {}", a.out.display());
            Ok(())
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&staging);
            Err(e)
        }
    }
}

fn staging_dir(out: &Path) -> Result<PathBuf> {
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "out".into());
    let parent = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).with_context(|| {
        format!(
            "{}: cannot create the output's parent folder",
            parent.display()
        )
    })?;
    let staging = parent.join(format!(".{name}.partial-{}", std::process::id()));
    std::fs::create_dir_all(&staging)
        .with_context(|| format!("{}: cannot write here", staging.display()))?;
    Ok(staging)
}

fn run_into(input: &Path, out: &Path, completer: &Completer, a: &RunArgs) -> Result<()> {
    let mut scene = read_scene(input)?;
    if a.segment {
        for f in &mut scene.frames {
            f.instances = None;
        }
    }
    let segmented = deocc_pipeline::ensure_instances(
        &mut scene,
        &deocc_pipeline::segment::ConvexitySegmenter::default(),
    );
    if segmented > 0 {
        eprintln!("segmented the frames with the default RGB-D segmenter: {segmented} instances across views");
    }
    let opts = PipelineOptions {
        steps: a.steps,
        rho: a.rho,
        ..PipelineOptions::default()
    };
    let result = run_pipeline(&scene, completer, &opts)?;
    write_point_cloud(
        &out.join("completed.ply"),
        &result.completed,
        PlyEncoding::BinaryLittleEndian,
    )?;
    write_point_cloud(
        &out.join("observed.ply"),
        &result.observed,
        PlyEncoding::BinaryLittleEndian,
    )?;
    std::fs::create_dir_all(out.join("instances"))?;
    for inst in &result.report.instances {
        let ids = result.completed.instance.as_deref().unwrap_or(&[]);
        let one = result
            .completed
            .filter(|i| ids.get(i) == Some(&(inst.instance_id as u32)));
        write_point_cloud(
            &out.join("instances")
                .join(format!("instance_{:04}.ply", inst.instance_id)),
            &one,
            PlyEncoding::BinaryLittleEndian,
        )?;
    }
    // Pictures: the first input view, and a novel view from higher up and to the side.
    let cam = scene.frames[0].camera;
    let before = splat(&result.observed, &cam, 1, true);
    let after = splat(&result.completed, &cam, 1, true);
    deocc_io::images::write_rgb_png(
        &out.join("render_input_view.png"),
        &side_by_side(&before, &after),
    )?;
    let focus = result.observed.centroid().unwrap_or(Point3::origin());
    let eye = cam.center()
        + (focus - cam.center()).cross(&Vector3::z()).normalize() * 1.2
        + Vector3::new(0.0, 0.0, 0.6);
    if let Ok(pose) = deocc_geometry::camera::look_at(&eye, &focus, &Vector3::z()) {
        let novel = deocc_geometry::Camera {
            intrinsics: cam.intrinsics,
            world_from_camera: pose,
        };
        let b = splat(&result.observed, &novel, 1, true);
        let c = splat(&result.completed, &novel, 1, true);
        deocc_io::images::write_rgb_png(&out.join("render_novel_view.png"), &side_by_side(&b, &c))?;
    }
    let evaluation = evaluate(input, &scene, &result)?;
    #[derive(Serialize)]
    struct Full<'a> {
        input: String,
        #[serde(flatten)]
        run: &'a deocc_pipeline::RunReport,
        evaluation: Option<Evaluation>,
    }
    let full = Full {
        input: input.display().to_string(),
        run: &result.report,
        evaluation,
    };
    deocc_io::cameras::write_json(&out.join("report.json"), &full)?;
    let r = &result.report;
    println!(
        "{} frames, {} occluded instances, {} completed ({:.2} objects/s), {} observed + {} generated points, {:.1} s",
        r.frames,
        r.instances.len(),
        r.objects_completed,
        r.objects_per_second,
        r.points_observed,
        r.points_generated,
        r.timings.total_s
    );
    if let Some(e) = &full.evaluation {
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
    Ok(())
}

/// Figures against the scene's ground truth when it has one (benchmark scenes do).
fn evaluate(
    input: &Path,
    scene: &deocc_pipeline::input::SceneInput,
    result: &deocc_pipeline::PipelineOutput,
) -> Result<Option<Evaluation>> {
    let gt_path = input.join("ground_truth.ply");
    if !gt_path.exists() {
        return Ok(None);
    }
    let gt = read_ply(&gt_path)?;
    let seen: Vec<bool> = match gt.extra("seen") {
        Some(s) => s.iter().map(|&v| v > 0.0).collect(),
        None => vec![true; gt.vertices.len()],
    };
    let cams: Vec<_> = scene.frames.iter().map(|f| f.camera).collect();
    let egt = in_frustum(&gt.vertices, &seen, &cams);
    let vis = figures(&result.observed, &egt)?;
    let deo = figures(&result.completed, &egt)?;
    Ok(Some(Evaluation {
        ground_truth_points_in_frustum: egt.cloud.len(),
        completeness_gain_whole_scene: 1.0
            - deo.whole_scene.completeness_mean / vis.whole_scene.completeness_mean,
        completeness_gain_hidden_region: 1.0
            - deo.hidden_region.completeness_mean / vis.hidden_region.completeness_mean,
        accuracy_change: deo.whole_scene.accuracy_mean / vis.whole_scene.accuracy_mean - 1.0,
        visible_only: vis,
        with_deocclusion: deo,
    }))
}
