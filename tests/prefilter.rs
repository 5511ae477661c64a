//! The identification pre-filter `W_p` against its analytic definition (paper Section II-B).

use nanopos_id::filters::response::Complex;
use nanopos_id::filters::{PrefilterDesign, PrefilterState, Prefiltered};

const T: f64 = 1e-4;

/// The continuous realisation integrated with RK4 at `T / 1000` (an independent path to the same signals).
fn continuous_step_response(design: &PrefilterDesign, samples: usize) -> Vec<Prefiltered<f64>> {
    let ([d0, d1, d2], g) = design.continuous();
    let f = |x: [f64; 3], u: f64| [x[1], x[2], -d0 * x[0] - d1 * x[1] - d2 * x[2] + g * u];
    let sub = 1000;
    let h = T / sub as f64;
    let mut x = [0.0; 3];
    let mut out = Vec::with_capacity(samples);
    for k in 0..samples {
        // The second derivative at the instant the input steps: mean of its left (input 0 before k = 0) and right
        // limits, the pre-filter's documented convention.
        let left = if k == 0 { 0.0 } else { 1.0 };
        out.push(Prefiltered { value: x[1], d1: x[2], d2: 0.5 * (f(x, left)[2] + f(x, 1.0)[2]) });
        for _ in 0..sub {
            x = rk4_step(design, x, 1.0, h);
        }
    }
    out
}

#[test]
fn prefilter_outputs_are_the_exact_samples_of_the_continuous_filter_for_a_held_input() {
    let design = PrefilterDesign::default();
    let filter = design.design::<f64>(T);
    let reference = continuous_step_response(&design, 400);
    let mut state = PrefilterState::default();
    let (mut peak, mut worst) = ([0.0f64; 3], [0.0f64; 3]);
    for r in &reference {
        let d = filter.update(&mut state, 1.0);
        for (i, (a, b)) in [(d.value, r.value), (d.d1, r.d1), (d.d2, r.d2)].into_iter().enumerate() {
            peak[i] = peak[i].max(b.abs());
            worst[i] = worst[i].max((a - b).abs());
        }
    }
    // ZOH is exact for a held input; what remains is RK4's error at h = 1e-7 s ((w h)^4 ~ 1e-14) and rounding.
    for i in 0..3 {
        assert!(worst[i] <= 1e-10 * peak[i], "output {i}: error {:e} of peak {:e}", worst[i], peak[i]);
    }
}

fn peak_frequency(response: impl Fn(f64) -> Complex) -> f64 {
    // Golden-section search for the magnitude maximum between 300 and 600 Hz (the resonant low-pass's peak).
    let (mut a, mut b) = (300.0, 600.0);
    let r = (5f64.sqrt() - 1.0) / 2.0;
    while b - a > 1e-6 {
        let (c, d) = (b - r * (b - a), a + r * (b - a));
        if response(c).abs() > response(d).abs() {
            b = d;
        } else {
            a = c;
        }
    }
    0.5 * (a + b)
}

#[test]
fn prefilter_peaks_where_the_analytic_transfer_function_does() {
    let design = PrefilterDesign::default();
    let filter = design.design::<f64>(T);
    let analog = peak_frequency(|f| design.analog_response(0, f));
    let digital = peak_frequency(|f| filter.response(0, f, T));
    // Analytic: the resonant low-pass peaks at f_p sqrt(1 - 2 zeta^2) = 445.5 Hz; the 100 Hz high-pass tilts that up.
    assert!(analog > 445.0 && analog < 452.0, "analog peak at {analog} Hz");
    // The ZOH equivalent of a held input adds a sinc(f T) droop and aliasing terms of relative size (wT)^2 / 24
    // ~ 3e-3; its slope across the 90 Hz-wide peak moves the maximum by well under 1 Hz.
    assert!((digital - analog).abs() < 1.0, "digital peak {digital} Hz, analog {analog} Hz");
}

