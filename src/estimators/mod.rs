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
