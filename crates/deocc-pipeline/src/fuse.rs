//! Stage: alignment and fusion of one completion. The completion's relative near-side depth is
//! fitted to the observed depth on the visible pixels (robust Huber scale and shift); a poor fit
//! is rejected. Then what was hidden is back-projected into world points: the near side where
//! the object is revealed (amodal minus visible, and only where something in front hid it) and
//! the far side (its back) wherever the object is. Every generated point carries the completer's
//! probability that its pixel belongs to the object as its confidence.

use deocc_completion::{CropCompletion, Provenance};
use deocc_geometry::robust::{huber_affine_fit, HuberOptions};
use deocc_geometry::PointCloud;
use deocc_io::scene::Frame;

use crate::crops::CropWindow;
use crate::report::CompletionRecord;

/// Tolerance of the free-space test: a generated point must lie at least this far behind the
/// observed surface at its pixel (something in front hid it), else the sensor saw empty space there.
const FREE_SPACE_MARGIN_M: f32 = 0.01;

/// A far side closer than this to the near side is the same surface.
const MIN_THICKNESS_M: f32 = 0.005;

/// A fit is rejected when its scale is not positive, fewer than this fraction of the visible
/// pixels are inliers, or its residual scale is above [`MAX_FIT_RESIDUAL_M`].
const MIN_FIT_INLIERS: f64 = 0.5;
const MAX_FIT_RESIDUAL_M: f64 = 0.03;

/// Aligns a completion's depth to the observed depth and back-projects what was hidden, each
/// point carrying `provenance`.
pub fn fuse_completion(
    window: &CropWindow,
    visible: &[bool],
    completion: &CropCompletion,
    frame: &Frame,
    completer: &str,
    provenance: Provenance,
) -> (PointCloud, CompletionRecord) {
    let n = window.resolution * window.resolution;
    let vis: Vec<usize> = (0..n).filter(|&k| visible[k]).collect();
    let amodal_px = completion.amodal.iter().filter(|&&a| a).count();
    let mut record = CompletionRecord {
        instance_id: window.instance_id,
        view: window.view,
        completer: completer.to_string(),
        visible_px: vis.len(),
        amodal_px,
        new_points: 0,
        metric_scale_m: window.metric_scale_m,
        fit: None,
        mean_confidence: None,
        seen_through_fraction: None,
        gated: false,
        accepted: false,
        reason: String::new(),
    };
    let x: Vec<f32> = vis.iter().map(|&k| completion.depth[k]).collect();
    let y: Vec<f32> = vis.iter().map(|&k| window.observed_depth_m[k]).collect();
    let fit = match huber_affine_fit(&x, &y, &HuberOptions::default()) {
        Ok(f) => f,
        Err(e) => {
            record.reason = format!("depth fit failed: {e}");
            return (PointCloud::default(), record);
        }
    };
    record.fit = Some(fit);
    // A poor fit would put generated geometry at the wrong depth: reject rather than pollute.
    if fit.alpha <= 0.0 || fit.inlier_fraction < MIN_FIT_INLIERS || fit.scale > MAX_FIT_RESIDUAL_M {
        record.reason = format!(
            "poor depth fit (alpha {:.3}, inliers {:.2}, residual scale {:.3} m)",
            fit.alpha, fit.inlier_fraction, fit.scale
        );
        return (PointCloud::default(), record);
    }
    let mut positions = Vec::new();
    let mut colors = Vec::new();
    let mut confidence = Vec::new();
    let mut push = |k: usize, z: f32, shade: f32| {
        let (u, v) = window.pixel_centre(k);
        let p_cam = frame.camera.intrinsics.unproject(u, v, z);
        positions.push(frame.camera.world_from_camera.transform_point(&p_cam));
        colors.push(std::array::from_fn(|c| {
            (completion.rgb[3 * k + c] as f32 * shade) as u8
        }));
        confidence.push(
            completion
                .mask_probability
                .get(k)
                .copied()
                .unwrap_or(0.5)
                .clamp(0.0, 1.0),
        );
    };
    for (k, &is_visible) in visible.iter().enumerate().take(n) {
        if !completion.amodal[k] || window.source_pixel[k].is_none() {
            continue;
        }
        let obs = window.observed_depth_m[k];
        // Near side: observed where visible, generated where revealed.
        let front = if is_visible {
            obs
        } else {
            let z = fit.apply(completion.depth[k] as f64) as f32;
            if !(z.is_finite() && z > 0.05) {
                continue;
            }
            if obs > 0.0 && obs > z - FREE_SPACE_MARGIN_M {
                continue; // the sensor saw this pixel at or beyond the generated depth: nothing hides it
            }
            push(k, z, 1.0);
            z
        };
        // Far side (the object's back, which no view shows), behind the near side.
        let back = fit.apply(completion.back_depth[k] as f64) as f32;
        if back.is_finite()
            && back > front + MIN_THICKNESS_M
            && !(obs > 0.0 && obs > back + FREE_SPACE_MARGIN_M)
        {
            push(k, back, 0.75);
        }
    }
    record.new_points = positions.len();
    record.accepted = true;
    record.reason = "ok".into();
    let len = positions.len();
    let cloud = PointCloud {
        positions,
        colors: Some(colors),
        instance: Some(vec![window.instance_id as u32; len]),
        generated: Some(vec![provenance.code(); len]),
        confidence: Some(confidence),
        normals: None,
    };
    (cloud, record)
}
