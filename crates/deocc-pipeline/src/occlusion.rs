//! Stage: occlusion. Per view, two instance masks that touch, the farther one (by the median depth step
//! across their shared boundary) is occluded by the nearer one. Also records truncation by the
//! image border and missing depth along an instance's boundary.
//!
//! A band without depth between two masks counts as a shared boundary, and the depth order is
//! judged across it: a structured-light projector or a stereo camera's second eye leaves such a
//! band beside every near edge (the far surface there is in the emitter's shadow), so the masks
//! of an occluder and what it hides touch only through pixels without depth. Bands up to
//! [`max_band_px`] wide are crossed, through pixels of the two masks or of none.

use std::collections::BTreeMap;

use deocc_geometry::DepthMap;
use deocc_io::images::InstanceMap;
use serde::Serialize;

/// A depth step smaller than this (metres) is contact, not occlusion (objects standing on a table
/// touch it in the image without hiding each other).
pub const MIN_STEP_M: f32 = 0.02;

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct MaskOcclusion {
    pub instance_id: u16,
    pub visible_px: usize,
    /// Instances in front of this one along a shared boundary.
    pub occluded_by: Vec<u16>,
    /// The mask touches the image border.
    pub truncated: bool,
    /// Fraction of the mask's boundary pixels next to missing depth.
    pub missing_depth_boundary: f32,
}

impl MaskOcclusion {
    pub fn is_occluded(&self) -> bool {
        !self.occluded_by.is_empty()
    }
}

/// The widest band without depth crossed between two masks: 1/40 of the image width (16 px at
/// 640, the shadow of an edge 1 m in front of a surface 0.5 m behind it at a 7.5 cm baseline).
pub fn max_band_px(width: usize) -> usize {
    (width / 40).max(4)
}

/// Settings of the occlusion stage.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct OcclusionOptions {
    /// The widest band without depth crossed across the image's rows (up or down), pixels; 0 =
    /// as wide as along them ([`max_band_px`]). An emitter's shadow lies along its baseline, the
    /// camera's x axis, so a shadow band is crossed along a row; a band across the rows is a
    /// surface the sensor did not measure (a bowl's lower belly at a grazing angle), and below
    /// an object standing on a table the table beyond it lies nearer by the band's height times
    /// its slope in the image, which reads as the table hiding the object (docs/decisions.md,
    /// "Occlusion across bands below an object").
    pub max_band_across_rows_px: usize,
}

/// Occlusion analysis of one view, with the default [`OcclusionOptions`].
pub fn analyse_view(instances: &InstanceMap, depth: &DepthMap) -> Vec<MaskOcclusion> {
    analyse_view_with(instances, depth, &OcclusionOptions::default())
}

