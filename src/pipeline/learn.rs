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
use crate::detect::template::{Learned, TemplateError, TemplateLearner};
use crate::dsp::pulse::{PulseShape, Shape};
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
    /// Grid bins of the return shape, and how many of them were interpolated
    /// (no shot reached them, or too few did; see `TemplateLearner::interpolated_bins`).
    pub bins: usize,
    /// See `bins`.
    pub interpolated_bins: usize,
    /// Times the pass learned again on a wider grid because the shape
    /// reached beyond an end of the grid (see `learn_shapes`).
    pub widenings: u32,
    /// Start pulses used (0: the frames have no timed start pulse).
    pub start_shots: u64,
    /// FWHM of the learned start shape, s (0 when none was learned).
    pub start_fwhm_s: f64,
    /// Interpolated bins of the start shape's grid (0 when none was learned).
    pub start_interpolated_bins: usize,
}

/// Why shapes could not be learned.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LearnError {
    /// No frames.
    #[error("no frames to learn from")]
    NoFrames,
    /// The return shape of a pass.
    #[error("pass {pass}: {error}")]
    Return {
        /// Pass number, from 1.
        pass: u32,
        /// What failed (in the message, so not also a `source`: printed once).
        error: TemplateError,
    },
    /// The start shape of a pass.
    #[error("pass {pass}: learning the start pulse: {error}")]
    Start {
        /// Pass number, from 1.
        pass: u32,
        /// What failed.
        error: TemplateError,
    },
}

/// Grid extent around a pulse's peak, samples: (before, after), before negative.
type Grid = (f64, f64);

/// The first equivalent-time grid around a pulse of `shape`: 1.5 times its support.
fn initial_grid(shape: &Shape) -> Grid {
    let (lo, hi) = shape.support();
    (1.5 * lo, 1.5 * hi)
}

/// A pass learns again on a wider grid at most this many times. The
/// scene's shape is a first guess: a receiver whose pulse rings or
/// undershoots (an AC-coupled amplifier's bipolar pulse) carries energy
/// well past where a bigaussian of the same rise and width ends, and a grid
/// that stopped there would cut the learned shape off.
const MAX_WIDENINGS: u32 = 4;

/// `grid` widened after the peak when the learned shape reached its end:
/// twice as far plus four FWHM.
fn widen(grid: Grid, learned: &Learned, fwhm: f64) -> Grid {
    if learned.cut_after { (grid.0, 2.0 * grid.1 + 4.0 * fwhm) } else { grid }
}

/// What one run of the pipeline over the frames gathered.
struct Gathered {
    returns: TemplateLearner,
    start: TemplateLearner,
}

