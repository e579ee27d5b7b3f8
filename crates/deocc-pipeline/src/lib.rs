//! # deocc-pipeline
//!
//! The de-occlusion pipeline of DESIGN.md, as plain functions over plain data:
//! 1. reconstruct: back-project every frame's depth into one observed cloud (colour, instance);
//! 2. segment: instance maps given with the input (benchmark or user masks), or the default RGB-D
//!    segmenter ([`segment`]) with cross-view matching ([`ensure_instances`]);
//! 3. occlusion: per view, adjacent instance masks, the farther one is occluded ([`occlusion`]);
//!    every object's far side is hidden in every view, so by default unoccluded objects are
//!    completed too (their far side only); `complete_unoccluded: false` restricts to occluded ones;
//! 4. match: given instance maps are consistent across views; the segmenter's per-view masks are
//!    matched by 3-D centroids with an adaptive threshold ([`matching`]);
//! 5. select views: the largest visible mask first, then one more every `view_delta_deg` of viewing
//!    direction;
//! 6. complete each occluded instance in its selected views with GL-DoT, conditioning on its other
//!    selected views (rho);
//! 7. align the generated relative depth to the observed depth with the Huber fit; reject poor fits;
//! 8. fuse the newly revealed pixels into the cloud with provenance and voxel de-duplication.

pub mod carve;
pub mod complete;
pub mod input;
pub mod matching;
pub mod occlusion;
pub mod planes;
pub mod poses;
pub mod render;
pub mod segment;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use deocc_geometry::depth::backproject;
use deocc_geometry::voxel::{fuse_generated, voxel_downsample};
use deocc_geometry::PointCloud;
use deocc_model::infer::Completer;
use serde::Serialize;
use thiserror::Error;

use crate::complete::{
    cond_tensor, fuse_completion, make_crop, visible_centroid, CompletionRecord, Crop,
};
use crate::input::SceneInput;
use crate::occlusion::{analyse_view, MaskOcclusion};

