//! Stage: view selection. An instance is completed in the view that shows most of it, and in up to
//! `max_views_per_instance - 1` more that look at it from at least `view_delta_deg` away from
//! every view already chosen (their completions condition each other).

use std::collections::BTreeMap;

use deocc_io::scene::SceneInput;
use nalgebra::Vector3;

use crate::stats::InstanceStats;
use crate::PipelineOptions;

/// The views to complete instance `id` in, from `candidates` (view, visible pixels).
pub fn select_views(
    scene: &SceneInput,
    stats: &[BTreeMap<u16, InstanceStats>],
    id: u16,
    candidates: &[(usize, usize)],
    opts: &PipelineOptions,
) -> Vec<usize> {
    let mut sorted = candidates.to_vec();
    sorted.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    let dir = |v: usize| {
        let c = stats[v].get(&id)?.centroid?;
        Some((c - scene.frames[v].camera.center()).normalize())
    };
    let mut chosen: Vec<(usize, Vector3<f32>)> = Vec::new();
    for (v, _) in sorted {
        let Some(d) = dir(v) else { continue };
        let far_enough = chosen
            .iter()
            .all(|(_, e)| e.dot(&d).clamp(-1.0, 1.0).acos().to_degrees() >= opts.view_delta_deg);
        if chosen.is_empty() || far_enough {
            chosen.push((v, d));
        }
        if chosen.len() >= opts.max_views_per_instance {
            break;
        }
    }
    chosen.into_iter().map(|(v, _)| v).collect()
}

/// The views to complete each instance in, from its candidate views (view, visible pixels).
pub fn select_all(
    scene: &SceneInput,
    stats: &[BTreeMap<u16, InstanceStats>],
    candidates: &BTreeMap<u16, Vec<(usize, usize)>>,
    opts: &PipelineOptions,
) -> BTreeMap<u16, Vec<usize>> {
    candidates
        .iter()
        .map(|(&id, c)| (id, select_views(scene, stats, id, c, opts)))
        .collect()
}
