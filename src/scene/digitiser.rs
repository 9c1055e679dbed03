//! `[digitiser]` and `[channels]`: what the digitiser delivers and which channel is which.

use super::check::{check, FieldError, Range};
use crate::frame::limits::{MAX_SAMPLES_PER_FRAME, MAX_SAMPLE_INTERVAL_S, MIN_SAMPLE_INTERVAL_S};
use serde::{Deserialize, Serialize};

/// Digitiser expectations.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct DigitiserConfig {
    /// Expected sampling period, seconds; 0 accepts any.
    pub sample_interval_s: f64,
    /// Expected samples per frame; 0 accepts any.
    pub samples_per_frame: usize,
    /// Lower clip level, volts (0 with high = 0: infer from codes).
    pub full_scale_low_v: f64,
    /// Upper clip level, volts.
    pub full_scale_high_v: f64,
}

/// Channel mapping.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ChannelsConfig {
    /// Start channel name.
    pub start: String,
    /// Stop channel name.
    pub stop: String,
    /// Time reference offset from the trigger when there is no start pulse, seconds.
    pub reference_offset_s: f64,
    /// Minimum start pulse amplitude, volts.
    pub start_min_amplitude_v: f64,
}

impl Default for ChannelsConfig {
    fn default() -> Self {
        ChannelsConfig {
            start: "CH1".into(),
            stop: "CH2".into(),
            reference_offset_s: 0.0,
            start_min_amplitude_v: 0.05,
        }
    }
}

impl DigitiserConfig {
    /// Checks `[digitiser]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.sample_interval_s != 0.0 {
            check(&[(
                "digitiser.sample_interval_s",
                self.sample_interval_s.into(),
                Range::closed(MIN_SAMPLE_INTERVAL_S, MAX_SAMPLE_INTERVAL_S),
                "0 (any) or a period in [1e-12, 1] s (frame::limits::MIN_SAMPLE_INTERVAL_S, MAX_SAMPLE_INTERVAL_S)",
            )])?;
        }
        check(&[(
            "digitiser.samples_per_frame",
            self.samples_per_frame.into(),
            Range::closed(0.0, MAX_SAMPLES_PER_FRAME as f64),
            "0 (any) or at most 4194304 (frame::limits::MAX_SAMPLES_PER_FRAME)",
        )])?;
        let (low, high) = (self.full_scale_low_v, self.full_scale_high_v);
        if !low.is_finite() || !high.is_finite() || (low != 0.0 || high != 0.0) && low >= high {
            return Err(FieldError::new(
                "digitiser.full_scale_high_v",
                format!("{high} (low {low})"),
                "both 0 (infer) or low < high, finite volts",
            ));
        }
        Ok(())
    }
}

impl ChannelsConfig {
    /// Checks `[channels]`: a stop channel, a start channel other than it, and the levels.
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.stop.trim().is_empty() {
            return Err(FieldError::new("channels.stop", format!("{:?}", self.stop), "a channel name"));
        }
        if crate::frame::channel_key(&self.start) == crate::frame::channel_key(&self.stop) {
            return Err(FieldError::new(
                "channels.start",
                format!("{:?}", self.start),
                "a channel other than channels.stop",
            ));
        }
        check(&[
            ("channels.reference_offset_s", self.reference_offset_s.into(), Range::closed(-1.0, 1.0), "[-1, 1] s"),
            ("channels.start_min_amplitude_v", self.start_min_amplitude_v.into(), Range::non_negative(), "[0, inf) V"),
        ])
    }
}
