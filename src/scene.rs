//! Scene: the declarative description of one sensor set-up (TOML).
//!
//! Parsed with `deny_unknown_fields` and validated at load, so a bad scene
//! fails before any frame is processed, with an error naming the field and the
//! allowed range. The pipeline is built from a validated scene (`pipeline::build`).

use crate::dsp::pulse::{Pulse, Shape, TablePulse};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The embedded default scene (the source's prototype), commented.
pub const DEFAULT_SCENE_TOML: &str = include_str!("default_scene.toml");

/// Speed of light in vacuum, m/s.
pub const C_VACUUM_M_PER_S: f64 = 299_792_458.0;

/// Errors from loading or validating a scene.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The file could not be read.
    #[error("cannot read scene {path}: {source}")]
    Io {
        /// File path.
        path: String,
        /// Cause.
        source: std::io::Error,
    },
    /// TOML syntax error, unknown key or wrong type.
    #[error("scene {origin}: {message}")]
    Parse {
        /// File path or "embedded default".
        origin: String,
        /// The TOML parser's message (names the key and line).
        message: String,
    },
    /// A value out of its allowed range.
    #[error("scene {origin}: {field} = {value} is out of range: allowed {allowed}")]
    Invalid {
        /// File path or "embedded default".
        origin: String,
        /// Dotted field name, e.g. `detector.pfa`.
        field: &'static str,
        /// The offending value.
        value: String,
        /// The allowed range or set.
        allowed: &'static str,
    },
    /// The `[simulation]` section is invalid (the message names the dotted field).
    #[error("scene {origin}: {source}")]
    Simulation {
        /// File path or "embedded default".
        origin: String,
        /// The physics layer's error, naming the field and the allowed range.
        source: crate::physics::PhysicsError,
    },
}

/// One sensor set-up.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Free text shown in logs.
    #[serde(default = "default_name")]
    pub name: String,
    /// What the digitiser delivers.
    #[serde(default)]
    pub digitiser: DigitiserConfig,
    /// Which channel is which.
    #[serde(default)]
    pub channels: ChannelsConfig,
    /// Shape of a return on the stop channel.
    #[serde(default = "PulseConfig::default_return")]
    pub return_pulse: PulseConfig,
    /// Shape of the start pulse.
    #[serde(default = "PulseConfig::default_start")]
    pub start_pulse: PulseConfig,
    /// Where returns are sought.
    #[serde(default)]
    pub range_gate: RangeGateConfig,
    /// Where the noise model is fitted.
    #[serde(default)]
    pub noise_gate: NoiseGateConfig,
    /// Detector and false-alarm target.
    #[serde(default)]
    pub detector: DetectorConfig,
    /// How instants are measured.
    #[serde(default)]
    pub timing: TimingConfig,
    /// Ensemble averaging.
    #[serde(default)]
    pub averaging: AveragingConfig,
    /// Baseline (offset) removal; absent: no baseline stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub baseline: Option<BaselineConfig>,
    /// Structured-interference cancellation; absent: no denoise stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub denoise: Option<DenoiseConfig>,
    /// System delay.
    #[serde(default)]
    pub calibration: CalibrationConfig,
    /// Propagation medium.
    #[serde(default)]
    pub medium: MediumConfig,
    /// What `tofwave simulate` synthesises for this scene (laser, targets,
    /// receiver, noise, digitiser); absent in scenes of real sensors.
    #[serde(default)]
    pub simulation: Option<crate::physics::SimulationConfig>,
}

fn default_name() -> String {
    "unnamed".into()
}

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

/// Parametric pulse shapes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PulseModel {
    /// Gaussian rising half, slower Gaussian falling half.
    Bigaussian,
    /// Symmetric Gaussian (rise time is implied by the FWHM).
    Gaussian,
    /// A measured shape: `table` values (unit peak) every `table_step_s`,
    /// the first at `table_first_s` relative to the peak. `tofwave template` learns one.
    Table,
}

