//! The run-time control protocol: one command per text line, parsed without allocation.
//!
//! Lines are ASCII, at most [`MAX_LINE`] bytes, ended by `\n`, `\r` or `\r\n` (what a terminal's Enter sends);
//! words are separated by spaces or tabs, in any case (`STATUS` is `status`, as in SCPI); numbers are decimal (`1`,
//! `0.5`, `-2.5e-1`). Every line gets one answer: `ok ...` or `error: ...` naming what was wrong and where.
//!
//! | command | meaning |
//! |---|---|
//! | `help` | the commands and their words ([`HELP`]) |
//! | `status` | counters, faults, the excitation and the estimates |
//! | `excite off` / `excite constant V` / `excite prbs AMP_V [OFFSET_V]` / `excite triangle AMP_V HZ [OFFSET_V]` / `excite sine AMP_V HZ [OFFSET_V]` / `excite multisine AMP_V F_LO F_HI [OFFSET_V]` | choose the excitation (AMP_V in 0..=10, HZ in (0, 1000], F_HI above F_LO, V and OFFSET_V in -10..=10) |
//! | `start` / `stop` | run or stop the excitation (the output ramps to its safe value) |
//! | `select EST,...` / `select all` / `select none` | which estimators run (`rls`, `ekf`, `hekf`, `arx`; commas or spaces) |
//! | `reset EST,...` / `freeze EST,...` / `adapt EST,...` | reset, freeze or unfreeze estimators (`all` for every one) |
//! | `tuning prbs` / `tuning triangle` | the paper's tuning for that input (Q2 / Q1) |
//! | `tune initial B0 A1 A0` / `tune spike_ratio N` / `tune SECTION KEY VALUE...` | one tuning value, the keys of [`crate::estimators::tuning`] (`tune ekf q 1e-12 1e-6 1.5e9 0.25 5e8`); without values, report it |
//! | `limits MIN_V MAX_V SLEW_V_PER_S` / `limits` | output clamp (within -10..=10 V, MIN < MAX) and slew limit (> 0 here; the design refuses one under [`crate::pipeline::OutputLimits::min_slew_v_per_s`]); without values, report them and the clamp in force |
//! | `record off` / `record on` / `record burst N` | stream raw samples: off, continuously, or the next N (1..=1 000 000) |

use crate::estimators::TuningKey;

/// Longest accepted line, bytes (without the terminator).
pub const MAX_LINE: usize = 96;

/// `help`'s reply before its `ok`: every command and its words (values in capitals; the README has what each does).
pub const HELP: &str = "\
help | status
excite off | constant V | prbs AMP [OFFSET] | triangle AMP HZ [OFFSET] | sine AMP HZ [OFFSET]
excite multisine AMP F_LO F_HI [OFFSET]
start | stop
select all | none | EST... (EST: rls ekf hekf arx)
reset | freeze | adapt all | EST...
tuning prbs | triangle
tune initial B0 A1 A0 | initial EST | stage EST | prefilter F_LC F_P ZETA | spike_ratio N
tune rls | ekf | arx KEY [VALUE...] (no KEY: the keys; no VALUE: the value in use)
limits [MIN_V MAX_V SLEW_V_PER_S]
record off | on | burst N
";

/// The estimators, as bits of an [`EstimatorSet`].
pub const ESTIMATOR_NAMES: [&str; 4] = ["rls", "ekf", "hekf", "arx"];

/// A set of estimators: bit `i` is [`ESTIMATOR_NAMES`]`[i]`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EstimatorSet(pub u8);

impl EstimatorSet {
    /// Every estimator.
    pub const ALL: EstimatorSet = EstimatorSet(0b1111);
    /// Whether estimator `i` is in the set.
    pub fn contains(self, i: usize) -> bool {
        self.0 & (1 << i) != 0
    }

    /// The estimators a change of the tuning values `keys` restarts: the union of their
    /// [`crate::estimators::TuningKey::estimators`].
    pub fn restarted_by(keys: impl Iterator<Item = crate::estimators::TuningKey>) -> EstimatorSet {
        EstimatorSet(keys.fold(0, |set, key| set | key.estimators().0))
    }

    /// The names of the estimators in the set, in [`ESTIMATOR_NAMES`]' order.
    pub fn names(self) -> impl Iterator<Item = &'static str> {
        ESTIMATOR_NAMES.iter().enumerate().filter(move |&(i, _)| self.contains(i)).map(|(_, n)| *n)
    }
}

/// The excitation a command asks for.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ExcitationChoice {
    /// No excitation (output at its safe value).
    Off,
    /// A constant level, V: the stage held at an operating point.
    Constant {
        /// Level, V.
        level_v: f32,
    },
    /// The paper's PRBS with this amplitude, V.
    Prbs {
        /// Amplitude, V.
        amplitude_v: f32,
        /// Offset the waveform runs about (the operating point), V.
        offset_v: f32,
    },
    /// The smoothed triangle.
    Triangle {
        /// Amplitude, V.
        amplitude_v: f32,
        /// Frequency, Hz.
        frequency_hz: f32,
        /// Offset, V.
        offset_v: f32,
    },
    /// A sine.
    Sine {
        /// Amplitude, V.
        amplitude_v: f32,
        /// Frequency, Hz.
        frequency_hz: f32,
        /// Offset, V.
        offset_v: f32,
    },
    /// A multisine (the power of a sine of `amplitude_v`) from `f_lo_hz` to `f_hi_hz`.
    Multisine {
        /// Amplitude of the sine of the same power, V.
        amplitude_v: f32,
        /// Lowest tone, Hz.
        f_lo_hz: f32,
        /// Highest tone, Hz.
        f_hi_hz: f32,
        /// Offset, V.
        offset_v: f32,
    },
}

/// Recording of the raw samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Recording {
    /// Not recording.
    Off,
    /// Every sample, until `record off`.
    On,
    /// The next `n` samples.
    Burst(u32),
}

