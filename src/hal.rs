//! The board, as one sample of it: a probe reading in, an amplifier command out, at a fixed sample rate.
//!
//! [`StageBoard`] is all the core knows of hardware. The NUCLEO-G474RE firmware implements it on the ADC and DAC
//! registers inside the sample-clock interrupt; `hal-sim` implements it on a simulated stage. Both then call
//! [`run_sample`], the same code, once per sample.
//!
//! Converters are described by [`ConverterFormat`] (bits and full-scale voltage), never assumed to be 12-bit: the
//! G474's ADC with hardware oversampling delivers 16-bit codes, and an external 16-18-bit SPI converter is the
//! natural upgrade. The analog front end between converter and instrument (divider, level shift, sensor gain) is a
//! setting of the pipeline ([`crate::pipeline::ProbeFrontEnd`], [`crate::pipeline::AmplifierFrontEnd`]).

use crate::estimator::EstimatorBank;
use crate::pipeline::{Pipeline, PipelineConfig, SampleOutput};
use crate::Real;

/// A converter's code range and the voltage it spans: code `c` is `c * full_scale_v / 2^bits` volts, and the codes
/// run from 0 to `max_code`.
///
/// `max_code` is `2^bits - 1` for a plain converter ([`ConverterFormat::new`]) but not for an oversampling one
/// ([`ConverterFormat::oversampled`]): the G474's ADC accumulating 64 12-bit conversions and shifting the sum right
/// by 2 delivers 16-bit codes whose largest is `4095 * 64 / 4 = 65520`, not 65535 (the STM32 reference manuals,
/// "Oversampler", their table of maximum results). Over-range is judged from the largest code the converter
/// delivers, so the margin a [`crate::pipeline::FaultSettings`] asks for is the same at both ends.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub struct ConverterFormat {
    /// Resolution of the delivered code (for an oversampling ADC: after accumulation and shift).
    pub bits: u8,
    /// Voltage of code `2^bits` (the reference), V.
    pub full_scale_v: f64,
    /// The largest code the converter delivers (at or near its full scale): `2^bits - 1` or less, or `2^bits` for an
    /// oversampler that shifts out more bits than its accumulation added and rounds up to the full scale.
    pub max_code: u32,
}

impl ConverterFormat {
    /// A converter whose codes span all of `bits`: 0 to `2^bits - 1`.
    pub const fn new(bits: u8, full_scale_v: f64) -> Self {
        let max_code = if bits == 0 || bits > 32 { 0 } else { u32::MAX >> (32 - bits as u32) };
        ConverterFormat { bits, full_scale_v, max_code }
    }

    /// An oversampling ADC: `ratio` conversions of `native_bits` each summed and shifted right by `shift`, rounded to
    /// nearest (as the STM32 oversamplers do). The largest code is the sum of `ratio` full-scale conversions, shifted
    /// and rounded. `bits` is `native_bits + log2(ratio) - shift`; a `ratio` that is not a power of two from 1 to 256,
    /// or a shift beyond the sum's width, gives a format the pipeline refuses ([`ConverterFormat::is_valid`]). The
    /// STM32's data register holds 16 bits and drops the rest without saturating: keep `bits` at 16 or fewer there.
    pub const fn oversampled(native_bits: u8, ratio: u32, shift: u8, full_scale_v: f64) -> Self {
        let valid = native_bits > 0
            && native_bits <= 24
            && ratio.is_power_of_two()
            && ratio <= 256
            && (shift as u32) <= native_bits as u32 + ratio.trailing_zeros();
        if !valid {
            return ConverterFormat { bits: 0, full_scale_v, max_code: 0 };
        }
        let bits = native_bits as u32 + ratio.trailing_zeros() - shift as u32;
        let sum = ((1u64 << native_bits) - 1) * ratio as u64;
        let max_code = if shift == 0 { sum } else { (sum + (1 << (shift - 1))) >> shift };
        ConverterFormat { bits: bits as u8, full_scale_v, max_code: max_code as u32 }
    }

    /// Volts per code.
    pub fn volts_per_code(&self) -> f64 {
        self.full_scale_v / (1u64 << self.bits) as f64
    }

    /// Whether the pipeline can work with it: 1 to 24 bits, a positive finite full scale, and a largest code from
    /// half the range to `2^bits`.
    pub fn is_valid(&self) -> bool {
        (1..=24).contains(&self.bits)
            && self.full_scale_v.is_finite()
            && self.full_scale_v > 0.0
            && self.max_code <= 1 << self.bits
            && self.max_code >= 1 << (self.bits - 1)
    }
}

