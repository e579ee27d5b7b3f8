//! The vendored candle-core's autograd patch (vendor/candle-core/DEOCC-PATCH.md) stores the first
//! gradient that reaches a tensor instead of adding it to zeroes. These tests pin what that must
//! not change: gradients shared between arguments, several consumers of one tensor, views
//! (transpose, narrow, broadcast) as first gradients, and contiguous results for the optimiser.

use candle_core::{Device, Tensor, Var};
use deocc_model::ops;

fn values(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

fn assert_close(got: &[f32], want: &[f32], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g - w).abs() <= 1e-5 * (1.0 + w.abs()),
            "{what}[{i}]: {g} != {w}"
        );
    }
}

#[test]
fn gradients_of_shared_and_viewed_uses_match_the_analytic_ones() {
    let dev = Device::Cpu;
    let xv: Vec<f32> = (0..6).map(|i| 0.3 * i as f32 - 0.7).collect();
    let bv = [0.5f32, -1.0, 2.0];
    let w1: Vec<f32> = (0..6).map(|i| 1.0 + i as f32).collect();
    let w2: Vec<f32> = (0..6).map(|i| 0.1 * i as f32 - 0.2).collect();
    let w3: Vec<f32> = (0..4).map(|i| -(i as f32) - 1.0).collect();
    let x = Var::from_slice(&xv, (2, 3), &dev).unwrap();
    let bias = Var::from_slice(&bv, 3, &dev).unwrap();
    let w1t = Tensor::from_slice(&w1, (2, 3), &dev).unwrap();
    let w2t = Tensor::from_slice(&w2, (3, 2), &dev).unwrap();
    let w3t = Tensor::from_slice(&w3, (2, 2), &dev).unwrap();

    // x + x: both arguments of one add receive the same gradient tensor.
    let doubled = (x.as_tensor() + x.as_tensor()).unwrap();
    // A transposed view and a narrowed view: their gradients arrive as views.
    let transposed = x.t().unwrap();
    let narrowed = x.narrow(1, 0, 2).unwrap();
    // A broadcast bias: its gradient is a sum over the broadcast rows.
    let shifted = x.broadcast_add(&bias).unwrap();
    let loss = ((doubled * &w1t).unwrap().sum_all().unwrap()
        + (transposed * &w2t).unwrap().sum_all().unwrap()
        + (narrowed * &w3t).unwrap().sum_all().unwrap()
        + shifted.sqr().unwrap().sum_all().unwrap())
    .unwrap();
    let grads = loss.backward().unwrap();

    let mut want_x = vec![0f32; 6];
    let mut want_b = vec![0f32; 3];
    for r in 0..2 {
        for c in 0..3 {
            let k = r * 3 + c;
            let square = 2.0 * (xv[k] + bv[c]);
            want_x[k] = 2.0 * w1[k] + w2[c * 2 + r] + square;
            if c < 2 {
                want_x[k] += w3[r * 2 + c];
            }
            want_b[c] += square;
        }
    }
    let gx = grads.get(&x).expect("x has a gradient");
    let gb = grads.get(&bias).expect("bias has a gradient");
    assert_close(&values(gx), &want_x, "d loss / d x");
    assert_close(&values(gb), &want_b, "d loss / d bias");
}

#[test]
fn a_first_gradient_that_is_a_broadcast_view_is_stored_contiguous() {
    let dev = Device::Cpu;
    let xv: Vec<f32> = (0..12).map(|i| 0.25 * i as f32 - 1.5).collect();
    let x = Var::from_slice(&xv, (3, 4), &dev).unwrap();
    // sum_all's backward broadcasts a scalar back to (3, 4): a stride-0 view.
    let grads = x.sum_all().unwrap().backward().unwrap();
    let gx = grads.get(&x).expect("x has a gradient");
    assert!(gx.is_contiguous(), "the stored gradient is contiguous");
    assert_close(&values(gx), &[1.0; 12], "d sum / d x");

    // The same view reaching a custom op's backward (which reads its gradient as a slice).
    let grads = ops::silu(x.as_tensor())
        .unwrap()
        .sum_all()
        .unwrap()
        .backward()
        .unwrap();
    let want: Vec<f32> = xv
        .iter()
        .map(|&v| {
            let s = 1.0 / (1.0 + (-v).exp());
            s * (1.0 + v * (1.0 - s))
        })
        .collect();
    assert_close(
        &values(grads.get(&x).expect("x has a gradient")),
        &want,
        "d sum(silu) / d x",
    );
}
