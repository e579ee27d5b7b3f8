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

/// What the residual model's colour and depth start from (its output with a zero residual).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ResidualBase {
    /// The visible pixels' colour on white and the visible depth for both depth channels: the
    /// base of every model up to runs/gldot-small-v10, hence the default of stored configs.
    #[default]
    Visible,
    /// The rules completer's answer ([`deocc_completion::rules`]): the nearest visible colour,
    /// the plane through the visible near side, the symmetric far side, inside the prior mask.
    /// Carried as condition channels 7-11, so the model sees where it starts from; a zero
    /// residual is the rules baseline.
    Rules,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
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
    /// Which mask the residual is added to.
    #[serde(default)]
    pub mask_prior: MaskPrior,
    /// What colour and depth the residual is added to.
    #[serde(default)]
    pub base: ResidualBase,
    /// One more output channel: a per-pixel logit that the pixel belongs to the object, added
    /// to +-[`crate::encode::PRIOR_LOGIT`] on the prior's pixels (a zero head is the prior),
    /// trained as a classification (BCE + Dice over the pixels where the object can be hidden)
    /// from pure noise at t = 1 and read at the sampler's first step. The flow's mask channel is
    /// then not used.
    #[serde(default)]
    pub mask_head: bool,
    /// Five more output channels after the mask head: the colour (3), near-side and far-side
    /// residuals over the base, read like the mask head at the first step (t = 1) and trained
    /// with an L1 loss on the object's pixels: an estimate of the median completion, which
    /// the error figures (mean absolute colour and depth error) reward, where one flow sample
    /// carries the noise the velocity fails to reproduce (runs/gldot-small-v12: colour 19.1 against
    /// 14.5 for its own base on 600 val pairs; 20.9 read at one step). The flow still trains
    /// beside it and is sampled when `inference_reads_mean` is off.
    #[serde(default)]
    pub mean_head: bool,
    /// Two more output channels after the mean head: the expected absolute error of its near-side
    /// and far-side depth, as `exp(channel + `[`ERROR_LOG_OFFSET`]`)` in relative depth (crop
    /// widths), trained with a Laplace likelihood against the mean head's own error (the mean
    /// held fixed, so the head learns how far off the mean is, not to move it). The pipeline
    /// turns it into metres with the depth fit's scale and leaves out points expected further
    /// off than its limit (`completers.gldot.max_expected_error_m`).
    #[serde(default)]
    pub error_head: bool,
}

/// Channels of the mean head: R, G, B, near side, far side (the target's channels 0-2, 4, 5).
pub const MEAN_CHANNELS: usize = 5;

/// Channels of the error head: near side, far side.
pub const ERROR_CHANNELS: usize = 2;

/// The error head's zero: `exp(ERROR_LOG_OFFSET)` = 0.05 crop widths, about the mean head's
/// typical error, so a grown head starts near the right scale (a zero-initialised layer moves
/// its output slowly).
pub const ERROR_LOG_OFFSET: f32 = -3.0;

impl GlDotConfig {
    /// For tests: a few thousand parameters' worth of everything.
    pub fn tiny() -> Self {
        Self {
            resolution: 16,
            patch: 4,
            target_channels: 6,
            cond_channels: 12,
            width: 32,
            depth: 2,
            head_dim: 16,
            mlp_ratio: 2.5,
            attention: AttentionKind::Linear,
            cond_patch: 8,
            cond_depth: 1,
            residual: true,
            mask_prior: MaskPrior::EllipseOrBoxInFront,
            base: ResidualBase::Rules,
            mask_head: true,
            mean_head: false,
            error_head: false,
        }
    }

    /// The CPU model: 64x64 crops, 256 tokens of width 128, 6 blocks, the rules base and the mask
    /// head (runs/gldot-small-v10, shipped before, has the visible base and no head).
    pub fn small() -> Self {
        Self {
            resolution: 64,
            patch: 4,
            target_channels: 6,
            cond_channels: 12,
            width: 128,
            depth: 6,
            head_dim: 32,
            mlp_ratio: 2.5,
            attention: AttentionKind::Linear,
            cond_patch: 8,
            cond_depth: 2,
            residual: true,
            mask_prior: MaskPrior::EllipseOrBoxInFront,
            base: ResidualBase::Rules,
            mask_head: true,
            mean_head: false,
            error_head: false,
        }
    }

    /// Shaped like the reference SANA-600M (width 1152, 28 blocks, head dim 32) for a GPU, on
    /// 128x128 pixel crops with patch 2.
    pub fn large() -> Self {
        Self {
            resolution: 128,
            patch: 2,
            target_channels: 6,
            cond_channels: 12,
            width: 1152,
            depth: 28,
            head_dim: 32,
            mlp_ratio: 2.5,
            attention: AttentionKind::Linear,
            cond_patch: 8,
            cond_depth: 4,
            residual: true,
            mask_prior: MaskPrior::EllipseOrBoxInFront,
            base: ResidualBase::Rules,
            mask_head: true,
            mean_head: false,
            error_head: false,
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
    /// Output channels of the denoiser: the velocity of every target channel, the mask logit,
    /// then the mean head's [`MEAN_CHANNELS`], then the error head's [`ERROR_CHANNELS`].
    pub fn out_channels(&self) -> usize {
        self.target_channels
            + self.mask_head as usize
            + MEAN_CHANNELS * self.mean_head as usize
            + ERROR_CHANNELS * self.error_head as usize
    }

    pub fn mlp_hidden(&self) -> usize {
        (self.mlp_ratio * self.width as f64).round() as usize
    }

    /// Checks the shape arithmetic; every constructor path calls it.
    pub fn validate(&self) -> Result<(), String> {
        if self.patch == 0 || self.cond_patch == 0 || self.resolution == 0 || self.width == 0 {
            return Err(format!(
                "resolution {}, patch {}, cond_patch {} and width {} must be positive",
                self.resolution, self.patch, self.cond_patch, self.width
            ));
        }
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
        if self.base == ResidualBase::Rules && (self.cond_channels < 12 || !self.residual) {
            return Err(format!(
                "base rules reads condition channels 7-11 of a residual model, but cond_channels is \
                 {} (residual {})",
                self.cond_channels, self.residual
            ));
        }
        if self.mean_head && !(self.mask_head && self.residual) {
            return Err(
                "mean_head needs mask_head and residual (it is read beside the mask head, as a residual over the base)"
                    .into(),
            );
        }
        if self.error_head && !self.mean_head {
            return Err("error_head needs mean_head (it estimates the mean head's error)".into());
        }
        if self.mask_head && (self.mask_prior == MaskPrior::Visible || self.target_channels < 6) {
            return Err(
                "mask_head needs a geometric mask_prior (condition channel 6) and 6 target channels"
                    .into(),
            );
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
