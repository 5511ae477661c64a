//! A damping loop on the estimates, on the simulated board: what the estimators are for (README "A controller on the
//! estimates"). Worked through here, not shipped in the firmware: the controller is the user's.
//!
//! The loop is a resonant controller, `u = g BP(s) y` with the band-pass `BP(s) = 2 zeta_c w_c s / (s^2 +
//! 2 zeta_c w_c s + w_c^2)`, added to the excitation through `Simulation::step_adding` (on the board,
//! `Instrument::sample_adding`). Velocity feedback `u = -k x'` would damp the stage's mode, `a1 -> a1 + k b0`, but the
//! analog chain between the DAC and the ADC (the two 1 kHz Butterworth filters, the amplifier, the sensor, the DAC's
//! hold and the sample the command waits) lags by about 110 degrees at the resonance: the controller must make up for
//! it. So it is tuned from the hybrid EKF's estimate (`f0`, `b0 / a0`) and the chain's response as the pipeline's
//! settings describe it (its replicas' cut-offs and lags: what a controller on the board has; the simulated board's
//! chain is the same nominal one): `w_c` where the band-pass's phase at `f0` is the -90 degrees of a velocity
//! feedback less the chain's phase, and `g` for an added damping ratio `dzeta = g |BP| |H_chain| (b0 / a0) / 2` at
//! `f0`. Retuned at 10 Hz, as a controller would from the firmware's status snapshot: in the simulations while the
//! EKF reports `adapting`; through the firmware's interrupt body (`Lab`) while `instrument::trusted_ekf_estimate`
//! gives it, which `a_controller_follows_an_ekf_only_once_a_reference_confirms_it` shows a controller needs.
//!
//! The damping is measured as a ring: the excitation off, a kick through the command (10 V asked for three samples,
//! which the slew limit of 2.5 V a sample shapes into a triangle), and the decay rate of the ring's peaks
//! (`zeta = sigma / w0`).

use hal_sim::board::BoardSettings;
use hal_sim::lab::Lab;
use hal_sim::sim::{Scenario, Simulation};
use nanopos_id::estimator::{Adaptation, Estimator};
use nanopos_id::estimators::ekf::{Cekf, EkfDesign, Hekf};
use nanopos_id::excitation::ExcitationDesign;
use nanopos_id::filters::design::{bilinear2, prewarp_constant};
use nanopos_id::filters::response::Complex;
use nanopos_id::filters::{Biquad, BiquadState};
use nanopos_id::hal::StageBoard;
use nanopos_id::instrument::{disagreement, trusted_ekf_estimate, Status};
use nanopos_id::pipeline::PipelineSettings;
use nanopos_id::StageParams;
use std::f64::consts::PI;

/// The sample rate, Hz.
const FS: f64 = 1e4;

/// The analog chain's response at `f_hz` from the DAC's code to the ADC's reading, the stage's mode left out, as the
/// pipeline's settings describe it (what the firmware knows of the hardware, and all a controller on the board has):
/// the reconstruction and anti-aliasing filters (2nd-order Butterworth at the replicas' cut-offs), the amplifier's
/// and the sensor's lags (the lag replica's poles), and 1.5 samples (the DAC's hold, half a sample on average, and
/// the sample a command waits in the DAC's holding register).
fn chain(settings: &PipelineSettings, f_hz: f64) -> Complex {
    let delay = Complex::expj(-2.0 * PI * f_hz * 1.5 / settings.sample_rate_hz);
    settings.reconstruction.analog(f_hz) * settings.antialias.analog(f_hz) * settings.lags.analog(f_hz) * delay
}

/// The resonant damping controller.
struct Damper {
    section: Biquad<f64>,
    state: BiquadState<f64>,
    /// The band-pass's damping ratio: wide (0.5) is robust to an estimate that is off, narrow acts less off the
    /// resonance.
    zeta_c: f64,
    /// The damping ratio to add.
    added_zeta: f64,
}

impl Damper {
    /// Off until tuned.
    fn new(added_zeta: f64, zeta_c: f64) -> Self {
        let off = Biquad { b: [0.0; 3], a: [0.0; 2] };
        Damper { section: off, state: BiquadState::default(), zeta_c, added_zeta }
    }

