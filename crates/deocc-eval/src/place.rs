//! `deocc eval place`: placement maps of place-v1 (or place-v2) from each cloud, against the ground truth.
//!
//! Every scene is rendered and run through the pipeline once per completer (ground-truth
//! instance maps). On the table's plane (its true height and extent: the support surface is
//! given, so the rows differ only in what they know of the space over it), maps for an object of
//! [`FOOTPRINT_M`] and [`HEIGHT_M`] are built from: the observed cloud with unseen space free
//! (`observed_optimistic`) and occupied (`observed_conservative`), each completer's cloud, and
//! the ground truth (dense samples of the objects and the table), and the ground truth of the table
//! and the objects the view sees ([`SEEN_TRUTH`]: the bound of any completer, since an object
//! wholly hidden behind the clutter leaves nothing to complete). Scored over the workspace (the
//! table top's cells): IoU of the placeable cells, the false-placeable rate (predicted placeable
//! cells whose dilated footprint meets true geometry) and placement success (the chosen cell is
//! placeable in the ground truth).
//!
//! Every figure is also given over the part of the workspace **behind the clutter**: the table-top
//! cells whose centre the robot's view does not see (the paper's task is placing behind clutter).
//! On the whole table top the cells in plain view are scored right by every map and dilute the
//! difference; behind the clutter is where the maps differ. There the placement is chosen among
//! the cells behind the clutter only (`success_behind`).
//!
//! Why a map misses truly placeable cells is split in two (`missed_blocked`,
//! `missed_unsupported`, shares of the truly placeable cells): something the map holds lies under
//! the dilated footprint (a completion too big, a stray point), or too little of the footprint
//! has support (the table's fill does not reach there).

use deocc_completion::CompleterChain;
use deocc_robot::picture::{
    captioned, comparison_image, comparison_legend, side_by_side, RgbImage,
};
use deocc_robot::place::{
    build_map, build_map_seen_from, build_map_with_errors, choose_placement, compare_maps,
    PlaceMap, PlaceOptions, SupportPlane, UnseenSpace,
};
use nalgebra::Point3;
use serde::Serialize;

use crate::stats::{compare, estimate, share_of_bound, Comparison, Estimate, ShareOfBound};
use crate::EvalError;

/// The row of the true surfaces of the table and of the objects the view sees (at least one
/// visible pixel): the bound of any completer, which cannot know of an object wholly hidden.
pub const SEEN_TRUTH: &str = "ground_truth_seen_objects";

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
    /// The same over the cells behind the clutter (the module's header).
    pub iou_behind: f64,
    pub false_placeable_rate_behind: f64,
    pub success_behind: f64,
    pub chosen_behind: bool,
    /// Share of the truly placeable cells the map misses because something it holds is in the
    /// way, and because it lacks support there (NaN without truly placeable cells).
    pub missed_blocked: f64,
    pub missed_unsupported: f64,
    /// The same behind the clutter.
    pub missed_blocked_behind: f64,
    pub missed_unsupported_behind: f64,
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
    /// The share of the ground truth's IoU gain over the optimistic map this map recovers
    /// (`mean(iou - optimistic) / mean(ground truth - optimistic)`, bootstrap over scenes).
    pub share_of_ground_truth_gain: ShareOfBound,
    /// Over the cells behind the clutter (the module's header).
    pub iou_behind: Estimate,
    pub false_placeable_rate_behind: Estimate,
    pub success_behind: Estimate,
    pub no_placement_behind: usize,
    pub iou_behind_vs_optimistic: Comparison,
    /// Why truly placeable cells are missed (shares of them; the module's header).
    pub missed_blocked: Estimate,
    pub missed_unsupported: Estimate,
    pub missed_blocked_behind: Estimate,
    pub missed_unsupported_behind: Estimate,
}

#[derive(Debug, Clone, Serialize)]
pub struct PlaceReport {
    pub benchmark: String,
    pub scenes: usize,
    pub options: PlaceOptions,
    pub mean_hidden_free_fraction: f64,
    /// Mean share of the workspace's cells that lie behind the clutter.
    pub mean_behind_fraction: f64,
    pub rows: Vec<PlaceRow>,
    pub per_scene: Vec<(String, Vec<ScenePlace>)>,
}

