//! `nanopos-sim decode`: a captured serial stream of the firmware's recording (`record on` / `record burst N`) into
//! the CSV `identify` reads (`t,u,y`).
//!
//! The capture may hold anything else the link carried (command replies, several recordings): only the chosen
//! recording's header, frames and end line are decoded, and the rest of the capture is read for the headers of the
//! recordings after it, which a note counts (decoding the first of two said nothing of the second). `t` counts from
//! the recording's first sample; `u` is the command in effect over the sample period (V) and `y` the probe reading at
//! its start (um), the convention of `simulate` and of the pipeline.
//!
//! **Damage.** A frame whose checksum fails, and a gap between frames (lines lost in the capture), are errors that
//! name the capture's line: `identify` needs uniformly sampled data, and a hole must not be bridged silently. With
//! `--segments` nothing is refused and nothing good is thrown away: damaged frames are skipped (each reported), and
//! every gap-free run of samples goes to its own file, `OUT` with `-1`, `-2`, ... before the extension. `t` keeps
//! counting from the recording's first sample in every segment, so the segments keep their place in time (from the
//! first intact frame's, when the recording's first frames were damaged: the message names the board sample at
//! `t = 0`).
//!
//! **The board's tuning.** The recording's tuning lines ([`nanopos_id::record::write_tuning_line`]: every key's
//! values, exact) go to a TOML file beside the output, `OUT` with `.tuning.toml` for its extension, which `identify
//! --tuning` reads: a replay then runs the estimators as the board ran them. Their damage refuses nothing (the
//! samples are whole without them): the file is not written, and a note says why; so for a capture without them
//! (a firmware before them), and for a tuning changed while the recording ran (the file holds the tuning at its
//! start; the board's estimators whose tuning changed restarted there, which a replay does not).

use super::{clip, fail, io_reason, show, CliError, OutputFile};
use nanopos_id::control::EstimatorSet;
use nanopos_id::estimators::TuningKey;
use nanopos_id::record::{
    checked_body, decode_frame, read_tuning_line, RawSample, RecordHeader, TuningLine, TuningLineError, END_TAG,
    FRAME_SAMPLES, HEADER_TAG, HEADER_TAG_V1, TUNING_TAG,
};
use std::io::{BufRead, Write};
use std::path::Path;

/// A gap-free run of samples.
#[derive(Clone, Debug, PartialEq)]
pub struct Segment {
    /// Index of its first sample since the board started.
    pub first_index: u64,
    /// How many samples it has.
    pub len: u64,
}

/// What a decoded recording holds (its samples went to the files as they were read).
#[derive(Clone, Debug, PartialEq)]
pub struct Recording {
    /// The header.
    pub header: RecordHeader,
    /// The gap-free runs of samples, in order; exactly one unless damage was allowed ([`Damage::Skip`]).
    pub segments: Vec<Segment>,
    /// Every damaged or lost part, one line each, naming the capture's line (empty unless damage was allowed).
    pub damage: Vec<String>,
    /// The end line: `Some(overflowed)` when present.
    pub ended: Option<bool>,
    /// Whether the header and the end line carried their CRC (the format's `v2`; `v1` did not, and its header's
    /// rate and scalings are taken as they are).
    pub checked: bool,
    /// The TOML file the board's tuning at the recording's start went to (see the module's doc), if it did.
    pub tuning_file: Option<std::path::PathBuf>,
    /// Why it did not, that the tuning changed while the recording ran, and frames seen outside any recording
    /// before it: one line each.
    pub notes: Vec<String>,
}

impl Recording {
    /// Index of the recording's first decoded sample since the board started.
    pub fn first_index(&self) -> u64 {
        self.segments.first().map_or(0, |s| s.first_index)
    }

    /// Samples decoded, over all segments.
    pub fn len(&self) -> u64 {
        self.segments.iter().map(|s| s.len).sum()
    }

    /// Whether no sample was decoded.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// How every header line of the format begins, and its end line.
const HEADER_PREFIX: &str = "# nanopos-record ";

/// What to do with a damaged frame or a gap.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Damage {
    /// Refuse the capture, naming the line.
    Refuse,
    /// Skip the frame, start a new segment after a gap, and report each.
    Skip,
}

/// The fewest samples a segment needs to be written (`identify` needs at least a sample period).
pub const MIN_SAMPLES: usize = 2;

/// What frames outside any recording mean.
const ORPHANS: &str = "their header was lost or damaged in transfer, or the capture began after it (start the \
                       capture before `record on`)";

const SEGMENTS_HINT: &str = "(`decode --segments` keeps the undamaged parts, one file per gap-free run)";

fn header_value(name: &str, line_no: usize, line: &str, key: &str) -> Result<f64, CliError> {
    let word = line
        .split_ascii_whitespace()
        .find_map(|w| w.strip_prefix(key).and_then(|w| w.strip_prefix('=')))
        .ok_or_else(|| CliError(format!("{name}:{line_no}: recording header without {key}=")))?;
    word.parse::<f64>()
        .ok()
        .filter(|x| x.is_finite())
        .ok_or_else(|| CliError(format!("{name}:{line_no}: {key}={}: not a number", clip(word, 40))))
}

