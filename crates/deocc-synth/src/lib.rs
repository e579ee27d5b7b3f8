//! # deocc-synth
//!
//! The synthetic occlusion benchmark: procedural indoor scenes with realistic furniture and
//! household objects ([`scene`], [`shapes`]), a z-buffer renderer producing RGB, depth, visible
//! instance maps and per-object amodal masks ([`render`]), dense ground truth of every surface with
//! a "seen by some view" flag ([`ground_truth`]), the on-disk scene layout and the `bench-v1`
//! definition ([`dataset`]), and amodal training pairs for GL-DoT ([`pairs`]).
//!
//! Determinism: a config and a seed give byte-identical files.
//! World frame: metres, z up, the floor at z = 0.

pub mod dataset;
pub mod generate;
pub mod ground_truth;
pub mod mesh;
pub mod pairs;
pub mod render;
pub mod scene;
pub mod sensor;
pub mod sensor_kind;
pub mod shapes;
pub mod sheet;
pub mod tasks;

use thiserror::Error;

#[derive(Debug, Error)]
pub enum SynthError {
    #[error(transparent)]
    Io(#[from] deocc_io::IoError),
    #[error(transparent)]
    Geometry(#[from] deocc_geometry::GeometryError),
    #[error("invalid configuration: {0}")]
    Config(String),
    #[error("{path}: {msg}")]
    Data { path: String, msg: String },
}

pub type Result<T, E = SynthError> = std::result::Result<T, E>;
