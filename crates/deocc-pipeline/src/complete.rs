//! Step 6-8 for one (instance, view): crop the view around the instance's visible mask, complete
//! it with GL-DoT, fit the generated relative depth to the observed depth (Huber), and back-project
//! the newly revealed pixels into world points.

use candle_core::{Device, Tensor};
use deocc_geometry::robust::{huber_affine_fit, AffineFit, HuberOptions};
use deocc_geometry::PointCloud;
use deocc_model::data::{condition_prior, COND_CHANNELS, DEPTH_SCALE};
use deocc_model::infer::Completion;
use deocc_model::MaskPrior;
use nalgebra::Point3;
use serde::Serialize;

use crate::input::Frame;

/// Crop side = visible box side * this (the middle of the training range [1.4, 2.2)).
pub const CROP_SCALE: f32 = 1.8;

/// A square window of a frame resampled to R x R, with everything the model and the fusion need.
pub struct Crop {
    pub instance_id: u16,
    pub view: usize,
    pub x0: f32,
    pub y0: f32,
    pub side: f32,
    pub resolution: usize,
    /// (R*R*6) model condition: RGB, visible mask, visible relative depth, observed relative depth
    /// of the whole crop (clamped to [-1, 1], 0 where unmeasured), as in the training pairs.
    pub cond: Vec<f32>,
    pub visible: Vec<bool>,
    /// Observed metric depth per crop pixel (0 = none or outside the image).
    pub observed_depth_m: Vec<f32>,
    /// Crop pixel -> image pixel index (None outside the image).
    pub source_pixel: Vec<Option<usize>>,
    /// Metres per unit of relative depth: the crop's width at the object's median visible depth.
    /// The model's relative depth is in these units, so the Huber fit's scale should be near it.
    pub metric_scale_m: f32,
}

/// Builds the crop of `id` in `frame`, its condition channel 6 made for a model with `mask_prior`;
/// `None` if the instance is not visible there.
pub fn make_crop(
    frame: &Frame,
    view: usize,
    id: u16,
    resolution: usize,
    mask_prior: MaskPrior,
) -> Option<Crop> {
    let inst = frame.instances.as_ref()?;
    let (w, h) = (inst.width as usize, inst.height as usize);
    let mut b = (usize::MAX, usize::MAX, 0usize, 0usize);
    for (i, &v) in inst.ids.iter().enumerate() {
        if v == id {
            let (u, vv) = (i % w, i / w);
            b = (b.0.min(u), b.1.min(vv), b.2.max(u + 1), b.3.max(vv + 1));
        }
    }
    if b.0 == usize::MAX {
        return None;
    }
    let vis_side = ((b.2 - b.0).max(b.3 - b.1)) as f32;
    let side = (vis_side * CROP_SCALE).max(24.0);
    let (cx, cy) = ((b.0 + b.2) as f32 / 2.0, (b.1 + b.3) as f32 / 2.0);
    let (x0, y0) = (cx - side / 2.0, cy - side / 2.0);
    let r = resolution;
    let n = r * r;
    let depth = frame.depth.data();
    let mut source_pixel = vec![None; n];
    let mut visible = vec![false; n];
    let mut observed = vec![0f32; n];
    for (k, src) in source_pixel.iter_mut().enumerate() {
        let x = x0 + ((k % r) as f32 + 0.5) * side / r as f32;
        let y = y0 + ((k / r) as f32 + 0.5) * side / r as f32;
        if x < 0.0 || y < 0.0 || x >= w as f32 || y >= h as f32 {
            continue;
        }
        let i = y as usize * w + x as usize;
        *src = Some(i);
        visible[k] = inst.ids[i] == id && depth[i] > 0.0;
        observed[k] = depth[i];
    }
    let mut vis_depths: Vec<f32> = (0..n)
        .filter(|&k| visible[k])
        .map(|k| observed[k])
        .collect();
    if vis_depths.len() < 8 {
        return None;
    }
    let mid = vis_depths.len() / 2;
    vis_depths.select_nth_unstable_by(mid, f32::total_cmp);
    let m = vis_depths[mid];
    let scale_m = side * m / frame.camera.intrinsics.fx();
    let scene_rel: Vec<f32> = (0..n)
        .map(|k| {
            if observed[k] > 0.0 {
                ((observed[k] - m) / scale_m).clamp(-1.0, 1.0)
            } else {
                0.0
            }
        })
        .collect();
    let prior = condition_prior(mask_prior, &visible, &scene_rel, r);
    let mut cond = vec![0f32; n * COND_CHANNELS];
    for k in 0..n {
        let c = &mut cond[k * COND_CHANNELS..(k + 1) * COND_CHANNELS];
        if let Some(i) = source_pixel[k] {
            let px = frame.rgb.as_raw();
            for ch in 0..3 {
                c[ch] = px[3 * i + ch] as f32 / 127.5 - 1.0;
            }
        } else {
            c[..3].fill(-1.0);
        }
        c[3] = if visible[k] { 1.0 } else { -1.0 };
        c[4] = if visible[k] {
            (observed[k] - m) / scale_m * DEPTH_SCALE
        } else {
            0.0
        };
        c[5] = scene_rel[k] * DEPTH_SCALE;
        c[6] = if prior[k] { 1.0 } else { -1.0 };
    }
    Some(Crop {
        instance_id: id,
        view,
        x0,
        y0,
        side,
        resolution: r,
        cond,
        visible,
        observed_depth_m: observed,
        source_pixel,
        metric_scale_m: scale_m,
    })
}

