//! Learning the pulse shapes of a scene from frames (what `tofwave template`
//! runs): the pipeline times every shot, and [`TemplateLearner`]s place the
//! clean returns, and the start pulses, on an equivalent-time grid.
//!
//! The first pass times shots by the matched-filter peak: a model-based fit
//! with a shape that does not match yet would split and flag the returns it
//! is meant to learn from. Later passes fit the shape the previous pass
//! learned. Every clean return of a frame is used, with the frame's other
//! returns subtracted (with the current shape), so a neighbour inside the
//! learning window does not become a bump in the template.

use std::sync::{Arc, Mutex};

use super::Pipeline;
use crate::frame::FrameFlag;
use crate::detect::template::{TemplateError, TemplateLearner};
use crate::dsp::pulse::PulseShape;
use crate::frame::{Frame, Return};
use crate::scene::{Scene, TimingMethod};

/// How to learn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LearnOptions {
    /// Grid points per sample period.
    pub oversample: usize,
    /// Only returns with at least this peak SNR, dB.
    pub min_snr_db: f64,
    /// Learning passes.
    pub passes: u32,
}

impl Default for LearnOptions {
    fn default() -> Self {
        LearnOptions { oversample: 8, min_snr_db: 20.0, passes: 2 }
    }
}

/// What one pass learned.
#[derive(Debug, Clone, PartialEq)]
pub struct PassSummary {
    /// Pass number, from 1.
    pub pass: u32,
    /// Returns used.
    pub shots: u64,
    /// FWHM of the learned return shape, s.
    pub fwhm_s: f64,
    /// Half-rise point before the peak, s.
    pub half_rise_s: f64,
    /// Start pulses used (0: the frames have no timed start pulse).
    pub start_shots: u64,
    /// FWHM of the learned start shape, s (0 when none was learned).
    pub start_fwhm_s: f64,
}

/// Why shapes could not be learned.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LearnError {
    /// No frames.
    #[error("no frames to learn from")]
    NoFrames,
    /// The return shape of a pass.
    #[error("pass {pass}: {source}")]
    Return {
        /// Pass number, from 1.
        pass: u32,
        /// What failed.
        source: TemplateError,
    },
    /// The start shape of a pass.
    #[error("pass {pass}: learning the start pulse: {source}")]
    Start {
        /// Pass number, from 1.
        pass: u32,
        /// What failed.
        source: TemplateError,
    },
}

/// `scene` with `return_pulse` (and, where the frames have a start pulse,
/// `start_pulse`) learned from `frames`; the timing method is left as it
/// was. `on_pass` sees each pass's summary; `on_refused` each refused frame.
pub fn learn_shapes(
    scene: &Scene,
    sensor: &str,
    frames: &[Frame],
    opts: &LearnOptions,
    mut on_pass: impl FnMut(&PassSummary),
    mut on_refused: impl FnMut(&super::FrameError),
) -> Result<Scene, LearnError> {
    let dt = frames.first().ok_or(LearnError::NoFrames)?.sample_interval_s;
    let mut scene = scene.clone();
    let user_method = scene.timing.method;
    for pass in 0..opts.passes.max(1) {
        scene.timing.method = if pass == 0 { TimingMethod::PeakParabolic } else { TimingMethod::Ml };
        let shape = scene.return_pulse.shape(dt);
        let (lo, hi) = shape.support();
        let learner = Arc::new(Mutex::new(TemplateLearner::new(opts.oversample, 1.5 * lo, 1.5 * hi)));
        // The start pulse's shape is learned the same way, aligned on the
        // start timing: a start shape that does not match the pulse makes its
        // timing depend on the sample phase, which no calibration removes.
        let start_shape = scene.start_pulse.shape(dt);
        let (slo, shi) = start_shape.support();
        let start_learner = Arc::new(Mutex::new(TemplateLearner::new(opts.oversample, 1.5 * slo, 1.5 * shi)));
        let start_offset = start_shape.fraction_offset(scene.timing.fraction);
        let mut pipeline = Pipeline::new(&scene, sensor);
        let (l, sl) = (learner.clone(), start_learner.clone());
        let min_snr = opts.min_snr_db;
        let (mut cleaned, mut start_v, mut sorted) = (Vec::new(), Vec::new(), Vec::new());
        pipeline.set_observer(Box::new(move |w| {
            let to_index = |t_s: f64| (t_s - w.frame.first_sample_offset_s) / w.frame.sample_interval_s;
            let timed_start = !w.report.flags.iter().any(|f| f.name().starts_with("no_start") || *f == FrameFlag::StartTimingFallback);
            if let (Some(s), true) = (w.source.start, timed_start) {
                w.frame.channels[s].volts_into(&mut start_v);
                sorted.clone_from(&start_v);
                sorted.sort_by(f64::total_cmp);
                let baseline = sorted[sorted.len() / 2];
                let amplitude = sorted[sorted.len() - 1] - baseline;
                sl.lock().expect("not poisoned").add(&start_v, baseline, to_index(w.reference.t_ref_s) - start_offset, amplitude);
            }
            // Noise that fails the normality test (e.g. coarse quantisation)
            // does not spoil a shot, and a shape that does not fit the scene's
            // model is what learning is for.
            let clean = |r: &Return| r.flags.iter().all(|f| f == "non_gaussian_noise" || f == "shape_mismatch");
            for (i, r) in w.report.returns.iter().enumerate() {
                if !(clean(r) && r.snr_db >= min_snr) {
                    continue;
                }
                cleaned.clear();
                cleaned.extend_from_slice(&w.buffers.stop_v);
                let last = cleaned.len().saturating_sub(1);
                for (j, o) in w.report.returns.iter().enumerate() {
                    if j == i {
                        continue;
                    }
                    let p = to_index(o.t_peak_s);
                    let a = (p + lo).floor().max(0.0) as usize;
                    let b = ((p + hi).ceil().max(0.0) as usize).min(last);
                    for (k, v) in cleaned.iter_mut().enumerate().take(b + 1).skip(a) {
                        *v -= o.amplitude_v * shape.value_and_slope(k as f64 - p).0;
                    }
                }
                l.lock().expect("not poisoned").add(&cleaned, w.noise.summary.mean_v, to_index(r.t_peak_s), r.amplitude_v);
            }
        }));
        let mut reports = Vec::new();
        for f in frames.iter().cloned() {
            reports.clear();
            if let Err(e) = pipeline.push(f, &mut reports) {
                on_refused(&e);
            }
        }
        pipeline.flush(&mut reports);
        drop(pipeline);
        let p = pass + 1;
        let learner = learner.lock().expect("not poisoned");
        scene.return_pulse = learner.finish(dt).map_err(|source| LearnError::Return { pass: p, source })?;
        let start_learner = start_learner.lock().expect("not poisoned");
        let mut start_fwhm_s = 0.0;
        if start_learner.shots() > 0 {
            scene.start_pulse = start_learner.finish(dt).map_err(|source| LearnError::Start { pass: p, source })?;
            start_fwhm_s = scene.start_pulse.shape(dt).fwhm() * dt;
        }
        let learned = scene.return_pulse.shape(dt);
        on_pass(&PassSummary {
            pass: p,
            shots: learner.shots(),
            fwhm_s: learned.fwhm() * dt,
            half_rise_s: -learned.half_rise_offset() * dt,
            start_shots: start_learner.shots(),
            start_fwhm_s,
        });
    }
    scene.timing.method = user_method;
    Ok(scene)
}
