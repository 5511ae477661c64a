//! What the sample interrupt owns: the pipeline with every estimator, its configuration, the mailbox through which a
//! new configuration arrives, and the recording buffer. The firmware's interrupt calls [`Instrument::sample`] and
//! nothing else; host tests call it on the simulated board.
//!
//! ## Changes arrive whole, between samples
//! Configuration (excitation, limits, which estimators run, their tuning) is designed at low priority (f64, the
//! expensive part) into a [`Change`] and [`Instrument::post`]ed: a move into a one-slot mailbox, which the firmware
//! does under its lock (a copy of about a kilobyte, no design work). The next [`Instrument::sample`] applies it
//! before it touches anything else, so a sample runs entirely with the old configuration or entirely with the new
//! one. While a change waits, `post` refuses another (the caller retries after a sample period): nothing is
//! overwritten or half-applied.
//!
//! ## Recording
//! When on, every sample's converter codes go into a ring of [`RECORD_BUFFER`] samples that low priority drains
//! ([`Instrument::drain_recorded`]) into frames ([`crate::record`]). A full ring stops the recording rather than
//! leave a gap: what was recorded is contiguous, and the stop is reported.

use crate::control::EstimatorSet;
use crate::estimator::{Adaptation, Estimator, Health, PeLevel};
use crate::estimators::{full_bank, restart_bank, FullBank, TuningConfig};
use crate::hal::{run_sample_with, StageBoard};
use crate::pipeline::{FaultCounters, Faults, Pipeline, PipelineConfig, SampleOutput};
use crate::record::RawSample;
use crate::{Real, StageParams};

/// Samples the recording ring holds: 0.1 s at 10 kHz, 4 000 bytes (the firmware's static RAM stays under 16 000
/// bytes: 1 024 samples, as it was, would be 96 more).
pub const RECORD_BUFFER: usize = 1000;

/// The ring's slot of `i`, a slot plus at most a ring's length (a compare rather than a division by 1 000).
#[inline(always)]
fn ring_slot(i: usize) -> usize {
    debug_assert!(i < 2 * RECORD_BUFFER);
    if i >= RECORD_BUFFER {
        i - RECORD_BUFFER
    } else {
        i
    }
}

/// A change prepared at low priority and applied whole between two samples.
#[derive(Clone, Debug, Default)]
pub struct Change<T> {
    /// A new pipeline configuration (excitation, limits, selection, scaling).
    pub config: Option<PipelineConfig<T>>,
    /// New tuning: the estimators of `restart` restart with it (from their initial parameters and `P0`).
    pub tuning: Option<TuningConfig<T>>,
    /// The estimators the new `tuning` restarts: those whose tuning it changes
    /// ([`crate::estimators::Tuning::restarted_by`]). The others' is the same, and they run on.
    pub restart: EstimatorSet,
    /// Estimators to reset to their initial state (applied after `tuning`).
    pub reset: EstimatorSet,
    /// Estimators to freeze.
    pub freeze: EstimatorSet,
    /// Estimators to let adapt again.
    pub adapt: EstimatorSet,
    /// Clear the latched faults (the excitation resumes).
    pub clear_faults: bool,
    /// Start (`Some(Some(n))`: the next `n` samples, `Some(None)`: until stopped) or stop (`Some(Some(0))`) recording.
    pub record: Option<Option<u32>>,
}

/// The recorder's state, as status reports it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RecordStatus {
    /// Recording now.
    pub active: bool,
    /// Samples still to record in a burst (`None`: until stopped).
    pub remaining: Option<u32>,
    /// Samples recorded since the recording started.
    pub recorded: u64,
    /// The recording stopped because the ring was full (the link drained it too slowly).
    pub overflowed: bool,
    /// Samples waiting in the ring.
    pub buffered: usize,
}

/// A snapshot for status and telemetry.
#[derive(Clone, Copy, Debug)]
pub struct Status<T> {
    /// Samples since start.
    pub samples: u64,
    /// Latched faults.
    pub faults: Faults,
    /// Fault counts.
    pub counters: FaultCounters,
    /// The last command written, V.
    pub command_v: T,
    /// The excitation monitor's level of the input.
    pub excitation_level: PeLevel<T>,
    /// Estimators fed (bit `i`: [`crate::control::ESTIMATOR_NAMES`]`[i]`).
    pub selected: EstimatorSet,
    /// Each estimator's parameters and health, in the bank's order.
    pub estimates: [(StageParams<T>, Health); 4],
    /// The recorder.
    pub record: RecordStatus,
    /// The most cycles a sample's interrupt took since start-up, from its conversion's end to its own end: the board
    /// fills it in ([`Instrument::status`] cannot: 0, which no interrupt takes, for none counted; a `u32`, not an
    /// `Option`, to keep the console task's copy of the snapshot within the static RAM's 16 000 bytes).
    pub isr_cycles_max: u32,
}

/// The mailbox was full: the change comes back, to be posted again after the next sample.
#[derive(Debug)]
pub struct Busy<T>(pub Change<T>);

/// The interrupt's state.
pub struct Instrument<T: Real> {
    /// The pipeline and its estimators.
    pub pipeline: Pipeline<T, FullBank<T>>,
    config: PipelineConfig<T>,
    pending: Option<Change<T>>,
    /// DAC code in effect over the current sample period (what the recording stores as `u`).
    code_in_effect: u32,
    /// The last DAC code written, whether or not it made its deadline.
    code_written: u32,
    ring: [RawSample; RECORD_BUFFER],
    ring_head: usize,
    ring_len: usize,
    /// Sample index of the oldest sample in the ring.
    ring_first: u64,
    record: RecordStatus,
    /// Index of the first sample the last change applied to.
    changed_at: u64,
}

impl<T: Real> Instrument<T> {
    /// At rest, with every estimator fresh.
    pub fn new(config: PipelineConfig<T>, tuning: &TuningConfig<T>) -> Self {
        // A pipeline at rest outputs its safe value.
        let code_in_effect = config.safe_code();
        Instrument {
            pipeline: Pipeline::new(&config, full_bank(tuning)),
            config,
            pending: None,
            code_in_effect,
            code_written: code_in_effect,
            ring: [RawSample::default(); RECORD_BUFFER],
            ring_head: 0,
            ring_len: 0,
            ring_first: 0,
            record: RecordStatus::default(),
            changed_at: 0,
        }
    }

    /// The configuration in use.
    pub fn config(&self) -> &PipelineConfig<T> {
        &self.config
    }

    /// Hand a change to the next sample. Refused while another is waiting.
    // The refused change comes back by value to be posted again: there is no heap to box it in.
    #[allow(clippy::result_large_err)]
    pub fn post(&mut self, change: Change<T>) -> Result<(), Busy<T>> {
        if self.pending.is_some() {
            return Err(Busy(change));
        }
        self.pending = Some(change);
        Ok(())
    }

