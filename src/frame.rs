//! Domain types shared by every layer: frames in, reports out.
//!
//! No prost or tonic types here: `wire` maps the wire contract to
//! and from these.

use serde::Serialize;

pub mod limits;

/// What a channel carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ChannelRole {
    /// Not said by the source: the scene's channel names decide.
    Unspecified,
    /// Transmitted-pulse reference.
    Start,
    /// Receiver output holding the returns.
    Stop,
    /// Carried along, not processed.
    Other,
}

/// Samples as the digitiser delivered them. Integer codes stay integers so
/// that averaging can accumulate them exactly.
#[derive(Debug, Clone, PartialEq)]
pub enum Samples {
    /// 8-bit codes.
    I8(Vec<i8>),
    /// 16-bit codes.
    I16(Vec<i16>),
    /// 32-bit codes.
    I32(Vec<i32>),
    /// Single-precision values (before `volts_per_code`/`offset_v`).
    F32(Vec<f32>),
    /// Double-precision values (averages, CSV readings).
    F64(Vec<f64>),
}

impl Samples {
    /// Number of samples.
    pub fn len(&self) -> usize {
        match self {
            Samples::I8(v) => v.len(),
            Samples::I16(v) => v.len(),
            Samples::I32(v) => v.len(),
            Samples::F32(v) => v.len(),
            Samples::F64(v) => v.len(),
        }
    }

    /// True when there are no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// True for integer ADC codes.
    pub fn is_integer(&self) -> bool {
        matches!(self, Samples::I8(_) | Samples::I16(_) | Samples::I32(_))
    }

    /// Name of the sample type, for messages.
    pub fn kind(&self) -> &'static str {
        match self {
            Samples::I8(_) => "i8",
            Samples::I16(_) => "i16",
            Samples::I32(_) => "i32",
            Samples::F32(_) => "f32",
            Samples::F64(_) => "f64",
        }
    }

    /// Sample `i` as an integer code, if these are integer codes.
    #[inline]
    pub fn code(&self, i: usize) -> Option<i64> {
        match self {
            Samples::I8(v) => Some(v[i] as i64),
            Samples::I16(v) => Some(v[i] as i64),
            Samples::I32(v) => Some(v[i] as i64),
            _ => None,
        }
    }

    /// Sample `i` as a raw (unscaled) f64.
    #[inline]
    pub fn raw(&self, i: usize) -> f64 {
        match self {
            Samples::I8(v) => v[i] as f64,
            Samples::I16(v) => v[i] as f64,
            Samples::I32(v) => v[i] as f64,
            Samples::F32(v) => v[i] as f64,
            Samples::F64(v) => v[i],
        }
    }
}

/// One digitised channel.
#[derive(Debug, Clone, PartialEq)]
pub struct Channel {
    /// Name as the capture spells it; matched loosely (see [`channel_key`]).
    pub name: String,
    /// Role if the source said so; otherwise the scene's names decide.
    pub role: ChannelRole,
    /// The samples, codes or values.
    pub samples: Samples,
    /// volts = raw * volts_per_code + offset_v.
    pub volts_per_code: f64,
    /// Offset added after scaling, volts.
    pub offset_v: f64,
}

impl Channel {
    /// A channel already in volts.
    pub fn from_volts(name: impl Into<String>, role: ChannelRole, volts: Vec<f64>) -> Self {
        Channel {
            name: name.into(),
            role,
            samples: Samples::F64(volts),
            volts_per_code: 1.0,
            offset_v: 0.0,
        }
    }

    /// Writes the channel in volts into `out` (cleared first).
    pub fn volts_into(&self, out: &mut Vec<f64>) {
        self.volts_of_into(0..self.samples.len(), out);
    }

