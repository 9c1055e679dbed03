//! Accuracy of the detector's statistical numerics against external
//! high-precision tables (Boost.Math, mpmath, SciPy; see
//! `tests/data/numerics/README.md`), plus Monte-Carlo checks of the
//! per-report threshold and of the noise fitter.
//!
//! Measured maximum errors are printed (`cargo test --release --test
//! numerics -- --nocapture`).

use tofwave::math::special::{erfc, ln_q, ln_q_inv, per_cell_pfa, q, q_inv};

/// One table: rows of decimal strings, header and `#` comments skipped.
fn table(text: &str) -> Vec<Vec<&str>> {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .skip(1)
        .map(|l| l.split(',').map(str::trim).collect())
        .collect()
}

fn num(s: &str) -> f64 {
    s.parse::<f64>()
        .unwrap_or_else(|e| panic!("bad number {s:?}: {e}"))
}

const EPS: f64 = f64::EPSILON / 2.0; // unit roundoff 2^-53 = 1.11e-16

/// Relative error of `got` against the f64 rounding of a decimal reference.
fn rel(got: f64, want: f64) -> f64 {
    if got == want {
        0.0
    } else {
        ((got - want) / want).abs()
    }
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

/// For a short decimal p = M·10^−E (M < 2^53, E ≤ 22) the exact rounding
/// residual p − fl(p), from an FMA: then the reference can be moved to the
/// f64 input exactly (x(fl p) = x(p) + (p − fl p)/φ(x)).
fn decimal_residual(p_str: &str, p: f64) -> Option<f64> {
    let (mant, exp) = match p_str.split_once(['e', 'E']) {
        Some((m, e)) => (m, e.parse::<i32>().ok()?),
        None => (p_str, 0),
    };
    let (int, frac) = mant.split_once('.').unwrap_or((mant, ""));
    let digits = format!("{int}{frac}");
    let m: u64 = digits.parse().ok()?;
    let e = frac.len() as i32 - exp; // p = m / 10^e
    if m >= 1 << 53 || !(0..=22).contains(&e) {
        return None;
    }
    let scale = 10f64.powi(e); // exact for e ≤ 22
    Some((-p).mul_add(scale, m as f64) / scale)
}

/// Checks q_inv at one (p, x) pair: relative error must be ≤ 1e-14 beyond
/// the unavoidable part caused by rounding the decimal p to f64. Where the
/// residual of that rounding is known exactly the reference is corrected by
/// it; otherwise the bound is widened by |dx| ≤ ½ulp(p)/φ(x). Returns the
/// relative error (after the correction, when there is one).
fn check_qinv(p_str: &str, want: f64, table_name: &str) -> f64 {
    let p = num(p_str);
    let got = q_inv(p);
    let phi = tofwave::math::special::phi(want);
    let (want, input_rounding) = match decimal_residual(p_str, p) {
        Some(res) => (want + res / phi, 0.0),
        // half an ulp of p: relative for normal p, absolute 2^-1075 for subnormal p
        None => (want, (EPS * p / phi).max(0.5 * (f64::from_bits(1) / phi))),
    };
    let err = (got - want).abs();
    let bound = 1e-14 * want.abs() + input_rounding;
    assert!(
        err <= bound,
        "{table_name}: q_inv({p_str}) = {got:e}, want {want:e}, err {err:e} > {bound:e}"
    );
    if want == 0.0 { err } else { err / want.abs() }
}

#[test]
fn q_inv_matches_boost_derived_table() {
    let mut m = MaxErr::default();
    for r in table(include_str!(
        "../data/numerics/boost-math/derived_qinv_double_range.csv"
    )) {
        let e = check_qinv(r[0], num(r[1]), "derived_qinv_double_range");
        m.add(e, num(r[0]));
    }
    println!(
        "q_inv vs boost derived_qinv_double_range: {} rows, max rel err {:.2e} at p={:e}",
        m.rows, m.err, m.at
    );
    assert_eq!(m.rows, 96);
}

#[test]
fn q_inv_matches_boost_erfc_inv_tables() {
    // erfc_inv(x) = Q⁻¹(x/2)/√2; x/2 is exact in binary while x/2 ≥ DBL_MIN.
    for (name, text) in [
        (
            "erfc_inv_data",
            include_str!("../data/numerics/boost-math/erfc_inv_data.csv"),
        ),
        (
            "erfc_inv_big_data",
            include_str!("../data/numerics/boost-math/erfc_inv_big_data.csv"),
        ),
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
            let bound = 1e-14 * want.abs() + EPS * p / tofwave::math::special::phi(want);
            assert!(
                err <= bound,
                "{name}: q_inv({p:e}) = {got:e}, want {want:e}"
            );
            m.add(if want == 0.0 { err } else { err / want.abs() }, p);
        }
        println!(
            "q_inv vs boost {name}: {} rows in double range, max rel err {:.2e} at p={:e}",
            m.rows, m.err, m.at
        );
        assert!(m.rows >= 49, "{name}: {}", m.rows);
    }
}

