//! A starting scene measured from a capture (`tofwave scene --from-capture`).
//!
//! Everything a scene says about the data is read off the frames: the
//! sampling period and record length, which channel is the start and which
//! the stop, the noise (mean and a robust sigma from samples away from every
//! pulse), the start and return pulses' 10–90 % rise time and FWHM (median
//! over the frames of each frame's strongest pulse), a range gate around
//! the returns seen and a noise-gate guard that keeps the pulses' tails —
//! undershoot and ringing included — out of the noise gates. The result is
//! the default scene's commented TOML with those fields replaced, each with
//! a comment saying what it was measured from; it validates with
//! [`Scene::from_toml_str`].
//!
//! Pulse times and shapes are read on the samples interpolated with a cubic
//! (Catmull–Rom) between them: a fast pulse has only a few samples on its
//! edge, and straight lines between them would bend the 10 % and 90 %
//! points inwards.

use std::path::PathBuf;

use super::{CaptureError, ReadOptions};
use crate::detect::gates::GatePlacer;
use crate::detect::noise_model::NoiseFitter;
use crate::frame::{channel_key, ChannelRole, Frame};
use crate::math::quantised::{grid_step, quantised_sigma};
use crate::math::select::{mad_sigma, median};
use crate::scene::{PulseConfig, PulseModel, Scene, SceneError, DEFAULT_PROCESSING_TOML};

/// At most this many frames are measured (the first ones): enough for
/// medians and noise statistics, and memory stays bounded on long recordings.
pub const MAX_FRAMES: usize = 1000;

/// A frame's strongest excursion must reach this many noise sigmas to count
/// as a pulse whose shape is measured (20 dB: the 10 % point then sits 2
/// sigma above the noise).
pub const MIN_PULSE_SIGMA: f64 = 10.0;

/// A sample this many sigmas from the baseline belongs to a pulse, not to
/// the noise (Gaussian noise reaches it once in 3.5 million samples).
const PULSE_SIGMA: f64 = 5.0;

/// A pulse ends (and begins) where this many samples in a row lie within
/// [`QUIET_SIGMA`] sigmas of the baseline.
const QUIET_RUN: usize = 4;

/// See [`QUIET_RUN`].
const QUIET_SIGMA: f64 = 3.0;

/// Samples kept out of the noise on each side of a pulse's extent.
const PULSE_PAD: usize = 2;

/// Why no scene could be measured. Every message names the capture.
#[derive(Debug, thiserror::Error)]
pub enum MeasureError {
    /// The capture could not be read.
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// No frames, or frames without samples.
    #[error("{origin}: no frames with samples to measure")]
    NoFrames {
        /// The capture(s).
        origin: String,
    },
    /// Frames disagree about the sampling period.
    #[error("{origin}: frames have different sample intervals ({first_s:e} s and {other_s:e} s); measure them separately")]
    MixedIntervals {
        /// The capture(s).
        origin: String,
        /// The first frame's interval, s.
        first_s: f64,
        /// A later frame's, s.
        other_s: f64,
    },
    /// No channel holds a pulse strong enough to measure.
    #[error(
        "{origin}: no pulse to measure in {frames} frame(s): the largest excursion above the noise mean is \
         {best_sigma:.1} noise sigmas (channel {channel}; at least {MIN_PULSE_SIGMA} needed){negative}"
    )]
    NoPulse {
        /// The capture(s).
        origin: String,
        /// Frames looked at.
        frames: usize,
        /// The channel with the largest excursion.
        channel: String,
        /// That excursion in noise sigmas.
        best_sigma: f64,
        /// A hint when the pulses go negative.
        negative: String,
    },
    /// The pulses fill the record: no samples hold only noise.
    #[error("{origin}: channel {channel}: no samples away from the pulses to measure the noise on")]
    NoNoise {
        /// The capture(s).
        origin: String,
        /// The channel.
        channel: String,
    },
    /// The measured values do not make a valid scene (a bug, or a pulse
    /// shape no scene model describes).
    #[error("{origin}: the measured scene is invalid: {cause}")]
    Scene {
        /// The capture(s).
        origin: String,
        /// What the scene check said.
        cause: SceneError,
    },
}

/// One pulse channel, measured.
#[derive(Debug, Clone, PartialEq)]
pub struct PulseChannel {
    /// The channel's name as the capture spells it.
    pub name: String,
    /// Frames whose strongest pulse reached [`MIN_PULSE_SIGMA`].
    pub pulses: usize,
    /// Noise mean of the samples away from every pulse, V.
    pub noise_mean_v: f64,
    /// Robust noise sigma of those samples (1.4826·MAD, or for quantised
    /// samples the probit fit of `math::quantised`), V.
    pub noise_sigma_v: f64,
    /// Plain standard deviation of the same samples, V.
    pub noise_plain_sigma_v: f64,
    /// Samples the noise was measured on.
    pub noise_samples: u64,
    /// Step of the grid the samples lie on (scope codes), V; 0 when continuous.
    pub quantisation_step_v: f64,
    /// Median peak amplitude above the noise mean, V.
    pub amplitude_v: f64,
    /// Smallest and largest peak amplitude, V.
    pub amplitude_range_v: (f64, f64),
    /// Median 10–90 % rise time, s.
    pub rise_time_s: f64,
    /// Smallest and largest, s.
    pub rise_time_range_s: (f64, f64),
    /// Median full width at half maximum, s.
    pub fwhm_s: f64,
    /// Smallest and largest, s.
    pub fwhm_range_s: (f64, f64),
    /// Median deepest value after the peak, as a fraction of the amplitude
    /// (negative: an undershoot below the noise mean).
    pub undershoot_fraction: f64,
    /// Largest time from the peak to where the pulse is back in the noise, s.
    pub tail_after_peak_s: f64,
    /// Largest time from where the pulse leaves the noise to its peak, s.
    pub onset_before_peak_s: f64,
    /// Per measured frame: (frame index, 50 % leading-edge time relative to the trigger, s).
    pub half_rise_times_s: Vec<(usize, f64)>,
    /// Per measured frame: (frame index, peak time relative to the trigger, s).
    pub peak_times_s: Vec<(usize, f64)>,
    /// Per frame holding pulses: (frame index, where the earliest pulse
    /// leaves the noise, where the latest is back in it), relative to the
    /// trigger, s. Every pulse counts, not only the strongest: the range
    /// gate must hold them all and the noise gates none.
    pub activity_s: Vec<(usize, f64, f64)>,
}

