//! The identification pre-filter (paper Section II-B):
//!
//! ```text
//! W_p(s) = s / (s + w_lc)  *  w_p^2 / (s^2 + 2 zeta_p w_p s + w_p^2),   w_lc = 2 pi f_lc,  w_p = 2 pi f_p
//! ```
//!
//! with `f_lc = 100 Hz`, `f_p = 450 Hz`, `zeta_p = 0.1` (the paper prints the damping term as `2 zeta pi f0 s`; we use
//! the standard `2 zeta w s`, so `zeta_p` is the damping ratio the text states). It concentrates the signal power
//! where the parameter sensitivities peak (the resonance band) and, being strictly proper of relative degree two,
//! gives the filtered signal's first and second derivatives as proper transfer functions, which the continuous-time
//! RLS needs as regressor and target.
//!
//! ## Realisation
//! Controllable canonical form of `w_p^2 / ((s + w_lc)(s^2 + 2 zeta_p w_p s + w_p^2))`:
//!
//! ```text
//! xi1' = xi2,  xi2' = xi3,  xi3' = -d0 xi1 - d1 xi2 - d2 xi3 + w_p^2 in
//! d2 = w_lc + 2 zeta_p w_p,  d1 = w_p^2 + 2 zeta_p w_p w_lc,  d0 = w_lc w_p^2
//! ```
//!
//! so that `W_p in = xi2`, `s W_p in = xi3` and `s^2 W_p in = xi3'`. The same realisation as the float64 reference.
//!
//! ## Discretisation
//! The filter runs as a discrete filter on the sampled signal: the exact zero-order-hold discretisation of the
//! realisation above (`xi[k+1] = Phi xi[k] + Gam in[k]`, outputs read from `xi[k]` and `in[k]`). Its outputs are
//! the exact samples of the continuous filter's response to the input held over each sample period. Applied to both
//! the sampled `u'` and `y'`, it commutes with the ZOH-sampled plant, so an estimator that integrates the stage model
//! with the filtered `u` held over each step sees exactly the filtered `y` (SPEC section 6, "Discretisation matters
//! more than the estimator").
//!
//! The input steps at each sample instant, and with it the second derivative `xi3'` (the feed-through `w_p^2 in`).
//! The `d2` output is the mean of its left and right limits at the instant, i.e. the feed-through of
//! `(in[k] + in[k-1]) / 2`: that is the value of `s^2 W_p` applied to the smooth signal the samples stand for
//! (the held input is that signal delayed by half a sample, the same for all three outputs), while the right limit
//! alone would add a jump of `w_p^2 (in[k] - in[k-1])` per sample. Cost per sample: 14 multiplies, 12 adds.

use crate::filters::response::{polyval, s_at, Complex};
use crate::linalg::{congruence, mat_mul, mat_vec, zoh, Mat};
use crate::Real;

/// Physical description of `W_p`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PrefilterDesign {
    /// High-pass corner `f_lc`, Hz.
    pub f_lc_hz: f64,
    /// Resonant low-pass natural frequency `f_p`, Hz.
    pub f_p_hz: f64,
    /// Resonant low-pass damping ratio `zeta_p`.
    pub zeta_p: f64,
}

impl Default for PrefilterDesign {
    fn default() -> Self {
        PrefilterDesign { f_lc_hz: 100.0, f_p_hz: 450.0, zeta_p: 0.1 }
    }
}

impl PrefilterDesign {
    /// Denominator coefficients `[d0, d1, d2]` (monic, `s^3 + d2 s^2 + d1 s + d0`) and the numerator gain `w_p^2`.
    pub fn continuous(&self) -> ([f64; 3], f64) {
        let wc = 2.0 * core::f64::consts::PI * self.f_lc_hz;
        let wp = 2.0 * core::f64::consts::PI * self.f_p_hz;
        let d2 = wc + 2.0 * self.zeta_p * wp;
        let d1 = wp * wp + 2.0 * self.zeta_p * wp * wc;
        let d0 = wc * wp * wp;
        ([d0, d1, d2], wp * wp)
    }

