//! `deocc synth`: scenes, training pairs, contact sheets.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use deocc_synth::dataset::{
    preset, render_full_scene, scene_dir, set_stats, write_scene, Preset, SceneInfo,
};
use deocc_synth::pairs::{save_pairs, split_scene_pairs, PairConfig, PairSet, Split};
use rayon::prelude::*;
use serde::Serialize;

use crate::progress::bar;
use crate::scene_options::SceneOptions;

#[derive(Subcommand)]
pub enum SynthCommand {
    /// Render scenes (RGB, depth, instances, amodal masks, cameras, ground-truth cloud) to a folder.
    Scenes(ScenesArgs),
    /// Render amodal training pairs for GL-DoT into safetensors shards.
    Pairs(PairsArgs),
    /// Write a contact sheet PNG (RGB | depth | instances | amodal) of one scene.
    Sheet(crate::sheet::SheetArgs),
    /// Write the built-in example of `deocc run --example` (bench-v1 scene 0, its ground truth
    /// every second point) into a folder; `crates/deocc-cli/example` is embedded in the binary.
    Example(ExampleArgs),
}

#[derive(Args)]
pub struct ExampleArgs {
    /// Output folder (crates/deocc-cli/example to refresh the embedded example).
    #[arg(long)]
    out: PathBuf,
}

#[derive(Args)]
pub struct ScenesArgs {
    /// Number of scenes (scene i has seed SEED + i).
    #[arg(long, default_value_t = 1, conflicts_with = "preset")]
    count: usize,
    #[arg(long, default_value_t = 0, conflicts_with = "preset")]
    seed: u64,
    /// A named preset instead of --count/--seed and the scene options (all but --sensor, which
    /// measures the preset's scenes as it does in `deocc eval --sensor`): bench-v1,
    /// bench-v1-small, chairs-v1, pickup-v1, pickup-v2, place-v1, place-v2.
    #[arg(long)]
    preset: Option<String>,
    /// With --preset: only its first N scenes.
    #[arg(long, requires = "preset")]
    first: Option<usize>,
    /// With --preset: its kind of scene from this seed on instead of its test seeds (the
    /// tuning scenes `deocc eval --tuning` scores: pickup-v2 9450000, place-v1 9350000), as
    /// many as the preset has or --first says.
    #[arg(long, requires = "preset", value_name = "SEED")]
    from_seed: Option<u64>,
    /// Output folder (scene_000000/, ..., manifest.json, stats.json).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    options: SceneOptions,
}

#[derive(Args)]
pub struct PairsArgs {
    #[arg(long, value_enum)]
    split: SplitArg,
    /// Number of scenes to render pairs from.
    #[arg(long, default_value_t = 100)]
    scenes: u64,
    /// First scene index (to extend a set).
    #[arg(long, default_value_t = 0)]
    start: u64,
    /// Scenes per shard file.
    #[arg(long, default_value_t = 50)]
    scenes_per_shard: u64,
    #[arg(long, default_value_t = 64)]
    resolution: u32,
    /// Output folder for {split}-NNNNN.safetensors shards and manifest.json.
    #[arg(long)]
    out: PathBuf,
    /// Also make pairs of objects that leave the image (tables seen from a few metres), the
    /// crop empty outside the image as the pipeline's is. Off keeps the splits as they were.
    #[arg(long)]
    edge_objects: bool,
    /// Also put pickup-v2's target families that the other pools lack (faceted bottles,
    /// flasks) on the tables. Off keeps the splits as they were.
    #[arg(long)]
    grasp_families: bool,
    /// The condition's depth as a sensor measures it (targets noise-free): pairs for a model
    /// that meets a real sensor; `random` draws a sensor per scene. Clean keeps the splits as
    /// they were.
    #[command(flatten)]
    sensor: crate::sensor::SensorArgs,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum SplitArg {
    Train,
    Val,
    Test,
}

pub fn run(cmd: SynthCommand) -> Result<()> {
    match cmd {
        SynthCommand::Scenes(a) => scenes(a),
        SynthCommand::Pairs(a) => pairs(a),
        SynthCommand::Sheet(a) => crate::sheet::sheet(a),
        SynthCommand::Example(a) => {
            write_example_scene(&a.out)?;
            println!("wrote the built-in example to {}", a.out.display());
            Ok(())
        }
    }
}

#[derive(Serialize)]
struct Manifest<'a> {
    preset: &'a Preset,
    scenes: Vec<String>,
}

fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir)
        .with_context(|| format!("{}: cannot create the output folder", dir.display()))
}

