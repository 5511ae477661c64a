//! The low-priority side of run-time control: a parsed command ([`crate::control`]) in, a [`Change`] for the
//! interrupt and the reply text out.
//!
//! The [`Controller`] keeps the physical settings (f64) and designs every new configuration itself, so the
//! interrupt only ever receives finished values. A command that cannot be honoured changes nothing and is answered
//! `error: ...` naming why. Replies are lines; the last line of every reply starts with `ok` or `error:`, and
//! `status` sends one `est ...` line per estimator before its `ok` line.
//!
//! A reply is written in parts of at most [`REPLY_BYTES`], the console's buffer: every reply is one part but
//! `status` (about 1 KiB, 1.3 KiB with every counter at its widest), which comes a line at a time from one snapshot
//! ([`Rest`]).

use crate::control::{Command, EstimatorSet, ExcitationChoice, ParseError, Recording, TuningPreset, ESTIMATOR_NAMES};
use crate::estimators::ekf::EkfDesign;
use crate::estimators::{Expected, Tuning, TuningConfig, TuningKey, Unrunnable};
use crate::excitation::{ExcitationDesign, Waveform};
use crate::hal::BoardDescription;
use crate::instrument::{self, Change, RecordStatus, Status, DISAGREEMENT_F0_RATIO};
use crate::pipeline::{Faults, PipelineConfig, PipelineSettings, SettingsError};
use crate::record::RecordHeader;
use crate::text::{Num, TextBuf};
use crate::Real;
use core::fmt::{self, Write};

/// The most bytes one part of a reply takes: the console's reply buffer. The longest part is `status`'s `ok` line,
/// 490 bytes with every counter at its widest, the longest numbers, every fault and the widest excitation (a
/// multisine about an offset) (the whole reply with the longest note, the EKFs' disagreement, 1 695 bytes;
/// `the_widest_status_reply_fits_the_consoles_buffer_line_by_line` in `tests/instrument.rs`); the longest error is
/// about 300.
pub const REPLY_BYTES: usize = 512;

/// The most bytes a command's reply takes before [`Controller::execute`] fits it into [`REPLY_BYTES`] (a scratch
/// buffer on the stack while the command runs, not in the console's state). Its notes can add up to more than the
/// reply's buffer: `excite multisine 2.9e-5 1.2e-9 2.2e-9 -9.77` (within a step of the DAC, beyond the clamp, a band
/// that misses the resonance) has three and its verdict, 528 bytes. `excite`, with the most kinds of note, can write
/// five: about 1 100 bytes with the longest numbers. A debug build checks that no reply outgrows this (the host tests,
/// the random session's 20 000 commands among them).
const BODY_BYTES: usize = 3 * REPLY_BYTES;

/// `body`, lines each ended by `\n` and the last the verdict, into `reply` within [`REPLY_BYTES`]: whole, or with its
/// last `note:` lines left out and a line saying how many, so that the verdict always ends the reply. The notes come
/// most urgent first ([`Controller::fit_note`]'s before [`Controller::tuning_note`]'s).
fn fit_reply(body: &str, reply: &mut impl Write) -> fmt::Result {
    if body.len() <= REPLY_BYTES {
        return reply.write_str(body);
    }
    // The notes kept are the first ones whose length leaves room for the rest and the line that says what is left out.
    const LEFT_OUT: usize = "note: 99 more notes left out (the reply's buffer is full)\n".len();
    let is_note = |line: &str| line.starts_with("note: ");
    let (notes, notes_len) = lines(body).filter(|l| is_note(l)).fold((0, 0), |(n, len), l| (n + 1, len + l.len()));
    let room = notes_len.saturating_sub(body.len() + LEFT_OUT - REPLY_BYTES);
    let (mut kept, mut kept_len, mut dropping, mut end) = (0, 0, false, 0);
    for line in lines(body) {
        end += line.len();
        if end == body.len() && kept < notes {
            let n = notes - kept;
            writeln!(
                reply,
                "note: {n} more note{} left out (the reply's buffer is full)",
                if n == 1 { "" } else { "s" }
            )?;
        }
        if is_note(line) {
            dropping |= kept_len + line.len() > room;
            if dropping {
                continue;
            }
            (kept, kept_len) = (kept + 1, kept_len + line.len());
        }
        reply.write_str(line)?;
    }
    Ok(())
}

/// The lines of `text`, each with its `\n` (the last without, if it has none).
fn lines(text: &str) -> impl Iterator<Item = &str> {
    let mut rest = text;
    core::iter::from_fn(move || {
        let end = rest.bytes().position(|b| b == b'\n').map_or(rest.len(), |i| i + 1);
        // After a `\n` or at the end: always a character boundary (checked: no panic's formatting in the firmware).
        let (line, after) = rest.split_at_checked(end)?;
        rest = after;
        (!line.is_empty()).then_some(line)
    })
}

/// Whether a value of `t` differs from the preset `p`'s (`status`'s `+tune`), key by key: in a loop, and once
/// (`Tuning`'s derived comparison, field by field in soft double, took 2.2 KiB of flash at a second call).
#[inline(never)]
fn differs_from(t: &Tuning, p: TuningPreset) -> bool {
    let preset = Tuning::of(p);
    TuningKey::ALL.iter().any(|&key| t.get(key) != preset.get(key))
}

/// The excitation's amplitude, V, from which a PRBS or a multisine with the paper's `Q2` (made for its PRBS of 1 V)
/// is noted ([`Controller::tuning_note`]). On the simulated board a PRBS of 2 V makes the hybrid EKF's `b0` wander
/// up to 0.70 % off the truth instead of 0.59 % at 1 V (0.86 % at 4 V, 1.07 % at 8 V; the paper's 200 s in
/// `hal_sim::experiment`).
const Q2_STRONG_AMPLITUDE_V: f64 = 2.0;

/// What remains of a reply once [`Controller::execute`] wrote its first part: for `status`, its lines, written one
/// at a time by [`Rest::write_next`] from the snapshot taken when the command ran.
#[derive(Clone, Copy, Debug)]
pub struct Rest<T> {
    status: Option<Status<T>>,
    next: usize,
}

impl<T> Rest<T> {
    /// Nothing more.
    pub const fn none() -> Self {
        Rest { status: None, next: 0 }
    }
}

impl<T: Real> Rest<T> {
    /// Write the next part into `reply` (emptied by the caller): `false`, writing nothing, when the reply is complete.
    #[inline(never)]
    pub fn write_next(&mut self, ctl: &Controller, reply: &mut impl Write) -> bool {
        let Some(s) = &self.status else { return false };
        // An `est` line per estimator; after them the note if there is one (judged here, once), then the `ok` line.
        let len = s.estimates.len();
        let (note, next) = match self.next {
            n if n < len => (None, n + 1),
            n if n == len => {
                let note = ctl.status_note(s);
                (note, if note.is_some() { len + 1 } else { len + 2 })
            }
            n if n == len + 1 => (None, len + 2),
            _ => return false,
        };
        // A part that does not fit is cut by the buffer (and marked); the next ones still come.
        let _ = ctl.write_status_line(s, note, self.next, reply);
        self.next = next;
        true
    }
}

