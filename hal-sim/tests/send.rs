//! `nanopos-sim send`: a script sent to the firmware's console a line at a time, each after its verdict, and the
//! recording's stream captured, against the simulated board's console (`nanopos-sim console`: in process through a
//! channel, and as a process on a pseudo-terminal, the serial port's kind of device).

use hal_sim::cmd::console::{self, ConsoleArgs};
use hal_sim::cmd::send::{self, Link, SendOptions, Sent};
use hal_sim::cmd::CliError;
use std::io::Write;
use std::path::Path;
use std::process::{Command, Output};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

/// The simulated console's link, from `send`'s side: what it transmits is the console's input, what the console
/// writes arrives through the channel.
struct ConsoleLink {
    to_console: Option<mpsc::Sender<Vec<u8>>>,
    from_console: mpsc::Receiver<Vec<u8>>,
    pending: Vec<u8>,
}

impl Link for ConsoleLink {
    fn receive(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if self.pending.is_empty() {
            match self.from_console.recv_timeout(Duration::from_millis(100)) {
                Ok(bytes) => self.pending = bytes,
                Err(_) => return Ok(0),
            }
        }
        let n = buf.len().min(self.pending.len());
        buf[..n].copy_from_slice(&self.pending[..n]);
        self.pending.drain(..n);
        Ok(n)
    }

    fn transmit(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        let _ = self.to_console.as_ref().expect("the console's input is open").send(bytes.to_vec());
        Ok(())
    }
}

/// The console's input, from the channel: its end once the sender is gone.
struct FromChannel(mpsc::Receiver<Vec<u8>>);

impl std::io::Read for FromChannel {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        match self.0.recv() {
            Ok(bytes) => {
                // The link's sends are a line or a byte: always within the console's 256-byte reads.
                assert!(bytes.len() <= buf.len(), "a send longer than the console's read");
                buf[..bytes.len()].copy_from_slice(&bytes);
                Ok(bytes.len())
            }
            Err(_) => Ok(0),
        }
    }
}

/// The console's output, into the channel.
struct ToChannel(mpsc::Sender<Vec<u8>>);