    /// Tuned for the stage `p` behind the chain `settings` describe.
    fn tune<T: nanopos_id::Real>(&mut self, p: &StageParams<T>, settings: &PipelineSettings) {
        let (p, zc): (StageParams<f64>, f64) = (p.cast(), self.zeta_c);
        let f0 = p.f0_hz();
        let h = chain(settings, f0);
        // The phase the controller needs at f0. The band-pass's there is atan((w_c^2 - w0^2) / (2 zeta_c w_c w0)),
        // within +-90 degrees: solved for w_c; a phase beyond (a chain lagging more than 180 degrees, as near its
        // filters' cut-off) is the other sign's, half a turn round, which has the same tangent.
        let need = -PI / 2.0 - h.arg();
        let (t, sign) = (need.tan(), need.cos().signum());
        let wc = 2.0 * PI * f0 * (zc * t + (zc * zc * t * t + 1.0).sqrt());
        let bp =
            bilinear2([0.0, 2.0 * zc * wc, 0.0], [wc * wc, 2.0 * zc * wc, 1.0], prewarp_constant(wc / 2.0 / PI, FS));
        let g = sign * 2.0 * self.added_zeta / (bp.response(f0, 1.0 / FS).abs() * h.abs() * (p.b0 / p.a0));
        self.section = Biquad { b: bp.b.map(|x| g * x), a: bp.a };
    }

    /// The command for this sample's reading, V.
    fn command(&mut self, y_um: f64) -> f64 {
        self.section.update(&mut self.state, y_um)
    }
}

/// The EKFs, the estimators a damping loop needs (the continuous-time RLS takes 13 s to follow a payload change).
type Ekfs = (Hekf<f64>, Cekf<f64>);

fn ekfs() -> Ekfs {
    let d = EkfDesign::default();
    (Hekf::new(d.design()), Cekf::new(d.design()))
}

/// The damping ratio of a stage whose resonance is at `w0` (rad/s), from its ring: `step(kick)` runs one sample with
/// `kick` V added to the command (the damper's, if any) and returns the reading, the excitation off (the estimators
/// starve and hold). 0.5 s to settle, the kick, the peaks of the ring over 0.2 s above a tenth of the first fitted by
/// `ln |y| = c - sigma t`.
fn ring_zeta(mut step: impl FnMut(f64) -> f64, w0: f64) -> f64 {
    for _ in 0..5000 {
        step(0.0);
    }
    let ys: Vec<f64> = (0..2000).map(|k| step(if k < 3 { 10.0 } else { 0.0 })).skip(10).collect();
    let mean = ys.iter().sum::<f64>() / ys.len() as f64;
    let d: Vec<f64> = ys.iter().map(|y| (y - mean).abs()).collect();
    let peaks: Vec<(f64, f64)> =
        (1..d.len() - 1).filter(|&i| d[i] > d[i - 1] && d[i] >= d[i + 1]).map(|i| (i as f64 / FS, d[i])).collect();
    let first = peaks[0].1;
    let pts: Vec<(f64, f64)> = peaks.into_iter().filter(|p| p.1 > 0.1 * first).map(|(t, a)| (t, a.ln())).collect();
    let n = pts.len() as f64;
    let (sx, sy, sxx, sxy) =
        pts.iter().fold((0.0, 0.0, 0.0, 0.0), |(a, b, c, d), p| (a + p.0, b + p.1, c + p.0 * p.0, d + p.0 * p.1));
    let sigma = -(n * sxy - sx * sy) / (n * sxx - sx * sx);
    sigma / w0
}

/// [`ring_zeta`] of a simulation with `damper` in its loop, its excitation turned off.
fn sim_ring_zeta(sim: &mut Simulation<Ekfs>, damper: &mut Damper, settings: &PipelineSettings) -> f64 {
    let quiet = PipelineSettings { excitation: ExcitationDesign::OFF, ..*settings };
    sim.config = quiet.design(&sim.board.description()).expect("the same pipeline, the excitation off");
    let w0 = sim.board.plant().params().a0.sqrt();
    ring_zeta(|kick| sim.step_adding(|y| damper.command(y) + kick).0.y_um, w0)
}

