//! The interface every online estimator implements, and the slot in the pipeline that holds them.
//!
//! An estimator sees, once per sample, a [`FilteredSample`]: the filter-replica input `u'`, the measured `y'`, and
//! both through the pre-filter with the derivatives of the filtered output, and the filtered input's excitation level
//! ([`PeLevel`], measured once by the pipeline's [`PeMonitor`]). Timing convention: `u_f` is the filtered
//! command *issued* at this sample (it acts over the coming period); `y_f` is the response *measured* at this
//! sample, to the commands up to the previous one. An estimator that integrates the stage model from the previous
//! sample to this one therefore holds the previous sample's `u_f` (the paper's `f(x, u_{k-1})`).
//!
//! The estimators themselves (discrete RLS, continuous-time RLS, continuous and hybrid EKF) implement [`Estimator`];
//! the pipeline holds any number of them as an [`EstimatorBank`]: `()` for none, one estimator, or a tuple.

use crate::filters::Prefiltered;
use crate::{Real, StageParams};

/// What an estimator receives each sample.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FilteredSample<T> {
    /// Command after the filter replicas, `u'`, V.
    pub u: T,
    /// Measured displacement `y'`, um.
    pub y: T,
    /// `W_p u'` and its derivatives.
    pub u_f: Prefiltered<T>,
    /// `W_p y'` and its derivatives.
    pub y_f: Prefiltered<T>,
    /// How well `u_f` excites the stage, measured once for every estimator by the pipeline's [`PeMonitor`].
    pub pe: PeLevel<T>,
}

/// The persistent-excitation monitor's measurement of one sample of `u_f`: what each estimator compares with its
/// own floor (`pe_floor_v2`) to decide whether the input can identify the three parameters. The default (no power)
/// starves every estimator whose monitor is on.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PeLevel<T> {
    /// The filtered input's power averaged over [`PE_POWER_TAU_S`], V^2.
    pub power: T,
    /// Whether `u_f` looks like a single sinusoid over [`PE_SPREAD_TAU_S`]: its spread below [`PE_SPREAD_MIN`].
    pub single: bool,
}

/// Time constant of the power average of [`PeLevel`], s.
pub const PE_POWER_TAU_S: f64 = 0.01;
/// Below this spectral spread of the filtered input (0 for a single sinusoid; over [`PE_SPREAD_TAU_S`], 0.06 or
/// more for the paper's PRBS and 0.9 or more for its smoothed triangle) the input cannot identify the three
/// parameters.
pub const PE_SPREAD_MIN: f64 = 0.01;
/// Time constant of the averages the spread is computed from, s.
pub const PE_SPREAD_TAU_S: f64 = 0.03;

/// The persistent-excitation monitor on the pre-filtered input `u_f`, run once per sample by the pipeline (every
/// estimator reads the same `u_f`). An estimator whose floor is above zero starves (its parameters and their
/// covariance held, [`Adaptation::Starved`] reported) when the input is
/// - **too weak**: its power, averaged over 10 ms, below the floor (1e-6 V^2 by default). With nothing to learn
///   from, the parameters would only follow the noise: 10 s after the excitation stopped, the continuous-time RLS was
///   66 % off, the ARX 123 %;
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
/// Measured once, not in each estimator: an estimator reset or selected at run time sees the input's level at
/// once. A non-finite `u_f` (which the board cannot produce: it delivers integer codes) restarts the averages from
/// zero, which starves, so it cannot leave the monitor stuck. `hal-sim/tests/ekf_health.rs` measures
/// both tests. Cost: 4 running means, a comparison and the finiteness check, about 20 flops per sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeMonitor<T> {
    alpha: T,
    spread_alpha: T,
    /// `1 - PE_SPREAD_MIN`.
    single_ratio: T,
    /// The filtered input's power, V^2 (over [`PE_POWER_TAU_S`]).
    power: T,
    /// `<u^2>`, `<u''^2>` and `<u u''>` over [`PE_SPREAD_TAU_S`].
    uu: T,
    aa: T,
    ua: T,
}

impl<T: Real> PeMonitor<T> {
    /// At rest (no power: starving) for the sample period `t_s`.
    pub fn new(t_s: f64) -> Self {
        PeMonitor {
            alpha: T::of(t_s / PE_POWER_TAU_S),
            spread_alpha: T::of(t_s / PE_SPREAD_TAU_S),
            single_ratio: T::of(1.0 - PE_SPREAD_MIN),
            power: T::zero(),
            uu: T::zero(),
            aa: T::zero(),
            ua: T::zero(),
        }
    }

    /// One sample of `u_f`.
    #[inline(always)]
    pub fn update(&mut self, u_f: &Prefiltered<T>) -> PeLevel<T> {
        let (u, a) = (u_f.value, u_f.d2);
        let u2 = u * u;
        self.power += self.alpha * (u2 - self.power);
        self.uu += self.spread_alpha * (u2 - self.uu);
        self.aa += self.spread_alpha * (a * a - self.aa);
        self.ua += self.spread_alpha * (u * a - self.ua);
        // `power` and `uu` are finite exactly when `u` was; `aa` and `ua` when `a` was too (or, harmlessly, near
        // overflow anyway).
        if !(self.power + self.aa + self.ua).is_finite() {
            (self.power, self.uu, self.aa, self.ua) = (T::zero(), T::zero(), T::zero(), T::zero());
        }
        PeLevel { power: self.power, single: self.ua * self.ua > self.single_ratio * (self.uu * self.aa) }
    }
}

