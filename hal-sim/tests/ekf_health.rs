//! Health of the estimators, each fault injected into the estimator's input: for the EKFs outliers, NaN, no
//! excitation and a plant change; for all four numeric faults, no excitation and a single sine. (Raw readings
//! cannot be NaN: the board delivers integer codes and the CSV reader rejects non-finite values; a raw one-sample
//! glitch is smeared by the band-pass pre-filter into a few nm.)

#![allow(clippy::needless_range_loop)] // covariance indices follow the state layout

use hal_sim::experiment::{relock_time, Feed, Sample};
use hal_sim::noise::NormalStream;
use hal_sim::plant::{Plant, PlantSettings};
use nanopos_id::estimator::{Adaptation, Estimator, FilteredSample};
use nanopos_id::estimators::ekf::{Cekf, Continuous, Ekf, EkfDesign, EkfKind, Hekf, Hybrid};
use nanopos_id::excitation::{ExcitationDesign, ExcitationState};
use nanopos_id::StageParams;

/// Reference-style data (ideal plant, PRBS, payload off at `change_at_s`) into `est`. `input_off(k)` stops the
/// excitation; `tamper` may alter the estimator's input; `observe` sees the estimator after each sample.
fn drive<E: Estimator<f64>>(
    est: &mut E,
    seconds: f64,
    change_at_s: f64,
    input_off: impl Fn(u64) -> bool,
    tamper: impl FnMut(u64, &mut FilteredSample<f64>),
    observe: impl FnMut(u64, &E),
) {
    drive_raw(est, seconds, change_at_s, input_off, |_, y| y, tamper, observe);
}

/// [`drive`], with `raw(k, y)` the reading the filters see (a glitch in the probe's signal, which the pre-filter
/// spreads over the following samples).
fn drive_raw<E: Estimator<f64>>(
    est: &mut E,
    seconds: f64,
    change_at_s: f64,
    input_off: impl Fn(u64) -> bool,
    raw: impl Fn(u64, f64) -> f64,
    mut tamper: impl FnMut(u64, &mut FilteredSample<f64>),
    mut observe: impl FnMut(u64, &E),
) {
    let gen = ExcitationDesign::PAPER_PRBS.design::<f64>(1e4);
    let mut ex = ExcitationState::default();
    let mut plant =
        Plant::new(PlantSettings::ideal(StageParams::PAYLOAD, StageParams::NO_PAYLOAD, (change_at_s * 1e4) as u64));
    let mut noise = NormalStream::new(1);
    let mut feed = Feed::new(1e-4);
    for k in 0..(seconds * 1e4) as u64 {
        let y = plant.output_um() + 1.25e-3 * noise.next_normal();
        let u = if input_off(k) { 0.0 } else { gen.next(&mut ex) };
        let mut s = feed.sample(u, raw(k, y));
        tamper(k, &mut s);
        est.update(&s);
        observe(k, est);
        plant.advance(u);
    }
}

fn rel(p: &StageParams<f64>, q: &StageParams<f64>) -> f64 {
    [(p.a0, q.a0), (p.a1, q.a1), (p.b0, q.b0)].iter().map(|(a, b)| (a / b - 1.0).abs()).fold(0.0, f64::max)
}

#[test]
fn gating_rejects_outliers_and_keeps_the_estimate() {
    let design = EkfDesign::default();
    let run = |design: EkfDesign, spikes: bool| {
        let mut est = Hekf::new(design.design());
        // 0.2 um in the filtered reading (about 50 noise sigmas) once a second after convergence.
        let tamper = |k: u64, s: &mut FilteredSample<f64>| {
            if spikes && k > 20_000 && k % 10_000 == 0 {
                s.y_f.value += 0.2;
            }
        };
        drive(&mut est, 10.0, f64::INFINITY, |_| false, tamper, |_, _| {});
        est
    };
    let clean = run(design, false);
    let gated = run(design, true);
    let mut no_gate = design;
    no_gate.health.change_samples = 0;
    let ungated = run(no_gate, true);
    let h = gated.health();
    let (eg, eu) = (rel(&gated.params(), &clean.params()), rel(&ungated.params(), &clean.params()));
    eprintln!("outliers: rejected {}, error vs clean: gated {eg:.1e}, ungated {eu:.1e}", h.rejected_samples);
    assert_eq!(h.rejected_samples, 7, "exactly the 7 outliers (k = 30 000 .. 90 000)");
    assert_eq!(h.changes_detected, 0);
    assert!(eg < 0.1 * eu, "gating keeps the estimate ({eg:e} vs {eu:e})");
}

/// A NaN in the filtered reading, or an infinity in the filtered input, each alone: the filter is reset and the
/// fault counted as a numeric reset, and only as that (no rejected outlier, no change); it converges again.
fn a_non_finite_value_resets_the_filter<K: EkfKind>(tamper: fn(&mut FilteredSample<f64>)) {
    let mut est = Ekf::<f64, K>::new(EkfDesign::default().design());
    let once = |k: u64, s: &mut FilteredSample<f64>| {
        if k == 10_000 {
            tamper(s);
        }
    };
    drive(&mut est, 4.0, f64::INFINITY, |_| false, once, |_, _| {});
    let h = est.health();
    assert_eq!((h.numeric_resets, h.rejected_samples, h.changes_detected), (1, 0, 0), "{}", K::NAME);
    let p = est.params();
    // Three seconds after the reset it has converged again.
    assert!(rel(&p, &StageParams::PAYLOAD) < 5e-3, "{}: {p:?}", K::NAME);
}

#[test]
fn a_nan_or_an_infinity_resets_the_filter_counts_it_and_the_filter_carries_on() {
    // A NaN reading, an infinite input.
    let tampers: [fn(&mut FilteredSample<f64>); 2] = [|s| s.y_f.value = f64::NAN, |s| s.u_f.value = f64::INFINITY];
    for tamper in tampers {
        a_non_finite_value_resets_the_filter::<Continuous>(tamper);
        a_non_finite_value_resets_the_filter::<Hybrid>(tamper);
    }
}

