//! `nanopos-sim identify`: the outputs' shape, the validation figure, and bad inputs.

use std::path::Path;
use std::process::{Command, Output};

fn nanopos_sim(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_nanopos-sim")).args(args).current_dir(dir).output().expect("run nanopos-sim")
}

/// `run.csv` in `dir`: the paper's PRBS run on the simulated board, `seconds` long.
fn simulate_prbs(dir: &Path, seconds: &str) {
    let out = nanopos_sim(&["simulate", "--scenario", "prbs", "--duration", seconds, "--out", "run.csv"], dir);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

/// `run.csv` in `dir` with field `column` of every row (not the header's) replaced by `f` of it, written to `name`.
fn rewrite_column(dir: &Path, name: &str, column: usize, f: impl Fn(&str) -> String) {
    let run = std::fs::read_to_string(dir.join("run.csv")).unwrap();
    let mut lines = run.lines();
    let mut text = lines.next().unwrap().to_string() + "\n";
    for line in lines {
        let mut fields: Vec<String> = line.split(',').map(str::to_string).collect();
        fields[column] = f(&fields[column]);
        text += &(fields.join(",") + "\n");
    }
    std::fs::write(dir.join(name), text).unwrap();
}

/// The number after the first `"key": ` in a summary's JSON text.
fn number_after(json: &str, key: &str) -> f64 {
    let rest = json.split(&format!("\"{key}\": ")).nth(1).unwrap_or_else(|| panic!("no {key}: {json}"));
    rest.split([',', '}']).next().unwrap().parse().unwrap()
}

/// What `identify` says of an 8 s PRBS record (`run.csv` in `dir`) whose `y` went through `f`, written to `name`.
fn notes_with_y(dir: &Path, name: &str, f: impl Fn(&str) -> String) -> String {
    simulate_prbs(dir, "8");
    rewrite_column(dir, name, 2, f);
    identify_notes(dir, name)
}

/// The rest of the line of `text` from where `start` is in it (which it must be).
fn line_from<'a>(text: &'a str, start: &str) -> &'a str {
    let at = text.find(start).unwrap_or_else(|| panic!("no {start:?} in {text}"));
    text[at..].lines().next().unwrap()
}

/// What `identify` with all four estimators says on standard error about `input` in `dir` (it must succeed).
fn identify_notes(dir: &Path, input: &str) -> String {
    let out = nanopos_sim(&["identify", "--input", input, "--summary", "s.json"], dir);
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(out.status.success(), "{stderr}");
    stderr
}

#[test]
fn identify_writes_estimates_and_a_summary_of_a_simulated_run() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_prbs(d, "4");
    let out = nanopos_sim(
        &[
            "identify",
            "--input",
            "run.csv",
            "--estimators",
            "hekf,arx",
            "--window",
            "1:2",
            "--window",
            "3:4",
            "--out",
            "est.csv",
            "--summary",
            "sum.json",
            "--plot",
            "fig.svg",
        ],
        d,
    );
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let est = std::fs::read_to_string(d.join("est.csv")).unwrap();
    let lines: Vec<&str> = est.lines().collect();
    assert_eq!(lines[0], "t,estimator,a0,a1,b0,f0_hz,zeta,dc_gain");
    // 100 Hz for 4 s, two estimators.
    assert_eq!(lines.len() - 1, 400 * 2);
    assert!(lines[1].contains(",hekf,") && lines[2].contains(",arx,"));
    let sum = std::fs::read_to_string(d.join("sum.json")).unwrap();
    for key in [
        "\"windows\"",
        "\"t0\": 1.0",
        "\"t1\": 4.0",
        "\"hekf\"",
        "\"arx\"",
        "\"rmse_nm\"",
        "\"innovation_rms_nm\"",
        "\"starved\": 0.0",
        "\"resets\": 0",
        "\"f0_hz\"",
        "\"zeta\"",
        "\"dc_gain\"",
        "\"truth\"",
    ] {
        assert!(sum.contains(key), "{key} missing in {sum}");
    }
    assert!(!sum.contains("NaN") && !sum.contains("inf"));
    let svg = std::fs::read_to_string(d.join("fig.svg")).unwrap();
    for word in ["<svg", "hekf", "arx", "truth", "error against the truth"] {
        assert!(svg.contains(word), "{word} missing in the plot");
    }
}

/// A record whose input is one sinusoid (1 V at 100 Hz, in the board's DAC steps) identifies nothing: every
/// estimator is held by the excitation monitor, the summary says so (`starved` 1 over a window after the first
/// second), and a note on standard error per estimator and window tells the user the means are held values.
/// `--health`: each estimator's health on the rows of `EST.csv`, as the board's `status` gives it. On the simulated
/// PRBS record with the payload removed at 2 s both EKFs detect the change (their counts go from 0 to 1 there), and
/// their innovation RMS, of the last second, shows it and is back at the record's level 2 s later (measured: 6.2-6.3
/// nm before, 56-58 nm 0.5 s after, 6.7-6.8 nm at the end); the ARX has no innovation.
#[test]
fn identify_writes_the_estimators_health_over_time() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_prbs(d, "4");
    let args =
        ["identify", "--input", "run.csv", "--estimators", "ekf,hekf,arx", "--health", "h.csv", "--out", "e.csv"];
    let out = nanopos_sim(&args, d);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let health = std::fs::read_to_string(d.join("h.csv")).unwrap();
    let est = std::fs::read_to_string(d.join("e.csv")).unwrap();
    let lines: Vec<&str> = health.lines().collect();
    assert_eq!(lines[0], "t,estimator,state,rejected,changes,resets,repairs,innovation_rms_um");
    // The rows of EST.csv: the same times and estimators.
    let keys = |text: &str| {
        text.lines().skip(1).map(|l| l.split(',').take(2).collect::<Vec<_>>().join(",")).collect::<Vec<_>>()
    };
    assert_eq!(keys(&health), keys(&est));
    assert_eq!(lines.len() - 1, 400 * 3);
    let row = |t: &str, name: &str| -> Vec<String> {
        let l = lines.iter().find(|l| l.starts_with(&format!("{t},{name},"))).unwrap_or_else(|| panic!("{t} {name}"));
        l.split(',').map(String::from).collect()
    };
    let innovation = |t: &str, name: &str| row(t, name)[7].parse::<f64>().unwrap();
    for name in ["ekf", "hekf"] {
        assert_eq!(row("1.9999", name)[2..7], ["adapting", "0", "0", "0", "0"], "{name}");
        assert_eq!(row("3.9999", name)[4], "1", "{name}: the change, detected");
        let (before, after, end) = (innovation("1.9999", name), innovation("2.4999", name), innovation("3.9999", name));
        assert!(before < 0.01 && after > 5.0 * before && end < 1.2 * before, "{name}: {before} {after} {end}");
    }
    assert_eq!(row("3.9999", "arx")[2..], ["adapting", "0", "0", "0", "0", ""]);
}

