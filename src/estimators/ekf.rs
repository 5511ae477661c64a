//! The paper's extended Kalman filters, one model and core, two filters:
//! [`Hekf`], the hybrid (continuous-discrete) EKF of Section IV-B, and [`Cekf`], the continuous EKF of Section IV-A.
//!
//! State `chi = [x1, x2, a0, a1, b0]` (paper eq. for the augmented system), parameters as random walks:
//!
//! ```text
//! x1' = x2,   x2' = -a0 x1 - a1 x2 + b0 u,   a0' = a1' = b0' = 0   (+ process noise, covariance Q)
//! F = [[0, 1, 0, 0, 0], [-a0, -a1, -x1, -x2, u], 0, 0, 0],   H = [1, 0, 0, 0, 0]
//! ```
//!
//! **Hybrid EKF.**
//! 1. Prediction from `t_(k-1)` to `t_k`: `chi' = f(chi, u_(k-1))` by RK4 in `substeps` steps of `T / substeps`
//!    (paper: 4, i.e. 40 kHz). The covariance goes through the Jacobian `Phi` of that RK4 map,
//!    `P = Phi P Phi' + Qd`, where the paper and the SPEC integrate `P' = F P + P F' + Q` by the same RK4: both rules
//!    are fourth-order, they agree per step to 2e-4 of the covariance's scale at the start and 1.3e-6 once converged
//!    (plus 2 % of the process noise's small share), and this one costs a third. See `EkfCore::predict`.
//! 2. Update with the sample `y_k`: `K = P H' / (H P H' + R_d)`, `chi += K (y_k - x1)`,
//!    `P = (I - K H) P (I - K H)' + K R_d K'` (Joseph form), `R_d = R / T`.
//!
//! **Continuous EKF.** One RK4 step of `T` per sample of `chi' = f(chi, u) + K (y - x1)`,
//! `P' = F P + P F' + Q - P H' H P / R`, `K = P H' / R`, with `u` held at `u_(k-1)` and `y` linear between
//! `y_(k-1)` and `y_k` over the step, plus the curvature the line misses. The measurement is continuous in this
//! filter; a straight line between samples shrinks the response near resonance by `(w T)^2 / 12` and biased `b0` by
//! -0.6 % here (as the float64 reference found), holding `y` instead shifts it by half a sample and biases `a1`.
//! The line misses `x1'' tau (tau - T) / 2`, and the filter's model supplies `x1'' = -a0 x1 - a1 x2 + b0 u`, so
//! that term is added, with `x1''` at the step's middle (from the state at its start and `x1'''`), where the RK4
//! stages sample the line. One RK4 step per sample also turns the model's oscillation slower than the exact
//! solution, by `(w T)^4 / 120` of its phase (`w T` is 0.3 at 483 Hz), and the filter settles on an `a0` that much
//! too high to match the data; the report undoes it (`Continuous::reported`). On the reference's PRBS data the two
//! took `a0` from +5e-5 and +1e-4 (curvature at the step's start, no dispersion term) to +1e-6 and -2e-6, and the
//! validation RMSE from +13 % and +46 % over the noise floor to +0.1 % and +1.6 % (`hal-sim/tests/paper_reference.rs`).
//!
//! ## Discretisation (SPEC section 6)
//! The estimator runs on the pre-filtered pair: `u = W_p u'` and `y = W_p y'`, both from the discrete (exact-ZOH)
//! pre-filter. Over each prediction the filtered input of the previous sample is held, which is exactly what the
//! stage sees between samples up to the pre-filter: the sampled model then matches the data, and the float64
//! reference measured this convention within 0.005 % of the true parameters. (Interpolating `y` linearly and
//! integrating the pre-filter continuously biased `b0` by -0.6 %; holding raw `y` biased `a1` by up to 10 %.)
//!
//! ## Numerics
//! Internally the state is normalised, `z = [x1, x2 / W, a0 / a0_init, a1 / a1_init, b0 / b0_init]` with
//! `W = sqrt(a0_init)`, so that every state is of order one and the covariance spans a few decades instead of
//! twenty: an f32 step of `a0 ~ 7e6` would otherwise be 0.5, a few ulps per update. `P` is stored symmetric
//! (15 entries); `F` has two non-zero rows, so `F P` costs 2 x 5 dot products instead of 25; `H = e1` makes the
//! update a rank-one correction from column 0 of `P`. After each step a state variance below zero is repaired (that
//! state decorrelated, its variance floored; a parameter variance is floored anyway), and a non-finite value resets
//! the estimator (counted), as does an innovation RMS beyond a metre ([`INNOVATION_CEILING_UM`]: a filter thrown off
//! by a glitch could otherwise run on for good, its state finite and its prediction astray), and a filter that has not
//! relocked 5 s after a start or a change ([`RELOCK_NIS_RATIO`]: the same, in a wrong optimum). After a start or a
//! reset the first sample sets the states, the filtered reading and its rate, with the variance of one
//! measurement, and the filter steps from the next (`Ekf::prime`): the console restarts the estimators wherever the
//! signals are. So does the first sample after a gap in the samples (a fault:
//! [`crate::estimator::Estimator::resume`]), the parameters kept. Cost per update: hybrid, about 560 flops for the
//! prediction and 120 for the update; continuous, 4 derivatives of about 110 flops, 120 of stage arguments and 120 of
//! the RK4 sum: about 680.

#![allow(clippy::needless_range_loop)] // packed-symmetric loops read best with the indices of the algebra

#[cfg(feature = "dense-ekf")]
pub mod dense;

use crate::estimator::{Adaptation, Estimator, FilteredSample, Health};
use crate::estimators::{all_finite, axpy, rk4_combine, rk4_dispersed_start, undo_rk4_dispersion, PeFloor};
use crate::scalar::fmax;
use crate::{Real, StageParams};

/// Packed index of `(i, j)` in a symmetric 5 x 5 matrix (upper triangle, row-major).
#[inline(always)]
const fn idx(i: usize, j: usize) -> usize {
    let (r, c) = if i <= j { (i, j) } else { (j, i) };
    r * 5 - r * (r + 1) / 2 + c
}

/// Packed indices of the parameter block (rows and columns 2..5).
const PARAM_BLOCK: [usize; 6] = [idx(2, 2), idx(2, 3), idx(2, 4), idx(3, 3), idx(3, 4), idx(4, 4)];

/// Physical tuning (paper Section V-C), for either filter.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EkfDesign {
    /// Process noise `diag(Q)` for `[x1, x2, a0, a1, b0]` in the paper's units.
    pub q_diag: [f64; 5],
    /// Initial covariance `diag(P0)`.
    pub p0_diag: [f64; 5],
    /// Continuous measurement noise `R`, um^2 (the update uses `R / T`).
    pub r: f64,
    /// RK4 substeps per sample (the hybrid filter's prediction; the continuous filter takes one step).
    pub substeps: u32,
    /// Health: the settings of gating, change detection, the PE monitor and the covariance bounds.
    pub health: EkfHealthDesign,
    /// Where the estimate starts.
    pub initial: StageParams<f64>,
    /// Sample period, s.
    pub sample_period_s: f64,
}

impl EkfDesign {
    /// `Q2`, the paper's tuning for PRBS.
    pub const Q2: [f64; 5] = [1e-12, 1e-6, 1.5e9, 2.5e-1, 5.0e8];
    /// `Q1`, the paper's tuning for the smoothed triangle.
    pub const Q1: [f64; 5] = [1e-12, 1e-6, 1.5e11, 2.5e1, 5.0e10];

    /// `Q2` for an input `strength` times as strong, in power, as the paper's PRBS of 1 V it was made for: its
    /// parameters' entries over `strength`, its states' as they are. On an input scaled by `A` (`strength` `A^2`)
    /// the EKFs are then the ones on the input at 1 V, but for the noise, which weighs less; with `Q2` they wander
    /// further (README, "The EKFs' `Q` is for an amplitude"; the console's and `identify`'s notes give it).
    pub fn q2_for_strength(strength: f64) -> [f64; 5] {
        let mut q = Self::Q2;
        q[2..].iter_mut().for_each(|x| *x /= strength);
        q
    }

    /// The paper's tuning with process noise `q` (`P0 = 10 Q`, `R = 1.5e-6`, 4 substeps).
    pub fn paper(q: [f64; 5]) -> Self {
        EkfDesign {
            q_diag: q,
            p0_diag: q.map(|x| 10.0 * x),
            r: 1.5e-6,
            substeps: 4,
            health: EkfHealthDesign::default(),
            initial: StageParams::INITIAL,
            sample_period_s: 1e-4,
        }
    }

    /// Normalise and round to the working scalar.
    #[inline(never)]
    pub fn design<T: Real>(&self) -> EkfConfig<T> {
        let p = &self.initial;
        let w = libm::sqrt(p.a0);
        let scale = [1.0, 1.0 / w, 1.0 / p.a0, 1.0 / p.a1, 1.0 / p.b0];
        let h = self.sample_period_s / self.substeps as f64;
        let (step, period) = (T::of(h), T::of(h * self.substeps.max(1) as f64));
        let hd = &self.health;
        let t = self.sample_period_s;
        // At least one sample: a reopening at once is the whole widening added in the sample of the detection.
        let ramp_samples = libm::round(hd.reopen_ramp_s / t).max(1.0);
        let innovation_block = libm::round(INNOVATION_WINDOW_S / t).clamp(1.0, u32::MAX as f64) as u32;
        // `T Q`, normalised.
        let q_period = |i: usize| t * self.q_diag[i] * scale[i] * scale[i];
        EkfConfig {
            gate2: T::of(hd.gate_sigma * hd.gate_sigma),
            nis_alpha: T::of(t / hd.nis_tau_s),
            change_samples: hd.change_samples,
            holdoff_samples: libm::round(hd.holdoff_s / t) as u32,
            // Off (0) as an infinite ratio, which no level exceeds (`inf * 0` is NaN, also never exceeded): no test
            // for it per sample.
            drift_ratio: T::of(if hd.drift_ratio > 0.0 { hd.drift_ratio } else { f64::INFINITY }),
            drift_alpha: T::of(t / hd.drift_tau_s),
            // At least one sample: the long-run level held over a wait (the relock's reference, at least 1 after a
            // change) is released only at its end.
            drift_wait_samples: libm::round(hd.drift_wait_s / t).max(1.0) as u32,
            pe: PeFloor::new(hd.pe_floor_v2),
            // The innovation RMS in the health report is over the last second.
            innovation_block,
            innovation_to_range: T::of(
                T::max_value().as_f64() / (INNOVATION_CEILING_UM * INNOVATION_CEILING_UM * innovation_block as f64),
            ),
            p_ceiling: core::array::from_fn(|i| T::of(hd.ceiling * self.p0_diag[i] * scale[i] * scale[i])),
            p_floor: core::array::from_fn(|i| T::of(hd.floor * self.p0_diag[i] * scale[i] * scale[i])),
            ramp_samples: ramp_samples as u32,
            p_ramp_step: core::array::from_fn(|k| {
                let (i, widening) = (k + 2, (hd.reopen.min(hd.ceiling) - 1.0).max(0.0));
                T::of(widening * self.p0_diag[i] * scale[i] * scale[i] / ramp_samples)
            }),
            inv_r: T::of(1.0 / self.r),
            q: core::array::from_fn(|i| T::of(self.q_diag[i] * scale[i] * scale[i])),
            p0: core::array::from_fn(|i| T::of(self.p0_diag[i] * scale[i] * scale[i])),
            r_d: T::of(self.r / self.sample_period_s),
            w: T::of(w),
            c0: T::of(p.a0 / w),
            c1: T::of(p.a1),
            c2: T::of(p.b0 / w),
            h: step,
            h_quarter: T::of(h / 4.0),
            h_third: T::of(h / 3.0),
            h_sq_half: T::of(h * h / 2.0),
            q_period: core::array::from_fn(|i| T::of(q_period(i))),
            q_xt: core::array::from_fn(|i| core::array::from_fn(|m| T::of(q_period(m + 2) / [3.0, 2.0][i]))),
            q_xx: core::array::from_fn(|k| core::array::from_fn(|m| T::of(q_period(m + 2) / [5.0, 4.0, 3.0][k]))),
            period,
            period6: period / T::of(6.0),
            bow_gain: {
                let t = h * self.substeps.max(1) as f64;
                T::of(-w * t * t / 2.0)
            },
            half_period: period * T::of(0.5),
            c0w: T::of(p.a0),
            b0_scale: T::of(p.b0),
            dispersed_start: rk4_dispersed_start(T::of(p.a0), period),
            substeps: self.substeps.max(1),
            initial: *p,
        }
    }
}