    /// Samples `range` (clamped to the channel) in volts into `out` (cleared
    /// first): each the very value [`volts_into`](Self::volts_into) gives it.
    pub fn volts_of_into(&self, range: std::ops::Range<usize>, out: &mut Vec<f64>) {
        out.clear();
        let (g, o) = (self.volts_per_code, self.offset_v);
        let end = range.end.min(self.samples.len());
        let r = range.start.min(end)..end;
        // One loop per sample type (not a `match` per sample), so each vectorises.
        match &self.samples {
            Samples::I8(v) => out.extend(v[r].iter().map(|&x| x as f64 * g + o)),
            Samples::I16(v) => decode_i16(&v[r], g, o, out),
            Samples::I32(v) => out.extend(v[r].iter().map(|&x| x as f64 * g + o)),
            Samples::F32(v) => out.extend(v[r].iter().map(|&x| x as f64 * g + o)),
            Samples::F64(v) => out.extend(v[r].iter().map(|&x| x * g + o)),
        }
    }

    /// The channel in volts.
    pub fn volts(&self) -> Vec<f64> {
        let mut v = Vec::with_capacity(self.samples.len());
        self.volts_into(&mut v);
        v
    }
}

/// `code · g + o` for every i16 code, appended to `out` (a multiply, then an
/// add: the same bits on every path). Four or eight at a time where the CPU
/// has AVX2 or AVX-512 (picked at run time; the portable build's SSE2 has no
/// sign-extending load and converts two at a time).
fn decode_i16(codes: &[i16], g: f64, o: f64, out: &mut Vec<f64>) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: AVX-512F checked just above.
            return unsafe { decode_i16_avx512(codes, g, o, out) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 checked just above.
            return unsafe { decode_i16_avx2(codes, g, o, out) };
        }
    }
    decode_i16_body(codes, g, o, out);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
fn decode_i16_avx512(codes: &[i16], g: f64, o: f64, out: &mut Vec<f64>) {
    decode_i16_body(codes, g, o, out);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn decode_i16_avx2(codes: &[i16], g: f64, o: f64, out: &mut Vec<f64>) {
    decode_i16_body(codes, g, o, out);
}

#[inline(always)]
fn decode_i16_body(codes: &[i16], g: f64, o: f64, out: &mut Vec<f64>) {
    // Written once (no zero fill first).
    out.reserve(codes.len());
    out.extend(codes.iter().map(|&c| c as f64 * g + o));
}

/// One acquisition: one laser shot or one scope trigger.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Sensor this frame came from.
    pub sensor_id: String,
    /// Per-sensor sequence number (segment index for multi-segment captures).
    pub sequence: u64,
    /// Absolute trigger instant, seconds (capture epoch or sensor clock).
    pub trigger_time_s: f64,
    /// Sampling period, seconds; > 0.
    pub sample_interval_s: f64,
    /// Time of sample 0 relative to the trigger, seconds (negative: pre-trigger).
    pub first_sample_offset_s: f64,
    /// The channels, in the order the source gave them.
    pub channels: Vec<Channel>,
    /// The laser was known to be off (noise-only frame).
    pub laser_off: bool,
}

impl Frame {
    /// Samples per channel (of the first channel; readers keep them equal).
    pub fn len(&self) -> usize {
        self.channels.first().map_or(0, |c| c.samples.len())
    }

    /// True when the frame has no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A frame with no channels and an empty sensor id (allocates nothing).
    pub fn empty() -> Frame {
        Frame {
            sensor_id: String::new(),
            sequence: 0,
            trigger_time_s: 0.0,
            sample_interval_s: 0.0,
            first_sample_offset_s: 0.0,
            channels: Vec::new(),
            laser_off: false,
        }
    }

    /// Time of sample `i` relative to the trigger, seconds.
    pub fn sample_time_s(&self, i: f64) -> f64 {
        self.first_sample_offset_s + i * self.sample_interval_s
    }

    /// Finds a channel by name, matching vendor spellings loosely
    /// (`CH2`, `Ch2`, `C2`, `2` and `channel 2` are one channel).
    pub fn channel(&self, name: &str) -> Option<&Channel> {
        let key = channel_key(name);
        self.channels.iter().find(|c| channel_key(&c.name) == key)
    }

