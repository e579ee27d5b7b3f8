//! Building blocks with the shapes GL-DoT needs, written so they train fast on a CPU, one file
//! per op family: `conv.rs` (depthwise convolution), `norm.rs` (LayerNorm-modulate), `bias.rs`,
//! `linear.rs`, `attention.rs` (linear self-attention, softmax cross-attention), `activation.rs`
//! (SiLU, GELU, the SiLU gate, `fast_exp`), `products.rs` (the matrix products they share); the
//! composed reference ops are here.
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

pub(crate) fn contiguous_f32<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [f32]> {
    let data = s.as_slice::<f32>()?;
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&data[a..b]),
        None => candle_core::bail!("{what} must be contiguous"),
    }
}

mod activation;
mod attention;
mod bias;
mod conv;
mod linear;
mod norm;
mod products;

pub use activation::*;
pub use attention::*;
pub use bias::*;
pub use conv::*;
pub use linear::*;
pub use norm::*;
pub(crate) use products::*;

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
