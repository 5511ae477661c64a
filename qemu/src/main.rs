//! The nanopos-id core on the Cortex-M4F instruction set, under QEMU (`mps2-an386`): `qemu/run` at the repository
//! root builds and runs it.
//!
//! 1. **Correctness.** Replays the probe codes the simulated board produced (`target/qemu-vectors.bin`, embedded)
//!    through the harness workload (the pipeline with the paper's three estimators, the ARX RLS in f32 and in
//!    Q31.32, the dense hybrid EKF): every DAC code and every final estimate must equal the host's, bit for bit.
//! 2. **Cost.** Times each kernel per update with SysTick under `-icount` (every instruction advances QEMU's virtual
//!    clock by exactly `2^shift` ns), converts to instructions exactly, and writes `target/qemu-bench.json`.
//!
//! The verdict is the semihosting exit status: 0 when every check passed.
//!
//! Built for `thumbv7m-none-eabi` (`qemu/run`'s third run) the same harness runs on QEMU's Cortex-M3
//! (`mps2-an385`, the same memory map), a core without an FPU: `f32` in software, which the fixed-point kernels are
//! for; built for `thumbv6m-none-eabi` (the fourth), on the Cortex-M0 of QEMU's `microbit`, its memories enlarged to
//! the same map, which has no 64-bit multiply and no divide either. The same checks against the host, the counts in
//! `target/qemu-bench-cortex-m3.json` and `target/qemu-bench-cortex-m0.json`.

#![no_std]
#![no_main]

#[cfg(all(feature = "command-latency", any(cortex_m3, cortex_m0)))]
compile_error!("the command-latency build counts the board's interrupt: build it for thumbv7em-none-eabihf");

/// The firmware's loader of the code that runs from RAM, the same file.
#[path = "../../src/bin/nanopos-fw/ram_code.rs"]
mod ram_code;

use core::fmt::Write as _;

use cortex_m::peripheral::syst::SystClkSource;
use cortex_m::peripheral::SYST;
use cortex_m_rt::{entry, exception, ExceptionFrame};
use defmt_semihosting as _;
use nanopos_id::console::{Controller, REPLY_BYTES};
use nanopos_id::control::{parse, EstimatorSet};
use nanopos_id::estimator::{Estimator, FilteredSample, Health};
use nanopos_id::excitation::{ExcitationDesign, ExcitationState};
use nanopos_id::filters::{BiquadState, PrefilterState};
use nanopos_id::fixed::Q32;
use nanopos_id::hal::{BoardDescription, BoardFaults, StageBoard};
use nanopos_id::harness::{Results, Vectors, Workload};
use nanopos_id::instrument::{Change, Instrument, Status};
use nanopos_id::pipeline::{Faults, Pipeline, PipelineSettings};
use nanopos_id::record::{RawSample, FRAME_SAMPLES};
use nanopos_id::text::TextBuf;
use nanopos_id::Scalar;

static VECTORS: &[u8] = include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/../target/qemu-vectors.bin"));

/// Updates timed per kernel: the last `BENCH` samples of the run (estimators converged, the payload change behind).
const BENCH: usize = 1000;
/// SysTick's period, ps: mps2-an386 and mps2-an385 clock it with their 25 MHz system clock (40 ns), the microbit
/// (the Cortex-M0) with its 16 MHz (62.5 ns).
#[cfg(not(cortex_m0))]
const TICK_PS: u64 = 40_000;
#[cfg(cortex_m0)]
const TICK_PS: u64 = 62_500;

/// Exact instruction counts from SysTick ticks.
struct Clock {
    /// `-icount shift`: each instruction takes `2^shift` ns of virtual time.
    shift: u32,
    /// Instructions of the timing frame itself (two SysTick reads with nothing between).
    frame: u32,
    /// Instructions from the frame's first reading to a mark taken first thing in the timed call (the
    /// `command-latency` build's).
    #[cfg_attr(not(feature = "command-latency"), allow(dead_code))]
    to_mark: u32,
    /// Instructions of SysTick's exception handler, which counts the counter's wraps in a long count
    /// ([`Clock::count_long`]): what each wrap adds to it.
    wrap_cost: u32,
}

/// SysTick's wraps during a long count ([`Clock::count_long`]), counted by its exception.
static WRAPS: core::sync::atomic::AtomicU32 = core::sync::atomic::AtomicU32::new(0);

/// SYST_CSR's TICKINT: SysTick's exception on each wrap.
const SYST_CSR_TICKINT: u32 = 1 << 1;

/// Calls the closure behind `ctx` (the timed call: its body and its prologue and epilogue are what is counted).
unsafe extern "C" fn trampoline<F: FnMut()>(ctx: *mut F) {
    // SAFETY: `ticks` passes a pointer to a live `F` that nothing else borrows during the call.
    unsafe { (*ctx)() }
}

/// Ticks of SysTick (counting down over 2^24) across one call of `f`. The two reads and the call are one `asm!`
/// block, so the compiler cannot schedule anything else into the timed region: it holds the first read, the call,
/// `f`'s body and its return, and nothing else.
#[inline(always)]
fn ticks<F: FnMut()>(f: &mut F) -> u32 {
    let (t0, t1) = ticks_at(f);
    t0.wrapping_sub(t1) & 0x00FF_FFFF
}

