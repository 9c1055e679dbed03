//! Prewhitening for coloured noise: an autoregressive (AR) model of the
//! noise-gate samples, fitted by Levinson-Durbin on their autocovariance
//! accumulated over frames, turned into a short whitening FIR.
//!
//! # Why and how
//!
//! In coloured noise with covariance R the optimal linear detector for a known
//! shape s is the matched filter on whitened data: with W such that
//! W R Wᵀ = I, correlate W x with W s. Its deflection is
//! d² = A² sᵀR⁻¹s ≥ A² (sᵀs)²/(sᵀRs), the deflection of the plain matched
//! filter (Cauchy-Schwarz), with equality only for white noise.
//!
//! An AR(p) model x_n + a₁x_{n−1} + … + a_p x_{n−p} = e_n (e white, variance
//! E_p) gives W directly: the prediction-error filter h = (1, a₁, …, a_p)/√E_p
//! maps the noise to unit-variance white noise. Levinson-Durbin solves the
//! Yule-Walker equations in O(p²) and passes through every lower order m < p
//! with its own predictor and error E_m; the first p samples of a frame are
//! whitened with those (the exact innovations, i.e. the Cholesky factor of
//! the Toeplitz covariance), so every whitened sample has unit variance,
//! not only those with p samples of history. The autocovariance is estimated
//! per lag from all pairs inside the gate segments seen, about the mean of all
//! of them ([`AutocovarianceAccumulator`](crate::math::autocov::AutocovarianceAccumulator)).
//! That estimate is not guaranteed positive definite; where the recursion
//! meets a reflection coefficient with |k| ≥ 1 it stops at the last valid
//! order, so the filter is always minimum phase (stable).
//!
//! The whitened template is g = h ∗ s (full convolution, L + p taps, same
//! peak tap): the whitened signal of a pulse A s placed at P is A g. The
//! matched filter on the whitened data uses g normalised to unit energy, so
//! its noise output has σ = 1 (known, not re-estimated) and a return of
//! amplitude A gives the deflection d = A ‖g‖.

/// An AR noise model from Levinson-Durbin, with every intermediate order.
#[derive(Debug, Clone, PartialEq)]
pub struct ArModel {
    /// Prediction-error filters of orders 0..=p: `predictors[m]` = (1, a₁, …, a_m).
    predictors: Vec<Vec<f64>>,
    /// Prediction-error variances E_0 (= c₀), …, E_p.
    errors: Vec<f64>,
}

impl ArModel {
    /// Fits AR(`order`) to the autocovariance `c` (c[0] = variance, c[k] at lag k).
    ///
    /// Returns `None` when c[0] is not positive and finite. If the recursion
    /// reaches a reflection coefficient with |k| ≥ 1 (a singular covariance:
    /// a pure sinusoid or a constant gate), or runs out of lags, the model
    /// stops at the last order that was still strictly positive definite.
    pub fn levinson_durbin(c: &[f64], order: usize) -> Option<ArModel> {
        let c0 = *c.first()?;
        if !(c0 > 0.0 && c0.is_finite()) {
            return None;
        }
        let order = order.min(c.len() - 1);
        let mut predictors = vec![vec![1.0]];
        let mut errors = vec![c0];
        for m in 1..=order {
            let prev = &predictors[m - 1];
            let e = errors[m - 1];
            // k_m = −(c_m + Σ_{j=1}^{m−1} a_j c_{m−j}) / E_{m−1}
            let acc: f64 = c[m] + (1..m).map(|j| prev[j] * c[m - j]).sum::<f64>();
            let k = -acc / e;
            // NaN fails both tests: a non-finite k stops the recursion too.
            if k.is_nan() || k.abs() >= 1.0 {
                break;
            }
            let mut next = prev.clone();
            next.push(0.0);
            for j in 1..m {
                next[j] = prev[j] + k * prev[m - j];
            }
            next[m] = k;
            let e_next = e * (1.0 - k * k);
            if e_next.is_nan() || e_next <= 0.0 {
                break;
            }
            predictors.push(next);
            errors.push(e_next);
        }
        Some(ArModel { predictors, errors })
    }

    /// Order reached.
    pub fn order(&self) -> usize {
        self.predictors.len() - 1
    }

    /// Prediction-error filter (1, a₁, …, a_p) of the final order.
    pub fn coefficients(&self) -> &[f64] {
        self.predictors.last().expect("order 0 always present")
    }

    /// Innovation variance E_p, V².
    pub fn innovation_variance(&self) -> f64 {
        *self.errors.last().expect("order 0 always present")
    }

    /// Prediction error variance of order `m` (clamped to the final order).
    pub fn error_variance(&self, m: usize) -> f64 {
        self.errors[m.min(self.order())]
    }