impl Write for ToChannel {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        if !bytes.is_empty() {
            let _ = self.0.send(bytes.to_vec());
        }
        Ok(bytes.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// What a session against the simulated console gave: `send`'s result, its standard output and the capture.
struct Session {
    result: Result<Sent, CliError>,
    out: String,
    capture: String,
}

/// `script` sent by `send` (with a capture, and a 2 s timeout) to a console session on the simulated board.
fn session(script: &str) -> Session {
    session_with(script, SendOptions { timeout: Duration::from_secs(2), interrupted: None, echo: true })
}

/// [`session`] with `options`.
fn session_with(script: &str, options: SendOptions) -> Session {
    let (writer, reader) = mpsc::channel();
    let reader = FromChannel(reader);
    let (tx, rx) = mpsc::channel();
    let board = std::thread::spawn(move || {
        let mut link = ToChannel(tx);
        console::run(ConsoleArgs::default(), reader, &mut link, &mut std::io::sink()).expect("the console runs")
    });
    let mut link = ConsoleLink { to_console: Some(writer), from_console: rx, pending: Vec::new() };
    let (mut out, mut capture) = (Vec::new(), Vec::new());
    let result = send::run(
        &mut script.as_bytes(),
        "script.txt",
        &mut link,
        &mut out,
        Some(&mut capture as &mut dyn Write),
        &options,
    );
    // The input's end ends the console's session.
    link.to_console = None;
    board.join().expect("the console's session ends");
    Session { result, out: String::from_utf8(out).unwrap(), capture: String::from_utf8(capture).unwrap() }
}

fn nanopos_sim(args: &[&str], dir: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_nanopos-sim")).args(args).current_dir(dir).output().expect("run nanopos-sim")
}

/// `nanopos-sim ARGS` in `dir`, started, its outputs piped.
#[cfg(target_os = "linux")]
fn nanopos_sim_started(args: &[&str], dir: &Path) -> std::process::Child {
    use std::process::Stdio;
    let mut command = Command::new(env!("CARGO_BIN_EXE_nanopos-sim"));
    command.args(args).current_dir(dir).stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
    command.spawn().expect("run nanopos-sim")
}

/// Comments, blank lines and `sleep` stay on the host; each command is answered before the next goes; the replies
/// on standard output, the recording's lines only in the capture, which `decode` reads whole.
#[test]
fn a_script_goes_a_line_at_a_time_and_its_recording_is_captured() {
    let s = session(
        "# the triangle's tuning, then a burst\r\ntuning triangle\n\n  status  \nrecord burst 300\nsleep 0.1\nlimits\n",
    );
    let sent = s.result.unwrap_or_else(|e| panic!("{e}\n{}", s.out));
    assert_eq!(sent.accepted, 4, "{}", s.out);
    assert!(sent.notes.is_empty(), "{:?}", sent.notes);
    let sent_lines: Vec<&str> = s.out.lines().filter(|l| l.starts_with("> ")).collect();
    assert_eq!(sent_lines, ["> tuning triangle", "> status", "> record burst 300", "> limits"], "{}", s.out);
    // Each line's verdict comes before the next line is sent.
    let lines: Vec<&str> = s.out.lines().collect();
    for (k, l) in lines.iter().enumerate().filter(|(_, l)| l.starts_with("> ")).skip(1) {
        let before =
            lines[..k].iter().rev().find(|l| l.starts_with("> ") || l.starts_with("ok") || l.starts_with("error:"));
        assert!(
            before.is_some_and(|b| b.starts_with("ok")),
            "{l} sent before the verdict of the line before:\n{}",
            s.out
        );
    }
    assert_eq!(s.out.lines().filter(|l| l.starts_with("est ")).count(), 4, "status' lines: {}", s.out);
    assert!(s.out.lines().last().unwrap().starts_with("ok limits -10 V to 10 V"), "{}", s.out);
    assert!(!s.out.contains("nanopos-record") && !s.out.lines().any(|l| l.starts_with('R')), "{}", s.out);
    assert!(s.capture.contains("# nanopos-record end samples=300 overflow=0 "), "{}", s.capture);
    assert!(s.capture.contains("ok tuning triangle"), "the capture has every byte received");

    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("cap.txt"), &s.capture).unwrap();
    let out = nanopos_sim(&["decode", "--input", "cap.txt", "--out", "run.csv"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(std::fs::read_to_string(dir.path().join("run.csv")).unwrap().lines().count(), 301);
}

/// A refused line stops the script: the message names it and the board's reason, and nothing after it is sent.
#[test]
fn a_refused_line_stops_the_script_and_is_named() {
    let s = session("status\ntune ekf q 1\nstart\n");
    let e = s.result.expect_err("the board refuses line 2").0;
    assert!(e.starts_with("script.txt: line 2: 'tune ekf q 1': refused by the board (error: "), "{e}");
    assert!(e.ends_with("the lines after it not sent"), "{e}");
    assert!(!s.out.contains("> start"), "{}", s.out);
    assert!(s.out.lines().last().unwrap().starts_with("error: "), "{}", s.out);
    // Typed at a terminal, the lines are not written again.
    let s = session_with("status\n", SendOptions { timeout: Duration::from_secs(2), interrupted: None, echo: false });
    assert_eq!(s.result.map(|sent| sent.accepted).ok(), Some(1));
    assert!(s.out.starts_with("est rls ") && !s.out.contains("> "), "{}", s.out);
}

/// A script that ends with a recording running stops it, as the simulated console does at its input's end, and
/// waits for the end line; a `sleep` that does not read as one is refused before anything after it is sent.
#[test]
fn a_recording_left_running_is_stopped_and_a_bad_sleep_refused() {
    let s = session("record on\nsleep 0.25\n");
    let sent = s.result.unwrap_or_else(|e| panic!("{e}\n{}", s.out));
    assert_eq!(sent.notes, ["the recording still running at the end: stopped with record off"]);
    assert!(
        s.out.contains("> record off\n") && s.out.lines().last().unwrap().starts_with("ok record off"),
        "{}",
        s.out
    );
    let end = s.capture.lines().find(|l| l.starts_with("# nanopos-record end samples=")).expect("the end line");
    let samples: u64 = end["# nanopos-record end samples=".len()..].split(' ').next().unwrap().parse().unwrap();
    // The sleep's 0.25 s at 10 kHz, give or take the console's lag behind the wall clock on a loaded machine.
    assert!((2_000..40_000).contains(&samples), "{end}");

    let s = session("status\nsleep soon\nstart\n");
    let e = s.result.expect_err("line 2 is not a sleep").0;
    assert_eq!(e, "script.txt: line 2: 'sleep soon': expected sleep S, the seconds to wait (0 to 86400)");
    assert!(!s.out.contains("> start"), "{}", s.out);
}

/// A Ctrl-C (the flag its handler sets) cuts a `sleep` short, sends no further line, and stops a burst the script
/// started, whose end line `send` still waits for.
#[test]
fn an_interruption_stops_the_script_and_its_burst() {
    let flag = Arc::new(AtomicBool::new(false));
    let setter = Arc::clone(&flag);
    std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(600));
        setter.store(true, Ordering::Relaxed);
    });
    let start = Instant::now();
    let options = SendOptions { timeout: Duration::from_secs(2), interrupted: Some(flag), echo: true };
    let s = session_with("record burst 1000000\nsleep 100\nstatus\n", options);
    let sent = s.result.unwrap_or_else(|e| panic!("{e}\n{}", s.out));
    assert!(start.elapsed() < Duration::from_secs(10), "{:?}", start.elapsed());
    assert_eq!(
        sent.notes,
        [
            "interrupted: script.txt line 3 and those after it not sent",
            "the recording interrupted: stopped with record off"
        ]
    );
    assert!(!s.out.contains("> status") && s.out.contains("> record off\nok record off"), "{}", s.out);
    assert!(s.capture.contains("# nanopos-record end samples="), "{}", s.capture);
}

