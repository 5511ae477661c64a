//! Reading recorded runs: a CSV file with a header line naming at least the columns asked for (others ignored),
//! uniformly sampled in `t`. Every problem is reported as `FILE:LINE: what` and nothing is guessed: a missing
//! column, a field that is not a number, NaN or infinity, a row with the wrong number of fields, time that does
//! not advance uniformly.

use crate::cmd::CliError;
use std::io::Read;
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
///
/// The file is read whole and its rows parsed in parallel, one chunk per core (a 200 s record at 10 kHz is 2 million
/// rows and 118 MB): the rows are split at line ends, so each chunk is whole lines, and the columns are joined in
/// order. Line numbers in messages are the file's.
pub fn read_columns_optional(
    path: &Path,
    names: &[&str],
    optional: &[&str],
    time: Time,
) -> Result<(Columns, Option<Columns>), CliError> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()).min(8);
    read_columns_in(path, names, optional, time, Chunks { most: threads, least_bytes: 1 << 16 })
}

/// How the rows are cut for parsing in parallel.
#[derive(Clone, Copy, Debug)]
struct Chunks {
    /// At most this many pieces.
    most: usize,
    /// None smaller than this (but the last).
    least_bytes: usize,
}

fn read_columns_in(
    path: &Path,
    names: &[&str],
    optional: &[&str],
    time: Time,
    chunks: Chunks,
) -> Result<(Columns, Option<Columns>), CliError> {
    let shown = path.display();
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .map_err(|e| CliError(format!("{shown}: cannot open: {}", crate::cmd::io_reason(&e))))?
        .read_to_end(&mut bytes)
        .map_err(|e| CliError(format!("{shown}: cannot read: {}", crate::cmd::io_reason(&e))))?;
    if is_blank(&bytes) {
        return Err(CliError(format!("{shown}: empty file (a header line naming {} is needed)", names.join(","))));
    }
    let header_end = bytes.iter().position(|&b| b == b'\n').unwrap_or(bytes.len());
    let header = std::str::from_utf8(&bytes[..header_end])
        .map_err(|_| CliError(format!("{shown}:1: the header is not text")))?;
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
    // For each field of a row: the output column it fills, if any.
    let mut slot = vec![None; fields.len()];
    for (c, name) in names.iter().enumerate() {
        match fields.iter().position(|f| f == name) {
            Some(i) => slot[i] = Some(c),
            None => {
                return Err(CliError(format!(
                    "{shown}:1: no column '{name}' in the header (found: {})",
                    fields.join(",")
                )))
            }
        }
    }
    let body = &bytes[(header_end + 1).min(bytes.len())..];
    let pieces = split_lines(body, chunks);
    let parse = |piece: &[u8]| parse_rows(piece, &slot, &names, fields.len());
    // The first piece on this thread, the others on their own.
    let parsed: Vec<Parsed> = std::thread::scope(|s| {
        let jobs: Vec<_> = pieces[1..].iter().map(|&piece| s.spawn(move || parse(piece))).collect();
        let first = parse(pieces[0]);
        core::iter::once(first)
            .chain(jobs.into_iter().map(|j| j.join().expect("a CSV chunk's parser does not panic")))
            .collect()
    });
    let mut parts = Vec::with_capacity(parsed.len());
    for (i, result) in parsed.into_iter().enumerate() {
        match result {
            Ok(columns) => parts.push(columns),
            Err((line, what)) => {
                // Lines before this piece: the header's and the earlier pieces'.
                let before: usize = pieces[..i].iter().map(|p| line_ends(p)).sum();
                return Err(CliError(format!("{shown}:{}: {what}", 1 + before + line)));
            }
        }
    }
    let mut parts = parts.into_iter();
    let mut data = parts.next().unwrap_or_else(|| vec![Vec::new(); names.len()]);
    let rest: Vec<_> = parts.collect();
    for (c, column) in data.iter_mut().enumerate() {
        column.reserve_exact(rest.iter().map(|p| p[c].len()).sum());
        for part in &rest {
            column.extend_from_slice(&part[c]);
        }
    }
    let mut out = Columns { data, sample_period_s: None };
    if let Some(tc) = names[..required].iter().position(|&n| n == "t") {
        let step = check_uniform(&out.data[tc])
            .map_err(|(row, what)| CliError(format!("{shown}:{}: {what}", 1 + line_of_row(body, row))))?;
        out.sample_period_s = step;
    }
    let extra = with_optional.then(|| Columns { data: out.data.split_off(required), sample_period_s: None });
    Ok((out, extra))
}