    /// The largest amplification per step, `|R(lambda h)|`, of RK4 (`R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24`) over
    /// the poles `lambda` of `W_p`, for steps of `h` seconds. Above 1 an RK4 integration of this filter at that step
    /// grows without bound: at `h` = 0.1 ms a real pole beyond about 4.43 kHz (`|z|` > 2.785) or a lightly damped
    /// pair beyond about 4.5 kHz.
    pub fn rk4_amplification(&self, h: f64) -> f64 {
        let two_pi = 2.0 * core::f64::consts::PI;
        let (wc, wp, z) = (two_pi * self.f_lc_hz, two_pi * self.f_p_hz, self.zeta_p);
        // The pair: -z wp +- wp sqrt(z^2 - 1), real for z >= 1.
        let (re, root) = (-z * wp, wp * libm::sqrt(libm::fabs(z * z - 1.0)));
        let poles = if z >= 1.0 {
            [Complex::new(-wc, 0.0), Complex::new(re + root, 0.0), Complex::new(re - root, 0.0)]
        } else {
            [Complex::new(-wc, 0.0), Complex::new(re, root), Complex::new(re, -root)]
        };
        // One pole at a time, not inlined: unrolled over the three in soft double it took 2.7 KiB of the firmware.
        #[inline(never)]
        fn squared(z: Complex) -> f64 {
            let r = polyval(&[1.0, 1.0, 0.5, 1.0 / 6.0, 1.0 / 24.0], z);
            r.re * r.re + r.im * r.im
        }
        // NaN (a non-finite pole) stays NaN: `f64::max` would drop it.
        let worst =
            poles.iter().map(|p| squared(p.scale(h))).fold(0.0, |m: f64, x| if m.is_nan() || m >= x { m } else { x });
        libm::sqrt(worst)
    }

    /// The time constant of the slowest pole of `W_p`, s: `1 / min(w_lc, zeta_p w_p)` for a lightly damped pair,
    /// the pair's slower real pole `w_p (zeta_p - sqrt(zeta_p^2 - 1))` in its place from `zeta_p = 1` on (NaN for a
    /// design with a NaN in it; an infinite corner is a pole at infinity, never the slowest). How long the filter
    /// rings after its input stops, and how far its state (the controllable form's, whose first state integrates the
    /// input over the high-pass corner's time constant) can grow.
    pub fn slowest_time_constant_s(&self) -> f64 {
        let two_pi = 2.0 * core::f64::consts::PI;
        let (wc, wp, z) = (two_pi * self.f_lc_hz, two_pi * self.f_p_hz, self.zeta_p);
        // `z - sqrt(z^2 - 1)` as `1 / (z + sqrt(z^2 - 1))`, which does not cancel for a large `z`.
        let pair = if z < 1.0 { z * wp } else { wp / (z + libm::sqrt(z * z - 1.0)) };
        if wc.is_nan() || pair.is_nan() {
            return f64::NAN;
        }
        1.0 / if wc < pair { wc } else { pair }
    }

    /// The longest [`Self::slowest_time_constant_s`] the estimators take, s: the default pre-filter's is 3.5 ms (its
    /// pair, `zeta_p w_p`), one with `zeta_p = 0.01` at 450 Hz 35 ms. A pre-filter slower than this rings on after
    /// the excitation stops, where the excitation monitor takes its ringing for excitation and the estimators go on
    /// adapting to it, and its state grows with it: a later pre-filter, which starts from that state, then feeds
    /// the restarted estimators a transient that can leave an EKF on a wrong solution (`tune prefilter 1.4e-8 9.9
    /// 6e-9`, an undamped oscillator at 9.9 Hz on an integrator, was taken before this bound: with the excitation
    /// stopped the monitor's power grew from 78 to 131 V^2 in 56 ms, and after it the paper's pre-filter left the
    /// continuous EKF with `b0` negative: `tests/instrument.rs`, the random session).
    pub const MAX_TIME_CONSTANT_S: f64 = 0.1;

