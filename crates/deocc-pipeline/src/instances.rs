//! Stage: instances. Every frame needs an instance map whose ids are consistent across views.
//! Maps given with the input are kept; frames without one are segmented ([`Segmenter`]) and their
//! masks matched across views by 3-D centroids ([`crate::matching`]). When some frames carry maps
//! and others do not, the segmented instances get ids above every given one, so no id means two
//! objects.

use std::collections::{BTreeMap, BTreeSet};

use deocc_io::images::InstanceMap;
use deocc_io::scene::SceneInput;
use nalgebra::Point3;

use crate::matching::{match_masks, MaskCentroid, Threshold};
use crate::segment::Segmenter;
use crate::PipelineError;

/// Segments that span more than this (metres, horizontally) are room structure (floor, walls).
pub const STRUCTURE_EXTENT_M: f32 = 2.0;

/// Gives every frame without an instance map one (see the module docs) and marks segments wider
/// than [`STRUCTURE_EXTENT_M`] as room structure. Returns the number of 3-D instances made by
/// segmentation (0 if every frame already had its map).
pub fn ensure_instances(
    scene: &mut SceneInput,
    segmenter: &dyn Segmenter,
) -> Result<usize, PipelineError> {
    if scene.frames.iter().all(|f| f.instances.is_some()) {
        return Ok(0);
    }
    // Segmented ids start above the largest given one.
    let given_max = scene
        .frames
        .iter()
        .filter_map(|f| f.instances.as_ref())
        .flat_map(|m| m.ids.iter().copied())
        .max()
        .unwrap_or(0);
    let todo: Vec<usize> = (0..scene.frames.len())
        .filter(|&v| scene.frames[v].instances.is_none())
        .collect();
    let mut local: BTreeMap<usize, InstanceMap> = BTreeMap::new();
    for &v in &todo {
        let map = segmenter.segment(&scene.frames[v])?;
        let f = &scene.frames[v];
        if (map.width, map.height) != (f.depth.width(), f.depth.height()) {
            return Err(PipelineError::input(
                &scene.dir,
                format!(
                    "the segmenter returned a {}x{} map for frame {} of {}x{}",
                    map.width,
                    map.height,
                    f.name,
                    f.depth.width(),
                    f.depth.height()
                ),
            ));
        }
        local.insert(v, map);
    }
    let mut masks = Vec::new();
    let mut extents = Vec::new();
    for (&v, map) in &local {
        let f = &scene.frames[v];
        let w = map.width as usize;
        let mut per: BTreeMap<u16, Vec<Point3<f32>>> = BTreeMap::new();
        for (i, &id) in map.ids.iter().enumerate() {
            if id != 0 {
                per.entry(id).or_default().push(f.camera.unproject_pixel(
                    (i % w) as u32,
                    (i / w) as u32,
                    f.depth.data()[i],
                ));
            }
        }
        for (id, pts) in per {
            let Some(c) = deocc_geometry::cloud::centroid(&pts) else {
                continue;
            };
            let (lo, hi) = pts
                .iter()
                .fold((pts[0], pts[0]), |(lo, hi), p| (lo.inf(p), hi.sup(p)));
            extents.push((hi.x - lo.x).max(hi.y - lo.y));
            masks.push(MaskCentroid {
                view: v,
                local_id: id,
                centroid: c,
                points: pts.len(),
            });
        }
    }
    let matched = match_masks(&masks, Threshold::Adaptive);
    if given_max as usize + matched.groups > u16::MAX as usize {
        return Err(PipelineError::input(
            &scene.dir,
            format!(
                "{} segmented instances do not fit above the given ids (up to {given_max}) in u16",
                matched.groups
            ),
        ));
    }
    let mut global: BTreeMap<(usize, u16), u16> = BTreeMap::new();
    let mut structure = BTreeSet::new();
    for (k, m) in masks.iter().enumerate() {
        let id = given_max + (matched.group[k] + 1) as u16;
        global.insert((m.view, m.local_id), id);
        if extents[k] > STRUCTURE_EXTENT_M {
            structure.insert(id);
        }
    }
    for (v, map) in local {
        let ids = map
            .ids
            .iter()
            .map(|&l| {
                if l == 0 {
                    0
                } else {
                    global.get(&(v, l)).copied().unwrap_or(0)
                }
            })
            .collect();
        scene.frames[v].instances = Some(InstanceMap {
            width: map.width,
            height: map.height,
            ids,
        });
    }
    scene.structure_ids.extend(structure);
    Ok(matched.groups)
}