/// Noise gates of the measured scene, checked on the frames.
#[derive(Debug, Clone, PartialEq)]
pub struct GateCheck {
    /// Fewest noise-gate samples in a frame.
    pub min_samples: usize,
    /// Most noise-gate samples in a frame.
    pub max_samples: usize,
    /// Frames whose noise gates overlap a pulse's extent (0 when the gates hold only noise).
    pub frames_touching_pulses: usize,
    /// Frames whose gate noise the noise model calls contaminated.
    pub frames_contaminated: usize,
}

/// What [`measure`] read off a capture.
#[derive(Debug, Clone, PartialEq)]
pub struct CaptureMeasurement {
    /// The capture(s), as given.
    pub origin: String,
    /// Frames in the capture (all of them, measured or not).
    pub frames_total: usize,
    /// Frames measured (the first [`MAX_FRAMES`]).
    pub frames_measured: usize,
    /// Sampling period, s.
    pub sample_interval_s: f64,
    /// Samples per channel when every frame has the same number, else 0.
    pub samples_per_frame: usize,
    /// Record start relative to the trigger (first frame), s.
    pub first_sample_offset_s: f64,
    /// Channel names of the first frame, in the capture's order.
    pub channel_names: Vec<String>,
    /// The return (stop) channel.
    pub stop: PulseChannel,
    /// The start channel, when the capture has one with a pulse in it.
    pub start: Option<PulseChannel>,
    /// How the channels were assigned, one line each.
    pub channel_notes: Vec<String>,
    /// Times of flight of the strongest return (stop 50 % point minus the
    /// start's, or minus the trigger), smallest and largest, s.
    pub tof_range_s: (f64, f64),
    /// Where any pulse on the stop channel was seen, from the same
    /// reference: the earliest onset and the latest end of a tail, s.
    pub activity_range_s: (f64, f64),
    /// The range gate written, m.
    pub range_gate_m: (f64, f64),
    /// Noise-gate guard written, s.
    pub guard_s: f64,
    /// Noise gates used (before the reference, beyond the range gate).
    pub gates_used: (bool, bool),
    /// The gates checked on the frames.
    pub gates: GateCheck,
    /// Leading-edge level written, V above the noise mean.
    pub leading_edge_v: f64,
}

/// Reads `paths` (files or directories) and measures them; see [`measure`].
pub fn measure_paths(paths: &[PathBuf], opts: &ReadOptions) -> Result<CaptureMeasurement, MeasureError> {
    let origin = paths.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ");
    let mut frames = Vec::new();
    let mut total = 0;
    for f in super::frames(paths, opts)? {
        let f = f?;
        total += 1;
        if frames.len() < MAX_FRAMES {
            frames.push(f);
        }
    }
    let mut m = measure(&frames, &origin)?;
    m.frames_total = total;
    Ok(m)
}

/// Measures a starting scene from `frames` (at most the first [`MAX_FRAMES`]
/// are used); `origin` names the capture in errors and in the scene's comments.
pub fn measure(frames: &[Frame], origin: &str) -> Result<CaptureMeasurement, MeasureError> {
    let frames = &frames[..frames.len().min(MAX_FRAMES)];
    let first = frames
        .iter()
        .find(|f| !f.is_empty())
        .ok_or_else(|| MeasureError::NoFrames { origin: origin.to_string() })?;
    let dt = first.sample_interval_s;
    if let Some(f) = frames.iter().find(|f| (f.sample_interval_s - dt).abs() > 1e-6 * dt) {
        return Err(MeasureError::MixedIntervals { origin: origin.to_string(), first_s: dt, other_s: f.sample_interval_s });
    }
    let channel_names: Vec<String> = first.channels.iter().map(|c| c.name.clone()).collect();
    let lengths: Vec<usize> = frames.iter().map(|f| f.len()).collect();
    let samples_per_frame = if lengths.iter().all(|&n| n == lengths[0]) { lengths[0] } else { 0 };

    // Each channel: its pulses and noise.
    let mut measured: Vec<Result<PulseChannel, ChannelMiss>> =
        channel_names.iter().map(|name| measure_channel(frames, name)).collect();
    let (stop_i, start_i, channel_notes) = assign_channels(first, &channel_names, &measured, frames.len())
        .map_err(|miss| no_pulse(origin, frames.len(), &miss))?;
    let stop = std::mem::replace(&mut measured[stop_i], Err(ChannelMiss::default()))
        .map_err(|miss| no_pulse(origin, frames.len(), &miss))?;
    let start = match start_i {
        Some(i) => std::mem::replace(&mut measured[i], Err(ChannelMiss::default())).ok(),
        None => None,
    };
    if stop.noise_samples == 0 {
        return Err(MeasureError::NoNoise { origin: origin.to_string(), channel: stop.name.clone() });
    }

    // Times of flight of the strongest return: from the start pulse's 50 %
    // point when there is one, else from the trigger (reference offset 0).
    let t_ref = |frame: usize| -> Option<f64> {
        match &start {
            Some(s) => s.half_rise_times_s.iter().find(|(i, _)| *i == frame).map(|p| p.1),
            None => Some(0.0),
        }
    };
    let tofs: Vec<f64> = stop.half_rise_times_s.iter().filter_map(|&(i, t)| t_ref(i).map(|r| t - r)).collect();
    let (tof_min, tof_max) = min_max(&tofs).unwrap_or((0.0, 0.0));
    let (starts, ends): (Vec<f64>, Vec<f64>) =
        stop.activity_s.iter().filter_map(|&(i, a, e)| t_ref(i).map(|r| (a - r, e - r))).unzip();
    let activity = (
        min_max(&starts).map_or(tof_min, |m| m.0.min(tof_min)),
        min_max(&ends).map_or(tof_max, |m| m.1.max(tof_max)),
    );

    let mut m = CaptureMeasurement {
        origin: origin.to_string(),
        frames_total: frames.len(),
        frames_measured: frames.len(),
        sample_interval_s: dt,
        samples_per_frame,
        first_sample_offset_s: first.first_sample_offset_s,
        channel_names,
        leading_edge_v: leading_edge_level(&stop),
        stop,
        start,
        channel_notes,
        tof_range_s: (tof_min, tof_max),
        activity_range_s: activity,
        range_gate_m: (0.0, 0.0),
        guard_s: 0.0,
        gates_used: (true, true),
        gates: GateCheck { min_samples: 0, max_samples: 0, frames_touching_pulses: 0, frames_contaminated: 0 },
    };
    place_gates(&mut m, frames)?;
    Ok(m)
}

/// Why a channel gave no measurement: its best excursion.
#[derive(Debug, Clone, Default, PartialEq)]
struct ChannelMiss {
    channel: String,
    best_sigma: f64,
    negative_sigma: f64,
}

