//! The simulated stage against independent references: the float64 reference's data, fine numerical integration,
//! and a frequency sweep through the real pipeline.

use hal_sim::board::{BoardSettings, SimBoard, Tone};
use hal_sim::noise::NormalStream;
use hal_sim::plant::{Plant, PlantSettings, STATES};
use hal_sim::sim::{Scenario, Simulation};
use nanopos_id::excitation::{ExcitationDesign, ExcitationState};
use nanopos_id::hal::{run_sample, StageBoard};
use nanopos_id::pipeline::PipelineSettings;
use nanopos_id::StageParams;

/// `data_fingerprint` of `../shared/golden/paper-reference.json` (float64 reference, numpy), copied here so the
/// test stands without the shared folder: ideal ZOH plant, Table I parameters, switch at 100 s, noise 1.25 nm. Its
/// excitation and noise stream are the scenario's, as `simulate` and `paper` run it by default (seed 1 for the
/// PRBS, 2 for the triangle).
struct Fingerprint {
    scenario: Scenario,
    segment_samples: u64,
    u_first5: [f64; 5],
    y_first5: [f64; 5],
    u_sum: f64,
    y_sum: f64,
    y_sumsq: f64,
    x1_at_end_seg1: f64,
}

const PRBS_SEG100: Fingerprint = Fingerprint {
    scenario: Scenario::Prbs,
    segment_samples: 1_000_000,
    u_first5: [-1.0; 5],
    y_first5: [
        -4.283415223981393e-05,
        -0.005621691423114443,
        -0.01882739804842363,
        -0.03307262771475241,
        -0.058078469739104,
    ],
    u_sum: -930.0,
    y_sum: -107.24826590377349,
    y_sumsq: 551865.9343335293,
    x1_at_end_seg1: 0.4228771749704778,
};

const TRIANGLE_SEG100: Fingerprint = Fingerprint {
    scenario: Scenario::Triangle,
    segment_samples: 1_000_000,
    u_first5: [0.0, 0.003976180515826248, 0.007961460501146928, 0.01196146456481152, 0.015976194060673722],
    y_first5: [
        -8.932528350125886e-06,
        -0.0016718988040809587,
        0.00017863928538707925,
        -0.001595828384749815,
        -0.0004015881358200443,
    ],
    u_sum: -6.693312570860144e-11,
    y_sum: -1.8501381991254746,
    y_sumsq: 8880.39720218678,
    x1_at_end_seg1: -0.0008380340093454559,
};

fn regenerate_and_compare(fp: &Fingerprint) {
    let gen = fp.scenario.excitation().design::<f64>(10_000.0);
    let mut ex = ExcitationState::default();
    let mut plant = Plant::new(PlantSettings::ideal(StageParams::PAYLOAD, StageParams::NO_PAYLOAD, fp.segment_samples));
    let mut noise = NormalStream::new(fp.scenario.default_seed());
    let (mut u_sum, mut y_sum, mut y_sumsq) = (0.0, 0.0, 0.0);
    for k in 0..2 * fp.segment_samples {
        let y = plant.output_um() + 1.25e-3 * noise.next_normal();
        let u = gen.next(&mut ex);
        if k < 5 {
            // The triangle's recurrence and the reference's direct sum round differently in the last bit.
            assert!((u - fp.u_first5[k as usize]).abs() < 1e-15, "u[{k}] = {u:e}");
            // Same formula, same order of operations up to the matrix exponential (scipy's Pade vs our Taylor):
            // agreement to a few ulps of the noise term.
            assert!(
                (y - fp.y_first5[k as usize]).abs() < 1e-15,
                "y[{k}] = {y:e}, reference {:e}",
                fp.y_first5[k as usize]
            );
        }
        u_sum += u;
        y_sum += y;
        y_sumsq += y * y;
        plant.advance(u);
        if plant.sample() == fp.segment_samples - 1 {
            // The last sample of the first segment. A million ZOH steps: the Phi rounding difference (~1e-16 per
            // step) is forgotten within the mode's ~25 ms memory, so the states agree to ~1e-14.
            let x1 = plant.stage_x1_um();
            assert!(
                (x1 - fp.x1_at_end_seg1).abs() < 1e-12,
                "x1 at the end of segment 1: {x1} vs {}",
                fp.x1_at_end_seg1
            );
        }
    }
    // u: PRBS sums are exact integers; the triangle's sum of 2e6 values of size 1 carries ~1e-10 of rounding.
    assert!((u_sum - fp.u_sum).abs() < 1e-9, "u_sum {u_sum} vs {}", fp.u_sum);
    assert!((y_sum / fp.y_sum - 1.0).abs() < 1e-9, "y_sum {y_sum} vs {}", fp.y_sum);
    assert!((y_sumsq / fp.y_sumsq - 1.0).abs() < 1e-10, "y_sumsq {y_sumsq} vs {}", fp.y_sumsq);
}

