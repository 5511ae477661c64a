//! The `nanopos-sim` commands, one file each, and what they share: the error type (one line, exit code 2), output
//! files that appear only when complete, and progress on a terminal.

pub mod commands;
pub mod console;
pub mod decode;
pub mod fit;
pub mod identify;
pub mod paper;
pub mod send;
pub mod simulate;

use std::fmt;
use std::fs::File;
use std::io::{BufWriter, IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// A user-facing error: one line that names what was wrong and where.
#[derive(Debug)]
pub struct CliError(pub String);

impl fmt::Display for CliError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for CliError {}

/// A number as JSON: the shortest text that reads back to `x` (`1e-6`, `0.25`), or `null` for NaN and the
/// infinities, which JSON has no word for (a diverged estimate's `f0_hz` is NaN; `NaN` in the text would make the
/// whole file unreadable to a JSON parser).
pub fn json_number(x: f64) -> String {
    if x.is_finite() {
        format!("{x:?}")
    } else {
        "null".into()
    }
}

/// A number for a message: as `Display` writes it for everyday magnitudes, in exponent form beyond them, where
/// `Display` would write `1e300` with 300 digits and `1e-300` with 300 zeros.
pub fn show(x: f64) -> String {
    if x == 0.0 || !x.is_finite() || (1e-4..1e16).contains(&x.abs()) {
        format!("{x}")
    } else {
        format!("{x:e}")
    }
}

/// Text from the input as a message quotes it: whole up to `max` characters, else its first `max` and how long it
/// is (a field of ten million digits made a ten-megabyte error line); characters a terminal would not show as
/// themselves escaped as Rust writes them (`\r`, `\u{feff}`: a carriage return inside a field sent the cursor back
/// over the message's start).
pub fn clip(text: &str, max: usize) -> String {
    let (shown, more) = match text.char_indices().nth(max) {
        None => (text, String::new()),
        Some((cut, _)) => (&text[..cut], format!("... ({} characters)", text.chars().count())),
    };
    let escaped: String = shown
        .chars()
        .map(|c| if matches!(c, '\'' | '"' | '\\') { c.to_string() } else { c.escape_debug().to_string() })
        .collect();
    escaped + &more
}

/// `n` and the noun for it, singular for one: `count(1, "time", "times")` is `1 time`.
pub fn count(n: impl Into<u64>, one: &str, many: &str) -> String {
    let n = n.into();
    format!("{n} {}", if n == 1 { one } else { many })
}

/// `x` to three significant digits, as a note gives a figure.
pub fn sig(x: f64) -> String {
    if x == 0.0 || !x.is_finite() {
        format!("{x}")
    } else if (1e-3..1e6).contains(&x.abs()) {
        // The digits after the point that leave three significant ones.
        let after = (2 - x.abs().log10().floor() as i32).clamp(0, 5) as usize;
        format!("{x:.after$}")
    } else {
        format!("{x:.2e}")
    }
}

/// How large one column of a record runs: its largest magnitude and when, and a histogram of the magnitudes in
/// steps of a quarter octave (the binary exponent and the mantissa's first two bits), from which the level most of
/// the samples stay within is read to 19 % without holding the column.
#[derive(Clone, Debug)]
pub struct Spread {
    /// Samples per quarter octave of `|x|`: the top 13 bits of its `f64` (0: zero and the smallest subnormals).
    by_exponent: Box<[u64; 1 << 13]>,
    /// The largest `|x|`.
    pub largest: f64,
    /// Where the first sample that reached it is: the `at` it was added with (`identify` gives the time, s; `fit`
    /// the sample's index).
    pub largest_at: f64,
}

impl Default for Spread {
    fn default() -> Self {
        Spread { by_exponent: Box::new([0; 1 << 13]), largest: 0.0, largest_at: f64::NAN }
    }
}

impl Spread {
    /// How many times the level 90 % of the samples stay within a sample may reach before [`Self::wild`] says so.
    /// One sample of `y` at 10^5 times the PRBS record's level (under 1 um) left the hybrid EKF with a model 200-300
    /// times worse than the data for the rest of the record (`wild_samples_are_noted`; the continuous EKF, which
    /// did at 10^4 until its health logic reset on an innovation beyond a metre, now resets and relocks); at 10^3
    /// both kept their estimates, their innovation RMS inflated for a while. A record's own peaks reach a few times
    /// its level.
    pub const WILD: f64 = 1e3;

    /// Count `x`, the sample at `at`.
    pub fn add(&mut self, x: f64, at: f64) {
        let m = x.abs();
        self.by_exponent[(m.to_bits() >> 50) as usize & 0x1fff] += 1;
        if m > self.largest {
            (self.largest, self.largest_at) = (m, at);
        }
    }

    /// An upper bound, within 19 %, of the level a share `q` (0 to 1) of the samples stay within (`0` when that many
    /// are zero or subnormal).
    pub fn level(&self, q: f64) -> f64 {
        let total: u64 = self.by_exponent.iter().sum();
        let mut seen = 0;
        for (e, &count) in self.by_exponent.iter().enumerate() {
            seen += count;
            if seen as f64 >= q * total as f64 && seen > 0 {
                // Bucket `e` holds the magnitudes whose top bits are `e`; the next bucket's first is its bound.
                return if e == 0 { 0.0 } else { f64::from_bits((e as u64 + 1).min(0x1ff8) << 50) };
            }
        }
        0.0
    }

    /// The largest sample's ratio to the level 90 % of the samples stay within, when it is over [`Self::WILD`].
    pub fn wild(&self) -> Option<f64> {
        self.wild_at(self.largest)
    }

    /// [`Self::wild`] of a sample of magnitude `x`.
    pub fn wild_at(&self, x: f64) -> Option<f64> {
        let level = self.level(0.9);
        (level > 0.0 && x > Self::WILD * level).then(|| x / level)
    }

    /// When [`Self::wild`], what a note says of it: the column's largest sample, `at` (where it is, as the command
    /// can say it), and how far above the record's level.
    pub fn wild_note(&self, column: &str, unit: &str, at: &str) -> Option<String> {
        self.wild().map(|ratio| {
            format!(
                "{column} reaches {} {unit} at {at}, {} times the level 90 % of the record stays within ({} {unit}): \
                 a glitch, or a logger's overflow value?",
                sig(self.largest),
                sig(ratio),
                sig(self.level(0.9)),
            )
        })
    }
}

/// `--gain-drift PCT_PER_MIN` as the plant takes it ([`crate::plant::PlantSettings::gain_drift_per_s`]): a number,
/// in % of the starting gain per minute.
pub fn gain_drift_per_s(pct_per_min: f64) -> Result<f64, CliError> {
    if !pct_per_min.is_finite() {
        return fail(format!("--gain-drift {}: must be a number (% per minute)", show(pct_per_min)));
    }
    Ok(pct_per_min / 100.0 / 60.0)
}

/// `--hum HZ:NM`: a sinusoid of mains pickup on the probe's reading ([`crate::board::BoardSettings::hum`]), its
/// frequency in Hz (below the board's Nyquist frequency) and peak amplitude in nm (up to the probe's range).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HumArg(pub crate::board::Tone);

impl std::str::FromStr for HumArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || {
            format!(
                "'{s}': expected HZ:NM, a frequency in Hz (above 0, below the board's 5 kHz Nyquist frequency) and a \
                 peak amplitude in nm (0 to 50 000, the probe's range), as 50:20"
            )
        };
        let (hz, nm) = s.split_once(':').ok_or_else(bad)?;
        let (hz, nm) = (hz.trim().parse::<f64>().map_err(|_| bad())?, nm.trim().parse::<f64>().map_err(|_| bad())?);
        if !(hz > 0.0 && hz < 5e3 && (0.0..=5e4).contains(&nm)) {
            return Err(bad());
        }
        Ok(HumArg(crate::board::Tone { amplitude_um: nm * 1e-3, freq_hz: hz }))
    }
}

