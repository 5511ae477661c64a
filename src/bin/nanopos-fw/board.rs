//! Everything specific to the NUCLEO-G474RE, in one place: clocks, pins, the sample clock, the probe ADC, the
//! amplifier DAC, and the safe output. Moving to another STM32 with an ADC and a DAC means rewriting this file.
//!
//! ## Wiring
//! | Signal | Pin | Nucleo header | Goes to |
//! |---|---|---|---|
//! | probe in (ADC1_IN1) | PA0 | A0 (CN8 pin 1) | anti-aliasing filter output, through the +-10 V -> 0-3.3 V divider |
//! | amplifier out (DAC1_OUT1) | PA4 | A2 (CN8 pin 3) | reconstruction filter input, then 0-3.3 V -> +-10 V level shift |
//! | ground | GND | CN8 | analog ground of filters and instruments |
//!
//! The DAC's output buffer is on (it drives the filter), and a buffered STM32 DAC is specified from 0.2 V to its
//! reference less 0.2 V, not rail to rail ([`DESCRIPTION`]`.amplifier_swing_v`): through the 0-3.3 V -> +-10 V
//! level shift the output reaches -8.78 to 8.78 V, and the pipeline keeps it there. For the whole +-10 V, build the
//! level shift for 0.2-3.1 V and set `dac_v_per_command_v` to 2.9 / 20 in [`settings`].
//!
//! | console TX (LPUART1_TX) | PA2 | ST-LINK virtual COM port (USB) | host terminal, 921 600 baud 8N1 |
//! | console RX (LPUART1_RX) | PA3 | ST-LINK virtual COM port (USB) | host terminal |
//!
//! ## Console and watchdog
//! LPUART1 is wired to the ST-LINK's virtual COM port on the Nucleo (solder bridges SB12/SB13 closed as shipped):
//! the run-time commands and the recording stream use it at 921 600 baud, which continuous recording needs (575
//! kbit/s). The UART's 8-byte FIFOs carry it through the sample interrupt (about 35 us, up to about 50 us on the
//! sample that applies a command's change, and with `tune ekf substeps 64`, the heaviest configuration, whose 75 us
//! came near the limit until its substeps were squared: under the 87 us a FIFO lasts at this rate, and a byte lost
//! is a receive error, whose line is refused). A status snapshot (about 10 us with the interrupts off) is not added to it: the tasks take the lock
//! only where it ends before the next sample ([`clear_of_sample`]), and after a sample the UART's interrupt runs
//! before them. The independent watchdog (IWDG, LSI 32 kHz) resets the board 0.5 s after its last feed.
//!
//! ## Clocks
//! HSE 24 MHz (the Nucleo's crystal X3) / 6 * 85 / 2 = 170 MHz SYSCLK (PLL R, range-1 boost), APB1/APB2 at
//! 170 MHz, so TIM2 counts at 170 MHz. ADC12 kernel clock = SYSCLK; embassy's ADC driver divides it by 4 to
//! 42.5 MHz (limit 60 MHz).
//!
//! The sample period is the time base of every estimate: the firmware takes it for exactly 100 us, and a clock off by a
//! fraction `e` sets every frequency the estimators give off by `e` and `a0` by `2 e` (the stage seen on a stretched
//! time axis), `a1` and `b0` by more (on the simulated board at 0.5 %: 1.4 `e` and 2.3 `e`). A crystal is within about
//! 50 ppm. The HSI16 RC oscillator, which clocked the firmware before, is factory-trimmed only to about 1 % and drifts
//! by about as much again with temperature (STM32 datasheets, "HSI16 oscillator characteristics"): `a0` a few % off,
//! against the 0.1 % the estimators reach. If the crystal does not start within 50 ms ([`crystal_starts`]: not fitted,
//! or its solder bridges changed) the firmware still runs, from HSI16 / 4 * 85 / 2 (the same 170 MHz), and says so in
//! the log. A crystal that fails while running is caught by the clock security system ([`watch_crystal`]).
//!
//! ## Sample clock (10 kHz), all in hardware
//! TIM2 counts 0..16 999 (170 MHz / 17 000 = 10 kHz).
//! - Its update event (TRGO, `t_k`) loads DAC1 channel 1 from its holding register: the code written during sample
//!   `k-1` appears exactly at `t_k`, with no interrupt jitter (`actuation_delay_samples = 1`).
//! - Its channel 2 (PWM mode 2, rising at CCR2) triggers ADC1 half an oversampling window before `t_k`, so the
//!   window is centred on `t_k`: 64 conversions of 6.5 + 12.5 ADC cycles = 28.6 us at 42.5 MHz, accumulated and shifted
//!   right by 2 to a 16-bit code. A centred boxcar adds no delay; its droop at 450 Hz is 0.03 %.
//! - ADC1's end of conversion (at `t_k` + 14.3 us) raises ADC1_2, the highest-priority interrupt, which reads the
//!   code, computes the next command and writes its code to the DAC's holding register first (a posted change
//!   applied, the excitation, the limits: at most 2 357 instructions, QEMU's `isr_to_command_write`), then runs the
//!   filters and the estimators. The command's deadline: the next TIM2 update, 85.7 us ([`DEADLINE_CYCLES`], 14 568
//!   cycles) after the conversion ends; crossing it is detected (TIM2's update flag set again when the code is
//!   written, or TIM2's count at the interrupt's entry past it: [`G474Board::entered`]) and counted. The rest of the
//!   interrupt has until the next conversion ends, a sample period after this one: beyond it the next interrupt
//!   starts late, and a conversion not read before the following one ends is an ADC overrun, counted too.

