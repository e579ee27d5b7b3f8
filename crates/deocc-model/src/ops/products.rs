//! Matrix products on strided views (one task each) and on candle's pool (row blocks).

/// `dst (m x n) = lhs (m x k) * rhs (k x n)` through gemm's runtime-dispatched SIMD kernels, on
/// strided views given as (row stride, column stride); `dst` is contiguous, row-major. Single
/// threaded: the callers run one (sample, head) per task of the pool.
#[allow(clippy::too_many_arguments)]
pub(crate) fn small_matmul(
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
pub(crate) struct MatView<'a> {
    data: &'a [f32],
    row_stride: usize,
    col_stride: usize,
}

impl<'a> MatView<'a> {
    pub(crate) fn rows(data: &'a [f32], cols: usize) -> Self {
        Self {
            data,
            row_stride: cols,
            col_stride: 1,
        }
    }

    pub(crate) fn transposed(self) -> Self {
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
pub(crate) fn pool_gemm(
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
