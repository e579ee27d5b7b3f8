//! Cross-view matching: masks of different views that show the same object become one 3-D
//! instance, by their 3-D centroids.
//!
//! The threshold `tau` adapts to the scene: for every mask, the distance to the nearest centroid
//! in each other view is collected. Most of these nearest distances are between two views of the
//! same object (partial views shift a centroid by a fraction of the object's size), a minority are
//! between different objects (a mask with no counterpart in that view). The bulk is summarised
//! robustly and `tau = median + 3 * 1.4826 * MAD` of the nearest distances, clamped to
//! [2 cm, 50 cm]: tight in a cluttered tabletop, looser for large furniture, and blind to the
//! minority of wrong nearest neighbours. Pairs are linked only when mutual nearest neighbours
//! within tau (no chaining through a third object), then grouped by union-find.

use nalgebra::Point3;
use serde::Serialize;

/// One mask of one view with its 3-D centroid.
#[derive(Debug, Clone)]
pub struct MaskCentroid {
    pub view: usize,
    /// The mask's id in its own view.
    pub local_id: u16,
    pub centroid: Point3<f32>,
    pub points: usize,
}

#[derive(Debug, Clone, Copy, Serialize)]
pub enum Threshold {
    Adaptive,
    Fixed(f32),
}

#[derive(Debug, Clone, Serialize)]
pub struct Matching {
    pub tau_m: f32,
    /// Group (3-D instance) of every mask, in the input order.
    pub group: Vec<usize>,
    pub groups: usize,
}

/// The adaptive threshold from nearest inter-view centroid distances.
pub fn adaptive_tau(nearest: &[f32]) -> f32 {
    if nearest.is_empty() {
        return 0.1;
    }
    let mut v = nearest.to_vec();
    v.sort_by(f32::total_cmp);
    let med = v[v.len() / 2];
    let mut dev: Vec<f32> = v.iter().map(|d| (d - med).abs()).collect();
    dev.sort_by(f32::total_cmp);
    let mad = dev[dev.len() / 2];
    (med + 3.0 * 1.4826 * mad).clamp(0.02, 0.5)
}

fn find(parent: &mut [usize], i: usize) -> usize {
    let mut r = i;
    while parent[r] != r {
        r = parent[r];
    }
    let mut i = i;
    while parent[i] != r {
        let next = parent[i];
        parent[i] = r;
        i = next;
    }
    r
}

/// Groups masks across views.
pub fn match_masks(masks: &[MaskCentroid], threshold: Threshold) -> Matching {
    let n = masks.len();
    let views: std::collections::BTreeSet<usize> = masks.iter().map(|m| m.view).collect();
    // nearest[i][view] = (index, distance) of the closest mask of that view.
    let mut nearest: Vec<Vec<(usize, usize, f32)>> = vec![Vec::new(); n];
    let mut all_nearest = Vec::new();
    for i in 0..n {
        for &v in &views {
            if v == masks[i].view {
                continue;
            }
            let best = (0..n)
                .filter(|&j| masks[j].view == v)
                .map(|j| (j, (masks[i].centroid - masks[j].centroid).norm()))
                .min_by(|a, b| a.1.total_cmp(&b.1));
            if let Some((j, d)) = best {
                nearest[i].push((v, j, d));
                all_nearest.push(d);
            }
        }
    }
    let tau = match threshold {
        Threshold::Adaptive => adaptive_tau(&all_nearest),
        Threshold::Fixed(t) => t,
    };
    let mut parent: Vec<usize> = (0..n).collect();
    for i in 0..n {
        for &(_, j, d) in &nearest[i] {
            let mutual = nearest[j]
                .iter()
                .any(|&(v, k, _)| v == masks[i].view && k == i);
            if d < tau && mutual {
                let (a, b) = (find(&mut parent, i), find(&mut parent, j));
                parent[a] = b;
            }
        }
    }
    let mut label = std::collections::BTreeMap::new();
    let group: Vec<usize> = (0..n)
        .map(|i| {
            let r = find(&mut parent, i);
            let next = label.len();
            *label.entry(r).or_insert(next)
        })
        .collect();
    Matching {
        tau_m: tau,
        groups: label.len(),
        group,
    }
}
