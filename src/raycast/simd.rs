//! Lane vectors for the packet traversal: [`F4`] (SSE/SSE2 on x86_64 — part of the x86_64
//! baseline, no detection needed — plain arrays elsewhere) and [`F8`] (AVX, x86_64 only, used
//! behind a runtime `is_x86_feature_detected!("avx")` check; never `target-cpu=native`).
//!
//! Every lane operation is the IEEE single-precision operation of the scalar code (no FMA
//! contraction, Rust never contracts), so a lane computes bit-identically to the scalar path
//! and F4 and F8 packets give identical results. `min`/`max` follow SSE semantics
//! (`a < b ? a : b`); the traversal never feeds them NaNs.

// The SSE intrinsics used here are safe to call on Rust >= 1.87 where the feature is enabled
// statically, but still `unsafe` on older toolchains and for the AVX ones; every block carries a
// `// SAFETY:` line and the lint for blocks that are no longer needed is silenced.
#![allow(unused_unsafe)]

use std::ops::{Add, Div, Mul, Sub};

/// A vector of `N` f32 lanes with a lane mask type.
pub trait Lanes:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Div<Output = Self>
{
    const N: usize;
    type M: Mask;
    fn splat(x: f32) -> Self;
    /// Load `N` values (`a.len() >= N`).
    fn load(a: &[f32]) -> Self;
    /// Store `N` values (`out.len() >= N`).
    fn store(self, out: &mut [f32]);
    fn min(self, o: Self) -> Self;
    fn max(self, o: Self) -> Self;
    fn lt(self, o: Self) -> Self::M;
    fn le(self, o: Self) -> Self::M;
    fn gt(self, o: Self) -> Self::M;
    fn eq(self, o: Self) -> Self::M;
    fn hmin(self) -> f32;
    fn hmax(self) -> f32;
    /// `|x|` per lane (clears the sign bit).
    fn abs(self) -> Self;
    /// Bit i set when lane i has its sign bit set (also for -0.0 and negative NaNs).
    fn sign_bits(self) -> u32;
}

