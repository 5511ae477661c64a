//! Reading recorded runs: a CSV file with a header line naming at least the columns asked for (others ignored),
//! uniformly sampled in `t`. Every problem is reported as `FILE:LINE: what` and nothing is guessed: a missing
//! column, a field that is not a number, NaN or infinity, a row with the wrong number of fields, time that does
//! not advance uniformly.

use crate::cmd::CliError;
use std::io::{BufRead, BufReader};
use std::path::Path;

/// Columns read from a file, in the order asked for (then `t`, if it was read and not asked for).
#[derive(Clone, Debug, Default)]
pub struct Columns {
    /// One vector per requested column.
    pub data: Vec<Vec<f64>>,
    /// The sample period, s (when `t` was among the requested columns and there are two rows or more).
    pub sample_period_s: Option<f64>,
}

/// Whether the file must have a time column `t`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Time {
    /// `t` must be there (it is then read as the last column).
    Required,
    /// `t` is checked when the header has it.
    IfPresent,
}

/// Read `names` from `path`, and `t` as [`Time`] says. Time may start anywhere but must advance by a constant step
/// (to a relative 1e-6 of the step, which printed decimal times meet).
pub fn read_columns(path: &Path, names: &[&str], time: Time) -> Result<Columns, CliError> {
    read_columns_optional(path, names, &[], time).map(|(c, _)| c)
}

/// [`read_columns`], plus the `optional` columns in the same pass if the header names all of them (then returned
/// as a second [`Columns`], else `None`).
pub fn read_columns_optional(
    path: &Path,
    names: &[&str],
    optional: &[&str],
    time: Time,
) -> Result<(Columns, Option<Columns>), CliError> {
    let shown = path.display();
    let file = std::fs::File::open(path)
        .map_err(|e| CliError(format!("{shown}: cannot open: {}", crate::cmd::io_reason(&e))))?;
    let mut lines = BufReader::with_capacity(1 << 20, file).lines();
    let header = match lines.next() {
        Some(Ok(h)) => h,
        Some(Err(e)) => return Err(CliError(format!("{shown}:1: cannot read: {}", crate::cmd::io_reason(&e)))),
        None => {
            return Err(CliError(format!("{shown}: empty file (a header line naming {} is needed)", names.join(","))))
        }
    };
    let fields: Vec<&str> = header.split(',').map(str::trim).collect();
    let mut names: Vec<&str> = names.to_vec();
    if !names.contains(&"t") && (time == Time::Required || fields.contains(&"t")) {
        names.push("t");
    }
    let required = names.len();
    let with_optional = !optional.is_empty() && optional.iter().all(|o| fields.contains(o));
    if with_optional {
        names.extend_from_slice(optional);
    }
    let mut index = Vec::with_capacity(names.len());
    for name in &names {
        match fields.iter().position(|f| f == name) {
            Some(i) => index.push(i),
            None => {
                return Err(CliError(format!(
                    "{shown}:1: no column '{name}' in the header (found: {})",
                    fields.join(",")
                )))
            }
        }
    }
    let t_col = names[..required].iter().position(|&n| n == "t");
    let mut out = Columns { data: vec![Vec::new(); names.len()], sample_period_s: None };
    let mut t0 = 0.0;
    let mut step = 0.0;
    for (i, line) in lines.enumerate() {
        let line_no = i + 2;
        let line =
            line.map_err(|e| CliError(format!("{shown}:{line_no}: cannot read: {}", crate::cmd::io_reason(&e))))?;
        if line.trim().is_empty() {
            continue;
        }
        let row: Vec<&str> = line.split(',').collect();
        if row.len() != fields.len() {
            return Err(CliError(format!("{shown}:{line_no}: {} fields, the header has {}", row.len(), fields.len())));
        }
        for (c, (&col, name)) in index.iter().zip(&names).enumerate() {
            let text = row[col].trim();
            let v: f64 = text
                .parse()
                .map_err(|_| CliError(format!("{shown}:{line_no}: column '{name}': '{text}' is not a number")))?;
            if !v.is_finite() {
                return Err(CliError(format!("{shown}:{line_no}: column '{name}': {text} is not a finite number")));
            }
            out.data[c].push(v);
        }
        if let Some(tc) = t_col {
            let t = &out.data[tc];
            let k = t.len() - 1;
            let now = t[k];
            match k {
                0 => t0 = now,
                1 => {
                    step = now - t0;
                    if step <= 0.0 {
                        return Err(CliError(format!("{shown}:{line_no}: time {now} does not advance from {t0}")));
                    }
                }
                _ => {
                    let expected = t0 + k as f64 * step;
                    if (now - expected).abs() > 1e-6 * step + 1e-12 * now.abs() {
                        return Err(CliError(format!(
                            "{shown}:{line_no}: time {now} breaks the uniform sampling (expected {expected}, step {step})"
                        )));
                    }
                }
            }
        }
    }
    if t_col.is_some() && step > 0.0 {
        out.sample_period_s = Some(step);
    }
    let extra = with_optional.then(|| Columns { data: out.data.split_off(required), sample_period_s: None });
    Ok((out, extra))
}
