//! GL-DoT: a linear diffusion transformer for amodal completion.
//!
//! Structure (SANA's linear DiT, see DESIGN.md): the noisy target (RGB, mask, relative depth) is
//! concatenated with the conditioning image (crop RGB, visible mask, visible depth) and patchified
//! into tokens; each block does
//! `x += gate_msa * linear_attn(modulate(LN(x)))`, `x += cross_attn(x, cond)`,
//! `x += gate_mlp * mix_ffn(modulate(LN(x)))` with adaLN-single timestep modulation (one shared
//! `t_block` plus a per-block `scale_shift_table`); the final layer is zero-initialised.
//! Conditioning tokens come from a small ViT encoder `phi` trained jointly; across views they mix
//! as `(1 - rho) phi(I_v) + rho mean_j phi(I_j)`.
//!
//! Tensors are channels-last: images (B, H, W, C), tokens (B, N, D).

use candle_core::{Device, Result, Tensor};
use candle_nn::{Init, VarBuilder};

use crate::config::{AttentionKind, GlDotConfig};
use crate::ops::{
    bias_add, cross_attention, depthwise_conv3x3, gelu, layer_norm, layer_norm_modulate, linear,
    linear_attention_qkv, silu, silu_gate, softmax_attention,
};

const LN_EPS: f64 = 1e-6;
const ATTN_EPS: f64 = 1e-6;

/// (B, H, W, C) -> (B, (H/p)(W/p), p*p*C)
pub fn patchify(x: &Tensor, p: usize) -> Result<Tensor> {
    let (b, h, w, c) = x.dims4()?;
    x.reshape((b, h / p, p, w / p, p, c))?
        .permute((0, 1, 3, 2, 4, 5))?
        .reshape((b, (h / p) * (w / p), p * p * c))
}

/// (B, g*g, p*p*C) -> (B, g*p, g*p, C)
pub fn unpatchify(x: &Tensor, p: usize, c: usize) -> Result<Tensor> {
    let (b, n, _) = x.dims3()?;
    let g = (n as f64).sqrt() as usize;
    x.reshape((b, g, g, p, p, c))?
        .permute((0, 1, 3, 2, 4, 5))?
        .reshape((b, g * p, g * p, c))
}

/// Fixed 2-D sine-cosine position embedding (g*g, dim).
pub fn sincos_2d(g: usize, dim: usize, device: &Device) -> Result<Tensor> {
    let quarter = dim / 4;
    let mut data = vec![0f32; g * g * dim];
    for y in 0..g {
        for x in 0..g {
            let row = &mut data[(y * g + x) * dim..][..dim];
            for k in 0..quarter {
                let omega = 1.0 / 10000f32.powf(k as f32 / quarter as f32);
                row[k] = (x as f32 * omega).sin();
                row[quarter + k] = (x as f32 * omega).cos();
                row[2 * quarter + k] = (y as f32 * omega).sin();
                row[3 * quarter + k] = (y as f32 * omega).cos();
            }
        }
    }
    Tensor::from_vec(data, (g * g, dim), device)
}

/// Sinusoidal embedding of timesteps t in [0, 1] (scaled to [0, 1000] as in DiT/SANA): (B, dim).
pub fn timestep_embedding(t: &Tensor, dim: usize) -> Result<Tensor> {
    let half = dim / 2;
    let freqs: Vec<f32> = (0..half)
        .map(|i| (-(10000f32.ln()) * i as f32 / half as f32).exp())
        .collect();
    let freqs = Tensor::from_vec(freqs, (1, half), t.device())?;
    let args = (t.unsqueeze(1)? * 1000.0)?.broadcast_mul(&freqs)?;
    Tensor::cat(&[args.cos()?, args.sin()?], 1)
}

/// A linear layer (`weight` (out, in), `bias` (out), the names candle_nn uses) whose input is
/// flattened to rows so the product is one matrix multiplication, fused with the bias
/// ([`linear`]).
struct Linear {
    weight: Tensor,
    bias: Tensor,
}

impl Linear {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let (inner, out) = (dims[dims.len() - 1], self.weight.dim(0)?);
        let rows = x.elem_count() / inner.max(1);
        let y = linear(&x.reshape((rows, inner))?, &self.weight, &self.bias)?;
        let mut out_dims = dims;
        *out_dims
            .last_mut()
            .expect("a linear layer's input has a last dimension") = out;
        y.reshape(out_dims)
    }
}

