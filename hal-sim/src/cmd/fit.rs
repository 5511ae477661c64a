//! `nanopos-sim fit --input FILE.csv --arx NA,NB,NK [--zero-initial] [--weight A,GAMMA]`
//!
//! Batch (weighted) least squares of the ARX model
//! `y(k) = a1 y(k-1) + ... + a_NA y(k-NA) + b1 u(k-NK) + ... + b_NB u(k-NK-NB+1)` on the file's `u` and `y`,
//! by the core's QR solver ([`nanopos_id::estimators::lsq`]). Prints `{"a": [...], "b": [...], "sse": ..., "rows":
//! ...}`. Rows are those with full history, or with `--zero-initial` every sample, with the signals taken as zero
//! before the first. `--weight A,GAMMA` weights row `k` of `N` by `A GAMMA^(N-k)` (textbook 13.4). A `t` column, when
//! present, must be uniformly sampled. A sample of `u` or `y` more than 1 000 times the level 90 % of the record stays
//! within (a glitch, or a logger's overflow value, which can decide the fit alone) gets a note on standard error, as in
//! `identify`. An `sse` beyond f64's range (values of 1e154 and more) is `null`, with a note.
//!
//! **An offset.** The model has no constant term, and a reading that sits off it (the probe's zero, the stage's
//! position) biases every coefficient: 0.1 um on the paper's PRBS record, a fifth of its spread, moves `1 + a2`, the
//! damping's term, by 39 %. The fit is also made with a constant `c` (one more column of ones); where that lowers
//! the residual by more than [`OFFSET_NOTE`], a note says so. `--offset` reports that fit, with `"c"` in the JSON.

use super::{fail, json_number, CliError, Spread};
use crate::csv::{Reader, Time};
use nanopos_id::estimators::lsq::{LsError, WeightedLs};
use std::path::Path;

/// Most parameters a fit may have (`NA + NB`).
pub const MAX_PARAMETERS: usize = 32;

/// The share of the residual's sum of squares a constant term may remove before a note says that the fit without
/// it is biased by an offset: on the paper's PRBS record (8 s) 0.07 % for a reading 5 nm off (the coefficients moved
/// by under 0.1 %), 2.6 % for 25 nm (`1 + a2` by 2 %), 30 % for 0.1 um (39 %); 1e-6 for the record as simulated.
pub const OFFSET_NOTE: f64 = 0.01;

/// The model orders.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ArxOrders {
    /// Output lags.
    pub na: usize,
    /// Input taps.
    pub nb: usize,
    /// Input delay.
    pub nk: usize,
}

impl std::str::FromStr for ArxOrders {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let parts: Vec<&str> = s.split(',').map(str::trim).collect();
        let bad = || format!("'{s}': expected NA,NB,NK (three whole numbers, e.g. 2,2,1)");
        if parts.len() != 3 {
            return Err(bad());
        }
        let n: Vec<usize> = parts.iter().map(|p| p.parse::<usize>()).collect::<Result<_, _>>().map_err(|_| bad())?;
        let orders = ArxOrders { na: n[0], nb: n[1], nk: n[2] };
        if orders.na + orders.nb == 0 {
            return Err(format!("'{s}': the model needs at least one parameter (NA + NB >= 1)"));
        }
        if orders.na + orders.nb > MAX_PARAMETERS {
            return Err(format!("'{s}': at most {MAX_PARAMETERS} parameters (NA + NB)"));
        }
        Ok(orders)
    }
}

/// Row weights `a gamma^(N-k)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Weight {
    /// Weight of the newest row, > 0.
    pub a: f64,
    /// Discount per row into the past, 0 < gamma <= 1.
    pub gamma: f64,
}

impl std::str::FromStr for Weight {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let parts: Vec<&str> = s.split(',').map(str::trim).collect();
        let bad = || format!("'{s}': expected A,GAMMA with A > 0 and 0 < GAMMA <= 1 (e.g. 0.2,0.8)");
        if parts.len() != 2 {
            return Err(bad());
        }
        let a: f64 = parts[0].parse().map_err(|_| bad())?;
        let gamma: f64 = parts[1].parse().map_err(|_| bad())?;
        if !(a.is_finite() && a > 0.0 && gamma > 0.0 && gamma <= 1.0) {
            return Err(bad());
        }
        Ok(Weight { a, gamma })
    }
}