/// `samples` samples of the firmware's interrupt body on `lab` with `damper` in the loop, retuned every 0.1 s from
/// sample `from` on with what `rule` takes from the status snapshot, as a controller on the board would (the chain
/// from the pipeline's settings in force at the start), and `observe(k, lab)` after each sample: the retunes, the
/// first one's time (s) and the peak command (V).
fn lab_loop(
    lab: &mut Lab,
    damper: &mut Damper,
    samples: u64,
    from: u64,
    rule: impl Fn(&Status<f32>) -> Option<StageParams<f32>>,
    mut observe: impl FnMut(u64, &Lab),
) -> (u32, Option<f64>, f32) {
    let settings = *lab.ctl.settings();
    let (mut retunes, mut first, mut u_peak) = (0, None, 0.0f32);
    for k in 0..samples {
        if k >= from && k % 1000 == 0 {
            if let Some(p) = rule(&lab.isr.status()) {
                damper.tune(&p, &settings);
                retunes += 1;
                first = first.or(Some(k as f64 / FS));
            }
        }
        u_peak = u_peak.max(lab.isr.sample_adding(&mut lab.board, |y| damper.command(y as f64) as f32).u_v.abs());
        observe(k, lab);
    }
    (retunes, first, u_peak)
}

/// [`ring_zeta`] on `lab` with `damper` in the loop, its excitation turned off (`excite off`).
fn lab_ring_zeta(lab: &mut Lab, damper: &mut Damper) -> f64 {
    lab.send("excite off\n");
    let w0 = lab.board.plant().params().a0.sqrt();
    ring_zeta(
        |kick| lab.isr.sample_adding(&mut lab.board, |y| (damper.command(y as f64) + kick) as f32).y_um as f64,
        w0,
    )
}

/// The hybrid EKF's estimate when [`trusted_ekf_estimate`] gives it.
fn trusted(status: &Status<f32>) -> Option<StageParams<f32>> {
    trusted_ekf_estimate(status, 2)
}

/// The ring measures the stage's damping: open loop, over noise seeds 1-8 on both stages, within 5 % of the truth's
/// (measured: 0 to 2.6 % low; 0.01432 against 0.01460 with the payload, seed 1).
#[test]
fn the_ring_measures_the_stages_damping() {
    let mut worst = 0.0f64;
    for (seed, stage) in (1..=8).flat_map(|seed| [(seed, StageParams::PAYLOAD), (seed, StageParams::NO_PAYLOAD)]) {
        let (mut board, settings) = Scenario::Prbs.settings(1.0, seed);
        board.plant.before = stage;
        board.plant.change_at_sample = u64::MAX;
        let mut sim = Simulation::new(board, &settings, ekfs()).unwrap();
        let zeta = sim_ring_zeta(&mut sim, &mut Damper::new(0.0, 0.5), &settings);
        let truth = stage.a1 / (2.0 * stage.a0.sqrt());
        println!("open loop, noise seed {seed}: ring zeta {zeta:.5}, the truth's {truth:.5}");
        worst = worst.max((zeta / truth - 1.0).abs());
    }
    println!("worst: {:.1} %", 100.0 * worst);
    assert!(worst < 0.05, "{worst}");
}

/// `seconds` of the PRBS on `board` (its stage `before` for good) with `damper` in the loop from 2 s, retuned every
/// 0.1 s from the hybrid EKF's estimate while it adapts: the EKFs' mean errors over the last 10 s (a0, a1, b0,
/// relative), the peak command, and the ring's damping ratio at the end.
fn damped_run(board: BoardSettings, mut damper: Damper, seconds: u64) -> ([[f64; 3]; 2], f64, f64) {
    let (_, settings) = Scenario::Prbs.settings(seconds as f64, 1);
    let truth = board.plant.before;
    let mut sim = Simulation::new(board, &settings, ekfs()).unwrap();
    let (mut sums, mut n, mut u_peak) = ([[0.0; 3]; 2], 0.0, 0.0f64);
    let end = seconds * 10_000;
    for k in 0..end {
        let hekf = &sim.pipeline.estimators.0;
        if k >= 20_000 && k % 1000 == 0 && hekf.health().adaptation == Adaptation::Adapting {
            damper.tune(&hekf.params(), &settings);
        }
        let (_, out) = sim.step_adding(|y| damper.command(y));
        u_peak = u_peak.max(out.u_v.abs());
        if k >= end - 100_000 && k % 100 == 0 {
            let e = &sim.pipeline.estimators;
            for (s, p) in sums.iter_mut().zip([e.0.params(), e.1.params()]) {
                *s = [s[0] + p.a0, s[1] + p.a1, s[2] + p.b0];
            }
            n += 1.0;
        }
    }
    let rel = sums.map(|s| [s[0] / n / truth.a0 - 1.0, s[1] / n / truth.a1 - 1.0, s[2] / n / truth.b0 - 1.0]);
    (rel, u_peak, sim_ring_zeta(&mut sim, &mut damper, &settings))
}