fn no_pulse(origin: &str, frames: usize, miss: &ChannelMiss) -> MeasureError {
    let negative = if miss.negative_sigma >= MIN_PULSE_SIGMA && miss.negative_sigma > 2.0 * miss.best_sigma {
        format!(
            "; the largest excursion below it is {:.1} sigmas: tofwave expects positive-going pulses (invert the channel)",
            miss.negative_sigma
        )
    } else {
        String::new()
    };
    MeasureError::NoPulse {
        origin: origin.to_string(),
        frames,
        channel: miss.channel.clone(),
        best_sigma: miss.best_sigma,
        negative,
    }
}

/// Start and stop among the measured channels, and a note on each choice.
/// Roles the capture states win; otherwise the start is the channel whose
/// pulse comes first (the transmitted pulse precedes its returns) and the
/// stop the next. With one pulsed channel, it is the stop channel.
fn assign_channels(
    first: &Frame,
    names: &[String],
    measured: &[Result<PulseChannel, ChannelMiss>],
    frames: usize,
) -> Result<(usize, Option<usize>, Vec<String>), ChannelMiss> {
    let pulsed: Vec<usize> = (0..names.len()).filter(|&i| measured[i].as_ref().is_ok_and(|c| 2 * c.pulses >= frames)).collect();
    let mut notes = Vec::new();
    let by_role = |role: ChannelRole| first.channels.iter().position(|c| c.role == role);
    let median_peak = |i: usize| -> f64 {
        let mut t: Vec<f64> = measured[i].as_ref().map(|c| c.peak_times_s.iter().map(|p| p.1).collect()).unwrap_or_default();
        median(&mut t).unwrap_or(f64::INFINITY)
    };
    if let Some(s) = by_role(ChannelRole::Stop).filter(|s| pulsed.contains(s)) {
        let start = by_role(ChannelRole::Start).filter(|i| pulsed.contains(i));
        notes.push(format!("{} is the stop channel (the capture says so)", names[s]));
        if let Some(i) = start {
            notes.push(format!("{} is the start channel (the capture says so)", names[i]));
        }
        return Ok((s, start, notes));
    }
    match pulsed.len() {
        0 => {
            // Report the channel that came closest.
            let best = measured
                .iter()
                .map(|m| match m {
                    Ok(c) => ChannelMiss { channel: c.name.clone(), best_sigma: c.amplitude_v / c.noise_sigma_v, negative_sigma: 0.0 },
                    Err(miss) => miss.clone(),
                })
                .max_by(|a, b| a.best_sigma.total_cmp(&b.best_sigma))
                .unwrap_or_default();
            Err(best)
        }
        1 => {
            let s = pulsed[0];
            if names.len() == 1 {
                notes.push(format!(
                    "one channel ({}): it is the stop channel, and times of flight are measured from the trigger \
                     (channels.reference_offset_s); no start channel",
                    names[s]
                ));
            } else {
                let others: Vec<&str> = names.iter().enumerate().filter(|(i, _)| *i != s).map(|(_, n)| n.as_str()).collect();
                notes.push(format!(
                    "{} is the only channel with a pulse in most frames: it is the stop channel, timed from the \
                     trigger; {} hold(s) no pulse and is not used as the start",
                    names[s],
                    others.join(", ")
                ));
            }
            Ok((s, None, notes))
        }
        _ => {
            let mut order = pulsed.clone();
            order.sort_by(|&a, &b| median_peak(a).total_cmp(&median_peak(b)).then(a.cmp(&b)));
            let (start, stop) = (order[0], order[1]);
            notes.push(format!(
                "{} is the start channel: its pulse comes first (median peak {:.2} ns after the trigger)",
                names[start],
                median_peak(start) * 1e9
            ));
            notes.push(format!(
                "{} is the stop channel: its strongest pulse follows (median peak {:.2} ns after the trigger)",
                names[stop],
                median_peak(stop) * 1e9
            ));
            for &o in &order[2..] {
                notes.push(format!("{} also holds pulses; it is not used", names[o]));
            }
            Ok((stop, Some(start), notes))
        }
    }
}

/// Per-frame facts about the strongest pulse on one channel.
#[derive(Debug, Clone, Copy)]
struct Shot {
    frame: usize,
    amplitude_v: f64,
    rise_s: f64,
    fwhm_s: f64,
    half_rise_t_s: f64,
    peak_t_s: f64,
    undershoot: f64,
    tail_s: f64,
    onset_s: f64,
}

