//! One sensor's pipeline on several threads, with the single-thread results.
//!
//! The stages are cut into consecutive segments, one thread each (a stage
//! pipeline): segment 0 validates frame k + 1 while segment 1 detects in
//! frame k. Every stage still sees exactly the calls it would see in
//! [`Pipeline`] — the same units, in the same order, then the same flush —
//! so every piece of running state (the start method's mismatch gap, the
//! baseline's drift, the averaging group in progress, the forgetting noise
//! model, the pooled colour, the false-alarm counters, the timing floor) is
//! updated in frame order on one thread, and the reports are bit-identical to
//! the single-thread run whatever the cut. What the cut changes is only how
//! fast: the slowest segment sets the pace. The first frames run on the
//! calling thread, the later of them timed stage by stage, and the cut that
//! balances those times best is used for the rest.
//!
//! Units that finish (their report went out, or averaging consumed them) go
//! back to segment 0, whose validate stage reuses their buffers.

use super::{retire, FrameError, Pipeline, Stage, Work};
use crate::frame::{Frame, Report};
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
}

/// Frames per message between threads: amortises the hand-over (a wake-up
/// costs a few microseconds) without holding many frames in flight.
const CHUNK: usize = 8;
/// Messages a segment may hold queued ahead of it.
const QUEUE: usize = 4;
/// Frames run on one thread first whose step times are not used: the
/// pipeline's start-up (plans built, error tables measured, the pooled colour
/// and the thresholds it sets still settling) costs far more per frame than
/// the steady state the cut is for.
const PILOT_WARMUP: usize = 200;
/// Frames after those, still on one thread, whose step times choose the cut.
const PILOT_TIMED: usize = 200;

/// One push's units on their way through the segments.
struct InFlight {
    units: Vec<Work>,
    result: Result<(), FrameError>,
    /// A stage's flush made these (not a frame).
    flush: bool,
}

enum Msg {
    /// The units of one push (or of one stage's flush, whose errors
    /// [`Pipeline::flush`] ignores).
    Push(InFlight),
    /// End of input: flush the segment's stages in order, then pass it on.
    Flush,
}

/// How the stages were cut: the stage names of each segment, and the pilot
/// run's share of the time per segment (empty when no pilot ran).
#[derive(Debug, Clone, PartialEq)]
pub struct Cut {
    /// Stage names per segment (validate first in segment 0).
    pub segments: Vec<Vec<&'static str>>,
    /// Fraction of the pilot's time each segment took (sums to 1).
    pub shares: Vec<f64>,
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
        Ok(())
    }
}