/// The run-time settings and what the user chose.
#[derive(Clone, Debug)]
pub struct Controller {
    settings: PipelineSettings,
    board: BoardDescription,
    /// The excitation `start` runs.
    chosen: ExcitationDesign,
    running: bool,
    /// The tuning in use: `preset`, with values changed by `tune` if `tuned`.
    tuning: Tuning,
    preset: TuningPreset,
    /// Kept rather than derived (`tuning != Tuning::of(preset)` in `status`): the comparison of two `Tuning`s in
    /// soft double costs 1.2 KiB of flash.
    tuned: bool,
    frozen: EstimatorSet,
    /// The recording stream: a change of the tuning goes into it while it runs; no other recording starts until
    /// its end line went out.
    stream: Stream,
    /// The recording stream owes the tuning's lines ([`Controller::take_tuning_due`]).
    tuning_due: bool,
}

impl Controller {
    /// Start from `settings` (its excitation is the one `start` runs), running it or not. Fails if the settings do
    /// not design for `board`.
    pub fn new(settings: PipelineSettings, board: BoardDescription, running: bool) -> Result<Self, SettingsError> {
        let mut tuning = Tuning::of(TuningPreset::Prbs);
        // One pre-filter for the stage, as in the paper: the pipeline's, and the continuous-time RLS's own.
        tuning.rls.prefilter = settings.prefilter;
        tuning.spike_ratio = settings.faults.spike_ratio;
        let c = Controller {
            chosen: settings.excitation,
            settings,
            board,
            running,
            tuning,
            preset: TuningPreset::Prbs,
            tuned: tuning != Tuning::of(TuningPreset::Prbs),
            frozen: EstimatorSet(0),
            stream: Stream::Closed,
            tuning_due: false,
        };
        c.design::<f32>(&c.settings, running)?;
        Ok(c)
    }

    /// The configuration of the current settings.
    pub fn config<T: Real>(&self) -> PipelineConfig<T> {
        // Validated in `new` and before every change of `settings`.
        self.design(&self.settings, self.running)
            .unwrap_or_else(|_| unreachable!("settings are validated before they are kept"))
    }

    /// The current tuning, designed.
    pub fn tuning<T: Real>(&self) -> TuningConfig<T> {
        self.tuning.design()
    }

    /// The settings in use (the excitation of a stopped controller is the constant safe value).
    pub fn settings(&self) -> &PipelineSettings {
        &self.settings
    }

    /// `s` designed for the board, with the excitation running or held at the safe value.
    fn design<T: Real>(&self, s: &PipelineSettings, running: bool) -> Result<PipelineConfig<T>, SettingsError> {
        let mut s = *s;
        if !running {
            s.excitation = ExcitationDesign::constant(s.limits.safe_v);
        }
        s.design(&self.board)
    }

    /// A recording was started and its end line has not gone out (the console still owes the stream its frames or
    /// its end).
    pub fn recording_open(&self) -> bool {
        self.stream != Stream::Closed
    }

    /// The recording stopped (`record off`, a burst's end, or an overflow), and its end line went out.
    pub fn record_ended(&mut self) {
        self.stream = Stream::Closed;
    }

    /// Whether the recording stream owes the tuning's lines, once: after the reply to `record on` or `record burst`
    /// (the header is in the reply), and to a change of the tuning while a recording runs. They are the
    /// recording's, as its frames are, not the reply's, which ends with its verdict: write them after it, before any
    /// frame that follows, with [`Controller::write_tuning_line`].
    pub fn take_tuning_due(&mut self) -> bool {
        core::mem::take(&mut self.tuning_due)
    }

    /// Write the recording's tuning line `k` (from 0; [`crate::record::write_tuning_line`]) into `out`, the tuning in
    /// effect from sample `at` (the interrupt's [`crate::instrument::Instrument::changed_at`] after the change that
    /// made them due): `false`, writing nothing, after the last.
    pub fn write_tuning_line(&self, k: usize, at: u64, out: &mut impl Write) -> bool {
        let Some(&key) = TuningKey::ALL.get(k) else { return false };
        let _ = crate::record::write_tuning_line(out, at, key, &self.tuning.get(key)[..key.len()]);
        true
    }

    /// The recording header of the current settings.
    pub fn record_header(&self) -> RecordHeader {
        let p = &self.settings.probe;
        let um_per_adc_v = p.um_per_v / p.adc_v_per_sensor_v;
        RecordHeader {
            rate_hz: self.settings.sample_rate_hz,
            delay: self.board.actuation_delay_samples,
            u_v_per_code: self.dac_step_v(),
            u_v_offset: -self.settings.amplifier.dac_offset_v / self.settings.amplifier.dac_v_per_command_v,
            y_um_per_code: self.board.probe.volts_per_code() * um_per_adc_v,
            y_um_offset: -p.adc_offset_v * um_per_adc_v,
        }
    }

    /// The clamp in force, V ([`PipelineSettings::clamp_v`]; the settings in force were designed, so there is one).
    fn clamp_v(&self) -> [f64; 2] {
        let l = &self.settings.limits;
        self.settings.clamp_v(&self.board).unwrap_or([l.min_v, l.max_v])
    }

    /// The DAC's step as a command, V: what one code of the amplifier's DAC moves the command by.
    fn dac_step_v(&self) -> f64 {
        self.board.amplifier.volts_per_code() / self.settings.amplifier.dac_v_per_command_v
    }