fn linear_init(i: usize, o: usize, vb: VarBuilder, std: f64) -> Result<Linear> {
    let weight = vb.get_with_hints(
        (o, i),
        "weight",
        Init::Randn {
            mean: 0.0,
            stdev: std,
        },
    )?;
    let bias = vb.get_with_hints(o, "bias", Init::Const(0.0))?;
    Ok(Linear { weight, bias })
}

fn xavier(i: usize, o: usize, vb: VarBuilder) -> Result<Linear> {
    linear_init(i, o, vb, (2.0 / (i + o) as f64).sqrt())
}

fn split_heads(x: &Tensor, heads: usize) -> Result<Tensor> {
    let (b, n, d) = x.dims3()?;
    x.reshape((b, n, heads, d / heads))?
        .transpose(1, 2)?
        .contiguous()
}

fn merge_heads(x: &Tensor) -> Result<Tensor> {
    let (b, h, n, d) = x.dims4()?;
    x.transpose(1, 2)?.reshape((b, n, h * d))
}

struct SelfAttention {
    qkv: Linear,
    proj: Linear,
    heads: usize,
    kind: AttentionKind,
}

impl SelfAttention {
    fn new(cfg: &GlDotConfig, kind: AttentionKind, vb: VarBuilder) -> Result<Self> {
        let d = cfg.width;
        Ok(Self {
            qkv: xavier(d, 3 * d, vb.pp("qkv"))?,
            proj: xavier(d, d, vb.pp("proj"))?,
            heads: cfg.heads(),
            kind,
        })
    }
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let qkv = self.qkv.forward(x)?;
        let out = match self.kind {
            AttentionKind::Linear => linear_attention_qkv(&qkv, self.heads, ATTN_EPS)?,
            AttentionKind::Softmax => {
                let d = x.dim(2)?;
                let q = split_heads(&qkv.narrow(2, 0, d)?, self.heads)?;
                let k = split_heads(&qkv.narrow(2, d, d)?, self.heads)?;
                let v = split_heads(&qkv.narrow(2, 2 * d, d)?, self.heads)?;
                merge_heads(&softmax_attention(&q, &k, &v)?)?
            }
        };
        self.proj.forward(&out)
    }
}

struct CrossAttention {
    q: Linear,
    kv: Linear,
    proj: Linear,
    heads: usize,
}

impl CrossAttention {
    fn new(cfg: &GlDotConfig, vb: VarBuilder) -> Result<Self> {
        let d = cfg.width;
        Ok(Self {
            q: xavier(d, d, vb.pp("q"))?,
            kv: xavier(d, 2 * d, vb.pp("kv"))?,
            proj: xavier(d, d, vb.pp("proj"))?,
            heads: cfg.heads(),
        })
    }
    fn forward(&self, x: &Tensor, cond: &Tensor) -> Result<Tensor> {
        let q = self.q.forward(x)?;
        let kv = self.kv.forward(cond)?;
        self.proj.forward(&cross_attention(&q, &kv, self.heads)?)
    }
}

/// SANA's GLUMBConv: 1x1 conv to 2h + SiLU, 3x3 depthwise conv, gate, 1x1 conv back.
struct MixFfn {
    inverted: Linear,
    dw_weight: Tensor,
    dw_bias: Tensor,
    point: Linear,
    hidden: usize,
    grid: usize,
}

impl MixFfn {
    fn new(cfg: &GlDotConfig, vb: VarBuilder) -> Result<Self> {
        let (d, h) = (cfg.width, cfg.mlp_hidden());
        Ok(Self {
            inverted: xavier(d, 2 * h, vb.pp("inverted"))?,
            dw_weight: vb.get_with_hints(
                (3, 3, 2 * h),
                "depthwise.weight",
                Init::Randn {
                    mean: 0.0,
                    stdev: (1.0f64 / 9.0).sqrt(),
                },
            )?,
            dw_bias: vb.get_with_hints(2 * h, "depthwise.bias", Init::Const(0.0))?,
            point: xavier(h, d, vb.pp("point"))?,
            hidden: h,
            grid: cfg.grid(),
        })
    }
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, n, _) = x.dims3()?;
        let y = silu(&self.inverted.forward(x)?)?;
        let y = y.reshape((b, self.grid, self.grid, 2 * self.hidden))?;
        let y = bias_add(&depthwise_conv3x3(&y, &self.dw_weight)?, &self.dw_bias)?;
        let y = y.reshape((b, n, 2 * self.hidden))?;
        self.point.forward(&silu_gate(&y)?)
    }
}

struct Block {
    attn: SelfAttention,
    cross: CrossAttention,
    ffn: MixFfn,
    scale_shift_table: Tensor, // (6, D)
}

