//! Accuracy of the detector's statistical numerics against external
//! high-precision tables (Boost.Math, mpmath, SciPy; see
//! `tests/data/numerics/README.md`), plus Monte-Carlo checks of the
//! per-report threshold and of the noise fitter.
//!
//! Measured maximum errors are printed (`cargo test --release --test
//! numerics -- --nocapture`).

use tofwave::detect::qfunc::{erfc, ln_q, ln_q_inv, per_cell_pfa, q, q_inv};

/// One table: rows of decimal strings, header and `#` comments skipped.
fn table(text: &str) -> Vec<Vec<&str>> {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .skip(1)
        .map(|l| l.split(',').map(str::trim).collect())
        .collect()
}

fn num(s: &str) -> f64 {
    s.parse::<f64>().unwrap_or_else(|e| panic!("bad number {s:?}: {e}"))
}

const EPS: f64 = f64::EPSILON / 2.0; // unit roundoff 2^-53 = 1.11e-16

/// Relative error of `got` against the f64 rounding of a decimal reference.
fn rel(got: f64, want: f64) -> f64 {
    if got == want { 0.0 } else { ((got - want) / want).abs() }
}

/// Largest error seen, with the argument where it occurred.
#[derive(Default)]
struct MaxErr {
    err: f64,
    at: f64,
    rows: usize,
}
impl MaxErr {
    fn add(&mut self, err: f64, at: f64) {
        self.rows += 1;
        if err > self.err || err.is_nan() {
            self.err = err;
            self.at = at;
        }
    }
}

/// Checks q_inv at one (p, x) pair: relative error must be ≤ 1e-14 beyond
/// the unavoidable part caused by rounding the decimal p to f64
/// (|dx| = |dp| / φ(x) ≤ EPS · p / φ(x)); returns the relative error.
fn check_qinv(p_str: &str, want: f64, table_name: &str) -> f64 {
    let p = num(p_str);
    let got = q_inv(p);
    let err = (got - want).abs();
    // half an ulp of p: relative for normal p, absolute 2^-1075 for subnormal p
    let phi = tofwave::detect::qfunc::phi(want);
    let input_rounding = (EPS * p / phi).max(0.5 * (f64::from_bits(1) / phi));
    let bound = 1e-14 * want.abs() + input_rounding;
    assert!(err <= bound, "{table_name}: q_inv({p_str}) = {got:e}, want {want:e}, err {err:e} > {bound:e}");
    if want == 0.0 { err } else { err / want.abs() }
}

#[test]
fn q_inv_matches_boost_derived_table() {
    let mut m = MaxErr::default();
    for r in table(include_str!("data/numerics/boost-math/derived_qinv_double_range.csv")) {
        let e = check_qinv(r[0], num(r[1]), "derived_qinv_double_range");
        m.add(e, num(r[0]));
    }
    println!("q_inv vs boost derived_qinv_double_range: {} rows, max rel err {:.2e} at p={:e}", m.rows, m.err, m.at);
    assert_eq!(m.rows, 96);
}

#[test]
fn q_inv_matches_boost_erfc_inv_tables() {
    // erfc_inv(x) = Q⁻¹(x/2)/√2; x/2 is exact in binary while x/2 ≥ DBL_MIN.
    for (name, text) in [
        ("erfc_inv_data", include_str!("data/numerics/boost-math/erfc_inv_data.csv")),
        ("erfc_inv_big_data", include_str!("data/numerics/boost-math/erfc_inv_big_data.csv")),
    ] {
        let mut m = MaxErr::default();
        for r in table(text) {
            let x = num(r[0]);
            if x / 2.0 < f64::MIN_POSITIVE {
                continue; // long-double-only rows
            }
            let want = num(r[1]) * std::f64::consts::SQRT_2;
            let p = x / 2.0;
            let got = q_inv(p);
            let err = (got - want).abs();
            // the reference times √2 rounds twice (2 EPS), plus the rounding of the decimal x
            let bound = 1e-14 * want.abs() + EPS * p / tofwave::detect::qfunc::phi(want);
            assert!(err <= bound, "{name}: q_inv({p:e}) = {got:e}, want {want:e}");
            m.add(if want == 0.0 { err } else { err / want.abs() }, p);
        }
        println!("q_inv vs boost {name}: {} rows in double range, max rel err {:.2e} at p={:e}", m.rows, m.err, m.at);
        assert!(m.rows >= 49, "{name}: {}", m.rows);
    }
}

