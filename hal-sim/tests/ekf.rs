//! The hybrid EKF against the float64 reference, on the reference's own data (ideal ZOH plant, no analog filters).

use hal_sim::experiment::ReferenceData;
use nanopos_id::estimator::Estimator;
use nanopos_id::estimators::ekf::{Cekf, EkfDesign as HekfDesign, Hekf};
use nanopos_id::excitation::ExcitationDesign;
use nanopos_id::{Real, StageParams};

/// Run an estimator on the reference's data (`segment_s` per payload state) and return estimates every 10 ms.
fn on_reference_data<T: Real, E: Estimator<T>>(
    mut est: E,
    excitation: ExcitationDesign,
    seed: u64,
    segment_s: f64,
) -> Vec<(f64, StageParams<f64>)> {
    let h = ReferenceData::generate(excitation, seed, segment_s).run(&mut est);
    h.iter().map(|s| (s.t_s, s.est)).collect()
}

fn window_rel_errors(h: &[(f64, StageParams<f64>)], t0: f64, t1: f64, truth: &StageParams<f64>) -> [f64; 3] {
    let w: Vec<_> = h.iter().filter(|(t, _)| *t > t0 && *t <= t1).map(|(_, p)| *p).collect();
    let n = w.len() as f64;
    let m = |f: fn(&StageParams<f64>) -> f64| w.iter().map(f).sum::<f64>() / n;
    [m(|p| p.a0) / truth.a0 - 1.0, m(|p| p.a1) / truth.a1 - 1.0, m(|p| p.b0) / truth.b0 - 1.0]
}

#[test]
fn hekf_matches_the_reference_on_its_prbs_data() {
    let h =
        on_reference_data::<f64, _>(Hekf::new(HekfDesign::default().design()), ExcitationDesign::PAPER_PRBS, 1, 20.0);
    // Reference (variant y_zoh+uf_hold, seg 20 s, windows = last 25 % of each segment):
    // payload a0 +9.2e-10, a1 -4.17e-5, b0 -4.78e-5; no payload a0 +7.5e-7, a1 -8.3e-6, b0 -2.1e-5.
    let reference = [
        [9.205347595298008e-10, -4.1692448505936675e-05, -4.7797053421727576e-05],
        [7.458991131414905e-07, -8.33855124349192e-06, -2.0850230554314564e-05],
    ];
    for (w, (t0, t1, truth)) in
        [(15.0, 20.0, StageParams::PAYLOAD), (35.0, 40.0, StageParams::NO_PAYLOAD)].into_iter().enumerate()
    {
        let e = window_rel_errors(&h, t0, t1, &truth);
        eprintln!(
            "hekf f64 {t0}-{t1}: a0 {:+.2e} a1 {:+.2e} b0 {:+.2e} (reference {:+.2e} {:+.2e} {:+.2e})",
            e[0], e[1], e[2], reference[w][0], reference[w][1], reference[w][2]
        );
        // Same algorithm and convention: the errors agree to the difference between a mean of the estimate every
        // 10 ms (here) and every sample (reference), ~1e-6 for estimates that wander by ~1e-5.
        for i in 0..3 {
            assert!(
                (e[i] - reference[w][i]).abs() < 2e-6,
                "window {t0}-{t1}, parameter {i}: {} vs {}",
                e[i],
                reference[w][i]
            );
            // And the paper-experiment goals with room: a0, b0 within 0.1 %, a1 within 1 % (here 1e-4 and below).
            assert!(e[i].abs() < 1e-4);
        }
    }
}

#[test]
fn hekf_f32_stays_with_f64_on_the_reference_prbs_data() {
    let design = HekfDesign::default();
    let h64 = on_reference_data::<f64, _>(Hekf::new(design.design()), ExcitationDesign::PAPER_PRBS, 1, 20.0);
    let h32 = on_reference_data::<f32, _>(Hekf::<f32>::new(design.design()), ExcitationDesign::PAPER_PRBS, 1, 20.0);
    for (t0, t1, truth) in [(15.0, 20.0, StageParams::PAYLOAD), (35.0, 40.0, StageParams::NO_PAYLOAD)] {
        let (e64, e32) = (window_rel_errors(&h64, t0, t1, &truth), window_rel_errors(&h32, t0, t1, &truth));
        eprintln!(
            "hekf f32 - f64 {t0}-{t1}: a0 {:.1e} a1 {:.1e} b0 {:.1e}",
            e32[0] - e64[0],
            e32[1] - e64[1],
            e32[2] - e64[2]
        );
        // SPEC 10: converged means of f32 within 1e-4 relative of f64 (reference float32 run: 2e-5).
        for i in 0..3 {
            assert!((e32[i] - e64[i]).abs() < 1e-4, "{t0}-{t1} parameter {i}");
        }
    }
}

