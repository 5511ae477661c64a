//! The firmware's glue: start-up, the sample interrupt, the console, telemetry and the watchdog.
//!
//! Three contexts:
//! - **`ADC1_2`**, the highest priority: one [`Instrument::sample`] per conversion (the pipeline, every selected
//!   estimator, a waiting configuration change applied first, the recording ring).
//! - **`console`** task (thread mode): reads command lines from LPUART1, designs each change with the
//!   [`Controller`], posts it, waits for the interrupt to apply it, replies; streams the recording.
//! - **`telemetry`** task (thread mode): every 100 ms, logs over defmt/RTT and feeds the watchdog if the sample
//!   clock ran.
//!
//! Thread mode touches the interrupt's state only under the lock, for copies (a posted change, 1 760 instructions on
//! QEMU with its kilobyte, the longest; a frame of recorded samples, 276) and the status snapshot (1 713), and takes
//! it only when the next sample's conversion ends later than such a hold ([`with_task`]): the sample interrupt starts
//! on time (taken at any moment, the lock could delay it by about 2 000 cycles: its command, written first, would
//! still make its deadline, but the heaviest configuration's whole interrupt, about 12 600 cycles, would end near
//! the next conversion, 17 000 cycles after its own). The sample instants never move (hardware-timed).
//! The defmt logger takes no lock (defmt-rtt's `drop-on-contention`, `Cargo.toml`).

use crate::board::{self, G474Board, ResetCause, CONSOLE_RX_BYTES};
use core::cell::RefCell;
use core::sync::atomic::{AtomicU16, Ordering};
use cortex_m::interrupt::Mutex;
use cortex_m::peripheral::DWT;
use defmt_rtt as _;
use embassy_executor::Spawner;
use embassy_stm32::interrupt::{InterruptExt, Priority};
use embassy_stm32::pac::interrupt;
use embassy_stm32::peripherals::IWDG;
use embassy_stm32::usart::BufferedUart;
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_time::{Duration, Ticker, Timer};
use embedded_io_async::{BufRead, Write};
use nanopos_id::console::{write_record_end, Controller, Rest, REPLY_BYTES};
use nanopos_id::control::{LineBuffer, ESTIMATOR_NAMES};
use nanopos_id::estimator::Health;
use nanopos_id::instrument::{Change, EventWatch, Instrument, Status, WatchdogGate};
use nanopos_id::pipeline::{FaultCounters, Faults};
use nanopos_id::record::{encode_frame, RawSample, FRAME_MAX_BYTES, FRAME_SAMPLES};
use nanopos_id::text::TextBuf;
use nanopos_id::StageParams;

/// What the interrupt owns.
struct SampleTask {
    board: G474Board,
    instrument: Instrument<f32>,
    stats: SampleStats,
    /// The most cycles of a sample since start-up (`status`'s `isr_cycles_max`).
    max_cycles: u32,
}

/// Interrupt statistics over one telemetry window.
#[derive(Clone, Copy, Default)]
struct SampleStats {
    window_samples: u32,
    /// At most 17 000 a sample, and the watchdog resets the board if nobody starts a new window for 0.5 s (5 000
    /// samples): no overflow before 250 000.
    window_cycles: u32,
    window_max_cycles: u32,
    y_um: f32,
}

/// The interrupt's state lives in a zero-initialised static (`singleton!`), so its 11 KiB cost RAM only; `TASK`
/// holds a reference to it once installed.
static TASK: Mutex<RefCell<Option<&'static mut SampleTask>>> = Mutex::new(RefCell::new(None));

/// The DAC code the fault handler writes: the safe value of the configuration in use.
static SAFE_CODE: AtomicU16 = AtomicU16::new(2048);

/// The longest the tasks hold the lock: a change posted (1 760 instructions on QEMU, `lock_post_change`: a 1 KiB
/// copy, by `memcpy` from the flash, loads and stores of 2 cycles) or the status snapshot (1 713, `status_snapshot`),
/// with room for their extra cycles. With the interrupt's slack either side, 4 512 cycles between the end of one
/// sample's interrupt and the next conversion: the heaviest configuration leaves about 6 000 on a usual sample.
const LOCK_HOLD_CYCLES: u32 = 4_000;

