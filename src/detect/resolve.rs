//! Resolving returns closer than a pulse width: successive cancellation.
//! The strongest matched-filter peak is fitted (amplitude and delay, maximum
//! likelihood) and subtracted; the filter runs again on the residual, until no
//! peak is above the threshold. Then every pulse is refitted with the others
//! subtracted (a few sweeps of coordinate descent on the joint fit).
//!
//! A fit whose residual is much larger than the noise means the scene's shape
//! does not match the data; no further pulse is sought under it (such a
//! residual is the mismatch, not a second return) and it is flagged.

use super::kernels::DetectorPlan;
use crate::math::linalg::solve_in_place;
use crate::dsp::mlfit::fit_delay;
use crate::dsp::pulse::{PulseShape, Shape};
use std::ops::Range;

/// One resolved pulse.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Component {
    /// Fractional sample index of the pulse peak.
    pub peak_index: f64,
    /// Amplitude above the noise mean, volts.
    pub amplitude_v: f64,
    /// Integer position where the detector found it.
    pub detected_at: usize,
    /// RMS of the fit residual over the pulse, in noise sigmas (about 1 when the shape fits).
    pub misfit: f64,
}

/// A residual RMS above this many noise sigmas marks a shape mismatch.
pub const MISFIT_LIMIT: f64 = 1.5;

/// Scratch for [`Resolver::resolve`], kept between frames: once its buffers
/// have grown, resolving allocates nothing.
#[derive(Debug, Default, Clone)]
pub struct Resolver {
    residual: Vec<f64>,
    /// The components before a trial split (restored when the split fails).
    before: Vec<Component>,
    /// The components less the one being tested for its place.
    rest: Vec<Component>,
    /// The joint refit's normal equations and trial step.
    refit: RefitScratch,
}

/// Buffers of one Levenberg-Marquardt refit (`m` = 2 × components unknowns).
#[derive(Debug, Default, Clone)]
struct RefitScratch {
    /// JᵀJ, row-major m × m.
    jtj: Vec<f64>,
    /// Jᵀr.
    jtr: Vec<f64>,
    /// One row of J.
    row: Vec<f64>,
    /// JᵀJ with the damped diagonal; destroyed by the solver.
    aug: Vec<f64>,
    /// The step (Jᵀr on entry to the solver).
    step: Vec<f64>,
    /// The components after the step.
    trial: Vec<Component>,
}