/// A link that never answers: the first line's wait ends at the timeout, with a message that names the line and
/// what to check.
#[test]
fn a_line_without_a_verdict_ends_the_script_at_the_timeout() {
    struct Silent(Vec<u8>);
    impl Link for Silent {
        fn receive(&mut self, _: &mut [u8]) -> std::io::Result<usize> {
            std::thread::sleep(Duration::from_millis(10));
            Ok(0)
        }
        fn transmit(&mut self, bytes: &[u8]) -> std::io::Result<()> {
            self.0.extend_from_slice(bytes);
            Ok(())
        }
    }
    let mut link = Silent(Vec::new());
    let options = SendOptions { timeout: Duration::from_millis(300), interrupted: None, echo: true };
    let start = Instant::now();
    let e = send::run(&mut &b"status\nstart\n"[..], "script.txt", &mut link, &mut Vec::new(), None, &options)
        .expect_err("no verdict")
        .0;
    assert!(start.elapsed() < Duration::from_secs(2), "{:?}", start.elapsed());
    assert!(e.starts_with("script.txt: line 1: 'status': no verdict from the board within 0.3 s"), "{e}");
    assert_eq!(link.0, b"\x15status\n", "Ctrl-U first, then line 1 alone");
}

/// A link that fails, reading or writing: the script ends with a message naming the link (`the link` unless its
/// [`Link::name`] says otherwise), which way it failed and why.
#[test]
fn a_failing_link_is_named_with_what_failed() {
    struct Broken {
        reads: bool,
    }
    impl Link for Broken {
        fn receive(&mut self, _: &mut [u8]) -> std::io::Result<usize> {
            if self.reads {
                Ok(0)
            } else {
                Err(std::io::Error::other("the cable came out"))
            }
        }
        fn transmit(&mut self, _: &[u8]) -> std::io::Result<()> {
            if self.reads {
                Err(std::io::Error::other("the cable came out"))
            } else {
                Ok(())
            }
        }
    }
    let options = SendOptions { timeout: Duration::from_millis(300), interrupted: None, echo: false };
    for (reads, said) in
        [(true, "the link: cannot write: the cable came out"), (false, "the link: cannot read: the cable came out")]
    {
        let e = send::run(&mut &b"status\n"[..], "script.txt", &mut Broken { reads }, &mut Vec::new(), None, &options)
            .expect_err("a link that fails")
            .0;
        assert_eq!(e, said);
    }
}