/// The fit's result.
#[derive(Clone, Debug, PartialEq)]
pub struct ArxFit {
    /// Output coefficients `a1..a_NA`.
    pub a: Vec<f64>,
    /// Input coefficients `b1..b_NB`.
    pub b: Vec<f64>,
    /// Weighted sum of squared residuals.
    pub sse: f64,
    /// Rows used.
    pub rows: u64,
    /// The constant term, with `--offset`.
    pub c: Option<f64>,
    /// For standard error: a wild sample in `u` or `y` ([`Spread::wild_note`]); an offset the model does not have.
    pub notes: Vec<String>,
}

impl ArxFit {
    /// The JSON the command prints.
    pub fn to_json(&self) -> String {
        let list = |v: &[f64]| v.iter().map(|&x| json_number(x)).collect::<Vec<_>>().join(", ");
        let c = self.c.map_or(String::new(), |c| format!(", \"c\": {}", json_number(c)));
        format!(
            "{{\"a\": [{}], \"b\": [{}]{c}, \"sse\": {}, \"rows\": {}}}",
            list(&self.a),
            list(&self.b),
            json_number(self.sse),
            self.rows
        )
    }
}

fn column_name(o: &ArxOrders, j: usize) -> String {
    if j == o.na + o.nb {
        "1 (the constant)".to_string()
    } else if j < o.na {
        format!("y(k-{})", j + 1)
    } else {
        let lag = o.nk + (j - o.na);
        if lag == 0 {
            "u(k)".to_string()
        } else {
            format!("u(k-{lag})")
        }
    }
}

