//! One sensor's pipeline on several threads, with the single-thread results.
//!
//! The stages are cut into consecutive segments, one thread each (a stage
//! pipeline): segment 0 validates frame k + 1 while segment 1 detects in
//! frame k. On two threads the cut may instead be a ring of three segments,
//! the first and last on one thread (which takes new frames and the middle
//! segment's output from one queue) and the middle on the other: a heavy
//! stage in the middle no longer leaves one thread with everything after
//! it. Every stage still sees exactly the calls it would see in
//! [`Pipeline`] — the same units, in the same order, then the same flush —
//! so every piece of running state (the start method's mismatch gap, the
//! baseline's drift, the averaging group in progress, the forgetting noise
//! model, the pooled colour, the false-alarm counters, the timing floor) is
//! updated in frame order on one thread, and the reports are bit-identical to
//! the single-thread run whatever the cut. What the cut changes is only how
//! fast: the slowest segment sets the pace. The first frames run on the
//! calling thread, the later of them timed stage by stage, and the cut that
//! balances those times best is used from then on. Once start-up has passed
//! ([`REPILOT_AT`] frames), the stages come back to the calling thread, are
//! timed there once more (a second pilot, now on the steady state's costs),
//! and are cut again for good.
//!
//! Units that finish (their report went out, or averaging consumed them) go
//! back to segment 0, whose validate stage reuses their buffers.

use super::{retire, FrameError, Observer, Pipeline, Stage, Unit};
use crate::frame::{Frame, NoiseSummary, Report};
use crate::scene::Scene;
use std::sync::mpsc::{channel, sync_channel, Receiver, Sender, SyncSender};
use std::time::Instant;

/// What one pushed frame gave: exactly what [`Pipeline::push`] gives for it.
#[derive(Debug)]
pub struct Outcome {
    /// The reports it completed (0 while an average fills, more when a group closes).
    pub reports: Vec<Report>,
    /// Why it (or a unit it completed) was refused, if it was.
    pub result: Result<(), FrameError>,
    /// A stage panicked on it: the message (its unit is lost, the stage rebuilt).
    pub panic: Option<String>,
}

/// Frames per message between threads: amortises the hand-over (a wake-up
/// costs a few microseconds) without holding many frames in flight.
const CHUNK: usize = 8;
/// Longest wait in [`Staged::settle_while`] before it asks again whether input has come.
const SETTLE_POLL: std::time::Duration = std::time::Duration::from_micros(100);
/// Messages a segment of the chain may hold queued ahead of it.
const QUEUE: usize = 4;
/// Most frames in flight in the ring (its queues are unbounded: this is
/// their bound): sixteen chunks, so that each of its queues can hold work
/// while the calling thread, which feeds it, is off the core.
const RING_IN_FLIGHT: usize = 16 * CHUNK;

/// What every stage thread's name starts with (`tofwave-seg0`, `-seg1`, …;
/// the ring's `tofwave-seg0+2` and `tofwave-seg1`): how tools tell them
/// from the process's other threads.
pub const SEGMENT_THREAD_PREFIX: &str = "tofwave-seg";

/// About the most frames pushed to a pipeline on `threads` threads whose
/// outcome has not come out: the ring's limit, or each segment of a chain
/// with its queue full and a chunk in hand, and the chunk being filled.
/// (A caller that stops taking outcomes lets the chain's last queue grow.)
pub fn most_in_flight(threads: usize) -> usize {
    RING_IN_FLIGHT.max(threads * (QUEUE + 1) * CHUNK) + CHUNK
}

/// Frames run on one thread first whose step times are not used: the
/// pipeline's start-up (plans built, error tables measured, the pooled colour
/// and the thresholds it sets still settling) costs far more per frame than
/// the steady state the cut is for.
pub const PILOT_WARMUP: usize = 200;
/// Frames after those, still on one thread, whose step times choose the cut.
const PILOT_TIMED: usize = 200;
/// Frames a pipeline on several threads runs on the calling thread before
/// its stages go to their threads.
pub const PILOT_FRAMES: usize = PILOT_WARMUP + PILOT_TIMED;
/// Frames pushed after which a pipeline on threads brings its stages back
/// to the calling thread once, times them there for [`PILOT_TIMED`] frames
/// more (the second pilot) and cuts them again by those times, for good.
/// The first pilot runs while start-up still costs: the detect stage pools
/// the noise colour from every unit, and solves the detector's thresholds
/// again for each new estimate, until the colour rests on 10⁶ gate samples
/// (some 800 units of the prototype's gates; by this many frames, those of
/// any gates of more than 500 samples where frames are not averaged, of
/// more than 500·N where they are averaged N to a unit), and from one unit
/// in eight after that. Its shares of the first pilot's time can then be
/// far from the steady state's, enough to choose the wrong cut.
pub const REPILOT_AT: usize = 2000;
/// Frames after which a pipeline on several threads keeps its cut (the
/// second pilot's end): the start of its steady state.
pub const SETTLED_FRAMES: usize = REPILOT_AT + PILOT_TIMED;

/// One push's units on their way through the segments.
struct InFlight {
    units: Vec<Unit>,
    result: Result<(), FrameError>,
    /// A stage's flush made these (not a frame).
    flush: bool,
    /// A stage panicked on this frame.
    panic: Option<String>,
}

enum Msg {
    /// The units of one push (or of one stage's flush, whose errors
    /// [`Pipeline::flush`] ignores).
    Push(InFlight),
    /// End of input: flush the segment's stages in order, then pass it on.
    Flush,
    /// Pass it on, then end the thread, handing its stages back unflushed
    /// (see [`Parts`]).
    HandBack,
}

/// How a run of messages left a segment.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Ended {
    /// It carries on.
    No,
    /// The end of input passed (its stages flushed).
    Flushed,
    /// A hand-back passed: the thread returns its stages.
    HandedBack,
}

/// What a stage thread returns when a hand-back reaches it: each run of its
/// stages with the pipeline index of the run's first stage, and on the head
/// thread its validate stage, its spare units and their queue. Empty where
/// the thread ended otherwise (end of input, or its queue gone).
#[derive(Default)]
struct Parts {
    head: Option<(super::validate::Validate, Vec<Unit>, Receiver<Unit>)>,
    runs: Vec<(usize, Vec<Box<dyn Stage>>)>,
}

/// How the stages were cut: the stage names of each segment, and the pilot
/// run's share of the time per segment (empty when no pilot ran).
#[derive(Debug, Clone, PartialEq)]
pub struct Cut {
    /// Stage names per segment (validate first in segment 0).
    pub segments: Vec<Vec<&'static str>>,
    /// Fraction of the pilot's time each segment took (sums to 1).
    pub shares: Vec<f64>,
    /// The frames (first and last, counted from 1) whose stage times chose
    /// the cut: the first pilot's, or once [`SETTLED_FRAMES`] frames have
    /// been pushed, the second's (None before a pilot ends).
    pub pilot: Option<(usize, usize)>,
    /// Each stage's mean time per frame over the pilot's timed frames, s
    /// (validate first; empty when no pilot ran).
    pub stage_s: Vec<(&'static str, f64)>,
    /// The thread each segment runs on (0, 1, … one each; on two threads
    /// the ring `[0, 1, 0]`: the first and last segments share thread 0).
    pub threads: Vec<usize>,
}

impl std::fmt::Display for Cut {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for (i, s) in self.segments.iter().enumerate() {
            if i > 0 {
                write!(f, " | ")?;
            }
            write!(f, "{}", s.join("+"))?;
            if let Some(share) = self.shares.get(i) {
                write!(f, " ({:.0} %)", share * 100.0)?;
            }
        }
        if self.threads.len() == 3 && self.threads[0] == self.threads[2] {
            write!(f, "; the first and last on one thread")?;
        }
        Ok(())
    }
}