fn parse_header(name: &str, line_no: usize, line: &str) -> Result<RecordHeader, CliError> {
    let v = |key| header_value(name, line_no, line, key);
    let delay = v("delay")?;
    // A float cast would quietly make 300 of it 255 and 2.5 of it 2: a misaligned replay.
    if !(delay.fract() == 0.0 && (0.0..=u8::MAX as f64).contains(&delay)) {
        return fail(format!("{name}:{line_no}: delay={}: not a whole number of samples from 0 to 255", show(delay)));
    }
    let header = RecordHeader {
        rate_hz: v("rate_hz")?,
        delay: delay as u8,
        u_v_per_code: v("u_v_per_code")?,
        u_v_offset: v("u_v_offset")?,
        y_um_per_code: v("y_um_per_code")?,
        y_um_offset: v("y_um_offset")?,
    };
    // A negative scaling is an inverting front end; a zero one would make every sample read the same.
    let refused = [
        ("rate_hz", header.rate_hz, header.rate_hz <= 0.0),
        ("u_v_per_code", header.u_v_per_code, header.u_v_per_code == 0.0),
        ("y_um_per_code", header.y_um_per_code, header.y_um_per_code == 0.0),
    ];
    if let Some((key, value, _)) = refused.into_iter().find(|&(_, _, bad)| bad) {
        return fail(format!(
            "{name}:{line_no}: {key}={}: a recording header needs a positive rate and scalings other than 0",
            show(value)
        ));
    }
    Ok(header)
}

impl Recording {
    /// A damaged or lost part, `msg`: an error, or with [`Damage::Skip`] a note in [`Recording::damage`].
    fn refuse_or_skip(&mut self, damage: Damage, msg: String) -> Result<(), CliError> {
        match damage {
            Damage::Refuse => fail(format!("{msg} {SEGMENTS_HINT}")),
            Damage::Skip => {
                self.damage.push(msg);
                Ok(())
            }
        }
    }
}

/// Why recording `which` (`r`, with the end line's count `end_samples`; the capture `lines` long) gave no run of
/// [`MIN_SAMPLES`] or more samples to write: no frame came (the capture ended first, or the recording was stopped
/// before its first sample), every frame was damaged (with `--segments`, which skips them), or the runs between the
/// gaps are single samples.
fn no_run(name: &str, which: usize, r: &Recording, end_samples: Option<u64>, lines: usize) -> String {
    if !r.segments.is_empty() {
        return format!("{name}: recording {which} holds no run of {MIN_SAMPLES} or more samples");
    }
    match (r.ended, end_samples, r.damage.len()) {
        (Some(_), Some(0), _) => format!(
            "{name}: recording {which} is empty: its end line counts 0 samples (stopped before its first sample)"
        ),
        (_, _, 0) if r.ended.is_none() => format!(
            "{name}: recording {which} has no frame: the capture ends at line {lines}, before its first (stopped \
             before the recording's frames came?)"
        ),
        (_, _, 0) => {
            format!("{name}: recording {which} has no frame before its end line (its frames lost in the capture)")
        }
        (_, _, n) => format!(
            "{name}: recording {which} has no intact frame: {} of it damaged in transfer, the first: {}",
            super::count(n as u64, "line", "lines"),
            r.damage[0]
        ),
    }
}

/// Where segment `k` (1-based) of a decode into `out` goes: `run.csv` -> `run-2.csv`.
pub fn segment_path(out: &Path, k: usize) -> std::path::PathBuf {
    let stem = out.file_stem().map_or_else(String::new, |s| s.to_string_lossy().into_owned());
    let name = match out.extension() {
        Some(ext) => format!("{stem}-{k}.{}", ext.to_string_lossy()),
        None => format!("{stem}-{k}"),
    };
    out.with_file_name(name)
}

/// Files numbered after the `written` segment files of a decode into `out` that are already there (`run-4.csv`,
/// `run-5.csv`, ... after three): left from an earlier decode of another capture, which a `run-*.csv` would take for
/// this one's (up to the first number that is not there). Left as they are; `decode` says so.
pub fn stale_segments(out: &Path, written: usize) -> Vec<std::path::PathBuf> {
    (written + 1..).map(|k| segment_path(out, k)).take_while(|p| p.exists()).collect()
}