/// A pulse shape.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PulseConfig {
    /// Model family.
    pub model: PulseModel,
    /// 10-90 % rise time, seconds (bigaussian only).
    #[serde(default)]
    pub rise_time_s: f64,
    /// Full width at half maximum, seconds (parametric models).
    #[serde(default)]
    pub fwhm_s: f64,
    /// Table model: spacing of the values, seconds.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub table_step_s: f64,
    /// Table model: time of the first value relative to the peak, seconds (negative).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub table_first_s: f64,
    /// Table model: the shape, unit peak.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub table: Vec<f64>,
}

impl Default for PulseConfig {
    /// The source's measured return pulse.
    fn default() -> Self {
        PulseConfig::default_return()
    }
}

fn is_zero(x: &f64) -> bool {
    *x == 0.0
}

impl PulseConfig {
    /// The shape at sampling period `dt_s` (units of samples): parametric, or
    /// the measured table.
    pub fn shape(&self, dt_s: f64) -> Shape {
        match self.model {
            PulseModel::Table => Shape::Table(TablePulse::new(
                self.table.clone(),
                self.table_step_s / dt_s,
                self.table_first_s / dt_s,
            )),
            _ => Shape::Parametric(self.pulse(dt_s)),
        }
    }

    /// The parametric shape at sampling period `dt_s`; a table model falls
    /// back to a Gaussian of the table's FWHM.
    pub fn pulse(&self, dt_s: f64) -> Pulse {
        match self.model {
            // The table's FWHM is already in samples: a period of 1 keeps it so.
            PulseModel::Table => Pulse::gaussian(self.shape(dt_s).fwhm(), 1.0),
            PulseModel::Gaussian => Pulse::gaussian(self.fwhm_s, dt_s),
            PulseModel::Bigaussian => Pulse::bigaussian(self.rise_time_s, self.fwhm_s, dt_s),
        }
    }

    fn default_return() -> Self {
        PulseConfig {
            model: PulseModel::Bigaussian,
            rise_time_s: 8.08e-9,
            fwhm_s: 26.04e-9,
            table_step_s: 0.0,
            table_first_s: 0.0,
            table: Vec::new(),
        }
    }
    fn default_start() -> Self {
        PulseConfig {
            model: PulseModel::Bigaussian,
            rise_time_s: 3.02e-9,
            fwhm_s: 8.0e-9,
            table_step_s: 0.0,
            table_first_s: 0.0,
            table: Vec::new(),
        }
    }
}

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

