//! Rendering scenes to disk in the documented layout, and the `bench-v1` benchmark definition.
//!
//! ```text
//! scene_000000/
//!   scene.json            seed, config, objects (id, category), per-view visibility statistics
//!   cameras.json          intrinsics + world_from_camera per frame (deocc-io format)
//!   rgb/000000.png        8-bit RGB
//!   depth/000000.png      16-bit depth, millimetres, 0 = no measurement
//!   instances/000000.png  16-bit visible instance ids, 0 = background
//!   amodal/000000/0007.png  8-bit amodal mask of instance 7 in view 0 (objects in view only)
//!   ground_truth.ply      dense surface samples: x y z nx ny nz instance seen
//! ```
//! The frame files, cameras.json and the fields of scene.json that deocc reads are the scene-folder
//! format of [`deocc_io::scene`], which `deocc run` reads; `amodal/` and the rest of scene.json are
//! the benchmark's ground truth.

use std::path::{Path, PathBuf};

use deocc_geometry::camera::Camera;
use deocc_geometry::DepthMap;
use deocc_io::cameras::{write_cameras_json, write_json, FrameCamera};
use deocc_io::images::{
    write_depth_png, write_instance_png, write_mask_png, write_rgb_png, InstanceMap,
};
use deocc_io::ply::write_point_cloud_with_extras;
use deocc_io::scene::{frame_paths, Frame as SceneFrame, SceneInput};
use deocc_io::PlyEncoding;
use image::RgbImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::generate::generate_scene;
use crate::ground_truth::{sample_surfaces, seen_flags, GroundTruth};
use crate::render::{rasterize_coverage, render_scene, shade, Frame, PixelBox, SceneTriangles};
use crate::scene::{CameraPath, Scene, SceneConfig, SceneKind};
use crate::{Result, SynthError};

/// One object's visibility in one view.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Visibility {
    pub view: usize,
    pub instance_id: u16,
    pub visible_px: u32,
    pub amodal_px: u32,
    /// The object's silhouette reaches the image border.
    pub truncated: bool,
}

impl Visibility {
    /// Fraction of the amodal area hidden by other objects (0 when not in view).
    pub fn occlusion(&self) -> f32 {
        if self.amodal_px == 0 {
            0.0
        } else {
            1.0 - self.visible_px as f32 / self.amodal_px as f32
        }
    }
    /// The benchmark's definition of "occluded": amodal area more than 5% above the visible area.
    pub fn is_occluded(&self) -> bool {
        self.amodal_px as f32 > 1.05 * self.visible_px as f32
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ObjectInfo {
    pub instance_id: u16,
    pub category: crate::shapes::Category,
    pub structure: bool,
    pub held_out: bool,
}

/// The `scene.json` of a rendered scene.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SceneInfo {
    pub seed: u64,
    pub config: SceneConfig,
    pub objects: Vec<ObjectInfo>,
    pub visibility: Vec<Visibility>,
    pub ground_truth_points: usize,
    pub ground_truth_seen: usize,
    /// The object a task scene is about (the grasp target of pickup-v1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<u16>,
}

/// Everything rendered for one view.
pub struct RenderedView {
    pub camera: Camera,
    /// Noise-free render (ground truth).
    pub frame: Frame,
    /// What the sensor reports (noisy if configured).
    pub depth: DepthMap,
    pub rgb: RgbImage,
    /// Amodal masks of the objects in view.
    pub amodal: Vec<AmodalMask>,
    pub visibility: Vec<Visibility>,
}

/// An object's amodal mask in one view, stored as the rectangle it covers (a full-frame mask per
/// object and view was most of the renderer's memory traffic).
#[derive(Debug, Clone, PartialEq)]
pub struct AmodalMask {
    pub instance_id: u16,
    /// `[u0, v0, u1, v1]`, inclusive.
    pub rect: PixelBox,
    /// Row-major over the rectangle.
    pub mask: Vec<bool>,
}

impl AmodalMask {
    /// Whether image pixel (u, v) is inside the mask.
    #[inline]
    pub fn contains(&self, u: u32, v: u32) -> bool {
        let [u0, v0, u1, v1] = self.rect;
        u >= u0
            && u <= u1
            && v >= v0
            && v <= v1
            && self.mask[((v - v0) * (u1 - u0 + 1) + (u - u0)) as usize]
    }

