//! Run-time dispatch of hot element-wise kernels to AVX2.
//!
//! The workspace builds for baseline x86-64 (SSE2: four f32 lanes) so that its binaries run on
//! any x86-64 CPU; gemm picks AVX-512 at run time, but our own loops (activations, the gated FFN,
//! the depthwise convolution, softmax rows) stayed at four lanes. [`simd_dispatch!`] compiles a
//! kernel twice, once with AVX2 enabled, and picks at run time. Rust never contracts `a * b + c`
//! into an FMA on its own and every reduction here runs on fixed lanes, so both versions return
//! the same bits: results do not depend on the CPU.

/// True when the CPU has AVX2 (the detection is cached by std).
#[inline]
pub fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Defines `fn name(args) -> ret` that calls `kernel(args)` (an `#[inline(always)]` function)
/// compiled with AVX2 enabled when the CPU has it, and compiled for the baseline otherwise.
/// Arguments are plain identifiers with their types.
macro_rules! simd_dispatch {
    ($(#[$meta:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? = $kernel:path;) => {
        $(#[$meta])*
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                fn avx2($($arg: $ty),*) $(-> $ret)? {
                    $kernel($($arg),*)
                }
                if $crate::simd::has_avx2() {
                    // SAFETY: the CPU has AVX2, checked just above.
                    return unsafe { avx2($($arg),*) };
                }
            }
            $kernel($($arg),*)
        }
    };
}

pub(crate) use simd_dispatch;
