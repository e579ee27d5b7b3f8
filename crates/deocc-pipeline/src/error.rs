//! The pipeline's error: bad input names the file or field it is about.

use std::path::PathBuf;

use thiserror::Error;

#[derive(Debug, Error)]
pub enum PipelineError {
    #[error("{}: {msg}", path.display())]
    Input { path: PathBuf, msg: String },
    /// An option out of range, naming it.
    #[error("option {field}: {msg}")]
    Option { field: &'static str, msg: String },
    /// The caller's [`crate::Observer`] stopped the run (a cancelled or timed-out request).
    #[error("cancelled before stage {stage}")]
    Cancelled { stage: &'static str },
    #[error(transparent)]
    Io(#[from] deocc_io::IoError),
    #[error(transparent)]
    Geometry(#[from] deocc_geometry::GeometryError),
    #[error(transparent)]
    Completion(#[from] deocc_completion::CompletionError),
}

impl PipelineError {
    pub fn input(path: impl Into<PathBuf>, msg: impl Into<String>) -> Self {
        Self::Input {
            path: path.into(),
            msg: msg.into(),
        }
    }
}
