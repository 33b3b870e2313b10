"""Exact fused multiply-add emulation for the xscale reference (SPEC §4.2).

Owns: `fma_f32` (vectorised, bit-exact IEEE-754 binary32 fma with round-to-nearest-even) and `fma_f64`
(element-wise, bit-exact binary64 fma). Python 3.11 has no `math.fma` and NumPy / PyTorch expose no fused
multiply-add, so both are built here from operations whose exactness can be argued:

fma_f32(a, b, c) = RN32(a*b + c), a, b, c float32:
  1. a*b is computed in float64 and is EXACT: each significand has 24 bits, the product has at most 48 <= 53,
     and the exponent range of float64 (down to 2^-1074) covers the smallest product 2^-149 * 2^-149 = 2^-298.
  2. s = RN64(a*b + c) and its error e = (a*b + c) - s are obtained with Knuth's TwoSum, which is exact in
     round-to-nearest binary64 arithmetic barring overflow (float32 inputs cannot overflow float64 here).
  3. s is turned into RO64(a*b + c), the exact sum rounded *to odd*: if e != 0 and s has an even last
     significand bit, s is replaced by its neighbour in the direction of e (the two float64 numbers bracketing
     the exact value have consecutive bit patterns, so exactly one of them is odd).
  4. The result is RN32(RO64(a*b + c)) (NumPy's float64 -> float32 cast rounds to nearest even).
  Boldo & Melquiond (2008), "Emulation of FMA and correctly rounded sums: proved algorithms using rounding to
  odd", IEEE Trans. Computers 57(4), Theorem 1: rounding to odd in precision p followed by rounding to nearest in
  precision q is the correct rounding to nearest in precision q whenever p >= q + 2. Here p = 53 >= 24 + 2 = 26
  (in the float32 subnormal range q is smaller still, and float64 is normal there, so the condition holds).
  The naive RN32(RN64(a*b + c)) is NOT always correct (double rounding); the tests exhibit such cases and check
  this function against the C library's `fmaf` (correctly rounded in glibc) via ctypes.

fma_f64(a, b, c) = RN64(a*b + c): computed exactly as a ratio of Python integers (every finite float is n / 2^k),
  then rounded once by CPython's `int / int` true division, which is correctly rounded to nearest even.
  Pure Python (~1 us per element) but obviously exact; the batch sizes of the oracle are small.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np


def fma_f32(a, b, c) -> np.ndarray:
    """Bit-exact float32 fused multiply-add, element-wise with NumPy broadcasting. Inputs are cast to float32
    first (a no-op for float32 inputs)."""
    a64 = np.asarray(a, dtype=np.float32).astype(np.float64)
    b64 = np.asarray(b, dtype=np.float32).astype(np.float64)
    c64 = np.asarray(c, dtype=np.float32).astype(np.float64)
    prod = a64 * b64  # exact (step 1)
    with np.errstate(invalid="ignore", over="ignore"):
        s = prod + c64  # RN64 (step 2: TwoSum)
        bb = s - prod
        e = (prod - (s - bb)) + (c64 - bb)
        s = np.asarray(s)
        e = np.asarray(e)
        odd = (s.view(np.uint64) & np.uint64(1)) == np.uint64(1)
        fix = (e != 0) & ~odd & np.isfinite(s) & np.isfinite(e)
        toward = np.where(e > 0, np.inf, -np.inf)
        s_odd = np.where(fix, np.nextafter(s, toward), s)  # step 3: round to odd
    return s_odd.astype(np.float32)  # step 4: RN32


def fma_f64_scalar(a: float, b: float, c: float) -> float:
    """Bit-exact float64 fma of three finite float64 values: the exact value as a ratio of Python integers
    (every finite float is n/d with d a power of two: float.as_integer_ratio), then one correctly rounded
    int / int true division (CPython's long true division rounds correctly, half to even)."""
    na, da = a.as_integer_ratio()
    nb, db = b.as_integer_ratio()
    nc, dc = c.as_integer_ratio()
    return (na * nb * dc + nc * da * db) / (da * db * dc)


def fma_f64_fraction(a: float, b: float, c: float) -> float:
    """Same with fractions.Fraction (slower); kept as a cross-check for the tests."""
    return float(Fraction(a) * Fraction(b) + Fraction(c))


def fma_f64(a, b, c) -> np.ndarray:
    """Element-wise bit-exact float64 fma with NumPy broadcasting (pure-Python loop)."""
    a, b, c = np.broadcast_arrays(
        np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64), np.asarray(c, dtype=np.float64)
    )
    out = np.empty(a.shape, dtype=np.float64)
    fa, fb, fc, fo = a.reshape(-1), b.reshape(-1), c.reshape(-1), out.reshape(-1)
    for i in range(fo.size):
        fo[i] = fma_f64_scalar(float(fa[i]), float(fb[i]), float(fc[i]))
    return out