/// What the pipeline must know of a board: its converters and its timing.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub struct BoardDescription {
    /// Format of the probe ADC's code.
    pub probe: ConverterFormat,
    /// Format of the amplifier DAC's code.
    pub amplifier: ConverterFormat,
    /// The DAC output, V, lowest first, within which its code sets the output: what it is specified to reach. The
    /// G474's DAC with its output buffer on (the buffer drives the reconstruction filter) is specified from 0.2 V to
    /// its reference less 0.2 V, not rail to rail (STM32 datasheets, "DAC characteristics"); beyond, the output
    /// stops short of the code and the estimators, fed the command, would take a drive the stage never saw. The
    /// pipeline keeps the output within it ([`BoardDescription::amplifier_codes`]). An unbuffered or external DAC:
    /// `[0, full_scale_v]`.
    pub amplifier_swing_v: [f64; 2],
    /// Samples between writing a DAC code and the DAC output changing, 0 or 1. The G474 firmware loads the DAC from
    /// the sample timer (TIM2 TRGO), so a code written during sample `k` appears exactly at `t_(k+1)`: one sample,
    /// without jitter. A board that writes the DAC directly from the interrupt would be 0 (plus the interrupt's
    /// latency, which this model cannot express: avoid).
    pub actuation_delay_samples: u8,
}

impl BoardDescription {
    /// The amplifier DAC's first and last codes within [`Self::amplifier_swing_v`]: the codes the pipeline writes.
    /// `None` if the swing is not finite or holds fewer than two codes.
    pub fn amplifier_codes(&self) -> Option<[u32; 2]> {
        let (a, [low, high]) = (&self.amplifier, self.amplifier_swing_v);
        if !(low.is_finite() && high.is_finite()) {
            return None;
        }
        let first = libm::ceil(low / a.volts_per_code()).max(0.0);
        let last = libm::floor(high / a.volts_per_code()).min(a.max_code as f64);
        (first < last).then_some([first as u32, last as u32])
    }
}

/// What went wrong on the board during one sample (counted by the pipeline, reported by telemetry).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub struct BoardFaults {
    /// A probe conversion was lost: the previous one was not read before the next completed.
    pub adc_overrun: bool,
    /// The next sample instant passed before this sample's command was written: the DAC output a stale code.
    pub deadline_missed: bool,
}

/// One sample of a stage's board.
pub trait StageBoard {
    /// The hardware sample rate, Hz.
    fn sample_rate_hz(&self) -> f64;
    /// Converters and timing.
    fn description(&self) -> BoardDescription;
    /// The probe conversion of this sample (converted at the sample instant).
    fn read_probe(&mut self) -> u32;
    /// The amplifier command; it takes effect `actuation_delay_samples` sample instants later. Called as soon as
    /// the command is known, before the filters and the estimators run ([`run_sample`]): a board with a deadline
    /// for the command checks it here.
    fn write_amplifier(&mut self, code: u32);
    /// The faults of this sample, read at its end (a late write of the command, as [`Self::write_amplifier`] saw it).
    fn sample_faults(&mut self) -> BoardFaults;
}

/// One sample, end to end: read the probe, run the pipeline, write the amplifier. The command is written as soon as
/// it is known (the excitation, an external command, the limits), before the filters and the estimators: on the
/// board only that part must beat the next sample instant; the estimators have until the next conversion.
#[inline]
pub fn run_sample<B, T, E>(board: &mut B, pipeline: &mut Pipeline<T, E>, cfg: &PipelineConfig<T>) -> SampleOutput<T>
where
    B: StageBoard + ?Sized,
    T: Real,
    E: EstimatorBank<T>,
{
    run_sample_with(board, pipeline, cfg, None::<fn(T) -> T>)
}

/// [`run_sample`] with the excitation added to an external command, V, `command(y_um)` of this sample's reading
/// ([`Pipeline::step_adding`]): a scan, or a controller built on the estimates.
#[inline]
pub fn run_sample_adding<B, T, E>(
    board: &mut B,
    pipeline: &mut Pipeline<T, E>,
    cfg: &PipelineConfig<T>,
    command: impl FnOnce(T) -> T,
) -> SampleOutput<T>
where
    B: StageBoard + ?Sized,
    T: Real,
    E: EstimatorBank<T>,
{
    run_sample_with(board, pipeline, cfg, Some(command))
}

/// [`run_sample`] (`None`) or [`run_sample_adding`].
#[inline(always)]
pub(crate) fn run_sample_with<B, T, E>(
    board: &mut B,
    pipeline: &mut Pipeline<T, E>,
    cfg: &PipelineConfig<T>,
    command: Option<impl FnOnce(T) -> T>,
) -> SampleOutput<T>
where
    B: StageBoard + ?Sized,
    T: Real,
    E: EstimatorBank<T>,
{
    let code = board.read_probe();
    let mut out = pipeline.step_with(cfg, code, command, |dac_code| board.write_amplifier(dac_code));
    out.board_faults = board.sample_faults();
    pipeline.count_board_faults(out.board_faults);
    out
}