impl Block {
    fn new(cfg: &GlDotConfig, vb: VarBuilder) -> Result<Self> {
        let d = cfg.width;
        Ok(Self {
            attn: SelfAttention::new(cfg, cfg.attention, vb.pp("attn"))?,
            cross: CrossAttention::new(cfg, vb.pp("cross_attn"))?,
            ffn: MixFfn::new(cfg, vb.pp("mlp"))?,
            scale_shift_table: vb.get_with_hints(
                (6, d),
                "scale_shift_table",
                Init::Randn {
                    mean: 0.0,
                    stdev: 1.0 / (d as f64).sqrt(),
                },
            )?,
        })
    }

    /// `t_mod`: (B, 6, D) from the shared t_block.
    fn forward(&self, x: &Tensor, cond: &Tensor, t_mod: &Tensor) -> Result<Tensor> {
        let m = t_mod.broadcast_add(&self.scale_shift_table.unsqueeze(0)?)?;
        let part = |i: usize| m.narrow(1, i, 1);
        let (shift_msa, scale_msa, gate_msa) = (part(0)?, part(1)?, part(2)?);
        let (shift_mlp, scale_mlp, gate_mlp) = (part(3)?, part(4)?, part(5)?);
        let h = layer_norm_modulate(x, &shift_msa, &scale_msa, LN_EPS)?;
        let x = (x + self.attn.forward(&h)?.broadcast_mul(&gate_msa)?)?;
        let x = (&x + self.cross.forward(&x, cond)?)?;
        let h = layer_norm_modulate(&x, &shift_mlp, &scale_mlp, LN_EPS)?;
        &x + self.ffn.forward(&h)?.broadcast_mul(&gate_mlp)?
    }
}

/// A plain pre-norm ViT block (softmax attention, GELU MLP) for the condition encoder.
struct EncoderBlock {
    ln1_w: Tensor,
    ln2_w: Tensor,
    attn: SelfAttention,
    fc1: Linear,
    fc2: Linear,
}

impl EncoderBlock {
    fn new(cfg: &GlDotConfig, vb: VarBuilder) -> Result<Self> {
        let d = cfg.width;
        Ok(Self {
            ln1_w: vb.get_with_hints(d, "norm1.weight", Init::Const(1.0))?,
            ln2_w: vb.get_with_hints(d, "norm2.weight", Init::Const(1.0))?,
            attn: SelfAttention::new(cfg, AttentionKind::Softmax, vb.pp("attn"))?,
            fc1: xavier(d, 4 * d, vb.pp("fc1"))?,
            fc2: xavier(4 * d, d, vb.pp("fc2"))?,
        })
    }
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let h = layer_norm(x, LN_EPS)?.broadcast_mul(&self.ln1_w)?;
        let x = (x + self.attn.forward(&h)?)?;
        let h = layer_norm(&x, LN_EPS)?.broadcast_mul(&self.ln2_w)?;
        &x + self.fc2.forward(&gelu(&self.fc1.forward(&h)?)?)?
    }
}

/// phi: the conditioning image (B, H, W, cond_channels) -> tokens (B, M, D).
pub struct ConditionEncoder {
    embed: Linear,
    pos: Tensor,
    blocks: Vec<EncoderBlock>,
    patch: usize,
}

impl ConditionEncoder {
    fn new(cfg: &GlDotConfig, vb: VarBuilder) -> Result<Self> {
        let p = cfg.cond_patch;
        Ok(Self {
            embed: xavier(p * p * cfg.cond_channels, cfg.width, vb.pp("embed"))?,
            pos: sincos_2d(cfg.cond_grid(), cfg.width, vb.device())?,
            blocks: (0..cfg.cond_depth)
                .map(|i| EncoderBlock::new(cfg, vb.pp(format!("blocks.{i}"))))
                .collect::<Result<_>>()?,
            patch: p,
        })
    }
    pub fn forward(&self, cond_image: &Tensor) -> Result<Tensor> {
        let mut x = self
            .embed
            .forward(&patchify(cond_image, self.patch)?)?
            .broadcast_add(&self.pos)?;
        for b in &self.blocks {
            x = b.forward(&x)?;
        }
        layer_norm(&x, LN_EPS)
    }
}

/// The whole model.
pub struct GlDot {
    pub config: GlDotConfig,
    x_embed: Linear,
    pos: Tensor,
    t_fc1: Linear,
    t_fc2: Linear,
    t_block: Linear,
    blocks: Vec<Block>,
    final_table: Tensor, // (2, D)
    final_linear: Linear,
    pub encoder: ConditionEncoder,
}

