//! denoise: cancels a structured, repeating interference burst on the stop
//! channel, or (for comparison) filters it with a plain notch / high-pass.
//!
//! Template method: the first `learn_frames` frames are held back while their
//! noise gates (whole frames when the laser is off) teach the burst waveform
//! ([`BurstLearner`]); then those frames and every later one go through
//! [`BurstCanceller`], which detects the burst by correlation at its own
//! false-detection probability (`denoise.pfa` per frame), fits amplitude and
//! sub-sample shift on the gates and subtracts it from the whole frame. Once a
//! burst is found, the next frame is first searched where the trigger times
//! put it (`denoise.predict`). A frame with a cancelled burst is flagged
//! `interference_cancelled`; if learning found no burst the frames pass
//! unchanged, flagged `no_interference_learned`.

use crate::detect::gates::GatePlacer;
use super::{FrameError, Stage, Unit, Work};
use crate::frame::FrameFlag;
use crate::dsp::interference::{BurstCanceller, BurstLearner, BurstTemplate};
use crate::dsp::notch::ZeroPhaseFilter;
use crate::scene::{DenoiseConfig, DenoiseMethod, Scene};

/// What the stage is doing.
#[derive(Debug)]
enum State {
    /// Collecting noise gates; the frames wait here.
    Learning {
        learner: BurstLearner,
        held: Vec<Unit>,
    },
    /// Cancelling with a learned template (planned per frame length).
    Cancelling {
        template: BurstTemplate,
        canceller: Option<Box<BurstCanceller>>,
    },
    /// Learning found nothing to cancel.
    Idle,
    /// Plain filtering, planned per sampling period.
    Filtering(Option<(f64, ZeroPhaseFilter)>),
}

/// Interference cancellation.
#[derive(Debug)]
pub struct Denoise {
    cfg: DenoiseConfig,
    gates: GatePlacer,
    state: State,
    /// Absolute sample index and template lag of the last burst found.
    last: Option<(i64, f64)>,
    volts: Vec<f64>,
}

/// Absolute sample index of a frame's first sample on the trigger clock.
fn abs_pos(w: &Work) -> i64 {
    let f = &w.frame;
    ((f.trigger_time_s + f.first_sample_offset_s) / f.sample_interval_s).round() as i64
}

impl Denoise {
    /// From the scene's `[denoise]` section.
    pub fn new(scene: &Scene, cfg: &DenoiseConfig) -> Denoise {
        let state = match cfg.method {
            DenoiseMethod::Template => State::Learning {
                learner: BurstLearner::new(1, 0.0),
                held: Vec::new(),
            },
            DenoiseMethod::Notch | DenoiseMethod::Highpass => State::Filtering(None),
        };
        Denoise {
            cfg: cfg.clone(),
            gates: GatePlacer::new(scene),
            state,
            last: None,
            volts: Vec::new(),
        }
    }

    fn learner_for(&self, w: &Work) -> BurstLearner {
        let dt = w.frame.sample_interval_s;
        BurstLearner::new(
            (self.cfg.max_burst_s / dt).ceil() as usize,
            self.cfg.bandwidth_hz * dt,
        )
    }

    /// Ends learning: plans the canceller (or gives up) and runs the held frames.
    fn finish_learning(&mut self, out: &mut Vec<Unit>) {
        let State::Learning { learner, held } = std::mem::replace(&mut self.state, State::Idle)
        else {
            return;
        };
        self.state = match learner.finish() {
            Some(template) => State::Cancelling {
                template,
                canceller: None,
            },
            None => State::Idle,
        };
        for w in held {
            self.cancel(w, out);
        }
    }

    fn cancel(&mut self, mut w: Unit, out: &mut Vec<Unit>) {
        match &mut self.state {
            State::Idle => {
                w.report.flags.push(FrameFlag::NoInterferenceLearned);
            }
            State::Cancelling {
                template,
                canceller,
            } => {
                let n = w.frame.len();
                if canceller.as_ref().is_none_or(|c| c.frame_len() != n) {
                    *canceller = Some(Box::new(BurstCanceller::new(
                        template.clone(),
                        n,
                        self.cfg.pfa,
                    )));
                }
                let c = canceller.as_mut().expect("planned above");
                let ranges = w.quiet_ranges(&mut self.gates);
                let pos = abs_pos(&w);
                let predicted = self
                    .last
                    .filter(|_| self.cfg.predict)
                    .map(|(p, lag)| (lag + (pos - p) as f64).round() as i64)
                    .filter(|&l| l > -(n as i64) && l < template.values.len() as i64);
                w.frame.channels[w.source.stop].volts_into(&mut self.volts);
                if self.volts.len() != n {
                    out.push(w);
                    return;
                }
                match c.cancel(&mut self.volts, &ranges, predicted) {
                    Some(found) => {
                        self.last = Some((pos, found.lag));
                        replace_with_volts(&mut w, &mut self.volts);
                        w.report.flags.push(FrameFlag::InterferenceCancelled);
                    }
                    None => self.last = None,
                }
            }
            State::Filtering(plan) => {
                let dt = w.frame.sample_interval_s;
                if plan.as_ref().is_none_or(|p| p.0 != dt) {
                    let f = match self.cfg.method {
                        DenoiseMethod::Notch => ZeroPhaseFilter::notches(
                            &self.cfg.notch_frequencies_hz,
                            self.cfg.notch_q,
                            dt,
                        ),
                        _ => ZeroPhaseFilter::highpass(self.cfg.highpass_hz, dt),
                    };
                    *plan = Some((dt, f));
                }
                w.frame.channels[w.source.stop].volts_into(&mut self.volts);
                plan.as_ref()
                    .expect("planned above")
                    .1
                    .apply(&mut self.volts);
                replace_with_volts(&mut w, &mut self.volts);
            }
            State::Learning { .. } => unreachable!("learning frames are held, not cancelled"),
        }
        out.push(w);
    }
}

/// Makes the stop channel of `w` hold the cleaned `volts` (the channel takes
/// the buffer; name and role stay, no copy of either), leaving spare storage
/// of the unit in `volts` for the next frame.
fn replace_with_volts(w: &mut Work, volts: &mut Vec<f64>) {
    let spare = w.spare_volts();
    w.set_volts(w.source.stop, std::mem::replace(volts, spare));
}

impl Stage for Denoise {
    fn name(&self) -> &'static str {
        "denoise"
    }

    fn process(&mut self, w: Unit, out: &mut Vec<Unit>) -> Result<(), FrameError> {
        if let State::Learning { held, .. } = &self.state {
            let fresh = held.is_empty().then(|| self.learner_for(&w));
            let ranges = w.quiet_ranges(&mut self.gates);
            w.frame.channels[w.source.stop].volts_into(&mut self.volts);
            let State::Learning { learner, held } = &mut self.state else {
                unreachable!("matched above")
            };
            if let Some(l) = fresh {
                *learner = l;
            }
            learner.push(abs_pos(&w), &self.volts, &ranges);
            held.push(w);
            if held.len() >= self.cfg.learn_frames as usize {
                self.finish_learning(out);
            }
            return Ok(());
        }
        self.cancel(w, out);
        Ok(())
    }

    fn flush(&mut self, out: &mut Vec<Unit>) {
        self.finish_learning(out);
    }
}