    /// Whether a posted change is still waiting for a sample.
    pub fn change_pending(&self) -> bool {
        self.pending.is_some()
    }

    /// The index (samples since the start, from 0) of the first sample the last change applied to: where a new
    /// tuning took over, or a recording started (its first sample).
    pub fn changed_at(&self) -> u64 {
        self.changed_at
    }

    /// One sample: apply a waiting change, run the pipeline on the board, record.
    #[inline]
    pub fn sample<B: StageBoard + ?Sized>(&mut self, board: &mut B) -> SampleOutput<T> {
        self.sample_with(board, None::<fn(T) -> T>)
    }

    /// [`Instrument::sample`] with the excitation added to an external command, V, `command(y_um)` of this sample's
    /// probe reading: a scan, or a controller built on the estimates ([`Pipeline::step_adding`] says what the
    /// pipeline does with it). The recording stores the sum, as the DAC outputs it.
    #[inline]
    pub fn sample_adding<B: StageBoard + ?Sized>(
        &mut self,
        board: &mut B,
        command: impl FnOnce(T) -> T,
    ) -> SampleOutput<T> {
        self.sample_with(board, Some(command))
    }

    #[inline(always)]
    fn sample_with<B: StageBoard + ?Sized>(
        &mut self,
        board: &mut B,
        command: Option<impl FnOnce(T) -> T>,
    ) -> SampleOutput<T> {
        if self.pending.is_some() {
            self.apply_pending();
        }
        let out = run_sample_with(board, &mut self.pipeline, &self.config, command);
        // The code in effect over this period: the one written now, or, with the board's delay, the last one. Over the
        // next, the one written now, unless it missed its deadline: then the next instant loaded the one written
        // before it (the late one is loaded at the instant after only if the next sample's write misses too, and is
        // overwritten first if it does not), which the pipeline's filters and estimators take as well.
        let in_effect = if self.config.actuation_delay_samples == 0 { out.dac_code } else { self.code_in_effect };
        self.code_in_effect = out.dac_code;
        if out.board_faults.deadline_missed {
            self.hold_written();
        }
        self.code_written = out.dac_code;
        if self.record.active {
            self.record_sample(RawSample { u_code: in_effect as u16, y_code: out.probe_code as u16 });
        }
        out
    }

    /// A missed deadline: the code written before this sample's is in effect over the next period.
    #[inline(never)]
    #[cold]
    fn hold_written(&mut self) {
        self.code_in_effect = self.code_written;
        self.pipeline.hold_command(self.config.command_of_code(self.code_written));
    }

    #[inline(never)]
    #[cold]
    // From RAM on the board (src/bin/nanopos-fw/ram_code.rs): the sample that applies a change also runs all of the
    // sample path, and this is about 1 500 instructions of mostly straight-line copies and constructions (QEMU's
    // `isr_body_applying_change`), at 2.5 cycles each from the flash.
    #[cfg_attr(target_os = "none", link_section = ".ramtext.apply_pending")]
    fn apply_pending(&mut self) {
        // Read in place, not taken out of the mailbox: `take` copied the whole change (1 KiB) first.
        let Some(c) = &self.pending else { return };
        self.changed_at = self.pipeline.samples();
        if let Some(cfg) = &c.config {
            self.pipeline.retarget(&self.config, cfg);
            self.config = *cfg;
        }
        let bank = &mut self.pipeline.estimators;
        if let Some(t) = &c.tuning {
            restart_bank(bank, t, c.restart);
        }
        control(bank, c.reset, Op::Reset);
        control(bank, c.freeze, Op::Freeze);
        control(bank, c.adapt, Op::Adapt);
        if c.clear_faults {
            self.pipeline.clear_faults();
        }
        match c.record {
            None => {}
            Some(Some(0)) => self.record.active = false,
            Some(burst) => {
                // A new recording starts with an empty ring: what an earlier one left was already announced ended.
                self.ring_len = 0;
                self.record = RecordStatus { active: true, remaining: burst, ..RecordStatus::default() };
            }
        }
        self.pending = None;
    }

    fn record_sample(&mut self, s: RawSample) {
        if self.ring_len == RECORD_BUFFER {
            self.record.active = false;
            self.record.overflowed = true;
            return;
        }
        if self.ring_len == 0 {
            self.ring_first = self.pipeline.samples() - 1;
        }
        self.ring[ring_slot(self.ring_head + self.ring_len)] = s;
        self.ring_len += 1;
        self.record.recorded += 1;
        if let Some(n) = &mut self.record.remaining {
            *n -= 1;
            if *n == 0 {
                self.record.active = false;
            }
        }
    }

    /// Move up to `out.len()` recorded samples, oldest first, into `out`: returns the index of the first (samples
    /// since start, counting from 0) and how many. The samples of one call are consecutive.
    pub fn drain_recorded(&mut self, out: &mut [RawSample]) -> (u64, usize) {
        let n = out.len().min(self.ring_len);
        // The samples from the head to the ring's end, then those from its start.
        let to_end = n.min(RECORD_BUFFER - self.ring_head);
        out[..to_end].copy_from_slice(&self.ring[self.ring_head..self.ring_head + to_end]);
        out[to_end..n].copy_from_slice(&self.ring[..n - to_end]);
        let first = self.ring_first;
        self.ring_head = ring_slot(self.ring_head + n);
        self.ring_len -= n;
        self.ring_first += n as u64;
        (first, n)
    }

    /// The recorder's state.
    pub fn record_status(&self) -> RecordStatus {
        RecordStatus { buffered: self.ring_len, ..self.record }
    }

    /// Each estimator's parameters and health.
    pub fn estimates(&self) -> [(StageParams<T>, Health); 4] {
        let e = &self.pipeline.estimators;
        [e.0.report(), e.1.report(), e.2.report(), e.3.report()]
    }

    /// A snapshot of everything status reports. The firmware takes it under the lock, holding off the sample
    /// interrupt meanwhile: about 1 700 instructions (QEMU's `status_snapshot`; the ARX's conversion to the stage is
    /// most of it), so it runs from RAM on the board like the interrupt (src/bin/nanopos-fw/ram_code.rs), and the
    /// firmware takes the lock only when the next sample is due later than that (`with_task` in
    /// src/bin/nanopos-fw/firmware.rs): it delays no sample.
    #[inline(never)]
    #[cfg_attr(target_os = "none", link_section = ".ramtext.status")]
    pub fn status(&self) -> Status<T> {
        Status {
            samples: self.pipeline.samples(),
            faults: self.pipeline.faults(),
            counters: self.pipeline.fault_counters(),
            command_v: self.pipeline.command_v(),
            excitation_level: self.pipeline.excitation_level(),
            selected: EstimatorSet(self.config.estimators & EstimatorSet::ALL.0),
            estimates: self.estimates(),
            record: self.record_status(),
            isr_cycles_max: 0,
        }
    }
}