/// The loop damps the stage tenfold, and the EKFs still identify it. On both stages (the payload on and off), with
/// 0.1 of damping asked for: the ring's damping ratio 0.0145 -> 0.161 with the payload, 0.0142 -> 0.149 without,
/// the command within 2.1 V (1.0 V open loop). The EKFs identify the stage from `u` to `y` whatever feeds `u`, but
/// the loop takes the resonance's response away from them and correlates `u` with the probe's noise: without the
/// board's second mode their errors stay within the PRBS goals (a0 0.008 %, b0 0.05 %, a1 0.15 %, from 0.007, 0.07
/// and 0.05 % open loop); with it, the second mode's share of what they see grows and its bias doubles (the payload
/// off: b0 +0.27 -> +0.59 %, a1 +0.22 -> +0.55 %), the payload on little changed (b0 -0.04 %, a1 +0.2 %).
#[test]
fn a_damping_loop_on_the_estimate_damps_the_stage_and_the_ekfs_still_identify_it() {
    for second_mode in [false, true] {
        for stage in [StageParams::PAYLOAD, StageParams::NO_PAYLOAD] {
            let mut board = BoardSettings::default();
            board.plant.before = stage;
            board.plant.change_at_sample = u64::MAX;
            if !second_mode {
                board.plant.second_mode = None;
            }
            let mut open = [[0.0; 3]; 2];
            for added in [0.0, 0.1] {
                let (rel, u_peak, zeta) = damped_run(board, Damper::new(added, 0.5), 20);
                let pct = |e: &[f64; 3]| e.map(|x| format!("{:+.3}%", 100.0 * x)).join(" ");
                println!(
                    "second mode {second_mode}, f0 {:.0} Hz, {added} asked: ring zeta {zeta:.4}, |u| <= {u_peak:.2} V; \
                     hekf a0 a1 b0 {}, ekf {}",
                    stage.f0_hz(),
                    pct(&rel[0]),
                    pct(&rel[1])
                );
                assert!(u_peak < 2.5, "{u_peak}");
                if added == 0.0 {
                    open = rel;
                    continue;
                }
                assert!(zeta > 0.13, "the loop damps: {zeta}");
                for (e, o) in rel.iter().zip(&open) {
                    assert!(e[0].abs() < 3e-4, "a0 {e:?}");
                    if second_mode {
                        // The second mode's bias, grown: by at most 0.4 % (b0) and 0.4 % (a1) from open loop.
                        assert!((e[2] - o[2]).abs() < 4e-3 && (e[1] - o[1]).abs() < 4e-3, "{e:?} from {o:?}");
                    } else {
                        assert!(e[2].abs() < 1e-3 && e[1].abs() < 1e-2, "the PRBS goals in the loop: {e:?}");
                    }
                }
            }
        }
    }
}

/// What retuning from the estimate is for: through the paper's experiment (the payload removed at 100 s, 423 Hz ->
/// 483 Hz), the loop retuned from the hybrid EKF keeps its damping, 0.153 at the end, where the same loop tuned once
/// on the payload's stage (at 2 s) and left is down to 0.083; with a narrower band-pass (`zeta_c` 0.15, which acts
/// less away from the resonance and so depends more on where it is) 0.067 against 0.021. In the loop the hybrid EKF
/// relocks within 1 % of the truth's a0 and b0 0.07-0.17 s after the change (0.21 s open loop in the `paper` table).
#[test]
fn the_loop_retuned_from_the_estimate_keeps_its_damping_through_the_payload_change() {
    for zeta_c in [0.5, 0.15] {
        let mut zetas = Vec::new();
        for adaptive in [true, false] {
            let (board, settings) = Scenario::Prbs.settings(200.0, 1);
            let mut sim = Simulation::new(board, &settings, ekfs()).unwrap();
            let mut damper = Damper::new(0.1, zeta_c);
            let mut relock = None;
            for k in 0..2_000_000u64 {
                let hekf = &sim.pipeline.estimators.0;
                if k >= 20_000 && k % 1000 == 0 && (adaptive || k == 20_000) {
                    assert_eq!(hekf.health().adaptation, Adaptation::Adapting);
                    damper.tune(&hekf.params(), &settings);
                }
                let (r, out) = sim.step_adding(|y| damper.command(y));
                assert!(out.faults.is_empty() && out.u_v.abs() < 2.5, "{k}: {out:?}");
                if k >= 1_000_000 {
                    let p = sim.pipeline.estimators.0.params();
                    let near = (p.a0 / r.truth.a0 - 1.0).abs() < 0.01 && (p.b0 / r.truth.b0 - 1.0).abs() < 0.01;
                    relock = if near { relock.or(Some((k - 1_000_000) as f64 / FS)) } else { None };
                }
            }
            let zeta = sim_ring_zeta(&mut sim, &mut damper, &settings);
            println!(
                "zeta_c {zeta_c}, retuned from the estimate {adaptive}: ring zeta at the end {zeta:.4}; hekf relocked \
                 {relock:?} s"
            );
            let relock = relock.expect("the hybrid EKF relocks in the loop");
            assert!(relock < 0.5, "{relock}");
            zetas.push(zeta);
        }
        assert!(zetas[0] > 1.5 * zetas[1], "{zeta_c}: {zetas:?}");
        if zeta_c == 0.5 {
            assert!(zetas[0] > 0.13 && zetas[1] < 0.1, "{zetas:?}");
        }
    }
}