    /// Before the verdict of `excite`, `start` and `limits`: a line for each way the chosen excitation does not fit
    /// the output ([`ExcitationDesign::reach`]): within one step of the DAC, beyond the clamp, or steeper than the
    /// slew limit. The DAC cannot carry the first (the output holds one code or toggles between two, and the
    /// excitation monitor starves every estimator: `tests/instrument.rs`); the limits distort the others, which
    /// `status` counts as `limited=` and the log warns about; a distorted excitation can bias the estimates (see
    /// [`crate::pipeline::FaultCounters::limited`]).
    /// Returns whether the excitation is within one step of the DAC, and whether the clamp clips it.
    fn fit_note(&self, reply: &mut impl Write) -> Result<(bool, bool), fmt::Error> {
        let (l, fs) = (&self.settings.limits, self.settings.sample_rate_hz);
        let r = self.chosen.reach(fs);
        let [min_v, max_v] = self.clamp_v();
        let (span, dac_step) = (r.high_v - r.low_v, self.dac_step_v());
        let within_step = self.chosen.waveform != Waveform::Off && span < dac_step;
        if within_step {
            writeln!(
                reply,
                "note: the excitation spans {} V, less than one step of the DAC ({} V): the output holds one code or \
                 toggles between two, and the excitation monitor holds the estimators (starved)",
                Num(span, 6),
                Num(dac_step, 6)
            )?;
        }
        let clipped = r.low_v < min_v || r.high_v > max_v;
        if clipped {
            writeln!(
                reply,
                "note: the excitation spans {} V to {} V, beyond the clamp's {} V to {} V: the clamp will clip it",
                Num(r.low_v, 6),
                Num(r.high_v, 6),
                Num(min_v, 6),
                Num(max_v, 6)
            )?;
        }
        let max_step = l.max_slew_v_per_s / fs;
        if r.step_v > max_step {
            // In V/s too, the unit `limits` takes: the slew limit that would pass it.
            writeln!(
                reply,
                "note: the excitation steps by up to {} V a sample ({} V/s), beyond the slew limit's {} V: it will be \
                 ramped",
                Num(r.step_v, 6),
                Num(r.step_v * fs, 6),
                Num(max_step, 6)
            )?;
        }
        Ok((within_step, clipped))
    }