impl Scene {
    /// Checks the averaging, baseline and denoise sections.
    fn validate_denoise_and_averaging(&self, origin: &str) -> Result<(), SceneError> {
        let bad = |field: &'static str, value: String, allowed: &'static str| SceneError::Invalid {
            origin: origin.to_string(),
            field,
            value,
            allowed,
        };
        let a = &self.averaging;
        if a.frames == 0 || a.frames > 10_000_000 {
            return Err(bad("averaging.frames", a.frames.to_string(), "[1, 10000000]"));
        }
        let stored = a.mode == AveragingMode::Sliding || a.method != AveragingMethod::Mean;
        if stored && a.frames > 65_536 {
            return Err(bad(
                "averaging.frames",
                a.frames.to_string(),
                "[1, 65536] with mode = \"sliding\" or a robust method (they keep every frame of the window)",
            ));
        }
        if a.hop == 0 || a.hop > a.frames {
            return Err(bad("averaging.hop", a.hop.to_string(), "[1, averaging.frames]"));
        }
        if !(a.trim_fraction >= 0.0 && a.trim_fraction < 0.5) {
            return Err(bad("averaging.trim_fraction", a.trim_fraction.to_string(), "[0, 0.5)"));
        }
        if a.stationarity_block > a.frames {
            return Err(bad(
                "averaging.stationarity_block",
                a.stationarity_block.to_string(),
                "0 (no guard) or [1, averaging.frames]",
            ));
        }
        if !(a.stationarity_max_shift_s.is_finite() && a.stationarity_max_shift_s > 0.0 && a.stationarity_max_shift_s <= 1e-3) {
            return Err(bad(
                "averaging.stationarity_max_shift_s",
                a.stationarity_max_shift_s.to_string(),
                "(0, 1e-3] s",
            ));
        }
        if !(a.stationarity_max_amplitude_change.is_finite() && a.stationarity_max_amplitude_change > 0.0) {
            return Err(bad(
                "averaging.stationarity_max_amplitude_change",
                a.stationarity_max_amplitude_change.to_string(),
                "(0, inf)",
            ));
        }
        if let Some(b) = &self.baseline {
            if !(b.trim_fraction >= 0.0 && b.trim_fraction < 0.5) {
                return Err(bad("baseline.trim_fraction", b.trim_fraction.to_string(), "[0, 0.5)"));
            }
            if !(b.smoothing > 0.0 && b.smoothing <= 1.0) {
                return Err(bad("baseline.smoothing", b.smoothing.to_string(), "(0, 1]"));
            }
        }
        if let Some(d) = &self.denoise {
            if d.learn_frames == 0 || d.learn_frames > 1_000_000 {
                return Err(bad("denoise.learn_frames", d.learn_frames.to_string(), "[1, 1000000]"));
            }
            if !(d.max_burst_s.is_finite() && d.max_burst_s > 0.0 && d.max_burst_s <= 1e-2) {
                return Err(bad("denoise.max_burst_s", d.max_burst_s.to_string(), "(0, 1e-2] s"));
            }
            if !(d.pfa > 0.0 && d.pfa <= 0.5) {
                return Err(bad("denoise.pfa", d.pfa.to_string(), "(0, 0.5]"));
            }
            if !(d.bandwidth_hz.is_finite() && d.bandwidth_hz > 0.0) {
                return Err(bad("denoise.bandwidth_hz", d.bandwidth_hz.to_string(), "(0, inf) Hz"));
            }
            if d.method == DenoiseMethod::Notch && d.notch_frequencies_hz.is_empty() {
                return Err(bad("denoise.notch_frequencies_hz", "[]".into(), "at least one frequency with method = \"notch\""));
            }
            if let Some(f) = d.notch_frequencies_hz.iter().find(|f| !(f.is_finite() && **f > 0.0)) {
                return Err(bad("denoise.notch_frequencies_hz", f.to_string(), "positive, finite Hz below the Nyquist frequency"));
            }
            if !(d.notch_q.is_finite() && d.notch_q > 0.0 && d.notch_q <= 1e4) {
                return Err(bad("denoise.notch_q", d.notch_q.to_string(), "(0, 10000]"));
            }
            if !(d.highpass_hz.is_finite() && d.highpass_hz > 0.0) {
                return Err(bad("denoise.highpass_hz", d.highpass_hz.to_string(), "(0, inf) Hz below the Nyquist frequency"));
            }
            let dt = self.digitiser.sample_interval_s;
            if dt > 0.0 {
                let nyquist = 0.5 / dt;
                if let Some(f) = d.notch_frequencies_hz.iter().find(|f| **f >= nyquist) {
                    return Err(bad("denoise.notch_frequencies_hz", f.to_string(), "positive, finite Hz below the Nyquist frequency"));
                }
                if d.highpass_hz >= nyquist {
                    return Err(bad("denoise.highpass_hz", d.highpass_hz.to_string(), "(0, inf) Hz below the Nyquist frequency"));
                }
            }
        }
        Ok(())
    }
}

/// Calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct CalibrationConfig {
    /// Fixed start-to-stop delay, seconds.
    pub delay_s: f64,
    /// Leading-edge walk table: return amplitudes, volts, strictly increasing.
    /// Empty: no walk correction.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub walk_amplitude_v: Vec<f64>,
    /// Leading-edge walk table: extra delay at each amplitude, seconds
    /// (subtracted, with `delay_s`, from the time of flight; interpolated
    /// linearly in ln amplitude, held constant beyond the ends).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub walk_delay_s: Vec<f64>,
}