/// Whether an estimator is adapting its parameters.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum Adaptation {
    /// Parameters follow the data.
    Adapting,
    /// Frozen by the user.
    Frozen,
    /// Frozen by the persistent-excitation monitor: the input is too poor to identify from.
    Starved,
}

impl Adaptation {
    /// What the user's `set_adapting(on)` asks for: adapting or frozen.
    pub fn asked(on: bool) -> Self {
        if on {
            Adaptation::Adapting
        } else {
            Adaptation::Frozen
        }
    }
}

/// An estimator's health report.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub struct Health {
    /// Adapting or frozen, and why.
    pub adaptation: Adaptation,
    /// Times a non-finite value was caught and the estimator reset to its initial state.
    pub numeric_resets: u32,
    /// Samples rejected by innovation gating.
    pub rejected_samples: u32,
    /// Times a plant change was detected and the covariance reopened.
    pub changes_detected: u32,
    /// Times a state variance fell below zero in the covariance's integration and was repaired in place (the state
    /// decorrelated, its variance floored) instead of resetting the estimator. Rare and harmless one by one; a
    /// steady count means the integration of the covariance is marginal for this tuning and input.
    pub covariance_repairs: u32,
    /// Running RMS of the innovations (output minus the model's prediction), um; `NaN` if the estimator has no
    /// such notion. With a right model it is the measurement noise; far above it, the model does not fit the data
    /// (wrong tuning for the input, a plant the model cannot describe).
    pub innovation_rms_um: f32,
}

impl Health {
    /// Adapting, no events.
    pub const fn new() -> Self {
        Health {
            adaptation: Adaptation::Adapting,
            numeric_resets: 0,
            rejected_samples: 0,
            changes_detected: 0,
            covariance_repairs: 0,
            innovation_rms_um: f32::NAN,
        }
    }
}

impl Default for Health {
    fn default() -> Self {
        Self::new()
    }
}

/// An online estimator of the stage parameters.
pub trait Estimator<T: Real> {
    /// Short name used in reports and on the command line (`rls`, `ekf`, `hekf`, `arx`).
    const NAME: &'static str;
    /// Consume one sample.
    fn update(&mut self, sample: &FilteredSample<T>);
    /// The current estimate.
    fn params(&self) -> StageParams<T>;
    /// Covariance of the estimate, rows and columns in the order `(a0, a1, b0)`.
    fn param_covariance(&self) -> [[T; 3]; 3];
    /// Back to the initial parameters and covariance.
    fn reset(&mut self);
    /// Enable or freeze adaptation.
    fn set_adapting(&mut self, on: bool);
    /// Health report.
    fn health(&self) -> Health;
}

/// The pipeline's estimator slot: zero or more estimators updated together.
pub trait EstimatorBank<T: Real> {
    /// How many estimators the bank holds.
    const LEN: usize;
    /// Feed one sample to each.
    #[inline]
    fn update(&mut self, sample: &FilteredSample<T>) {
        self.update_selected(sample, u8::MAX);
    }
    /// Feed one sample to the estimators whose bit is set in `mask` (bit `i`: the bank's `i`-th estimator); the
    /// others are not touched (their state stays as it was).
    fn update_selected(&mut self, sample: &FilteredSample<T>, mask: u8);
    /// Reset each.
    fn reset(&mut self);
}

/// No estimators: the pipeline only excites and filters (recording, commissioning).
impl<T: Real> EstimatorBank<T> for () {
    const LEN: usize = 0;
    fn update_selected(&mut self, _: &FilteredSample<T>, _: u8) {}
    fn reset(&mut self) {}
}

macro_rules! bank_for_tuple {
    ($len:expr; $($name:ident . $idx:tt),+) => {
        impl<T: Real, $($name: Estimator<T>),+> EstimatorBank<T> for ($($name,)+) {
            const LEN: usize = $len;
            #[inline]
            fn update_selected(&mut self, sample: &FilteredSample<T>, mask: u8) {
                $(if mask & (1 << $idx) != 0 {
                    self.$idx.update(sample);
                })+
            }
            fn reset(&mut self) {
                $(self.$idx.reset();)+
            }
        }
    };
}
bank_for_tuple!(1; A.0);
bank_for_tuple!(2; A.0, B.1);
bank_for_tuple!(3; A.0, B.1, C.2);
bank_for_tuple!(4; A.0, B.1, C.2, D.3);
bank_for_tuple!(5; A.0, B.1, C.2, D.3, E.4);

#[cfg(test)]
mod tests {
    use super::*;

    /// A non-finite `u_f` restarts the averages from zero (no power: starving) instead of leaving them stuck, and
    /// they build up again from the next finite sample.
    #[test]
    fn a_non_finite_input_restarts_the_excitation_monitor() {
        let mut pe = PeMonitor::<f64>::new(1e-4);
        let at = |value: f64, d2: f64| Prefiltered { value, d1: 0.0, d2 };
        // A square wave's filtered curvature is not tied to its value: rich.
        let square = |k: u32| if (k / 20) % 2 == 0 { 1.0 } else { -1.0 };
        let mut level = PeLevel::default();
        for k in 0..1000 {
            level = pe.update(&at(square(k), -3.0 * square(k + 7)));
        }
        assert!(level.power > 0.9 && !level.single, "{level:?}");
        for bad in [at(f64::NAN, 0.0), at(0.5, f64::INFINITY), at(f64::NEG_INFINITY, f64::NAN)] {
            assert_eq!(pe.update(&bad), PeLevel { power: 0.0, single: false }, "{bad:?}");
            let next = pe.update(&at(1.0, 2.0));
            assert!(next.power.is_finite() && next.power > 0.0, "{next:?}");
        }
    }
}