use core::sync::atomic::{AtomicBool, Ordering};
use embassy_stm32::pac;
use embassy_stm32::pac::adc::vals::{Exten, Ovrmod, Rovsm, SampleTime, Trovs};
use embassy_stm32::pac::timer::vals::{Mms, Ocm};
use embassy_stm32::usart::{BufferedUart, Config as UartConfig};
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_stm32::{bind_interrupts, peripherals, Peripherals};
use nanopos_id::hal::{BoardDescription, BoardFaults, ConverterFormat, StageBoard};
use nanopos_id::pipeline::{AmplifierFrontEnd, PipelineSettings, ProbeFrontEnd};

/// Sample rate, Hz.
pub const SAMPLE_RATE_HZ: u32 = 10_000;
/// Timer clock, Hz.
const TIMER_HZ: u32 = 170_000_000;
/// Timer ticks per sample.
pub const TICKS_PER_SAMPLE: u32 = TIMER_HZ / SAMPLE_RATE_HZ;
/// ADC1 channel of PA0.
const PROBE_CHANNEL: u8 = 1;
/// Oversampling: 64 conversions, their sum shifted right by 2 (rounded): 12 + 6 - 2 = 16-bit codes, the largest
/// 4095 * 64 / 4 = 65520 (the reference manual's "Oversampler": beyond 16 bits the data register would drop the
/// top bits, without saturating).
const OVERSAMPLING_RATIO: u32 = 64;
const OVERSAMPLING_SHIFT: u8 = 2;
/// The ratio as ADC_CFGR2.OVSR codes it: 2^(OVSR + 1).
const OVERSAMPLING_RATIO_CODE: u8 = OVERSAMPLING_RATIO.trailing_zeros() as u8 - 1;
const PROBE_FORMAT: ConverterFormat = ConverterFormat::oversampled(12, OVERSAMPLING_RATIO, OVERSAMPLING_SHIFT, 3.3);
const _: () = assert!(PROBE_FORMAT.bits == 16 && PROBE_FORMAT.max_code == 65_520);
/// Conversion window: 64 * (6.5 + 12.5) ADC cycles at 42.5 MHz, in timer ticks (170 MHz: 4 ticks per ADC cycle).
const WINDOW_TICKS: u32 = OVERSAMPLING_RATIO * 19 * 4;
/// TIM2's count when the conversion ends and raises the sample interrupt: the window is centred on the update.
const CONVERSION_END_TICK: u32 = WINDOW_TICKS / 2;
/// The command's deadline, in cycles from the conversion's end (when the sample interrupt is raised) to the next
/// sample instant, where the DAC loads the code the interrupt writes: 85.7 us. The interrupt writes it before its
/// filters and estimators, which have the whole sample period ([`TICKS_PER_SAMPLE`] cycles).
pub const DEADLINE_CYCLES: u32 = TICKS_PER_SAMPLE - CONVERSION_END_TICK;
const _: () = assert!(DEADLINE_CYCLES == 14_568);
/// Slack either side of [`CONVERSION_END_TICK`] for the ADC's trigger and end-of-conversion delays (a few ADC cycles
/// of 4 ticks) and the interrupt's entry: 1.5 us.
const CONVERSION_SLACK_TICKS: u32 = 256;
/// ADC12 EXTSEL code of TIM2_CC2 (RM0440, ADC1/2 external triggers: EXT3; stm32-data's STM32G474RE metadata, as
/// stm32-metapac 21 ships it, agrees: ADC1's `ADC_EXT_TRG3` is `TIM2_CC2`).
const ADC_TRIGGER_TIM2_CC2: u8 = 3;
/// DAC TSEL code of TIM2_TRGO (RM0440, DAC1 triggers: 4; stm32-data agrees: DAC1's `DAC_CHX_TRG4` is `TIM2_TRGO`,
/// TSEL 0 being the software trigger).
const DAC_TRIGGER_TIM2_TRGO: u8 = 4;
/// Console baud rate (the ST-LINK/V3 virtual COM port supports it; continuous recording needs it).
pub const CONSOLE_BAUD: u32 = 921_600;
/// Watchdog timeout, us.
pub const WATCHDOG_TIMEOUT_US: u32 = 500_000;

