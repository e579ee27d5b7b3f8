use thiserror::Error;

/// Everything that can go wrong in the geometry core. Each variant says which input was bad and why,
/// so that a caller at the edge (a loader, the CLI) can add the file name and report it as is.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum GeometryError {
    #[error("invalid intrinsics: {0}")]
    InvalidIntrinsics(String),
    #[error("{what} is empty")]
    Empty { what: &'static str },
    #[error("{what} has a non-finite value (NaN or infinity) at index {index}")]
    NonFinite { what: &'static str, index: usize },
    #[error("size mismatch: {what} (expected {expected}, got {got})")]
    SizeMismatch {
        what: &'static str,
        expected: usize,
        got: usize,
    },
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    #[error("degenerate input: {0}")]
    Degenerate(String),
}

pub type Result<T, E = GeometryError> = std::result::Result<T, E>;
