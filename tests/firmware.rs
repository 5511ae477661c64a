//! The firmware builds for the board (release, `thumbv7em-none-eabihf`) without a warning, and fits.
//!
//! The build runs in its own target directory (`target/firmware`), so it never waits on the lock of the `cargo test`
//! that runs it. Sizes are read from the ELF's section headers (Berkeley `size` convention: text = allocated
//! read-only sections, data = initialised RAM, bss = zeroed RAM) and written to `target/firmware-size.json`.

use std::path::{Path, PathBuf};
use std::process::Command;

#[derive(Debug, Default)]
struct Sizes {
    text: u64,
    data: u64,
    bss: u64,
}

fn section_sizes(elf: &[u8]) -> Sizes {
    let u16_at = |o: usize| u16::from_le_bytes([elf[o], elf[o + 1]]) as usize;
    let u32_at = |o: usize| u32::from_le_bytes(elf[o..o + 4].try_into().unwrap()) as u64;
    assert_eq!(&elf[..5], b"\x7fELF\x01", "a 32-bit ELF");
    let (shoff, shentsize, shnum) = (u32_at(0x20) as usize, u16_at(0x2E), u16_at(0x30));
    const SHT_NOBITS: u64 = 8;
    const SHF_WRITE: u64 = 1;
    const SHF_ALLOC: u64 = 2;
    let mut sizes = Sizes::default();
    for i in 0..shnum {
        let h = shoff + i * shentsize;
        let (kind, flags, size) = (u32_at(h + 4), u32_at(h + 8), u32_at(h + 20));
        if flags & SHF_ALLOC == 0 {
            continue;
        }
        if kind == SHT_NOBITS {
            sizes.bss += size;
        } else if flags & SHF_WRITE != 0 {
            sizes.data += size;
        } else {
            sizes.text += size;
        }
    }
    sizes
}

#[test]
fn firmware_builds_for_the_g474_without_warnings_and_fits() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let target_dir = root.join("target").join("firmware");
    let out = Command::new(env!("CARGO"))
        .current_dir(&root)
        .args(["build", "--release", "--target", "thumbv7em-none-eabihf", "--bin", "nanopos-fw", "--color", "never"])
        .env("CARGO_TARGET_DIR", &target_dir)
        .output()
        .expect("run cargo");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "firmware build failed:\n{stderr}");
    let warnings: Vec<&str> = stderr.lines().filter(|l| l.starts_with("warning")).collect();
    assert!(warnings.is_empty(), "firmware build warns:\n{stderr}");

    let elf_path: &Path = &target_dir.join("thumbv7em-none-eabihf/release/nanopos-fw");
    let sizes = section_sizes(&std::fs::read(elf_path).expect("firmware ELF"));
    let (flash, ram) = (sizes.text + sizes.data, sizes.data + sizes.bss);
    let report = format!(
        "{{\"text\": {}, \"data\": {}, \"bss\": {}, \"flash\": {flash}, \"static_ram\": {ram}}}\n",
        sizes.text, sizes.data, sizes.bss
    );
    std::fs::write(root.join("target/firmware-size.json"), &report).unwrap();
    println!(
        "firmware: text {} B, data {} B, bss {} B: flash {flash} B, static RAM {ram} B",
        sizes.text, sizes.data, sizes.bss
    );
    // The STM32G474RE's limits (memory.x): 512 KiB flash, 96 KiB SRAM.
    assert!(flash <= 512 * 1024 && ram <= 96 * 1024, "{sizes:?}");
}
