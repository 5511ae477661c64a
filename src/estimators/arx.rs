//! `arx`: the stage identified as a 2nd-order ARX model at the sample rate by the discrete RLS, and converted to
//! the stage model `(a0, a1, b0)` through the exact zero-order-hold relation.
//!
//! ## Model
//! Sampled with a zero-order hold, the stage `x'' = -a0 x - a1 x' + b0 u` is exactly
//!
//! ```text
//! y(k) = A1 y(k-1) + A2 y(k-2) + B1 u(k-1) + B2 u(k-2)
//! A1 = trace Phi = 2 r cos(theta),  A2 = -det Phi = -r^2,   r e^{+-j theta} = e^{s T}, s = -a1/2 +- j sqrt(a0 - a1^2/4)
//! ```
//!
//! (`Phi`, `Gam` the ZOH matrices; `B1 = Gam_1`, `B2 = Phi_12 Gam_2 - Phi_22 Gam_1`). The estimator fits it to the
//! pre-filtered `u_f` and `y_f` (`W_p` is linear and common to both, so the relation carries over, and it
//! concentrates the fit on the resonance band); `u_f` of sample `k` acts over `[t_k, t_(k+1))`, so it is the
//! `u(k)` of this model. Back to the stage: `a1 = -ln(r^2) / T`, `a0 = (ln^2 r + theta^2) / T^2`, and `b0` matches
//! the static gain, `b0 / a0 = (B1 + B2) / (1 - A1 - A2)`.
//!
//! ## Numerics
//! At 10 kHz the poles sit near `z = 1` (`r = 0.9961`): the stage lives in the small quantities `1 + A2 = 1 - r^2`
//! (damping, 0.0078) and `1 - A1 - A2` (stiffness, 0.07), which a plain f32 `A1 = 1.93` would blur. So the RLS
//! estimates the deviation `delta` from the ARX image of the initial parameters (normalisation), and the
//! conversion forms the small quantities from their exact f64 nominal values plus `delta`; `ln r` is
//! `ln_1p(-(1 + A2)) / 2`.
//!
//! ## Tuning and health
//! Forgetting `lambda = 0.9998` (a 0.5 s memory: the payload change is followed within about a second), windup
//! bound on `trace F`, `F0` below. The persistent-excitation monitor ([`crate::estimator::PeMonitor`], run once by
//! the pipeline for every estimator) holds the estimate and `F` while the pre-filtered input's power is below 1e-6
//! V^2 (over 10 ms), or the input is a single sinusoid, reported as `Starved`: the bound keeps `F` finite
//! without it, but the forgetting let the noise carry the estimate 123 % off within 10 s of the excitation stopping
//! (`hal-sim/tests/ekf_health.rs`). A non-finite error, estimate or factor resets the estimator to its initial
//! state and counts it. A parameter pair with no continuous equivalent (real or non-positive poles, `r >= 1`)
//! leaves the reported parameters at their last valid value. Cost per update: the RLS (`n = 4`: 42 multiplies, 4
//! divisions) and 4 multiply-adds for the target; the conversion (`ln`, `atan2`, `sqrt`) only when parameters are
//! read.

use crate::estimator::{Adaptation, Estimator, FilteredSample, Health};
use crate::estimators::rls::{DiscreteRls, RlsErrors, RlsGain};
use crate::estimators::{all_finite, PeFloor};
use crate::linalg::zoh;
use crate::{Real, Scalar, StageParams};
use core::cell::Cell;

/// The ARX coefficients `[A1, A2, B1, B2]` of a stage, sampled at `t_s` (f64, exact).
pub fn arx_of_stage(p: &StageParams<f64>, t_s: f64) -> [f64; 4] {
    let (phi, psi) = zoh(&[[0.0, 1.0], [-p.a0, -p.a1]], t_s);
    let gam = [psi[0][1] * p.b0, psi[1][1] * p.b0];
    let a1 = phi[0][0] + phi[1][1];
    let a2 = -(phi[0][0] * phi[1][1] - phi[0][1] * phi[1][0]);
    [a1, a2, gam[0], phi[0][1] * gam[1] - phi[1][1] * gam[0]]
}