#[test]
fn q_inv_matches_mpmath_table_down_to_smallest_subnormal() {
    let mut m = MaxErr::default();
    let mut sub = 0;
    for r in table(include_str!("../data/numerics/mpmath/qinv_table_mpmath.csv")) {
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
    let x = q_inv(f64::from_bits(1));
    assert!((x - 38.467_405_617_144_3).abs() < 1e-12, "{x}");
}

#[test]
fn statrs_comparison_in_the_tail() {
    // For the record: statrs's erfc_inv-based quantile in the tail (it is not used).
    let mut ours = MaxErr::default();
    let mut theirs = MaxErr::default();
    for r in table(include_str!("../data/numerics/mpmath/qinv_table_mpmath.csv")) {
        let p = num(r[0]);
        let want = num(r[1]);
        if !(f64::MIN_POSITIVE..=0.1).contains(&p) {
            continue;
        }
        ours.add(rel(q_inv(p), want), p);
        let s = std::f64::consts::SQRT_2 * statrs::function::erf::erfc_inv(2.0 * p);
        theirs.add(rel(s, want), p);
    }
    println!(
        "tail p in [DBL_MIN, 0.1]: ours max rel {:.2e}; statrs max rel {:.2e} at p={:e}",
        ours.err, theirs.err, theirs.at
    );
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
        assert!(
            (y - want).abs() <= 1e-14 * want.abs(),
            "p={p}: {y} vs {want}"
        );
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
        assert!(
            (ln_q(x) - ln_p).abs() <= 1e-14 * ln_p.abs(),
            "ln_p={ln_p}: x={x} ln_q={}",
            ln_q(x)
        );
    }
    assert_eq!(ln_q_inv(0.0), f64::NEG_INFINITY);
    assert_eq!(ln_q_inv(f64::NEG_INFINITY), f64::INFINITY);
    assert!(ln_q_inv(f64::NAN).is_nan());
}

#[test]
fn q_and_ln_q_match_mpmath_tail_table() {
    let mut mq = MaxErr::default();
    let mut ml = MaxErr::default();
    for r in table(include_str!("../data/numerics/mpmath/q_tail_mpmath.csv")) {
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
    println!(
        "q vs mpmath q_tail (x = 0..37.5): {} rows, max rel err {:.2e} at x={}",
        mq.rows, mq.err, mq.at
    );
    println!(
        "ln_q vs mpmath q_tail (x = 0..40): {} rows, max rel err {:.2e} at x={}",
        ml.rows, ml.err, ml.at
    );
}

#[test]
fn erfc_matches_boost_tables() {
    for (name, text) in [
        (
            "erf_data",
            include_str!("../data/numerics/boost-math/erf_data.csv"),
        ),
        (
            "erf_large_data",
            include_str!("../data/numerics/boost-math/erf_large_data.csv"),
        ),
        (
            "erf_small_data",
            include_str!("../data/numerics/boost-math/erf_small_data.csv"),
        ),
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
            assert!(
                e <= 1e-14,
                "{name}: erfc({z:e}) = {got:e}, want {want:e}, rel {e:e}"
            );
            m.add(e, z);
        }
        println!(
            "erfc vs boost {name}: {} rows, max rel err {:.2e} at z={}",
            m.rows, m.err, m.at
        );
        assert!(m.rows >= 68, "{name}: {}", m.rows);
    }
}

#[test]
fn q_matches_boost_derived_q_tail() {
    // x = √2·z is irrational: its rounding to f64 moves Q by x·φ(x)/Q(x)·EPS·x ≈ (x² + 1)·EPS.
    let mut m = MaxErr::default();
    for r in table(include_str!(
        "../data/numerics/boost-math/derived_q_tail_double_range.csv"
    )) {
        let x = num(r[1]);
        let want = num(r[2]);
        let got = q(x);
        let e = rel(got, want);
        let bound = 1e-14 + (x * x + 1.0) * EPS;
        assert!(e <= bound, "q({x}) = {got:e}, want {want:e}, rel {e:e}");
        m.add(e / bound * 1e-14, x);
    }
    println!(
        "q vs boost derived_q_tail: {} rows, max error (scaled to the 1e-14 budget) {:.2e} at x={}",
        m.rows, m.err, m.at
    );
}

