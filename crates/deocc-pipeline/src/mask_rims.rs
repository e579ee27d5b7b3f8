//! Stage: masks meet depth. Runs in the front half after the depth front end, on frames that
//! came with instance maps (a segmenter's own masks are cut from the depth and need none of it).
//!
//! A mask drawn on colour (ground truth, an RGB segmenter, a hand label) and a sensor's depth
//! never share their edges exactly: lateral edge noise, a projector's shadow and a pixel of
//! registration put the wall behind, the table below or the occluder in front on the mask's rim.
//! Back-projected, those pixels are points of the object tens of centimetres to metres away from
//! it, and everything after believes them: a grasp planner sees a target wider than any gripper,
//! a completer a crop with a spike.
//!
//! Inside each instance's mask the pixels with depth are split into depth-connected pieces
//! (4-neighbours within `connect_sigmas * sigma(z) + 2% z`, the depth front end's own
//! connectivity, with the frame's noise `sigma(z)`). The largest piece stays. Another piece
//! stays unless it is a **rim**: smaller than `min_piece_px`, or with at least `rim_fraction` of
//! its pixels on the mask's border (a strip one or two pixels wide along the edge; a part of the
//! object cut off by a thin occluder is thick and stays). A rim's pixels lose their instance
//! (id 0): their depth is kept as an observation of whatever it is, no instance claims it.

use deocc_geometry::noise::DepthNoise;
use deocc_io::scene::Frame;
use serde::{Deserialize, Serialize};

use crate::depth_clean::neighbours4;
use crate::PipelineError;

/// The stage's settings.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct MaskRimOptions {
    /// Run the stage at all.
    pub enabled: bool,
    /// Neighbours within this many sigmas (plus 2% of the depth) are one surface.
    pub connect_sigmas: f32,
    /// Pieces smaller than this are rims whatever their shape, pixels.
    pub min_piece_px: usize,
    /// A piece with at least this share of its pixels on the mask's border is a rim.
    pub rim_fraction: f32,
}

impl Default for MaskRimOptions {
    fn default() -> Self {
        Self {
            enabled: true,
            connect_sigmas: 4.0,
            min_piece_px: 12,
            rim_fraction: 0.6,
        }
    }
}

impl MaskRimOptions {
    pub fn validate(&self) -> Result<(), PipelineError> {
        let bad = |field: &'static str, msg: String| PipelineError::Option { field, msg };
        if !(0.5..=50.0).contains(&self.connect_sigmas) {
            return Err(bad(
                "mask_rims.connect_sigmas",
                format!("{} is outside [0.5, 50]", self.connect_sigmas),
            ));
        }
        if self.min_piece_px > 10_000 {
            return Err(bad(
                "mask_rims.min_piece_px",
                format!("{} is over 10000", self.min_piece_px),
            ));
        }
        if !(0.0..=1.0).contains(&self.rim_fraction) {
            return Err(bad(
                "mask_rims.rim_fraction",
                format!("{} is outside [0, 1]", self.rim_fraction),
            ));
        }
        Ok(())
    }
}

/// What the stage did to one frame.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq, Eq)]
pub struct MaskRimRecord {
    /// Instances whose mask lost a rim.
    pub instances: usize,
    /// Pixels that lost their instance.
    pub pixels: usize,
}