/// The stage of ARX coefficients given as `A1`, `1 + A2`, `1 - A1 - A2` and `B1 + B2` (the small quantities kept
/// apart for precision); `None` if the poles have no continuous underdamped equivalent.
fn stage_of_arx<T: Real>(a1: T, one_plus_a2: T, one_minus_sum: T, b_sum: T, inv_t: T) -> Option<StageParams<T>> {
    let r2 = T::one() - one_plus_a2;
    if !(r2 > T::zero() && one_plus_a2 > T::zero()) {
        return None;
    }
    let disc = T::of(4.0) * r2 - a1 * a1;
    if disc <= T::zero() || disc.is_nan() {
        return None;
    }
    let theta = disc.sqrt().atan2(a1);
    let ln_r = (-one_plus_a2).ln_1p() * T::of(0.5);
    let a0 = (ln_r * ln_r + theta * theta) * inv_t * inv_t;
    let p = StageParams { a0, a1: T::of(-2.0) * ln_r * inv_t, b0: a0 * b_sum / one_minus_sum };
    (p.a0.is_finite() && p.a1.is_finite() && p.b0.is_finite()).then_some(p)
}

/// The f64 conversion of plain coefficients `[A1, A2, B1, B2]`, for reports and tests.
pub fn stage_of_arx_f64(c: &[f64; 4], t_s: f64) -> Option<StageParams<f64>> {
    stage_of_arx(c[0], 1.0 + c[1], 1.0 - c[0] - c[1], c[2] + c[3], 1.0 / t_s)
}

/// Physical tuning of the `arx` estimator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ArxDesign {
    /// Forgetting factor per sample.
    pub lambda: f64,
    /// Windup bound on `trace F`.
    pub max_trace: f64,
    /// Initial `F` (diagonal), for `[A1, A2, B1, B2]` deviations.
    pub f0_diag: [f64; 4],
    /// Where the estimate starts.
    pub initial: StageParams<f64>,
    /// Sample period, s.
    pub sample_period_s: f64,
    /// Pre-filtered input power below which the estimate and `F` are held, V^2 (0: the excitation monitor off), as
    /// in the EKFs (see [`crate::estimator::PeMonitor`]).
    pub pe_floor_v2: f64,
}

impl Default for ArxDesign {
    /// `F0`: the ARX coefficients of the initial guess differ from the reference stage's by ~1e-2 (`A`) and ~1e-3
    /// (`B`); `F0` is a few hundred times those squared, so the prior weighs as much as a few samples.
    fn default() -> Self {
        ArxDesign {
            lambda: 0.9998,
            max_trace: 1e3,
            f0_diag: [1e-1, 1e-1, 1e-3, 1e-3],
            initial: StageParams::INITIAL,
            sample_period_s: 1e-4,
            pe_floor_v2: 1e-6,
        }
    }
}

/// The designed configuration in the working scalar.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ArxConfig<T> {
    gain: RlsGain<T>,
    f0: [T; 4],
    nominal: [T; 4],
    /// The nominal ARX coefficients, exact (the small quantities of the conversion are formed from these).
    nominal64: [f64; 4],
    sample_period_s: f64,
    /// The initial parameters in the working scalar (what the estimate reports before its first valid conversion).
    initial: StageParams<T>,
    pe: PeFloor<T>,
}

impl ArxDesign {
    /// Round to the working scalar (float or fixed point).
    #[inline(never)]
    pub fn design<T: Scalar>(&self) -> ArxConfig<T> {
        let n = arx_of_stage(&self.initial, self.sample_period_s);
        ArxConfig {
            gain: RlsGain::forgetting(T::of(self.lambda), T::of(self.max_trace)),
            f0: self.f0_diag.map(T::of),
            nominal: n.map(T::of),
            nominal64: n,
            sample_period_s: self.sample_period_s,
            initial: self.initial.cast(),
            pe: PeFloor::new(self.pe_floor_v2),
        }
    }
}

/// The ARX recursion itself, generic over [`Scalar`] so that it also runs in fixed point: the UD RLS on the
/// deviations from the nominal coefficients, and the regressor history.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ArxRls<T> {
    rls: DiscreteRls<T, 4>,
    /// `[y(k-1), y(k-2), u(k-1), u(k-2)]`.
    phi: [T; 4],
}

impl<T: Scalar> ArxRls<T> {
    /// At the nominal coefficients with covariance `F0`.
    pub fn new(cfg: &ArxConfig<T>) -> Self {
        ArxRls { rls: DiscreteRls::new([T::zero(); 4], cfg.f0), phi: [T::zero(); 4] }
    }

