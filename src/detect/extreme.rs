//! Maxima of stationary Gaussian sequences: thresholds for a per-report pfa.
//!
//! A detector compares every cell of the range gate with one threshold; the
//! scene specifies the false-alarm probability *per report* (P(any of the n
//! cells exceeds u)). For white noise that is `1 − (1 − Q(u))^n`. A matched
//! filter's output is correlated between neighbouring cells, so exceedances
//! come in clumps and the same u gives fewer false reports than the
//! independent-cell formula claims (the threshold it gives is too high).
//!
//! Approximation (discrete up-crossings, first-order Markov / Poisson
//! clumping): a false report happens if the first cell exceeds u or an
//! up-crossing (X_k ≤ u < X_{k+1}) occurs anywhere, and those are treated as
//! independent rare events:
//!
//! ```text
//! P(max > u) ≈ 1 − (1 − Q(u)) · (1 − p_up(u)/(1 − Q(u)))^(n−1),
//! p_up(u) = P(X_k ≤ u, X_{k+1} > u) = Q(u) − P(X_k > u, X_{k+1} > u) = 2 T(u, a),
//! a = √((1 − ρ₁)/(1 + ρ₁)),
//! ```
//!
//! with Owen's T function (the bivariate-normal orthant identity
//! L(h, h; ρ) = Q(h) − 2T(h, a)). p_up/(1 − Q) is the first-order Markov
//! transition probability P(X_{k+1} > u | X_k ≤ u) (the often-quoted form
//! with p_up alone differs by the factor 1/(1 − Q), negligible in the tail
//! but not exact for white noise). For ρ₁ = 0, p_up = Q(1 − Q) and the
//! formula is exact; as ρ₁ → 1, p_up → 0 and P → Q(u) (one effective cell).
//! It counts clumps by their first up-crossing, so it is accurate when an
//! excursion above u rarely dips below and re-crosses within one clump —
//! true at the thresholds of interest for smooth (low-pass) correlation; the
//! Monte-Carlo tests in `tests/suite/numerics.rs` check it for white noise and for
//! a 26-tap Gaussian-kernel moving average (ρ₁ = 0.985).
//!
//! T is evaluated as `T(h, a) = φ(h)/√(2π) · ∫₀^{atan a} exp(−h² tan²θ / 2) dθ`
//! (composite Simpson on the finite θ interval, cut where the integrand is
//! below e⁻⁵⁰), and the whole probability is carried in logarithms, so
//! u up to ~38 (p_report down to 1e-300 with n = 1e9) stays accurate.

use crate::math::special::{ln_phi, ln_q, ln_q_inv, q};

const LN_SQRT_2PI: f64 = 0.918_938_533_204_672_8;
/// Simpson intervals for the Owen's T integral (even).
const SIMPSON_INTERVALS: usize = 1024;

/// A threshold for a per-report false-alarm probability.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReportThreshold {
    /// Threshold in units of the noise sigma above the mean.
    pub u: f64,
    /// Per-cell false-alarm probability Q(u).
    pub p_cell: f64,
    /// Effectively independent cells: log1p(-P) / log1p(-p_cell).
    pub cells_effective: f64,
}

/// tan θ at the Simpson nodes of [0, `upper`] (θ = i·upper/intervals; the
/// last node is `upper` itself), as [`ln_owen_integral`] evaluates them: one
/// threshold solve evaluates the integral at every step of its root search
/// on the same interval (the lag-1 correlation sets it), so the tangents are
/// taken once per solve instead of once per step (the same values: the
/// integral is bit for bit the same).
struct TanGrid {
    upper: f64,
    tan: [f64; SIMPSON_INTERVALS + 1],
}

impl TanGrid {
    fn new(upper: f64) -> TanGrid {
        let step = upper / SIMPSON_INTERVALS as f64;
        let mut tan = [0.0; SIMPSON_INTERVALS + 1];
        tan[0] = 0.0f64.tan();
        for (i, t) in tan.iter_mut().enumerate().take(SIMPSON_INTERVALS).skip(1) {
            *t = (i as f64 * step).tan();
        }
        tan[SIMPSON_INTERVALS] = upper.tan();
        TanGrid { upper, tan }
    }