/// Unlabels the rims of `frame`'s instance masks (see the module docs); nothing without a map.
pub fn unlabel_mask_rims(frame: &mut Frame, opts: &MaskRimOptions) -> MaskRimRecord {
    let mut rec = MaskRimRecord::default();
    if !opts.enabled {
        return rec;
    }
    let Some(map) = frame.instances.as_mut() else {
        return rec;
    };
    let (w, h) = (frame.depth.width() as usize, frame.depth.height() as usize);
    if map.ids.len() != w * h {
        return rec;
    }
    let noise = DepthNoise::estimate(&frame.depth);
    let d = frame.depth.data();
    let ids = &mut map.ids;
    let n = w * h;
    // Piece label per pixel; pieces of one instance in `pieces[id]` as (start, members).
    let mut seen = vec![false; n];
    let mut stack = Vec::new();
    let mut by_instance: std::collections::BTreeMap<u16, Vec<Vec<usize>>> = Default::default();
    for start in 0..n {
        let id = ids[start];
        if id == 0 || seen[start] || d[start] <= 0.0 || d[start].is_nan() {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let mut members = Vec::new();
        while let Some(i) = stack.pop() {
            members.push(i);
            let z = d[i];
            let tol = opts.connect_sigmas * noise.sigma(z) + 0.02 * z;
            for j in neighbours4(i, w, h) {
                if !seen[j] && ids[j] == id && d[j] > 0.0 && (d[j] - z).abs() <= tol {
                    seen[j] = true;
                    stack.push(j);
                }
            }
        }
        by_instance.entry(id).or_default().push(members);
    }
    for (id, mut pieces) in by_instance {
        if pieces.len() < 2 {
            continue;
        }
        pieces.sort_by_key(|p| std::cmp::Reverse(p.len()));
        let mut lost = 0;
        for piece in &pieces[1..] {
            let border = piece
                .iter()
                .filter(|&&i| {
                    let (u, v) = (i % w, i / w);
                    let edge = u == 0 || v == 0 || u + 1 == w || v + 1 == h;
                    edge || neighbours4(i, w, h).any(|j| ids[j] != id)
                })
                .count();
            let rim = piece.len() < opts.min_piece_px
                || border as f32 >= opts.rim_fraction * piece.len() as f32;
            if rim {
                lost += piece.len();
                for &i in piece {
                    ids[i] = 0;
                }
            }
        }
        if lost > 0 {
            rec.instances += 1;
            rec.pixels += lost;
        }
    }
    rec
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use deocc_geometry::camera::{Camera, Intrinsics};
    use deocc_geometry::DepthMap;
    use deocc_io::images::InstanceMap;
    use image::RgbImage;

    /// A 40 x 40 object (id 1) at 1.5 m on a wall at 2.5 m; the mask is one pixel wider than the
    /// object all round (the rim sees the wall), and a thick block of the object (rows 30-39)
    /// sits across a 2-pixel gap with no depth (a thin occluder's shadow).
    fn frame() -> Frame {
        let (w, h) = (80usize, 80usize);
        let mut d = vec![2.5f32; w * h];
        let mut ids = vec![0u16; w * h];
        for v in 19..61 {
            for u in 19..61 {
                ids[v * w + u] = 1;
                if (20..60).contains(&v) && (20..60).contains(&u) {
                    d[v * w + u] = 1.5 + 0.001 * u as f32;
                }
            }
        }
        for u in 20..60 {
            d[40 * w + u] = 0.0;
            d[41 * w + u] = 0.0;
        }
        masked_frame(w, h, d, ids)
    }

    /// A `w x h` frame at the origin (60 degrees across) with depth `d` and instance map `ids`.
    pub(crate) fn masked_frame(w: usize, h: usize, d: Vec<f32>, ids: Vec<u16>) -> Frame {
        Frame {
            name: "f".into(),
            camera: Camera {
                intrinsics: Intrinsics::from_fov(w as u32, h as u32, 60.0).unwrap(),
                world_from_camera: nalgebra::Isometry3::identity(),
            },
            rgb: RgbImage::new(w as u32, h as u32),
            depth: DepthMap::new(w as u32, h as u32, d).unwrap(),
            instances: Some(InstanceMap {
                width: w as u32,
                height: h as u32,
                ids,
            }),
        }
    }

    #[test]
    fn the_rim_that_sees_the_wall_loses_its_label_the_cut_off_part_keeps_it() {
        let mut f = frame();
        let rec = unlabel_mask_rims(&mut f, &MaskRimOptions::default());
        let ids = &f.instances.as_ref().unwrap().ids;
        let w = 80;
        // The one-pixel rim (42 x 4 - 4 = 164 pixels) is unlabelled, nothing else.
        assert_eq!(rec.pixels, 164, "{rec:?}");
        assert_eq!(rec.instances, 1);
        for v in 19..61 {
            for u in 19..61 {
                let rim = u == 19 || u == 60 || v == 19 || v == 60;
                let label = ids[v * w + u];
                assert_eq!(label, if rim { 0 } else { 1 }, "pixel {u}, {v}");
            }
        }
    }

    #[test]
    fn off_or_without_a_map_nothing_changes() {
        let mut f = frame();
        let before = f.instances.clone();
        let off = MaskRimOptions {
            enabled: false,
            ..Default::default()
        };
        assert_eq!(unlabel_mask_rims(&mut f, &off), MaskRimRecord::default());
        assert_eq!(f.instances, before);
        f.instances = None;
        assert_eq!(
            unlabel_mask_rims(&mut f, &MaskRimOptions::default()),
            MaskRimRecord::default()
        );
    }

    #[test]
    fn settings_out_of_range_are_named() {
        let bad = MaskRimOptions {
            rim_fraction: 1.5,
            ..Default::default()
        };
        let e = bad.validate().unwrap_err().to_string();
        assert!(e.contains("mask_rims.rim_fraction"), "{e}");
    }
}
