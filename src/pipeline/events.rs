//! events: tells each detection's return from an interference event
//! (`detect::events`), drops the events and marks the returns an event
//! overlaps. Learns the waveform of events that repeat
//! (`detect::events::EventTemplate`) and, where it fits a frame, drops the
//! detections that no longer stand above the threshold once the event is
//! taken off. Where the frame holds an event, seeks the returns its
//! troughs hid from the detector (`hidden_returns`; their score is the
//! events test's). A return with an event on it, alone in its window, is timed
//! on the samples less the event fitted under it
//! ([`EventTest::event_under`]). Keeps the false-alarm self-check: the noise
//! gates' excursions are judged as detections are, and those judged events
//! are not counted (see `FrameJudge`). Runs between detect and timing when
//! `[events] enabled`.

use super::detect::FalseAlarmCounter;
use super::{FrameError, GateCount, Stage, Unit};
use crate::detect::events::{EventTemplate, EventTest, EventTestConfig, NoiseTerms, Verdict};
use crate::detect::gates::at_rail;
use crate::detect::return_shape::ReturnShapeLearner;
use crate::dsp::pulse::Shape;
use crate::frame::FrameFlag;
use crate::scene::{EventsConfig, PulseConfig, Scene};

/// Scratch sized for this many detections a frame before any frame needs it.
const MAX_DETECTIONS: usize = 64;

/// Span of the learned event waveform before its strongest lobe, s.
const TEMPLATE_BEFORE_S: f64 = 0.5e-6;

/// Span of the learned event waveform from its strongest lobe on, s (the
/// prototype's events last a fraction of its 2.5 µs frame).
const TEMPLATE_AFTER_S: f64 = 2e-6;

/// The event fitted under a return is taken off before timing where it
/// reaches beyond this many noise sigmas over the pulse's support.
const UNDER_SIGMAS: f64 = 3.0;

/// The events stage.
#[derive(Debug)]
pub struct Events {
    cfg: EventsConfig,
    pulse_cfg: PulseConfig,
    /// Shape and test for the current sampling period.
    plan: Option<(f64, Shape, EventTest)>,
    /// The event waveform learned from the frames' events (see
    /// [`EventTemplate`]), for the current sampling period.
    template: EventTemplate,
    /// Peak indices of the frame's detections (scratch).
    peaks: Vec<f64>,
    /// Verdicts, one per detection (scratch).
    verdicts: Vec<Verdict>,
    /// Where a detection's return was found beside it (scratch; see
    /// `EventTest::set_search`).
    moves: Vec<Option<f64>>,
    /// Sample indices of the frame's event detections (scratch).
    anchors: Vec<usize>,
    /// The event under a return, over its window (scratch).
    under: Vec<f64>,
    /// The sensor's return shape, learned from the first frames with strong
    /// returns and no event; the test takes it where the scene's misfits
    /// (see [`ReturnShapeLearner`]).
    learner: Option<ReturnShapeLearner>,
    /// The false-alarm self-check, counting the noise gates' crossings that
    /// are not judged events (detect leaves the count to this stage).
    false_alarms: FalseAlarmCounter,
    /// The frame's detections then the noise gates' excursions, and their
    /// verdicts (scratch).
    gate_peaks: Vec<f64>,
    gate_verdicts: Vec<Verdict>,
    /// Places a hidden return is sought at: (prominence, index) (scratch).
    candidates: Vec<(f64, usize)>,
    /// Whether the self-check counts the gates yet (see `process`), and
    /// the frames since the test was built (for this sampling period).
    counting: bool,
    warmup: usize,
}

/// Frames after which the self-check counts the gates even where the
/// events test's null is not learned (gates shorter than its window never
/// give one): the 16 windows its null needs, at one a frame.
const WARMUP_FRAMES: usize = 16;

impl Events {
    /// From the scene's `[events]` and return-pulse sections.
    pub fn new(scene: &Scene) -> Events {
        Events {
            cfg: scene.events.clone(),
            pulse_cfg: scene.return_pulse.clone(),
            plan: None,
            template: EventTemplate::default(),
            peaks: Vec::new(),
            verdicts: Vec::new(),
            moves: Vec::new(),
            anchors: Vec::new(),
            under: Vec::new(),
            learner: None,
            false_alarms: FalseAlarmCounter::default(),
            gate_peaks: Vec::new(),
            gate_verdicts: Vec::new(),
            candidates: Vec::new(),
            counting: false,
            warmup: 0,
        }
    }
}