    /// The grid for the integral of [`ln_upcrossing_prob`] at `rho1` when
    /// it is not cut short by h (None where it is empty).
    fn for_rho1(rho1: f64) -> Option<TanGrid> {
        let rho = rho1.clamp(-1.0, 1.0);
        if !(rho < 1.0) {
            return None;
        }
        let theta_max = ((1.0 - rho) / (1.0 + rho)).sqrt().atan();
        (theta_max > 0.0).then(|| TanGrid::new(theta_max))
    }
}

/// ln ∫₀^{atan a} exp(−h² tan²θ/2) dθ for h ≥ 0, a ≥ 0 (a = ∞ allowed).
fn ln_owen_integral(h: f64, a: f64, grid: Option<&TanGrid>) -> f64 {
    let theta_max = a.atan();
    if theta_max <= 0.0 {
        return f64::NEG_INFINITY;
    }
    // Beyond tan θ = 10/h the integrand is below e^-50 of its value at 0.
    let upper = if h > 0.0 {
        theta_max.min((10.0 / h).atan())
    } else {
        theta_max
    };
    let hh = 0.5 * h * h;
    let step = upper / SIMPSON_INTERVALS as f64;
    if let Some(g) = grid.filter(|g| g.upper.to_bits() == upper.to_bits()) {
        let f = |tt: f64| (-hh * tt * tt).exp();
        let mut sum = f(g.tan[0]) + f(g.tan[SIMPSON_INTERVALS]);
        for i in 1..SIMPSON_INTERVALS {
            let w = if i % 2 == 1 { 4.0 } else { 2.0 };
            sum += w * f(g.tan[i]);
        }
        return (sum * step / 3.0).ln();
    }
    let f = |t: f64| {
        let tt = t.tan();
        (-hh * tt * tt).exp()
    };
    let mut sum = f(0.0) + f(upper);
    for i in 1..SIMPSON_INTERVALS {
        let w = if i % 2 == 1 { 4.0 } else { 2.0 };
        sum += w * f(i as f64 * step);
    }
    (sum * step / 3.0).ln()
}

/// ln p_up(u) = ln P(X_k ≤ u, X_{k+1} > u) for a standard bivariate normal
/// pair with correlation `rho1`, u ≥ 0.
pub fn ln_upcrossing_prob(u: f64, rho1: f64) -> f64 {
    ln_upcrossing_prob_on(u, rho1, None)
}

/// [`ln_upcrossing_prob`] with the integral's tangents from `grid` where it
/// covers the interval.
fn ln_upcrossing_prob_on(u: f64, rho1: f64, grid: Option<&TanGrid>) -> f64 {
    let rho = rho1.clamp(-1.0, 1.0);
    if rho >= 1.0 {
        return f64::NEG_INFINITY;
    }
    let a = ((1.0 - rho) / (1.0 + rho)).sqrt(); // +∞ at ρ = −1: θ_max = π/2
    let h = u.abs();
    // 2 T(h, a) = 2 φ(h)/√(2π) · I; for u < 0 use T(−h, a) = T(h, a).
    std::f64::consts::LN_2 + ln_phi(h) - LN_SQRT_2PI + ln_owen_integral(h, a, grid)
}

/// ln P(max of `n` cells > u) under the up-crossing approximation.
pub fn ln_max_exceed_prob(u: f64, n: usize, rho1: f64) -> f64 {
    ln_max_exceed_prob_on(u, n, rho1, None)
}

