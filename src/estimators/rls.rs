//! Discrete recursive least squares (lecture notes, eqs. 11-17; textbook 13.5) for `y(k+1) = theta' phi(k)`, in one
//! implementation that covers every row of the lecture's table through the general gain
//!
//! ```text
//! F(k+1)^-1 = lambda1 F(k)^-1 + lambda2 phi phi'                       (lecture eq. 17)
//! theta(k+1) = theta(k) + lambda2 F(k+1) phi eps0(k+1)
//!            = theta(k) + F phi / (lambda1/lambda2 + phi' F phi) eps0(k+1)
//! eps0(k+1) = y(k+1) - theta(k)' phi          (a priori error)
//! eps(k+1)  = y(k+1) - theta(k+1)' phi = eps0 lambda1 / (lambda1 + lambda2 phi' F phi)   (a posteriori, eq. 13)
//! ```
//!
//! `(lambda1, lambda2) = (1, 0)`: constant gain (F and theta stay put); `(1, 1)`: least squares; `(lambda < 1, 1)`:
//! least squares with forgetting (eq. 16); `(gamma, a)`: the textbook's exponentially weighted form (13.5), whose
//! `P` is this `F`. Because `0 < lambda1 / (lambda1 + lambda2 phi'F phi) <= 1`, `|eps| <= |eps0|` always.
//!
//! ## Numerics: Bierman's UD factorisation
//! `F = U D U'` with `U` unit upper triangular and `D` diagonal is updated directly (Bierman 1977): the
//! measurement update with noise `r = lambda1 / lambda2`, then `D /= lambda1`. `F` is never formed, so it cannot
//! lose symmetry, and stays positive definite as long as `D > 0`, which the update preserves by construction: the
//! classic remedy for the covariance form's loss of definiteness in single precision over long runs. Cost per
//! update: `1.5 n^2 + 4.5 n` multiplies, `2 n + 1` divisions (n = 4: 42 and 9; two per factor, by `alpha` before
//! and after it, and the gain's). In floating point a division is one instruction (14 cycles on the M4F); in fixed
//! point it is most of the update (`Fx`'s, about 210 instructions on the Cortex-M4, BENCHMARKS.md).
//!
//! ## Windup
//! With forgetting and no excitation `F` grows as `lambda1^-k` (ten minutes at 10 kHz with `lambda1 = 0.9995`:
//! `10^1300`). The protection is a bound on the covariance: forgetting is skipped for any step after which
//! `trace F` would exceed `max_trace`, so `F` stays bounded whatever the input, and adaptation resumes at full gain
//! when excitation returns. Chosen over directional forgetting because it is one comparison per sample, it is
//! exact least squares with forgetting whenever the bound is not reached, and its behaviour is easy to state.
//!
//! ## Initialisation
//! From a prior `(theta0, F0)` (then the estimate minimises the lecture's prior-regularised cost), or from a batch
//! solve over the first `k0` samples ([`DiscreteRls::from_batch`]): `F(k0) = (D'WD)^-1 = R^-1 R^-T` comes straight
//! from the QR factor `R` of [`WeightedLs`], as `U_ij = r_jj (R^-1)_ij` and `D_j = 1 / r_jj^2`.

#![allow(clippy::needless_range_loop)] // triangular-matrix loops read best with the indices of the algebra

use crate::estimators::lsq::{LsError, WeightedLs};
use crate::{Real, Scalar};

/// The gain settings (configuration).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RlsGain<T> {
    /// Forgetting, `0 < lambda1 <= 1`.
    lambda1: T,
    /// Weight of the new sample, `0 <= lambda2 <= 2`.
    lambda2: T,
    /// Forgetting pauses while `trace F` would exceed this (windup bound).
    max_trace: T,
    /// `lambda1 / lambda2` (0 without new samples) and `1 / lambda1`: computed here once, not per sample.
    r: T,
    inv_lambda1: T,
}