/// SysTick's readings before and after one call of `f` (see [`ticks`]).
#[inline(always)]
fn ticks_at<F: FnMut()>(f: &mut F) -> (u32, u32) {
    let (t0, t1): (u32, u32);
    // SAFETY: SYST_CVR (0xE000_E018) is always mapped on a Cortex-M; the callee follows the C ABI, whose
    // caller-saved registers (r0-r3, r12, lr, d0-d7) are declared clobbered; the address and the first reading live
    // in callee-saved r4/r5.
    unsafe {
        core::arch::asm!(
            "ldr r5, [r4]",
            "blx r2",
            "ldr r1, [r4]",
            inout("r0") f as *mut F => _,
            lateout("r1") t1,
            inout("r2") trampoline::<F> as *const () as usize => _,
            in("r4") 0xE000_E018u32,
            out("r5") t0,
            // The rest of the C ABI's caller-saved registers (this FPU has d0-d15 only).
            out("r3") _, out("r12") _, out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
        );
    }
    (t0, t1)
}

/// SysTick's current value: read inside a timed call, it marks how far into the call an event came.
#[cfg(feature = "command-latency")]
#[inline(always)]
fn systick_now() -> u32 {
    // SAFETY: SYST_CVR, always mapped; reading it has no side effect (COUNTFLAG is in SYST_CSR).
    unsafe { core::ptr::read_volatile(0xE000_E018 as *const u32) }
}

/// SysTick when the board was last handed a command ([`VectorBoard::write_amplifier`]).
#[cfg(feature = "command-latency")]
static COMMAND_MARK: core::sync::atomic::AtomicU32 = core::sync::atomic::AtomicU32::new(0);

/// 1 000 `nop`s, called: inlined into a loop, its size (which LLVM does not know from the `.rept`) put the loop's
/// branch out of reach.
#[inline(never)]
fn thousand_nops() {
    nops::<1000>();
}

/// Exactly `N` instructions.
#[inline(always)]
fn nops<const N: usize>() {
    // SAFETY: `nop` has no effect on memory, stack, registers or flags.
    unsafe { core::arch::asm!(".rept {n}", "nop", ".endr", n = const N, options(nomem, nostack, preserves_flags)) }
}

impl Clock {
    /// Start SysTick and find `shift` from 1000 known instructions; `None` when the counts cannot be exact.
    fn calibrate(syst: &mut SYST) -> Option<Self> {
        syst.set_clock_source(SystClkSource::Core);
        syst.set_reload(0x00FF_FFFF);
        syst.clear_current();
        syst.enable_counter();
        // The first reads after enabling see the counter's first reload: warm up.
        let _ = ticks(&mut || ());
        let empty = ticks(&mut || ());
        let one = ticks(&mut nops::<1>);
        let thousand = ticks(&mut nops::<1000>);
        // Ticks per instruction are 2^shift ns over the tick: find the power of two.
        let ns_per_insn = (u64::from(thousand - empty) * TICK_PS / 1000 + 500) / 1000;
        let shift = 63 - ns_per_insn.max(1).leading_zeros();
        defmt::info!(
            "clock: 1000 instructions took {} ticks (frame {} ticks): icount shift {}",
            thousand - empty,
            empty,
            shift
        );
        // Under 3 ticks an instruction (2^7 ns with a 40 ns tick, 2^8 with 62.5 ns) a reading's tick is not well
        // below half an instruction, and rounding the difference of two is not exact.
        if (1000 << shift) < 3 * TICK_PS || ns_per_insn.abs_diff(1 << shift) * 100 > 1 << shift {
            defmt::error!(
                "run under -icount shift=N, 2^N ns >= 3 SysTick ticks ({=u64} ps each): counts would not be exact",
                TICK_PS
            );
            return None;
        }
        let mut clock = Clock { shift, frame: 0, to_mark: 0, wrap_cost: 0 };
        clock.frame = clock.instructions(empty);
        // The instructions from the first reading to a mark taken first thing in the call.
        #[cfg(feature = "command-latency")]
        {
            let (t0, _) = ticks_at(&mut || COMMAND_MARK.store(systick_now(), core::sync::atomic::Ordering::Relaxed));
            let mark = COMMAND_MARK.load(core::sync::atomic::Ordering::Relaxed);
            clock.to_mark = clock.instructions(t0.wrapping_sub(mark) & 0x00FF_FFFF);
        }
        let exact = clock.instructions(one) == 1 + clock.frame && clock.instructions(thousand) == 1000 + clock.frame;
        defmt::info!("clock: the timing frame (two reads and an empty call) is {} instructions; 1 and 1000 instructions counted exactly: {}", clock.frame, exact);
        if !exact {
            return None;
        }
        clock.wrap_cost = clock.calibrate_wraps()?;
        Some(clock)
    }

    /// The instructions each wrap adds to a long count, from runs of `k` blocks of 1 000 `nop`s: two within
    /// SysTick's range give the cost of a block (its loop included), and two past it (6 and 11 million
    /// instructions: one wrap and two) what each wrap adds beyond it. `None` unless both agree on a whole number.
    fn calibrate_wraps(&self) -> Option<u32> {
        let blocks = |k: u32| {
            move || {
                // Read at run time, so that the loop is the same code for every `k`.
                for _ in 0..core::hint::black_box(k) {
                    thousand_nops();
                }
            }
        };
        let raw = |k: u32| self.count_long_raw(blocks(k));
        let ((_, short, w0), (_, shorter, w1)) = (raw(20), raw(10));
        let block = (short - shorter) / 10;
        let per_wrap = |k: u32| {
            let (_, n, wraps) = raw(k);
            let extra = n.checked_sub(short + (k - 20) * block)?;
            (wraps > 0 && extra.is_multiple_of(wraps)).then(|| extra / wraps)
        };
        let (a, b) = (per_wrap(6_000), per_wrap(11_000));
        let cost = a.filter(|&a| w0 == 0 && w1 == 0 && (short - shorter).is_multiple_of(10) && Some(a) == b);
        defmt::info!(
            "clock: a block of 1 000 nops counted as {} instructions; each SysTick wrap in a long count adds {}: {}",
            block,
            a.unwrap_or(0),
            if cost.is_some() { "exact" } else { "NOT EXACT" }
        );
        cost
    }

