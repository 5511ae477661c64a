//! The estimators, one file each, and what they share.
//!
//! - [`arx`]: the stage as a 2nd-order ARX at the sample rate, by the discrete RLS, converted through the exact ZOH.
//! - [`crls`]: the paper's continuous-time RLS with forgetting (Section III).
//! - [`ekf`]: the paper's continuous and hybrid extended Kalman filters (Sections IV-A, IV-B).
//! - [`lsq`]: batch and exponentially weighted least squares (textbook 13.2-13.4) by a streaming QR factorisation.
//! - [`rls`]: discrete recursive least squares, every form of the lecture notes, in Bierman UD form.
//! - [`tuning`]: tuning values set one at a time by name, the same checks for the host's TOML and the console.

pub mod arx;
pub mod crls;
pub mod ekf;
pub mod lsq;
pub mod rls;
pub mod tuning;

pub use tuning::{Expected, Refused, TuningKey};

use crate::control::EstimatorSet;
use crate::estimator::{Adaptation, Health, PeLevel};
use crate::filters::prefilter::PrefilterDesign;
use crate::{Real, Scalar, StageParams};

/// The paper's three estimators: continuous-time RLS, continuous EKF, hybrid EKF.
pub type PaperBank<T> = (crls::Crls<T>, ekf::Cekf<T>, ekf::Hekf<T>);

/// The paper's three estimators at their defaults (the PRBS tuning: the paper's RLS settings and `Q2`).
pub fn paper_bank<T: Real>() -> PaperBank<T> {
    let ekf = ekf::EkfDesign::default();
    (crls::Crls::new(crls::CrlsDesign::default().design()), ekf::Cekf::new(ekf.design()), ekf::Hekf::new(ekf.design()))
}

/// Tuning of every estimator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tuning {
    /// Continuous-time RLS.
    pub rls: crls::CrlsDesign,
    /// Both EKFs.
    pub ekf: ekf::EkfDesign,
    /// The ARX RLS.
    pub arx: arx::ArxDesign,
    /// The pipeline's spike gate: its ratio ([`crate::pipeline::FaultSettings::spike_ratio`], 0: off). Not an
    /// estimator's, but what the estimators are fed: a tuning value so that the console's `tune spike_ratio` sets it
    /// at run time and a recording's tuning lines carry it to the replay.
    pub spike_ratio: u16,
}

impl Tuning {
    /// `prbs`: the paper's Q2 and RLS settings (the default); `triangle`: Q1.
    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "prbs" => Some(Self::of(crate::control::TuningPreset::Prbs)),
            "triangle" => Some(Self::of(crate::control::TuningPreset::Triangle)),
            _ => None,
        }
    }

    /// The paper's tuning for an input: the EKFs' `Q2` for PRBS, `Q1` for the triangle; the RLS settings for both.
    pub fn of(preset: crate::control::TuningPreset) -> Self {
        let q = match preset {
            crate::control::TuningPreset::Prbs => ekf::EkfDesign::Q2,
            crate::control::TuningPreset::Triangle => ekf::EkfDesign::Q1,
        };
        Tuning {
            rls: crls::CrlsDesign::default(),
            ekf: ekf::EkfDesign::paper(q),
            arx: arx::ArxDesign::default(),
            spike_ratio: crate::pipeline::FaultSettings::default().spike_ratio,
        }
    }

    /// The estimators (in [`crate::control::ESTIMATOR_NAMES`]' order) whose tuning differs between `self` and `to`:
    /// those a change from one to the other restarts. Both EKFs have one tuning; the initial parameters are every
    /// estimator's, the pre-filter the continuous-time RLS's own (the others read the pipeline's, which they identify
    /// the same stage through), and the spike gate's ratio none's.
    ///
    /// Compared key by key ([`TuningKey::ALL`], every value a tuning can change; the designs' other fields are the
    /// same in every tuning) and bit by bit: the designs' own comparison, field by field in software double
    /// precision, took 1.3 KiB of the firmware's flash.
    pub fn restarted_by(&self, to: &Tuning) -> EstimatorSet {
        let differs = |key: TuningKey| self.get(key).map(f64::to_bits) != to.get(key).map(f64::to_bits);
        EstimatorSet::restarted_by(TuningKey::ALL.into_iter().filter(|&k| differs(k)))
    }

    /// Design every estimator's configuration in the working scalar.
    #[inline(never)]
    pub fn design<T: Real>(&self) -> TuningConfig<T> {
        TuningConfig { rls: self.rls.design(), ekf: self.ekf.design(), arx: self.arx.design() }
    }

    /// [`Tuning::design`], or why the estimators could not run it although each value is in its range (they would
    /// reset over and over): a constant out of `T`'s range once normalised ([`TuningConfig::fits`]), or a
    /// pre-filter the continuous-time RLS cannot integrate by RK4 at the sample period
    /// ([`PrefilterDesign::rk4_amplification`] above 1; the pipeline's own pre-filter is exact at any pole), or a
    /// pre-filter that rings for longer than [`PrefilterDesign::MAX_TIME_CONSTANT_S`].
    pub fn runnable<T: Real>(&self) -> Result<TuningConfig<T>, Unrunnable> {
        let growth = self.rls.prefilter.rk4_amplification(self.rls.sample_period_s);
        if growth.is_nan() || growth > 1.0 {
            return Err(Unrunnable::PrefilterRk4 { growth });
        }
        let tau_s = self.rls.prefilter.slowest_time_constant_s();
        if tau_s.is_nan() || tau_s > PrefilterDesign::MAX_TIME_CONSTANT_S {
            return Err(Unrunnable::PrefilterSlow { tau_s });
        }
        let designed = self.design::<T>();
        if designed.fits() {
            Ok(designed)
        } else {
            Err(Unrunnable::Range)
        }
    }
}

