//! `deocc bench`: our speed against a peer on the same data in the same run, written to a report.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand};
use deocc_geometry::align::{icp, IcpMethod, IcpOptions, IcpTarget};
use deocc_geometry::metrics::chamfer;
use deocc_geometry::normals::estimate_normals;
use deocc_geometry::voxel::voxel_downsample;
use deocc_geometry::{KdIndex, PointCloud};
use deocc_io::{write_point_cloud, PlyEncoding};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};
use rand::{Rng, SeedableRng};
use serde::Serialize;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Geometry core against Open3D: kd-tree, nearest neighbours, Chamfer, voxels, normals, ICP.
    Geometry(GeometryArgs),
    /// Synthetic benchmark speed: views rendered per second at 640x480 with every output written,
    /// and training pairs per second.
    Synth(SynthArgs),
    /// GL-DoT speed: training step, forward, 4-step completions, token scaling (linear against
    /// softmax attention), and the same model in PyTorch timed in the same run.
    Model(ModelArgs),
}

#[derive(Args)]
pub struct ModelArgs {
    #[arg(long, default_value = "bench/model.json")]
    json: PathBuf,
    /// Python interpreter with torch installed (skip the comparison with --no-torch).
    #[arg(long, default_value = "python3")]
    python: String,
    #[arg(long)]
    no_torch: bool,
    /// Rounds, each timing our side and then PyTorch's: the shared host's load drifts over
    /// seconds, so the ratios are taken per round (neighbouring measurements) and the report
    /// gives their median.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=20))]
    rounds: u32,
}

/// One round's times of our side, in seconds.
#[derive(Serialize, Clone, Copy)]
struct OurTimes {
    train_step_batch_8_s: f64,
    forward_batch_1_s: f64,
    complete_4_steps_batch_1_s: f64,
    complete_4_steps_batch_8_s: f64,
}

#[derive(Serialize)]
struct ModelRound {
    ours: OurTimes,
    torch: Option<serde_json::Value>,
    train_step_ratio: Option<f64>,
    forward_ratio: Option<f64>,
    complete_4_steps_batch_1_ratio: Option<f64>,
}

#[derive(Serialize)]
struct ModelReport {
    threads: usize,
    parameters: usize,
    rounds: usize,
    /// Our times: medians over the rounds.
    train_step_batch_8_s: f64,
    forward_batch_1_s: f64,
    complete_4_steps_batch_1_s: f64,
    complete_4_steps_batch_8_s: f64,
    completions_per_second_batch_1: f64,
    completions_per_second_batch_8: f64,
    /// Forward time at 128x128 (4x the tokens) over 64x64.
    scaling_128_over_64_linear: f64,
    scaling_128_over_64_softmax: f64,
    /// PyTorch's report of the round whose training-step ratio is the median.
    torch: Option<serde_json::Value>,
    /// ours / PyTorch: medians of the per-round ratios.
    train_step_ratio: Option<f64>,
    forward_ratio: Option<f64>,
    complete_4_steps_batch_1_ratio: Option<f64>,
    /// Every round, ours and PyTorch's, in the order they ran.
    per_round: Vec<ModelRound>,
}

/// The upper median (element `len / 2` after sorting), the convention of both sides' timers
/// (`median_time` here and in scripts/bench_torch.py); NaN when empty.
fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn torch_missing(python: &str) -> anyhow::Error {
    anyhow::anyhow!(
        "PyTorch is not installed for {python}: `pip install torch` (or pass --no-torch)"
    )
}

