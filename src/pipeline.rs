//! One sample of the signal chain, the same on the board and on the host (SPEC section 3a):
//!
//! ```text
//! probe code --front end--> y' (um) --spike gate------------------------------+
//! excitation --> target (V) --> clamp, slew --> DAC code --> u (V, as output)  |
//!                                                  u --> replicas --> u' (V)   |
//!                              (u', y') --> pre-filter W_p --> estimators <----+
//! ```
//!
//! The target is the excitation, or with [`Pipeline::step_adding`] the excitation added to an external command (a
//! scan, a controller's output).
//!
//! [`PipelineSettings`] is the physical description (sample rate, excitation, limits, filter designs, analog front
//! end), validated and designed once into a [`PipelineConfig`] in the working scalar. The configuration is a value
//! apart from the [`Pipeline`] state: the interrupt owns the state and reads the configuration; a new configuration
//! is swapped in whole between two samples.
//!
//! The command fed to the replicas is the one the DAC really outputs during the current sample period (after clamp,
//! slew limit and quantisation, decoded back to volts, and after the board's actuation delay), so the estimators
//! see the drive the stage received: `u_v` of sample `k` acts over `[t_k, t_(k+1))`, and `y_um` of sample `k`
//! responds to the drive up to `t_k`.
//!
//! ## Faults
//! A probe code at either end of the ADC range (within a margin) is an over-range; the same code for
//! `stuck_samples` consecutive samples while the command moves is a stuck probe. Either latches a fault: the
//! excitation stops, the output returns to its safe value through the slew limiter, and the estimators stop adapting
//! (they are not fed) until [`Pipeline::clear_faults`]. Each event is counted. A reading out of line with the
//! readings before it, by far more than the stage moves in a sample (a glitch at the ADC's input), is replaced by
//! the curve through them before any filter sees it, and counted ([`crate::filters::spike`]); it latches nothing.
//! Cost per sample, without estimators:
//! three replica biquads, two pre-filters, the excitation monitor (its shaping filter and averages: about 50
//! flops), the excitation, the limits, the spike gate: about 150 flops (QEMU: `pipeline_bare_f32`, 467 instructions).

use crate::estimator::{EstimatorBank, FilteredSample, PeLevel, SampleFilter};
use crate::excitation::{Excitation, ExcitationDesign, ExcitationState};
use crate::filters::design::{LagReplica, ReplicaDesign};
use crate::filters::spike::{SpikeBound, SpikeGate};
use crate::filters::{Biquad, BiquadState, Prefilter, PrefilterDesign};
use crate::hal::{BoardDescription, BoardFaults};
use crate::scalar::{fmax, fmin};
use crate::Real;

/// Probe side of the analog front end: sensor -> divider/level shift -> ADC.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProbeFrontEnd {
    /// Sensor sensitivity, um per sensor volt (reference probe: 5 um/V).
    pub um_per_v: f64,
    /// Divider gain, ADC volts per sensor volt (+-10 V onto 0-3.3 V: 0.165).
    pub adc_v_per_sensor_v: f64,
    /// ADC voltage of a 0 V sensor output (mid-rail: 1.65 V).
    pub adc_offset_v: f64,
}

impl Default for ProbeFrontEnd {
    fn default() -> Self {
        ProbeFrontEnd { um_per_v: 5.0, adc_v_per_sensor_v: 3.3 / 20.0, adc_offset_v: 1.65 }
    }
}

/// Amplifier side: DAC -> level shift/gain -> amplifier input.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AmplifierFrontEnd {
    /// DAC volts per amplifier-input volt (0-3.3 V onto +-10 V: 0.165).
    pub dac_v_per_command_v: f64,
    /// DAC voltage of a 0 V command (mid-rail: 1.65 V).
    pub dac_offset_v: f64,
}

impl Default for AmplifierFrontEnd {
    fn default() -> Self {
        AmplifierFrontEnd { dac_v_per_command_v: 3.3 / 20.0, dac_offset_v: 1.65 }
    }
}

impl AmplifierFrontEnd {
    /// The command, V, that a DAC output of `dac_v` gives at the amplifier's input.
    pub fn command_v(&self, dac_v: f64) -> f64 {
        (dac_v - self.dac_offset_v) / self.dac_v_per_command_v
    }

    /// Command, V, to the unrounded code of a DAC of `vpc_out` volts per code, in `T`:
    /// `(u * gain + offset) / (V/code)`.
    fn code_map<T: Real>(&self, vpc_out: f64) -> Affine<T> {
        Affine { scale: T::of(self.dac_v_per_command_v / vpc_out), offset: T::of(self.dac_offset_v / vpc_out) }
    }
}

/// Output limits, at the amplifier input.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OutputLimits {
    /// Lowest command, V.
    pub min_v: f64,
    /// Highest command, V.
    pub max_v: f64,
    /// Largest change per second, V/s. The default (25 000 V/s, 2.5 V per sample at 10 kHz) passes the paper's
    /// 2 V PRBS steps and turns a full-scale jump into an 8-sample ramp. At least [`OutputLimits::min_slew_v_per_s`]
    /// of the DAC's range: a fault's ramp to the safe value goes through it too.
    pub max_slew_v_per_s: f64,
    /// Where the output goes on a fault, V.
    pub safe_v: f64,
}

impl Default for OutputLimits {
    fn default() -> Self {
        OutputLimits { min_v: -10.0, max_v: 10.0, max_slew_v_per_s: 25_000.0, safe_v: 0.0 }
    }
}

impl OutputLimits {
    /// The longest a fault's (or `stop`'s) ramp to the safe value may take, s: from wherever the output is, the
    /// output is safe within this time. Without a bound a slew limit of 1e-30 V/s was accepted, and after a fault
    /// the output stayed where it was.
    pub const MAX_RAMP_TO_SAFE_S: f64 = 0.1;

