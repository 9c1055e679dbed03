//! Fractional-delay filter.

/// Writes `x` delayed by `delay` samples (positive: later) into `out`, by linear interpolation;
/// samples that would come from outside `x` repeat the edge value.
pub fn shift(x: &[f64], delay: f64, out: &mut [f64]) {
    let n = x.len();
    for (i, o) in out.iter_mut().enumerate().take(n) {
        let t = (i as f64 - delay).clamp(0.0, (n - 1) as f64);
        let k = (t.floor() as usize).min(n.saturating_sub(2));
        let f = t - k as f64;
        *o = if n < 2 { x[0] } else { x[k] * (1.0 - f) + x[k + 1] * f };
    }
}
