//! Excitation signals, in volts at the amplifier input (before the output limits).
//!
//! - **PRBS**: a maximum-length sequence from the 15-bit Fibonacci LFSR `x^15 + x^14 + 1` (period 32 767 bits),
//!   each bit held `hold` samples, `+-amplitude`. With the default `hold = 5` at 10 kHz the bit rate is 2 kHz: a
//!   `sinc^2` spectrum whose main lobe ends at 2 kHz and is 3.9 dB down at 1 kHz; the board's 1 kHz reconstruction
//!   filter then confines the drive to 0-1 kHz, as in the paper. The register starts at `0x7FFF` and each clock emits
//!   `b = s14 ^ s13`, exactly the convention of the float64 reference, so its data can be regenerated bit for bit.
//! - **Smoothed triangle**: the unit triangle's Fourier series cut at `max_hz` (paper: 10 Hz fundamental, 1 kHz):
//!   `u(t) = A 8/pi^2 sum_{n odd} (-1)^((n-1)/2) sin(n w t) / n^2`. Evaluated per sample with one `sin`, one `cos`
//!   and the recurrence `sin((n+2) x) = 2 cos(2x) sin(n x) - sin((n-2) x)`: about 3 flops per harmonic, no table.
//!   At most [`MAX_HARMONICS`] odd harmonics (a fundamental below 7.9 Hz is cut there, not at `max_hz`).
//! - **Multisine**: [`MAX_TONES`] sines equally spaced from `f_lo` to `f_hi`, each of amplitude `A / sqrt(N)` (so that
//!   the sum has the power of a sine of amplitude `A`), with Schroeder's phases `phi_j = -pi j (j + 1) / N`:
//!   `u(t) = A / sqrt(N) sum_j sin(psi + j theta + phi_j)`, `psi = 2 pi f_lo t`, `theta = 2 pi df t`, the tone at
//!   `f_lo` times an envelope that depends on `theta` only, whose maximum with these phases is 1.3545: the peak is
//!   at most 1.36 `A` whatever the band (equal phases would reach `sqrt(N) A` = 5.7 `A`). Evaluated per
//!   sample with two `sin_cos` and a rotation by `theta` from tone to tone: about 10 flops per tone. Its power sits
//!   where the user puts it (around the resonance), and every tone counts for the excitation monitor's richness.
//! - **Sine**, **constant**, **off**.
//!
//! Phase is a 64-bit accumulator (`2^64` = one cycle), so periodic signals never drift and need no `fmod`; its sine
//! and cosine come from [`Real::phase_sin_cos`], which in f32 reduces the phase in integers and stays in f32 (libm's
//! `sinf` works in f64, in software on the M4F: the triangle took 2 778 instructions a sample with it, 70 times the
//! PRBS; QEMU's `excitation_*` kernels in BENCHMARKS.md). Everything adds `offset_v` (a static command the
//! excitation rides on).

use crate::Real;

/// Most odd harmonics the smoothed triangle sums.
pub const MAX_HARMONICS: usize = 64;
/// Tones of a multisine (two weights each, in the triangle's table).
pub const MAX_TONES: usize = MAX_HARMONICS / 2;

/// PRBS register length (bits) and its period in bits.
pub const PRBS_BITS: u32 = 15;
/// `2^15 - 1`.
pub const PRBS_PERIOD_BITS: u32 = (1 << PRBS_BITS) - 1;

/// Which signal, in physical terms.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Waveform {
    /// No excitation: the output sits at the offset.
    Off,
    /// PRBS, each bit held `hold` samples.
    Prbs {
        /// Samples per bit (>= 1).
        hold: u32,
    },
    /// Smoothed triangle: fundamental `freq_hz`, harmonics up to `max_hz`.
    Triangle {
        /// Fundamental, Hz.
        freq_hz: f64,
        /// Highest harmonic kept, Hz.
        max_hz: f64,
    },
    /// A sine at `freq_hz`.
    Sine {
        /// Frequency, Hz.
        freq_hz: f64,
    },
    /// [`MAX_TONES`] sines from `f_lo_hz` to `f_hi_hz`, equally spaced, Schroeder-phased.
    Multisine {
        /// Lowest tone, Hz.
        f_lo_hz: f64,
        /// Highest tone, Hz (above `f_lo_hz`; equal, every tone is at `f_lo_hz`).
        f_hi_hz: f64,
    },
}

/// What to generate: waveform, amplitude and offset.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExcitationDesign {
    /// The waveform.
    pub waveform: Waveform,
    /// Peak amplitude, V.
    pub amplitude_v: f64,
    /// Constant added to the waveform, V.
    pub offset_v: f64,
}

impl ExcitationDesign {
    /// The paper's PRBS: 1 V, bits held 5 samples at 10 kHz.
    pub const PAPER_PRBS: Self =
        ExcitationDesign { waveform: Waveform::Prbs { hold: 5 }, amplitude_v: 1.0, offset_v: 0.0 };
    /// The paper's smoothed triangle: 10 Hz, 1 V, harmonics to 1 kHz.
    pub const PAPER_TRIANGLE: Self = ExcitationDesign {
        waveform: Waveform::Triangle { freq_hz: 10.0, max_hz: 1000.0 },
        amplitude_v: 1.0,
        offset_v: 0.0,
    };
    /// Nothing.
    pub const OFF: Self = ExcitationDesign { waveform: Waveform::Off, amplitude_v: 0.0, offset_v: 0.0 };

    /// A sine of `amplitude_v` at `freq_hz`.
    pub fn sine(freq_hz: f64, amplitude_v: f64) -> Self {
        ExcitationDesign { waveform: Waveform::Sine { freq_hz }, amplitude_v, offset_v: 0.0 }
    }

    /// A multisine from `f_lo_hz` to `f_hi_hz` with the power of a sine of `amplitude_v`.
    pub fn multisine(f_lo_hz: f64, f_hi_hz: f64, amplitude_v: f64) -> Self {
        ExcitationDesign { waveform: Waveform::Multisine { f_lo_hz, f_hi_hz }, amplitude_v, offset_v: 0.0 }
    }

    /// A constant `v`.
    pub fn constant(v: f64) -> Self {
        ExcitationDesign { waveform: Waveform::Off, amplitude_v: 0.0, offset_v: v }
    }

