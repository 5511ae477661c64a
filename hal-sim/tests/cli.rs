//! `nanopos-sim simulate` as a user runs it: the file it writes, determinism, and every kind of bad input.

#[cfg(target_os = "linux")]
use std::os::unix::fs::FileTypeExt;
use std::path::Path;
use std::process::{Command, Output};

fn nanopos_sim(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_nanopos-sim")).args(args).current_dir(dir).output().expect("run nanopos-sim")
}

fn assert_clean_failure(out: &Output, must_mention: &str) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "exit code; stderr: {stderr}");
    assert_eq!(stderr.trim_end().lines().count(), 1, "one line expected, got: {stderr:?}");
    assert!(stderr.contains(must_mention), "{stderr:?} should mention {must_mention:?}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(out.stdout.is_empty());
}

fn no_stray_files(dir: &Path) {
    let names: Vec<_> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert!(names.is_empty(), "left behind: {names:?}");
}

#[test]
fn simulate_writes_the_documented_columns_with_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let out = nanopos_sim(&["simulate", "--scenario", "prbs", "--duration", "0.01", "--out", "a.csv"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = std::fs::read_to_string(dir.path().join("a.csv")).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines[0], "t,u,y,a0,a1,b0");
    assert_eq!(lines.len(), 1 + 100);
    // Payload on for the first half (paper Table I), off after.
    assert!(lines[1].starts_with("0.0000,") && lines[1].ends_with(",7060000,77.6,808000"), "{}", lines[1]);
    assert!(lines[51].starts_with("0.0050,") && lines[51].ends_with(",9210000,86.8,1070000"), "{}", lines[51]);
    // The DAC is loaded by the sample timer: the first command acts one sample later, at mid-scale (0 V) before.
    assert!(lines[1].starts_with("0.0000,0.0,"), "{}", lines[1]);
    for line in &lines[2..] {
        let v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        assert_eq!(v.len(), 6);
        // PRBS of 1 V through a 12-bit DAC over +-10 V: +-1 V to within half a code (2.4 mV).
        assert!((v[1].abs() - 1.0).abs() < 0.0025, "{line}");
    }
}

/// The rows of `simulate --scenario prbs --duration DURATION` with the flags `extra`, written to `name` in `dir`.
fn simulated_rows(dir: &Path, duration: &str, extra: &[&str], name: &str) -> Vec<Vec<f64>> {
    let mut args = vec!["simulate", "--scenario", "prbs", "--duration", duration, "--out", name];
    args.extend_from_slice(extra);
    let out = nanopos_sim(&args, dir);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = std::fs::read_to_string(dir.join(name)).unwrap();
    text.lines().skip(1).map(|l| l.split(',').map(|x| x.parse().unwrap()).collect()).collect()
}

/// `simulate` says what its file holds that was not asked for: a fault the firmware's pipeline latched, which stopped
/// the excitation (mains pickup of 49 um on the probe's 50 um range), and an excitation too small to move the DAC.
#[test]
fn simulate_notes_a_fault_and_an_excitation_the_dac_cannot_show() {
    let dir = tempfile::tempdir().unwrap();
    let run = |extra: &[&str], name: &str| {
        let mut args = vec!["simulate", "--scenario", "prbs", "--duration", "1", "--out", name];
        args.extend_from_slice(extra);
        let out = nanopos_sim(&args, dir.path());
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let text = std::fs::read_to_string(dir.path().join(name)).unwrap();
        let u: Vec<f64> = text.lines().skip(1).map(|l| l.split(',').nth(1).unwrap().parse().unwrap()).collect();
        (String::from_utf8_lossy(&out.stderr).into_owned(), u)
    };
    let (stderr, u) = run(&["--hum", "50:49000"], "hum.csv");
    let note = "nanopos-sim: note: the firmware's pipeline latched a fault (over_range) at t = ";
    let at = stderr.find(note).unwrap_or_else(|| panic!("{stderr}")) + note.len();
    let (t, rest) = stderr[at..].split_once(" s (line ").unwrap();
    let line: usize = rest.split_once(' ').unwrap().0.parse().unwrap();
    assert!(
        rest.contains(
            "it stopped the excitation there, as the board's does until `start`: u is the safe value from \
                       the next line on"
        ),
        "{stderr}"
    );
    // Line 1 is the header: row `line - 2` is the fault's, and its time is the note's.
    let row = line - 2;
    assert_eq!(t, format!("{}.{:04}", row / 10_000, row % 10_000));
    assert!(u[..=row].iter().any(|&v| v != 0.0) && u[row + 1..].iter().all(|&v| v == 0.0), "row {row}");
    assert!(row > 1000 && row + 1000 < u.len(), "within the run, not at its ends: row {row}");

    let (stderr, u) = run(&["--amplitude", "0.002"], "small.csv");
    let note = "nanopos-sim: note: u never moved from 0 V: the excitation's 0.002 V is under half the DAC's step of \
                0.0048828125 V, to which the command is rounded (the board's `excite` says so too)";
    assert!(stderr.contains(note) && u.iter().all(|&v| v == 0.0), "{stderr}");
    // One code moves it, and nothing is noted.
    let (stderr, u) = run(&["--amplitude", "0.003"], "code.csv");
    assert!(!stderr.contains("note") && u.iter().any(|&v| v != 0.0), "{stderr}");
    let (stderr, _) = run(&["--amplitude", "0"], "zero.csv");
    assert!(!stderr.contains("note"), "{stderr}");
    // Both, when a fault latches after the first sample under an excitation that never moved the DAC (the hum alone
    // reaches the range here, 0.5 s in).
    let (stderr, _) = run(&["--amplitude", "0.002", "--hum", "50:49900"], "both.csv");
    assert!(stderr.contains("latched a fault (over_range)") && stderr.contains(note), "{stderr}");
}

/// The shortest run: two samples, the payload change at the second.
#[test]
fn simulate_writes_a_run_of_two_samples() {
    let dir = tempfile::tempdir().unwrap();
    let rows = simulated_rows(dir.path(), "0.0002", &[], "two.csv");
    assert_eq!(rows.len(), 2);
    assert_eq!((rows[0][0], rows[1][0]), (0.0, 1e-4));
    assert!(rows[0][3] < rows[1][3], "a0 rises when the payload comes off: {rows:?}");
}

/// `--hysteresis` and `--creep` change the stage, not the command: the same `t` and `u` columns, another `y`.
#[test]
fn simulate_adds_the_piezos_hysteresis_and_creep_on_request() {
    let dir = tempfile::tempdir().unwrap();
    let columns = |extra: &[&str], name: &str| {
        let rows = simulated_rows(dir.path(), "0.5", extra, name);
        let column = |i: usize| rows.iter().map(|r| r[i]).collect::<Vec<f64>>();
        (column(1), column(2))
    };
    let (u, y) = columns(&[], "plain.csv");
    for (flag, name) in [("--hysteresis", "h.csv"), ("--creep", "c.csv")] {
        let (u_with, y_with) = columns(&[flag], name);
        assert_eq!(u_with, u, "{flag}: the command is the same");
        let most = y.iter().zip(&y_with).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        println!("{flag}: the reading differs by up to {:.2} nm over 0.5 s of PRBS", most * 1e3);
        assert!(most > 1e-4, "{flag}: {most} um");
    }
}

/// `--gain-drift PCT_PER_MIN` drifts the piezo's gain, and the truth's `b0` with it, from the start: the same
/// command, another reading, `a0` and `a1` as they were; 600 % per minute over 0.01 s is 0.1 %.
#[test]
fn simulate_drifts_the_gain_and_the_truth_on_request() {
    let dir = tempfile::tempdir().unwrap();
    let rows = |extra: &[&str], name: &str| simulated_rows(dir.path(), "0.01", extra, name);
    let (still, drifting) = (rows(&[], "still.csv"), rows(&["--gain-drift", "600"], "drift.csv"));
    for (k, (s, d)) in still.iter().zip(&drifting).enumerate() {
        assert_eq!((d[0], d[1], d[3], d[4]), (s[0], s[1], s[3], s[4]), "row {k}: t, u, a0, a1");
        // 600 % per minute is 0.1 per second: the gain at sample k is 1 + 1e-5 k.
        let gain = 1.0 + 1e-5 * k as f64;
        assert!((d[5] / (s[5] * gain) - 1.0).abs() < 1e-12, "row {k}: b0 {} against {}", d[5], s[5]);
    }
    assert!(still.iter().zip(&drifting).skip(20).any(|(s, d)| s[2] != d[2]), "the reading moved");
    assert_eq!(rows(&["--gain-drift", "0"], "zero.csv"), still, "no drift: the same file");
}