#[test]
fn ln_q_matches_scipy_log_ndtr() {
    // log Φ(x) = ln Q(−x). Tolerance: SciPy's own per-row rtol (column 3);
    // for x ≥ 8.3, −log_ndtr(x) is Q(x) to double precision: check q too.
    let mut m = MaxErr::default();
    for r in table(include_str!("../data/numerics/scipy/log_ndtr_reference.csv")) {
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
    println!(
        "ln Φ vs scipy log_ndtr: {} rows, max rel err {:.2e} at x={}",
        m.rows, m.err, m.at
    );
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
    let above = ln_q(1_000.000_000_001);
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

use tofwave::math::stats::{
    binomial_acceptance_counts, binomial_two_sided_interval_99, clopper_pearson,
    clopper_pearson_alpha, clopper_pearson_solved, jarque_bera, poisson_interval, poisson_interval_alpha,
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
    // k = 0: upper = 1 − (α/2)^(1/n); k = n: lower = (α/2)^(1/n).
    // `clopper_pearson_alpha` returns these closed forms; the root finder
    // that solves every other bound (`clopper_pearson_solved`, which does
    // not special-case them) must agree with them.
    let mut worst: f64 = 0.0;
    for n in [1u64, 2, 10, 1000, 1_000_000, 1_000_000_000] {
        for alpha in [0.05, 0.01, 1e-6, 1e-12, 1e-100] {
            for (k, (lo, hi)) in [(0, clopper_pearson_alpha(0, n, alpha)), (n, clopper_pearson_alpha(n, n, alpha))] {
                let solved = clopper_pearson_solved(k, n, alpha);
                assert!(
                    rel(lo, solved.0) < 1e-12 && rel(hi, solved.1) < 1e-12,
                    "k={k} n={n} α={alpha}: closed form ({lo:e}, {hi:e}), solved ({:e}, {:e})",
                    solved.0,
                    solved.1
                );
            }
            let (lo, hi) = clopper_pearson_solved(0, n, alpha);
            let want_hi = -((0.5 * alpha).ln() / n as f64).exp_m1();
            assert_eq!(lo, 0.0);
            worst = worst.max(rel(hi, want_hi));
            assert!(
                rel(hi, want_hi) < 1e-12,
                "n={n} α={alpha}: {hi:e} vs {want_hi:e}"
            );
            let (lo, hi) = clopper_pearson_solved(n, n, alpha);
            let want_lo = ((0.5 * alpha).ln() / n as f64).exp();
            assert_eq!(hi, 1.0);
            worst = worst.max(rel(lo, want_lo));
            assert!(
                rel(lo, want_lo) < 1e-13,
                "n={n} α={alpha}: {lo:e} vs {want_lo:e}"
            );
        }
    }
    println!("Clopper-Pearson k=0 / k=n vs closed form: max rel err {worst:.2e}");
}

#[test]
fn clopper_pearson_solves_its_defining_equations() {
    // Independent check by direct pmf summation (n ≤ 200).
    let mut worst: f64 = 0.0;
    for (k, n) in [
        (1u64, 10u64),
        (3, 20),
        (7, 20),
        (50, 200),
        (199, 200),
        (1, 200),
    ] {
        for conf in [0.95, 0.99] {
            let a2 = 0.5 * (1.0 - conf);
            let (lo, hi) = clopper_pearson(k, n, conf);
            let tail_lo: f64 = binom_pmf(n, lo)[k as usize..].iter().sum();
            let tail_hi: f64 = binom_pmf(n, hi)[..=k as usize].iter().sum();
            worst = worst.max(rel(tail_lo, a2)).max(rel(tail_hi, a2));
            assert!(
                rel(tail_lo, a2) < 1e-11 && rel(tail_hi, a2) < 1e-11,
                "k={k} n={n}: {tail_lo} {tail_hi}"
            );
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
    println!(
        "k=1,n=1e9: ({lo:e}, {hi:e}); exact lower {want_lo:e}, upper residual {:.1e}",
        rel(cdf1, 0.025)
    );
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
    assert!(
        (lo - 0.025_317_8).abs() < 1e-7 && (hi - 5.571_643_2).abs() < 1e-6,
        "{lo} {hi}"
    );
    let (lo, hi) = poisson_interval(10, 0.95);
    assert!(
        (lo - 4.795_389_5).abs() < 1e-6 && (hi - 18.390_356).abs() < 1e-5,
        "{lo} {hi}"
    );
    // defining equations by direct summation of the Poisson pmf
    for k in [1u64, 2, 5, 30, 100] {
        for alpha in [0.05, 0.01, 1e-6] {
            let (lo, hi) = poisson_interval_alpha(k, alpha);
            let pmf = |mu: f64, j: u64| {
                ((j as f64) * mu.ln() - mu - (1..=j).map(|i| (i as f64).ln()).sum::<f64>()).exp()
            };
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
        assert!(
            below <= 0.005 + 1e-12 && above <= 0.005 + 1e-12,
            "n={n} p={p}: {below} {above}"
        );
        assert!(
            below + pmf[lo as usize] > 0.005 && above + pmf[hi as usize] > 0.005,
            "n={n} p={p}"
        );
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

/// Trials per Monte-Carlo case: full size in release (CI), 1/10 in debug so
/// a debug `cargo test` stays quick; the acceptance band is derived from the
/// trial count actually run, so both are valid tests.
fn trials(release: u64) -> u64 {
    if cfg!(debug_assertions) {
        release / 10
    } else {
        release
    }
}

/// 26-tap Gaussian kernel (σ = 4 samples, like a matched filter for a
/// ~9 ns FWHM pulse at 1 GS/s), normalised to unit output variance.
fn gaussian_kernel() -> Vec<f64> {
    let mut h: Vec<f64> = (0..26)
        .map(|i| (-((i as f64 - 12.5).powi(2)) / (2.0 * 16.0)).exp())
        .collect();
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
        w.iter_mut()
            .for_each(|v| *v = StandardNormal.sample(&mut rng));
        let m = match kernel {
            None => w.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            Some(h) => (0..n)
                .map(|j| {
                    w[j..j + taps]
                        .iter()
                        .zip(h)
                        .map(|(a, b)| a * b)
                        .sum::<f64>()
                })
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
        assert!(
            lo <= hits && hits <= hi,
            "{label} p={p}: {hits} outside [{lo}, {hi}]"
        );
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
    check_report_rate(
        "gaussian-kernel MA (deep)",
        &maxima,
        2000,
        rho1,
        &[1e-4, 1e-5],
    );
}

// ---------------------------------------------------------------- noise ----

use tofwave::detect::noise_model::{Moments, NoiseFitter, NoiseTracker, autocorrelation, welch_psd};

fn normals(n: usize, seed: u64) -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| StandardNormal.sample(&mut rng)).collect()
}

/// Two-pass reference moments (mean, unbiased var, g1, g2) of values given
/// as offsets from an exact origin.
fn two_pass(r: &[f64]) -> (f64, f64, f64, f64) {
    let n = r.len() as f64;
    let mean = r.iter().sum::<f64>() / n;
    let (mut m2, mut m3, mut m4) = (0.0, 0.0, 0.0);
    for &v in r {
        let d = v - mean;
        m2 += d * d;
        m3 += d * d * d;
        m4 += d * d * d * d;
    }
    (
        mean,
        m2 / (n - 1.0),
        n.sqrt() * m3 / m2.powf(1.5),
        n * m4 / (m2 * m2) - 3.0,
    )
}

#[test]
fn moments_have_no_cancellation_at_large_offset() {
    // mean 1 kV, σ 1 µV: x − 1000 is exact (Sterbenz), so the two-pass
    // reference on the offsets is exact to ~1e-15.
    let z = normals(100_000, 11);
    let x: Vec<f64> = z.iter().map(|v| 1e3 + 1e-6 * v).collect();
    let r: Vec<f64> = x.iter().map(|v| v - 1e3).collect();
    let (mean_r, var_r, g1, g2) = two_pass(&r);
    let mut m = Moments::default();
    x.iter().for_each(|&v| m.push(v));
    let sigma_err = rel(m.variance().sqrt(), var_r.sqrt());
    println!(
        "1 kV ± 1 µV: σ rel err {sigma_err:.2e}, skew abs err {:.1e}",
        (m.skewness() - g1).abs()
    );
    assert!(sigma_err < 1e-9);
    assert!((m.mean() - (1e3 + mean_r)).abs() < 1e-12);
    assert!((m.skewness() - g1).abs() < 1e-6 && (m.excess_kurtosis() - g2).abs() < 1e-6);
}

#[test]
fn moments_merge_equals_single_pass() {
    let x: Vec<f64> = normals(10_000, 12)
        .iter()
        .map(|v| 3.0 + 0.5 * v * v)
        .collect(); // skewed data
    let mut whole = Moments::default();
    x.iter().for_each(|&v| whole.push(v));
    let mut merged = Moments::default();
    for chunk in x.chunks(777) {
        let mut part = Moments::default();
        chunk.iter().for_each(|&v| part.push(v));
        merged.merge(&part);
    }
    merged.merge(&Moments::default());
    assert_eq!(merged.count(), whole.count());
    assert!(rel(merged.mean(), whole.mean()) < 1e-14);
    assert!(rel(merged.variance(), whole.variance()) < 1e-12);
    assert!(rel(merged.skewness(), whole.skewness()) < 1e-11);
    assert!(rel(merged.excess_kurtosis(), whole.excess_kurtosis()) < 1e-11);
}

#[test]
fn noise_tracker_forgets_and_follows_drift() {
    let frames: Vec<Vec<f64>> = (0..60).map(|i| normals(1000, 100 + i)).collect();
    // λ = 1: identical to merging everything
    let mut t1 = NoiseTracker::with_forgetting(1.0);
    let mut all = Moments::default();
    for f in &frames {
        let mut m = Moments::default();
        f.iter().for_each(|&v| m.push(v));
        t1.update(&m);
        all.merge(&m);
    }
    assert!(rel(t1.variance(), all.variance()) < 1e-12);
    assert!((t1.mean() - all.mean()).abs() < 1e-14);
    // λ = 0.9: σ steps from 1 to 2 after frame 30; 30 frames later the weight
    // of the old regime is 0.9^30 ≈ 4 %, so the variance is ≈ 4·0.96 + 0.04 = 3.88.
    let mut t = NoiseTracker::with_forgetting(0.9);
    for (i, f) in frames.iter().enumerate() {
        let scale = if i < 30 { 1.0 } else { 2.0 };
        let mut m = Moments::default();
        f.iter().for_each(|&v| m.push(scale * v));
        t.update(&m);
    }
    let old_w = 0.9f64.powi(30);
    let want = 4.0 * (1.0 - old_w) + old_w;
    // statistical tolerance: n_eff ≈ 19000 samples, sd of a variance estimate ≈ want·√(2/n_eff) ≈ 0.04; allow 4 sd
    assert!(
        (t.variance() - want).abs() < 4.0 * want * (2.0 / t.effective_samples()).sqrt(),
        "{} vs {want}",
        t.variance()
    );
    let n_eff = t.effective_samples();
    assert!((n_eff / (1000.0 * 1.9 / 0.1) - 1.0).abs() < 0.01, "{n_eff}"); // m(1+λ)/(1−λ)
    // λ = 0 keeps only the latest frame
    let mut t0 = NoiseTracker::with_forgetting(0.0);
    let mut last = Moments::default();
    for f in &frames[..3] {
        last = Moments::default();
        f.iter().for_each(|&v| last.push(v));
        t0.update(&last);
    }
    assert!(rel(t0.variance(), last.variance()) < 1e-12);
}

#[test]
fn noise_fit_degenerate_inputs_are_defined() {
    let mut f = NoiseFitter::default();
    let s = f.fit(&[], 0.01);
    assert_eq!(
        (s.samples, s.sigma_v, s.gaussian, s.contaminated),
        (0, 0.0, false, false)
    );
    let s = f.fit(&[&[2.5]], 0.01);
    assert_eq!(
        (s.samples, s.mean_v, s.sigma_v, s.robust_sigma_v),
        (1, 2.5, 0.0, 0.0)
    );
    assert!(!s.gaussian && s.normality_p_value.is_finite());
    let flat = [0.7; 500];
    let s = f.fit(&[&flat], 0.01);
    assert_eq!(
        (s.mean_v, s.sigma_v, s.skewness, s.excess_kurtosis),
        (0.7, 0.0, 0.0, 0.0)
    );
    assert!(!s.gaussian && !s.contaminated && s.normality_p_value == 0.0);
    // NaN/Inf are skipped and counted
    let s = f.fit(
        &[
            &[1.0, f64::NAN, 2.0],
            &[f64::INFINITY, 3.0, f64::NEG_INFINITY],
        ],
        0.01,
    );
    assert_eq!((s.samples, f.skipped_nonfinite()), (3, 3));
    assert!(rel(s.mean_v, 2.0) < 1e-15 && rel(s.sigma_v, 1.0) < 1e-15);
    for v in [
        s.mean_v,
        s.sigma_v,
        s.skewness,
        s.excess_kurtosis,
        s.normality_p_value,
        s.robust_sigma_v,
    ] {
        assert!(v.is_finite());
    }
}

#[test]
fn noise_fit_contamination_false_alarm_rate_matches_alpha() {
    // Under H0 (pure Gaussian) the criterion flags with probability ≈ α; the
    // observed count must lie in the 99 % binomial band for the number of fits.
    let alpha = 0.05;
    for (n, fits) in [
        (1000usize, trials(4000)),
        (100, trials(4000)),
        (30, trials(4000)),
    ] {
        let mut rng = ChaCha8Rng::seed_from_u64(7 + n as u64);
        let mut fitter = NoiseFitter::default();
        let mut buf = vec![0.0; n];
        let mut flagged = 0u64;
        for _ in 0..fits {
            buf.iter_mut().for_each(|v| {
                let z: f64 = StandardNormal.sample(&mut rng);
                *v = 0.013 * z - 5e-4
            });
            if fitter.fit(&[&buf], alpha).contaminated {
                flagged += 1;
            }
        }
        let (lo, hi) = binomial_acceptance_counts(fits, alpha, 0.99);
        println!(
            "contamination flag under H0: n={n}: {flagged}/{fits} = {:.4} (α = {alpha}, 99 % band [{lo}, {hi}])",
            flagged as f64 / fits as f64
        );
        assert!(
            lo <= flagged && flagged <= hi,
            "n={n}: {flagged} outside [{lo}, {hi}]"
        );
    }
}

/// Scope codes: Gaussian noise of unit sigma on a grid of `step`, at a
/// random phase of the grid, scaled as a reader scales codes to volts.
fn quantised_noise(rng: &mut ChaCha8Rng, buf: &mut [f64], step: f64) {
    let phase: f64 = rand::Rng::random(rng);
    for v in buf.iter_mut() {
        let z: f64 = StandardNormal.sample(rng);
        *v = ((z / step + phase).round() * step) * 0.013 - 5e-4;
    }
}

#[test]
fn noise_fit_contamination_on_quantised_noise_is_at_most_alpha() {
    // An 8-bit scope at a sensitive range puts the code step near one noise
    // sigma; there the MAD is quantised and flagged every clean gate. The
    // quantised robust sigma keeps the verdict at or below α (conservative:
    // see `NoiseFitter::fit`); the count must not exceed the upper end of
    // the 99 % binomial band at α.
    let alpha = 0.05;
    for step in [0.5, 1.28, 2.0] {
        for (n, fits) in [(1400usize, trials(1000)), (300, trials(2000)), (60, trials(2000))] {
            let mut rng = ChaCha8Rng::seed_from_u64(41 + n as u64 + (step * 100.0) as u64);
            let mut fitter = NoiseFitter::default();
            let mut buf = vec![0.0; n];
            let mut flagged = 0u64;
            let mut ratio = 0.0;
            for _ in 0..fits {
                quantised_noise(&mut rng, &mut buf, step);
                let s = fitter.fit(&[&buf], alpha);
                flagged += s.contaminated as u64;
                ratio += s.robust_sigma_v / s.sigma_v;
            }
            let (_, hi) = binomial_acceptance_counts(fits, alpha, 0.99);
            println!(
                "quantised noise, step {step} sigma, n={n}: flagged {flagged}/{fits} (at most {hi}); mean robust/plain {:.4}",
                ratio / fits as f64
            );
            assert!(flagged <= hi, "step {step}, n={n}: {flagged} > {hi}");
            // Both estimate the quantised samples' sd: on average within 1 %
            // plus a small-sample bias of order 1/n (s is low by ~1/(4n),
            // the fit on a few boundaries high by ~1.5/n).
            let tol = 0.01 + 2.0 / n as f64;
            assert!((ratio / fits as f64 - 1.0).abs() < tol, "step {step}, n={n}: robust/plain {}", ratio / fits as f64);
        }
    }
}

/// Codes of Gaussian noise `sigma_codes` wide about `centre`, on a grid of
/// `grid` codes, with a pulse of `pulse_codes` on every 25th sample when
/// asked (a contaminated gate).
fn noise_codes(rng: &mut ChaCha8Rng, n: usize, centre: f64, sigma_codes: f64, grid: i32, pulse_codes: f64) -> Vec<i16> {
    let phase: f64 = rand::Rng::random(rng);
    (0..n)
        .map(|i| {
            let z: f64 = StandardNormal.sample(rng);
            let pulse = if i % 25 == 0 { pulse_codes } else { 0.0 };
            let c = ((centre + sigma_codes * z + pulse) / f64::from(grid) + phase).round() as i32 * grid;
            c.clamp(-32768, 32767) as i16
        })
        .collect()
}

#[test]
fn noise_fit_on_codes_is_the_fit_on_their_volts() {
    // `fit_codes` (what the noise stage runs on a digitiser's codes) against
    // `fit` on the volts the channel decodes them to, on gates of every kind
    // the stage sees: the verdicts and counts identical, the numbers within
    // what the decode's rounding allows. Each decoded sample is off its
    // exact value by at most δ = ½ ulp(max |v|), which moves the mean and
    // σ by at most δ and a sigma-scaled statistic by δ/σ; beyond that
    // both paths agree to 1e-10 (`fit_codes` rounds its moments once, `fit`
    // every sample's deviation and power: see `Moments::of_codes`; 1e-13
    // relative allowed for that, where f64 sums of 2000 samples err by
    // up to ~2000 ulp ≈ 4e-13 at worst and by ~√2000 ulp ≈ 1e-14 typically). The
    // robust σ scales with the grid step, which `fit` finds by a
    // floating-point Euclid over differences of rounded volts, each off by
    // up to 2δ, and a remainder of a difference L levels wide by up to
    // 2(L + 1)δ (4(L + 1)δ/step relative allowed), and `fit_codes` takes
    // exactly as the scale times the codes' grid.
    let mut rng = ChaCha8Rng::seed_from_u64(0xc0de);
    let mut worst = [0.0f64; 5];
    // (volts per code, offset V, samples, centre and σ in codes, grid in codes, pulse in codes, parts)
    type Case = (f64, f64, usize, f64, f64, i32, f64, usize);
    let cases: [Case; 11] = [
        (1.0 / 4096.0, 0.0, 2000, 0.0, 82.0, 1, 0.0, 2),     // the reference frames' 12-bit digitiser
        (1.0 / 4096.0, 0.0, 2000, 3.0, 82.0, 1, 600.0, 2),   // a pulse leaking into the gate
        (0.013 * 1.28, -5e-4, 1400, 0.0, 0.78, 1, 0.0, 1),   // 8-bit at a sensitive range (step 1.28 σ)
        (0.013 * 0.5, -5e-4, 300, 0.0, 2.0, 1, 0.0, 3),      // step 0.5 σ
        (1.0 / 65536.0, 0.01, 1200, -200.0, 30.0, 16, 0.0, 2), // 12-bit codes shifted into 16 bits
        (3.1e-5, 1000.0, 500, 100.0, 12.0, 1, 0.0, 2),       // a large offset (the decode rounds)
        (2e-4, -0.3, 60, 0.0, 5.0, 3, 0.0, 1),               // a grid of three codes
        (1e-3, 0.0, 800, 0.0, 400.0, 1, 0.0, 2),             // a grid finer than σ/256: the MAD
        (1e-3, 0.0, 300, 0.0, 0.2, 1, 0.0, 2),               // nearly all on one level: no probit fit, the MAD
        (1e-3, 0.0, 40, 7.0, 0.0, 1, 0.0, 1),                // one code: σ = 0
        (1e-3, 0.25, 1, 7.0, 3.0, 1, 0.0, 1),                // one sample
    ];
    for (case, &(g, o, n, centre, sigma, grid, pulse, parts)) in cases.iter().enumerate() {
        for trial in 0..40 {
            let codes = noise_codes(&mut rng, n, centre, sigma, grid, pulse);
            let volts: Vec<f64> = codes.iter().map(|&c| f64::from(c) * g + o).collect();
            let cut: Vec<usize> = (0..=parts).map(|k| k * n / parts).collect();
            let code_parts: Vec<&[i16]> = cut.windows(2).map(|w| &codes[w[0]..w[1]]).collect();
            let volt_parts: Vec<&[f64]> = cut.windows(2).map(|w| &volts[w[0]..w[1]]).collect();
            for alpha in [0.001, 0.05] {
                let a = NoiseFitter::default().fit_codes(&code_parts, g, o, alpha).expect("within reach");
                let b = NoiseFitter::default().fit(&volt_parts, alpha);
                let at = format!("case {case}, trial {trial}, α {alpha}: {a:?} vs {b:?}");
                assert_eq!((a.samples, a.gaussian, a.contaminated), (b.samples, b.gaussian, b.contaminated), "{at}");
                let delta = 0.5 * f64::EPSILON * volts.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                let sd = b.sigma_v.max(f64::MIN_POSITIVE);
                let levels = f64::from(codes.iter().max().unwrap() - codes.iter().min().unwrap()) / f64::from(grid);
                let dev = [
                    // Each side also rounds its mean once more (½ ulp ≤ δ).
                    (a.mean_v - b.mean_v).abs() / (3.0 * delta + 1e-13 * sd),
                    (a.sigma_v - b.sigma_v).abs() / (delta + 1e-13 * sd),
                    (a.robust_sigma_v - b.robust_sigma_v).abs() / ((4.0 * (levels + 1.0) * delta / (g * f64::from(grid)) + 1e-13) * a.robust_sigma_v.max(f64::MIN_POSITIVE)),
                    ((a.skewness - b.skewness).abs() / b.skewness.abs().max(1.0))
                        .max((a.excess_kurtosis - b.excess_kurtosis).abs() / b.excess_kurtosis.abs().max(1.0))
                        / (16.0 * delta / sd + 1e-13),
                    // p = e^(−JB/2) with JB = n(S² + K²/4)/6: a change of
                    // the moments within their bound moves p by at most
                    // p·n(2|S| + |K|/2)/12 times that bound.
                    (a.normality_p_value - b.normality_p_value).abs()
                        / (b.normality_p_value * (b.samples as f64 * (2.0 * b.skewness.abs() + 0.5 * b.excess_kurtosis.abs()) / 12.0 * (16.0 * delta / sd + 1e-13) + 1e-14) + 1e-300),
                ];
                for (w, d) in worst.iter_mut().zip(dev) {
                    *w = w.max(d);
                }
                assert!(dev.iter().all(|&d| d <= 1.0), "{at}: deviations over their bounds {dev:?}");
            }
        }
    }
    println!("fit_codes against fit, deviation over its bound at worst (mean, σ, robust σ, moments, p): {worst:?}");
}

#[test]
fn noise_fit_on_codes_keeps_the_codes_grid_under_a_large_offset() {
    // 1 µV codes on a 1 kV offset (the decode still keeps the codes' order
    // and spacing): the volts path's grid search tolerates 1e-9 of the
    // volts, half a code here, and can settle on a grid of several codes;
    // the codes' own grid is one code, and the quantised robust σ stays
    // with the sample sd (σ = 1 code: both estimate √(σ² + q²/12)).
    let (g, o) = (1e-6, 1000.0);
    assert!(tofwave::detect::gates::codes_keep_order(g, o));
    let mut rng = ChaCha8Rng::seed_from_u64(0x0ff5e7);
    let mut ratio = 0.0;
    let fits = 200;
    for _ in 0..fits {
        let codes = noise_codes(&mut rng, 1000, 0.0, 1.0, 1, 0.0);
        let s = NoiseFitter::default().fit_codes(&[&codes], g, o, 0.001).expect("within reach");
        assert!(!s.contaminated, "{s:?}");
        ratio += s.robust_sigma_v / s.sigma_v;
    }
    // The fit on a few boundaries of a coarse grid: within 5 % on average
    // (the test above's 1 % + 2/n bound is for steps of 0.5 to 2 σ over
    // more boundaries).
    println!("codes under a 1 kV offset: mean robust/plain {:.4}", ratio / fits as f64);
    assert!((ratio / fits as f64 - 1.0).abs() < 0.05, "robust/plain {}", ratio / fits as f64);
}

#[test]
fn noise_fit_on_codes_flags_quantised_noise_as_the_fit_on_volts_does() {
    // The Monte Carlo of `noise_fit_contamination_on_quantised_noise_is_at_most_alpha`
    // through `fit_codes`: the same flag on every gate (asserted gate by
    // gate), so the same count and the same bound hold for the path the
    // stage runs.
    let alpha = 0.05;
    for step in [0.5, 1.28, 2.0] {
        let (g, o) = (0.013 * step, -5e-4);
        for n in [1400usize, 300, 60] {
            let mut rng = ChaCha8Rng::seed_from_u64(0xf1a9 + n as u64 + (step * 100.0) as u64);
            let (mut by_codes, mut by_volts) = (0u64, 0u64);
            let fits = trials(1000);
            for _ in 0..fits {
                let codes = noise_codes(&mut rng, n, 0.0, 1.0 / step, 1, 0.0);
                let volts: Vec<f64> = codes.iter().map(|&c| f64::from(c) * g + o).collect();
                let on_codes = NoiseFitter::default().fit_codes(&[&codes], g, o, alpha).expect("within reach").contaminated;
                let on_volts = NoiseFitter::default().fit(&[&volts], alpha).contaminated;
                assert_eq!(on_codes, on_volts, "step {step}, n {n}: one gate flagged by one path only");
                by_codes += on_codes as u64;
                by_volts += on_volts as u64;
            }
            let (_, hi) = binomial_acceptance_counts(fits, alpha, 0.99);
            println!("quantised noise on codes, step {step} σ, n = {n}: flagged {by_codes}/{fits} (on volts {by_volts}, at most {hi})");
            assert_eq!(by_codes, by_volts, "step {step}, n {n}");
            assert!(by_codes <= hi, "step {step}, n {n}: {by_codes} > {hi}");
        }
    }
}

#[test]
fn noise_fit_detects_a_pulse_in_quantised_noise() {
    // 4 % of a 1000-sample gate of 8-bit-like noise (step 1.28 sigma) is a
    // leaked pulse at +8 sigma: still flagged (s grows by ~1.9, the robust
    // sigma by ~4 %).
    let mut rng = ChaCha8Rng::seed_from_u64(43);
    let mut buf = vec![0.0; 1000];
    quantised_noise(&mut rng, &mut buf, 1.28);
    let clean = NoiseFitter::default().fit(&[&buf], 0.001);
    assert!(!clean.contaminated, "{clean:?}");
    for v in buf.iter_mut().step_by(25) {
        *v += 8.0 * 0.013;
    }
    let s = NoiseFitter::default().fit(&[&buf], 0.001);
    assert!(s.contaminated, "{s:?}");
}

#[test]
fn noise_fit_detects_outliers_and_skew() {
    let mut z = normals(2000, 21);
    // 2 % of the gate is a leaked pulse at +8σ: s grows by ~√(1 + 0.02·64) ≈ 1.5, the MAD barely moves
    for v in z.iter_mut().step_by(50) {
        *v += 8.0;
    }
    let s = NoiseFitter::default().fit(&[&z[..1000], &z[1000..]], 0.01);
    assert!(s.contaminated && !s.gaussian, "{s:?}");
    let clean = normals(2000, 22);
    let s = NoiseFitter::default().fit(&[&clean], 0.01);
    assert!(
        !s.contaminated && rel(s.sigma_v, 1.0) < 0.1 && rel(s.robust_sigma_v, 1.0) < 0.1,
        "{s:?}"
    );
}

#[test]
fn noise_fit_ten_million_samples() {
    let n = if cfg!(debug_assertions) {
        200_000
    } else {
        10_000_000
    };
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    let x: Vec<f64> = (0..n)
        .map(|_| {
            let z: f64 = StandardNormal.sample(&mut rng);
            1e-3 + 0.01 * z
        })
        .collect();
    let mut f = NoiseFitter::default();
    let t = std::time::Instant::now();
    let s = f.fit(&[&x], 0.01);
    println!(
        "fit of {n} samples: {:?}; σ = {:.6e}, robust σ = {:.6e}",
        t.elapsed(),
        s.sigma_v,
        s.robust_sigma_v
    );
    // sd of s is σ/√(2n): 2.2e-6 relative at 1e7; allow 5 sd
    assert!(rel(s.sigma_v, 0.01) < 5.0 / (2.0 * n as f64).sqrt());
    assert!(rel(s.robust_sigma_v, 0.01) < 5.0 * 1.17 / (n as f64).sqrt());
    assert_eq!(s.samples, n as u64);
}

#[test]
fn welch_psd_matches_naive_dft_and_parseval() {
    // naive reference: two half-overlapping 8-sample Hann segments
    let x: Vec<f64> = normals(12, 41);
    let dt = 1e-9;
    let got = welch_psd(&x, 8, dt);
    let mut want = vec![0.0; 5];
    let w: Vec<f64> = (0..8)
        .map(|i| 0.5 * (1.0 - (2.0 * std::f64::consts::PI * i as f64 / 8.0).cos()))
        .collect();
    let w2: f64 = w.iter().map(|v| v * v).sum();
    for start in [0, 4] {
        let seg = &x[start..start + 8];
        let mean = seg.iter().sum::<f64>() / 8.0;
        for (k, wk) in want.iter_mut().enumerate() {
            let (mut re, mut im) = (0.0, 0.0);
            for (i, (&v, &wi)) in seg.iter().zip(&w).enumerate() {
                let ph = -2.0 * std::f64::consts::PI * (k * i) as f64 / 8.0;
                re += (v - mean) * wi * ph.cos();
                im += (v - mean) * wi * ph.sin();
            }
            let one_sided = if k == 0 || k == 4 { 1.0 } else { 2.0 };
            *wk += one_sided * (re * re + im * im) * dt / w2 / 2.0;
        }
    }
    for (g, w) in got.iter().zip(&want) {
        assert!(
            (g - w).abs() <= 1e-12 * want.iter().cloned().fold(0.0, f64::max),
            "{got:?} vs {want:?}"
        );
    }
    // white noise of variance σ²: one-sided level 2σ²·dt; Σ PSD·Δf ≈ σ²
    let sigma = 0.02;
    let x: Vec<f64> = normals(1 << 16, 42).iter().map(|v| sigma * v).collect();
    let psd = welch_psd(&x, 256, dt);
    let df = 1.0 / (256.0 * dt);
    let total: f64 = psd.iter().sum::<f64>() * df;
    let level = psd[10..118].iter().sum::<f64>() / 108.0;
    println!(
        "Welch white: level/(2σ²dt) = {:.4}, ΣPSD·Δf/σ² = {:.4}",
        level / (2.0 * sigma * sigma * dt),
        total / (sigma * sigma)
    );
    // ~511 segments × 108 bins averaged: relative sd ≈ 1/√(511·108/ (overlap ≈ 1.9)) < 0.6 %; allow 3 %
    assert!(rel(level, 2.0 * sigma * sigma * dt) < 0.03);
    assert!(rel(total, sigma * sigma) < 0.03);
    // a tone at bin 32 dominates its bin
    let tone: Vec<f64> = (0..4096)
        .map(|i| (2.0 * std::f64::consts::PI * 32.0 * i as f64 / 256.0).sin())
        .collect();
    let p = welch_psd(&tone, 256, dt);
    let peak = p
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|(i, _)| i);
    assert_eq!(peak, Some(32));
    assert!(welch_psd(&tone, 1, dt).is_empty() && welch_psd(&tone[..10], 16, dt).is_empty());
}

#[test]
fn autocorrelation_of_moving_average_and_edges() {
    let h = gaussian_kernel();
    let rho1: f64 = h.windows(2).map(|w| w[0] * w[1]).sum();
    let w = normals(200_025, 51);
    let y: Vec<f64> = (0..200_000)
        .map(|j| w[j..j + 26].iter().zip(&h).map(|(a, b)| a * b).sum())
        .collect();
    let r = autocorrelation(&y, 3);
    assert_eq!(r.len(), 4);
    assert_eq!(r[0], 1.0);
    // sd of ρ̂(1) for a smooth process is far below 1/√n; allow 5/√n
    assert!(
        (r[1] - rho1).abs() < 5.0 / (200_000f64).sqrt(),
        "{} vs {rho1}",
        r[1]
    );
    // naive reference on a short sequence
    let x = [1.0, 3.0, 2.0, 5.0, 4.0];
    let m = 3.0;
    let c0: f64 = x.iter().map(|v| (v - m) * (v - m)).sum();
    let c1: f64 = x.windows(2).map(|p| (p[0] - m) * (p[1] - m)).sum();
    assert!((autocorrelation(&x, 10)[1] - c1 / c0).abs() < 1e-15);
    assert_eq!(autocorrelation(&x, 10).len(), 5);
    assert_eq!(autocorrelation(&[2.0; 4], 2), vec![1.0, 0.0, 0.0]);
    assert!(autocorrelation(&[], 3).is_empty());
}