/// Runs `frames` through `scene`'s pipeline on up to `threads` threads and
/// calls `each` with every frame's outcome, in frame order, then once more
/// with the reports the final flush completes. The reports are those of
/// [`Pipeline::push`] + [`Pipeline::flush`], bit for bit. `threads` ≤ 1 runs
/// on the calling thread. Each outcome's reports are lent to `each`, then
/// reused ([`Staged::recycle`]): a report to keep is cloned.
pub fn run<I, F>(scene: &Scene, sensor: &str, threads: usize, frames: I, mut each: F) -> Cut
where
    I: IntoIterator<Item = Frame>,
    F: FnMut(&Outcome),
{
    let mut staged = Staged::new(scene, sensor, threads);
    let mut out = Vec::new();
    for frame in frames {
        staged.push(frame, &mut out);
        for o in out.drain(..) {
            each(&o);
            staged.recycle(o.reports);
        }
    }
    let flushed = staged.finish(&mut out);
    out.iter().for_each(&mut each);
    each(&flushed);
    staged.cut()
}

/// One sensor's pipeline, on the calling thread or cut over threads: frames
/// go in with [`Staged::push`], outcomes come out in frame order, one per
/// pushed frame (with the stages on threads, a few pushes later; at once
/// after [`Staged::sync`]).
///
/// With more than one thread the first frames run on the calling thread
/// (the pilot: start-up, then the stages timed); from then on the stages
/// run on one thread per segment of the cut, and the calling thread only
/// hands frames in and takes outcomes out, except for the second pilot
/// (frames [`REPILOT_AT`] + 1 to [`SETTLED_FRAMES`], on the calling thread
/// again), after which the stages are cut again for good.
///
/// A stage that panics costs the unit it held (its frame's outcome says so)
/// and its own running state: that stage is rebuilt from the scene, and the
/// other frames and the other stages carry on. (On one thread the whole
/// pipeline is rebuilt, as a fresh one.)
pub struct Staged {
    threads: usize,
    /// The scene and sensor the pipeline was built for: a stage (or the
    /// whole pipeline) is built afresh from them after a panic.
    rebuild: Rebuild,
    mode: Mode,
    observer: Option<Observer>,
    last_noise: Option<NoiseSummary>,
    /// Stage names, validate first.
    names: Vec<&'static str>,
    cut: Option<Cut>,
    /// Two threads: the ring (true), the chain (false), or by the pilot (None).
    ring: Option<bool>,
    /// Frames pushed so far.
    pushed: usize,
}

impl std::fmt::Debug for Staged {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Staged").field("sensor", &self.rebuild.sensor).field("threads", &self.threads).field("cut", &self.cut).finish()
    }
}

enum Mode {
    /// On the calling thread: the pilot's step times, and emptied report
    /// lists handed back by [`Staged::recycle`].
    Local { pipeline: Box<Pipeline>, costs: Vec<f64>, lists: Vec<Vec<Report>> },
    /// The segments on their threads.
    Split(Pool),
    /// Finished.
    Done,
}

/// The threads of a cut pipeline and the channels to them.
struct Pool {
    frames: Option<FramesTx>,
    /// Most frames in flight before `push` waits for outcomes (the ring's
    /// queues are unbounded, this bounds them; the chain's bounded queues
    /// hold the caller back themselves).
    limit: usize,
    /// Frames pushed and not yet sent (sent by the chunk).
    pending: Vec<Frame>,
    out: Receiver<Vec<Msg>>,
    spare_tx: Sender<Unit>,
    /// Finished units on their way back to the head.
    back: Vec<Unit>,
    /// Frames sent whose outcome has not come back.
    in_flight: usize,
    /// What the stages' final flushes completed.
    flushed: Vec<Report>,
    /// Reports and emptied report lists handed back by [`Staged::recycle`]:
    /// the next outcomes' lists, and their reports' storage (a report goes
    /// back to the head in its unit and is filled again there).
    spare_reports: Vec<Report>,
    lists: Vec<Vec<Report>>,
    handles: Vec<std::thread::JoinHandle<Parts>>,
}

/// Most reports, and most report lists, [`Staged::recycle`] keeps once the
/// stages are on threads: twice the most frames the ring holds in flight
/// (the chain's bounded queues hold fewer), so that a caller recycling
/// every outcome is always given back as many as are in flight.
const RECYCLED: usize = 2 * RING_IN_FLIGHT;

impl Staged {
    /// A pipeline for `scene` on up to `threads` threads (≤ 1: the calling thread only).
    pub fn new(scene: &Scene, sensor: &str, threads: usize) -> Staged {
        let pipeline = Box::new(Pipeline::new(scene, sensor));
        let names = pipeline.stage_names();
        let costs = vec![0.0; names.len()];
        Staged {
            threads: threads.clamp(1, costs.len()),
            rebuild: Rebuild { scene: scene.clone(), sensor: sensor.to_string(), first: 0 },
            mode: Mode::Local { pipeline, costs, lists: Vec::new() },
            observer: None,
            last_noise: None,
            names,
            cut: None,
            ring: None,
            pushed: 0,
        }
    }

    /// On two threads, the ring (`Some(true)`, wherever there are three
    /// stages or more), the chain (`Some(false)`), or whichever the pilot's
    /// stage times favour (`None`, the default), at each pilot's cut. For
    /// tests and experiments; call it before the first pilot ends.
    pub fn prefer_ring(&mut self, ring: Option<bool>) {
        self.ring = ring;
    }

    /// Calls `f` with every finished unit of work (on the calling thread).
    pub fn set_observer(&mut self, f: Observer) {
        match &mut self.mode {
            Mode::Local { pipeline, .. } => pipeline.set_observer(f),
            _ => self.observer = Some(f),
        }
    }

    /// The latest report's noise model, once a report has come out.
    pub fn noise_model(&self) -> Option<NoiseSummary> {
        self.last_noise
    }

    /// The scene the pipeline was built from.
    pub fn scene(&self) -> &Scene {
        &self.rebuild.scene
    }

    /// How the stages are cut (one segment until the first pilot has
    /// chosen; the latest pilot's choice after, the first's while the
    /// second pilot runs on the calling thread).
    pub fn cut(&self) -> Cut {
        self.cut.clone().unwrap_or_else(|| Cut {
            segments: vec![self.names.clone()],
            shares: vec![1.0],
            pilot: None,
            stage_s: Vec::new(),
            threads: vec![0],
        })
    }

    /// Frames pushed whose outcome has not come out yet.
    pub fn in_flight(&self) -> usize {
        match &self.mode {
            Mode::Split(pool) => pool.in_flight + pool.pending.len(),
            _ => 0,
        }
    }

