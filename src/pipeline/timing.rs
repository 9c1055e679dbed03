//! timing: times each detection on the stop channel, subtracts the time
//! reference and the calibrated delay, and turns it into a range with its
//! uncertainty, amplitude, SNR, probability of detection and flags.

use super::{FrameError, Stage, Work};
use crate::detect::finite_gate::{detection_probability, rho_squared_sum};
use crate::detect::resolve::MISFIT_LIMIT;
use crate::detect::error_table::ErrorTable;
use crate::detect::pulse_timing::{crlb_samples, joint_crlb_samples, time_pulse, JointScratch, mismatch_gap, ShapeFit, Timed, TimingInput, MISMATCH_Z};
use crate::detect::walk::WalkTable;
use std::sync::Arc;
use crate::dsp::pulse::{PulseShape, Shape};
use crate::frame::{Return, ReturnFlag, ReturnFlags};
use crate::scene::{DetectorKind, Scene, TimingMethod};

/// Returns closer than this many pulse widths are flagged "overlapping":
/// their tails add, so each one's timing depends on the other's fit.
const OVERLAP_FWHM: f64 = 2.0;

/// Weight of each new mismatch gap in its running mean.
const GAP_SMOOTHING: f64 = 0.05;

/// The swing of the shape-mismatch gap (see `mismatch_gap`) beyond noise,
/// one per sensor and channel: the uncertainty a pulse shape the model does
/// not describe adds to the timing point.
///
/// The gap's typical value is a constant the calibration absorbs; its swing
/// about that value holds two things: the noise of the two estimates it
/// compares (the samples' crossing and the fitted model's position), which
/// the method's own width already holds, and the mismatch's change with
/// amplitude and sub-sample phase, which it does not. The first is the
/// gap's scatter on the model shape at the same SNR (measured with the
/// error table), so the running mean square keeps what is left after it.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct MismatchSwing {
    /// Running mean of the gap and of its squared swing less the noise
    /// part, samples (None before the first mismatched pulse).
    state: Option<(f64, f64)>,
}

impl MismatchSwing {
    /// Adds a mismatched pulse's gap (none where the crossing failed), whose
    /// noise-only RMS at this pulse's SNR is `noise` samples; returns the
    /// mismatch's one-sigma, samples.
    pub(crate) fn update(&mut self, gap: Option<f64>, noise: f64) -> f64 {
        if let Some(gap) = gap.filter(|g| g.is_finite()) {
            let (typical, excess2) = self.state.get_or_insert((gap, 0.0));
            let d = gap - *typical;
            *excess2 += GAP_SMOOTHING * (d * d - noise * noise - *excess2);
            *typical += GAP_SMOOTHING * d;
        }
        self.state.map_or(0.0, |(_, excess2)| excess2.max(0.0).sqrt())
    }
}

/// Timing points closer than this (samples) belong to one pulse.
const SAME_PULSE_SAMPLES: f64 = 0.25;

/// At most this many returns per report (the strongest).
const MAX_RETURNS: usize = 32;

/// A timing method's error table and its fallback's ([`ErrorTable::get_with_fallback`]).
type ErrorTables = (Option<Arc<ErrorTable>>, Option<Arc<ErrorTable>>);