    /// `f_p / f0` when the centre `f_p` is more than a factor of [`Self::OFF_RESONANCE`] away from a resonance at
    /// `f0_hz` (`None` within it, or for a resonance that is not a positive frequency). The pre-filter weighs the fit
    /// towards its band, and what the stage's model cannot represent (the analog chain, higher modes) then biases the
    /// estimates: on the simulated board (resonance 423 Hz, PRBS, `identify` over 15-20 s of a 40 s run) `b0` was off
    /// with `f_p` at 0.5 / 1.06 / 2 times the resonance by +2.1 / -0.02 / -0.4 % in the EKFs and +2.4 / -1.5 / -7 %
    /// in the continuous-time RLS (the ARX as the RLS), `f_lc` from 10 to 2000 Hz moving it by 0.1 % at most; on a
    /// stage at 1 kHz with `f_p` left at 450 Hz, 5-8 % in every estimator (`tests/instrument.rs`). The console's
    /// `tune` and `identify` say so in a note.
    pub fn off_resonance(&self, f0_hz: f64) -> Option<f64> {
        let ratio = self.f_p_hz / f0_hz;
        let far = ratio * Self::OFF_RESONANCE < 1.0 || ratio > Self::OFF_RESONANCE;
        (f0_hz > 0.0 && f0_hz.is_finite() && far).then_some(ratio)
    }

    /// How far from the resonance [`Self::off_resonance`] notes the centre, as a factor either way.
    pub const OFF_RESONANCE: f64 = 2.0;

    /// The analog response of `s^order W_p(s)` at `f_hz` (`order` 0, 1 or 2).
    pub fn analog_response(&self, order: u32, f_hz: f64) -> Complex {
        let ([d0, d1, d2], g) = self.continuous();
        let s = s_at(f_hz);
        let mut num = [0.0; 4];
        num[1 + order as usize] = g;
        polyval(&num, s) / polyval(&[d0, d1, d2, 1.0], s)
    }

    /// The discrete filter for sample period `t_s`.
    #[inline(never)]
    pub fn design<T: Real>(&self, t_s: f64) -> Prefilter<T> {
        let d = self.discrete(t_s);
        let c = T::of;
        Prefilter {
            phi: d.phi.map(|row| row.map(c)),
            gam: d.gam.map(c),
            accel: d.accel.map(c),
            half_feedthrough: c(d.half_feedthrough),
        }
    }

    /// The discrete filter's white-noise gains: the sums of the squares of the impulse responses of its `value` and
    /// `d2` outputs, so that a white input of variance `s2` comes out with the powers `s2 * gains`. From the
    /// controllability Gramian `P = sum_j Phi^j Gam Gam' Phi'^j`, summed by doubling (`P += M P M'`, `M = M^2`,
    /// 2^24 samples: far past the slowest pole's decay for any corner above a hundredth of a hertz at 10 kHz).
    /// The impulse gives `value = xi2` from the first sample on, and `d2 = h` at once, `accel . Gam + h` one sample
    /// later and `accel . Phi^(k-1) Gam` after, `h` the half feed-through.
    #[inline(never)]
    pub fn noise_gains(&self, t_s: f64) -> [f64; 2] {
        let d = self.discrete(t_s);
        let mut p: Mat<3> = core::array::from_fn(|i| core::array::from_fn(|j| d.gam[i] * d.gam[j]));
        let mut m = d.phi;
        for _ in 0..24 {
            let add = congruence(&m, &p);
            p = core::array::from_fn(|i| core::array::from_fn(|j| p[i][j] + add[i][j]));
            m = mat_mul(&m, &m);
        }
        let later = congruence(&d.phi, &p);
        let quad = |q: &Mat<3>| -> f64 {
            (0..3).map(|i| (0..3).map(|j| d.accel[i] * q[i][j] * d.accel[j]).sum::<f64>()).sum()
        };
        let first = (0..3).map(|i| d.accel[i] * d.gam[i]).sum::<f64>() + d.half_feedthrough;
        let h = d.half_feedthrough;
        [p[1][1], h * h + first * first + quad(&later)]
    }