    /// Names of the channels, for error messages.
    pub fn channel_names(&self) -> Vec<&str> {
        self.channels.iter().map(|c| c.name.as_str()).collect()
    }
}

/// Canonical form of a channel name: vendor spellings of channel n all map
/// to `"n"`; other names are lower-cased and trimmed.
pub fn channel_key(name: &str) -> String {
    let mut key = String::with_capacity(name.len());
    channel_key_into(name, &mut key);
    key
}

/// [`channel_key`] written into `key` (cleared first): no allocation once
/// `key` has grown to the name's length.
pub fn channel_key_into(name: &str, key: &mut String) {
    key.clear();
    key.extend(name.trim().chars().map(|c| c.to_ascii_lowercase()));
    let lower = key.as_str();
    let stripped = ["channel", "chan", "ch", "c"]
        .iter()
        .find_map(|p| lower.strip_prefix(p))
        .map(|r| r.trim_start_matches([' ', '_', '-']))
        .unwrap_or(lower);
    if !stripped.is_empty() && stripped.bytes().all(|b| b.is_ascii_digit()) {
        // The number without leading zeros: a suffix of `key`.
        let digits = stripped.trim_start_matches('0').len();
        let cut = key.len() - digits;
        key.drain(..cut);
    }
}

/// Gaussian noise model as reported (JSON contract `noise`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct NoiseSummary {
    /// Mean of the gate, volts.
    pub mean_v: f64,
    /// Standard deviation of the gate, volts.
    pub sigma_v: f64,
    /// Sample skewness.
    pub skewness: f64,
    /// Sample excess kurtosis (0 for a Gaussian).
    pub excess_kurtosis: f64,
    /// Normality test passed.
    pub gaussian: bool,
    /// Jarque-Bera p-value.
    pub normality_p_value: f64,
    /// Robust sigma, volts: MAD * 1.4826, or for coarsely quantised samples
    /// the probit fit of their distribution (`math::quantised`).
    pub robust_sigma_v: f64,
    /// Samples in the gate.
    pub samples: u64,
    /// Robust and plain sigma disagree.
    pub contaminated: bool,
}

/// The detector used (JSON contract `detector`).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct DetectorSummary {
    /// "matched_filter" or "threshold".
    pub kind: &'static str,
    /// Design false-alarm probability per report over the range gate.
    pub pfa_design: f64,
    /// Threshold, in volts of (template) amplitude.
    pub threshold: f64,
    /// Per-cell false-alarm probability.
    pub pfa_cell: f64,
    /// Effectively independent cells in the range gate.
    pub cells_effective: f64,
}

/// Empirical false-alarm statistics (JSON contract `false_alarm`),
/// cumulative per sensor. With the events stage on, the count starts once
/// its test has learned its null from the gates (at most 16 frames): until
/// then `cells` is 0 (as for a frame without a noise gate).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct FalseAlarmStats {
    /// Crossings expected in the noise gate at the design per-cell rate.
    pub expected_per_frame: f64,
    /// Crossings observed in the noise gate (less those the events stage
    /// judged interference events, where it runs).
    pub observed: u64,
    /// Effectively independent noise-gate cells examined.
    pub cells: f64,
    /// observed / cells.
    pub rate: f64,
    /// 95 % Clopper-Pearson interval of the per-cell rate.
    pub ci95: [f64; 2],
    /// The observed rate is above the design's interval.
    pub excess: bool,
}

