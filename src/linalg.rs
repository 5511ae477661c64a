//! Small dense linear algebra in `f64` for design-time work (discretisations), not for the sample path.
//!
//! [`zoh`] computes the exact zero-order-hold discretisation of `x' = A x + B u`:
//! `Phi = e^{A T}`, `Gam = (integral_0^T e^{A s} ds) B`, by scaling and squaring of a Taylor series:
//! with `h = T / 2^s` chosen so that `||A h||_1 <= 1/2`, `Phi_h = sum (A h)^k / k!` and
//! `Psi_h = sum A^k h^(k+1) / (k+1)!` converge to machine precision in under 20 terms, and the doubling
//! `Phi_2h = Phi_h^2`, `Psi_2h = Psi_h + Phi_h Psi_h` climbs back to `T`. No inverse of `A` is needed, so it works for
//! singular `A` (integrators) too. Physical state spaces are badly scaled (the pre-filter's companion matrix spans
//! 1 to 5e9, the stage model 1 to 1e7), which would inflate `||A||` and the number of squarings; so `A` is first
//! balanced by an exact power-of-two diagonal similarity (Parlett-Reinsch), `A_b = D^-1 A D`, and the result mapped
//! back: `Phi = D Phi_b D^-1`, `Psi = D Psi_b D^-1`.

/// A square matrix, row-major.
pub type Mat<const N: usize> = [[f64; N]; N];

/// `a * b`.
pub fn mat_mul<const N: usize>(a: &Mat<N>, b: &Mat<N>) -> Mat<N> {
    let mut c = [[0.0; N]; N];
    for i in 0..N {
        for k in 0..N {
            let aik = a[i][k];
            if aik == 0.0 {
                continue;
            }
            for j in 0..N {
                c[i][j] += aik * b[k][j];
            }
        }
    }
    c
}

/// `m * p * m'`: `p` mapped through `m` (a covariance or Gramian through a state transition).
pub fn congruence<const N: usize>(m: &Mat<N>, p: &Mat<N>) -> Mat<N> {
    let mt: Mat<N> = core::array::from_fn(|i| core::array::from_fn(|j| m[j][i]));
    mat_mul(&mat_mul(m, p), &mt)
}

/// `a * v`.
pub fn mat_vec<const N: usize>(a: &Mat<N>, v: &[f64; N]) -> [f64; N] {
    let mut y = [0.0; N];
    for i in 0..N {
        for j in 0..N {
            y[i] += a[i][j] * v[j];
        }
    }
    y
}

/// The identity.
pub fn identity<const N: usize>() -> Mat<N> {
    let mut m = [[0.0; N]; N];
    for (i, row) in m.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    m
}

fn norm1<const N: usize>(a: &Mat<N>) -> f64 {
    (0..N).map(|j| (0..N).map(|i| libm::fabs(a[i][j])).sum::<f64>()).fold(0.0, f64::max)
}

/// Exact ZOH discretisation over `t` seconds: returns `(Phi, Psi)` with `Phi = e^{A t}` and
/// `Psi = integral_0^t e^{A s} ds`, so that for an input held at `u` over the interval
/// `x(t) = Phi x(0) + Psi B u`.
///
/// Any finite `||A t||_1` terminates (scaling and squaring: at most about 1 100 squarings, for a norm near
/// `f64::MAX`); a non-finite entry of `A` or `t`, or a norm that overflows, gives NaN in every entry of both, for the
/// caller to refuse.
pub fn zoh<const N: usize>(a: &Mat<N>, t: f64) -> (Mat<N>, Mat<N>) {
    // (`norm1` alone would pass a NaN: `f64::max` ignores it.)
    if !((norm1(a) * libm::fabs(t)).is_finite() && a.iter().flatten().all(|x| x.is_finite())) {
        return ([[f64::NAN; N]; N], [[f64::NAN; N]; N]);
    }
    let (ab, d) = balance(a);
    let (phi, psi) = zoh_balanced(&ab, t);
    let unbalance = |m: Mat<N>| -> Mat<N> { core::array::from_fn(|i| core::array::from_fn(|j| m[i][j] * d[i] / d[j])) };
    (unbalance(phi), unbalance(psi))
}