/// More substeps than 4 (`tune ekf substeps`), taken by squaring their map (7: an odd count, one substep taken before
/// the squarings; 64: the most the tuning accepts): the same filter on the reference's PRBS data as with 4, within
/// the substeps' RK4 error (each window's means within 1e-5 of 4's), and f32 with f64 within SPEC 10's 1e-4. Before
/// the map was held as its deviation from the identity, 64 substeps in f32 took `a1` 1.1e-4 from f64 (the loop of
/// substeps) and 1.6e-4 (the squaring).
#[test]
fn hekf_with_many_substeps_is_the_same_filter_in_f64_and_f32() {
    let design = |substeps| HekfDesign { substeps, ..HekfDesign::default() };
    let run64 = |substeps| {
        on_reference_data::<f64, _>(Hekf::new(design(substeps).design()), ExcitationDesign::PAPER_PRBS, 1, 20.0)
    };
    let four = run64(4);
    for substeps in [7, 64] {
        let h64 = run64(substeps);
        let h32 =
            on_reference_data::<f32, _>(Hekf::new(design(substeps).design()), ExcitationDesign::PAPER_PRBS, 1, 20.0);
        for (t0, t1, truth) in [(15.0, 20.0, StageParams::PAYLOAD), (35.0, 40.0, StageParams::NO_PAYLOAD)] {
            let e4 = window_rel_errors(&four, t0, t1, &truth);
            let (e64, e32) = (window_rel_errors(&h64, t0, t1, &truth), window_rel_errors(&h32, t0, t1, &truth));
            eprintln!(
                "hekf {substeps} substeps {t0}-{t1}: f64 a0 {:+.2e} a1 {:+.2e} b0 {:+.2e} (4 substeps {:+.2e} {:+.2e} \
                 {:+.2e}), f32 - f64 {:.1e} {:.1e} {:.1e}",
                e64[0],
                e64[1],
                e64[2],
                e4[0],
                e4[1],
                e4[2],
                e32[0] - e64[0],
                e32[1] - e64[1],
                e32[2] - e64[2]
            );
            for i in 0..3 {
                assert!((e64[i] - e4[i]).abs() < 1e-5, "{substeps} substeps, {t0}-{t1}, parameter {i}: against 4");
                assert!((e32[i] - e64[i]).abs() < 1e-4, "{substeps} substeps, {t0}-{t1}, parameter {i}: f32");
            }
        }
    }
}

/// SPEC 10 on the full board: a0 and b0 within 0.1 %, a1 within 1 %, relock in about a second. Met, except b0
/// without payload (+0.28 to +0.30 %): the second mode (1.9 kHz) that the 2nd-order model cannot represent (+0.06 %
/// with it switched off, see hekf_bias_by_board_effect). That window's b0 is guarded at 0.35 % and the limit written
/// down; a pre-filter placed for this board's second mode meets it, at a cost to the other estimators
/// (a_prefilter_placed_for_the_boards_second_mode_meets_the_b0_goal_in_both_windows).
fn assert_ekf_goals(name: &str, r: &hal_sim::experiment::Report) {
    for (w, e) in r.windows.iter().enumerate() {
        let b0_bound = if w == 0 { 1e-3 } else { 3.5e-3 };
        assert!(e[0].abs() < 1e-3 && e[1].abs() < 1e-2 && e[2].abs() < b0_bound, "{name} window {w}: {e:?}");
    }
    assert!(r.relock_s.is_some_and(|t| t < 1.0), "{name}: {:?}", r.relock_s);
}

#[test]
fn hekf_on_the_full_simulated_board() {
    let design = HekfDesign::default();
    let h = hal_sim::experiment::paper_prbs(|| Hekf::<f64>::new(design.design()), || Hekf::<f32>::new(design.design()));
    for (name, hist) in h.both() {
        assert_ekf_goals(name, &hal_sim::experiment::report(&format!("hekf board {name}"), hist));
    }
}