#[test]
fn identify_reports_a_window_the_excitation_monitor_held() {
    let dir = tempfile::tempdir().unwrap();
    let lsb = 3.3 / 4096.0 / 0.165;
    let mut text = String::from("t,u,y\n");
    for k in 0..30_000 {
        let t = k as f64 * 1e-4;
        let u = ((2.0 * std::f64::consts::PI * 100.0 * t).sin() / lsb).round() * lsb;
        text += &format!("{t},{u},{}\n", 0.1 * u);
    }
    std::fs::write(dir.path().join("sine.csv"), text).unwrap();
    let out = nanopos_sim(&["identify", "--input", "sine.csv", "--window", "2:3"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let json = String::from_utf8(out.stdout).unwrap();
    assert_eq!(json.matches("\"starved\": 1.0").count(), 4, "{json}");
    let stderr = String::from_utf8(out.stderr).unwrap();
    for name in ["rls", "ekf", "hekf", "arx"] {
        let note = format!("note: {name} was held by the excitation monitor for 100 % of window 2:3");
        assert!(stderr.contains(&note), "{note} missing in {stderr}");
    }
}

/// On a stage at 1 kHz, far from the initial parameters (423 Hz), the ARX's discrete model has no continuous
/// equivalent for most of its first 2 s, and it reports the last parameters that had, near the initial ones: the
/// summary says the share of the window they were held (`held`), `HEALTH.csv` says `held`, and a note says what the
/// means are; once it has converged, none.
#[test]
fn identify_reports_a_window_where_the_arx_held_its_parameters() {
    use hal_sim::{lab::Lab, sim::Simulation};
    let dir = tempfile::tempdir().unwrap();
    let w = 2.0 * std::f64::consts::PI * 1000.0;
    let stage = nanopos_id::StageParams { a0: w * w, a1: 0.02 * w, b0: 0.05 * w * w };
    let (board, settings) = Lab::settings(Some(stage));
    let mut sim = Simulation::new(board, &settings, ()).unwrap();
    let mut text = String::from("t,u,y\n");
    for _ in 0..60_000 {
        let (r, _) = sim.step();
        text += &format!("{},{},{}\n", r.t_s, r.u_v, r.y_um);
    }
    std::fs::write(dir.path().join("khz.csv"), text).unwrap();
    let args = [
        "identify",
        "--input",
        "khz.csv",
        "--estimators",
        "arx",
        "--window",
        "0:1",
        "--window",
        "5:6",
        "--health",
        "h.csv",
    ];
    let out = nanopos_sim(&args, dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let json = String::from_utf8(out.stdout).unwrap();
    let held: Vec<f64> = json
        .match_indices("\"held\": ")
        .map(|(i, _)| json[i + 8..].split([',', '}']).next().unwrap().parse().unwrap())
        .collect();
    // Measured: 0.98 (the first rows' conversion still had one) and 0.
    assert!(held.len() == 2 && held[0] > 0.9 && held[1] == 0.0, "{json}");
    let stderr = String::from_utf8(out.stderr).unwrap();
    let note = format!(
        "note: arx's parameters were held for {:.0} % of window 0:1 (its model had no continuous equivalent",
        100.0 * held[0]
    );
    assert!(stderr.contains(&note), "{note} missing in {stderr}");
    assert!(!stderr.contains("window 5:6 (its model"), "{stderr}");
    let health = std::fs::read_to_string(dir.path().join("h.csv")).unwrap();
    assert!(health.contains("\n0.5099,arx,held,") && health.contains("\n5.9999,arx,adapting,"), "{health}");
    // Every estimator: the EKFs settled on a wrong solution, and the notes say their model fits far worse than the
    // ARX's and take the ARX's resonance (1 kHz, not the hybrid EKF's 370 Hz) for the pre-filter's note.
    let out = nanopos_sim(&["identify", "--input", "khz.csv", "--window", "5:6"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stderr = String::from_utf8(out.stderr).unwrap();
    println!("{stderr}");
    for name in ["ekf", "hekf"] {
        assert!(stderr.contains(&format!("note: {name}'s model fits window 5:6 ")), "{name}: {stderr}");
    }
    assert!(stderr.contains(" times the resonance (1000 Hz, arx's mean)"), "{stderr}");
    assert!(stderr.contains("note: window 5:6: the resonance, 1000 Hz (arx's mean), is at w T = 0.63 "), "{stderr}");
    // Without the continuous EKF, no such note.
    let out =
        nanopos_sim(&["identify", "--input", "khz.csv", "--window", "5:6", "--estimators", "hekf,arx"], dir.path());
    assert!(out.status.success() && !String::from_utf8_lossy(&out.stderr).contains(" w T = "));
}

/// A tuning that drives an estimator to non-finite values resets it over and over (each time back to its initial
/// parameters, and adapting again): the summary counts the resets per window and a note says its means are of runs
/// that diverged. Here `R` a million times below the paper's, which the continuous EKF cannot integrate and the
/// hybrid one can (`tests/instrument.rs`, `a_far_smaller_r_breaks_the_continuous_ekf_and_not_the_hybrid`).
#[test]
fn identify_reports_an_estimator_that_keeps_resetting() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_prbs(d, "2");
    std::fs::write(d.join("small_r.toml"), "[ekf]\nr = 1.5e-12\n").unwrap();
    let args = ["identify", "--input", "run.csv", "--estimators", "ekf,hekf", "--tuning", "small_r.toml"];
    let out = nanopos_sim(&[&args[..], &["--window", "1:2"]].concat(), d);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let json = String::from_utf8(out.stdout).unwrap();
    let resets = |name: &str| {
        let at = json.find(&format!("\"{name}\": {{")).unwrap();
        let at = at + json[at..].find("\"resets\": ").unwrap() + 10;
        json[at..].split('}').next().unwrap().trim().parse::<u32>().unwrap()
    };
    let (ekf, hekf) = (resets("ekf"), resets("hekf"));
    eprintln!("resets in 1-2 s: ekf {ekf}, hekf {hekf}");
    assert!(ekf > 50 && hekf == 0, "{ekf} {hekf}");
    let stderr = String::from_utf8(out.stderr).unwrap();
    let note = format!(
        "note: ekf met a non-finite value (or an innovation beyond a metre, or no relock within 5 s) and went back to \
         its initial parameters {ekf} times in window 1:2"
    );
    assert!(stderr.contains(&note), "{note} missing in {stderr}");
    assert!(!stderr.contains("hekf met"), "{stderr}");
}

/// The excitation monitor discounts the board's DAC steps (4.88 mV) by default; a record from elsewhere, not rounded,
/// says so with `--dac-step 0`. A PRBS of 5 mV (about one DAC step) that is not rounded is then rich; taken for the
/// board's it is held more than half the time (its spread is what the rounding could leave).
#[test]
fn identify_takes_the_inputs_dac_step() {
    let dir = tempfile::tempdir().unwrap();
    let mut text = String::from("t,u,y\n");
    let mut lfsr = 0x7FFFu16;
    for k in 0..30_000 {
        if k % 5 == 0 {
            lfsr = ((lfsr << 1) | (((lfsr >> 14) ^ (lfsr >> 13)) & 1)) & 0x7FFF;
        }
        let u = if lfsr & 1 == 1 { 0.005 } else { -0.005 };
        text += &format!("{},{u},{}\n", k as f64 * 1e-4, 0.1 * u);
    }
    std::fs::write(dir.path().join("prbs.csv"), text).unwrap();
    let starved = |extra: &[&str]| {
        let args = [&["identify", "--input", "prbs.csv", "--estimators", "hekf", "--window", "2:3"], extra].concat();
        let out = nanopos_sim(&args, dir.path());
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let json = String::from_utf8(out.stdout).unwrap();
        let at = json.find("\"starved\": ").unwrap() + 11;
        json[at..].split(['}', ',']).next().unwrap().trim().parse::<f64>().unwrap()
    };
    let (board, unrounded) = (starved(&[]), starved(&["--dac-step", "0"]));
    eprintln!("5 mV PRBS held {board} of the window as the board's input, {unrounded} as unrounded");
    assert!(board > 0.5 && unrounded == 0.0, "{board} {unrounded}");
}

/// A tuning is checked at the sample period of the record it runs on, not the board's 10 kHz: a pre-filter at 4.9 kHz
/// (beyond what the continuous-time RLS's RK4 step follows at 10 kHz) and a forgetting rate of 15 000 /s run on a
/// 40 kHz record, and are refused for a 10 kHz one. (They were refused on reading the file, whatever the record.)
#[test]
fn a_tuning_is_checked_at_its_records_sample_rate() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for (name, dt, n) in [("r40.csv", 2.5e-5, 20_000), ("r10.csv", 1e-4, 5_000)] {
        let rows = (0..n).map(|k| format!("{},{},0\n", k as f64 * dt, if k % 7 < 3 { 0.5 } else { -0.5 }));
        std::fs::write(d.join(name), rows.fold("t,u,y\n".to_string(), |a, b| a + &b)).unwrap();
    }
    std::fs::write(d.join("fast_band.toml"), "prefilter = [100, 4900, 0.1]\n").unwrap();
    std::fs::write(d.join("fast_rls.toml"), "[rls]\ngamma = 15000\n").unwrap();
    for toml in ["fast_band.toml", "fast_rls.toml"] {
        let out = nanopos_sim(&["identify", "--input", "r40.csv", "--tuning", toml, "--estimators", "rls"], d);
        assert!(out.status.success(), "{toml}: {}", String::from_utf8_lossy(&out.stderr));
        let out = nanopos_sim(&["identify", "--input", "r10.csv", "--tuning", toml, "--estimators", "rls"], d);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{toml}: {stderr}");
        assert!(stderr.contains(&format!("nanopos-sim: {toml}: ")), "{stderr}");
    }
}

/// `--precision f32` runs the pipeline and the estimators in the firmware's scalar: on the paper's PRBS run its window
/// means agree with f64's to 1e-4 (SPEC 10), the summary says which it is, and a tuning f32 cannot hold (`R` of
/// 1e-45 um^2: `1 / R` overflows f32), which the board's `tune` refuses and f64 runs, is refused, naming the tuning.
#[test]
fn identify_in_the_firmwares_f32() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_prbs(d, "8");
    let summary = |precision: &str| {
        let args = ["identify", "--input", "run.csv", "--estimators", "rls,ekf,hekf", "--precision", precision];
        let out = nanopos_sim(&args, d);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8(out.stdout).unwrap()
    };
    let (s64, s32) = (summary("f64"), summary("f32"));
    assert!(s64.starts_with("{\"precision\": \"f64\", ") && s32.starts_with("{\"precision\": \"f32\", "));
    assert_eq!(summary("f64"), s64, "the default is f64 and repeatable");
    let numbers = |s: &str, key: &str| -> Vec<f64> {
        s.split(&format!("\"{key}\": ")).skip(1).map(|v| v.split([',', '}']).next().unwrap().parse().unwrap()).collect()
    };
    let mut worst = 0.0f64;
    for key in ["a0", "a1", "b0"] {
        let (v64, v32) = (numbers(&s64, key), numbers(&s32, key));
        assert_eq!(v64.len(), 2 * 4, "{key}: two windows, three estimators and the truth");
        for (a, b) in v64.iter().zip(&v32) {
            worst = worst.max((b / a - 1.0).abs());
        }
    }
    eprintln!("f32 against f64, window means of a0, a1, b0: worst relative difference {worst:.1e}");
    assert!(worst > 0.0 && worst < 1e-4, "{worst:e}");

    std::fs::write(d.join("tiny_r.toml"), "[ekf]\nr = 1e-45\n").unwrap();
    let args = ["identify", "--input", "run.csv", "--estimators", "ekf", "--tuning", "tiny_r.toml", "--window", "7:8"];
    let out = nanopos_sim(&args, d);
    assert!(out.status.success(), "f64 holds it: {}", String::from_utf8_lossy(&out.stderr));
    let out = nanopos_sim(&[&args[..], &["--precision", "f32"]].concat(), d);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    let refusal =
        "nanopos-sim: tiny_r.toml: at the sample period of run.csv (0.0001 s), in f32: the estimators cannot \
                   hold this tuning";
    assert!(stderr.starts_with(refusal) && stderr.lines().count() == 1, "{stderr}");
    assert!(out.stdout.is_empty());
}

/// A pre-filter centred more than a factor of 2 from the resonance is noted per window, against the hybrid EKF's
/// mean there: at 900 Hz it is 2.13 times the payload's 423 Hz and 1.86 times the 483 Hz without it, so only the first
/// window is noted (on this board `b0` is then 7-9 % off in the RLS and the ARX: `PrefilterDesign::off_resonance`).
#[test]
fn identify_notes_a_prefilter_far_from_the_resonance() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_prbs(d, "8");
    std::fs::write(d.join("wide.toml"), "prefilter = [100, 900, 0.1]\n").unwrap();
    // The EKFs only: in 8 s the RLS-type estimators have not converged, which another note says.
    let ekfs = ["--estimators", "ekf,hekf"];
    let out = nanopos_sim(
        &[&["identify", "--input", "run.csv", "--tuning", "wide.toml", "--summary", "s.json"], &ekfs[..]].concat(),
        d,
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert_eq!(
        stderr,
        "nanopos-sim: note: window 3:4: the pre-filter's f_p (900 Hz) is 2.129 times the resonance (423 Hz, hekf's \
         mean): the estimates can come out biased by several %; give --tuning a pre-filter near the resonance \
         (prefilter = [F_LC, F_P, ZETA])\n"
    );
    let out = nanopos_sim(&[&["identify", "--input", "run.csv", "--summary", "s.json"], &ekfs[..]].concat(), d);
    assert!(out.status.success() && out.stderr.is_empty(), "{}", String::from_utf8_lossy(&out.stderr));
}

/// Wild samples in a record (a glitch, or a logger's overflow value). One reading of 10^5 um (10^5 times the PRBS
/// record's level) went through the pre-filter as an impulse and the estimators took it for data: the hybrid EKF kept
/// a model 200-300 times worse than the data for the rest of the record, with exit 0 and not a word. Now the spike
/// gate replaces it before the filters (`nanopos_id::filters::spike`), and the notes name the sample, say that it was
/// replaced, and count the gate's replacements; no estimator misfits. A burst of five such readings is more than the
/// gate replaces in a row (`spike::MAX_RUN`): its third is taken, and the estimators see it. That one the notes say
/// the estimators took for data, with the estimator whose model does not fit the window after it; and since the EKFs
/// reset a filter that has not relocked 5 s after a change (`RELOCK_NIS_RATIO`), the hybrid one fits the last window
/// again; so does the single reading with the gate off (`--spike-ratio 0`). A spike a thousand times smaller, below
/// the wild bound (`Spread::WILD`), gets the gate's note alone; the record as simulated, none.
#[test]
fn wild_samples_are_noted() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_prbs(d, "8");
    let run = std::fs::read_to_string(d.join("run.csv")).unwrap();
    let with = |column: usize, lines: std::ops::Range<usize>, value: &str| {
        let mut all: Vec<String> = run.lines().map(str::to_string).collect();
        for line in lines {
            let mut fields: Vec<&str> = all[line - 1].split(',').collect();
            fields[column] = value;
            all[line - 1] = fields.join(",");
        }
        all.join("\n") + "\n"
    };
    let notes_with = |csv: &str, options: &[&str]| {
        std::fs::write(d.join("wild.csv"), csv).unwrap();
        let args = ["identify", "--input", "wild.csv", "--estimators", "ekf,hekf", "--summary", "s.json"];
        let out = nanopos_sim(&[&args[..], options].concat(), d);
        let stderr = String::from_utf8(out.stderr).unwrap();
        assert!(out.status.success(), "{stderr}");
        stderr
    };
    let notes = |csv: &str| notes_with(csv, &[]);
    let replaced = |n: usize| format!("note: the spike gate replaced {n} of y's readings, the first at 0.0998 s: ");
    let stderr = notes(&with(2, 1000..1001, "1e5"));
    eprintln!("{stderr}");
    assert!(stderr.contains("note: y reaches 100000 um at 0.0998 s, "), "{stderr}");
    assert!(stderr.contains("times the level 90 % of the record stays within"), "{stderr}");
    assert!(stderr.contains("The spike gate replaced it, and every reading that far out: the estimators did not"));
    assert!(stderr.contains(&replaced(1)), "{stderr}");
    assert!(!stderr.contains("'s model fits window"), "{stderr}");
    // The gate off (`--spike-ratio 0`): the estimators take it, as before the gate.
    let stderr = notes_with(&with(2, 1000..1001, "1e5"), &["--spike-ratio", "0"]);
    assert!(stderr.contains("The filters spread one such sample over tenths of a second and the estimators take it"));
    assert!(stderr.contains("note: hekf's model fits window 3:4 ") && !stderr.contains("spike gate"), "{stderr}");
    // So in a tuning file (as `decode` writes the board's after `tune spike_ratio 0`); `--spike-ratio` overrides it.
    std::fs::write(d.join("off.toml"), "spike_ratio = 0\n").unwrap();
    assert_eq!(notes_with(&with(2, 1000..1001, "1e5"), &["--tuning", "off.toml"]), stderr);
    let summary = std::fs::read_to_string(d.join("s.json")).unwrap();
    assert!(summary.ends_with(", \"spike_gate\": {\"ratio\": 0, \"replaced\": 0}}\n"), "{summary}");
    let on = notes_with(&with(2, 1000..1001, "1e5"), &["--tuning", "off.toml", "--spike-ratio", "32"]);
    assert!(on.contains(&replaced(1)) && !on.contains("'s model fits window"), "{on}");
    // The summary says what the gate did: the last run's (ratio 32, one replaced).
    let summary = std::fs::read_to_string(d.join("s.json")).unwrap();
    assert!(summary.ends_with(", \"spike_gate\": {\"ratio\": 32, \"replaced\": 1}}\n"), "{summary}");
    let stderr = notes(&with(2, 1000..1005, "1e5"));
    eprintln!("{stderr}");
    assert!(stderr.contains("note: y reaches 100000 um at 0.0998 s, "), "{stderr}");
    assert!(stderr.contains("The filters spread one such sample over tenths of a second and the estimators take it"));
    // The burst's first two readings, and the first two after it (the drop back), replaced.
    assert!(stderr.contains(&replaced(4)), "{stderr}");
    assert!(stderr.contains("note: hekf's model fits window 3:4 "), "{stderr}");
    assert!(!stderr.contains("note: hekf's model fits window 7:8 "), "{stderr}");
    assert!(!stderr.contains("note: ekf's model"), "{stderr}");
    let stderr = notes(&with(1, 5000..5001, "-9.9e37"));
    assert!(stderr.contains("note: u reaches 9.90e37 V at 0.4998 s, "), "{stderr}");
    let stderr = notes(&with(2, 1000..1001, "1e2"));
    assert!(stderr.starts_with(&format!("nanopos-sim: {}", replaced(1))) && stderr.lines().count() == 1, "{stderr}");
    assert!(notes(&run).is_empty(), "the record as simulated");
}

/// A record's time may start anywhere: the default windows are the last quarter of each half of the record's own
/// span (from 10 s to 18 s: 13-14 s and 17-18 s, as 3-4 s and 7-8 s from 0), and the estimates there are those of
/// the same record from 0 (to the rounding of its sample period, read from the times).
#[test]
fn the_default_windows_follow_a_record_that_starts_late() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_prbs(d, "8");
    rewrite_column(d, "late.csv", 0, |t| format!("{:.4}", t.parse::<f64>().unwrap() + 10.0));
    let summary = |name: &str| {
        let out = nanopos_sim(&["identify", "--input", name, "--estimators", "hekf", "--summary", "s.json"], d);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        std::fs::read_to_string(d.join("s.json")).unwrap()
    };
    let (early, late) = (summary("run.csv"), summary("late.csv"));
    let a0 =
        |json: &str, t0: &str| number_after(json.split(&format!("{{\"t0\": {t0}, \"t1\": ")).nth(1).expect(json), "a0");
    for (from_0, from_10) in [("3.0", "13.0"), ("7.0", "17.0")] {
        let (e, l) = (a0(&early, from_0), a0(&late, from_10));
        assert!((l / e - 1.0).abs() < 1e-9, "window from {from_10} s: a0 {l} against {e}");
    }
}

