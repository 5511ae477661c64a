//! The spike gate: a probe reading that jumps out of line with the readings before it is replaced before any
//! filter or estimator sees it.
//!
//! ## Why
//! The reading reaches the ADC through the anti-aliasing filter (2nd-order, 1 kHz), after a stage whose first
//! resonance is a few hundred Hz: at 10 kHz it is smooth from one sample to the next, and a reading far off the
//! curve through the samples before it is not the stage's motion but the converter's or the wiring's (a
//! disturbance coupled into the ADC's input, a bit error) or a logger's (an overflow value). One such sample goes
//! through the band-pass pre-filter as an impulse, which rings at the pre-filter's centre, where the estimators
//! look for the resonance, for tens of milliseconds: the estimators took it for the stage. On the simulated board's
//! PRBS, one reading of 50 um (inside the probe's +-50 um, so not an over-range) moved the EKFs' and the ARX's `a1`
//! by 14-19 % and `b0` by up to 11 % on average over the half second after it, and the ARX's `a1` was still 7 % off
//! over the half second after that; one of 10 um moved `b0` by 0.8 % (`nanopos-sim identify` on a 20 s record, the
//! reading at 3 s replaced by hand). On the board (`tests/instrument.rs`), one of 26 um moved the EKFs' parameters by
//! up to 63-83 % within half a second (as it fell in the PRBS); with the gate, by under 3e-5.
//!
//! ## How
//! Each reading `y_k` is compared with the parabola through the three readings passed on before it,
//! `p_k = y_(k-3) + 3 (y_(k-1) - y_(k-2))`: the residual `r_k = y_k - p_k` is the third difference of the readings,
//! a few nm on the simulated board (the noise, 1.25 nm RMS, makes it `sqrt(20)` times that; the motion's third
//! derivative adds `(w T)^3` of its amplitude). A reading whose `|r_k|` is above both `ratio` times the mean of the
//! past `|r|` (an exponential average over 64 samples) and a floor (a few ADC codes, for a reading that does not
//! move) is replaced by `p_k` and counted. The readings replaced are not averaged in, so a spike does not raise the
//! bound for the next one. A reading taken with a residual beyond a quarter of that bound ([`SUSPECT`]) is passed
//! on as read, but the curve goes on from it clipped to that quarter: its residual `e` would come back as `-3e`,
//! `3e`, `-e` in the next three predictions, and good readings after it were replaced by predictions that far off.
//!
//! - The bound: on the simulated board's runs (the PRBS with the payload's bump and the smoothed triangle, 200 s
//!   each; the multisine; an 8 V PRBS from rest without a slew limit; hysteresis and creep) the gate's first
//!   replacements come at a ratio of 7 (2 in 60 s of the multisine; 18 of the triangle's 200 s at 6), the noise's
//!   Gaussian tail: the default `ratio` of 32 is more than four times that (25 noise sigmas: never, for noise), and
//!   a spike of 1 um, 200 times the noise, is far above it (`hal-sim/tests/spike.rs`). Noise with heavier tails,
//!   Student's t of the same RMS: none either with 3 degrees of freedom on the simulated board; with a 10 nm probe
//!   noise that dominates the reading, 1 in 60 s with 3 degrees, none with 4 or more (15 and 2 before the curve
//!   was clipped, [`SUSPECT`]).
//! - A reading that really moved (a step of the probe's offset, a stage knocked hard) is not lost: at most
//!   [`MAX_RUN`] readings in a row are replaced; the next is taken, and the curve the gate extrapolates restarts
//!   from it and the readings replaced before it, as they were read, so it follows the new level from there.
//! - At the start the mean residual is a millimetre ([`START_UM`]), beyond any nanopositioning stage's reading:
//!   the gate passes everything until the average has learnt the reading's own (about 80 ms at 10 kHz, the average
//!   falling by `1 - 1/64` a sample to a few nm).
//! - A `ratio` of 0 in the settings (infinite here) turns it off. The ratio is a tuning value (`spike_ratio`,
//!   [`crate::estimators::TuningKey::SpikeRatio`]): the console's `tune spike_ratio N` sets it at run time; off, the
//!   gate still learns its average (spikes included, which raise it for some tens of samples), so that turned on
//!   again it judges at once, without the start's 80 ms.
//!
//! Cost per sample: about 10 flops (the prediction, the residual, the average, the clip's margin), four compares and
//! two branches; the replacement and the clip are out of line.

use crate::Real;

/// Readings in a row the gate replaces at most; the next is taken whatever it is.
pub const MAX_RUN: u8 = 2;
const _: () = assert!(MAX_RUN == 2, "the curve restarts from two replaced readings");

