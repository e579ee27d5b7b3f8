//! Batches for GL-DoT from the synthetic training pairs.
//!
//! Target channels (in [-1, 1] roughly): RGB `v / 127.5 - 1`, amodal mask `2 m - 1`, relative
//! depth of the object's near side and of its far side (its back, which no view shows), times
//! [`DEPTH_SCALE`]. Conditioning channels: crop RGB, visible mask, visible relative
//! depth, and the whole crop's observed relative depth (clamped to [-1, 1]), scaled the same way.
//! The last one tells the model where something is in front of the object (it may continue
//! there) and where the scene is behind it (it cannot: it would be seen). The seventh is a
//! geometric prior of the model's [`MaskPrior`]: [`hull_prior`] (the visible mask's convex hull
//! where the scene is in front) or [`ellipse_prior`] (that, plus the ellipse fitted to the
//! object's own contour where the scene is in front). Models read the first channels they were
//! trained with, so older weights keep working.

use std::collections::HashMap;
use std::path::Path;

use crate::config::MaskPrior;
use candle_core::{Device, Result, Tensor};
use deocc_geometry::mask2d::{conic_value, convex_hull_mask, fit_ellipse};
use deocc_synth::pairs::{load_pairs, PairSet};
use rand::Rng;

/// Relative depth is (d - median visible) / crop width: about +-0.5; doubled to fill [-1, 1].
pub const DEPTH_SCALE: f32 = 2.0;
pub const TARGET_CHANNELS: usize = 6;
pub const COND_CHANNELS: usize = 7;

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

