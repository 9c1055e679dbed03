//! The per-sensor pipeline: stages built from a scene, frames in, reports out.
//!
//! Every stage has one shape ([`Stage`]): it takes a unit of work and pushes
//! 0..n units on (1:1 for most, N:1 for averaging). Stages never see async
//! code; the service runs a sensor's pipeline on a blocking worker. The
//! pipeline holds only the stages its scene needs, and each report names the
//! stages that ran.

mod average;
mod baseline;
mod denoise;
mod detect;
mod events;
/// Learning the return and start pulse shapes from frames (`tofwave template`).
pub mod learn;
mod noise;
mod start;
/// One sensor's pipeline on several threads (a stage pipeline), bit-identical to one thread.
pub mod threaded;
mod timing;
mod validate;

use crate::detect::gates::{GatePlacer, Gates, QuietRanges};
use crate::frame::{Frame, NoiseSummary, Report, Samples};
use crate::scene::Scene;
use std::sync::Arc;

/// A frame the pipeline refused; the pipeline itself carries on.
#[derive(Debug, Clone, thiserror::Error)]
#[error("frame {sequence} of sensor {sensor}: {field}: {message}")]
pub struct FrameError {
    /// Sensor id.
    pub sensor: String,
    /// Sequence number.
    pub sequence: u64,
    /// Field at fault, e.g. `sample_interval_s` or `channels[CH2].samples`.
    pub field: String,
    /// What was wrong and what was expected.
    pub message: String,
}

impl FrameError {
    fn new(frame: &Frame, field: impl Into<String>, message: impl Into<String>) -> FrameError {
        FrameError {
            sensor: frame.sensor_id.clone(),
            sequence: frame.sequence,
            field: field.into(),
            message: message.into(),
        }
    }
}

/// A unit of work as it passes from stage to stage: boxed, so that passing
/// it on moves a pointer rather than the unit's kilobyte.
pub type Unit = Box<Work>;

/// One unit of work moving through the stages: a frame (or an averaged group)
/// and what the stages have found so far, in named parts. Each part says
/// which stage writes it and which stages read it; a stage reads only parts
/// written before it (validate → start → baseline → denoise → average →
/// noise → detect → events → timing).
#[derive(Debug, Clone)]
pub struct Work {
    /// The frame (after averaging: the mean frame, F64 volts).
    pub frame: Frame,
    /// Which channels hold what and how the stop channel was digitised.
    pub source: Source,
    /// Per-sample buffers, kept with their capacity from frame to frame.
    pub buffers: Buffers,
    /// The time reference.
    pub reference: TimeReference,
    /// Gates and noise model of the stop channel.
    pub noise: NoiseModel,
    /// The detector's threshold terms.
    pub threshold: ThresholdTerms,
    /// The report being built; every stage may add flags to it.
    pub report: Report,
}

/// Where the channels are and how the stop channel was digitised. Written by
/// validate (average rewrites it for the mean frame); read by every stage.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Source {
    /// Index of the stop channel in `frame.channels`.
    pub stop: usize,
    /// Index of the start channel, if the frame has one.
    pub start: Option<usize>,
    /// Last sequence number in the group.
    pub seq_last: u64,
    /// Frames in the group.
    pub frames_averaged: u32,
    /// Clip levels of the stop channel, volts (low, high), if known.
    pub clip_v: Option<(f64, f64)>,
    /// Quantisation step of the stop channel, volts (0 for float data).
    pub lsb_v: f64,
}

impl Source {
    /// The stop channel's rails: its clip levels a quarter step inside
    /// (a sample within a quarter step of a clip level is clipped; see
    /// [`crate::detect::gates::at_rail`]), if known.
    pub fn rails(&self) -> Option<(f64, f64)> {
        let margin = 0.25 * self.lsb_v;
        self.clip_v.map(|(lo, hi)| (lo + margin, hi - margin))
    }
}

