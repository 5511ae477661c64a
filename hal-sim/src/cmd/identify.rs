//! `nanopos-sim identify --input FILE.csv [--estimators rls,ekf,hekf,arx] [--tuning prbs|triangle]
//! [--window T0:T1]... [--out EST.csv] [--summary SUMMARY.json] [--plot FIG.svg] [--health HEALTH.csv]
//! [--dac-step V] [--spike-ratio N] [--precision f64|f32]`
//!
//! Runs the firmware's pipeline ([`nanopos_id::pipeline::Pipeline::replay`]: spike gate, filter replicas,
//! pre-filter, estimators) on a recorded run: `t,u,y` with `u` the command in effect over each sample and `y` the
//! reading at its start (the convention of `simulate` and of the firmware's recording); `a0,a1,b0` columns, when
//! present, are the truth and are reported next to the estimates.
//!
//! - `EST.csv`: `t,estimator,a0,a1,b0,f0_hz,zeta,dc_gain` at 100 Hz.
//! - `HEALTH.csv`: on the same rows, `t,estimator,state,rejected,changes,resets,repairs,innovation_rms_um`: each
//!   estimator's health as the board's `status` gives it (the counts since the record's start; the innovation RMS of
//!   the last second, empty for `rls` and `arx`): when an EKF saw the change, whether the monitor held it, how well
//!   its model followed the data, when the ARX's parameters were `held`.
//! - `--precision`: the scalar of the pipeline and the estimators, f64 (the reference, default) or f32 (the
//!   firmware's: the board's results on the same samples, and its refusal of a tuning f32 cannot hold).
//! - `SUMMARY.json`: `precision` (`"f64"` or `"f32"`), then per window, each estimator's mean parameters over it and
//!   the validation RMSE of SPEC section 7: model (1) with those means, simulated exactly (zero-order hold) on the
//!   replica input `u'` from zero state one second before the window (the transient of the wrong start has decayed
//!   by e^-38 by then), against `y'`; and the estimator's own innovation RMS (of the last second) averaged over the
//!   window (`null` for the RLS-type estimators), the health view of the same question: far above the noise floor, the
//!   model does not fit; and `starved`, the share of the window the excitation monitor held the estimator (input too
//!   weak, or a single sinusoid; sampled with the 100 Hz rows), where the mean is of held values; and `held`, the share
//!   of the window the estimator's parameters were held (the ARX's, while its discrete model had no continuous
//!   equivalent: not yet converged), where the mean is of the last it could report; and `resets`, the times in the
//!   window the estimator met a non-finite value (or an EKF an innovation beyond a metre, or no relock within 5 s of a
//!   start or a change) and went back to its initial parameters (a tuning that does not suit the record resets it over
//!   and over, and its mean is then of runs that diverged). Above 10 % starved or held, or any reset, a note on
//!   standard error says so ([`health_notes`]); and of a window the record does not wholly cover, what its figures are
//!   of; and of a window whose resonance is far from the pre-filter's centre; and of an estimator whose means are not
//!   of a stage (`a0 <= 0` or not finite: it diverged) or whose validation RMSE is more than 3 times the best one's in
//!   the window (not yet converged, or diverged); and of a sample of `u` or `y` more than 1 000 times the level 90 % of
//!   the record stays within (a glitch, or a logger's overflow value: of `y`, whether the spike gate replaced it; else
//!   the filters spread it over tenths of a second, and the estimators take it for data); and of the readings the spike
//!   gate replaced.
//! - Windows default to the last quarter of each half of the record: the paper's payload-on, payload-off layout.
//! - The excitation monitor discounts the input's DAC steps (`PipelineConfig::command_lsb_v`): by default the
//!   board's (4.88 mV, what `simulate` and `decode` write), `--dac-step V` for a record from elsewhere (0: not
//!   rounded).
//! - The spike gate ([`nanopos_id::filters::spike`]) replaces a reading out of line with the three before it, as on
//!   the board, with the tuning's ratio (`spike_ratio`: 32, the firmware's default, or the board's in a tuning file
//!   `decode` wrote); `--spike-ratio N` another, 0 the gate off. A note counts the readings it replaced.
//!
//! It uses every core: the CSV is parsed in parallel pieces ([`crate::csv`]) and the estimators run on worker
//! threads fed by the pipeline (same results as one loop, bit for bit). Memory: the file is read a block (8 MiB) at
//! a time; what is held is the 100 Hz rows (about 130 bytes each with four estimators and the truth) and, for each
//! window's validation, the replicas' `u'`, `y'` and `t` from a second before it to its end (24 bytes a sample).
//! The default windows need the record's last time before the rest: it is read from the end of the file.

use super::{fail, json_number, show, sig, CliError, OutputFile, Progress, Spread};
use crate::bank::{Bank, Tuning, NAMES};
use crate::board::SimBoard;
use crate::csv::{Reader, Time};
use crate::tuning::TuningArg;
use nanopos_id::estimator::{Adaptation, EstimatorBank, FilteredSample, Health};
use nanopos_id::estimators::ekf::EkfDesign;
use nanopos_id::filters::PrefilterDesign;
use nanopos_id::hal::StageBoard;
use nanopos_id::linalg::zoh;
use nanopos_id::pipeline::{Pipeline, PipelineSettings, SettingsError};
use nanopos_id::{Real, StageParams};
use std::io::Write;
use std::path::Path;
use std::sync::Arc;

/// An estimation window `[t0, t1)`, s.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Window {
    /// Start, s.
    pub t0: f64,
    /// End, s.
    pub t1: f64,
}

/// As `--window` takes it, `T0:T1`, each number as a message writes it ([`show`]).
impl std::fmt::Display for Window {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}:{}", show(self.t0), show(self.t1))
    }
}

impl std::str::FromStr for Window {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("'{s}': expected T0:T1 in seconds with T0 < T1 (e.g. 75:100)");
        let (a, b) = s.split_once(':').ok_or_else(bad)?;
        let (t0, t1): (f64, f64) = (a.trim().parse().map_err(|_| bad())?, b.trim().parse().map_err(|_| bad())?);
        if !(t0.is_finite() && t1.is_finite() && t0 < t1) {
            return Err(bad());
        }
        Ok(Window { t0, t1 })
    }
}

/// One estimator's figures over one window.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WindowFigures {
    /// Mean estimate.
    pub mean: StageParams<f64>,
    /// Validation RMSE, nm.
    pub rmse_nm: f64,
    /// Mean of the estimator's own innovation RMS over the window, nm (`NaN` if it reports none): far above the
    /// noise, the model does not fit (health's view; the RMSE is the validation's).
    pub innovation_rms_nm: f64,
    /// Share of the window's rows (0 to 1) at which the excitation monitor held the estimator (`Starved`): where it
    /// is large, the mean is of held values, not of what this input identifies (`NaN` for the truth).
    pub starved: f64,
    /// Share of the window's rows (0 to 1) at which the estimator's parameters were held ([`Health::held`]: the
    /// ARX's, while its discrete model had no continuous equivalent, as it can have before it converges): where it is
    /// large, the mean is of the last parameters it could report (`NaN` for the truth).
    pub held: f64,
    /// Numeric resets in the window (sampled with the 100 Hz rows; 0 for the truth).
    pub resets: u32,
    /// RMS of the reading `y` about its mean over the window, nm: what a model has to explain (the same for every
    /// estimator of the window; [`RESPONSE_MIN`]).
    pub reading_rms_nm: f64,
    /// How fast the input moves over the window: the frequency of a sine whose change from sample to sample has the
    /// same RMS, relative to its own, as the input's ([`input_rms_hz`]; the same for every estimator of the window).
    pub input_rms_hz: f64,
    /// How strongly the input reaches the estimators: its pre-filtered power over the window (the excitation
    /// monitor's) relative to the paper's 1 V PRBS's through the same pipeline ([`prbs_power_v2`]; the same for
    /// every estimator of the window).
    pub input_strength: f64,
    /// RMS of the model's output about its mean over the window, nm, driven by the input as in the validation: the
    /// response the model gives the input ([`validation_nm`]).
    pub model_rms_nm: f64,
    /// Mean of the validation's residual (the reading less the model's output) over the window, nm: a constant the
    /// reading has and model (1) does not (the probe's zero, the stage's position, drift), which the RMSE includes.
    pub offset_nm: f64,
    /// The validation's RMS about the residual's mean ([`Self::offset_nm`]), nm: how well the model follows the
    /// reading, whatever constant the reading sits at. What the estimators are compared by (on the paper's records
    /// within 0.5 % of the RMSE; with a probe's offset, the RMSE's ranking would be that of the models' responses to
    /// the input's mean against the offset).
    pub fit_nm: f64,
}

/// The result of a run.
pub struct Identified {
    /// Estimator names, in report order.
    pub names: Vec<&'static str>,
    /// Time of each 100 Hz row, s.
    pub times: Vec<f64>,
    /// Estimates per row, in `names` order.
    pub estimates: Vec<Vec<StageParams<f64>>>,
    /// Health per row (the innovation RMS, whether the excitation monitor held the estimator, ...), in `names` order.
    pub healths: Vec<Vec<Health>>,
    /// Truth per row, when the input has it.
    pub truth: Option<Vec<StageParams<f64>>>,
    /// Windows and, per window, the figures of each estimator in `names` order, and the truth's when known: its
    /// mean and the validation RMSE of model (1) with it, the least any estimate can reach on this data.
    pub windows: Vec<(Window, Vec<WindowFigures>, Option<WindowFigures>)>,
    /// The times of the record's first and last samples, s.
    pub span: (f64, f64),
    /// The record's sample period, s.
    pub period: f64,
    /// The scalar the pipeline and the estimators ran in: `"f64"`, or `"f32"`, the firmware's.
    pub precision: &'static str,
    /// The stage's pre-filter `W_p` the tuning gave (the pipeline's, and the continuous-time RLS's own).
    pub prefilter: PrefilterDesign,
    /// The EKFs' process noise `diag(Q)` the tuning gave (the paper's units).
    pub ekf_q: [f64; 5],
    /// How large the record's `u` and `y` run (for the note of a wild sample).
    pub spread: [Spread; 2],
    /// The readings the pipeline's spike gate replaced.
    pub spikes: Spikes,
}

/// The readings of `y` the pipeline's spike gate replaced ([`nanopos_id::filters::spike`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct Spikes {
    /// The gate's ratio (0: off).
    pub ratio: u16,
    /// How many.
    pub count: u32,
    /// The first one's time, s.
    pub first_at: f64,
    /// The largest `|y|` of the readings the gate took (the estimators' data), um.
    pub largest_taken: f64,
}

/// The input's step for one DAC code that `identify` assumes without `--dac-step`, V: the simulated board's, which is
/// the firmware's (3.3 V / 4096 / 0.165, 4.88 mV).
pub fn default_dac_step_v() -> f64 {
    let board = SimBoard::new(Default::default());
    PipelineSettings::default().design::<f64>(&board.description()).map_or(f64::NAN, |c| c.command_lsb_v)
}

/// Parse `--estimators`.
pub fn parse_estimators(list: &str) -> Result<Vec<&'static str>, CliError> {
    let mut out = Vec::new();
    for name in list.split(',').map(str::trim) {
        match NAMES.iter().find(|n| **n == name) {
            Some(n) if !out.contains(n) => out.push(*n),
            Some(_) => return fail(format!("--estimators: '{name}' given twice")),
            None => return fail(format!("--estimators: unknown estimator '{name}' (known: {})", NAMES.join(","))),
        }
    }
    Ok(out)
}

/// A recorded run, as columns.
#[derive(Clone, Copy)]
pub struct Recording<'a> {
    /// Where it came from (for messages).
    pub source: &'a str,
    /// Time, s.
    pub t: &'a [f64],
    /// Command in effect, V.
    pub u: &'a [f64],
    /// Reading, um.
    pub y: &'a [f64],
    /// Columns `a0`, `a1`, `b0` of the truth, if known.
    pub truth: Option<&'a [Vec<f64>]>,
}