/// Run `f` on the interrupt's state under the lock (`None` before it is installed), when holding the interrupts off
/// for [`LOCK_HOLD_CYCLES`] delays no sample ([`mask_clear_of_sample`]).
fn with_task<R>(f: impl FnOnce(&mut SampleTask) -> R) -> Option<R> {
    let was_active = mask_clear_of_sample();
    // SAFETY: the interrupts are masked from `mask_clear_of_sample` until they are unmasked below.
    let cs = unsafe { cortex_m::interrupt::CriticalSection::new() };
    let out = TASK.borrow(&cs).borrow_mut().as_deref_mut().map(f);
    if was_active {
        // SAFETY: they were on before `mask_clear_of_sample`; `f` is done with the lock.
        unsafe { cortex_m::interrupt::enable() };
    }
    out
}

/// Mask the interrupts at a moment when holding them off for [`LOCK_HOLD_CYCLES`] delays no sample
/// ([`board::clear_of_sample`]); returns whether they were on before. While the next sample is due sooner, or its
/// interrupt is pending, it waits for that interrupt to run (spinning with them on: at most the hold and its slack,
/// about 25 us, and the interrupt). Past two sample periods of waiting (the sample clock stopped, or an interrupt
/// that leaves no such window) it masks them anyway. One function for every taking of the lock, never inlined:
/// `tests/firmware.rs` checks it.
#[inline(never)]
fn mask_clear_of_sample() -> bool {
    let start = DWT::cycle_count();
    loop {
        let was_active = cortex_m::register::primask::read().is_active();
        cortex_m::interrupt::disable();
        if DWT::cycle_count().wrapping_sub(start) >= 2 * board::TICKS_PER_SAMPLE
            || board::clear_of_sample(LOCK_HOLD_CYCLES)
        {
            return was_active;
        }
        if was_active {
            // SAFETY: they were on on entry to this iteration; nothing was done with them off.
            unsafe { cortex_m::interrupt::enable() };
        }
    }
}

#[embassy_executor::main]
async fn main(spawner: Spawner) {
    // The output safe first, on the reset clock, from the settings alone (their design takes milliseconds).
    let early_safe = board::settings().safe_code::<f32>(&board::DESCRIPTION) as u16;
    board::early_safe_output(early_safe);
    SAFE_CODE.store(early_safe, Ordering::Relaxed);
    // SAFETY: once, before anything in `.ramtext` has run (its interrupt is enabled further down).
    unsafe { crate::ram_code::load() };
    let crystal = board::crystal_starts();
    let p = embassy_stm32::init(board::clocks(crystal));
    if crystal {
        board::watch_crystal();
    }
    // The embassy time driver (TIM15) and the console's UART must not delay the sample interrupt.
    embassy_stm32::interrupt::TIM1_BRK_TIM15.set_priority(Priority::P1);
    embassy_stm32::interrupt::LPUART1.set_priority(Priority::P2);
    let cause = board::reset_cause();

    let mut core = cortex_m::Peripherals::take().expect("core peripherals taken once");
    core.DCB.enable_trace();
    core.DWT.enable_cycle_counter();

    // After a watchdog reset (a hang, a panic, a fault) the stage stays still until someone sends `start`.
    let running = cause != ResetCause::Watchdog;
    let controller = match Controller::new(board::settings(), board::DESCRIPTION, running) {
        Ok(c) => c,
        Err(e) => defmt::panic!("pipeline settings: {}", e),
    };
    let config = controller.config::<f32>();
    let safe = config.safe_code() as u16;
    SAFE_CODE.store(safe, Ordering::Relaxed);
    let parts = board::init(p, safe);
    let task = cortex_m::singleton!(: SampleTask = SampleTask {
        board: G474Board::default(),
        instrument: Instrument::new(config, &controller.tuning()),
        stats: SampleStats::default(),
        max_cycles: 0,
    })
    .expect("the interrupt's state is made once");
    cortex_m::interrupt::free(|cs| {
        TASK.borrow(cs).replace(Some(task));
    });
    embassy_stm32::interrupt::ADC1_2.set_priority(Priority::P0);
    // SAFETY: the handler below only touches state behind `TASK`, installed just above.
    unsafe { embassy_stm32::interrupt::ADC1_2.enable() };
    board::start_sample_clock();
    if cause == ResetCause::Watchdog {
        defmt::warn!("nanopos-fw: reset by the watchdog (a hang or a fault): excitation stopped, send `start`");
    }
    if crystal {
        defmt::info!("nanopos-fw: sample clock from the 24 MHz crystal (HSE)");
    } else {
        defmt::warn!(
            "nanopos-fw: the 24 MHz crystal (HSE) did not start: the sample clock runs from the HSI16 RC oscillator, \
             about 1 % off and drifting with temperature, and every estimate with it (f0 by as much, a0 twice, a1 and \
             b0 more)"
        );
    }
    defmt::info!(
        "nanopos-fw: sampling at {=u32} Hz, {=str}, probe {=u8}-bit (codes 0 to {=u32}), DAC {=u8}-bit, command \
         deadline {=u32} cycles after each conversion, reset cause {}, console LPUART1 {=u32} baud (`help` lists its \
         commands)",
        board::SAMPLE_RATE_HZ,
        if running { "PRBS 1 V running" } else { "excitation stopped" },
        board::DESCRIPTION.probe.bits,
        board::DESCRIPTION.probe.max_code,
        board::DESCRIPTION.amplifier.bits,
        board::DEADLINE_CYCLES,
        cause,
        board::CONSOLE_BAUD
    );
    spawner.spawn(telemetry(parts.watchdog).expect("telemetry task spawns once"));
    spawner.spawn(console(parts.console, controller).expect("console task spawns once"));
}