/// What meets the b0 goal on the full board: the second mode's bias on `b0` depends on where the pre-filter sits
/// against the resonance and on its width. Moving `f_p` alone, the bias crosses zero near 1.06 times the resonance:
/// the paper's 450 Hz is there for the payload's 423 Hz (b0 -0.035 %) but not for the 483 Hz without it (+0.28 %);
/// at 512 Hz the window without payload is within 0.1 % (b0 -0.008 % in f64) and the one with it is not (-0.26 %).
/// Widening the pre-filter as well moves the two windows' biases differently: at `f_p` 525 Hz and `zeta_p` 0.22 both
/// EKFs meet every PRBS goal in both windows (b0 -0.07 / +0.07 % hybrid, -0.06 / +0.08 % continuous; seeds 1 to 4
/// within 0.005 % of each other). That pair was found by a grid search over `f_p` 420-530 Hz and `zeta_p` 0.02-0.28
/// against the simulated truth, which a user of a real stage does not have, for this board's illustrative 1.9 kHz
/// mode; and the replicas, matched at `f_p`, move with it. It costs the other two estimators: on the same record
/// (`identify --tuning` with `prefilter = [100, 525, 0.22]`) the RLS's and the ARX's `b0` with the payload go from
/// -0.05 / -0.08 % to -0.58 / -0.68 % and their validation RMSE from 5.5 / 6.0 nm to 8.8 / 9.3 nm; and the smoothed
/// triangle, whose errors come from the second mode's static compliance, gets worse in every estimator (the EKFs'
/// `b0` +3.2 % instead of +2.7 % with the payload, the RLS's +33 % instead of +7.7 %). So the defaults stay the
/// paper's (SPEC section 4).
#[test]
fn a_prefilter_placed_for_the_boards_second_mode_meets_the_b0_goal_in_both_windows() {
    use hal_sim::experiment::{rel_errors, run, window_mean};
    use nanopos_id::filters::PrefilterDesign;
    let design = HekfDesign::default();
    let errors = |hist: &[hal_sim::experiment::Sample]| {
        [(75.0, 100.0), (175.0, 200.0)].map(|(t0, t1)| {
            let (mean, truth) = window_mean(hist, t0, t1);
            rel_errors(&mean, &truth)
        })
    };
    let at = |f_p_hz: f64, zeta_p: f64| {
        let moved = PrefilterDesign { f_p_hz, zeta_p, ..PrefilterDesign::default() };
        move |_: &mut hal_sim::board::BoardSettings, p: &mut nanopos_id::pipeline::PipelineSettings| {
            *p = p.with_prefilter(moved)
        }
    };
    let hekf_at = |f_p_hz: f64, zeta_p: f64| {
        let (d64, d32) = (design.design(), design.design());
        run(
            hal_sim::sim::Scenario::Prbs,
            200.0,
            1,
            || Hekf::<f64>::new(d64),
            || Hekf::<f32>::new(d32),
            at(f_p_hz, zeta_p),
        )
    };
    // f_p alone: one window or the other.
    let h = hekf_at(512.0, 0.1);
    for (name, hist) in h.both() {
        let [with, without] = errors(hist);
        eprintln!("hekf {name}, f_p 512 Hz: a0, a1, b0 with payload {with:+.4?}, without {without:+.4?}");
        assert!(without[0].abs() < 1e-3 && without[1].abs() < 1e-2 && without[2].abs() < 1e-3, "{without:?}");
        assert!(with[2] < -2e-3, "with the payload the moved pre-filter is off its resonance: {with:?}");
    }
    // f_p and zeta_p: both windows, both filters, both precisions.
    let hekf = hekf_at(525.0, 0.22);
    let cekf = run(
        hal_sim::sim::Scenario::Prbs,
        200.0,
        1,
        || Cekf::<f64>::new(design.design()),
        || Cekf::<f32>::new(design.design()),
        at(525.0, 0.22),
    );
    for (filter, h) in [("hekf", &hekf), ("cekf", &cekf)] {
        for (name, hist) in h.both() {
            let [with, without] = errors(hist);
            let r = hal_sim::experiment::report(&format!("{filter} {name} at 525 Hz, 0.22"), hist);
            for e in [with, without] {
                assert!(e[0].abs() < 1e-3 && e[1].abs() < 1e-2 && e[2].abs() < 1e-3, "{filter} {name}: {e:?}");
            }
            assert!(r.relock_s.is_some_and(|t| t < 1.0), "{filter} {name}: {:?}", r.relock_s);
        }
    }
}

#[test]
#[ignore = "diagnosis: which board effect biases the estimate (run with --ignored --nocapture)"]
fn hekf_bias_by_board_effect() {
    let design = HekfDesign::default();
    type Adjust = fn(&mut hal_sim::board::BoardSettings, &mut nanopos_id::pipeline::PipelineSettings);
    let cases: [(&str, Adjust); 6] = [
        ("all effects", |_, _| {}),
        ("no amplifier pole", |b, _| b.plant.amplifier_hz = None),
        ("no sensor pole", |b, _| b.plant.sensor_hz = None),
        ("no second mode", |b, _| b.plant.second_mode = None),
        ("no bump", |b, _| b.plant.bump_um_per_s = 0.0),
        ("replicas at 1 kHz pre-warp", |_, p| {
            p.reconstruction.prewarp_hz = 1000.0;
            p.antialias.prewarp_hz = 1000.0
        }),
    ];
    for (name, adjust) in cases {
        let errors =
            paper_window_errors(|| Hekf::<f64>::new(design.design()), || Hekf::<f32>::new(design.design()), adjust);
        eprintln!("{name:28}: {}", percent_line(errors));
    }
}

#[test]
fn cekf_on_the_reference_data_and_on_the_full_board() {
    let design = HekfDesign::default();
    let h = on_reference_data::<f64, _>(Cekf::new(design.design()), ExcitationDesign::PAPER_PRBS, 1, 20.0);
    for (t0, t1, truth) in [(15.0, 20.0, StageParams::PAYLOAD), (35.0, 40.0, StageParams::NO_PAYLOAD)] {
        let e = window_rel_errors(&h, t0, t1, &truth);
        eprintln!("cekf reference data {t0}-{t1}: a0 {:+.2e} a1 {:+.2e} b0 {:+.2e}", e[0], e[1], e[2]);
        // With the curvature term the line's (w T)^2 / 12 gain loss (b0 -0.6 % without it) is gone: what is left is
        // O((w T)^3) and the estimate's wander, measured below 2e-4.
        assert!(e.iter().all(|x| x.abs() < 5e-4), "{e:?}");
    }
    let b = hal_sim::experiment::paper_prbs(|| Cekf::<f64>::new(design.design()), || Cekf::<f32>::new(design.design()));
    for (name, hist) in b.both() {
        assert_ekf_goals(name, &hal_sim::experiment::report(&format!("cekf board {name}"), hist));
    }
}

