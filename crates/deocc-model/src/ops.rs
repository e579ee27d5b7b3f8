//! Building blocks with the shapes GL-DoT needs, written so they train fast on a CPU.
//!
//! - [`depthwise_conv3x3`]: a channels-last 3x3 depthwise convolution as a candle `CustomOp2` with a
//!   hand-written backward. candle's grouped `conv2d` runs one convolution per group (thousands of
//!   tiny convolutions per block), and composing it from shifted slices has a slow backward; this op
//!   is one pass over memory in each direction (see ../shared/notes/candle-on-this-cpu.md).
//! - [`layer_norm`]: LayerNorm without affine parameters, composed from ops that have a backward
//!   (candle_nn's fused layer_norm has none).
//! - [`linear_attention`]: SANA's ReLU linear attention, O(N d^2).
//! - [`layer_norm_modulate`]: adaLN's `LayerNorm(x) * (1 + scale) + shift` as one custom op with a
//!   hand-written backward.
//! - [`linear`]: a linear layer as row blocks of single-threaded gemm on candle's pool (forward
//!   and both gradient products), never on gemm's rayon threads.
//! - [`silu`], [`gelu`]: single-pass activations with a hand-written backward on [`fast_exp`].
//!
//! The element-wise kernels (activations, the SiLU gate, the depthwise convolution, softmax rows)
//! run on AVX2 when the CPU has it, with the same results bit for bit ([`crate::simd`]).

use candle_core::{CpuStorage, CustomOp2, CustomOp3, DType, Layout, Result, Shape, Tensor, D};

use crate::simd::simd_dispatch;

/// `y = x * (1 + scale) + shift`, with `shift` and `scale` of shape (B, 1, D) broadcast over tokens.
pub fn modulate(x: &Tensor, shift: &Tensor, scale: &Tensor) -> Result<Tensor> {
    x.broadcast_mul(&(scale + 1.0)?)?.broadcast_add(shift)
}

/// LayerNorm over the last dimension, no affine parameters.
pub fn layer_norm(x: &Tensor, eps: f64) -> Result<Tensor> {
    let mean = x.mean_keepdim(D::Minus1)?;
    let centered = x.broadcast_sub(&mean)?;
    let var = centered.sqr()?.mean_keepdim(D::Minus1)?;
    centered.broadcast_div(&(var + eps)?.sqrt()?)
}

/// ReLU linear attention. `q`, `k`, `v`: (B, heads, N, d). Returns (B, heads, N, d):
/// `out_i = relu(q_i) (sum_j relu(k_j)^T v_j) / (relu(q_i) . sum_j relu(k_j) + eps)`.
///
/// As in SANA, `v` is padded with a column of ones so that the numerator and the normaliser come
/// out of one matmul; everything stays in f32.
pub fn linear_attention(q: &Tensor, k: &Tensor, v: &Tensor, eps: f64) -> Result<Tensor> {
    let q = q.relu()?;
    let k = k.relu()?;
    let (b, h, n, d) = v.dims4()?;
    let ones = Tensor::ones((b, h, n, 1), v.dtype(), v.device())?;
    let v1 = Tensor::cat(&[v, &ones], 3)?; // (B, h, N, d + 1)
    let kv = k.transpose(2, 3)?.contiguous()?.matmul(&v1)?; // (B, h, d, d + 1)
    let out = q.matmul(&kv)?; // (B, h, N, d + 1)
    let num = out.narrow(3, 0, d)?;
    let den = out.narrow(3, d, 1)?;
    num.broadcast_div(&(den + eps)?)
}

/// Softmax attention with the same interface, for the cost-contrast config switch and for
/// cross-attention. `q`: (B, h, N, d), `k`, `v`: (B, h, M, d).
pub fn softmax_attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
    let d = q.dim(3)? as f64;
    let scores = (q.matmul(&k.transpose(2, 3)?.contiguous()?)? / d.sqrt())?;
    candle_nn::ops::softmax(&scores, D::Minus1)?.matmul(v)
}

fn contiguous_f32<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [f32]> {
    let data = s.as_slice::<f32>()?;
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&data[a..b]),
        None => candle_core::bail!("{what} must be contiguous"),
    }
}

/// y[b,i,j,c] = sum_{a,e in 0..3} x[b, i+a-1, j+e-1, c] * w[a, e, c], zero padding.
fn dwconv_forward(x: &[f32], w: &[f32], bsz: usize, h: usize, wd: usize, c: usize) -> Vec<f32> {
    let mut y = vec![0f32; bsz * h * wd * c];
    crate::pool::for_each_chunk_mut(&mut y, wd * c, |row_idx, out_row| {
        dwconv_row(x, w, out_row, row_idx, h, wd, c)
    });
    y
}

simd_dispatch! {
    /// One output row (image `row_idx / h`, row `row_idx % h`) of [`dwconv_forward`].
    fn dwconv_row(x: &[f32], w: &[f32], out_row: &mut [f32], row_idx: usize, h: usize, wd: usize, c: usize)
        = dwconv_row_kernel;
}

#[inline(always)]
fn dwconv_row_kernel(
    x: &[f32],
    w: &[f32],
    out_row: &mut [f32],
    row_idx: usize,
    h: usize,
    wd: usize,
    c: usize,
) {
    let b = row_idx / h;
    for_each_tap(row_idx % h, h, wd, |tap, ii, jj, j| {
        let src = &x[((b * h + ii) * wd + jj) * c..][..c];
        let wk = &w[tap * c..][..c];
        let dst = &mut out_row[j * c..][..c];
        for ((d, s), k) in dst.iter_mut().zip(src).zip(wk) {
            *d += s * k;
        }
    });
}

/// Calls `f(tap, source row, source column, output column)` for every in-bounds tap of a 3x3
/// stencil (tap = 3 * row offset + column offset, zero padding) around output row `i` of an
/// image `h` rows by `w` columns: the walk the convolution and its weight gradient share.
#[inline(always)]
fn for_each_tap(i: usize, h: usize, w: usize, mut f: impl FnMut(usize, usize, usize, usize)) {
    for a in 0..3 {
        let Some(ii) = (i + a).checked_sub(1).filter(|&ii| ii < h) else {
            continue;
        };
        for e in 0..3 {
            for j in 0..w {
                if let Some(jj) = (j + e).checked_sub(1).filter(|&jj| jj < w) {
                    f(a * 3 + e, ii, jj, j);
                }
            }
        }
    }
}

/// Depthwise 3x3 convolution, channels last: x (B, H, W, C), weight (3, 3, C) -> (B, H, W, C).
struct DepthwiseConv3x3;