/// Why the estimators cannot run a tuning ([`Tuning::runnable`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Unrunnable {
    /// A normalised constant leaves the working scalar's range.
    Range,
    /// The continuous-time RLS's RK4 step amplifies the pre-filter's fastest pole `growth` times per sample.
    PrefilterRk4 {
        /// `|R(lambda T)|`, above 1.
        growth: f64,
    },
    /// The pre-filter's slowest pole has the time constant `tau_s` (or none: NaN), beyond
    /// [`PrefilterDesign::MAX_TIME_CONSTANT_S`].
    PrefilterSlow {
        /// [`PrefilterDesign::slowest_time_constant_s`], s.
        tau_s: f64,
    },
}

impl core::fmt::Display for Unrunnable {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Unrunnable::Range => f.write_str(
                "the estimators cannot hold this tuning: a normalised constant (Q, P0 or a bound over the square of \
                 an initial parameter, 1 / R, ...) leaves the range of their arithmetic",
            ),
            Unrunnable::PrefilterRk4 { growth } => write!(
                f,
                "the continuous-time RLS steps its pre-filter by RK4 at the sample period, and this pre-filter has a \
                 pole too fast for that step (amplified {} times a sample): lower f_lc, f_p or zeta_p",
                crate::text::Num(*growth, 3)
            ),
            Unrunnable::PrefilterSlow { tau_s } => write!(
                f,
                "this pre-filter is too slow: its slowest pole's time constant is {} s, over {} s (it rings on, \
                 which the estimators take for excitation); raise f_lc, or zeta_p f_p, to {} Hz or more",
                crate::text::Num(*tau_s, 3),
                crate::text::Num(PrefilterDesign::MAX_TIME_CONSTANT_S, 3),
                crate::text::Num(1.0 / (2.0 * core::f64::consts::PI * PrefilterDesign::MAX_TIME_CONSTANT_S), 3)
            ),
        }
    }
}

/// [`Tuning`], designed: the estimators' configurations.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TuningConfig<T> {
    /// Continuous-time RLS.
    pub rls: crls::CrlsConfig<T>,
    /// Both EKFs.
    pub ekf: ekf::EkfConfig<T>,
    /// The ARX RLS.
    pub arx: arx::ArxConfig<T>,
}

