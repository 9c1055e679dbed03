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
//! For long gates both reduce to μ + σ Q⁻¹(p) and Q(Q⁻¹(p) − d). The t
//! quantile itself is [`crate::math::stats::t_quantile_from_z`].

use crate::math::special::q;

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
    fn long_gates_reduce_to_the_gaussian_forms() {
        assert!((mean_error_inflation(6.0, 1_000_000_000) - 1.0).abs() < 1e-7);
        assert!((detection_probability(5.0, 6.0, 1.0, f64::INFINITY) - q(-1.0)).abs() < 1e-15);
    }
}