/// One reading of 10^4 um (a glitch; the PRBS's reading stays within 0.3 um): the pre-filter spreads it over tenths
/// of a second, the gate sees a change and opens, and the continuous filter follows the ring until its innovation's
/// square overflows. Its state stayed finite, so it was not reset: it ran on for good with `a0` 60 times the truth, a
/// change detected every 20 samples and an innovation RMS of NaN. Now an innovation RMS beyond a metre
/// (`INNOVATION_CEILING_UM`) resets it (counted) until the ring has passed, and it converges again.
#[test]
fn a_glitch_that_throws_the_continuous_filter_off_resets_it() {
    let mut est = Cekf::new(EkfDesign::default().design());
    let glitch = |k: u64, y: f64| if k == 10_000 { y + 1e4 } else { y };
    let mut worst_after = 0.0f64;
    let observe = |k: u64, e: &Cekf<f64>| {
        if k >= 50_000 {
            worst_after = worst_after.max(rel(&e.params(), &StageParams::PAYLOAD));
        }
    };
    drive_raw(&mut est, 10.0, f64::INFINITY, |_| false, glitch, |_, _| {}, observe);
    let h = est.health();
    eprintln!(
        "glitch: resets {}, innovation RMS {} um, worst error 5-10 s {worst_after:.1e}",
        h.numeric_resets, h.innovation_rms_um
    );
    assert!(h.numeric_resets > 0 && h.innovation_rms_um.is_finite(), "{h:?}");
    // Converged again: the last reset met the ring's tail and the filter took until about 4 s (within 1 % at 3.75 s,
    // 0.26 % at 4 s) to come back from it.
    assert!(worst_after < 5e-3, "{worst_after}");
}

/// One reading of 10^5 um (10^5 times the PRBS's level; a logger's overflow value in a record replayed on the host,
/// as the board's ADC cannot deliver one): its ring through the pre-filter passes for a plant change, the gate opens
/// and the hybrid filter follows the ring into a wrong optimum, every value finite. It stayed there for good (at the
/// start `b0` negative and `a0` 40 times the truth; at 7 s, parameters off by 1 600 % to 3 500 % 7 to 13 s later,
/// the innovation RMS 2 um against 1 nm), its gate's and drift detector's references following its own innovations,
/// and missed the payload change. Now, when drift detection resumes 5 s after the change it saw, `nu^2 / S` is still
/// more than `RELOCK_NIS_RATIO` (100) times 1, what a filter whose noise model is right averages, and the filter is
/// reset (counted) and converges again: a glitch at 0.1 s or at 7 s (after the start's wait). The same data without
/// the glitch, payload change included, resets it never.
#[test]
fn a_filter_that_does_not_relock_is_reset() {
    for glitch_s in [None, Some(0.1), Some(7.0)] {
        let mut est = Hekf::new(EkfDesign::default().design());
        let at = glitch_s.map_or(u64::MAX, |s: f64| (s * 1e4) as u64);
        let glitch = |k: u64, y: f64| if k == at { y + 1e5 } else { y };
        // The payload comes off at 16 s, after the filter reset at 12 s has converged again.
        let (mut worst_before, mut worst_after) = (0.0f64, 0.0f64);
        let observe = |k: u64, e: &Hekf<f64>| {
            if (140_000..160_000).contains(&k) {
                worst_before = worst_before.max(rel(&e.params(), &StageParams::PAYLOAD));
            } else if k >= 180_000 {
                worst_after = worst_after.max(rel(&e.params(), &StageParams::NO_PAYLOAD));
            }
        };
        drive_raw(&mut est, 20.0, 16.0, |_| false, glitch, |_, _| {}, observe);
        let h = est.health();
        eprintln!(
            "glitch at {glitch_s:?} s: resets {}, changes {}, worst error 14-16 s {worst_before:.1e}, 18-20 s \
             {worst_after:.1e}",
            h.numeric_resets, h.changes_detected
        );
        assert_eq!(h.numeric_resets, u32::from(glitch_s.is_some()), "{glitch_s:?}: {h:?}");
        assert!(worst_before < 1e-3 && worst_after < 1e-3, "{glitch_s:?}: {worst_before:e} {worst_after:e}");
    }
}

/// Innovations more than 10 times what the filter's `R` allows for, for good (here 2 um of white noise added to the
/// filtered reading, 16 times the 122 nm per sample the paper's `R / T` stands for): the filter did not relock by
/// `RELOCK_NIS_RATIO`'s test, and is reset, once; the level that failed is the next wait's reference, so it is not
/// reset every 5 s (it was 5 times in 30 s when the reference went back to 1), nor taken for a drift. A filter
/// merely told of less noise than there is (`R` down to 1e-8 of the paper's, the probe's 1.25 nm against 0.012 nm)
/// is not reset: its own covariance grows to match.
#[test]
fn a_filter_whose_innovations_exceed_its_noise_model_for_good_is_reset_once() {
    for r in [1.5e-10, 1.5e-12, 1.5e-14] {
        let mut est = Hekf::new(EkfDesign { r, ..EkfDesign::default() }.design());
        drive(&mut est, 30.0, f64::INFINITY, |_| false, |_, _| {}, |_, _| {});
        assert_eq!(est.health().numeric_resets, 0, "R = {r}");
    }
    let mut est = Hekf::new(EkfDesign::default().design());
    let mut extra = NormalStream::new(7);
    let noisy = |_: u64, s: &mut FilteredSample<f64>| s.y_f.value += 2.0 * extra.next_normal();
    let (mut resets_at, mut changes_at) = (Vec::new(), Vec::new());
    let observe = |k: u64, e: &Hekf<f64>| {
        if e.health().numeric_resets as usize > resets_at.len() {
            resets_at.push(k as f64 * 1e-4);
        }
        if e.health().changes_detected as usize > changes_at.len() {
            changes_at.push(k as f64 * 1e-4);
        }
    };
    drive(&mut est, 30.0, f64::INFINITY, |_| false, noisy, observe);
    eprintln!("resets at {resets_at:?} s, changes at {changes_at:?} s");
    assert_eq!(resets_at.len(), 1, "{resets_at:?}");
    // With the failed level as its reference, the drift detector stays quiet while the noise stays the same (a
    // change is seen once, 62 ms after the reset, as the filter starts again from its initial parameters).
    assert!(changes_at.iter().all(|&t| t < resets_at[0] + 1.0), "{changes_at:?}");
}

