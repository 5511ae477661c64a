//! `nanopos-sim console [--status-every S] [--stage B0,A1,A0] [--payload-off S|never] [--gain-drift PCT_PER_MIN]`:
//! the firmware's console on the simulated board, without a board.
//!
//! Standard input is the link's receive side, standard output its transmit side: type the README's commands (or pipe
//! a script) and read the replies, the recording's header, tuning lines, frames and end line exactly as the
//! NUCLEO-G474RE sends them over its virtual COM port, so that `nanopos-sim decode` takes the output as it takes a
//! capture of the board's. The board runs the firmware's interrupt body ([`Lab`]: the same pipeline, estimators,
//! limits and fault logic) on the paper's stage, the payload removed after 100 s (`--payload-off`: at another time,
//! or never), the PRBS running from the start; with `--stage`, on a stage of model (1) of your own, unchanging (to
//! rehearse `tune initial`, `tune prefilter` for it, say). `--gain-drift` lets the piezo's gain drift at a steady
//! rate, as with temperature, to watch the estimators follow it.
//!
//! Time runs at the board's pace, 10 000 samples a second of the wall clock, in steps of 10 ms (a line is taken at
//! the next step), so a script with pauses (`sleep 5` between commands) sees what it would see on the board: the
//! estimators converge while it sleeps. `--status-every S` writes the `status` reply every `S` s to standard error,
//! where the firmware's defmt log would go.
//!
//! At the end of the input (Ctrl-D, or a script's end) the session ends: a last line without its line end is ended
//! (with a note on standard error: the board would wait for it), a burst recording runs to its end, a recording
//! `record on` started is stopped (`record off`, its reply written), and the recording's end line goes out. Every
//! line gets its reply, a malformed one an `error:` reply, as on the board; the command exits 0.
//!
//! Unlike the board's, the link loses nothing: lines are taken however fast they come, where the board's 128-byte
//! receive buffer drops what arrives while it is full (`nanopos-sim send` waits for each verdict, as the board needs).
//! With `--pty PATH` ([`Pty`], Linux and macOS) the link is a pseudo-terminal instead of standard input and output,
//! which `send --port PATH` opens as it opens the board's port; the session then ends at Ctrl-C.

use super::CliError;
use crate::lab::Lab;
use nanopos_id::StageParams;
use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

/// Samples in a step of the session: 10 ms at 10 kHz (the recording's ring holds 0.1 s).
const STEP_SAMPLES: u64 = 100;

/// `--stage B0,A1,A0`: the stage of `y'' = -a0 y - a1 y' + b0 u`, in the paper's units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StageArg(pub StageParams<f64>);

impl std::str::FromStr for StageArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || {
            format!(
                "'{s}': expected B0,A1,A0 of y'' = -a0 y - a1 y' + b0 u (um/(s^2 V), 1/s, 1/s^2): b0 not 0, a1 > 0, \
                 and 0 < a0 < (pi 10 kHz)^2, a resonance below the board's Nyquist frequency (the paper's stage: \
                 8.08e5,77.6,7.06e6)"
            )
        };
        let v: Vec<f64> = s.split(',').map(|p| p.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|_| bad())?;
        let nyquist = std::f64::consts::PI * 1e4;
        match v[..] {
            [b0, a1, a0]
                if b0.is_finite() && b0 != 0.0 && a1 > 0.0 && a1.is_finite() && a0 > 0.0 && a0 < nyquist * nyquist =>
            {
                Ok(StageArg(StageParams { b0, a1, a0 }))
            }
            _ => Err(bad()),
        }
    }
}

/// `--payload-off S|never`: when the paper's payload comes off, in seconds from the start (`None`: never).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PayloadOff(pub Option<f64>);

impl std::str::FromStr for PayloadOff {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "never" {
            return Ok(PayloadOff(None));
        }
        match s.parse::<f64>() {
            Ok(t) if t.is_finite() && (0.0..=super::simulate::MAX_DURATION_S).contains(&t) => Ok(PayloadOff(Some(t))),
            _ => Err(format!(
                "'{s}': expected the seconds from the start after which the payload comes off (0 to {}), or never",
                super::simulate::MAX_DURATION_S
            )),
        }
    }
}