/// Decode recording `which` of `input` into `out` (with [`Damage::Skip`], into one file per segment of 2 or more
/// samples, numbered from 1 in time order by [`segment_path`]; a lone sample between two gaps is not written);
/// returns the recording and, for each of its segments, the file it went to (`None`: too short to write).
///
/// The capture is read a line at a time and each frame's samples written as they come: what is held is a line and
/// the few samples of a segment too short yet to have a file, whatever the length of the capture (an hour of
/// continuous recording is about 200 MB). The files are written under temporary names and moved into place only
/// once the whole recording decoded: a capture refused half way leaves nothing behind.
pub fn run(
    input: &Path,
    out: &Path,
    which: usize,
    damage: Damage,
) -> Result<(Recording, Vec<Option<std::path::PathBuf>>), CliError> {
    let name = input.display().to_string();
    if which == 0 {
        return fail("--recording 0: recordings are counted from 1 (the capture's first is 1)");
    }
    match damage {
        Damage::Skip if std::fs::metadata(out).is_ok_and(|m| !m.is_file()) => {
            return fail(format!(
                "--out {}: not a file name: --segments writes one file per run, named after it (run.csv -> \
                 run-1.csv, run-2.csv, ...)",
                out.display()
            ))
        }
        // Each segment's file is checked when it is made (with `--segments` no file takes the name `out`).
        Damage::Skip => {}
        Damage::Refuse => super::check_distinct(&[("--input", input)], &[("--out", out)])?,
    }
    let cannot_read = |e: std::io::Error| CliError(format!("{name}: cannot read: {}", io_reason(&e)));
    let mut reader = std::io::BufReader::with_capacity(1 << 20, super::open_input(input)?);
    // The chosen recording, once its header is read, and where its samples go.
    let (mut found, mut chosen): (usize, Option<(Recording, Sink)>) = (0, None);
    let mut frame = [RawSample::default(); FRAME_SAMPLES];
    let mut bytes = Vec::new();
    // The end line's count of the samples recorded, when it has one.
    let mut end_samples = None;
    let mut tuning = TuningLines::default();
    // Between a recording's header and its end line; and the first intact frame seen outside any (before the
    // chosen recording): its header was lost, or the capture began after it.
    let (mut inside, mut orphan) = (false, None);
    // Past the chosen recording: the rest of the capture is only searched for the recordings after it.
    let mut done = false;
    // The capture's lines read, for the message of a capture that ends before the chosen recording's frames.
    let mut lines = 0;
    // The first line with a header after something else (a terminal's timestamp): where, and what comes first.
    let mut prefixed: Option<(usize, String)> = None;
    for line_no in 1.. {
        bytes.clear();
        if reader.read_until(b'\n', &mut bytes).map_err(cannot_read)? == 0 {
            break;
        }
        lines = line_no;
        if line_no == 1 && crate::csv::utf16(&bytes) {
            return fail(format!(
                "{name}: UTF-16 text (its first bytes say so: a redirection in Windows PowerShell writes it): decode \
                 reads the serial stream's bytes as they came; capture them to a file as they are"
            ));
        }
        // Captures can hold noise from before the link settled: decode what is text, the frames carry their
        // checksums.
        let text = String::from_utf8_lossy(&bytes);
        let line = text.strip_suffix('\n').unwrap_or(&text).trim_end_matches('\r');
        // A byte-order mark an editor saved the capture with (as a spreadsheet's CSV has, see `csv`).
        let line = if line_no == 1 { line.strip_prefix('\u{feff}').unwrap_or(line) } else { line };
        // A header: of this format (v2, checked), of the first (v1), or a line that starts as one and is neither
        // (its version damaged in transfer, or a later format's): counted all the same, so that `--recording N`
        // keeps its number for the recordings after it.
        let version = [(HEADER_TAG, Some(true)), (HEADER_TAG_V1, Some(false)), (HEADER_PREFIX, None)]
            .into_iter()
            .find(|(tag, _)| line.starts_with(tag) && !line.starts_with(END_TAG));
        // Only until a header is found: the note is for a capture without one (not a search of every line).
        if found == 0 && version.is_none() && prefixed.is_none() {
            if let Some(at) = line.find(HEADER_PREFIX).filter(|&at| at > 0) {
                prefixed = Some((line_no, line[..at].to_string()));
            }
        }
        if done || (version.is_some() && chosen.is_some()) {
            (found, done) = (found + version.is_some() as usize, true);
            continue;
        }
        if let Some((_, version)) = version {
            (found, inside) = (found + 1, true);
            if found == which {
                let Some(checked) = version else {
                    return fail(format!(
                        "{name}:{line_no}: '{}': a recording header of no version this decoder reads (damaged in \
                         transfer, or from a later firmware)",
                        clip(line, 40)
                    ));
                };
                // Its rate and scalings apply to every sample: a header that lost or changed a character is refused,
                // with `--segments` too (nothing could be decoded with it).
                let body = intact(line, checked).ok_or_else(|| {
                    CliError(format!(
                        "{name}:{line_no}: recording header damaged in transfer (its checksum does not match): its \
                         rate and scalings cannot be trusted; record again"
                    ))
                })?;
                let header = parse_header(&name, line_no, body)?;
                let rec = Recording {
                    header,
                    segments: Vec::new(),
                    damage: Vec::new(),
                    ended: None,
                    checked,
                    tuning_file: None,
                    notes: Vec::new(),
                };
                chosen = Some((rec, Sink::new(input, out, damage, header)));
            }
            continue;
        }
        let Some((r, sink)) = chosen.as_mut() else {
            if line.starts_with(END_TAG) {
                inside = false;
            } else if !inside && orphan.is_none() && decode_frame(line.as_bytes(), &mut frame).is_ok() {
                orphan = Some(line_no);
            }
            continue;
        };
        if line.starts_with(END_TAG) {
            match intact(line, r.checked) {
                Some(body) => {
                    r.ended = Some(body.contains("overflow=1"));
                    end_samples = body
                        .split_ascii_whitespace()
                        .find_map(|w| w.strip_prefix("samples="))
                        .and_then(|n| n.parse::<u64>().ok());
                }
                None => r.refuse_or_skip(
                    damage,
                    format!(
                        "{name}:{line_no}: the recording's end line damaged in transfer (its checksum does not \
                         match): whether the recording overflowed, and how many samples it had, are not known"
                    ),
                )?,
            }
            done = true;
            continue;
        }
        if line.starts_with(TUNING_TAG) {
            tuning.read(line, line_no, r, &name);
            continue;
        }
        if !line.starts_with('R') {
            continue;
        }
        let (index, n) = match decode_frame(line.as_bytes(), &mut frame) {
            Ok(decoded) => decoded,
            Err(e) => {
                r.refuse_or_skip(damage, format!("{name}:{line_no}: {e}"))?;
                continue;
            }
        };
        // The sample the current segment continues with, if there is one.
        let expected = r.segments.last().map(|s| s.first_index + s.len);
        match expected {
            Some(e) if index == e => r.segments.last_mut().expect("a last segment").len += n as u64,
            Some(e) if index < e => {
                r.refuse_or_skip(
                    damage,
                    format!(
                        "{name}:{line_no}: frame starts at sample {index}, before the expected {e} (a line repeated \
                         in the capture)"
                    ),
                )?;
                continue;
            }
            _ => {
                if let Some(e) = expected {
                    r.refuse_or_skip(
                        damage,
                        format!(
                            "{name}:{line_no}: frame starts at sample {index}, expected {e}: {} missing (lines lost \
                             in the capture)",
                            super::count(index - e, "sample", "samples")
                        ),
                    )?;
                }
                sink.start(index);
                r.segments.push(Segment { first_index: index, len: n as u64 });
            }
        }
        sink.push(&frame[..n])?;
    }
    // Frames lost at the recording's start or end leave no gap between frames; the end line's count shows them.
    if let (Some((r, _)), Some(recorded)) = (chosen.as_mut(), end_samples) {
        if let (Some(first), Some(last)) = (r.segments.first(), r.segments.last()) {
            let span = last.first_index + last.len - first.first_index;
            if span != recorded {
                let msg = format!(
                    "{name}: the end line counts {recorded} samples recorded, the frames span {span} (board samples \
                     {} to {}): frames lost at the recording's start or end",
                    first.first_index,
                    last.first_index + last.len
                );
                r.refuse_or_skip(damage, msg)?;
            }
        }
    }
    let (mut rec, sink) = match chosen {
        Some((r, s)) if r.segments.iter().any(|s| s.len >= MIN_SAMPLES as u64) => (r, s),
        Some((r, _)) => return fail(no_run(&name, which, &r, end_samples, lines)),
        None if found == 0 => {
            if let Some((l, prefix)) = prefixed {
                return fail(format!(
                    "{name}:{l}: the recording header comes after '{}': the capture's lines carry something before \
                     the board's (a terminal's timestamps?), which decode does not read: capture without it",
                    clip(&prefix, 40)
                ));
            }
            return fail(format!("{name}: no recording in the capture (no '{HEADER_PREFIX}' header line){}", {
                orphan.map_or(String::new(), |l| format!("; frames from line {l} on: {ORPHANS}"))
            }));
        }
        None => {
            return fail(format!("{name}: recording {which} asked for, the capture holds {found}{}", {
                orphan.map_or(String::new(), |l| format!(" and frames from line {l} outside any: {ORPHANS}"))
            }))
        }
    };
    if found > which {
        rec.notes.push(format!(
            "{name}: the capture holds {found} recordings; this is recording {which} (--recording {} decodes the \
             next)",
            which + 1
        ));
    }
    if let Some(l) = orphan {
        rec.notes.push(format!(
            "{name}:{l}: frames outside any recording before this one: {ORPHANS}, so this one may be numbered one \
             lower than the board's"
        ));
    }
    let tuning_file = tuning.file(&mut rec, input, out, damage)?;
    let (files, written) = sink.finish();
    // Every file is complete before any is moved into place.
    for file in files.into_iter().chain(tuning_file) {
        file.commit()?;
    }
    Ok((rec, written))
}

