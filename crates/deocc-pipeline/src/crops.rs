//! Crops: a square window of a view around an instance's visible box, resampled to the
//! completer's resolution, as the [`CropCondition`] a completer reads and the [`CropWindow`] that
//! maps its pixels back to the image; with several frames, what the others observed of the
//! instance, reprojected into the crop ([`seen_elsewhere`]).

use std::collections::BTreeMap;

use deocc_completion::{CropCondition, SeenElsewhere};
use deocc_geometry::reproject::{reproject_views, reproject_views_and_backs, SourceView};
use deocc_io::scene::Frame;

use crate::stats::InstanceStats;

/// Crop side = visible box side * this (the middle of the training range [1.4, 2.2)).
pub const CROP_SCALE: f32 = 1.8;

/// Fewest crop pixels with depth an instance needs to be completed.
pub const MIN_CROP_VISIBLE_PX: usize = 8;

/// Where a crop lies in its view, and what the sensor measured there.
#[derive(Debug, Clone)]
pub struct CropWindow {
    pub instance_id: u16,
    pub view: usize,
    /// Top-left corner and side of the window, image pixels.
    pub x0: f32,
    pub y0: f32,
    pub side: f32,
    pub resolution: usize,
    /// Observed metric depth per crop pixel (0 = none or outside the image).
    pub observed_depth_m: Vec<f32>,
    /// Crop pixel -> image pixel index (`None` outside the image).
    pub source_pixel: Vec<Option<usize>>,
    /// Metres per unit of relative depth: the crop's width at the object's median visible depth.
    pub metric_scale_m: f32,
    /// The object's median visible depth, metres (relative depth 0).
    pub median_depth_m: f32,
}

impl CropWindow {
    /// Image coordinates of crop pixel `k`'s centre.
    pub fn pixel_centre(&self, k: usize) -> (f32, f32) {
        let r = self.resolution;
        (
            self.x0 + ((k % r) as f32 + 0.5) * self.side / r as f32,
            self.y0 + ((k / r) as f32 + 0.5) * self.side / r as f32,
        )
    }
}

/// The crop of instance `id` in `frame` at `resolution`, or `None` if it has fewer than
/// [`MIN_CROP_VISIBLE_PX`] visible pixels with depth there.
pub fn make_crop(
    frame: &Frame,
    view: usize,
    id: u16,
    stats: &InstanceStats,
    resolution: usize,
) -> Option<(CropWindow, CropCondition)> {
    let inst = frame.instances.as_ref()?;
    let (w, h) = (inst.width as usize, inst.height as usize);
    let b = stats.bbox;
    let vis_side = ((b[2] - b[0]).max(b[3] - b[1])) as f32;
    let side = (vis_side * CROP_SCALE).max(24.0);
    let (cx, cy) = ((b[0] + b[2]) as f32 / 2.0, (b[1] + b[3]) as f32 / 2.0);
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
    if vis_depths.len() < MIN_CROP_VISIBLE_PX {
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
    let visible_rel: Vec<f32> = (0..n)
        .map(|k| {
            if visible[k] {
                (observed[k] - m) / scale_m
            } else {
                0.0
            }
        })
        .collect();
    let px = frame.rgb.as_raw();
    let rgb: Vec<u8> = source_pixel
        .iter()
        .flat_map(|src| match src {
            Some(i) => [px[3 * i], px[3 * i + 1], px[3 * i + 2]],
            None => [0; 3],
        })
        .collect();
    let mut condition = CropCondition::new(r, rgb, visible, visible_rel, scene_rel, Some(scale_m));
    // The prior reads a band without depth inside the image (a projector's shadow, a stereo
    // invalid band between the object and what hides it) as what borders it nearest, so the
    // hidden part may run on through it behind an occluder, and the band is no silhouette.
    let measured: Vec<bool> = (0..n)
        .map(|k| source_pixel[k].is_none() || observed[k] > 0.0)
        .collect();
    // The object's own pixels without depth are seen in the image: the prior starts from the
    // whole mask.
    if measured.iter().any(|&m| !m) {
        let bridged = bridge_unmeasured(&condition.scene_depth, &measured, r, BAND_BRIDGE_PX);
        let seen: Vec<bool> = source_pixel
            .iter()
            .map(|src| src.is_some_and(|i| inst.ids[i] == id))
            .collect();
        condition.prior = deocc_completion::priors::mask_prior(
            deocc_completion::priors::MaskPrior::EllipseOrBoxInFront,
            &seen,
            &bridged,
            r,
        );
    }
    let window = CropWindow {
        instance_id: id,
        view,
        x0,
        y0,
        side,
        resolution: r,
        observed_depth_m: observed,
        source_pixel,
        metric_scale_m: scale_m,
        median_depth_m: m,
    };
    Some((window, condition))
}

/// Every frame's pixels of each instance (with depth), for [`seen_elsewhere`].
pub fn instance_pixels(frames: &[Frame]) -> Vec<BTreeMap<u16, Vec<u32>>> {
    frames
        .iter()
        .map(|f| {
            let mut m: BTreeMap<u16, Vec<u32>> = BTreeMap::new();
            if let Some(inst) = &f.instances {
                for (i, (&id, &d)) in inst.ids.iter().zip(f.depth.data()).enumerate() {
                    if id != 0 && d > 0.0 {
                        m.entry(id).or_default().push(i as u32);
                    }
                }
            }
            m
        })
        .collect()
}

/// What the other frames observed of a window's instance, reprojected into its crop in relative
/// depth ([`seen_elsewhere`]).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Elsewhere {
    /// The surfaces facing the crop's camera (the model's condition); `None` when no point lands.
    pub front: Option<SeenElsewhere>,
    /// (r*r) the farthest surface facing away from the crop's camera: where the object's back
    /// along the pixel's ray was observed, infinite where none; `None` when no point lands.
    pub back: Option<Vec<f32>>,
}