    /// One sample of the pre-filtered input and output; `adapt` false only shifts the history.
    #[inline]
    pub fn update(&mut self, cfg: &ArxConfig<T>, u: T, y: T, adapt: bool) -> RlsErrors<T> {
        let mut e = RlsErrors::default();
        if adapt {
            let mut target = y;
            for (n, p) in cfg.nominal.iter().zip(self.phi.iter()) {
                target -= *n * *p;
            }
            e = self.rls.update(&cfg.gain, &self.phi, target);
        }
        self.phi = [y, self.phi[0], u, self.phi[2]];
        e
    }

    /// The RLS state (deviations, covariance of the deviations).
    pub fn rls(&self) -> &DiscreteRls<T, 4> {
        &self.rls
    }

    /// The ARX coefficients `[A1, A2, B1, B2]`, in f64.
    pub fn arx_f64(&self, cfg: &ArxConfig<T>) -> [f64; 4] {
        let d = self.rls.theta();
        core::array::from_fn(|i| cfg.nominal64[i] + d[i].as_f64())
    }

    /// The stage, computed in f64 from the exact nominal small quantities and the deviations (any scalar).
    pub fn stage_f64(&self, cfg: &ArxConfig<T>) -> Option<StageParams<f64>> {
        let n = &cfg.nominal64;
        let d = self.rls.theta().map(|x| x.as_f64());
        stage_of_arx(
            n[0] + d[0],
            (1.0 + n[1]) + d[1],
            (1.0 - n[0] - n[1]) - d[0] - d[1],
            n[2] + n[3] + d[2] + d[3],
            1.0 / cfg.sample_period_s,
        )
    }
}

/// The `arx` estimator (float: it also converts to the stage in its own precision).
#[derive(Clone, Debug)]
pub struct ArxEstimator<T: Copy> {
    cfg: ArxConfig<T>,
    core: ArxRls<T>,
    adapting: bool,
    /// Samples of the history `[y(k-1), y(k-2), u(k-1), u(k-2)]` taken since a start, a reset or a resume: it
    /// adapts from 2 on.
    fresh: u8,
    health: Health,
    last_valid: Cell<StageParams<T>>,
}

impl<T: Real> ArxConfig<T> {
    /// Whether every constant is a finite number (see [`crate::estimators::TuningConfig::fits`]).
    pub(crate) fn fits(&self) -> bool {
        let initial = [self.initial.b0, self.initial.a1, self.initial.a0];
        self.gain.fits() && self.pe.fits() && all_finite(&[&self.f0, &self.nominal, &initial])
    }
}

impl<T: Real> ArxEstimator<T> {
    /// At the initial parameters.
    pub fn new(cfg: ArxConfig<T>) -> Self {
        ArxEstimator {
            core: ArxRls::new(&cfg),
            adapting: true,
            fresh: 0,
            health: Health::new(),
            last_valid: Cell::new(cfg.initial),
            cfg,
        }
    }

    /// What [`ArxEstimator::new`] returns, written over this one in place: the interrupt restarts the estimators with
    /// a new tuning this way, without building a whole estimator on the stack and copying it in.
    pub fn restart(&mut self, cfg: &ArxConfig<T>) {
        self.cfg = *cfg;
        self.adapting = true;
        self.health = Health::new();
        self.reset();
    }

    /// The RLS state (covariance, deviations).
    pub fn rls(&self) -> &DiscreteRls<T, 4> {
        self.core.rls()
    }

    /// The current ARX coefficients `[A1, A2, B1, B2]`.
    pub fn arx(&self) -> [f64; 4] {
        self.core.arx_f64(&self.cfg)
    }

    fn convert(&self) -> Option<StageParams<T>> {
        let n = &self.cfg.nominal64;
        let d = self.core.rls().theta();
        stage_of_arx(
            T::of(n[0]) + d[0],
            T::of(1.0 + n[1]) + d[1],
            T::of(1.0 - n[0] - n[1]) - d[0] - d[1],
            T::of(n[2] + n[3]) + d[2] + d[3],
            T::of(1.0 / self.cfg.sample_period_s),
        )
    }
}

impl<T: Real> Estimator<T> for ArxEstimator<T> {
    const NAME: &'static str = "arx";