    fn discrete(&self, t_s: f64) -> Discrete {
        let ([d0, d1, d2], g) = self.continuous();
        let a = [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-d0, -d1, -d2]];
        let (phi, psi) = zoh(&a, t_s);
        Discrete { phi, gam: mat_vec(&psi, &[0.0, 0.0, g]), accel: [-d0, -d1, -d2], half_feedthrough: g / 2.0 }
    }
}

/// [`Prefilter`] in `f64`, before rounding to the working scalar.
struct Discrete {
    phi: Mat<3>,
    gam: [f64; 3],
    accel: [f64; 3],
    half_feedthrough: f64,
}

/// The discretised pre-filter (the configuration).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prefilter<T> {
    phi: [[T; 3]; 3],
    gam: [T; 3],
    /// `[-d0, -d1, -d2]`: the row of the realisation that gives the second derivative.
    accel: [T; 3],
    /// `w_p^2 / 2`, the direct feed-through of the second derivative (applied to `in[k] + in[k-1]`).
    half_feedthrough: T,
}

/// The pre-filter's state `xi`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PrefilterState<T> {
    xi: [T; 3],
    last_input: T,
}

/// The filtered signal and its first two time derivatives at one sample.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Prefiltered<T> {
    /// `W_p in`.
    pub value: T,
    /// `s W_p in`, per second.
    pub d1: T,
    /// `s^2 W_p in`, per second squared.
    pub d2: T,
}

impl<T: Real> Prefilter<T> {
    /// Whether every constant of the realisation is a finite number (the discretisation of a stable filter,
    /// exact, is stable when it is finite).
    pub fn is_finite(&self) -> bool {
        crate::estimators::all_finite(&[self.phi.as_flattened(), &self.gam, &self.accel, &[self.half_feedthrough]])
    }

    /// The state `s` of the filter `self`, taken over by the filter `to` (a pre-filter changed while the signals
    /// run). The second and third states are the filtered signal and its rate, which carry over as they are; the
    /// first is their integral, `in / w_lc` for an input at rest, so it is rescaled by the ratio of the two `w_lc`:
    /// taken over as it was it stood for another level of the input, `w_lc'` / `w_lc` times the one it had, and the
    /// filtered signal jumped by the difference (the reading 20 um off zero, `f_lc` halved: 16 um in a filtered
    /// reading whose PRBS peaks at 6 um; `tests/instrument.rs`). The same filter: the state stays as it is, to the bit.
    /// Tried instead: the new filter at rest at the last input (`xi = [in / w_lc, 0, 0]`), which also drops what an
    /// old filter still rang with; but it breaks the filtered signals' history, the same for `u` and `y` only
    /// at rest, and with the PRBS running the restarted EKFs came within 1 % after 1.3 s instead of 0.1 s. What the
    /// old state still holds the estimators do not see: the pipeline feeds them again once the new filter has
    /// settled ([`crate::pipeline::Pipeline::retarget`]); the excitation monitor, which runs on every sample, does.
    pub fn retarget(&self, s: &mut PrefilterState<T>, to: &Prefilter<T>) {
        // w_lc = d0 / w_p^2 from the realisation's constants (`accel[0] = -d0`, `half_feedthrough = w_p^2 / 2`), the
        // ratio in one division; the same filter's is 1 exactly.
        s.xi[0] *= (self.accel[0] * to.half_feedthrough) / (self.half_feedthrough * to.accel[0]);
    }

