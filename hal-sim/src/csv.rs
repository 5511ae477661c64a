//! Reading recorded runs: a CSV file with a header line naming at least the columns asked for (others ignored),
//! uniformly sampled in `t`. Every problem is reported as `FILE:LINE: what` and nothing is guessed: a missing
//! column, one named twice, part of a group of columns that go together, a field that is not a number, NaN or
//! infinity, a row with the wrong number of fields, time that does not advance uniformly. What spreadsheets and
//! other tools write is read: a UTF-8 byte-order mark before the header, blank lines and `#` comments (a logger's
//! notes, in UTF-8 or Latin-1) before it and among the rows, a header after a comment mark (numpy's `savetxt` writes
//! `# t,u,y`) or in Latin-1, a column's unit in its name (`y [um]`; `y [nm]` and the like are scaled to the unit the
//! column is read in, a unit of another quantity is refused), and fields in double quotes (`"t"`, `"0.5"`; a field
//! never holds a comma here).

use crate::cmd::{clip, show, CliError};
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

/// Whether `bytes` start with a UTF-16 byte-order mark (little- or big-endian): a text file of another encoding,
/// which Excel's "Unicode text" and a redirection in Windows PowerShell write.
pub fn utf16(bytes: &[u8]) -> bool {
    bytes.starts_with(&[0xFF, 0xFE]) || bytes.starts_with(&[0xFE, 0xFF])
}

/// Read `names` from `path`, and `t` as [`Time`] says. Time may start anywhere but must advance by a constant step
/// (to a relative 1e-6 of the step, which printed decimal times meet).
pub fn read_columns(path: &Path, names: &[&str], time: Time) -> Result<Columns, CliError> {
    read_columns_optional(path, names, &[], time).map(|(c, _)| c)
}

/// [`read_columns`], plus the `optional` columns in the same pass if the header names all of them (then returned
/// as a second [`Columns`], else `None`). Reads through a [`Reader`], so messages are the same.
pub fn read_columns_optional(
    path: &Path,
    names: &[&str],
    optional: &[&str],
    time: Time,
) -> Result<(Columns, Option<Columns>), CliError> {
    read_columns_in(path, names, optional, time, Chunks::for_this_machine())
}

fn read_columns_in(
    path: &Path,
    names: &[&str],
    optional: &[&str],
    time: Time,
    chunks: Chunks,
) -> Result<(Columns, Option<Columns>), CliError> {
    let mut reader = Reader::open_in(path, names, optional, time, chunks)?;
    let mut data: Vec<Vec<f64>> = vec![Vec::new(); reader.width()];
    while let Some(block) = reader.next_block()? {
        append_columns(&mut data, block);
    }
    let mut out = Columns { data, sample_period_s: reader.sample_period_s() };
    let extra =
        reader.has_optional().then(|| Columns { data: out.data.split_off(reader.required), sample_period_s: None });
    Ok((out, extra))
}

/// How the file is cut: into blocks read one after the other, each block into pieces parsed in parallel.
#[derive(Clone, Copy, Debug)]
struct Chunks {
    /// Bytes read per block (more if a line is longer).
    block_bytes: usize,
    /// At most this many pieces per block.
    most: usize,
    /// No piece smaller than this (but the last).
    least_bytes: usize,
}

impl Chunks {
    /// 8 MiB blocks (about 140 000 rows of `simulate`'s output), one piece per core, up to 8.
    fn for_this_machine() -> Chunks {
        let most = std::thread::available_parallelism().map_or(1, |n| n.get()).min(8);
        Chunks { block_bytes: 8 << 20, most, least_bytes: 1 << 16 }
    }
}

/// A CSV file read a block of rows at a time, so that a long record (an hour at 10 kHz is 2 GB of text) never has
/// to be in memory whole. Each block is whole lines, parsed in parallel, one piece per core; time is checked
/// across blocks, and line numbers in messages are the file's.
pub struct Reader {
    path: std::path::PathBuf,
    shown: String,
    file: std::fs::File,
    /// The output columns: the requested, `t` if it is read, then the optional ones when all are present.
    names: Vec<String>,
    /// How many of `names` are not optional.
    required: usize,
    with_optional: bool,
    /// For each field of a row: the output column it fills, if any, and the scale of its unit.
    slot: Vec<Option<Slot>>,
    /// Fields per row.
    fields: usize,
    /// The field of `t` in a row, and its output column, when `t` is read.
    t_field: Option<(usize, usize)>,
    chunks: Chunks,
    /// Bytes read but not yet parsed (the start of a line).
    carry: Vec<u8>,
    eof: bool,
    /// Lines of the file before `carry` (the header's and those of earlier blocks).
    lines_before: usize,
    bytes_done: u64,
    file_len: u64,
    rows: usize,
    /// The first time and the step, once known.
    t0: Option<f64>,
    step: Option<f64>,
}

impl Reader {
    /// Open `path` and read its header: the columns `names`, `t` as [`Time`] says, and the `optional` columns if the
    /// header names all of them ([`Reader::has_optional`]). Blocks come in that order.
    pub fn open(path: &Path, names: &[&str], optional: &[&str], time: Time) -> Result<Reader, CliError> {
        Reader::open_in(path, names, optional, time, Chunks::for_this_machine())
    }