/// The board's [`crate::board::BoardSettings::hum`] from the `--hum` options given (at most two).
pub fn hum_tones(hum: &[HumArg]) -> Result<[crate::board::Tone; 2], CliError> {
    let mut tones = [crate::board::Tone::default(); 2];
    if hum.len() > tones.len() {
        return fail(format!("--hum: at most {} tones ({} given)", tones.len(), hum.len()));
    }
    for (t, h) in tones.iter_mut().zip(hum) {
        *t = h.0;
    }
    Ok(tones)
}

/// Largest `--noise`, nm RMS: the probe's range, as `--hum` takes it.
pub const MAX_NOISE_NM: f64 = 5e4;

/// Most degrees of freedom `--noise-tail` takes: each reading draws that many normals more, and at 100 the noise's
/// excess kurtosis is 0.06 (0 for a Gaussian), beyond which the option changes nothing one could measure.
pub const MAX_NOISE_TAIL_DOF: u32 = 100;

/// The departures from the paper's board that `simulate` and `console` both take: the piezo's gain drift
/// (`--gain-drift`), mains pickup (`--hum`), and the probe's noise on the displacement, its RMS (`--noise`,
/// [`crate::board::BoardSettings::noise_um_rms`], the paper's 1.25 nm if not given) and its distribution
/// (`--noise-tail`: Gaussian, or Student's t with `DOF` degrees of freedom at the same RMS,
/// [`crate::board::BoardSettings::noise_tail_dof`]: heavier tails, the fewer the degrees).
#[derive(Clone, Debug, Default, PartialEq, clap::Args)]
pub struct Disturbances {
    /// Let the piezo's gain drift (as with temperature) at this many % of its starting value per minute, negative
    /// for a fall (stopping at zero): the stage's b0 (and the truth's) at the rate
    #[arg(long = "gain-drift", value_name = "PCT_PER_MIN", default_value_t = 0.0, allow_negative_numbers = true)]
    pub gain_drift_pct_per_min: f64,
    /// Add mains pickup to the probe's reading: a sinusoid of HZ Hz and NM nm peak (up to two: --hum 50:20
    /// --hum 150:5)
    #[arg(long, value_name = "HZ:NM", allow_hyphen_values = true)]
    pub hum: Vec<HumArg>,
    /// The probe's noise on the displacement, nm RMS (0 to 50 000) [default: 1.25, the paper's]
    #[arg(long = "noise", value_name = "NM", allow_negative_numbers = true)]
    pub noise_rms_nm: Option<f64>,
    /// Make the probe's noise heavier-tailed at the same RMS: Student's t with DOF degrees of freedom (3 to 100;
    /// the fewer, the heavier: 3 has outliers of 10 times the RMS) instead of Gaussian
    #[arg(long = "noise-tail", value_name = "DOF", allow_negative_numbers = true)]
    pub noise_tail_dof: Option<u32>,
}