/// `--noise NM` sets the probe's noise and `--noise-tail DOF` makes it Student's t: the same command and truth; the
/// reading moved by the noise asked for (the difference to a run without noise, whose ADC noise is the same: its own
/// stream of the seed), at the RMS asked for, and with the tails asked for. Over 10 s (100 000 readings) of 10 nm:
/// beyond 4 times the RMS a Gaussian has 6 readings to expect, Student's t with 5 degrees about 360.
#[test]
fn simulate_sets_the_probes_noise_and_its_tails_on_request() {
    let dir = tempfile::tempdir().unwrap();
    let rows = |extra: &[&str], name: &str| simulated_rows(dir.path(), "10", extra, name);
    let silent = rows(&["--noise", "0"], "silent.csv");
    for (extra, name) in [(&["--noise", "10"][..], "gauss.csv"), (&["--noise", "10", "--noise-tail", "5"], "t5.csv")] {
        let noisy = rows(extra, name);
        assert_eq!(noisy.len(), silent.len());
        let mut d = Vec::with_capacity(noisy.len());
        for (k, (s, n)) in silent.iter().zip(&noisy).enumerate() {
            assert_eq!((n[0], n[1], n[3], n[4], n[5]), (s[0], s[1], s[3], s[4], s[5]), "{name} row {k}: t, u, truth");
            d.push(1e3 * (n[2] - s[2]));
        }
        let rms = (d.iter().map(|d| d * d).sum::<f64>() / d.len() as f64).sqrt();
        let beyond = d.iter().filter(|d| d.abs() > 40.0).count();
        println!("{extra:?}: the reading moved by {rms:.3} nm RMS, {beyond} readings beyond 40 nm");
        // The standard error of the RMS: 0.2 % (Gaussian), 0.5 % (t5, kurtosis 9); the ADC's 1.5 nm code rounds
        // each run's reading, 0.6 nm RMS more on their difference in quadrature (+0.2 %).
        assert!((rms / 10.0 - 1.0).abs() < 0.03, "{name}: {rms} nm RMS");
        match extra.len() {
            2 => assert!(beyond < 30, "{name}: {beyond} beyond 4 RMS"),
            _ => assert!((200..600).contains(&beyond), "{name}: {beyond} beyond 4 RMS"),
        }
    }
    assert_eq!(rows(&["--noise", "1.25"], "paper.csv"), rows(&[], "default.csv"), "the paper's noise is the default");
}

/// `--hum HZ:NM` adds mains pickup to the reading: the same command and truth, the reading moved by the tone (to the
/// ADC's 1.5 nm code and the noise: the two runs share the noise's seed).
#[test]
fn simulate_adds_mains_hum_on_request() {
    let dir = tempfile::tempdir().unwrap();
    let rows = |extra: &[&str], name: &str| simulated_rows(dir.path(), "0.1", extra, name);
    let (quiet, hum) = (rows(&[], "quiet.csv"), rows(&["--hum", "50:100", "--hum", "150:20"], "hum.csv"));
    for (k, (q, h)) in quiet.iter().zip(&hum).enumerate() {
        assert_eq!((h[0], h[1], h[3], h[4], h[5]), (q[0], q[1], q[3], q[4], q[5]), "row {k}: t, u and the truth");
        let t = h[0];
        let tone =
            0.1 * (2.0 * std::f64::consts::PI * 50.0 * t).sin() + 0.02 * (2.0 * std::f64::consts::PI * 150.0 * t).sin();
        assert!((h[2] - q[2] - tone).abs() < 2e-3, "row {k}: {} against {} + {tone}", h[2], q[2]);
    }
    assert_eq!(rows(&["--hum", "50:0"], "zero.csv"), quiet, "no amplitude: the same file");
}

/// `--amplitude` scales the excitation as `excite` would, through the firmware's default output limits: a PRBS of
/// 0.5 V is +-0.5 V (to half a DAC code); one of 8 V reaches +-8 V, its steps of 16 V ramped by the slew limit's 2.5 V
/// a sample (41 V^2 of power over this second, not 64); the time and the truth are the same.
#[test]
fn simulate_drives_the_excitation_at_another_amplitude_on_request() {
    let dir = tempfile::tempdir().unwrap();
    let rows = |extra: &[&str], name: &str| simulated_rows(dir.path(), "1", extra, name);
    let (paper, half, strong) =
        (rows(&[], "one.csv"), rows(&["--amplitude", "0.5"], "half.csv"), rows(&["--amplitude", "8"], "eight.csv"));
    for ((p, h), s) in paper.iter().zip(&half).zip(&strong) {
        assert_eq!((h[0], h[3], h[4], h[5]), (p[0], p[3], p[4], p[5]));
        assert_eq!((s[0], s[3], s[4], s[5]), (p[0], p[3], p[4], p[5]));
    }
    for h in &half[1..] {
        assert!((h[1].abs() - 0.5).abs() < 0.0025, "{h:?}");
    }
    let u: Vec<f64> = strong.iter().map(|r| r[1]).collect();
    let peak = u.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let mean = u.iter().sum::<f64>() / u.len() as f64;
    let power = u.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / u.len() as f64;
    let largest_step = u.windows(2).map(|w| (w[1] - w[0]).abs()).fold(0.0f64, f64::max);
    assert!((peak - 8.0).abs() < 0.0025 && (30.0..50.0).contains(&power), "peak {peak}, power {power}");
    assert!(largest_step < 2.5 + 0.005, "{largest_step}");
    assert_eq!(rows(&["--amplitude", "1"], "again.csv"), paper, "the default");
}

