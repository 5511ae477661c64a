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
    /// Every symbol: value, size, type (`STT_*`) and name.
    fn symbols(&self) -> impl Iterator<Item = (u64, u64, u8, &'a str)> + '_ {
        let symtab = self.section(".symtab").expect("symbols");
        let strtab = self.sections().nth(self.u32_at(symtab + 24) as usize).expect("the symbols' strings");
        let (sym_off, sym_size) = (self.u32_at(symtab + 16) as usize, self.u32_at(symtab + 20) as usize);
        let strings = self.u32_at(strtab + 16) as usize;
        (sym_off..sym_off + sym_size).step_by(16).map(move |s| {
            (
                self.u32_at(s + 4),
                self.u32_at(s + 8),
                self.0[s + 12] & 0xF,
                self.str_at(strings + self.u32_at(s) as usize),
            )
        })
    }
    /// Every function: start address (the Thumb bit cleared), size and name.
    fn functions(&self) -> Vec<(u64, u64, &'a str)> {
        const STT_FUNC: u8 = 2;
        self.symbols().filter(|s| s.2 == STT_FUNC).map(|(value, size, _, name)| (value & !1, size, name)).collect()
    }
    /// Where the byte at `addr` (a run-time address: `.ramtext`'s are in the CCM) is in the file.
    fn file_offset(&self, addr: u64) -> Option<usize> {
        const SHT_NOBITS: u64 = 8;
        const SHF_ALLOC: u64 = 2;
        self.sections()
            .find(|&h| {
                let (kind, flags, start, size) =
                    (self.u32_at(h + 4), self.u32_at(h + 8), self.u32_at(h + 12), self.u32_at(h + 20));
                kind != SHT_NOBITS && flags & SHF_ALLOC != 0 && (start..start + size).contains(&addr)
            })
            .map(|h| (self.u32_at(h + 16) + addr - self.u32_at(h + 12)) as usize)
    }
    /// The calls out of the function at `start` of `len` bytes (BL, BLX, and B.W to outside it): the index of the
    /// instruction and the target, in order.
    fn calls_out(&self, start: u64, len: u64) -> Vec<(usize, u64)> {
        self.instructions(start, len)
            .into_iter()
            .enumerate()
            .filter_map(|(i, (pc, h1, h2))| h2.and_then(|h2| branch_target(pc, h1, h2)).map(|to| (i, to)))
            .filter(|&(_, to)| !(start..start + len).contains(&to))
            .collect()
    }
    /// The Thumb instructions of `len` bytes from `start`: address, first halfword, and the second of a 32-bit one.
    fn instructions(&self, start: u64, len: u64) -> Vec<(u64, u16, Option<u16>)> {
        let at = self.file_offset(start).unwrap_or_else(|| panic!("no code at {start:#x}"));
        let halfword = |pc: u64| self.u16_at(at + (pc - start) as usize) as u16;
        let mut out = Vec::new();
        let mut pc = start;
        while pc + 2 <= start + len {
            let h1 = halfword(pc);
            if h1 >> 11 >= 0b11101 && pc + 4 <= start + len {
                out.push((pc, h1, Some(halfword(pc + 2))));
                pc += 4;
            } else {
                out.push((pc, h1, None));
                pc += 2;
            }
        }
        out
    }
}

/// Where a 32-bit branch with link (BL, BLX) or wide branch (B.W, a tail call) at `pc` goes.
fn branch_target(pc: u64, h1: u16, h2: u16) -> Option<u64> {
    let (h1, h2) = (h1 as i64, h2 as i64);
    if h1 >> 11 != 0b11110 || !matches!(h2 & 0xD000, 0xD000 | 0xC000 | 0x9000) {
        return None;
    }
    let s = (h1 >> 10) & 1;
    let (i1, i2) = (1 ^ ((h2 >> 13) & 1) ^ s, 1 ^ ((h2 >> 11) & 1) ^ s);
    let imm = (s << 24 | i1 << 23 | i2 << 22 | (h1 & 0x3FF) << 12 | (h2 & 0x7FF) << 1) << 39 >> 39;
    let base = if h2 & 0xD000 == 0xC000 { (pc + 4) & !3 } else { pc + 4 };
    Some((base as i64 + imm) as u64)
}