impl CustomOp2 for DepthwiseConv3x3 {
    fn name(&self) -> &'static str {
        "depthwise-conv3x3-nhwc"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let [b, h, w, c] = l1.dims() else {
            candle_core::bail!("depthwise conv input must be (B, H, W, C)")
        };
        if l2.dims() != [3, 3, *c] {
            candle_core::bail!(
                "depthwise conv weight must be (3, 3, {c}), got {:?}",
                l2.dims()
            );
        }
        let x = contiguous_f32(s1, l1, "depthwise conv input")?;
        let k = contiguous_f32(s2, l2, "depthwise conv weight")?;
        let y = dwconv_forward(x, k, *b, *h, *w, *c);
        Ok((CpuStorage::F32(y), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        // dL/dx is the same convolution of the output gradient with the kernel flipped in space.
        let flipped = {
            let rows: Vec<Tensor> = (0..3)
                .rev()
                .map(|a| w.narrow(0, a, 1))
                .collect::<Result<_>>()?;
            let w = Tensor::cat(&rows, 0)?;
            let cols: Vec<Tensor> = (0..3)
                .rev()
                .map(|e| w.narrow(1, e, 1))
                .collect::<Result<_>>()?;
            Tensor::cat(&cols, 1)?.contiguous()?
        };
        let grad = grad.contiguous()?;
        let gx = grad.apply_op2_no_bwd(&flipped, &DepthwiseConv3x3)?;
        let gw = x
            .contiguous()?
            .apply_op2_no_bwd(&grad, &DepthwiseConv3x3WeightGrad)?;
        Ok((Some(gx), Some(gw)))
    }
}

simd_dispatch! {
    /// One image row's share of the depthwise convolution's weight gradient, into `acc` (3, 3, C).
    fn dwconv_weight_grad_row(x: &[f32], g: &[f32], acc: &mut [f32], row_idx: usize, h: usize, w: usize, c: usize)
        = dwconv_weight_grad_row_kernel;
}

#[inline(always)]
fn dwconv_weight_grad_row_kernel(
    x: &[f32],
    g: &[f32],
    acc: &mut [f32],
    row_idx: usize,
    h: usize,
    w: usize,
    c: usize,
) {
    let bi = row_idx / h;
    let g_row = &g[row_idx * w * c..][..w * c];
    for_each_tap(row_idx % h, h, w, |tap, ii, jj, j| {
        let xs = &x[((bi * h + ii) * w + jj) * c..][..c];
        let gs = &g_row[j * c..][..c];
        let dst = &mut acc[tap * c..][..c];
        for ((d, xv), gv) in dst.iter_mut().zip(xs).zip(gs) {
            *d += xv * gv;
        }
    });
}

/// dL/dw[a, e, c] = sum_{b,i,j} grad[b,i,j,c] * x[b, i+a-1, j+e-1, c].
struct DepthwiseConv3x3WeightGrad;

impl CustomOp2 for DepthwiseConv3x3WeightGrad {
    fn name(&self) -> &'static str {
        "depthwise-conv3x3-nhwc-weight-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let [b, h, w, c] = *l1.dims() else {
            candle_core::bail!("expected (B, H, W, C)")
        };
        let x = contiguous_f32(s1, l1, "input")?;
        let g = contiguous_f32(s2, l2, "output gradient")?;
        // One partial (3, 3, C) sum per image row, reduced at the end: parallel and deterministic.
        let partial: Vec<Vec<f32>> = crate::pool::map(b * h, |row_idx| {
            let mut acc = vec![0f32; 9 * c];
            dwconv_weight_grad_row(x, g, &mut acc, row_idx, h, w, c);
            acc
        });
        let mut out = vec![0f32; 9 * c];
        for p in &partial {
            for (o, v) in out.iter_mut().zip(p) {
                *o += v;
            }
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&[3, 3, c])))
    }
}

/// Depthwise 3x3 convolution of channels-last `x` (B, H, W, C) with `weight` (3, 3, C), zero
/// padding, stride 1. f32 on CPU through the custom op; any other device falls back to candle's
/// grouped conv2d.
pub fn depthwise_conv3x3(x: &Tensor, weight: &Tensor) -> Result<Tensor> {
    if x.device().is_cpu() && x.dtype() == DType::F32 {
        x.contiguous()?
            .apply_op2(&weight.contiguous()?, DepthwiseConv3x3)
    } else {
        let c = x.dim(3)?;
        let xc = x.permute((0, 3, 1, 2))?.contiguous()?;
        let k = weight.permute((2, 0, 1))?.reshape((c, 1, 3, 3))?;
        xc.conv2d(&k, 1, 1, 1, c)?.permute((0, 2, 3, 1))
    }
}

/// `modulate(layer_norm(x), shift, scale)` in one pass: `x` (B, N, C), `shift` and `scale`
/// (B, 1, C). The composed version is ten candle ops forward and about twice that backward, each
/// a pass over (B, N, C) memory with its own allocation, and the reductions among them run on one
/// thread; the profile of a training step had them among the largest costs after the matmuls.
/// f32 on CPU through a custom op with a hand-written backward; other devices compose it.
pub fn layer_norm_modulate(x: &Tensor, shift: &Tensor, scale: &Tensor, eps: f64) -> Result<Tensor> {
    if x.device().is_cpu() && x.dtype() == DType::F32 {
        x.contiguous()?.apply_op3(
            &shift.contiguous()?,
            &scale.contiguous()?,
            LayerNormModulate { eps: eps as f32 },
        )
    } else {
        modulate(&layer_norm(x, eps)?, shift, scale)
    }
}

struct LayerNormModulate {
    eps: f32,
}

/// Checks (B, N, C) against two (B, 1, C) tensors and returns (B, N, C).
fn ln_mod_dims(lx: &Layout, l2: &Layout, l3: &Layout) -> Result<(usize, usize, usize)> {
    let [b, n, c] = *lx.dims() else {
        candle_core::bail!(
            "layer_norm_modulate input must be (B, N, C), got {:?}",
            lx.dims()
        )
    };
    for l in [l2, l3] {
        if l.dims() != [b, 1, c] {
            candle_core::bail!(
                "layer_norm_modulate shift and scale must be ({b}, 1, {c}), got {:?}",
                l.dims()
            );
        }
    }
    Ok((b, n, c))
}

/// Mean and 1 / standard deviation of a row (two passes, as the composed version).
#[inline]
fn row_stats(row: &[f32], eps: f32) -> (f32, f32) {
    let c = row.len() as f32;
    let mean = row.iter().sum::<f32>() / c;
    let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / c;
    (mean, 1.0 / (var + eps).sqrt())
}

impl CustomOp3 for LayerNormModulate {
    fn name(&self) -> &'static str {
        "layer-norm-modulate"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (_, n, c) = ln_mod_dims(l1, l2, l3)?;
        let x = contiguous_f32(s1, l1, "layer_norm_modulate input")?;
        let shift = contiguous_f32(s2, l2, "layer_norm_modulate shift")?;
        let scale = contiguous_f32(s3, l3, "layer_norm_modulate scale")?;
        let mut y = vec![0f32; x.len()];
        crate::pool::for_each_chunk_mut(&mut y, c, |r, out| {
            let row = &x[r * c..][..c];
            let bi = r / n;
            let (sh, sc) = (&shift[bi * c..][..c], &scale[bi * c..][..c]);
            let (mean, inv) = row_stats(row, self.eps);
            for (((o, v), s), t) in out.iter_mut().zip(row).zip(sc).zip(sh) {
                *o = (v - mean) * inv * (1.0 + s) + t;
            }
        });
        Ok((CpuStorage::F32(y), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        _shift: &Tensor,
        scale: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let n = x.dim(1)?;
        // One op gives all three gradients, stacked along the token axis: N rows of dL/dx, then
        // dL/dshift and dL/dscale.
        let all = x.apply_op3_no_bwd(
            scale,
            &grad.contiguous()?,
            &LayerNormModulateBackward { eps: self.eps },
        )?;
        Ok((
            Some(all.narrow(1, 0, n)?),
            Some(all.narrow(1, n, 1)?),
            Some(all.narrow(1, n + 1, 1)?),
        ))
    }
}

/// With `xh` the normalised row, `inv` 1 / std and `g = dy * (1 + scale)`:
/// `dx = inv * (g - mean(g) - xh * mean(g * xh))`, `dshift = sum_n dy`, `dscale = sum_n dy * xh`.
struct LayerNormModulateBackward {
    eps: f32,
}

impl CustomOp3 for LayerNormModulateBackward {
    fn name(&self) -> &'static str {
        "layer-norm-modulate-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (b, n, c) = ln_mod_dims(l1, l2, l2)?;
        if l3.dims() != l1.dims() {
            candle_core::bail!("layer_norm_modulate gradient must have the input's shape");
        }
        let x = contiguous_f32(s1, l1, "layer_norm_modulate input")?;
        let scale = contiguous_f32(s2, l2, "layer_norm_modulate scale")?;
        let dy = contiguous_f32(s3, l3, "layer_norm_modulate output gradient")?;
        let mut out = vec![0f32; b * (n + 2) * c];
        // One sample per task: its token rows and its own shift/scale sums (deterministic).
        crate::pool::for_each_chunk_mut(&mut out, (n + 2) * c, |bi, out| {
            let sc = &scale[bi * c..][..c];
            let (dx, sums) = out.split_at_mut(n * c);
            let (dshift, dscale) = sums.split_at_mut(c);
            let mut xh = vec![0f32; c];
            let mut g = vec![0f32; c];
            for t in 0..n {
                let row = &x[(bi * n + t) * c..][..c];
                let dyr = &dy[(bi * n + t) * c..][..c];
                let (mean, inv) = row_stats(row, self.eps);
                let (mut g_mean, mut gx_mean) = (0f32, 0f32);
                for j in 0..c {
                    xh[j] = (row[j] - mean) * inv;
                    g[j] = dyr[j] * (1.0 + sc[j]);
                    g_mean += g[j];
                    gx_mean += g[j] * xh[j];
                    dshift[j] += dyr[j];
                    dscale[j] += dyr[j] * xh[j];
                }
                g_mean /= c as f32;
                gx_mean /= c as f32;
                let dxr = &mut dx[t * c..][..c];
                for j in 0..c {
                    dxr[j] = inv * (g[j] - g_mean - xh[j] * gx_mean);
                }
            }
        });
        Ok((CpuStorage::F32(out), Shape::from_dims(&[b, n + 2, c])))
    }
}

