//! The firmware's interrupt body ([`Instrument::sample`]), its run-time control ([`Controller`]) and its safety
//! logic, on the simulated board through the HAL trait: the same calls the firmware makes, in the same order.

use hal_sim::board::SimBoard;
use hal_sim::lab::Lab;
use hal_sim::sim::Scenario;
use nanopos_id::console::REPLY_BYTES;
use nanopos_id::control::{EstimatorSet, ESTIMATOR_NAMES};
use nanopos_id::estimator::{Adaptation, Estimator};
use nanopos_id::estimators::{full_bank, restart_bank, Tuning, TuningKey};
use nanopos_id::hal::{BoardFaults, StageBoard};
use nanopos_id::instrument::{
    compare_ekfs, disagreement, response_ratio, trusted_ekf_estimate, weak_response, Change, EventWatch, Instrument,
    News, RecordStatus, WatchdogGate, RECORD_BUFFER,
};
use nanopos_id::pipeline::{FaultCounters, Faults, Pipeline};
use nanopos_id::record::{decode_frame, RawSample, END_TAG, FRAME_SAMPLES, HEADER_TAG};
use nanopos_id::text::{Num, TextBuf};
use nanopos_id::StageParams;
use std::path::{Path, PathBuf};

/// What these tests read of the firmware on the simulated board ([`Lab`]).
trait Measure {
    /// 20 s on the paper's stage with the payload on; over the last 10 s, every 10 ms, each estimator's samples
    /// starved (of 1 000) and the relative errors `(a0, a1, b0)` of its mean parameters against the truth.
    fn run_measuring(&mut self) -> ([usize; 4], [[f64; 3]; 4]);
    /// Estimator `i`'s parameters (`rls`, `ekf`, `hekf`, `arx`).
    fn params(&self, i: usize) -> StageParams<f32>;
}

impl Measure for Lab {
    fn run_measuring(&mut self) -> ([usize; 4], [[f64; 3]; 4]) {
        let truth = StageParams::PAYLOAD;
        let (mut starved, mut sums) = ([0usize; 4], [[0.0f64; 3]; 4]);
        for k in 0..200_000 {
            self.sample();
            if k >= 100_000 && k % 100 == 0 {
                for (i, (p, h)) in self.isr.estimates().iter().enumerate() {
                    starved[i] += (h.adaptation == Adaptation::Starved) as usize;
                    sums[i] = [sums[i][0] + p.a0 as f64, sums[i][1] + p.a1 as f64, sums[i][2] + p.b0 as f64];
                }
            }
        }
        let rel = sums.map(|s| [s[0] / 1e3 / truth.a0 - 1.0, s[1] / 1e3 / truth.a1 - 1.0, s[2] / 1e3 / truth.b0 - 1.0]);
        (starved, rel)
    }

    fn params(&self, i: usize) -> StageParams<f32> {
        self.isr.estimates()[i].0
    }
}

/// The last line of a reply.
fn verdict(reply: &str) -> &str {
    reply.lines().last().unwrap_or("")
}

/// The `note:` lines of a reply.
fn notes(reply: &str) -> Vec<String> {
    reply.lines().filter(|l| l.starts_with("note: ")).map(String::from).collect()
}

/// The end of the reply to a tuning that changes the EKFs' only.
const EKFS_RESTARTED: &str = "ekf,hekf restarted; rls,arx kept";
/// The end of the reply to a tuning that changes no estimator's.
const KEPT: &str = "estimators kept: their tuning is unchanged";

#[test]
fn the_interrupt_body_is_the_pipeline_the_host_tests() {
    // With nothing posted, `Instrument::sample` is exactly `run_sample` on a pipeline with every estimator.
    let mut lab = Lab::new();
    let (board_settings, _) = Scenario::Prbs.settings(200.0, 1);
    let mut board = SimBoard::new(board_settings);
    let cfg = lab.ctl.config::<f32>();
    let mut reference = Pipeline::new(&cfg, full_bank(&Tuning::preset("prbs").unwrap().design()));
    for _ in 0..20_000 {
        let a = lab.sample();
        let b = nanopos_id::hal::run_sample(&mut board, &mut reference, &cfg);
        assert_eq!(a, b);
    }
    let e = &reference.estimators;
    let want = [e.0.params(), e.1.params(), e.2.params(), e.3.params()];
    for (i, w) in want.iter().enumerate() {
        assert_eq!(lab.params(i), *w, "{}", ESTIMATOR_NAMES[i]);
    }
    // And it identifies: 2 s of PRBS bring the hybrid EKF's f0 within 1 % of the truth.
    let truth = lab.board.plant().params();
    let f0 = lab.params(2).f0_hz() as f64;
    assert!((f0 / truth.f0_hz() - 1.0).abs() < 0.01, "{f0} vs {}", truth.f0_hz());
}

/// A new tuning restarts every estimator in place ([`restart_bank`], what the interrupt does, to spare the copies of
/// building a bank and moving it in) to exactly what building them afresh ([`full_bank`]) gives: nothing of the run
/// before survives, not the previous samples, the health counters, a freeze or a gating pause.
#[test]
fn a_new_tuning_restarts_every_estimator_as_if_built_afresh() {
    let (board_settings, _) = Scenario::Prbs.settings(200.0, 1);
    let mut board = SimBoard::new(board_settings);
    let lab = Lab::new();
    let cfg = lab.ctl.config::<f32>();
    let prbs = Tuning::preset("prbs").unwrap().design::<f32>();
    let triangle = Tuning::preset("triangle").unwrap().design::<f32>();
    let mut run = Pipeline::new(&cfg, full_bank(&prbs));
    for k in 0..30_000 {
        if k == 20_000 {
            let e = &mut run.estimators;
            e.0.set_adapting(false);
            e.1.set_adapting(false);
            e.2.set_adapting(false);
            e.3.set_adapting(false);
        }
        nanopos_id::hal::run_sample(&mut board, &mut run, &cfg);
    }
    let fresh = full_bank(&triangle);
    assert_ne!(format!("{:?}", run.estimators), format!("{fresh:?}"));
    restart_bank(&mut run.estimators, &triangle, EstimatorSet::ALL);
    assert_eq!(format!("{:?}", run.estimators), format!("{fresh:?}"));
}

/// A new tuning restarts the estimators whose tuning it changes, and only those: the others run on with theirs, which
/// is the same. The initial parameters are every estimator's; the pre-filter is the continuous-time RLS's own (the
/// others read the pipeline's); the spike gate's ratio is none's.
#[test]
fn a_new_tuning_restarts_the_estimators_whose_tuning_it_changes() {
    let prbs = Tuning::preset("prbs").unwrap();
    // The set compared key by key, bit by bit, is the set of designs that differ.
    let designs_differ = |a: &Tuning, b: &Tuning| {
        let (rls, ekf, arx) = (a.rls != b.rls, a.ekf != b.ekf, a.arx != b.arx);
        EstimatorSet(rls as u8 | (ekf as u8) << 1 | (ekf as u8) << 2 | (arx as u8) << 3)
    };
    let changed = |key: TuningKey, values: &[f64]| {
        let mut t = prbs;
        t.set(key, values).unwrap();
        let set = prbs.restarted_by(&t);
        // The spike gate's ratio is in no design.
        if key != TuningKey::SpikeRatio {
            assert_eq!(set, designs_differ(&prbs, &t), "{key:?}");
        }
        set
    };
    assert_eq!(prbs.restarted_by(&prbs), EstimatorSet(0));
    assert_eq!(prbs.restarted_by(&Tuning::preset("triangle").unwrap()), EstimatorSet(0b0110));
    assert_eq!(changed(TuningKey::Initial, &[6e5, 70.0, 6e6]), EstimatorSet::ALL);
    assert_eq!(changed(TuningKey::Prefilter, &[100.0, 500.0, 0.1]), EstimatorSet(0b0001));
    assert_eq!(changed(TuningKey::SpikeRatio, &[8.0]), EstimatorSet(0));
    assert_eq!(changed(TuningKey::RlsGamma, &[0.5]), EstimatorSet(0b0001));
    assert_eq!(changed(TuningKey::EkfR, &[2e-6]), EstimatorSet(0b0110));
    assert_eq!(changed(TuningKey::ArxLambda, &[0.999]), EstimatorSet(0b1000));
    for key in TuningKey::ALL {
        // Every key: the preset's values moved a little (whole numbers by one, `lambda` towards 1).
        let moved = |v: f64| match key {
            TuningKey::ArxLambda => v.sqrt(),
            TuningKey::EkfReopen => v / 2.0, // the preset's is the ceiling's
            _ if v.fract() == 0.0 => v + 1.0,
            _ => 1.25 * v,
        };
        let values = prbs.get(key).map(moved);
        assert_eq!(changed(key, &values[..key.len()]), key.estimators(), "{key:?}");
    }
    // In place, as the interrupt does: the EKFs restarted as if built afresh, the RLS and the ARX untouched.
    let (board_settings, _) = Scenario::Prbs.settings(200.0, 1);
    let mut board = SimBoard::new(board_settings);
    let cfg = Lab::new().ctl.config::<f32>();
    let mut run = Pipeline::new(&cfg, full_bank(&prbs.design::<f32>()));
    for _ in 0..5_000 {
        nanopos_id::hal::run_sample(&mut board, &mut run, &cfg);
    }
    let triangle = Tuning::preset("triangle").unwrap().design::<f32>();
    let before = format!("{:?}", (&run.estimators.0, &run.estimators.3));
    restart_bank(&mut run.estimators, &triangle, EstimatorSet(0b0110));
    let fresh = full_bank(&triangle);
    assert_eq!(format!("{:?}", (&run.estimators.0, &run.estimators.3)), before);
    assert_eq!(format!("{:?}", (&run.estimators.1, &run.estimators.2)), format!("{:?}", (&fresh.1, &fresh.2)));
}

#[test]
fn a_change_applies_whole_between_two_samples_and_never_overwrites_a_waiting_one() {
    let mut lab = Lab::new();
    lab.run(100);
    let mut tight = *lab.ctl.settings();
    tight.limits.min_v = -0.25;
    tight.limits.max_v = 0.25;
    let cfg = tight.design::<f32>(&lab.board.description()).unwrap();
    let change = Change { config: Some(cfg), freeze: nanopos_id::control::EstimatorSet(0b0100), ..Change::default() };
    assert!(lab.isr.post(change.clone()).is_ok());
    // A second change while the first waits comes back untouched.
    let back = lab.isr.post(Change { clear_faults: true, ..Change::default() }).unwrap_err();
    assert!(back.0.clear_faults);
    assert!(lab.isr.change_pending());
    // The very next sample runs entirely with the new configuration: the limits and the freeze together.
    lab.sample();
    assert!(!lab.isr.change_pending());
    assert_eq!(lab.isr.config(), &cfg);
    assert_eq!(lab.isr.estimates()[2].1.adaptation, Adaptation::Frozen);
    for out in lab.run(200) {
        assert!(out.u_v.abs() <= 0.25 + 0.005, "{}", out.u_v);
    }
}

#[test]
fn every_command_is_answered_and_does_what_it_says() {
    let mut lab = Lab::new();
    lab.run(2000);
    // `help`: the commands, in one part of the reply.
    let r = lab.send("help\n");
    assert_eq!(verdict(&r), "ok help");
    assert!(r.len() <= REPLY_BYTES && r.starts_with("help | status\n"), "{r}");
    // Words in any case.
    let r = lab.send("STATUS\n");
    assert!(verdict(&r).starts_with("ok status samples="), "{r}");
    assert_eq!(r.lines().filter(|l| l.starts_with("est ")).count(), 4, "{r}");
    // Every estimator line carries the health counters, the covariance repairs among them.
    assert_eq!(r.lines().filter(|l| l.starts_with("est ") && l.contains(" resets=0 repairs=0 ")).count(), 4, "{r}");
    assert!(r.contains("excitation=prbs 1 V running"), "{r}");
    // The excitation monitor's level: the PRBS is rich, and its power far above the default floor (1e-6 V^2).
    let power: f64 = r.split("pe_power_v2=").nth(1).and_then(|s| s.split(' ').next()).unwrap().parse().unwrap();
    assert!(power > 1e-3 && r.contains(" pe_single=no "), "{r}");

    // Selection: only hekf runs; the others hold their estimates; selecting them again restarts them.
    assert_eq!(verdict(&lab.send("select hekf\n")), "ok select hekf");
    let before: Vec<_> = (0..4).map(|i| lab.params(i)).collect();
    lab.run(1000);
    for i in [0, 1, 3] {
        assert_eq!(lab.params(i), before[i], "{}", ESTIMATOR_NAMES[i]);
    }
    assert_ne!(lab.params(2), before[2]);
    assert!(lab.send("status\n").contains("est rls a0="));
    assert!(lab.send("status\n").lines().any(|l| l.starts_with("est rls") && l.contains(" off ")));
    assert_eq!(verdict(&lab.send("select all\n")), "ok select rls,ekf,hekf,arx");
    // `send` ran one sample after the reset: the restarted estimators are still at their initial parameters.
    let initial = StageParams::INITIAL.cast::<f32>();
    for i in [0, 1, 3] {
        let p = lab.params(i);
        assert!((p.a0 / initial.a0 - 1.0).abs() < 1e-3, "{}: {p:?}", ESTIMATOR_NAMES[i]);
    }

    // Freeze and adapt.
    assert_eq!(verdict(&lab.send("freeze ekf hekf\n")), "ok freeze ekf,hekf");
    let frozen = lab.params(2);
    lab.run(500);
    assert_eq!(lab.params(2), frozen);
    assert_eq!(lab.isr.estimates()[1].1.adaptation, Adaptation::Frozen);
    assert_eq!(verdict(&lab.send("adapt all\n")), "ok adapt rls,ekf,hekf,arx");
    lab.run(500);
    assert_ne!(lab.params(2), frozen);

    // Reset: back to the initial parameters.
    lab.send("reset hekf\n");
    let p = lab.params(2);
    assert!((p.a0 / initial.a0 - 1.0).abs() < 1e-3, "{p:?}");

    // Tuning: the estimators whose tuning changes restart (the triangle's preset differs from the PRBS's in the EKFs'
    // `Q`), the others run on; frozen ones stay frozen.
    lab.send("freeze rls\n");
    lab.run(2_000);
    let (rls, arx) = (lab.params(0), lab.params(3));
    assert_eq!(verdict(&lab.send("tuning triangle\n")), "ok tuning triangle (ekf,hekf restarted; rls,arx kept)");
    assert_eq!(lab.params(0), rls, "frozen and kept");
    assert!(a0_b0_off(lab.params(3), arx.a0 as f64, arx.b0 as f64) < 1e-4, "the ARX ran on: {arx:?}");
    for i in [1, 2] {
        let p = lab.params(i);
        assert!((p.a0 / initial.a0 - 1.0).abs() < 1e-3, "restarted from the initial parameters: {p:?}");
    }
    assert_eq!(lab.isr.estimates()[0].1.adaptation, Adaptation::Frozen);
    // The pipeline measures the input's excitation, not the estimator: a restarted estimator adapts from the first
    // sample after the change (the one `send` ran), with no wait for evidence that the input is rich.
    assert_eq!(lab.isr.estimates()[2].1.adaptation, Adaptation::Adapting);
    lab.run(100);
    assert_eq!(lab.isr.estimates()[0].1.adaptation, Adaptation::Frozen);
    assert_eq!(lab.isr.estimates()[2].1.adaptation, Adaptation::Adapting);
    assert!(lab.send("status\n").contains("tuning=triangle"));

    // One tuning value: another stage's initial parameters; the estimators restart from them.
    let r = lab.send("tune initial 1e6 90 3.9e7\n");
    assert_eq!(verdict(&r), "ok tune initial = 1e6 90 3.9e7 (estimators restarted)", "{r}");
    let p = lab.params(2);
    assert!((p.a0 / 3.9e7 - 1.0).abs() < 1e-3 && (p.b0 / 1e6 - 1.0).abs() < 1e-3, "{p:?}");
    assert_eq!(lab.isr.estimates()[0].1.adaptation, Adaptation::Frozen, "frozen ones stay frozen");
    assert!(lab.send("status\n").contains("tuning=triangle+tune "));
    assert_eq!(
        verdict(&lab.send("tune ekf drift_ratio 0\n")),
        format!("ok tune [ekf] drift_ratio = 0 ({EKFS_RESTARTED})")
    );
    // The spike gate's ratio, in the configuration the interrupt runs from the sample that applied it; 0: off.
    assert_eq!(lab.isr.config().spike.ratio, 32.0);
    assert_eq!(verdict(&lab.send("tune spike_ratio 16\n")), format!("ok tune spike_ratio = 16 ({KEPT})"));
    assert_eq!(lab.isr.config().spike.ratio, 16.0);
    // A preset replaces every value but the stage's (initial parameters, pre-filter, spike ratio).
    lab.send("tuning triangle\n");
    assert_eq!(verdict(&lab.send("tune ekf drift_ratio\n")), "ok tune [ekf] drift_ratio = 4");
    assert_eq!(verdict(&lab.send("tune initial\n")), "ok tune initial = 1e6 90 3.9e7");
    assert_eq!(verdict(&lab.send("tune spike_ratio\n")), "ok tune spike_ratio = 16");
    assert_eq!(verdict(&lab.send("tune spike_ratio 0\n")), format!("ok tune spike_ratio = 0 ({KEPT})"));
    assert_eq!(lab.isr.config().spike.ratio, f32::INFINITY);
    assert!(lab.send("status\n").contains("tuning=triangle+tune "));
    // The stage's pre-filter: the pipeline's and the continuous-time RLS's own change together. The RLS restarts; the
    // others identify the same stage through the pipeline's new filter, and run on once it has settled.
    let before = *lab.isr.config();
    assert_eq!(
        verdict(&lab.send("tune prefilter 100 600 0.1\n")),
        "ok tune prefilter = 100 600 0.1 (rls restarted; ekf,hekf,arx kept)"
    );
    assert_ne!(lab.isr.config().prefilter, before.prefilter);
    assert_eq!(lab.ctl.settings().prefilter.f_p_hz, 600.0);
    // One the pipeline cannot design (f_p above the Nyquist frequency) is refused, and nothing changes.
    assert_eq!(
        verdict(&lab.send("tune prefilter 100 6000 0.1\n")),
        "error: pre-filter: 6000 Hz: frequencies must be positive and below the Nyquist frequency, 5000 Hz"
    );
    assert_eq!(verdict(&lab.send("tune prefilter\n")), "ok tune prefilter = 100 600 0.1");
    // Nor one whose poles the continuous-time RLS's RK4 step cannot follow (a real pole at -11.9 W: it reset the
    // RLS 564 times in 5 s), though the pipeline's exact pre-filter could; 4 is within reach.
    assert_eq!(
        verdict(&lab.send("tune prefilter 100 450 6\n")),
        "error: the continuous-time RLS steps its pre-filter by RK4 at the sample period, and this pre-filter has a \
         pole too fast for that step (amplified 2.3 times a sample): lower f_lc, f_p or zeta_p"
    );
    assert_eq!(verdict(&lab.send("tune prefilter\n")), "ok tune prefilter = 100 600 0.1");
    // Nor one too close to 0 Hz (for the replicas' match there the lag replica came out NaN, and every estimator
    // reset on every sample, before the pre-filter's slowest pole was bounded: `PrefilterDesign::MAX_TIME_CONSTANT_S`).
    assert_eq!(
        verdict(&lab.send("tune prefilter 100 1e-6 0.1\n")),
        "error: this pre-filter is too slow: its slowest pole's time constant is 1.59e6 s, over 0.1 s (it rings on, \
         which the estimators take for excitation); raise f_lc, or zeta_p f_p, to 1.59 Hz or more"
    );
    assert_eq!(verdict(&lab.send("tune prefilter\n")), "ok tune prefilter = 100 600 0.1");
    assert_eq!(
        verdict(&lab.send("tune prefilter 100 450 4\n")),
        "ok tune prefilter = 100 450 4 (rls restarted; ekf,hekf,arx kept)"
    );
    lab.send("tune prefilter 100 450 0.1\n");
    lab.send("tune initial 5e5 70 6e6\n");
    lab.send("tune spike_ratio 32\n");
    // Frozen, so that the sample that applies a restart does not also move the estimate.
    lab.send("freeze hekf\n");
    lab.send("tuning triangle\n");
    assert!(lab.send("status\n").contains("tuning=triangle "), "the paper's stage again: no change left");
    assert_eq!(lab.params(2), initial, "restarted from the paper's initial parameters");
    lab.send("adapt hekf\n");
    // Without values: the value in use, and nothing restarts.
    lab.run(2000);
    let moved = lab.params(2);
    assert!((moved.b0 / initial.b0 - 1.0).abs() > 0.1, "{moved:?}");
    assert_eq!(verdict(&lab.send("tune initial\n")), "ok tune initial = 500000 70 6e6");
    assert_eq!(verdict(&lab.send("tune ekf q\n")), "ok tune [ekf] q = 1e-12 1e-6 1.5e11 25 5e10", "Q1, the triangle's");
    lab.run(1);
    // A restart would put b0 back at its initial value, one sample away from it.
    assert!((lab.params(2).b0 / initial.b0 - 1.0).abs() > 0.1, "not restarted: {:?}", lab.params(2));

    // Excitation: a sine, then stop (output ramps to 0 V), then start.
    assert_eq!(verdict(&lab.send("excite sine 0.5 200\n")), "ok excite sine 0.5 V 200 Hz (running)");
    let peak = lab.run(500).iter().map(|o| o.u_v.abs()).fold(0.0, f32::max);
    assert!((peak - 0.5).abs() < 0.01, "{peak}");
    // A single sinusoid: the monitor says so (after its 10 ms averages have forgotten the PRBS), and no estimator
    // adapts (those not frozen above read `starved`).
    lab.run(5000);
    let r = lab.send("status\n");
    assert!(r.contains(" pe_single=yes "), "{r}");
    assert!(r.lines().any(|l| l.starts_with("est hekf") && l.contains(" starved ")), "{r}");
    assert!(!r.contains(" adapting "), "{r}");
    assert_eq!(verdict(&lab.send("stop\n")), "ok stop (output to 0 V at the slew limit)");
    let tail = lab.run(100);
    assert!(
        tail[20..].iter().all(|o| o.u_v.abs() < 0.005),
        "{:?}",
        tail[..5].iter().map(|o| o.u_v).collect::<Vec<_>>()
    );
    assert!(lab.send("status\n").contains("excitation=sine 0.5 V 200 Hz stopped"));
    assert_eq!(verdict(&lab.send("start\n")), "ok start sine 0.5 V 200 Hz (latched faults cleared)");
    let peak = lab.run(500).iter().map(|o| o.u_v.abs()).fold(0.0, f32::max);
    assert!(peak > 0.45, "{peak}");
    assert_eq!(verdict(&lab.send("excite off\n")), "ok excite off (running)");
}

#[test]
fn every_malformed_or_impossible_command_gets_an_error_and_changes_nothing() {
    let mut lab = Lab::new();
    lab.run(100);
    let cfg = *lab.isr.config();
    let bad = [
        "",
        "launch",
        "status now",
        "excite",
        "excite square 1",
        "excite prbs 11",
        "excite prbs NaN",
        "excite sine 1 0",
        "excite triangle 1 10 3 4",
        "excite triangle 1 10 11",
        "excite multisine 1 800 200",
        "excite multisine 1 200 1001",
        "excite constant 10.5",
        "select hekf,,arx",
        "reset none",
        "freeze",
        "tuning sine",
        "limits 5 -5 100",
        "limits -5 5 0",
        // Parses, but cannot be honoured: the safe value (0 V) would be outside the clamp.
        "limits 1 5 1000",
        "record burst 0",
        "status\u{7f}",
        "tune",
        "tune kalman q 1",
        "tune ekf q 1 2 3",
        "tune rls gamma x",
        "tune rls gamma 1e20",
        // Parse, but out of range.
        "tune ekf reopen 5000",
        "tune ekf q 1 1 -1 1 1",
        "tune initial 5e5 70 0",
        "tune spike_ratio 2.5",
        "tune spike_ratio 65536",
        "tune spike_ratio -1",
        // In range, but out of f32's once normalised (`q_b0 / b0^2`, `1 / R`); the last hung the console before
        // `linalg::zoh` counted its halvings in floating point.
        "tune initial 1e-20 70 6e6",
        "tune ekf r 1e-45",
        "tune initial 500000 1e38 6e6",
        // Pre-filters that ring for ever, or for seconds (`PrefilterDesign::MAX_TIME_CONSTANT_S`): an undamped
        // oscillator on an integrator, a pair with `zeta_p w_p` of 0.3 /s, a high-pass corner at 0.5 Hz.
        "tune prefilter 1.4e-8 9.9 6e-9",
        "tune prefilter 100 450 1e-4",
        "tune prefilter 0.5 450 0.1",
    ];
    for line in bad {
        let r = lab.send(&format!("{line}\n"));
        assert_eq!(r.lines().count(), 1, "{line:?}: {r}");
        assert!(r.starts_with("error: "), "{line:?}: {r}");
        assert_eq!(lab.isr.config(), &cfg, "{line:?} changed the configuration");
    }
    assert_eq!(
        lab.send("limits 1 5 1000\n").trim_end(),
        "error: output limits need min_v < max_v, safe_v between them, and a positive slew limit"
    );
    assert_eq!(
        lab.send("tune ekf reopen 5000\n").trim_end(),
        "error: word 4: 5000: between 1 and 500 (the variance ceiling)"
    );
    assert_eq!(lab.send("tune ekf q 1 1 -1 1 1\n").trim_end(), "error: word 6: -1: must be a positive number");
    assert_eq!(lab.send("tune initial 5e5 70 0\n").trim_end(), "error: word 5: 0: must be a positive number");
    assert_eq!(
        lab.send("tune spike_ratio 65536\n").trim_end(),
        "error: word 3: 65536: a whole number from 0 (off) to 65535"
    );
    assert_eq!(
        lab.send("tune rls gamma 1e20\n").trim_end(),
        "error: word 4: 1e20: above 0 and at most 10000 /s (the sample rate)"
    );
    assert_eq!(
        lab.send("tune prefilter 100 450 1e-4\n").trim_end(),
        "error: this pre-filter is too slow: its slowest pole's time constant is 3.54 s, over 0.1 s (it rings on, \
         which the estimators take for excitation); raise f_lc, or zeta_p f_p, to 1.59 Hz or more"
    );
    assert!(lab.send("status\n").contains(" tuning=prbs "), "no refused value was kept");
    assert_eq!(
        lab.send("tune ekf r 1e-45\n").trim_end(),
        "error: the estimators cannot hold this tuning: a normalised constant (Q, P0 or a bound over the square of an \
         initial parameter, 1 / R, ...) leaves the range of their arithmetic"
    );
    // A stage that fits the PRBS tuning (Q2) but not the triangle's, whose Q is 100 times larger: the preset is
    // refused, and the tuning stays.
    assert_eq!(
        verdict(&lab.send("tune initial 3e-13 70 6e6\n")),
        "ok tune initial = 3e-13 70 6e6 (estimators restarted)"
    );
    let tuning = lab.ctl.tuning::<f32>();
    assert!(verdict(&lab.send("tuning triangle\n")).starts_with("error: the estimators cannot hold this tuning"));
    assert_eq!(lab.ctl.tuning::<f32>(), tuning);
    assert!(lab.send("status\n").contains(" tuning=prbs+tune "));
    lab.send("tuning prbs\ntune initial 5e5 70 6e6\n");
    // The preset's own values back: `status` names the preset alone, as after `tuning`.
    assert!(lab.send("status\n").contains(" tuning=prbs "));
    let r = lab.send(&format!("{}\n", "x".repeat(200)));
    assert!(r.starts_with("error: line longer than 96 bytes"), "{r}");

    // Noise on the line: every line gets exactly one final answer, nothing panics.
    let mut next = nanopos_id::xorshift64(0x2545_F491_4F6C_DD1D);
    let words = [
        "status", "excite", "prbs", "sine", "1", "-3", "1e3", "x", "select", "all", "hekf,rls", "limits", "record",
        "burst", "0.5", ",", "\t", "\u{1}",
    ];
    for _ in 0..3000 {
        let n = (next() % 5) as usize;
        let line: Vec<&str> = (0..n).map(|_| words[(next() % words.len() as u64) as usize]).collect();
        let r = lab.send(&format!("{}\n", line.join(" ")));
        let last = verdict(&r);
        assert!(last.starts_with("ok") || last.starts_with("error: "), "{line:?}: {r}");
        lab.sample();
    }
}