/// A NaN in the measurement and an infinity in the input, each in the raw and the pre-filtered value (the
/// continuous-time RLS reads the raw ones): each resets the estimator to its initial state and is counted, no
/// estimate is ever non-finite, and the estimator converges again. `seconds` of the reference-style PRBS, faults at
/// 1 s and 2 s; at the end every parameter within `tol` of the truth (measured after 40 s: the RLS 3.3e-4, the ARX
/// 1.0e-4).
fn numeric_faults_reset_and_count<E: Estimator<f64>>(mut est: E, seconds: f64, tol: f64) {
    let faults = |k: u64, s: &mut FilteredSample<f64>| match k {
        10_000 => (s.y, s.y_f.value) = (f64::NAN, f64::NAN),
        20_000 => (s.u, s.u_f.value) = (f64::INFINITY, f64::INFINITY),
        _ => {}
    };
    let mut non_finite = 0u32;
    let observe = |_: u64, e: &E| {
        let p = e.params();
        non_finite += u32::from(![p.a0, p.a1, p.b0].iter().all(|v| v.is_finite()));
    };
    drive(&mut est, seconds, f64::INFINITY, |_| false, faults, observe);
    assert_eq!((E::NAME, est.health().numeric_resets, non_finite), (E::NAME, 2, 0));
    let p = est.params();
    assert!(rel(&p, &StageParams::PAYLOAD) < tol, "{}: {p:?}", E::NAME);
}

#[test]
fn numeric_faults_in_the_rls_and_the_arx_reset_them_and_are_counted() {
    use nanopos_id::estimators::arx::{ArxDesign, ArxEstimator};
    use nanopos_id::estimators::crls::{Crls, CrlsDesign};
    numeric_faults_reset_and_count(Crls::new(CrlsDesign::default().design()), 40.0, 2e-3);
    numeric_faults_reset_and_count(ArxEstimator::new(ArxDesign::default().design()), 40.0, 2e-3);
}

/// The excitation stops at 30 s (every estimator converged) and comes back at 60 s: within 0.2 s the estimator
/// reports `Starved` and holds its parameters (moved by less than 1e-3 meanwhile, then not at all), and adapts again
/// once the input is back. Returns the estimator after 65 s.
fn starves_and_holds<E: Estimator<f64>>(mut est: E) -> E {
    let (stop, back) = (300_000, 600_000);
    let mut at_freeze = None;
    let (mut before_stop, mut before_back) = (StageParams::default(), StageParams::default());
    drive(
        &mut est,
        65.0,
        f64::INFINITY,
        |k| (stop..back).contains(&k),
        |_, _| {},
        |k, e| {
            if k == stop - 1 {
                before_stop = e.params();
            }
            if k == back - 1 {
                before_back = e.params();
            }
            if k >= stop && at_freeze.is_none() && e.health().adaptation == Adaptation::Starved {
                at_freeze = Some((k, e.params()));
            }
        },
    );
    let (k_freeze, p_freeze) = at_freeze.expect("starves");
    let delay_s = (k_freeze - stop) as f64 * 1e-4;
    let drift = rel(&p_freeze, &before_stop);
    eprintln!("{}: starved {delay_s:.3} s after the input stopped, drift meanwhile {drift:.1e}", E::NAME);
    assert!(delay_s < 0.2 && drift < 1e-3, "{}", E::NAME);
    assert_eq!(before_back, p_freeze, "{}: held parameters do not move in 30 s", E::NAME);
    assert_eq!(est.health().adaptation, Adaptation::Adapting, "{}", E::NAME);
    est
}

#[test]
fn without_excitation_the_parameters_freeze_and_the_covariance_stays_bounded() {
    let est = starves_and_holds(Hekf::new(EkfDesign::default().design()));
    let c = est.covariance();
    let ceiling = EkfDesign::default().health.ceiling;
    for i in 2..5 {
        assert!(c[i][i] <= ceiling * 10.0 * EkfDesign::Q2[i] * (1.0 + 1e-9), "variance {i} above the ceiling");
    }
}

/// The same monitor holds the continuous-time RLS and the ARX. Without it their covariance bounds kept `P` and `F`
/// finite but not the estimates: 10 s after the excitation stopped the noise had carried them 66 % and 123 % off,
/// and over the next 4 minutes up to 74 % and 261 % (the largest relative error of a0, a1, b0).
#[test]
fn without_excitation_the_rls_and_the_arx_hold_their_estimates() {
    use nanopos_id::estimators::arx::{ArxDesign, ArxEstimator};
    use nanopos_id::estimators::crls::{Crls, CrlsDesign};
    starves_and_holds(Crls::new(CrlsDesign::default().design()));
    starves_and_holds(ArxEstimator::new(ArxDesign::default().design()));
}

#[test]
fn change_detection_on_the_payload_change() {
    let mut relocks = Vec::new();
    for detect in [true, false] {
        let mut design = EkfDesign::default();
        if !detect {
            design.health.change_samples = 0;
            design.health.drift_ratio = 0.0;
        }
        let mut est = Hekf::new(design.design());
        let mut history = Vec::new();
        drive(
            &mut est,
            15.0,
            5.0,
            |_| false,
            |_, _| {},
            |k, e| {
                if k % 100 == 99 {
                    let t_s = (k + 1) as f64 * 1e-4;
                    let truth = if t_s <= 5.0 { StageParams::PAYLOAD } else { StageParams::NO_PAYLOAD };
                    history.push(Sample { t_s, est: e.params(), truth });
                }
            },
        );
        let relock = relock_time(&history, 5.0, 0.01);
        let h = est.health();
        eprintln!(
            "change detection {detect}: detected {}, rejected {}, relock to 1 % {relock:?} s",
            h.changes_detected, h.rejected_samples
        );
        assert_eq!(h.changes_detected, u32::from(detect));
        relocks.push(relock.expect("relocks"));
    }
    // With PRBS the filter relocks in well under a second either way; detection must not slow it much.
    assert!(relocks[0] < 1.0 && relocks[0] <= 1.5 * relocks[1], "{relocks:?}");
}

