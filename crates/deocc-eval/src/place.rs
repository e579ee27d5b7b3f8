//! `deocc eval place`: placement maps of place-v1 from each cloud, against the ground truth.
//!
//! Every scene is rendered and run through the pipeline once per completer (ground-truth
//! instance maps). On the table's plane (its true height and extent: the support surface is
//! given, so the rows differ only in what they know of the space over it), maps for an object of
//! [`FOOTPRINT_M`] and [`HEIGHT_M`] are built from: the observed cloud with unseen space free
//! (`observed_optimistic`) and occupied (`observed_conservative`), each completer's cloud, and
//! the ground truth (dense samples of the objects and the table). Scored over the workspace (the
//! table top's cells): IoU of the placeable cells, the false-placeable rate (predicted placeable
//! cells whose dilated footprint meets true geometry) and placement success (the chosen cell is
//! placeable in the ground truth).

use deocc_completion::CompleterChain;
use deocc_robot::place::{
    build_map, choose_placement, compare_maps, PlaceMap, PlaceOptions, SupportPlane, UnseenSpace,
};
use nalgebra::Point3;
use serde::Serialize;

use crate::stats::{compare, estimate, Comparison, Estimate};
use crate::EvalError;

pub const FOOTPRINT_M: [f32; 2] = [0.08, 0.08];
pub const HEIGHT_M: f32 = 0.12;
/// Ground-truth samples per square metre.
pub const GT_DENSITY: f32 = 40_000.0;