    /// After `excite`: a line when the chosen excitation cannot identify the stage: a sine (which the monitor holds),
    /// or a multisine whose band misses the stage's resonance (which the monitor may pass), as `resonance` has it (Hz,
    /// and the estimator whose estimate it is), else as `tune initial` gives it. Returns whether it wrote one.
    fn identify_note(
        &self,
        resonance: Option<(f64, &'static str)>,
        reply: &mut impl Write,
    ) -> Result<bool, fmt::Error> {
        let mut noted = false;
        if let Waveform::Multisine { f_lo_hz, f_hi_hz } = self.chosen.waveform {
            // A band that misses the resonance does not identify the stage (tests/instrument.rs: 600-1000 Hz and
            // 50-150 Hz about 423 Hz).
            let (f0, from) = self.resonance_or_initial(resonance);
            if !(f_lo_hz..=f_hi_hz).contains(&f0) {
                writeln!(
                    reply,
                    "note: {} to {} Hz misses the resonance ({} Hz, {from}): such a band does not identify the stage",
                    Num(f_lo_hz, 6),
                    Num(f_hi_hz, 6),
                    Num(f0, 4)
                )?;
                noted = true;
            }
        }
        if matches!(self.chosen.waveform, Waveform::Sine { .. }) {
            let t = &self.tuning;
            let off = [t.rls.pe_floor_v2, t.ekf.health.pe_floor_v2, t.arx.pe_floor_v2].contains(&0.0);
            writeln!(
                reply,
                "note: a sine alone identifies a gain and a phase, not the three parameters: the excitation \
                 monitor holds the estimators (starved){}",
                if off { "; one whose pe_floor_v2 is 0 drifts" } else { "" }
            )?;
            noted = true;
        }
        Ok(noted)
    }

    /// After `excite` and `tuning`: a line when the triangle is chosen with the EKFs' `Q` the paper's `Q2`, for the
    /// PRBS, with which they fail on the triangle (`b0` 15 % low in the float64 reference; on the simulated board 24 %
    /// and 46 % low in the last 7.5 s of each half of a 60 s run, within 3.2 % with `Q1`). Not after `excite` of a
    /// triangle within a step of the DAC (`within_step`, as [`Self::fit_note`] found it), which identifies nothing.
    /// (These two rules came to keep replies within [`REPLY_BYTES`]; since `fit_reply` leaves out whatever last notes
    /// do not fit, they only keep a reply to what matters most.)
    ///
    /// Or, unless `quiet`, a line when a PRBS or a multisine of [`Q2_STRONG_AMPLITUDE_V`] or more runs with `Q2`,
    /// with the `tune ekf q` that keeps them as at 1 V: the parameters' entries divided by the amplitude squared (the
    /// filter on the input scaled by `A` is then the one on the input at 1 V, but for the noise, which weighs less).
    /// The EKFs' misfit grows with the input; `Q` fixed, their parameters follow it faster and wander further: on the
    /// simulated board a PRBS of 8 V sets `b0` up to 1.03-1.05 % off the truth instead of 0.52-0.54 % at 1 V,
    /// 0.54-0.56 % with `Q / 64`; a multisine of 6 V up to 0.88-0.90 % instead of 0.39-0.40 % at 1 V, 0.35-0.36 % with
    /// `Q / 36` (`tests/instrument.rs`, the firmware's figures). `quiet` is for an `excite` with more urgent notes,
    /// whose length leaves no room for this one: the clamp's, [`Self::identify_note`]'s multisine beside the
    /// resonance, or within a step.
    fn tuning_note(&self, within_step: bool, quiet: bool, reply: &mut impl Write) -> fmt::Result {
        let c = &self.chosen;
        // Bit for bit: `Q2` is what `tuning prbs` sets (and `tune ekf q` with its values), and an integer comparison
        // takes less code than soft double's.
        let q2 = self.tuning.ekf.q_diag.map(f64::to_bits) == EkfDesign::Q2.map(f64::to_bits);
        match c.waveform {
            _ if !q2 => Ok(()),
            Waveform::Triangle { .. } if !within_step => writeln!(
                reply,
                "note: the EKFs fail on the triangle with Q2, the paper's q for the PRBS: tuning triangle gives its Q1"
            ),
            Waveform::Prbs { .. } | Waveform::Multisine { .. } if c.amplitude_v >= Q2_STRONG_AMPLITUDE_V && !quiet => {
                let a2 = c.amplitude_v * c.amplitude_v;
                write!(
                    reply,
                    "note: the EKFs' q is Q2, for the paper's PRBS of 1 V: at {} V their parameters follow the data \
                     faster and wander further; q's last three over {} keep them as at 1 V: tune ekf q",
                    Num(c.amplitude_v, 6),
                    Num(a2, 6),
                )?;
                EkfDesign::q2_for_strength(a2).iter().try_for_each(|x| write!(reply, " {}", Num(*x, 6)))?;
                writeln!(reply)
            }
            _ => Ok(()),
        }
    }

    /// After `tune initial` and `tune prefilter`: a line when the pre-filter's centre is far from the stage's
    /// resonance ([`crate::filters::PrefilterDesign::off_resonance`]), where the estimates can come out biased by
    /// several %: for `tune initial` the resonance of the new initial parameters (a new stage, the pre-filter left
    /// where the last one needed it), for `tune prefilter` `resonance` (the interrupt's estimate, taken before the
    /// restart), else `tune initial`'s.
    fn prefilter_note(
        &self,
        key: TuningKey,
        resonance: Option<(f64, &'static str)>,
        reply: &mut impl Write,
    ) -> fmt::Result {
        let (f0, from) = match key {
            TuningKey::Initial => self.resonance_or_initial(None),
            TuningKey::Prefilter => self.resonance_or_initial(resonance),
            _ => return Ok(()),
        };
        let f_p = self.tuning.rls.prefilter.f_p_hz;
        if let Some(ratio) = self.tuning.rls.prefilter.off_resonance(f0) {
            writeln!(
                reply,
                "note: the pre-filter's f_p ({} Hz) is {} times the resonance ({} Hz, {from}): the estimates can \
                 come out biased by several %; keep f_p near the stage's resonance (tune prefilter) and the initial \
                 parameters near the stage (tune initial)",
                Num(f_p, 6),
                Num(ratio, 3),
                Num(f0, 4)
            )?;
        }
        Ok(())
    }

    /// The stage's resonance and where it is from: `resonance` (Hz, and the estimator whose estimate it is), else
    /// the one of `tune initial`.
    fn resonance_or_initial(&self, resonance: Option<(f64, &'static str)>) -> (f64, Whose) {
        match resonance {
            Some((f0, name)) => (f0, Whose::Estimate(name)),
            None => (self.tuning.ekf.initial.f0_hz(), Whose::Initial),
        }
    }

    /// `tune initial ESTIMATOR`: `tune initial` with the `b0 a1 a0` that `estimator` reports in `status`, which must
    /// be one the estimators run (the reply gives them, for the log); with `prefilter` (`tune stage ESTIMATOR`),
    /// also `tune prefilter` with `f_p` at that estimate's resonance, `f_lc` and `zeta_p` kept, in the same restart.
    /// A stage far from the paper's initial parameters is found by the ARX, linear in its parameters, where the EKFs,
    /// which are local, settle on a wrong solution (README: "Another stage").
    fn seed_from<T: Real>(
        &mut self,
        status: &Status<T>,
        estimator: usize,
        prefilter: bool,
        reply: &mut impl Write,
    ) -> Result<Option<Change<T>>, Refusal> {
        let Some(&name) = ESTIMATOR_NAMES.get(estimator) else {
            return Err(Refusal::Text("no such estimator"));
        };
        let refuse = |why| Err(Refusal::Seed { estimator: name, why });
        if !status.selected.contains(estimator) {
            return refuse(Seed::NotRunning);
        }
        let (p, health) = status.estimates[estimator];
        if health.held {
            return refuse(Seed::Held);
        }
        let values = [p.b0, p.a1, p.a0].map(|x| x.to_f64().unwrap_or(f64::NAN));
        // Its initial parameters, to the rounding of the working scalar (the ARX reports them through its conversion
        // from the discrete model): an estimate that has not moved from them would restart everything where it was.
        let t = &self.tuning;
        let initial = [t.rls.initial, t.ekf.initial, t.ekf.initial, t.arx.initial][estimator];
        let near = |v: f64, i: f64| (v - i).abs() <= 1e-4 * i.abs();
        // `tune prefilter`'s values with `f_p` at the resonance `f0`, `f_lc` and `zeta_p` kept (`tune initial` does
        // not move the pre-filter).
        let pf = t.rls.prefilter;
        let centre_on = |f0: f64| [pf.f_lc_hz, f0, pf.zeta_p];
        if near(values[0], initial.b0) && near(values[1], initial.a1) && near(values[2], initial.a0) {
            // For `tune stage`, the pre-filter may still be off them (after `tune initial arx`, say): the command
            // that centres it.
            let f0 = initial.f0_hz();
            let centre = (prefilter && !near(pf.f_p_hz, f0)).then_some(centre_on(f0));
            return refuse(Seed::Unmoved { centre });
        }
        let mut t = self.tuning;
        if let Err(r) = t.set(TuningKey::Initial, &values) {
            return refuse(Seed::Value(["b0", "a1", "a0"][r.index], values[r.index], r.expected));
        }
        let centred = centre_on(t.ekf.initial.f0_hz());
        if prefilter {
            // `a0` was taken as positive: so is its resonance.
            t.set(TuningKey::Prefilter, &centred).map_err(|_| Refusal::Text("the estimate has no resonance"))?;
        }
        let keys: &[(TuningKey, &[f64])] = if prefilter {
            &[(TuningKey::Initial, &values), (TuningKey::Prefilter, &centred)]
        } else {
            &[(TuningKey::Initial, &values)]
        };
        // Its note is on the resonance of the new initial parameters, not on an estimate.
        self.retune(t, keys, None, reply, name).map(Some)
    }

    /// Run the tuning `t`, which differs from the one running by `keys` set to their values (`from`: the estimator
    /// they are the estimate of, or ""): the change to post, the notes and the reply.
    fn retune<T: Real>(
        &mut self,
        t: Tuning,
        keys: &[(TuningKey, &[f64])],
        resonance: Option<(f64, &'static str)>,
        reply: &mut impl Write,
        from: &'static str,
    ) -> Result<Change<T>, Refusal> {
        let restart = self.tuning.restarted_by(&t);
        // A frequency the pipeline cannot hold (above the Nyquist frequency) is refused as such, before the RLS's
        // step would refuse the pole it makes.
        let s = self.settings.with_stage_of(&t);
        s.check_frequencies()?;
        let mut change = Change { tuning: Some(t.runnable()?), restart, ..Change::default() };
        // The stage's pre-filter: the pipeline's (with its replicas' match) and the continuous-time RLS's change
        // together, in one sample; the spike gate's ratio with them.
        if t.rls.prefilter != self.settings.prefilter || t.spike_ratio != self.settings.faults.spike_ratio {
            change.config = Some(self.design(&s, self.running)?);
            self.settings = s;
        }
        change.freeze = self.frozen;
        self.tuning = t;
        // As after `tuning`: tuned while it differs from the preset (the preset's own values back: untuned).
        self.tuned = differs_from(&t, self.preset);
        self.prefilter_note(keys[0].0, resonance, reply)?;
        match keys {
            [(key, values)] => write_tune(reply, *key, values)?,
            // `tune stage`: both of the stage's keys.
            _ => {
                reply.write_str("ok tune stage =")?;
                for (i, (key, values)) in keys.iter().enumerate() {
                    write!(reply, "{} {key}", if i > 0 { "," } else { "" })?;
                    values.iter().try_for_each(|v| write!(reply, " {}", Num(*v, 6)))?;
                }
            }
        }
        match from {
            "" => writeln!(reply, " ({})", Restarted(restart))?,
            name => writeln!(reply, " ({name}'s estimate; {})", Restarted(restart))?,
        }
        Ok(change)
    }

    /// Answer a line that did not parse.
    pub fn refuse(&self, e: ParseError, reply: &mut impl Write) {
        let _ = writeln!(reply, "error: {e}");
    }

    /// Carry out `cmd`: the change to post (if any), the reply's first part in `reply` and the [`Rest`] of it.
    /// `status` is called only for `status` (whose reply is all in the rest). Nothing changes when the reply is an
    /// error.
    // Not inlined: in the firmware's console task it was, once its reply came in parts, for 4 KiB more flash.
    #[inline(never)]
    pub fn execute<T: Real>(
        &mut self,
        cmd: Command,
        status: impl FnOnce() -> Status<T>,
        reply: &mut impl Write,
    ) -> (Option<Change<T>>, Rest<T>) {
        if matches!(cmd, Command::Status) {
            return (None, Rest { status: Some(status()), next: 0 });
        }
        // The reply in full first, then fitted to the console's buffer (`fit_reply`): a note cut there took the
        // verdict with it, and the note's write error refused the command after its settings were taken.
        let mut body = TextBuf::<BODY_BYTES>::default();
        // For `tune initial|stage ESTIMATOR`, that estimator's estimate; for the notes of `excite multisine` and `tune
        // prefilter`, the resonance as the interrupt estimates it now.
        let result = if let Command::FromEstimate { estimator, prefilter } = cmd {
            self.seed_from(&status(), estimator, prefilter, &mut body)
        } else {
            let resonance = matches!(
                cmd,
                Command::Excite(ExcitationChoice::Multisine { .. })
                    | Command::Tune { key: TuningKey::Prefilter, values: Some(_) }
            )
            .then(|| estimated_resonance(&status()))
            .flatten();
            self.try_execute(cmd, resonance, &mut body)
        };
        debug_assert!(!body.truncated(), "a reply outgrew BODY_BYTES: {}", body.as_str());
        let change = match result {
            Ok(change) => {
                // The tuning the estimators run, into the recording: at its start, and at each change while it runs.
                self.tuning_due |= self.stream == Stream::Running
                    && change.as_ref().is_some_and(|c| c.tuning.is_some() || c.record.is_some());
                change
            }
            Err(e) => {
                if body.truncated() {
                    body.clear();
                }
                let _ = writeln!(body, "error: {e}");
                None
            }
        };
        let _ = fit_reply(body.as_str(), reply);
        (change, Rest::none())
    }

    // Not inlined into `execute`: inlined, its callees were inlined differently, for 1.9 KiB more flash.
    #[inline(never)]
    fn try_execute<T: Real>(
        &mut self,
        cmd: Command,
        resonance: Option<(f64, &'static str)>,
        reply: &mut impl Write,
    ) -> Result<Option<Change<T>>, Refusal> {
        let mut change = Change::default();
        match cmd {
            // Answered by `execute` from the snapshot, a line at a time; carried out by `seed_from`.
            Command::Status | Command::FromEstimate { .. } => return Ok(None),
            Command::Help => writeln!(reply, "{}ok help", crate::control::HELP)?,
            Command::Excite(choice) => {
                let design = excitation(choice);
                let mut s = self.settings;
                s.excitation = design;
                change.config = Some(self.design(&s, self.running)?);
                self.settings = s;
                self.chosen = design;
                let (within_step, clipped) = self.fit_note(reply)?;
                let beside = self.identify_note(resonance, reply)?;
                self.tuning_note(within_step, within_step || clipped || beside, reply)?;
                let state = if self.running { "running" } else { "stopped, send start" };
                writeln!(reply, "ok excite {} ({state})", Exc(&self.chosen))?;
            }
            Command::Start | Command::Stop => {
                let running = cmd == Command::Start;
                let mut s = self.settings;
                s.excitation = self.chosen;
                change.config = Some(self.design(&s, running)?);
                self.settings = s;
                self.running = running;
                if running {
                    change.clear_faults = true;
                    self.fit_note(reply)?;
                    writeln!(reply, "ok start {} (latched faults cleared)", Exc(&self.chosen))?;
                } else {
                    writeln!(reply, "ok stop (output to {} V at the slew limit)", Num(s.limits.safe_v, 6))?;
                }
            }
            Command::Select(set) => {
                let mut s = self.settings;
                let before = EstimatorSet(s.estimators & EstimatorSet::ALL.0);
                s.estimators = set.0;
                change.config = Some(self.design(&s, self.running)?);
                // An estimator not fed for a while holds stale signals: it restarts when selected again.
                change.reset = EstimatorSet(set.0 & !before.0);
                self.settings = s;
                writeln!(reply, "ok select {}", Names(set))?;
            }
            Command::Reset(set) => {
                change.reset = set;
                writeln!(reply, "ok reset {}", Names(set))?;
            }
            Command::Freeze(set) => {
                change.freeze = set;
                self.frozen.0 |= set.0;
                writeln!(reply, "ok freeze {}", Names(set))?;
            }
            Command::Adapt(set) => {
                change.adapt = set;
                self.frozen.0 &= !set.0;
                writeln!(reply, "ok adapt {}", Names(set))?;
            }
            Command::Tuning(p) => {
                // The preset for the input; the stage's initial parameters and pre-filter stay.
                let t = Tuning::of(p).with_stage_of(&self.tuning);
                change.tuning = Some(t.runnable()?);
                // The estimators whose tuning changes restart with the new one; frozen ones stay frozen.
                change.restart = self.tuning.restarted_by(&t);
                change.freeze = self.frozen;
                self.preset = p;
                self.tuned = differs_from(&t, p);
                self.tuning = t;
                self.tuning_note(false, false, reply)?;
                writeln!(reply, "ok tuning {} ({})", tuning_name(p), Restarted(change.restart))?;
            }
            Command::Tune { key, values: None } => {
                write_tune(reply, key, &self.tuning.get(key)[..key.len()])?;
                writeln!(reply)?;
                return Ok(None);
            }
            Command::Tune { key, values: Some(values) } => {
                let values = &values[..key.len()];
                let mut t = self.tuning;
                t.set(key, values).map_err(|r| Refusal::Value {
                    // `tune initial V...` has its values from word 3, `tune SECTION KEY V...` from word 4.
                    word: r.index + if key.path().0.is_empty() { 3 } else { 4 },
                    value: values[r.index],
                    expected: r.expected,
                })?;
                return self.retune(t, &[(key, values)], resonance, reply, "").map(Some);
            }
            Command::LimitsInUse => {
                let [low, high] = self.clamp_v();
                write_limits(reply, &self.settings.limits)?;
                writeln!(
                    reply,
                    " (the clamp in force, within the DAC's reach: {} V to {} V)",
                    Num(low, 6),
                    Num(high, 6)
                )?;
                return Ok(None);
            }
            Command::Limits { min_v, max_v, slew_v_per_s } => {
                let mut s = self.settings;
                s.limits.min_v = min_v as f64;
                s.limits.max_v = max_v as f64;
                s.limits.max_slew_v_per_s = slew_v_per_s as f64;
                change.config = Some(self.design(&s, self.running)?);
                self.settings = s;
                let beyond = |r: &[f64; 2]| s.limits.min_v < r[0] || s.limits.max_v > r[1];
                if let Some((_, [low_v, high_v])) = s.dac_reach(&self.board).filter(|(_, r)| beyond(r)) {
                    let [low, high] = self.board.amplifier_swing_v;
                    writeln!(
                        reply,
                        "note: the DAC reaches {} V to {} V (its output is specified from {} V to {} V): the clamp \
                         stops the output there",
                        Num(low_v, 6),
                        Num(high_v, 6),
                        Num(low, 6),
                        Num(high, 6)
                    )?;
                }
                self.fit_note(reply)?;
                write_limits(reply, &s.limits)?;
                writeln!(reply)?;
            }
            Command::Record(r) => {
                if self.board.probe.max_code > 0xFFFF || self.board.amplifier.max_code > 0xFFFF {
                    return Err(Refusal::Text("record: the v1 stream carries 16-bit codes; this board's are wider"));
                }
                if r != Recording::Off && self.stream != Stream::Closed {
                    return Err(Refusal::Text(
                        "record: a recording runs (or its end line has not gone out): record off first",
                    ));
                }
                change.record = Some(match r {
                    Recording::Off => Some(0),
                    Recording::On => None,
                    Recording::Burst(n) => Some(n),
                });
                if r != Recording::Off {
                    self.record_header().write(reply)?;
                }
                match r {
                    Recording::Off => writeln!(reply, "ok record off")?,
                    Recording::On => writeln!(reply, "ok record on")?,
                    Recording::Burst(n) => writeln!(reply, "ok record burst {n}")?,
                }
                // Once the command is taken (its change is what the console posts).
                self.stream = match (r, self.stream) {
                    (Recording::Off, Stream::Closed) => Stream::Closed,
                    (Recording::Off, _) => Stream::Closing,
                    _ => Stream::Running,
                };
            }
        }
        Ok(Some(change))
    }

    /// `status`'s note: the EKFs' [`disagreement`] with the estimators linear in their parameters; else an EKF
    /// model that explains little of the measurement ([`instrument::weak_response`]); else a resonance too fast for
    /// the continuous EKF while it runs ([`instrument::fast_resonance`]).
    fn status_note<T: Real>(&self, s: &Status<T>) -> Option<StatusNote> {
        let verdict = instrument::compare_ekfs(s);
        match verdict.filter(|d| d.ekfs.0 != 0) {
            Some(d) => Some(StatusNote::Disagreement(d)),
            None => instrument::weak_response_given(s, verdict).map(StatusNote::WeakResponse).or_else(|| {
                instrument::fast_resonance_given(s, self.settings.sample_rate_hz, false).map(StatusNote::FastResonance)
            }),
        }
    }

    /// Line `line` of `status`'s reply: the `est` line of estimator `line`; after the last, `note`
    /// ([`Controller::status_note`]) if there is one, else the `ok status` line.
    fn write_status_line<T: Real>(
        &self,
        s: &Status<T>,
        note: Option<StatusNote>,
        line: usize,
        w: &mut impl Write,
    ) -> fmt::Result {
        if let Some((p, h)) = s.estimates.get(line) {
            let f = |x: T| Num(x.to_f64().unwrap_or(f64::NAN), 6);
            write!(
                w,
                "est {} a0={} a1={} b0={} f0_hz={} zeta={} gain_um_per_v={} ",
                ESTIMATOR_NAMES[line],
                f(p.a0),
                f(p.a1),
                f(p.b0),
                f(p.f0_hz()),
                f(p.damping_ratio()),
                f(p.dc_gain())
            )?;
            let state = if !s.selected.contains(line) { "off" } else { h.state() };
            return writeln!(
                w,
                "{state} rejected={} changes={} resets={} repairs={} innovation_rms_um={}",
                h.rejected_samples,
                h.changes_detected,
                h.numeric_resets,
                h.covariance_repairs,
                Num(h.innovation_rms_um as f64, 4)
            );
        }
        match note.filter(|_| line == s.estimates.len()) {
            Some(StatusNote::Disagreement(d)) => {
                let reference = d.reference_name();
                return writeln!(
                    w,
                    "note: {} disagree with {reference} on the resonance (more than {} times apart) or the gain's \
                     sign: the EKFs are local and, started far from the stage, settle on a wrong solution; the \
                     {reference} cannot, but converges more slowly. Once its estimate holds, start the EKFs there: \
                     tune stage {reference}",
                    d.ekf_names(),
                    Num(DISAGREEMENT_F0_RATIO, 6)
                );
            }
            Some(StatusNote::WeakResponse(r)) => {
                return writeln!(
                    w,
                    "note: {}'s model explains little of the measurement: the response it allows the excitation is {} \
                     times its innovations, under the {} a trusted estimate needs. Is the probe connected and seeing \
                     the stage, and the excitation large enough?",
                    ESTIMATOR_NAMES[r.ekf],
                    Num(r.ratio, 2),
                    Num(instrument::TRUSTED_RESPONSE_RATIO, 2)
                );
            }
            Some(StatusNote::FastResonance(f)) => {
                return writeln!(
                    w,
                    "note: the resonance, {} Hz ({}), is at w T = {} of this sample rate, where {}: take hekf's",
                    Num(f.f0_hz, 4),
                    Whose::Estimate(ESTIMATOR_NAMES[f.estimator]),
                    Num(f.wt, 2),
                    instrument::FAST_RESONANCE_EFFECT
                );
            }
            None => {}
        }
        let c = &s.counters;
        writeln!(
            w,
            "ok status samples={} excitation={} {} faults={} over_range={} stuck={} spikes={} not_finite={} \
             deadline_misses={} adc_overruns={} isr_cycles_max={} limited={} command_v={} pe_power_v2={} \
             pe_single={} selected={} tuning={}{} record={}",
            s.samples,
            Exc(&self.chosen),
            if self.running { "running" } else { "stopped" },
            FaultNames(s.faults),
            c.probe_over_range,
            c.probe_stuck,
            c.spikes,
            c.command_not_finite,
            c.deadline_misses,
            c.adc_overruns,
            Cycles(s.isr_cycles_max),
            c.limited,
            Num(s.command_v.to_f64().unwrap_or(f64::NAN), 6),
            Num(s.excitation_level.power.to_f64().unwrap_or(f64::NAN), 3),
            if s.excitation_level.single { "yes" } else { "no" },
            Names(s.selected),
            tuning_name(self.preset),
            if self.tuned { "+tune" } else { "" },
            Rec(s.record)
        )
    }
}

/// The line that closes a recording (once it stopped and its last frame went out).
pub fn write_record_end(r: &RecordStatus, w: &mut impl Write) -> fmt::Result {
    let end = crate::record::END_TAG;
    crate::record::write_checked_line(w, format_args!("{end} samples={} overflow={}", r.recorded, r.overflowed as u8))
}

/// Why a command was refused.
enum Refusal {
    Settings(SettingsError),
    /// A tuning value out of its range.
    Value {
        word: usize,
        value: f64,
        expected: Expected,
    },
    Text(&'static str),
    /// `tune initial ESTIMATOR` refused: whose estimate, and why.
    Seed {
        estimator: &'static str,
        why: Seed,
    },
    /// Each value in range, the whole not runnable.
    Unrunnable(Unrunnable),
    /// The reply did not fit its buffer (it was cut, and says so).
    Reply,
}

/// The recording stream, as the console has it.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Stream {
    /// No recording, or the last one's end line went out ([`Controller::record_ended`]).
    Closed,
    /// Since `record on` or `record burst`: a change of the tuning goes into it.
    Running,
    /// After `record off`, until its end line went out: another recording would clear the ring before the console
    /// drained it, and the one before would lose its last samples and its end line. (The firmware's console sends a
    /// stopped recording's end before it executes the next line, so a `record on` does not find it closing.)
    Closing,
}

/// Why `tune initial ESTIMATOR` was refused.
#[derive(Clone, Copy)]
enum Seed {
    /// The estimator is not selected.
    NotRunning,
    /// Its estimate is its initial parameters (within 1e-4 of each); for `tune stage`, `tune prefilter`'s values
    /// that centre the pre-filter on them, unless it is.
    Unmoved {
        /// `f_lc`, `f_p`, `zeta_p`.
        centre: Option<[f64; 3]>,
    },
    /// Its estimate is held ([`crate::estimator::Health::held`]).
    Held,
    /// A value `tune initial` refuses: which, its value, and what it should have been.
    Value(&'static str, f64, Expected),
}

/// A tuning the estimators could not run ([`Tuning::runnable`]).
impl From<Unrunnable> for Refusal {
    fn from(u: Unrunnable) -> Self {
        Refusal::Unrunnable(u)
    }
}

impl From<SettingsError> for Refusal {
    fn from(e: SettingsError) -> Self {
        Refusal::Settings(e)
    }
}

impl From<fmt::Error> for Refusal {
    fn from(_: fmt::Error) -> Self {
        Refusal::Reply
    }
}

impl fmt::Display for Refusal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Refusal::Settings(e) => write!(f, "{e}"),
            Refusal::Value { word, value, expected } => write!(f, "word {word}: {}: {expected}", Num(*value, 6)),
            Refusal::Text(t) => f.write_str(t),
            Refusal::Seed { estimator, why: Seed::NotRunning } => {
                write!(f, "{estimator} is not running: select it, and let it find the stage, first")
            }
            Refusal::Seed { estimator, why: Seed::Held } => write!(
                f,
                "{estimator}'s estimate is held (its model has no continuous equivalent now): let it find the stage \
                 first (status)"
            ),
            Refusal::Seed { estimator, why: Seed::Unmoved { centre } } => {
                write!(f, "{estimator}'s estimate is its initial parameters: let it find the stage first (status)")?;
                match centre {
                    Some([f_lc, f_p, zeta]) => write!(
                        f,
                        ", or centre the pre-filter on them: tune prefilter {} {} {}",
                        Num(*f_lc, 6),
                        Num(*f_p, 6),
                        Num(*zeta, 6)
                    ),
                    None => Ok(()),
                }
            }
            Refusal::Seed { estimator, why: Seed::Value(name, value, expected) } => {
                write!(f, "{estimator}'s estimate has {name} = {}: {expected}", Num(*value, 6))
            }
            Refusal::Unrunnable(u) => write!(f, "{u}"),
            Refusal::Reply => f.write_str("reply too long for the buffer"),
        }
    }
}

/// `ok limits MIN V to MAX V, SLEW V/s`, without the line end: `limits`' verdict, setting them or asking.
fn write_limits(w: &mut dyn Write, l: &crate::pipeline::OutputLimits) -> fmt::Result {
    write!(w, "ok limits {} V to {} V, {} V/s", Num(l.min_v, 6), Num(l.max_v, 6), Num(l.max_slew_v_per_s, 6))
}

/// `ok tune KEY = V...`, without the line end.
fn write_tune(w: &mut dyn Write, key: TuningKey, values: &[f64]) -> fmt::Result {
    write!(w, "ok tune {key} =")?;
    values.iter().try_for_each(|v| write!(w, " {}", Num(*v, 6)))
}

fn tuning_name(p: TuningPreset) -> &'static str {
    match p {
        TuningPreset::Prbs => "prbs",
        TuningPreset::Triangle => "triangle",
    }
}

fn excitation(c: ExcitationChoice) -> ExcitationDesign {
    match c {
        ExcitationChoice::Off => ExcitationDesign::OFF,
        ExcitationChoice::Constant { level_v } => ExcitationDesign::constant(level_v as f64),
        ExcitationChoice::Prbs { amplitude_v, offset_v } => ExcitationDesign {
            amplitude_v: amplitude_v as f64,
            offset_v: offset_v as f64,
            ..ExcitationDesign::PAPER_PRBS
        },
        ExcitationChoice::Triangle { amplitude_v, frequency_hz, offset_v } => ExcitationDesign {
            waveform: Waveform::Triangle { freq_hz: frequency_hz as f64, max_hz: 1000.0 },
            amplitude_v: amplitude_v as f64,
            offset_v: offset_v as f64,
        },
        ExcitationChoice::Sine { amplitude_v, frequency_hz, offset_v } => ExcitationDesign {
            offset_v: offset_v as f64,
            ..ExcitationDesign::sine(frequency_hz as f64, amplitude_v as f64)
        },
        ExcitationChoice::Multisine { amplitude_v, f_lo_hz, f_hi_hz, offset_v } => ExcitationDesign {
            offset_v: offset_v as f64,
            ..ExcitationDesign::multisine(f_lo_hz as f64, f_hi_hz as f64, amplitude_v as f64)
        },
    }
}

/// An excitation as the protocol names it.
struct Exc<'a>(&'a ExcitationDesign);

impl fmt::Display for Exc<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (a, offset) = (Num(self.0.amplitude_v, 6), self.0.offset_v);
        match self.0.waveform {
            Waveform::Off if offset == 0.0 => return f.write_str("off"),
            Waveform::Off => return write!(f, "constant {} V", Num(offset, 6)),
            Waveform::Prbs { .. } => write!(f, "prbs {a} V"),
            Waveform::Triangle { freq_hz, .. } => write!(f, "triangle {a} V {} Hz", Num(freq_hz, 6)),
            Waveform::Sine { freq_hz } => write!(f, "sine {a} V {} Hz", Num(freq_hz, 6)),
            Waveform::Multisine { f_lo_hz, f_hi_hz } => {
                write!(f, "multisine {a} V {} to {} Hz", Num(f_lo_hz, 6), Num(f_hi_hz, 6))
            }
        }?;
        if offset != 0.0 {
            write!(f, " offset {} V", Num(offset, 6))?;
        }
        Ok(())
    }
}