/// `excite constant V` holds the stage at an operating point, and every waveform can run about one (`excite prbs
/// AMP OFFSET`): the output is the waveform plus the offset, still clamped by `limits`, `status` says so, and the
/// estimators, which see the input through band-pass filters, identify the same stage about 2 V as about 0 V.
#[test]
fn an_excitation_runs_about_an_offset_and_a_constant_holds_the_stage() {
    let lsb = 20.0 / 4096.0;
    // Two runs alike but for the offset of the second half.
    let hekf_after = |offset: &str| {
        let mut lab = Lab::new();
        lab.run(50_000);
        let reply = lab.send(&format!("excite prbs 1 {offset}\n"));
        let out = lab.run(50_000);
        (lab, reply, out)
    };
    let (zero, _, _) = hekf_after("0");
    let (mut lab, reply, out) = hekf_after("2");
    assert_eq!(verdict(&reply), "ok excite prbs 1 V offset 2 V (running)");
    assert!(lab.send("status\n").contains(" excitation=prbs 1 V offset 2 V running "));
    let (lo, hi) = out[100..].iter().fold((f32::MAX, f32::MIN), |(a, b), o| (a.min(o.u_v), b.max(o.u_v)));
    assert!((lo - 1.0).abs() <= lsb && (hi - 3.0).abs() <= lsb, "{lo} {hi}");
    let (about_zero, about_two) = (zero.params(2), lab.params(2));
    let rel = |a: f32, b: f32| (a / b - 1.0).abs();
    println!("hekf after 5 s about 0 V: {about_zero:?}; about 2 V: {about_two:?}");
    assert!(rel(about_two.a0, about_zero.a0) < 1e-4 && rel(about_two.b0, about_zero.b0) < 1e-3, "{about_two:?}");

    assert_eq!(verdict(&lab.send("excite constant -1.5\n")), "ok excite constant -1.5 V (running)");
    assert!(lab.send("status\n").contains(" excitation=constant -1.5 V running "));
    let out = lab.run(10_000);
    assert!(out[100..].iter().all(|o| (o.u_v + 1.5).abs() <= lsb), "{:?}", out.last().map(|o| o.u_v));
    // Once the step has rung out of the monitor's band-pass (5-20 Hz), a constant identifies nothing.
    let held = lab.isr.estimates().map(|(_, h)| h.adaptation);
    assert!(held.iter().all(|&a| a == Adaptation::Starved), "{held:?}");
    // Clamped as any command; refused out of range, nothing changed.
    assert!(verdict(&lab.send("limits -1 1 25000\n")).starts_with("ok limits"));
    assert!(lab.run(1000)[100..].iter().all(|o| (o.u_v + 1.0).abs() <= lsb));
    assert_eq!(verdict(&lab.send("excite constant 12\n")), "error: word 3: expected a level in V, -10 to 10");
    assert!(lab.send("status\n").contains(" excitation=constant -1.5 V running "));
    assert_eq!(verdict(&lab.send("excite off\n")), "ok excite off (running)");
    assert!(lab.run(1000)[500..].iter().all(|o| o.u_v.abs() <= lsb));
}

#[test]
fn the_output_is_clamped_and_slew_limited_as_configured_at_run_time() {
    let mut lab = Lab::new();
    // `limits` alone reports the limits in use and the clamp they make within the DAC's reach (there was no way to
    // ask: `status` does not give them), and changes nothing.
    let cfg = *lab.isr.config();
    assert_eq!(
        lab.send("limits\n"),
        "ok limits -10 V to 10 V, 25000 V/s (the clamp in force, within the DAC's reach: -8.78418 V to 8.78418 V)\n"
    );
    assert_eq!(lab.isr.config(), &cfg);
    assert_eq!(verdict(&lab.send("limits -0.4 0.6 500\n")), "ok limits -0.4 V to 0.6 V, 500 V/s");
    assert_eq!(
        verdict(&lab.send("limits\n")),
        "ok limits -0.4 V to 0.6 V, 500 V/s (the clamp in force, within the DAC's reach: -0.4 V to 0.6 V)"
    );
    let lsb = 20.0 / 4096.0;
    let out = lab.run(5000);
    let (lo, hi) = out.iter().fold((f32::MAX, f32::MIN), |(a, b), o| (a.min(o.u_v), b.max(o.u_v)));
    assert!(lo >= -0.4 - lsb && hi <= 0.6 + lsb, "{lo} {hi}");
    assert!(lo < -0.35 && hi > 0.55, "the clamp is reached: {lo} {hi}");
    let max_step = out.windows(2).map(|w| (w[1].u_v - w[0].u_v).abs()).fold(0.0, f32::max);
    assert!(max_step <= 0.05 + lsb, "{max_step} V per sample for 500 V/s");
    assert!(max_step > 0.04);

    // A fault's ramp (and `stop`'s) goes through the slew limit, so the limit may not be so slow that the output
    // would take more than 0.1 s back to its safe value from anywhere the DAC reaches (-8.78 to 8.78 V, its buffered
    // output's 0.2 to 3.1 V; the clamp's range does not bound it: narrowed, the output ramps into it from where it
    // was): 1e-30 V/s was accepted, and a fault left the output where it was. The slowest allowed brings it back from
    // the DAC's end within 1 000 samples.
    let cfg = *lab.isr.config();
    assert_eq!(
        verdict(&lab.send("limits -0.4 0.6 87.8\n")),
        "error: slew limit: at least 87.8418 V/s, so that after a fault the output reaches its safe value within 0.1 s \
         from anywhere in the DAC's range"
    );
    assert_eq!(lab.isr.config(), &cfg);
    // Limits beyond the DAC's reach: accepted, and the reply says where the output stops (and that the PRBS, 2 V
    // steps, will be ramped).
    let reply = lab.send("limits -10 10 87.9\n");
    assert_eq!(
        notes(&reply),
        [
            "note: the DAC reaches -8.78418 V to 8.78418 V (its output is specified from 0.2 V to 3.1 V): the clamp \
             stops the output there",
            "note: the excitation steps by up to 2 V a sample (20000 V/s), beyond the slew limit's 0.00879 V: it \
             will be ramped"
        ]
    );
    assert_eq!(verdict(&reply), "ok limits -10 V to 10 V, 87.9 V/s");
    let reply = lab.send("excite constant -10\n");
    assert_eq!(
        notes(&reply),
        ["note: the excitation spans -10 V to -10 V, beyond the clamp's -8.78418 V to 8.78418 V: the clamp will clip \
          it"]
    );
    assert_eq!(verdict(&reply), "ok excite constant -10 V (running)");
    let last = *lab.run(3000).last().unwrap();
    assert!((last.u_v + 8.78418).abs() <= 1e-5 && last.dac_code == 249, "{last:?}");
    assert!(verdict(&lab.send("stop\n")).starts_with("ok stop"));
    let back = lab.run(1100).iter().position(|o| o.u_v.abs() <= lsb / 2.0);
    assert!(back.is_some_and(|k| k <= 1001), "{back:?}");
}

#[test]
fn a_probe_over_range_or_stuck_stops_the_excitation_until_start() {
    for (name, code, samples) in [("over_range", 0u32, 50usize), ("stuck", 30_000, 1200)] {
        let mut lab = Lab::new();
        lab.run(1000);
        lab.board.forced_probe_code = Some(code);
        let out = lab.run(samples);
        let last = out.last().unwrap();
        assert!(!last.faults.is_empty(), "{name}");
        assert!(last.estimator_input.is_none(), "{name}: estimators not fed while a fault is latched");
        // The output went to the safe value (0 V: the DAC's mid-scale) through the slew limiter, and stays.
        let safe = lab.isr.config().safe_code();
        assert_eq!(safe, 2048);
        let tail = lab.run(20);
        assert!(tail.iter().all(|o| o.dac_code == safe), "{name}");
        let status = lab.send("status\n");
        assert!(status.contains(&format!("faults={name}")), "{status}");
        // Cleared by start once the probe is back.
        lab.board.forced_probe_code = None;
        assert!(lab.send("start\n").starts_with("ok start"));
        let out = lab.run(200);
        assert!(out.iter().all(|o| o.faults == Faults::default()), "{name}");
        assert!(out.iter().any(|o| o.u_v.abs() > 0.9), "{name}: excitation resumed");
    }
}

/// One probe reading out of line with the others (code 50 000: 26 um, inside the probe's +-50 um, so no
/// over-range), 3 s into the paper's PRBS on the board. The spike gate replaces it and counts it (`status`:
/// `spikes=1`), and over the half second after it every estimator stays within 1e-4 of the same run without the
/// glitch (measured: 2.5e-5 at most, the EKFs, from the few nm by which the curve misses the true reading); with the
/// gate off (`tune spike_ratio 0` on the console, the firmware as it was) the glitch moved the EKFs' parameters by up
/// to 83 % and the ARX's by 9 % in that half second (the RLS's by 0.1 %; with the gate set in the settings instead,
/// the glitch one sample earlier in the PRBS, 63-67 %, 9 % and 0.2 %).
#[test]
fn a_probe_glitch_is_replaced_and_moves_no_estimate() {
    // Each estimator's parameters every 10 ms for 0.5 s from the glitch's sample on, and the lab after.
    // The telemetry's news (a warning in the log) of the replaced readings, at its looks 0.1 s apart around it.
    let run = |glitch: bool, spike_ratio: u16| {
        let (board, settings) = Lab::settings(None);
        let mut lab = Lab::on_board(board, settings);
        if spike_ratio != settings.faults.spike_ratio {
            let reply = lab.send(&format!("tune spike_ratio {spike_ratio}\n"));
            // The gate's ratio is no estimator's tuning: they run on.
            assert_eq!(reply, format!("ok tune spike_ratio = {spike_ratio} ({KEPT})\n"));
            assert_eq!(lab.send("tune spike_ratio\n"), format!("ok tune spike_ratio = {spike_ratio}\n"));
        }
        let mut watch = EventWatch::new(1e4);
        let mut news = Vec::new();
        for _ in 0..300 {
            lab.run(100);
            news.push(watch.look(&lab.isr.status()).spikes);
        }
        if glitch {
            lab.board.forced_probe_code = Some(50_000);
            let out = lab.run(1)[0];
            assert!((out.y_um - 26.2).abs() < 0.1 && out.faults.is_empty(), "{out:?}");
            lab.board.forced_probe_code = None;
        } else {
            lab.run(1);
        }
        let seen: Vec<_> = (0..50).map(|_| (lab.run(100), lab.isr.status().estimates).1).collect();
        news.extend((0..2).map(|_| watch.look(&lab.isr.status()).spikes));
        (seen, lab, news)
    };
    // The largest relative difference of any parameter, per estimator, between two runs.
    let worst = |a: &[[(StageParams<f32>, _); 4]], b: &[[(StageParams<f32>, _); 4]]| {
        let mut worst = [0.0f64; 4];
        for (x, y) in a.iter().zip(b) {
            for (i, ((p, _), (q, _))) in x.iter().zip(y).enumerate() {
                worst[i] = worst[i].max(worst_relative(&[p.cast()], &[*q]));
            }
        }
        worst
    };
    let default = nanopos_id::pipeline::FaultSettings::default().spike_ratio;
    let (clean, _, _) = run(false, default);
    let (gated, mut lab, news) = run(true, default);
    let ((off, off_lab, _), (clean_off, _, _)) = (run(true, 0), run(false, 0));
    // Nothing before the glitch, from the gate's start on; the one, once.
    assert_eq!(news[..300], [0; 300]);
    assert_eq!(news[300..], [1, 0]);
    let (with, without) = (worst(&gated, &clean), worst(&off, &clean_off));
    let show = |w: [f64; 4]| w.map(|x| format!("{x:.1e}")).join(" ");
    eprintln!("the most a0, a1, b0 moved over 0.5 s (rls ekf hekf arx): gate {}, off {}", show(with), show(without));
    assert_eq!(lab.isr.status().counters.spikes, 1);
    assert_eq!(off_lab.isr.status().counters.spikes, 0);
    let status = lab.status_reply();
    assert!(status.contains(" spikes=1 "), "{status}");
    for i in 0..4 {
        assert!(with[i] < 1e-4, "{}: {:e} with the gate", ESTIMATOR_NAMES[i], with[i]);
        assert!(i == 0 || without[i] > 0.05, "{}: {:e} without the gate", ESTIMATOR_NAMES[i], without[i]);
    }
}

/// `status` at its widest fits the console's buffer a line at a time (it was written whole into the firmware's
/// 768-byte buffer, which cut it after about three `est` lines: the `ok status` line never reached the board's user;
/// the host's tests used a 1 KiB buffer). Every counter at its largest, the longest numbers, every fault, the
/// longest excitation, tuning and recorder words, and the note of the EKFs' disagreement.
#[test]
fn the_widest_status_reply_fits_the_consoles_buffer_line_by_line() {
    let mut lab = Lab::new();
    lab.run(100);
    // The widest excitation: two frequencies and an offset, every number at full width.
    let excite = "excite multisine 9.87654321 987.654321 999.987654 -9.87654321\n";
    for cmd in [excite, "tune ekf r 1.23456789e-7\n", "select all\n"] {
        assert!(verdict(&lab.send(cmd)).starts_with("ok"), "{cmd}");
    }
    let mut st = lab.isr.status();
    let long = -1.17549e-38f32;
    st.samples = u64::MAX;
    st.faults = Faults(0xFF);
    st.counters = FaultCounters {
        probe_over_range: u32::MAX,
        probe_stuck: u32::MAX,
        spikes: u32::MAX,
        command_not_finite: u32::MAX,
        deadline_misses: u32::MAX,
        adc_overruns: u32::MAX,
        limited: u32::MAX,
    };
    (st.command_v, st.excitation_level.power, st.excitation_level.single) = (long, long, true);
    st.record =
        RecordStatus { active: false, remaining: None, recorded: u64::MAX, overflowed: true, buffered: usize::MAX };
    st.isr_cycles_max = u32::MAX;
    for (p, h) in st.estimates.iter_mut() {
        // a0 > 0 and tiny, the rest negative: every derived number in exponent form with a sign.
        *p = StageParams { a0: 1.23457e-30, a1: -1.23457e-30, b0: long };
        h.adaptation = Adaptation::Adapting;
        (h.rejected_samples, h.changes_detected, h.numeric_resets, h.covariance_repairs) =
            (u32::MAX, u32::MAX, u32::MAX, u32::MAX);
        h.innovation_rms_um = long;
    }
    // The EKFs' gain of the other sign: the note of their disagreement with the ARX, its longest form, too.
    for (p, _) in &mut st.estimates[1..3] {
        p.b0 = -long;
    }
    let cmd = nanopos_id::control::parse(b"status").unwrap();
    let mut reply = TextBuf::<REPLY_BYTES>::default();
    let (change, mut rest) = lab.ctl.execute(cmd, || st, &mut reply);
    assert!(change.is_none() && reply.as_str().is_empty());
    let mut lines = Vec::new();
    while {
        reply.clear();
        rest.write_next(&lab.ctl, &mut reply)
    } {
        assert!(!reply.truncated(), "{}", reply.as_str());
        lines.push(reply.as_str().to_string());
    }
    let widest = lines.iter().map(String::len).max().unwrap();
    let whole: usize = lines.iter().map(String::len).sum();
    println!(
        "status at its widest: {whole} bytes in {} lines, the widest {widest} (buffer {REPLY_BYTES})",
        lines.len()
    );
    for l in &lines {
        println!("{}", l.trim_end());
    }
    assert_eq!(lines.len(), 6);
    assert!(
        lines[..4].iter().all(|l| l.starts_with("est "))
            && lines[4].starts_with("note: ekf,hekf disagree with arx ")
            && lines[5].starts_with("ok status samples=18446744073709551615 ")
            && lines[5].contains(" isr_cycles_max=4294967295 ")
    );
    assert!(whole > 1024, "the whole would not fit one buffer of 1 KiB either: {whole}");
}

/// A limit, kept measured: the continuous EKF takes one RK4 step of its Riccati equation per sample (SPEC 6.4), whose
/// measurement term `P H' H P / R` grows stiff as `R` shrinks. With `R` a million times below the paper's it resets
/// over and over on the board's PRBS, where the hybrid filter (four substeps, the update in Joseph form) converges
/// without a reset (10 s after the restart: `a0` -0.04 %, `a1` +0.7 %, `b0` +0.8 %). Until the EKFs took every sample
/// for the first 0.5 s after a restart, it reset once: its states taken from the first sample, whose rate is within
/// 0.5 % of a converged filter's `x2` (3 nm over a sample where this `R` expects 1e-3 nm), it moved its parameters far,
/// gated most samples, and its relock test reset it 5 s after the restart. (Started at zero, it had taken the start
/// for a change and was never reset.) A tuning that fits but diverges is the health logic's to report. At 1e-2 of the
/// paper's both converge without a reset, their innovation RMS at the noise 10 s after the start. (Started at zero,
/// the continuous filter's start-up transient threw its innovation RMS beyond a metre, `INNOVATION_CEILING_UM`, and it
/// reset 3 times; before that ceiling, its state stayed finite and its innovation RMS read NaN for good.)
#[test]
fn a_far_smaller_r_breaks_the_continuous_ekf_and_not_the_hybrid() {
    let run = |r: &str| {
        let mut lab = Lab::new();
        lab.run(2000);
        // The paper's R is the preset's: nothing to restart.
        let what = if r == "1.5e-6" { "estimators kept: their tuning is unchanged" } else { EKFS_RESTARTED };
        assert_eq!(verdict(&lab.send(&format!("tune ekf r {r}\n"))), format!("ok tune [ekf] r = {r} ({what})"));
        lab.run(100_000);
        let st = lab.isr.status();
        for (_, h) in &st.estimates[1..3] {
            assert!(!h.innovation_rms_um.is_nan(), "R = {r}: {h:?}");
        }
        st
    };
    let resets = |r: &str| {
        let st = run(r);
        (st.estimates[1].1.numeric_resets, st.estimates[2].1.numeric_resets)
    };
    assert_eq!(resets("1.5e-6"), (0, 0), "the paper's R");
    let st = run("1.5e-8");
    let (cekf, hekf) = (st.estimates[1].1.numeric_resets, st.estimates[2].1.numeric_resets);
    assert!(cekf == 0 && hekf == 0, "{cekf} {hekf}");
    // Its innovation RMS is of the last second: at the noise, as the hybrid filter's (measured 5.3 and 5.5 nm). As an
    // exponential average of the squares it had read 589 um here, with the start-up's resets in it.
    let (ci, hi) = (st.estimates[1].1.innovation_rms_um, st.estimates[2].1.innovation_rms_um);
    assert!(ci < 1.5 * hi && hi < 0.01, "{ci} {hi}");
    for (p, _) in &st.estimates[1..3] {
        let t = StageParams::PAYLOAD;
        let e = [p.a0 as f64 / t.a0, p.a1 as f64 / t.a1, p.b0 as f64 / t.b0].map(|x| (x - 1.0).abs());
        assert!(e.iter().all(|&e| e < 5e-3), "{p:?}");
    }
    let st = run("1.5e-12");
    let (cekf, hekf) = (st.estimates[1].1.numeric_resets, st.estimates[2].1.numeric_resets);
    let (p, t) = (st.estimates[2].0, StageParams::PAYLOAD);
    let off = [p.a0 as f64 / t.a0, p.a1 as f64 / t.a1, p.b0 as f64 / t.b0].map(|x| x - 1.0);
    let [a0, a1, b0] = off;
    println!("R = 1.5e-12 um^2 over 10 s: the continuous EKF reset {cekf} times, the hybrid {hekf} (a0 {a0:+.1e} a1 {a1:+.1e} b0 {b0:+.1e})");
    assert!(cekf > 1000 && hekf == 0, "{cekf} {hekf}");
    assert!(off.iter().all(|e| e.abs() < 0.01), "the hybrid converged: {p:?}");
}

/// A large excitation after a long pause: two minutes without excitation (the payload coming off meanwhile), then a
/// PRBS or a multisine of 8 V, whose misfit (the board's second mode) makes innovations 15 times those of the pause
/// (40 nm against 2.6 nm; `nu^2 / S` about 240 times its long-run level then). The EKFs see a change, relock, and are
/// not taken for filters that did not: `RELOCK_NIS_RATIO` compares their level 5 s later with 1 as well as with the
/// level before (compared with that alone, each EKF was reset once, 5 s after the excitation came back). 12 s after
/// it `a0` and `b0` are within 1 % of the truth. (`b0` read 0.6 % high here under the PRBS, against 0.3 % under the
/// paper's 1 V one: not a bias of the amplitude but the random walk's wander. Sampled every few seconds from 1 to
/// 40 s after the excitation came back, `b0` was 0.11-0.76 % high at 8 V and 0.15-0.39 % at 1 V: with `Q` fixed,
/// 64 times the input's power makes the filters' gain, and so their wander, larger (Q2 was tuned for 1 V); with the
/// payload on for good and averaged over 10 s, both EKFs' `b0` was within 0.04 % of the truth at 1, 2, 4 and 8 V.)
#[test]
fn a_large_excitation_after_a_long_pause_resets_no_estimator() {
    for excitation in ["excite prbs 8\n", "excite multisine 8 200 800\n"] {
        let mut lab = Lab::new();
        assert!(verdict(&lab.send("limits -10 10 1000000\n")).starts_with("ok"));
        lab.run(100_000);
        assert!(verdict(&lab.send("excite off\n")).starts_with("ok"));
        lab.run(1_200_000);
        assert!(verdict(&lab.send(excitation)).starts_with("ok"));
        lab.run(120_000);
        let st = lab.isr.status();
        for (name, (p, h)) in ["ekf", "hekf"].iter().zip(&st.estimates[1..3]) {
            let t = StageParams::NO_PAYLOAD;
            let e = [p.a0 as f64 / t.a0, p.b0 as f64 / t.b0].map(|x| (x - 1.0).abs());
            println!(
                "{} {name}: changes {}, resets {}, a0 and b0 off by {:.1e} and {:.1e}",
                excitation.trim(),
                h.changes_detected,
                h.numeric_resets,
                e[0],
                e[1]
            );
            assert!(h.changes_detected > 0 && h.numeric_resets == 0, "{excitation} {name}: {h:?}");
            assert!(e.iter().all(|&e| e < 1e-2), "{excitation} {name}: {p:?}");
        }
    }
}

/// The EKFs' `Q` against the excitation's amplitude: the paper's Q2 was made for its 1 V PRBS. The misfit of their
/// model (the board's second mode and analog chain here; a real stage's higher modes and hysteresis) grows with the
/// input, and with `Q` fixed their parameters follow the data faster (their covariance settles where the input's
/// power meets `Q`): at 8 V they wander about twice as far. `Q`'s parameter entries divided by the amplitude squared
/// keep them as at 1 V (the filter on the scaled input is the one on the input at 1 V, but for the noise, which then
/// weighs less: the PRBS, whose misfit dominates, as at 1 V; the multisine, whose band leaves the second mode alone,
/// better). So a PRBS or a multisine of 2 V or more with Q2 is noted with that `tune ekf q`; not when the clamp clips
/// it, its band misses the resonance or the triangle's note applies (the reply would overflow, the excitation is
/// unfit anyway), nor with another `q`.
///
/// Measured on the firmware over the paper's 200 s (`cargo test --release --test instrument -- --nocapture
/// strong_excitation`), the largest excursion of the EKFs' `b0` from the truth from 20 s on, but for the 10 s after
/// the payload comes off: at 1 V 0.52-0.54 %; at 8 V 1.03-1.05 % (beyond the 1 % within which `paper` counts a relock:
/// never for good); at 8 V with the note's `q` 0.54-0.56 % (1.04 times 1 V's). The `a1` bias of their means over
/// 75-100 s: +0.02-0.03 %, +0.10-0.18 %, +0.03 %. With the default slew limit, which ramps the 8 V PRBS's steps (39 V^2
/// of power left, not 64), the same `q` does as well: 1.05-1.07 % with Q2, 0.54-0.55 % with it; `a1` +0.14-0.21 %,
/// +0.04-0.05 %. A multisine of 200-800 Hz: 0.39-0.40 % at 1 V, 0.88-0.90 % at 6 V, 0.35-0.36 % at 6 V with the note's
/// `q` (over 36). A trade: at 1 V with the 8 V PRBS's `q` the EKFs wander less (0.34-0.35 %) but relock in 1.3 s
/// instead of 0.3 s (the 1 V multisine with the 6 V one's: less wander, relock as fast). (`hal_sim::experiment`'s
/// PRBS in f64 and f32 alike: 0.59-0.61, 1.07-1.09, 0.55-0.57 %.)
#[test]
fn a_strong_excitation_with_the_papers_q_is_noted_and_its_advice_keeps_the_ekfs_as_at_1_v() {
    const STRONG: &str = "note: the EKFs' q is Q2, for the paper's PRBS of 1 V: at ";
    let noted = |lab: &mut Lab, cmd: &str| {
        let reply = lab.send(cmd);
        assert!(verdict(&reply).starts_with("ok"), "{cmd}: {reply}");
        notes(&reply).into_iter().find(|n| n.starts_with(STRONG))
    };
    let mut lab = Lab::new();
    assert!(verdict(&lab.send("limits -10 10 1000000\n")).starts_with("ok"));
    for (cmd, note) in [
        ("excite prbs 1\n", false),
        ("excite prbs 1.99\n", false),
        ("excite prbs 2\n", true),
        ("excite prbs 8 0.5\n", true),
        ("excite multisine 6 200 800\n", true),
        ("excite multisine 1.99 200 800\n", false),
        ("excite multisine 2 200 800\n", true),
        ("excite multisine 8 200 800\n", false),
        ("excite multisine 6 20 80\n", false),
        ("excite prbs 8 5\n", false),
        ("excite triangle 8 10\n", false),
        ("excite sine 8 100\n", false),
    ] {
        assert_eq!(noted(&mut lab, cmd).is_some(), note, "{cmd}");
    }
    // `tuning prbs` with a strong PRBS running says it too; `tuning triangle` (Q1) does not, nor `excite` then.
    noted(&mut lab, "excite prbs 8\n").expect("noted");
    assert!(noted(&mut lab, "tuning triangle\n").is_none() && noted(&mut lab, "excite prbs 8\n").is_none());
    let advice = noted(&mut lab, "tuning prbs\n").expect("noted after tuning prbs");
    assert!(advice.contains("at 8 V") && advice.ends_with("tune ekf q 1e-12 1e-6 2.34375e7 0.00390625 7.8125e6"));
    // Followed: the console takes the line, and with it `excite` notes nothing more.
    let tune = &advice[advice.find("tune ekf q").expect("a command")..];
    assert!(verdict(&lab.send(&format!("{tune}\n"))).starts_with("ok tune [ekf] q"), "{tune}");
    assert!(noted(&mut lab, "excite prbs 8\n").is_none());

    // What the note is about, on the firmware: the worst `b0` of both EKFs from 20 s on (but the second after the
    // payload comes off at 100 s), their `a1` mean over 75-100 s, and their relock: the time from the change after
    // which `a0` and `b0` stay within 1 % of the truth (as `paper` counts it).
    let run = |excite: &str, limits: &str, tune: Option<&str>| {
        let mut lab = Lab::new();
        assert!(verdict(&lab.send(limits)).starts_with("ok"));
        if let Some(t) = tune {
            assert!(verdict(&lab.send(&format!("{t}\n"))).starts_with("ok"));
        }
        assert!(verdict(&lab.send(&format!("excite {excite}\n"))).starts_with("ok"));
        let (mut worst, mut a1, mut relock) = ([0.0f64; 2], [0.0f64; 2], [0.0f64; 2]);
        for k in 1..=2000 {
            lab.run(1000);
            let t_s = k as f64 / 10.0;
            let truth = if t_s <= 100.0 { StageParams::PAYLOAD } else { StageParams::NO_PAYLOAD };
            for (j, (p, _)) in lab.isr.estimates()[1..3].iter().enumerate() {
                let e = errors(&truth, *p);
                if t_s >= 20.0 && !(100.0..110.0).contains(&t_s) {
                    worst[j] = worst[j].max(e[2].abs());
                }
                if t_s > 75.0 && t_s <= 100.0 {
                    a1[j] += e[1] / 250.0;
                }
                if t_s > 100.0 && (e[0].abs() >= 1e-2 || e[2].abs() >= 1e-2) {
                    relock[j] = t_s - 100.0 + 0.1;
                }
            }
        }
        let (limits, tune) = (limits.trim(), tune.unwrap_or("Q2"));
        println!(
            "{excite}, {limits}, {tune}: ekf, hekf worst b0 {worst:.5?}, a1 75-100 s {a1:+.5?}, relock {relock:.1?}"
        );
        (worst, a1, relock)
    };
    // The paper's PRBS against one of 8 V with the slew limit out of the way, and with the default one (25 000 V/s,
    // which ramps its steps of 16 V over 7 samples: 39 V^2 of power left, and the advice still right); a multisine.
    let (wide, default) = ("limits -10 10 1000000\n", "limits -10 10 25000\n");
    for (weak, strong, limits) in [
        ("prbs 1", "prbs 8", wide),
        ("prbs 1", "prbs 8", default),
        ("multisine 1 200 800", "multisine 6 200 800", wide),
    ] {
        let advice = noted(&mut Lab::new(), &format!("excite {strong}\n")).expect("noted");
        let tune = &advice[advice.find("tune ekf q").expect("a command")..];
        let (paper_worst, paper_a1, paper_relock) = run(weak, limits, None);
        let (strong_worst, strong_a1, _) = run(strong, limits, None);
        let (advised_worst, advised_a1, advised_relock) = run(strong, limits, Some(tune));
        for j in 0..2 {
            assert!(strong_worst[j] > 1.5 * paper_worst[j], "{strong} {j}: {strong_worst:?} against {paper_worst:?}");
            // The PRBS's `a1` reads high with it; the multisine's moves the other way, less.
            if strong.starts_with("prbs") {
                assert!(strong_a1[j] > 2.0 * paper_a1[j], "{strong} {j}: {strong_a1:?} against {paper_a1:?}");
            }
            assert!(advised_worst[j] < 1.1 * paper_worst[j], "{strong} {j}: {advised_worst:?} against {paper_worst:?}");
            // Within 0.025 % of a1: 0.007 % at most, but 0.018-0.021 % for the ramped PRBS, no scaled copy of the
            // paper's (its `a1` +0.21 / +0.14 % with Q2).
            assert!((advised_a1[j] - paper_a1[j]).abs() < 2.5e-4, "{strong} {j}: {advised_a1:?} against {paper_a1:?}");
            assert!(paper_relock[j] < 0.5 && advised_relock[j] < 0.5, "{strong} {j}: {advised_relock:?}");
        }
        // A trade, not a free gain: the 1 V PRBS with the 8 V one's `q` wanders less and relocks slower (the
        // multisine of 1 V with the 6 V one's wanders less and relocks as fast: Q2 is the PRBS's).
        let (slow_worst, _, slow_relock) = run(weak, limits, Some(tune));
        for j in 0..2 {
            assert!(slow_worst[j] < 0.8 * paper_worst[j], "{weak} {j}: {slow_worst:?} against {paper_worst:?}");
            if weak.starts_with("prbs") {
                assert!(slow_relock[j] > 1.0, "{weak} {j}: {slow_relock:?}");
            }
        }
    }
}