/// The drift detector compares the last half second of `nu^2 / S` with the last 10 s. On a plant that does not
/// change, over 100 s of each input on the full board (its second mode, filters and converters: a misfit the model
/// cannot remove), with each input's own tuning, it must stay quiet: every false alarm reopens the covariance and
/// costs a relock.
#[test]
fn drift_detection_stays_quiet_on_an_unchanging_plant() {
    use hal_sim::sim::{Scenario, Simulation};
    for (scenario, q) in [(Scenario::Prbs, EkfDesign::Q2), (Scenario::Triangle, EkfDesign::Q1)] {
        let (mut board, settings) = Scenario::settings(scenario, 100.0, scenario.default_seed());
        board.plant.change_at_sample = u64::MAX;
        let d = EkfDesign::paper(q).design();
        let mut sim = Simulation::new(board, &settings, (Hekf::<f64>::new(d), Cekf::<f64>::new(d))).unwrap();
        for _ in 0..1_000_000 {
            sim.step();
        }
        let (h, c) = (sim.pipeline.estimators.0.health(), sim.pipeline.estimators.1.health());
        eprintln!("{scenario:?} without a change: hybrid {h:?}, continuous {c:?}");
        assert_eq!((h.changes_detected, c.changes_detected), (0, 0), "{scenario:?}");
        // No numeric reset, and no repair of the covariance either (the next test has one).
        assert_eq!((h.numeric_resets, c.numeric_resets), (0, 0), "{scenario:?}");
        assert_eq!((h.covariance_repairs, c.covariance_repairs), (0, 0), "{scenario:?}");
    }
}

/// The continuous filter integrates the Riccati equation in one RK4 step per sample, and a state variance can
/// overshoot below zero. With the paper's PRBS tuning (`Q2`) on the smoothed triangle, the misfit of the next test,
/// its `x2` variance does so about 14 times a second on every noise seed (first 0.7-1.3 s after the start, seeds
/// 1-6). Each time it is repaired in place (`bound_covariance`: the state decorrelated, its variance floored),
/// counted, and the filter carries on without a reset. (With the right tuning, `Q1`, the same start needs no repair:
/// the test above. Until the EKFs took their states from the first sample, with the variance of one measurement,
/// `Q1` with the excitation monitor off needed one, 30 ms after the start: that was this test's case.)
#[test]
fn a_negative_state_variance_is_repaired_and_counted() {
    use hal_sim::sim::{Scenario, Simulation};
    let (mut board, settings) = Scenario::settings(Scenario::Triangle, 100.0, Scenario::Triangle.default_seed());
    board.plant.change_at_sample = u64::MAX;
    let d = EkfDesign::paper(EkfDesign::Q2);
    let mut sim = Simulation::new(board, &settings, (Cekf::<f64>::new(d.design()),)).unwrap();
    let mut first = None;
    for k in 0..20_000 {
        sim.step();
        if first.is_none() && sim.pipeline.estimators.0.health().covariance_repairs > 0 {
            first = Some(k);
        }
    }
    let (h, p) = (sim.pipeline.estimators.0.health(), sim.pipeline.estimators.0.params());
    eprintln!("first repair at sample {first:?}; after 2 s: {h:?}, {p:?}");
    assert!(first.is_some_and(|k| k < 15_000), "{first:?}");
    assert!(h.covariance_repairs >= 2, "{h:?}");
    assert_eq!(h.numeric_resets, 0, "{h:?}");
    assert!(p.a0.is_finite() && p.a1.is_finite() && p.b0.is_finite(), "{p:?}");
    assert!(h.innovation_rms_um < 0.01, "{h:?}");
}

#[test]
fn the_wrong_tuning_for_the_input_is_reported_not_turned_into_nan() {
    // The paper's PRBS tuning (Q2) on the smoothed triangle fails (the float64 reference: b0 -15 %, a1 +38 %). The
    // filter must stay finite and its health must show the misfit: its innovations are far above the noise that
    // the right tuning (Q1) leaves.
    use hal_sim::sim::{Scenario, Simulation};
    let mut rms = Vec::new();
    for q in [EkfDesign::Q1, EkfDesign::Q2] {
        let (board, settings) = Scenario::Triangle.settings(60.0, 2);
        let mut sim = Simulation::new(board, &settings, (Hekf::<f64>::new(EkfDesign::paper(q).design()),)).unwrap();
        for _ in 0..600_000 {
            sim.step();
        }
        let est = &sim.pipeline.estimators.0;
        let (p, h) = (est.params(), est.health());
        assert!(p.a0.is_finite() && p.a1.is_finite() && p.b0.is_finite());
        assert_eq!(h.numeric_resets, 0);
        eprintln!(
            "triangle with {}: innovation RMS {:.2} nm, estimate error {:.1} %",
            if q == EkfDesign::Q1 { "Q1" } else { "Q2" },
            h.innovation_rms_um * 1e3,
            100.0 * rel(&p, &StageParams::NO_PAYLOAD)
        );
        rms.push(h.innovation_rms_um);
    }
    assert!(rms[1] > 2.0 * rms[0], "Q2's misfit shows in its innovations: {rms:?}");
}

/// Seconds after the payload change on the full board's triangle (noise `seed`) until `a0` and `b0` stay within 3 %
/// of their mean over 175-200 s, f64 and f32.
fn board_triangle_settle<K: EkfKind>(d: &EkfDesign, seed: u64) -> [Option<f64>; 2]
where
    Ekf<f64, K>: Estimator<f64>,
    Ekf<f32, K>: Estimator<f32>,
{
    use hal_sim::experiment::{run, settle_time};
    use hal_sim::sim::Scenario;
    let new64 = || Ekf::<f64, K>::new(d.design());
    let new32 = || Ekf::<f32, K>::new(d.design());
    let h = run(Scenario::Triangle, 200.0, seed, new64, new32, |_, _| {});
    assert_eq!(h.code_mismatches, 0, "the paper's triangle: f32 and f64 command the same codes");
    [&h.f64, &h.f32].map(|h| settle_time(h, 100.0, (175.0, 200.0), 0.03))
}

