//! The analog signal chain of the paper's Fig. 4, as one linear state space sampled exactly:
//!
//! ```text
//! u (V, DAC out) -> [reconstruction: 2nd-order Butterworth, 1 kHz] -> [amplifier: 1st order, 10 kHz]
//!   -> stage: mode 1 (a0, a1, b0) + mode 2 (optional, in parallel) -> [sensor: 1st order, 100 kHz]
//!   -> [anti-aliasing: 2nd-order Butterworth, 1 kHz] -> y (um)
//! ```
//!
//! Gains: the amplifier's 20 V/V and the sensor's 5 um/V are inside `b0` (the paper's `u` is the amplifier input
//! and `y` the displacement), so the amplifier and sensor blocks here have unity gain and only their bandwidth.
//! Every block can be switched off (it is then a wire). The DAC output is held over each sample period, so the
//! zero-order-hold discretisation of the whole chain (`linalg::zoh`) is exact: `x[k+1] = Phi x[k] + Gam u[k]`.
//! The stage parameters change once, at the payload-removal sample, with the state carried over and an optional
//! velocity kick (the disturbance bump of taking the payload off by hand). The piezo's gain may drift at a steady
//! rate (as with temperature), scaling the drive and so `b0`.
//!
//! Optional piezo hysteresis acts on the held drive level: a Prandtl-Ishlinskii sum of play operators mixed with
//! the linear path. Being applied per sample to a held level, it keeps the sampling exact. Optional creep follows
//! it: the drive plus a share of its slow first-order lags, one per decade of time ([`Creep`]), so that after a step
//! the displacement keeps growing by about the same share per decade of time, as a piezo's does (the log law of
//! the datasheets). Each lag is advanced exactly over the sample and enters the held drive with its value at the
//! sample's start: over one sample it closes at most `T / first_tau_s` (1e-3 by default) of its distance to the
//! drive, so the step response is the lags' law delayed by about half a sample (within 1e-6 of it, `tests/plant.rs`).

use nanopos_id::linalg::{mat_vec, zoh, Mat};
use nanopos_id::StageParams;

/// States: 0-1 reconstruction, 2 amplifier, 3-4 mode 1 (x1 um, x2 um/s), 5-6 mode 2, 7 sensor, 8-9 anti-aliasing.
pub const STATES: usize = 10;
const X1: usize = 3;
const X2: usize = 4;

/// A second vibration mode, in parallel with the first.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SecondMode {
    /// Natural frequency, Hz.
    pub f0_hz: f64,
    /// Damping ratio.
    pub damping_ratio: f64,
    /// Static gain, um/V.
    pub dc_gain_um_per_v: f64,
}

impl Default for SecondMode {
    /// Illustrative: the paper's Fig. 3 shows a second mode above the first but gives no numbers. 1.9 kHz, 2 %
    /// damping, 3.5 % of the first mode's static gain: visible in a sweep, 20 dB down after the 1 kHz filters.
    fn default() -> Self {
        SecondMode { f0_hz: 1900.0, damping_ratio: 0.02, dc_gain_um_per_v: 0.004 }
    }
}

/// Piezo hysteresis: `v_out = (1 - fraction) v + fraction * mean_i play_{r_i}(v)`, `r_i = i * width_v / n`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hysteresis {
    /// Share of the drive that goes through the play operators (0-1).
    pub fraction: f64,
    /// Largest play half-width, V.
    pub width_v: f64,
}

impl Default for Hysteresis {
    fn default() -> Self {
        Hysteresis { fraction: 0.1, width_v: 0.5 }
    }
}

/// The hysteresis' play operators, `n` in [`Hysteresis`]'s formula.
pub const PLAYS: usize = 8;

/// Piezo creep: `v_out = v + per_decade * sum_i lag_i(v)`, `lag_i` the first-order lag of `v` with the time constant
/// `first_tau_s * 10^i`, `i = 0..CREEP_LAGS`. After a step of the drive the output grows by about `per_decade` of
/// the step per decade of time from `first_tau_s` to `first_tau_s * 10^(CREEP_LAGS - 1)`, and in all by
/// `CREEP_LAGS * per_decade`; at the stage's resonance the lags pass `per_decade / (2 pi f first_tau_s)`, below
/// 1e-4 of the drive by default.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Creep {
    /// Growth per decade of time, as a share of the step (0-1).
    pub per_decade: f64,
    /// The fastest lag's time constant, s.
    pub first_tau_s: f64,
}

impl Default for Creep {
    /// 1 % per decade from 0.1 s to 100 s: a piezo actuator's creep is typically 1 to 2 % of a step per decade of
    /// time.
    fn default() -> Self {
        Creep { per_decade: 0.01, first_tau_s: 0.1 }
    }
}

/// Lags of [`Creep`], one per decade.
pub const CREEP_LAGS: usize = 4;