impl Disturbances {
    /// Checked, onto `board`.
    pub fn apply(&self, board: &mut crate::board::BoardSettings) -> Result<(), CliError> {
        board.plant.gain_drift_per_s = gain_drift_per_s(self.gain_drift_pct_per_min)?;
        board.hum = hum_tones(&self.hum)?;
        if let Some(nm) = self.noise_rms_nm {
            if !(0.0..=MAX_NOISE_NM).contains(&nm) {
                return fail(format!("--noise {}: must be 0 to {MAX_NOISE_NM} nm RMS", show(nm)));
            }
            board.noise_um_rms = nm / 1e3;
        }
        if let Some(dof) = self.noise_tail_dof {
            if !(3..=MAX_NOISE_TAIL_DOF).contains(&dof) {
                return fail(format!(
                    "--noise-tail {dof}: must be 3 to {MAX_NOISE_TAIL_DOF} degrees of freedom (below 3 the noise has \
                     no finite RMS)"
                ));
            }
            board.noise_tail_dof = Some(dof);
        }
        Ok(())
    }
}

/// Shorthand for building a [`CliError`].
pub fn fail<T>(msg: impl Into<String>) -> Result<T, CliError> {
    Err(CliError(msg.into()))
}

/// The temporaries of the [`OutputFile`]s being written, for [`handle_ctrl_c`] to remove.
static PARTIALS: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

