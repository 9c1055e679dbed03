//! Sub-sample peak interpolation from three samples around a local maximum.

/// Offset in (-0.5, 0.5) of the vertex of the parabola through
/// `(-1, ym)`, `(0, y0)`, `(1, yp)`, and the vertex height. `y0` must be a
/// local maximum; a flat top gives offset 0.
pub fn parabolic(ym: f64, y0: f64, yp: f64) -> (f64, f64) {
    let denom = ym - 2.0 * y0 + yp;
    if denom >= 0.0 || !denom.is_finite() {
        return (0.0, y0);
    }
    let d = (0.5 * (ym - yp) / denom).clamp(-0.5, 0.5);
    (d, y0 - 0.25 * (ym - yp) * d)
}

/// Gaussian (log-parabola) interpolation: exact for a sampled Gaussian peak.
/// Falls back to [`parabolic`] when a sample is not positive.
pub fn gaussian(ym: f64, y0: f64, yp: f64) -> (f64, f64) {
    if ym <= 0.0 || y0 <= 0.0 || yp <= 0.0 {
        return parabolic(ym, y0, yp);
    }
    let (lm, l0, lp) = (ym.ln(), y0.ln(), yp.ln());
    let (d, lh) = parabolic(lm, l0, lp);
    (d, lh.exp())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parabola_vertex_is_exact_for_a_parabola() {
        let f = |x: f64| 3.0 - 2.0 * (x - 0.3) * (x - 0.3);
        let (d, h) = parabolic(f(-1.0), f(0.0), f(1.0));
        assert!((d - 0.3).abs() < 1e-12 && (h - 3.0).abs() < 1e-12);
    }

    #[test]
    fn gaussian_is_exact_for_a_gaussian() {
        let f = |x: f64| 2.0 * (-(x + 0.2f64).powi(2) / (2.0 * 1.7f64.powi(2))).exp();
        let (d, h) = gaussian(f(-1.0), f(0.0), f(1.0));
        assert!((d + 0.2).abs() < 1e-12 && (h - 2.0).abs() < 1e-12);
    }
}
