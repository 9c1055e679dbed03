//! baseline: removes each frame's offset, measured robustly (median or
//! trimmed mean) on the noise gates and smoothed across frames to follow a
//! slow drift. The offset is subtracted through the stop channel's
//! `offset_v`, so integer codes stay integer (exact averaging downstream).
//!
//! Also home of [`GatePlacer`]: the one place that turns a scene and a
//! frame's time reference into range and noise gates, for the noise stage
//! and the stages before it (baseline, denoise, average).

use super::{FrameError, Stage, Work};
use crate::detect::gates::{GateInputs, Gates};
use crate::dsp::offset::{DriftTracker, OffsetEstimator, robust_offset};
use crate::dsp::pulse::Shape;
use crate::scene::{BaselineConfig, BaselineEstimator, Scene};
use std::ops::Range;

/// Places a frame's range and noise gates (every stage that needs them calls this).
#[derive(Debug)]
pub(crate) struct GatePlacer {
    scene: Scene,
    /// Return-pulse shape for the current sampling period.
    pulse: Option<(f64, Shape)>,
}

impl GatePlacer {
    pub(crate) fn new(scene: &Scene) -> GatePlacer {
        GatePlacer {
            scene: scene.clone(),
            pulse: None,
        }
    }

    /// Gates of `w` (its time reference must be set: the start stage has run).
    pub(crate) fn place(&mut self, w: &Work) -> Gates {
        let s = &self.scene;
        let dt = w.frame.sample_interval_s;
        if self.pulse.as_ref().is_none_or(|p| p.0 != dt) {
            self.pulse = Some((dt, s.return_pulse.shape(dt)));
        }
        let pulse = &self.pulse.as_ref().expect("set above").1;
        let (lo, hi) = pulse.support();
        Gates::place(&GateInputs {
            samples: w.frame.channels[w.stop].samples.len(),
            dt_s: dt,
            first_sample_offset_s: w.frame.first_sample_offset_s,
            t_ref_s: w.t_ref_s,
            delay_s: s.calibration.delay_s,
            c_m_per_s: s.c_medium_m_per_s(),
            min_range_m: s.range_gate.min_m,
            max_range_m: s.range_gate.max_m,
            support_lo: lo,
            support_hi: hi,
            timing_offset: pulse.fraction_offset(s.timing.fraction),
            guard_s: s.noise_gate.guard_s,
            pre: s.noise_gate.pre_trigger,
            beyond: s.noise_gate.beyond_range,
            margin: pulse.fwhm(),
        })
    }

    /// Sample ranges free of returns: the whole frame when the laser is off,
    /// else the noise gates.
    pub(crate) fn quiet_ranges(&mut self, w: &Work) -> Vec<Range<usize>> {
        if w.frame.laser_off {
            return std::iter::once(0..w.frame.len()).collect();
        }
        let g = self.place(w);
        [g.pre, g.beyond]
            .into_iter()
            .filter(|r| !r.is_empty())
            .collect()
    }
}

/// Removes the stop channel's offset.
#[derive(Debug)]
pub struct Baseline {
    estimator: OffsetEstimator,
    tracker: DriftTracker,
    gates: GatePlacer,
    volts: Vec<f64>,
    scratch: Vec<f64>,
}

impl Baseline {
    /// From the scene's `[baseline]` section.
    pub fn new(scene: &Scene, cfg: &BaselineConfig) -> Baseline {
        Baseline {
            estimator: match cfg.estimator {
                BaselineEstimator::Median => OffsetEstimator::Median,
                BaselineEstimator::TrimmedMean => OffsetEstimator::TrimmedMean(cfg.trim_fraction),
            },
            tracker: DriftTracker::new(cfg.smoothing),
            gates: GatePlacer::new(scene),
            volts: Vec::new(),
            scratch: Vec::new(),
        }
    }
}

impl Stage for Baseline {
    fn name(&self) -> &'static str {
        "baseline"
    }

    fn process(&mut self, mut w: Work, out: &mut Vec<Work>) -> Result<(), FrameError> {
        let ranges = self.gates.quiet_ranges(&w);
        w.frame.channels[w.stop].volts_into(&mut self.volts);
        self.scratch.clear();
        for r in &ranges {
            self.scratch.extend_from_slice(&self.volts[r.clone()]);
        }
        let b = match robust_offset(&mut self.scratch, self.estimator) {
            Some(m) => self.tracker.update(m),
            None => {
                w.report.flags.push("no_baseline_gate".into());
                self.tracker.offset_v().unwrap_or(0.0)
            }
        };
        w.frame.channels[w.stop].offset_v -= b;
        out.push(w);
        Ok(())
    }
}