fn partials() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    PARTIALS.lock().unwrap_or_else(|e| e.into_inner())
}

/// Ctrl-C (SIGINT): the outputs being written are removed (no `.NAME.partial-PID` left behind, no output under its
/// name) and the process ends with exit code 130, as the shell reports one the signal ended. With `graceful` (the
/// console), the first Ctrl-C only sets it, for the command to end as the input's end would; the second ends it
/// at once. Without a handler (it could not be installed) Ctrl-C ends the process as it would anyway.
pub fn handle_ctrl_c(graceful: Option<Arc<AtomicBool>>) {
    let installed = ctrlc::set_handler(move || {
        if graceful.as_ref().is_some_and(|g| !g.swap(true, Ordering::Relaxed)) {
            return;
        }
        for temp in partials().drain(..) {
            let _ = std::fs::remove_file(temp);
        }
        std::process::exit(130);
    });
    if let Err(e) = installed {
        eprintln!("nanopos-sim: note: no Ctrl-C handler ({e}): an interruption may leave a .NAME.partial-PID file");
    }
}

/// An output file written under a temporary name in the same directory and renamed into place by
/// [`OutputFile::commit`]; dropped without commit (an error, a panic), it removes the temporary, so no partial file
/// is ever left under the requested name.
///
/// A path that names a device, a pipe or a socket (`/dev/stdout`, a named pipe another program reads) is a stream,
/// not a file to replace: it is written directly, and `commit` only flushes it. (Renamed over, `/dev/stdout` itself
/// was replaced by a regular file when run as root, and as anyone else the temporary could not be made in `/dev`.)
/// A symbolic link is followed: the file it names is replaced, next to it, and the link stays (renamed over, the
/// link was replaced by the file and the file it named kept the old contents).
pub struct OutputFile {
    /// As the user named it (for messages).
    path: PathBuf,
    /// Where the file goes: `path`, or the file a link at `path` names.
    target: PathBuf,
    /// The temporary name; `None` for a stream.
    temp: Option<PathBuf>,
    writer: Option<BufWriter<File>>,
}

/// Whether what a path names is a device, a pipe or a socket: a stream, written directly, with no file to replace.
pub(crate) fn is_stream(m: &std::fs::Metadata) -> bool {
    !m.is_file() && !m.is_dir()
}

/// The file `path` names through any symbolic links (the last one's target may not exist yet); `path` itself if it
/// is not a link, or the links go round in a loop.
fn link_target(path: &Path) -> PathBuf {
    let mut at = path.to_path_buf();
    for _ in 0..40 {
        match std::fs::read_link(&at) {
            Ok(to) => at = at.parent().map_or(to.clone(), |dir| dir.join(&to)),
            Err(_) => return at,
        }
    }
    path.to_path_buf()
}

impl OutputFile {
    /// Start writing `path`.
    pub fn create(path: &Path) -> Result<Self, CliError> {
        let cannot = |e: std::io::Error| CliError(format!("{}: cannot create: {}", path.display(), io_reason(&e)));
        let (file, target, temp) = match std::fs::metadata(path) {
            Ok(m) if m.is_dir() => return fail(format!("{}: is a directory, not a file name", path.display())),
            Ok(m) if is_stream(&m) => {
                (File::options().write(true).open(path).map_err(cannot)?, path.to_path_buf(), None)
            }
            _ => {
                let target = link_target(path);
                let name =
                    target.file_name().ok_or_else(|| CliError(format!("{}: not a file name", path.display())))?;
                let temp = target.with_file_name(format!(".{}.partial-{}", name.to_string_lossy(), std::process::id()));
                let file = File::create(&temp).map_err(cannot)?;
                partials().push(temp.clone());
                (file, target, Some(temp))
            }
        };
        Ok(OutputFile { path: path.to_path_buf(), target, temp, writer: Some(BufWriter::with_capacity(1 << 20, file)) })
    }

    /// The path it will have.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The buffered writer.
    pub fn writer(&mut self) -> &mut BufWriter<File> {
        self.writer.as_mut().expect("writer present until commit")
    }

