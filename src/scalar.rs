//! The scalar the core is generic over: `f32` on the Cortex-M4F (single-precision FPU), `f64` on the host as the
//! reference. Designs (filter coefficients, discretisations) are always computed in `f64` and then rounded once to
//! the working scalar with [`Scalar::of`], so the f32 and f64 paths differ only by that rounding and by arithmetic.

use core::fmt::Debug;
use core::ops::{AddAssign, Div, MulAssign, Neg, Sub, SubAssign};
use num_traits::{Float, FloatConst, One, Zero};

/// The arithmetic a kernel needs when it uses nothing but `+ - * /` and comparisons (the biquad, the discrete
/// RLS): implemented by `f32`, `f64` and the fixed-point [`crate::fixed::Fx`], so one generic implementation serves
/// all.
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
    /// The scalar's name, `"f32"` or `"f64"` (what a host tool's output says it was computed in).
    const NAME: &'static str;
    /// A 64-bit phase accumulator as a fraction of a cycle in `[0, 1)`, to the precision this scalar holds
    /// (24 bits for f32, 53 for f64), without a 64-bit float conversion on the target.
    fn phase_fraction(phase: u64) -> Self;
    /// `sin` of the phase `2 pi phase / 2^64`.
    fn phase_sin(phase: u64) -> Self {
        (Self::phase_fraction(phase) * Self::TAU()).sin()
    }
    /// `(sin, cos)` of the phase `2 pi phase / 2^64`.
    fn phase_sin_cos(phase: u64) -> (Self, Self) {
        (Self::phase_fraction(phase) * Self::TAU()).sin_cos()
    }
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
    const NAME: &'static str = "f32";

    #[inline(always)]
    fn phase_fraction(phase: u64) -> Self {
        // Top 24 bits: exactly representable in f32, and a u32 -> f32 conversion is one VCVT.
        ((phase >> 40) as u32) as f32 * (1.0 / 16_777_216.0)
    }

    #[inline(always)]
    fn phase_sin(phase: u64) -> Self {
        Self::phase_sin_cos(phase).0
    }

    /// In f32 throughout: libm's `sinf`/`cosf`/`sincosf` evaluate their kernels in f64, in software on the M4F
    /// (about 1 200 instructions a `sinf`). The phase is reduced in integers to the nearest quarter cycle `q` and a
    /// remainder `x` in `[-pi/4, pi/4]` (to the nearest 2^-27 cycle, 2.3e-8 rad), where Taylor polynomials to `x^9` and
    /// `x^8` are within 2e-9 and 3e-8 of `sin x` and `cos x`; `q` then swaps and negates them.
    #[inline]
    fn phase_sin_cos(phase: u64) -> (Self, Self) {
        let q = phase.wrapping_add(1 << 61) >> 62;
        let r = phase.wrapping_sub(q << 62) as i64;
        // `r` in [-2^61, 2^61) to the nearest 2^-27 of a cycle: at most 2^24 units, exact in f32.
        let x = ((r + (1 << 36)) >> 37) as i32 as f32 * (core::f32::consts::TAU / 134_217_728.0);
        let x2 = x * x;
        let sin = x + x * x2 * (-1.0 / 6.0 + x2 * (1.0 / 120.0 + x2 * (-1.0 / 5040.0 + x2 * (1.0 / 362_880.0))));
        let cos = 1.0 + x2 * (-0.5 + x2 * (1.0 / 24.0 + x2 * (-1.0 / 720.0 + x2 * (1.0 / 40_320.0))));
        match q & 3 {
            0 => (sin, cos),
            1 => (cos, -sin),
            2 => (-sin, -cos),
            _ => (-cos, sin),
        }
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
    const NAME: &'static str = "f64";

    #[inline(always)]
    fn phase_fraction(phase: u64) -> Self {
        (phase >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }
}

#[cfg(test)]
mod tests {
    use super::{fmax, fmin, Real, Scalar};

    /// `(sin, cos)` of the phase `2 pi p / 2^64`, in f64.
    fn exact(p: u64) -> (f64, f64) {
        libm::sincos(core::f64::consts::TAU * (p as f64 / 18_446_744_073_709_551_616.0))
    }

    /// The phase as a fraction of a cycle: its top 24 bits in f32, 53 in f64, from 0 to just below 1.
    #[test]
    fn a_phase_is_its_fraction_of_a_cycle_to_the_scalars_precision() {
        for (phase, fraction) in [(0u64, 0.0f64), (1 << 62, 0.25), (1 << 63, 0.5), (3 << 62, 0.75)] {
            assert_eq!((f32::phase_fraction(phase), f64::phase_fraction(phase)), (fraction as f32, fraction));
        }
        assert_eq!(f32::phase_fraction(u64::MAX), 1.0 - 2f32.powi(-24));
        assert_eq!(f64::phase_fraction(u64::MAX), 1.0 - 2f64.powi(-53));
        // What lies below the scalar's precision is dropped, not rounded up.
        assert_eq!((f32::phase_fraction((1 << 40) - 1), f32::phase_fraction(1 << 40)), (0.0, 2f32.powi(-24)));
        assert_eq!((f64::phase_fraction((1 << 11) - 1), f64::phase_fraction(1 << 11)), (0.0, 2f64.powi(-53)));
        // f64's sine and cosine are libm's of that fraction of a turn.
        let (s, c) = f64::phase_sin_cos(1 << 61);
        // Within an ulp or two of the exact value: `pi / 4` itself is rounded.
        assert!((s - 0.5f64.sqrt()).abs() < 3e-16 && (c - 0.5f64.sqrt()).abs() < 3e-16, "{s} {c}");
        assert_eq!(f64::phase_sin(1 << 61), s);
    }

    /// The remainder is rounded to the nearest 2^-27 of a cycle, not truncated: near a zero of the sine, where the
    /// sine is the angle, it is within half that unit (2.34e-8 rad) of the exact one, on both sides of the zero.
    #[test]
    fn the_f32_phase_is_rounded_to_the_nearest_unit() {
        let half_unit = core::f64::consts::PI / 134_217_728.0;
        for k in 1..64u64 {
            for p in [k << 34, (k << 34).wrapping_neg(), (1 << 63) + (k << 34)] {
                let exact = exact(p).0;
                let s = f32::phase_sin_cos(p).0 as f64;
                assert!((s - exact).abs() <= half_unit * (1.0 + 1e-6), "{p:#x}: {s:e} for {exact:e}");
            }
        }
    }

    /// One comparison each, and what a NaN does: a NaN second operand comes back, a NaN first one gives the second.
    #[test]
    fn fmax_and_fmin_pick_by_one_comparison() {
        assert_eq!((fmax(1.0, 2.0), fmax(2.0, 1.0), fmin(1.0, 2.0), fmin(2.0, 1.0)), (2.0, 2.0, 1.0, 1.0));
        assert!(fmax(1.0, f64::NAN).is_nan() && fmin(1.0, f64::NAN).is_nan());
        assert_eq!((fmax(f64::NAN, 1.0), fmin(f64::NAN, 1.0)), (1.0, 1.0));
        assert_eq!((fmax(-0.0f64, 0.0).to_bits(), fmin(-0.0f64, 0.0).to_bits()), (0.0f64.to_bits(), 0.0f64.to_bits()));
    }

    /// The conversions round once, the greatest value is unbounded, the names are the types'.
    #[test]
    fn each_float_converts_once_and_names_itself() {
        assert_eq!((f32::of(0.1), f32::of(0.1).as_f64()), (0.1f32, 0.1f32 as f64));
        assert_eq!((f64::of(0.1), 0.1f64.as_f64()), (0.1, 0.1));
        assert_eq!((f32::greatest(), f64::greatest()), (f32::INFINITY, f64::INFINITY));
        assert_eq!((f32::NAME, f64::NAME), ("f32", "f64"));
    }

    #[test]
    fn f32_sine_and_cosine_of_a_phase_are_within_a_few_ulps_of_the_exact_ones() {
        let mut worst = 0.0f64;
        let mut next = crate::xorshift64(0x9E37_79B9_7F4A_7C15);
        // Random phases, and every octant's edges with their neighbours.
        let edges = (0..8u64).flat_map(|k| [0u64, 1, u64::MAX].map(move |d| (k << 61).wrapping_add(d)));
        let random = (0..1_000_000).map(|_| next());
        for p in edges.chain(random) {
            let (s, c) = f32::phase_sin_cos(p);
            let (es, ec) = exact(p);
            worst = worst.max((s as f64 - es).abs()).max((c as f64 - ec).abs());
            assert_eq!(f32::phase_sin(p), s);
        }
        // The remainder to half a unit (2.3e-8 rad), the polynomials' truncation (3e-8) and f32's rounding (half an
        // ulp is 3e-8 below 1): measured 9.6e-8.
        std::println!("f32 sin/cos of a phase: worst error {worst:.2e}");
        assert!(worst < 1.5e-7, "{worst:e}");
    }
}
