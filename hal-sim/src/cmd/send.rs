//! `nanopos-sim send [--port DEVICE] [--input SCRIPT] [--capture FILE] [--timeout S] [--baud N]`: a script of console
//! lines to the board, each sent after the last one's verdict, and what the board sends back to standard output (or,
//! for the recording's stream, to a capture file that `decode` reads).
//!
//! The board's console takes a line at a time: its receive buffer holds 128 bytes, and what arrives while it is full
//! (during a long reply, or a `tune` being designed) is dropped (the README's "Run-time control"). So each line goes
//! out only once the reply to the one before has ended, with its verdict: a line starting `ok` or `error:`.
//!
//! The script, a line per command (the README's commands; what `nanopos-sim commands` writes):
//! - blank lines and lines starting with `#` are skipped;
//! - `sleep S` waits S seconds (0 to 86 400), receiving all the while (the estimators converge, a recording streams);
//! - every other line is sent as it is, trimmed of the spaces around it, ended by `\n`; the board checks it.
//!
//! It stops at the first line the board refuses (`error: ...`; a refused command changes nothing, and the lines after
//! it may have counted on it) and at a line that gets no verdict within `--timeout` (2 s: the usual commands take 2 to
//! 7 ms on the board and the slowest, a `tune` refused after the longest design, about 55 ms, by BENCHMARKS.md's
//! estimate; a line lost whole on the link gets none), naming the script's line; the exit code is then 2 and the lines
//! after it are not sent.
//!
//! A recording it started is taken to its end: at the script's end (or a refusal) a `record on` still running is
//! stopped with `record off` (as `nanopos-sim console` does at its input's end), a burst runs to its last sample (a
//! Ctrl-C stops either), and `send` waits for the recording's end line (`# nanopos-record end ...`) as long as the
//! stream keeps coming. With `--capture FILE` every byte received goes to FILE as it arrives (kept whatever happens
//! after: it is the board's data), and standard output has the rest: the lines sent (after `> `) and the replies,
//! without the recording's lines; without it, standard output has everything (a line that does not end within 4 KiB,
//! noise at the wrong baud rate, in pieces of that length).
//!
//! Before the first line `send` sends Ctrl-U, which clears whatever a terminal left typed on the board's line (the
//! console answers nothing to it), and drops what arrives in the next 0.2 s, with a note when something did: the end
//! of a reply to someone else's command, or a recording left running, whose frames then go on without their header
//! until a `record off`.
//!
//! The link is a [`Link`]: the serial port ([`SerialLink`], the `serialport` crate's on Linux, macOS and Windows,
//! held by this program alone while it runs) on the command line, a channel to the simulated console in the tests.
//! Without `--port` it is the one ST-LINK virtual COM port plugged in ([`find_port`]).

use super::{clip, io_reason, stdout_error, CliError};
use nanopos_id::control::{parse, Command, Recording};
use nanopos_id::record::{END_TAG, HEADER_TAG, HEADER_TAG_V1, TUNING_TAG};
use std::io::{BufRead, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The board's console link, as `send` uses it.
pub trait Link {
    /// What arrived, into `buf`: waits at most about 0.1 s, and gives 0 when nothing did.
    fn receive(&mut self, buf: &mut [u8]) -> std::io::Result<usize>;
    /// Send all of `bytes`.
    fn transmit(&mut self, bytes: &[u8]) -> std::io::Result<()>;
    /// What the messages call it.
    fn name(&self) -> String {
        "the link".into()
    }
}

/// How long `send` drops what arrives after its Ctrl-U, before the first line.
const SETTLE: Duration = Duration::from_millis(200);

/// The longest `sleep`, s: a day.
const MAX_SLEEP_S: f64 = 86_400.0;

/// The longest line `send` holds before it shows it, bytes: far beyond the board's longest, a frame's 276.
const MAX_RECEIVED_LINE: usize = 4096;

/// Ctrl-U: the board's console clears the line typed so far.
const CLEAR_LINE: u8 = 0x15;

/// The command line's options.
pub struct SendOptions {
    /// How long a line may wait for its verdict, and the recording's stream for its next bytes at the end.
    pub timeout: Duration,
    /// Set (by a Ctrl-C handler) to send no further line: a recording started is taken to its end, as at the script's
    /// end.
    pub interrupted: Option<Arc<AtomicBool>>,
    /// Write each line sent to the output, after `> ` (not for lines typed at a terminal, which shows them already).
    pub echo: bool,
}

/// What a session did.
#[derive(Debug, Default, PartialEq)]
pub struct Sent {
    /// Lines the board answered `ok` (`sleep` and comments not counted).
    pub accepted: usize,
    /// For standard error: what the user should know that is not an error.
    pub notes: Vec<String>,
}

/// The received stream, line by line: to standard output and the capture, its verdicts and the recording's
/// header and end line told apart.
struct Stream<'a> {
    out: &'a mut dyn Write,
    capture: Option<&'a mut dyn Write>,
    /// The received line not yet ended.
    partial: Vec<u8>,
    /// A recording's header has arrived and its end line not yet.
    recording: bool,
}

