//! `nanopos-sim paper [--duration S] [--out-dir DIR]`: the paper's whole experiment on the simulated board.
//!
//! For each input (PRBS with the `prbs` tuning, the smoothed triangle with `triangle`), simulate the stage with the
//! payload removed at half the run, identify with every estimator in f64 and in f32 (the firmware's precision)
//! through the firmware's pipeline, and print a table in the manner of the paper's Table II: per estimator and
//! window, the errors of `a0`, `a1`, `b0` against the truth, the validation RMSE, the relock time after the
//! payload change (a0 and b0 back within 1 % of the truth, for good) and the settling time (a0 and b0 within 3 %
//! of their own means over the last window, for good: what can be measured without the truth, and what shows the
//! relock where the model cannot reach the truth, as on the triangle, whose b0 the board's second mode biases by
//! +2.9 %; 3 % because the triangle's estimates wander up to 1.4 % about their mean). Writes each input's
//! `SUMMARY.json` and plot into `DIR` (default `paper-out`): `prbs-summary.json`, `prbs.svg`, and the triangle's.
//!
//! The simulation is not held: it runs a block of rows at a time, each fed to both precisions' identifications at
//! once (the one-hour run peaked at 4.6 GB when the records were held whole).

use super::identify::{identify_streamed, summary_json, Identified};
use super::{fail, show, CliError, OutputFile};
use crate::bank::{Tuning, NAMES};
use crate::sim::{Scenario, Simulation};
use nanopos_id::estimator::Unfiltered;
use nanopos_id::Real;
use std::io::Write;
use std::path::Path;
use std::sync::{mpsc, Arc};

/// One input's runs.
pub struct PaperRun {
    /// Input name.
    pub input: &'static str,
    /// f64 result.
    pub f64: Identified,
    /// f32 result.
    pub f32: Identified,
    /// The payload change, s.
    pub t_change: f64,
}

/// Run the experiment (`duration_s` per input).
pub fn run(duration_s: f64, out_dir: Option<&Path>) -> Result<Vec<PaperRun>, CliError> {
    if !(4.0..=3600.0).contains(&duration_s) {
        return fail(format!("--duration {duration_s}: between 4 and 3600 s"));
    }
    if let Some(d) = out_dir {
        if std::fs::metadata(d).is_ok_and(|m| !m.is_dir()) {
            return fail(format!("--out-dir {}: not a directory", d.display()));
        }
        std::fs::create_dir_all(d)
            .map_err(|e| CliError(format!("{}: cannot create: {}", d.display(), super::io_reason(&e))))?;
    }
    // Each input on a thread of its own (simulate, then both precisions' identifications at once); the
    // identifications also spread their estimators over the cores. The outputs are written afterwards, in order.
    let inputs = [(Scenario::Prbs, "prbs"), (Scenario::Triangle, "triangle")];
    let identified: Vec<Result<(Identified, Identified), CliError>> = std::thread::scope(|s| {
        let jobs: Vec<_> = inputs
            .iter()
            .map(|&(scenario, input)| s.spawn(move || identify_input(scenario, input, duration_s)))
            .collect();
        jobs.into_iter().map(|j| j.join().expect("an identification does not panic")).collect()
    });
    let mut runs = Vec::new();
    for ((_, input), result) in inputs.into_iter().zip(identified) {
        let (r64, r32) = result?;
        if let Some(d) = out_dir {
            let mut f = OutputFile::create(&d.join(format!("{input}-summary.json")))?;
            f.writer().write_all(summary_json(&r64).as_bytes()).map_err(|e| f.write_error(e))?;
            f.commit()?;
            crate::plot::write(OutputFile::create(&d.join(format!("{input}.svg")))?, &r64)?.commit()?;
        }
        runs.push(PaperRun { input, f64: r64, f32: r32, t_change: duration_s / 2.0 });
    }
    Ok(runs)
}

/// Rows of the simulated record per block (as `identify` reads a file's).
const BLOCK_ROWS: usize = 1 << 16;

/// A block of the simulated record (the columns of [`block`]) and the row it reaches.
type Block = Arc<(Vec<Vec<f64>>, u64)>;

