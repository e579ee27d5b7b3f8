//! The bias add and its row-sum gradient.

use super::*;

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

pub(crate) struct BiasAdd;

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
pub(crate) struct RowSum;

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