    fn open_in(path: &Path, names: &[&str], optional: &[&str], time: Time, chunks: Chunks) -> Result<Reader, CliError> {
        let shown = path.display().to_string();
        let file = crate::cmd::open_input(path)?;
        let file_len = file.metadata().map_or(0, |m| m.len());
        let mut r = Reader {
            path: path.to_path_buf(),
            shown,
            file,
            names: Vec::new(),
            required: 0,
            with_optional: false,
            slot: Vec::new(),
            fields: 0,
            t_field: None,
            chunks,
            carry: Vec::new(),
            eof: false,
            lines_before: 1,
            bytes_done: 0,
            file_len,
            rows: 0,
            t0: None,
            step: None,
        };
        // Every column the header must name: `t` first when it is required.
        let needed: Vec<&str> = (time == Time::Required && !names.contains(&"t"))
            .then_some("t")
            .into_iter()
            .chain(names.iter().copied())
            .collect();
        // Whether a line names them all, separated by `sep`.
        let names_all = |line: &str, sep: char| needed.iter().all(|n| line.split(sep).any(|f| name_of(f) == *n));
        r.fill(1 << 16)?;
        if utf16(&r.carry) {
            return Err(CliError(format!(
                "{}: UTF-16 text (its first bytes say so: Excel's \"Unicode text\" and a redirection in Windows \
                 PowerShell write it): save it as CSV in UTF-8 or ASCII",
                r.shown
            )));
        }
        // A spreadsheet's UTF-8 export starts with a byte-order mark, which would otherwise be part of the first name.
        let mut start = if r.carry.starts_with("\u{feff}".as_bytes()) { 3 } else { 0 };
        // The header: the first line, whatever its length, that is neither blank nor a comment. A comment starts with
        // '#' (numpy's `savetxt` writes its `header=` lines so, a logger its run's details) unless it names every
        // column needed: numpy's header itself, `# t,u,y`. One that names them separated otherwise (`savetxt`'s
        // default spaces) is kept, in case no line names them with commas: it is then the header refused below.
        let (mut skipped, mut comments) = (0, 0);
        let mut otherwise: Option<(usize, String)> = None;
        let (header_start, header_end) = loop {
            if start >= r.carry.len() && r.eof {
                if otherwise.is_some() {
                    // (`start` is past the end when the last line has no line end.)
                    let end = r.carry.len();
                    break (end, end);
                }
                let message = if comments == 0 {
                    format!("{}: empty file (a header line naming {} is needed)", r.shown, needed.join(","))
                } else {
                    format!(
                        "{}: no header: {comments} line{} starting with '#', read as comments, and none names {}",
                        r.shown,
                        if comments == 1 { "" } else { "s" },
                        needed.join(",")
                    )
                };
                return Err(CliError(message));
            }
            let end = match r.carry[start..].iter().position(|&b| b == b'\n') {
                Some(i) => start + i,
                None if r.eof => r.carry.len(),
                None => {
                    // Lines skipped are not kept: a file of nothing but comments is read 64 KiB at a time.
                    r.carry.drain(..start);
                    r.bytes_done += start as u64;
                    start = 0;
                    r.fill(1 << 16)?;
                    continue;
                }
            };
            let text = r.carry[start..end].trim_ascii_start();
            let skip = match text.strip_prefix(b"#") {
                Some(rest) => {
                    let rest = std::str::from_utf8(rest).ok();
                    let comment = !rest.is_some_and(|h| names_all(h, ','));
                    if comment {
                        comments += 1;
                        if let Some(h) = rest.filter(|h| [';', '\t', ' '].into_iter().any(|sep| names_all(h, sep))) {
                            otherwise = Some((skipped + 1, format!("#{h}")));
                        }
                    }
                    comment
                }
                None => text.is_empty(),
            };
            if !skip {
                break (start, end);
            }
            skipped += 1;
            start = end + 1;
        };
        // The header's line in the file, for the messages.
        let mut header_line = skipped + 1;
        let header_bytes = &r.carry[header_start..header_end];
        let decoded: std::borrow::Cow<str> = match std::str::from_utf8(header_bytes) {
            Ok(text) => text.into(),
            // Not UTF-8 but text: Latin-1 (Windows' Western European, a logger's `y [\xb5m]`; the units' signs the
            // same in both).
            Err(_) if !header_bytes.iter().any(|&b| b < b' ' && b != b'\t' && b != b'\r' || b == 0x7f) => {
                header_bytes.iter().map(|&b| char::from(b)).collect::<String>().into()
            }
            Err(_) => {
                return Err(CliError(format!(
                    "{}:{header_line}: the header is not text (is the file a spreadsheet's own, not its CSV export?)",
                    r.shown
                )))
            }
        };
        let mut header = decoded.as_ref();
        if let Some((line, comment)) = otherwise.as_ref().filter(|_| !names_all(header, ',')) {
            (header_line, header) = (*line, comment);
        }
        let written = header.trim_start();
        // numpy's `savetxt` writes its header after its comment mark, `# t,u,y`, unless told `comments=''`.
        let header = written.strip_prefix('#').unwrap_or(written);
        let fields: Vec<String> = header.split(',').map(|f| unquote(f.trim()).to_string()).collect();
        // The columns' names, their units aside.
        let named: Vec<&str> = fields.iter().map(|f| name_of(f)).collect();
        let has = |name: &str| named.contains(&name);
        let mut wanted: Vec<&str> = names.to_vec();
        if !wanted.contains(&"t") && (time == Time::Required || has("t")) {
            wanted.push("t");
        }
        r.required = wanted.len();
        let present: Vec<&str> = optional.iter().copied().filter(|o| has(o)).collect();
        if !present.is_empty() && present.len() < optional.len() {
            return Err(CliError(format!(
                "{}:{header_line}: columns {} go together, the header has only {}",
                r.shown,
                optional.join(", "),
                present.join(", ")
            )));
        }
        r.with_optional = !optional.is_empty() && present.len() == optional.len();
        if r.with_optional {
            wanted.extend_from_slice(optional);
        }
        r.slot = vec![None; fields.len()];
        for (c, name) in wanted.iter().enumerate() {
            let mut at = named.iter().enumerate().filter(|(_, f)| *f == name).map(|(i, _)| i + 1);
            if let (Some(first), Some(second)) = (at.next(), at.next()) {
                return Err(CliError(format!(
                    "{}:{header_line}: column '{name}' named twice in the header (fields {first} and {second}): \
                     which one is meant?",
                    r.shown
                )));
            }
            match named.iter().position(|f| f == name) {
                Some(i) => {
                    let scale =
                        unit_read(&fields[i], name).map_err(|e| CliError(format!("{}:{header_line}: {e}", r.shown)))?;
                    r.slot[i] = Some(Slot { column: c, scale });
                    if *name == "t" && c < r.required {
                        r.t_field = Some((i, c));
                    }
                }
                None if fields.iter().all(|f| f.parse::<f64>().is_ok()) => {
                    // A file without a header (`savetxt` without `header=`), or whose header is behind the comments.
                    return Err(CliError(format!(
                        "{}:{header_line}: numbers where the header should be (found: {}): the first line, blank lines \
                         and '#' comments aside, must name the columns {}",
                        r.shown,
                        clip(written.trim(), 120),
                        needed.join(",")
                    )));
                }
                None => {
                    // One field holding the others, this one among them: another separator (Excel in a locale with
                    // a decimal comma writes ';', numpy's `savetxt` spaces by default).
                    let apart = |sep: char| fields[0].split(sep).any(|f| name_of(f) == *name);
                    let other = [(';', "';'"), ('\t', "tabs"), (' ', "spaces")]
                        .into_iter()
                        .find(|&(sep, _)| fields.len() == 1 && apart(sep))
                        .map_or(String::new(), |(_, what)| {
                            format!(
                                ": its fields are separated by {what}; this reads commas, and '.' as the decimal point"
                            )
                        });
                    return Err(CliError(format!(
                        "{}:{header_line}: no column '{name}' in the header (found: {}){other}",
                        r.shown,
                        clip(written.trim(), 120)
                    )));
                }
            }
        }
        r.fields = fields.len();
        r.names = wanted.iter().map(|n| n.to_string()).collect();
        let body_start = (header_end + 1).min(r.carry.len());
        r.carry.drain(..body_start);
        r.bytes_done += body_start as u64;
        r.lines_before = header_line;
        Ok(r)
    }

    /// Read up to `bytes` more into `carry`.
    fn fill(&mut self, bytes: usize) -> Result<(), CliError> {
        let start = self.carry.len();
        self.carry.resize(start + bytes, 0);
        let mut got = 0;
        while got < bytes {
            match self.file.read(&mut self.carry[start + got..]) {
                Ok(0) => {
                    self.eof = true;
                    break;
                }
                Ok(n) => got += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(CliError(format!("{}: cannot read: {}", self.shown, crate::cmd::io_reason(&e)))),
            }
        }
        self.carry.truncate(start + got);
        Ok(())
    }

    /// Columns per block.
    pub fn width(&self) -> usize {
        self.names.len()
    }

    /// Whether the optional columns are read (after the others).
    pub fn has_optional(&self) -> bool {
        self.with_optional
    }

    /// Bytes of the file parsed so far, and its length: progress.
    pub fn progress(&self) -> (u64, u64) {
        (self.bytes_done, self.file_len)
    }

    /// The sample period once two rows are read (when `t` is read).
    pub fn sample_period_s(&self) -> Option<f64> {
        self.step
    }

    /// The time on the file's last line that is not blank, read from its end without reading the rest; `None` if
    /// there is no `t` or that line does not give one (reading the blocks then reports what is wrong with it).
    pub fn last_time(&self) -> Option<f64> {
        use std::io::{Seek, SeekFrom};
        let (field, _) = self.t_field?;
        let scale = self.slot[field].and_then(|s| s.scale);
        let mut file = std::fs::File::open(&self.path).ok()?;
        let len = file.metadata().ok()?.len();
        let tail = len.min(1 << 16);
        file.seek(SeekFrom::Start(len - tail)).ok()?;
        let mut bytes = Vec::with_capacity(tail as usize);
        file.read_to_end(&mut bytes).ok()?;
        let mut lines = bytes.split(|&b| b == b'\n').filter(|l| !holds_no_row(l));
        let last = lines.next_back()?;
        // The first line of the tail may be cut; a whole line has a line end before it.
        if lines.next().is_none() && (tail as usize) < len as usize {
            return None;
        }
        let text = unquote(std::str::from_utf8(last).ok()?.split(',').nth(field)?.trim());
        text.parse().ok().map(|t: f64| scale.map_or(t, |s| s.apply(text, t))).filter(|t| t.is_finite())
    }