#[test]
fn q_inv_matches_mpmath_table_down_to_smallest_subnormal() {
    let mut m = MaxErr::default();
    let mut sub = 0;
    for r in table(include_str!("data/numerics/mpmath/qinv_table_mpmath.csv")) {
        let e = check_qinv(r[0], num(r[1]), "qinv_table_mpmath");
        if num(r[0]) >= f64::MIN_POSITIVE {
            m.add(e, num(r[0]));
        } else {
            sub += 1; // subnormal p: checked against the bound widened by p's own rounding
        }
    }
    println!(
        "q_inv vs mpmath qinv_table: {} rows with normal p, max rel err {:.2e} at p={:e}; {sub} subnormal rows within input-rounding bound",
        m.rows, m.err, m.at
    );
    assert_eq!(m.rows + sub, 309);
    let x = q_inv(4.940_656_458_412_465_4e-324);
    assert!((x - 38.467_405_617_144_3).abs() < 1e-12, "{x}");
}

#[test]
fn statrs_comparison_in_the_tail() {
    // For the record: statrs's erfc_inv-based quantile in the tail (it is not used).
    let mut ours = MaxErr::default();
    let mut theirs = MaxErr::default();
    for r in table(include_str!("data/numerics/mpmath/qinv_table_mpmath.csv")) {
        let p = num(r[0]);
        let want = num(r[1]);
        if p < f64::MIN_POSITIVE || p > 0.1 {
            continue;
        }
        ours.add(rel(q_inv(p), want), p);
        let s = std::f64::consts::SQRT_2 * statrs::function::erf::erfc_inv(2.0 * p);
        theirs.add(rel(s, want), p);
    }
    println!("tail p in [DBL_MIN, 0.1]: ours max rel {:.2e}; statrs max rel {:.2e} at p={:e}", ours.err, theirs.err, theirs.at);
    assert!(ours.err < 1e-15);
}

#[test]
fn q_inv_special_values_and_symmetry() {
    assert_eq!(q_inv(0.0), f64::INFINITY);
    assert_eq!(q_inv(1.0), f64::NEG_INFINITY);
    assert!(q_inv(f64::NAN).is_nan());
    assert_eq!(q_inv(-1.0), f64::INFINITY);
    assert_eq!(q_inv(2.0), f64::NEG_INFINITY);
    assert_eq!(q_inv(0.5), 0.0);
    for p in [1e-10, 1e-3, 0.01, 0.05, 0.07, 0.1, 0.3, 0.49] {
        let x = q_inv(p);
        let y = q_inv(1.0 - p);
        // 1 − p is exact only when p is not tiny; compare with the exact complement
        let exact_complement = 1.0 - (1.0 - p);
        let want = -q_inv(exact_complement);
        assert!((y - want).abs() <= 1e-14 * want.abs(), "p={p}: {y} vs {want}");
        assert!(x > 0.0 && y < 0.0);
    }
    // ln_q_inv agrees with q_inv inside the double range and goes beyond it
    for p in [0.4f64, 0.2, 0.08, 0.05, 1e-5, 1e-100, 1e-300, 4.94e-324] {
        let a = ln_q_inv(p.ln());
        let b = q_inv(p);
        assert!((a - b).abs() <= 2e-15 * b.abs(), "p={p}: {a} vs {b}");
    }
    for ln_p in [-1e3, -1e4, -1e6, -1e12] {
        let x = ln_q_inv(ln_p);
        assert!((ln_q(x) - ln_p).abs() <= 1e-14 * ln_p.abs(), "ln_p={ln_p}: x={x} ln_q={}", ln_q(x));
    }
    assert_eq!(ln_q_inv(0.0), f64::NEG_INFINITY);
    assert_eq!(ln_q_inv(f64::NEG_INFINITY), f64::INFINITY);
    assert!(ln_q_inv(f64::NAN).is_nan());
}