/// The command line's options.
#[derive(Clone, Debug, Default)]
pub struct ConsoleArgs {
    /// The stage instead of the paper's (and no payload change).
    pub stage: Option<StageArg>,
    /// Write the `status` reply to the log every this many seconds of simulated time.
    pub status_every_s: Option<f64>,
    /// When the paper's payload comes off, if not after 100 s.
    pub payload_off: Option<PayloadOff>,
    /// The piezo's gain drift, mains pickup, the probe's noise.
    pub disturbances: super::Disturbances,
    /// Set (by a Ctrl-C handler) to end the session as the input's end does.
    pub interrupted: Option<Arc<AtomicBool>>,
}

/// Run the session: `input` is what the link receives, `link` what it sends back, `log` where the periodic status
/// goes. Returns the samples the board ran.
pub fn run(
    args: ConsoleArgs,
    input: impl Read + Send + 'static,
    link: &mut dyn Write,
    log: &mut dyn Write,
) -> Result<u64, CliError> {
    if let Some(s) = args.status_every_s {
        if !(s.is_finite() && s >= 0.01) {
            return Err(CliError(format!("--status-every {s}: at least 0.01 s")));
        }
    }
    let link_error = super::stdout_error;
    let log_error = |e: std::io::Error| CliError(format!("standard error: cannot write: {}", super::io_reason(&e)));
    // The receive side on a thread of its own, so that the board runs on while nothing is typed.
    let (to_board, received) = mpsc::channel::<Vec<u8>>();
    std::thread::spawn(move || {
        let mut input = input;
        let mut buf = [0u8; 256];
        while let Ok(n @ 1..) = input.read(&mut buf) {
            if to_board.send(buf[..n].to_vec()).is_err() {
                break;
            }
        }
    });
    if args.stage.is_some() && args.payload_off.is_some() {
        return Err(CliError("--payload-off: only on the paper's stage (a --stage has no payload to take off)".into()));
    }
    let (mut board, settings) = Lab::settings(args.stage.map(|s| s.0));
    args.disturbances.apply(&mut board)?;
    let rate_hz = 1.0 / board.plant.sample_period_s;
    if let Some(PayloadOff(off)) = args.payload_off {
        board.plant.change_at_sample = off.map_or(u64::MAX, |t| (t * rate_hz).round() as u64);
    }
    let mut lab = Lab::on_board(board, settings);
    let status_every = args.status_every_s.map(|s| ((s * rate_hz).round() as u64).max(1));
    let start = Instant::now();
    let mut samples = 0u64;
    let mut ended = false;
    // The last byte received: whether the input ends inside a line.
    let mut last_byte = None;
    loop {
        // What arrived: every line it completes is executed (its change applied by one sample) and answered. The
        // input's end, or an interruption once what arrived is taken, ends the session.
        let interrupted = args.interrupted.as_ref().is_some_and(|i| i.load(Ordering::Relaxed));
        loop {
            match received.try_recv() {
                Ok(bytes) => {
                    last_byte = bytes.last().copied().or(last_byte);
                    lab.send_bytes(&bytes);
                }
                Err(mpsc::TryRecvError::Empty) if !interrupted => break,
                Err(_) => {
                    if !ended {
                        ended = true;
                        // A script whose last line has no line end: the line is ended, as its author meant (the
                        // board would wait for the end; a `record off` below would have been joined to it, refused,
                        // and the session never ended).
                        if last_byte.is_some_and(|b| b != b'\n' && b != b'\r') {
                            log.write_all(
                                b"nanopos-sim: note: the input's last line has no line end: ended there (the board's \
                                  console waits for one)\n",
                            )
                            .map_err(log_error)?;
                            lab.send("\n");
                        }
                        // A recording until stopped would never end: stopped as the user would.
                        let st = lab.isr.record_status();
                        if st.active && st.remaining.is_none() {
                            lab.send("record off\n");
                        }
                    }
                    break;
                }
            }
        }
        link.write_all(lab.link.as_bytes()).map_err(link_error)?;
        lab.link.clear();
        for _ in 0..STEP_SAMPLES {
            lab.sample();
            samples += 1;
            if status_every.is_some_and(|n| samples % n == 0) {
                let status = lab.status_reply();
                log.write_all(status.as_bytes()).map_err(log_error)?;
            }
        }
        let frames = lab.drain_recording();
        link.write_all(frames.as_bytes()).map_err(link_error)?;
        link.flush().map_err(link_error)?;
        if ended && !lab.isr.record_status().active {
            // The end line went out with the last frames (`Lab::drain_recording`).
            return Ok(samples);
        }
        let due = start + Duration::from_secs_f64(samples as f64 / rate_hz);
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
    }
}

