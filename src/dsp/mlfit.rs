//! Maximum-likelihood fit of amplitude and delay of a known pulse shape in white
//! Gaussian noise (least squares, Gauss-Newton).

use super::pulse::PulseShape;

/// Result of a fit. Model: `x[k] = baseline + amplitude * shape(k - delay)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MlFit {
    /// Fitted amplitude (same units as x).
    pub amplitude: f64,
    /// Fitted delay, samples (position of the shape's t = 0).
    pub delay: f64,
    /// Gauss-Newton iterations used.
    pub iterations: u32,
    /// The step fell below tolerance within the iteration limit.
    pub converged: bool,
    /// Σ_k shape'(k - delay)² over the window: the delay's Fisher information is amplitude² times this over sigma².
    pub slope_energy: f64,
    /// RMS of the residual over the window.
    pub residual_rms: f64,
}

/// Fits amplitude and delay over `x[window]`, starting from `delay0` (samples).
pub fn fit_delay(
    x: &[f64],
    baseline: f64,
    shape: &dyn PulseShape,
    delay0: f64,
    window: std::ops::Range<usize>,
    max_iter: u32,
) -> MlFit {
    let mut delay = delay0;
    let mut amplitude = 0.0;
    let mut converged = false;
    let mut iterations = 0;
    for it in 0..max_iter {
        iterations = it + 1;
        // Linear least squares for amplitude at this delay, then a Gauss-Newton step in delay.
        let (mut ss, mut sx, mut dd, mut dr) = (0.0, 0.0, 0.0, 0.0);
        for k in window.clone() {
            let (s, _) = shape.value_and_slope(k as f64 - delay);
            ss += s * s;
            sx += s * (x[k] - baseline);
        }
        if ss <= 0.0 {
            break;
        }
        amplitude = sx / ss;
        for k in window.clone() {
            let (s, ds) = shape.value_and_slope(k as f64 - delay);
            let r = x[k] - baseline - amplitude * s;
            let j = -amplitude * ds;
            dd += j * j;
            dr += j * r;
        }
        if dd <= 0.0 {
            break;
        }
        let step = (dr / dd).clamp(-1.0, 1.0);
        delay += step;
        if step.abs() < 1e-9 {
            converged = true;
            break;
        }
    }
    let (mut slope_energy, mut rss) = (0.0, 0.0);
    for k in window.clone() {
        let (s, ds) = shape.value_and_slope(k as f64 - delay);
        slope_energy += ds * ds;
        let r = x[k] - baseline - amplitude * s;
        rss += r * r;
    }
    let n = window.len().max(1) as f64;
    MlFit { amplitude, delay, iterations, converged, slope_energy, residual_rms: (rss / n).sqrt() }
}