/// The weight of a new `|r|` in the average: a memory of 64 samples.
const AVERAGE_WEIGHT: f64 = 1.0 / 64.0;

/// The mean residual the gate starts from, um: a millimetre, beyond any nanopositioning stage's reading.
pub const START_UM: f64 = 1e3;

/// The share of the bound beyond which a reading taken does not extend the curve as it is ([`SpikeGate::pass`]):
/// its residual `e` comes back as `-3e`, `3e` and `-e` in the next three, so under a third of the bound it cannot
/// push a good reading over it alone; a quarter leaves the noise room.
pub const SUSPECT: f64 = 0.25;

/// The firmware's ratio ([`crate::pipeline::FaultSettings::spike_ratio`]'s default). A smaller one, a more eager
/// gate, does not clip the curve closer than a quarter of the bound at this one ([`SpikeBound::clip_ratio`]): the
/// stage's own motion reaches several mean residuals (the first replacements on the simulated board's runs come at
/// a ratio of 7), and a curve clipped there lagged it (at a ratio of 10, 52 readings of the PRBS replaced, none
/// without the clip).
pub const DEFAULT_RATIO: u16 = 32;

/// The gate's bounds in the working scalar (part of the pipeline's configuration).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpikeBound<T> {
    /// A reading is out of line when its residual exceeds this many times the mean residual (infinite: never).
    pub ratio: T,
    /// ... and this floor, um.
    pub floor_um: T,
    /// A reading taken goes into the curve clipped to this many times the mean residual around the prediction
    /// (and `clip_floor_um`): [`SUSPECT`] times the larger of `ratio` and [`DEFAULT_RATIO`] (infinite: never).
    pub clip_ratio: T,
    /// ... and [`SUSPECT`] times the floor, um.
    pub clip_floor_um: T,
}

impl<T: Real> SpikeBound<T> {
    /// The bounds for `ratio` (0: the gate off) and `floor_um`.
    pub fn new(ratio: u16, floor_um: f64) -> Self {
        let ratio = match ratio {
            0 => f64::INFINITY,
            r => f64::from(r),
        };
        SpikeBound {
            ratio: T::of(ratio),
            floor_um: T::of(floor_um),
            clip_ratio: T::of(SUSPECT * ratio.max(f64::from(DEFAULT_RATIO))),
            clip_floor_um: T::of(SUSPECT * floor_um),
        }
    }
}

/// The gate's state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpikeGate<T> {
    /// The last three readings passed on, the latest first.
    last: [T; 3],
    /// The mean `|r|` of the readings taken, um.
    mean: T,
    /// Readings replaced in a row just before this one.
    run: u8,
    /// Those readings as read, in order: where the curve restarts from when the next is taken.
    replaced: [T; MAX_RUN as usize],
}

impl<T: Real> Default for SpikeGate<T> {
    fn default() -> Self {
        Self::new()
    }
}

impl<T: Real> SpikeGate<T> {
    /// At the start, with nothing learnt: it passes everything until its average has come down from
    /// [`START_UM`].
    pub fn new() -> Self {
        SpikeGate { last: [T::zero(); 3], mean: T::of(START_UM), run: 0, replaced: [T::zero(); MAX_RUN as usize] }
    }

    /// The reading `y` (um) to pass on: `y` itself, or the prediction in its place (then `replaced` is counted).
    #[inline(always)]
    pub fn pass(&mut self, bound: &SpikeBound<T>, y: T, replaced: &mut u32) -> T {
        let [y1, y2, y3] = self.last;
        let predicted = y3 + T::of(3.0) * (y1 - y2);
        let size = (y - predicted).abs();
        let limit = bound.ratio * self.mean;
        // Written so that a NaN bound (an infinite ratio times a mean that decayed to 0) takes the reading.
        if size > bound.floor_um && size > limit {
            return self.out_of_line(y, predicted, replaced);
        }
        self.mean = self.mean + T::of(AVERAGE_WEIGHT) * (size - self.mean);
        self.run = 0;
        let margin = [bound.clip_floor_um, bound.clip_ratio * self.mean];
        if size > margin[0] && size > margin[1] {
            return self.suspect(y, predicted, margin);
        }
        self.last = [y, y1, y2];
        y
    }