impl<T: Real> RlsGain<T> {
    /// Whether every constant is a finite number (see [`crate::estimators::TuningConfig::fits`]).
    pub(crate) fn fits(&self) -> bool {
        crate::estimators::all_finite(&[&[self.lambda1, self.lambda2, self.max_trace, self.r, self.inv_lambda1]])
    }
}

impl<T: Scalar> RlsGain<T> {
    /// The general gain: forgetting `0 < lambda1 <= 1`, weight of the new sample `0 <= lambda2 <= 2`, forgetting
    /// paused while `trace F` would exceed `max_trace`.
    pub fn new(lambda1: T, lambda2: T, max_trace: T) -> Self {
        let r = if lambda2 > T::zero() { lambda1 / lambda2 } else { T::zero() };
        RlsGain { lambda1, lambda2, max_trace, r, inv_lambda1: T::one() / lambda1 }
    }
    /// Ordinary least squares.
    pub fn least_squares() -> Self {
        Self::new(T::one(), T::one(), T::greatest())
    }
    /// Least squares with forgetting factor `lambda`.
    pub fn forgetting(lambda: T, max_trace: T) -> Self {
        Self::new(lambda, T::one(), max_trace)
    }
    /// The textbook's weights `a gamma^(N-k)`: `lambda1 = gamma`, `lambda2 = a`.
    pub fn textbook(a: T, gamma: T) -> Self {
        Self::new(gamma, a, T::greatest())
    }
}

/// The errors of one update.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RlsErrors<T> {
    /// `y - theta(k)' phi`.
    pub a_priori: T,
    /// `y - theta(k+1)' phi`.
    pub a_posteriori: T,
}

/// RLS state: estimate and UD factors of `F`, for `N` parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DiscreteRls<T, const N: usize> {
    theta: [T; N],
    /// Unit upper triangular; only the strict upper part is stored meaningfully.
    u: [[T; N]; N],
    d: [T; N],
}

impl<T: Scalar, const N: usize> DiscreteRls<T, N> {
    /// Start from `theta0` and a diagonal `F0`.
    pub fn new(theta0: [T; N], f0_diag: [T; N]) -> Self {
        let mut u = [[T::zero(); N]; N];
        for (i, row) in u.iter_mut().enumerate() {
            row[i] = T::one();
        }
        DiscreteRls { theta: theta0, u, d: f0_diag }
    }

    /// Start from a batch least-squares solve (the first `k0` samples accumulated in `ls`).
    pub fn from_batch<const MAX: usize>(ls: &WeightedLs<T, MAX>) -> Result<Self, LsError>
    where
        T: Real,
    {
        assert_eq!(ls.parameters(), N, "batch fit and RLS must have the same number of parameters");
        let sol = ls.solve()?;
        let r = ls.r_factor();
        // Invert the upper-triangular R column by column: X = R^-1, upper triangular.
        let mut x = [[T::zero(); N]; N];
        for j in 0..N {
            x[j][j] = T::one() / r[j][j];
            for i in (0..j).rev() {
                let mut acc = T::zero();
                for k in i + 1..=j {
                    acc += r[i][k] * x[k][j];
                }
                x[i][j] = -acc / r[i][i];
            }
        }
        let mut s = Self::new([T::zero(); N], [T::zero(); N]);
        for j in 0..N {
            s.d[j] = x[j][j] * x[j][j];
            for i in 0..j {
                s.u[i][j] = x[i][j] / x[j][j];
            }
            s.theta[j] = sol.theta[j];
        }
        Ok(s)
    }

    /// The estimate.
    pub fn theta(&self) -> &[T; N] {
        &self.theta
    }

    /// Replace the estimate (keeping `F`).
    pub fn set_theta(&mut self, theta: [T; N]) {
        self.theta = theta;
    }

    /// `F = U D U'` (for reports and tests; the update never forms it).
    pub fn covariance(&self) -> [[T; N]; N] {
        let mut f = [[T::zero(); N]; N];
        for i in 0..N {
            for j in i..N {
                let mut acc = T::zero();
                for k in j..N {
                    acc += self.u[i][k] * self.d[k] * self.u[j][k];
                }
                f[i][j] = acc;
                f[j][i] = acc;
            }
        }
        f
    }