/// The telemetry's warnings: looked at every 0.1 s, the watch says how many numeric resets each estimator had
/// since the last look (the continuous EKF's, with `R` a million below the paper's, in nearly every look; nobody
/// else's), a new tuning (which restarts the estimators and their counts) is not taken for billions of resets, and
/// a deadline miss or an ADC overrun is told once, and an excitation the output limits clip at every look while it
/// lasts.
#[test]
fn the_telemetry_says_when_an_estimator_keeps_resetting() {
    let mut lab = Lab::new();
    let mut watch = EventWatch::new(1e4);
    let mut look = |lab: &mut Lab, samples: usize| {
        lab.run(samples);
        watch.look(&lab.isr.status())
    };
    lab.run(2000);
    assert_eq!(look(&mut lab, 1000), News::default(), "the paper's tuning");
    assert!(verdict(&lab.send("tune ekf r 1.5e-12\n")).starts_with("ok tune"));
    let news: Vec<News> = (0..50).map(|_| look(&mut lab, 1000)).collect();
    let warned = news.iter().filter(|n| n.resets[1] > 0).count();
    let total: u32 = news.iter().map(|n| n.resets[1]).sum();
    println!("R = 1.5e-12 um^2: the continuous EKF warned in {warned} of 50 looks, {total} resets");
    assert!(warned > 40, "{warned}");
    assert_eq!(total, lab.isr.status().estimates[1].1.numeric_resets, "every reset told once");
    assert!(news.iter().all(|n| n.resets[0] == 0 && n.resets[2] == 0 && n.resets[3] == 0 && n.deadline_misses == 0));
    assert!(verdict(&lab.send("tune ekf r 1.5e-6\n")).starts_with("ok tune"));
    assert_eq!(look(&mut lab, 1000), News::default(), "restarted counts are not news");
    // The board's faults, told once each.
    lab.board.inject_faults = Some(BoardFaults { deadline_missed: true, adc_overrun: true });
    let news = look(&mut lab, 10);
    assert_eq!((news.deadline_misses, news.adc_overruns, news.resets), (1, 1, [0; 4]));
    assert_eq!(look(&mut lab, 10), News::default());
    // An excitation the clamp clips (8 V + 3 V sin, above the DAC's reach of 8.78 V 41.6 % of the time): counted at
    // every look, and told from the second on; back within the limits, nothing more.
    lab.board.inject_faults = None;
    assert!(verdict(&lab.send("excite sine 3 100 8\n")).starts_with("ok"));
    let clipped: Vec<News> = (0..5).map(|_| look(&mut lab, 1000)).collect();
    assert!(clipped.iter().all(|n| (396..=436).contains(&n.limited)), "{clipped:?}");
    assert_eq!(clipped.iter().map(|n| n.limiting).collect::<Vec<_>>(), [false, true, true, true, true]);
    assert!(verdict(&lab.send("excite sine 3 100 5\n")).starts_with("ok"));
    lab.run(100);
    look(&mut lab, 0);
    assert_eq!(look(&mut lab, 1000), News::default());
    // A step of the command: `excite constant 5` from 0 V, 2.5 V a sample, counted once and not told.
    assert!(verdict(&lab.send("excite constant 0\n")).starts_with("ok"));
    look(&mut lab, 1000);
    look(&mut lab, 1000);
    assert!(verdict(&lab.send("excite constant 5\n")).starts_with("ok"));
    let step = [look(&mut lab, 1000), look(&mut lab, 1000)];
    assert_eq!(step.map(|n| (n.limited, n.limiting)), [(1, false), (0, false)]);
    let status = lab.send("status\n");
    assert!(verdict(&status).contains(&format!(" limited={} ", lab.isr.status().counters.limited)), "{status}");
}

/// The stage at 1 kHz of the tests on another stage: damping ratio 0.01, static gain 0.05 um/V (`w` = 2 pi 1 kHz).
const KHZ_STAGE: StageParams<f64> = StageParams { a0: KHZ_W * KHZ_W, a1: 0.02 * KHZ_W, b0: 0.05 * KHZ_W * KHZ_W };
const KHZ_W: f64 = 2.0 * std::f64::consts::PI * 1000.0;

/// Both EKFs within 0.1 % of [`KHZ_STAGE`] on `a0`, 10 % on `a1` (the continuous one's is about 5 % low at this
/// `w T`), 1 % on `b0`, 5 s after `what`.
fn ekfs_near_the_khz_stage(lab: &Lab, what: &str) {
    for ekf in [1, 2] {
        let e = errors(&KHZ_STAGE, lab.params(ekf));
        println!("{} 5 s after {what}: a0, a1, b0 {e:+.4?}", ESTIMATOR_NAMES[ekf]);
        assert!(e[0].abs() < 1e-3 && e[1].abs() < 0.1 && e[2].abs() < 0.01, "{}: {e:?}", ESTIMATOR_NAMES[ekf]);
    }
}

/// The relative errors `(a0, a1, b0)` of `p` against `stage`.
fn errors(stage: &StageParams<f64>, p: StageParams<f32>) -> [f64; 3] {
    [p.a0 as f64 / stage.a0 - 1.0, p.a1 as f64 / stage.a1 - 1.0, p.b0 as f64 / stage.b0 - 1.0]
}

/// A limit, kept measured: the EKFs are local. Started at the paper's initial parameters (390 Hz), on a stage at
/// 1 kHz they settle on a wrong solution (`b0` of the wrong sign) and stay there. The ARX, linear in its parameters,
/// finds the stage within 5 s with the pre-filter left at the paper's 450 Hz (`a0` within 0.03 %, `b0` 7 % high); the
/// estimators restarted from its estimate (`tune initial arx`), and the pre-filter (and so the replicas' match)
/// moved to its resonance, the EKFs land within 1 % on `b0` 5 s later: a stage found with no number typed but the
/// resonance `status` shows. With the replicas left matched at 450 Hz, `b0` was 6 % high in every estimator. The
/// continuous EKF's `a1` stays about 5 % low at this `w T` (0.63).
#[test]
fn the_ekfs_need_a_start_near_the_stage_and_the_arx_gives_one() {
    let stage = KHZ_STAGE;
    let err = |p: StageParams<f32>| errors(&stage, p);
    let mut lab = Lab::with_stage(Some(stage));
    lab.run(200_000);
    for ekf in [1, 2] {
        let e = err(lab.params(ekf));
        assert!(e[2] < -0.9, "{}: {e:?}", ESTIMATOR_NAMES[ekf]);
    }
    // `status` says they disagree with the ARX, between the estimators' lines and its own, and what to do; the notes
    // on an excitation's band judge it by the ARX's resonance, not by the hybrid EKF's 360 Hz (within 200-600 Hz:
    // no note).
    let status = lab.send("status\n");
    let lines: Vec<&str> = status.lines().collect();
    assert!(lines.len() == 6 && lines[..4].iter().all(|l| l.starts_with("est ")), "{status}");
    assert_eq!(lines[4], DISAGREEMENT_NOTE, "{status}");
    assert!(lines[5].starts_with("ok status "), "{status}");
    let r = lab.send("excite multisine 1 200 600\n");
    let f0 = notes(&r).iter().find_map(|n| {
        let rest = n.split_once("misses the resonance (")?.1;
        rest.split_once(" Hz, arx's estimate)")?.0.parse::<f64>().ok()
    });
    assert!(f0.is_some_and(|f| (f / 1000.0 - 1.0).abs() < 0.01), "{r}");
    let mut lab = Lab::with_stage(Some(stage));
    lab.run(50_000);
    let arx = lab.params(3);
    println!("arx 5 s after the start, the pre-filter at 450 Hz: a0, a1, b0 {:+.4?}", err(arx));
    assert!(err(arx)[0].abs() < 1e-3 && err(arx).iter().all(|e| e.abs() < 0.1), "arx: {:?}", err(arx));
    // The ARX's estimate as the sample before the command left it, taken as every estimator's initial parameters;
    // the note says the pre-filter is far from it.
    let r = lab.send("tune initial arx\n");
    let seed = [arx.b0, arx.a1, arx.a0].map(|x| Num(x as f64, 6).to_string()).join(" ");
    assert_eq!(verdict(&r), format!("ok tune initial = {seed} (arx's estimate; estimators restarted)"), "{r}");
    assert!(notes(&r).len() == 1 && notes(&r)[0].starts_with("note: the pre-filter's f_p (450 Hz) is 0.45"), "{r}");
    assert_eq!(verdict(&lab.send("tune initial\n")), format!("ok tune initial = {seed}"));
    assert!(lab.send("status\n").contains("+tune "));
    // The pre-filter to the resonance the ARX found, as `status` shows it.
    let f0 = Num(arx.f0_hz() as f64, 6).to_string();
    let r = lab.send(&format!("tune prefilter 100 {f0} 0.1\n"));
    assert!(notes(&r).is_empty() && verdict(&r).starts_with("ok tune prefilter"), "{r}");
    lab.run(50_000);
    ekfs_near_the_khz_stage(&lab, "its seed from the arx");
    // They agree; the note now is of the continuous EKF's `a1` at this `w T` (0.63).
    let status = lab.send("status\n");
    assert!(!status.contains(" disagree ") && status.contains("\nnote: the resonance, "), "{status}");
    assert_eq!(lab.isr.config(), &lab.ctl.config(), "what the console designed is what runs");
    let s = lab.ctl.settings();
    let f0: f64 = f0.parse().unwrap();
    assert_eq!([s.reconstruction.prewarp_hz, s.antialias.prewarp_hz, s.lags.match_hz], [f0; 3]);
}

/// `status`'s note on the 1 kHz stage, where the EKFs settled on a wrong solution.
const DISAGREEMENT_NOTE: &str = "note: ekf,hekf disagree with arx on the resonance (more than 1.25 times apart) or \
                                 the gain's sign: the EKFs are local and, started far from the stage, settle on a \
                                 wrong solution; the arx cannot, but converges more slowly. Once its estimate \
                                 holds, start the EKFs there: tune stage arx";

/// A run of the firmware on the simulated board: what, the stage (`None`: the paper's), the commands sent at the
/// start, seconds.
type Run<'a> = (&'a str, Option<StageParams<f64>>, &'a [&'a str], usize);

/// The console's commands for the paper's smoothed triangle with its tuning.
const TRIANGLE: &[&str] = &["tuning triangle\n", "excite triangle 1 10\n"];

/// A lab on `stage` (the paper's if `None`) with `commands` sent, each answered `ok`.
fn lab_with(stage: Option<StageParams<f64>>, commands: &[&str]) -> Lab {
    let mut lab = Lab::with_stage(stage);
    for c in commands {
        assert!(verdict(&lab.send(c)).starts_with("ok"), "{c}");
    }
    lab
}

/// A disconnected probe: a stage of zero gain, the ADC reading the divider's mid-scale and the noise.
const DISCONNECTED: StageParams<f64> = StageParams { b0: 0.0, a1: 77.6, a0: 7.06e6 };

/// A 200 Hz stage, damping 0.01, gain 0.1 um/V.
const STAGE_200_HZ: StageParams<f64> = {
    let w = 2.0 * std::f64::consts::PI * 200.0;
    StageParams { a0: w * w, a1: 0.02 * w, b0: 0.1 * w * w }
};

/// The EKFs' disagreement with the estimators linear in their parameters ([`disagreement`]), looked at every 0.1 s
/// as the telemetry does: never on the paper's stage (PRBS and triangle over the whole experiment, through the
/// payload's removal and the RLS's 13 s to follow it; a 50 mV PRBS, at which the ARX takes 35-58 s; a multisine),
/// nor, told, on it wired the other way round (with the triangle the estimators disagree for up to 0.9 s while the
/// ARX's gain crosses zero). On the 1 kHz stage, told once, 2 s after the start; on a stage at 200 Hz, which the
/// EKFs take about 20 s to find, told once and over by 30 s. Measured: the resonances of the RLS and the ARX against
/// the EKFs' stay within 1.14 times on the paper's runs (1.25 is the bound).
#[test]
fn the_ekfs_disagreement_is_told_on_another_stage_and_never_on_the_papers() {
    let inverted = StageParams { b0: -8.08e5, a1: 77.6, a0: 7.06e6 };
    let triangle = TRIANGLE;
    // Whether it disagrees at any look; whether the watch told it, when.
    let runs: [Run; 8] = [
        ("paper prbs", None, &[], 200),
        ("paper triangle", None, triangle, 200),
        ("paper prbs 50 mV", None, &["excite prbs 0.05\n"], 60),
        ("paper multisine", None, &["excite multisine 1 200 800\n"], 60),
        ("inverted prbs", Some(inverted), &[], 20),
        ("inverted triangle", Some(inverted), triangle, 20),
        ("1 kHz", Some(KHZ_STAGE), &[], 20),
        ("200 Hz", Some(STAGE_200_HZ), &[], 40),
    ];
    for (what, stage, commands, seconds) in runs {
        let mut lab = lab_with(stage, commands);
        let (mut watch, mut told, mut last, mut weak) = (EventWatch::new(1e4), vec![], None, vec![]);
        for look in 1..=seconds * 10 {
            lab.run(1000);
            let status = lab.isr.status();
            if disagreement(&status).is_some() {
                last = Some(look);
            }
            let news = watch.look(&status);
            if let Some(d) = news.disagreement {
                told.push((look, d.ekf_names()));
            }
            weak.extend(news.weak_response.map(|r| (look, r.ratio)));
        }
        println!("{what}: last disagreeing at look {last:?}, told {told:?}, weak response told {weak:?}");
        // The EKFs' model explains the measurement on every stage here, the probe connected.
        assert!(weak.is_empty(), "{what}: {weak:?}");
        match what {
            "inverted prbs" | "inverted triangle" => assert!(told.is_empty(), "{what}: {told:?}"),
            "1 kHz" => assert_eq!(told, [(20, "ekf,hekf")], "{what}"),
            "200 Hz" => assert!(told.len() == 1 && last.is_some_and(|l| l < 300), "{what}: {told:?} {last:?}"),
            _ => assert_eq!((last, told.len()), (None, 0), "{what}"),
        }
    }
}

/// `tune stage arx`: the flow of the test above in one command and one restart, the initial parameters from the
/// ARX's estimate and the pre-filter's centre at its resonance (`f_lc`, `zeta_p` kept); 5 s later the EKFs are as
/// close (measured: ekf a0/a1/b0 -0.04 / -5.2 / +0.63 %, hekf -0.00 / +0.61 / +0.40 %).
#[test]
fn tune_stage_takes_the_initial_parameters_and_the_prefilter_from_an_estimate() {
    let mut lab = Lab::with_stage(Some(KHZ_STAGE));
    lab.run(50_000);
    let arx = lab.params(3);
    let r = lab.send("tune stage arx\n");
    let seed = [arx.b0, arx.a1, arx.a0].map(|x| Num(x as f64, 6).to_string()).join(" ");
    let f0 = Num(StageParams { b0: arx.b0 as f64, a1: arx.a1 as f64, a0: arx.a0 as f64 }.f0_hz(), 6);
    let reply =
        format!("ok tune stage = initial {seed}, prefilter 100 {f0} 0.1 (arx's estimate; estimators restarted)");
    assert!(notes(&r).is_empty() && verdict(&r) == reply, "{r}");
    assert_eq!(verdict(&lab.send("tune prefilter\n")), format!("ok tune prefilter = 100 {f0} 0.1"));
    // Refused as `tune initial arx` is: the ARX restarted from the estimate it gave.
    let r = lab.send("tune stage arx\n");
    assert_eq!(verdict(&r), "error: arx's estimate is its initial parameters: let it find the stage first (status)");
    lab.run(50_000);
    ekfs_near_the_khz_stage(&lab, "tune stage arx");
    assert_eq!(
        verdict(&lab.send("select hekf\ntune stage arx\n")),
        "error: arx is not running: select it, and let it find the stage, first"
    );
    // After `tune initial arx` the ARX's estimate is its initial parameters too, but the pre-filter is still the
    // paper's: the refusal gives the command that centres it on them, which does what `tune stage` would have.
    let mut lab = Lab::with_stage(Some(KHZ_STAGE));
    lab.run(50_000);
    assert!(verdict(&lab.send("tune initial arx\n")).starts_with("ok tune initial = "));
    let r = lab.send("tune stage arx\n");
    let (refusal, command) = verdict(&r).split_once(", or centre the pre-filter on them: ").unwrap_or(("", ""));
    assert_eq!(refusal, "error: arx's estimate is its initial parameters: let it find the stage first (status)");
    // The resonance of the initial parameters in use (`ok tune initial = B0 A1 A0`).
    let initial: Vec<f64> = verdict(&lab.send("tune initial\n")).split(' ').filter_map(|w| w.parse().ok()).collect();
    let f0 = Num(StageParams { b0: initial[0], a1: initial[1], a0: initial[2] }.f0_hz(), 6);
    assert_eq!(command, format!("tune prefilter 100 {f0} 0.1"), "{r}");
    let r = lab.send(&format!("{command}\n"));
    // The EKFs, restarted from the ARX's estimate just before, run on through the pre-filter's change.
    assert_eq!(verdict(&r), format!("ok tune prefilter = 100 {f0} 0.1 (rls restarted; ekf,hekf,arx kept)"));
    lab.run(50_000);
    ekfs_near_the_khz_stage(&lab, "tune initial arx, then the refusal's tune prefilter");
}

/// `tune initial ESTIMATOR` takes an estimate only from an estimator that runs, and only one that can start the
/// estimators: the paper's stage wired the other way round (`b0` negative), which the hybrid EKF finds within a
/// second, cannot (`tune initial` takes positive values); nor can an estimate that is still the initial parameters,
/// nor one held: the ARX's on a stage at 1 kHz for its first 2.1 s, while its discrete model has no continuous
/// equivalent and it reports the last that had, its initial parameters (`status` says `held`; nor do the notes on
/// an excitation's band take it for the resonance). A refusal names the estimator and the value, and changes
/// nothing.
#[test]
fn tune_initial_from_an_estimator_refuses_what_cannot_start_the_estimators() {
    let mut lab = Lab::with_stage(Some(KHZ_STAGE));
    let arx_line =
        |lab: &mut Lab| lab.send("status\n").lines().find(|l| l.starts_with("est arx ")).unwrap().to_string();
    assert_eq!(
        verdict(&lab.send("tune initial arx\n")),
        "error: arx's estimate is its initial parameters: let it find the stage first (status)"
    );
    lab.run(10_000);
    assert!(arx_line(&mut lab).contains(" a0=6e6 a1=70 b0=500000 ") && arx_line(&mut lab).contains(" held "));
    assert_eq!(
        verdict(&lab.send("tune initial arx\n")),
        "error: arx's estimate is held (its model has no continuous equivalent now): let it find the stage first \
         (status)"
    );
    assert!(!lab.send("status\n").contains("+tune"), "not tuned");
    // Nor is a held estimate the resonance a note judges an excitation's band by: with the ARX alone, the initial
    // parameters' (390 Hz) are, and the note says they are.
    lab.send("select arx\n");
    let r = lab.send("excite multisine 1 600 1000\n");
    assert!(notes(&r).iter().any(|n| n.contains("misses the resonance (389.8 Hz, tune initial)")), "{r}");
    lab.send("excite prbs 1\n");
    lab.run(20_000);
    assert!(arx_line(&mut lab).contains(" adapting "), "{}", arx_line(&mut lab));
    let r = lab.send("excite multisine 1 200 800\n");
    let f0 = notes(&r).iter().find_map(|n| {
        let rest = n.split_once("misses the resonance (")?.1;
        rest.split_once(" Hz, arx's estimate)")?.0.parse::<f64>().ok()
    });
    assert!(f0.is_some_and(|f| (f / 1000.0 - 1.0).abs() < 0.01), "{r}");

    let mut lab = Lab::with_stage(Some(StageParams { b0: -8.08e5, a1: 77.6, a0: 7.06e6 }));
    lab.run(10_000);
    let hekf = lab.params(2).b0;
    assert!((hekf as f64 / -8.08e5 - 1.0).abs() < 0.1, "{hekf}");
    let r = lab.send("tune initial hekf\n");
    let refusal = format!("error: hekf's estimate has b0 = {}: must be a positive number", Num(hekf as f64, 6));
    assert_eq!(verdict(&r), refusal, "{r}");
    assert_eq!(verdict(&lab.send("select ekf,hekf\n")), "ok select ekf,hekf");
    assert_eq!(
        verdict(&lab.send("tune initial arx\n")),
        "error: arx is not running: select it, and let it find the stage, first"
    );
    assert_eq!(verdict(&lab.send("tune initial\n")), "ok tune initial = 500000 70 6e6", "unchanged");
    assert!(lab.send("status\n").contains("tuning=prbs "), "not tuned");
}

/// An estimate is "still the initial parameters" only when all three are: a stage whose gain (or stiffness) the
/// initial parameters had right, with the rest moved, is taken (a status made by hand, the hybrid EKF's estimate set
/// to each such case, as the console's `execute` is given it).
#[test]
fn tune_initial_from_an_estimator_takes_an_estimate_with_some_parameters_at_their_initial_values() {
    let initial = |lab: &mut Lab| {
        let r = lab.send("tune initial\n");
        let v: Vec<f64> = verdict(&r).split_once("= ").unwrap().1.split(' ').map(|x| x.parse().unwrap()).collect();
        StageParams { b0: v[0] as f32, a1: v[1] as f32, a0: v[2] as f32 }
    };
    let mut lab = Lab::new();
    lab.run(100);
    let init = initial(&mut lab);
    let moved = StageParams { b0: 1.125 * init.b0, a1: 1.5 * init.a1, a0: 1.25 * init.a0 }; // exact in f32
    let cases = [
        StageParams { b0: init.b0, ..moved },
        StageParams { a1: init.a1, ..moved },
        StageParams { a0: init.a0, ..moved },
        StageParams { b0: init.b0, a0: init.a0, ..moved },
    ];
    // `tune initial hekf` on a fresh lab whose status has the hybrid EKF's estimate `p`, adapting: whether it was
    // taken, the reply, and the lab after it.
    let seed = |p: StageParams<f32>| {
        let mut lab = Lab::new();
        lab.run(100);
        let mut st = lab.isr.status();
        st.estimates[2] = (p, nanopos_id::estimator::Health::new());
        let mut reply = TextBuf::<REPLY_BYTES>::default();
        let (change, _) = lab.ctl.execute(nanopos_id::control::parse(b"tune initial hekf").unwrap(), || st, &mut reply);
        (change.is_some(), reply.as_str().to_string(), lab)
    };
    for p in cases {
        let (taken, reply, mut lab) = seed(p);
        assert!(taken, "{p:?}: {reply}");
        assert_eq!(initial(&mut lab), p, "{reply}");
    }
    // All three at their initial values: refused.
    let (taken, reply, _) = seed(init);
    assert!(!taken && reply.contains("estimate is its initial parameters"), "{reply}");
}

/// The pre-filter's centre far from the stage's resonance biases the estimates, and `tune` says so. On the stage at
/// 1 kHz of the test above, the estimators started near it (`tune initial`) but the pre-filter left at the paper's
/// 450 Hz: 5 s later `b0` is more than 5 % off in every estimator (measured 5.3 / 7.6 / 7.4 / 7.0 % for rls, ekf,
/// hekf, arx); 5 s after the pre-filter moved to the stage the EKFs are within 1 % (0.65 / 0.41 %). The RLS and the
/// ARX stay 3-5 % off there (2.8 / 3.7 %; 4.6 / 3.7 % after 20 s): at this `w T` (0.63) they have biases of their
/// own. `tune initial` notes the mismatch against the new initial parameters, `tune prefilter` against the hybrid
/// EKF's estimate (taken before the restart); neither once it is gone.
#[test]
fn a_prefilter_far_from_the_resonance_biases_the_estimates_and_is_noted() {
    let stage = KHZ_STAGE;
    let b0_errors = |lab: &Lab| (0..4).map(|i| (lab.params(i).b0 as f64 / stage.b0 - 1.0).abs()).collect::<Vec<_>>();
    let mut lab = Lab::with_stage(Some(stage));
    let r = lab.send(&format!("tune initial {} {} {}\n", 1.02 * stage.b0, 1.1 * stage.a1, 0.99 * stage.a0));
    assert_eq!(
        notes(&r),
        [format!("note: the pre-filter's f_p (450 Hz) is 0.452 times the resonance (995 Hz, tune initial){FAR}")],
        "{r}"
    );
    lab.run(50_000);
    let far = b0_errors(&lab);
    let r = lab.send("tune prefilter 100 1000 0.1\n");
    assert!(notes(&r).is_empty() && verdict(&r).starts_with("ok tune prefilter"), "{r}");
    lab.run(50_000);
    let near = b0_errors(&lab);
    println!(
        "b0 errors of rls, ekf, hekf, arx 5 s after the start: pre-filter at 450 Hz {far:.4?}, at 1 kHz {near:.4?}"
    );
    assert!(far.iter().all(|&e| e > 0.05) && near[1] < 0.01 && near[2] < 0.01, "{far:?} {near:?}");
    // Against the hybrid EKF's estimate (the stage's, here), taken before the restart.
    let r = lab.send("tune prefilter 100 2500 0.1\n");
    let note = notes(&r);
    let f0 = note.first().and_then(|n| {
        let rest = n.strip_prefix("note: the pre-filter's f_p (2500 Hz) is 2.5 times the resonance (")?;
        rest.strip_suffix(&format!(" Hz, hekf's estimate){FAR}"))?.parse::<f64>().ok()
    });
    assert!(note.len() == 1 && f0.is_some_and(|f| (f / 1000.0 - 1.0).abs() < 0.01), "{r}");
    assert!(verdict(&r).starts_with("ok tune prefilter"), "{r}");
}

