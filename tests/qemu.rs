//! The core on the Cortex-M4F instruction set: `qemu/run` (the harness under QEMU, see `qemu/src/main.rs`) passes,
//! builds without warnings, and writes every kernel's instruction count to `target/qemu-bench.json`; and on the
//! Cortex-M3 and the Cortex-M0, without an FPU, to `target/qemu-bench-cortex-m3.json` and `-cortex-m0.json`.
//!
//! Needs `qemu-system-arm` and `defmt-print` on the PATH and the targets `thumbv7em-none-eabihf`,
//! `thumbv7m-none-eabi` and `thumbv6m-none-eabi` (`.ci/run` installs them).

use std::path::PathBuf;
use std::process::Command;

/// The kernels the issue asks for, and the ones the table adds.
const KERNELS: [&str; 34] = [
    "pipeline_all_f32",
    "pipeline_bare_f32",
    "crls_f32",
    "cekf_f32",
    "hekf_f32",
    "hekf_f32_64_substeps",
    "hekf_dense_f32",
    "arx_rls_f32",
    "arx_rls_fixed",
    "prefilter_f32",
    "reconstruction_replica_f32",
    "antialias_replica_f32",
    "lag_replica_f32",
    "biquad_fixed",
    "excitation_prbs_f32",
    "excitation_triangle_f32",
    "excitation_sine_f32",
    "excitation_multisine_f32",
    "isr_body_all_f32",
    "console_tune_initial",
    "console_tune_prefilter",
    "console_tuning_triangle",
    "console_excite_prbs",
    "console_limits",
    "console_tune_refused_longest",
    "isr_body_applying_change",
    "status_snapshot",
    "console_excite_multisine",
    "isr_body_multisine_f32",
    "isr_body_applying_change_multisine",
    "isr_body_heaviest_applying",
    "isr_body_heaviest_f32",
    "lock_post_change",
    "lock_drain_frame",
];

/// Cycles of a sample period at 170 MHz: the interrupt body has until the next conversion ends, a sample after its
/// own (it writes the command first, whose deadline is earlier: `src/bin/nanopos-fw/board.rs`). Each instruction
/// takes at least a cycle, so a body of more instructions would fall behind the sample clock.
const SAMPLE_CYCLES: u64 = 17_000;

/// Cycles from the conversion's end, when the interrupt starts, to the next sample instant, by which the command
/// must reach the DAC (`board::DEADLINE_CYCLES`).
const COMMAND_DEADLINE_CYCLES: u64 = 14_568;

