//! The fixed workload the on-target harness (`qemu/`) runs and the host computes, so both run the very same code
//! (feature `harness`).
//!
//! The host (`cargo run --release -p hal-sim --example qemu-vectors`) drives the simulated board through the
//! pipeline, records every sample's probe code and DAC code, and writes them with its own f32 results into a
//! [`Vectors`] file. The harness embeds that file, replays the probe codes through the same [`Workload`] on the
//! Cortex-M4F and compares: every DAC code, and the final estimates bit for bit.
//!
//! File layout (little-endian): magic `NPV4`, `u32` sample count, the [`BoardDescription`] (`u8` bits, `f64` full
//! scale and `u32` largest code of the probe, the same of the amplifier, two `f64` of the DAC's swing, `u8` actuation
//! delay), the [`Results`], then per sample the `u32` probe code and the `u32` DAC code. (`NPV1`, before the swing,
//! `NPV2`, before the largest code, and `NPV3`, before the hybrid filter at 7 substeps, are refused.)

use crate::estimator::{Estimator, FilteredSample};
use crate::estimators::arx::{ArxConfig, ArxDesign, ArxEstimator, ArxRls};
use crate::estimators::ekf::dense::DenseHekf;
use crate::estimators::ekf::{EkfDesign, Hekf};
use crate::fixed::Q32;
use crate::hal::{BoardDescription, ConverterFormat};
use crate::pipeline::{Pipeline, PipelineConfig, PipelineSettings, SampleOutput, SettingsError};
use crate::{Scalar, StageParams};

/// The paper's three estimators in f32 with their PRBS tuning: the bank of `pipeline_all_f32`.
pub type PaperBank = crate::estimators::PaperBank<f32>;

/// What the workload ends with: every estimator's parameters, as exact bit patterns.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Results {
    /// Continuous-time RLS `[a0, a1, b0]` (f32 bits).
    pub crls: [u32; 3],
    /// Continuous EKF.
    pub cekf: [u32; 3],
    /// Hybrid EKF.
    pub hekf: [u32; 3],
    /// Dense hybrid EKF (nalgebra).
    pub hekf_dense: [u32; 3],
    /// Hybrid EKF with [`SQUARED_SUBSTEPS`] substeps: its substep map squared, an odd count's map taken first.
    pub hekf_squared: [u32; 3],
    /// ARX RLS in f32.
    pub arx: [u32; 3],
    /// ARX RLS in Q31.32: the raw deviations of `[A1, A2, B1, B2]`.
    pub arx_fixed: [i64; 4],
    /// Sum of all DAC codes written (the excitation and the output path).
    pub dac_code_sum: u64,
}

fn bits(p: StageParams<f32>) -> [u32; 3] {
    [p.a0.to_bits(), p.a1.to_bits(), p.b0.to_bits()]
}

impl Results {
    /// Serialised size.
    pub const BYTES: usize = 6 * 3 * 4 + 4 * 8 + 8;

    fn write(&self, out: &mut [u8; Self::BYTES]) {
        let mut w = Writer { buf: out, at: 0 };
        for p in [self.crls, self.cekf, self.hekf, self.hekf_dense, self.hekf_squared, self.arx] {
            p.iter().for_each(|x| w.put(&x.to_le_bytes()));
        }
        self.arx_fixed.iter().for_each(|x| w.put(&x.to_le_bytes()));
        w.put(&self.dac_code_sum.to_le_bytes());
    }

    fn read(r: &mut Reader) -> Option<Self> {
        let mut three = || Some([r.u32()?, r.u32()?, r.u32()?]);
        let (crls, cekf, hekf, hekf_dense) = (three()?, three()?, three()?, three()?);
        let (hekf_squared, arx) = (three()?, three()?);
        let arx_fixed = [r.i64()?, r.i64()?, r.i64()?, r.i64()?];
        Some(Results { crls, cekf, hekf, hekf_dense, hekf_squared, arx, arx_fixed, dac_code_sum: r.u64()? })
    }
}

/// Every estimator of the harness, fed from one pipeline.
#[derive(Clone, Debug)]
pub struct Workload {
    /// Pipeline configuration (default settings on the recorded board).
    pub cfg: PipelineConfig<f32>,
    /// The whole per-sample pipeline with the paper's three estimators.
    pub pipeline: Pipeline<f32, PaperBank>,
    /// ARX RLS, f32.
    pub arx: ArxEstimator<f32>,
    /// ARX RLS in fixed point, fed the f32 pre-filtered signals converted to Q31.32.
    pub arx_fixed: ArxRls<Q32>,
    /// Its configuration.
    pub arx_fixed_cfg: ArxConfig<Q32>,
    /// The dense hybrid EKF.
    pub hekf_dense: DenseHekf<f32>,
    /// The hybrid EKF with [`SQUARED_SUBSTEPS`] substeps.
    pub hekf_squared: Hekf<f32>,
    dac_code_sum: u64,
}

