//! Tuning values set one at a time, by name: the keys of the host's `--tuning` TOML files and of the console's
//! `tune` command, checked in one place ([`Tuning::set`]) so that both accept and refuse exactly the same values.
//!
//! | key | values | range |
//! |---|---|---|
//! | `initial` | `b0 a1 a0`: every estimator's initial parameters (and the normalisation of the continuous RLS and the EKFs) | positive |
//! | `prefilter` | `f_lc f_p zeta_p` of the stage's pre-filter `W_p` (SPEC 4), one for all as in the paper: the pipeline's (whose output the EKFs and the ARX read) and the continuous-time RLS's own (inside its RK4 step); put `f_p` near the stage's resonance | positive, the frequencies below the Nyquist frequency (checked when the pipeline is designed) |
//! | `spike_ratio` | the pipeline's spike gate ([`crate::filters::spike`]): a reading whose third difference exceeds this many times its recent mean (and 16 probe codes) is replaced; 0 turns the gate off | whole, 0 to 65 535 |
//! | `rls gamma` | forgetting, 1/s | positive |
//! | `rls p0` | diag `P(0)` for `[b0, a1, a0]` | positive |
//! | `rls r0` | bound on `||P||_F` | positive |
//! | `rls pe_floor_v2` | pre-filtered input power below which the estimate is held, V^2 | 0 or more |
//! | `ekf q` | diag `Q` for `[x1, x2, a0, a1, b0]`; also sets `p0` to `10 Q` (SPEC 6.4), which `ekf p0` then overrides | positive |
//! | `ekf p0` | diag `P(0)` | positive |
//! | `ekf r` | measurement noise, um^2 | positive |
//! | `ekf substeps` | the hybrid filter's prediction substeps (up to 4 about 68 instructions each on the M4F, above 4 taken by squaring: 64 cost about 1 070 more than 4, and the board's interrupt takes up to about 6 600 there, BENCHMARKS.md) | whole, 1 to 64 |
//! | `ekf gate_sigma` | innovation gate, relative to the running level | positive |
//! | `ekf change_samples` | gated samples in a row that mean a change (0: off, gating off too) | whole, 0 or more |
//! | `ekf drift_ratio` | short- over long-run `nu^2/S` that means a gentle change | 0 (off) or at least 1 |
//! | `ekf reopen` | parameter variances after a drift, times `P0` | 1 to the variance ceiling (500) |
//! | `ekf pe_floor_v2` | input power below which the parameters freeze, V^2 | 0 or more |
//! | `arx lambda` | forgetting per sample | in (0, 1] |
//! | `arx max_trace` | windup bound on `trace F` | positive |
//! | `arx pe_floor_v2` | pre-filtered input power below which the estimate is held, V^2 | 0 or more |

use super::Tuning;
use crate::control::EstimatorSet;
use crate::filters::prefilter::PrefilterDesign;
use crate::StageParams;
use core::fmt;

/// A tuning value that can be set by name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TuningKey {
    /// Every estimator's initial `[b0, a1, a0]`.
    Initial,
    /// The pre-filter `W_p`.
    Prefilter,
    /// The pipeline's spike gate's ratio.
    SpikeRatio,
    /// Continuous-time RLS forgetting.
    RlsGamma,
    /// Continuous-time RLS `diag P(0)`.
    RlsP0,
    /// Continuous-time RLS covariance bound.
    RlsR0,
    /// Continuous-time RLS persistent-excitation floor.
    RlsPeFloor,
    /// EKF `diag Q` (and `P(0) = 10 Q`).
    EkfQ,
    /// EKF `diag P(0)`.
    EkfP0,
    /// EKF measurement noise.
    EkfR,
    /// Hybrid EKF prediction substeps.
    EkfSubsteps,
    /// EKF innovation gate.
    EkfGateSigma,
    /// EKF change detection: gated samples in a row.
    EkfChangeSamples,
    /// EKF drift detection ratio.
    EkfDriftRatio,
    /// EKF covariance reopening after a drift.
    EkfReopen,
    /// EKF persistent-excitation floor.
    EkfPeFloor,
    /// ARX forgetting.
    ArxLambda,
    /// ARX windup bound.
    ArxMaxTrace,
    /// ARX persistent-excitation floor.
    ArxPeFloor,
}