/// A set of estimators, comma-separated (`none` if empty).
struct Names(EstimatorSet);

impl fmt::Display for Names {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        list(f, self.0.names())
    }
}

/// What a new tuning did to the estimators (the set it restarted, [`Tuning::restarted_by`]), for its reply.
struct Restarted(EstimatorSet);

impl fmt::Display for Restarted {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            EstimatorSet::ALL => f.write_str("estimators restarted"),
            EstimatorSet(0) => f.write_str("estimators kept: their tuning is unchanged"),
            s => write!(f, "{} restarted; {} kept", Names(s), Names(EstimatorSet(EstimatorSet::ALL.0 & !s.0))),
        }
    }
}

/// `a,b,c`, or `none`.
fn list<'a>(f: &mut fmt::Formatter<'_>, names: impl Iterator<Item = &'a str>) -> fmt::Result {
    let mut first = true;
    for name in names {
        f.write_str(if first { "" } else { "," })?;
        f.write_str(name)?;
        first = false;
    }
    if first {
        f.write_str("none")?;
    }
    Ok(())
}

/// [`instrument::estimated_resonance`], with the estimator's name.
fn estimated_resonance<T: Real>(status: &Status<T>) -> Option<(f64, &'static str)> {
    instrument::estimated_resonance(status).map(|(f0, i)| (f0, ESTIMATOR_NAMES[i]))
}