#[derive(Debug, Error)]
pub enum PipelineError {
    #[error("{}: {msg}", path.display())]
    Input { path: PathBuf, msg: String },
    #[error(transparent)]
    Io(#[from] deocc_io::IoError),
    #[error(transparent)]
    Geometry(#[from] deocc_geometry::GeometryError),
    #[error("model: {0}")]
    Model(String),
}

impl From<candle_core::Error> for PipelineError {
    fn from(e: candle_core::Error) -> Self {
        PipelineError::Model(e.to_string())
    }
}
impl From<deocc_model::train::TrainError> for PipelineError {
    fn from(e: deocc_model::train::TrainError) -> Self {
        PipelineError::Model(e.to_string())
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct PipelineOptions {
    pub steps: usize,
    pub rho: f32,
    pub view_delta_deg: f32,
    pub max_views_per_instance: usize,
    /// Voxel of the observed cloud (de-duplicates the views), metres.
    pub observed_voxel_m: f64,
    /// Voxel of the fusion of generated points, metres.
    pub fusion_voxel_m: f64,
    pub batch: usize,
    pub seed: u64,
    /// Also complete objects no other object hides: their far side is hidden in every view, and
    /// GL-DoT's far-side channel fills it.
    pub complete_unoccluded: bool,
    /// Masks smaller than this (pixels) are not completed.
    pub min_visible_px: usize,
    /// Fill the hidden parts of large planes (floor, walls) where the views agree they are
    /// hidden ([`planes`]).
    pub complete_planes: bool,
    /// Keep a generated point only if every view agrees it is hidden ([`carve`]).
    pub carve_generated: bool,
    /// Crops wider than this at the object's depth (metres) are not completed by GL-DoT: at 64
    /// pixels a crop of furniture has 3+ cm pixels and the model's relative-depth error becomes
    /// decimetres (measured: mean errors 0.1-0.6 m on shelves and segments of them, against
    /// 1-3 cm on table-top objects). Their planar parts are filled by [`planes`].
    pub max_crop_width_m: f32,
}

impl Default for PipelineOptions {
    fn default() -> Self {
        Self {
            steps: 4,
            rho: 0.5,
            view_delta_deg: 90.0,
            max_views_per_instance: 3,
            observed_voxel_m: 0.005,
            fusion_voxel_m: 0.01,
            batch: 8,
            seed: 0,
            complete_unoccluded: true,
            min_visible_px: 200,
            complete_planes: true,
            carve_generated: true,
            max_crop_width_m: 0.6,
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct InstanceReport {
    pub instance_id: u16,
    pub occluded_in_views: Vec<usize>,
    pub selected_views: Vec<usize>,
    pub generated_points: usize,
}

#[derive(Debug, Clone, Default, Serialize)]
pub struct StageTimings {
    pub reconstruct_s: f64,
    pub occlusion_s: f64,
    pub select_views_s: f64,
    pub complete_s: f64,
    pub fuse_s: f64,
    pub planes_s: f64,
    pub total_s: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    pub frames: usize,
    pub options: PipelineOptions,
    pub occlusion: Vec<Vec<MaskOcclusion>>,
    pub instances: Vec<InstanceReport>,
    pub completions: Vec<CompletionRecord>,
    pub objects_completed: usize,
    pub objects_per_second: f64,
    pub points_observed: usize,
    pub points_generated: usize,
    /// Of those, filled in on planes (floor, walls) rather than generated by GL-DoT.
    pub points_plane_fill: usize,
    /// GL-DoT points removed because a view saw them or saw through them ([`carve`]).
    pub points_carved: usize,
    /// Crops not completed because they are wider than `max_crop_width_m`.
    pub crops_too_large: usize,
    pub timings: StageTimings,
    /// "given" (poses from cameras.json) or "icp" (pose-free input registered frame to frame).
    pub poses: &'static str,
    /// Per-frame ICP figures for pose-free input.
    pub registration: Vec<poses::FrameRegistration>,
}

pub struct PipelineOutput {
    pub observed: PointCloud,
    pub completed: PointCloud,
    pub report: RunReport,
}

/// Step 1: every frame's depth back-projected, coloured, labelled, voxel de-duplicated.
pub fn reconstruct(scene: &SceneInput, voxel_m: f64) -> Result<PointCloud, PipelineError> {
    let mut all = PointCloud::default();
    for f in &scene.frames {
        let (mut cloud, pixels) = backproject(&f.depth, &f.camera)?;
        let rgb = f.rgb.as_raw();
        cloud.colors = Some(
            pixels
                .iter()
                .map(|&i| {
                    [
                        rgb[3 * i as usize],
                        rgb[3 * i as usize + 1],
                        rgb[3 * i as usize + 2],
                    ]
                })
                .collect(),
        );
        if let Some(inst) = &f.instances {
            cloud.instance = Some(
                pixels
                    .iter()
                    .map(|&i| inst.ids[i as usize] as u32)
                    .collect(),
            );
        }
        cloud.generated = Some(vec![0; cloud.len()]);
        all.append(&cloud);
    }
    Ok(voxel_downsample(&all, voxel_m)?)
}

/// Step 5: views of an occluded instance to complete it in.
fn select_views(
    scene: &SceneInput,
    id: u16,
    candidates: &[(usize, usize)],
    opts: &PipelineOptions,
) -> Vec<usize> {
    let mut sorted = candidates.to_vec();
    sorted.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    let dir = |v: usize| {
        let f = &scene.frames[v];
        visible_centroid(f, id).map(|c| (c - f.camera.center()).normalize())
    };
    let mut chosen: Vec<(usize, nalgebra::Vector3<f32>)> = Vec::new();
    for (v, _) in sorted {
        let Some(d) = dir(v) else { continue };
        let far_enough = chosen
            .iter()
            .all(|(_, e)| e.dot(&d).clamp(-1.0, 1.0).acos().to_degrees() >= opts.view_delta_deg);
        if chosen.is_empty() || far_enough {
            chosen.push((v, d));
        }
        if chosen.len() >= opts.max_views_per_instance {
            break;
        }
    }
    chosen.into_iter().map(|(v, _)| v).collect()
}

/// The whole pipeline on a loaded scene.
pub fn run(
    scene: &SceneInput,
    completer: &Completer,
    opts: &PipelineOptions,
) -> Result<PipelineOutput, PipelineError> {
    let t_all = Instant::now();
    let mut timings = StageTimings::default();
    if scene.frames.iter().any(|f| f.instances.is_none()) {
        return Err(PipelineError::Input {
            path: scene.dir.join("instances"),
            msg: "every frame needs an instance map (instances/NAME.png), or call ensure_instances() to segment it".into(),
        });
    }

    let t = Instant::now();
    let observed = reconstruct(scene, opts.observed_voxel_m)?;
    timings.reconstruct_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let occlusion: Vec<Vec<MaskOcclusion>> = scene
        .frames
        .iter()
        .map(|f| {
            f.instances
                .as_ref()
                .map(|m| analyse_view(m, &f.depth))
                .unwrap_or_default()
        })
        .collect();
    // (view, visible px) of every view where each instance is occluded.
    let mut occluded: BTreeMap<u16, Vec<(usize, usize)>> = BTreeMap::new();
    for (v, masks) in occlusion.iter().enumerate() {
        for m in masks {
            if m.is_occluded() && !scene.structure_ids.contains(&m.instance_id) && !m.truncated {
                occluded
                    .entry(m.instance_id)
                    .or_default()
                    .push((v, m.visible_px));
            }
        }
    }
    timings.occlusion_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let selected: BTreeMap<u16, Vec<usize>> = occluded
        .iter()
        .map(|(&id, c)| (id, select_views(scene, id, c, opts)))
        .collect();
    timings.select_views_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let r = completer.resolution();
    let mask_prior = completer.model.config.mask_prior;
    let (crops, too_large): (Vec<Crop>, Vec<Crop>) = selected
        .iter()
        .flat_map(|(&id, views)| {
            views
                .iter()
                .filter_map(move |&v| make_crop(&scene.frames[v], v, id, r, mask_prior))
        })
        .partition(|c| c.metric_scale_m <= opts.max_crop_width_m);
    let crops_too_large = too_large.len();
    let device = completer.device.clone();
    let mut completions = Vec::with_capacity(crops.len());
    for chunk in crops.chunks(opts.batch.max(1)) {
        let refs: Vec<&Crop> = chunk.iter().collect();
        let cond = cond_tensor(&refs, &device)?;
        // Cross-view conditioning: the other selected views of the same instance.
        let others = chunk
            .iter()
            .map(|c| {
                crops
                    .iter()
                    .filter(|o| o.instance_id == c.instance_id && o.view != c.view)
                    .map(|o| cond_tensor(&[o], &device))
                    .collect::<candle_core::Result<Vec<_>>>()
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        completions.extend(completer.complete(&cond, &others, opts.rho, opts.steps, opts.seed)?);
    }
    timings.complete_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let mut generated = PointCloud::default();
    let mut records = Vec::new();
    for (crop, comp) in crops.iter().zip(&completions) {
        let (cloud, rec) = fuse_completion(crop, comp, &scene.frames[crop.view]);
        generated.append(&cloud);
        records.push(rec);
    }
    let mut points_carved = 0;
    if opts.carve_generated {
        (generated, points_carved) = carve::keep_hidden(&generated, scene);
    }
    let mut completed = fuse_generated(&observed, &generated, opts.fusion_voxel_m)?;
    timings.fuse_s = t.elapsed().as_secs_f64();

    let t = Instant::now();
    if opts.complete_planes {
        let fill = planes::complete_planes(scene, &planes::PlaneOptions::default());
        completed = fuse_generated(&completed, &fill, opts.fusion_voxel_m)?;
    }
    timings.planes_s = t.elapsed().as_secs_f64();
    timings.total_s = t_all.elapsed().as_secs_f64();

    let gen_flags = completed.generated.as_deref().unwrap_or(&[]);
    let ids = completed.instance.as_deref().unwrap_or(&[]);
    let instances: Vec<InstanceReport> = selected
        .iter()
        .map(|(&id, views)| InstanceReport {
            instance_id: id,
            occluded_in_views: occluded
                .get(&id)
                .map(|c| c.iter().map(|c| c.0).collect())
                .unwrap_or_default(),
            selected_views: views.clone(),
            generated_points: gen_flags
                .iter()
                .zip(ids)
                .filter(|(&g, &i)| g > 0 && i == id as u32)
                .count(),
        })
        .collect();
    let objects_completed = records
        .iter()
        .filter(|r| r.accepted)
        .map(|r| r.instance_id)
        .collect::<std::collections::BTreeSet<_>>()
        .len();
    let points_generated = gen_flags.iter().filter(|&&g| g > 0).count();
    let points_plane_fill = gen_flags
        .iter()
        .filter(|&&g| g == planes::PLANE_FILL)
        .count();
    let report = RunReport {
        frames: scene.frames.len(),
        options: opts.clone(),
        occlusion,
        instances,
        completions: records,
        objects_completed,
        objects_per_second: objects_completed as f64 / timings.total_s.max(1e-9),
        points_observed: observed.len(),
        points_generated,
        points_plane_fill,
        points_carved,
        crops_too_large,
        timings,
        poses: if scene.registration.is_empty() {
            "given"
        } else {
            "icp"
        },
        registration: scene.registration.clone(),
    };
    Ok(PipelineOutput {
        observed,
        completed,
        report,
    })
}

/// Gives every frame without an instance map one: each view is segmented by `segmenter`, masks are
/// matched across views by their 3-D centroids ([`matching`]) and relabelled with consistent ids.
/// Segments spanning more than 2 m (floor, walls) are marked as room structure. Returns the
/// number of 3-D instances found (0 if every frame already had its map).
pub fn ensure_instances(scene: &mut SceneInput, segmenter: &dyn segment::Segmenter) -> usize {
    use matching::{match_masks, MaskCentroid, Threshold};
    if scene.frames.iter().all(|f| f.instances.is_some()) {
        return 0;
    }
    let local: Vec<deocc_io::images::InstanceMap> = scene
        .frames
        .iter()
        .map(|f| segmenter.segment(&f.depth, &f.camera))
        .collect();
    let mut masks = Vec::new();
    let mut extents = Vec::new();
    for (v, (f, map)) in scene.frames.iter().zip(&local).enumerate() {
        let w = map.width as usize;
        let mut per: BTreeMap<u16, Vec<nalgebra::Point3<f32>>> = BTreeMap::new();
        for (i, &id) in map.ids.iter().enumerate() {
            if id != 0 {
                per.entry(id).or_default().push(f.camera.unproject_pixel(
                    (i % w) as u32,
                    (i / w) as u32,
                    f.depth.data()[i],
                ));
            }
        }
        for (id, pts) in per {
            let Some(c) = deocc_geometry::cloud::centroid(&pts) else {
                continue;
            };
            let (lo, hi) = pts
                .iter()
                .fold((pts[0], pts[0]), |(lo, hi), p| (lo.inf(p), hi.sup(p)));
            extents.push((hi.x - lo.x).max(hi.y - lo.y));
            masks.push(MaskCentroid {
                view: v,
                local_id: id,
                centroid: c,
                points: pts.len(),
            });
        }
    }
    let matched = match_masks(&masks, Threshold::Adaptive);
    let mut global: BTreeMap<(usize, u16), u16> = BTreeMap::new();
    let mut structure = std::collections::BTreeSet::new();
    for (k, m) in masks.iter().enumerate() {
        let id = (matched.group[k] + 1).min(u16::MAX as usize) as u16;
        global.insert((m.view, m.local_id), id);
        if extents[k] > 2.0 {
            structure.insert(id);
        }
    }
    for (v, (f, map)) in scene.frames.iter_mut().zip(local).enumerate() {
        if f.instances.is_none() {
            let ids = map
                .ids
                .iter()
                .map(|&l| {
                    if l == 0 {
                        0
                    } else {
                        global.get(&(v, l)).copied().unwrap_or(0)
                    }
                })
                .collect();
            f.instances = Some(deocc_io::images::InstanceMap {
                width: map.width,
                height: map.height,
                ids,
            });
        }
    }
    scene.structure_ids.extend(structure);
    matched.groups
}
