//! The fused CPU ops against candle's composed ops: values and gradients.

mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::{assert_same_gradients, max_abs_diff, rng};
use deocc_model::init::randn;
use deocc_model::ops::{
    bias_add, depthwise_conv3x3, layer_norm, layer_norm_modulate, linear_attention,
    linear_attention_qkv, modulate,
};

#[test]
fn linear_attention_equals_a_naive_loop() {
    let dev = Device::Cpu;
    let (b, h, n, d) = (2, 3, 7, 4);
    let mut g = rng(4);
    let q = randn((b, h, n, d), &mut g, &dev).unwrap();
    let k = randn((b, h, n, d), &mut g, &dev).unwrap();
    let v = randn((b, h, n, d), &mut g, &dev).unwrap();
    let got = linear_attention(&q, &k, &v, 1e-6)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    let (qv, kv, vv) = (
        q.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        k.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        v.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
    );
    let at =
        |x: &[f32], bi: usize, hi: usize, i: usize, c: usize| x[((bi * h + hi) * n + i) * d + c];
    for bi in 0..b {
        for hi in 0..h {
            for i in 0..n {
                // out_i = sum_j (relu(q_i).relu(k_j)) v_j / (sum_j relu(q_i).relu(k_j) + eps)
                let mut num = vec![0f32; d];
                let mut den = 0f32;
                for j in 0..n {
                    let s: f32 = (0..d)
                        .map(|c| at(&qv, bi, hi, i, c).max(0.0) * at(&kv, bi, hi, j, c).max(0.0))
                        .sum();
                    den += s;
                    for (c, acc) in num.iter_mut().enumerate() {
                        *acc += s * at(&vv, bi, hi, j, c);
                    }
                }
                for c in 0..d {
                    let expect = num[c] / (den + 1e-6);
                    let g = got[((bi * h + hi) * n + i) * d + c];
                    assert!(
                        (g - expect).abs() < 1e-4 * (1.0 + expect.abs()),
                        "{g} vs {expect}"
                    );
                }
            }
        }
    }
}

#[test]
fn fused_layer_norm_modulate_matches_the_composed_ops_and_their_gradients() {
    let dev = Device::Cpu;
    let (b, n, c) = (3, 5, 24);
    let mut g = rng(6);
    // Rows with an offset and a spread, as activations have.
    let x = (randn((b, n, c), &mut g, &dev).unwrap() * 3.0).unwrap();
    let x = Var::from_tensor(&(x + 0.7).unwrap()).unwrap();
    let shift = Var::from_tensor(&randn((b, 1, c), &mut g, &dev).unwrap()).unwrap();
    let scale = Var::from_tensor(&randn((b, 1, c), &mut g, &dev).unwrap()).unwrap();
    let ours =
        layer_norm_modulate(x.as_tensor(), shift.as_tensor(), scale.as_tensor(), 1e-6).unwrap();
    let reference = modulate(
        &layer_norm(x.as_tensor(), 1e-6).unwrap(),
        shift.as_tensor(),
        scale.as_tensor(),
    )
    .unwrap();
    assert_eq!(ours.dims(), &[b, n, c]);
    assert!(max_abs_diff(&ours, &reference) < 1e-5);
    assert_same_gradients(ours, reference, &[&x, &shift, &scale], 1e-4, 7);
    // A shift of the wrong shape is an error, not a silent broadcast.
    let wrong = Tensor::zeros((b, 2, c), DType::F32, &dev).unwrap();
    assert!(layer_norm_modulate(x.as_tensor(), &wrong, scale.as_tensor(), 1e-6).is_err());
}

#[test]
fn fused_linear_attention_matches_the_composed_ops_and_their_gradients() {
    let dev = Device::Cpu;
    let (b, n, heads, hd) = (2, 9, 3, 4);
    let dm = heads * hd;
    let mut g = rng(9);
    let qkv = Var::from_tensor(&randn((b, n, 3 * dm), &mut g, &dev).unwrap()).unwrap();
    let ours = linear_attention_qkv(qkv.as_tensor(), heads, 1e-6).unwrap();
    let split = |i: usize| {
        qkv.as_tensor()
            .narrow(2, i * dm, dm)
            .unwrap()
            .reshape((b, n, heads, hd))
            .unwrap()
            .transpose(1, 2)
            .unwrap()
            .contiguous()
            .unwrap()
    };
    let reference = linear_attention(&split(0), &split(1), &split(2), 1e-6)
        .unwrap()
        .transpose(1, 2)
        .unwrap()
        .reshape((b, n, dm))
        .unwrap();
    assert_eq!(ours.dims(), &[b, n, dm]);
    assert!(
        max_abs_diff(&ours, &reference) < 1e-5,
        "{}",
        max_abs_diff(&ours, &reference)
    );
    assert_same_gradients(ours, reference, &[&qkv], 1e-4, 10);
    assert!(linear_attention_qkv(qkv.as_tensor(), 5, 1e-6).is_err());
}

