//! Stage: a given mask's holes take its own depth. Runs in the front half after
//! [`crate::mask_rims`], on frames that came with instance maps (a segmenter's masks are cut from
//! the depth and have no holes to fill).
//!
//! A mask drawn on colour covers the whole object; a sensor measures less of it: the projector's
//! or the second camera's shadow, grazing drop-outs along a curved body's sides, speckle on a
//! dark label. Back-projected, such an object is narrower and shorter than it is, and every
//! stage after it believes that: the completer completes a smaller object, the place planner
//! stands a cup where its edge is, a grasp closes on a target thinner than the true one.
//!
//! Each pixel of an instance's mask without depth is filled from the measured pixels **of the
//! same instance** within `window_px` of it (then, if too few, within `max_window_px`): a
//! least-squares plane in inverse depth over the image (exact for a plane seen in perspective),
//! read at the pixel and kept within the depth range of the pixels it was fitted to (no
//! extrapolation beyond what the object shows). Pixels with fewer than `min_samples` measured
//! neighbours of their instance stay without depth; measured pixels never change; pixels of no
//! instance (id 0) are not touched.

use deocc_geometry::DepthMap;
use deocc_io::scene::Frame;
use serde::{Deserialize, Serialize};

use crate::PipelineError;

/// The stage's settings.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct MaskHoleOptions {
    /// Run the stage at all.
    pub enabled: bool,
    /// The window the plane is fitted in first: pixels within this many of the hole, each way.
    pub window_px: usize,
    /// The wider window tried when the first has too few samples (one no wider than
    /// `window_px` tries nothing more).
    pub max_window_px: usize,
    /// Measured pixels of the instance a fit needs.
    pub min_samples: usize,
    /// Instances whose mask covers more than this share of the frame are left as they are: the
    /// room's surfaces (a table top, the floor, a wall), which the plane stage completes, and
    /// where a fit to a few noisy pixels at a grazing angle puts points a centimetre over the
    /// surface, which a place planner reads as obstacles.
    pub max_instance_fraction: f32,
}

impl Default for MaskHoleOptions {
    fn default() -> Self {
        Self {
            enabled: true,
            window_px: 4,
            max_window_px: 10,
            min_samples: 8,
            max_instance_fraction: 0.05,
        }
    }
}

impl MaskHoleOptions {
    pub fn validate(&self) -> Result<(), PipelineError> {
        let bad = |field: &'static str, msg: String| PipelineError::Option { field, msg };
        for (field, v, lo, hi) in [
            ("mask_holes.window_px", self.window_px, 1, 64),
            ("mask_holes.max_window_px", self.max_window_px, 1, 64),
            ("mask_holes.min_samples", self.min_samples, 3, 10_000),
        ] {
            if !(lo..=hi).contains(&v) {
                return Err(bad(field, format!("{v} is outside {lo} ..= {hi}")));
            }
        }
        let share = self.max_instance_fraction;
        if !(0.0..=1.0).contains(&share) {
            return Err(bad(
                "mask_holes.max_instance_fraction",
                format!("{share} is outside [0, 1]"),
            ));
        }
        Ok(())
    }
}

/// What the stage did to one frame.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq, Eq)]
pub struct MaskHoleRecord {
    /// Mask pixels without depth before the stage (of the instances small enough to fill).
    pub holes: usize,
    /// Of them, pixels filled.
    pub filled: usize,
}

