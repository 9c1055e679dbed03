//! `[averaging]`: ensemble averaging of frames.

use super::check::{check, FieldError, Range};
use serde::{Deserialize, Serialize};

/// How frames are grouped for averaging.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AveragingMode {
    /// N consecutive frames per report (one report per N frames).
    Block,
    /// The last N frames, one report every `hop` frames.
    Sliding,
}

/// The per-sample statistic of an averaged group.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AveragingMethod {
    /// Arithmetic mean (exact integer accumulation for integer codes).
    Mean,
    /// Mean after dropping `trim_fraction` of the smallest and largest values
    /// per sample: rejects sporadic bursts at a small cost in noise.
    TrimmedMean,
    /// Per-sample median.
    Median,
}

/// How frames are aligned before they are averaged.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AveragingAlign {
    /// Shift every frame (sub-sample, fractional-delay filter) so its start
    /// pulse lands where the group's first frame had it; frames without a
    /// start pulse are averaged as they are.
    Start,
    /// Average the samples as they are.
    None,
}

/// Averaging configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AveragingConfig {
    /// Frames per report.
    pub frames: u32,
    /// Block (N consecutive frames) or sliding window.
    pub mode: AveragingMode,
    /// Sliding window: frames between reports.
    pub hop: u32,
    /// Mean, trimmed mean or median.
    pub method: AveragingMethod,
    /// Trimmed mean: fraction dropped at each end per sample.
    pub trim_fraction: f64,
    /// Start-pulse alignment.
    pub align: AveragingAlign,
    /// Stationarity guard: frames per test block (0: no guard).
    pub stationarity_block: u32,
    /// Stationarity guard: a return moving more than this between blocks splits the group, s.
    pub stationarity_max_shift_s: f64,
    /// Stationarity guard: a relative amplitude change larger than this splits the group.
    pub stationarity_max_amplitude_change: f64,
}

impl Default for AveragingConfig {
    fn default() -> Self {
        AveragingConfig {
            frames: 1,
            mode: AveragingMode::Block,
            hop: 1,
            method: AveragingMethod::Mean,
            trim_fraction: 0.1,
            align: AveragingAlign::Start,
            stationarity_block: 0,
            stationarity_max_shift_s: 2e-9,
            stationarity_max_amplitude_change: 0.3,
        }
    }
}

impl AveragingConfig {
    /// Checks `[averaging]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[("averaging.frames", self.frames.into(), Range::closed(1.0, 1e7), "[1, 10000000]")])?;
        let stored = self.mode == AveragingMode::Sliding || self.method != AveragingMethod::Mean;
        if stored {
            check(&[(
                "averaging.frames",
                self.frames.into(),
                Range::closed(1.0, 65_536.0),
                "[1, 65536] with mode = \"sliding\" or a robust method (they keep every frame of the window)",
            )])?;
        }
        let frames = f64::from(self.frames);
        check(&[
            ("averaging.hop", self.hop.into(), Range::closed(1.0, frames), "[1, averaging.frames]"),
            ("averaging.trim_fraction", self.trim_fraction.into(), Range::closed_open(0.0, 0.5), "[0, 0.5)"),
            (
                "averaging.stationarity_block",
                self.stationarity_block.into(),
                Range::closed(0.0, frames),
                "0 (no guard) or [1, averaging.frames]",
            ),
            (
                "averaging.stationarity_max_shift_s",
                self.stationarity_max_shift_s.into(),
                Range::positive_max(1e-3),
                "(0, 1e-3] s",
            ),
            (
                "averaging.stationarity_max_amplitude_change",
                self.stationarity_max_amplitude_change.into(),
                Range::positive(),
                "(0, inf)",
            ),
        ])
    }
}
