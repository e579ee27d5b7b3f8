//! `deocc bench synth`: the renderer's speed, views per second with every output and training
//! pairs per second.

use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use super::timing::TempDir;
use crate::EvalError;

#[derive(Serialize)]
pub struct SynthReport {
    /// The machine and its load when the figures were taken.
    pub machine: super::timing::Machine,
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
pub struct SynthStages {
    generate: f64,
    render_views: f64,
    sample_ground_truth: f64,
    seen_flags: f64,
    write_files: f64,
}

/// Renders `scenes` bench-v1 scenes (all outputs, then render only) and the pairs of as many
/// training scenes.
pub fn synth_bench(scenes: usize) -> Result<SynthReport, EvalError> {
    use deocc_synth::dataset::{render_view, write_scene, RenderedScene};
    use deocc_synth::ground_truth::{sample_surfaces, seen_flags, GroundTruth};
    use deocc_synth::pairs::{split_scene_pairs, PairConfig, Split};
    use deocc_synth::render::SceneTriangles;
    let p = deocc_synth::dataset::bench_v1();
    let tmp = TempDir::new("bench-synth")?;
    let dir = tmp.0.clone();
    let seeds = &p.seeds[..scenes.min(p.seeds.len())];
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
        .map(|(i, &seed)| -> Result<usize, EvalError> {
            let r = deocc_synth::dataset::render_full_scene(&p.config, seed)?;
            write_scene(&dir.join(format!("s{i}")), &p.config, &r)?;
            Ok(r.views.len())
        })
        .collect::<Result<Vec<_>, EvalError>>()?
        .iter()
        .sum();
    let all = views as f64 / t0.elapsed().as_secs_f64();
    // The steps of `render_full_scene` + `write_scene`, one scene at a time, timed one by one.
    let mut stages = SynthStages::default();
    for (i, &seed) in seeds.iter().enumerate() {
        let t = Instant::now();
        let scene = deocc_synth::generate::generate_scene(&p.config, seed)?;
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
        let scene = deocc_synth::generate::generate_scene(&p.config, seed)?;
        let tris = SceneTriangles::new(&scene);
        let _: Vec<_> = (0..scene.cameras.len())
            .into_par_iter()
            .map(|v| render_view(&scene, &tris, &p.config, v))
            .collect();
    }
    let render_only = views as f64 / t0.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let pairs: usize = (0..scenes as u64)
        .into_par_iter()
        .map(|i| split_scene_pairs(Split::Train, i, &PairConfig::default()).map(|s| s.len()))
        .collect::<Result<Vec<_>, _>>()?
        .iter()
        .sum();
    let pairs_per_second = pairs as f64 / t0.elapsed().as_secs_f64();
    drop(tmp);
    Ok(SynthReport {
        machine: super::timing::Machine::now(),
        threads: rayon::current_num_threads(),
        scenes: seeds.len(),
        views,
        resolution: [p.config.width, p.config.height],
        views_per_second_with_all_outputs: all,
        views_per_second_render_only: render_only,
        seconds_per_scene: stages,
        pairs,
        pairs_per_second,
    })
}
