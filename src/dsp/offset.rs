//! Baseline (offset) estimation: a robust per-frame offset from noise-gate
//! samples, and exponential smoothing of it across frames to follow a slow
//! drift without passing each frame's estimation noise on.
//!
//! Named `offset` (not `baseline`) because `pipeline::baseline` is the stage
//! built on it; the kernel estimates an offset.
//!
//! Why robust: a gate can hold a stray return, a burst or a clipped sample;
//! the median (or a trimmed mean) of the gate moves little when a few samples
//! are wild, where the plain mean would follow them.

use crate::math::select::trimmed_mean;

/// How one frame's offset is estimated from its gate samples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OffsetEstimator {
    /// Median of the samples.
    Median,
    /// Mean after dropping this fraction of the samples at each end, [0, 0.5).
    TrimmedMean(f64),
}

/// Robust offset of `values` (reordered in place); non-finite samples are
/// ignored. `None` when no finite sample is left.
pub fn robust_offset(values: &mut Vec<f64>, estimator: OffsetEstimator) -> Option<f64> {
    values.retain(|v| v.is_finite());
    match estimator {
        OffsetEstimator::Median => trimmed_mean(values, 0.5),
        OffsetEstimator::TrimmedMean(t) => trimmed_mean(values, t),
    }
}

/// Exponentially smoothed offset across frames: `b_k = b_{k-1} + α (m_k − b_{k-1})`.
/// With α = 1 each frame keeps its own offset; with α ≪ 1 the estimate's
/// noise variance falls to α/(2 − α) of one frame's while a drift slower than
/// ~1/α frames is still followed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DriftTracker {
    /// Weight of the newest frame, (0, 1].
    smoothing: f64,
    /// The smoothed offset so far (none before the first frame).
    state: Option<f64>,
}

impl DriftTracker {
    /// A tracker with weight `smoothing` for the newest frame (clamped to (0, 1]).
    pub fn new(smoothing: f64) -> DriftTracker {
        let smoothing = if smoothing.is_finite() {
            smoothing.clamp(f64::MIN_POSITIVE, 1.0)
        } else {
            1.0
        };
        DriftTracker {
            smoothing,
            state: None,
        }
    }

    /// Feeds one frame's offset and returns the smoothed offset. A non-finite
    /// offset leaves the state unchanged (and returns it, or 0 before any frame).
    pub fn update(&mut self, offset_v: f64) -> f64 {
        if !offset_v.is_finite() {
            return self.state.unwrap_or(0.0);
        }
        let b = match self.state {
            None => offset_v,
            Some(prev) => prev + self.smoothing * (offset_v - prev),
        };
        self.state = Some(b);
        b
    }

    /// The current smoothed offset, if any frame has been seen.
    pub fn offset_v(&self) -> Option<f64> {
        self.state
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_ignores_outliers_and_non_finite() {
        let mut v = vec![1.0, 2.0, 3.0, 1000.0, f64::NAN, 2.5, -0.5];
        assert_eq!(robust_offset(&mut v, OffsetEstimator::Median), Some(2.25));
        let mut v = vec![f64::NAN];
        assert_eq!(robust_offset(&mut v, OffsetEstimator::Median), None);
        let mut v: Vec<f64> = (0..10).map(|i| i as f64).chain([1e6]).collect();
        // 11 values, trim 0.1: drops one at each end (0 and 1e6).
        assert_eq!(
            robust_offset(&mut v, OffsetEstimator::TrimmedMean(0.1)),
            Some(5.0)
        );
    }

    #[test]
    fn tracker_follows_a_ramp_with_lag_and_averages_noise() {
        let mut t = DriftTracker::new(1.0);
        assert_eq!(t.update(3.0), 3.0);
        assert_eq!(t.update(-1.0), -1.0);
        // α = 0.1 on a ramp of slope s per frame lags by s(1 − α)/α in steady state.
        let mut t = DriftTracker::new(0.1);
        let mut b = 0.0;
        for k in 0..500 {
            b = t.update(0.01 * k as f64);
        }
        let lag = 0.01 * 499.0 - b;
        assert!((lag - 0.01 * 0.9 / 0.1).abs() < 1e-9, "{lag}");
        assert_eq!(t.update(f64::NAN), b);
    }
}
