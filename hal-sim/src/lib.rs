//! # hal-sim: the simulated stage
//!
//! The paper's signal chain ([`plant`]) behind the same `StageBoard` trait as the NUCLEO-G474RE ([`board`]),
//! driven by the real `nanopos-id` pipeline ([`sim`]), deterministic for a seed ([`noise`]); the firmware's interrupt
//! body, command side and console loop on it ([`lab`]). The `nanopos-sim` binary's commands live in [`cmd`].
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod bank;
pub mod board;
pub mod cmd;
pub mod csv;
pub mod experiment;
pub mod lab;
pub mod noise;
pub mod plant;
pub mod plot;
pub mod sim;
pub mod tuning;