    /// Writes the mask into a full-frame buffer of width `width` (only the rectangle is touched).
    pub fn paint(&self, width: u32, full: &mut [bool], value: bool) {
        let [u0, v0, u1, v1] = self.rect.map(|x| x as usize);
        let rw = u1 - u0 + 1;
        for v in v0..=v1 {
            let dst = &mut full[v * width as usize + u0..v * width as usize + u0 + rw];
            let src = &self.mask[(v - v0) * rw..(v - v0 + 1) * rw];
            for (d, &m) in dst.iter_mut().zip(src) {
                *d = m && value;
            }
        }
    }

    /// The mask over the full image.
    pub fn to_full(&self, width: u32, height: u32) -> Vec<bool> {
        let mut full = vec![false; width as usize * height as usize];
        self.paint(width, &mut full, true);
        full
    }
}

pub fn render_view(
    scene: &Scene,
    tris: &SceneTriangles,
    config: &SceneConfig,
    view: usize,
) -> RenderedView {
    let camera = scene.cameras[view];
    let frame = render_scene(&camera, scene, tris);
    let mut rgb = shade(&frame, &camera, scene, tris, [0, 0, 0]);
    let (w, h) = (frame.width, frame.height);
    let kind = config.sensor_kind();
    let render_seed = scene.seed.wrapping_mul(1000).wrapping_add(view as u64);
    let sensor_depth = if kind != crate::sensor::SensorKind::Clean {
        let mut sensor = frame.clone();
        crate::sensor::apply(
            kind,
            &mut sensor,
            &camera,
            tris,
            scene.seed,
            render_seed,
            camera.intrinsics.fx(),
        );
        sensor.depth_m
    } else {
        frame.depth_m.clone()
    };
    if let Some(c) = crate::sensor::scene_colour(kind, scene.seed) {
        crate::sensor::colour_realism(&mut rgb, &c, render_seed);
    }
    let depth = DepthMap::new(w, h, sensor_depth).unwrap_or_else(|_| DepthMap::zeros(w, h));
    let mut amodal = Vec::new();
    let mut visibility = Vec::new();
    // Visible pixel counts of every instance in one pass.
    let mut visible_count = vec![0u32; scene.objects.len() + 2];
    for &i in &frame.instance {
        if let Some(c) = visible_count.get_mut(i as usize) {
            *c += 1;
        }
    }
    // One coverage buffer for every object rendered alone; cleared after each use.
    let (w_us, h_us) = (w as usize, h as usize);
    let mut coverage = vec![false; w_us * h_us];
    for (k, obj) in scene.objects.iter().enumerate() {
        // Room structure is never completed: no amodal mask for it (it would be a full-frame
        // render per view for nothing).
        if obj.category.is_structure() {
            continue;
        }
        let Some(rect) =
            rasterize_coverage(&camera, tris, tris.object_ranges[k].clone(), &mut coverage)
        else {
            continue;
        };
        // Copy out and clear only the rectangle the object was drawn in.
        let [u0, v0, u1, v1] = rect.map(|x| x as usize);
        let mut mask = Vec::with_capacity((u1 - u0 + 1) * (v1 - v0 + 1));
        for v in v0..=v1 {
            let row = &mut coverage[v * w_us + u0..=v * w_us + u1];
            mask.extend_from_slice(row);
            row.fill(false);
        }
        let amodal_px = mask.iter().filter(|&&m| m).count() as u32;
        if amodal_px == 0 {
            continue;
        }
        let visible_px = visible_count
            .get(obj.instance_id as usize)
            .copied()
            .unwrap_or(0);
        // Touching the image border: the drawn rectangle reaches it (spans are exact).
        let truncated = u0 == 0 || v0 == 0 || u1 == w_us - 1 || v1 == h_us - 1;
        visibility.push(Visibility {
            view,
            instance_id: obj.instance_id,
            visible_px,
            amodal_px,
            truncated,
        });
        amodal.push(AmodalMask {
            instance_id: obj.instance_id,
            rect,
            mask,
        });
    }
    RenderedView {
        camera,
        frame,
        depth,
        rgb,
        amodal,
        visibility,
    }
}

/// A scene with all its views rendered and its ground truth sampled.
pub struct RenderedScene {
    pub scene: Scene,
    pub views: Vec<RenderedView>,
    pub ground_truth: GroundTruth,
}

impl RenderedScene {
    /// The scene as pipeline input, without a round trip through files: depth is quantised to
    /// millimetres as the PNG files store it, so results match `deocc run` on the written scene.
    pub fn scene_input(&self) -> SceneInput {
        let rendered = self;
        let frames = rendered
            .views
            .iter()
            .enumerate()
            .map(|(v, view)| {
                let mm: Vec<f32> = view
                    .depth
                    .data()
                    .iter()
                    .map(|&d| {
                        let q = (d * 1000.0).round();
                        if q > 0.0 && q <= 65535.0 {
                            q / 1000.0
                        } else {
                            0.0
                        }
                    })
                    .collect();
                let (w, h) = (view.frame.width, view.frame.height);
                SceneFrame {
                    name: format!("{v:06}"),
                    camera: view.camera,
                    rgb: view.rgb.clone(),
                    depth: DepthMap::new(w, h, mm).unwrap_or_else(|_| DepthMap::zeros(w, h)),
                    instances: Some(InstanceMap {
                        width: w,
                        height: h,
                        ids: view.frame.instance.clone(),
                    }),
                }
            })
            .collect();
        SceneInput {
            dir: format!("<scene seed {}>", rendered.scene.seed).into(),
            frames,
            structure_ids: rendered.scene.structure_ids(),
            posed: true,
        }
    }
}

pub fn render_full_scene(config: &SceneConfig, seed: u64) -> Result<RenderedScene> {
    let mut scene = generate_scene(config, seed)?;
    if config.burst > 1 {
        // Each pose `burst` times in a row: views of their own, the sensor's noise drawn anew.
        scene.cameras = scene
            .cameras
            .iter()
            .flat_map(|c| std::iter::repeat_n(*c, config.burst))
            .collect();
    }
    let tris = SceneTriangles::new(&scene);
    let views: Vec<RenderedView> = (0..scene.cameras.len())
        .into_par_iter()
        .map(|v| render_view(&scene, &tris, config, v))
        .collect();
    let cloud = sample_surfaces(&scene, &tris, config.gt_points_per_m2, seed);
    let frames: Vec<&Frame> = views.iter().map(|v| &v.frame).collect();
    let seen = seen_flags(&cloud, &scene.cameras, &frames);
    Ok(RenderedScene {
        scene,
        views,
        ground_truth: GroundTruth { cloud, seen },
    })
}

fn frame_name(view: usize) -> String {
    format!("{view:06}")
}

/// Writes a rendered scene into `dir` (created if needed).
pub fn write_scene(
    dir: &Path,
    config: &SceneConfig,
    rendered: &RenderedScene,
) -> Result<SceneInfo> {
    for sub in ["rgb", "depth", "instances", "amodal"] {
        std::fs::create_dir_all(dir.join(sub))
            .map_err(|e| deocc_io::IoError::new(&dir.join(sub), e))?;
    }
    // The ground-truth PLY (tens of MB) is written while the views are.
    let gt = &rendered.ground_truth;
    let (views_done, gt_done) = rayon::join(
        || {
            rendered
                .views
                .par_iter()
                .enumerate()
                .try_for_each(|(v, view)| -> Result<()> {
                    let name = frame_name(v);
                    let [rgb_path, depth_path, inst_path] = frame_paths(dir, &name);
                    write_rgb_png(&rgb_path, &view.rgb)?;
                    write_depth_png(&depth_path, &view.depth)?;
                    let inst = InstanceMap {
                        width: view.frame.width,
                        height: view.frame.height,
                        ids: view.frame.instance.clone(),
                    };
                    write_instance_png(&inst_path, &inst)?;
                    let adir = dir.join("amodal").join(&name);
                    std::fs::create_dir_all(&adir).map_err(|e| deocc_io::IoError::new(&adir, e))?;
                    let (w, h) = (view.frame.width, view.frame.height);
                    let mut full = vec![false; w as usize * h as usize];
                    for m in &view.amodal {
                        m.paint(w, &mut full, true);
                        write_mask_png(
                            &adir.join(format!("{:04}.png", m.instance_id)),
                            w,
                            h,
                            &full,
                        )?;
                        m.paint(w, &mut full, false);
                    }
                    Ok(())
                })
        },
        || {
            let seen_u8: Vec<u8> = gt.seen.iter().map(|&s| s as u8).collect();
            write_point_cloud_with_extras(
                &dir.join("ground_truth.ply"),
                &gt.cloud,
                &[("seen", &seen_u8)],
                PlyEncoding::BinaryLittleEndian,
            )
        },
    );
    views_done?;
    gt_done?;
    let frames: Vec<FrameCamera> = rendered
        .views
        .iter()
        .enumerate()
        .map(|(v, view)| FrameCamera {
            name: frame_name(v),
            intrinsics: view.camera.intrinsics,
            world_from_camera: Some(view.camera.world_from_camera),
            lens: Default::default(),
        })
        .collect();
    write_cameras_json(&dir.join("cameras.json"), &frames)?;
    let info = SceneInfo {
        seed: rendered.scene.seed,
        config: config.clone(),
        objects: rendered
            .scene
            .objects
            .iter()
            .map(|o| ObjectInfo {
                instance_id: o.instance_id,
                category: o.category,
                structure: o.category.is_structure(),
                held_out: o.category.is_held_out(),
            })
            .collect(),
        visibility: rendered
            .views
            .iter()
            .flat_map(|v| v.visibility.clone())
            .collect(),
        ground_truth_points: gt.cloud.len(),
        ground_truth_seen: gt.seen.iter().filter(|&&s| s).count(),
        target: rendered.scene.target,
    };
    write_json(&dir.join("scene.json"), &info)?;
    Ok(info)
}

/// A named set of scenes: the config and the seeds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Preset {
    pub name: String,
    pub config: SceneConfig,
    pub seeds: Vec<u64>,
}

