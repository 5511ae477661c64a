//! Code that runs from RAM: the sample path's longest functions, copied there from flash at start-up.
//!
//! On the STM32G474 at 170 MHz the flash needs 4 wait states, and the sample interrupt is long straight-line FPU
//! code (32-bit instructions, loops unrolled) that the 1 KiB instruction cache cannot hold from one sample to the
//! next: fetched from flash it runs at about one 64-bit line per 5 cycles, 2.5 cycles per instruction. The 32 KiB CCM
//! SRAM is zero-wait-state on the instruction bus, so the interrupt's code is placed there, in the section
//! `.ramtext`, which each image's `memory.x` maps to its RAM with the load address in flash:
//!
//! ```text
//! SECTIONS {
//!   .ramtext : ALIGN(4) { __sramtext = .; *(.ramtext .ramtext.*); . = ALIGN(4); __eramtext = .; } > CCMRAM AT > FLASH
//!   __siramtext = LOADADDR(.ramtext);
//! } INSERT AFTER .rodata;
//! ```
//!
//! A function goes there with `#[cfg_attr(target_os = "none", link_section = ".ramtext.NAME")]` (in the core,
//! which forbids `unsafe`, that attribute is all it takes); what it inlines goes with it, and what it calls in flash
//! is reached through the linker's long-branch veneers (a few instructions a call). [`load`] copies the section
//! before anything in it runs. The QEMU harness (`qemu/`) includes this file and places the same functions in its
//! RAM the same way, so the copy and the code's running from RAM are checked there, bit for bit against the host.

extern "C" {
    static __sramtext: u32;
    static __eramtext: u32;
    static __siramtext: u32;
}

/// Copy `.ramtext` from its load address in flash to RAM; the barriers make the core fetch the new instructions.
///
/// # Safety
/// Call once at start-up, before anything placed in `.ramtext` can run (before the interrupts that run it are
/// enabled), with the `memory.x` above linked in.
pub unsafe fn load() {
    let (mut to, end, mut from) = (
        core::ptr::addr_of!(__sramtext) as *mut u32,
        core::ptr::addr_of!(__eramtext),
        core::ptr::addr_of!(__siramtext),
    );
    while (to as *const u32) < end {
        to.write_volatile(from.read_volatile());
        to = to.add(1);
        from = from.add(1);
    }
    // The writes complete before any fetch from the copied region.
    core::arch::asm!("dsb", "isb", options(nostack, preserves_flags));
}
