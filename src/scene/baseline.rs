//! `[baseline]`: per-frame offset removal.

use super::check::{check, FieldError, Range};
use serde::{Deserialize, Serialize};

/// Robust estimator of a frame's offset.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BaselineEstimator {
    /// Median of the noise-gate samples.
    Median,
    /// Trimmed mean of the noise-gate samples (`trim_fraction` at each end).
    TrimmedMean,
}

/// `[baseline]`: per-frame offset from the noise gate, tracked across frames.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BaselineConfig {
    /// Robust estimator of the offset.
    pub estimator: BaselineEstimator,
    /// Trimmed mean: fraction dropped at each end.
    pub trim_fraction: f64,
    /// Weight of the newest frame in the exponentially smoothed offset, (0, 1]:
    /// 1 removes each frame's own offset, smaller values track a slow drift
    /// with less noise (time constant ~1/smoothing frames).
    pub smoothing: f64,
}

impl Default for BaselineConfig {
    fn default() -> Self {
        BaselineConfig {
            estimator: BaselineEstimator::Median,
            trim_fraction: 0.1,
            smoothing: 1.0,
        }
    }
}

impl BaselineConfig {
    /// Checks `[baseline]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("baseline.trim_fraction", self.trim_fraction.into(), Range::closed_open(0.0, 0.5), "[0, 0.5)"),
            ("baseline.smoothing", self.smoothing.into(), Range::positive_max(1.0), "(0, 1]"),
        ])
    }
}
