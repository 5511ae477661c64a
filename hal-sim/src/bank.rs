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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{Scenario, Simulation};

    /// 0.3 s of the paper's PRBS on the simulated board as the pipeline hands it to the estimators.
    fn samples() -> Vec<FilteredSample<f64>> {
        let (board, settings) = Scenario::Prbs.settings(1.0, Scenario::Prbs.default_seed());
        let mut sim = Simulation::new(board, &settings, ()).unwrap();
        (0..3_000).filter_map(|_| sim.step().1.estimator_input).collect()
    }

    fn reports(bank: &Bank<f64>) -> Vec<(&'static str, StageParams<f64>, Health)> {
        bank.reports().collect()
    }

    /// A bank of the four estimators with the paper's PRBS tuning.
    fn all_four() -> Bank<f64> {
        Bank::new(&NAMES, &Tuning::preset("prbs").unwrap())
    }

    /// The bank's mask selects by position in [`NAMES`]: an estimator not selected is not touched.
    #[test]
    fn a_mask_feeds_only_the_estimators_it_selects() {
        let (data, fresh) = (samples(), reports(&all_four()));
        assert!(data.len() > 2_000, "{} samples", data.len());
        let mut bank = all_four();
        for s in &data {
            bank.update_selected(s, 0b0101);
        }
        let now = reports(&bank);
        let names: Vec<&str> = now.iter().map(|r| r.0).collect();
        assert_eq!(names, NAMES);
        for (i, (got, was)) in now.iter().zip(&fresh).enumerate() {
            let selected = i % 2 == 0;
            assert_eq!(got.1 != was.1, selected, "{}: {:?} from {:?}", got.0, got.1, was.1);
        }
    }

    /// `reset` and `resume` reach every estimator of the bank: its reports are those of the four estimators run alone
    /// and reset or resumed at the same sample; without them the reports differ.
    #[test]
    fn reset_and_resume_reach_every_estimator() {
        let data = samples();
        let (first, rest) = data.split_at(1_500);
        let tuning = Tuning::preset("prbs").unwrap();
        for reset in [false, true] {
            let (mut bank, mut plain) = (all_four(), all_four());
            let mut alone = (
                Crls::new(tuning.rls.design()),
                Cekf::new(tuning.ekf.design()),
                Hekf::new(tuning.ekf.design()),
                ArxEstimator::new(tuning.arx.design()),
            );
            for s in first {
                bank.update(s);
                plain.update(s);
                alone.update(s);
            }
            if reset {
                bank.reset();
                alone.reset();
            } else {
                bank.resume();
                alone.resume();
            }
            for s in rest {
                bank.update(s);
                plain.update(s);
                alone.update(s);
            }
            let alone_reports = [alone.0.report(), alone.1.report(), alone.2.report(), alone.3.report()];
            let got = reports(&bank);
            for ((name, p, h), want) in got.iter().zip(alone_reports) {
                // (Compared as printed: a health's innovation RMS is NaN before its first block.)
                assert_eq!(format!("{:?}", (p, h)), format!("{:?}", want), "{name}, reset {reset}");
            }
            // What each does is seen: the reset estimators start again; resumed, the EKFs take their states again
            // from the next sample and the ARX its regressors.
            let plain = reports(&plain);
            for ((name, p, _), (_, q, _)) in got.iter().zip(&plain) {
                let seen = reset || *name != "rls";
                assert_eq!(p != q, seen, "{name}, reset {reset}: {p:?} against {q:?}");
            }
        }
    }
}
