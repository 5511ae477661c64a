//! The firmware builds for the board (release, `thumbv7em-none-eabihf`) without a warning, and fits.
//!
//! The build runs in its own target directory (`target/firmware`), so it never waits on the lock of the `cargo test`
//! that runs it. Sizes are read from the ELF's section headers (Berkeley `size` convention: text = allocated
//! read-only sections, data = initialised RAM, bss = zeroed RAM) and written to `target/firmware-size.json`, with
//! `ccm_code`, the code that runs from CCM SRAM (in `text`: it is stored in flash).

use std::path::{Path, PathBuf};
use std::process::Command;

#[derive(Debug, Default)]
struct Sizes {
    text: u64,
    data: u64,
    bss: u64,
}

/// A little-endian 32-bit ELF, read in place: fields by offset, section headers by index.
struct Elf<'a>(&'a [u8]);

impl<'a> Elf<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        assert_eq!(&bytes[..6], b"\x7fELF\x01\x01", "a 32-bit little-endian ELF");
        Elf(bytes)
    }
    fn u16_at(&self, o: usize) -> usize {
        u16::from_le_bytes([self.0[o], self.0[o + 1]]) as usize
    }
    fn u32_at(&self, o: usize) -> u64 {
        u32::from_le_bytes(self.0[o..o + 4].try_into().unwrap()) as u64
    }
    /// The NUL-terminated string at `o`.
    fn str_at(&self, o: usize) -> &'a str {
        let end = self.0[o..].iter().position(|&b| b == 0).unwrap();
        std::str::from_utf8(&self.0[o..o + end]).unwrap()
    }
    /// Offsets of the section headers.
    fn sections(&self) -> impl Iterator<Item = usize> + '_ {
        let (shoff, shentsize, shnum) = (self.u32_at(0x20) as usize, self.u16_at(0x2E), self.u16_at(0x30));
        (0..shnum).map(move |i| shoff + i * shentsize)
    }
    /// The header of the section named `name`.
    fn section(&self, name: &str) -> Option<usize> {
        let names_header = self.sections().nth(self.u16_at(0x32))?;
        let names = self.u32_at(names_header + 16) as usize;
        self.sections().find(|&h| self.str_at(names + self.u32_at(h) as usize) == name)
    }
}