impl TuningKey {
    /// Every key, in the order of the table above.
    pub const ALL: [TuningKey; 19] = [
        TuningKey::Initial,
        TuningKey::Prefilter,
        TuningKey::SpikeRatio,
        TuningKey::RlsGamma,
        TuningKey::RlsP0,
        TuningKey::RlsR0,
        TuningKey::RlsPeFloor,
        TuningKey::EkfQ,
        TuningKey::EkfP0,
        TuningKey::EkfR,
        TuningKey::EkfSubsteps,
        TuningKey::EkfGateSigma,
        TuningKey::EkfChangeSamples,
        TuningKey::EkfDriftRatio,
        TuningKey::EkfReopen,
        TuningKey::EkfPeFloor,
        TuningKey::ArxLambda,
        TuningKey::ArxMaxTrace,
        TuningKey::ArxPeFloor,
    ];

    /// `(section, name)`: the section is `""` for `initial`, `prefilter` and `spike_ratio`, else `rls`, `ekf` or
    /// `arx`.
    pub const fn path(self) -> (&'static str, &'static str) {
        match self {
            TuningKey::Initial => ("", "initial"),
            TuningKey::Prefilter => ("", "prefilter"),
            TuningKey::SpikeRatio => ("", "spike_ratio"),
            TuningKey::RlsGamma => ("rls", "gamma"),
            TuningKey::RlsP0 => ("rls", "p0"),
            TuningKey::RlsR0 => ("rls", "r0"),
            TuningKey::RlsPeFloor => ("rls", "pe_floor_v2"),
            TuningKey::EkfQ => ("ekf", "q"),
            TuningKey::EkfP0 => ("ekf", "p0"),
            TuningKey::EkfR => ("ekf", "r"),
            TuningKey::EkfSubsteps => ("ekf", "substeps"),
            TuningKey::EkfGateSigma => ("ekf", "gate_sigma"),
            TuningKey::EkfChangeSamples => ("ekf", "change_samples"),
            TuningKey::EkfDriftRatio => ("ekf", "drift_ratio"),
            TuningKey::EkfReopen => ("ekf", "reopen"),
            TuningKey::EkfPeFloor => ("ekf", "pe_floor_v2"),
            TuningKey::ArxLambda => ("arx", "lambda"),
            TuningKey::ArxMaxTrace => ("arx", "max_trace"),
            TuningKey::ArxPeFloor => ("arx", "pe_floor_v2"),
        }
    }

    /// The estimators whose tuning this key is part of (bit `i`: [`crate::control::ESTIMATOR_NAMES`]`[i]`): the
    /// initial parameters every estimator's, the pre-filter the continuous-time RLS's own (the others read the
    /// pipeline's), the spike gate's ratio none's, a section's keys its estimators' (both EKFs share one).
    pub const fn estimators(self) -> EstimatorSet {
        match (self, self.path().0.as_bytes()) {
            (TuningKey::Initial, _) => EstimatorSet::ALL,
            (TuningKey::Prefilter, _) | (_, b"rls") => EstimatorSet(0b0001),
            (_, b"ekf") => EstimatorSet(0b0110),
            (_, b"arx") => EstimatorSet(0b1000),
            _ => EstimatorSet(0),
        }
    }