fn score(
    map: &PlaceMap,
    truth: &PlaceMap,
    workspace: &[bool],
    behind: &[bool],
    robot: &Point3<f32>,
    opts: &PlaceOptions,
    seed: u64,
) -> Result<ScenePlace, EvalError> {
    let err = |e: deocc_robot::RobotError| EvalError::Data(e.to_string());
    let s = compare_maps(map, truth, workspace).map_err(err)?;
    let b = compare_maps(map, truth, behind).map_err(err)?;
    let success = |chosen: Option<deocc_robot::place::Placement>| {
        chosen
            .as_ref()
            .map(|c| truth.placeable[c.cell] as u8 as f64)
            .unwrap_or(f64::NAN)
    };
    let chosen = choose_placement(map, robot, opts);
    // The same map with its placeable cells outside the clutter's shadow taken away.
    let mut only_behind = map.clone();
    for (p, &w) in only_behind.placeable.iter_mut().zip(behind) {
        *p &= w;
    }
    let chosen_behind = choose_placement(&only_behind, robot, opts);
    let share = |n: usize, of: usize| {
        if of == 0 {
            f64::NAN
        } else {
            n as f64 / of as f64
        }
    };
    Ok(ScenePlace {
        seed,
        iou: s.iou,
        false_placeable_rate: s.false_placeable_rate,
        placeable_cells: s.placeable_cells,
        true_placeable_cells: s.true_placeable_cells,
        chosen: chosen.is_some(),
        success: success(chosen),
        iou_behind: b.iou,
        false_placeable_rate_behind: b.false_placeable_rate,
        chosen_behind: chosen_behind.is_some(),
        success_behind: success(chosen_behind),
        missed_blocked: share(s.missed_blocked, s.true_placeable_cells),
        missed_unsupported: share(s.missed_unsupported, s.true_placeable_cells),
        missed_blocked_behind: share(b.missed_blocked, b.true_placeable_cells),
        missed_unsupported_behind: share(b.missed_unsupported, b.true_placeable_cells),
    })
}

/// The workspace's cells whose centre, on the table top, `view` does not see: behind the clutter
/// (or under an object, where no map may place anyway).
fn behind_clutter(
    workspace: &[bool],
    truth: &PlaceMap,
    table_id: u16,
    view: &deocc_synth::dataset::RenderedView,
) -> Vec<bool> {
    workspace
        .iter()
        .enumerate()
        .map(|(i, &w)| {
            w && !deocc_synth::ground_truth::visible_in(
                &truth.cell_center(i),
                table_id,
                &view.camera,
                &view.frame,
            )
        })
        .collect()
}

/// Where [`place_benchmark`] hands each scene's picture, with the scene's seed.
pub type PictureSink<'a> = &'a mut dyn FnMut(u64, RgbImage) -> Result<(), EvalError>;