/// What [`Stream::pump`] waits for.
enum Until {
    /// A verdict, until this instant.
    Verdict(Instant),
    /// The recording's end line, while the stream goes on: each arrival gives it this long again.
    RecordingEnd(Duration),
    /// Nothing: receive until this instant.
    Time(Instant),
}

/// A frame of the recording: `R` and its first sample's 12 hex digits.
fn is_frame(line: &str) -> bool {
    let b = line.as_bytes();
    b.len() > 13 && b[0] == b'R' && b[1..13].iter().all(u8::is_ascii_hexdigit)
}

/// A line of the recording's stream (header, tuning line, frame, end line), which a capture takes instead of
/// standard output.
fn is_recording_line(line: &str) -> bool {
    is_frame(line) || line.starts_with("# nanopos-record") || line.starts_with(TUNING_TAG)
}

/// The last line of a reply: `ok`, `ok ...` or `error: ...`.
fn is_verdict(line: &str) -> bool {
    line == "ok" || line.starts_with("ok ") || line.starts_with("error:")
}

impl Stream<'_> {
    fn write_out(&mut self, bytes: &[u8]) -> Result<(), CliError> {
        self.out.write_all(bytes).map_err(stdout_error)
    }

    /// Take what the link delivers until `until` is met. Returns the verdict's line for [`Until::Verdict`], an
    /// empty line for the recording's end, `None` when the time ran out first or, but for a verdict's wait (bounded
    /// by the timeout), `interrupted` said so.
    fn pump(
        &mut self,
        link: &mut dyn Link,
        until: Until,
        interrupted: &dyn Fn() -> bool,
    ) -> Result<Option<String>, CliError> {
        let mut buf = [0u8; 4096];
        let mut deadline = match until {
            Until::Verdict(t) | Until::Time(t) => t,
            Until::RecordingEnd(idle) => Instant::now() + idle,
        };
        let mut found = None;
        loop {
            if let Until::RecordingEnd(_) = until {
                if !self.recording {
                    return Ok(Some(String::new()));
                }
            }
            if found.is_some() {
                return Ok(found);
            }
            if Instant::now() >= deadline || !matches!(until, Until::Verdict(_)) && interrupted() {
                return Ok(None);
            }
            let n = link
                .receive(&mut buf)
                .map_err(|e| CliError(format!("{}: cannot read: {}", link.name(), io_reason(&e))))?;
            if n == 0 {
                continue;
            }
            if let Until::RecordingEnd(idle) = until {
                deadline = Instant::now() + idle;
            }
            if let Some(capture) = self.capture.as_mut() {
                capture
                    .write_all(&buf[..n])
                    .and_then(|()| capture.flush())
                    .map_err(|e| CliError(format!("--capture: cannot write: {}", io_reason(&e))))?;
            }
            for &b in &buf[..n] {
                self.partial.push(b);
                // A line ends at its `\n`, or where it grew beyond any the board sends (bytes at the wrong baud
                // rate): shown all the same.
                if b != b'\n' && self.partial.len() < MAX_RECEIVED_LINE {
                    continue;
                }
                let mut bytes = std::mem::take(&mut self.partial);
                if b != b'\n' {
                    bytes.push(b'\n');
                }
                let line = String::from_utf8_lossy(&bytes);
                let text = line.trim_end_matches(['\r', '\n']);
                let recording_line = is_recording_line(text);
                if text.starts_with(HEADER_TAG) || text.starts_with(HEADER_TAG_V1) {
                    self.recording = true;
                } else if text.starts_with(END_TAG) {
                    self.recording = false;
                }
                if !(recording_line && self.capture.is_some()) {
                    self.write_out(&bytes)?;
                }
                if matches!(until, Until::Verdict(_)) && !recording_line && is_verdict(text) && found.is_none() {
                    found = Some(text.to_string());
                }
            }
            self.out.flush().map_err(stdout_error)?;
        }
    }

    /// Send `line` to the board, ended by `\n`; shown first after `> ` when `echo`.
    fn send_line(&mut self, link: &mut dyn Link, line: &[u8], echo: bool) -> Result<(), CliError> {
        if echo {
            self.write_out(&[&b"> "[..], line, b"\n"].concat())?;
        }
        link.transmit(&[line, &b"\n"[..]].concat()).map_err(|e| link_write_error(link, e))
    }

    /// What arrived of a line that never ended, to standard output, so that nothing received is lost from it.
    fn finish(&mut self) -> Result<(), CliError> {
        if !self.partial.is_empty() {
            let mut bytes = std::mem::take(&mut self.partial);
            bytes.push(b'\n');
            self.write_out(&bytes)?;
        }
        self.out.flush().map_err(stdout_error)
    }
}