/// Identify on a recording, in f64.
pub fn identify(
    rec: &Recording,
    names: &[&'static str],
    tuning: &Tuning,
    windows: &[Window],
) -> Result<Identified, CliError> {
    identify_in::<f64>(rec, names, tuning, windows)
}

/// Identify on a recording with the pipeline and estimators in scalar `T` (f32: the firmware's precision).
pub fn identify_in<T: Real>(
    rec: &Recording,
    names: &[&'static str],
    tuning: &Tuning,
    windows: &[Window],
) -> Result<Identified, CliError> {
    let (rows, last_t, has_truth) = (rec.t.len() as u64, rec.t.last().copied(), rec.truth.is_some());
    identify_streamed::<T>(rec.source, rows, last_t, has_truth, names, tuning, windows, rec.blocks(1 << 16))
}

/// Identify on a record that arrives in blocks (the columns `u`, `y`, `t`, then the truth's `a0`, `a1`, `b0` if
/// `has_truth`; each block with the row it reaches), `rows` in all, the last at `last_t`: the record is never held.
#[allow(clippy::too_many_arguments)]
pub(crate) fn identify_streamed<T: Real>(
    source: &str,
    rows: u64,
    last_t: Option<f64>,
    has_truth: bool,
    names: &[&'static str],
    tuning: &Tuning,
    windows: &[Window],
    blocks: impl Iterator<Item = Result<(Vec<Vec<f64>>, u64), CliError>>,
) -> Result<Identified, CliError> {
    let record = Stream { source, last_t, has_truth, progress_total: rows, dac_step_v: None, spike_ratio: None };
    identify_blocks::<T>(&record, names, &TuningArg::from(*tuning), windows, blocks)
}

impl<'a> Recording<'a> {
    /// The record as [`identify_blocks`] takes it: blocks of `rows` rows (copied), each with the row it reaches.
    fn blocks(self, rows: usize) -> impl Iterator<Item = Result<(Vec<Vec<f64>>, u64), CliError>> + 'a {
        let n = self.t.len();
        (0..n).step_by(rows).map(move |start| {
            let end = (start + rows).min(n);
            let mut block = vec![self.u[start..end].to_vec(), self.y[start..end].to_vec(), self.t[start..end].to_vec()];
            block.extend(self.truth.into_iter().flatten().map(|c| c[start..end].to_vec()));
            Ok((block, end as u64))
        })
    }
}

/// A recorded run as it arrives in blocks (see [`identify_blocks`]).
struct Stream<'a> {
    /// Where it came from (for messages).
    source: &'a str,
    /// The time of the last row, when known before the blocks are read (needed for the default windows; without
    /// it every row's `u'` and `y'` are kept until the end).
    last_t: Option<f64>,
    /// Whether the blocks carry the truth.
    has_truth: bool,
    /// Progress units of the whole record (each block says how far it reaches).
    progress_total: u64,
    /// The input's step for one DAC code, V, which the excitation monitor discounts (`None`: the simulated board's).
    dac_step_v: Option<f64>,
    /// The spike gate's ratio (`None`: the tuning's).
    spike_ratio: Option<u16>,
}

/// What is kept of the pipeline's output for the validation of one window: `t`, `u'`, `y'` from a second before the
/// window to its end (or everything, when the windows are not known before the end).
#[derive(Default)]
struct Kept {
    from: f64,
    to: f64,
    t: Vec<f64>,
    u: Vec<f64>,
    y: Vec<f64>,
    /// The pre-filtered input's power as the excitation monitor measures it (`FilteredSample::pe`), V^2: in f32,
    /// half the memory, for a figure a note gives to three digits.
    pe: Vec<f32>,
}

/// The identification of a record that comes in blocks, each the columns `u`, `y`, `t` and, when the record has
/// it, the truth's `a0`, `a1`, `b0`, with how far into the record it reaches (progress units). Nothing of the record
/// is held but the 100 Hz rows and the samples the windows' validation needs.
fn identify_blocks<T: Real>(
    record: &Stream,
    names: &[&'static str],
    tuning: &TuningArg,
    windows: &[Window],
    mut blocks: impl Iterator<Item = Result<(Vec<Vec<f64>>, u64), CliError>>,
) -> Result<Identified, CliError> {
    let source = record.source;
    let defaulted = windows.is_empty();
    // The start and the sample period, from the first rows.
    let mut head: Vec<Vec<f64>> = Vec::new();
    let mut done = 0;
    while head.first().map_or(0, Vec::len) < 4 {
        let Some(next) = blocks.next() else { break };
        let (block, reached) = next?;
        done = reached;
        if head.is_empty() {
            head = block;
        } else {
            head.iter_mut().zip(block).for_each(|(c, b)| c.extend_from_slice(&b));
        }
    }
    let n_head = head.first().map_or(0, Vec::len);
    if n_head < 4 {
        return fail(format!("{source}: too few rows ({n_head}): identification needs a record of at least 4 samples"));
    }
    let (t_first, dt) = (head[2][0], head[2][1] - head[2][0]);
    // The tuning at the record's sample period: its values' ranges and whether the estimators can run it depend on
    // it (a tuning is not checked at the board's 10 kHz when it is read).
    let (name, tuning) = (&tuning.name, tuning.at(dt)?);
    // A time column in ms or in samples reads as a record sampled 1 000 or 10 000 times too slowly: say that, rather
    // than what it does to the pre-filter's RK4 step. A record fast enough for the paper's band has its time right,
    // and the tuning's band is the one to question.
    let f_p = tuning.rls.prefilter.f_p_hz;
    if 1.0 / dt <= 2.0 * f_p {
        let question = if 1.0 / dt > 2.0 * PrefilterDesign::default().f_p_hz {
            format!("is {name}'s f_p in Hz, and below {} Hz?", show(0.5 / dt))
        } else {
            "is t in seconds? (a header's `t [ms]` reads it in ms)".to_string()
        };
        return fail(format!(
            "{source}: a sample every {} s ({} Hz) cannot show the pre-filter's band at {} Hz ({name}'s f_p), which \
             needs more than {} samples a second: {question}",
            show(dt),
            show(1.0 / dt),
            show(f_p),
            show(2.0 * f_p)
        ));
    }
    tuning.runnable::<T>().map_err(|u| {
        CliError(format!("{name}: at the sample period of {source} ({} s), in {}: {u}", show(dt), T::NAME))
    })?;
    // The stage's pre-filter is the tuning's (the continuous-time RLS has its own copy of it), the replicas matched
    // at its centre as on the board; so is the spike gate's ratio (the board's, in a file `decode` wrote), unless
    // `--spike-ratio` is given.
    let mut settings =
        PipelineSettings { sample_rate_hz: 1.0 / dt, ..PipelineSettings::default() }.with_stage_of(&tuning);
    if let Some(ratio) = record.spike_ratio {
        settings.faults.spike_ratio = ratio;
    }
    let board = SimBoard::new(Default::default());
    let mut cfg = settings.design::<T>(&board.description()).map_err(|e| {
        // The replicas are the board's analog filters, not the record's: say so, and what they need.
        let board_filters = match e {
            SettingsError::FilterFrequency { filter, .. } if filter.ends_with(" replica") => {
                let highest = [settings.reconstruction, settings.antialias]
                    .iter()
                    .flat_map(|r| [r.cutoff_hz, r.prewarp_hz])
                    .chain([settings.lags.match_hz])
                    .fold(0.0, f64::max);
                format!(
                    " (identify replicates the board's analog filters, as the board does: they need more than {} \
                     samples a second)",
                    show(2.0 * highest)
                )
            }
            _ => String::new(),
        };
        CliError(format!("{source}: sample period {} s: {e}{board_filters}", show(dt)))
    })?;
    if let Some(step) = record.dac_step_v {
        cfg.command_lsb_v = step;
    }
    let default_windows = |t_last: f64| {
        let (start, end) = (t_first, t_last + dt);
        let half = (end - start) / 2.0;
        let window = |t0: f64, t1: f64| Window { t0: tidy(t0, dt), t1: tidy(t1, dt) };
        vec![window(start + 0.75 * half, start + half), window(start + 1.75 * half, end)]
    };
    let planned = match (windows.is_empty(), record.last_t) {
        (false, _) => Some(windows.to_vec()),
        (true, Some(t_last)) => Some(default_windows(t_last)),
        (true, None) => None,
    };
    let prbs_power = prbs_power_v2(&cfg);
    let mut kept: Vec<Kept> = match &planned {
        Some(ws) => ws.iter().map(|w| Kept { from: w.t0 - 1.0, to: w.t1, ..Kept::default() }).collect(),
        None => vec![Kept { from: f64::NEG_INFINITY, to: f64::INFINITY, ..Kept::default() }],
    };

    // The pipeline runs here; the estimators, which only read its output, run on worker threads in groups of about
    // equal cost, fed blocks of filtered samples. Each estimator sees exactly the sequence it would in one loop.
    let mut pipeline = Pipeline::new(&cfg, ());
    let every = ((0.01 / dt).round() as usize).max(1);
    let names: Vec<&'static str> = NAMES.iter().copied().filter(|n| names.contains(n)).collect();
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get());
    let groups = cost_groups(&names, workers);
    let (mut times, mut truth_rows) = (Vec::new(), Vec::new());
    let (mut n, mut t_last) = (0usize, t_first);
    let mut spread = [Spread::default(), Spread::default()];
    let mut spikes = Spikes { ratio: settings.faults.spike_ratio, ..Spikes::default() };
    let mut progress = Progress::new("identify", record.progress_total);
    let results: Result<Vec<GroupRows>, CliError> = std::thread::scope(|scope| {
        let (feeds, jobs): (Vec<_>, Vec<_>) = groups
            .iter()
            .map(|group| {
                let (tx, rx) = std::sync::mpsc::sync_channel::<Arc<Vec<FilteredSample<T>>>>(4);
                let tuning = &tuning;
                (tx, scope.spawn(move || run_group::<T>(group, tuning, every, rx)))
            })
            .unzip();
        let mut filtered = Vec::with_capacity(BLOCK);
        let mut run = |cols: &[Vec<f64>]| {
            let (u, y, t) = (&cols[0], &cols[1], &cols[2]);
            for k in 0..t.len() {
                spread[0].add(u[k], t[k]);
                spread[1].add(y[k], t[k]);
                let s = pipeline.replay(&cfg, T::of(u[k]), T::of(y[k]));
                let replaced = pipeline.fault_counters().spikes;
                let spike = replaced != spikes.count;
                if spike && spikes.count == 0 {
                    spikes.first_at = t[k];
                }
                spikes.count = replaced;
                if !spike {
                    spikes.largest_taken = spikes.largest_taken.max(y[k].abs());
                }
                for keep in kept.iter_mut().filter(|keep| t[k] >= keep.from && t[k] < keep.to) {
                    keep.t.push(t[k]);
                    keep.u.push(s.u.as_f64());
                    keep.y.push(s.y.as_f64());
                    keep.pe.push(s.pe.power.as_f64() as f32);
                }
                filtered.push(s);
                n += 1;
                if n % every == 0 {
                    times.push(t[k]);
                    if record.has_truth {
                        truth_rows.push(StageParams { a0: cols[3][k], a1: cols[4][k], b0: cols[5][k] });
                    }
                }
                if filtered.len() == BLOCK {
                    feed_all(&feeds, std::mem::replace(&mut filtered, Vec::with_capacity(BLOCK)));
                }
            }
            t_last = t.last().copied().unwrap_or(t_last);
        };
        run(&head);
        progress.update(done);
        let mut failed = None;
        for next in blocks.by_ref() {
            match next {
                Ok((cols, reached)) => {
                    run(&cols);
                    progress.update(reached);
                }
                Err(e) => {
                    failed = Some(e);
                    break;
                }
            }
        }
        if !filtered.is_empty() {
            feed_all(&feeds, filtered);
        }
        drop(feeds);
        let rows = jobs.into_iter().map(|j| j.join().expect("an estimator worker does not panic")).collect();
        match failed {
            Some(e) => Err(e),
            None => Ok(rows),
        }
    });
    progress.finish();
    let results = results?;
    let windows = match planned {
        Some(ws) => ws,
        None => default_windows(t_last),
    };
    if defaulted && record.last_t.is_some_and(|t| t != t_last) {
        return fail(format!("{source}: the file changed while it was read (its last time {} s)", show(t_last)));
    }
    // Rows in report order: each estimator's column from its group.
    let column = |name: &str| {
        results
            .iter()
            .find_map(|g| g.names.iter().position(|n| *n == name).map(|i| (g, i)))
            .expect("every estimator ran")
    };
    let columns: Vec<_> = names.iter().map(|n| column(n)).collect();
    let (estimates, healths): (Vec<Vec<StageParams<f64>>>, Vec<Vec<Health>>) =
        (0..times.len()).map(|r| columns.iter().map(|(g, i)| (g.estimates[r][*i], g.healths[r][*i])).unzip()).unzip();

    let mut summary = Vec::new();
    for (i, w) in windows.iter().enumerate() {
        let keep = &kept[i.min(kept.len() - 1)];
        let rows: Vec<usize> = (0..times.len()).filter(|&i| times[i] >= w.t0 && times[i] < w.t1).collect();
        if rows.is_empty() {
            // A record of a few tens of ms: its default windows can fall between the rows.
            let rows_at = match times.first() {
                Some(&t) => format!("estimates are taken every {} s from {} s", show(every as f64 * dt), show(t)),
                None => format!("it is shorter than the {} s between estimates", show(every as f64 * dt)),
            };
            // Not asked for: say whose it is and what to do.
            let whose = if defaulted { "default " } else { "" };
            let advice = if defaulted { ": give --window T0:T1, or a longer record" } else { "" };
            return fail(format!(
                "{source}: {whose}window {w} holds no estimate (the record covers {} to {} s; {rows_at}){advice}",
                show(t_first),
                show(t_last)
            ));
        }
        let validation = |p: &StageParams<f64>| validation_nm(p, &keep.t, &keep.u, &keep.y, dt, w);
        let reading_rms_nm = reading_rms_nm(&keep.t, &keep.y, w);
        let input_rms_hz = input_rms_hz(&keep.t, &keep.u, dt, w);
        let pe = inside(&keep.t, &keep.pe, w);
        let input_strength = pe.iter().map(|&p| p as f64).sum::<f64>() / pe.len() as f64 / prbs_power;
        let figures = (0..names.len())
            .map(|col| {
                let mean = mean_params(rows.iter().map(|&i| estimates[i][col]));
                let health = |i: usize| &healths[i][col];
                let innovation_rms_nm =
                    1e3 * rows.iter().map(|&i| health(i).innovation_rms_um as f64).sum::<f64>() / rows.len() as f64;
                let share = |f: &dyn Fn(&Health) -> bool| {
                    rows.iter().filter(|&&i| f(health(i))).count() as f64 / rows.len() as f64
                };
                let starved = share(&|h| h.adaptation == Adaptation::Starved);
                let held = share(&|h| h.held);
                // Counted from the row before the window (the record's start: none yet).
                let before = rows[0].checked_sub(1).map_or(0, |i| health(i).numeric_resets);
                let resets = health(rows[rows.len() - 1]).numeric_resets.wrapping_sub(before);
                let [rmse_nm, model_rms_nm, offset_nm, fit_nm] = validation(&mean);
                WindowFigures {
                    mean,
                    rmse_nm,
                    innovation_rms_nm,
                    starved,
                    held,
                    resets,
                    reading_rms_nm,
                    input_rms_hz,
                    input_strength,
                    model_rms_nm,
                    offset_nm,
                    fit_nm,
                }
            })
            .collect();
        let window_truth = record.has_truth.then(|| {
            let mean = mean_params(rows.iter().map(|&i| truth_rows[i]));
            let [rmse_nm, model_rms_nm, offset_nm, fit_nm] = validation(&mean);
            WindowFigures {
                mean,
                rmse_nm,
                innovation_rms_nm: f64::NAN,
                starved: f64::NAN,
                held: f64::NAN,
                resets: 0,
                reading_rms_nm,
                input_rms_hz,
                input_strength,
                model_rms_nm,
                offset_nm,
                fit_nm,
            }
        });
        summary.push((*w, figures, window_truth));
    }
    let truth = record.has_truth.then_some(truth_rows);
    let span = (t_first, t_last);
    let (precision, prefilter) = (T::NAME, tuning.rls.prefilter);
    Ok(Identified {
        names,
        times,
        estimates,
        healths,
        truth,
        windows: summary,
        span,
        period: dt,
        precision,
        prefilter,
        ekf_q: tuning.ekf.q_diag,
        spread,
        spikes,
    })
}

/// Hand one block of filtered samples to every estimator worker.
fn feed_all<T>(feeds: &[std::sync::mpsc::SyncSender<Arc<Vec<FilteredSample<T>>>>], block: Vec<FilteredSample<T>>) {
    let block = Arc::new(block);
    for feed in feeds {
        feed.send(Arc::clone(&block)).expect("an estimator worker runs until its feed closes");
    }
}

/// The mean of `params`, component by component, in order.
fn mean_params(params: impl ExactSizeIterator<Item = StageParams<f64>> + Clone) -> StageParams<f64> {
    let n = params.len() as f64;
    let m = |f: fn(&StageParams<f64>) -> f64| params.clone().map(|p| f(&p)).sum::<f64>() / n;
    StageParams { a0: m(|p| p.a0), a1: m(|p| p.a1), b0: m(|p| p.b0) }
}

/// Filtered samples per block handed to the estimator workers (256 KiB in f64).
const BLOCK: usize = 4096;

/// Relative cost per sample of each estimator on the host (measured before the hybrid filter's prediction went
/// through the RK4 map's Jacobian: hekf 1.3 s, ekf 0.75 s, rls 0.67 s per 200 s record, arx a tenth of that; the
/// hybrid filter is now 2.5 times cheaper, as on the M4F).
fn cost(name: &str) -> f64 {
    match name {
        "hekf" => 1.6,
        "ekf" => 2.2,
        "rls" => 2.0,
        _ => 0.4,
    }
}

/// `names` in at most `workers` groups of about equal cost (largest first, each to the cheapest group so far).
fn cost_groups(names: &[&'static str], workers: usize) -> Vec<Vec<&'static str>> {
    let mut sorted = names.to_vec();
    sorted.sort_by(|a, b| cost(b).total_cmp(&cost(a)));
    let mut groups: Vec<(f64, Vec<&'static str>)> = vec![(0.0, Vec::new()); workers.clamp(1, names.len().max(1))];
    for name in sorted {
        let g = groups.iter_mut().min_by(|a, b| a.0.total_cmp(&b.0)).expect("at least one group");
        g.0 += cost(name);
        g.1.push(name);
    }
    groups.into_iter().map(|(_, g)| g).filter(|g| !g.is_empty()).collect()
}

/// One group's estimates and health at every reported row, in its bank's order of `names`.
struct GroupRows {
    names: Vec<&'static str>,
    estimates: Vec<Vec<StageParams<f64>>>,
    healths: Vec<Vec<Health>>,
}

/// Run the estimators `group` on every block `feed` delivers, keeping their state every `every` samples.
fn run_group<T: Real>(
    group: &[&'static str],
    tuning: &Tuning,
    every: usize,
    feed: std::sync::mpsc::Receiver<Arc<Vec<FilteredSample<T>>>>,
) -> GroupRows {
    let mut bank = Bank::<T>::new(group, tuning);
    let mut rows =
        GroupRows { names: bank.estimates().map(|(n, _)| n).collect(), estimates: Vec::new(), healths: Vec::new() };
    let mut k = 0;
    for block in feed {
        for s in block.iter() {
            bank.update(s);
            k += 1;
            if k % every == 0 {
                let (estimates, healths) = bank.reports().map(|(_, p, h)| (p.cast::<f64>(), h)).unzip();
                rows.estimates.push(estimates);
                rows.healths.push(healths);
            }
        }
    }
    rows
}

/// The samples of `x` (a column of the record, its times `t`) inside the window: the record is uniformly sampled, so
/// its times are sorted and the window is one slice.
fn inside<'a, X>(t: &[f64], x: &'a [X], w: &Window) -> &'a [X] {
    &x[t.partition_point(|&t| t < w.t0)..t.partition_point(|&t| t < w.t1)]
}

/// The mean square of `x` about its mean (`NaN` if empty).
fn spread(x: &[f64]) -> f64 {
    let n = x.len() as f64;
    let mean = x.iter().sum::<f64>() / n;
    x.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n
}

/// RMS (nm) of `y` about its mean over the window (`NaN` if it holds no sample).
pub fn reading_rms_nm(t: &[f64], y: &[f64], w: &Window) -> f64 {
    1e3 * spread(inside(t, y, w)).sqrt()
}

/// How many times the best model's response to the input ([`WindowFigures::model_rms_nm`]) the reading's RMS
/// ([`WindowFigures::reading_rms_nm`]) may reach before a note says that the reading barely follows the input. On
/// the paper's simulated records the best model's response is the reading's but for the noise (PRBS: 493-519 nm
/// against 4.8 nm of residual; triangle: 69 against 3.4); on a reading of noise alone (a disconnected probe) under
/// the board's PRBS or triangle, 0.008 and 0.05 nm against 3.3 nm (10 s records, 5-10 s). A model that has not
/// converged (a window at a record's start) can respond beyond the reading, and is no such case.
pub const RESPONSE_MIN: f64 = 3.0;

/// `x` (s) rounded to the decimal digit at or below a millionth of the sample period `dt`: a default window's
/// bound, computed from the record's span, without the rounding its arithmetic leaves in the last digits (4.6275,
/// not 4.6274999999999995, for a record of 12.34 s at 10 kHz), which every note and the summary print. It moves the
/// bound by at most half a millionth of a sample, and not at all where that is below `x`'s own resolution (a time
/// in Unix seconds).
fn tidy(x: f64, dt: f64) -> f64 {
    let decimals = (-(dt * 1e-6).log10()).ceil().clamp(0.0, 20.0) as usize;
    format!("{x:.decimals$}").parse().expect("a float as Rust writes it parses")
}

/// The pre-filtered power (V^2) of the paper's PRBS of 1 V through a pipeline of `cfg`, as its excitation monitor
/// measures it: the mean over one whole period of the sequence (163 835 samples, 16.4 s at 10 kHz) after 0.2 s of
/// settling, the periodic input's power (2.513 V^2 with the defaults at 10 kHz, 3.119 at 5 kHz). What
/// [`WindowFigures::input_strength`] compares a record's input with: the input the paper's `Q2` was made for. It was
/// the mean over 1 s, a sample of the sequence's spectrum near the resonance rather than its power: 2.7 % low at 10
/// kHz, 14 % at 5 kHz, so that every strength read that much high. About 20 ms on the host.
pub fn prbs_power_v2<T: Real>(cfg: &nanopos_id::pipeline::PipelineConfig<T>) -> f64 {
    use nanopos_id::excitation::{ExcitationDesign, Waveform, PRBS_PERIOD_BITS};
    let fs = 1.0 / cfg.sample_period_s;
    let Waveform::Prbs { hold } = ExcitationDesign::PAPER_PRBS.waveform else { unreachable!("the paper's PRBS") };
    let prbs = ExcitationDesign::PAPER_PRBS.design::<T>(fs);
    let mut state = Default::default();
    let mut pipeline = Pipeline::new(cfg, ());
    let (settle, count) = ((0.2 * fs).round() as usize, PRBS_PERIOD_BITS as usize * hold as usize);
    let mut sum = 0.0;
    for k in 0..settle + count {
        let s = pipeline.replay(cfg, prbs.next(&mut state), T::zero());
        if k >= settle {
            sum += s.pe.power.as_f64();
        }
    }
    sum / count as f64
}

/// How fast `u` moves over the window, Hz: the frequency `f` of a sine whose RMS change from one sample to the next,
/// `2 sin(pi f dt)` times its RMS, is in the same ratio to its RMS as the input's (`NaN` for an input that does not
/// change). A mean frequency of the input's spectrum, weighted by its power: on the simulated board's records the
/// PRBS about 1 030 Hz, the multisine of 200-800 Hz 530 Hz, the smoothed triangle of 10 Hz 11-12 Hz.
pub fn input_rms_hz(t: &[f64], u: &[f64], dt: f64, w: &Window) -> f64 {
    let u = inside(t, u, w);
    let mean_square = spread(u);
    if mean_square == 0.0 {
        return f64::NAN;
    }
    let change = u.windows(2).map(|p| (p[1] - p[0]) * (p[1] - p[0])).sum::<f64>() / (u.len() as f64 - 1.0);
    let half_ratio = (change / mean_square).sqrt() / 2.0;
    half_ratio.min(1.0).asin() / (std::f64::consts::PI * dt)
}

/// SPEC section 7: RMSE (nm) between `y'` and model (1) with `p` driven by `u'` over the window.
pub fn validation_rmse_nm(p: &StageParams<f64>, t: &[f64], u: &[f64], y: &[f64], dt: f64, w: &Window) -> f64 {
    validation_nm(p, t, u, y, dt, w)[0]
}

/// [`validation_rmse_nm`], the RMS (nm) of the model's output about its mean over the window (how much of a response
/// to the input the model gives), the mean of the residual `y - x1` over the window (nm: a constant offset the RMSE
/// includes) and the residual's RMS about that mean (nm; its sums taken about the window's first residual, so that
/// an offset a million times the rest does not cancel it away).
pub fn validation_nm(p: &StageParams<f64>, t: &[f64], u: &[f64], y: &[f64], dt: f64, w: &Window) -> [f64; 4] {
    let (phi, psi) = zoh(&[[0.0, 1.0], [-p.a0, -p.a1]], dt);
    let gam = [psi[0][1] * p.b0, psi[1][1] * p.b0];
    let mut x = [0.0f64; 2];
    let (mut sum, mut count, mut out, mut out2) = (0.0, 0usize, 0.0, 0.0);
    // The residual's sum and sum of squares about its first value in the window.
    let (mut first, mut shifted, mut shifted2) = (None, 0.0, 0.0);
    for k in 0..t.len() {
        if t[k] >= w.t1 {
            break;
        }
        if t[k] >= w.t0 - 1.0 {
            if t[k] >= w.t0 {
                let r = y[k] - x[0];
                sum += r * r;
                let d = r - *first.get_or_insert(r);
                (shifted, shifted2) = (shifted + d, shifted2 + d * d);
                (out, out2) = (out + x[0], out2 + x[0] * x[0]);
                count += 1;
            }
            x = [
                phi[0][0] * x[0] + phi[0][1] * x[1] + gam[0] * u[k],
                phi[1][0] * x[0] + phi[1][1] * x[1] + gam[1] * u[k],
            ];
        }
    }
    let Some(first) = first else {
        return [f64::NAN; 4];
    };
    let n = count as f64;
    let (mean, shift) = (out / n, shifted / n);
    // Not finite where the model ran away (`max` would make a NaN 0).
    let about = (shifted2 / n - shift * shift).max(0.0).sqrt();
    let fit = if about.is_finite() && shifted2.is_finite() { about } else { f64::NAN };
    [1e3 * (sum / n).sqrt(), 1e3 * (out2 / n - mean * mean).max(0.0).sqrt(), 1e3 * (first + shift), 1e3 * fit]
}

/// The command line's arguments.
pub struct IdentifyArgs<'a> {
    /// Input CSV.
    pub input: &'a Path,
    /// Estimators.
    pub estimators: Vec<&'static str>,
    /// Tuning (applied at the record's sample period).
    pub tuning: TuningArg,
    /// Windows (empty: the default two).
    pub windows: Vec<Window>,
    /// `EST.csv`.
    pub out: Option<&'a Path>,
    /// `SUMMARY.json`.
    pub summary: Option<&'a Path>,
    /// `FIG.svg`.
    pub plot: Option<&'a Path>,
    /// `HEALTH.csv`.
    pub health: Option<&'a Path>,
    /// The input's step for one DAC code, V (0: not rounded; `None`: the simulated board's, as the firmware's).
    pub dac_step_v: Option<DacStep>,
    /// The spike gate's ratio (`None`: the tuning's).
    pub spike_ratio: Option<SpikeRatio>,
    /// The scalar the pipeline and the estimators run in.
    pub precision: Precision,
}

impl<'a> IdentifyArgs<'a> {
    /// `identify --input INPUT` with `tuning` and every other option at its default: every estimator, the default
    /// windows, no output file, the board's DAC step and the tuning's spike ratio, f64.
    pub fn new(input: &'a Path, tuning: TuningArg) -> Self {
        IdentifyArgs {
            input,
            estimators: NAMES.to_vec(),
            tuning,
            windows: Vec::new(),
            out: None,
            summary: None,
            plot: None,
            health: None,
            dac_step_v: None,
            spike_ratio: None,
            precision: Precision::F64,
        }
    }
}

/// `--precision`: the scalar of the pipeline and the estimators.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Precision {
    /// f64, the reference.
    #[default]
    F64,
    /// f32, the firmware's: what the board computes from the same samples (the QEMU harness shows the Cortex-M4F's
    /// f32 results equal the host's bit for bit on the same f32 input; a CSV's decimal volts round to it), including
    /// its refusal of a tuning f32 cannot hold.
    F32,
}

/// `--dac-step V`: the input's step for one DAC code, finite and not negative.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DacStep(pub f64);

impl std::str::FromStr for DacStep {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().parse::<f64>() {
            Ok(v) if v.is_finite() && v >= 0.0 => Ok(DacStep(v)),
            _ => Err(format!("'{s}': expected the input's step for one DAC code in volts, 0 or more (0: not rounded)")),
        }
    }
}

