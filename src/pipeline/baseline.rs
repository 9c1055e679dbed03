//! baseline: removes each frame's offset, measured robustly (median or
//! trimmed mean) on the noise gates and smoothed across frames to follow a
//! slow drift. The offset is subtracted through the stop channel's
//! `offset_v`, so integer codes stay integer (exact averaging downstream).

use super::{FrameError, Stage, Unit};
use crate::frame::FrameFlag;
use crate::detect::gates::GatePlacer;
use crate::dsp::offset::{DriftTracker, OffsetEstimator, robust_offset};
use crate::scene::{BaselineConfig, BaselineEstimator, Scene};

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

    fn process(&mut self, mut w: Unit, out: &mut Vec<Unit>) -> Result<(), FrameError> {
        let ranges = w.quiet_ranges(&mut self.gates);
        w.frame.channels[w.source.stop].volts_into(&mut self.volts);
        self.scratch.clear();
        for r in ranges.iter() {
            self.scratch.extend_from_slice(&self.volts[r.clone()]);
        }
        let b = match robust_offset(&mut self.scratch, self.estimator) {
            Some(m) => self.tracker.update(m),
            None => {
                w.report.flags.push(FrameFlag::NoBaselineGate);
                self.tracker.offset_v().unwrap_or(0.0)
            }
        };
        w.frame.channels[w.source.stop].offset_v -= b;
        out.push(w);
        Ok(())
    }
}
