//! Linear self-attention from the fused projection, and multi-head softmax cross-attention.

use super::*;

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

pub(crate) struct LinearAttentionQkv {
    heads: usize,
    eps: f32,
}

/// Per-(sample, head) outputs (task = sample * heads + head, each N x hd) merged into
/// (B, N, heads * hd), heads side by side.
pub(crate) fn merge_heads(
    parts: &[Vec<f32>],
    b: usize,
    n: usize,
    heads: usize,
    hd: usize,
) -> Vec<f32> {
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
pub(crate) struct HeadTerms {
    rq: Vec<f32>,
    rk: Vec<f32>,
    v1: Vec<f32>,
    kv: Vec<f32>,
    /// relu(q) kv: (N x (hd + 1)), numerators and normaliser.
    o: Vec<f32>,
}

pub(crate) fn head_terms(qkv: &[f32], n: usize, dm: usize, hd: usize, off: usize) -> HeadTerms {
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
pub(crate) struct LinearAttentionQkvBackward {
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

pub(crate) struct CrossAttention {
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
pub(crate) fn cross_probabilities(
    q: &[f32],
    kv: &[f32],
    n: usize,
    m: usize,
    d: usize,
    hd: usize,
) -> Vec<f32> {
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
pub(crate) fn lane_sum(xs: &[f32]) -> f32 {
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
    pub(crate) fn lane_dot(a: &[f32], b: &[f32]) -> f32 = lane_dot_kernel;
}

#[inline(always)]
pub(crate) fn lane_dot_kernel(a: &[f32], b: &[f32]) -> f32 {
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
    pub(crate) fn softmax_row(row: &mut [f32], scale: f32) = softmax_row_kernel;
}

#[inline(always)]
pub(crate) fn softmax_row_kernel(row: &mut [f32], scale: f32) {
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
pub(crate) struct CrossAttentionBackward {
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
