//! Noise colour: the autocorrelation of the noise gates, pooled over frames,
//! and what it does to the detector output.
//!
//! A receiver's noise is rarely white: the TIA and the digitiser band-limit it,
//! so neighbouring samples are correlated over several nanoseconds. The
//! matched filter then sums correlated noise and its output sigma is not the
//! sample sigma: for unit-energy taps h and noise autocorrelation ρ(k),
//!
//! ```text
//! Var(y) / σ² = g = Σ_k ρ(k) A_h(k),   A_h(k) = Σ_i h_i h_{i+k}
//! ```
//!
//! (1 for white noise, several for noise band-limited like the pulse). The
//! output's own correlation, which sets how many cells of a range gate are
//! effectively independent, widens in the same way. A threshold set on the
//! white-noise assumption is then too low by √g and the false-alarm rate is
//! orders of magnitude above design. The autocorrelation is pooled over frames
//! (the colour is a property of the receiver, slow to change) so that a single
//! short gate does not make the threshold jitter.

/// Pooled autocovariance of noise-gate samples, lags 0..=max_lag.
#[derive(Debug, Clone)]
pub struct NoiseColour {
    /// Σ (x_i − m)(x_{i+k} − m) per lag, over every segment seen.
    sums: Vec<f64>,
    /// Number of products per lag.
    counts: Vec<f64>,
    /// Samples pooled (lag 0 count).
    frames: u64,
}

/// Pooled samples beyond which old sums are halved, so that the estimate
/// follows a receiver whose colour drifts (about 2 000 frames of 2 000 gate
/// samples).
const POOL_CAP: f64 = 4.0e6;
/// Pooled samples beyond which only every 8th frame is added (the estimate
/// has converged; saves the per-frame cost).
const POOL_CONVERGED: f64 = 1.0e6;

impl NoiseColour {
    /// Estimator for lags up to `max_lag` samples.
    pub fn new(max_lag: usize) -> NoiseColour {
        NoiseColour {
            sums: vec![0.0; max_lag + 1],
            counts: vec![0.0; max_lag + 1],
            frames: 0,
        }
    }

    /// Largest lag estimated.
    pub fn max_lag(&self) -> usize {
        self.sums.len() - 1
    }

    /// Adds one frame's noise segments (each contiguous; no products are taken
    /// across segments), centred on `mean`.
    pub fn add_frame<'a>(&mut self, segments: impl IntoIterator<Item = &'a [f64]>, mean: f64) {
        self.frames += 1;
        if self.counts[0] > POOL_CONVERGED && self.frames % 8 != 0 {
            return;
        }
        if self.counts[0] > POOL_CAP {
            self.sums.iter_mut().for_each(|s| *s *= 0.5);
            self.counts.iter_mut().for_each(|c| *c *= 0.5);
        }
        let lags = self.sums.len();
        let mut centred = Vec::new();
        for seg in segments {
            centred.clear();
            centred.extend(seg.iter().map(|v| v - mean));
            let n = centred.len();
            for k in 0..lags.min(n) {
                // Per-frame partial sum first: the pooled sum then adds values
                // of similar size, frame after frame.
                let s: f64 = centred[..n - k].iter().zip(&centred[k..]).map(|(a, b)| a * b).sum();
                self.sums[k] += s;
                self.counts[k] += (n - k) as f64;
            }
        }
    }

    /// Normalised autocorrelation ρ(0..=max_lag) (ρ(0) = 1), or `None` before
    /// any noise sample has been seen or when the pooled variance is zero.
    pub fn rho(&self) -> Option<Vec<f64>> {
        if self.counts[0] < 2.0 || !(self.sums[0] > 0.0) {
            return None;
        }
        let c0 = self.sums[0] / self.counts[0];
        Some(
            self.sums
                .iter()
                .zip(&self.counts)
                .map(|(s, c)| if *c > 0.0 { (s / c / c0).clamp(-1.0, 1.0) } else { 0.0 })
                .collect(),
        )
    }

    /// Integrated correlation time in samples, τ = 1 + 2 Σ_{k≥1} ρ(k): the
    /// variance of a mean of n samples is σ² τ / n. At least 1/n-small; 1 for
    /// white noise or before any data.
    pub fn correlation_time(&self) -> f64 {
        match self.rho() {
            Some(r) => (1.0 + 2.0 * r[1..].iter().sum::<f64>()).max(0.05),
            None => 1.0,
        }
    }

    /// The detector output's variance gain and lag-1 correlation for the
    /// unit-energy `taps` (see [`output_gain`]); white-noise values before
    /// any data.
    pub fn output(&self, taps: &[f64]) -> OutputColour {
        match self.rho() {
            Some(r) => output_gain(taps, &r),
            None => output_gain(taps, &[1.0]),
        }
    }
}

/// How noise colour shapes the detector output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutputColour {
    /// Var(output) / σ² for unit-energy taps (1 for white noise).
    pub variance_gain: f64,
    /// Lag-1 correlation of the output.
    pub rho1: f64,
}

