//! The paper's PRBS experiment (issue 4, SPEC 10) on the float64 reference's own data: 200 s, payload removed at
//! 100 s, windows 75-100 s and 175-200 s, the ideal ZOH plant with nothing outside model (1). Here the goals can
//! be held exactly as written: the estimators' own bias, the validation RMSE against the noise floor (the noise's
//! RMS in the window, which a perfect model reaches), the relock and f32 against f64. On the full simulated board
//! (`tests/ekf.rs`, `nanopos-sim paper`) the second mode and the analog chain add what model (1) cannot represent.

use hal_sim::cmd::identify::{validation_rmse_nm, Window};
use hal_sim::experiment::{rel_errors, relock_time, window_mean, ReferenceData, Sample};
use nanopos_id::estimator::Estimator;
use nanopos_id::estimators::crls::{Crls, CrlsDesign};
use nanopos_id::estimators::ekf::{Cekf, EkfDesign, Hekf};
use nanopos_id::excitation::ExcitationDesign;

const WINDOWS: [(f64, f64); 2] = [(75.0, 100.0), (175.0, 200.0)];

/// One window's figures: relative errors `(a0, a1, b0)` of the mean estimate and its validation RMSE over the
/// noise floor.
struct Figures {
    errors: [f64; 3],
    rmse_nm: f64,
    floor_nm: f64,
}

fn figures(data: &ReferenceData, t: &[f64], h: &[Sample]) -> [Figures; 2] {
    WINDOWS.map(|(t0, t1)| {
        let (mean, truth) = window_mean(h, t0, t1);
        Figures {
            errors: rel_errors(&mean, &truth),
            rmse_nm: validation_rmse_nm(&mean, t, &data.u, &data.y, ReferenceData::T_S, &Window { t0, t1 }),
            floor_nm: data.noise_rms_nm(t0, t1),
        }
    })
}

/// The goals one estimator is held to.
#[derive(Clone, Copy)]
struct Goals {
    /// a0 and b0, relative.
    a0_b0: f64,
    /// a1, relative.
    a1: f64,
    /// a0 and b0 within 1 % this long after the change, s.
    relock_s: Option<f64>,
}

/// Run one estimator in f64 and f32, print its rows, check the [`Goals`], the validation RMSE within 10 % of the
/// noise floor and the f32 window means within 1e-4 of the f64 ones.
fn check<E64: Estimator<f64>, E32: Estimator<f32>>(
    data: &ReferenceData,
    name: &str,
    mut e64: E64,
    mut e32: E32,
    goals: Goals,
) {
    let t = data.t();
    let (h64, h32) = (data.run(&mut e64), data.run(&mut e32));
    // Every row printed first, then the goals checked: a failure shows the whole table.
    let mut missed = Vec::new();
    for (prec, h) in [("f64", &h64), ("f32", &h32)] {
        let relock = relock_time(h, 100.0, 0.01);
        for ((t0, t1), f) in WINDOWS.iter().zip(figures(data, &t, h)) {
            let [a0, a1, b0] = f.errors.map(|e| e * 100.0);
            eprintln!(
                "{name:5} {prec} {t0:>3}-{t1}: a0 {a0:+.4}% a1 {a1:+.4}% b0 {b0:+.4}%  RMSE {:.3} nm (floor {:.3}, \
                 {:+.2}%)  relock {relock:?} s",
                f.rmse_nm,
                f.floor_nm,
                (f.rmse_nm / f.floor_nm - 1.0) * 100.0
            );
            let [a0, a1, b0] = f.errors;
            if !(a0.abs() < goals.a0_b0 && b0.abs() < goals.a0_b0 && a1.abs() < goals.a1) {
                missed.push(format!("{prec} {t0}-{t1}: errors {:?}", f.errors));
            }
            if f.rmse_nm / f.floor_nm - 1.0 >= 0.1 {
                missed.push(format!("{prec} {t0}-{t1}: RMSE {} nm, floor {} nm", f.rmse_nm, f.floor_nm));
            }
        }
        if goals.relock_s.is_some_and(|limit| !relock.is_some_and(|r| r <= limit)) {
            missed.push(format!("{prec}: relock {relock:?} s"));
        }
    }
    for (t0, t1) in WINDOWS {
        let d = rel_errors(&window_mean(&h32, t0, t1).0, &window_mean(&h64, t0, t1).0);
        eprintln!("{name:5} f32 - f64 {t0}-{t1}: {:+.1e} {:+.1e} {:+.1e}", d[0], d[1], d[2]);
        if d.iter().any(|x| x.abs() >= 1e-4) {
            missed.push(format!("f32 - f64 {t0}-{t1}: {d:?}"));
        }
    }
    assert!(missed.is_empty(), "{name}: {missed:#?}");
}