fn scenes(a: ScenesArgs) -> Result<()> {
    let p = match &a.preset {
        Some(name) => {
            let mut p = preset(name)?;
            if let Some(s) = a.from_seed {
                let n = p.seeds.len() as u64;
                let end = s.checked_add(n).with_context(|| {
                    format!("--from-seed {s}: the preset's {n} seeds run past the last seed")
                })?;
                p.seeds = (s..end).collect();
            }
            if let Some(n) = a.first {
                p.seeds.truncate(n);
            }
            deocc_eval::with_sensor(&mut p, a.options.sensor_kind()?);
            p.config.burst = a.options.burst();
            p
        }
        None => Preset {
            name: "custom".into(),
            config: a.options.config()?,
            seeds: (a.seed..a.seed + a.count as u64).collect(),
        },
    };
    create_dir(&a.out)?;
    let pb = bar(p.seeds.len() as u64, "scenes");
    // Scenes in parallel as well as the views within a scene: the per-scene steps that are not
    // parallel (file writes, the ground-truth PLY) then overlap with another scene's rendering.
    let infos: Vec<SceneInfo> = p
        .seeds
        .par_iter()
        .enumerate()
        .map(|(i, &seed)| {
            let rendered = render_full_scene(&p.config, seed)?;
            let info = write_scene(&scene_dir(&a.out, i), &p.config, &rendered)?;
            pb.inc(1);
            Ok(info)
        })
        .collect::<Result<_>>()?;
    pb.finish_and_clear();
    let manifest = Manifest {
        preset: &p,
        scenes: (0..infos.len()).map(|i| format!("scene_{i:06}")).collect(),
    };
    deocc_io::cameras::write_json(&a.out.join("manifest.json"), &manifest)?;
    let stats = set_stats(&infos);
    deocc_io::cameras::write_json(&a.out.join("stats.json"), &stats)?;
    println!(
        "wrote {} scenes ({} views) to {}: {:.1} objects per scene; object views unoccluded {}, light {}, heavy {}",
        stats.scenes,
        stats.views,
        a.out.display(),
        stats.objects_per_scene_mean,
        stats.unoccluded,
        stats.light,
        stats.heavy
    );
    Ok(())
}

fn pairs(a: PairsArgs) -> Result<()> {
    let split = match a.split {
        SplitArg::Train => Split::Train,
        SplitArg::Val => Split::Val,
        SplitArg::Test => Split::Test,
    };
    if a.scenes_per_shard == 0 || a.resolution < 8 {
        bail!("--scenes-per-shard must be positive and --resolution at least 8");
    }
    create_dir(&a.out)?;
    let config = PairConfig {
        resolution: a.resolution,
        edge_objects: a.edge_objects,
        grasp_families: a.grasp_families,
        sensor: a.sensor.kind_without_burst("deocc synth pairs")?,
        ..PairConfig::default()
    };
    let name = format!("{split:?}").to_lowercase();
    let pb = bar(a.scenes, "pairs");
    let mut shards = Vec::new();
    let mut total = 0;
    let mut first = a.start;
    while first < a.start + a.scenes {
        let last = (first + a.scenes_per_shard).min(a.start + a.scenes);
        let parts: Vec<PairSet> = (first..last)
            .into_par_iter()
            .map(|i| {
                let s = split_scene_pairs(split, i, &config);
                pb.inc(1);
                s
            })
            .collect::<Result<_, _>>()?;
        let mut set = PairSet {
            resolution: a.resolution,
            ..Default::default()
        };
        for p in &parts {
            set.extend(p);
        }
        let file = format!("{name}-{:05}.safetensors", first / a.scenes_per_shard);
        save_pairs(&a.out.join(&file), &set)?;
        total += set.len();
        shards.push(file);
        first = last;
    }
    pb.finish_and_clear();
    #[derive(Serialize)]
    struct PairsManifest {
        split: Split,
        config: PairConfig,
        scenes: std::ops::Range<u64>,
        pairs: usize,
        shards: Vec<String>,
    }
    deocc_io::cameras::write_json(
        &a.out.join(format!("{name}-manifest.json")),
        &PairsManifest {
            split,
            config,
            scenes: a.start..a.start + a.scenes,
            pairs: total,
            shards,
        },
    )?;
    println!(
        "wrote {total} {name} pairs from {} scenes to {}",
        a.scenes,
        a.out.display()
    );
    Ok(())
}

/// The example of `deocc run --example`: bench-v1 scene 0 as a scene folder, without what the
/// run does not read (the amodal masks) and with every second point of
/// its ground truth (positions and `seen` flags; the figures the run reports against it are
/// means over the ground truth's points, so they barely move), small enough to embed.
pub fn write_example_scene(dir: &Path) -> Result<()> {
    let p = deocc_synth::dataset::bench_v1();
    let rendered = render_full_scene(&p.config, p.seeds[0])?;
    write_scene(dir, &p.config, &rendered)?;
    let amodal = dir.join("amodal");
    std::fs::remove_dir_all(&amodal)
        .with_context(|| format!("{}: cannot remove", amodal.display()))?;
    let gt = &rendered.ground_truth;
    let keep: Vec<usize> = (0..gt.cloud.len()).step_by(2).collect();
    let thin = deocc_geometry::PointCloud::from_positions(
        keep.iter().map(|&i| gt.cloud.positions[i]).collect(),
    );
    let seen: Vec<u8> = keep.iter().map(|&i| gt.seen[i] as u8).collect();
    deocc_io::ply::write_point_cloud_with_extras(
        &dir.join("ground_truth.ply"),
        &thin,
        &[("seen", &seen)],
        deocc_io::ply::PlyEncoding::BinaryLittleEndian,
    )?;
    Ok(())
}
