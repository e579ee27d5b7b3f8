//! # deocc-io
//!
//! File formats of deocc. Every function takes a path and every error names it
//! ([`IoError`] carries the path and what was wrong). Writers are atomic: a file is written to a
//! temporary name and renamed into place, so a failure never leaves a half-written file.
//!
//! - [`ply`]: point clouds and meshes (ASCII, binary little/big-endian) with colour, normals,
//!   instance id and generated flag;
//! - [`images`]: 16-bit depth PNG in millimetres, u16 instance maps, masks, RGB;
//! - [`cameras`]: intrinsics, lens distortion, depth units, a separate depth camera and
//!   `world_from_camera` poses as JSON;
//! - [`lens`]: turns what a real camera gives into the pinhole frame the stages use;
//! - [`npy`]: float32 / uint16 depth as NumPy arrays;
//! - [`mesh`]: OBJ / STL / PLY meshes;
//! - [`scene`]: the scene folder (frames, cameras, metadata), deocc's input;
//! - [`tum`]: the TUM RGB-D sequence layout, read into the same scene;
//! - [`pairs`]: GL-DoT training-pair shards (safetensors).

pub mod atomic;
pub mod cameras;
pub mod depth_source;
pub mod error;
pub mod images;
pub mod lens;
pub mod mesh;
pub mod npy;
pub mod pairs;
pub mod ply;
pub mod rawlog;
pub mod scene;
pub mod tum;
pub mod weights;

pub use error::{IoError, IoErrorKind, Result};
pub use ply::{read_point_cloud, write_point_cloud, PlyEncoding};