/// Everything the simulated stage is made of. `Default` is the paper's stage, with every effect on except
/// hysteresis and creep.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlantSettings {
    /// Stage parameters before the payload change (paper Table I, with payload).
    pub before: StageParams<f64>,
    /// After the change (Table I, without payload).
    pub after: StageParams<f64>,
    /// Sample index at which `after` takes over (`u64::MAX`: never).
    pub change_at_sample: u64,
    /// Velocity kick at the change, um/s (0: none).
    pub bump_um_per_s: f64,
    /// Reconstruction filter cut-off (2nd-order Butterworth), Hz; `None`: off.
    pub reconstruction_hz: Option<f64>,
    /// Amplifier bandwidth (1st order), Hz; `None`: off.
    pub amplifier_hz: Option<f64>,
    /// Second mode; `None`: off.
    pub second_mode: Option<SecondMode>,
    /// Sensor bandwidth (1st order), Hz; `None`: off.
    pub sensor_hz: Option<f64>,
    /// Anti-aliasing filter cut-off (2nd-order Butterworth), Hz; `None`: off.
    pub antialias_hz: Option<f64>,
    /// Hysteresis; `None`: off.
    pub hysteresis: Option<Hysteresis>,
    /// Creep; `None`: off.
    pub creep: Option<Creep>,
    /// The piezo's gain drift (with temperature, SPEC section 1), relative, per second: the drive, and so the
    /// stage's `b0` and the second mode's gain alike, times `1 + gain_drift_per_s * t` (0: none), a falling gain
    /// stopping at zero. Applied to the
    /// drive at the DAC, ahead of the reconstruction filter and the amplifier: for a drift slow against their
    /// milliseconds the same as a drifting `b0` (the difference is the drift over their delay, below 1e-6 of `b0`
    /// at 0.1 % per second).
    pub gain_drift_per_s: f64,
    /// Sample period, s.
    pub sample_period_s: f64,
}

impl Default for PlantSettings {
    fn default() -> Self {
        PlantSettings {
            before: StageParams::PAYLOAD,
            after: StageParams::NO_PAYLOAD,
            change_at_sample: u64::MAX,
            bump_um_per_s: 300.0,
            reconstruction_hz: Some(1000.0),
            amplifier_hz: Some(10_000.0),
            second_mode: Some(SecondMode::default()),
            sensor_hz: Some(100_000.0),
            antialias_hz: Some(1000.0),
            hysteresis: None,
            creep: None,
            gain_drift_per_s: 0.0,
            sample_period_s: 1e-4,
        }
    }
}

impl PlantSettings {
    /// Only the stage model (1): no filters, no second mode, no bump, no hysteresis, no creep. The float64
    /// reference's plant.
    pub fn ideal(before: StageParams<f64>, after: StageParams<f64>, change_at_sample: u64) -> Self {
        PlantSettings {
            before,
            after,
            change_at_sample,
            bump_um_per_s: 0.0,
            reconstruction_hz: None,
            amplifier_hz: None,
            second_mode: None,
            sensor_hz: None,
            antialias_hz: None,
            hysteresis: None,
            creep: None,
            gain_drift_per_s: 0.0,
            sample_period_s: 1e-4,
        }
    }

    /// The continuous state space `(A, B, C)` for stage parameters `p`.
    pub fn continuous(&self, p: &StageParams<f64>) -> (Mat<STATES>, [f64; STATES], [f64; STATES]) {
        // A signal is a linear combination of the states and the input: value = c . x + d u.
        #[derive(Clone, Copy)]
        struct Signal {
            c: [f64; STATES],
            d: f64,
        }
        let state = |i: usize| {
            let mut c = [0.0; STATES];
            c[i] = 1.0;
            Signal { c, d: 0.0 }
        };
        let mut a = [[0.0; STATES]; STATES];
        let mut b = [0.0; STATES];
        let drive = |a: &mut Mat<STATES>, b: &mut [f64; STATES], row: usize, gain: f64, s: Signal| {
            for (aj, cj) in a[row].iter_mut().zip(s.c.iter()) {
                *aj += gain * cj;
            }
            b[row] += gain * s.d;
        };
        let w = |f_hz: f64| 2.0 * std::f64::consts::PI * f_hz;
        let butterworth = |a: &mut Mat<STATES>, b: &mut [f64; STATES], first: usize, fc: f64, input: Signal| {
            let wc = w(fc);
            a[first][first + 1] = 1.0;
            a[first + 1][first] = -wc * wc;
            a[first + 1][first + 1] = -std::f64::consts::SQRT_2 * wc;
            drive(a, b, first + 1, wc * wc, input);
            state(first)
        };

        let mut sig = Signal { c: [0.0; STATES], d: 1.0 };
        if let Some(fc) = self.reconstruction_hz {
            sig = butterworth(&mut a, &mut b, 0, fc, sig);
        }
        if let Some(fa) = self.amplifier_hz {
            a[2][2] = -w(fa);
            drive(&mut a, &mut b, 2, w(fa), sig);
            sig = state(2);
        }
        a[X1][X2] = 1.0;
        a[X2][X1] = -p.a0;
        a[X2][X2] = -p.a1;
        drive(&mut a, &mut b, X2, p.b0, sig);
        let mut displacement = state(X1);
        if let Some(m) = self.second_mode {
            let w2 = w(m.f0_hz);
            a[5][6] = 1.0;
            a[6][5] = -w2 * w2;
            a[6][6] = -2.0 * m.damping_ratio * w2;
            drive(&mut a, &mut b, 6, m.dc_gain_um_per_v * w2 * w2, sig);
            displacement.c[5] = 1.0;
        }
        sig = displacement;
        if let Some(fs) = self.sensor_hz {
            a[7][7] = -w(fs);
            drive(&mut a, &mut b, 7, w(fs), sig);
            sig = state(7);
        }
        if let Some(fc) = self.antialias_hz {
            sig = butterworth(&mut a, &mut b, 8, fc, sig);
        }
        debug_assert_eq!(sig.d, 0.0, "the chain is strictly proper");
        (a, b, sig.c)
    }

