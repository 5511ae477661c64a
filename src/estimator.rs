//! The interface every online estimator implements, and the slot in the pipeline that holds them.
//!
//! An estimator sees, once per sample, a [`FilteredSample`]: the filter-replica input `u'`, the measured `y'`, and
//! both through the pre-filter with the derivatives of the filtered output. Timing convention: `u_f` is the filtered
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