/// A board that sends `early` at once, and `answer` once a line has come, a chunk per read, whatever the line.
#[derive(Default)]
struct Scripted {
    early: std::collections::VecDeque<Vec<u8>>,
    answer: std::collections::VecDeque<Vec<u8>>,
    asked: bool,
}

impl Scripted {
    fn answering(chunks: &[&[u8]]) -> Self {
        Scripted { answer: chunks.iter().map(|c| c.to_vec()).collect(), ..Scripted::default() }
    }
}

impl Link for Scripted {
    fn receive(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let next = match self.early.pop_front() {
            Some(chunk) => Some(chunk),
            None if self.asked => self.answer.pop_front(),
            None => None,
        };
        let Some(chunk) = next else {
            std::thread::sleep(Duration::from_millis(10));
            return Ok(0);
        };
        buf[..chunk.len()].copy_from_slice(&chunk);
        Ok(chunk.len())
    }
    fn transmit(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.asked |= bytes.ends_with(b"\n");
        Ok(())
    }
}

/// A verdict is a reply's line, found when it comes in pieces and among the recording's frames; bytes without a line
/// end (a wrong baud rate's) are shown in lines of 4 KiB at most, every byte of them; what the board sent before the
/// script is dropped with a note that says whether a recording was running.
#[test]
fn verdicts_are_found_in_a_stream_that_arrives_in_pieces() {
    let chunks: Vec<&[u8]> = vec![
        b"# nanopos-record v2 rate_hz=10000 crc=0000\nR000000000000 ok 0000\no",
        b"k record on\nR000000000030 AAAA 0000\n",
    ];
    let mut link = Scripted::answering(&chunks);
    let (mut out, mut capture) = (Vec::new(), Vec::new());
    let options = SendOptions { timeout: Duration::from_millis(500), interrupted: None, echo: false };
    let capture_out = Some(&mut capture as &mut dyn Write);
    // The recording is stopped at the end (the scripted board sends no end line: the wait ends at the timeout).
    let e = send::run(&mut &b"record on\n"[..], "s", &mut link, &mut out, capture_out, &options).expect_err("no end");
    assert!(e.0.starts_with("the recording's end line did not come"), "{e}");
    assert_eq!(String::from_utf8(out).unwrap(), "ok record on\n");
    assert!(capture.ends_with(b"ok record on\nR000000000030 AAAA 0000\n"));

    let noise = vec![b'x'; 2_500];
    let mut link = Scripted::answering(&[&noise, &noise, &noise, &noise, b"\nok\n"]);
    let mut out = Vec::new();
    let sent = send::run(&mut &b"status\n"[..], "s", &mut link, &mut out, None, &options).expect("ok");
    assert_eq!(sent.accepted, 1);
    let lines: Vec<usize> = String::from_utf8(out).unwrap().lines().map(str::len).collect();
    assert_eq!(lines, [4096, 4096, 1808, 2]);
    // What came after the last verdict without its line's end is shown at the end, ended.
    let mut link = Scripted::answering(&[b"ok status\nhalf a li"]);
    let mut out = Vec::new();
    send::run(&mut &b"status\n"[..], "s", &mut link, &mut out, None, &options).expect("ok");
    assert_eq!(String::from_utf8(out).unwrap(), "ok status\nhalf a li\n");

    // A board already recording, and one ending a reply to someone else: dropped for 0.2 s, and said which.
    for (early, note) in [
        (&b"R000000000030 AAAA 0000\n"[..], "a recording was running on the board before the script began (24 bytes"),
        // A line not yet ended when the script began counts too.
        (b"R000000000030 AAAA 0000\nR0000000000", "a recording was running on the board before the script began (35 "),
        (b"ok status samples=1\n", "the board was sending before the script began (20 bytes; the end of a reply)"),
    ] {
        let mut link = Scripted::answering(&[b"ok status\n"]);
        link.early.push_back(early.to_vec());
        let mut out = Vec::new();
        let sent = send::run(&mut &b"status\n"[..], "s", &mut link, &mut out, None, &options).expect("answered");
        assert!(sent.notes.len() == 1 && sent.notes[0].starts_with(note), "{:?}", sent.notes);
        assert_eq!(out, b"ok status\n", "what came before the script is not shown");
    }
}