/// A failed write to `link`, as the messages say it.
fn link_write_error(link: &dyn Link, e: std::io::Error) -> CliError {
    CliError(format!("{}: cannot write: {}", link.name(), io_reason(&e)))
}

/// A script's line, as `send` takes it.
#[derive(Debug, PartialEq)]
enum ScriptLine<'a> {
    /// Blank, or a comment.
    Skip,
    /// `sleep S`.
    Sleep(Duration),
    /// A line for the board.
    Send(&'a [u8]),
}

/// Read a script's line (without its line end).
fn script_line(raw: &[u8]) -> Result<ScriptLine<'_>, String> {
    let line = raw.trim_ascii();
    if line.is_empty() || line.starts_with(b"#") {
        return Ok(ScriptLine::Skip);
    }
    let mut words = line.split(|b| b.is_ascii_whitespace()).filter(|w| !w.is_empty());
    if words.next() != Some(b"sleep".as_slice()) {
        return Ok(ScriptLine::Send(line));
    }
    let seconds = match (words.next(), words.next()) {
        (Some(s), None) => std::str::from_utf8(s).ok().and_then(|s| s.parse::<f64>().ok()),
        _ => None,
    };
    match seconds {
        Some(s) if (0.0..=MAX_SLEEP_S).contains(&s) => Ok(ScriptLine::Sleep(Duration::from_secs_f64(s))),
        _ => Err(format!("expected sleep S, the seconds to wait (0 to {MAX_SLEEP_S})")),
    }
}

