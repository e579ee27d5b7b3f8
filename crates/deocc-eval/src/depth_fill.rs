//! How well a depth source fills what the sensor did not measure, against the noise-free render.
//!
//! bench-v1 scenes rendered with the sensor model (depth noise growing with z^2, no depth at
//! grazing angles), and in each view one object's depth dropped whole, as a depth camera loses a
//! black, shiny or transparent object. Every depth source fills the same frames through the
//! pipeline's depth stage; each hole pixel is scored against the noise-free depth: the share
//! filled, the share filled within 2 cm, the mean relative error of the filled ones. Per scene,
//! with 95% bootstrap intervals over scenes. Rows: the interpolation (no weights; across an edge
//! the nearer side, its default, and the farther), a perfect
//! relative-depth model (the true disparity at an arbitrary scale and shift: what any monocular
//! model could reach after the alignment), and any learned source the caller hands in.

use deocc_pipeline::depth::{fill_depth, DepthEstimate, DepthFillOptions, DepthSource};
use deocc_pipeline::Frame;
use serde::Serialize;

use crate::stats::{estimate, Estimate};
use deocc_robot::picture::{captioned, side_by_side, Rgb, RgbImage};

/// A picture's panel: half size (five VGA panels side by side are wider than a screen), with
/// its caption.
fn panel(img: &RgbImage, caption: &str) -> RgbImage {
    let half = image::imageops::resize(
        img,
        img.width().div_ceil(2),
        img.height().div_ceil(2),
        image::imageops::FilterType::Triangle,
    );
    captioned(&half, caption)
}

/// The 2nd and 98th percentiles of the positive depths, metres.
fn depth_range(depth: &[f32]) -> (f32, f32) {
    let mut d: Vec<f32> = depth.iter().copied().filter(|&z| z > 0.0).collect();
    if d.is_empty() {
        return (0.0, 1.0);
    }
    d.sort_unstable_by(f32::total_cmp);
    let at = |q: f32| d[((q * (d.len() - 1) as f32) as usize).min(d.len() - 1)];
    let (lo, hi) = (at(0.02), at(0.98));
    (lo, hi.max(lo + 1e-3))
}

/// Depth in colour, near blue through green and yellow to far red; no depth black.
fn depth_image(depth: &[f32], w: u32, h: u32, (lo, hi): (f32, f32)) -> RgbImage {
    const STOPS: [[f32; 3]; 5] = [
        [40.0, 40.0, 200.0],
        [30.0, 170.0, 230.0],
        [60.0, 200.0, 80.0],
        [240.0, 220.0, 40.0],
        [220.0, 50.0, 30.0],
    ];
    RgbImage::from_fn(w, h, |u, v| {
        let z = depth[(v * w + u) as usize];
        if z <= 0.0 {
            return Rgb([0, 0, 0]);
        }
        let t = ((z - lo) / (hi - lo)).clamp(0.0, 1.0) * (STOPS.len() - 1) as f32;
        let i = (t.floor() as usize).min(STOPS.len() - 2);
        let f = t - i as f32;
        Rgb(std::array::from_fn(|c| {
            (STOPS[i][c] * (1.0 - f) + STOPS[i + 1][c] * f) as u8
        }))
    })
}

/// The hole kinds scored.
pub const KINDS: [&str; 3] = ["grazing", "dropped_object", "all"];

/// Hole pixels of one kind in one scene.
#[derive(Debug, Clone, Copy, Default)]
struct Tally {
    holes: usize,
    filled: usize,
    within_2cm: usize,
    abs_rel_sum: f64,
}

impl Tally {
    fn add(&mut self, truth: f32, filled: f32) {
        self.holes += 1;
        if filled > 0.0 {
            self.filled += 1;
            let err = (filled - truth).abs();
            if err <= 0.02 {
                self.within_2cm += 1;
            }
            self.abs_rel_sum += (err / truth) as f64;
        }
    }
}

/// One kind of hole for one source.
#[derive(Debug, Clone, Serialize)]
pub struct HoleFigures {
    pub kind: String,
    pub hole_pixels: usize,
    /// Share of the hole pixels filled (per scene, then the mean over scenes).
    pub filled: Estimate,
    /// Share of the hole pixels filled within 2 cm of the truth.
    pub within_2cm: Estimate,
    /// Mean |z - z_true| / z_true of the filled pixels.
    pub abs_rel: Estimate,
}