/// The console's receive buffer, bytes: more than a command line (96 bytes and its end). embassy's ring buffer holds
/// all of them (its indices wrap at twice the length: full is 128 bytes, not 127), so a read of 128 bytes is how the
/// console learns it was full (`LineBuffer::read`).
pub const CONSOLE_RX_BYTES: usize = 128;

bind_interrupts!(struct Irqs {
    LPUART1 => ConsoleRxErrors, embassy_stm32::usart::BufferedInterruptHandler<peripherals::LPUART1>;
});

/// A receive error of the console's link (overrun, framing, noise, parity) since the console last looked.
static CONSOLE_RX_ERROR: AtomicBool = AtomicBool::new(false);

/// Set by the first panic (the panic handler logs only that one).
static PANICKED: AtomicBool = AtomicBool::new(false);

/// True the first time it is asked: the panic handler's guard against a panic while it logs a panic.
pub fn first_panic() -> bool {
    !PANICKED.swap(true, Ordering::Relaxed)
}

/// Bound ahead of embassy's handler of LPUART1, which clears the receive errors and, in its buffered reader, only
/// logs them (embassy-stm32 0.6: `read` never returns an error): notes them for [`take_console_rx_error`].
pub struct ConsoleRxErrors;

impl embassy_stm32::interrupt::typelevel::Handler<embassy_stm32::interrupt::typelevel::LPUART1> for ConsoleRxErrors {
    unsafe fn on_interrupt() {
        let isr = pac::LPUART1.isr().read();
        if isr.ore() || isr.fe() || isr.ne() || isr.pe() {
            CONSOLE_RX_ERROR.store(true, Ordering::Relaxed);
        }
    }
}

/// Whether the console's link had a receive error since the last call. Taken under the same lock as the bytes
/// read from the receive buffer, the errors are of those bytes: the UART's interrupt, which stores bytes and notes
/// errors, cannot run in between.
pub fn take_console_rx_error() -> bool {
    CONSOLE_RX_ERROR.swap(false, Ordering::Relaxed)
}

/// The Nucleo's HSE crystal, Hz.
const CRYSTAL_HZ: u32 = 24_000_000;
/// How long the crystal has to start, ms (its datasheet start-up time is about 2 ms).
const CRYSTAL_START_MS: u32 = 50;