/// `--spike-ratio N`: the pipeline's spike gate's ratio ([`nanopos_id::pipeline::FaultSettings::spike_ratio`]), a
/// whole number from 0 (the gate off) to 65 535.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SpikeRatio(pub u16);

impl std::str::FromStr for SpikeRatio {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        s.trim().parse::<u16>().map(SpikeRatio).map_err(|_| {
            format!("'{s}': expected the spike gate's ratio, a whole number from 0 (the gate off) to 65535")
        })
    }
}

/// Run the command: the input is read a block at a time ([`Reader`]); what is held is what the report needs (the
/// 100 Hz rows and the windows' samples), not the record.
pub fn run(args: &IdentifyArgs) -> Result<Identified, CliError> {
    let tuning = args.tuning.file.as_deref().map(|f| ("--tuning", f));
    let inputs: Vec<_> = [Some(("--input", args.input)), tuning].into_iter().flatten().collect();
    let outputs = [("--out", args.out), ("--summary", args.summary), ("--plot", args.plot), ("--health", args.health)];
    let outputs: Vec<_> = outputs.into_iter().filter_map(|(option, p)| Some((option, p?))).collect();
    super::check_distinct(&inputs, &outputs)?;
    args.plot.map(crate::plot::check_name).transpose()?;
    // The outputs are opened (under their temporary names) before the run, so that a directory that is not there
    // or not writable is said at once, not after the whole record.
    let open = |p: Option<&Path>| p.map(OutputFile::create).transpose();
    let (est, sum, fig, health) = (open(args.out)?, open(args.summary)?, open(args.plot)?, open(args.health)?);
    let source = args.input.display().to_string();
    let mut reader = Reader::open(args.input, &["u", "y"], &["a0", "a1", "b0"], Time::Required)?;
    let record = Stream {
        source: &source,
        last_t: reader.last_time(),
        has_truth: reader.has_optional(),
        progress_total: reader.progress().1,
        dac_step_v: args.dac_step_v.map(|s| s.0),
        spike_ratio: args.spike_ratio.map(|r| r.0),
    };
    let blocks = std::iter::from_fn(|| match reader.next_block() {
        Ok(Some(block)) => Some(Ok((block, reader.progress().0))),
        Ok(None) => None,
        Err(e) => Some(Err(e)),
    });
    let (names, tuning, windows) = (&args.estimators, &args.tuning, &args.windows);
    let result = match args.precision {
        Precision::F64 => identify_blocks::<f64>(&record, names, tuning, windows, blocks)?,
        Precision::F32 => identify_blocks::<f32>(&record, names, tuning, windows, blocks)?,
    };
    // Every file is written before any is moved into place.
    let est = est.map(|f| write_estimates(f, &result)).transpose()?;
    let sum = sum.map(|f| write_summary(f, &result)).transpose()?;
    let fig = fig.map(|f| crate::plot::write(f, &result)).transpose()?;
    let health = health.map(|f| write_health(f, &result)).transpose()?;
    for f in est.into_iter().chain(sum).chain(fig).chain(health) {
        f.commit()?;
    }
    Ok(result)
}

