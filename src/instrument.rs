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
use crate::estimator::{Estimator, Health, PeLevel};
use crate::estimators::{full_bank, restart_bank, FullBank, TuningConfig};
use crate::hal::{run_sample_with, StageBoard};
use crate::pipeline::{FaultCounters, Faults, Pipeline, PipelineConfig, SampleOutput};
use crate::record::RawSample;
use crate::{Real, StageParams};

/// Samples the recording ring holds: 0.1 s at 10 kHz, 4 KiB (the firmware's static RAM stays under 16 KiB).
pub const RECORD_BUFFER: usize = 1024;

/// A change prepared at low priority and applied whole between two samples.
#[derive(Clone, Debug, Default)]
pub struct Change<T> {
    /// A new pipeline configuration (excitation, limits, selection, scaling).
    pub config: Option<PipelineConfig<T>>,
    /// New tuning: the estimators restart with it (from their initial parameters and `P0`).
    pub tuning: Option<TuningConfig<T>>,
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
        // The code in effect over this period: the one written now, or, with the board's delay, the last one.
        let in_effect = if self.config.actuation_delay_samples == 0 { out.dac_code } else { self.code_in_effect };
        self.code_in_effect = out.dac_code;
        if self.record.active {
            self.record_sample(RawSample { u_code: in_effect as u16, y_code: out.probe_code as u16 });
        }
        out
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
            self.config = *cfg;
        }
        let bank = &mut self.pipeline.estimators;
        if let Some(t) = &c.tuning {
            restart_bank(bank, t);
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
        self.ring[(self.ring_head + self.ring_len) % RECORD_BUFFER] = s;
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
        for (k, o) in out[..n].iter_mut().enumerate() {
            *o = self.ring[(self.ring_head + k) % RECORD_BUFFER];
        }
        let first = self.ring_first;
        self.ring_head = (self.ring_head + n) % RECORD_BUFFER;
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
    /// most of it), so it runs from RAM on the board like the interrupt (src/bin/nanopos-fw/ram_code.rs), to keep the
    /// delay it can add to a sample well inside the deadline's slack.
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

/// What grew since the last look at the interrupt's [`Status`]: for the telemetry, which warns once per event rather
/// than leaving the user to read it off climbing counters. Numeric resets matter most: a tuning the data drive to
/// non-finite values resets an estimator over and over, each time back to its initial parameters and `adapting`,
/// so its parameters look steady while nothing is identified.
#[derive(Clone, Copy, Debug, Default)]
pub struct EventWatch {
    /// The counts at the last look (nothing seen: all zero).
    seen: News,
    /// Whether the output limits changed commands in the interval the last look covered.
    limited_before: bool,
}

/// Events since the last look ([`EventWatch::look`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct News {
    /// Numeric resets per estimator, in the bank's order.
    pub resets: [u32; 4],
    /// Deadline misses.
    pub deadline_misses: u32,
    /// ADC overruns.
    pub adc_overruns: u32,
    /// Samples whose command the output limits changed ([`crate::pipeline::FaultCounters::limited`]).
    pub limited: u32,
    /// The limits changed commands both since the last look and in the interval before it: the excitation does not
    /// fit them. A single step of the command (a start about an offset: a sample or two, once) does not count.
    pub limiting: bool,
}

impl EventWatch {
    /// The counts' growth since the last look. A count that went down was restarted (a new tuning restarts the
    /// estimators and their health): all of it is new.
    pub fn look<T>(&mut self, status: &Status<T>) -> News {
        let now = News {
            resets: core::array::from_fn(|i| status.estimates[i].1.numeric_resets),
            deadline_misses: status.counters.deadline_misses,
            adc_overruns: status.counters.adc_overruns,
            limited: status.counters.limited,
            limiting: false,
        };
        let grown = |now: u32, seen: u32| if now >= seen { now - seen } else { now };
        let limited = grown(now.limited, self.seen.limited);
        let news = News {
            resets: core::array::from_fn(|i| grown(now.resets[i], self.seen.resets[i])),
            deadline_misses: grown(now.deadline_misses, self.seen.deadline_misses),
            adc_overruns: grown(now.adc_overruns, self.seen.adc_overruns),
            limited,
            limiting: limited > 0 && self.limited_before,
        };
        self.limited_before = limited > 0;
        self.seen = now;
        news
    }
}