#[derive(Debug, Clone, Serialize)]
pub struct DepthFillRow {
    pub source: String,
    pub holes: Vec<HoleFigures>,
    /// Frames the source left as they were (a poor fit), of all frames.
    pub frames_skipped: usize,
    pub frames: usize,
    pub seconds_per_frame: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct DepthBenchmarkReport {
    pub benchmark: String,
    pub scenes: usize,
    pub views_per_scene: usize,
    pub rows: Vec<DepthFillRow>,
}

/// The true disparity of a frame at an arbitrary scale and shift: the bound of any relative
/// depth model once aligned.
pub struct TrueDisparity {
    truth: Vec<Vec<f32>>,
    names: Vec<String>,
}

impl DepthSource for TrueDisparity {
    fn name(&self) -> &str {
        "true_disparity"
    }
    fn estimate(
        &self,
        frame: &Frame,
    ) -> Result<Option<DepthEstimate>, deocc_pipeline::depth::DepthSourceError> {
        let i = self
            .names
            .iter()
            .position(|n| *n == frame.name)
            .ok_or_else(|| {
                deocc_pipeline::depth::DepthSourceError("no true depth for this frame".into())
            })?;
        Ok(Some(DepthEstimate::Disparity(
            self.truth[i]
                .iter()
                .map(|&z| if z > 0.0 { 2.5 / z + 0.7 } else { 0.0 })
                .collect(),
        )))
    }
}

/// Runs the benchmark on the first `scenes` of bench-v1 (`views` views each; with `tuning`,
/// bench-v1-like scenes of other seeds, 9,050,000 on, where settings are chosen) for `sources`
/// (name, source; the interpolations and the true disparity are added first). `tick` after each
/// scene.
///
/// With `picture = Some((n, sink))`, the first view of each of the first `n` scenes is drawn
/// (RGB, the sensor's depth with its holes in black, each source's filled depth, the truth) and
/// handed to `sink` with the scene's seed.
pub fn depth_fill_benchmark(
    sources: &[(&str, &dyn DepthSource)],
    scenes: usize,
    views: usize,
    tuning: bool,
    mut picture: Option<(usize, crate::place::PictureSink<'_>)>,
    tick: &mut dyn FnMut(),
) -> Result<DepthBenchmarkReport, crate::EvalError> {
    let mut preset = deocc_synth::dataset::bench_v1();
    preset.config.sensor_noise = true;
    if tuning {
        preset.name = "bench-v1 tuning scenes".into();
        preset.seeds = (9_050_000..9_050_000 + scenes as u64).collect();
    }
    let n = scenes.min(preset.seeds.len());
    let interpolated = deocc_pipeline::depth::InterpolatedDepth::default();
    let farther = deocc_pipeline::depth::InterpolatedDepth {
        edge_side: deocc_pipeline::depth::EdgeSide::Farther,
        ..Default::default()
    };
    // [source][scene][kind]
    let rows = 3 + sources.len();
    let mut tallies: Vec<Vec<[Tally; 3]>> = vec![Vec::new(); rows];
    let mut skipped = vec![0usize; rows];
    let mut seconds = vec![0f64; rows];
    let mut names = vec![
        "interpolated".to_string(),
        "interpolated_farther".to_string(),
        "true_disparity".to_string(),
    ];
    names.extend(sources.iter().map(|(n, _)| n.to_string()));
    let mut frames_total = 0usize;
    for (scene_index, &seed) in preset.seeds[..n].iter().enumerate() {
        let rendered = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        let mut scene = rendered.scene_input();
        let nv = views.min(scene.frames.len());
        scene.frames.truncate(nv);
        let structure = scene.structure_ids.clone();
        // One object per view loses its depth: the one with the most visible pixels among those
        // with at least 400, chosen by the seed among the three largest.
        let mut dropped_masks = Vec::with_capacity(nv);
        for (v, frame) in scene.frames.iter_mut().enumerate() {
            let ids = &rendered.views[v].frame.instance;
            let mut counts = std::collections::BTreeMap::<u16, usize>::new();
            for &id in ids {
                if id != 0 && !structure.contains(&id) {
                    *counts.entry(id).or_default() += 1;
                }
            }
            let mut big: Vec<(usize, u16)> = counts
                .into_iter()
                .filter(|&(_, c)| c >= 400)
                .map(|(id, c)| (c, id))
                .collect();
            big.sort_unstable_by(|a, b| b.cmp(a));
            big.truncate(3);
            let drop = (!big.is_empty()).then(|| big[(seed as usize + v) % big.len()].1);
            let mask: Vec<bool> = ids.iter().map(|&id| Some(id) == drop).collect();
            let (w, h) = (frame.depth.width(), frame.depth.height());
            let mut d = frame.depth.clone().into_data();
            for (z, &m) in d.iter_mut().zip(&mask) {
                if m {
                    *z = 0.0;
                }
            }
            frame.depth = deocc_geometry::DepthMap::new(w, h, d)?;
            dropped_masks.push(mask);
        }
        let truth: Vec<Vec<f32>> = (0..nv)
            .map(|v| rendered.views[v].frame.depth_m.clone())
            .collect();
        let oracle = TrueDisparity {
            truth: truth.clone(),
            names: scene.frames.iter().map(|f| f.name.clone()).collect(),
        };
        let mut all: Vec<&dyn DepthSource> = vec![&interpolated, &farther, &oracle];
        all.extend(sources.iter().map(|(_, s)| *s));
        let draw = picture.as_ref().is_some_and(|(k, _)| scene_index < *k);
        let mut panels = Vec::new();
        if draw {
            let f = &scene.frames[0];
            let (w, h) = (f.depth.width(), f.depth.height());
            let range = depth_range(&truth[0]);
            panels.push(panel(&f.rgb, "rgb"));
            panels.push(panel(
                &depth_image(f.depth.data(), w, h, range),
                "sensor (black: no depth)",
            ));
            panels.push(panel(&depth_image(&truth[0], w, h, range), "true depth"));
        }
        for (r, source) in all.iter().enumerate() {
            let mut t = [Tally::default(); 3];
            for (v, frame) in scene.frames.iter().enumerate() {
                let mut filled = frame.clone();
                let start = std::time::Instant::now();
                let report = fill_depth(&mut filled, *source, &DepthFillOptions::default())?;
                seconds[r] += start.elapsed().as_secs_f64();
                if report.as_ref().is_some_and(|x| x.skipped.is_some()) {
                    skipped[r] += 1;
                }
                let before = frame.depth.data();
                let after = filled.depth.data();
                // The true disparity's fill is the truth's panel, drawn once already.
                if draw && v == 0 && names[r] != "true_disparity" {
                    let (w, h) = (frame.depth.width(), frame.depth.height());
                    let img = depth_image(after, w, h, depth_range(&truth[0]));
                    panels.insert(panels.len() - 1, panel(&img, &names[r]));
                }
                for i in 0..before.len() {
                    let z_true = truth[v][i];
                    if before[i] > 0.0 || z_true <= 0.0 {
                        continue;
                    }
                    let kind = usize::from(dropped_masks[v][i]);
                    t[kind].add(z_true, after[i]);
                    t[2].add(z_true, after[i]);
                }
            }
            tallies[r].push(t);
        }
        if let (true, Some((_, sink))) = (draw, picture.as_mut()) {
            sink(seed, side_by_side(&panels, 4))?;
        }
        frames_total += nv;
        tick();
    }
    let rows = names
        .iter()
        .enumerate()
        .map(|(r, name)| {
            let holes = KINDS
                .iter()
                .enumerate()
                .map(|(k, kind)| {
                    let per_scene = |f: &dyn Fn(&Tally) -> f64| -> Vec<f64> {
                        tallies[r].iter().map(|t| f(&t[k])).collect()
                    };
                    let share = |a: usize, b: usize| {
                        if b == 0 {
                            f64::NAN
                        } else {
                            a as f64 / b as f64
                        }
                    };
                    HoleFigures {
                        kind: kind.to_string(),
                        hole_pixels: tallies[r].iter().map(|t| t[k].holes).sum(),
                        filled: estimate(&per_scene(&|t| share(t.filled, t.holes)), 2000, 7),
                        within_2cm: estimate(
                            &per_scene(&|t| share(t.within_2cm, t.holes)),
                            2000,
                            8,
                        ),
                        abs_rel: estimate(
                            &per_scene(&|t| {
                                if t.filled == 0 {
                                    f64::NAN
                                } else {
                                    t.abs_rel_sum / t.filled as f64
                                }
                            }),
                            2000,
                            9,
                        ),
                    }
                })
                .collect();
            DepthFillRow {
                source: name.clone(),
                holes,
                frames_skipped: skipped[r],
                frames: frames_total,
                seconds_per_frame: seconds[r] / frames_total.max(1) as f64,
            }
        })
        .collect();
    Ok(DepthBenchmarkReport {
        benchmark: format!(
            "{} with the sensor model and one object's depth dropped per view",
            preset.name
        ),
        scenes: n,
        views_per_scene: views,
        rows,
    })
}