impl CalibrationConfig {
    /// Checks the walk table: equal lengths, finite, amplitudes positive and
    /// strictly increasing, delays within ±1 s. Names the offending field.
    pub fn validate_walk(&self, origin: &str) -> Result<(), SceneError> {
        let bad = |field: &'static str, value: String, allowed: &'static str| SceneError::Invalid {
            origin: origin.to_string(),
            field,
            value,
            allowed,
        };
        let (a, d) = (&self.walk_amplitude_v, &self.walk_delay_s);
        if a.len() != d.len() {
            return Err(bad(
                "calibration.walk_delay_s",
                format!("{} values ({} amplitudes)", d.len(), a.len()),
                "as many values as calibration.walk_amplitude_v",
            ));
        }
        if a.iter().any(|v| !(v.is_finite() && *v > 0.0)) || a.windows(2).any(|w| w[1] <= w[0]) {
            return Err(bad(
                "calibration.walk_amplitude_v",
                format!("{a:?}"),
                "finite, positive, strictly increasing volts",
            ));
        }
        if d.iter().any(|v| !(v.is_finite() && v.abs() <= 1.0)) {
            return Err(bad("calibration.walk_delay_s", format!("{d:?}"), "finite, [-1, 1] s"));
        }
        Ok(())
    }
}

/// Medium.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MediumConfig {
    /// Group refractive index.
    pub refractive_index: f64,
}

impl Default for MediumConfig {
    fn default() -> Self {
        MediumConfig {
            refractive_index: 1.000268,
        }
    }
}

impl Scene {
    /// The embedded default scene (the source's prototype).
    pub fn default_scene() -> Scene {
        Scene::from_toml_str(DEFAULT_SCENE_TOML, "embedded default")
            .expect("the embedded default scene is valid (tested)")
    }

