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

use crate::estimator::{Adaptation, Health};
use crate::filters::Prefiltered;
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
        Tuning { rls: crls::CrlsDesign::default(), ekf: ekf::EkfDesign::paper(q), arx: arx::ArxDesign::default() }
    }

    /// Design every estimator's configuration in the working scalar.
    #[inline(never)]
    pub fn design<T: Real>(&self) -> TuningConfig<T> {
        TuningConfig { rls: self.rls.design(), ekf: self.ekf.design(), arx: self.arx.design() }
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

/// Every estimator, in the order of [`crate::control::ESTIMATOR_NAMES`] (`rls`, `ekf`, `hekf`, `arx`): the bank the
/// firmware's interrupt runs, any subset of it selected at run time.
pub type FullBank<T> = (crls::Crls<T>, ekf::Cekf<T>, ekf::Hekf<T>, arx::ArxEstimator<T>);

/// Every estimator, fresh, with the tuning `cfg`.
pub fn full_bank<T: Real>(cfg: &TuningConfig<T>) -> FullBank<T> {
    (crls::Crls::new(cfg.rls), ekf::Cekf::new(cfg.ekf), ekf::Hekf::new(cfg.ekf), arx::ArxEstimator::new(cfg.arx))
}

/// Model (1)'s parameters from an estimator that integrates its continuous equations by one RK4 step of `step` a
/// sample. Such a step turns an oscillation at `w` by `w step (1 - (w step)^4 / 120)`: a model run that way is slow,
/// and a fit settles where that matches the data, on `a0 (1 + (w step)^4 / 60)` (+1.4e-4 at 483 Hz and 10 kHz).
/// Undone here: `a0` and `b0` scaled by `1 - (a0 step^2)^2 / 60` (RK4 keeps a fixed point where it is, so the DC
/// gain `b0 / a0` was right). For reporting, not the sample path.
pub(crate) fn undo_rk4_dispersion<T: Real>(p: StageParams<T>, step: T) -> StageParams<T> {
    let turn = p.a0 * step * step;
    let back = T::one() - turn * turn / T::of(60.0);
    StageParams { a0: p.a0 * back, b0: p.b0 * back, ..p }
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

/// The persistent-excitation monitor's setting, designed: the filtered input's power averaged over `tau_s` (a first
/// order average) and the floor below which it means the input is too weak to identify from; and the averages over
/// [`PE_SPREAD_TAU_S`] that tell a single sinusoid (see [`PeMonitor`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct PeConfig<T> {
    alpha: T,
    floor: T,
    spread_alpha: T,
    /// `1 - PE_SPREAD_MIN`, or the greatest value (never exceeded) when the monitor is off.
    single_ratio: T,
}

/// Below this spectral spread of the filtered input (0 for a single sinusoid; over [`PE_SPREAD_TAU_S`], 0.06 or
/// more for the paper's PRBS and 0.9 or more for its smoothed triangle) the input cannot identify the three
/// parameters.
pub const PE_SPREAD_MIN: f64 = 0.01;
/// Time constant of the averages the spread is computed from, s.
pub const PE_SPREAD_TAU_S: f64 = 0.03;

impl<T: Scalar> PeConfig<T> {
    /// Floor `floor_v2` (V^2; 0: the monitor off), average over `tau_s`, sample period `t_s`.
    pub(crate) fn new(floor_v2: f64, tau_s: f64, t_s: f64) -> Self {
        PeConfig {
            alpha: T::of(t_s / tau_s),
            floor: T::of(floor_v2),
            spread_alpha: T::of(t_s / PE_SPREAD_TAU_S),
            single_ratio: if floor_v2 > 0.0 { T::of(1.0 - PE_SPREAD_MIN) } else { T::greatest() },
        }
    }
}

/// The persistent-excitation monitor every online estimator runs on the pre-filtered input `u_f`. It starves the
/// estimator (its parameters and their covariance held, [`Adaptation::Starved`] reported) when the input is
/// - **too weak**: its power, averaged over 10 ms, below the floor (1e-6 V^2). With nothing to learn from, the
///   parameters would only follow the noise: 10 s after the excitation stopped, the continuous-time RLS was 66 % off,
///   the ARX 123 %;
/// - **not rich enough**: a single sinusoid identifies two numbers (a gain and a phase), not three, and along the
///   direction it leaves open the estimates drift: 10 s of a 1 V sine at 100, 450 or 1 000 Hz after PRBS moved the
///   continuous-time RLS by up to 391 %, the ARX by 284 %, the EKFs by 2.3 %. For a single sinusoid `u'' = -w^2 u`
///   at every instant, so the Cauchy-Schwarz inequality `<u u''>^2 <= <u^2> <u''^2>` holds with equality whatever
///   the averaging window; its slack, the spread `1 - <u u''>^2 / (<u^2> <u''^2>)`, is 1e-6 to 2e-3 for such sines
///   on the simulated board (the DAC's steps and the replicas keep it off zero) and at least 0.06 for the paper's
///   PRBS over 30 ms (0.02 over 10 ms). Below [`PE_SPREAD_MIN`] it starves, within 0.5 s of a switch from PRBS
///   to a sine. An input that is one frequency at a time over 30 ms (a slow sweep) would starve too (reasoned, not
///   measured): a floor of 0 turns the monitor off for such data.
///
/// `hal-sim/tests/ekf_health.rs` measures both. Cost: 4 running means and a comparison, about 15 flops per sample.
///
/// [`Adaptation::Starved`]: crate::estimator::Adaptation::Starved
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct PeMonitor<T> {
    /// The filtered input's power, V^2 (over `tau_s`).
    pub(crate) power: T,
    /// `<u^2>`, `<u''^2>` and `<u u''>` over [`PE_SPREAD_TAU_S`].
    uu: T,
    aa: T,
    ua: T,
}

impl<T: Scalar> PeMonitor<T> {
    /// One sample of `u_f`: whether to adapt, given the user's `adapting`. While the user lets it adapt, the health
    /// report says whether the input starves it.
    #[inline(always)]
    pub(crate) fn adapt(
        &mut self,
        cfg: &PeConfig<T>,
        u_f: &Prefiltered<T>,
        adapting: bool,
        health: &mut Health,
    ) -> bool {
        let (u, a) = (u_f.value, u_f.d2);
        let u2 = u * u;
        self.power += cfg.alpha * (u2 - self.power);
        self.uu += cfg.spread_alpha * (u2 - self.uu);
        self.aa += cfg.spread_alpha * (a * a - self.aa);
        self.ua += cfg.spread_alpha * (u * a - self.ua);
        let single = self.ua * self.ua > cfg.single_ratio * (self.uu * self.aa);
        let starved = self.power < cfg.floor || single;
        if adapting {
            health.adaptation = if starved { Adaptation::Starved } else { Adaptation::Adapting };
        }
        adapting && !starved
    }
}
