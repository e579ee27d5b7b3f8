//! SiLU, GELU and the SiLU gate with hand-written backward passes on a branch-free exp.

use super::*;

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
pub(crate) fn sigmoid(z: f32) -> f32 {
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

pub(crate) const GELU_C: f32 = 0.797_884_6; // sqrt(2 / pi)
pub(crate) const GELU_A: f32 = 0.044_715;

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
    pub(crate) fn activation_values(kind: Activation, src: &[f32], out: &mut [f32]) = activation_values_kernel;
}

#[inline(always)]
pub(crate) fn activation_values_kernel(kind: Activation, src: &[f32], out: &mut [f32]) {
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
    pub(crate) fn activation_gradients(kind: Activation, xs: &[f32], grad: &[f32], out: &mut [f32])
        = activation_gradients_kernel;
}

#[inline(always)]
pub(crate) fn activation_gradients_kernel(
    kind: Activation,
    xs: &[f32],
    grad: &[f32],
    out: &mut [f32],
) {
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
pub(crate) const ACTIVATION_CHUNK: usize = 16 * 1024;

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
pub(crate) struct ActivationBackward(Activation);

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

pub(crate) struct SiluGate;

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
    pub(crate) fn silu_gate_rows(src: &[f32], out: &mut [f32], h: usize) = silu_gate_rows_kernel;
}

#[inline(always)]
pub(crate) fn silu_gate_rows_kernel(src: &[f32], out: &mut [f32], h: usize) {
    for (orow, row) in out.chunks_exact_mut(h).zip(src.chunks_exact(2 * h)) {
        let (v, gate) = row.split_at(h);
        for ((ov, vv), gv) in orow.iter_mut().zip(v).zip(gate) {
            *ov = vv * gv * sigmoid(*gv);
        }
    }
}

simd_dispatch! {
    /// The gradient rows `[dv | dgate]` of [`silu_gate_rows`] from the output gradient's rows.
    pub(crate) fn silu_gate_gradient_rows(src: &[f32], grad: &[f32], out: &mut [f32], h: usize)
        = silu_gate_gradient_rows_kernel;
}

#[inline(always)]
pub(crate) fn silu_gate_gradient_rows_kernel(src: &[f32], grad: &[f32], out: &mut [f32], h: usize) {
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
pub(crate) struct SiluGateBackward;

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