impl GlDot {
    pub fn new(config: &GlDotConfig, vb: VarBuilder) -> Result<Self> {
        config.validate().map_err(candle_core::Error::msg)?;
        let (d, p) = (config.width, config.patch);
        let in_ch = config.target_channels + config.cond_channels;
        Ok(Self {
            x_embed: xavier(p * p * in_ch, d, vb.pp("x_embedder"))?,
            pos: sincos_2d(config.grid(), d, vb.device())?,
            t_fc1: linear_init(256, d, vb.pp("t_embedder.fc1"), 0.02)?,
            t_fc2: linear_init(d, d, vb.pp("t_embedder.fc2"), 0.02)?,
            t_block: linear_init(d, 6 * d, vb.pp("t_block"), 0.02)?,
            blocks: (0..config.depth)
                .map(|i| Block::new(config, vb.pp(format!("blocks.{i}"))))
                .collect::<Result<_>>()?,
            final_table: vb.get_with_hints(
                (2, d),
                "final_layer.scale_shift_table",
                Init::Randn {
                    mean: 0.0,
                    stdev: 1.0 / (d as f64).sqrt(),
                },
            )?,
            final_linear: linear_init(
                d,
                p * p * config.out_channels(),
                vb.pp("final_layer.linear"),
                0.0,
            )?,
            encoder: ConditionEncoder::new(config, vb.pp("cond_encoder"))?,
            config: config.clone(),
        })
    }

    /// The first `cond_channels` channels of a condition image: data carries every channel we
    /// know of, and a model trained before a channel was added reads the ones it knows.
    fn own_channels(&self, cond_image: &Tensor) -> Result<Tensor> {
        let c = cond_image.dim(3)?;
        if c == self.config.cond_channels {
            Ok(cond_image.clone())
        } else if c > self.config.cond_channels {
            cond_image.narrow(3, 0, self.config.cond_channels)
        } else {
            candle_core::bail!(
                "condition has {c} channels, the model needs {}",
                self.config.cond_channels
            )
        }
    }

    /// Condition tokens of a batch of conditioning images.
    pub fn encode(&self, cond_image: &Tensor) -> Result<Tensor> {
        self.encoder.forward(&self.own_channels(cond_image)?)
    }

    /// Predicted velocity for noisy targets `x_t` (B, R, R, target_channels) at times `t` (B,),
    /// given the conditioning image (B, R, R, cond_channels) and condition tokens (B, M, D):
    /// (B, R, R, out_channels), the velocity first, then (with `mask_head`) the mask head's raw
    /// output (the logit less the prior's +-[`crate::encode::PRIOR_LOGIT`]).
    pub fn forward(
        &self,
        x_t: &Tensor,
        t: &Tensor,
        cond_image: &Tensor,
        cond_tokens: &Tensor,
    ) -> Result<Tensor> {
        let cfg = &self.config;
        let x = Tensor::cat(&[x_t, &self.own_channels(cond_image)?], 3)?;
        let mut x = self
            .x_embed
            .forward(&patchify(&x, cfg.patch)?)?
            .broadcast_add(&self.pos)?;
        let t_emb = self
            .t_fc2
            .forward(&silu(&self.t_fc1.forward(&timestep_embedding(t, 256)?)?)?)?; // (B, D)
        let b = t_emb.dim(0)?;
        let t_mod = self
            .t_block
            .forward(&silu(&t_emb)?)?
            .reshape((b, 6, cfg.width))?;
        for block in &self.blocks {
            x = block.forward(&x, cond_tokens, &t_mod)?;
        }
        let m = self
            .final_table
            .unsqueeze(0)?
            .broadcast_add(&t_emb.unsqueeze(1)?)?; // (B, 2, D)
        let x = layer_norm_modulate(&x, &m.narrow(1, 0, 1)?, &m.narrow(1, 1, 1)?, LN_EPS)?;
        unpatchify(
            &self.final_linear.forward(&x)?,
            cfg.patch,
            cfg.out_channels(),
        )
    }
}

/// Mixes a view's condition tokens with the mean of its other views': `(1 - rho) own + rho others`.
/// `rho` (B,) per sample; where a sample has no other view pass its own tokens as `others`.
pub fn mix_views(own: &Tensor, others_mean: &Tensor, rho: &Tensor) -> Result<Tensor> {
    let rho = rho.reshape((rho.dim(0)?, 1, 1))?;
    own.broadcast_mul(&(rho.neg()? + 1.0)?)?
        .broadcast_add(&others_mean.broadcast_mul(&rho)?)
}

/// Number of parameters of a var map.
pub fn parameter_count(varmap: &candle_nn::VarMap) -> usize {
    varmap.all_vars().iter().map(|v| v.elem_count()).sum()
}