    /// One sample: the outputs at this sample, then the state advanced to the next.
    #[inline]
    pub fn update(&self, s: &mut PrefilterState<T>, input: T) -> Prefiltered<T> {
        let [x1, x2, x3] = s.xi;
        let out = Prefiltered {
            value: x2,
            d1: x3,
            d2: self.accel[0] * x1
                + self.accel[1] * x2
                + self.accel[2] * x3
                + self.half_feedthrough * (input + s.last_input),
        };
        s.last_input = input;
        let p = &self.phi;
        s.xi = [
            p[0][0] * x1 + p[0][1] * x2 + p[0][2] * x3 + self.gam[0] * input,
            p[1][0] * x1 + p[1][1] * x2 + p[1][2] * x3 + self.gam[1] * input,
            p[2][0] * x1 + p[2][1] * x2 + p[2][2] * x3 + self.gam[2] * input,
        ];
        out
    }

    /// The discrete filter's frequency response at `f_hz` for output `order` (0: value, 1: d1, 2: d2):
    /// `C (zI - Phi)^-1 Gam + D`, by Cramer's rule on the 3x3 system.
    pub fn response(&self, order: u32, f_hz: f64, t_s: f64) -> Complex {
        let z = crate::filters::response::z_at(f_hz, t_s);
        let m: [[Complex; 3]; 3] = core::array::from_fn(|i| {
            core::array::from_fn(|j| {
                let d = if i == j { z } else { Complex::new(0.0, 0.0) };
                d - self.phi[i][j].as_f64().into()
            })
        });
        let g: [Complex; 3] = self.gam.map(|x| x.as_f64().into());
        let det3 = |m: &[[Complex; 3]; 3]| {
            m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
                + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
        };
        let det = det3(&m);
        let x: [Complex; 3] = core::array::from_fn(|col| {
            let mut mc = m;
            for (row, gi) in mc.iter_mut().zip(g.iter()) {
                row[col] = *gi;
            }
            det3(&mc) / det
        });
        match order {
            0 => x[1],
            1 => x[2],
            _ => {
                let a = self.accel.map(|v| v.as_f64());
                let zi = Complex::new(1.0, 0.0) / z;
                let half_sum = (Complex::new(1.0, 0.0) + zi).scale(self.half_feedthrough.as_f64());
                x[0].scale(a[0]) + x[1].scale(a[1]) + x[2].scale(a[2]) + half_sum
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{PrefilterDesign, PrefilterState};

    /// A filter settled on a constant input, taken over by one of another `f_lc`, stays at rest (its integral state
    /// rescaled); kept as it was, the new filter's output left rest by about the input times the change. Taken over
    /// by the same filter, the state is the same to the bit.
    #[test]
    fn a_filter_at_rest_taken_over_by_another_stays_at_rest() {
        let t_s = 1e-4;
        let old = PrefilterDesign::default().design::<f64>(t_s);
        let new = PrefilterDesign { f_lc_hz: 50.0, f_p_hz: 600.0, zeta_p: 0.2 }.design::<f64>(t_s);
        let level = 20.0;
        let mut settled = PrefilterState::default();
        for _ in 0..20_000 {
            old.update(&mut settled, level);
        }
        let peak =
            |mut s: PrefilterState<f64>| (0..2_000).map(|_| new.update(&mut s, level).value.abs()).fold(0.0, f64::max);
        let mut taken = settled;
        old.retarget(&mut taken, &new);
        assert!(peak(taken) < 1e-9 * level, "{}", peak(taken));
        assert!(peak(settled) > 0.3 * level, "kept as it was: {}", peak(settled));
        let mut same = settled;
        old.retarget(&mut same, &old);
        assert_eq!(same, settled);
    }

    #[test]
    fn a_centre_more_than_twice_or_half_the_resonance_is_off_it() {
        let p = PrefilterDesign::default(); // f_p = 450 Hz
        for f0 in [225.0, 423.0, 483.0, 900.0] {
            assert_eq!(p.off_resonance(f0), None, "{f0}");
        }
        assert_eq!(p.off_resonance(224.0), Some(450.0 / 224.0));
        assert_eq!(p.off_resonance(901.0), Some(450.0 / 901.0));
        // No resonance to compare with: nothing said.
        for f0 in [0.0, -423.0, f64::NAN, f64::INFINITY] {
            assert_eq!(p.off_resonance(f0), None, "{f0}");
        }
    }
}
