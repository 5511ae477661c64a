//! The least-squares family against the textbook's worked examples (chapter 13) and the lecture notes' forms,
//! with the float64 reference's values (`../shared/golden/textbook-reference.json`, copied where used).
#![allow(clippy::needless_range_loop, clippy::type_complexity)] // tests index parallel arrays by parameter

use nanopos_id::estimators::lsq::{weighted_fit, LsError, WeightedLs};
use nanopos_id::estimators::rls::{DiscreteRls, RlsGain};

/// Table 13.1: thermal system, unit step at k = 0, T = 0.25 s; y(0..=20).
const Y: [f64; 21] = [
    0.0, 0.01953, 0.07567, 0.14890, 0.22945, 0.31001, 0.39300, 0.47111, 0.54922, 0.62245, 0.69324, 0.76159, 0.82750,
    0.89096, 0.95199, 1.00812, 1.06427, 1.11553, 1.16435, 1.21561, 1.26199,
];

fn u(k: i64) -> f64 {
    if k >= 0 {
        1.0
    } else {
        0.0
    }
}

fn y(k: i64) -> f64 {
    if k >= 0 {
        Y[k as usize]
    } else {
        0.0
    }
}

/// Regressor of Example 13.3: d(k) = [y(k-1), y(k-2), u(k-1), u(k-2)], signals zero before k = 0.
fn d(k: i64) -> [f64; 4] {
    [y(k - 1), y(k - 2), u(k - 1), u(k - 2)]
}

#[test]
fn example_13_3_exact_optimum_and_the_books_low_precision_digits() {
    let rows: Vec<[f64; 4]> = (1..=20).map(d).collect();
    let refs: Vec<&[f64]> = rows.iter().map(|r| &r[..]).collect();
    let targets: Vec<f64> = (1..=20).map(y).collect();
    let s = weighted_fit::<f64, 8>(&refs, &targets, 1.0, 1.0).unwrap();
    // Reference optimum (QR and normal equations agree to 3e-13 there; cond(D'D) = 2.7e4).
    let exact = [1.4706942596816603, -0.4908359715216343, 0.01952999999999714, 0.027723581792437734];
    for i in 0..4 {
        assert!((s.theta[i] - exact[i]).abs() < 1e-10, "theta[{i}] = {}", s.theta[i]);
    }
    assert!((s.sse / 4.596675770259521e-05 - 1.0).abs() < 1e-8, "sse {}", s.sse);
    // The book prints [1.47023, -0.49018, 0.01953, 0.02776] with J = 4.63e-5: a low-precision solution of the same
    // problem. Evaluated on these rows, the book's theta gives exactly the book's J (reference: 4.63489e-5) ...
    let book = [1.47023, -0.49018, 0.01953, 0.02776];
    let sse_book: f64 = (1..=20)
        .map(|k| {
            let r = d(k);
            (y(k) - (0..4).map(|i| book[i] * r[i]).sum::<f64>()).powi(2)
        })
        .sum();
    assert!((sse_book / 4.634890556533664e-05 - 1.0).abs() < 1e-6, "{sse_book}");
    assert!((sse_book - 4.63e-5).abs() < 0.005e-5);
    // ... and its digits match the optimum to 5e-4 in a1, b1 and b0. Not in a0: |-0.4908360 - (-0.49018)| = 6.6e-4
    // (the reference's relative difference, 1.34e-3, says the same), so a0 is held to what it is, 7e-4.
    for (i, tol) in [(0, 5e-4), (1, 7e-4), (2, 5e-4), (3, 5e-4)] {
        assert!((s.theta[i] - book[i]).abs() < tol, "theta[{i}]");
    }
}

#[test]
fn example_13_3_with_full_history_rows_is_rank_deficient_in_the_input_columns() {
    // From k = 2 on, u(k-1) = u(k-2) = 1 in every row: the two input columns are the same.
    let rows: Vec<[f64; 4]> = (2..=20).map(d).collect();
    let refs: Vec<&[f64]> = rows.iter().map(|r| &r[..]).collect();
    let targets: Vec<f64> = (2..=20).map(y).collect();
    match weighted_fit::<f64, 8>(&refs, &targets, 1.0, 1.0).unwrap_err() {
        LsError::RankDeficient(r) => {
            assert_eq!(r.column, 3, "u(k-2)");
            assert_eq!(r.combines, 1 << 2, "equals u(k-1)");
        }
        e => panic!("{e:?}"),
    }
}

const THETA0: [f64; 4] = [1.0, -0.5, 0.02, 0.02];