    /// The generator's configuration for sample rate `fs_hz`.
    #[inline(never)]
    pub fn design<T: Real>(&self, fs_hz: f64) -> Excitation<T> {
        let phase_step = |f_hz: f64| phase_step(f_hz, fs_hz);
        let mut weights = [T::zero(); MAX_HARMONICS];
        let mut spacing_step = 0;
        let (kind, step, harmonics) = match self.waveform {
            Waveform::Off => (Kind::Off, 0, 0),
            Waveform::Multisine { f_lo_hz, f_hi_hz } => {
                let n = MAX_TONES as f64;
                let a = T::of(1.0 / libm::sqrt(n));
                for (j, w) in weights.chunks_exact_mut(2).enumerate() {
                    // Its sine in the working scalar (in f32 on the board, not libm's f64 in software).
                    let (sin, cos) = T::phase_sin_cos(schroeder_phase(j));
                    w[0] = a * cos;
                    w[1] = a * sin;
                }
                spacing_step = phase_step(multisine_spacing_hz(f_lo_hz, f_hi_hz));
                (Kind::Multisine, phase_step(f_lo_hz), MAX_TONES)
            }
            Waveform::Prbs { hold } => (Kind::Prbs { hold: hold.max(1) }, 0, 0),
            Waveform::Sine { freq_hz } => (Kind::Sine, phase_step(freq_hz), 0),
            Waveform::Triangle { freq_hz, max_hz } => {
                let count = triangle_harmonics(freq_hz, max_hz);
                for (k, w) in weights[..count].iter_mut().enumerate() {
                    let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
                    *w = T::of(sign * triangle_weight::<f64>(k));
                }
                (Kind::Triangle, phase_step(freq_hz), count)
            }
        };
        Excitation {
            kind,
            phase_step: step,
            spacing_step,
            amplitude: T::of(self.amplitude_v),
            offset: T::of(self.offset_v),
            weights,
            harmonics,
        }
    }
}

/// How many odd harmonics `n f` (`n = 1, 3, 5, ...`) of `freq_hz` (above 0) the smoothed triangle has up to `max_hz`
/// (and a part in 1e12 above, so that a top harmonic meant to be at `max_hz` is not lost to rounding), at most
/// [`MAX_HARMONICS`]: the odd numbers up to `top = max_hz (1 + 1e-12) / freq_hz` are `floor((top + 1) / 2)`. In a
/// closed form rather than a loop: on the board, where this is soft double, the loop took 864 B of flash.
#[inline(never)]
fn triangle_harmonics(freq_hz: f64, max_hz: f64) -> usize {
    let top = max_hz * (1.0 + 1e-12) / freq_hz;
    if top >= 1.0 {
        libm::fmin(libm::floor((top + 1.0) / 2.0), MAX_HARMONICS as f64) as usize
    } else {
        0
    }
}

/// The magnitude of the triangle's harmonic `2 k + 1`, for a unit amplitude: `8 / (pi^2 (2 k + 1)^2)`, in `T`.
fn triangle_weight<T: Real>(k: usize) -> T {
    let (n, pi) = (T::of((2 * k + 1) as f64), core::f64::consts::PI);
    T::of(8.0 / (pi * pi)) / (n * n)
}

/// How far an excitation takes the command ([`ExcitationDesign::reach`]), V.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Reach {
    /// The lowest value.
    pub low_v: f64,
    /// The highest value.
    pub high_v: f64,
    /// The largest change from one sample to the next over every phase the samples can take (the PRBS: exact; a
    /// sine or the smoothed triangle: its samples may miss it by up to `1 - cos(pi f / fs)`, `f` the top frequency;
    /// the multisine: over every relative phase of its tones, which its samples come within a few % of once those
    /// have turned through the crest, see `multisine_steepest_step`).
    pub step_v: f64,
}

impl ExcitationDesign {
    /// The excitation's extent at the sample rate `fs_hz`: its lowest and highest values (exact for the PRBS and the
    /// constant; the sine's and the smoothed triangle's crests, which the samples may miss by up to `1 - cos(pi f /
    /// fs)` of the amplitude, `f` the sine's or the triangle's top harmonic's; the multisine's envelope bound of 1.36
    /// `A`) and its largest step. What the console compares with the
    /// output limits, to say before it runs that an excitation will be clipped or slew-limited.
    #[inline(never)]
    pub fn reach(&self, fs_hz: f64) -> Reach {
        let a = libm::fabs(self.amplitude_v);
        let (peak, step_v) = match self.waveform {
            Waveform::Off => (0.0, 0.0),
            Waveform::Prbs { .. } => (a, 2.0 * a),
            Waveform::Sine { freq_hz } => {
                (a, 2.0 * a * libm::fabs(libm::sin(core::f64::consts::PI * libm::fmin(freq_hz / fs_hz, 0.5))))
            }
            Waveform::Triangle { freq_hz, max_hz } => {
                // Summed in f32, to 1e-7, and raised by 1e-6 for it (it fell 2e-9 short of the generator's crest at
                // 171 Hz): on the board a loop of soft-double calls took 1.2 KiB of flash.
                let harmonics = triangle_harmonics(freq_hz, max_hz);
                let sum: f32 = (0..harmonics).map(triangle_weight::<f32>).sum();
                (a * sum as f64 * (1.0 + 1e-6), a * triangle_steepest_step(phase_step(freq_hz, fs_hz), harmonics))
            }
            Waveform::Multisine { f_lo_hz, f_hi_hz } => {
                let spacing = phase_step(multisine_spacing_hz(f_lo_hz, f_hi_hz), fs_hz);
                (MULTISINE_PEAK * a, a * multisine_steepest_step(phase_step(f_lo_hz, fs_hz), spacing))
            }
        };
        Reach { low_v: self.offset_v - peak, high_v: self.offset_v + peak, step_v }
    }
}

/// The phase a sample of `f_hz` at `fs_hz` turns, in 2^-64 of a cycle (the generators' unit). Out of line: soft
/// double on the board, in the designs and in `reach`.
#[inline(never)]
fn phase_step(f_hz: f64, fs_hz: f64) -> u64 {
    let cycles = f_hz / fs_hz;
    let frac = cycles - libm::floor(cycles);
    (frac * 18_446_744_073_709_551_616.0) as u64
}