    /// A reading taken, but too far off the curve to extend it as it is: the next three predictions would carry its
    /// residual `e` as `-3e`, `3e` and `-e`, and the good readings after it could look out of line and be replaced
    /// by them. Passed on as read, not counted; the curve goes on from it clipped to the `margin` around the
    /// prediction (the larger of the two: [`SpikeBound::clip_floor_um`], and [`SpikeBound::clip_ratio`] times the
    /// mean residual), so that it cannot push the next reading over the bound alone, and a reading that moved is still
    /// followed, a margin a sample.
    #[cold]
    #[inline(never)]
    fn suspect(&mut self, y: T, predicted: T, margin: [T; 2]) -> T {
        let [y1, y2, _] = self.last;
        let m = if margin[1] > margin[0] { margin[1] } else { margin[0] };
        let clipped = if y > predicted { predicted + m } else { predicted - m };
        self.last = [clipped, y1, y2];
        y
    }

    /// A reading out of line: replaced by `predicted`, unless [`MAX_RUN`] were replaced just before it.
    #[cold]
    #[inline(never)]
    fn out_of_line(&mut self, y: T, predicted: T, replaced: &mut u32) -> T {
        if let Some(held) = self.replaced.get_mut(usize::from(self.run)) {
            let [y1, y2, _] = self.last;
            *held = y;
            self.run += 1;
            *replaced = replaced.saturating_add(1);
            self.last = [predicted, y1, y2];
            return predicted;
        }
        // Taken: the reading moved for good. The curve restarts from the readings as read, the replaced ones
        // included; from the extrapolated ones it would miss the next readings by several times their third
        // difference, and a gate set tight enough to take that for a spike again replaced half the readings of a run.
        let [r1, r2] = self.replaced;
        self.run = 0;
        self.last = [y, r2, r1];
        y
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BOUND: SpikeBound<f64> = SpikeBound { ratio: 32.0, floor_um: 0.025, clip_ratio: 8.0, clip_floor_um: 0.00625 };

    /// A 400 Hz sine of 1 um with 1.25 nm of deterministic "noise", sample `k`.
    fn reading(k: usize) -> f64 {
        let t = k as f64 * 1e-4;
        (2.0 * core::f64::consts::PI * 400.0 * t).sin() + 1.25e-3 * ((k * 7919 % 1000) as f64 / 500.0 - 1.0) * 1.7
    }

    /// The gate after `n` samples of [`reading`], and the count it replaced.
    fn settled(n: usize) -> (SpikeGate<f64>, u32) {
        let mut gate = SpikeGate::new();
        let mut replaced = 0;
        for k in 0..n {
            assert_eq!(gate.pass(&BOUND, reading(k), &mut replaced), reading(k));
        }
        (gate, replaced)
    }

    /// The bound is a threshold to exceed: a residual exactly at the floor, or exactly at the ratio times the mean
    /// residual, is taken; one a step beyond either is replaced.
    #[test]
    fn a_residual_at_the_bound_is_taken_and_one_beyond_it_replaced() {
        // A gate that has learnt a still reading: its mean residual far below the floor over the ratio.
        let quiet = |bound: &SpikeBound<f64>| {
            let (mut gate, mut replaced) = (SpikeGate::new(), 0);
            for _ in 0..5_000 {
                assert_eq!(gate.pass(bound, 0.0, &mut replaced), 0.0);
            }
            assert!(replaced == 0 && gate.mean > 0.0 && bound.ratio * gate.mean < 1e-20, "{}", gate.mean);
            gate
        };
        // The curve predicts 0: the residual is the reading. At the floor (the ratio's bound far below it), then with
        // no floor at the ratio times the mean residual.
        let no_floor = SpikeBound { floor_um: 0.0, ..BOUND };
        let at_floor: fn(&SpikeGate<f64>) -> f64 = |_| BOUND.floor_um;
        let at_ratio: fn(&SpikeGate<f64>) -> f64 = |g| BOUND.ratio * g.mean;
        for (bound, at) in [(BOUND, at_floor), (no_floor, at_ratio)] {
            let mut replaced = 0;
            let mut gate = quiet(&bound);
            let y = at(&gate);
            assert_eq!(gate.pass(&bound, y, &mut replaced), y, "at the bound, {y}");
            assert_eq!(replaced, 0);
            let mut gate = quiet(&bound);
            let y = at(&gate).next_up();
            assert_eq!(gate.pass(&bound, y, &mut replaced), 0.0, "beyond the bound, {y}");
            assert_eq!(replaced, 1);
        }
    }

    #[test]
    fn a_smooth_reading_passes_unchanged_from_the_start() {
        let (gate, replaced) = settled(20_000);
        assert_eq!(replaced, 0);
        // The average has learnt the reading's own residual: a few nm.
        assert!(gate.mean > 1e-3 && gate.mean < 0.05, "{}", gate.mean);
    }

    /// How far the `i`-th reading replaced in a row (from 0) may be from the true one: the curve's error is the
    /// reading's third difference (about 16 nm here, and the noise's), and the next extrapolation from a replaced
    /// reading carries it three times more.
    fn replaced_within(i: usize) -> f64 {
        [0.03, 0.1][i]
    }

    #[test]
    fn a_spike_and_a_burst_of_two_are_replaced_by_the_curve() {
        for burst in [1, 2] {
            let (mut gate, mut replaced) = settled(5_000);
            for k in 5_000..5_100 {
                let spike = k >= 5_050 && k < 5_050 + burst;
                let y = reading(k) + if spike { 1.0 } else { 0.0 };
                let out = gate.pass(&BOUND, y, &mut replaced);
                let within = if spike { replaced_within(k - 5_050) } else { 0.0 };
                assert!((out - reading(k)).abs() <= within, "burst {burst}, k {k}: {out} against {}", reading(k));
            }
            assert_eq!(replaced, burst as u32);
        }
    }

    /// A reading off the curve by half the bound is taken, but the curve goes on from it clipped to a quarter: as it
    /// was, its residual came back three times over in the next predictions, and the next reading, a good one, was
    /// replaced by a prediction half the bound and more off (the noise's far tail did that on the board's
    /// heavy-tailed noise, `hal-sim/tests/spike.rs`). Above and below the curve, where it crosses zero and near its
    /// peaks (the clip is about the prediction, not about zero).
    #[test]
    fn a_reading_taken_far_off_the_curve_does_not_get_good_ones_replaced() {
        // The 400 Hz sine crosses zero at sample 5 050 and peaks 6 samples later or earlier.
        for (at, sign) in [(5_050, 1.0), (5_050, -1.0), (5_056, 1.0), (5_056, -1.0), (5_044, 1.0), (5_044, -1.0)] {
            let (mut gate, mut replaced) = settled(5_000);
            let off = sign * 0.5 * BOUND.ratio * gate.mean;
            assert!(off.abs() > BOUND.floor_um, "{off}");
            for k in 5_000..5_100 {
                let y = reading(k) + if k == at { off } else { 0.0 };
                assert_eq!(gate.pass(&BOUND, y, &mut replaced), y, "off {off} at {at}, k {k}");
            }
            assert_eq!(replaced, 0, "off {off} at {at}");
        }
    }

    #[test]
    fn a_reading_that_moved_for_good_is_taken_after_the_longest_run() {
        let (mut gate, mut replaced) = settled(5_000);
        let outs: Vec<f64> = (5_000..5_010).map(|k| gate.pass(&BOUND, reading(k) + 5.0, &mut replaced)).collect();
        assert_eq!(replaced, u32::from(MAX_RUN));
        for (i, out) in outs.iter().enumerate() {
            let k = 5_000 + i;
            if i < usize::from(MAX_RUN) {
                assert!((out - reading(k)).abs() < replaced_within(i), "{i}: {out}");
            } else {
                assert_eq!(*out, reading(k) + 5.0, "{i}: taken, and the next ones too");
            }
        }
    }

    #[test]
    fn a_reading_that_does_not_move_passes_small_steps_under_the_floor() {
        let mut gate = SpikeGate::new();
        let mut replaced = 0;
        for _ in 0..20_000 {
            gate.pass(&BOUND, 3.0, &mut replaced);
        }
        assert!(gate.mean < 1e-30, "{}", gate.mean);
        assert_eq!(gate.pass(&BOUND, 3.02, &mut replaced), 3.02, "a step under the floor");
        assert_eq!(replaced, 0);
        let mut other = SpikeGate::new();
        for _ in 0..20_000 {
            other.pass(&BOUND, 3.0, &mut replaced);
        }
        assert_eq!(other.pass(&BOUND, 3.5, &mut replaced), 3.0, "a step over the floor");
        assert_eq!(replaced, 1);
    }

    #[test]
    fn an_infinite_ratio_passes_everything() {
        let off = SpikeBound::new(0, BOUND.floor_um);
        assert_eq!((off.ratio, off.clip_ratio), (f64::INFINITY, f64::INFINITY));
        assert_eq!(SpikeBound::<f64>::new(32, 0.025), BOUND);
        assert_eq!(SpikeBound::<f64>::new(10, 0.025).clip_ratio, 8.0, "not closer than at the default");
        assert_eq!(SpikeBound::<f64>::new(64, 0.025).clip_ratio, 16.0);
        let mut gate = SpikeGate::new();
        let mut replaced = 0;
        for k in 0..40_000 {
            let y = if k % 1_000 == 999 { 1e4 } else { 0.0 };
            assert_eq!(gate.pass(&off, y, &mut replaced), y);
        }
        assert_eq!(replaced, 0);
    }
}
