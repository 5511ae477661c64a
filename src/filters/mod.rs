//! Filters, each split into a coefficient value (designed once, in f64, then rounded to the working scalar) and a
//! state value (updated once per sample), so one design drives many states and a new design can be swapped in
//! between samples.
//!
//! - [`biquad`]: Direct Form 1 second-order section, the workhorse of the filter replicas.
//! - [`design`]: bilinear-transform designs with pre-warping: 2nd-order Butterworth low-pass (the replicas of the
//!   reconstruction and anti-aliasing filters, paper Fig. 5) and a 1st-order high-pass.
//! - [`prefilter`]: the identification pre-filter `W_p` (paper Section II-B) as a state-space filter that yields the
//!   filtered signal and its first and second derivatives.
//! - [`response`]: frequency responses, for design checks and tests.
//! - [`spike`]: the gate that replaces a probe reading out of line with the readings before it.

pub mod biquad;
pub mod design;
pub mod prefilter;
pub mod response;
pub mod spike;

pub use biquad::{Biquad, BiquadState};
pub use prefilter::{Prefilter, PrefilterDesign, PrefilterState, Prefiltered};