/// Whether the HSE crystal starts within [`CRYSTAL_START_MS`]: switched on, waited for, and switched off again, so
/// that `embassy_stm32::init` finds the reset state (it would wait for a missing crystal for ever). Call before it,
/// on the reset clock (HSI16).
pub fn crystal_starts() -> bool {
    let cr = pac::RCC.cr();
    cr.modify(|w| w.set_hseon(true));
    let mut started = false;
    for _ in 0..CRYSTAL_START_MS {
        if cr.read().hserdy() {
            started = true;
            break;
        }
        cortex_m::asm::delay(16_000); // At least 1 ms at 16 MHz.
    }
    cr.modify(|w| w.set_hseon(false));
    // A running crystal stops within six of its cycles; a bounded wait all the same.
    for _ in 0..1000 {
        if !cr.read().hserdy() {
            break;
        }
    }
    started
}

/// Watch the running crystal: the clock security system switches the system clock to HSI16 if it fails, and raises
/// the NMI ([`clear_crystal_failure`]). Call after `embassy_stm32::init` started the crystal.
pub fn watch_crystal() {
    pac::RCC.cr().modify(|w| w.set_csson(true));
}

/// Acknowledge the clock security system's failure flag (the NMI comes back at once until it is cleared).
pub fn clear_crystal_failure() {
    pac::RCC.cicr().write(|w| w.set_cssc(true));
}

/// The clock tree above: from the crystal if it started ([`crystal_starts`]), else from HSI16 (same frequencies).
pub fn clocks(crystal: bool) -> embassy_stm32::Config {
    use embassy_stm32::rcc::*;
    let mut config = embassy_stm32::Config::default();
    let (source, prediv) = if crystal {
        config.rcc.hse = Some(Hse { freq: embassy_stm32::time::Hertz(CRYSTAL_HZ), mode: HseMode::Oscillator });
        (PllSource::HSE, PllPreDiv::DIV6)
    } else {
        config.rcc.hsi = true;
        (PllSource::HSI, PllPreDiv::DIV4)
    };
    config.rcc.pll =
        Some(Pll { source, prediv, mul: PllMul::MUL85, divp: None, divq: None, divr: Some(PllRDiv::DIV2) });
    config.rcc.sys = Sysclk::PLL1_R;
    config.rcc.boost = true;
    config.rcc.mux.adc12sel = mux::Adcsel::SYS;
    config
}

/// The board's converters and timing, as the pipeline needs them.
pub const DESCRIPTION: BoardDescription = BoardDescription {
    probe: PROBE_FORMAT,
    amplifier: ConverterFormat::new(12, 3.3),
    // DAC1 channel 1 with its output buffer on (it drives the reconstruction filter): specified from 0.2 V to
    // VREF+ - 0.2 V, which the pipeline keeps the output within (codes 249 to 3847: -8.78 to 8.78 V with the level
    // shift of `settings`).
    amplifier_swing_v: [0.2, 3.1],
    actuation_delay_samples: 1,
};

/// What the rest of the firmware gets from the board.
pub struct Parts {
    /// The console (commands, replies, recording).
    pub console: BufferedUart<'static>,
    /// The independent watchdog, not yet started.
    pub watchdog: IndependentWatchdog<'static, peripherals::IWDG>,
}

/// Why the board last reset, read (and cleared) once at start.
#[derive(Clone, Copy, PartialEq, Eq, defmt::Format)]
pub enum ResetCause {
    /// Power on or brown-out.
    PowerOn,
    /// The reset pin (the Nucleo's button, or the probe).
    Pin,
    /// The software reset (a probe's or a debugger's reset request).
    Software,
    /// The independent or window watchdog: the firmware hung or faulted.
    Watchdog,
    /// Anything else (low-power, option bytes).
    Other,
}

/// Read and clear the reset flags.
pub fn reset_cause() -> ResetCause {
    let rcc = pac::RCC;
    let csr = rcc.csr().read();
    rcc.csr().modify(|w| w.set_rmvf(true));
    if csr.iwdgrstf() || csr.wwdgrstf() {
        ResetCause::Watchdog
    } else if csr.borrstf() {
        ResetCause::PowerOn
    } else if csr.sftrstf() {
        ResetCause::Software
    } else if csr.pinrstf() {
        ResetCause::Pin
    } else {
        ResetCause::Other
    }
}