#[test]
fn bias_add_matches_broadcast_add_and_its_gradients() {
    let dev = Device::Cpu;
    let mut g = rng(8);
    // More rows than one reduction chunk (256), so the chunked gradient sum is exercised.
    let x = Var::from_tensor(&randn((3, 130, 5), &mut g, &dev).unwrap()).unwrap();
    let bias = Var::from_tensor(&randn(5, &mut g, &dev).unwrap()).unwrap();
    let ours = bias_add(x.as_tensor(), bias.as_tensor()).unwrap();
    let reference = x.as_tensor().broadcast_add(bias.as_tensor()).unwrap();
    assert_eq!(max_abs_diff(&ours, &reference), 0.0);
    assert_same_gradients(ours, reference, &[&x, &bias], 1e-4, 9);
    let wrong = Tensor::zeros(4, DType::F32, &dev).unwrap();
    assert!(bias_add(x.as_tensor(), &wrong).is_err());
}

#[test]
fn depthwise_conv_matches_candle_conv2d_and_its_gradients() {
    let dev = Device::Cpu;
    let (b, hh, ww, c) = (2, 5, 6, 7);
    let mut g = rng(5);
    let x = Var::from_tensor(&randn((b, hh, ww, c), &mut g, &dev).unwrap()).unwrap();
    let w = Var::from_tensor(&randn((3, 3, c), &mut g, &dev).unwrap()).unwrap();
    let ours = depthwise_conv3x3(x.as_tensor(), w.as_tensor()).unwrap();
    // Reference: candle's grouped conv2d in NCHW.
    let reference = x
        .as_tensor()
        .permute((0, 3, 1, 2))
        .unwrap()
        .contiguous()
        .unwrap()
        .conv2d(
            &w.as_tensor()
                .permute((2, 0, 1))
                .unwrap()
                .reshape((c, 1, 3, 3))
                .unwrap(),
            1,
            1,
            1,
            c,
        )
        .unwrap()
        .permute((0, 2, 3, 1))
        .unwrap();
    assert!(max_abs_diff(&ours, &reference) < 1e-5);
    // Gradients of a random linear functional agree with the reference's autograd.
    assert_same_gradients(ours, reference, &[&x, &w], 1e-4, 6);
}

#[test]
fn fused_cross_attention_matches_the_composed_ops_and_their_gradients() {
    use deocc_model::ops::{cross_attention, softmax_attention};
    let dev = Device::Cpu;
    let (b, n, m, heads, hd) = (2, 7, 5, 3, 4);
    let d = heads * hd;
    let mut g = rng(12);
    let q = Var::from_tensor(&randn((b, n, d), &mut g, &dev).unwrap()).unwrap();
    let kv = Var::from_tensor(&randn((b, m, 2 * d), &mut g, &dev).unwrap()).unwrap();
    let ours = cross_attention(q.as_tensor(), kv.as_tensor(), heads).unwrap();
    let split = |x: &Tensor, len: usize| {
        x.reshape((b, len, heads, hd))
            .unwrap()
            .transpose(1, 2)
            .unwrap()
            .contiguous()
            .unwrap()
    };
    let k = split(&kv.as_tensor().narrow(2, 0, d).unwrap(), m);
    let v = split(&kv.as_tensor().narrow(2, d, d).unwrap(), m);
    let reference = softmax_attention(&split(q.as_tensor(), n), &k, &v)
        .unwrap()
        .transpose(1, 2)
        .unwrap()
        .reshape((b, n, d))
        .unwrap();
    assert_eq!(ours.dims(), &[b, n, d]);
    assert!(
        max_abs_diff(&ours, &reference) < 1e-5,
        "{}",
        max_abs_diff(&ours, &reference)
    );
    assert_same_gradients(ours, reference, &[&q, &kv], 1e-4, 13);
    assert!(cross_attention(q.as_tensor(), kv.as_tensor(), 5).is_err());
}

