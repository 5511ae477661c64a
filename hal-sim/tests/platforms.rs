//! The host tools on the other desktops a lab has: `nanopos-sim` (and its tests) must build for macOS and Windows
//! without warnings, `send`'s serial port included. Checked here (`cargo check`, no linking: neither system's linker is
//! on a Linux machine), not run: the suite runs on Linux, where `send` is tested on a pseudo-terminal.

use std::path::PathBuf;
use std::process::Command;

/// Apple silicon and 64-bit Windows with Microsoft's toolchain: what a lab's desktops run. `.ci/run` installs their
/// standard libraries (`rustup target add`).
const TARGETS: [&str; 2] = ["aarch64-apple-darwin", "x86_64-pc-windows-msvc"];

#[test]
fn the_host_tools_build_for_macos_and_windows_without_warnings() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    // A target directory each: cargo locks one while it builds, and the two checks run side by side.
    let checks: Vec<_> = TARGETS
        .iter()
        .map(|target| {
            let target_dir = root.join("target").join("platforms").join(target);
            let root = root.clone();
            std::thread::spawn(move || {
                let out = Command::new(env!("CARGO"))
                    .current_dir(&root)
                    .args(["check", "-p", "hal-sim", "--all-targets", "--target", target, "--color", "never"])
                    .env("CARGO_TARGET_DIR", &target_dir)
                    .output()
                    .expect("run cargo");
                (target, out)
            })
        })
        .collect();
    for check in checks {
        let (target, out) = check.join().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        let missing = if stderr.contains("target may not be installed") {
            format!(" (its standard library is missing: rustup target add {target})")
        } else {
            String::new()
        };
        assert!(out.status.success(), "nanopos-sim does not build for {target}{missing}:\n{stderr}");
        let warnings: Vec<&str> = stderr.lines().filter(|l| l.starts_with("warning")).collect();
        assert!(warnings.is_empty(), "nanopos-sim warns on {target}:\n{stderr}");
    }
}