/// The pipeline's settings on this board: the sample rate, and the analog front end's scaling (the reference probe's
/// 5 um/V; the divider mapping +-10 V onto the ADC's 0-3.3 V, the level shift mapping the DAC's 0-3.3 V onto
/// +-10 V, of which its buffered output reaches -8.78 to 8.78 V). Change them with the hardware; the rest are the
/// paper's defaults.
pub fn settings() -> PipelineSettings {
    PipelineSettings {
        sample_rate_hz: SAMPLE_RATE_HZ as f64,
        probe: ProbeFrontEnd { um_per_v: 5.0, adc_v_per_sensor_v: 3.3 / 20.0, adc_offset_v: 1.65 },
        amplifier: AmplifierFrontEnd { dac_v_per_command_v: 3.3 / 20.0, dac_offset_v: 1.65 },
        ..PipelineSettings::default()
    }
}

/// Drive the amplifier at `code` (its safe value) from the reset clock on, before anything else of the start-up:
/// DAC1 channel 1 on PA4 (analog out of reset on the G4) switched on with its output buffer, for the external pin,
/// untriggered, so that its output follows the code at once. From any reset (power-up, the watchdog, a flashing)
/// until here the DAC is off and its pin floats: the RAM's initialisation, about 1.5 ms at 16 MHz (13 KiB of statics
/// zeroed by cortex-m-rt's loop, 7 to 8 cycles a word; an estimate), where before this the copy of the RAM code,
/// the crystal's start-up, the clocks and the designs came first too: a few ms, over 50 without the crystal.
/// [`init`] then sets its trigger, without resetting it (embassy's driver would: the output off again).
/// Never inlined: `tests/firmware.rs` checks that it is the start-up's first call.
#[inline(never)]
pub fn early_safe_output(code: u16) {
    pac::RCC.ahb2enr().modify(|w| w.set_dac1en(true));
    // Read back: the clock is on before DAC1 is written.
    let _ = pac::RCC.ahb2enr().read();
    let dac = pac::DAC1;
    // With the channel off (the mode can be written only then). The interface's high-frequency mode for the 170 MHz
    // AHB the clocks will run at (RM0440, DAC_MCR.HFSEL: above 160 MHz), which only adds wait cycles below it.
    dac.mcr().modify(|w| {
        w.set_hfsel(0b10);
        w.set_mode(0, pac::dac::vals::Mode::NORMAL_EXT_BUFEN);
    });
    // Untriggered, a code written reaches the output register a clock later; written before and after the channel
    // is on, it is there whether or not that transfer happens with the channel off (else the reset's code 0, -10 V
    // at the amplifier, would stay).
    dac.dhr12r(0).write(|w| w.set_dhr(code));
    dac.cr().modify(|w| w.set_en(0, true));
    dac.dhr12r(0).write(|w| w.set_dhr(code));
}

