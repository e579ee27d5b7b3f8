//! # deocc-eval
//!
//! How well deocc works, measured on held-out data with baselines beside every figure.
//! - [`amodal`]: 2-D amodal completion (mask mIoU per step count, per occlusion level, on held-out
//!   shapes; cross-view gain; hidden-part depth error; completions per second).
//! - [`masks`]: mask utilities shared by the baselines (IoU, convex hull).

pub mod amodal;
pub mod masks;
pub mod perception;
pub mod reconstruction;
