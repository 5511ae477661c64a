//! The stage model of the paper, eq. (1), per axis:
//!
//! ```text
//! x1' = x2
//! x2' = -a0 x1 - a1 x2 + b0 u        x1 in um, u in V, t in s
//! ```
//!
//! with the derived quantities every report carries next to the raw parameters: natural frequency
//! `f0 = sqrt(a0) / 2 pi`, damping ratio `zeta = a1 / (2 sqrt(a0))` and DC gain `b0 / a0`.

use crate::{Real, Scalar};

/// Parameters of the second-order stage model (paper eq. (1)).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub struct StageParams<T> {
    /// Stiffness over mass, 1/s^2.
    pub a0: T,
    /// Damping over mass, 1/s.
    pub a1: T,
    /// Actuator gain over mass, um/(s^2 V).
    pub b0: T,
}

impl<T: Real> StageParams<T> {
    /// Undamped natural frequency `sqrt(a0) / 2 pi`, Hz.
    pub fn f0_hz(&self) -> T {
        self.a0.sqrt() / (T::of(2.0) * T::PI())
    }

    /// Damping ratio `a1 / (2 sqrt(a0))`, dimensionless.
    pub fn damping_ratio(&self) -> T {
        self.a1 / (T::of(2.0) * self.a0.sqrt())
    }

    /// Static gain `b0 / a0`, um/V.
    pub fn dc_gain(&self) -> T {
        self.b0 / self.a0
    }

    /// The same parameters in another scalar.
    pub fn cast<U: Scalar>(&self) -> StageParams<U> {
        StageParams { a0: U::of(self.a0.as_f64()), a1: U::of(self.a1.as_f64()), b0: U::of(self.b0.as_f64()) }
    }

    /// Build from the physical description: natural frequency (Hz), damping ratio and DC gain (um/V).
    pub fn from_modal(f0_hz: T, damping_ratio: T, dc_gain: T) -> Self {
        let w0 = T::of(2.0) * T::PI() * f0_hz;
        let a0 = w0 * w0;
        StageParams { a0, a1: T::of(2.0) * damping_ratio * w0, b0: dc_gain * a0 }
    }
}

impl StageParams<f64> {
    /// The reference stage with the 24.75 g payload (paper Table I).
    pub const PAYLOAD: Self = StageParams { a0: 7.06e6, a1: 77.6, b0: 0.808e6 };
    /// The reference stage without payload (paper Table I).
    pub const NO_PAYLOAD: Self = StageParams { a0: 9.21e6, a1: 86.8, b0: 1.07e6 };
    /// Where every estimator starts (paper Section V-C): `[b0, a1, a0] = [5e5, 70, 6e6]`.
    pub const INITIAL: Self = StageParams { a0: 6.0e6, a1: 70.0, b0: 5.0e5 };
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_one_derived_quantities_match_the_paper() {
        // The paper prints f0, zeta and the DC gain to 3 significant digits; half a unit in the last digit.
        let p = StageParams::PAYLOAD;
        assert!((p.f0_hz() - 423.0).abs() < 0.5);
        assert!((p.damping_ratio() - 0.0146).abs() < 0.00005);
        assert!((p.dc_gain() - 0.114).abs() < 0.0005);
        let n = StageParams::NO_PAYLOAD;
        assert!((n.f0_hz() - 483.0).abs() < 0.5);
        assert!((n.damping_ratio() - 0.0143).abs() < 0.00005);
        assert!((n.dc_gain() - 0.116).abs() < 0.0005);
    }

    #[test]
    fn modal_form_round_trips() {
        let p = StageParams::PAYLOAD;
        let q = StageParams::from_modal(p.f0_hz(), p.damping_ratio(), p.dc_gain());
        for (x, y) in [(p.a0, q.a0), (p.a1, q.a1), (p.b0, q.b0)] {
            assert!((x / y - 1.0).abs() < 1e-14);
        }
    }
}