#[derive(Clone, Copy)]
enum Op {
    Reset,
    Freeze,
    Adapt,
}

/// Apply `op` to the estimators of `bank` in `set`.
fn control<T: Real>(bank: &mut FullBank<T>, set: EstimatorSet, op: Op) {
    fn one<T: Real, E: Estimator<T>>(e: &mut E, op: Op) {
        match op {
            Op::Reset => e.reset(),
            Op::Freeze => e.set_adapting(false),
            Op::Adapt => e.set_adapting(true),
        }
    }
    if set.contains(0) {
        one(&mut bank.0, op);
    }
    if set.contains(1) {
        one(&mut bank.1, op);
    }
    if set.contains(2) {
        one(&mut bank.2, op);
    }
    if set.contains(3) {
        one(&mut bank.3, op);
    }
}

/// Feeds the independent watchdog only while the sample clock runs: the low-priority task asks each time it would
/// feed, and is allowed to only if the interrupt counted at least `min_samples` samples since the last time. A stopped
/// sample clock, a hung interrupt or a hung task (nobody asks) all end in a watchdog reset.
#[derive(Clone, Copy, Debug)]
pub struct WatchdogGate {
    last_samples: u64,
    min_samples: u64,
}

impl WatchdogGate {
    /// Allow feeding when at least `min_samples` samples passed between two asks.
    pub const fn new(min_samples: u64) -> Self {
        WatchdogGate { last_samples: 0, min_samples }
    }

    /// Whether to feed now, given the interrupt's sample count.
    pub fn may_feed(&mut self, samples: u64) -> bool {
        let ok = samples.wrapping_sub(self.last_samples) >= self.min_samples;
        self.last_samples = samples;
        ok
    }
}

/// The EKFs' resonance against that of the estimators linear in their parameters ([`disagreement`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Disagreement {
    /// The EKFs whose estimate is off the reference's.
    pub ekfs: EstimatorSet,
    /// The reference: the ARX if it runs with an estimate to report, else the continuous-time RLS (an index in
    /// [`crate::control::ESTIMATOR_NAMES`]).
    pub reference: usize,
}

impl Disagreement {
    /// The EKFs off the reference, as a list of names (`ekf`, `hekf` or `ekf,hekf`).
    pub fn ekf_names(&self) -> &'static str {
        match (self.ekfs.contains(1), self.ekfs.contains(2)) {
            (true, false) => "ekf",
            (false, true) => "hekf",
            _ => "ekf,hekf",
        }
    }

    /// The reference's name.
    pub fn reference_name(&self) -> &'static str {
        crate::control::ESTIMATOR_NAMES[self.reference]
    }
}

/// How far apart two resonances may be before they disagree, as a ratio. The payload's removal moves the paper's
/// stage by 14 %, and the continuous-time RLS takes 13 s to follow it where the EKFs take 0.2 s: that must not count.
pub const DISAGREEMENT_F0_RATIO: f64 = 1.25;

/// Whether the running EKFs disagree with the estimators linear in their parameters: a resonance more than 1.25
/// times above or below theirs ([`DISAGREEMENT_F0_RATIO`]), or a static gain of the other sign. The EKFs are local:
/// started far from the stage (the paper's initial parameters, 390 Hz, on a stage at 1 kHz) they settle on a wrong
/// solution, `b0` of the wrong sign, and report it as steadily as a right one. The RLS and the ARX are linear in
/// their parameters and cannot settle wrong, but they converge more slowly (the ARX 35-58 s at a 50 mV PRBS, the RLS
/// 13 s after the payload's removal): a disagreement is either. The reference is the ARX if it runs and its estimate
/// is not held, else the RLS; when both run they must agree with each other, or there is no verdict (`None`), as
/// there is none with no EKF or no reference running. Computed from a [`Status`] in the working scalar, no square
/// root.
pub fn disagreement<T: Real>(status: &Status<T>) -> Option<Disagreement> {
    compare_ekfs(status).filter(|d| d.ekfs.0 != 0)
}

/// The verdict of [`disagreement`], agreement included: `Some` with no EKF in [`Disagreement::ekfs`] where every
/// running EKF agrees with the reference; `None` where there is no verdict.
pub fn compare_ekfs<T: Real>(status: &Status<T>) -> Option<Disagreement> {
    // Compared on `a0`, the square of the resonance.
    let ratio = T::of(DISAGREEMENT_F0_RATIO * DISAGREEMENT_F0_RATIO);
    // The gains' signs compared, not their product, which underflows for tiny ones.
    let zero = T::zero();
    let agree = |p: &StageParams<T>, q: &StageParams<T>| {
        let same_sign = (p.b0 > zero && q.b0 > zero) || (p.b0 < zero && q.b0 < zero);
        p.a0 > zero && p.a0 < ratio * q.a0 && q.a0 < ratio * p.a0 && same_sign
    };
    let reports = |i: usize| status.selected.contains(i) && !status.estimates[i].1.held;
    let (rls, arx) = (&status.estimates[0].0, &status.estimates[3].0);
    let reference = match (reports(3), reports(0)) {
        (true, true) if !agree(arx, rls) => return None,
        (true, _) => 3,
        (false, true) => 0,
        (false, false) => return None,
    };
    let r = &status.estimates[reference].0;
    // A reference with no resonance (`a0` not positive, or not a number) judges nothing, as no EKF running is judged.
    let judged = r.a0 > T::zero() && (status.selected.contains(1) || status.selected.contains(2));
    if !judged {
        return None;
    }
    let off = [1, 2].into_iter().filter(|&i| status.selected.contains(i) && !agree(&status.estimates[i].0, r));
    Some(Disagreement { ekfs: EstimatorSet(off.fold(0, |set, i| set | 1 << i)), reference })
}