/// Runs from CCM SRAM ([`crate::ram_code`]), loaded at start-up before this interrupt is enabled.
#[interrupt]
#[link_section = ".ramtext.adc1_2"]
fn ADC1_2() {
    let start = DWT::cycle_count();
    let late = board::cycles_since_conversion();
    cortex_m::interrupt::free(|cs| {
        let mut task = TASK.borrow(cs).borrow_mut();
        let Some(t) = task.as_deref_mut() else {
            // Not started: acknowledge the conversion and leave the output where it is (safe).
            G474Board::discard_conversion();
            return;
        };
        // A controller on the estimates goes here: `t.instrument.sample_adding(&mut t.board, |y_um| command_v)`
        // adds its command to the excitation (README, "A controller on the estimates").
        t.board.entered(late);
        let out = t.instrument.sample(&mut t.board);
        // From the conversion's end, which is what the next conversion bounds: the interrupt's own cycles and how
        // late it started.
        let cycles = DWT::cycle_count().wrapping_sub(start).wrapping_add(late);
        let s = &mut t.stats;
        s.window_samples += 1;
        s.window_cycles = s.window_cycles.saturating_add(cycles);
        s.window_max_cycles = s.window_max_cycles.max(cycles);
        t.max_cycles = t.max_cycles.max(cycles);
        s.y_um = out.y_um;
    });
}