    /// The limits within `reach` (the commands the DAC reaches, V, lowest first): the clamp in force.
    pub fn within(&self, [low, high]: [f64; 2]) -> [f64; 2] {
        [self.min_v.max(low), self.max_v.min(high)]
    }

    /// The slowest slew limit allowed with a DAC whose output spans `dac_span_v` (the commands of its first and last
    /// codes within its swing, V: [`PipelineSettings::dac_reach`]): its end farthest from the safe value, reached back
    /// in [`Self::MAX_RAMP_TO_SAFE_S`] (87.8 V/s on the board, -8.78 to 8.78 V about 0 V). The DAC's ends, not the
    /// clamp's: after the clamp is narrowed, the output ramps into it from wherever it was.
    pub fn min_slew_v_per_s(&self, dac_span_v: [f64; 2]) -> f64 {
        let [a, b] = dac_span_v.map(|v| libm::fabs(v - self.safe_v));
        a.max(b) / Self::MAX_RAMP_TO_SAFE_S
    }
}

/// Fault detection settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaultSettings {
    /// A probe code within this many codes of either end of the range (0 and the converter's
    /// [`crate::hal::ConverterFormat::max_code`]) is an over-range.
    pub over_range_margin_codes: u32,
    /// This many identical consecutive probe codes while the command moves is a stuck probe.
    pub stuck_samples: u32,
    /// A reading whose third difference from the readings before it exceeds this many times their mean (and
    /// [`FaultSettings::spike_floor_codes`]) is replaced before the filters see it ([`crate::filters::spike`]);
    /// 0: never (the gate off). Integers, as the other fault settings, which the console's settings hold in
    /// RAM several times over.
    pub spike_ratio: u16,
    /// ... and this many probe codes.
    pub spike_floor_codes: u16,
}

impl Default for FaultSettings {
    fn default() -> Self {
        FaultSettings {
            over_range_margin_codes: 16,
            stuck_samples: 1000,
            spike_ratio: crate::filters::spike::DEFAULT_RATIO,
            spike_floor_codes: 16,
        }
    }
}

/// The whole pipeline in physical terms. `Default` is the paper's experiment on a NUCLEO-G474RE front end.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PipelineSettings {
    /// Sample rate, Hz.
    pub sample_rate_hz: f64,
    /// What to drive the stage with.
    pub excitation: ExcitationDesign,
    /// Output clamp, slew limit and safe value.
    pub limits: OutputLimits,
    /// Replica of the reconstruction filter (between DAC and amplifier).
    pub reconstruction: ReplicaDesign,
    /// Replica of the anti-aliasing filter (between probe and ADC).
    pub antialias: ReplicaDesign,
    /// Replica of the amplifier's and sensor's fast lags (matched in band).
    pub lags: LagReplica,
    /// The identification pre-filter.
    pub prefilter: PrefilterDesign,
    /// Probe scaling.
    pub probe: ProbeFrontEnd,
    /// Amplifier scaling.
    pub amplifier: AmplifierFrontEnd,
    /// Fault detection.
    pub faults: FaultSettings,
    /// Which estimators of the bank run: bit `i` for the bank's `i`-th (all by default). The others are not fed.
    pub estimators: u8,
}

impl Default for PipelineSettings {
    fn default() -> Self {
        PipelineSettings {
            sample_rate_hz: 10_000.0,
            excitation: ExcitationDesign::PAPER_PRBS,
            limits: OutputLimits::default(),
            reconstruction: ReplicaDesign::default(),
            antialias: ReplicaDesign::default(),
            lags: LagReplica::default(),
            prefilter: PrefilterDesign::default(),
            probe: ProbeFrontEnd::default(),
            amplifier: AmplifierFrontEnd::default(),
            faults: FaultSettings::default(),
            estimators: u8::MAX,
        }
    }
}

