//! The depth-source seam: where a frame's depth comes from when the sensor did not measure it.
//! It lives beside the frame type, below the pipeline, so that a learned source (the model
//! crate's Depth Anything) implements it without depending on the pipeline; the pipeline's depth
//! stage (`deocc_pipeline::depth`) fits an estimate to the measured pixels and fills the holes.

use deocc_geometry::DepthMap;

use crate::scene::Frame;

/// A depth source's answer for one frame.
#[derive(Debug, Clone)]
pub enum DepthEstimate {
    /// Metric depth (metres, 0 = no estimate), at an unknown scale and shift: fitted to the
    /// measured pixels.
    Metric(DepthMap),
    /// Metric depth made from the frame's own measurements (already at their scale: no fit).
    SensorScale(DepthMap),
    /// Relative inverse depth (larger = nearer; 0 or less = no estimate), at an unknown scale and
    /// shift, row-major, the frame's size.
    Disparity(Vec<f32>),
}

/// Why a depth source could not answer (the pipeline names the frame and the source).
#[derive(Debug, Clone, thiserror::Error)]
#[error("{0}")]
pub struct DepthSourceError(pub String);

/// Where a frame's depth comes from. `estimate` returns `None` to keep the sensor's depth as it
/// is. Not `Send`: candle-transformers' networks are not, and the stage runs on the caller's
/// thread.
pub trait DepthSource {
    /// A short name for reports (`sensor`, `interpolated`, `depth-anything-v2-small`).
    fn name(&self) -> &str;
    fn estimate(&self, frame: &Frame) -> Result<Option<DepthEstimate>, DepthSourceError>;
}