/// `body` cut into pieces of whole lines as `chunks` says (each but the last ends with its line's `\n`).
fn split_lines(body: &[u8], chunks: Chunks) -> Vec<&[u8]> {
    let target = body.len().div_ceil(chunks.most.max(1)).max(chunks.least_bytes.max(1));
    let mut pieces = Vec::new();
    let mut rest = body;
    while rest.len() > target {
        match rest[target..].iter().position(|&b| b == b'\n') {
            Some(i) => {
                let (piece, tail) = rest.split_at(target + i + 1);
                pieces.push(piece);
                rest = tail;
            }
            None => break,
        }
    }
    pieces.push(rest);
    pieces
}

/// A piece's columns, or the line (within the piece) and what is wrong with it.
type Parsed = Result<Vec<Vec<f64>>, (usize, String)>;

/// The rows of one piece: one vector per output column. An error carries its line, counted from 1 within the piece.
fn parse_rows(piece: &[u8], slot: &[Option<usize>], names: &[&str], width: usize) -> Parsed {
    let piece = std::str::from_utf8(piece).map_err(|e| {
        let line = 1 + line_ends(&piece[..e.valid_up_to()]);
        (line, "not text (invalid UTF-8)".to_string())
    })?;
    let rows_guess = piece.len() / 40 + 1;
    let mut data: Vec<Vec<f64>> = names.iter().map(|_| Vec::with_capacity(rows_guess)).collect();
    for (i, line) in piece.split('\n').enumerate() {
        let line_no = i + 1;
        if is_blank(line.as_bytes()) {
            continue;
        }
        // Fields by a plain byte scan: faster than `str::split` on short fields. `,` is ASCII, so every cut is on a
        // character boundary of the validated text.
        let ends = line.bytes().enumerate().filter(|&(_, b)| b == b',').map(|(j, _)| j).chain([line.len()]);
        let (mut count, mut start) = (0, 0);
        for end in ends {
            if let Some(c) = slot.get(count).copied().flatten() {
                let text = line[start..end].trim_ascii();
                let v: f64 =
                    text.parse().map_err(|_| (line_no, format!("column '{}': '{text}' is not a number", names[c])))?;
                if !v.is_finite() {
                    return Err((line_no, format!("column '{}': {text} is not a finite number", names[c])));
                }
                data[c].push(v);
            }
            count += 1;
            start = end + 1;
        }
        if count != width {
            return Err((line_no, format!("{count} fields, the header has {width}")));
        }
    }
    Ok(data)
}

/// The step of a uniformly advancing time column (to a relative 1e-6 of the step, which printed decimal times
/// meet), `None` with fewer than two rows; or the first row that breaks it, with why.
fn check_uniform(t: &[f64]) -> Result<Option<f64>, (usize, String)> {
    if t.len() < 2 {
        return Ok(None);
    }
    let (t0, step) = (t[0], t[1] - t[0]);
    if step <= 0.0 {
        return Err((1, format!("time {} does not advance from {t0}", t[1])));
    }
    for (k, &now) in t.iter().enumerate().skip(2) {
        let expected = t0 + k as f64 * step;
        if (now - expected).abs() > 1e-6 * step + 1e-12 * now.abs() {
            return Err((k, format!("time {now} breaks the uniform sampling (expected {expected}, step {step})")));
        }
    }
    Ok(Some(step))
}