/// A setting that cannot be designed, with what was wrong.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum SettingsError {
    /// Sample rate not finite and positive.
    SampleRate,
    /// A filter frequency not inside (0, Nyquist), or a lag pole not positive and finite: names the filter and
    /// carries the frequency, Hz, and the bound it must stay below (the Nyquist frequency; `None` for a lag pole,
    /// which may lie above it).
    FilterFrequency {
        /// The filter: `"reconstruction replica"`, `"anti-aliasing replica"`, `"lag replica"` or `"pre-filter"`.
        filter: &'static str,
        /// The frequency refused, Hz.
        hz: f64,
        /// The Nyquist frequency, Hz; `None` for a lag pole.
        below_hz: Option<f64>,
    },
    /// Pre-filter damping not positive.
    PrefilterDamping,
    /// `min_v < max_v`, `safe_v` inside, slew positive: one of these fails.
    Limits,
    /// A slew limit so slow that a fault's ramp to the safe value would outlast
    /// [`OutputLimits::MAX_RAMP_TO_SAFE_S`]; carries the slowest allowed, V/s.
    SlowSlew(f64),
    /// A front-end gain is zero or not finite; names the side.
    FrontEnd(&'static str),
    /// A converter format with 0 or more than 24 bits, a non-positive full scale or a largest code outside its bits
    /// ([`crate::hal::ConverterFormat::is_valid`]), or a DAC swing
    /// ([`BoardDescription::amplifier_swing_v`]) that holds fewer than two of its codes.
    Converter,
    /// The safe value is beyond what the DAC reaches with this front end ([`PipelineSettings::dac_reach`]); carries
    /// that reach, V.
    DacReach([f64; 2]),
    /// An actuation delay other than 0 or 1 sample.
    ActuationDelay,
    /// Excitation frequency or amplitude out of range.
    Excitation,
    /// A filter whose design at these frequencies is not a stable filter with finite coefficients in the working
    /// scalar; names the filter.
    Unrealisable(&'static str),
}

impl core::fmt::Display for SettingsError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            SettingsError::SampleRate => write!(f, "sample rate must be a positive number of Hz"),
            SettingsError::FilterFrequency { filter, hz, below_hz: Some(nyquist) } => write!(
                f,
                "{filter}: {} Hz: frequencies must be positive and below the Nyquist frequency, {} Hz",
                crate::text::Num(*hz, 6),
                crate::text::Num(*nyquist, 6)
            ),
            SettingsError::FilterFrequency { filter, hz, below_hz: None } => {
                write!(f, "{filter}: a pole at {} Hz: poles must be positive and finite", crate::text::Num(*hz, 6))
            }
            SettingsError::PrefilterDamping => {
                write!(f, "pre-filter damping ratio must be positive")
            }
            SettingsError::Limits => {
                write!(f, "output limits need min_v < max_v, safe_v between them, and a positive slew limit")
            }
            SettingsError::SlowSlew(min) => write!(
                f,
                "slew limit: at least {} V/s, so that after a fault the output reaches its safe value within {} s \
                 from anywhere in the DAC's range",
                crate::text::Num(*min, 6),
                crate::text::Num(OutputLimits::MAX_RAMP_TO_SAFE_S, 3)
            ),
            SettingsError::FrontEnd(which) => {
                write!(f, "{which} front end: gains must be finite and non-zero")
            }
            SettingsError::Converter => {
                write!(
                    f,
                    "converter format: 1 to 24 bits, a positive full scale, a largest code within the bits, and a \
                     DAC swing of two codes or more"
                )
            }
            SettingsError::DacReach([low, high]) => write!(
                f,
                "safe value: the DAC reaches {} V to {} V with this front end, and the safe value must lie between",
                crate::text::Num(*low, 6),
                crate::text::Num(*high, 6)
            ),
            SettingsError::ActuationDelay => write!(f, "board actuation delay must be 0 or 1 sample"),
            SettingsError::Excitation => {
                write!(f, "excitation: frequencies below Nyquist, finite amplitude and offset")
            }
            SettingsError::Unrealisable(which) => write!(
                f,
                "{which}: no stable filter with finite coefficients at these frequencies (one too close to 0 Hz \
                 for the sample rate)"
            ),
        }
    }
}

/// An affine map `y = scale * x + offset`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Affine<T> {
    /// Slope.
    pub scale: T,
    /// Intercept.
    pub offset: T,
}

impl<T: Real> Affine<T> {
    #[inline(always)]
    fn apply(&self, x: T) -> T {
        self.scale * x + self.offset
    }
}

/// The designed pipeline in the working scalar (the configuration the interrupt reads).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PipelineConfig<T> {
    /// Excitation generator.
    pub excitation: Excitation<T>,
    /// Reconstruction-filter replica.
    pub reconstruction: Biquad<T>,
    /// Anti-aliasing-filter replica.
    pub antialias: Biquad<T>,
    /// Amplifier and sensor lag replica.
    pub lags: Biquad<T>,
    /// Pre-filter.
    pub prefilter: Prefilter<T>,
    /// Probe code -> um.
    pub probe: Affine<T>,
    /// Command V -> DAC code (before rounding).
    pub amplifier: Affine<T>,
    /// DAC code -> command V.
    pub amplifier_inverse: Affine<T>,
    /// Largest DAC code. The codes written stay within the DAC's swing ([`BoardDescription::amplifier_codes`])
    /// without a clamp of their own: `min_v` and `max_v` are within the commands of its first and last codes, and
    /// the encoding of a command there rounds to that code (half a code to spare: the f32 error is a thousandth).
    pub dac_max_code: u32,
    /// Lowest probe code that is not over-range.
    pub probe_low_code: u32,
    /// Highest probe code that is not over-range.
    pub probe_high_code: u32,
    /// Clamp, V.
    pub min_v: T,
    /// Clamp, V.
    pub max_v: T,
    /// Slew limit, V per sample.
    pub max_step_v: T,
    /// Safe output, V.
    pub safe_v: T,
    /// Stuck-probe threshold, samples.
    pub stuck_samples: u32,
    /// The spike gate's bounds.
    pub spike: SpikeBound<T>,
    /// Samples between writing a DAC code and its output (0 or 1).
    pub actuation_delay_samples: u8,
    /// Sample period, s.
    pub sample_period_s: f64,
    /// The command's step for one DAC code, V: the rounding the excitation monitor discounts.
    pub command_lsb_v: f64,
    /// Samples the estimators are not fed after a change of the pre-filter ([`Pipeline::retarget`]) and after a
    /// latched fault: ten of the pre-filter's slowest time constants ([`PrefilterDesign::slowest_time_constant_s`];
    /// 35 ms for the default), after which what its state held from before (another filter's output, a fault's
    /// readings) is below e^-10 = 5e-5 of what it was, and the filtered signals are the stage's again.
    pub prefilter_settle_samples: u32,
    /// Which estimators are fed (bit `i`: the bank's `i`-th).
    pub estimators: u8,
}

/// Whether `hz` lies inside (0, `nyquist`).
fn in_band(hz: f64, nyquist: f64) -> bool {
    hz.is_finite() && hz > 0.0 && hz < nyquist
}

/// `x` rounded up, as a count (`as u32` saturates: 0 for NaN and below 0). Not libm's `ceil`: 200 B of flash for one
/// use in the designs.
fn ceil_u32(x: f64) -> u32 {
    let n = x as u32;
    if (n as f64) < x && n < u32::MAX {
        n + 1
    } else {
        n
    }
}