    /// Takes back an outcome's reports (its list and the reports in it,
    /// once read) so that later outcomes reuse their storage instead of
    /// allocating, as [`Pipeline::recycle`] does for a pipeline.
    pub fn recycle(&mut self, mut reports: Vec<Report>) {
        let lists = match &mut self.mode {
            Mode::Local { pipeline, lists, .. } => {
                pipeline.recycle(&mut reports);
                lists
            }
            Mode::Split(pool) => {
                let room = RECYCLED.saturating_sub(pool.spare_reports.len());
                // (What `take` leaves, the drain drops.)
                pool.spare_reports.extend(reports.drain(..).take(room));
                &mut pool.lists
            }
            Mode::Done => return,
        };
        if lists.len() < RECYCLED {
            lists.push(reports);
        }
    }

    /// Processes `frame`; appends the outcomes that are ready (this frame's
    /// and earlier ones', in order) to `out`.
    pub fn push(&mut self, frame: Frame, out: &mut Vec<Outcome>) {
        if self.pushed == REPILOT_AT && matches!(self.mode, Mode::Split(_)) {
            self.hand_back(out);
        }
        let seen = self.pushed;
        self.pushed += 1;
        match &mut self.mode {
            Mode::Local { pipeline, costs, lists } => {
                let timed = self.threads > 1 && seen >= PILOT_WARMUP;
                // A pilot rebuilds only the stage that panicked (as the
                // stage threads do); one thread, the whole pipeline.
                let run = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    if self.threads > 1 {
                        push_timed(pipeline, frame, timed.then_some(costs.as_mut_slice()), lists.pop().unwrap_or_default(), Some(&self.rebuild))
                    } else {
                        let mut reports = lists.pop().unwrap_or_default();
                        let result = pipeline.push(frame, &mut reports);
                        (reports, result, None)
                    }
                }));
                let outcome = match run {
                    Ok((reports, result, panic)) => Outcome { reports, result, panic },
                    Err(panic) => {
                        **pipeline = fresh(&self.rebuild, pipeline.observer.take());
                        Outcome { reports: Vec::new(), result: Ok(()), panic: Some(panic_message(panic.as_ref())) }
                    }
                };
                if let Some(n) = pipeline.noise_model() {
                    self.last_noise = Some(n);
                }
                out.push(outcome);
                // Each pilot's end (on several threads the pipeline is here
                // only up to the first and within the second).
                if self.threads > 1 && (self.pushed == PILOT_FRAMES || self.pushed >= SETTLED_FRAMES) {
                    self.split();
                }
            }
            Mode::Split(pool) => {
                pool.pending.push(frame);
                if pool.pending.len() >= CHUNK {
                    pool.send();
                }
                pool.collect(false, &mut self.observer, &mut self.last_noise, out);
                while pool.in_flight > pool.limit {
                    let Ok(msgs) = pool.out.recv() else { break };
                    pool.take(msgs, &mut self.observer, &mut self.last_noise, out);
                }
            }
            Mode::Done => panic!("Staged::push after finish"),
        }
    }

    /// Waits until every pushed frame's outcome is in `out`.
    pub fn sync(&mut self, out: &mut Vec<Outcome>) {
        if let Mode::Split(pool) = &mut self.mode {
            pool.send();
            pool.collect(true, &mut self.observer, &mut self.last_noise, out);
        }
    }

    /// [`sync`](Self::sync) for as long as `idle()` holds: the pending
    /// frames go to the threads and outcomes are taken as they come back,
    /// until none is in flight or `idle()` turns false (checked after each
    /// outcome, and at least every [`SETTLE_POLL`]). A caller whose input
    /// ran dry gets its outcomes at once, as with `sync`; when input comes
    /// back while it waits, it feeds the threads again at once, instead of
    /// letting them run dry while the last frames finish.
    pub fn settle_while(&mut self, idle: impl Fn() -> bool, out: &mut Vec<Outcome>) {
        let Mode::Split(pool) = &mut self.mode else { return };
        pool.send();
        pool.collect(false, &mut self.observer, &mut self.last_noise, out);
        while pool.in_flight > 0 && idle() {
            match pool.out.recv_timeout(SETTLE_POLL) {
                Ok(msgs) => pool.take(msgs, &mut self.observer, &mut self.last_noise, out),
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
            }
        }
    }

    /// End of input: every pushed frame's outcome goes to `out`, and the
    /// reports the stages' flush completes (averages in progress) are
    /// returned as one more outcome. The threads are joined.
    pub fn finish(&mut self, out: &mut Vec<Outcome>) -> Outcome {
        self.sync(out);
        let mut reports = Vec::new();
        match std::mem::replace(&mut self.mode, Mode::Done) {
            Mode::Local { mut pipeline, .. } => {
                pipeline.flush(&mut reports);
                if let Some(n) = pipeline.noise_model() {
                    self.last_noise = Some(n);
                }
            }
            Mode::Split(mut pool) => {
                pool.frames = None;
                pool.collect(true, &mut self.observer, &mut self.last_noise, out);
                while let Ok(msgs) = pool.out.recv() {
                    pool.take(msgs, &mut self.observer, &mut self.last_noise, out);
                }
                reports = std::mem::take(&mut pool.flushed);
                for h in pool.handles.drain(..) {
                    let _ = h.join();
                }
            }
            Mode::Done => {}
        }
        Outcome { reports, result: Ok(()), panic: None }
    }

    /// Brings the stages back from their threads to the calling thread, as
    /// they are (nothing flushed), for the second pilot: every frame in
    /// flight first finishes, its outcome to `out`; then the hand-back goes
    /// through the threads (on the ring, round and back to the head), each
    /// passing it on and returning its stages.
    fn hand_back(&mut self, out: &mut Vec<Outcome>) {
        self.sync(out);
        let Mode::Split(mut pool) = std::mem::replace(&mut self.mode, Mode::Done) else { return };
        // (The frames' queue is dropped only once the threads have ended:
        // dropping the ring's tells its head the input has ended.)
        let sent = pool.frames.as_ref().is_some_and(|tx| tx.send(HeadMsg::HandBack));
        let (mut head, mut runs) = (None, Vec::new());
        for h in pool.handles.drain(..) {
            // (A thread cannot panic out: its stages' panics are caught.)
            if let Ok(parts) = h.join() {
                head = head.or(parts.head);
                runs.extend(parts.runs);
            }
        }
        runs.sort_by_key(|r| r.0);
        let stages: Vec<Box<dyn Stage>> = runs.into_iter().flat_map(|r| r.1).collect();
        let observer = self.observer.take();
        let pipeline = match head {
            Some((validate, mut spare, spare_rx)) if sent && stages.len() + 1 == self.names.len() => {
                spare.extend(spare_rx.try_iter());
                spare.append(&mut pool.back);
                Pipeline {
                    scene: self.rebuild.scene.clone(),
                    sensor: self.rebuild.sensor.clone(),
                    validate,
                    stages,
                    last_noise: self.last_noise,
                    observer,
                    entering: Vec::new(),
                    leaving: Vec::new(),
                    spare,
                    spare_reports: std::mem::take(&mut pool.spare_reports),
                }
            }
            _ => {
                // (Not seen: the threads catch their stages' panics.)
                tracing::error!(sensor = %self.rebuild.sensor, "the stage threads did not hand their stages back: the pipeline starts afresh");
                debug_assert!(false, "the stage threads did not hand their stages back");
                fresh(&self.rebuild, observer)
            }
        };
        self.mode = Mode::Local { pipeline: Box::new(pipeline), costs: vec![0.0; self.names.len()], lists: std::mem::take(&mut pool.lists) };
    }

    /// Cuts the stages by the pilot's times and starts their threads.
    fn split(&mut self) {
        let Mode::Local { pipeline, costs, lists, .. } = std::mem::replace(&mut self.mode, Mode::Done) else {
            return;
        };
        let mut pipeline = *pipeline;
        self.observer = pipeline.observer.take();
        let names = self.names.clone();
        // No stage took measurable time: cut evenly by count.
        let even = costs.iter().sum::<f64>() <= 0.0;
        let costs: Vec<f64> = if even { vec![1.0; costs.len()] } else { costs };
        let chain = partition(&costs, self.threads);
        // Two threads: the ring (first and last segments on one thread) where
        // it sets a pace at least RING_GAIN of the chain's.
        let ring = if self.threads == 2 { ring_partition(&costs) } else { None };
        let (bounds, threads) = match (ring, self.ring) {
            (Some(r), Some(true)) => (r, vec![0, 1, 0]),
            (Some(r), None) if ring_pace(&costs, &r) < RING_GAIN * chain_pace(&costs, &chain) => (r, vec![0, 1, 0]),
            _ => (chain.clone(), (0..chain.len() - 1).collect()),
        };
        let total: f64 = costs.iter().sum();
        let cut = Cut {
            segments: bounds.windows(2).map(|b| names[b[0]..b[1]].to_vec()).collect(),
            shares: bounds.windows(2).map(|b| costs[b[0]..b[1]].iter().sum::<f64>() / total).collect(),
            pilot: Some((self.pushed + 1 - PILOT_TIMED, self.pushed)),
            stage_s: if even { Vec::new() } else { names.iter().zip(&costs).map(|(n, c)| (*n, c / PILOT_TIMED as f64)).collect() },
            threads: threads.clone(),
        };
        tracing::info!(sensor = %self.rebuild.sensor, threads = self.threads, cut = %cut, "stages cut over threads");
        self.cut = Some(cut);
        // Cost index 0 is validate; pipeline stage i is cost index i + 1.
        let mut all = std::mem::take(&mut pipeline.stages);
        let mut groups: Vec<(usize, Vec<Box<dyn Stage>>)> = Vec::new();
        for b in bounds.windows(2).rev() {
            let first = b[0].saturating_sub(1);
            groups.push((first, all.split_off(first)));
        }
        groups.reverse();
        let spare = std::mem::take(&mut pipeline.spare);
        let (spare_tx, spare_rx) = channel::<Unit>();
        let rebuild = |first: usize| Rebuild { first, ..self.rebuild.clone() };
        if threads == [0, 1, 0] {
            let [(f0, g0), (f1, g1), (f2, g2)]: [(usize, Vec<Box<dyn Stage>>); 3] = groups.try_into().ok().expect("three segments");
            let (head_tx, head_rx) = channel::<HeadMsg>();
            // Unbounded as the head's own queue is: the head thread never
            // waits to hand a chunk on (it would leave the last segment's
            // work queued behind it idle); `limit` bounds what is in flight.
            let (mid_tx, mid_rx) = channel::<Vec<Msg>>();
            let (out_tx, out_rx) = channel::<Vec<Msg>>();
            let (back, spare_b, r1) = (head_tx.clone(), spare_tx.clone(), rebuild(f1));
            let mid = std::thread::Builder::new().name(format!("{SEGMENT_THREAD_PREFIX}1")).spawn(move || segment(g1, mid_rx, Out::Back(back), spare_b, r1));
            let (r0, r2) = (rebuild(f0), rebuild(f2));
            let validate = pipeline.validate;
            let ends = Ends { first: g0, last: g2, rebuild_first: r0, rebuild_last: r2 };
            let head = std::thread::Builder::new()
                .name(format!("{SEGMENT_THREAD_PREFIX}0+2"))
                .spawn(move || ring_head(validate, spare, spare_rx, head_rx, mid_tx, out_tx, ends));
            self.mode = Mode::Split(Pool {
                frames: Some(FramesTx::Ring(head_tx)),
                limit: RING_IN_FLIGHT,
                pending: Vec::with_capacity(CHUNK),
                out: out_rx,
                spare_tx,
                back: Vec::new(),
                in_flight: 0,
                flushed: Vec::new(),
                spare_reports: std::mem::take(&mut pipeline.spare_reports),
                lists,
                handles: vec![head.expect("spawning a pipeline thread"), mid.expect("spawning a pipeline thread")],
            });
            return;
        }
        let (frames_tx, frames_rx) = sync_channel::<HeadMsg>(QUEUE);
        let mut handles = Vec::new();
        let mut input: Option<Receiver<Vec<Msg>>> = None;
        let mut head = Some((pipeline.validate, spare, spare_rx, frames_rx));
        let count = groups.len();
        for (i, (first, group)) in groups.into_iter().enumerate() {
            // The last segment's output is unbounded: the calling thread
            // drains it only between pushes, and must never block a segment
            // that blocks it in turn.
            let (tx, rx) = if i + 1 == count {
                let (tx, rx) = channel::<Vec<Msg>>();
                (Out::Last(tx), rx)
            } else {
                let (tx, rx) = sync_channel::<Vec<Msg>>(QUEUE);
                (Out::Next(tx), rx)
            };
            let rebuild = rebuild(first);
            let name = format!("{SEGMENT_THREAD_PREFIX}{i}");
            let handle = match head.take() {
                Some((validate, spare, spare_rx, frames_rx)) => std::thread::Builder::new()
                    .name(name)
                    .spawn(move || head_segment(validate, spare, spare_rx, frames_rx, group, tx, rebuild)),
                None => {
                    let from = input.take().expect("an earlier segment");
                    let spare_tx = spare_tx.clone();
                    std::thread::Builder::new().name(name).spawn(move || segment(group, from, tx, spare_tx, rebuild))
                }
            };
            handles.push(handle.expect("spawning a pipeline thread"));
            input = Some(rx);
        }
        self.mode = Mode::Split(Pool {
            frames: Some(FramesTx::Chain(frames_tx)),
            limit: usize::MAX,
            pending: Vec::with_capacity(CHUNK),
            out: input.expect("at least one segment"),
            spare_tx,
            back: Vec::new(),
            in_flight: 0,
            flushed: Vec::new(),
            spare_reports: std::mem::take(&mut pipeline.spare_reports),
            lists,
            handles,
        });
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if let Mode::Split(pool) = &mut self.mode {
            pool.frames = None;
            while pool.out.recv().is_ok() {}
            for h in pool.handles.drain(..) {
                let _ = h.join();
            }
        }
    }
}