/// Occlusion analysis of one view.
pub fn analyse_view_with(
    instances: &InstanceMap,
    depth: &DepthMap,
    o: &OcclusionOptions,
) -> Vec<MaskOcclusion> {
    let (w, h) = (instances.width as usize, instances.height as usize);
    let band = max_band_px(w);
    let band_across_rows = match o.max_band_across_rows_px {
        0 => band,
        n => n.min(band),
    };
    let ids = &instances.ids;
    let d = depth.data();
    // depth(a) - depth(b) across every boundary pixel pair (a, b), keyed by (a, b).
    let mut steps: BTreeMap<(u16, u16), Vec<f32>> = BTreeMap::new();
    let mut area: BTreeMap<u16, usize> = BTreeMap::new();
    let mut truncated: BTreeMap<u16, bool> = BTreeMap::new();
    let mut boundary: BTreeMap<u16, (usize, usize)> = BTreeMap::new();
    for v in 0..h {
        for u in 0..w {
            let i = v * w + u;
            let a = ids[i];
            if a == 0 {
                continue;
            }
            *area.entry(a).or_default() += 1;
            if u == 0 || v == 0 || u == w - 1 || v == h - 1 {
                truncated.insert(a, true);
            }
            for (du, dv) in [(1i64, 0i64), (0, 1), (-1, 0), (0, -1)] {
                let (nu, nv) = (u as i64 + du, v as i64 + dv);
                if nu < 0 || nv < 0 || nu >= w as i64 || nv >= h as i64 {
                    continue;
                }
                let j = nv as usize * w + nu as usize;
                let b = ids[j];
                // Across a band without depth (each pair once: forward directions only). The
                // band may begin inside this mask: with masks that cover the emitter's shadow
                // (ground truth, or a segmenter that labels it), the farther object's mask holds
                // the band, and its depth pixels meet the band inside their own mask.
                if d[i] > 0.0 && d[j] <= 0.0 && du >= 0 && dv >= 0 {
                    let reach = if dv != 0 { band_across_rows } else { band };
                    if let Some((c, k)) = across_band(ids, d, w, h, (u, v), (du, dv), a, reach) {
                        steps.entry((a, c)).or_default().push(d[i] - d[k]);
                        steps.entry((c, a)).or_default().push(d[k] - d[i]);
                    }
                }
                if b == a {
                    continue;
                }
                let e = boundary.entry(a).or_default();
                e.0 += 1;
                if d[j] <= 0.0 || d[i] <= 0.0 {
                    e.1 += 1;
                    continue;
                }
                if b != 0 && du >= 0 && dv >= 0 {
                    // Each unordered neighbour pair once; store both orientations.
                    steps.entry((a, b)).or_default().push(d[i] - d[j]);
                    steps.entry((b, a)).or_default().push(d[j] - d[i]);
                }
            }
        }
    }
    let mut occluded_by: BTreeMap<u16, Vec<u16>> = BTreeMap::new();
    for ((a, b), mut s) in steps {
        if s.len() < 3 {
            continue;
        }
        let mid = s.len() / 2;
        s.select_nth_unstable_by(mid, f32::total_cmp);
        if s[mid] > MIN_STEP_M {
            occluded_by.entry(a).or_default().push(b);
        }
    }
    area.iter()
        .map(|(&id, &px)| {
            let (n, missing) = boundary.get(&id).copied().unwrap_or((0, 0));
            MaskOcclusion {
                instance_id: id,
                visible_px: px,
                occluded_by: occluded_by.remove(&id).unwrap_or_default(),
                truncated: truncated.get(&id).copied().unwrap_or(false),
                missing_depth_boundary: if n == 0 {
                    0.0
                } else {
                    missing as f32 / n as f32
                },
            }
        })
        .collect()
}

/// From pixel `(u, v)` of mask `a` along `(du, dv)`, across pixels without depth that belong to
/// `a` or to no mask: the first pixel with depth, if it lies at most `band` pixels on and belongs
/// to another mask (its id and index).
#[allow(clippy::too_many_arguments)]
fn across_band(
    ids: &[u16],
    d: &[f32],
    w: usize,
    h: usize,
    (u, v): (usize, usize),
    (du, dv): (i64, i64),
    a: u16,
    band: usize,
) -> Option<(u16, usize)> {
    let mut other: Option<u16> = None;
    for k in 1..=band as i64 + 1 {
        let (x, y) = (u as i64 + du * k, v as i64 + dv * k);
        if x < 0 || y < 0 || x >= w as i64 || y >= h as i64 {
            return None;
        }
        let j = y as usize * w + x as usize;
        let id = ids[j];
        if d[j] > 0.0 {
            return (id != 0 && id != a && other.is_none_or(|o| o == id)).then_some((id, j));
        }
        // A band pixel of a third mask: not a boundary between these two.
        if id != 0 && id != a {
            match other {
                None => other = Some(id),
                Some(o) if o != id => return None,
                _ => {}
            }
        }
    }
    None
}