#[test]
fn q_and_ln_q_match_mpmath_tail_table() {
    let mut mq = MaxErr::default();
    let mut ml = MaxErr::default();
    for r in table(include_str!("data/numerics/mpmath/q_tail_mpmath.csv")) {
        let x = num(r[0]); // exact: multiples of 0.5
        let want_q = num(r[1]);
        let want_l = num(r[2]);
        let lq = ln_q(x);
        let el = rel(lq, want_l);
        assert!(el <= 1e-15, "ln_q({x}) = {lq:e}, want {want_l:e}");
        ml.add(el, x);
        if want_q >= f64::MIN_POSITIVE {
            let g = q(x);
            let e = rel(g, want_q);
            assert!(e <= 1e-14, "q({x}) = {g:e}, want {want_q:e}, rel {e:e}");
            mq.add(e, x);
        }
    }
    println!("q vs mpmath q_tail (x = 0..37.5): {} rows, max rel err {:.2e} at x={}", mq.rows, mq.err, mq.at);
    println!("ln_q vs mpmath q_tail (x = 0..40): {} rows, max rel err {:.2e} at x={}", ml.rows, ml.err, ml.at);
}

#[test]
fn erfc_matches_boost_tables() {
    for (name, text) in [
        ("erf_data", include_str!("data/numerics/boost-math/erf_data.csv")),
        ("erf_large_data", include_str!("data/numerics/boost-math/erf_large_data.csv")),
        ("erf_small_data", include_str!("data/numerics/boost-math/erf_small_data.csv")),
    ] {
        let mut m = MaxErr::default();
        for r in table(text) {
            let z = num(r[0]);
            let want = num(r[2]);
            if want < f64::MIN_POSITIVE {
                continue; // erfc below the normal double range
            }
            let got = erfc(z);
            let e = rel(got, want);
            assert!(e <= 1e-14, "{name}: erfc({z:e}) = {got:e}, want {want:e}, rel {e:e}");
            m.add(e, z);
        }
        println!("erfc vs boost {name}: {} rows, max rel err {:.2e} at z={}", m.rows, m.err, m.at);
        assert!(m.rows >= 68, "{name}: {}", m.rows);
    }
}

#[test]
fn q_matches_boost_derived_q_tail() {
    // x = √2·z is irrational: its rounding to f64 moves Q by x·φ(x)/Q(x)·EPS·x ≈ (x² + 1)·EPS.
    let mut m = MaxErr::default();
    for r in table(include_str!("data/numerics/boost-math/derived_q_tail_double_range.csv")) {
        let x = num(r[1]);
        let want = num(r[2]);
        let got = q(x);
        let e = rel(got, want);
        let bound = 1e-14 + (x * x + 1.0) * EPS;
        assert!(e <= bound, "q({x}) = {got:e}, want {want:e}, rel {e:e}");
        m.add(e / bound * 1e-14, x);
    }
    println!("q vs boost derived_q_tail: {} rows, max error (scaled to the 1e-14 budget) {:.2e} at x={}", m.rows, m.err, m.at);
}

#[test]
fn ln_q_matches_scipy_log_ndtr() {
    // log Φ(x) = ln Q(−x). Tolerance: SciPy's own per-row rtol (column 3);
    // for x ≥ 8.3, −log_ndtr(x) is Q(x) to double precision: check q too.
    let mut m = MaxErr::default();
    for r in table(include_str!("data/numerics/scipy/log_ndtr_reference.csv")) {
        let x = num(r[0]);
        let want = num(r[1]);
        let rtol = num(r[2]);
        let got = ln_q(-x);
        let e = rel(got, want);
        assert!(e <= rtol, "log_ndtr({x}) = {got:e}, want {want:e}");
        m.add(e, x);
        if x >= 8.3 {
            let e2 = rel(q(x), -want);
            assert!(e2 <= rtol, "q({x}) = {:e} vs {:e}", q(x), -want);
        }
    }
    println!("ln Φ vs scipy log_ndtr: {} rows, max rel err {:.2e} at x={}", m.rows, m.err, m.at);
}

