//! validate: checks a frame against the scene and picks its start and stop
//! channels. The only stage that turns a frame into work; a bad frame is
//! refused here with the field at fault named.

use super::{Buffers, FrameError, NoiseModel, Source, ThresholdTerms, TimeReference, Unit, Work};
use crate::detect::gates::Gates;
use std::sync::Arc;
use crate::frame::{limits, FrameFlag};
use crate::frame::{channel_key, channel_key_into, ChannelRole, Frame, NoiseSummary, Report, Samples};
use crate::scene::Scene;

/// Checks frames and starts their work.
#[derive(Debug)]
pub struct Validate {
    stop_key: String,
    start_key: String,
    stop_name: String,
    start_name: String,
    sample_interval_s: f64,
    samples_per_frame: usize,
    full_scale_v: Option<(f64, f64)>,
    /// Channel keys of the frame being checked, one at a time (reused).
    key_scratch: String,
    /// The empty autocorrelation (white noise) every unit starts with, shared.
    white: Arc<[f64]>,
    /// The scene, for the resource bounds a frame's sampling period makes of
    /// its durations (checked before any later stage sizes a buffer).
    scene: Scene,
}

impl Validate {
    /// From the scene's digitiser and channel sections.
    pub fn new(scene: &Scene) -> Validate {
        let d = &scene.digitiser;
        Validate {
            stop_key: channel_key(&scene.channels.stop),
            start_key: channel_key(&scene.channels.start),
            stop_name: scene.channels.stop.clone(),
            start_name: scene.channels.start.clone(),
            sample_interval_s: d.sample_interval_s,
            samples_per_frame: d.samples_per_frame,
            full_scale_v: (d.full_scale_low_v != 0.0 || d.full_scale_high_v != 0.0)
                .then_some((d.full_scale_low_v, d.full_scale_high_v)),
            key_scratch: String::new(),
            white: Arc::from(Vec::new()),
            scene: scene.clone(),
        }
    }