/// Runs `frames` through `scene`'s pipeline on up to `threads` threads and
/// calls `each` with every frame's outcome, in frame order, then once more
/// with the reports the final flush completes. The reports are those of
/// [`Pipeline::push`] + [`Pipeline::flush`], bit for bit. `threads` ≤ 1 runs
/// on the calling thread.
pub fn run<I, F>(scene: &Scene, sensor: &str, threads: usize, frames: I, mut each: F) -> Cut
where
    I: IntoIterator<Item = Frame>,
    I::IntoIter: Send,
    F: FnMut(Outcome),
{
    let mut frames = frames.into_iter();
    let mut pipeline = Pipeline::new(scene, sensor);
    let names = pipeline.stage_names();
    let segments = threads.min(names.len()).max(1);
    // The first frames run here, one thread, each step timed once the
    // pipeline's start-up (plans, tables, a settling colour estimate) is past.
    let pilot = if segments == 1 { usize::MAX } else { PILOT_WARMUP + PILOT_TIMED };
    let mut costs = vec![0.0; names.len()];
    let (mut units, mut leaving, mut retired) = (Vec::new(), Vec::new(), Vec::new());
    for (k, frame) in frames.by_ref().take(pilot).enumerate() {
        let timed = segments > 1 && k >= PILOT_WARMUP;
        let t0 = Instant::now();
        let mut result = pipeline.validate.process(frame, &mut pipeline.spare, &mut units);
        if timed {
            costs[0] += t0.elapsed().as_secs_f64();
        }
        if result.is_ok() {
            for (i, stage) in pipeline.stages.iter_mut().enumerate() {
                let t0 = Instant::now();
                run_stages(std::slice::from_mut(stage), &mut units, &mut leaving, &mut result, &mut retired);
                if timed {
                    costs[i + 1] += t0.elapsed().as_secs_f64();
                }
            }
        }
        pipeline.spare.append(&mut retired);
        let reports = units.drain(..).map(|w| finish(w, &mut pipeline.spare)).collect();
        each(Outcome { reports, result });
    }
    if segments == 1 || costs.iter().sum::<f64>() == 0.0 {
        // One thread, or the input ended during the pilot.
        let mut reports = Vec::new();
        pipeline.flush(&mut reports);
        each(Outcome { reports, result: Ok(()) });
        return Cut { segments: vec![names], shares: vec![1.0] };
    }
    let bounds = partition(&costs, segments);
    let total: f64 = costs.iter().sum();
    let cut = Cut {
        segments: bounds.windows(2).map(|b| names[b[0]..b[1]].to_vec()).collect(),
        shares: bounds.windows(2).map(|b| costs[b[0]..b[1]].iter().sum::<f64>() / total).collect(),
    };
    // Cost index 0 is validate; pipeline stage i is cost index i + 1.
    let mut all = std::mem::take(&mut pipeline.stages);
    let mut groups: Vec<Vec<Box<dyn Stage>>> = Vec::new();
    for b in bounds.windows(2).rev() {
        groups.push(all.split_off(b[0].saturating_sub(1)));
    }
    groups.reverse();
    let validate = pipeline.validate;
    let spare = std::mem::take(&mut pipeline.spare);

    std::thread::scope(|s| {
        let (spare_tx, spare_rx) = channel::<Work>();
        let (frames_tx, frames_rx) = sync_channel::<Vec<Frame>>(QUEUE);
        s.spawn(move || {
            let mut chunk = Vec::with_capacity(CHUNK);
            for f in frames {
                chunk.push(f);
                if chunk.len() == CHUNK && frames_tx.send(std::mem::replace(&mut chunk, Vec::with_capacity(CHUNK))).is_err() {
                    return;
                }
            }
            if !chunk.is_empty() {
                let _ = frames_tx.send(chunk);
            }
        });
        let mut input: Option<Receiver<Vec<Msg>>> = None;
        let mut head = Some((validate, spare, spare_rx, frames_rx));
        for group in groups {
            let (tx, rx) = sync_channel::<Vec<Msg>>(QUEUE);
            let spare_tx = spare_tx.clone();
            match head.take() {
                Some((validate, spare, spare_rx, frames_rx)) => {
                    s.spawn(move || head_segment(validate, spare, spare_rx, frames_rx, group, tx));
                }
                None => {
                    let from = input.take().expect("an earlier segment");
                    s.spawn(move || segment(group, from, tx, spare_tx));
                }
            }
            input = Some(rx);
        }
        // The collector: units become reports; their buffers go back to the head.
        let from = input.expect("at least one segment");
        let (mut flushed, mut back) = (Vec::new(), Vec::new());
        while let Ok(msgs) = from.recv() {
            for msg in msgs {
                match msg {
                    Msg::Push(inflight) => {
                        let mut reports = Vec::with_capacity(inflight.units.len());
                        reports.extend(inflight.units.into_iter().map(|w| finish(w, &mut back)));
                        back.drain(..).for_each(|w| drop(spare_tx.send(w)));
                        if inflight.flush {
                            flushed.extend(reports);
                        } else {
                            each(Outcome { reports, result: inflight.result });
                        }
                    }
                    Msg::Flush => {}
                }
            }
        }
        each(Outcome { reports: flushed, result: Ok(()) });
    });
    cut
}