/// Buffers sized by the frame, reused across frames so that the per-frame
/// path does not allocate once they have grown.
#[derive(Debug, Clone, Default)]
pub struct Buffers {
    /// Stop channel in volts. Written by noise; read by detect and timing.
    pub stop_v: Vec<f64>,
    /// Detector output indexed by peak position. Written by detect; read by timing.
    pub detector_output: Vec<f64>,
    /// Detected peak positions, strongest first. Written by detect; read by timing.
    pub detections: Vec<usize>,
    /// Pulses resolved by successive cancellation (maximum-likelihood timing
    /// only). Written by detect; read by timing (which then times these
    /// instead of `detections`).
    pub components: Vec<crate::detect::resolve::Component>,
    /// Detections (their `detections` entry or component's `detected_at`)
    /// that an interference event overlaps. Written by events; read by timing.
    pub interfered: Vec<usize>,
    /// Detections the events stage placed away from the detector's local
    /// maxima (a return found beside its detection, or one an event's
    /// trough hid from the detector) and their statistic over the
    /// threshold (the events test's z over u), which the report gives as the
    /// return's score: the detector output there is not what found it.
    /// Written by events; read by timing.
    pub placed: Vec<(usize, f64)>,
    /// The noise gates' excursions above the false-alarm self-check's level
    /// (each excursion's highest position and the crossings it counts; 0
    /// for those over the gates' samples the cleaning left out, listed as
    /// context), for the events stage to judge. Written by detect (cleared
    /// every frame; filled only when the events stage runs and the kept
    /// gate runs crossed); read by events.
    pub gate_excursions: Vec<(usize, u64)>,
    /// The noise gates' samples the noise model was fitted on: the gates,
    /// less what the cleaning of a contaminated gate dropped (sample ranges,
    /// in frame order). Written by noise; read by detect (noise colour,
    /// whitener, false-alarm self-check).
    pub quiet: Vec<std::ops::Range<usize>>,
    /// The noise gates' band energies, window by window, as the events gate
    /// screen computed them (empty where it did not run). Written by noise
    /// (cleared every frame); read by events (its test's null, for the same
    /// runs: the screen dropped nothing).
    pub gate_band: crate::detect::events::GateBand,
    /// Storage for channel samples a stage rewrites in volts (denoise: the
    /// cleaned stop channel; average: the mean channels). Lent to the frame
    /// by [`Work::set_volts`] and taken back when the unit is done, so the
    /// next frames reuse it instead of allocating.
    pub volts: Vec<Vec<f64>>,
    /// Channels of the frame whose samples are storage lent by `set_volts`.
    lent: Vec<usize>,
}

/// The frame's time reference. Written by start (average replaces it with
/// the group's); read by baseline, denoise, average and noise (gate
/// placement) and timing (time of flight).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TimeReference {
    /// Time reference relative to the trigger, s.
    pub t_ref_s: f64,
    /// One-sigma uncertainty of the reference, s.
    pub t_ref_sigma_s: f64,
}

/// Gates and noise model of the stop channel. Written by noise (detect
/// replaces `sigma_v` by σ_eff when it whitens, and sets `rho`;
/// `raw_sigma_v` stays the samples'); read by detect and timing.
#[derive(Debug, Clone, Default)]
pub struct NoiseModel {
    /// Range and noise gates on this frame.
    pub gates: Gates,
    /// Noise model of the stop channel (as reported).
    pub summary: NoiseSummary,
    /// Noise sigma used for thresholds (floored where the gate had none;
    /// σ_eff of the whitened domain when detect whitens).
    pub sigma_v: f64,
    /// Noise sigma of the raw stop samples (floored as `sigma_v`): what the
    /// timing methods read, whitened or not.
    pub raw_sigma_v: f64,
    /// Normalised noise autocorrelation ρ(0..) pooled over the noise gates
    /// (empty: white). Shared with detect's colour estimate, not copied.
    pub rho: Arc<[f64]>,
}