/// Run the session: `script` (named `script_name` in messages) line by line over `link`; what the board sends to
/// `out`, its recording's lines to `capture` instead when given (every byte of the stream, as it arrives).
pub fn run<'a>(
    script: &mut dyn BufRead,
    script_name: &str,
    link: &mut dyn Link,
    out: &'a mut dyn Write,
    capture: Option<&'a mut dyn Write>,
    options: &SendOptions,
) -> Result<Sent, CliError> {
    let interrupted = || options.interrupted.as_ref().is_some_and(|i| i.load(Ordering::Relaxed));
    let mut sent = Sent::default();
    // What arrives before the first line is not a reply to the script: dropped, not shown.
    link.transmit(&[CLEAR_LINE]).map_err(|e| link_write_error(link, e))?;
    let mut stale = Vec::new();
    let unended = {
        let mut settle = Stream { out: &mut stale, capture: None, partial: Vec::new(), recording: false };
        settle.pump(link, Until::Time(Instant::now() + SETTLE), &|| false)?;
        settle.partial.len()
    };
    let dropped = stale.len() + unended;
    let frames = String::from_utf8_lossy(&stale).lines().any(is_frame);
    if frames {
        sent.notes.push(format!(
            "a recording was running on the board before the script began ({} of it dropped): its frames go on {}, \
             without their header, until a record off",
            super::count(dropped as u64, "byte", "bytes"),
            if capture.is_some() { "into the capture" } else { "among the replies" }
        ));
    } else if dropped > 0 {
        sent.notes.push(format!(
            "the board was sending before the script began ({}; the end of a reply): dropped",
            super::count(dropped as u64, "byte", "bytes")
        ));
    }
    let mut stream = Stream { out, capture, partial: Vec::new(), recording: false };
    // The recording the script started, if it asked for one until stopped.
    let mut record_on = false;
    let mut outcome = Ok(());
    let mut raw = Vec::new();
    for n in 1.. {
        raw.clear();
        match script.read_until(b'\n', &mut raw) {
            Ok(0) => break,
            Ok(_) => {}
            Err(e) => {
                outcome = Err(CliError(format!("{script_name}: line {n}: cannot read: {}", io_reason(&e))));
                break;
            }
        }
        if interrupted() {
            sent.notes.push(format!("interrupted: {script_name} line {n} and those after it not sent"));
            break;
        }
        let text = raw.strip_suffix(b"\n").unwrap_or(&raw);
        let text = text.strip_suffix(b"\r").unwrap_or(text);
        let shown = || clip(&String::from_utf8_lossy(text.trim_ascii()), 100);
        let line = match script_line(text) {
            Ok(line) => line,
            Err(why) => {
                outcome = Err(CliError(format!("{script_name}: line {n}: '{}': {why}", shown())));
                break;
            }
        };
        match line {
            ScriptLine::Skip => {}
            ScriptLine::Sleep(d) => {
                stream.pump(link, Until::Time(Instant::now() + d), &interrupted)?;
            }
            ScriptLine::Send(cmd) => {
                stream.send_line(link, cmd, options.echo)?;
                match stream.pump(link, Until::Verdict(Instant::now() + options.timeout), &|| false)? {
                    Some(verdict) if verdict.starts_with("error:") => {
                        outcome = Err(CliError(format!(
                            "{script_name}: line {n}: '{}': refused by the board ({}): the lines after it not sent",
                            shown(),
                            clip(&verdict, 200)
                        )));
                        break;
                    }
                    Some(_) => {
                        sent.accepted += 1;
                        if let Ok(Command::Record(r)) = parse(cmd) {
                            record_on = r == Recording::On;
                        }
                    }
                    None => {
                        outcome = Err(CliError(format!(
                            "{script_name}: line {n}: '{}': no verdict from the board within {} s (a board running \
                             the firmware answers every line: check the port, the baud rate, and that no other \
                             program, a terminal left open, reads the port too; a line lost whole on the link gets \
                             none, so ask `status` what it did): the lines after it not sent",
                            shown(),
                            super::show(options.timeout.as_secs_f64())
                        )));
                        break;
                    }
                }
            }
        }
    }
    // A recording the script started is taken to its end, whatever ended the script: one until stopped is stopped,
    // a burst runs to its last sample unless a Ctrl-C stops it too.
    let mut stopped = false;
    while stream.recording {
        if !stopped && (record_on || interrupted()) {
            stopped = true;
            let why = if record_on { "still running at the end" } else { "interrupted" };
            sent.notes.push(format!("the recording {why}: stopped with record off"));
            stream.send_line(link, b"record off", options.echo)?;
            // Its verdict, then the recording's last frames and end line (or they came first).
            stream.pump(link, Until::Verdict(Instant::now() + options.timeout), &|| false)?;
            continue;
        }
        // A first Ctrl-C during a burst ends this wait, to stop it above.
        let stop_it = || !stopped && interrupted();
        if stream.pump(link, Until::RecordingEnd(options.timeout), &stop_it)?.is_none() && !stop_it() {
            let why = format!(
                "the recording's end line did not come: nothing arrived for {} s (what did is kept)",
                super::show(options.timeout.as_secs_f64())
            );
            outcome = outcome.and(Err(CliError(why)));
            break;
        }
    }
    stream.finish()?;
    outcome.map(|()| sent)
}

/// STMicroelectronics' USB vendor ID.
const ST_VID: u16 = 0x0483;

/// The USB product IDs of the ST-LINKs (V2-1, V3 and their variants: 0x374B, 0x374E, 0x374F, 0x3752-0x3757); an STM32's
/// own USB serial port (0x5740) is not one.
const STLINK_PIDS: std::ops::RangeInclusive<u16> = 0x3740..=0x375F;

