//! `[denoise]`: cancellation of structured interference.

use super::check::{check, FieldError, Range};
use serde::{Deserialize, Serialize};

/// Interference-cancellation methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DenoiseMethod {
    /// Learn the burst waveform from the noise gates, detect each occurrence
    /// by correlation, subtract it (amplitude and sub-sample shift fitted).
    Template,
    /// Zero-phase notch filters at `notch_frequencies_hz` (the plain alternative).
    Notch,
    /// Zero-phase high-pass filter at `highpass_hz` (the plain alternative).
    Highpass,
}

/// `[denoise]`: cancellation of a structured, repeating interference burst.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DenoiseConfig {
    /// Template (learned burst), notch or high-pass.
    pub method: DenoiseMethod,
    /// Template: frames whose noise gates teach the burst waveform (held back
    /// until the template is learned, then cancelled like every later frame).
    pub learn_frames: u32,
    /// Template: longest burst to learn, s.
    pub max_burst_s: f64,
    /// Template: probability per frame of detecting a burst that is not there.
    pub pfa: f64,
    /// Template: the learned waveform is low-passed to this band, Hz (the
    /// burst's modes lie below it; the cut removes the noise averaged into it).
    pub bandwidth_hz: f64,
    /// Template: once a burst is found, look for it in the next frame where
    /// the trigger times put it before searching the whole template.
    pub predict: bool,
    /// Notch: centre frequencies, Hz.
    pub notch_frequencies_hz: Vec<f64>,
    /// Notch: quality factor (centre / -3 dB bandwidth).
    pub notch_q: f64,
    /// High-pass: -3 dB corner, Hz (second-order Butterworth, run forward and backward).
    pub highpass_hz: f64,
}

impl Default for DenoiseConfig {
    fn default() -> Self {
        DenoiseConfig {
            method: DenoiseMethod::Template,
            learn_frames: 2000,
            max_burst_s: 60e-6,
            pfa: 1e-3,
            bandwidth_hz: 12e6,
            predict: true,
            notch_frequencies_hz: Vec::new(),
            notch_q: 5.0,
            highpass_hz: 10e6,
        }
    }
}

impl DenoiseConfig {
    /// Checks `[denoise]`; filter frequencies must lie below the Nyquist
    /// frequency of `sample_interval_s` when the scene states one (> 0).
    pub fn validate(&self, sample_interval_s: f64) -> Result<(), FieldError> {
        const BELOW_NYQUIST: &str = "positive, finite Hz below the Nyquist frequency";
        const HIGHPASS: &str = "(0, inf) Hz below the Nyquist frequency";
        check(&[
            ("denoise.learn_frames", self.learn_frames.into(), Range::closed(1.0, 1e6), "[1, 1000000]"),
            ("denoise.max_burst_s", self.max_burst_s.into(), Range::positive_max(1e-2), "(0, 1e-2] s"),
            ("denoise.pfa", self.pfa.into(), Range::positive_max(0.5), "(0, 0.5]"),
            ("denoise.bandwidth_hz", self.bandwidth_hz.into(), Range::positive(), "(0, inf) Hz"),
        ])?;
        if self.method == DenoiseMethod::Notch && self.notch_frequencies_hz.is_empty() {
            return Err(FieldError::new(
                "denoise.notch_frequencies_hz",
                "[]",
                "at least one frequency with method = \"notch\"",
            ));
        }
        if let Some(f) = self.notch_frequencies_hz.iter().find(|f| !Range::positive().contains(**f)) {
            return Err(FieldError::new("denoise.notch_frequencies_hz", f, BELOW_NYQUIST));
        }
        check(&[
            ("denoise.notch_q", self.notch_q.into(), Range::positive_max(1e4), "(0, 10000]"),
            ("denoise.highpass_hz", self.highpass_hz.into(), Range::positive(), HIGHPASS),
        ])?;
        if sample_interval_s > 0.0 {
            let nyquist = 0.5 / sample_interval_s;
            if let Some(f) = self.notch_frequencies_hz.iter().find(|f| **f >= nyquist) {
                return Err(FieldError::new("denoise.notch_frequencies_hz", f, BELOW_NYQUIST));
            }
            if self.highpass_hz >= nyquist {
                return Err(FieldError::new("denoise.highpass_hz", self.highpass_hz, HIGHPASS));
            }
        }
        Ok(())
    }
}

/// `[events]`: telling returns from the receiver's interference events
/// (oscillations below `max_frequency_hz` at random times; see
/// `detect::events`). On by default: the default scene is the prototype,
/// whose receiver has them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EventsConfig {
    /// Test every detection's shape; false: no events stage.
    pub enabled: bool,
    /// Highest frequency of an event's modes, Hz (the prototype's lay below 10 MHz).
    pub max_frequency_hz: f64,
    /// Span each side of a pulse's support where a return leaves only noise, s.
    pub flank_s: f64,
    /// Probability that a clean return's flanks fail the return-model test
    /// (it is then tested against the event subspace, at some SNR cost).
    pub fit_alpha: f64,
}

impl Default for EventsConfig {
    fn default() -> Self {
        EventsConfig { enabled: true, max_frequency_hz: 10e6, flank_s: 60e-9, fit_alpha: 1e-3 }
    }
}

impl EventsConfig {
    /// Checks `[events]`.
    pub fn validate(&self) -> Result<(), FieldError> {
        check(&[
            ("events.max_frequency_hz", self.max_frequency_hz.into(), Range::positive(), "(0, inf) Hz"),
            ("events.flank_s", self.flank_s.into(), Range::positive_max(1e-3), "(0, 1e-3] s"),
            ("events.fit_alpha", self.fit_alpha.into(), Range::positive_max(0.5), "(0, 0.5]"),
        ])
    }
}