/// The inverse-depth plane through the measured pixels of instance `id` within `r` of `(u, v)`,
/// read at `(u, v)` and clamped to their depth range; `None` with fewer than `min` of them or a
/// degenerate fit.
fn fit_at(
    d: &[f32],
    ids: &[u16],
    (w, h): (usize, usize),
    (u, v): (usize, usize),
    id: u16,
    r: usize,
    min: usize,
) -> Option<f32> {
    let (u0, u1) = (u.saturating_sub(r), (u + r).min(w - 1));
    let (v0, v1) = (v.saturating_sub(r), (v + r).min(h - 1));
    // Normal equations of q = a x + b y + c over centred pixel offsets (x, y).
    let (mut sxx, mut sxy, mut syy, mut sx, mut sy, mut n) = (0f64, 0f64, 0f64, 0f64, 0f64, 0f64);
    let (mut sxq, mut syq, mut sq) = (0f64, 0f64, 0f64);
    let (mut lo, mut hi) = (f32::MAX, f32::MIN);
    for y in v0..=v1 {
        for x in u0..=u1 {
            let i = y * w + x;
            let z = d[i];
            if ids[i] != id || !(z > 0.0 && z.is_finite()) {
                continue;
            }
            let (fx, fy, q) = (x as f64 - u as f64, y as f64 - v as f64, 1.0 / z as f64);
            sxx += fx * fx;
            sxy += fx * fy;
            syy += fy * fy;
            sx += fx;
            sy += fy;
            n += 1.0;
            sxq += fx * q;
            syq += fy * q;
            sq += q;
            lo = lo.min(z);
            hi = hi.max(z);
        }
    }
    if (n as usize) < min {
        return None;
    }
    let m = nalgebra::Matrix3::new(sxx, sxy, sx, sxy, syy, sy, sx, sy, n);
    let rhs = nalgebra::Vector3::new(sxq, syq, sq);
    // A line of samples (one row, one column) leaves the plane free across it: their mean then.
    let c = match m.lu().solve(&rhs) {
        Some(s) if m.determinant().abs() > 1e-6 * n * n * n => s.z,
        _ => sq / n,
    };
    let z = (1.0 / c) as f32;
    (z.is_finite() && z > 0.0).then(|| z.clamp(lo, hi))
}