/// The ports among `ports` (what `serialport::available_ports` lists) that are an ST-LINK's virtual COM port, each
/// with what to show of it. macOS lists each port twice, as `/dev/cu.*` and `/dev/tty.*`: the second (the dial-in
/// device, whose open waits for a carrier) is left out.
pub fn stlink_ports(ports: &[serialport::SerialPortInfo]) -> Vec<(String, String)> {
    ports
        .iter()
        .filter(|p| !p.port_name.starts_with("/dev/tty."))
        .filter_map(|p| match &p.port_type {
            serialport::SerialPortType::UsbPort(usb) if usb.vid == ST_VID && STLINK_PIDS.contains(&usb.pid) => {
                let product = usb.product.as_deref().unwrap_or("ST-LINK");
                let serial = usb.serial_number.as_deref().map(|s| format!(", serial {s}")).unwrap_or_default();
                Some((p.port_name.clone(), format!("{product}{serial}")))
            }
            _ => None,
        })
        .collect()
}

/// No `--port`: the one ST-LINK virtual COM port plugged in, and what to show of it.
pub fn find_port() -> Result<(std::path::PathBuf, String), CliError> {
    let unlisted = |why: &str| CliError(format!("no --port given, and the serial ports cannot be listed: {why}"));
    // serialport lists Linux's ports from sysfs, and panics where it is not mounted (a minimal container).
    if cfg!(target_os = "linux") && !std::path::Path::new("/sys/class/tty").is_dir() {
        return Err(unlisted("no /sys/class/tty: name the port with --port"));
    }
    let ports = serialport::available_ports().map_err(|e| unlisted(&e.description))?;
    let found = stlink_ports(&ports);
    match found.as_slice() {
        [(name, what)] => Ok((name.into(), what.clone())),
        [] => {
            let names: Vec<&str> = ports.iter().map(|p| p.port_name.as_str()).collect();
            let listed = if names.is_empty() { "none".to_string() } else { names.join(", ") };
            Err(CliError(format!(
                "no --port given, and no ST-LINK virtual COM port is plugged in (serial ports: {listed}): connect the \
                 board's USB, or name its port with --port"
            )))
        }
        several => {
            let listed: Vec<String> = several.iter().map(|(name, what)| format!("{name} ({what})")).collect();
            Err(CliError(format!(
                "no --port given, and {} ST-LINK virtual COM ports are plugged in ({}): choose one with --port",
                several.len(),
                listed.join("; ")
            )))
        }
    }
}

/// The board's serial port `path` at `baud`: [`SerialLink::open`].
pub fn open_port(path: &std::path::Path, baud: u32) -> Result<Box<dyn Link>, CliError> {
    Ok(Box::new(SerialLink::open(path, baud)?))
}

/// The board's serial port, raw, 8N1, no flow control, reads returning after at most 0.1 s: the `serialport` crate's,
/// on Linux, macOS and Windows alike.
pub struct SerialLink {
    port: Box<dyn serialport::SerialPort>,
    /// As `--port` named it.
    path: std::path::PathBuf,
}

impl SerialLink {
    /// The baud rates `--baud` takes (the firmware's: 921 600): those every platform's serial driver and the
    /// ST-LINK's virtual COM port have.
    pub const BAUDS: [u32; 8] = [9_600, 19_200, 38_400, 57_600, 115_200, 230_400, 460_800, 921_600];

    /// How long a read waits for the first byte.
    const READ_WAIT: Duration = Duration::from_millis(100);

