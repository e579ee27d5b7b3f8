//! Amodal training pairs for GL-DoT, rendered straight at crop resolution.
//!
//! For an object in a view: a square crop around its visible box (grown by a random factor in
//! [1.4, 2.2) and jittered: the pipeline only knows the visible box), holding
//! - `crop_rgb`: the scene as seen in the crop (occluders included),
//! - `visible_mask`: where the object is visible,
//! - `visible_depth`: observed depth on the visible mask, relative (below),
//! - `scene_depth`: observed depth of everything in the crop, relative and clamped to [-1, 1]
//!   (0 where nothing was measured): where the scene is in front of the object, the object may
//!   continue hidden; where it is behind, it cannot (it would be seen),
//! - `whole_rgb`: the object alone on a white background,
//! - `amodal_mask`: the whole object's silhouette,
//! - `whole_depth`: the whole object's depth, relative;
//! - `whole_back_depth`: the depth of its far side (the surface no view shows), relative.
//!
//! Relative depth is `(d - m) / s` with `m` the median visible depth of the object and `s` the
//! crop's width in metres at depth `m`: dimensionless, predictable from the crop alone, and put
//! back into metres by the Huber fit on the visible pixels (step 7 of the pipeline).
//!
//! Crops are rendered with a camera whose intrinsics map the crop window to `resolution` pixels,
//! so there is no resampling blur. Objects whose box leaves the image are skipped (truncation is
//! not occlusion). Several views of each object share a `group` id for cross-view conditioning,
//! and each pair carries what the other views observed of its object, reprojected into its crop
//! (`elsewhere_rgb`, `elsewhere_depth`: `deocc_geometry::reproject`), as the pipeline computes it
//! from its other frames.

use deocc_geometry::camera::Camera;
use deocc_geometry::reproject::{reproject_views, SourceView};
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use crate::generate::generate_scene;
use crate::render::{rasterize, shade, Frame, SceneTriangles};
use crate::scene::{CameraPath, Scene, SceneConfig};
use crate::sensor::SensorKind;
pub use deocc_io::pairs::{load_pairs, save_pairs, PairSet};

use crate::Result;

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default)]
pub struct PairConfig {
    pub resolution: u32,
    /// Views rendered per scene (an arc); every object yields up to this many pairs.
    pub views_per_scene: usize,
    /// Minimum side of the amodal box in the full image, pixels.
    pub min_box_px: f32,
    /// Crop side = visible box side * a factor drawn from [crop_scale_min, crop_scale_max).
    pub crop_scale_min: f32,
    pub crop_scale_max: f32,
    /// Pairs whose visible part is below this fraction of the amodal area are skipped.
    pub min_visible_fraction: f32,
    /// Fraction of unoccluded object views kept (they teach "nothing to add" but are plentiful).
    pub keep_unoccluded: f64,
    /// Also make pairs of objects whose projected box leaves the image (tables seen from a
    /// few metres, chairs at the frame's edge), and crop every pair as the pipeline does: the
    /// crop pixels outside the image carry no colour, depth or visibility, and the object there
    /// counts as hidden. Off by default, which keeps the existing splits as they were.
    #[serde(default)]
    pub edge_objects: bool,
    /// The condition's depth as a sensor measures it (the renderer's sensor model: noise growing
    /// with distance, no depth at grazing angles), in the crop and in the other views; a pixel
    /// without depth is not visible, as in the pipeline's crops. The targets stay noise-free.
    /// Off by default, which keeps the existing splits as they were.
    #[serde(default)]
    pub sensor_noise: bool,
    /// The sensor of the condition ([`crate::sensor`]; `sensor_noise` is the first model's
    /// switch). Under `random` every scene gets its own sensor and colour camera.
    #[serde(default)]
    pub sensor: crate::sensor::SensorKind,
    /// Add pickup-v2's target families the other pools lack (faceted bottles, flasks:
    /// [`crate::shapes::Category::TABLETOP_GRASP`]) to the split's scenes. Off by default,
    /// which keeps the existing splits as they were.
    #[serde(default)]
    pub grasp_families: bool,
}

