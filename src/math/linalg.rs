//! Dense linear systems: the one Gaussian-elimination solver of the crate
//! (Levenberg-Marquardt steps of the joint refit, the photodetector's
//! state-space steady state and DC gain), and the eigenvalues of a small
//! symmetric matrix (a CFAR training window's correlation) and the Cholesky
//! factor of a small positive definite one (drawing correlated training
//! windows). Small systems only (a few dozen unknowns): O(n³), no blocking.

/// Solves `a x = b` in place by Gaussian elimination with partial pivoting.
///
/// `a` is row-major `n × n` and is destroyed (left upper triangular); `x`
/// holds `b` on entry and the solution on return. A column whose largest
/// remaining magnitude is NaN, zero or below `min_pivot` makes the system
/// singular: the function returns `false` and leaves `a` and `x` part-way
/// reduced. Pass `0.0` to accept any nonzero pivot. Rows whose elimination
/// factor is zero are skipped. The solution is not checked for finiteness.
///
/// Panics if `a.len() < n * n` or `x.len() < n`.
pub fn solve_in_place(a: &mut [f64], x: &mut [f64], n: usize, min_pivot: f64) -> bool {
    for col in 0..n {
        let Some(piv) =
            (col..n).max_by(|&i, &j| a[i * n + col].abs().total_cmp(&a[j * n + col].abs()))
        else {
            return false;
        };
        let p = a[piv * n + col].abs();
        if !(p > 0.0) || p < min_pivot {
            return false;
        }
        if piv != col {
            for k in 0..n {
                a.swap(col * n + k, piv * n + k);
            }
            x.swap(col, piv);
        }
        for r in col + 1..n {
            let f = a[r * n + col] / a[col * n + col];
            if f == 0.0 {
                continue;
            }
            for k in col..n {
                a[r * n + k] -= f * a[col * n + k];
            }
            x[r] -= f * x[col];
        }
    }
    for col in (0..n).rev() {
        let mut v = x[col];
        for k in col + 1..n {
            v -= a[col * n + k] * x[k];
        }
        x[col] = v / a[col * n + col];
    }
    true
}

/// [`solve_in_place`] on copies: `a x = b` for row-major `n × n` `a`, or
/// `None` when singular (see there for `min_pivot`).
pub fn solve(a: &[f64], b: &[f64], n: usize, min_pivot: f64) -> Option<Vec<f64>> {
    let mut m = a[..n * n].to_vec();
    let mut x = b[..n].to_vec();
    solve_in_place(&mut m, &mut x, n, min_pivot).then_some(x)
}

/// Eigenvalues of the symmetric row-major `n × n` matrix `a` (only its
/// upper triangle is read), ascending, by cyclic Jacobi rotations until the
/// off-diagonal part is below 1e-15 of the matrix's norm (at most 64
/// sweeps; quadratic convergence makes that 6 to 10 for a few dozen rows).
///
/// Panics if `a.len() < n * n`.
pub fn symmetric_eigenvalues(a: &[f64], n: usize) -> Vec<f64> {
    let mut m = vec![0.0; n * n];
    for i in 0..n {
        for j in i..n {
            m[i * n + j] = a[i * n + j];
            m[j * n + i] = a[i * n + j];
        }
    }
    let norm2: f64 = m.iter().map(|v| v * v).sum();
    for _ in 0..64 {
        let off2: f64 = (0..n).flat_map(|i| (i + 1..n).map(move |j| (i, j))).map(|(i, j)| 2.0 * m[i * n + j] * m[i * n + j]).sum();
        if !(off2 > 1e-30 * norm2) {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = m[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                // The rotation that zeroes m[p][q] (Golub & Van Loan 8.5.2).
                let tau = (m[q * n + q] - m[p * n + p]) / (2.0 * apq);
                let sign = if tau >= 0.0 { 1.0 } else { -1.0 };
                let t = sign / (tau.abs() + (1.0 + tau * tau).sqrt());
                let c = 1.0 / (1.0 + t * t).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (mkp, mkq) = (m[k * n + p], m[k * n + q]);
                    m[k * n + p] = c * mkp - s * mkq;
                    m[k * n + q] = s * mkp + c * mkq;
                }
                for k in 0..n {
                    let (mpk, mqk) = (m[p * n + k], m[q * n + k]);
                    m[p * n + k] = c * mpk - s * mqk;
                    m[q * n + k] = s * mpk + c * mqk;
                }
            }
        }
    }
    let mut ev: Vec<f64> = (0..n).map(|i| m[i * n + i]).collect();
    ev.sort_by(f64::total_cmp);
    ev
}