impl Default for EkfDesign {
    fn default() -> Self {
        Self::paper(Self::Q2)
    }
}

/// Health settings of the EKFs.
///
/// - **Gating**: a sample whose normalised innovation `nu^2 / S` exceeds `gate_sigma^2` times its running mean
///   over the accepted samples (time constant `nis_tau_s`, 0.5 s: long enough to average the noise, short enough
///   to forget the start-up transient within seconds) is not used, and counted. Relative, because the real noise
///   need not match `R`: the paper's `R_d = R / T` stands for 122 nm per sample where the probe has about 1 nm, so
///   `nu^2 / S` runs near 1e-4.
/// - **Change detection**: `change_samples` gated samples in a row are not an outlier but a changed plant (the
///   payload came off): the parameter covariance is reopened, the estimates kept, and gating paused for
///   `holdoff_s` while the filter relocks. Counted. Gating is only active together with change detection: a gate
///   alone would lock a changed plant out for good. It is paused for `holdoff_s` after a start or a reset too: a
///   filter restarted from its initial parameters in the middle of a run (`tune`, `reset`) met innovations hundreds
///   of times its `S`, gated half its samples without 20 in a row, and learnt from those its wrong model happened to
///   fit (`b0` 90 % low for half a second); 300 restarts on the paper's PRBS after the payload change relocked to
///   1 % in a median 0.33 s (continuous) and 0.18 s (hybrid), 17 and 40 of them over 1 s, and with the pause in
///   0.07 s, one over 1 s (`tests/instrument.rs`). From rest (the paper's start) the gate rejects nothing then.
/// - **Drift detection**: a change too gentle for the gate. The smoothed triangle excites the stage so little near
///   its resonance that the payload change raises the innovation RMS only about 5x (25x in `nu^2 / S`): per sample
///   that is within the chi-square's spread, so it hardly ever gives `change_samples` gated samples in a row. The
///   short-run level of `nu^2 / S` (the gate's reference, `nis_tau_s`) is compared with a long-run level
///   (`drift_tau_s`, 10 s), both over the accepted samples; above `drift_ratio` times it (4: twice the RMS) the
///   parameter covariance is reopened, counted as a change. For `drift_wait_s` after a start, a reset or any detected
///   change the long-run level holds the one before and is not compared (the start-up transient and a relock are not
///   drifts); at the wait's end the short-run level must be within [`RELOCK_NIS_RATIO`] times it (and 1), or the
///   filter did not relock and is reset, and the long-run level starts from the short-run one. Rejected samples feed
///   neither level, so a lone outlier cannot trigger it. On the reference's triangle it fires 0.24 s after the
///   change. A step up of the noise or of a model misfit (say more amplitude on a mode the model
///   lacks) would trigger it too: harmless, the filter relocks to the same parameters. Cost: 3 flops per sample.
/// - **Reopening**: after a change the gate saw, the parameters to `P0` and the state to `R / T`; after a drift,
///   the parameters to `reopen` times `P0` (500, the ceiling), grown over `reopen_ramp_s` (10 ms) rather than at
///   once. The gate sees a change with a transient (the payload-removal bump on the board, a velocity kick that
///   rings at the new resonance): reopened wide then, the ring pulls the parameters far off (on the board's
///   triangle the hybrid filter's a1 went to -160 % and took 30 s to come back), where `P0` relocks; and with the
///   state's variance left small the ring still pulled them (b0 to -105 % 0.1 s after the change, back within 3 %
///   of the final mean after 8-18 s over seeds 1-8). With the state reopened too the filter explains the ring as a
///   state: 0.5-1.2 s (`tests/ekf_health.rs`). A drift is quiet, and
///   there `P0` is too narrow: on the reference's triangle the hybrid filter reopened to `P0` kept a0 at -25 % for
///   25 s while a1 grew threefold (the new resonance sits on the triangle's 47th harmonic, where a model tuned 12 %
///   lower has almost no gradient) and a0, b0 reached 1 % after 67 s. Reopened wide *at once*, the relock depended
///   on the noise: in the first milliseconds the parameters' prior spread is several times their values and the
///   linearisation guesses; where it guessed wrong, `a1` swung to several times its value and `b0` followed it back
///   over tens of seconds (on the reference's triangle, noise seeds 2-50, hybrid / continuous: medians 0.8 / 1.2 s,
///   6 / 5 of 49 seeds over 10 s, the slowest 27 / 25 s). The same widening added as process noise over 10 ms (the
///   change modelled as a burst of the parameters' random walk) lets the data correct the parameters while their
///   spread grows: medians 0.32 / 0.31 s, the slowest 0.7 s, none over 1 s (`tests/ekf.rs`). The choice is not
///   delicate: growth over 1 to 50 ms, to 100 to 2 000 `P0`, left none over 2 s; 500 `P0` reaches the new
///   parameters fastest (at 100 `P0` the medians are 0.55 s). Cost: a counter test per sample, three adds per
///   sample during the growth.
/// - **Persistent excitation**: the filtered input's power, averaged over 10 ms by the pipeline's
///   [`PeMonitor`](crate::estimator::PeMonitor), below `pe_floor_v2`, or a single sinusoid, freezes the parameters
///   (reported as `Starved`): with nothing to learn from they would only drift. 10 ms: an abrupt stop of the
///   excitation freezes them within about 0.15 s (a 0.1 s average took 1.4 s, and they drifted 0.6 % meanwhile).
/// - **Covariance bounds**: parameter variances are held between `floor` and `ceiling` times their `P0` (a
///   diagonal congruence for the ceiling and a diagonal addition for the floor, both keeping `P` positive
///   semidefinite): no windup, and no collapse that would stop adaptation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EkfHealthDesign {
    /// Gate, in standard deviations of the innovation relative to its long-run level (`f64::INFINITY`: off).
    pub gate_sigma: f64,
    /// Time constant of the long-run normalised innovation, s.
    pub nis_tau_s: f64,
    /// Gated samples in a row that mean a plant change (0: change detection off).
    pub change_samples: u32,
    /// Gating pause after a detected change, s.
    pub holdoff_s: f64,
    /// Short-run over long-run `nu^2 / S` that means a plant change (0: drift detection off).
    pub drift_ratio: f64,
    /// Time constant of the long-run `nu^2 / S`, s.
    pub drift_tau_s: f64,
    /// No drift detection for this long after a start, a reset or a detected change, s (at least one sample).
    pub drift_wait_s: f64,
    /// Filtered input power below which adaptation starves, V^2 (0: the excitation monitor off).
    pub pe_floor_v2: f64,
    /// Parameter variance ceiling, times `P0`.
    pub ceiling: f64,
    /// Parameter variance floor, times `P0`.
    pub floor: f64,
    /// Parameter variances after a drift, times `P0` (at most `ceiling`; after a change the gate saw, `P0`).
    pub reopen: f64,
    /// After a drift, the parameter variances grow from `P0` to `reopen` times it over this long, s (0: at once).
    pub reopen_ramp_s: f64,
}

impl Default for EkfHealthDesign {
    fn default() -> Self {
        EkfHealthDesign {
            gate_sigma: 5.0,
            nis_tau_s: 0.5,
            change_samples: 20,
            holdoff_s: 0.5,
            drift_ratio: 4.0,
            drift_tau_s: 10.0,
            drift_wait_s: 5.0,
            pe_floor_v2: 1e-6,
            ceiling: 500.0,
            floor: 1e-9,
            reopen: 500.0,
            reopen_ramp_s: 0.01,
        }
    }
}

/// The innovation RMS, um, beyond which an EKF is taken for diverged and reset (counted), as for a non-finite value:
/// a metre, which no nanopositioning stage moves. Without it a filter thrown off by a glitch could run on for good
/// with its state finite and its prediction astray: the continuous EKF, after one reading of 10^4 um on the board's
/// PRBS, at an innovation RMS of 10^17 um and `a0` 20 times the truth (`tests/ekf_health.rs`). In f32 the bound is
/// met long before the innovation's square overflows; in f64 it keeps the reference resetting where the board does.
pub const INNOVATION_CEILING_UM: f64 = 1e6;

/// When drift detection resumes (`drift_wait_s`, 5 s, after a start, a reset or a detected change), an EKF whose
/// normalised innovation `nu^2 / S` (its short-run level) is more than this many times both 1 and its level before
/// the wait did not relock: it is reset (counted), as for a non-finite value. 1 is what `nu^2 / S` averages in a filter
/// whose noise model is right; 100, innovations 10 times what the filter's own covariance and `R` make of them, and
/// 10 times what they were if they were that large already. After such a reset the level that failed is the next
/// wait's reference, so a filter whose innovations are that large for good (noise or a misfit its `R` does not allow
/// for) is reset for it once, not every 5 s.
///
/// Without it a filter thrown into a wrong optimum stayed there for good with every value finite and its gate's and
/// drift detector's references following its own innovations: the hybrid EKF after one reading of 10^5 um on the
/// PRBS (the ring the pre-filter makes of it passed for a plant change, which opened the gate), missing the payload
/// change after it: at 0.1 s, `b0` negative and `a0` 40 times the truth for the rest of the record, `nu^2 / S` 580
/// 5 s after; at 3 s, 330 (`tests/ekf_health.rs`). With the paper's `R` (`R_d = R / T` stands for 122 nm per sample
/// where the board's probe has about 1 nm) `nu^2 / S` runs near 1e-4, 1e-3 on the triangle, and 0.1 under a PRBS of
/// 8 V, whose misfit (the second mode) makes 40 nm of innovation: no relock (5 s after the payload change both EKFs
/// are within 1.2 times the level before it), no change of the excitation (a PRBS or a multisine of 8 V after two
/// minutes without excitation, `tests/instrument.rs`) and no `R` down to 1e-8 of the paper's (the filter's own
/// covariance grows to match) comes near it, and `paper`'s output is the same with this test as without.
pub const RELOCK_NIS_RATIO: f64 = 100.0;

/// The span of the innovation RMS in the health report, s.
pub const INNOVATION_WINDOW_S: f64 = 1.0;

/// The innovations' level for the health report: their RMS over the last [`INNOVATION_WINDOW_S`]. The squares are
/// summed in blocks of that span; the report takes the current block's sum and the last complete block's, weighted
/// by the share of the span the current one has yet to cover (as if the last block's squares were spread evenly over
/// it). A transient leaves the report within two spans of its end, whatever its size. An exponential average of the
/// squares (this report's earlier form, with a time constant of 1 s) keeps one for `ln` of its squares' ratio to the
/// noise's in seconds: after the payload change the hybrid EKF relocked within 0.25 s, and its innovation RMS read 30
/// times the noise's 2.5 s later and was back within 10 % of it only after about 10 s (`tests/ekf_health.rs`).
/// Per sample one multiply-add and a count; each block's end moves the sum.
#[derive(Clone, Copy, Debug, PartialEq)]
struct InnovationLevel<T> {
    /// Sum of the squares in the current block, um^2.
    sum: T,
    /// Samples in the current block.
    count: u32,
    /// Sum of the squares of the last complete block, um^2; negative before the first.
    last: T,
}

impl<T: Real> InnovationLevel<T> {
    fn new() -> Self {
        InnovationLevel { sum: T::zero(), count: 0, last: -T::one() }
    }

    #[inline(always)]
    fn add(&mut self, nu: T, block: u32) {
        self.sum += nu * nu;
        self.count += 1;
        if self.count >= block {
            self.last = self.sum;
            self.sum = T::zero();
            self.count = 0;
        }
    }