/// Whether a critical section of `hold` ticks, started `since` ticks after the sample interrupt was last raised
/// (a timer counting `0..period` once a sample: [`ticks_since`] the moment it is raised), ends before it is raised
/// again, with `margin` ticks of slack on either side of that moment for its jitter. The firmware's thread-mode
/// tasks take the interrupt's state under a lock that holds the interrupt off; they take it only when this holds
/// (and the interrupt is not pending), so that holding it delays no sample.
pub const fn clear_of_sample(since: u32, period: u32, hold: u32, margin: u32) -> bool {
    since >= margin && period - since >= hold.saturating_add(margin)
}

/// Whether an interrupt raised once a period, entered `since` ticks after it was raised ([`ticks_since`]), entered
/// past its `deadline` (ticks after it is raised): the firmware's sample interrupt, whose command is then late
/// whatever it does. Within `margin` ticks before a period has passed it is taken as an interrupt raised a little
/// early instead (the moment it is raised is computed, not read), not as one a whole period late.
pub const fn entered_past(since: u32, period: u32, deadline: u32, margin: u32) -> bool {
    since >= deadline && since < period.saturating_sub(margin)
}

/// Ticks from the last time a timer counting `0..period` read `at` to its reading `count` (0 to `period - 1`).
pub const fn ticks_since(count: u32, at: u32, period: u32) -> u32 {
    (count % period + period - at % period) % period
}

#[cfg(test)]
mod tests {
    use super::{clear_of_sample, entered_past, ticks_since, BoardDescription, ConverterFormat};

    /// The STM32 reference manuals' "Oversampler" section, its table of maximum results for a raw conversion of
    /// 0xFFF (the same in RM0351, RM0432, RM0444 and RM0453, read for this test; the G474's RM0440 was not
    /// available here, its ADC has the same OVSR/OVSS oversampler): the sum shifted and rounded to nearest, where
    /// the result fits in 16 bits.
    #[test]
    fn an_oversampled_adc_tops_out_where_the_reference_manual_says() {
        for (ratio, shift, max) in [
            (2, 0, 0x1FFE),
            (16, 0, 0xFFF0),
            (32, 1, 0xFFF0),
            (64, 2, 0xFFF0),
            (256, 4, 0xFFF0),
            (64, 6, 0x0FFF),
            (32, 6, 0x0800),
            (256, 8, 0x0FFF),
        ] {
            let f = ConverterFormat::oversampled(12, ratio, shift, 3.3);
            assert_eq!(f.max_code, max, "{ratio}x, shift {shift}");
            assert!(f.is_valid(), "{ratio}x, shift {shift}: {f:?}");
        }
        let g474 = ConverterFormat::oversampled(12, 64, 2, 3.3);
        assert_eq!((g474.bits, g474.max_code), (16, 65_520));
        // One code is full scale / 2^bits whichever way the bits came.
        assert_eq!(g474.volts_per_code(), 3.3 / 65_536.0);
        assert_eq!(ConverterFormat::new(16, 3.3).volts_per_code(), 3.3 / 65_536.0);
        assert_eq!(ConverterFormat::new(12, 3.3).volts_per_code(), 3.3 / 4_096.0);
        assert_eq!(ConverterFormat::oversampled(12, 1, 0, 3.3), ConverterFormat::new(12, 3.3));
    }

    #[test]
    fn a_lock_is_clear_of_the_sample_only_well_after_it_and_long_enough_before_the_next() {
        // The G474's timing: 17 000 ticks a sample, the interrupt raised at 2 432, a hold of 4 000 ticks, 256 of slack.
        let clear = |count| clear_of_sample(ticks_since(count, 2_432, 17_000), 17_000, 4_000, 256);
        // At the moment and within the slack after it (the interrupt may be late, or pending): no.
        assert!(!clear(2_432) && !clear(2_432 + 255));
        assert!(clear(2_432 + 256));
        // Mid-period: yes; the last moment whose hold and slack end before the next sample: 17 000 + 2 432 - 4 256.
        assert!(clear(9_000) && clear(15_176) && !clear(15_177));
        // Before the update (counts wrap at 17 000) and just after it, until the interrupt: no.
        assert!(!clear(16_999) && !clear(0) && !clear(2_431));
        // Counts beyond the period are taken modulo it; a hold that cannot fit between two samples never is.
        assert_eq!(clear(17_000 + 9_000), clear(9_000));
        assert!((0..17_000).all(|since| !clear_of_sample(since, 17_000, 16_500, 256)));
        assert!((0..17_000).all(|since| !clear_of_sample(since, 17_000, u32::MAX, 256)));
    }

