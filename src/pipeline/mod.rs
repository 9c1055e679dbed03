//! The per-sensor pipeline: stages built from a scene, frames in, reports out.
//!
//! (Interface fixed; the stages are being filled in.)

use crate::frame::{Frame, NoiseSummary, Report};
use crate::scene::Scene;

/// A frame the pipeline refused; the pipeline itself carries on.
#[derive(Debug, thiserror::Error)]
#[error("frame {sequence} of sensor {sensor}: {field}: {message}")]
pub struct FrameError {
    /// Sensor id.
    pub sensor: String,
    /// Sequence number.
    pub sequence: u64,
    /// Field at fault, e.g. `sample_interval_s` or `channels[CH2].samples[17]`.
    pub field: String,
    /// What was wrong and what was expected.
    pub message: String,
}

/// One sensor's pipeline.
pub struct Pipeline {
    scene: Scene,
    sensor: String,
}

impl Pipeline {
    /// Builds the stages `scene` needs.
    pub fn new(scene: &Scene, sensor: &str) -> Pipeline {
        Pipeline { scene: scene.clone(), sensor: sensor.to_string() }
    }

    /// The scene this pipeline was built from.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Processes one frame; pushes 0..n reports (0 while an average fills).
    pub fn push(&mut self, frame: Frame, out: &mut Vec<Report>) -> Result<(), FrameError> {
        let _ = (frame, out, &self.sensor);
        Ok(())
    }

    /// Emits what a partly filled average holds (end of input).
    pub fn flush(&mut self, out: &mut Vec<Report>) {
        let _ = out;
    }

    /// The latest noise model, if any frame has been processed.
    pub fn noise_model(&self) -> Option<NoiseSummary> {
        None
    }
}

/// A report as one JSON line (the `process` / `subscribe` output shape).
pub fn report_json(report: &Report) -> String {
    serde_json::to_string(report).expect("reports always serialise")
}
