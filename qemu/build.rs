//! Put this crate's `memory.x` (mps2-an386) first on the linker's search path, and check that the vectors exist.
use std::path::PathBuf;

fn main() {
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
