//! The hybrid EKF written the way a general EKF library writes it, as the peer the structured [`super::Hekf`] is
//! measured against (feature `dense-ekf`, nalgebra fixed-size matrices).
//!
//! Same model, same normalised coordinates, same tuning and the same RK4 in `substeps` steps, but with full 5 x 5
//! matrices: the Jacobian `F` is formed as a matrix, the covariance derivative is `F P + P F' + Q` by two full
//! matrix products, and the update is the full Joseph form `(I - K H) P (I - K H)' + K R_d K'` with `H` a row vector.
//! It has none of the structured filter's health logic (gating, change detection, PE monitor, covariance bounds):
//! that logic only adds to the structured filter's count, so the measured ratio understates the gain from structure.
//!
//! Cost per update: each of the 16 RK4 stages two 5 x 5 products (250 multiply-adds) plus the sums; the update two
//! more 5 x 5 products. About 10 000 flops, against about 1 500 for the structured filter.

use nalgebra::{Matrix5, RowVector5, Vector5};

use super::EkfConfig;
use crate::{Real, StageParams};

/// The dense hybrid EKF (no health logic).
#[derive(Clone, Copy, Debug)]
pub struct DenseHekf<T: Real> {
    cfg: EkfConfig<T>,
    z: Vector5<T>,
    p: Matrix5<T>,
    q: Matrix5<T>,
    u_prev: T,
}

impl<T: Real> DenseHekf<T> {
    /// At the initial parameters, zero states, `P0`.
    pub fn new(cfg: EkfConfig<T>) -> Self {
        DenseHekf {
            z: Vector5::new(T::zero(), T::zero(), T::one(), T::one(), T::one()),
            p: Matrix5::from_diagonal(&Vector5::from(cfg.p0)),
            q: Matrix5::from_diagonal(&Vector5::from(cfg.q)),
            u_prev: T::zero(),
            cfg,
        }
    }

    /// `f(z, u)`.
    fn f(&self, z: &Vector5<T>, u: T) -> Vector5<T> {
        let c = &self.cfg;
        Vector5::new(
            c.w * z[1],
            -c.c0 * z[2] * z[0] - c.c1 * z[3] * z[1] + c.c2 * z[4] * u,
            T::zero(),
            T::zero(),
            T::zero(),
        )
    }

    /// The Jacobian of `f` at `(z, u)`.
    fn jacobian(&self, z: &Vector5<T>, u: T) -> Matrix5<T> {
        let c = &self.cfg;
        let mut f = Matrix5::zeros();
        f[(0, 1)] = c.w;
        f[(1, 0)] = -c.c0 * z[2];
        f[(1, 1)] = -c.c1 * z[3];
        f[(1, 2)] = -c.c0 * z[0];
        f[(1, 3)] = -c.c1 * z[1];
        f[(1, 4)] = c.c2 * u;
        f
    }

    fn derivative(&self, z: &Vector5<T>, p: &Matrix5<T>, u: T) -> (Vector5<T>, Matrix5<T>) {
        let f = self.jacobian(z, u);
        (self.f(z, u), f * p + p * f.transpose() + self.q)
    }

    /// One sample: prediction over `T` with the previous filtered input held, then the Joseph-form update with `y`.
    pub fn update(&mut self, u: T, y: T) {
        let (h, half, two) = (self.cfg.h, T::of(0.5), T::of(2.0));
        let h6 = h / T::of(6.0);
        let u_held = self.u_prev;
        for _ in 0..self.cfg.substeps {
            let (z, p) = (self.z, self.p);
            let (k1z, k1p) = self.derivative(&z, &p, u_held);
            let (k2z, k2p) = self.derivative(&(z + k1z * (h * half)), &(p + k1p * (h * half)), u_held);
            let (k3z, k3p) = self.derivative(&(z + k2z * (h * half)), &(p + k2p * (h * half)), u_held);
            let (k4z, k4p) = self.derivative(&(z + k3z * h), &(p + k3p * h), u_held);
            self.z = z + (k1z + (k2z + k3z) * two + k4z) * h6;
            self.p = p + (k1p + (k2p + k3p) * two + k4p) * h6;
        }
        let hrow = RowVector5::new(T::one(), T::zero(), T::zero(), T::zero(), T::zero());
        let s = (hrow * self.p * hrow.transpose())[(0, 0)] + self.cfg.r_d;
        let k = self.p * hrow.transpose() * (T::one() / s);
        let innovation = y - (hrow * self.z)[(0, 0)];
        self.z += k * innovation;
        let i_kh = Matrix5::identity() - k * hrow;
        self.p = i_kh * self.p * i_kh.transpose() + k * k.transpose() * self.cfg.r_d;
        self.u_prev = u;
    }

    /// The parameter estimates.
    pub fn params(&self) -> StageParams<T> {
        let i = &self.cfg.initial;
        StageParams { a0: self.z[2] * T::of(i.a0), a1: self.z[3] * T::of(i.a1), b0: self.z[4] * T::of(i.b0) }
    }
}