impl PipelineSettings {
    /// These settings with the identification pre-filter `p`, and the three filter replicas matched to the analog
    /// chain at its centre `f_p` (the bilinear replicas pre-warped there, the lag replica exact there): where the
    /// pre-filter passes the estimators' information, as the defaults match both at 450 Hz for the paper's stage.
    /// On another stage a pre-filter moved to its resonance alone kept the replicas' error of the old band: on a
    /// simulated stage at 1 kHz, `b0` +6 % in all four estimators; with the replicas moved too +0.4 and +0.6 % in the
    /// EKFs, +4 % in the RLS and the ARX (the board's second mode at 1.9 kHz), within 0.4 % in all four without it.
    pub fn with_prefilter(mut self, p: PrefilterDesign) -> Self {
        self.prefilter = p;
        self.reconstruction.prewarp_hz = p.f_p_hz;
        self.antialias.prewarp_hz = p.f_p_hz;
        self.lags.match_hz = p.f_p_hz;
        self
    }

    /// These settings with what of `tuning` is the pipeline's: the stage's pre-filter ([`Self::with_prefilter`])
    /// and the spike gate's ratio. The console, `identify` and `commands` take a tuning to the pipeline through it.
    pub fn with_stage_of(self, tuning: &crate::estimators::Tuning) -> Self {
        let mut s = self.with_prefilter(tuning.rls.prefilter);
        s.faults.spike_ratio = tuning.spike_ratio;
        s
    }

    /// The DAC's codes within its swing ([`BoardDescription::amplifier_codes`]) and the commands they give with
    /// this amplifier front end, V, lowest first: what the output can reach (with the defaults on the board, codes
    /// 249 to 3847, -8.78 to 8.78 V). The clamp in force is the output limits within it. `None` if the swing holds
    /// no two codes.
    pub fn dac_reach(&self, board: &BoardDescription) -> Option<([u32; 2], [f64; 2])> {
        let codes = board.amplifier_codes()?;
        let [p, q] = codes.map(|c| self.amplifier.command_v(c as f64 * board.amplifier.volts_per_code()));
        // An inverting front end (a negative gain) turns the order round.
        Some((codes, [p.min(q), p.max(q)]))
    }

    /// The clamp in force, V: the output limits within [`Self::dac_reach`]. `None` where that is.
    pub fn clamp_v(&self, board: &BoardDescription) -> Option<[f64; 2]> {
        Some(self.limits.within(self.dac_reach(board)?.1))
    }

    /// The DAC code of the safe output, in `T`: [`PipelineConfig::safe_code`] of [`Self::design`]'s configuration,
    /// without the design (which takes milliseconds on the board's reset clock), for the start-up to put the output
    /// safe before anything else. Settings the design refuses still give a code (the DAC's nearest to the safe value).
    pub fn safe_code<T: Real>(&self, board: &BoardDescription) -> u32 {
        let dac = &board.amplifier;
        code_of(&self.amplifier.code_map(dac.volts_per_code()), dac.max_code, T::of(self.limits.safe_v))
    }

    /// The sample rate, then every filter's frequencies: the first of [`Self::design`]'s checks, without the design.
    pub fn check_frequencies(&self) -> Result<(), SettingsError> {
        let fs = self.sample_rate_hz;
        if !(fs.is_finite() && fs > 0.0) {
            return Err(SettingsError::SampleRate);
        }
        let nyquist = fs / 2.0;
        let (rec, aa, lag, pf) = ("reconstruction replica", "anti-aliasing replica", "lag replica", "pre-filter");
        let (r, a, p) = (&self.reconstruction, &self.antialias, &self.prefilter);
        let band = |filter, hz| match in_band(hz, nyquist) {
            true => Ok(()),
            false => Err(SettingsError::FilterFrequency { filter, hz, below_hz: Some(nyquist) }),
        };
        // The pre-filter's first: the replicas are matched at its `f_p` ([`Self::with_stage_of`]), so a refusal of that
        // names what was set.
        let filters = [
            (pf, p.f_lc_hz),
            (pf, p.f_p_hz),
            (rec, r.cutoff_hz),
            (rec, r.prewarp_hz),
            (aa, a.cutoff_hz),
            (aa, a.prewarp_hz),
            (lag, self.lags.match_hz),
        ];
        for (filter, hz) in filters {
            band(filter, hz)?;
        }
        for &hz in self.lags.poles_hz.iter().flatten() {
            if !(hz.is_finite() && hz > 0.0) {
                return Err(SettingsError::FilterFrequency { filter: lag, hz, below_hz: None });
            }
        }
        Ok(())
    }

