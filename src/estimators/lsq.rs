//! Batch and exponentially weighted least squares (textbook sections 13.2-13.4), solved by a streaming QR
//! factorisation: never the normal equations' explicit inverse.
//!
//! Minimises `J = sum_k w_k (y_k - d_k' theta)^2` with the textbook's exponential weights `w_k = a gamma^(N-k)`
//! (eq. 13.4.2; `a = gamma = 1` is ordinary least squares, eq. 13.3.16).
//!
//! ## Method
//! The weighted data `sqrt(w_k) [d_k' | y_k]` are reduced row by row with Givens rotations to an upper-triangular
//! `[R | z]` and a residual `e` such that `R'R = D'WD`, `R'z = D'Wy` and `e^2 = min J`. Forgetting (`gamma`) scales
//! `[R | z | e]` by `sqrt(gamma)` before each new row. The estimate is the back substitution `R theta = z`. Rows are
//! not stored, so the same object accumulates a fit of any length, on the host or on the board (the discrete RLS
//! is initialised from it). The condition number enters once, not squared as with the normal equations: Example
//! 13.3's `D'D` has condition 2.7e4, which in f32 normal equations already moves the third digit.
//!
//! ## Rank
//! Column `j` is (nearly) dependent on the columns before it when the part of it that they cannot explain,
//! `|R_jj|`, is below `sqrt(eps) / 10` of its weighted norm (for f64, 1.5e-9: a condition number beyond ~1e9).
//! That norm is the norm of `R`'s column `j` (the rotations keep it), taken by `hypot`: a running sum of squares
//! of the data overflowed for entries beyond about 1e154 (f64) or 1e19 (f32) and called every column dependent.
//! [`WeightedLs::solve`] then returns [`RankDeficient`] with that column and the earlier columns it combines,
//! `R[..j, ..j] c = R[..j, j]`, rather than numbers. Capacity: `MAX` parameters (a const generic, no allocation).
//!
//! Cost per row: `n (n + 3) / 2` rotations' worth of work (about `2 n^2` multiplies) and `n` square roots.

#![allow(clippy::needless_range_loop)] // triangular-matrix loops read best with the indices of the algebra

use crate::Real;

/// A weighted least-squares problem being accumulated.
#[derive(Clone, Debug)]
pub struct WeightedLs<T, const MAX: usize> {
    n: usize,
    r: [[T; MAX]; MAX],
    z: [T; MAX],
    e2: T,
    rows: u64,
}

/// The solution.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LsSolution<T, const MAX: usize> {
    /// Parameters (the first `n` entries are used).
    pub theta: [T; MAX],
    /// Number of parameters.
    pub n: usize,
    /// Weighted sum of squared residuals at the optimum.
    pub sse: T,
    /// Rows accumulated.
    pub rows: u64,
}

/// Column `column` is (nearly) a combination of the earlier columns flagged in `combines`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RankDeficient {
    /// The dependent column (0-based).
    pub column: usize,
    /// Bit `i` set: earlier column `i` takes part in the combination (0 if the column is (nearly) zero).
    pub combines: u64,
    /// `|R_jj|` over the column's weighted norm: how independent it is (0: exactly dependent).
    pub independence: f64,
}

/// Why a fit has no solution.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LsError {
    /// Fewer rows than parameters.
    TooFewRows {
        /// Rows accumulated.
        rows: u64,
        /// Parameters.
        parameters: usize,
    },
    /// The columns are (nearly) linearly dependent.
    RankDeficient(RankDeficient),
}

impl<T: Real, const MAX: usize> WeightedLs<T, MAX> {
    /// An empty problem with `n <= MAX` parameters.
    pub fn new(n: usize) -> Self {
        assert!(n <= MAX && n <= 64, "at most MAX (and 64) parameters");
        WeightedLs { n, r: [[T::zero(); MAX]; MAX], z: [T::zero(); MAX], e2: T::zero(), rows: 0 }
    }

    /// Number of parameters.
    pub fn parameters(&self) -> usize {
        self.n
    }

    /// Rows accumulated.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// Discount everything accumulated so far by `gamma` (the textbook's exponential weighting, applied before
    /// each new row).
    pub fn forget(&mut self, gamma: T) {
        let s = gamma.sqrt();
        for i in 0..self.n {
            for x in self.r[i][i..self.n].iter_mut() {
                *x *= s;
            }
            self.z[i] *= s;
        }
        self.e2 *= gamma;
    }