/// Set up the ADC, the sample timer, the DAC's trigger, the console and the watchdog; the DAC is on already
/// ([`early_safe_output`]). The timer is left stopped: [`start_sample_clock`] starts it. `safe_code` is the DAC
/// code the output holds until the pipeline runs.
pub fn init(p: Peripherals, safe_code: u16) -> Parts {
    let dac = pac::DAC1;
    dac.dhr12r(0).write(|w| w.set_dhr(safe_code));

    // TIM2: 10 kHz, TRGO on update (DAC), CH2 in PWM mode 2 rising half a window before the update (ADC). Stopped
    // until `start_sample_clock`.
    embassy_stm32::rcc::enable_and_reset::<embassy_stm32::peripherals::TIM2>();
    let tim = pac::TIM2;
    tim.psc().write_value(0);
    tim.arr().write_value(TICKS_PER_SAMPLE - 1);
    tim.ccr(1).write_value(TICKS_PER_SAMPLE - WINDOW_TICKS / 2);
    tim.ccmr_output(0).modify(|w| w.set_ocm(1, Ocm::PWM_MODE2));
    tim.ccer().modify(|w| w.set_cce(1, true));
    tim.cr2().modify(|w| w.set_mms(Mms::UPDATE));

    // The DAC on TIM2's update (its trigger is chosen with the channel off), then one update by software: its TRGO
    // loads the safe code into the output register again, whatever disabling the channel did to it.
    dac.cr().modify(|w| w.set_en(0, false));
    dac.cr().modify(|w| {
        w.set_tsel(0, DAC_TRIGGER_TIM2_TRGO);
        w.set_ten(0, true);
    });
    dac.cr().modify(|w| w.set_en(0, true));
    tim.egr().write(|w| w.set_ug(true));
    tim.sr().write_value(Default::default());

    // ADC1: the driver powers up, calibrates and enables it with 64x oversampling; channel, trigger and interrupt are
    // set here. PA0 is in analog mode out of reset on the G4.
    let adc = embassy_stm32::adc::Adc::new(
        p.ADC1,
        embassy_stm32::adc::AdcConfig {
            oversampling_ratio: Some(OVERSAMPLING_RATIO_CODE),
            oversampling_shift: Some(OVERSAMPLING_SHIFT),
            oversampling_mode: Some((Rovsm::CONTINUED, Trovs::AUTOMATIC, true)),
            ..Default::default()
        },
    );
    // Kept configured for good: the driver has no `Drop` today, but one that powered the ADC down would stop the
    // sample path.
    #[allow(clippy::forget_non_drop)]
    core::mem::forget(adc);
    let adc = pac::ADC1;
    adc.smpr().modify(|w| w.set_smp(PROBE_CHANNEL as usize, SampleTime::CYCLES6_5));
    adc.sqr1().modify(|w| {
        w.set_l(0);
        w.set_sq(0, PROBE_CHANNEL);
    });
    adc.cfgr().modify(|w| {
        w.set_cont(false);
        w.set_extsel(ADC_TRIGGER_TIM2_CC2);
        w.set_exten(Exten::RISING_EDGE);
        w.set_ovrmod(Ovrmod::OVERWRITE);
    });
    adc.isr().write(|w| {
        w.set_eoc(true);
        w.set_ovr(true);
    });
    adc.ier().modify(|w| w.set_eocie(true));
    adc.cr().modify(|w| w.set_adstart(true));

    let mut uart_config = UartConfig::default();
    uart_config.baudrate = CONSOLE_BAUD;
    // One singleton for both (one taken flag and its padding, not two).
    let (tx_buf, rx_buf) =
        cortex_m::singleton!(: ([u8; 1024], [u8; CONSOLE_RX_BYTES]) = ([0; 1024], [0; CONSOLE_RX_BYTES]))
            .expect("console buffers taken once");
    let console = BufferedUart::new(p.LPUART1, p.PA3, p.PA2, tx_buf, rx_buf, Irqs, uart_config)
        .expect("LPUART1 at 921 600 baud from a 170 MHz clock");
    Parts { console, watchdog: IndependentWatchdog::new(p.IWDG, WATCHDOG_TIMEOUT_US) }
}

/// Whether the interrupts may be held off for `cycles` now without delaying a sample: the sample interrupt is not
/// pending and its next conversion ends later than that (`nanopos_id::hal::clear_of_sample`; TIM2 counts CPU cycles).
/// Asked with the interrupts masked, the answer holds until they are unmasked. Never inlined, so that
/// `tests/firmware.rs` finds it asked in every taking of the lock.
#[inline(never)]
pub fn clear_of_sample(cycles: u32) -> bool {
    !embassy_stm32::interrupt::InterruptExt::is_pending(embassy_stm32::interrupt::ADC1_2)
        && nanopos_id::hal::clear_of_sample(cycles_since_conversion(), TICKS_PER_SAMPLE, cycles, CONVERSION_SLACK_TICKS)
}