#[test]
fn ideal_plant_regenerates_the_reference_prbs_data() {
    regenerate_and_compare(&PRBS_SEG100);
}

#[test]
fn ideal_plant_regenerates_the_reference_triangle_data() {
    regenerate_and_compare(&TRIANGLE_SEG100);
}

#[test]
fn zoh_plant_matches_a_finely_integrated_analog_chain() {
    // The whole chain (filters, amplifier, two modes, sensor) under a held, changing input, against RK4 at T/2000.
    let settings = PlantSettings::default();
    let (a, b, c) = settings.continuous(&settings.before);
    let f = |x: &[f64; STATES], u: f64| -> [f64; STATES] {
        std::array::from_fn(|i| (0..STATES).map(|j| a[i][j] * x[j]).sum::<f64>() + b[i] * u)
    };
    let mut plant = Plant::new(settings);
    let mut x = [0.0; STATES];
    let sub = 2000;
    let h = settings.sample_period_s / sub as f64;
    let (mut worst, mut peak) = (0.0f64, 0.0f64);
    for k in 0..60 {
        let u = [1.0, -1.0, 0.5, 0.0, 2.0][k % 5];
        for _ in 0..sub {
            let k1 = f(&x, u);
            let k2 = f(&std::array::from_fn(|i| x[i] + 0.5 * h * k1[i]), u);
            let k3 = f(&std::array::from_fn(|i| x[i] + 0.5 * h * k2[i]), u);
            let k4 = f(&std::array::from_fn(|i| x[i] + h * k3[i]), u);
            x = std::array::from_fn(|i| x[i] + h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]));
        }
        plant.advance(u);
        let y_ref: f64 = c.iter().zip(x.iter()).map(|(ci, xi)| ci * xi).sum();
        worst = worst.max((plant.output_um() - y_ref).abs());
        peak = peak.max(y_ref.abs());
    }
    // RK4 at h = 5e-8 s against the fastest pole (sensor, 6.3e5 rad/s): (w h)^4 / 120 ~ 8e-9 per step.
    assert!(worst < 1e-7 * peak, "worst {worst:e} of peak {peak:e}");
}

/// A held input settles, through every filter of the chain (each of unit static gain), at the stage's static
/// response `b0 / a0` plus the second mode's, with the input's sign: what the ZOH test above cannot see (it checks the
/// discretisation against the same continuous model) nor the sweep (magnitudes near the resonance, where the
/// second mode's 3.5 % of the static gain is a fraction of a percent).
#[test]
fn a_held_input_settles_at_the_two_modes_static_gains() {
    use hal_sim::plant::SecondMode;
    let full = PlantSettings::default();
    // The whole chain, and with each filter left out in turn: every block couples to the next with its own sign.
    let chains = [
        full,
        PlantSettings { reconstruction_hz: None, ..full },
        PlantSettings { amplifier_hz: None, ..full },
        PlantSettings { sensor_hz: None, ..full },
        PlantSettings { antialias_hz: None, ..full },
    ];
    for (params, chain) in
        [StageParams::PAYLOAD, StageParams::NO_PAYLOAD].into_iter().flat_map(|p| chains.map(|c| (p, c)))
    {
        for second_mode in [Some(SecondMode::default()), None] {
            let settings = PlantSettings { before: params, second_mode, ..chain };
            for u in [1.0, -2.5] {
                let mut plant = Plant::new(settings);
                // 1 s: the payload mode's envelope decays as exp(-a1 t / 2), to below 1e-16.
                for _ in 0..10_000 {
                    plant.advance(u);
                }
                let stage = u * params.b0 / params.a0;
                let want = stage + u * second_mode.map_or(0.0, |m| m.dc_gain_um_per_v);
                let (y, x1) = (plant.output_um(), plant.stage_x1_um());
                assert!((y / want - 1.0).abs() < 1e-9, "{settings:?} u {u}: y {y} um, want {want}");
                assert!((x1 / stage - 1.0).abs() < 1e-9, "{settings:?} u {u}: x1 {x1} um, want {stage}");
            }
        }
    }
}