    /// Add the row `y = d' theta` with weight `weight` (`d.len()` must be the number of parameters).
    pub fn add_row(&mut self, d: &[T], y: T, weight: T) {
        debug_assert_eq!(d.len(), self.n);
        let s = weight.sqrt();
        let mut row = [T::zero(); MAX];
        for (rj, dj) in row.iter_mut().zip(d.iter()) {
            *rj = s * *dj;
        }
        let mut rhs = s * y;
        for j in 0..self.n {
            let (a, b) = (self.r[j][j], row[j]);
            if b == T::zero() {
                continue;
            }
            let h = a.hypot(b);
            let (c, sn) = (a / h, b / h);
            self.r[j][j] = h;
            for k in j + 1..self.n {
                let (rk, xk) = (self.r[j][k], row[k]);
                self.r[j][k] = c * rk + sn * xk;
                row[k] = c * xk - sn * rk;
            }
            let zj = self.z[j];
            self.z[j] = c * zj + sn * rhs;
            rhs = c * rhs - sn * zj;
        }
        self.e2 += rhs * rhs;
        self.rows += 1;
    }

    /// The upper-triangular factor `R` (`R'R = D'WD`), row-major, for the first `n` rows and columns.
    pub fn r_factor(&self) -> &[[T; MAX]; MAX] {
        &self.r
    }

    /// Solve, or say why not.
    pub fn solve(&self) -> Result<LsSolution<T, MAX>, LsError> {
        let n = self.n;
        if self.rows < n as u64 {
            return Err(LsError::TooFewRows { rows: self.rows, parameters: n });
        }
        let tol = T::epsilon().sqrt() * T::of(0.1);
        for j in 0..n {
            // The weighted column's norm: `Q` is orthogonal, so it is that of `R`'s column.
            let norm = self.r[..=j].iter().fold(T::zero(), |acc, row| acc.hypot(row[j]));
            let rjj = self.r[j][j].abs();
            if rjj <= tol * norm || rjj.is_nan() {
                // Which earlier columns explain it: R[..j, ..j] c = R[..j, j].
                let mut c = [T::zero(); MAX];
                for i in (0..j).rev() {
                    let mut acc = self.r[i][j];
                    for k in i + 1..j {
                        acc -= self.r[i][k] * c[k];
                    }
                    c[i] = acc / self.r[i][i];
                }
                let biggest = c[..j].iter().fold(T::zero(), |m, x| m.max(x.abs()));
                let mut combines = 0u64;
                for (i, ci) in c[..j].iter().enumerate() {
                    if biggest > T::zero() && ci.abs() > biggest * T::of(1e-6) {
                        combines |= 1 << i;
                    }
                }
                let independence = if norm > T::zero() { (rjj / norm).as_f64() } else { 0.0 };
                return Err(LsError::RankDeficient(RankDeficient { column: j, combines, independence }));
            }
        }
        let mut theta = [T::zero(); MAX];
        for i in (0..n).rev() {
            let mut acc = self.z[i];
            for k in i + 1..n {
                acc -= self.r[i][k] * theta[k];
            }
            theta[i] = acc / self.r[i][i];
        }
        Ok(LsSolution { theta, n, sse: self.e2, rows: self.rows })
    }
}