/// One detected return (JSON contract `returns[]`).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Return {
    /// c_air * tof / 2, metres.
    pub range_m: f64,
    /// One-sigma range uncertainty, metres.
    pub range_sigma_m: f64,
    /// Time of flight after calibration, seconds.
    pub tof_s: f64,
    /// Estimated pulse amplitude above the noise mean, volts.
    pub amplitude_v: f64,
    /// 20 log10(amplitude / sigma), dB.
    pub snr_db: f64,
    /// Detector statistic over threshold (>= 1 when detected).
    pub score: f64,
    /// Probability of detection for the fitted amplitude.
    pub pd: f64,
    /// Stop timing instant relative to the trigger, seconds.
    pub t_stop_s: f64,
    /// Time of the sample-level peak relative to the trigger, seconds.
    pub t_peak_s: f64,
    /// "saturated", "frame_edge", "weak", "non_gaussian_noise", "overlapping", ...
    pub flags: ReturnFlags,
}

/// A condition of one return (JSON: its [`name`](ReturnFlag::name)).
/// Declared in the order reports list them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReturnFlag {
    /// The pulse reaches past the first or last sample.
    FrameEdge,
    /// A sample of the pulse is at (or within a quarter step of) a rail.
    Saturated,
    /// Probability of detection below one half at the fitted amplitude.
    Weak,
    /// The noise gate failed the normality test.
    NonGaussianNoise,
    /// Another return lies within two FWHM.
    Overlapping,
    /// The timing method fell back to the sample-level peak.
    TimingFallback,
    /// The fitted pulse shape left a residual above the misfit limit.
    ShapeMismatch,
    /// An interference event lies on or beside the return (it stood out of
    /// the event subspace by the detector's threshold).
    Interference,
}

impl ReturnFlag {
    /// Every flag, in report order.
    pub const ALL: [ReturnFlag; 8] = [
        ReturnFlag::FrameEdge,
        ReturnFlag::Saturated,
        ReturnFlag::Weak,
        ReturnFlag::NonGaussianNoise,
        ReturnFlag::Overlapping,
        ReturnFlag::TimingFallback,
        ReturnFlag::ShapeMismatch,
        ReturnFlag::Interference,
    ];

    /// Name in reports (JSON and protobuf).
    pub fn name(self) -> &'static str {
        match self {
            ReturnFlag::FrameEdge => "frame_edge",
            ReturnFlag::Saturated => "saturated",
            ReturnFlag::Weak => "weak",
            ReturnFlag::NonGaussianNoise => "non_gaussian_noise",
            ReturnFlag::Overlapping => "overlapping",
            ReturnFlag::TimingFallback => "timing_fallback",
            ReturnFlag::ShapeMismatch => "shape_mismatch",
            ReturnFlag::Interference => "interference",
        }
    }
}

impl std::fmt::Display for ReturnFlag {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl PartialEq<str> for ReturnFlag {
    fn eq(&self, other: &str) -> bool {
        self.name() == other
    }
}

impl PartialEq<&str> for ReturnFlag {
    fn eq(&self, other: &&str) -> bool {
        self.name() == *other
    }
}

/// The flags of one return: a set, listed in [`ReturnFlag::ALL`] order
/// (no heap allocation).
#[derive(Clone, Copy, Default, PartialEq, Eq)]
pub struct ReturnFlags(u8);

impl ReturnFlags {
    /// Adds `flag`.
    pub fn insert(&mut self, flag: ReturnFlag) {
        self.0 |= 1 << flag as u8;
    }

    /// True when `flag` is set.
    pub fn contains(&self, flag: ReturnFlag) -> bool {
        self.0 & (1 << flag as u8) != 0
    }

    /// True when no flag is set.
    pub fn is_empty(&self) -> bool {
        self.0 == 0
    }

    /// Number of flags set.
    pub fn len(&self) -> usize {
        self.0.count_ones() as usize
    }

    /// The flags set, in report order.
    pub fn iter(&self) -> ReturnFlagsIter {
        ReturnFlagsIter { flags: *self, next: 0 }
    }
}

/// Iterator over [`ReturnFlags`], in report order.
#[derive(Debug, Clone)]
pub struct ReturnFlagsIter {
    flags: ReturnFlags,
    next: usize,
}

impl Iterator for ReturnFlagsIter {
    type Item = ReturnFlag;