#[test]
fn q_special_values_and_far_tail() {
    assert_eq!(q(f64::INFINITY), 0.0);
    assert_eq!(q(f64::NEG_INFINITY), 1.0);
    assert!(q(f64::NAN).is_nan());
    assert_eq!(q(0.0), 0.5);
    assert_eq!(q(1e3), 0.0);
    assert!(ln_q(f64::NAN).is_nan());
    assert_eq!(ln_q(f64::INFINITY), f64::NEG_INFINITY);
    // ln Q(1e3) = −5e5 − ln(1e3) − ln√(2π) + ln(1 − 1e-6 + 3e-12)
    let want = -5e5 - 1e3f64.ln() - 0.918_938_533_204_672_8 + (-1e-6f64 + 3e-12).ln_1p();
    assert!(rel(ln_q(1e3), want) < 1e-15);
    // continuity across the switch to the asymptotic branch at x = 1e3
    let below = ln_q(999.999_999_999);
    let above = ln_q(1000.000_000_001);
    assert!((below - above).abs() < 1e-5 && below > above);
    assert_eq!(ln_q(1e200), f64::NEG_INFINITY); // −x²/2 = −5e399 is beyond the double range
    assert!(ln_q(1e150).is_finite());
    // negative x: Q(−x) = 1 − Q(x)
    for x in [0.1, 1.0, 3.0, 10.0] {
        assert!(rel(q(-x), 1.0 - q(x)) < 1e-15);
        assert!(rel(ln_q(-x), (-q(x)).ln_1p()) < 1e-15);
    }
    // round trip through the whole normal range
    for k in 1..=307 {
        let p = 10f64.powi(-k);
        // Q amplifies an x error by x²: allow the q_inv rounding (x²·EPS) and q's own 1e-14
        let x = q_inv(p);
        assert!(rel(q(x), p) < 1e-14 + 2.0 * (x * x + 1.0) * EPS, "k={k}");
    }
}

#[test]
fn per_cell_pfa_is_accurate_at_the_extremes() {
    // P = 0.5 over 2 cells: 1 − √0.5
    assert!(rel(per_cell_pfa(0.5, 2.0), 1.0 - 0.5f64.sqrt()) < 1e-15);
    // tiny P, huge M: P/M (1 + P/2) to double precision
    assert!(rel(per_cell_pfa(1e-300, 1e9), 1e-309) < 1e-6); // subnormal result: ~47 bits
    assert!(rel(per_cell_pfa(1e-12, 1e9), 1e-21 * (1.0 + 0.5e-12)) < 1e-15);
    // round trip: 1 − (1 − p)^M = P
    for (pt, m) in [(1e-3, 2500.0), (0.1, 1e6), (0.5, 1e9), (1e-9, 7.0)] {
        let p = per_cell_pfa(pt, m);
        let back = -(m * (-p).ln_1p()).exp_m1();
        assert!(rel(back, pt) < 1e-13, "{pt} {m}: {back}");
    }
    assert_eq!(per_cell_pfa(1e-3, 1.0), 1e-3);
    assert_eq!(per_cell_pfa(0.0, 10.0), 0.0);
    assert_eq!(per_cell_pfa(1.0, 10.0), 1.0);
}

// ---------------------------------------------------------------- stats ----

use tofwave::detect::stats::{
    binomial_acceptance_counts, binomial_two_sided_interval_99, clopper_pearson, clopper_pearson_alpha, jarque_bera,
    poisson_interval, poisson_interval_alpha,
};

/// Binomial pmf terms by the recurrence, in f64: an independent reference for small n.
fn binom_pmf(n: u64, p: f64) -> Vec<f64> {
    let mut v = vec![0.0; n as usize + 1];
    // log-space start to avoid underflow, then normalise
    let mut lp = n as f64 * (-p).ln_1p();
    for k in 0..=n {
        v[k as usize] = lp.exp();
        lp += ((n - k) as f64 / (k + 1) as f64).ln() + p.ln() - (-p).ln_1p();
    }
    v
}

#[test]
fn clopper_pearson_closed_forms_k0_and_kn() {
    // k = 0: upper = 1 − (α/2)^(1/n); k = n: lower = (α/2)^(1/n). The solver does not special-case these.
    let mut worst: f64 = 0.0;
    for n in [1u64, 2, 10, 1000, 1_000_000, 1_000_000_000] {
        for alpha in [0.05, 0.01, 1e-6, 1e-12, 1e-100] {
            let (lo, hi) = clopper_pearson_alpha(0, n, alpha);
            let want_hi = -((0.5 * alpha as f64).ln() / n as f64).exp_m1();
            assert_eq!(lo, 0.0);
            worst = worst.max(rel(hi, want_hi));
            assert!(rel(hi, want_hi) < 1e-12, "n={n} α={alpha}: {hi:e} vs {want_hi:e}");
            let (lo, hi) = clopper_pearson_alpha(n, n, alpha);
            let want_lo = ((0.5 * alpha as f64).ln() / n as f64).exp();
            assert_eq!(hi, 1.0);
            // the bound near 1: compare its complement, which carries the information
            assert!(rel(1.0 - lo, -(0.5 * alpha as f64).ln() / n as f64 * 1.0).abs() < 1.0);
            worst = worst.max(rel(lo, want_lo));
            assert!(rel(lo, want_lo) < 1e-13, "n={n} α={alpha}: {lo:e} vs {want_lo:e}");
        }
    }
    println!("Clopper-Pearson k=0 / k=n vs closed form: max rel err {worst:.2e}");
}