fn measure_channel(frames: &[Frame], name: &str) -> Result<PulseChannel, ChannelMiss> {
    let key = channel_key(name);
    let mut fitter = NoiseFitter::default();
    let mut noise: Vec<f64> = Vec::new();
    let mut shots: Vec<Shot> = Vec::new();
    let mut activity: Vec<(usize, f64, f64)> = Vec::new();
    let (mut best_sigma, mut negative_sigma) = (0.0f64, 0.0f64);
    let mut x = Vec::new();
    let mut scratch = Vec::new();
    let mut levels = Vec::new();
    for (fi, frame) in frames.iter().enumerate() {
        let Some(ch) = frame.channels.iter().find(|c| channel_key(&c.name) == key) else {
            continue;
        };
        ch.volts_into(&mut x);
        if x.iter().any(|v| !v.is_finite()) || x.len() < 8 {
            continue;
        }
        // A first look at the whole frame: pulses are a small part of it,
        // and a robust sigma does not see them.
        scratch.clone_from(&x);
        let base = median(&mut scratch).unwrap_or(0.0);
        let sigma = robust_sigma(&mut scratch, &mut levels);
        if !(sigma > 0.0) {
            continue;
        }
        let mask = pulse_mask(&x, base, sigma);
        let frame_noise: Vec<f64> = x.iter().zip(&mask).filter(|(_, m)| !**m).map(|(v, _)| *v).collect();
        noise.extend_from_slice(&frame_noise);
        // The frame's own baseline and sigma, from its noise only.
        let (b, s) = if frame_noise.len() >= 8 {
            let mean = frame_noise.iter().sum::<f64>() / frame_noise.len() as f64;
            let mut fnoise = frame_noise.clone();
            (mean, robust_sigma(&mut fnoise, &mut levels).max(f64::MIN_POSITIVE))
        } else {
            (base, sigma)
        };
        if let Some((a, e)) = pulse_span(&x, &mask, b, s) {
            activity.push((fi, frame.sample_time_s(a as f64), frame.sample_time_s(e as f64)));
        }
        let (k, top) = x.iter().enumerate().fold((0, f64::NEG_INFINITY), |a, (i, &v)| if v > a.1 { (i, v) } else { a });
        let bottom = x.iter().copied().fold(f64::INFINITY, f64::min);
        best_sigma = best_sigma.max((top - b) / s);
        negative_sigma = negative_sigma.max((b - bottom) / s);
        if (top - b) / s < MIN_PULSE_SIGMA {
            continue;
        }
        if let Some(shot) = measure_pulse(&x, k, b, s, frame, fi) {
            shots.push(shot);
        }
    }
    if shots.is_empty() {
        return Err(ChannelMiss { channel: name.to_string(), best_sigma, negative_sigma });
    }
    let summary = fitter.fit(&[&noise], 0.001);
    let step = if summary.sigma_v > 0.0 { grid_step(&noise, summary.sigma_v / 256.0).unwrap_or(0.0) } else { 0.0 };
    let pick = |f: fn(&Shot) -> f64| -> Vec<f64> { shots.iter().map(f).collect() };
    let med = |mut v: Vec<f64>| median(&mut v).unwrap_or(0.0);
    let range = |v: Vec<f64>| min_max(&v).unwrap_or((0.0, 0.0));
    Ok(PulseChannel {
        name: frames
            .iter()
            .flat_map(|f| f.channels.iter())
            .find(|c| channel_key(&c.name) == key)
            .map_or_else(|| name.to_string(), |c| c.name.clone()),
        pulses: shots.len(),
        noise_mean_v: summary.mean_v,
        noise_sigma_v: summary.robust_sigma_v,
        noise_plain_sigma_v: summary.sigma_v,
        noise_samples: summary.samples,
        quantisation_step_v: step,
        amplitude_v: med(pick(|s| s.amplitude_v)),
        amplitude_range_v: range(pick(|s| s.amplitude_v)),
        rise_time_s: med(pick(|s| s.rise_s)),
        rise_time_range_s: range(pick(|s| s.rise_s)),
        fwhm_s: med(pick(|s| s.fwhm_s)),
        fwhm_range_s: range(pick(|s| s.fwhm_s)),
        undershoot_fraction: med(pick(|s| s.undershoot)),
        tail_after_peak_s: pick(|s| s.tail_s).into_iter().fold(0.0, f64::max),
        onset_before_peak_s: pick(|s| s.onset_s).into_iter().fold(0.0, f64::max),
        half_rise_times_s: shots.iter().map(|s| (s.frame, s.half_rise_t_s)).collect(),
        peak_times_s: shots.iter().map(|s| (s.frame, s.peak_t_s)).collect(),
        activity_s: activity,
    })
}

/// Robust sigma of `x` (reordered): the quantised estimate for scope codes, else the MAD's.
fn robust_sigma(x: &mut [f64], levels: &mut Vec<u32>) -> f64 {
    let n = x.len() as f64;
    let mean = x.iter().sum::<f64>() / n.max(1.0);
    let plain = (x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt();
    if plain > 0.0
        && let Some(r) = grid_step(x, plain / 256.0).and_then(|q| quantised_sigma(x, q, levels))
    {
        return r;
    }
    mad_sigma(x)
}

/// Samples that belong to a pulse: every excursion beyond [`PULSE_SIGMA`],
/// extended to where the signal is back in the noise, plus a pad.
fn pulse_mask(x: &[f64], base: f64, sigma: f64) -> Vec<bool> {
    let n = x.len();
    let mut mask = vec![false; n];
    let mut i = 0;
    while i < n {
        if (x[i] - base).abs() > PULSE_SIGMA * sigma {
            let (a, e) = extent(x, i, base, sigma);
            let (a, e) = (a.saturating_sub(PULSE_PAD), (e + PULSE_PAD).min(n - 1));
            mask[a..=e].iter_mut().for_each(|m| *m = true);
            i = e + 1;
        } else {
            i += 1;
        }
    }
    mask
}

/// First and last sample of the pulse regions of `mask` that hold a
/// positive excursion of [`PULSE_SIGMA`] (a return, not only its undershoot).
fn pulse_span(x: &[f64], mask: &[bool], base: f64, sigma: f64) -> Option<(usize, usize)> {
    let mut span: Option<(usize, usize)> = None;
    let mut i = 0;
    while i < mask.len() {
        if !mask[i] {
            i += 1;
            continue;
        }
        let a = i;
        while i < mask.len() && mask[i] {
            i += 1;
        }
        let e = i - 1;
        if x[a..=e].iter().any(|&v| v - base > PULSE_SIGMA * sigma) {
            span = Some(span.map_or((a, e), |(s0, e0)| (s0.min(a), e0.max(e))));
        }
    }
    span
}

/// First and last sample of the pulse around `k`: walking out from it, the
/// pulse ends where [`QUIET_RUN`] samples in a row are within
/// [`QUIET_SIGMA`] sigmas of the baseline (undershoot and ringing count as pulse).
fn extent(x: &[f64], k: usize, base: f64, sigma: f64) -> (usize, usize) {
    let quiet = |v: f64| (v - base).abs() <= QUIET_SIGMA * sigma;
    let (mut first, mut run) = (k, 0);
    for i in (0..k).rev() {
        if quiet(x[i]) {
            run += 1;
            if run >= QUIET_RUN {
                break;
            }
        } else {
            run = 0;
            first = i;
        }
    }
    let (mut last, mut run) = (k, 0);
    for (i, &v) in x.iter().enumerate().skip(k + 1) {
        if quiet(v) {
            run += 1;
            if run >= QUIET_RUN {
                break;
            }
        } else {
            run = 0;
            last = i;
        }
    }
    (first, last)
}

/// Catmull–Rom cubic through the samples, at fractional index `t` (edges repeat).
fn cubic(x: &[f64], t: f64) -> f64 {
    let n = x.len();
    let t = t.clamp(0.0, (n - 1) as f64);
    let k = (t.floor() as usize).min(n - 2);
    let s = t - k as f64;
    let at = |i: isize| x[i.clamp(0, n as isize - 1) as usize];
    let (p0, p1, p2, p3) = (at(k as isize - 1), at(k as isize), at(k as isize + 1), at(k as isize + 2));
    0.5 * (2.0 * p1
        + (p2 - p0) * s
        + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * s * s
        + (3.0 * (p1 - p2) + p3 - p0) * s * s * s)
}

/// Where the cubic crosses `level` between `a` and `b` (which lie on
/// opposite sides of it), by bisection.
fn bisect(x: &[f64], mut a: f64, mut b: f64, level: f64) -> f64 {
    let a_below = cubic(x, a) < level;
    for _ in 0..50 {
        let m = 0.5 * (a + b);
        if (cubic(x, m) < level) == a_below {
            a = m;
        } else {
            b = m;
        }
    }
    0.5 * (a + b)
}

/// The leading-edge crossing of `level` nearest before `peak` (fractional
/// index, where the cubic is at or above `level`).
fn rising_crossing(x: &[f64], peak: f64, level: f64) -> Option<f64> {
    let mut j = peak.floor() as usize;
    while x[j] >= level {
        j = j.checked_sub(1)?;
    }
    let above = if j as f64 + 1.0 <= peak { j as f64 + 1.0 } else { peak };
    Some(bisect(x, j as f64, above, level))
}

/// The trailing-edge crossing of `level` nearest after `peak`.
fn falling_crossing(x: &[f64], peak: f64, level: f64) -> Option<f64> {
    let mut j = peak.ceil() as usize;
    while *x.get(j)? >= level {
        j += 1;
    }
    let above = if j as f64 - 1.0 >= peak { j as f64 - 1.0 } else { peak };
    Some(bisect(x, above, j as f64, level))
}

/// Rise, width and times of the pulse whose largest sample is `k`, on
/// baseline `b` with noise sigma `s`.
fn measure_pulse(x: &[f64], k: usize, b: f64, s: f64, frame: &Frame, fi: usize) -> Option<Shot> {
    let n = x.len();
    if k == 0 || k + 1 >= n {
        return None;
    }
    // The top between the neighbouring samples, on the cubic.
    let (peak, top) = (0..=128)
        .map(|i| k as f64 - 1.0 + i as f64 / 64.0)
        .map(|t| (t, cubic(x, t)))
        .fold((k as f64, x[k]), |a, p| if p.1 > a.1 { p } else { a });
    let amplitude = top - b;
    let level = |f: f64| b + f * amplitude;
    let r10 = rising_crossing(x, peak, level(0.1))?;
    let r50 = rising_crossing(x, peak, level(0.5))?;
    let r90 = rising_crossing(x, peak, level(0.9))?;
    let f50 = falling_crossing(x, peak, level(0.5))?;
    let (first, last) = extent(x, k, b, s);
    let dt = frame.sample_interval_s;
    let undershoot = x[k..=last].iter().copied().fold(f64::INFINITY, f64::min) - b;
    Some(Shot {
        frame: fi,
        amplitude_v: amplitude,
        rise_s: (r90 - r10) * dt,
        fwhm_s: (f50 - r50) * dt,
        half_rise_t_s: frame.sample_time_s(r50),
        peak_t_s: frame.sample_time_s(peak),
        undershoot: (undershoot / amplitude).min(0.0),
        tail_s: (last as f64 - peak).max(0.0) * dt,
        onset_s: (peak - first as f64).max(0.0) * dt,
    })
}

fn min_max(v: &[f64]) -> Option<(f64, f64)> {
    if v.is_empty() {
        return None;
    }
    Some(v.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| (a.min(x), b.max(x))))
}