/// Which preset tuning.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TuningPreset {
    /// The paper's PRBS tuning (Q2).
    Prbs,
    /// The paper's triangle tuning (Q1).
    Triangle,
}

/// A parsed command.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Command {
    /// List the commands.
    Help,
    /// Report status.
    Status,
    /// Choose the excitation.
    Excite(ExcitationChoice),
    /// Run the excitation.
    Start,
    /// Stop the excitation.
    Stop,
    /// Run exactly these estimators.
    Select(EstimatorSet),
    /// Reset these estimators to their initial state.
    Reset(EstimatorSet),
    /// Freeze these estimators' parameters.
    Freeze(EstimatorSet),
    /// Let these estimators adapt again.
    Adapt(EstimatorSet),
    /// Load a preset tuning.
    Tuning(TuningPreset),
    /// `tune initial ESTIMATOR`: the initial parameters from that estimator's estimate (index into
    /// [`ESTIMATOR_NAMES`]), as `tune initial` with its `b0 a1 a0` would set them; `tune stage ESTIMATOR`: and the
    /// pre-filter's centre `f_p` at its resonance, as `tune prefilter` would, in the same restart.
    FromEstimate {
        /// Whose estimate.
        estimator: usize,
        /// The pre-filter's centre too (`tune stage`).
        prefilter: bool,
    },
    /// Set one tuning value by name (the first [`TuningKey::len`] of `values`), or, without values, report it.
    Tune {
        /// Which.
        key: TuningKey,
        /// Its new values, if any.
        values: Option<[f64; 5]>,
    },
    /// The output clamp and slew limit in use (`limits` without values).
    LimitsInUse,
    /// Output clamp and slew limit.
    Limits {
        /// Lowest command, V.
        min_v: f32,
        /// Highest command, V.
        max_v: f32,
        /// Largest change, V/s.
        slew_v_per_s: f32,
    },
    /// Recording mode.
    Record(Recording),
}

/// Why a line was refused. `word` is the 1-based position of the offending word.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ParseError {
    /// Nothing but spaces.
    Empty,
    /// Longer than [`MAX_LINE`] (the rest of the line was discarded).
    TooLong,
    /// Bytes of the line were lost or changed on the link (a receive error, a full receive buffer): refused whole,
    /// whatever arrived of it.
    Damaged,
    /// A byte outside printable ASCII.
    NotAscii {
        /// Byte offset in the line.
        at: usize,
        /// The byte.
        byte: u8,
    },
    /// The first word is no command.
    UnknownCommand,
    /// A word is missing.
    Missing {
        /// Position the word should have had.
        word: usize,
        /// What it should have been.
        expected: &'static str,
    },
    /// A word is not what the command takes.
    Invalid {
        /// Its position.
        word: usize,
        /// What was expected.
        expected: &'static str,
    },
    /// More words than the command takes.
    Extra {
        /// Position of the first extra word.
        word: usize,
    },
}

impl core::fmt::Display for ParseError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            ParseError::Empty => write!(f, "empty line"),
            ParseError::TooLong => write!(f, "line longer than {MAX_LINE} bytes"),
            ParseError::Damaged => write!(f, "bytes of this line were lost on the link: send it again"),
            ParseError::NotAscii { at, byte } => {
                // Counted from 1, as the words are (`byte 0` read as a NUL byte).
                write!(f, "byte {} is not printable ASCII", at + 1)?;
                // UTF-8 pasted from a document: a minus sign (U+2212), a non-breaking space, a typographic quote.
                if (0xC2..=0xF4).contains(byte) {
                    f.write_str(", the start of a Unicode character (a pasted minus sign or non-breaking space?)")?;
                }
                Ok(())
            }
            ParseError::UnknownCommand => write!(
                f,
                "unknown command (help, status, excite, start, stop, select, reset, freeze, adapt, tuning, tune, \
                 limits, record)"
            ),
            ParseError::Missing { word, expected } => write!(f, "word {word}: missing, expected {expected}"),
            ParseError::Invalid { word, expected } => write!(f, "word {word}: expected {expected}"),
            ParseError::Extra { word } => write!(f, "word {word}: unexpected extra word"),
        }
    }
}

/// The words of a line, with their positions.
struct Words<'a> {
    it: core::str::SplitAsciiWhitespace<'a>,
    n: usize,
}

impl<'a> Words<'a> {
    fn next(&mut self, expected: &'static str) -> Result<(usize, &'a str), ParseError> {
        self.n += 1;
        self.it.next().map(|w| (self.n, w)).ok_or(ParseError::Missing { word: self.n, expected })
    }

    fn number(&mut self, expected: &'static str, ok: impl Fn(f32) -> bool) -> Result<f32, ParseError> {
        let (word, w) = self.next(expected)?;
        match crate::text::parse_decimal(w).map(|x| x as f32) {
            Some(x) if x.is_finite() && ok(x) => Ok(x),
            _ => Err(ParseError::Invalid { word, expected }),
        }
    }

    /// A finite number, in full precision (a tuning value: its range is checked by [`crate::estimators::Tuning::set`]).
    fn number64(&mut self, expected: &'static str) -> Result<f64, ParseError> {
        let (word, w) = self.next(expected)?;
        crate::text::parse_decimal(w).filter(|x| x.is_finite()).ok_or(ParseError::Invalid { word, expected })
    }

    /// Whether no word is left.
    fn is_done(&self) -> bool {
        self.it.clone().next().is_none()
    }

    fn end(mut self) -> Result<(), ParseError> {
        match self.it.next() {
            None => Ok(()),
            Some(_) => Err(ParseError::Extra { word: self.n + 1 }),
        }
    }
}

