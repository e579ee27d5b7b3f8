//! # deocc-geometry
//!
//! The geometry core of deocc: pinhole cameras in the OpenCV convention, depth maps and their
//! back-projection, point clouds with provenance, exact nearest neighbours (kiddo), the
//! reconstruction metrics and alignment of the field's evaluation protocol (Umeyama + ICP), PCA
//! normals, voxel downsampling and fusion, a robust Huber line fit, and exact point-to-triangle
//! distances for scoring against a true surface.
//!
//! No ML dependency lives here: this crate is what a robotics user can take alone.
//!
//! Conventions: positions are `f32` metres; poses are named by their frames
//! (`world_from_camera`); alignment and statistics accumulate in `f64`.

pub mod align;
pub mod camera;
pub mod cell_grid;
pub mod cloud;
pub mod depth;
pub mod distortion;
pub mod error;
pub mod knn;
pub mod mask2d;
pub mod metrics;
pub mod noise;
pub mod normals;
pub mod reproject;
pub mod robust;
pub mod rotation;
pub mod surface;
pub mod voxel;

pub use camera::{Camera, Intrinsics};
pub use cell_grid::CellGrid;
pub use cloud::{PointCloud, Provenance};
pub use depth::DepthMap;
pub use error::{GeometryError, Result};
pub use knn::KdIndex;