/// Fit `orders` to the `u`, `y` of `path`. The file is read a block at a time ([`Reader`]): the rows go into the
/// streaming QR factorisation as they come, with the last samples of a block kept as the next one's history, so a
/// record of any length fits in a few MiB.
pub fn run(
    path: &Path,
    orders: ArxOrders,
    zero_initial: bool,
    weight: Option<Weight>,
    offset: bool,
) -> Result<ArxFit, CliError> {
    let mut reader = Reader::open(path, &["u", "y"], &[], Time::IfPresent)?;
    let n = orders.na + orders.nb;
    let history = orders.na.max(if orders.nb > 0 { orders.nk + orders.nb - 1 } else { 0 });
    let first = if zero_initial { 0 } else { history };
    let Weight { a, gamma } = weight.unwrap_or(Weight { a: 1.0, gamma: 1.0 });
    // Without and with the constant (the last column, of ones).
    let mut ls = WeightedLs::<f64, { MAX_PARAMETERS + 1 }>::new(n);
    let mut with_c = WeightedLs::<f64, { MAX_PARAMETERS + 1 }>::new(n + 1);
    let mut row = vec![1.0; n + 1];
    // The targets' weighted sum of squares: the scale of the residuals' rounding.
    let mut targets = 0.0;
    // The samples of this block, after up to `history` of the ones before it; `start` is the index of `u[0]`.
    let (mut u, mut y, mut start) = (Vec::new(), Vec::new(), 0usize);
    let mut spread = [Spread::default(), Spread::default()];
    while let Some(block) = reader.next_block()? {
        let kept = u.len();
        for (s, column) in spread.iter_mut().zip(&block) {
            column.iter().enumerate().for_each(|(i, &x)| s.add(x, (start + kept + i) as f64));
        }
        u.extend_from_slice(&block[0]);
        y.extend_from_slice(&block[1]);
        // Sample k of the record is u[k - start]; a lag before the record's start reads 0 (--zero-initial).
        let at = |s: &[f64], k: usize, lag: usize| if k >= lag { s[k - lag - start] } else { 0.0 };
        for k in (start + kept).max(first)..start + u.len() {
            for (j, r) in row[..n].iter_mut().enumerate() {
                *r = if j < orders.na { at(&y, k, j + 1) } else { at(&u, k, orders.nk + (j - orders.na)) };
            }
            if gamma < 1.0 {
                ls.forget(gamma);
                with_c.forget(gamma);
            }
            if !offset {
                ls.add_row(&row[..n], y[k - start], a);
            }
            with_c.add_row(&row, y[k - start], a);
            targets = targets * gamma + a * y[k - start] * y[k - start];
        }
        let drop = u.len().saturating_sub(history);
        u.drain(..drop);
        y.drain(..drop);
        start += drop;
    }
    let samples = start + u.len();
    let rows = samples.saturating_sub(first);
    let (n, solved) = if offset { (n + 1, with_c.solve()) } else { (n, ls.solve()) };
    if rows < n {
        return fail(format!(
            "{}: too few rows: {} {}{}, {n} parameters need at least {n}",
            path.display(),
            super::count(samples as u64, "sample gives", "samples give"),
            super::count(rows as u64, "regression row", "regression rows"),
            if zero_initial { "" } else { " with full history" }
        ));
    }
    match solved {
        Ok(s) => {
            let mut notes: Vec<String> = [("u", "V"), ("y", "um")]
                .into_iter()
                .zip(&spread)
                .filter_map(|((column, unit), s)| {
                    let at = format!("sample {} (the first is 0)", s.largest_at);
                    let note = s.wild_note(column, unit, &at)?;
                    Some(note + " A least-squares fit weighs a sample by its square: one such sample can decide it")
                })
                .collect();
            if let (false, Ok(sc)) = (offset, with_c.solve()) {
                // A noise-free record's residuals are rounding, whose ratio means nothing.
                let lower = 1.0 - sc.sse / s.sse;
                if lower > OFFSET_NOTE && s.sse - sc.sse > 1e-12 * targets {
                    // The constant as an offset of y: `c / (1 - a1 - ... - a_NA)`, the level the model holds it at.
                    let gain = 1.0 - sc.theta[..orders.na].iter().sum::<f64>();
                    notes.push(format!(
                        "a constant term would lower the fit's residual by {:.1} % (c = {}{}): y sits off the model \
                         (the probe's zero, the stage's position, or a low-frequency response the model misses), \
                         which biases every coefficient; --offset fits c too",
                        100.0 * lower,
                        super::sig(sc.theta[orders.na + orders.nb]),
                        if gain.abs() > 1e-9 {
                            format!(", y {} um off", super::sig(sc.theta[orders.na + orders.nb] / gain))
                        } else {
                            String::new()
                        }
                    ));
                }
            }
            if !s.sse.is_finite() {
                notes.push(
                    "the residual's sum of squares is beyond f64's range (values of 1e154 and more square past \
                     1e308): sse is null; the coefficients, solved from the rows as they are, stand"
                        .to_string(),
                );
            }
            let (na, nb) = (orders.na, orders.nb);
            let (a, b) = (s.theta[..na].to_vec(), s.theta[na..na + nb].to_vec());
            let c = offset.then(|| s.theta[na + nb]);
            Ok(ArxFit { a, b, sse: s.sse, rows: s.rows, c, notes })
        }
        Err(LsError::RankDeficient(r)) => {
            let others: Vec<String> =
                (0..r.column).filter(|i| r.combines & (1 << i) != 0).map(|i| column_name(&orders, i)).collect();
            let what = if others.is_empty() {
                "is (nearly) zero".to_string()
            } else {
                format!("is (nearly) a combination of {}", others.join(", "))
            };
            // Weights `a gamma^(N-k)` leave about `(1 + gamma) / (1 - gamma)` rows that count (their sum squared over
            // the sum of their squares): too few of those, not the input, can be why.
            let weighing = (1.0 + gamma) / (1.0 - gamma);
            let why = if weighing < 3.0 * (n + offset as usize) as f64 {
                format!(
                    "--weight {},{} leaves about {weighing:.1} rows that count ((1 + GAMMA) / (1 - GAMMA)): a GAMMA \
                     nearer 1 keeps more",
                    super::show(a),
                    super::show(gamma),
                )
            } else {
                format!(
                    "the input does not excite this model{}",
                    if zero_initial { "" } else { " (a step input, for instance, needs --zero-initial)" }
                )
            };
            fail(format!(
                "{}: rank-deficient fit: column {} {what} (independent part {:.1e} of its norm); {why}",
                path.display(),
                column_name(&orders, r.column),
                r.independence,
            ))
        }
        Err(LsError::TooFewRows { rows, parameters }) => {
            fail(format!("{}: too few rows: {rows} for {parameters} parameters", path.display()))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Orders and weights are taken up to their bounds and refused beyond: 32 parameters, not 33; a model of the
    /// outputs or the inputs alone, not of neither; `A` and `GAMMA` above 0, not at it; `GAMMA` up to 1.
    #[test]
    fn orders_and_weights_are_taken_up_to_their_bounds() {
        for ok in ["16,16,1", "32,0,0", "2,0,0", "0,2,1"] {
            assert!(ok.parse::<ArxOrders>().is_ok(), "{ok}");
        }
        for bad in ["16,17,1", "33,0,0", "0,0,3"] {
            assert!(bad.parse::<ArxOrders>().is_err(), "{bad}");
        }
        for ok in ["1e-300,1", "1,1e-300", "0.2,0.8"] {
            assert!(ok.parse::<Weight>().is_ok(), "{ok}");
        }
        for bad in ["0,0.8", "1,0", "1,1.0000001", "inf,1", "NaN,1", "1,NaN"] {
            assert!(bad.parse::<Weight>().is_err(), "{bad}");
        }
    }

    /// Read in blocks (this file is two of them), the fit adds exactly the rows of the whole record in memory, in
    /// the same order: the same solution bit for bit, with full history and with zero initial conditions.
    #[test]
    fn a_file_read_in_blocks_fits_as_the_record_in_memory() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("arx.csv");
        let (mut u, mut y) = (Vec::new(), Vec::new());
        let mut text = String::from("t,u,y\n");
        let mut next = nanopos_id::xorshift64(0x9E37_79B9_7F4A_7C15);
        for k in 0..400_000usize {
            let seed = next();
            let uk = if seed & 1 == 0 { 1.0 } else { -1.0 };
            let noise = ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 1e-3;
            let yk =
                if k < 2 { 0.0 } else { 1.6 * y[k - 1] - 0.8 * y[k - 2] + 0.3 * u[k - 1] + 0.1 * u[k - 2] + noise };
            u.push(uk);
            y.push(yk);
            text += &format!("{},{uk},{yk}\n", k as f64 * 1e-4);
        }
        std::fs::write(&path, text).unwrap();
        assert!(std::fs::metadata(&path).unwrap().len() > 8 << 20, "two blocks");
        let orders = ArxOrders { na: 2, nb: 2, nk: 1 };
        for zero_initial in [false, true] {
            let weight = Some(Weight { a: 1.0, gamma: 0.99999 });
            let got = run(&path, orders, zero_initial, weight, false).unwrap();
            let mut ls = WeightedLs::<f64, { MAX_PARAMETERS + 1 }>::new(4);
            let at = |s: &[f64], k: usize, lag: usize| if k >= lag { s[k - lag] } else { 0.0 };
            for k in if zero_initial { 0 } else { 2 }..u.len() {
                ls.forget(0.99999);
                ls.add_row(&[at(&y, k, 1), at(&y, k, 2), at(&u, k, 1), at(&u, k, 2)], y[k], 1.0);
            }
            let s = ls.solve().unwrap();
            assert_eq!((got.a.as_slice(), got.b.as_slice()), (&s.theta[..2], &s.theta[2..4]), "{zero_initial}");
            assert_eq!((got.sse, got.rows), (s.sse, s.rows));
            assert!((got.a[0] - 1.6).abs() < 1e-3 && (got.b[1] - 0.1).abs() < 1e-3, "{got:?}");
        }
        // A wild sample in the second block is named by its place in the record, not in its block.
        let k = 300_000;
        let (line, wild) =
            (format!("\n{},{},{}\n", k as f64 * 1e-4, u[k], y[k]), format!("\n{},{},1e6\n", k as f64 * 1e-4, u[k]));
        std::fs::write(&path, std::fs::read_to_string(&path).unwrap().replacen(&line, &wild, 1)).unwrap();
        let got = run(&path, orders, false, None, false).unwrap();
        assert!(got.notes.iter().any(|n| n.contains(&format!(" at sample {k} (the first is 0)"))), "{:?}", got.notes);
    }

    /// The rows a model's orders leave: those with every lag inside the record, `max(NA, NK + NB - 1)` samples in.
    #[test]
    fn the_rows_are_those_with_every_lag_in_the_record() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rows.csv");
        let mut next = nanopos_id::xorshift64(0x0123_4567_89AB_CDEF);
        let text: String = (0..100).map(|k| format!("{},{},{}\n", k, next() % 7, next() % 11)).collect();
        std::fs::write(&path, format!("t,u,y\n{text}")).unwrap();
        for (orders, rows) in [("2,0,0", 98), ("0,2,0", 99), ("1,2,3", 96), ("4,1,0", 96), ("1,1,0", 99)] {
            let got = run(&path, orders.parse().unwrap(), false, None, false).unwrap();
            assert_eq!(got.rows, rows, "{orders}");
            assert_eq!(run(&path, orders.parse().unwrap(), true, None, false).unwrap().rows, 100, "{orders}");
        }
    }
}