/// The first value of `tune initial`.
const INITIAL: &str = "3 numbers: b0 a1 a0, or an estimator whose estimate to take: rls, ekf, hekf or arx";
/// The word after `tune stage`.
const ESTIMATOR: &str = "an estimator whose estimate to take: rls, ekf, hekf or arx";
const EST_LIST: &str = "estimators: all, none, or rls, ekf, hekf, arx separated by commas or spaces";
const EXCITATIONS: &str = "off, constant, prbs, triangle, sine or multisine";
const AMP: &str = "an amplitude in V, 0 to 10";
const OFFSET: &str = "an offset in V, -10 to 10 (or nothing)";
const LEVEL: &str = "a level in V, -10 to 10";
const HZ: &str = "a frequency in Hz, above 0 and at most 1000";
const HZ_HI: &str = "a frequency in Hz, above the lowest and at most 1000";

// Not inlined, for flash (see `parse`).
#[inline(never)]
fn estimator_set(word: usize, w: &str, allow_none: bool) -> Result<EstimatorSet, ParseError> {
    let invalid = ParseError::Invalid { word, expected: EST_LIST };
    match w {
        "all" => return Ok(EstimatorSet::ALL),
        "none" if allow_none => return Ok(EstimatorSet(0)),
        _ => {}
    }
    let mut set = 0u8;
    for name in w.split(',') {
        set |= 1 << estimator_index(name).ok_or(invalid)?;
    }
    Ok(EstimatorSet(set))
}

/// The index of the estimator `name` in [`ESTIMATOR_NAMES`].
// Not inlined, for flash (see `parse`).
#[inline(never)]
fn estimator_index(name: &str) -> Option<usize> {
    ESTIMATOR_NAMES.iter().position(|n| *n == name)
}

/// Parse one line (without its terminator).
// Not inlined, nor `estimator_set` and `estimator_index`: inlined into the firmware's console task, the three took
// 0.9 KiB more flash (measured when `tune initial ESTIMATOR` came).
#[inline(never)]
pub fn parse(line: &[u8]) -> Result<Command, ParseError> {
    if line.len() > MAX_LINE {
        return Err(ParseError::TooLong);
    }
    let line = line.strip_suffix(b"\r").unwrap_or(line);
    if let Some(at) = line.iter().position(|&b| !(b == b' ' || b == b'\t' || b.is_ascii_graphic())) {
        return Err(ParseError::NotAscii { at, byte: line[at] });
    }
    // Words in any case: one lowercase copy of the line.
    let mut lower = [0u8; MAX_LINE];
    let lower = &mut lower[..line.len()];
    lower.copy_from_slice(line);
    lower.make_ascii_lowercase();
    // Printable ASCII is UTF-8.
    let text = core::str::from_utf8(lower)
        .map_err(|e| ParseError::NotAscii { at: e.valid_up_to(), byte: lower[e.valid_up_to()] })?;
    let mut words = Words { it: text.split_ascii_whitespace(), n: 0 };
    let (_, command) = words.next("a command").map_err(|_| ParseError::Empty)?;
    let amplitude = |x: f32| (0.0..=10.0).contains(&x);
    let frequency = |x: f32| x > 0.0 && x <= 1000.0;
    let volts = |x: f32| (-10.0..=10.0).contains(&x);
    let parsed = match command {
        "help" => Command::Help,
        "status" => Command::Status,
        "start" => Command::Start,
        "stop" => Command::Stop,
        "excite" => {
            let (word, kind) = words.next(EXCITATIONS)?;
            // The waveforms' last word, optional: the offset they run about (0 V if not given).
            let offset = |words: &mut Words| if words.is_done() { Ok(0.0) } else { words.number(OFFSET, volts) };
            Command::Excite(match kind {
                "off" => ExcitationChoice::Off,
                "constant" => ExcitationChoice::Constant { level_v: words.number(LEVEL, volts)? },
                "prbs" => {
                    ExcitationChoice::Prbs { amplitude_v: words.number(AMP, amplitude)?, offset_v: offset(&mut words)? }
                }
                "triangle" => ExcitationChoice::Triangle {
                    amplitude_v: words.number(AMP, amplitude)?,
                    frequency_hz: words.number(HZ, frequency)?,
                    offset_v: offset(&mut words)?,
                },
                "sine" => ExcitationChoice::Sine {
                    amplitude_v: words.number(AMP, amplitude)?,
                    frequency_hz: words.number(HZ, frequency)?,
                    offset_v: offset(&mut words)?,
                },
                "multisine" => {
                    let amplitude_v = words.number(AMP, amplitude)?;
                    let f_lo_hz = words.number(HZ, frequency)?;
                    let f_hi_hz = words.number(HZ_HI, |x| frequency(x) && x > f_lo_hz)?;
                    ExcitationChoice::Multisine { amplitude_v, f_lo_hz, f_hi_hz, offset_v: offset(&mut words)? }
                }
                _ => return Err(ParseError::Invalid { word, expected: EXCITATIONS }),
            })
        }
        "select" | "reset" | "freeze" | "adapt" => {
            let (word, w) = words.next(EST_LIST)?;
            let mut set = estimator_set(word, w, command == "select")?;
            // Names separated by spaces as well as commas (`all` and `none` alone).
            while !(words.is_done() || w == "all" || w == "none") {
                let (word, w) = words.next(EST_LIST)?;
                set.0 |= estimator_set(word, w, false)?.0;
            }
            match command {
                "select" => Command::Select(set),
                "reset" => Command::Reset(set),
                "freeze" => Command::Freeze(set),
                _ => Command::Adapt(set),
            }
        }
        "tuning" => {
            let (word, w) = words.next("prbs or triangle")?;
            Command::Tuning(match w {
                "prbs" => TuningPreset::Prbs,
                "triangle" => TuningPreset::Triangle,
                _ => return Err(ParseError::Invalid { word, expected: "prbs or triangle" }),
            })
        }
        "tune" => {
            const SECTIONS: &str = "initial, prefilter, spike_ratio, stage, rls, ekf (both EKFs) or arx";
            let (word, section) = words.next(SECTIONS)?;
            if section == "stage" {
                let (word, name) = words.next(ESTIMATOR)?;
                let estimator = estimator_index(name).ok_or(ParseError::Invalid { word, expected: ESTIMATOR })?;
                words.end()?;
                return Ok(Command::FromEstimate { estimator, prefilter: true });
            }
            let key = if let Some(key) = TuningKey::parse("", section) {
                key
            } else {
                let names = TuningKey::names_of(section).ok_or(ParseError::Invalid { word, expected: SECTIONS })?;
                let (word, name) = words.next(names)?;
                TuningKey::parse(section, name).ok_or(ParseError::Invalid { word, expected: names })?
            };
            // `tune initial arx`: from an estimator's estimate (a name where the first value would be).
            let from = match key {
                TuningKey::Initial => words.it.clone().next().and_then(estimator_index),
                _ => None,
            };
            if let Some(estimator) = from {
                words.next(INITIAL)?;
                words.end()?;
                return Ok(Command::FromEstimate { estimator, prefilter: false });
            }
            // Without values: a query.
            let values = if words.is_done() {
                None
            } else {
                let mut values = [0.0; 5];
                for (i, v) in values.iter_mut().take(key.len()).enumerate() {
                    *v = words.number64(if i == 0 && key == TuningKey::Initial {
                        INITIAL
                    } else {
                        key.values_hint()
                    })?;
                }
                Some(values)
            };
            Command::Tune { key, values }
        }
        "limits" if words.is_done() => Command::LimitsInUse,
        "limits" => {
            let min_v = words.number("the lowest command in V, -10 to 10", volts)?;
            let max_v =
                words.number("the highest command in V, above the lowest, at most 10", |x| volts(x) && x > min_v)?;
            let slew_v_per_s = words.number("a slew limit in V/s, above 0", |x| x > 0.0)?;
            Command::Limits { min_v, max_v, slew_v_per_s }
        }
        "record" => {
            let (word, w) = words.next("off, on or burst")?;
            Command::Record(match w {
                "off" => Recording::Off,
                "on" => Recording::On,
                "burst" => {
                    let (word, n) = words.next("a sample count, 1 to 1000000")?;
                    match n.parse::<u32>() {
                        Ok(n) if (1..=1_000_000).contains(&n) => Recording::Burst(n),
                        _ => return Err(ParseError::Invalid { word, expected: "a sample count, 1 to 1000000" }),
                    }
                }
                _ => return Err(ParseError::Invalid { word, expected: "off, on or burst" }),
            })
        }
        _ => return Err(ParseError::UnknownCommand),
    };
    words.end()?;
    Ok(parsed)
}