/// A record of fewer than 4 samples is refused for its count; one of 4 passes the count and is refused for what it is
/// then: too short for an estimate (one every 0.01 s) in its window.
#[test]
fn a_record_of_fewer_than_four_samples_is_refused_for_its_count() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for (rows, said) in [
        (3, "short.csv: too few rows (3): identification needs a record of at least 4 samples"),
        (4, "short.csv: window 0:1 holds no estimate (the record covers 0 to 0.0003 s;"),
    ] {
        let body: String = (0..rows).map(|k| format!("{:.4},0.5,0.01\n", k as f64 * 1e-4)).collect();
        std::fs::write(d.join("short.csv"), format!("t,u,y\n{body}")).unwrap();
        let out = nanopos_sim(&["identify", "--input", "short.csv", "--window", "0:1", "--summary", "s.json"], d);
        let stderr = String::from_utf8(out.stderr).unwrap();
        assert!(out.status.code() == Some(2) && stderr.contains(said), "{rows} rows: {stderr}");
        assert!(!d.join("s.json").exists(), "{rows} rows: no summary");
    }
}

/// A reading that never changes (a stuck probe, or the wrong column: here `y` all zeros under the PRBS) is said to
/// be one, per window; the models' misfits against each other, which every model fitting zeros to within rounding
/// made ratios of 1e45 and more, are not.
#[test]
fn a_reading_that_never_changes_is_noted_as_such() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let stderr = notes_with_y(d, "still.csv", |_| "0".to_string());
    for w in ["3:4", "7:8"] {
        let note = format!("note: window {w}: y does not change over it: there is nothing to identify from");
        assert!(stderr.contains(&note), "{stderr}");
    }
    // Nor is it asked whether y is in um: it does not move at all, not too little.
    assert!(!stderr.contains("times worse") && !stderr.contains("is y in um"), "{stderr}");
}