/// The stage at 1 kHz of `tests/instrument.rs`: damping ratio 0.01, static gain 0.05 um/V. From the paper's initial
/// parameters (390 Hz) both EKFs settle on a wrong solution there (`b0` of the wrong sign, `f0` near 370 Hz).
const KHZ_STAGE: StageParams<f64> = StageParams { a0: KHZ_W * KHZ_W, a1: 0.02 * KHZ_W, b0: 0.05 * KHZ_W * KHZ_W };
const KHZ_W: f64 = 2.0 * PI * 1000.0;

/// A controller must not follow an EKF the ARX or the RLS has not confirmed. The firmware's interrupt body (f32,
/// `Lab`), the damper retuned at 10 Hz from 2 s on from the hybrid EKF's estimate in the status snapshot, as a
/// controller on the board would, by one of two rules. "No disagreement" ([`disagreement`] is `None` and the hybrid EKF
/// adapts): on the 1 kHz stage the comparison has no verdict from 2.1 to 10.3 s (the RLS, converging, apart from the
/// ARX), the rule lets the wrong estimate through from 2.2 s, and the loop drives the output to its clamp (8.78 V, the
/// DAC's reach, within the 10 V limits; 3 675 samples limited; with a DAC reaching 10 V, 4 040, and the loop then ran
/// at 2-6 V and pushed the hybrid EKF further off, f0 362 -> 292 Hz). [`trusted_ekf_estimate`] (a verdict, and it is
/// agreement): never retuned there, the output the PRBS's 1 V; on the paper's stage, where the verdict is agreement
/// throughout, both rules retune every 0.1 s and the loop damps as in the tests above (0.150). From the start instead
/// of 2 s, the trusted rule took the initial parameters (every estimator starts at them, so they agree) and that loop
/// left the 1 kHz mode undamped (-0.0001), the command up to 5.4 V, 11 286 samples limited, until the rule asked for
/// a model that explains the measurement ([`nanopos_id::instrument::response_ratio`]): before the first sample there
/// is no innovation RMS, and from 0.1 s on the EKFs disagreed there (their ratio 0 to 5), so it never retunes now. A
/// controller should still give the estimators time after a start or a restart: agreement at the initial
/// parameters is no evidence. And on the 1 kHz stage taken as the README's "Another stage" says
/// (`tune stage arx` after 5 s, 2 s for the EKFs), the trusted rule follows the hybrid EKF from then on: 0.010 -> 0.028
/// with 0.1 asked for, the command within 4.7 V. The chain lags about 240 degrees there (its 1 kHz filters at their
/// cut-off), so the band-pass takes the other sign, and a gain several times the paper stage's makes up for the
/// filters' and the stage's smaller gains: the simple design gets a third of what it asks there.
#[test]
fn a_controller_follows_an_ekf_only_once_a_reference_confirms_it() {
    let naive = |s: &Status<f32>| {
        let (p, h) = s.estimates[2];
        (disagreement(s).is_none() && h.adaptation == Adaptation::Adapting).then_some(p)
    };
    /// Whether, and from what, the controller retunes.
    type Rule<'a> = &'a dyn Fn(&Status<f32>) -> Option<StageParams<f32>>;
    // (name, rule, the first sample it may retune at)
    let rules: [(&str, Rule, u64); 3] =
        [("no disagreement", &naive, 20_000), ("trusted", &trusted, 20_000), ("trusted from the start", &trusted, 0)];
    for (stage, name) in [(Some(KHZ_STAGE), "1 kHz"), (None, "paper")] {
        for (rule, take, from) in rules {
            if name == "paper" && from == 0 {
                continue;
            }
            let mut lab = Lab::with_stage(stage);
            let mut damper = Damper::new(0.1, 0.5);
            let (retunes, first, u_peak) = lab_loop(&mut lab, &mut damper, 200_000, from, take, |_, _| ());
            let limited = lab.isr.status().counters.limited;
            let zeta = lab_ring_zeta(&mut lab, &mut damper);
            println!(
                "{name}, {rule}: {retunes} retunes (the first at {first:?} s), |u| <= {u_peak:.2} V, {limited} samples \
                 limited; the ring's damping ratio after {zeta:.4}"
            );
            match (name, rule) {
                // To the clamp: the DAC's reach (8.78 V), within the output limits (10 V).
                ("1 kHz", "no disagreement") => {
                    let clamp = lab.isr.config().max_v;
                    assert!(retunes > 0 && u_peak >= clamp - 0.01 && limited > 1000, "{u_peak} {clamp}")
                }
                ("1 kHz", _) => assert!(retunes == 0 && u_peak <= 1.01 && limited == 0, "{rule}: {retunes}"),
                _ => assert!(retunes == 180 && u_peak < 2.5 && zeta > 0.13),
            }
        }
    }
    // The 1 kHz stage the way the README's "Another stage" takes it: 5 s, `tune stage arx` (the EKFs restarted at the
    // ARX's estimate, the pre-filter centred there), 2 s, then the trusted rule.
    let mut lab = Lab::with_stage(Some(KHZ_STAGE));
    lab.run(50_000);
    assert!(lab.send("tune stage arx\n").contains("ok tune stage"));
    lab.run(20_000);
    let mut damper = Damper::new(0.1, 0.5);
    let (retunes, _, u_peak) = lab_loop(&mut lab, &mut damper, 100_000, 0, trusted, |_, _| ());
    let zeta = lab_ring_zeta(&mut lab, &mut damper);
    println!(
        "1 kHz after tune stage arx, trusted: {retunes} retunes, |u| <= {u_peak:.2} V; the ring's damping ratio \
         {zeta:.4}"
    );
    assert!(retunes == 100 && u_peak < 6.0 && zeta > 0.02, "{retunes} {u_peak} {zeta}");
}