/// Where the board's tuning of a decode into `out` goes: `run.csv` -> `run.tuning.toml`.
pub fn tuning_path(out: &Path) -> std::path::PathBuf {
    out.with_extension("tuning.toml")
}

/// The chosen recording's tuning lines, as they come.
#[derive(Default)]
struct TuningLines {
    /// Every intact one, in the capture's order.
    lines: Vec<TuningLine>,
    /// One was damaged or of an unknown key (its note is in the recording's).
    bad: bool,
}

impl TuningLines {
    /// Take tuning line `line` (the capture's line `line_no`) of recording `r`.
    fn read(&mut self, line: &str, line_no: usize, r: &mut Recording, name: &str) {
        match read_tuning_line(line) {
            Ok(t) => self.lines.push(t),
            Err(e) => {
                self.bad = true;
                r.notes.push(match e {
                    TuningLineError::Damaged => {
                        format!("{name}:{line_no}: a tuning line damaged in transfer (its checksum does not match)")
                    }
                    TuningLineError::Unknown => format!(
                        "{name}:{line_no}: '{}': a tuning line of a key this decoder does not know (a later \
                         firmware's)",
                        clip(line, 40)
                    ),
                });
            }
        }
    }

    /// Which estimators the change of the tuning at board sample `at` restarted, as the board's console decides it
    /// ([`TuningKey::estimators`] of each key whose values at `at` differ from those before), in words.
    fn restarted_at(&self, at: u64) -> String {
        let last = |key: TuningKey, when: &dyn Fn(u64) -> bool| {
            self.lines.iter().rev().find(|l| l.key == key && when(l.at)).map(|l| l.values.map(f64::to_bits))
        };
        let set =
            EstimatorSet::restarted_by(TuningKey::ALL.into_iter().filter(
                |&key| matches!((last(key, &|t| t == at), last(key, &|t| t < at)), (Some(a), Some(b)) if a != b),
            ));
        let names: Vec<&str> = set.names().collect();
        match names.len() {
            0 => "no estimator's tuning changed".to_string(),
            4 => "every estimator restarted there".to_string(),
            _ => format!("{} restarted there", names.join(",")),
        }
    }

