//! Mask IoU and the convex-hull baseline live in the geometry core (the completion model's
//! geometric prior uses the same hull); re-exported here for the evaluation's callers.

pub use deocc_geometry::mask2d::{convex_hull_mask, iou};