impl PairConfig {
    /// The sensor in force: `sensor`, or the first model when only `sensor_noise` is set.
    pub fn sensor_kind(&self) -> crate::sensor::SensorKind {
        match (self.sensor, self.sensor_noise) {
            (crate::sensor::SensorKind::Clean, true) => crate::sensor::SensorKind::Gaussian,
            (k, _) => k,
        }
    }
}

impl Default for PairConfig {
    fn default() -> Self {
        Self {
            resolution: 64,
            views_per_scene: 6,
            min_box_px: 24.0,
            crop_scale_min: 1.4,
            crop_scale_max: 2.2,
            min_visible_fraction: 0.08,
            keep_unoccluded: 0.3,
            edge_objects: false,
            sensor_noise: false,
            sensor: crate::sensor::SensorKind::Clean,
            grasp_families: false,
        }
    }
}

/// The sensor model's seed for one render of a scene's pairs.
fn noise_seed(scene_seed: u64, render: u64) -> u64 {
    scene_seed.wrapping_mul(0x9E37_79B9).wrapping_add(render) ^ 0x6e6f_6973
}

/// The box (u0, v0, u1, v1) of an object's projected vertices; `None` if any is behind the camera.
fn projected_box(camera: &Camera, scene: &Scene, object: usize) -> Option<(f32, f32, f32, f32)> {
    let mut b = (
        f32::INFINITY,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NEG_INFINITY,
    );
    for p in &scene.objects[object].mesh.vertices {
        let (px, _) = camera.project_world(p)?;
        b = (b.0.min(px.x), b.1.min(px.y), b.2.max(px.x), b.3.max(px.y));
    }
    Some(b)
}

/// Boxes (u0, v0, u1, v1) of every instance's visible pixels, pixel edges included, indexed by
/// instance id; one pass over the frame.
fn visible_boxes(frame: &Frame) -> Vec<Option<(f32, f32, f32, f32)>> {
    let w = frame.width as usize;
    let max_id = frame.instance.iter().copied().max().unwrap_or(0) as usize;
    let mut boxes = vec![(usize::MAX, usize::MAX, 0usize, 0usize); max_id + 1];
    for (i, &inst) in frame.instance.iter().enumerate() {
        let (u, v) = (i % w, i / w);
        let b = &mut boxes[inst as usize];
        *b = (b.0.min(u), b.1.min(v), b.2.max(u + 1), b.3.max(v + 1));
    }
    boxes
        .into_iter()
        .map(|b| (b.2 > 0).then_some((b.0 as f32, b.1 as f32, b.2 as f32, b.3 as f32)))
        .collect()
}

fn median(mut v: Vec<f32>) -> f32 {
    let mid = v.len() / 2;
    v.select_nth_unstable_by(mid, f32::total_cmp);
    v[mid]
}