    /// The squares of the current block and the last, for the health logic's finiteness and ceiling test (the
    /// negative `last` before the first block changes nothing there).
    #[inline(always)]
    fn squares(&self) -> T {
        self.sum + self.last
    }

    /// The RMS over the last `block` samples, um; over the samples so far before the first block is complete, 0
    /// before any.
    fn rms(&self, block: u32) -> T {
        let (n, b) = (T::of(self.count as f64), T::of(block as f64));
        let ms = if self.last >= T::zero() {
            (self.last * ((b - n) / b) + self.sum) / b
        } else if self.count > 0 {
            self.sum / n
        } else {
            T::zero()
        };
        ms.sqrt()
    }
}

/// The normalised configuration.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EkfConfig<T> {
    gate2: T,
    nis_alpha: T,
    change_samples: u32,
    holdoff_samples: u32,
    drift_ratio: T,
    drift_alpha: T,
    drift_wait_samples: u32,
    pe: PeFloor<T>,
    /// Samples in a block of the innovation level ([`InnovationLevel`]), at least one.
    innovation_block: u32,
    /// The innovations' sum of squares times this overflows when their RMS over a block passes
    /// [`INNOVATION_CEILING_UM`].
    innovation_to_range: T,
    p_ceiling: [T; 5],
    p_floor: [T; 5],
    /// Samples (at least one) over which a drift's reopening grows from `P0` to `reopen P0`, and the growth of each
    /// parameter variance per sample.
    ramp_samples: u32,
    p_ramp_step: [T; 3],
    inv_r: T,
    q: [T; 5],
    p0: [T; 5],
    r_d: T,
    w: T,
    c0: T,
    c1: T,
    c2: T,
    /// The hybrid filter's substep, `T / substeps`.
    h: T,
    /// The hybrid filter's substep polynomial: `h / 4`, `h / 3`, `h^2 / 2`.
    h_quarter: T,
    h_third: T,
    h_sq_half: T,
    /// The process noise over one sample period: `T Q` (all five); `T Q_theta / (1 + k_i)` for row `i` of the
    /// state-parameter block and `T Q_theta / (1 + k_i + k_j)` for entries `00`, `01`, `11` of the state block,
    /// `k = [2, 1]` (see [`EkfCore::predict`]).
    q_period: [T; 5],
    q_xt: [[T; 3]; 2],
    q_xx: [[T; 3]; 3],
    /// The continuous filter's step, `h * substeps` (the sample period).
    period: T,
    /// `period / 6`.
    period6: T,
    /// `-W period^2 / 2`: the continuous filter's curvature term per unit of `x2'` (normalised).
    bow_gain: T,
    /// `period / 2`: from the step's start to its middle.
    half_period: T,
    /// `a0_init` (normalised `c0 W`): `x2''` from `x2` and `x2'` with the parameters and `u` held; and the report's
    /// scale of `z[2]`.
    c0w: T,
    /// `b0_init`: the report's scale of `z[4]` (`c1`, `a1_init`, is `z[3]`'s).
    b0_scale: T,
    /// Where the continuous filter starts its normalised `a0` and `b0`: the model it reports as the initial
    /// parameters (`estimators::rk4_dispersed_start`, 1 + 6e-5 for the paper's stage).
    dispersed_start: T,
    substeps: u32,
    initial: StageParams<f64>,
}

/// Which filter: the hybrid or the continuous EKF.
pub trait EkfKind: Copy + core::fmt::Debug + Default {
    /// Name in reports.
    const NAME: &'static str;
    /// Advance `(z, P)` over one sample period with `u` held and the measurements `y_prev`, `y`; a sample whose
    /// normalised innovation `nu^2 / S` exceeds `gate_nis` is not used. Returns the innovation and, when the sample
    /// was used, its normalised square.
    fn step<T: Real>(core: &mut EkfCore<T>, u: T, y_prev: T, y: T, gate_nis: T) -> (T, Option<T>);
    /// Model (1)'s parameters from the filter's: its model's as they are.
    #[inline]
    fn reported<T: Real>(core: &EkfCore<T>) -> StageParams<T> {
        core.model_params()
    }
    /// The normalised `a0` and `b0` a start or a reset puts the filter at: the model it reports as the initial
    /// parameters.
    #[inline]
    fn start<T: Real>(_cfg: &EkfConfig<T>) -> T {
        T::one()
    }
}

/// Section IV-B: RK4 prediction in substeps, then a Joseph-form update.
#[derive(Clone, Copy, Debug, Default)]
pub struct Hybrid;
/// Section IV-A: one RK4 step of the continuous filter per sample.
#[derive(Clone, Copy, Debug, Default)]
pub struct Continuous;

impl EkfKind for Hybrid {
    const NAME: &'static str = "hekf";
    #[inline]
    fn step<T: Real>(core: &mut EkfCore<T>, u: T, _y_prev: T, y: T, gate_nis: T) -> (T, Option<T>) {
        core.predict(u);
        // Gate on the a priori innovation.
        let nu = y - core.z[0];
        let s = core.p[idx(0, 0)] + core.cfg.r_d;
        if nu * nu > gate_nis * s {
            return (nu, None);
        }
        let inv_s = T::one() / s;
        core.correct(nu, s, inv_s);
        (nu, Some(nu * nu * inv_s))
    }
}

impl EkfKind for Continuous {
    const NAME: &'static str = "ekf";
    #[inline]
    fn step<T: Real>(core: &mut EkfCore<T>, u: T, y_prev: T, y: T, gate_nis: T) -> (T, Option<T>) {
        // The line through the samples misses the output's curvature, x1'' tau (tau - T) / 2 + O(T^3); the model
        // supplies x1'' = W x2', taken at the step's middle (x2' + x2'' T / 2 from its start, x2'' with the
        // parameters and u held), where the stages sample the line: what is left there is O(T^4). The term
        // vanishes at the samples.
        let c = &core.cfg;
        let c2u = c.c2 * u;
        let (z, rate) = (&core.z, core.x2_rate(&core.z, c2u));
        let rate_of_rate = -c.c0w * z[2] * z[1] - c.c1 * z[3] * rate;
        let bow = c.bow_gain * (rate + c.half_period * rate_of_rate);
        let before = (core.z, core.p);
        core.rk4(&before, u, Some((y_prev, y, bow)));
        // Gate on the residual at the step's end against the discrete-equivalent innovation variance; an outlier
        // step is taken again without the measurement.
        let nu = y - core.z[0];
        let s = core.p[idx(0, 0)] + core.cfg.r_d;
        if nu * nu > gate_nis * s {
            core.rk4(&before, u, None);
            return (nu, None);
        }
        (nu, Some(nu * nu / s))
    }

    /// The model's, with one RK4 step's dispersion undone (`estimators::undo_rk4_dispersion`: +1.4e-4 on `a0` at
    /// 483 Hz, measured +1.0e-4 before the curvature term moved to the step's middle). The hybrid filter's substeps
    /// of `T / 4` make its share 256 times smaller (5e-7), below its other errors: not applied.
    #[inline]
    fn reported<T: Real>(core: &EkfCore<T>) -> StageParams<T> {
        undo_rk4_dispersion(core.model_params(), core.cfg.period)
    }

    #[inline]
    fn start<T: Real>(cfg: &EkfConfig<T>) -> T {
        cfg.dispersed_start
    }
}

/// The shared state: normalised `z`, packed `P`, configuration.
#[derive(Clone, Copy, Debug)]
pub struct EkfCore<T> {
    cfg: EkfConfig<T>,
    z: [T; 5],
    p: [T; 15],
}

/// An EKF of kind `K`: [`Hekf`] or [`Cekf`].
#[derive(Clone, Copy, Debug)]
pub struct Ekf<T, K> {
    core: EkfCore<T>,
    u_prev: T,
    y_prev: T,
    adapting: bool,
    /// Whether the states hold a sample's filtered reading: false from a start or a reset until the next sample
    /// (`Ekf::prime`).
    primed: bool,
    health: Health,
    /// Long-run mean of the normalised innovation (the gate's reference).
    nis_mean: T,
    /// Gated samples in a row.
    gated_run: u32,
    /// Samples left in the gating pause after a change.
    holdoff: u32,
    /// Long-run mean of the normalised innovation (the drift detector's reference).
    nis_long: T,
    /// Samples left before drift detection.
    drift_wait: u32,
    /// Samples left in the growth of the parameter variances after a drift.
    ramp: u32,
    /// The innovations' level over the last second, for the health report.
    innovation: InnovationLevel<T>,
    kind: K,
}

/// The hybrid EKF.
pub type Hekf<T> = Ekf<T, Hybrid>;
/// The continuous EKF.
pub type Cekf<T> = Ekf<T, Continuous>;

impl<T: Real, K: EkfKind> Ekf<T, K> {
    /// At the initial parameters and `P0`, its states taken from the first sample (the filtered reading and its
    /// rate: see the module's doc).
    pub fn new(cfg: EkfConfig<T>) -> Self {
        let mut s = Ekf {
            core: EkfCore { cfg, z: [T::zero(); 5], p: [T::zero(); 15] },
            u_prev: T::zero(),
            y_prev: T::zero(),
            adapting: true,
            primed: false,
            health: Health::new(),
            nis_mean: T::one(),
            gated_run: 0,
            holdoff: 0,
            nis_long: T::one(),
            drift_wait: 0,
            ramp: 0,
            innovation: InnovationLevel::new(),
            kind: K::default(),
        };
        s.reset_state();
        s
    }

    /// What [`Ekf::new`] returns, written over this one in place: the interrupt restarts the estimators with a new
    /// tuning this way, without building a whole filter on the stack and copying it in.
    pub fn restart(&mut self, cfg: &EkfConfig<T>) {
        self.core.cfg = *cfg;
        self.u_prev = T::zero();
        self.y_prev = T::zero();
        self.adapting = true;
        self.health = Health::new();
        self.kind = K::default();
        self.reset_state();
    }

    /// A reset for a fault (a non-finite value, an innovation beyond the ceiling, no relock), counted. After no
    /// relock, `failed` is the level that failed, which becomes the next wait's reference: a filter whose innovations
    /// are that large for good (noise or a misfit its `R` does not allow for) is reset for it once, not every
    /// `drift_wait_s`. Out of line: rare, and kept out of the sample path's code.
    #[cold]
    #[inline(never)]
    fn reset_counted(&mut self, failed: Option<T>) {
        self.reset_state();
        // The gate on at once, unlike after a start: what threw the filter off (a glitch's ring through the
        // pre-filter) is often still in the signals, and with the gate paused the continuous filter restarted on a
        // 1e4 um glitch's tail took it for the stage and settled 22 times off with its innovations at the noise
        // (`hal-sim/tests/ekf_health.rs`).
        self.holdoff = 0;
        self.health.numeric_resets = self.health.numeric_resets.saturating_add(1);
        if let Some(level) = failed.filter(|l| l.is_finite()) {
            self.nis_long = level;
        }
    }

    fn reset_state(&mut self) {
        let c = &mut self.core;
        let start = K::start(&c.cfg);
        c.z = [T::zero(), T::zero(), start, T::one(), start];
        c.p = [T::zero(); 15];
        for i in 0..5 {
            c.p[idx(i, i)] = c.cfg.p0[i];
        }
        self.primed = false;
        self.nis_mean = T::one();
        self.gated_run = 0;
        // No gate while the filter locks on (see `EkfHealthDesign`'s gating).
        self.holdoff = self.core.cfg.holdoff_samples;
        self.nis_long = T::one();
        self.drift_wait = self.core.cfg.drift_wait_samples;
        self.ramp = 0;
        // A blow-up's innovation would otherwise stay in the health report's RMS (and, beyond the ceiling, reset the
        // filter again).
        self.innovation = InnovationLevel::new();
    }