/// `deocc eval place` on the first `scenes` of `preset` (place-v1 or place-v2) with each named
/// chain. With `picture = Some((m, f))`, the first `m` scenes' maps against the ground truth (one
/// panel a map, captioned with its name, in the rows' order without the ground truth:
/// [`deocc_robot::picture::comparison_image`], then the legend) are handed to `f` with the
/// scene's seed; the other scenes are not drawn. `planner` gives the placer's settings; the
/// object's footprint and height are the benchmark's.
pub fn place_benchmark(
    preset: &deocc_synth::dataset::Preset,
    chains: &[crate::ChainRow],
    opts: &deocc_pipeline::PipelineOptions,
    planner: &PlaceOptions,
    scenes: usize,
    mut picture: Option<(usize, PictureSink<'_>)>,
    tick: &mut dyn FnMut(),
) -> Result<PlaceReport, EvalError> {
    if preset.config.kind != deocc_synth::scene::SceneKind::Place {
        return Err(EvalError::Data(format!(
            "{} is not a placing benchmark (place-v1, place-v2)",
            preset.name
        )));
    }
    let n = scenes.min(preset.seeds.len());
    let popts = PlaceOptions {
        footprint: FOOTPRINT_M,
        height: HEIGHT_M,
        ..planner.clone()
    };
    let mut names = vec![
        "observed_optimistic".to_string(),
        "observed_conservative".to_string(),
    ];
    names.extend(chains.iter().map(|c| c.name.clone()));
    names.push(SEEN_TRUTH.into());
    names.push("ground_truth".into());
    let mut per: Vec<Vec<ScenePlace>> = vec![Vec::new(); names.len()];
    let mut hidden = Vec::new();
    let mut behind_share = Vec::new();
    for (i, &seed) in preset.seeds[..n].iter().enumerate() {
        let draw = picture.as_ref().is_some_and(|(m, _)| i < *m);
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
        let behind = behind_clutter(&workspace, &truth, table.instance_id, &rendered.views[0]);
        let cells = workspace.iter().filter(|&&w| w).count().max(1);
        behind_share.push(behind.iter().filter(|&&b| b).count() as f64 / cells as f64);
        let robot = Point3::from(
            rendered.scene.cameras[0]
                .world_from_camera
                .translation
                .vector,
        );
        let input = rendered.scene_input();
        let empty = CompleterChain::default();
        let out = crate::run_as_product(&input, &empty, opts)?;
        let mut rows = Vec::new();
        let mut panels = Vec::new();
        let mut panel = |m: &PlaceMap, name: &str| {
            if draw {
                panels.push(captioned(&comparison_image(m, &truth, &workspace, 3), name));
            }
        };
        for (unseen, name) in [
            (UnseenSpace::Free, "optimistic"),
            (UnseenSpace::Occupied, "conservative"),
        ] {
            // The sight lines from the one camera tell empty space past the table's edges.
            let m = build_map_seen_from(
                &out.observed.positions,
                &plane,
                &popts,
                unseen,
                Some(&robot),
            )
            .map_err(err)?;
            panel(&m, name);
            rows.push(score(
                &m, &truth, &workspace, &behind, &robot, &popts, seed,
            )?);
        }
        for row in chains {
            let (name, chain) = (&row.name, &row.chain);
            let out = crate::run_as_product(&input, chain, row.options_or(opts))?;
            let m = build_map_with_errors(
                &out.completed.positions,
                out.completed.expected_error.as_deref(),
                &plane,
                &popts,
                UnseenSpace::AsPoints,
                // One view: its camera's sight lines give the hidden side's envelope.
                Some(&robot),
            )
            .map_err(err)?;
            panel(&m, name);
            rows.push(score(
                &m, &truth, &workspace, &behind, &robot, &popts, seed,
            )?);
        }
        if let (true, Some((_, f))) = (draw, picture.as_mut()) {
            panels.push(comparison_legend());
            f(seed, side_by_side(&panels, 6))?;
        }
        // What a perfect completer of the objects the view sees could reach: the true surfaces of
        // the table and of every object with a visible pixel (an object wholly hidden behind the
        // clutter is beyond any completer of a single view).
        let seen: std::collections::HashSet<u32> = rendered.views[0]
            .visibility
            .iter()
            .filter(|v| v.visible_px > 0)
            .map(|v| v.instance_id as u32)
            .chain([table.instance_id as u32])
            .collect();
        let seen_points: Vec<Point3<f32>> = gt
            .positions
            .iter()
            .zip(gt.instance.as_deref().unwrap_or_default())
            .filter(|(_, i)| seen.contains(i))
            .map(|(p, _)| *p)
            .collect();
        let m = build_map(&seen_points, &plane, &popts, UnseenSpace::AsPoints).map_err(err)?;
        rows.push(score(
            &m, &truth, &workspace, &behind, &robot, &popts, seed,
        )?);
        rows.push(score(
            &truth, &truth, &workspace, &behind, &robot, &popts, seed,
        )?);
        for (k, r) in rows.into_iter().enumerate() {
            per[k].push(r);
        }
        tick();
    }
    // The ground-truth map is the last row.
    let truth_iou: Vec<f64> = per
        .last()
        .map(|rows| rows.iter().map(|s| s.iou).collect())
        .unwrap_or_default();
    let rows = names
        .iter()
        .enumerate()
        .map(|(k, name)| {
            let col = |f: fn(&ScenePlace) -> f64| per[k].iter().map(f).collect::<Vec<f64>>();
            let iou = col(|s| s.iou);
            let base = per[0].iter().map(|s| s.iou).collect::<Vec<f64>>();
            let iou_behind = col(|s| s.iou_behind);
            let base_behind = per[0].iter().map(|s| s.iou_behind).collect::<Vec<f64>>();
            let clusters: Vec<u32> = (0..iou.len() as u32).collect();
            PlaceRow {
                map: name.clone(),
                iou: estimate(&iou, 1000, 21),
                false_placeable_rate: estimate(&col(|s| s.false_placeable_rate), 1000, 22),
                success: estimate(&col(|s| s.success), 1000, 23),
                no_placement: per[k].iter().filter(|s| !s.chosen).count(),
                iou_vs_optimistic: compare(&iou, &base, &clusters, 1000, 24),
                share_of_ground_truth_gain: share_of_bound(&iou, &base, &truth_iou, 1000, 33),
                iou_behind: estimate(&iou_behind, 1000, 25),
                false_placeable_rate_behind: estimate(
                    &col(|s| s.false_placeable_rate_behind),
                    1000,
                    26,
                ),
                success_behind: estimate(&col(|s| s.success_behind), 1000, 27),
                no_placement_behind: per[k].iter().filter(|s| !s.chosen_behind).count(),
                iou_behind_vs_optimistic: compare(&iou_behind, &base_behind, &clusters, 1000, 28),
                missed_blocked: estimate(&col(|s| s.missed_blocked), 1000, 29),
                missed_unsupported: estimate(&col(|s| s.missed_unsupported), 1000, 30),
                missed_blocked_behind: estimate(&col(|s| s.missed_blocked_behind), 1000, 31),
                missed_unsupported_behind: estimate(
                    &col(|s| s.missed_unsupported_behind),
                    1000,
                    32,
                ),
            }
        })
        .collect();
    Ok(PlaceReport {
        benchmark: preset.name.clone(),
        scenes: n,
        options: popts,
        mean_hidden_free_fraction: crate::stats::mean(hidden),
        mean_behind_fraction: crate::stats::mean(behind_share),
        rows,
        per_scene: names.into_iter().zip(per).collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a dense place-v2 table: the ground truth scores 1 everywhere; some but not all of the
    /// table top lies behind the clutter; there the conservative map (unseen space occupied)
    /// finds next to nothing placeable while it does find room in plain view, and the optimistic
    /// map (unseen space free) is wrong more often than on the whole table.
    #[test]
    fn behind_the_clutter_is_the_unseen_part_of_the_table() {
        let preset = deocc_synth::dataset::place_v2();
        let chains = vec![crate::ChainRow::new(
            "rules",
            CompleterChain::new(vec![Box::new(
                deocc_completion::rules::RulesCompleter::default(),
            )]),
        )];
        let opts = deocc_pipeline::PipelineOptions::default();
        let mut pictures = Vec::new();
        let mut keep = |seed: u64, img: RgbImage| {
            pictures.push((seed, img));
            Ok(())
        };
        let r = place_benchmark(
            &preset,
            &chains,
            &opts,
            &PlaceOptions::default(),
            3,
            Some((2, &mut keep)),
            &mut || {},
        )
        .unwrap();
        // One picture a scene for the first two scenes only, a panel a map but the ground
        // truth's.
        assert_eq!(pictures.len(), 2);
        assert_eq!(pictures[0].0, preset.seeds[0]);
        assert!(pictures[0].1.width() > 3 * pictures[0].1.height() / 2);
        assert!(
            r.mean_behind_fraction > 0.2 && r.mean_behind_fraction < 0.9,
            "{}",
            r.mean_behind_fraction
        );
        let row = |name: &str| r.rows.iter().find(|x| x.map == name).unwrap();
        let truth = row("ground_truth");
        assert_eq!(truth.iou.mean, 1.0);
        assert_eq!(truth.iou_behind.mean, 1.0);
        assert_eq!(truth.success_behind.mean, 1.0);
        let conservative = row("observed_conservative");
        assert!(
            conservative.iou_behind.mean < 0.1,
            "{:?}",
            conservative.iou_behind
        );
        assert!(conservative.iou.mean > 0.15, "{:?}", conservative.iou);
        // The conservative map misses what it cannot see because it holds it taken; the truth
        // misses nothing.
        assert!(
            conservative.missed_blocked_behind.mean > 0.9,
            "{:?}",
            conservative.missed_blocked_behind
        );
        assert_eq!(
            truth.missed_blocked.mean + truth.missed_unsupported.mean,
            0.0
        );
        let optimistic = row("observed_optimistic");
        assert!(
            optimistic.false_placeable_rate_behind.mean > optimistic.false_placeable_rate.mean,
            "{:?} vs {:?}",
            optimistic.false_placeable_rate_behind,
            optimistic.false_placeable_rate
        );
        assert!(row("rules").iou.mean > conservative.iou.mean);
        // The truth of the seen objects lies between the rules' guess and the whole truth.
        let seen = row(SEEN_TRUTH);
        assert!(
            seen.iou.mean <= 1.0 && seen.iou.mean >= row("rules").iou.mean,
            "{:?}",
            seen.iou
        );
        assert!(seen.false_placeable_rate.mean <= row("rules").false_placeable_rate.mean);
    }
}