/// The estimate of EKF `ekf` (1: the continuous, 2: the hybrid) when a controller may retune from it: the EKF runs
/// and adapts (not frozen, not starved), and [`compare_ekfs`] has a verdict and it is agreement with the ARX or the
/// RLS. Health alone does not do: an EKF settled on a wrong solution reports `adapting`. Nor does the absence of a
/// [`disagreement`]: with no verdict (the RLS and the ARX apart, as from 2 to 10 s on a stage at 1 kHz while the RLS
/// converges, or neither running) the EKFs are not checked, and on that stage a damping loop retuned from the hybrid
/// EKF then, `b0` of the wrong sign, drove the output to its limits (`tests/damping.rs`). So keep the ARX running
/// (294 instructions a sample) if a controller is to follow the EKFs. Nor does agreement mean much at first: every
/// estimator starts at the initial parameters, so they agree until the data move them; a controller gives them time
/// after a start or a restart (on the PRBS of 1 V, 2 s did on the stages tested).
///
/// Nor does agreement mean the probe sees the stage: on a disconnected probe (the ADC reading noise) every estimator
/// fits the noise, they agree on the pre-filter's own resonance, and this rule gave the hybrid EKF's noise fit (a
/// gain of 1e-4 um/V) at 359 of 1 981 looks with the PRBS and at every look with the triangle. So the estimate is
/// given only if the response it allows the excitation stands [`TRUSTED_RESPONSE_RATIO`] times above the EKF's
/// innovation RMS ([`response_ratio`]).
pub fn trusted_ekf_estimate<T: Real>(status: &Status<T>, ekf: usize) -> Option<StageParams<T>> {
    let (params, _) = status.estimates.get(ekf).filter(|_| ekf == 1 || ekf == 2)?;
    let adapting = adapts(status, ekf);
    let agrees = compare_ekfs(status).is_some_and(|d| !d.ekfs.contains(ekf));
    let responds = response_ratio(status, ekf).is_some_and(|r| r >= T::of(TRUSTED_RESPONSE_RATIO));
    (adapting && agrees && responds).then_some(*params)
}

/// Whether estimator `i` runs and adapts (not frozen, not starved).
fn adapts<T: Real>(status: &Status<T>, i: usize) -> bool {
    status.selected.contains(i) && status.estimates[i].1.adaptation == Adaptation::Adapting
}

/// The least [`response_ratio`] at which [`trusted_ekf_estimate`] gives an EKF's estimate. Measured on the simulated
/// board at the looks (0.1 s apart, from 2 s on) where the hybrid EKF adapted and agreed with the reference, the rule
/// without this test (`cargo test --release --test instrument -- --ignored --nocapture response_ratio_where`): with
/// the probe disconnected 0.003 to 2.2 (PRBS, 359 of 1 981 looks), 0.5 to 4.3 (triangle, all 981), up to 0.8
/// (multisine, PRBS of 0.1 V); on the paper's stage at least 82 (PRBS), 24 (triangle), 53 (PRBS of 50 mV), 524
/// (multisine), on the 1 kHz stage after `tune stage arx` 13. Below it: a PRBS of 10 mV (0.4 to 33, the rule now
/// refusing 124 of 503 looks: under the 50 mV the console calls a useful excitation) and, on a 200 Hz stage, 3 of
/// 173 looks while the model did not fit the measurement (down to 2). Over 20 minutes of a disconnected probe (a
/// scratch run, not kept) the hybrid EKF agreed at 633 looks (PRBS) and 11 976 (triangle), its ratio at most 2.2 and
/// 5.1: never given. It is the EKFs' ratio because their `a1` stays near where the data leave it (on the disconnected
/// probe 70 to 225); the RLS's noise fit has `a1` down to 6, a peak gain without meaning (ratios up to 83 000).
pub const TRUSTED_RESPONSE_RATIO: f64 = 10.0;

/// How far the response the estimate of EKF `ekf` allows the excitation stands above what it leaves unexplained:
/// its resonance's peak gain `|b0| / (a1 sqrt(a0))` times the pre-filtered input's RMS (an upper bound on the RMS
/// of the model's output), over the EKF's innovation RMS. A model that explains the measurement has it far above
/// 1; on a probe that sees nothing of the excitation it is of order 1 or below, whatever the estimates. `None`
/// without an innovation RMS to compare with (not an EKF, or its first second) or a resonance (`a0 <= 0`); an
/// estimate without positive damping has no finite peak and gets 0.
pub fn response_ratio<T: Real>(status: &Status<T>, ekf: usize) -> Option<T> {
    let (p, health) = status.estimates.get(ekf)?;
    let noise = T::of(health.innovation_rms_um as f64);
    if !(noise > T::zero() && p.a0 > T::zero()) {
        return None;
    }
    let input_rms = status.excitation_level.power.max(T::zero()).sqrt();
    let peak_gain = if p.a1 > T::zero() { p.b0.abs() / (p.a1 * p.a0.sqrt()) } else { T::zero() };
    Some(peak_gain * input_rms / noise)
}

/// The stage's resonance as the interrupt's estimators have it, Hz, and whose estimate it is (an index in
/// [`crate::control::ESTIMATOR_NAMES`]): the hybrid EKF's if it runs, else the first running estimator's whose
/// parameters are not held ([`Health::held`]: the ARX's, the last it could report); where the EKFs [`disagreement`]
/// with the estimators linear in their parameters, the latter's (the ARX's, else the RLS's). `None` if none runs or
/// its estimate has no resonance (`a0 <= 0`).
pub fn estimated_resonance<T: Real>(status: &Status<T>) -> Option<(f64, usize)> {
    resonance_given(status, disagreement(status))
}

/// [`estimated_resonance`] with the [`disagreement`] judged.
fn resonance_given<T: Real>(status: &Status<T>, disagreement: Option<Disagreement>) -> Option<(f64, usize)> {
    let running = |i: usize| status.selected.contains(i) && !status.estimates[i].1.held;
    let i = match disagreement {
        Some(d) => d.reference,
        None if running(2) => 2,
        None => (0..4).find(|&i| running(i))?,
    };
    let f0 = status.estimates[i].0.f0_hz().to_f64()?;
    (f0.is_finite() && f0 > 0.0).then_some((f0, i))
}

/// An EKF whose model explains little of the measurement ([`weak_response`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WeakResponse {
    /// The EKF (an index in [`crate::control::ESTIMATOR_NAMES`]: 1 or 2).
    pub ekf: usize,
    /// Its [`response_ratio`].
    pub ratio: f64,
}

/// The hybrid EKF (else the continuous one), adapting, with a [`response_ratio`] under [`TRUSTED_RESPONSE_RATIO`]
/// while [`compare_ekfs`] finds the EKFs agreeing with the ARX or the RLS: the estimators agree on a model that
/// explains little of the measurement, so [`trusted_ekf_estimate`] refuses it. On the simulated board: a
/// disconnected probe (the estimators fit its noise and agree), or an excitation too small for the stage (a PRBS of
/// 10 mV on the paper's stage, at a quarter of the looks). Not where they disagree (that is the news there) nor
/// where there is no verdict: on the 1 kHz stage from 2 to 10 s, the RLS and the ARX apart, the EKFs on a wrong
/// solution have ratios of 0 to 5 too. On the paper's stage over 200 s with the PRBS or the triangle, through the
/// payload's change, at no look (a scratch run of 0.1 s looks, not kept); at single looks while a model settles: 3
/// on a 200 Hz stage just after its EKFs stopped disagreeing, 9 in the first 1.1 s of a PRBS of 50 mV (ratios 2 to
/// 9). The telemetry waits for 2 s of it ([`WARNING_LOOKS`]).
pub fn weak_response<T: Real>(status: &Status<T>) -> Option<WeakResponse> {
    weak_response_given(status, compare_ekfs(status))
}