/// [`ln_max_exceed_prob`] with the tangents of [`ln_upcrossing_prob_on`].
fn ln_max_exceed_prob_on(u: f64, n: usize, rho1: f64, grid: Option<&TanGrid>) -> f64 {
    if u.is_nan() || rho1.is_nan() {
        return f64::NAN;
    }
    let n = n.max(1) as f64;
    let lq = ln_q(u);
    if n <= 1.0 {
        return lq;
    }
    let qv = lq.exp();
    // transition probability P(X_{k+1} > u | X_k ≤ u) = p_up / (1 − Q)
    let lup = ln_upcrossing_prob_on(u, rho1, grid) - (-qv).ln_1p();
    // p_tr/Q ≤ 1/(1 − Q); ln(Q + (n−1) p_tr)
    let r = (lup - lq).exp();
    let ln_sum = lq + ((n - 1.0) * r).ln_1p();
    if ln_sum < -46.0 {
        // S < 1e-20: 1 − (1−Q)(1−p)^(n−1) = S (1 − O(S)), exact to double precision.
        return ln_sum;
    }
    let pu = lup.exp().min(1.0);
    let l = (-qv).ln_1p() + (n - 1.0) * (-pu).ln_1p();
    (-l.exp_m1()).ln()
}

/// Probability that the maximum of `n` standard-normal samples with lag-1
/// correlation `rho1` exceeds `u` (up-crossing approximation, see the module
/// documentation; exact for `rho1 = 0`).
pub fn max_exceed_prob(u: f64, n: usize, rho1: f64) -> f64 {
    ln_max_exceed_prob(u, n, rho1).exp()
}

