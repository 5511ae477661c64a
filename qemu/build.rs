//! Put this crate's `memory.x` (mps2-an386 and mps2-an385 have the same map, and the runner gives the microbit's
//! memories that size) first on the linker's search path, check that the vectors exist, and tell the harness which
//! core it is built for: `cortex_m3` for `thumbv7m-none-eabi` (no FPU: QEMU's mps2-an385), `cortex_m0` for
//! `thumbv6m-none-eabi` (QEMU's microbit), none for `thumbv7em-none-eabihf` (the board's Cortex-M4F).
use std::path::PathBuf;

fn main() {
    println!("cargo::rustc-check-cfg=cfg(cortex_m3, cortex_m0)");
    match std::env::var("TARGET").as_deref() {
        Ok("thumbv7m-none-eabi") => println!("cargo:rustc-cfg=cortex_m3"),
        Ok("thumbv6m-none-eabi") => println!("cargo:rustc-cfg=cortex_m0"),
        _ => {}
    }
    let out = PathBuf::from(std::env::var_os("OUT_DIR").unwrap());
    std::fs::copy("memory.x", out.join("memory.x")).expect("copy memory.x");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.x");
    let vectors = PathBuf::from("../target/qemu-vectors.bin");
    println!("cargo:rerun-if-changed={}", vectors.display());
    if !vectors.exists() {
        panic!(
            "{} is missing: `qemu/run` generates it (cargo run --release -p hal-sim --example qemu-vectors)",
            vectors.display()
        );
    }
}