fn section_sizes(elf: &Elf) -> Sizes {
    const SHT_NOBITS: u64 = 8;
    const SHF_WRITE: u64 = 1;
    const SHF_ALLOC: u64 = 2;
    let mut sizes = Sizes::default();
    for h in elf.sections() {
        let (kind, flags, size) = (elf.u32_at(h + 4), elf.u32_at(h + 8), elf.u32_at(h + 20));
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
    let bytes = std::fs::read(elf_path).expect("firmware ELF");
    let elf = Elf::new(&bytes);
    let sizes = section_sizes(&elf);
    let (flash, ram) = (sizes.text + sizes.data, sizes.data + sizes.bss);
    let ccm_code = check_ram_code(&elf);
    check_stack_below_statics(&elf);
    let report = format!(
        "{{\"text\": {}, \"data\": {}, \"bss\": {}, \"flash\": {flash}, \"static_ram\": {ram}, \"ccm_code\": {ccm_code}}}\n",
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

/// Linked by flip-link (`.cargo/config.toml`): the stack starts below every static and grows down to the start of
/// RAM, so an overflow faults at the RAM's edge instead of overwriting the statics. Without it the stack starts at
/// the top of RAM, above them.
fn check_stack_below_statics(elf: &Elf) {
    const RAM_START: u64 = 0x2000_0000;
    let symtab = elf.section(".symtab").expect("symbols");
    let strtab = elf.sections().nth(elf.u32_at(symtab + 24) as usize).expect("the symbols' strings");
    let (sym_off, sym_size, strings) =
        (elf.u32_at(symtab + 16) as usize, elf.u32_at(symtab + 20) as usize, elf.u32_at(strtab + 16) as usize);
    let stack_start = (sym_off..sym_off + sym_size)
        .step_by(16)
        .find(|&s| elf.str_at(strings + elf.u32_at(s) as usize) == "_stack_start")
        .map(|s| elf.u32_at(s + 4))
        .expect("a _stack_start symbol");
    for name in [".data", ".bss", ".uninit"] {
        let h = elf.section(name).unwrap_or_else(|| panic!("a {name} section"));
        let addr = elf.u32_at(h + 12);
        assert!(
            stack_start <= addr,
            "the stack starts at {stack_start:#x}, above {name} at {addr:#x}: not flip-link's"
        );
    }
    let stack = stack_start - RAM_START;
    assert!(stack >= 64 * 1024, "a stack of {stack} B");
    println!("firmware: stack {stack} B, from {stack_start:#x} down to the start of RAM, below the statics");
}

/// The sample interrupt runs from CCM SRAM (`src/bin/nanopos-fw/ram_code.rs`): `.ramtext` lies in the CCM, is
/// loaded from flash where nothing else is loaded, and holds the interrupt and the EKFs' RK4 step. Returns its size
/// (part of `text`, the flash figure; not of the static RAM, which counts SRAM1 and SRAM2).
fn check_ram_code(elf: &Elf) -> u64 {
    const CCM: core::ops::Range<u64> = 0x1000_0000..0x1000_8000;
    const FLASH: core::ops::Range<u64> = 0x0800_0000..0x0808_0000;
    let u32_at = |o: usize| elf.u32_at(o);
    let text = elf.section(".ramtext").expect("a .ramtext section");
    let (addr, size) = (u32_at(text + 12), u32_at(text + 20));
    assert!(CCM.contains(&addr) && addr + size <= CCM.end && size > 0, ".ramtext at {addr:#x}, {size} B");

    // Load addresses: the segment holding .ramtext is loaded in flash, overlapping no other segment's load range.
    let (phoff, phentsize, phnum) = (u32_at(0x1C) as usize, elf.u16_at(0x2A), elf.u16_at(0x2C));
    const PT_LOAD: u64 = 1;
    let loads: Vec<(u64, u64, u64)> = (0..phnum)
        .map(|i| phoff + i * phentsize)
        .filter(|&p| u32_at(p) == PT_LOAD && u32_at(p + 16) > 0)
        .map(|p| (u32_at(p + 8), u32_at(p + 12), u32_at(p + 16)))
        .collect();
    let &(_, lma, filesz) = loads.iter().find(|l| l.0 == addr).expect("a segment for .ramtext");
    assert!(FLASH.contains(&lma) && lma + filesz <= FLASH.end && filesz == size, "loaded from {lma:#x}");
    for &(vaddr, paddr, len) in &loads {
        let disjoint = paddr + len <= lma || lma + filesz <= paddr;
        assert!(vaddr == addr || disjoint, "the segment at {vaddr:#x} is loaded over .ramtext's image");
    }

    // The symbols placed there.
    let symtab = elf.section(".symtab").expect("symbols");
    let strtab = elf.sections().nth(u32_at(symtab + 24) as usize).expect("the symbols' strings");
    let (sym_off, sym_size) = (u32_at(symtab + 16) as usize, u32_at(symtab + 20) as usize);
    let strings = u32_at(strtab + 16) as usize;
    let in_ccm = |needle: &str| {
        (sym_off..sym_off + sym_size).step_by(16).any(|s| {
            let value = u32_at(s + 4) & !1;
            elf.str_at(strings + u32_at(s) as usize).contains(needle) && (addr..addr + size).contains(&value)
        })
    };
    let placed = [
        "ADC1_2",
        "EkfCore$LT$T$GT$3rk4",
        "EkfCore$LT$T$GT$16bound_covariance",
        "13apply_pending",
        "Instrument$LT$T$GT$6status",
    ];
    for needle in placed {
        assert!(in_ccm(needle), "{needle} is not in .ramtext");
    }
    println!("firmware: .ramtext {size} B of the 32 KiB CCM SRAM at {addr:#x}, loaded from {lma:#x}");
    check_sample_path_calls(elf, addr, size);
    size
}

/// What the sample interrupt and the functions it calls in `.ramtext` branch to: the EKFs' RK4 step (which shows
/// the decoding finds calls), and no software double-precision routine (`__aeabi_d*`, `__aeabi_f2d`) and no libm
/// function but `sqrtf` (the covariance bounds' repair), directly or through a long-branch veneer. libm's `sinf`
/// works in f64: the triangle excitation took 2 778 instructions a sample through it (BENCHMARKS.md).
fn check_sample_path_calls(elf: &Elf, ram_addr: u64, ram_size: u64) {
    let symtab = elf.section(".symtab").expect("symbols");
    let strtab = elf.sections().nth(elf.u32_at(symtab + 24) as usize).expect("the symbols' strings");
    let (sym_off, sym_size) = (elf.u32_at(symtab + 16) as usize, elf.u32_at(symtab + 20) as usize);
    let strings = elf.u32_at(strtab + 16) as usize;
    const STT_FUNC: u64 = 2;
    // (address, size, name) of every function.
    let functions: Vec<(u64, u64, &str)> = (sym_off..sym_off + sym_size)
        .step_by(16)
        .filter(|&s| elf.0[s + 12] as u64 & 0xF == STT_FUNC)
        .map(|s| (elf.u32_at(s + 4) & !1, elf.u32_at(s + 8), elf.str_at(strings + elf.u32_at(s) as usize)))
        .collect();
    let text = elf.section(".ramtext").unwrap();
    let file_at = |a: u64| (elf.u32_at(text + 16) + a - ram_addr) as usize;
    // The 32-bit Thumb branches with link (BL, BLX) and wide branches (B.W, tail calls) in a function's bytes.
    let targets = |start: u64, len: u64| {
        let mut out = Vec::new();
        let mut pc = start;
        while pc + 4 <= start + len {
            let (h1, h2) = (elf.u16_at(file_at(pc)) as i64, elf.u16_at(file_at(pc) + 2) as i64);
            if h1 >> 11 == 0b11110 && matches!(h2 & 0xD000, 0xD000 | 0xC000 | 0x9000) {
                let s = (h1 >> 10) & 1;
                let (i1, i2) = (1 ^ ((h2 >> 13) & 1) ^ s, 1 ^ ((h2 >> 11) & 1) ^ s);
                let imm = (s << 24 | i1 << 23 | i2 << 22 | (h1 & 0x3FF) << 12 | (h2 & 0x7FF) << 1) << 39 >> 39;
                let base = if h2 & 0xD000 == 0xC000 { (pc + 4) & !3 } else { pc + 4 };
                out.push((base as i64 + imm) as u64);
                pc += 4;
            } else {
                pc += 2;
            }
        }
        out
    };
    let name_at = |a: u64| functions.iter().find(|f| f.0 == a).map(|f| f.2);
    let mut callees = Vec::new();
    for needle in ["ADC1_2", "EkfCore$LT$T$GT$3rk4", "13apply_pending"] {
        let &(start, len, _) = functions
            .iter()
            .find(|f| f.2.contains(needle) && (ram_addr..ram_addr + ram_size).contains(&f.0))
            .unwrap_or_else(|| panic!("{needle} in .ramtext"));
        callees.extend(targets(start, len).into_iter().filter_map(name_at).map(|n| (needle, n)));
    }
    assert!(callees.iter().any(|(from, to)| *from == "ADC1_2" && to.contains("EkfCore$LT$T$GT$3rk4")), "{callees:?}");
    let forbidden =
        |n: &str| n.contains("aeabi_d") || n.contains("aeabi_f2d") || (n.contains("libm") && !n.contains("sqrtf"));
    let bad: Vec<_> = callees.iter().filter(|(_, to)| forbidden(to)).collect();
    assert!(bad.is_empty(), "the sample path calls software double or libm: {bad:?}");
}