/// On the full board the payload comes off with a kick (the disturbance bump: 300 um/s, a ring of about 0.1 um at
/// the new resonance). The gate sees it and reports a change; reopening only the parameters then let the filter
/// explain the ring by moving them (b0 to -105 % on the triangle, 0.1 s after the change) and the triangle's weak
/// excitation took 8-18 s to bring them back. The state is reopened too (to `R / T`), so the ring is a state.
/// Relock here is against the estimates' own mean over 175-200 s (the second mode biases the triangle's b0 by
/// +2.9 %, so the truth is out of reach, and the estimates wander 1.4 % about their mean): within 3 %.
/// Measured, seeds 1-4, hybrid / continuous (f32 the same): 0.58 0.80 0.75 0.49 / 0.59 0.80 0.75 0.49 s (the
/// parameters alone: 9.6 13.9 17.7 8.0 / 8.0 13.9 17.7 7.5 s; seeds 5-8 alike). On the paper's PRBS run the hybrid
/// filter's relock to the truth went from 0.37 to 0.21 s, the continuous one's stayed 0.21 s.
#[test]
fn the_bump_of_the_payload_change_is_explained_as_a_state() {
    use nanopos_id::estimators::ekf::{Continuous, Hybrid};
    let d = EkfDesign::paper(EkfDesign::Q1);
    let seeds = [1u64, 2, 3, 4];
    let settles: Vec<[Option<f64>; 4]> = std::thread::scope(|s| {
        let jobs: Vec<_> = seeds
            .iter()
            .map(|&seed| {
                s.spawn(move || {
                    let ([h64, h32], [c64, c32]) =
                        (board_triangle_settle::<Hybrid>(&d, seed), board_triangle_settle::<Continuous>(&d, seed));
                    [h64, h32, c64, c32]
                })
            })
            .collect();
        jobs.into_iter().map(|j| j.join().unwrap()).collect()
    });
    for (seed, t) in seeds.iter().zip(&settles) {
        eprintln!(
            "board triangle, seed {seed}: settled within 3 % after [hybrid f64, f32, continuous f64, f32] {t:?} s"
        );
    }
    assert!(settles.iter().flatten().all(|t| t.is_some_and(|t| t <= 2.0)), "{settles:?}");
}

/// The innovation RMS in the health report restarts with the estimator: a reset (the user's, or one after a
/// non-finite value) does not carry the old run's level, or a blow-up's, into the new one.
#[test]
fn the_innovation_rms_restarts_with_the_filter() {
    let mut est = Hekf::new(EkfDesign::default().design());
    drive(&mut est, 2.0, f64::INFINITY, |_| false, |_, _| {}, |_, _| {});
    assert!(est.health().innovation_rms_um > 0.0);
    est.reset();
    assert_eq!(est.health().innovation_rms_um, 0.0);
}

/// The innovation RMS in the health report is of the last second: it shows the payload change, and 2.5 s later it
/// is back at the noise. Measured: both EKFs relock within 0.25 s; their innovation RMS, 0.92-0.93 nm before the
/// change (the pre-filtered noise), reads 94-95 nm in the second after it and 0.96-0.99 nm 2.5 s after. As an
/// exponential average of the squares with a time constant of 1 s (its form before) it read 28 nm 2.5 s after the
/// change (16 times its level before, itself still 1.8 times the noise 5 s after the start, from the start-up) and
/// came within 10 % of the noise only about 10 s after.
fn innovation_rms_after_a_change<K: EkfKind>() -> [f32; 3]
where
    Ekf<f64, K>: Estimator<f64>,
{
    let mut est = Ekf::<f64, K>::new(EkfDesign::default().design());
    let mut rms = [f32::NAN; 3];
    drive(
        &mut est,
        7.5,
        5.0,
        |_| false,
        |_, _| {},
        |k, e| match k {
            49_999 => rms[0] = e.health().innovation_rms_um,
            55_000 => rms[1] = e.health().innovation_rms_um,
            74_999 => rms[2] = e.health().innovation_rms_um,
            _ => {}
        },
    );
    rms
}

#[test]
fn the_innovation_rms_is_of_the_last_second() {
    for (name, [before, after, later]) in
        [("hekf", innovation_rms_after_a_change::<Hybrid>()), ("ekf", innovation_rms_after_a_change::<Continuous>())]
    {
        eprintln!("{name}: innovation RMS before the change {before:.3e} um, 0.5 s after {after:.3e}, 2.5 s after {later:.3e}");
        assert!(before < 1.5e-3, "{name}: {before} (the noise: 1.25e-3 um before the pre-filter)");
        assert!(after > 10.0 * before, "{name}: the change shows: {after} against {before}");
        assert!(later < 1.2 * before, "{name}: gone 2.5 s after: {later} against {before}");
    }
}

/// The paper's PRBS on the board for 30 s, then a sine of `volts` at `hz` for 10 s (no payload change): the relative
/// change of `E`'s f64 and f32 estimates (largest of a0, a1, b0) from 30 s to 30.5 s and from 30.5 s to 40 s.
fn drift_under_a_sine<E64: Estimator<f64>, E32: Estimator<f32>>(
    (hz, volts): (f64, f64),
    new64: impl FnOnce() -> E64,
    new32: impl FnOnce() -> E32,
) -> [[f64; 2]; 2] {
    drift_after_prbs(ExcitationDesign::sine(hz, volts), true, new64, new32)
}

/// 30 s of the board's PRBS (its payload kept on), then 10 s of `excitation`, on the full board or without its second
/// mode: per f64 and f32, the estimate's largest relative change over 30-30.5 s and over 30.5-40 s.
fn drift_after_prbs<E64: Estimator<f64>, E32: Estimator<f32>>(
    excitation: ExcitationDesign,
    second_mode: bool,
    new64: impl FnOnce() -> E64,
    new32: impl FnOnce() -> E32,
) -> [[f64; 2]; 2] {
    use hal_sim::experiment::run_scheduled;
    use hal_sim::sim::Scenario;
    let mut switch = |k: u64| {
        (k == 300_000).then(|| {
            let (_, mut p) = Scenario::Prbs.settings(40.0, 1);
            p.excitation = excitation;
            p
        })
    };
    let board = |b: &mut hal_sim::board::BoardSettings, _: &mut _| {
        b.plant.change_at_sample = u64::MAX;
        if !second_mode {
            b.plant.second_mode = None;
        }
    };
    let h = run_scheduled(Scenario::Prbs, 40.0, 1, new64, new32, board, &mut switch);
    [&h.f64, &h.f32].map(|h| {
        let at = |t: f64| h.iter().find(|s| (s.t_s - t).abs() < 1e-6).expect("sampled").est;
        [rel(&at(30.5), &at(30.0)), rel(&at(40.0), &at(30.5))]
    })
}

