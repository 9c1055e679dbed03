//! `tofwave::math` against statrs, used here as an independent oracle over
//! the ranges where statrs is itself accurate (its erf/erfc, incomplete
//! beta/gamma and Student-t follow Boost/Numerical Recipes). Where statrs is
//! not accurate, the test says so instead of comparing:
//!
//! * erf and erfc for |x| ≥ 0.5: statrs follows Boost's rational
//!   approximations but writes each interval's offset (a `float` literal in
//!   Boost, e.g. `0.3440242112F` = 0.34402421116829) as the f64 literal
//!   0.3440242112, 3e-11 away from the value the fit was made for, so its
//!   erfc is off by up to ~1e-10 relative there (Python's `math.erf`, the C
//!   library, and ours agree to 1 ulp; `tests/suite/numerics.rs` checks ours against
//!   tables). Only |x| < 0.5 is a tight comparison;
//! * `erfc_inv` in the far tail: statrs's Q⁻¹ through `√2 erfc_inv(2p)` drifts
//!   from ~1e-15 to ~1e-9 relative below p ≈ 1e-200 (`tests/suite/numerics.rs`
//!   measures ours against high-precision tables there instead);
//! * `0.5 erfc(x/√2)` as Q(x): the rounding of x/√2 costs ~x²·1.1e-16
//!   relative, so the comparison tolerance grows with x²;
//! * incomplete beta/gamma at shape parameters ≳ 1e5 and the extreme tails,
//!   where statrs's continued fractions lose digits (the Clopper-Pearson
//!   comparison in `tests/suite/numerics.rs` covers n = 1e6 and 1e9).
//!
//! Inputs are fixed grids and a seeded generator.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use statrs::distribution::{ContinuousCDF, StudentsT};
use tofwave::math::special::{erf, erfc, q, q_inv};
use tofwave::math::stats::{beta_inc_reg, gamma_p, gamma_q, t_quantile_from_z};

fn rel(a: f64, b: f64) -> f64 {
    if a == b { 0.0 } else { ((a - b) / b).abs() }
}

/// Runs `f` over `xs`, returning the largest relative difference and where.
fn worst(xs: impl Iterator<Item = f64>, f: impl Fn(f64) -> (f64, f64)) -> (f64, f64) {
    xs.map(|x| {
        let (ours, theirs) = f(x);
        (rel(ours, theirs), x)
    })
    .fold((0.0, f64::NAN), |a, b| if b.0 > a.0 { b } else { a })
}

fn grid(lo: f64, hi: f64, n: usize) -> impl Iterator<Item = f64> {
    (0..=n).map(move |i| lo + (hi - lo) * i as f64 / n as f64)
}

#[test]
fn erf_and_erfc_match_statrs() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let random: Vec<f64> = (0..20_000).map(|_| rng.random_range(-7.0..7.0)).collect();
    let (e, at) = worst(
        grid(-7.0, 7.0, 20_000)
            .chain(random.iter().copied())
            .filter(|x| x.abs() < 0.5),
        |x| (erf(x), statrs::function::erf::erf(x)),
    );
    println!("erf |x| < 0.5: max rel {e:.2e} at {at}");
    assert!(e <= 2.3e-16, "erf: {e:e} at {at}");
    // Tiny arguments: erf(x) = 2x/√π to rounding.
    for x in [1e-300, 1e-20, 3e-9, -1e-12] {
        assert!(rel(erf(x), statrs::function::erf::erf(x)) <= 2.3e-16, "{x}");
    }
    // Beyond 0.5 the difference is statrs's own error (see the module docs).
    let (e, at) = worst(grid(-7.0, 7.0, 20_000).chain(random.iter().copied()), |x| {
        (erf(x), statrs::function::erf::erf(x))
    });
    println!("erf: max rel {e:.2e} at {at}");
    assert!(e <= 2e-10, "erf: {e:e} at {at}");
    // erfc to 26 (erfc(26) = 5.7e-296): agreement to statrs's error.
    let (e, at) = worst(grid(-6.0, 26.0, 32_000), |x| {
        (erfc(x), statrs::function::erf::erfc(x))
    });
    println!("erfc: max rel {e:.2e} at {at}");
    assert!(e <= 2e-10, "erfc: {e:e} at {at}");
    let (e, at) = worst(grid(-0.49, 0.49, 2_000), |x| {
        (erfc(x), statrs::function::erf::erfc(x))
    });
    assert!(e <= 2.3e-16, "erfc: {e:e} at {at}");
    assert_eq!((erf(f64::INFINITY), erf(f64::NEG_INFINITY)), (1.0, -1.0));
    assert!(erf(f64::NAN).is_nan());
}