    /// Validate and design for the board's converters.
    #[inline(never)]
    pub fn design<T: Real>(&self, board: &BoardDescription) -> Result<PipelineConfig<T>, SettingsError> {
        let (probe_adc, amplifier_dac) = (board.probe, board.amplifier);
        if board.actuation_delay_samples > 1 {
            return Err(SettingsError::ActuationDelay);
        }
        self.check_frequencies()?;
        let (fs, nyquist) = (self.sample_rate_hz, self.sample_rate_hz / 2.0);
        if !(self.prefilter.zeta_p.is_finite() && self.prefilter.zeta_p > 0.0) {
            return Err(SettingsError::PrefilterDamping);
        }
        let l = &self.limits;
        let finite = [l.min_v, l.max_v, l.max_slew_v_per_s, l.safe_v].iter().all(|x| x.is_finite());
        if !(finite && l.min_v < l.max_v && l.safe_v >= l.min_v && l.safe_v <= l.max_v && l.max_slew_v_per_s > 0.0) {
            return Err(SettingsError::Limits);
        }
        let nonzero = |x: f64| x.is_finite() && x != 0.0;
        let (p, a) = (&self.probe, &self.amplifier);
        if !(nonzero(p.um_per_v) && nonzero(p.adc_v_per_sensor_v) && p.adc_offset_v.is_finite()) {
            return Err(SettingsError::FrontEnd("probe"));
        }
        if !(nonzero(a.dac_v_per_command_v) && a.dac_offset_v.is_finite()) {
            return Err(SettingsError::FrontEnd("amplifier"));
        }
        for c in [probe_adc, amplifier_dac] {
            if !c.is_valid() {
                return Err(SettingsError::Converter);
            }
        }
        let (_, reach) = self.dac_reach(board).ok_or(SettingsError::Converter)?;
        // The safe value must be an output the DAC can give (the limits then overlap what it reaches).
        if !(l.safe_v >= reach[0] && l.safe_v <= reach[1]) {
            return Err(SettingsError::DacReach(reach));
        }
        // The output cannot leave the DAC's reach, so that is where a fault's ramp may start from.
        let min_slew = l.min_slew_v_per_s(reach);
        let clamp = l.within(reach);
        // The floor as the message prints it (6 digits) is accepted.
        if l.max_slew_v_per_s < min_slew * (1.0 - 1e-6) {
            return Err(SettingsError::SlowSlew(min_slew));
        }
        let e = &self.excitation;
        let below_nyquist = |hz| in_band(hz, nyquist);
        let freq_ok = match e.waveform {
            crate::excitation::Waveform::Sine { freq_hz } => below_nyquist(freq_hz),
            crate::excitation::Waveform::Triangle { freq_hz, max_hz } => below_nyquist(freq_hz) && max_hz.is_finite(),
            crate::excitation::Waveform::Multisine { f_lo_hz, f_hi_hz } => {
                below_nyquist(f_lo_hz) && below_nyquist(f_hi_hz)
            }
            _ => true,
        };
        if !(freq_ok && e.amplitude_v.is_finite() && e.offset_v.is_finite()) {
            return Err(SettingsError::Excitation);
        }

        // code -> um: ((code * V/code) - offset) / divider * um/V
        let k_probe = p.um_per_v / p.adc_v_per_sensor_v;
        let vpc_in = probe_adc.volts_per_code();
        let vpc_out = amplifier_dac.volts_per_code();
        let margin = self.faults.over_range_margin_codes;
        let um_per_code = libm::fabs(vpc_in * k_probe);
        // Each filter as it will run, checked: the frequency ranges above do not guarantee a design (the lag
        // replica matched at 1e-6 Hz comes out NaN, and would feed NaN to every estimator on every sample).
        let (reconstruction, antialias, lags) =
            (self.reconstruction.design(fs).cast(), self.antialias.design(fs).cast(), self.lags.design(fs).cast());
        let prefilter = self.prefilter.design(1.0 / fs);
        for (name, section) in
            [("reconstruction replica", &reconstruction), ("anti-aliasing replica", &antialias), ("lag replica", &lags)]
        {
            if !section.is_stable() {
                return Err(SettingsError::Unrealisable(name));
            }
        }
        if !prefilter.is_finite() {
            return Err(SettingsError::Unrealisable("pre-filter"));
        }
        Ok(PipelineConfig {
            excitation: e.design(fs),
            reconstruction,
            antialias,
            lags,
            prefilter,
            probe: Affine { scale: T::of(vpc_in * k_probe), offset: T::of(-p.adc_offset_v * k_probe) },
            amplifier: a.code_map(vpc_out),
            amplifier_inverse: Affine {
                scale: T::of(vpc_out / a.dac_v_per_command_v),
                offset: T::of(-a.dac_offset_v / a.dac_v_per_command_v),
            },
            dac_max_code: amplifier_dac.max_code,
            probe_low_code: margin,
            probe_high_code: probe_adc.max_code.saturating_sub(margin),
            min_v: T::of(clamp[0]),
            max_v: T::of(clamp[1]),
            max_step_v: T::of(l.max_slew_v_per_s / fs),
            safe_v: T::of(l.safe_v),
            stuck_samples: self.faults.stuck_samples.max(2),
            spike: SpikeBound::new(self.faults.spike_ratio, f64::from(self.faults.spike_floor_codes) * um_per_code),
            actuation_delay_samples: board.actuation_delay_samples,
            sample_period_s: 1.0 / fs,
            command_lsb_v: vpc_out / libm::fabs(a.dac_v_per_command_v),
            prefilter_settle_samples: ceil_u32(10.0 * self.prefilter.slowest_time_constant_s() * fs),
            estimators: self.estimators,
        })
    }
}

impl<T: Real> PipelineConfig<T> {
    /// The DAC code of the safe output: what a fault handler writes when the pipeline cannot run.
    pub fn safe_code(&self) -> u32 {
        encode(self, self.safe_v).0
    }

    /// The command, V, that DAC code `code` outputs (what the pipeline takes a code it wrote for; a recording's `u`).
    pub fn command_of_code(&self, code: u32) -> T {
        self.amplifier_inverse.apply(num_traits::cast::<u32, T>(code).unwrap_or_else(T::zero))
    }
}

/// Fault bits. A latched fault stops the excitation until cleared. In the defmt log by name, as `status` prints them:
/// `none`, or the names of [`Faults::NAMES`] that are set, comma-separated.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Faults(pub u8);

impl Faults {
    /// The probe code reached either end of the ADC range.
    pub const PROBE_OVER_RANGE: Faults = Faults(1 << 0);
    /// The probe code did not change for `stuck_samples` while the command moved.
    pub const PROBE_STUCK: Faults = Faults(1 << 1);
    /// The command (the excitation, plus the external command if any) was not finite: a configuration error, or a
    /// controller's; the output went safe.
    pub const COMMAND_NOT_FINITE: Faults = Faults(1 << 2);

    /// No fault.
    pub const fn is_empty(self) -> bool {
        self.0 == 0
    }
    /// All of `other`'s bits are set.
    pub const fn contains(self, other: Faults) -> bool {
        self.0 & other.0 == other.0
    }