/// Output autocorrelation of the FIR `taps` driven by noise of normalised
/// autocorrelation `rho` (lags 0.., zero beyond): r(m) = Σ_k ρ(k) A_h(m − k).
/// Returns r(0) and r(1)/r(0). A non-positive r(0) (an autocorrelation
/// estimate that is not positive definite) falls back to white noise.
pub fn output_gain(taps: &[f64], rho: &[f64]) -> OutputColour {
    let len = taps.len() as isize;
    let a = |j: isize| -> f64 {
        let j = j.unsigned_abs();
        if j >= taps.len() {
            return 0.0;
        }
        taps[..taps.len() - j].iter().zip(&taps[j..]).map(|(x, y)| x * y).sum()
    };
    let kmax = (rho.len() as isize - 1).min(len);
    let r = |m: isize| -> f64 {
        (-kmax..=kmax)
            .map(|k| rho[k.unsigned_abs()] * a(m - k))
            .sum::<f64>()
    };
    let white = || {
        let e: f64 = taps.iter().map(|t| t * t).sum();
        OutputColour {
            variance_gain: e,
            rho1: if e > 0.0 { a(1) / e } else { 0.0 },
        }
    };
    let r0 = r(0);
    if !(r0 > 0.0) || !r0.is_finite() {
        return white();
    }
    OutputColour {
        variance_gain: r0,
        rho1: (r(1) / r0).clamp(-1.0, 1.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    fn unit(taps: &[f64]) -> Vec<f64> {
        let e = taps.iter().map(|t| t * t).sum::<f64>().sqrt();
        taps.iter().map(|t| t / e).collect()
    }

    #[test]
    fn white_noise_leaves_the_output_sigma_alone() {
        let h = unit(&[0.2, 0.6, 1.0, 0.7, 0.3]);
        let c = output_gain(&h, &[1.0]);
        assert!((c.variance_gain - 1.0).abs() < 1e-15);
        let a1: f64 = h.windows(2).map(|w| w[0] * w[1]).sum();
        assert!((c.rho1 - a1).abs() < 1e-15);
    }

    #[test]
    fn ar1_noise_gain_matches_the_closed_form() {
        // AR(1), ρ(k) = φ^k: a 2-tap box [1,1]/√2 has Var = (1 + ρ(1)), exactly.
        let phi: f64 = 0.8;
        let rho: Vec<f64> = (0..10).map(|k| phi.powi(k)).collect();
        let h = unit(&[1.0, 1.0]);
        let c = output_gain(&h, &rho);
        assert!((c.variance_gain - (1.0 + phi)).abs() < 1e-14, "{c:?}");
        // Lag-1 output covariance: (ρ(0)+2ρ(1)+ρ(2))/2 over (1+ρ(1)).
        let want = (1.0 + 2.0 * phi + phi * phi) / 2.0 / (1.0 + phi);
        assert!((c.rho1 - want).abs() < 1e-14);
    }

    #[test]
    fn pooled_estimate_recovers_an_ar1_process() {
        // 200 frames x 1000 samples of AR(1) with φ = 0.7: ρ̂(k) has standard
        // error about √((1+φ²)/(1−φ²)/n) ≈ 0.005 at n = 2e5; 0.03 is > 5 of them.
        let phi = 0.7;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut est = NoiseColour::new(8);
        let mut x = 0.0;
        for _ in 0..200 {
            let seg: Vec<f64> = (0..1000)
                .map(|_| {
                    let e: f64 = StandardNormal.sample(&mut rng);
                    x = phi * x + e;
                    x
                })
                .collect();
            est.add_frame([seg.as_slice()], 0.0);
        }
        let r = est.rho().expect("data");
        for (k, rk) in r.iter().enumerate() {
            assert!((rk - phi.powi(k as i32)).abs() < 0.03, "lag {k}: {rk}");
        }
        let tau_true = (1.0 + phi) / (1.0 - phi);
        // Truncated at lag 8 the true τ is 1 + 2 Σ_{1..8} φ^k.
        let tau_trunc = 1.0 + 2.0 * (1..=8).map(|k| phi.powi(k)).sum::<f64>();
        assert!((est.correlation_time() - tau_trunc).abs() < 0.3, "{} vs {tau_trunc} ({tau_true})", est.correlation_time());
    }

    #[test]
    fn no_data_and_zero_variance_are_white() {
        let est = NoiseColour::new(4);
        assert!(est.rho().is_none());
        assert_eq!(est.correlation_time(), 1.0);
        let mut z = NoiseColour::new(4);
        z.add_frame([[0.5; 100].as_slice()], 0.5);
        assert!(z.rho().is_none());
        let h = unit(&[1.0, 2.0, 1.0]);
        assert!((z.output(&h).variance_gain - 1.0).abs() < 1e-15);
    }
}