#[test]
fn clopper_pearson_solves_its_defining_equations() {
    // Independent check by direct pmf summation (n ≤ 200).
    let mut worst: f64 = 0.0;
    for (k, n) in [(1u64, 10u64), (3, 20), (7, 20), (50, 200), (199, 200), (1, 200)] {
        for conf in [0.95, 0.99] {
            let a2 = 0.5 * (1.0 - conf);
            let (lo, hi) = clopper_pearson(k, n, conf);
            let tail_lo: f64 = binom_pmf(n, lo)[k as usize..].iter().sum();
            let tail_hi: f64 = binom_pmf(n, hi)[..=k as usize].iter().sum();
            worst = worst.max(rel(tail_lo, a2)).max(rel(tail_hi, a2));
            assert!(rel(tail_lo, a2) < 1e-11 && rel(tail_hi, a2) < 1e-11, "k={k} n={n}: {tail_lo} {tail_hi}");
        }
    }
    println!("Clopper-Pearson tails vs direct pmf sums: max rel err {worst:.2e}");
    // The classic textbook value: 0/10 at 95 %: upper 0.30850
    let (_, hi) = clopper_pearson(0, 10, 0.95);
    assert!((hi - 0.308_497_2).abs() < 1e-6);
    // degenerate inputs are defined
    assert_eq!(clopper_pearson(0, 0, 0.95), (0.0, 1.0));
    assert_eq!(clopper_pearson(5, 3, 0.95), clopper_pearson(3, 3, 0.95));
    assert_eq!(clopper_pearson(1, 10, f64::NAN), (0.0, 1.0));
}

#[test]
fn clopper_pearson_large_n_and_statrs_comparison() {
    use statrs::distribution::{Beta, ContinuousCDF};
    // k = 1 of n = 1e9: lower bound solves 1 − (1 − p)^n = α/2, i.e. p = −expm1(log1p(−α/2)/n);
    // upper bound solves (1 − p)^n (1 + n p/(1 − p)) = α/2 (checked through its residual).
    let n = 1_000_000_000u64;
    let (lo, hi) = clopper_pearson(1, n, 0.95);
    let want_lo = -((-0.025f64).ln_1p() / n as f64).exp_m1();
    assert!(rel(lo, want_lo) < 1e-12, "{lo:e} vs {want_lo:e}");
    let nf = n as f64;
    let cdf1 = (nf * (-hi).ln_1p()).exp() * (1.0 + nf * hi / (1.0 - hi));
    assert!(rel(cdf1, 0.025) < 1e-9, "{cdf1}");
    println!("k=1,n=1e9: ({lo:e}, {hi:e}); exact lower {want_lo:e}, upper residual {:.1e}", rel(cdf1, 0.025));
    // statrs on a smaller problem (n = 1e6; at 1e9 its inverse_cdf does not return in reasonable time)
    let n6 = 1_000_000u64;
    let (lo6, hi6) = clopper_pearson(1, n6, 0.95);
    let s_lo = Beta::new(1.0, n6 as f64).unwrap().inverse_cdf(0.025);
    let s_hi = Beta::new(2.0, n6 as f64 - 1.0).unwrap().inverse_cdf(0.975);
    let want_lo6 = -((-0.025f64).ln_1p() / n6 as f64).exp_m1();
    println!(
        "k=1,n=1e6: ours ({lo6:e}, {hi6:e}), statrs ({s_lo:e}, {s_hi:e}); exact lower {want_lo6:e}: rel err ours {:.1e}, statrs {:.1e}",
        rel(lo6, want_lo6),
        rel(s_lo, want_lo6)
    );
    assert!(rel(lo6, want_lo6) < 1e-12);
    // half-and-half at n = 1e9: symmetric about 0.5, half-width ≈ 1.96·√(0.25/n)
    let t = std::time::Instant::now();
    let (lo, hi) = clopper_pearson(500_000_000, n, 0.95);
    println!("k=n/2, n=1e9: ({lo}, {hi}) in {:?}", t.elapsed());
    assert!((lo + hi - 1.0).abs() < 1e-12);
    let hw = 1.959_963_984_540_054 * (0.25 / nf).sqrt();
    assert!(rel(hi - 0.5, hw) < 1e-3, "{}", hi - 0.5);
}