/// Runs the pipeline of `scene` over `frames` and places every clean return
/// (and start pulse) on the grids `grid` and `start_grid`. `raw_snr`: also
/// admit a return whose raw samples' peak reaches the SNR (the first pass,
/// where the scene's shape is a guess and may fit a fraction of the amplitude).
#[allow(clippy::too_many_arguments)]
fn gather(
    scene: &Scene,
    sensor: &str,
    frames: &[Frame],
    opts: &LearnOptions,
    grid: Grid,
    start_grid: Grid,
    raw_snr: bool,
    on_refused: &mut impl FnMut(&super::FrameError),
) -> Gathered {
    let dt = frames.first().map_or(1.0, |f| f.sample_interval_s);
    let shape = scene.return_pulse.shape(dt);
    let (lo, hi) = shape.support();
    let fwhm = shape.fwhm();
    let learner = Arc::new(Mutex::new(TemplateLearner::new(opts.oversample, grid.0, grid.1)));
    // The start pulse's shape is learned the same way, aligned on the
    // start timing: a start shape that does not match the pulse makes its
    // timing depend on the sample phase, which no calibration removes.
    let start_shape = scene.start_pulse.shape(dt);
    let start_learner = Arc::new(Mutex::new(TemplateLearner::new(opts.oversample, start_grid.0, start_grid.1)));
    let start_offset = start_shape.fraction_offset(scene.timing.fraction);
    let mut pipeline = Pipeline::new(scene, sensor);
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
        let sigma = w.noise.raw_sigma_v;
        let x = &w.buffers.stop_v;
        for (i, r) in w.report.returns.iter().enumerate() {
            let p = to_index(r.t_peak_s);
            // Peak SNR: the fitted amplitude's, or in the first pass the
            // raw samples' within half a FWHM of the peak, if larger.
            let snr_db = if raw_snr && sigma > 0.0 {
                let (a, b) = ((p - 0.5 * fwhm).floor().max(0.0) as usize, ((p + 0.5 * fwhm).ceil().max(0.0) as usize + 1).min(x.len()));
                let top = x.get(a..b).into_iter().flatten().fold(f64::NEG_INFINITY, |m, &v| m.max(v)) - w.noise.summary.mean_v;
                if top > 0.0 { r.snr_db.max(20.0 * (top / sigma).log10()) } else { r.snr_db }
            } else {
                r.snr_db
            };
            if !(clean(r) && snr_db >= min_snr) {
                continue;
            }
            cleaned.clear();
            cleaned.extend_from_slice(x);
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
            l.lock().expect("not poisoned").add(&cleaned, w.noise.summary.mean_v, p, r.amplitude_v);
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
    let take = |m: Arc<Mutex<TemplateLearner>>| match Arc::try_unwrap(m) {
        Ok(m) => m.into_inner().expect("not poisoned"),
        Err(m) => m.lock().expect("not poisoned").clone(),
    };
    Gathered { returns: take(learner), start: take(start_learner) }
}

/// `scene` with `return_pulse` (and, where the frames have a start pulse,
/// `start_pulse`) learned from `frames`; the timing method is left as it
/// was. `on_pass` sees each pass's summary; `on_refused` each refused frame.
///
/// A pass whose learned shape is still large at the end of its grid (see
/// [`Learned::cut_after`]) runs again on a grid reaching further after the
/// peak, up to [`MAX_WIDENINGS`] times.
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
    // The shape is what is being learned: the scene's may not fit the data
    // yet, and the events stage judges detections by it (a return wider
    // than the scene's pulse looks like an event's lobe). It is restored below.
    let user_events = scene.events.enabled;
    scene.events.enabled = false;
    for pass in 0..opts.passes.max(1) {
        scene.timing.method = if pass == 0 { TimingMethod::PeakParabolic } else { TimingMethod::Ml };
        let p = pass + 1;
        let shape = scene.return_pulse.shape(dt);
        let start_shape = scene.start_pulse.shape(dt);
        let (mut grid, mut start_grid) = (initial_grid(&shape), initial_grid(&start_shape));
        let mut widenings = 0;
        let (g, learned, start_learned) = loop {
            let g = gather(&scene, sensor, frames, opts, grid, start_grid, pass == 0, &mut on_refused);
            let learned = g.returns.finish_learned(dt).map_err(|error| LearnError::Return { pass: p, error })?;
            let start_learned = if g.start.shots() > 0 {
                Some(g.start.finish_learned(dt).map_err(|error| LearnError::Start { pass: p, error })?)
            } else {
                None
            };
            let cut = |l: &Learned| l.cut_after;
            if widenings >= MAX_WIDENINGS || !(cut(&learned) || start_learned.as_ref().is_some_and(cut)) {
                break (g, learned, start_learned);
            }
            grid = widen(grid, &learned, shape.fwhm());
            if let Some(sl) = &start_learned {
                start_grid = widen(start_grid, sl, start_shape.fwhm());
            }
            widenings += 1;
        };
        scene.return_pulse = learned.pulse;
        let mut start_fwhm_s = 0.0;
        if let Some(sl) = start_learned {
            scene.start_pulse = sl.pulse;
            start_fwhm_s = scene.start_pulse.shape(dt).fwhm() * dt;
        }
        let learned = scene.return_pulse.shape(dt);
        on_pass(&PassSummary {
            pass: p,
            shots: g.returns.shots(),
            fwhm_s: learned.fwhm() * dt,
            half_rise_s: -learned.half_rise_offset() * dt,
            bins: g.returns.bins(),
            interpolated_bins: g.returns.interpolated_bins(),
            widenings,
            start_shots: g.start.shots(),
            start_fwhm_s,
            start_interpolated_bins: if g.start.shots() > 0 { g.start.interpolated_bins() } else { 0 },
        });
    }
    scene.timing.method = user_method;
    scene.events.enabled = user_events;
    Ok(scene)
}