fn run_example_13_4(gain: RlsGain<f64>) -> (DiscreteRls<f64, 4>, Vec<[f64; 4]>, Vec<(f64, f64)>) {
    let mut rls = DiscreteRls::new(THETA0, [1e4; 4]);
    let mut history = vec![*rls.theta()];
    let mut errors = Vec::new();
    for k in 1..=20 {
        let e = rls.update(&gain, &d(k), y(k));
        history.push(*rls.theta());
        errors.push((e.a_priori, e.a_posteriori));
    }
    (rls, history, errors)
}

#[test]
fn example_13_4_recursive_history_matches_the_reference() {
    let (rls, history, errors) = run_example_13_4(RlsGain::textbook(0.2, 0.8));
    let final_ref = [1.3800931705451007, -0.4030818744726914, 0.019536406201148868, 0.035551909073228666];
    for i in 0..4 {
        assert!((rls.theta()[i] - final_ref[i]).abs() < 1e-10, "theta[{i}]");
    }
    // Selected rows of the reference history (estimate after y(j)).
    let ref_rows: [(usize, [f64; 4]); 3] = [
        (2, [1.0003240327851708, -0.5, 0.019536821887428762, 0.036591540459329865]),
        (3, [1.3670036516436574, -0.37240495905428117, 0.0195347959159746, 0.03152458585246745]),
        (15, [1.460865838051074, -0.4823617103871706, 0.01953382982248982, 0.029108386047043605]),
    ];
    for (j, row) in ref_rows {
        for i in 0..4 {
            assert!((history[j][i] - row[i]).abs() < 1e-10, "history[{j}][{i}]");
        }
    }
    // First a priori errors of the reference.
    assert!((errors[0].0 - -0.00047000000000000167).abs() < 1e-15);
    assert!((errors[1].0 - 0.016609812075169927).abs() < 1e-12);
    // Final P (= F) of the reference, relative to its largest entry.
    let p_ref = [
        [34716.909218974295, -33680.58704246447, -1.1836132765833864, -2960.216804767462],
        [-33680.58704246446, 32691.899626963026, 1.141951232765005, 2856.0200331786687],
        [-1.1836132765919343, 1.1419512327738777, 346.6674042213374, -346.5600308625213],
        [-2960.216804767495, 2856.020033178691, -346.560030862522, 615.1008012621671],
    ];
    let f = rls.covariance();
    for i in 0..4 {
        for j in 0..4 {
            assert!((f[i][j] - p_ref[i][j]).abs() < 1e-7 * 34716.9, "F[{i}][{j}] = {} vs {}", f[i][j], p_ref[i][j]);
        }
    }
}

#[test]
fn example_13_4_equals_the_closed_form_prior_regularised_weighted_least_squares() {
    // The recursion minimises gamma^N (theta - theta0)' P0^-1 (theta - theta0) + sum a gamma^(N-k) e_k^2:
    // pose the prior as four rows sqrt(1e-4) e_i = sqrt(1e-4) theta0_i, discounted like the data.
    let (rls, _, _) = run_example_13_4(RlsGain::textbook(0.2, 0.8));
    let mut ls = WeightedLs::<f64, 8>::new(4);
    for i in 0..4 {
        let mut row = [0.0; 4];
        row[i] = 1.0;
        ls.add_row(&row, THETA0[i], 1e-4);
    }
    for k in 1..=20 {
        ls.forget(0.8);
        ls.add_row(&d(k), y(k), 0.2);
    }
    let closed = ls.solve().unwrap();
    for i in 0..4 {
        // Reference: max relative difference 3e-11 (the recursion's rounding over 20 steps of a cond-3e4 problem).
        assert!((rls.theta()[i] / closed.theta[i] - 1.0).abs() < 1e-9, "theta[{i}]");
    }
}

#[test]
fn lecture_forgetting_forms_match_the_reference_and_errors_obey_eq_13() {
    // Lecture eq. 16 + 11 (lambda1 = lambda, lambda2 = 1) from the same start, final estimates of the reference.
    let cases = [
        (1.0, [1.4598276919896462, -0.48006957486018165, 0.019530894654414988, 0.028477438807579657]),
        (0.95, [1.4583665642332462, -0.4787447337058125, 0.01953086704076061, 0.02865761189471801]),
        (0.8, [1.3898174737767834, -0.4125147684868234, 0.019531215626175817, 0.03472654281280418]),
    ];
    for (lambda, final_ref) in cases {
        let gain = RlsGain::forgetting(lambda, f64::INFINITY);
        let (rls, history, errors) = run_example_13_4(gain);
        for i in 0..4 {
            assert!((rls.theta()[i] - final_ref[i]).abs() < 1e-10, "lambda {lambda}: theta[{i}]");
        }
        for (k, &(prior, post)) in errors.iter().enumerate() {
            // |a posteriori| <= |a priori|, and the a posteriori error is the residual of the updated estimate.
            assert!(post.abs() <= prior.abs(), "step {k}");
            let dk = d(k as i64 + 1);
            let direct = y(k as i64 + 1) - (0..4).map(|i| history[k + 1][i] * dk[i]).sum::<f64>();
            assert!((post - direct).abs() < 1e-12, "step {k}: {post} vs {direct}");
        }
    }
}