    fn instructions(&self, ticks: u32) -> u32 {
        self.instructions_long(u64::from(ticks))
    }

    /// Instructions `f` executes from its call to the command's write ([`COMMAND_MARK`]; its prologue included),
    /// and in all.
    #[cfg(feature = "command-latency")]
    #[inline(always)]
    fn count_to_command<R>(&self, mut f: impl FnMut() -> R) -> (R, u32, u32) {
        let mut out = None;
        let (t0, t1) = ticks_at(&mut || out = Some(f()));
        let mark = COMMAND_MARK.load(core::sync::atomic::Ordering::Relaxed);
        let to = self.instructions(t0.wrapping_sub(mark) & 0x00FF_FFFF).saturating_sub(self.to_mark);
        let all = self.instructions(t0.wrapping_sub(t1) & 0x00FF_FFFF).saturating_sub(self.frame);
        (out.unwrap_or_else(|| fail("timed call did not run")), to, all)
    }

    /// Instructions `f` executes when called (its body, prologue and epilogue; not the return itself).
    #[inline(always)]
    fn count<R>(&self, mut f: impl FnMut() -> R) -> (R, u32) {
        let mut out = None;
        let n = ticks(&mut || out = Some(f()));
        (out.unwrap_or_else(|| fail("timed call did not run")), self.instructions(n).saturating_sub(self.frame))
    }

    /// [`Clock::count`] for a call that may run past SysTick's range (2^24 ticks: 5.2 million instructions on
    /// mps2, 4.1 on the microbit), a console command's: SysTick restarted, its exception counting the wraps, and
    /// what its handler adds each time taken off ([`Clock::calibrate_wraps`]).
    fn count_long<R>(&self, f: impl FnMut() -> R) -> (R, u32) {
        let (out, n, wraps) = self.count_long_raw(f);
        (out, n - wraps * self.wrap_cost)
    }

    /// [`Clock::count_long`] with the handler's instructions left in, and the wraps.
    fn count_long_raw<R>(&self, mut f: impl FnMut() -> R) -> (R, u32, u32) {
        use core::sync::atomic::Ordering::Relaxed;
        // SAFETY: SysTick's registers, always mapped; nothing else uses SysTick while this runs.
        // Writing the current value restarts the count from the reload value and clears COUNTFLAG.
        let syst = unsafe { &*SYST::PTR };
        unsafe { syst.cvr.write(0) };
        WRAPS.store(0, Relaxed);
        unsafe { syst.csr.modify(|v| v | SYST_CSR_TICKINT) };
        let mut out = None;
        let (t0, t1) = ticks_at(&mut || out = Some(f()));
        unsafe { syst.csr.modify(|v| v & !SYST_CSR_TICKINT) };
        let (t2, mut wraps) = (syst.cvr.read(), WRAPS.load(Relaxed));
        // A wrap in the few instructions after the last reading (the count has gone up since): counted by the
        // handler if it came before its exception was turned off, else left pending.
        if t2 > t1 {
            if cortex_m::peripheral::SCB::is_pendst_pending() {
                cortex_m::peripheral::SCB::clear_pendst();
            } else {
                wraps -= 1;
            }
        }
        let ticks = u64::from(wraps) << 24 | u64::from(t0.wrapping_sub(t1) & 0x00FF_FFFF);
        let n = self.instructions_long(ticks).saturating_sub(self.frame);
        (out.unwrap_or_else(|| fail("timed call did not run")), n, wraps)
    }

    fn instructions_long(&self, ticks: u64) -> u32 {
        let ps_per_insn = 1000u64 << self.shift;
        u32::try_from((ticks * TICK_PS + ps_per_insn / 2) / ps_per_insn).unwrap_or_else(|_| fail("a count past 2^32"))
    }
}

/// Counts SysTick's wraps while [`Clock::count_long`] has its exception on.
#[exception]
fn SysTick() {
    use core::sync::atomic::Ordering::Relaxed;
    WRAPS.store(WRAPS.load(Relaxed) + 1, Relaxed);
}

/// Per-update counts of one kernel.
#[derive(Clone, Copy, Default)]
struct Stats {
    total: u64,
    max: u32,
    updates: u32,
}

impl Stats {
    fn add(&mut self, n: u32) {
        self.total += u64::from(n);
        self.max = self.max.max(n);
        self.updates += 1;
    }
    fn mean(&self) -> u32 {
        ((self.total + u64::from(self.updates) / 2) / u64::from(self.updates.max(1))) as u32
    }
}

/// A fixed-capacity text buffer (the JSON and the table lines).
struct Text<const N: usize> {
    buf: [u8; N],
    len: usize,
}

impl<const N: usize> Text<N> {
    const fn new() -> Self {
        Text { buf: [0; N], len: 0 }
    }
    fn as_str(&self) -> &str {
        core::str::from_utf8(&self.buf[..self.len]).unwrap_or("")
    }
}

impl<const N: usize> core::fmt::Write for Text<N> {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        let end = self.len + s.len();
        self.buf.get_mut(self.len..end).ok_or(core::fmt::Error)?.copy_from_slice(s.as_bytes());
        self.len = end;
        Ok(())
    }
}

