//! `nanopos-sim simulate --scenario NAME [--duration S] [--seed N] [--hysteresis] [--creep] [--gain-drift PCT_PER_MIN]
//! [--hum HZ:NM]... [--noise NM] [--noise-tail DOF] [--amplitude V] --out FILE.csv`
//!
//! The paper's experiment on the simulated stage, driven by the real pipeline: payload on, removed at half the
//! duration; with the piezo's hysteresis and creep if asked (their defaults, [`crate::plant::Hysteresis`] and
//! [`crate::plant::Creep`]), and its gain drifting at a steady rate
//! ([`crate::plant::PlantSettings::gain_drift_per_s`]: the truth's `b0` follows it), and mains pickup on the probe
//! ([`crate::board::BoardSettings::hum`]), another probe noise ([`super::Disturbances`]), the excitation at another
//! amplitude if asked (through the firmware's default output limits: an 8 V PRBS's steps of 16 V are ramped by its slew
//! limit of 2.5 V a sample, as on the board). Writes `t,u,y,a0,a1,b0` per sample: time (s), the commanded input as
//! output by the DAC (V), the probe reading (um), and the true stage parameters at that sample.

use super::{fail, show, CliError, OutputFile, Progress};
use crate::sim::{Scenario, Simulation};
use nanopos_id::estimator::Unfiltered;
use std::io::Write;
use std::path::Path;

/// Longest run accepted, s (a day of samples at 10 kHz is 864 M rows, about 40 GB of CSV).
pub const MAX_DURATION_S: f64 = 86_400.0;

/// Largest `--amplitude`, V: what the console's `excite` takes (the DAC reaches 8.78 V; the clamp cuts beyond).
pub const MAX_AMPLITUDE_V: f64 = 10.0;

/// What `simulate` was asked for.
#[derive(Clone, Debug)]
pub struct SimulateArgs<'a> {
    /// Which experiment.
    pub scenario: Scenario,
    /// Length, s.
    pub duration_s: f64,
    /// Noise seed (default: the reference's, 1 for PRBS and 2 for the triangle).
    pub seed: Option<u64>,
    /// With the default piezo hysteresis.
    pub hysteresis: bool,
    /// With the default piezo creep.
    pub creep: bool,
    /// The piezo's gain drift, mains pickup, the probe's noise.
    pub disturbances: super::Disturbances,
    /// The excitation's amplitude, V (default: the scenario's, 1 V).
    pub amplitude_v: Option<f64>,
    /// Where to write.
    pub out: &'a Path,
}

/// What `simulate` wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct Simulated {
    /// Rows written (samples).
    pub rows: u64,
    /// What the file holds that was not asked for: the firmware's pipeline stopped the excitation at a fault, or the
    /// excitation was too small to move the DAC.
    pub notes: Vec<String>,
}