/// A lane mask.
pub trait Mask: Copy {
    /// Bit i set when lane i is true.
    fn bits(self) -> u32;
    fn and(self, o: Self) -> Self;
    fn or(self, o: Self) -> Self;
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Lanes, Mask};
    use std::arch::x86_64::*;

    /// Four f32 lanes (SSE).
    #[derive(Clone, Copy)]
    #[repr(transparent)]
    pub struct F4(__m128);

    #[derive(Clone, Copy)]
    #[repr(transparent)]
    pub struct M4(__m128);

    impl Mask for M4 {
        #[inline(always)]
        fn bits(self) -> u32 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { _mm_movemask_ps(self.0) as u32 }
        }
        #[inline(always)]
        fn and(self, o: M4) -> M4 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { M4(_mm_and_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn or(self, o: M4) -> M4 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { M4(_mm_or_ps(self.0, o.0)) }
        }
    }

    impl Lanes for F4 {
        const N: usize = 4;
        type M = M4;
        #[inline(always)]
        fn splat(x: f32) -> F4 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { F4(_mm_set1_ps(x)) }
        }
        #[inline(always)]
        fn load(a: &[f32]) -> F4 {
            assert!(a.len() >= 4);
            // SAFETY: SSE is in the x86_64 baseline; the assert above guarantees 4 readable f32 at the (unaligned) pointer.
            unsafe { F4(_mm_loadu_ps(a.as_ptr())) }
        }
        #[inline(always)]
        fn store(self, out: &mut [f32]) {
            assert!(out.len() >= 4);
            // SAFETY: SSE is in the x86_64 baseline; the assert above guarantees 4 writable f32 at the (unaligned) pointer.
            unsafe { _mm_storeu_ps(out.as_mut_ptr(), self.0) }
        }
        #[inline(always)]
        fn min(self, o: F4) -> F4 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { F4(_mm_min_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn max(self, o: F4) -> F4 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { F4(_mm_max_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn lt(self, o: F4) -> M4 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { M4(_mm_cmplt_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn le(self, o: F4) -> M4 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { M4(_mm_cmple_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn gt(self, o: F4) -> M4 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { M4(_mm_cmpgt_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn eq(self, o: F4) -> M4 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { M4(_mm_cmpeq_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn hmin(self) -> f32 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe {
                let a = _mm_min_ps(self.0, _mm_movehl_ps(self.0, self.0));
                let b = _mm_min_ss(a, _mm_shuffle_ps(a, a, 1));
                _mm_cvtss_f32(b)
            }
        }
        #[inline(always)]
        fn hmax(self) -> f32 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe {
                let a = _mm_max_ps(self.0, _mm_movehl_ps(self.0, self.0));
                let b = _mm_max_ss(a, _mm_shuffle_ps(a, a, 1));
                _mm_cvtss_f32(b)
            }
        }
        #[inline(always)]
        fn abs(self) -> F4 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { F4(_mm_andnot_ps(_mm_set1_ps(-0.0), self.0)) }
        }
        #[inline(always)]
        fn sign_bits(self) -> u32 {
            // SAFETY: SSE/SSE2 are in the x86_64 baseline, so the intrinsic is always available; it touches only register values.
            unsafe { _mm_movemask_ps(self.0) as u32 }
        }
    }

    /// Eight f32 lanes (AVX).
    ///
    /// Invariant (what makes every `unsafe` block below sound): an `F8` is only created and used
    /// inside code compiled with `#[target_feature(enable = "avx")]` that is reached only after
    /// `is_x86_feature_detected!("avx")` returned true (`raycast::bvh` dispatches that way).
    /// `splat` and `load` — the only constructors — check it in debug builds.
    #[derive(Clone, Copy)]
    #[repr(transparent)]
    pub struct F8(__m256);

    #[derive(Clone, Copy)]
    #[repr(transparent)]
    pub struct M8(__m256);

    impl Mask for M8 {
        #[inline(always)]
        fn bits(self) -> u32 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { _mm256_movemask_ps(self.0) as u32 }
        }
        #[inline(always)]
        fn and(self, o: M8) -> M8 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { M8(_mm256_and_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn or(self, o: M8) -> M8 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { M8(_mm256_or_ps(self.0, o.0)) }
        }
    }

    impl Lanes for F8 {
        const N: usize = 8;
        type M = M8;
        #[inline(always)]
        fn splat(x: f32) -> F8 {
            debug_assert!(is_x86_feature_detected!("avx"));
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { F8(_mm256_set1_ps(x)) }
        }
        #[inline(always)]
        fn load(a: &[f32]) -> F8 {
            debug_assert!(is_x86_feature_detected!("avx"));
            assert!(a.len() >= 8);
            // SAFETY: AVX is available by the F8 invariant (type doc, debug-asserted in splat/load); the assert above guarantees 8 readable f32.
            unsafe { F8(_mm256_loadu_ps(a.as_ptr())) }
        }
        #[inline(always)]
        fn store(self, out: &mut [f32]) {
            assert!(out.len() >= 8);
            // SAFETY: AVX is available by the F8 invariant (type doc); the assert above guarantees 8 writable f32.
            unsafe { _mm256_storeu_ps(out.as_mut_ptr(), self.0) }
        }
        #[inline(always)]
        fn min(self, o: F8) -> F8 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { F8(_mm256_min_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn max(self, o: F8) -> F8 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { F8(_mm256_max_ps(self.0, o.0)) }
        }
        #[inline(always)]
        fn lt(self, o: F8) -> M8 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { M8(_mm256_cmp_ps::<_CMP_LT_OQ>(self.0, o.0)) }
        }
        #[inline(always)]
        fn le(self, o: F8) -> M8 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { M8(_mm256_cmp_ps::<_CMP_LE_OQ>(self.0, o.0)) }
        }
        #[inline(always)]
        fn gt(self, o: F8) -> M8 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { M8(_mm256_cmp_ps::<_CMP_GT_OQ>(self.0, o.0)) }
        }
        #[inline(always)]
        fn eq(self, o: F8) -> M8 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { M8(_mm256_cmp_ps::<_CMP_EQ_OQ>(self.0, o.0)) }
        }
        #[inline(always)]
        fn hmin(self) -> f32 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe {
                let h = _mm_min_ps(
                    _mm256_castps256_ps128(self.0),
                    _mm256_extractf128_ps::<1>(self.0),
                );
                let a = _mm_min_ps(h, _mm_movehl_ps(h, h));
                _mm_cvtss_f32(_mm_min_ss(a, _mm_shuffle_ps(a, a, 1)))
            }
        }
        #[inline(always)]
        fn hmax(self) -> f32 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe {
                let h = _mm_max_ps(
                    _mm256_castps256_ps128(self.0),
                    _mm256_extractf128_ps::<1>(self.0),
                );
                let a = _mm_max_ps(h, _mm_movehl_ps(h, h));
                _mm_cvtss_f32(_mm_max_ss(a, _mm_shuffle_ps(a, a, 1)))
            }
        }
        #[inline(always)]
        fn abs(self) -> F8 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { F8(_mm256_andnot_ps(_mm256_set1_ps(-0.0), self.0)) }
        }
        #[inline(always)]
        fn sign_bits(self) -> u32 {
            // SAFETY: AVX is available by the F8 invariant (an F8 exists only after is_x86_feature_detected!("avx")); registers only.
            unsafe { _mm256_movemask_ps(self.0) as u32 }
        }
    }

    macro_rules! ops {
        ($t:ident, $add:ident, $sub:ident, $mul:ident, $div:ident) => {
            impl std::ops::Add for $t {
                type Output = $t;
                #[inline(always)]
                fn add(self, o: $t) -> $t {
                    // SAFETY: F4: SSE is baseline; F8: AVX by its invariant. Register arithmetic only, no memory access.
                    unsafe { $t($add(self.0, o.0)) }
                }
            }
            impl std::ops::Sub for $t {
                type Output = $t;
                #[inline(always)]
                fn sub(self, o: $t) -> $t {
                    // SAFETY: F4: SSE is baseline; F8: AVX by its invariant. Register arithmetic only, no memory access.
                    unsafe { $t($sub(self.0, o.0)) }
                }
            }
            impl std::ops::Mul for $t {
                type Output = $t;
                #[inline(always)]
                fn mul(self, o: $t) -> $t {
                    // SAFETY: F4: SSE is baseline; F8: AVX by its invariant. Register arithmetic only, no memory access.
                    unsafe { $t($mul(self.0, o.0)) }
                }
            }
            impl std::ops::Div for $t {
                type Output = $t;
                #[inline(always)]
                fn div(self, o: $t) -> $t {
                    // SAFETY: F4: SSE is baseline; F8: AVX by its invariant. Register arithmetic only, no memory access.
                    unsafe { $t($div(self.0, o.0)) }
                }
            }
        };
    }
    ops!(F4, _mm_add_ps, _mm_sub_ps, _mm_mul_ps, _mm_div_ps);
    ops!(
        F8,
        _mm256_add_ps,
        _mm256_sub_ps,
        _mm256_mul_ps,
        _mm256_div_ps
    );
}

#[cfg(not(target_arch = "x86_64"))]
mod portable {
    use super::{Lanes, Mask};

    /// Four f32 lanes (portable fallback).
    #[derive(Clone, Copy)]
    pub struct F4([f32; 4]);

    #[derive(Clone, Copy)]
    pub struct M4([bool; 4]);

    impl Mask for M4 {
        fn bits(self) -> u32 {
            (0..4).map(|i| (self.0[i] as u32) << i).sum()
        }
        fn and(self, o: M4) -> M4 {
            M4(std::array::from_fn(|i| self.0[i] && o.0[i]))
        }
        fn or(self, o: M4) -> M4 {
            M4(std::array::from_fn(|i| self.0[i] || o.0[i]))
        }
    }

    fn map2(a: [f32; 4], b: [f32; 4], f: impl Fn(f32, f32) -> f32) -> F4 {
        F4(std::array::from_fn(|i| f(a[i], b[i])))
    }
    fn cmp(a: [f32; 4], b: [f32; 4], f: impl Fn(f32, f32) -> bool) -> M4 {
        M4(std::array::from_fn(|i| f(a[i], b[i])))
    }

    impl Lanes for F4 {
        const N: usize = 4;
        type M = M4;
        fn splat(x: f32) -> F4 {
            F4([x; 4])
        }
        fn load(a: &[f32]) -> F4 {
            F4([a[0], a[1], a[2], a[3]])
        }
        fn store(self, out: &mut [f32]) {
            out[..4].copy_from_slice(&self.0);
        }
        fn min(self, o: F4) -> F4 {
            map2(self.0, o.0, |a, b| if a < b { a } else { b })
        }
        fn max(self, o: F4) -> F4 {
            map2(self.0, o.0, |a, b| if a > b { a } else { b })
        }
        fn lt(self, o: F4) -> M4 {
            cmp(self.0, o.0, |a, b| a < b)
        }
        fn le(self, o: F4) -> M4 {
            cmp(self.0, o.0, |a, b| a <= b)
        }
        fn gt(self, o: F4) -> M4 {
            cmp(self.0, o.0, |a, b| a > b)
        }
        fn eq(self, o: F4) -> M4 {
            cmp(self.0, o.0, |a, b| a == b)
        }
        fn hmin(self) -> f32 {
            let m = |a: f32, b: f32| if a < b { a } else { b };
            m(m(self.0[0], self.0[2]), m(self.0[1], self.0[3]))
        }
        fn hmax(self) -> f32 {
            let m = |a: f32, b: f32| if a > b { a } else { b };
            m(m(self.0[0], self.0[2]), m(self.0[1], self.0[3]))
        }
        fn abs(self) -> F4 {
            F4(self.0.map(f32::abs))
        }
        fn sign_bits(self) -> u32 {
            (0..4)
                .map(|i| (self.0[i].is_sign_negative() as u32) << i)
                .sum()
        }
    }

    impl std::ops::Add for F4 {
        type Output = F4;
        fn add(self, o: F4) -> F4 {
            map2(self.0, o.0, |a, b| a + b)
        }
    }
    impl std::ops::Sub for F4 {
        type Output = F4;
        fn sub(self, o: F4) -> F4 {
            map2(self.0, o.0, |a, b| a - b)
        }
    }
    impl std::ops::Mul for F4 {
        type Output = F4;
        fn mul(self, o: F4) -> F4 {
            map2(self.0, o.0, |a, b| a * b)
        }
    }
    impl std::ops::Div for F4 {
        type Output = F4;
        fn div(self, o: F4) -> F4 {
            map2(self.0, o.0, |a, b| a / b)
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
pub use portable::F4;
#[cfg(target_arch = "x86_64")]
pub use x86::{F4, F8};