/// `x + bias` with `x` (..., C) and `bias` (C). candle's broadcast_add reduces its bias gradient
/// with a strided, single-threaded sum over every leading dimension: 15% of a training step in
/// the profile (every linear layer has a bias). Here the gradient is a row-wise sum, parallel over
/// fixed chunks of rows and reduced in order (deterministic). CPU f32; elsewhere broadcast_add.
pub fn bias_add(x: &Tensor, bias: &Tensor) -> Result<Tensor> {
    if x.device().is_cpu() && x.dtype() == DType::F32 {
        x.contiguous()?.apply_op2(&bias.contiguous()?, BiasAdd)
    } else {
        x.broadcast_add(bias)
    }
}

struct BiasAdd;

impl CustomOp2 for BiasAdd {
    fn name(&self) -> &'static str {
        "bias-add"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let c = *l1.dims().last().unwrap_or(&0);
        if l2.dims() != [c] {
            candle_core::bail!(
                "bias_add: bias must be ({c}) for input {:?}, got {:?}",
                l1.dims(),
                l2.dims()
            );
        }
        let x = contiguous_f32(s1, l1, "bias_add input")?;
        let b = contiguous_f32(s2, l2, "bias_add bias")?;
        let mut y = x.to_vec();
        if c > 0 {
            crate::pool::for_each_chunk_mut(&mut y, c, |_, row| {
                for (v, bv) in row.iter_mut().zip(b) {
                    *v += bv;
                }
            });
        }
        Ok((CpuStorage::F32(y), l1.shape().clone()))
    }

    fn bwd(
        &self,
        _x: &Tensor,
        _bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let db = grad.contiguous()?.apply_op1_no_bwd(&RowSum)?;
        Ok((Some(grad.clone()), Some(db)))
    }
}

/// Sum of the rows of (..., C) -> (C).
struct RowSum;

impl candle_core::CustomOp1 for RowSum {
    fn name(&self) -> &'static str {
        "row-sum"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let c = *l.dims().last().unwrap_or(&0);
        let g = contiguous_f32(s, l, "row_sum input")?;
        let mut out = vec![0f32; c];
        if c > 0 {
            const ROWS: usize = 256;
            let partial: Vec<Vec<f32>> = crate::pool::map(g.len().div_ceil(ROWS * c), |k| {
                let chunk = &g[k * ROWS * c..g.len().min((k + 1) * ROWS * c)];
                let mut acc = vec![0f32; c];
                for row in chunk.chunks_exact(c) {
                    for (a, v) in acc.iter_mut().zip(row) {
                        *a += v;
                    }
                }
                acc
            });
            for p in &partial {
                for (o, v) in out.iter_mut().zip(p) {
                    *o += v;
                }
            }
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&[c])))
    }
}

/// SANA's ReLU linear attention straight from the fused projection: `qkv` (B, N, 3D) holding q, k
/// and v side by side, `heads` heads of D / heads channels, out (B, N, D) with the heads merged.
/// The same function as [`linear_attention`] after splitting heads, without the head
/// split/merge copies, the ones column, the concatenation and the division as separate ops
/// (about a dozen candle ops forward and twice that backward per block). CPU f32 custom op with a
/// hand-written backward; other devices use the composed version.
pub fn linear_attention_qkv(qkv: &Tensor, heads: usize, eps: f64) -> Result<Tensor> {
    let (b, n, three_d) = qkv.dims3()?;
    if heads == 0 || three_d % (3 * heads) != 0 {
        candle_core::bail!("linear_attention_qkv: {three_d} channels are not 3 x {heads} heads");
    }
    if qkv.device().is_cpu() && qkv.dtype() == DType::F32 {
        qkv.contiguous()?.apply_op1(LinearAttentionQkv {
            heads,
            eps: eps as f32,
        })
    } else {
        let d = three_d / 3;
        let split = |i: usize| -> Result<Tensor> {
            qkv.narrow(2, i * d, d)?
                .reshape((b, n, heads, d / heads))?
                .transpose(1, 2)?
                .contiguous()
        };
        let out = linear_attention(&split(0)?, &split(1)?, &split(2)?, eps)?;
        out.transpose(1, 2)?.reshape((b, n, d))
    }
}

struct LinearAttentionQkv {
    heads: usize,
    eps: f32,
}

/// `dst (m x n) = lhs (m x k) * rhs (k x n)` through gemm's runtime-dispatched SIMD kernels, on
/// strided views given as (row stride, column stride); `dst` is contiguous, row-major. Single
/// threaded: the callers run one (sample, head) per task of the pool.
#[allow(clippy::too_many_arguments)]
fn small_matmul(
    m: usize,
    n: usize,
    k: usize,
    dst: &mut [f32],
    lhs: &[f32],
    (lhs_rs, lhs_cs): (usize, usize),
    rhs: &[f32],
    (rhs_rs, rhs_cs): (usize, usize),
) {
    assert_eq!(dst.len(), m * n, "small_matmul: destination size");
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        dst.fill(0.0);
        return;
    }
    // The furthest element each operand is read at, so that the raw-pointer call stays in bounds.
    assert!(
        (m - 1) * lhs_rs + (k - 1) * lhs_cs < lhs.len(),
        "small_matmul: lhs bounds"
    );
    assert!(
        (k - 1) * rhs_rs + (n - 1) * rhs_cs < rhs.len(),
        "small_matmul: rhs bounds"
    );
    // SAFETY: the asserts above bound every index gemm reads; dst is m x n, row-major.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            false,
            lhs.as_ptr(),
            lhs_cs as isize,
            lhs_rs as isize,
            rhs.as_ptr(),
            rhs_cs as isize,
            rhs_rs as isize,
            0.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// A strided view of a row-major f32 matrix: `data[r * row_stride + c * col_stride]`.
#[derive(Clone, Copy)]
struct MatView<'a> {
    data: &'a [f32],
    row_stride: usize,
    col_stride: usize,
}

impl<'a> MatView<'a> {
    fn rows(data: &'a [f32], cols: usize) -> Self {
        Self {
            data,
            row_stride: cols,
            col_stride: 1,
        }
    }