/// The smoothed triangle's largest change from one sample to the next, for a unit amplitude, over every phase: the
/// change from phase `x` to `x + d` (`d` the phase a sample turns, `step`) is `sum_k w_k (sin(n_k (x + d)) - sin(n_k
/// x))`, that is `g(phi) = sum_k c_k cos(n_k phi)` with `c_k = 2 w_k sin(n_k d / 2)` (`w_k` signed, `n_k = 2 k + 1`) at
/// `phi = x + d / 2`; `|g|` repeats every half period and is even, so a quarter period holds its maximum. Sampled at 16
/// points a period of the top harmonic, each local maximum within 3 % of the largest then refined by 16 ternary steps
/// (to 2e-3 of a grid step): the sum's largest lobe is a few grid steps wide, so the coarse grid finds every candidate,
/// and the refinement takes the missed crest's 1-2 % back. In f32 with the generators' own sines (at most 509 points of
/// at most 64 terms, `cos(n phi)` by the recurrence `2 cos(2 phi) cos(n phi) - cos((n - 2) phi)`), raised by
/// [`TRIANGLE_STEP_RAISE`] for its rounding: measured from 1.0e-5 below to 1.3e-5 above the maximum over a grid of
/// 2^17 phases in f64, for 800 fundamentals from 0.5 Hz to 1 kHz (half of them under 20 Hz, where it is least
/// accurate); 1.1e-7 with the sum in f64, which on the board would be soft double. `excite triangle 1 10` takes 425 000
/// instructions on the M4F, 201 000 more than `excite prbs 1` (QEMU, measured once). The steepest step sits next to the
/// crests, where the harmonics' sum overshoots the straight flank (Gibbs): about 1.18 times `4 A f / fs` when there are
/// many.
#[inline(never)]
fn triangle_steepest_step(step: u64, harmonics: usize) -> f64 {
    if harmonics == 0 {
        return 0.0;
    }
    let mut c = [0f32; MAX_HARMONICS];
    for (k, c) in c[..harmonics].iter_mut().enumerate() {
        let sign = if k % 2 == 0 { 2.0 } else { -2.0 };
        *c = sign * triangle_weight::<f32>(k) * f32::phase_sin_cos((step / 2).wrapping_mul(2 * k as u64 + 1)).0;
    }
    let c = &c[..harmonics];
    let points = 4 * (2 * harmonics - 1);
    // A quarter cycle is 2^62.
    let h = (1u64 << 62) / points as u64;
    let mut grid = [0.0f32; 4 * (2 * MAX_HARMONICS - 1) + 1];
    // `|g|` is even about both ends of the quarter period.
    let best = refined_max(&mut grid[..=points], h, false, |x| abs_odd_cosine_series(c, x));
    best as f64 * (1.0 + TRIANGLE_STEP_RAISE)
}

/// What [`triangle_steepest_step`] adds for its f32 rounding, relative.
const TRIANGLE_STEP_RAISE: f64 = 2e-5;

/// The largest of `f` (at least 0) over phases, from the grid `grid[i] = f(i h)` (filled here): each local maximum of
/// the grid within 3 % of its largest refined by 16 ternary steps over `[i h - h, i h + h]` (to 2e-3 of a grid step). A
/// grid that misses a lobe's crest by at most 1.9 % (for a trigonometric polynomial, 16 points a period of its top
/// harmonic) finds every lobe that can hold the maximum. `periodic`: the grid goes round, its last point next to its
/// first; else `f` is even about both ends, each a local maximum when no less than its one neighbour.
fn refined_max(grid: &mut [f32], h: u64, periodic: bool, f: impl Fn(u64) -> f32) -> f32 {
    for (i, g) in grid.iter_mut().enumerate() {
        *g = f(i as u64 * h);
    }
    let (grid, n) = (&*grid, grid.len());
    let coarse = grid.iter().fold(0.0f32, |m, &g| m.max(g));
    let mut best = coarse;
    for (i, &g) in grid.iter().enumerate() {
        let (before, after) = if periodic {
            (grid[(i + n - 1) % n], grid[(i + 1) % n])
        } else {
            (if i > 0 { grid[i - 1] } else { 0.0 }, grid.get(i + 1).copied().unwrap_or(0.0))
        };
        if g >= before && g >= after && g >= 0.97 * coarse {
            let (mut lo, mut hi) = ((i as u64 * h).wrapping_sub(h), (i as u64 * h).wrapping_add(h));
            for _ in 0..16 {
                let third = hi.wrapping_sub(lo) / 3;
                let (m1, m2) = (lo.wrapping_add(third), hi.wrapping_sub(third));
                if f(m1) < f(m2) {
                    lo = m1;
                } else {
                    hi = m2;
                }
            }
            best = best.max(f(lo.wrapping_add(hi.wrapping_sub(lo) / 2)));
        }
    }
    best
}

/// `|sum_k c_k cos((2 k + 1) phi)|` at the phase `phi` (2^-64 of a cycle), by the recurrence.
#[inline(never)]
fn abs_odd_cosine_series(c: &[f32], phi: u64) -> f32 {
    let c1 = f32::phase_sin_cos(phi).1;
    let two_c2 = 4.0 * c1 * c1 - 2.0;
    let (mut prev, mut cos_n, mut sum) = (c1, c1, 0.0f32);
    for &ck in c {
        sum += ck * cos_n;
        (prev, cos_n) = (cos_n, two_c2 * cos_n - prev);
    }
    libm::fabsf(sum)
}

/// The multisine's peak over its amplitude, at most ([`Waveform::Multisine`]: the envelope's maximum 1.3545).
pub const MULTISINE_PEAK: f64 = 1.36;

/// The multisine's tone spacing, Hz: [`MAX_TONES`] tones from `f_lo_hz` to `f_hi_hz`.
fn multisine_spacing_hz(f_lo_hz: f64, f_hi_hz: f64) -> f64 {
    libm::fmax(f_hi_hz - f_lo_hz, 0.0) / (MAX_TONES - 1) as f64
}

/// Schroeder's phase of tone `j`, `phi_j = -pi j (j + 1) / N`, as a phase: `-j (j + 1) / (2 N)` of a cycle, exact in
/// integers.
fn schroeder_phase(j: usize) -> u64 {
    ((j * (j + 1)) as u64).wrapping_mul((1 << 63) / MAX_TONES as u64).wrapping_neg()
}