/// The instances to complete, each with its candidate views `(view, visible pixels)`: an
/// instance occluded in some view (and not truncated there, not room structure) with those
/// views; with `unoccluded_too`, also every other non-structure instance with every view it is
/// seen untruncated in (its far side is hidden in all of them).
pub fn instances_to_complete(
    occlusion: &[Vec<MaskOcclusion>],
    structure_ids: &[u16],
    unoccluded_too: bool,
) -> BTreeMap<u16, Vec<(usize, usize)>> {
    let mut occluded: BTreeMap<u16, Vec<(usize, usize)>> = BTreeMap::new();
    let mut seen: BTreeMap<u16, Vec<(usize, usize)>> = BTreeMap::new();
    for (v, masks) in occlusion.iter().enumerate() {
        for m in masks {
            if structure_ids.contains(&m.instance_id) || m.truncated {
                continue;
            }
            if m.is_occluded() {
                occluded
                    .entry(m.instance_id)
                    .or_default()
                    .push((v, m.visible_px));
            }
            seen.entry(m.instance_id)
                .or_default()
                .push((v, m.visible_px));
        }
    }
    if unoccluded_too {
        for (id, views) in seen {
            occluded.entry(id).or_insert(views);
        }
    }
    occluded
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A near mask (1 m, left) and a far one (2 m, right) separated by `band` pixels without depth
    /// whose ids are `band_id`.
    fn pair(band: usize, band_id: u16) -> (InstanceMap, DepthMap) {
        two_masks((400, 20), band, band_id, |u, _| u)
    }

    /// A near mask and a far one in a `w` x `h` image, along the coordinate `along(u, v)`
    /// picks: from 10 the near one up to 60, then `band` pixels without depth (id `band_id`),
    /// then the far one up to 10 short of the image's end.
    fn two_masks(
        (w, h): (usize, usize),
        band: usize,
        band_id: u16,
        along: fn(usize, usize) -> usize,
    ) -> (InstanceMap, DepthMap) {
        let mut ids = vec![0u16; w * h];
        let mut d = vec![0f32; w * h];
        let end = along(w, h) - 10;
        for v in 0..h {
            for u in 0..w {
                let i = v * w + u;
                let x = along(u, v);
                if !(10..end).contains(&x) {
                    continue;
                }
                if x < 60 {
                    (ids[i], d[i]) = (1, 1.0);
                } else if x < 60 + band {
                    ids[i] = band_id;
                } else {
                    (ids[i], d[i]) = (2, 2.0);
                }
            }
        }
        (
            InstanceMap {
                width: w as u32,
                height: h as u32,
                ids,
            },
            DepthMap::new(w as u32, h as u32, d).unwrap(),
        )
    }

    fn occluded(masks: &[MaskOcclusion], id: u16) -> Vec<u16> {
        masks
            .iter()
            .find(|m| m.instance_id == id)
            .map(|m| m.occluded_by.clone())
            .unwrap_or_default()
    }

    #[test]
    fn the_depth_order_is_judged_across_a_shadow_band() {
        // The band is the far object's (ground-truth masks), or nobody's (a segmenter's).
        // Mirrored too: the far object on the left, the band inside its own mask, so the
        // crossing begins inside the farther mask (the projector's shadow falls on either side
        // of a near edge, depending on where the projector sits).
        for band_id in [2, 0] {
            for mirrored in [false, true] {
                let (mut map, depth) = pair(8, band_id);
                let depth = if mirrored {
                    let w = map.width as usize;
                    for row in map.ids.chunks_mut(w) {
                        row.reverse();
                    }
                    let mut d = depth.data().to_vec();
                    for row in d.chunks_mut(w) {
                        row.reverse();
                    }
                    DepthMap::new(map.width, map.height, d).unwrap()
                } else {
                    depth
                };
                let m = analyse_view(&map, &depth);
                assert_eq!(
                    occluded(&m, 2),
                    vec![1],
                    "band of {band_id}, mirrored {mirrored}"
                );
                assert!(occluded(&m, 1).is_empty());
            }
        }
        // Wider than the widest band crossed (400 / 40 = 10 px here): no verdict.
        let (map, depth) = pair(11, 0);
        assert_eq!(max_band_px(400), 10);
        assert!(occluded(&analyse_view(&map, &depth), 2).is_empty());
        // A band through a third mask is no boundary between these two.
        let (map, depth) = pair(3, 7);
        assert!(occluded(&analyse_view(&map, &depth), 2).is_empty());
    }

    /// A near mask above a far one, `band` rows without depth between them.
    fn stacked(band: usize) -> (InstanceMap, DepthMap) {
        two_masks((400, 200), band, 0, |_, v| v)
    }

    /// By default a band across the rows is crossed as far as one along them; with
    /// `max_band_across_rows_px` only that far, while a band along a row keeps its reach.
    #[test]
    fn a_band_across_the_rows_is_crossed_only_as_far_as_the_option_says() {
        let narrow = OcclusionOptions {
            max_band_across_rows_px: 6,
        };
        let (map, depth) = stacked(8);
        assert_eq!(occluded(&analyse_view(&map, &depth), 2), vec![1]);
        assert!(occluded(&analyse_view_with(&map, &depth, &narrow), 2).is_empty());
        let (map, depth) = stacked(5);
        assert_eq!(
            occluded(&analyse_view_with(&map, &depth, &narrow), 2),
            vec![1]
        );
        let (map, depth) = pair(8, 0);
        assert_eq!(
            occluded(&analyse_view_with(&map, &depth, &narrow), 2),
            vec![1]
        );
    }
}