/// [`weak_response`] for a caller that has [`compare_ekfs`]' verdict already.
pub(crate) fn weak_response_given<T: Real>(status: &Status<T>, verdict: Option<Disagreement>) -> Option<WeakResponse> {
    if verdict.is_none_or(|d| d.ekfs.0 != 0) {
        return None;
    }
    let ekf = [2, 1].into_iter().find(|&i| adapts(status, i))?;
    let ratio = response_ratio(status, ekf)?.to_f64()?;
    (ratio < TRUSTED_RESPONSE_RATIO).then_some(WeakResponse { ekf, ratio })
}

/// What a resonance beyond [`FAST_RESONANCE_WT`] does to the EKFs, as the console's and `identify`'s notes say it.
pub const FAST_RESONANCE_EFFECT: &str = "the continuous EKF's one RK4 step a sample leaves its a1 low (on the \
    simulated board -1.3 % at w T 0.5, -5.2 % at 0.63, -20 % at 0.82); the hybrid EKF's substeps keep it within 1 %";

/// The `w T` (resonance in radians a sample) above which the continuous EKF's `a1` comes out low: 1.3 % on the
/// simulated board, 5.2 % at 0.63 (1 kHz at 10 kHz), 20 % at 0.82, where the hybrid EKF stays within 1 %
/// (`which_estimator_for_which_stage` in `tests/instrument.rs`).
pub const FAST_RESONANCE_WT: f64 = 0.5;

/// A resonance too fast for the continuous EKF ([`fast_resonance`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FastResonance {
    /// The resonance, Hz.
    pub f0_hz: f64,
    /// Whose estimate it is (an index in [`crate::control::ESTIMATOR_NAMES`]).
    pub estimator: usize,
    /// Its `w T` at the sample rate.
    pub wt: f64,
}

/// The [`estimated_resonance`] where it is beyond [`FAST_RESONANCE_WT`] at `sample_rate_hz`, while the continuous
/// EKF runs and the EKFs do not [`disagreement`] with the ARX or the RLS (where they settled on a wrong solution,
/// which of them to take is not the question yet).
pub fn fast_resonance<T: Real>(status: &Status<T>, sample_rate_hz: f64) -> Option<FastResonance> {
    fast_resonance_given(status, sample_rate_hz, disagreement(status).is_some())
}

/// [`fast_resonance`] for a caller that has judged the [`disagreement`] already.
pub(crate) fn fast_resonance_given<T: Real>(
    status: &Status<T>,
    sample_rate_hz: f64,
    disagreeing: bool,
) -> Option<FastResonance> {
    if !status.selected.contains(1) || disagreeing {
        return None;
    }
    // No disagreement: the hybrid EKF's resonance, else the first running estimator's.
    let (f0_hz, estimator) = resonance_given(status, None)?;
    let wt = 2.0 * core::f64::consts::PI * f0_hz / sample_rate_hz;
    (wt > FAST_RESONANCE_WT).then_some(FastResonance { f0_hz, estimator, wt })
}

/// What grew since the last look at the interrupt's [`Status`]: for the telemetry, which warns once per event rather
/// than leaving the user to read it off climbing counters. Numeric resets matter most: a tuning the data drive to
/// non-finite values resets an estimator over and over, each time back to its initial parameters and `adapting`,
/// so its parameters look steady while nothing is identified.
#[derive(Clone, Copy, Debug)]
pub struct EventWatch {
    /// The counts at the last look (nothing seen: all zero).
    seen: Counts,
    /// Whether the output limits changed commands in the interval the last look covered.
    limited_before: bool,
    /// Looks at which the EKFs disagreed with the estimators linear in their parameters ([`disagreement`]) since
    /// they last agreed (looks with no verdict, the RLS and the ARX apart, neither count nor end it).
    disagreeing: u8,
    /// Looks in a row at which the resonance was too fast for the continuous EKF ([`fast_resonance`]).
    fast: u8,
    /// Looks in a row at which the EKFs' model explained little of the measurement ([`weak_response`]).
    weak: u8,
    /// The interrupt's sample rate, Hz (f32: the watch lives in the telemetry task's static state).
    sample_rate_hz: f32,
}

/// The counts [`EventWatch`] follows, as the last look saw them.
#[derive(Clone, Copy, Debug)]
struct Counts {
    resets: [u32; 4],
    deadline_misses: u32,
    adc_overruns: u32,
    limited: u32,
    spikes: u32,
}

/// Looks (0.1 s apart in the telemetry) at which the EKFs disagree ([`disagreement`]), with no agreement between them,
/// or the resonance is too fast for the continuous EKF ([`fast_resonance`]), in a row, before it is news: 2 s, so that
/// the estimators' own convergence from their start does not warn (on the paper's stage wired the other way round, with
/// the triangle, the EKFs find the negative gain within 0.1 s, the ARX's passes zero after 1.7 s: they disagree for
/// 0.9 s, then for 0.5 s).
pub const WARNING_LOOKS: u8 = 20;

/// Events since the last look ([`EventWatch::look`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct News {
    /// Numeric resets per estimator, in the bank's order.
    pub resets: [u32; 4],
    /// Deadline misses.
    pub deadline_misses: u32,
    /// ADC overruns.
    pub adc_overruns: u32,
    /// Samples whose command the output limits changed ([`crate::pipeline::FaultCounters::limited`]).
    pub limited: u32,
    /// Probe readings the spike gate replaced ([`crate::pipeline::FaultCounters::spikes`]).
    pub spikes: u32,
    /// The limits changed commands both since the last look and in the interval before it: the excitation does not
    /// fit them. A single step of the command (a start about an offset: a sample or two, once) does not count.
    pub limiting: bool,
    /// The EKFs' [`disagreement`], on the look that completes [`WARNING_LOOKS`] since they last agreed; once
    /// per spell.
    pub disagreement: Option<Disagreement>,
    /// The [`fast_resonance`], on the look that completes [`WARNING_LOOKS`] of it in a row; once per spell.
    pub fast_resonance: Option<FastResonance>,
    /// The [`weak_response`], on the look that completes [`WARNING_LOOKS`] of it in a row; once per spell.
    pub weak_response: Option<WeakResponse>,
}

impl EventWatch {
    /// Nothing seen yet, for an interrupt at `sample_rate_hz`.
    pub const fn new(sample_rate_hz: f32) -> Self {
        let seen = Counts { resets: [0; 4], deadline_misses: 0, adc_overruns: 0, limited: 0, spikes: 0 };
        EventWatch { seen, limited_before: false, disagreeing: 0, fast: 0, weak: 0, sample_rate_hz }
    }