#[test]
fn constant_gain_row_leaves_f_and_theta_alone_as_lambda2_vanishes() {
    let (rls, history, _) = run_example_13_4(RlsGain::new(1.0, 0.0, f64::INFINITY));
    assert_eq!(rls.covariance()[0][0], 1e4);
    assert_eq!(rls.covariance()[0][1], 0.0);
    assert_eq!(history.last().unwrap(), &THETA0);
    // lambda2 = 1e-12: F moves by at most ~ lambda2 phi'F phi F (reference: 2e-3 of 1e4), theta by ~1e-7.
    let (rls, _, _) = run_example_13_4(RlsGain::new(1.0, 1e-12, f64::INFINITY));
    let f = rls.covariance();
    for i in 0..4 {
        assert!((f[i][i] - 1e4).abs() < 3e-3);
        assert!((rls.theta()[i] - THETA0[i]).abs() < 1e-6);
    }
}

#[test]
fn rls_initialised_from_a_batch_solve_continues_as_the_batch_would() {
    // Batch over rows 1..=10, then RLS over 11..=20 == batch over all 20 rows (ordinary least squares).
    let mut ls = WeightedLs::<f64, 8>::new(4);
    for k in 1..=10 {
        ls.add_row(&d(k), y(k), 1.0);
    }
    let mut rls = DiscreteRls::<f64, 4>::from_batch(&ls).unwrap();
    let ls_f = {
        // F(k0) = (D'D)^-1: check F (D'D) = I through the accumulated rows.
        let f = rls.covariance();
        let mut dtd = [[0.0; 4]; 4];
        for k in 1..=10 {
            let r = d(k);
            for i in 0..4 {
                for j in 0..4 {
                    dtd[i][j] += r[i] * r[j];
                }
            }
        }
        let mut worst = 0.0f64;
        for i in 0..4 {
            for j in 0..4 {
                let p: f64 = (0..4).map(|m| f[i][m] * dtd[m][j]).sum();
                worst = worst.max((p - if i == j { 1.0 } else { 0.0 }).abs());
            }
        }
        worst
    };
    // cond(D'D) over 10 rows is ~1e7: F D'D = I to ~1e-9.
    assert!(ls_f < 1e-8, "{ls_f}");
    for k in 11..=20 {
        rls.update(&RlsGain::least_squares(), &d(k), y(k));
    }
    let exact = [1.4706942596816603, -0.4908359715216343, 0.01952999999999714, 0.027723581792437734];
    for i in 0..4 {
        assert!((rls.theta()[i] - exact[i]).abs() < 1e-8, "theta[{i}] = {}", rls.theta()[i]);
    }
}

#[test]
fn ud_form_equals_the_lectures_plain_covariance_form_step_by_step() {
    // Lecture eq. 17 as printed, in the covariance form F (independent of the UD code), lambda1 = gamma = 0.8,
    // lambda2 = a = 0.2: theta += F(k+1) phi lambda2 eps0 with F(k+1) = (F - F phi phi'F / (l1/l2 + phi'F phi)) / l1.
    let (l1, l2) = (0.8, 0.2);
    let mut f = [[0.0; 4]; 4];
    for i in 0..4 {
        f[i][i] = 1e4;
    }
    let mut theta = THETA0;
    let (_, ud_history, _) = run_example_13_4(RlsGain::textbook(0.2, 0.8));
    for k in 1..=20 {
        let phi = d(k);
        let eps0 = y(k) - (0..4).map(|i| theta[i] * phi[i]).sum::<f64>();
        let fphi: Vec<f64> = (0..4).map(|i| (0..4).map(|j| f[i][j] * phi[j]).sum()).collect();
        let phifphi: f64 = (0..4).map(|i| phi[i] * fphi[i]).sum();
        let denom = l1 / l2 + phifphi;
        for i in 0..4 {
            for j in 0..4 {
                f[i][j] = (f[i][j] - fphi[i] * fphi[j] / denom) / l1;
            }
        }
        for i in 0..4 {
            theta[i] += (0..4).map(|j| f[i][j] * phi[j]).sum::<f64>() * l2 * eps0;
        }
        for i in 0..4 {
            // The two forms round differently on a cond-3e4 problem: agreement to ~1e-12 (reference: 6e-13).
            assert!((theta[i] - ud_history[k as usize][i]).abs() < 1e-10, "step {k}, theta[{i}]");
        }
    }
}
