//! `nanopos-sim`: the simulated nanopositioning stage and the host tools around the nanopos-id pipeline.
//! Bad input: one line on standard error naming what was wrong and where, exit code 2, no partial output file, and
//! no output written over an input or another output.

use clap::{Parser, Subcommand, ValueEnum};
use hal_sim::cmd::{simulate, CliError};
use hal_sim::sim::Scenario;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser, Debug)]
#[command(name = "nanopos-sim", version, about = "Simulated nanopositioning stage and host tools for nanopos-id")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Simulate the paper's experiment (payload removed at half the duration) and write t,u,y,a0,a1,b0 as CSV.
    Simulate {
        /// Which excitation.
        #[arg(long, value_enum)]
        scenario: ScenarioArg,
        /// Length of the run, s.
        #[arg(long, default_value_t = 200.0, allow_negative_numbers = true)]
        duration: f64,
        /// Noise seed [default: 1 for prbs, 2 for triangle, as in the float64 reference; 3 for multisine].
        #[arg(long, allow_negative_numbers = true)]
        seed: Option<u64>,
        /// Add piezo hysteresis (10 % of the drive through play operators up to 0.5 V wide).
        #[arg(long)]
        hysteresis: bool,
        /// Add piezo creep (1 % of a step per decade of time, from 0.1 s to 100 s).
        #[arg(long)]
        creep: bool,
        #[command(flatten)]
        disturbances: hal_sim::cmd::Disturbances,
        /// The excitation's amplitude, V, 0 to 10, as the console's `excite` takes it (the paper's: 1), through the
        /// firmware's default output limits
        #[arg(long, value_name = "V", allow_negative_numbers = true)]
        amplitude: Option<f64>,
        /// Output CSV file.
        #[arg(long)]
        out: PathBuf,
    },
    /// Run the firmware's pipeline and estimators on a recorded run (t,u,y); write estimates and a summary.
    Identify {
        /// CSV with a header naming at least t, u, y: s, V, um, or the unit a name gives (`t [ms]`, `y [nm]`); a0, a1,
        /// b0: the truth, optional.
        #[arg(long)]
        input: PathBuf,
        /// Estimators to run.
        #[arg(long, default_value = "rls,ekf,hekf,arx")]
        estimators: String,
        /// Tuning: a preset, prbs (the paper's Q2) or triangle (Q1), or a TOML file overriding one (`decode` writes
        /// the board's beside its CSV) [default: prbs].
        #[arg(long)]
        tuning: Option<String>,
        /// Averaging window T0:T1 in seconds (repeatable; T0 may be negative, as a record's time may be)
        /// [default: the last quarter of each half].
        #[arg(long = "window", value_name = "T0:T1", allow_hyphen_values = true)]
        windows: Vec<hal_sim::cmd::identify::Window>,
        /// Estimates at 100 Hz: t,estimator,a0,a1,b0,f0_hz,zeta,dc_gain.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Window means and validation RMSE, JSON.
        #[arg(long)]
        summary: Option<PathBuf>,
        /// Every estimate against time (and the truth when present), SVG: a name ending .svg, or one without an
        /// extension.
        #[arg(long)]
        plot: Option<PathBuf>,
        /// Health at 100 Hz: t,estimator,state,rejected,changes,resets,repairs,innovation_rms_um (counts since the
        /// record's start, as the board's status gives them; no innovation for rls and arx).
        #[arg(long)]
        health: Option<PathBuf>,
        /// The input's step for one DAC code, V, which the excitation monitor does not take for excitation (0: an
        /// input that is not rounded) [default: the board's, 3.3 V / 4096 / 0.165 = 4.88 mV].
        #[arg(long, value_name = "V", allow_negative_numbers = true)]
        dac_step: Option<hal_sim::cmd::identify::DacStep>,
        /// The spike gate's ratio: a reading whose third difference exceeds this many times its recent mean (and 16
        /// ADC codes) is replaced by the curve through the readings before it, as on the board (0: the gate off)
        /// [default: the tuning's `spike_ratio`: 32, the firmware's, unless a tuning file (the board's, from
        /// `decode`) says otherwise].
        #[arg(long, value_name = "N", allow_negative_numbers = true)]
        spike_ratio: Option<hal_sim::cmd::identify::SpikeRatio>,
        /// The scalar of the pipeline and the estimators: f64 (the reference) or f32 (the firmware's: what the board
        /// computes from these samples, and which tunings it refuses).
        #[arg(long, value_enum, default_value = "f64")]
        precision: PrecisionArg,
    },
    /// The paper's whole experiment on the simulated board: PRBS and triangle, every estimator, f64 and f32;
    /// prints a Table II-style table and writes the summaries.
    Paper {
        /// Length of each run, s (payload removed at half).
        #[arg(long, default_value_t = 200.0, allow_negative_numbers = true)]
        duration: f64,
        /// Where to write each input's summary and plot (prbs-summary.json, prbs.svg, triangle-summary.json,
        /// triangle.svg).
        #[arg(long, default_value = "paper-out")]
        out_dir: PathBuf,
    },
    /// Batch (weighted) least squares of an ARX model on a recorded run's u and y; prints JSON.
    Fit {
        /// CSV with a header naming at least u and y: V and um, or the unit a name gives (`u [mV]`, `y [nm]`).
        #[arg(long)]
        input: PathBuf,
        /// Orders NA,NB,NK: y(k) = a1 y(k-1)+..+a_NA y(k-NA) + b1 u(k-NK)+..+b_NB u(k-NK-NB+1).
        #[arg(long, value_name = "NA,NB,NK", allow_hyphen_values = true)]
        arx: hal_sim::cmd::fit::ArxOrders,
        /// Use every row, with the signals taken as zero before the first sample.
        #[arg(long)]
        zero_initial: bool,
        /// Weight row k of N by A GAMMA^(N-k).
        #[arg(long, value_name = "A,GAMMA", allow_hyphen_values = true)]
        weight: Option<hal_sim::cmd::fit::Weight>,
        /// Fit a constant term c as well (y sitting off the model: the probe's zero, the stage's position), printed
        /// as "c".
        #[arg(long)]
        offset: bool,
    },
    /// The firmware's console on the simulated board: commands on standard input, the board's replies and recording
    /// stream on standard output (what `decode` reads), at the board's pace.
    Console {
        /// Write the `status` reply to standard error every S seconds of simulated time.
        #[arg(long, value_name = "S", allow_negative_numbers = true)]
        status_every: Option<f64>,
        /// A stage of y'' = -a0 y - a1 y' + b0 u instead of the paper's (its payload change too) [default: the
        /// paper's, 8.08e5,77.6,7.06e6, payload removed after 100 s].
        #[arg(long, value_name = "B0,A1,A0", allow_hyphen_values = true)]
        stage: Option<hal_sim::cmd::console::StageArg>,
        /// When the paper's payload comes off, seconds from the start, or never [default: 100]
        #[arg(long, value_name = "S|never", allow_hyphen_values = true)]
        payload_off: Option<hal_sim::cmd::console::PayloadOff>,
        #[command(flatten)]
        disturbances: hal_sim::cmd::Disturbances,
        /// The link on a pseudo-terminal instead of standard input and output, PATH a symbolic link to it: what
        /// `send --port PATH` or a terminal program opens as the board's serial port (Linux, macOS; Ctrl-C ends the
        /// session).
        #[arg(long, value_name = "PATH")]
        pty: Option<PathBuf>,
    },
    /// The board's console commands that give it a tuning (a file decode wrote, or one for identify --tuning), one
    /// a line on standard output: send them one at a time, each after the last one's verdict (`send` does).
    Commands {
        /// A preset (prbs, triangle) or a TOML file, as identify's --tuning reads it.
        #[arg(long)]
        tuning: String,
    },
    /// Turn a captured serial stream of the firmware's recording (`record on`, `record burst N`) into t,u,y CSV.
    Decode {
        /// The capture (everything the board sent; replies and other lines are skipped).
        #[arg(long)]
        input: PathBuf,
        /// Output CSV file, for `identify --input`; the board's tuning goes beside it, OUT with the extension
        /// .tuning.toml, for `identify --tuning`.
        #[arg(long)]
        out: PathBuf,
        /// Which recording of the capture, counting from 1.
        #[arg(long, default_value_t = 1, allow_negative_numbers = true)]
        recording: usize,
        /// Keep what is intact of a damaged capture: skip damaged frames and write each gap-free run of samples to
        /// its own file, OUT with -1, -2, ... before the extension (without it, damage or a gap is an error).
        #[arg(long)]
        segments: bool,
    },
    /// Send a script of console lines to the board over its serial port, each after the last one's verdict (the
    /// console drops what arrives while its buffer is full); the replies on standard output, the recording's stream
    /// in --capture.
    Send {
        /// The board's serial port: the ST-LINK's virtual COM port (/dev/ttyACM0 on Linux, /dev/cu.usbmodem... on
        /// macOS, COM5 or the like on Windows) [default: the one ST-LINK plugged in].
        #[arg(long)]
        port: Option<PathBuf>,
        /// The script: a command a line (`sleep S` waits S seconds; blank lines and # comments skipped)
        /// [default: standard input].
        #[arg(long)]
        input: Option<PathBuf>,
        /// Everything the board sends, as it arrives, for decode (standard output then leaves out the recording's
        /// lines).
        #[arg(long)]
        capture: Option<PathBuf>,
        /// Seconds a line waits for its verdict (and a recording's end for the next of its stream).
        #[arg(long, value_name = "S", default_value_t = 2.0, allow_negative_numbers = true)]
        timeout: f64,
        /// The link's baud rate: the firmware's by default.
        #[arg(long, default_value_t = 921_600, allow_negative_numbers = true)]
        baud: u32,
    },
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum ScenarioArg {
    /// PRBS, 1 V, content 0-1 kHz.
    Prbs,
    /// Smoothed triangle, 10 Hz, 1 V.
    Triangle,
    /// Multisine, 32 tones from 200 to 800 Hz, the power of a 1 V sine (the board's `excite multisine 1 200 800`).
    Multisine,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum PrecisionArg {
    /// Double precision, the reference.
    F64,
    /// Single precision, the firmware's.
    F32,
}

impl From<PrecisionArg> for hal_sim::cmd::identify::Precision {
    fn from(p: PrecisionArg) -> Self {
        match p {
            PrecisionArg::F64 => Self::F64,
            PrecisionArg::F32 => Self::F32,
        }
    }
}

impl From<ScenarioArg> for Scenario {
    fn from(s: ScenarioArg) -> Self {
        match s {
            ScenarioArg::Prbs => Scenario::Prbs,
            ScenarioArg::Triangle => Scenario::Triangle,
            ScenarioArg::Multisine => Scenario::Multisine,
        }
    }
}

fn run(cli: Cli, interrupted: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>) -> Result<(), CliError> {
    match cli.command {
        Command::Simulate { scenario, duration, seed, hysteresis, creep, disturbances, amplitude, out } => {
            let args = simulate::SimulateArgs {
                scenario: scenario.into(),
                duration_s: duration,
                seed,
                hysteresis,
                creep,
                disturbances,
                amplitude_v: amplitude,
                out: &out,
            };
            for note in simulate::run(&args)?.notes {
                eprintln!("nanopos-sim: note: {note}");
            }
            Ok(())
        }
        Command::Identify {
            input,
            estimators,
            tuning,
            windows,
            out,
            summary,
            plot,
            health,
            dac_step,
            spike_ratio,
            precision,
        } => {
            use hal_sim::cmd::identify;
            // A decoded board recording has the board's tuning beside it: a replay without it runs the preset.
            let beside = hal_sim::cmd::decode::tuning_path(&input);
            if tuning.is_none() && beside.is_file() {
                eprintln!(
                    "nanopos-sim: note: {} beside the input holds the board's tuning (decode wrote it); without \
                     --tuning {} the replay runs the prbs preset, not the board's estimators",
                    beside.display(),
                    beside.display()
                );
            }
            let tuning = hal_sim::tuning::resolve(tuning.as_deref().unwrap_or("prbs"))?;
            let args = identify::IdentifyArgs {
                input: &input,
                estimators: identify::parse_estimators(&estimators)?,
                tuning,
                windows,
                out: out.as_deref(),
                summary: summary.as_deref(),
                plot: plot.as_deref(),
                health: health.as_deref(),
                dac_step_v: dac_step,
                spike_ratio,
                precision: precision.into(),
            };
            let result = identify::run(&args)?;
            for note in identify::health_notes(&result) {
                eprintln!("nanopos-sim: note: {note}");
            }
            if args.summary.is_none() {
                hal_sim::cmd::write_stdout(&identify::summary_json(&result))?;
            }
            Ok(())
        }
        Command::Paper { duration, out_dir } => {
            let runs = hal_sim::cmd::paper::run(duration, Some(&out_dir))?;
            hal_sim::cmd::write_stdout(&hal_sim::cmd::paper::table(&runs))
        }
        Command::Decode { input, out, recording, segments } => {
            use hal_sim::cmd::decode::{self, Damage};
            use hal_sim::cmd::{identify, show};
            let damage = if segments { Damage::Skip } else { Damage::Refuse };
            let (rec, files) = decode::run(&input, &out, recording, damage)?;
            let rate = rec.header.rate_hz;
            let origin = rec.first_index();
            if !rec.checked {
                eprintln!(
                    "nanopos-sim: note: the recording's header has no checksum (format v1, from a firmware before \
                     v2): its rate and scalings are taken as they are"
                );
            }
            for msg in &rec.damage {
                eprintln!("nanopos-sim: skipped: {msg}");
            }
            for (seg, file) in rec.segments.iter().zip(&files) {
                let n = seg.len;
                let at = (seg.first_index - origin) as f64 / rate;
                match file {
                    Some(path) => eprintln!(
                        "nanopos-sim: {n} samples ({} s at {rate} Hz) from board sample {} (t = {at} s) written \
                         to {}",
                        n as f64 / rate,
                        seg.first_index,
                        path.display()
                    ),
                    None => eprintln!(
                        "nanopos-sim: skipped: {n} sample at board sample {} (t = {at} s), too short to identify",
                        seg.first_index
                    ),
                }
            }
            // `identify` discounts the input's DAC steps; a board whose front end differs from the firmware's default
            // has steps of another size, which the header says and the CSV does not carry.
            let (step, assumed) = (rec.header.u_v_per_code.abs(), identify::default_dac_step_v());
            if (step / assumed - 1.0).abs() > 1e-9 {
                eprintln!(
                    "nanopos-sim: note: this board's DAC steps by {} V, not the {} V identify assumes: give it \
                     --dac-step {}",
                    show(step),
                    show(assumed),
                    show(step)
                );
            }
            if segments {
                let written = files.iter().flatten().count();
                for stale in decode::stale_segments(&out, written) {
                    eprintln!(
                        "nanopos-sim: note: {} is from an earlier decode, not this capture (its runs went to {written} \
                         files): left as it was",
                        stale.display()
                    );
                }
            }
            if let Some(path) = &rec.tuning_file {
                let path = path.display();
                eprintln!(
                    "nanopos-sim: the board's tuning at the recording's start written to {path}: replay with identify \
                     --tuning {path}; give it back to a board that reset with commands --tuning {path}"
                );
            }
            for msg in &rec.notes {
                eprintln!("nanopos-sim: note: {msg}");
            }
            match rec.ended {
                Some(true) => eprintln!(
                    "nanopos-sim: note: the recording stopped early: the board's buffer overflowed (the link is \
                     slower than the stream; see the README's recording section)"
                ),
                Some(false) => {}
                None => eprintln!("nanopos-sim: note: the capture ends before the recording's end line"),
            }
            Ok(())
        }
        Command::Console { status_every, stage, payload_off, disturbances, pty } => {
            let args = hal_sim::cmd::console::ConsoleArgs {
                status_every_s: status_every,
                stage,
                payload_off,
                disturbances,
                interrupted,
            };
            if let Some(path) = pty {
                return console_on_pty(args, &path);
            }
            if std::io::IsTerminal::is_terminal(&std::io::stdin()) {
                eprintln!(
                    "nanopos-sim: the board's console on the simulated stage, 10 kHz; type commands (help lists \
                     them; the README says what each does); {END_OF_INPUT} or Ctrl-C ends the session (a recording is \
                     stopped and its end line sent; a second Ctrl-C quits at once)"
                );
            }
            let (mut link, mut log) = (std::io::stdout().lock(), std::io::stderr().lock());
            hal_sim::cmd::console::run(args, std::io::stdin(), &mut link, &mut log).map(|_| ())
        }
        Command::Commands { tuning } => {
            let commands = hal_sim::cmd::commands::run(&hal_sim::tuning::resolve(&tuning)?)?;
            for note in &commands.notes {
                eprintln!("nanopos-sim: note: {note}");
            }
            hal_sim::cmd::write_stdout(&commands.lines.iter().map(|l| format!("{l}\n")).collect::<String>())
        }
        Command::Send { port, input, capture, timeout, baud } => send(port, input, capture, timeout, baud, interrupted),
        Command::Fit { input, arx, zero_initial, weight, offset } => {
            let fit = hal_sim::cmd::fit::run(&input, arx, zero_initial, weight, offset)?;
            for note in &fit.notes {
                eprintln!("nanopos-sim: note: {note}");
            }
            hal_sim::cmd::write_stdout(&format!("{}\n", fit.to_json()))
        }
    }
}

/// `console --pty PATH`: the session's link on a pseudo-terminal, until Ctrl-C.
fn console_on_pty(args: hal_sim::cmd::console::ConsoleArgs, path: &std::path::Path) -> Result<(), CliError> {
    #[cfg(unix)]
    {
        let pty = hal_sim::cmd::console::Pty::open(path)?;
        let cannot = |e: std::io::Error| CliError(format!("--pty: {}", hal_sim::cmd::io_reason(&e)));
        let input = pty.master.try_clone().map_err(cannot)?;
        let mut link = pty.master.try_clone().map_err(cannot)?;
        eprintln!(
            "nanopos-sim: the board's console on the simulated stage, 10 kHz, on {} ({}): nanopos-sim send --port {}, \
             or a terminal program; Ctrl-C ends the session",
            path.display(),
            pty.device().display(),
            path.display()
        );
        let mut log = std::io::stderr().lock();
        hal_sim::cmd::console::run(args, input, &mut link, &mut log).map(|_| ())
    }
    #[cfg(not(unix))]
    {
        let _ = args;
        Err(CliError(format!("--pty {}: pseudo-terminals are set up on Linux and macOS only", path.display())))
    }
}

/// What ends the input typed at a terminal.
const END_OF_INPUT: &str = if cfg!(windows) { "Ctrl-Z then Enter" } else { "Ctrl-D" };

/// `send`: the options checked, the files and the port opened, the session run.
fn send(
    port: Option<PathBuf>,
    input: Option<PathBuf>,
    capture: Option<PathBuf>,
    timeout: f64,
    baud: u32,
    interrupted: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
) -> Result<(), CliError> {
    use hal_sim::cmd::send::{self, SendOptions};
    use hal_sim::cmd::{check_distinct, io_reason, open_input};
    use std::io::{BufRead, BufReader};
    if !(timeout.is_finite() && (0.1..=3600.0).contains(&timeout)) {
        return Err(CliError(format!("--timeout {}: expected seconds, 0.1 to 3600", hal_sim::cmd::show(timeout))));
    }
    let inputs: Vec<(&str, &std::path::Path)> = input.iter().map(|p| ("--input", p.as_path())).collect();
    let outputs: Vec<(&str, &std::path::Path)> = capture.iter().map(|p| ("--capture", p.as_path())).collect();
    check_distinct(&inputs, &outputs)?;
    let (mut script, script_name): (Box<dyn BufRead>, String) = match &input {
        Some(path) => (Box::new(BufReader::new(open_input(path)?)), path.display().to_string()),
        None => (Box::new(std::io::stdin().lock()), "standard input".into()),
    };
    let port = match port {
        Some(port) => port,
        None => {
            let (port, what) = send::find_port()?;
            eprintln!("nanopos-sim: the ST-LINK's virtual COM port: {} ({what})", port.display());
            port
        }
    };
    let typed = input.is_none() && std::io::IsTerminal::is_terminal(&std::io::stdin());
    if typed {
        eprintln!(
            "nanopos-sim: the lines typed go to the board on {}, each after the last one's verdict; {END_OF_INPUT} \
             ends (a recording started is taken to its end)",
            port.display()
        );
    }
    let mut link = send::open_port(&port, baud)?;
    // The capture is the board's data: written as it arrives, kept whatever happens after.
    let mut capture_file = match &capture {
        Some(path) => Some(
            std::fs::File::create(path)
                .map_err(|e| CliError(format!("--capture {}: cannot create: {}", path.display(), io_reason(&e))))?,
        ),
        None => None,
    };
    let options = SendOptions { timeout: std::time::Duration::from_secs_f64(timeout), interrupted, echo: !typed };
    let mut out = std::io::stdout().lock();
    let capture = capture_file.as_mut().map(|f| f as &mut dyn std::io::Write);
    let sent = send::run(&mut script, &script_name, link.as_mut(), &mut out, capture, &options)?;
    for note in &sent.notes {
        eprintln!("nanopos-sim: note: {note}");
    }
    Ok(())
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) if !e.use_stderr() => {
            // --help, --version.
            let _ = e.print();
            return ExitCode::SUCCESS;
        }
        Err(e) if e.kind() == clap::error::ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => {
            eprintln!("nanopos-sim: no command given (try 'nanopos-sim simulate --help' or 'nanopos-sim --help')");
            return ExitCode::from(2);
        }
        Err(e) => {
            // clap's message spans several lines (usage, hints); keep the substance on one.
            let text = e.render().to_string();
            let line: Vec<&str> = text
                .lines()
                .map(str::trim)
                .filter(|l| !l.is_empty() && !l.starts_with("Usage:") && !l.starts_with("For more information"))
                .collect();
            eprintln!("nanopos-sim: {}", line.join(" ").trim_start_matches("error: "));
            return ExitCode::from(2);
        }
    };
    // The console and send end their session at the first Ctrl-C; everything else stops at once, its outputs removed.
    let interrupted = matches!(cli.command, Command::Console { .. } | Command::Send { .. })
        .then(|| std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false)));
    hal_sim::cmd::handle_ctrl_c(interrupted.clone());
    match run(cli, interrupted) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("nanopos-sim: {e}");
            ExitCode::from(2)
        }
    }
}
