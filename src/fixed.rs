//! Fixed point: `Fx<F>`, a signed Q(63-F).F number in an `i64` with an `i128` intermediate, for FPU-less chips and
//! bit-exact reproducibility. It implements [`crate::Scalar`], so the biquad and the discrete RLS run on it from
//! the same generic code as on `f32`/`f64`.
//!
//! ## Why a type of our own
//! The arithmetic needed is four operations with one rounding rule and one overflow rule, about sixty lines. The
//! `fixed` crate's `FixedI64<U32>` would do the same multiply, but its operators panic on overflow in debug builds
//! and wrap in release, where a control loop needs saturation that behaves the same in every build; here every
//! result is rounded to nearest (ties away from zero) and saturates at the range ends. Nothing is
//! platform-dependent, so a host run and a Cortex-M run are bit-identical.
//!
//! ## The format used: [`Q32`] = Q31.32
//! Range `+-2^31` (+-2.1e9), resolution `2^-32` (2.3e-10), rounding error at most `2^-33` (1.2e-10) per operation.
//! It holds, with room, every quantity of the ARX RLS on the stage: signals (`u` within +-10 V, pre-filtered
//! `y` within +-50 um, values of order 1), ARX coefficients (`|A1| < 2`, `B` ~ 1e-2), the UD factors (`D` bounded by
//! the windup bound, 1e3; `|U_ij|` of order 10), and `alpha = lambda1/lambda2 + phi'F phi` (at most
//! `1e3 * 4 * 100^2 = 4e7`). The smallest `D` entries (~1e-6 once converged) keep 12 significant bits; their error
//! only perturbs the gain, not the least-squares fixed point the estimate converges to. Biquad coefficients
//! (`|a_i| < 2`) and states take the same format: a DF1 section with the accumulator this wide rounds each product
//! once, so its output error is at most `5 * 2^-33` per sample times the noise gain of `1/A(z)`.

use crate::Scalar;
use core::cmp::Ordering;
use core::ops::{Add, AddAssign, Div, Mul, MulAssign, Neg, Sub, SubAssign};
use num_traits::{One, Zero};

/// A fixed-point number with `F` fractional bits in an `i64`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub struct Fx<const F: u32>(pub i64);

/// Q31.32, the format the fixed-point kernels use.
pub type Q32 = Fx<32>;

impl<const F: u32> Fx<F> {
    /// `2^F`.
    const ONE: i64 = 1 << F;

    #[inline(always)]
    fn saturate(x: i128) -> Self {
        Fx(x.clamp(i64::MIN as i128, i64::MAX as i128) as i64)
    }
}

impl<const F: u32> Add for Fx<F> {
    type Output = Self;
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        Fx(self.0.saturating_add(o.0))
    }
}
impl<const F: u32> Sub for Fx<F> {
    type Output = Self;
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        Fx(self.0.saturating_sub(o.0))
    }
}
impl<const F: u32> Mul for Fx<F> {
    type Output = Self;
    #[inline(always)]
    fn mul(self, o: Self) -> Self {
        let p = self.0 as i128 * o.0 as i128;
        // Round to nearest, ties away from zero: add half an LSB of the result in the direction of the sign.
        let half = 1i128 << (F - 1);
        let r = if p >= 0 { (p + half) >> F } else { -((-p + half) >> F) };
        Self::saturate(r)
    }
}
impl<const F: u32> Div for Fx<F> {
    type Output = Self;
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        if o.0 == 0 {
            return Fx(match self.0.cmp(&0) {
                Ordering::Less => i64::MIN,
                Ordering::Equal => 0,
                Ordering::Greater => i64::MAX,
            });
        }
        let n = (self.0 as i128) << F;
        let d = o.0 as i128;
        let (q, r) = (n / d, n % d);
        // Round to nearest, ties away from zero.
        let q = if 2 * r.abs() >= d.abs() { q + if (n < 0) == (d < 0) { 1 } else { -1 } } else { q };
        Self::saturate(q)
    }
}
impl<const F: u32> Neg for Fx<F> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        Fx(self.0.saturating_neg())
    }
}
impl<const F: u32> AddAssign for Fx<F> {
    #[inline(always)]
    fn add_assign(&mut self, o: Self) {
        *self = *self + o;
    }
}
impl<const F: u32> SubAssign for Fx<F> {
    #[inline(always)]
    fn sub_assign(&mut self, o: Self) {
        *self = *self - o;
    }
}
impl<const F: u32> MulAssign for Fx<F> {
    #[inline(always)]
    fn mul_assign(&mut self, o: Self) {
        *self = *self * o;
    }
}
impl<const F: u32> Zero for Fx<F> {
    fn zero() -> Self {
        Fx(0)
    }
    fn is_zero(&self) -> bool {
        self.0 == 0
    }
}
impl<const F: u32> One for Fx<F> {
    fn one() -> Self {
        Fx(Self::ONE)
    }
}

impl<const F: u32> Scalar for Fx<F> {
    fn of(x: f64) -> Self {
        let scaled = x * Self::ONE as f64;
        let r = if scaled >= 0.0 { libm::floor(scaled + 0.5) } else { -libm::floor(-scaled + 0.5) };
        // `as` saturates at the i64 range (and maps NaN to 0).
        Fx(r as i64)
    }
    fn as_f64(self) -> f64 {
        self.0 as f64 / Self::ONE as f64
    }
    fn greatest() -> Self {
        Fx(i64::MAX)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn q(x: f64) -> Q32 {
        Q32::of(x)
    }

    #[test]
    fn arithmetic_rounds_to_nearest_within_half_an_lsb() {
        let lsb = 2f64.powi(-32);
        for (a, b) in [(1.5, 2.25), (-3.7, 0.013), (123.456, -0.5), (1e-6, 7.0), (-2.0, -1e-3)] {
            assert_eq!((q(a) + q(b)).as_f64(), q(a).as_f64() + q(b).as_f64());
            let exact_mul = q(a).as_f64() * q(b).as_f64();
            assert!(((q(a) * q(b)).as_f64() - exact_mul).abs() <= lsb / 2.0, "{a} * {b}");
            let exact_div = q(a).as_f64() / q(b).as_f64();
            assert!(((q(a) / q(b)).as_f64() - exact_div).abs() <= lsb / 2.0 * (1.0 + 1e-9), "{a} / {b}");
        }
        assert_eq!(q(0.1).as_f64(), (0.1f64 * 2f64.powi(32)).round() / 2f64.powi(32));
    }

    #[test]
    fn overflow_saturates_instead_of_wrapping() {
        let big = q(2.0e9);
        assert_eq!((big * big).0, i64::MAX);
        assert_eq!((-big * big).0, i64::MIN);
        assert_eq!((big + big).0, i64::MAX);
        assert_eq!((q(1.0) / Q32::zero()).0, i64::MAX);
        assert_eq!((-q(1.0) / Q32::zero()).0, i64::MIN);
        assert_eq!(Q32::greatest().0, i64::MAX);
    }
}