/// A note of `status`'s, between the estimators' lines and its `ok` line.
#[derive(Clone, Copy, Debug)]
enum StatusNote {
    /// The EKFs disagree with the ARX or the RLS.
    Disagreement(crate::instrument::Disagreement),
    /// The continuous EKF runs at a resonance beyond [`instrument::FAST_RESONANCE_WT`].
    FastResonance(instrument::FastResonance),
    /// The EKFs' model explains little of the measurement.
    WeakResponse(instrument::WeakResponse),
}

/// Where a resonance in a note is from: an estimator's estimate, or `tune initial`.
#[derive(Clone, Copy)]
enum Whose {
    Estimate(&'static str),
    Initial,
}

impl fmt::Display for Whose {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Whose::Estimate(name) => write!(f, "{name}'s estimate"),
            Whose::Initial => f.write_str("tune initial"),
        }
    }
}

/// Latched faults by name (`none` if none).
struct FaultNames(Faults);

impl fmt::Display for FaultNames {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        list(f, self.0.names())
    }
}

/// A count of cycles, or `-` for 0, none counted.
struct Cycles(u32);

impl fmt::Display for Cycles {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            0 => f.write_str("-"),
            n => write!(f, "{n}"),
        }
    }
}

/// The recorder, in one word and its counts.
struct Rec(RecordStatus);