/// `bench-v1`: 50 test scenes of 10 robot-head views each at 640x480, held-out shapes allowed,
/// seeds 9_000_000..9_000_050. Fixed forever: results across commits are comparable.
pub fn bench_v1() -> Preset {
    Preset {
        name: "bench-v1".into(),
        config: SceneConfig {
            views: 10,
            camera_path: CameraPath::RobotHead,
            held_out_shapes: true,
            ..SceneConfig::default()
        },
        seeds: (9_000_000..9_000_050).collect(),
    }
}

/// `chairs-v1`: the failure case named by the reference work, on its own: 10 scenes with 3-4
/// chairs each, every one with a hollow back (two posts and a rail: non-convex, fragmenting
/// masks and pulling centroids off the object), few things on the table, no shelf.
pub fn chairs_v1() -> Preset {
    Preset {
        name: "chairs-v1".into(),
        config: SceneConfig {
            views: 10,
            camera_path: CameraPath::RobotHead,
            held_out_shapes: true,
            chairs_min: 3,
            chairs_max: 4,
            hollow_back_probability: 1.0,
            tabletop_objects_min: 1,
            tabletop_objects_max: 2,
            shelf_probability: 0.0,
            ..SceneConfig::default()
        },
        seeds: (9_100_000..9_100_010).collect(),
    }
}

