//! `--tuning`: a preset name (`prbs`, `triangle`) or a TOML file that starts from a preset and overrides any single
//! value. Every key is optional; an unknown key, a wrong type or an out-of-range value is an error naming the file,
//! the key and the problem. The values are checked by the core's [`Tuning::set`], as the firmware's `tune` command
//! checks them (see [`nanopos_id::estimators::tuning`] for the keys and ranges), at the sample period of the record
//! they are used on (`identify` reads it from the record's first rows): `rls gamma`'s range and whether the
//! estimators can run the whole (`Tuning::runnable`) depend on it.
//!
//! ```toml
//! preset = "triangle"            # the base (default: prbs)
//! initial = [5e5, 70, 6e6]       # every estimator's initial [b0, a1, a0] (another stage: near its own values)
//! prefilter = [100, 450, 0.1]    # W_p: f_lc Hz, f_p Hz (near the stage's resonance), zeta_p
//! spike_ratio = 32               # the spike gate: third difference over its recent mean that is a spike (0: off)
//! [rls]                          # continuous-time RLS
//! gamma = 0.25                   # forgetting, 1/s
//! p0 = [1e6, 1e1, 1e7]           # diag P(0) for [b0, a1, a0]
//! r0 = 1e9                       # bound on ||P||_F
//! pe_floor_v2 = 1e-6             # pre-filtered input power below which the estimate is held, V^2
//! [ekf]                          # both EKFs
//! q = [1e-12, 1e-6, 1.5e9, 0.25, 5e8]   # diag Q for [x1, x2, a0, a1, b0]
//! p0 = [1e-11, 1e-5, 1.5e10, 2.5, 5e9]  # diag P(0) (default 10 Q)
//! r = 1.5e-6                     # measurement noise, um^2 (hybrid: R / T per sample)
//! substeps = 4                   # hybrid prediction substeps
//! gate_sigma = 5.0               # innovation gate (relative to the running level)
//! change_samples = 20            # gated samples in a row that mean a plant change (0: off, gating off too)
//! drift_ratio = 4.0              # short- over long-run nu^2/S that means a gentle change (0: off; else >= 1)
//! reopen = 500.0                 # parameter variances after a drift, times P0 (1 to 500)
//! pe_floor_v2 = 1e-6             # input power below which the parameters freeze
//! [arx]
//! lambda = 0.9998                # forgetting per sample
//! max_trace = 1e3                # windup bound on trace F
//! pe_floor_v2 = 1e-6             # as for the RLS and the EKFs
//! ```

