//! The simulated NUCLEO-G474RE: the [`Plant`] behind the same [`StageBoard`] trait as the real board, with the
//! converters and the analog front end in between.
//!
//! - **DAC**: 12 bits over 0-3.3 V, its output within the buffered G474 DAC's specified swing (0.2 to 3.1 V: a code
//!   beyond gives the swing's end); the output is decoded back to the amplifier-input voltage through the front end
//!   (0-3.3 V onto +-10 V, so -8.79 to 8.79 V) and held over the sample period. Like the firmware's timer-triggered
//!   DAC, a code takes effect at the next sample instant (`actuation_delay_samples = 1`; 0 applies it at once).
//! - **ADC timing**: the firmware centres the oversampling window on the sample instant, so the reading is the
//!   displacement at `t_k` (the window's averaging, a 0.03 % droop at 450 Hz, is not modelled).
//! - **Noise**: 1.25 nm RMS on the displacement (the paper's noise floor), Gaussian, from the seed; optionally with
//!   heavier tails at the same RMS (Student's t, [`BoardSettings::noise_tail_dof`]: a real probe's noise is not
//!   known to be Gaussian), and mains pickup, sinusoids on the reading ([`BoardSettings::hum`]; none by default).
//! - **ADC**: the G474's 12-bit ADC with hardware oversampling: `ratio` conversions are accumulated and shifted right
//!   by `shift`, giving `12 + log2(ratio) - shift` bits (the firmware's 64x and shift 2: 16 bits, from 0 to
//!   `4095 * 64 / 4 = 65520`, where a reading beyond the reference stops). Each conversion carries its own
//!   input-referred noise (`conversion_noise_lsb`, in 12-bit LSB RMS; 1 LSB assumed); averaging divides it by
//!   `sqrt(ratio)`, and it dithers the 12-bit quantisation so the average resolves below one 12-bit code. The model
//!   draws the averaged noise directly (one normal per sample, not `ratio`) and rounds to the output code.
//!
//! Effective resolution with the defaults (probe +-10 V = +-50 um onto 0-3.3 V): one 12-bit code is 24.4 nm, one
//! 16-bit code 1.53 nm; averaged conversion noise 1 LSB12 / sqrt(64) = 3.05 nm RMS, output quantisation
//! 1.53 / sqrt(12) = 0.44 nm RMS; with the probe's 1.25 nm the floor is sqrt(1.25^2 + 3.05^2 + 0.44^2) = 3.3 nm RMS
//! ([`SimBoard::noise_floor_um`]; measured by the `noise_floor_at_rest_is_the_modelled_one` test). The ADC, not
//! the probe, sets it: 256x oversampling would give 2.0 nm but fills 90 us of each 100 us period (a 2.5-cycle
//! sampling time, which needs a buffered source), and an external 16-18-bit ADC over a narrower range is the way
//! to the probe's own 1.25 nm.

use crate::noise::NormalStream;
use crate::plant::{Plant, PlantSettings};
use nanopos_id::hal::{BoardDescription, BoardFaults, ConverterFormat, StageBoard};
use nanopos_id::pipeline::{AmplifierFrontEnd, ProbeFrontEnd};

/// The G474's ADC in oversampling mode.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdcModel {
    /// Native resolution, bits.
    pub native_bits: u8,
    /// Conversions accumulated per sample (1 to 256, a power of two).
    pub oversampling: u32,
    /// Right shift of the accumulated sum.
    pub shift: u8,
    /// Reference voltage, V.
    pub vref_v: f64,
    /// Input-referred noise of one conversion, native LSB RMS (an assumption: about what a G4 ADC reaches with a
    /// quiet reference and layout).
    pub conversion_noise_lsb: f64,
}

impl Default for AdcModel {
    fn default() -> Self {
        AdcModel { native_bits: 12, oversampling: 64, shift: 2, vref_v: 3.3, conversion_noise_lsb: 1.0 }
    }
}

impl AdcModel {
    /// The delivered code's format.
    pub fn format(&self) -> ConverterFormat {
        ConverterFormat::oversampled(self.native_bits, self.oversampling, self.shift, self.vref_v)
    }
}

/// The DAC.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DacModel {
    /// Resolution, bits.
    pub bits: u8,
    /// Reference voltage, V.
    pub vref_v: f64,
    /// The output the DAC reaches, V, lowest first: the G474's with its output buffer on, as specified (0.2 V to
    /// the reference less 0.2 V). A code beyond gives the nearest end ([`nanopos_id::hal::BoardDescription::
    /// amplifier_swing_v`]; a real buffer stops short softly, and often a little further out).
    pub swing_v: [f64; 2],
}