impl Events {
    /// Builds the shape and the test for sampling period `dt` when it changes.
    fn refresh(&mut self, dt: f64) {
        if self.plan.as_ref().is_none_or(|p| p.0 != dt) {
            let cfg = EventTestConfig {
                max_frequency: self.cfg.max_frequency_hz * dt,
                flank: (self.cfg.flank_s / dt).ceil().max(1.0) as usize,
                fit_alpha: self.cfg.fit_alpha,
            };
            let shape = self.pulse_cfg.shape(dt);
            let mut test = EventTest::new(cfg);
            test.reserve(&shape);
            self.learner = Some(ReturnShapeLearner::new(&shape));
            self.plan = Some((dt, shape, test));
            self.template = EventTemplate::new((TEMPLATE_BEFORE_S / dt).ceil() as usize, (TEMPLATE_AFTER_S / dt).ceil() as usize);
            self.counting = false;
            self.warmup = 0;
        }
    }
}

/// Whether the detection at `p` lies from `before` samples before to
/// `after` samples after a detection judged an event.
fn reached(peaks: &[f64], verdicts: &[Verdict], p: f64, before: f64, after: f64) -> bool {
    peaks.iter().zip(verdicts).any(|(&e, v)| matches!(v, Verdict::Event(_)) && p >= e - before && p <= e + after)
}

/// The events test's frame-wide terms, for judging places near the events
/// found in the frame ([`FrameJudge::near_events`], the detections' second
/// pass) and the noise gates' excursions for the false-alarm self-check as
/// the frame's detections are judged ([`FrameJudge::events`]): the test on each, then, where an
/// event found in the frame (among the detections or the excursions)
/// reaches it, the test near an event, repeated while that finds more. The
/// detections' verdicts are not changed. The self-check so counts what
/// the stage would report were the gates range: an event in a gate, or its
/// tail, is not read as false alarms the range gate never reports. (The
/// learned event waveform's second look is left out: the excursions are
/// judged before it, and detections it turns into events do not reach
/// them. Nor are the gates sought for hidden returns: the returns
/// `hidden_returns` reports, right or wrong, are not in the count.)
struct FrameJudge<'a> {
    x: &'a [f64],
    noise: NoiseTerms<'a>,
    /// Threshold, noise sigmas.
    u: f64,
    /// An event's reach before and after its detection, samples.
    before: f64,
    after: f64,
}

impl FrameJudge<'_> {
    /// Judges again, near an event, the places `peaks[from..]` judged
    /// returns that an event found in the frame reaches (their window may
    /// look like noise to step 1 while it holds the event's weak lobe),
    /// repeated while that finds more events; a return found beside its
    /// place moves there (`moved(k, place)` is told).
    fn near_events(&self, test: &mut EventTest, shape: &Shape, peaks: &mut [f64], verdicts: &mut [Verdict], from: usize, mut moved: impl FnMut(usize, f64)) {
        loop {
            let mut found = false;
            for k in from..peaks.len() {
                if verdicts[k] == Verdict::Return && reached(peaks, verdicts, peaks[k], self.before, self.after) {
                    let v = test.judge_near_event(self.x, self.noise, shape, peaks, k, self.u);
                    found |= matches!(v, Verdict::Event(_));
                    verdicts[k] = v;
                    if let Some(m) = test.moved_to() {
                        moved(k, m);
                        peaks[k] = m;
                    }
                }
            }
            if !found {
                break;
            }
        }
    }

    /// The crossings of `excursions` (highest position, crossings) judged
    /// events beside the detections at `peaks` with `verdicts`; `all` and
    /// `all_v` are scratch.
    #[allow(clippy::too_many_arguments)]
    fn events(
        &self,
        test: &mut EventTest,
        shape: &Shape,
        peaks: &[f64],
        verdicts: &[Verdict],
        excursions: &[(usize, u64)],
        all: &mut Vec<f64>,
        all_v: &mut Vec<Verdict>,
    ) -> u64 {
        if excursions.is_empty() {
            return 0;
        }
        let n = peaks.len();
        all.clear();
        all.extend_from_slice(peaks);
        all.extend(excursions.iter().map(|e| e.0 as f64));
        all_v.clear();
        all_v.extend_from_slice(verdicts);
        test.set_search(true);
        for k in n..all.len() {
            let v = test.judge(self.x, self.noise, shape, all, k, self.u);
            all_v.push(v);
            if let Some(m) = test.moved_to() {
                all[k] = m;
            }
        }
        self.near_events(test, shape, all, all_v, n, |_, _| {});
        excursions.iter().zip(&all_v[n..]).filter(|(_, v)| matches!(v, Verdict::Event(_))).map(|(e, _)| e.1).sum()
    }
}