    /// One-sided power spectral density of the model, V²/Hz, at frequency
    /// `f_hz` for sampling period `dt_s`: 2 E_p dt / |A(e^{iω})|² (for a
    /// comparison with [`super::noise_model::welch_psd`]).
    pub fn psd(&self, f_hz: f64, dt_s: f64) -> f64 {
        let w = 2.0 * std::f64::consts::PI * f_hz * dt_s;
        let (mut re, mut im) = (0.0, 0.0);
        for (k, a) in self.coefficients().iter().enumerate() {
            re += a * (w * k as f64).cos();
            im -= a * (w * k as f64).sin();
        }
        2.0 * self.innovation_variance() * dt_s / (re * re + im * im)
    }
}

/// A whitening filter from an AR model: y_n = Σ_k h_k x_{n−k} with the
/// lower-order predictors over the first p samples (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Whitener {
    /// Normalised prediction-error filters of orders 0..=p: a^(m) / √E_m.
    filters: Vec<Vec<f64>>,
}

impl Whitener {
    /// From a fitted model.
    pub fn new(model: &ArModel) -> Whitener {
        let filters = model
            .predictors
            .iter()
            .zip(&model.errors)
            .map(|(a, e)| a.iter().map(|v| v / e.sqrt()).collect())
            .collect();
        Whitener { filters }
    }

    /// The steady-state whitening filter h = (1, a₁, …, a_p)/√E_p, 1/V.
    pub fn taps(&self) -> &[f64] {
        self.filters.last().expect("order 0 always present")
    }

    /// Model order p.
    pub fn order(&self) -> usize {
        self.filters.len() - 1
    }

    /// Whitens `x − mean` into `out` (same length; `out` is cleared).
    pub fn apply(&self, x: &[f64], mean: f64, out: &mut Vec<f64>) {
        out.clear();
        let p = self.order();
        for n in 0..x.len() {
            let h = &self.filters[n.min(p)];
            let mut acc = 0.0;
            for (k, hk) in h.iter().enumerate() {
                acc += hk * (x[n - k] - mean);
            }
            out.push(acc);
        }
    }

    /// The whitened template g = h ∗ `taps` (L + p values; the peak tap index
    /// is unchanged), in 1/V per unit of the template.
    pub fn whiten_template(&self, taps: &[f64]) -> Vec<f64> {
        let h = self.taps();
        let mut g = vec![0.0; taps.len() + h.len() - 1];
        for (i, t) in taps.iter().enumerate() {
            for (k, hk) in h.iter().enumerate() {
                g[i + k] += hk * t;
            }
        }
        g
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn levinson_recovers_ar1() {
        // AR(1) x_n = 0.8 x_{n−1} + e, Var e = 1: c_k = 0.8^k / (1 − 0.64).
        let c: Vec<f64> = (0..6).map(|k| 0.8f64.powi(k) / 0.36).collect();
        let m = ArModel::levinson_durbin(&c, 5).unwrap();
        assert_eq!(m.order(), 5);
        let a = m.coefficients();
        assert!((a[1] + 0.8).abs() < 1e-12, "{a:?}");
        assert!(a[2..].iter().all(|v| v.abs() < 1e-12), "{a:?}");
        assert!((m.innovation_variance() - 1.0).abs() < 1e-12);
        assert!((m.error_variance(0) - 1.0 / 0.36).abs() < 1e-12);
    }

    #[test]
    fn whitened_ar1_covariance_is_identity() {
        // Cholesky check: W R Wᵀ = I for the exact AR(1) covariance, including
        // the first sample (order-0 filter).
        let c: Vec<f64> = (0..8).map(|k| 0.8f64.powi(k) / 0.36).collect();
        let w = Whitener::new(&ArModel::levinson_durbin(&c, 1).unwrap());
        let n = 6;
        let mut rows = Vec::new();
        for i in 0..n {
            let mut e = vec![0.0; n];
            e[i] = 1.0;
            let mut out = Vec::new();
            w.apply(&e, 0.0, &mut out);
            rows.push(out); // column i of W
        }
        for a in 0..n {
            for b in 0..n {
                let mut s = 0.0;
                for i in 0..n {
                    for j in 0..n {
                        s += rows[i][a] * c[i.abs_diff(j)] * rows[j][b];
                    }
                }
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((s - want).abs() < 1e-12, "({a},{b}) = {s}");
            }
        }
    }

    #[test]
    fn singular_covariance_stops_early() {
        // A constant gate beyond its variance: c_k = c_0 for all k (|k1| = 1).
        let m = ArModel::levinson_durbin(&[1.0, 1.0, 1.0], 2).unwrap();
        assert_eq!(m.order(), 0);
        assert!(ArModel::levinson_durbin(&[0.0, 0.0], 1).is_none());
    }

    #[test]
    fn whitened_template_is_the_convolution() {
        let w = Whitener {
            filters: vec![vec![1.0], vec![2.0, -1.0]],
        };
        assert_eq!(
            w.whiten_template(&[1.0, 2.0, 3.0]),
            vec![2.0, 3.0, 4.0, -3.0]
        );
    }
}