/// `pickup-v1`: 120 table-top scenes, one robot-head view each, a graspable target hidden
/// 5-95% behind a large box ([`crate::tasks::pickup_scene`]); seeds 9_200_000..9_200_120.
pub fn pickup_v1() -> Preset {
    Preset {
        name: "pickup-v1".into(),
        config: SceneConfig {
            kind: SceneKind::Pickup,
            views: 1,
            camera_path: CameraPath::Single,
            gt_points_per_m2: 2_000.0,
            ..SceneConfig::default()
        },
        seeds: (9_200_000..9_200_120).collect(),
    }
}

/// `pickup-v2`: 120 robot-head views of harder targets ([`crate::tasks::PICKUP_V2_TARGETS`]:
/// shouldered, faceted and flattened bottles, cans, mugs with handles, small boxes) behind a
/// box, a carton or a jar, 50-95% hidden ([`crate::tasks::pickup_v2_scene`]); seeds
/// 9_400_000..9_400_120 (tuning scenes from 9_450_000).
pub fn pickup_v2() -> Preset {
    Preset {
        name: "pickup-v2".into(),
        config: SceneConfig {
            kind: SceneKind::PickupV2,
            views: 1,
            camera_path: CameraPath::Single,
            gt_points_per_m2: 2_000.0,
            ..SceneConfig::default()
        },
        seeds: (9_400_000..9_400_120).collect(),
    }
}