/// A reading in metres where um is read (a logger's SI units) moves 5e-4 nm RMS: the notes said that the reading
/// barely follows the input and asked whether the probe is connected. Now a note asks whether `y` is in um, as it
/// does for a reading in pm, and the probe's question goes; the record in um gets neither.
#[test]
fn a_reading_in_another_unit_is_asked_about() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scaled = |f: f64| move |y: &str| format!("{:?}", y.parse::<f64>().unwrap() * f);
    let asked = |w: &str| format!("note: window {w}: y moves ");
    let metres = notes_with_y(d, "m.csv", scaled(1e-6));
    for w in ["3:4", "7:8"] {
        let line = line_from(&metres, &asked(w));
        assert!(line.contains("nm RMS over it, less than a picometre, which no probe resolves: is y in um?"), "{line}");
        assert!(line.ends_with("in metres the stage's motion reads a million times too small)"), "{line}");
    }
    assert!(!metres.contains("barely follows"), "{metres}");
    let pm = notes_with_y(d, "pm.csv", scaled(1e6));
    for w in ["3:4", "7:8"] {
        assert!(pm.contains(&asked(w)), "{pm}");
    }
    assert!(pm.contains("more than a centimetre, which no nanopositioning stage moves: is y in um?"), "{pm}");
    let um = notes_with_y(d, "um.csv", str::to_string);
    assert!(!um.contains("y moves") && !um.contains("barely follows"), "{um}");
}

/// A command in mV or in DAC codes: every gain the estimators give reads that scale too small, and nothing else
/// said so. A note asks whether `u` is in V; none for the record in V, nor for the command about an offset of 8 V,
/// nor for one up to twice the +-10 V.
#[test]
fn a_command_in_another_unit_is_asked_about() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let asked = "note: u stays within ";
    simulate_prbs(d, "8");
    let scaled = |f: f64, o: f64| move |u: &str| format!("{:?}", u.parse::<f64>().unwrap() * f + o);
    rewrite_column(d, "mv.csv", 1, scaled(1e3, 0.0));
    let mv = identify_notes(d, "mv.csv");
    let line = line_from(&mv, asked);
    assert!(line.contains(" V for 90 % of the record, beyond the +-10 V of a command"), "{line}");
    assert!(
        line.contains("is u in V? (identify reads it so; in mV every gain, b0 and the DC gain, reads a thousand"),
        "{line}"
    );
    // 12-bit codes about mid-scale, 204.8 a volt.
    rewrite_column(d, "codes.csv", 1, scaled(204.8, 2048.0));
    assert!(identify_notes(d, "codes.csv").contains(asked));
    rewrite_column(d, "offset.csv", 1, scaled(1.0, 8.0));
    // Up to twice the +-10 V (an amplifier that takes more): the 1-V PRBS as 17.6 V, whose level reads 20 V, the
    // bound itself.
    rewrite_column(d, "twice.csv", 1, scaled(17.6, 0.0));
    for name in ["run.csv", "offset.csv", "twice.csv"] {
        let notes = identify_notes(d, name);
        assert!(!notes.contains(asked), "{name}: {notes}");
    }
}