#[derive(Debug, Clone, Serialize)]
pub struct ScenePlace {
    pub seed: u64,
    pub iou: f64,
    pub false_placeable_rate: f64,
    pub placeable_cells: usize,
    pub true_placeable_cells: usize,
    /// NaN when the map has no placeable cell.
    pub success: f64,
    pub chosen: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct PlaceRow {
    pub map: String,
    pub iou: Estimate,
    pub false_placeable_rate: Estimate,
    /// Over scenes where the map offers a placement.
    pub success: Estimate,
    /// Scenes where the map offers no placement at all.
    pub no_placement: usize,
    pub iou_vs_optimistic: Comparison,
}

#[derive(Debug, Clone, Serialize)]
pub struct PlaceReport {
    pub benchmark: String,
    pub scenes: usize,
    pub options: PlaceOptions,
    pub mean_hidden_free_fraction: f64,
    pub rows: Vec<PlaceRow>,
    pub per_scene: Vec<(String, Vec<ScenePlace>)>,
}

fn score(
    map: &PlaceMap,
    truth: &PlaceMap,
    workspace: &[bool],
    robot: &Point3<f32>,
    opts: &PlaceOptions,
    seed: u64,
) -> Result<ScenePlace, EvalError> {
    let s = compare_maps(map, truth, workspace).map_err(|e| EvalError::Data(e.to_string()))?;
    let chosen = choose_placement(map, robot, opts);
    Ok(ScenePlace {
        seed,
        iou: s.iou,
        false_placeable_rate: s.false_placeable_rate,
        placeable_cells: s.placeable_cells,
        true_placeable_cells: s.true_placeable_cells,
        success: chosen
            .as_ref()
            .map(|c| truth.placeable[c.cell] as u8 as f64)
            .unwrap_or(f64::NAN),
        chosen: chosen.is_some(),
    })
}

/// `deocc eval place` on the first `scenes` of place-v1 with each named chain.
pub fn place_benchmark(
    chains: &[(String, CompleterChain)],
    opts: &deocc_pipeline::PipelineOptions,
    scenes: usize,
    tick: &mut dyn FnMut(),
) -> Result<PlaceReport, EvalError> {
    let preset = deocc_synth::dataset::place_v1();
    let n = scenes.min(preset.seeds.len());
    let popts = PlaceOptions {
        footprint: FOOTPRINT_M,
        height: HEIGHT_M,
        ..PlaceOptions::default()
    };
    let mut names = vec![
        "observed_optimistic".to_string(),
        "observed_conservative".to_string(),
    ];
    names.extend(chains.iter().map(|(n, _)| n.clone()));
    names.push("ground_truth".into());
    let mut per: Vec<Vec<ScenePlace>> = vec![Vec::new(); names.len()];
    let mut hidden = Vec::new();
    for &seed in &preset.seeds[..n] {
        let rendered = deocc_synth::dataset::render_full_scene(&preset.config, seed)?;
        let table = rendered
            .scene
            .table
            .ok_or_else(|| EvalError::Data(format!("place seed {seed}: no table")))?;
        hidden.push(deocc_synth::tasks::hidden_free_fraction(&rendered.scene) as f64);
        let corners: Vec<(f32, f32)> = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
            .iter()
            .map(|&(sx, sy)| table.to_world(sx * table.size.x / 2.0, sy * table.size.y / 2.0))
            .collect();
        let fold = |f: fn(f32, f32) -> f32, init: f32, pick: fn(&(f32, f32)) -> f32| {
            corners.iter().map(pick).fold(init, f)
        };
        let plane = SupportPlane {
            height: table.size.z,
            bounds: [
                fold(f32::min, f32::MAX, |c| c.0),
                fold(f32::min, f32::MAX, |c| c.1),
                fold(f32::max, f32::MIN, |c| c.0),
                fold(f32::max, f32::MIN, |c| c.1),
            ],
            points: 0,
        };
        let gt = deocc_synth::ground_truth::object_surfaces(&rendered.scene, GT_DENSITY, seed);
        let err = |e: deocc_robot::RobotError| EvalError::Data(e.to_string());
        let truth = build_map(&gt.positions, &plane, &popts, UnseenSpace::AsPoints).map_err(err)?;
        // The workspace: the table top's cells (where the true table surface is).
        let on_table: Vec<Point3<f32>> = gt
            .positions
            .iter()
            .zip(gt.instance.as_deref().unwrap_or_default())
            .filter(|(_, &i)| i == table.instance_id as u32)
            .map(|(p, _)| *p)
            .collect();
        let workspace = build_map(&on_table, &plane, &popts, UnseenSpace::AsPoints)
            .map_err(err)?
            .support;
        let robot = Point3::from(
            rendered.scene.cameras[0]
                .world_from_camera
                .translation
                .vector,
        );
        let input = rendered.scene_input();
        let empty = CompleterChain::default();
        let out = deocc_pipeline::run(&input, &empty, opts, &Vec::new())?;
        let mut rows = Vec::new();
        for unseen in [UnseenSpace::Free, UnseenSpace::Occupied] {
            let m = build_map(&out.observed.positions, &plane, &popts, unseen).map_err(err)?;
            rows.push(score(&m, &truth, &workspace, &robot, &popts, seed)?);
        }
        for (_, chain) in chains {
            let out = deocc_pipeline::run(&input, chain, opts, &Vec::new())?;
            let m = build_map(
                &out.completed.positions,
                &plane,
                &popts,
                UnseenSpace::AsPoints,
            )
            .map_err(err)?;
            rows.push(score(&m, &truth, &workspace, &robot, &popts, seed)?);
        }
        rows.push(score(&truth, &truth, &workspace, &robot, &popts, seed)?);
        for (k, r) in rows.into_iter().enumerate() {
            per[k].push(r);
        }
        tick();
    }
    let rows = names
        .iter()
        .enumerate()
        .map(|(k, name)| {
            let col = |f: fn(&ScenePlace) -> f64| per[k].iter().map(f).collect::<Vec<f64>>();
            let iou = col(|s| s.iou);
            let base = per[0].iter().map(|s| s.iou).collect::<Vec<f64>>();
            let clusters: Vec<u32> = (0..iou.len() as u32).collect();
            PlaceRow {
                map: name.clone(),
                iou: estimate(&iou, 1000, 21),
                false_placeable_rate: estimate(&col(|s| s.false_placeable_rate), 1000, 22),
                success: estimate(&col(|s| s.success), 1000, 23),
                no_placement: per[k].iter().filter(|s| !s.chosen).count(),
                iou_vs_optimistic: compare(&iou, &base, &clusters, 1000, 24),
            }
        })
        .collect();
    Ok(PlaceReport {
        benchmark: preset.name,
        scenes: n,
        options: popts,
        mean_hidden_free_fraction: crate::stats::mean(hidden),
        rows,
        per_scene: names.into_iter().zip(per).collect(),
    })
}