    /// The stage name.
    pub fn name(&self) -> &'static str {
        "validate"
    }

    /// Validates `frame` and pushes its work, reusing a unit from `spare`
    /// (its buffers and report keep their capacity) when there is one.
    pub fn process(&mut self, frame: Frame, spare: &mut Vec<Unit>, out: &mut Vec<Unit>) -> Result<(), FrameError> {
        let err = |field: &str, msg: String| Err(FrameError::new(&frame, field, msg));
        if frame.channels.is_empty() {
            return err("channels", "the frame has no channels".into());
        }
        let dt = frame.sample_interval_s;
        if !(dt.is_finite() && dt > 0.0) {
            return err("sample_interval_s", format!("{dt} is not a positive, finite period"));
        }
        if self.sample_interval_s > 0.0 && ((dt - self.sample_interval_s) / self.sample_interval_s).abs() > 1e-6 {
            return err(
                "sample_interval_s",
                format!("{dt} s does not match the scene's digitiser.sample_interval_s = {} s", self.sample_interval_s),
            );
        }
        if !frame.first_sample_offset_s.is_finite() || !frame.trigger_time_s.is_finite() {
            return err("first_sample_offset_s", "trigger time and first-sample offset must be finite".into());
        }
        let n = frame.channels[0].samples.len();
        if n == 0 {
            return err(&format!("channels[{}].samples", frame.channels[0].name), "no samples".into());
        }
        for c in &frame.channels {
            if c.samples.len() != n {
                return err(
                    &format!("channels[{}].samples", c.name),
                    format!("{} samples, but channel {} has {n}", c.samples.len(), frame.channels[0].name),
                );
            }
            if !(c.volts_per_code.is_finite() && c.volts_per_code != 0.0 && c.offset_v.is_finite()) {
                return err(
                    &format!("channels[{}].volts_per_code", c.name),
                    format!("scale {} / offset {} must be finite and the scale non-zero", c.volts_per_code, c.offset_v),
                );
            }
        }
        // Resource bounds (frame::limits): the period and length every later
        // stage sizes its buffers and templates from.
        if let Some(problem) = limits::sample_interval_problem(dt) {
            return err("sample_interval_s", problem);
        }
        if let Some(problem) = limits::samples_per_frame_problem(n) {
            return err(&format!("channels[{}].samples", frame.channels[0].name), problem);
        }
        if let Some(e) = self.scene.work_at(dt, n) {
            return err(
                "sample_interval_s",
                format!(
                    "{dt:e} s with the scene's {} ({}) makes {}: a longer sampling period or a smaller {} is needed",
                    e.field,
                    e.value,
                    e.describe(),
                    e.field
                ),
            );
        }
        if self.samples_per_frame > 0 && n != self.samples_per_frame {
            return err(
                "samples",
                format!("{n} samples per channel, the scene's digitiser.samples_per_frame is {}", self.samples_per_frame),
            );
        }
        let scratch = &mut self.key_scratch;
        let mut by_key = |key: &str| {
            frame.channels.iter().position(|c| {
                channel_key_into(&c.name, scratch);
                scratch == key
            })
        };
        let by_role = |role| frame.channels.iter().position(|c| c.role == role);
        let stop = by_role(ChannelRole::Stop).or_else(|| by_key(&self.stop_key)).or_else(|| {
            // A capture with a single channel is the stop channel, timed from the trigger.
            (frame.channels.len() == 1).then_some(0)
        });
        let Some(stop) = stop else {
            return err(
                "channels",
                format!(
                    "no stop channel {:?} (channels.stop in the scene); the frame has {}",
                    self.stop_name,
                    frame.channel_names().join(", ")
                ),
            );
        };
        let start = by_role(ChannelRole::Start).or_else(|| by_key(&self.start_key)).filter(|&s| s != stop);
        let _ = &self.start_name;
        let ch = &frame.channels[stop];
        let clip_v = self.full_scale_v.or_else(|| code_limits_v(&ch.samples, ch.volts_per_code, ch.offset_v));
        let lsb_v = if ch.samples.is_integer() { ch.volts_per_code.abs() } else { 0.0 };
        let source = Source {
            stop,
            start,
            seq_last: frame.sequence,
            frames_averaged: 1,
            clip_v,
            lsb_v,
        };
        // A unit of work from an earlier frame keeps its buffers' and report's
        // capacity; everything else starts afresh.
        let mut w = match spare.pop() {
            Some(mut w) => {
                w.source = source;
                w.buffers.clear();
                w.reference = TimeReference::default();
                w.noise.gates = Gates::default();
                w.noise.summary = NoiseSummary::default();
                w.noise.sigma_v = 0.0;
                w.noise.raw_sigma_v = 0.0;
                w.noise.rho = Arc::clone(&self.white);
                w.threshold = ThresholdTerms::default();
                w.report.reset();
                w
            }
            None => Box::new(Work {
                frame: Frame::empty(),
                source,
                buffers: Buffers::default(),
                reference: TimeReference::default(),
                noise: NoiseModel {
                    rho: Arc::clone(&self.white),
                    ..NoiseModel::default()
                },
                threshold: ThresholdTerms::default(),
                report: Report::default(),
            }),
        };
        let report = &mut w.report;
        report.sensor.push_str(&frame.sensor_id);
        report.seq_first = frame.sequence;
        report.seq_last = frame.sequence;
        report.frames_averaged = 1;
        report.time_s = frame.trigger_time_s;
        report.stages.push(self.name());
        if frame.laser_off {
            report.flags.push(FrameFlag::LaserOff);
        }
        w.frame = frame;
        out.push(w);
        Ok(())
    }
}

/// Volts of the extreme codes of an integer sample type: where an ADC clips.
fn code_limits_v(s: &Samples, scale: f64, offset: f64) -> Option<(f64, f64)> {
    let (lo, hi) = match s {
        Samples::I8(_) => (i8::MIN as f64, i8::MAX as f64),
        Samples::I16(_) => (i16::MIN as f64, i16::MAX as f64),
        Samples::I32(_) => (i32::MIN as f64, i32::MAX as f64),
        _ => return None,
    };
    let (a, b) = (lo * scale + offset, hi * scale + offset);
    Some((a.min(b), a.max(b)))
}