impl fmt::Display for Rec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let r = &self.0;
        let state = match (r.active, r.remaining, r.overflowed) {
            (true, None, _) => "on",
            (true, Some(_), _) => "burst",
            (false, _, true) => "overflowed",
            (false, _, false) => "off",
        };
        write!(f, "{state} recorded={} buffered={}", r.recorded, r.buffered)
    }
}

#[cfg(test)]
mod tests {
    use super::{fit_reply, REPLY_BYTES};
    use crate::text::TextBuf;

    fn fitted(body: &str) -> String {
        let mut reply = TextBuf::<REPLY_BYTES>::default();
        fit_reply(body, &mut reply).unwrap();
        assert!(!reply.truncated());
        reply.as_str().to_string()
    }

    /// A reply that fits goes out as it is; one that does not loses its last notes, whole lines, and says how many,
    /// and keeps every other line and its verdict last.
    #[test]
    fn a_reply_too_long_for_the_buffer_loses_its_last_notes_not_its_verdict() {
        let short = "note: one\nok done\n";
        assert_eq!(fitted(short), short);
        let note = |c: char| format!("note: {}\n", c.to_string().repeat(194)); // 201 bytes
        let header = "# a protocol line, not a note\n";
        let body = format!("{}{header}{}{}ok excite\n", note('a'), note('b'), note('c'));
        assert!(body.len() > REPLY_BYTES);
        let reply = fitted(&body);
        assert_eq!(
            reply,
            format!(
                "{}{header}{}note: 1 more note left out (the reply's buffer is full)\nok excite\n",
                note('a'),
                note('b')
            )
        );
        let body = format!("{}{}{}{}error: no\n", note('a'), note('b'), note('c'), note('d'));
        assert!(fitted(&body)
            .ends_with(&format!("{}note: 2 more notes left out (the reply's buffer is full)\nerror: no\n", note('b'))));
        // Exactly full: whole.
        let full = format!("{}{}", "x".repeat(REPLY_BYTES - 8), "ok full\n");
        assert_eq!(fitted(&full), full);
    }