    /// A write error, named after the final path.
    pub fn write_error(&self, e: std::io::Error) -> CliError {
        CliError(format!("{}: cannot write: {}", self.path.display(), io_reason(&e)))
    }

    /// Flush and move into place (a stream: flush). On an error the temporary is removed.
    pub fn commit(mut self) -> Result<(), CliError> {
        let (w, temp) = (self.writer.take().expect("commit once"), self.temp.take());
        let done = w.into_inner().map_err(|e| self.write_error(e.into_error())).and_then(|file| {
            let Some(temp) = &temp else { return Ok(()) };
            file.sync_all().map_err(|e| self.write_error(e))?;
            std::fs::rename(temp, &self.target)
                .map_err(|e| CliError(format!("{}: cannot move into place: {}", self.path.display(), io_reason(&e))))
        });
        if let Some(temp) = &temp {
            forget_partial(temp);
            if done.is_err() {
                let _ = std::fs::remove_file(temp);
            }
        }
        done
    }
}

/// `temp` renamed into place or removed: no longer one for [`handle_ctrl_c`] to remove.
fn forget_partial(temp: &Path) {
    partials().retain(|p| p != temp);
}

impl Drop for OutputFile {
    fn drop(&mut self) {
        if let (Some(_), Some(temp)) = (self.writer.take(), &self.temp) {
            forget_partial(temp);
            let _ = std::fs::remove_file(temp);
        }
    }
}

/// Write `text` to standard output and flush it: an error (a full disk, a closed pipe) is reported, not lost with
/// the output, as `print!` loses it when the buffer is flushed at exit.
pub fn write_stdout(text: &str) -> Result<(), CliError> {
    let mut out = std::io::stdout().lock();
    out.write_all(text.as_bytes()).and_then(|()| out.flush()).map_err(stdout_error)
}

/// A failed write to standard output, as every command reports it.
pub fn stdout_error(e: std::io::Error) -> CliError {
    CliError(format!("standard output: cannot write: {}", io_reason(&e)))
}

/// What a path names, to tell whether two paths are one file however they are spelled: an existing file by its device
/// and inode on Unix (the same through `..`, symbolic links and hard links), elsewhere by its canonical path (the
/// same through `..` and symbolic links, not hard links), a file yet to be made by its directory's canonical path and
/// its name.
#[derive(Debug, PartialEq)]
enum FileId {
    #[cfg(unix)]
    Existing(u64, u64),
    New(PathBuf),
}

/// `None` when it cannot be told (its directory does not exist: creating the file will fail and say so), and for a
/// device, a pipe or a socket: a stream, written directly with nothing to replace (reading `/dev/stdin` and writing
/// `/dev/stdout` in a terminal names one device twice, and is no conflict).
fn file_id(path: &Path) -> Option<FileId> {
    match std::fs::metadata(path) {
        Ok(m) if is_stream(&m) => None,
        #[cfg(unix)]
        Ok(m) => {
            use std::os::unix::fs::MetadataExt;
            Some(FileId::Existing(m.dev(), m.ino()))
        }
        #[cfg(not(unix))]
        Ok(_) => std::fs::canonicalize(path).ok().map(FileId::New),
        Err(_) => {
            let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
            Some(FileId::New(std::fs::canonicalize(dir).ok()?.join(path.file_name()?)))
        }
    }
}

/// Refuse, before anything is read or written, outputs that would replace an input (the file a user recorded on the
/// board, the tuning they wrote) or each other (two outputs under one name: one of them lost). Each file is given
/// with the option that named it, for the message.
pub fn check_distinct(inputs: &[(&str, &Path)], outputs: &[(&str, &Path)]) -> Result<(), CliError> {
    let ids: Vec<_> = outputs.iter().map(|(_, p)| file_id(p)).collect();
    for (k, ((option, path), id)) in outputs.iter().zip(&ids).enumerate() {
        let Some(id) = id else { continue };
        if let Some((input_option, input)) = inputs.iter().find(|(_, p)| file_id(p).as_ref() == Some(id)) {
            return fail(format!(
                "{option} {}: the same file as {input_option} {}: writing it would replace the input; choose \
                 another name",
                path.display(),
                input.display()
            ));
        }
        if let Some(j) = ids[..k].iter().position(|other| other.as_ref() == Some(id)) {
            return fail(format!(
                "{option} {}: the same file as {} {}: each output needs a file of its own",
                path.display(),
                outputs[j].0,
                outputs[j].1.display()
            ));
        }
    }
    Ok(())
}

