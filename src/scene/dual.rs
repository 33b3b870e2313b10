//! Forward-mode dual numbers with two partials: the exact Jacobian of a lens distortion
//! ([`crate::scene::Distortion::distort_jacobian`]) from the same code that evaluates it, so the
//! map and its derivative cannot drift apart.
//!
//! [`Real`] is the arithmetic the distortion formulas use; `f64` implements it with its own
//! operations (the value path is unchanged), [`Dual2`] carries `∂/∂x` and `∂/∂y` along.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// The arithmetic of the distortion formulas: ring operations, mixing with `f64` constants on
/// the right, and the few functions they call.
pub trait Real:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + Add<f64, Output = Self>
    + Sub<f64, Output = Self>
    + Mul<f64, Output = Self>
    + Div<f64, Output = Self>
{
    /// A constant.
    fn cst(v: f64) -> Self;
    /// The value (for branches).
    fn val(self) -> f64;
    fn sqrt(self) -> Self;
    fn atan(self) -> Self;
    fn tan(self) -> Self;
    /// `max(self, 0)`.
    fn max0(self) -> Self;
}

impl Real for f64 {
    #[inline]
    fn cst(v: f64) -> f64 {
        v
    }
    #[inline]
    fn val(self) -> f64 {
        self
    }
    #[inline]
    fn sqrt(self) -> f64 {
        f64::sqrt(self)
    }
    #[inline]
    fn atan(self) -> f64 {
        f64::atan(self)
    }
    #[inline]
    fn tan(self) -> f64 {
        f64::tan(self)
    }
    #[inline]
    fn max0(self) -> f64 {
        self.max(0.0)
    }
}

/// A value and its partial derivatives with respect to two inputs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dual2 {
    pub v: f64,
    pub d: [f64; 2],
}

impl Dual2 {
    /// Input number `i` (0 or 1) with value `v`.
    pub fn var(v: f64, i: usize) -> Dual2 {
        let mut d = [0.0; 2];
        d[i] = 1.0;
        Dual2 { v, d }
    }
    #[inline]
    fn chain(self, v: f64, dv: f64) -> Dual2 {
        Dual2 {
            v,
            d: [self.d[0] * dv, self.d[1] * dv],
        }
    }
}

impl Add for Dual2 {
    type Output = Dual2;
    #[inline]
    fn add(self, o: Dual2) -> Dual2 {
        Dual2 {
            v: self.v + o.v,
            d: [self.d[0] + o.d[0], self.d[1] + o.d[1]],
        }
    }
}
impl Sub for Dual2 {
    type Output = Dual2;
    #[inline]
    fn sub(self, o: Dual2) -> Dual2 {
        Dual2 {
            v: self.v - o.v,
            d: [self.d[0] - o.d[0], self.d[1] - o.d[1]],
        }
    }
}
impl Mul for Dual2 {
    type Output = Dual2;
    #[inline]
    fn mul(self, o: Dual2) -> Dual2 {
        Dual2 {
            v: self.v * o.v,
            d: [
                self.d[0] * o.v + self.v * o.d[0],
                self.d[1] * o.v + self.v * o.d[1],
            ],
        }
    }
}
impl Div for Dual2 {
    type Output = Dual2;
    #[inline]
    fn div(self, o: Dual2) -> Dual2 {
        let q = self.v / o.v;
        Dual2 {
            v: q,
            d: [
                (self.d[0] - q * o.d[0]) / o.v,
                (self.d[1] - q * o.d[1]) / o.v,
            ],
        }
    }
}
impl Neg for Dual2 {
    type Output = Dual2;
    #[inline]
    fn neg(self) -> Dual2 {
        Dual2 {
            v: -self.v,
            d: [-self.d[0], -self.d[1]],
        }
    }
}
impl Add<f64> for Dual2 {
    type Output = Dual2;
    #[inline]
    fn add(self, c: f64) -> Dual2 {
        Dual2 {
            v: self.v + c,
            d: self.d,
        }
    }
}
impl Sub<f64> for Dual2 {
    type Output = Dual2;
    #[inline]
    fn sub(self, c: f64) -> Dual2 {
        Dual2 {
            v: self.v - c,
            d: self.d,
        }
    }
}
impl Mul<f64> for Dual2 {
    type Output = Dual2;
    #[inline]
    fn mul(self, c: f64) -> Dual2 {
        Dual2 {
            v: self.v * c,
            d: [self.d[0] * c, self.d[1] * c],
        }
    }
}
impl Div<f64> for Dual2 {
    type Output = Dual2;
    #[inline]
    fn div(self, c: f64) -> Dual2 {
        Dual2 {
            v: self.v / c,
            d: [self.d[0] / c, self.d[1] / c],
        }
    }
}

impl Real for Dual2 {
    fn cst(v: f64) -> Dual2 {
        Dual2 { v, d: [0.0; 2] }
    }
    fn val(self) -> f64 {
        self.v
    }
    fn sqrt(self) -> Dual2 {
        let s = self.v.sqrt();
        self.chain(s, 0.5 / s)
    }
    fn atan(self) -> Dual2 {
        self.chain(self.v.atan(), 1.0 / (1.0 + self.v * self.v))
    }
    fn tan(self) -> Dual2 {
        let t = self.v.tan();
        self.chain(t, 1.0 + t * t)
    }
    fn max0(self) -> Dual2 {
        if self.v > 0.0 {
            self
        } else {
            Dual2::cst(0.0)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each rule against central differences of the f64 function.
    #[test]
    fn rules_match_finite_differences() {
        let f = |x: Dual2, y: Dual2| {
            let a = (x * y + 0.3).sqrt() / (y - x * 0.2);
            (a * x).atan() + (y * 0.4).tan() - a / 1.7 + (-x).max0()
        };
        let (x0, y0) = (0.7, 1.3);
        let d = f(Dual2::var(x0, 0), Dual2::var(y0, 1));
        let h = 1e-6;
        let fx = |x: f64, y: f64| f(Dual2::cst(x), Dual2::cst(y)).v;
        let gx = (fx(x0 + h, y0) - fx(x0 - h, y0)) / (2.0 * h);
        let gy = (fx(x0, y0 + h) - fx(x0, y0 - h)) / (2.0 * h);
        assert!((d.d[0] - gx).abs() < 1e-8, "{} vs {gx}", d.d[0]);
        assert!((d.d[1] - gy).abs() < 1e-8, "{} vs {gy}", d.d[1]);
        assert!(d.d[0].abs() > 0.01 && d.d[1].abs() > 0.01);
    }
}
