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