/// Open an input file, or say why not as the other messages do: `-`, which many tools read as standard input, is a
/// file name here, and a missing `-` says where standard input is.
pub fn open_input(path: &Path) -> Result<File, CliError> {
    File::open(path).map_err(|e| {
        let stdin = if path == Path::new("-") && e.kind() == std::io::ErrorKind::NotFound {
            " (standard input is /dev/stdin here, not -)"
        } else {
            ""
        };
        CliError(format!("{}: cannot open: {}{stdin}", path.display(), io_reason(&e)))
    })
}

/// An I/O error's reason without Rust's " (os error N)" suffix.
pub fn io_reason(e: &std::io::Error) -> String {
    let s = e.to_string();
    match s.find(" (os error") {
        Some(i) => s[..i].to_string(),
        None => s,
    }
}

/// Progress on standard error, only when it is a terminal.
pub struct Progress {
    label: &'static str,
    total: u64,
    shown_percent: u64,
    enabled: bool,
}

impl Progress {
    /// Progress over `total` steps.
    pub fn new(label: &'static str, total: u64) -> Self {
        Progress { label, total: total.max(1), shown_percent: u64::MAX, enabled: std::io::stderr().is_terminal() }
    }

    /// Report that `done` steps are done.
    #[inline]
    pub fn update(&mut self, done: u64) {
        if !self.enabled {
            return;
        }
        let percent = done * 100 / self.total;
        if percent != self.shown_percent {
            self.shown_percent = percent;
            eprint!("\r{}: {percent:3}%", self.label);
        }
    }

    /// Clear the line.
    pub fn finish(&self) {
        if self.enabled {
            eprint!("\r{}\r", " ".repeat(self.label.len() + 6));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A message's count reads as English: one of a thing, and none or many of things.
    #[test]
    fn a_count_of_one_is_singular() {
        assert_eq!(count(1u32, "time", "times"), "1 time");
        assert_eq!(count(0u32, "time", "times"), "0 times");
        assert_eq!(count(48u64, "sample", "samples"), "48 samples");
    }

    /// What a message quotes from the input: control characters escaped, quotes as they are, long text cut.
    #[test]
    fn a_quote_shows_what_a_terminal_would_hide() {
        assert_eq!(clip("1\r5", 40), "1\\r5");
        assert_eq!(clip("\u{feff}t", 40), "\\u{feff}t");
        assert_eq!(clip("\"1\"'", 40), "\"1\"'");
        assert_eq!(clip("−5", 40), "−5");
        assert_eq!(clip("abcdef", 3), "abc... (6 characters)");
    }

    /// An output committed or dropped forgets its own temporary only: those of the others still being written stay
    /// listed, for a Ctrl-C between two outputs' commits to remove.
    #[test]
    fn an_output_done_leaves_the_others_temporaries_listed() {
        let dir = tempfile::tempdir().unwrap();
        let [a, b, c] = ["a.csv", "b.csv", "c.csv"].map(|name| dir.path().join(name));
        let [fa, fb, fc] = [&a, &b, &c].map(|path| OutputFile::create(path).unwrap());
        let [ta, tb, tc] = [&fa, &fb, &fc].map(|f| f.temp.clone().expect("a file, not a stream"));
        let listed = |temp: &PathBuf| partials().contains(temp);
        assert!(listed(&ta) && listed(&tb) && listed(&tc));
        fa.commit().unwrap();
        assert!(a.exists() && !ta.exists());
        assert!(!listed(&ta) && listed(&tb) && listed(&tc));
        drop(fb);
        assert!(!b.exists() && !tb.exists());
        assert!(!listed(&tb) && listed(&tc));
        fc.commit().unwrap();
        assert!(!listed(&tc));
    }
}