impl<T: Real> TuningConfig<T> {
    /// Whether every constant of the design is a finite number of `T` and no normalisation vanished in it.
    ///
    /// The tuning's ranges ([`Expected`]) are checked in f64, before the design normalises: `Q`, `P0` and the
    /// bounds are divided by the squares of the initial parameters, `R` is inverted, and a value each range
    /// accepts can still leave f32's range (`tune initial 1e-20 70 6e6`: `q_b0 / b0^2 = 5e48`; `tune ekf r 1e-45`:
    /// `1 / R` infinite). An estimator designed so would reset on every sample; the console and `--tuning` files
    /// refuse such a tuning instead. A tuning that fits but diverges on the data (a `Q` far too large) is the health
    /// logic's to report (`resets=` in `status`).
    pub fn fits(&self) -> bool {
        self.rls.fits() && self.ekf.fits() && self.arx.fits()
    }
}

/// Every estimator, in the order of [`crate::control::ESTIMATOR_NAMES`] (`rls`, `ekf`, `hekf`, `arx`): the bank the
/// firmware's interrupt runs, any subset of it selected at run time.
pub type FullBank<T> = (crls::Crls<T>, ekf::Cekf<T>, ekf::Hekf<T>, arx::ArxEstimator<T>);

/// Every estimator, fresh, with the tuning `cfg`.
pub fn full_bank<T: Real>(cfg: &TuningConfig<T>) -> FullBank<T> {
    (crls::Crls::new(cfg.rls), ekf::Cekf::new(cfg.ekf), ekf::Hekf::new(cfg.ekf), arx::ArxEstimator::new(cfg.arx))
}

/// [`full_bank`]'s result written over the estimators `which` of `bank` in place, estimator by estimator: how the
/// interrupt applies a new tuning to the estimators whose tuning it changes ([`Tuning::restarted_by`]; the others'
/// is the same, and they run on). Building the bank and then moving it in copied its 1.3 KiB twice, much of it byte
/// by byte (the fields after the flags are not word-aligned in the copies' ranges): 1 400 instructions of a sample's
/// worst case.
pub fn restart_bank<T: Real>(bank: &mut FullBank<T>, cfg: &TuningConfig<T>, which: EstimatorSet) {
    if which.contains(0) {
        bank.0.restart(&cfg.rls);
    }
    if which.contains(1) {
        bank.1.restart(&cfg.ekf);
    }
    if which.contains(2) {
        bank.2.restart(&cfg.ekf);
    }
    if which.contains(3) {
        bank.3.restart(&cfg.arx);
    }
}

/// Model (1)'s parameters from an estimator that integrates its continuous equations by one RK4 step of `step` a
/// sample. Such a step turns an oscillation at `w` by `w step (1 - (w step)^4 / 120)`: a model run that way is slow,
/// and a fit settles where that matches the data, on `a0 (1 + (w step)^4 / 60)` (+1.4e-4 at 483 Hz and 10 kHz).
/// Undone here: `a0` and `b0` scaled by `1 - (a0 step^2)^2 / 60` (RK4 keeps a fixed point where it is, so the DC
/// gain `b0 / a0` was right). For reporting, not the sample path.
///
/// Only where the series holds, a resonance well below the sample rate (`a0 step^2` 0.07 for the paper's stage):
/// from `a0 step^2 = 1` (`f0 = fs / 2 pi`) on the estimate is reported as it is. Applied to an estimate gone wild (on
/// a pre-filter tuned to ring for ever, in a random console session), the correction overflowed f32 and reported a
/// finite state as `a0 = -inf` (from an `a0` of about 1e20 on).
pub(crate) fn undo_rk4_dispersion<T: Real>(p: StageParams<T>, step: T) -> StageParams<T> {
    let turn = p.a0 * step * step;
    if !(turn < T::one() && -turn < T::one()) {
        return p;
    }
    let back = T::one() - turn * turn / T::of(60.0);
    StageParams { a0: p.a0 * back, b0: p.b0 * back, ..p }
}

