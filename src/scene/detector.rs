//! `[detector]`: detector kind, false-alarm target, threshold mode, whitening, CFAR.

use super::check::{check, FieldError, Range};
use serde::{Deserialize, Serialize};

/// Detector kinds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DetectorKind {
    /// Correlate with the unit-energy return template, threshold the output.
    MatchedFilter,
    /// Threshold the raw samples.
    Threshold,
}

impl DetectorKind {
    /// The name used in reports.
    pub fn name(self) -> &'static str {
        match self {
            DetectorKind::MatchedFilter => "matched_filter",
            DetectorKind::Threshold => "threshold",
        }
    }
}

/// What `detector.pfa` is a probability of.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PfaScope {
    /// At least one false alarm anywhere in one report's range gate.
    Report,
    /// A false alarm in one sample (cell).
    Sample,
}

/// Where the threshold's tail probability comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ThresholdMode {
    /// Gaussian noise model: mean + sigma * Q⁻¹(p), Student-t for the gate size.
    Gaussian,
    /// Empirical quantile of the detector output in the noise gates, accumulated
    /// over frames (exponential tail beyond what was observed); Gaussian until
    /// 10 000 gate cells have been seen.
    Empirical,
}

/// Constant-false-alarm-rate thresholding against a background that varies along the frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CfarKind {
    /// One threshold from the noise-gate model for the whole range gate.
    Off,
    /// Cell averaging: the local sigma is the RMS of the training cells.
    Ca,
    /// Ordered statistic: the local scale is the k-th smallest |training cell|
    /// (robust to a second return in the training window).
    Os,
}

impl CfarKind {
    /// The stage name in reports (`cfar_ca`, `cfar_os`); empty when off.
    pub fn name(self) -> &'static str {
        match self {
            CfarKind::Off => "",
            CfarKind::Ca => "cfar_ca",
            CfarKind::Os => "cfar_os",
        }
    }
}

/// Detector configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DetectorConfig {
    /// Detector kind.
    pub kind: DetectorKind,
    /// Design false-alarm probability.
    pub pfa: f64,
    /// Scope of `pfa`.
    pub pfa_scope: PfaScope,
    /// Jarque-Bera significance level.
    pub normality_alpha: f64,
    /// Gaussian or empirical threshold.
    pub threshold_mode: ThresholdMode,
    /// Prewhiten data and template with an AR model of the gate noise before
    /// the matched filter (coloured noise).
    pub whiten: bool,
    /// Order of the autoregressive noise model used for whitening.
    pub whiten_order: usize,
    /// CFAR thresholding: "off", "ca" or "os".
    pub cfar: CfarKind,
    /// CFAR guard cells on each side, beyond the samples the template covers.
    pub cfar_guard_cells: usize,
    /// CFAR training cells on each side.
    pub cfar_training_cells: usize,
    /// OS-CFAR rank k (1-based) among the 2·training cells; 0 = ⌈3/4 · 2·training⌉.
    pub cfar_os_rank: usize,
}

impl Default for DetectorConfig {
    fn default() -> Self {
        DetectorConfig {
            kind: DetectorKind::MatchedFilter,
            pfa: 1e-6,
            pfa_scope: PfaScope::Report,
            normality_alpha: 1e-3,
            threshold_mode: ThresholdMode::Gaussian,
            whiten: false,
            whiten_order: 8,
            cfar: CfarKind::Off,
            cfar_guard_cells: 2,
            cfar_training_cells: 16,
            cfar_os_rank: 0,
        }
    }
}

impl DetectorConfig {
    /// Checks `[detector]`, including the options that only go with some kinds.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("detector.pfa", self.pfa.into(), Range::positive_max(0.5), "(0, 0.5]"),
            ("detector.normality_alpha", self.normality_alpha.into(), Range::open(0.0, 1.0), "(0, 1)"),
        ])?;
        if self.whiten && self.kind != DetectorKind::MatchedFilter {
            return Err(FieldError::new(
                "detector.whiten",
                "true (with kind = \"threshold\")",
                "false unless detector.kind = \"matched_filter\" (whitening prewhitens the matched filter)",
            ));
        }
        if self.whiten {
            check(&[("detector.whiten_order", self.whiten_order.into(), Range::closed(1.0, 64.0), "[1, 64]")])?;
        }
        if self.cfar != CfarKind::Off {
            check(&[
                (
                    "detector.cfar_training_cells",
                    self.cfar_training_cells.into(),
                    Range::closed(1.0, 1024.0),
                    "[1, 1024] cells on each side",
                ),
                ("detector.cfar_guard_cells", self.cfar_guard_cells.into(), Range::closed(0.0, 4096.0), "[0, 4096]"),
            ])?;
            if self.cfar == CfarKind::Os {
                check(&[(
                    "detector.cfar_os_rank",
                    self.cfar_os_rank.into(),
                    Range::closed(0.0, (2 * self.cfar_training_cells) as f64),
                    "0 (3/4 of the training cells) or [1, 2 * cfar_training_cells]",
                )])?;
            }
            if self.threshold_mode == ThresholdMode::Empirical {
                return Err(FieldError::new(
                    "detector.threshold_mode",
                    "\"empirical\" (with cfar)",
                    "\"gaussian\" when detector.cfar is \"ca\" or \"os\" (CFAR sets its own threshold)",
                ));
            }
        }
        Ok(())
    }
}