/// Times detections and forms ranges.
#[derive(Debug)]
pub struct Timing {
    method: TimingMethod,
    fraction: f64,
    leading_edge_v: f64,
    delay_s: f64,
    /// Standard error of the calibrated delay, s.
    delay_sigma_s: f64,
    c_m_per_s: f64,
    matched: bool,
    pulse_cfg: crate::scene::PulseConfig,
    /// Shape and its template norm for the current sampling period.
    pulse: Option<(f64, Shape, f64)>,
    /// Measured bias and width of the method by SNR (none for leading edge),
    /// and the same for the peak interpolation a failed crossing falls back
    /// to; `None` until a frame's detections are timed one by one (measuring
    /// them simulates thousands of pulses, and pulses the resolver fitted
    /// jointly, as maximum likelihood times them, never read them).
    errors: Option<ErrorTables>,
    /// The method fits the template (peak interpolation or maximum likelihood).
    template_timed: bool,
    /// Leading-edge walk table (leading-edge timing with a calibrated table only).
    walk: Option<WalkTable>,
    /// Each pulse of the current frame: where the detector found it, how it
    /// was timed, how well the shape fitted (kept between frames).
    timed: Vec<(usize, Timed, f64)>,
    /// The mismatch gap's swing beyond noise.
    mismatch: MismatchSwing,
    /// Scratch for the joint Cramér–Rao bounds of resolved pulses.
    joint: JointScratch,
    /// (peak index, amplitude) of the resolved pulses, and their joint bounds.
    resolved: Vec<(f64, f64)>,
    joint_crlb: Vec<f64>,
    /// Scratch for the normalised pulse slope and its autocorrelation.
    slope: Vec<f64>,
    /// See `slope`.
    acf: Vec<f64>,
}

/// Variance gain of coloured noise (normalised autocorrelation `rho`) on the
/// unit-energy slope of `pulse` with its peak at `peak_index` (1 for white noise).
/// `slope` and `acf` are scratch, kept between calls.
fn slope_colour_gain(pulse: &Shape, n: usize, peak_index: f64, rho: &[f64], slope: &mut Vec<f64>, acf: &mut Vec<f64>) -> f64 {
    let (lo, hi) = pulse.support();
    let first = (peak_index + lo).floor().max(0.0) as usize;
    let last = ((peak_index + hi).ceil().max(0.0) as usize).min(n.saturating_sub(1));
    slope.clear();
    slope.extend((first..=last).map(|k| pulse.value_and_slope(k as f64 - peak_index).1));
    let e = slope.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !(e > 0.0) {
        return 1.0;
    }
    slope.iter_mut().for_each(|v| *v /= e);
    crate::detect::colour::output_gain_with(slope, rho, acf).variance_gain
}

impl Timing {
    /// From the scene's timing, calibration, medium and return-pulse sections.
    pub fn new(scene: &Scene) -> Timing {
        Timing {
            method: scene.timing.method,
            fraction: scene.timing.fraction,
            leading_edge_v: scene.timing.leading_edge_v,
            delay_s: scene.calibration.delay_s,
            delay_sigma_s: scene.calibration.delay_sigma_s,
            c_m_per_s: scene.c_medium_m_per_s(),
            matched: scene.detector.kind == DetectorKind::MatchedFilter,
            pulse_cfg: scene.return_pulse.clone(),
            pulse: None,
            errors: None,
            template_timed: matches!(
                scene.timing.method,
                TimingMethod::Ml | TimingMethod::PeakParabolic | TimingMethod::PeakGaussian
            ),
            walk: if scene.timing.method == TimingMethod::LeadingEdge {
                WalkTable::new(&scene.calibration.walk_amplitude_v, &scene.calibration.walk_delay_s)
            } else {
                None
            },
            timed: Vec::with_capacity(MAX_RETURNS),
            joint: JointScratch::default(),
            resolved: Vec::new(),
            joint_crlb: Vec::new(),
            slope: Vec::new(),
            acf: Vec::new(),
            mismatch: MismatchSwing::default(),
        }
    }
}