    fn transposed(self) -> Self {
        Self {
            row_stride: self.col_stride,
            col_stride: self.row_stride,
            ..self
        }
    }
}

/// `dst (m x n, row-major) = [dst +] lhs (m x k) * rhs (k x n)`, the rows of `dst` split into one
/// block per thread of candle's pool, each a single-threaded gemm. gemm's own parallelism runs on
/// rayon, whose workers have to be woken while candle's pool worker spins for its next op on the
/// same two cores; on the pool the spinning worker takes its block at once.
fn pool_gemm(
    m: usize,
    n: usize,
    k: usize,
    dst: &mut [f32],
    accumulate: bool,
    lhs: MatView,
    rhs: MatView,
) {
    assert_eq!(dst.len(), m * n, "pool_gemm: destination size");
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            dst.fill(0.0);
        }
        return;
    }
    assert!(
        (m - 1) * lhs.row_stride + (k - 1) * lhs.col_stride < lhs.data.len(),
        "pool_gemm: lhs bounds"
    );
    assert!(
        (k - 1) * rhs.row_stride + (n - 1) * rhs.col_stride < rhs.data.len(),
        "pool_gemm: rhs bounds"
    );
    // Blocks of whole rows, a multiple of gemm's 6-row micro-tile where possible.
    let threads = crate::pool::threads();
    let block_rows = if m * n * k < 1 << 18 {
        m
    } else {
        m.div_ceil(threads).div_ceil(6) * 6
    };
    crate::pool::for_each_chunk_mut(dst, block_rows * n, |i, block| {
        let rows = block.len() / n;
        let lhs_block = &lhs.data[i * block_rows * lhs.row_stride..];
        // SAFETY: the asserts above bound every index gemm reads (the block's rows are a subset
        // of lhs's m rows); `block` is rows x n, row-major.
        unsafe {
            gemm::gemm(
                rows,
                n,
                k,
                block.as_mut_ptr(),
                1,
                n as isize,
                accumulate,
                lhs_block.as_ptr(),
                lhs.col_stride as isize,
                lhs.row_stride as isize,
                rhs.data.as_ptr(),
                rhs.col_stride as isize,
                rhs.row_stride as isize,
                1.0,
                1.0,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
    });
}

/// Per-(sample, head) outputs (task = sample * heads + head, each N x hd) merged into
/// (B, N, heads * hd), heads side by side.
fn merge_heads(parts: &[Vec<f32>], b: usize, n: usize, heads: usize, hd: usize) -> Vec<f32> {
    let d = heads * hd;
    let mut out = vec![0f32; b * n * d];
    for (task, part) in parts.iter().enumerate() {
        let (bi, h) = (task / heads, task % heads);
        for i in 0..n {
            out[(bi * n + i) * d + h * hd..][..hd].copy_from_slice(&part[i * hd..][..hd]);
        }
    }
    out
}

/// One (sample, head) of linear attention: relu(q), relu(k) and [v, 1] gathered contiguous, and
/// `kv` (hd x (hd + 1)) = relu(k)^T [v, 1], whose last column is the key sum (the normaliser).
struct HeadTerms {
    rq: Vec<f32>,
    rk: Vec<f32>,
    v1: Vec<f32>,
    kv: Vec<f32>,
    /// relu(q) kv: (N x (hd + 1)), numerators and normaliser.
    o: Vec<f32>,
}

fn head_terms(qkv: &[f32], n: usize, dm: usize, hd: usize, off: usize) -> HeadTerms {
    let w = hd + 1;
    let (mut rq, mut rk, mut v1) = (vec![0f32; n * hd], vec![0f32; n * hd], vec![1f32; n * w]);
    for i in 0..n {
        let row = &qkv[i * 3 * dm..][..3 * dm];
        for a in 0..hd {
            rq[i * hd + a] = row[off + a].max(0.0);
            rk[i * hd + a] = row[dm + off + a].max(0.0);
        }
        v1[i * w..i * w + hd].copy_from_slice(&row[2 * dm + off..][..hd]);
    }
    let mut kv = vec![0f32; hd * w];
    small_matmul(hd, w, n, &mut kv, &rk, (1, hd), &v1, (w, 1));
    let mut o = vec![0f32; n * w];
    small_matmul(n, w, hd, &mut o, &rq, (hd, 1), &kv, (w, 1));
    HeadTerms { rq, rk, v1, kv, o }
}

impl LinearAttentionQkv {
    fn dims(&self, l: &Layout) -> Result<(usize, usize, usize, usize)> {
        let [b, n, three_d] = *l.dims() else {
            candle_core::bail!("linear attention input must be (B, N, 3D)")
        };
        let dm = three_d / 3;
        Ok((b, n, dm, dm / self.heads))
    }
}

impl candle_core::CustomOp1 for LinearAttentionQkv {
    fn name(&self) -> &'static str {
        "linear-attention-qkv"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let (b, n, dm, hd) = self.dims(l)?;
        let x = contiguous_f32(s, l, "linear attention input")?;
        let w = hd + 1;
        // One task per (sample, head), then the heads are merged into (B, N, D).
        let heads: Vec<Vec<f32>> = crate::pool::map(b * self.heads, |task| {
            let (bi, h) = (task / self.heads, task % self.heads);
            let t = head_terms(&x[bi * n * 3 * dm..][..n * 3 * dm], n, dm, hd, h * hd);
            let mut out = vec![0f32; n * hd];
            for i in 0..n {
                let den = t.o[i * w + hd] + self.eps;
                for c in 0..hd {
                    out[i * hd + c] = t.o[i * w + c] / den;
                }
            }
            out
        });
        let out = merge_heads(&heads, b, n, self.heads, hd);
        Ok((CpuStorage::F32(out), Shape::from_dims(&[b, n, dm])))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let g = arg.apply_op2_no_bwd(
            &grad.contiguous()?,
            &LinearAttentionQkvBackward {
                heads: self.heads,
                eps: self.eps,
            },
        )?;
        Ok(Some(g))
    }
}

/// With r = relu(q_i), den_i = r . ksum + eps, out_i = r KV / den_i and dO the output gradient,
/// `G` (N x (hd + 1)) holds dnum = dO / den and, in its last column, dden = -(dO . out) / den:
/// d relu(q) = G KV^T, dKV = relu(q)^T G, d relu(k) = [v, 1] dKV^T, dv = relu(k) dKV[:, :hd];
/// the ReLU masks the q and k gradients.
struct LinearAttentionQkvBackward {
    heads: usize,
    eps: f32,
}