/// The mask of condition channel 6 for a model with this residual prior. Models trained with the
/// visible or the hull prior were given the hull there.
pub fn condition_prior(
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

/// Pairs plus an index of which pairs show the same object.
pub struct PairData {
    pub set: PairSet,
    groups: HashMap<u32, Vec<usize>>,
    /// Which prior condition channel 6 carries (set it to the model's, see [`condition_prior`]).
    mask_prior: MaskPrior,
}

impl PairData {
    pub fn new(set: PairSet) -> Self {
        let mut groups: HashMap<u32, Vec<usize>> = HashMap::new();
        for (i, &g) in set.group.iter().enumerate() {
            groups.entry(g).or_default().push(i);
        }
        Self {
            set,
            groups,
            mask_prior: MaskPrior::HullInFront,
        }
    }

    /// The same pairs with condition channel 6 made for a model with this residual prior.
    pub fn with_mask_prior(mut self, kind: MaskPrior) -> Self {
        self.mask_prior = kind;
        self
    }

    /// Loads and concatenates shards (group ids are made unique per shard file).
    pub fn load(paths: &[impl AsRef<Path>]) -> std::result::Result<Self, deocc_synth::SynthError> {
        let mut all = PairSet::default();
        for (k, p) in paths.iter().enumerate() {
            let mut s = load_pairs(p.as_ref())?;
            for g in &mut s.group {
                *g = g.wrapping_add((k as u32) << 24);
            }
            all.extend(&s);
        }
        Ok(Self::new(all))
    }

    pub fn len(&self) -> usize {
        self.set.len()
    }
    pub fn is_empty(&self) -> bool {
        self.set.is_empty()
    }
    pub fn resolution(&self) -> usize {
        self.set.resolution as usize
    }

    /// Other pairs of the same object (other views).
    pub fn other_views(&self, i: usize) -> Vec<usize> {
        self.groups
            .get(&self.set.group[i])
            .map(|v| v.iter().copied().filter(|&j| j != i).collect())
            .unwrap_or_default()
    }

    /// A random other view of pair `i`, if there is one.
    pub fn random_other_view(&self, i: usize, rng: &mut impl Rng) -> Option<usize> {
        let others = self.other_views(i);
        (!others.is_empty()).then(|| others[rng.random_range(0..others.len())])
    }

    fn pixel(&self, i: usize, p: usize) -> usize {
        i * self.set.pixels() + p
    }

    /// Writes pair `i`'s target (R*R*5) and condition (R*R*5), optionally mirrored left-right.
    fn write_pair(&self, i: usize, flip: bool, target: &mut [f32], cond: &mut [f32]) {
        let r = self.resolution();
        let s = &self.set;
        let prior = self.condition_prior(i);
        for v in 0..r {
            for u in 0..r {
                let src_u = if flip { r - 1 - u } else { u };
                let p = self.pixel(i, v * r + src_u);
                let o = v * r + u;
                for c in 0..3 {
                    target[o * TARGET_CHANNELS + c] = s.whole_rgb[3 * p + c] as f32 / 127.5 - 1.0;
                    cond[o * COND_CHANNELS + c] = s.crop_rgb[3 * p + c] as f32 / 127.5 - 1.0;
                }
                target[o * TARGET_CHANNELS + 3] = 2.0 * s.amodal_mask[p] as f32 - 1.0;
                target[o * TARGET_CHANNELS + 4] = s.whole_depth[p] * DEPTH_SCALE;
                target[o * TARGET_CHANNELS + 5] = s.whole_back_depth[p] * DEPTH_SCALE;
                cond[o * COND_CHANNELS + 3] = 2.0 * s.visible_mask[p] as f32 - 1.0;
                cond[o * COND_CHANNELS + 4] = s.visible_depth[p] * DEPTH_SCALE;
                cond[o * COND_CHANNELS + 5] = s.scene_depth[p] * DEPTH_SCALE;
                cond[o * COND_CHANNELS + 6] = if prior[v * r + src_u] { 1.0 } else { -1.0 };
            }
        }
    }

    /// (x0 (B, R, R, 5), cond image (B, R, R, 5)) for the given pairs; `flips[k]` mirrors sample k.
    pub fn batch(
        &self,
        indices: &[usize],
        flips: &[bool],
        device: &Device,
    ) -> Result<(Tensor, Tensor)> {
        let r = self.resolution();
        let n = r * r;
        let mut target = vec![0f32; indices.len() * n * TARGET_CHANNELS];
        let mut cond = vec![0f32; indices.len() * n * COND_CHANNELS];
        for (k, &i) in indices.iter().enumerate() {
            let flip = flips.get(k).copied().unwrap_or(false);
            self.write_pair(
                i,
                flip,
                &mut target[k * n * TARGET_CHANNELS..(k + 1) * n * TARGET_CHANNELS],
                &mut cond[k * n * COND_CHANNELS..(k + 1) * n * COND_CHANNELS],
            );
        }
        let b = indices.len();
        Ok((
            Tensor::from_vec(target, (b, r, r, TARGET_CHANNELS), device)?,
            Tensor::from_vec(cond, (b, r, r, COND_CHANNELS), device)?,
        ))
    }

    /// [`hull_prior`] of pair `i` (unmirrored).
    pub fn hull_prior(&self, i: usize) -> Vec<bool> {
        self.prior_of(i, hull_prior)
    }

    /// [`ellipse_prior`] of pair `i` (unmirrored).
    pub fn ellipse_prior(&self, i: usize) -> Vec<bool> {
        self.prior_of(i, ellipse_prior)
    }

    /// Condition channel 6 of pair `i` (unmirrored): the prior of [`PairData::with_mask_prior`].
    pub fn condition_prior(&self, i: usize) -> Vec<bool> {
        let kind = self.mask_prior;
        self.prior_of(i, |v, s, r| condition_prior(kind, v, s, r))
    }

    fn prior_of(&self, i: usize, prior: impl Fn(&[bool], &[f32], usize) -> Vec<bool>) -> Vec<bool> {
        let n = self.set.pixels();
        let visible: Vec<bool> = self.visible_mask(i).iter().map(|&m| m > 0).collect();
        prior(
            &visible,
            &self.set.scene_depth[i * n..(i + 1) * n],
            self.resolution(),
        )
    }

    pub fn amodal_mask(&self, i: usize) -> &[u8] {
        let n = self.set.pixels();
        &self.set.amodal_mask[i * n..(i + 1) * n]
    }
    pub fn visible_mask(&self, i: usize) -> &[u8] {
        let n = self.set.pixels();
        &self.set.visible_mask[i * n..(i + 1) * n]
    }
    pub fn whole_depth(&self, i: usize) -> &[f32] {
        let n = self.set.pixels();
        &self.set.whole_depth[i * n..(i + 1) * n]
    }
    pub fn whole_back_depth(&self, i: usize) -> &[f32] {
        let n = self.set.pixels();
        &self.set.whole_back_depth[i * n..(i + 1) * n]
    }
    pub fn visible_depth(&self, i: usize) -> &[f32] {
        let n = self.set.pixels();
        &self.set.visible_depth[i * n..(i + 1) * n]
    }
}

/// Every `*.safetensors` shard of a split in a folder, sorted.
pub fn shards(dir: &Path, split: &str) -> std::io::Result<Vec<std::path::PathBuf>> {
    let mut v: Vec<_> = std::fs::read_dir(dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(&format!("{split}-")) && n.ends_with(".safetensors"))
        })
        .collect();
    v.sort();
    Ok(v)
}

/// The prior of a condition batch (B, R, R, 7) in target channels (B, R, R, 6): the crop's RGB on
/// the visible pixels and white elsewhere, the chosen mask prior as the amodal mask (the visible
/// mask, channel 3, or the hull-in-front prior, channel 6), and the visible depth for both the
/// near and the far side. With the visible mask it is the "amodal = visible" answer, exact on
/// every pixel an occluder does not hide, which is why the residual model generates only the rest.
pub fn residual_prior(cond: &Tensor, mask_prior: MaskPrior) -> Result<Tensor> {
    let rgb = cond.narrow(3, 0, 3)?;
    let vis_mask = cond.narrow(3, 3, 1)?;
    let depth = cond.narrow(3, 4, 1)?;
    let vis = ((&vis_mask + 1.0)? * 0.5)?; // {0, 1}
    let white = (vis.neg()? + 1.0)?;
    let prior_rgb = rgb.broadcast_mul(&vis)?.broadcast_add(&white)?;
    let prior_depth = depth.mul(&vis)?;
    let mask = match mask_prior {
        MaskPrior::Visible => vis_mask,
        MaskPrior::HullInFront | MaskPrior::EllipseInFront | MaskPrior::EllipseOrBoxInFront => {
            cond.narrow(3, 6, 1)?
        }
    };
    Tensor::cat(&[&prior_rgb, &mask, &prior_depth, &prior_depth], 3)
}
