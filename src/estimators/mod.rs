//! The estimators, one file each, and what they share.
//!
//! - [`arx`]: the stage as a 2nd-order ARX at the sample rate, by the discrete RLS, converted through the exact ZOH.
//! - [`crls`]: the paper's continuous-time RLS with forgetting (Section III).
//! - [`ekf`]: the paper's continuous and hybrid extended Kalman filters (Sections IV-A, IV-B).
//! - [`lsq`]: batch and exponentially weighted least squares (textbook 13.2-13.4) by a streaming QR factorisation.
//! - [`rls`]: discrete recursive least squares, every form of the lecture notes, in Bierman UD form.

pub mod arx;
pub mod crls;
pub mod ekf;
pub mod lsq;
pub mod rls;

use crate::Real;

/// The paper's three estimators: continuous-time RLS, continuous EKF, hybrid EKF.
pub type PaperBank<T> = (crls::Crls<T>, ekf::Cekf<T>, ekf::Hekf<T>);

/// The paper's three estimators at their defaults (the PRBS tuning: the paper's RLS settings and `Q2`).
pub fn paper_bank<T: Real>() -> PaperBank<T> {
    let ekf = ekf::EkfDesign::default();
    (crls::Crls::new(crls::CrlsDesign::default().design()), ekf::Cekf::new(ekf.design()), ekf::Hekf::new(ekf.design()))
}

/// `a + h b`, the RK4 stage argument.
#[inline(always)]
pub(crate) fn axpy<T: Real, const N: usize>(a: &[T; N], b: &[T; N], h: T) -> [T; N] {
    core::array::from_fn(|i| a[i] + h * b[i])
}

/// `x += h / 6 (k1 + 2 k2 + 2 k3 + k4)`, the RK4 step.
#[inline(always)]
pub(crate) fn rk4_combine<T: Real, const N: usize>(x: &mut [T; N], k: [&[T; N]; 4], h: T) {
    let (h6, two) = (h / T::of(6.0), T::of(2.0));
    for i in 0..N {
        x[i] += h6 * (k[0][i] + two * (k[1][i] + k[2][i]) + k[3][i]);
    }
}
