//! The rule-based completer: the strongest answer hand-made rules give, and the baseline every
//! learned completer is measured against.
//!
//! - mask: the geometric prior ([`MaskPrior::EllipseOrBoxInFront`] by default);
//! - colour: each hidden pixel takes the colour of the nearest visible pixel;
//! - near side: a plane fitted (Huber IRLS) to the visible relative depth over the crop, extended
//!   under the hidden pixels; visible pixels keep their observed depth;
//! - with other views ([`CropCondition::seen_elsewhere`]), the points they saw join the mask
//!   and keep their colour and depth, and seed the colour fill and the plane as visible pixels
//!   do;
//! - far side: the near side mirrored about the object's axis, row by row, as for a solid of
//!   revolution standing upright (a can, a bottle): each row's cross-section is a circle as wide
//!   as the row's extent in the mask.
//!
//! The same functions are GL-DoT's residual base when its config says `base: rules`: the model
//! then generates only what the rules get wrong.

use deocc_geometry::Provenance;

use crate::crop::{CompletionOptions, CropCompletion, CropCondition, CropRequest};
use crate::priors::MaskPrior;
use crate::{Completer, CompletionError};

/// Probability given to a prior pixel that is not visible. On the 3,273 test pairs of main at
/// 014499d, 120 of the ellipse-or-box prior's 159 hidden pixels per pair were object (precision
/// 0.75, ../shared/notes/gldot-headroom.md).
pub const PRIOR_PIXEL_PROBABILITY: f32 = 0.75;

/// The rule-based completer.
#[derive(Debug, Clone)]
pub struct RulesCompleter {
    /// Crop side it asks the pipeline for (any works; the shipped model's 64 by default).
    pub resolution: usize,
    pub mask: MaskPrior,
}

impl Default for RulesCompleter {
    fn default() -> Self {
        Self {
            resolution: 64,
            mask: MaskPrior::EllipseOrBoxInFront,
        }
    }
}

impl RulesCompleter {
    /// Completes one crop.
    pub fn complete_one(&self, c: &CropCondition) -> CropCompletion {
        let r = c.resolution;
        let amodal = c.prior_of(self.mask);
        let mask_probability = amodal
            .iter()
            .zip(&c.visible)
            .map(|(&a, &v)| {
                if v {
                    1.0
                } else if a {
                    PRIOR_PIXEL_PROBABILITY
                } else {
                    0.0
                }
            })
            .collect();
        // Visible pixels and, with several views, the points other views saw of the object.
        let seen = c.observed();
        let fill = nearest_visible_colour(&seen.rgb, &seen.mask, r);
        let rgb = (0..r * r)
            .flat_map(|p| {
                let px = if amodal[p] {
                    [fill[3 * p], fill[3 * p + 1], fill[3 * p + 2]]
                } else {
                    [255; 3]
                };
                px.into_iter()
            })
            .collect();
        let depth = plane_near_side(&seen.depth, &seen.mask, r);
        let back_depth = symmetric_far_side(&depth, &amodal, r);
        CropCompletion {
            amodal,
            mask_probability,
            rgb,
            depth,
            back_depth,
            expected_error: None,
        }
    }
}