/// One line per window that reaches beyond the record, by a sample or more (its figures are of the part the record
/// covers, not of the window asked for), and per estimator and window whose means are not what the input identifies:
/// the excitation monitor held the estimator for more than a tenth of the window (its means are of held values), or
/// it reset itself (its means are of runs that diverged, each restarted from the initial parameters); and per window
/// where the pre-filter's centre is far from the resonance ([`PrefilterDesign::off_resonance`]: the estimates can
/// come out biased by several %), the resonance as the hybrid EKF's mean has it (else the first estimator's, as the
/// board's console takes it; where another's model fits the window far better, that one's); and where that
/// resonance is beyond `w T` 0.5 with the continuous EKF run, that its `a1` comes out low there; and per window
/// where the reading does not change at all, moves less or more than a stage's reading in um can
/// ([`READING_RMS_NM`]: then no note that it barely follows the input), or sits off the best model by more than
/// [`OFFSET_MIN`] of its RMSE.
pub fn health_notes(r: &Identified) -> Vec<String> {
    let mut notes = Vec::new();
    let ((first, last), dt) = (r.span, r.period);
    // The resonance the pre-filter is compared with: the hybrid EKF's, else the first estimator's.
    let by = r.names.iter().position(|&n| n == "hekf").unwrap_or(0);
    for (column, unit, spread) in [("u", "V", &r.spread[0]), ("y", "um", &r.spread[1])] {
        if let Some(note) = spread.wild_note(column, unit, &format!("{} s", show(spread.largest_at))) {
            // Whether the gate kept every reading that far out from the estimators (a burst of more than
            // `spike::MAX_RUN` readings in a row is taken from its third on).
            let kept_out = spread.wild_at(r.spikes.largest_taken).is_none();
            notes.push(if column == "y" && kept_out {
                note + " The spike gate replaced it, and every reading that far out: the estimators did not see them"
            } else {
                note + " The filters spread one such sample over tenths of a second and the estimators take it for data"
            });
        }
    }
    if r.spikes.count > 0 {
        notes.push(format!(
            "the spike gate replaced {} of y's readings, the first at {} s: each out of line with the readings before \
             it by far more than a stage moves in a sample (a glitch, or a logger's error), and replaced by the curve \
             through them before the filters saw it; a few are glitches the estimators did not see, many a noisy \
             reading",
            r.spikes.count,
            show(r.spikes.first_at)
        ));
    }
    // A command beyond what an amplifier's input takes for most of the record: most likely not in V (a logger's mV,
    // DAC codes, the piezo's own voltage), which scales every gain the estimators give and nothing else.
    let level = r.spread[0].level(0.9);
    if level > COMMAND_LEVEL_V {
        notes.push(format!(
            "u stays within {} V for 90 % of the record, beyond the +-10 V of a command to the stage's amplifier: is \
             u in V? (identify reads it so; in mV every gain, b0 and the DC gain, reads a thousand times too small, \
             in DAC codes or the piezo's own volts by their scale; a0 and a1 do not depend on u's unit)",
            sig(level)
        ));
    }
    for (w, figs, _) in &r.windows {
        // A window is half open, `[t0, t1)`: one that ends a sample after the last covers it all.
        if w.t0 < first - 0.5 * dt || w.t1 > last + 1.5 * dt {
            notes.push(format!(
                "window {w} reaches beyond the record ({} to {} s): its figures are of {} to {} s",
                show(first),
                show(last),
                show(w.t0.max(first)),
                show(w.t1.min(last))
            ));
        }
        // A reading that does not move (a stuck probe, a column of zeros): nothing to identify from, and every model
        // fits it to within rounding, which makes the ratios of [`misfit`] meaningless (1e45 and more).
        let moved = figs.first().map_or(f64::NAN, |f| f.reading_rms_nm);
        let still = moved == 0.0;
        if still {
            notes.push(format!(
                "window {w}: y does not change over it: there is nothing to identify from (a stuck probe, or a \
                 column that is not the reading?)",
            ));
        }
        // A reading that moves less than any probe resolves, or farther than any nanopositioning stage: most likely
        // not in um (a logger's metres, or picometres), which none of the notes below would say.
        let [least, most] = READING_RMS_NM;
        let unit = moved > 0.0 && !(least..=most).contains(&moved);
        if unit {
            let (bound, what, scale) = if moved < least {
                ("less than a picometre, which no probe resolves", "in metres", "a million times too small")
            } else {
                (
                    "more than a centimetre, which no nanopositioning stage moves",
                    "in nm or pm",
                    "a thousand or a million times too large",
                )
            };
            notes.push(format!(
                "window {w}: y moves {} nm RMS over it, {bound}: is y in um? (identify reads it so; {what} the \
                 stage's motion reads {scale})",
                sig(moved)
            ));
        }
        // A reading that sits off the best model's response (the probe's zero, the stage's position, drift): model (1)
        // has no constant, so the RMSE of every estimator and of the truth is mostly that offset.
        if let Some(b) = best_fit(figs).filter(|&b| figs[b].offset_nm.abs() > OFFSET_MIN * figs[b].rmse_nm) {
            let f = &figs[b];
            notes.push(format!(
                "window {w}: the reading sits {} nm off {}'s model throughout (the probe's zero, the stage's \
                 position, or drift: model (1) has no constant), which its validation RMSE of {} nm includes; about \
                 that offset it is {} nm, and the estimators are compared about it",
                sig(f.offset_nm),
                r.names[b],
                sig(f.rmse_nm),
                sig(f.fit_nm)
            ));
        }
        // A reading the best model explains little of: noise alone (a disconnected probe) or an input too small.
        let weak = |b: &usize| figs[*b].model_rms_nm * RESPONSE_MIN < figs[*b].reading_rms_nm;
        if let Some(b) = best_fit(figs).filter(weak).filter(|_| !unit) {
            notes.push(format!(
                "window {w}: the best model ({}'s) responds to the input with {} nm RMS, under a third of the \
                 reading's {} nm: the reading barely follows the input. Is the probe connected and seeing the stage, \
                 and the input large enough?",
                r.names[b],
                sig(figs[b].model_rms_nm),
                sig(figs[b].reading_rms_nm)
            ));
        }
        // The hybrid EKF's mean, unless another estimator's model fits the window far better ([`misfit`]: the EKFs
        // settled on a wrong solution, as on a stage far from the initial parameters): then that one's, as the
        // board's console takes the ARX's or the RLS's resonance where the EKFs disagree with them.
        let by = figs.get(by).and_then(|f| misfit(figs, f)).unwrap_or(by);
        if let Some(f) = figs.get(by) {
            let f0 = f.mean.f0_hz();
            // As the board's `status` says it: the continuous EKF's `a1` low at a fast resonance.
            let wt = 2.0 * std::f64::consts::PI * f0 * dt;
            if r.names.contains(&"ekf") && wt > nanopos_id::instrument::FAST_RESONANCE_WT {
                notes.push(format!(
                    "window {w}: the resonance, {f0:.0} Hz ({}'s mean), is at w T = {wt:.2} of the record's sample \
                     rate, where {}",
                    r.names[by],
                    nanopos_id::instrument::FAST_RESONANCE_EFFECT
                ));
            }
            if let Some(ratio) = r.prefilter.off_resonance(f0) {
                notes.push(format!(
                    "window {w}: the pre-filter's f_p ({} Hz) is {:.3} times the resonance ({:.0} Hz, {}'s mean): \
                     the estimates can come out biased by several %; give --tuning a pre-filter near the resonance \
                     (prefilter = [F_LC, F_P, ZETA])",
                    show(r.prefilter.f_p_hz),
                    ratio,
                    f0,
                    r.names[by]
                ));
            }
        }
        if let Some(note) = slow_input_note(r, figs).or_else(|| strong_input_note(r, figs)) {
            notes.push(format!("window {w}: {note}"));
        }
        for (name, f) in r.names.iter().zip(figs) {
            if f.starved > 0.1 {
                notes.push(format!(
                    "{name} was held by the excitation monitor for {:.0} % of window {w} (the input too weak, or a \
                     single sinusoid): its means there are of held values",
                    100.0 * f.starved,
                ));
            }
            if f.held > 0.1 {
                notes.push(format!(
                    "{name}'s parameters were held for {:.0} % of window {w} (its model had no continuous \
                     equivalent: not yet converged): its means there are of the last parameters it could report",
                    100.0 * f.held,
                ));
            }
            let m = &f.mean;
            if !(m.a0 > 0.0 && m.a0.is_finite() && m.a1.is_finite() && m.b0.is_finite()) {
                notes.push(format!(
                    "{name}'s means over window {w} are not of a stage (a0 {}, a1 {}, b0 {}): it diverged",
                    sig(m.a0),
                    sig(m.a1),
                    sig(m.b0)
                ));
            } else if let Some(best) = misfit(figs, f).filter(|_| !still) {
                let (best_name, best_nm) = (r.names[best], sig(figs[best].fit_nm));
                notes.push(if f.fit_nm.is_finite() {
                    format!(
                        "{name}'s model fits window {w} {} times worse than {best_name}'s (validation RMSE {} nm \
                         against {best_nm}): its estimates there are not to be trusted (not yet converged, or \
                         diverged)",
                        sig(f.fit_nm / figs[best].fit_nm),
                        sig(f.fit_nm),
                    )
                } else {
                    format!(
                        "{name}'s model does not fit window {w} at all: its validation is not finite (the model \
                         with its means runs away), against {best_name}'s RMSE of {best_nm} nm: its estimates there \
                         are not to be trusted (not yet converged, or diverged)",
                    )
                });
            }
            if f.resets > 0 {
                notes.push(format!(
                    "{name} met a non-finite value (or an innovation beyond a metre, or no relock within 5 s) and \
                     went back to its initial parameters {} in window {w} (a tuning that does not suit this \
                     record, or a glitch in it): its means there are of runs that diverged",
                    super::count(f.resets, "time", "times")
                ));
            }
        }
    }
    notes
}

