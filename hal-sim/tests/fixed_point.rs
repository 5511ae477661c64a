//! Fixed point (Q31.32) against f64: the biquad replica and the `arx` RLS, from the same generic code.

use hal_sim::experiment::{rel_errors, window_mean, Sample};
use hal_sim::sim::{Scenario, Simulation};
use nanopos_id::estimator::Estimator;
use nanopos_id::estimators::arx::{ArxDesign, ArxEstimator, ArxRls};
use nanopos_id::excitation::{ExcitationDesign, ExcitationState};
use nanopos_id::filters::design::ReplicaDesign;
use nanopos_id::filters::{Biquad, BiquadState};
use nanopos_id::fixed::Q32;
use nanopos_id::Scalar;

#[test]
fn fixed_point_biquad_tracks_f64_within_its_rounding_bound() {
    let design = ReplicaDesign::default().design(10_000.0);
    let fx: Biquad<Q32> = design.cast();
    // The same (quantised) coefficients in f64, so only the arithmetic differs.
    let fl: Biquad<f64> = fx.cast();
    // Noise gain of 1/A(z): the l1 norm of its impulse response.
    let all_pole = Biquad { b: [1.0, 0.0, 0.0], a: fl.a };
    let mut s = BiquadState::default();
    let l1: f64 = (0..20_000).map(|k| all_pole.update(&mut s, if k == 0 { 1.0 } else { 0.0 }).abs()).sum();
    // Five products, each rounded once (|error| <= 2^-33), per sample, through 1/A(z).
    let bound = 5.0 * 2f64.powi(-33) * l1;
    let gen = ExcitationDesign::PAPER_PRBS.design::<f64>(10_000.0);
    let mut ex = ExcitationState::default();
    let (mut sx, mut sf) = (BiquadState::default(), BiquadState::default());
    let mut worst = 0.0f64;
    for _ in 0..200_000 {
        let u = gen.next(&mut ex);
        let a = fx.update(&mut sx, Q32::of(u)).as_f64();
        let b = fl.update(&mut sf, u);
        worst = worst.max((a - b).abs());
    }
    eprintln!("fixed biquad: worst error {worst:.2e}, bound {bound:.2e}");
    assert!(worst <= bound, "{worst:e} > {bound:e}");
}

fn fixed_arx_run(duration_s: f64) -> (Vec<Sample>, Vec<Sample>, Vec<[i64; 4]>) {
    let design = ArxDesign::default();
    let (board, settings) = Scenario::Prbs.settings(duration_s, 1);
    let mut sim = Simulation::new(board, &settings, (ArxEstimator::<f64>::new(design.design()),)).unwrap();
    let cfg_fx = design.design::<Q32>();
    let mut fx = ArxRls::new(&cfg_fx);
    let (mut h64, mut hfx, mut raw) = (Vec::new(), Vec::new(), Vec::new());
    let samples = (duration_s * 10_000.0) as u64;
    for k in 0..samples {
        let truth = sim.board.plant().params();
        let (_, out) = sim.step();
        let s = out.estimator_input.expect("no faults in this run");
        fx.update(&cfg_fx, Q32::of(s.u_f.value), Q32::of(s.y_f.value), true);
        if (k + 1) % 100 == 0 {
            let t_s = (k + 1) as f64 * 1e-4;
            h64.push(Sample { t_s, est: sim.pipeline.estimators.0.params(), truth });
            hfx.push(Sample { t_s, est: fx.stage_f64(&cfg_fx).expect("valid estimate"), truth });
            raw.push(fx.rls().theta().map(|q| q.0));
        }
    }
    (h64, hfx, raw)
}

#[test]
fn fixed_point_arx_agrees_with_f64_within_its_q_format_bound_and_repeats_bit_for_bit() {
    let (h64, hfx, raw) = fixed_arx_run(200.0);
    // Bound from the format: an update rounds ~20 times (each <= 2^-33 = 1.2e-10) into the deviations, and the
    // forgetting (memory 1/(1 - 0.9998) = 5000 samples) lets at most 5000 of those add up: 1.2e-5 in the ARX
    // coefficients, worst case. Through the conversion: a0 ~ (1 - A1 - A2) / T^2 moves by 1.2e-5 / 0.07 = 1.7e-4
    // relative; a1 = -ln(-A2) / T by 1.2e-5 / (T a1) = 1.6e-3; b0 ~ (B1 + B2) a0 / (1 - A1 - A2) by 1.2e-5 / 6.8e-3
    // = 1.8e-3 (B1 + B2 = 6.8e-3 with payload).
    let bound = [1.7e-4, 1.6e-3, 1.8e-3];
    for (t0, t1) in [(75.0, 100.0), (175.0, 200.0)] {
        let (m64, truth) = window_mean(&h64, t0, t1);
        let (mfx, _) = window_mean(&hfx, t0, t1);
        let d = rel_errors(&mfx, &m64);
        let e = rel_errors(&mfx, &truth);
        eprintln!(
            "fixed vs f64, window {t0}-{t1}: a0 {:.1e}, a1 {:.1e}, b0 {:.1e}; fixed vs truth: a0 {:+.4}%, a1 {:+.4}%, b0 {:+.4}%",
            d[0], d[1], d[2], e[0] * 100.0, e[1] * 100.0, e[2] * 100.0
        );
        for i in 0..3 {
            assert!(d[i].abs() <= bound[i], "window {t0}-{t1}, parameter {i}: {:e} > {:e}", d[i], bound[i]);
        }
    }
    eprintln!("fixed arx relock to 1%: {:?} s", hal_sim::experiment::relock_time(&hfx, 100.0, 0.01));
    // Integer arithmetic: a second run is identical to the last bit.
    let (_, _, again) = fixed_arx_run(200.0);
    assert_eq!(raw, again);
}