/// What the other frames observed of the window's instance, reprojected into its crop
/// (`deocc_geometry::reproject`) in relative depth; the backs only when `backs` is set.
/// `pixels` is [`instance_pixels`] of `frames`.
pub fn seen_elsewhere(
    frames: &[Frame],
    pixels: &[BTreeMap<u16, Vec<u32>>],
    window: &CropWindow,
    backs: bool,
) -> Elsewhere {
    let sources: Vec<SourceView<'_>> = frames
        .iter()
        .zip(pixels)
        .enumerate()
        .filter(|&(v, _)| v != window.view)
        .filter_map(|(_, (f, px))| {
            Some(SourceView {
                camera: &f.camera,
                depth_m: f.depth.data(),
                rgb: f.rgb.as_raw(),
                pixels: px.get(&window.instance_id)?,
            })
        })
        .collect();
    if sources.is_empty() {
        return Elsewhere::default();
    }
    let Ok(camera) = frames[window.view].camera.crop(
        window.x0,
        window.y0,
        window.side,
        window.resolution as u32,
    ) else {
        return Elsewhere::default();
    };
    let seen = if backs {
        reproject_views_and_backs(&camera, &sources)
    } else {
        reproject_views(&camera, &sources)
    };
    let (m, s) = (window.median_depth_m, window.metric_scale_m);
    let relative = |depth: &[f32]| -> Vec<f32> {
        depth
            .iter()
            .map(|&d| if d > 0.0 { (d - m) / s } else { f32::INFINITY })
            .collect()
    };
    let back = (seen.back_hits() > 0).then(|| relative(&seen.back_depth_m));
    let front = (seen.hits() > 0).then(|| SeenElsewhere {
        depth: relative(&seen.depth_m),
        rgb: seen.rgb,
    });
    Elsewhere { front, back }
}

/// Crop pixels a band without depth is bridged across ([`bridge_unmeasured`]).
const BAND_BRIDGE_PX: usize = 4;

/// `rel` with its unmeasured pixels (`measured` false) given the nearest (least) relative depth
/// of the pixels around them, grown `steps` pixels into each unmeasured region (4-neighbours a
/// step); pixels still unreached keep their value.
fn bridge_unmeasured(rel: &[f32], measured: &[bool], r: usize, steps: usize) -> Vec<f32> {
    let mut out = rel.to_vec();
    let mut known = measured.to_vec();
    for _ in 0..steps {
        let (prev, prev_known) = (out.clone(), known.clone());
        for k in 0..r * r {
            if prev_known[k] {
                continue;
            }
            let (u, v) = (k % r, k / r);
            let neighbours = [
                (u > 0).then(|| k - 1),
                (u + 1 < r).then(|| k + 1),
                (v > 0).then(|| k - r),
                (v + 1 < r).then(|| k + r),
            ];
            let nearest = neighbours
                .iter()
                .flatten()
                .filter(|&&q| prev_known[q])
                .map(|&q| prev[q])
                .fold(f32::INFINITY, f32::min);
            if nearest.is_finite() {
                out[k] = nearest;
                known[k] = true;
            }
        }
    }
    out
}

#[cfg(test)]
mod bridge_tests {
    use super::*;

    /// A band without depth between an occluder (in front, -0.5) and the object (0) takes the
    /// occluder's depth up to the bridge width; measured pixels never change; pixels beyond the
    /// bridge's reach keep their value.
    #[test]
    fn a_band_without_depth_takes_the_nearest_depth_beside_it() {
        let r = 12;
        // Columns 0-2 occluder, 3-5 no depth, 6-11 object at 0; row 0 is all unmeasured.
        let mut rel = vec![0.0f32; r * r];
        let mut measured = vec![true; r * r];
        for v in 0..r {
            for u in 0..r {
                let k = v * r + u;
                if u < 3 {
                    rel[k] = -0.5;
                } else if u < 6 {
                    measured[k] = false;
                }
            }
        }
        let out = bridge_unmeasured(&rel, &measured, r, 2);
        for v in 0..r {
            let at = |u: usize| out[v * r + u];
            assert_eq!(at(0), -0.5);
            assert_eq!(at(7), 0.0);
            // One step from the occluder and from the object: the least of the two sides.
            assert_eq!(at(3), -0.5, "row {v}");
            assert_eq!(at(5), 0.0, "row {v}");
            // Two steps from both sides: the occluder's 2-step front meets the object's.
            assert_eq!(at(4), -0.5, "row {v}");
        }
        // Without steps nothing changes.
        assert_eq!(bridge_unmeasured(&rel, &measured, r, 0), rel);
    }
}