#[test]
fn crls_on_the_reference_data() {
    use nanopos_id::estimators::crls::{Crls, CrlsDesign};
    let design = CrlsDesign::default();
    let h = on_reference_data::<f64, _>(Crls::new(design.design()), ExcitationDesign::PAPER_PRBS, 1, 100.0);
    for (t0, t1, truth) in [(75.0, 100.0, StageParams::PAYLOAD), (175.0, 200.0, StageParams::NO_PAYLOAD)] {
        let e = window_rel_errors(&h, t0, t1, &truth);
        eprintln!("crls reference data {t0}-{t1}: a0 {:+.2e} a1 {:+.2e} b0 {:+.2e}", e[0], e[1], e[2]);
        // SPEC 10: the continuous RLS within 1 %; measured a1 -0.04 % / -0.08 %, b0 +0.03 %, a0 below 1e-5 (the
        // float64 reference's linear interpolation had b0 -0.6 %).
        assert!(e.iter().all(|x| x.abs() < 5e-3), "{e:?}");
    }
}

#[test]
fn crls_on_the_full_board_in_f64_and_f32() {
    use hal_sim::experiment::{paper_prbs, rel_errors, report, window_mean};
    use nanopos_id::estimators::crls::{Crls, CrlsDesign};
    let design = CrlsDesign::default();
    let b = paper_prbs(|| Crls::<f64>::new(design.design()), || Crls::<f32>::new(design.design()));
    assert_eq!(b.code_mismatches, 0, "the paper's PRBS: f32 and f64 command the same codes");
    for (name, hist) in b.both() {
        // SPEC 10: the continuous RLS within 1 %.
        let r = report(&format!("crls board {name}"), hist);
        assert!(r.windows.iter().flatten().all(|x| x.abs() < 1e-2), "{name}: {r:?}");
    }
    let (m64, _) = window_mean(&b.f64, 175.0, 200.0);
    let (m32, _) = window_mean(&b.f32, 175.0, 200.0);
    let d = rel_errors(&m32, &m64);
    eprintln!("crls f32 - f64 175-200: {d:?}");
    assert!(d.iter().all(|x| x.abs() < 1e-4), "{d:?}");
}

/// A relock time (`None`: never) and the number of changes detected.
type Relock = (Option<f64>, u32);

/// Relock after the payload change at 100 s on the reference's triangle data with noise seed `seed`: `a0` and
/// `b0` within 1 % of the truth for good; and the number of changes detected.
fn triangle_relock<K: nanopos_id::estimators::ekf::EkfKind>(design: &HekfDesign, seed: u64) -> Relock
where
    nanopos_id::estimators::ekf::Ekf<f64, K>: Estimator<f64>,
{
    let mut est = nanopos_id::estimators::ekf::Ekf::<f64, K>::new(design.design());
    let samples = ReferenceData::generate(ExcitationDesign::PAPER_TRIANGLE, seed, 100.0).run(&mut est);
    let health = est.health();
    (hal_sim::experiment::relock_time(&samples, 100.0, 0.01), health.changes_detected)
}

