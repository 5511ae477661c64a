//! `nanopos-sim commands --tuning FILE|PRESET`: the console commands that give the board a tuning (a file `decode`
//! wrote from a recording, or one written for `identify --tuning`), one per line, to send it one at a time
//! (`nanopos-sim send` does: [`super::send`]).
//!
//! The board loses its tuning when it resets; the recording carries it to the host (`decode` writes it beside the
//! CSV) and these lines carry it back. They are `tuning PRESET` (the file's base: the console's `status` names it),
//! then `tune initial`, `tune prefilter` and `tune spike_ratio` ([`TuningKey::STAGE`]), which `tuning` keeps from
//! before, then `tune SECTION KEY VALUES` for every other key whose value differs from the preset's, in the order
//! [`TuningKey::ALL`] gives (`q` before `p0`, which `q` sets to 10 Q). Each line is what the board's `tune` accepts:
//! the tuning is checked here at the board's sample rate as the console checks it (every value in its range, the
//! whole runnable in f32, the pre-filter one the pipeline can match), and every line after the stage's leaves a
//! tuning the board can run. The values are written in full (Rust's shortest form that reads back to the same
//! `f64`), unless a line would pass the console's [`MAX_LINE`]: then to as many significant digits as fit, which a
//! note says; the board then holds those values, and a key they set besides (`q` sets `p0`) gets its own line. The
//! board's decimal parser is within a few ulps of the correctly rounded value, so the board's values are the file's to
//! within a few ulps.

use super::{show, CliError};
use crate::board::SimBoard;
use crate::tuning::TuningArg;
use nanopos_id::control::MAX_LINE;
use nanopos_id::estimators::{Tuning, TuningKey};
use nanopos_id::hal::StageBoard;
use nanopos_id::pipeline::PipelineSettings;

/// The lines, and the notes to print beside them.
pub struct Commands {
    /// The console commands, in the order to send them.
    pub lines: Vec<String>,
    /// What a user should know of them (values shortened to fit a line).
    pub notes: Vec<String>,
}

/// The commands that give the board the tuning `arg`.
pub fn run(arg: &TuningArg) -> Result<Commands, CliError> {
    let settings = PipelineSettings::default();
    let dt = 1.0 / settings.sample_rate_hz;
    let target = arg.at(dt)?;
    let board = SimBoard::new(Default::default());
    target
        .runnable::<f32>()
        .map_err(|u| CliError(format!("{}: at the board's {} Hz, in f32: {u}", arg.name, show(1.0 / dt))))?;
    settings
        .with_stage_of(&target)
        .design::<f32>(&board.description())
        .map_err(|e| CliError(format!("{}: the board's pipeline refuses its pre-filter: {e}", arg.name)))?;
    // A tuning made otherwise than from a preset is told as the PRBS preset's with every key that differs.
    let preset = arg.preset().unwrap_or("prbs");
    let mut lines = vec![format!("tuning {preset}")];
    let mut notes = Vec::new();
    // What the board holds after each line: the preset with the file's stage, then each key set in turn.
    let mut board_tuning = Tuning::preset(preset).expect("a preset").at_sample_period(dt).with_stage_of(&target);
    for key in TuningKey::ALL {
        let values = &target.get(key)[..key.len()];
        let stage = TuningKey::STAGE.contains(&key);
        if !stage && board_tuning.get(key)[..key.len()] == *values {
            continue;
        }
        let (line, digits) = line_of(key, values);
        // What the board holds after the line: the values as written, which differ from the file's where they were
        // shortened; so may a key they set besides (`q` sets `p0`), which then gets its own line.
        let written: Vec<f64> = match digits {
            None => values.to_vec(),
            Some(d) => values.iter().map(|&v| shortened(v, d).parse().expect("a number written")).collect(),
        };
        board_tuning.set(key, &written).map_err(|r| {
            CliError(format!(
                "{}: {key} = {}: {} once shortened to fit the console's {MAX_LINE}-byte line",
                arg.name,
                show(written[r.index]),
                r.expected
            ))
        })?;
        if board_tuning.runnable::<f32>().is_err() {
            // The keys set so far with the rest at the preset's: a board would refuse this line, though the whole was
            // checked above. Met by 3 of 20 000 random files, at the ends of f32's range (`q` 3.4e38, whose `p0 = 10
            // Q` no order of the lines avoids; an `initial` `a0` of 8e-13 under the preset's `p0`).
            let also = if key == TuningKey::EkfQ { " (`tune ekf q` also sets p0 to 10 Q)" } else { "" };
            return Err(CliError(format!(
                "{}: {key} set before the keys after it leaves a tuning the board cannot run, and the console refuses \
                 such a line{also}: this order of the lines cannot give the board this tuning",
                arg.name
            )));
        }
        if let Some(digits) = digits {
            notes.push(format!(
                "{key}'s values written to {digits} significant digits (each within {} of the file's, relative), to \
                 fit the console's {MAX_LINE}-byte line",
                show(0.5 * 10f64.powi(1 - digits as i32))
            ));
        }
        lines.push(line);
    }
    Ok(Commands { lines, notes })
}