    /// The counts' growth since the last look. A count that went down was restarted (a new tuning restarts the
    /// estimators and their health): all of it is new.
    pub fn look<T: Real>(&mut self, status: &Status<T>) -> News {
        let now = Counts {
            resets: core::array::from_fn(|i| status.estimates[i].1.numeric_resets),
            deadline_misses: status.counters.deadline_misses,
            adc_overruns: status.counters.adc_overruns,
            limited: status.counters.limited,
            spikes: status.counters.spikes,
        };
        let grown = |now: u32, seen: u32| if now >= seen { now - seen } else { now };
        let limited = grown(now.limited, self.seen.limited);
        let found = compare_ekfs(status);
        self.disagreeing = match found {
            Some(d) if d.ekfs.0 != 0 => self.disagreeing.saturating_add(1),
            Some(_) => 0,
            None => self.disagreeing,
        };
        let disagreeing = found.is_some_and(|d| d.ekfs.0 != 0);
        let fast = fast_resonance_given(status, self.sample_rate_hz as f64, disagreeing);
        self.fast = if fast.is_some() { self.fast.saturating_add(1) } else { 0 };
        let weak = weak_response_given(status, found);
        self.weak = if weak.is_some() { self.weak.saturating_add(1) } else { 0 };
        let news = News {
            resets: core::array::from_fn(|i| grown(now.resets[i], self.seen.resets[i])),
            deadline_misses: grown(now.deadline_misses, self.seen.deadline_misses),
            adc_overruns: grown(now.adc_overruns, self.seen.adc_overruns),
            limited,
            spikes: grown(now.spikes, self.seen.spikes),
            limiting: limited > 0 && self.limited_before,
            disagreement: found.filter(|_| disagreeing && self.disagreeing == WARNING_LOOKS),
            fast_resonance: fast.filter(|_| self.fast == WARNING_LOOKS),
            weak_response: weak.filter(|_| self.weak == WARNING_LOOKS),
        };
        self.limited_before = limited > 0;
        self.seen = now;
        news
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The paper's stage with the payload, `f0` 422.9 Hz.
    const STAGE: StageParams<f32> = StageParams { a0: 7.06e6, a1: 77.6, b0: 0.808e6 };

    /// A status with every estimator selected at [`STAGE`], `est` changing it: a pre-filtered input of 1 V RMS, the
    /// EKFs' innovations 5 nm RMS (their [`response_ratio`] 784).
    fn status(est: impl Fn(&mut [(StageParams<f32>, Health); 4])) -> Status<f32> {
        let mut estimates = [(STAGE, Health::new()); 4];
        for (_, h) in &mut estimates[1..3] {
            h.innovation_rms_um = 0.005;
        }
        est(&mut estimates);
        Status {
            samples: 0,
            faults: Faults::default(),
            counters: FaultCounters::default(),
            command_v: 0.0,
            excitation_level: PeLevel { power: 1.0, single: false },
            selected: EstimatorSet::ALL,
            estimates,
            record: RecordStatus::default(),
            isr_cycles_max: 0,
        }
    }

    /// `STAGE` with its resonance times `ratio` (and its gain kept).
    fn moved(ratio: f32) -> StageParams<f32> {
        let k = ratio * ratio;
        StageParams { a0: STAGE.a0 * k, a1: STAGE.a1, b0: STAGE.b0 * k }
    }

    #[test]
    fn the_ekfs_disagree_beyond_the_ratio_or_with_the_other_sign() {
        assert_eq!(disagreement(&status(|_| ())), None, "all at one stage");
        let agreed = Disagreement { ekfs: EstimatorSet(0), reference: 3 };
        assert_eq!(compare_ekfs(&status(|_| ())), Some(agreed));
        // Just within and just beyond 1.25, above and below, for either EKF.
        for (ratio, off) in [(1.249, false), (1.251, true), (1.0 / 1.249, false), (1.0 / 1.251, true)] {
            for ekf in [1, 2] {
                let d = disagreement(&status(|e| e[ekf].0 = moved(ratio)));
                let expect = off.then_some(Disagreement { ekfs: EstimatorSet(1 << ekf), reference: 3 });
                assert_eq!(d, expect, "ekf {ekf} at {ratio}");
            }
        }
        // The gain's sign, and a stage with no resonance.
        let flipped = StageParams { b0: -STAGE.b0, ..STAGE };
        let d = disagreement(&status(|e| e[1].0 = flipped)).unwrap();
        assert_eq!((d.ekfs, d.ekf_names(), d.reference_name()), (EstimatorSet(0b010), "ekf", "arx"));
        let none = StageParams { a0: -STAGE.a0, ..STAGE };
        let d = disagreement(&status(|e| (e[1].0, e[2].0) = (none, flipped))).unwrap();
        assert_eq!((d.ekfs, d.ekf_names()), (EstimatorSet(0b110), "ekf,hekf"));
        // Gains too small for their product in f32 (it underflows to zero) keep their signs.
        let tiny = |e: &mut [(StageParams<f32>, Health); 4]| e.iter_mut().for_each(|(p, _)| p.b0 = 1e-30);
        assert_eq!(compare_ekfs(&status(tiny)), Some(agreed));
        let d = disagreement(&status(|e| {
            tiny(e);
            e[2].0.b0 = -1e-30;
        }));
        assert_eq!(d.map(|d| d.ekf_names()), Some("hekf"));
        // A gain of exactly zero has no sign: it agrees with no gain of either sign, the EKF's or the reference's
        // (the RLS held, so that the ARX alone is the reference).
        for sign in [1.0, -1.0] {
            let signed = |e: &mut [(StageParams<f32>, Health); 4]| e.iter_mut().for_each(|(p, _)| p.b0 *= sign);
            let d = disagreement(&status(|e| {
                signed(e);
                e[1].0.b0 = 0.0;
            }));
            assert_eq!(d.map(|d| d.ekf_names()), Some("ekf"), "gains of sign {sign}");
            let d = disagreement(&status(|e| {
                signed(e);
                e[3].0.b0 = 0.0;
                e[0].1.held = true;
            }));
            assert_eq!(d.map(|d| (d.ekf_names(), d.reference_name())), Some(("ekf,hekf", "arx")), "sign {sign}");
        }
        // Not finite: no agreement either.
        let nan = StageParams { a0: f32::NAN, ..STAGE };
        assert_eq!(disagreement(&status(|e| e[2].0 = nan)).map(|d| d.ekf_names()), Some("hekf"));
    }

    #[test]
    fn a_controller_may_follow_an_ekf_only_while_it_adapts_and_agrees_with_a_reference() {
        assert_eq!(trusted_ekf_estimate(&status(|_| ()), 2), Some(STAGE));
        assert_eq!(trusted_ekf_estimate(&status(|_| ()), 1), Some(STAGE));
        // Not an EKF, or no estimator at all.
        assert_eq!(trusted_ekf_estimate(&status(|_| ()), 0), None);
        assert_eq!(trusted_ekf_estimate(&status(|_| ()), 3), None);
        assert_eq!(trusted_ekf_estimate(&status(|_| ()), 4), None);
        // Off the reference: not that one; the other still.
        let off = status(|e| e[2].0 = moved(2.0));
        assert_eq!((trusted_ekf_estimate(&off, 2), trusted_ekf_estimate(&off, 1)), (None, Some(STAGE)));
        // No verdict: the RLS and the ARX apart, or neither running.
        assert_eq!(trusted_ekf_estimate(&status(|e| e[0].0 = moved(2.0)), 2), None);
        let mut alone = status(|_| ());
        alone.selected = EstimatorSet(0b0110);
        assert_eq!(trusted_ekf_estimate(&alone, 2), None);
        // With the RLS alone as the reference (the ARX not running, or held), a verdict again.
        alone.selected = EstimatorSet(0b0111);
        assert_eq!(trusted_ekf_estimate(&alone, 2), Some(STAGE));
        assert_eq!(trusted_ekf_estimate(&status(|e| e[3].1.held = true), 2), Some(STAGE));
        // Not running, frozen or starved.
        alone.selected = EstimatorSet(0b1011);
        assert_eq!(trusted_ekf_estimate(&alone, 2), None);
        for a in [Adaptation::Frozen, Adaptation::Starved] {
            assert_eq!(trusted_ekf_estimate(&status(|e| e[2].1.adaptation = a), 2), None, "{a:?}");
        }
    }

    #[test]
    fn a_controller_may_follow_an_ekf_only_while_its_model_explains_the_measurement() {
        // STAGE's peak gain, b0 / (a1 sqrt(a0)) = 3.92 um/V, times 1 V over 5 nm.
        let ratio = response_ratio(&status(|_| ()), 2).unwrap();
        assert!((ratio - 783.75).abs() < 0.01, "{ratio}");
        // Just above and below the least ratio, through the innovations or the input.
        let peak_um = 808e3 / (77.6 * 7.06e6f32.sqrt());
        for (k, trusted) in [(1.001, true), (0.999, false)] {
            let noise = peak_um / (TRUSTED_RESPONSE_RATIO as f32 * k);
            let st = status(|e| e[2].1.innovation_rms_um = noise);
            assert_eq!(trusted_ekf_estimate(&st, 2).is_some(), trusted, "innovations {noise} um");
            let mut st = status(|_| ());
            st.excitation_level.power = (TRUSTED_RESPONSE_RATIO as f32 * k * 0.005 / peak_um).powi(2);
            assert_eq!(trusted_ekf_estimate(&st, 2).is_some(), trusted, "input {} V^2", st.excitation_level.power);
        }
        // The disconnected probe's hybrid EKF (tests/instrument.rs): 1e-4 um/V, innovations 7 nm, PRBS of 1 V.
        let noise_fit = StageParams { a0: 5.876e6, a1: 71.3, b0: -1120.0 };
        let mut st = status(|e| {
            (e[1].0, e[2].0, e[1].1.innovation_rms_um, e[2].1.innovation_rms_um) = (noise_fit, noise_fit, 0.007, 0.007)
        });
        (st.estimates[0].0, st.estimates[3].0) = (noise_fit, noise_fit);
        st.excitation_level.power = 2.5;
        assert!(compare_ekfs(&st).is_some_and(|d| d.ekfs.0 == 0), "they agree");
        assert!(response_ratio(&st, 2).is_some_and(|r| (r - 1.46).abs() < 0.01), "{:?}", response_ratio(&st, 2));
        assert_eq!(trusted_ekf_estimate(&st, 2), None);
        // No innovations yet, no resonance, no damping, no input.
        for rms in [f32::NAN, 0.0] {
            assert_eq!(response_ratio(&status(|e| e[2].1.innovation_rms_um = rms), 2), None, "innovations {rms}");
        }
        for a0 in [-1.0, 0.0] {
            assert_eq!(response_ratio(&status(|e| e[2].0.a0 = a0), 2), None, "a0 {a0}");
        }
        assert_eq!(response_ratio(&status(|_| ()), 0), None, "the RLS has no innovations");
        assert_eq!(response_ratio(&status(|e| e[2].0.a1 = 0.0), 2), Some(0.0));
        let mut st = status(|_| ());
        st.excitation_level.power = 0.0;
        assert_eq!(trusted_ekf_estimate(&st, 2), None);
    }

    #[test]
    fn a_weak_response_is_told_only_where_the_ekfs_agree_with_the_reference() {
        assert_eq!(weak_response(&status(|_| ())), None, "784");
        // The hybrid EKF's ratio 7.84 (innovations 10 times larger, the input 10 times smaller).
        let weak = |e: &mut [(StageParams<f32>, Health); 4]| {
            (e[1].1.innovation_rms_um, e[2].1.innovation_rms_um) = (0.05, 0.05)
        };
        let mut st = status(weak);
        st.excitation_level.power = 0.01;
        let r = weak_response(&st).unwrap();
        assert!(r.ekf == 2 && (r.ratio - 7.8375).abs() < 1e-3, "{r:?}");
        // The continuous EKF's when the hybrid one does not run or adapt.
        st.selected = EstimatorSet(0b1011);
        assert_eq!(weak_response(&st).map(|r| r.ekf), Some(1));
        st.estimates[1].1.adaptation = Adaptation::Frozen;
        assert_eq!(weak_response(&st), None, "no EKF adapting");
        // Not where they disagree (that note stands), nor without a verdict (the RLS and the ARX apart).
        let mut st = status(|e| {
            weak(e);
            e[2].0 = moved(2.0)
        });
        st.excitation_level.power = 0.01;
        assert_eq!(weak_response(&st), None);
        let mut st = status(|e| {
            weak(e);
            e[0].0 = moved(2.0)
        });
        st.excitation_level.power = 0.01;
        assert_eq!((compare_ekfs(&st), weak_response(&st)), (None, None));
    }

    #[test]
    fn the_reference_is_the_arx_else_the_rls_and_they_must_agree() {
        let ekfs_off = |e: &mut [(StageParams<f32>, Health); 4]| (e[1].0, e[2].0) = (moved(2.0), moved(2.0));
        assert_eq!(disagreement(&status(ekfs_off)).map(|d| d.reference), Some(3));
        // The ARX held (or not running): the RLS.
        let held = |e: &mut [(StageParams<f32>, Health); 4]| {
            ekfs_off(e);
            e[3].1.held = true;
        };
        assert_eq!(disagreement(&status(held)).map(|d| d.reference), Some(0));
        let mut s = status(ekfs_off);
        s.selected = EstimatorSet(0b0111);
        assert_eq!(disagreement(&s).map(|d| (d.reference, d.ekfs)), Some((0, EstimatorSet(0b110))));
        // The RLS and the ARX apart: no verdict.
        let apart = |e: &mut [(StageParams<f32>, Health); 4]| {
            ekfs_off(e);
            e[0].0 = moved(1.3);
        };
        assert_eq!(compare_ekfs(&status(apart)), None);
        // No reference, no EKF, a reference with no resonance: no verdict. An EKF not running is not judged.
        for selected in [0b0110, 0b1001] {
            let mut s = status(ekfs_off);
            s.selected = EstimatorSet(selected);
            assert_eq!(compare_ekfs(&s), None, "{selected:#b}");
        }
        let no_resonance = |e: &mut [(StageParams<f32>, Health); 4]| {
            ekfs_off(e);
            e[3].0.a0 = 0.0;
            e[0].1.held = true;
        };
        assert_eq!(compare_ekfs(&status(no_resonance)), None);
        let nan_reference = |e: &mut [(StageParams<f32>, Health); 4]| {
            ekfs_off(e);
            e[3].0.a0 = f32::NAN;
            e[0].1.held = true;
        };
        assert_eq!(compare_ekfs(&status(nan_reference)), None);
        let mut s = status(|e| e[1].0 = moved(2.0));
        s.selected = EstimatorSet(0b1101);
        assert_eq!(disagreement(&s), None, "the continuous EKF off");
    }

    #[test]
    fn the_estimated_resonance_is_the_hybrid_ekfs_else_a_references_and_needs_a_resonance() {
        let f0 = STAGE.f0_hz() as f64;
        assert_eq!(estimated_resonance(&status(|_| ())), Some((f0, 2)));
        // The EKFs off the reference: the ARX's. The hybrid EKF off: the first running estimator's, the RLS's.
        assert_eq!(estimated_resonance(&status(|e| e[2].0 = moved(2.0))), Some((f0, 3)));
        let mut s = status(|_| ());
        s.selected = EstimatorSet(0b1011);
        assert_eq!(estimated_resonance(&s), Some((f0, 0)));
        // The RLS alone (no EKF to judge), with no resonance: `a0` zero, negative, infinite or not a number.
        for a0 in [0.0, -1.0, f32::INFINITY, f32::NAN] {
            let mut s = status(|e| e[0].0.a0 = a0);
            s.selected = EstimatorSet(0b0001);
            assert_eq!(estimated_resonance(&s), None, "a0 {a0}");
        }
        let mut s = status(|_| ());
        s.selected = EstimatorSet(0);
        assert_eq!(estimated_resonance(&s), None, "none running");
    }

    #[test]
    fn a_resonance_too_fast_for_the_continuous_ekf_is_told_once_after_2_s() {
        let khz = |e: &mut [(StageParams<f32>, Health); 4]| e.iter_mut().for_each(|(p, _)| *p = moved(1000.0 / 422.9));
        let f = fast_resonance(&status(khz), 1e4).expect("1 kHz at 10 kHz");
        assert_eq!(f.estimator, 2, "the hybrid EKF's");
        assert!((f.f0_hz / 1000.0 - 1.0).abs() < 1e-4 && (f.wt - 0.2 * core::f64::consts::PI).abs() < 1e-4, "{f:?}");
        // Not at the paper's stage, nor at 20 kHz, nor with the continuous EKF off, nor while the EKFs disagree.
        assert_eq!(fast_resonance(&status(|_| ()), 1e4), None);
        assert_eq!(fast_resonance(&status(khz), 2e4), None);
        let mut off = status(khz);
        off.selected = EstimatorSet(0b1101);
        assert_eq!(fast_resonance(&off, 1e4), None);
        let apart = |e: &mut [(StageParams<f32>, Health); 4]| {
            khz(e);
            e[1].0 = STAGE;
        };
        assert_eq!(fast_resonance(&status(apart), 1e4), None);
        // The hybrid EKF off: the first running estimator's, the RLS's.
        let mut no_hekf = status(khz);
        no_hekf.selected = EstimatorSet(0b1011);
        assert_eq!(fast_resonance(&no_hekf, 1e4).map(|f| f.estimator), Some(0));
        // Told on the 20th look in a row, once; again after a look without.
        let mut watch = EventWatch::new(1e4);
        let told: Vec<bool> = (0..100).map(|_| watch.look(&status(khz)).fast_resonance.is_some()).collect();
        assert_eq!((told.iter().position(|&t| t), told.iter().filter(|&&t| t).count()), (Some(19), 1));
        assert_eq!(watch.look(&status(|_| ())), News::default());
        assert_eq!((0..20).filter(|_| watch.look(&status(khz)).fast_resonance.is_some()).count(), 1);
    }

    #[test]
    fn the_watch_tells_a_disagreement_once_after_2_s() {
        let mut watch = EventWatch::new(1e4);
        let (agree, off) = (status(|_| ()), status(|e| e[2].0 = moved(2.0)));
        let told = |watch: &mut EventWatch, s: &Status<f32>, looks: usize| {
            (0..looks).map(|_| watch.look(s).disagreement.is_some()).collect::<Vec<_>>()
        };
        // One look short, then agreement: nothing; enough in a row: told on the last, and not again while it lasts.
        let looks = WARNING_LOOKS as usize;
        assert!(!told(&mut watch, &off, looks - 1).contains(&true));
        assert!(!told(&mut watch, &agree, 1)[0]);
        let spell = told(&mut watch, &off, 300);
        assert_eq!(spell.iter().position(|&t| t), Some(looks - 1));
        assert_eq!(spell.iter().filter(|&&t| t).count(), 1, "{spell:?}");
        // Looks with no verdict (the RLS and the ARX apart) neither end a spell nor count in it.
        let undecided = status(|e| (e[2].0, e[0].0) = (moved(2.0), moved(1.3)));
        assert_eq!(compare_ekfs(&undecided), None);
        assert!(!told(&mut watch, &undecided, 300).contains(&true));
        assert!(!told(&mut watch, &off, 300).contains(&true), "the same spell");
        told(&mut watch, &agree, 1);
        told(&mut watch, &off, looks - 2);
        told(&mut watch, &undecided, 5);
        assert_eq!(told(&mut watch, &off, 2), [false, true]);
        // Over: the next spell is told again.
        told(&mut watch, &agree, 1);
        assert_eq!(told(&mut watch, &off, looks).iter().filter(|&&t| t).count(), 1);
        let news = watch.look(&agree);
        assert_eq!(news, News::default());
    }
}