/// A triangle record identified with the default tuning (the paper's Q2, for the PRBS): the EKFs fit 5 times worse
/// than the ARX, which the notes said without why. Now a note names the slow input and the tuning for it; with that
/// tuning no note at all, and on the PRBS record none of the kind.
#[test]
fn a_slow_input_with_the_prbs_tuning_is_given_the_triangle_tuning() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = nanopos_sim(&["simulate", "--scenario", "triangle", "--duration", "8", "--out", "tri.csv"], d);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let notes = identify_notes(d, "tri.csv");
    for w in ["3:4", "7:8"] {
        let note = format!("note: window {w}: the input moves slowly against the resonance (11 Hz RMS against ");
        let line = line_from(&notes, &note);
        assert!(line.contains("the EKFs' Q is the paper's Q2, for the PRBS"), "{line}");
        assert!(line
            .ends_with("ekf and hekf fit worse here; --tuning triangle gives them Q1, the paper's for the triangle"));
    }
    // The EKFs alone: nothing to compare them with, and the same note says so.
    let out = nanopos_sim(&["identify", "--input", "tri.csv", "--estimators", "ekf,hekf", "--summary", "s.json"], d);
    let alone = String::from_utf8(out.stderr).unwrap();
    for w in ["3:4", "7:8"] {
        let line = line_from(&alone, &format!("note: window {w}: the input moves slowly against the resonance"));
        assert!(line.contains("and with no ARX or RLS run (the default runs all four) nothing here tells"), "{line}");
    }
    let out = nanopos_sim(&["identify", "--input", "tri.csv", "--tuning", "triangle", "--summary", "s.json"], d);
    assert!(out.status.success() && out.stderr.is_empty(), "{}", String::from_utf8_lossy(&out.stderr));
    simulate_prbs(d, "8");
    assert!(!identify_notes(d, "run.csv").contains("moves slowly"));
    let out = nanopos_sim(&["identify", "--input", "run.csv", "--estimators", "ekf,hekf", "--summary", "s.json"], d);
    assert!(out.status.success() && out.stderr.is_empty(), "{}", String::from_utf8_lossy(&out.stderr));
}

/// A record of a PRBS of 8 V (`simulate --amplitude 8`, ramped by the default slew limit) identified with the
/// paper's Q2, made for 1 V: the EKFs' parameters wander twice as far (the board's console notes it at `excite`;
/// `tests/instrument.rs` measures it). `identify` notes it per window with the strength it sees (the pre-filtered
/// power against the 1 V PRBS's over a period of it: 45.5-46.0 here) and the `q` for it; with that `q`, without an
/// EKF, or at 1 V, not.
#[test]
fn a_strong_input_with_the_papers_q_is_noted_with_the_q_for_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let args = ["simulate", "--scenario", "prbs", "--duration", "8", "--amplitude", "8", "--out", "strong.csv"];
    let out = nanopos_sim(&args, d);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let notes = identify_notes(d, "strong.csv");
    let mut advice = Vec::new();
    for w in ["3:4", "7:8"] {
        let line = line_from(&notes, &format!("note: window {w}: the input reaches the estimators "));
        let strength: f64 = line.split(' ').nth(8).unwrap().parse().unwrap();
        assert!((40.0..55.0).contains(&strength), "{line}");
        assert!(line.contains("the EKFs' Q, the paper's Q2, was made"), "{line}");
        let q = &line[line.find("q = [").unwrap() + 4..line.find("] (Q2's").unwrap() + 1];
        assert!(q.starts_with("[1e-12, 1e-6, 3."), "{q}");
        advice.push(q.to_string());
    }
    std::fs::write(d.join("q.toml"), format!("[ekf]\nq = {}\n", advice[0])).unwrap();
    let quiet = |args: &[&str]| {
        let out = nanopos_sim(&[&["identify", "--summary", "s.json"], args].concat(), d);
        let stderr = String::from_utf8(out.stderr).unwrap();
        assert!(out.status.success() && !stderr.contains("reaches the estimators"), "{args:?}: {stderr}");
    };
    quiet(&["--input", "strong.csv", "--tuning", "q.toml"]);
    quiet(&["--input", "strong.csv", "--estimators", "rls,arx"]);
    simulate_prbs(d, "8");
    quiet(&["--input", "run.csv"]);
    // At the board console's edge, 2 V, noted for a PRBS and a multisine; a PRBS of 1.8 V is not.
    for (scenario, amplitude, noted) in [("prbs", "2", true), ("multisine", "2", true), ("prbs", "1.8", false)] {
        let args = ["simulate", "--scenario", scenario, "--duration", "8", "--amplitude", amplitude, "--out", "e.csv"];
        assert!(nanopos_sim(&args, d).status.success());
        let notes = identify_notes(d, "e.csv");
        let lines = notes.lines().filter(|l| l.contains(": the input reaches the estimators ")).count();
        assert_eq!(lines, if noted { 2 } else { 0 }, "{scenario} of {amplitude} V: {notes}");
    }
}

/// A reading millions of times the stage's (`y` in pm where um is read): the EKFs reset on innovations beyond a metre,
/// and the hybrid one's means can make a model that runs away in the validation. Its note said "NaN times worse ...
/// (validation RMSE NaN nm ...)"; now that the validation is not finite. Which scale and which window run away moves
/// with any change to how the EKFs start or reset (at 1e6, the first window until the EKFs took their states from
/// their first sample, then the second, then neither once they took the variance of one measurement with them), so
/// three scales are read: the note must come for one of them, and no NaN for any.
#[test]
fn a_validation_that_runs_away_is_named_as_such() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut named = false;
    for scale in [1e6, 3e6, 6e6] {
        let stderr = notes_with_y(d, "pm.csv", |y| format!("{:?}", y.parse::<f64>().unwrap() * scale));
        let runaway = stderr.lines().any(|l| {
            l.contains("note: hekf's model does not fit window ") && l.contains(" at all: its validation is not finite")
        });
        named |= runaway;
        eprintln!("y times {scale:e}: {}", if runaway { "runs away" } else { "no runaway" });
        assert!(!stderr.contains("NaN"), "{stderr}");
    }
    assert!(named, "at none of the scales did the hybrid EKF's validation run away");
}

/// A reading 50 um off the stage's response (the probe's zero; the stage at a position): model (1) has no constant,
/// so every validation RMSE, the truth's too, was about 50 000 nm, the estimators' within 0.01 % of each other, and
/// the RLS's misfit (not converged in 8 s: 100 times the EKFs' 4.8 nm) went unnoted. Now a note gives the offset and
/// the RMSE about it, and the estimators are compared about it: the misfit is noted as on the record without it.
#[test]
fn an_offset_of_the_reading_is_noted_and_the_estimators_compared_about_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let stderr = notes_with_y(d, "offset.csv", |y| format!("{:?}", y.parse::<f64>().unwrap() + 50.0));
    for w in ["3:4", "7:8"] {
        let offset = format!("note: window {w}: the reading sits ");
        assert!(stderr.contains(&offset), "{stderr}");
        assert!(stderr.contains(&format!("note: rls's model fits window {w} ")), "{stderr}");
    }
    let summary = std::fs::read_to_string(d.join("s.json")).unwrap();
    let rmse = number_after(&summary, "rmse_nm");
    assert!((rmse / 5e4 - 1.0).abs() < 1e-3, "the summary's RMSE is the SPEC's, offset included: {rmse}");
    // Without the offset: the same misfits, no offset note.
    let stderr = identify_notes(d, "run.csv");
    assert!(stderr.contains("note: rls's model fits window 3:4 ") && !stderr.contains("sits"), "{stderr}");
}

