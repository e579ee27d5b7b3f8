//! GL-DoT configurations as named presets.

use serde::{Deserialize, Serialize};

/// Self-attention flavour of the DiT blocks. `Linear` is SANA's ReLU linear attention (the model);
/// `Softmax` exists to show the cost contrast at higher resolutions.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AttentionKind {
    Linear,
    Softmax,
}

/// The amodal mask the residual model starts from (its output with a zero residual), carried
/// in condition channel 6: [`deocc_completion::priors`].
pub use deocc_completion::MaskPrior;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GlDotConfig {
    /// Crop side in pixels.
    pub resolution: usize,
    /// Patch side of the denoiser's tokens.
    pub patch: usize,
    /// Channels of the target: RGB (3), amodal mask (1), relative depth of the near side (1) and
    /// of the far side (1).
    pub target_channels: usize,
    /// Channels of the conditioning image: crop RGB (3), visible mask (1), visible depth (1).
    pub cond_channels: usize,
    pub width: usize,
    pub depth: usize,
    pub head_dim: usize,
    /// Mix-FFN hidden width = mlp_ratio * width.
    pub mlp_ratio: f64,
    pub attention: AttentionKind,
    /// Patch side of the condition encoder's tokens.
    pub cond_patch: usize,
    pub cond_depth: usize,
    /// The denoiser generates the residual over the visible prior (the crop's visible pixels on
    /// white, the visible mask, the visible depth; see [`crate::encode::residual_prior`]) instead of
    /// the whole target. The unoccluded part of an object is then zero to generate, and the model
    /// spends its capacity on the hidden part. Older weights were trained without it.
    #[serde(default)]
    pub residual: bool,
    /// Which mask the residual is added to (RGB and depth priors are always the visible ones).
    #[serde(default)]
    pub mask_prior: MaskPrior,
}

impl GlDotConfig {
    /// For tests: a few thousand parameters' worth of everything.
    pub fn tiny() -> Self {
        Self {
            resolution: 16,
            patch: 4,
            target_channels: 6,
            cond_channels: 7,
            width: 32,
            depth: 2,
            head_dim: 16,
            mlp_ratio: 2.5,
            attention: AttentionKind::Linear,
            cond_patch: 8,
            cond_depth: 1,
            residual: true,
            mask_prior: MaskPrior::EllipseOrBoxInFront,
        }
    }

    /// The shipped CPU model: 64x64 crops, 256 tokens of width 128, 6 blocks.
    pub fn small() -> Self {
        Self {
            resolution: 64,
            patch: 4,
            target_channels: 6,
            cond_channels: 7,
            width: 128,
            depth: 6,
            head_dim: 32,
            mlp_ratio: 2.5,
            attention: AttentionKind::Linear,
            cond_patch: 8,
            cond_depth: 2,
            residual: true,
            mask_prior: MaskPrior::EllipseOrBoxInFront,
        }
    }

    /// Shaped like the reference SANA-600M (width 1152, 28 blocks, head dim 32) for a GPU, on
    /// 128x128 pixel crops with patch 2.
    pub fn large() -> Self {
        Self {
            resolution: 128,
            patch: 2,
            target_channels: 6,
            cond_channels: 7,
            width: 1152,
            depth: 28,
            head_dim: 32,
            mlp_ratio: 2.5,
            attention: AttentionKind::Linear,
            cond_patch: 8,
            cond_depth: 4,
            residual: true,
            mask_prior: MaskPrior::EllipseOrBoxInFront,
        }
    }

    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "tiny" => Some(Self::tiny()),
            "small" => Some(Self::small()),
            "large" => Some(Self::large()),
            _ => None,
        }
    }

    pub fn heads(&self) -> usize {
        self.width / self.head_dim
    }
    pub fn grid(&self) -> usize {
        self.resolution / self.patch
    }
    pub fn tokens(&self) -> usize {
        self.grid() * self.grid()
    }
    pub fn cond_grid(&self) -> usize {
        self.resolution / self.cond_patch
    }
    pub fn mlp_hidden(&self) -> usize {
        (self.mlp_ratio * self.width as f64).round() as usize
    }

    /// Checks the shape arithmetic; every constructor path calls it.
    pub fn validate(&self) -> Result<(), String> {
        if self.resolution % self.patch != 0 || self.resolution % self.cond_patch != 0 {
            return Err(format!(
                "resolution {} must be a multiple of patch {} and cond_patch {}",
                self.resolution, self.patch, self.cond_patch
            ));
        }
        if self.head_dim == 0 || self.width % self.head_dim != 0 {
            return Err(format!(
                "width {} must be a multiple of head_dim {}",
                self.width, self.head_dim
            ));
        }
        if self.depth == 0 || self.target_channels == 0 {
            return Err("depth and target_channels must be positive".into());
        }
        if self.mask_prior != MaskPrior::Visible && self.cond_channels < 7 {
            return Err(format!(
                "mask_prior {:?} reads condition channel 6, but cond_channels is {}",
                self.mask_prior, self.cond_channels
            ));
        }
        Ok(())
    }
}