/// Amplitude of `|Y/U|` at `f_hz` through the real pipeline and the simulated board: a stepped sine, settled, then
/// demodulated over a whole number of periods.
fn gain_at(board: BoardSettings, f_hz: f64) -> f64 {
    let pipeline = PipelineSettings { excitation: ExcitationDesign::sine(f_hz, 0.5), ..PipelineSettings::default() };
    let mut sim = Simulation::new(board, &pipeline, ()).unwrap();
    // 0.3 s is 11 time constants 1/(zeta w0) of the payload mode: the start transient is below 2e-5.
    for _ in 0..3000 {
        sim.step();
    }
    let periods = (0.3 * f_hz).round();
    let n = (periods * 10_000.0 / f_hz).round() as usize;
    let (mut yc, mut ys, mut uc, mut us) = (0.0, 0.0, 0.0, 0.0);
    for i in 0..n {
        let (r, _) = sim.step();
        let w = 2.0 * std::f64::consts::PI * f_hz * i as f64 / 10_000.0;
        yc += r.y_um * w.cos();
        ys += r.y_um * w.sin();
        uc += r.u_v * w.cos();
        us += r.u_v * w.sin();
    }
    (yc * yc + ys * ys).sqrt() / (uc * uc + us * us).sqrt()
}

fn resonance_from_sweep(board: BoardSettings) -> f64 {
    let coarse: Vec<f64> = (0..=40).map(|i| 350.0 + 5.0 * i as f64).collect();
    let best =
        coarse.iter().copied().map(|f| (f, gain_at(board, f))).fold((0.0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
    let fine: Vec<(f64, f64)> = (-16..=16).map(|i| best.0 + 0.25 * i as f64).map(|f| (f, gain_at(board, f))).collect();
    let i = (1..fine.len() - 1).max_by(|&a, &b| fine[a].1.total_cmp(&fine[b].1)).unwrap();
    // Parabola through the log-magnitudes of the top three points.
    let (l0, l1, l2) = (fine[i - 1].1.ln(), fine[i].1.ln(), fine[i + 1].1.ln());
    fine[i].0 + 0.25 * 0.5 * (l0 - l2) / (l0 - 2.0 * l1 + l2)
}

#[test]
fn simulated_stage_resonates_at_423_hz_with_and_at_483_hz_without_payload() {
    // The full board: both 1 kHz filters, amplifier and sensor bandwidth, second mode, converters, 1.25 nm noise.
    // The peak of |G| sits at f0 sqrt(1 - 2 zeta^2) (0.09 Hz below f0) and the filters' slope moves it by ~0.01 Hz.
    for (params, paper_hz) in [(StageParams::PAYLOAD, 423.0), (StageParams::NO_PAYLOAD, 483.0)] {
        let mut board = BoardSettings::default();
        board.plant.before = params;
        let peak = resonance_from_sweep(board);
        assert!((peak - params.f0_hz()).abs() < 1.0, "peak {peak} Hz, f0 {} Hz", params.f0_hz());
        assert!((peak - paper_hz).abs() < 1.0, "peak {peak} Hz, paper {paper_hz} Hz");
        eprintln!("resonance {peak:.2} Hz (f0 {:.2} Hz)", params.f0_hz());
    }
}

#[test]
fn payload_change_switches_parameters_and_kicks_the_stage() {
    let mut s = PlantSettings::ideal(StageParams::PAYLOAD, StageParams::NO_PAYLOAD, 10);
    s.bump_um_per_s = 300.0;
    let mut with_bump = Plant::new(s);
    s.bump_um_per_s = 0.0;
    let mut without = Plant::new(s);
    for _ in 0..10 {
        assert_eq!(with_bump.params(), StageParams::PAYLOAD);
        with_bump.advance(0.0);
        without.advance(0.0);
    }
    assert_eq!(with_bump.params(), StageParams::NO_PAYLOAD);
    with_bump.advance(0.0);
    without.advance(0.0);
    // One sample after a 300 um/s kick at rest: x1 ~ 300 um/s * 1e-4 s = 30 nm (less the spring's pull).
    let dx = with_bump.stage_x1_um() - without.stage_x1_um();
    assert!((dx - 0.03).abs() < 0.001, "{dx}");
}

/// Creep: after a step of the drive the displacement keeps growing, about 1 % of the step per decade of time from
/// 0.1 s to 100 s (the default), by the lags' sum `1 + 0.01 * sum_i (1 - exp(-t / tau_i))` exactly; without creep it
/// holds.
#[test]
fn creep_grows_the_step_response_by_a_share_per_decade() {
    let ideal = PlantSettings::ideal(StageParams::PAYLOAD, StageParams::PAYLOAD, u64::MAX);
    let creeping = PlantSettings { creep: Some(hal_sim::plant::Creep::default()), ..ideal };
    let static_um = StageParams::PAYLOAD.dc_gain();
    let at_times = |settings: PlantSettings| {
        let mut plant = Plant::new(settings);
        let mut out = Vec::new();
        for k in 1..=1_000_000u64 {
            plant.advance(1.0);
            if [10_000, 100_000, 1_000_000].contains(&k) {
                out.push(plant.output_um() / static_um);
            }
        }
        out
    };
    let (with, without) = (at_times(creeping), at_times(ideal));
    let law = |t: f64| 1.0 + 0.01 * (0..4).map(|i| 1.0 - (-t / (0.1 * 10f64.powi(i))).exp()).sum::<f64>();
    eprintln!("step response over its static value at 1, 10, 100 s: with creep {with:?}, without {without:?}");
    for (got, t) in with.iter().zip([1.0, 10.0, 100.0]) {
        // The lags enter with their value at each sample's start: a delay of half a sample, 5e-5 s.
        assert!((got - law(t)).abs() < 1e-6, "{t} s: {got} against {}", law(t));
    }
    for decade in [with[1] - with[0], with[2] - with[1]] {
        assert!((0.008..0.011).contains(&decade), "{decade}");
    }
    assert!(without.iter().all(|r| (r - 1.0).abs() < 1e-9), "{without:?}");
}

/// The gain's drift: under a constant drive the displacement follows the truth's static gain `b0 / a0` as `b0`
/// drifts (1 % per second here, 10 % in 10 s), lagging it by the stage's own `a1 / a0` (11 us) and by half a sample
/// (the gain is held over each sample from its start, as the drive is): 6e-7 of it at this rate, measured over 1-6 s
/// and 7-10 s; the payload's change at 6 s carries the drift over. A falling gain stops at zero.
#[test]
fn a_drifting_gain_moves_the_static_response_with_the_truth() {
    let ideal = PlantSettings::ideal(StageParams::PAYLOAD, StageParams::NO_PAYLOAD, 60_000);
    let mut plant = Plant::new(PlantSettings { gain_drift_per_s: 0.01, ..ideal });
    let mut worst: f64 = 0.0;
    for k in 1..=100_000u64 {
        plant.advance(1.0);
        // After the start's and the change's rings (time constant 2 / a1: 26 ms and 23 ms) have died out.
        if (10_000..60_000).contains(&k) || k >= 70_000 {
            worst = worst.max((plant.output_um() / plant.params().dc_gain() - 1.0).abs());
        }
    }
    let p = plant.params();
    eprintln!("drifting gain: b0 at 10 s {} (x {}), output within {worst:.1e} of its static gain", p.b0, p.b0 / 1.07e6);
    assert!((p.b0 / (1.07e6 * 1.1) - 1.0).abs() < 1e-12 && p.a0 == 9.21e6 && p.a1 == 86.8, "{p:?}");
    assert!(worst < 1e-6, "{worst}");
    // A falling gain stops at zero (here after 1 s): no drive reaches the stage, whose output rings down.
    let mut falling = Plant::new(PlantSettings { gain_drift_per_s: -1.0, ..ideal });
    for _ in 0..15_000 {
        falling.advance(1.0);
    }
    assert_eq!(falling.params().b0, 0.0);
    assert!(falling.output_um().abs() < 1e-6, "{}", falling.output_um());
}

#[test]
fn hysteresis_makes_the_static_response_depend_on_the_path() {
    let settings = PlantSettings {
        hysteresis: Some(hal_sim::plant::Hysteresis::default()),
        ..PlantSettings::ideal(StageParams::PAYLOAD, StageParams::PAYLOAD, u64::MAX)
    };
    let settle = |plant: &mut Plant, u: f64| {
        for _ in 0..20_000 {
            plant.advance(u);
        }
        plant.output_um()
    };
    let mut up = Plant::new(settings);
    let bottom = settle(&mut up, -1.0);
    let from_below = settle(&mut up, 0.0);
    let mut down = Plant::new(settings);
    let top = settle(&mut down, 1.0);
    let from_above = settle(&mut down, 0.0);
    // 10 % of the drive through plays of half-widths r_i = 0.5 V i / n, i = 1..n (their mean 0.5 (n + 1) / 2n V): a
    // swing of 1 V beyond each leaves each play r_i behind the input, so at -1 and +1 V the drive is short by 10 % of
    // the mean width, and at 0 V it keeps that much of where it came from. The two branches at 0 V differ by
    // 0.1 * 0.281 V * 2 * 0.114 um/V, 6.4 nm.
    let h = hal_sim::plant::Hysteresis::default();
    let n = hal_sim::plant::PLAYS as f64;
    let lag_v = h.fraction * h.width_v * (n + 1.0) / (2.0 * n);
    let gain = StageParams::PAYLOAD.b0 / StageParams::PAYLOAD.a0;
    for (y, drive_v) in [(top, 1.0 - lag_v), (from_above, lag_v), (bottom, lag_v - 1.0), (from_below, -lag_v)] {
        assert!((y - drive_v * gain).abs() < 1e-12, "{y} um, want {} um", drive_v * gain);
    }
    assert!(from_above - from_below > 0.006, "{from_above} vs {from_below}");
    let linear = PlantSettings::ideal(StageParams::PAYLOAD, StageParams::PAYLOAD, u64::MAX);
    let (mut a, mut b) = (Plant::new(linear), Plant::new(linear));
    settle(&mut a, -1.0);
    settle(&mut b, 1.0);
    assert!((settle(&mut a, 0.0) - settle(&mut b, 0.0)).abs() < 1e-9);
}

/// `n` readings of a board at rest (no excitation, the output at the safe code) through the pipeline, um.
fn readings_at_rest(settings: BoardSettings, n: usize) -> (SimBoard, Vec<f64>) {
    let mut board = SimBoard::new(settings);
    let settings = PipelineSettings { excitation: ExcitationDesign::OFF, ..PipelineSettings::default() };
    let cfg = settings.design::<f64>(&board.description()).unwrap();
    let mut pipeline = nanopos_id::pipeline::Pipeline::new(&cfg, ());
    let y = (0..n).map(|_| run_sample(&mut board, &mut pipeline, &cfg).y_um).collect();
    (board, y)
}

/// The RMS about the mean and the kurtosis of `y`.
fn rms_and_kurtosis(y: &[f64]) -> (f64, f64) {
    let mean = y.iter().sum::<f64>() / y.len() as f64;
    let m = |p: i32| y.iter().map(|v| (v - mean).powi(p)).sum::<f64>() / y.len() as f64;
    (m(2).sqrt(), m(4) / m(2).powi(2))
}

#[test]
fn noise_floor_at_rest_is_the_modelled_one() {
    // Stage at rest, output at the safe code: the readings' spread is the probe noise, the averaged ADC noise and
    // the 16-bit quantisation, which SimBoard::noise_floor_um adds up (3.3 nm with the defaults).
    let (board, y) = readings_at_rest(BoardSettings::default(), 200_000);
    let rms = rms_and_kurtosis(&y).0;
    let model = board.noise_floor_um();
    eprintln!("noise floor: measured {:.3} nm, model {:.3} nm", rms * 1e3, model * 1e3);
    assert!((model * 1e3 - 3.33).abs() < 0.01);
    // The quantisation term assumes a uniform error, which the 1-code-RMS dither makes nearly exact; the sample
    // estimate of an RMS from 2e5 values has a 0.2 % standard error.
    assert!((rms / model - 1.0).abs() < 0.01, "measured {rms}, model {model}");
}

/// What the simulated board adds to the reading, each as its settings say: Student's t noise at the RMS set, with
/// its heavy tails (kurtosis 9 for 5 degrees of freedom, 3 for Gaussian noise); mains hum as `A sin(2 pi f t)` from
/// the first sample, each tone at its amplitude and phase. And what the board reports: its sample rate, its settings
/// and the voltage it drove, which is the pipeline's `u_v`.
#[test]
fn the_reading_carries_the_noise_and_the_hum_as_set() {
    // 50 nm of noise, far above the ADC's 3 nm: the tails are the noise's.
    let noisy = |dof| BoardSettings { noise_um_rms: 0.05, noise_tail_dof: dof, ..BoardSettings::default() };
    for (dof, kurtosis) in [(None, 2.9..3.1), (Some(5), 5.0..20.0)] {
        let (board, y) = readings_at_rest(noisy(dof), 200_000);
        let (rms, k) = rms_and_kurtosis(&y);
        eprintln!(
            "noise {dof:?}: rms {:.3} nm (model {:.3}), kurtosis {k:.2}",
            rms * 1e3,
            board.noise_floor_um() * 1e3
        );
        assert!((rms / board.noise_floor_um() - 1.0).abs() < 0.02, "{dof:?}: rms {rms}");
        assert!(kurtosis.contains(&k), "{dof:?}: kurtosis {k}");
    }
    // 20 s of hum: whole periods of both tones, so the stage's constant output drops out.
    let hum = [Tone { amplitude_um: 0.02, freq_hz: 50.0 }, Tone { amplitude_um: 0.01, freq_hz: 150.0 }];
    let (board, y) = readings_at_rest(BoardSettings { hum, ..BoardSettings::default() }, 200_000);
    assert_eq!(board.settings().hum, hum);
    let fs = board.sample_rate_hz();
    assert_eq!(fs, 10_000.0);
    for Tone { amplitude_um, freq_hz } in hum {
        let part = |phase: fn(f64) -> f64| {
            let w = 2.0 * std::f64::consts::PI * freq_hz / fs;
            2.0 / y.len() as f64 * y.iter().enumerate().map(|(k, v)| v * phase(w * k as f64)).sum::<f64>()
        };
        let (in_phase, quadrature) = (part(f64::sin), part(f64::cos));
        eprintln!("hum at {freq_hz} Hz: {in_phase:.6} um in phase, {quadrature:.2e} in quadrature");
        // The noise's share: 3.3 nm sqrt(2 / n), 1e-5 um. A sample late would put 2 pi f / fs of the amplitude, 6e-4
        // um at 50 Hz, in quadrature.
        assert!((in_phase - amplitude_um).abs() < 1e-4, "{freq_hz} Hz: {in_phase}");
        assert!(quadrature.abs() < 1e-4, "{freq_hz} Hz: {quadrature}");
    }
    let fast = PlantSettings { sample_period_s: 5e-5, ..PlantSettings::default() };
    assert_eq!(SimBoard::new(BoardSettings { plant: fast, ..BoardSettings::default() }).sample_rate_hz(), 20_000.0);
    // The voltage the board drove over each sample is the command the pipeline says was in effect, with the DAC's
    // holding register (the default) or without.
    for delay in [0, 1] {
        let delayed = BoardSettings { actuation_delay_samples: delay, ..BoardSettings::default() };
        let mut board = SimBoard::new(delayed);
        let cfg = PipelineSettings::default().design::<f64>(&board.description()).unwrap();
        let mut pipeline = nanopos_id::pipeline::Pipeline::new(&cfg, ());
        let mut moved = 0;
        for _ in 0..2_000 {
            let out = run_sample(&mut board, &mut pipeline, &cfg);
            assert!((board.last_u_v() - out.u_v).abs() < 1e-9, "{delay}: {} against {}", board.last_u_v(), out.u_v);
            moved += usize::from(out.u_v.abs() > 0.5);
        }
        assert!(moved > 1_000, "{delay}: {moved}");
        // A code written goes out now, or at the next write (mid-scale before the first).
        let mut board = SimBoard::new(delayed);
        let volts = |code: u32| {
            let dac = board.description().amplifier;
            board.settings().amplifier.command_v(code as f64 * dac.volts_per_code())
        };
        let (mid, high) = (volts(2048), volts(3000));
        board.write_amplifier(3000);
        assert_eq!(board.last_u_v(), if delay == 0 { high } else { mid }, "{delay}");
        board.write_amplifier(2048);
        assert_eq!(board.last_u_v(), if delay == 0 { mid } else { high }, "{delay}");
    }
}