/// What the threshold is in noise units and how the detector output's sigma
/// relates to the noise sigma. Written by detect; read by timing (scores and
/// the probability of detection) and events (the threshold; it takes
/// `gate_count`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThresholdTerms {
    /// Threshold in units of the fitted noise sigma.
    pub u: f64,
    /// Student-t threshold in units of the inflated output sigma (sigma * kappa).
    pub t: f64,
    /// Inflation of the output sigma by the gate's mean error.
    pub kappa: f64,
    /// Degrees of freedom of the gate's sigma.
    pub nu: f64,
    /// Detector output sigma per unit of `sigma_v` (√g of the noise colour; 1 for white noise).
    pub out_gain: f64,
    /// This frame's noise-gate count for the false-alarm self-check, left
    /// by detect for the events stage, which takes off the crossings it
    /// judges interference events before counting (as it drops such
    /// detections from the range gate). `None` where detect counted itself.
    pub gate_count: Option<GateCount>,
}

/// One frame's noise-gate threshold crossings and what they are counted
/// against (see `detect::FalseAlarmCounter`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GateCount {
    /// Crossings (exceedances with CFAR) observed in the noise gates.
    pub observed: u64,
    /// Effective noise-gate cells examined.
    pub gate_cells: f64,
    /// Design per-cell probability.
    pub p_cell: f64,
    /// Variance of the frame's count over its binomial variance.
    pub dispersion: f64,
}

impl Default for ThresholdTerms {
    fn default() -> ThresholdTerms {
        ThresholdTerms {
            u: 0.0,
            t: 0.0,
            kappa: 1.0,
            nu: f64::INFINITY,
            out_gain: 1.0,
            gate_count: None,
        }
    }
}

impl Buffers {
    /// Empties every per-frame buffer, keeping its capacity (the spare
    /// `volts` storage stays).
    pub fn clear(&mut self) {
        self.stop_v.clear();
        self.detector_output.clear();
        self.detections.clear();
        self.components.clear();
        self.interfered.clear();
        self.placed.clear();
        self.gate_excursions.clear();
    }
}

impl Work {
    /// Gates of this frame's stop channel at its time reference.
    pub(crate) fn place_gates(&self, placer: &mut GatePlacer) -> Gates {
        placer.place(&self.frame, self.frame.channels[self.source.stop].samples.len(), self.reference.t_ref_s)
    }

    /// This frame's quiet sample ranges (see [`GatePlacer::quiet_ranges`]).
    pub(crate) fn quiet_ranges(&self, placer: &mut GatePlacer) -> QuietRanges {
        placer.quiet_ranges(&self.frame, self.frame.channels[self.source.stop].samples.len(), self.reference.t_ref_s)
    }

    /// Empty storage for a channel in volts: spare storage of this unit
    /// (`buffers.volts`), or a new vector when it has none.
    pub(crate) fn spare_volts(&mut self) -> Vec<f64> {
        let mut v = self.buffers.volts.pop().unwrap_or_default();
        v.clear();
        v
    }

    /// Makes channel `c` of the frame hold `volts` (scale 1, offset 0; name
    /// and role stay). The storage is lent: [`Work::reclaim_volts`] takes it
    /// back into `buffers.volts` (storage lent to `c` before comes back now).
    pub(crate) fn set_volts(&mut self, c: usize, volts: Vec<f64>) {
        let ch = &mut self.frame.channels[c];
        let old = std::mem::replace(&mut ch.samples, Samples::F64(volts));
        ch.volts_per_code = 1.0;
        ch.offset_v = 0.0;
        if !self.buffers.lent.contains(&c) {
            self.buffers.lent.push(c);
        } else if let Samples::F64(v) = old {
            self.buffers.volts.push(v);
        }
    }

    /// Takes the storage lent to the frame's channels back into
    /// `buffers.volts` (those channels are left empty).
    pub(crate) fn reclaim_volts(&mut self) {
        let Buffers { volts, lent, .. } = &mut self.buffers;
        for c in lent.drain(..) {
            if let Some(ch) = self.frame.channels.get_mut(c)
                && let Samples::F64(v) = std::mem::replace(&mut ch.samples, Samples::F64(Vec::new()))
            {
                volts.push(v);
            }
        }
    }
}