    /// The first sample after a start or a reset: the states are the filtered reading and its rate, and the filter
    /// steps from the next sample on. Their variances are those of one measurement (`R_d`, as after a change:
    /// `EkfCore::reopen_states`), not `P0`'s (`10 Q` in the paper, 1e-11 um^2 for the position), which trusts them
    /// as a filter at rest can: the rate is within about 0.5 % of a converged filter's `x2`, 85 um/s on a 6 um
    /// oscillation, where `P0` allows 0.003 um/s, and the continuous EKF, restarted in the middle of a run, rejected
    /// its first samples, took a jump and settled on `b0` 10 % high for more than 5 s (a random session's end, seed
    /// 1329). The paper starts with the pre-filter at rest and the state at zero. Started at zero in
    /// the middle of a run instead (a `tune` restarts the estimators wherever the signals are), the filter met a
    /// filtered reading of several um, or of 19 um where the pre-filter still rang on a fault's readings, with
    /// state variances of 1e-11 um^2: it moved its parameters to explain it, and where it rang both EKFs settled on
    /// `b0` below zero until their relock test reset them 5 s later (`tests/instrument.rs`). The rate, `s W_p y'`, is
    /// the pre-filter's own derivative; it is within about 0.5 % of the converged filters' `x2` on the paper's PRBS.
    #[cold]
    #[inline(never)]
    fn prime(&mut self, s: &FilteredSample<T>) {
        let rate = s.y_f.d1 / self.core.cfg.w;
        self.core.z[0] = s.y_f.value;
        self.core.z[1] = if rate.is_finite() { rate } else { T::zero() };
        self.core.reopen_states();
        self.u_prev = s.u_f.value;
        self.y_prev = s.y_f.value;
        self.primed = true;
    }

    /// The state in the paper's units `[x1, x2, a0, a1, b0]`.
    pub fn state(&self) -> [f64; 5] {
        self.core.state()
    }

    /// The covariance in the paper's units.
    pub fn covariance(&self) -> [[f64; 5]; 5] {
        self.core.covariance()
    }
}

impl<T: Real> EkfConfig<T> {
    /// Whether every constant is a finite number and no normalisation (`W`, `c0`, `c1`, `c2`, `1 / R`) vanished
    /// (see [`crate::estimators::TuningConfig::fits`]). `drift_ratio` is infinite by design when drift detection is
    /// off.
    pub(crate) fn fits(&self) -> bool {
        let s =
            [self.gate2, self.nis_alpha, self.drift_alpha, self.innovation_to_range, self.r_d, self.h, self.h_quarter];
        let t = [self.h_third, self.h_sq_half, self.period, self.period6, self.bow_gain, self.half_period];
        let (q_xt, q_xx) = (self.q_xt.as_flattened(), self.q_xx.as_flattened());
        let arrays = [&self.p_ceiling[..], &self.p_floor, &self.p_ramp_step, &self.q, &self.p0, &self.q_period];
        let scales = [self.inv_r, self.w, self.c0, self.c1, self.c2, self.c0w, self.b0_scale];
        all_finite(&[&s, &t, q_xt, q_xx])
            && all_finite(&arrays)
            && scales.iter().all(|x| x.is_normal())
            && self.pe.fits()
    }
}

/// Up to this many of the hybrid filter's substeps are taken one at a time, with `R` whole (the paper's 4: f32 within
/// 1.5e-7 of f64 there); more are taken as powers of the substep map ([`SubstepMap`], squared). Taking a map costs
/// about 60 flops and squaring one about 130, so squaring pays from 5 on.
const DIRECT_SUBSTEPS: u32 = 4;

/// `m` of the hybrid filter's substeps as one affine map of the state `x = [x1, x2]`, `x -> P x + q` (`P = R^m`,
/// `q = (R^(m-1) + ... + I) S [0, b]`, see [`EkfCore::predict`]), with the derivatives of `P` and `q` along `g0` and
/// `g1`, and of `q` along `z4` (`P` does not depend on it). The parameters and `u` are constant over the period, so
/// every substep is the same map, and maps of a power of two substeps come by squaring: 64 substeps take four
/// squarings and four maps instead of 64 steps of the state and its sensitivities and 63 products for `Psi`.
///
/// `P` is held as its deviation from the identity, `D = P - I`, and the maps are taken as `x + (D x + q)`: a substep
/// moves the state by a small part of itself (`h A`, 0.02 at 64 substeps of the paper's stage), which `P` itself,
/// rounded near 1, would keep to a few of the working scalar's digits. In f32 with `P` whole, 64 substeps took
/// `a1`'s means 1.1e-4 to 1.6e-4 from f64's, past SPEC 10's 1e-4 (the loop of substeps before the squaring, and the
/// squaring, alike); with `D` 5e-7 (`hal-sim/tests/ekf.rs`,
/// `hekf_with_many_substeps_is_the_same_filter_in_f64_and_f32`).
struct SubstepMap<T> {
    /// `D = P - I`, 2 x 2 row-major, and the derivatives of `P` along `g0` and `g1`.
    d: [T; 4],
    p0: [T; 4],
    p1: [T; 4],
    /// `q` and its derivatives along `g0`, `g1` and `z4`.
    q: [T; 2],
    q0: [T; 2],
    q1: [T; 2],
    qb: [T; 2],
}

/// The state after the substeps taken so far, and its sensitivities to `g0`, `g1` and `z4` (zero at the period's
/// start).
struct Track<T> {
    x: [T; 2],
    t0: [T; 2],
    t1: [T; 2],
    tb: [T; 2],
}

/// `m v`, `m` 2 x 2 row-major.
#[inline(always)]
fn mv2<T: Real>(m: &[T; 4], v: &[T; 2]) -> [T; 2] {
    [m[0] * v[0] + m[1] * v[1], m[2] * v[0] + m[3] * v[1]]
}

/// `a b`, both 2 x 2 row-major.
#[inline(always)]
fn mm2<T: Real>(a: &[T; 4], b: &[T; 4]) -> [T; 4] {
    [a[0] * b[0] + a[1] * b[2], a[0] * b[1] + a[1] * b[3], a[2] * b[0] + a[3] * b[2], a[2] * b[1] + a[3] * b[3]]
}

impl<T: Real> SubstepMap<T> {
    /// Take the map once on `s`: `x + (D x + q)`, and each sensitivity `t + (D t + dP x + dq)` (with the `x` before
    /// the map).
    #[inline(always)]
    fn take(&self, s: &mut Track<T>) {
        let (dt0, dt1, dtb) = (mv2(&self.d, &s.t0), mv2(&self.d, &s.t1), mv2(&self.d, &s.tb));
        let (p0x, p1x, dx) = (mv2(&self.p0, &s.x), mv2(&self.p1, &s.x), mv2(&self.d, &s.x));
        s.t0 = core::array::from_fn(|i| s.t0[i] + (dt0[i] + p0x[i] + self.q0[i]));
        s.t1 = core::array::from_fn(|i| s.t1[i] + (dt1[i] + p1x[i] + self.q1[i]));
        s.tb = core::array::from_fn(|i| s.tb[i] + (dtb[i] + self.qb[i]));
        s.x = core::array::from_fn(|i| s.x[i] + (dx[i] + self.q[i]));
    }

    /// `(I + D) (I + B) - I = D + B + D B`: the deviation of this map's `P` times `I + B`.
    #[inline(always)]
    fn after(&self, b: &[T; 4]) -> [T; 4] {
        let db = mm2(&self.d, b);
        core::array::from_fn(|i| (self.d[i] + b[i]) + db[i])
    }

    /// The map taken twice, in terms of `D`: `P P - I = 2 D + D D`, `P q + q = 2 q + D q`, and the derivatives
    /// `dP P + P dP = 2 dP + dP D + D dP`, `dP q + P dq + dq = 2 dq + dP q + D dq`.
    #[inline(always)]
    fn squared(&self) -> Self {
        let (d, q) = (&self.d, &self.q);
        let dp = |e: &[T; 4]| {
            let (a, b) = (mm2(e, d), mm2(d, e));
            core::array::from_fn(|i| (e[i] + e[i]) + (a[i] + b[i]))
        };
        let dq = |e: &[T; 4], f: &[T; 2]| {
            let (a, b) = (mv2(e, q), mv2(d, f));
            core::array::from_fn(|i| (f[i] + f[i]) + (a[i] + b[i]))
        };
        let (dd, dq0, dqb) = (mm2(d, d), mv2(d, q), mv2(d, &self.qb));
        SubstepMap {
            d: core::array::from_fn(|i| (d[i] + d[i]) + dd[i]),
            p0: dp(&self.p0),
            p1: dp(&self.p1),
            q: core::array::from_fn(|i| (q[i] + q[i]) + dq0[i]),
            q0: dq(&self.p0, &self.q0),
            q1: dq(&self.p1, &self.q1),
            qb: core::array::from_fn(|i| (self.qb[i] + self.qb[i]) + dqb[i]),
        }
    }

    /// Take the map `n` times on `s`, squaring it while more than [`DIRECT_SUBSTEPS`] remain (for an odd count taken
    /// once first); returns `s` and `P^n`. Out of line and in RAM beside the RK4, its arguments by value: the paper's
    /// 4 substeps never come here, and the hybrid filter's loop of them keeps its values in registers as without it
    /// (with the squaring inline, or `&mut` arguments, they went to the stack: 30 to 60 instructions more a sample).
    #[inline(never)]
    #[cfg_attr(target_os = "none", link_section = ".ramtext.ekf_take_squaring")] // src/bin/nanopos-fw/ram_code.rs
    fn take_squaring(mut self, mut s: Track<T>, mut n: u32) -> (Track<T>, [T; 4]) {
        // `P^n - I` so far.
        let mut power = [T::zero(); 4];
        while n > DIRECT_SUBSTEPS {
            if n % 2 == 1 {
                self.take(&mut s);
                power = self.after(&power);
            }
            n /= 2;
            self = self.squared();
        }
        for _ in 0..n {
            self.take(&mut s);
            power = self.after(&power);
        }
        let one = T::one();
        (s, [one + power[0], power[1], power[2], one + power[3]])
    }
}

impl<T: Real> EkfCore<T> {
    /// The state in the paper's units `[x1, x2, a0, a1, b0]`.
    pub fn state(&self) -> [f64; 5] {
        let i = &self.cfg.initial;
        let z = self.z.map(|x| x.as_f64());
        [z[0], z[1] * self.cfg.w.as_f64(), z[2] * i.a0, z[3] * i.a1, z[4] * i.b0]
    }

    /// The covariance in the paper's units.
    pub fn covariance(&self) -> [[f64; 5]; 5] {
        let i = &self.cfg.initial;
        let s = [1.0, self.cfg.w.as_f64(), i.a0, i.a1, i.b0];
        core::array::from_fn(|r| core::array::from_fn(|c| self.p[idx(r, c)].as_f64() * s[r] * s[c]))
    }