/// A comparator level half way up the smallest strong pulse seen (at least
/// 5 noise sigmas), so that leading-edge timing crosses every return on its
/// steep part and never falls back.
fn leading_edge_level(stop: &PulseChannel) -> f64 {
    (0.5 * stop.amplitude_range_v.0).max(5.0 * stop.noise_sigma_v)
}

/// The return pulse as the scene describes it: a bigaussian of the measured
/// rise and FWHM (a Gaussian when the rise is too slow for one).
fn pulse_config(c: &PulseChannel) -> PulseConfig {
    let max_rise = c.fwhm_s * 1.686_922_421_262_926_4 / 1.177_410_022_515_474_6;
    let bigaussian = c.rise_time_s > 0.0 && c.rise_time_s < 0.98 * max_rise;
    PulseConfig {
        model: if bigaussian { PulseModel::Bigaussian } else { PulseModel::Gaussian },
        rise_time_s: if bigaussian { c.rise_time_s } else { 0.0 },
        fwhm_s: c.fwhm_s,
        table_step_s: 0.0,
        table_first_s: 0.0,
        table: Vec::new(),
    }
}

/// Chooses the range gate and the noise-gate guard, widening the guard
/// until no frame's noise gates touch a pulse (or the gates would vanish),
/// and records the check.
///
/// The range gate holds every pulse seen on the stop channel, from the
/// earliest onset to the latest end of a tail (a timing point lies between
/// them), one FWHM beyond each; the gates then keep the pulse support and a
/// FWHM more clear of it, so the guard starts at a few samples.
fn place_gates(m: &mut CaptureMeasurement, frames: &[Frame]) -> Result<(), MeasureError> {
    let c = crate::scene::C_VACUUM_M_PER_S / crate::scene::MediumConfig::default().refractive_index;
    let dt = m.sample_interval_s;
    let fwhm = m.stop.fwhm_s.max(dt);
    let (a, e) = m.activity_range_s;
    m.range_gate_m = (0.5 * c * (a - fwhm), 0.5 * c * (e + fwhm));
    let mut guard = round_up((PULSE_PAD as f64 + 1.0) * dt, dt);
    // The pulse masks, to check the gates against.
    let masks: Vec<Option<Vec<bool>>> = frames.iter().map(|f| frame_mask(f, &m.stop)).collect();
    let mut tries = 0;
    loop {
        m.guard_s = guard;
        m.gates = check_gates(m, frames, &masks)?;
        if m.gates.frames_touching_pulses == 0 || tries >= 8 {
            break;
        }
        // Some frame's pulse reaches further than the others' (a late
        // return, ringing): widen the guard by a FWHM at a time.
        guard = round_up(guard + fwhm, dt);
        tries += 1;
    }
    Ok(())
}

/// `x` rounded up to a multiple of a tenth of `step`, keeping three significant digits readable.
fn round_up(x: f64, step: f64) -> f64 {
    let unit = step / 10.0;
    (x / unit).ceil() * unit
}

/// The stop channel's pulse mask of one frame (None when the frame lacks the channel).
fn frame_mask(frame: &Frame, stop: &PulseChannel) -> Option<Vec<bool>> {
    let key = channel_key(&stop.name);
    let ch = frame.channels.iter().find(|c| channel_key(&c.name) == key)?;
    let x = ch.volts();
    Some(pulse_mask(&x, stop.noise_mean_v, stop.noise_sigma_v.max(f64::MIN_POSITIVE)))
}