/// Collects bytes from a serial port into lines, without allocation. A line ends at `\n`, at `\r` (a terminal's
/// Enter: picocom, screen, PuTTY send it alone), or at both (`\r\n`, one line end). A terminal's Backspace (BS or
/// DEL, whichever it sends) takes back the line's last byte, and Ctrl-U the whole line typed so far, as a terminal's
/// own line editing does: typed at a terminal, the line executed is the line the user corrected, not one with the
/// mistake and a control byte in it (which the parser refused). A line longer than [`MAX_LINE`]
/// is reported once, as [`ParseError::TooLong`], and its rest discarded up to its end; a line that lost bytes on
/// the link ([`LineBuffer::lost_bytes`]) is refused whole at its end, as [`ParseError::Damaged`].
///
/// Fed a read of the link's receive buffer at a time ([`LineBuffer::read`]), it also refuses the lines a receive
/// error or a full buffer may have damaged: no line that lost or changed a byte is executed as what arrived of it.
#[derive(Clone, Debug)]
pub struct LineBuffer {
    buf: [u8; MAX_LINE],
    len: usize,
    overflowed: bool,
    damaged: bool,
    /// The last byte ended a line with `\r`: a `\n` right after it belongs to that line end.
    after_cr: bool,
}

impl Default for LineBuffer {
    fn default() -> Self {
        LineBuffer { buf: [0; MAX_LINE], len: 0, overflowed: false, damaged: false, after_cr: false }
    }
}

impl LineBuffer {
    /// Feed one byte; at the end of a line, the parsed command (or why not).
    pub fn push(&mut self, byte: u8) -> Option<Result<Command, ParseError>> {
        let after_cr = core::mem::replace(&mut self.after_cr, byte == b'\r');
        if byte == b'\n' && after_cr {
            return None;
        }
        if byte == b'\n' || byte == b'\r' {
            let result = if self.overflowed {
                Err(ParseError::TooLong)
            } else if self.damaged {
                Err(ParseError::Damaged)
            } else {
                parse(&self.buf[..self.len])
            };
            (self.len, self.overflowed, self.damaged) = (0, false, false);
            return Some(result);
        }
        if matches!(byte, 0x08 | 0x7F | 0x15) {
            self.edit(byte);
            return None;
        }
        if self.len < MAX_LINE {
            self.buf[self.len] = byte;
            self.len += 1;
        } else {
            self.overflowed = true;
        }
        None
    }

    /// A terminal's editing byte: Backspace (BS, or DEL, which most terminals send for it) takes back the last byte,
    /// Ctrl-U the line typed so far. On a line that overflowed, the bytes Backspace would take back were discarded
    /// already, and the line stays refused; Ctrl-U starts it afresh. Bytes the link lost may have belonged to the
    /// next line as well, so a damaged line's refusal stands.
    #[cold]
    #[inline(never)]
    fn edit(&mut self, byte: u8) {
        if byte == 0x15 {
            (self.len, self.overflowed) = (0, false);
        } else if !self.overflowed {
            self.len = self.len.saturating_sub(1);
        }
    }