/// The median of relock times, `never` counting as infinite.
fn median_relock(times: &[Relock]) -> f64 {
    let mut t: Vec<f64> = times.iter().map(|(t, _)| t.unwrap_or(f64::INFINITY)).collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

/// The smoothed triangle's payload change is too gentle for the gate (25x in `nu^2 / S`, within the per-sample
/// spread): without drift detection nothing is detected and the filters relock slowly or not at all; with it, the
/// change is seen about 0.24 s after it happens and the parameter variances grow to 500 `P0` over the next 10 ms.
/// Held on the noise seeds 2 (the reference's) to 50: every seed within the goal (10 s) and the median within 1 s,
/// one detection per run; without detection (seeds 2-12) the median over 30 s and nothing detected. Measured,
/// hybrid / continuous: median 0.32 / 0.31 s, the slowest 0.7 / 0.7 s; without detection median 69.4 s (seed 2:
/// 74.2 s, the reference's own 74.4 s). Reopened at once instead of over 10 ms, the relock depends on the noise: in
/// the first milliseconds the parameters' prior spread is several times their values and the linearisation
/// guesses; where it guesses wrong `a1` swings to several times its value and `b0` takes tens of seconds to
/// follow it back (medians 0.8 / 1.2 s, 6 / 5 of the 49 seeds over 10 s, the slowest 27 / 25 s; at 100 `P0`
/// 7.7 / 4.9 s and 20 / 19 over 10 s). Any growth from 1 ms to 50 ms, to 100 to 2 000 `P0`, gave none over 2 s.
#[test]
fn drift_detection_relocks_the_triangle() {
    use nanopos_id::estimators::ekf::{Continuous, Hybrid};
    let with = HekfDesign::paper(HekfDesign::Q1);
    let without =
        HekfDesign { health: nanopos_id::estimators::ekf::EkfHealthDesign { drift_ratio: 0.0, ..with.health }, ..with };
    // Per seed `[hybrid, continuous]` with detection, and without on seeds 2-12; the seeds dealt out to one thread
    // per core (each run holds 200 s of data).
    let seeds: Vec<u64> = (2..=50).collect();
    let threads = std::thread::available_parallelism().map_or(2, |n| n.get());
    let mut runs: Vec<(u64, [Option<Relock>; 4])> = std::thread::scope(|s| {
        let jobs: Vec<_> = (0..threads)
            .map(|i| {
                let mine: Vec<u64> = seeds.iter().copied().skip(i).step_by(threads).collect();
                s.spawn(move || {
                    mine.into_iter()
                        .map(|seed| {
                            let off = seed <= 12;
                            (
                                seed,
                                [
                                    Some(triangle_relock::<Hybrid>(&with, seed)),
                                    Some(triangle_relock::<Continuous>(&with, seed)),
                                    off.then(|| triangle_relock::<Hybrid>(&without, seed)),
                                    off.then(|| triangle_relock::<Continuous>(&without, seed)),
                                ],
                            )
                        })
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        jobs.into_iter().flat_map(|j| j.join().unwrap()).collect()
    });
    runs.sort_by_key(|r| r.0);
    let runs: Vec<_> = runs.into_iter().map(|r| r.1).collect();
    let column = |i: usize| runs.iter().filter_map(|r| r[i]).collect::<Vec<_>>();
    let [hybrid, continuous, hybrid_off, continuous_off] = [0, 1, 2, 3].map(column);
    for (name, r) in [
        ("hybrid, seeds 2-50", &hybrid),
        ("continuous, seeds 2-50", &continuous),
        ("hybrid, no detection, seeds 2-12", &hybrid_off),
        ("continuous, no detection, seeds 2-12", &continuous_off),
    ] {
        let times: Vec<String> = r.iter().map(|(t, _)| t.map_or("never".into(), |t| format!("{t:.1}"))).collect();
        eprintln!("triangle relock, {name}: median {:.2} s [{}]", median_relock(r), times.join(" "));
    }
    // One change detected in every run with detection, none without.
    assert!(hybrid.iter().chain(&continuous).all(|r| r.1 == 1), "{hybrid:?} {continuous:?}");
    assert!(hybrid_off.iter().chain(&continuous_off).all(|r| r.1 == 0), "{hybrid_off:?} {continuous_off:?}");
    // The goal on every seed, and the several-fold cut (SPEC 10).
    let within = |r: &[Relock], limit: f64| r.iter().all(|(t, _)| t.is_some_and(|t| t <= limit));
    assert!(within(&hybrid, 10.0) && within(&continuous, 10.0), "{hybrid:?} {continuous:?}");
    assert!(median_relock(&hybrid) <= 1.0 && median_relock(&continuous) <= 1.0, "{hybrid:?} {continuous:?}");
    assert!(median_relock(&hybrid_off) > 30.0 && median_relock(&continuous_off) > 30.0);
}

/// The dense peer (nalgebra, full `F P + P F'`, full Joseph form) computes the same filter as the structured one:
/// on 20 s of PRBS on the full board (no payload change, so the structured filter's health logic stays idle) the
/// two f64 estimates agree to 1e-6. They are not the same arithmetic: the dense filter integrates the Riccati
/// equation by RK4 (the SPEC's rule), the structured one propagates the covariance through the Jacobian of the
/// state's RK4 map with a leading-order `Qd` (`EkfCore::predict`; per step they agree to 1.8e-2 of the process
/// noise's part and 2e-4 of the rest, tested in `estimators::ekf`). Measured: a0 4.2e-8, a1 1.7e-7, b0 3.7e-7. A wrong
/// term in `F` or the Joseph form moves the estimate by 1e-3 or more.
#[test]
fn the_dense_hekf_computes_the_same_filter_as_the_structured_one() {
    use hal_sim::sim::{Scenario, Simulation};
    use nanopos_id::estimators::ekf::dense::DenseHekf;
    let (mut board, settings) = Scenario::Prbs.settings(20.0, 1);
    board.plant.change_at_sample = u64::MAX;
    let design = HekfDesign::default();
    let mut sim = Simulation::new(board, &settings, (Hekf::<f64>::new(design.design()),)).unwrap();
    let mut dense = DenseHekf::<f64>::new(design.design());
    for _ in 0..200_000 {
        let (_, out) = sim.step();
        let s = out.estimator_input.expect("no faults");
        dense.update(s.u_f.value, s.y_f.value);
    }
    let (a, b) = (sim.pipeline.estimators.0.params(), dense.params());
    let health = sim.pipeline.estimators.0.health();
    assert_eq!((health.rejected_samples, health.changes_detected, health.numeric_resets), (0, 0, 0));
    for (name, x, y) in [("a0", a.a0, b.a0), ("a1", a.a1, b.a1), ("b0", a.b0, b.b0)] {
        let rel = (x / y - 1.0).abs();
        println!("{name}: structured {x:.9e}, dense {y:.9e}, relative {rel:.1e}");
        assert!(rel < 1e-6, "{name}: structured {x} against dense {y}");
    }
}

/// The f32 and f64 pipelines compute a multisine's tones each in its own precision, so now and then a sample's
/// command falls on either side of a DAC code's rounding boundary (`experiment`'s module doc): counted, rare, and
/// the f32 filter stays with the f64 one. 40 s of 1 V from 420 to 480 Hz after 30 s of PRBS, the monitor off.
#[test]
fn f32_and_f64_pipelines_one_code_apart_on_a_multisine() {
    use hal_sim::experiment::run_scheduled;
    use hal_sim::sim::Scenario;
    use nanopos_id::excitation::ExcitationDesign;
    let mut design = HekfDesign::default();
    design.health.pe_floor_v2 = 0.0;
    let mut switch = |k: u64| {
        (k == 300_000).then(|| {
            let (_, mut p) = Scenario::Prbs.settings(40.0, 1);
            p.excitation = ExcitationDesign::multisine(420.0, 480.0, 1.0);
            p
        })
    };
    let h = run_scheduled(
        Scenario::Prbs,
        40.0,
        1,
        || Hekf::<f64>::new(design.design()),
        || Hekf::<f32>::new(design.design()),
        |b, _| b.plant.change_at_sample = u64::MAX,
        &mut switch,
    );
    let last = |h: &[hal_sim::experiment::Sample]| h.last().expect("sampled").est;
    let d = hal_sim::experiment::rel_errors(&last(&h.f32), &last(&h.f64));
    eprintln!("multisine 420-480 Hz: {} of 100 000 samples one code apart; f32 - f64 at 40 s {d:?}", h.code_mismatches);
    assert!(h.code_mismatches > 0 && h.code_mismatches < 100, "{}", h.code_mismatches);
    assert!(d.iter().all(|x| x.abs() < 1e-4), "{d:?}");
}

/// Creep is below the pre-filter's band: the full board's PRBS about a 3 V offset (so that the creep has a step to
/// follow: 12 nm at 30 s), with the default creep (1 % per decade) and without it, the same noise: the hybrid
/// filter's and the continuous RLS's means over 20-30 s differ by less than 1e-4 relative. Measured, hekf / rls:
/// a0 1.5e-6 / 3e-8, a1 1.4e-5 / 6.5e-5, b0 3.4e-6 / 7.0e-6, where the board's other effects leave b0 0.3 % off.
#[test]
fn creep_does_not_reach_the_estimators() {
    use hal_sim::sim::{Scenario, Simulation};
    use nanopos_id::estimators::crls::{Crls, CrlsDesign};
    let run = |creep: bool| {
        let (mut board, mut p) = Scenario::Prbs.settings(200.0, 1);
        board.plant.creep = creep.then(hal_sim::plant::Creep::default);
        p.excitation.offset_v = 3.0;
        let bank = (Hekf::<f64>::new(HekfDesign::default().design()), Crls::<f64>::new(CrlsDesign::default().design()));
        let mut sim = Simulation::new(board, &p, bank).unwrap();
        let (mut sums, mut y_end) = ([[0.0f64; 3]; 2], 0.0);
        for k in 0..300_000 {
            let (r, _) = sim.step();
            y_end = r.y_um;
            if k >= 200_000 && k % 100 == 0 {
                let e = [sim.pipeline.estimators.0.params(), sim.pipeline.estimators.1.params()];
                for (s, p) in sums.iter_mut().zip(e) {
                    *s = [s[0] + p.a0, s[1] + p.a1, s[2] + p.b0];
                }
            }
        }
        (sums, y_end)
    };
    let ((with, y_with), (without, y_without)) = (run(true), run(false));
    let d: Vec<f64> = with.iter().flatten().zip(without.iter().flatten()).map(|(a, b)| (a / b - 1.0).abs()).collect();
    let moved = (y_with - y_without) * 1e3;
    let shown: Vec<String> = d.iter().map(|x| format!("{x:.1e}")).collect();
    eprintln!("creep: the reading at 30 s moved by {moved:.1} nm; hekf then rls, a0 a1 b0, relative: {shown:?}");
    assert!(moved > 10.0, "{moved} nm: the creep did not act");
    assert!(d.iter().all(|x| *x < 1e-4), "{d:?}");
}

/// Piezo hysteresis (the default: 10 % of the drive through play operators of half-widths 1/16 to 8/16 of 0.5 V)
/// makes the stage's gain depend on the amplitude: a play of half-width `r` passes `1 - r / A` of a square wave of
/// amplitude `A`, so for the 1 V PRBS the drive's gain is `1 - 0.1 * 0.28125 = 0.971875`. The hybrid filter finds
/// exactly that: b0 in that ratio to its estimate without hysteresis (measured 0.97190), a0 and a1 unchanged (the
/// plays delay nothing at a PRBS's levels). The linear model of the stage at the amplitude it is driven with.
#[test]
fn hysteresis_shows_as_the_gain_at_the_drives_amplitude() {
    let means = |hysteresis: bool| {
        hekf_on_the_board(200.0, (75.0, 100.0), |b| {
            b.plant.hysteresis = hysteresis.then(hal_sim::plant::Hysteresis::default)
        })
        .0
    };
    let (with, without) = (means(true), means(false));
    let ratio = [with.a0 / without.a0, with.a1 / without.a1, with.b0 / without.b0];
    eprintln!("hysteresis: a0, a1, b0 over their values without it, 75-100 s: {ratio:?}");
    assert!((ratio[0] - 1.0).abs() < 1e-5 && (ratio[1] - 1.0).abs() < 1e-4, "{ratio:?}");
    assert!((ratio[2] - 0.971875).abs() < 2e-4, "{ratio:?}");
}

/// The sample period is the time base of every estimate. A board whose clock runs slow by a fraction `e` takes
/// samples `T (1 + e)` apart while the pipeline takes them for `T`: it sees the stage on a stretched time axis, `f0`
/// and `a1` high by `e`, `a0` and `b0` by `2 e` (`(1 + e)^2 - 1`), whatever the estimator; and the 1 kHz filters'
/// replicas, matched at the assumed rate, then take their phase at the resonance at the wrong frequency, which adds
/// to `a1` and `b0`. Measured on the full board's PRBS, the hybrid EKF's means over 10-15 s (payload on) against the
/// board without the error, for `e` = +-0.5 % (the HSI16 RC oscillator's order of error, why the firmware clocks
/// from the crystal, 50 ppm): `a0` moved by 1.03 times `2 e`, `a1` by 1.41-1.42 times `e`, `b0` by 1.14 times `2 e`.
#[test]
fn a_sample_clock_off_by_e_sets_a0_and_b0_off_by_2e() {
    let errors = |e: f64| {
        let (mean, truth) = hekf_on_the_board(30.0, (10.0, 15.0), |b| b.plant.sample_period_s *= 1.0 + e);
        hal_sim::experiment::rel_errors(&mean, &truth)
    };
    let base = errors(0.0);
    for e in [0.005, -0.005] {
        let got = errors(e);
        let moved: Vec<f64> = (0..3).map(|i| (1.0 + got[i]) / (1.0 + base[i]) - 1.0).collect();
        let want = [(1.0 + e) * (1.0 + e) - 1.0, e, (1.0 + e) * (1.0 + e) - 1.0];
        println!("clock off by {e:+}: a0, a1, b0 moved by {moved:+.5?}, expected {want:+.5?} (without: {base:+.5?})");
        // a0 (the resonance) as the stretched axis says; a1 and b0 by more, the same way: the replicas' phase at the
        // resonance taken at the wrong frequency.
        let ratio: Vec<f64> = (0..3).map(|i| moved[i] / want[i]).collect();
        println!("  moved / expected {ratio:.3?}");
        assert!((ratio[0] - 1.0).abs() < 0.05, "{e}: a0 {ratio:?}");
        assert!((1.0..1.6).contains(&ratio[1]) && (1.0..1.25).contains(&ratio[2]), "{e}: a1, b0 {ratio:?}");
    }
}

/// The hybrid EKF (the paper's PRBS tuning) on the full board's PRBS for `duration_s`, the board changed by `adjust`:
/// the f64 estimate's mean over `window` and the truth's.
fn hekf_on_the_board(
    duration_s: f64,
    (t0, t1): (f64, f64),
    adjust: impl FnOnce(&mut hal_sim::board::BoardSettings),
) -> (StageParams<f64>, StageParams<f64>) {
    let design = HekfDesign::default();
    let h = hal_sim::experiment::run(
        hal_sim::sim::Scenario::Prbs,
        duration_s,
        1,
        || Hekf::<f64>::new(design.design()),
        || Hekf::<f32>::new(design.design()),
        |b, _| adjust(b),
    );
    hal_sim::experiment::window_mean(&h.f64, t0, t1)
}

/// The f64 run's window means' errors against the truth (75-100 s, 175-200 s) on the paper's PRBS experiment, the
/// board and pipeline as `adjust` leaves them.
fn paper_window_errors<E64: Estimator<f64>, E32: Estimator<f32>>(
    make64: impl FnOnce() -> E64,
    make32: impl FnOnce() -> E32,
    adjust: impl FnOnce(&mut hal_sim::board::BoardSettings, &mut nanopos_id::pipeline::PipelineSettings),
) -> [[f64; 3]; 2] {
    use hal_sim::experiment::{rel_errors, run, window_mean};
    let h = run(hal_sim::sim::Scenario::Prbs, 200.0, 1, make64, make32, adjust);
    [(75.0, 100.0), (175.0, 200.0)].map(|(t0, t1)| {
        let (m, t) = window_mean(&h.f64, t0, t1);
        rel_errors(&m, &t)
    })
}

/// [`paper_window_errors`] in percent, a0, a1, b0, each for both windows.
fn percent_line([e1, e2]: [[f64; 3]; 2]) -> String {
    let p = |x: f64| x * 100.0;
    format!(
        "a0 {:+.3}% {:+.3}%  a1 {:+.3}% {:+.3}%  b0 {:+.3}% {:+.3}%",
        p(e1[0]),
        p(e2[0]),
        p(e1[1]),
        p(e2[1]),
        p(e1[2]),
        p(e2[2])
    )
}

/// Mains pickup on the probe (the lab's 50 Hz, and 150 Hz, its strongest odd harmonic), measured on the paper's
/// PRBS experiment: every estimator's window means' errors against no hum. Measured: both EKFs within 0.002 % of
/// their errors without hum up to 100 nm at both 50 and 150 Hz (30 times the noise floor's RMS); the continuous-time
/// RLS moved by up to 0.17 % in `a0` and 0.5 % in `a1` and `b0` there, the ARX by 0.17 % in `a0`, 0.7 % in `a1` and
/// 0.5 % in `b0`; at 20 nm both by under 0.05 % but the ARX's `a1` (0.04 % at 50 Hz, 0.09 % at 60 + 180 Hz).
#[test]
#[ignore = "measurement: cargo test --release -p hal-sim --test ekf -- --ignored --nocapture mains_hum"]
fn estimates_under_mains_hum() {
    use hal_sim::board::Tone;
    use nanopos_id::estimators::arx::{ArxDesign, ArxEstimator};
    use nanopos_id::estimators::crls::{Crls, CrlsDesign};
    let tone = |amplitude_nm: f64, freq_hz: f64| Tone { amplitude_um: amplitude_nm * 1e-3, freq_hz };
    let cases: [(&str, [Tone; 2]); 7] = [
        ("none", [Tone::default(); 2]),
        ("50 Hz, 5 nm", [tone(5.0, 50.0), Tone::default()]),
        ("50 Hz, 20 nm", [tone(20.0, 50.0), Tone::default()]),
        ("50 Hz, 100 nm", [tone(100.0, 50.0), Tone::default()]),
        ("150 Hz, 20 nm", [tone(20.0, 150.0), Tone::default()]),
        ("60 + 180 Hz, 20 nm each", [tone(20.0, 60.0), tone(20.0, 180.0)]),
        ("50 + 150 Hz, 100 nm each", [tone(100.0, 50.0), tone(100.0, 150.0)]),
    ];
    let (ekf, crls, arx) = (HekfDesign::default(), CrlsDesign::default(), ArxDesign::default());
    for (name, hum) in cases {
        let hummed = |b: &mut hal_sim::board::BoardSettings, _: &mut _| b.hum = hum;
        let rows = [
            ("hekf", paper_window_errors(|| Hekf::<f64>::new(ekf.design()), || Hekf::<f32>::new(ekf.design()), hummed)),
            ("ekf", paper_window_errors(|| Cekf::<f64>::new(ekf.design()), || Cekf::<f32>::new(ekf.design()), hummed)),
            (
                "rls",
                paper_window_errors(|| Crls::<f64>::new(crls.design()), || Crls::<f32>::new(crls.design()), hummed),
            ),
            (
                "arx",
                paper_window_errors(
                    || ArxEstimator::<f64>::new(arx.design()),
                    || ArxEstimator::<f32>::new(arx.design()),
                    hummed,
                ),
            ),
        ];
        for (est, errors) in rows {
            eprintln!("{name:26} {est:5}: {}", percent_line(errors));
        }
    }
}

/// Mains pickup does not bias the hybrid EKF: 100 nm at both 50 and 150 Hz on the probe's reading (30 times the
/// noise floor's RMS; the pre-filter's 100 Hz high-pass passes half of the 50 Hz) moves its window means by less
/// than 0.01 % of the truth (measured 0.002 %: the model's innovations take the hum for noise, uncorrelated with
/// the input). The whole table: `estimates_under_mains_hum`.
#[test]
fn mains_hum_on_the_probe_leaves_the_hybrid_ekf_where_it_was() {
    use hal_sim::board::Tone;
    let design = HekfDesign::default();
    let hum = [Tone { amplitude_um: 0.1, freq_hz: 50.0 }, Tone { amplitude_um: 0.1, freq_hz: 150.0 }];
    let errors = |hum: [Tone; 2]| {
        paper_window_errors(
            || Hekf::<f64>::new(design.design()),
            || Hekf::<f32>::new(design.design()),
            |b, _| b.hum = hum,
        )
    };
    let (quiet, hummed) = (errors([Tone::default(); 2]), errors(hum));
    for w in 0..2 {
        for p in 0..3 {
            let moved = hummed[w][p] - quiet[w][p];
            assert!(moved.abs() < 1e-4, "window {w}, parameter {p}: {:+.4} %", moved * 100.0);
        }
    }
}
