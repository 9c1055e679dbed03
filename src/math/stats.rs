//! Confidence intervals (binomial, Poisson), binomial acceptance bands for
//! Monte-Carlo tests, the Jarque-Bera normality test and the Student-t
//! quantile (Cornish-Fisher).
//!
//! The intervals need quantiles of the beta and gamma distributions far in
//! their tails (k = 0/1 out of n = 1e9, confidence 1 − 1e-12). They are
//! solved here by bisection on the *logarithm* of the relevant tail
//! probability, evaluated with continued fractions / series whose prefactor
//! `x^a (1−x)^b / B(a, b)` (resp. `x^a e^−x / Γ(a)`) is written with Loader's
//! deviance `bd0` and the Stirling remainder, so it keeps full relative
//! accuracy when a, b ~ 1e9 (where `a ln x + b ln(1−x) − ln B(a, b)` would
//! cancel 9 digits away).

use std::f64::consts::PI;
use crate::math::roots::illinois_from;

const LN_SQRT_2PI: f64 = 0.918_938_533_204_672_8;
const TINY: f64 = 1e-300;
/// Convergence of the continued fractions: two ulps of 1 (|del − 1| cannot
/// go below one ulp once rounding noise dominates).
const CF_EPS: f64 = 4.5e-16;
const MAX_CF_ITER: usize = 2_000_000;

/// Stirling remainder δ(z) = ln Γ(z) − (z − ½) ln z + z − ln √(2π), z > 0.
fn stirling_delta(z: f64) -> f64 {
    let mut z = z;
    let mut acc = 0.0;
    // δ(z) = δ(z + 1) + (z + ½) ln(1 + 1/z) − 1: climb to where the series is exact.
    while z < 15.0 {
        acc += (z + 0.5) * (1.0 / z).ln_1p() - 1.0;
        z += 1.0;
    }
    let t = 1.0 / (z * z);
    acc + (1.0 / 12.0
        - t * (1.0 / 360.0
            - t * (1.0 / 1260.0 - t * (1.0 / 1680.0 - t * (1.0 / 1188.0 - t * 691.0 / 360_360.0)))))
        / z
}

/// Loader's deviance term bd0(x, m) = x ln(x/m) + m − x ≥ 0, without
/// cancellation when x ≈ m.
fn bd0(x: f64, m: f64) -> f64 {
    if x == 0.0 {
        return m;
    }
    if (x - m).abs() < 0.1 * (x + m) {
        let v = (x - m) / (x + m);
        let mut s = (x - m) * v;
        let mut ej = 2.0 * x * v;
        let v2 = v * v;
        for j in 1..1000 {
            ej *= v2;
            let s1 = s + ej / (2 * j + 1) as f64;
            if s1 == s {
                return s1;
            }
            s = s1;
        }
        return s;
    }
    x * (x / m).ln() + m - x
}

/// ln[x^a y^b / B(a, b)] with y = 1 − x (passed separately for accuracy).
fn ln_beta_prefactor(a: f64, b: f64, x: f64, y: f64) -> f64 {
    let s = a + b;
    -bd0(a, s * x) - bd0(b, s * y) + 0.5 * (a * b / s).ln()
        - LN_SQRT_2PI
        - stirling_delta(a)
        - stirling_delta(b)
        + stirling_delta(s)
}

/// Continued fraction of I_x(a, b) (modified Lentz), converging fast for
/// x < (a + 1)/(a + b + 2); y = 1 − x.
fn beta_cf(a: f64, b: f64, x: f64, y: f64) -> f64 {
    let (qab, qap, qam) = (a + b, a + 1.0, a - 1.0);
    let mut c = 1.0;
    // 1 − (a + b)x/(a + 1), written with y so that x → 1 (a ≫ b) does not cancel.
    let mut d = ((a + 1.0) * y - (b - 1.0) * x) / qap;
    if d.abs() < TINY {
        d = TINY;
    }
    d = 1.0 / d;
    let mut h = d;
    for m in 1..MAX_CF_ITER {
        let m = m as f64;
        let m2 = 2.0 * m;
        let aa = m * (b - m) * x / ((qam + m2) * (a + m2));
        d = 1.0 + aa * d;
        if d.abs() < TINY {
            d = TINY;
        }
        c = 1.0 + aa / c;
        if c.abs() < TINY {
            c = TINY;
        }
        d = 1.0 / d;
        h *= d * c;
        let aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2));
        d = 1.0 + aa * d;
        if d.abs() < TINY {
            d = TINY;
        }
        c = 1.0 + aa / c;
        if c.abs() < TINY {
            c = TINY;
        }
        d = 1.0 / d;
        let del = d * c;
        h *= del;
        if (del - 1.0).abs() < CF_EPS {
            break;
        }
    }
    h
}