/// The estimator whose validation RMSE about the reading's offset ([`WindowFigures::fit_nm`]) in the window is the
/// lowest, when `f`'s is more than [`MISFIT`] times it (or not finite).
fn misfit(figs: &[WindowFigures], f: &WindowFigures) -> Option<usize> {
    let best = best_fit(figs)?;
    let worse = !f.fit_nm.is_finite() || f.fit_nm > MISFIT * figs[best].fit_nm;
    (worse && figs[best].fit_nm > 0.0).then_some(best)
}

/// Where an EKF's model fits a window worse than the best ([`misfit`]), a model linear in its parameters (the ARX
/// or the RLS), on an input that moves slowly against the resonance (its [`input_rms_hz`] under [`SLOW_INPUT`] of
/// the best model's), with the paper's `Q2` (the `prbs` preset's): what the float64 reference found (`shared/golden`:
/// the EKFs with `Q2` fail on the smoothed triangle, for which the paper tuned `Q1`), and the tuning that fits.
/// With only EKFs run, nothing to compare them with: the same note where the input is slow and `Q` is `Q2`, saying
/// that they may have failed and what would tell.
fn slow_input_note(r: &Identified, figs: &[WindowFigures]) -> Option<String> {
    let best = best_fit(figs)?;
    let ekf = |i: usize| r.names[i].ends_with("ekf");
    let worse: Vec<&str> =
        (0..figs.len()).filter(|&i| ekf(i) && misfit(figs, &figs[i]).is_some()).map(|i| r.names[i]).collect();
    let (pace, f0) = (figs[best].input_rms_hz, figs[best].mean.f0_hz());
    // False where either is NaN.
    let slow = pace < SLOW_INPUT * f0;
    // Shown to fit worse than a model linear in its parameters, or with none run to compare them with.
    let (only_ekfs, shown) = ((0..figs.len()).all(ekf), !worse.is_empty() && !ekf(best));
    if !(only_ekfs || shown) || r.ekf_q != EkfDesign::Q2 || !slow {
        return None;
    }
    let here = if only_ekfs {
        "with no ARX or RLS run (the default runs all four) nothing here tells whether they did".to_string()
    } else {
        format!("{} fit worse here", worse.join(" and "))
    };
    Some(format!(
        "the input moves slowly against the resonance ({pace:.0} Hz RMS against {f0:.0} Hz, {}'s mean), as the \
         smoothed triangle does, and the EKFs' Q is the paper's Q2, for the PRBS: with it the EKFs fail on the \
         triangle in the float64 reference (b0 -15 %), and {here}; --tuning triangle gives them Q1, the paper's for \
         the triangle",
        r.names[best],
    ))
}

/// Where EKFs ran with the paper's `Q2` on an input [`STRONG_INPUT`] times or more as strong as the 1 V PRBS it was
/// made for ([`WindowFigures::input_strength`]): their parameters follow the data faster and wander further (the
/// board's console says so at `excite`, for the amplitude it is given: `tests/instrument.rs`), and `Q2`'s parameter
/// entries over the strength keep them about as at 1 V. The strength is the pre-filtered power's ratio, not the
/// amplitude squared, which a record does not give: for a PRBS of 8 V ramped by the default slew limit 46 (the
/// console's 64 does a little better: `b0` up to 0.54-0.55 % off against 0.57-0.58 % with 45), for a multisine of
/// 6 V 32 (the console's 36).
fn strong_input_note(r: &Identified, figs: &[WindowFigures]) -> Option<String> {
    let strength = figs.first()?.input_strength;
    // A NaN strength (a window without samples) is not strong.
    let strong = strength >= STRONG_INPUT;
    if !r.names.iter().any(|n| n.ends_with("ekf")) || r.ekf_q != EkfDesign::Q2 || !strong {
        return None;
    }
    let q = EkfDesign::q2_for_strength(strength);
    Some(format!(
        "the input reaches the estimators {} times as strongly as the paper's PRBS of 1 V (its power through the \
         pre-filter), for which the EKFs' Q, the paper's Q2, was made: with it their parameters follow the data \
         faster and wander further (on the simulated board at 8 V, b0 up to 1.05 % off the truth instead of 0.54 %); \
         a --tuning file with [ekf] q = [{:e}, {:e}, {}, {}, {}] (Q2's last three over that) keeps them about as at \
         1 V",
        sig(strength),
        q[0],
        q[1],
        sig(q[2]),
        sig(q[3]),
        sig(q[4]),
    ))
}

/// How much stronger than the paper's 1 V PRBS ([`WindowFigures::input_strength`]) an input must reach the
/// estimators for [`health_notes`]' note on the EKFs' `Q2`: a PRBS or a multisine of 2 V, as the board's console
/// has it (it notes the amplitude). Through the slew limit and the pre-filter, in the 1-s and 5-s windows of
/// `simulate` records of 8 s and 40 s, a PRBS of 2 V reaches 3.84-3.98, a multisine of 2 V 3.58-3.66; one of
/// 1.9 V 3.24-3.31, a PRBS of 1.8 V 3.15-3.22. (It was 4, which a 2-V multisine never reached, and a 2-V PRBS only
/// while the reference read every strength 2.7 % high.)
pub const STRONG_INPUT: f64 = 3.4;

/// The share of the resonance below which [`health_notes`]' note on the tuning calls an input's [`input_rms_hz`]
/// slow: on the simulated board's records the smoothed triangle's is 0.026 of the resonance, the multisine's of
/// 200-800 Hz 1.25, the PRBS's 2.4.
pub const SLOW_INPUT: f64 = 0.25;

/// The estimator whose validation RMSE about the reading's offset in the window is the lowest (of those finite).
fn best_fit(figs: &[WindowFigures]) -> Option<usize> {
    (0..figs.len()).filter(|&i| figs[i].fit_nm.is_finite()).min_by(|&a, &b| figs[a].fit_nm.total_cmp(&figs[b].fit_nm))
}

/// The RMS (nm) of a reading about its mean over a window outside which a note asks whether `y` is in um: a
/// picometre, less than any probe resolves at these rates, and a centimetre, farther than any nanopositioning stage
/// moves. On the simulated board's records 493-519 nm (PRBS) and 69 nm (triangle); in metres 4.5e-4 to 5.2e-4 nm, in pm
/// 4.7e8 to 5.3e8 nm.
/// A reading that does not change at all (0) has a note of its own.
pub const READING_RMS_NM: [f64; 2] = [1e-3, 1e7];

/// The level (V) 90 % of a record's command `u` may stay within before a note asks whether `u` is in V: twice the
/// +-10 V an amplifier's input and the board's command span ([`Spread::level`] reads up to 19 % high). On the simulated
/// board's records 1 V (PRBS) and 1.2 V (triangle); in mV 1 000 and more, in 12-bit DAC codes 2 048 and more.
pub const COMMAND_LEVEL_V: f64 = 20.0;

/// The share of the best model's validation RMSE in a window its residual's mean may reach before a note says that
/// the RMSE is mostly an offset of the reading: at 0.7 the offset is half its mean square. On the paper's records
/// the residual's mean is under a tenth of the RMSE.
pub const OFFSET_MIN: f64 = 0.7;

/// How many times the best estimator's validation RMSE in a window another's may reach before a note says so. On the
/// paper's records the four stay within 1.3 times each other once converged (PRBS: 4.8 to 6.0 nm; triangle: 3.3 to
/// 3.6 nm).
const MISFIT: f64 = 3.0;