/// `scenario` simulated and identified in f64 and f32 with the tuning preset `input`: the simulation a block at a
/// time, on a thread of its own, each block to both identifications.
fn identify_input(scenario: Scenario, input: &str, duration_s: f64) -> Result<(Identified, Identified), CliError> {
    let (board, settings) = scenario.settings(duration_s, scenario.default_seed());
    let mut sim = Simulation::new(board, &settings, Unfiltered).map_err(|e| CliError(format!("settings: {e}")))?;
    let n = (duration_s * 1e4).round() as usize;
    // The last row's time as the simulation stamps it, known before the rows (the default windows need it).
    let last_t = n.checked_sub(1).map(|k| k as f64 * sim.config.sample_period_s);
    let source = format!("paper/{input}");
    let tuning = Tuning::preset(input).expect("preset exists");
    let (to64, from64) = mpsc::sync_channel::<Block>(2);
    let (to32, from32) = mpsc::sync_channel::<Block>(2);
    // Every estimator, the preset, the default windows, on the blocks as they come.
    fn identify<T: Real>(
        from: mpsc::Receiver<Block>,
        source: &str,
        rows: usize,
        last_t: Option<f64>,
        tuning: &Tuning,
    ) -> Result<Identified, CliError> {
        // The identification that takes a block last takes it whole; the other copies it.
        let blocks = from.into_iter().map(|b| Ok(Arc::unwrap_or_clone(b)));
        identify_streamed::<T>(source, rows as u64, last_t, true, &NAMES, tuning, &[], blocks)
    }
    std::thread::scope(|s| {
        s.spawn(move || {
            for start in (0..n).step_by(BLOCK_ROWS) {
                let end = (start + BLOCK_ROWS).min(n);
                let b: Block = Arc::new((block(&mut sim, end - start), end as u64));
                // An identification that stopped (an error) closed its end: so does the simulation.
                if to64.send(b.clone()).is_err() || to32.send(b).is_err() {
                    break;
                }
            }
        });
        let r32 = s.spawn(|| identify::<f32>(from32, &source, n, last_t, &tuning));
        let r64 = identify::<f64>(from64, &source, n, last_t, &tuning);
        Ok((r64?, r32.join().expect("an identification does not panic")?))
    })
}

/// One simulated run, held (for tests): time, command, reading, and the truth's `a0`, `a1`, `b0`.
#[cfg(test)]
pub(crate) struct Simulated {
    pub(crate) t: Vec<f64>,
    pub(crate) u: Vec<f64>,
    pub(crate) y: Vec<f64>,
    pub(crate) truth: Vec<Vec<f64>>,
}

/// `n` samples of `sim`, recorded.
#[cfg(test)]
pub(crate) fn record(sim: &mut Simulation<Unfiltered>, n: usize) -> Simulated {
    let mut c = block(sim, n).into_iter();
    let mut next = || c.next().expect("six columns");
    let (u, y, t) = (next(), next(), next());
    Simulated { t, u, y, truth: vec![next(), next(), next()] }
}

/// The next `n` samples of `sim` as the columns `identify` reads: `u`, `y`, `t`, and the truth's `a0`, `a1`, `b0`.
fn block(sim: &mut Simulation<Unfiltered>, n: usize) -> Vec<Vec<f64>> {
    let mut c: Vec<Vec<f64>> = (0..6).map(|_| Vec::with_capacity(n)).collect();
    for _ in 0..n {
        let (r, _) = sim.step();
        for (col, x) in c.iter_mut().zip([r.u_v, r.y_um, r.t_s, r.truth.a0, r.truth.a1, r.truth.b0]) {
            col.push(x);
        }
    }
    c
}

/// The table.
pub fn table(runs: &[PaperRun]) -> String {
    let mut s = String::new();
    s += "input     prec estimator window      a0 err    a1 err    b0 err   RMSE nm  relock s  settle s\n";
    for run in runs {
        for (prec, r) in [("f64", &run.f64), ("f32", &run.f32)] {
            // The truth's own validation RMSE: what model (1) can reach on this data at best.
            for (w, _, truth) in &r.windows {
                let rmse = truth.expect("simulated runs carry the truth").rmse_nm;
                s += &format!(
                    "{:9} {prec}  {:9} {:>5}-{:<5} {:>30} {rmse:8.2}\n",
                    run.input,
                    "truth",
                    show(w.t0),
                    show(w.t1),
                    ""
                );
            }
            for (col, name) in r.names.iter().enumerate() {
                let time = |t: Option<f64>| t.map_or("never".to_string(), |t| format!("{t:.2}"));
                let relock = time(r.relock_s(col, run.t_change));
                let last = &r.windows.last().expect("windows").0;
                let settle = time(r.settle_s(col, run.t_change, last, 0.03));
                for (w, figs, truth) in &r.windows {
                    let (m, tr) = (figs[col].mean, truth.expect("simulated runs carry the truth").mean);
                    let e = |a: f64, b: f64| 100.0 * (a / b - 1.0);
                    s += &format!(
                        "{:9} {prec}  {name:9} {:>5}-{:<5} {:+8.3}% {:+8.3}% {:+8.3}% {:8.2} {:>9} {:>9}\n",
                        run.input,
                        show(w.t0),
                        show(w.t1),
                        e(m.a0, tr.a0),
                        e(m.a1, tr.a1),
                        e(m.b0, tr.b0),
                        figs[col].rmse_nm,
                        if w.t0 > run.t_change { relock.as_str() } else { "" },
                        if w.t0 > run.t_change { settle.as_str() } else { "" },
                    );
                }
            }
        }
    }
    s
}