/// The plot of a record without excitation: every estimator held at the initial parameters, -38 % in `b0` against
/// the truth, beyond the +-20 % the relative panels show. Their range was then empty, and drawing panicked (exit
/// code 101, no file).
#[test]
fn the_plot_of_estimates_held_far_from_the_truth_is_drawn() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_prbs(d, "4");
    rewrite_column(d, "no_input.csv", 1, |_| "0".to_string());
    let out = nanopos_sim(&["identify", "--input", "no_input.csv", "--summary", "s.json", "--plot", "p.svg"], d);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let svg = std::fs::read_to_string(d.join("p.svg")).unwrap();
    assert!(svg.starts_with("<svg") && svg.contains("b0 (um/s^2 V): error against the truth, %"));
}

/// The plot is SVG: a `--plot` named for another image format is refused before the run (a `fig.png` held SVG text
/// no PNG viewer opens); `.SVG` and a name without an extension are taken.
#[test]
fn a_plot_named_for_another_format_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_prbs(d, "1");
    let out = nanopos_sim(&["identify", "--input", "run.csv", "--plot", "fig.png"], d);
    let stderr = String::from_utf8_lossy(&out.stderr);
    let want =
        "nanopos-sim: --plot fig.png: the plot is SVG: name it .svg (an image viewer would not open SVG text in \
                a .png file; a browser opens the .svg, and e.g. `rsvg-convert fig.svg -o fig.png` converts it)";
    assert_eq!((out.status.code(), stderr.trim_end()), (Some(2), want));
    assert!(out.stdout.is_empty() && !d.join("fig.png").exists());
    for name in ["fig.SVG", "fig"] {
        let out = nanopos_sim(&["identify", "--input", "run.csv", "--summary", "s.json", "--plot", name], d);
        assert!(out.status.success(), "{name}: {}", String::from_utf8_lossy(&out.stderr));
        assert!(std::fs::read_to_string(d.join(name)).unwrap().starts_with("<svg"), "{name}");
    }
}

/// A record no stage could produce (an unstable plant, `a0 = -1e4`, under a PRBS: the reading grows to 1e21 um in
/// 0.5 s) drives estimates where the derived quantities have no value (the hybrid EKF's `a0 < 0`: no `f0`): the
/// summary says `null`, and stays JSON (it wrote `NaN`). (The record this test used, the probe pinned at 1e30 um,
/// now resets the EKFs on every sample, their innovation beyond a metre.)
#[test]
fn a_diverged_estimate_is_null_in_the_summary() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut next = nanopos_id::xorshift64(0x9E37_79B9_7F4A_7C15);
    let mut csv = String::from("t,u,y\n");
    let (a0, b0, h) = (-1e4, 1e6, 1e-6);
    let (mut x, mut v) = (0.0f64, 0.0f64);
    for k in 0..5_000 {
        let u = if next() & 1 == 0 { 1.0 } else { -1.0 };
        csv += &format!("{},{u},{x:?}\n", k as f64 * 1e-4);
        for _ in 0..100 {
            let acc = -a0 * x + b0 * u;
            x += h * v + 0.5 * h * h * acc;
            v += h * acc;
        }
    }
    std::fs::write(d.join("unstable.csv"), csv).unwrap();
    let out = nanopos_sim(&["identify", "--input", "unstable.csv", "--summary", "sum.json"], d);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let sum = std::fs::read_to_string(d.join("sum.json")).unwrap();
    assert!(sum.contains("\"f0_hz\": null"), "the case this test is for: {sum}");
    for word in ["NaN", "nan", "inf"] {
        assert!(!sum.contains(word), "{word} in {sum}");
    }
}