#[test]
fn fused_linear_matches_matmul_plus_bias_and_its_gradients() {
    use deocc_model::ops::linear;
    let dev = Device::Cpu;
    let mut g = rng(31);
    // A small layer (one gemm block) and one large enough that the products are split into
    // row blocks across the pool, with a partial last block (613 rows).
    for (rows, inner, out, tolerance) in [(37, 11, 5, 1e-4), (613, 64, 96, 1e-3)] {
        let x = Var::from_tensor(&randn((rows, inner), &mut g, &dev).unwrap()).unwrap();
        let w = Var::from_tensor(&randn((out, inner), &mut g, &dev).unwrap()).unwrap();
        let b = Var::from_tensor(&randn(out, &mut g, &dev).unwrap()).unwrap();
        let ours = linear(x.as_tensor(), w.as_tensor(), b.as_tensor()).unwrap();
        let reference = x
            .as_tensor()
            .matmul(&w.as_tensor().t().unwrap())
            .unwrap()
            .broadcast_add(b.as_tensor())
            .unwrap();
        assert_eq!(ours.dims(), &[rows, out]);
        assert!(max_abs_diff(&ours, &reference) < tolerance);
        assert_same_gradients(ours, reference, &[&x, &w, &b], tolerance, 32);
        assert!(linear(x.as_tensor(), &w.as_tensor().t().unwrap(), b.as_tensor()).is_err());
    }
}

#[test]
fn fused_activations_match_candle_and_their_gradients() {
    use deocc_model::ops::{gelu, silu};
    let dev = Device::Cpu;
    // 40,000 elements: more than one chunk of the pool's loops; values out to +-12 reach the
    // saturated tails of the sigmoid.
    let x =
        Var::from_tensor(&(randn((40, 1000), &mut rng(43), &dev).unwrap() * 4.0).unwrap()).unwrap();
    let cases: [(Tensor, Tensor); 2] = [
        (
            silu(x.as_tensor()).unwrap(),
            candle_nn::ops::silu(x.as_tensor()).unwrap(),
        ),
        (gelu(x.as_tensor()).unwrap(), x.as_tensor().gelu().unwrap()),
    ];
    for (ours, reference) in cases {
        assert_eq!(ours.dims(), x.dims());
        let diff = max_abs_diff(&ours, &reference);
        assert!(diff < 1e-5, "values differ by {diff}");
        assert_same_gradients(ours, reference, &[&x], 1e-5, 44);
    }
}

#[test]
fn fast_exp_is_accurate_over_the_float_range() {
    use deocc_model::ops::fast_exp;
    let mut worst = 0f64;
    for i in 0..=200_000 {
        let x = -87.0 + 175.0 * i as f32 / 200_000.0;
        let exact = f64::from(x).exp();
        worst = worst.max(((f64::from(fast_exp(x)) - exact) / exact).abs());
    }
    assert!(worst < 5e-7, "relative error {worst}");
    assert_eq!(fast_exp(0.0), 1.0);
    // Clamped, not infinite or NaN, far outside the range.
    assert!(fast_exp(1000.0).is_finite() && fast_exp(-1000.0) >= 0.0);
}

#[test]
fn fused_silu_gate_matches_the_composed_ops_and_their_gradients() {
    use deocc_model::ops::silu_gate;
    let dev = Device::Cpu;
    let mut g = rng(41);
    // 2 x 70 rows: more than one chunk of the pool's loops, and a partial last chunk.
    let y = Var::from_tensor(&(randn((2, 70, 10), &mut g, &dev).unwrap() * 3.0).unwrap()).unwrap();
    let ours = silu_gate(y.as_tensor()).unwrap();
    let reference = (y.as_tensor().narrow(2, 0, 5).unwrap()
        * candle_nn::ops::silu(&y.as_tensor().narrow(2, 5, 5).unwrap()).unwrap())
    .unwrap();
    assert_eq!(ours.dims(), &[2, 70, 5]);
    assert!(max_abs_diff(&ours, &reference) < 1e-5);
    assert_same_gradients(ours, reference, &[&y], 1e-4, 42);
    assert!(silu_gate(&randn((2, 3), &mut g, &dev).unwrap()).is_err());
}