/// The measured scene's noise gates on every frame: sizes, overlap with pulses, and the noise model's verdict.
fn check_gates(m: &mut CaptureMeasurement, frames: &[Frame], masks: &[Option<Vec<bool>>]) -> Result<GateCheck, MeasureError> {
    let scene = m.scene()?;
    let mut placer = GatePlacer::new(&scene);
    let mut fitter = NoiseFitter::default();
    let key = channel_key(&m.stop.name);
    let start_t: std::collections::HashMap<usize, f64> =
        m.start.as_ref().map(|s| s.half_rise_times_s.iter().copied().collect()).unwrap_or_default();
    let mut check = GateCheck { min_samples: usize::MAX, max_samples: 0, frames_touching_pulses: 0, frames_contaminated: 0 };
    let (mut any_pre, mut any_beyond) = (false, false);
    for (i, (frame, mask)) in frames.iter().zip(masks).enumerate() {
        let (Some(mask), Some(ch)) = (mask, frame.channels.iter().find(|c| channel_key(&c.name) == key)) else {
            continue;
        };
        let t_ref = if m.start.is_some() {
            match start_t.get(&i) {
                Some(&t) => t,
                None => continue,
            }
        } else {
            scene.channels.reference_offset_s
        };
        let g = placer.place(frame, mask.len(), t_ref);
        any_pre |= !g.pre.is_empty();
        any_beyond |= !g.beyond.is_empty();
        let samples = g.noise_samples();
        check.min_samples = check.min_samples.min(samples);
        check.max_samples = check.max_samples.max(samples);
        if g.pre.clone().chain(g.beyond.clone()).any(|k| mask[k]) {
            check.frames_touching_pulses += 1;
        }
        let x = ch.volts();
        let s = fitter.fit(&[&x[g.pre.clone()], &x[g.beyond.clone()]], scene.detector.normality_alpha);
        check.frames_contaminated += s.contaminated as usize;
    }
    if check.min_samples == usize::MAX {
        check.min_samples = 0;
    }
    // A gate that no frame reaches is switched off (at least one stays on).
    if any_pre || any_beyond {
        m.gates_used = (any_pre, any_beyond);
    }
    Ok(check)
}

/// A float as TOML: plain decimals for everyday magnitudes, else an exponent.
fn toml_float(x: f64) -> String {
    if x == 0.0 {
        return "0.0".to_string();
    }
    let a = x.abs();
    if (1e-3..1e5).contains(&a) {
        let decimals = (5 - a.log10().floor() as i32).clamp(1, 8) as usize;
        let s = format!("{x:.decimals$}");
        // Trim trailing zeros, keeping one decimal.
        let t = s.trim_end_matches('0');
        if t.ends_with('.') { format!("{t}0") } else { t.to_string() }
    } else {
        format!("{x:.4e}")
    }
}

/// Replaces `key = ...` in `[section]` (`""`: the top level) of the scene
/// text with `key = value`, the `comment` lines just above it.
fn set_key(text: &mut Vec<String>, section: &str, key: &str, value: &str, comment: &[String]) {
    let start = if section.is_empty() {
        0
    } else {
        let header = format!("[{section}]");
        match text.iter().position(|l| l.trim() == header) {
            Some(i) => i + 1,
            None => {
                text.push(String::new());
                text.push(header);
                text.len()
            }
        }
    };
    let end = text[start..].iter().position(|l| l.trim_start().starts_with('[')).map_or(text.len(), |i| start + i);
    let is_key = |l: &str| l.split('=').next().is_some_and(|k| k.trim() == key) && !l.trim_start().starts_with('#');
    let line = format!("{key} = {value}");
    let commented = comment.iter().map(|c| format!("# {c}"));
    match text[start..end].iter().position(|l| is_key(l)) {
        Some(i) => {
            text[start + i] = line;
            let at = start + i;
            text.splice(at..at, commented);
        }
        None => {
            // After the section's last line with content.
            let mut at = end;
            while at > start && text[at - 1].trim().is_empty() {
                at -= 1;
            }
            let mut lines: Vec<String> = commented.collect();
            lines.push(line);
            text.splice(at..at, lines);
        }
    }
}

fn ns(s: f64) -> String {
    format!("{:.2} ns", s * 1e9)
}

fn mv(v: f64) -> String {
    format!("{:.1} mV", v * 1e3)
}

impl PulseChannel {
    /// One line on the noise measurement.
    fn noise_line(&self) -> String {
        let step = if self.quantisation_step_v > 0.0 {
            format!(", on a grid of {} (scope codes)", mv(self.quantisation_step_v))
        } else {
            String::new()
        };
        format!(
            "noise on {}: mean {}, sigma {} (robust; plain {}), from {} samples away from every pulse{step}",
            self.name,
            mv(self.noise_mean_v),
            mv(self.noise_sigma_v),
            mv(self.noise_plain_sigma_v),
            self.noise_samples
        )
    }

    /// Comment lines and the pulse section's fields.
    fn pulse_lines(&self, what: &str) -> Vec<String> {
        let mut lines = vec![format!(
            "Measured on channel {} from the strongest {what} pulse of {} frames (median; smallest-largest):",
            self.name, self.pulses
        )];
        lines.push(format!(
            "amplitude {:.3} V ({:.3}-{:.3}), 10-90 % rise {} ({}-{}), FWHM {} ({}-{}).",
            self.amplitude_v,
            self.amplitude_range_v.0,
            self.amplitude_range_v.1,
            ns(self.rise_time_s),
            ns(self.rise_time_range_s.0),
            ns(self.rise_time_range_s.1),
            ns(self.fwhm_s),
            ns(self.fwhm_range_s.0),
            ns(self.fwhm_range_s.1)
        ));
        if self.undershoot_fraction < -0.05 {
            lines.push(format!(
                "The pulse undershoots to {:.0} % of its peak below the noise mean and is back in the noise {} after",
                -100.0 * self.undershoot_fraction,
                ns(self.tail_after_peak_s)
            ));
            lines.push(
                "its peak: no parametric model describes that; learn the shape with `tofwave template` (see the top).".to_string(),
            );
        }
        lines
    }
}

