//! Stage: occlusion. Per view, two instance masks that touch, the farther one (by the median depth step
//! across their shared boundary) is occluded by the nearer one. Also records truncation by the
//! image border and missing depth along an instance's boundary.

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

/// Occlusion analysis of one view.
pub fn analyse_view(instances: &InstanceMap, depth: &DepthMap) -> Vec<MaskOcclusion> {
    let (w, h) = (instances.width as usize, instances.height as usize);
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