/// Most places a frame's hidden returns are sought at (the most prominent).
const MAX_HIDDEN_CANDIDATES: usize = 16;

/// Most places listed before the most prominent are chosen (scratch room
/// taken once; past it a place replaces the least prominent listed).
const MAX_CANDIDATE_PLACES: usize = 256;

/// Prominence, in detector-output sigmas, that a place needs to be sought
/// for a hidden return: the output's height there above the mean of the
/// output a pulse width before and after it (its second difference over a
/// pulse width), at a local maximum of that prominence. It keeps about three
/// quarters of a pulse's answer and takes off an event's slope and most of
/// its slow curvature; noise alone gives it about one output sigma.
const HIDDEN_PROMINENCE: f64 = 3.0;

/// Returns an event hid from the detector, sought where the frame holds an
/// event (a detection judged one): an event's trough under a return takes
/// the detector's answer down with it, below the threshold (or off its
/// local maximum, on the event's slope), and only the event's crests are
/// detected. Places within an event's reach, in `range`, where the detector
/// output `y` stands [`HIDDEN_PROMINENCE`] output sigmas (`sigma_y`) above
/// its neighbourhood a pulse width each side, and no detection lies within
/// a pulse width, are judged with [`EventTest::judge_hidden`] (the most
/// prominent first, at most [`MAX_HIDDEN_CANDIDATES`]): a return must stand
/// out of the event model (less the clipped samples, with the event's onset
/// where the window shows one) by the threshold and by the model's misfit.
/// Those found are appended to `peaks`, `verdicts` and `moves` (their
/// place); the detections not judged events, within an event's reach, whose
/// window they reach are judged again with them in the model (an event's
/// crest beside a hidden return took the return's answer as its own; an
/// event this finds does not start another round). Returns how many were
/// found. `candidates` is scratch (past [`MAX_CANDIDATE_PLACES`] the least
/// prominent make way). (The test's rails must be set.)
#[allow(clippy::too_many_arguments)]
fn hidden_returns(
    judge: &FrameJudge,
    test: &mut EventTest,
    shape: &Shape,
    y: &[f64],
    range: std::ops::Range<usize>,
    sigma_y: f64,
    peaks: &mut Vec<f64>,
    verdicts: &mut Vec<Verdict>,
    moves: &mut Vec<Option<f64>>,
    candidates: &mut Vec<(f64, usize)>,
) -> usize {
    let d = shape.fwhm().round().max(1.0) as usize;
    let apart = shape.fwhm();
    let end = range.end.min(y.len().saturating_sub(d + 1));
    candidates.clear();
    if !(sigma_y > 0.0) {
        return 0;
    }
    let h = |p: usize| y[p] - 0.5 * (y[p - d] + y[p + d]);
    for p in range.start.max(d + 1)..end {
        let v = h(p);
        if !(v > HIDDEN_PROMINENCE * sigma_y && v > h(p - 1) && v >= h(p + 1)) {
            continue;
        }
        let prominence = v / sigma_y;
        if reached(peaks, verdicts, p as f64, judge.before, judge.after) && !peaks.iter().any(|&o| (o - p as f64).abs() < apart) {
            if candidates.len() < MAX_CANDIDATE_PLACES {
                candidates.push((prominence, p));
            } else if let Some(least) = candidates.iter_mut().min_by(|a, b| a.0.total_cmp(&b.0)).filter(|l| l.0 < prominence) {
                *least = (prominence, p);
            }
        }
    }
    candidates.sort_unstable_by(|a, b| b.0.total_cmp(&a.0));
    candidates.truncate(MAX_HIDDEN_CANDIDATES);
    let before = peaks.len();
    test.set_search(true);
    let reach = test.window_len(shape);
    for &(_, p) in candidates.iter() {
        // Not where a return found already stands.
        if peaks[before..].iter().any(|&o| (o - p as f64).abs() < apart) {
            continue;
        }
        peaks.push(p as f64);
        let k = peaks.len() - 1;
        let v = test.judge_hidden(judge.x, judge.noise, shape, peaks, k, judge.u);
        match (v, test.moved_to()) {
            (Verdict::ReturnWithEvent(_), m) if m.is_none_or(|m| !peaks[..k].iter().any(|&o| (o - m).abs() < apart)) => {
                if let Some(m) = m {
                    peaks[k] = m;
                }
                verdicts.push(v);
                moves.push(Some(peaks[k]));
            }
            _ => {
                peaks.pop();
            }
        }
    }
    let found = peaks.len() - before;
    if found > 0 {
        for k in 0..before {
            if matches!(verdicts[k], Verdict::Event(_))
                || !reached(peaks, verdicts, peaks[k], judge.before, judge.after)
                || !peaks[before..].iter().any(|&h| (h - peaks[k]).abs() < reach as f64)
            {
                continue;
            }
            verdicts[k] = test.judge_near_event(judge.x, judge.noise, shape, peaks, k, judge.u);
            if let Some(m) = test.moved_to() {
                moves[k] = Some(m);
                peaks[k] = m;
            }
        }
    }
    found
}