/// The exact response of the ZOH equivalent of `H(s)` at `f`: the alias sum
/// `sum_k H(j w_k) (1 - e^{-j w T}) / (j w_k T)`, `w_k = w + k w_s`, summed symmetrically (which, where the filter
/// output jumps at the sample instant, converges to the mean of its left and right limits).
///
/// The asymptote `H(s) ~ h_inf + c / s` is split off and summed in closed form (its sums converge slowly, the
/// constant only conditionally): `sum_k 1 / w_k = (T / 2) cot(w T / 2)` gives `h_inf (1 + z^-1) / 2`, and
/// `sum_k 1 / w_k^2 = (T / 2)^2 / sin^2(w T / 2)` gives `-c (1 - z^-1) T / (4 sin^2(w T / 2))`. The remainder
/// decays as `1/k^3`.
fn zoh_alias_sum(h: impl Fn(f64) -> Complex, h_inf: f64, c: f64, f: f64, terms: i64) -> Complex {
    let fs = 1.0 / T;
    let zinv = Complex::expj(-2.0 * std::f64::consts::PI * f * T);
    let one_minus_zinv = Complex::new(1.0, 0.0) - zinv;
    let half_wt = std::f64::consts::PI * f * T;
    let mut sum = (Complex::new(1.0, 0.0) + zinv).scale(h_inf / 2.0)
        + one_minus_zinv.scale(-c * T / (4.0 * half_wt.sin().powi(2)));
    for k in -terms..=terms {
        let fk = f + k as f64 * fs;
        let s = Complex::new(0.0, 2.0 * std::f64::consts::PI * fk);
        let asymptote = Complex::from(h_inf) + Complex::from(c) / s;
        sum = sum + (h(fk) - asymptote) * one_minus_zinv / s.scale(T);
    }
    sum
}

#[test]
fn prefilter_derivative_outputs_are_s_and_s_squared_times_w_p_sampled_exactly() {
    let design = PrefilterDesign::default();
    let filter = design.design::<f64>(T);
    for f in (1..=49).map(|i| i as f64 * 100.0 - 50.0) {
        for order in 0..3 {
            // s^order W_p(s) = w_p^2 s^(order+1) / (s^3 + d2 s^2 + ...) ~ h_inf + c / s.
            let ([_, _, d2], wp2) = design.continuous();
            let (h_inf, c) = [(0.0, 0.0), (0.0, wp2), (wp2, -wp2 * d2)][order as usize];
            let exact = zoh_alias_sum(|fk| design.analog_response(order, fk), h_inf, c, f, 20_000);
            let h_d = filter.response(order, f, T);
            // The remaining terms decay as 1/k^3: the tail beyond k = 20 000 is far below 1e-7 relative.
            assert!((h_d - exact).abs() <= 1e-7 * exact.abs(), "order {order} at {f} Hz: {h_d:?} vs {exact:?}");
        }
    }
}

#[test]
fn prefilter_outputs_are_the_analytic_ones_delayed_half_a_sample_in_the_resonance_band() {
    // What the estimators use: over 350-550 Hz all three outputs are W_p, s W_p, s^2 W_p of the sampled signal,
    // delayed by T/2, to within the ZOH's sinc droop and aliasing, O((w T)^2 / 8) < 1.5 %.
    let design = PrefilterDesign::default();
    let filter = design.design::<f64>(T);
    for f in (35..=55).map(|i| i as f64 * 10.0) {
        let delay = Complex::expj(-std::f64::consts::PI * f * T);
        let w_t = 2.0 * std::f64::consts::PI * f * T;
        for order in 0..3 {
            let (h_d, h_a) = (filter.response(order, f, T), design.analog_response(order, f) * delay);
            assert!((h_d - h_a).abs() / h_a.abs() < w_t * w_t / 8.0, "order {order} at {f} Hz");
        }
    }
}

/// The white-noise gains (the persistent-excitation monitor's reference for the DAC's rounding) are the sums of the
/// squared impulse responses, for the pre-filter and for the monitor's shaping filter (a pole at 5 Hz: 0.9969 per
/// sample, so the direct sum runs 20 000 samples, e^-63 of the way).
#[test]
fn noise_gains_are_the_sums_of_the_squared_impulse_responses() {
    for design in [PrefilterDesign::default(), nanopos_id::estimator::PE_SPREAD_SHAPE] {
        let filter = design.design::<f64>(T);
        let mut state = PrefilterState::default();
        let mut sums = [0.0f64; 2];
        for k in 0..20_000 {
            let out = filter.update(&mut state, if k == 0 { 1.0 } else { 0.0 });
            sums[0] += out.value * out.value;
            sums[1] += out.d2 * out.d2;
        }
        let gains = design.noise_gains(T);
        for i in 0..2 {
            assert!((gains[i] / sums[i] - 1.0).abs() < 1e-9, "{design:?}: {gains:?} against {sums:?}");
        }
    }
}

/// One RK4 step of `h` seconds of the continuous realisation (`x' = A x + [0, 0, g] u`, `A` the companion form of
/// `W_p`'s denominator) with the input held at `u`.
fn rk4_step(d: &PrefilterDesign, x: [f64; 3], u: f64, h: f64) -> [f64; 3] {
    let ([d0, d1, d2], g) = d.continuous();
    let f = |x: [f64; 3]| [x[1], x[2], -d0 * x[0] - d1 * x[1] - d2 * x[2] + g * u];
    let add = |x: [f64; 3], k: [f64; 3], s: f64| [x[0] + s * k[0], x[1] + s * k[1], x[2] + s * k[2]];
    let k1 = f(x);
    let k2 = f(add(x, k1, h / 2.0));
    let k3 = f(add(x, k2, h / 2.0));
    let k4 = f(add(x, k3, h));
    core::array::from_fn(|i| x[i] + h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]))
}