    fn next(&mut self) -> Option<ReturnFlag> {
        while let Some(&f) = ReturnFlag::ALL.get(self.next) {
            self.next += 1;
            if self.flags.contains(f) {
                return Some(f);
            }
        }
        None
    }
}

impl IntoIterator for &ReturnFlags {
    type Item = ReturnFlag;
    type IntoIter = ReturnFlagsIter;

    fn into_iter(self) -> ReturnFlagsIter {
        self.iter()
    }
}

impl std::fmt::Debug for ReturnFlags {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.iter().map(ReturnFlag::name)).finish()
    }
}

impl Serialize for ReturnFlags {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_seq(self.iter().map(ReturnFlag::name))
    }
}

/// A frame-level condition of a report (JSON: its name, with a count where
/// it carries one: `non_finite_samples:3`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameFlag {
    /// The frame said the laser was off.
    LaserOff,
    /// The frame has no start channel: the trigger is the reference.
    NoStartChannel,
    /// No start pulse above its noise: the trigger is the reference.
    NoStartPulse,
    /// The start pulse was timed by the fallback method.
    StartTimingFallback,
    /// No quiet samples to measure the baseline on.
    NoBaselineGate,
    /// Interference cancellation found no template to learn.
    NoInterferenceLearned,
    /// An interference burst was cancelled.
    InterferenceCancelled,
    /// The average holds fewer frames than asked (end of input).
    PartialAverage,
    /// The averaged frames' noise or returns moved within the group.
    Nonstationary,
    /// A frame of the group had the laser off.
    LaserOffInGroup,
    /// Non-finite samples in the stop channel (how many).
    NonFiniteSamples(usize),
    /// The noise gate holds few samples.
    NoiseGateSmall,
    /// Too few noise samples for a noise model.
    NoNoiseEstimate,
    /// The noise gate has zero spread.
    ZeroNoise,
    /// The noise gate failed the normality test.
    NonGaussianNoise,
    /// Robust and plain noise sigma disagree.
    NoiseGateContaminated,
    /// Whitening asked for, its noise model not ready yet.
    WhitenWarmingUp,
    /// The threshold came from the empirical tail.
    EmpiricalThreshold,
    /// Empirical threshold asked for, too few gate outputs yet.
    EmpiricalThresholdWarmingUp,
    /// Noise-gate false alarms above the design's interval.
    FalseAlarmExcess,
    /// Detections judged interference events and dropped (how many).
    InterferenceEvents(usize),
}

impl FrameFlag {
    /// Name in reports, without the count a flag may carry.
    pub fn name(&self) -> &'static str {
        match self {
            FrameFlag::LaserOff => "laser_off",
            FrameFlag::NoStartChannel => "no_start_channel",
            FrameFlag::NoStartPulse => "no_start_pulse",
            FrameFlag::StartTimingFallback => "start_timing_fallback",
            FrameFlag::NoBaselineGate => "no_baseline_gate",
            FrameFlag::NoInterferenceLearned => "no_interference_learned",
            FrameFlag::InterferenceCancelled => "interference_cancelled",
            FrameFlag::PartialAverage => "partial_average",
            FrameFlag::Nonstationary => "nonstationary",
            FrameFlag::LaserOffInGroup => "laser_off_in_group",
            FrameFlag::NonFiniteSamples(_) => "non_finite_samples",
            FrameFlag::NoiseGateSmall => "noise_gate_small",
            FrameFlag::NoNoiseEstimate => "no_noise_estimate",
            FrameFlag::ZeroNoise => "zero_noise",
            FrameFlag::NonGaussianNoise => "non_gaussian_noise",
            FrameFlag::NoiseGateContaminated => "noise_gate_contaminated",
            FrameFlag::WhitenWarmingUp => "whiten_warming_up",
            FrameFlag::EmpiricalThreshold => "empirical_threshold",
            FrameFlag::EmpiricalThresholdWarmingUp => "empirical_threshold_warming_up",
            FrameFlag::FalseAlarmExcess => "false_alarm_excess",
            FrameFlag::InterferenceEvents(_) => "interference_events",
        }
    }
}