/// A single sinusoid identifies a gain and a phase, not three parameters: the monitor sees it (the spread of the
/// input through its shaping filter, `estimator::PeMonitor`) and holds every estimator from 0.5 s after the switch
/// from PRBS on, from 5 Hz to 1 kHz at 1 V, and the small or fast sines whose spread is the DAC's rounding (450 Hz
/// at 0.1 V, 1 200 Hz at 50 mV, 3.5 kHz at 1 V), which without the rounding floor moved rls / arx / hekf / cekf by
/// 0.75 / 264 / 0.50 / 0.47 %, 38 / 243 / 0.04 / 0.04 % and 57 / 294 / 0.03 / 0.02 % over 30.5-40 s. Measured,
/// largest parameter change over 30.5-40 s, rls / arx / hekf / cekf: 0 for all. With the power test alone, at 100,
/// 450 and 1 000 Hz: 20 / 274 / 2.3 / 2.2 %, 0.5 / 278 / 0.1 / 0.1 % and 391 / 284 / 1.6 / 1.6 %; with the spread
/// measured on the pre-filtered input `u_f` instead (as it once was), whose curvature below about 60 Hz is the
/// DAC's rounding, at 5, 20 and 50 Hz: 41 / 240 / 1.1 / 1.1 %, 5 / 80 / 2.9 / 2.8 % and 11 / 267 / 2.9 / 2.9 %. Before
/// the monitor sees the sine (30-30.5 s) the estimates move at most 0.8 % (the EKFs at 450 Hz) but for the RLS at 1
/// kHz, 3.6 %: held to 5 %.
#[test]
fn a_single_sine_starves_every_estimator() {
    use nanopos_id::estimators::arx::{ArxDesign, ArxEstimator};
    use nanopos_id::estimators::crls::{Crls, CrlsDesign};
    let (ekf, rls, arx) = (EkfDesign::default(), CrlsDesign::default(), ArxDesign::default());
    // Per sine (Hz, V), per estimator, f64 and f32: [change before the monitor sees it, change after].
    type Drifts = [[[f64; 2]; 2]; 4];
    let drifts: Vec<((f64, f64), Drifts)> = std::thread::scope(|s| {
        let sines = [(5.0, 1.0), (20.0, 1.0), (50.0, 1.0), (100.0, 1.0), (450.0, 1.0), (1000.0, 1.0)];
        let small_or_fast = [(450.0, 0.1), (1200.0, 0.05), (3500.0, 1.0)];
        let jobs: Vec<_> = sines
            .into_iter()
            .chain(small_or_fast)
            .map(|sine| {
                s.spawn(move || {
                    let d = [
                        drift_under_a_sine(sine, || Crls::<f64>::new(rls.design()), || Crls::<f32>::new(rls.design())),
                        drift_under_a_sine(
                            sine,
                            || ArxEstimator::<f64>::new(arx.design()),
                            || ArxEstimator::<f32>::new(arx.design()),
                        ),
                        drift_under_a_sine(sine, || Hekf::<f64>::new(ekf.design()), || Hekf::<f32>::new(ekf.design())),
                        drift_under_a_sine(sine, || Cekf::<f64>::new(ekf.design()), || Cekf::<f32>::new(ekf.design())),
                    ];
                    (sine, d)
                })
            })
            .collect();
        jobs.into_iter().map(|j| j.join().unwrap()).collect()
    });
    for ((hz, volts), d) in &drifts {
        eprintln!(
            "sine {hz} Hz {volts} V: change [f64: 30-30.5 s, 30.5-40 s; f32: the same] rls {:?} arx {:?} \
             hekf {:?} cekf {:?}",
            d[0], d[1], d[2], d[3]
        );
    }
    assert!(
        drifts.iter().all(|(_, d)| d.iter().flatten().all(|[delay, held]| *delay < 5e-2 && *held == 0.0)),
        "{drifts:?}"
    );
}

/// A limit, kept measured: a sine the output clamp clips (8 V + 3 V sin at 100 Hz, above the DAC's reach of 8.78 V
/// 42 % of the time, counted in `FaultCounters::limited`) is no longer a sine: its harmonics reach the estimators,
/// and the monitor passes it part of the time. What the hybrid filter then learns is biased by the stage's second
/// mode, as on the full board's triangle: after 30 s of PRBS it moved by 1.5 % over the first 0.5 s of the clipped
/// sine and by 2.1 % over the next 9.5 s (f64 and f32 alike), and by 0.05 % and 0.5 % with the second mode switched
/// off (clipped at 10 V, before the DAC's reach was modelled, 27 % of the time: 1.7 and 1.6 %, 0.06 and 0.3 %). The
/// output limits are not a waveform generator.
#[test]
fn a_clipped_sine_is_rich_and_biased_by_the_second_mode() {
    let ekf = EkfDesign::default();
    let clipped = ExcitationDesign { offset_v: 8.0, ..ExcitationDesign::sine(100.0, 3.0) };
    let [full, without] = std::thread::scope(|s| {
        [true, false]
            .map(|mode| {
                s.spawn(move || {
                    drift_after_prbs(
                        clipped,
                        mode,
                        || Hekf::<f64>::new(ekf.design()),
                        || Hekf::<f32>::new(ekf.design()),
                    )
                })
            })
            .map(|j| j.join().unwrap())
    });
    eprintln!("clipped sine, the hybrid filter's change [f64: 30-30.5 s, 30.5-40 s; f32]: {full:?}; without the second mode {without:?}");
    assert!(full.iter().flatten().all(|&change| change > 0.01), "{full:?}");
    assert!(without.iter().all(|&[first, then]| first < 0.002 && then < 0.006), "{without:?}");
}

/// The smoothed triangle (harmonics to 1 kHz) on the board: the paper's 10 Hz triangle is never taken for a single
/// sinusoid, at 1 V or 0.1 V. A documented limit: from about 200 Hz it always is (its harmonics, at 1/9 and 1/25 of
/// the fundamental, weigh little through the monitor's shaping filter), so it starves the estimators; 30 and 50 Hz
/// triangles are taken for one 15 to 21 % of the time, and a 100 Hz triangle at 0.1 V half the time. Should the
/// second assertion fail, the monitor has learned to see such triangles: the README's limit is then out of date.
#[test]
fn the_papers_triangle_is_rich_and_a_fast_triangle_is_not() {
    use hal_sim::sim::{Scenario, Simulation};
    use nanopos_id::excitation::Waveform;
    let single_fraction = |freq_hz: f64, amplitude_v: f64| {
        let (board, mut p) = Scenario::Triangle.settings(10.0, 2);
        p.excitation =
            ExcitationDesign { waveform: Waveform::Triangle { freq_hz, max_hz: 1000.0 }, amplitude_v, offset_v: 0.0 };
        let mut sim = Simulation::new(board, &p, ()).unwrap();
        let levels: Vec<_> = (0..30_000).map(|_| sim.step().1.estimator_input.expect("no fault").pe).collect();
        levels[10_000..].iter().filter(|l| l.single).count() as f64 / 20_000.0
    };
    let fractions = [(10.0, 1.0), (10.0, 0.1), (200.0, 1.0), (200.0, 0.1)].map(|(f, a)| single_fraction(f, a));
    eprintln!("triangle single-sinusoid fraction: 10 Hz 1 V / 0.1 V, 200 Hz 1 V / 0.1 V: {fractions:?}");
    assert_eq!(fractions[..2], [0.0, 0.0]);
    assert_eq!(fractions[2..], [1.0, 1.0]);
}