/// `rk4_amplification` against the thing itself: RK4 steps of `x' = A x` (the companion form of `W_p`'s
/// denominator) at 0.1 ms from a unit state, 2 000 of them. Above 1 the state grows without bound (the
/// continuous-time RLS's own pre-filter then overflows and resets it over and over); below 1 it decays.
#[test]
fn rk4_amplification_says_whether_an_rk4_integration_of_the_prefilter_grows() {
    let h = 1e-4;
    let grows = |d: &PrefilterDesign| {
        // Scaled so that the three states weigh alike (W_p's coefficients span 1e11).
        let w = 2.0 * std::f64::consts::PI * d.f_p_hz.max(d.f_lc_hz);
        let mut x = [1.0, w, w * w];
        let size = |x: &[f64; 3]| x[0].abs() + x[1].abs() / w + x[2].abs() / (w * w);
        for _ in 0..2000 {
            x = rk4_step(d, x, 0.0, h);
        }
        // Overflowed to infinity or NaN counts as grown.
        let s = size(&x);
        s.is_nan() || s >= 1e3
    };
    let cases = [
        ((100.0, 450.0, 0.1), false), // the paper's
        ((100.0, 450.0, 4.0), false),
        ((100.0, 450.0, 6.0), true), // a real pole at -11.9 w: |z| = 3.4
        ((100.0, 4000.0, 0.1), false),
        ((100.0, 4900.0, 0.1), true), // |z| = 3.1, lightly damped
        ((4000.0, 450.0, 0.1), false),
        ((4900.0, 450.0, 0.1), true), // |z| = 3.1 on the real axis
    ];
    // Poles that overflow: above 1 or not a number, refused either way by `Tuning::runnable`.
    for zeta_p in [1e200, 1e300] {
        let a = PrefilterDesign { f_lc_hz: 100.0, f_p_hz: 450.0, zeta_p }.rk4_amplification(h);
        assert!(a.is_nan() || a > 1.0, "{zeta_p}: {a}");
    }
    for ((f_lc_hz, f_p_hz, zeta_p), unstable) in cases {
        let d = PrefilterDesign { f_lc_hz, f_p_hz, zeta_p };
        let a = d.rk4_amplification(h);
        assert_eq!(a > 1.0, unstable, "{d:?}: amplification {a}");
        assert_eq!(grows(&d), unstable, "{d:?}: amplification {a}");
    }
}

/// `rk4_amplification`'s value, not only which side of 1 it falls: the rate at which RK4 steps of `x' = A x` at 0.1 ms
/// decay, measured over steps 1 000 to 4 000, when the slowest mode is left (its ratio per step is the largest
/// `|R(lambda h)|`). With `zeta_p = 4` that is the pair's slower real pole (`|R|` 0.965), not the high-pass corner
/// (0.939) nor the faster pole (0.44), where `|R|` is not monotonic along the real axis.
#[test]
fn rk4_amplification_is_the_decay_per_step_of_the_slowest_rk4_mode() {
    let h = 1e-4;
    let measured = |d: &PrefilterDesign| {
        let w = 2.0 * std::f64::consts::PI * d.f_p_hz.max(d.f_lc_hz);
        let size = |x: &[f64; 3]| x[0].hypot(x[1] / w).hypot(x[2] / (w * w));
        let (mut x, mut at_1000) = ([1.0, 0.3 * w, -0.7 * w * w], 0.0);
        for k in 1..=4000 {
            x = rk4_step(d, x, 0.0, h);
            if k == 1000 {
                at_1000 = size(&x);
            }
        }
        (size(&x) / at_1000).powf(1.0 / 3000.0)
    };
    // (f_lc, f_p, zeta_p): the paper's (the pair slowest), an overdamped pair, a critically damped one, and the
    // high-pass corner slowest.
    for (f_lc_hz, f_p_hz, zeta_p) in [(100.0, 450.0, 0.1), (100.0, 450.0, 4.0), (100.0, 450.0, 1.0), (10.0, 450.0, 0.1)]
    {
        let d = PrefilterDesign { f_lc_hz, f_p_hz, zeta_p };
        let (a, m) = (d.rk4_amplification(h), measured(&d));
        assert!((a / m - 1.0).abs() < 1e-3, "{d:?}: rk4_amplification {a}, measured {m}");
    }
}

