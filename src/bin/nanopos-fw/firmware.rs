//! The firmware's glue: start-up, the sample interrupt, telemetry.

use crate::board::{self, G474Board};
use core::cell::RefCell;
use cortex_m::interrupt::Mutex;
use cortex_m::peripheral::DWT;
use defmt_rtt as _;
use embassy_executor::Spawner;
use embassy_stm32::interrupt::{InterruptExt, Priority};
use embassy_stm32::pac::interrupt;
use embassy_time::{Duration, Ticker};
use nanopos_id::estimator::{Estimator, Health};
use nanopos_id::estimators::arx::{ArxDesign, ArxEstimator};
use nanopos_id::estimators::crls::Crls;
use nanopos_id::estimators::ekf::{Cekf, Hekf};
use nanopos_id::estimators::paper_bank;
use nanopos_id::hal::run_sample;
use nanopos_id::pipeline::{FaultCounters, Faults, Pipeline, PipelineConfig, PipelineSettings};
use nanopos_id::StageParams;
use panic_probe as _;

/// Cycles per sample period at 170 MHz.
const CYCLES_PER_SAMPLE: u32 = 17_000;

/// Every estimator, in the interrupt (PRBS tuning). Run-time selection and tuning: issue 6.
type Bank = (Crls<f32>, Cekf<f32>, Hekf<f32>, ArxEstimator<f32>);
/// Their names in the telemetry, in the bank's order.
const NAMES: [&str; 4] = [Crls::<f32>::NAME, Cekf::<f32>::NAME, Hekf::<f32>::NAME, ArxEstimator::<f32>::NAME];

/// What the interrupt owns.
struct SampleTask {
    board: G474Board,
    pipeline: Pipeline<f32, Bank>,
    config: PipelineConfig<f32>,
    stats: SampleStats,
}

/// Interrupt statistics over one telemetry window, plus totals.
#[derive(Clone, Copy, Default)]
struct SampleStats {
    samples: u64,
    window_samples: u32,
    window_cycles: u64,
    window_max_cycles: u32,
    y_um: f32,
    u_v: f32,
    faults: Faults,
    counters: FaultCounters,
}

/// The interrupt's state, shared with the telemetry task for the few cycles a snapshot takes. Taking the lock in
/// thread mode masks the sample interrupt for that copy (about 100 cycles): it delays one interrupt's start by under
/// a microsecond, inside its 85.7 us slack, and never moves the sample instants, which are hardware-timed.
static TASK: Mutex<RefCell<Option<SampleTask>>> = Mutex::new(RefCell::new(None));

#[embassy_executor::main]
async fn main(spawner: Spawner) {
    let p = embassy_stm32::init(board::clocks());
    // The embassy time driver (TIM15) must not delay the sample interrupt.
    embassy_stm32::interrupt::TIM1_BRK_TIM15.set_priority(Priority::P1);

    let mut core = cortex_m::Peripherals::take().expect("core peripherals taken once");
    core.DCB.enable_trace();
    core.DWT.enable_cycle_counter();

    let settings = PipelineSettings::default();
    let config: PipelineConfig<f32> = match settings.design(&board::DESCRIPTION) {
        Ok(c) => c,
        Err(e) => defmt::panic!("pipeline settings: {}", e),
    };
    board::init(p);
    cortex_m::interrupt::free(|cs| {
        TASK.borrow(cs).replace(Some(SampleTask {
            board: G474Board::default(),
            pipeline: {
                let (crls, cekf, hekf) = paper_bank();
                Pipeline::new(&config, (crls, cekf, hekf, ArxEstimator::new(ArxDesign::default().design())))
            },
            config,
            stats: SampleStats::default(),
        }));
    });
    embassy_stm32::interrupt::ADC1_2.set_priority(Priority::P0);
    // SAFETY: the handler below only touches state behind `TASK`, initialised just above.
    unsafe { embassy_stm32::interrupt::ADC1_2.enable() };
    board::start_sample_clock();
    defmt::info!(
        "nanopos-fw: sampling at {=u32} Hz, PRBS 1 V, probe 16-bit, DAC 12-bit, cycle budget {=u32}",
        board::SAMPLE_RATE_HZ,
        CYCLES_PER_SAMPLE
    );
    spawner.spawn(telemetry().expect("telemetry task spawns once"));
}

