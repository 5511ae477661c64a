//! Direct Form 1 second-order section:
//!
//! ```text
//! y[n] = b0 x[n] + b1 x[n-1] + b2 x[n-2] - a1 y[n-1] - a2 y[n-2]
//! ```
//!
//! Direct Form 1 rather than the transposed Direct Form 2: its state is the past inputs and outputs themselves, so a
//! coefficient change between samples takes effect without a transient from re-interpreted internal states, there is
//! one summing junction (one accumulator, the form that carries over to fixed point with a wide accumulator), and the
//! state never holds values larger than the signals. It costs four state words instead of two; at two replicas per
//! sample that is nothing.
//!
//! Coefficients are `[b0, b1, b2, a1, a2]` with `a0` normalised to 1. Cost per sample: 5 multiplies, 4 adds.

use crate::filters::response::{polyval, z_at, Complex};
use crate::Scalar;

/// Coefficients of one section (the configuration).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Biquad<T> {
    /// Feed-forward `[b0, b1, b2]`.
    pub b: [T; 3],
    /// Feedback `[a1, a2]` (with `a0 = 1`).
    pub a: [T; 2],
}

/// The state of one section: the last two inputs and outputs.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BiquadState<T> {
    x: [T; 2],
    y: [T; 2],
}

impl<T: Scalar> BiquadState<T> {
    /// Set the state to the steady state of a constant input `x` (so a filter can start settled).
    pub fn settle(&mut self, coeffs: &Biquad<T>, x: T) {
        let y = x * coeffs.dc_gain();
        self.x = [x, x];
        self.y = [y, y];
    }
}

impl<T: Scalar> Biquad<T> {
    /// The identity section.
    pub fn passthrough() -> Self {
        Biquad { b: [T::one(), T::zero(), T::zero()], a: [T::zero(), T::zero()] }
    }

    /// One sample.
    #[inline]
    pub fn update(&self, s: &mut BiquadState<T>, x: T) -> T {
        let y = self.b[0] * x + self.b[1] * s.x[0] + self.b[2] * s.x[1] - self.a[0] * s.y[0] - self.a[1] * s.y[1];
        s.x = [x, s.x[0]];
        s.y = [y, s.y[0]];
        y
    }

    /// Whether the section can run: every coefficient finite and both poles strictly inside the unit circle
    /// (`|a2| < 1` and `|a1| < 1 + a2`). A design asked for the impossible (a match at a frequency too close to
    /// 0 Hz for its sample rate) comes out with NaN or infinite coefficients, or unstable, and fails this.
    pub fn is_stable(&self) -> bool {
        let [b0, b1, b2] = self.b.map(|x| x.as_f64());
        let [a1, a2] = self.a.map(|x| x.as_f64());
        let finite = [b0, b1, b2, a1, a2].iter().all(|x| x.is_finite());
        finite && libm::fabs(a2) < 1.0 && libm::fabs(a1) < 1.0 + a2
    }

    /// Gain at DC.
    pub fn dc_gain(&self) -> T {
        (self.b[0] + self.b[1] + self.b[2]) / (T::one() + self.a[0] + self.a[1])
    }

    /// The same section in another scalar.
    pub fn cast<U: Scalar>(&self) -> Biquad<U> {
        let c = |x: T| U::of(x.as_f64());
        Biquad { b: [c(self.b[0]), c(self.b[1]), c(self.b[2])], a: [c(self.a[0]), c(self.a[1])] }
    }

    /// Frequency response at `f_hz` for sample period `t_s`.
    pub fn response(&self, f_hz: f64, t_s: f64) -> Complex {
        let zi = Complex::new(1.0, 0.0) / z_at(f_hz, t_s);
        let b = [self.b[0].as_f64(), self.b[1].as_f64(), self.b[2].as_f64()];
        let a = [1.0, self.a[0].as_f64(), self.a[1].as_f64()];
        polyval(&b, zi) / polyval(&a, zi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn difference_equation_is_direct_form_one() {
        let f = Biquad { b: [0.5, 0.25, 0.125], a: [-0.5, 0.25] };
        let mut s = BiquadState::default();
        let x = [1.0, 0.0, 0.0, 2.0];
        let mut y_ref = [0.0f64; 4];
        for n in 0..4 {
            let xm = |k: usize| if n >= k { x[n - k] } else { 0.0 };
            let ym = |k: usize, y: &[f64; 4]| if n >= k { y[n - k] } else { 0.0 };
            y_ref[n] = 0.5 * xm(0) + 0.25 * xm(1) + 0.125 * xm(2) + 0.5 * ym(1, &y_ref) - 0.25 * ym(2, &y_ref);
            assert_eq!(f.update(&mut s, x[n]), y_ref[n]);
        }
    }

    /// A gain of 7/6, not 1: at 1 the settled output `x * gain` and `x / gain` are the same.
    #[test]
    fn settled_state_outputs_the_dc_response_at_once() {
        let f: Biquad<f64> = Biquad { b: [0.2, 0.3, 0.2], a: [-0.6, 0.2] };
        assert!((f.dc_gain() - 7.0 / 6.0).abs() < 1e-15);
        let mut s = BiquadState::default();
        s.settle(&f, 2.0);
        for _ in 0..3 {
            let y = f.update(&mut s, 2.0);
            assert!((y - 2.0 * 7.0 / 6.0).abs() < 1e-15, "{y}");
        }
    }

    /// `is_stable` is the stability triangle `|a2| < 1`, `|a1| < 1 + a2` (both poles strictly inside the unit
    /// circle) with every coefficient finite: a pole on the circle (at 1, at -1, or a pair with `a2 = 1`) is not.
    #[test]
    fn is_stable_is_the_stability_triangle_with_finite_coefficients() {
        let with = |a: [f64; 2]| Biquad { b: [0.2, 0.3, 0.2], a };
        for a in [[-0.5, 0.25], [-1.9, 0.95], [1.9, 0.95], [0.0, -0.99], [0.0, 0.0]] {
            assert!(with(a).is_stable(), "{a:?}");
        }
        let outside = [
            [0.0, 1.0],    // a pair on the circle
            [0.0, -1.0],   // poles at +-1
            [-1.5, 0.5],   // a pole at 1
            [1.5, 0.5],    // a pole at -1
            [-1.6, 0.5],   // a real pole beyond 1
            [1.6, 0.5],    // and beyond -1
            [0.0, 1.2],    // a pair outside
            [-2.5, -1.05], // |a2| > 1 with |a1| < 1 + a2 failing as well
        ];
        for a in outside {
            assert!(!with(a).is_stable(), "{a:?}");
        }
        for bad in [f64::NAN, f64::INFINITY] {
            assert!(!Biquad { b: [bad, 0.3, 0.2], a: [-0.5, 0.25] }.is_stable());
            assert!(!with([-0.5, bad]).is_stable());
            assert!(!with([bad, 0.25]).is_stable());
        }
    }
}