/// Empties `v` and gives it room for `n` (emptied first: `reserve` counts
/// from the length, so the room is taken once and kept).
fn emptied_with_room<T>(v: &mut Vec<T>, n: usize) {
    v.clear();
    v.reserve(n);
}

impl Stage for Events {
    fn name(&self) -> &'static str {
        "events"
    }

    fn process(&mut self, mut w: Unit, out: &mut Vec<Unit>) -> Result<(), FrameError> {
        let (frame, gates) = (MAX_DETECTIONS + MAX_HIDDEN_CANDIDATES, 2 * MAX_DETECTIONS + MAX_HIDDEN_CANDIDATES);
        emptied_with_room(&mut w.buffers.interfered, MAX_DETECTIONS);
        emptied_with_room(&mut w.buffers.placed, MAX_DETECTIONS);
        emptied_with_room(&mut self.peaks, frame);
        emptied_with_room(&mut self.verdicts, frame);
        emptied_with_room(&mut self.moves, frame);
        emptied_with_room(&mut self.anchors, MAX_DETECTIONS);
        emptied_with_room(&mut self.gate_peaks, gates);
        emptied_with_room(&mut self.gate_verdicts, gates);
        emptied_with_room(&mut self.candidates, MAX_CANDIDATE_PLACES);
        let dt = w.frame.sample_interval_s;
        self.refresh(dt);
        let (_, shape, test) = self.plan.as_mut().expect("set above");
        let noise = NoiseTerms { mean_v: w.noise.summary.mean_v, sigma_v: w.noise.raw_sigma_v, rho: &w.noise.rho };
        // The test's null distribution, learned from this frame's noise gates.
        test.learn_null(&w.buffers.stop_v, noise, &w.buffers.quiet, shape, &w.buffers.gate_band);
        // The self-check counts the gates from the frame on which step 1's
        // null is learned from them (or the WARMUP_FRAMES-th, for gates too
        // short to give its windows): before, the gate screen has no null
        // either, so an event in the gates is in the frame's sigma, and its
        // lobes' crossings pass step 1 against that inflated sigma as noise's
        // would (laser off, Ringing 4 sigma events in every frame: 2 such
        // crossings in the second frame of 2 of 12 runs flagged an excess
        // in 140 of their 600 reports). Those frames' cells and crossings
        // stay out of the count; once started it goes on (a null learned
        // again for a new shape does not stop it).
        self.warmup += 1;
        self.counting |= test.null_learned() || self.warmup >= WARMUP_FRAMES;
        let mut gate_count = w.threshold.gate_count.take();
        if !self.counting {
            gate_count = gate_count.map(|c| GateCount { observed: 0, gate_cells: 0.0, ..c });
            w.buffers.gate_excursions.clear();
        }
        let resolved = !w.buffers.components.is_empty();
        self.peaks.clear();
        if resolved {
            self.peaks.extend(w.buffers.components.iter().map(|c| c.peak_index));
        } else {
            self.peaks.extend(w.buffers.detections.iter().map(|&p| p as f64));
        }
        let (before, after) = ((TEMPLATE_BEFORE_S / dt).ceil(), (TEMPLATE_AFTER_S / dt).ceil());
        if self.peaks.is_empty() {
            if let Some(count) = gate_count {
                let gates = FrameJudge { x: &w.buffers.stop_v, noise, u: w.threshold.u, before, after };
                let events = gates.events(test, shape, &[], &[], &w.buffers.gate_excursions, &mut self.gate_peaks, &mut self.gate_verdicts);
                self.false_alarms.count(&mut w.report, count, events);
            }
            out.push(w);
            return Ok(());
        }
        // Detections not yet fitted may be moved to a return beside them
        // (see `EventTest::set_search`); fitted pulses keep their place.
        test.set_search(!resolved);
        self.verdicts.clear();
        self.moves.clear();
        for k in 0..self.peaks.len() {
            self.verdicts.push(test.judge(&w.buffers.stop_v, noise, shape, &self.peaks, k, w.threshold.u));
            self.moves.push(test.moved_to());
            // The later judgements see the return at its own place.
            if let Some(m) = test.moved_to() {
                self.peaks[k] = m;
            }
        }
        // An event found in the frame reaches the detections around it (its
        // tail lasts a good part of the frame): those step 1 passed must
        // stand out of the event subspace too. Repeated while that finds
        // more events.
        let judge = FrameJudge { x: &w.buffers.stop_v, noise, u: w.threshold.u, before, after };
        let moves = &mut self.moves;
        judge.near_events(test, shape, &mut self.peaks, &mut self.verdicts, 0, |k, m| moves[k] = Some(m));
        let rails = w.source.rails();
        // Returns an event's trough hid from the detector (see `hidden_returns`).
        if !resolved && self.verdicts.iter().any(|v| matches!(v, Verdict::Event(_))) {
            test.set_rails(rails);
            let sigma_y = w.noise.sigma_v * w.threshold.out_gain;
            let found = hidden_returns(
                &judge,
                test,
                shape,
                &w.buffers.detector_output,
                w.noise.gates.range.clone(),
                sigma_y,
                &mut self.peaks,
                &mut self.verdicts,
                &mut self.moves,
                &mut self.candidates,
            );
            // Placed where they were found (below).
            let n = self.peaks.len();
            w.buffers.detections.extend(self.peaks[n - found..].iter().map(|&p| p.round().max(0.0) as usize));
        }
        // The noise gates' excursions, judged beside the frame's detections.
        if let Some(count) = gate_count {
            let events = judge.events(test, shape, &self.peaks, &self.verdicts, &w.buffers.gate_excursions, &mut self.gate_peaks, &mut self.gate_verdicts);
            self.false_alarms.count(&mut w.report, count, events);
        }
        // The frame's event, when it holds one: its detections (the one on
        // the highest sample first) anchor the learned waveform. Where the
        // waveform fits, the detections in its span that step 1 passed must
        // stand above the threshold with the event taken off.
        let x = &w.buffers.stop_v;
        let last = x.len().max(1) - 1;
        self.anchors.clear();
        self.anchors.extend(
            (0..self.peaks.len())
                .filter(|&k| matches!(self.verdicts[k], Verdict::Event(_)))
                .map(|k| self.peaks[k].round().clamp(0.0, last as f64) as usize),
        );
        if let Some(top) = (0..self.anchors.len()).max_by(|&a, &b| x[self.anchors[a]].total_cmp(&x[self.anchors[b]])) {
            self.anchors.swap(0, top);
            let template = &self.template;
            // One alignment serves the fit and the learning (the template changes after both).
            let aligned = template.align(x, noise.mean_v, &self.anchors);
            if let Some(fit) = template.fit(x, noise, aligned, self.cfg.fit_alpha) {
                for k in 0..self.peaks.len() {
                    // Detections step 2 kept already stand out of the event
                    // subspace; those step 1 passed are judged again.
                    if self.verdicts[k] == Verdict::Return && template.covers(fit, self.peaks[k]) {
                        let z = test.pulse_z(x, noise, shape, self.peaks[k], &|j| template.at(fit, j))
                            / (1.0 + template.added_variance(fit)).sqrt();
                        if z <= w.threshold.u {
                            self.verdicts[k] = Verdict::Event(z);
                        }
                    }
                }
            }
            // Every event frame teaches it, less the supports of the
            // detections kept as returns.
            let (lo, hi) = shape.support();
            let (peaks, verdicts) = (&self.peaks, &self.verdicts);
            let kept = |j: usize| {
                peaks.iter().zip(verdicts).any(|(&p, v)| !matches!(v, Verdict::Event(_)) && j as f64 >= p + lo && j as f64 <= p + hi)
            };
            self.template.add(x, noise.mean_v, &self.anchors, aligned, &kept);
        }
        // The sensor's return shape, from frames that hold no event and no
        // sample at a rail: once learned, the test takes it where the
        // scene's misfits.
        if let Some(learner) = self.learner.as_mut().filter(|l| !l.done())
            && !self.verdicts.iter().any(|v| matches!(v, Verdict::Event(_)))
            && !x.iter().any(|&v| at_rail(rails, v))
            && learner.offer(x, noise.mean_v, noise.sigma_v, &self.peaks, shape)
            && let Some(learned) = learner.learned()
        {
            tracing::info!(
                misfit = learned.misfit,
                frames = learned.frames,
                returns = learned.returns,
                fwhm_samples = learned.shape.fwhm(),
                "events: the scene's return shape misfits the sensor's returns; the events test uses the shape learned from them"
            );
            *shape = learned.shape.clone();
            test.forget_pulses();
            test.reserve(shape);
        }
        // A return with an event on it (an event found in the frame whose
        // reach covers it) is timed with the event taken off (its fit over
        // the return's window): the event's lobe under the leading edge would
        // otherwise move the timing point. Only where the fitted event under
        // the pulse stands out of the noise (beyond `UNDER_SIGMAS` σ: a clean
        // return whose shape misfits step 1 leaves a fit of noise and misfit
        // there, and is timed as it is), and not where the window holds a
        // sample at a rail (the fit is not the event there, and the samples
        // keep their saturation).
        let (lo, hi) = shape.support();
        for k in 0..self.peaks.len() {
            let p = self.peaks[k];
            if !matches!(self.verdicts[k], Verdict::ReturnWithEvent(_)) || !reached(&self.peaks, &self.verdicts, p, before, after) {
                continue;
            }
            // Nor where another return shares the window: the fit's event
            // would carry its misfit (shape, place) into both.
            let near = test.window_len(shape) as f64;
            if (0..self.peaks.len()).any(|j| j != k && !matches!(self.verdicts[j], Verdict::Event(_)) && (self.peaks[j] - p).abs() < near) {
                continue;
            }
            let x = &mut w.buffers.stop_v;
            let Some(first) = test.event_under(x, noise, shape, &self.peaks, k, &mut self.under) else { continue };
            let window = &mut x[first..first + self.under.len()];
            if window.iter().any(|&v| at_rail(rails, v)) {
                continue;
            }
            let support = ((p + lo).ceil().max(first as f64) as usize - first)..(((p + hi).floor() + 1.0).max(0.0) as usize).saturating_sub(first).min(self.under.len());
            let under = self.under.get(support).map_or(0.0, |u| u.iter().fold(0.0f64, |m, v| m.max(v.abs())));
            if !(under > UNDER_SIGMAS * noise.sigma_v) {
                continue;
            }
            window.iter_mut().zip(&self.under).for_each(|(v, e)| *v -= e);
        }
        // Returns found beside their detection are timed at their place.
        if !resolved {
            let last = w.buffers.stop_v.len().saturating_sub(1) as f64;
            for ((d, m), v) in w.buffers.detections.iter_mut().zip(&self.moves).zip(&self.verdicts) {
                if let Some(m) = m {
                    *d = m.round().clamp(0.0, last) as usize;
                    // The detector's output there is not what found it.
                    if let Verdict::ReturnWithEvent(z) = v {
                        w.buffers.placed.push((*d, z / w.threshold.u));
                    }
                }
            }
        }
        let mut dropped = 0;
        let mut k = 0;
        let verdicts = &self.verdicts;
        let interfered = &mut w.buffers.interfered;
        let mut keep = |at: usize| {
            let v = verdicts[k];
            k += 1;
            match v {
                Verdict::Return => true,
                Verdict::ReturnWithEvent(_) => {
                    interfered.push(at);
                    true
                }
                Verdict::Event(_) => {
                    dropped += 1;
                    false
                }
            }
        };
        if resolved {
            w.buffers.components.retain(|c| keep(c.detected_at));
        } else {
            w.buffers.detections.retain(|&p| keep(p));
        }
        if dropped > 0 {
            w.report.flags.push(FrameFlag::InterferenceEvents(dropped));
        }
        out.push(w);
        Ok(())
    }
}