/// Under a scan: the paper's smoothed triangle (1 V, 10 Hz, the `triangle` tuning, Q1), the firmware's interrupt body,
/// the payload removed at 100 s, the loop retuned at 10 Hz from 2 s on by [`trusted_ekf_estimate`] (agreement
/// throughout: 1 980 retunes). The ring's damping ratio at 200 s 0.0142 open loop, 0.152 in the loop; the command
/// within 1.01 V (the triangle puts little near the resonance for the loop to answer). The hybrid EKF's window
/// means, a0 / b0 against the truth: open loop 75-100 s -0.09 / +2.86 %, 175-200 s -0.07 / +2.78 % (b0 the board's
/// second mode's, as in the `paper` table); in the loop -0.96 / -1.53 % and +1.45 / +1.29 %. The triangle hardly
/// excites the resonance, and the loop takes away what it does: a0 moves by up to 1.5 %, b0 comes nearer the truth.
#[test]
fn the_loop_keeps_damping_under_a_scan_through_the_payload_change() {
    for added_zeta in [0.0, 0.1] {
        let mut lab = Lab::new();
        for command in ["tuning triangle\n", "excite triangle 1 10\n"] {
            assert!(lab.send(command).starts_with("ok"), "{command}");
        }
        let mut damper = Damper::new(added_zeta, 0.5);
        // Sums of the hybrid EKF's relative errors of a0 and b0 over 75-100 s and 175-200 s, at 100 Hz (the truth
        // after the sample is the sample's in both: the payload comes off at 100 s).
        let mut windows = [[0.0; 2]; 2];
        let observe = |k: u64, lab: &Lab| {
            let window = match k {
                750_000..1_000_000 => 0,
                1_750_000..2_000_000 => 1,
                _ => return,
            };
            if k % 100 == 0 {
                let (p, truth) = (lab.isr.status().estimates[2].0, lab.board.plant().params());
                windows[window][0] += (p.a0 as f64 / truth.a0 - 1.0) / 2500.0;
                windows[window][1] += (p.b0 as f64 / truth.b0 - 1.0) / 2500.0;
            }
        };
        let (retunes, _, u_peak) = lab_loop(&mut lab, &mut damper, 2_000_000, 20_000, trusted, observe);
        let zeta = lab_ring_zeta(&mut lab, &mut damper);
        let pct = |w: [f64; 2]| format!("{:+.2} / {:+.2} %", 100.0 * w[0], 100.0 * w[1]);
        println!(
            "triangle, {added_zeta} asked: {retunes} retunes, |u| <= {u_peak:.2} V, the ring's damping ratio at the \
             end {zeta:.4}; hekf a0 / b0 75-100 s {}, 175-200 s {}",
            pct(windows[0]),
            pct(windows[1])
        );
        assert!(retunes == 1980 && u_peak < 1.1, "{retunes} {u_peak}");
        if added_zeta > 0.0 {
            assert!(zeta > 0.13, "{zeta}");
            assert!(windows.iter().all(|w| w[0].abs() < 0.03 && w[1].abs() < 0.03), "{windows:?}");
        }
    }
}