    /// The key `name` of `section` (`""` for `initial`).
    pub fn parse(section: &str, name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.path() == (section, name))
    }

    /// The keys of a section, for messages (`None` for a section that does not exist).
    pub const fn names_of(section: &str) -> Option<&'static str> {
        match section.as_bytes() {
            b"rls" => Some("gamma, p0, r0 or pe_floor_v2"),
            b"ekf" => Some("q, p0, r, substeps, gate_sigma, change_samples, drift_ratio, reopen or pe_floor_v2"),
            b"arx" => Some("lambda, max_trace or pe_floor_v2"),
            _ => None,
        }
    }

    /// The keys that describe the stage and its probe rather than the input: a preset chosen on the console keeps
    /// them.
    pub const STAGE: [TuningKey; 3] = [TuningKey::Initial, TuningKey::Prefilter, TuningKey::SpikeRatio];

    /// How many values it takes.
    pub const fn len(self) -> usize {
        match self {
            TuningKey::Initial | TuningKey::Prefilter | TuningKey::RlsP0 => 3,
            TuningKey::EkfQ | TuningKey::EkfP0 => 5,
            _ => 1,
        }
    }

    /// What its values are, for messages.
    pub const fn values_hint(self) -> &'static str {
        match self {
            TuningKey::Initial => "3 numbers: b0 a1 a0",
            TuningKey::Prefilter => "3 numbers: f_lc_hz f_p_hz zeta_p",
            TuningKey::RlsP0 => "3 numbers: diag P(0) for b0 a1 a0",
            TuningKey::EkfQ | TuningKey::EkfP0 => "5 numbers, for x1 x2 a0 a1 b0",
            _ => "a number",
        }
    }

    /// Never: every key takes at least one value (for clippy's `len_without_is_empty`).
    pub const fn is_empty(self) -> bool {
        false
    }
}

impl fmt::Display for TuningKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.path() {
            ("", name) => f.write_str(name),
            (section, name) => write!(f, "[{section}] {name}"),
        }
    }
}

/// What a refused value should have been.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Expected {
    /// Above zero and finite.
    Positive,
    /// Zero or above, finite.
    NonNegative,
    /// A whole number from 1 to 64.
    Substeps,
    /// A whole number, zero or more.
    Whole,
    /// A whole number from 0 to 65 535 (0: off).
    Ratio,
    /// Zero or at least one.
    DriftRatio,
    /// From 1 to the variance ceiling.
    Reopen {
        /// The ceiling, times `P0`.
        ceiling: f64,
    },
    /// In `(0, 1]`.
    Forgetting,
    /// A rate above zero and at most `max` (per second).
    Rate {
        /// The largest rate, 1/s.
        max: f64,
    },
}

impl fmt::Display for Expected {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Expected::Positive => f.write_str("must be a positive number"),
            Expected::NonNegative => f.write_str("must be zero or positive"),
            Expected::Substeps => f.write_str("between 1 and 64"),
            Expected::Whole => f.write_str("must be a whole number, 0 or more"),
            Expected::Ratio => f.write_str("a whole number from 0 (off) to 65535"),
            Expected::DriftRatio => f.write_str("0 (off) or at least 1"),
            // The crate's number formatting, not `f64`'s `Display` (which would add 30 KiB of flash to the firmware).
            Expected::Reopen { ceiling } => {
                write!(f, "between 1 and {} (the variance ceiling)", crate::text::Num(*ceiling, 6))
            }
            Expected::Forgetting => f.write_str("must be in (0, 1]"),
            Expected::Rate { max } => {
                write!(f, "above 0 and at most {} /s (the sample rate)", crate::text::Num(*max, 6))
            }
        }
    }
}

/// A refused value: its index among the key's values and what it should have been.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Refused {
    /// Index of the value.
    pub index: usize,
    /// What was expected.
    pub expected: Expected,
}

impl Expected {
    /// Whether `x` is in the range.
    fn accepts(self, x: f64) -> bool {
        let whole = libm::trunc(x) == x;
        match self {
            Expected::Positive => x.is_finite() && x > 0.0,
            Expected::NonNegative => x.is_finite() && x >= 0.0,
            Expected::Substeps => whole && (1.0..=64.0).contains(&x),
            Expected::Whole => whole && (0.0..=u32::MAX as f64).contains(&x),
            Expected::Ratio => whole && (0.0..=u16::MAX as f64).contains(&x),
            Expected::DriftRatio => x == 0.0 || (x.is_finite() && x >= 1.0),
            Expected::Reopen { ceiling } => (1.0..=ceiling).contains(&x),
            Expected::Forgetting => x > 0.0 && x <= 1.0,
            Expected::Rate { max } => x > 0.0 && x <= max,
        }
    }
}

