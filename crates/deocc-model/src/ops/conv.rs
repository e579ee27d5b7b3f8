//! The depthwise 3x3 convolution of the Mix-FFN and its weight gradient.

use super::*;

/// y[b,i,j,c] = sum_{a,e in 0..3} x[b, i+a-1, j+e-1, c] * w[a, e, c], zero padding.
pub(crate) fn dwconv_forward(
    x: &[f32],
    w: &[f32],
    bsz: usize,
    h: usize,
    wd: usize,
    c: usize,
) -> Vec<f32> {
    let mut y = vec![0f32; bsz * h * wd * c];
    crate::pool::for_each_chunk_mut(&mut y, wd * c, |row_idx, out_row| {
        dwconv_row(x, w, out_row, row_idx, h, wd, c)
    });
    y
}

simd_dispatch! {
    /// One output row (image `row_idx / h`, row `row_idx % h`) of [`dwconv_forward`].
    pub(crate) fn dwconv_row(x: &[f32], w: &[f32], out_row: &mut [f32], row_idx: usize, h: usize, wd: usize, c: usize)
        = dwconv_row_kernel;
}

#[inline(always)]
pub(crate) fn dwconv_row_kernel(
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
pub(crate) fn for_each_tap(
    i: usize,
    h: usize,
    w: usize,
    mut f: impl FnMut(usize, usize, usize, usize),
) {
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
pub(crate) struct DepthwiseConv3x3;

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
    pub(crate) fn dwconv_weight_grad_row(x: &[f32], g: &[f32], acc: &mut [f32], row_idx: usize, h: usize, w: usize, c: usize)
        = dwconv_weight_grad_row_kernel;
}

#[inline(always)]
pub(crate) fn dwconv_weight_grad_row_kernel(
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
pub(crate) struct DepthwiseConv3x3WeightGrad;

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