    /// The hybrid filter's prediction over one sample period: the state by RK4 in `substeps` steps of `h` with `u`
    /// held, the covariance through the Jacobian of that same RK4 map.
    ///
    /// With the parameters constant over the period and `u` held, the state equation is linear with constant
    /// coefficients, `x' = A x + [0, b]`, `A = [[0, W], [g0, g1]]` (`g0 = -c0 z2`, `g1 = -c1 z3`, `b = c2 z4 u`), and
    /// one RK4 step of length `h` is exactly the matrix polynomial
    ///
    /// ```text
    /// x+ = R x + S [0, b],   S = h (I + (h A / 2) (I + (h A / 3) (I + h A / 4))),   R = I + A S
    /// ```
    ///
    /// (Horner's form of `R = I + h A + (h A)^2 / 2 + (h A)^3 / 6 + (h A)^4 / 24`). `R` and `S` are computed once per
    /// sample, with their derivatives along `g0` and `g1` carried alongside (forward differentiation), and the
    /// `substeps` steps are taken on `x` and on its sensitivities to the parameters, `dx/dz2`, `dx/dz3`, `dx/dz4`: one
    /// at a time up to [`DIRECT_SUBSTEPS`], above it as powers of the one step's map ([`SubstepMap`], squared), the
    /// same in exact arithmetic.
    /// That gives the state RK4 gives, and `Phi = [[Psi, Sigma], [0, I]]`, the exact Jacobian of the RK4 map over
    /// the period (`Psi = R^substeps`, `Sigma` the sensitivities). The covariance is then propagated as the
    /// discrete EKF of that map propagates it:
    ///
    /// ```text
    /// P- = Phi P Phi' + Qd,   Qd_tt = T Q_t,   Qd_xt[i, :] = T / (1 + k_i) Sigma[i, :] Q_t,
    /// Qd_xx[i, j] = T Q_x[i] d_ij + T / (1 + k_i + k_j) Sigma[i, :] Q_t Sigma[j, :]',   k = [2, 1]
    /// ```
    ///
    /// `Qd` is `int_0^T Phi(T, s) Q Phi(T, s)' ds` to its leading order in `T`: a parameter disturbance entering at
    /// `s` moves `x2(T)` by about `Sigma[1, :] (T - s) / T` and `x1(T)` by `Sigma[0, :] ((T - s) / T)^2`, hence the
    /// powers `k`. It is exact in the parameter block; in the others it misses how the Jacobian's row
    /// `[-c0 x1, -c1 x2, c2 u]` moves over the period: 1.8 % of the process noise's part with `Q2` (`b0`'s share
    /// leading, whose row entry `c2 u` is held), up to 12 % of `a0`'s noise alone and 10 % of `a1`'s, in `x2`'s
    /// variance (measured: `tests::each_process_noise_alone_enters_where_it_belongs`), where `Q` is a tuning anyway.
    ///
    /// For the state this is the SPEC's RK4 in steps of `T / 4`, the same in exact arithmetic. For the covariance
    /// it is the Jacobian of that RK4 map instead of an RK4 of the Riccati equation `P' = F P + P F' + Q`: both are
    /// fourth-order, and per step they differ by 2e-4 of the covariance's scale `sqrt(P_ii P_jj)` at the start and
    /// 1.3e-6 once converged (`tests::the_prediction_matches_the_rk4_of_the_riccati_equation`); over 20 s of PRBS
    /// the estimates of the two differ by 4e-7 at most (`hal-sim/tests/ekf.rs`, against the dense peer, which keeps
    /// the Riccati RK4). Cost: about 130 flops for `R`, `S` and their derivatives, 60 per substep (about 130 per
    /// squaring above 4), 150 for `Phi P Phi' + Qd`: about 560 a sample, against about 1 600 for the Riccati RK4
    /// computed by parts (QEMU: `hekf_f32` 2 638 -> 1 011 instructions, 1 014 with the veneer to the covariance
    /// bounds in RAM).
    #[inline]
    fn predict(&mut self, u: T) {
        let c = &self.cfg;
        let (zero, one) = (T::zero(), T::one());
        let (w, g0, g1) = (c.w, -c.c0 * self.z[2], -c.c1 * self.z[3]);
        let (b, db) = (c.c2 * self.z[4] * u, c.c2 * u);
        // 2 x 2 matrices row-major, with their derivatives along g0 and g1: (M, dM/dg0, dM/dg1).
        let a_mul = |m: &[T; 4]| [w * m[2], w * m[3], g0 * m[0] + g1 * m[2], g0 * m[1] + g1 * m[3]];
        // (d I + k A M)' = k (E0 M + A M0), k (E1 M + A M1), with dA/dg0 = E0 = [[0, 0], [1, 0]], dA/dg1 = E1 =
        // [[0, 0], [0, 1]].
        let horner = |(m, m0, m1): ([T; 4], [T; 4], [T; 4]), d: T, k: T| {
            let (am, am0, am1) = (a_mul(&m), a_mul(&m0), a_mul(&m1));
            (
                [d + k * am[0], k * am[1], k * am[2], d + k * am[3]],
                [k * am0[0], k * am0[1], k * (m[0] + am0[2]), k * (m[1] + am0[3])],
                [k * am1[0], k * am1[1], k * (m[2] + am1[2]), k * (m[3] + am1[3])],
            )
        };
        let k = c.h_quarter;
        let m3 = ([one, k * w, k * g0, one + k * g1], [zero, zero, k, zero], [zero, zero, zero, k]);
        let m2 = horner(m3, one, c.h_third);
        let s = horner(m2, c.h, c.h_sq_half);
        let (r, r0, r1) = horner(s, one, one);
        // S [0, 1] and its derivatives: the input's column.
        let (sb, sb0, sb1) = ([s.0[1], s.0[3]], [s.1[1], s.1[3]], [s.2[1], s.2[3]]);
        let x0 = [self.z[0], self.z[1]];
        // The state and its sensitivities to g0, g1 and z4 (zero at the period's start), and Psi = R^substeps.
        let (Track { x, t0, t1, tb }, psi) = if c.substeps <= DIRECT_SUBSTEPS {
            // One substep at a time, `R` whole (`b S [0, 1]` and its derivatives in the loop: precomputed, the host's
            // f32 filter took 10 % longer).
            let (mut x, mut t0, mut t1, mut tb) = (x0, [zero; 2], [zero; 2], [zero; 2]);
            for _ in 0..c.substeps {
                let (rt0, rt1, rtb) = (mv2(&r, &t0), mv2(&r, &t1), mv2(&r, &tb));
                let (r0x, r1x, rx) = (mv2(&r0, &x), mv2(&r1, &x), mv2(&r, &x));
                t0 = core::array::from_fn(|i| rt0[i] + r0x[i] + b * sb0[i]);
                t1 = core::array::from_fn(|i| rt1[i] + r1x[i] + b * sb1[i]);
                tb = core::array::from_fn(|i| rtb[i] + db * sb[i]);
                x = core::array::from_fn(|i| rx[i] + b * sb[i]);
            }
            let mut psi = r;
            for _ in 1..c.substeps {
                psi = mm2(&r, &psi);
            }
            (Track { x, t0, t1, tb }, psi)
        } else {
            // `D = R - I = A S` (`R`'s last Horner step without its `I`: the same products, not rounded near 1).
            let map = SubstepMap {
                d: a_mul(&s.0),
                p0: r0,
                p1: r1,
                q: sb.map(|v| b * v),
                q0: sb0.map(|v| b * v),
                q1: sb1.map(|v| b * v),
                qb: sb.map(|v| db * v),
            };
            map.take_squaring(Track { x: x0, t0: [zero; 2], t1: [zero; 2], tb: [zero; 2] }, c.substeps)
        };
        self.z[0] = x[0];
        self.z[1] = x[1];
        // Sigma = dx/d[z2, z3, z4] (rows x1, x2).
        let sig = [[-c.c0 * t0[0], -c.c1 * t1[0], tb[0]], [-c.c0 * t0[1], -c.c1 * t1[1], tb[1]]];
        let p = &mut self.p;
        let pxx = [[p[idx(0, 0)], p[idx(0, 1)]], [p[idx(0, 1)], p[idx(1, 1)]]];
        let pxt: [[T; 3]; 2] = core::array::from_fn(|i| core::array::from_fn(|m| p[idx(i, m + 2)]));
        let ptt: [[T; 3]; 3] = core::array::from_fn(|l| core::array::from_fn(|m| p[idx(l + 2, m + 2)]));
        // Y = Psi Pxt + Sigma Ptt (the new Pxt before Qd), V = Psi Pxx + Sigma Pxt'.
        let y: [[T; 3]; 2] = core::array::from_fn(|i| {
            core::array::from_fn(|m| {
                psi[2 * i] * pxt[0][m]
                    + psi[2 * i + 1] * pxt[1][m]
                    + (sig[i][0] * ptt[0][m] + sig[i][1] * ptt[1][m] + sig[i][2] * ptt[2][m])
            })
        });
        let v: [[T; 2]; 2] = core::array::from_fn(|i| {
            core::array::from_fn(|j| {
                psi[2 * i] * pxx[0][j]
                    + psi[2 * i + 1] * pxx[1][j]
                    + (sig[i][0] * pxt[j][0] + sig[i][1] * pxt[j][1] + sig[i][2] * pxt[j][2])
            })
        });
        // Pxx- = V Psi' + Y Sigma' + Qd_xx.
        for (k, (i, j)) in [(0, 0), (0, 1), (1, 1)].into_iter().enumerate() {
            let q = if i == j { c.q_period[i] } else { zero };
            let (si, sj, qk) = (&sig[i], &sig[j], &c.q_xx[k]);
            p[idx(i, j)] = v[i][0] * psi[2 * j]
                + v[i][1] * psi[2 * j + 1]
                + ((y[i][0] + si[0] * qk[0]) * sj[0]
                    + (y[i][1] + si[1] * qk[1]) * sj[1]
                    + (y[i][2] + si[2] * qk[2]) * sj[2])
                + q;
        }
        for i in 0..2 {
            for m in 0..3 {
                p[idx(i, m + 2)] = y[i][m] + sig[i][m] * c.q_xt[i][m];
            }
        }
        for m in 0..3 {
            p[idx(m + 2, m + 2)] += c.q_period[m + 2];
        }
    }

    /// The model's parameters, from the normalised state.
    fn model_params(&self) -> StageParams<T> {
        let (c, z) = (&self.cfg, &self.z);
        StageParams { a0: z[2] * c.c0w, a1: z[3] * c.c1, b0: z[4] * c.b0_scale }
    }

    /// The model's `x2'` (normalised) at `z` with the input as `c2u = c2 u`: `-c0 z2 z0 - c1 z3 z1 + c2u z4`.
    #[inline(always)]
    fn x2_rate(&self, z: &[T; 5], c2u: T) -> T {
        let c = &self.cfg;
        -c.c0 * z[2] * z[0] - c.c1 * z[3] * z[1] + c2u * z[4]
    }

    /// `(z', P')` at `(z, P)` with input `u` (as `c2 u`, the same in every stage), and for the continuous filter the
    /// measurement `y` at that instant. Written entry by entry: `F` has two non-zero rows, so `F P + P F'` is zero in
    /// the parameter block and `Q` is on the diagonal only (an added `+0.0` is an instruction: the compiler may not
    /// drop it, `-0.0 + 0.0` being `+0.0`).
    #[inline(always)]
    fn derivative(&self, z: &[T; 5], p: &[T; 15], c2u: T, y: Option<T>) -> ([T; 5], [T; 15]) {
        let c = &self.cfg;
        // Row 1 of F; row 0 is W e2.
        let f1 = [-c.c0 * z[2], -c.c1 * z[3], -c.c0 * z[0], -c.c1 * z[1], c2u];
        // x2' is `Self::x2_rate`, here from the Jacobian row's products.
        let mut dz = [c.w * z[1], f1[0] * z[0] + f1[1] * z[1] + c2u * z[4], T::zero(), T::zero(), T::zero()];
        // M = F P: row 0 = W P[1, :], row 1 = f1 . P[:, j].
        let m0: [T; 5] = core::array::from_fn(|j| c.w * p[idx(1, j)]);
        let m1: [T; 5] = core::array::from_fn(|j| {
            f1[0] * p[idx(0, j)]
                + f1[1] * p[idx(1, j)]
                + f1[2] * p[idx(2, j)]
                + f1[3] * p[idx(3, j)]
                + f1[4] * p[idx(4, j)]
        });
        let mut dp = [T::zero(); 15];
        dp[idx(0, 0)] = (m0[0] + m0[0]) + c.q[0];
        dp[idx(0, 1)] = m0[1] + m1[0];
        dp[idx(1, 1)] = (m1[1] + m1[1]) + c.q[1];
        for j in 2..5 {
            dp[idx(0, j)] = m0[j];
            dp[idx(1, j)] = m1[j];
            dp[idx(j, j)] = c.q[j];
        }
        if let Some(y) = y {
            // Continuous measurement: K = P H' / R, z' += K (y - x1), P' -= P H' H P / R.
            let p0: [T; 5] = core::array::from_fn(|i| p[idx(0, i)]);
            let k: [T; 5] = p0.map(|v| v * c.inv_r);
            let innovation = y - z[0];
            for i in 0..5 {
                dz[i] += k[i] * innovation;
                for j in i..5 {
                    dp[idx(i, j)] -= k[i] * p0[j];
                }
            }
        }
        (dz, dp)
    }