use crate::bank::Tuning;
use crate::cmd::{fail, show, CliError};
use nanopos_id::estimators::TuningKey;
use serde::Deserialize;
use std::path::Path;

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct File {
    preset: Option<String>,
    initial: Option<[f64; 3]>,
    prefilter: Option<[f64; 3]>,
    spike_ratio: Option<u32>,
    rls: Option<Rls>,
    ekf: Option<Ekf>,
    arx: Option<Arx>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct Rls {
    gamma: Option<f64>,
    p0: Option<[f64; 3]>,
    r0: Option<f64>,
    pe_floor_v2: Option<f64>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct Ekf {
    q: Option<[f64; 5]>,
    p0: Option<[f64; 5]>,
    r: Option<f64>,
    substeps: Option<u32>,
    gate_sigma: Option<f64>,
    change_samples: Option<u32>,
    drift_ratio: Option<f64>,
    reopen: Option<f64>,
    pe_floor_v2: Option<f64>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct Arx {
    lambda: Option<f64>,
    max_trace: Option<f64>,
    pe_floor_v2: Option<f64>,
}

/// A `--tuning` as read: its preset and the file's values over it, checked and applied once the sample period is
/// known ([`TuningArg::at`]): `rls gamma`'s range and what the estimators can run depend on it (a pre-filter at
/// 4 kHz suits a 40 kHz record, not the board's 10 kHz).
#[derive(Clone, Debug)]
pub struct TuningArg {
    /// The file, or `--tuning NAME` for a preset (for messages).
    pub name: String,
    /// The file read, if any (no output may replace it).
    pub file: Option<std::path::PathBuf>,
    base: Tuning,
    /// The file's values, in its section order.
    values: Vec<(TuningKey, Vec<f64>)>,
}

impl From<Tuning> for TuningArg {
    /// A tuning already made (its sample period is replaced by the record's).
    fn from(base: Tuning) -> Self {
        TuningArg { name: "the tuning".into(), file: None, base, values: Vec::new() }
    }
}

impl TuningArg {
    /// The preset the tuning starts from, when it is one's (a file's `preset`, `prbs` by default).
    pub fn preset(&self) -> Option<&'static str> {
        ["prbs", "triangle"].into_iter().find(|&name| Tuning::preset(name) == Some(self.base))
    }

    /// The tuning for samples `dt` seconds apart: the preset's, with every value of the file through the core's one
    /// check (the console's `tune` uses it too), in the file's section order; `q` before `p0`, since `q` also sets
    /// `p0` to 10 Q. Whether the estimators can run the whole is the caller's check (in its scalar).
    pub fn at(&self, dt: f64) -> Result<Tuning, CliError> {
        let mut t = self.base.at_sample_period(dt);
        for (key, values) in &self.values {
            t.set(*key, values)
                .map_err(|r| CliError(format!("{}: {key} = {}: {}", self.name, show(values[r.index]), r.expected)))?;
        }
        Ok(t)
    }
}

/// Resolve `--tuning`: a preset name, or a TOML file.
pub fn resolve(arg: &str) -> Result<TuningArg, CliError> {
    if let Some(base) = Tuning::preset(arg) {
        return Ok(TuningArg { name: format!("--tuning {arg}"), file: None, base, values: Vec::new() });
    }
    let path = Path::new(arg);
    if !path.exists() && !arg.ends_with(".toml") {
        return fail(format!("--tuning: '{arg}' is neither a preset (prbs, triangle) nor a file"));
    }
    let bytes =
        std::fs::read(path).map_err(|e| CliError(format!("{arg}: cannot read: {}", crate::cmd::io_reason(&e))))?;
    let text = String::from_utf8(bytes).map_err(|e| {
        let bytes = e.as_bytes();
        let at = e.utf8_error().valid_up_to();
        let line = 1 + bytes[..at].iter().filter(|&&b| b == b'\n').count();
        CliError(format!("{arg}:{line}: not UTF-8 text (byte {:#04x}): is it a tuning file?", bytes[at]))
    })?;
    Ok(TuningArg { file: Some(path.to_path_buf()), ..parse(arg, &text)? })
}

/// A TOML reader's message as ours read: a number as [`show`] writes it (serde writes `1e-300` in 300 digits), a whole
/// number asked for in words (`expected u32`: `substeps = 4.5`).
fn readable(msg: &str) -> String {
    const FLOAT: &str = "floating point `";
    let mut msg = msg.replace("expected u32", "expected a whole number");
    if let Some(start) = msg.find(FLOAT).map(|i| i + FLOAT.len()) {
        if let Some(len) = msg[start..].find('`') {
            if let Ok(x) = msg[start..start + len].parse::<f64>() {
                msg.replace_range(start..start + len, &show(x));
            }
        }
    }
    msg
}

/// Parse a tuning file's text (`name` for messages): its syntax, keys, types and preset now, its values at
/// [`TuningArg::at`].
pub fn parse(name: &str, text: &str) -> Result<TuningArg, CliError> {
    let file: File = toml::from_str(text).map_err(|e| {
        let msg = readable(&e.message().replace('\n', " "));
        let at = e.span().map(|s| format!(":{}", 1 + text[..s.start].matches('\n').count())).unwrap_or_default();
        CliError(format!("{name}{at}: {msg}"))
    })?;
    let preset = file.preset.as_deref().unwrap_or("prbs");
    let base = Tuning::preset(preset)
        .ok_or_else(|| CliError(format!("{name}: preset '{preset}' unknown (known: prbs, triangle)")))?;
    let one = |x: Option<f64>| x.map(|x| vec![x]);
    let whole = |n: Option<u32>| n.map(|n| vec![n as f64]);
    let (r, e, a) = (file.rls.unwrap_or_default(), file.ekf.unwrap_or_default(), file.arx.unwrap_or_default());
    let values: [(TuningKey, Option<Vec<f64>>); 19] = [
        (TuningKey::Initial, file.initial.map(|v| v.to_vec())),
        (TuningKey::Prefilter, file.prefilter.map(|v| v.to_vec())),
        (TuningKey::SpikeRatio, whole(file.spike_ratio)),
        (TuningKey::RlsGamma, one(r.gamma)),
        (TuningKey::RlsP0, r.p0.map(|v| v.to_vec())),
        (TuningKey::RlsR0, one(r.r0)),
        (TuningKey::RlsPeFloor, one(r.pe_floor_v2)),
        (TuningKey::EkfQ, e.q.map(|v| v.to_vec())),
        (TuningKey::EkfP0, e.p0.map(|v| v.to_vec())),
        (TuningKey::EkfR, one(e.r)),
        (TuningKey::EkfSubsteps, whole(e.substeps)),
        (TuningKey::EkfGateSigma, one(e.gate_sigma)),
        (TuningKey::EkfChangeSamples, whole(e.change_samples)),
        (TuningKey::EkfDriftRatio, one(e.drift_ratio)),
        (TuningKey::EkfReopen, one(e.reopen)),
        (TuningKey::EkfPeFloor, one(e.pe_floor_v2)),
        (TuningKey::ArxLambda, one(a.lambda)),
        (TuningKey::ArxMaxTrace, one(a.max_trace)),
        (TuningKey::ArxPeFloor, one(a.pe_floor_v2)),
    ];
    let values = values.into_iter().filter_map(|(key, v)| Some((key, v?))).collect();
    Ok(TuningArg { name: name.to_string(), file: None, base, values })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nanopos_id::estimators::ekf::EkfDesign;

    /// A file's tuning at the board's sample period.
    fn at_board(text: &str) -> Result<Tuning, CliError> {
        parse("t.toml", text)?.at(1e-4)
    }

    #[test]
    fn a_file_overrides_single_values_of_its_preset() {
        let t = at_board(
            "preset = \"triangle\"\n[ekf]\nsubsteps = 8\ndrift_ratio = 0\nreopen = 10\n[rls]\ngamma = 0.5\n\
             pe_floor_v2 = 0\n",
        )
        .unwrap();
        assert_eq!(t.ekf.q_diag, EkfDesign::Q1);
        assert_eq!(t.ekf.substeps, 8);
        assert_eq!((t.ekf.health.drift_ratio, t.ekf.health.reopen), (0.0, 10.0));
        assert_eq!((t.rls.gamma, t.rls.pe_floor_v2), (0.5, 0.0));
        assert_eq!(t.arx, Tuning::preset("triangle").unwrap().arx);
        assert_eq!(at_board("[arx]\npe_floor_v2 = 2e-6\n").unwrap().arx.pe_floor_v2, 2e-6);
        assert_eq!((t.spike_ratio, at_board("spike_ratio = 0\n").unwrap().spike_ratio), (32, 0));
        let q = at_board("[ekf]\nq = [1e-12, 1e-6, 1e9, 1.0, 1e8]\n").unwrap();
        assert_eq!(q.ekf.p0_diag, [1e-12, 1e-6, 1e9, 1.0, 1e8].map(|x: f64| 10.0 * x), "P0 follows Q unless given");
        // Another stage: every estimator starts from its parameters.
        let other = at_board("initial = [1e6, 90, 3.9e7]\nprefilter = [150, 1000, 0.2]\n").unwrap();
        assert_eq!(
            (other.rls.prefilter.f_lc_hz, other.rls.prefilter.f_p_hz, other.rls.prefilter.zeta_p),
            (150.0, 1000.0, 0.2)
        );
        let p = nanopos_id::StageParams { b0: 1e6, a1: 90.0, a0: 3.9e7 };
        assert_eq!((other.rls.initial, other.ekf.initial, other.arx.initial), (p, p, p));
    }

    #[test]
    fn bad_files_say_where_and_what() {
        let cases = [
            ("[ekf]\nsubsteps = 0\n", "t.toml: [ekf] substeps = 0: between 1 and 64"),
            ("[ekf]\nq = [1, 2]\n", "t.toml:2:"),
            ("[ekf]\nkalman = 1\n", "kalman"),
            ("[rls]\ngamma = -1\n", "[rls] gamma = -1: above 0 and at most 10000 /s (the sample rate)"),
            ("preset = \"fast\"\n", "preset 'fast' unknown"),
            ("[arx]\nlambda = 1.5\n", "[arx] lambda = 1.5: must be in (0, 1]"),
            ("[arx]\npe_floor_v2 = -1\n", "[arx] pe_floor_v2 = -1: must be zero or positive"),
            ("[ekf\n", "t.toml:1:"),
            ("[ekf]\ndrift_ratio = 0.5\n", "[ekf] drift_ratio = 0.5: 0 (off) or at least 1"),
            ("[ekf]\nreopen = 5000\n", "[ekf] reopen = 5000: between 1 and 500 (the variance ceiling)"),
            ("initial = [5e5, 70, -6e6]\n", "t.toml: initial = -6000000: must be a positive number"),
            ("[ekf]\nq = [1, 1, 1, 0, 1]\n", "t.toml: [ekf] q = 0: must be a positive number"),
            ("spike_ratio = 70000\n", "t.toml: spike_ratio = 70000: a whole number from 0 (off) to 65535"),
            ("spike_ratio = 2.5\n", "t.toml:1: invalid type: floating point `2.5`, expected a whole number"),
            // Not 1e-300 in 300 digits.
            ("[ekf]\nsubsteps = 1e-300\n", "t.toml:2: invalid type: floating point `1e-300`, expected a whole number"),
            ("spike_ratio = -1\n", "t.toml:1:"),
        ];
        for (text, want) in cases {
            let e = at_board(text).unwrap_err().0;
            assert!(e.contains(want), "{text:?}: {e}");
            assert!(!e.contains('\n'));
        }
    }

    /// A file's values are checked at the sample period they are used at, not the board's: `gamma` of 15 000 /s is
    /// refused for 10 kHz samples and taken for 20 kHz ones, and the tuning is designed for the period given.
    #[test]
    fn a_files_values_are_checked_at_the_records_rate() {
        let file = parse("t.toml", "[rls]\ngamma = 15000\n").unwrap();
        let e = file.at(1e-4).unwrap_err().0;
        assert_eq!(e, "t.toml: [rls] gamma = 15000: above 0 and at most 10000 /s (the sample rate)");
        let fast = file.at(5e-5).unwrap();
        assert_eq!(fast.rls.gamma, 15000.0);
        assert_eq!((fast.rls.sample_period_s, fast.ekf.sample_period_s, fast.arx.sample_period_s), (5e-5, 5e-5, 5e-5));
        // The file is read once: syntax, keys and types at once, before any period is known.
        assert!(parse("t.toml", "[rls]\ngamma = \"fast\"\n").unwrap_err().0.starts_with("t.toml:2:"));
        let preset = resolve("triangle").unwrap();
        assert_eq!(preset.name, "--tuning triangle");
        assert_eq!(preset.at(1e-4).unwrap(), Tuning::preset("triangle").unwrap());
    }
}