/// Runs `units` through `stages` as [`Pipeline`]'s `run_from` does (each
/// unit through a stage before the next stage; the last error kept);
/// consumed units go to `retired`.
fn run_stages(
    stages: &mut [Box<dyn Stage>],
    units: &mut Vec<Work>,
    leaving: &mut Vec<Work>,
    result: &mut Result<(), FrameError>,
    retired: &mut Vec<Work>,
) {
    for stage in stages {
        leaving.clear();
        for mut w in units.drain(..) {
            w.report.stages.push(stage.name());
            if let Err(e) = stage.process(w, leaving) {
                *result = Err(e);
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
fn flush_stages(stages: &mut [Box<dyn Stage>], out: &mut Vec<Msg>, retired: &mut Vec<Work>) {
    let mut leaving = Vec::new();
    for i in 0..stages.len() {
        let mut units = Vec::new();
        stages[i].flush(&mut units);
        while let Some(w) = stages[i].consumed() {
            retire(retired, w);
        }
        if !units.is_empty() {
            let mut result = Ok(());
            run_stages(&mut stages[i + 1..], &mut units, &mut leaving, &mut result, retired);
            out.push(Msg::Push(InFlight { units, result: Ok(()), flush: true }));
        }
    }
    out.push(Msg::Flush);
}

/// Segment 0: validates each frame (reusing finished units' buffers) and
/// runs its stages.
fn head_segment(
    mut validate: super::validate::Validate,
    mut spare: Vec<Work>,
    spare_rx: Receiver<Work>,
    frames: Receiver<Vec<Frame>>,
    mut stages: Vec<Box<dyn Stage>>,
    out: SyncSender<Vec<Msg>>,
) {
    let mut leaving = Vec::new();
    while let Ok(chunk) = frames.recv() {
        spare.extend(spare_rx.try_iter());
        let mut msgs = Vec::with_capacity(chunk.len());
        for frame in chunk {
            let mut units = Vec::with_capacity(1);
            let mut result = validate.process(frame, &mut spare, &mut units);
            if result.is_ok() {
                run_stages(&mut stages, &mut units, &mut leaving, &mut result, &mut spare);
            }
            msgs.push(Msg::Push(InFlight { units, result, flush: false }));
        }
        if out.send(msgs).is_err() {
            return;
        }
    }
    let mut msgs = Vec::new();
    flush_stages(&mut stages, &mut msgs, &mut spare);
    let _ = out.send(msgs);
}

/// A later segment: runs its stages on what the segment before it passes on.
fn segment(mut stages: Vec<Box<dyn Stage>>, from: Receiver<Vec<Msg>>, out: SyncSender<Vec<Msg>>, spare_tx: Sender<Work>) {
    let mut leaving = Vec::new();
    let mut retired = Vec::new();
    while let Ok(msgs) = from.recv() {
        let mut next = Vec::with_capacity(msgs.len());
        for msg in msgs {
            match msg {
                Msg::Push(mut inflight) => {
                    run_stages(&mut stages, &mut inflight.units, &mut leaving, &mut inflight.result, &mut retired);
                    next.push(Msg::Push(inflight));
                }
                Msg::Flush => flush_stages(&mut stages, &mut next, &mut retired),
            }
        }
        retired.drain(..).for_each(|w| drop(spare_tx.send(w)));
        if out.send(next).is_err() {
            return;
        }
    }
}

/// A finished unit's report; the unit goes to `spare` for reuse.
fn finish(mut w: Work, spare: &mut Vec<Work>) -> Report {
    let report = std::mem::take(&mut w.report);
    retire(spare, w);
    report
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
    use super::partition;

    #[test]
    fn partition_minimises_the_largest_run() {
        assert_eq!(partition(&[1.0, 1.0, 1.0, 1.0], 2), vec![0, 2, 4]);
        assert_eq!(partition(&[0.1, 0.1, 0.4, 0.2, 0.2], 2), vec![0, 3, 5]);
        assert_eq!(partition(&[5.0, 1.0, 1.0, 1.0], 2), vec![0, 1, 4]);
        assert_eq!(partition(&[1.0, 2.0, 3.0], 3), vec![0, 1, 2, 3]);
        assert_eq!(partition(&[1.0, 2.0], 5), vec![0, 1, 2]);
        assert_eq!(partition(&[0.0, 0.0, 0.0], 2).len(), 3);
    }
}