/// Fills the holes of `frame`'s instance masks from their own depth (see the module docs);
/// nothing without a map.
pub fn fill_mask_holes(frame: &mut Frame, opts: &MaskHoleOptions) -> MaskHoleRecord {
    let mut rec = MaskHoleRecord::default();
    if !opts.enabled {
        return rec;
    }
    let Some(map) = frame.instances.as_ref() else {
        return rec;
    };
    let (w, h) = (frame.depth.width() as usize, frame.depth.height() as usize);
    if map.ids.len() != w * h || w == 0 || h == 0 {
        return rec;
    }
    let d = frame.depth.data();
    let ids = &map.ids;
    let mut area = vec![0usize; u16::MAX as usize + 1];
    for &id in ids {
        area[id as usize] += 1;
    }
    let most = (opts.max_instance_fraction as f64 * (w * h) as f64) as usize;
    let holes: Vec<usize> = (0..w * h)
        .filter(|&i| {
            ids[i] != 0 && area[ids[i] as usize] <= most && !(d[i] > 0.0 && d[i].is_finite())
        })
        .collect();
    rec.holes = holes.len();
    if holes.is_empty() {
        return rec;
    }
    // Every fit reads the measured depth only, so the order of the holes does not matter.
    let filled: Vec<(usize, f32)> = holes
        .iter()
        .filter_map(|&i| {
            let (u, v) = (i % w, i / w);
            fit_at(
                d,
                ids,
                (w, h),
                (u, v),
                ids[i],
                opts.window_px,
                opts.min_samples,
            )
            .or_else(|| {
                (opts.max_window_px > opts.window_px).then_some(())?;
                fit_at(
                    d,
                    ids,
                    (w, h),
                    (u, v),
                    ids[i],
                    opts.max_window_px,
                    opts.min_samples,
                )
            })
            .map(|z| (i, z))
        })
        .collect();
    rec.filled = filled.len();
    let mut out = d.to_vec();
    for (i, z) in filled {
        out[i] = z;
    }
    frame.depth = DepthMap::new(w as u32, h as u32, out).expect("same size as the frame's depth");
    rec
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 40 x 40 object (id 1) on a tilted plane, 1/z = 0.6 + 0.002 u + 0.001 v, on a wall at
    /// 2.5 m (id 2); a 6-pixel band of the object has no depth (a shadow), as does a 3 x 3 patch
    /// of the wall next to it and a corner of the wall far from any measured wall pixel.
    fn frame() -> (Frame, Vec<f32>) {
        let (w, h) = (80usize, 80usize);
        let mut truth = vec![2.5f32; w * h];
        let mut ids = vec![2u16; w * h];
        for v in 20..60 {
            for u in 20..60 {
                ids[v * w + u] = 1;
                truth[v * w + u] = 1.0 / (0.6 + 0.002 * u as f32 + 0.001 * v as f32);
            }
        }
        let mut d = truth.clone();
        for v in 20..60 {
            for u in 40..46 {
                d[v * w + u] = 0.0;
            }
        }
        for v in 30..33 {
            for u in 10..13 {
                d[v * w + u] = 0.0;
            }
        }
        // The wall's top-left corner: 24 x 24 pixels without depth.
        for v in 0..24 {
            for u in 0..24 {
                if ids[v * w + u] == 2 {
                    d[v * w + u] = 0.0;
                }
            }
        }
        (crate::mask_rims::tests::masked_frame(w, h, d, ids), truth)
    }

    #[test]
    fn a_masks_holes_take_its_own_surface_and_nothing_else() {
        let (mut f, truth) = frame();
        let before = f.depth.data().to_vec();
        // Object and wall are both under the share here: the wall is filled too.
        let all = MaskHoleOptions {
            max_instance_fraction: 1.0,
            ..Default::default()
        };
        let rec = fill_mask_holes(&mut f, &all);
        let after = f.depth.data();
        let w = 80;
        // The object's band lies on the object's plane, not between it and the wall: on it where
        // the window holds both sides of the band, within the depth range of the side it holds
        // (no extrapolation) elsewhere.
        for v in 20..60 {
            for u in 40..46 {
                let (z, t) = (after[v * w + u], truth[v * w + u]);
                let tol = if (42..44).contains(&u) { 1e-3 } else { 0.01 };
                assert!((z - t).abs() < tol, "({u}, {v}): {z} against {t}");
            }
        }
        // The wall's small hole is the wall.
        for v in 30..33 {
            for u in 10..13 {
                assert!((after[v * w + u] - 2.5).abs() < 1e-4);
            }
        }
        // Far from any measured pixel of its instance a hole stays a hole.
        assert_eq!(after[2 * w + 2], 0.0);
        // Measured pixels never change.
        for (a, b) in before.iter().zip(after) {
            if *a > 0.0 {
                assert_eq!(a, b);
            }
        }
        assert_eq!(
            rec.filled,
            after.iter().zip(&before).filter(|(a, b)| a != b).count()
        );
        assert!(rec.holes > rec.filled && rec.filled >= 40 * 6 + 9);
    }

    /// At the default share the wall (75% of the frame) is a room's surface and keeps its holes;
    /// the object (25%) is filled only once the share lets it in.
    #[test]
    fn the_rooms_surfaces_keep_their_holes() {
        let (mut f, _) = frame();
        let before = f.depth.data().to_vec();
        let opts = MaskHoleOptions {
            max_instance_fraction: 0.3,
            ..Default::default()
        };
        let rec = fill_mask_holes(&mut f, &opts);
        assert_eq!(rec.holes, 40 * 6);
        assert_eq!(rec.filled, 40 * 6);
        assert_eq!(f.depth.data()[31 * 80 + 11], 0.0, "the wall's hole stays");
        f.depth = DepthMap::new(80, 80, before.clone()).unwrap();
        let rec = fill_mask_holes(&mut f, &MaskHoleOptions::default());
        assert_eq!(
            rec,
            MaskHoleRecord::default(),
            "the object is 25% of the frame"
        );
        assert_eq!(f.depth.data(), &before[..]);
    }

    #[test]
    fn off_or_without_a_map_nothing_changes() {
        let (mut f, _) = frame();
        let before = f.depth.data().to_vec();
        let off = MaskHoleOptions {
            enabled: false,
            ..Default::default()
        };
        assert_eq!(fill_mask_holes(&mut f, &off), MaskHoleRecord::default());
        f.instances = None;
        assert_eq!(
            fill_mask_holes(&mut f, &MaskHoleOptions::default()),
            MaskHoleRecord::default()
        );
        assert_eq!(f.depth.data(), &before[..]);
    }

    #[test]
    fn out_of_range_settings_are_refused_by_name() {
        let o = MaskHoleOptions {
            max_window_px: 65,
            ..Default::default()
        };
        assert!(o
            .validate()
            .unwrap_err()
            .to_string()
            .contains("max_window_px"));
        let o = MaskHoleOptions {
            min_samples: 1,
            ..Default::default()
        };
        assert!(o
            .validate()
            .unwrap_err()
            .to_string()
            .contains("min_samples"));
    }
}
