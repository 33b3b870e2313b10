//! Memory hints, none of which changes a result:
//! - large arrays on transparent huge pages (Linux): the hash tables, their gradients and Adam
//!   state are hundreds of MB touched at random entries every step, and the sample arrays are
//!   written once in parallel. With 4 KiB pages the first costs a TLB miss per access and the
//!   second serialises page faults on the address-space lock (a no-op elsewhere or when the kernel
//!   refuses);
//! - [`prefetch`] / [`prefetch_l2`]: start loading a cache line that a loop will need a few
//!   iterations later (scattered table entries whose addresses are known ahead: the grids'
//!   corners, Adam's touched entries). A core has few L1 miss buffers (a `prefetcht0` waits for
//!   one when they are all busy), and more outstanding misses to L2: prefetching far ahead into
//!   L2 keeps many more lines in flight, which is what the random table accesses wait on
//!   (`docs/performance.md`, "Prefetching into L2").

use rayon::prelude::*;
use std::mem::MaybeUninit;

/// Ask the CPU to start loading the cache line at `p` into all cache levels (x86-64
/// `prefetcht0`; a no-op elsewhere). Never faults, whatever the address.
#[inline(always)]
pub fn prefetch<T>(p: *const T) {
    prefetch_into::<false, T>(p)
}

/// Ask the CPU to start loading the cache line at `p` into L2 (x86-64 `prefetcht1`; a no-op
/// elsewhere): for lines needed many iterations later, without taking an L1 miss buffer while
/// they arrive. Never faults, whatever the address.
#[inline(always)]
pub fn prefetch_l2<T>(p: *const T) {
    prefetch_into::<true, T>(p)
}

/// `prefetcht1` (into L2) if `L2`, else `prefetcht0` (into all levels).
#[inline(always)]
fn prefetch_into<const L2: bool, T>(p: *const T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch never faults, whatever the address.
    unsafe {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0, _MM_HINT_T1};
        if L2 {
            _mm_prefetch::<_MM_HINT_T1>(p as *const i8)
        } else {
            _mm_prefetch::<_MM_HINT_T0>(p as *const i8)
        }
    };
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Ask Linux for transparent huge pages on a vector's untouched spare capacity when it spans
/// several of them (call before the elements are first written: the hint only changes how
/// future page faults are served).
pub fn advise<T>(v: &mut Vec<T>) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let spare = v.spare_capacity_mut();
        let bytes = std::mem::size_of_val(spare);
        if bytes < 2 * HUGE {
            return;
        }
        let start = spare.as_mut_ptr() as usize;
        let (lo, hi) = (start.next_multiple_of(HUGE), (start + bytes) / HUGE * HUGE);
        if hi > lo {
            // SAFETY: [lo, hi) lies inside the vector's allocation; MADV_HUGEPAGE changes no
            // contents and no mapping, only how future page faults are served.
            unsafe {
                libc::madvise(lo as *mut libc::c_void, hi - lo, libc::MADV_HUGEPAGE);
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = v;
}

/// Elements per parallel piece when [`filled`] and [`copied`] write a new vector.
const FILL_CHUNK: usize = 1 << 16;

/// `vec![value; n]` on huge pages, written in parallel pieces: a fresh page is faulted in (and
/// zeroed by the kernel) on the thread that first writes it, so all threads share that cost
/// (the Adam state of `small`: a short `xscale train` took less wall time, in alternating A/B
/// runs; the faults of fresh huge pages are slow on virtual machines; docs/changelog.md).
pub fn filled<T: Copy + Send + Sync>(n: usize, value: T) -> Vec<T> {
    built(n, |_, piece| {
        for x in piece {
            x.write(value);
        }
    })
}

/// A copy of `src` on huge pages, written in parallel pieces (as [`filled`]).
pub fn copied<T: Copy + Send + Sync>(src: &[T]) -> Vec<T> {
    built(src.len(), |at, piece| {
        for (x, &s) in piece.iter_mut().zip(&src[at..]) {
            x.write(s);
        }
    })
}

/// A vector of `n` elements on huge pages, written in parallel pieces of [`FILL_CHUNK`]:
/// `fill(at, piece)` must write every element of `piece`, elements `at..at + piece.len()`.
pub fn built<T: Send>(n: usize, fill: impl Fn(usize, &mut [MaybeUninit<T>]) + Sync) -> Vec<T> {
    let mut v = Vec::with_capacity(n);
    advise(&mut v);
    v.spare_capacity_mut()[..n]
        .par_chunks_mut(FILL_CHUNK)
        .enumerate()
        .for_each(|(ci, piece)| fill(ci * FILL_CHUNK, piece));
    // SAFETY: the pieces tile ..n and `fill` writes every element of its piece (both callers
    // above do: a loop over the whole piece).
    unsafe { v.set_len(n) };
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filled_and_copied_write_every_element() {
        for n in [0, 1, FILL_CHUNK - 1, FILL_CHUNK, 3 * FILL_CHUNK + 17] {
            assert_eq!(filled(n, 7u32), vec![7u32; n], "filled {n}");
            let src: Vec<u64> = (0..n as u64).map(|i| i * 3 + 1).collect();
            assert_eq!(copied(&src), src, "copied {n}");
        }
    }
}