/// Random scripts of valid and invalid lines, `sleep`s, comments and recordings, sent to the simulated console: each
/// line goes out only after the verdict of the one before; the script ends at its end or at the first refusal, which
/// the message names by its line; every recording that started ends in the capture, and the lines sent and answered
/// add up. To soak it: `SEND_SOAK_SEED=N SEND_SOAK_SCRIPTS=M cargo test --release -p hal-sim --test send random`.
#[test]
fn random_scripts_keep_the_promises_of_send() {
    let from_env = |name: &str| std::env::var(name).ok().map(|v| v.parse().unwrap_or_else(|_| panic!("{name}={v}")));
    let mut next = nanopos_id::xorshift64(from_env("SEND_SOAK_SEED").unwrap_or(0x5EED_5E4D));
    let pool = [
        "status",
        "help",
        "limits",
        "limits -5 5 1000",
        "excite prbs 0.5",
        "excite triangle 1 10",
        "excite multisine 1 200 800",
        "excite off",
        "start",
        "stop",
        "select ekf hekf",
        "select all",
        "reset all",
        "freeze rls",
        "adapt all",
        "tuning triangle",
        "tuning prbs",
        "tune ekf substeps",
        "record burst 150",
        "record on",
        "record off",
        "sleep 0.03",
        "# a comment",
        "",
        "frob",
        "tune ekf q 1",
        "excite prbs 11",
    ];
    for _ in 0..from_env("SEND_SOAK_SCRIPTS").unwrap_or(6) {
        let lines: Vec<&str> = (0..next() % 12 + 1).map(|_| pool[(next() % pool.len() as u64) as usize]).collect();
        let script = lines.iter().map(|l| format!("{l}\n")).collect::<String>();
        let s = session(&script);
        let context = || format!("script:\n{script}\noutput:\n{}\ncapture:\n{}", s.out, s.capture);
        let out: Vec<&str> = s.out.lines().collect();
        // Each line sent has its verdict before the next is sent.
        let sent_at: Vec<usize> = (0..out.len()).filter(|&k| out[k].starts_with("> ")).collect();
        for pair in sent_at.windows(2) {
            let verdicts = out[pair[0]..pair[1]].iter().filter(|l| l.starts_with("ok") || l.starts_with("error:"));
            assert_eq!(verdicts.count(), 1, "{}", context());
        }
        let commands: Vec<(usize, &str)> = lines
            .iter()
            .enumerate()
            .filter(|(_, l)| !l.is_empty() && !l.starts_with('#') && !l.starts_with("sleep"))
            .map(|(k, l)| (k + 1, *l))
            .collect();
        // The lines sent: the script's commands up to the end or the refusal, then at most `send`'s own `record off`.
        let script_sent = match &s.result {
            Ok(sent) => {
                assert_eq!(sent.accepted, commands.len(), "{}", context());
                commands.len()
            }
            Err(e) => {
                let refused = out.iter().position(|l| l.starts_with("error:")).expect("a refusal");
                let n = out[..refused].iter().filter(|l| l.starts_with("> ")).count();
                let (line, text) = commands[n - 1];
                assert!(e.0.starts_with(&format!("script.txt: line {line}: '{text}': refused")), "{e}\n{}", context());
                n
            }
        };
        let own: Vec<&&str> = sent_at[script_sent.min(sent_at.len())..].iter().map(|&k| &out[k]).collect();
        for (k, &text) in sent_at.iter().take(script_sent).zip(&commands) {
            assert_eq!(&out[*k][2..], text.1, "{}", context());
        }
        assert!(own.is_empty() || own == [&"> record off"], "{}", context());
        let headers = s.capture.lines().filter(|l| l.starts_with("# nanopos-record v2")).count();
        let ends = s.capture.lines().filter(|l| l.starts_with("# nanopos-record end")).count();
        assert_eq!(headers, ends, "every recording started ended: {}", context());
    }
}