/// The console: command lines in, replies and the recording stream out.
#[embassy_executor::task]
async fn console(uart: BufferedUart<'static>, mut ctl: Controller) {
    let (mut tx, mut rx) = uart.split();
    let mut line = LineBuffer::default();
    let mut reply = TextBuf::<REPLY_BYTES>::default();
    let mut bytes = [0u8; CONSOLE_RX_BYTES];
    let mut stream = RecordStream { frame: [0u8; FRAME_MAX_BYTES], samples: [RawSample::default(); FRAME_SAMPLES] };
    loop {
        // Commands: whatever arrived, or nothing within 2 ms (the recording needs draining every 4.8 ms). All of the
        // receive buffer is taken at once, with the receive errors noted so far, under the lock (a copy of at most
        // 128 bytes): the lines those errors or a full buffer may have damaged are refused (`LineBuffer::read`).
        let arrived = embassy_futures::select::select(rx.fill_buf(), Timer::after_millis(2)).await;
        let (n, error) = match arrived {
            embassy_futures::select::Either::First(_) => cortex_m::interrupt::free(|_| {
                let n = embedded_io::Read::read(&mut rx, &mut bytes);
                (n.unwrap_or(0), board::take_console_rx_error() || n.is_err())
            }),
            embassy_futures::select::Either::Second(()) => (0, board::take_console_rx_error()),
        };
        if error {
            defmt::warn!(
                "console: receive error (bytes lost or changed on the link; the lines they touch are refused)"
            );
        }
        for parsed in line.read(&bytes[..n], error, CONSOLE_RX_BYTES) {
            // A recording that stopped (`record off` earlier in this batch, a burst's end, an overflow) ends before
            // the line: its last frames and end line go out first, and a `record on` starts a new one.
            if ctl.recording_open() && with_task(|t| !t.instrument.record_status().active).unwrap_or(false) {
                stream.send(&mut tx, &mut ctl, &mut reply).await;
            }
            reply.clear();
            let (mut change, mut rest) = match parsed {
                Ok(cmd) => ctl.execute(cmd, board_status, &mut reply),
                Err(e) => {
                    ctl.refuse(e, &mut reply);
                    (None, Rest::none())
                }
            };
            // The change stays in `change` (one copy in this future: a binding or a temporary of it across the
            // await would be another kilobyte of static RAM).
            if let Some(c) = &change {
                if let Some(cfg) = &c.config {
                    SAFE_CODE.store(cfg.safe_code() as u16, Ordering::Relaxed);
                }
                post(&mut change).await;
            }
            // The reply in parts (`status` a line at a time), each sent before the next is written.
            loop {
                if tx.write_all(reply.as_bytes()).await.is_err() {
                    defmt::warn!("console: transmit error");
                }
                reply.clear();
                if !rest.write_next(&ctl, &mut reply) {
                    break;
                }
            }
            // The recording's tuning lines, after the reply's verdict and before the frames that follow, with the
            // sample the change applied to.
            if ctl.take_tuning_due() {
                let at = with_task(|t| t.instrument.changed_at()).unwrap_or(0);
                for k in 0.. {
                    reply.clear();
                    if !ctl.write_tuning_line(k, at, &mut reply) {
                        break;
                    }
                    let _ = tx.write_all(reply.as_bytes()).await;
                }
            }
        }
        stream.send(&mut tx, &mut ctl, &mut reply).await;
    }
}

/// The recording's side of the console: its buffers (whether a recording's end line is still to go out is the
/// controller's: [`Controller::recording_open`]).
struct RecordStream {
    frame: [u8; FRAME_MAX_BYTES],
    samples: [RawSample; FRAME_SAMPLES],
}

impl RecordStream {
    /// Send what the recording has: whole frames while it runs; the rest, and the end line (which `ctl` learns of),
    /// once it stopped. The end line is written through `reply`.
    async fn send(&mut self, tx: &mut impl Write, ctl: &mut Controller, reply: &mut TextBuf<REPLY_BYTES>) {
        while ctl.recording_open() {
            let samples = &mut self.samples;
            let Some((first, n, status)) = with_task(|t| {
                let st = t.instrument.record_status();
                if st.active && st.buffered < FRAME_SAMPLES {
                    return (0, 0, st);
                }
                let (first, n) = t.instrument.drain_recorded(samples);
                (first, n, t.instrument.record_status())
            }) else {
                break;
            };
            if n > 0 {
                let len = encode_frame(first, &self.samples[..n], &mut self.frame);
                let _ = tx.write_all(&self.frame[..len]).await;
            }
            if !status.active && status.buffered == 0 {
                reply.clear();
                let _ = write_record_end(&status, reply);
                let _ = tx.write_all(reply.as_bytes()).await;
                ctl.record_ended();
            }
            if n == 0 {
                break;
            }
        }
    }
}

/// The interrupt's status snapshot with its most cycles since start-up. Not inlined: as a closure inlined into
/// `Controller::execute` it took 1 640 B more flash.
#[inline(never)]
fn board_status() -> Status<f32> {
    with_task(|t| Status { isr_cycles_max: t.max_cycles, ..t.instrument.status() }).unwrap_or_else(idle_status)
}

/// Before the interrupt's state is installed (never, once the console runs).
fn idle_status() -> Status<f32> {
    Status {
        samples: 0,
        faults: Faults::default(),
        counters: FaultCounters::default(),
        command_v: 0.0,
        excitation_level: Default::default(),
        selected: Default::default(),
        estimates: [(StageParams::INITIAL.cast(), Health::new()); 4],
        record: Default::default(),
        isr_cycles_max: 0,
    }
}

