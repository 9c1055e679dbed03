//! Resolving returns closer than a pulse width: successive cancellation.
//! The strongest matched-filter peak is fitted (amplitude and delay, maximum
//! likelihood) and subtracted; the filter runs again on the residual, until no
//! peak is above the threshold. Then every pulse is refitted with the others
//! subtracted (a few sweeps of coordinate descent on the joint fit).
//!
//! A fit whose residual is much larger than the noise means the scene's shape
//! does not match the data; no further pulse is sought under it (such a
//! residual is the mismatch, not a second return) and it is flagged.

use super::detector::DetectorPlan;
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

/// Scratch for [`resolve`], kept between frames.
#[derive(Debug, Default, Clone)]
pub struct Resolver {
    residual: Vec<f64>,
}

impl Resolver {
    /// Finds up to `max` pulses whose detector output exceeds `threshold`
    /// (output units) at peak positions in `range`.
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
    ) -> Vec<Component> {
        let n = x.len();
        let (lo, hi) = shape.support();
        self.residual.clear();
        self.residual.extend(x.iter().map(|v| v - mean_v));
        let mut comps: Vec<Component> = Vec::new();
        let window = |peak: f64| {
            let a = (peak + lo).floor().max(0.0) as usize;
            let b = ((peak + hi).ceil().max(0.0) as usize + 1).min(n);
            a..b.max(a)
        };
        while comps.len() < max {
            let y = plan.run(&self.residual, 0.0);
            let end = range.end.min(y.len());
            let blocked = |p: usize| {
                comps.iter().any(|c| c.misfit > MISFIT_LIMIT && window(c.peak_index).contains(&p))
            };
            let Some(p) = (range.start.min(end)..end)
                .filter(|&p| !blocked(p))
                .max_by(|&a, &b| y[a].total_cmp(&y[b]))
            else {
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
        // Joint refinement: each pulse refitted with the others removed.
        if comps.len() > 1 {
            for _sweep in 0..4 {
                for i in 0..comps.len() {
                    let c = comps[i];
                    self.subtract(shape, &c, &window, 1.0);
                    let mut f = self.fit(shape, c.peak_index, c.detected_at, sigma_v, &window);
                    if !(f.amplitude_v > 0.0) || (f.peak_index - c.peak_index).abs() > 3.0 {
                        f = c;
                    }
                    self.subtract(shape, &f, &window, -1.0);
                    comps[i] = f;
                }
            }
        }
        comps
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