/// Parlett-Reinsch balancing with powers of two: returns `A_b = D^-1 A D` and the diagonal of `D`.
#[allow(clippy::needless_range_loop)] // row i and column i are read together: indices say it best
fn balance<const N: usize>(a: &Mat<N>) -> (Mat<N>, [f64; N]) {
    let mut m = *a;
    let mut d = [1.0; N];
    for _ in 0..64 {
        let mut converged = true;
        for i in 0..N {
            let (mut c, mut r) = (0.0, 0.0);
            for j in 0..N {
                if j != i {
                    c += libm::fabs(m[j][i]);
                    r += libm::fabs(m[i][j]);
                }
            }
            // (An infinite sum of finite entries would never leave the loops below.)
            if c == 0.0 || r == 0.0 || !(c + r).is_finite() {
                continue;
            }
            let mut f = 1.0;
            let s = c + r;
            while c < r / 2.0 {
                c *= 2.0;
                r /= 2.0;
                f *= 2.0;
            }
            while c >= r * 2.0 {
                c /= 2.0;
                r *= 2.0;
                f /= 2.0;
            }
            if (c + r) < 0.95 * s {
                converged = false;
                d[i] *= f;
                for j in 0..N {
                    m[i][j] /= f;
                    m[j][i] *= f;
                }
            }
        }
        if converged {
            break;
        }
    }
    (m, d)
}