/// `HEALTH.csv`: each estimator's health on the rows of `EST.csv`, in the words and counts of the board's `status`
/// (the counts since the record's start); the innovation RMS, of the last second, empty for the estimators without
/// one (`rls`, `arx`).
fn write_health(f: OutputFile, r: &Identified) -> Result<OutputFile, CliError> {
    write_rows(f, r, "state,rejected,changes,resets,repairs,innovation_rms_um", |w, i, j| {
        let h = &r.healths[i][j];
        let state = h.state();
        write!(
            w,
            "{state},{},{},{},{},",
            h.rejected_samples, h.changes_detected, h.numeric_resets, h.covariance_repairs
        )?;
        if h.innovation_rms_um.is_nan() {
            writeln!(w)
        } else {
            writeln!(w, "{}", h.innovation_rms_um)
        }
    })
}

fn write_estimates(f: OutputFile, r: &Identified) -> Result<OutputFile, CliError> {
    write_rows(f, r, "a0,a1,b0,f0_hz,zeta,dc_gain", |w, i, j| {
        let p = &r.estimates[i][j];
        writeln!(w, "{},{},{},{},{},{}", p.a0, p.a1, p.b0, p.f0_hz(), p.damping_ratio(), p.dc_gain())
    })
}

/// A file of the 100 Hz rows: the header `t,estimator,` and `columns`, then per row and estimator its time and name
/// and what `fields(w, row, estimator)` writes, its line end included.
fn write_rows(
    mut f: OutputFile,
    r: &Identified,
    columns: &str,
    fields: impl Fn(&mut dyn Write, usize, usize) -> std::io::Result<()>,
) -> Result<OutputFile, CliError> {
    let res = (|| -> std::io::Result<()> {
        let w = f.writer();
        writeln!(w, "t,estimator,{columns}")?;
        for (i, t) in r.times.iter().enumerate() {
            for (j, name) in r.names.iter().enumerate() {
                write!(w, "{t},{name},")?;
                fields(w, i, j)?;
            }
        }
        Ok(())
    })();
    res.map_err(|e| f.write_error(e))?;
    Ok(f)
}

fn json_params(p: &StageParams<f64>) -> String {
    let n = json_number;
    format!(
        "\"a0\": {}, \"a1\": {}, \"b0\": {}, \"f0_hz\": {}, \"zeta\": {}, \"dc_gain\": {}",
        n(p.a0),
        n(p.a1),
        n(p.b0),
        n(p.f0_hz()),
        n(p.damping_ratio()),
        n(p.dc_gain())
    )
}

/// The summary as JSON (SPEC section 9), with the truth per window when known (and its validation RMSE), and the
/// spike gate's ratio and how many readings it replaced.
pub fn summary_json(r: &Identified) -> String {
    let num = json_number;
    let windows: Vec<String> = r
        .windows
        .iter()
        .map(|(w, figs, truth)| {
            let ests: Vec<String> = r
                .names
                .iter()
                .zip(figs)
                .map(|(n, f)| {
                    format!(
                        "\"{n}\": {{{}, \"rmse_nm\": {}, \"innovation_rms_nm\": {}, \"starved\": {}, \"held\": {}, \"resets\": {}}}",
                        json_params(&f.mean),
                        num(f.rmse_nm),
                        num(f.innovation_rms_nm),
                        num(f.starved),
                        num(f.held),
                        f.resets
                    )
                })
                .collect();
            let truth = truth
                .map(|p| format!(", \"truth\": {{{}, \"rmse_nm\": {}}}", json_params(&p.mean), num(p.rmse_nm)))
                .unwrap_or_default();
            format!("{{\"t0\": {:?}, \"t1\": {:?}, \"estimators\": {{{}}}{truth}}}", w.t0, w.t1, ests.join(", "))
        })
        .collect();
    // After the windows, which the SPEC's format starts with: what the spike gate did (its ratio, 0 off).
    format!(
        "{{\"precision\": \"{}\", \"windows\": [{}], \"spike_gate\": {{\"ratio\": {}, \"replaced\": {}}}}}\n",
        r.precision,
        windows.join(", "),
        r.spikes.ratio,
        r.spikes.count
    )
}

fn write_summary(mut f: OutputFile, r: &Identified) -> Result<OutputFile, CliError> {
    let text = summary_json(r);
    f.writer().write_all(text.as_bytes()).map_err(|e| f.write_error(e))?;
    Ok(f)
}

impl Identified {
    /// Seconds after `t_change` until estimator `col` holds a0 and b0 within 1 % of the truth (needs the truth).
    pub fn relock_s(&self, col: usize, t_change: f64) -> Option<f64> {
        let truth = self.truth.as_ref()?;
        crate::experiment::relock_time(&self.samples(col, Some(truth)), t_change, 0.01)
    }

    /// Seconds after `t_change` until estimator `col` holds a0 and b0 within `tol` of their own means over
    /// `window` (no truth needed).
    pub fn settle_s(&self, col: usize, t_change: f64, window: &Window, tol: f64) -> Option<f64> {
        crate::experiment::settle_time(&self.samples(col, None), t_change, (window.t0, window.t1), tol)
    }