    /// `trace F`.
    pub fn trace(&self) -> T {
        let mut t = T::zero();
        for j in 0..N {
            let mut col = T::zero();
            for i in 0..j {
                col += self.u[i][j] * self.u[i][j];
            }
            t += self.d[j] * (T::one() + col);
        }
        t
    }

    /// The smallest diagonal entry of `D` (positive definiteness holds while it is positive).
    pub fn min_d(&self) -> T {
        self.d.iter().fold(T::greatest(), |m, &x| if x < m { x } else { m })
    }

    /// One sample: regressor `phi`, target `y`.
    #[inline]
    pub fn update(&mut self, gain: &RlsGain<T>, phi: &[T; N], y: T) -> RlsErrors<T> {
        let mut predicted = T::zero();
        for (t, p) in self.theta.iter().zip(phi) {
            predicted += *t * *p;
        }
        let a_priori = y - predicted;
        let mut a_posteriori = a_priori;
        if gain.lambda2 > T::zero() {
            // Bierman: f = U' phi, v = D f.
            let mut f = [T::zero(); N];
            for j in 0..N {
                let mut acc = phi[j];
                for i in 0..j {
                    acc += self.u[i][j] * phi[i];
                }
                f[j] = acc;
            }
            let mut b = [T::zero(); N];
            let mut alpha = gain.r;
            let r = alpha;
            for j in 0..N {
                let v = self.d[j] * f[j];
                let alpha_prev = alpha;
                alpha += f[j] * v;
                self.d[j] = self.d[j] * alpha_prev / alpha;
                let p = -f[j] / alpha_prev;
                for i in 0..j {
                    let uij = self.u[i][j];
                    self.u[i][j] = uij + b[i] * p;
                    b[i] += uij * v;
                }
                b[j] = v;
            }
            // alpha = r + phi' F phi: K = b / alpha.
            let k = a_priori / alpha;
            for (t, bi) in self.theta.iter_mut().zip(b.iter()) {
                *t += *bi * k;
            }
            // `eps0 r / alpha`, from the gain's quotient: one division fewer (ten to nine in fixed point).
            a_posteriori = k * r;
        }
        if gain.lambda1 < T::one() && self.trace() <= gain.max_trace * gain.lambda1 {
            for d in self.d.iter_mut() {
                *d *= gain.inv_lambda1;
            }
        }
        RlsErrors { a_priori, a_posteriori }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `trace F` from the factors is the trace of `F = U D U'` formed, with `U` full; and it is what bounds the
    /// windup: with forgetting and no excitation `F` grows by `1 / lambda1` a sample until one more step would take
    /// its trace past the bound, and then stays.
    #[test]
    fn the_trace_is_that_of_f_and_bounds_the_windup() {
        let (lambda, bound) = (0.99, 50.0);
        let gain = RlsGain::forgetting(lambda, bound);
        let mut rls = DiscreteRls::<f64, 3>::new([0.0; 3], [1.0, 2.0, 3.0]);
        let mut next = crate::xorshift64(0x7AC3_5EED);
        for _ in 0..20 {
            let phi = [0, 1, 2].map(|_| next() as f64 / u64::MAX as f64 - 0.5);
            rls.update(&gain, &phi, 0.3);
        }
        let formed_trace = |rls: &DiscreteRls<f64, 3>| (0..3).map(|i| rls.covariance()[i][i]).sum::<f64>();
        let f = rls.covariance();
        assert!(f.iter().flatten().all(|x| *x != 0.0), "{f:?}");
        let formed = formed_trace(&rls);
        assert!((rls.trace() / formed - 1.0).abs() < 1e-12, "{} against {formed}", rls.trace());
        assert!(formed < lambda * bound);
        for _ in 0..2_000 {
            rls.update(&gain, &[0.0; 3], 0.0);
        }
        let formed = formed_trace(&rls);
        assert!(formed > lambda * bound && formed <= bound * (1.0 + 1e-12), "{formed}");
    }
}
