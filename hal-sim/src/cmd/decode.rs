//! `nanopos-sim decode`: a captured serial stream of the firmware's recording (`record on` / `record burst N`) into
//! the CSV `identify` reads (`t,u,y`).
//!
//! The capture may hold anything else the link carried (command replies, several recordings): only the chosen
//! recording's header, frames and end line are read. `t` counts from the recording's first sample; `u` is the
//! command in effect over the sample period (V) and `y` the probe reading at its start (um), the convention of
//! `simulate` and of the pipeline.
//!
//! **Damage.** A frame whose checksum fails, and a gap between frames (lines lost in the capture), are errors that
//! name the capture's line: `identify` needs uniformly sampled data, and a hole must not be bridged silently. With
//! `--segments` nothing is refused and nothing good is thrown away: damaged frames are skipped (each reported), and
//! every gap-free run of samples goes to its own file, `OUT` with `-1`, `-2`, ... before the extension. `t` keeps
//! counting from the recording's first sample in every segment, so the segments keep their place in time.

use super::{clip, fail, io_reason, show, CliError, OutputFile};
use nanopos_id::record::{decode_frame, RawSample, RecordHeader, END_TAG, FRAME_SAMPLES, HEADER_TAG};
use std::io::Write;
use std::path::Path;

/// A gap-free run of samples.
#[derive(Clone, Debug, PartialEq)]
pub struct Segment {
    /// Index of its first sample since the board started.
    pub first_index: u64,
    /// The samples.
    pub samples: Vec<RawSample>,
}

/// What a decoded recording holds.
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
}

impl Recording {
    /// Index of the recording's first decoded sample since the board started.
    pub fn first_index(&self) -> u64 {
        self.segments.first().map_or(0, |s| s.first_index)
    }

    /// Samples decoded, over all segments.
    pub fn len(&self) -> usize {
        self.segments.iter().map(|s| s.samples.len()).sum()
    }

    /// Whether no sample was decoded.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

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
    if header.rate_hz <= 0.0 || header.u_v_per_code == 0.0 || header.y_um_per_code == 0.0 {
        return fail(format!("{name}:{line_no}: recording header with a zero rate or scale"));
    }
    Ok(header)
}

/// Recording number `which` (1-based) of the capture `text` (`name` for messages).
pub fn parse(name: &str, text: &str, which: usize, damage: Damage) -> Result<Recording, CliError> {
    let mut found = 0;
    let mut rec: Option<Recording> = None;
    let mut frame = [RawSample::default(); FRAME_SAMPLES];
    for (i, line) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = line.trim_end_matches('\r');
        if line.starts_with(HEADER_TAG) {
            if rec.is_some() {
                break;
            }
            found += 1;
            if found == which {
                let header = parse_header(name, line_no, line)?;
                rec = Some(Recording { header, segments: Vec::new(), damage: Vec::new(), ended: None });
            }
            continue;
        }
        let Some(r) = rec.as_mut() else { continue };
        if line.starts_with(END_TAG) {
            r.ended = Some(line.contains("overflow=1"));
            break;
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
        let expected = r.segments.last().map(|s| s.first_index + s.samples.len() as u64);
        match expected {
            Some(e) if index == e => r.segments.last_mut().expect("a last segment").samples.extend(&frame[..n]),
            Some(e) if index < e => r.refuse_or_skip(
                damage,
                format!(
                    "{name}:{line_no}: frame starts at sample {index}, before the expected {e} (a line repeated in \
                     the capture)"
                ),
            )?,
            _ => {
                if let Some(e) = expected {
                    r.refuse_or_skip(
                        damage,
                        format!(
                            "{name}:{line_no}: frame starts at sample {index}, expected {e}: {} samples missing \
                             (lines lost in the capture)",
                            index - e
                        ),
                    )?;
                }
                r.segments.push(Segment { first_index: index, samples: frame[..n].to_vec() });
            }
        }
    }
    match rec {
        Some(r) if r.segments.iter().any(|s| s.samples.len() >= MIN_SAMPLES) => Ok(r),
        Some(_) => fail(format!("{name}: recording {which} holds no run of {MIN_SAMPLES} or more samples")),
        None if found == 0 => fail(format!("{name}: no recording in the capture (no '{HEADER_TAG}' line)")),
        None => fail(format!("{name}: recording {which} asked for, the capture holds {found}")),
    }
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
pub fn run(
    input: &Path,
    out: &Path,
    which: usize,
    damage: Damage,
) -> Result<(Recording, Vec<Option<std::path::PathBuf>>), CliError> {
    let name = input.display().to_string();
    if damage == Damage::Skip && std::fs::metadata(out).is_ok_and(|m| !m.is_file()) {
        return fail(format!(
            "--out {}: not a file name: --segments writes one file per run, named after it (run.csv -> run-1.csv, \
             run-2.csv, ...)",
            out.display()
        ));
    }
    let bytes = std::fs::read(input).map_err(|e| CliError(format!("{name}: cannot read: {}", io_reason(&e))))?;
    // Captures can hold noise from before the link settled: decode what is text, the frames carry their checksums.
    let text = String::from_utf8_lossy(&bytes);
    let rec = parse(&name, &text, which.max(1), damage)?;
    let h = rec.header;
    let origin = rec.first_index();
    // Every file is complete before any is moved into place.
    let mut files = Vec::new();
    let mut written = Vec::new();
    for seg in &rec.segments {
        if seg.samples.len() < MIN_SAMPLES {
            written.push(None);
            continue;
        }
        let path = match damage {
            Damage::Refuse => out.to_path_buf(),
            Damage::Skip => segment_path(out, files.len() + 1),
        };
        // Each file written, not `out` itself: with `--segments` no file takes that name.
        super::check_distinct(&[("--input", input)], &[("--out", &path)])?;
        let mut file = OutputFile::create(&path)?;
        let result = (|| -> std::io::Result<()> {
            let w = file.writer();
            writeln!(w, "t,u,y")?;
            for (j, s) in seg.samples.iter().enumerate() {
                let (u, y) = h.physical(*s);
                writeln!(w, "{},{},{}", (seg.first_index - origin + j as u64) as f64 / h.rate_hz, u, y)?;
            }
            Ok(())
        })();
        result.map_err(|e| file.write_error(e))?;
        written.push(Some(path));
        files.push(file);
    }
    for file in files {
        file.commit()?;
    }
    Ok((rec, written))
}
