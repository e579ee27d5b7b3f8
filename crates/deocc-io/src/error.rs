use std::path::{Path, PathBuf};

use thiserror::Error;

/// An I/O failure, always naming the file it is about.
#[derive(Debug, Error)]
#[error("{}: {kind}", path.display())]
pub struct IoError {
    pub path: PathBuf,
    pub kind: IoErrorKind,
}

#[derive(Debug, Error)]
pub enum IoErrorKind {
    #[error("{0}")]
    Os(#[from] std::io::Error),
    #[error("malformed PLY header: {0}")]
    PlyHeader(String),
    #[error("malformed PLY data: {0}")]
    PlyData(String),
    #[error("image: {0}")]
    Image(String),
    #[error("JSON: {0}")]
    Json(String),
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Geometry(#[from] deocc_geometry::GeometryError),
}

impl IoError {
    pub fn new(path: &Path, kind: impl Into<IoErrorKind>) -> Self {
        Self {
            path: path.to_path_buf(),
            kind: kind.into(),
        }
    }
    pub fn invalid(path: &Path, msg: impl Into<String>) -> Self {
        Self::new(path, IoErrorKind::Invalid(msg.into()))
    }
}

pub type Result<T, E = IoError> = std::result::Result<T, E>;