    /// One RK4 step over the sample period from `(z, p)` (the caller's copy of the state, which the step then
    /// replaces: one copy a step, which the continuous filter's gate needs anyway) with `u` held; with
    /// `ys = (y_start, y_end, bow)` the continuous measurement, `y_start + (y_end - y_start) f + bow f (1 - f)` at the
    /// fraction `f` of the step.
    #[cfg_attr(target_os = "none", link_section = ".ramtext.ekf_rk4")] // from RAM: src/bin/nanopos-fw/ram_code.rs
    fn rk4(&mut self, (z, p): &([T; 5], [T; 15]), u: T, ys: Option<(T, T, T)>) {
        let (h, h6, half) = (self.cfg.period, self.cfg.period6, T::of(0.5));
        let hh = h * half;
        let y_at = |frac: T| ys.map(|(a, b, bow)| a + (b - a) * frac + bow * frac * (T::one() - frac));
        let c2u = self.cfg.c2 * u;
        let (k1z, k1p) = self.derivative(z, p, c2u, y_at(T::zero()));
        let (z2, p2) = (axpy(z, &k1z, hh), axpy(p, &k1p, hh));
        let (k2z, k2p) = self.derivative(&z2, &p2, c2u, y_at(half));
        let (z3, p3) = (axpy(z, &k2z, hh), axpy(p, &k2p, hh));
        let (k3z, k3p) = self.derivative(&z3, &p3, c2u, y_at(half));
        let (z4, p4) = (axpy(z, &k3z, h), axpy(p, &k3p, h));
        let (k4z, k4p) = self.derivative(&z4, &p4, c2u, y_at(T::one()));
        rk4_combine(&mut self.z, z, [&k1z, &k2z, &k3z, &k4z], h6);
        rk4_combine(&mut self.p, p, [&k1p, &k2p, &k3p, &k4p], h6);
    }

    /// Joseph-form update with the innovation `innovation` of `x1`, its variance `s = P00 + R_d` and `1 / s`.
    fn correct(&mut self, innovation: T, s: T, inv_s: T) {
        let p0: [T; 5] = core::array::from_fn(|i| self.p[idx(0, i)]);
        let k: [T; 5] = p0.map(|x| x * inv_s);
        for i in 0..5 {
            self.z[i] += k[i] * innovation;
        }
        // (I - K H) P (I - K H)' + K R_d K' = P - K p0' - p0 K' + K K' (p00 + R_d), entry by entry.
        for i in 0..5 {
            for j in i..5 {
                let e = idx(i, j);
                self.p[e] = self.p[e] - k[i] * p0[j] - p0[i] * k[j] + k[i] * k[j] * s;
            }
        }
    }

    /// Hold the parameters: decouple them from the states (block-diagonal `P`, which stays positive semidefinite)
    /// and return what to restore after the step.
    fn freeze_parameters(&mut self) -> ([T; 3], [T; 6]) {
        for i in 0..2 {
            for j in 2..5 {
                self.p[idx(i, j)] = T::zero();
            }
        }
        ([self.z[2], self.z[3], self.z[4]], core::array::from_fn(|k| self.p[PARAM_BLOCK[k]]))
    }

    fn restore_parameters(&mut self, f: &([T; 3], [T; 6])) {
        self.z[2..5].copy_from_slice(&f.0);
        for (k, &e) in PARAM_BLOCK.iter().enumerate() {
            self.p[e] = f.1[k];
        }
        for i in 0..2 {
            for j in 2..5 {
                self.p[idx(i, j)] = T::zero();
            }
        }
    }

    /// After a detected change: parameter covariance reopened to `P0`, uncorrelated (after a drift it then grows,
    /// [`Self::widen_parameters`]).
    fn reopen_parameters(&mut self) {
        let p = self.cfg.p0;
        for j in 2..5 {
            for i in 0..5 {
                self.p[idx(i, j)] = T::zero();
            }
            self.p[idx(j, j)] = p[j];
        }
    }

    /// After a change the gate saw: the state variances reopened to `R_d = R / T` (one measurement's worth of
    /// uncertainty), uncorrelated. Not to the size of the transient (`nu^2`, above `R_d` on the board's bump): the
    /// continuous filter's one RK4 step of the Riccati equation, whose measurement term decays `P00` at the rate
    /// `2 P00 / R`, is stable only below `P00 = 1.39 R / T` (RK4's 2.785 on the real axis), and with `nu^2` its
    /// PRBS relock slowed from 0.21 s to 0.5-0.8 s. At `R_d` both filters relock alike.
    fn reopen_states(&mut self) {
        for i in 0..2 {
            for j in 0..5 {
                self.p[idx(i, j)] = T::zero();
            }
            self.p[idx(i, i)] = self.cfg.r_d;
        }
    }

    /// One sample's growth of the parameter variances after a drift: process noise added to their diagonal, which
    /// keeps `P` positive semidefinite.
    fn widen_parameters(&mut self) {
        for (k, j) in (2..5).enumerate() {
            self.p[idx(j, j)] += self.cfg.p_ramp_step[k];
        }
    }

    /// Parameter variances within their floor and ceiling; a state variance below zero repaired, and counted in
    /// `repairs`.
    #[cfg_attr(target_os = "none", link_section = ".ramtext.ekf_bound_covariance")]
    fn bound_covariance(&mut self, repairs: &mut u32) {
        // The continuous filter integrates the Riccati equation in one RK4 step per sample, and a state variance
        // swinging near zero can overshoot below it (on the board's triangle, adapting from the first sample, 30 ms
        // after the start, the x2 variance fell from 37.6 by 84 um^2/s^2 per sample: `hal-sim/tests/ekf_health.rs`).
        // Decorrelate that state and give it its floor: `P` is then positive semidefinite again if the rest of it
        // was, and the filter carries on instead of resetting.
        for i in 0..2 {
            if self.p[idx(i, i)] < T::zero() {
                for j in 0..5 {
                    self.p[idx(i, j)] = T::zero();
                }
                self.p[idx(i, i)] = self.cfg.p_floor[i];
                *repairs = repairs.saturating_add(1);
            }
        }
        for i in 2..5 {
            let v = self.p[idx(i, i)];
            if v > self.cfg.p_ceiling[i] {
                // Congruence with diag(1, .., sqrt(c / v), ..): scales row and column i, keeps P >= 0.
                let f = (self.cfg.p_ceiling[i] / v).sqrt();
                for j in 0..5 {
                    if j != i {
                        self.p[idx(i, j)] *= f;
                    }
                }
                self.p[idx(i, i)] = self.cfg.p_ceiling[i];
            } else if v < self.cfg.p_floor[i] {
                self.p[idx(i, i)] = self.cfg.p_floor[i];
            }
        }
    }

    /// Called after [`Self::bound_covariance`], which leaves no finite diagonal below zero: finiteness is all that
    /// is left to check, of the state, the covariance, `levels` (the health logic's own) and the parameters as
    /// reported. A normalised parameter can be finite and its report not: with `b0`'s `q` at 3.4e38 (`p0` 10 times
    /// that, still finite normalised by a `b0_init` of 5e5) a diverging continuous EKF reported `b0 = inf` for a
    /// sample before its state overflowed (the random session of seed 7, 500 000 lines).
    fn healthy(&self, levels: T) -> bool {
        let p = self.model_params();
        // The sum of all is finite exactly when each is (or, harmlessly, when they are near overflow anyway).
        let sum = self.z.iter().chain(self.p.iter()).fold(levels + (p.a0 + p.a1 + p.b0), |acc, &x| acc + x);
        sum.is_finite()
    }
}

impl<T: Real, K: EkfKind> Estimator<T> for Ekf<T, K> {
    const NAME: &'static str = K::NAME;

    fn update(&mut self, s: &FilteredSample<T>) {
        let _ = self.kind;
        let cfg = &self.core.cfg;
        let innovation_block = cfg.innovation_block;
        let (nis_alpha, change_samples, holdoff_samples) = (cfg.nis_alpha, cfg.change_samples, cfg.holdoff_samples);
        let (drift_ratio, drift_alpha, drift_wait_samples) = (cfg.drift_ratio, cfg.drift_alpha, cfg.drift_wait_samples);
        let gate2 = cfg.gate2;
        let u = s.u_f.value;
        if !(u.is_finite() && s.y_f.value.is_finite()) {
            // Caught at the door: nothing non-finite reaches the state or the stored previous sample.
            self.reset_counted(None);
            return;
        }
        if !self.primed {
            self.prime(s);
            return;
        }
        let adapt = self.core.cfg.pe.adapt(&s.pe, self.adapting, &mut self.health);
        let frozen = (!adapt).then(|| self.core.freeze_parameters());
        let gating = change_samples > 0 && self.holdoff == 0;
        let gate = if gating { gate2 * fmax(self.nis_mean, T::epsilon()) } else { T::greatest() };
        let (nu, nis) = K::step(&mut self.core, self.u_prev, self.y_prev, s.y_f.value, gate);
        self.innovation.add(nu, innovation_block);
        if let Some(f) = frozen {
            self.core.restore_parameters(&f);
        }
        self.holdoff = self.holdoff.saturating_sub(1);
        let waiting = self.drift_wait > 0;
        self.drift_wait = self.drift_wait.saturating_sub(1);
        // A detected change, and whether the drift detector saw it.
        let changed = if let Some(nis) = nis {
            self.gated_run = 0;
            self.nis_mean += nis_alpha * (nis - self.nis_mean);
            if waiting {
                // The long-run level holds the one before the wait, which the wait's end compares with.
                None
            } else {
                self.nis_long += drift_alpha * (nis - self.nis_long);
                // A sustained rise: the plant drifted or changed by less than the gate sees.
                (self.nis_mean > drift_ratio * self.nis_long).then_some(true)
            }
        } else {
            self.gated_run += 1;
            self.health.rejected_samples = self.health.rejected_samples.saturating_add(1);
            // Not an outlier: the plant changed.
            (self.gated_run >= change_samples).then_some(false)
        };
        if let Some(drift) = changed {
            // Reopen the parameter covariance and let the filter relock. A drift is quiet: the parameter variances
            // then grow over `ramp_samples`, from this sample on. A change the gate saw comes with a transient (the
            // bump): the state is reopened too, so that the filter explains it as a state, not by moving the
            // parameters.
            self.core.reopen_parameters();
            if drift {
                self.ramp = self.core.cfg.ramp_samples;
            } else {
                self.ramp = 0;
                self.core.reopen_states();
            }
            self.health.changes_detected = self.health.changes_detected.saturating_add(1);
            self.gated_run = 0;
            self.holdoff = holdoff_samples;
            self.drift_wait = drift_wait_samples;
            // The relock's reference over the wait: the long-run level before it, at least 1.
            self.nis_long = fmax(self.nis_long, T::one());
        }
        // The wait's end (no change detected in its last sample): a filter whose `nu^2 / S` is [`RELOCK_NIS_RATIO`]
        // times the long-run level held over the wait (at least 1) did not relock, and is reset below. The long-run
        // level starts from the short-run one.
        let mut no_relock = false;
        if waiting && self.drift_wait == 0 {
            no_relock = self.nis_mean > T::of(RELOCK_NIS_RATIO) * self.nis_long;
            self.nis_long = self.nis_mean;
        }
        if self.ramp > 0 {
            self.ramp -= 1;
            self.core.widen_parameters();
        }
        self.core.bound_covariance(&mut self.health.covariance_repairs);
        // The innovation's levels too: they are state of the health logic, and one non-finite (an innovation whose
        // square overflowed) would stay in the report for good and blind the gate and the drift test. And an
        // innovation RMS beyond [`INNOVATION_CEILING_UM`] is no stage's: the squares of the current and the last
        // block, scaled so that they overflow the sum there, in either scalar.
        let levels = self.innovation.squares() * self.core.cfg.innovation_to_range + self.nis_mean + self.nis_long;
        if no_relock || !self.core.healthy(levels) {
            self.reset_counted(no_relock.then_some(self.nis_long));
        }
        self.u_prev = u;
        self.y_prev = s.y_f.value;
    }

    fn params(&self) -> StageParams<T> {
        K::reported(&self.core)
    }

    fn param_covariance(&self) -> [[T; 3]; 3] {
        let c = self.covariance();
        core::array::from_fn(|r| core::array::from_fn(|col| T::of(c[2 + r][2 + col])))
    }