/// ln I_x(a, b) (regularised incomplete beta, lower tail), y = 1 − x.
fn ln_beta_inc(a: f64, b: f64, x: f64, y: f64) -> f64 {
    if x <= 0.0 {
        return f64::NEG_INFINITY;
    }
    if y <= 0.0 {
        return 0.0;
    }
    if x <= (a + 1.0) / (a + b + 2.0) {
        ln_beta_prefactor(a, b, x, y) + beta_cf(a, b, x, y).ln() - a.ln()
    } else {
        let upper = (ln_beta_prefactor(b, a, y, x) + beta_cf(b, a, y, x).ln() - b.ln()).exp();
        (-upper).ln_1p()
    }
}

/// Regularised incomplete beta function I_x(a, b) = P(Beta(a, b) ≤ x), for
/// a, b > 0 and x in [0, 1] (x clamped to [0, 1]; NaN gives NaN). Relative
/// accuracy ~1e-14 in the lower tail for a, b up to ~1e9.
pub fn beta_inc_reg(a: f64, b: f64, x: f64) -> f64 {
    if x.is_nan() || a.is_nan() || b.is_nan() || a <= 0.0 || b <= 0.0 {
        return f64::NAN;
    }
    ln_beta_inc(a, b, x.clamp(0.0, 1.0), 1.0 - x.clamp(0.0, 1.0)).exp()
}

/// ln of the prefactor x^a e^−x / Γ(a).
fn ln_gamma_prefactor(a: f64, x: f64) -> f64 {
    a.ln() - bd0(a, x) - stirling_delta(a) - 0.5 * (2.0 * PI * a).ln()
}