/// Each stage's mean time per frame, s (validate first), over `frames`
/// on one pipeline on the calling thread, the first `warmup` frames left
/// out (start-up: plans, error tables, the pooled colour settling). The
/// clock is read around each stage (wall time: a loaded machine charges
/// its waits to whichever stage was running).
pub fn stage_times(scene: &Scene, frames: &[Frame], warmup: usize) -> Vec<(&'static str, f64)> {
    let mut pipeline = Pipeline::new(scene, "stage-times");
    let names = pipeline.stage_names();
    let mut costs = vec![0.0; names.len()];
    let mut timed = 0usize;
    for (i, f) in frames.iter().enumerate() {
        let on = i >= warmup;
        let _ = push_timed(&mut pipeline, f.clone(), on.then_some(costs.as_mut_slice()), Vec::new(), None);
        timed += on as usize;
    }
    names.into_iter().zip(costs).map(|(n, c)| (n, c / timed.max(1) as f64)).collect()
}

/// A fresh pipeline for `rebuild`'s scene and sensor, with `observer`.
fn fresh(rebuild: &Rebuild, observer: Option<Observer>) -> Pipeline {
    let mut p = Pipeline::new(&rebuild.scene, &rebuild.sensor);
    p.observer = observer;
    p
}

/// One frame through `pipeline` stage by stage, each stage's time added to
/// `costs` (index 0 validate) when given; its reports go to `reports` (a
/// recycled list), each leaving a recycled report in its unit, as
/// [`Pipeline::push`] does. With `rebuild`, a stage (or validate) that
/// panics is built afresh and the panic's message returned, as on the
/// stage threads; without, the panic goes on up.
fn push_timed(
    pipeline: &mut Pipeline,
    frame: Frame,
    mut costs: Option<&mut [f64]>,
    mut reports: Vec<Report>,
    rebuild: Option<&Rebuild>,
) -> (Vec<Report>, Result<(), FrameError>, Option<String>) {
    let (mut units, mut leaving, mut retired) = (Vec::new(), Vec::new(), Vec::new());
    let t0 = Instant::now();
    let (mut result, mut panic) = match rebuild {
        None => (pipeline.validate.process(frame, &mut pipeline.spare, &mut units), None),
        Some(r) => validate_caught(&mut pipeline.validate, frame, &mut pipeline.spare, &mut units, r),
    };
    if let Some(c) = costs.as_deref_mut() {
        c[0] += t0.elapsed().as_secs_f64();
    }
    if result.is_ok() && panic.is_none() {
        for (i, stage) in pipeline.stages.iter_mut().enumerate() {
            let t0 = Instant::now();
            run_stages(std::slice::from_mut(stage), &mut units, &mut leaving, &mut result, &mut retired, &mut panic, rebuild.map(|r| (r, i)));
            if let Some(c) = costs.as_deref_mut() {
                c[i + 1] += t0.elapsed().as_secs_f64();
            }
        }
    }
    pipeline.spare.append(&mut retired);
    for mut w in units.drain(..) {
        if let Some(f) = &mut pipeline.observer {
            f(&w);
        }
        pipeline.last_noise = Some(w.report.noise);
        reports.push(std::mem::replace(&mut w.report, pipeline.spare_reports.pop().unwrap_or_default()));
        retire(&mut pipeline.spare, w);
    }
    (reports, result, panic)
}

