//! `deocc eval grasp` and `deocc eval place`: the robot-task benchmarks.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

#[derive(Args)]
pub struct GraspArgs {
    #[arg(long, default_value = "bench/grasp.json")]
    json: PathBuf,
    /// GL-DoT model folder; default: the built-in model.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// The benchmark: pickup-v1 (bottles and cans behind a box, 5-95% visible) or pickup-v2
    /// (shouldered, faceted and flattened bottles, cans, mugs, small boxes behind a box, a
    /// carton or a jar, 5-50% visible).
    #[arg(long, default_value = "pickup-v1", value_parser = ["pickup-v1", "pickup-v2"])]
    preset: String,
    /// Number of scenes (the first N of the preset's 120).
    #[arg(long, default_value_t = 120)]
    scenes: usize,
    /// Score scenes of other seeds (pickup-v1: 9,250,000 on; pickup-v2: 9,450,000 on), not
    /// the test scenes: where the planner's and the revolve stage's limits are chosen.
    #[arg(long)]
    tuning: bool,
    #[command(flatten)]
    sensor: crate::sensor::SensorArgs,
    #[command(flatten)]
    pipeline: crate::completers::PipelineArgs,
    /// Grasp planner settings (JSON of GraspOptions: gripper geometry, seeds, friction, ...);
    /// `--options` is the pipeline's.
    #[arg(long)]
    grasp_options: Option<PathBuf>,
}

pub fn grasp(a: GraspArgs) -> Result<()> {
    let opts = a.pipeline.options()?;
    let chains = grasp_chains(a.weights.as_ref(), &opts)?;
    let options = crate::robot::grasp_options(a.grasp_options.as_deref())?;
    let (mut preset, tuning_from) = if a.preset == "pickup-v2" {
        (deocc_synth::dataset::pickup_v2(), 9_450_000)
    } else {
        (deocc_synth::dataset::pickup_v1(), 9_250_000)
    };
    a.sensor.apply(&mut preset)?;
    if a.tuning {
        preset.name = format!("{} tuning scenes", preset.name);
        preset.seeds = (tuning_from..tuning_from + a.scenes as u64).collect();
    }
    let n = a.scenes.min(preset.seeds.len());
    let pb = crate::progress::bar(n as u64, "scenes");
    let report =
        deocc_eval::grasp::grasp_benchmark(&chains, &opts, &options, &preset, n, &mut || {
            pb.inc(1)
        })?;
    pb.finish_and_clear();
    crate::report::write_report(&a.json, &report)?;
    Ok(())
}

/// The completer rows of the grasping benchmark: the rules completer at the pipeline's options
/// and at the silhouette-relative cap ([`deocc_eval::RULES_WIDTH_CAP_FOR_ROBOT_TASKS`]), and the
/// shipped chain.
fn grasp_chains(
    weights: Option<&PathBuf>,
    opts: &deocc_pipeline::PipelineOptions,
) -> Result<Vec<deocc_eval::ChainRow>> {
    let mut rows: Vec<deocc_eval::ChainRow> = crate::completers::named_chains(
        weights.map(PathBuf::as_path),
        &["rules", "rules", "gldot,rules"],
    )?
    .into_iter()
    .map(|(name, chain)| deocc_eval::ChainRow::new(name, chain))
    .collect();
    rows[1].name = deocc_eval::RULES_WIDTH_CAP_ROW.into();
    let mut capped = opts.clone();
    let patch = capped.completers.entry("rules".into()).or_default();
    patch.max_thickness_per_width = Some(deocc_eval::RULES_WIDTH_CAP_FOR_ROBOT_TASKS);
    rows[1].options = Some(capped);
    Ok(rows)
}

