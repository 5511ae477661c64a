//! Fixed point: `Fx<F>`, a signed Q(63-F).F number in an `i64` with 128-bit products, for FPU-less chips and
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
//! ## Cost (QEMU's instruction counts, BENCHMARKS.md "Without an FPU")
//! A product is four 32 x 32 -> 64-bit multiplies and their carries, a division about 210 instructions (16-bit
//! digits, each estimated by one `udiv`). The ARX RLS in Q31.32: 5 067 instructions an update on the Cortex-M4,
//! 5 169 on the M3, where software `f32` takes 8 727; on the Cortex-M0, which has neither a 64-bit multiply nor a
//! divide, 24 041 against 15 016 for software `f32`: there this format buys reproducibility, not speed.
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
        // In magnitudes: the 128-bit product of two `u64` (four 32-bit multiplies), rounded half up (so, with the
        // sign applied after, to nearest with ties away from zero) and saturated. The same number as the signed
        // `i128` product rounded by the sign's branch, and cheaper on the Cortex-M4 (`arx_rls_fixed` 8 324 -> 7 499
        // instructions); a branch-free rounding of the signed product, `(p + half - (p < 0)) >> F`, cost more.
        let negative = (self.0 < 0) != (o.0 < 0);
        let p = self.0.unsigned_abs() as u128 * o.0.unsigned_abs() as u128;
        let m = (p + (1u128 << (F - 1))) >> F;
        Fx(if negative {
            if m >= 1 << 63 {
                i64::MIN
            } else {
                -(m as i64)
            }
        } else {
            m.min(i64::MAX as u128) as i64
        })
    }
}

impl<const F: u32> Div for Fx<F> {
    type Output = Self;
    /// `a 2^F / d`, rounded to nearest (ties away from zero), saturated; `x / 0` is the end of the range in `x`'s
    /// direction (0 for `0 / 0`). In magnitudes: the saturation decided by a comparison, then the quotient of the
    /// 128-bit numerator by `div_wide` (16-bit digits, each estimated by one 32-bit division). Bit for bit the
    /// `i128` division's result (the reference in the tests). About 210 instructions on the Cortex-M4 (and on the
    /// M3); by two library 64-bit divisions and 32 steps of binary long division, its way before, about 490.
    #[inline(always)]
    fn div(self, o: Self) -> Self {
        const { assert!(F >= 1 && F <= 62, "a fraction of 1 to 62 bits") };
        if o.0 == 0 {
            return Fx(match self.0.cmp(&0) {
                Ordering::Less => i64::MIN,
                Ordering::Equal => 0,
                Ordering::Greater => i64::MAX,
            });
        }
        let negative = (self.0 < 0) != (o.0 < 0);
        let (a, d) = (self.0.unsigned_abs(), o.0.unsigned_abs());
        // The quotient's whole part at `2^(63 - F)` or more (`a >= d 2^(63 - F)`, where that product fits): at
        // least 2^63 with the fraction, beyond the range.
        let k = 63 - F;
        if d.leading_zeros() >= k && d << k <= a {
            return Fx(if negative { i64::MIN } else { i64::MAX });
        }
        // Now `a 2^F < d 2^63`: the quotient fits 63 bits.
        let (mut q, r) = div_wide((a as u128) << F, d);
        // Round to nearest, ties away from zero: `2 r >= d`. Then `q <= 2^63`.
        q += (r >= d - r) as u64;
        Fx(if negative { 0i64.wrapping_sub(q as i64) } else { q.min(i64::MAX as u64) as i64 })
    }
}