/// `place-v1`: 100 cluttered tables (6-10 things) seen once from 1.5-2.5 m, at least 30% of the
/// free table top hidden ([`crate::tasks::place_scene`]); seeds 9_300_000..9_300_100.
pub fn place_v1() -> Preset {
    Preset {
        name: "place-v1".into(),
        config: SceneConfig {
            kind: SceneKind::Place,
            views: 1,
            camera_path: CameraPath::Single,
            tabletop_objects_min: 6,
            tabletop_objects_max: 10,
            gt_points_per_m2: 2_000.0,
            ..SceneConfig::default()
        },
        seeds: (9_300_000..9_300_100).collect(),
    }
}

/// `place-v2`: place-v1 with twice the clutter (12-18 things), so that the space the view does
/// not see is often taken: where assuming unseen space free goes wrong. Seeds
/// 9_400_000..9_400_100.
pub fn place_v2() -> Preset {
    let mut p = place_v1();
    p.name = "place-v2".into();
    p.config.tabletop_objects_min = 12;
    p.config.tabletop_objects_max = 18;
    p.seeds = (9_400_000..9_400_100).collect();
    p
}

/// Named presets known to `deocc synth scenes --preset`.
pub fn preset(name: &str) -> Result<Preset> {
    match name {
        "bench-v1" => Ok(bench_v1()),
        "chairs-v1" => Ok(chairs_v1()),
        "pickup-v1" => Ok(pickup_v1()),
        "pickup-v2" => Ok(pickup_v2()),
        "place-v1" => Ok(place_v1()),
        "place-v2" => Ok(place_v2()),
        "bench-v1-small" => {
            // The first 5 scenes of bench-v1 at 320x240: for tests and quick looks.
            let mut p = bench_v1();
            p.name = "bench-v1-small".into();
            p.config.width = 320;
            p.config.height = 240;
            p.config.gt_points_per_m2 = 4000.0;
            p.seeds.truncate(5);
            Ok(p)
        }
        other => Err(SynthError::Config(format!(
            "unknown preset '{other}' (known: bench-v1, bench-v1-small, chairs-v1, pickup-v1, pickup-v2, place-v1, place-v2)"
        ))),
    }
}

/// Statistics of a set of scenes, written beside them as `stats.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SetStats {
    pub scenes: usize,
    pub views: usize,
    pub objects_per_scene_mean: f64,
    /// Object-view pairs (non-structure, in view, not truncated) per occlusion level.
    pub unoccluded: usize,
    /// 10-40% hidden.
    pub light: usize,
    /// Over 40% hidden.
    pub heavy: usize,
    /// Occlusion-ratio histogram in 10 bins of 0.1.
    pub occlusion_histogram: [usize; 10],
}

pub fn set_stats(infos: &[SceneInfo]) -> SetStats {
    let mut hist = [0usize; 10];
    let (mut un, mut light, mut heavy) = (0, 0, 0);
    let mut objects = 0usize;
    let mut views = 0usize;
    for info in infos {
        objects += info.objects.iter().filter(|o| !o.structure).count();
        views += info.config.views;
        for v in &info.visibility {
            let structure = info
                .objects
                .iter()
                .any(|o| o.instance_id == v.instance_id && o.structure);
            if structure || v.truncated {
                continue;
            }
            let occ = v.occlusion();
            hist[((occ * 10.0) as usize).min(9)] += 1;
            match occ {
                o if o < 0.1 => un += 1,
                o if o <= 0.4 => light += 1,
                _ => heavy += 1,
            }
        }
    }
    SetStats {
        scenes: infos.len(),
        views,
        objects_per_scene_mean: objects as f64 / infos.len().max(1) as f64,
        unoccluded: un,
        light,
        heavy,
        occlusion_histogram: hist,
    }
}

/// The directory of scene `i` of a set.
pub fn scene_dir(root: &Path, i: usize) -> PathBuf {
    root.join(format!("scene_{i:06}"))
}
