//! Which depth source a command uses: the sensor's depth as it is (default), `--fill-depth`
//! (the sensor's holes interpolated from their measured neighbours, no weights), or
//! `--depth-model FILE` (Depth Anything V2 from the user's weights, put at the sensor's scale).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use deocc_model::depth_anything::DepthAnything;
use deocc_pipeline::PipelineOptions;

#[derive(Args, Clone, Debug, Default)]
pub struct DepthArgs {
    /// Fill the pixels the depth sensor did not measure before the run, from their measured
    /// neighbours along the row and the column (linear within a surface, the near surface continued
    /// across an edge; holes up to 8 px between two measured pixels, the option
    /// `fill_depth_max_gap_px`). Measured pixels never change; filled ones count as observed.
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
    /// The learned depth source `--depth-model` names, loaded.
    pub fn model(&self) -> Result<Option<DepthAnything>> {
        self.depth_model
            .as_ref()
            .map(|path| {
                DepthAnything::load(path, &candle_core::Device::Cpu).context("--depth-model")
            })
            .transpose()
    }

    /// `--fill-depth`: the interpolation's gap limit in the options, unless they set one.
    pub fn apply(&self, opts: &mut PipelineOptions) {
        if self.fill_depth && opts.fill_depth_max_gap_px == 0 {
            opts.fill_depth_max_gap_px = deocc_pipeline::depth::DEFAULT_MAX_GAP_PX;
        }
    }
}

/// One line on stderr per frame the depth stage filled (or left, and why).
pub fn print_depth_fill(fills: &[deocc_pipeline::depth::DepthFillReport]) {
    for r in fills {
        match &r.skipped {
            None => eprintln!(
                "frame {}: filled {} unmeasured depth pixels from {} ({} measured)",
                r.frame, r.filled, r.source, r.measured
            ),
            Some(why) => eprintln!("frame {}: depth not filled by {}: {why}", r.frame, r.source),
        }
    }
}