    /// The link lost bytes (a receive error: overrun, framing, noise): the line in progress, whatever else of it
    /// arrives, is refused at its end. Executing what arrived could run another command than was sent (`excite prbs
    /// 1.5` without its `.5`).
    pub fn lost_bytes(&mut self) {
        self.damaged = true;
        self.after_cr = false;
    }

    /// The lines that `bytes`, one read of the link's receive buffer of `capacity` bytes, completes, each parsed
    /// (or why not), in order.
    ///
    /// - `error`: the link reported a receive error (overrun, framing, noise, parity) since the last read and before
    ///   this one took its bytes, so one of them is wrong or bytes were lost among them: the line in progress, every
    ///   line this read ends and the one it leaves in progress are refused.
    /// - A read that took all of the buffer found it full, and a byte that arrived while it was full was dropped
    ///   (embassy's buffered UART drops it without a word): the line the read leaves in progress, which the dropped
    ///   bytes would have continued, is refused.
    ///
    /// Both take effect when the lines are done with (the iterator dropped; bytes left unread count as lost).
    pub fn read<'a>(&'a mut self, bytes: &'a [u8], error: bool, capacity: usize) -> ReadLines<'a> {
        if error {
            self.lost_bytes();
        }
        ReadLines { full: bytes.len() >= capacity, suspect: error, line: self, bytes: bytes.iter() }
    }
}

/// The lines one read of the link completes: [`LineBuffer::read`].
pub struct ReadLines<'a> {
    line: &'a mut LineBuffer,
    bytes: core::slice::Iter<'a, u8>,
    /// The read took the whole receive buffer.
    full: bool,
    /// The read came with a receive error: every line it ends is refused.
    suspect: bool,
}

impl Iterator for ReadLines<'_> {
    type Item = Result<Command, ParseError>;

    fn next(&mut self) -> Option<Self::Item> {
        let parsed = self.bytes.by_ref().find_map(|&b| self.line.push(b));
        // The next line, begun in this read, is refused too (a `\r\n` across the line end stays one).
        self.line.damaged |= self.suspect && parsed.is_some();
        parsed
    }
}