/// `slowest_time_constant_s` is the time constant of the pole of `W_p` nearest zero, checked on the denominator
/// `s^3 + d2 s^2 + d1 s + d0` itself: `r = -1 / tau` is a real root of it, or the real part of a complex pair of
/// roots `r +- i w` (with `w^2 = 3 r^2 + 2 d2 r + d1` from the imaginary part, the real part zero to rounding against
/// its largest term), and the roots left by deflation (their sum `-d2` and product `-d0` known) are no nearer zero.
/// For `zeta_p` from 1 on, the pair's slower real pole, slower than the high-pass corner at 4, and at `zeta_p = 1e6`
/// still exact where `z - sqrt(z^2 - 1)` would keep four digits.
#[test]
fn slowest_time_constant_is_that_of_the_pole_nearest_zero() {
    let cases = [
        (100.0, 450.0, 0.1, "the pair"),
        (10.0, 450.0, 0.1, "the high-pass corner"),
        (100.0, 450.0, 1.0, "the pair, critically damped"),
        (100.0, 450.0, 2.0, "the high-pass corner, the pair overdamped"),
        (100.0, 450.0, 4.0, "the pair's slower pole"),
        (100.0, 450.0, 1e6, "the pair's slower pole, far overdamped"),
    ];
    let near_zero = |terms: &[f64]| {
        let largest = terms.iter().fold(0.0_f64, |m, t| m.max(t.abs()));
        terms.iter().sum::<f64>().abs() < 1e-12 * largest
    };
    for (f_lc_hz, f_p_hz, zeta_p, slowest) in cases {
        let d = PrefilterDesign { f_lc_hz, f_p_hz, zeta_p };
        let ([d0, d1, d2], _) = d.continuous();
        let tau = d.slowest_time_constant_s();
        let r = -1.0 / tau;
        let w2 = 3.0 * r * r + 2.0 * d2 * r + d1;
        // The other roots' largest real part.
        let others = if near_zero(&[r * r * r, d2 * r * r, d1 * r, d0]) {
            let (sum, product) = (-d2 - r, -d0 / r);
            let disc = sum * sum - 4.0 * product;
            (sum + if disc > 0.0 { disc.sqrt() } else { 0.0 }) / 2.0
        } else {
            let complex_root = w2 > 0.0 && near_zero(&[r * r * r, -3.0 * r * w2, d2 * (r * r - w2), d1 * r, d0]);
            assert!(complex_root, "{d:?} ({slowest}): tau {tau}: -1/tau is not a root's real part");
            -d2 - 2.0 * r
        };
        assert!(others <= r * (1.0 - 1e-9), "{d:?} ({slowest}): tau {tau}, another root at real part {others}");
    }
    let wp = 2.0 * std::f64::consts::PI * 450.0;
    let d = PrefilterDesign { f_lc_hz: 100.0, f_p_hz: 450.0, zeta_p: 1e6 };
    assert!((d.slowest_time_constant_s() / (2.0 * 1e6 / wp) - 1.0).abs() < 1e-9);
    // A NaN anywhere: NaN, for the caller to refuse (a NaN corner compares as neither slower nor faster).
    for (f_lc_hz, f_p_hz, zeta_p) in [(f64::NAN, 450.0, 0.1), (100.0, f64::NAN, 0.1), (100.0, 450.0, f64::NAN)] {
        let d = PrefilterDesign { f_lc_hz, f_p_hz, zeta_p };
        assert!(d.slowest_time_constant_s().is_nan(), "{d:?}: {}", d.slowest_time_constant_s());
    }
    // An infinite corner is a pole at infinity: the other's.
    let d = PrefilterDesign { f_lc_hz: f64::INFINITY, f_p_hz: 450.0, zeta_p: 0.1 };
    assert_eq!(d.slowest_time_constant_s(), 1.0 / (0.1 * wp));
}

/// `is_finite` says whether the designed filter's constants are all numbers in the working scalar: the paper's in
/// either, a damping of 1e36 (its `d2`, 5.7e39, beyond `f32`'s range) in `f64` but not `f32`, a NaN corner in neither.
#[test]
fn is_finite_says_whether_every_constant_of_the_design_is_a_number_in_its_scalar() {
    let paper = PrefilterDesign::default();
    assert!(paper.design::<f32>(T).is_finite() && paper.design::<f64>(T).is_finite());
    let wide = PrefilterDesign { zeta_p: 1e36, ..paper };
    assert!(wide.design::<f64>(T).is_finite());
    assert!(!wide.design::<f32>(T).is_finite());
    let nan = PrefilterDesign { f_lc_hz: f64::NAN, ..paper };
    assert!(!nan.design::<f32>(T).is_finite() && !nan.design::<f64>(T).is_finite());
}