    fn reset(&mut self) {
        self.reset_state();
    }

    /// The states taken again from the next sample; the parameters and the covariance kept.
    fn resume(&mut self) {
        self.primed = false;
    }

    fn set_adapting(&mut self, on: bool) {
        self.adapting = on;
        self.health.adaptation = Adaptation::asked(on);
    }

    fn health(&self) -> Health {
        // The square root when asked, not per sample, and in the working scalar: on the target libm's `sqrtf`, in
        // software but in f32 (70 instructions, about 50 on a normal number's way: rustc 1.95 has no stable way to
        // emit `vsqrt.f32` in `no_std`, see BENCHMARKS.md on `vfma`), not a software f64 one under the lock the
        // status is taken in. The same f32 either way (a square root rounded to f64 and then to f32 is the correctly
        // rounded f32 one).
        Health { innovation_rms_um: self.innovation.rms(self.core.cfg.innovation_block).as_f64() as f32, ..self.health }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimator::PeLevel;
    use crate::filters::prefilter::Prefiltered;

    /// The design states the physical tuning in samples and in the normalised units: each constant checked against
    /// its value worked out by hand for the paper's tuning at 10 kHz with 4 substeps (the health logic's defaults:
    /// a 5-sigma gate, 0.5 s level and hold-off, a drift test at 4 times the 10-s level after 5 s, a ceiling and a
    /// reopening of 500 `P0` ramped over 10 ms, a floor of 1e-9 `P0`).
    #[test]
    fn the_design_states_the_tuning_in_samples_and_normalised_units() {
        let design = EkfDesign::paper(EkfDesign::Q2);
        let c = design.design::<f64>();
        let close = |got: f64, want: f64, what: &str| {
            assert!((got / want - 1.0).abs() < 1e-12, "{what}: {got} against {want}");
        };
        close(c.gate2, 25.0, "gate2");
        close(c.nis_alpha, 2e-4, "nis_alpha");
        close(c.drift_ratio, 4.0, "drift_ratio");
        close(c.drift_alpha, 1e-5, "drift_alpha");
        assert_eq!(
            (c.change_samples, c.holdoff_samples, c.drift_wait_samples, c.innovation_block, c.ramp_samples),
            (20, 5_000, 50_000, 10_000, 100)
        );
        // The innovation's sum over a block of 10 000 samples at the ceiling of 1e6 um stays in range.
        close(c.innovation_to_range, f64::MAX / 1e16, "innovation_to_range");
        close(c.h, 2.5e-5, "h");
        close(c.period, 1e-4, "period");
        close(c.inv_r, 1.0 / 1.5e-6, "inv_r");
        close(c.r_d, 1.5e-2, "r_d");
        // Normalised: the states by 1 and `1 / w`, the parameters by their initial values.
        let p = StageParams::INITIAL;
        let scale = [1.0, 1.0 / p.a0.sqrt(), 1.0 / p.a0, 1.0 / p.a1, 1.0 / p.b0];
        for i in 0..5 {
            let p0 = 10.0 * EkfDesign::Q2[i] * scale[i] * scale[i];
            close(c.p0[i], p0, "p0");
            close(c.q[i], EkfDesign::Q2[i] * scale[i] * scale[i], "q");
            close(c.q_period[i], 1e-4 * c.q[i], "q_period");
            close(c.p_ceiling[i], 500.0 * p0, "p_ceiling");
            close(c.p_floor[i], 1e-9 * p0, "p_floor");
            if i >= 2 {
                // The reopening's widening, 500 P0 less the P0 there is, over 100 samples.
                close(c.p_ramp_step[i - 2], 499.0 * p0 / 100.0, "p_ramp_step");
            }
        }
        // The model's constants in the normalised state (`x2 = x' / w`) and the RK4's steps over the sample.
        let w = p.a0.sqrt();
        for (got, want, what) in [
            (c.w, w, "w"),
            (c.c0, p.a0 / w, "c0"),
            (c.c1, p.a1, "c1"),
            (c.c2, p.b0 / w, "c2"),
            (c.c0w, p.a0, "c0w"),
            (c.b0_scale, p.b0, "b0_scale"),
            (c.period6, 1e-4 / 6.0, "period6"),
            (c.half_period, 5e-5, "half_period"),
            (c.bow_gain, -w * 1e-8 / 2.0, "bow_gain"),
        ] {
            close(got, want, what);
        }
        // The drift test off: an infinite ratio, which no level exceeds.
        let off = EkfDesign { health: EkfHealthDesign { drift_ratio: 0.0, ..design.health }, ..design };
        assert_eq!(off.design::<f64>().drift_ratio, f64::INFINITY);
        // `Q2` for an input 4 times as strong in power: the parameters' entries a quarter, the states' as they are.
        let q2x4 = EkfDesign::q2_for_strength(4.0);
        for i in 0..5 {
            let want = if i < 2 { EkfDesign::Q2[i] } else { EkfDesign::Q2[i] / 4.0 };
            close(q2x4[i], want, "q2_for_strength");
        }
    }

    /// The first sample after a start, a reset or a resume sets the states, the filtered reading and its rate, and
    /// steps nothing; a reset also takes the parameters back to the initial ones, a resume keeps them.
    #[test]
    fn the_first_sample_after_a_start_a_reset_or_a_resume_sets_the_states() {
        let pe = PeLevel { power: 1.0, single: false };
        let at = |value, d1| FilteredSample {
            u: 0.3,
            y: value,
            u_f: Prefiltered { value: 0.3, d1: 0.0, d2: 0.0 },
            y_f: Prefiltered { value, d1, d2: 0.0 },
            pe,
        };
        let sets = |state: [f64; 5], value: f64, rate: f64| state[0] == value && (state[1] / rate - 1.0).abs() < 1e-12;
        let design = EkfDesign::default().design();
        let mut started = Cekf::<f64>::new(design);
        started.update(&at(2.5, 4000.0));
        assert!(sets(started.state(), 2.5, 4000.0), "{:?}", started.state());
        assert_eq!(started.params(), Cekf::<f64>::new(design).params());
        let mut f = converged_hybrid(1.0);
        let converged = f.params();
        f.resume();
        f.update(&at(-1.5, -300.0));
        assert!(sets(f.state(), -1.5, -300.0), "{:?}", f.state());
        assert_eq!(f.params(), converged);
        // The next sample steps from there.
        f.update(&at(-1.5, -300.0));
        assert!(f.state()[0] != -1.5);
        f.reset();
        f.update(&at(0.7, 50.0));
        assert!(sets(f.state(), 0.7, 50.0), "{:?}", f.state());
        assert_eq!(f.params(), Hekf::<f64>::new(design).params());
    }

    /// The hybrid filter after `seconds` of a pseudo-random +-1 V input on the exact model (1) at the payload's
    /// parameters, sampled at 10 kHz with the input held (what the filter assumes), no noise.
    fn converged_hybrid(seconds: f64) -> Hekf<f64> {
        let truth = StageParams::PAYLOAD;
        let mut f = Hekf::<f64>::new(EkfDesign::default().design());
        let (mut x, mut v, mut u, mut lfsr) = (0.0f64, 0.0f64, 0.0f64, 0xACE1u16);
        for _ in 0..(seconds * 1e4) as usize {
            let sample = |value| Prefiltered { value, d1: 0.0, d2: 0.0 };
            let pe = PeLevel { power: 1.0, single: false }; // the level of a +-1 V PRBS
            f.update(&FilteredSample { u, y: x, u_f: sample(u), y_f: sample(x), pe });
            // The next input, held over the next period; the plant by fine RK4 (exact to rounding at 1 us).
            lfsr = (lfsr >> 1) ^ (0u16.wrapping_sub(lfsr & 1) & 0xB400);
            u = if lfsr & 1 == 1 { 1.0 } else { -1.0 };
            for _ in 0..100 {
                let d = |x: f64, v: f64| (v, -truth.a0 * x - truth.a1 * v + truth.b0 * u);
                let h = 1e-6;
                let k1 = d(x, v);
                let k2 = d(x + h / 2.0 * k1.0, v + h / 2.0 * k1.1);
                let k3 = d(x + h / 2.0 * k2.0, v + h / 2.0 * k2.1);
                let k4 = d(x + h * k3.0, v + h * k3.1);
                x += h / 6.0 * (k1.0 + 2.0 * k2.0 + 2.0 * k3.0 + k4.0);
                v += h / 6.0 * (k1.1 + 2.0 * k2.1 + 2.0 * k3.1 + k4.1);
            }
        }
        f
    }

    /// A wait of no length is one of a sample: without its end the long-run level, floored at 1 for the relock test
    /// at a change, would stay there and blind the drift detector for tens of seconds.
    #[test]
    fn a_drift_wait_is_at_least_one_sample() {
        let mut design = EkfDesign::default();
        design.health.drift_wait_s = 0.0;
        assert_eq!(design.design::<f64>().drift_wait_samples, 1);
        design.health.drift_wait_s = 5.0;
        assert_eq!(design.design::<f64>().drift_wait_samples, 50_000);
    }

    /// A continuous step whose residual the gate rejects is the step without the measurement from the state before
    /// it (not from the rejected step's result); one the gate passes uses the measurement.
    #[test]
    fn a_rejected_continuous_step_is_taken_again_from_where_it_started_without_the_measurement() {
        let before = converged_hybrid(0.01).core;
        let (u, y_prev, y) = (0.7, before.z[0], before.z[0] + 0.5);
        let mut free = before;
        free.rk4(&(before.z, before.p), u, None);
        let mut rejected = before;
        let (nu, nis) = Continuous::step(&mut rejected, u, y_prev, y, 0.0);
        assert!(nis.is_none() && nu != 0.0, "a zero gate rejects every residual");
        assert_eq!((rejected.z, rejected.p), (free.z, free.p));
        let mut accepted = before;
        let (_, nis) = Continuous::step(&mut accepted, u, y_prev, y, f64::INFINITY);
        assert!(nis.is_some());
        assert!(accepted.z[0] > free.z[0] + 1e-6, "the measurement above pulls x1 up");
    }

    /// One hybrid prediction by the RK4 of the whole state and Riccati equation (`z' = f`, `P' = F P + P F' + Q`,
    /// 20 values): the continuous filter's RK4 without a measurement, its step set to the substep, `substeps`
    /// times. The SPEC's rule, which [`EkfCore::predict`] replaces.
    fn predict_by_riccati_rk4(before: &EkfCore<f64>, u: f64) -> ([f64; 5], [f64; 15]) {
        let mut core = *before;
        (core.cfg.period, core.cfg.period6) = (before.cfg.h, before.cfg.h / 6.0);
        for _ in 0..before.cfg.substeps {
            core.rk4(&(core.z, core.p), u, None);
        }
        (core.z, core.p)
    }

    /// `z` is `reference` within `tolerance` of `1 + |reference|` in every value.
    fn assert_same_state(z: &[f64; 5], reference: &[f64; 5], tolerance: f64, what: &str) {
        for i in 0..5 {
            assert!(
                (z[i] - reference[i]).abs() <= tolerance * (1.0 + reference[i].abs()),
                "{what}: z{i} {} against {}",
                z[i],
                reference[i]
            );
        }
    }

    /// The largest difference of two covariances entry by entry, relative to the correlation scale
    /// `sqrt(P_ii P_jj)` of `reference`.
    fn worst_difference(p: &[f64; 15], reference: &[f64; 15]) -> (f64, (usize, usize)) {
        let mut worst = (0.0, (0, 0));
        for i in 0..5 {
            for j in i..5 {
                let e = idx(i, j);
                let rel = (p[e] - reference[e]).abs() / (reference[idx(i, i)] * reference[idx(j, j)]).sqrt();
                if rel > worst.0 {
                    worst = (rel, (i, j));
                }
            }
        }
        worst
    }

    /// The prediction through the RK4 map's Jacobian against the RK4 of the Riccati equation, at the start (`P0`)
    /// and on filters converged for 10 ms to 3 s. The state is the same RK4, so it agrees to rounding.
    /// - **Without process noise** the covariances differ only by the two fourth-order rules' `O(h^5)`: measured
    ///   at most 2.0e-4 of the correlation scale at the start (`P0`'s wide parameter variances make `Sigma C Sigma'`
    ///   largest there) and 1.3e-6 once converged.
    /// - **The process noise alone** (`P = 0` before the step, so `P-` is `Qd`): the parameter block exactly
    ///   `T Q_theta`, the rest within 1.8e-2 of the scale (the leading-order rule misses how `e = [-c0 x1, -c1 x2,
    ///   c2 u]` moves over the period). A wrong coefficient (`1/2` for `1/3` in a row, `1/3` for `1/5`) is off by 0.3
    ///   or more.
    #[test]
    fn the_prediction_matches_the_rk4_of_the_riccati_equation() {
        for (seconds, homogeneous_bound) in [(1e-4, 3e-4), (0.01, 2e-6), (0.3, 2e-6), (3.0, 2e-6)] {
            let converged = converged_hybrid(seconds).core;
            let u = 0.7;
            let mut no_noise = converged;
            (no_noise.cfg.q, no_noise.cfg.q_period) = ([0.0; 5], [0.0; 5]);
            (no_noise.cfg.q_xt, no_noise.cfg.q_xx) = ([[0.0; 3]; 2], [[0.0; 3]; 3]);
            let mut noise_only = converged;
            noise_only.p = [0.0; 15];
            for (before, bound) in
                [(no_noise, homogeneous_bound), (noise_only, 2.5e-2), (converged, homogeneous_bound + 2.5e-2)]
            {
                let (z, p) = predict_by_riccati_rk4(&before, u);
                let mut new = before;
                new.predict(u);
                assert_same_state(&new.z, &z, 1e-15, &format!("{seconds} s"));
                let (worst, (i, j)) = worst_difference(&new.p, &p);
                assert!(
                    worst < bound,
                    "{seconds} s: P{i}{j} {} against {}: {worst:.1e}",
                    new.p[idx(i, j)],
                    p[idx(i, j)]
                );
                for e in PARAM_BLOCK {
                    assert!((new.p[e] - p[e]).abs() <= 1e-15 * p[e].abs(), "{seconds} s: the parameter block");
                }
            }
        }
    }

    /// Each source of process noise alone, from `P = 0`, on filters converged for 10 ms to 3 s. A parameter's:
    /// `Qd` within 0.15 of the correlation scale of the Riccati RK4's, and nothing where the RK4 has none. Measured
    /// at most 0.12 (`a0`'s), 0.10 (`a1`'s) and 0.012 (`b0`'s), always in `x2`'s variance: `Qd` misses how the
    /// Jacobian's row `[-c0 x1, -c1 x2, c2 u]` moves over the period, and only `u` is held. With `Q2` all together
    /// `b0`'s share leads and the difference is within 1.8e-2 (above), where `a1`'s share of `Qd_xx` with its sign
    /// wrong went unseen; alone, a wrong sign is off by 2 and a wrong coefficient by 0.3 or more. A state's: `T Q_x`
    /// on its own diagonal and nothing else, to leading order as `Qd` is (the RK4 also carries `x2`'s noise into
    /// `x1`, at `O(T^3)`).
    #[test]
    fn each_process_noise_alone_enters_where_it_belongs() {
        for seconds in [0.01, 0.1, 0.3, 1.0, 3.0] {
            let converged = converged_hybrid(seconds).core;
            let u = 0.7;
            for m in 0..5 {
                let mut q = [0.0; 5];
                q[m] = EkfDesign::Q2[m];
                let mut before = converged;
                before.cfg = EkfDesign::paper(q).design();
                before.p = [0.0; 15];
                let mut new = before;
                new.predict(u);
                if m < 2 {
                    let mut expected = [0.0; 15];
                    expected[idx(m, m)] = before.cfg.q_period[m];
                    assert!(expected[idx(m, m)] > 0.0);
                    assert_eq!(new.p, expected, "{seconds} s, x{m}'s noise alone");
                } else {
                    let (_, p) = predict_by_riccati_rk4(&before, u);
                    let (worst, (i, j)) = worst_difference(&new.p, &p);
                    assert!(
                        worst < 0.15,
                        "{seconds} s, parameter {m}'s noise alone: P{i}{j} {} against {}",
                        new.p[idx(i, j)],
                        p[idx(i, j)]
                    );
                }
            }
        }
    }

    /// The continuous filter's right-hand side, written entry by entry, is the dense one: `z' = f(z) + K (y - x1)`
    /// and `P' = F P + P F' + Q - K H P` (`K = P H' / R`, `H = e1`), with the measurement and without, at a
    /// converged filter's state and covariance; and `x2_rate` (the curvature term's) is `f(z)`'s `x2'`. The
    /// hybrid filter's tests compare its prediction with the RK4 of this derivative, so they cannot see its errors:
    /// the state noise's sign, the measurement's terms wrong, passed them all.
    #[test]
    fn the_derivative_is_the_dense_right_hand_side() {
        let core = converged_hybrid(0.3).core;
        let (c, z) = (&core.cfg, core.z);
        let c2u = c.c2 * 0.7;
        let mut f = [[0.0; 5]; 5];
        f[0][1] = c.w;
        f[1] = [-c.c0 * z[2], -c.c1 * z[3], -c.c0 * z[0], -c.c1 * z[1], c2u];
        let p: [[f64; 5]; 5] = core::array::from_fn(|i| core::array::from_fn(|j| core.p[idx(i, j)]));
        // F P and its terms' magnitudes, for a bound on the rounding.
        let fp: [[f64; 5]; 5] =
            core::array::from_fn(|i| core::array::from_fn(|j| (0..5).map(|k| f[i][k] * p[k][j]).sum()));
        let size: [[f64; 5]; 5] =
            core::array::from_fn(|i| core::array::from_fn(|j| (0..5).map(|k| (f[i][k] * p[k][j]).abs()).sum()));
        let rate = -c.c0 * z[2] * z[0] - c.c1 * z[3] * z[1] + c2u * z[4];
        assert!((core.x2_rate(&z, c2u) - rate).abs() <= 1e-15 * rate.abs().max(1.0));
        for y in [None, Some(z[0] + 0.3), Some(z[0] - 2.0)] {
            let (dz, dp) = core.derivative(&z, &core.p, c2u, y);
            let mut want_z = [c.w * z[1], rate, 0.0, 0.0, 0.0];
            for i in 0..5 {
                let gain = y.map_or(0.0, |y| p[i][0] * c.inv_r * (y - z[0]));
                want_z[i] += gain;
                assert!(
                    (dz[i] - want_z[i]).abs() <= 1e-14 * (want_z[i].abs() + 1.0),
                    "{y:?}: z{i}' {} against {}",
                    dz[i],
                    want_z[i]
                );
                for j in i..5 {
                    let measured = if y.is_some() { p[i][0] * p[0][j] * c.inv_r } else { 0.0 };
                    let q = if i == j { c.q[i] } else { 0.0 };
                    let want = fp[i][j] + fp[j][i] + q - measured;
                    let bound = 1e-14 * (size[i][j] + size[j][i] + q + measured.abs());
                    assert!((dp[idx(i, j)] - want).abs() <= bound, "{y:?}: P{i}{j}' {} against {want}", dp[idx(i, j)]);
                }
            }
        }
    }

    /// The covariance's bounds, each on its own entries: a parameter variance above its ceiling brought to it by a
    /// congruence (its row and column times `sqrt(ceiling / v)`, the correlations kept), one below its floor raised to
    /// it alone, a state variance below zero decorrelated, floored and counted; the rest as it was, to the bit.
    /// (The suites' filters never reach the ceiling: with the excitation gone the monitor holds them first.)
    #[test]
    fn the_covariance_bounds_scale_raise_and_repair_only_their_own_entries() {
        let mut core = converged_hybrid(0.3).core;
        let (ceiling, floor) = (core.cfg.p_ceiling, core.cfg.p_floor);
        // a0's variance 4 times its ceiling (its row and column halved), b0's half its floor, x2's below zero.
        core.p[idx(2, 2)] = 4.0 * ceiling[2];
        core.p[idx(4, 4)] = 0.5 * floor[4];
        core.p[idx(1, 1)] = -1e-9;
        let start = core.p;
        let mut repairs = 3;
        core.bound_covariance(&mut repairs);
        assert_eq!(repairs, 4);
        for i in 0..5 {
            for j in i..5 {
                let want = match (i, j) {
                    (1, 1) => floor[1],
                    (1, _) | (_, 1) => 0.0,
                    (2, 2) => ceiling[2],
                    (2, _) | (_, 2) => start[idx(i, j)] * 0.5,
                    (4, 4) => floor[4],
                    _ => start[idx(i, j)],
                };
                assert_eq!(core.p[idx(i, j)], want, "P{i}{j}");
            }
        }
        assert!(start[idx(0, 2)] != 0.0 && start[idx(2, 3)] != 0.0 && start[idx(2, 4)] != 0.0, "correlated");
        assert!(floor[3] < start[idx(3, 3)] && start[idx(3, 3)] < ceiling[3], "a1's variance within its bounds");
        // Nothing beyond a bound: nothing changes.
        let settled = core.p;
        core.bound_covariance(&mut repairs);
        assert_eq!((core.p, repairs), (settled, 4));
    }

    /// The prediction with any number of substeps, the maps squared above `DIRECT_SUBSTEPS`: the state is the RK4's
    /// in `substeps` steps (to rounding), and `Psi` and `Sigma` are the derivatives of that state along the states and
    /// the parameters, against central differences of the prediction itself. Read from the covariance it predicts
    /// without process noise: from `P` a unit variance of parameter `m` alone, `P-[i, 2 + m]` is `Sigma[i, m]`; from
    /// a unit variance of state `k` alone, `P-[i, j]` is `Psi[i, k] Psi[j, k]`.
    #[test]
    fn any_number_of_substeps_predicts_the_rk4_state_and_its_derivatives() {
        let converged = converged_hybrid(0.3).core;
        let u = 0.7;
        for substeps in [1, 2, 3, 4, 5, 6, 7, 8, 9, 16, 17, 31, 33, 64] {
            let mut before = converged;
            before.cfg = EkfDesign { substeps, ..EkfDesign::default() }.design();
            let (z, _) = predict_by_riccati_rk4(&before, u);
            let mut new = before;
            new.predict(u);
            assert_same_state(&new.z, &z, 1e-13, &format!("{substeps} substeps"));
            (before.cfg.q_period, before.cfg.q_xt, before.cfg.q_xx) = ([0.0; 5], [[0.0; 3]; 2], [[0.0; 3]; 3]);
            let derivative = |k: usize| {
                let eps = 1e-6 * before.z[k].abs().max(1.0);
                let (mut plus, mut minus) = (before, before);
                plus.z[k] += eps;
                minus.z[k] -= eps;
                plus.predict(u);
                minus.predict(u);
                [0, 1].map(|i| (plus.z[i] - minus.z[i]) / (2.0 * eps))
            };
            let unit = |k: usize| {
                let mut c = before;
                c.p = [0.0; 15];
                c.p[idx(k, k)] = 1.0;
                c.predict(u);
                c.p
            };
            for m in 0..3 {
                let (sigma, p) = (derivative(2 + m), unit(2 + m));
                for i in 0..2 {
                    let got = p[idx(i, 2 + m)];
                    assert!(
                        (got - sigma[i]).abs() <= 1e-6 * (sigma[0].abs() + sigma[1].abs()),
                        "{substeps} substeps: Sigma[{i}, {m}] {got} against {}",
                        sigma[i]
                    );
                }
            }
            for k in 0..2 {
                let (psi, p) = (derivative(k), unit(k));
                for (i, j) in [(0, 0), (0, 1), (1, 1)] {
                    let got = p[idx(i, j)];
                    assert!(
                        (got - psi[i] * psi[j]).abs() <= 1e-6 * (psi[0] * psi[0] + psi[1] * psi[1]),
                        "{substeps} substeps: Psi[{i}, {k}] Psi[{j}, {k}] {got} against {}",
                        psi[i] * psi[j]
                    );
                }
            }
        }
    }
}
