//! The geometric amodal priors: where an occluded object's hidden part probably is, from the
//! visible mask and the observed scene depth alone. They are the strongest masks measured without
//! a model and the starting point of every completer: the rules completer returns one as its mask,
//! GL-DoT reads one as condition channel 6 and, with `mask_head`, predicts a correction to it.
//!
//! Masks are `r x r` row-major; `scene_rel_depth` is the crop's observed depth relative to the
//! object's median visible depth, in crop widths, clamped to [-1, 1], and 0 where nothing is
//! measured ([`crate::CropCondition::scene_depth`]).

use deocc_geometry::mask2d::{conic_value, convex_hull_mask, fit_ellipse};
use serde::{Deserialize, Serialize};

/// Which geometric prior a mask starts from (a model's residual base, the rules completer's mask).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MaskPrior {
    /// The visible mask ("amodal = visible"): what models before the seventh condition channel
    /// were trained with, hence the default when a stored config does not name one.
    #[default]
    Visible,
    /// The visible mask's convex hull where the scene is in front ([`hull_prior`]).
    HullInFront,
    /// The hull prior extended by the ellipse fitted to the object's own contour where the scene
    /// is in front ([`ellipse_prior`]): validation mIoU 0.816 against 0.780 for the hull.
    EllipseInFront,
    /// The ellipse prior extended by the bounding box of the object's silhouette where the scene
    /// is in front ([`ellipse_or_box_prior`]): validation mIoU 0.825. The default prior of crops
    /// ([`crate::CropCondition::prior`]) and of the presets.
    EllipseOrBoxInFront,
}

/// The geometric amodal prior: the visible mask, plus the pixels of its convex hull where the
/// observed scene is nearer than the object's median visible depth (`scene_rel_depth < 0`) —
/// where something occludes the object, so a hidden part can be there without being seen.
/// `scene_rel_depth` is 0 where nothing is observed (outside the image, missing depth).
pub fn hull_prior(visible: &[bool], scene_rel_depth: &[f32], r: usize) -> Vec<bool> {
    let hull = convex_hull_mask(visible, r);
    (0..r * r)
        .map(|p| visible[p] || (hull[p] && scene_rel_depth[p] < 0.0))
        .collect()
}

/// The ellipse prior: [`hull_prior`], plus the pixels where the scene is in front that lie inside
/// the ellipse fitted to the object's own contour. That contour is the visible pixels next to
/// a pixel (inside the crop) that is neither the object nor in front of it: there the object's
/// silhouette ends, while next to an occluder it only stops being seen. Most objects project to
/// convex, roundish silhouettes, so the ellipse through the seen part of the silhouette runs on
/// behind the occluder where the convex hull stops at the visible pixels. An ellipse larger than
/// three times the visible area (an almost straight contour, a poor fit) adds nothing.
/// Measured without a model on 300 validation pairs: mIoU 0.816 against 0.780 for [`hull_prior`].
pub fn ellipse_prior(visible: &[bool], scene_rel_depth: &[f32], r: usize) -> Vec<bool> {
    let mut prior = hull_prior(visible, scene_rel_depth, r);
    let contour = silhouette_pixels(visible, scene_rel_depth, r);
    if contour.len() < MIN_SILHOUETTE {
        return prior;
    }
    let points: Vec<(f64, f64)> = contour
        .iter()
        .map(|&(u, v)| ((u as f64 + 0.5) / r as f64, (v as f64 + 0.5) / r as f64))
        .collect();
    const MAX_AREA_OVER_VISIBLE: usize = 3;
    let Some(q) = fit_ellipse(&points) else {
        return prior;
    };
    let value = |p: usize| {
        let (u, v) = ((p % r) as f64 + 0.5, (p / r) as f64 + 0.5);
        conic_value(&q, u / r as f64, v / r as f64)
    };
    // Inside is the side the visible pixels are on (the median's sign, robust to a stray pixel).
    let mut on_visible: Vec<f64> = (0..r * r).filter(|&p| visible[p]).map(value).collect();
    on_visible.sort_unstable_by(f64::total_cmp);
    let sign = on_visible[on_visible.len() / 2].signum();
    let inside: Vec<bool> = (0..r * r).map(|p| value(p) * sign > 0.0).collect();
    let area = inside.iter().filter(|&&i| i).count();
    if area >= MAX_AREA_OVER_VISIBLE * on_visible.len().max(1) {
        return prior;
    }
    for p in 0..r * r {
        prior[p] |= inside[p] && scene_rel_depth[p] < 0.0;
    }
    prior
}

/// Fewest silhouette pixels a shape is fitted to.
const MIN_SILHOUETTE: usize = 8;

/// The object's own silhouette, (u, v) pixels: visible pixels next to a pixel (inside the crop)
/// that is neither the object nor in front of it. There the object's outline ends, while next
/// to an occluder it only stops being seen.
fn silhouette_pixels(visible: &[bool], scene_rel_depth: &[f32], r: usize) -> Vec<(usize, usize)> {
    let at = |u: usize, v: usize| v * r + u;
    let mut contour = Vec::new();
    for v in 0..r {
        for u in 0..r {
            if !visible[at(u, v)] {
                continue;
            }
            let neighbours = [
                (u > 0).then(|| at(u - 1, v)),
                (u + 1 < r).then(|| at(u + 1, v)),
                (v > 0).then(|| at(u, v - 1)),
                (v + 1 < r).then(|| at(u, v + 1)),
            ];
            let silhouette = neighbours
                .iter()
                .flatten()
                .any(|&q| !visible[q] && scene_rel_depth[q] >= 0.0);
            if silhouette {
                contour.push((u, v));
            }
        }
    }
    contour
}

/// The ellipse-or-box prior: [`ellipse_prior`], plus the pixels where the scene is in front inside
/// the image-axis-aligned bounding box of the object's silhouette pixels. Upright boxes, books,
/// cans and bottles project to silhouettes that fill their bounding box better than an ellipse
/// does (their hidden corners), and the seen outline already spans the object's extent along
/// the sides where it is seen. Measured without a model on 300 validation pairs: mIoU 0.825
/// against 0.816 for the ellipse prior (`deocc eval amodal --split val`, baseline fields).
pub fn ellipse_or_box_prior(visible: &[bool], scene_rel_depth: &[f32], r: usize) -> Vec<bool> {
    let mut prior = ellipse_prior(visible, scene_rel_depth, r);
    let contour = silhouette_pixels(visible, scene_rel_depth, r);
    if contour.len() < MIN_SILHOUETTE {
        return prior;
    }
    let (mut u0, mut u1, mut v0, mut v1) = (r, 0, r, 0);
    for &(u, v) in &contour {
        (u0, u1, v0, v1) = (u0.min(u), u1.max(u), v0.min(v), v1.max(v));
    }
    for v in v0..=v1 {
        for u in u0..=u1 {
            let p = v * r + u;
            prior[p] |= scene_rel_depth[p] < 0.0;
        }
    }
    prior
}

/// The prior of this kind. `Visible` gives the hull prior: models trained with the visible or the
/// hull prior were given the hull as condition channel 6.
pub fn mask_prior(
    kind: MaskPrior,
    visible: &[bool],
    scene_rel_depth: &[f32],
    r: usize,
) -> Vec<bool> {
    match kind {
        MaskPrior::Visible | MaskPrior::HullInFront => hull_prior(visible, scene_rel_depth, r),
        MaskPrior::EllipseInFront => ellipse_prior(visible, scene_rel_depth, r),
        MaskPrior::EllipseOrBoxInFront => ellipse_or_box_prior(visible, scene_rel_depth, r),
    }
}