impl CaptureMeasurement {
    /// The measured scene as commented TOML: the embedded default scene's
    /// processing text (without the prototype's `[simulation]`) with the measured fields replaced, each preceded by a comment
    /// saying what it was measured from. It validates with `Scene::from_toml_str`.
    pub fn scene_toml(&self) -> String {
        let mut text: Vec<String> = DEFAULT_PROCESSING_TOML.lines().map(str::to_string).collect();
        // The default's opening paragraph describes the prototype: replace it.
        let para = text.iter().position(|l| l.trim().is_empty()).unwrap_or(0);
        let mut header = vec![
            format!("# tofwave scene measured by `tofwave scene --from-capture` from {}:", self.origin),
            format!(
                "# {} frames{}, {} samples per channel, sampled every {}; channels: {}.",
                self.frames_measured,
                if self.frames_total > self.frames_measured { format!(" (the first of {})", self.frames_total) } else { String::new() },
                if self.samples_per_frame > 0 { self.samples_per_frame.to_string() } else { "varying".to_string() },
                ns(self.sample_interval_s),
                self.channel_names.join(", ")
            ),
        ];
        header.extend(self.channel_notes.iter().map(|n| format!("# {n}.")));
        header.push(format!("# {}.", self.stop.noise_line()));
        if let Some(s) = &self.start {
            header.push(format!("# {}.", s.noise_line()));
        }
        header.push(format!(
            "# Noise gates: {}-{} samples per frame; they overlap a pulse in {} of {} frames, and the noise model",
            self.gates.min_samples, self.gates.max_samples, self.gates.frames_touching_pulses, self.frames_measured
        ));
        header.push(format!("# calls them contaminated in {} frames.", self.gates.frames_contaminated));
        header.push("# Every value marked \"measured\" below is a starting point: check it against your set-up.".to_string());
        header.push("# The return pulse is a bigaussian of the measured rise and FWHM; a measured shape fits".to_string());
        header.push("# better (and model-based timing needs it):".to_string());
        header.push(format!(
            "#   tofwave template --scene THIS.toml --input {} --out learned.toml",
            self.origin.split(", ").next().unwrap_or("CAPTURE")
        ));
        text.splice(0..para, header);

        let stem = self.origin.rsplit(['/', '\\']).next().unwrap_or(&self.origin);
        set_key(&mut text, "", "name", &format!("{:?}", format!("from-capture {stem}")), &[]);
        set_key(
            &mut text,
            "digitiser",
            "sample_interval_s",
            &toml_float(self.sample_interval_s),
            &[format!("measured: the capture's sampling period ({}).", ns(self.sample_interval_s))],
        );
        if self.samples_per_frame > 0 {
            set_key(
                &mut text,
                "digitiser",
                "samples_per_frame",
                &self.samples_per_frame.to_string(),
                &["measured: every frame of the capture has this many samples.".to_string()],
            );
        }
        let start_name = match &self.start {
            Some(s) => s.name.clone(),
            // Any name the capture does not have: the trigger is the reference.
            None => ["CH1", "CH2", "CH3"]
                .into_iter()
                .find(|n| !self.channel_names.iter().any(|c| channel_key(c) == channel_key(n)))
                .unwrap_or("start")
                .to_string(),
        };
        let start_comment = match &self.start {
            Some(_) => "measured: the channel whose pulse comes first.".to_string(),
            None => format!("measured: the capture has no start channel ({start_name} is not in it): times are taken from the trigger."),
        };
        set_key(&mut text, "channels", "start", &format!("{start_name:?}"), &[start_comment]);
        set_key(
            &mut text,
            "channels",
            "stop",
            &format!("{:?}", self.stop.name),
            &["measured: the channel holding the returns.".to_string()],
        );
        if let Some(s) = &self.start {
            let level = (0.25 * s.amplitude_range_v.0).max(6.0 * s.noise_sigma_v);
            set_key(
                &mut text,
                "channels",
                "start_min_amplitude_v",
                &toml_float(level),
                &[format!(
                    "measured: a quarter of the smallest start pulse ({:.3} V), at least 6 noise sigmas.",
                    s.amplitude_range_v.0
                )],
            );
        }
        let write_pulse = |text: &mut Vec<String>, section: &str, c: &PulseChannel, what: &str| {
            let p = pulse_config(c);
            let mut lines = c.pulse_lines(what);
            let model = match p.model {
                PulseModel::Gaussian => {
                    lines.push("The rise is too slow for a bigaussian of this FWHM: a Gaussian.".to_string());
                    "\"gaussian\""
                }
                _ => "\"bigaussian\"",
            };
            set_key(text, section, "model", model, &lines);
            if p.model == PulseModel::Bigaussian {
                set_key(text, section, "rise_time_s", &toml_float(p.rise_time_s), &["measured (median 10-90 % rise).".to_string()]);
            }
            set_key(text, section, "fwhm_s", &toml_float(p.fwhm_s), &["measured (median FWHM).".to_string()]);
        };
        write_pulse(&mut text, "return_pulse", &self.stop, "return");
        if let Some(s) = &self.start {
            write_pulse(&mut text, "start_pulse", s, "start");
        }
        let (t0, t1) = self.tof_range_s;
        let (a0, a1) = self.activity_range_s;
        let reference = if self.start.is_some() { "the start pulse's 50 % point" } else { "the trigger" };
        set_key(
            &mut text,
            "range_gate",
            "min_m",
            &toml_float(self.range_gate_m.0),
            &[
                format!("measured: pulses on {} were seen from {} to {} after {reference} (onset to the end", self.stop.name, ns(a0), ns(a1)),
                format!("of the tail; the strongest returns' 50 % points at {} to {}); the gate reaches one FWHM", ns(t0), ns(t1)),
                "beyond them. Widen it if returns can come from elsewhere; the noise gates shrink with it.".to_string(),
            ],
        );
        set_key(&mut text, "range_gate", "max_m", &toml_float(self.range_gate_m.1), &["measured (see min_m).".to_string()]);
        set_key(
            &mut text,
            "noise_gate",
            "guard_s",
            &toml_float(self.guard_s),
            &[
                format!(
                    "measured: with the range gate above, keeps every pulse's onset (up to {} before the peak) and",
                    ns(self.stop.onset_before_peak_s)
                ),
                format!(
                    "tail (up to {} after it, undershoot and ringing included) out of the noise gates.",
                    ns(self.stop.tail_after_peak_s)
                ),
            ],
        );
        if !self.gates_used.0 {
            set_key(&mut text, "noise_gate", "pre_trigger", "false", &["measured: the record holds no samples before the earliest return.".to_string()]);
        }
        if !self.gates_used.1 {
            set_key(&mut text, "noise_gate", "beyond_range", "false", &["measured: the record ends before any sample beyond the range gate.".to_string()]);
        }
        if self.gates.min_samples < 32 {
            set_key(
                &mut text,
                "noise_gate",
                "min_samples",
                &self.gates.min_samples.max(2).to_string(),
                &["measured: the smallest noise gate of the capture's frames.".to_string()],
            );
        }
        set_key(
            &mut text,
            "timing",
            "leading_edge_v",
            &toml_float(self.leading_edge_v),
            &["measured: half the smallest return's amplitude (at least 5 noise sigmas).".to_string()],
        );
        let mut out = text.join("\n");
        out.push('\n');
        out
    }

