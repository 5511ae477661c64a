//! The estimators, one file each, and what they share.
//!
//! - [`arx`]: the stage as a 2nd-order ARX at the sample rate, by the discrete RLS, converted through the exact ZOH.
//! - [`hekf`]: the paper's hybrid extended Kalman filter (Section IV-B).
//! - [`lsq`]: batch and exponentially weighted least squares (textbook 13.2-13.4) by a streaming QR factorisation.
//! - [`rls`]: discrete recursive least squares, every form of the lecture notes, in Bierman UD form.

pub mod arx;
pub mod hekf;
pub mod lsq;
pub mod rls;