impl Pool {
    /// Sends the pending frames as one chunk (on the chain, blocks while the head's queue is full).
    fn send(&mut self) {
        if self.pending.is_empty() {
            return;
        }
        let chunk = std::mem::replace(&mut self.pending, Vec::with_capacity(CHUNK));
        self.in_flight += chunk.len();
        if let Some(tx) = &self.frames
            && !tx.send(HeadMsg::Frames(chunk))
        {
            // The head is gone (it cannot panic out: stages are caught).
            self.frames = None;
        }
    }

    /// Takes the outcomes that have come back; with `all`, waits for every frame in flight.
    fn collect(&mut self, all: bool, observer: &mut Option<Observer>, noise: &mut Option<NoiseSummary>, out: &mut Vec<Outcome>) {
        loop {
            let msgs = if all && self.in_flight > 0 {
                match self.out.recv() {
                    Ok(m) => m,
                    Err(_) => break,
                }
            } else {
                match self.out.try_recv() {
                    Ok(m) => m,
                    Err(_) => break,
                }
            };
            self.take(msgs, observer, noise, out);
        }
    }

    /// Units become reports (seen by the observer first); their buffers go back to the head.
    fn take(&mut self, msgs: Vec<Msg>, observer: &mut Option<Observer>, noise: &mut Option<NoiseSummary>, out: &mut Vec<Outcome>) {
        for msg in msgs {
            let Msg::Push(inflight) = msg else { continue };
            let mut reports = self.lists.pop().unwrap_or_else(|| Vec::with_capacity(inflight.units.len()));
            for mut w in inflight.units {
                if let Some(f) = observer {
                    f(&w);
                }
                *noise = Some(w.report.noise);
                reports.push(std::mem::replace(&mut w.report, self.spare_reports.pop().unwrap_or_default()));
                retire(&mut self.back, w);
            }
            self.back.drain(..).for_each(|w| drop(self.spare_tx.send(w)));
            if inflight.flush {
                self.flushed.extend(reports);
            } else {
                self.in_flight = self.in_flight.saturating_sub(1);
                out.push(Outcome { reports, result: inflight.result, panic: inflight.panic });
            }
        }
    }
}

/// Where a segment sends what it passed on.
enum Out {
    Next(SyncSender<Vec<Msg>>),
    Last(Sender<Vec<Msg>>),
    /// Back to the ring's head thread (its last segment).
    Back(Sender<HeadMsg>),
}

impl Out {
    fn send(&self, msgs: Vec<Msg>) -> bool {
        match self {
            Out::Next(tx) => tx.send(msgs).is_ok(),
            Out::Last(tx) => tx.send(msgs).is_ok(),
            Out::Back(tx) => tx.send(HeadMsg::Back(msgs)).is_ok(),
        }
    }
}

/// What a head thread is sent: frames from the calling thread, the
/// middle segment's output (the ring's), the end of input (the ring's: the
/// chain's head sees its queue close), and the hand-back.
enum HeadMsg {
    Frames(Vec<Frame>),
    Back(Vec<Msg>),
    End,
    HandBack,
}

/// How the calling thread hands frames to the head thread.
enum FramesTx {
    /// The chain's head queue (bounded: a full queue holds the caller back).
    Chain(SyncSender<HeadMsg>),
    /// The ring's head queue (unbounded, as the middle segment writes to it
    /// too; [`Pool::limit`] holds the caller back). Dropping it ends the input.
    Ring(Sender<HeadMsg>),
}

impl FramesTx {
    /// False when the head thread is gone.
    fn send(&self, msg: HeadMsg) -> bool {
        match self {
            FramesTx::Chain(tx) => tx.send(msg).is_ok(),
            FramesTx::Ring(tx) => tx.send(msg).is_ok(),
        }
    }
}

impl Drop for FramesTx {
    fn drop(&mut self) {
        // The chain's head sees its queue close; the ring's cannot (the middle
        // segment holds a sender too), so it is told.
        if let FramesTx::Ring(tx) = self {
            let _ = tx.send(HeadMsg::End);
        }
    }
}