    /// Open `path` (`/dev/ttyACM0` on Linux, `/dev/cu.usbmodem...` on macOS, `COM5` on Windows: the ST-LINK's virtual
    /// COM port) at `baud`, for this program alone, dropping what it had received. On Unix it is opened without
    /// waiting for a carrier (`O_NONBLOCK`, then `CLOCAL`; a virtual COM port may never raise DCD) and locked against
    /// other programs opening it after (`TIOCEXCL`, `flock`): a terminal program opened on it too would take some of
    /// the replies.
    pub fn open(path: &std::path::Path, baud: u32) -> Result<Self, CliError> {
        use serialport::{ClearBuffer, DataBits, ErrorKind, FlowControl, Parity, StopBits};
        if !Self::BAUDS.contains(&baud) {
            let known: Vec<String> = Self::BAUDS.iter().map(|b| b.to_string()).collect();
            return Err(CliError(format!("--baud {baud}: expected one of {}", known.join(", "))));
        }
        let name = path.to_string_lossy();
        let fail = |e: serialport::Error| {
            let why = match e.kind() {
                ErrorKind::Io(std::io::ErrorKind::PermissionDenied) if cfg!(target_os = "linux") => format!(
                    "{} (a serial port is usually open to the group dialout: sudo usermod -aG dialout $USER, then log \
                     in again)",
                    e.description
                ),
                // Another program holds it (`TIOCEXCL` or `flock` on Unix); on Windows, which opens a port once, also
                // a port that is not there.
                ErrorKind::NoDevice if cfg!(windows) => format!(
                    "{} (no such port: see the Device Manager's Ports; or another program has it open: close it first)",
                    e.description
                ),
                ErrorKind::NoDevice => format!("{} (another program has it open: close it first)", e.description),
                _ => e.description,
            };
            CliError(format!("--port {}: cannot open: {why}", path.display()))
        };
        let port = serialport::new(name, baud)
            .data_bits(DataBits::Eight)
            .parity(Parity::None)
            .stop_bits(StopBits::One)
            .flow_control(FlowControl::None)
            .timeout(Self::READ_WAIT)
            .open()
            .map_err(|e| match is_terminal(path) {
                // `/dev/null` or a file: an ioctl of terminals refused, which the error says only in the C
                // library's words.
                false => CliError(format!(
                    "--port {}: not a serial port (a terminal device is needed, such as /dev/ttyACM0)",
                    path.display()
                )),
                true => fail(e),
            })?;
        port.clear(ClearBuffer::Input).map_err(|e| {
            CliError(format!("--port {}: cannot drop what it had received: {}", path.display(), e.description))
        })?;
        Ok(SerialLink { port, path: path.to_owned() })
    }
}

/// Whether `path` is a terminal device, as a serial port is (`/dev/null` and files are not): opened as `serialport`
/// opens it, without waiting for a carrier. True where it cannot be told (it does not open; or Windows, whose ports
/// are not files): `serialport`'s error then says why it failed.
fn is_terminal(path: &std::path::Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        let file = std::fs::OpenOptions::new().read(true).custom_flags(libc::O_NOCTTY | libc::O_NONBLOCK).open(path);
        file.map_or(true, |f| std::io::IsTerminal::is_terminal(&f))
    }
    #[cfg(not(unix))]
    {
        let _ = path;
        true
    }
}

/// A read or write that failed once the port was open: the port went away, as a USB port does when the board is
/// unplugged or its ST-LINK resets.
fn went_away(e: std::io::Error) -> std::io::Error {
    let why = io_reason(&e);
    std::io::Error::new(e.kind(), format!("{why} (the port went away: the board unplugged, or its ST-LINK reset?)"))
}

impl Link for SerialLink {
    fn receive(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        use std::io::{ErrorKind, Read};
        match self.port.read(buf) {
            Err(e) if matches!(e.kind(), ErrorKind::Interrupted | ErrorKind::TimedOut) => Ok(0),
            other => other.map_err(went_away),
        }
    }

    fn transmit(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        // A write waits at most the read's 0.1 s for room; the port drains at the baud rate, so waiting again is
        // right, up to a bound (9600 baud sends the longest line, 97 bytes, in 0.1 s).
        let mut rest = bytes;
        let mut waits = 0;
        while !rest.is_empty() {
            match self.port.write(rest) {
                Ok(0) => return Err(went_away(std::io::ErrorKind::WriteZero.into())),
                Ok(n) => rest = &rest[n..],
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut && waits < 20 => waits += 1,
                Err(e) => return Err(went_away(e)),
            }
        }
        self.port.flush().map_err(went_away)
    }