impl CustomOp2 for LinearAttentionQkvBackward {
    fn name(&self) -> &'static str {
        "linear-attention-qkv-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let fwd = LinearAttentionQkv {
            heads: self.heads,
            eps: self.eps,
        };
        let (b, n, dm, hd) = fwd.dims(l1)?;
        if l2.dims() != [b, n, dm] {
            candle_core::bail!("linear attention gradient must be ({b}, {n}, {dm})");
        }
        let x = contiguous_f32(s1, l1, "linear attention input")?;
        let dout = contiguous_f32(s2, l2, "linear attention output gradient")?;
        let w = hd + 1;
        // Per task: (dq, dk, dv), each N x hd.
        let parts: Vec<[Vec<f32>; 3]> = crate::pool::map(b * self.heads, |task| {
            let (bi, h) = (task / self.heads, task % self.heads);
            let qkv = &x[bi * n * 3 * dm..][..n * 3 * dm];
            let t = head_terms(qkv, n, dm, hd, h * hd);
            let mut g = vec![0f32; n * w];
            for i in 0..n {
                let den = t.o[i * w + hd] + self.eps;
                let go = &dout[(bi * n + i) * dm + h * hd..][..hd];
                let mut dot = 0f32;
                for c in 0..hd {
                    g[i * w + c] = go[c] / den;
                    dot += go[c] * (t.o[i * w + c] / den);
                }
                g[i * w + hd] = -dot / den;
            }
            let mut dq = vec![0f32; n * hd];
            small_matmul(n, hd, w, &mut dq, &g, (w, 1), &t.kv, (1, w));
            let mut dkv = vec![0f32; hd * w];
            small_matmul(hd, w, n, &mut dkv, &t.rq, (1, hd), &g, (w, 1));
            let mut dk = vec![0f32; n * hd];
            small_matmul(n, hd, w, &mut dk, &t.v1, (w, 1), &dkv, (1, w));
            let mut dv = vec![0f32; n * hd];
            small_matmul(n, hd, hd, &mut dv, &t.rk, (hd, 1), &dkv, (w, 1));
            // ReLU: no gradient where the input was not positive.
            for (d, r) in dq.iter_mut().zip(&t.rq) {
                if *r <= 0.0 {
                    *d = 0.0;
                }
            }
            for (d, r) in dk.iter_mut().zip(&t.rk) {
                if *r <= 0.0 {
                    *d = 0.0;
                }
            }
            [dq, dk, dv]
        });
        let mut dx = vec![0f32; x.len()];
        for (task, [dq, dk, dv]) in parts.iter().enumerate() {
            let (bi, h) = (task / self.heads, task % self.heads);
            for i in 0..n {
                let row = &mut dx[(bi * n + i) * 3 * dm..][..3 * dm];
                let off = h * hd;
                row[off..][..hd].copy_from_slice(&dq[i * hd..][..hd]);
                row[dm + off..][..hd].copy_from_slice(&dk[i * hd..][..hd]);
                row[2 * dm + off..][..hd].copy_from_slice(&dv[i * hd..][..hd]);
            }
        }
        Ok((CpuStorage::F32(dx), l1.shape().clone()))
    }
}

/// Multi-head softmax cross-attention straight from the projections: `q` (B, N, D) from the
/// tokens, `kv` (B, M, 2D) holding the condition's keys and values side by side, `heads` heads of
/// D / heads channels, out (B, N, D) with the heads merged. The same function as splitting heads
/// and calling [`softmax_attention`], without the head split/merge copies, the key transpose, the
/// scaling and the five ops of a composed softmax (about fifteen candle ops per block forward,
/// more backward). CPU f32 custom op with a hand-written backward; other devices use the
/// composed version.
pub fn cross_attention(q: &Tensor, kv: &Tensor, heads: usize) -> Result<Tensor> {
    let (b, n, d) = q.dims3()?;
    let (bk, m, two_d) = kv.dims3()?;
    if heads == 0 || d % heads != 0 || two_d != 2 * d || bk != b {
        candle_core::bail!(
            "cross_attention: q {:?} and kv {:?} do not fit {heads} heads",
            q.dims(),
            kv.dims()
        );
    }
    if q.device().is_cpu() && q.dtype() == DType::F32 && kv.dtype() == DType::F32 {
        q.contiguous()?
            .apply_op2(&kv.contiguous()?, CrossAttention { heads })
    } else {
        let split = |x: &Tensor, len: usize| -> Result<Tensor> {
            x.reshape((b, len, heads, d / heads))?
                .transpose(1, 2)?
                .contiguous()
        };
        let k = split(&kv.narrow(2, 0, d)?, m)?;
        let v = split(&kv.narrow(2, d, d)?, m)?;
        let out = softmax_attention(&split(q, n)?, &k, &v)?;
        out.transpose(1, 2)?.reshape((b, n, d))
    }
}

struct CrossAttention {
    heads: usize,
}

impl CrossAttention {
    /// (B, N, M, D, head dim) of a (q, kv) pair of layouts.
    fn dims(&self, lq: &Layout, lkv: &Layout) -> Result<(usize, usize, usize, usize, usize)> {
        let (&[b, n, d], &[bk, m, two_d]) = (lq.dims(), lkv.dims()) else {
            candle_core::bail!("cross attention inputs must be (B, N, D) and (B, M, 2D)")
        };
        if bk != b || two_d != 2 * d || d % self.heads != 0 {
            candle_core::bail!("cross attention: q {:?}, kv {:?}", lq.dims(), lkv.dims());
        }
        Ok((b, n, m, d, d / self.heads))
    }
}

/// Softmax probabilities (N x M) of one (sample, head): `q` starts at the head's first channel of
/// the sample's first token (rows D apart), `kv` at the head's key channels (rows 2D apart).
fn cross_probabilities(q: &[f32], kv: &[f32], n: usize, m: usize, d: usize, hd: usize) -> Vec<f32> {
    let mut p = vec![0f32; n * m];
    small_matmul(n, m, hd, &mut p, q, (d, 1), kv, (1, 2 * d));
    let scale = 1.0 / (hd as f32).sqrt();
    for row in p.chunks_exact_mut(m) {
        softmax_row(row, scale);
    }
    p
}

/// Sum over eight independent lanes (vectorisable; the order differs from a serial sum).
#[inline(always)]
fn lane_sum(xs: &[f32]) -> f32 {
    let mut sums = [0f32; 8];
    let mut chunks = xs.chunks_exact(8);
    for chunk in &mut chunks {
        for (lane, &v) in sums.iter_mut().zip(chunk) {
            *lane += v;
        }
    }
    chunks.remainder().iter().chain(&sums).sum()
}

simd_dispatch! {
    /// Dot product over eight independent lanes.
    fn lane_dot(a: &[f32], b: &[f32]) -> f32 = lane_dot_kernel;
}

#[inline(always)]
fn lane_dot_kernel(a: &[f32], b: &[f32]) -> f32 {
    let mut sums = [0f32; 8];
    let (mut ca, mut cb) = (a.chunks_exact(8), b.chunks_exact(8));
    for (x, y) in (&mut ca).zip(&mut cb) {
        for ((lane, &u), &v) in sums.iter_mut().zip(x).zip(y) {
            *lane += u * v;
        }
    }
    let tail: f32 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(u, v)| u * v)
        .sum();
    tail + sums.iter().sum::<f32>()
}

simd_dispatch! {
    /// `row <- softmax(scale * row)` in place (scale > 0). The max and the sum run on eight
    /// independent lanes and the exponentials in a loop of their own: a single running max or
    /// sum is a serial chain the compiler may not reorder, which kept these loops scalar.
    fn softmax_row(row: &mut [f32], scale: f32) = softmax_row_kernel;
}

#[inline(always)]
fn softmax_row_kernel(row: &mut [f32], scale: f32) {
    let mut lanes = [f32::NEG_INFINITY; 8];
    let mut chunks = row.chunks_exact(8);
    for chunk in &mut chunks {
        for (lane, &v) in lanes.iter_mut().zip(chunk) {
            *lane = lane.max(v);
        }
    }
    let max = chunks
        .remainder()
        .iter()
        .chain(&lanes)
        .fold(f32::NEG_INFINITY, |a, &v| a.max(v));
    let shift = max * scale;
    for v in row.iter_mut() {
        *v = fast_exp(*v * scale - shift);
    }
    let inv = 1.0 / lane_sum(row);
    for v in row.iter_mut() {
        *v *= inv;
    }
}