/// How the notes of `tune` on the pre-filter and the resonance end.
const FAR: &str =
    ": the estimates can come out biased by several %; keep f_p near the stage's resonance (tune prefilter) \
                   and the initial parameters near the stage (tune initial)";

#[test]
fn a_multisine_about_the_resonance_identifies_the_stage_like_the_prbs() {
    // Both from the start, the payload on; means over 10-20 s of each estimator, against the truth.
    let run = |command: &str| {
        let mut lab = Lab::new();
        let reply = lab.send(command);
        let (_, rel) = lab.run_measuring();
        (lab, reply, rel)
    };
    let (_, _, prbs) = run("excite prbs 1\n");
    let (mut lab, reply, multisine) = run("excite multisine 1 200 800\n");
    assert_eq!(verdict(&reply), "ok excite multisine 1 V 200 to 800 Hz (running)");
    assert!(lab.send("status\n").contains(" excitation=multisine 1 V 200 to 800 Hz running "));
    let held = lab.isr.estimates().map(|(_, h)| h.adaptation);
    assert!(held.iter().all(|&a| a == Adaptation::Adapting), "{held:?}");
    for (i, name) in ESTIMATOR_NAMES.iter().enumerate() {
        println!(
            "{name:4} prbs      a0 {:+.4}% a1 {:+.4}% b0 {:+.4}%",
            prbs[i][0] * 1e2,
            prbs[i][1] * 1e2,
            prbs[i][2] * 1e2
        );
        let m = multisine[i];
        println!("{name:4} multisine a0 {:+.4}% a1 {:+.4}% b0 {:+.4}%", m[0] * 1e2, m[1] * 1e2, m[2] * 1e2);
    }
    // The EKFs meet the PRBS goals (0.1 % on a0 and b0, 1 % on a1; measured within 0.011 % and 0.11 %), the ARX is
    // within 0.3 %, and the continuous-time RLS, still on its way after 20 s with either input (it takes about 13 s
    // to relock), within 4 % with both (measured 3.3 % and 3.5 % on b0).
    for ekf in [1, 2] {
        let m = multisine[ekf];
        assert!(m[0].abs() < 1e-3 && m[2].abs() < 1e-3 && m[1].abs() < 1e-2, "{}: {m:?}", ESTIMATOR_NAMES[ekf]);
    }
    assert!(multisine[3].iter().all(|e| e.abs() < 3e-3), "arx: {:?}", multisine[3]);
    assert!([multisine[0], prbs[0]].iter().flatten().all(|e| e.abs() < 0.04), "rls: {:?}, {:?}", multisine[0], prbs[0]);
}

#[test]
fn deadline_misses_and_overruns_are_counted_and_reported() {
    let mut lab = Lab::new();
    lab.run(10);
    lab.board.inject_faults = Some(BoardFaults { deadline_missed: true, adc_overrun: false });
    lab.sample();
    lab.board.inject_faults = Some(BoardFaults { deadline_missed: true, adc_overrun: true });
    lab.sample();
    let s = lab.send("status\n");
    // The interrupt's cycles are the board's to count: none on the simulated one.
    assert!(s.contains("deadline_misses=2 adc_overruns=1 isr_cycles_max=- "), "{s}");
    // Reported, not a reason to stop: the excitation runs on.
    assert!(s.contains("faults=none"), "{s}");
}

/// A missed deadline skips a code: the DAC holds the one before it for a second period, and the next code follows
/// the skipped one's. The slew limiter steps from the code the DAC holds, so that the output never moves by more
/// than the slew limit (and the DAC's rounding) from one period to the next, one miss or two in a row, in the middle
/// of the PRBS's ramps at 1 000 V/s. It moved by twice the limit before (found by the random session).
#[test]
fn a_missed_deadline_does_not_make_the_output_jump_past_the_slew_limit() {
    for misses in [&[40usize][..], &[40, 41], &[40, 42], &[7, 19, 33, 34, 61]] {
        let mut lab = Lab::new();
        assert!(verdict(&lab.send("limits -5 5 1000\n")).starts_with("ok limits"));
        assert!(verdict(&lab.send("excite prbs 4\n")).starts_with("ok excite"));
        let (step, lsb) = (lab.isr.config().max_step_v as f64, lab.isr.config().command_lsb_v);
        let bound = step + 2.0 * lsb + 1e-9;
        let (mut last, mut worst, mut ramping) = (lab.board.last_u_v(), 0.0f64, 0);
        for k in 0..2_000 {
            if misses.contains(&(k % 100)) {
                lab.board.inject_faults = Some(BoardFaults { deadline_missed: true, adc_overrun: false });
            }
            lab.sample();
            let u = lab.board.last_u_v();
            worst = worst.max((u - last).abs());
            ramping += ((u - last).abs() > 0.5 * step) as usize;
            last = u;
        }
        assert!(ramping > 200, "{misses:?}: the misses fell in ramps ({ramping} samples stepping)");
        assert!(worst <= bound, "{misses:?}: the output moved {worst} V in a period, the limit {bound} V");
        assert!(lab.send("status\n").contains(&format!("deadline_misses={} ", 20 * misses.len())));
    }
}

#[test]
fn the_watchdog_is_fed_only_while_the_sample_clock_runs() {
    // Asked every 100 ms: 1000 samples at 10 kHz; half of that suffices.
    let mut gate = WatchdogGate::new(500);
    let mut lab = Lab::new();
    let mut fed = 0;
    for _ in 0..5 {
        lab.run(1000);
        fed += gate.may_feed(lab.isr.status().samples) as u32;
    }
    assert_eq!(fed, 5);
    // The sample clock stops (the interrupt no longer runs): no more feeding, so the watchdog resets the board.
    assert!(!gate.may_feed(lab.isr.status().samples));
    assert!(!gate.may_feed(lab.isr.status().samples));
    // A clock running at a tenth of its rate is not enough either.
    lab.run(100);
    assert!(!gate.may_feed(lab.isr.status().samples));
    lab.run(1000);
    assert!(gate.may_feed(lab.isr.status().samples));
}

/// The recording's stream carries 16-bit codes: a board whose ADC gives more (the simulated ADC summing 256
/// conversions without a shift: 20 bits, largest code 1 048 320) is refused `record`, with the reason; the G474's
/// 64x / 4 (16 bits, largest code 65 520) records. So for the amplifier's DAC.
#[test]
fn record_refuses_codes_wider_than_its_stream() {
    let mut lab = Lab::with_board(|board| {
        (board.adc.oversampling, board.adc.shift) = (256, 0);
        assert_eq!((board.adc.format().bits, board.adc.format().max_code), (20, 1_048_320));
    });
    for line in ["record on\n", "record burst 10\n"] {
        let reply = lab.send(line);
        assert_eq!(reply, "error: record: the v1 stream carries 16-bit codes; this board's are wider\n", "{line}");
    }
    let reply = Lab::new().send("record burst 10\n");
    assert!(reply.starts_with("# nanopos-record v2 ") && reply.ends_with("ok record burst 10\n"), "{reply}");
    // The amplifier's DAC too: 16 bits (largest code 65 535, the stream's own) record, 17 do not.
    for (bits, records) in [(16, true), (17, false)] {
        let reply = Lab::with_board(|board| board.dac.bits = bits).send("record burst 10\n");
        assert_eq!(reply.ends_with("ok record burst 10\n"), records, "{bits} bits: {reply}");
    }
}

#[test]
fn a_recording_carries_exactly_what_the_interrupt_saw() {
    let mut lab = Lab::new();
    lab.run(777);
    let start = lab.link.len();
    lab.send("record burst 3000\n");
    let mut link = lab.link[start..].to_string();
    assert!(link.starts_with("# nanopos-record v2 rate_hz=10000 delay=1 u_v_per_code=0.0048828125 u_v_offset=-10 y_um_per_code=0.00152587890625 y_um_offset=-50 crc=29b1\n"), "{link}");
    // Then the tuning the estimators run, a line per key.
    let (reply, tuning) = link.split_once("ok record burst 3000\n").unwrap();
    assert!(reply.ends_with(" crc=29b1\n"), "{reply}");
    let lines: Vec<_> = tuning.lines().map(|l| nanopos_id::record::read_tuning_line(l).unwrap()).collect();
    assert_eq!(lines.iter().map(|l| l.key).collect::<Vec<_>>(), nanopos_id::estimators::TuningKey::ALL);
    // In effect from the recording's first sample, the 778th.
    assert!(lines.iter().all(|l| l.at == 777), "{tuning}");
    // 15 ms of the link at 921 600 baud before the first frame, inside the board's 0.1 s buffer (src/record.rs).
    assert_eq!(tuning.len(), 1408);
    // `send` ran the sample that applied the change: the first recorded sample is that one.
    let first_index = lab.isr.status().samples - 1;
    let mut outputs = Vec::new();
    for k in 0..4000 {
        let out = lab.sample();
        outputs.push(out);
        if k % 10 == 0 {
            link.push_str(&lab.drain_recording());
        }
    }
    // The burst ended long ago: its last frames and end line went out, and nothing is left.
    assert!(link.ends_with("# nanopos-record end samples=3000 overflow=0 crc=8f53\n"), "{link}");
    assert_eq!(lab.drain_recording(), "");
    let st = lab.isr.record_status();
    assert!(!st.active && !st.overflowed && st.recorded == 3000 && st.buffered == 0, "{st:?}");

    // Decode: contiguous frames from the sample the change applied on; y is each sample's probe code, u the code
    // in effect over its period (the board's delay of one sample: the code written one sample earlier).
    let mut decoded = Vec::new();
    let mut expect_index = first_index;
    for line in link.lines().filter(|l| l.starts_with('R')) {
        let mut out = [RawSample::default(); FRAME_SAMPLES];
        let (index, n) = decode_frame(line.as_bytes(), &mut out).unwrap();
        assert_eq!(index, expect_index);
        expect_index += n as u64;
        decoded.extend_from_slice(&out[..n]);
    }
    assert_eq!(decoded.len(), 3000);
    // Sample 0 of the recording was the `send`'s sample; compare from the next one, whose outputs we kept.
    for (k, s) in decoded.iter().enumerate().skip(1) {
        let out = &outputs[k - 1];
        assert_eq!(s.y_code as u32, out.probe_code, "{k}");
        assert_eq!(lab.isr.config().command_of_code(s.u_code as u32), out.u_v, "{k}");
    }
}

#[test]
fn the_interrupt_adds_the_excitation_to_a_command_of_its_own_and_records_the_sum() {
    // The PRBS (1 V) added to a command of 2 V: the output is the sum, clamped as any, and the recording stores it
    // as the DAC output it. (That the sum is the excitation about an offset, code for code: `tests/pipeline.rs`.)
    let mut lab = Lab::new();
    let mut link = lab.send("record burst 2000\n");
    let mut outputs = Vec::new();
    for k in 0..3000 {
        let mut seen = f32::NAN;
        let out = lab.isr.sample_adding(&mut lab.board, |y_um| {
            seen = y_um;
            2.0
        });
        assert_eq!(seen, out.y_um, "the command is given this sample's reading");
        outputs.push(out);
        if k % 10 == 0 {
            link.push_str(&lab.drain_recording());
        }
    }
    assert!(link.lines().last().unwrap().starts_with("# nanopos-record end samples=2000 overflow=0 crc="), "{link}");
    let cfg = lab.isr.config();
    let u: Vec<f32> = recorded_samples(&link).iter().map(|s| cfg.command_of_code(s.u_code as u32)).collect();
    assert_eq!(u.len(), 2000);
    // Recorded sample k + 1 is the period of output k (the first was the `send`'s sample).
    for (k, v) in u.iter().enumerate().skip(1) {
        assert_eq!(*v, outputs[k - 1].u_v, "{k}");
    }
    let (lo, hi) = u[10..].iter().fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    assert!((lo - 1.0).abs() < 0.005 && (hi - 3.0).abs() < 0.005, "{lo} {hi}");
    assert!(verdict(&lab.send("limits -10 2.5 25000\n")).starts_with("ok limits"));
    let out = (0..1000).map(|_| lab.isr.sample_adding(&mut lab.board, |_| 2.0)).collect::<Vec<_>>();
    assert!(out.iter().all(|o| o.u_v <= 2.5 + 0.0025) && out.iter().any(|o| o.u_v > 2.49));
}

/// While it records, the console sends a frame as soon as it is whole, and only whole frames (`Lab::drain_recording`
/// as the firmware's console task).
#[test]
fn a_recording_goes_out_a_whole_frame_at_a_time() {
    let mut lab = Lab::new();
    assert!(verdict(&lab.send("record burst 3000\n")).starts_with("ok record burst 3000"));
    let mut sizes = Vec::new();
    for _ in 0..2_000 {
        lab.sample();
        for line in lab.drain_recording().lines() {
            let mut out = [RawSample::default(); FRAME_SAMPLES];
            sizes.push(decode_frame(line.as_bytes(), &mut out).unwrap_or_else(|e| panic!("{e:?}: {line}")).1);
        }
        let st = lab.isr.record_status();
        assert!(st.active && st.buffered < FRAME_SAMPLES, "{st:?}");
    }
    assert!(sizes.iter().all(|&n| n == FRAME_SAMPLES), "{sizes:?}");
    // The `send`'s sample and the 2 000 after it.
    assert_eq!(sizes.len() * FRAME_SAMPLES + lab.isr.record_status().buffered, 2_001);
    // A line while it records leaves the frames to the console task: the link gets the reply alone.
    lab.run(100);
    let at = lab.link.len();
    assert!(verdict(&lab.send("status\n")).starts_with("ok status"));
    assert!(!lab.link[at..].lines().any(|l| l.starts_with('R')), "{}", &lab.link[at..]);
    assert!(lab.isr.record_status().buffered >= 100);
}

/// The samples of every frame on `link`, in order (each frame intact).
fn recorded_samples(link: &str) -> Vec<RawSample> {
    let mut samples = Vec::new();
    let mut out = [RawSample::default(); FRAME_SAMPLES];
    for line in link.lines().filter(|l| l.starts_with('R')) {
        let (_, n) = decode_frame(line.as_bytes(), &mut out).unwrap();
        samples.extend_from_slice(&out[..n]);
    }
    samples
}

/// A recording is closed by its end line before another may start: `record on` or `record burst` while one runs, or
/// while its end line is still to come (`record off` and a new one in the same batch of bytes, before the console
/// drained the ring), is refused. Taken, the new recording cleared the ring: the old one's last samples were lost,
/// and its end line never came (a header inside a recording; found by the random session).
#[test]
fn a_recording_is_closed_before_another_starts() {
    let refused = "error: record: a recording runs (or its end line has not gone out): record off first";
    // The frames as the console task writes them after each batch of lines, on the link after the replies.
    let drain = |lab: &mut Lab| {
        let frames = lab.drain_recording();
        lab.link.push_str(&frames);
    };
    for second in ["record on", "record burst 5"] {
        let mut lab = Lab::new();
        let start = lab.link.len();
        assert!(verdict(&lab.send("record on\n")).starts_with("ok record on"));
        lab.run(150);
        drain(&mut lab);
        // While it runs: refused, and the recording goes on.
        assert_eq!(verdict(&lab.send(&format!("{second}\n"))), refused);
        assert!(lab.isr.record_status().active);
        lab.run(150);
        // Stopped in the same batch: the stopped one's last frames and end line go out before the next line
        // executes, which starts the new one.
        let at = lab.link.len();
        let reply = lab.send(&format!("record off\n{second}\n"));
        assert!(reply.contains("ok record off\n") && verdict(&reply).starts_with("ok record"), "{reply}");
        let sent = &lab.link[at..];
        let end = sent.find("# nanopos-record end samples=301 ").expect("the first recording's end line");
        assert!(end > sent.find("ok record off\n").unwrap() && end < sent.find(HEADER_TAG).unwrap(), "{sent}");
        lab.run(300);
        // A burst that ended by itself, its end line not yet out: the next line's `record` starts another.
        lab.send("record off\n");
        assert_eq!(verdict(&lab.send("record burst 5\n")), "ok record burst 5");
        lab.run(20);
        assert_eq!(verdict(&lab.send("record burst 7\n")), "ok record burst 7");
        lab.run(20);
        drain(&mut lab);
        let mut watch = RecordWatch::default();
        watch.feed(&lab.link[start..], String::new);
        assert_eq!(watch.ended, 4, "{second}");
        let second_len = if second == "record on" { 301 } else { 5 };
        assert_eq!(watch.samples, 301 + second_len + 5 + 7, "{second}");
    }
}

/// Random batches of lines, one to four a batch as a pasted script arrives, among them `record off`, `record on` and
/// short bursts, with up to 0.01 s of samples between batches: every line answered once, a recording asked for right
/// after a `record off` in the same batch taken (the stopped one ends first), and every recording in the stream whole.
#[test]
fn recording_commands_pasted_in_batches_keep_the_stream_whole() {
    let mut lab = Lab::new();
    let mut next = nanopos_id::xorshift64(0x5EED_BA7C);
    let words = [
        "record on",
        "record off",
        "record burst 1",
        "record burst 7",
        "record burst 60",
        "status",
        "excite prbs 1",
        "tune ekf r 2e-6",
        "bogus",
    ];
    let mut watch = RecordWatch::default();
    let (mut after_off, mut refused) = (0, 0);
    lab.link.clear();
    for _ in 0..3000 {
        let batch: Vec<&str> = (0..1 + next() % 4).map(|_| words[(next() % words.len() as u64) as usize]).collect();
        let reply = lab.send(&batch.iter().map(|l| format!("{l}\n")).collect::<String>());
        let verdicts: Vec<&str> = reply.lines().filter(|l| l.starts_with("ok") || l.starts_with("error: ")).collect();
        assert_eq!(verdicts.len(), batch.len(), "{batch:?}: {reply}");
        for (k, (line, verdict)) in batch.iter().zip(&verdicts).enumerate() {
            if k > 0 && batch[k - 1] == "record off" && line.starts_with("record ") && *line != "record off" {
                assert!(verdict.starts_with("ok record"), "{batch:?}: {reply}");
                after_off += 1;
            }
            refused += verdict.starts_with("error: record") as usize;
        }
        for _ in 0..next() % 100 {
            let o = lab.sample();
            watch.saw(&lab, &o, false);
        }
        let frames = lab.drain_recording();
        lab.link.push_str(&frames);
        watch.feed(&lab.link, || format!("{batch:?}"));
        lab.link.clear();
    }
    lab.send("record off\n");
    let frames = lab.drain_recording();
    lab.link.push_str(&frames);
    watch.feed(&lab.link, String::new);
    assert!(watch.inside.is_none(), "the last recording ended");
    println!(
        "{} recordings, {} samples ({} checked against the interrupt's codes); {after_off} asked for right after a \
         `record off` in the same batch, {refused} refused while one ran",
        watch.ended, watch.samples, watch.checked
    );
    assert!(after_off > 50 && refused > 50 && watch.ended > 500, "the cases do not cover the batches");
}

#[test]
fn a_recording_the_link_cannot_drain_stops_instead_of_leaving_a_gap() {
    let mut lab = Lab::new();
    lab.send("record on\n");
    lab.run(RECORD_BUFFER + 500);
    let st = lab.isr.record_status();
    assert!(!st.active && st.overflowed, "{st:?}");
    assert_eq!(st.recorded, RECORD_BUFFER as u64);
    let start = lab.link.len();
    let reply = lab.send("status\n");
    assert!(reply.contains(&format!("record=overflowed recorded={RECORD_BUFFER}")));
    // The stopped recording's frames and end line went out before the line's reply.
    let link = lab.link[start..].strip_suffix(reply.as_str()).expect("the reply last").to_string();
    assert_eq!(lab.drain_recording(), "");
    assert_eq!(recorded_samples(&link).len(), RECORD_BUFFER);
    let end = link.lines().last().unwrap();
    assert!(end.starts_with(&format!("# nanopos-record end samples={RECORD_BUFFER} overflow=1 ")), "{end}");
}

