//! `[range_gate]` and `[noise_gate]`: where returns are sought and where the noise model is fitted.

use super::check::{check, FieldError, Range};
use serde::{Deserialize, Serialize};

/// Range gate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RangeGateConfig {
    /// Nearest range sought, metres.
    pub min_m: f64,
    /// Farthest range sought, metres.
    pub max_m: f64,
}

impl Default for RangeGateConfig {
    fn default() -> Self {
        RangeGateConfig {
            min_m: 0.0,
            max_m: 150.0,
        }
    }
}

/// Noise gate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NoiseGateConfig {
    /// Use samples before the time reference.
    pub pre_trigger: bool,
    /// Guard before the reference, seconds.
    pub guard_s: f64,
    /// Use samples past the range gate.
    pub beyond_range: bool,
    /// Minimum gate size before flagging.
    pub min_samples: usize,
    /// Time constant, frames, of the exponentially forgetting noise model
    /// (mean and sigma blended over frames with weight e^(−1/N) per frame, so
    /// slow drift is followed without one frame throwing the model).
    /// 0 (the default): each frame's model is fitted on that frame's gates alone.
    pub forgetting_frames: u32,
}

impl Default for NoiseGateConfig {
    fn default() -> Self {
        NoiseGateConfig {
            pre_trigger: true,
            guard_s: 20e-9,
            beyond_range: true,
            min_samples: 32,
            forgetting_frames: 0,
        }
    }
}

impl RangeGateConfig {
    /// Checks `[range_gate]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        let (min, max) = (self.min_m, self.max_m);
        if !(min.is_finite() && max.is_finite() && min >= -1000.0 && max > min && max <= 1e6) {
            return Err(FieldError::new(
                "range_gate.max_m",
                format!("{max} (min_m {min})"),
                "min_m >= -1000, min_m < max_m <= 1e6 m",
            ));
        }
        Ok(())
    }
}

impl NoiseGateConfig {
    /// Checks `[noise_gate]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[("noise_gate.guard_s", self.guard_s.into(), Range::closed(0.0, 1.0), "[0, 1] s")])?;
        if !self.pre_trigger && !self.beyond_range {
            return Err(FieldError::new(
                "noise_gate.pre_trigger",
                "false (and beyond_range false)",
                "at least one of pre_trigger, beyond_range true",
            ));
        }
        check(&[
            ("noise_gate.min_samples", self.min_samples.into(), Range::at_least(2.0), "[2, inf)"),
            (
                "noise_gate.forgetting_frames",
                self.forgetting_frames.into(),
                Range::closed(0.0, 1e6),
                "0 (off) or [1, 1000000] frames",
            ),
        ])
    }
}