/// ln P(a, x) and ln Q(a, x) (regularised incomplete gamma), the small one
/// computed directly (series below a + 1, continued fraction above).
fn ln_gamma_inc(a: f64, x: f64) -> (f64, f64) {
    if x <= 0.0 {
        return (f64::NEG_INFINITY, 0.0);
    }
    if x < a + 1.0 {
        // P = x^a e^-x / Γ(a+1) · Σ x^n / ((a+1)…(a+n))
        let mut term = 1.0;
        let mut sum = 1.0;
        let mut ap = a;
        for _ in 0..MAX_CF_ITER {
            ap += 1.0;
            term *= x / ap;
            sum += term;
            if term < sum * CF_EPS {
                break;
            }
        }
        let lp = ln_gamma_prefactor(a, x) - a.ln() + sum.ln();
        (lp, (-lp.exp()).ln_1p())
    } else {
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / TINY;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..MAX_CF_ITER {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < TINY {
                d = TINY;
            }
            c = b + an / c;
            if c.abs() < TINY {
                c = TINY;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < CF_EPS {
                break;
            }
        }
        let lq = ln_gamma_prefactor(a, x) + h.ln();
        ((-lq.exp()).ln_1p(), lq)
    }
}

/// Regularised lower incomplete gamma P(a, x) = P(Gamma(a, 1) ≤ x).
pub fn gamma_p(a: f64, x: f64) -> f64 {
    if a.is_nan() || x.is_nan() || a <= 0.0 {
        return f64::NAN;
    }
    ln_gamma_inc(a, x).0.exp()
}

/// Regularised upper incomplete gamma Q(a, x) = 1 − P(a, x).
pub fn gamma_q(a: f64, x: f64) -> f64 {
    if a.is_nan() || x.is_nan() || a <= 0.0 {
        return f64::NAN;
    }
    ln_gamma_inc(a, x).1.exp()
}

/// Bisection for the root of a monotone `f` on [lo, hi] (f(lo), f(hi) of
/// opposite signs, or the nearer end is returned): 200 halvings at most,
/// stops when the bracket is below 4 ulps.
fn bisect(mut lo: f64, mut hi: f64, f: impl Fn(f64) -> f64) -> f64 {
    let flo = f(lo);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if mid <= lo
            || mid >= hi
            || (hi - lo) <= 4.0 * f64::EPSILON * mid.abs().max(f64::MIN_POSITIVE)
        {
            break;
        }
        let fm = f(mid);
        if fm.is_nan() {
            break;
        }
        if (fm > 0.0) == (flo > 0.0) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// ln(p / (1 − p)), finite for p in (0, 1) and clamped to ±745 beyond.
fn logit(p: f64) -> f64 {
    if p > 0.0 && p < 1.0 { (p / (1.0 - p)).ln().clamp(-745.0, 745.0) } else if p <= 0.0 { -745.0 } else { 745.0 }
}

/// Wilson's score interval for k of n at normal deviate z (a starting point
/// for the exact bounds).
fn wilson(k: f64, n: f64, z: f64) -> (f64, f64) {
    let (p, z2) = (k / n, z * z);
    let centre = (p + z2 / (2.0 * n)) / (1.0 + z2 / n);
    let half = z / (1.0 + z2 / n) * (p * (1.0 - p) / n + z2 / (4.0 * n * n)).sqrt();
    ((centre - half).max(0.0), (centre + half).min(1.0))
}

/// p and 1 − p from the logit t, both to full relative accuracy.
fn logistic(t: f64) -> (f64, f64) {
    if t >= 0.0 {
        let e = (-t).exp();
        (1.0 / (1.0 + e), e / (1.0 + e))
    } else {
        let e = t.exp();
        (e / (1.0 + e), 1.0 / (1.0 + e))
    }
}

/// ln of the binomial pmf at 0 < k < n (Loader 2000: Stirling remainders and
/// deviances, no cancellation for n up to 1e15).
fn ln_binom_pmf(k: f64, n: f64, p: f64, q: f64) -> f64 {
    let lc = stirling_delta(n)
        - stirling_delta(k)
        - stirling_delta(n - k)
        - bd0(k, n * p)
        - bd0(n - k, n * q);
    lc - 0.5 * ((2.0 * PI).ln() + k.ln() + (-k / n).ln_1p())
}

/// Direct summation of the binomial pmf from `k` towards the tail, in the
/// direction where the terms decrease (`down`: j = k, k−1, …, 0; else
/// j = k, k+1, …, n). Used where the continued fraction would cancel
/// (x → 1 with a ≫ b). Returns ln Σ.
fn ln_binom_tail_sum(k: f64, n: f64, p: f64, q: f64, down: bool) -> f64 {
    // q^n and p^n: through whichever of p, q is the small one, where it is exact.
    let ln_pow = |small: f64, big: f64| {
        if small < 0.5 {
            n * (-small).ln_1p()
        } else {
            n * big.ln()
        }
    };
    let ln_t0 = if k == 0.0 {
        ln_pow(p, q)
    } else if k == n {
        ln_pow(q, p)
    } else {
        ln_binom_pmf(k, n, p, q)
    };
    let (mut t, mut sum, mut j) = (1.0f64, 1.0f64, k);
    let ratio_up = p / q;
    for _ in 0..10_000_000 {
        if down {
            if j <= 0.0 {
                break;
            }
            t *= j / (n - j + 1.0) / ratio_up;
            j -= 1.0;
        } else {
            if j >= n {
                break;
            }
            t *= (n - j) / (j + 1.0) * ratio_up;
            j += 1.0;
        }
        sum += t;
        if t < 1e-17 * sum {
            break;
        }
    }
    ln_t0 + sum.ln()
}

/// Terms needed by [`ln_binom_tail_sum`] before it is cheaper to use the
/// continued fraction.
const MAX_SUM_TERMS: f64 = 20_000.0;

/// ln P(X ≥ k) for X ~ Binomial(n, p), 1 ≤ k ≤ n: ln I_p(k, n − k + 1).
fn ln_binom_sf_ge(k: f64, n: f64, p: f64, q: f64) -> f64 {
    let mean = n * p;
    // k above the mean: the upper tail is small and its terms decrease from k.
    if k > mean + 1.0 && 40.0 * (mean * q).sqrt() + 50.0 < MAX_SUM_TERMS {
        return ln_binom_tail_sum(k, n, p, q, false);
    }
    ln_beta_inc(k, n - k + 1.0, p, q)
}

/// ln P(X ≤ k) for X ~ Binomial(n, p), 0 ≤ k < n: ln I_{1−p}(n − k, k + 1).
fn ln_binom_cdf_le(k: f64, n: f64, p: f64, q: f64) -> f64 {
    let mean = n * p;
    // k below the mean: the lower tail is small and its terms decrease towards 0.
    if k + 1.0 < mean && (k < MAX_SUM_TERMS || 40.0 * (mean * q).sqrt() + 50.0 < MAX_SUM_TERMS) {
        return ln_binom_tail_sum(k, n, p, q, true);
    }
    ln_beta_inc(n - k, k + 1.0, q, p)
}

/// P(X ≤ k) for X ~ Binomial(n, p).
pub fn binomial_cdf(k: u64, n: u64, p: f64) -> f64 {
    if p.is_nan() {
        return f64::NAN;
    }
    if k >= n || p <= 0.0 {
        return 1.0;
    }
    if p >= 1.0 {
        return 0.0;
    }
    ln_binom_cdf_le(k as f64, n as f64, p, 1.0 - p).exp()
}

/// Two-sided Clopper-Pearson ("exact") interval for `successes` out of
/// `trials` at `confidence` (e.g. 0.95). Equal-tailed: each bound leaves
/// (1 − confidence)/2 in its tail. For confidence extremely close to 1 use
/// [`clopper_pearson_alpha`], which takes α directly (1 − confidence loses
/// digits). Defined answers: `trials == 0` → (0, 1); `successes > trials` is
/// clamped to `trials`; confidence is clamped to [0, 1] (NaN → (0, 1)).
pub fn clopper_pearson(successes: u64, trials: u64, confidence: f64) -> (f64, f64) {
    if confidence.is_nan() {
        return (0.0, 1.0);
    }
    clopper_pearson_alpha(successes, trials, 1.0 - confidence.clamp(0.0, 1.0))
}

/// Clopper-Pearson interval with total tail probability `alpha` (each bound
/// leaves α/2): the lower bound solves P(X ≥ k | p) = α/2, the upper bound
/// P(X ≤ k | p) = α/2. Where the equation has a closed form it is used:
/// k = 0 gives the upper bound 1 − (α/2)^(1/n) (from (1 − p)ⁿ = α/2) and
/// k = n the lower bound (α/2)^(1/n) (the running false-alarm count,
/// zero for most of a clean run, solves nothing). Both carry the rounding
/// of ln(α/2): the upper bound within about 2ε relative, the lower within
/// about |ln(α/2)|/n·ε (1 or 2 ε at ordinary α, 58 ε at n = 1 and
/// α = 1e-100; ε = 2.2e-16). The
/// other bounds come from Illinois false position on logit(p) of the log
/// tail, started from Wilson's score bounds ([`clopper_pearson_solved`]).
/// Relative accuracy ~1e-13 for n up to 1e9 and α down to 1e-300. α ≤ 0
/// gives (0, 1); α ≥ 1 gives the point estimate k/n twice; NaN gives (0, 1).
pub fn clopper_pearson_alpha(successes: u64, trials: u64, alpha: f64) -> (f64, f64) {
    clopper_pearson_with(successes, trials, alpha, true)
}

/// [`clopper_pearson_alpha`] with every bound solved by the root finder,
/// the closed forms at k = 0 and k = n included: what checks the solver
/// against them.
pub fn clopper_pearson_solved(successes: u64, trials: u64, alpha: f64) -> (f64, f64) {
    clopper_pearson_with(successes, trials, alpha, false)
}

fn clopper_pearson_with(successes: u64, trials: u64, alpha: f64, closed: bool) -> (f64, f64) {
    if trials == 0 || alpha.is_nan() || alpha <= 0.0 {
        return (0.0, 1.0);
    }
    let k = successes.min(trials);
    if alpha >= 1.0 {
        let p = k as f64 / trials as f64;
        return (p, p);
    }
    let (kf, nf) = (k as f64, trials as f64);
    let ln_target = (0.5 * alpha).ln();
    if closed && k == 0 {
        return (0.0, -(ln_target / nf).exp_m1());
    }
    if closed && k == trials {
        return ((ln_target / nf).exp(), 1.0);
    }
    // Wilson's score bounds start the search (within a few logit units of
    // the exact ones), Illinois false position finishes it.
    let (wlo, whi) = wilson(kf, nf, crate::math::special::q_inv(0.5 * alpha));
    let lo = if k == 0 {
        0.0
    } else {
        // P(X ≥ k | p) increases with p.
        let t = illinois_from(logit(wlo), 0.25, -745.0, 745.0, 0.0, |t| {
            let (p, q) = logistic(t);
            ln_binom_sf_ge(kf, nf, p, q) - ln_target
        });
        logistic(t).0
    };
    let hi = if k == trials {
        1.0
    } else {
        // P(X ≤ k | p) decreases with p; solve on -logit so the bound's
        // complement 1 − p keeps its digits when the bound is near 1.
        let t = illinois_from(-logit(whi), 0.25, -745.0, 745.0, 0.0, |t| {
            let (q, p) = logistic(t);
            ln_target - ln_binom_cdf_le(kf, nf, p, q)
        });
        logistic(t).1
    };
    (lo, hi)
}

/// Garwood ("exact") two-sided interval for a Poisson mean given `count`
/// events, at `confidence`: lower = Γ⁻¹(α/2; k), upper = Γ⁻¹(1 − α/2; k + 1)
/// (i.e. χ²_{α/2}(2k)/2 and χ²_{1−α/2}(2k+2)/2). k = 0 gives a lower bound of
/// 0 and an upper bound of −ln(α/2). Confidence is clamped to [0, 1]; NaN or
/// confidence 1 gives (0, ∞).
pub fn poisson_interval(count: u64, confidence: f64) -> (f64, f64) {
    if confidence.is_nan() {
        return (0.0, f64::INFINITY);
    }
    poisson_interval_alpha(count, 1.0 - confidence.clamp(0.0, 1.0))
}

/// [`poisson_interval`] with the total tail probability α given directly.
pub fn poisson_interval_alpha(count: u64, alpha: f64) -> (f64, f64) {
    if alpha.is_nan() || alpha <= 0.0 {
        return (0.0, f64::INFINITY);
    }
    let k = count as f64;
    if alpha >= 1.0 {
        return (k, k);
    }
    let ln_target = (0.5 * alpha).ln();
    // Bracket in ln x: the mean is within ~40 sd + 750 e-folds of k.
    let top = (k + 1.0 + 40.0 * (k + 1.0).sqrt() + 800.0).ln();
    let lo = if count == 0 {
        0.0
    } else {
        // P(k, x) increases with x.
        bisect(-745.0, top, |t| ln_gamma_inc(k, t.exp()).0 - ln_target).exp()
    };
    // Q(k + 1, x) increases with x as well.
    let hi = bisect(-745.0, top, |t| {
        ln_target - ln_gamma_inc(k + 1.0, t.exp()).1
    })
    .exp();
    (lo, hi)
}

/// Central acceptance band [lo, hi] for a binomial count at two-sided
/// `confidence`: with tail = (1 − confidence)/2, `lo` is the largest count
/// with P(X < lo) ≤ tail and `hi` the smallest with P(X > hi) ≤ tail, for
/// X ~ Binomial(trials, p). A count c passes iff `lo ≤ c ≤ hi`; under the
/// null hypothesis it fails with probability ≤ 1 − confidence (less, since
/// the distribution is discrete).
pub fn binomial_acceptance_counts(trials: u64, p: f64, confidence: f64) -> (u64, u64) {
    let tail = 0.5 * (1.0 - confidence.clamp(0.0, 1.0));
    if trials == 0 || p.is_nan() {
        return (0, trials);
    }
    // smallest k with P(X ≤ k) > tail: then P(X < k) ≤ tail.
    let first_above = |level: f64, strict: bool| -> u64 {
        let (mut a, mut b) = (0u64, trials);
        while a < b {
            let mid = a + (b - a) / 2;
            let c = binomial_cdf(mid, trials, p);
            let ok = if strict { c > level } else { c >= level };
            if ok {
                b = mid;
            } else {
                a = mid + 1;
            }
        }
        a
    };
    let lo = first_above(tail, true);
    // smallest k with P(X > k) ≤ tail, i.e. P(X ≤ k) ≥ 1 − tail.
    let hi = first_above(1.0 - tail, false);
    (lo, hi)
}

/// Acceptance band for an observed *fraction* of `trials` Bernoulli(p)
/// trials at 99 % two-sided confidence: `binomial_acceptance_counts(trials,
/// p, 0.99)` divided by `trials`. Monte-Carlo tests assert
/// `lo ≤ hits / trials ≤ hi`, which a correct implementation fails with
/// probability ≤ 1 %.
pub fn binomial_two_sided_interval_99(trials: u64, p: f64) -> (f64, f64) {
    let (lo, hi) = binomial_acceptance_counts(trials, p, 0.99);
    let n = trials.max(1) as f64;
    (lo as f64 / n, hi as f64 / n)
}

/// Jarque-Bera statistic JB = n/6 (g1² + g2²/4) and its asymptotic p-value
/// (chi-squared with 2 degrees of freedom: exp(−JB/2)). n = 0 gives (0, 1).
pub fn jarque_bera(n: u64, skewness: f64, excess_kurtosis: f64) -> (f64, f64) {
    if n == 0 {
        return (0.0, 1.0);
    }
    let jb = n as f64 / 6.0 * (skewness * skewness + excess_kurtosis * excess_kurtosis / 4.0);
    (jb, (-jb / 2.0).exp())
}

/// Upper quantile of Student's t with `nu` degrees of freedom whose tail
/// probability equals that of the standard normal at `z` (Cornish-Fisher
/// expansion, Abramowitz & Stegun 26.7.5, to 1/ν⁴). Infinite ν gives `z`.
/// Accurate to better than 1e-4 relative for ν ≥ 30 with z ≤ 5.5 and for
/// ν ≥ 100 with z ≤ 7 (against statrs's Student t, `tests/suite/math_oracle.rs`);
/// at ν = 30 the error grows to 8e-4 at z = 7. Small gates are flagged by
/// the pipeline.
pub fn t_quantile_from_z(z: f64, nu: f64) -> f64 {
    if !nu.is_finite() || nu <= 0.0 {
        return z;
    }
    let z2 = z * z;
    let g1 = (z2 + 1.0) * z / 4.0;
    let g2 = ((5.0 * z2 + 16.0) * z2 + 3.0) * z / 96.0;
    let g3 = (((3.0 * z2 + 19.0) * z2 + 17.0) * z2 - 15.0) * z / 384.0;
    let g4 = ((((79.0 * z2 + 776.0) * z2 + 1482.0) * z2 - 1920.0) * z2 - 945.0) * z / 92160.0;
    z + g1 / nu + g2 / (nu * nu) + g3 / nu.powi(3) + g4 / nu.powi(4)
}

/// Upper `alpha` quantile of χ² with `nu` degrees of freedom
/// (Wilson–Hilferty; relative error under 1 % for ν ≥ 3 at α ≥ 1e-6).
pub fn chi2_upper(nu: f64, alpha: f64) -> f64 {
    let z = crate::math::special::q_inv(alpha);
    let a = 2.0 / (9.0 * nu);
    (nu * (1.0 - a + z * a.sqrt()).powi(3)).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chi2_quantile_matches_tables() {
        // χ²(100) upper 1e-3: 149.449; χ²(10) upper 0.01: 23.209.
        assert!((chi2_upper(100.0, 1e-3) / 149.449 - 1.0).abs() < 2e-3);
        assert!((chi2_upper(10.0, 0.01) / 23.209 - 1.0).abs() < 5e-3);
    }


    fn rel(a: f64, b: f64) -> f64 {
        ((a - b) / b).abs()
    }

    /// The bounds by halving the logit bracket: the solver the Illinois one replaced.
    fn clopper_pearson_by_halving(k: u64, n: u64, alpha: f64) -> (f64, f64) {
        let (kf, nf, ln_target) = (k as f64, n as f64, (0.5 * alpha).ln());
        let lo = if k == 0 {
            0.0
        } else {
            logistic(bisect(-745.0, 745.0, |t| {
                let (p, q) = logistic(t);
                ln_binom_sf_ge(kf, nf, p, q) - ln_target
            }))
            .0
        };
        let hi = if k == n {
            1.0
        } else {
            logistic(bisect(-745.0, 745.0, |t| {
                let (q, p) = logistic(t);
                ln_target - ln_binom_cdf_le(kf, nf, p, q)
            }))
            .1
        };
        (lo, hi)
    }

    #[test]
    fn clopper_pearson_by_illinois_equals_halving() {
        let mut worst = 0.0f64;
        for &(k, n) in &[(0, 10), (1, 10), (5, 10), (9, 10), (10, 10), (0, 1), (1, 1), (3, 2000), (38, 40_000), (8817, 40_000),
            (1, 1_000_000_000), (999_999_999, 1_000_000_000), (500_000, 1_000_000), (17, 300), (299, 300), (2, 5_000_000)]
        {
            for alpha in [0.5, 0.05, 0.01, 1e-3, 1e-9, 1e-100, 1e-300] {
                // The root finder (the closed forms at k = 0 and k = n are
                // checked against it in `tests/suite/numerics.rs`).
                let (a, b) = (clopper_pearson_solved(k, n, alpha), clopper_pearson_by_halving(k, n, alpha));
                for (x, y) in [(a.0, b.0), (a.1, b.1), (1.0 - a.0, 1.0 - b.0), (1.0 - a.1, 1.0 - b.1)] {
                    let e = if y == 0.0 { x.abs() } else { rel(x, y) };
                    assert!(e < 1e-11, "k {k} n {n} alpha {alpha}: {a:?} vs {b:?}");
                    worst = worst.max(e);
                }
            }
        }
        eprintln!("Clopper-Pearson, Illinois vs halving: worst relative difference {worst:.1e}");
    }

    #[test]
    fn stirling_delta_matches_known_values() {
        // δ(1) = 1 − ln√(2π); δ(2) = 2 − 1.5 ln 2 − ln√(2π); δ(0.5) = ln√π + ½ − ln√(2π)
        assert!(rel(stirling_delta(1.0), 1.0 - LN_SQRT_2PI) < 1e-14);
        assert!(rel(stirling_delta(2.0), 2.0 - 1.5 * 2f64.ln() - LN_SQRT_2PI) < 1e-14);
        assert!(rel(stirling_delta(0.5), 0.5 * PI.ln() + 0.5 - LN_SQRT_2PI) < 1e-14);
    }

    #[test]
    fn beta_inc_closed_forms() {
        // I_x(1, b) = 1 − (1 − x)^b; I_x(a, 1) = x^a
        for &(b, x) in &[(1.0f64, 0.3f64), (7.0, 0.01), (1e9, 1e-12), (1e6, 1e-3)] {
            let want = -(b * (-x).ln_1p()).exp_m1();
            assert!(rel(beta_inc_reg(1.0, b, x), want) < 1e-13, "b={b} x={x}");
        }
        for &(a, x) in &[(3.0, 0.5), (1e9, 1.0 - 1e-10), (50.0, 0.2)] {
            let want = (a * f64::ln(x)).exp();
            assert!(rel(beta_inc_reg(a, 1.0, x), want) < 1e-12, "a={a} x={x}");
        }
        // symmetric case: I_0.5(a, a) = 0.5
        assert!(rel(beta_inc_reg(1e6, 1e6, 0.5), 0.5) < 1e-12);
    }

    #[test]
    fn gamma_inc_closed_forms() {
        // P(1, x) = 1 − e^−x; Q(2, x) = (1 + x) e^−x
        for x in [1e-5, 0.3, 2.0, 30.0, 700.0] {
            assert!(rel(gamma_p(1.0, x), -(-x).exp_m1()) < 1e-14, "{x}");
            assert!(rel(gamma_q(2.0, x), (1.0 + x) * (-x).exp()) < 1e-13, "{x}");
        }
    }

    #[test]
    fn t_quantiles_match_tables() {
        // Two-sided 99 % (upper 0.005, z = 2.5758293035489) points of Student t.
        for (nu, t) in [
            (30.0, 2.749995653),
            (60.0, 2.660283029),
            (120.0, 2.617421145),
        ] {
            let got = t_quantile_from_z(2.575829303548901, nu);
            assert!((got / t - 1.0).abs() < 2e-4, "nu {nu}: {got} vs {t}");
        }
        assert_eq!(t_quantile_from_z(3.0, f64::INFINITY), 3.0);
    }

    #[test]
    fn t_quantile_of_long_gates_is_the_normal_one() {
        assert!((t_quantile_from_z(5.0, 1e9) - 5.0).abs() < 1e-7);
    }
}
