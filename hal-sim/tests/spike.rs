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
/// ratio of 16: 4; at 10: 21); with a probe noise of 10 nm, which then dominates the reading, 15 readings (0.25 a
/// second) with 3 degrees, 2 with 4, none with 5 or more (at 10: 367, 85, 26). Those are the noise's own far tail
/// (beyond 32 times its mean third difference) taken for spikes: `spikes=` then climbs by about one every 4 s on the
/// board, which README's Safety section says how to read and `tune spike_ratio` how to change.
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
    let (board_t3, loud_t3, loud_t4, loud_t5) =
        (run(3, None), run(3, Some(10e-3)), run(4, Some(10e-3)), run(5, Some(10e-3)));
    eprintln!("replaced of 600 000: board t3 {board_t3}; 10 nm probe: t3 {loud_t3}, t4 {loud_t4}, t5 {loud_t5}");
    assert_eq!(board_t3, 0);
    assert!((1..=60).contains(&loud_t3), "{loud_t3}: some, under one a second");
    assert!(loud_t4 <= loud_t3 && loud_t5 == 0, "{loud_t4} {loud_t5}");
}