/// `CPSID` (interrupts or faults off), or `MSR` to PRIMASK, BASEPRI, BASEPRI_MAX or FAULTMASK.
fn masks_interrupts(h1: u16, h2: Option<u16>) -> bool {
    match h2 {
        None => h1 & 0xFFF8 == 0xB670 && h1 & 0x7 != 0,
        Some(h2) => h1 & 0xFFF0 == 0xF380 && h2 & 0xFF00 == 0x8800 && (0x10..=0x13).contains(&(h2 & 0xFF)),
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
    check_logger_leaves_interrupts_on(&elf, &root);
    check_panic_puts_the_output_safe_first(&elf);
    check_start_up_puts_the_output_safe_first(&elf);
    check_tasks_lock_clear_of_samples(&elf);
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
    let stack_start = elf.symbols().find(|s| s.3 == "_stack_start").map(|s| s.0).expect("a _stack_start symbol");
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
    let in_ccm =
        |needle: &str| elf.symbols().any(|s| s.3.contains(needle) && (addr..addr + size).contains(&(s.0 & !1)));
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
    let functions = elf.functions();
    let targets = |start: u64, len: u64| -> Vec<u64> {
        elf.instructions(start, len).into_iter().filter_map(|(pc, h1, h2)| branch_target(pc, h1, h2?)).collect()
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

/// The defmt logger neither masks interrupts nor waits for the host (defmt-rtt's `drop-on-contention` and
/// `disable-blocking-mode`, `Cargo.toml`). Its default writes each log frame with every interrupt masked, so the
/// sample interrupt waited for every telemetry line, and once `probe-rs run` has put the channel in blocking mode
/// (it does, for defmt) it spins there while the buffer is full: a host that stops reading stopped the sample clock,
/// the console and, in the panic handler, the fault handler's safe output. Checked on the linked code: the logger's
/// entry points and the functions they call (but the panic path's, whose handler masks interrupts on purpose)
/// contain no `CPSID` and no `MSR` to the masking registers; the same scan finds the sample interrupt's own lock
/// (`cortex_m::interrupt::free` in `ADC1_2`), which shows it sees one. The features from `cargo tree`.
fn check_logger_leaves_interrupts_on(elf: &Elf, root: &Path) {
    let functions = elf.functions();
    let function = |name: &str| *functions.iter().find(|f| f.2 == name).unwrap_or_else(|| panic!("no {name}"));
    // The instructions that mask, in `from` and what it calls (a function once, the panic path not followed).
    let masking = |from: &str| {
        let (mut todo, mut seen, mut found) = (vec![function(from)], Vec::new(), Vec::new());
        while let Some((start, len, name)) = todo.pop() {
            if seen.contains(&start) || name.contains("panicking") {
                continue;
            }
            seen.push(start);
            for (pc, h1, h2) in elf.instructions(start, len) {
                if masks_interrupts(h1, h2) {
                    found.push(format!("{name} at {pc:#x}"));
                }
                let callee = h2.and_then(|h2| branch_target(pc, h1, h2));
                todo.extend(callee.and_then(|a| functions.iter().find(|f| f.0 == a && f.1 > 0)));
            }
        }
        (found, seen)
    };
    let (isr, _) = masking("ADC1_2");
    assert!(!isr.is_empty(), "the scan does not see ADC1_2's lock");
    let mut scanned = Vec::new();
    for entry in ["_defmt_acquire", "_defmt_write", "_defmt_release", "_defmt_timestamp"] {
        let (found, seen) = masking(entry);
        assert!(found.is_empty(), "the logger masks interrupts: {found:?}");
        scanned.extend(seen.into_iter().filter(|f| !scanned.contains(f)).collect::<Vec<_>>());
    }
    let out = Command::new(env!("CARGO"))
        .current_dir(root)
        .args(["tree", "-e", "features", "-i", "defmt-rtt", "--target", "thumbv7em-none-eabihf", "--prefix", "none"])
        .output()
        .expect("run cargo tree");
    let tree = String::from_utf8_lossy(&out.stdout);
    for feature in ["drop-on-contention", "disable-blocking-mode"] {
        assert!(tree.contains(&format!("defmt-rtt feature \"{feature}\"")), "defmt-rtt without {feature}:\n{tree}");
    }
    let scanned = scanned.len();
    println!("firmware: the defmt logger ({scanned} functions) leaves interrupts on and never waits for the host");
}

/// The panic handlers (Rust's and defmt's) mask interrupts and put the output safe (`board::force_safe_output`,
/// their first call) before they log or fault: `probe-rs run` halts the core at the HardFault vector by default,
/// so a panic that left the safe output to the HardFault handler (panic-probe's way) held the last command until
/// the watchdog reset the board.
fn check_panic_puts_the_output_safe_first(elf: &Elf) {
    let functions = elf.functions();
    // Rust's panic handler, and defmt's (`defmt::panic!`, `unwrap!`).
    for handler in ["rust_begin_unwind", "_defmt_panic"] {
        let &(start, len, _) = functions
            .iter()
            .find(|f| f.2.contains(handler) && !f.2.contains("default"))
            .unwrap_or_else(|| panic!("the panic handler {handler}"));
        let code = elf.instructions(start, len);
        let &(first_call, to) = elf.calls_out(start, len).first().unwrap_or_else(|| panic!("a call in {handler}"));
        let callee = functions.iter().find(|f| f.0 == to);
        assert!(
            callee.is_some_and(|f| f.2.contains("force_safe_output")),
            "{handler} calls {callee:?} first, not board::force_safe_output"
        );
        assert!(
            code[..first_call].iter().any(|&(_, h1, h2)| masks_interrupts(h1, h2)),
            "{handler} does not mask interrupts before it puts the output safe"
        );
    }
    println!("firmware: the panic handlers mask interrupts and put the output safe first");
}

/// The start-up drives the output to its safe value (`board::early_safe_output`) before anything else: from a reset
/// until then the DAC is off and its pin floats, and whatever ran before it (the RAM code's copy, the crystal's
/// start-up, the clocks, the designs) would keep it floating for longer. Its call is the start-up's first, within
/// its first [`EARLY_CALL_WITHIN`] instructions (the prologue and the task's state dispatch), so that nothing
/// inlined comes before it either (the RAM code's copy or the crystal's wait would: loops of their own).
fn check_start_up_puts_the_output_safe_first(elf: &Elf) {
    const EARLY_CALL_WITHIN: usize = 24;
    let functions = elf.functions();
    let target = |f: &(u64, u64, &str)| f.2.contains("early_safe_output");
    let &(early, _, _) = functions.iter().find(|f| target(f)).expect("board::early_safe_output, never inlined");
    let callers: Vec<_> = functions
        .iter()
        .filter(|f| !target(f))
        .map(|f| (f.2, elf.calls_out(f.0, f.1)))
        .filter(|(_, calls)| calls.iter().any(|c| c.1 == early))
        .collect();
    assert_eq!(callers.len(), 1, "board::early_safe_output called from {:?}", callers.iter().map(|c| c.0));
    let (caller, calls) = &callers[0];
    let (at, first) = calls[0];
    let first_name = functions.iter().find(|f| f.0 == first).map(|f| f.2);
    assert_eq!(first, early, "the start-up ({caller}) calls {first_name:?} first, not board::early_safe_output");
    assert!(at < EARLY_CALL_WITHIN, "the start-up calls board::early_safe_output at its instruction {at}");
    println!("firmware: the start-up puts the output safe first (its instruction {at})");
}

/// The tasks take the interrupt's state (`with_task`, which holds the interrupts off) only when the sample interrupt
/// is not due within the hold: `mask_clear_of_sample` masks interrupts and, masked, asks `board::clear_of_sample`
/// (its arithmetic is `nanopos_id::hal::clear_of_sample`, tested on the host) before it goes on. (That the tasks take
/// the lock only after it is the source's: `firmware.rs` has no other `TASK.borrow` outside the interrupt and the
/// start-up.) A snapshot taken without it could hold the sample interrupt off by 2 000 cycles, which with the
/// heaviest configuration leaves it near its deadline (BENCHMARKS.md).
fn check_tasks_lock_clear_of_samples(elf: &Elf) {
    let functions = elf.functions();
    let instances: Vec<_> =
        functions.iter().filter(|f| f.2.contains("firmware20mask_clear_of_sample") && f.1 > 0).collect();
    let &[&(start, len, name)] = instances.as_slice() else { panic!("mask_clear_of_sample: {instances:?} (inlined?)") };
    let code = elf.instructions(start, len);
    let masked = code.iter().position(|&(_, h1, h2)| masks_interrupts(h1, h2));
    let asks = code.iter().position(|&(pc, h1, h2)| {
        let callee = h2.and_then(|h2| branch_target(pc, h1, h2));
        callee.and_then(|a| functions.iter().find(|f| f.0 == a)).is_some_and(|f| f.2.contains("clear_of_sample"))
    });
    assert!(
        matches!((masked, asks), (Some(m), Some(a)) if m < a),
        "{name} does not ask board::clear_of_sample with interrupts masked (mask at {masked:?}, ask at {asks:?})"
    );
    println!("firmware: the tasks take the lock only clear of a sample");
}