/// Hand `change` to the interrupt and wait until a sample applied it. By reference: the kilobyte stays where the
/// console's future holds it (by value, this future held a second copy: 1 KiB more of static RAM).
async fn post(change: &mut Option<Change<f32>>) {
    while let Some(c) = change.take() {
        // The refused change comes back whole, to be posted again.
        #[allow(clippy::result_large_err)]
        match with_task(|t| t.instrument.post(c)) {
            Some(Ok(())) => break,
            Some(Err(busy)) => *change = Some(busy.0),
            None => return,
        }
        Timer::after_micros(100).await;
    }
    while with_task(|t| t.instrument.change_pending()).unwrap_or(false) {
        Timer::after_micros(100).await;
    }
}

/// 10 Hz: interrupt cost, deadlines, faults, the last sample; then one line per estimator: the model
/// `y'' = -a0 y - a1 y' + b0 u` (a0 in 1/s^2, a1 in 1/s, b0 in um/(s^2 V)) and what it means: natural frequency,
/// damping ratio, static gain (um/V), with the estimator's health. Feeds the watchdog while samples are counted.
#[embassy_executor::task]
async fn telemetry(mut watchdog: IndependentWatchdog<'static, IWDG>) {
    // Asked every 100 ms, when 1000 samples should have run: fed if at least half did.
    let mut gate = WatchdogGate::new(500);
    watchdog.unleash();
    let mut ticker = Ticker::every(Duration::from_millis(100));
    let mut watch = EventWatch::new(board::SAMPLE_RATE_HZ as f32);
    loop {
        ticker.next().await;
        let Some((s, st)) = with_task(|t| {
            let snapshot = (t.stats, t.instrument.status());
            t.stats = SampleStats::default();
            snapshot
        }) else {
            continue;
        };
        if gate.may_feed(st.samples) {
            watchdog.pet();
        }
        let mean = s.window_cycles.checked_div(s.window_samples).unwrap_or(0);
        let c = &st.counters;
        defmt::info!(
            "samples={=u64} isr_cycles mean={=u32} max={=u32} of {=u32} a sample, from the conversion | y={=f32} um u={=f32} V | pe_power={=f32} V^2 pe_single={=bool} | faults={} over_range={=u32} stuck={=u32} spikes={=u32} not_finite={=u32}",
            st.samples,
            mean,
            s.window_max_cycles,
            board::TICKS_PER_SAMPLE,
            s.y_um,
            st.command_v,
            st.excitation_level.power,
            st.excitation_level.single,
            st.faults,
            c.probe_over_range,
            c.probe_stuck,
            c.spikes,
            c.command_not_finite
        );
        for (i, (p, h)) in st.estimates.iter().enumerate() {
            if !st.selected.contains(i) {
                continue;
            }
            defmt::info!(
                "{=str}: a0={=f32} a1={=f32} b0={=f32} | f0={=f32} Hz zeta={=f32} gain={=f32} um/V | {=str} rejected={=u32} changes={=u32} resets={=u32} repairs={=u32} innovation_rms={=f32} um",
                ESTIMATOR_NAMES[i],
                p.a0,
                p.a1,
                p.b0,
                p.f0_hz(),
                p.damping_ratio(),
                p.dc_gain(),
                h.state(),
                h.rejected_samples,
                h.changes_detected,
                h.numeric_resets,
                h.covariance_repairs,
                h.innovation_rms_um
            );
        }
        let news = watch.look(&st);
        for (i, &resets) in news.resets.iter().enumerate() {
            if resets > 0 {
                defmt::warn!(
                    "{=str}: numeric resets in the last 0.1 s: {=u32} (non-finite values, each time back to the initial parameters): the tuning does not suit this stage or input",
                    ESTIMATOR_NAMES[i],
                    resets
                );
            }
        }
        if news.spikes > 0 {
            defmt::warn!(
                "spike gate: probe readings replaced in the last 0.1 s: {=u32} (spikes={=u32}), each out of line with the readings before it by far more than the stage moves in a sample: glitches at the ADC's input, which the estimators did not see; many mean a noisy or loose connection",
                news.spikes,
                c.spikes
            );
        }
        if news.deadline_misses > 0 || news.adc_overruns > 0 {
            defmt::warn!("deadline misses={=u32} adc overruns={=u32}", c.deadline_misses, c.adc_overruns);
        }
        if news.limiting {
            defmt::warn!(
                "commands the output limits changed in the last 0.1 s: {=u32}, and some in the 0.1 s before (limited={=u32}): the excitation is clipped or slew-limited, a distorted input that can bias the estimates by a few %",
                news.limited,
                c.limited
            );
        }
        if let Some(f) = news.fast_resonance {
            defmt::warn!(
                "the resonance, {=f64} Hz ({=str}'s estimate), is at w T = {=f64} of the sample rate: there the continuous EKF (ekf) leaves a1 low (-5 % at w T 0.63); the hybrid EKF (hekf) keeps it within 1 %",
                f.f0_hz,
                ESTIMATOR_NAMES[f.estimator],
                f.wt
            );
        }
        if let Some(r) = news.weak_response {
            defmt::warn!(
                "{=str}'s model explains little of the measurement for 2 s (its response ratio {=f64}, under {=f64}): is the probe connected and seeing the stage, and the excitation large enough? (see `status`)",
                ESTIMATOR_NAMES[r.ekf],
                r.ratio,
                nanopos_id::instrument::TRUSTED_RESPONSE_RATIO
            );
        }
        if let Some(d) = news.disagreement {
            defmt::warn!(
                "{=str} disagree with {=str} on the resonance or the gain's sign for 2 s: the EKFs are local and may have settled on a wrong solution, or the {=str} has not converged yet (see `status`)",
                d.ekf_names(),
                d.reference_name(),
                d.reference_name()
            );
        }
    }
}