    /// Reads and validates a scene file.
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Scene::from_toml_str(&text, &path.display().to_string())
    }

    /// Parses and validates TOML text; `origin` names it in errors.
    pub fn from_toml_str(text: &str, origin: &str) -> Result<Scene, SceneError> {
        let scene: Scene = toml::from_str(text).map_err(|e| SceneError::Parse {
            origin: origin.to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        scene.validate(origin)?;
        Ok(scene)
    }

    /// The scene as TOML (uncommented; see [`DEFAULT_SCENE_TOML`] for the commented default).
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("a scene always serialises")
    }

    /// Speed of light in the medium, m/s.
    pub fn c_medium_m_per_s(&self) -> f64 {
        C_VACUUM_M_PER_S / self.medium.refractive_index
    }

    /// Checks every value against its allowed range.
    pub fn validate(&self, origin: &str) -> Result<(), SceneError> {
        let bad = |field: &'static str, value: String, allowed: &'static str| SceneError::Invalid {
            origin: origin.to_string(),
            field,
            value,
            allowed,
        };
        let finite_nonneg = |x: f64| x.is_finite() && x >= 0.0;
        let d = &self.digitiser;
        if !finite_nonneg(d.sample_interval_s) || d.sample_interval_s > 1.0 {
            return Err(bad(
                "digitiser.sample_interval_s",
                d.sample_interval_s.to_string(),
                "0 (any) or a period in (0, 1] s",
            ));
        }
        if !d.full_scale_low_v.is_finite()
            || !d.full_scale_high_v.is_finite()
            || (d.full_scale_low_v != 0.0 || d.full_scale_high_v != 0.0)
                && d.full_scale_low_v >= d.full_scale_high_v
        {
            return Err(bad(
                "digitiser.full_scale_high_v",
                format!("{} (low {})", d.full_scale_high_v, d.full_scale_low_v),
                "both 0 (infer) or low < high, finite volts",
            ));
        }
        let c = &self.channels;
        if c.stop.trim().is_empty() {
            return Err(bad("channels.stop", format!("{:?}", c.stop), "a channel name"));
        }
        if crate::frame::channel_key(&c.start) == crate::frame::channel_key(&c.stop) {
            return Err(bad(
                "channels.start",
                format!("{:?}", c.start),
                "a channel other than channels.stop",
            ));
        }
        if !c.reference_offset_s.is_finite() || c.reference_offset_s.abs() > 1.0 {
            return Err(bad(
                "channels.reference_offset_s",
                c.reference_offset_s.to_string(),
                "[-1, 1] s",
            ));
        }
        if !finite_nonneg(c.start_min_amplitude_v) {
            return Err(bad(
                "channels.start_min_amplitude_v",
                c.start_min_amplitude_v.to_string(),
                "[0, inf) V",
            ));
        }
        for (p, fwhm_field, rise_field, table_field) in [
            (&self.return_pulse, "return_pulse.fwhm_s", "return_pulse.rise_time_s", "return_pulse.table"),
            (&self.start_pulse, "start_pulse.fwhm_s", "start_pulse.rise_time_s", "start_pulse.table"),
        ] {
            if p.model == PulseModel::Table {
                let peak = p.table.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                if p.table.len() < 4
                    || p.table.iter().any(|v| !v.is_finite())
                    || (peak - 1.0).abs() > 0.01
                    || !(p.table_step_s.is_finite() && p.table_step_s > 0.0)
                    || !(p.table_first_s.is_finite() && p.table_first_s < 0.0)
                {
                    return Err(bad(
                        table_field,
                        format!("{} values, step {} s, first {} s, peak {peak}", p.table.len(), p.table_step_s, p.table_first_s),
                        "at least 4 finite values with peak 1 (within 1 %), table_step_s > 0, table_first_s < 0",
                    ));
                }
                continue;
            }
            if !(p.fwhm_s.is_finite() && p.fwhm_s > 0.0 && p.fwhm_s <= 1e-3) {
                return Err(bad(fwhm_field, p.fwhm_s.to_string(), "(0, 1e-3] s"));
            }
            if p.model == PulseModel::Bigaussian {
                // The rising half's share of the FWHM is 1.1774/1.6869 of the
                // rise time; it must leave a positive falling half.
                let max_rise = p.fwhm_s * 1.686_922_421_262_926_4 / 1.177_410_022_515_474_6;
                if !(p.rise_time_s.is_finite() && p.rise_time_s > 0.0 && p.rise_time_s < max_rise) {
                    return Err(bad(
                        rise_field,
                        p.rise_time_s.to_string(),
                        "(0, 1.43 * fwhm_s) s: the rising half must fit inside the FWHM",
                    ));
                }
            }
        }
        let r = &self.range_gate;
        if !(r.min_m.is_finite() && r.max_m.is_finite() && r.min_m >= -1000.0 && r.max_m > r.min_m && r.max_m <= 1e6) {
            return Err(bad(
                "range_gate.max_m",
                format!("{} (min_m {})", r.max_m, r.min_m),
                "min_m >= -1000, min_m < max_m <= 1e6 m",
            ));
        }
        let g = &self.noise_gate;
        if !finite_nonneg(g.guard_s) || g.guard_s > 1.0 {
            return Err(bad("noise_gate.guard_s", g.guard_s.to_string(), "[0, 1] s"));
        }
        if !g.pre_trigger && !g.beyond_range {
            return Err(bad(
                "noise_gate.pre_trigger",
                "false (and beyond_range false)".into(),
                "at least one of pre_trigger, beyond_range true",
            ));
        }
        if g.min_samples < 2 {
            return Err(bad("noise_gate.min_samples", g.min_samples.to_string(), "[2, inf)"));
        }
        if g.forgetting_frames > 1_000_000 {
            return Err(bad(
                "noise_gate.forgetting_frames",
                g.forgetting_frames.to_string(),
                "0 (off) or [1, 1000000] frames",
            ));
        }
        let det = &self.detector;
        if !(det.pfa > 0.0 && det.pfa <= 0.5) {
            return Err(bad("detector.pfa", det.pfa.to_string(), "(0, 0.5]"));
        }
        if !(det.normality_alpha > 0.0 && det.normality_alpha < 1.0) {
            return Err(bad(
                "detector.normality_alpha",
                det.normality_alpha.to_string(),
                "(0, 1)",
            ));
        }
        if det.whiten && det.kind != DetectorKind::MatchedFilter {
            return Err(bad(
                "detector.whiten",
                "true (with kind = \"threshold\")".into(),
                "false unless detector.kind = \"matched_filter\" (whitening prewhitens the matched filter)",
            ));
        }
        if det.whiten && !(1..=64).contains(&det.whiten_order) {
            return Err(bad("detector.whiten_order", det.whiten_order.to_string(), "[1, 64]"));
        }
        if det.cfar != CfarKind::Off {
            if !(1..=1024).contains(&det.cfar_training_cells) {
                return Err(bad(
                    "detector.cfar_training_cells",
                    det.cfar_training_cells.to_string(),
                    "[1, 1024] cells on each side",
                ));
            }
            if det.cfar_guard_cells > 4096 {
                return Err(bad("detector.cfar_guard_cells", det.cfar_guard_cells.to_string(), "[0, 4096]"));
            }
            if det.cfar == CfarKind::Os && det.cfar_os_rank > 2 * det.cfar_training_cells {
                return Err(bad(
                    "detector.cfar_os_rank",
                    det.cfar_os_rank.to_string(),
                    "0 (3/4 of the training cells) or [1, 2 * cfar_training_cells]",
                ));
            }
            if det.threshold_mode == ThresholdMode::Empirical {
                return Err(bad(
                    "detector.threshold_mode",
                    "\"empirical\" (with cfar)".into(),
                    "\"gaussian\" when detector.cfar is \"ca\" or \"os\" (CFAR sets its own threshold)",
                ));
            }
        }
        let t = &self.timing;
        if !(t.fraction > 0.0 && t.fraction < 1.0) {
            return Err(bad("timing.fraction", t.fraction.to_string(), "(0, 1)"));
        }
        if !(t.leading_edge_v.is_finite() && t.leading_edge_v > 0.0) {
            return Err(bad("timing.leading_edge_v", t.leading_edge_v.to_string(), "(0, inf) V"));
        }
        self.validate_denoise_and_averaging(origin)?;
        if !self.calibration.delay_s.is_finite() || self.calibration.delay_s.abs() > 1.0 {
            return Err(bad(
                "calibration.delay_s",
                self.calibration.delay_s.to_string(),
                "[-1, 1] s",
            ));
        }
        self.calibration.validate_walk(origin)?;
        let n = self.medium.refractive_index;
        if !(n.is_finite() && (1.0..=4.0).contains(&n)) {
            return Err(bad("medium.refractive_index", n.to_string(), "[1, 4]"));
        }
        if let Some(sim) = &self.simulation {
            sim.validate().map_err(|source| SceneError::Simulation {
                origin: origin.to_string(),
                source,
            })?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_scene_parses_and_round_trips() {
        let s = Scene::default_scene();
        assert_eq!(s.channels.stop, "CH2");
        assert_eq!(s.detector.pfa, 1e-6);
        let again = Scene::from_toml_str(&s.to_toml(), "round trip").unwrap();
        assert_eq!(s, again);
    }

    #[test]
    fn unknown_key_is_refused_by_name() {
        let text = DEFAULT_SCENE_TOML.replace("[detector]", "[detector]\npfaa = 1e-3");
        let e = Scene::from_toml_str(&text, "x.toml").unwrap_err().to_string();
        assert!(e.contains("pfaa"), "{e}");
        assert!(e.contains("x.toml"), "{e}");
    }

    #[test]
    fn out_of_range_names_field_and_range() {
        let text = DEFAULT_SCENE_TOML.replace("pfa = 1e-6", "pfa = 0.7");
        let e = Scene::from_toml_str(&text, "x.toml").unwrap_err().to_string();
        assert!(e.contains("detector.pfa") && e.contains("(0, 0.5]"), "{e}");
    }

    #[test]
    fn minimal_scene_takes_defaults() {
        let s = Scene::from_toml_str("name = \"m\"\n", "m").unwrap();
        assert_eq!(s.detector.kind, DetectorKind::MatchedFilter);
        assert_eq!(s.return_pulse.fwhm_s, 26.04e-9);
    }
}

/// A calibration file written by `tofwave calibrate` and applied by
/// `tofwave process --calibration`: the measured delay plus how it was measured,
/// so a scene timed differently can be refused rather than silently biased.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFile {
    /// The delay to apply.
    pub calibration: CalibrationConfig,
    /// How it was measured.
    pub measurement: CalibrationMeasurement,
}

/// Provenance and statistics of a calibration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationMeasurement {
    /// Range of the calibration target, m.
    pub known_range_m: f64,
    /// Returns used.
    pub returns: u64,
    /// Reports without a usable return, or rejected as outliers.
    pub excluded: u64,
    /// Standard deviation of the per-report delay, s.
    pub delay_std_s: f64,
    /// Standard error of the mean delay, s.
    pub delay_sem_s: f64,
    /// Mean amplitude of the returns used, V.
    pub mean_amplitude_v: f64,
    /// Timing method the delay belongs to.
    pub timing_method: TimingMethod,
    /// Timing fraction the delay belongs to.
    pub timing_fraction: f64,
    /// Leading-edge level the walk table belongs to, volts (0 in files
    /// written before walk tables existed).
    #[serde(default)]
    pub leading_edge_v: f64,
    /// Frames averaged per report when measured.
    pub frames_averaged: u32,
    /// Inputs measured.
    pub inputs: Vec<String>,
}