#[test]
fn the_noise_floor_is_the_references() {
    // truth_rmse_tableI_column of the reference, prbs/seg100: the noise's RMS per window.
    let data = ReferenceData::generate(ExcitationDesign::PAPER_PRBS, 1, 100.0);
    for ((t0, t1), reference) in WINDOWS.into_iter().zip([1.250978233705868, 1.2490767437185188]) {
        let floor = data.noise_rms_nm(t0, t1);
        assert!((floor / reference - 1.0).abs() < 1e-9, "{t0}-{t1}: {floor} nm vs the reference's {reference} nm");
    }
}

/// The validation's sensitivity near resonance: model (1) with the true parameters but `a0` off by `+1e-4` (the
/// resonance 50 ppm, 24 mHz, off) leaves an RMSE far above the noise floor, because the response at resonance is
/// `Q` (about 35) times the static one and its phase turns by about `Q` times the frequency error. So the RMSE goal
/// (within 10 % of the floor) asks `a0` to about 3e-5, thirty times the 0.1 % asked of it directly: the continuous
/// filters below missed it by this alone before their one-step RK4's dispersion was undone.
#[test]
fn the_validation_rmse_sees_a_resonance_off_by_50_ppm() {
    use nanopos_id::StageParams;
    let data = ReferenceData::generate(ExcitationDesign::PAPER_PRBS, 1, 100.0);
    let t = data.t();
    for ((t0, t1), truth) in WINDOWS.into_iter().zip([StageParams::PAYLOAD, StageParams::NO_PAYLOAD]) {
        let w = Window { t0, t1 };
        let rmse = |p: &StageParams<f64>| validation_rmse_nm(p, &t, &data.u, &data.y, ReferenceData::T_S, &w);
        let (exact, off) = (rmse(&truth), rmse(&StageParams { a0: truth.a0 * (1.0 + 1e-4), ..truth }));
        let floor = data.noise_rms_nm(t0, t1);
        eprintln!("{t0}-{t1}: truth {exact:.3} nm, a0 +1e-4 {off:.3} nm, floor {floor:.3} nm");
        assert!((exact / floor - 1.0).abs() < 1e-3, "{t0}-{t1}: the truth's RMSE is the noise's");
        assert!(off / floor - 1.0 > 0.25, "{t0}-{t1}: {off} nm");
    }
}

/// The hybrid EKF: every goal. a0, b0 within 0.1 %, a1 within 1 %, RMSE within 10 % of the floor, relock in about
/// a second.
#[test]
fn hekf_meets_the_prbs_goals_on_the_reference_data() {
    let data = ReferenceData::generate(ExcitationDesign::PAPER_PRBS, 1, 100.0);
    let d = EkfDesign::default();
    let goals = Goals { a0_b0: 1e-3, a1: 1e-2, relock_s: Some(1.0) };
    check(&data, "hekf", Hekf::<f64>::new(d.design()), Hekf::<f32>::new(d.design()), goals);
}