#[test]
fn q_and_q_inv_match_statrs_where_it_is_accurate() {
    // Q(x) = ½ erfc(x/√2): statrs's erfc error (~1e-10 beyond x/√2 = 0.5)
    // plus the rounding of the argument (~x²·1.1e-16 relative).
    let (e, at) = worst(grid(-8.0, 37.0, 9_000), |x| {
        let theirs = 0.5 * statrs::function::erf::erfc(x / std::f64::consts::SQRT_2);
        (q(x), theirs)
    });
    println!("q: max rel {e:.2e} at {at}");
    assert!(e <= 2e-10, "q at {at}");
    let (e, at) = worst(grid(-0.7, 0.7, 1_400), |x| {
        (
            q(x),
            0.5 * statrs::function::erf::erfc(x / std::f64::consts::SQRT_2),
        )
    });
    assert!(e <= 4.5e-16, "q at {at}");
    // Q⁻¹(p) = √2 erfc⁻¹(2p) for p in [1e-200, 1 − 1e-12].
    let ps = (1..=2000)
        .map(|i| 10f64.powf(-200.0 * i as f64 / 2000.0))
        .chain(grid(0.001, 0.999, 998));
    let (e, at) = worst(ps, |p| {
        (
            q_inv(p),
            std::f64::consts::SQRT_2 * statrs::function::erf::erfc_inv(2.0 * p),
        )
    });
    println!("q_inv: max rel {e:.2e} at p = {at:e}");
    assert!(e <= 1e-13, "q_inv at p = {at:e}");
}

#[test]
fn incomplete_beta_and_gamma_match_statrs() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let (mut worst_b, mut worst_g) = (0.0f64, 0.0f64);
    for _ in 0..3_000 {
        let a = 10f64.powf(rng.random_range(-1.0..3.0));
        let b = 10f64.powf(rng.random_range(-1.0..3.0));
        let x = rng.random_range(0.0..1.0);
        let theirs = statrs::function::beta::beta_reg(a, b, x);
        if theirs > 1e-250 {
            worst_b = worst_b.max(rel(beta_inc_reg(a, b, x), theirs));
        }
        let g = 10f64.powf(rng.random_range(-1.0..3.0));
        let y = g * rng.random_range(0.05..3.0);
        let (lp, lq) = (
            statrs::function::gamma::gamma_lr(g, y),
            statrs::function::gamma::gamma_ur(g, y),
        );
        if lp > 1e-250 {
            worst_g = worst_g.max(rel(gamma_p(g, y), lp));
        }
        if lq > 1e-250 {
            worst_g = worst_g.max(rel(gamma_q(g, y), lq));
        }
    }
    println!("beta_inc_reg: max rel {worst_b:.2e}; gamma_p/q: max rel {worst_g:.2e}");
    assert!(worst_b <= 1e-11, "beta {worst_b:e}");
    assert!(worst_g <= 1e-11, "gamma {worst_g:e}");
}

#[test]
fn t_quantile_matches_statrs_students_t() {
    // Cornish-Fisher to 1/ν⁴. The lower tail of statrs's t keeps its digits
    // (the upper loses them to 1 − p); its cdf rests on the incomplete beta
    // checked above. Within 1e-4 where documented; at ν = 30 beyond z = 5.5
    // the omitted 1/ν⁵ terms grow to 8e-4 at z = 7. At ν = 1e5 the ~5e-5
    // left is statrs's (the whole correction there is ~1e-5 of z).
    for (nu, z_max, tol) in [
        (30.0, 5.5, 1e-4),
        (30.0, 7.0, 1e-3),
        (45.0, 6.8, 1e-4),
        (100.0, 7.0, 1e-4),
        (1e3, 7.0, 1e-4),
        (1e5, 7.0, 1e-4),
    ] {
        let t = StudentsT::new(0.0, 1.0, nu).unwrap();
        let (e, at) = worst(grid(0.5, z_max, 65), |z| {
            (t_quantile_from_z(z, nu), -t.inverse_cdf(q(z)))
        });
        println!("t_quantile_from_z, nu {nu}, z <= {z_max}: max rel {e:.2e} at z = {at}");
        assert!(e <= tol, "nu {nu}: {e:e} at z = {at}");
    }
}