    /// The tuning file of `rec` decoded into `out`, to commit with the samples' files, when the recording carried
    /// every key intact: each key's last line in effect at the recording's first decoded sample. Else a note in
    /// `rec` says why there is none; and a change of the tuning inside the recording is noted with its sample.
    fn file(
        self,
        rec: &mut Recording,
        input: &Path,
        out: &Path,
        damage: Damage,
    ) -> Result<Option<OutputFile>, CliError> {
        let (first, end) = (rec.first_index(), rec.segments.last().map_or(0, |s| s.first_index + s.len));
        if let Some(at) = self.lines.iter().map(|l| l.at).filter(|&at| at > first && at < end).min() {
            rec.notes.push(format!(
                "the board's tuning changed at board sample {at} (t = {} s; a `tune` or `tuning` while recording: {}): \
                 the tuning file holds the tuning at the recording's start, and a replay of the samples from there on \
                 is not the board's",
                show((at - first) as f64 / rec.header.rate_hz),
                self.restarted_at(at)
            ));
        }
        let keys: Vec<(TuningKey, [f64; 5])> = TuningKey::ALL
            .into_iter()
            .filter_map(|key| self.lines.iter().rev().find(|l| l.key == key && l.at <= first).map(|l| (key, l.values)))
            .collect();
        let missing = TuningKey::ALL.len() - keys.len();
        let give = "identify replays the tuning it is given (--tuning), which must be the board's for its estimates";
        let why_not = if self.bad {
            Some(format!("the board's tuning is not written: {give}"))
        } else if self.lines.is_empty() {
            Some(format!("the recording carries no tuning (from a firmware before the tuning lines): {give}"))
        } else if missing > 0 {
            // Named: a key newer than the firmware that recorded (`spike_ratio`, say) is missing from every line.
            let names: Vec<String> = TuningKey::ALL
                .into_iter()
                .filter(|key| keys.iter().all(|(k, _)| k != key))
                .map(|key| key.to_string())
                .collect();
            Some(format!(
                "the board's tuning is not written: {missing} of its {} keys are missing at the recording's start \
                 ({}: lines lost in the capture, or a firmware from before the key): {give}",
                TuningKey::ALL.len(),
                names.join(", ")
            ))
        } else if std::fs::metadata(out).is_ok_and(|m| super::is_stream(&m)) && damage == Damage::Refuse {
            Some(format!("--out {} is not a file: the board's tuning is not written beside it", out.display()))
        } else {
            None
        };
        let path = tuning_path(out);
        if let Some(msg) = why_not {
            rec.notes.push(msg);
            if path.exists() {
                rec.notes
                    .push(format!("{} is from an earlier decode, not this capture: left as it was", path.display()));
            }
            return Ok(None);
        }
        super::check_distinct(&[("--input", input)], &[("the tuning file", &path)])?;
        let mut file = OutputFile::create(&path)?;
        let text = tuning_toml(&keys, &input.display().to_string());
        file.writer().write_all(text.as_bytes()).map_err(|e| file.write_error(e))?;
        rec.tuning_file = Some(path);
        Ok(Some(file))
    }
}

/// The TOML of `identify --tuning` (`crate::tuning`) holding every key of `keys` (in [`TuningKey::ALL`]'s order, its
/// sections'), values as Rust writes an `f64`: the shortest decimal that reads back to the same bits.
pub fn tuning_toml(keys: &[(TuningKey, [f64; 5])], source: &str) -> String {
    let mut text = format!(
        "# The board's estimator tuning at the start of its recording in {source} (nanopos-sim decode), exact.\n\
         # Replay with it: nanopos-sim identify --input <the decoded CSV> --tuning <this file>\n"
    );
    let mut section = "";
    for &(key, values) in keys {
        let (sec, name) = key.path();
        if sec != section {
            text.push_str(&format!("\n[{sec}]\n"));
            section = sec;
        }
        let whole = matches!(key, TuningKey::EkfSubsteps | TuningKey::EkfChangeSamples | TuningKey::SpikeRatio);
        let v: Vec<String> = values[..key.len()]
            .iter()
            .map(|v| if whole { format!("{}", *v as u64) } else { format!("{v:?}") })
            .collect();
        match key.len() {
            1 => text.push_str(&format!("{name} = {}\n", v[0])),
            _ => text.push_str(&format!("{name} = [{}]\n", v.join(", "))),
        }
    }
    text
}

/// A header or end line without its CRC if it is intact (`checked`: the format has one), or as it is (v1).
fn intact(line: &str, checked: bool) -> Option<&str> {
    if checked {
        checked_body(line)
    } else {
        Some(line)
    }
}

/// Where the chosen recording's samples go as they are decoded: a file per segment, made once the segment has
/// [`MIN_SAMPLES`] (its first samples held until then), rows `t,u,y` with `t` from the recording's first sample.
struct Sink<'a> {
    input: &'a Path,
    out: &'a Path,
    damage: Damage,
    header: RecordHeader,
    /// Index of the recording's first decoded sample (`t = 0`).
    origin: Option<u64>,
    /// Index of the next sample of the current segment.
    next: u64,
    /// The current segment's file, once it has one.
    file: Option<OutputFile>,
    /// The current segment's samples while it has too few for a file.
    held: Vec<RawSample>,
    /// The finished segments' files, to commit.
    done: Vec<OutputFile>,
    /// For each finished segment, the file it went to (`None`: too short).
    written: Vec<Option<std::path::PathBuf>>,
}

impl<'a> Sink<'a> {
    fn new(input: &'a Path, out: &'a Path, damage: Damage, header: RecordHeader) -> Self {
        Sink {
            input,
            out,
            damage,
            header,
            origin: None,
            next: 0,
            file: None,
            held: Vec::new(),
            done: Vec::new(),
            written: Vec::new(),
        }
    }

    /// A segment starts at sample `index` (the first one: the recording's `t = 0`).
    fn start(&mut self, index: u64) {
        if self.origin.is_some() {
            self.close();
        }
        self.origin.get_or_insert(index);
        self.next = index;
    }

    fn close(&mut self) {
        match self.file.take() {
            Some(file) => {
                self.written.push(Some(file.path().to_path_buf()));
                self.done.push(file);
            }
            None => self.written.push(None),
        }
        self.held.clear();
    }