impl CalibrationFile {
    /// Reads a calibration file.
    pub fn load(path: &Path) -> Result<CalibrationFile, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let f: CalibrationFile = toml::from_str(&text).map_err(|e| SceneError::Parse {
            origin: path.display().to_string(),
            message: e.to_string().trim_end().to_string(),
        })?;
        if !f.calibration.delay_s.is_finite() || f.calibration.delay_s.abs() > 1.0 {
            return Err(SceneError::Invalid {
                origin: path.display().to_string(),
                field: "calibration.delay_s",
                value: f.calibration.delay_s.to_string(),
                allowed: "[-1, 1] s",
            });
        }
        f.calibration.validate_walk(&path.display().to_string())?;
        Ok(f)
    }

    /// Applies the delay to `scene`, refusing a scene timed differently from the calibration.
    pub fn apply(&self, scene: &mut Scene, origin: &str) -> Result<(), SceneError> {
        let m = &self.measurement;
        if m.timing_method != scene.timing.method || m.timing_fraction != scene.timing.fraction {
            return Err(SceneError::Invalid {
                origin: origin.to_string(),
                field: "measurement.timing_method",
                value: format!("{} at fraction {}", m.timing_method.name(), m.timing_fraction),
                allowed: "the scene's timing.method and timing.fraction (re-run `tofwave calibrate` with this scene)",
            });
        }
        if !self.calibration.walk_amplitude_v.is_empty() && scene.timing.leading_edge_v != m.leading_edge_v {
            return Err(SceneError::Invalid {
                origin: origin.to_string(),
                field: "measurement.leading_edge_v",
                value: m.leading_edge_v.to_string(),
                allowed: "the scene's timing.leading_edge_v (a walk table belongs to one comparator level)",
            });
        }
        scene.calibration = self.calibration.clone();
        Ok(())
    }
}