/// Without `--port`, `send` takes the one ST-LINK plugged in, and says which; with none (this suite's machines), it
/// names the serial ports it found instead. Which of these it must say is asked of the machine here, not read from
/// what it said.
#[test]
fn without_a_port_send_looks_for_the_stlink() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("empty.txt"), "").unwrap();
    let unlistable = cfg!(target_os = "linux") && !Path::new("/sys/class/tty").is_dir();
    let listed = if unlistable { None } else { serialport::available_ports().ok() };
    let found = listed.as_deref().map(send::stlink_ports);
    if found.as_ref().is_some_and(|f| f.len() == 1) {
        // A board on this machine: `send` would take it and send it the script. Not run here.
        return;
    }
    let out = nanopos_sim(&["send", "--input", "empty.txt", "--timeout", "0.5"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    match found.as_deref() {
        // A machine without the system's list of ports (a container without /sys/class/tty): said, not a panic.
        None if unlistable => assert_eq!(
            stderr,
            "nanopos-sim: no --port given, and the serial ports cannot be listed: no /sys/class/tty: name the port \
             with --port\n"
        ),
        None => assert!(stderr.starts_with("nanopos-sim: no --port given, and the serial ports cannot be listed: ")),
        Some([]) => {
            let names: Vec<&str> = listed.iter().flatten().map(|p| p.port_name.as_str()).collect();
            let names = if names.is_empty() { "none".to_string() } else { names.join(", ") };
            assert_eq!(
                stderr,
                format!(
                    "nanopos-sim: no --port given, and no ST-LINK virtual COM port is plugged in (serial ports: \
                     {names}): connect the board's USB, or name its port with --port\n"
                )
            );
        }
        Some(several) => assert!(
            stderr.starts_with(&format!("nanopos-sim: no --port given, and {} ST-LINK", several.len()))
                && stderr.ends_with("choose one with --port\n"),
            "{stderr}"
        ),
    }
}

/// `nanopos-sim console --pty PATH`, killed if the test fails before it ends it (it runs until Ctrl-C).
#[cfg(target_os = "linux")]
struct PtySession(Option<std::process::Child>);

#[cfg(target_os = "linux")]
impl PtySession {
    /// The session started, once its link is there.
    fn start(path: &Path) -> Self {
        let session =
            PtySession(Some(nanopos_sim_started(&["console", "--pty", path.to_str().unwrap()], Path::new("."))));
        let start = Instant::now();
        while !path.exists() {
            assert!(start.elapsed() < Duration::from_secs(10), "the link never appeared");
            std::thread::sleep(Duration::from_millis(20));
        }
        session
    }
}

/// Wait until the capture `path` of a `send` holds a `status` verdict: its port is open, its script under way.
#[cfg(target_os = "linux")]
fn wait_for_verdict(path: &Path) {
    let start = Instant::now();
    while !std::fs::read_to_string(path).is_ok_and(|c| c.lines().any(|l| l.starts_with("ok status"))) {
        assert!(start.elapsed() < Duration::from_secs(20), "no verdict in {}", path.display());
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[cfg(target_os = "linux")]
impl Drop for PtySession {
    fn drop(&mut self) {
        if let Some(mut child) = self.0.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// `console --pty PATH`: the simulated board's link on a pseudo-terminal (the kind of device a serial port is) that
/// `send --port PATH` opens as it opens the board's port, up between the programs that open and close it, until
/// Ctrl-C, which removes PATH; a PATH that is something else already is refused and left alone. And `send`'s option
/// errors.
#[cfg(target_os = "linux")]
#[test]
fn the_console_on_a_pseudo_terminal_takes_send_as_the_board_does() {
    let dir = tempfile::tempdir().unwrap();
    let board_path = dir.path().join("board");
    let mut board = PtySession::start(&board_path);
    std::fs::write(dir.path().join("a.txt"), "excite prbs 0.5\nrecord burst 400\n").unwrap();
    std::fs::write(dir.path().join("b.txt"), "status\n").unwrap();
    // The second at another baud rate, which a pseudo-terminal takes as a serial port does (and ignores).
    for (script, baud, expect) in [("a.txt", "921600", "ok record burst 400"), ("b.txt", "115200", "ok status")] {
        let capture = script.replace(".txt", ".cap");
        let args = ["send", "--port", "board", "--input", script, "--capture", &capture, "--baud", baud];
        let out = nanopos_sim(&args, dir.path());
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{}\n{stdout}", String::from_utf8_lossy(&out.stderr));
        assert!(stdout.lines().any(|l| l.starts_with(expect)), "{stdout}");
    }
    // The port is this program's while it runs: a second `send` (or a terminal program opened after it) is refused,
    // rather than taking some of the first one's replies.
    std::fs::write(dir.path().join("c.txt"), "status\nsleep 1\nstatus\n").unwrap();
    let first = nanopos_sim_started(&["send", "--port", "board", "--input", "c.txt", "--capture", "c.cap"], dir.path());
    wait_for_verdict(&dir.path().join("c.cap"));
    let second = nanopos_sim(&["send", "--port", "board", "--input", "b.txt"], dir.path());
    let stderr = String::from_utf8_lossy(&second.stderr);
    assert_eq!(second.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("--port board: cannot open: ")
            && stderr.ends_with(" (another program has it open: close it first)\n"),
        "{stderr}"
    );
    let first = first.wait_with_output().unwrap();
    assert!(first.status.success(), "{}", String::from_utf8_lossy(&first.stderr));
    assert!(String::from_utf8_lossy(&first.stdout).lines().any(|l| l.starts_with("ok status")));

    let out = nanopos_sim(&["decode", "--input", "a.cap", "--out", "a.csv"], dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(std::fs::read_to_string(dir.path().join("a.csv")).unwrap().lines().count(), 401);

    let child = board.0.take().expect("the session");
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(child.id() as i32), nix::sys::signal::Signal::SIGINT).unwrap();
    let out = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("nanopos-sim send --port "), "{stderr}");
    assert!(out.stdout.is_empty(), "the link is the pseudo-terminal, not standard output");
    assert!(std::fs::symlink_metadata(&board_path).is_err(), "the link is removed at the end");

    for (args, message) in [
        (&["--port", "/dev/null"][..], "nanopos-sim: --port /dev/null: not a serial port"),
        (&["--port", "nowhere"], "nanopos-sim: --port nowhere: cannot open: No such file or directory"),
        (&["--port", "board", "--baud", "12345"], "nanopos-sim: --baud 12345: expected one of 9600, 19200,"),
        (&["--port", "board", "--baud", "-5"], "nanopos-sim: invalid value '-5' for '--baud <BAUD>'"),
        (&["--port", "board", "--timeout", "0"], "nanopos-sim: --timeout 0: expected seconds, 0.1 to 3600"),
        (&["--port", "board", "--input", "script.txt", "--capture", "script.txt"], "the same file as --input"),
    ] {
        let out = nanopos_sim(&[&["send"][..], args].concat(), dir.path());
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains(message) && stderr.lines().count() == 1, "{args:?}: {stderr}");
    }

    std::fs::write(&board_path, "mine").unwrap();
    let out = nanopos_sim(&["console", "--pty", "board"], dir.path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.starts_with("nanopos-sim: --pty board: is there already"), "{stderr}");
    assert_eq!(std::fs::read_to_string(&board_path).unwrap(), "mine");

    // The port going away under `send` (a board unplugged, an ST-LINK reset; here the session killed): an error that
    // names the port and says so, exit code 2, and what was captured kept.
    let mut gone = PtySession::start(&dir.path().join("gone"));
    std::fs::write(dir.path().join("d.txt"), "status\nsleep 10\nstatus\n").unwrap();
    let send = nanopos_sim_started(&["send", "--port", "gone", "--input", "d.txt", "--capture", "d.cap"], dir.path());
    wait_for_verdict(&dir.path().join("d.cap"));
    let mut gone_board = gone.0.take().expect("the session");
    gone_board.kill().unwrap();
    gone_board.wait().unwrap();
    let out = send.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("--port gone: cannot read: ") && stderr.contains("the port went away"), "{stderr}");
    let captured = std::fs::read_to_string(dir.path().join("d.cap")).unwrap();
    assert!(captured.lines().any(|l| l.starts_with("ok status")), "{captured}");
}