/// Where an estimator whose report [`undo_rk4_dispersion`] corrects starts its `a0` and `b0`, relative to the
/// initial parameters: the model whose report is `initial`, so that a filter just started or reset reports the
/// initial parameters it was given (started at them, the continuous EKF reported `a0 = 5.99964e6` for the paper's
/// `6e6`), and its model starts where one fitted to a stage of those parameters would settle.
///
/// With `u = a0 step^2` the initial turn and `x` the model's, the root of `x - x^3 / 60 = u`, by three Newton steps
/// from `u` (within 1e-10 of it after two at the end of the range, to the rounding after three), in the working
/// scalar as the report's correction is, and out of line: 196 B of the firmware (in f64, a fixed-point iteration
/// unrolled 1.6 KiB of soft double into it, these Newton steps 576 B). 1 where the correction does not apply, and
/// also just below it, for `u` from about 0.984 to 1, where the model's turn would be beyond it (no model reports
/// those initial parameters).
#[inline(never)]
pub(crate) fn rk4_dispersed_start<T: Real>(a0: T, step: T) -> T {
    let u = a0 * step * step;
    if !(u != T::zero() && u < T::one() && -u < T::one()) {
        return T::one();
    }
    let mut x = u;
    for _ in 0..3 {
        let x2 = x * x;
        x = x - (x - x * x2 / T::of(60.0) - u) / (T::one() - x2 / T::of(20.0));
    }
    if x < T::one() && -x < T::one() {
        x / u
    } else {
        T::one()
    }
}

/// `a + h b`, the RK4 stage argument.
#[inline(always)]
pub(crate) fn axpy<T: Real, const N: usize>(a: &[T; N], b: &[T; N], h: T) -> [T; N] {
    core::array::from_fn(|i| a[i] + h * b[i])
}

/// `out = x + h6 (k1 + 2 k2 + 2 k3 + k4)`, the RK4 step, with `h6 = h / 6` computed once in the configuration (the
/// same rounding as per step, without a division per sample: VDIV takes 14 cycles on the M4F). `out` may be where
/// `x` was copied from: written in place, not returned (a returned array is built on the stack and copied).
#[inline(always)]
pub(crate) fn rk4_combine<T: Real, const N: usize>(out: &mut [T; N], x: &[T; N], k: [&[T; N]; 4], h6: T) {
    let two = T::of(2.0);
    for i in 0..N {
        out[i] = x[i] + h6 * (k[0][i] + two * (k[1][i] + k[2][i]) + k[3][i]);
    }
}

/// An estimator's side of the persistent-excitation monitor ([`PeMonitor`], which the pipeline runs once for all):
/// its floor on the filtered input's power, V^2. A floor of 0 turns both of the monitor's tests off.
///
/// [`PeMonitor`]: crate::estimator::PeMonitor
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct PeFloor<T>(T);

/// Whether every value of every slice is a finite number. Not inlined: a check at the console's pace, where
/// unrolled it cost 1.7 KiB of flash.
#[inline(never)]
pub(crate) fn all_finite<T: Real>(slices: &[&[T]]) -> bool {
    slices.iter().all(|s| s.iter().all(|x| x.is_finite()))
}

impl<T: Real> PeFloor<T> {
    /// Whether the floor is a finite number.
    pub(crate) fn fits(&self) -> bool {
        self.0.is_finite()
    }
}

impl<T: Scalar> PeFloor<T> {
    /// Floor `floor_v2`, V^2 (0: the monitor off).
    pub(crate) fn new(floor_v2: f64) -> Self {
        PeFloor(T::of(floor_v2))
    }