/// The richness test against the DAC's rounding, on the board: a sine of any frequency (1 Hz to 4.5 kHz) and
/// amplitude (3 mV to 2 V) never passes for a rich input once the monitor has settled (after 0.5 s), where "passes"
/// is what the estimators see with their default floor: `power >= 1e-6 V^2` and not `single`. Small and fast sines
/// are where the rounding weighs: a small sine's steps, or a fast one's harmonics folded into the shaping filter's
/// band, made the spread test call them rich (`estimator::PE_ROUNDING_FLOOR`). Rich inputs down to 50 mV stay rich:
/// the paper's PRBS at 1 V, 0.1 V and 50 mV is never taken for a sinusoid.
#[test]
fn no_sine_passes_for_rich_input_whatever_its_frequency_and_amplitude() {
    use hal_sim::sim::{Scenario, Simulation};
    let passed = |excitation: ExcitationDesign| {
        let (board, mut p) = Scenario::Prbs.settings(10.0, 1);
        p.excitation = excitation;
        let mut sim = Simulation::new(board, &p, ()).unwrap();
        let levels: Vec<_> = (0..15_000).map(|_| sim.step().1.estimator_input.expect("no fault").pe).collect();
        levels[5_000..].iter().filter(|l| l.power >= 1e-6 && !l.single).count()
    };
    let sines: Vec<(f64, f64)> = [1.0, 5.0, 20.0, 79.5, 173.0, 450.0, 1035.0, 1200.0, 1783.0, 3500.0, 4500.0]
        .iter()
        .flat_map(|&hz| [0.003, 0.03, 0.1, 1.0, 2.0].map(|v| (hz, v)))
        .collect();
    let passing: Vec<((f64, f64), usize)> = std::thread::scope(|s| {
        let jobs: Vec<_> = sines
            .chunks(14)
            .map(|c| {
                s.spawn(move || {
                    c.iter().map(|&(hz, v)| ((hz, v), passed(ExcitationDesign::sine(hz, v)))).collect::<Vec<_>>()
                })
            })
            .collect();
        jobs.into_iter().flat_map(|j| j.join().unwrap()).collect()
    });
    let failed: Vec<_> = passing.iter().filter(|(_, n)| *n > 0).collect();
    eprintln!("{} of {} sines pass for rich input (Hz, V; samples of 10 000): {failed:?}", failed.len(), sines.len());
    assert!(failed.is_empty(), "{failed:?}");
    for volts in [1.0, 0.1, 0.05] {
        let prbs = ExcitationDesign { amplitude_v: volts, ..ExcitationDesign::PAPER_PRBS };
        assert_eq!(passed(prbs), 10_000, "PRBS at {volts} V");
    }
}

/// The measurement behind `estimator::PE_ROUNDING_FLOOR` (ignored: about 15 s in release; `cargo test --release -p
/// hal-sim --test ekf_health -- --ignored --nocapture rounding_floor`). The monitor's statistics, recomputed here
/// from their definition (the replicas' `u'` through `PE_SPREAD_SHAPE`, averages over `PE_TAU_S`), on the board,
/// after 1 s: over the samples where the spread test alone calls the input rich and the power is above the default
/// floor, the off-sine power over `<v''^2>` and over `<v^2>` in units of the DAC's rounding as white noise. For 280
/// sines (0.2 Hz to 4.9 kHz, 3 mV to 2 V) the largest of each; for the paper's inputs at smaller amplitudes the least,
/// and the share of the time the monitor holds the estimators (with the default floor).
#[test]
#[ignore]
fn rounding_floor_margins() {
    use hal_sim::sim::{Scenario, Simulation};
    use nanopos_id::estimator::{PE_SPREAD_MIN, PE_SPREAD_SHAPE, PE_TAU_S};
    use nanopos_id::filters::PrefilterState;
    let (board, _) = Scenario::Prbs.settings(10.0, 1);
    let lsb = board.dac.format().volts_per_code() / board.amplifier.dac_v_per_command_v;
    let [gain_v, gain_a] = PE_SPREAD_SHAPE.noise_gains(1e-4);
    let white = [gain_v, gain_a].map(|g| g * lsb * lsb / 12.0);
    let floor = nanopos_id::estimator::PE_ROUNDING_FLOOR;
    // Per excitation, where the spread test alone passes it: the largest and the least ratio in the unit that
    // decides (a sine passes the rounding floor when that ratio is above its floor).
    let ratios = |excitation: ExcitationDesign| {
        let (board, mut p) = Scenario::Prbs.settings(10.0, 1);
        p.excitation = excitation;
        let mut sim = Simulation::new(board, &p, ()).unwrap();
        let shape = PE_SPREAD_SHAPE.design::<f64>(1e-4);
        let (mut state, alpha) = (PrefilterState::default(), 1e-4 / PE_TAU_S);
        let (mut vv, mut aa, mut va) = (0.0f64, 0.0f64, 0.0f64);
        let (mut most, mut least, mut held) = ([0.0f64; 2], [f64::INFINITY; 2], 0);
        for k in 0..30_000 {
            let input = sim.step().1.estimator_input.expect("no fault");
            held += usize::from(k >= 10_000 && (input.pe.single || input.pe.power < 1e-6));
            let shaped = shape.update(&mut state, input.u);
            vv += alpha * (shaped.value * shaped.value - vv);
            aa += alpha * (shaped.d2 * shaped.d2 - aa);
            va += alpha * (shaped.value * shaped.d2 - va);
            let slack = vv * aa - va * va;
            if k >= 10_000 && input.pe.power >= 1e-6 && slack >= PE_SPREAD_MIN * vv * aa {
                // The unit that decides: the one whose ratio is the smaller share of its floor.
                let r = [slack / aa / white[0], slack / vv / white[1]];
                let c = usize::from(r[1] / floor[1] < r[0] / floor[0]);
                (most[c], least[c]) = (most[c].max(r[c]), least[c].min(r[c]));
            }
        }
        (most, least, held as f64 / 20_000.0)
    };
    let sines: Vec<(f64, f64)> = (0..40)
        .flat_map(|i| {
            let hz = 0.2 * (4900.0f64 / 0.2).powf(i as f64 / 39.0) * (1.0 + 0.013 * (i % 3) as f64);
            [0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 2.0].map(|v| (hz, v))
        })
        .collect();
    let most: Vec<[f64; 2]> = std::thread::scope(|s| {
        let jobs: Vec<_> = sines
            .chunks(20)
            .map(|c| {
                s.spawn(move || c.iter().map(|&(hz, v)| ratios(ExcitationDesign::sine(hz, v)).0).collect::<Vec<_>>())
            })
            .collect();
        jobs.into_iter().flat_map(|j| j.join().unwrap()).collect()
    });
    let worst = most.iter().fold([0.0f64; 2], |w, m| [w[0].max(m[0]), w[1].max(m[1])]);
    eprintln!("{} sines: the largest ratios [v, v''], each where it decides: {worst:.3?}", sines.len());
    let rich = [
        ("paper's triangle, 0.1 V", ExcitationDesign { amplitude_v: 0.1, ..ExcitationDesign::PAPER_TRIANGLE }),
        ("paper's triangle, 50 mV", ExcitationDesign { amplitude_v: 0.05, ..ExcitationDesign::PAPER_TRIANGLE }),
        ("paper's PRBS, 50 mV", ExcitationDesign { amplitude_v: 0.05, ..ExcitationDesign::PAPER_PRBS }),
        ("paper's PRBS, 20 mV", ExcitationDesign { amplitude_v: 0.02, ..ExcitationDesign::PAPER_PRBS }),
    ];
    for (name, e) in rich {
        let (_, least, held) = ratios(e);
        eprintln!("{name}: the least ratios [v, v''], each where it decides: {least:.3?}; held {held:.3} of the time");
    }
    eprintln!("PE_ROUNDING_FLOOR: {floor:?}");
    assert!(worst[0] < floor[0] && worst[1] < floor[1], "{worst:?}");
}