/// All pairs of one scene. `group_base` makes group ids unique across scenes.
pub fn scene_pairs(scene: &Scene, config: &PairConfig, group_base: u32) -> Result<PairSet> {
    let tris = SceneTriangles::new(scene);
    let kind = config.sensor_kind();
    let colour = crate::sensor::scene_colour(kind, scene.seed);
    let res = config.resolution;
    let n = (res * res) as usize;
    let mut out = PairSet {
        resolution: res,
        ..Default::default()
    };
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(scene.seed ^ 0x7061_6972);
    // Every view's render, colour and object pixels, for the other views' observations.
    let views: Vec<(Frame, Vec<u8>)> = scene
        .cameras
        .iter()
        .enumerate()
        .map(|(v, camera)| {
            let mut frame = crate::render::render_scene(camera, scene, &tris);
            let mut rgb = shade(&frame, camera, scene, &tris, [0, 0, 0]);
            let seed = noise_seed(scene.seed, v as u64);
            if kind != SensorKind::Clean {
                let fx = camera.intrinsics.fx();
                crate::sensor::apply(kind, &mut frame, camera, &tris, scene.seed, seed, fx);
            }
            if let Some(c) = &colour {
                crate::sensor::colour_realism(&mut rgb, c, seed);
            }
            (frame, rgb.into_raw())
        })
        .collect();
    let object_pixels: Vec<std::collections::HashMap<u16, Vec<u32>>> = views
        .iter()
        .map(|(f, _)| {
            let mut m: std::collections::HashMap<u16, Vec<u32>> = Default::default();
            for (i, (&id, &d)) in f.instance.iter().zip(&f.depth_m).enumerate() {
                if id != 0 && d > 0.0 {
                    m.entry(id).or_default().push(i as u32);
                }
            }
            m
        })
        .collect();
    for (ci, camera) in scene.cameras.iter().enumerate() {
        let full_view = &views[ci].0;
        let boxes = visible_boxes(full_view);
        let (w, h) = (
            camera.intrinsics.width() as f32,
            camera.intrinsics.height() as f32,
        );
        for (k, obj) in scene.objects.iter().enumerate() {
            if obj.category.is_structure() {
                continue;
            }
            let Some((u0, v0, u1, v1)) = projected_box(camera, scene, k) else {
                continue;
            };
            let side = (u1 - u0).max(v1 - v0);
            let leaves_image = u0 < 0.0 || v0 < 0.0 || u1 >= w || v1 >= h;
            if side < config.min_box_px || (leaves_image && !config.edge_objects) {
                continue;
            }
            // The crop is placed around the VISIBLE box, as the pipeline must do (it does not know
            // the amodal box), with a random scale and jitter so the model sees the range of
            // framings the pipeline produces.
            let Some((vu0, vv0, vu1, vv1)) = boxes.get(obj.instance_id as usize).copied().flatten()
            else {
                continue;
            };
            let vis_side = (vu1 - vu0).max(vv1 - vv0);
            let crop_side = (vis_side
                * r.random_range(config.crop_scale_min..config.crop_scale_max))
            .max(config.min_box_px);
            let mut jitter = || (r.random::<f32>() - 0.5) * 0.2 * crop_side;
            let (cx, cy) = ((vu0 + vu1) / 2.0 + jitter(), (vv0 + vv1) / 2.0 + jitter());
            let (x0, y0) = (cx - crop_side / 2.0, cy - crop_side / 2.0);
            let crop = camera.crop(x0, y0, crop_side, res)?;
            let mut full = Frame::new(res, res);
            let inst = |ti: usize| scene.objects[tris.object[ti] as usize].instance_id;
            rasterize(&crop, &tris, 0..tris.corners.len(), &inst, &mut full);
            // With `edge_objects`, crop pixels whose centre is outside the image hold nothing
            // observed (the pipeline's crop leaves them empty); without it they show the scene
            // as before (the existing splits).
            let outside: Vec<bool> = (0..n)
                .map(|i| {
                    if !config.edge_objects {
                        return false;
                    }
                    let step = crop_side / res as f32;
                    let x = x0 + ((i % res as usize) as f32 + 0.5) * step;
                    let y = y0 + ((i / res as usize) as f32 + 0.5) * step;
                    x < 0.0 || y < 0.0 || x >= w || y >= h
                })
                .collect();
            for (i, _) in outside.iter().enumerate().filter(|(_, &o)| o) {
                full.instance[i] = 0;
                full.depth_m[i] = 0.0;
                full.triangle[i] = u32::MAX;
            }
            let mut alone = Frame::new(res, res);
            rasterize(
                &crop,
                &tris,
                tris.object_ranges[k].clone(),
                &|_| obj.instance_id,
                &mut alone,
            );
            let mut back = Frame::new(res, res);
            back.farthest = true;
            rasterize(
                &crop,
                &tris,
                tris.object_ranges[k].clone(),
                &|_| obj.instance_id,
                &mut back,
            );
            // What the sensor measured of the crop (the shading stays the noise-free render's).
            let mut sensed = full.clone();
            let crop_seed = noise_seed(scene.seed, 1000 + (ci * 4096 + k) as u64);
            if kind != SensorKind::Clean {
                crate::sensor::apply(
                    kind,
                    &mut sensed,
                    &crop,
                    &tris,
                    scene.seed,
                    crop_seed,
                    camera.intrinsics.fx(),
                );
            }
            let visible: Vec<bool> = full
                .instance
                .iter()
                .zip(&sensed.depth_m)
                .map(|(&i, &d)| i == obj.instance_id && d > 0.0)
                .collect();
            let amodal: Vec<bool> = alone.instance.iter().map(|&i| i != 0).collect();
            let (vis_px, amo_px) = (
                visible.iter().filter(|&&b| b).count(),
                amodal.iter().filter(|&&b| b).count(),
            );
            if amo_px == 0
                || (vis_px as f32) < config.min_visible_fraction * amo_px as f32
                || vis_px < 8
            {
                continue;
            }
            let occlusion = 1.0 - vis_px as f32 / amo_px as f32;
            if occlusion < 0.02 && !r.random_bool(config.keep_unoccluded) {
                continue;
            }
            let m = median(
                (0..n)
                    .filter(|&i| visible[i])
                    .map(|i| sensed.depth_m[i])
                    .collect(),
            );
            let s = crop_side * m / camera.intrinsics.fx();
            let mut rgb = shade(&full, &crop, scene, &tris, [0, 0, 0]);
            if let Some(c) = &colour {
                crate::sensor::colour_realism(&mut rgb, c, crop_seed);
            }
            let whole = shade(&alone, &crop, scene, &tris, [255, 255, 255]);
            out.crop_rgb.extend_from_slice(rgb.as_raw());
            out.whole_rgb.extend_from_slice(whole.as_raw());
            out.visible_mask.extend(visible.iter().map(|&b| b as u8));
            out.amodal_mask.extend(amodal.iter().map(|&b| b as u8));
            out.scene_depth.extend(sensed.depth_m.iter().map(|&d| {
                if d > 0.0 {
                    ((d - m) / s).clamp(-1.0, 1.0)
                } else {
                    0.0
                }
            }));
            out.visible_depth.extend((0..n).map(|i| {
                if visible[i] {
                    (sensed.depth_m[i] - m) / s
                } else {
                    0.0
                }
            }));
            out.whole_depth.extend((0..n).map(|i| {
                if amodal[i] {
                    (alone.depth_m[i] - m) / s
                } else {
                    0.0
                }
            }));
            out.whole_back_depth.extend((0..n).map(|i| {
                if amodal[i] {
                    (back.depth_m[i] - m) / s
                } else {
                    0.0
                }
            }));
            out.group.push(group_base + obj.instance_id as u32);
            out.category.push(obj.category as u8);
            out.held_out.push(obj.category.is_held_out() as u8);
            out.occlusion.push(occlusion);
            out.crop_width_m.push(s);
            // What the other views saw of the object, from this crop's camera.
            let sources: Vec<SourceView<'_>> = (0..scene.cameras.len())
                .filter(|&cj| cj != ci)
                .filter_map(|cj| {
                    let pixels = object_pixels[cj].get(&obj.instance_id)?;
                    Some(SourceView {
                        camera: &scene.cameras[cj],
                        depth_m: &views[cj].0.depth_m,
                        rgb: &views[cj].1,
                        pixels,
                    })
                })
                .collect();
            let seen = reproject_views(&crop, &sources);
            out.elsewhere_rgb.extend_from_slice(&seen.rgb);
            out.elsewhere_depth.extend(seen.depth_m.iter().map(|&d| {
                if d > 0.0 {
                    (d - m) / s
                } else {
                    f32::INFINITY
                }
            }));
        }
    }
    Ok(out)
}

/// A split of the pair data: its seeds never overlap another split's, and only `test` contains
/// the held-out shapes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    pub fn seed_base(self) -> u64 {
        match self {
            Split::Train => 1_000_000,
            Split::Val => 2_000_000,
            Split::Test => 3_000_000,
        }
    }
    pub fn scene_config(self) -> SceneConfig {
        SceneConfig {
            views: PairConfig::default().views_per_scene,
            camera_path: CameraPath::Arc,
            held_out_shapes: self == Split::Test,
            extra_families: true,
            ..SceneConfig::default()
        }
    }
}

/// Pairs of scene `index` of a split.
pub fn split_scene_pairs(split: Split, index: u64, config: &PairConfig) -> Result<PairSet> {
    let mut sc = split.scene_config();
    sc.views = config.views_per_scene;
    sc.grasp_families = config.grasp_families;
    let scene = generate_scene(&sc, split.seed_base() + index)?;
    // 256 ids per scene: scenes have far fewer objects.
    scene_pairs(&scene, config, (index as u32) << 8)
}