    /// The current segment's next samples.
    fn push(&mut self, samples: &[RawSample]) -> Result<(), CliError> {
        if self.file.is_none() {
            self.held.extend_from_slice(samples);
            if self.held.len() < MIN_SAMPLES {
                return Ok(());
            }
            let path = match self.damage {
                Damage::Refuse => self.out.to_path_buf(),
                Damage::Skip => segment_path(self.out, self.done.len() + 1),
            };
            if self.damage == Damage::Skip {
                super::check_distinct(&[("--input", self.input)], &[("--out", &path)])?;
            }
            let mut file = OutputFile::create(&path)?;
            writeln!(file.writer(), "t,u,y").map_err(|e| file.write_error(e))?;
            self.file = Some(file);
            let held = std::mem::take(&mut self.held);
            return self.push(&held);
        }
        let (h, origin) = (self.header, self.origin.expect("a segment started"));
        let file = self.file.as_mut().expect("a file");
        let result = samples.iter().try_for_each(|s| {
            let (u, y) = h.physical(*s);
            let t = (self.next - origin) as f64 / h.rate_hz;
            self.next += 1;
            writeln!(file.writer(), "{t},{u},{y}")
        });
        result.map_err(|e| file.write_error(e))
    }

    /// The files to commit and, per segment, where it went.
    fn finish(mut self) -> (Vec<OutputFile>, Vec<Option<std::path::PathBuf>>) {
        if self.origin.is_some() {
            self.close();
        }
        (self.done, self.written)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nanopos_id::record::{encode_frame, write_checked_line, FRAME_MAX_BYTES};

    /// The tuning lines of the PRBS preset with `[ekf] r` at 2.2e-6.
    fn tuning_lines() -> Vec<Vec<u8>> {
        let mut t = nanopos_id::estimators::Tuning::of(nanopos_id::control::TuningPreset::Prbs);
        t.set(TuningKey::EkfR, &[2.2e-6]).unwrap();
        let mut text = String::new();
        nanopos_id::record::write_tuning_lines(&mut text, 1000, &t).unwrap();
        text.split_inclusive('\n').map(|l| l.as_bytes().to_vec()).collect()
    }

    /// A capture of `n` samples from board sample 1000 with replies around it, as lines: the header, `ok`, the
    /// tuning lines, the frames, the end line.
    fn capture(n: usize) -> Vec<Vec<u8>> {
        let mut h = nanopos_id::text::TextBuf::<256>::default();
        RecordHeader::EXAMPLE.write(&mut h).unwrap();
        let mut lines = vec![b"ok status samples=12\n".to_vec(), h.as_str().as_bytes().to_vec()];
        lines.push(b"ok record on\n".to_vec());
        lines.extend(tuning_lines());
        let samples: Vec<RawSample> =
            (0..n).map(|k| RawSample { u_code: 2000 + (k % 97) as u16, y_code: 30_000 + (k % 1013) as u16 }).collect();
        let mut buf = [0u8; FRAME_MAX_BYTES];
        for (i, chunk) in samples.chunks(FRAME_SAMPLES).enumerate() {
            let len = encode_frame(1000 + (i * FRAME_SAMPLES) as u64, chunk, &mut buf);
            lines.push(buf[..len].to_vec());
        }
        let mut end = nanopos_id::text::TextBuf::<80>::default();
        write_checked_line(&mut end, format_args!("{END_TAG} samples={n} overflow=0")).unwrap();
        lines.push(end.as_str().as_bytes().to_vec());
        lines
    }

    /// The board's tuning goes beside the output, or a note says why it does not: none in the capture, a damaged or
    /// lost tuning line; and a change of the tuning inside the recording is noted at its sample, the file holding
    /// the tuning at the start, wherever the change's lines come in the capture (before the first frame, too: the
    /// board writes its frames after its replies).
    #[test]
    fn the_boards_tuning_goes_beside_the_output_or_a_note_says_why_not() {
        let dir = tempfile::tempdir().unwrap();
        let (cap, out) = (dir.path().join("cap.txt"), dir.path().join("run.csv"));
        let decode = |lines: &[Vec<u8>]| {
            std::fs::write(&cap, lines.concat()).unwrap();
            let _ = std::fs::remove_file(tuning_path(&out));
            let (rec, _) = run(&cap, &out, 1, Damage::Refuse).unwrap();
            let written = tuning_path(&out).exists();
            assert_eq!(rec.tuning_file.is_some(), written);
            (rec.tuning_file.is_some(), rec.notes.join(" | "))
        };
        let good = capture(500);
        let (written, notes) = decode(&good);
        assert!(written && notes.is_empty(), "{notes}");
        let first = good.iter().position(|l| l.starts_with(TUNING_TAG.as_bytes())).unwrap();
        let n = TuningKey::ALL.len();
        // None: a firmware before the tuning lines.
        let mut none = good.clone();
        none.drain(first..first + n);
        let (written, notes) = decode(&none);
        assert!(!written && notes.contains("the recording carries no tuning"), "{notes}");
        // Not taken for this capture's: a tuning file an earlier decode left.
        std::fs::write(tuning_path(&out), "# another capture's\n").unwrap();
        std::fs::write(&cap, none.concat()).unwrap();
        let (rec, _) = run(&cap, &out, 1, Damage::Refuse).unwrap();
        assert!(rec.notes[1].ends_with("run.tuning.toml is from an earlier decode, not this capture: left as it was"));
        // One lost.
        let mut lost = good.clone();
        lost.remove(first + 7);
        let (written, notes) = decode(&lost);
        assert!(!written && notes.contains("1 of its 19 keys are missing at the recording's start"), "{notes}");
        assert!(notes.contains("([ekf] q: lines lost in the capture, or a firmware from before the key)"), "{notes}");
        // Without `spike_ratio`'s line, as from a firmware before `tune spike_ratio`: a lost line cannot be told
        // from it, so no file (its ratio may not have been the default), and the key named.
        let mut older = good.clone();
        let spike_line = first + TuningKey::ALL.iter().position(|&k| k == TuningKey::SpikeRatio).unwrap();
        assert!(older.remove(spike_line).starts_with(b"# nanopos-tuning at=1000 spike_ratio 4040"));
        let (written, notes) = decode(&older);
        assert!(!written && notes.contains("1 of its 19 keys are missing") && notes.contains("(spike_ratio: "));
        // One damaged.
        let mut damaged = good.clone();
        damaged[first + 3][20] ^= 1;
        let (written, notes) = decode(&damaged);
        assert!(!written && notes.contains(&format!("cap.txt:{}: a tuning line damaged", first + 4)), "{notes}");
        // Changed while recording (a `tune`), its lines after the first frame or before it: the file holds the
        // tuning at the start, the note the change's sample. A change after the recording's end is none of it.
        let frame = good.iter().position(|l| l.starts_with(b"R")).unwrap();
        let r_at = |at: u64| {
            let mut l = nanopos_id::text::TextBuf::<256>::default();
            nanopos_id::record::write_tuning_line(&mut l, at, TuningKey::EkfR, &[9e-6]).unwrap();
            l.as_str().as_bytes().to_vec()
        };
        for (at, place) in [(1096, frame + 2), (1003, frame), (1500, good.len() - 1)] {
            let mut changed = good.clone();
            changed.insert(place, r_at(at));
            let (written, notes) = decode(&changed);
            let t = (at - 1000) as f64 / 1e4;
            let note = format!(
                "the board's tuning changed at board sample {at} (t = {t} s; a `tune` or `tuning` while \
                 recording: ekf,hekf restarted there)"
            );
            assert!(written && notes.contains(&note) == (at < 1500), "{at}: {notes}");
            assert!(std::fs::read_to_string(tuning_path(&out)).unwrap().contains("\nr = 2.2e-6\n"), "{at}");
        }
        // What the change restarted, as the console decides it: by the keys whose values changed.
        for (key, values, said) in [
            (TuningKey::SpikeRatio, &[8.0][..], "no estimator's tuning changed"),
            (TuningKey::Initial, &[6e5, 70.0, 6e6][..], "every estimator restarted there"),
            (TuningKey::Prefilter, &[100.0, 500.0, 0.1][..], "rls restarted there"),
        ] {
            let mut line = nanopos_id::text::TextBuf::<256>::default();
            nanopos_id::record::write_tuning_line(&mut line, 1096, key, values).unwrap();
            let mut changed = good.clone();
            changed.insert(frame + 2, line.as_str().as_bytes().to_vec());
            let (written, notes) = decode(&changed);
            assert!(written && notes.contains(&format!("while recording: {said})")), "{key:?}: {notes}");
        }
    }

    /// The shortest recording written has [`MIN_SAMPLES`] (a sample period for `identify`); one sample is refused.
    #[test]
    fn a_recording_of_two_samples_is_written_and_one_sample_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (cap, out) = (dir.path().join("cap.txt"), dir.path().join("run.csv"));
        std::fs::write(&cap, capture(2).concat()).unwrap();
        let (rec, written) = run(&cap, &out, 1, Damage::Refuse).unwrap();
        assert_eq!((rec.len(), written), (2, vec![Some(out.clone())]));
        let text = std::fs::read_to_string(&out).unwrap();
        let t: Vec<&str> = text.lines().map(|row| row.split(',').next().unwrap()).collect();
        assert_eq!(t, ["t", "0", "0.0001"]);
        std::fs::write(&cap, capture(1).concat()).unwrap();
        let e = run(&cap, &out, 1, Damage::Refuse).unwrap_err().0;
        assert!(e.ends_with("cap.txt: recording 1 holds no run of 2 or more samples"), "{e}");
    }