impl CustomOp2 for CrossAttention {
    fn name(&self) -> &'static str {
        "cross-attention"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (b, n, m, d, hd) = self.dims(l1, l2)?;
        let q = contiguous_f32(s1, l1, "cross attention q")?;
        let kv = contiguous_f32(s2, l2, "cross attention kv")?;
        let heads: Vec<Vec<f32>> = crate::pool::map(b * self.heads, |task| {
            let (bi, h) = (task / self.heads, task % self.heads);
            let (q0, kv0) = (&q[bi * n * d + h * hd..], &kv[bi * m * 2 * d + h * hd..]);
            let p = cross_probabilities(q0, kv0, n, m, d, hd);
            let mut out = vec![0f32; n * hd];
            small_matmul(n, hd, m, &mut out, &p, (m, 1), &kv0[d..], (2 * d, 1));
            out
        });
        let out = merge_heads(&heads, b, n, self.heads, hd);
        Ok((CpuStorage::F32(out), Shape::from_dims(&[b, n, d])))
    }

    fn bwd(
        &self,
        q: &Tensor,
        kv: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        // One op computes both gradients, packed flat: dq (B*N*D) then dkv (B*M*2D).
        let packed = q.apply_op3_no_bwd(
            kv,
            &grad.contiguous()?,
            &CrossAttentionBackward { heads: self.heads },
        )?;
        let nq = q.elem_count();
        Ok((
            Some(packed.narrow(0, 0, nq)?.reshape(q.shape())?),
            Some(packed.narrow(0, nq, kv.elem_count())?.reshape(kv.shape())?),
        ))
    }
}

/// With P the probabilities, dO the output gradient and s = 1 / sqrt(hd): dP = dO V^T,
/// dS = P * (dP - rowsum(dP * P)), dq = s dS K, dk = s dS^T q, dv = P^T dO.
struct CrossAttentionBackward {
    heads: usize,
}

impl CustomOp3 for CrossAttentionBackward {
    fn name(&self) -> &'static str {
        "cross-attention-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (b, n, m, d, hd) = CrossAttention { heads: self.heads }.dims(l1, l2)?;
        if l3.dims() != [b, n, d] {
            candle_core::bail!("cross attention gradient must be ({b}, {n}, {d})");
        }
        let q = contiguous_f32(s1, l1, "cross attention q")?;
        let kv = contiguous_f32(s2, l2, "cross attention kv")?;
        let dout = contiguous_f32(s3, l3, "cross attention output gradient")?;
        let scale = 1.0 / (hd as f32).sqrt();
        // Per task: dq (N x hd), dk and dv (M x hd).
        let parts: Vec<[Vec<f32>; 3]> = crate::pool::map(b * self.heads, |task| {
            let (bi, h) = (task / self.heads, task % self.heads);
            let (q0, kv0) = (&q[bi * n * d + h * hd..], &kv[bi * m * 2 * d + h * hd..]);
            let do0 = &dout[bi * n * d + h * hd..];
            let p = cross_probabilities(q0, kv0, n, m, d, hd);
            let mut ds = vec![0f32; n * m];
            small_matmul(n, m, hd, &mut ds, do0, (d, 1), &kv0[d..], (1, 2 * d));
            for (dsr, pr) in ds.chunks_exact_mut(m).zip(p.chunks_exact(m)) {
                let dot = lane_dot(dsr, pr);
                for (g, pv) in dsr.iter_mut().zip(pr) {
                    *g = pv * (*g - dot) * scale;
                }
            }
            let mut dq = vec![0f32; n * hd];
            small_matmul(n, hd, m, &mut dq, &ds, (m, 1), kv0, (2 * d, 1));
            let mut dk = vec![0f32; m * hd];
            small_matmul(m, hd, n, &mut dk, &ds, (1, m), q0, (d, 1));
            let mut dv = vec![0f32; m * hd];
            small_matmul(m, hd, n, &mut dv, &p, (1, m), do0, (d, 1));
            [dq, dk, dv]
        });
        let mut packed = vec![0f32; b * n * d + b * m * 2 * d];
        let (dq_all, dkv_all) = packed.split_at_mut(b * n * d);
        for (task, [dq, dk, dv]) in parts.iter().enumerate() {
            let (bi, h) = (task / self.heads, task % self.heads);
            for i in 0..n {
                dq_all[(bi * n + i) * d + h * hd..][..hd].copy_from_slice(&dq[i * hd..][..hd]);
            }
            for j in 0..m {
                let row = &mut dkv_all[(bi * m + j) * 2 * d..][..2 * d];
                row[h * hd..][..hd].copy_from_slice(&dk[j * hd..][..hd]);
                row[d + h * hd..][..hd].copy_from_slice(&dv[j * hd..][..hd]);
            }
        }
        Ok((
            CpuStorage::F32(packed),
            Shape::from_dims(&[b * n * d + b * m * 2 * d]),
        ))
    }
}

/// A linear layer on rows: `x` (R, in), `weight` (out, in), `bias` (out) -> `x W^T + b` (R, out).
/// On the CPU one gemm call accumulates the product into rows pre-filled with the bias: no
/// zero-filled product buffer and no second pass to add the bias (candle's matmul zero-fills its
/// output, and the bias add read and wrote it again). The backward is two matrix products and a
/// row sum. Other devices use the composed ops.
pub fn linear(x: &Tensor, weight: &Tensor, bias: &Tensor) -> Result<Tensor> {
    let (_, inner) = x.dims2()?;
    let (out, w_inner) = weight.dims2()?;
    if w_inner != inner || bias.dims() != [out] {
        candle_core::bail!(
            "linear: x {:?}, weight {:?}, bias {:?} do not fit",
            x.dims(),
            weight.dims(),
            bias.dims()
        );
    }
    if x.device().is_cpu() && [x, weight, bias].iter().all(|t| t.dtype() == DType::F32) {
        x.contiguous()?
            .apply_op3(&weight.contiguous()?, &bias.contiguous()?, Linear)
    } else {
        x.matmul(&weight.t()?)?.broadcast_add(bias)
    }
}

struct Linear;

impl CustomOp3 for Linear {
    fn name(&self) -> &'static str {
        "linear"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (&[rows, inner], &[out, _]) = (l1.dims(), l2.dims()) else {
            candle_core::bail!("linear: x must be (R, in) and weight (out, in)")
        };
        let x = contiguous_f32(s1, l1, "linear input")?;
        let w = contiguous_f32(s2, l2, "linear weight")?;
        let b = contiguous_f32(s3, l3, "linear bias")?;
        let mut y = Vec::with_capacity(rows * out);
        for _ in 0..rows {
            y.extend_from_slice(b);
        }
        // y = x W^T + b: W^T is W read with its strides swapped.
        pool_gemm(
            rows,
            out,
            inner,
            &mut y,
            true,
            MatView::rows(x, inner),
            MatView::rows(w, inner).transposed(),
        );
        Ok((CpuStorage::F32(y), Shape::from_dims(&[rows, out])))
    }

    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        _bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let dx = grad.apply_op2_no_bwd(
            weight,
            &MatMul {
                lhs_transposed: false,
            },
        )?;
        let dw = grad.apply_op2_no_bwd(
            x,
            &MatMul {
                lhs_transposed: true,
            },
        )?;
        let db = grad.apply_op1_no_bwd(&RowSum)?;
        Ok((Some(dx), Some(dw), Some(db)))
    }
}

/// `lhs * rhs` or `lhs^T * rhs` of contiguous 2-D f32 matrices through [`pool_gemm`]: the linear
/// layer's gradients `grad W` and `grad^T x`.
struct MatMul {
    lhs_transposed: bool,
}

impl CustomOp2 for MatMul {
    fn name(&self) -> &'static str {
        "pool-matmul"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (&[r1, c1], &[r2, c2]) = (l1.dims(), l2.dims()) else {
            candle_core::bail!(
                "pool matmul: 2-D operands, got {:?} and {:?}",
                l1.dims(),
                l2.dims()
            )
        };
        let a = contiguous_f32(s1, l1, "matmul lhs")?;
        let b = contiguous_f32(s2, l2, "matmul rhs")?;
        let (lhs, m, k) = if self.lhs_transposed {
            (MatView::rows(a, c1).transposed(), c1, r1)
        } else {
            (MatView::rows(a, c1), r1, c1)
        };
        if k != r2 {
            candle_core::bail!(
                "pool matmul: {:?} and {:?} do not fit",
                l1.dims(),
                l2.dims()
            );
        }
        let mut dst = vec![0f32; m * c2];
        pool_gemm(m, c2, k, &mut dst, false, lhs, MatView::rows(b, c2));
        Ok((CpuStorage::F32(dst), Shape::from_dims(&[m, c2])))
    }
}