/// The continuous EKF: every goal. Measured a0 +0.0001 % and -0.0002 %, RMSE +0.14 % and +1.6 % over the floor.
/// Before its curvature term moved to the step's middle and its report undid one RK4 step's dispersion
/// (`estimators::ekf`, `Continuous::reported`), a0 was +5e-5 and +1e-4 off and the RMSE +13 % and +46 %.
#[test]
fn cekf_meets_the_prbs_goals_on_the_reference_data() {
    let data = ReferenceData::generate(ExcitationDesign::PAPER_PRBS, 1, 100.0);
    let d = EkfDesign::default();
    let goals = Goals { a0_b0: 1e-3, a1: 1e-2, relock_s: Some(1.0) };
    check(&data, "cekf", Cekf::<f64>::new(d.design()), Cekf::<f32>::new(d.design()), goals);
}

/// The continuous-time RLS: within 1 % (SPEC 10), and the RMSE goal too. Measured a0 -0.0001 % / -0.0005 %, RMSE
/// +2.5 % / +6.1 % over the floor; before its mid-step cubic and its report undoing the RK4 dispersion
/// (`estimators::crls`, "Discretisation") a0 was +6e-5 / +1e-4 off and the RMSE +21 % / +47 %. No relock goal (the
/// paper's RLS forgets over seconds: 14.6 s here).
#[test]
fn crls_meets_the_prbs_goals_on_the_reference_data() {
    let data = ReferenceData::generate(ExcitationDesign::PAPER_PRBS, 1, 100.0);
    let d = CrlsDesign::default();
    let goals = Goals { a0_b0: 1e-2, a1: 1e-2, relock_s: None };
    check(&data, "crls", Crls::<f64>::new(d.design()), Crls::<f32>::new(d.design()), goals);
}

/// The smoothed triangle (seed 2, the EKFs with `Q1`): all converge (the issue asks for errors and relock times).
/// Measured, f64: hybrid a0 -0.022 % / +0.005 %, a1 +0.19 % / +0.16 %, b0 -0.095 % / +0.033 %, relock 0.28 s;
/// continuous a0 -0.022 % / +0.005 %, a1 +0.14 % / +0.06 %, b0 -0.093 % / +0.034 %, relock 0.28 s (the goal is 10 s;
/// over other seeds see `tests/ekf.rs`, `drift_detection_relocks_the_triangle`; with the reopening at once instead
/// of over 10 ms it was 1.01 s and 9.05 s); RMSE within 0.1 % of the floor for both (the triangle puts little energy
/// near resonance). The float64 reference, without drift detection: a1 +0.7 % / +3.7 %, b0 -0.21 % / +0.08 %.
/// Held: the PRBS goals, and the relock within 1 s as on PRBS.
#[test]
fn the_ekfs_converge_on_the_triangle_reference_data() {
    let data = ReferenceData::generate(ExcitationDesign::PAPER_TRIANGLE, 2, 100.0);
    let d = EkfDesign::paper(EkfDesign::Q1);
    let goals = Goals { a0_b0: 1e-3, a1: 1e-2, relock_s: Some(1.0) };
    check(&data, "hekf", Hekf::<f64>::new(d.design()), Hekf::<f32>::new(d.design()), goals);
    check(&data, "cekf", Cekf::<f64>::new(d.design()), Cekf::<f32>::new(d.design()), goals);
}

/// The continuous-time RLS on the smoothed triangle converges as far as this input lets it: measured a0 +0.67 % /
/// -0.91 %, a1 -3.1 % / -6.1 %, b0 +0.69 % / -0.93 %, relock (1 %) 79.8 s; the float64 reference's own: a0 +0.58 % /
/// -1.02 %, a1 -3.7 % / -7.0 %, b0 +0.59 % / -1.05 %. Held to 2 % (a0, b0) and 10 % (a1): converged, as the
/// reference's did; RMSE within 10 % of the floor (measured +0.8 %).
#[test]
fn crls_converges_on_the_triangle_reference_data() {
    let data = ReferenceData::generate(ExcitationDesign::PAPER_TRIANGLE, 2, 100.0);
    let d = CrlsDesign::default();
    let goals = Goals { a0_b0: 2e-2, a1: 1e-1, relock_s: None };
    check(&data, "crls", Crls::<f64>::new(d.design()), Crls::<f32>::new(d.design()), goals);
}