/// Lower-triangular Cholesky factor `l` (row-major `n × n`, zeros above the
/// diagonal) with `l lᵀ = a` for the symmetric positive definite row-major
/// `a` (only its lower triangle is read), or `None` when a pivot is not
/// positive (not positive definite to working precision).
///
/// Panics if `a.len() < n * n`.
pub fn cholesky(a: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let dot: f64 = (0..j).map(|k| l[i * n + k] * l[j * n + k]).sum();
            let v = a[i * n + j] - dot;
            if i == j {
                if !(v > 0.0) {
                    return None;
                }
                l[i * n + i] = v.sqrt();
            } else {
                l[i * n + j] = v / l[j * n + j];
            }
        }
    }
    Some(l)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Naive reference: Cramer's rule with cofactor determinants (n ≤ 5).
    fn det(a: &[f64], n: usize) -> f64 {
        if n == 1 {
            return a[0];
        }
        (0..n)
            .map(|c| {
                let minor: Vec<f64> = (1..n)
                    .flat_map(|r| (0..n).filter(move |&k| k != c).map(move |k| (r, k)))
                    .map(|(r, k)| a[r * n + k])
                    .collect();
                let sign = if c % 2 == 0 { 1.0 } else { -1.0 };
                sign * a[c] * det(&minor, n - 1)
            })
            .sum()
    }

    #[test]
    fn matches_cramer_on_random_systems() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for n in 1..=5 {
            for _ in 0..50 {
                let a: Vec<f64> = (0..n * n).map(|_| rng.random_range(-1.0..1.0)).collect();
                let b: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
                let d = det(&a, n);
                if d.abs() < 1e-3 {
                    continue;
                }
                let x = solve(&a, &b, n, 0.0).expect("non-singular");
                for (i, xi) in x.iter().enumerate() {
                    let mut ai = a.clone();
                    for r in 0..n {
                        ai[r * n + i] = b[r];
                    }
                    let want = det(&ai, n) / d;
                    assert!(
                        (xi - want).abs() < 1e-9 * (1.0 + want.abs()),
                        "n={n} x{i}: {xi} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn needs_pivoting_and_detects_singular() {
        // Zero leading entry: only row exchange solves it.
        assert_eq!(
            solve(&[0.0, 1.0, 1.0, 0.0], &[2.0, 3.0], 2, 0.0),
            Some(vec![3.0, 2.0])
        );
        assert_eq!(solve(&[1.0, 2.0, 2.0, 4.0], &[1.0, 1.0], 2, 0.0), None);
        assert_eq!(solve(&[f64::NAN, 0.0, 0.0, 1.0], &[1.0, 1.0], 2, 0.0), None);
        // A tiny but nonzero pivot: accepted at 0, refused at 1e-300.
        assert!(solve(&[1e-310, 0.0, 0.0, 1.0], &[1.0, 1.0], 2, 0.0).is_some());
        assert_eq!(
            solve(&[1e-310, 0.0, 0.0, 1.0], &[1.0, 1.0], 2, 1e-300),
            None
        );
        assert_eq!(solve(&[], &[], 0, 0.0), Some(vec![]));
    }

    #[test]
    fn symmetric_eigenvalues_of_known_matrices() {
        // [[2, 1], [1, 2]]: 1 and 3.
        let ev = symmetric_eigenvalues(&[2.0, 1.0, 1.0, 2.0], 2);
        assert!((ev[0] - 1.0).abs() < 1e-14 && (ev[1] - 3.0).abs() < 1e-14, "{ev:?}");
        // The second-difference matrix tridiag(−1, 2, −1) of order n has
        // eigenvalues 2 − 2 cos(kπ/(n+1)), k = 1..n.
        let n = 20;
        let mut a = vec![0.0; n * n];
        for i in 0..n {
            a[i * n + i] = 2.0;
            if i + 1 < n {
                a[i * n + i + 1] = -1.0;
                a[(i + 1) * n + i] = -1.0;
            }
        }
        let ev = symmetric_eigenvalues(&a, n);
        for (k, v) in ev.iter().enumerate() {
            let want = 2.0 - 2.0 * ((k + 1) as f64 * std::f64::consts::PI / (n + 1) as f64).cos();
            assert!((v - want).abs() < 1e-12, "{k}: {v} vs {want}");
        }
        assert!(symmetric_eigenvalues(&[], 0).is_empty());
    }

    #[test]
    fn cholesky_reproduces_the_matrix_and_refuses_indefinite_ones() {
        // AR(1) correlation φ^|i−j|: l lᵀ = a, l lower triangular.
        let n: usize = 12;
        let a: Vec<f64> = (0..n * n).map(|k| 0.9f64.powi((k / n).abs_diff(k % n) as i32)).collect();
        let l = cholesky(&a, n).expect("positive definite");
        for i in 0..n {
            for j in 0..n {
                let v: f64 = (0..n).map(|k| l[i * n + k] * l[j * n + k]).sum();
                assert!((v - a[i * n + j]).abs() < 1e-13, "({i}, {j}): {v}");
                if j > i {
                    assert_eq!(l[i * n + j], 0.0);
                }
            }
        }
        assert_eq!(cholesky(&[1.0, 2.0, 2.0, 1.0], 2), None);
        assert_eq!(cholesky(&[f64::NAN], 1), None);
    }
}
