//! # nanopos-fw: the NUCLEO-G474RE firmware
//!
//! Drives the stage's amplifier and reads its probe at 10 kHz, running one sample of the `nanopos-id` pipeline in
//! the highest-priority interrupt (`ADC1_2`), and logs over defmt/RTT at 10 Hz. Board specifics (pins, clocks,
//! triggers) are in `board.rs`; the algorithms are in the library.
//!
//! Flash and watch: `cargo fw-run` (alias for `cargo run --release --target thumbv7em-none-eabihf --bin nanopos-fw`).
//!
//! Deadline: the interrupt starts when the ADC's oversampled conversion ends (`t_k` + 14.3 us) and must write the
//! next DAC code before the next sample instant loads it (`t_(k+1)`): 85.7 us, 14 568 cycles at 170 MHz. It writes
//! the code first, then runs the filters and the estimators, which have until the next conversion ends (17 000
//! cycles after its own). Every sample's cycles from its conversion's end to the interrupt's end (DWT, and TIM2's
//! count for the start) feed the mean and maximum in the log; a missed deadline or an ADC overrun is counted and
//! logged as a warning, never silent.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(target_os = "none")]
mod board;
#[cfg(target_os = "none")]
mod firmware;
#[cfg(target_os = "none")]
mod ram_code;

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "nanopos-fw runs on the NUCLEO-G474RE. Build it with `cargo fw`, flash it with `cargo fw-run`; \
         on the host, run the simulated stage with `cargo sim simulate --scenario prbs --out run.csv`."
    );
    std::process::exit(2);
}
