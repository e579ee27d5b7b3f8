//! A run's figures against its scene's ground truth: what `deocc run` reports when the scene
//! folder holds `ground_truth.ply` (a benchmark scene, or a user's own scan of the scene), and the
//! figures the benchmarks average. Completeness and accuracy over the ground truth inside the
//! cameras' frusta, and over the part no input view sees.

use deocc_geometry::camera::Camera;
use deocc_geometry::metrics::{reconstruction_metrics, MetricOptions, ReconstructionMetrics};
use deocc_geometry::{GeometryError, PointCloud};
use serde::Serialize;

/// Ground truth as evaluated: only points inside some view's frustum (the scene the cameras
/// look at; far floor and wall outside every image are no one's task), with the "seen" flags.
pub struct EvalGroundTruth {
    pub cloud: PointCloud,
    pub seen: Vec<bool>,
}

/// Keeps the ground-truth points that project inside at least one camera's image.
pub fn in_frustum(gt: &PointCloud, seen: &[bool], cameras: &[Camera]) -> EvalGroundTruth {
    let keep: Vec<usize> = (0..gt.len())
        .filter(|&i| {
            cameras.iter().any(|c| {
                c.project_world(&gt.positions[i]).is_some_and(|(px, z)| {
                    z > 0.1
                        && px.x >= 0.0
                        && px.y >= 0.0
                        && px.x < c.intrinsics.width() as f32
                        && px.y < c.intrinsics.height() as f32
                })
            })
        })
        .collect();
    EvalGroundTruth {
        cloud: gt.select(&keep),
        seen: keep.iter().map(|&i| seen[i]).collect(),
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct MethodFigures {
    pub whole_scene: ReconstructionMetrics,
    /// Completeness and recall over the ground-truth points no input view sees.
    pub hidden_region: ReconstructionMetrics,
}

pub fn figures(
    prediction: &PointCloud,
    gt: &EvalGroundTruth,
) -> Result<MethodFigures, GeometryError> {
    let opts = MetricOptions::default();
    let hidden: Vec<bool> = gt.seen.iter().map(|s| !s).collect();
    Ok(MethodFigures {
        whole_scene: reconstruction_metrics(
            &prediction.positions,
            None,
            &gt.cloud.positions,
            None,
            None,
            &opts,
        )?,
        hidden_region: reconstruction_metrics(
            &prediction.positions,
            None,
            &gt.cloud.positions,
            None,
            Some(&hidden),
            &opts,
        )?,
    })
}

/// ICP refinement of a prediction onto the ground truth, as the protocol does after its similarity
/// alignment (point-to-point, 0.1 m, at most 30 iterations). Our predictions are already in the
/// ground-truth frame (known poses), so the Umeyama step is the identity.
pub fn align_to_ground_truth(
    prediction: &PointCloud,
    gt: &EvalGroundTruth,
) -> Result<PointCloud, GeometryError> {
    use deocc_geometry::align::{icp, IcpOptions, IcpTarget};
    let target = IcpTarget::new(&gt.cloud.positions, None)?;
    // The transform is estimated on an even subsample (at most 50k points) and applied to all:
    // the same alignment, 20x less work on million-point clouds.
    let stride = (prediction.len() / 50_000).max(1);
    let sample: Vec<_> = prediction
        .positions
        .iter()
        .step_by(stride)
        .copied()
        .collect();
    let r = icp(
        &sample,
        &target,
        &nalgebra::Isometry3::identity(),
        &IcpOptions::default(),
    )?;
    let mut out = prediction.clone();
    out.transform(&r.target_from_source.cast::<f32>());
    Ok(out)
}

/// A run's figures against its scene's ground truth (what `deocc run` reports for benchmark
/// scenes): visible-only against completed, both aligned to the ground truth as the benchmark
/// aligns them ([`align_to_ground_truth`]), so pose-free input is scored fairly.
#[derive(Debug, Clone, Serialize)]
pub struct RunEvaluation {
    pub ground_truth_points_in_frustum: usize,
    pub visible_only: MethodFigures,
    pub with_deocclusion: MethodFigures,
    pub completeness_gain_whole_scene: f64,
    pub completeness_gain_hidden_region: f64,
    pub accuracy_change: f64,
}

/// Relative gain of `after` over `before` for a lower-is-better figure (`1 - after / before`).
pub fn gain(before: f64, after: f64) -> f64 {
    1.0 - after / before
}

/// Reads a ground-truth PLY with its `seen` flags (every point seen when the file has none).
pub fn read_ground_truth(
    path: &std::path::Path,
) -> Result<(PointCloud, Vec<bool>), deocc_io::IoError> {
    let gt = deocc_io::ply::read_ply(path)?;
    let seen: Vec<bool> = match gt.extra("seen") {
        Some(s) => s.iter().map(|&v| v > 0.0).collect(),
        None => vec![true; gt.vertices.len()],
    };
    Ok((gt.vertices, seen))
}

/// [`RunEvaluation`] of an observed and a completed cloud.
pub fn evaluate_run(
    gt: &PointCloud,
    seen: &[bool],
    cameras: &[Camera],
    observed: &PointCloud,
    completed: &PointCloud,
) -> Result<RunEvaluation, GeometryError> {
    let egt = in_frustum(gt, seen, cameras);
    let vis = figures(&align_to_ground_truth(observed, &egt)?, &egt)?;
    let deo = figures(&align_to_ground_truth(completed, &egt)?, &egt)?;
    Ok(RunEvaluation {
        ground_truth_points_in_frustum: egt.cloud.len(),
        completeness_gain_whole_scene: gain(
            vis.whole_scene.completeness_mean,
            deo.whole_scene.completeness_mean,
        ),
        completeness_gain_hidden_region: gain(
            vis.hidden_region.completeness_mean,
            deo.hidden_region.completeness_mean,
        ),
        accuracy_change: deo.whole_scene.accuracy_mean / vis.whole_scene.accuracy_mean - 1.0,
        visible_only: vis,
        with_deocclusion: deo,
    })
}