    /// Frames outside any recording (a header lost or damaged beyond recognition, or a capture begun after it) are
    /// said: in the refusal when no recording is left to decode, in a note when the one decoded may be numbered one
    /// lower than the board's.
    #[test]
    fn frames_outside_any_recording_are_said() {
        let dir = tempfile::tempdir().unwrap();
        let (cap, out) = (dir.path().join("cap.txt"), dir.path().join("run.csv"));
        let good = capture(200);
        let header = good.iter().position(|l| l.starts_with(HEADER_TAG.as_bytes())).unwrap();
        let frame = good.iter().position(|l| l.starts_with(b"R")).unwrap();
        // Begun after the header.
        std::fs::write(&cap, good[header + 1..].concat()).unwrap();
        let e = run(&cap, &out, 1, Damage::Refuse).unwrap_err().0;
        let lost =
            format!("no '{HEADER_PREFIX}' header line); frames from line {} on: their header was lost", frame - header);
        assert!(e.contains(&lost), "{e}");
        // The first of two recordings lost its header: the second is recording 1 in the capture, and said to be.
        let mut two = good.clone();
        two[header] = b"# nanopos-recorX v2 rate_hz=10000\n".to_vec();
        two.extend(good.iter().cloned());
        std::fs::write(&cap, two.concat()).unwrap();
        let (rec, _) = run(&cap, &out, 1, Damage::Refuse).unwrap();
        assert_eq!(rec.len(), 200);
        assert!(!rec.is_empty() && Recording { segments: Vec::new(), ..rec.clone() }.is_empty());
        let note = format!("cap.txt:{}: frames outside any recording before this one", frame + 1);
        assert!(
            rec.notes.iter().any(|n| n.contains(&note) && n.ends_with("numbered one lower than the board's")),
            "{:?}",
            rec.notes
        );
        let e = run(&cap, &out, 2, Damage::Refuse).unwrap_err().0;
        assert!(
            e.contains(&format!(
                "recording 2 asked for, the capture holds 1 and frames from line {} outside any",
                frame + 1
            )),
            "{e}"
        );
        // Intact, no such note.
        std::fs::write(&cap, good.concat()).unwrap();
        let (rec, _) = run(&cap, &out, 1, Damage::Refuse).unwrap();
        assert!(rec.notes.is_empty(), "{:?}", rec.notes);
    }