/// The multisine's largest change from one sample to the next, for a unit amplitude, over every relative phase of its
/// tones. Tone `j` turns `d_j` a sample (`step` and `spacing`: `d_j = step + j spacing`), so from `x_j = psi + j
/// theta + phi_j` to `x_j + d_j` the sum changes by `sum_j 2 sin(d_j / 2) cos(x_j + d_j / 2) / sqrt(N)`: the real
/// part of `e^(i psi') Z(theta') / sqrt(N)`, `Z(theta) = sum_j c_j e^(i j theta)` with `c_j = 2 sin(d_j / 2) e^(i
/// phi_j)` (`psi'`, `theta'` the phases half a sample on). So it is at most `max |Z| / sqrt(N)`, and reaches it where
/// `psi'` comes round to `-arg Z` with `theta'` at the crest of `|Z|`: the samples came within 2.3 % of it in 40 s
/// (200-800 Hz; within 1.5 % in other bands from 50-2000 Hz to 400-450 Hz), once the tones' relative phases have
/// turned through the crest (within `1 / df`, the spacing's period). `|Z|^2`, a trigonometric polynomial of degree 31
/// (`N - 1`), is sampled at 16 points a period of its top harmonic (by Bernstein's inequality a crest is missed by at
/// most `pi^2 / 512`, 1.9 %), and each local maximum within 3 % of the largest refined by 16 ternary steps, as for
/// the triangle ([`triangle_steepest_step`]). In f32 with the generators' sines, `Z` by Horner's scheme, but for the
/// tones' steps `2 sin(d_j / 2)`, in f64: the f32 sine holds the phase to 2^-27 of a cycle, 3e-5 of the half step
/// of a tone of 1.4 Hz, which put the bound up to 2e-5 below the maximum in bands under 4 Hz. Raised by
/// [`MULTISINE_STEP_RAISE`] for the rounding: measured within 1.7e-6 either way of the maximum over a grid of 2^16
/// phases in f64, for 3 000 bands of random edges from 1 Hz to 1 kHz.
#[inline(never)]
fn multisine_steepest_step(step: u64, spacing: u64) -> f64 {
    let mut c = [(0.0f32, 0.0f32); MAX_TONES];
    for (j, c) in c.iter_mut().enumerate() {
        let d = step.wrapping_add(spacing.wrapping_mul(j as u64));
        // In f64: the generators' f32 sine holds the phase to 2^-27 of a cycle, which is up to 3e-5 of `d / 2`
        // for tones of a few Hz.
        let size = (2.0 * f64::phase_sin(d / 2)) as f32;
        let (sin, cos) = f32::phase_sin_cos(schroeder_phase(j));
        *c = (size * cos, size * sin);
    }
    const POINTS: usize = 16 * (MAX_TONES - 1);
    let h = u64::MAX / POINTS as u64;
    let best = refined_max(&mut [0.0f32; POINTS], h, true, |x| tone_sum_power(&c, x));
    libm::sqrtf(best / MAX_TONES as f32) as f64 * (1.0 + MULTISINE_STEP_RAISE)
}

/// What [`multisine_steepest_step`] adds for its f32 rounding, relative.
const MULTISINE_STEP_RAISE: f64 = 1e-5;

/// `|sum_j c_j e^(i j theta)|^2` at the phase `theta` (2^-64 of a cycle), the `c_j` complex `(re, im)`, by Horner's
/// scheme.
#[inline(never)]
fn tone_sum_power(c: &[(f32, f32)], theta: u64) -> f32 {
    let (sin, cos) = f32::phase_sin_cos(theta);
    let Some((&(mut re, mut im), rest)) = c.split_last() else { return 0.0 };
    for &(cr, ci) in rest.iter().rev() {
        (re, im) = (re * cos - im * sin + cr, re * sin + im * cos + ci);
    }
    re * re + im * im
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    Off,
    Prbs { hold: u32 },
    Triangle,
    Sine,
    Multisine,
}

/// A designed generator (the configuration).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Excitation<T> {
    kind: Kind,
    phase_step: u64,
    /// The multisine's tone spacing, as a phase step.
    spacing_step: u64,
    amplitude: T,
    offset: T,
    weights: [T; MAX_HARMONICS],
    harmonics: usize,
}

/// A generator's running state: the LFSR, the hold counter and the phases.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExcitationState {
    lfsr: u16,
    bit_high: bool,
    hold_left: u32,
    phase: u64,
    /// The multisine's tone spacing's phase.
    spacing_phase: u64,
}

impl Default for ExcitationState {
    fn default() -> Self {
        ExcitationState { lfsr: 0x7FFF, bit_high: false, hold_left: 0, phase: 0, spacing_phase: 0 }
    }
}

impl<T: Real> Excitation<T> {
    /// The next sample, V.
    #[inline]
    pub fn next(&self, s: &mut ExcitationState) -> T {
        let unit = match self.kind {
            Kind::Off => T::zero(),
            Kind::Prbs { hold } => {
                if s.hold_left == 0 {
                    let b = ((s.lfsr >> 14) ^ (s.lfsr >> 13)) & 1;
                    s.lfsr = ((s.lfsr << 1) | b) & 0x7FFF;
                    s.bit_high = b == 1;
                    s.hold_left = hold;
                }
                s.hold_left -= 1;
                if s.bit_high {
                    T::one()
                } else {
                    -T::one()
                }
            }
            Kind::Sine => {
                let sin = T::phase_sin(s.phase);
                s.phase = s.phase.wrapping_add(self.phase_step);
                sin
            }
            Kind::Triangle => {
                let x = T::phase_sin_cos(s.phase);
                s.phase = s.phase.wrapping_add(self.phase_step);
                self.odd_sine_series(x)
            }
            Kind::Multisine => {
                let (psi, theta) = (T::phase_sin_cos(s.phase), T::phase_sin_cos(s.spacing_phase));
                s.phase = s.phase.wrapping_add(self.phase_step);
                s.spacing_phase = s.spacing_phase.wrapping_add(self.spacing_step);
                self.tones(psi, theta)
            }
        };
        self.offset + self.amplitude * unit
    }

    /// `sum_m w_m sin((2m + 1) x)` by the three-term recurrence, from `(sin x, cos x)`: two chains of `4x` steps,
    /// `sin((4j + 1) x)` and `sin((4j + 3) x)`, each `2 cos(4x) s_j - s_(j-1)`, which run side by side (one chain of
    /// `2x` steps is as long as the harmonics, each step waiting on the last multiply-add).
    #[inline]
    fn odd_sine_series(&self, (s1, c1): (T, T)) -> T {
        let two_cos_2x = T::of(2.0) * (c1 * c1 - s1 * s1);
        let two_cos_4x = two_cos_2x * two_cos_2x - T::of(2.0);
        // sin(3x); the chains' (sin((4j - 3) x), sin((4j + 1) x)) and (sin((4j - 1) x), sin((4j + 3) x)) from j = 0.
        let s3 = s1 * (two_cos_2x + T::one());
        let (mut a_prev, mut a) = (-s3, s1);
        let (mut b_prev, mut b) = (-s1, s3);
        let (mut sum_a, mut sum_b) = (T::zero(), T::zero());
        let weights = &self.weights[..self.harmonics];
        let mut pairs = weights.chunks_exact(2);
        for w in &mut pairs {
            sum_a += w[0] * a;
            sum_b += w[1] * b;
            (a_prev, a) = (a, two_cos_4x * a - a_prev);
            (b_prev, b) = (b, two_cos_4x * b - b_prev);
        }
        if let [w] = pairs.remainder() {
            sum_a += *w * a;
        }
        sum_a + sum_b
    }