/// The board's first 20 001 samples recorded (from its first sample, so that a replay starts from the same rest as
/// the interrupt's estimators) and decoded on the host: what the interrupt's estimators hold after the last one and
/// after the 20 000th (`identify`'s last row), the decoded recording, and the folder of the capture and what
/// `decode` wrote (to remove).
fn record_from_the_start(lab: &mut Lab, name: &str) -> (Recorded, hal_sim::cmd::decode::Recording, PathBuf) {
    // `record on` applies on the recording's first sample; its reply, then the tuning's lines.
    let start = lab.link.len();
    lab.send("record on\n");
    let mut link = lab.link[start..].to_string();
    let mut at_last_row = Vec::new();
    for k in 0..20_000 {
        lab.sample();
        if k % 20 == 0 {
            link.push_str(&lab.drain_recording());
        }
        if k == 19_998 {
            at_last_row = (0..4).map(|i| lab.params(i)).collect();
        }
    }
    // What the interrupt's estimators hold after the last recorded sample (`record off` applies before its sample).
    let board: Vec<_> = (0..4).map(|i| lab.params(i)).collect();
    link.push_str(&lab.send("record off\n"));
    link.push_str(&lab.drain_recording());
    let st = lab.isr.record_status();
    assert!(!st.overflowed && st.recorded == 20_001, "{st:?}");

    let dir = std::env::temp_dir().join(format!("nanopos-record-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (capture, csv) = (dir.join("capture.txt"), dir.join("run.csv"));
    std::fs::write(&capture, &link).unwrap();
    let (rec, files) = hal_sim::cmd::decode::run(&capture, &csv, 1, hal_sim::cmd::decode::Damage::Refuse).unwrap();
    assert_eq!((rec.first_index(), rec.len(), rec.segments.len(), rec.ended), (0, 20_001, 1, Some(false)));
    assert_eq!(files, [Some(csv.clone())]);
    (Recorded { board, at_last_row }, rec, dir)
}

/// What the interrupt's estimators held in [`record_from_the_start`].
struct Recorded {
    /// After the last recorded sample.
    board: Vec<StageParams<f32>>,
    /// After the 20 000th, where `identify` writes its last row.
    at_last_row: Vec<StageParams<f32>>,
}

/// `nanopos-sim identify --precision f32` with `tuning` on the decoded file `csv`.
fn identify_f32(csv: &Path, tuning: hal_sim::tuning::TuningArg) -> hal_sim::cmd::identify::Identified {
    use hal_sim::cmd::identify::{self, IdentifyArgs, Precision};
    identify::run(&IdentifyArgs { precision: Precision::F32, ..IdentifyArgs::new(csv, tuning) }).unwrap()
}

#[test]
fn a_recorded_run_decodes_on_the_host_and_replays_to_the_interrupts_estimates() {
    let mut lab = Lab::new();
    let (Recorded { board, .. }, _, dir) = record_from_the_start(&mut lab, "replay");
    let csv = dir.join("run.csv");
    let cols = hal_sim::csv::read_columns(&csv, &["u", "y"], hal_sim::csv::Time::Required).unwrap();
    let replayed = identify_f32(&csv, hal_sim::bank::Tuning::preset("prbs").unwrap().into());
    assert_eq!(replayed.names, ESTIMATOR_NAMES);
    std::fs::remove_dir_all(&dir).unwrap();

    // The host's replay of the decoded file, in f32 like the board: the interrupt's estimates, to rounding of the
    // decoded volts (f64 in the file, f32 on the board).
    let cfg = lab.ctl.config::<f32>();
    let mut replay = Pipeline::new(&cfg, full_bank(&lab.ctl.tuning::<f32>()));
    let (u, y) = (&cols.data[0], &cols.data[1]);
    let mut at_last_row = None;
    for k in 0..u.len() {
        replay.replay(&cfg, u[k] as f32, y[k] as f32);
        let e = &replay.estimators;
        if k + 1 == 100 * replayed.times.len() {
            at_last_row = Some([e.0.params(), e.1.params(), e.2.params(), e.3.params()]);
        }
    }
    let e = &replay.estimators;
    for (i, h) in [e.0.params(), e.1.params(), e.2.params(), e.3.params()].iter().enumerate() {
        let b = board[i];
        for (x, z) in [(h.a0, b.a0), (h.a1, b.a1), (h.b0, b.b0)] {
            assert!(((x - z) / z).abs() < 1e-4, "{}: host {h:?} board {b:?}", ESTIMATOR_NAMES[i]);
        }
    }
    // `identify --precision f32` is this replay, bit for bit (its rows every 100 samples).
    let row = replayed.estimates.last().unwrap();
    for (i, h) in at_last_row.expect("a row").iter().enumerate() {
        assert_eq!(row[i], StageParams { a0: h.a0 as f64, a1: h.a1 as f64, b0: h.b0 as f64 }, "{}", ESTIMATOR_NAMES[i]);
    }
}

/// The tuning's lines go into the recording after the reply to `record on` and to each change of the tuning while
/// it runs, and only then; the reply still ends with its verdict.
#[test]
fn the_tuning_lines_follow_the_recordings_start_and_each_change_of_the_tuning_in_it() {
    let mut lab = Lab::new();
    let tuning_lines = |lab: &mut Lab, command: &str| {
        let start = lab.link.len();
        let reply = lab.send(command);
        // After the reply (a stopped recording's last frames and end line go out before it).
        let sent = &lab.link[start..];
        let after = sent[sent.find(reply.as_str()).expect("the reply on the link") + reply.len()..].to_string();
        assert!(verdict(&reply).starts_with("ok"), "{command}: {reply}");
        let lines: Vec<_> = after.lines().map(|l| nanopos_id::record::read_tuning_line(l).unwrap()).collect();
        assert!(lines.is_empty() || lines.len() == nanopos_id::estimators::TuningKey::ALL.len(), "{command}: {after}");
        // From the sample the change applied to: the one the command's sample ran.
        assert!(lines.iter().all(|l| l.at == lab.isr.pipeline.samples() - 1), "{command}: {after}");
        lines.iter().find(|l| l.key == nanopos_id::estimators::TuningKey::EkfR).map(|l| l.values[0])
    };
    assert_eq!(tuning_lines(&mut lab, "tune ekf r 2e-6\n"), None, "not recording");
    assert_eq!(tuning_lines(&mut lab, "record on\n"), Some(2e-6));
    assert_eq!(tuning_lines(&mut lab, "tune ekf r 3e-6\n"), Some(3e-6));
    assert_eq!(tuning_lines(&mut lab, "tuning triangle\n"), Some(1.5e-6), "a preset: every key");
    assert_eq!(tuning_lines(&mut lab, "excite prbs 1\n"), None, "not a change of the tuning");
    assert_eq!(tuning_lines(&mut lab, "tune ekf r\n"), None, "a question");
    assert_eq!(tuning_lines(&mut lab, "record off\n"), None);
    assert_eq!(tuning_lines(&mut lab, "tune ekf r 4e-6\n"), None, "stopped");
    assert_eq!(tuning_lines(&mut lab, "record burst 10\n"), Some(4e-6));
    lab.run(20);
    assert_eq!(tuning_lines(&mut lab, "tune ekf r 5e-6\n"), None, "the burst ended");
    assert_eq!(lab.link.matches(END_TAG).count(), 2, "{}", lab.link);
}

/// The largest relative difference between an estimate and the board's, over the estimators and the parameters.
fn worst_relative(row: &[StageParams<f64>], board: &[StageParams<f32>]) -> f64 {
    row.iter()
        .zip(board)
        .flat_map(|(h, b)| [(h.a0, b.a0), (h.a1, b.a1), (h.b0, b.b0)])
        .map(|(x, z)| ((x - z as f64) / z as f64).abs())
        .fold(0.0, f64::max)
}

/// A board tuned on the console records its tuning with its samples: `decode` writes it beside the CSV, and a replay
/// with it is the interrupt's estimates bit for bit (this board's scalings are exact in f32: the decoded volts round
/// to the interrupt's), where a replay with the preset is 20 % off. The spike gate's ratio too: at 4, where the
/// gate replaces some of the noise's tail, the replay replaces the same readings; at the default 32 it does not, and
/// its estimates are not the board's.
#[test]
fn a_recording_carries_the_boards_tuning_and_a_replay_with_it_is_the_boards() {
    let mut lab = Lab::new();
    for (command, restarted) in [
        ("tune initial 6.5e5 72.5 6.3e6\n", "estimators restarted"),
        ("tune rls gamma 0.7\n", "rls restarted; ekf,hekf,arx kept"),
        ("tune ekf q 1e-12 1e-6 3e9 0.3 1e9\n", EKFS_RESTARTED),
        ("tune ekf r 2.2e-6\n", EKFS_RESTARTED),
        ("tune ekf substeps 3\n", EKFS_RESTARTED),
        ("tune arx lambda 0.9995\n", "arx restarted; rls,ekf,hekf kept"),
        ("tune spike_ratio 4\n", KEPT),
    ] {
        assert!(lab.send(command).contains(&format!("({restarted})")), "{command}");
    }
    // A board started with this tuning (a replay starts from rest).
    lab.board = Lab::new().board;
    lab.isr = Instrument::new(lab.ctl.config(), &lab.ctl.tuning());
    let (recorded, rec, dir) = record_from_the_start(&mut lab, "tuning");
    let board = recorded.at_last_row;
    let csv = dir.join("run.csv");
    let toml = hal_sim::cmd::decode::tuning_path(&csv);
    assert_eq!((rec.tuning_file.as_deref(), rec.notes.len()), (Some(toml.as_path()), 0), "{:?}", rec.notes);
    let text = std::fs::read_to_string(&toml).unwrap();
    assert!(text.contains("\ninitial = [650000.0, 72.5, 6300000.0]\n") && text.contains("\nsubsteps = 3\n"), "{text}");
    assert!(text.contains("\nspike_ratio = 4\n") && lab.isr.status().counters.spikes > 0, "{text}");
    let from_file = hal_sim::tuning::resolve(toml.to_str().unwrap()).unwrap();
    let designed = from_file.at(1e-4).unwrap().design::<f64>();
    assert!(designed == lab.ctl.tuning::<f64>(), "the file holds the board's tuning exactly");
    let with_file = identify_f32(&csv, from_file.clone());
    let with_preset = identify_f32(&csv, hal_sim::bank::Tuning::preset("prbs").unwrap().into());
    let args = hal_sim::cmd::identify::IdentifyArgs::new(&csv, from_file);
    let default_gate = hal_sim::cmd::identify::IdentifyArgs {
        precision: hal_sim::cmd::identify::Precision::F32,
        spike_ratio: Some(hal_sim::cmd::identify::SpikeRatio(32)),
        ..args
    };
    let default_gate = hal_sim::cmd::identify::run(&default_gate).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    let (tuned, preset, gate) = (
        worst_relative(with_file.estimates.last().unwrap(), &board),
        worst_relative(with_preset.estimates.last().unwrap(), &board),
        worst_relative(default_gate.estimates.last().unwrap(), &board),
    );
    println!(
        "identify's last row against the board's estimates: with the recorded tuning {tuned:.1e}, with the preset \
         {preset:.1e}, with the recorded tuning but the default spike ratio {gate:.1e}"
    );
    assert!(tuned == 0.0 && preset > 1e-2 && gate > 0.0, "{tuned} {preset} {gate}");
}

/// The recording's round trip under random tunings: the lines `commands` writes for a random tuning file
/// ([`random_tuning_file`]) given to a board, which then starts from rest and records 2 s; `decode` writes a tuning
/// file that designs to the board's tuning exactly, and `identify --precision f32` with it is the interrupt's
/// estimates bit for bit. 100 tunings here; measured over 1 000 (the loop's count raised): none differed.
#[test]
fn a_recording_under_a_random_tuning_replays_to_the_boards_estimates() {
    let mut next = nanopos_id::xorshift64(0xBB67_AE85_84CA_A73B);
    let mut n = 0;
    while n < 100 {
        let text = random_tuning_file(&mut next);
        let arg = hal_sim::tuning::parse("t.toml", &text).unwrap();
        let Ok(cmds) = hal_sim::cmd::commands::run(&arg) else { continue };
        n += 1;
        let mut lab = Lab::new();
        for line in &cmds.lines {
            assert!(verdict(&lab.send(&format!("{line}\n"))).starts_with("ok "), "{text}\n{line}");
        }
        // A board started with this tuning (a replay starts from rest).
        lab.board = Lab::new().board;
        lab.isr = Instrument::new(lab.ctl.config(), &lab.ctl.tuning());
        let (recorded, rec, dir) = record_from_the_start(&mut lab, &format!("random-{n}"));
        let csv = dir.join("run.csv");
        let toml = hal_sim::cmd::decode::tuning_path(&csv);
        assert_eq!(rec.tuning_file.as_deref(), Some(toml.as_path()), "{text}\n{:?}", rec.notes);
        let from_file = hal_sim::tuning::resolve(toml.to_str().unwrap()).unwrap();
        let exact = from_file.at(1e-4).unwrap().design::<f64>() == lab.ctl.tuning::<f64>();
        let replay = identify_f32(&csv, from_file);
        std::fs::remove_dir_all(&dir).unwrap();
        assert!(exact, "{text}: the decoded file is not the board's tuning");
        let off = worst_relative(replay.estimates.last().unwrap(), &recorded.at_last_row);
        assert_eq!(off, 0.0, "{text}: the replay is {off:e} off the board's estimates");
    }
}

/// A limit of the excitation monitor, kept measured: it judges richness through its 5-20 Hz shaping filter, where a
/// tone above 20 Hz weighs as `f^-4`, and asks the off-sine power to clear the DAC's rounding. So a multisine counts
/// as rich only with tones low and strong enough: at 1 V, 200-800 Hz never starves, 350-550 Hz always does (the
/// parameters held wherever the start left them: the EKFs' a1 1.4 % and b0 0.5 % off); with the monitor off
/// (`pe_floor_v2 0`) the same narrow band
/// identifies the stage: the EKFs within 0.01 % on a0 and 0.3 % on b0 (measured -0.008 % and -0.26 %). But a
/// multisine's richness is not enough: the band must cover the resonance. Above it, 600-1000 Hz at 1 V with the
/// monitor off left the EKFs 5.1 % off in b0 and 6.8 % in a1, the RLS 72 % in a1 (950-1000 Hz: the EKFs 33 % in b0);
/// the monitor, on, starves them. Below it, 50-150 Hz at 1 V passes the monitor, and after 20 s the EKFs' a0 is still
/// 14 % off (from 15 % at the start) and the ARX's a1 is 210 % off: a limit of the monitor, which judges the input's
/// richness, not where its power is against the resonance.
#[test]
fn a_multisine_passes_the_excitation_monitor_only_wide_and_low_enough() {
    let run = |band: &str, monitor: bool| {
        let mut lab = Lab::new();
        if !monitor {
            for e in ["rls", "ekf", "arx"] {
                assert!(verdict(&lab.send(&format!("tune {e} pe_floor_v2 0\n"))).starts_with("ok"));
            }
        }
        assert!(verdict(&lab.send(&format!("excite multisine {band}\n"))).starts_with("ok"));
        let (starved, rel) = lab.run_measuring();
        println!(
            "multisine {band} V/Hz, monitor {monitor}: starved {starved:?} of 1000 over 10-20 s, errors % {:+.3?}",
            rel.map(|e| e.map(|x| x * 100.0))
        );
        (starved, rel)
    };
    assert_eq!(run("1 200 800", true).0, [0; 4]);
    assert_eq!(run("1 350 550", true).0, [1000; 4]);
    let (starved, rel) = run("1 350 550", false);
    assert_eq!(starved, [0; 4]);
    for ekf in [1, 2] {
        let e = rel[ekf];
        assert!(e[0].abs() < 1e-4 && e[1].abs() < 1e-2 && e[2].abs() < 3e-3, "{}: {e:?}", ESTIMATOR_NAMES[ekf]);
    }
    // Why the monitor must not simply trust a multisine: a band above the resonance (423 Hz), where the stage's
    // response nears its mass line, is starved with the monitor on, and with it off leaves the EKFs 5 % off in b0.
    assert_eq!(run("1 600 1000", true).0, [1000; 4]);
    let (starved, rel) = run("1 600 1000", false);
    assert_eq!(starved, [0; 4]);
    for ekf in [1, 2] {
        assert!(rel[ekf][2].abs() > 0.03, "{}: {:?}", ESTIMATOR_NAMES[ekf], rel[ekf]);
    }
    // And a limit: a band below the resonance passes the monitor (its tones weigh more the lower they are) and
    // does not identify the stage either: after 20 s the EKFs' a0 is still more than 10 % off.
    let (starved, rel) = run("1 50 150", true);
    assert_eq!(starved, [0; 4]);
    for ekf in [1, 2] {
        assert!(rel[ekf][0].abs() > 0.1, "{}: {:?}", ESTIMATOR_NAMES[ekf], rel[ekf]);
    }
}

/// The EKFs' parameter covariance is no error bar. It tells a well-excited stage from a poorly excited one (the hybrid
/// filter's standard deviation of a0 after 20 s: 0.065 % on the PRBS, 1.7 % on a 50-150 Hz multisine), but it does
/// not bound the error: on the PRBS the estimate is well inside it (0.009 %: the random-walk `Q` keeps the
/// covariance open), on the low multisine eight times beyond it (14 %: the filter is overconfident where the input
/// carries little of a0). A controller built on the estimates should not take `sqrt(P)` for their accuracy.
#[test]
fn the_ekfs_covariance_is_no_error_bar() {
    let measure = |excitation: &str| {
        let mut lab = Lab::new();
        assert!(verdict(&lab.send(&format!("excite {excitation}\n"))).starts_with("ok"));
        lab.run(200_000);
        let e = &lab.isr.pipeline.estimators;
        let (p, c) = (e.2.params(), e.2.param_covariance());
        let sd = (c[0][0] as f64).sqrt() / p.a0 as f64;
        let err = (p.a0 as f64 / StageParams::PAYLOAD.a0 - 1.0).abs();
        println!("hekf after 20 s of {excitation}: a0's sd {:.3} %, its error {:.3} %", sd * 100.0, err * 100.0);
        (sd, err)
    };
    let (sd_rich, err_rich) = measure("prbs 1");
    let (sd_poor, err_poor) = measure("multisine 1 50 150");
    assert!(sd_poor > 10.0 * sd_rich, "the covariance tells the inputs apart");
    assert!(err_rich < sd_rich, "well inside it on the PRBS");
    assert!(err_poor > 4.0 * sd_poor, "far beyond it on the low multisine");
}

/// The notes of [`the_console_says_when_an_excitation_will_not_fit_the_limits`] on 500 random limits and
/// excitations of every waveform (the PRBS, the sine, the smoothed triangle, the multisine, the constant): where a
/// note says the clamp will clip or the slew limit ramp, the limits change commands over the next 0.5 s, and only
/// there; but for a sine or a triangle whose samples miss its crest or its steepest step, by up to `1 - cos(pi f /
/// fs)` of them (`f` the top harmonic's), and a multisine whose samples come within 3.5 % of its peak's bound and 2.5
/// % of its steepest step's, which may leave a note with nothing limited. (Before the triangle's and the multisine's
/// steps were judged, the same check over all five waveforms found 32 mismatches in 400, each a triangle or a
/// multisine ramped by a slew limit of a few hundred V/s without a note; with the triangle's judged, it fails on the
/// first multisine so ramped.)
#[test]
fn the_fit_notes_of_random_excitations_and_limits_are_the_limits_effect() {
    let mut next = nanopos_id::xorshift64(0x3C6E_F372_FE94_F82B);
    let mut unit = move || (next() >> 11) as f64 / (1u64 << 53) as f64;
    let (mut noted, mut quiet, mut multisines, mut multisines_noted) = (0, 0, 0, 0);
    for _ in 0..500 {
        let mut lab = Lab::new();
        let (lo, hi) = (-10.0 + 10.0 * unit(), 10.0 * unit());
        let slew = 10f64.powf(1.0 + 4.5 * unit());
        let limits = format!("limits {lo:.3} {hi:.3} {slew:.1}\n");
        let (amp, f) = (10f64.powf(-1.5 + 2.0 * unit()), 10f64.powf(1.0 + 2.0 * unit()));
        let off = (lo + hi) / 2.0 + (unit() - 0.5) * 4.0;
        // The top harmonic's frequency, for the waveforms whose samples may miss their crest and steepest step.
        let (excite, top) = match (unit() * 5.0) as usize {
            0 => (format!("excite prbs {amp:.3} {off:.3}\n"), None),
            1 => (format!("excite sine {amp:.3} {f:.2} {off:.3}\n"), Some(f)),
            2 => (
                format!("excite triangle {amp:.3} {f:.2} {off:.3}\n"),
                Some(f * (2.0 * ((1000.0 / f + 1.0) / 2.0).floor() - 1.0)),
            ),
            // Tones at least 2 Hz apart, so that their relative phases turn through every value in the 0.5 s
            // watched.
            3 => {
                let lo = (f / 2.0).min(900.0);
                let hi = (lo + 31.0 * (2.0 + 30.0 * unit())).min(1000.0);
                (format!("excite multisine {amp:.3} {lo:.2} {hi:.2} {off:.3}\n"), None)
            }
            _ => (format!("excite constant {off:.3}\n"), None),
        };
        let multisine = excite.contains("multisine");
        if !verdict(&lab.send(&limits)).starts_with("ok ") {
            continue;
        }
        let reply = lab.send(&excite);
        if !verdict(&reply).starts_with("ok ") {
            continue;
        }
        // The ramp from the last command to the new excitation (a step the excitation did not make) first.
        lab.run(3000);
        let before = lab.isr.status().counters.limited;
        lab.run(5000);
        let limited = lab.isr.status().counters.limited > before;
        let says = notes(&reply).iter().any(|n| n.contains("will clip") || n.contains("will be ramped"));
        // The note's steepest step (the sine's `2 A sin(pi f / fs)`, the triangle's and the multisine's searched).
        let step = notes(&reply).iter().find_map(|n| {
            n.strip_prefix("note: the excitation steps by up to ")?.split_once(' ')?.0.parse::<f64>().ok()
        });
        // The multisine's samples come within 3.5 % of its peak's bound (1.36 `A`) and within 2.5 % of its steepest
        // step's (`multisine_steepest_step`).
        let missed_bound = says && !limited && multisine && {
            let near = |edge: f64, crest: f64| (edge - crest).abs() <= 0.035 * 1.36 * amp;
            near(hi, off + 1.36 * amp)
                || near(lo, off - 1.36 * amp)
                || step.is_some_and(|s| s * (1.0 - 0.025) <= slew * 1e-4)
        };
        let missed_crest = says
            && !limited
            && top.is_some_and(|top| {
                let miss = 1.0 - (std::f64::consts::PI * top / 1e4).cos();
                let near = |edge: f64, crest: f64| (edge - crest).abs() <= miss * amp;
                near(hi, off + amp) || near(lo, off - amp) || step.is_some_and(|s| (slew * 1e-4 - s).abs() <= miss * s)
            });
        assert!(says == limited || missed_crest || missed_bound, "{limits}{excite}{reply}limited: {limited}");
        (noted, quiet) = (noted + says as usize, quiet + !says as usize);
        (multisines, multisines_noted) =
            (multisines + multisine as usize, multisines_noted + (multisine && says) as usize);
    }
    println!("{noted} noted, {quiet} quiet; of {multisines} multisines {multisines_noted} noted");
    assert!(noted > 50 && quiet > 50, "{noted} noted, {quiet} quiet: the cases do not cover both");
}

/// The smoothed triangle's steepest step is judged against the slew limit like the PRBS's and the sine's: next to
/// its crests its harmonics overshoot the flank's `4 A f / fs` (0.04 V a sample for 1 V at 100 Hz) by Gibbs's 18 %,
/// and a slew limit between the two ramps it there (a 1 V, 100 Hz triangle under 300 V/s: 0.047 V a sample against
/// 0.03, limited in most of its samples); at 10 Hz it steps by 0.0047 V and passes.
#[test]
fn the_triangles_steepest_step_is_judged_against_the_slew_limit() {
    let mut lab = Lab::new();
    assert!(verdict(&lab.send("limits -5 5 300\n")).starts_with("ok limits"));
    let r = lab.send("excite triangle 1 100\n");
    assert!(
        notes(&r).contains(
            &"note: the excitation steps by up to 0.0471592 V a sample (471.592 V/s), beyond the slew limit's 0.03 V: \
              it will be ramped"
                .to_string()
        ),
        "{r}"
    );
    lab.run(3000);
    let before = lab.isr.status().counters.limited;
    lab.run(1000);
    assert!(lab.isr.status().counters.limited - before > 500, "ramped in most samples");
    let r = lab.send("excite triangle 1 10\n");
    assert!(!r.contains("will be ramped"), "{r}");
    lab.run(3000);
    let before = lab.isr.status().counters.limited;
    lab.run(2000);
    assert_eq!(lab.isr.status().counters.limited, before, "not ramped");
}

/// The multisine's steepest step is judged against the slew limit too: `excite multisine 1 200 800` steps by up to
/// 0.556 V a sample (its tones' relative phases turned through their crest: its samples reach 0.543 V), which 1 000
/// V/s (0.1 V a sample) ramps in most samples and 5 000 V/s in some; 6 000 V/s passes it whole.
#[test]
fn the_multisines_steepest_step_is_judged_against_the_slew_limit() {
    let mut lab = Lab::new();
    let note = |limit: &str| {
        format!(
            "note: the excitation steps by up to 0.555887 V a sample (5558.87 V/s), beyond the slew limit's {limit} V: \
             it will be ramped"
        )
    };
    let limited = |lab: &mut Lab| {
        lab.run(3000);
        let before = lab.isr.status().counters.limited;
        lab.run(5000);
        lab.isr.status().counters.limited - before
    };
    assert!(verdict(&lab.send("limits -5 5 1000\n")).starts_with("ok limits"));
    let r = lab.send("excite multisine 1 200 800\n");
    assert!(notes(&r).contains(&note("0.1")), "{r}");
    assert!(limited(&mut lab) > 2500, "ramped in most samples");
    let r = lab.send("limits -5 5 5000\n");
    assert!(notes(&r).contains(&note("0.5")), "{r}");
    assert!(limited(&mut lab) > 0, "ramped at the steepest steps");
    let r = lab.send("limits -5 5 6000\n");
    assert!(!r.contains("will be ramped"), "{r}");
    assert_eq!(limited(&mut lab), 0, "not ramped");
}

/// `excite`, `start` and `limits` say, before the verdict, when the chosen excitation will not fit the output
/// limits: beyond the clamp (the sine's and PRBS's extent exact, the multisine's from its 1.36 `A` bound), or with
/// steps steeper than the slew limit (the PRBS's and the sine's here; the triangle's and the multisine's in tests of
/// their own). Where the note says so, the limits then change
/// commands (`limited=` grows over the next 0.2 s); where it is silent, they do not. `excite sine` also says that a
/// sine cannot identify the stage, and `excite multisine` that a band missing the resonance (as the estimators have
/// it, else from `tune initial`) cannot either.
#[test]
fn the_console_says_when_an_excitation_will_not_fit_the_limits() {
    const DAC_REACH: &str = "note: the DAC reaches -8.78418 V to 8.78418 V (its output is specified from 0.2 V to 3.1 \
                             V): the clamp stops the output there";
    let mut lab = Lab::new();
    lab.run(100);
    let cases: [(&str, &[&str]); 12] = [
        ("excite prbs 1\n", &[]),
        (
            "excite sine 3 100 8\n",
            &[
                "note: the excitation spans 5 V to 11 V, beyond the clamp's -8.78418 V to 8.78418 V: the clamp will \
                 clip it",
                SINE,
            ],
        ),
        ("excite sine 3 100 5\n", &[SINE]),
        (
            "excite prbs 1.5\n",
            &["note: the excitation steps by up to 3 V a sample (30000 V/s), beyond the slew limit's 2.5 V: it will be \
               ramped"],
        ),
        ("excite multisine 1 200 800 7\n", &[]),
        (
            "excite multisine 2 200 800 8\n",
            &["note: the excitation spans 5.28 V to 10.72 V, beyond the clamp's -8.78418 V to 8.78418 V: the clamp \
               will clip it"],
        ),
        ("excite prbs 1\n", &[]),
        (
            "limits -0.5 0.5 1000\n",
            &[
                "note: the excitation spans -1 V to 1 V, beyond the clamp's -0.5 V to 0.5 V: the clamp will clip it",
                "note: the excitation steps by up to 2 V a sample (20000 V/s), beyond the slew limit's 0.1 V: it will be \
                 ramped",
            ],
        ),
        // Limits the excitation reaches exactly (its extent and its step): nothing to clip or ramp, and nothing said.
        ("limits -1 1 20000\n", &[]),
        // Limits beyond the DAC's reach on either side, or both.
        ("limits -10 5 25000\n", &[DAC_REACH]),
        ("limits -5 10 25000\n", &[DAC_REACH]),
        ("limits -10 10 25000\n", &[DAC_REACH]),
    ];
    for (cmd, want) in cases {
        let reply = lab.send(cmd);
        assert!(verdict(&reply).starts_with("ok"), "{cmd}: {reply}");
        assert_eq!(notes(&reply), want.to_vec(), "{cmd}");
        // The sample applying the change ramps from the last command (a step the excitation did not make): after it,
        // the count grows where a note said it would, and only there.
        lab.run(100);
        let before = lab.isr.status().counters.limited;
        lab.run(2000);
        let grew = lab.isr.status().counters.limited > before;
        let acts = want.iter().any(|n| n.contains("will clip") || n.contains("will be ramped"));
        assert_eq!(grew, acts, "{cmd}: limited grew {grew}");
    }
    // `start` says it again for the excitation it starts.
    assert!(verdict(&lab.send("excite sine 3 100 8\n")).starts_with("ok"));
    assert!(verdict(&lab.send("stop\n")).starts_with("ok"));
    assert_eq!(notes(&lab.send("start\n")).len(), 1);
    // A multisine band that misses the resonance: as the hybrid EKF estimates it (423 Hz, the stage's) or, with no
    // estimator running, as `tune initial` puts it (390 Hz).
    let reply = lab.send("excite multisine 1 50 150\n");
    let band = notes(&reply);
    assert!(
        band.len() == 1
            && band[0].starts_with("note: 50 to 150 Hz misses the resonance (42")
            && band[0].ends_with(" Hz, hekf's estimate): such a band does not identify the stage"),
        "{reply}"
    );
    assert!(verdict(&lab.send("select none\n")).starts_with("ok"));
    let reply = lab.send("excite multisine 1 450 550\n");
    assert_eq!(
        notes(&reply),
        ["note: 450 to 550 Hz misses the resonance (389.8 Hz, tune initial): such a band does not identify the stage"]
    );
    // Selected again, the estimators restart from `tune initial`; 2 s of PRBS bring the hybrid EKF to the stage.
    assert!(verdict(&lab.send("select all\n")).starts_with("ok"));
    assert!(verdict(&lab.send("excite prbs 1\n")).starts_with("ok"));
    lab.run(20_000);
    assert!(notes(&lab.send("excite multisine 1 400 500\n")).is_empty());
    // A sine with an estimator's monitor off: it says that one drifts.
    assert!(verdict(&lab.send("tune arx pe_floor_v2 0\n")).starts_with("ok"));
    let reply = lab.send("excite sine 1 450\n");
    assert_eq!(notes(&reply), [format!("{SINE}; one whose pe_floor_v2 is 0 drifts")], "{reply}");
}

/// The triangle chosen with the paper's `Q2` (the default `prbs` tuning), with which the EKFs fail on it (`identify`
/// of a simulated triangle: `b0` 24 % and 46 % low), and `tuning prbs` with the triangle chosen: a note gives the
/// tuning for it. Nothing with `Q1`, with another excitation, or with a triangle within a step of the DAC (which
/// identifies nothing: its own note says so; with the clamp's note too, the reply could overflow the console's
/// buffer). With the clamp's note it fits.
#[test]
fn the_triangle_with_the_prbs_tuning_is_given_the_triangle_tuning() {
    const Q2: &str =
        "note: the EKFs fail on the triangle with Q2, the paper's q for the PRBS: tuning triangle gives its Q1";
    let mut lab = Lab::new();
    let cases: [(&str, &[&str]); 8] = [
        ("excite triangle 1 10\n", &[Q2]),
        ("tuning triangle\n", &[]),
        ("excite triangle 1 10\n", &[]),
        ("tuning prbs\n", &[Q2]),
        ("excite prbs 1\n", &[]),
        ("tuning prbs\n", &[]),
        (
            "excite triangle 1e-3 10\n",
            &["note: the excitation spans 0.0019919 V, less than one step of the DAC \
                                          (0.00488281 V): the output holds one code or toggles between two, and the \
                                          excitation monitor holds the estimators (starved)"],
        ),
        ("tune ekf q 1e-12 1e-6 1.5e11 25 5e10\n", &[]),
    ];
    for (cmd, want) in cases {
        let reply = lab.send(cmd);
        assert!(verdict(&reply).starts_with("ok"), "{cmd}: {reply}");
        assert_eq!(notes(&reply), want.to_vec(), "{cmd}");
    }
    assert!(verdict(&lab.send("tune ekf q 1e-12 1e-6 1.5e9 0.25 5e8\n")).starts_with("ok"));
    assert!(verdict(&lab.send("limits -0.5 0.5 100\n")).starts_with("ok"));
    let reply = lab.send("excite triangle 8.5 1000 0.3\n");
    let notes = notes(&reply);
    assert!(
        notes.len() == 3 && notes[0].contains("clip") && notes[1].contains("will be ramped") && notes[2] == Q2,
        "{reply}"
    );
}

/// An excitation that spans less than one step of the DAC (4.88 mV as a command): the output holds one code (about
/// an offset on a code) or toggles between two (about an offset half a step off one, as for a sine of 1e-45 V
/// there), which no estimator can identify the stage from; the console says so, and the excitation monitor holds
/// every estimator, for each waveform. A PRBS of two steps is not noted (and identifies the stage slowly:
/// [`how_small_a_prbs_identifies_the_stage`]).
#[test]
fn an_excitation_within_a_dac_step_is_noted_and_starves_every_estimator() {
    const WITHIN: &str = "toggles between two, and the excitation monitor holds the estimators (starved)";
    let half_step = 0.0048828125 / 2.0;
    for cmd in [
        "excite prbs 0.002".to_string(),
        format!("excite prbs 0.002 {half_step}"),
        format!("excite sine 1e-45 100 {half_step}"),
        format!("excite triangle 0.002 10 {half_step}"),
        format!("excite multisine 0.0015 200 800 {half_step}"),
    ] {
        let mut lab = Lab::new();
        let reply = lab.send(&format!("{cmd}\n"));
        assert!(verdict(&reply).starts_with("ok"), "{cmd}: {reply}");
        let within: Vec<String> = notes(&reply).into_iter().filter(|n| n.ends_with(WITHIN)).collect();
        assert!(
            within.len() == 1 && within[0].starts_with("note: the excitation spans ") && within[0].contains(
                " V, less than one step of the DAC (0.00488281 V): the output holds one code or toggles between two"
            ),
            "{cmd}: {reply}"
        );
        let mut codes = std::collections::BTreeSet::new();
        for k in 0..30_000 {
            let out = lab.sample();
            codes.insert(out.dac_code);
            if k >= 10_000 {
                let starved = lab.isr.estimates().iter().all(|(_, h)| h.adaptation == Adaptation::Starved);
                assert!(starved, "{cmd}: sample {k}");
            }
        }
        // Two codes at most, and the safe code the output started from.
        assert!(codes.len() <= 2 + 1, "{cmd}: codes {codes:?}");
        // `start` says it again.
        lab.send("stop\n");
        assert!(notes(&lab.send("start\n")).iter().any(|n| n.ends_with(WITHIN)), "{cmd}");
    }
    let mut lab = Lab::new();
    for cmd in ["excite prbs 0.005\n", "excite off\n", "excite constant 0.001\n"] {
        let reply = lab.send(cmd);
        assert!(verdict(&reply).starts_with("ok") && notes(&reply).is_empty(), "{cmd}: {reply}");
    }
}

/// How small a PRBS identifies the paper's stage, from the paper's initial parameters, and how long it takes: the
/// time after which both EKFs' `b0` and `a1` stay within 1 % of the truth (a single estimate moves by more than
/// 0.1 %; their means over a window get within it), and their means over 20-30 s. The paper's 1 V moves the probe's
/// reading by 490 nm RMS and brings the EKFs within 1 % in 0.22 s. A twentieth of it, 50 mV (24 nm RMS, twenty times
/// the probe's noise), takes 4.5 s, and the 20-30 s means are within 0.003 % on `a0`, 0.06 % on `a1` and 0.10 % on
/// `b0` (-0.090 % and -0.099 %: at the goal's edge, guarded at 0.15 %; the ARX takes 35-58 s to within 1 %).
/// 10 mV (two DAC steps, 5.8 nm RMS) is starved 13 % of the time and leaves the EKFs 4 % off `b0` and 5.6 % off
/// `a1` after 30 s. Measured (`cargo test --release --test instrument -- --nocapture how_small`; 0.2 V and 20 mV on
/// the side: 1.3 s and 27 s).
#[test]
fn how_small_a_prbs_identifies_the_stage() {
    let truth = StageParams::PAYLOAD;
    let run = |amplitude: &str| {
        let mut lab = Lab::new();
        assert!(verdict(&lab.send(&format!("excite prbs {amplitude}\n"))).starts_with("ok"));
        // Per EKF: the last time `b0` or `a1` was 1 % or more off; the sums for the means over 20-30 s.
        let (mut outside, mut sums, mut starved) = ([0.0f64; 2], [[0.0f64; 3]; 2], 0usize);
        let (mut y_sum, mut y_squares) = (0.0f64, 0.0f64);
        for k in 0..300_000 {
            let y = lab.sample().y_um as f64;
            (y_sum, y_squares) = (y_sum + y, y_squares + y * y);
            if k % 100 == 0 {
                for (j, (p, h)) in lab.isr.estimates()[1..3].iter().enumerate() {
                    let e = errors(&truth, *p);
                    if e[1].abs() >= 1e-2 || e[2].abs() >= 1e-2 {
                        outside[j] = k as f64 / 1e4;
                    }
                    if k >= 200_000 {
                        sums[j] = [sums[j][0] + e[0], sums[j][1] + e[1], sums[j][2] + e[2]];
                        starved += (h.adaptation == Adaptation::Starved) as usize;
                    }
                }
            }
        }
        let n = 300_000.0;
        let rms_nm = 1e3 * (y_squares / n - (y_sum / n) * (y_sum / n)).sqrt();
        let means = sums.map(|s| s.map(|e| e / 1e3));
        println!(
            "prbs {amplitude} V: stage {rms_nm:.1} nm RMS; ekf, hekf within 1 % of b0 and a1 from {outside:?} s; \
             20-30 s means (a0, a1, b0) % {:+.3?}; starved {starved} of 2000",
            means.map(|e| e.map(|x| x * 100.0))
        );
        (rms_nm, outside, means, starved)
    };
    let (paper_nm, paper_s, _, _) = run("1");
    assert!(paper_s.iter().all(|&t| t < 0.5), "{paper_s:?}");
    let (small_nm, small_s, small, small_starved) = run("0.05");
    assert!(small_nm < paper_nm / 15.0 && small_nm > 10.0 * 1.25, "{small_nm} nm against {paper_nm} nm");
    assert!(small_s.iter().all(|&t| t < 6.0) && small_starved == 0, "{small_s:?}, starved {small_starved}");
    for e in small {
        assert!(e[0].abs() < 1e-3 && e[1].abs() < 1e-2 && e[2].abs() < 1.5e-3, "{e:?}");
    }
    let (_, tiny_s, _, tiny_starved) = run("0.01");
    assert!(tiny_s.iter().all(|&t| t > 29.0) && tiny_starved > 0, "{tiny_s:?}, starved {tiny_starved}");
}

/// The larger of the relative distances of `p`'s `a0` and `b0` from `a0` and `b0`.
fn a0_b0_off(p: StageParams<f32>, a0: f64, b0: f64) -> f64 {
    (p.a0 as f64 / a0 - 1.0).abs().max((p.b0 as f64 / b0 - 1.0).abs())
}

/// A pre-filter change carries the filter's state over at the new filter's scale, and holds the estimators until
/// the new filter has settled. The pre-filter's first state is the integral of its output, `in / w_lc` for an input
/// at rest: taken over as it was by a filter of another `f_lc` it stood for another level, and the filtered signal
/// jumped by the input's level times the change. A stage probed away from its zero (here the reading 20 um off, where
/// the PRBS moves it by 0.3 um), halving `f_lc` put 16 um into the filtered reading (the PRBS's own peak there 6 um).
/// Found by a longer random session (seed 1100, 100 000 lines), which ended at the preset's `tune prefilter 100 450
/// 0.1` from a slower pre-filter: 366 um in the filtered reading, and the hybrid EKF was still 2.1 % off `b0` after
/// the 5 s it is given. Carried over at scale ([`nanopos_id::filters::Prefilter::retarget`]), the state is still
/// the old filter's and not the new one's response to the signals: the estimators are not fed for ten of the new
/// filter's slowest time constants (`PipelineConfig::prefilter_settle_samples`, 35 ms here). The EKFs, whose tuning
/// a pre-filter change does not touch, then run on, their states taken again from the first sample; restarted as
/// well (`reset`, or `tune stage`, which changes the initial parameters too), they start from it. Measured, the time
/// from the change until both EKFs stay within 1 % of `a0` and `b0`: kept, they never leave it (at most 0.30 % and
/// 0.55 % off, the second the bias of a pre-filter centred at 600 Hz, off the 423 Hz resonance); restarted, 0.08 s
/// and 0.10 s. Restarted, without the wait (the states taken from the first sample) 0.10 s and 1.16 s; with the wait
/// but the states at zero, 1.29 s after the first; before either (the EKFs started at zero, fed at once) 0.10 s and
/// 0.10 s here, but at the end of the random session of seed 1031 (100 000 lines), and in
/// `estimators_restarted_after_a_fault_start_from_the_settled_filter`, both EKFs settled on `b0` below zero until their
/// relock test reset them 5 s later.
#[test]
fn a_pre_filter_change_holds_the_estimators_until_the_new_filter_settles() {
    let changes = [(20.0, "tune prefilter 50 450 0.1"), (-15.0, "tune prefilter 200 600 0.2")];
    for ((dc_um, change), restart) in changes.into_iter().flat_map(|c| [(c, false), (c, true)]) {
        // The board's probe reads `dc_um` off the pipeline's zero: a stage held away from its probe's zero.
        let mut lab = Lab::with_board(|board| {
            board.probe.adc_offset_v += dc_um * board.probe.adc_v_per_sensor_v / board.probe.um_per_v
        });
        let peak = |out: &[nanopos_id::pipeline::SampleOutput<f32>]| {
            out.iter()
                .map(|o| o.estimator_input.expect("no fault"))
                .fold([0.0f32; 2], |m, f| [m[0].max(f.u_f.value.abs()), m[1].max(f.y_f.value.abs())])
        };
        let before = peak(&lab.run(30_000)[20_000..]);
        let reply = lab.send(&format!("{change}\n"));
        let values = change.strip_prefix("tune prefilter ").unwrap();
        assert_eq!(verdict(&reply), format!("ok tune prefilter = {values} (rls restarted; ekf,hekf,arx kept)"));
        if restart {
            assert_eq!(verdict(&lab.send("reset ekf,hekf\n")), "ok reset ekf,hekf");
        }
        // The EKFs every 10 ms for 3 s from the change: the last look at which either is beyond 1 % of `a0` or
        // `b0` (0: none), and the most either is off.
        let truth = lab.board.plant().params();
        let off =
            |lab: &Lab| a0_b0_off(lab.params(1), truth.a0, truth.b0).max(a0_b0_off(lab.params(2), truth.a0, truth.b0));
        let (mut run, mut relock_s, mut worst) = (Vec::new(), 0.0, 0.0f64);
        for k in 1..=300 {
            let out = lab.run(100);
            if k <= 10 {
                run.extend(out);
            }
            worst = worst.max(off(&lab));
            if off(&lab) > 0.01 {
                relock_s = k as f64 * 0.01;
            }
        }
        // Not fed while the new filter settles (from the sample that applied the change, in `send`), then fed again.
        let settle = lab.isr.config().prefilter_settle_samples as usize;
        let unfed = run.iter().take_while(|o| o.estimator_input.is_none()).count();
        assert_eq!(unfed + 1 + restart as usize, settle, "{change}");
        let after = peak(&run[unfed..]);
        println!("{change}, the reading {dc_um} um off: peak u_f, y_f {before:?} before, {after:?} over 0.1 s after");
        // The new filter's own response to the same signals differs in size: within twice the peak before.
        assert!(after[0] < 2.0 * before[0] && after[1] < 2.0 * before[1], "{change}: {before:?} -> {after:?}");
        let how = if restart { "restarted" } else { "kept" };
        println!("  EKFs {how}: within 1 % of a0 and b0 from {relock_s:.2} s on, at most {worst:.1e} off");
        if restart {
            assert!(relock_s < 0.5, "{change}: EKFs relocked after {relock_s} s");
        } else {
            assert!(worst < 0.01, "{change}: the EKFs kept left 1 %: {worst:.1e}");
        }
    }
}

/// The estimators restarted right after a fault start from the settled pre-filter. The filters run on every reading,
/// a fault's too: after 0.1 s of the probe over range (its end of range, about 50 um off the stage) the pre-filter
/// still rings with it when the probe is back. `reset all` (a restart: the random session of seed 1031 ended with
/// `tuning prbs` from another tuning) and `start` (the fault cleared) at once: measured before the wait and the
/// states from the first sample, the filtered reading was 34.5 um at the restart with the reading within 0.1 um, and
/// neither EKF came within 1 % of `a0` and `b0` in the first second (160 % off); with the states from the first
/// sample but no wait, 0.80 s and 0.97 s (100-140 % off meanwhile); with the wait but the states at zero, 0.62 s and
/// 0.56 s (18-20 % off); with both, 0.063 s after the wait, at most 0.3 % off from 0.1 s on (0.074 s with the states'
/// variances `P0`'s). At `zeta_p` 0.02 the filter rings five times as long, and the wait is five times as long (177
/// ms): 0.046 s after it, at most 0.7 % off (0.022 s with `P0`'s).
#[test]
fn estimators_restarted_after_a_fault_start_from_the_settled_filter() {
    for (zeta, wait) in [("0.1", 354), ("0.02", 1769)] {
        let mut lab = Lab::new();
        assert!(verdict(&lab.send(&format!("tune prefilter 100 450 {zeta}\n"))).starts_with("ok tune prefilter"));
        lab.run(10_000);
        lab.board.forced_probe_code = Some(0);
        lab.run(1_000);
        lab.board.forced_probe_code = None;
        lab.run(5);
        assert_eq!(verdict(&lab.send("reset all\n")), "ok reset rls,ekf,hekf,arx");
        assert!(verdict(&lab.send("start\n")).starts_with("ok start"));
        // Not fed from the fault's end (the sample that cleared it, in `send`) until ten of the pre-filter's slowest
        // time constants have passed: `1 / (zeta_p w_p)`, 3.5 ms for the preset's.
        let settle = lab.isr.config().prefilter_settle_samples as usize;
        assert_eq!(settle, wait);
        let run = lab.run(settle - 1);
        assert!(run.iter().all(|o| o.faults.is_empty() && o.estimator_input.is_none()));
        let truth = lab.board.plant().params();
        let mut worst = [0.0f64; 2];
        let mut relock_s = [0.0f64; 2];
        for k in 1..=1_000 {
            assert!(lab.run(10).iter().all(|o| o.estimator_input.is_some()));
            for e in 0..2 {
                let off = a0_b0_off(lab.params(e + 1), truth.a0, truth.b0);
                if off > 0.01 {
                    relock_s[e] = k as f64 * 1e-3;
                }
                if k >= 100 {
                    worst[e] = worst[e].max(off);
                }
            }
        }
        println!(
            "zeta_p {zeta}: after the wait, the EKFs within 1 % from {:.3} s, {:.3} s on; worst from 0.1 to 1 s \
             {:.1e}, {:.1e}",
            relock_s[0], relock_s[1], worst[0], worst[1]
        );
        assert!(relock_s.iter().all(|&t| t < 0.5) && worst.iter().all(|&w| w < 0.01), "{relock_s:?} {worst:?}");
    }
}

/// A fault leaves the estimates where they were. While a fault is latched no estimator is fed, and after it none until
/// the pre-filter has settled from the fault's readings (354 samples); then the EKFs take their states again from the
/// first sample (`Estimator::resume`: the parameters and their covariance kept) and the ARX refills its history of
/// two samples before it adapts again. Measured over the 2 s after `start`, the largest move from the estimate before
/// the fault, for faults of 0.01, 0.1 and 1 s (the same within 0.03 %): the EKFs 0.28-0.31 % and the ARX 0.06-0.07 %,
/// as on the same samples without a fault (0.33 % and 0.06 %: their wander on the PRBS); before, resumed from their
/// states of before the fault, the EKFs took the jump for a change of the stage (19 % off, back within 1 % in 55 ms)
/// and the ARX moved by 1.4-1.6 %. The RLS, still converging 5 s after the start, moves 9 % in those 2 s with or
/// without a fault: not compared.
#[test]
fn a_fault_leaves_the_estimates_where_they_were() {
    let mut lab = Lab::new();
    lab.run(50_000);
    let before: Vec<_> = (0..4).map(|i| lab.params(i)).collect();
    let changes = |lab: &Lab| lab.isr.estimates().map(|(_, h)| h.changes_detected);
    let changes_before = changes(&lab);
    lab.board.forced_probe_code = Some(0);
    assert!(lab.run(1_000).iter().all(|o| o.estimator_input.is_none()));
    lab.board.forced_probe_code = None;
    lab.run(5);
    assert!(verdict(&lab.send("start\n")).starts_with("ok start"));
    let settle = lab.isr.config().prefilter_settle_samples as usize;
    assert!(lab.run(settle - 1).iter().all(|o| o.faults.is_empty() && o.estimator_input.is_none()));
    let mut worst = [0.0f64; 4];
    for _ in 0..2_000 {
        assert!(lab.run(10).iter().all(|o| o.estimator_input.is_some()));
        for (e, w) in worst.iter_mut().enumerate() {
            let b = before[e];
            *w = w.max(a0_b0_off(lab.params(e), b.a0 as f64, b.b0 as f64));
        }
    }
    let [rls, ekf, hekf, arx] = worst;
    println!("the largest move from the estimate before the fault: rls {rls:.1e}, ekf {ekf:.1e}, hekf {hekf:.1e}, arx {arx:.1e}");
    assert!(worst[1] < 0.01 && worst[2] < 0.01 && worst[3] < 0.005, "{worst:?}");
    assert_eq!(changes(&lab), changes_before, "a change of the stage detected");
}

/// What `excite sine` says of a sine.
const SINE: &str =
    "note: a sine alone identifies a gain and a phase, not the three parameters: the excitation monitor \
                    holds the estimators (starved)";

/// A long random session at the console, as a user in a hurry (or a noisy link) would type it: commands of every
/// verb with numbers from everyday to absurd (`nan`, `inf`, `1e39`, `1e-45`, huge counts), interleaved with runs of
/// samples, now and then with an external command added (steady, following the probe, huge or not finite), and now
/// and then a probe fault (over range, stuck, a lone glitch), a missed deadline or a lost conversion; lines corrected
/// with Backspace or Ctrl-U; the recording drained between lines, as the console task does. What must hold
/// throughout: every line gets exactly one final `ok` or `error:`, and a refused one leaves the interrupt's
/// configuration as it was; every DAC code is within the DAC's swing (codes 249 to 3847, whatever the limits) and
/// every command finite within -8.78 to 8.78 V, and within the slew limit of the last (`SlewWatch`); every estimate
/// finite, and a frozen one's unmoved; after `stop` (without an external command, which `stop` does not stop) or a
/// fault the output is at its safe value within 0.1 s; once a change has had 0.2 s to ramp in, the output is inside
/// the clamp in force; the missed deadlines and lost conversions counted; every recording in the stream whole
/// (`RecordWatch`: a header, frames following on from each other, an end line with their count) and each sample in
/// it the codes the interrupt read and wrote. Found so far: a slew limit of 1e-30 V/s accepted (the output then never
/// went safe); 22 000 lines into a longer run, the continuous EKF's `a0 = -inf` from a finite state (its RK4
/// dispersion correction, applied to an estimate gone wild on a pre-filter tuned to ring for ever, `tune prefilter
/// 25 0.5 1e-45`); at 500 000 lines, `b0 = inf` reported from a finite state; the output moving by twice the slew
/// limit after a missed deadline (`a_missed_deadline_does_not_make_the_output_jump_past_the_slew_limit`); and a
/// recording started while another ran, or before its end line, which lost the other's last samples and end line
/// (`a_recording_is_closed_before_another_starts`). At its end the preset's commands give back a firmware that
/// identifies the stage (see there for what that found).
///
/// To soak it, `SOAK_SEED` and `SOAK_LINES` in the environment replace the seed and the 20 000 lines, e.g.
/// `for s in $(seq 1001 1100); do SOAK_SEED=$s SOAK_LINES=100000 cargo test -q --release --test instrument --
/// a_random_session_of_commands_keeps_every_promise || echo "seed $s failed"; done` (about 5 s a seed).
#[test]
fn a_random_session_of_commands_keeps_every_promise() {
    let from_env = |name: &str| std::env::var(name).ok().map(|v| v.parse().unwrap_or_else(|_| panic!("{name}={v}")));
    random_session(
        from_env("SOAK_SEED").unwrap_or(0x9E37_79B9_7F4A_7C15),
        from_env("SOAK_LINES").unwrap_or(20_000),
        false,
    );
}

/// [`a_random_session_of_commands_keeps_every_promise`] for the session of `seed`, `length` lines long: the
/// recordings it streamed, and with `keep_stream` the stream itself (the link's every byte: replies, recordings).
fn random_session(seed: u64, length: u64, keep_stream: bool) -> (RecordWatch, String) {
    let mut lab = Lab::new();
    let mut next = nanopos_id::xorshift64(seed);
    let nums = [
        "1", "0", "-0", "-1", "2", "10", "-10", "11", "0.5", "1e3", "1e-3", "450", "100", "1000", "5000", "1e6", "5e5",
        "70", "6e6", "nan", "inf", "-inf", "1e39", "1e-45", "1e-30", "3.4e38", "0.1", "0.9999", "1.5e-6", "1e-12",
        "25000", "4", "16", "3", "0.05", "8e6", "1e10", "25", "5e8", "1.5e9", "1e-6", "3000", "9.99", "x", "",
    ];
    let keys = [
        "r",
        "substeps",
        "gate_sigma",
        "change_samples",
        "drift_ratio",
        "reopen",
        "pe_floor_v2",
        "gamma",
        "r0",
        "lambda",
        "max_trace",
        "p0",
        "q",
    ];
    let sets = ["all", "none", "rls", "ekf,hekf", "arx", "hekf,rls,rls", "kalman", ""];
    let templates: [&str; 36] = [
        "help",
        "select $ $",
        "excite prbs #",
        "excite prbs # #",
        "excite triangle # #",
        "excite sine # # #",
        "excite multisine # # #",
        "excite multisine # # # #",
        "excite constant #",
        "excite off",
        "start",
        "stop",
        "limits # # #",
        "limits -# # #",
        "tune initial # # #",
        "tune initial $",
        "tune stage $",
        "tune prefilter # # #",
        "tune ekf q # # # # #",
        "tune ekf @ #",
        "tune rls @ #",
        "tune arx @ #",
        "tune rls p0 # # #",
        "tuning prbs",
        "tuning triangle",
        "status",
        "record burst #",
        "record off",
        "select $",
        "reset $",
        "freeze $",
        "adapt $",
        "record on",
        "tune spike_ratio #",
        "tune ekf @",
        "tune initial",
    ];
    let lsb = 20.0 / 4096.0;
    let mut slew = SlewWatch::new(&lab);
    let (mut records, mut stream) = (RecordWatch::default(), String::new());
    lab.link.clear();
    let (mut since_change, mut lines, mut accepted, mut frozen_runs) = (0usize, 0usize, 0usize, 0usize);
    let mut restarts_checked = 0usize;
    // The session so far, for a failure's message: each line with the samples run after it.
    let mut session: Vec<String> = Vec::new();
    let recent = |s: &[String]| s[s.len().saturating_sub(30)..].join("\n");
    for _ in 0..length {
        let template = templates[(next() % templates.len() as u64) as usize];
        let mut line = String::new();
        for word in template.split(' ') {
            let r = next() as usize;
            let w = match word {
                // A third of the numbers with every digit, from 1e-12 to 1e12 either side of 0 (notes quote them).
                "#" if r % 3 == 0 => {
                    let unit = (next() >> 11) as f64 / (1u64 << 53) as f64;
                    format!("{}{}", ["", "-"][r / 3 % 2], 10f64.powf(24.0 * unit - 12.0))
                }
                "#" => nums[r % nums.len()].to_string(),
                "-#" => format!("-{}", nums[r % nums.len()]),
                "@" => keys[r % keys.len()].to_string(),
                "$" => sets[r % sets.len()].to_string(),
                w => w.to_string(),
            };
            line.push_str(&w);
            line.push(' ');
        }
        // Now and then the verb alone, a word cut short, a control byte, every word in capitals, a line too long,
        // or one corrected as typed: a byte taken back with Backspace (DEL), or what came before it with Ctrl-U.
        match next() % 16 {
            0 => line.truncate(line.find(' ').unwrap_or(0)),
            1 => line.truncate(line.len() / 2),
            2 => line.push('\u{1}'),
            3 => line.make_ascii_uppercase(),
            4 if next() % 4 == 0 => line.push_str(&" ".repeat(nanopos_id::control::MAX_LINE)),
            5 => line.insert_str(next() as usize % (line.len() + 1), "q\u{7f}"),
            6 => line.insert_str(0, "excite prbs 10\u{15}"),
            _ => {}
        }
        let line = if line.len() > nanopos_id::control::MAX_LINE { line.as_str() } else { line.trim_end() };
        let config_before = format!("{:?}", lab.isr.config());
        let health_before = lab.isr.estimates().map(|(_, h)| h);
        let reply = lab.send(&format!("{line}\n"));
        lines += 1;
        slew.check(&lab, || format!("{line:?}\n{}", recent(&session)));
        let finals = reply.lines().filter(|l| l.starts_with("ok") || l.starts_with("error: ")).count();
        let last = verdict(&reply);
        assert!(
            finals == 1 && (last.starts_with("ok") || last.starts_with("error: ")),
            "{line:?}: {reply}\n{}",
            recent(&session)
        );
        if last.starts_with("ok") {
            accepted += 1;
            since_change = 0;
            // A query changes nothing: `limits` alone (its verdict names the clamp in force), `status`, `help`.
            if last.contains("(the clamp in force") || last.starts_with("ok status") || last == "ok help" {
                let config = format!("{:?}", lab.isr.config());
                assert_eq!(config, config_before, "{line:?}: {reply}\n{}", recent(&session));
            }
            // A new tuning restarts the estimators its reply names, frozen ones staying frozen (a tuning that left
            // them adapting fails this), and the others run on: their counts go on from where they were (a restart
            // starts them from zero; one whose counts are all zero, as the RLS's mostly are, is not told apart).
            let health = lab.isr.estimates().map(|(_, h)| h);
            if let Some((restarted, kept)) = restarted_and_kept(last) {
                for (k, (h, h0)) in health.iter().zip(&health_before).enumerate() {
                    let name = ESTIMATOR_NAMES[k];
                    let counts = |h: &nanopos_id::estimator::Health| {
                        [h.numeric_resets, h.rejected_samples, h.changes_detected, h.covariance_repairs]
                    };
                    if kept.contains(&name) {
                        let grew = counts(h).iter().zip(counts(h0)).all(|(a, b)| *a >= b);
                        assert!(grew, "{name} kept: {h0:?} -> {h:?}\n{line:?}: {last}\n{}", recent(&session));
                    } else if restarted.contains(&name) {
                        assert!(counts(h).iter().all(|&c| c <= 1), "{name} restarted: {h:?}\n{}", recent(&session));
                        if h0.adaptation == Adaptation::Frozen {
                            assert_eq!(h.adaptation, Adaptation::Frozen, "{name}\n{}", recent(&session));
                        }
                    }
                    restarts_checked += 1;
                }
            }
        } else {
            // A refused command changes nothing.
            assert_eq!(format!("{:?}", lab.isr.config()), config_before, "{line:?}: {reply}\n{}", recent(&session));
        }
        let samples = if last.starts_with("ok stop") { 1002 } else { (next() % 300) as usize };
        session.push(format!("{line:?} -> {last}, {samples} samples"));
        // Now and then a run with an external command added (a controller's or a scan's; `sample_adding`): a
        // steady one, one that follows the probe, or one that is not finite (a fault: the output goes safe).
        let external = match next() % 8 {
            0 => Some((next() % 4, [0.5f32, -3.0, 1e30, f32::NAN][(next() % 4) as usize])),
            _ => None,
        };
        if let Some((kind, level)) = external {
            session.push(format!("external command kind {kind} level {level}"));
        }
        // A frozen estimator's parameters do not move, whatever the samples bring (unless a health reset took it
        // back to its initial parameters, which it counts).
        let before = lab.isr.estimates();
        for _ in 0..samples {
            let o = match external {
                Some((0, level)) => lab.isr.sample_adding(&mut lab.board, |_| level),
                Some((1, level)) => lab.isr.sample_adding(&mut lab.board, |y_um| -0.05 * y_um + level.min(1.0)),
                Some((2, _)) => lab.isr.sample_adding(&mut lab.board, |y_um| 1e3 * y_um),
                Some(_) => lab.isr.sample_adding(&mut lab.board, |_| f32::INFINITY),
                None => lab.sample(),
            };
            slew.check(&lab, || format!("{external:?}\n{}", recent(&session)));
            records.saw(&lab, &o, false);
            since_change += 1;
            assert!(
                (249..=3847).contains(&o.dac_code) && o.u_v.is_finite() && o.u_v.abs() <= 8.7842,
                "{o:?}\n{}",
                recent(&session)
            );
            let cfg = lab.isr.config();
            if since_change > 2000 {
                assert!(
                    o.u_v >= cfg.min_v - lsb && o.u_v <= cfg.max_v + lsb,
                    "{} outside\n{}",
                    o.u_v,
                    recent(&session)
                );
            }
        }
        // The recording streamed as the firmware's console task drains it, between lines; every recording in the
        // session's capture is whole.
        let frames = lab.drain_recording();
        lab.link.push_str(&frames);
        records.feed(&lab.link, || recent(&session));
        // Read: a long session's stream would otherwise be held whole.
        if keep_stream {
            stream.push_str(&lab.link);
        }
        lab.link.clear();
        for (k, ((p, h), (p0, h0))) in lab.isr.estimates().iter().zip(before.iter()).enumerate() {
            if h0.adaptation == Adaptation::Frozen
                && h.adaptation == Adaptation::Frozen
                && h.numeric_resets == h0.numeric_resets
            {
                assert!(p == p0, "{} frozen moved: {p0:?} -> {p:?}\n{}", ESTIMATOR_NAMES[k], recent(&session));
                frozen_runs += (samples > 0) as usize;
            }
        }
        // `stop` stops the excitation, not an external command: with one, the output follows it.
        if last.starts_with("ok stop") && external.is_none() {
            assert!(lab.isr.status().command_v.abs() <= lsb / 2.0, "not safe 0.1 s after stop\n{}", recent(&session));
        }
        // Now and then the probe goes over range: the fault latches, and 0.1 s later the output is safe whatever the
        // excitation, limits and estimators; the next `start` (above) clears it.
        if next() % 50 == 0 {
            lab.board.forced_probe_code = Some(0);
            for _ in 0..1002 {
                lab.sample();
                slew.check(&lab, || format!("probe over range\n{}", recent(&session)));
            }
            lab.board.forced_probe_code = None;
            let st = lab.isr.status();
            assert!(st.faults.contains(Faults::PROBE_OVER_RANGE), "{:?}\n{}", st.faults, recent(&session));
            assert!(st.command_v.abs() <= lsb / 2.0, "not safe 0.1 s after a fault\n{}", recent(&session));
            session.push("probe over range, 1002 samples".into());
        }
        // Now and then a stuck probe (the same code for 0.12 s: while an excitation runs, the fault latches and the
        // output goes safe as above; without one a steady reading is no fault), a lone glitch of the reading (the
        // spike gate's, no fault), or a late sample or lost conversion (counted).
        match next() % 50 {
            0 => {
                let moving = lab.isr.config().excitation.is_active();
                lab.board.forced_probe_code = Some(30_000);
                for _ in 0..1200 {
                    lab.sample();
                    slew.check(&lab, || format!("probe stuck\n{}", recent(&session)));
                }
                lab.board.forced_probe_code = None;
                if moving {
                    let faults = lab.isr.status().faults;
                    assert!(faults.contains(Faults::PROBE_STUCK), "{faults:?}\n{}", recent(&session));
                }
                // Latched (until `start`): 0.1 s later the output is safe.
                for _ in 0..1002 {
                    lab.sample();
                    slew.check(&lab, || format!("after the probe stuck\n{}", recent(&session)));
                }
                let st = lab.isr.status();
                if !st.faults.is_empty() {
                    assert!(st.command_v.abs() <= lsb / 2.0, "not safe 0.1 s after a fault\n{}", recent(&session));
                }
                session.push(format!("probe stuck, 1200 samples (excitation moving: {moving}), 1002 after"));
            }
            1 => {
                lab.board.forced_probe_code = Some(50_000);
                lab.sample();
                slew.check(&lab, || format!("probe glitch\n{}", recent(&session)));
                lab.board.forced_probe_code = None;
                session.push("probe glitch, 1 sample".into());
            }
            2 => {
                let before = lab.isr.status().counters;
                let faults = BoardFaults { deadline_missed: next() % 2 == 0, adc_overrun: next() % 2 == 0 };
                lab.board.inject_faults = Some(faults);
                let o = lab.sample();
                records.saw(&lab, &o, faults.deadline_missed);
                slew.check(&lab, || format!("{faults:?}\n{}", recent(&session)));
                let after = lab.isr.status().counters;
                let grown = |b: u32, a: u32, f: bool| a == b.saturating_add(f as u32);
                assert!(
                    grown(before.deadline_misses, after.deadline_misses, faults.deadline_missed)
                        && grown(before.adc_overruns, after.adc_overruns, faults.adc_overrun),
                    "{faults:?}: {before:?} -> {after:?}\n{}",
                    recent(&session)
                );
                session.push(format!("{faults:?}, 1 sample"));
            }
            _ => {}
        }
        for (k, (p, _)) in lab.isr.estimates().iter().enumerate() {
            let name = ESTIMATOR_NAMES[k];
            assert!(p.a0.is_finite() && p.a1.is_finite() && p.b0.is_finite(), "{name}: {p:?}\n{}", recent(&session));
        }
    }
    // The session exercised the commands, not only their refusals.
    println!(
        "{accepted} of {lines} lines accepted; {frozen_runs} runs of a frozen estimator held it; {restarts_checked} \
         estimators checked restarted or kept as a reply said"
    );
    println!(
        "{} recordings ended whole, {} samples recorded, {} checked against the probe's codes, {} against the DAC's",
        records.ended, records.samples, records.checked, records.checked_u
    );
    assert!(accepted > lines / 5, "{accepted} of {lines}");

    // And it leaves a firmware that identifies the stage as one just started: the default limits and excitation,
    // the preset's commands (`nanopos-sim commands --tuning prbs`), every estimator reset, `start`; 5 s later both EKFs
    // within 1 % of the truth's `a0` and `b0`, and nothing latched. A session of the same kind found (and these checks,
    // the slew's and the long numbers came with it): a pre-filter that rang for ever (`tune prefilter 1.4e-8 9.9 6e-9`,
    // taken before `PrefilterDesign::MAX_TIME_CONSTANT_S`) left a state from which the paper's pre-filter sent the
    // restarted continuous EKF to `b0` = -4e5; and a reply whose notes overflowed the console's buffer
    // (`a_reply_whose_notes_do_not_fit_keeps_its_verdict_and_its_command`). 60 seeds of this session then held.
    let preset = hal_sim::cmd::commands::run(&Tuning::preset("prbs").unwrap().into()).unwrap().lines;
    let defaults = ["stop", "record off", "limits -10 10 25000", "excite prbs 1", "select all", "adapt all"];
    // `reset all`: the preset's commands restart only the estimators whose tuning they change.
    let last = ["reset all", "start"].map(String::from);
    for line in defaults.iter().map(|l| l.to_string()).chain(preset).chain(last) {
        let reply = lab.send(&format!("{line}\n"));
        assert!(verdict(&reply).starts_with("ok "), "{line}: {reply}\n{}", recent(&session));
    }
    lab.run(50_000);
    let truth = lab.board.plant().params();
    let status = lab.status_reply();
    assert!(status.contains(" faults=none ") && status.contains(" tuning=prbs "), "{status}");
    for i in [1, 2] {
        let p = lab.params(i);
        let (a0, b0) = (p.a0 as f64 / truth.a0 - 1.0, p.b0 as f64 / truth.b0 - 1.0);
        println!("after the session and 5 s: {} a0 {a0:+.2e} b0 {b0:+.2e}", ESTIMATOR_NAMES[i]);
        assert!(a0.abs() < 0.01 && b0.abs() < 0.01, "{}: {p:?} against {truth:?}\n{status}", ESTIMATOR_NAMES[i]);
    }
    (records, stream)
}

/// The stream of a random session, as a capture of the console would hold it (replies, `status` lines, tuning lines,
/// hundreds of recordings among them, bursts and runs, stopped, ended or overflowed), decodes recording by
/// recording: each to the samples and the end its own end line gives.
#[test]
fn a_random_sessions_capture_decodes_recording_by_recording() {
    use hal_sim::cmd::decode::{self, Damage};
    let (records, stream) = random_session(0x5EED, 6_000, true);
    let n = records.recordings.len();
    assert!(n > 100, "{n} recordings");
    let dir = std::env::temp_dir().join(format!("nanopos-random-capture-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let capture = dir.join("capture.txt");
    std::fs::write(&capture, &stream).unwrap();
    let (mut decoded, mut single) = (0, 0);
    for (k, &(samples, overflowed)) in records.recordings.iter().enumerate() {
        let out = dir.join(format!("run{k}.csv"));
        match decode::run(&capture, &out, k + 1, Damage::Refuse) {
            Ok((rec, files)) => {
                assert_eq!(
                    (rec.len(), rec.ended, rec.segments.len()),
                    (samples, Some(overflowed), 1),
                    "recording {}",
                    k + 1
                );
                assert!(rec.damage.is_empty() && files == [Some(out.clone())], "recording {}: {rec:?}", k + 1);
                let rows = std::fs::read_to_string(&out).unwrap().lines().count() as u64;
                assert_eq!(rows, samples + 1, "recording {}: a header and a row a sample", k + 1);
                decoded += 1;
            }
            Err(e) => {
                assert_eq!(samples, 1, "recording {} of {samples} samples: {e}", k + 1);
                single += 1;
            }
        }
    }
    println!("{n} recordings in the capture; {decoded} decoded, {single} of a single sample refused");
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(decoded > 100, "{decoded}");
}

/// The estimators a tuning's reply says it restarted and kept (`(ekf,hekf restarted; rls,arx kept)`, `(estimators
/// restarted)`, `(estimators kept: their tuning is unchanged)`), if it says.
fn restarted_and_kept(verdict: &str) -> Option<(Vec<&'static str>, Vec<&'static str>)> {
    let said = verdict.rsplit_once('(')?.1.strip_suffix(')')?;
    let names = |list: &str| ESTIMATOR_NAMES.iter().copied().filter(|n| list.split(',').any(|w| w == *n)).collect();
    match said {
        "estimators restarted" => Some((ESTIMATOR_NAMES.to_vec(), Vec::new())),
        "estimators kept: their tuning is unchanged" => Some((Vec::new(), ESTIMATOR_NAMES.to_vec())),
        _ => {
            let (restarted, kept) = said.split_once(" restarted; ")?;
            Some((names(restarted), names(kept.strip_suffix(" kept")?)))
        }
    }
}

/// The recordings of a capture, checked line by line as it grows: a header, frames whose samples follow on from each
/// other's (each frame's CRC checked), an end line whose count is the samples its frames carried; and nothing
/// outside a recording but replies.
#[derive(Default)]
struct RecordWatch {
    /// Inside a recording: the index of the next sample due, once a frame came, and the samples so far.
    inside: Option<(Option<u64>, u64)>,
    ended: usize,
    samples: u64,
    /// Each recording ended: its samples, and whether it overflowed.
    recordings: Vec<(u64, bool)>,
    /// The probe code the interrupt read and the DAC code it wrote, and whether that write missed its deadline, by
    /// sample index since the board started (of the samples the test ran itself; the ring holds the last 0.1 s): a
    /// recorded sample of one of those carries its probe code, and the sample after it its DAC code (in effect over
    /// the next period, on time).
    read: std::collections::HashMap<u64, (u16, u16, bool)>,
    /// Recorded samples checked against them: their probe codes, their DAC codes.
    checked: u64,
    checked_u: u64,
}

impl RecordWatch {
    /// The sample the interrupt just ran gave `o`, its write `late` or not.
    fn saw(&mut self, lab: &Lab, o: &nanopos_id::pipeline::SampleOutput<f32>, late: bool) {
        self.read.insert(lab.isr.pipeline.samples() - 1, (o.probe_code as u16, o.dac_code as u16, late));
    }

    fn feed(&mut self, text: &str, context: impl Fn() -> String) {
        let mut out = [RawSample::default(); FRAME_SAMPLES];
        for line in text.lines() {
            if line.starts_with(HEADER_TAG) {
                assert!(self.inside.is_none(), "a header inside a recording: {line}\n{}", context());
                self.inside = Some((None, 0));
            } else if line.starts_with('R') {
                let Some((next, count)) = self.inside.as_mut() else {
                    panic!("a frame outside: {line}\n{}", context())
                };
                let (first, n) =
                    decode_frame(line.as_bytes(), &mut out).unwrap_or_else(|e| panic!("{e:?}: {line}\n{}", context()));
                assert!(next.is_none_or(|k| k == first), "a gap before {line} ({next:?})\n{}", context());
                (*next, *count) = (Some(first + n as u64), *count + n as u64);
                for (k, s) in out[..n].iter().enumerate() {
                    let i = first + k as u64;
                    if let Some(&(y, _, _)) = self.read.get(&i) {
                        assert_eq!(s.y_code, y, "sample {i}'s y of {line}\n{}", context());
                        self.checked += 1;
                    }
                    if let Some(&(_, u, false)) = i.checked_sub(1).and_then(|j| self.read.get(&j)) {
                        assert_eq!(s.u_code, u, "sample {i}'s u of {line}\n{}", context());
                        self.checked_u += 1;
                    }
                }
            } else if let Some(rest) = line.strip_prefix(END_TAG) {
                let Some((_, count)) = self.inside.take() else { panic!("an end outside: {line}\n{}", context()) };
                let said = rest.split_once("samples=").and_then(|(_, r)| r.split(' ').next()?.parse::<u64>().ok());
                assert_eq!(said, Some(count), "{line}\n{}", context());
                self.ended += 1;
                self.samples += count;
                self.recordings.push((count, rest.contains(" overflow=1 ")));
            }
        }
        // What the ring can no longer hold is not recorded any more.
        if self.read.len() > 4 * RECORD_BUFFER {
            let newest = self.read.keys().max().copied().unwrap_or(0);
            self.read.retain(|&k, _| k + 2 * RECORD_BUFFER as u64 > newest);
        }
    }
}

/// The output's move from one sample to the next, checked: at most the slew limit in force before or after it
/// (a change of `limits` takes effect between the two) and the DAC's rounding at both ends, whatever the
/// excitation, the limits, a fault's ramp to the safe value, or an external command. Read from the board (the
/// amplifier's input over the sample just simulated), so that the sample applying a change is checked too.
struct SlewWatch {
    last_v: f64,
    step_v: f64,
}

impl SlewWatch {
    fn new(lab: &Lab) -> Self {
        SlewWatch { last_v: lab.board.last_u_v(), step_v: lab.isr.config().max_step_v as f64 }
    }

    fn check(&mut self, lab: &Lab, context: impl Fn() -> String) {
        let cfg = lab.isr.config();
        let (u, step) = (lab.board.last_u_v(), cfg.max_step_v as f64);
        let bound = self.step_v.max(step) + 2.0 * cfg.command_lsb_v + 1e-9;
        assert!(
            (u - self.last_v).abs() <= bound,
            "output {} -> {u} V, slew step {bound} V\n{}",
            self.last_v,
            context()
        );
        (self.last_v, self.step_v) = (u, step);
    }
}

/// The piezo's gain drifts with temperature (SPEC section 1): every estimator follows a steady drift of `b0`, each
/// with its own lag. Over 50-100 s of the paper's PRBS (payload on), the mean of each estimate's `b0` error against
/// the truth of its own sample, with the gain drifting at 6 % per minute (0.1 % per second, a stress: a piezo's gain
/// moves by a few 0.1 % per kelvin) up and down, against the same run without drift: the difference
/// over the rate (relative to the gain at the window's middle) is the estimator's lag. Measured (f32, the
/// firmware's interrupt; up / down): ekf and hekf 0.049 / 0.042 s (0.005 % of `b0` at this rate: their random walk
/// on `b0`, Q2), arx 0.51 / 0.50 s, rls 3.0 / 3.0 s (its forgetting, gamma = 0.25 /s); `a0` and `a1` move by less
/// than 3e-5, and the drift is no change to the EKFs' detectors (`cargo test --release --test instrument --
/// --nocapture drifting`).
#[test]
fn every_estimator_follows_a_drifting_gain_with_its_own_lag() {
    let run = |pct_per_min: f64| {
        let mut lab = Lab::with_board(|board| board.plant.gain_drift_per_s = pct_per_min / 100.0 / 60.0);
        let mut sums = [[0.0f64; 3]; 4];
        for k in 0..1_000_000 {
            let truth = lab.board.plant().params();
            lab.sample();
            if k >= 500_000 && k % 100 == 0 {
                for (s, (p, _)) in sums.iter_mut().zip(lab.isr.estimates()) {
                    let e = errors(&truth, p);
                    *s = [s[0] + e[0], s[1] + e[1], s[2] + e[2]];
                }
            }
        }
        let changes: Vec<u32> = lab.isr.estimates().iter().map(|(_, h)| h.changes_detected).collect();
        (sums.map(|s| s.map(|e| e / 5e3)), changes)
    };
    let (still, _) = run(0.0);
    let rate = 0.1 / 100.0; // per second
    for pct_per_min in [6.0, -6.0] {
        let (drifting, changes) = run(pct_per_min);
        // The rate relative to the gain at the window's middle (75 s): 0.1 % of the start's is 0.093 % of 1.075.
        let sign = pct_per_min.signum();
        let relative_rate = rate / (1.0 + sign * rate * 75.0);
        let lag: Vec<f64> = (0..4).map(|i| -sign * (drifting[i][2] - still[i][2]) / relative_rate).collect();
        let moved: Vec<[f64; 2]> =
            (0..4).map(|i| [drifting[i][0] - still[i][0], drifting[i][1] - still[i][1]]).collect();
        let shown: Vec<String> = moved.iter().flatten().map(|m| format!("{m:.1e}")).collect();
        println!(
            "gain drifting {pct_per_min:+} %/min: b0 lag (s) rls, ekf, hekf, arx {lag:.3?}; a0, a1 moved {shown:?}; \
             changes detected {changes:?}"
        );
        assert!(lag[1].abs() < 0.1 && lag[2].abs() < 0.1, "the EKFs: {lag:?}");
        assert!((0.3..0.8).contains(&lag[3]), "the arx: {lag:?}");
        assert!((2.5..3.5).contains(&lag[0]), "the rls: {lag:?}");
        assert!(moved.iter().flatten().all(|m| m.abs() < 1e-4), "{moved:?}");
        assert_eq!(changes, [0, 0, 0, 0]);
    }
}

/// Which estimator for which stage: on stages of damping ratio 0.01 and static gain 0.05 um/V from 300 Hz to 1.6 kHz
/// (the board's second mode left at 1.9 kHz), the estimators started at the stage and the pre-filter centred on it
/// (what `tune stage` sets), the mean errors over 5-10 s. The hybrid EKF, whose substeps of `T / 4` follow the
/// resonance, stays within 1 % everywhere (0.84 % on `a1` at 1.3 kHz at worst). The continuous EKF's one RK4 step a
/// sample does not: its `a1` comes out low as `w T` grows, -1.3 % at 800 Hz (`w T` 0.50), -5.2 % at 1 kHz (0.63),
/// -20 % at 1.3 kHz (0.82), and its `b0` 12 % high at 1.6 kHz. The RLS and the ARX keep `a0` within 0.4 % (1 % at
/// 1.6 kHz), but their `b0` comes out high from 600 Hz on (the ARX 1.5 % there, 2.6-4.6 % above; the RLS 1.6 % at
/// 800 Hz, 3.2-4.5 % above: the second mode nearer, and their own discretisation), and at 1.6 kHz their `a1` is off
/// by 20-40 %. Measured (`cargo test --release --test
/// instrument -- --nocapture which_estimator`); README "Which estimator for which stage". From `w T` 0.5 on,
/// `status` notes the continuous EKF's `a1` ([`nanopos_id::instrument::FAST_RESONANCE_WT`]) while it runs, and the
/// telemetry warns of it once.
#[test]
fn which_estimator_for_which_stage() {
    let mut table = Vec::new();
    for f0 in [300.0, 423.0, 600.0, 800.0, 1000.0, 1300.0, 1600.0] {
        let w = 2.0 * std::f64::consts::PI * f0;
        let stage = StageParams { a0: w * w, a1: 0.02 * w, b0: 0.05 * w * w };
        let mut lab = Lab::with_stage(Some(stage));
        for cmd in
            [format!("tune initial {} {} {}\n", stage.b0, stage.a1, stage.a0), format!("tune prefilter 100 {f0} 0.1\n")]
        {
            assert!(verdict(&lab.send(&cmd)).starts_with("ok tune"), "{cmd}");
        }
        let (mut sums, mut watch, mut told) = ([[0.0f64; 3]; 4], EventWatch::new(1e4), 0);
        for k in 0..100_000 {
            lab.sample();
            if k >= 50_000 && k % 100 == 0 {
                for (s, (p, _)) in sums.iter_mut().zip(lab.isr.estimates()) {
                    let e = errors(&stage, p);
                    *s = [s[0] + e[0], s[1] + e[1], s[2] + e[2]];
                }
            }
            if k % 1000 == 999 {
                told += watch.look(&lab.isr.status()).fast_resonance.is_some() as usize;
            }
        }
        // The telemetry warns of it once, from `w T` 0.5 on.
        assert_eq!(told, usize::from(w * 1e-4 > 0.5), "{f0} Hz");
        let means = sums.map(|s| s.map(|e| e / 500.0));
        let shown = means.map(|e| e.map(|x| format!("{:+.2}", 100.0 * x)));
        println!(
            "{f0} Hz, w T {:.2}: % a0 a1 b0 rls {:?} ekf {:?} hekf {:?} arx {:?}",
            w * 1e-4,
            shown[0],
            shown[1],
            shown[2],
            shown[3]
        );
        table.push((f0, means));
        // `status` notes the continuous EKF's `a1` from `w T` 0.5 on, while it runs.
        let fast: Vec<String> = notes(&lab.send("status\n")).into_iter().filter(|n| n.contains(" w T = ")).collect();
        assert_eq!(fast.len(), usize::from(w * 1e-4 > 0.5), "{f0} Hz: {fast:?}");
        if f0 == 1000.0 {
            let hekf = Num(lab.params(2).f0_hz() as f64, 4);
            assert_eq!(
                fast[0],
                format!(
                    "note: the resonance, {hekf} Hz (hekf's estimate), is at w T = 0.63 of this sample rate, where the \
                     continuous EKF's one RK4 step a sample leaves its a1 low (on the simulated board -1.3 % at w T \
                     0.5, -5.2 % at 0.63, -20 % at 0.82); the hybrid EKF's substeps keep it within 1 %: take hekf's"
                )
            );
            assert!(verdict(&lab.send("select rls,hekf,arx\n")).starts_with("ok"));
            assert!(notes(&lab.send("status\n")).is_empty(), "the continuous EKF not running");
        }
    }
    for (f0, m) in &table {
        assert!(m[2].iter().all(|e| e.abs() < 0.01), "hekf at {f0} Hz: {:?}", m[2]);
        assert!(m.iter().all(|e| e[0].abs() < 0.02), "a0 at {f0} Hz: {m:?}");
    }
    // The continuous EKF's `a1`: within 1 % to 600 Hz, then low, more so as `w T` grows.
    let ekf_a1: Vec<f64> = table.iter().map(|(_, m)| m[1][1]).collect();
    assert!(ekf_a1[..3].iter().all(|e| e.abs() < 0.01), "{ekf_a1:?}");
    assert!(ekf_a1[3] < -0.01 && ekf_a1[4] < -0.04 && ekf_a1[5] < -0.15, "{ekf_a1:?}");
}

/// The EKFs' basin from the paper's initial parameters (390 Hz), and the disagreement on every stage outside it: stages
/// of damping ratio 0.01 and static gain 0.05 um/V, 30 s of the board's PRBS with nothing typed. Measured: both EKFs
/// find the stage (f0 within 1 %, b0 within 5 %) at 250, 300, 450 and 480 Hz; at 500 Hz the continuous one does and the
/// hybrid one does not; at 200 Hz and from 550 Hz up (and at 220 and 520 Hz, measured on the side) both settle on a
/// wrong solution (b0 of the wrong sign, f0 330-380 Hz), and the disagreement with the ARX names exactly the EKFs that
/// did (`cargo test --release --test instrument -- --nocapture basin`). The basin is this stage's and this noise's: the
/// 200 Hz stage of twice the gain is found after about 20 s
/// (`the_ekfs_disagreement_is_told_on_another_stage_and_never_on_the_papers`).
#[test]
fn the_ekfs_basin_from_the_papers_initial_parameters() {
    let mut found = Vec::new();
    for f0 in [200.0, 250.0, 300.0, 450.0, 480.0, 500.0, 550.0, 700.0, 1300.0] {
        let w = 2.0 * std::f64::consts::PI * f0;
        let stage = StageParams { a0: w * w, a1: 0.02 * w, b0: 0.05 * w * w };
        let mut lab = Lab::with_stage(Some(stage));
        lab.run(300_000);
        let status = lab.isr.status();
        let mut wrong = EstimatorSet(0);
        for ekf in [1, 2] {
            let p = status.estimates[ekf].0;
            let (f0_error, b0_error) = (p.f0_hz() as f64 / f0 - 1.0, p.b0 as f64 / stage.b0 - 1.0);
            let right = f0_error.abs() < 0.01 && b0_error.abs() < 0.05;
            assert!(right || p.b0 < 0.0, "{f0} Hz, {}: f0 {f0_error:+.3}, b0 {b0_error:+.3}", ESTIMATOR_NAMES[ekf]);
            if !right {
                wrong.0 |= 1 << ekf;
            }
        }
        let told = disagreement(&status);
        println!("{f0} Hz: wrong {wrong:?}, disagreement {told:?}");
        assert_eq!(told.map_or(EstimatorSet(0), |d| d.ekfs), wrong, "{f0} Hz");
        assert!(told.is_none_or(|d| d.reference_name() == "arx"), "{f0} Hz");
        found.push((f0, wrong.0));
    }
    // The anchors: found at 300 and 450 Hz, missed by both at 200, 700 and 1300 Hz.
    for (f0, wrong) in found {
        match f0 {
            300.0 | 450.0 => assert_eq!(wrong, 0, "{f0} Hz"),
            200.0 | 700.0 | 1300.0 => assert_eq!(wrong, 0b110, "{f0} Hz"),
            _ => {}
        }
    }
}

/// A limit, measured: a disconnected probe (the ADC reading the divider's mid-scale and the noise, no stage: here a
/// stage of zero gain) is no fault. Nothing is over-range or stuck (the noise moves the 16-bit code every sample),
/// the excitation runs, every estimator reads `adapting`, and they fit the noise, the EKFs on the pre-filter's own
/// resonance. The gain shows it: every estimator's below 5 % of the paper stage's 0.114 um/V (measured 3e-4 to
/// 8e-4 with the PRBS, 3e-3 to 4e-3 with the triangle). Where the EKFs agree with the ARX (with the PRBS at 17 of
/// these 300 looks, the rest disagreeing (187) or without a verdict; with the triangle at 295), `trusted_ekf_estimate`
/// gave their noise fit to a controller until it asked for a model that explains the measurement
/// (`instrument::response_ratio`, 0.01 to 4 here against the 10 it asks): now never, and `status` notes the weak
/// response there, the telemetry after 2 s of it (with the triangle: at 2.5 s). Where they disagree, the
/// disagreement's note stands, its advice (`tune stage arx`) beside the point. Telling the probe's silence for what
/// it is needs the output's response measured in the interrupt: not done (README, Safety).
#[test]
fn a_disconnected_probe_is_no_fault_but_every_gain_collapses() {
    for (what, commands) in [("prbs", &[][..]), ("triangle", TRIANGLE)] {
        let mut lab = lab_with(Some(DISCONNECTED), commands);
        let (mut disagreeing, mut trusted, mut weak, mut watch, mut told) = (0, 0, 0, EventWatch::new(1e4), vec![]);
        for look in 1..=300 {
            lab.run(1000);
            let status = lab.isr.status();
            assert!(status.faults.is_empty(), "{what}: {:?}", status.faults);
            disagreeing += disagreement(&status).is_some() as u32;
            trusted += trusted_ekf_estimate(&status, 2).is_some() as u32;
            told.extend(watch.look(&status).weak_response.map(|r| (look, r.ekf)));
            if weak_response(&status).is_some() {
                weak += 1;
                // `status` says so, in a line the console's buffer holds.
                let reply = lab.status_reply();
                let note = reply.lines().find(|l| l.starts_with("note: ")).unwrap_or_default();
                assert!(note.starts_with("note: hekf's model explains little of the measurement: "), "{reply}");
                let question = "Is the probe connected and seeing the stage, and the excitation large enough?";
                assert!(note.ends_with(question), "{note}");
                assert!(note.len() < nanopos_id::console::REPLY_BYTES);
            }
        }
        let status = lab.isr.status();
        for (i, (p, h)) in status.estimates.iter().enumerate() {
            let gain = (p.b0 / p.a0).abs();
            println!("{what}: {}: gain {gain:.2e} um/V, {}", ESTIMATOR_NAMES[i], h.state());
            assert!(gain < 0.05 * 0.114, "{what}: {}: {gain}", ESTIMATOR_NAMES[i]);
            assert_eq!(h.adaptation, Adaptation::Adapting);
        }
        println!(
            "{what}: looks (of 300, 0.1 s apart) disagreeing {disagreeing}, weak response {weak} (told {told:?}), \
             hybrid EKF trusted {trusted}"
        );
        assert_eq!(trusted, 0, "{what}");
        match what {
            "prbs" => assert!(disagreeing > 0 && weak > 0, "{disagreeing} {weak}"),
            _ => assert!(weak > 200 && told.first().is_some_and(|&(look, ekf)| look <= 60 && ekf == 2), "{told:?}"),
        }
    }
}

/// The measurement behind `instrument::TRUSTED_RESPONSE_RATIO` (about 40 s; `cargo test --release --test instrument
/// -- --ignored --nocapture response_ratio_where`): at every look (0.1 s apart, from 2 s on) where the hybrid EKF
/// adapts and agrees with the reference (the trusted rule without its response test), the range of its
/// `response_ratio`, and at how many looks the rule now gives the estimate. Printed, not asserted: the assertions
/// are the tests that use the rule (`tests/damping.rs`, `a_disconnected_probe_...` above).
#[test]
#[ignore]
fn response_ratio_where_the_trusted_rule_gave_the_estimate() {
    let dead = Some(DISCONNECTED);
    let triangle = TRIANGLE;
    let runs: [Run; 11] = [
        ("paper, prbs", None, &[], 200),
        ("paper, triangle", None, triangle, 200),
        ("paper, prbs 50 mV", None, &["excite prbs 0.05\n"], 60),
        ("paper, prbs 10 mV", None, &["excite prbs 0.01\n"], 60),
        ("paper, multisine", None, &["excite multisine 1 200 800\n"], 60),
        ("1 kHz, tune stage arx at 11 s", Some(KHZ_STAGE), &[], 20),
        ("200 Hz", Some(STAGE_200_HZ), &[], 40),
        ("disconnected, prbs", dead, &[], 200),
        ("disconnected, prbs 0.1 V", dead, &["excite prbs 0.1\n"], 100),
        ("disconnected, triangle", dead, triangle, 100),
        ("disconnected, multisine", dead, &["excite multisine 1 200 800\n"], 100),
    ];
    for (what, stage, commands, seconds) in runs {
        let mut lab = lab_with(stage, commands);
        let (mut agreed, mut trusted, mut low, mut high) = (0, 0, f32::MAX, 0.0f32);
        for look in 1..=seconds * 10 {
            lab.run(1000);
            if stage == Some(KHZ_STAGE) && look == 110 {
                assert!(lab.send("tune stage arx\n").contains("ok tune stage"));
            }
            let status = lab.isr.status();
            let adapting = status.estimates[2].1.adaptation == Adaptation::Adapting;
            let agrees = compare_ekfs(&status).is_some_and(|d| !d.ekfs.contains(2));
            if look < 20 || !(adapting && agrees) {
                continue;
            }
            agreed += 1;
            trusted += trusted_ekf_estimate(&status, 2).is_some() as u32;
            let ratio = response_ratio(&status, 2).unwrap_or(f32::NAN);
            (low, high) = (low.min(ratio), high.max(ratio));
        }
        println!(
            "{what:32} agreeing at {agreed:5} looks, response ratio {low:9.3} to {high:9.3}, trusted at {trusted:5}"
        );
    }
}

/// The board's tuning, key by key, as its recording carries it (exact: the values' bits).
fn board_tuning(lab: &Lab) -> Vec<nanopos_id::record::TuningLine> {
    (0..)
        .map_while(|k| {
            let mut line = String::new();
            lab.ctl
                .write_tuning_line(k, 0, &mut line)
                .then(|| nanopos_id::record::read_tuning_line(line.trim_end()).expect("a tuning line reads back"))
        })
        .collect()
}

/// `nanopos-sim commands` turns a tuning file into console lines that give the board that tuning, whatever it held
/// before: every line accepted, and every value the file's to within a few ulps (the board's decimal parser; the
/// shortest forms that read back exactly, as Rust writes them, come out exact here), a value of 17 digits included.
#[test]
fn a_tuning_files_commands_give_the_board_its_tuning() {
    let dir = std::env::temp_dir().join(format!("nanopos-commands-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("t.toml");
    std::fs::write(
        &file,
        "preset = \"triangle\"\ninitial = [6.5e5, 72.5, 6.3e6]\nprefilter = [120, 430, 0.15]\n[rls]\ngamma = 0.7\n\
         p0 = [2e6, 20, 3e7]\n[ekf]\nq = [1e-12, 1e-6, 3e9, 0.3, 1e9]\n\
         p0 = [1.0000000000000002e-11, 1e-5, 3.3333333333333336e10, 3, 1e10]\nr = 2.2e-6\nsubsteps = 3\n\
         gate_sigma = 6\n[arx]\nlambda = 0.9995\n",
    )
    .unwrap();
    let arg = hal_sim::tuning::resolve(file.to_str().unwrap()).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    let commands = hal_sim::cmd::commands::run(&arg).unwrap();
    assert!(commands.notes.is_empty(), "{:?}", commands.notes);
    // The stage's keys always (`tuning` keeps the board's): the file's spike ratio is the preset's, 32.
    assert_eq!(
        commands.lines[..4],
        ["tuning triangle", "tune initial 6.5e5 72.5 6.3e6", "tune prefilter 120 430 0.15", "tune spike_ratio 32"]
    );
    // The keys at the triangle preset's values are not sent; the file's eight others are, once.
    assert_eq!(commands.lines.len(), 4 + 8, "{:?}", commands.lines);
    let mut lab = Lab::new();
    let before =
        ["tune initial 2e6 100 5e7\n", "tune spike_ratio 7\n", "tune ekf gate_sigma 7\n", "tune arx max_trace 500\n"];
    for line in before.into_iter().chain(["tuning prbs\n"]) {
        assert!(verdict(&lab.send(line)).starts_with("ok "), "{line}");
    }
    for line in &commands.lines {
        let reply = lab.send(&format!("{line}\n"));
        assert!(verdict(&reply).starts_with("ok "), "{line}: {reply}");
    }
    let target = arg.at(1e-4).unwrap();
    let held = board_tuning(&lab);
    assert_eq!(held.len(), nanopos_id::estimators::TuningKey::ALL.len());
    for line in held {
        let want = &target.get(line.key)[..line.key.len()];
        for (got, want) in line.values.iter().zip(want) {
            assert!((got / want - 1.0).abs() <= 4.0 * f64::EPSILON, "{}: {got} for {want}", line.key);
        }
    }
    assert!(lab.send("status\n").contains(" tuning=triangle+tune "));
}

/// A command written after its deadline (the next sample instant passed) is not what that instant loads: the DAC
/// holds the one written before it for another period, and loads the late one at the instant after only if the next
/// sample's write is late too (else that one overwrites it first). The pipeline's command in effect, which its
/// filters and estimators take, and the recording say so, sample by sample, around deadline misses injected on the
/// simulated board (whose DAC then does as the board's): one alone, and two in a row. They took the late code for
/// the one in effect.
#[test]
fn a_command_written_too_late_is_not_taken_for_the_one_in_effect() {
    let mut lab = Lab::new();
    // A sine: the command changes every sample.
    assert!(verdict(&lab.send("excite sine 2 450\n")).starts_with("ok excite"));
    lab.run(100);
    let start = lab.link.len();
    lab.send("record burst 40\n");
    let mut link = lab.link[start..].to_string();
    let (mut in_effect, mut applied, mut codes) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..39 {
        if [20, 30, 31].contains(&k) {
            lab.board.inject_faults = Some(BoardFaults { deadline_missed: true, adc_overrun: false });
        }
        let out = lab.sample();
        in_effect.push(out.u_v);
        applied.push(lab.board.last_u_v() as f32);
        codes.push(out.dac_code);
    }
    lab.run(10);
    link.push_str(&lab.drain_recording());
    let recorded = recorded_samples(&link);
    assert_eq!(recorded.len(), 40);
    let cfg = lab.isr.config();
    // The recording's first sample is the `send`'s; the loop's samples follow it.
    for (k, s) in recorded[1..].iter().enumerate() {
        let u = cfg.command_of_code(s.u_code as u32);
        assert_eq!((u, in_effect[k]), (applied[k], applied[k]), "sample {k}");
    }
    // The code written at sample 20 never went out: sample 21 ran on sample 19's, sample 22 on sample 21's. Sample
    // 31, late too, ran on sample 29's, and let sample 30's out over sample 32 (recorded sample k + 1 is sample k).
    let u = |k: usize| recorded[k + 1].u_code as u32;
    assert!(codes[19] != codes[20] && codes[29] != codes[30] && codes[30] != codes[31]);
    assert_eq!([u(21), u(22)], [codes[19], codes[21]]);
    assert_eq!([u(31), u(32), u(33)], [codes[29], codes[30], codes[32]]);
    assert!(lab.send("status\n").contains(" deadline_misses=3 "));
}

/// A reply whose notes do not fit the console's buffer (`REPLY_BYTES`) loses its last notes, whole, and says so;
/// its verdict ends it, and the command is carried out. Found by the random session: `excite sine` of 29 uV about
/// -9.77 V (within a step of the DAC, beyond the clamp, a sine) had three notes and its verdict, 600 bytes; the
/// third note was cut at the buffer's end, the verdict lost with it, and the command refused (its reply's write
/// failed) after the console had taken its excitation: the interrupt ran the old one, the console the new.
#[test]
fn a_reply_whose_notes_do_not_fit_keeps_its_verdict_and_its_command() {
    let mut lab = Lab::new();
    lab.run(100);
    let r = lab.send("excite sine 2.884753544431569E-5 1.1969678585509862E-9 -9.770093206781224\n");
    let lines: Vec<&str> = r.lines().collect();
    assert!(r.len() <= REPLY_BYTES, "{r}");
    assert_eq!(lines.len(), 4, "{r}");
    assert!(lines[0].starts_with("note: the excitation spans 5.76951e-5 V, less than one step of the DAC"), "{r}");
    assert!(lines[1].starts_with("note: the excitation spans -9.77012 V to -9.77006 V, beyond the clamp's"), "{r}");
    assert_eq!(lines[2], "note: 1 more note left out (the reply's buffer is full)");
    assert_eq!(lines[3], "ok excite sine 2.88475e-5 V 1.19697e-9 Hz offset -9.77009 V (running)");
    assert!(lab.send("status\n").contains(" excitation=sine 2.88475e-5 V 1.19697e-9 Hz offset -9.77009 V running "));
    assert_eq!(lab.isr.config().excitation, lab.ctl.config::<f32>().excitation, "the interrupt runs the console's");
    // Today that sine's reply is 515 bytes before it is fitted; a multisine of the same kind, whose band misses the
    // resonance too, is 528: either is written whole before it is fitted, whatever its length (`BODY_BYTES`).
    let r = lab.send("excite multisine 2.8847535E-5 1.1969678E-9 2.1969678E-9 -9.7700932\n");
    let lines: Vec<&str> = r.lines().collect();
    assert!(r.len() <= REPLY_BYTES && lines.len() == 4, "{r}");
    assert!(lines[1].starts_with("note: the excitation spans -9.77013 V to -9.77005 V, beyond the clamp's"), "{r}");
    assert_eq!(lines[2], "note: 1 more note left out (the reply's buffer is full)");
    assert_eq!(lines[3], "ok excite multisine 2.88475e-5 V 1.19697e-9 to 2.19697e-9 Hz offset -9.77009 V (running)");
}

/// A capture damaged in every way a serial link and a user's editor can (a line lost, doubled, swapped, cut short, a
/// byte changed, garbage inserted, `\r\n` endings, the end line lost, the file cut anywhere), 400 ways: `decode`
/// never panics; it refuses (one line naming the problem, and no output left where it refuses) or decodes, and what
/// it writes is the board's samples: every row of every file it writes has the intact capture's `u` and `y` of that
/// sample, to the bit (a file's time starts at 0 with its segment). With `--segments` (`Damage::Skip`) a frame damaged
/// costs that frame (and the next, where the damage took the line's end) and no more.
#[test]
fn a_damaged_capture_is_refused_or_decoded_to_the_boards_samples_never_a_panic() {
    use hal_sim::cmd::decode::{run, Damage};
    let mut lab = Lab::new();
    lab.run(100);
    let start = lab.link.len();
    lab.send("record burst 3000\n");
    let mut capture = lab.link[start..].to_string();
    for _ in 0..30 {
        lab.run(100);
        capture.push_str(&lab.drain_recording());
    }
    capture.push_str(&lab.drain_recording());
    assert!(capture.contains("# nanopos-record end samples=3000 "), "{capture}");
    let dir = std::env::temp_dir().join(format!("nanopos-damaged-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let rows = |path: &Path| -> Vec<String> {
        std::fs::read_to_string(path).unwrap().lines().skip(1).map(String::from).collect::<Vec<_>>()
    };
    std::fs::write(dir.join("intact.txt"), &capture).unwrap();
    let (whole, _) = run(&dir.join("intact.txt"), &dir.join("intact.csv"), 1, Damage::Refuse).unwrap();
    // Each row's `u,y` (a file's time starts at 0 with its segment), by its sample's index since the board started.
    let values = |row: &str| row.split_once(',').unwrap().1.to_string();
    let intact: Vec<String> = rows(&dir.join("intact.csv")).iter().map(|r| values(r)).collect();
    assert_eq!(intact.len(), 3000);

    let mut next = nanopos_id::xorshift64(0xD1B5_4A32_D192_ED03);
    let lines: Vec<&str> = capture.split_inclusive('\n').collect();
    let (mut refused, mut decoded, mut kept_rows) = (0, 0, 0usize);
    for k in 0..400 {
        let mut below = |n: usize| (next() % n as u64) as usize;
        let mut damaged: Vec<String> = lines.iter().map(|l| l.to_string()).collect();
        let at = below(damaged.len());
        let what = k % 9;
        match what {
            0 => drop(damaged.remove(at)),
            1 => damaged.insert(at, damaged[at].clone()),
            2 => {
                let other = below(damaged.len());
                damaged.swap(at, other);
            }
            3 => {
                let cut = below(damaged[at].len());
                damaged[at].truncate(cut);
            }
            4 => {
                let mut bytes = damaged[at].clone().into_bytes();
                let i = below(bytes.len());
                bytes[i] = b"0aZ+/ #=\x7f"[below(9)];
                damaged[at] = String::from_utf8_lossy(&bytes).into_owned();
            }
            5 => damaged.insert(at, "R00000000zz!! garbage 1234\n".to_string()),
            6 => damaged.iter_mut().for_each(|l| *l = l.replace('\n', "\r\n")),
            7 => drop(damaged.pop()),
            _ => {}
        }
        let mut text = damaged.concat();
        if what == 8 {
            text.truncate(below(text.len()));
        }
        let input = dir.join(format!("damaged-{k}.txt"));
        std::fs::write(&input, &text).unwrap();
        for damage in [Damage::Refuse, Damage::Skip] {
            let out = dir.join(format!("out-{k}-{}.csv", damage == Damage::Skip));
            let result = std::panic::catch_unwind(|| run(&input, &out, 1, damage));
            match result.unwrap_or_else(|_| panic!("decode panicked on damage {what} at line {at}")) {
                Err(e) => {
                    refused += 1;
                    assert!(!e.0.is_empty() && !e.0.contains('\n'), "{e:?}");
                    if damage == Damage::Refuse {
                        assert!(!out.exists(), "damage {what}: a refused capture left {}", out.display());
                    }
                }
                Ok((rec, files)) => {
                    decoded += 1;
                    // A frame cut short or changed: `--segments` keeps every other frame (but the next one, where
                    // the damage took the line's end and the two lines became one).
                    if damage == Damage::Skip && [3, 4].contains(&what) && lines[at].starts_with('R') {
                        let kept: u64 = rec.segments.iter().map(|s| s.len).sum();
                        assert!(kept >= 3000 - 2 * 48, "damage {what} at line {at}: {kept} samples kept");
                    }
                    for (segment, file) in rec.segments.iter().zip(files) {
                        let Some(file) = file else { continue };
                        let first = (segment.first_index - whole.first_index()) as usize;
                        for (j, row) in rows(&file).iter().enumerate() {
                            let board = intact.get(first + j);
                            assert_eq!(board, Some(&values(row)), "damage {what} at line {at}: {}", file.display());
                            kept_rows += 1;
                        }
                    }
                }
            }
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
    println!("{refused} refusals, {decoded} decodes keeping {kept_rows} rows, every one the board's");
    assert!(refused > 100 && decoded > 100, "both outcomes seen");
}

/// At the pre-filter's bound (`PrefilterDesign::MAX_TIME_CONSTANT_S`), the slowest pre-filters the console takes
/// (a high-pass corner at 1.6 Hz; a pair at 10 Hz with `zeta_p` 0.16): 2 s of PRBS, 2 s of a held 5 V, stopped, then
/// the paper's pre-filter back with the PRBS: 5 s later both EKFs are within 1 % of `a0` and `b0`. Beyond the bound,
/// with the bound lifted for the measurement, `tune prefilter 1.41899e-8 9.87154 5.97602e-9` (the random session's
/// find: an undamped pair on a near-integrator, which the held 5 V fills) left the hybrid EKF at 19.7 times the
/// truth's `a0` and 1.42 times its `b0` in the same run.
#[test]
fn from_the_slowest_pre_filter_taken_the_paper_s_brings_the_ekfs_back() {
    for slow in ["tune prefilter 1.6 450 0.1", "tune prefilter 100 10 0.16", "tune prefilter 1.6 10 0.16"] {
        let mut lab = Lab::new();
        lab.run(20_000);
        assert!(verdict(&lab.send(&format!("{slow}\n"))).starts_with("ok tune prefilter"), "{slow}");
        lab.run(20_000);
        // A step held at an operating point: a pre-filter whose high-pass corner is near 0 Hz integrates it.
        lab.send("excite constant 5\n");
        lab.run(20_000);
        lab.send("stop\n");
        lab.run(10_000);
        for line in ["tune prefilter 100 450 0.1", "excite prbs 1", "start"] {
            assert!(verdict(&lab.send(&format!("{line}\n"))).starts_with("ok "), "{line}");
        }
        lab.run(50_000);
        let truth = lab.board.plant().params();
        for i in [1, 2] {
            let p = lab.params(i);
            let (a0, b0) = (p.a0 as f64 / truth.a0 - 1.0, p.b0 as f64 / truth.b0 - 1.0);
            println!("{slow}: {} a0 {a0:+.2e} b0 {b0:+.2e}", ESTIMATOR_NAMES[i]);
            assert!(a0.abs() < 0.01 && b0.abs() < 0.01, "{slow}: {}: {p:?}", ESTIMATOR_NAMES[i]);
        }
    }
}

/// EKFs restarted (`reset ekf,hekf`) in the middle of a run, 300 times 3.7 ms further apart each, on the paper's PRBS
/// after the payload came off (483 Hz; the initial parameters at 390 Hz): the time until both stay within 1 % of `a0`
/// and `b0`, looked at every 10 ms for 2 s. Measured: both EKFs' median 0.07 s, 90 % within 0.14 s, one of 300 over
/// 1 s (1.02 s: the 48th restart, where both were within 1 % from 0.05 s on and then both, alike, drifted to `b0`
/// +1.1-1.2 % between 0.8 and 1.0 s, a young covariance following the data, not a failed lock). Until the gate was
/// paused for the first 0.5 s after a start or a reset (`EkfHealthDesign`), the restarted filters met innovations
/// hundreds of times their `S` and gated half their samples, learning from those their wrong model fitted: the
/// continuous EKF's median 0.33 s, 17 of 300 over 1 s, some not within 2 s; the hybrid's 0.18 s, 40 over 1 s. (With the
/// states primed with `P0`'s variances instead of a measurement's, then: 0.36 s, 14; 0.18 s, 51; that change came from
/// the end of a random session, seed 1329 as the session was then, where the continuous EKF, primed on a 6 um ring with
/// variances of 1e-11 um^2, stood at `b0` +9.6 % 5 s later.)
#[test]
fn ekfs_reset_in_the_middle_of_a_run_relock() {
    let mut lab = Lab::with_stage(Some(StageParams::NO_PAYLOAD));
    let truth = lab.board.plant().params();
    lab.run(10_000);
    let mut relock = [Vec::new(), Vec::new()];
    for r in 0..300 {
        lab.run(37 * r);
        assert_eq!(verdict(&lab.send("reset ekf,hekf\n")), "ok reset ekf,hekf");
        let mut last = [0usize; 2];
        for k in 1..=200 {
            lab.run(100);
            for (e, l) in last.iter_mut().enumerate() {
                if a0_b0_off(lab.params(e + 1), truth.a0, truth.b0) > 0.01 {
                    *l = k;
                }
            }
        }
        for e in 0..2 {
            relock[e].push(last[e] as f64 * 0.01);
        }
    }
    for (e, times) in relock.iter_mut().enumerate() {
        times.sort_by(f64::total_cmp);
        let (n, over) = (times.len(), times.iter().filter(|&&t| t > 1.0).count());
        let (median, name) = (times[n / 2], ["ekf", "hekf"][e]);
        println!(
            "{name}: median {median:.2} s, 90 % {:.2} s, over 1 s {over} of {n}, most {:.2} s",
            times[n * 9 / 10],
            times[n - 1]
        );
        assert!(median < 0.15 && over < n / 50, "{name}: median {median} s, {over} of {n} over 1 s");
    }
}

/// The continuous-time RLS restarted (`reset rls`) in the middle of a run relocks as from rest: its own pre-filter
/// starts from zero on signals that are not, and the transient of its states does not show in the relock, which is
/// the normalised law's own time scale from the initial parameters (53 % off the truth here). Measured, on the
/// paper's PRBS after the payload came off, the time after which `a0` and `b0` stay within 2 % (the estimator's bias
/// there is 0.8 %), looked at every 0.1 s for 40 s: 16.4 s from rest, 16.3-16.4 s after each of three resets.
#[test]
fn the_rls_reset_in_the_middle_of_a_run_relocks_as_from_rest() {
    let mut lab = Lab::with_stage(Some(StageParams::NO_PAYLOAD));
    let truth = lab.board.plant().params();
    let relock = |lab: &mut Lab| {
        let mut last = 0;
        for k in 1..=400 {
            lab.run(1000);
            if a0_b0_off(lab.params(0), truth.a0, truth.b0) > 0.02 {
                last = k;
            }
        }
        last as f64 * 0.1
    };
    let from_rest = relock(&mut lab);
    println!("rls from rest: {from_rest:.1} s");
    assert!(from_rest < 30.0, "{from_rest} s");
    for r in 0..3 {
        lab.run(37 * r);
        assert_eq!(verdict(&lab.send("reset rls\n")), "ok reset rls");
        let t = relock(&mut lab);
        println!("rls reset {r}: {t:.1} s");
        assert!((t - from_rest).abs() <= 0.5, "reset {r}: {t} s against {from_rest} s from rest");
    }
}

/// A random tuning file, as `identify --tuning` reads it: one to four keys, each value the preset's times a power of
/// ten from 1e-30 to 1e30, zero, negative or near f64's ends, the whole numbers from everyday to out of range.
fn random_tuning_file(next: &mut impl FnMut() -> u64) -> String {
    let unit = |next: &mut dyn FnMut() -> u64| (next() >> 11) as f64 / (1u64 << 53) as f64;
    let prbs = Tuning::preset("prbs").unwrap();
    let (mut head, mut sections) = (String::new(), [String::new(), String::new(), String::new()]);
    if next() % 4 == 0 {
        head += "preset = \"triangle\"\n";
    }
    let mut keys: Vec<TuningKey> = Vec::new();
    for _ in 0..1 + next() % 4 {
        let key = TuningKey::ALL[(next() % TuningKey::ALL.len() as u64) as usize];
        if keys.contains(&key) {
            continue;
        }
        keys.push(key);
        let whole = matches!(key, TuningKey::SpikeRatio | TuningKey::EkfSubsteps | TuningKey::EkfChangeSamples);
        let values: Vec<String> = prbs.get(key)[..key.len()]
            .iter()
            .map(|&base| {
                if whole {
                    return [0, 1, 2, 3, 8, 64, 65, 1000, next() % 100][(next() % 9) as usize].to_string();
                }
                let c = unit(next);
                let v = if c < 0.5 {
                    base * 10f64.powf(6.0 * unit(next) - 3.0)
                } else if c < 0.7 {
                    base * 10f64.powf(60.0 * unit(next) - 30.0)
                } else if c < 0.8 {
                    0.0
                } else if c < 0.9 {
                    -base * 10f64.powf(6.0 * unit(next) - 3.0)
                } else {
                    [1e308, 5e-324, 1e-320, 3.4e38, 1e38][(next() % 5) as usize]
                };
                format!("{v:?}")
            })
            .collect();
        let (section, name) = key.path();
        let line = match values.as_slice() {
            [one] => format!("{name} = {one}\n"),
            _ => format!("{name} = [{}]\n", values.join(", ")),
        };
        match section {
            "" => head += &line,
            s => sections[["rls", "ekf", "arx"].iter().position(|&n| n == s).unwrap()] += &line,
        }
    }
    for (name, body) in ["rls", "ekf", "arx"].iter().zip(sections) {
        if !body.is_empty() {
            head += &format!("[{name}]\n{body}");
        }
    }
    head
}

/// `nanopos-sim commands` on random tuning files ([`random_tuning_file`], 20 000 of them): every file it takes gives
/// lines the board's console answers `ok`, one by one, and after them the board holds the file's tuning, every value
/// within the board's decimal parser's 4 ulps ([`nanopos_id::text::parse_decimal`]) or, for a key whose values were
/// shortened to fit a console line, within what its note says. This found the shortening's other effect: `q` written
/// to 12 digits set the board's `p0` to 10 times those, 3e-12 off the file's, with no note and no `p0` line (the tool
/// had followed the board with the file's `q`; it now follows it with the values as written). Measured: 6 558 files
/// taken (the rest refused, most for a value out of its range), every value within 3 ulps where not shortened.
#[test]
fn the_lines_commands_writes_give_the_board_the_files_tuning() {
    let mut next = nanopos_id::xorshift64(0x6A09_E667_F3BC_C908);
    let (mut taken, mut worst) = (0, 0.0f64);
    for i in 0..20_000 {
        let text = random_tuning_file(&mut next);
        let arg = hal_sim::tuning::parse("t.toml", &text).unwrap_or_else(|e| panic!("{i}: {text}: {}", e.0));
        let Ok(cmds) = hal_sim::cmd::commands::run(&arg) else { continue };
        taken += 1;
        let file = arg.at(1e-4).unwrap();
        let mut lab = Lab::new();
        for line in &cmds.lines {
            let reply = lab.send(&format!("{line}\n"));
            assert!(verdict(&reply).starts_with("ok "), "{i}: {text}\n{line}: {reply}");
        }
        for (k, key) in TuningKey::ALL.iter().enumerate() {
            let mut out = String::new();
            assert!(lab.ctl.write_tuning_line(k, 0, &mut out));
            let board = nanopos_id::record::read_tuning_line(out.trim_end()).unwrap();
            // A shortened key's note: "KEY's values written to D significant digits (each within ... relative)".
            let digits = cmds.notes.iter().find_map(|n| {
                n.strip_prefix(&format!("{key}'s values written to "))?.split(' ').next()?.parse::<i32>().ok()
            });
            for (b, f) in board.values.iter().zip(&file.get(*key)[..key.len()]) {
                let off = (b - f).abs() / f.abs();
                let bound = match digits {
                    Some(d) => 0.5 * 10f64.powi(1 - d) + 4.0 * f64::EPSILON,
                    None => {
                        worst = worst.max(off / f64::EPSILON);
                        4.0 * f64::EPSILON
                    }
                };
                assert!(off <= bound || b == f, "{i}: {text}\n{key}: the board's {b:e}, the file's {f:e}");
            }
        }
    }
    println!("{taken} of 20 000 files taken; the board's values within {worst} ulps of the file's where not shortened");
    assert!(taken > 5_000, "{taken}: too few taken to test anything");
}

/// An estimate is never reported non-finite, also where the normalised state is finite and its report is not: the
/// random session of seed 7 (500 000 lines) tuned the EKFs' `q` for `b0` to 3.4e38 on a stage of `b0_init` 5e5 (`p0`
/// 10 times that, finite once normalised), and the continuous EKF, resetting every few samples on that tuning,
/// reported `b0 = inf` for one sample before its state overflowed. Now the report's overflow is a numeric reset too.
#[test]
fn an_estimate_whose_report_overflows_is_reset_not_reported() {
    let mut lab = Lab::new();
    for line in ["tuning triangle", "tune initial 5e5 8e6 1000", "excite prbs 4", "tune ekf reopen 2"] {
        assert!(verdict(&lab.send(&format!("{line}\n"))).starts_with("ok "), "{line}");
    }
    lab.run(500);
    assert!(verdict(&lab.send("tune ekf q 0.05 0.037865561410726396 5e8 1000 3.4e38\n")).starts_with("ok "));
    for k in 0..2_000 {
        lab.run(1);
        for (i, (p, _)) in lab.isr.estimates().iter().enumerate() {
            assert!(p.a0.is_finite() && p.a1.is_finite() && p.b0.is_finite(), "{k}: {}: {p:?}", ESTIMATOR_NAMES[i]);
        }
    }
    // The tuning does not suit the stage, and the health report says so.
    assert!(lab.isr.estimates()[1].1.numeric_resets > 100);
}