    #[inline]
    fn update(&mut self, s: &FilteredSample<T>) {
        // The history after a start or a reset (zeros: the signals' only if they were at rest, not after a restart
        // in the middle of a run) or after a gap (samples from before it) is not this sample's: until two samples
        // have refilled it, they are only shifted in.
        let fresh = self.fresh >= 2;
        self.fresh = self.fresh.saturating_add(1);
        let adapt = self.cfg.pe.adapt(&s.pe, self.adapting, &mut self.health) && fresh;
        let e = self.core.update(&self.cfg, s.u_f.value, s.y_f.value, adapt);
        let rls = self.core.rls();
        let ok = e.a_priori.is_finite()
            && rls.theta().iter().all(|x| x.is_finite())
            && rls.min_d() > T::zero()
            && rls.trace().is_finite();
        if !ok {
            self.reset();
            self.health.numeric_resets = self.health.numeric_resets.saturating_add(1);
        }
    }

    fn params(&self) -> StageParams<T> {
        self.report().0
    }

    fn param_covariance(&self) -> [[T; 3]; 3] {
        // First-order propagation J F J' with the Jacobian of the conversion by central differences.
        let f = self.core.rls().covariance();
        let base = self.core.rls().theta();
        let mut jac = [[T::zero(); 4]; 3];
        for k in 0..4 {
            let h = f[k][k].sqrt().max(T::epsilon()) * T::of(1e-3);
            let eval = |sign: T| {
                let mut probe = self.clone();
                let mut d = *base;
                d[k] += sign * h;
                probe.core.rls.set_theta(d);
                probe.convert()
            };
            if let (Some(p), Some(m)) = (eval(T::one()), eval(-T::one())) {
                let inv = T::one() / (T::of(2.0) * h);
                jac[0][k] = (p.a0 - m.a0) * inv;
                jac[1][k] = (p.a1 - m.a1) * inv;
                jac[2][k] = (p.b0 - m.b0) * inv;
            }
        }
        let mut c = [[T::zero(); 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                let mut acc = T::zero();
                for k in 0..4 {
                    for l in 0..4 {
                        acc += jac[i][k] * f[k][l] * jac[j][l];
                    }
                }
                c[i][j] = acc;
            }
        }
        c
    }

    fn reset(&mut self) {
        self.core = ArxRls::new(&self.cfg);
        self.fresh = 0;
        self.last_valid.set(self.cfg.initial);
    }

    fn resume(&mut self) {
        self.fresh = 0;
    }

    fn set_adapting(&mut self, on: bool) {
        self.adapting = on;
        self.health.adaptation = Adaptation::asked(on);
    }

    fn health(&self) -> Health {
        self.report().1
    }