    /// A capture mangled at random (bytes changed, lines lost, repeated, swapped, cut short, noise added) never makes
    /// `decode` panic or leave a temporary file: refusing, it writes nothing; decoding, each file holds its segment's
    /// samples, each the intact capture's at that board sample, a sample period apart.
    #[test]
    fn a_mangled_capture_is_decoded_or_refused_never_a_panic() {
        let dir = tempfile::tempdir().unwrap();
        let good = capture(2000);
        let (input, whole) = (dir.path().join("good.txt"), dir.path().join("whole.csv"));
        std::fs::write(&input, good.concat()).unwrap();
        run(&input, &whole, 1, Damage::Refuse).unwrap();
        // The tuning file without its comments (which name the capture).
        let settings = |path: &Path| {
            let text = std::fs::read_to_string(path).unwrap();
            text.lines().filter(|l| !l.starts_with('#')).collect::<Vec<_>>().join("\n")
        };
        let tuning = settings(&tuning_path(&whole));
        let whole = std::fs::read_to_string(&whole).unwrap();
        // `u,y` of board sample 1000 + k.
        let intact: Vec<&str> = whole.lines().skip(1).map(|r| r.split_once(',').unwrap().1).collect();
        let mut next = nanopos_id::xorshift64(0x5DEE_CE66_D1CE_4E5B);
        let (mut refused, mut segmented) = (0, 0);
        const CASES: usize = 300;
        for case in 0..CASES {
            let mut lines = good.clone();
            for _ in 0..1 + next() % 4 {
                let at = (next() % lines.len() as u64) as usize;
                match next() % 6 {
                    0 => {
                        let line = &mut lines[at];
                        let k = (next() % line.len() as u64) as usize;
                        line[k] = (next() % 256) as u8;
                    }
                    1 => drop(lines.remove(at)),
                    2 => {
                        let line = lines[at].clone();
                        lines.insert(at, line);
                    }
                    3 => {
                        let other = (next() % lines.len() as u64) as usize;
                        lines.swap(at, other);
                    }
                    4 => lines[at].truncate((next() % 40) as usize),
                    _ => lines.insert(at, (0..next() % 60).map(|_| (next() % 256) as u8).collect()),
                }
            }
            let dir = tempfile::tempdir().unwrap();
            let (cap, out) = (dir.path().join("cap.txt"), dir.path().join("run.csv"));
            std::fs::write(&cap, lines.concat()).unwrap();
            for damage in [Damage::Refuse, Damage::Skip] {
                let result = run(&cap, &out, 1, damage);
                let mut names: Vec<String> = std::fs::read_dir(dir.path())
                    .unwrap()
                    .map(|e| e.unwrap().file_name().into_string().unwrap())
                    .collect();
                names.sort();
                match result {
                    Err(e) => {
                        assert!(!e.0.is_empty() && !e.0.contains('\n'), "case {case}: {e:?}");
                        assert_eq!(names, ["cap.txt"], "case {case} {damage:?}: refused, and left files: {e:?}");
                        refused += 1;
                    }
                    Ok((rec, written)) => {
                        assert_eq!(written.len(), rec.segments.len(), "case {case}");
                        for (seg, path) in rec.segments.iter().zip(&written) {
                            let Some(path) = path else { continue };
                            let text = std::fs::read_to_string(path).unwrap();
                            let got: Vec<&str> = text.lines().collect();
                            assert_eq!(got[0], "t,u,y");
                            assert_eq!(got.len() as u64, seg.len + 1, "case {case}: {}", path.display());
                            let mut last_t: Option<f64> = None;
                            for (j, row) in got[1..].iter().enumerate() {
                                let (t, uy) = row.split_once(',').unwrap();
                                let k = (seg.first_index - 1000) as usize + j;
                                assert_eq!(Some(&uy), intact.get(k), "case {case}: board sample {}", 1000 + k);
                                let t: f64 = t.parse().unwrap();
                                if let Some(last) = last_t {
                                    assert!((t - last - 1e-4).abs() < 1e-9, "case {case}: t {last} then {t}");
                                }
                                last_t = Some(t);
                            }
                        }
                        // A tuning file holds the board's tuning exactly, or there is none and a note says why.
                        match &rec.tuning_file {
                            Some(path) => assert_eq!(settings(path), tuning, "case {case}"),
                            None => assert!(!rec.notes.is_empty(), "case {case}"),
                        }
                        segmented += (rec.segments.len() > 1) as usize;
                        for name in names.iter().filter(|n| *n != "cap.txt") {
                            std::fs::remove_file(dir.path().join(name)).unwrap();
                        }
                    }
                }
            }
        }
        eprintln!("mangled captures: {refused} refusals, {segmented} decodes into several segments (of {})", 2 * CASES);
        assert!(tuning.contains("\nr = 2.2e-6\n"), "{tuning}");
        assert!(refused > 50 && segmented > 20, "the cases reach both ways: {refused} {segmented}");
    }
}
