//! Deterministic Gaussian noise, counter-based, in the float64 reference's exact convention: word `i` of stream
//! `seed` is `splitmix64(seed + (i + 1) * 0x9E3779B97F4A7C15)`, `U_i = (word_i >> 11) 2^-53`, and Box-Muller on
//! pairs: `r = sqrt(-2 ln(1 - U_2j))`, `n_2j = r cos(2 pi U_2j+1)`, `n_2j+1 = r sin(2 pi U_2j+1)`. Sample `k` of a
//! run is `n_k` whatever else was drawn, so a seed fixes the data.

/// The golden ratio increment of splitmix64.
const GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A counter-based standard-normal stream.
#[derive(Clone, Debug)]
pub struct NormalStream {
    seed: u64,
    next_index: u64,
    spare: Option<f64>,
}

impl NormalStream {
    /// Stream `seed`, from its first value.
    pub fn new(seed: u64) -> Self {
        NormalStream { seed, next_index: 0, spare: None }
    }

    fn uniform(&self, i: u64) -> f64 {
        (mix(self.seed.wrapping_add((i + 1).wrapping_mul(GAMMA))) >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }

    /// The next standard-normal value.
    pub fn next_normal(&mut self) -> f64 {
        if let Some(x) = self.spare.take() {
            return x;
        }
        let j = self.next_index;
        self.next_index += 2;
        let r = (-2.0 * (1.0 - self.uniform(j)).ln()).sqrt();
        let theta = 2.0 * std::f64::consts::PI * self.uniform(j + 1);
        self.spare = Some(r * theta.sin());
        r * theta.cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moments_are_standard_normal() {
        let mut s = NormalStream::new(7);
        let n = 200_000;
        let (mut m1, mut m2) = (0.0, 0.0);
        for _ in 0..n {
            let x = s.next_normal();
            m1 += x;
            m2 += x * x;
        }
        // Standard errors: 1/sqrt(n) = 2.2e-3 for the mean, sqrt(2/n) = 3.2e-3 for the variance; 5 sigma.
        assert!((m1 / n as f64).abs() < 0.011);
        assert!((m2 / n as f64 - 1.0).abs() < 0.016);
    }
}