impl Resolver {
    /// Finds up to `max` pulses whose detector output exceeds `threshold`
    /// (output units) at peak positions in `range`, into `comps` (cleared first).
    #[allow(clippy::too_many_arguments)]
    pub fn resolve(
        &mut self,
        x: &[f64],
        mean_v: f64,
        sigma_v: f64,
        shape: &Shape,
        plan: &mut DetectorPlan,
        range: Range<usize>,
        threshold: f64,
        max: usize,
        comps: &mut Vec<Component>,
    ) {
        let n = x.len();
        let (lo, hi) = shape.support();
        self.residual.clear();
        self.residual.extend(x.iter().map(|v| v - mean_v));
        comps.clear();
        let window = |peak: f64| {
            let a = (peak + lo).floor().max(0.0) as usize;
            let b = ((peak + hi).ceil().max(0.0) as usize + 1).min(n);
            a..b.max(a)
        };
        while comps.len() < max {
            let y = plan.run(&self.residual, 0.0);
            let end = range.end.min(y.len());
            let Some(p) = (range.start.min(end)..end).max_by(|&a, &b| y[a].total_cmp(&y[b])) else {
                break;
            };
            if !(y[p] > threshold) {
                break;
            }
            let start = if p > 0 && p + 1 < y.len() {
                p as f64 + crate::dsp::interp::parabolic(y[p - 1], y[p], y[p + 1]).0
            } else {
                p as f64
            };
            let mut c = self.fit(shape, start, p, sigma_v, &window);
            if !(c.amplitude_v > 0.0) {
                // Nothing fits here; take the detector's own estimate and move on.
                c.amplitude_v = y[p] / plan.norm();
                c.peak_index = start;
            }
            self.subtract(shape, &c, &window, -1.0);
            comps.push(c);
        }
        if comps.is_empty() {
            return;
        }
        // Refit every pulse jointly with its overlapping neighbours.
        self.joint_refit(x, mean_v, sigma_v, shape, comps, &window);
        // A pulse the shape cannot explain alone may be two returns closer than
        // a pulse width: try a split and keep it if it explains the data.
        let fwhm = shape.fwhm();
        let mut i = 0;
        while i < comps.len() && comps.len() < max {
            if comps[i].misfit > MISFIT_LIMIT {
                self.before.clear();
                self.before.extend_from_slice(comps);
                let old = comps[i];
                let (a, b) = (
                    Component { peak_index: old.peak_index - fwhm / 3.0, amplitude_v: 0.6 * old.amplitude_v, ..old },
                    Component { peak_index: old.peak_index + fwhm / 3.0, amplitude_v: 0.6 * old.amplitude_v, ..old },
                );
                comps[i] = a;
                comps.push(b);
                self.joint_refit(x, mean_v, sigma_v, shape, comps, &window);
                let j = comps.len() - 1;
                let worse = comps[i].misfit > 0.8 * old.misfit && comps[j].misfit > 0.8 * old.misfit;
                let weak = [comps[i], comps[j]].iter().any(|c| !(c.amplitude_v * plan.norm() > threshold));
                if worse || weak {
                    std::mem::swap(comps, &mut self.before);
                    self.residual_from(x, mean_v, shape, comps, &window);
                }
            }
            i += 1;
        }
        // Each pulse must earn its place: removing it (and refitting the rest)
        // must raise the residual sum of squares by more than the detection
        // threshold squared, the generalised likelihood-ratio form of the same
        // Neyman-Pearson test (for one pulse at a known delay ΔRSS = y²).
        // Otherwise it was the others' leftover or fitted noise.
        while comps.len() > 1 {
            self.residual_from(x, mean_v, shape, comps, &window);
            let (a, b) = span(comps, &window);
            let rss_all: f64 = self.residual[a..b].iter().map(|v| v * v).sum();
            let mut weakest: Option<(usize, f64)> = None;
            for j in 0..comps.len() {
                let mut rest = std::mem::take(&mut self.rest);
                rest.clear();
                rest.extend(comps.iter().enumerate().filter(|&(i, _)| i != j).map(|(_, c)| *c));
                self.joint_refit(x, mean_v, sigma_v, shape, &mut rest, &window);
                self.rest = rest;
                let rss_rest: f64 = self.residual[a..b].iter().map(|v| v * v).sum();
                let gain = rss_rest - rss_all;
                if weakest.is_none_or(|w| gain < w.1) {
                    weakest = Some((j, gain));
                }
            }
            match weakest {
                Some((j, gain)) if !(gain > threshold * threshold) => {
                    comps.remove(j);
                    self.joint_refit(x, mean_v, sigma_v, shape, comps, &window);
                }
                _ => break,
            }
        }
        comps.retain(|c| c.amplitude_v > 0.0);
        self.residual_from(x, mean_v, shape, comps, &window);
    }

    /// residual = x - mean - Σ pulses.
    fn residual_from(&mut self, x: &[f64], mean_v: f64, shape: &Shape, comps: &[Component], window: &dyn Fn(f64) -> Range<usize>) {
        self.residual.clear();
        self.residual.extend(x.iter().map(|v| v - mean_v));
        for c in comps {
            self.subtract(shape, c, window, -1.0);
        }
    }

