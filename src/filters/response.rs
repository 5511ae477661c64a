//! Complex arithmetic just wide enough to evaluate transfer functions on the unit circle and the imaginary axis.

use core::ops::{Add, Div, Mul, Sub};

/// A complex number in f64.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Complex {
    /// Real part.
    pub re: f64,
    /// Imaginary part.
    pub im: f64,
}

impl Complex {
    /// `re + j im`.
    pub const fn new(re: f64, im: f64) -> Self {
        Complex { re, im }
    }
    /// `e^{j theta}`.
    pub fn expj(theta: f64) -> Self {
        Complex::new(libm::cos(theta), libm::sin(theta))
    }
    /// Magnitude.
    pub fn abs(self) -> f64 {
        libm::hypot(self.re, self.im)
    }
    /// Phase in radians, in (-pi, pi].
    pub fn arg(self) -> f64 {
        libm::atan2(self.im, self.re)
    }
    /// Magnitude in dB.
    pub fn db(self) -> f64 {
        20.0 * libm::log10(self.abs())
    }
    /// `x * self`.
    pub fn scale(self, x: f64) -> Self {
        Complex::new(self.re * x, self.im * x)
    }
}

impl From<f64> for Complex {
    fn from(re: f64) -> Self {
        Complex::new(re, 0.0)
    }
}
impl Add for Complex {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Complex::new(self.re + o.re, self.im + o.im)
    }
}
impl Sub for Complex {
    type Output = Self;
    fn sub(self, o: Self) -> Self {
        Complex::new(self.re - o.re, self.im - o.im)
    }
}
impl Mul for Complex {
    type Output = Self;
    fn mul(self, o: Self) -> Self {
        Complex::new(self.re * o.re - self.im * o.im, self.re * o.im + self.im * o.re)
    }
}
impl Div for Complex {
    type Output = Self;
    fn div(self, o: Self) -> Self {
        let d = o.re * o.re + o.im * o.im;
        Complex::new((self.re * o.re + self.im * o.im) / d, (self.im * o.re - self.re * o.im) / d)
    }
}

/// Evaluate the polynomial `c[0] + c[1] x + c[2] x^2 + ...` at `x` (Horner).
pub fn polyval(c: &[f64], x: Complex) -> Complex {
    c.iter().rev().fold(Complex::new(0.0, 0.0), |acc, &ci| acc * x + ci.into())
}

/// `j 2 pi f`, the Laplace variable on the imaginary axis at `f_hz`.
pub fn s_at(f_hz: f64) -> Complex {
    Complex::new(0.0, 2.0 * core::f64::consts::PI * f_hz)
}

/// `e^{j 2 pi f T}`, the z variable on the unit circle at `f_hz` for sample period `t_s`.
pub fn z_at(f_hz: f64, t_s: f64) -> Complex {
    Complex::expj(2.0 * core::f64::consts::PI * f_hz * t_s)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each operation against a value worked out by hand, exact in binary.
    #[test]
    fn complex_arithmetic_is_exact_where_the_values_are() {
        let (a, b) = (Complex::new(3.0, 4.0), Complex::new(1.0, -2.0));
        assert_eq!(a + b, Complex::new(4.0, 2.0));
        assert_eq!(a - b, Complex::new(2.0, 6.0));
        assert_eq!(a * b, Complex::new(11.0, -2.0));
        assert_eq!((a * b) / b, a);
        assert_eq!(a / Complex::new(0.0, 2.0), Complex::new(2.0, -1.5));
        assert_eq!(a.scale(-0.5), Complex::new(-1.5, -2.0));
        assert_eq!(Complex::from(2.5), Complex::new(2.5, 0.0));
        assert_eq!(a.abs(), 5.0);
        assert_eq!(Complex::new(10.0, 0.0).db(), 20.0);
        assert_eq!(Complex::new(-1.0, 0.0).arg(), core::f64::consts::PI);
        assert_eq!(Complex::new(0.0, -2.0).arg(), -core::f64::consts::FRAC_PI_2);
        let e = Complex::expj(core::f64::consts::FRAC_PI_3);
        assert!((e.re - 0.5).abs() < 1e-15 && (e.im - 0.75f64.sqrt()).abs() < 1e-15, "{e:?}");
    }

    /// Horner from the constant term up: `1 + 2 x + 3 x^2` at `j` is `-2 + 2 j`; `s` and `z` at a frequency.
    #[test]
    fn polynomials_are_evaluated_with_the_constant_term_first() {
        assert_eq!(polyval(&[1.0, 2.0, 3.0], Complex::new(0.0, 1.0)), Complex::new(-2.0, 2.0));
        assert_eq!(polyval(&[], Complex::new(5.0, 5.0)), Complex::new(0.0, 0.0));
        assert_eq!(s_at(0.5), Complex::new(0.0, core::f64::consts::PI));
        // A quarter of the sample rate: `z = e^{j pi / 2} = j`.
        let z = z_at(2500.0, 1e-4);
        assert!(z.re.abs() < 1e-15 && (z.im - 1.0).abs() < 1e-15, "{z:?}");
    }
}
