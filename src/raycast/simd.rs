//! A minimal 4-lane f32 vector for the packet traversal: SSE/SSE2 on x86_64 (part of the
//! x86_64 baseline, so no runtime detection and no `target-cpu` flag is needed), plain arrays
//! elsewhere. Every lane operation is the IEEE single-precision operation of the scalar code
//! (no FMA contraction), so a lane computes bit-identically to the scalar path.
//!
//! `min`/`max` follow SSE semantics (`a < b ? a : b`); the traversal never feeds them NaNs.

#![allow(unused_unsafe)]

#[cfg(target_arch = "x86_64")]
mod imp {
    use std::arch::x86_64::*;

    /// Four f32 lanes.
    #[derive(Clone, Copy)]
    #[repr(transparent)]
    pub struct F4(__m128);

    /// A lane mask (all bits set = true).
    #[derive(Clone, Copy)]
    #[repr(transparent)]
    pub struct M4(__m128);

    impl F4 {
        #[inline(always)]
        pub fn splat(x: f32) -> F4 {
            unsafe { F4(_mm_set1_ps(x)) }
        }
        #[inline(always)]
        pub fn from_array(a: [f32; 4]) -> F4 {
            unsafe { F4(_mm_loadu_ps(a.as_ptr())) }
        }
        #[inline(always)]
        pub fn to_array(self) -> [f32; 4] {
            let mut a = [0.0f32; 4];
            unsafe { _mm_storeu_ps(a.as_mut_ptr(), self.0) };
            a
        }
        #[inline(always)]
        pub fn min(self, o: F4) -> F4 {
            unsafe { F4(_mm_min_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn max(self, o: F4) -> F4 {
            unsafe { F4(_mm_max_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn lt(self, o: F4) -> M4 {
            unsafe { M4(_mm_cmplt_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn le(self, o: F4) -> M4 {
            unsafe { M4(_mm_cmple_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn gt(self, o: F4) -> M4 {
            unsafe { M4(_mm_cmpgt_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn eq(self, o: F4) -> M4 {
            unsafe { M4(_mm_cmpeq_ps(self.0, o.0)) }
        }
        /// `m ? a : b` per lane.
        #[inline(always)]
        pub fn select(m: M4, a: F4, b: F4) -> F4 {
            unsafe { F4(_mm_or_ps(_mm_and_ps(m.0, a.0), _mm_andnot_ps(m.0, b.0))) }
        }
        /// Smallest lane.
        #[inline(always)]
        pub fn hmin(self) -> f32 {
            unsafe {
                let a = _mm_min_ps(self.0, _mm_movehl_ps(self.0, self.0));
                let b = _mm_min_ss(a, _mm_shuffle_ps(a, a, 1));
                _mm_cvtss_f32(b)
            }
        }
        /// Largest lane.
        #[inline(always)]
        pub fn hmax(self) -> f32 {
            unsafe {
                let a = _mm_max_ps(self.0, _mm_movehl_ps(self.0, self.0));
                let b = _mm_max_ss(a, _mm_shuffle_ps(a, a, 1));
                _mm_cvtss_f32(b)
            }
        }
    }

    impl M4 {
        #[inline(always)]
        pub fn from_bits(bits: u32) -> M4 {
            let f = |i: u32| if bits >> i & 1 != 0 { -1i32 } else { 0 };
            unsafe { M4(_mm_castsi128_ps(_mm_setr_epi32(f(0), f(1), f(2), f(3)))) }
        }
        /// Bit i set when lane i is true.
        #[inline(always)]
        pub fn bits(self) -> u32 {
            unsafe { _mm_movemask_ps(self.0) as u32 }
        }
        #[inline(always)]
        pub fn and(self, o: M4) -> M4 {
            unsafe { M4(_mm_and_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn or(self, o: M4) -> M4 {
            unsafe { M4(_mm_or_ps(self.0, o.0)) }
        }
    }

    impl std::ops::Add for F4 {
        type Output = F4;
        #[inline(always)]
        fn add(self, o: F4) -> F4 {
            unsafe { F4(_mm_add_ps(self.0, o.0)) }
        }
    }
    impl std::ops::Sub for F4 {
        type Output = F4;
        #[inline(always)]
        fn sub(self, o: F4) -> F4 {
            unsafe { F4(_mm_sub_ps(self.0, o.0)) }
        }
    }
    impl std::ops::Mul for F4 {
        type Output = F4;
        #[inline(always)]
        fn mul(self, o: F4) -> F4 {
            unsafe { F4(_mm_mul_ps(self.0, o.0)) }
        }
    }
    impl std::ops::Div for F4 {
        type Output = F4;
        #[inline(always)]
        fn div(self, o: F4) -> F4 {
            unsafe { F4(_mm_div_ps(self.0, o.0)) }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod imp {
    /// Four f32 lanes (portable fallback).
    #[derive(Clone, Copy)]
    pub struct F4([f32; 4]);

    /// A lane mask.
    #[derive(Clone, Copy)]
    pub struct M4([bool; 4]);

    #[inline(always)]
    fn map2(a: [f32; 4], b: [f32; 4], f: impl Fn(f32, f32) -> f32) -> F4 {
        F4([f(a[0], b[0]), f(a[1], b[1]), f(a[2], b[2]), f(a[3], b[3])])
    }
    #[inline(always)]
    fn cmp(a: [f32; 4], b: [f32; 4], f: impl Fn(f32, f32) -> bool) -> M4 {
        M4([f(a[0], b[0]), f(a[1], b[1]), f(a[2], b[2]), f(a[3], b[3])])
    }

    impl F4 {
        #[inline(always)]
        pub fn splat(x: f32) -> F4 {
            F4([x; 4])
        }
        #[inline(always)]
        pub fn from_array(a: [f32; 4]) -> F4 {
            F4(a)
        }
        #[inline(always)]
        pub fn to_array(self) -> [f32; 4] {
            self.0
        }
        #[inline(always)]
        pub fn min(self, o: F4) -> F4 {
            map2(self.0, o.0, |a, b| if a < b { a } else { b })
        }
        #[inline(always)]
        pub fn max(self, o: F4) -> F4 {
            map2(self.0, o.0, |a, b| if a > b { a } else { b })
        }
        #[inline(always)]
        pub fn lt(self, o: F4) -> M4 {
            cmp(self.0, o.0, |a, b| a < b)
        }
        #[inline(always)]
        pub fn le(self, o: F4) -> M4 {
            cmp(self.0, o.0, |a, b| a <= b)
        }
        #[inline(always)]
        pub fn gt(self, o: F4) -> M4 {
            cmp(self.0, o.0, |a, b| a > b)
        }
        #[inline(always)]
        pub fn eq(self, o: F4) -> M4 {
            cmp(self.0, o.0, |a, b| a == b)
        }
        #[inline(always)]
        pub fn select(m: M4, a: F4, b: F4) -> F4 {
            F4(std::array::from_fn(
                |i| if m.0[i] { a.0[i] } else { b.0[i] },
            ))
        }
        #[inline(always)]
        pub fn hmin(self) -> f32 {
            let m = |a: f32, b: f32| if a < b { a } else { b };
            m(m(self.0[0], self.0[2]), m(self.0[1], self.0[3]))
        }
        #[inline(always)]
        pub fn hmax(self) -> f32 {
            let m = |a: f32, b: f32| if a > b { a } else { b };
            m(m(self.0[0], self.0[2]), m(self.0[1], self.0[3]))
        }
    }

    impl M4 {
        #[inline(always)]
        pub fn from_bits(bits: u32) -> M4 {
            M4(std::array::from_fn(|i| bits >> i & 1 != 0))
        }
        #[inline(always)]
        pub fn bits(self) -> u32 {
            (0..4).map(|i| (self.0[i] as u32) << i).sum()
        }
        #[inline(always)]
        pub fn and(self, o: M4) -> M4 {
            M4(std::array::from_fn(|i| self.0[i] && o.0[i]))
        }
        #[inline(always)]
        pub fn or(self, o: M4) -> M4 {
            M4(std::array::from_fn(|i| self.0[i] || o.0[i]))
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

pub use imp::F4;
#[allow(unused_imports)]
pub use imp::M4;