    /// Estimator `col`'s history, with the truth if given (else the estimates stand in for it).
    fn samples(&self, col: usize, truth: Option<&Vec<StageParams<f64>>>) -> Vec<crate::experiment::Sample> {
        self.times
            .iter()
            .zip(&self.estimates)
            .enumerate()
            .map(|(k, (&t_s, e))| crate::experiment::Sample {
                t_s,
                est: e[col],
                truth: truth.map_or(e[col], |tr| tr[k]),
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{Scenario, Simulation};

    #[test]
    fn a_window_bound_loses_its_rounding_and_nothing_else() {
        assert_eq!(tidy(0.75 * 6.17, 1e-4), 4.6275);
        assert_eq!(0.75 * 6.17, 4.6274999999999995);
        assert_eq!(tidy(2e-4 * 0.999_999_999_999_999_9, 1e-4), 2e-4);
        // In Unix seconds a millionth of a sample is below the time's resolution: unchanged.
        let unix = 1.7e9 + 0.123_456_7;
        assert_eq!(tidy(unix, 1e-4), unix);
        // A bound half a millionth of a sample off a decimal stays where it is.
        assert_eq!(tidy(1.000_000_000_1, 1e-4), 1.000_000_000_1);
        assert_eq!(tidy(1.000_000_000_01, 1e-4), 1.0);
    }

    /// A window takes the samples from its start, included, to its end, excluded, on the bounds or between samples.
    #[test]
    fn a_window_holds_its_start_and_not_its_end() {
        let t = [0.0, 0.5, 1.0, 1.5, 2.0];
        let x = ['a', 'b', 'c', 'd', 'e'];
        let at = |t0, t1| inside(&t, &x, &Window { t0, t1 }).iter().collect::<String>();
        assert_eq!(at(0.5, 1.5), "bc");
        assert_eq!(at(0.4, 1.6), "bcd");
        assert_eq!(at(0.0, 2.0), "abcd");
        assert_eq!(at(1.2, 1.3), "");
        assert_eq!(at(2.0, 9.0), "e");
    }

    /// The reading's RMS is taken about its mean over the window, in nanometres: 3 nm of noise read a centimetre off
    /// zero (a probe's absolute position) is 3 nm, where the mean of the squares less the square of the mean would
    /// have lost it to rounding.
    #[test]
    fn a_readings_rms_is_about_its_mean_even_a_centimetre_off_zero() {
        let t: Vec<f64> = (0..3000).map(|k| k as f64 / 1e4).collect();
        for offset_um in [0.0, -250.0, 1e4 + 0.1] {
            let y: Vec<f64> = (0..t.len()).map(|k| offset_um + if k % 2 == 0 { 0.003 } else { -0.003 }).collect();
            let rms = reading_rms_nm(&t, &y, &Window { t0: 0.1, t1: 0.2 });
            assert!((rms / 3.0 - 1.0).abs() < 1e-6, "{offset_um} um: {rms} nm");
        }
        assert!(reading_rms_nm(&t, &vec![0.0; t.len()], &Window { t0: 0.5, t1: 0.6 }).is_nan(), "no sample");
    }

    /// An estimator fits a window badly when its fit about the reading's offset is more than `MISFIT` times the
    /// best's, or not finite; against a best fit of exactly 0 (a record without noise) no ratio says so.
    #[test]
    fn a_misfit_is_more_than_three_times_the_best_fit() {
        let fig = |fit_nm: f64| WindowFigures {
            mean: StageParams { a0: 7e6, a1: 80.0, b0: 8e5 },
            rmse_nm: fit_nm,
            innovation_rms_nm: f64::NAN,
            starved: 0.0,
            held: 0.0,
            resets: 0,
            reading_rms_nm: 500.0,
            input_rms_hz: 1000.0,
            input_strength: 1.0,
            model_rms_nm: 500.0,
            offset_nm: 0.0,
            fit_nm,
        };
        let figs = [fig(12.0), fig(4.0), fig(12.01), fig(f64::NAN), fig(f64::INFINITY)];
        assert_eq!(best_fit(&figs), Some(1));
        let got: Vec<_> = figs.iter().map(|f| misfit(&figs, f)).collect();
        assert_eq!(got, [None, None, Some(1), Some(1), Some(1)]);
        let exact = [fig(0.0), fig(1.0)];
        assert_eq!((best_fit(&exact), misfit(&exact, &exact[1])), (Some(0), None));
        assert_eq!(misfit(&[fig(f64::NAN)], &fig(f64::NAN)), None, "nothing fits: no best to compare with");
    }

    #[test]
    fn the_input_rms_frequency_of_a_sine_is_its_frequency() {
        let dt = 1e-4;
        let t: Vec<f64> = (0..20_000).map(|k| k as f64 * dt).collect();
        let w = Window { t0: 0.5, t1: 1.5 };
        for f in [10.0, 423.0, 2_000.0] {
            let u: Vec<f64> = t.iter().map(|t| 0.3 + 2.0 * (2.0 * std::f64::consts::PI * f * t + 0.4).sin()).collect();
            let got = input_rms_hz(&t, &u, dt, &w);
            assert!((got / f - 1.0).abs() < 1e-3, "{f} Hz: {got}");
        }
        assert!(input_rms_hz(&t, &vec![1.0; t.len()], dt, &w).is_nan());
    }

    #[test]
    fn a_spread_reads_its_level_to_a_quarter_octave_and_finds_the_wild_sample() {
        let mut s = Spread::default();
        // 1 000 samples spread evenly over 0 to 1 (with signs), then one at 2 000.
        for k in 0..1000 {
            let x = (k as f64 + 0.5) / 1000.0;
            s.add(if k % 2 == 0 { x } else { -x }, k as f64);
        }
        // 90 % lie within 0.9; the bound is the next quarter octave's start, 1.0 (0.875 = 7/8 is the one below).
        assert_eq!(s.level(0.9), 1.0);
        assert_eq!(s.level(0.5), 0.5);
        assert_eq!(s.wild(), None);
        s.add(999.0, 1000.0);
        assert_eq!(s.wild(), None, "999 is not more than 1 000 times the level");
        s.add(-2000.0, 1001.0);
        assert_eq!((s.largest, s.largest_at, s.wild()), (2000.0, 1001.0, Some(2000.0)));
        // At a level other than 1 (a quarter: samples over 0 to 0.25), the bound is 1 000 times the level, itself
        // not wild, and the ratio is the largest's to the level.
        let mut q = Spread::default();
        (0..1000).for_each(|k| q.add((k as f64 + 0.5) / 4000.0, k as f64));
        assert_eq!(q.level(0.9), 0.25);
        q.add(250.0, 1000.0);
        assert_eq!(q.wild(), None, "250 is 1 000 times the level, not more");
        q.add(251.0, 1001.0);
        assert_eq!(q.wild(), Some(1004.0));
        // A record of zeros has no level to compare with.
        let mut z = Spread::default();
        (0..10).for_each(|k| z.add(0.0, k as f64));
        z.add(1e30, 10.0);
        assert_eq!((z.level(0.9), z.wild()), (0.0, None));
        // The largest magnitudes have a bucket too.
        z.add(f64::MAX, 11.0);
        assert_eq!(z.largest, f64::MAX);
    }

    #[test]
    fn a_note_gives_three_significant_digits() {
        let cases = [(0.0, "0"), (4.776, "4.78"), (10000.0, "10000"), (-8.464e9, "-8.46e9"), (2.5e-4, "2.50e-4")];
        for (x, text) in cases {
            assert_eq!(sig(x), text, "{x}");
        }
        assert_eq!((sig(f64::NAN), sig(f64::INFINITY)), ("NaN".into(), "inf".into()));
    }

    #[test]
    fn numbers_without_a_value_are_null_in_json() {
        let p = StageParams { b0: 5e5, a1: f64::INFINITY, a0: -6e6 };
        let json = json_params(&p);
        assert_eq!(
            json,
            "\"a0\": -6000000.0, \"a1\": null, \"b0\": 500000.0, \"f0_hz\": null, \"zeta\": null, \"dc_gain\": \
             -0.08333333333333333"
        );
    }

    #[test]
    fn groups_balance_cost_and_keep_every_estimator_once() {
        assert_eq!(cost_groups(&NAMES, 1), vec![vec!["ekf", "rls", "hekf", "arx"]]);
        assert_eq!(cost_groups(&NAMES, 2), vec![vec!["ekf", "arx"], vec!["rls", "hekf"]]);
        assert_eq!(cost_groups(&["rls"], 8), vec![vec!["rls"]]);
        for workers in 1..6 {
            let mut all: Vec<_> = cost_groups(&NAMES, workers).concat();
            all.sort();
            assert_eq!(all, ["arx", "ekf", "hekf", "rls"], "{workers} workers");
        }
    }

    /// The workers see the pipeline's samples in order: the result is the one loop's, bit for bit.
    #[test]
    fn estimators_on_worker_threads_equal_one_loop() {
        let (board, settings) = Scenario::Prbs.settings(2.0, Scenario::Prbs.default_seed());
        let mut sim = Simulation::new(board, &settings, ()).unwrap();
        let (mut t, mut u, mut y) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..10_000 {
            let (r, _) = sim.step();
            t.push(r.t_s);
            u.push(r.u_v);
            y.push(r.y_um);
        }
        let rec = Recording { source: "test", t: &t, u: &u, y: &y, truth: None };
        let tuning = Tuning::preset("prbs").unwrap();
        let got = identify_in::<f32>(&rec, &NAMES, &tuning, &[]).unwrap();

        let cfg = PipelineSettings { sample_rate_hz: 1e4, ..PipelineSettings::default() }
            .design::<f32>(&SimBoard::new(Default::default()).description())
            .unwrap();
        let mut tuned = tuning;
        (tuned.rls.sample_period_s, tuned.ekf.sample_period_s, tuned.arx.sample_period_s) = (t[1], t[1], t[1]);
        let mut pipeline = Pipeline::new(&cfg, Bank::<f32>::new(&NAMES, &tuned));
        let mut rows = Vec::new();
        for k in 0..t.len() {
            pipeline.replay(&cfg, u[k] as f32, y[k] as f32);
            if (k + 1) % 100 == 0 {
                rows.push(pipeline.estimators.estimates().map(|(_, p)| p.cast::<f64>()).collect::<Vec<_>>());
            }
        }
        assert_eq!(got.names, NAMES);
        assert_eq!(got.estimates, rows);
    }

    /// The validation's four figures on a record made of model (1)'s own response (integrated here by RK4 in 50
    /// substeps a sample, the input held: not the exact discretisation the validation uses), an offset and a noise
    /// of alternating sign: the RMSE is the offset's and the noise's together, the response's RMS is the model's own,
    /// the residual's mean is the offset and its RMS about that mean the noise's, each to 1e-7. The window takes its
    /// first sample and not its last (a sample more or less moves the noise's mean), the model starts a second before
    /// it, and an offset of a centimetre leaves the nanometres of the noise as they are.
    #[test]
    fn the_validation_figures_of_a_known_response() {
        let p = StageParams { a0: 7.06e6, a1: 77.6, b0: 8.08e5 };
        let dt = 1e-4;
        let t: Vec<f64> = (0..21_000).map(|k| k as f64 / 1e4).collect();
        let mut rng = nanopos_id::xorshift64(7);
        let u: Vec<f64> = t.iter().map(|_| if rng() & 1 == 0 { 1.0 } else { -1.0 }).collect();
        let (mut x, mut response) = ([0.0f64; 2], Vec::new());
        for &uk in &u {
            response.push(x[0]);
            let f = |x: [f64; 2]| [x[1], -p.a0 * x[0] - p.a1 * x[1] + p.b0 * uk];
            let h = dt / 50.0;
            for _ in 0..50 {
                let k1 = f(x);
                let k2 = f([x[0] + h / 2.0 * k1[0], x[1] + h / 2.0 * k1[1]]);
                let k3 = f([x[0] + h / 2.0 * k2[0], x[1] + h / 2.0 * k2[1]]);
                let k4 = f([x[0] + h * k3[0], x[1] + h * k3[1]]);
                x = [0, 1].map(|i| x[i] + h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]));
            }
        }
        // 5 000 samples from 1.5 s (the record goes on to 2.1 s): the noise's mean over them is 0.
        let w = Window { t0: 1.5, t1: 2.0 };
        let in_window = &response[15_000..20_000];
        let mean = in_window.iter().sum::<f64>() / 5e3;
        let model_rms_nm = 1e3 * (in_window.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / 5e3).sqrt();
        assert!(model_rms_nm > 100.0, "the response is well above the noise: {model_rms_nm} nm");
        let noise_um = 0.003;
        for offset_um in [0.05, -0.02, 1e4] {
            let y: Vec<f64> =
                (0..t.len()).map(|k| response[k] + offset_um + if k % 2 == 0 { noise_um } else { -noise_um }).collect();
            let got = validation_nm(&p, &t, &u, &y, dt, &w);
            let rmse_nm = 1e3 * (offset_um * offset_um + noise_um * noise_um).sqrt();
            let want = [rmse_nm, model_rms_nm, 1e3 * offset_um, 1e3 * noise_um];
            for i in 0..4 {
                assert!((got[i] / want[i] - 1.0).abs() < 1e-7, "offset {offset_um} um: {got:?} against {want:?}");
            }
            assert_eq!(validation_rmse_nm(&p, &t, &u, &y, dt, &w), got[0]);
        }
        // No sample in the window: nothing to say. A model that runs away (a negative stiffness): no fit.
        let y = response.clone();
        assert!(validation_nm(&p, &t, &u, &y, dt, &Window { t0: 2.5, t1: 3.0 }).iter().all(|v| v.is_nan()));
        let unstable = StageParams { a0: -7.06e6, ..p };
        let got = validation_nm(&unstable, &t, &u, &y, dt, &w);
        assert!(got[3].is_nan() && !got[0].is_finite(), "{got:?}");
    }

    /// The paper's PRBS of 1 V reads as strength 1 over a window of one whole period of the sequence, wherever it
    /// starts; the reference it is compared with was a 1-s sample of it, and read the board's 1 V as 1.030.
    #[test]
    fn the_papers_prbs_has_strength_one_over_its_period() {
        let s = prbs_record(20.0, false);
        let rec = Recording { source: "test", t: &s.t, u: &s.u, y: &s.y, truth: None };
        let tuning = Tuning::preset("prbs").unwrap();
        let strength = |t0: f64, span_s: f64| {
            let got = identify(&rec, &["arx"], &tuning, &[Window { t0, t1: t0 + span_s }]).unwrap();
            got.windows[0].1[0].input_strength
        };
        // One period (32 767 bits of 5 samples): 1.002 (the record's input is the board's, through its DAC), the same
        // from either start.
        let period_s = (nanopos_id::excitation::PRBS_PERIOD_BITS * 5) as f64 / 1e4;
        let (a, b) = (strength(1.0, period_s), strength(3.5, period_s));
        assert!((a - 1.0).abs() < 0.005 && (b / a - 1.0).abs() < 1e-9, "{a} {b}");
        // A window of 1 s is a sample of the sequence: 0.987 to 1.047 from these four starts.
        for t0 in [1.0, 3.5, 7.0, 12.0] {
            assert!((strength(t0, 1.0) - 1.0).abs() < 0.06, "{t0}");
        }
    }

    /// `seconds` of the paper's PRBS on the full board, the payload removed at half of them or (`change` false) on
    /// throughout.
    fn prbs_record(seconds: f64, change: bool) -> crate::cmd::paper::Simulated {
        let (mut board, settings) = Scenario::Prbs.settings(seconds, Scenario::Prbs.default_seed());
        if !change {
            board.plant.change_at_sample = u64::MAX;
        }
        let mut sim = Simulation::new(board, &settings, nanopos_id::estimator::Unfiltered).unwrap();
        crate::cmd::paper::record(&mut sim, (seconds * 1e4) as usize)
    }

    /// The truth's own validation RMSE is reported with it: the least model (1) can reach on the data. On the full
    /// board with PRBS it is well above the effective noise floor (3.33 nm, README): the second mode and the analog
    /// chain are outside the model (measured on the 200 s paper run: 4.75 nm, the EKFs 4.75-5.03 nm). A converged
    /// estimate sits near it, not near the floor.
    #[test]
    fn the_truth_has_a_validation_rmse_and_a_converged_estimate_is_near_it() {
        let s = prbs_record(20.0, false);
        let rec = Recording { source: "test", t: &s.t, u: &s.u, y: &s.y, truth: Some(&s.truth) };
        let got =
            identify(&rec, &["hekf"], &Tuning::preset("prbs").unwrap(), &[Window { t0: 15.0, t1: 20.0 }]).unwrap();
        let (_, figs, truth) = &got.windows[0];
        let truth = truth.expect("the record has the truth");
        eprintln!("validation RMSE: truth {:.3} nm, hekf {:.3} nm", truth.rmse_nm, figs[0].rmse_nm);
        assert!(truth.rmse_nm > 1.3 * 3.33, "{}", truth.rmse_nm);
        assert!((figs[0].rmse_nm / truth.rmse_nm - 1.0).abs() < 0.05, "{} vs {}", figs[0].rmse_nm, truth.rmse_nm);
        assert!(summary_json(&got).contains(&format!("\"rmse_nm\": {:?}}}", truth.rmse_nm)));
    }

    /// `estimators` (the `prbs` tuning) on 2 s of the paper's PRBS on the full board, one window, 1.5 to 2 s.
    fn identified_2_s(estimators: &[&'static str]) -> Identified {
        identified_2_s_over(&prbs_record(2.0, true), estimators, Window { t0: 1.5, t1: 2.0 })
    }

    /// [`identified_2_s`] over the window `w`, of the record `s` (`prbs_record(2.0, true)`).
    fn identified_2_s_over(s: &crate::cmd::paper::Simulated, estimators: &[&'static str], w: Window) -> Identified {
        let rec = Recording { source: "test", t: &s.t, u: &s.u, y: &s.y, truth: None };
        identify(&rec, estimators, &Tuning::preset("prbs").unwrap(), &[w]).unwrap()
    }

    /// A window's innovation RMS is the mean of its 100 Hz rows' (in nm), over the rows from its start to before its
    /// end: a window ending on a row's time leaves that row out.
    #[test]
    fn a_windows_innovation_rms_is_the_mean_of_its_rows() {
        let s = prbs_record(2.0, true);
        let times = identified_2_s_over(&s, &["hekf"], Window { t0: 1.5, t1: 2.0 }).times;
        let w = Window { t0: times[150], t1: times[190] };
        let got = identified_2_s_over(&s, &["hekf"], w);
        let rows = &got.healths[150..190];
        let mean = 1e3 * rows.iter().map(|h| h[0].innovation_rms_um as f64).sum::<f64>() / rows.len() as f64;
        assert_eq!(got.windows[0].1[0].innovation_rms_nm, mean);
        assert!(mean > 0.0 && got.healths[190][0].innovation_rms_um as f64 * 1e3 != mean);
    }

    /// The slow input's note (the EKFs with `Q2` on a triangle) names the EKFs whose models fit worse than the best, a
    /// model linear in its parameters, and only those; with the EKFs alone it says that nothing tells; it is not given
    /// without an EKF, nor with `Q1`, nor on an input that is not slow.
    #[test]
    fn the_slow_input_note_names_only_the_ekfs_that_fit_worse() {
        let mut r = identified_2_s(&["hekf"]);
        let base = r.windows[0].1[0];
        let fig = |fit_nm: f64, input_rms_hz: f64| WindowFigures {
            // A resonance of 421 Hz: 11 Hz RMS (the triangle's) is slow against it, 1 kHz (the PRBS's) is not.
            mean: StageParams { a0: 7e6, a1: 80.0, b0: 8e5 },
            input_rms_hz,
            fit_nm,
            ..base
        };
        let mut note = |names: &[&'static str], q: [f64; 5], fits: &[f64], hz: f64| {
            (r.names, r.ekf_q) = (names.to_vec(), q);
            let figs: Vec<WindowFigures> = fits.iter().map(|&f| fig(f, hz)).collect();
            slow_input_note(&r, &figs)
        };
        let (q1, q2) = (EkfDesign::Q1, EkfDesign::Q2);
        let four = ["rls", "ekf", "hekf", "arx"];
        // The ARX fits best; the continuous EKF more than 3 times worse, the hybrid one not.
        let got = note(&four, q2, &[4.0, 20.0, 4.5, 3.9], 11.0).expect("the continuous EKF fits worse");
        assert!(
            got.ends_with(", and ekf fit worse here; --tuning triangle gives them Q1, the paper's for the triangle")
        );
        assert!(got.starts_with("the input moves slowly against the resonance (11 Hz RMS against 421 Hz, arx's mean)"));
        assert_eq!(note(&four, q2, &[4.0, 4.1, 4.5, 3.9], 11.0), None, "every model fits");
        assert_eq!(note(&four, q1, &[4.0, 20.0, 4.5, 3.9], 11.0), None, "Q1");
        assert_eq!(note(&four, q2, &[4.0, 20.0, 4.5, 3.9], 1000.0), None, "not slow");
        assert_eq!(note(&["rls", "arx"], q2, &[4.0, 3.9], 11.0), None, "no EKF");
        let alone = note(&["ekf", "hekf"], q2, &[20.0, 4.5], 11.0).expect("the EKFs alone");
        assert!(alone.contains("and with no ARX or RLS run (the default runs all four) nothing here tells"), "{alone}");
        assert_eq!(note(&["ekf", "hekf"], q1, &[20.0, 4.5], 11.0), None, "the EKFs alone with Q1");
    }

    /// What the command keeps of the pipeline's output for a window's validation starts a second before it, where
    /// model (1) starts (from rest) to have settled by the window: on a window of half a second the hybrid EKF's RMSE
    /// is the board's (4.91 nm; 4.75-4.98 nm over the paper's windows), not a start's transient (61 nm kept from the
    /// window's start), and every figure of the window is there.
    #[test]
    fn a_windows_validation_starts_a_second_before_it() {
        let f = identified_2_s(&["hekf"]).windows[0].1[0];
        assert!((4.5..5.5).contains(&f.rmse_nm), "{f:?}");
        assert!([f.reading_rms_nm, f.input_rms_hz, f.input_strength, f.model_rms_nm].iter().all(|x| x.is_finite()));
    }

    /// An estimator held by the excitation monitor, or whose parameters were held, for more than a tenth of a window
    /// has a note that its means there are of held values; for a tenth exactly (500 samples of 5 000), not.
    #[test]
    fn held_means_are_noted_above_a_tenth_of_the_window() {
        let mut got = identified_2_s(&["hekf"]);
        let said = |r: &Identified, what: &str| health_notes(r).iter().any(|n| n.contains(what));
        let (starved, held) = ("hekf was held by the excitation monitor for ", "hekf's parameters were held for ");
        assert!(!said(&got, starved) && !said(&got, held), "{:?}", health_notes(&got));
        for (share, noted) in [(500.0 / 5000.0, false), (501.0 / 5000.0, true)] {
            got.windows[0].1[0].starved = share;
            assert_eq!(said(&got, &format!("{starved}10 % of window 1.5:2")), noted, "starved {share}");
            got.windows[0].1[0].starved = 0.0;
            got.windows[0].1[0].held = share;
            assert_eq!(said(&got, &format!("{held}10 % of window 1.5:2")), noted, "held {share}");
            got.windows[0].1[0].held = 0.0;
        }
    }

    /// An estimator whose means over a window are not a stage's (`a0` not above zero, or a parameter not finite) is
    /// said to have diverged, for each of those alone; one whose means are a stage's is not.
    #[test]
    fn means_that_are_not_a_stage_are_said_to_have_diverged() {
        let mut got = identified_2_s(&["ekf", "hekf"]);
        let diverged = |r: &Identified| {
            let notes = health_notes(r);
            let said = notes.iter().any(|n| n.starts_with("ekf's means over window 1.5:2 are not of a stage (a0 "));
            (said, notes)
        };
        let (said, notes) = diverged(&got);
        assert!(!said, "{notes:?}");
        let m = got.windows[0].1[0].mean;
        for broken in [
            StageParams { a0: -m.a0, ..m },
            StageParams { a0: 0.0, ..m },
            StageParams { a0: f64::INFINITY, ..m },
            StageParams { a1: f64::NAN, ..m },
            StageParams { b0: f64::NEG_INFINITY, ..m },
        ] {
            got.windows[0].1[0].mean = broken;
            let (said, notes) = diverged(&got);
            assert!(said, "{broken:?}: {notes:?}");
        }
    }

    /// The command reads its file a block at a time (16 s of `simulate` is two blocks of 8 MiB): the result is the
    /// one of the whole record in memory, bit for bit, and so it is when the record's end is not known beforehand
    /// (the default windows are then placed at the end, from everything kept).
    #[test]
    fn a_file_read_in_blocks_identifies_as_the_record_in_memory() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("run.csv");
        let sim = crate::cmd::simulate::SimulateArgs {
            scenario: Scenario::Prbs,
            duration_s: 16.0,
            seed: None,
            hysteresis: false,
            creep: false,
            disturbances: Default::default(),
            amplitude_v: None,
            out: &input,
        };
        crate::cmd::simulate::run(&sim).unwrap();
        assert!(std::fs::metadata(&input).unwrap().len() > 8 << 20, "more than one block");
        let tuning = Tuning::preset("prbs").unwrap();
        let args = IdentifyArgs::new(&input, tuning.into());
        let streamed = run(&args).unwrap();
        let streamed32 = run(&IdentifyArgs { precision: Precision::F32, ..args }).unwrap();

        let (cols, truth) =
            crate::csv::read_columns_optional(&input, &["u", "y"], &["a0", "a1", "b0"], Time::Required).unwrap();
        let (u, y, t) = (&cols.data[0], &cols.data[1], &cols.data[2]);
        let truth = truth.as_ref().map(|c| &c.data[..]);
        let whole = identify(&Recording { source: "test", t, u, y, truth }, &NAMES, &tuning, &[]).unwrap();
        let unknown_end = {
            let blocks = Recording { source: "test", t, u, y, truth }.blocks(50_000);
            let record = Stream {
                source: "test",
                last_t: None,
                has_truth: true,
                progress_total: t.len() as u64,
                dac_step_v: None,
                spike_ratio: None,
            };
            identify_blocks::<f64>(&record, &NAMES, &tuning.into(), &[], blocks).unwrap()
        };
        for other in [&whole, &unknown_end] {
            assert_eq!(streamed.times, other.times);
            assert_eq!(streamed.estimates, other.estimates);
            assert_eq!(summary_json(&streamed), summary_json(other));
        }
        // `--precision f32`: the pipeline and the estimators in f32, as the firmware runs them; the summary says so.
        let whole32 = identify_in::<f32>(&Recording { source: "test", t, u, y, truth }, &NAMES, &tuning, &[]).unwrap();
        assert_eq!(streamed32.estimates, whole32.estimates);
        assert_eq!(summary_json(&streamed32), summary_json(&whole32));
        assert_ne!(streamed32.estimates, streamed.estimates, "f32 rounds differently from f64");
        assert!(summary_json(&streamed).starts_with("{\"precision\": \"f64\", \"windows\": ["));
        assert!(summary_json(&streamed32).starts_with("{\"precision\": \"f32\", \"windows\": ["));
        assert_eq!(streamed.windows[1].0, Window { t0: 14.0, t1: 16.0 });
    }

    /// A record whose end is not where it was before the read (the file grew, or was cut or rewritten, while
    /// `identify` read it; the default windows were placed from the end read first) is an error that names the file
    /// and the end it found, and so is a read that fails part way: the error, no result, so nothing is written.
    #[test]
    fn a_record_that_changes_or_fails_while_it_is_read_is_an_error() {
        let n = 20_000;
        let t: Vec<f64> = (0..n).map(|k| k as f64 * 1e-4).collect();
        let u: Vec<f64> = t.iter().map(|t| (2.0 * std::f64::consts::PI * 300.0 * t).sin()).collect();
        let y: Vec<f64> = u.iter().map(|u| 0.08 * u).collect();
        let rec = Recording { source: "run.csv", t: &t, u: &u, y: &y, truth: None };
        let tuning: TuningArg = Tuning::preset("prbs").unwrap().into();
        let identify_ending = |last_t: Option<f64>, windows: &[Window], fail_at: Option<u64>| {
            let record = Stream {
                source: "run.csv",
                last_t,
                has_truth: false,
                progress_total: n as u64,
                dac_step_v: None,
                spike_ratio: None,
            };
            let blocks = rec.blocks(5_000).map(|b| match (b, fail_at) {
                (Ok((_, reached)), Some(at)) if reached > at => {
                    Err(CliError(format!("run.csv: line {}: cannot read: Input/output error", at + 2)))
                }
                (b, _) => b,
            });
            identify_blocks::<f64>(&record, &["ekf"], &tuning, windows, blocks)
        };
        let end = t[n - 1];
        let whole = identify_ending(Some(end), &[], None).unwrap();
        assert_eq!(whole.windows.last().unwrap().0.t1, 2.0, "the default windows at the end, 1.9999 s");
        // It grew (the end read first was earlier) or was cut (later).
        for first_end in [end - 0.5, end + 0.5] {
            let e = identify_ending(Some(first_end), &[], None).err().expect("an error");
            assert_eq!(e.0, "run.csv: the file changed while it was read (its last time 1.9999 s)");
        }
        // Windows of the user's own need no end read first: the rows read are the record.
        let asked = [Window { t0: 1.0, t1: 1.5 }];
        assert_eq!(identify_ending(Some(end - 0.5), &asked, None).unwrap().windows.len(), 1);
        // A read that fails in the third block: that error, whatever the windows.
        for windows in [&[][..], &asked[..]] {
            let e = identify_ending(Some(end), windows, Some(10_000)).err().expect("an error");
            assert_eq!(e.0, "run.csv: line 10002: cannot read: Input/output error");
        }
    }

    /// The tuning's pre-filter is the stage's `W_p` for the pipeline (the EKFs and the ARX read its output) and for
    /// the continuous-time RLS (which filters `u'`, `y'` with its own `W_p` inside its RK4 step): moved to 600 Hz,
    /// both estimates change, and the EKF's stays on the truth.
    #[test]
    fn the_tunings_prefilter_reaches_the_pipeline_and_the_rls() {
        let s = prbs_record(20.0, false);
        let rec = Recording { source: "test", t: &s.t, u: &s.u, y: &s.y, truth: Some(&s.truth) };
        let truth = StageParams { a0: s.truth[0][0], a1: s.truth[1][0], b0: s.truth[2][0] };
        let err = |p: &StageParams<f64>| crate::experiment::rel_errors(p, &truth);
        let window = [Window { t0: 15.0, t1: 20.0 }];
        let paper = Tuning::preset("prbs").unwrap();
        let mut moved = paper;
        moved.set(nanopos_id::estimators::TuningKey::Prefilter, &[100.0, 600.0, 0.1]).unwrap();
        let hekf = |t: &Tuning| err(&identify(&rec, &["hekf"], t, &window).unwrap().windows[0].1[0].mean);
        let (hekf_450, hekf_600) = (hekf(&paper), hekf(&moved));
        let rls = |t: &Tuning| err(&identify(&rec, &["rls"], t, &window).unwrap().windows[0].1[0].mean);
        let (rls_450, rls_600) = (rls(&paper), rls(&moved));
        eprintln!("hekf {hekf_450:?} -> {hekf_600:?}; rls {rls_450:?} -> {rls_600:?}");
        assert_ne!(hekf_450, hekf_600);
        assert_ne!(rls_450, rls_600);
        for e in [hekf_450, hekf_600] {
            assert!(e[0].abs() < 1e-3 && e[2].abs() < 1e-2, "{e:?}");
        }
    }
}