/// A stop channel's integer codes as i16 (8-bit codes widened into
/// `wide`), or None for float samples or codes wider than 16 bits.
pub(crate) fn stop_codes<'a>(samples: &'a Samples, wide: &'a mut Vec<i16>) -> Option<&'a [i16]> {
    match samples {
        Samples::I16(c) => Some(c),
        Samples::I8(c) => {
            wide.clear();
            wide.extend(c.iter().map(|&v| i16::from(v)));
            Some(wide)
        }
        _ => None,
    }
}

/// Puts a unit whose work is done (its report went out, or a stage consumed
/// it) with the spare units: storage lent to its frame comes back to its
/// buffers and the frame, the caller's, is dropped now rather than held.
fn retire(spare: &mut Vec<Unit>, mut w: Unit) {
    w.reclaim_volts();
    w.frame = Frame::empty();
    spare.push(w);
}

/// A pipeline step.
pub trait Stage: Send {
    /// Name in reports: the file name and the scene's word for it.
    fn name(&self) -> &'static str;
    /// Processes one unit; pushes 0..n units to `out`.
    fn process(&mut self, work: Unit, out: &mut Vec<Unit>) -> Result<(), FrameError>;
    /// End of input: pushes whatever is held back.
    fn flush(&mut self, _out: &mut Vec<Unit>) {}
    /// A unit the stage has consumed and no longer needs (a frame averaged
    /// into another unit), if any: the pipeline reuses its buffers for the
    /// next frames. Called after every `process` and `flush` until `None`.
    fn consumed(&mut self) -> Option<Unit> {
        None
    }
}

/// Sees every finished unit of work before it becomes a report (tools that
/// need the waveforms, e.g. template learning).
pub type Observer = Box<dyn FnMut(&Work) + Send>;

/// One sensor's pipeline.
pub struct Pipeline {
    scene: Scene,
    sensor: String,
    validate: validate::Validate,
    stages: Vec<Box<dyn Stage>>,
    last_noise: Option<NoiseSummary>,
    observer: Option<Observer>,
    /// Units entering the next stage (kept for their capacity).
    entering: Vec<Unit>,
    /// Units the current stage pushes (kept for their capacity).
    leaving: Vec<Unit>,
    /// Units whose report went out: their buffers are reused for the next frames.
    spare: Vec<Unit>,
    /// Reports handed back by [`Pipeline::recycle`], reused for the next reports.
    spare_reports: Vec<Report>,
}

impl std::fmt::Debug for Pipeline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pipeline")
            .field("sensor", &self.sensor)
            .field("stages", &self.stage_names())
            .finish()
    }
}

impl Pipeline {
    /// Builds the stages `scene` needs (the scene is already validated).
    pub fn new(scene: &Scene, sensor: &str) -> Pipeline {
        // validate → start → baseline → denoise → average → noise → detect → events → timing.
        // The start stage runs first: the noise gates the baseline and denoise
        // stages work on, and the alignment of averaged frames, need each
        // frame's own time reference.
        let mut stages: Vec<Box<dyn Stage>> = vec![Box::new(start::Start::new(scene))];
        if let Some(b) = &scene.baseline {
            stages.push(Box::new(baseline::Baseline::new(scene, b)));
        }
        if let Some(d) = &scene.denoise {
            stages.push(Box::new(denoise::Denoise::new(scene, d)));
        }
        if scene.averaging.frames > 1 {
            stages.push(Box::new(average::Average::new(scene)));
        }
        stages.push(Box::new(noise::Noise::new(scene)));
        stages.push(Box::new(detect::Detect::new(scene)));
        if scene.events.enabled {
            stages.push(Box::new(events::Events::new(scene)));
        }
        stages.push(Box::new(timing::Timing::new(scene)));
        Pipeline {
            scene: scene.clone(),
            sensor: sensor.to_string(),
            validate: validate::Validate::new(scene),
            stages,
            last_noise: None,
            observer: None,
            entering: Vec::new(),
            leaving: Vec::new(),
            spare: Vec::new(),
            spare_reports: Vec::new(),
        }
    }