    fn name(&self) -> String {
        format!("--port {}", self.path.display())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame is `R`, its first sample's 12 hex digits and more: those 13 characters alone are not one, nor a reply
    /// that starts with `R`.
    #[test]
    fn a_frame_is_told_by_its_start() {
        use nanopos_id::record::{encode_frame, RawSample, FRAME_MAX_BYTES};
        let mut buf = [0u8; FRAME_MAX_BYTES];
        let n = encode_frame(0x30, &[RawSample::default(); 3], &mut buf);
        let frame = std::str::from_utf8(&buf[..n]).unwrap().trim_end();
        assert!(is_frame(frame) && is_recording_line(frame), "{frame}");
        assert!(!is_frame(&frame[..13]) && is_frame(&frame[..14]), "{frame}");
        assert!(!is_frame("Rate 000000000000 Hz") && !is_frame("r000000000030 AAAA"));
    }

    #[test]
    fn the_stlinks_ports_are_told_from_the_others() {
        use serialport::{SerialPortInfo, SerialPortType, UsbPortInfo};
        let usb = |name: &str, vid, pid, product: Option<&str>, serial: Option<&str>| SerialPortInfo {
            port_name: name.into(),
            port_type: SerialPortType::UsbPort(UsbPortInfo {
                vid,
                pid,
                serial_number: serial.map(Into::into),
                manufacturer: Some("STMicroelectronics".into()),
                product: product.map(Into::into),
            }),
        };
        let ports = [
            SerialPortInfo { port_name: "/dev/ttyS0".into(), port_type: SerialPortType::Unknown },
            // An STM32's own USB serial port, a USB-serial adapter: not ST-LINKs.
            usb("/dev/ttyACM1", 0x0483, 0x5740, Some("STM32 Virtual ComPort"), None),
            usb("/dev/ttyUSB0", 0x0403, 0x6001, Some("FT232R USB UART"), None),
            // The Nucleo's ST-LINK/V3E; macOS lists it twice, the dial-in device left out.
            usb("/dev/cu.usbmodem14203", 0x0483, 0x374E, Some("STLINK-V3"), Some("0026003B")),
            usb("/dev/tty.usbmodem14203", 0x0483, 0x374E, Some("STLINK-V3"), Some("0026003B")),
            usb("COM5", 0x0483, 0x374B, None, None),
        ];
        assert_eq!(
            stlink_ports(&ports),
            [
                ("/dev/cu.usbmodem14203".to_string(), "STLINK-V3, serial 0026003B".to_string()),
                ("COM5".to_string(), "ST-LINK".to_string())
            ]
        );
        assert!(stlink_ports(&ports[..3]).is_empty());
    }

    #[test]
    fn script_lines_are_read_as_documented() {
        assert_eq!(script_line(b""), Ok(ScriptLine::Skip));
        assert_eq!(script_line(b"   \t"), Ok(ScriptLine::Skip));
        assert_eq!(script_line(b"# a comment"), Ok(ScriptLine::Skip));
        assert_eq!(script_line(b"  status  "), Ok(ScriptLine::Send(b"status")));
        assert_eq!(script_line(b"sleep 1.5"), Ok(ScriptLine::Sleep(Duration::from_millis(1500))));
        assert_eq!(script_line(b"sleep  0"), Ok(ScriptLine::Sleep(Duration::ZERO)));
        assert_eq!(script_line(b"sleepy"), Ok(ScriptLine::Send(b"sleepy")));
        for bad in [&b"sleep"[..], b"sleep -1", b"sleep 1e9", b"sleep nan", b"sleep 1 2", b"sleep x"] {
            assert!(script_line(bad).is_err(), "{}", String::from_utf8_lossy(bad));
        }
    }

    #[test]
    fn verdicts_and_recording_lines_are_told_apart() {
        for v in ["ok", "ok excite prbs 1 V", "error: word 2: expected ..."] {
            assert!(is_verdict(v), "{v}");
        }
        for v in ["okay", "note: the clamp will clip it", "est ekf a0=7.06e6", "R00000000a3f2 AAAA 1c0f"] {
            assert!(!is_verdict(v), "{v}");
        }
        for r in [
            "R00000000a3f2 AAAA 1c0f",
            "# nanopos-record v2 rate_hz=10000 crc=29b1",
            "# nanopos-record end samples=1 overflow=0 crc=3faa",
            "# nanopos-tuning at=1000 ekf q 3d719799812dea11 crc=0000",
        ] {
            assert!(is_recording_line(r), "{r}");
        }
        for r in ["Restarted", "R", "ok", "est rls a0=1", "Rxééééééé"] {
            assert!(!is_recording_line(r), "{r}");
        }
    }
}
