//! # deocc-eval
//!
//! How well deocc works, measured on held-out data with baselines beside every figure.
//! - [`amodal`]: 2-D amodal completion (mask mIoU per step count, per occlusion level, on held-out
//!   shapes; cross-view gain; hidden-part depth error; completions per second).
//! - [`masks`]: mask utilities shared by the baselines (IoU, convex hull);
//! - [`objects`]: per-object 3-D hidden completeness, a row per completer;
//! - [`reconstruction`], [`perception`]: the bench-v1 scene benchmarks;
//! - [`bench`]: speed against peers; [`stats`]: bootstrap intervals, AUC.

pub mod amodal;
pub mod bench;
pub mod grasp;
pub mod masks;
pub mod objects;
pub mod perception;
pub mod place;
pub mod reconstruction;
pub mod scenes;
pub mod stats;

/// What can stop an evaluation.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(transparent)]
    Pipeline(#[from] deocc_pipeline::PipelineError),
    #[error(transparent)]
    Synth(#[from] deocc_synth::SynthError),
    #[error(transparent)]
    Geometry(#[from] deocc_geometry::GeometryError),
    #[error(transparent)]
    Io(#[from] deocc_io::IoError),
    #[error(transparent)]
    Completion(#[from] deocc_completion::CompletionError),
    #[error("model: {0}")]
    Model(String),
    #[error("{0}")]
    Data(String),
}

impl From<candle_core::Error> for EvalError {
    fn from(e: candle_core::Error) -> Self {
        EvalError::Model(e.to_string())
    }
}