    /// The conversion to the stage once for both; the parameters held (and said so) while it has none.
    fn report(&self) -> (StageParams<T>, Health) {
        let now = self.convert();
        if let Some(p) = now {
            self.last_valid.set(p);
        }
        (self.last_valid.get(), Health { held: now.is_none(), ..self.health })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One sample of the stage `x' = A x + [0, b0 u]` with `u` held, from its ZOH matrices `(phi, psi)` ([`zoh`]).
    fn zoh_step(phi: &[[f64; 2]; 2], psi: &[[f64; 2]; 2], b0: f64, x: [f64; 2], u: f64) -> [f64; 2] {
        [0, 1].map(|i| phi[i][0] * x[0] + phi[i][1] * x[1] + psi[i][1] * b0 * u)
    }

    /// After a start, a reset or a resume the ARX shifts two samples into its history before it adapts: the
    /// regression of the third is the first whose history is the signals'.
    #[test]
    fn the_arx_refills_its_history_before_it_adapts() {
        let at = |k: u32| sample([0.3, -0.2, 0.5, 0.1, -0.4][k as usize % 5], 0.01 * k as f64);
        let mut arx = ArxEstimator::<f64>::new(ArxDesign::default().design());
        let theta = |a: &ArxEstimator<f64>| *a.rls().theta();
        let start = theta(&arx);
        for round in 0..2 {
            arx.update(&at(1));
            arx.update(&at(2));
            assert_eq!(theta(&arx), start, "round {round}: adapted on a history that is not the signals'");
            arx.update(&at(3));
            assert_ne!(theta(&arx), start, "round {round}");
            arx.reset();
        }
        for k in 4..10 {
            arx.update(&at(k));
        }
        let before = theta(&arx);
        arx.resume();
        arx.update(&at(10));
        arx.update(&at(11));
        assert_eq!(theta(&arx), before);
        arx.update(&at(12));
        assert_ne!(theta(&arx), before);
    }

    /// The parameters' covariance is the RLS's covariance of the ARX coefficients carried through the conversion to
    /// the stage to first order, `J F J'` with rows and columns in the order `(a0, a1, b0)`: checked here against a
    /// Jacobian of [`ArxRls::stage_f64`] (the f64 conversion) taken with a tenth of the step, after a run on the
    /// ZOH-sampled stage with a random input and a little noise has made every entry of `F` non-zero.
    #[test]
    fn the_parameters_covariance_is_the_coefficients_covariance_carried_through_the_conversion() {
        let p = StageParams::PAYLOAD;
        let (phi, psi) = zoh(&[[0.0, 1.0], [-p.a0, -p.a1]], 1e-4);
        let mut arx = ArxEstimator::<f64>::new(ArxDesign::default().design());
        let mut next = crate::xorshift64(0xA2C0_5EED);
        let mut x = [0.0f64; 2];
        for _ in 0..5_000 {
            let u = if next() % 2 == 0 { 1.0 } else { -1.0 };
            let y = x[0] + 1e-3 * (next() as f64 / u64::MAX as f64 - 0.5);
            arx.update(&sample(u, y));
            x = zoh_step(&phi, &psi, p.b0, x, u);
        }
        let f = arx.core.rls().covariance();
        assert!(f.iter().flatten().all(|v| *v != 0.0), "{f:?}");
        let theta = *arx.core.rls().theta();
        // Column k of J: the stage's (a0, a1, b0) along the coefficient k.
        let column = |k: usize| {
            let h = 1e-4 * f[k][k].sqrt();
            let at = |step: f64| {
                let mut core = arx.core;
                let mut d = theta;
                d[k] += step;
                core.rls.set_theta(d);
                core.stage_f64(&arx.cfg).expect("a stage near the estimate")
            };
            let (plus, minus) = (at(h), at(-h));
            [plus.a0 - minus.a0, plus.a1 - minus.a1, plus.b0 - minus.b0].map(|d| d / (2.0 * h))
        };
        let j: [[f64; 3]; 4] = core::array::from_fn(column);
        let want = |r: usize, c: usize| -> f64 {
            (0..4).map(|k| (0..4).map(|l| j[k][r] * f[k][l] * j[l][c]).sum::<f64>()).sum()
        };
        let got = arx.param_covariance();
        for (r, row) in got.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                let scale = (want(r, r) * want(c, c)).sqrt();
                assert!(scale > 0.0);
                assert!((v - want(r, c)).abs() <= 1e-5 * scale, "C[{r}][{c}] {v} against {}", want(r, c));
            }
        }
    }

    /// The conversion refuses coefficients whose poles have no continuous underdamped equivalent, and a stage it
    /// cannot represent: each case on its own, the others at a valid stage.
    #[test]
    fn the_conversion_refuses_poles_with_no_continuous_underdamped_equivalent() {
        let t = 1e-4;
        let p = StageParams::PAYLOAD;
        let valid = arx_of_stage(&p, t);
        assert!(stage_of_arx_f64(&valid, t).is_some());
        // The same stage with its damping negated: the ZOH image of an unstable pair, `r > 1` (`1 + A2 < 0`).
        let unstable = arx_of_stage(&StageParams { a1: -p.a1, ..p }, t);
        assert!(1.0 + unstable[1] < 0.0 && 4.0 * -unstable[1] > unstable[0] * unstable[0], "{unstable:?}");
        // A pair on the unit circle, `r = 1` exactly (`1 + A2 = 0`): undamped, refused with the unstable.
        let on_circle = [valid[0], -1.0, valid[2], valid[3]];
        // A double real pole at `z = 1/2` (`4 r^2 = A1^2` exactly) and two distinct real poles, 1/2 and 9/10.
        let double_real = [1.0, -0.25, valid[2], valid[3]];
        let real = [1.4, -0.45, valid[2], valid[3]];
        // The poles valid, the input's coefficients overflowing: `b0` infinite.
        let infinite_gain = [valid[0], valid[1], f64::MAX, f64::MAX];
        let nan = [valid[0], f64::NAN, valid[2], valid[3]];
        for (name, c) in [
            ("unstable", unstable),
            ("on the circle", on_circle),
            ("double real", double_real),
            ("real", real),
            ("infinite gain", infinite_gain),
            ("NaN", nan),
        ] {
            assert_eq!(stage_of_arx_f64(&c, t), None, "{name}: {c:?}");
        }
    }

    /// The ARX coefficients reported are the exact nominal ones, those of the initial stage, plus the deviations the
    /// RLS estimates; and they convert to the stage the estimator reports.
    #[test]
    fn the_arx_coefficients_are_the_nominal_ones_plus_the_deviations() {
        let design = ArxDesign::default();
        let mut arx = ArxEstimator::<f64>::new(design.design());
        let nominal = arx_of_stage(&design.initial, design.sample_period_s);
        assert_eq!(arx.arx(), nominal);
        let d = [1e-4, -2e-5, 3e-7, -1e-7];
        arx.core.rls.set_theta(d);
        let got = arx.arx();
        for i in 0..4 {
            assert_eq!(got[i], nominal[i] + d[i], "coefficient {i}");
        }
        let (from_arx, reported) = (stage_of_arx_f64(&got, design.sample_period_s).unwrap(), arx.params());
        for (x, y) in [(from_arx.a0, reported.a0), (from_arx.a1, reported.a1), (from_arx.b0, reported.b0)] {
            assert!((x / y - 1.0).abs() < 1e-9, "{x} against {y}");
        }
        assert_ne!(from_arx, design.initial);
    }

    /// The tuning fits its scalar when every constant is a number in it: each constant out of f32's range alone
    /// makes it unfit in f32 and leaves it fit in f64; a NaN fits neither.
    #[test]
    fn fits_says_whether_every_constant_of_the_tuning_is_a_number_in_its_scalar() {
        let base = ArxDesign::default();
        assert!(base.design::<f32>().fits() && base.design::<f64>().fits());
        let huge = 1e39;
        for (name, d) in [
            ("max_trace", ArxDesign { max_trace: huge, ..base }),
            ("f0", ArxDesign { f0_diag: [1e-1, 1e-1, huge, 1e-3], ..base }),
            ("pe_floor", ArxDesign { pe_floor_v2: huge, ..base }),
            ("initial b0", ArxDesign { initial: StageParams { b0: huge, ..base.initial }, ..base }),
        ] {
            assert!(!d.design::<f32>().fits(), "{name}: fits f32");
            assert!(d.design::<f64>().fits(), "{name}: does not fit f64");
        }
        let nan = ArxDesign { lambda: f64::NAN, ..base };
        assert!(!nan.design::<f32>().fits() && !nan.design::<f64>().fits());
    }

    /// One sample of the pre-filtered signals, the excitation rich.
    fn sample<T: Real>(u: T, y: T) -> FilteredSample<T> {
        use crate::estimator::PeLevel;
        use crate::filters::prefilter::Prefiltered;
        let f = |value| Prefiltered { value, d1: T::zero(), d2: T::zero() };
        FilteredSample { u, y, u_f: f(u), y_f: f(y), pe: PeLevel { power: T::one(), single: false } }
    }

    /// A sample that leaves any part of the RLS unusable resets the estimator to its initial state at once, and is
    /// counted: a NaN output (the error and the estimate NaN, the factors still finite), and an input so large in
    /// f32 that `phi' F phi` overflows (the error and the estimate finite, a factor of `F` zero).
    #[test]
    fn a_sample_that_breaks_the_rls_resets_the_estimator_at_once() {
        let cfg = ArxDesign::default().design::<f32>();
        let mut arx = ArxEstimator::new(cfg);
        let initial = arx.params();
        for k in 0..50 {
            arx.update(&sample([0.5f32, -0.3, 0.2][k % 3], 1e-3 * k as f32));
        }
        assert_ne!(*arx.rls().theta(), [0.0; 4], "adapted before the fault");
        arx.update(&sample(0.1, f32::NAN));
        assert_eq!(arx.health().numeric_resets, 1, "NaN output");
        assert_eq!((*arx.rls().theta(), arx.params()), ([0.0; 4], initial));
        // `phi = [0, 0, 0, 1e30]` on the third sample after the reset, its first adaptation: the last factor of `D`
        // becomes `d r / inf = 0`, and nothing else is infinite or NaN.
        arx.update(&sample(1e30, 0.0));
        arx.update(&sample(0.0, 0.0));
        assert_eq!(arx.health().numeric_resets, 1);
        let mut probe = arx.core;
        probe.update(&arx.cfg, 0.0, 0.0, true);
        assert_eq!(probe.rls().min_d(), 0.0);
        assert!(probe.rls().theta().iter().all(|x| x.is_finite()) && probe.rls().trace().is_finite());
        arx.update(&sample(0.0, 0.0));
        assert_eq!(arx.health().numeric_resets, 2, "a factor of F zero");
        assert_eq!(*arx.rls(), ArxRls::new(&arx.cfg).rls);
    }

    /// Frozen, the estimator keeps its estimate and `F` while the history still shifts (so that adapting resumes on
    /// the signals' history at once), and its health says frozen; let adapt again, it adapts on the next sample.
    #[test]
    fn a_frozen_estimator_holds_its_estimate_and_resumes_when_let_adapt() {
        let mut arx = ArxEstimator::<f64>::new(ArxDesign::default().design());
        let u = |k: usize| [0.5, -0.3, 0.2, 0.7][k % 4];
        for k in 0..20 {
            arx.update(&sample(u(k), 1e-3 * k as f64));
        }
        arx.set_adapting(false);
        assert_eq!(arx.health().adaptation, Adaptation::Frozen);
        let frozen = *arx.rls();
        for k in 20..40 {
            arx.update(&sample(u(k), 1e-3 * k as f64));
        }
        assert_eq!(*arx.rls(), frozen);
        assert_eq!(arx.core.phi, [1e-3 * 39.0, 1e-3 * 38.0, u(39), u(38)]);
        arx.set_adapting(true);
        assert_eq!(arx.health().adaptation, Adaptation::Adapting);
        arx.update(&sample(u(40), 0.04));
        assert_ne!(*arx.rls().theta(), *frozen.theta());
    }

    /// Coefficients with no stage hold the parameters at their last valid value, and the health says so.
    #[test]
    fn parameters_with_no_stage_are_held_and_reported_held() {
        let mut arx = ArxEstimator::<f64>::new(ArxDesign::default().design());
        let mut d = [1e-5, 0.0, 0.0, 0.0];
        arx.core.rls.set_theta(d);
        let valid = arx.params();
        assert!(!arx.health().held && valid != arx.cfg.initial);
        // `1 + A2 = -1e-3`: an unstable pair.
        d[1] = -(1.0 + arx.cfg.nominal64[1]) - 1e-3;
        arx.core.rls.set_theta(d);
        let (params, health) = arx.report();
        assert_eq!(params, valid);
        assert!(health.held && arx.health().held);
        assert_eq!(arx.params(), valid);
    }

    #[test]
    fn zoh_arx_round_trips_to_the_stage() {
        for p in [StageParams::PAYLOAD, StageParams::NO_PAYLOAD, StageParams::INITIAL] {
            let c = arx_of_stage(&p, 1e-4);
            let q = stage_of_arx_f64(&c, 1e-4).unwrap();
            // The conversion is exact; rounding of the small quantities (1 + A2 ~ 8e-3) leaves ~1e-13.
            for (x, y) in [(p.a0, q.a0), (p.a1, q.a1), (p.b0, q.b0)] {
                assert!((x / y - 1.0).abs() < 1e-11, "{x} vs {y}");
            }
        }
    }

    #[test]
    fn arx_reproduces_the_zoh_sampled_stage_exactly() {
        let p = StageParams::PAYLOAD;
        let c = arx_of_stage(&p, 1e-4);
        let (phi, psi) = zoh(&[[0.0, 1.0], [-p.a0, -p.a1]], 1e-4);
        let mut x = [0.0f64; 2];
        let (mut y, mut u) = ([0.0f64; 3], [0.0f64; 3]);
        for k in 0..200 {
            let uk = if (k / 7) % 2 == 0 { 1.0 } else { -1.0 };
            let yk = x[0];
            if k >= 2 {
                let pred = c[0] * y[0] + c[1] * y[1] + c[2] * u[0] + c[3] * u[1];
                assert!((pred - yk).abs() < 1e-12, "k = {k}");
            }
            x = zoh_step(&phi, &psi, p.b0, x, uk);
            y = [yk, y[0], y[1]];
            u = [uk, u[0], u[1]];
        }
    }
}