/// The ring's first and last segments, run by its head thread.
struct Ends {
    first: Vec<Box<dyn Stage>>,
    last: Vec<Box<dyn Stage>>,
    rebuild_first: Rebuild,
    rebuild_last: Rebuild,
}

/// Builds a fresh copy of a segment's stage after a panic.
#[derive(Clone)]
struct Rebuild {
    scene: Scene,
    sensor: String,
    /// Pipeline index of the segment's first stage.
    first: usize,
}

impl Rebuild {
    fn stage(&self, i: usize) -> Box<dyn Stage> {
        let mut p = Pipeline::new(&self.scene, &self.sensor);
        p.stages.swap_remove(self.first + i)
    }
}

/// Runs `units` through `stages` as [`Pipeline`]'s `run_from` does (each
/// unit through a stage before the next stage; the last error kept);
/// consumed units go to `retired`. With `rebuild`, a stage that panics is
/// replaced by a fresh one and the panic's message kept in `panic` (the
/// unit it held is lost); without, the panic goes on up.
fn run_stages(
    stages: &mut [Box<dyn Stage>],
    units: &mut Vec<Unit>,
    leaving: &mut Vec<Unit>,
    result: &mut Result<(), FrameError>,
    retired: &mut Vec<Unit>,
    panic: &mut Option<String>,
    rebuild: Option<(&Rebuild, usize)>,
) {
    for (i, stage) in stages.iter_mut().enumerate() {
        leaving.clear();
        for mut w in units.drain(..) {
            w.report.stages.push(stage.name());
            match rebuild {
                None => {
                    if let Err(e) = stage.process(w, leaving) {
                        *result = Err(e);
                    }
                }
                Some((r, offset)) => {
                    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| stage.process(w, leaving))) {
                        Ok(Ok(())) => {}
                        Ok(Err(e)) => *result = Err(e),
                        Err(p) => {
                            *panic = Some(panic_message(p.as_ref()));
                            *stage = r.stage(offset + i);
                        }
                    }
                }
            }
            while let Some(w) = stage.consumed() {
                retire(retired, w);
            }
        }
        std::mem::swap(units, leaving);
    }
}

/// Flushes `stages` in order as [`Pipeline::flush`] does, each stage's
/// output run through the rest of the segment; one message per stage.
fn flush_stages(stages: &mut [Box<dyn Stage>], out: &mut Vec<Msg>, retired: &mut Vec<Unit>, rebuild: &Rebuild) {
    let mut leaving = Vec::new();
    for i in 0..stages.len() {
        let mut units = Vec::new();
        let flushed = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| stages[i].flush(&mut units)));
        if flushed.is_err() {
            stages[i] = rebuild.stage(i);
            continue;
        }
        while let Some(w) = stages[i].consumed() {
            retire(retired, w);
        }
        if !units.is_empty() {
            let (mut result, mut panic) = (Ok(()), None);
            run_stages(&mut stages[i + 1..], &mut units, &mut leaving, &mut result, retired, &mut panic, Some((rebuild, i + 1)));
            out.push(Msg::Push(InFlight { units, result: Ok(()), flush: true, panic: None }));
        }
    }
    out.push(Msg::Flush);
}

/// Validates each frame of `chunk` (reusing finished units' buffers from
/// `spare`) and runs `stages` on it: one message per frame.
fn head_chunk(
    validate: &mut super::validate::Validate,
    spare: &mut Vec<Unit>,
    chunk: Vec<Frame>,
    stages: &mut [Box<dyn Stage>],
    leaving: &mut Vec<Unit>,
    rebuild: &Rebuild,
) -> Vec<Msg> {
    let mut msgs = Vec::with_capacity(chunk.len());
    for frame in chunk {
        let mut units = Vec::with_capacity(1);
        let (mut result, mut panic) = validate_caught(validate, frame, spare, &mut units, rebuild);
        if result.is_ok() && panic.is_none() {
            run_stages(stages, &mut units, leaving, &mut result, spare, &mut panic, Some((rebuild, 0)));
        }
        msgs.push(Msg::Push(InFlight { units, result, flush: false, panic }));
    }
    msgs
}

/// Validates `frame` into `units` (reusing `spare`) as [`Validate::process`]
/// does; a panic there rebuilds the validate stage and is returned as its
/// message, the frame's result left Ok (its units empty).
///
/// [`Validate::process`]: super::validate::Validate::process
fn validate_caught(
    validate: &mut super::validate::Validate,
    frame: Frame,
    spare: &mut Vec<Unit>,
    units: &mut Vec<Unit>,
    rebuild: &Rebuild,
) -> (Result<(), FrameError>, Option<String>) {
    match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| validate.process(frame, spare, units))) {
        Ok(r) => (r, None),
        Err(p) => {
            *validate = super::validate::Validate::new(&rebuild.scene);
            (Ok(()), Some(panic_message(p.as_ref())))
        }
    }
}

/// Runs `stages` on what the segment before passed on, and says whether
/// the end of input or a hand-back passed (nothing comes after either).
fn pass_on(stages: &mut [Box<dyn Stage>], msgs: Vec<Msg>, leaving: &mut Vec<Unit>, retired: &mut Vec<Unit>, rebuild: &Rebuild) -> (Vec<Msg>, Ended) {
    let mut next = Vec::with_capacity(msgs.len());
    let mut ended = Ended::No;
    for msg in msgs {
        match msg {
            Msg::Push(mut inflight) => {
                run_stages(stages, &mut inflight.units, leaving, &mut inflight.result, retired, &mut inflight.panic, Some((rebuild, 0)));
                next.push(Msg::Push(inflight));
            }
            Msg::Flush => {
                flush_stages(stages, &mut next, retired, rebuild);
                ended = Ended::Flushed;
            }
            Msg::HandBack => {
                next.push(Msg::HandBack);
                ended = Ended::HandedBack;
            }
        }
    }
    (next, ended)
}

/// Segment 0 of the chain: validates each frame (reusing finished units'
/// buffers) and runs its stages; flushes them when its queue closes.
fn head_segment(
    mut validate: super::validate::Validate,
    mut spare: Vec<Unit>,
    spare_rx: Receiver<Unit>,
    frames: Receiver<HeadMsg>,
    mut stages: Vec<Box<dyn Stage>>,
    out: Out,
    rebuild: Rebuild,
) -> Parts {
    let mut leaving = Vec::new();
    while let Ok(msg) = frames.recv() {
        match msg {
            HeadMsg::Frames(chunk) => {
                spare.extend(spare_rx.try_iter());
                let msgs = head_chunk(&mut validate, &mut spare, chunk, &mut stages, &mut leaving, &rebuild);
                if !out.send(msgs) {
                    return Parts::default();
                }
            }
            HeadMsg::HandBack => {
                let _ = out.send(vec![Msg::HandBack]);
                return Parts { head: Some((validate, spare, spare_rx)), runs: vec![(rebuild.first, stages)] };
            }
            HeadMsg::Back(_) | HeadMsg::End => break,
        }
    }
    let mut msgs = Vec::new();
    flush_stages(&mut stages, &mut msgs, &mut spare, &rebuild);
    let _ = out.send(msgs);
    Parts::default()
}