/// `tune SECTION KEY VALUES` for `values`, in full (each the shorter of Rust's two forms that read back to it, `0.25`
/// and `1e-12`), or to the significant digits (returned) that fit [`MAX_LINE`].
fn line_of(key: TuningKey, values: &[f64]) -> (String, Option<usize>) {
    let (section, name) = key.path();
    let head = if section.is_empty() { format!("tune {name}") } else { format!("tune {section} {name}") };
    let with = |digits: Option<usize>| {
        values.iter().fold(head.clone(), |line, v| match digits {
            None => {
                let (plain, exp) = (format!("{v}"), format!("{v:e}"));
                format!("{line} {}", if plain.len() <= exp.len() { plain } else { exp })
            }
            Some(d) => format!("{line} {}", shortened(*v, d)),
        })
    };
    let full = with(None);
    if full.len() <= MAX_LINE {
        return (full, None);
    }
    let digits = (1..=17).rev().find(|&d| with(Some(d)).len() <= MAX_LINE).expect("one digit always fits");
    (with(Some(digits)), Some(digits))
}

/// `v` to `digits` significant digits, without the zeros that end the mantissa: `1e-12`, not `1.00000000000e-12`.
fn shortened(v: f64, digits: usize) -> String {
    let text = format!("{v:.*e}", digits - 1);
    let (mantissa, exp) = text.split_once('e').expect("an exponent");
    let mantissa = if mantissa.contains('.') { mantissa.trim_end_matches('0') } else { mantissa };
    format!("{}e{exp}", mantissa.trim_end_matches('.'))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_too_long_in_full_is_shortened_to_the_digits_that_fit() {
        let (line, digits) = line_of(TuningKey::EkfQ, &[1e-12, 1e-6, 1.5e9, 0.25, 5e8]);
        assert_eq!((line.as_str(), digits), ("tune ekf q 1e-12 1e-6 1.5e9 0.25 5e8", None));
        let odd = [1.0000000000000002e-12, 1.1e-6 / 3.0, 1.5e9 / 7.0, 0.1 + 0.2, -5e8 / 3.0];
        let (line, digits) = line_of(TuningKey::EkfP0, &odd);
        assert!(line.len() <= MAX_LINE && digits.is_some_and(|d| d < 17), "{line}");
        let read: Vec<f64> = line.split(' ').skip(3).map(|w| w.parse().unwrap()).collect();
        let d = digits.unwrap() as i32;
        for (r, v) in read.iter().zip(odd) {
            assert!((r / v - 1.0).abs() <= 0.5 * 10f64.powi(1 - d), "{r} {v}");
        }
    }
}