/// The crystal failed while running (the clock security system, [`board::watch_crystal`]): the system clock is now
/// HSI16 without the PLL, the sample clock about 10 times slower, and nothing the estimators compute means anything.
/// As on a fault: the amplifier goes to its safe value (the timer, on HSI16 now, loads it within its own period,
/// about 1 ms) and the board waits for the watchdog; after the reset the crystal does not start, and the firmware
/// runs from HSI16 and says so.
#[cortex_m_rt::exception]
unsafe fn NonMaskableInt() -> ! {
    board::force_safe_output(SAFE_CODE.load(Ordering::Relaxed));
    board::clear_crystal_failure();
    loop {
        cortex_m::asm::wfi();
    }
}

/// A panic: interrupts off (the sample interrupt writes no further code), the amplifier to its safe value (the
/// sample timer, running in hardware, loads it within one sample period), then the message to the log, then a
/// HardFault. In that order because the fault may never be handled here: `probe-rs run` catches HardFaults by
/// default, halting the core at the vector to print a backtrace, before [`HardFault`] could put the output safe
/// (panic-probe, which this replaces, logged and faulted, and left the output to the fault handler). The log is
/// never waited for (defmt-rtt's `disable-blocking-mode`). Nothing feeds the watchdog any more: 0.5 s later the
/// board resets, and comes back with the excitation stopped.
#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    fail(Some(info))
}

/// `defmt::panic!`, and defmt's `unwrap!` and `expect!` (embassy's own checks use them), which have logged their
/// message already: as [`panic`], without a second message ("explicit panic", defmt's default handing on to
/// `core::panic!`).
#[defmt::panic_handler]
fn defmt_panic() -> ! {
    fail(None)
}

/// Interrupts off, the output safe, `info` logged (once: a panic while logging one, the logger taken by the code
/// that panicked, goes straight on), the HardFault.
#[inline(always)]
fn fail(info: Option<&core::panic::PanicInfo>) -> ! {
    cortex_m::interrupt::disable();
    board::force_safe_output(SAFE_CODE.load(Ordering::Relaxed));
    if let Some(info) = info.filter(|_| board::first_panic()) {
        defmt::error!("{}", defmt::Display2Format(info));
    }
    board::hard_fault()
}

/// Any fault (a panic ends here too, unless a debugger catches the fault first): the amplifier goes to its safe
/// value; the sample timer keeps running in hardware and loads it within one sample period. Nothing feeds the
/// watchdog any more, so 0.5 s later the board resets, and comes back with the excitation stopped.
#[cortex_m_rt::exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    board::force_safe_output(SAFE_CODE.load(Ordering::Relaxed));
    loop {
        cortex_m::asm::wfi();
    }
}