#[test]
fn simulate_runs_the_boards_multisine_and_identify_finds_it_rich() {
    let dir = tempfile::tempdir().unwrap();
    let out = nanopos_sim(&["simulate", "--scenario", "multisine", "--duration", "4", "--out", "m.csv"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = std::fs::read_to_string(dir.path().join("m.csv")).unwrap();
    let u: Vec<f64> = text.lines().skip(2).map(|l| l.split(',').nth(1).unwrap().parse().unwrap()).collect();
    // The power of a 1 V sine (over whole periods of the 19.35 Hz spacing), the peak under 1.36 V, in DAC steps.
    let rms = (u[..31_000].iter().map(|v| v * v).sum::<f64>() / 31_000.0).sqrt();
    let peak = u.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!((rms - 0.5f64.sqrt()).abs() < 0.003 && peak < 1.36, "RMS {rms}, peak {peak}");
    let args = ["identify", "--input", "m.csv", "--estimators", "ekf,hekf", "--window", "1:2"];
    let out = nanopos_sim(&args, dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let json = String::from_utf8(out.stdout).unwrap();
    assert_eq!(json.matches("\"starved\": 0.0").count(), 2, "{json}");
}

/// A window the record does not wholly cover is still reported (its figures are of the part that is there), with a
/// note naming what the figures are of; a window inside the record, or ending one sample after its last, or starting
/// less than half a sample before its first, has none. A window may start at a negative time (`--window -1:2`, as a
/// record's time may be negative: not taken for an option).
#[test]
fn identify_says_when_a_window_reaches_beyond_the_record() {
    let dir = tempfile::tempdir().unwrap();
    let out = nanopos_sim(&["simulate", "--scenario", "prbs", "--duration", "2", "--out", "r.csv"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let identify = |window: &str| {
        let out =
            nanopos_sim(&["identify", "--input", "r.csv", "--estimators", "hekf", "--window", window], dir.path());
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        // Reported as asked.
        let t1 = window.split(':').nth(1).unwrap();
        assert!(String::from_utf8(out.stdout).unwrap().contains(&format!("\"t1\": {t1}")));
        String::from_utf8(out.stderr).unwrap()
    };
    for inside in ["0:2", "1:1.5", "-0.00004:1"] {
        assert_eq!(identify(inside), "", "{inside}");
    }
    let before =
        "nanopos-sim: note: window -0.0001:1 reaches beyond the record (0 to 1.9999 s): its figures are of 0 to 1 s\n";
    assert_eq!(identify("-0.0001:1"), before);
    let note =
        "nanopos-sim: note: window 1.5:2.0002 reaches beyond the record (0 to 1.9999 s): its figures are of 1.5 \
                to 1.9999 s\n";
    assert_eq!(identify("1.5:2.0002"), note);
    assert!(identify("1.5:30").contains("window 1.5:30 reaches beyond the record (0 to 1.9999 s)"));
    // A window's numbers as the other messages write them: not 1e300 in 301 digits.
    assert!(identify("1.5:1e300").contains("window 1.5:1e300 reaches beyond the record (0 to 1.9999 s)"));
}

/// An output that names a device or a pipe is written to it as a stream, not replaced by a file renamed over it
/// (as root that turned `/dev/stdout` and `/dev/full` into regular files; as anyone else the temporary could not be
/// made in `/dev`); a write that fails, to a file or to standard output, is an error, not output lost with exit 0;
/// and a directory is refused before the run.
#[cfg(target_os = "linux")]
#[test]
fn outputs_to_devices_and_pipes_are_streamed_and_their_errors_reported() {
    use std::process::Stdio;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    assert!(nanopos_sim(&["simulate", "--scenario", "prbs", "--duration", "0.5", "--out", "r.csv"], d)
        .status
        .success());
    let summary = ["identify", "--input", "r.csv", "--estimators", "hekf", "--window", "0.2:0.5"];
    let plain = nanopos_sim(&summary, d);
    assert!(plain.status.success() && plain.stdout.starts_with(b"{\"precision\": \"f64\", \"windows\""));

    // Standard output (a pipe here) through its device name: the same text; the link itself still a link.
    let through = nanopos_sim(&[&summary[..], &["--summary", "/dev/stdout"]].concat(), d);
    assert!(through.status.success(), "{}", String::from_utf8_lossy(&through.stderr));
    assert_eq!(through.stdout, plain.stdout);
    assert!(std::fs::symlink_metadata("/dev/stdout").unwrap().file_type().is_symlink());

    // A named pipe that another program reads: the whole file, as a plain file gets it.
    let fifo = d.join("fifo");
    assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    let reader = std::thread::spawn({
        let fifo = fifo.clone();
        move || std::fs::read(fifo).unwrap()
    });
    let out = nanopos_sim(&["simulate", "--scenario", "prbs", "--duration", "0.5", "--out", "fifo"], d);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // (Before the join: a pipe replaced by a file leaves the reader waiting for ever.)
    assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());
    assert_eq!(reader.join().unwrap(), std::fs::read(d.join("r.csv")).unwrap());

    // A device that takes nothing: an error naming it, for a named output and for standard output alike.
    let full = nanopos_sim(&[&summary[..], &["--summary", "/dev/full"]].concat(), d);
    assert_clean_failure(&full, "/dev/full: cannot write: No space left on device");
    assert!(std::fs::metadata("/dev/full").unwrap().file_type().is_char_device());
    for args in [&summary[..], &["fit", "--input", "r.csv", "--arx", "2,2,1"]] {
        let to_full = std::fs::OpenOptions::new().write(true).open("/dev/full").unwrap();
        let out = Command::new(env!("CARGO_BIN_EXE_nanopos-sim"))
            .args(args)
            .current_dir(d)
            .stdout(Stdio::from(to_full))
            .output()
            .unwrap();
        assert_clean_failure(&out, "standard output: cannot write: No space left on device");
    }

    // `decode --segments` names its files after --out: a device is no name to number.
    std::fs::write(d.join("capture.txt"), with_tuning(&capture(300, 0))).unwrap();
    let out = nanopos_sim(&["decode", "--input", "capture.txt", "--out", "/dev/stdout", "--segments"], d);
    assert_clean_failure(&out, "--out /dev/stdout: not a file name: --segments writes one file per run");
    // Without --segments the samples go to the stream, and the board's tuning nowhere (no /dev/stdout.tuning.toml).
    let out = nanopos_sim(&["decode", "--input", "capture.txt", "--out", "/dev/stdout"], d);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && out.stdout.starts_with(b"t,u,y\n"), "{stderr}");
    let note = "note: --out /dev/stdout is not a file: the board's tuning is not written beside it";
    assert!(stderr.contains(note) && !Path::new("/dev/stdout.tuning.toml").exists(), "{stderr}");
    std::fs::remove_file(d.join("capture.txt")).unwrap();

    // A directory: refused before the run, and nothing left in it.
    std::fs::create_dir(d.join("est")).unwrap();
    let out = nanopos_sim(&[&summary[..], &["--out", "est"]].concat(), d);
    assert_clean_failure(&out, "est: is a directory, not a file name");
    assert_eq!(std::fs::read_dir(d.join("est")).unwrap().count(), 0);
    let names: Vec<_> = std::fs::read_dir(d).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(names.len(), 3, "left behind: {names:?}");
}

/// An output named through a symbolic link replaces the file the link names, and the link stays (renamed over, the
/// link became the new file and the file it named kept the old contents); a link to a file not there yet makes it.
#[cfg(unix)]
#[test]
fn an_output_through_a_symbolic_link_writes_the_file_it_names() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir(d.join("data")).unwrap();
    std::fs::write(d.join("data/run.csv"), "old\n").unwrap();
    std::os::unix::fs::symlink("data/run.csv", d.join("link.csv")).unwrap();
    std::os::unix::fs::symlink("data/new.csv", d.join("dangling.csv")).unwrap();
    for (link, file) in [("link.csv", "data/run.csv"), ("dangling.csv", "data/new.csv")] {
        let out = nanopos_sim(&["simulate", "--scenario", "prbs", "--duration", "0.01", "--out", link], d);
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        assert!(std::fs::symlink_metadata(d.join(link)).unwrap().file_type().is_symlink(), "{link}");
        assert!(std::fs::read_to_string(d.join(file)).unwrap().starts_with("t,u,y,a0,a1,b0\n"), "{file}");
    }
    let mut names: Vec<_> = std::fs::read_dir(d.join("data")).unwrap().map(|e| e.unwrap().file_name()).collect();
    names.sort();
    assert_eq!(names, ["new.csv", "run.csv"], "no temporary left");
}

/// On a terminal, `simulate` and `identify` show how far they are on standard error, a percentage redrawn in place,
/// and clear the line when done; on a pipe (every other test here) they show nothing.
#[cfg(unix)]
#[test]
fn progress_is_shown_on_a_terminal_and_cleared() {
    use std::io::Read;
    let dir = tempfile::tempdir().unwrap();
    let on_a_terminal = |args: &[&str]| {
        let pty = nix::pty::openpty(None, None).expect("a pseudo-terminal");
        let mut command = Command::new(env!("CARGO_BIN_EXE_nanopos-sim"));
        command.args(args).current_dir(dir.path()).stderr(std::process::Stdio::from(pty.slave));
        let mut child = command.spawn().expect("run nanopos-sim");
        drop(command); // the terminal's last other end: its reads end when the program's does
        let (mut master, mut shown, mut buf) = (std::fs::File::from(pty.master), Vec::new(), [0; 4096]);
        loop {
            match master.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => shown.extend_from_slice(&buf[..n]),
                Err(e) if e.raw_os_error() == Some(libc::EIO) => break, // Linux: the other end closed
                Err(e) => panic!("reading the terminal: {e}"),
            }
        }
        assert!(child.wait().unwrap().success(), "{}", String::from_utf8_lossy(&shown));
        String::from_utf8(shown).unwrap()
    };
    let cleared = format!("\r{}\r", " ".repeat(14));
    // 200 000 samples, shown every 65 536.
    let shown = on_a_terminal(&["simulate", "--scenario", "prbs", "--duration", "20", "--out", "run.csv"]);
    assert_eq!(shown, format!("\rsimulate:   0%\rsimulate:  32%\rsimulate:  65%\rsimulate:  98%{cleared}"));
    // Shown per block read (8 MiB: this file's 12 MB in two), cleared before the notes that follow on their own lines.
    let shown = on_a_terminal(&["identify", "--input", "run.csv", "--out", "est.csv"]);
    let (progress, notes) = shown.split_once(&cleared).expect(&shown);
    let percents: Vec<u32> = progress
        .strip_prefix('\r')
        .expect(&shown)
        .split('\r')
        .map(|p| p.strip_prefix("identify: ").and_then(|p| p.strip_suffix('%')).expect(&shown).trim().parse().unwrap())
        .collect();
    assert!(percents.len() >= 2 && percents.windows(2).all(|w| w[0] < w[1]) && percents.ends_with(&[100]), "{shown:?}");
    assert!(notes.lines().all(|l| l.starts_with("nanopos-sim: note: ")), "{shown:?}");
}

#[test]
fn same_seed_gives_the_same_file_and_another_seed_does_not() {
    let dir = tempfile::tempdir().unwrap();
    for (name, seed) in [("a.csv", "5"), ("b.csv", "5"), ("c.csv", "6")] {
        let args = ["simulate", "--scenario", "triangle", "--duration", "0.2", "--seed", seed, "--out", name];
        assert!(nanopos_sim(&args, dir.path()).status.success());
    }
    let read = |n: &str| std::fs::read(dir.path().join(n)).unwrap();
    assert_eq!(read("a.csv"), read("b.csv"));
    assert_ne!(read("a.csv"), read("c.csv"));
}

#[test]
fn bad_arguments_fail_with_one_line_exit_2_and_no_file() {
    let cases: &[(&[&str], &str)] = &[
        (&["simulate", "--scenario", "sawtooth", "--out", "x.csv"], "sawtooth"),
        (&["simulate", "--out", "x.csv"], "--scenario"),
        (&["simulate", "--scenario", "prbs"], "--out"),
        (&["simulate", "--scenario", "prbs", "--duration", "0", "--out", "x.csv"], "--duration 0: must be a positive"),
        (
            &["simulate", "--scenario", "prbs", "--duration", "-3", "--out", "x.csv"],
            "--duration -3: must be a positive",
        ),
        (
            &["simulate", "--scenario", "prbs", "--duration", "NaN", "--out", "x.csv"],
            "--duration NaN: must be a positive",
        ),
        (
            &["simulate", "--scenario", "prbs", "--duration", "inf", "--out", "x.csv"],
            "--duration inf: must be a positive",
        ),
        (&["simulate", "--scenario", "prbs", "--duration", "ten", "--out", "x.csv"], "ten"),
        (
            &["simulate", "--scenario", "prbs", "--duration", "1e9", "--out", "x.csv"],
            "1000000000: longer than the 86400 s",
        ),
        (&["simulate", "--scenario", "prbs", "--duration", "0.00001", "--out", "x.csv"], "two samples"),
        // In exponent form, not 1e-300 with its 300 zeros.
        (&["simulate", "--scenario", "prbs", "--duration", "1e-300", "--out", "x.csv"], "--duration 1e-300: shorter"),
        (&["simulate", "--scenario", "prbs", "--gain-drift", "NaN", "--out", "x.csv"], "--gain-drift NaN: must be"),
        (&["simulate", "--scenario", "prbs", "--gain-drift", "inf", "--out", "x.csv"], "--gain-drift inf: must be"),
        (&["simulate", "--scenario", "prbs", "--gain-drift", "fast", "--out", "x.csv"], "fast"),
        // -50 % per minute: the gain is gone after 120 s, within the default 200 s.
        (
            &["simulate", "--scenario", "prbs", "--gain-drift", "-50", "--out", "x.csv"],
            "--gain-drift -50: the gain would reach zero after 120 s, within the run's 200 s",
        ),
        (&["simulate", "--scenario", "prbs", "--hum", "50", "--out", "x.csv"], "'50': expected HZ:NM"),
        (&["simulate", "--scenario", "prbs", "--hum", "0:20", "--out", "x.csv"], "'0:20': expected HZ:NM"),
        (&["simulate", "--scenario", "prbs", "--hum", "6000:20", "--out", "x.csv"], "Nyquist"),
        (&["simulate", "--scenario", "prbs", "--hum", "5000:20", "--out", "x.csv"], "'5000:20': expected HZ:NM"),
        (&["simulate", "--scenario", "prbs", "--hum", "50:50001", "--out", "x.csv"], "'50:50001': expected HZ:NM"),
        (&["simulate", "--scenario", "prbs", "--hum", "50:-1", "--out", "x.csv"], "'50:-1'"),
        (&["simulate", "--scenario", "prbs", "--hum", "50:NaN", "--out", "x.csv"], "'50:NaN'"),
        (&["simulate", "--scenario", "prbs", "--hum", "-50:1", "--out", "x.csv"], "'-50:1': expected HZ:NM"),
        (
            &["simulate", "--scenario", "prbs", "--hum", "50:1", "--hum", "150:1", "--hum", "250:1", "--out", "x.csv"],
            "--hum: at most 2 tones (3 given)",
        ),
        (&["simulate", "--scenario", "prbs", "--noise", "-1", "--out", "x.csv"], "--noise -1: must be 0 to 50000 nm"),
        (&["simulate", "--scenario", "prbs", "--noise", "NaN", "--out", "x.csv"], "--noise NaN: must be"),
        (&["simulate", "--scenario", "prbs", "--noise", "1e6", "--out", "x.csv"], "--noise 1000000: must be"),
        (&["simulate", "--scenario", "prbs", "--noise", "loud", "--out", "x.csv"], "loud"),
        (
            &["simulate", "--scenario", "prbs", "--noise-tail", "2", "--out", "x.csv"],
            "--noise-tail 2: must be 3 to 100",
        ),
        (&["simulate", "--scenario", "prbs", "--noise-tail", "101", "--out", "x.csv"], "--noise-tail 101: must be"),
        (&["simulate", "--scenario", "prbs", "--noise-tail", "3.5", "--out", "x.csv"], "'3.5'"),
        (&["simulate", "--scenario", "prbs", "--amplitude", "11", "--out", "x.csv"], "--amplitude 11: must be 0 to 10"),
        (&["simulate", "--scenario", "prbs", "--amplitude", "-1", "--out", "x.csv"], "--amplitude -1: must be"),
        (&["simulate", "--scenario", "prbs", "--amplitude", "NaN", "--out", "x.csv"], "--amplitude NaN: must be"),
        (&["simulate", "--scenario", "prbs", "--amplitude", "big", "--out", "x.csv"], "big"),
        // A negative number is the option's value, refused as such (not "unexpected argument '-1'").
        (&["simulate", "--scenario", "prbs", "--seed", "-1", "--out", "x.csv"], "invalid value '-1' for '--seed"),
        (
            &["simulate", "--scenario", "prbs", "--noise-tail", "-3", "--out", "x.csv"],
            "invalid value '-3' for '--noise-tail",
        ),
        (&["simulate", "--scenario", "prbs", "--seed", "x", "--out", "x.csv"], "--seed"),
        (&["identify", "--input", "r.csv", "--window", "100:75"], "'100:75': expected T0:T1 in seconds with T0 < T1"),
        (&["identify", "--input", "r.csv", "--window", "75-100"], "'75-100': expected T0:T1"),
        (&["identify", "--input", "r.csv", "--window", "1:inf"], "'1:inf': expected T0:T1"),
        (&["identify", "--input", "r.csv", "--window", "-2:-3"], "'-2:-3': expected T0:T1"),
        (&["simulate", "--scenario", "prbs", "--out", "no/such/dir/x.csv"], "no/such/dir/x.csv"),
        (&["simulate", "--scenario", "prbs", "--out", "."], "."),
        (&["simulate", "--scenario", "prbs", "--bogus", "--out", "x.csv"], "--bogus"),
        (&["frobnicate"], "frobnicate"),
        (&[], "no command given"),
        // The limit itself is taken (a day: here it stops at its first write, to a device that is always full).
        (
            &["simulate", "--scenario", "prbs", "--duration", "86400", "--out", "/dev/full"],
            "/dev/full: cannot write: No space left on device",
        ),
    ];
    for (args, mention) in cases {
        let dir = tempfile::tempdir().unwrap();
        let out = nanopos_sim(args, dir.path());
        assert_clean_failure(&out, mention);
        no_stray_files(dir.path());
    }
}

#[test]
fn a_failed_run_leaves_an_existing_output_untouched() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("keep.csv"), "precious").unwrap();
    let out = nanopos_sim(&["simulate", "--scenario", "prbs", "--duration", "-1", "--out", "keep.csv"], dir.path());
    assert_clean_failure(&out, "--duration");
    assert_eq!(std::fs::read_to_string(dir.path().join("keep.csv")).unwrap(), "precious");
}

