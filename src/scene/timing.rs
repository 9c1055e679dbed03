//! `[timing]`: how start and stop instants are measured.

use super::check::{check, FieldError, Range};
use serde::{Deserialize, Serialize};

/// Timing methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TimingMethod {
    /// Crossing of a fraction of the peak on the leading edge.
    ConstantFraction,
    /// Crossing of a fixed voltage (a comparator, as the source's TDC).
    LeadingEdge,
    /// Matched-filter peak, parabolic interpolation.
    PeakParabolic,
    /// Matched-filter peak, Gaussian (log-parabola) interpolation.
    PeakGaussian,
    /// Maximum-likelihood fit of amplitude and delay of the pulse shape.
    Ml,
}

impl TimingMethod {
    /// Every method, in the order of the variants (for the CLI's parser and
    /// for tests that run them all).
    pub const ALL: [TimingMethod; 5] = [
        TimingMethod::ConstantFraction,
        TimingMethod::LeadingEdge,
        TimingMethod::PeakParabolic,
        TimingMethod::PeakGaussian,
        TimingMethod::Ml,
    ];

    /// The name used in reports and stage lists.
    pub fn name(self) -> &'static str {
        match self {
            TimingMethod::ConstantFraction => "constant_fraction",
            TimingMethod::LeadingEdge => "leading_edge",
            TimingMethod::PeakParabolic => "peak_parabolic",
            TimingMethod::PeakGaussian => "peak_gaussian",
            TimingMethod::Ml => "ml",
        }
    }
}

/// Timing configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TimingConfig {
    /// Method for start and stop.
    pub method: TimingMethod,
    /// Constant fraction.
    pub fraction: f64,
    /// Leading-edge threshold, volts above the noise mean.
    pub leading_edge_v: f64,
}

impl Default for TimingConfig {
    fn default() -> Self {
        TimingConfig {
            method: TimingMethod::ConstantFraction,
            fraction: 0.5,
            leading_edge_v: 1.0,
        }
    }
}

impl TimingConfig {
    /// Checks `[timing]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("timing.fraction", self.fraction.into(), Range::open(0.0, 1.0), "(0, 1)"),
            ("timing.leading_edge_v", self.leading_edge_v.into(), Range::positive(), "(0, inf) V"),
        ])
    }
}