    /// Each fault with its name in `status` and in the log.
    pub const NAMES: [(Faults, &'static str); 3] = [
        (Faults::PROBE_OVER_RANGE, "over_range"),
        (Faults::PROBE_STUCK, "stuck"),
        (Faults::COMMAND_NOT_FINITE, "not_finite"),
    ];

    /// The names of the faults set, in [`Faults::NAMES`]' order.
    pub fn names(self) -> impl Iterator<Item = &'static str> {
        Faults::NAMES.into_iter().filter(move |&(bit, _)| self.contains(bit)).map(|(_, name)| name)
    }
}

#[cfg(target_os = "none")]
impl defmt::Format for Faults {
    fn format(&self, f: defmt::Formatter) {
        let mut names = self.names();
        match names.next() {
            None => defmt::write!(f, "none"),
            Some(first) => {
                defmt::write!(f, "{=str}", first);
                for name in names {
                    defmt::write!(f, ",{=str}", name);
                }
            }
        }
    }
}

impl core::ops::BitOrAssign for Faults {
    fn bitor_assign(&mut self, o: Faults) {
        self.0 |= o.0;
    }
}

/// Counts of fault events since start. Each saturates at `u32::MAX` (a count a sample reaches it after five days).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub struct FaultCounters {
    /// Samples with an over-range probe code.
    pub probe_over_range: u32,
    /// Stuck-probe detections.
    pub probe_stuck: u32,
    /// Non-finite commands replaced by the safe value.
    pub command_not_finite: u32,
    /// Samples whose command was written after the next sample instant (board-reported).
    pub deadline_misses: u32,
    /// Lost probe conversions (board-reported).
    pub adc_overruns: u32,
    /// Probe readings the spike gate replaced ([`crate::filters::spike`]): out of line with the readings before
    /// them, by far more than the stage moves in a sample. A few over hours are glitches the estimators did not
    /// see; a count that keeps climbing means a noisy or loose connection at the ADC's input.
    pub spikes: u32,
    /// Samples whose command the output limits changed while the estimators were fed: the excitation (with the
    /// external command) clamped to `min_v..max_v` or slew-limited, so that the stage runs on a distorted input.
    /// The estimators see the command as written and stay consistent, but the distortion's sharp corners put the
    /// input's power where the stage model fits least: on the simulated board (its second mode) a sine clipped by
    /// the clamp moved the hybrid filter by 1.7 % in half a second and 1.6 % more by 10 s (0.06 % and 0.3 % with the
    /// second mode switched off; `hal-sim/tests/ekf_health.rs`).
    /// A step of the command (`excite constant 5` from rest) counts a sample or two; a count that keeps climbing
    /// means the excitation does not fit the limits.
    pub limited: u32,
}

/// What one sample produced.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SampleOutput<T> {
    /// Code written to the amplifier DAC (it takes effect after the board's actuation delay).
    pub dac_code: u32,
    /// The command in effect over this sample period, as the DAC outputs it, V.
    pub u_v: T,
    /// The probe reading, um (as read: before the spike gate).
    pub y_um: T,
    /// The probe code it came from.
    pub probe_code: u32,
    /// Latched faults after this sample.
    pub faults: Faults,
    /// What the estimators were fed: `None` while a fault is latched, and for
    /// [`PipelineConfig::prefilter_settle_samples`] after it and after a pre-filter change ([`Pipeline::retarget`]).
    pub estimator_input: Option<FilteredSample<T>>,
    /// The board's faults of this sample (filled in by [`crate::hal::run_sample`]).
    pub board_faults: BoardFaults,
}

/// The per-sample state.
#[derive(Clone, Debug)]
pub struct Pipeline<T, E> {
    excitation: ExcitationState,
    /// The last command written (as the DAC outputs it), V: with an actuation delay of one sample, the command in
    /// effect over the current period.
    command_v: T,
    /// The slew limiter's last output before the DAC's rounding, V: what the next step starts from. From the rounded
    /// command, a step under half a DAC code (a slew limit under 24 V/s on the board) rounded back to the same code
    /// every sample, and the output never moved, not even to its safe value after a fault.
    slewed_v: T,
    reconstruction: BiquadState<T>,
    antialias: BiquadState<T>,
    lags: BiquadState<T>,
    spike: SpikeGate<T>,
    sample_filter: SampleFilter<T>,
    last_probe_code: u32,
    same_code_run: u32,
    /// Samples left before the estimators are fed again after a pre-filter change or a fault.
    settle_left: u32,
    /// The last external command ([`Pipeline::step_adding`]), V: whether it moved.
    external_v: T,
    faults: Faults,
    counters: FaultCounters,
    samples: u64,
    /// The estimator slot.
    pub estimators: E,
}

impl<T: Real, E: EstimatorBank<T>> Pipeline<T, E> {
    /// A pipeline at rest (output at the safe value of `cfg`) with the given estimators.
    pub fn new(cfg: &PipelineConfig<T>, estimators: E) -> Self {
        Pipeline {
            excitation: ExcitationState::default(),
            command_v: cfg.safe_v,
            slewed_v: cfg.safe_v,
            reconstruction: BiquadState::default(),
            antialias: BiquadState::default(),
            lags: BiquadState::default(),
            spike: SpikeGate::new(),
            sample_filter: SampleFilter::new(cfg.sample_period_s, cfg.command_lsb_v),
            last_probe_code: u32::MAX,
            same_code_run: 0,
            settle_left: 0,
            external_v: T::zero(),
            faults: Faults::default(),
            counters: FaultCounters::default(),
            samples: 0,
            estimators,
        }
    }

    /// One sample: `probe_code` is this sample's conversion; returns the DAC code for the coming period.
    #[inline]
    pub fn step(&mut self, cfg: &PipelineConfig<T>, probe_code: u32) -> SampleOutput<T> {
        self.step_with(cfg, probe_code, None::<fn(T) -> T>, |_| {})
    }