impl Completer for RulesCompleter {
    fn name(&self) -> &str {
        "rules"
    }
    fn provenance(&self) -> Provenance {
        Provenance::Rules
    }
    fn resolution(&self) -> usize {
        self.resolution
    }
    fn complete(
        &self,
        batch: &[CropRequest<'_>],
        _opts: &CompletionOptions,
    ) -> Result<Vec<CropCompletion>, CompletionError> {
        Ok(batch
            .iter()
            .map(|req| self.complete_one(req.condition))
            .collect())
    }
}

/// Every pixel's colour taken from the nearest pixel where `seeds` is set (r*r*3; the seeds keep
/// their own). Nearest in the Euclidean sense, by two raster passes that propagate each pixel's
/// nearest seed from its neighbours (exact for all but rare configurations). Without seeds, white.
pub fn nearest_visible_colour(rgb: &[u8], seeds: &[bool], r: usize) -> Vec<u8> {
    let nearest = nearest_seed(seeds, r);
    (0..r * r)
        .flat_map(|p| {
            let px = match nearest[p] {
                Some(s) => [rgb[3 * s], rgb[3 * s + 1], rgb[3 * s + 2]],
                None => [255; 3],
            };
            px.into_iter()
        })
        .collect()
}

/// Index of the nearest seed pixel of every pixel (`None` without seeds).
pub fn nearest_seed(seeds: &[bool], r: usize) -> Vec<Option<usize>> {
    let mut near: Vec<Option<usize>> = (0..r * r).map(|p| seeds[p].then_some(p)).collect();
    let d2 = |p: usize, s: usize| {
        let (du, dv) = (
            (p % r) as i64 - (s % r) as i64,
            (p / r) as i64 - (s / r) as i64,
        );
        du * du + dv * dv
    };
    let relax = |p: usize, q: usize, near: &mut [Option<usize>]| {
        if let Some(s) = near[q] {
            if near[p].is_none_or(|cur| d2(p, s) < d2(p, cur)) {
                near[p] = Some(s);
            }
        }
    };
    let ri = r as i64;
    let at = |u: i64, v: i64| (u >= 0 && v >= 0 && u < ri && v < ri).then(|| (v * ri + u) as usize);
    // Forward pass (from the top-left neighbours), then backward (from the bottom-right).
    for pass in 0..2 {
        for k in 0..r * r {
            let p = if pass == 0 { k } else { r * r - 1 - k };
            let (u, v) = ((p % r) as i64, (p / r) as i64);
            let s = if pass == 0 { -1 } else { 1 };
            for (du, dv) in [(s, 0), (0, s), (s, s), (-s, s)] {
                if let Some(q) = at(u + du, v + dv) {
                    relax(p, q, &mut near);
                }
            }
        }
    }
    near
}

/// Huber threshold of the plane fit, in relative depth (crop widths).
const PLANE_HUBER_DELTA: f64 = 0.02;

/// The near side: visible pixels keep their depth, the others take the plane
/// `z = a x + b y + c` fitted to the visible pixels (x, y in crop widths; Huber IRLS, 8 rounds).
/// With fewer than 3 visible pixels or a degenerate fit, the median visible depth.
pub fn plane_near_side(visible_depth: &[f32], visible: &[bool], r: usize) -> Vec<f32> {
    let pts: Vec<(f64, f64, f64)> = (0..r * r)
        .filter(|&p| visible[p])
        .map(|p| {
            (
                ((p % r) as f64 + 0.5) / r as f64,
                ((p / r) as f64 + 0.5) / r as f64,
                visible_depth[p] as f64,
            )
        })
        .collect();
    let plane = fit_plane_huber(&pts);
    (0..r * r)
        .map(|p| {
            if visible[p] {
                visible_depth[p]
            } else {
                let (x, y) = (
                    ((p % r) as f64 + 0.5) / r as f64,
                    ((p / r) as f64 + 0.5) / r as f64,
                );
                (plane[0] * x + plane[1] * y + plane[2]) as f32
            }
        })
        .collect()
}

/// `[a, b, c]` of `z = a x + b y + c` by Huber IRLS; a constant plane at the median when the
/// points do not determine one.
pub fn fit_plane_huber(pts: &[(f64, f64, f64)]) -> [f64; 3] {
    let median = {
        let mut z: Vec<f64> = pts.iter().map(|p| p.2).collect();
        if z.is_empty() {
            return [0.0; 3];
        }
        let mid = z.len() / 2;
        z.select_nth_unstable_by(mid, f64::total_cmp);
        z[mid]
    };
    let flat = [0.0, 0.0, median];
    if pts.len() < 3 {
        return flat;
    }
    let mut plane = flat;
    let mut weights = vec![1.0; pts.len()];
    for _ in 0..8 {
        let mut ata = nalgebra::Matrix3::<f64>::zeros();
        let mut atb = nalgebra::Vector3::<f64>::zeros();
        for (&(x, y, z), &w) in pts.iter().zip(&weights) {
            let a = nalgebra::Vector3::new(x, y, 1.0);
            ata += a * a.transpose() * w;
            atb += a * (z * w);
        }
        let Some(sol) = ata.try_inverse().map(|inv| inv * atb) else {
            return flat;
        };
        plane = [sol[0], sol[1], sol[2]];
        for (w, &(x, y, z)) in weights.iter_mut().zip(pts) {
            let res = (z - (plane[0] * x + plane[1] * y + plane[2])).abs();
            *w = if res <= PLANE_HUBER_DELTA {
                1.0
            } else {
                PLANE_HUBER_DELTA / res
            };
        }
    }
    if plane.iter().all(|c| c.is_finite()) {
        plane
    } else {
        flat
    }
}

/// The far side by symmetry: in each row the object's cross-section is taken to be a circle as
/// wide as the row's extent in `amodal` (half-width `h`, centre `x_c`), whose axis lies at
/// `z_c = median(near + sqrt(h^2 - (x - x_c)^2))` over the row; the back is the near side mirrored
/// about it, `2 z_c - near`, and never in front of the near side. 0 outside the mask.
pub fn symmetric_far_side(near: &[f32], amodal: &[bool], r: usize) -> Vec<f32> {
    let mut back = vec![0f32; r * r];
    for v in 0..r {
        let row = &amodal[v * r..(v + 1) * r];
        let (Some(u0), Some(u1)) = (row.iter().position(|&a| a), row.iter().rposition(|&a| a))
        else {
            continue;
        };
        let half = (u1 - u0 + 1) as f32 / (2.0 * r as f32);
        let centre = (u0 + u1 + 1) as f32 / (2.0 * r as f32);
        let chord = |u: usize| {
            let x = (u as f32 + 0.5) / r as f32 - centre;
            (half * half - x * x).max(0.0).sqrt()
        };
        let mut axis: Vec<f32> = (u0..=u1)
            .filter(|&u| row[u])
            .map(|u| near[v * r + u] + chord(u))
            .collect();
        let mid = axis.len() / 2;
        axis.select_nth_unstable_by(mid, f32::total_cmp);
        let zc = axis[mid];
        for u in (u0..=u1).filter(|&u| row[u]) {
            let p = v * r + u;
            back[p] = (2.0 * zc - near[p]).max(near[p]);
        }
    }
    back
}