#[test]
fn help_exits_zero() {
    let dir = tempfile::tempdir().unwrap();
    let out = nanopos_sim(&["simulate", "--help"], dir.path());
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout).contains("--scenario"));
}

/// The board's recording header.
const HEADER: nanopos_id::record::RecordHeader = nanopos_id::record::RecordHeader::EXAMPLE;

/// A capture as the board's serial link delivers it: replies around a recording of `n` samples.
fn capture(n: usize, first: u64) -> String {
    capture_with(n, first, HEADER)
}

/// [`capture`] with another header.
fn capture_with(n: usize, first: u64, header: nanopos_id::record::RecordHeader) -> String {
    use nanopos_id::record::{encode_frame, write_checked_line, RawSample, END_TAG, FRAME_MAX_BYTES, FRAME_SAMPLES};
    let mut text = String::from("ok status samples=12\n");
    let mut h = nanopos_id::text::TextBuf::<256>::default();
    header.write(&mut h).unwrap();
    text.push_str(h.as_str());
    text.push_str("ok record burst 100\n");
    let samples: Vec<RawSample> =
        (0..n).map(|k| RawSample { u_code: 2048 + (k % 3) as u16, y_code: 32768 + k as u16 }).collect();
    let mut buf = [0u8; FRAME_MAX_BYTES];
    for (i, chunk) in samples.chunks(FRAME_SAMPLES).enumerate() {
        let len = encode_frame(first + (i * FRAME_SAMPLES) as u64, chunk, &mut buf);
        text.push_str(std::str::from_utf8(&buf[..len]).unwrap());
    }
    let mut end = nanopos_id::text::TextBuf::<80>::default();
    write_checked_line(&mut end, format_args!("{END_TAG} samples={n} overflow=0")).unwrap();
    text.push_str(end.as_str());
    text.push_str("ok status samples=99\n");
    text
}