/// The counts' JSON's buffer: 34 kernels and the mark's take about 3 100 bytes.
const JSON_BYTES: usize = 4096;

fn fail(what: &str) -> ! {
    defmt::error!("FAIL: {=str}", what);
    semihosting::process::exit(1)
}

fn compare(name: &str, got: &[u32], expected: &[u32]) -> bool {
    let same = got == expected;
    if same {
        defmt::info!("{=str}: bit-identical to the host: {:#010x}", name, got);
    } else {
        defmt::error!("{=str}: {:#010x} on QEMU, {:#010x} on the host", name, got, expected);
    }
    same
}

fn compare_results(got: &Results, expected: &Results) -> bool {
    let fixed = |r: &Results| -> [u32; 8] { core::array::from_fn(|i| (r.arx_fixed[i / 2] >> (32 * (i % 2))) as u32) };
    let sums = |r: &Results| [r.dac_code_sum as u32, (r.dac_code_sum >> 32) as u32];
    [
        compare("crls_f32 [a0, a1, b0]", &got.crls, &expected.crls),
        compare("cekf_f32 [a0, a1, b0]", &got.cekf, &expected.cekf),
        compare("hekf_f32 [a0, a1, b0]", &got.hekf, &expected.hekf),
        compare("hekf_dense_f32 [a0, a1, b0]", &got.hekf_dense, &expected.hekf_dense),
        compare("hekf_f32, 7 substeps [a0, a1, b0]", &got.hekf_squared, &expected.hekf_squared),
        compare("arx_rls_f32 [a0, a1, b0]", &got.arx, &expected.arx),
        compare("arx_rls_fixed theta (i64 halves)", &fixed(got), &fixed(expected)),
        compare("DAC code sum", &sums(got), &sums(expected)),
    ]
    .iter()
    .all(|&ok| ok)
}