    /// One sample with the excitation added to an external command, V at the amplifier's input: `command(y_um)`,
    /// given this sample's probe reading, um. A scan trajectory (`|_| scan_v`), or a controller built on the estimates
    /// (SPEC section 5), which sees the reading with no delay added: its command is written with the excitation's,
    /// in effect from the next sample instant on the G474 (`actuation_delay_samples`). The sum goes
    /// through the same limits (clamp, slew), the estimators see it as the stage's input, and while a fault is
    /// latched the output goes to its safe value, the external command ignored like the excitation. The
    /// stuck-probe check arms on a sample whose external command changed, as it does while the excitation runs (a
    /// held command may legitimately give a constant reading); a controller whose command follows the reading alone
    /// holds still when the probe sticks, so without the excitation nothing arms it.
    ///
    /// The estimators take the sum for the stage's input, which is right whatever the command. A command computed
    /// from the probe (a feedback controller) makes the identification closed-loop: its input is then correlated
    /// with the probe's noise. `tests/pipeline.rs` measures a scan and a proportional feedback on the simulated
    /// board; a loop the excitation does not dominate, or that saturates, is not tested.
    #[inline]
    pub fn step_adding(
        &mut self,
        cfg: &PipelineConfig<T>,
        probe_code: u32,
        command: impl FnOnce(T) -> T,
    ) -> SampleOutput<T> {
        self.step_with(cfg, probe_code, Some(command), |_| {})
    }

    /// [`Pipeline::step`] (`None`) or [`Pipeline::step_adding`], handing the DAC code to `write` as soon as it is
    /// known, before the filters and the estimators run: on the board the code must reach the DAC by the next
    /// sample instant, and the estimators need not ([`crate::hal::run_sample`]).
    #[inline(always)]
    pub(crate) fn step_with(
        &mut self,
        cfg: &PipelineConfig<T>,
        probe_code: u32,
        command: Option<impl FnOnce(T) -> T>,
        write: impl FnOnce(u32),
    ) -> SampleOutput<T> {
        self.samples = self.samples.wrapping_add(1);
        let y_um = cfg.probe.apply(num_traits::cast::<u32, T>(probe_code).unwrap_or_else(T::zero));
        let external_v = command.map(|f| f(y_um));
        let external_moved = match external_v {
            Some(v) => {
                let moved = v != self.external_v;
                self.external_v = v;
                moved
            }
            None => false,
        };
        self.check_probe(cfg, probe_code, external_moved);

        let mut target = if self.faults.is_empty() {
            let excitation = cfg.excitation.next(&mut self.excitation);
            match external_v {
                Some(v) => v + excitation,
                None => excitation,
            }
        } else {
            cfg.safe_v
        };
        if !target.is_finite() {
            self.faults |= Faults::COMMAND_NOT_FINITE;
            self.counters.command_not_finite = self.counters.command_not_finite.saturating_add(1);
            target = cfg.safe_v;
        }
        let clamped = fmin(fmax(target, cfg.min_v), cfg.max_v);
        let wanted_step = clamped - self.slewed_v;
        let step = fmin(fmax(wanted_step, -cfg.max_step_v), cfg.max_step_v);
        let slew_limited = step != wanted_step;
        let limited = clamped != target || slew_limited;
        self.counters.limited = self.counters.limited.saturating_add(u32::from(limited && self.faults.is_empty()));
        self.slewed_v = if slew_limited { self.slewed_v + step } else { clamped };
        let (dac_code, written_v) = encode(cfg, self.slewed_v);
        write(dac_code);
        let u_v = if cfg.actuation_delay_samples == 0 { written_v } else { self.command_v };
        self.command_v = written_v;

        let estimator_input = if !E::FILTERED {
            None
        } else {
            let sample = self.filter(cfg, u_v, y_um);
            // The filters run on a fault's readings too (they never hold stale state), so from the fault's end on
            // the pre-filter still rings with them for a while.
            if !self.faults.is_empty() {
                self.settle_left = cfg.prefilter_settle_samples;
                None
            } else if self.settle_left > 0 {
                self.settle_left -= 1;
                if self.settle_left == 0 {
                    // Fed again from the next sample: what the estimators hold of the signals is from before.
                    self.estimators.resume();
                }
                None
            } else {
                self.estimators.update_selected(&sample, cfg.estimators);
                Some(sample)
            }
        };
        SampleOutput {
            dac_code,
            u_v,
            y_um,
            probe_code,
            faults: self.faults,
            estimator_input,
            board_faults: BoardFaults::default(),
        }
    }

    fn check_probe(&mut self, cfg: &PipelineConfig<T>, code: u32, external_moved: bool) {
        if code < cfg.probe_low_code || code > cfg.probe_high_code {
            self.faults |= Faults::PROBE_OVER_RANGE;
            self.counters.probe_over_range = self.counters.probe_over_range.saturating_add(1);
        }
        // Stuck: the code does not move although the command did (a constant command legitimately gives a
        // constant reading once the noise is below one code).
        if code == self.last_probe_code && (external_moved || cfg.excitation.is_active()) {
            self.same_code_run = self.same_code_run.saturating_add(1);
            if self.same_code_run.saturating_add(1) == cfg.stuck_samples {
                self.faults |= Faults::PROBE_STUCK;
                self.counters.probe_stuck = self.counters.probe_stuck.saturating_add(1);
            }
        } else {
            self.same_code_run = 0;
        }
        self.last_probe_code = code;
    }

    /// The command in effect `u_v` through the replicas, the reading `y_um` through the spike gate, both through
    /// the pre-filter, and the filtered input's excitation measured once for every estimator (this runs every
    /// sample, faults or not, so the filters never hold stale state).
    #[inline]
    fn filter(&mut self, cfg: &PipelineConfig<T>, u_v: T, y_um: T) -> FilteredSample<T> {
        let rc = cfg.reconstruction.update(&mut self.reconstruction, u_v);
        let u_replica = cfg.lags.update(&mut self.lags, cfg.antialias.update(&mut self.antialias, rc));
        let y = self.spike.pass(&cfg.spike, y_um, &mut self.counters.spikes);
        self.sample_filter.sample(&cfg.prefilter, u_replica, y)
    }