/// `text` (a [`capture`] from board sample 0) with the tuning lines of the PRBS preset after `record burst`'s reply,
/// as the firmware sends them (a capture without them is a firmware's before them).
fn with_tuning(text: &str) -> String {
    let mut lines = String::new();
    let tuning = nanopos_id::estimators::Tuning::of(nanopos_id::control::TuningPreset::Prbs);
    nanopos_id::record::write_tuning_lines(&mut lines, 0, &tuning).unwrap();
    text.replacen("ok record burst 100\n", &format!("ok record burst 100\n{lines}"), 1)
}

/// `text` as a firmware before the header's and the end line's CRC wrote it (format v1).
fn v1(text: &str) -> String {
    text.lines()
        .map(|l| match l.rsplit_once(" crc=") {
            Some((body, _)) if l.starts_with("# nanopos-record") => body.replace("record v2", "record v1"),
            _ => l.to_string(),
        })
        .collect::<Vec<_>>()
        .join("\n")
        + "\n"
}

#[test]
fn decode_turns_a_capture_into_the_csv_identify_reads() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("cap.txt"), capture(1000, 5000)).unwrap();
    let out = nanopos_sim(&["decode", "--input", "cap.txt", "--out", "run.csv"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8_lossy(&out.stderr).contains("1000 samples (0.1 s at 10000 Hz) from board sample 5000"));
    let text = std::fs::read_to_string(dir.path().join("run.csv")).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 1001);
    assert_eq!(lines[0], "t,u,y");
    // Code 2048 is 0 V; code 32768 + 1 is 100/65536 um.
    assert_eq!(lines[1], "0,0,0");
    assert_eq!(lines[2], "0.0001,0.0048828125,0.00152587890625");
    // `identify` reads it.
    let out = nanopos_sim(&["identify", "--input", "run.csv", "--estimators", "hekf", "--window", "0:0.1"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

/// A board whose DAC steps by another size than the firmware's default (its front end changed in `board.rs`): `decode`
/// says what `--dac-step` to give `identify`, which cannot tell from the CSV; with the default it says nothing.
#[test]
fn decode_says_when_identify_needs_the_boards_dac_step() {
    let dir = tempfile::tempdir().unwrap();
    let default = capture(100, 0);
    let other = capture_with(100, 0, nanopos_id::record::RecordHeader { u_v_per_code: 20.0 / 2048.0, ..HEADER });
    for (text, note) in [(default, None), (other, Some("note: this board's DAC steps by 0.009765625 V, not the 0.0048828125 V identify assumes: give it --dac-step 0.009765625"))] {
        std::fs::write(dir.path().join("cap.txt"), text).unwrap();
        let out = nanopos_sim(&["decode", "--input", "cap.txt", "--out", "run.csv"], dir.path());
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{stderr}");
        assert_eq!(stderr.lines().find(|l| l.contains("DAC steps")).map(|l| l.trim_start_matches("nanopos-sim: ")), note, "{stderr}");
    }
}

/// `decode` does not write over its capture: not as `--out`, not as one of the segments' files.
#[test]
fn decode_never_replaces_its_capture() {
    let dir = tempfile::tempdir().unwrap();
    let text = capture(1000, 0);
    for (name, args) in
        [("cap.txt", &["--out", "cap.txt"][..]), ("run-1.csv", &["--out", "./run.csv", "--segments"][..])]
    {
        std::fs::write(dir.path().join(name), &text).unwrap();
        let mut all = vec!["decode", "--input", name];
        all.extend_from_slice(args);
        let out = nanopos_sim(&all, dir.path());
        assert_clean_failure(&out, "writing it would replace the input; choose another name");
        assert_eq!(std::fs::read_to_string(dir.path().join(name)).unwrap(), text);
        std::fs::remove_file(dir.path().join(name)).unwrap();
        no_stray_files(dir.path());
    }
}

#[test]
fn decode_segments_keeps_every_intact_run_of_a_damaged_capture() {
    // Ten frames of 48 samples from line 4 on. Frame 2 is lost (frame 3 on line 6), frame 6 damaged (line 9),
    // frame 8 repeated (lines 11 and 12).
    let good = capture(480, 7000);
    let lines: Vec<String> = good.lines().map(str::to_string).collect();
    let frame = |i: usize| lines[3 + i].clone();
    let mut damaged = lines.clone();
    damaged[3 + 6] = damaged[3 + 6].replacen('A', "B", 1);
    let mut text: Vec<String> = lines[..3].to_vec();
    for i in 0..10 {
        match i {
            2 => {}
            6 => text.push(damaged[3 + 6].clone()),
            8 => text.extend([frame(8), frame(8)]),
            _ => text.push(frame(i)),
        }
    }
    text.extend_from_slice(&lines[13..]);
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("cap.txt"), text.join("\n")).unwrap();

    // Without --segments: refused, with the way out in the message, and nothing written.
    let out = nanopos_sim(&["decode", "--input", "cap.txt", "--out", "run.csv"], dir.path());
    assert_clean_failure(&out, "cap.txt:6: frame starts at sample 7144, expected 7096: 48 samples missing");
    assert!(String::from_utf8_lossy(&out.stderr).contains("decode --segments"));
    assert!(!dir.path().join("run.csv").exists());

    // Files an earlier decode numbered beyond this one's are named, not taken for this capture's.
    for stale in ["run-4.csv", "run-5.csv", "run-7.csv"] {
        std::fs::write(dir.path().join(stale), "t,u,y\n").unwrap();
    }
    let out = nanopos_sim(&["decode", "--input", "cap.txt", "--out", "run.csv", "--segments"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    for stale in ["run-4.csv", "run-5.csv"] {
        let note = format!("note: {stale} is from an earlier decode, not this capture (its runs went to 3 files)");
        assert!(stderr.contains(&note), "{stderr}");
        assert_eq!(std::fs::read_to_string(dir.path().join(stale)).unwrap(), "t,u,y\n");
    }
    // Only those: not this decode's own files, nor one after a number that is not there (run-7.csv after no run-6).
    assert_eq!(stderr.matches("is from an earlier decode").count(), 2, "{stderr}");
    for msg in [
        "skipped: cap.txt:6: frame starts at sample 7144, expected 7096: 48 samples missing",
        "skipped: cap.txt:9: checksum mismatch",
        "skipped: cap.txt:10: frame starts at sample 7336, expected 7288: 48 samples missing",
        "skipped: cap.txt:12: frame starts at sample 7384, before the expected 7432",
        "96 samples (0.0096 s at 10000 Hz) from board sample 7000 (t = 0 s) written to run-1.csv",
        "144 samples (0.0144 s at 10000 Hz) from board sample 7144 (t = 0.0144 s) written to run-2.csv",
        "144 samples (0.0144 s at 10000 Hz) from board sample 7336 (t = 0.0336 s) written to run-3.csv",
    ] {
        assert!(stderr.contains(msg), "{stderr} should mention {msg:?}");
    }
    assert!(!dir.path().join("run.csv").exists());
    // Each file holds its samples at their time since the recording's start, with the values of the intact capture.
    let whole = nanopos_sim(&["decode", "--input", "good.txt", "--out", "whole.csv"], {
        std::fs::write(dir.path().join("good.txt"), &good).unwrap();
        dir.path()
    });
    assert!(whole.status.success());
    let whole = std::fs::read_to_string(dir.path().join("whole.csv")).unwrap();
    let whole: Vec<&str> = whole.lines().skip(1).collect();
    for (file, first, n) in [("run-1.csv", 0, 96), ("run-2.csv", 144, 144), ("run-3.csv", 336, 144)] {
        let text = std::fs::read_to_string(dir.path().join(file)).unwrap();
        let rows: Vec<&str> = text.lines().collect();
        assert_eq!(rows[0], "t,u,y");
        assert_eq!(&rows[1..], &whole[first..first + n], "{file}");
    }
    // identify reads a segment.
    let out = nanopos_sim(
        &["identify", "--input", "run-2.csv", "--estimators", "hekf", "--window", "0.014:0.0287"],
        dir.path(),
    );
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

/// A capture from a firmware before the header's CRC (format v1) still decodes, with a note that its scalings are
/// unchecked; a header of no known version is refused but counted; with `--segments`, frames lost at the recording's
/// end (which no frame's index shows; the end line's count does) are reported and the rest written.
#[test]
fn decode_reads_the_unchecked_v1_format_and_reports_frames_lost_at_the_end() {
    let dir = tempfile::tempdir().unwrap();
    let good = capture(200, 0);
    std::fs::write(dir.path().join("old.txt"), v1(&good)).unwrap();
    let out = nanopos_sim(&["decode", "--input", "old.txt", "--out", "old.csv"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("note: the recording's header has no checksum (format v1"), "{stderr}");
    std::fs::write(dir.path().join("new.txt"), with_tuning(&good)).unwrap();
    let out = nanopos_sim(&["decode", "--input", "new.txt", "--out", "new.csv"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && !stderr.contains("note"), "{stderr}");
    // The board's tuning beside it, which identify reads.
    let tuning =
        "the board's tuning at the recording's start written to new.tuning.toml: replay with identify --tuning \
                  new.tuning.toml; give it back to a board that reset with commands --tuning new.tuning.toml";
    assert!(stderr.contains(tuning), "{stderr}");
    let out = nanopos_sim(&["commands", "--tuning", "new.tuning.toml"], dir.path());
    assert!(out.status.success() && out.stderr.is_empty(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8(out.stdout).unwrap().starts_with("tuning prbs\ntune initial "));
    let out = nanopos_sim(
        &["identify", "--input", "new.csv", "--tuning", "new.tuning.toml", "--estimators", "arx"],
        dir.path(),
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && !stderr.contains("beside the input"), "{stderr}");
    // Without --tuning, a note says what is beside it.
    let out = nanopos_sim(&["identify", "--input", "new.csv", "--estimators", "arx"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    let note = "note: new.tuning.toml beside the input holds the board's tuning (decode wrote it); without --tuning \
                new.tuning.toml the replay runs the prbs preset";
    assert!(out.status.success() && stderr.contains(note), "{stderr}");
    let read = |f: &str| std::fs::read_to_string(dir.path().join(f)).unwrap();
    assert_eq!(read("old.csv"), read("new.csv"));

    let lines: Vec<&str> = good.lines().collect();
    // A header whose version was damaged (or is a later firmware's) is refused, and still counted, so that
    // `--recording 2` is the second recording.
    let two = capture(100, 0).replacen("record v2", "record w2", 1) + &capture(100, 5000);
    std::fs::write(dir.path().join("two.txt"), &two).unwrap();
    let out = nanopos_sim(&["decode", "--input", "two.txt", "--out", "two.csv"], dir.path());
    assert_clean_failure(
        &out,
        "two.txt:2: '# nanopos-record w2 rate_hz=10000 delay=... (138 characters)': a recording header of no version",
    );
    let out = nanopos_sim(&["decode", "--input", "two.txt", "--out", "two.csv", "--recording", "2"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success() && stderr.contains("100 samples (0.01 s at 10000 Hz) from board sample 5000"),
        "{stderr}"
    );
    // A capture of two recordings: decoding the first says that there is a second (it went unmentioned).
    std::fs::write(dir.path().join("pair.txt"), capture(100, 0) + &capture(100, 5000)).unwrap();
    let out = nanopos_sim(&["decode", "--input", "pair.txt", "--out", "pair.csv"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    let note = "note: pair.txt: the capture holds 2 recordings; this is recording 1 (--recording 2 decodes the next)";
    assert!(out.status.success() && stderr.contains(note), "{stderr}");
    let out = nanopos_sim(&["decode", "--input", "pair.txt", "--out", "pair2.csv", "--recording", "2"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && !stderr.contains("recordings"), "{stderr}");

    let cut = lines[..lines.len() - 3].iter().chain(&lines[lines.len() - 2..]).copied().collect::<Vec<_>>();
    std::fs::write(dir.path().join("cut.txt"), cut.join("\n")).unwrap();
    let out = nanopos_sim(&["decode", "--input", "cut.txt", "--out", "cut.csv", "--segments"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("skipped: cut.txt: the end line counts 200 samples recorded, the frames span 192"));
    assert!(stderr.contains("192 samples (0.0192 s at 10000 Hz) from board sample 0 (t = 0 s) written to cut-1.csv"));
}

/// A capture an editor saved again (a byte-order mark before its first line, CRLF line ends) decodes as it came.
#[test]
fn decode_reads_a_capture_an_editor_saved() {
    let dir = tempfile::tempdir().unwrap();
    // From the header on, as a capture started before `record on` has it.
    let good = capture(200, 0);
    let good = &good[good.find('#').unwrap()..];
    let saved = format!("\u{feff}{}", good.replace('\n', "\r\n"));
    for (name, text) in [("good", good), ("saved", saved.as_str())] {
        std::fs::write(dir.path().join(format!("{name}.txt")), text).unwrap();
        let out =
            nanopos_sim(&["decode", "--input", &format!("{name}.txt"), "--out", &format!("{name}.csv")], dir.path());
        assert!(out.status.success(), "{name}: {}", String::from_utf8_lossy(&out.stderr));
    }
    let read = |f: &str| std::fs::read_to_string(dir.path().join(f)).unwrap();
    assert_eq!(read("saved.csv"), read("good.csv"));
    assert_eq!(read("good.csv").lines().count(), 201);
}

#[test]
fn decode_refuses_damage_and_gaps_naming_the_line() {
    let good = capture(200, 0);
    let lines: Vec<&str> = good.lines().collect();
    // Line 4 is the first frame: one character changed.
    let mut damaged: Vec<String> = lines.iter().map(|l| l.to_string()).collect();
    damaged[3] = damaged[3].replacen('A', "B", 1);
    // A frame lost in the capture.
    let gap: Vec<&str> = lines.iter().enumerate().filter(|(i, _)| *i != 4).map(|(_, l)| *l).collect();
    // Every frame changed in one character (its index's last digit): with `--segments` nothing is left.
    let every_frame_damaged: Vec<String> = lines
        .iter()
        .map(|l| match l.strip_prefix('R') {
            Some(rest) => format!("R{}{}", if rest.starts_with('0') { '1' } else { '0' }, &rest[1..]),
            None => l.to_string(),
        })
        .collect();
    // The capture without the recording's frames, its end line kept.
    let no_frames: Vec<&str> = lines.iter().filter(|l| !l.starts_with('R')).copied().collect();
    // Every line behind a terminal's timestamp.
    let stamped: Vec<String> = lines.iter().map(|l| format!("[12:00:00.123] {l}")).collect();
    let cases: [(String, &[&str], &str); 22] = [
        (damaged.join("\n"), &[], "cap.txt:4: checksum mismatch"),
        (gap.join("\n"), &[], "cap.txt:5: frame starts at sample 96, expected 48: 48 samples missing"),
        ("ok status\n".into(), &[], "no recording in the capture"),
        (
            stamped.join("\n"),
            &[],
            "cap.txt:2: the recording header comes after '[12:00:00.123] ': the capture's lines carry something before \
             the board's (a terminal's timestamps?), which decode does not read: capture without it",
        ),
        (good.clone(), &["--recording", "2"], "recording 2 asked for, the capture holds 1"),
        // Not taken for the first.
        (good.clone(), &["--recording", "0"], "--recording 0: recordings are counted from 1 (the capture's first is 1)"),
        // A header changed in transfer: its CRC no longer matches.
        (good.replace("rate_hz=10000", "rate_hz=10800"), &[], "cap.txt:2: recording header damaged in transfer"),
        // In the format without the CRC (v1), a header is read as it is: what cannot be read is named.
        (v1(&good).replace("rate_hz=10000", "rate_hz=fast"), &[], "cap.txt:2: rate_hz=fast: not a number"),
        // Not quietly cast to a u8 (300 would have been 255, 2.5 would have been 2).
        (
            v1(&good).replace("delay=1", "delay=300"),
            &[],
            "cap.txt:2: delay=300: not a whole number of samples from 0 to 255",
        ),
        (v1(&good).replace("delay=1", "delay=2.5"), &[], "cap.txt:2: delay=2.5: not a whole number"),
        (v1(&good).replace("delay=1", "delay=1e300"), &[], "cap.txt:2: delay=1e300: not a whole number"),
        // A rate or a scaling no sample could be read with (a negative scaling is an inverting front end: read).
        (v1(&good).replace("rate_hz=10000", "rate_hz=0"), &[], "cap.txt:2: rate_hz=0: a recording header needs a"),
        (v1(&good).replace("rate_hz=10000", "rate_hz=-10000"), &[], "cap.txt:2: rate_hz=-10000: a recording"),
        (
            v1(&good).replace("u_v_per_code=0.0048828125", "u_v_per_code=0"),
            &[],
            "cap.txt:2: u_v_per_code=0: a recording header needs a positive rate and scalings other than 0",
        ),
        (
            v1(&good).replace("y_um_per_code=0.00152587890625", "y_um_per_code=0"),
            &[],
            "cap.txt:2: y_um_per_code=0: a recording header needs",
        ),
        // The end line changed in transfer, and frames lost at the recording's end, which no frame's index shows.
        (
            good.replace("samples=200 overflow=0", "samples=200 overflow=1"),
            &[],
            "cap.txt:9: the recording's end line damaged",
        ),
        (
            lines[..lines.len() - 3].iter().chain(&lines[lines.len() - 2..]).copied().collect::<Vec<_>>().join("\n"),
            &[],
            "cap.txt: the end line counts 200 samples recorded, the frames span 192 (board samples 0 to 192): frames \
             lost at the recording's start or end",
        ),
        // No frame at all: the capture stopped after the header, the recording stopped before its first sample, the
        // frames lost, or all damaged; and one sample, no run to write.
        (lines[..3].join("\n"), &[], "cap.txt: recording 1 has no frame: the capture ends at line 3, before its first"),
        (capture(0, 0), &[], "cap.txt: recording 1 is empty: its end line counts 0 samples"),
        (no_frames.join("\n"), &[], "cap.txt: recording 1 has no frame before its end line"),
        (
            every_frame_damaged.join("\n"),
            &["--segments"],
            "cap.txt: recording 1 has no intact frame: 5 lines of it damaged in transfer, the first: cap.txt:4: \
             checksum mismatch",
        ),
        (capture(1, 0), &[], "cap.txt: recording 1 holds no run of 2 or more samples"),
    ];
    for (text, extra, msg) in cases {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("cap.txt"), &text).unwrap();
        let mut args = vec!["decode", "--input", "cap.txt", "--out", "run.csv"];
        args.extend_from_slice(extra);
        let out = nanopos_sim(&args, dir.path());
        assert_clean_failure(&out, msg);
        std::fs::remove_file(dir.path().join("cap.txt")).unwrap();
        no_stray_files(dir.path());
    }
    // Saved as UTF-16 (little-endian, with its byte-order mark), as a redirection in Windows PowerShell writes it.
    let dir = tempfile::tempdir().unwrap();
    let utf16: Vec<u8> = [0xFF, 0xFE].into_iter().chain(good.encode_utf16().flat_map(u16::to_le_bytes)).collect();
    std::fs::write(dir.path().join("cap.txt"), utf16).unwrap();
    let out = nanopos_sim(&["decode", "--input", "cap.txt", "--out", "run.csv"], dir.path());
    assert_clean_failure(&out, "cap.txt: UTF-16 text (its first bytes say so");
}

/// Ctrl-C (SIGINT) in the middle of a long `simulate`: exit code 130, and neither the output nor its temporary
/// (`.NAME.partial-PID`, which the interruption used to leave behind, tens of MB of it by then) is left.
#[test]
fn ctrl_c_leaves_no_partial_output() {
    let dir = tempfile::tempdir().unwrap();
    let child = Command::new(env!("CARGO_BIN_EXE_nanopos-sim"))
        .args(["simulate", "--scenario", "prbs", "--duration", "3600", "--out", "run.csv"])
        .current_dir(dir.path())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run nanopos-sim simulate");
    let temp = dir.path().join(format!(".run.csv.partial-{}", child.id()));
    // Interrupted once it has written a few MB (its handler is installed before any output is made).
    let started = std::time::Instant::now();
    while std::fs::metadata(&temp).map_or(0, |m| m.len()) < 4 << 20 {
        assert!(started.elapsed() < std::time::Duration::from_secs(60), "no output after a minute");
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    let kill = Command::new("kill").args(["-INT", &child.id().to_string()]).status().expect("run kill");
    assert!(kill.success());
    let out = child.wait_with_output().expect("simulate ends");
    assert_eq!(out.status.code(), Some(130), "{}", String::from_utf8_lossy(&out.stderr));
    no_stray_files(dir.path());
}

/// `commands`: a preset or a tuning file to the board's console lines on standard output; values too long for a
/// console line in full are shortened, with a note; a file the board could not run, or not a tuning, is refused.
#[test]
fn commands_writes_the_console_lines_of_a_tuning_or_says_why_not() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = nanopos_sim(&["commands", "--tuning", "prbs"], d);
    assert!(out.status.success() && out.stderr.is_empty(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(
        String::from_utf8(out.stdout).unwrap(),
        "tuning prbs\ntune initial 5e5 70 6e6\ntune prefilter 100 450 0.1\ntune spike_ratio 32\n"
    );
    // The triangle's preset, named or a file's, is given as that preset (not as the PRBS one with its Q changed).
    std::fs::write(d.join("tri.toml"), "preset = \"triangle\"\n[arx]\nlambda = 0.999\n").unwrap();
    for (tuning, more) in [("triangle", ""), ("tri.toml", "tune arx lambda 0.999\n")] {
        let out = nanopos_sim(&["commands", "--tuning", tuning], d);
        assert!(out.status.success() && out.stderr.is_empty(), "{}", String::from_utf8_lossy(&out.stderr));
        assert_eq!(
            String::from_utf8(out.stdout).unwrap(),
            "tuning triangle\ntune initial 5e5 70 6e6\ntune prefilter 100 450 0.1\ntune spike_ratio 32\n".to_string()
                + more
        );
    }
    // Five values of 17 significant digits: 11 + 5 * 23 bytes, beyond the console's 96.
    let long = "[ekf]\nq = [1.0000000000000002e-12, 1.0000000000000002e-6, 1500000000.0000002, 0.25000000000000006, \
                500000000.00000006]\n";
    std::fs::write(d.join("long.toml"), long).unwrap();
    let out = nanopos_sim(&["commands", "--tuning", "long.toml"], d);
    let (stdout, stderr) = (String::from_utf8(out.stdout).unwrap(), String::from_utf8(out.stderr).unwrap());
    assert!(out.status.success(), "{stderr}");
    let q = stdout.lines().find(|l| l.starts_with("tune ekf q ")).unwrap();
    assert!(q.len() <= 96, "{q}");
    let note = "nanopos-sim: note: [ekf] q's values written to 16 significant digits (each within 5e-16 of the file's";
    assert!(stderr.starts_with(note), "{stderr}");
    let file =
        [1.0000000000000002e-12, 1.0000000000000002e-6, 1500000000.0000002, 0.25000000000000006, 5.000000000000001e8];
    for (word, want) in q.split(' ').skip(3).zip(file) {
        let got: f64 = word.parse().unwrap();
        assert!((got / want - 1.0).abs() <= 5e-16, "{q}");
    }
    for (file, text, says) in [
        ("r.toml", "[ekf]\nr = 1e-45\n", "r.toml: at the board's 10000 Hz, in f32: "),
        ("key.toml", "[ekf]\nkappa = 1\n", "key.toml:2: unknown field `kappa`"),
        ("pre.toml", "preset = \"sine\"\n", "pre.toml: preset 'sine' unknown"),
        // A tuning the board can run whose lines, in the console's order, pass through one it cannot: `q` at the top of
        // f32 with its own `p0` (`tune ekf q` sets `p0` to 10 Q first, beyond f32).
        (
            "q.toml",
            "[ekf]\nq = [3.4e38, 1e-6, 1.5e9, 0.25, 5e8]\np0 = [1e-11, 1e-5, 1.5e10, 2.5, 5e9]\n",
            "q.toml: [ekf] q set before the keys after it leaves a tuning the board cannot run, and the console refuses \
             such a line (`tune ekf q` also sets p0 to 10 Q): this order of the lines cannot give the board this tuning",
        ),
    ] {
        std::fs::write(d.join(file), text).unwrap();
        assert_clean_failure(&nanopos_sim(&["commands", "--tuning", file], d), says);
    }
    // Not text (it said "cannot read: stream did not contain valid UTF-8", as if the file could not be read).
    std::fs::write(d.join("bin.toml"), b"[ekf]\nr = 1.5e-6\nq = [1e-12\xff]\n").unwrap();
    assert_clean_failure(
        &nanopos_sim(&["commands", "--tuning", "bin.toml"], d),
        "bin.toml:3: not UTF-8 text (byte 0xff)",
    );
}

/// `text` with one to four random edits, as a noisy link or a hand edit leaves a file: a byte removed, changed, a run
/// of up to 200 bytes cut, the rest cut off, or a word inserted (a separator, a line end, `nan`, `1e999`, a header).
fn mutated(text: &str, next: &mut impl FnMut() -> u64) -> Vec<u8> {
    let words: [&[u8]; 14] =
        [b",", b"\n", b"\r\n", b"nan", b"inf", b"-", b"1e999", b"1e-320", b" ", b"\t", b".", b"#", b"\xff", b"t,u,y\n"];
    let mut b = text.as_bytes().to_vec();
    for _ in 0..1 + next() % 4 {
        if b.is_empty() {
            break;
        }
        let at = (next() % b.len() as u64) as usize;
        match next() % 5 {
            0 => drop(b.remove(at)),
            1 => drop(b.splice(at..at, words[(next() % words.len() as u64) as usize].iter().copied())),
            2 => b[at] = (next() & 0x7f) as u8,
            3 => drop(b.drain(at..(at + (next() % 200) as usize).min(b.len()))),
            _ => b.truncate(at),
        }
    }
    b
}

/// `nanopos-sim ARGS` on `input` in a directory of its own: it succeeds, or fails with one line naming what was
/// wrong (exit 2) and leaving no file but the input; never a panic.
fn succeeds_or_fails_cleanly(args: &[&str], input: (&str, &[u8])) -> bool {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(input.0), input.1).unwrap();
    let out = nanopos_sim(args, dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    let text = String::from_utf8_lossy(input.1);
    assert!(!stderr.contains("panicked"), "{args:?} on\n{text}\n{stderr}");
    if !out.status.success() {
        assert_clean_failure(&out, "nanopos-sim: ");
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(left, [input.0], "{args:?}: a failed run leaves only its input; {stderr}");
    }
    out.status.success()
}

/// Records, captures and tuning files with random damage (100 of each): `identify` and `decode` either take them or
/// refuse them with one line and no file; none panics, none leaves a partial output. (None did, over 300 of each;
/// reading their refusals found two that did not say what was wrong: a capture cut after its header was "holds no
/// run of 2 or more samples", now "the capture ends at line 3, before its first" frame; a tuning file with a byte
/// that is not UTF-8 was "cannot read: stream did not contain valid UTF-8", now "not UTF-8 text" with its line.)
#[test]
fn damaged_records_captures_and_tuning_files_are_taken_or_refused_in_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let out = nanopos_sim(&["simulate", "--scenario", "prbs", "--duration", "0.6", "--out", "run.csv"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let run = std::fs::read_to_string(dir.path().join("run.csv")).unwrap();
    let cap = with_tuning(&capture(3000, 0));
    let mut next = nanopos_id::xorshift64(0x2545_F491_4F6C_DD1D);
    let identify = ["identify", "--input", "in.csv", "--summary", "s.json", "--out", "e.csv", "--window", "0.2:0.6"];
    let decode = ["decode", "--input", "cap.txt", "--out", "run.csv"];
    // A tuning file with every key, and the record it is for (`--tuning` is read before the record).
    let tuning = "initial = [500000, 70, 6e6]\nprefilter = [100, 450, 0.1]\nspike_ratio = 32\n\n[rls]\ngamma = 0.25\n\
                  p0 = [1e6, 10, 1e7]\nr0 = 1e9\npe_floor_v2 = 1e-6\n\n[ekf]\nq = [1e-12, 1e-6, 1.5e9, 0.25, 5e8]\n\
                  r = 1.5e-6\nsubsteps = 4\ngate_sigma = 5\ndrift_ratio = 4\npe_floor_v2 = 1e-6\n\n[arx]\n\
                  lambda = 0.9999\nmax_trace = 1e6\npe_floor_v2 = 1e-6\n";
    let record = dir.path().join("run.csv");
    let replay = ["identify", "--input", record.to_str().unwrap(), "--tuning", "t.toml", "--window", "0.2:0.6"];
    let (mut taken, mut decoded, mut tuned) = (0, 0, 0);
    for _ in 0..100 {
        taken += succeeds_or_fails_cleanly(&identify, ("in.csv", &mutated(&run, &mut next))) as usize;
        decoded += succeeds_or_fails_cleanly(&decode, ("cap.txt", &mutated(&cap, &mut next))) as usize;
        tuned += succeeds_or_fails_cleanly(&replay, ("t.toml", &mutated(tuning, &mut next))) as usize;
    }
    println!(
        "identify took {taken} of 100 damaged records, decode {decoded} of 100 damaged captures, identify {tuned} of \
         100 damaged tuning files"
    );
    // Both kinds of outcome were exercised.
    assert!([taken, decoded, tuned].iter().all(|n| (1..100).contains(n)), "{taken} {decoded} {tuned}");
}