/// Least squares of `y = D theta` in one call: rows `d[k]`, targets `y[k]`, weights `a gamma^(N-k)`.
pub fn weighted_fit<T: Real, const MAX: usize>(
    d: &[&[T]],
    y: &[T],
    a: T,
    gamma: T,
) -> Result<LsSolution<T, MAX>, LsError> {
    let n = d.first().map_or(0, |r| r.len());
    let mut ls = WeightedLs::<T, MAX>::new(n);
    for (row, &yk) in d.iter().zip(y) {
        ls.forget(gamma);
        ls.add_row(row, yk, a);
    }
    ls.solve()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn example_13_2_line_through_three_points() {
        // (0, 1), (2, 2), (4, 4): y = m x + b.
        let rows: [&[f64]; 3] = [&[0.0, 1.0], &[2.0, 1.0], &[4.0, 1.0]];
        let s = weighted_fit::<f64, 4>(&rows, &[1.0, 2.0, 4.0], 1.0, 1.0).unwrap();
        assert!((s.theta[0] - 0.75).abs() < 1e-15 && (s.theta[1] - 5.0 / 6.0).abs() < 1e-15);
        // SSE: residuals (1 - 5/6, 2 - 7/3, 4 - 23/6) = (1/6, -1/3, 1/6): 1/6.
        assert!((s.sse - 1.0 / 6.0).abs() < 1e-15);
    }

    #[test]
    fn a_repeated_column_is_named_not_solved() {
        let rows: [&[f64]; 3] = [&[1.0, 2.0, 2.0], &[3.0, 1.0, 1.0], &[0.5, 4.0, 4.0]];
        let err = weighted_fit::<f64, 4>(&rows, &[1.0, 2.0, 3.0], 1.0, 1.0).unwrap_err();
        match err {
            LsError::RankDeficient(r) => {
                assert_eq!(r.column, 2);
                assert_eq!(r.combines, 0b10, "column 2 equals column 1");
                assert!(r.independence < 1e-12);
            }
            e => panic!("{e:?}"),
        }
        assert_eq!(
            weighted_fit::<f64, 4>(&rows[..2], &[1.0, 2.0], 1.0, 1.0).unwrap_err(),
            LsError::TooFewRows { rows: 2, parameters: 3 }
        );
    }

    /// The rank test is relative to each column's weighted norm: column 2 is column 1 plus `eps` times a direction
    /// orthogonal to it (`[1, -1, 1, -1]` against `[1, 1, 1, 1]`), so its independence `|R_22| / |column 2|` is `eps`.
    /// At `eps = 1e-8` (a condition number near 1e8) the fit solves, at `1e-10` it names the column with that
    /// independence; the same at every scale of the data. A zero column is named with independence 0.
    #[test]
    fn the_rank_test_is_relative_to_each_columns_norm() {
        let fit = |eps: f64, scale: f64| {
            let mut ls = WeightedLs::<f64, 4>::new(2);
            for k in 0..4 {
                let z = if k % 2 == 0 { 1.0 } else { -1.0 };
                ls.add_row(&[scale, scale * (1.0 + eps * z)], scale * k as f64, 1.0);
            }
            assert_eq!(ls.rows(), 4);
            ls.solve()
        };
        for scale in [1.0, 1e6, 1e-6] {
            let s = fit(1e-8, scale).unwrap_or_else(|e| panic!("scale {scale}: {e:?}"));
            assert_eq!(s.rows, 4);
            match fit(1e-10, scale) {
                Err(LsError::RankDeficient(r)) => {
                    assert_eq!((r.column, r.combines), (1, 0b1), "scale {scale}");
                    assert!((r.independence / 1e-10 - 1.0).abs() < 1e-4, "scale {scale}: {}", r.independence);
                }
                other => panic!("scale {scale}: {other:?}"),
            }
        }
        let mut ls = WeightedLs::<f64, 4>::new(2);
        for k in 0..3 {
            ls.add_row(&[1.0 + k as f64, 0.0], 1.0, 1.0);
        }
        assert_eq!(
            ls.solve(),
            Err(LsError::RankDeficient(RankDeficient { column: 1, combines: 0, independence: 0.0 }))
        );
    }

    #[test]
    fn forgetting_equals_explicit_weights() {
        // gamma-forgetting row by row == each row weighted a gamma^(N-k) from the start.
        let rows: [&[f64]; 5] = [&[1.0, 0.2], &[0.3, 1.0], &[2.0, -1.0], &[0.7, 0.7], &[-1.0, 0.5]];
        let y = [1.0, 0.5, -0.2, 0.9, 0.1];
        let a = 0.2;
        let g: f64 = 0.8;
        let streamed = weighted_fit::<f64, 4>(&rows, &y, a, g).unwrap();
        let mut explicit = WeightedLs::<f64, 4>::new(2);
        for (k, (r, &yk)) in rows.iter().zip(&y).enumerate() {
            explicit.add_row(r, yk, a * g.powi((rows.len() - 1 - k) as i32));
        }
        let e = explicit.solve().unwrap();
        for i in 0..2 {
            assert!((streamed.theta[i] - e.theta[i]).abs() < 1e-14);
        }
        assert!((streamed.sse - e.sse).abs() < 1e-15);
    }
}
