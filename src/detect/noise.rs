//! Noise-gate moments (Welford) and the fitted noise model.

use crate::frame::NoiseSummary;

/// Single-pass central moments up to the fourth (Welford/Terriberry), f64.
#[derive(Debug, Clone, Copy, Default)]
pub struct Moments {
    n: u64,
    mean: f64,
    m2: f64,
    m3: f64,
    m4: f64,
}

impl Moments {
    /// Adds one sample.
    pub fn push(&mut self, x: f64) {
        let n1 = self.n as f64;
        self.n += 1;
        let n = self.n as f64;
        let delta = x - self.mean;
        let delta_n = delta / n;
        let delta_n2 = delta_n * delta_n;
        let term1 = delta * delta_n * n1;
        self.mean += delta_n;
        self.m4 += term1 * delta_n2 * (n * n - 3.0 * n + 3.0) + 6.0 * delta_n2 * self.m2 - 4.0 * delta_n * self.m3;
        self.m3 += term1 * delta_n * (n - 2.0) - 3.0 * delta_n * self.m2;
        self.m2 += term1;
    }
    /// Samples seen.
    pub fn count(&self) -> u64 {
        self.n
    }
    /// Mean.
    pub fn mean(&self) -> f64 {
        self.mean
    }
    /// Unbiased variance (n - 1); 0 for fewer than two samples.
    pub fn variance(&self) -> f64 {
        if self.n < 2 { 0.0 } else { self.m2 / (self.n as f64 - 1.0) }
    }
    /// Sample skewness g1; 0 when the variance is 0.
    pub fn skewness(&self) -> f64 {
        if self.m2 <= 0.0 { 0.0 } else { (self.n as f64).sqrt() * self.m3 / self.m2.powf(1.5) }
    }
    /// Sample excess kurtosis g2; 0 when the variance is 0.
    pub fn excess_kurtosis(&self) -> f64 {
        if self.m2 <= 0.0 { 0.0 } else { self.n as f64 * self.m4 / (self.m2 * self.m2) - 3.0 }
    }
}

/// Fits the noise model on gate samples; keeps its scratch buffer between frames.
#[derive(Debug, Default)]
pub struct NoiseFitter {
    scratch: Vec<f64>,
}

impl NoiseFitter {
    /// Fits on the concatenation of `parts`.
    pub fn fit(&mut self, parts: &[&[f64]], normality_alpha: f64) -> NoiseSummary {
        let mut m = Moments::default();
        self.scratch.clear();
        for p in parts {
            for &x in *p {
                m.push(x);
                self.scratch.push(x);
            }
        }
        let n = m.count();
        let (_, p) = super::stats::jarque_bera(n, m.skewness(), m.excess_kurtosis());
        let robust = mad_sigma(&mut self.scratch);
        let sigma = m.variance().sqrt();
        NoiseSummary {
            mean_v: m.mean(),
            sigma_v: sigma,
            skewness: m.skewness(),
            excess_kurtosis: m.excess_kurtosis(),
            gaussian: p >= normality_alpha,
            normality_p_value: p,
            robust_sigma_v: robust,
            samples: n,
            contaminated: robust > 0.0 && (sigma / robust - 1.0).abs() > 0.25,
        }
    }
}

/// MAD * 1.4826 (reorders `x`).
pub fn mad_sigma(x: &mut [f64]) -> f64 {
    if x.is_empty() {
        return 0.0;
    }
    let med = median(x);
    for v in x.iter_mut() {
        *v = (*v - med).abs();
    }
    1.482_602_218_505_602 * median(x)
}

fn median(x: &mut [f64]) -> f64 {
    let n = x.len();
    let (_, m, _) = x.select_nth_unstable_by(n / 2, |a, b| a.total_cmp(b));
    let hi = *m;
    if n % 2 == 1 {
        hi
    } else {
        let lo = x[..n / 2].iter().copied().fold(f64::NEG_INFINITY, f64::max);
        0.5 * (lo + hi)
    }
}