/// The substeps of [`Workload::hekf_squared`]: more than the 4 taken one at a time, so that its substep map is squared
/// (`estimators::ekf`), and odd, so that a map is taken before the squaring too: every branch of it.
pub const SQUARED_SUBSTEPS: u32 = 7;

impl Workload {
    /// Every estimator at its defaults, the pipeline at its default settings for `board`.
    pub fn new(board: &BoardDescription) -> Result<Self, SettingsError> {
        let cfg = PipelineSettings::default().design::<f32>(board)?;
        let arx_fixed_cfg = ArxDesign::default().design::<Q32>();
        Ok(Workload {
            pipeline: Pipeline::new(&cfg, crate::estimators::paper_bank()),
            arx: ArxEstimator::new(ArxDesign::default().design()),
            arx_fixed: ArxRls::new(&arx_fixed_cfg),
            arx_fixed_cfg,
            hekf_dense: DenseHekf::new(EkfDesign::default().design()),
            hekf_squared: Hekf::new(EkfDesign { substeps: SQUARED_SUBSTEPS, ..EkfDesign::default() }.design()),
            cfg,
            dac_code_sum: 0,
        })
    }

    /// One sample: the pipeline (with the paper's estimators), then the other estimators on its output.
    pub fn step(&mut self, probe_code: u32) -> SampleOutput<f32> {
        let out = self.pipeline.step(&self.cfg, probe_code);
        self.step_others(&out);
        out
    }

    /// The second half of [`Workload::step`], after the pipeline's own step (the harness times that alone).
    pub fn step_others(&mut self, out: &SampleOutput<f32>) {
        if let Some(s) = &out.estimator_input {
            self.feed_others(s);
        }
        self.dac_code_sum += u64::from(out.dac_code);
    }

    /// The estimators outside the pipeline's bank, on one filtered sample.
    pub fn feed_others(&mut self, s: &FilteredSample<f32>) {
        self.arx.update(s);
        let (u, y) = (Q32::of(f64::from(s.u_f.value)), Q32::of(f64::from(s.y_f.value)));
        self.arx_fixed.update(&self.arx_fixed_cfg, u, y, true);
        self.hekf_dense.update(s.u_f.value, s.y_f.value);
        self.hekf_squared.update(s);
    }

    /// The final estimates.
    pub fn results(&self) -> Results {
        let (crls, cekf, hekf) = &self.pipeline.estimators;
        Results {
            crls: bits(crls.params()),
            cekf: bits(cekf.params()),
            hekf: bits(hekf.params()),
            hekf_dense: bits(self.hekf_dense.params()),
            hekf_squared: bits(self.hekf_squared.params()),
            arx: bits(self.arx.params()),
            arx_fixed: self.arx_fixed.rls().theta().map(|q| q.0),
            dac_code_sum: self.dac_code_sum,
        }
    }
}

/// A vectors file, parsed in place.
#[derive(Clone, Copy, Debug)]
pub struct Vectors<'a> {
    /// The recorded board.
    pub board: BoardDescription,
    /// The host's results on this input.
    pub expected: Results,
    samples: &'a [u8],
}

/// Why a vectors file was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VectorsError {
    /// It does not start with `NPV4`.
    Magic,
    /// It ends before its header says.
    Truncated,
}

const MAGIC: &[u8; 4] = b"NPV4";
const HEADER: usize = 4 + 4 + 2 * (1 + 8 + 4) + 2 * 8 + 1;

impl<'a> Vectors<'a> {
    /// Parse `bytes` (no copy).
    pub fn parse(bytes: &'a [u8]) -> Result<Self, VectorsError> {
        if bytes.get(..4) != Some(MAGIC) {
            return Err(VectorsError::Magic);
        }
        let mut r = Reader { buf: bytes, at: 4 };
        let parsed = (|| {
            let n = r.u32()? as usize;
            let mut converter =
                || Some(ConverterFormat { bits: r.u8()?, full_scale_v: f64::from_bits(r.u64()?), max_code: r.u32()? });
            let (probe, amplifier) = (converter()?, converter()?);
            let swing = [f64::from_bits(r.u64()?), f64::from_bits(r.u64()?)];
            let board =
                BoardDescription { probe, amplifier, amplifier_swing_v: swing, actuation_delay_samples: r.u8()? };
            let expected = Results::read(&mut r)?;
            let samples = r.buf.get(r.at..r.at.checked_add(n.checked_mul(8)?)?)?;
            Some(Vectors { board, expected, samples })
        })();
        parsed.ok_or(VectorsError::Truncated)
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.samples.len() / 8
    }