impl std::fmt::Display for FrameFlag {
    /// The flag as reports spell it (`non_finite_samples:3`).
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FrameFlag::NonFiniteSamples(n) | FrameFlag::InterferenceEvents(n) => write!(f, "{}:{n}", self.name()),
            _ => f.write_str(self.name()),
        }
    }
}

impl PartialEq<str> for FrameFlag {
    /// Compares with the flag as reports spell it.
    fn eq(&self, other: &str) -> bool {
        match self {
            FrameFlag::NonFiniteSamples(_) | FrameFlag::InterferenceEvents(_) => self.to_string() == other,
            _ => self.name() == other,
        }
    }
}

impl PartialEq<&str> for FrameFlag {
    fn eq(&self, other: &&str) -> bool {
        self == *other
    }
}

impl Serialize for FrameFlag {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match self {
            FrameFlag::NonFiniteSamples(_) | FrameFlag::InterferenceEvents(_) => serializer.collect_str(self),
            _ => serializer.serialize_str(self.name()),
        }
    }
}

/// Output for one processed frame or averaged group (JSON contract).
#[derive(Debug, Default, PartialEq, Serialize)]
pub struct Report {
    /// Sensor id.
    pub sensor: String,
    /// First sequence number in the group.
    pub seq_first: u64,
    /// Last sequence number in the group.
    pub seq_last: u64,
    /// Frames averaged into this report.
    pub frames_averaged: u32,
    /// Trigger time of the first frame, seconds.
    pub time_s: f64,
    /// Pipeline stages that ran, in order (each stage's `name()`).
    pub stages: Vec<&'static str>,
    /// Noise model used for detection.
    pub noise: NoiseSummary,
    /// Detector and threshold.
    pub detector: DetectorSummary,
    /// Empirical false alarms in the noise gate.
    pub false_alarm: FalseAlarmStats,
    /// Returns, nearest first.
    pub returns: Vec<Return>,
    /// Time reference (start pulse instant, or trigger + offset) relative to the trigger, seconds.
    pub t_start_s: f64,
    /// One-sigma uncertainty of `t_start_s`, seconds (0 when the trigger is the reference).
    pub t_start_sigma_s: f64,
    /// Frame-level flags ("no_start_pulse", "laser_off", "noise_gate_small", ...),
    /// in the order the stages raised them.
    pub flags: Vec<FrameFlag>,
    /// Averaged reports: realised SNR gain of the average, dB: the noise-gate
    /// sigma of the single frames (rms) over that of the averaged frame, for a
    /// return that adds coherently (aligned, stationary). Absent without averaging.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub snr_gain_db: Option<f64>,
}

impl Clone for Report {
    fn clone(&self) -> Report {
        let mut r = Report::default();
        r.clone_from(self);
        r
    }

    /// Field by field, reusing the storage of `self`'s strings and lists.
    fn clone_from(&mut self, source: &Report) {
        let Report {
            sensor,
            seq_first,
            seq_last,
            frames_averaged,
            time_s,
            stages,
            noise,
            detector,
            false_alarm,
            returns,
            t_start_s,
            t_start_sigma_s,
            flags,
            snr_gain_db,
        } = self;
        sensor.clone_from(&source.sensor);
        *seq_first = source.seq_first;
        *seq_last = source.seq_last;
        *frames_averaged = source.frames_averaged;
        *time_s = source.time_s;
        stages.clone_from(&source.stages);
        *noise = source.noise;
        detector.clone_from(&source.detector);
        *false_alarm = source.false_alarm;
        returns.clone_from(&source.returns);
        *t_start_s = source.t_start_s;
        *t_start_sigma_s = source.t_start_sigma_s;
        flags.clone_from(&source.flags);
        *snr_gain_db = source.snr_gain_db;
    }
}

