//! Thresholds and detection probabilities when the noise mean and sigma are
//! estimated from a finite gate of n samples rather than known.
//!
//! For white Gaussian noise the detector output at one cell is
//! y = Σ s_j (x_j − μ̂) with unit-energy taps s; the gate's mean error enters
//! every cell with the filter's DC gain Σ s_j, so y has variance
//! σ²(1 + (Σ s_j)²/n). The gate's σ̂ is independent of both (Gaussian samples),
//! so y / (σ̂ √(1 + (Σ s)²/n)) is Student-t with n − 1 degrees of freedom.
//! Thresholds therefore use the t quantile of the per-cell probability on the
//! inflated σ, and the probability of detection is the noncentral-t tail.
//! For long gates both reduce to μ + σ Q⁻¹(p) and Q(Q⁻¹(p) − d).

use super::qfunc::q;

/// Upper quantile of Student's t with `nu` degrees of freedom whose tail
/// probability equals that of the standard normal at `z` (Cornish-Fisher
/// expansion, Abramowitz & Stegun 26.7.5, to 1/ν⁴). Infinite ν gives `z`.
/// Accurate to better than 1e-4 relative for ν ≥ 30 and z ≤ 10; small gates
/// are flagged by the pipeline.
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

/// The factor by which the gate's mean error inflates the output sigma: √(1 + dc_gain²/n).
pub fn mean_error_inflation(dc_gain: f64, gate_samples: u64) -> f64 {
    if gate_samples == 0 {
        return 1.0;
    }
    (1.0 + dc_gain * dc_gain / gate_samples as f64).sqrt()
}

/// Probability that the output exceeds `u_t` output sigmas (σ̂ κ units) when
/// the return's output SNR is `d` (in units of the true σ), for a gate with
/// `nu` degrees of freedom and mean-error inflation `kappa`: the normal
/// approximation to the noncentral t tail, Q((u_t − d/κ) / √(1 + u_t²/(2ν))).
pub fn detection_probability(u_t: f64, d: f64, kappa: f64, nu: f64) -> f64 {
    let spread = if nu.is_finite() && nu > 0.0 { (1.0 + u_t * u_t / (2.0 * nu)).sqrt() } else { 1.0 };
    q((u_t - d / kappa) / spread)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn t_quantiles_match_tables() {
        // Two-sided 99 % (upper 0.005, z = 2.5758293035489) points of Student t.
        for (nu, t) in [(30.0, 2.749995653), (60.0, 2.660283029), (120.0, 2.617421145)] {
            let got = t_quantile_from_z(2.575829303548901, nu);
            assert!((got / t - 1.0).abs() < 2e-4, "nu {nu}: {got} vs {t}");
        }
        assert_eq!(t_quantile_from_z(3.0, f64::INFINITY), 3.0);
    }

    #[test]
    fn long_gates_reduce_to_the_gaussian_forms() {
        assert!((t_quantile_from_z(5.0, 1e9) - 5.0).abs() < 1e-7);
        assert!((mean_error_inflation(6.0, 1_000_000_000) - 1.0).abs() < 1e-7);
        assert!((detection_probability(5.0, 6.0, 1.0, f64::INFINITY) - q(-1.0)).abs() < 1e-15);
    }
}