/// Cycles since the last conversion ended (TIM2 counts CPU cycles): read first thing in the sample interrupt, how
/// late it started.
#[inline(always)]
pub fn cycles_since_conversion() -> u32 {
    nanopos_id::hal::ticks_since(pac::TIM2.cnt().read(), CONVERSION_END_TICK, TICKS_PER_SAMPLE)
}

/// Start the sample clock.
pub fn start_sample_clock() {
    pac::TIM2.cr1().modify(|w| w.set_cen(true));
}

/// Drive the amplifier to `code` (its safe value) and keep it there: usable from a fault handler. The timer keeps
/// running in hardware, so the next update (within 100 us) loads it. Never inlined: `tests/firmware.rs` checks
/// that it is the panic handler's first call.
#[inline(never)]
pub fn force_safe_output(code: u16) {
    pac::DAC1.dhr12r(0).write(|w| w.set_dhr(code));
}

/// Raise a HardFault (`udf`), with the UsageFault that an undefined instruction would raise first turned off.
pub fn hard_fault() -> ! {
    // SAFETY: a read-modify-write of SHCSR that clears USGFAULTENA (bit 18) only, by the panic handler, with
    // interrupts masked; the undefined instruction then escalates to the HardFault, whose handler is ours.
    unsafe { (*cortex_m::peripheral::SCB::PTR).shcsr.modify(|v| v & !(1 << 18)) };
    cortex_m::asm::udf()
}

/// The board seen from the sample interrupt. Reading the probe acknowledges the conversion, notes an ADC overrun
/// and arms the deadline check (TIM2's update flag, set again only if the next sample instant passes before the
/// command is written); writing the command looks at the flag right after: the deadline is the command's, which
/// the pipeline writes before its filters and estimators run. An interrupt that starts after the next sample
/// instant has missed the deadline before the flag is armed (the flag that instant set is the one reading the probe
/// clears): [`G474Board::entered`] tells it from the cycles since the conversion at the interrupt's entry.
#[derive(Default)]
pub struct G474Board {
    adc_overrun: bool,
    deadline_missed: bool,
    started_late: bool,
}

impl G474Board {
    /// At the sample interrupt's entry, `cycles` after its conversion ended ([`cycles_since_conversion`]): from
    /// [`DEADLINE_CYCLES`] on, the next sample instant has passed and this sample's command is late whatever follows
    /// (up to [`CONVERSION_SLACK_TICKS`] before a whole period: an interrupt raised a little before the computed end
    /// of its conversion; a whole period late, the next conversion has ended too: an ADC overrun).
    #[inline(always)]
    pub fn entered(&mut self, cycles: u32) {
        self.started_late =
            nanopos_id::hal::entered_past(cycles, TICKS_PER_SAMPLE, DEADLINE_CYCLES, CONVERSION_SLACK_TICKS);
    }

    /// Acknowledge a conversion without using it (the interrupt before the pipeline is installed).
    pub fn discard_conversion() {
        pac::ADC1.isr().write(|w| {
            w.set_eoc(true);
            w.set_ovr(true);
        });
    }
}

impl StageBoard for G474Board {
    fn sample_rate_hz(&self) -> f64 {
        SAMPLE_RATE_HZ as f64
    }

    fn description(&self) -> BoardDescription {
        DESCRIPTION
    }

    #[inline(always)]
    fn read_probe(&mut self) -> u32 {
        let isr = pac::ADC1.isr().read();
        let code = pac::ADC1.dr().read().rdata() as u32;
        pac::ADC1.isr().write(|w| {
            w.set_eoc(true);
            w.set_ovr(isr.ovr());
        });
        pac::TIM2.sr().write(|w| w.set_uif(false));
        self.adc_overrun = isr.ovr();
        code
    }

    #[inline(always)]
    fn write_amplifier(&mut self, code: u32) {
        pac::DAC1.dhr12r(0).write(|w| w.set_dhr(code.min(4095) as u16));
        self.deadline_missed = self.started_late | pac::TIM2.sr().read().uif();
    }

    #[inline(always)]
    fn sample_faults(&mut self) -> BoardFaults {
        BoardFaults { adc_overrun: self.adc_overrun, deadline_missed: self.deadline_missed }
    }
}