#[test]
fn poisson_garwood_interval() {
    // k = 0: (0, −ln(α/2)); textbook values (Garwood 1936 / chi-square tables) for 95 %.
    let (lo, hi) = poisson_interval(0, 0.95);
    assert_eq!(lo, 0.0);
    assert!(rel(hi, -(0.025f64).ln()) < 1e-13);
    let (lo, hi) = poisson_interval(1, 0.95);
    assert!((lo - 0.025_317_8).abs() < 1e-7 && (hi - 5.571_643_2).abs() < 1e-6, "{lo} {hi}");
    let (lo, hi) = poisson_interval(10, 0.95);
    assert!((lo - 4.795_389_5).abs() < 1e-6 && (hi - 18.390_356).abs() < 1e-5, "{lo} {hi}");
    // defining equations by direct summation of the Poisson pmf
    for k in [1u64, 2, 5, 30, 100] {
        for alpha in [0.05, 0.01, 1e-6] {
            let (lo, hi) = poisson_interval_alpha(k, alpha);
            let pmf = |mu: f64, j: u64| ((j as f64) * mu.ln() - mu - (1..=j).map(|i| (i as f64).ln()).sum::<f64>()).exp();
            let ge_k: f64 = (k..k + 2000).map(|j| pmf(lo, j)).sum();
            let le_k: f64 = (0..=k).map(|j| pmf(hi, j)).sum();
            assert!(rel(ge_k, alpha / 2.0) < 1e-8, "k={k} α={alpha}: {ge_k}");
            assert!(rel(le_k, alpha / 2.0) < 1e-10, "k={k} α={alpha}: {le_k}");
        }
    }
    assert_eq!(poisson_interval(3, f64::NAN), (0.0, f64::INFINITY));
}

#[test]
fn binomial_acceptance_band_has_the_stated_coverage() {
    for (n, p) in [(1000u64, 0.01), (20_000, 1e-3), (100_000, 1e-2), (50, 0.5)] {
        let (lo, hi) = binomial_acceptance_counts(n, p, 0.99);
        let pmf = binom_pmf(n, p);
        let below: f64 = pmf[..lo as usize].iter().sum();
        let above: f64 = pmf[hi as usize + 1..].iter().sum();
        // each tail ≤ 0.5 %, and the band is the tightest such (one more count would exceed)
        assert!(below <= 0.005 + 1e-12 && above <= 0.005 + 1e-12, "n={n} p={p}: {below} {above}");
        assert!(below + pmf[lo as usize] > 0.005 && above + pmf[hi as usize] > 0.005, "n={n} p={p}");
        let (flo, fhi) = binomial_two_sided_interval_99(n, p);
        assert_eq!((flo, fhi), (lo as f64 / n as f64, hi as f64 / n as f64));
        println!("99 % band for n={n}, p={p}: counts [{lo}, {hi}]");
    }
}

#[test]
fn jarque_bera_values() {
    let (jb, p) = jarque_bera(600, 0.2, 0.4);
    assert!(rel(jb, 100.0 * (0.04 + 0.04)) < 1e-15);
    assert!(rel(p, (-4.0f64).exp()) < 1e-15);
    assert_eq!(jarque_bera(0, 1.0, 1.0), (0.0, 1.0));
}

// ------------------------------------------------------ extreme (Monte-Carlo) ----

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use tofwave::detect::extreme::{max_exceed_prob, threshold_for_report};

/// Trials per Monte-Carlo case: full size in release (CI), 1/50 in debug so
/// a debug `cargo test` stays quick; the acceptance band is derived from the
/// trial count actually run, so both are valid tests.
fn trials(release: u64) -> u64 {
    if cfg!(debug_assertions) { release / 50 } else { release }
}