    /// The scene this pipeline was built from.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Names of the stages, in order.
    pub fn stage_names(&self) -> Vec<&'static str> {
        std::iter::once(self.validate.name()).chain(self.stages.iter().map(|s| s.name())).collect()
    }

    /// Processes one frame; pushes 0..n reports (0 while an average fills).
    /// A refused frame changes nothing else.
    ///
    /// In steady state the pipeline allocates nothing per frame when the
    /// caller hands its reports back once it is done with them:
    ///
    /// ```no_run
    /// # fn run(p: &mut tofwave::pipeline::Pipeline, frames: Vec<tofwave::frame::Frame>) {
    /// let mut out = Vec::new();
    /// for frame in frames {
    ///     p.recycle(&mut out); // empties `out`; the reports' storage is reused
    ///     p.push(frame, &mut out).ok();
    ///     // ... use `out` ...
    /// }
    /// # }
    /// ```
    pub fn push(&mut self, frame: Frame, out: &mut Vec<Report>) -> Result<(), FrameError> {
        let mut entering = std::mem::take(&mut self.entering);
        entering.clear();
        let result = self
            .validate
            .process(frame, &mut self.spare, &mut entering)
            .and_then(|()| self.run_from(0, &mut entering, out));
        self.entering = entering;
        result
    }

    /// Emits what a partly filled average holds (end of input).
    pub fn flush(&mut self, out: &mut Vec<Report>) {
        for i in 0..self.stages.len() {
            let mut entering = Vec::new();
            self.stages[i].flush(&mut entering);
            while let Some(w) = self.stages[i].consumed() {
                retire(&mut self.spare, w);
            }
            if !entering.is_empty() {
                // Errors past validation are not expected; a failing flush loses only that group.
                let _ = self.run_from(i + 1, &mut entering, out);
            }
        }
    }

    /// Runs `entering` through the stages from index `first` on.
    fn run_from(&mut self, first: usize, entering: &mut Vec<Unit>, out: &mut Vec<Report>) -> Result<(), FrameError> {
        let mut leaving = std::mem::take(&mut self.leaving);
        let mut result = Ok(());
        for stage in &mut self.stages[first..] {
            leaving.clear();
            for mut w in entering.drain(..) {
                w.report.stages.push(stage.name());
                if let Err(e) = stage.process(w, &mut leaving) {
                    result = Err(e);
                }
                while let Some(w) = stage.consumed() {
                    retire(&mut self.spare, w);
                }
            }
            std::mem::swap(entering, &mut leaving);
        }
        for mut w in entering.drain(..) {
            if let Some(f) = &mut self.observer {
                f(&w);
            }
            self.last_noise = Some(w.report.noise);
            let report = std::mem::replace(&mut w.report, self.spare_reports.pop().unwrap_or_default());
            out.push(report);
            retire(&mut self.spare, w);
        }
        self.leaving = leaving;
        result
    }

    /// Takes back the reports in `reports` (leaving it empty) so that later
    /// reports reuse their storage instead of allocating.
    pub fn recycle(&mut self, reports: &mut Vec<Report>) {
        self.spare_reports.extend(reports.drain(..));
    }

    /// Calls `f` with every finished unit of work.
    pub fn set_observer(&mut self, f: Observer) {
        self.observer = Some(f);
    }

    /// The latest noise model, if any frame has been processed.
    pub fn noise_model(&self) -> Option<NoiseSummary> {
        self.last_noise
    }
}

/// A report as one JSON line (the `process` / `subscribe` output shape).
pub fn report_json(report: &Report) -> String {
    serde_json::to_string(report).expect("reports always serialise")
}