    /// The measured scene, parsed and validated.
    pub fn scene(&self) -> Result<Scene, MeasureError> {
        Scene::from_toml_str(&self.scene_toml(), &format!("scene measured from {}", self.origin))
            .map_err(|source| MeasureError::Scene { origin: self.origin.clone(), cause: source })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dsp::pulse::{Pulse, PulseShape};
    use crate::frame::{Channel, Samples};
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};

    /// Frames of `channels` (name, pulse peak time after the trigger, amplitude; 0: none),
    /// 8-bit-like codes of 4 mV, 3 mV noise, 1 ns sampling, 400 samples, trigger at sample 100.
    fn frames(channels: &[(&str, f64, f64)], pulse: &Pulse, n: u64) -> Vec<Frame> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let noise = Normal::new(0.0, 0.003).unwrap();
        (0..n)
            .map(|seq| Frame {
                sensor_id: "t".into(),
                sequence: seq,
                trigger_time_s: seq as f64,
                sample_interval_s: 1e-9,
                first_sample_offset_s: -100e-9,
                channels: channels
                    .iter()
                    .map(|&(name, t_s, amp)| {
                        let jitter = 0.37 * seq as f64 % 1.0;
                        let peak = 100.0 + t_s * 1e9 + jitter;
                        let codes: Vec<i16> = (0..400)
                            .map(|k| {
                                let v = 0.01 + amp * pulse.value_and_slope(k as f64 - peak).0 + noise.sample(&mut rng);
                                (v / 0.004).round() as i16
                            })
                            .collect();
                        Channel { name: name.into(), role: ChannelRole::Unspecified, samples: Samples::I16(codes), volts_per_code: 0.004, offset_v: 0.0 }
                    })
                    .collect(),
                laser_off: false,
            })
            .collect()
    }

    #[test]
    fn measures_rise_width_noise_and_channels_of_a_two_channel_capture() {
        let pulse = Pulse::bigaussian(3e-9, 8e-9, 1e-9);
        let f = frames(&[("CH2", 60e-9, 0.8), ("CH1", 5e-9, 1.5)], &pulse, 12);
        let m = measure(&f, "synthetic").unwrap();
        assert_eq!(m.stop.name, "CH2");
        assert_eq!(m.start.as_ref().unwrap().name, "CH1");
        assert!((m.sample_interval_s - 1e-9).abs() < 1e-18);
        assert_eq!(m.samples_per_frame, 400);
        // 3 mV noise on 4 mV codes: sd of the codes sqrt(3² + 4²/12) = 3.25 mV.
        assert!((m.stop.noise_sigma_v - 0.00325).abs() < 0.0004, "{}", m.stop.noise_sigma_v);
        assert!((m.stop.noise_mean_v - 0.01).abs() < 0.0005, "{}", m.stop.noise_mean_v);
        assert!((m.stop.quantisation_step_v - 0.004).abs() < 1e-9);
        // Rise and FWHM from 1 GS/s samples of a 3 ns rise: within 10 %.
        assert!((m.stop.rise_time_s / 3e-9 - 1.0).abs() < 0.1, "{}", m.stop.rise_time_s);
        assert!((m.stop.fwhm_s / 8e-9 - 1.0).abs() < 0.05, "{}", m.stop.fwhm_s);
        // Time of flight: 55 ns between the pulses' 50 % points.
        assert!((m.tof_range_s.0 - 55e-9).abs() < 1e-9, "{:?}", m.tof_range_s);
        let scene = m.scene().unwrap();
        assert_eq!(scene.channels.start, "CH1");
        assert_eq!(scene.return_pulse.model, PulseModel::Bigaussian);
        assert!(scene.range_gate.min_m < 55e-9 * 1.5e8 && scene.range_gate.max_m > 55e-9 * 1.5e8);
        assert_eq!(m.gates.frames_touching_pulses, 0, "{:?}", m.gates);
        assert_eq!(m.gates.frames_contaminated, 0, "{:?}", m.gates);
        let text = m.scene_toml();
        assert!(text.contains("measured"), "{text}");
    }

    #[test]
    fn a_single_channel_is_the_stop_channel_timed_from_the_trigger() {
        let pulse = Pulse::bigaussian(2e-9, 6e-9, 1e-9);
        let f = frames(&[("C1", 3e-9, 1.0)], &pulse, 5);
        let m = measure(&f, "one.trc").unwrap();
        assert!(m.start.is_none());
        assert!(m.channel_notes[0].contains("one channel"), "{:?}", m.channel_notes);
        let scene = m.scene().unwrap();
        assert_eq!(scene.channels.stop, "C1");
        // The start names a channel the capture lacks.
        assert_eq!(scene.channels.start, "CH2");
        assert!(scene.range_gate.min_m < 0.0, "the pulse's 50 % point is about the trigger: {:?}", m.range_gate_m);
    }

    #[test]
    fn no_pulse_is_an_error_naming_the_capture() {
        let pulse = Pulse::bigaussian(2e-9, 6e-9, 1e-9);
        let f = frames(&[("C2", 3e-9, 0.0)], &pulse, 3);
        let e = measure(&f, "quiet.trc").unwrap_err().to_string();
        assert!(e.starts_with("quiet.trc: no pulse"), "{e}");
        let neg = frames(&[("C2", 3e-9, -0.5)], &pulse, 3);
        let e = measure(&neg, "neg.trc").unwrap_err().to_string();
        assert!(e.contains("positive-going"), "{e}");
        assert!(measure(&[], "empty.trc").unwrap_err().to_string().contains("empty.trc"));
    }

    #[test]
    fn set_key_replaces_in_the_right_section_and_keeps_comments() {
        let mut t: Vec<String> = "name = \"a\"\n[x]\n# about k\nk = 1\n[y]\nk = 2\n".lines().map(String::from).collect();
        set_key(&mut t, "y", "k", "3", &["measured".to_string()]);
        set_key(&mut t, "", "name", "\"b\"", &[]);
        set_key(&mut t, "x", "new", "4.0", &[]);
        assert_eq!(t.join("\n"), "name = \"b\"\n[x]\n# about k\nk = 1\nnew = 4.0\n[y]\n# measured\nk = 3");
    }

    #[test]
    fn toml_floats_parse_back() {
        for x in [0.0, 1e-9, 3.4567e-9, -1.953, 0.0123, 150.0, 2.5e7, -3.2e-12] {
            let s = toml_float(x);
            let v: toml::Table = format!("v = {s}").parse().unwrap();
            let back = v["v"].as_float().unwrap();
            assert!((back - x).abs() <= 1e-4 * x.abs(), "{x} -> {s} -> {back}");
        }
    }
}