/// A later segment: runs its stages on what the segment before it passes on.
fn segment(mut stages: Vec<Box<dyn Stage>>, from: Receiver<Vec<Msg>>, out: Out, spare_tx: Sender<Unit>, rebuild: Rebuild) -> Parts {
    let mut leaving = Vec::new();
    let mut retired = Vec::new();
    while let Ok(msgs) = from.recv() {
        let (next, ended) = pass_on(&mut stages, msgs, &mut leaving, &mut retired, &rebuild);
        retired.drain(..).for_each(|w| drop(spare_tx.send(w)));
        if !out.send(next) {
            break;
        }
        if ended == Ended::HandedBack {
            return Parts { head: None, runs: vec![(rebuild.first, stages)] };
        }
    }
    Parts::default()
}

/// The ring's head thread: the first segment on frames (validated here, as
/// [`head_segment`] does) and the last segment on what the middle one
/// passes back, in the order they arrive; each keeps its own order, so
/// every stage sees its units in frame order. The end of input flushes the
/// first segment into the middle one, whose flush comes back through the
/// last; then the thread ends. A hand-back goes round the same way, and the
/// thread returns its stages once it is back. Units the last segment
/// finishes with are reused here directly.
fn ring_head(
    mut validate: super::validate::Validate,
    mut spare: Vec<Unit>,
    spare_rx: Receiver<Unit>,
    input: Receiver<HeadMsg>,
    to_middle: Sender<Vec<Msg>>,
    out: Sender<Vec<Msg>>,
    mut ends: Ends,
) -> Parts {
    let mut leaving = Vec::new();
    let mut to_middle = Some(to_middle);
    while let Ok(msg) = input.recv() {
        match msg {
            HeadMsg::Frames(chunk) => {
                let Some(tx) = &to_middle else { continue };
                spare.extend(spare_rx.try_iter());
                let msgs = head_chunk(&mut validate, &mut spare, chunk, &mut ends.first, &mut leaving, &ends.rebuild_first);
                // Neither queue between the two threads is bounded, so
                // neither thread ever waits on the other to take a chunk
                // (the calling thread's in-flight limit bounds both).
                if tx.send(msgs).is_err() {
                    return Parts::default();
                }
            }
            HeadMsg::HandBack => {
                if let Some(tx) = &to_middle
                    && tx.send(vec![Msg::HandBack]).is_err()
                {
                    return Parts::default();
                }
            }
            HeadMsg::End => {
                if let Some(tx) = to_middle.take() {
                    let mut msgs = Vec::new();
                    flush_stages(&mut ends.first, &mut msgs, &mut spare, &ends.rebuild_first);
                    let _ = tx.send(msgs);
                }
            }
            HeadMsg::Back(msgs) => {
                let (next, ended) = pass_on(&mut ends.last, msgs, &mut leaving, &mut spare, &ends.rebuild_last);
                if out.send(next).is_err() || ended == Ended::Flushed {
                    return Parts::default();
                }
                if ended == Ended::HandedBack {
                    let runs = vec![(ends.rebuild_first.first, ends.first), (ends.rebuild_last.first, ends.last)];
                    return Parts { head: Some((validate, spare, spare_rx)), runs };
                }
            }
        }
    }
    Parts::default()
}

/// A panic's message, for the outcome of the frame it cost.
pub fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = panic.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = panic.downcast_ref::<String>() {
        s.clone()
    } else {
        "panic with a non-text payload".to_string()
    }
}

/// The ring on two threads is chosen only where its pace (its busier
/// thread's share) is below this fraction of the chain's: it hands each
/// frame over twice more.
const RING_GAIN: f64 = 0.9;

/// The chain's pace: its largest segment's cost.
fn chain_pace(costs: &[f64], bounds: &[usize]) -> f64 {
    bounds.windows(2).map(|b| costs[b[0]..b[1]].iter().sum::<f64>()).fold(0.0, f64::max)
}

/// The ring's pace: the larger of its head thread's cost (first and last
/// segments) and its middle segment's.
fn ring_pace(costs: &[f64], bounds: &[usize]) -> f64 {
    let sum = |a: usize, b: usize| costs[a..b].iter().sum::<f64>();
    let (i, j, m) = (bounds[1], bounds[2], bounds[3]);
    (sum(0, i) + sum(j, m)).max(sum(i, j))
}

/// The three non-empty consecutive segments `[0, i, j, m]` whose ring pace
/// is smallest (first and last on one thread, the middle on the other);
/// None for fewer than three stages.
fn ring_partition(costs: &[f64]) -> Option<Vec<usize>> {
    let m = costs.len();
    let mut best: Option<(f64, Vec<usize>)> = None;
    for i in 1..m {
        for j in i + 1..m {
            let b = vec![0, i, j, m];
            let pace = ring_pace(costs, &b);
            if best.as_ref().is_none_or(|(p, _)| pace < *p) {
                best = Some((pace, b));
            }
        }
    }
    best.map(|(_, b)| b)
}

/// Cuts `costs` into `parts` consecutive non-empty runs with the smallest
/// largest sum; returns the run boundaries (first 0, last `costs.len()`).
fn partition(costs: &[f64], parts: usize) -> Vec<usize> {
    let m = costs.len();
    let parts = parts.clamp(1, m.max(1));
    let prefix: Vec<f64> = std::iter::once(0.0)
        .chain(costs.iter().scan(0.0, |acc, c| {
            *acc += c;
            Some(*acc)
        }))
        .collect();
    // best[k][j]: smallest largest sum cutting costs[..j] into k runs; from[k][j]: where the last run starts.
    let mut best = vec![vec![f64::INFINITY; m + 1]; parts + 1];
    let mut from = vec![vec![0usize; m + 1]; parts + 1];
    best[0][0] = 0.0;
    for k in 1..=parts {
        for j in k..=m {
            for i in (k - 1)..j {
                let v = best[k - 1][i].max(prefix[j] - prefix[i]);
                if v < best[k][j] {
                    best[k][j] = v;
                    from[k][j] = i;
                }
            }
        }
    }
    let mut bounds = vec![m];
    let mut j = m;
    for k in (1..=parts).rev() {
        j = from[k][j];
        bounds.push(j);
    }
    bounds.reverse();
    bounds
}

#[cfg(test)]
mod tests {
    use super::{chain_pace, partition, ring_pace, ring_partition, Mode, Staged, RING_GAIN};
    use crate::frame::Frame;
    use crate::pipeline::{FrameError, Stage, Unit};
    use crate::scene::Scene;

    /// A stage that panics on the frame with sequence number `at` and
    /// otherwise is `inner` (a rebuilt stage is the scene's own: it panics once).
    struct Boom {
        inner: Box<dyn Stage>,
        at: u64,
    }