impl Report {
    /// Empties the report for reuse, keeping the capacity of its lists and
    /// strings (a recycled report costs no allocation).
    pub fn reset(&mut self) {
        let Report {
            sensor,
            seq_first,
            seq_last,
            frames_averaged,
            time_s,
            stages,
            noise,
            detector,
            false_alarm,
            returns,
            t_start_s,
            t_start_sigma_s,
            flags,
            snr_gain_db,
        } = self;
        sensor.clear();
        stages.clear();
        returns.clear();
        flags.clear();
        *seq_first = 0;
        *seq_last = 0;
        *frames_averaged = 0;
        *time_s = 0.0;
        *noise = NoiseSummary::default();
        *detector = DetectorSummary::default();
        *false_alarm = FalseAlarmStats::default();
        *t_start_s = 0.0;
        *t_start_sigma_s = 0.0;
        *snr_gain_db = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn i16_decode_is_the_scalar_formula_bit_for_bit() {
        let codes: Vec<i16> = (0..1037).map(|i| ((i * 7919) % 65536) as u16 as i16).collect();
        for (g, o) in [(1.0 / 4096.0, 0.0), (-3.1e-4, 0.0371), (0.7, -12.5)] {
            let mut paths: Vec<fn(&[i16], f64, f64, &mut Vec<f64>)> = vec![decode_i16, decode_i16_body];
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: AVX2 checked just above.
                paths.push(|c, g, o, out| unsafe { decode_i16_avx2(c, g, o, out) });
            }
            for decode in paths {
                let mut out = vec![42.0];
                decode(&codes, g, o, &mut out);
                assert_eq!(out.len(), 1 + codes.len());
                assert_eq!(out[0], 42.0);
                for (v, &c) in out[1..].iter().zip(&codes) {
                    assert_eq!(v.to_bits(), (c as f64 * g + o).to_bits());
                }
            }
        }
    }

    #[test]
    fn channel_keys_match_vendor_spellings() {
        for name in ["CH2", "Ch2", "C2", "2", "channel 2", " chan_02 ", "ch-2"] {
            assert_eq!(channel_key(name), "2", "{name:?}");
        }
        assert_eq!(channel_key(" Stop "), "stop");
        assert_eq!(channel_key("Coax"), "coax");
        assert_eq!(channel_key("C000"), "");
        let mut key = String::from("left over");
        channel_key_into("Channel 7", &mut key);
        assert_eq!(key, "7");
    }

    #[test]
    fn flags_serialise_as_their_names_in_report_order() {
        let mut f = ReturnFlags::default();
        f.insert(ReturnFlag::ShapeMismatch);
        f.insert(ReturnFlag::FrameEdge);
        f.insert(ReturnFlag::Weak);
        assert_eq!(serde_json::to_string(&f).unwrap(), r#"["frame_edge","weak","shape_mismatch"]"#);
        assert_eq!(f.len(), 3);
        assert!(f.contains(ReturnFlag::Weak) && !f.contains(ReturnFlag::Saturated));
        let frame = vec![FrameFlag::LaserOff, FrameFlag::NonFiniteSamples(3), FrameFlag::ZeroNoise];
        assert_eq!(serde_json::to_string(&frame).unwrap(), r#"["laser_off","non_finite_samples:3","zero_noise"]"#);
        assert!(frame[1] == "non_finite_samples:3" && frame[2] == "zero_noise");
        for (i, a) in ReturnFlag::ALL.iter().enumerate() {
            assert!(ReturnFlag::ALL[i + 1..].iter().all(|b| a.name() != b.name()));
        }
    }

    #[test]
    fn a_reset_report_equals_a_new_one() {
        let mut r = Report {
            sensor: "s".into(),
            seq_first: 3,
            stages: vec!["validate"],
            returns: vec![Return::default()],
            flags: vec![FrameFlag::LaserOff],
            snr_gain_db: Some(1.0),
            ..Report::default()
        };
        r.reset();
        assert_eq!(r, Report::default());
    }
}
