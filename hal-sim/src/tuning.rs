//! `--tuning`: a preset name (`prbs`, `triangle`) or a TOML file that starts from a preset and overrides any single
//! value. Every key is optional; an unknown key, a wrong type or an out-of-range value is an error naming the file,
//! the key and the problem.
//!
//! ```toml
//! preset = "triangle"            # the base (default: prbs)
//! [rls]                          # continuous-time RLS
//! gamma = 0.25                   # forgetting, 1/s
//! p0 = [1e6, 1e1, 1e7]           # diag P(0) for [b0, a1, a0]
//! r0 = 1e9                       # bound on ||P||_F
//! [ekf]                          # both EKFs
//! q = [1e-12, 1e-6, 1.5e9, 0.25, 5e8]   # diag Q for [x1, x2, a0, a1, b0]
//! p0 = [1e-11, 1e-5, 1.5e10, 2.5, 5e9]  # diag P(0) (default 10 Q)
//! r = 1.5e-6                     # measurement noise, um^2 (hybrid: R / T per sample)
//! substeps = 4                   # hybrid prediction substeps
//! gate_sigma = 5.0               # innovation gate (relative to the running level)
//! change_samples = 20            # gated samples in a row that mean a plant change (0: off, gating off too)
//! drift_ratio = 4.0              # short- over long-run nu^2/S that means a gentle change (0: off; else >= 1)
//! reopen = 100.0                 # parameter variances after a drift, times P0 (1 to 100)
//! pe_floor_v2 = 1e-6             # input power below which the parameters freeze
//! [arx]
//! lambda = 0.9998                # forgetting per sample
//! max_trace = 1e3                # windup bound on trace F
//! ```

use crate::bank::Tuning;
use crate::cmd::{fail, CliError};
use serde::Deserialize;
use std::path::Path;

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct File {
    preset: Option<String>,
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
}

/// Resolve `--tuning`: a preset name, or a TOML file.
pub fn resolve(arg: &str) -> Result<Tuning, CliError> {
    if let Some(t) = Tuning::preset(arg) {
        return Ok(t);
    }
    let path = Path::new(arg);
    if !path.exists() && !arg.ends_with(".toml") {
        return fail(format!("--tuning: '{arg}' is neither a preset (prbs, triangle) nor a file"));
    }
    let text = std::fs::read_to_string(path)
        .map_err(|e| CliError(format!("{arg}: cannot read: {}", crate::cmd::io_reason(&e))))?;
    parse(arg, &text)
}

