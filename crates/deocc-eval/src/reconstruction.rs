//! 3-D figures of a reconstruction against a benchmark scene's dense ground truth.

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

/// One row of the results table: a method's figures averaged over scenes.
#[derive(Debug, Clone, Serialize)]
pub struct TableRow {
    pub method: String,
    pub scenes: usize,
    pub accuracy_mean: f64,
    pub completeness_mean: f64,
    pub chamfer: f64,
    pub fscore: f64,
    pub completeness_hidden_mean: f64,
    pub recall_hidden: f64,
}

pub fn average_row(method: &str, figs: &[MethodFigures]) -> TableRow {
    let n = figs.len().max(1) as f64;
    let avg = |f: &dyn Fn(&MethodFigures) -> f64| figs.iter().map(f).sum::<f64>() / n;
    TableRow {
        method: method.into(),
        scenes: figs.len(),
        accuracy_mean: avg(&|m| m.whole_scene.accuracy_mean),
        completeness_mean: avg(&|m| m.whole_scene.completeness_mean),
        chamfer: avg(&|m| m.whole_scene.chamfer),
        fscore: avg(&|m| m.whole_scene.fscore),
        completeness_hidden_mean: avg(&|m| m.hidden_region.completeness_mean),
        recall_hidden: avg(&|m| m.hidden_region.recall),
    }
}