#[test]
fn the_core_on_qemu_matches_the_host_bit_for_bit_and_reports_every_kernel() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let json_path = root.join("target/qemu-bench.json");
    let latency_path = root.join("target/qemu-command-latency.json");
    let m3_path = root.join("target/qemu-bench-cortex-m3.json");
    let m0_path = root.join("target/qemu-bench-cortex-m0.json");
    for path in [&json_path, &latency_path, &m3_path, &m0_path] {
        let _ = std::fs::remove_file(path);
    }
    // The generator of the harness's input: the example `cargo test` built (see `built_generator`), which saves
    // `qemu/run` building the simulated board's crate again in a target directory of its own (about 80 s).
    let mut run = Command::new(root.join("qemu/run"));
    if let Some(generator) = built_generator() {
        run.env("NANOPOS_QEMU_GENERATOR", generator);
    }
    let out = run.current_dir(&root).output().expect("run qemu/run");
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    println!("{stdout}");
    assert!(out.status.success(), "qemu/run failed ({}):\n{stdout}\n{stderr}", out.status);
    // A verdict from each of the four runs: the M4F's two builds, the Cortex-M3's and the Cortex-M0's.
    let verdicts = stdout.lines().filter(|l| l.ends_with("PASS")).count();
    assert_eq!(verdicts, 4, "{verdicts} passing verdicts of 4 in the log:\n{stdout}");
    let warnings: Vec<&str> = stderr.lines().filter(|l| l.starts_with("warning")).collect();
    assert!(warnings.is_empty(), "the harness build warns:\n{stderr}");
    // The latched faults in the log by name, as in `status`, not as a bit mask to look up in the source.
    let faults = "faults as logged: none=none one=stuck all=over_range,stuck,not_finite";
    assert!(stdout.lines().any(|l| l.ends_with(faults)), "no line ending in `{faults}`:\n{stdout}");

    let json = std::fs::read_to_string(&json_path).expect("target/qemu-bench.json");
    let latency = std::fs::read_to_string(&latency_path).expect("target/qemu-command-latency.json");
    let m3 = std::fs::read_to_string(&m3_path).expect("target/qemu-bench-cortex-m3.json");
    let m0 = std::fs::read_to_string(&m0_path).expect("target/qemu-bench-cortex-m0.json");
    // Each whole, its last entry and the object closed (one was once cut short at its buffer's end).
    for (name, text) in [("bench", &json), ("command-latency", &latency), ("cortex-m3", &m3), ("cortex-m0", &m0)] {
        assert!(text.ends_with("}\n}\n"), "the {name} JSON is not closed:\n{text}");
    }
    let count = |k: &str, field: &str| count_in(&json, k, field);
    for k in KERNELS {
        assert!(count(k, "instructions_per_update") > 0, "{k}: zero instructions");
    }
    // Without an FPU: every kernel counted, the fixed-point ones among them, which are for such cores, and the
    // console's commands, some of them past SysTick's range there (`Clock::count_long` in `qemu/src/main.rs`).
    for k in KERNELS {
        assert!(count_in(&m3, k, "instructions_per_update") > 0, "{k}: zero instructions on the Cortex-M3");
        assert!(count_in(&m0, k, "instructions_per_update") > 0, "{k}: zero instructions on the Cortex-M0");
    }
    // One of them past the range (2^24 ticks of 40 ns at 128 ns an instruction), so counted across its wraps.
    assert!(count_in(&m3, "console_excite_multisine", "instructions_per_update") > 5_242_880);
    // The heaviest configuration the console accepts, on the sample that applies it and after: within a sample
    // counted as instructions (a necessary condition only: the board's cycles are more).
    for k in [
        "isr_body_heaviest_applying",
        "isr_body_heaviest_f32",
        "isr_body_applying_change",
        "isr_body_applying_change_multisine",
    ] {
        let worst = count(k, "max");
        assert!(worst < SAMPLE_CYCLES, "{k}: {worst} instructions, beyond the {SAMPLE_CYCLES} cycles of a sample");
    }
    // The command, written before the filters and estimators, within its deadline on every sample of the run, its
    // changes and the heaviest configuration (the `command-latency` build, whose board marks the write).
    let to_write = count_in(&latency, "isr_to_command_write", "max");
    assert!(
        to_write > 0 && to_write < COMMAND_DEADLINE_CYCLES,
        "the command is written {to_write} instructions into the interrupt, beyond the {COMMAND_DEADLINE_CYCLES} \
         cycles of its deadline"
    );
}

/// The example `qemu-vectors` as `cargo test` built it beside this test (in `examples/`, next to this binary's
/// `deps/`), if it is as new as the two libraries it is made of: a `cargo test --test qemu` after a change to the core
/// rebuilds them and not the example, whose results would then be the old code's (the harness would fail on them).
/// `None`: `qemu/run` builds the generator itself.
fn built_generator() -> Option<PathBuf> {
    let deps = std::env::current_exe().ok()?.parent()?.to_path_buf();
    let generator = deps.parent()?.join("examples").join(format!("qemu-vectors{}", std::env::consts::EXE_SUFFIX));
    let built = std::fs::metadata(&generator).ok()?.modified().ok()?;
    let newest_library = std::fs::read_dir(&deps)
        .ok()?
        .filter_map(Result::ok)
        .filter(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            (name.starts_with("libnanopos_id-") || name.starts_with("libhal_sim-")) && name.ends_with(".rlib")
        })
        .filter_map(|e| e.metadata().ok()?.modified().ok())
        .max()?;
    (built >= newest_library).then_some(generator)
}

/// `field` of kernel `k` in the harness's JSON.
fn count_in(json: &str, k: &str, field: &str) -> u64 {
    let key = format!("\"{k}\": {{\"instructions_per_update\": ");
    let at = json.find(&key).unwrap_or_else(|| panic!("{k} missing from the harness's JSON"));
    let entry = &json[at + key.len() - "\"instructions_per_update\": ".len()..];
    let entry = &entry[..entry.find('}').unwrap()];
    let value = entry.split(&format!("\"{field}\": ")).nth(1).unwrap_or_else(|| panic!("{k}: no {field}"));
    value.split(',').next().unwrap().trim().parse().unwrap_or_else(|e| panic!("{k}: {field}: {e}"))
}