    /// The next block of rows, one vector per column (`None` at the end of the file).
    pub fn next_block(&mut self) -> Result<Option<Vec<Vec<f64>>>, CliError> {
        // Whole lines: a block's worth, cut at its last line end (read on while a line is longer than that).
        if !self.eof && self.carry.len() < self.chunks.block_bytes {
            self.fill(self.chunks.block_bytes - self.carry.len())?;
        }
        let cut = loop {
            if self.eof {
                break self.carry.len();
            }
            if let Some(i) = self.carry.iter().rposition(|&b| b == b'\n') {
                break i + 1;
            }
            self.fill(self.chunks.block_bytes.max(1))?;
        };
        if cut == 0 {
            return Ok(None);
        }
        let rest = self.carry.split_off(cut);
        let body = std::mem::replace(&mut self.carry, rest);
        let pieces = split_lines(&body, self.chunks);
        let names: Vec<&str> = self.names.iter().map(String::as_str).collect();
        let parse = |piece: &[u8]| parse_rows(piece, &self.slot, &names, self.fields);
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
                    let before: usize = pieces[..i].iter().map(|p| line_ends(p)).sum();
                    return Err(CliError(format!("{}:{}: {what}", self.shown, self.lines_before + before + line)));
                }
            }
        }
        let mut data = vec![Vec::new(); names.len()];
        for part in parts {
            append_columns(&mut data, part);
        }
        if let Some((_, tc)) = self.t_field {
            self.check_time(&data[tc]).map_err(|(row, what)| {
                CliError(format!("{}:{}: {what}", self.shown, self.lines_before + line_of_row(&body, row)))
            })?;
        }
        self.rows += data.first().map_or(0, Vec::len);
        self.lines_before += line_ends(&body);
        self.bytes_done += body.len() as u64;
        Ok(Some(data))
    }

    /// Check that time advances by a constant step (to a relative 1e-6 of the step, which printed decimal times
    /// meet, and 1e-12 of the time, for its rounding) over the block `t`, which follows the rows read so far; or the
    /// row of the block that breaks it. The step is measured again, from the first row, at each row whose index is a
    /// power of two: the first difference alone carries the rounding of the first time (an ulp of 10 s is 1.8e-15 s,
    /// 1.8e-11 of a 0.1 ms step), which `t0 + k step` multiplies by `k`, and a record that started at 10 s (a
    /// simulated one cropped) broke the tolerance 83 s on.
    fn check_time(&mut self, t: &[f64]) -> Result<(), (usize, String)> {
        for (i, &now) in t.iter().enumerate() {
            let k = self.rows + i;
            match (self.t0, self.step) {
                (None, _) => self.t0 = Some(now),
                (Some(t0), None) => {
                    if now - t0 <= 0.0 {
                        return Err((i, format!("time {} does not advance from {}", show(now), show(t0))));
                    }
                    self.step = Some(now - t0);
                }
                (Some(t0), Some(step)) => {
                    let expected = t0 + k as f64 * step;
                    if (now - expected).abs() > 1e-6 * step + 1e-12 * now.abs() {
                        return Err((
                            i,
                            format!(
                                "time {} breaks the uniform sampling (expected {}, step {})",
                                show(now),
                                show_within(expected, 1e-6 * step),
                                show_within(step, 1e-6 * step)
                            ),
                        ));
                    }
                    if k.is_power_of_two() {
                        self.step = Some((now - t0) / k as f64);
                    }
                }
            }
        }
        Ok(())
    }
}

/// Append the columns `part` to `data`, column by column (the first part is moved, not copied).
fn append_columns(data: &mut [Vec<f64>], part: Vec<Vec<f64>>) {
    for (column, p) in data.iter_mut().zip(part) {
        if column.is_empty() {
            *column = p;
        } else {
            column.extend_from_slice(&p);
        }
    }
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
///
/// Rows are numbers, so text that is not UTF-8 can only be a comment's (a logger's note in Latin-1 or Windows-1252,
/// `# 23 \xb0C`): the piece is checked whole, and only where that fails is it taken apart at such comments.
fn parse_rows(piece: &[u8], slot: &[Option<Slot>], names: &[&str], width: usize) -> Parsed {
    let rows_guess = piece.len() / 40 + 1;
    let mut data: Vec<Vec<f64>> = names.iter().map(|_| Vec::with_capacity(rows_guess)).collect();
    // The lines before `rest`.
    let (mut rest, mut before) = (piece, 0);
    let text = loop {
        let bad = match std::str::from_utf8(rest) {
            Ok(text) => break text,
            Err(e) => e.valid_up_to(),
        };
        let start = rest[..bad].iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1);
        let end = rest[bad..].iter().position(|&b| b == b'\n').map_or(rest.len(), |i| bad + i);
        if !holds_no_row(&rest[start..end]) {
            return Err((before + 1 + line_ends(&rest[..bad]), "not text (invalid UTF-8)".to_string()));
        }
        // The text before the comment's line, up to its line end (the comment's line, blank now), then past it.
        let valid = std::str::from_utf8(&rest[..start]).expect("valid up to the line of the first error");
        parse_text(valid, before, slot, names, width, &mut data)?;
        before += line_ends(&rest[..end]);
        rest = &rest[end..];
    };
    parse_text(text, before, slot, names, width, &mut data)?;
    Ok(data)
}

/// The rows of `text`, whose first line is the piece's `before + 1`, appended to `data`.
fn parse_text(
    text: &str,
    before: usize,
    slot: &[Option<Slot>],
    names: &[&str],
    width: usize,
    data: &mut [Vec<f64>],
) -> Result<(), (usize, String)> {
    for (i, line) in text.split('\n').enumerate() {
        let line_no = before + i + 1;
        if holds_no_row(line.as_bytes()) {
            continue;
        }
        // Fields by a plain byte scan: faster than `str::split` on short fields. `,` is ASCII, so every cut is on a
        // character boundary of the validated text.
        let ends = line.bytes().enumerate().filter(|&(_, b)| b == b',').map(|(j, _)| j).chain([line.len()]);
        let (mut count, mut start) = (0, 0);
        for end in ends {
            if let Some(Slot { column: c, scale }) = slot.get(count).copied().flatten() {
                let text = unquote(line[start..end].trim_ascii());
                let v: f64 = text
                    .parse()
                    .map_err(|_| (line_no, format!("column '{}': '{}' is not a number", names[c], clip(text, 40))))?;
                if !v.is_finite() {
                    return Err((line_no, format!("column '{}': {} is not a finite number", names[c], clip(text, 40))));
                }
                let v = match scale {
                    None => v,
                    Some(s) => Some(s.apply(text, v)).filter(|v| v.is_finite()).ok_or_else(|| {
                        let read = UNITS.iter().find(|(n, _)| *n == names[c]).map_or("", |(_, units)| units[0].0);
                        (line_no, format!("column '{}': {} is too large in {read}", names[c], clip(text, 40)))
                    })?,
                };
                data[c].push(v);
            }
            count += 1;
            start = end + 1;
        }
        if count != width {
            return Err((line_no, format!("{count} fields, the header has {width}")));
        }
    }
    Ok(())
}