/// The completer rows of the placing benchmark: the rules completer and the shipped chain, each
/// at the pipeline's options (what `deocc place` runs) and with the thin far sides of
/// [`deocc_pipeline::PipelineOptions::for_placing`] on top (rows [`deocc_eval::PLACING_SUFFIX`]).
fn place_chains(
    weights: Option<&PathBuf>,
    opts: &deocc_pipeline::PipelineOptions,
) -> Result<Vec<deocc_eval::ChainRow>> {
    let names = ["rules", "rules", "gldot,rules", "gldot,rules"];
    let mut rows: Vec<deocc_eval::ChainRow> =
        crate::completers::named_chains(weights.map(PathBuf::as_path), &names)?
            .into_iter()
            .map(|(name, chain)| deocc_eval::ChainRow::new(name, chain))
            .collect();
    for k in [1, 3] {
        rows[k].name = format!("{}{}", rows[k].name, deocc_eval::PLACING_SUFFIX);
        rows[k].options = Some(opts.clone().for_placing());
    }
    Ok(rows)
}

#[derive(Args)]
pub struct PlaceArgs {
    #[arg(long, default_value = "bench/place.json")]
    json: PathBuf,
    /// GL-DoT model folder; default: the built-in model.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// The benchmark: place-v1 (6-10 things a table) or place-v2 (12-18: the unseen space is
    /// often taken).
    #[arg(long, default_value = "place-v1", value_parser = ["place-v1", "place-v2"])]
    preset: String,
    /// Number of scenes (the first N of the preset's 100).
    #[arg(long, default_value_t = 100)]
    scenes: usize,
    /// Score scenes of the preset's kind with other seeds (place-v1: 9,350,000 on; place-v2:
    /// 9,450,000 on), not the test scenes: where the placement settings are chosen.
    #[arg(long)]
    tuning: bool,
    /// Write, for each of the first N scenes, a picture of every map against the ground truth to
    /// DIR/place-SEED.png (panels, each captioned: optimistic, conservative, rules, shipped, and
    /// a legend; green placeable in both, red false placeable, orange missed with something in
    /// the way, blue missed for want of support, grey placeable in neither).
    #[arg(long, value_name = "DIR")]
    pictures: Option<PathBuf>,
    /// How many scenes get a picture with --pictures.
    #[arg(long, default_value_t = 12, requires = "pictures")]
    picture_scenes: usize,
    #[command(flatten)]
    sensor: crate::sensor::SensorArgs,
    #[command(flatten)]
    pipeline: crate::completers::PipelineArgs,
    /// Placer settings (JSON of PlaceOptions: cell size, support, gaps, the envelope's
    /// `expected_error_scale`, ...); the object's footprint and height are the benchmark's.
    #[arg(long)]
    place_options: Option<PathBuf>,
}

pub fn place(a: PlaceArgs) -> Result<()> {
    let opts = a.pipeline.options()?;
    let planner = place_options(a.place_options.as_deref())?;
    let chains = place_chains(a.weights.as_ref(), &opts)?;
    let mut preset = deocc_synth::dataset::preset(&a.preset)?;
    a.sensor.apply(&mut preset)?;
    if a.tuning {
        let first = preset.seeds[0] + 50_000;
        preset.name = format!("{} tuning scenes", preset.name);
        preset.seeds = (first..first + a.scenes as u64).collect();
    }
    let n = a.scenes.min(preset.seeds.len());
    let pb = crate::progress::bar(n as u64, "scenes");
    let writer = crate::report::PictureWriter::new(a.pictures.as_deref(), "place")?;
    let mut write = |seed, img| writer.as_ref().map_or(Ok(()), |w| w.write(seed, img));
    let picture = writer.is_some().then_some((
        a.picture_scenes,
        &mut write as deocc_eval::place::PictureSink<'_>,
    ));
    let report = deocc_eval::place::place_benchmark(
        &preset,
        &chains,
        &opts,
        &planner,
        n,
        picture,
        &mut || pb.inc(1),
    )?;
    pb.finish_and_clear();
    crate::report::write_report(&a.json, &report)?;
    Ok(())
}

/// Reads placer settings from a JSON file, or the defaults.
fn place_options(path: Option<&std::path::Path>) -> Result<deocc_robot::PlaceOptions> {
    let o: deocc_robot::PlaceOptions = match path {
        Some(p) => {
            let text = anyhow::Context::with_context(std::fs::read_to_string(p), || {
                format!("reading {}", p.display())
            })?;
            deocc_io::cameras::options_from_json(&text)
                .map_err(|e| anyhow::anyhow!("{}: place options: {e}", p.display()))?
        }
        None => deocc_robot::PlaceOptions::default(),
    };
    o.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(o)
}