/// SANA's gated Mix-FFN activation on a (..., 2H) input: `y[..., :H] * silu(y[..., H:])`, (..., H).
/// One pass forward, and a backward that writes the whole (..., 2H) gradient at once (the
/// composed version's two narrows each pad their gradient back to full width with zeros and
/// add). CPU f32 custom op; other devices use the composed ops.
pub fn silu_gate(y: &Tensor) -> Result<Tensor> {
    let two_h = *y.dims().last().unwrap_or(&0);
    if two_h % 2 != 0 {
        candle_core::bail!("silu_gate: the last dimension ({two_h}) must be even");
    }
    if y.device().is_cpu() && y.dtype() == DType::F32 {
        y.contiguous()?.apply_op1(SiluGate)
    } else {
        let d = y.rank() - 1;
        let h = two_h / 2;
        y.narrow(d, 0, h)? * candle_nn::ops::silu(&y.narrow(d, h, h)?)?
    }
}

/// `e^x` in f32 without branches or calls, so that loops over it vectorise (libm's `expf` is a
/// scalar call per element: the SiLU and GELU of one training step were a tenth of its profile).
/// Cody-Waite range reduction `x = n ln2 + r`, |r| <= ln2 / 2, Cephes' degree-6 polynomial for
/// `e^r`, and `2^n` assembled in the exponent bits. Relative error below 3e-7 over the whole
/// range; inputs are clamped to [-87.3, 88.3], where `e^x` is a normal f32.
#[inline(always)]
pub fn fast_exp(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Adding 1.5 * 2^23 rounds to an integer and leaves it in the low mantissa bits.
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.3, 88.3);
    let shifted = x * LOG2E + ROUND;
    let n = shifted - ROUND;
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = 1.987_569_2e-4;
    let p = p * r + 1.398_199_9e-3;
    let p = p * r + 8.333_452e-3;
    let p = p * r + 4.166_579_6e-2;
    let p = p * r + 1.666_666_5e-1;
    let p = p * r + 0.5;
    let er = p * r * r + r + 1.0;
    let n_bits = shifted.to_bits().wrapping_sub(ROUND.to_bits());
    er * f32::from_bits(n_bits.wrapping_add(127) << 23)
}

#[inline(always)]
fn sigmoid(z: f32) -> f32 {
    1.0 / (1.0 + fast_exp(-z))
}

/// Element-wise activations as single-pass custom ops with a hand-written backward (candle's
/// SiLU backward is seven tensor ops, its GELU backward ten, each a pass over memory and an
/// allocation). CPU f32; other devices use candle's ops.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// `x sigmoid(x)`.
    Silu,
    /// The tanh approximation, `0.5 x (1 + tanh(sqrt(2/pi) (x + 0.044715 x^3)))`, as candle's
    /// `gelu` and PyTorch's `gelu(approximate="tanh")`; written as `x sigmoid(2u)`.
    Gelu,
}

const GELU_C: f32 = 0.797_884_6; // sqrt(2 / pi)
const GELU_A: f32 = 0.044_715;

impl Activation {
    /// Value and derivative at `x`.
    #[inline(always)]
    fn value(self, x: f32) -> f32 {
        match self {
            Self::Silu => x * sigmoid(x),
            Self::Gelu => x * sigmoid(2.0 * GELU_C * (x + GELU_A * x * x * x)),
        }
    }

    #[inline(always)]
    fn derivative(self, x: f32) -> f32 {
        match self {
            Self::Silu => {
                let s = sigmoid(x);
                s * (1.0 + x * (1.0 - s))
            }
            Self::Gelu => {
                let x2 = x * x;
                let s = sigmoid(2.0 * GELU_C * (x + GELU_A * x2 * x));
                s + x * s * (1.0 - s) * 2.0 * GELU_C * (1.0 + 3.0 * GELU_A * x2)
            }
        }
    }

    pub fn apply(self, x: &Tensor) -> Result<Tensor> {
        if x.device().is_cpu() && x.dtype() == DType::F32 {
            x.contiguous()?.apply_op1(self)
        } else {
            match self {
                Self::Silu => candle_nn::ops::silu(x),
                Self::Gelu => x.gelu(),
            }
        }
    }
}

simd_dispatch! {
    /// `out = f(src)`.
    fn activation_values(kind: Activation, src: &[f32], out: &mut [f32]) = activation_values_kernel;
}

#[inline(always)]
fn activation_values_kernel(kind: Activation, src: &[f32], out: &mut [f32]) {
    // One loop per activation, so that each vectorises without a branch inside.
    match kind {
        Activation::Silu => {
            for (o, &v) in out.iter_mut().zip(src) {
                *o = Activation::Silu.value(v);
            }
        }
        Activation::Gelu => {
            for (o, &v) in out.iter_mut().zip(src) {
                *o = Activation::Gelu.value(v);
            }
        }
    }
}

simd_dispatch! {
    /// `out = grad * f'(xs)`.
    fn activation_gradients(kind: Activation, xs: &[f32], grad: &[f32], out: &mut [f32])
        = activation_gradients_kernel;
}

#[inline(always)]
fn activation_gradients_kernel(kind: Activation, xs: &[f32], grad: &[f32], out: &mut [f32]) {
    match kind {
        Activation::Silu => {
            for ((o, &v), &gv) in out.iter_mut().zip(xs).zip(grad) {
                *o = gv * Activation::Silu.derivative(v);
            }
        }
        Activation::Gelu => {
            for ((o, &v), &gv) in out.iter_mut().zip(xs).zip(grad) {
                *o = gv * Activation::Gelu.derivative(v);
            }
        }
    }
}

/// Elements per parallel chunk of the activation loops.
const ACTIVATION_CHUNK: usize = 16 * 1024;

impl candle_core::CustomOp1 for Activation {
    fn name(&self) -> &'static str {
        match self {
            Self::Silu => "fused-silu",
            Self::Gelu => "fused-gelu",
        }
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = contiguous_f32(s, l, "activation input")?;
        let mut y = vec![0f32; x.len()];
        crate::pool::for_each_chunk_mut(&mut y, ACTIVATION_CHUNK, |k, out| {
            activation_values(*self, &x[k * ACTIVATION_CHUNK..][..out.len()], out)
        });
        Ok((CpuStorage::F32(y), l.shape().clone()))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(arg.apply_op2_no_bwd(
            &grad.contiguous()?,
            &ActivationBackward(*self),
        )?))
    }
}

/// `dx = grad * f'(x)`.
struct ActivationBackward(Activation);

impl CustomOp2 for ActivationBackward {
    fn name(&self) -> &'static str {
        "fused-activation-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = contiguous_f32(s1, l1, "activation input")?;
        let g = contiguous_f32(s2, l2, "activation output gradient")?;
        if x.len() != g.len() {
            candle_core::bail!(
                "activation gradient {:?} for input {:?}",
                l2.dims(),
                l1.dims()
            );
        }
        let mut dx = vec![0f32; x.len()];
        crate::pool::for_each_chunk_mut(&mut dx, ACTIVATION_CHUNK, |k, out| {
            let xs = &x[k * ACTIVATION_CHUNK..][..out.len()];
            activation_gradients(self.0, xs, &g[k * ACTIVATION_CHUNK..][..out.len()], out)
        });
        Ok((CpuStorage::F32(dx), l1.shape().clone()))
    }
}