impl Stage for Timing {
    fn name(&self) -> &'static str {
        self.method.name()
    }

    fn process(&mut self, mut w: Work, out: &mut Vec<Work>) -> Result<(), FrameError> {
        let dt = w.frame.sample_interval_s;
        if self.pulse.as_ref().is_none_or(|p| p.0 != dt) {
            let shape = self.pulse_cfg.shape(dt);
            let norm = if self.matched {
                shape.template().0.iter().map(|v| v * v).sum::<f64>().sqrt()
            } else {
                1.0
            };
            self.errors = None;
            self.pulse = Some((dt, shape, norm));
        }
        let (_, pulse, norm) = self.pulse.as_ref().expect("set above");
        let (pulse, norm) = (pulse, *norm);
        let x = &w.buffers.stop_v;
        let n = x.len();
        let (lo, hi) = pulse.support();
        let fwhm = pulse.fwhm();
        // Each pulse: where the detector found it, how it was timed, how well the shape fitted.
        let timed = &mut self.timed;
        timed.clear();
        if !w.buffers.components.is_empty() {
            // Resolved pulses were fitted jointly: each delay's bound comes
            // from the joint Fisher matrix of the pulses it overlaps.
            self.resolved.clear();
            self.resolved.extend(w.buffers.components.iter().take(MAX_RETURNS).map(|c| (c.peak_index, c.amplitude_v)));
            joint_crlb_samples(pulse, n, &self.resolved, w.noise.raw_sigma_v, &mut self.joint, &mut self.joint_crlb);
            for (c, &joint) in w.buffers.components.iter().take(MAX_RETURNS).zip(&self.joint_crlb) {
                let crlb = joint.max(crlb_samples(pulse, n, c.peak_index, c.amplitude_v, w.noise.raw_sigma_v));
                let t = Timed {
                    index: c.peak_index + pulse.fraction_offset(self.fraction),
                    peak_index: c.peak_index,
                    amplitude_v: c.amplitude_v,
                    sigma_samples: crlb,
                    crlb_samples: crlb,
                    fallback: false,
                };
                timed.push((c.detected_at, t, c.misfit));
            }
        } else if !w.buffers.detections.is_empty() {
            let (errors, fallback_errors) =
                self.errors.get_or_insert_with(|| ErrorTable::get_with_fallback(self.method, pulse, self.fraction, self.matched));
            for &p in w.buffers.detections.iter().take(MAX_RETURNS) {
                let input = TimingInput {
                    x,
                    mean_v: w.noise.summary.mean_v,
                    sigma_v: w.noise.raw_sigma_v,
                    y: &w.buffers.detector_output,
                    norm,
                    pulse,
                    peak: p,
                    fraction: self.fraction,
                    leading_edge_v: self.leading_edge_v,
                };
                let mut t = time_pulse(self.method, &input);
                // The method's measured bias and width at the SNR it measured
                // (a failed crossing falls back to the parabolic peak's table).
                let table = if t.fallback { &*fallback_errors } else { &*errors };
                if let Some(table) = table {
                    (t.index, t.sigma_samples) = table.correct(t.index, t.amplitude_v / w.noise.raw_sigma_v);
                }
                // A shape that does not fit the samples (χ² test) is flagged,
                // and where it puts the timing point is uncertain by the gap
                // between its fraction point and the samples' own crossing.
                let fit = ShapeFit::measure(x, w.noise.summary.mean_v, w.noise.raw_sigma_v, pulse, t.index - pulse.fraction_offset(self.fraction));
                let gain = rho_squared_sum(&w.noise.rho);
                let mismatched = fit.mismatched(MISMATCH_Z, gain);
                if mismatched {
                    // What of the gap's swing noise would give on a fitting
                    // shape at this SNR is already in the method's width.
                    let snr = t.amplitude_v / w.noise.raw_sigma_v;
                    let noise = fallback_errors.as_ref().map_or(0.0, |e| e.gap_noise(snr));
                    let swing = self.mismatch.update(mismatch_gap(&input, &fit), noise);
                    t.sigma_samples = t.sigma_samples.hypot(swing);
                }
                let misfit = if mismatched { f64::INFINITY } else { 0.0 };
                // Two detector maxima on one pulse (a noisy double top) time
                // the same timing point: it is one return, the stronger
                // detection's (detections come strongest first).
                if timed.iter().any(|o| (o.1.index - t.index).abs() < SAME_PULSE_SAMPLES) {
                    continue;
                }
                timed.push((p, t, misfit));
            }
        }
        // The report's list keeps its capacity when the report is recycled.
        let returns = &mut w.report.returns;
        returns.clear();
        for (rank, &(p, one, misfit)) in timed.iter().enumerate() {
            let timed_peak = one.peak_index;
            // A comparator crossing comes earlier the larger the pulse: the
            // calibrated walk at this amplitude moves it to where the table's
            // reference amplitude would cross (not for a fallback timing).
            let walk_s = match &self.walk {
                Some(table) if !one.fallback => table.delay_s(one.amplitude_v),
                _ => 0.0,
            };
            let t_stop_s = w.frame.sample_time_s(one.index) - walk_s;
            let tof_s = t_stop_s - w.reference.t_ref_s - self.delay_s;
            // Template-based estimators fit as if the noise were white; in
            // coloured noise their variance is the sandwich
            // σ²·ṡᵀRṡ / (A²(ṡᵀṡ)²): the white bound times the colour's gain on
            // the normalised slope. (Crossing methods read one sample's noise,
            // which colour does not change.)
            let sigma_stop = if self.template_timed && !w.noise.rho.is_empty() && one.sigma_samples.is_finite() {
                one.sigma_samples * slope_colour_gain(pulse, n, one.peak_index, &w.noise.rho, &mut self.slope, &mut self.acf).sqrt()
            } else {
                one.sigma_samples
            };
            let sigma_t =
                ((sigma_stop * dt).powi(2) + w.reference.t_ref_sigma_s.powi(2) + self.delay_sigma_s.powi(2)).sqrt();
            let amplitude_v = one.amplitude_v;
            let d = amplitude_v * norm / (w.noise.sigma_v * w.threshold.out_gain);
            let mut flags = ReturnFlags::default();
            let first = (one.peak_index + lo).floor();
            let last = (one.peak_index + hi).ceil();
            if first < 0.0 || last > (n - 1) as f64 {
                flags.insert(ReturnFlag::FrameEdge);
            }
            if let Some((clip_lo, clip_hi)) = w.source.clip_v {
                let a = first.clamp(0.0, (n - 1) as f64) as usize;
                let b = last.clamp(0.0, (n - 1) as f64) as usize;
                // Within a quarter step of the rail counts as clipped.
                let margin = 0.25 * w.source.lsb_v;
                if x[a..=b].iter().any(|&v| v >= clip_hi - margin || v <= clip_lo + margin) {
                    flags.insert(ReturnFlag::Saturated);
                }
            }
            let pd = detection_probability(w.threshold.t, d, w.threshold.kappa, w.threshold.nu);
            if pd < 0.5 {
                flags.insert(ReturnFlag::Weak);
            }
            if !w.noise.summary.gaussian && w.noise.summary.samples >= 8 {
                flags.insert(ReturnFlag::NonGaussianNoise);
            }
            if timed.iter().enumerate().any(|(j, o)| j != rank && (o.1.peak_index - timed_peak).abs() < OVERLAP_FWHM * fwhm) {
                flags.insert(ReturnFlag::Overlapping);
            }
            if one.fallback {
                flags.insert(ReturnFlag::TimingFallback);
            }
            if misfit > MISFIT_LIMIT {
                flags.insert(ReturnFlag::ShapeMismatch);
            }
            if w.buffers.interfered.contains(&p) {
                flags.insert(ReturnFlag::Interference);
            }
            returns.push(Return {
                range_m: 0.5 * self.c_m_per_s * tof_s,
                range_sigma_m: 0.5 * self.c_m_per_s * sigma_t,
                tof_s,
                amplitude_v,
                snr_db: 20.0 * (amplitude_v.abs().max(f64::MIN_POSITIVE) / w.noise.raw_sigma_v).log10(),
                score: w.buffers.detector_output[p] / (w.threshold.u * w.noise.sigma_v * w.threshold.out_gain),
                pd,
                t_stop_s,
                t_peak_s: w.frame.sample_time_s(one.peak_index),
                flags,
            });
        }
        returns.sort_by(|a, b| a.tof_s.total_cmp(&b.tof_s));
        out.push(w);
        Ok(())
    }
}
