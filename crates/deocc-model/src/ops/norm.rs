//! adaLN's LayerNorm-modulate as one op.

use super::*;

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

pub(crate) struct LayerNormModulate {
    eps: f32,
}

/// Checks (B, N, C) against two (B, 1, C) tensors and returns (B, N, C).
pub(crate) fn ln_mod_dims(lx: &Layout, l2: &Layout, l3: &Layout) -> Result<(usize, usize, usize)> {
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
pub(crate) fn row_stats(row: &[f32], eps: f32) -> (f32, f32) {
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
pub(crate) struct LayerNormModulateBackward {
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
