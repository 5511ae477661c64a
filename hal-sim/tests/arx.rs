//! The `arx` estimator on the simulated paper experiment (PRBS, 200 s, payload removed at 100 s).

use hal_sim::experiment::{paper_prbs, rel_errors, relock_time, report, run, window_mean};
use hal_sim::sim::Scenario;
use nanopos_id::estimators::arx::{ArxDesign, ArxEstimator};

#[test]
fn arx_on_the_paper_prbs_experiment() {
    let design = ArxDesign::default();
    let h = paper_prbs(|| ArxEstimator::<f64>::new(design.design()), || ArxEstimator::<f32>::new(design.design()));
    for (name, hist) in h.both() {
        let r = report(&format!("arx {name}"), hist);
        // Regression guards, not derived bounds (the measured errors are this test's report): the resonance
        // frequency within 0.1 % of a0 (what an ARX at the sample rate pins best), damping and gain within
        // 1.5 % (measured up to 1.09 % and 0.83 %, the residual of the filter replicas and the second mode).
        for e in r.windows {
            assert!(e[0].abs() < 1e-3 && e[1].abs() < 1.5e-2 && e[2].abs() < 1.5e-2, "{name}: {e:?}");
        }
        // Measured 2.1 s with a 0.5 s memory (lambda = 0.9998); guard at 3 s.
        assert!(r.relock_s.is_some_and(|t| t < 3.0), "{name}: {:?}", r.relock_s);
    }
}

#[test]
fn arx_f32_stays_with_f64_over_an_hour() {
    // One hour of PRBS on the payload stage (no change): converged means of f32 and f64 on identical readings.
    let design = ArxDesign::default();
    let h = run(
        Scenario::Prbs,
        3600.0,
        1,
        || ArxEstimator::<f64>::new(design.design()),
        || ArxEstimator::<f32>::new(design.design()),
        |board, _| board.plant.change_at_sample = u64::MAX,
    );
    let mut worst = [0.0f64; 3];
    for t1 in [600.0, 1200.0, 1800.0, 2400.0, 3000.0, 3600.0] {
        let (m64, _) = window_mean(&h.f64, t1 - 25.0, t1);
        let (m32, _) = window_mean(&h.f32, t1 - 25.0, t1);
        let d = rel_errors(&m32, &m64);
        for i in 0..3 {
            worst[i] = worst[i].max(d[i].abs());
        }
    }
    eprintln!(
        "arx f32 vs f64 over 1 h (25 s means every 10 min): a0 {:.1e}, a1 {:.1e}, b0 {:.1e}",
        worst[0], worst[1], worst[2]
    );
    assert!(worst[0] < 1e-4 && worst[2] < 1e-4, "{worst:?}");
}

/// Seconds from `start` (s) until a0 and b0 stay within 1 % of `truth` for the rest of `history`.
fn settle(
    history: &[(f64, nanopos_id::StageParams<f64>)],
    start: f64,
    truth: &nanopos_id::StageParams<f64>,
) -> Option<f64> {
    let samples: Vec<hal_sim::experiment::Sample> =
        history.iter().map(|&(t_s, est)| hal_sim::experiment::Sample { t_s, est, truth: *truth }).collect();
    relock_time(&samples, start, 0.01)
}

#[test]
fn arx_ten_minutes_without_excitation_neither_winds_up_nor_slows_the_relock() {
    use hal_sim::sim::Simulation;
    use nanopos_id::estimator::Estimator;
    use nanopos_id::excitation::ExcitationDesign;
    use nanopos_id::hal::{run_sample, StageBoard};
    use nanopos_id::pipeline::{Pipeline, PipelineSettings};
    use nanopos_id::StageParams;

    let design = ArxDesign::default();
    let (mut board, prbs) = Scenario::Prbs.settings(1.0, 1);
    board.plant.change_at_sample = u64::MAX;
    let quiet = PipelineSettings { excitation: ExcitationDesign::OFF, ..prbs };
    // The f32 pipeline on the simulated board (the target's precision, where windup would overflow first).
    let mut sim = Simulation::new(board, &quiet, ()).unwrap();
    let desc = sim.board.description();
    let (cfg_quiet, cfg_prbs) = (quiet.design::<f32>(&desc).unwrap(), prbs.design::<f32>(&desc).unwrap());
    let mut p = Pipeline::new(&cfg_quiet, (ArxEstimator::<f32>::new(design.design()),));
    let truth = StageParams::PAYLOAD;
    let quiet_samples = 600 * 10_000;
    let mut max_trace = 0.0f32;
    let mut history = Vec::new();
    for k in 0..quiet_samples + 60 * 10_000 {
        let cfg = if k < quiet_samples { &cfg_quiet } else { &cfg_prbs };
        run_sample(&mut sim.board, &mut p, cfg);
        let est = &p.estimators.0;
        max_trace = max_trace.max(est.rls().trace());
        assert!(est.rls().trace().is_finite() && est.rls().min_d() > 0.0, "sample {k}");
        if k % 100 == 99 {
            history.push(((k + 1) as f64 * 1e-4, est.params().cast::<f64>()));
        }
    }
    let est = &p.estimators.0;
    assert_eq!(est.health().numeric_resets, 0);
    // The bound: forgetting pauses once trace F would pass 1e3; one update can add at most its own (bounded) term.
    assert!(max_trace <= 1.0e3 * 1.001, "trace F reached {max_trace}");
    let relock_after_quiet = settle(&history, 600.0, &truth).expect("relocks after the quiet period");

    // Cold start on the same stage, PRBS from t = 0.
    let (mut board, prbs) = Scenario::Prbs.settings(60.0, 1);
    board.plant.change_at_sample = u64::MAX;
    let mut cold = Simulation::new(board, &prbs, ()).unwrap();
    let cfg = prbs.design::<f32>(&cold.board.description()).unwrap();
    let mut p = Pipeline::new(&cfg, (ArxEstimator::<f32>::new(design.design()),));
    let mut cold_history = Vec::new();
    for k in 0..60 * 10_000 {
        run_sample(&mut cold.board, &mut p, &cfg);
        if k % 100 == 99 {
            cold_history.push(((k + 1) as f64 * 1e-4, p.estimators.0.params().cast::<f64>()));
        }
    }
    let relock_cold = settle(&cold_history, 0.0, &truth).expect("cold start locks");
    eprintln!("arx windup: max trace F {max_trace:.1}, relock after 10 min quiet {relock_after_quiet:.2} s, cold start {relock_cold:.2} s");
    // "Within the same time as from a cold start": allow the quiet period's drifted start to cost 20 % more.
    assert!(relock_after_quiet <= 1.2 * relock_cold, "{relock_after_quiet} s vs {relock_cold} s");
}
