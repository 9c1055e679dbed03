//! Confidence intervals and normality tests.

/// Two-sided Clopper-Pearson interval for `successes` out of `trials` at `confidence`.
pub fn clopper_pearson(successes: u64, trials: u64, confidence: f64) -> (f64, f64) {
    use statrs::distribution::{Beta, ContinuousCDF};
    if trials == 0 {
        return (0.0, 1.0);
    }
    let a = (1.0 - confidence) / 2.0;
    let (k, n) = (successes as f64, trials as f64);
    let lo = if successes == 0 { 0.0 } else { Beta::new(k, n - k + 1.0).unwrap().inverse_cdf(a) };
    let hi = if successes == trials { 1.0 } else { Beta::new(k + 1.0, n - k).unwrap().inverse_cdf(1.0 - a) };
    (lo, hi)
}

/// Jarque-Bera statistic and its asymptotic p-value (chi-squared, 2 dof: exp(-JB/2)).
pub fn jarque_bera(n: u64, skewness: f64, excess_kurtosis: f64) -> (f64, f64) {
    let jb = n as f64 / 6.0 * (skewness * skewness + excess_kurtosis * excess_kurtosis / 4.0);
    (jb, (-jb / 2.0).exp())
}