/// Across stages: the stages of "Which estimator for which stage" (damping ratio 0.01, 0.05 um/V), the hybrid EKF
/// started at the stage with the pre-filter on it, the loop (0.1 asked for) following the trusted estimate from 2 s,
/// 10 s. The ring's damping ratio (open loop 0.0092-0.0099 for 0.01: the ring method holds up to 1.3 kHz, 7.7 samples
/// a cycle) in the loop: 300 Hz 0.161, 450 Hz 0.157, 600 Hz 0.140, while the chain lags less than 150 degrees there
/// (68, 104, 142); 800 Hz 0.074, 1 kHz 0.028, 1.3 kHz 0.060, around the filters' cut-off, where they lag 190-300
/// degrees and take the gain away: the simple design's range on this board. The command within 2.4 V up to 600 Hz,
/// 4.7 V beyond. At 1.6 kHz (6 samples a cycle) the ring method fails (it read 0.0005 open loop) and with the loop
/// the command reached 7.9 V: measured while writing this test, not asserted, not tried further.
#[test]
fn the_loops_damping_across_stages() {
    for (f0, least) in [(300.0, 0.13), (450.0, 0.13), (600.0, 0.12), (800.0, 0.05), (1000.0, 0.02), (1300.0, 0.04)] {
        let w = 2.0 * PI * f0;
        let stage = StageParams { a0: w * w, a1: 0.02 * w, b0: 0.05 * w * w };
        let mut figures = Vec::new();
        for added_zeta in [0.0, 0.1] {
            let mut lab = Lab::with_stage(Some(stage));
            let start_there = [
                format!("tune initial {} {} {}\n", stage.b0, stage.a1, stage.a0),
                format!("tune prefilter 100 {f0} 0.1\n"),
            ];
            for command in start_there {
                let reply = lab.send(&command);
                assert!(reply.lines().last().is_some_and(|l| l.starts_with("ok tune")), "{command}: {reply}");
            }
            let mut damper = Damper::new(added_zeta, 0.5);
            let (retunes, _, u_peak) = lab_loop(&mut lab, &mut damper, 100_000, 20_000, trusted, |_, _| ());
            let zeta = lab_ring_zeta(&mut lab, &mut damper);
            figures.push(format!("{zeta:.4} ({retunes} retunes, |u| <= {u_peak:.2} V)"));
            assert_eq!(retunes, 80, "{f0} Hz: the estimate trusted from 2 s on");
            if added_zeta == 0.0 {
                assert!((zeta / 0.01 - 1.0).abs() < 0.1, "{f0} Hz, open loop: {zeta}");
            } else {
                assert!(zeta > least && u_peak < 5.0, "{f0} Hz: {zeta} {u_peak}");
            }
        }
        let lag = (-chain(&Lab::settings(None).1, f0).arg().to_degrees()).rem_euclid(360.0);
        println!("{f0} Hz (the chain lags {lag:.0} degrees): open loop {}, in the loop {}", figures[0], figures[1]);
    }
}
