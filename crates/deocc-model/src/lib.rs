//! # deocc-model
//!
//! GL-DoT, the generative part of deocc: a small SANA-style linear diffusion transformer that
//! completes an occluded object crop into the whole object (RGB, amodal mask, relative depth),
//! trained with rectified flow and sampled in a few Euler steps.
//!
//! - [`config`]: presets (`tiny` for tests, `small` shipped, `large` shaped like SANA-600M);
//! - [`model`]: the network; [`ops`]: fast CPU building blocks; [`simd`]: their AVX2 dispatch;
//! - [`flow`]: rectified-flow loss, timesteps, the Euler sampler;
//! - [`encode`]: the channel encoding of crops, written once for training and inference;
//! - [`data`]: batches from the training pairs;
//! - [`train`]: the resumable training loop (run directory, AdamW, EMA, checkpoints);
//! - [`export`]: shipping a run's EMA weights in f16;
//! - [`infer`]: loading a trained model and completing crops ([`GlDotCompleter`], one
//!   implementation of the pipeline's `deocc_completion::Completer` seam);
//! - [`depth_anything`]: Depth Anything V2 from a user's weights file, a
//!   `deocc_io::depth_source::DepthSource` (relative depth from RGB, to fill the sensor's holes).

pub mod builtin;
pub mod chain;
pub mod config;
pub mod data;
pub mod depth_anything;
pub mod encode;
pub mod export;
pub mod flow;
pub mod infer;
pub mod init;
pub mod model;
pub mod ops;
pub mod pool;
pub mod simd;
pub mod train;

pub use config::{GlDotConfig, MaskPrior};
pub use infer::GlDotCompleter;
pub use model::GlDot;
