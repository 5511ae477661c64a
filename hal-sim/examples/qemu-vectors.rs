//! Write the fixed input of the on-target harness: `cargo run --release -p hal-sim --example qemu-vectors -- OUT
//! [SAMPLES]`.
//!
//! The simulated board (the paper's PRBS experiment, payload removed half way) runs through the harness's
//! [`Workload`] in f32 on the host; the file holds every probe code, every DAC code, and the host's final results,
//! which the harness on the Cortex-M4F must reproduce bit for bit. `qemu/run` calls this.

use std::io::Write;
use std::process::ExitCode;

use hal_sim::board::SimBoard;
use hal_sim::sim::Scenario;
use nanopos_id::hal::StageBoard;
use nanopos_id::harness::{Vectors, Workload};
use nanopos_id::pipeline::PipelineSettings;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (Some(out), samples) = (args.first(), args.get(1)) else {
        eprintln!("usage: qemu-vectors OUT [SAMPLES]");
        return ExitCode::from(2);
    };
    let samples: usize = match samples {
        None => 20_000,
        Some(s) => match s.parse() {
            Ok(n) if n > 0 => n,
            _ => {
                eprintln!("qemu-vectors: SAMPLES must be a positive integer, got {s:?}");
                return ExitCode::from(2);
            }
        },
    };
    match run(out, samples) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("qemu-vectors: {out}: {e}");
            ExitCode::from(2)
        }
    }
}

fn run(out: &str, samples: usize) -> Result<(), String> {
    let (board_settings, pipeline_settings) = Scenario::Prbs.settings(samples as f64 * 1e-4, 1);
    // The harness designs its pipeline from the defaults: they must be what this board runs.
    if pipeline_settings != PipelineSettings::default() {
        return Err("the PRBS scenario's pipeline settings differ from the defaults the harness uses".into());
    }
    let mut board = SimBoard::new(board_settings);
    let description = board.description();
    let mut workload = Workload::new(&description).map_err(|e| e.to_string())?;
    let mut codes = Vec::with_capacity(samples);
    for _ in 0..samples {
        let probe = board.read_probe();
        let dac = workload.step(probe).dac_code;
        board.write_amplifier(dac);
        codes.push((probe, dac));
    }
    let mut bytes = Vec::new();
    Vectors::write(&description, &workload.results(), &codes, |b| bytes.extend_from_slice(b));
    if let Some(dir) = std::path::Path::new(out).parent() {
        std::fs::create_dir_all(dir).map_err(|e| e.to_string())?;
    }
    let tmp = format!("{out}.tmp");
    std::fs::File::create(&tmp)
        .and_then(|mut f| f.write_all(&bytes))
        .and_then(|()| std::fs::rename(&tmp, out))
        .map_err(|e| e.to_string())?;
    println!("qemu-vectors: {samples} samples, {} bytes -> {out}", bytes.len());
    Ok(())
}