impl Default for DacModel {
    fn default() -> Self {
        DacModel { bits: 12, vref_v: 3.3, swing_v: [0.2, 3.1] }
    }
}

impl DacModel {
    /// The code format.
    pub fn format(&self) -> ConverterFormat {
        ConverterFormat::new(self.bits, self.vref_v)
    }
}

/// Everything about the simulated board.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoardSettings {
    /// The analog chain.
    pub plant: PlantSettings,
    /// Displacement noise, um RMS (0: none).
    pub noise_um_rms: f64,
    /// The displacement noise's distribution: `None` Gaussian; `Some(dof)` Student's t with `dof` degrees of freedom
    /// (3 or more, for a finite RMS), scaled to the same RMS: heavier tails, the fewer the degrees (its extra draws
    /// from a stream of their own, so the Gaussian numerators are the Gaussian noise's).
    pub noise_tail_dof: Option<u32>,
    /// Noise seed.
    pub seed: u64,
    /// Probe ADC.
    pub adc: AdcModel,
    /// Amplifier DAC.
    pub dac: DacModel,
    /// Probe front end (must match the pipeline's for readings to mean um).
    pub probe: ProbeFrontEnd,
    /// Amplifier front end.
    pub amplifier: AmplifierFrontEnd,
    /// Samples between writing a code and the DAC output (0 or 1).
    pub actuation_delay_samples: u8,
    /// Mains pickup on the probe's reading: sinusoids added to the displacement the ADC converts (through the
    /// sensor's cable or supply: the lab's 50 or 60 Hz and its odd harmonics). None by default.
    pub hum: [Tone; 2],
}

/// A sinusoid on the probe's reading: `amplitude_um sin(2 pi freq_hz t)` (0: none).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Tone {
    /// Peak amplitude, um.
    pub amplitude_um: f64,
    /// Frequency, Hz.
    pub freq_hz: f64,
}

impl Default for BoardSettings {
    fn default() -> Self {
        BoardSettings {
            plant: PlantSettings::default(),
            noise_um_rms: 1.25e-3,
            noise_tail_dof: None,
            seed: 1,
            adc: AdcModel::default(),
            dac: DacModel::default(),
            probe: ProbeFrontEnd::default(),
            amplifier: AmplifierFrontEnd::default(),
            actuation_delay_samples: 1,
            hum: [Tone::default(); 2],
        }
    }
}

/// The simulated board.
#[derive(Clone, Debug)]
pub struct SimBoard {
    settings: BoardSettings,
    plant: Plant,
    probe_noise: NormalStream,
    adc_noise: NormalStream,
    tail_noise: NormalStream,
    last_u_v: f64,
    pending_code: Option<u32>,
    /// The last code written (what the holding register has).
    written_code: Option<u32>,
    /// A probe code to return instead of the measurement (fault injection).
    pub forced_probe_code: Option<u32>,
    /// Board faults to report for the next sample (fault injection; taken once).
    pub inject_faults: Option<BoardFaults>,
    /// The settings' per-sample constants, worked out once (a sample took eight divisions and a square root).
    scales: Scales,
}

/// Constants of [`SimBoard`]'s samples, each the same expression of the settings as it would be per sample, so that
/// the samples are the same to the bit.
#[derive(Clone, Copy, Debug)]
struct Scales {
    adc: ConverterFormat,
    adc_volts_per_code: f64,
    adc_v_per_um: f64,
    /// The averaged conversion noise, V RMS.
    adc_noise_v: f64,
    dac: ConverterFormat,
    dac_volts_per_code: f64,
}

impl Scales {
    fn of(settings: &BoardSettings) -> Self {
        let (adc, dac) = (&settings.adc, settings.dac.format());
        let native_lsb_v = adc.vref_v / (1u64 << adc.native_bits) as f64;
        Scales {
            adc: adc.format(),
            adc_volts_per_code: adc.format().volts_per_code(),
            adc_v_per_um: settings.probe.adc_v_per_sensor_v / settings.probe.um_per_v,
            adc_noise_v: adc.conversion_noise_lsb * native_lsb_v / (adc.oversampling as f64).sqrt(),
            dac,
            dac_volts_per_code: dac.volts_per_code(),
        }
    }
}