    fn discrete(&self, p: &StageParams<f64>) -> Discrete {
        let (a, b, c) = self.continuous(p);
        let (phi, psi) = zoh(&a, self.sample_period_s);
        Discrete { phi, gam: mat_vec(&psi, &b), c }
    }
}

#[derive(Clone, Debug)]
struct Discrete {
    phi: Mat<STATES>,
    gam: [f64; STATES],
    c: [f64; STATES],
}

/// The simulated analog chain.
#[derive(Clone, Debug)]
pub struct Plant {
    settings: PlantSettings,
    before: Discrete,
    after: Discrete,
    x: [f64; STATES],
    sample: u64,
    plays: [f64; PLAYS],
    /// The creep's lags, and the share of the way each moves to the drive in one sample (`1 - exp(-T / tau_i)`).
    lags: [f64; CREEP_LAGS],
    lag_steps: [f64; CREEP_LAGS],
}

impl Plant {
    /// At rest, at sample 0.
    pub fn new(settings: PlantSettings) -> Self {
        Plant {
            before: settings.discrete(&settings.before),
            after: settings.discrete(&settings.after),
            settings,
            x: [0.0; STATES],
            sample: 0,
            plays: [0.0; PLAYS],
            lags: [0.0; CREEP_LAGS],
            lag_steps: match settings.creep {
                Some(c) => core::array::from_fn(|i| {
                    -(-settings.sample_period_s / (c.first_tau_s * 10f64.powi(i as i32))).exp_m1()
                }),
                None => [0.0; CREEP_LAGS],
            },
        }
    }

    /// The noiseless measured displacement at the current sample, um.
    pub fn output_um(&self) -> f64 {
        let m = self.current();
        m.c.iter().zip(self.x.iter()).map(|(c, x)| c * x).sum()
    }

    /// The stage displacement `x1` of the first mode at the current sample, um.
    pub fn stage_x1_um(&self) -> f64 {
        self.x[X1]
    }

    /// The true stage parameters of the current sample (`b0` with the gain's drift).
    pub fn params(&self) -> StageParams<f64> {
        let p = if self.sample < self.settings.change_at_sample { self.settings.before } else { self.settings.after };
        StageParams { b0: p.b0 * self.gain(), ..p }
    }

    /// The piezo's gain at the current sample, relative to its start ([`PlantSettings::gain_drift_per_s`]).
    fn gain(&self) -> f64 {
        (1.0 + self.settings.gain_drift_per_s * self.settings.sample_period_s * self.sample as f64).max(0.0)
    }

    /// Index of the current sample.
    pub fn sample(&self) -> u64 {
        self.sample
    }

    fn current(&self) -> &Discrete {
        if self.sample < self.settings.change_at_sample {
            &self.before
        } else {
            &self.after
        }
    }

    /// Hold `u_v` over the current sample period and advance to the next sample.
    pub fn advance(&mut self, u_v: f64) {
        let mut drive = match self.settings.hysteresis {
            Some(h) => self.hysteresis(h, u_v),
            None => u_v,
        };
        if let Some(c) = self.settings.creep {
            drive = self.creep(c, drive);
        }
        if self.settings.gain_drift_per_s != 0.0 {
            drive *= self.gain();
        }
        let m = self.current();
        let mut next = mat_vec(&m.phi, &self.x);
        for (xi, gi) in next.iter_mut().zip(m.gam.iter()) {
            *xi += gi * drive;
        }
        self.x = next;
        self.sample += 1;
        if self.sample == self.settings.change_at_sample {
            self.x[X2] += self.settings.bump_um_per_s;
        }
    }

    /// The drive with the creep's lags as they are at the sample's start; then the lags advanced over the sample.
    fn creep(&mut self, c: Creep, v: f64) -> f64 {
        let out = v + c.per_decade * self.lags.iter().sum::<f64>();
        for (lag, step) in self.lags.iter_mut().zip(self.lag_steps) {
            *lag += step * (v - *lag);
        }
        out
    }

    fn hysteresis(&mut self, h: Hysteresis, v: f64) -> f64 {
        let mut sum = 0.0;
        for (i, p) in self.plays.iter_mut().enumerate() {
            let r = h.width_v * (i + 1) as f64 / PLAYS as f64;
            *p = p.max(v - r).min(v + r);
            sum += *p;
        }
        (1.0 - h.fraction) * v + h.fraction * sum / PLAYS as f64
    }
}