/// `--pty PATH`: the session's link on a pseudo-terminal, PATH a symbolic link to its device, which `nanopos-sim send
/// --port PATH` (or a terminal program) opens as it opens the board's virtual COM port: a script rehearsed on the
/// simulated board as it will run on the real one.
#[cfg(unix)]
pub struct Pty {
    /// The link's side: what a program writes to the device is read here, and what is written here it reads.
    pub master: std::fs::File,
    /// The device's side, held open so that the link stays up between the programs that open it and close it.
    _device: std::os::fd::OwnedFd,
    /// The symbolic link, removed when the session ends.
    path: std::path::PathBuf,
    /// The pseudo-terminal's device, which `path` links to.
    device: std::path::PathBuf,
}

#[cfg(unix)]
impl Pty {
    /// A pseudo-terminal set raw, as `send` sets a serial port, and `path` made a symbolic link to its device. A
    /// `path` that is a symbolic link to a pseudo-terminal (a session before this one) is replaced; anything else
    /// there is left alone and refused.
    pub fn open(path: &std::path::Path) -> Result<Self, CliError> {
        use nix::fcntl::{fcntl, FcntlArg, FdFlag};
        use nix::sys::termios;
        let shown = path.display();
        let fail = |what: &str, e: nix::Error| {
            CliError(format!("--pty {shown}: cannot {what}: {}", super::io_reason(&std::io::Error::from(e))))
        };
        if let Ok(m) = std::fs::symlink_metadata(path) {
            let stale = m.file_type().is_symlink() && std::fs::read_link(path).is_ok_and(|t| is_pseudo_terminal(&t));
            if !stale {
                return Err(CliError(format!(
                    "--pty {shown}: is there already (only a link to a pseudo-terminal, a session's before, is \
                     replaced): choose another name"
                )));
            }
            std::fs::remove_file(path)
                .map_err(|e| CliError(format!("--pty {shown}: cannot replace: {}", super::io_reason(&e))))?;
        }
        let pty = nix::pty::openpty(None, None).map_err(|e| fail("open a pseudo-terminal", e))?;
        for fd in [&pty.master, &pty.slave] {
            fcntl(fd, FcntlArg::F_SETFD(FdFlag::FD_CLOEXEC)).map_err(|e| fail("set up the pseudo-terminal", e))?;
        }
        let mut raw = termios::tcgetattr(&pty.slave).map_err(|e| fail("set up the pseudo-terminal", e))?;
        termios::cfmakeraw(&mut raw);
        termios::tcsetattr(&pty.slave, termios::SetArg::TCSANOW, &raw)
            .map_err(|e| fail("set up the pseudo-terminal", e))?;
        let device = nix::unistd::ttyname(&pty.slave).map_err(|e| fail("name the pseudo-terminal", e))?;
        std::os::unix::fs::symlink(&device, path)
            .map_err(|e| CliError(format!("--pty {shown}: cannot create: {}", super::io_reason(&e))))?;
        Ok(Pty { master: std::fs::File::from(pty.master), _device: pty.slave, path: path.to_owned(), device })
    }

    /// The pseudo-terminal's device, which `path` links to.
    pub fn device(&self) -> &std::path::Path {
        &self.device
    }
}

/// Whether `device` names a pseudo-terminal's device: `/dev/pts/N` on Linux, `/dev/ttysN` on macOS.
#[cfg(unix)]
fn is_pseudo_terminal(device: &std::path::Path) -> bool {
    device.starts_with("/dev/pts/") || device.to_str().is_some_and(|d| d.starts_with("/dev/ttys"))
}

#[cfg(unix)]
impl Drop for Pty {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}