/// 26-tap Gaussian kernel (σ = 4 samples, like a matched filter for a
/// ~9 ns FWHM pulse at 1 GS/s), normalised to unit output variance.
fn gaussian_kernel() -> Vec<f64> {
    let mut h: Vec<f64> = (0..26).map(|i| (-((i as f64 - 12.5).powi(2)) / (2.0 * 16.0)).exp()).collect();
    let norm = h.iter().map(|v| v * v).sum::<f64>().sqrt();
    h.iter_mut().for_each(|v| *v /= norm);
    h
}

/// Maxima of `trials` sequences of `n` cells: white if `kernel` is None,
/// else white noise correlated with the kernel (exact stationary MA process).
fn simulate_maxima(n: usize, kernel: Option<&[f64]>, trials: u64, seed: u64) -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let taps = kernel.map_or(1, |k| k.len());
    let mut w = vec![0.0f64; n + taps - 1];
    let mut maxima = Vec::with_capacity(trials as usize);
    for _ in 0..trials {
        w.iter_mut().for_each(|v| *v = StandardNormal.sample(&mut rng));
        let m = match kernel {
            None => w.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            Some(h) => (0..n)
                .map(|j| w[j..j + taps].iter().zip(h).map(|(a, b)| a * b).sum::<f64>())
                .fold(f64::NEG_INFINITY, f64::max),
        };
        maxima.push(m);
    }
    maxima
}

/// Checks the observed exceedance fraction at each p_report against the
/// two-sided 99 % binomial acceptance band for the trial count.
fn check_report_rate(label: &str, maxima: &[f64], n: usize, rho1: f64, p_reports: &[f64]) {
    let t = maxima.len() as u64;
    for &p in p_reports {
        let th = threshold_for_report(p, n, rho1);
        let hits = maxima.iter().filter(|&&m| m > th.u).count() as u64;
        let (lo, hi) = binomial_acceptance_counts(t, p, 0.99);
        let indep_u = q_inv(per_cell_pfa(p, n as f64));
        let indep_hits = maxima.iter().filter(|&&m| m > indep_u).count();
        println!(
            "{label}: n={n} rho1={rho1:.4} p_report={p:e}: u={:.4} (independent-cell u={indep_u:.4}), cells_eff={:.1}; \
             observed {hits}/{t} = {:.3e} (99 % band [{lo}, {hi}]); independent-cell threshold gives {:.3e}",
            th.u,
            th.cells_effective,
            hits as f64 / t as f64,
            indep_hits as f64 / t as f64
        );
        assert!(lo <= hits && hits <= hi, "{label} p={p}: {hits} outside [{lo}, {hi}]");
        assert!((max_exceed_prob(th.u, n, rho1) / p - 1.0).abs() < 1e-9);
    }
}

#[test]
fn report_threshold_monte_carlo_white() {
    let n = 1000;
    let maxima = simulate_maxima(n, None, trials(100_000), 0x5eed_0001);
    check_report_rate("white", &maxima, n, 0.0, &[1e-2, 1e-3]);
}

#[test]
fn report_threshold_monte_carlo_gaussian_kernel() {
    let h = gaussian_kernel();
    let rho1: f64 = h.windows(2).map(|w| w[0] * w[1]).sum();
    let n = 2000;
    let maxima = simulate_maxima(n, Some(&h), trials(100_000), 0x5eed_0002);
    check_report_rate("gaussian-kernel MA", &maxima, n, rho1, &[1e-2, 1e-3]);
}

#[test]
#[ignore = "slow: ~10^6-10^7 trials; run with --ignored in release"]
fn report_threshold_monte_carlo_deep_tail() {
    let n = 1000;
    let maxima = simulate_maxima(n, None, 3_000_000, 0x5eed_0003);
    check_report_rate("white (deep)", &maxima, n, 0.0, &[1e-4, 1e-5]);
    let h = gaussian_kernel();
    let rho1: f64 = h.windows(2).map(|w| w[0] * w[1]).sum();
    let maxima = simulate_maxima(2000, Some(&h), 2_000_000, 0x5eed_0004);
    check_report_rate("gaussian-kernel MA (deep)", &maxima, 2000, rho1, &[1e-4, 1e-5]);
}
