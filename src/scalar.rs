//! The scalar the core is generic over: `f32` on the Cortex-M4F (single-precision FPU), `f64` on the host as the
//! reference. Designs (filter coefficients, discretisations) are always computed in `f64` and then rounded once to
//! the working scalar with [`Scalar::of`], so the f32 and f64 paths differ only by that rounding and by arithmetic.

use core::fmt::Debug;
use core::ops::{AddAssign, Div, MulAssign, Neg, Sub, SubAssign};
use num_traits::{Float, FloatConst, One, Zero};

/// The arithmetic a kernel needs when it uses nothing but `+ - * /` and comparisons (the biquad, the discrete
/// RLS): implemented by `f32`, `f64` and the fixed-point [`crate::fixed::Fx`], so one generic implementation serves all.
pub trait Scalar:
    Copy
    + Default
    + Debug
    + PartialOrd
    + Zero
    + One
    + Sub<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
    + SubAssign
    + MulAssign
    + Send
    + Sync
    + 'static
{
    /// Round an `f64` (a design-time constant) to this scalar.
    fn of(x: f64) -> Self;
    /// Widen to `f64` (reporting, comparison with the reference).
    fn as_f64(self) -> f64;
    /// The largest representable value (an "unbounded" setting).
    fn greatest() -> Self;
}

/// `max(a, b)` by one comparison, for the sample path (`Float::max` is a libm call on the target). Unlike it, a NaN
/// `b` is returned as is; a NaN `a` gives `b`.
#[inline(always)]
pub fn fmax<T: PartialOrd>(a: T, b: T) -> T {
    if a > b {
        a
    } else {
        b
    }
}

/// `min(a, b)` by one comparison, as [`fmax`].
#[inline(always)]
pub fn fmin<T: PartialOrd>(a: T, b: T) -> T {
    if a < b {
        a
    } else {
        b
    }
}

/// A floating-point scalar the core runs in.
pub trait Real: Scalar + Float + FloatConst {
    /// A 64-bit phase accumulator as a fraction of a cycle in `[0, 1)`, to the precision this scalar holds
    /// (24 bits for f32, 53 for f64), without a 64-bit float conversion on the target.
    fn phase_fraction(phase: u64) -> Self;
}

impl Scalar for f32 {
    #[inline(always)]
    fn of(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn as_f64(self) -> f64 {
        self as f64
    }
    fn greatest() -> Self {
        f32::INFINITY
    }
}

impl Real for f32 {
    #[inline(always)]
    fn phase_fraction(phase: u64) -> Self {
        // Top 24 bits: exactly representable in f32, and a u32 -> f32 conversion is one VCVT.
        ((phase >> 40) as u32) as f32 * (1.0 / 16_777_216.0)
    }
}

impl Scalar for f64 {
    #[inline(always)]
    fn of(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn as_f64(self) -> f64 {
        self
    }
    fn greatest() -> Self {
        f64::INFINITY
    }
}

impl Real for f64 {
    #[inline(always)]
    fn phase_fraction(phase: u64) -> Self {
        (phase >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }
}
