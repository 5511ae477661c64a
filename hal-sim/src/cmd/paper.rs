//! `nanopos-sim paper [--duration S] [--out-dir DIR]`: the paper's whole experiment on the simulated board.
//!
//! For each input (PRBS with the `prbs` tuning, the smoothed triangle with `triangle`), simulate the stage with the
//! payload removed at half the run, identify with every estimator in f64 and in f32 (the firmware's precision)
//! through the firmware's pipeline, and print a table in the manner of the paper's Table II: per estimator and
//! window, the errors of `a0`, `a1`, `b0` against the truth, the validation RMSE, the relock time after the
//! payload change (a0 and b0 back within 1 % of the truth, for good) and the settling time (a0 and b0 within 3 %
//! of their own means over the last window, for good: what can be measured without the truth, and what shows the
//! relock where the model cannot reach the truth, as on the triangle, whose b0 the board's second mode biases by
//! +2.9 %; 3 % because the triangle's estimates wander up to 1.4 % about their mean). Writes each run's `simulate` CSV, `EST.csv` and `SUMMARY.json`
//! into `DIR` (default `paper-out`).

use super::identify::{identify_in, summary_json, Identified, Recording};
use super::{fail, CliError, OutputFile};
use crate::bank::{Tuning, NAMES};
use crate::sim::{Scenario, Simulation};
use std::io::Write;
use std::path::Path;

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

/// `scenario` simulated and identified in f64 and f32 with the tuning preset `input`.
fn identify_input(scenario: Scenario, input: &str, duration_s: f64) -> Result<(Identified, Identified), CliError> {
    let Simulated { t, u, y, truth } = simulate(scenario, duration_s)?;
    let source = format!("paper/{input}");
    let rec = Recording { source: &source, t: &t, u: &u, y: &y, truth: Some(&truth) };
    let tuning = Tuning::preset(input).expect("preset exists");
    std::thread::scope(|s| {
        let r32 = s.spawn(|| identify_in::<f32>(&rec, &NAMES, &tuning, &[]));
        let r64 = identify_in::<f64>(&rec, &NAMES, &tuning, &[]);
        Ok((r64?, r32.join().expect("an identification does not panic")?))
    })
}

/// One simulated run: time, command, reading, and the truth's `a0`, `a1`, `b0` (the columns `identify` reads).
pub(crate) struct Simulated {
    pub(crate) t: Vec<f64>,
    pub(crate) u: Vec<f64>,
    pub(crate) y: Vec<f64>,
    pub(crate) truth: Vec<Vec<f64>>,
}

/// The stage under `scenario` for `duration_s`, payload removed at half time.
fn simulate(scenario: Scenario, duration_s: f64) -> Result<Simulated, CliError> {
    let (board, settings) = scenario.settings(duration_s, scenario.default_seed());
    let mut sim = Simulation::new(board, &settings, ()).map_err(|e| CliError(format!("settings: {e}")))?;
    Ok(record(&mut sim, (duration_s * 1e4).round() as usize))
}

/// `n` samples of `sim`, recorded.
pub(crate) fn record(sim: &mut Simulation<()>, n: usize) -> Simulated {
    let (mut t, mut u, mut y) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n));
    let mut truth: Vec<Vec<f64>> = (0..3).map(|_| Vec::with_capacity(n)).collect();
    for _ in 0..n {
        let (r, _) = sim.step();
        t.push(r.t_s);
        u.push(r.u_v);
        y.push(r.y_um);
        truth[0].push(r.truth.a0);
        truth[1].push(r.truth.a1);
        truth[2].push(r.truth.b0);
    }
    Simulated { t, u, y, truth }
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
                    "{:9} {prec}  {:9} {:>5.0}-{:<5.0} {:>30} {rmse:8.2}\n",
                    run.input, "truth", w.t0, w.t1, ""
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
                        "{:9} {prec}  {name:9} {:>5.0}-{:<5.0} {:+8.3}% {:+8.3}% {:+8.3}% {:8.2} {:>9} {:>9}\n",
                        run.input,
                        w.t0,
                        w.t1,
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
