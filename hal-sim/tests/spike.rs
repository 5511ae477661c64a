//! The pipeline's spike gate (`nanopos_id::filters::spike`) on the simulated board's own runs: a reading the gate
//! replaced there would be the stage's motion lost, so it must replace none, with room to spare.

use hal_sim::board::BoardSettings;
use hal_sim::plant::{Creep, Hysteresis};
use hal_sim::sim::{Scenario, Simulation};
use nanopos_id::excitation::ExcitationDesign;
use nanopos_id::hal::StageBoard;
use nanopos_id::pipeline::PipelineSettings;

/// The readings the gate replaced over `seconds` of `scenario` (payload off at half the run) at the gate's ratio
/// `ratio`; the board and the pipeline's settings as `adjust` leaves them; with `quiet_s` seconds without
/// excitation first (the excitation then starts at once, from rest).
fn replaced(
    scenario: Scenario,
    seconds: f64,
    quiet_s: f64,
    ratio: u16,
    adjust: impl FnOnce(&mut BoardSettings, &mut PipelineSettings),
) -> u32 {
    let (mut board, mut settings) = scenario.settings(seconds, scenario.default_seed());
    adjust(&mut board, &mut settings);
    settings.faults.spike_ratio = ratio;
    let excitation = settings.excitation;
    settings.excitation = ExcitationDesign::OFF;
    let mut sim = Simulation::new(board, &settings, ()).expect("designs");
    let running = PipelineSettings { excitation, ..settings }.design(&sim.board.description()).expect("designs");
    for k in 0..(seconds * 1e4) as u64 {
        if k == (quiet_s * 1e4) as u64 {
            sim.config = running;
        }
        sim.step();
    }
    sim.pipeline.fault_counters().spikes
}

/// A change to the board's and the pipeline's settings.
type Adjust = dyn Fn(&mut BoardSettings, &mut PipelineSettings);

/// None replaced at the default ratio (32) nor at 10: the PRBS with the payload's bump, the triangle, the
/// multisine, an 8 V PRBS started from rest without a slew limit, a PRBS through a piezo with hysteresis and creep.
/// (A run that replaces nothing at 10 is, sample for sample, the run at 32: the gate's state is the same.) The first
/// replacements come at 7 (the multisine: 2 in 60 s; the triangle 18 at 6), the noise's tail.
///
/// At 4 every run replaces some, which shows the test can fail, and under 1 % of its readings: a gate that replaced
/// a reading wrongly does not go on replacing. It did, before the curve restarted from the readings as read after a
/// run of replacements (from the extrapolated ones it missed the next readings by several times their third
/// difference): 1.3 million of the two million readings of the PRBS and the triangle at ratios 4 and 5 (the
/// triangle's at 6 too), and 343 360 of the multisine's 600 000 at 6 and 7.
#[test]
fn the_gate_replaces_none_of_the_simulated_boards_readings() {
    let none = |_: &mut _, _: &mut _| {};
    let cases: [(&str, Scenario, f64, f64, Box<Adjust>); 5] = [
        ("prbs", Scenario::Prbs, 200.0, 0.0, Box::new(none)),
        ("triangle", Scenario::Triangle, 200.0, 0.0, Box::new(none)),
        ("multisine", Scenario::Multisine, 60.0, 0.0, Box::new(none)),
        (
            "8 V prbs from rest, no slew limit",
            Scenario::Prbs,
            20.0,
            1.0,
            Box::new(|_, s| {
                s.excitation.amplitude_v = 8.0;
                s.limits.max_slew_v_per_s = 1e9;
            }),
        ),
        (
            "prbs, hysteresis and creep",
            Scenario::Prbs,
            60.0,
            0.0,
            Box::new(|b: &mut BoardSettings, _| {
                b.plant.hysteresis = Some(Hysteresis::default());
                b.plant.creep = Some(Creep::default());
            }),
        ),
    ];
    for (name, scenario, seconds, quiet_s, adjust) in cases {
        let n = replaced(scenario, seconds, quiet_s, 10, |b, s| adjust(b, s));
        assert_eq!(n, 0, "{name}: {n} readings replaced at a ratio of 10");
        let n = replaced(scenario, seconds, quiet_s, 4, |b, s| adjust(b, s));
        eprintln!("{name}: {n} readings replaced at a ratio of 4");
        assert!(n > 0 && f64::from(n) < 0.01 * seconds * 1e4, "{name}: {n} readings replaced at a ratio of 4");
    }
}