impl Tuning {
    /// The range of `key`'s values in this tuning.
    pub fn expected(&self, key: TuningKey) -> Expected {
        match key {
            TuningKey::EkfSubsteps => Expected::Substeps,
            TuningKey::EkfChangeSamples => Expected::Whole,
            TuningKey::SpikeRatio => Expected::Ratio,
            TuningKey::EkfDriftRatio => Expected::DriftRatio,
            TuningKey::EkfReopen => Expected::Reopen { ceiling: self.ekf.health.ceiling },
            TuningKey::RlsPeFloor | TuningKey::EkfPeFloor | TuningKey::ArxPeFloor => Expected::NonNegative,
            TuningKey::ArxLambda => Expected::Forgetting,
            // A forgetting time shorter than a sample means nothing; far beyond it, one RK4 step of `P' = gamma P`
            // overflows (`gamma = 1e20` reset the RLS on every sample).
            TuningKey::RlsGamma => Expected::Rate { max: 1.0 / self.rls.sample_period_s },
            _ => Expected::Positive,
        }
    }

    /// This tuning for samples `dt` seconds apart (every estimator's design; `rls gamma`'s range follows it).
    pub fn at_sample_period(mut self, dt: f64) -> Tuning {
        self.rls.sample_period_s = dt;
        self.ekf.sample_period_s = dt;
        self.arx.sample_period_s = dt;
        self
    }

    /// This tuning with the stage's values ([`TuningKey::STAGE`]) of `stage`.
    pub fn with_stage_of(mut self, stage: &Tuning) -> Tuning {
        self.rls.initial = stage.rls.initial;
        self.ekf.initial = stage.ekf.initial;
        self.arx.initial = stage.arx.initial;
        self.rls.prefilter = stage.rls.prefilter;
        self.spike_ratio = stage.spike_ratio;
        self
    }

    /// The values of `key` (the first [`TuningKey::len`] of the array).
    pub fn get(&self, key: TuningKey) -> [f64; 5] {
        let (e, mut v) = (&self.ekf, [0.0; 5]);
        match key {
            // `set` gives every estimator the same initial parameters.
            TuningKey::Initial => v[..3].copy_from_slice(&[e.initial.b0, e.initial.a1, e.initial.a0]),
            TuningKey::Prefilter => {
                let f = &self.rls.prefilter;
                v[..3].copy_from_slice(&[f.f_lc_hz, f.f_p_hz, f.zeta_p]);
            }
            TuningKey::SpikeRatio => v[0] = self.spike_ratio as f64,
            TuningKey::RlsGamma => v[0] = self.rls.gamma,
            TuningKey::RlsP0 => v[..3].copy_from_slice(&self.rls.p0_diag),
            TuningKey::RlsR0 => v[0] = self.rls.r0,
            TuningKey::RlsPeFloor => v[0] = self.rls.pe_floor_v2,
            TuningKey::EkfQ => v = e.q_diag,
            TuningKey::EkfP0 => v = e.p0_diag,
            TuningKey::EkfR => v[0] = e.r,
            TuningKey::EkfSubsteps => v[0] = e.substeps as f64,
            TuningKey::EkfGateSigma => v[0] = e.health.gate_sigma,
            TuningKey::EkfChangeSamples => v[0] = e.health.change_samples as f64,
            TuningKey::EkfDriftRatio => v[0] = e.health.drift_ratio,
            TuningKey::EkfReopen => v[0] = e.health.reopen,
            TuningKey::EkfPeFloor => v[0] = e.health.pe_floor_v2,
            TuningKey::ArxLambda => v[0] = self.arx.lambda,
            TuningKey::ArxMaxTrace => v[0] = self.arx.max_trace,
            TuningKey::ArxPeFloor => v[0] = self.arx.pe_floor_v2,
        }
        v
    }