/// Stacks crops' conditions into a (B, R, R, COND_CHANNELS) tensor.
pub fn cond_tensor(crops: &[&Crop], device: &Device) -> candle_core::Result<Tensor> {
    let r = crops.first().map(|c| c.resolution).unwrap_or(0);
    let data: Vec<f32> = crops.iter().flat_map(|c| c.cond.iter().copied()).collect();
    Tensor::from_vec(data, (crops.len(), r, r, COND_CHANNELS), device)
}

/// Why a completion added nothing, or what it added.
#[derive(Debug, Clone, Serialize)]
pub struct CompletionRecord {
    pub instance_id: u16,
    pub view: usize,
    pub visible_px: usize,
    pub amodal_px: usize,
    pub new_points: usize,
    /// The crop's metric scale ([`Crop::metric_scale_m`]), to compare with the fit's.
    pub metric_scale_m: f32,
    pub fit: Option<AffineFit>,
    pub accepted: bool,
    pub reason: String,
}

/// Tolerance of the free-space test: a generated point must lie at least this far behind the
/// observed surface at its pixel (something in front hid it), else the sensor saw empty space there.
const FREE_SPACE_MARGIN_M: f32 = 0.01;

/// A far side closer than this to the near side is the same surface.
const MIN_THICKNESS_M: f32 = 0.005;

/// Aligns a completion's depth to the observed depth and back-projects what was hidden: the near
/// side where the object is revealed (amodal minus visible, and only where something in front hid
/// it) and the far side (the back) wherever the object is.
pub fn fuse_completion(
    crop: &Crop,
    completion: &Completion,
    frame: &Frame,
) -> (PointCloud, CompletionRecord) {
    let n = crop.resolution * crop.resolution;
    let vis: Vec<usize> = (0..n).filter(|&k| crop.visible[k]).collect();
    let amodal_px = completion.amodal.iter().filter(|&&a| a).count();
    let mut record = CompletionRecord {
        instance_id: crop.instance_id,
        view: crop.view,
        visible_px: vis.len(),
        amodal_px,
        new_points: 0,
        metric_scale_m: crop.metric_scale_m,
        fit: None,
        accepted: false,
        reason: String::new(),
    };
    let x: Vec<f32> = vis.iter().map(|&k| completion.depth_rel[k]).collect();
    let y: Vec<f32> = vis.iter().map(|&k| crop.observed_depth_m[k]).collect();
    let fit = match huber_affine_fit(&x, &y, &HuberOptions::default()) {
        Ok(f) => f,
        Err(e) => {
            record.reason = format!("depth fit failed: {e}");
            return (PointCloud::default(), record);
        }
    };
    record.fit = Some(fit);
    // A poor fit would put generated geometry at the wrong depth: reject rather than pollute.
    if fit.alpha <= 0.0 || fit.inlier_fraction < 0.5 || fit.scale > 0.03 {
        record.reason = format!(
            "poor depth fit (alpha {:.3}, inliers {:.2}, residual scale {:.3} m)",
            fit.alpha, fit.inlier_fraction, fit.scale
        );
        return (PointCloud::default(), record);
    }
    let mut positions = Vec::new();
    let mut colors = Vec::new();
    let r = crop.resolution;
    let push = |k: usize,
                z: f32,
                shade: f32,
                positions: &mut Vec<Point3<f32>>,
                colors: &mut Vec<[u8; 3]>| {
        let u = crop.x0 + ((k % r) as f32 + 0.5) * crop.side / r as f32;
        let v = crop.y0 + ((k / r) as f32 + 0.5) * crop.side / r as f32;
        let p_cam = frame.camera.intrinsics.unproject(u, v, z);
        positions.push(frame.camera.world_from_camera.transform_point(&p_cam));
        colors.push(std::array::from_fn(|c| {
            (completion.rgb[3 * k + c] as f32 * shade) as u8
        }));
    };
    for k in 0..n {
        if !completion.amodal[k] || crop.source_pixel[k].is_none() {
            continue;
        }
        let obs = crop.observed_depth_m[k];
        // Near side: observed where visible, generated where revealed.
        let front = if crop.visible[k] {
            obs
        } else {
            let z = fit.apply(completion.depth_rel[k] as f64) as f32;
            if !(z.is_finite() && z > 0.05) {
                continue;
            }
            if obs > 0.0 && obs > z - FREE_SPACE_MARGIN_M {
                continue; // the sensor saw this pixel at or beyond the generated depth: nothing hides it
            }
            push(k, z, 1.0, &mut positions, &mut colors);
            z
        };
        // Far side (the object's back, which no view shows), behind the near side.
        let back = fit.apply(completion.back_depth_rel[k] as f64) as f32;
        if back.is_finite()
            && back > front + MIN_THICKNESS_M
            && !(obs > 0.0 && obs > back + FREE_SPACE_MARGIN_M)
        {
            push(k, back, 0.75, &mut positions, &mut colors);
        }
    }
    record.new_points = positions.len();
    record.accepted = true;
    record.reason = "ok".into();
    let len = positions.len();
    let cloud = PointCloud {
        positions,
        colors: Some(colors),
        instance: Some(vec![crop.instance_id as u32; len]),
        generated: Some(vec![1; len]),
        normals: None,
    };
    (cloud, record)
}

/// World-frame centroid of an instance's visible pixels in a frame.
pub fn visible_centroid(frame: &Frame, id: u16) -> Option<Point3<f32>> {
    let inst = frame.instances.as_ref()?;
    let w = inst.width as usize;
    let d = frame.depth.data();
    let pts: Vec<Point3<f32>> = inst
        .ids
        .iter()
        .enumerate()
        .filter(|(i, &v)| v == id && d[*i] > 0.0)
        .map(|(i, _)| {
            frame
                .camera
                .unproject_pixel((i % w) as u32, (i / w) as u32, d[i])
        })
        .collect();
    deocc_geometry::cloud::centroid(&pts)
}
