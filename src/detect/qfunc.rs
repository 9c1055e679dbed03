//! Q(x) = P(N(0,1) > x) and its inverse.

/// Upper tail of the standard normal distribution.
pub fn q(x: f64) -> f64 {
    0.5 * statrs::function::erf::erfc(x / std::f64::consts::SQRT_2)
}

/// ln Q(x), finite where Q underflows.
pub fn ln_q(x: f64) -> f64 {
    q(x).ln()
}

/// Q⁻¹(p) = -Φ⁻¹(p): p in (0, 1); 0 gives +inf, 1 gives -inf, NaN gives NaN.
pub fn q_inv(p: f64) -> f64 {
    if p.is_nan() {
        return f64::NAN;
    }
    if p <= 0.0 {
        return f64::INFINITY;
    }
    if p >= 1.0 {
        return f64::NEG_INFINITY;
    }
    std::f64::consts::SQRT_2 * statrs::function::erf::erfc_inv(2.0 * p)
}

/// Per-cell probability from a probability over `cells` independent cells:
/// `-expm1(log1p(-p_total) / cells)`.
pub fn per_cell_pfa(p_total: f64, cells: f64) -> f64 {
    if cells <= 1.0 {
        return p_total;
    }
    -((-p_total).ln_1p() / cells).exp_m1()
}
