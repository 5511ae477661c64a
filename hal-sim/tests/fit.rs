//! `nanopos-sim fit`: the textbook's numbers through the command line, exact recovery, and every bad input.

use std::path::Path;
use std::process::{Command, Output};

fn nanopos_sim(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_nanopos-sim")).args(args).current_dir(dir).output().expect("run nanopos-sim")
}

const TABLE_13_1: [f64; 21] = [
    0.0, 0.01953, 0.07567, 0.14890, 0.22945, 0.31001, 0.39300, 0.47111, 0.54922, 0.62245, 0.69324, 0.76159, 0.82750,
    0.89096, 0.95199, 1.00812, 1.06427, 1.11553, 1.16435, 1.21561, 1.26199,
];

fn write(dir: &Path, name: &str, text: &str) {
    std::fs::write(dir.join(name), text).unwrap();
}

fn table_csv() -> String {
    let mut s = String::from("k,t,u,y\n");
    for (k, y) in TABLE_13_1.iter().enumerate() {
        s += &format!("{k},{},1,{y}\n", 0.25 * k as f64);
    }
    s
}

/// Pull the numbers out of `{"a": [..], "b": [..], "sse": x, "rows": n}` (`sse` is `null` where it overflows).
fn parse(json: &str) -> (Vec<f64>, Vec<f64>, Option<f64>, u64) {
    let list = |key: &str| -> Vec<f64> {
        let start = json.find(&format!("\"{key}\": [")).unwrap() + key.len() + 5;
        let end = start + json[start..].find(']').unwrap();
        json[start..end].split(',').filter(|s| !s.trim().is_empty()).map(|s| s.trim().parse().unwrap()).collect()
    };
    let scalar = |key: &str| -> &str {
        let start = json.find(&format!("\"{key}\": ")).unwrap() + key.len() + 4;
        let end = start + json[start..].find([',', '}']).unwrap();
        json[start..end].trim()
    };
    let sse = match scalar("sse") {
        "null" => None,
        x => Some(x.parse().unwrap()),
    };
    (list("a"), list("b"), sse, scalar("rows").parse().unwrap())
}

