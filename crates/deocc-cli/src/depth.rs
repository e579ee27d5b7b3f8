//! Which depth source a command uses: the sensor's depth as it is (default), `--fill-depth`
//! (the sensor's holes interpolated from their measured neighbours, no weights), or
//! `--depth-model FILE` (Depth Anything V2 from the user's weights, put at the sensor's scale).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use deocc_pipeline::depth::{DepthSource, InterpolatedDepth, SensorDepth};

#[derive(Args, Clone, Debug, Default)]
pub struct DepthArgs {
    /// Fill the pixels the depth sensor did not measure before the run, from their measured
    /// neighbours along the row and the column (linear within a surface, the farther side across
    /// an edge; holes up to 32 px). Measured pixels never change; filled ones count as observed.
    #[arg(long)]
    pub fill_depth: bool,
    /// Fill them instead from Depth Anything V2 (small, base or large, read from the file):
    /// a safetensors file in the original checkpoint's layout (`pretrained.*`, `depth_head.*`).
    /// Its relative depth is fitted to each frame's measured pixels (at least 0.5% of them;
    /// sparse depth is enough); a frame the model disagrees with is left as it is.
    #[arg(long, value_name = "FILE")]
    pub depth_model: Option<PathBuf>,
}

impl DepthArgs {
    /// The depth source the flags name.
    pub fn source(&self) -> Result<Box<dyn DepthSource>> {
        Ok(match (&self.depth_model, self.fill_depth) {
            (Some(path), _) => Box::new(
                deocc_model::depth_anything::DepthAnything::load(path, &candle_core::Device::Cpu)
                    .with_context(|| "--depth-model")?,
            ),
            (None, true) => Box::new(InterpolatedDepth::default()),
            (None, false) => Box::new(SensorDepth),
        })
    }
}