fn model_bench(a: ModelArgs) -> Result<()> {
    if !a.no_torch {
        // Fail before our side's minute of timing, not after it.
        let importable = Command::new(&a.python)
            .args(["-c", "import torch"])
            .stderr(std::process::Stdio::null())
            .status()
            .with_context(|| format!("cannot run {}", a.python))?;
        if !importable.success() {
            return Err(torch_missing(&a.python));
        }
    }
    use candle_core::{DType, Device, Tensor};
    use candle_nn::{VarBuilder, VarMap};
    use deocc_model::config::{AttentionKind, GlDotConfig};
    use deocc_model::flow::euler_sample;
    use deocc_model::init::{randn, SeededInit};
    use deocc_model::model::GlDot;
    use deocc_model::train::AdamW;
    let dev = Device::Cpu;
    let build = |cfg: &GlDotConfig| -> Result<(GlDot, VarMap)> {
        let vm = VarMap::new();
        let vb = VarBuilder::from_backend(
            Box::new(SeededInit::new(vm.clone(), 0)),
            DType::F32,
            dev.clone(),
        );
        Ok((GlDot::new(cfg, vb)?, vm))
    };
    let cfg = GlDotConfig::small();
    let (model, vm) = build(&cfg)?;
    let vars: std::collections::BTreeMap<String, candle_core::Var> = vm
        .data()
        .lock()
        .map(|d| d.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
        .unwrap_or_default();
    let mut opt = AdamW::new(&vars)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let (r, tc, cc) = (cfg.resolution, cfg.target_channels, cfg.cond_channels);
    let mut step = 0;
    // Three warm-up steps on both sides: the allocator's arenas grow over the first steps (their
    // page faults showed in perf timelines for about five steps), and training is thousands of
    // steps in the steady state.
    let mut train_step = || -> Result<f64> {
        Ok(warm_median_time_after(3, 9, || {
            let loss = deocc_model::train::random_batch_loss(&model, 8, &mut rng, &dev)?;
            let grads = loss.backward()?;
            let g: std::collections::BTreeMap<String, Tensor> = vars
                .iter()
                .filter_map(|(k, v)| grads.get(v).map(|t| (k.clone(), t.clone())))
                .collect();
            step += 1;
            opt.step(&vars, &g, step, 1e-4, 0.0)?;
            Ok(())
        })?
        .0)
    };
    let forward =
        |m: &GlDot, cfg: &GlDotConfig, b: usize, rng: &mut rand_chacha::ChaCha8Rng| -> Result<()> {
            let cond = randn(
                (b, cfg.resolution, cfg.resolution, cfg.cond_channels),
                rng,
                &dev,
            )?;
            let toks = m.encode(&cond)?;
            let x = randn(
                (b, cfg.resolution, cfg.resolution, cfg.target_channels),
                rng,
                &dev,
            )?;
            m.forward(&x, &Tensor::full(0.5f32, b, &dev)?, &cond, &toks)?;
            Ok(())
        };
    // Inference as users run it (`Completer`): the same weights as plain tensors, so candle
    // records no autograd graph (PyTorch's side runs under `torch.no_grad()`).
    let frozen = {
        let tensors: std::collections::HashMap<String, Tensor> = vars
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
            .collect();
        GlDot::new(&cfg, VarBuilder::from_tensors(tensors, DType::F32, &dev))?
    };
    let model = frozen;
    let mut infer_rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let rng2 = &mut infer_rng;
    let complete = |b: usize, rng: &mut rand_chacha::ChaCha8Rng| -> Result<f64> {
        Ok(warm_median_time(5, || {
            let cond = randn((b, r, r, cc), rng, &dev)?;
            let toks = model.encode(&cond)?;
            let noise = randn((b, r, r, tc), rng, &dev)?;
            euler_sample(&noise, 4, 1.0, |x, t| {
                model.forward(x, &Tensor::full(t, b, &dev)?, &cond, &toks)
            })?;
            Ok(())
        })?
        .0)
    };
    let torch_config = if a.no_torch {
        None
    } else {
        let dir = tempdir()?;
        let mut j = serde_json::to_value(&cfg)?;
        j["threads"] = serde_json::json!(rayon::current_num_threads());
        let cfg_path = dir.join("config.json");
        std::fs::write(&cfg_path, serde_json::to_string(&j)?)?;
        Some((dir, cfg_path))
    };
    let mut rounds = Vec::new();
    let mut run_rounds = || -> Result<()> {
        for round in 0..a.rounds {
            eprintln!("round {} of {}: ours", round + 1, a.rounds);
            let ours = OurTimes {
                train_step_batch_8_s: train_step()?,
                forward_batch_1_s: warm_median_time(30, || forward(&model, &cfg, 1, rng2))?.0,
                complete_4_steps_batch_1_s: complete(1, rng2)?,
                complete_4_steps_batch_8_s: complete(8, rng2)?,
            };
            let torch = match &torch_config {
                Some((dir, cfg_path)) => Some(run_torch_bench(&a.python, dir, cfg_path)?),
                None => None,
            };
            let ratio = |ours: f64, key: &str| {
                torch
                    .as_ref()
                    .and_then(|t| t[key].as_f64())
                    .map(|x| ours / x)
            };
            rounds.push(ModelRound {
                train_step_ratio: ratio(ours.train_step_batch_8_s, "train_step_batch_8_s"),
                forward_ratio: ratio(ours.forward_batch_1_s, "forward_batch_1_s"),
                complete_4_steps_batch_1_ratio: ratio(
                    ours.complete_4_steps_batch_1_s,
                    "complete_4_steps_batch_1_s",
                ),
                ours,
                torch,
            });
        }
        Ok(())
    };
    let result = run_rounds();
    // The temporary folder goes on every path, the failed ones too.
    if let Some((dir, _)) = &torch_config {
        let _ = std::fs::remove_dir_all(dir);
    }
    result?;
    let our_median =
        |f: fn(&OurTimes) -> f64| median(&rounds.iter().map(|r| f(&r.ours)).collect::<Vec<_>>());
    let ratio_median = |f: fn(&ModelRound) -> Option<f64>| -> Option<f64> {
        let v: Option<Vec<f64>> = rounds.iter().map(f).collect();
        v.map(|v| median(&v))
    };
    let train_s = our_median(|o| o.train_step_batch_8_s);
    let fwd_s = our_median(|o| o.forward_batch_1_s);
    let c1 = our_median(|o| o.complete_4_steps_batch_1_s);
    let c8 = our_median(|o| o.complete_4_steps_batch_8_s);
    let train_step_ratio = ratio_median(|r| r.train_step_ratio);
    // PyTorch's own figures from the round at the median training-step ratio.
    let torch = train_step_ratio.and_then(|m| {
        rounds
            .iter()
            .min_by(|x, y| {
                let d = |r: &ModelRound| (r.train_step_ratio.unwrap_or(f64::NAN) - m).abs();
                d(x).total_cmp(&d(y))
            })
            .and_then(|r| r.torch.clone())
    });
    let mut scaling = [0.0; 2];
    for (k, kind) in [AttentionKind::Linear, AttentionKind::Softmax]
        .into_iter()
        .enumerate()
    {
        let mut small = cfg.clone();
        small.attention = kind;
        let mut big = small.clone();
        big.resolution = 128;
        let (ms, _) = build(&small)?;
        let (mb, _) = build(&big)?;
        let (ts, _) = warm_median_time(5, || forward(&ms, &small, 1, rng2))?;
        let (tb, _) = warm_median_time(3, || forward(&mb, &big, 1, rng2))?;
        scaling[k] = tb / ts;
    }
    let report = ModelReport {
        threads: rayon::current_num_threads(),
        parameters: deocc_model::model::parameter_count(&vm),
        rounds: rounds.len(),
        train_step_batch_8_s: train_s,
        forward_batch_1_s: fwd_s,
        complete_4_steps_batch_1_s: c1,
        complete_4_steps_batch_8_s: c8,
        completions_per_second_batch_1: 1.0 / c1,
        completions_per_second_batch_8: 8.0 / c8,
        scaling_128_over_64_linear: scaling[0],
        scaling_128_over_64_softmax: scaling[1],
        train_step_ratio,
        forward_ratio: ratio_median(|r| r.forward_ratio),
        complete_4_steps_batch_1_ratio: ratio_median(|r| r.complete_4_steps_batch_1_ratio),
        torch,
        per_round: rounds,
    };
    crate::report::write_report(&a.json, &report)?;
    Ok(())
}

/// Runs scripts/bench_torch.py once with the model configuration at `cfg_path`.
fn run_torch_bench(python: &str, dir: &Path, cfg_path: &Path) -> Result<serde_json::Value> {
    let out = dir.join("torch.json");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scripts/bench_torch.py");
    eprintln!("torch: running scripts/bench_torch.py");
    let status = Command::new(python)
        .arg(&script)
        .arg(cfg_path)
        .arg(&out)
        .status()
        .with_context(|| format!("cannot run {python}"))?;
    if status.code() == Some(3) {
        return Err(torch_missing(python));
    }
    if !status.success() {
        bail!("{} failed ({status})", script.display());
    }
    let text =
        std::fs::read_to_string(&out).with_context(|| format!("reading {}", out.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", out.display()))
}

#[derive(Args)]
pub struct SynthArgs {
    #[arg(long, default_value = "bench/synth.json")]
    json: PathBuf,
    /// Scenes rendered (10 views each) and scenes turned into pairs. Ten: with five the
    /// all-outputs figure moved by +-10% from run to run.
    #[arg(long, default_value_t = 10)]
    scenes: usize,
}

#[derive(Serialize)]
struct SynthReport {
    threads: usize,
    scenes: usize,
    views: usize,
    resolution: [u32; 2],
    views_per_second_with_all_outputs: f64,
    /// Rendering only (RGB, depth, instances, amodal masks), no ground truth and no files.
    views_per_second_render_only: f64,
    /// Seconds per scene of each step, one scene at a time (the all-outputs figure runs scenes in
    /// parallel, so it is more than the inverse of their sum).
    seconds_per_scene: SynthStages,
    pairs: usize,
    pairs_per_second: f64,
}

#[derive(Serialize, Default)]
struct SynthStages {
    generate: f64,
    render_views: f64,
    sample_ground_truth: f64,
    seen_flags: f64,
    write_files: f64,
}

fn synth(a: SynthArgs) -> Result<()> {
    use deocc_synth::dataset::{render_view, write_scene, RenderedScene};
    use deocc_synth::ground_truth::{sample_surfaces, seen_flags, GroundTruth};
    use deocc_synth::pairs::{split_scene_pairs, PairConfig, Split};
    use deocc_synth::render::SceneTriangles;
    use rayon::prelude::*;
    let p = deocc_synth::dataset::bench_v1();
    let dir = tempdir()?;
    let seeds = &p.seeds[..a.scenes.min(p.seeds.len())];
    // Warm-up, untimed: the first scene touches the process's memory for the first time, and on
    // these VMs a first touch costs a host page fault (a one-off, not a cost per view).
    if let Some(&seed) = seeds.first() {
        let r = deocc_synth::dataset::render_full_scene(&p.config, seed)?;
        write_scene(&dir.join("warm-up"), &p.config, &r)?;
    }
    // All outputs, as `deocc synth scenes` makes them: scenes in parallel, views in parallel.
    let t0 = Instant::now();
    let views: usize = seeds
        .par_iter()
        .enumerate()
        .map(|(i, &seed)| -> Result<usize> {
            let r = deocc_synth::dataset::render_full_scene(&p.config, seed)?;
            write_scene(&dir.join(format!("s{i}")), &p.config, &r)?;
            Ok(r.views.len())
        })
        .collect::<Result<Vec<_>>>()?
        .iter()
        .sum();
    let all = views as f64 / t0.elapsed().as_secs_f64();
    // The steps of `render_full_scene` + `write_scene`, one scene at a time, timed one by one.
    let mut stages = SynthStages::default();
    for (i, &seed) in seeds.iter().enumerate() {
        let t = Instant::now();
        let scene = deocc_synth::scene::generate_scene(&p.config, seed)?;
        let tris = SceneTriangles::new(&scene);
        stages.generate += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let rendered: Vec<_> = (0..scene.cameras.len())
            .into_par_iter()
            .map(|v| render_view(&scene, &tris, &p.config, v))
            .collect();
        stages.render_views += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let cloud = sample_surfaces(&scene, &tris, p.config.gt_points_per_m2, seed);
        stages.sample_ground_truth += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let frames: Vec<_> = rendered.iter().map(|v| &v.frame).collect();
        let seen = seen_flags(&cloud, &scene.cameras, &frames);
        stages.seen_flags += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let r = RenderedScene {
            scene,
            views: rendered,
            ground_truth: GroundTruth { cloud, seen },
        };
        write_scene(&dir.join(format!("s{i}")), &p.config, &r)?;
        stages.write_files += t.elapsed().as_secs_f64();
    }
    let per_scene = 1.0 / seeds.len().max(1) as f64;
    for x in [
        &mut stages.generate,
        &mut stages.render_views,
        &mut stages.sample_ground_truth,
        &mut stages.seen_flags,
        &mut stages.write_files,
    ] {
        *x *= per_scene;
    }
    let t0 = Instant::now();
    for &seed in seeds {
        let scene = deocc_synth::scene::generate_scene(&p.config, seed)?;
        let tris = SceneTriangles::new(&scene);
        let _: Vec<_> = (0..scene.cameras.len())
            .into_par_iter()
            .map(|v| render_view(&scene, &tris, &p.config, v))
            .collect();
    }
    let render_only = views as f64 / t0.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let pairs: usize = (0..a.scenes as u64)
        .into_par_iter()
        .map(|i| split_scene_pairs(Split::Train, i, &PairConfig::default()).map(|s| s.len()))
        .collect::<Result<Vec<_>, _>>()?
        .iter()
        .sum();
    let pairs_per_second = pairs as f64 / t0.elapsed().as_secs_f64();
    let _ = std::fs::remove_dir_all(&dir);
    let report = SynthReport {
        threads: rayon::current_num_threads(),
        scenes: seeds.len(),
        views,
        resolution: [p.config.width, p.config.height],
        views_per_second_with_all_outputs: all,
        views_per_second_render_only: render_only,
        seconds_per_scene: stages,
        pairs,
        pairs_per_second,
    };
    crate::report::write_report(&a.json, &report)?;
    Ok(())
}

#[derive(Args)]
pub struct GeometryArgs {
    /// Report file (JSON); a Markdown table is written beside it (.md).
    #[arg(long, default_value = "bench/geometry.json")]
    json: PathBuf,
    /// Points in cloud A (B gets half).
    #[arg(long, default_value_t = 1_000_000)]
    points: usize,
    /// Python interpreter with open3d installed.
    #[arg(long, default_value = "python3")]
    python: String,
}

pub fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Geometry(a) => geometry(a),
        BenchCommand::Synth(a) => synth(a),
        BenchCommand::Model(a) => model_bench(a),
    }
}

#[derive(Serialize)]
struct Row {
    operation: String,
    ours_seconds: f64,
    open3d_seconds: f64,
    /// ours / Open3D: below 1 means we are faster.
    ratio: f64,
    ours_value: Option<f64>,
    open3d_value: Option<f64>,
    relative_difference: Option<f64>,
}

#[derive(Serialize)]
struct Report {
    points_a: usize,
    points_b: usize,
    threads: usize,
    open3d_version: String,
    rows: Vec<Row>,
}

/// [`median_time`] after one untimed warm-up call (first-touch page faults, lazily built thread
/// pools): the protocol of scripts/bench_torch.py's `median_time`, so the model comparison times
/// both sides alike.
fn warm_median_time<T>(repeats: usize, f: impl FnMut() -> Result<T>) -> Result<(f64, T)> {
    warm_median_time_after(1, repeats, f)
}

/// [`median_time`] after `warm_ups` untimed calls.
fn warm_median_time_after<T>(
    warm_ups: usize,
    repeats: usize,
    mut f: impl FnMut() -> Result<T>,
) -> Result<(f64, T)> {
    for _ in 0..warm_ups {
        f()?;
    }
    median_time(repeats, f)
}

/// Median wall time of `repeats` calls (the protocol of scripts/bench_open3d.py's `timed`).
fn median_time<T>(repeats: usize, mut f: impl FnMut() -> Result<T>) -> Result<(f64, T)> {
    let mut times = Vec::new();
    let mut out = None;
    for _ in 0..repeats {
        let t0 = Instant::now();
        out = Some(f()?);
        times.push(t0.elapsed().as_secs_f64());
    }
    Ok((median(&times), out.context("no repetition ran")?))
}

/// Surface points of a benchmark scene (so normals and ICP see real structure), `n` of them, and a
/// half-size subset moved by 1 degree / 1 cm with 1 mm noise.
/// Target and source clouds of the benchmark.
type CloudPair = (Vec<Point3<f32>>, Vec<Point3<f32>>);

fn bench_clouds(n: usize) -> Result<CloudPair> {
    use deocc_synth::render::SceneTriangles;
    let scene =
        deocc_synth::scene::generate_scene(&deocc_synth::scene::SceneConfig::default(), 9_000_000)?;
    let tris = SceneTriangles::new(&scene);
    let area: f64 = tris
        .corners
        .iter()
        .map(|c| 0.5 * (c[1] - c[0]).cross(&(c[2] - c[0])).norm() as f64)
        .sum();
    let density = (1.2 * n as f64 / area) as f32;
    let mut pts = deocc_synth::ground_truth::sample_surfaces(&scene, &tris, density, 1).positions;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    for i in (1..pts.len()).rev() {
        pts.swap(i, rng.random_range(0..=i));
    }
    if pts.len() < n {
        bail!("could only sample {} points", pts.len());
    }
    pts.truncate(n);
    let motion = Isometry3::from_parts(
        Translation3::new(0.01, -0.005, 0.005),
        UnitQuaternion::from_euler_angles(0.01, 0.0, 0.015),
    );
    let b = pts[..n / 2]
        .iter()
        .map(|p| {
            let q = motion.transform_point(p);
            q + nalgebra::Vector3::new(
                rng.random_range(-0.001..0.001),
                rng.random_range(-0.001..0.001),
                rng.random_range(-0.001..0.001),
            )
        })
        .collect();
    Ok((pts, b))
}

fn geometry(a: GeometryArgs) -> Result<()> {
    let dir = tempdir()?;
    let (pa, pb) = bench_clouds(a.points)?;
    let (path_a, path_b, path_n) = (
        dir.join("a.ply"),
        dir.join("b.ply"),
        dir.join("a_normals.ply"),
    );
    write_point_cloud(
        &path_a,
        &PointCloud::from_positions(pa.clone()),
        PlyEncoding::BinaryLittleEndian,
    )?;
    write_point_cloud(
        &path_b,
        &PointCloud::from_positions(pb.clone()),
        PlyEncoding::BinaryLittleEndian,
    )?;

    let mut ours: Vec<(&str, f64, Option<f64>)> = Vec::new();
    eprintln!(
        "deocc: {} and {} points, {} threads",
        pa.len(),
        pb.len(),
        rayon::current_num_threads()
    );
    let (t, _) = median_time(3, || Ok(KdIndex::build(&pa)?))?;
    ours.push(("kdtree_build", t, None));
    let (t, d) = median_time(3, || {
        let tree = KdIndex::build(&pa)?;
        let d = tree.nearest_distances(&pb);
        Ok(d.iter().map(|&x| x as f64).sum::<f64>() / d.len() as f64)
    })?;
    ours.push(("nearest_neighbour", t, Some(d)));
    let (t, c) = median_time(3, || Ok(chamfer(&pa, &pb)?.2))?;
    ours.push(("chamfer", t, Some(c)));
    let cloud_a = PointCloud::from_positions(pa.clone());
    let (t, down) = median_time(3, || Ok(voxel_downsample(&cloud_a, 0.01)?))?;
    ours.push(("voxel_downsample", t, Some(down.len() as f64)));
    let (t, normals) = median_time(1, || Ok(estimate_normals(&pa, 30)?))?;
    ours.push(("normals", t, None));
    let mut with_normals = PointCloud::from_positions(pa.clone());
    with_normals.normals = Some(normals.clone());
    write_point_cloud(&path_n, &with_normals, PlyEncoding::BinaryLittleEndian)?;
    for (name, method) in [
        ("icp_point_to_point", IcpMethod::PointToPoint),
        ("icp_point_to_plane", IcpMethod::PointToPlane),
    ] {
        let opts = IcpOptions {
            method,
            max_correspondence_m: 0.05,
            max_iterations: 30,
            relative_fitness: 0.0,
            relative_rmse: 0.0,
        };
        let (t, r) = median_time(1, || {
            // The tree build is part of the registration, as in Open3D's registration_icp.
            let target = IcpTarget::new(&pa, Some(&normals))?;
            Ok(icp(&pb, &target, &Isometry3::identity(), &opts)?)
        })?;
        ours.push((name, t, Some(r.inlier_rmse)));
    }

    eprintln!("open3d: running scripts/bench_open3d.py");
    let o3d_json = dir.join("open3d.json");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scripts/bench_open3d.py");
    let status = Command::new(&a.python)
        .arg(&script)
        .args([&path_a, &path_b, &path_n, &o3d_json])
        .status()
        .with_context(|| format!("cannot run {}", a.python))?;
    if status.code() == Some(3) {
        bail!("Open3D is not installed for {}: run `bash scripts/setup-peers.sh` (pip install open3d==0.20.0, apt libusb-1.0-0)", a.python);
    }
    if !status.success() {
        bail!("{} failed ({status})", script.display());
    }
    let o3d: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&o3d_json)?)?;
    let mut rows = Vec::new();
    for (name, t, value) in ours {
        let entry = &o3d[name];
        let ot = entry["seconds"]
            .as_f64()
            .with_context(|| format!("open3d result lacks {name}"))?;
        let ov = entry["value"].as_f64();
        // For normals Open3D's value is already the agreement (mean |dot|) with ours.
        let (value, ov) = if name == "normals" {
            (ov, Some(1.0))
        } else {
            (value, ov)
        };
        let rel = match (value, ov) {
            (Some(x), Some(y)) => Some((x - y).abs() / y.abs().max(1e-12)),
            _ => None,
        };
        rows.push(Row {
            operation: name.into(),
            ours_seconds: t,
            open3d_seconds: ot,
            ratio: t / ot,
            ours_value: value,
            open3d_value: ov,
            relative_difference: rel,
        });
    }
    let report = Report {
        points_a: pa.len(),
        points_b: pb.len(),
        threads: rayon::current_num_threads(),
        open3d_version: o3d["open3d_version"].as_str().unwrap_or("?").into(),
        rows,
    };
    if let Some(parent) = a.json.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("{}: cannot create", parent.display()))?;
    }
    deocc_io::cameras::write_json(&a.json, &report)?;
    let mut md = format!(
        "| operation | deocc (s) | Open3D {} (s) | ratio | result difference |\n|---|---|---|---|---|\n",
        report.open3d_version
    );
    for r in &report.rows {
        let diff = r
            .relative_difference
            .map(|d| format!("{d:.1e}"))
            .unwrap_or_else(|| "-".into());
        md.push_str(&format!(
            "| {} | {:.3} | {:.3} | {:.2} | {} |\n",
            r.operation, r.ours_seconds, r.open3d_seconds, r.ratio, diff
        ));
    }
    deocc_io::atomic::write_bytes_atomic(&a.json.with_extension("md"), md.as_bytes())?;
    print!("{md}");
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

fn tempdir() -> Result<PathBuf> {
    let dir = std::env::temp_dir().join(format!("deocc-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).with_context(|| format!("{}: cannot create", dir.display()))?;
    Ok(dir)
}
