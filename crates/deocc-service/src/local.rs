//! Completing a decoded request in this process: what the server's workers run, and what the
//! ROS 2 bridge runs when it has no server to call.

use deocc_completion::CompleterChain;
use deocc_pipeline::segment::ConvexitySegmenter;
use deocc_pipeline::{Observer, PipelineError, PipelineOptions, SceneInput};

use crate::cloud2;
use crate::proto::CompleteResult;

/// Runs the pipeline on `scene` and packs the result as the service answers it: the cloud in
/// the PointCloud2 layout and the report as JSON. `observer` sees each stage, then `encode`;
/// it may stop the run at any of them.
pub fn complete(
    scene: SceneInput,
    opts: &PipelineOptions,
    segment: bool,
    chain: &CompleterChain,
    observer: &dyn Observer,
) -> Result<CompleteResult, PipelineError> {
    let out = deocc_pipeline::run_in_memory(
        scene,
        chain,
        opts,
        &ConvexitySegmenter::default(),
        segment,
        observer,
    )?;
    if !observer.stage("encode", 0.99) {
        return Err(PipelineError::Cancelled { stage: "encode" });
    }
    Ok(CompleteResult {
        cloud: Some(cloud2::encode(&out.completed)),
        report_json: serde_json::to_string(&out.report).unwrap_or_default(),
        points_observed: out.report.points_observed as u64,
        points_generated: out.report.points_generated as u64,
    })
}