    /// Gauss-Newton (Levenberg-Marquardt damped) on all amplitudes and delays
    /// of pulses whose windows overlap; leaves `residual` consistent with the result.
    fn joint_refit(
        &mut self,
        x: &[f64],
        mean_v: f64,
        sigma_v: f64,
        shape: &Shape,
        comps: &mut [Component],
        window: &dyn Fn(f64) -> Range<usize>,
    ) {
        let k = comps.len();
        let m = 2 * k;
        let mut lambda = 1e-3;
        self.residual_from(x, mean_v, shape, comps, window);
        let rss = |r: &[f64], comps: &[Component]| -> f64 {
            let (a, b) = span(comps, window);
            r[a..b].iter().map(|v| v * v).sum()
        };
        let mut cost = rss(&self.residual, comps);
        let mut ws = std::mem::take(&mut self.refit);
        let RefitScratch { jtj, jtr, row, aug, step, trial } = &mut ws;
        for _it in 0..40 {
            let (a, b) = span(comps, window);
            for v in [&mut *jtj, &mut *jtr, &mut *row] {
                v.clear();
            }
            jtj.resize(m * m, 0.0);
            jtr.resize(m, 0.0);
            row.resize(m, 0.0);
            for t in a..b {
                for (i, c) in comps.iter().enumerate() {
                    let (v, dv) = shape.value_and_slope(t as f64 - c.peak_index);
                    row[2 * i] = v;
                    row[2 * i + 1] = -c.amplitude_v * dv;
                }
                let r = self.residual[t];
                for p in 0..m {
                    jtr[p] += row[p] * r;
                    for q in 0..m {
                        jtj[p * m + q] += row[p] * row[q];
                    }
                }
            }
            let mut improved = false;
            for _try in 0..8 {
                aug.clear();
                aug.extend_from_slice(jtj);
                for p in 0..m {
                    aug[p * m + p] *= 1.0 + lambda;
                    aug[p * m + p] += 1e-30;
                }
                step.clear();
                step.extend_from_slice(jtr);
                if !(solve_in_place(aug, step, m, 0.0) && step.iter().all(|v| v.is_finite())) {
                    break;
                }
                trial.clear();
                trial.extend(comps.iter().enumerate().map(|(i, c)| Component {
                    amplitude_v: c.amplitude_v + step[2 * i],
                    peak_index: c.peak_index + step[2 * i + 1].clamp(-2.0, 2.0),
                    ..*c
                }));
                self.residual_from(x, mean_v, shape, trial, window);
                let new_cost = rss(&self.residual, trial);
                if new_cost.is_finite() && new_cost < cost {
                    let small = step.iter().all(|s| s.abs() < 1e-9 * (1.0 + s.abs()));
                    comps.copy_from_slice(trial);
                    cost = new_cost;
                    lambda = (lambda * 0.3).max(1e-9);
                    improved = !small;
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        self.refit = ws;
        self.residual_from(x, mean_v, shape, comps, window);
        for i in 0..k {
            let w = window(comps[i].peak_index);
            let len = w.len().max(1) as f64;
            let ss: f64 = self.residual[w].iter().map(|v| v * v).sum();
            comps[i].misfit = if sigma_v > 0.0 { (ss / len).sqrt() / sigma_v } else { 0.0 };
        }
    }

    fn fit(&self, shape: &Shape, start: f64, detected_at: usize, sigma_v: f64, window: &dyn Fn(f64) -> Range<usize>) -> Component {
        let w = window(start);
        let fit = fit_delay(&self.residual, 0.0, shape, start, w.clone(), 30);
        let ok = fit.amplitude.is_finite() && fit.delay.is_finite() && (fit.delay - start).abs() <= 3.0;
        Component {
            peak_index: if ok { fit.delay } else { start },
            amplitude_v: if ok { fit.amplitude } else { f64::NAN },
            detected_at,
            misfit: if ok && sigma_v > 0.0 { fit.residual_rms / sigma_v } else { 0.0 },
        }
    }

    /// Adds `sign` times the component's pulse to the residual.
    fn subtract(&mut self, shape: &Shape, c: &Component, window: &dyn Fn(f64) -> Range<usize>, sign: f64) {
        for k in window(c.peak_index) {
            self.residual[k] += sign * c.amplitude_v * shape.value_and_slope(k as f64 - c.peak_index).0;
        }
    }
}

/// Sample span covering every component's window.
fn span(comps: &[Component], window: &dyn Fn(f64) -> Range<usize>) -> (usize, usize) {
    comps.iter().map(|c| window(c.peak_index)).fold((usize::MAX, 0), |(a, b), w| (a.min(w.start), b.max(w.end)))
}