#[entry]
fn main() -> ! {
    // SAFETY: first thing, once: the sample path's RAM code (as on the board) before anything calls it.
    unsafe { ram_code::load() };
    let mut core = cortex_m::Peripherals::take().unwrap_or_else(|| fail("core peripherals taken"));
    let Some(clock) = Clock::calibrate(&mut core.SYST) else { fail("instruction counting is not exact") };
    let vectors = Vectors::parse(VECTORS).unwrap_or_else(|_| fail("the embedded vectors file is damaged"));
    let n = vectors.len();
    if n <= BENCH {
        fail("the vectors hold too few samples for the benchmark window");
    }
    let mut w = Workload::new(&vectors.board).unwrap_or_else(|_| fail("the recorded board's settings are invalid"));

    // 1. The whole run, with the pipeline's step timed every sample (its worst case includes the payload change),
    //    snapshots at the start of the benchmark window, and the window's filtered samples kept.
    let mut pipeline_run = Stats::default();
    let mut window = [FilteredSample::<f32>::default(); BENCH];
    let mut snapshot = None;
    for k in 0..n {
        let (probe, dac) = vectors.sample(k);
        if k == n - BENCH {
            snapshot = Some(w.clone());
        }
        let (out, insns) = clock.count(|| w.pipeline.step(&w.cfg, probe));
        pipeline_run.add(insns);
        w.step_others(&out);
        if out.dac_code != dac {
            defmt::error!("sample {}: DAC code {} on QEMU, {} on the host", k, out.dac_code, dac);
            fail("the pipeline's output differs from the host's");
        }
        if k >= n - BENCH {
            window[k - (n - BENCH)] = out.estimator_input.unwrap_or_else(|| fail("a fault in the benchmark window"));
        }
    }
    let results = w.results();
    let correct = compare_results(&results, &vectors.expected);
    defmt::info!("{} samples: every DAC code equal to the host's", n);
    let start = snapshot.unwrap_or_else(|| fail("no snapshot"));

    // 2. Each kernel over the window, from the snapshot: the same updates as in the run, so each must end where the
    //    run ended (checked below), and the counts are those of converged estimators on real data.
    let mut json: Text<JSON_BYTES> = Text::new();
    let mut table = Bench { clock: &clock, json: &mut json, first: true };
    let mut bench_ok = true;

    defmt::println!("{=str}", "kernel                           instructions per update: mean      max updates");
    let mut p = start.pipeline.clone();
    table.kernel("pipeline_all_f32", |c, s| {
        for k in n - BENCH..n {
            s.add(c.count(|| p.step(&start.cfg, vectors.sample(k).0)).1);
        }
    });
    bench_ok &= p.estimators.2.params() == w.pipeline.estimators.2.params();
    let mut bare = Pipeline::new(&start.cfg, ());
    table.kernel("pipeline_bare_f32", |c, s| {
        for k in 0..BENCH {
            s.add(c.count(|| bare.step(&start.cfg, vectors.sample(k).0)).1);
        }
    });
    let (mut crls, mut cekf, mut hekf) = start.pipeline.estimators;
    table.kernel("crls_f32", |c, s| window.iter().for_each(|x| s.add(c.count(|| crls.update(x)).1)));
    table.kernel("cekf_f32", |c, s| window.iter().for_each(|x| s.add(c.count(|| cekf.update(x)).1)));
    table.kernel("hekf_f32", |c, s| window.iter().for_each(|x| s.add(c.count(|| hekf.update(x)).1)));
    // The hybrid filter at the largest substep count the tuning accepts (`tune ekf substeps 64`): what that setting
    // costs the interrupt. From its initial state, over the same window.
    let mut hekf64 = {
        use nanopos_id::estimators::{ekf::Hekf, Tuning, TuningKey};
        let mut t = Tuning::of(nanopos_id::control::TuningPreset::Prbs);
        t.set(TuningKey::EkfSubsteps, &[64.0]).unwrap_or_else(|_| fail("64 substeps refused"));
        Hekf::new(t.design::<f32>().ekf)
    };
    table.kernel("hekf_f32_64_substeps", |c, s| window.iter().for_each(|x| s.add(c.count(|| hekf64.update(x)).1)));
    let mut dense = start.hekf_dense;
    table.kernel("hekf_dense_f32", |c, s| {
        window.iter().for_each(|x| s.add(c.count(|| dense.update(x.u_f.value, x.y_f.value)).1))
    });
    let mut arx = start.arx.clone();
    table.kernel("arx_rls_f32", |c, s| window.iter().for_each(|x| s.add(c.count(|| arx.update(x)).1)));
    let fixed_in: [(Q32, Q32); BENCH] =
        core::array::from_fn(|i| (Q32::of(f64::from(window[i].u_f.value)), Q32::of(f64::from(window[i].y_f.value))));
    let mut arx_fixed = start.arx_fixed;
    table.kernel("arx_rls_fixed", |c, s| {
        fixed_in.iter().for_each(|&(u, y)| s.add(c.count(|| arx_fixed.update(&start.arx_fixed_cfg, u, y, true)).1))
    });
    bench_ok &= [crls.params(), cekf.params(), hekf.params()]
        == [w.pipeline.estimators.0.params(), w.pipeline.estimators.1.params(), w.pipeline.estimators.2.params()]
        && dense.params() == w.hekf_dense.params()
        && arx.params() == w.arx.params()
        && arx_fixed.rls().theta() == w.arx_fixed.rls().theta();

    let cfg = &start.cfg;
    let mut pre = PrefilterState::default();
    table.kernel("prefilter_f32", |c, s| {
        window.iter().for_each(|x| s.add(c.count(|| cfg.prefilter.update(&mut pre, x.u)).1))
    });
    for (name, biquad) in [
        ("reconstruction_replica_f32", &cfg.reconstruction),
        ("antialias_replica_f32", &cfg.antialias),
        ("lag_replica_f32", &cfg.lags),
    ] {
        let mut bq = BiquadState::default();
        table.kernel(name, |c, s| window.iter().for_each(|x| s.add(c.count(|| biquad.update(&mut bq, x.u)).1)));
    }
    // One of them in Q31.32, as a core without an FPU would run the pipeline's filters.
    let (fixed_biquad, mut fixed_state) = (cfg.reconstruction.cast::<Q32>(), BiquadState::default());
    let fixed_u: [Q32; BENCH] = core::array::from_fn(|i| Q32::of(f64::from(window[i].u)));
    table.kernel("biquad_fixed", |c, s| {
        fixed_u.iter().for_each(|&u| s.add(c.count(|| fixed_biquad.update(&mut fixed_state, u)).1))
    });
    let mut ex = ExcitationState::default();
    table.kernel("excitation_prbs_f32", |c, s| {
        (0..BENCH).for_each(|_| s.add(c.count(|| cfg.excitation.next(&mut ex)).1))
    });
    // The other excitations: what running one instead of the PRBS adds to the interrupt.
    let others = [
        ("excitation_triangle_f32", ExcitationDesign::PAPER_TRIANGLE),
        ("excitation_sine_f32", ExcitationDesign::sine(423.0, 1.0)),
        ("excitation_multisine_f32", ExcitationDesign::multisine(200.0, 800.0, 1.0)),
    ];
    for (name, design) in others {
        let excitation = design.design::<f32>(1.0 / cfg.sample_period_s);
        let mut ex = ExcitationState::default();
        table.kernel(name, |c, s| (0..BENCH).for_each(|_| s.add(c.count(|| excitation.next(&mut ex)).1)));
    }

    table.summary("pipeline_run_f32 (all samples)", &pipeline_run);

    // 3. The console's heaviest commands, each once from the controller's start: their designs (in f64, in
    //    software on the M4F) run in thread mode on the board, where they hold up the telemetry task, which feeds the
    //    watchdog (0.5 s), and the draining of the recording (a ring of 0.1 s). Counted across SysTick's wraps
    //    (`Clock::count_long`): on the cores without an FPU several run past its range.
    let mut ctl = Controller::new(PipelineSettings::default(), vectors.board, true)
        .unwrap_or_else(|_| fail("the controller's settings are invalid"));
    //    `excite multisine` and `tune prefilter` judge the band and the pre-filter against the interrupt's estimate: a
    //    snapshot taken beforehand, whose copy is counted here (the snapshot itself is `status_snapshot`, below).
    let prbs = nanopos_id::estimators::Tuning::preset("prbs").map_or_else(|| fail("prbs tuning"), |t| t.design());
    let snapshot = Instrument::new(start.cfg, &prbs).status();
    //    The last is refused, after the longest design there is: the ARX's zero-order hold of a matrix of norm near
    //    1e296 (about a thousand squarings).
    let mut changes: [Option<Change<f32>>; 7] = Default::default();
    for (i, (name, line, accepted)) in [
        ("console_tune_initial", "tune initial 5e5 70 6e6", true),
        ("console_tune_prefilter", "tune prefilter 100 600 0.1", true),
        ("console_tuning_triangle", "tuning triangle", true),
        ("console_excite_prbs", "excite prbs 1", true),
        ("console_limits", "limits -5 5 1000", true),
        ("console_excite_multisine", "excite multisine 1 200 800", true),
        ("console_tune_refused_longest", "tune initial 500000 1e300 6e6", false),
    ]
    .into_iter()
    .enumerate()
    {
        let cmd = parse(line.as_bytes()).unwrap_or_else(|_| fail("a console command did not parse"));
        let mut reply = TextBuf::<REPLY_BYTES>::default();
        table.kernel(name, |c, s| {
            let asks = matches!(name, "console_excite_multisine" | "console_tune_prefilter");
            let status = || if asks { snapshot } else { idle_status() };
            // Past SysTick's range on the cores without an FPU (double precision, and there f32 too, in software).
            let ((change, _), n) = c.count_long(|| ctl.execute::<f32>(cmd, status, &mut reply));
            if change.is_some() != accepted {
                defmt::error!("{=str}: {=str}", line, reply.as_str());
                fail("a console command was not answered as expected");
            }
            changes[i] = change;
            s.add(n);
        });
    }

    // 4. The firmware's interrupt body, `Instrument::sample`, over the whole run: every estimator (rls, ekf, hekf,
    //    arx) selected and recording on (drained outside the timing, as the console task does). Then, in the same
    //    loop, each change the commands above made, applied before a sample: the sample that pays for a command
    //    (`isr_body_applying_change`). The changes come 400 samples apart (those between are not counted): after a
    //    pre-filter change the estimators wait for the new filter to settle (354 samples), and a change applied then
    //    would be counted without them. A restart's sample is cheap (the EKFs take their states from it instead of
    //    stepping); the costly ones are the changes of a configuration that the estimators step through. One call
    //    site, as in the firmware's interrupt: a second one changed how the compiler inlined it, and the run's counts
    //    by 12 instructions. The last change starts the multisine, the
    //    costliest excitation, and the loop runs 900 samples more with it (`isr_body_multisine_f32`; the probe's code
    //    then stands still, and 1 000 such samples would latch a stuck probe). The interrupt's worst case is the
    //    largest of the maxima, less the lock and the cycle statistics around it.
    //    Then, with the multisine running, `tune prefilter 100 500 0.1` with every estimator restarted (a new tuning
    //    and a new pipeline configuration, as `tune stage` posts them: the costliest change to apply,
    //    `isr_body_applying_change_multisine`), and the heaviest
    //    configuration the console accepts: `tune ekf substeps 64` and `tune prefilter 100 600 0.1` on the next two
    //    samples, and `limits -5 5 1000` (the limits in force, a new pipeline configuration) 500 samples later, once
    //    the estimators step again (`isr_body_heaviest_applying`: these four samples), and `HEAVIEST` samples in all
    //    after the first three (`isr_body_heaviest_f32`; the first 266 without the estimators) on which the probe
    //    replays the run's last codes backwards: they move (a probe standing still for 1 000 samples would latch a
    //    fault), and they do not follow the command, so the EKFs' gates reject samples, the continuous filter taking
    //    its step again without the measurement (checked below): the costliest branch of a sample, with the largest
    //    substep count. The EKFs, restarted by these changes, take every sample for their first 0.5 s
    //    (`EkfHealthDesign::holdoff_s`), and their gates' level follows the misfit meanwhile: the phase runs 900
    //    samples beyond that, over which the reading is stepped by 20 000 codes, whose transient the gates reject.
    //    Their change detection may fire (logged); its reopening of a covariance sets a few entries.
    // The pre-filter's wait (266 samples), the EKFs' 0.5 s without a gate after their restart, then 900 samples.
    const HEAVIEST: usize = 266 + 5_000 + 900;
    let mut heavy: [Option<Change<f32>>; 4] = Default::default();
    let lines =
        ["tune prefilter 100 500 0.1", "tune ekf substeps 64", "tune prefilter 100 600 0.1", "limits -5 5 1000"];
    for (i, (slot, line)) in heavy.iter_mut().zip(lines).enumerate() {
        let cmd = parse(line.as_bytes()).unwrap_or_else(|_| fail("a console command did not parse"));
        let mut reply = TextBuf::<REPLY_BYTES>::default();
        *slot = ctl.execute::<f32>(cmd, || snapshot, &mut reply).0;
        // Each a change; the pre-filter's and the limits' with a new pipeline configuration.
        if slot.as_ref().is_none_or(|c| c.config.is_some() != (i != 1)) {
            defmt::error!("{=str}: {=str}", line, reply.as_str());
            fail("a console command was not answered as expected");
        }
    }
    //    The first applied as `tune stage` posts its change: a new pipeline configuration and every estimator
    //    restarted (`tune prefilter` restarts only the continuous-time RLS, whose own pre-filter it is; `tune stage`
    //    itself takes a running estimator's estimate, which this controller has not got).
    if let Some(c) = &mut heavy[0] {
        c.restart = EstimatorSet::ALL;
    }
    let mut isr = Instrument::new(start.cfg, &prbs);
    if isr.post(Change { record: Some(None), ..Change::default() }).is_err() {
        fail("the mailbox of a new instrument is full");
    }
    let mut board = VectorBoard { vectors: &vectors, k: 0, description: vectors.board, heavy: false, offset: 0 };
    let mut frame = [RawSample::default(); FRAME_SAMPLES];
    let mut pending = changes.iter_mut().filter_map(Option::take).peekable();
    // Samples left before the next of phase 1's changes.
    let mut spacing = 0;
    let [heavy @ .., late] = &mut heavy;
    let mut heavy = heavy.iter_mut().filter_map(Option::take);
    let mut late = late.take();
    let [mut applying, mut multisine, mut applying_multisine, mut heaviest_applying, mut heaviest] =
        [Stats::default(); 5];
    // What the firmware's tasks do under the lock besides the status snapshot: post a change, drain a frame.
    let [mut lock_post, mut lock_drain] = [Stats::default(); 2];
    let mut ended = None;
    // At the multisine's phase's end: the status snapshot's count, its faults, the estimators' health.
    let mut at_multisine_end = None;
    // Samples since the last change: the multisine's phase ends at 900, the heaviest configuration's `HEAVIEST` later.
    let mut after_changes = 0;
    // The changes of the last phase applied so far.
    let mut heavy_applied = 0usize;
    // How far into each sample the command is written (the `command-latency` build).
    #[cfg(feature = "command-latency")]
    let mut to_command = Stats::default();
    table.kernel("isr_body_all_f32", |c, s| {
        for k in 0.. {
            let mut changing = false;
            // A sample between two of phase 1's changes: not counted.
            let mut between = false;
            if k >= n {
                ended.get_or_insert_with(|| (isr.estimates().map(|(p, _)| p), isr.record_status().recorded));
                if after_changes == 900 && at_multisine_end.is_none() {
                    let (status, insns) = c.count(|| isr.status());
                    at_multisine_end = Some((insns, status.faults, isr.estimates().map(|(_, h)| h)));
                }
                let change = match after_changes {
                    0 if spacing > 0 => {
                        spacing -= 1;
                        between = true;
                        None
                    }
                    0 => pending.next(),
                    900 => heavy.next(),
                    1400 => late.take(),
                    _ => None,
                };
                if let Some(change) = change {
                    let mut change = Some(change);
                    let (posted, insns) = c.count(|| change.take().is_some_and(|change| isr.post(change).is_ok()));
                    lock_post.add(insns);
                    if !posted {
                        fail("the mailbox was full");
                    }
                    changing = true;
                    board.heavy = after_changes >= 900;
                    heavy_applied += usize::from(board.heavy);
                    if after_changes == 0 && pending.peek().is_some() {
                        spacing = 400;
                    }
                } else if between {
                } else if after_changes == 900 + HEAVIEST {
                    break;
                } else {
                    after_changes += 1;
                }
            }
            // Between phase 1's changes the probe's code moves by the run's last two (standing still for 1 000
            // samples, with the excitation on, would latch a stuck probe).
            // The last 900 of the heaviest phase with the reading stepped by 20 000 codes (30.5 um, within the
            // probe's range): the EKFs' gates, whose level the samples before set, reject its transient (40 samples;
            // 13 for a step of 3 000 codes, none without a step).
            // (The phase runs from 900 to 900 + `HEAVIEST` samples after the changes.)
            board.offset = if after_changes >= HEAVIEST { 20_000 } else { 0 };
            board.k = if board.heavy {
                n - 1 - (after_changes - 900)
            } else if between {
                n - 1 - (spacing & 1)
            } else {
                k.min(n - 1)
            };
            #[cfg(not(feature = "command-latency"))]
            let insns = c.count(|| isr.sample(&mut board)).1;
            #[cfg(feature = "command-latency")]
            let insns = {
                let (_, to, all) = c.count_to_command(|| isr.sample(&mut board));
                to_command.add(to);
                all
            };
            match (k < n, changing, heavy_applied) {
                _ if between => {}
                (true, _, _) => s.add(insns),
                (false, true, 0) => applying.add(insns),
                (false, false, 0) => multisine.add(insns),
                (false, true, 1) => applying_multisine.add(insns),
                (false, true, _) => heaviest_applying.add(insns),
                (false, false, _) => heaviest.add(insns),
            }
            if isr.record_status().buffered >= FRAME_SAMPLES {
                lock_drain.add(c.count(|| isr.drain_recorded(&mut frame)).1);
            }
        }
    });
    table.kernel("isr_body_applying_change", |_, s| *s = applying);
    table.kernel("isr_body_multisine_f32", |_, s| *s = multisine);
    table.kernel("isr_body_applying_change_multisine", |_, s| *s = applying_multisine);
    table.kernel("isr_body_heaviest_applying", |_, s| *s = heaviest_applying);
    table.kernel("isr_body_heaviest_f32", |_, s| *s = heaviest);
    #[cfg(feature = "command-latency")]
    table.kernel("isr_to_command_write", |_, s| *s = to_command);
    let Some((snapshot_insns, faults, before)) = at_multisine_end else { fail("the multisine's phase did not end") };
    if !faults.is_empty() || !isr.status().faults.is_empty() {
        fail("the samples after the run latched a fault: their counts are not the configurations'");
    }
    // The heaviest phase took the costliest branch: the continuous EKF (index 1) rejected samples, each its step
    // taken twice.
    let after = isr.estimates().map(|(_, h)| h);
    let grew = |i: usize, count: fn(&Health) -> u32| count(&after[i]).saturating_sub(count(&before[i]));
    let (rejected, changes) =
        (grew(1, |h| h.rejected_samples), [grew(1, |h| h.changes_detected), grew(2, |h| h.changes_detected)]);
    defmt::info!(
        "heaviest phase: the continuous EKF rejected {} samples; changes detected: ekf {}, hekf {}",
        rejected,
        changes[0],
        changes[1]
    );
    if rejected == 0 {
        fail("the heaviest phase took no rejected step of the continuous EKF: its count misses that branch");
    }
    // The snapshot the telemetry (10 Hz) and `status` take under the lock, with the interrupt held off meanwhile:
    // after the multisine's samples.
    table.kernel("status_snapshot", |_, s| s.add(snapshot_insns));
    table.kernel("lock_post_change", |_, s| *s = lock_post);
    table.kernel("lock_drain_frame", |_, s| *s = lock_drain);
    let expected = [
        w.pipeline.estimators.0.params(),
        w.pipeline.estimators.1.params(),
        w.pipeline.estimators.2.params(),
        w.arx.params(),
    ];
    bench_ok &= ended == Some((expected, n as u64));

    table.json_put(format_args!("\n}}\n"));
    // The `command-latency` build's counts carry its mark in the sample path: a file of their own, whose reader
    // takes `isr_to_command_write` from it.
    #[cfg(not(any(feature = "command-latency", cortex_m3, cortex_m0)))]
    let path = c"target/qemu-bench.json";
    #[cfg(all(feature = "command-latency", not(any(cortex_m3, cortex_m0))))]
    let path = c"target/qemu-command-latency.json";
    // The same core without an FPU (`f32` in software): what the fixed-point kernels are for.
    #[cfg(cortex_m3)]
    let path = c"target/qemu-bench-cortex-m3.json";
    #[cfg(cortex_m0)]
    let path = c"target/qemu-bench-cortex-m0.json";
    if semihosting::fs::write(path, json.as_str().as_bytes()).is_err() {
        fail("could not write the counts' JSON on the host");
    }
    defmt::info!("wrote {=str}", path.to_str().unwrap_or("the counts' JSON"));
    // The telemetry's fault word, as the firmware's defmt encoding and `defmt-print` show it (tests/qemu.rs).
    defmt::info!(
        "faults as logged: none={} one={} all={}",
        Faults::default(),
        Faults::PROBE_STUCK,
        Faults(Faults::PROBE_OVER_RANGE.0 | Faults::PROBE_STUCK.0 | Faults::COMMAND_NOT_FINITE.0)
    );

    if !bench_ok {
        fail("a benchmark replay did not end where the run ended");
    }
    if !correct {
        fail("results differ from the host's");
    }
    defmt::info!("PASS");
    semihosting::process::exit(0)
}