    /// `sum_j w_2j sin(psi + j theta) + w_2j+1 cos(psi + j theta)` from `(sin, cos)` of `psi` and `theta`, each
    /// tone the last rotated by `theta`.
    #[inline]
    fn tones(&self, (mut s, mut c): (T, T), (st, ct): (T, T)) -> T {
        let mut sum = T::zero();
        for w in self.weights.chunks_exact(2) {
            sum += w[0] * s + w[1] * c;
            (s, c) = (s * ct + c * st, c * ct - s * st);
        }
        sum
    }

    /// True when this generator emits a time-varying signal.
    pub fn is_active(&self) -> bool {
        self.kind != Kind::Off && self.amplitude != T::zero()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prbs_starts_like_the_reference_and_has_the_maximal_period() {
        let gen = ExcitationDesign::PAPER_PRBS.design::<f64>(10_000.0);
        let mut s = ExcitationState::default();
        let bits: std::vec::Vec<f64> = (0..(PRBS_PERIOD_BITS as usize + 3) * 5).map(|_| gen.next(&mut s)).collect();
        // Reference: first bit b = (1 ^ 1) & 1 = 0 -> -1 V, held for 5 samples.
        assert_eq!(&bits[..5], &[-1.0; 5]);
        let period = PRBS_PERIOD_BITS as usize * 5;
        assert_eq!(&bits[..15], &bits[period..period + 15]);
        // No shorter period: the register state sequence of a maximal LFSR visits all 32767 non-zero states.
        let mut reg = 0x7FFFu16;
        let mut seen = std::collections::HashSet::new();
        for _ in 0..PRBS_PERIOD_BITS {
            assert!(seen.insert(reg));
            let b = ((reg >> 14) ^ (reg >> 13)) & 1;
            reg = ((reg << 1) | b) & 0x7FFF;
        }
        assert_eq!(reg, 0x7FFF);
        // Balanced: 16384 ones and 16383 zeros per period.
        let sum: f64 = bits[..period].iter().sum();
        assert_eq!(sum, 5.0);
    }

    #[test]
    fn smoothed_triangle_matches_its_fourier_series_and_peaks_near_the_amplitude() {
        let fs = 10_000.0;
        let gen = ExcitationDesign::PAPER_TRIANGLE.design::<f64>(fs);
        let mut s = ExcitationState::default();
        let pi = core::f64::consts::PI;
        let mut max = 0.0f64;
        for k in 0..2000 {
            let t = k as f64 / fs;
            let direct: f64 = (0..50)
                .map(|m| {
                    let n = (2 * m + 1) as f64;
                    let sign = if m % 2 == 0 { 1.0 } else { -1.0 };
                    8.0 / (pi * pi) * sign * libm::sin(2.0 * pi * n * 10.0 * t) / (n * n)
                })
                .sum();
            let u = gen.next(&mut s);
            // The recurrence accumulates a few ulps per harmonic.
            assert!((u - direct).abs() < 1e-12, "k = {k}: {u} vs {direct}");
            max = max.max(u.abs());
        }
        // Truncation at 50 odd harmonics rounds the corners: the peak is 1 - 8/pi^2 sum_{n > 99} 1/n^2 ~ 0.996.
        assert!(max > 0.99 && max < 1.0, "{max}");
    }

    /// Every count of harmonics, odd ones (the last harmonic outside the two chains' pairs) too, is its series.
    #[test]
    fn a_triangle_of_any_count_of_harmonics_is_its_fourier_series() {
        let (fs, freq, pi) = (10_000.0, 10.0, core::f64::consts::PI);
        for count in 1..=MAX_HARMONICS {
            let design = ExcitationDesign {
                waveform: Waveform::Triangle { freq_hz: freq, max_hz: freq * (2 * count - 1) as f64 },
                ..ExcitationDesign::PAPER_TRIANGLE
            };
            let gen = design.design::<f64>(fs);
            assert_eq!(gen.harmonics, count);
            let mut s = ExcitationState::default();
            for k in 0..300 {
                let t = k as f64 / fs;
                let direct: f64 = (0..count)
                    .map(|m| {
                        let n = (2 * m + 1) as f64;
                        let sign = if m % 2 == 0 { 1.0 } else { -1.0 };
                        8.0 / (pi * pi) * sign * libm::sin(2.0 * pi * n * freq * t) / (n * n)
                    })
                    .sum();
                let u = gen.next(&mut s);
                assert!((u - direct).abs() < 1e-12, "{count} harmonics, k = {k}: {u} vs {direct}");
            }
        }
    }

    #[test]
    fn f32_triangle_stays_within_single_precision_noise_of_f64() {
        let g64 = ExcitationDesign::PAPER_TRIANGLE.design::<f64>(10_000.0);
        let g32 = ExcitationDesign::PAPER_TRIANGLE.design::<f32>(10_000.0);
        let (mut s64, mut s32) = (ExcitationState::default(), ExcitationState::default());
        for _ in 0..100_000 {
            let (a, b) = (g64.next(&mut s64), g32.next(&mut s32));
            // 24-bit phase (6e-8 cycle) times the steepest slope (4 V/cycle), plus f32 recurrence error.
            assert!((a - b as f64).abs() < 2e-5);
        }
    }

    #[test]
    fn sine_has_the_requested_frequency_and_amplitude() {
        // A frequency at or above the sample rate gives its alias's samples, and a negative one runs backwards, as
        // sampling such sines does (the phase step taken modulo a cycle); the reference's own rounding grows with
        // its argument (up to 1.3e5 rad here), hence the wider bound for those.
        for (f, tol) in [(423.0, 1e-12), (-423.0, 1e-10), (10_423.0, 1e-10), (20_000.0 - 423.0, 1e-10)] {
            let gen = ExcitationDesign::sine(f, 0.5).design::<f64>(10_000.0);
            let mut s = ExcitationState::default();
            for k in 0..10_000 {
                let expect = 0.5 * libm::sin(2.0 * core::f64::consts::PI * f * k as f64 / 10_000.0);
                let got = gen.next(&mut s);
                assert!((got - expect).abs() < tol, "{f} Hz, sample {k}: {got} against {expect}");
            }
        }
    }

    #[test]
    fn multisine_is_its_schroeder_phased_sum_with_the_power_of_a_sine_and_a_low_peak() {
        let fs = 10_000.0;
        let pi = core::f64::consts::PI;
        let n = MAX_TONES as f64;
        for (lo, hi) in [(200.0, 800.0), (300.0, 600.0), (10.0, 1000.0), (400.0, 410.0), (423.0, 483.0)] {
            let design = ExcitationDesign { offset_v: 0.5, ..ExcitationDesign::multisine(lo, hi, 2.0) };
            let gen = design.design::<f64>(fs);
            let g32 = design.design::<f32>(fs);
            let (mut s, mut s32) = (ExcitationState::default(), ExcitationState::default());
            let df = (hi - lo) / (n - 1.0);
            // Over whole periods of the spacing (1 / df) the tones are orthogonal: the mean power is exact.
            let samples = (libm::round(fs / df) * libm::ceil(df)) as usize;
            let (mut power, mut peak, mut worst32) = (0.0, 0.0f64, 0.0f64);
            for k in 0..samples {
                let t = k as f64 / fs;
                let direct: f64 = (0..MAX_TONES)
                    .map(|j| {
                        let phi = -pi * (j * (j + 1)) as f64 / n;
                        libm::sin(2.0 * pi * (lo + j as f64 * df) * t + phi) / libm::sqrt(n)
                    })
                    .sum();
                let u = gen.next(&mut s);
                // The rotation from tone to tone and the phase accumulators round at about 1e-15 per tone.
                assert!((u - (0.5 + 2.0 * direct)).abs() < 1e-11, "{lo}-{hi} Hz, k = {k}: {u} vs {direct}");
                worst32 = worst32.max((u - g32.next(&mut s32) as f64).abs());
                power += (u - 0.5) * (u - 0.5);
                peak = peak.max((u - 0.5).abs());
            }
            let rms = libm::sqrt(power / samples as f64);
            std::println!("multisine {lo}-{hi} Hz, 2 V: RMS {rms:.4} V, peak {peak:.3} V ({:.2} of the amplitude), f32 off by {worst32:.1e} V", peak / 2.0);
            assert!((rms - 2.0 / libm::sqrt(2.0)).abs() < 0.01, "{lo}-{hi} Hz: RMS {rms}");
            // The sum is the tone at `f_lo` times the envelope `|sum_j exp(i (j theta + phi_j))| / sqrt(N)`, whatever
            // the band: with these phases its maximum over `theta` is 1.3545 (computed on 20 000 points of a cycle).
            assert!(peak < 1.3546 * 2.0, "{lo}-{hi} Hz: peak {peak}");
            // f32: the two phases to 2.3e-8 rad and their sines to 1e-7 put tone j off by up to about (1 + j) 1.2e-7;
            // at A / sqrt(N) a tone, all aligned, 1.1e-5 A; the rotations' rounding adds a few ulps a tone (measured
            // 3.2e-6 A).
            assert!(worst32 < 1.2e-5 * 2.0, "{lo}-{hi} Hz: f32 off by {worst32}");
        }
    }

    /// `reach` bounds what the generator emits, and for the waveforms it calls exact it is reached: over 2 s at
    /// 10 kHz the extremes and the largest step within `1 - cos(pi f / fs)` of the amplitude and of the step's bound
    /// (the samples may miss the crest and the steepest point; `f` the sine's or the triangle's top frequency), the
    /// PRBS's exactly.
    #[test]
    fn the_reach_bounds_the_waveform_and_is_tight_where_exact() {
        let tri = |freq_hz: f64, amplitude_v: f64| ExcitationDesign {
            waveform: Waveform::Triangle { freq_hz, max_hz: 1000.0 },
            amplitude_v,
            offset_v: 0.0,
        };
        let designs = [
            (ExcitationDesign { offset_v: 0.5, ..ExcitationDesign::PAPER_PRBS }, true),
            (ExcitationDesign { amplitude_v: 0.25, ..ExcitationDesign::PAPER_PRBS }, true),
            (ExcitationDesign { offset_v: -2.0, ..ExcitationDesign::sine(97.0, 3.0) }, true),
            (ExcitationDesign::sine(1000.0, 1.0), true),
            (ExcitationDesign { offset_v: 1.0, ..ExcitationDesign::PAPER_TRIANGLE }, true),
            (tri(7.0, 2.0), true),
            (tri(33.3, 0.5), true),
            (tri(171.0, 1.0), true),
            (tri(333.4, 1.0), true),
            (tri(1000.0, 1.0), true),
            (ExcitationDesign::multisine(200.0, 800.0, 2.0), false),
            (ExcitationDesign::constant(4.0), true),
        ];
        for (design, tight) in designs {
            let r = design.reach(1e4);
            let gen = design.design::<f64>(1e4);
            let mut s = ExcitationState::default();
            let u: std::vec::Vec<f64> = (0..20_000).map(|_| gen.next(&mut s)).collect();
            let (low, high) = u.iter().fold((f64::MAX, f64::MIN), |(l, h), &v| (l.min(v), h.max(v)));
            let step = u.windows(2).map(|w| (w[1] - w[0]).abs()).fold(0.0, f64::max);
            let a = design.amplitude_v.max(1e-300);
            assert!(low >= r.low_v - 1e-12 && high <= r.high_v + 1e-12, "{design:?}: {low} {high} in {r:?}");
            // The samples' distance to the crest, and to the steepest step: `1 - cos(pi f / fs)`, `f` the top
            // frequency.
            let top = match design.waveform {
                Waveform::Sine { freq_hz } => freq_hz,
                Waveform::Triangle { max_hz, .. } => max_hz,
                _ => 0.0,
            };
            let near = libm::cos(core::f64::consts::PI * top / 1e4) - 1e-9;
            if tight {
                let slack = 1.0 - near;
                assert!(low - r.low_v <= slack * a && r.high_v - high <= slack * a, "{design:?}: {low} {high} {r:?}");
            } else {
                // The multisine's envelope bound (1.36 `A`) is 0.4 % above its maximum, which these 2 s come within
                // 1.8 % of.
                assert!(high - low >= 0.97 * (r.high_v - r.low_v), "{design:?}: {low} {high} in {r:?}");
            }
            // The triangle's and the multisine's from a search in f32, raised for its rounding (and off by that
            // rounding, up to 1e-5); the multisine's samples come within 2.5 % of it in these 2 s.
            let bound = r.step_v;
            let low = near * bound / (1.0 + TRIANGLE_STEP_RAISE + 1e-5) * if tight { 1.0 } else { 0.975 };
            assert!(step <= bound + 1e-12 && step >= low, "{design:?}: step {step}, bound {bound}");
        }
    }

    /// The multisine's steepest step, searched in f32, against the largest `|Z|` (see `multisine_steepest_step`)
    /// over a grid of 2^16 phases computed in f64, for 100 bands of random edges from 1 Hz to 1 kHz, some wider than
    /// the console takes, and three under 4 Hz (where a step size in f32 put it up to 2e-5 below): at or above it, by
    /// at most its raise and the f32 search's own error (measured within 1.7e-6 on 3 000 bands). And the
    /// generator's samples (f64, 40 s) reach it within 3 % in the bands of its doc.
    #[test]
    fn the_multisines_steepest_step_is_found_over_every_relative_phase() {
        let (fs, n) = (1e4, MAX_TONES);
        let brute = |lo: f64, hi: f64| {
            let df = multisine_spacing_hz(lo, hi);
            let c: std::vec::Vec<(f64, f64)> = (0..n)
                .map(|j| {
                    let size = 2.0 * libm::sin(core::f64::consts::PI * (lo + j as f64 * df) / fs);
                    let phi = -core::f64::consts::PI * (j * (j + 1)) as f64 / n as f64;
                    (size * libm::cos(phi), size * libm::sin(phi))
                })
                .collect();
            let points = 1 << 16;
            let most = (0..points)
                .map(|i| {
                    let theta = 2.0 * core::f64::consts::PI * i as f64 / points as f64;
                    let (mut re, mut im) = (0.0, 0.0);
                    for (j, (cr, ci)) in c.iter().enumerate() {
                        let (s, co) = (libm::sin(j as f64 * theta), libm::cos(j as f64 * theta));
                        (re, im) = (re + cr * co - ci * s, im + cr * s + ci * co);
                    }
                    re * re + im * im
                })
                .fold(0.0, f64::max);
            libm::sqrt(most / n as f64)
        };
        let found = |lo: f64, hi: f64| {
            let spacing = phase_step(multisine_spacing_hz(lo, hi), fs);
            multisine_steepest_step(phase_step(lo, fs), spacing)
        };
        let mut next = crate::xorshift64(0x003A_175E);
        let mut unit = move || (next() >> 11) as f64 / (1u64 << 53) as f64;
        let (mut worst, mut over) = (0.0f64, 0.0f64);
        let wide = [(200.0, 800.0), (50.0, 2000.0), (10.0, 4000.0), (400.0, 450.0), (999.0, 1000.0)];
        let low = [(1.439, 2.233), (1.927, 2.125), (1.141, 3.086)];
        let random = (0..100).map(|_| {
            let (a, b) = (libm::pow(1000.0, unit()), libm::pow(1000.0, unit()));
            (a.min(b), a.max(b) + 1e-3)
        });
        for (lo, hi) in wide.into_iter().chain(low).chain(random) {
            let (found, brute) = (found(lo, hi), brute(lo, hi));
            // The phase grid itself may miss the crest by a few 1e-6.
            let raised = found / (1.0 + MULTISINE_STEP_RAISE);
            assert!(found >= brute && raised <= brute * (1.0 + 1e-5), "{lo}-{hi} Hz: {found} against {brute}");
            worst = worst.max(1.0 - raised / brute);
            over = over.max(raised / brute - 1.0);
        }
        std::println!(
            "the multisine's steepest step searched in f32 from {worst:.1e} below the grid's to {over:.1e} above, \
             before the raise"
        );
        for (lo, hi) in [(200.0, 800.0), (100.0, 1000.0), (300.0, 500.0), (400.0, 450.0), (50.0, 2000.0)] {
            let design = ExcitationDesign::multisine(lo, hi, 1.0);
            let gen = design.design::<f64>(fs);
            let mut s = ExcitationState::default();
            let (mut last, mut step) = (gen.next(&mut s), 0.0f64);
            for _ in 0..400_000 {
                let u = gen.next(&mut s);
                step = step.max(libm::fabs(u - last));
                last = u;
            }
            let bound = design.reach(fs).step_v;
            std::println!("{lo}-{hi} Hz: the samples step by up to {:.4} of the bound", step / bound);
            assert!(step <= bound && step >= 0.97 * bound, "{lo}-{hi} Hz: {step} against {bound}");
        }
    }

    /// The triangle's steepest step, searched in f32, against the change from one phase to the next computed in f64
    /// on a grid of 2^17 phases a period (the unit triangle's series at `x` and `x + 2 pi f / fs`), for fundamentals
    /// from 0.5 Hz (64 harmonics, the most) to 1 kHz (one), and at 9.178 Hz (where its f32 sum is 1.0e-5 low): at
    /// or above it, by at most its raise and the f32 search's own error (measured from 1.0e-5 below to 1.3e-5 above
    /// on 800 fundamentals). And with many harmonics it is the flank's `4 f / fs` overshot by Gibbs's 1.18 (1.15-1.19
    /// here, as the harmonics' count and the sample period round the lobe).
    #[test]
    fn the_triangles_steepest_step_is_found_in_every_phase() {
        let fs = 1e4;
        let mut next = crate::xorshift64(0x7A1E);
        let mut worst = 0.0f64;
        for i in 0..40 {
            let f = match i {
                0 => 0.5,
                1 => 9.178005590049104,
                _ => 0.5 * libm::pow(2000.0, (next() >> 11) as f64 / (1u64 << 53) as f64),
            };
            let harmonics = triangle_harmonics(f, 1000.0);
            let d = 2.0 * core::f64::consts::PI * f / fs;
            // `sin(n x)` for odd `n` by the recurrence in f64 (its error a few 1e-15, far below what is judged).
            let u = |x: f64| {
                let (s1, two_c2) = (libm::sin(x), 2.0 * libm::cos(2.0 * x));
                let (mut prev, mut sin_n, mut sum) = (-s1, s1, 0.0);
                for k in 0..harmonics {
                    let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
                    sum += sign * triangle_weight::<f64>(k) * sin_n;
                    (prev, sin_n) = (sin_n, two_c2 * sin_n - prev);
                }
                sum
            };
            let points = 1 << 17;
            let brute = (0..points)
                .map(|j| 2.0 * core::f64::consts::PI * j as f64 / points as f64)
                .map(|x| libm::fabs(u(x + d) - u(x)))
                .fold(0.0, f64::max);
            let found = triangle_steepest_step(phase_step(f, fs), harmonics);
            // The phase grid itself may miss the crest of a lobe by up to 5e-6 (64 harmonics).
            let raised = found / (1.0 + TRIANGLE_STEP_RAISE);
            assert!(found >= brute && raised <= brute * (1.0 + 2e-5), "{f} Hz: {found} against {brute}");
            worst = worst.max(1.0 - raised / brute);
            if harmonics >= 16 {
                let gibbs = found / (4.0 * f / fs);
                assert!((1.15..1.19).contains(&gibbs), "{f} Hz: {gibbs} times the flank");
            }
        }
        std::println!(
            "the steepest step searched in f32 at most {worst:.1e} below the phase grid's in f64, before the raise"
        );
    }

    /// `refined_max` refines the local maxima of its grid within 3 % of the grid's largest, and no other point, each
    /// by 16 ternary steps and a last look (33 calls of `f`, the first a third of a grid step before the point), to
    /// 2e-3 of a grid step: on a flat grid even about both ends (an end a local maximum when no less than its one
    /// neighbour), and on a periodic one (its ends neighbours). Tents of slope 0.02-0.05 a grid step, the highest
    /// crest between two grid points, so that the grid misses it.
    #[test]
    fn the_search_refines_the_grids_highest_local_maxima_and_no_other_point() {
        // The largest of tents `(centre, height, slope)` at the distances `d(centre)`, in grid steps.
        fn tents(d: impl Fn(f64) -> f64, tents: &[(f64, f64, f64)]) -> f32 {
            tents.iter().map(|&(c, p, k)| p - k * d(c)).fold(0.0, f64::max) as f32
        }
        let calls = core::cell::RefCell::new(std::vec::Vec::new());
        // The points refined, in order, from the calls after the grid's `n`.
        let refined = |n: usize, h: u64| -> std::vec::Vec<usize> {
            let calls = calls.take();
            assert_eq!((calls.len() - n) % 33, 0, "{} calls for a grid of {n}", calls.len());
            let point = |x: u64| (libm::round(x as i64 as f64 / h as f64) as i64).rem_euclid(n as i64) as usize;
            calls[n..].chunks(33).map(|c| point(c[0])).collect()
        };

        // 13 points, even about both ends (the phases before 0 and past 12 steps fold back). The grid: 0.965 0.915
        // 0.928 0.948 0.968 0.988 0.992 0.972 0.952 0.94 0.97 0.94 0.91, its largest 0.992, so 3 % below is 0.962:
        // the local maxima 0, 6 and 10 are refined; 4, 5 (rising) and 7 (falling) are within 3 % but not maxima.
        let h = 1u64 << 58;
        let flat = |x: u64| {
            calls.borrow_mut().push(x);
            let s = 12.0 - libm::fabs(12.0 - libm::fabs(x as i64 as f64 / h as f64));
            tents(|c| libm::fabs(s - c), &[(5.6, 1.0, 0.02), (10.0, 0.97, 0.03), (0.0, 0.965, 0.05)])
        };
        let best = refined_max(&mut [0.0f32; 13], h, false, flat);
        assert_eq!(refined(13, h), [0, 6, 10], "the flat grid's points refined");
        assert!(best <= 1.0 && 1.0 - best <= 0.02 * 2e-3, "flat: {best} for 1 at 5.6 grid steps");

        // 12 points round a cycle, the highest crest 0.4 steps after the first point. The grid: 0.992 0.988 0.968
        // 0.948 0.928 0.94 0.97 0.94 0.912 0.932 0.952 0.972: the local maxima 0 and 6 are refined; 1 (falling) and
        // 11 (rising, next to 0) are within 3 % but not maxima.
        let h = u64::MAX / 12;
        let round = |x: u64| {
            calls.borrow_mut().push(x);
            let s = x as f64 / h as f64;
            let d = |c: f64| {
                let d = libm::fmod(libm::fabs(s - c), 12.0);
                d.min(12.0 - d)
            };
            tents(d, &[(0.4, 1.0, 0.02), (6.0, 0.97, 0.03)])
        };
        let best = refined_max(&mut [0.0f32; 12], h, true, round);
        assert_eq!(refined(12, h), [0, 6], "the periodic grid's points refined");
        assert!(best <= 1.0 && 1.0 - best <= 0.02 * 2e-3, "periodic: {best} for 1 at 0.4 grid steps");
    }

    /// The triangle's harmonic count in closed form is the count of the loop it replaced, over fundamentals from
    /// 0.1 Hz to 2 kHz (and every exact divisor of 1 kHz up to 1 kHz), tops from 10 Hz to 5 kHz.
    #[test]
    fn the_triangles_harmonics_are_counted_as_by_a_loop() {
        let by_loop = |f: f64, m: f64| {
            let mut count = 0;
            while count < MAX_HARMONICS && (2 * count + 1) as f64 * f <= m * (1.0 + 1e-12) {
                count += 1;
            }
            count
        };
        let tops = [10.0, 99.9, 100.0, 450.0, 999.0, 1000.0, 1000.0001, 2500.0, 4999.0];
        let divisors = (1..=1000u32).filter(|d| 1000 % d == 0).map(|d| 1000.0 / d as f64);
        let sweep = (0..20_000).map(|i| 0.1 * libm::pow(2e4, i as f64 / 19_999.0));
        for f in divisors.chain(sweep) {
            for m in tops {
                assert_eq!(triangle_harmonics(f, m), by_loop(f, m), "{f} Hz up to {m} Hz");
            }
        }
    }

    #[test]
    fn off_and_constant_emit_their_offset() {
        let mut s = ExcitationState::default();
        assert_eq!(ExcitationDesign::OFF.design::<f32>(1e4).next(&mut s), 0.0);
        assert_eq!(ExcitationDesign::constant(0.25).design::<f32>(1e4).next(&mut s), 0.25);
        assert!(!ExcitationDesign::OFF.design::<f32>(1e4).is_active());
        assert!(!ExcitationDesign::constant(0.25).design::<f32>(1e4).is_active());
    }

    #[test]
    fn a_waveform_is_active_only_with_an_amplitude() {
        // What the stuck-probe check asks: while the output holds still (`excite prbs 0` is a valid command) a
        // probe that reads the same code is no fault.
        let active = |design: ExcitationDesign| design.design::<f32>(1e4).is_active();
        for waveform in
            [ExcitationDesign::PAPER_PRBS, ExcitationDesign::PAPER_TRIANGLE, ExcitationDesign::sine(423.0, 1.0)]
        {
            assert!(active(waveform));
            assert!(!active(ExcitationDesign { amplitude_v: 0.0, offset_v: 1.0, ..waveform }));
        }
        assert!(active(ExcitationDesign::multisine(200.0, 800.0, 0.1)));
    }
}
