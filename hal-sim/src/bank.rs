//! The estimators chosen at run time (`--estimators rls,ekf,hekf,arx`), as one estimator bank for the pipeline,
//! and their tuning presets.

use nanopos_id::estimator::{Estimator, EstimatorBank, FilteredSample, Health};
use nanopos_id::estimators::arx::ArxEstimator;
use nanopos_id::estimators::crls::Crls;
use nanopos_id::estimators::ekf::{Cekf, Hekf};
pub use nanopos_id::estimators::Tuning;
use nanopos_id::{Real, StageParams};

/// The estimator names, in report order.
pub const NAMES: [&str; 4] = ["rls", "ekf", "hekf", "arx"];

/// Any subset of the four estimators, in one scalar.
pub struct Bank<T: Real> {
    /// Continuous-time RLS.
    pub rls: Option<Crls<T>>,
    /// Continuous EKF.
    pub ekf: Option<Cekf<T>>,
    /// Hybrid EKF.
    pub hekf: Option<Hekf<T>>,
    /// ARX.
    pub arx: Option<ArxEstimator<T>>,
}

impl<T: Real> Bank<T> {
    /// The estimators named in `names` (each one of [`NAMES`]).
    pub fn new(names: &[&str], tuning: &Tuning) -> Self {
        let on = |n: &str| names.contains(&n);
        Bank {
            rls: on("rls").then(|| Crls::new(tuning.rls.design())),
            ekf: on("ekf").then(|| Cekf::new(tuning.ekf.design())),
            hekf: on("hekf").then(|| Hekf::new(tuning.ekf.design())),
            arx: on("arx").then(|| ArxEstimator::new(tuning.arx.design())),
        }
    }

    /// `(name, estimate, health)` of each estimator present, in report order ([`Estimator::report`]: the ARX's
    /// conversion to the stage once for both).
    pub fn reports(&self) -> impl Iterator<Item = (&'static str, StageParams<T>, Health)> + '_ {
        [
            self.rls.as_ref().map(|e| ("rls", e.report())),
            self.ekf.as_ref().map(|e| ("ekf", e.report())),
            self.hekf.as_ref().map(|e| ("hekf", e.report())),
            self.arx.as_ref().map(|e| ("arx", e.report())),
        ]
        .into_iter()
        .flatten()
        .map(|(name, (p, h))| (name, p, h))
    }

    /// `(name, estimate)` of each estimator present, in report order.
    pub fn estimates(&self) -> impl Iterator<Item = (&'static str, StageParams<T>)> + '_ {
        self.reports().map(|(name, p, _)| (name, p))
    }
}

impl<T: Real> EstimatorBank<T> for Bank<T> {
    const LEN: usize = 4;
    fn update_selected(&mut self, s: &FilteredSample<T>, mask: u8) {
        let on = |i: u8| mask & (1 << i) != 0;
        if let Some(e) = self.rls.as_mut().filter(|_| on(0)) {
            e.update(s);
        }
        if let Some(e) = self.ekf.as_mut().filter(|_| on(1)) {
            e.update(s);
        }
        if let Some(e) = self.hekf.as_mut().filter(|_| on(2)) {
            e.update(s);
        }
        if let Some(e) = self.arx.as_mut().filter(|_| on(3)) {
            e.update(s);
        }
    }
    fn reset(&mut self) {
        self.rls.as_mut().map(Estimator::reset);
        self.ekf.as_mut().map(Estimator::reset);
        self.hekf.as_mut().map(Estimator::reset);
        self.arx.as_mut().map(Estimator::reset);
    }
    fn resume(&mut self) {
        self.rls.as_mut().map(Estimator::resume);
        self.ekf.as_mut().map(Estimator::resume);
        self.hekf.as_mut().map(Estimator::resume);
        self.arx.as_mut().map(Estimator::resume);
    }
}