/// [`Activation::Silu`].
pub fn silu(x: &Tensor) -> Result<Tensor> {
    Activation::Silu.apply(x)
}

/// [`Activation::Gelu`].
pub fn gelu(x: &Tensor) -> Result<Tensor> {
    Activation::Gelu.apply(x)
}

struct SiluGate;

impl candle_core::CustomOp1 for SiluGate {
    fn name(&self) -> &'static str {
        "silu-gate"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let two_h = *l.dims().last().unwrap_or(&0);
        let h = two_h / 2;
        let y = contiguous_f32(s, l, "silu_gate input")?;
        let mut out = vec![0f32; y.len() / 2];
        if h > 0 {
            crate::pool::for_each_chunk_mut(&mut out, 64 * h, |k, o| {
                silu_gate_rows(&y[k * 128 * h..][..o.len() * 2], o, h)
            });
        }
        let mut dims = l.dims().to_vec();
        if let Some(last) = dims.last_mut() {
            *last = h;
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&dims)))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(arg.apply_op2_no_bwd(
            &grad.contiguous()?,
            &SiluGateBackward,
        )?))
    }
}

simd_dispatch! {
    /// Rows of `[v | gate]` (width 2h) -> rows of `v * silu(gate)` (width h).
    fn silu_gate_rows(src: &[f32], out: &mut [f32], h: usize) = silu_gate_rows_kernel;
}

#[inline(always)]
fn silu_gate_rows_kernel(src: &[f32], out: &mut [f32], h: usize) {
    for (orow, row) in out.chunks_exact_mut(h).zip(src.chunks_exact(2 * h)) {
        let (v, gate) = row.split_at(h);
        for ((ov, vv), gv) in orow.iter_mut().zip(v).zip(gate) {
            *ov = vv * gv * sigmoid(*gv);
        }
    }
}

simd_dispatch! {
    /// The gradient rows `[dv | dgate]` of [`silu_gate_rows`] from the output gradient's rows.
    fn silu_gate_gradient_rows(src: &[f32], grad: &[f32], out: &mut [f32], h: usize)
        = silu_gate_gradient_rows_kernel;
}

#[inline(always)]
fn silu_gate_gradient_rows_kernel(src: &[f32], grad: &[f32], out: &mut [f32], h: usize) {
    for ((drow, row), grow) in out
        .chunks_exact_mut(2 * h)
        .zip(src.chunks_exact(2 * h))
        .zip(grad.chunks_exact(h))
    {
        let (dv, dgate) = drow.split_at_mut(h);
        let (v, gate) = row.split_at(h);
        for j in 0..h {
            let s = sigmoid(gate[j]);
            dv[j] = grow[j] * gate[j] * s;
            dgate[j] = grow[j] * v[j] * s * (1.0 + gate[j] * (1.0 - s));
        }
    }
}

/// d v = g silu(gate); d gate = g v s (1 + gate (1 - s)) with s = sigmoid(gate).
struct SiluGateBackward;

impl CustomOp2 for SiluGateBackward {
    fn name(&self) -> &'static str {
        "silu-gate-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let two_h = *l1.dims().last().unwrap_or(&0);
        let h = two_h / 2;
        let y = contiguous_f32(s1, l1, "silu_gate input")?;
        let g = contiguous_f32(s2, l2, "silu_gate output gradient")?;
        if g.len() * 2 != y.len() {
            candle_core::bail!(
                "silu_gate gradient {:?} for input {:?}",
                l2.dims(),
                l1.dims()
            );
        }
        let mut dy = vec![0f32; y.len()];
        if h > 0 {
            crate::pool::for_each_chunk_mut(&mut dy, 64 * two_h, |k, d| {
                let src = &y[k * 64 * two_h..][..d.len()];
                silu_gate_gradient_rows(src, &g[k * 64 * h..][..d.len() / 2], d, h)
            });
        }
        Ok((CpuStorage::F32(dy), l1.shape().clone()))
    }
}

#[cfg(test)]
mod tests {
    //! The AVX2 versions of the dispatched kernels against the baseline ones (the `_kernel`
    //! functions called from here are compiled without AVX2): the same bits, so results do not
    //! depend on the CPU.
    use super::*;

    fn inputs(n: usize, seed: u32) -> Vec<f32> {
        // A fixed pseudo-random spread over [-8, 8), including the activations' tails.
        (0..n as u32)
            .map(|i| {
                let h = (i ^ seed).wrapping_mul(2_654_435_761).rotate_left(13);
                (h % 16_000) as f32 / 1000.0 - 8.0
            })
            .collect()
    }

    fn same_bits(a: &[f32], b: &[f32], what: &str) {
        assert_eq!(a.len(), b.len(), "{what}: length");
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert_eq!(x.to_bits(), y.to_bits(), "{what}[{i}]: {x} != {y}");
        }
    }

    #[test]
    fn dispatched_kernels_give_the_baseline_bits() {
        if !crate::simd::has_avx2() {
            eprintln!("no AVX2 on this CPU: the dispatched kernels are the baseline ones");
        }
        // 1003: not a multiple of any vector width, so the tails are covered too.
        let x = inputs(1003, 1);
        let g = inputs(1003, 2);
        for kind in [Activation::Silu, Activation::Gelu] {
            let (mut a, mut b) = (vec![0f32; x.len()], vec![0f32; x.len()]);
            activation_values(kind, &x, &mut a);
            activation_values_kernel(kind, &x, &mut b);
            same_bits(&a, &b, "activation values");
            activation_gradients(kind, &x, &g, &mut a);
            activation_gradients_kernel(kind, &x, &g, &mut b);
            same_bits(&a, &b, "activation gradients");
        }

        let h = 37;
        let rows = inputs(2 * h * 5, 3);
        let grad = inputs(h * 5, 4);
        let (mut a, mut b) = (vec![0f32; h * 5], vec![0f32; h * 5]);
        silu_gate_rows(&rows, &mut a, h);
        silu_gate_rows_kernel(&rows, &mut b, h);
        same_bits(&a, &b, "silu gate");
        let (mut a, mut b) = (vec![0f32; 2 * h * 5], vec![0f32; 2 * h * 5]);
        silu_gate_gradient_rows(&rows, &grad, &mut a, h);
        silu_gate_gradient_rows_kernel(&rows, &grad, &mut b, h);
        same_bits(&a, &b, "silu gate gradient");

        let (mut a, mut b) = (x[..61].to_vec(), x[..61].to_vec());
        softmax_row(&mut a, 0.3);
        softmax_row_kernel(&mut b, 0.3);
        same_bits(&a, &b, "softmax row");
        let sum: f32 = a.iter().sum();
        assert!((sum - 1.0).abs() < 1e-5, "softmax row sums to {sum}");
        same_bits(&[lane_dot(&x, &g)], &[lane_dot_kernel(&x, &g)], "dot");

        let (bsz, hh, wd, c) = (2, 5, 6, 19);
        let img = inputs(bsz * hh * wd * c, 5);
        let w = inputs(9 * c, 6);
        let go = inputs(bsz * hh * wd * c, 7);
        for row in [0, 3, 4, 7] {
            let (mut a, mut b) = (vec![0f32; wd * c], vec![0f32; wd * c]);
            dwconv_row(&img, &w, &mut a, row, hh, wd, c);
            dwconv_row_kernel(&img, &w, &mut b, row, hh, wd, c);
            same_bits(&a, &b, "depthwise conv row");
            let (mut a, mut b) = (vec![0f32; 9 * c], vec![0f32; 9 * c]);
            dwconv_weight_grad_row(&img, &go, &mut a, row, hh, wd, c);
            dwconv_weight_grad_row_kernel(&img, &go, &mut b, row, hh, wd, c);
            same_bits(&a, &b, "depthwise conv weight gradient row");
        }
    }
}