#[interrupt]
fn ADC1_2() {
    let start = DWT::cycle_count();
    cortex_m::interrupt::free(|cs| {
        let mut task = TASK.borrow(cs).borrow_mut();
        let Some(t) = task.as_mut() else {
            // Not started: acknowledge the conversion and leave the output where it is (safe).
            G474Board::discard_conversion();
            return;
        };
        let out = run_sample(&mut t.board, &mut t.pipeline, &t.config);
        let cycles = DWT::cycle_count().wrapping_sub(start);
        let s = &mut t.stats;
        s.samples += 1;
        s.window_samples += 1;
        s.window_cycles += cycles as u64;
        s.window_max_cycles = s.window_max_cycles.max(cycles);
        s.y_um = out.y_um;
        s.u_v = out.u_v;
        s.faults = out.faults;
        s.counters = t.pipeline.fault_counters();
    });
}

/// Each estimator's parameters and health at the end of a window.
type Estimates = [(StageParams<f32>, Health); 4];

/// Take the statistics of the window since the last call, and the estimates (read under the lock: a few hundred
/// cycles, which delay one interrupt's start inside its slack; the sample instants are hardware-timed).
fn take_window() -> Option<(SampleStats, Estimates)> {
    cortex_m::interrupt::free(|cs| {
        let mut task = TASK.borrow(cs).borrow_mut();
        let t = task.as_mut()?;
        let e = &t.pipeline.estimators;
        let estimates = [
            (e.0.params(), e.0.health()),
            (e.1.params(), e.1.health()),
            (e.2.params(), e.2.health()),
            (e.3.params(), e.3.health()),
        ];
        let snapshot = (t.stats, estimates);
        t.stats.window_samples = 0;
        t.stats.window_cycles = 0;
        t.stats.window_max_cycles = 0;
        Some(snapshot)
    })
}

/// 10 Hz: interrupt cost, deadlines, faults, the last sample; then one line per estimator: the model
/// `y'' = -a0 y - a1 y' + b0 u` (a0 in 1/s^2, a1 in 1/s, b0 in um/(s^2 V)) and what it means: natural frequency,
/// damping ratio, static gain (um/V), with the estimator's health.
#[embassy_executor::task]
async fn telemetry() {
    let mut ticker = Ticker::every(Duration::from_millis(100));
    let mut reported_misses = 0;
    loop {
        ticker.next().await;
        let Some((s, estimates)) = take_window() else { continue };
        let mean = if s.window_samples > 0 { (s.window_cycles / s.window_samples as u64) as u32 } else { 0 };
        defmt::info!(
            "samples={=u64} isr_cycles mean={=u32} max={=u32} of {=u32} | y={=f32} um u={=f32} V | faults={=u8:#04x} over_range={=u32} stuck={=u32}",
            s.samples,
            mean,
            s.window_max_cycles,
            CYCLES_PER_SAMPLE,
            s.y_um,
            s.u_v,
            s.faults.0,
            s.counters.probe_over_range,
            s.counters.probe_stuck
        );
        for (name, (p, h)) in NAMES.iter().zip(estimates.iter()) {
            defmt::info!(
                "{=str}: a0={=f32} a1={=f32} b0={=f32} | f0={=f32} Hz zeta={=f32} gain={=f32} um/V | {} rejected={=u32} changes={=u32} resets={=u32} innovation_rms={=f32} um",
                name,
                p.a0,
                p.a1,
                p.b0,
                p.f0_hz(),
                p.damping_ratio(),
                p.dc_gain(),
                h.adaptation,
                h.rejected_samples,
                h.changes_detected,
                h.numeric_resets,
                h.innovation_rms_um
            );
        }
        let (misses, overruns) = (s.counters.deadline_misses, s.counters.adc_overruns);
        if misses + overruns != reported_misses {
            reported_misses = misses + overruns;
            defmt::warn!("deadline misses={=u32} adc overruns={=u32}", misses, overruns);
        }
    }
}

/// Any fault (a panic ends here too, through panic-probe's `udf`): the amplifier goes to its safe value; the
/// sample timer keeps running in hardware and loads it within one sample period.
#[cortex_m_rt::exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    board::force_safe_output();
    loop {
        cortex_m::asm::wfi();
    }
}