    /// The notes kept are counted from the first: a note that fills the room to the byte is kept; when not even the
    /// first fits, every note is left out and counted.
    #[test]
    fn the_notes_kept_fill_the_room_to_the_byte_and_the_count_is_of_those_left_out() {
        const LEFT_OUT: usize = "note: 99 more notes left out (the reply's buffer is full)\n".len();
        let note = |len: usize| format!("note: {}\n", "n".repeat(len - 7));
        let verdict = "ok excite\n";
        // The room for notes is what the buffer holds beside the verdict and the longest count line.
        let exact = note(REPLY_BYTES - verdict.len() - LEFT_OUT);
        let body = format!("{exact}{}{verdict}", note(100));
        let reply = fitted(&body);
        assert_eq!(reply, format!("{exact}note: 1 more note left out (the reply's buffer is full)\n{verdict}"));
        assert!(reply.len() <= REPLY_BYTES);
        // One byte more and it goes too: none kept, all five counted.
        let over = note(REPLY_BYTES - verdict.len() - LEFT_OUT + 1);
        let body = format!("{over}{}{}{}{}{verdict}", note(100), note(50), note(50), note(50));
        assert_eq!(fitted(&body), format!("note: 5 more notes left out (the reply's buffer is full)\n{verdict}"));
    }

    /// A reply too long without a note to leave out (none is: the longest error is about 300 bytes, `status`'s
    /// longest line 490) is cut by the buffer, which marks the cut, and no line claims notes were left out.
    #[test]
    fn a_reply_too_long_without_notes_is_cut_and_says_nothing_of_notes() {
        let first = format!("{}\n", "x".repeat(REPLY_BYTES - 40));
        let body = format!("{first}ok {}\n", "y".repeat(60));
        let mut reply = TextBuf::<REPLY_BYTES>::default();
        assert!(fit_reply(&body, &mut reply).is_err());
        let r = reply.as_str();
        assert!(reply.truncated() && r.starts_with(&format!("{first}ok yyy")) && !r.contains("note:"), "{r}");
    }
}