/// The column a header's field names, without the quotes and the unit ([`name_and_unit`]).
fn name_of(field: &str) -> &str {
    name_and_unit(unquote(field.trim())).0
}

/// A header's field (unquoted) as its column's name and unit, if it gives one: `y [um]`, `y (um)`, or `y / um`
/// (DIN 1313's quantity over unit, as some loggers write it).
fn name_and_unit(field: &str) -> (&str, Option<&str>) {
    for (open, close) in [('[', Some(']')), ('(', Some(')')), ('/', None)] {
        let Some((name, rest)) = field.split_once(open) else { continue };
        let unit = match close {
            Some(close) => rest.strip_suffix(close),
            None => Some(rest),
        };
        if let Some(unit) = unit.map(str::trim).filter(|u| !u.is_empty() && !name.trim().is_empty()) {
            return (name.trim_end(), Some(unit));
        }
    }
    (field, None)
}

/// Where a field of a row goes: its output column, and the scale of its unit when that is not the one read.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Slot {
    column: usize,
    scale: Option<Scale>,
}

/// How a value in a column's unit becomes one in the unit the column is read in: times `10^exp`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Scale {
    exp: i32,
}

impl Scale {
    /// The field `text`, read as `v`, in the unit read: the decimal with its point moved, so that it is the double a
    /// file in that unit would give (`3999.9` ms is `3.9999` s to the last bit, not `3.9999000000000002`, which `v /
    /// 1000` is); a field with an exponent of its own, or too long for the buffer, as `v` times the power of ten
    /// (one rounding).
    fn apply(self, text: &str, v: f64) -> f64 {
        let mut buf = [0u8; 64];
        // `e3` or `e-3` (the units' powers are single digits).
        let digit = b'0' + self.exp.unsigned_abs().min(9) as u8;
        let (negative, positive) = ([b'e', b'-', digit], [b'e', digit]);
        let suffix: &[u8] = if self.exp < 0 { &negative } else { &positive };
        let n = text.len() + suffix.len();
        if n <= buf.len() && !text.bytes().any(|b| b == b'e' || b == b'E') {
            buf[..text.len()].copy_from_slice(text.as_bytes());
            buf[text.len()..n].copy_from_slice(suffix);
            if let Some(x) = std::str::from_utf8(&buf[..n]).ok().and_then(|t| t.parse().ok()) {
                return x;
            }
        }
        let power = 10f64.powi(self.exp.abs());
        if self.exp < 0 {
            v / power
        } else {
            v * power
        }
    }
}

/// The units each column may be given in, with their scales to the first, the one it is read in: time in seconds,
/// the command in volts, the reading in micrometres (ASCII `u`, the micro sign, or the Greek mu, for micro); the
/// other columns (the truth's parameters) as plain numbers.
const UNITS: [(&str, &[(&str, Scale)]); 3] = {
    const fn by(exp: i32) -> Scale {
        Scale { exp }
    }
    [
        ("t", &[("s", by(0)), ("ms", by(-3)), ("us", by(-6)), ("\u{b5}s", by(-6))]),
        ("u", &[("V", by(0)), ("mV", by(-3))]),
        ("y", &[("um", by(0)), ("\u{b5}m", by(0)), ("nm", by(-3)), ("mm", by(3)), ("m", by(6))]),
    ]
};

/// The scale of the unit the header's `field`, which names column `name`, gives it: `None` for none or the unit it
/// is read in, an error for a unit it is not read in or a column read as a plain number. The Greek mu is read as the
/// micro sign (keyboards give one or the other).
fn unit_read(field: &str, name: &str) -> Result<Option<Scale>, String> {
    let Some(unit) = name_and_unit(field).1 else { return Ok(None) };
    let unit = unit.replace('\u{3bc}', "\u{b5}");
    match UNITS.iter().find(|(n, _)| *n == name) {
        Some((_, units)) => match units.iter().find(|(sign, _)| *sign == unit) {
            Some(&(_, scale)) => Ok(Some(scale).filter(|s| s.exp != 0)),
            None => {
                let signs: Vec<&str> = units.iter().map(|(sign, _)| *sign).filter(|s| s.is_ascii()).collect();
                let (last, rest) = signs.split_last().expect("every column read with a unit has units");
                Err(format!(
                    "column '{}': {name} is read in {} or {last}, not {}: scale the column",
                    clip(field, 40),
                    rest.join(", "),
                    clip(&unit, 20)
                ))
            }
        },
        None => Err(format!("column '{}': {name} is read as a plain number, without a unit", clip(field, 40))),
    }
}

/// A field without the double quotes around it, if it has them.
fn unquote(field: &str) -> &str {
    field.strip_prefix('"').and_then(|f| f.strip_suffix('"')).unwrap_or(field)
}

/// The line of `body` (counted from 1) that holds data row `row` (counted from 0; blank lines and comments hold
/// none).
fn line_of_row(body: &[u8], row: usize) -> usize {
    body.split(|&b| b == b'\n').enumerate().filter(|(_, l)| !holds_no_row(l)).nth(row).map_or(0, |(i, _)| i + 1)
}

/// A blank line or a comment (its first character '#': a logger's note of an event, a second file's header after
/// `cat`, whose restart of `t` is then refused): skipped among the rows wherever it is.
fn holds_no_row(line: &[u8]) -> bool {
    matches!(line.trim_ascii().first(), None | Some(b'#'))
}

/// How many lines end in `bytes`.
fn line_ends(bytes: &[u8]) -> usize {
    bytes.iter().filter(|&&b| b == b'\n').count()
}