    /// Whether there are no samples.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Sample `k`: `(probe code, DAC code)`.
    pub fn sample(&self, k: usize) -> (u32, u32) {
        let s = &self.samples[8 * k..8 * k + 8];
        (u32::from_le_bytes([s[0], s[1], s[2], s[3]]), u32::from_le_bytes([s[4], s[5], s[6], s[7]]))
    }

    /// Serialise: the header and results, then each sample, through `out`.
    pub fn write(board: &BoardDescription, expected: &Results, samples: &[(u32, u32)], mut out: impl FnMut(&[u8])) {
        let mut head = [0u8; HEADER];
        let mut w = Writer { buf: &mut head, at: 0 };
        w.put(MAGIC);
        w.put(&(samples.len() as u32).to_le_bytes());
        for c in [board.probe, board.amplifier] {
            w.put(&[c.bits]);
            w.put(&c.full_scale_v.to_bits().to_le_bytes());
            w.put(&c.max_code.to_le_bytes());
        }
        for v in board.amplifier_swing_v {
            w.put(&v.to_bits().to_le_bytes());
        }
        w.put(&[board.actuation_delay_samples]);
        out(&head);
        let mut results = [0u8; Results::BYTES];
        expected.write(&mut results);
        out(&results);
        for (probe, dac) in samples {
            out(&probe.to_le_bytes());
            out(&dac.to_le_bytes());
        }
    }
}

struct Writer<'a> {
    buf: &'a mut [u8],
    at: usize,
}

impl Writer<'_> {
    fn put(&mut self, b: &[u8]) {
        self.buf[self.at..self.at + b.len()].copy_from_slice(b);
        self.at += b.len();
    }
}

struct Reader<'a> {
    buf: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take<const N: usize>(&mut self) -> Option<[u8; N]> {
        let b = self.buf.get(self.at..self.at + N)?;
        self.at += N;
        b.try_into().ok()
    }
    fn u8(&mut self) -> Option<u8> {
        Some(self.take::<1>()?[0])
    }
    fn u32(&mut self) -> Option<u32> {
        Some(u32::from_le_bytes(self.take()?))
    }
    fn u64(&mut self) -> Option<u64> {
        Some(u64::from_le_bytes(self.take()?))
    }
    fn i64(&mut self) -> Option<i64> {
        Some(i64::from_le_bytes(self.take()?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vectors_round_trip_and_refuse_damage() {
        let board = BoardDescription {
            probe: ConverterFormat::oversampled(12, 64, 2, 3.3),
            amplifier: ConverterFormat::new(12, 3.3),
            amplifier_swing_v: [0.2, 3.1],
            actuation_delay_samples: 1,
        };
        let expected = Results {
            crls: [1, 2, 3],
            hekf_squared: [4, 5, 6],
            arx_fixed: [-5, 6, 7, i64::MIN],
            dac_code_sum: 99,
            ..Default::default()
        };
        let samples = [(1u32, 2u32), (40_000, 4095)];
        let mut bytes = std::vec::Vec::new();
        Vectors::write(&board, &expected, &samples, |b| bytes.extend_from_slice(b));
        let v = Vectors::parse(&bytes).unwrap();
        assert_eq!((v.board, v.expected, v.len()), (board, expected, 2));
        assert_eq!((v.sample(0), v.sample(1)), (samples[0], samples[1]));
        assert_eq!(Vectors::parse(&bytes[..bytes.len() - 1]).unwrap_err(), VectorsError::Truncated);
        assert_eq!(Vectors::parse(b"NPV1").unwrap_err(), VectorsError::Magic, "the format before the DAC's swing");
        let mut old = bytes.clone();
        old[..4].copy_from_slice(b"NPV2");
        assert_eq!(Vectors::parse(&old).unwrap_err(), VectorsError::Magic, "the format before the largest code");
        old[..4].copy_from_slice(b"NPV3");
        assert_eq!(Vectors::parse(&old).unwrap_err(), VectorsError::Magic, "the format before 7 substeps");
        assert_eq!(Vectors::parse(&bytes[..10]).unwrap_err(), VectorsError::Truncated);
    }
}