    /// One sample of a recording: `u_v` the command in effect over the sample period, `y_um` the reading at its
    /// start (the convention of `simulate`'s output and of the firmware's recording). The same spike gate, filters
    /// and estimators as [`Pipeline::step`], without excitation, limits or fault checks. A pipeline of
    /// [`crate::estimator::Unfiltered`], which has nothing to replay to, does not compile with it:
    ///
    /// ```compile_fail
    /// use nanopos_id::estimator::{FilteredSample, Unfiltered};
    /// use nanopos_id::pipeline::{Pipeline, PipelineConfig};
    /// type Replay = fn(&mut Pipeline<f64, Unfiltered>, &PipelineConfig<f64>, f64, f64) -> FilteredSample<f64>;
    /// let _: Replay = Pipeline::replay;
    /// ```
    #[inline]
    pub fn replay(&mut self, cfg: &PipelineConfig<T>, u_v: T, y_um: T) -> FilteredSample<T> {
        const { assert!(E::FILTERED, "replay feeds estimators: an Unfiltered pipeline has none") };
        let sample = self.filter(cfg, u_v, y_um);
        self.estimators.update(&sample);
        sample
    }

    /// The configuration `from` is replaced by `to` from the next sample on. Another pre-filter takes the state over
    /// at its own scale ([`crate::estimator::SampleFilter::retarget`]; the replicas' direct-form state needs
    /// nothing), and the estimators are not fed for its [`PipelineConfig::prefilter_settle_samples`]. The state is
    /// the old filter's, not the new one's response to the signals: until the new filter's own poles wash it out,
    /// the filtered input and reading are not related by the stage's model. Fed at once, the restarted EKFs, which
    /// take their states from the first sample they see, started from that transient: after `tune prefilter 200 600
    /// 0.2` on the paper's PRBS, the reading 15 um off, they were within 1 % of `a0` and `b0` only 1.16 s later
    /// (0.1 s with the wait; `tests/instrument.rs`). Unchanged, the pre-filter stays as it is, and so does the
    /// feeding.
    pub fn retarget(&mut self, from: &PipelineConfig<T>, to: &PipelineConfig<T>) {
        self.sample_filter.retarget(&from.prefilter, &to.prefilter);
        if from.prefilter != to.prefilter {
            self.settle_left = to.prefilter_settle_samples;
        }
    }

    /// Count the board's faults of a sample. They do not latch: a late sample is reported, not a reason to stop.
    pub fn count_board_faults(&mut self, f: BoardFaults) {
        self.counters.deadline_misses = self.counters.deadline_misses.saturating_add(f.deadline_missed as u32);
        self.counters.adc_overruns = self.counters.adc_overruns.saturating_add(f.adc_overrun as u32);
    }

    /// The command in effect over the next sample period is `v`, V, not the one just written: that one missed its
    /// deadline, and the DAC holds the one written before it (see [`crate::instrument::Instrument::sample`]). The
    /// slew limiter steps from `v` too: from the skipped one, the next code would follow it by a step and the output
    /// jump from `v` by two (the DAC never puts the skipped code out).
    #[cold]
    pub fn hold_command(&mut self, v: T) {
        self.command_v = v;
        self.slewed_v = v;
    }

    /// Latched faults.
    pub fn faults(&self) -> Faults {
        self.faults
    }

    /// Fault event counts since start.
    pub fn fault_counters(&self) -> FaultCounters {
        self.counters
    }

    /// Clear the latched faults; the excitation resumes where it stopped.
    pub fn clear_faults(&mut self) {
        self.faults = Faults::default();
        self.same_code_run = 0;
    }

    /// Samples processed since start.
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// The last command written, V.
    pub fn command_v(&self) -> T {
        self.command_v
    }

    /// The excitation monitor's level of the input so far ([`crate::estimator::PeMonitor`]): what each estimator
    /// compares with its floor.
    pub fn excitation_level(&self) -> PeLevel<T> {
        self.sample_filter.excitation()
    }
}

/// Command V -> (DAC code, the volts that code really outputs). Saturates at the code range (the clamp keeps the
/// command within the DAC's swing: [`PipelineConfig::dac_max_code`]).
#[inline]
fn encode<T: Real>(cfg: &PipelineConfig<T>, u_v: T) -> (u32, T) {
    let code = code_of(&cfg.amplifier, cfg.dac_max_code, u_v);
    (code, cfg.command_of_code(code))
}

/// The DAC code nearest `u_v` through `to_code`, within `0..=max_code`.
#[inline(always)]
fn code_of<T: Real>(to_code: &Affine<T>, max_code: u32, u_v: T) -> u32 {
    let raw = to_code.apply(u_v).round();
    if raw <= T::zero() {
        0
    } else {
        num_traits::cast::<T, u32>(raw).unwrap_or(max_code).min(max_code)
    }
}

#[cfg(test)]
mod tests {
    use super::ceil_u32;

    #[test]
    fn a_count_is_rounded_up_and_saturates() {
        assert_eq!(ceil_u32(353.7), 354);
        assert_eq!(ceil_u32(354.0), 354);
        assert_eq!(ceil_u32(0.2), 1);
        assert_eq!(ceil_u32(0.0), 0);
        assert_eq!(ceil_u32(-3.0), 0);
        assert_eq!(ceil_u32(f64::NAN), 0);
        assert_eq!(ceil_u32(1e30), u32::MAX);
        assert_eq!(ceil_u32(f64::INFINITY), u32::MAX);
    }
}