impl Drop for ReadLines<'_> {
    fn drop(&mut self) {
        if self.suspect || self.full || self.bytes.len() > 0 {
            self.line.lost_bytes();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(s: &str) -> Result<Command, ParseError> {
        parse(s.as_bytes())
    }

    #[test]
    fn every_command_parses() {
        assert_eq!(p("status"), Ok(Command::Status));
        assert_eq!(p("  start \r"), Ok(Command::Start));
        assert_eq!(p("stop"), Ok(Command::Stop));
        assert_eq!(p("excite off"), Ok(Command::Excite(ExcitationChoice::Off)));
        assert_eq!(p("excite prbs 1"), Ok(Command::Excite(ExcitationChoice::Prbs { amplitude_v: 1.0, offset_v: 0.0 })));
        assert_eq!(
            p("excite prbs 1 -2.5"),
            Ok(Command::Excite(ExcitationChoice::Prbs { amplitude_v: 1.0, offset_v: -2.5 }))
        );
        assert_eq!(p("excite constant 3"), Ok(Command::Excite(ExcitationChoice::Constant { level_v: 3.0 })));
        assert_eq!(
            p("excite\ttriangle 0.5 10"),
            Ok(Command::Excite(ExcitationChoice::Triangle { amplitude_v: 0.5, frequency_hz: 10.0, offset_v: 0.0 }))
        );
        assert_eq!(
            p("excite sine 2 4.2e2"),
            Ok(Command::Excite(ExcitationChoice::Sine { amplitude_v: 2.0, frequency_hz: 420.0, offset_v: 0.0 }))
        );
        assert_eq!(
            p("excite multisine 1 200 800 -1"),
            Ok(Command::Excite(ExcitationChoice::Multisine {
                amplitude_v: 1.0,
                f_lo_hz: 200.0,
                f_hi_hz: 800.0,
                offset_v: -1.0
            }))
        );
        assert_eq!(p("select hekf,arx"), Ok(Command::Select(EstimatorSet(0b1100))));
        assert_eq!(p("select none"), Ok(Command::Select(EstimatorSet(0))));
        // Names separated by spaces too, and words in any case.
        assert_eq!(p("select hekf arx"), Ok(Command::Select(EstimatorSet(0b1100))));
        assert_eq!(p("freeze rls ekf,hekf"), Ok(Command::Freeze(EstimatorSet(0b0111))));
        assert_eq!(p("STATUS"), Ok(Command::Status));
        assert_eq!(p("Select HEKF,arx"), Ok(Command::Select(EstimatorSet(0b1100))));
        assert_eq!(
            p("EXCITE PRBS 1E-1"),
            Ok(Command::Excite(ExcitationChoice::Prbs { amplitude_v: 0.1, offset_v: 0.0 }))
        );
        assert_eq!(p("help"), Ok(Command::Help));
        assert_eq!(p("reset all"), Ok(Command::Reset(EstimatorSet::ALL)));
        assert_eq!(p("freeze rls"), Ok(Command::Freeze(EstimatorSet(1))));
        assert_eq!(p("adapt ekf"), Ok(Command::Adapt(EstimatorSet(2))));
        assert_eq!(p("tuning triangle"), Ok(Command::Tuning(TuningPreset::Triangle)));
        assert_eq!(p("tuning PRBS"), Ok(Command::Tuning(TuningPreset::Prbs)));
        assert_eq!(p("limits -5 5 1000"), Ok(Command::Limits { min_v: -5.0, max_v: 5.0, slew_v_per_s: 1000.0 }));
        assert_eq!(p("limits"), Ok(Command::LimitsInUse));
        assert_eq!(
            p("limits -5"),
            Err(ParseError::Missing { word: 3, expected: "the highest command in V, above the lowest, at most 10" })
        );
        assert_eq!(p("record burst 20000"), Ok(Command::Record(Recording::Burst(20000))));
        assert_eq!(p("record on"), Ok(Command::Record(Recording::On)));
        assert_eq!(p("record off"), Ok(Command::Record(Recording::Off)));
        assert_eq!(
            p("tune initial 1e6 90 3.9e7"),
            Ok(Command::Tune { key: TuningKey::Initial, values: Some([1e6, 90.0, 3.9e7, 0.0, 0.0]) })
        );
        assert_eq!(
            p("tune ekf q 1e-12 1e-6 1.5e9 0.25 5e8"),
            Ok(Command::Tune { key: TuningKey::EkfQ, values: Some([1e-12, 1e-6, 1.5e9, 0.25, 5e8]) })
        );
        assert_eq!(p("tune ekf q"), Ok(Command::Tune { key: TuningKey::EkfQ, values: None }));
        assert_eq!(p("tune spike_ratio 0"), Ok(Command::Tune { key: TuningKey::SpikeRatio, values: Some([0.0; 5]) }));
        assert_eq!(p("tune spike_ratio"), Ok(Command::Tune { key: TuningKey::SpikeRatio, values: None }));
        assert_eq!(p("tune initial arx"), Ok(Command::FromEstimate { estimator: 3, prefilter: false }));
        assert_eq!(p("tune initial  rls "), Ok(Command::FromEstimate { estimator: 0, prefilter: false }));
        assert_eq!(p("tune stage hekf"), Ok(Command::FromEstimate { estimator: 2, prefilter: true }));
        // Out of range parses: `Tuning::set` refuses it with the range (the console's test).
        assert_eq!(
            p("tune ekf reopen 5000"),
            Ok(Command::Tune { key: TuningKey::EkfReopen, values: Some([5000.0, 0.0, 0.0, 0.0, 0.0]) })
        );
    }

    #[test]
    fn help_names_every_command_and_only_commands() {
        let text = std::format!("{}", ParseError::UnknownCommand);
        let listed = text.split_once('(').and_then(|(_, l)| l.strip_suffix(')')).expect("a list");
        let words: std::vec::Vec<&str> = HELP.split_whitespace().collect();
        for name in listed.split(", ") {
            assert!(words.contains(&name), "help lacks {name}");
        }
        for line in HELP.lines() {
            let first = line.split(' ').next().expect("a word");
            assert_ne!(p(first), Err(ParseError::UnknownCommand), "{line}");
        }
    }

    #[test]
    fn every_malformed_line_gets_an_error_that_says_where() {
        use ParseError::*;
        const EKF_KEYS: &str = "q, p0, r, substeps, gate_sigma, change_samples, drift_ratio, reopen or pe_floor_v2";
        let cases: [(&[u8], ParseError); 54] = [
            (b"", Empty),
            (b"   \r", Empty),
            (b"launch", UnknownCommand),
            (b"help me", Extra { word: 2 }),
            (b"select all ekf", Extra { word: 3 }),
            (b"reset none ekf", Invalid { word: 2, expected: EST_LIST }),
            (b"select ekf none", Invalid { word: 3, expected: EST_LIST }),
            (b"adapt ekf kalman", Invalid { word: 3, expected: EST_LIST }),
            (b"STATUS NOW", Extra { word: 2 }),
            (b"status now", Extra { word: 2 }),
            (b"excite", Missing { word: 2, expected: EXCITATIONS }),
            (b"excite square 1", Invalid { word: 2, expected: EXCITATIONS }),
            (b"excite prbs", Missing { word: 3, expected: AMP }),
            (b"excite prbs 11", Invalid { word: 3, expected: AMP }),
            (b"excite prbs -1", Invalid { word: 3, expected: AMP }),
            (b"excite prbs NaN", Invalid { word: 3, expected: AMP }),
            (b"excite prbs inf", Invalid { word: 3, expected: AMP }),
            (b"excite sine 1 0", Invalid { word: 4, expected: HZ }),
            (b"excite sine 1 1e9", Invalid { word: 4, expected: HZ }),
            (b"excite triangle 1 10 3 4", Extra { word: 6 }),
            (b"excite multisine 1 200", Missing { word: 5, expected: HZ_HI }),
            (b"excite multisine 1 800 200", Invalid { word: 5, expected: HZ_HI }),
            (b"excite multisine 1 200 200", Invalid { word: 5, expected: HZ_HI }),
            (b"excite multisine 1 200 800 1 2", Extra { word: 7 }),
            (b"excite triangle 1 10 11", Invalid { word: 5, expected: OFFSET }),
            (b"excite prbs 1 nan", Invalid { word: 4, expected: OFFSET }),
            (b"excite constant", Missing { word: 3, expected: LEVEL }),
            (b"excite constant -10.5", Invalid { word: 3, expected: LEVEL }),
            (b"excite constant 1 2", Extra { word: 4 }),
            (b"excite off 1", Extra { word: 3 }),
            (b"select hekf,,arx", Invalid { word: 2, expected: EST_LIST }),
            (b"reset none", Invalid { word: 2, expected: EST_LIST }),
            (b"freeze", Missing { word: 2, expected: EST_LIST }),
            (b"tuning sine", Invalid { word: 2, expected: "prbs or triangle" }),
            (
                b"limits 5 -5 100",
                Invalid { word: 3, expected: "the highest command in V, above the lowest, at most 10" },
            ),
            // The highest command must be above the lowest, not equal to it.
            (
                b"limits 5 5 100",
                Invalid { word: 3, expected: "the highest command in V, above the lowest, at most 10" },
            ),
            (b"limits -5 5 0", Invalid { word: 4, expected: "a slew limit in V/s, above 0" }),
            (b"record burst 0", Invalid { word: 3, expected: "a sample count, 1 to 1000000" }),
            (b"status\xff", NotAscii { at: 6, byte: 0xff }),
            ("limits \u{2212}5 5 100".as_bytes(), NotAscii { at: 7, byte: 0xe2 }),
            (
                b"tune",
                Missing { word: 2, expected: "initial, prefilter, spike_ratio, stage, rls, ekf (both EKFs) or arx" },
            ),
            (
                b"tune kalman q 1",
                Invalid { word: 2, expected: "initial, prefilter, spike_ratio, stage, rls, ekf (both EKFs) or arx" },
            ),
            // The hybrid EKF's keys are the continuous one's section's.
            (
                b"tune hekf q 1",
                Invalid { word: 2, expected: "initial, prefilter, spike_ratio, stage, rls, ekf (both EKFs) or arx" },
            ),
            (b"tune stage", Missing { word: 3, expected: ESTIMATOR }),
            (b"tune stage 5e5", Invalid { word: 3, expected: ESTIMATOR }),
            (b"tune stage arx 1", Extra { word: 4 }),
            (b"tune ekf gamma 1", Invalid { word: 3, expected: EKF_KEYS }),
            (b"tune ekf q 1 2 3", Missing { word: 7, expected: "5 numbers, for x1 x2 a0 a1 b0" }),
            (b"tune rls gamma x", Invalid { word: 4, expected: "a number" }),
            (b"tune arx lambda 0.5 1", Extra { word: 5 }),
            (b"tune initial kalman", Invalid { word: 3, expected: INITIAL }),
            (b"tune initial 5e5 x 6e6", Invalid { word: 4, expected: "3 numbers: b0 a1 a0" }),
            (b"tune initial arx 1", Extra { word: 4 }),
            (b"tune initial 5e5 arx 6e6", Invalid { word: 4, expected: "3 numbers: b0 a1 a0" }),
        ];
        for (line, err) in cases {
            assert_eq!(parse(line), Err(err), "{:?}", core::str::from_utf8(line));
            // Every error reads as one line.
            let text = std::format!("{err}");
            assert!(!text.is_empty() && !text.contains('\n'), "{text}");
        }
        // At most MAX_LINE bytes: the longest line is read, one byte more is refused.
        let mut longest = [b' '; MAX_LINE + 1];
        longest[..6].copy_from_slice(b"status");
        assert_eq!(parse(&longest[..MAX_LINE]), Ok(Command::Status));
        assert_eq!(parse(&longest), Err(TooLong));
        assert_eq!(parse(&[b'a'; MAX_LINE + 1]), Err(TooLong));
    }

    #[test]
    fn the_line_buffer_splits_lines_and_survives_an_overlong_one() {
        let mut lb = LineBuffer::default();
        let mut out = std::vec::Vec::new();
        let mut feed = |bytes: &[u8]| {
            for &b in bytes {
                if let Some(r) = lb.push(b) {
                    out.push(r);
                }
            }
        };
        feed(b"start\r\nstat");
        feed(b"us\n");
        feed(&[b'x'; 300]);
        feed(b"\nstop\n");
        assert_eq!(out, [Ok(Command::Start), Ok(Command::Status), Err(ParseError::TooLong), Ok(Command::Stop)]);
    }

    /// A terminal's Enter sends `\r` alone (picocom, screen, PuTTY), `\r\n`, or `\n`: each ends one line, also
    /// when the `\r\n` arrives split across two reads. `\n\r` is two line ends (the second an empty line).
    #[test]
    fn every_terminals_line_end_ends_one_line() {
        let mut lb = LineBuffer::default();
        let mut out = std::vec::Vec::new();
        for piece in [&b"start\rstop\r\nstatus\n"[..], b"stop\r", b"\nstart\n\r"] {
            out.extend(piece.iter().filter_map(|&b| lb.push(b)));
        }
        use Command::{Start, Status, Stop};
        assert_eq!(out, [Ok(Start), Ok(Stop), Ok(Status), Ok(Stop), Ok(Start), Err(ParseError::Empty)]);
    }

    /// Typed at a terminal, Backspace (BS or DEL) takes back a byte and Ctrl-U the line: the corrected line is the one
    /// executed. Backspace on an empty line does nothing; on a line too long, which is refused whatever is taken
    /// back, it does not make it short again.
    #[test]
    fn backspace_and_ctrl_u_edit_the_line_typed() {
        let mut lb = LineBuffer::default();
        let mut feed = |bytes: &[u8]| bytes.iter().filter_map(|&b| lb.push(b)).collect::<std::vec::Vec<_>>();
        let prbs = |amplitude_v| Ok(Command::Excite(ExcitationChoice::Prbs { amplitude_v, offset_v: 0.0 }));
        assert_eq!(feed(b"excite prbs 2\x7f1\r"), [prbs(1.0)]);
        assert_eq!(feed(b"excite prbs 1.5\x08\x08\r"), [prbs(1.0)]);
        assert_eq!(feed(b"\x7f\x08stop\r"), [Ok(Command::Stop)]);
        assert_eq!(feed(b"reset ekf\x15status\r"), [Ok(Command::Status)]);
        assert_eq!(feed(b"stopp\x7f\x7f\x7f\x7f\x7f\x7f\r"), [Err(ParseError::Empty)]);
        let mut long = [b'x'; MAX_LINE + 2].to_vec();
        long.extend_from_slice(&[0x7F; 4]);
        long.push(b'\r');
        assert_eq!(feed(&long), [Err(ParseError::TooLong)]);
        // Ctrl-U clears an overflowed line: what is typed after it is a line of its own.
        let mut long = [b'x'; MAX_LINE + 2].to_vec();
        long.extend_from_slice(b"\x15start\r");
        assert_eq!(feed(&long), [Ok(Command::Start)]);
    }

    /// Bytes lost on the link: the line they belonged to is refused whole at its end, not executed as what
    /// arrived of it; the next line is read as usual.
    #[test]
    fn a_line_that_lost_bytes_is_refused_whole() {
        let mut lb = LineBuffer::default();
        fn feed(lb: &mut LineBuffer, bytes: &[u8]) -> std::vec::Vec<Result<Command, ParseError>> {
            bytes.iter().filter_map(|&b| lb.push(b)).collect()
        }
        assert!(feed(&mut lb, b"excite prbs 1").is_empty());
        lb.lost_bytes();
        assert_eq!(feed(&mut lb, b"\n"), [Err(ParseError::Damaged)]);
        assert_eq!(feed(&mut lb, b"status\n"), [Ok(Command::Status)]);
        // Lost between lines: the next one is the damaged one.
        lb.lost_bytes();
        assert_eq!(feed(&mut lb, b"atus\r\nstop\r\n"), [Err(ParseError::Damaged), Ok(Command::Stop)]);
        assert_eq!(std::format!("{}", ParseError::Damaged), "bytes of this line were lost on the link: send it again");
        assert_eq!(
            std::format!("{}", parse("limits \u{2212}5 5 100".as_bytes()).unwrap_err()),
            "byte 8 is not printable ASCII, the start of a Unicode character (a pasted minus sign or \
             non-breaking space?)"
        );
    }

    /// A read that came with a receive error refuses every line it touches; one that took the whole receive buffer
    /// (it was full: bytes after it may have been dropped) refuses the line it leaves in progress; a clean read
    /// refuses nothing; one dropped before its last line refuses the line after.
    #[test]
    fn a_read_with_an_error_or_from_a_full_buffer_refuses_the_lines_it_may_have_damaged() {
        let mut lb = LineBuffer::default();
        fn read(
            lb: &mut LineBuffer,
            bytes: &[u8],
            error: bool,
            capacity: usize,
        ) -> std::vec::Vec<Result<Command, ParseError>> {
            lb.read(bytes, error, capacity).collect()
        }
        use Command::{Start, Status, Stop};
        let damaged = Err(ParseError::Damaged);
        assert_eq!(read(&mut lb, b"start\nsta", false, 128), [Ok(Start)]);
        assert_eq!(read(&mut lb, b"tus\nstop\nsta", true, 128), [damaged, damaged]);
        assert_eq!(read(&mut lb, b"rt\nstop\n", false, 128), [damaged, Ok(Stop)]);
        assert_eq!(read(&mut lb, b"status\nsta", false, 10), [Ok(Status)]);
        assert_eq!(read(&mut lb, b"rt\nstop\n", false, 10), [damaged, Ok(Stop)]);
        // Lines left unread when the read is dropped count as lost: the next line is refused.
        assert_eq!(lb.read(b"stop\nstart\nsta", false, 128).next(), Some(Ok(Stop)));
        assert_eq!(read(&mut lb, b"tus\nstop\n", false, 128), [damaged, Ok(Stop)]);
    }

    /// The console's reads of the link's receive buffer, modelled: a buffer of 128 bytes that drops what arrives
    /// while it is full (as embassy's buffered UART does, silently), bytes changed or lost with a receive error,
    /// and reads at random moments that take everything with the error flag. Whatever the link does, no command is
    /// executed but one that was sent, whole, in order; a line lost whole gets no verdict.
    #[test]
    fn no_line_the_link_damaged_is_executed() {
        use std::collections::VecDeque;
        const CAPACITY: usize = 128;
        let mut rnd = crate::xorshift64(0x5eed_1e55);
        let lines: std::vec::Vec<std::string::String> = (0..20_000)
            .map(|k| match rnd() % 3 {
                0 => std::format!("excite constant {}.{}", rnd() % 10, rnd() % 1000),
                1 => std::format!("limits -{}.{} {}.{} {}", rnd() % 10, rnd() % 100, rnd() % 10, rnd() % 100, 100 + k),
                _ => std::format!("record burst {}", 1 + k),
            })
            .collect();
        let stream: std::vec::Vec<u8> = lines.iter().flat_map(|l| l.bytes().chain([b'\n'])).collect();
        let (mut ring, mut error, mut at) = (VecDeque::new(), false, 0);
        let (mut lb, mut next, mut executed, mut refused) = (LineBuffer::default(), 0, 0, 0);
        while at < stream.len() || !ring.is_empty() {
            // Bytes arrive until the next read: sometimes more than the buffer holds.
            let gap = if rnd() % 8 == 0 { rnd() % 400 } else { rnd() % 100 };
            for _ in 0..gap {
                let Some(&b) = stream.get(at) else { break };
                at += 1;
                match rnd() % 2000 {
                    0 => error = true,                               // overrun: lost
                    1 => (error, _) = (true, ring.push_back(b ^ 4)), // framing or noise: changed
                    _ if ring.len() == CAPACITY => {}                // dropped without a word
                    _ => ring.push_back(b),
                }
            }
            // One read: everything there, and the errors noted so far.
            let bytes: std::vec::Vec<u8> = ring.drain(..).collect();
            for parsed in lb.read(&bytes, core::mem::take(&mut error), CAPACITY) {
                match parsed {
                    Ok(cmd) => {
                        let sent = lines[next..].iter().position(|l| parse(l.as_bytes()) == Ok(cmd));
                        let Some(k) = sent else {
                            panic!("executed {cmd:?}, which was not sent (next sent: {:?})", lines[next])
                        };
                        (next, executed) = (next + k + 1, executed + 1);
                    }
                    Err(e) => {
                        assert_eq!(e, ParseError::Damaged);
                        refused += 1;
                    }
                }
            }
        }
        // Every case exercised, many times.
        let lost = lines.len() - executed - refused;
        assert!(
            executed > 10_000 && refused > 500 && lost > 100,
            "{executed} executed, {refused} refused, {lost} lost"
        );
    }
}