/// Threshold whose per-report false-alarm probability over `n` cells with
/// lag-1 correlation `rho1` is `p_report`.
///
/// Solves `ln P(max > u) = ln p_report` by Illinois false position in u between the
/// single-cell bound Q⁻¹(P) and the union bound Q⁻¹(P/n) (P(max > u) lies
/// between Q(u) and n·Q(u)), to ~1e-13 relative; ~0.3 ms. Robust for
/// p_report in [1e-300, 0.5], n from 1 to 1e9, rho1 in [−1, 1) (values
/// outside are clamped; rho1 ≥ 1 means one effective cell). Defined edges:
/// n = 0 is treated as 1; p_report ≤ 0 gives u = +∞, p_report ≥ 1 gives
/// u = −∞; NaN p_report or rho1 gives NaN fields.
pub fn threshold_for_report(p_report: f64, n: usize, rho1: f64) -> ReportThreshold {
    let cells = n.max(1);
    if p_report.is_nan() || rho1.is_nan() {
        return ReportThreshold {
            u: f64::NAN,
            p_cell: f64::NAN,
            cells_effective: f64::NAN,
        };
    }
    if p_report <= 0.0 {
        return ReportThreshold {
            u: f64::INFINITY,
            p_cell: 0.0,
            cells_effective: cells as f64,
        };
    }
    if p_report >= 1.0 {
        return ReportThreshold {
            u: f64::NEG_INFINITY,
            p_cell: 1.0,
            cells_effective: cells as f64,
        };
    }
    let ln_p = p_report.ln();
    let u_single = ln_q_inv(ln_p);
    let u = if cells == 1 {
        u_single
    } else {
        let u_union = ln_q_inv(ln_p - (cells as f64).ln());
        let grid = TanGrid::for_rho1(rho1);
        let f = |u: f64| ln_max_exceed_prob_on(u, cells, rho1, grid.as_ref()) - ln_p;
        // Illinois false position on the bracket: 6–10 evaluations of the
        // quadrature (each ~40 µs) to its last ulps, where halving took ~50.
        crate::math::roots::illinois(u_single, u_union.max(u_single), 0.0, f)
    };
    let p_cell = q(u);
    let cells_effective = if p_cell >= 1e-250 {
        (-p_report).ln_1p() / (-p_cell).ln_1p()
    } else {
        // both tiny: −log1p(−x) = x to double precision
        (ln_p - ln_q(u)).exp()
    };
    ReportThreshold {
        u,
        p_cell,
        cells_effective,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::special::{per_cell_pfa, q_inv};

    #[test]
    fn tangents_taken_once_give_the_same_integral() {
        for rho1 in [-0.5, 0.0, 0.3, 0.9, 0.985, 0.9999] {
            let grid = TanGrid::for_rho1(rho1).expect("a non-empty interval");
            for u in [0.0, 0.5, 2.0, 4.75, 5.5, 7.0, 12.0, 40.0] {
                for n in [1usize, 2, 1000, 1_000_000] {
                    let want = ln_max_exceed_prob(u, n, rho1);
                    let got = ln_max_exceed_prob_on(u, n, rho1, Some(&grid));
                    assert_eq!(got.to_bits(), want.to_bits(), "u {u} n {n} rho1 {rho1}");
                }
            }
        }
        assert!(TanGrid::for_rho1(1.0).is_none());
    }

    #[test]
    fn white_noise_reduces_to_independent_cells() {
        for (p, n) in [
            (1e-2, 1000usize),
            (1e-6, 2500),
            (1e-300, 1_000_000_000),
            (0.5, 7),
        ] {
            let t = threshold_for_report(p, n, 0.0);
            let want = q_inv(per_cell_pfa(p, n as f64));
            assert!(
                ((t.u - want) / want).abs() < 1e-12,
                "p={p} n={n}: {} vs {want}",
                t.u
            );
            assert!(
                (t.cells_effective / n as f64 - 1.0).abs() < 1e-9,
                "{}",
                t.cells_effective
            );
        }
    }

    #[test]
    fn owen_t_matches_closed_forms() {
        // ρ = 0 (a = 1): p_up = Q(1 − Q); ρ = −1 (a = ∞): p_up = Q for u ≥ 0
        for u in [0.0, 0.5, 2.0, 6.0, 20.0, 37.0] {
            let qu = q(u);
            let got = ln_upcrossing_prob(u, 0.0).exp();
            assert!((got / (qu * (1.0 - qu)) - 1.0).abs() < 1e-11, "u={u}");
            let got = ln_upcrossing_prob(u, -1.0).exp();
            assert!((got / qu - 1.0).abs() < 1e-11, "u={u}");
        }
        // T(0, a) = atan(a)/(2π): p_up(0) = atan(a)/π
        let a = (0.5f64 / 1.5).sqrt();
        let got = ln_upcrossing_prob(0.0, 0.5).exp();
        assert!((got / (a.atan() / std::f64::consts::PI) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn correlated_threshold_is_lower_and_monotone() {
        let white = threshold_for_report(1e-3, 2000, 0.0).u;
        let mut last = white;
        for rho in [0.3, 0.7, 0.9, 0.985, 0.999, 0.999_999] {
            let t = threshold_for_report(1e-3, 2000, rho);
            assert!(t.u < last, "rho={rho}");
            assert!(t.cells_effective < 2000.0 && t.cells_effective >= 1.0);
            last = t.u;
        }
        // ρ → 1: one effective cell
        let single = q_inv(1e-3);
        assert!((threshold_for_report(1e-3, 2000, 1.0).u - single).abs() < 1e-12);
        assert!((threshold_for_report(1e-3, 2000, 1.0 - 1e-15).u - single).abs() < 1e-4);
        // extreme corners stay finite
        for (p, n, rho) in [
            (1e-300, 1_000_000_000usize, 0.9),
            (0.5, 1, 0.0),
            (1e-300, 1, -1.0),
            (0.5, 1_000_000_000, -0.9),
        ] {
            let t = threshold_for_report(p, n, rho);
            assert!(
                t.u.is_finite() && t.p_cell.is_finite() && t.cells_effective.is_finite(),
                "{p} {n} {rho}: {t:?}"
            );
            let back = ln_max_exceed_prob(t.u, n, rho);
            assert!(
                (back - p.ln()).abs() < 1e-9 * p.ln().abs().max(1.0),
                "{p} {n} {rho}: {back}"
            );
        }
    }
}