    impl Stage for Boom {
        fn name(&self) -> &'static str {
            self.inner.name()
        }
        fn process(&mut self, w: Unit, out: &mut Vec<Unit>) -> Result<(), FrameError> {
            if w.frame.sequence == self.at {
                panic!("boom in {} at frame {}", self.inner.name(), self.at);
            }
            self.inner.process(w, out)
        }
        fn flush(&mut self, out: &mut Vec<Unit>) {
            self.inner.flush(out)
        }
        fn consumed(&mut self) -> Option<Unit> {
            self.inner.consumed()
        }
    }

    /// A stage that panics on a thread costs its frame only: that frame's
    /// outcome carries the panic's message and no report, every other
    /// frame's outcome comes out once, in order, with its report, and the
    /// pipeline carries on (the stage rebuilt) — on the ring and on the
    /// chain. Every stage panics once, each on its own frame: the even
    /// ones on their threads after the first pilot (so every segment is
    /// tried whatever the cut), the odd ones in the second pilot, on the
    /// calling thread.
    #[test]
    fn a_stage_panicking_on_a_thread_costs_its_frame_only() {
        let scene = Scene::default_scene();
        let sim = crate::physics::Simulator::new(&scene).expect("the default scene simulates");
        let frames: Vec<Frame> = (0..super::SETTLED_FRAMES as u64 + 100).map(|i| sim.frame(5, i).0).collect();
        for ring in [true, false] {
            let mut s = Staged::new(&scene, "t", 2);
            s.prefer_ring(Some(ring));
            let Mode::Local { pipeline, .. } = &mut s.mode else { unreachable!("a new pipeline starts on the calling thread") };
            let n = pipeline.stages.len();
            assert!(n >= 3, "{n} stages");
            // After the first pilot (400 frames on the calling thread): on
            // the threads; in the second (frames 2001 to 2200): on the calling thread.
            let booms: Vec<(usize, u64)> = (0..n).map(|i| (i, if i % 2 == 0 { 450 + 80 * i as u64 } else { 2010 + 30 * i as u64 })).collect();
            for &(i, at) in &booms {
                let on_threads = (super::PILOT_FRAMES as u64..super::REPILOT_AT as u64).contains(&at);
                let in_second_pilot = (super::REPILOT_AT as u64..super::SETTLED_FRAMES as u64).contains(&at);
                assert!(if i % 2 == 0 { on_threads } else { in_second_pilot }, "stage {i} at frame {at}");
            }
            let mut names = Vec::new();
            for &(i, at) in &booms {
                let inner = pipeline.stages.remove(i);
                names.push(inner.name());
                pipeline.stages.insert(i, Box::new(Boom { inner, at }));
            }
            let mut outcomes = Vec::new();
            let mut out = Vec::new();
            for f in &frames {
                s.push(f.clone(), &mut out);
                outcomes.append(&mut out);
            }
            let flushed = s.finish(&mut out);
            outcomes.append(&mut out);
            assert!(flushed.reports.is_empty() && flushed.panic.is_none());
            let cut = s.cut();
            assert_eq!(cut.threads == [0, 1, 0], ring, "{cut}");
            assert_eq!(outcomes.len(), frames.len(), "{cut}: one outcome per frame");
            for (i, o) in outcomes.iter().enumerate() {
                match booms.iter().zip(&names).find(|(b, _)| b.1 == i as u64) {
                    Some((_, name)) => {
                        let msg = o.panic.as_deref().unwrap_or_else(|| panic!("{cut}: frame {i}: no panic reported"));
                        assert_eq!(msg, format!("boom in {name} at frame {i}"), "{cut}");
                        assert!(o.reports.is_empty(), "{cut}: frame {i}: its unit is lost");
                    }
                    None => {
                        assert!(o.panic.is_none(), "{cut}: frame {i}: {:?}", o.panic);
                        assert!(o.result.is_ok(), "{cut}: frame {i}: {:?}", o.result);
                        assert_eq!(o.reports.len(), 1, "{cut}: frame {i}");
                        assert_eq!(o.reports[0].seq_first, i as u64, "{cut}: in order");
                    }
                }
            }
        }
    }

    /// The threads a pipeline runs on once cut: on three, a chain of three
    /// segments, each on a thread of its own; on two, the ring when asked
    /// for (the first and last segments on one thread). Checked after each
    /// pilot.
    #[test]
    fn each_segment_of_a_chain_has_a_thread_of_its_own() {
        let scene = Scene::default_scene();
        let sim = crate::physics::Simulator::new(&scene).expect("the default scene simulates");
        let frames: Vec<Frame> = (0..super::SETTLED_FRAMES as u64 + 10).map(|i| sim.frame(5, i).0).collect();
        for (threads, ring, want) in [(3, None, 3), (2, Some(true), 2), (2, Some(false), 2)] {
            let mut s = Staged::new(&scene, "t", threads);
            s.prefer_ring(ring);
            let mut out = Vec::new();
            for (i, f) in frames.iter().enumerate() {
                s.push(f.clone(), &mut out);
                out.clear();
                let pilot = match i + 1 {
                    n if n == super::PILOT_FRAMES + 10 => (201, 400),
                    n if n == super::SETTLED_FRAMES + 10 => (2001, 2200),
                    _ => continue,
                };
                let Mode::Split(pool) = &s.mode else { panic!("{threads} threads: on threads after the pilot") };
                let cut = s.cut();
                assert_eq!(cut.pilot, Some(pilot), "{cut}");
                assert_eq!(pool.handles.len(), want, "{threads} threads, ring {ring:?}: {cut}");
                let used = cut.threads.iter().max().map_or(0, |t| t + 1);
                assert_eq!(used, want, "{cut}");
                assert_eq!(cut.threads == [0, 1, 0], ring == Some(true), "{cut}");
            }
            s.finish(&mut out);
        }
    }

    #[test]
    fn partition_minimises_the_largest_run() {
        assert_eq!(partition(&[1.0, 1.0, 1.0, 1.0], 2), vec![0, 2, 4]);
        assert_eq!(partition(&[0.1, 0.1, 0.4, 0.2, 0.2], 2), vec![0, 3, 5]);
        assert_eq!(partition(&[5.0, 1.0, 1.0, 1.0], 2), vec![0, 1, 4]);
        assert_eq!(partition(&[1.0, 2.0, 3.0], 3), vec![0, 1, 2, 3]);
        assert_eq!(partition(&[1.0, 2.0], 5), vec![0, 1, 2]);
        assert_eq!(partition(&[0.0, 0.0, 0.0], 2).len(), 3);
    }

    #[test]
    fn the_ring_pairs_the_first_and_last_segments_against_the_middle() {
        // A heavy middle stage: the chain's best pace is 0.65, the ring's 0.5.
        let costs = [0.02, 0.13, 0.2, 0.5, 0.15];
        let chain = partition(&costs, 2);
        assert!((chain_pace(&costs, &chain) - 0.65).abs() < 1e-12);
        let ring = ring_partition(&costs).unwrap();
        assert_eq!(ring, vec![0, 3, 4, 5]);
        assert!((ring_pace(&costs, &ring) - 0.5).abs() < 1e-12);
        assert!(ring_pace(&costs, &ring) < RING_GAIN * chain_pace(&costs, &chain));
        // Evenly spread costs: the ring gains nothing over the chain.
        let flat = [0.25; 4];
        let r = ring_partition(&flat).unwrap();
        assert!(ring_pace(&flat, &r) >= RING_GAIN * chain_pace(&flat, &partition(&flat, 2)));
        assert_eq!(ring_partition(&[1.0, 1.0]), None);
    }
}