/// No status: the counted commands but `excite multisine` and `tune prefilter` do not ask for it.
fn idle_status() -> Status<f32> {
    fail("a counted command asked for the status")
}

/// The recorded run as a board: the probe code of sample `k`; the amplifier's codes are checked elsewhere.
struct VectorBoard<'a> {
    vectors: &'a Vectors<'a>,
    k: usize,
    description: BoardDescription,
    /// In the last phase (the probe's codes replayed backwards once its changes are applied).
    heavy: bool,
    /// Added to the probe's code: a step in the reading, late in the last phase.
    offset: u32,
}

impl StageBoard for VectorBoard<'_> {
    fn sample_rate_hz(&self) -> f64 {
        10_000.0
    }
    fn description(&self) -> BoardDescription {
        self.description
    }
    fn read_probe(&mut self) -> u32 {
        self.vectors.sample(self.k).0 + self.offset
    }
    fn write_amplifier(&mut self, _code: u32) {
        #[cfg(feature = "command-latency")]
        COMMAND_MARK.store(systick_now(), core::sync::atomic::Ordering::Relaxed);
    }
    fn sample_faults(&mut self) -> BoardFaults {
        // Read at run time, as the G474's registers are: the interrupt's count includes the code that takes a fault
        // (a deadline missed holds the command in effect), which a constant would let the compiler remove.
        // SAFETY: volatile reads of a static, valid and aligned.
        let [deadline_missed, adc_overrun] = unsafe { core::ptr::read_volatile(&NO_BOARD_FAULTS) };
        BoardFaults { deadline_missed, adc_overrun }
    }
}