/// Parse a tuning file's text (`name` for messages).
pub fn parse(name: &str, text: &str) -> Result<Tuning, CliError> {
    let file: File = toml::from_str(text).map_err(|e| {
        let msg = e.message().replace('\n', " ");
        let at = e.span().map(|s| format!(":{}", 1 + text[..s.start].matches('\n').count())).unwrap_or_default();
        CliError(format!("{name}{at}: {msg}"))
    })?;
    let preset = file.preset.as_deref().unwrap_or("prbs");
    let mut t = Tuning::preset(preset)
        .ok_or_else(|| CliError(format!("{name}: preset '{preset}' unknown (known: prbs, triangle)")))?;
    let positive = |key: &str, x: f64| -> Result<f64, CliError> {
        if x.is_finite() && x > 0.0 {
            Ok(x)
        } else {
            fail(format!("{name}: {key} = {x}: must be a positive number"))
        }
    };
    let all_positive = |key: &str, v: &[f64]| -> Result<(), CliError> {
        for x in v {
            positive(key, *x)?;
        }
        Ok(())
    };
    if let Some(r) = file.rls {
        if let Some(x) = r.gamma {
            t.rls.gamma = positive("[rls] gamma", x)?;
        }
        if let Some(v) = r.p0 {
            all_positive("[rls] p0", &v)?;
            t.rls.p0_diag = v;
        }
        if let Some(x) = r.r0 {
            t.rls.r0 = positive("[rls] r0", x)?;
        }
    }
    if let Some(e) = file.ekf {
        if let Some(v) = e.q {
            all_positive("[ekf] q", &v)?;
            t.ekf.q_diag = v;
            if e.p0.is_none() {
                t.ekf.p0_diag = v.map(|x| 10.0 * x);
            }
        }
        if let Some(v) = e.p0 {
            all_positive("[ekf] p0", &v)?;
            t.ekf.p0_diag = v;
        }
        if let Some(x) = e.r {
            t.ekf.r = positive("[ekf] r", x)?;
        }
        if let Some(n) = e.substeps {
            if !(1..=64).contains(&n) {
                return fail(format!("{name}: [ekf] substeps = {n}: between 1 and 64"));
            }
            t.ekf.substeps = n;
        }
        if let Some(x) = e.gate_sigma {
            t.ekf.health.gate_sigma = positive("[ekf] gate_sigma", x)?;
        }
        if let Some(n) = e.change_samples {
            t.ekf.health.change_samples = n;
        }
        if let Some(x) = e.drift_ratio {
            if !(x == 0.0 || (x.is_finite() && x >= 1.0)) {
                return fail(format!("{name}: [ekf] drift_ratio = {x}: 0 (off) or at least 1"));
            }
            t.ekf.health.drift_ratio = x;
        }
        if let Some(x) = e.reopen {
            let ceiling = t.ekf.health.ceiling;
            if !(1.0..=ceiling).contains(&x) {
                return fail(format!("{name}: [ekf] reopen = {x}: between 1 and {ceiling} (the variance ceiling)"));
            }
            t.ekf.health.reopen = x;
        }
        if let Some(x) = e.pe_floor_v2 {
            if !(x.is_finite() && x >= 0.0) {
                return fail(format!("{name}: [ekf] pe_floor_v2 = {x}: must be zero or positive"));
            }
            t.ekf.health.pe_floor_v2 = x;
        }
    }
    if let Some(a) = file.arx {
        if let Some(x) = a.lambda {
            if !(x > 0.0 && x <= 1.0) {
                return fail(format!("{name}: [arx] lambda = {x}: must be in (0, 1]"));
            }
            t.arx.lambda = x;
        }
        if let Some(x) = a.max_trace {
            t.arx.max_trace = positive("[arx] max_trace", x)?;
        }
    }
    Ok(t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nanopos_id::estimators::ekf::EkfDesign;

    #[test]
    fn a_file_overrides_single_values_of_its_preset() {
        let t = parse(
            "t.toml",
            "preset = \"triangle\"\n[ekf]\nsubsteps = 8\ndrift_ratio = 0\nreopen = 10\n[rls]\ngamma = 0.5\n",
        )
        .unwrap();
        assert_eq!(t.ekf.q_diag, EkfDesign::Q1);
        assert_eq!(t.ekf.substeps, 8);
        assert_eq!((t.ekf.health.drift_ratio, t.ekf.health.reopen), (0.0, 10.0));
        assert_eq!(t.rls.gamma, 0.5);
        assert_eq!(t.arx, Tuning::preset("triangle").unwrap().arx);
        let q = parse("t.toml", "[ekf]\nq = [1e-12, 1e-6, 1e9, 1.0, 1e8]\n").unwrap();
        assert_eq!(q.ekf.p0_diag, [1e-12, 1e-6, 1e9, 1.0, 1e8].map(|x: f64| 10.0 * x), "P0 follows Q unless given");
    }

    #[test]
    fn bad_files_say_where_and_what() {
        let cases = [
            ("[ekf]\nsubsteps = 0\n", "t.toml: [ekf] substeps = 0: between 1 and 64"),
            ("[ekf]\nq = [1, 2]\n", "t.toml:2:"),
            ("[ekf]\nkalman = 1\n", "kalman"),
            ("[rls]\ngamma = -1\n", "[rls] gamma = -1: must be a positive number"),
            ("preset = \"fast\"\n", "preset 'fast' unknown"),
            ("[arx]\nlambda = 1.5\n", "[arx] lambda = 1.5: must be in (0, 1]"),
            ("[ekf\n", "t.toml:1:"),
            ("[ekf]\ndrift_ratio = 0.5\n", "[ekf] drift_ratio = 0.5: 0 (off) or at least 1"),
            ("[ekf]\nreopen = 1000\n", "[ekf] reopen = 1000: between 1 and 100 (the variance ceiling)"),
        ];
        for (text, want) in cases {
            let e = parse("t.toml", text).unwrap_err().0;
            assert!(e.contains(want), "{text:?}: {e}");
            assert!(!e.contains('\n'));
        }
    }
}