/// Run it.
pub fn run(args: &SimulateArgs) -> Result<Simulated, CliError> {
    if !(args.duration_s.is_finite() && args.duration_s > 0.0) {
        return fail(format!("--duration {}: must be a positive number of seconds", show(args.duration_s)));
    }
    if args.duration_s > MAX_DURATION_S {
        return fail(format!("--duration {}: longer than the {MAX_DURATION_S} s limit", show(args.duration_s)));
    }
    let drift = args.disturbances.gain_drift_pct_per_min;
    let drift_per_s = super::gain_drift_per_s(drift)?;
    if 1.0 + drift_per_s * args.duration_s <= 0.0 {
        return fail(format!(
            "--gain-drift {}: the gain would reach zero after {} s, within the run's {} s",
            show(drift),
            show(-1.0 / drift_per_s),
            show(args.duration_s)
        ));
    }
    if let Some(a) = args.amplitude_v.filter(|a| !(0.0..=MAX_AMPLITUDE_V).contains(a)) {
        return fail(format!("--amplitude {}: must be 0 to {MAX_AMPLITUDE_V} V, as `excite` takes it", show(a)));
    }
    let seed = args.seed.unwrap_or(args.scenario.default_seed());
    let (mut board, mut pipeline) = args.scenario.settings(args.duration_s, seed);
    if let Some(a) = args.amplitude_v {
        pipeline.excitation.amplitude_v = a;
    }
    board.plant.hysteresis = args.hysteresis.then(crate::plant::Hysteresis::default);
    board.plant.creep = args.creep.then(crate::plant::Creep::default);
    args.disturbances.apply(&mut board)?;
    let samples = (args.duration_s / board.plant.sample_period_s).round() as u64;
    if samples < 2 {
        return fail(format!("--duration {}: shorter than two samples", show(args.duration_s)));
    }
    let mut sim = Simulation::new(board, &pipeline, Unfiltered).map_err(|e| CliError(format!("settings: {e}")))?;
    let time = TimeColumn::new(sim.config.sample_period_s);

    let mut out = OutputFile::create(args.out)?;
    let mut progress = Progress::new("simulate", samples);
    let mut fmt = ryu::Buffer::new();
    let mut truth_text = String::new();
    let mut truth_of = None;
    // The first sample a fault latched at (the pipeline stops the excitation, as the board's does), and whether the
    // command ever moved from the first sample's.
    let mut first_fault = None;
    let (mut u_first, mut u_moved) = (None, false);
    let mut write_all = |out: &mut OutputFile| -> std::io::Result<()> {
        let w = out.writer();
        w.write_all(b"t,u,y,a0,a1,b0\n")?;
        for k in 0..samples {
            let (r, o) = sim.step();
            if first_fault.is_none() && !o.faults.is_empty() {
                first_fault = Some((k, r.t_s, o.faults));
            }
            u_moved |= *u_first.get_or_insert(r.u_v) != r.u_v;
            if truth_of != Some(r.truth) {
                truth_text = format!("{},{},{}\n", r.truth.a0, r.truth.a1, r.truth.b0);
                truth_of = Some(r.truth);
            }
            time.write(w, k, r.t_s)?;
            w.write_all(fmt.format(r.u_v).as_bytes())?;
            w.write_all(b",")?;
            w.write_all(fmt.format(r.y_um).as_bytes())?;
            w.write_all(b",")?;
            w.write_all(truth_text.as_bytes())?;
            if k % 65_536 == 0 {
                progress.update(k);
            }
        }
        Ok(())
    };
    let result = write_all(&mut out);
    progress.finish();
    result.map_err(|e| out.write_error(e))?;
    out.commit()?;
    let mut notes = Vec::new();
    if let Some((k, t_s, faults)) = first_fault {
        notes.push(format!(
            "the firmware's pipeline latched a fault ({}) at t = {} s (line {} of {}): it stopped the excitation \
             there, as the board's does until `start`: u is the safe value from the next line on",
            faults.names().collect::<Vec<_>>().join(", "),
            time.text(k, t_s),
            k + 2,
            args.out.display()
        ));
    }
    let amplitude_v = pipeline.excitation.amplitude_v;
    if !u_moved && amplitude_v > 0.0 && first_fault.is_none_or(|(k, _, _)| k > 0) {
        notes.push(format!(
            "u never moved from {} V: the excitation's {} V is under half the DAC's step of {} V, to which the \
             command is rounded (the board's `excite` says so too)",
            show(u_first.unwrap_or(0.0)),
            show(amplitude_v),
            show(sim.config.command_lsb_v)
        ));
    }
    Ok(Simulated { rows: samples, notes })
}

/// Writes the time column. When the sample period is a power of ten (1e-4 s at 10 kHz) the time of sample `k` is
/// printed exactly from `k` with integer arithmetic (`k / 10^d`, `.`, `k % 10^d`), which is also several times faster
/// than float formatting; otherwise the shortest round-trip representation of `k T`.
struct TimeColumn {
    decimals: Option<u32>,
}

impl TimeColumn {
    fn new(period_s: f64) -> Self {
        let decimals = (0..=9u32).find(|&d| (period_s * 10f64.powi(d as i32) - 1.0).abs() < 1e-12);
        TimeColumn { decimals }
    }

    /// Sample `k`'s time as the column has it (for a message).
    fn text(&self, k: u64, t_s: f64) -> String {
        let mut bytes = Vec::new();
        self.write(&mut bytes, k, t_s).expect("a Vec takes every byte");
        String::from_utf8_lossy(bytes.strip_suffix(b",").unwrap_or(&bytes)).into_owned()
    }

    fn write(&self, w: &mut impl Write, k: u64, t_s: f64) -> std::io::Result<()> {
        match self.decimals {
            Some(d) => {
                let scale = 10u64.pow(d);
                let mut int = itoa::Buffer::new();
                w.write_all(int.format(k / scale).as_bytes())?;
                if d > 0 {
                    let frac = k % scale;
                    let mut digits = [b'0'; 9];
                    let mut f = frac;
                    for i in (0..d as usize).rev() {
                        digits[i] = b'0' + (f % 10) as u8;
                        f /= 10;
                    }
                    w.write_all(b".")?;
                    w.write_all(&digits[..d as usize])?;
                }
                w.write_all(b",")
            }
            None => {
                let mut fmt = ryu::Buffer::new();
                w.write_all(fmt.format(t_s).as_bytes())?;
                w.write_all(b",")
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::TimeColumn;

    /// A power-of-ten period is printed from the sample's index with as many decimals as it has, none for 1 s; another
    /// as the shortest representation of the time.
    #[test]
    fn the_time_column_prints_the_periods_decimals() {
        let text = |period: f64, k: u64| TimeColumn::new(period).text(k, k as f64 * period);
        assert_eq!(text(1e-4, 123_456), "12.3456");
        assert_eq!(text(1e-4, 7), "0.0007");
        assert_eq!(text(0.01, 1_005), "10.05");
        assert_eq!(text(1.0, 5), "5");
        assert_eq!(text(2e-4, 3), "0.0006000000000000001");
    }
}