/// A diagnosis, kept measured (ignored: a few seconds; `cargo test --release -p hal-sim --test ekf_health --
/// --ignored --nocapture in_its_band`): why the monitor does not also judge richness in the pre-filter's band, from
/// `u_f`'s value `v` and second derivative `a` (which the pipeline computes anyway), with the same spread test and a
/// rounding floor in units of the DAC's rounding as white noise through `W_p`. It would pass narrow multisines about
/// the resonance (350-550 Hz), which the shaping filter starves; but
/// - a 2 V sine at 3 408 Hz, slew-limited (its harmonics fold onto 450 Hz), leaves more off-sine power over `<a^2>`
///   than a 0.2 V multisine from 350 to 550 Hz: no floor passes the one and holds the other, and with the monitor
///   off that sine moved the RLS by 20 % and the ARX by 57 % in 10 s;
/// - a 1 V multisine from 600 to 1000 Hz, which does not identify the stage (with the monitor off the EKFs 5 % off
///   in b0 and 7 % in a1, `tests/instrument.rs`), has more spread and off-sine power there than the 0.2 V one from
///   350 to 550 Hz, which does.
///
/// Richness alone cannot tell a band that identifies the stage from one that does not (nor can the shaping filter's:
/// it passes a band below the resonance that does not identify it either, 50-150 Hz, `tests/instrument.rs`).
#[test]
#[ignore]
fn richness_in_its_band_cannot_tell_a_useful_band() {
    use hal_sim::sim::{Scenario, Simulation};
    use nanopos_id::estimator::PE_TAU_S;
    use nanopos_id::filters::PrefilterDesign;
    // After 1 s, where the spread is above 1e-3 and the power above the default floor: the least and the largest
    // off-sine power over `<a^2>`, in rounding units, and the mean spread.
    let band = |excitation: ExcitationDesign| {
        let (board, mut p) = Scenario::Prbs.settings(10.0, 1);
        let lsb = board.dac.format().volts_per_code() / board.amplifier.dac_v_per_command_v;
        let white_a = PrefilterDesign::default().noise_gains(1e-4)[1] * lsb * lsb / 12.0;
        p.excitation = excitation;
        let mut sim = Simulation::new(board, &p, ()).unwrap();
        let alpha = 1e-4 / PE_TAU_S;
        let (mut vv, mut aa, mut va) = (0.0f64, 0.0f64, 0.0f64);
        let (mut least, mut most, mut spread) = (f64::INFINITY, 0.0f64, 0.0);
        for k in 0..30_000 {
            let u_f = sim.step().1.estimator_input.expect("no fault").u_f;
            vv += alpha * (u_f.value * u_f.value - vv);
            aa += alpha * (u_f.d2 * u_f.d2 - aa);
            va += alpha * (u_f.value * u_f.d2 - va);
            let slack = vv * aa - va * va;
            if k >= 10_000 {
                spread += slack / (vv * aa) / 20_000.0;
                if vv >= 1e-6 && slack >= 1e-3 * vv * aa {
                    let r = slack / vv / white_a;
                    (least, most) = (least.min(r), most.max(r));
                }
            }
        }
        (least, most, spread)
    };
    let slewed = band(ExcitationDesign::sine(3408.3333, 2.0));
    let useful = band(ExcitationDesign::multisine(350.0, 550.0, 0.2));
    let strong = band(ExcitationDesign::multisine(350.0, 550.0, 1.0));
    let useless = band(ExcitationDesign::multisine(600.0, 1000.0, 1.0));
    for (name, b) in [
        ("sine 3 408 Hz 2 V", slewed),
        ("350-550 Hz 0.2 V", useful),
        ("350-550 Hz 1 V", strong),
        ("600-1000 Hz 1 V", useless),
    ] {
        eprintln!("{name}: off-sine power over <a^2> {:.0} to {:.0} rounding units, mean spread {:.4}", b.0, b.1, b.2);
    }
    assert!(slewed.1 > useful.0, "a floor would tell them apart: {slewed:?} {useful:?}");
    assert!(useless.2 > useful.2 && useless.0 > useful.0, "{useless:?} {useful:?}");
}
