//! The linear layer as one gemm accumulating into bias-filled rows.

use super::*;

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

pub(crate) struct Linear;

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
pub(crate) struct MatMul {
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
