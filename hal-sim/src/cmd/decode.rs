//! `nanopos-sim decode`: a captured serial stream of the firmware's recording (`record on` / `record burst N`) into
//! the CSV `identify` reads (`t,u,y`).
//!
//! The capture may hold anything else the link carried (command replies, several recordings): only the chosen
//! recording's header, frames and end line are read. `t` counts from the recording's first sample; `u` is the
//! command in effect over the sample period (V) and `y` the probe reading at its start (um), the convention of
//! `simulate` and of the pipeline. A damaged frame or a gap between frames is an error naming the capture's line:
//! `identify` needs uniformly sampled data, and a hole would be silently bridged.

use super::{fail, io_reason, CliError, OutputFile};
use nanopos_id::record::{decode_frame, RawSample, RecordHeader, END_TAG, FRAME_SAMPLES, HEADER_TAG};
use std::io::Write;
use std::path::Path;

/// What a decoded recording holds.
#[derive(Clone, Debug, PartialEq)]
pub struct Recording {
    /// The header.
    pub header: RecordHeader,
    /// Index of the first sample since the board started.
    pub first_index: u64,
    /// The samples.
    pub samples: Vec<RawSample>,
    /// The end line: `Some(overflowed)` when present.
    pub ended: Option<bool>,
}

fn header_value(name: &str, line_no: usize, line: &str, key: &str) -> Result<f64, CliError> {
    let word = line
        .split_ascii_whitespace()
        .find_map(|w| w.strip_prefix(key).and_then(|w| w.strip_prefix('=')))
        .ok_or_else(|| CliError(format!("{name}:{line_no}: recording header without {key}=")))?;
    word.parse::<f64>()
        .ok()
        .filter(|x| x.is_finite())
        .ok_or_else(|| CliError(format!("{name}:{line_no}: {key}={word}: not a number")))
}

fn parse_header(name: &str, line_no: usize, line: &str) -> Result<RecordHeader, CliError> {
    let v = |key| header_value(name, line_no, line, key);
    let header = RecordHeader {
        rate_hz: v("rate_hz")?,
        delay: v("delay")? as u8,
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
pub fn parse(name: &str, text: &str, which: usize) -> Result<Recording, CliError> {
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
                rec = Some(Recording { header, first_index: 0, samples: Vec::new(), ended: None });
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
        let (index, n) =
            decode_frame(line.as_bytes(), &mut frame).map_err(|e| CliError(format!("{name}:{line_no}: {e}")))?;
        if r.samples.is_empty() {
            r.first_index = index;
        } else {
            let expected = r.first_index + r.samples.len() as u64;
            if index != expected {
                return fail(format!(
                    "{name}:{line_no}: frame starts at sample {index}, expected {expected}: {} samples missing \
                     (lines lost in the capture)",
                    index as i64 - expected as i64
                ));
            }
        }
        r.samples.extend_from_slice(&frame[..n]);
    }
    match rec {
        Some(r) if r.samples.len() >= 2 => Ok(r),
        Some(_) => fail(format!("{name}: recording {which} holds fewer than 2 samples")),
        None if found == 0 => fail(format!("{name}: no recording in the capture (no '{HEADER_TAG}' line)")),
        None => fail(format!("{name}: recording {which} asked for, the capture holds {found}")),
    }
}

/// Decode recording `which` of `input` into `out`; returns it, for the caller's report.
pub fn run(input: &Path, out: &Path, which: usize) -> Result<Recording, CliError> {
    let name = input.display().to_string();
    let bytes = std::fs::read(input).map_err(|e| CliError(format!("{name}: cannot read: {}", io_reason(&e))))?;
    // Captures can hold noise from before the link settled: decode what is text, the frames carry their checksums.
    let text = String::from_utf8_lossy(&bytes);
    let rec = parse(&name, &text, which.max(1))?;
    let mut file = OutputFile::create(out)?;
    let h = rec.header;
    let result = (|| -> std::io::Result<()> {
        let w = file.writer();
        writeln!(w, "t,u,y")?;
        for (k, s) in rec.samples.iter().enumerate() {
            let (u, y) = h.physical(*s);
            writeln!(w, "{},{},{}", k as f64 / h.rate_hz, u, y)?;
        }
        Ok(())
    })();
    result.map_err(|e| file.write_error(e))?;
    file.commit()?;
    Ok(rec)
}