    #[test]
    fn an_interrupt_entered_after_the_next_sample_instant_is_past_its_deadline() {
        // The board's numbers: raised at count 2 432, the next sample instant at 17 000 (14 568 later).
        let past = |count| entered_past(ticks_since(count, 2_432, 17_000), 17_000, 14_568, 256);
        // On time, however late within the period: no.
        assert!(!past(2_432) && !past(2_460) && !past(16_999));
        // After the next instant, until the next conversion ends (less the margin): yes.
        assert!(past(0) && past(1_000) && past(2_432 - 257));
        // Within the margin before the moment it is raised: raised early, not a period late.
        assert!(!past(2_432 - 256) && !past(2_431));
    }

    #[test]
    fn ticks_since_a_moment_wrap_at_the_period() {
        assert_eq!(ticks_since(2_432, 2_432, 17_000), 0);
        assert_eq!(ticks_since(2_460, 2_432, 17_000), 28);
        assert_eq!(ticks_since(16_999, 2_432, 17_000), 14_567);
        // After the update, before the moment: almost a period since the last one.
        assert_eq!(ticks_since(0, 2_432, 17_000), 14_568);
        assert_eq!(ticks_since(2_431, 2_432, 17_000), 16_999);
        // Readings beyond the period are taken modulo it, to the last a u32 holds (2^32 - 1 = 17 000 * 252 645 +
        // 2 295), without overflowing.
        assert_eq!(ticks_since(u32::MAX, 2_432, 17_000), 16_863);
        assert_eq!(ticks_since(2_295, 2_432 + 17_000, 17_000), 16_863);
        assert_eq!(ticks_since(2_295, u32::MAX, 17_000), 0);
        assert_eq!(ticks_since(2_432, u32::MAX, 17_000), 137);
    }

    /// The codes within the DAC's swing: the G474's buffered DAC (0.2 to 3.1 V of 3.3 V in 12 bits) writes 249 to
    /// 3 847, the first code at or above the swing's bottom and the last at or below its top; a swing beyond the
    /// DAC's codes is cut to them; one that is not a number or holds fewer than two codes gives none.
    #[test]
    fn the_dac_writes_the_codes_within_its_swing() {
        let board = |low: f64, high: f64| BoardDescription {
            probe: ConverterFormat::new(16, 3.3),
            amplifier: ConverterFormat::new(12, 3.3),
            amplifier_swing_v: [low, high],
            actuation_delay_samples: 1,
        };
        assert_eq!(board(0.2, 3.1).amplifier_codes(), Some([249, 3_847]));
        assert_eq!(board(0.0, 3.3).amplifier_codes(), Some([0, 4_095]));
        assert_eq!(board(-1.0, 5.0).amplifier_codes(), Some([0, 4_095]));
        // Exactly on a code: that code.
        let lsb = 3.3 / 4_096.0;
        assert_eq!(board(10.0 * lsb, 20.0 * lsb).amplifier_codes(), Some([10, 20]));
        assert_eq!(board(10.0 * lsb, 11.0 * lsb).amplifier_codes(), Some([10, 11]));
        // One code, none, a swing upside down, not a number.
        assert_eq!(board(10.0 * lsb, 10.5 * lsb).amplifier_codes(), None);
        assert_eq!(board(10.2 * lsb, 10.8 * lsb).amplifier_codes(), None);
        assert_eq!(board(3.1, 0.2).amplifier_codes(), None);
        assert_eq!(board(f64::NAN, 3.1).amplifier_codes(), None);
        assert_eq!(board(0.2, f64::INFINITY).amplifier_codes(), None);
        assert_eq!(board(f64::NEG_INFINITY, 3.1).amplifier_codes(), None);
    }

    #[test]
    fn formats_the_pipeline_cannot_use_are_invalid() {
        assert_eq!(ConverterFormat::new(12, 3.3).max_code, 4095);
        assert_eq!(ConverterFormat::new(24, 3.3).max_code, 0xFF_FFFF);
        for bad in [
            ConverterFormat::oversampled(12, 48, 0, 3.3),
            ConverterFormat::oversampled(12, 512, 0, 3.3),
            ConverterFormat::oversampled(12, 4, 15, 3.3),
            ConverterFormat::oversampled(0, 4, 0, 3.3),
            ConverterFormat::new(0, 3.3),
            ConverterFormat::new(25, 3.3),
            ConverterFormat::new(12, 0.0),
            ConverterFormat::new(12, f64::NAN),
            ConverterFormat { max_code: 4097, ..ConverterFormat::new(12, 3.3) },
            ConverterFormat { max_code: 2047, ..ConverterFormat::new(12, 3.3) },
        ] {
            assert!(!bad.is_valid(), "{bad:?}");
        }
    }
}