impl SimBoard {
    /// A board at rest.
    pub fn new(settings: BoardSettings) -> Self {
        assert!(settings.noise_tail_dof.is_none_or(|dof| dof >= 3), "Student's t noise needs 3 or more degrees");
        SimBoard {
            plant: Plant::new(settings.plant),
            probe_noise: NormalStream::new(settings.seed),
            // A separate stream, so switching the ADC noise off leaves the probe noise sample-for-sample the same.
            adc_noise: NormalStream::new(settings.seed ^ 0xADC0_ADC0_ADC0_ADC0),
            tail_noise: NormalStream::new(settings.seed ^ 0x7A11_7A11_7A11_7A11),
            last_u_v: 0.0,
            pending_code: None,
            written_code: None,
            forced_probe_code: None,
            inject_faults: None,
            scales: Scales::of(&settings),
            settings,
        }
    }

    /// The plant (true parameters, state).
    pub fn plant(&self) -> &Plant {
        &self.plant
    }

    /// The settings.
    pub fn settings(&self) -> &BoardSettings {
        &self.settings
    }

    /// The amplifier-input voltage over the sample period just simulated, V.
    pub fn last_u_v(&self) -> f64 {
        self.last_u_v
    }

    /// ADC volts per micrometre of displacement.
    fn adc_v_per_um(&self) -> f64 {
        self.scales.adc_v_per_um
    }

    /// The RMS noise of a reading at rest, um, from the models above (probe noise, averaged conversion noise,
    /// output quantisation).
    pub fn noise_floor_um(&self) -> f64 {
        let adc = &self.settings.adc;
        let native_lsb_um = adc.vref_v / (1u64 << adc.native_bits) as f64 / self.adc_v_per_um();
        let out_lsb_um = self.settings.adc.format().volts_per_code() / self.adc_v_per_um();
        let conversion = adc.conversion_noise_lsb * native_lsb_um / (adc.oversampling as f64).sqrt();
        let quantisation = out_lsb_um / 12f64.sqrt();
        (self.settings.noise_um_rms.powi(2) + conversion.powi(2) + quantisation.powi(2)).sqrt()
    }
}

impl StageBoard for SimBoard {
    fn sample_rate_hz(&self) -> f64 {
        1.0 / self.settings.plant.sample_period_s
    }

    fn description(&self) -> BoardDescription {
        BoardDescription {
            probe: self.settings.adc.format(),
            amplifier: self.settings.dac.format(),
            amplifier_swing_v: self.settings.dac.swing_v,
            actuation_delay_samples: self.settings.actuation_delay_samples,
        }
    }

    fn read_probe(&mut self) -> u32 {
        let mut noise = self.probe_noise.next_normal();
        if let Some(dof) = self.settings.noise_tail_dof {
            // t = z / sqrt(chi2 / dof), its variance dof / (dof - 2): scaled back to 1.
            let chi2: f64 = (0..dof).map(|_| self.tail_noise.next_normal().powi(2)).sum();
            let dof = f64::from(dof);
            noise *= ((dof - 2.0) / chi2).sqrt();
        }
        let mut y_um = self.plant.output_um() + self.settings.noise_um_rms * noise;
        let t_s = self.plant.sample() as f64 * self.settings.plant.sample_period_s;
        for tone in self.settings.hum.iter().filter(|t| t.amplitude_um != 0.0) {
            y_um += tone.amplitude_um * (2.0 * std::f64::consts::PI * tone.freq_hz * t_s).sin();
        }
        let c = &self.scales;
        let v = self.settings.probe.adc_offset_v + c.adc_v_per_um * y_um;
        let v = v + c.adc_noise_v * self.adc_noise.next_normal();
        let code = (v / c.adc_volts_per_code).round().clamp(0.0, c.adc.max_code as f64) as u32;
        self.forced_probe_code.unwrap_or(code)
    }

    fn write_amplifier(&mut self, code: u32) {
        let dac = self.scales.dac;
        // An injected deadline miss: this code comes after the next instant, which loads the code written before it
        // (as on the board); it is loaded at the instant after only if the next sample's write misses too.
        let late = self.inject_faults.is_some_and(|f| f.deadline_missed);
        let mid = 1 << (dac.bits - 1);
        let next = if late { self.written_code.unwrap_or(mid) } else { code };
        self.written_code = Some(code);
        let code = match self.settings.actuation_delay_samples {
            0 => code,
            // The DAC's holding register: the previous code goes out now (mid-scale before the first write).
            _ => self.pending_code.replace(next).unwrap_or(mid),
        };
        let code = code.min(dac.max_code);
        let [low, high] = self.settings.dac.swing_v;
        let v_dac = (code as f64 * self.scales.dac_volts_per_code).max(low).min(high);
        self.last_u_v = self.settings.amplifier.command_v(v_dac);
        self.plant.advance(self.last_u_v);
    }

    fn sample_faults(&mut self) -> BoardFaults {
        // Simulated time never runs late: only injected faults.
        self.inject_faults.take().unwrap_or_default()
    }
}