    /// Whether to adapt on a sample of excitation `level`, given the user's `adapting`. While the user lets it
    /// adapt, the health report says whether the input starves it.
    #[inline(always)]
    pub(crate) fn adapt(&self, level: &PeLevel<T>, adapting: bool, health: &mut Health) -> bool {
        let starved = self.0 > T::zero() && (level.power < self.0 || level.single);
        if adapting {
            health.adaptation = if starved { Adaptation::Starved } else { Adaptation::Adapting };
        }
        adapting && !starved
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::Estimator;

    /// The RK4 dispersion is undone for a resonance well below the sample rate, and an estimate beyond it is
    /// reported as it is: finite in, finite out (a wild `a0` of 1e20 came out as `-inf`).
    #[test]
    fn the_dispersion_is_undone_only_where_its_series_holds() {
        let t = 1e-4f32;
        let stage = StageParams { a0: 9.21e6f32, a1: 86.8, b0: 1.07e6 };
        let back = 1.0 - (9.21e6f32 * t * t).powi(2) / 60.0;
        assert_eq!(undo_rk4_dispersion(stage, t), StageParams { a0: stage.a0 * back, b0: stage.b0 * back, ..stage });
        for a0 in [1e8f32, 1e20, -1e20, f32::MAX] {
            let wild = StageParams { a0, a1: -3e8, b0: 1e30 };
            assert_eq!(undo_rk4_dispersion(wild, t), wild);
        }
        // At a turn of exactly 1 or -1 (a step of 2^-10, `a0` +-2^20, all exact) the series no longer holds either.
        for a0 in [1048576.0f32, -1048576.0] {
            let at_one = StageParams { a0, a1: 70.0, b0: 5e5 };
            assert_eq!(undo_rk4_dispersion(at_one, 1.0 / 1024.0), at_one);
        }
    }

    /// A model started at [`rk4_dispersed_start`] reports the initial parameters (in f64 to its rounding), from a slow
    /// stage to where the correction stops; beyond it the start is the initial parameters themselves.
    #[test]
    fn a_model_started_dispersed_reports_the_initial_parameters() {
        let t = 1e-4f64;
        for a0 in [1.0, 6e6, 9.21e6, 4e7, 9.8e7, -6e6] {
            let initial = StageParams { a0, a1: 70.0, b0: 5e5 };
            let f = rk4_dispersed_start(a0, t);
            assert!(f >= 1.0, "{a0}: {f}");
            let started = StageParams { a0: a0 * f, b0: initial.b0 * f, ..initial };
            let reported = undo_rk4_dispersion(started, t);
            for (r, i) in [(reported.a0, a0), (reported.b0, initial.b0)] {
                assert!(((r - i) / i).abs() < 4.0 * f64::EPSILON, "{a0}: {r} for {i}");
            }
        }
        let at_paper = rk4_dispersed_start(StageParams::INITIAL.a0, t);
        assert!((at_paper - 1.0 - 6e-5).abs() < 1e-6, "{at_paper}");
        // Also for a negative `a0` whose model would be beyond the series' turn (`u = -0.99`: `x = -1.007`).
        for a0 in [0.99e8, 1.01e8, 1e20, f64::MAX, 0.0, f64::NAN, -0.99e8, -1e20] {
            assert_eq!(rk4_dispersed_start(a0, t), 1.0, "{a0}");
        }
    }

    /// Every estimator, started and after a reset, reports the initial parameters it was given, in f32 and f64 (the
    /// continuous EKF and the continuous-time RLS reported the paper's `a0 = 6e6` as 5.99964e6 and 5.99961e6:
    /// started at them, their models were ones whose report undoes the RK4 step's dispersion). Within an ulp; the
    /// ARX's through its discrete equivalent and back, within 2.8 ulps in f32 and 143 in f64 (`a1` from the log of
    /// the poles' radius, near 1).
    #[test]
    fn every_estimator_started_or_reset_reports_its_initial_parameters() {
        fn check<T: Real>(initial: StageParams<f64>, arx_ulps: f64) {
            let mut tuning = Tuning::preset("prbs").unwrap();
            tuning.set(TuningKey::Initial, &[initial.b0, initial.a1, initial.a0]).unwrap();
            let mut bank = full_bank::<T>(&tuning.design());
            let reports = |bank: &mut FullBank<T>, reset: bool| {
                if reset {
                    bank.0.reset();
                    bank.1.reset();
                    bank.2.reset();
                    bank.3.reset();
                }
                [bank.0.params(), bank.1.params(), bank.2.params(), bank.3.params()]
            };
            for reset in [false, true] {
                for (name, p) in crate::control::ESTIMATOR_NAMES.iter().zip(reports(&mut bank, reset)) {
                    for (got, want) in [(p.a0, initial.a0), (p.a1, initial.a1), (p.b0, initial.b0)] {
                        let off = (got.as_f64() / want - 1.0).abs() / T::epsilon().as_f64();
                        let ulps = if *name == "arx" { arx_ulps } else { 1.0 };
                        assert!(off <= ulps, "{name} (reset {reset}): {} for {want}, {off} ulps", got.as_f64());
                    }
                }
            }
        }
        for initial in [StageParams::INITIAL, StageParams { b0: 2e6, a1: 300.0, a0: 3.9e7 }] {
            check::<f32>(initial, 4.0);
            check::<f64>(initial, 256.0);
        }
    }

    /// The PRBS preset with `key` set to `values`.
    fn prbs_with(key: TuningKey, values: &[f64]) -> Tuning {
        let mut t = Tuning::preset("prbs").unwrap();
        t.set(key, values).unwrap();
        t
    }

    /// The presets by name, and the estimators a change of tuning restarts: those whose tuning it changed, bit by bit.
    #[test]
    fn a_change_of_tuning_restarts_the_estimators_whose_values_it_changed() {
        use crate::control::TuningPreset;
        assert_eq!(Tuning::preset("prbs"), Some(Tuning::of(TuningPreset::Prbs)));
        assert_eq!(Tuning::preset("triangle"), Some(Tuning::of(TuningPreset::Triangle)));
        assert_eq!(Tuning::preset("sine"), None);
        let base = Tuning::of(TuningPreset::Prbs);
        assert_eq!(base.restarted_by(&base), EstimatorSet(0));
        // Q1 and Q2 differ in the EKFs' `Q` (and `P0`) only.
        assert_eq!(base.restarted_by(&Tuning::of(TuningPreset::Triangle)), EstimatorSet(0b0110));
        let changed = |key: TuningKey, values: &[f64]| base.restarted_by(&prbs_with(key, values));
        assert_eq!(changed(TuningKey::Initial, &[1e6, 90.0, 3.9e7]), EstimatorSet::ALL);
        assert_eq!(changed(TuningKey::Prefilter, &[150.0, 1000.0, 0.2]), EstimatorSet(0b0001));
        assert_eq!(changed(TuningKey::ArxLambda, &[0.999]), EstimatorSet(0b1000));
        assert_eq!(changed(TuningKey::SpikeRatio, &[0.0]), EstimatorSet(0));
        // Two values apart by an ulp differ; the same value set again does not.
        let r = base.get(TuningKey::EkfR)[0];
        assert_eq!(changed(TuningKey::EkfR, &[r.next_up()]), EstimatorSet(0b0110));
        assert_eq!(changed(TuningKey::EkfR, &[r]), EstimatorSet(0));
    }

    /// A tuning whose values are each in range but which the estimators cannot run is refused with the reason, each
    /// test at its own bound: RK4 growth above 1 (a slow pole's, exactly 1, passes that test), a time constant above
    /// [`PrefilterDesign::MAX_TIME_CONSTANT_S`] (exactly it passes), a constant out of f32's range.
    #[test]
    fn a_tuning_the_estimators_cannot_run_is_refused_with_its_reason() {
        assert!(Tuning::preset("prbs").unwrap().runnable::<f32>().is_ok());
        // A low-pass corner at 4.9 kHz: `lambda T = -3.08`, beyond RK4's interval of stability (-2.79).
        let fast = prbs_with(TuningKey::Prefilter, &[4900.0, 450.0, 0.7]);
        let growth = fast.rls.prefilter.rk4_amplification(fast.rls.sample_period_s);
        assert!(growth > 1.0 && fast.runnable::<f32>() == Err(Unrunnable::PrefilterRk4 { growth }), "{growth}");
        let said = format!("{}", Unrunnable::PrefilterRk4 { growth: 1.5 });
        assert!(said.contains("amplified 1.5 times a sample"), "{said}");
        // A low corner at 1e-20 Hz: its RK4 factor rounds to exactly 1, its time constant is for ever.
        let slow = prbs_with(TuningKey::Prefilter, &[1e-20, 450.0, 0.7]);
        assert_eq!(slow.rls.prefilter.rk4_amplification(slow.rls.sample_period_s), 1.0);
        assert!(matches!(slow.runnable::<f32>(), Err(Unrunnable::PrefilterSlow { tau_s }) if tau_s > 1e18));
        // At 1 Hz, 0.16 s; at the corner whose time constant is the bound to the last bit, accepted.
        let one_hz = prbs_with(TuningKey::Prefilter, &[1.0, 450.0, 0.7]);
        let tau_s = one_hz.rls.prefilter.slowest_time_constant_s();
        assert!(tau_s > 0.15 && one_hz.runnable::<f64>() == Err(Unrunnable::PrefilterSlow { tau_s }), "{tau_s}");
        let said = format!("{}", Unrunnable::PrefilterSlow { tau_s });
        assert!(said.contains("time constant is 0.159 s, over 0.1 s") && said.contains("to 1.59 Hz"), "{said}");
        let near = 1.0 / (2.0 * core::f64::consts::PI * PrefilterDesign::MAX_TIME_CONSTANT_S);
        let ulps_away = |k: i32| (0..k.abs()).fold(near, |f, _| if k > 0 { f.next_up() } else { f.next_down() });
        let at_bound = (-8..=8)
            .map(|k| prbs_with(TuningKey::Prefilter, &[ulps_away(k), 450.0, 0.7]))
            .find(|t| t.rls.prefilter.slowest_time_constant_s() == PrefilterDesign::MAX_TIME_CONSTANT_S)
            .expect("a corner within 8 ulps whose time constant rounds to the bound");
        assert!(at_bound.runnable::<f64>().is_ok());
        // In range for the tuning, out of f32's once normalised.
        let tiny_r = prbs_with(TuningKey::EkfR, &[1e-45]);
        assert_eq!(tiny_r.runnable::<f32>(), Err(Unrunnable::Range));
        assert!(tiny_r.runnable::<f64>().is_ok());
        assert!(format!("{}", Unrunnable::Range).contains("leaves the range of their arithmetic"));
    }

    /// Only the estimators named are restarted, each with the new configuration; the others run on as they were.
    #[test]
    fn restart_bank_restarts_only_the_estimators_it_is_given() {
        let old = Tuning::preset("prbs").unwrap();
        let new = prbs_with(TuningKey::Initial, &[1e6, 90.0, 3.9e7]);
        let reports = |bank: &FullBank<f64>| [bank.0.params(), bank.1.params(), bank.2.params(), bank.3.params()];
        let before = reports(&full_bank::<f64>(&old.design()));
        let after = reports(&full_bank::<f64>(&new.design()));
        for which in [0b0000, 0b0101, 0b1010, 0b1111] {
            let mut bank = full_bank::<f64>(&old.design());
            restart_bank(&mut bank, &new.design(), EstimatorSet(which));
            for (i, p) in reports(&bank).into_iter().enumerate() {
                let want = if which & (1 << i) != 0 { after[i] } else { before[i] };
                assert_eq!(p, want, "{which:04b}: estimator {i}");
            }
        }
    }

    /// A floor above zero starves on too little power or a single sinusoid, and reports it only while the user lets
    /// the estimator adapt; a floor of 0 turns both tests off.
    #[test]
    fn the_floor_decides_and_zero_turns_the_monitor_off() {
        let rich = PeLevel { power: 1e-3, single: false };
        let weak = PeLevel { power: 1e-7, single: false };
        let single = PeLevel { power: 1.0, single: true };
        let mut h = Health::new();
        let on = PeFloor::<f32>::new(1e-6);
        assert!(on.adapt(&rich, true, &mut h) && h.adaptation == Adaptation::Adapting);
        assert!(!on.adapt(&weak, true, &mut h) && h.adaptation == Adaptation::Starved);
        assert!(on.adapt(&rich, true, &mut h) && h.adaptation == Adaptation::Adapting);
        assert!(!on.adapt(&single, true, &mut h) && h.adaptation == Adaptation::Starved);
        // A power at the floor exactly is enough.
        let at_floor = PeLevel { power: 1e-6, single: false };
        assert!(on.adapt(&at_floor, true, &mut h) && h.adaptation == Adaptation::Adapting);
        let mut frozen = Health { adaptation: Adaptation::Frozen, ..Health::new() };
        assert!(!on.adapt(&rich, false, &mut frozen) && frozen.adaptation == Adaptation::Frozen);
        let off = PeFloor::<f32>::new(0.0);
        for level in [rich, weak, single, PeLevel::default()] {
            assert!(off.adapt(&level, true, &mut h) && h.adaptation == Adaptation::Adapting, "{level:?}");
        }
    }
}