/// A real probe's noise need not be Gaussian. With the displacement noise drawn from Student's t at the same RMS
/// (`BoardSettings::noise_tail_dof`), 60 s of the PRBS at the default ratio (32): on the simulated board (1.25 nm of
/// probe noise under 3 nm of the ADC's Gaussian conversion noise) none replaced even with 3 degrees of freedom (at a
/// ratio of 16: 4; at 10: 21); with a probe noise of 10 nm, which then dominates the reading, 1 reading with 3
/// degrees, none with 4 or more (at 16: 66, 8, 2; at 10: 363, 83, 26): the noise's own far tail, beyond 32 times its
/// mean third difference. It was 15 with 3 degrees (2 with 4) before the gate clipped the curve at a reading taken
/// far off it (`spike::SUSPECT`): 14 of them good readings replaced by predictions that such a reading had thrown
/// off, which moved the estimates (below).
#[test]
fn the_gate_on_heavy_tailed_noise_replaces_its_far_tail_only() {
    let run = |dof: u32, noise_um: Option<f64>| {
        replaced(Scenario::Prbs, 60.0, 0.0, 32, |b, _| {
            b.noise_tail_dof = Some(dof);
            if let Some(rms) = noise_um {
                b.noise_um_rms = rms;
            }
        })
    };
    let board_t3 = run(3, None);
    let (loud_t3, loud_t4, loud_t5) = (run(3, Some(10e-3)), run(4, Some(10e-3)), run(5, Some(10e-3)));
    eprintln!("replaced of 600 000: board t3 {board_t3}; 10 nm probe: t3 {loud_t3}, t4 {loud_t4}, t5 {loud_t5}");
    assert_eq!(board_t3, 0);
    assert!(loud_t3 <= 5 && loud_t4 == 0 && loud_t5 == 0, "{loud_t3} {loud_t4} {loud_t5}");
}

/// The estimates on such noise (10 nm, Student's t with 3 degrees of freedom), the paper's PRBS experiment: after the
/// payload change and the relock, the hybrid EKF (f64) and the continuous one (f32) stay within 1 % of the truth's
/// a0 and b0, as with the gate off (0.86-0.88 % at most, both ways) and as on Gaussian noise (0.74-0.76 %). Before
/// the curve was clipped they did not: up to 18-19 % off in b0 (20 rows of 100 Hz beyond 1 % from 118 s to 171 s),
/// each time a good reading replaced by a prediction a taken outlier had thrown off.
#[test]
fn heavy_tailed_noise_through_the_gate_moves_no_estimate_off() {
    use hal_sim::experiment::{rel_errors, run};
    use nanopos_id::estimators::ekf::{Cekf, EkfDesign, Hekf};
    let d = EkfDesign::default();
    let h = run(
        Scenario::Prbs,
        200.0,
        1,
        || Hekf::new(d.design::<f64>()),
        || Cekf::new(d.design::<f32>()),
        |b, _| {
            b.noise_tail_dof = Some(3);
            b.noise_um_rms = 10e-3;
        },
    );
    for (name, history) in [("hekf f64", &h.f64), ("ekf f32", &h.f32)] {
        let worst = history
            .iter()
            .filter(|s| s.t_s > 101.0)
            .map(|s| rel_errors(&s.est, &s.truth))
            .fold(0.0f64, |w, e| w.max(e[0].abs()).max(e[2].abs()));
        eprintln!("{name}: a0 and b0 at most {:.2} % off the truth from 101 s on", 100.0 * worst);
        assert!(worst < 0.01, "{name}: {worst}");
    }
}