#[test]
fn fit_reproduces_example_13_3_from_a_csv() {
    let dir = tempfile::tempdir().unwrap();
    write(dir.path(), "t.csv", &table_csv());
    let out = nanopos_sim(&["fit", "--input", "t.csv", "--arx", "2,2,1", "--zero-initial"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (a, b, sse, rows) = parse(&String::from_utf8(out.stdout).unwrap());
    let exact = [1.4706942596816603, -0.4908359715216343, 0.01952999999999714, 0.027723581792437734];
    assert!((a[0] - exact[0]).abs() < 1e-10 && (a[1] - exact[1]).abs() < 1e-10);
    assert!((b[0] - exact[2]).abs() < 1e-10 && (b[1] - exact[3]).abs() < 1e-10);
    assert!((sse.unwrap() / 4.596675770259521e-05 - 1.0).abs() < 1e-8);
    // Every sample is a row with --zero-initial: y(0) with an all-zero regressor included.
    assert_eq!(rows, 21);
}

/// `u`, `y` of y(k) = 1.5 y(k-1) - 0.7 y(k-2) + 0.3 u(k-2) + 0.1 u(k-3), driven by a deterministic, rich input, 400
/// samples.
fn noise_free_arx() -> (Vec<f64>, Vec<f64>) {
    let n = 400;
    let u: Vec<f64> = (0..n).map(|k| ((k * 7919) % 13) as f64 / 6.0 - 1.0).collect();
    let mut y = vec![0.0; n];
    for k in 3..n {
        y[k] = 1.5 * y[k - 1] - 0.7 * y[k - 2] + 0.3 * u[k - 2] + 0.1 * u[k - 3];
    }
    (u, y)
}

#[test]
fn fit_recovers_a_noise_free_arx_exactly_with_and_without_weights() {
    let (u, y) = noise_free_arx();
    let n = u.len();
    let dir = tempfile::tempdir().unwrap();
    // Also in units 1e200 times larger: the same coefficients (the fit is scale-free). The rank test once took
    // the columns' norms from a running sum of squares, which overflowed and called every column dependent.
    for (name, scale) in [("arx.csv", 1.0), ("arx_1e200.csv", 1e200)] {
        let mut text = String::from("t,u,y\n");
        for k in 0..n {
            text += &format!("{},{:?},{:?}\n", k as f64 * 1e-4, u[k] * scale, y[k] * scale);
        }
        write(dir.path(), name, &text);
    }
    for (file, extra) in [("arx.csv", &[][..]), ("arx.csv", &["--weight", "0.5,0.97"][..]), ("arx_1e200.csv", &[][..])]
    {
        let mut args = vec!["fit", "--input", file, "--arx", "2,2,2"];
        args.extend_from_slice(extra);
        let out = nanopos_sim(&args, dir.path());
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let (a, b, sse, rows) = parse(&String::from_utf8(out.stdout).unwrap());
        for (got, want) in a.iter().chain(&b).zip([1.5, -0.7, 0.3, 0.1]) {
            assert!((got - want).abs() < 1e-9, "{file} {extra:?}: {got} vs {want}");
        }
        // The residual's square, about 1e400 * 1e-30, is beyond f64: `null`, not a number JSON cannot read, and a
        // note says why (it was `null` without a word).
        let overflow = String::from_utf8_lossy(&out.stderr).contains("note: the residual's sum of squares is beyond");
        match file {
            "arx_1e200.csv" => assert!(sse.is_none() && overflow),
            _ => assert!(sse.unwrap() < 1e-20 && !overflow),
        }
        // Full history: rows from k = max(NA, NK + NB - 1) = 3.
        assert_eq!(rows, n as u64 - 3);
    }
}

/// The noise-free ARX above, read 2 um off (the probe's zero): the model has no constant, and every coefficient came
/// out biased without a word. A note now says that a constant would lower the residual and how far `y` sits off;
/// `--offset` fits the constant `c` too, the coefficients exact again and `c = 2 (1 - a1 - a2)`. The record without
/// the offset gets no note (its residuals are rounding).
#[test]
fn an_offset_of_y_is_noted_and_fitted_with_offset() {
    let (u, y) = noise_free_arx();
    let dir = tempfile::tempdir().unwrap();
    let csv = |offset: f64, scale: f64| {
        let rows = (0..u.len()).map(|k| format!("{},{:?},{:?}\n", k as f64 * 1e-4, u[k], (y[k] + offset) * scale));
        rows.fold(String::from("t,u,y\n"), |a, r| a + &r)
    };
    write(dir.path(), "off.csv", &csv(2.0, 1.0));
    write(dir.path(), "on.csv", &csv(0.0, 1.0));
    // The same in pm read as um (1e-6 as large): the note's test of a residual that is only rounding is to the scale
    // of `y` (cargo-mutants' `a + y^2` for `a y^2` in that scale passed).
    write(dir.path(), "off_small.csv", &csv(2.0, 1e-6));
    write(dir.path(), "on_small.csv", &csv(0.0, 1e-6));
    let fit_orders = |file: &str, offset: bool, orders: &str| {
        let mut args = vec!["fit", "--input", file, "--arx", orders];
        if offset {
            args.push("--offset");
        }
        let out = nanopos_sim(&args, dir.path());
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        (String::from_utf8(out.stdout).unwrap(), String::from_utf8(out.stderr).unwrap())
    };
    let fit = |file: &str, offset: bool| fit_orders(file, offset, "2,2,2");
    // With orders whose sum is not their product, the constant is still the one after the coefficients.
    let (_, stderr) = fit_orders("off.csv", false, "3,2,2");
    assert!(stderr.contains("(c = 0.400, y 2.00 um off): y sits off the model"), "{stderr}");
    let (json, stderr) = fit("off.csv", false);
    assert!(stderr.contains("note: a constant term would lower the fit's residual by "), "{stderr}");
    assert!(stderr.contains(", y 2.00 um off): y sits off the model"), "{stderr}");
    let (a, _, _, _) = parse(&json);
    assert!((a[0] - 1.5).abs() > 1e-3, "biased: {json}");
    let (json, stderr) = fit("off.csv", true);
    assert!(stderr.is_empty(), "{stderr}");
    let (a, b, _, _) = parse(&json);
    for (got, want) in a.iter().chain(&b).zip([1.5, -0.7, 0.3, 0.1]) {
        assert!((got - want).abs() < 1e-9, "{got} vs {want}: {json}");
    }
    let c: f64 = json.split("\"c\": ").nth(1).unwrap().split(',').next().unwrap().parse().unwrap();
    assert!((c - 2.0 * (1.0 - 1.5 + 0.7)).abs() < 1e-9, "{json}");
    let (_, stderr) = fit("on.csv", false);
    assert!(stderr.is_empty(), "{stderr}");
    let (_, stderr) = fit("off_small.csv", false);
    assert!(stderr.contains("note: a constant term would lower the fit's residual by "), "{stderr}");
    let (_, stderr) = fit("on_small.csv", false);
    assert!(stderr.is_empty(), "{stderr}");
}

/// One wild sample (a glitch, or a logger's overflow value) decides a least-squares fit, which weighs each sample by
/// its square: the noise-free ARX above, recovered to 1e-9, is lost with one `y` 10^4 times the record's level. The
/// fit cannot tell; a note on standard error names the sample. The record without it gets none.
#[test]
fn a_wild_sample_is_noted() {
    let (u, y) = noise_free_arx();
    let n = u.len();
    let dir = tempfile::tempdir().unwrap();
    let fit = |glitch: f64| {
        let mut text = String::from("t,u,y\n");
        for k in 0..n {
            let y = if k == 200 { glitch } else { y[k] };
            text += &format!("{},{:?},{y:?}\n", k as f64 * 1e-4, u[k]);
        }
        write(dir.path(), "arx.csv", &text);
        let out = nanopos_sim(&["fit", "--input", "arx.csv", "--arx", "2,2,2"], dir.path());
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let (a, _, _, _) = parse(&String::from_utf8(out.stdout).unwrap());
        (a[0], String::from_utf8(out.stderr).unwrap())
    };
    let (a1, stderr) = fit(y[200]);
    assert!((a1 - 1.5).abs() < 1e-9 && stderr.is_empty(), "{a1} {stderr}");
    let level = y.iter().map(|y| y.abs()).fold(0.0, f64::max);
    let (a1, stderr) = fit(1e4 * level);
    eprintln!("{a1} {stderr}");
    assert!((a1 - 1.5).abs() > 0.1, "the case this test is for: {a1}");
    assert!(
        stderr.starts_with("nanopos-sim: note: y reaches ") && stderr.contains(" at sample 200 (the first is 0), "),
        "{stderr}"
    );
}

#[test]
fn bad_inputs_fail_with_one_line_naming_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write(d, "t.csv", &table_csv());
    write(d, "nocol.csv", "t,u,x\n0,1,2\n");
    write(d, "word.csv", "t,u,y\n0,1,2\n0.1,1,abc\n");
    write(d, "nan.csv", "t,u,y\n0,1,2\n0.1,NaN,3\n");
    write(d, "inf.csv", "t,u,y\n0,1,2\n0.1,1,inf\n");
    write(d, "jump.csv", "t,u,y\n0,1,2\n0.1,1,3\n0.2,1,4\n0.35,1,5\n");
    write(d, "still.csv", "t,u,y\n0,1,2\n0,1,3\n");
    write(d, "short.csv", "t,u,y\n0,1,2\n0.1,1,3\n0.2,1,4\n");
    write(d, "one.csv", "t,u,y\n0,1,2\n");
    write(d, "ragged.csv", "t,u,y\n0,1,2\n0.1,1\n");
    write(d, "empty.csv", "");
    // A record rich enough for 2,2,1 (a random binary input through a damped resonance), which a weighting that
    // forgets all but the last row is not.
    let mut next = nanopos_id::xorshift64(0x0123_4567_89AB_CDEF);
    let (mut rich, mut y) = (String::from("t,u,y\n"), [0.0f64; 2]);
    for k in 0..200 {
        let u = if next() & 1 == 0 { 1.0 } else { -1.0 };
        rich += &format!("{},{u},{}\n", k as f64 * 0.001, y[0]);
        y = [1.8 * y[0] - 0.9 * y[1] + 0.1 * u, y[0]];
    }
    write(d, "rich.csv", &rich);
    // A constant input: with --offset its column and the constant's are the same.
    let still: String = (0..50).map(|k| format!("{},1,{}\n", k as f64 * 0.001, (next() % 1000) as f64)).collect();
    write(d, "still_u.csv", &format!("t,u,y\n{still}"));
    assert_eq!(
        nanopos_sim(&["fit", "--input", "rich.csv", "--arx", "2,2,1", "--weight", "1,0.9"], d).status.code(),
        Some(0)
    );
    // As many rows as parameters are enough (the fit is then exact): 3 samples, 2 rows with full history for 1,1,1.
    let out = nanopos_sim(&["fit", "--input", "short.csv", "--arx", "1,1,1"], d);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(String::from_utf8(out.stdout).unwrap().ends_with("\"rows\": 2}\n"));
    let cases: &[(&[&str], &str)] = &[
        (
            &["fit", "--input", "rich.csv", "--arx", "2,2,1", "--weight", "1,1e-300"],
            "of its norm); --weight 1,1e-300 leaves about 1.0 rows that count ((1 + GAMMA) / (1 - GAMMA)): a GAMMA \
             nearer 1 keeps more",
        ),
        (&["fit", "--input", "missing.csv", "--arx", "2,2,1"], "missing.csv: cannot open"),
        (&["fit", "--input", "nocol.csv", "--arx", "2,2,1"], "nocol.csv:1: no column 'y'"),
        (&["fit", "--input", "word.csv", "--arx", "1,1,1"], "word.csv:3: column 'y': 'abc' is not a number"),
        (&["fit", "--input", "nan.csv", "--arx", "1,1,1"], "nan.csv:3: column 'u'"),
        (&["fit", "--input", "inf.csv", "--arx", "1,1,1"], "inf.csv:3: column 'y'"),
        (&["fit", "--input", "jump.csv", "--arx", "1,1,1"], "jump.csv:5: time 0.35 breaks the uniform sampling"),
        (&["fit", "--input", "still.csv", "--arx", "1,1,1"], "still.csv:3: time 0 does not advance"),
        (
            &["fit", "--input", "short.csv", "--arx", "2,2,1"],
            "short.csv: too few rows: 3 samples give 1 regression row with full history, 4 parameters need at least 4",
        ),
        (
            &["fit", "--input", "short.csv", "--arx", "1,1,1", "--offset"],
            "short.csv: too few rows: 3 samples give 2 regression rows with full history, 3 parameters need at least 3",
        ),
        (
            &["fit", "--input", "one.csv", "--arx", "1,1,1"],
            "one.csv: too few rows: 1 sample gives 0 regression rows with full history, 2 parameters need at least 2",
        ),
        (&["fit", "--input", "ragged.csv", "--arx", "1,1,1"], "ragged.csv:3: 2 fields, the header has 3"),
        (&["fit", "--input", "empty.csv", "--arx", "1,1,1"], "empty.csv: empty file"),
        (
            &["fit", "--input", "t.csv", "--arx", "2,2,1"],
            "rank-deficient fit: column u(k-2) is (nearly) a combination of u(k-1)",
        ),
        (
            &["fit", "--input", "still_u.csv", "--arx", "1,1,1", "--offset"],
            "rank-deficient fit: column 1 (the constant) is (nearly) a combination of u(k-1)",
        ),
        (&["fit", "--input", "t.csv", "--arx", "2,2"], "NA,NB,NK"),
        // Refused as --arx's value, not as an unknown option '-1'.
        (&["fit", "--input", "t.csv", "--arx", "-1,2,1"], "'-1,2,1': expected NA,NB,NK"),
        (&["fit", "--input", "t.csv", "--arx", "0,0,1"], "at least one parameter"),
        (&["fit", "--input", "t.csv", "--arx", "20,20,1"], "at most 32 parameters"),
        (&["fit", "--input", "t.csv", "--arx", "2,2,1", "--weight", "0.2,1.5"], "0 < GAMMA <= 1"),
        (&["fit", "--input", "t.csv", "--arx", "2,2,1", "--weight", "-1,0.9"], "A > 0"),
        (&["fit", "--arx", "2,2,1"], "--input"),
    ];
    for (args, mention) in cases {
        let out = nanopos_sim(args, d);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
        assert_eq!(stderr.trim_end().lines().count(), 1, "{args:?}: {stderr:?}");
        assert!(stderr.contains(mention), "{args:?}: {stderr:?} should contain {mention:?}");
        assert!(out.stdout.is_empty() && !stderr.contains("panicked"));
    }
}