fn zoh_balanced<const N: usize>(a: &Mat<N>, t: f64) -> (Mat<N>, Mat<N>) {
    // Halve `h` until `||A h||_1 <= 1/2`. Counted by halving a float, not by `norm / 2^k` with an integer shift:
    // that overflowed past 63 halvings (`||A t|| > 2^62`) and, wrapped in a release build, never ended.
    let mut norm = norm1(a) * libm::fabs(t);
    let mut squarings = 0u32;
    let mut h = t;
    while norm > 0.5 {
        squarings += 1;
        norm *= 0.5;
        h *= 0.5;
    }
    // Taylor terms: term_k = (A h)^k / k!, Phi = sum term_k, Psi = h * sum term_k / (k + 1).
    let mut ah = *a;
    for row in ah.iter_mut() {
        for x in row.iter_mut() {
            *x *= h;
        }
    }
    let mut term = identity::<N>();
    let mut phi = identity::<N>();
    let mut psi = identity::<N>();
    for k in 1..30 {
        term = mat_mul(&term, &ah);
        let inv_k = 1.0 / k as f64;
        let mut small = true;
        for i in 0..N {
            for j in 0..N {
                term[i][j] *= inv_k;
                phi[i][j] += term[i][j];
                psi[i][j] += term[i][j] / (k as f64 + 1.0);
                if libm::fabs(term[i][j]) > 1e-18 * (1.0 + libm::fabs(phi[i][j])) {
                    small = false;
                }
            }
        }
        if small {
            break;
        }
    }
    for row in psi.iter_mut() {
        for x in row.iter_mut() {
            *x *= h;
        }
    }
    for _ in 0..squarings {
        let phi_psi = mat_mul(&phi, &psi);
        for i in 0..N {
            for j in 0..N {
                psi[i][j] += phi_psi[i][j];
            }
        }
        phi = mat_mul(&phi, &phi);
    }
    (phi, psi)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zoh_of_a_harmonic_oscillator_is_the_rotation() {
        // x1' = x2, x2' = -w^2 x1: Phi = [[cos wt, sin wt / w], [-w sin wt, cos wt]].
        let w = 2.0 * core::f64::consts::PI * 423.0;
        let t = 1e-4;
        let (phi, psi) = zoh(&[[0.0, 1.0], [-w * w, 0.0]], t);
        let (s, c) = (libm::sin(w * t), libm::cos(w * t));
        let expect = [[c, s / w], [-w * s, c]];
        for i in 0..2 {
            for j in 0..2 {
                // Balanced, ||A|| T = w T ~ 0.27: no squaring, a few ulps.
                let rel = (phi[i][j] - expect[i][j]).abs() / expect[i][j].abs();
                assert!(rel <= 1e-14, "Phi[{i}][{j}]: {rel:e}");
            }
        }
        // Psi [0, 1]' is the response to a unit step in x2': [(1 - cos)/w^2, sin/w].
        assert!((psi[0][1] / ((1.0 - c) / (w * w)) - 1.0).abs() < 1e-14);
        assert!((psi[1][1] / (s / w) - 1.0).abs() < 1e-14);
    }

    #[test]
    fn zoh_ends_for_any_finite_matrix_and_refuses_a_non_finite_one() {
        // A stage with a1 = 1e38 over 1e-4 s: ||A t|| ~ 1e34, 113 halvings (the integer count overflowed at 64 and
        // looped forever). Its poles, -1e38 and -a0 / a1 ~ -6e-32: the slow one integrates, the fast one is gone.
        let (phi, psi) = zoh(&[[0.0, 1.0], [-6e6, -1e38]], 1e-4);
        assert!(phi.iter().chain(psi.iter()).flatten().all(|x| x.is_finite()), "{phi:?} {psi:?}");
        assert_eq!(phi[0][0], 1.0);
        assert!((psi[0][0] - 1e-4).abs() <= 1e-4 * 1e-12, "{psi:?}");
        // Near the largest f64: ends, about 1 000 squarings.
        let (phi, _) = zoh(&[[-1e300]], 1e8);
        assert_eq!(phi[0][0], 0.0);
        let (phi, _) = zoh(&[[-1e300]], 1e9);
        assert!(phi[0][0].is_nan(), "the norm overflows");
        for bad in [f64::INFINITY, f64::NAN] {
            let (phi, psi) = zoh(&[[0.0, 1.0], [-6e6, -bad]], 1e-4);
            assert!(phi.iter().chain(psi.iter()).flatten().all(|x| x.is_nan()));
            let (phi, _) = zoh(&[[-1.0]], bad);
            assert!(phi[0][0].is_nan());
        }
    }

    /// `balance` is what `zoh` relies on: an exact similarity (`A_b[i][j] = A[i][j] d[j] / d[i]` to the bit, each
    /// `d[i]` a power of two), converged in Parlett and Reinsch's sense (for no state would a factor of 2 either way
    /// lower the sum of its off-diagonal row and column by 5 %), a state coupled one way or not at all left alone (no
    /// power of two evens a zero row with a non-zero column: tried, the loops never end), and a balanced matrix left
    /// as it is. The pre-filter's companion matrix (entries 1 to 5e9) comes out with a norm of 5.3e3.
    #[test]
    fn balancing_is_an_exact_power_of_two_similarity_that_evens_rows_and_columns() {
        let two_pi = 2.0 * core::f64::consts::PI;
        let (wc, wp, z) = (two_pi * 100.0, two_pi * 450.0, 0.1);
        let (d2, d1, d0) = (wc + 2.0 * z * wp, wp * wp + 2.0 * z * wp * wc, wc * wp * wp);
        let companion = [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-d0, -d1, -d2]];
        // The first state on its own: its off-diagonal row and column are zero.
        let decoupled = [[-1e3, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -6e6, -2e3]];
        // The first state drives the others but is not driven (its row is zero), and the other way round.
        let drives = [[-1e3, 0.0, 0.0], [5.0, 0.0, 1.0], [0.0, -6e6, -2e3]];
        let driven = [[-1e3, 5.0, 0.0], [0.0, 0.0, 1.0], [0.0, -6e6, -2e3]];
        let even = [[-1.0, 2.0, 0.0], [2.0, -1.0, 2.0], [0.0, 2.0, -1.0]];
        let cases = [
            ("companion", companion),
            ("decoupled", decoupled),
            ("drives", drives),
            ("driven", driven),
            ("even", even),
        ];
        for (name, a) in cases {
            let (ab, d) = balance(&a);
            for i in 0..3 {
                assert!(d[i] > 0.0 && libm::frexp(d[i]).0 == 0.5, "{name}: d[{i}] = {} is not a power of two", d[i]);
                for j in 0..3 {
                    assert_eq!(ab[i][j], a[i][j] * d[j] / d[i], "{name}: [{i}][{j}]");
                }
                let c: f64 = (0..3).filter(|&j| j != i).map(|j| ab[j][i].abs()).sum();
                let r: f64 = (0..3).filter(|&j| j != i).map(|j| ab[i][j].abs()).sum();
                for f in [2.0, 0.5].into_iter().filter(|_| c > 0.0 && r > 0.0) {
                    assert!(c * f + r / f >= 0.95 * (c + r), "{name}: state {i} not balanced: column {c}, row {r}");
                }
            }
            match name {
                "companion" => assert!(norm1(&ab) < 1e4 && norm1(&a) > 5e9, "{ab:?}"),
                "decoupled" | "drives" | "driven" => assert_eq!(d[0], 1.0, "{name}"),
                _ => assert_eq!(d, [1.0; 3]),
            }
        }
    }

    #[test]
    fn zoh_of_a_pure_integrator_is_exact() {
        let (phi, psi) = zoh(&[[0.0]], 0.25);
        assert_eq!(phi[0][0], 1.0);
        assert_eq!(psi[0][0], 0.25);
    }
}