/// A disconnected probe's record: the board's PRBS as the command, a reading of noise alone (3.3 nm RMS, the
/// simulated board's floor). The best model's response to the input is a small part of the reading, and a note says
/// so per window; the simulated stage's own record gets none (its best model's response is the reading's).
#[test]
fn identify_notes_a_reading_that_does_not_follow_the_input() {
    let dir = tempfile::tempdir().unwrap();
    simulate_prbs(dir.path(), "3");
    let out = nanopos_sim(&["identify", "--input", "run.csv", "--window", "2:3"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(
        !String::from_utf8_lossy(&out.stderr).contains("barely follows"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = std::fs::read_to_string(dir.path().join("run.csv")).unwrap();
    let mut noise = hal_sim::noise::NormalStream::new(7);
    let mut dead = String::from("t,u,y\n");
    for line in text.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        dead += &format!("{},{},{:?}\n", f[0], f[1], 3.3e-3 * noise.next_normal());
    }
    std::fs::write(dir.path().join("dead.csv"), dead).unwrap();
    let out = nanopos_sim(&["identify", "--input", "dead.csv", "--window", "1:2", "--window", "2:3"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stderr = String::from_utf8(out.stderr).unwrap();
    for w in ["1:2", "2:3"] {
        let note = format!("nanopos-sim: note: window {w}: the best model (");
        let line = stderr.lines().find(|l| l.starts_with(&note) && l.contains("barely follows the input"));
        assert!(
            line.is_some_and(
                |l| l.ends_with("Is the probe connected and seeing the stage, and the input large enough?")
            ),
            "{w}: {stderr}"
        );
    }
}

#[test]
fn validation_rmse_on_noise_only_data_is_the_noise() {
    // u = 0 and y = white noise of 2 nm RMS: every model predicts 0, so the RMSE is the noise's RMS.
    let dir = tempfile::tempdir().unwrap();
    let mut text = String::from("t,u,y\n");
    let mut state = 12345u64;
    let mut sum2 = 0.0;
    let n = 30_000;
    let mut ys = Vec::new();
    for k in 0..n {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let y = ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2e-3 * 12f64.sqrt();
        ys.push(y);
        text += &format!("{},0,{y:?}\n", k as f64 * 1e-4);
    }
    for y in &ys[20_000..] {
        sum2 += y * y;
    }
    let rms_nm = 1e3 * (sum2 / 10_000.0).sqrt();
    std::fs::write(dir.path().join("noise.csv"), text).unwrap();
    let out = nanopos_sim(&["identify", "--input", "noise.csv", "--estimators", "hekf", "--window", "2:3"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let json = String::from_utf8(out.stdout).unwrap();
    let at = json.find("\"rmse_nm\": ").unwrap() + 11;
    let rmse: f64 = json[at..].split(['}', ',']).next().unwrap().trim().parse().unwrap();
    assert!((rmse / rms_nm - 1.0).abs() < 1e-9, "{rmse} vs {rms_nm}");
}

#[test]
fn bad_identify_inputs_fail_with_one_line_and_leave_no_files() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // 100 rows of zeros every `dt` s, the times to `decimals` places.
    let zeros = |name: &str, dt: f64, decimals: usize| {
        let rows: String = (0..100).map(|k| format!("{:.*},0,0\n", decimals, k as f64 * dt)).collect();
        std::fs::write(d.join(name), format!("t,u,y\n{rows}")).unwrap();
    };
    zeros("ok.csv", 1e-4, 4);
    std::fs::write(d.join("no_t.csv"), "u,y\n0,0\n").unwrap();
    // `t` in ms.
    zeros("ms.csv", 0.1, 1);
    std::fs::write(d.join("late.csv"), "t,u,y\n1e300,0,0\n1.0000000000000001e300,0,0\n").unwrap();
    // A pre-filter the RLS's RK4 follows at the board's 10 kHz (|lambda T| = 0.75) but not at this record's 2.5 kHz.
    zeros("slow.csv", 4e-4, 4);
    // Sampled at 1 kHz: fast enough for the pre-filter's band, not for the board's 1 kHz filters' replicas.
    zeros("khz.csv", 1e-3, 3);
    // Saved as UTF-16 (little-endian, with its byte-order mark).
    let utf16: Vec<u8> =
        [0xFF, 0xFE].into_iter().chain("t,u,y\n0,0,0\n".encode_utf16().flat_map(u16::to_le_bytes)).collect();
    std::fs::write(d.join("utf16.csv"), utf16).unwrap();
    std::fs::write(d.join("semicolons.csv"), "t;u;y\n0;0;0\n0,0001;0;0\n").unwrap();
    zeros("hz500.csv", 2e-3, 3);
    std::fs::write(d.join("fast_band.toml"), "prefilter = [100, 1200, 0.1]\n").unwrap();
    std::fs::write(d.join("above_nyquist.toml"), "prefilter = [100, 6000, 0.1]\n").unwrap();
    std::fs::write(d.join("tiny.toml"), "initial = [1e-160, 70, 6e6]\n").unwrap();
    std::fs::write(d.join("near_dc.toml"), "prefilter = [100, 1e-6, 0.1]\n").unwrap();
    std::fs::write(d.join("fast_rls.toml"), "[rls]\ngamma = 15000\n").unwrap();
    let cases: &[(&[&str], &str)] = &[
        // (The whole line: the hint of the next case is for `-` alone.)
        (&["identify", "--input", "missing.csv"], "nanopos-sim: missing.csv: cannot open: No such file or directory\n"),
        (&["identify", "--input", "-"], "-: cannot open: No such file or directory (standard input is /dev/stdin here, not -)"),
        (&["identify", "--input", "no_t.csv"], "no_t.csv:1: no column 't'"),
        (
            &["identify", "--input", "ms.csv"],
            "ms.csv: a sample every 0.1 s (10 Hz) cannot show the pre-filter's band at 450 Hz (--tuning prbs's f_p), \
             which needs more than 900 samples a second: is t in seconds? (a header's `t [ms]` reads it in ms)",
        ),
        // Too slow for the paper's band too (more than 2 f_p = 900 Hz needed): the time is questioned.
        (
            &["identify", "--input", "hz500.csv"],
            "hz500.csv: a sample every 0.002 s (500 Hz) cannot show the pre-filter's band at 450 Hz (--tuning prbs's \
             f_p), which needs more than 900 samples a second: is t in seconds? (a header's `t [ms]` reads it in ms)",
        ),
        // A record fast enough for the paper's band: the tuning's band is the one questioned.
        (
            &["identify", "--input", "ok.csv", "--tuning", "above_nyquist.toml"],
            "ok.csv: a sample every 0.0001 s (10000 Hz) cannot show the pre-filter's band at 6000 Hz (above_nyquist.toml's \
             f_p), which needs more than 12000 samples a second: is above_nyquist.toml's f_p in Hz, and below 5000 Hz?",
        ),
        (
            &["identify", "--input", "khz.csv"],
            "khz.csv: sample period 0.001 s: reconstruction replica: 1000 Hz: frequencies must be positive and below the \
             Nyquist frequency, 500 Hz (identify replicates the board's analog filters, as the board does: they need \
             more than 2000 samples a second)",
        ),
        (&["identify", "--input", "utf16.csv"], "utf16.csv: UTF-16 text (its first bytes say so"),
        (
            &["identify", "--input", "semicolons.csv"],
            "semicolons.csv:1: no column 'u' in the header (found: t;u;y): its fields are separated by ';'; this reads \
             commas, and '.' as the decimal point",
        ),
        (&["identify", "--input", "ok.csv", "--estimators", "rls,kalman"], "unknown estimator 'kalman'"),
        (&["identify", "--input", "ok.csv", "--estimators", "rls,rls"], "'rls' given twice"),
        (&["identify", "--input", "ok.csv", "--tuning", "fast"], "'fast' is neither a preset"),
        (&["identify", "--input", "ok.csv", "--tuning", "missing.toml"], "missing.toml: cannot read"),
        (&["identify", "--input", "ok.csv", "--window", "5:1"], "T0 < T1"),
        (&["identify", "--input", "ok.csv", "--dac-step", "-1"], "'-1': expected the input's step for one DAC code"),
        (&["identify", "--input", "ok.csv", "--dac-step", "nan"], "'nan': expected the input's step"),
        (&["identify", "--input", "ok.csv", "--spike-ratio", "-1"], "'-1': expected the spike gate's ratio, a whole"),
        (&["identify", "--input", "ok.csv", "--spike-ratio", "2.5"], "'2.5': expected the spike gate's ratio"),
        (&["identify", "--input", "ok.csv", "--spike-ratio", "65536"], "'65536': expected the spike gate's ratio"),
        (&["identify", "--input", "ok.csv", "--precision", "f16"], "invalid value 'f16' for '--precision"),
        (&["identify", "--input", "ok.csv", "--window", "50:60", "--out", "e.csv"], "window 50:60 holds no estimate"),
        // 10 ms: its default windows fall between the 100 Hz rows.
        (
            &["identify", "--input", "ok.csv"],
            "ok.csv: default window 0.00375:0.005 holds no estimate (the record covers 0 to 0.0099 s; estimates are \
             taken every 0.01 s from 0.0099 s): give --window T0:T1, or a longer record",
        ),
        // In exponent form, not the 301 digits of `Display`.
        (&["identify", "--input", "late.csv", "--out", "e.csv"], "late.csv:3: time 1e300 does not advance from 1e300"),
        (&["identify", "--input", "ok.csv", "--window", "1e-300:1e-299"], "window 1e-300:1e-299 holds no estimate"),
        (
            &["identify", "--input", "slow.csv", "--tuning", "fast_band.toml"],
            "fast_band.toml: at the sample period of slow.csv (0.0004 s), in f64: the continuous-time RLS steps its \
             pre-filter by RK4",
        ),
        // Each value in range; `q_b0 / b0^2` is not a number in f64.
        (&["identify", "--input", "ok.csv", "--tuning", "tiny.toml"], "tiny.toml: at the sample period of ok.csv"),
        (&["identify", "--input", "ok.csv", "--tuning", "near_dc.toml"], "this pre-filter is too slow"),
        (
            &["identify", "--input", "ok.csv", "--tuning", "fast_rls.toml"],
            "fast_rls.toml: [rls] gamma = 15000: above 0 and at most 10000 /s",
        ),
    ];
    for (args, mention) in cases {
        let out = nanopos_sim(args, d);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
        assert_eq!(stderr.trim_end().lines().count(), 1, "{args:?}: {stderr:?}");
        // One line of words, not a number written out in 300 digits.
        assert!(stderr.len() < 280, "{args:?}: {stderr:?}");
        assert!(stderr.contains(mention), "{args:?}: {stderr:?}");
        assert!(!d.join("e.csv").exists(), "no partial output");
    }
}

/// No output replaces an input (the record, the tuning file), however the path is spelled (another directory's `..`,
/// a hard or a symbolic link), nor another output: refused before anything is read, the files as they were. An output
/// that cannot be made is said before the record is read (not after the run).
#[test]
fn an_output_never_replaces_an_input_or_another_output() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    simulate_prbs(d, "0.5");
    std::fs::rename(d.join("run.csv"), d.join("prbs.csv")).unwrap();
    let record = std::fs::read(d.join("prbs.csv")).unwrap();
    std::fs::write(d.join("t.toml"), "[ekf]\nr = 1.5e-6\n").unwrap();
    std::fs::create_dir(d.join("sub")).unwrap();
    std::fs::hard_link(d.join("prbs.csv"), d.join("hard.csv")).unwrap();
    #[cfg(unix)]
    std::os::unix::fs::symlink("prbs.csv", d.join("soft.csv")).unwrap();
    let same = "writing it would replace the input; choose another name";
    let own = "each output needs a file of its own";
    let mut cases: Vec<(&[&str], String)> = vec![
        (&["--out", "prbs.csv"], format!("--out prbs.csv: the same file as --input prbs.csv: {same}")),
        (
            &["--summary", "sub/../prbs.csv"],
            format!("--summary sub/../prbs.csv: the same file as --input prbs.csv: {same}"),
        ),
        (
            &["--tuning", "t.toml", "--summary", "./t.toml"],
            format!("--summary ./t.toml: the same file as --tuning t.toml: {same}"),
        ),
        (&["--out", "e.csv", "--summary", "e.csv"], format!("--summary e.csv: the same file as --out e.csv: {own}")),
        (
            &["--out", "e.csv", "--summary", "s.json", "--plot", "sub/../e.csv"],
            format!("--plot sub/../e.csv: the same file as --out e.csv: {own}"),
        ),
        (&["--health", "prbs.csv"], format!("--health prbs.csv: the same file as --input prbs.csv: {same}")),
        (&["--out", "e.csv", "--health", "e.csv"], format!("--health e.csv: the same file as --out e.csv: {own}")),
    ];
    // A hard link and a symbolic link: the same file by its device and inode on Unix (Windows tells files by their
    // canonical paths, which a hard link does not share).
    if cfg!(unix) {
        cases.push((&["--plot", "hard.csv"], format!("--plot hard.csv: the same file as --input prbs.csv: {same}")));
        cases.push((&["--out", "soft.csv"], format!("--out soft.csv: the same file as --input prbs.csv: {same}")));
    }
    for (extra, mention) in &cases {
        let mut args = vec!["identify", "--input", "prbs.csv"];
        args.extend_from_slice(extra);
        let out = nanopos_sim(&args, d);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!((out.status.code(), stderr.trim_end()), (Some(2), format!("nanopos-sim: {mention}").as_str()));
        assert_eq!(std::fs::read(d.join("prbs.csv")).unwrap(), record, "{args:?}");
        assert_eq!(std::fs::read_to_string(d.join("t.toml")).unwrap(), "[ekf]\nr = 1.5e-6\n");
        for name in ["e.csv", "s.json"] {
            assert!(!d.join(name).exists(), "{args:?}: {name}");
        }
    }
    // A device named twice is a stream written twice, not one file replacing another: no conflict.
    if cfg!(unix) {
        let out = nanopos_sim(&["identify", "--input", "prbs.csv", "--out", "/dev/null", "--summary", "/dev/null"], d);
        assert_eq!(out.status.code(), Some(0), "{}", String::from_utf8_lossy(&out.stderr));
    }
    // The output's directory is missing and the record is bad at its end: the output is what is said.
    let mut bad = record.clone();
    bad.extend_from_slice(b"x,0,0\n");
    std::fs::write(d.join("bad.csv"), bad).unwrap();
    let out = nanopos_sim(&["identify", "--input", "bad.csv", "--out", "none/e.csv"], d);
    assert_eq!(
        String::from_utf8_lossy(&out.stderr).trim_end(),
        "nanopos-sim: none/e.csv: cannot create: No such file or directory"
    );
    let mut names: Vec<_> =
        std::fs::read_dir(d).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
    names.sort();
    let mut want = vec!["bad.csv", "hard.csv", "prbs.csv", "sub", "t.toml"];
    if cfg!(unix) {
        want.push("soft.csv");
    }
    want.sort();
    assert_eq!(names, want, "no partial file left");
}

/// The part of a summary's JSON text from `"name": {` on (the first such: a window's, or the estimator's or the
/// truth's within a window's part).
fn part<'a>(json: &'a str, name: &str) -> &'a str {
    json.split_once(&format!("\"{name}\": {{")).unwrap_or_else(|| panic!("no {name}: {json}")).1
}

/// `paper`'s PRBS run is `simulate`'s record identified with the PRBS tuning: over 8 s, so that `paper` feeds its
/// identifications more than one block of the simulation (65 536 rows), its summary is `identify`'s byte for byte; and
/// its table's errors and RMSE, f64 and f32, are those of `identify`'s summaries (no test had read the table's
/// figures, nor crossed a block: cargo-mutants' changes to both passed).
#[test]
fn papers_prbs_run_is_identify_on_simulates_record_and_its_table_the_summaries() {
    let dir = tempfile::tempdir().unwrap();
    let out = nanopos_sim(&["paper", "--duration", "8", "--out-dir", "res"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let table = String::from_utf8(out.stdout).unwrap();
    simulate_prbs(dir.path(), "8");
    let mut rows = 0;
    for prec in ["f64", "f32"] {
        let summary = format!("{prec}.json");
        let args = ["identify", "--input", "run.csv", "--tuning", "prbs", "--precision", prec, "--summary", &summary];
        let out = nanopos_sim(&args, dir.path());
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let json = std::fs::read_to_string(dir.path().join(&summary)).unwrap();
        if prec == "f64" {
            assert_eq!(json, std::fs::read_to_string(dir.path().join("res/prbs-summary.json")).unwrap());
        }
        for row in table.lines().filter(|l| l.starts_with(&format!("prbs      {prec} "))) {
            let cells: Vec<&str> = row.split_whitespace().collect();
            let (name, t0) = (cells[2], cells[3].split('-').next().unwrap().parse::<f64>().unwrap());
            let window = json.split("{\"t0\": ").find(|w| w.starts_with(&format!("{t0:?},"))).expect("window");
            let truth = part(window, "truth");
            let (figures, rmse) = if name == "truth" { (truth, cells[4]) } else { (part(window, name), cells[7]) };
            assert_eq!(rmse, format!("{:.2}", number_after(figures, "rmse_nm")), "{row}");
            if name != "truth" {
                for (cell, key) in cells[4..7].iter().zip(["a0", "a1", "b0"]) {
                    let error = 100.0 * (number_after(figures, key) / number_after(truth, key) - 1.0);
                    assert_eq!(*cell, format!("{error:+.3}%"), "{key}: {row}");
                }
            }
            rows += 1;
        }
    }
    assert_eq!(rows, 20, "{table}");
}

#[test]
fn paper_prints_the_table_for_both_inputs_and_writes_the_summaries() {
    let dir = tempfile::tempdir().unwrap();
    let out = nanopos_sim(&["paper", "--duration", "4", "--out-dir", "res"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let table = String::from_utf8(out.stdout).unwrap();
    // Header, then 2 inputs x 2 precisions x (the truth and 4 estimators) x 2 windows.
    assert_eq!(table.lines().count(), 1 + 40, "{table}");
    for word in ["prbs", "triangle", "f32", "f64", "truth", "rls", "ekf", "hekf", "arx", "RMSE"] {
        assert!(table.contains(word), "{word}");
    }
    // The windows as they are, 1.5-2 s and 3.5-4 s (they were printed rounded, as 2-2 and 4-4).
    assert!(table.lines().nth(1).unwrap().starts_with("prbs      f64  truth       1.5-2   "), "{table}");
    assert!(table.lines().nth(2).unwrap().starts_with("prbs      f64  truth       3.5-4   "), "{table}");
    for f in ["prbs-summary.json", "triangle-summary.json"] {
        assert!(dir.path().join("res").join(f).exists(), "{f}");
    }
    // Relock and settle times after the change at 2 s, on the rows of the window after it only: the EKFs back
    // within 1 % of the truth in 0.05-0.06 s with PRBS (within 3 % of their last window's means in 0.02 s); the RLS
    // and the ARX, not converged in 4 s, never, though they settle on their own means (1.3-1.4 s); on the triangle
    // in 4 s no estimator relocks.
    for row in table.lines().skip(1) {
        let cells: Vec<&str> = row.split_whitespace().collect();
        let (input, estimator, after) = (cells[0], cells[2], cells[3] == "3.5-4");
        if estimator == "truth" || !after {
            assert_eq!(cells.len(), if estimator == "truth" { 5 } else { 8 }, "no times: {row}");
            continue;
        }
        let (relock, settle) = (cells[cells.len() - 2], cells[cells.len() - 1]);
        let seconds = |s: &str| s.parse::<f64>().unwrap_or_else(|_| panic!("{row}"));
        assert!((0.0..1.5).contains(&seconds(settle)) && seconds(settle) > 0.0, "{row}");
        match (input, estimator) {
            ("prbs", "ekf" | "hekf") => {
                assert!([relock, settle].iter().all(|&t| seconds(t) > 0.0 && seconds(t) < 0.5), "{row}")
            }
            _ => assert_eq!(relock, "never", "{row}"),
        }
    }
    let bad = nanopos_sim(&["paper", "--duration", "1"], dir.path());
    assert_eq!(bad.status.code(), Some(2));
    // A file where the directory should be: said at once, before the run.
    let file = dir.path().join("res").join("prbs-summary.json");
    let bad = nanopos_sim(&["paper", "--out-dir", file.to_str().unwrap()], dir.path());
    let stderr = String::from_utf8(bad.stderr).unwrap();
    assert_eq!(bad.status.code(), Some(2));
    assert_eq!(stderr, format!("nanopos-sim: --out-dir {}: not a directory\n", file.display()));
}