/// The board faults [`VectorBoard`] reports: none, but not known to the compiler.
static NO_BOARD_FAULTS: [bool; 2] = [false, false];

/// The table on the log and the JSON file.
struct Bench<'a> {
    clock: &'a Clock,
    json: &'a mut Text<JSON_BYTES>,
    first: bool,
}

impl Bench<'_> {
    fn kernel(&mut self, name: &str, run: impl FnOnce(&Clock, &mut Stats)) {
        let mut s = Stats::default();
        run(self.clock, &mut s);
        self.json_put(format_args!(
            "{}\n  \"{}\": {{\"instructions_per_update\": {}, \"max\": {}, \"updates\": {}}}",
            if self.first { "{" } else { "," },
            name,
            s.mean(),
            s.max,
            s.updates
        ));
        self.first = false;
        self.summary(name, &s);
    }

    /// Append to the JSON; a run whose JSON outgrows [`JSON_BYTES`] stops (it was once cut short silently).
    fn json_put(&mut self, text: core::fmt::Arguments) {
        if self.json.write_fmt(text).is_err() {
            fail("the counts' JSON outgrew its buffer (JSON_BYTES)");
        }
    }

    fn summary(&self, name: &str, s: &Stats) {
        let mut line: Text<96> = Text::new();
        let _ = write!(line, "{:<32} {:>30} {:>8} {:>7}", name, s.mean(), s.max, s.updates);
        defmt::println!("{=str}", line.as_str());
    }
}

#[exception]
unsafe fn HardFault(_frame: &ExceptionFrame) -> ! {
    fail("HardFault")
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    let mut msg: Text<256> = Text::new();
    let _ = write!(msg, "{info}");
    fail(msg.as_str())
}