/// The line of `body` (counted from 1) that holds data row `row` (counted from 0; blank lines hold none).
fn line_of_row(body: &[u8], row: usize) -> usize {
    body.split(|&b| b == b'\n').enumerate().filter(|(_, l)| !is_blank(l)).nth(row).map_or(0, |(i, _)| i + 1)
}

/// A line with nothing but white space, skipped wherever it is.
fn is_blank(line: &[u8]) -> bool {
    line.trim_ascii().is_empty()
}

/// How many lines end in `bytes`.
fn line_ends(bytes: &[u8]) -> usize {
    bytes.iter().filter(|&&b| b == b'\n').count()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(name: &str, text: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("nanopos-csv-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    }

    /// Cut into pieces of a line or two: every piece boundary is exercised.
    const TINY: Chunks = Chunks { most: 64, least_bytes: 1 };

    fn rows(n: usize) -> String {
        let mut s = String::from("t, u ,y,extra\n");
        for k in 0..n {
            s += &format!("{:.4},{},{},x\n", k as f64 * 1e-4, (k as f64).sin(), k);
            if k % 7 == 3 {
                s += "\n"; // blank lines are skipped wherever they fall
            }
        }
        s
    }

    #[test]
    fn pieces_are_whole_lines_and_join_in_order() {
        let body = b"1,2\n3,4\n5,6\n7,8";
        for least in 1..body.len() + 2 {
            let pieces = split_lines(body, Chunks { most: 3, least_bytes: least });
            assert_eq!(pieces.concat(), body, "least {least}");
            assert!(pieces[..pieces.len() - 1].iter().all(|p| p.ends_with(b"\n")), "least {least}");
        }
    }

    #[test]
    fn parallel_pieces_read_exactly_what_one_piece_reads() {
        let path = file("many.csv", &rows(500));
        let one = read_columns_in(&path, &["y", "u"], &[], Time::Required, Chunks { most: 1, least_bytes: 1 }).unwrap();
        let many = read_columns_in(&path, &["y", "u"], &[], Time::Required, TINY).unwrap();
        assert_eq!(one.0.data, many.0.data);
        assert_eq!(one.0.data[0].len(), 500);
        assert_eq!(one.0.data[0][499], 499.0);
        assert_eq!(many.0.sample_period_s, Some(1e-4));
    }

    #[test]
    fn an_error_in_a_late_piece_names_its_line_in_the_file() {
        let text = rows(300);
        let mut lines: Vec<&str> = text.lines().collect();
        let bad_line = lines.len() - 5; // 1-based line number of the line replaced below
        lines[bad_line - 1] = "0.5,zz,1,x";
        let path = file("late.csv", &(lines.join("\n") + "\n"));
        for chunks in [Chunks { most: 1, least_bytes: 1 }, TINY] {
            let e = read_columns_in(&path, &["u"], &[], Time::Required, chunks).unwrap_err();
            assert!(e.0.ends_with(&format!("late.csv:{bad_line}: column 'u': 'zz' is not a number")), "{}", e.0);
        }
        // Time that jumps, found after the pieces are joined, is reported at its line too (blank lines counted).
        let mut lines: Vec<&str> = text.lines().collect();
        let jump = lines.len() - 2;
        lines[jump - 1] = "9.0,0,0,x";
        let path = file("jump.csv", &(lines.join("\n") + "\n"));
        let e = read_columns_in(&path, &["u"], &[], Time::Required, TINY).unwrap_err();
        assert!(e.0.contains(&format!("jump.csv:{jump}: time 9 breaks the uniform sampling")), "{}", e.0);
    }

    #[test]
    fn invalid_utf8_is_refused_with_its_line() {
        let path = file("bytes.csv", "t,u\n0,1\n0.1,\u{0}\n");
        let mut bytes = std::fs::read(&path).unwrap();
        let at = bytes.iter().position(|&b| b == 0).unwrap();
        bytes[at] = 0xff;
        std::fs::write(&path, bytes).unwrap();
        let e = read_columns(&path, &["u"], Time::Required).unwrap_err();
        assert!(e.0.ends_with("bytes.csv:3: not text (invalid UTF-8)"), "{}", e.0);
    }
}