/// `x` with the fewest decimals that stay within `tol` of it (a time computed as `t0 + k step` is shown as `4.9998`,
/// not `4.9998000000000005`).
fn show_within(x: f64, tol: f64) -> String {
    // Beyond 1e15 the decimals are not the question (and `{:.0}` would spell out every digit).
    let most = if x.abs() < 1e15 { 18 } else { 0 };
    (0..most)
        .map(|digits| format!("{x:.digits$}"))
        .find(|text| text.parse::<f64>().is_ok_and(|v| (v - x).abs() <= tol))
        .unwrap_or_else(|| show(x))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A file named `name` holding `text`, in a temporary directory of its own that goes with it (these tests once
    /// left 3.6 MB in the system's temporary directory per run).
    struct TestFile {
        path: std::path::PathBuf,
        _dir: tempfile::TempDir,
    }

    impl std::ops::Deref for TestFile {
        type Target = Path;
        fn deref(&self) -> &Path {
            &self.path
        }
    }

    impl AsRef<Path> for TestFile {
        fn as_ref(&self) -> &Path {
            &self.path
        }
    }

    fn file(name: &str, text: impl AsRef<[u8]>) -> TestFile {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        TestFile { path, _dir: dir }
    }

    /// Cut into blocks of a few lines and pieces of a line or two: every boundary is exercised.
    const TINY: Chunks = Chunks { block_bytes: 100, most: 64, least_bytes: 1 };

    fn rows(n: usize) -> String {
        let mut s = String::from("t, u ,y,extra\n");
        for k in 0..n {
            s += &format!("{:.4},{},{},x\n", k as f64 * 1e-4, (k as f64).sin(), k);
            if k % 7 == 3 {
                s += "\n"; // blank lines are skipped wherever they fall
            }
            if k % 11 == 5 {
                s += "  # and comments\n";
            }
        }
        s
    }

    #[test]
    fn pieces_are_whole_lines_and_join_in_order() {
        let body = b"1,2\n3,4\n5,6\n7,8";
        for least in 1..body.len() + 2 {
            let pieces = split_lines(body, Chunks { block_bytes: 1, most: 3, least_bytes: least });
            assert_eq!(pieces.concat(), body, "least {least}");
            assert!(pieces[..pieces.len() - 1].iter().all(|p| p.ends_with(b"\n")), "least {least}");
        }
    }

    /// `path` read in one piece and in [`TINY`] pieces, with the time checked and not: no panic, and both readings
    /// the same, the same columns or the same message naming the same line. How many of the two checks read it.
    fn read_both_ways(path: &Path, what: &str) -> usize {
        let one_piece = Chunks { block_bytes: 1 << 30, most: 1, least_bytes: 1 };
        let mut read = 0;
        for time in [Time::Required, Time::IfPresent] {
            let read_in = |chunks| {
                std::panic::catch_unwind(|| read_columns_in(path, &["y", "u"], &[], time, chunks))
                    .unwrap_or_else(|_| panic!("the reader panicked on {what}"))
            };
            match (read_in(one_piece), read_in(TINY)) {
                (Ok((a, _)), Ok((b, _))) => {
                    assert_eq!((a.data, a.sample_period_s), (b.data, b.sample_period_s), "{what}");
                    read += 1;
                }
                (Err(a), Err(b)) => assert_eq!(a.0, b.0, "{what}"),
                (a, b) => panic!("{what}: in one piece {:?}, in many {:?}", a.map(|_| ()), b.map(|_| ())),
            }
        }
        read
    }

    /// Every file of up to three lines made of blank lines, comments, headers (with commas, spaces, after `#`) and
    /// rows, with and without a line end at the end: no panic (a comment naming the columns with spaces as the last
    /// line without a line end panicked), and the same in one piece and in many.
    #[test]
    fn files_of_comments_headers_and_rows_never_panic() {
        let lines = ["", "# c", "# t u y", "# t,u,y", "t,u,y", "0,1,2", "\u{feff}t,u,y"];
        let mut files = vec![String::new()];
        for _ in 0..3 {
            let longer: Vec<String> =
                files.iter().flat_map(|f| lines.iter().map(move |l| format!("{f}{l}\n"))).collect();
            files.extend(longer);
        }
        let (mut read, mut refused) = (0, 0);
        for (k, text) in files.iter().flat_map(|f| [f.clone(), f.trim_end_matches('\n').to_string()]).enumerate() {
            let ok = read_both_ways(&file(&format!("lines-{k}.csv"), &text), &format!("{text:?}"));
            (read, refused) = (read + ok, refused + 2 - ok);
        }
        assert!(read > 500 && refused > 500, "{read} read, {refused} refused");
    }

    /// 600 damaged files (bytes changed to one of the characters a CSV is made of, `#` among them, or to a byte that
    /// is not UTF-8 (Latin-1's degree sign), or removed, or inserted; a line doubled or lost; the file cut anywhere),
    /// each read in one piece and in [`TINY`] pieces, with the time checked and not: no panic, and both readings the
    /// same, the same columns or the same message naming the same line.
    #[test]
    fn a_damaged_file_reads_the_same_in_one_piece_and_in_many() {
        let good = rows(40);
        let mut next = nanopos_id::xorshift64(0x2F68_1C3A_99E1_0B47);
        let mut below = |n: usize| (next() % n.max(1) as u64) as usize;
        let (mut read, mut refused) = (0, 0);
        for k in 0..600 {
            let mut text = good.clone().into_bytes();
            let alphabet = b",.\n\r-e x\"0123456789+iInNaA\t#\xb0";
            for _ in 0..1 + below(3) {
                if text.is_empty() {
                    break;
                }
                let at = below(text.len());
                let b = alphabet[below(alphabet.len())];
                match below(6) {
                    0 => text[at] = b,
                    1 => drop(text.remove(at)),
                    2 => text.insert(at, b),
                    3 => text.truncate(at),
                    4 => {
                        let line: Vec<u8> =
                            text[at..].iter().copied().take_while(|&c| c != b'\n').chain([b'\n']).collect();
                        text.splice(at..at, line);
                    }
                    _ => {
                        let end = text[at..].iter().position(|&c| c == b'\n').map_or(text.len(), |i| at + i + 1);
                        text.drain(at..end);
                    }
                }
            }
            let what = format!("file {k}, {:?}", String::from_utf8_lossy(&text));
            let ok = read_both_ways(&file(&format!("damaged-{k}.csv"), &text), &what);
            (read, refused) = (read + ok, refused + 2 - ok);
        }
        println!("{read} read, {refused} refused, the same in one piece and in many");
        assert!(read > 100 && refused > 100, "{read} read, {refused} refused");
    }

    #[test]
    fn parallel_pieces_read_exactly_what_one_piece_reads() {
        let path = file("many.csv", rows(500));
        let one = read_columns_in(
            &path,
            &["y", "u"],
            &[],
            Time::Required,
            Chunks { block_bytes: 1 << 30, most: 1, least_bytes: 1 },
        )
        .unwrap();
        let many = read_columns_in(&path, &["y", "u"], &[], Time::Required, TINY).unwrap();
        assert_eq!(one.0.data, many.0.data);
        assert_eq!(one.0.data[0].len(), 500);
        assert_eq!(one.0.data[0][499], 499.0);
        assert_eq!(many.0.sample_period_s, Some(1e-4));
    }

    /// A message quotes at most the start of an absurd field or header: a field of a hundred thousand digits made a
    /// message as long.
    #[test]
    fn a_message_quotes_only_the_start_of_a_huge_field() {
        let huge = "1".repeat(100_000);
        let path = file("huge.csv", format!("t,u,y\n0,{huge},0\n0.0001,0,0\n"));
        let e = read_columns(&path, &["u", "y"], Time::Required).unwrap_err();
        let want = format!("huge.csv:2: column 'u': {}... (100000 characters) is not a finite number", &huge[..40]);
        assert!(e.0.ends_with(&want), "{}", &e.0[..e.0.len().min(300)]);
        let path = file("wide.csv", format!("t,{}\n", vec!["x"; 50_000].join(",")));
        let e = read_columns(&path, &["u"], Time::Required).unwrap_err();
        assert!(e.0.len() < 250 && e.0.ends_with("... (100001 characters))"), "{}", &e.0[..e.0.len().min(300)]);
    }

    #[test]
    fn an_error_in_a_late_piece_names_its_line_in_the_file() {
        let text = rows(300);
        let mut lines: Vec<&str> = text.lines().collect();
        let bad_line = lines.len() - 5; // 1-based line number of the line replaced below
        lines[bad_line - 1] = "0.5,zz,1,x";
        let path = file("late.csv", &(lines.join("\n") + "\n"));
        for chunks in [Chunks { block_bytes: 1 << 30, most: 1, least_bytes: 1 }, TINY] {
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
        // The expected time and the step as the file would write them, not as the sum `t0 + k step` rounds.
        assert_eq!(show_within(0.1 + 0.2, 1e-10), "0.3");
        assert_eq!(show_within(4.9998000000000005, 1e-10), "4.9998");
        assert_eq!(show_within(1e-4, 1e-10), "0.0001");
        assert_eq!(show_within(1e300, 1.0), "1e300");
    }

    /// Time that starts far from 0 (a record cropped, a logger's clock): the first difference carries the start's
    /// rounding, which `t0 + k step` multiplied by `k` until the check refused a uniform record ("time 1004.3997
    /// breaks the uniform sampling" at 1000 s, 44 000 rows on). A missing sample is still found at its line.
    #[test]
    fn time_far_from_zero_is_uniform_and_a_hole_is_still_found() {
        // Times printed as a logger would, from whole ticks of 0.1 ms: `-4.9999`, `1000.0001`.
        let rows = |t0_ticks: i64, n: i64, hole_at: Option<i64>| {
            let mut s = String::from("t,y\n");
            for k in 0..n {
                let tick = t0_ticks + k + hole_at.map_or(0, |h| (k >= h) as i64);
                let sign = if tick < 0 { "-" } else { "" };
                s += &format!("{sign}{}.{:04},{k}\n", tick.abs() / 10_000, tick.abs() % 10_000);
            }
            s
        };
        for t0_s in [1000, 100, -5] {
            let path = file("far.csv", rows(t0_s * 10_000, 100_000, None));
            let read = read_columns(&path, &["y"], Time::Required);
            let c = read.unwrap_or_else(|e| panic!("t0 {t0_s} s: {}", e.0));
            assert_eq!(c.data[0].len(), 100_000);
            let period = c.sample_period_s.unwrap();
            assert!((period / 1e-4 - 1.0).abs() < 1e-12, "t0 {t0_s} s: {period:e}");
        }
        let path = file("hole.csv", rows(1000 * 10_000, 100_000, Some(60_000)));
        let e = read_columns(&path, &["y"], Time::Required).unwrap_err();
        assert!(
            e.0.ends_with("hole.csv:60002: time 1006.0001 breaks the uniform sampling (expected 1006, step 0.0001)"),
            "{}",
            e.0
        );
    }

    /// A row that is not UTF-8 is refused at its line; a comment that is not (a logger's note in Latin-1) is skipped
    /// as any comment, before the header and among the rows, in one piece and in many.
    #[test]
    fn invalid_utf8_is_refused_with_its_line_unless_a_comment() {
        let e = read_columns(&file("bytes.csv", b"t,u\n0,1\n0.1,\xff\n"), &["u"], Time::Required).unwrap_err();
        assert!(e.0.ends_with("bytes.csv:3: not text (invalid UTF-8)"), "{}", e.0);
        let plain = read_columns(&file("plain.csv", "t,u\n0,1\n0.5,2\n1,3\n"), &["u"], Time::Required).unwrap();
        let latin = b"# 23 \xb0C\nt,u\n0,1\n# 23.5 \xb0C\n0.5,2\n  #\xb5\n#\xe9\n1,3\n# \xff";
        for chunks in [Chunks::for_this_machine(), TINY] {
            let got = read_columns_in(&file("latin.csv", latin), &["u"], &[], Time::Required, chunks).unwrap().0;
            assert_eq!((&got.data, got.sample_period_s), (&plain.data, plain.sample_period_s), "{chunks:?}");
            // Line numbers past such comments are the file's, for a bad row and for a bad field alike.
            for (row, line, what) in [(&b"1,\xb0"[..], 9, "not text (invalid UTF-8)"), (b"1,x", 9, "column 'u'")] {
                let text = [&latin[..latin.len() - 3], row, b"\n# \xff\n"].concat();
                let e = read_columns_in(&file("late.csv", text), &["u"], &[], Time::Required, chunks).unwrap_err();
                assert!(e.0.contains(&format!("late.csv:{line}: {what}")), "{}", e.0);
            }
        }
    }

    /// A field quoted in a message shows what a terminal would not as escapes: a carriage return in it had sent the
    /// cursor back over the message's start.
    #[test]
    fn a_field_quoted_in_a_message_shows_its_control_characters() {
        let path = file("cr.csv", "t,u\n0,1\n0.0001,1\r5\n");
        let e = read_columns(&path, &["u"], Time::Required).unwrap_err();
        assert!(e.0.ends_with("cr.csv:3: column 'u': '1\\r5' is not a number"), "{}", e.0);
        let path = file("quote.csv", "t,u\n0,\"1\"\"\n");
        let e = read_columns(&path, &["u"], Time::Required).unwrap_err();
        assert!(e.0.ends_with("quote.csv:2: column 'u': '1\"' is not a number"), "{}", e.0);
    }

    #[test]
    fn the_last_time_is_read_from_the_end() {
        let read = |text: &str| Reader::open(&file("tail.csv", text), &["u"], &[], Time::Required).unwrap().last_time();
        assert_eq!(read(&rows(500)), Some(499e-4));
        assert_eq!(read("t,u\n0,1\n0.5,2"), Some(0.5), "no line end at the end");
        assert_eq!(read("t,u\n0,1\n0.5,2\n\n  \n"), Some(0.5), "blank lines at the end");
        assert_eq!(read("t,u\n0,1\nzz,2\n"), None, "reading the rows says what is wrong");
        assert_eq!(read("t,u\n"), None, "no rows");
        let e = Reader::open(&file("blank.csv", " \n\n"), &["u"], &[], Time::Required).err().unwrap();
        assert!(e.0.ends_with("blank.csv: empty file (a header line naming t,u is needed)"), "{}", e.0);
        assert_eq!(read("t,u\n\"0\",\"1\"\n\"0.5\",\"2\"\n"), Some(0.5), "quoted");
        assert_eq!(read("t [ms],u\n0,1\n500,2\n"), Some(0.5), "in the unit read, s");
        // Beyond the 64 KiB read from the end: the last line of a long file; and none when the last line is longer
        // than that (the tail starts inside it: here its 70 000 zeros cut, `0.000...05` would read as 5).
        let long = rows(3_000);
        assert!(long.len() > 1 << 16);
        assert_eq!(read(&long), Some(2_999e-4));
        assert_eq!(read(&format!("t,u\n0,1\n0.{}5,2\n", "0".repeat(70_000))), None, "a last line beyond the tail");
    }

    /// Blank lines and `#` comments before the header are skipped, beyond one read (64 KiB) too, and among the rows,
    /// as numpy's `loadtxt` skips them: a logger's notes of its run, `savetxt`'s `header=` of several lines. Line
    /// numbers in later messages are the file's; a file of nothing else is said to be empty, or to have no header.
    #[test]
    fn blank_lines_and_comments_are_skipped_before_the_header_and_among_the_rows() {
        let plain = read_columns(&file("plain.csv", "t,u\n0,1\n0.5,2\n"), &["u"], Time::Required).unwrap();
        let blank = "\n".repeat(200_000);
        let notes = "# logger 7, run 3\n".repeat(5_000);
        // Each file's lines before its header, and its header (numpy's is among the comments).
        for (name, before, header) in [
            ("late.csv", blank.as_str(), "t,u\n"),
            ("one.csv", "\n", "t,u\n"),
            ("spaces.csv", "  \r\n", "t,u\n"),
            ("notes.csv", notes.as_str(), "t,u\n"),
            ("numpy.csv", "# run 3: 1 V PRBS\n# t,u\n", ""),
            ("mixed.csv", "\u{feff}# logger 7\n\n  # gain 1\r\n", "t,u\n"),
        ] {
            let text = format!("{before}{header}0,1\n0.5,2\n");
            let got = read_columns_in(&file(name, &text), &["u"], &[], Time::Required, TINY).unwrap().0;
            assert_eq!((&got.data, got.sample_period_s), (&plain.data, plain.sample_period_s), "{name}");
            // The lines before the header count: a bad field on the third row names its line in the file.
            let e = read_columns(&file(name, format!("{before}{header}0,1\n0.5,2\n1,x\n")), &["u"], Time::Required);
            let line = before.matches('\n').count() + header.len().min(1) + 3;
            let want = format!("{name}:{line}: column 'u': 'x' is not a number");
            assert!(e.as_ref().unwrap_err().0.ends_with(&want), "{e:?}, not {want}");
        }
        let e = Reader::open(&file("blanks.csv", &blank), &["u"], &[], Time::Required).err().unwrap();
        assert!(e.0.ends_with("blanks.csv: empty file (a header line naming t,u is needed)"), "{}", e.0);
        let e = Reader::open(&file("notes.csv", format!("{notes}\n")), &["u"], &[], Time::Required).err().unwrap();
        let want = "notes.csv: no header: 5000 lines starting with '#', read as comments, and none names t,u";
        assert!(e.0.ends_with(want), "{}", e.0);
        // Among the rows too (the helper `rows` puts some there); two of numpy's files one after the other (`cat`):
        // the second's header is a comment, its time's restart refused at its line.
        let text = "# t,u\n0,1\n  # payload off\n0.5,2\n# t,u\n0,3\n0.5,4\n";
        let e = read_columns(&file("cat.csv", text), &["u"], Time::Required).unwrap_err();
        assert!(e.0.ends_with("cat.csv:6: time 0 breaks the uniform sampling (expected 1, step 0.5)"), "{}", e.0);
        let event = text.strip_suffix("# t,u\n0,3\n0.5,4\n").unwrap();
        let got = read_columns(&file("event.csv", event), &["u"], Time::Required).unwrap();
        assert_eq!(got.data, plain.data);
        // Without a time column asked for, numpy's header names the others only; `t` is not needed.
        let got = read_columns(&file("no_t.csv", "# run 3\n# u,y\n1,2\n3,4\n"), &["u", "y"], Time::IfPresent).unwrap();
        assert_eq!(got.data, [[1.0, 3.0], [2.0, 4.0]]);
        let e = read_columns(&file("none.csv", "\n"), &["u", "y"], Time::IfPresent).unwrap_err();
        assert!(e.0.ends_with("none.csv: empty file (a header line naming u,y is needed)"), "{}", e.0);
        // The header's own line in its messages.
        let e = read_columns(&file("twice.csv", "# run 3\n\nt,u,u\n0,1,2\n"), &["u"], Time::Required).unwrap_err();
        assert!(e
            .0
            .ends_with("twice.csv:3: column 'u' named twice in the header (fields 2 and 3): which one is meant?"));
        // Rows where the header should be: no header, or one left in a comment without all the columns.
        for (name, text, line) in [("bare.csv", "0,1\n0.5,2\n", 1), ("hidden.csv", "# run 3\n# t\n0,1\n", 3)] {
            let e = read_columns(&file(name, text), &["u"], Time::Required).unwrap_err();
            let want = format!(
                "{name}:{line}: numbers where the header should be (found: 0,1): the first line, blank lines and '#' \
                 comments aside, must name the columns t,u"
            );
            assert!(e.0.ends_with(&want), "{}", e.0);
        }
    }

    /// What a spreadsheet writes reads as the plain file does: a byte-order mark before the header, quoted names and
    /// numbers, CRLF line ends; and so does what numpy's `savetxt(..., delimiter=',', header='t,u,y')` writes: the
    /// header after `# `, the numbers in exponent form.
    #[test]
    fn a_spreadsheets_export_reads_as_the_plain_file() {
        let plain = read_columns(&file("plain.csv", "t,u,y\n0,1,2\n0.5,3,4\n"), &["u", "y"], Time::Required).unwrap();
        let numpy = "# t,u,y\n0.0e+00,1.0e+00,2.0e+00\n5.0e-01,3.0e+00,4.0e+00\n";
        for (name, text) in [
            ("bom.csv", "\u{feff}t,u,y\n0,1,2\n0.5,3,4\n"),
            ("quoted.csv", "\u{feff}\"t\",\"u\",\"y\"\r\n\"0\",\"1\",\"2\"\r\n\"0.5\",\"3\",\"4\"\r\n"),
            ("numpy.csv", numpy),
        ] {
            let got = read_columns(&file(name, text), &["u", "y"], Time::Required).unwrap();
            assert_eq!((&got.data, got.sample_period_s), (&plain.data, plain.sample_period_s), "{name}");
        }
    }

    /// Progress counts the bytes parsed against the file's length: the header's (and the comments' before it) on
    /// opening, each block's as it is read, the whole file at the end.
    #[test]
    fn progress_counts_the_bytes_parsed() {
        // Without and with comments before the header, more of them than one read holds.
        for notes in [String::new(), "# logger 7, run 3\n".repeat(5_000)] {
            let text = notes.clone() + &rows(500);
            let path = file("progress.csv", &text);
            let mut r = Reader::open_in(&path, &["u"], &[], Time::Required, TINY).unwrap();
            let len = text.len() as u64;
            assert_eq!(r.progress(), ((notes.len() + "t, u ,y,extra\n".len()) as u64, len));
            let mut last = r.progress().0;
            while r.next_block().unwrap().is_some() {
                let (done, of) = r.progress();
                assert!(done > last && done <= len && of == len, "{done} of {of}, after {last}");
                last = done;
            }
            assert_eq!(r.progress(), (len, len));
        }
    }

    /// A header without a column asked for says so, as written; it names another separator only when the header is
    /// one field that holds the column when split by it (Excel in a locale with a decimal comma writes ';'), not for a
    /// single name, nor for a ';' inside one of several fields, nor for a line of words without the column.
    #[test]
    fn a_missing_column_names_another_separator_only_when_it_is_the_reason() {
        let missing = |name: &str, header: &str| {
            read_columns(&file(name, format!("{header}\n1\n")), &["u", "y"], Time::IfPresent).unwrap_err().0
        };
        let note = ": its fields are separated by";
        assert!(missing("semi.csv", "t;u;y").ends_with(
            "(found: t;u;y): its fields are separated by ';'; this reads commas, and '.' as the decimal point"
        ));
        assert!(missing("tabs.csv", "t\tu\ty").contains(": its fields are separated by tabs;"));
        // numpy's `savetxt` without `delimiter=','`: its header too after `# `.
        assert!(missing("spaces.csv", "# t u y").ends_with(
            "(found: # t u y): its fields are separated by spaces; \
             this reads commas, and '.' as the decimal point"
        ));
        // ... also with its rows, and after a comment of its own.
        let e = missing("numpy.csv", "# run 3\n# t u y\n0.0e+00 1.0e+00 2.0e+00");
        assert!(
            e.contains("numpy.csv:2: no column 'u' in the header (found: # t u y): its fields are separated by spaces")
        );
        // A comment naming the columns with spaces before a header naming them with commas is only a comment.
        let text = "# columns: t u y\nt,u,y\n0,1,2\n0.5,3,4\n";
        assert!(read_columns(&file("noted.csv", text), &["u", "y"], Time::IfPresent).is_ok());
        // A line of words without the columns is not a header of another separator.
        let e = missing("words.csv", "time volts microns");
        assert!(e.ends_with("words.csv:1: no column 'u' in the header (found: time volts microns)"), "{e}");
        // Nor a comment: it is skipped, and the next line is the header, here with ';'.
        let e = missing("comment.csv", "# logger 7, run 3\nt;u;y");
        assert!(
            e.contains("comment.csv:2: no column 'u' in the header (found: t;u;y): its fields are separated by ';'")
        );
        for (name, header) in [("one.csv", "time"), ("inside.csv", "u;v,t")] {
            let e = missing(name, header);
            assert!(e.contains("1: no column '") && !e.contains(note), "{e}");
        }
    }

    /// A column's unit in its name (`y [um]`, `u (V)`, DIN 1313's `t / s`; numpy's header too) is read when it is the
    /// one the column is read in, scaled when it is another of its quantity (`y [nm]`, `t [ms]`, `u (mV)`), and
    /// refused, named, otherwise: a reading in nm read as um would be a stage a thousand times larger. A header that
    /// is not UTF-8 but text is read as Latin-1 (a Windows logger's `\xb5m`).
    #[test]
    fn a_unit_in_a_columns_name_is_read_when_it_is_the_columns() {
        let plain = read_columns(&file("plain.csv", "t,u,y\n0,1,2\n0.5,3,4\n"), &["u", "y"], Time::Required).unwrap();
        let read = |header: &[u8]| {
            let text = [header, b"\n0,1,2\n0.5,3,4\n"].concat();
            read_columns(&file("units.csv", text), &["u", "y"], Time::Required).map(|c| (c.data, c.sample_period_s))
        };
        for header in [
            &b"t [s],u [V],y [um]"[..],
            b"t(s), u (V) ,y (\xc2\xb5m)",
            b"\"t / s\",\"u/V\",\"y / \xce\xbcm\"",
            b"# t [s],u [V],y [um]",
            b"t,u [V],y [\xb5m]",
        ] {
            let got = read(header).unwrap_or_else(|e| panic!("{}: {}", String::from_utf8_lossy(header), e.0));
            assert_eq!(got, (plain.data.clone(), plain.sample_period_s), "{}", String::from_utf8_lossy(header));
        }
        // A column not read has what name it likes.
        let text = b"t,u,y,temp [\xb0C]\n0,1,2,20\n0.5,3,4,21\n";
        let got = read_columns(&file("temp.csv", text), &["u", "y"], Time::Required).unwrap();
        assert_eq!((got.data, got.sample_period_s), (plain.data.clone(), plain.sample_period_s));
        // Another unit of the quantity, scaled: to the last bit where the scaled value is exact in binary.
        let scaled = |header: &[u8], rows: &str| {
            let text = [header, rows.as_bytes()].concat();
            read_columns(&file("scaled.csv", text), &["u", "y"], Time::Required).map(|c| (c.data, c.sample_period_s))
        };
        for header in [&b"t [ms],u (mV),y [nm]"[..], b"t / \xb5s,u/mV,y / nm", b"t [\xce\xbcs],u [mV],y [nm]"] {
            let micro = header.starts_with(b"t [\xce") || header.contains(&0xb5);
            let rows = if micro { "\n0,1000,2000\n500000,3000,4000\n" } else { "\n0,1000,2000\n500,3000,4000\n" };
            let got = scaled(header, rows).unwrap_or_else(|e| panic!("{}: {}", String::from_utf8_lossy(header), e.0));
            assert_eq!(got, (plain.data.clone(), plain.sample_period_s), "{}", String::from_utf8_lossy(header));
        }
        let (data, _) = scaled(b"t,u,y [mm]", "\n0,1,0.5\n0.5,3,0.25\n").unwrap();
        assert_eq!(data[1], [500.0, 250.0]);
        // The decimal's point moved: the double a file in um or s gives, to the last bit (`1234.56 / 1000` is not).
        let (data, period) = scaled(b"t [ms],u,y [nm]", "\n3999.8,1,1234.56\n3999.9,3,-0.7\n").unwrap();
        assert_eq!(data[1], [1.23456, -0.0007]);
        assert_eq!(data[2], [3.9998, 3.9999]);
        assert_eq!(period, Some(3.9999 - 3.9998));
        assert_ne!(1234.56 / 1e3, 1.23456, "the division would have been another double");
        let (data, _) = scaled(b"t,u,y [nm]", "\n0,1,2.5e3\n0.5,3,-1E2\n").unwrap();
        assert_eq!(data[1], [2.5, -0.1]);
        // So is a field longer than the buffer the point is moved in (64 bytes).
        let long = format!("1234.{}", "0".repeat(70));
        let (data, _) = scaled(b"t,u,y [nm]", &format!("\n0,1,{long}\n0.5,3,{long}\n")).unwrap();
        assert_eq!(data[1], [1.234; 2]);
        // A value with an exponent of its own gains one rounding: 1.5e-6 m is 1.5 um to within an ulp.
        let (data, _) = scaled(b"t,u,y [m]", "\n0,1,1.5e-6\n0.5,3,-2.5e-7\n").unwrap();
        for (got, want) in data[1].iter().zip([1.5, -0.25]) {
            assert!((got - want).abs() <= f64::EPSILON * want.abs(), "{got} against {want}");
        }
        // Time scaled before its steps are checked: a step of 0.1 ms.
        let (_, period) = scaled(b"t [ms],u,y", "\n0,1,2\n0.1,3,4\n0.2,5,6\n").unwrap();
        assert!((period.unwrap() - 1e-4).abs() < 1e-18, "{period:?}");
        for (header, want) in [
            ("t,u,y [pm]", "units.csv:1: column 'y [pm]': y is read in um, nm, mm or m, not pm: scale the column"),
            ("t,u (kV),y", "units.csv:1: column 'u (kV)': u is read in V or mV, not kV"),
            ("t / min,u,y", "units.csv:1: column 't / min': t is read in s, ms or us, not min"),
            ("t,u,y [um],a0 [1/s^2],a1,b0", "units.csv:1: column 'a0 [1/s^2]': a0 is read as a plain number"),
        ] {
            let text = format!("{header}\n0,1,2,3,4,5\n");
            let e = read_columns_optional(&file("units.csv", &text), &["u", "y"], &["a0", "a1", "b0"], Time::Required)
                .unwrap_err();
            assert!(e.0.contains(want), "{header}: {}", e.0);
        }
        // A value that leaves f64's range once scaled is refused at its line, not read as infinity.
        let e = scaled(b"t,u,y [m]", "\n0,1,2\n0.5,3,1e303\n").unwrap_err();
        assert!(e.0.ends_with("scaled.csv:3: column 'y': 1e303 is too large in um"), "{}", e.0);
        // Not a unit: no name before it, nothing in it, or not closed.
        for header in ["t,u,[V]", "t,u,y []", "t,u,y [um"] {
            let e = read(header.as_bytes()).unwrap_err();
            assert!(e.0.contains("units.csv:1: no column 'y' in the header"), "{header}: {}", e.0);
        }
        // A spreadsheet's own file (here the start of an .xlsx, a zip) is not text in any encoding.
        let e = read(b"PK\x03\x04\x14\0\x06\0\x08\0\0\0!\0b\xee\x9dh^\x01").unwrap_err();
        assert!(
            e.0.ends_with("units.csv:1: the header is not text (is the file a spreadsheet's own, not its CSV export?)"),
            "{}",
            e.0
        );
    }

    /// `t` may be asked for like any column: it is then the one whose steps are checked, in its place in the output.
    #[test]
    fn time_asked_for_by_name_is_the_time_checked() {
        let text = "u,t\n5,0\n3,0.5\n8,1\n";
        let got = read_columns(&file("t_named.csv", text), &["t", "u"], Time::Required).unwrap();
        assert_eq!((got.data, got.sample_period_s), (vec![vec![0.0, 0.5, 1.0], vec![5.0, 3.0, 8.0]], Some(0.5)));
    }

    /// A column named twice, or part of a group of columns that go together (the truth's `a0, a1, b0`), is refused,
    /// not resolved by a guess.
    #[test]
    fn an_ambiguous_header_is_refused() {
        let e = read_columns(&file("twice.csv", "t,u,y,u\n0,1,2,3\n"), &["u", "y"], Time::Required).unwrap_err();
        assert!(
            e.0.ends_with("twice.csv:1: column 'u' named twice in the header (fields 2 and 4): which one is meant?"),
            "{}",
            e.0
        );
        let part = |header: &str| {
            let text = format!("{header}\n{}\n", vec!["1"; header.split(',').count()].join(","));
            read_columns_optional(&file("part.csv", &text), &["u"], &["a0", "a1", "b0"], Time::IfPresent)
        };
        let e = part("u,a0,b0").unwrap_err();
        assert!(e.0.ends_with("part.csv:1: columns a0, a1, b0 go together, the header has only a0, b0"), "{}", e.0);
        assert!(part("u,b0,a1,a0").is_ok() && part("u").is_ok() && part("u,x").is_ok());
    }
}