/// `(n / d, n % d)` for `d != 0` and `n < d 2^64` (the quotient fits 64 bits): long division in base 2^16 on the
/// divisor normalised to its top bit (Knuth's algorithm D), each quotient digit estimated from the remainder's top
/// 32 bits and the divisor's top 16 by one 32-bit division (the Cortex-M3/M4's `udiv`), at most 2 above the digit,
/// and corrected. Rust's `u128 / u64` is, on a 32-bit target, a library loop over the numerator's bits.
#[inline(always)]
fn div_wide(n: u128, d: u64) -> (u64, u64) {
    let s = d.leading_zeros();
    let dn = d << s;
    // `n 2^s < dn 2^64 <= 2^128`.
    let n = n << s;
    // The divisor's top 16 bits, at least 2^15.
    let top = (dn >> 48) as u32;
    // The remainder, below `dn` throughout; the digits of the numerator's low half come in below it.
    let (mut r, low) = ((n >> 64) as u64, n as u64);
    let mut q = 0u64;
    for shift in [48, 32, 16, 0] {
        // `r 2^16 + digit < dn 2^16`, so the digit is below 2^16; its estimate at most 2 above it.
        let wide = ((r as u128) << 16) | ((low >> shift) & 0xFFFF) as u128;
        let mut digit = ((r >> 32) as u32 / top).min(0xFFFF);
        // `digit dn` from two 32 x 32 -> 64-bit products, not a general 128-bit multiply. (The same in 64-bit
        // halves with explicit carries took 29 more instructions a division on the Cortex-M4.)
        let product = ((((dn >> 32) * digit as u64) as u128) << 32) + ((dn & 0xFFFF_FFFF) * digit as u64) as u128;
        let mut rest = wide as i128 - product as i128;
        while rest < 0 {
            digit -= 1;
            rest += dn as i128;
        }
        r = rest as u64;
        q = q << 16 | digit as u64;
    }
    (q, r >> s)
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
            assert_eq!((q(a) - q(b)).as_f64(), q(a).as_f64() - q(b).as_f64());
            let (mut sum, mut difference, mut product) = (q(a), q(a), q(a));
            sum += q(b);
            difference -= q(b);
            product *= q(b);
            assert_eq!((sum, difference, product), (q(a) + q(b), q(a) - q(b), q(a) * q(b)), "{a}, {b}");
            let exact_mul = q(a).as_f64() * q(b).as_f64();
            assert!(((q(a) * q(b)).as_f64() - exact_mul).abs() <= lsb / 2.0, "{a} * {b}");
            let exact_div = q(a).as_f64() / q(b).as_f64();
            assert!(((q(a) / q(b)).as_f64() - exact_div).abs() <= lsb / 2.0 * (1.0 + 1e-9), "{a} / {b}");
        }
        assert_eq!(q(0.1).as_f64(), (0.1f64 * 2f64.powi(32)).round() / 2f64.powi(32));
    }

    /// The division by an `i128` numerator (as it was at first).
    fn div_reference<const F: u32>(x: Fx<F>, y: Fx<F>) -> Fx<F> {
        if y.0 == 0 {
            return x / y;
        }
        let n = (x.0 as i128) << F;
        let d = y.0 as i128;
        let (q, r) = (n / d, n % d);
        let q = if 2 * r.abs() >= d.abs() { q + if (n < 0) == (d < 0) { 1 } else { -1 } } else { q };
        Fx(q.clamp(i64::MIN as i128, i64::MAX as i128) as i64)
    }

    /// The multiplication as it was, rounding by the sign's branch.
    fn mul_branching(x: Q32, y: Q32) -> Q32 {
        let p = x.0 as i128 * y.0 as i128;
        let half = 1i128 << 31;
        let r = if p >= 0 { (p + half) >> 32 } else { -((-p + half) >> 32) };
        Fx(r.clamp(i64::MIN as i128, i64::MAX as i128) as i64)
    }

    /// The division by 16-bit digits is the `i128` division, and the multiplication's one rounding the branching one,
    /// bit for bit: edges of the range and of the saturation, divisors on both sides of 2^32, ties, and a million
    /// pseudo-random pairs over every magnitude.
    #[test]
    fn division_and_multiplication_are_the_wide_ones_bit_for_bit() {
        let edges = [
            0,
            1,
            -1,
            2,
            3,
            (1 << 31) - 1,
            1 << 31,
            (1 << 32) - 1,
            1 << 32,
            (1 << 32) + 1,
            1 << 33,
            (1 << 62) - 1,
            1 << 62,
            i64::MAX,
            i64::MAX - 1,
            i64::MIN,
            i64::MIN + 1,
            -(1 << 32),
            -(1 << 31),
            0x1234_5678_9ABC_DEF0,
            -0x0FED_CBA9_8765_4321,
        ];
        let check = |a: i64, d: i64| {
            let (x, y) = (Fx::<32>(a), Fx::<32>(d));
            assert_eq!((x / y).0, div_reference(x, y).0, "{a} / {d}");
            assert_eq!((x * y).0, mul_branching(x, y).0, "{a} * {d}");
        };
        for &a in &edges {
            for &d in &edges {
                check(a, d);
            }
        }
        // Ties: `a 2^32 / d` exactly half-way, both signs.
        for (a, d) in [
            (1, 1 << 33),
            (3, 1 << 33),
            (-1, 1 << 33),
            (1, -(1 << 33)),
            (5, 10 << 32),
            (1 << 31, 1),
            (-(1 << 31), 1),
            (3 << 31, -1),
        ] {
            check(a, d);
        }
        // Magnitudes over the whole range: a random value shifted right by a random amount, for both operands.
        let mut next = crate::xorshift64(0x9E37_79B9_7F4A_7C15);
        for _ in 0..1_000_000 {
            let (ra, rd, sa, sd) = (next(), next(), next() % 64, next() % 64);
            check((ra as i64) >> sa, (rd as i64) >> sd);
        }
    }

    /// The division at every other fraction's width the generic code can be built with: the normalisation shift,
    /// the saturation's comparison and the numerator's shift all depend on `F`.
    #[test]
    fn division_of_other_formats_is_the_wide_one_bit_for_bit() {
        fn check<const F: u32>(next: &mut impl FnMut() -> u64) {
            let edges = [0, 1, -1, 3, 1 << F, (1 << F) - 1, -(1 << F), i64::MAX, i64::MIN, i64::MIN + 1];
            let pair = |a: i64, d: i64| {
                let (x, y) = (Fx::<F>(a), Fx::<F>(d));
                assert_eq!((x / y).0, div_reference(x, y).0, "Fx<{F}>: {a} / {d}");
            };
            for &a in &edges {
                for &d in &edges {
                    pair(a, d);
                }
            }
            for _ in 0..100_000 {
                let (ra, rd, sa, sd) = (next(), next(), next() % 64, next() % 64);
                pair((ra as i64) >> sa, (rd as i64) >> sd);
            }
        }
        let mut next = crate::xorshift64(0x2545_F491_4F6C_DD1D);
        check::<1>(&mut next);
        check::<15>(&mut next);
        check::<16>(&mut next);
        check::<31>(&mut next);
        check::<33>(&mut next);
        check::<48>(&mut next);
        check::<62>(&mut next);
    }

    /// From f64 to the nearest step, ties away from zero, the same for both signs; beyond the range its ends, NaN 0.
    #[test]
    fn conversion_rounds_to_the_nearest_step_ties_away_from_zero() {
        let step = 2f64.powi(-32);
        for (x, raw) in [(2.5, 3), (1.5, 2), (2.3, 2), (2.7, 3), (0.5, 1), (0.49, 0)] {
            assert_eq!(Q32::of(x * step).0, raw, "{x} steps");
            assert_eq!(Q32::of(-x * step).0, -raw, "-{x} steps");
        }
        assert_eq!(q(-0.1).0, -q(0.1).0);
        assert_eq!(q(-1.5).0, -3 << 31);
        assert_eq!((q(1e30).0, q(-1e30).0, q(f64::NAN).0), (i64::MAX, i64::MIN, 0));
        assert_eq!((Fx::<32>(1).as_f64(), Fx::<32>(-1 << 33).as_f64()), (step, -2.0));
        assert_eq!((Q32::one(), Q32::zero()), (q(1.0), Fx(0)));
        assert!(Q32::zero().is_zero() && !Fx::<32>(1).is_zero() && !Fx::<32>(-1).is_zero());
    }

    #[test]
    fn overflow_saturates_instead_of_wrapping() {
        let big = q(2.0e9);
        assert_eq!((big * big).0, i64::MAX);
        assert_eq!((-big * big).0, i64::MIN);
        assert_eq!((big + big).0, i64::MAX);
        assert_eq!((-big - big).0, i64::MIN);
        assert_eq!((big - -big).0, i64::MAX);
        assert_eq!((-Fx::<32>(i64::MIN)).0, i64::MAX);
        let (mut up, mut down, mut times) = (big, -big, big);
        up += big;
        down -= big;
        times *= big;
        assert_eq!((up.0, down.0, times.0), (i64::MAX, i64::MIN, i64::MAX));
        assert_eq!((q(1.0) / Q32::zero()).0, i64::MAX);
        assert_eq!((-q(1.0) / Q32::zero()).0, i64::MIN);
        assert_eq!(Q32::greatest().0, i64::MAX);
    }
}