    /// Set `key` to `values` (exactly [`TuningKey::len`] of them). A refused value leaves the tuning unchanged.
    ///
    /// Not inlined: it runs at a command's pace, and one copy keeps the firmware small (the core is built for speed).
    #[inline(never)]
    pub fn set(&mut self, key: TuningKey, values: &[f64]) -> Result<(), Refused> {
        assert!(values.len() == key.len(), "tuning: a wrong count of values");
        let expected = self.expected(key);
        if let Some(index) = values.iter().position(|&x| !expected.accepts(x)) {
            return Err(Refused { index, expected });
        }
        let (v, x) = (values, values[0]);
        let ekf = &mut self.ekf;
        match key {
            TuningKey::Initial => {
                let p = StageParams { b0: v[0], a1: v[1], a0: v[2] };
                (self.rls.initial, ekf.initial, self.arx.initial) = (p, p, p);
            }
            TuningKey::Prefilter => {
                self.rls.prefilter = PrefilterDesign { f_lc_hz: v[0], f_p_hz: v[1], zeta_p: v[2] };
            }
            TuningKey::SpikeRatio => self.spike_ratio = x as u16,
            TuningKey::RlsGamma => self.rls.gamma = x,
            TuningKey::RlsP0 => self.rls.p0_diag.copy_from_slice(v),
            TuningKey::RlsR0 => self.rls.r0 = x,
            TuningKey::RlsPeFloor => self.rls.pe_floor_v2 = x,
            TuningKey::EkfQ => {
                ekf.q_diag.copy_from_slice(v);
                ekf.p0_diag = ekf.q_diag.map(|q| 10.0 * q);
            }
            TuningKey::EkfP0 => ekf.p0_diag.copy_from_slice(v),
            TuningKey::EkfR => ekf.r = x,
            TuningKey::EkfSubsteps => ekf.substeps = x as u32,
            TuningKey::EkfGateSigma => ekf.health.gate_sigma = x,
            TuningKey::EkfChangeSamples => ekf.health.change_samples = x as u32,
            TuningKey::EkfDriftRatio => ekf.health.drift_ratio = x,
            TuningKey::EkfReopen => ekf.health.reopen = x,
            TuningKey::EkfPeFloor => ekf.health.pe_floor_v2 = x,
            TuningKey::ArxLambda => self.arx.lambda = x,
            TuningKey::ArxMaxTrace => self.arx.max_trace = x,
            TuningKey::ArxPeFloor => self.arx.pe_floor_v2 = x,
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::TuningPreset;

    #[test]
    fn every_key_parses_from_its_path_and_takes_its_count() {
        for key in TuningKey::ALL {
            let (section, name) = key.path();
            assert_eq!(TuningKey::parse(section, name), Some(key));
            if !section.is_empty() {
                assert!(TuningKey::names_of(section).unwrap().contains(name), "{key}");
            }
            let mut t = Tuning::of(TuningPreset::Prbs);
            let ones = [1.0; 5];
            assert_eq!(t.set(key, &ones[..key.len()]), Ok(()), "{key}: 1 is in every range");
            // What is set reads back, and a preset's values set again change nothing.
            assert_eq!(t.get(key)[..key.len()], ones[..key.len()], "{key}");
            let preset = Tuning::of(TuningPreset::Triangle);
            let mut again = preset;
            again.set(key, &preset.get(key)[..key.len()]).unwrap();
            assert_eq!(again, preset, "{key}");
        }
        assert_eq!(TuningKey::parse("ekf", "gamma"), None);
        assert_eq!(TuningKey::parse("", "q"), None);
    }

    #[test]
    fn a_tuning_fits_the_working_scalar_or_says_so() {
        for preset in [TuningPreset::Prbs, TuningPreset::Triangle] {
            assert!(Tuning::of(preset).design::<f32>().fits() && Tuning::of(preset).design::<f64>().fits());
        }
        // Each accepted by its range, each out of f32's once normalised; all but the last within f64's.
        let cases: [(TuningKey, &[f64], bool); 6] = [
            (TuningKey::Initial, &[1e-20, 70.0, 6e6], true), // q_b0 / b0^2 = 5e48
            (TuningKey::Initial, &[5e5, 70.0, 1e-90], true), // P0 / W^2 (W = sqrt(a0))
            (TuningKey::Initial, &[5e5, 1e38, 6e6], true),   // the RLS's norm weights, a1^4
            (TuningKey::EkfR, &[1e-45], true),               // 1 / R
            (TuningKey::EkfR, &[1e39], true),                // R itself
            (TuningKey::RlsP0, &[1e6, 10.0, 1e300], false),  // P0 / a0^2
        ];
        for (key, values, fits_f64) in cases {
            let mut t = Tuning::of(TuningPreset::Prbs);
            t.set(key, values).unwrap();
            assert!(!t.design::<f32>().fits(), "{key} {values:?}");
            if fits_f64 {
                assert!(t.design::<f64>().fits(), "{key} {values:?}");
            }
        }
    }

    #[test]
    fn a_refused_value_names_its_index_and_changes_nothing() {
        let base = Tuning::of(TuningPreset::Triangle);
        let cases: [(TuningKey, &[f64], usize, Expected); 13] = [
            (TuningKey::EkfQ, &[1e-12, 1e-6, -1.0, 1.0, 1.0], 2, Expected::Positive),
            (TuningKey::Initial, &[5e5, 70.0, f64::NAN], 2, Expected::Positive),
            (TuningKey::EkfSubsteps, &[0.0], 0, Expected::Substeps),
            (TuningKey::EkfSubsteps, &[2.5], 0, Expected::Substeps),
            (TuningKey::EkfChangeSamples, &[-1.0], 0, Expected::Whole),
            (TuningKey::EkfDriftRatio, &[0.5], 0, Expected::DriftRatio),
            (TuningKey::EkfReopen, &[5000.0], 0, Expected::Reopen { ceiling: 500.0 }),
            (TuningKey::EkfPeFloor, &[f64::INFINITY], 0, Expected::NonNegative),
            (TuningKey::ArxLambda, &[1.5], 0, Expected::Forgetting),
            (TuningKey::RlsGamma, &[1e20], 0, Expected::Rate { max: 1e4 }),
            (TuningKey::SpikeRatio, &[65536.0], 0, Expected::Ratio),
            (TuningKey::SpikeRatio, &[2.5], 0, Expected::Ratio),
            (TuningKey::SpikeRatio, &[-1.0], 0, Expected::Ratio),
        ];
        for (key, values, index, expected) in cases {
            let mut t = base;
            assert_eq!(t.set(key, values), Err(Refused { index, expected }), "{key}");
            assert_eq!(t, base, "{key}");
        }
    }

    #[test]
    fn each_range_takes_its_ends_and_refuses_what_lies_just_beyond() {
        let ceiling = 500.0;
        let max = 1e4;
        // (range, accepted, refused): each end and the nearest number past it, and what is never a value.
        let cases: [(Expected, &[f64], &[f64]); 9] = [
            (Expected::Positive, &[f64::MIN_POSITIVE, 1e300], &[0.0, -0.0, -1e-300, f64::INFINITY]),
            (Expected::NonNegative, &[0.0, -0.0, 1e300], &[-f64::MIN_POSITIVE, f64::INFINITY]),
            (Expected::Substeps, &[1.0, 64.0], &[0.0, 65.0, 1.5, 64.0f64.next_up()]),
            (Expected::Whole, &[0.0, u32::MAX as f64], &[-1.0, u32::MAX as f64 + 1.0, 0.5, f64::INFINITY]),
            (Expected::Ratio, &[0.0, 65535.0], &[-1.0, 65536.0, 0.5]),
            (Expected::DriftRatio, &[0.0, 1.0, 1e300], &[1.0f64.next_down(), f64::MIN_POSITIVE, f64::INFINITY]),
            (Expected::Reopen { ceiling }, &[1.0, ceiling], &[1.0f64.next_down(), ceiling.next_up()]),
            (Expected::Forgetting, &[f64::MIN_POSITIVE, 1.0], &[0.0, 1.0f64.next_up(), -1.0]),
            (Expected::Rate { max }, &[f64::MIN_POSITIVE, max], &[0.0, max.next_up(), -1.0]),
        ];
        for (expected, accepted, refused) in cases {
            for &x in accepted {
                assert!(expected.accepts(x), "{expected:?} refused {x:e}");
            }
            for &x in refused.iter().chain(&[f64::NAN, f64::NEG_INFINITY]) {
                assert!(!expected.accepts(x), "{expected:?} took {x:e}");
            }
            // Every refusal says what it wanted; the two ranges with a bound from the tuning name it.
            let said = format!("{expected}");
            assert!(said.len() > 10, "{expected:?}: '{said}'");
            match expected {
                Expected::Reopen { .. } => assert!(said.contains("and 500 "), "{said}"),
                Expected::Rate { .. } => assert!(said.contains("at most 10000 /s"), "{said}"),
                _ => {}
            }
        }
    }

    #[test]
    fn each_key_restarts_the_estimators_whose_tuning_it_is_part_of_and_says_how_many_values_it_takes() {
        for key in TuningKey::ALL {
            let set = match key.path() {
                ("", "initial") => EstimatorSet::ALL,
                ("", "prefilter") | ("rls", _) => EstimatorSet(0b0001),
                ("", _) => EstimatorSet(0),
                ("ekf", _) => EstimatorSet(0b0110),
                ("arx", _) => EstimatorSet(0b1000),
                path => panic!("{path:?}"),
            };
            assert_eq!(key.estimators(), set, "{key}");
            assert!(!key.is_empty(), "{key}");
            // The hint counts the values as `len` does, and names them where there are several.
            let (hint, count) = (key.values_hint(), key.len());
            let counted = ["", "a number", "", "3 numbers", "", "5 numbers"][count];
            assert!(!counted.is_empty() && hint.starts_with(counted), "{key}: '{hint}' for {count}");
            let names = match key {
                TuningKey::Initial => "b0 a1 a0",
                TuningKey::Prefilter => "f_lc_hz f_p_hz zeta_p",
                TuningKey::RlsP0 => "P(0) for b0 a1 a0",
                TuningKey::EkfQ | TuningKey::EkfP0 => "x1 x2 a0 a1 b0",
                _ => "a number",
            };
            assert!(hint.ends_with(names), "{key}: '{hint}'");
        }
    }

    #[test]
    fn a_preset_with_the_stage_of_another_takes_exactly_the_stage_keys() {
        let mut stage = Tuning::of(TuningPreset::Prbs);
        stage.set(TuningKey::Initial, &[1e6, 90.0, 3.9e7]).unwrap();
        stage.set(TuningKey::Prefilter, &[150.0, 1000.0, 0.2]).unwrap();
        stage.set(TuningKey::SpikeRatio, &[0.0]).unwrap();
        stage.set(TuningKey::EkfR, &[1e-3]).unwrap();
        let preset = Tuning::of(TuningPreset::Triangle);
        let both = preset.with_stage_of(&stage);
        for key in TuningKey::ALL {
            let from = if TuningKey::STAGE.contains(&key) { &stage } else { &preset };
            assert_eq!(both.get(key), from.get(key), "{key}");
        }
    }

    #[test]
    fn q_sets_p0_to_ten_q_and_initial_reaches_every_estimator() {
        let mut t = Tuning::of(TuningPreset::Prbs);
        t.set(TuningKey::EkfQ, &[1.0, 2.0, 3.0, 4.0, 5.0]).unwrap();
        assert_eq!(t.ekf.p0_diag, [10.0, 20.0, 30.0, 40.0, 50.0]);
        t.set(TuningKey::EkfP0, &[1.0; 5]).unwrap();
        assert_eq!((t.ekf.q_diag[4], t.ekf.p0_diag[4]), (5.0, 1.0));
        t.set(TuningKey::Initial, &[1e6, 90.0, 3.9e7]).unwrap();
        let p = StageParams { b0: 1e6, a1: 90.0, a0: 3.9e7 };
        assert_eq!((t.rls.initial, t.ekf.initial, t.arx.initial), (p, p, p));
        assert_eq!(format!("{}", TuningKey::EkfReopen), "[ekf] reopen");
    }
}
