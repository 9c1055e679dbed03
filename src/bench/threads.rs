//! `tofwave bench --threads N`: one sensor on N threads, offline
//! (`process --threads`) and in the service (`serve --workers-per-sensor`),
//! against one thread, on the same frames in trials alternating the arms.
//!
//! Rates are steady-state: outcomes (offline) or reports reaching a
//! subscriber (service) from the 2201st to the last, divided by the time
//! between them, on every arm: the first 2200 frames hold the threaded
//! pipeline's two pilots (frames it runs on one thread to choose its cut,
//! the second once start-up has passed) and the frames in which any
//! pipeline pays its start-up. With fewer than 2600 frames per trial the
//! clock starts at the 401st, after the first pilot (and past 2000 frames
//! the second pilot is then on the clock), and with fewer than 800 at the
//! first.
//!
//! Every arm renders each report's JSON line: the offline arms as `process`
//! does (on its calling thread, as the frames finish), the service for its
//! subscribers (every report carries its line). Left out of the offline
//! arms, that work (a few µs per report) would count against the service
//! alone.
//!
//! Each trial also runs the machine's own yardstick: N independent copies
//! of the one-thread pipeline at once, one per thread, each over the same
//! frames, clocked together from the end of their warm-up. That is N
//! threads' worth of the same work with nothing handed between threads:
//! its rate over one thread's shows how the machine's cores scale on this
//! work at that time. On a machine whose cores slow each other down
//! (shared caches, power, a virtual machine's host), it falls short of N.
//! It is a reference, not a bound: the pipeline's threads each hold a part
//! of its state, and its calling thread is one thread more.
//!
//! The report also gives each stage's time per frame on one thread (in the
//! pilot, and in steady state) and, on Linux, each pipeline thread's CPU
//! time per frame on one and on N threads (from /proc).

use std::sync::mpsc::{channel, Receiver, Sender};
use std::time::Instant;

use super::BenchError;
use super::cluster::trial;
use super::service::{median, stat_cpu_s, USER_HZ};
use crate::frame::Frame;
use crate::pipeline::{report_json, threaded};
use crate::scene::Scene;
use crate::wire::{frame_to_proto, proto};

/// One sensor on one and on N threads, offline and in the service.
#[derive(Debug, Clone, PartialEq)]
pub struct ThreadsCost {
    /// Threads of the N arm.
    pub threads: usize,
    /// Frames per trial.
    pub frames: usize,
    /// Samples per channel per frame.
    pub samples_per_frame: usize,
    /// How the N arm cut the stages (the last offline trial's).
    pub cut: String,
    /// Each stage's time per frame in that trial's pilot, s.
    pub stage_s: Vec<(&'static str, f64)>,
    /// That pilot's timed frames, first and last (counted from 1).
    pub pilot: Option<(usize, usize)>,
    /// Each stage's time per frame on one thread over the second half of
    /// the frames (steady state: the noise colour and the thresholds it sets
    /// have settled), s.
    pub steady_stage_s: Vec<(&'static str, f64)>,
    /// CPU time per frame of the pipeline's threads on one thread, s (user +
    /// system, from /proc: Linux only, else empty), over the last trial's
    /// CPU window (see [`offline`]): the calling thread's.
    pub cpu_1: Vec<(String, f64)>,
    /// The same on N threads: the calling thread's, then each stage thread's.
    pub cpu_n: Vec<(String, f64)>,
    /// One /proc tick over the CPU windows' frames (the fewer of the two
    /// arms'), s/frame: how far each thread's figure may be off.
    pub cpu_tick_s: f64,
    /// Offline frames/s per trial, one thread.
    pub offline_1: Vec<f64>,
    /// Offline frames/s per trial, N threads.
    pub offline_n: Vec<f64>,
    /// N independent one-thread pipelines at once (the machine's
    /// yardstick, see [`copies`]): their frames/s together, per trial.
    pub copies_n: Vec<f64>,
    /// Service (loopback gRPC, one sensor) frames/s per trial, one worker.
    pub service_1: Vec<f64>,
    /// The same with N workers for the sensor.
    pub service_n: Vec<f64>,
}

impl ThreadsCost {
    /// Offline N threads over one (medians).
    pub fn offline_speedup(&self) -> f64 {
        median(&self.offline_n) / median(&self.offline_1)
    }

    /// N independent one-thread pipelines at once over one alone (medians):
    /// how the machine's cores scale on this work with no hand-over (a
    /// reference, not a bound: see the module's notes).
    pub fn copies_speedup(&self) -> f64 {
        median(&self.copies_n) / median(&self.offline_1)
    }

    /// Service with N workers over offline with N threads (medians).
    pub fn service_share(&self) -> f64 {
        median(&self.service_n) / median(&self.offline_n)
    }

    /// The result as Markdown.
    pub fn markdown(&self) -> String {
        let row = |name: &str, v: &[f64]| {
            let cells: Vec<String> = v.iter().map(|x| format!("{x:.0}")).collect();
            format!("| {name} | {} | {:.0} |\n", cells.join(" / "), median(v))
        };
        let n = self.threads;
        let skip = pilot_skip(self.frames);
        let clock = if skip > 0 {
            let pilots = if skip >= threaded::SETTLED_FRAMES { "two pilots" } else { "first pilot" };
            format!("; each rate from the {} outcome to the last (the first {skip}, the threaded pipeline's {pilots} on one thread and every arm's start-up, off the clock)", ordinal(skip + 1))
        } else {
            "; each rate from the first outcome to the last".to_string()
        };
        let mut md = format!(
            "One sensor, {} frames of {} samples per channel per trial, {} trials per arm (alternating){clock}. \
             Every arm renders each report's JSON line (offline as `process` does for its output, the service for its subscribers).\n\n\
             | arm | frames/s per trial | median |\n|---|---|---|\n",
            self.frames,
            self.samples_per_frame,
            self.offline_1.len()
        );
        md += &row("offline, 1 thread (`process --threads 1`)", &self.offline_1);
        md += &row(&format!("offline, {n} threads (`process --threads {n}`)"), &self.offline_n);
        md += &row(&format!("offline, {n} independent copies of the 1-thread arm at once (the machine's yardstick)"), &self.copies_n);
        md += &row("service, 1 worker (`serve`)", &self.service_1);
        md += &row(&format!("service, {n} workers (`serve --workers-per-sensor {n}`)"), &self.service_n);
        // Enough digits to tell a ratio or share from the targets' 1.8× and
        // 80 % (rounded to 1.80× or 80 %, 1.797× or 79.6 % would pass).
        md += &format!(
            "\nOffline {n} threads / 1 thread: **{:.3}×**; service with {n} workers / offline with {n} threads: **{:.1} %**; \
             service with 1 worker / offline 1 thread: {:.1} %. Cut: {}.\n",
            self.offline_speedup(),
            100.0 * self.service_share(),
            100.0 * median(&self.service_1) / median(&self.offline_1),
            self.cut
        );
        let ratios = |v: &[f64]| v.iter().zip(&self.offline_1).map(|(a, b)| format!("{:.3}×", a / b)).collect::<Vec<_>>().join(", ");
        md += &format!(
            "\nThe machine's yardstick: {n} independent copies of the one-thread pipeline at once, each on a thread of its \
             own and over the same frames (clocked together once each is past the outcomes every arm leaves off its clock), \
             ran **{:.3}×** one alone (medians): {n} whole pipelines side by side, each \
             feeding its own frames and rendering its own JSON lines, nothing handed between threads. It shows how this \
             machine's cores scaled on this work in these trials; it is a reference, not a bound (the pipeline's threads \
             each hold a part of its state, and its calling thread is one thread more). The pipeline on {n} threads reached \
             {:.1} % of it. Trial by trial (each against the same trial's one thread): {n} threads {}; \
             {n} copies {}.\n",
            self.copies_speedup(),
            100.0 * self.offline_speedup() / self.copies_speedup(),
            ratios(&self.offline_n),
            ratios(&self.copies_n)
        );
        md += &self.stage_table();
        md += &self.cpu_table();
        md
    }

    /// Stage times per frame on one thread: the pilot's (which chose the
    /// cut) beside the steady state's.
    fn stage_table(&self) -> String {
        let total = |v: &[(&str, f64)]| v.iter().map(|s| s.1).sum::<f64>();
        let (pilot, steady) = (total(&self.stage_s), total(&self.steady_stage_s));
        let cell = |t: Option<f64>, all: f64| t.map_or("–".to_string(), |t| format!("{:.1} | {:.0} %", t * 1e6, 100.0 * t / all));
        let timed = self.pilot.map_or("in the pilot (none ran: too few frames)".to_string(), |(a, b)| format!("in the pilot's timed frames ({a}–{b}, whose times chose the cut)"));
        let mut md = format!(
            "\nStage times per frame on one thread: {timed} \
             and over the second half of the frames (steady state: the pooled noise colour, and the thresholds it sets, have settled):\n\n\
             | stage | pilot µs/frame | share | steady µs/frame | share |\n|---|---|---|---|---|\n"
        );
        let names = if self.stage_s.is_empty() { &self.steady_stage_s } else { &self.stage_s };
        for (name, _) in names {
            let of = |v: &[(&str, f64)]| v.iter().find(|s| s.0 == *name).map(|s| s.1);
            md += &format!("| {name} | {} | {} |\n", cell(of(&self.stage_s), pilot), cell(of(&self.steady_stage_s), steady));
        }
        md
    }

    /// CPU time per frame by thread on one and on N threads, and the
    /// speed-up that CPU allows where N cores are all there is and the
    /// one-thread arm runs all the time.
    fn cpu_table(&self) -> String {
        let sum = |v: &[(String, f64)]| v.iter().map(|c| c.1).sum::<f64>();
        let (one, many) = (sum(&self.cpu_1), sum(&self.cpu_n));
        let n = self.threads;
        // On threads only once a stage thread ran (the pilot ended).
        if !(one > 0.0 && many > 0.0 && self.cpu_n.iter().any(|c| c.0.starts_with(threaded::SEGMENT_THREAD_PREFIX))) {
            return format!(
                "\nCPU time by thread: not measured (it needs /proc, the {n}-thread arm past its pilot with its threads running through \
                 the CPU window, and at least {MIN_CPU_S} s of CPU time in each arm's window: a longer run).\n"
            );
        }
        let mut md = format!(
            "\nCPU time per frame by thread in the last trial, from its first timed outcome to the one nine tenths of the way \
             to the last (user + system, from /proc, in 10 ms ticks: each figure within ±{:.1} µs/frame; the calling thread \
             feeds the frames and renders the JSON lines, and on one thread runs every stage too):\n\n\
             | thread | 1 thread, µs/frame | {n} threads, µs/frame |\n|---|---|---|\n",
            self.cpu_tick_s * 1e6
        );
        for (name, t) in &self.cpu_n {
            let alone = self.cpu_1.iter().find(|c| c.0 == *name).map_or("–".to_string(), |c| format!("{:.1}", c.1 * 1e6));
            md += &format!("| {name} | {alone} | {:.1} |\n", t * 1e6);
        }
        md += &format!("| all | {:.1} | {:.1} |\n", one * 1e6, many * 1e6);
        md += &format!(
            "\nOn {n} threads the pipeline spends {:+.0} % CPU per frame against one thread. Where {n} cores are all the \
             process has, and one thread runs without pause, that alone allows at most {n} × {:.1} / {:.1} = {:.2}× \
             (that trial's: {:.2}×).\n",
            100.0 * (many / one - 1.0),
            one * 1e6,
            many * 1e6,
            n as f64 * one / many,
            self.offline_n.last().zip(self.offline_1.last()).map_or(f64::NAN, |(a, b)| a / b)
        );
        md
    }
}

/// Measures `frames` through `scene` on 1 and `threads` threads, offline and
/// in a loopback service, `trials` times each; `progress` hears of each trial.
pub fn measure_threads_cost(
    scene: &Scene,
    frames: &[Frame],
    threads: usize,
    trials: usize,
    mut progress: impl FnMut(&str),
) -> Result<ThreadsCost, BenchError> {
    let err = |e: &dyn std::fmt::Display| BenchError::Service(e.to_string());
    if frames.len() < 2 {
        return Err(BenchError::Service("give at least 2 frames".into()));
    }
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().map_err(|e| err(&e))?;
    let wire: Vec<proto::Frame> = frames.iter().map(frame_to_proto).collect();
    let mut cost = ThreadsCost {
        threads,
        frames: frames.len(),
        samples_per_frame: frames[0].len(),
        cut: String::new(),
        stage_s: Vec::new(),
        pilot: None,
        steady_stage_s: threaded::stage_times(scene, frames, frames.len() / 2),
        cpu_1: Vec::new(),
        cpu_n: Vec::new(),
        cpu_tick_s: 0.0,
        offline_1: Vec::new(),
        offline_n: Vec::new(),
        copies_n: Vec::new(),
        service_1: Vec::new(),
        service_n: Vec::new(),
    };
    for t in 0..trials {
        for (n, into) in [(1, &mut cost.offline_1), (threads, &mut cost.offline_n)] {
            let (fps, cut, cpu) = offline(scene, frames, n);
            into.push(fps);
            let (per_frame, window) = cpu.unwrap_or_default();
            if n == 1 {
                cost.cpu_1 = per_frame;
                cost.cpu_tick_s = 0.0;
            } else {
                cost.cut = cut.to_string();
                cost.stage_s = cut.stage_s;
                cost.pilot = cut.pilot;
                cost.cpu_n = per_frame;
            }
            if window > 0 {
                cost.cpu_tick_s = cost.cpu_tick_s.max(1.0 / USER_HZ / window as f64);
            }
        }
        cost.copies_n.push(copies(scene, frames, threads)?);
        for (n, into) in [(1, &mut cost.service_1), (threads, &mut cost.service_n)] {
            let sensor = format!("threads-{t}-{n}");
            let (fps, _) = rt.block_on(trial(scene, &wire, &sensor, None, n, pilot_skip(frames.len())))?;
            into.push(fps);
        }
        progress(&format!(
            "trial {}: offline {:.0} / {:.0} frames/s ({threads} independent copies at once: {:.0}), service {:.0} / {:.0} frames/s (1 / {threads} threads)",
            t + 1,
            cost.offline_1[t],
            cost.offline_n[t],
            cost.copies_n[t],
            cost.service_1[t],
            cost.service_n[t]
        ));
    }
    Ok(cost)
}

/// Outcomes left off the clock out of `frames`: both pilots' and
/// start-up's, [`threaded::SETTLED_FRAMES`], where at least
/// [`threaded::PILOT_FRAMES`] follow them, else the first pilot's,
/// [`threaded::PILOT_FRAMES`], where as many follow it, else none.
fn pilot_skip(frames: usize) -> usize {
    [threaded::SETTLED_FRAMES, threaded::PILOT_FRAMES].into_iter().find(|&skip| frames >= skip + threaded::PILOT_FRAMES).unwrap_or(0)
}

/// `n` as an English ordinal: 1st, 2nd, 3rd, 4th, 11th, 12th, 13th, 21st, 101st.
fn ordinal(n: usize) -> String {
    let suffix = match (n % 10, n % 100) {
        (_, 11..=13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    format!("{n}{suffix}")
}

/// Steady-state outcomes per second of `frames` on `threads` threads, and
/// the cut: the clock runs from the outcome of frame [`pilot_skip`] on,
/// whatever the thread count (before it a pipeline on several threads runs
/// on one while it chooses its cut, and every pipeline pays its start-up),
/// or from the first outcome where there are too few frames for that.
///
/// Also, where /proc can be read, each pipeline thread's CPU time per frame
/// (see [`ThreadsCost::cpu_n`]) and the frames it is over (the CPU window):
/// from the first timed outcome to the one nine tenths of the way to the
/// last, and at least [`threaded::most_in_flight`] outcomes before the last
/// (the stage threads end before the outcomes still in flight at the end
/// come out). None where the window is empty, a stage thread ended within
/// it, or it holds under [`MIN_CPU_S`] of CPU time.
fn offline(scene: &Scene, frames: &[Frame], threads: usize) -> (f64, threaded::Cut, Option<CpuWindow>) {
    let skip = pilot_skip(frames.len());
    let (mut first, mut last, mut count, mut seen) = (None, None, 0usize, 0usize);
    let cpu_end = (skip + (frames.len() - skip) * 9 / 10).min(frames.len().saturating_sub(threaded::most_in_flight(threads)));
    let (mut cpu_from, mut cpu) = (None, None);
    let cut = threaded::run(scene, "bench", threads, frames.iter().cloned(), |o| {
        if o.reports.is_empty() && seen == frames.len() {
            return; // the final flush's outcome
        }
        render(o);
        seen += 1;
        if seen <= skip {
            return;
        }
        let now = Instant::now();
        first.get_or_insert(now);
        last = Some(now);
        count += 1;
        if count == 1 {
            cpu_from = pipeline_cpu_s();
        } else if seen == cpu_end
            && let (Some(from), Some(to)) = (&cpu_from, pipeline_cpu_s())
            // Every thread there at the start is there still.
            && from.iter().all(|f| to.iter().any(|t| t.0 == f.0))
        {
            let spent: Vec<(String, f64)> = to.into_iter().filter_map(|(tid, name, t)| from.iter().find(|f| f.0 == tid).map(|f| (name, t - f.2))).collect();
            if spent.iter().map(|s| s.1).sum::<f64>() >= MIN_CPU_S {
                let window = count - 1;
                cpu = Some((spent.into_iter().map(|(name, t)| (name, t / window as f64)).collect(), window));
            }
        }
    });
    let span = match (first, last) {
        (Some(a), Some(b)) => b.duration_since(a).as_secs_f64().max(1e-9),
        _ => f64::INFINITY,
    };
    ((count.saturating_sub(1)) as f64 / span, cut, cpu)
}

/// Steady-state frames/s of `n` independent copies of the one-thread arm
/// run at once, one per thread (the machine's yardstick): each copy is a
/// one-thread pipeline of its own over all of `frames`, run as [`offline`]
/// runs its arms (each report's JSON line rendered). Every copy runs its
/// first [`pilot_skip`] frames (at least one) off the clock and says so;
/// once all have, all start together, and the rate is the outcomes after
/// those, all copies', over the time from the first copy's start to the
/// last copy's last outcome (the slowest copy sets it, as the slowest
/// thread sets a cut's pace). A copy that panics before the start stops the
/// others (its panic goes on up); a thread that cannot be started is an
/// error.
fn copies(scene: &Scene, frames: &[Frame], n: usize) -> Result<f64, BenchError> {
    let skip = pilot_skip(frames.len());
    let runs: Vec<Option<Timed>> = std::thread::scope(|s| {
        let (ready_tx, ready_rx) = channel();
        let (mut gates, mut handles) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for k in 0..n {
            let (go_tx, go_rx) = channel();
            let ready = ready_tx.clone();
            let copy = std::thread::Builder::new().name(format!("tofwave-copy{k}")).spawn_scoped(s, move || timed_copy(scene, frames, skip, ready, go_rx));
            match copy {
                Ok(h) => {
                    gates.push(go_tx);
                    handles.push(h);
                }
                // The copies started wait for a start that will not come: the gates' close ends them.
                Err(e) => return Err(BenchError::Service(format!("starting copy {} of {n} of the one-thread pipeline: {e}", k + 1))),
            }
        }
        drop(ready_tx);
        // Every copy past its warm-up (a copy that panicked there dropped its sender unsent).
        if (0..n).all(|_| ready_rx.recv().is_ok()) {
            for g in &gates {
                let _ = g.send(());
            }
        }
        drop(gates);
        Ok(handles.into_iter().map(|h| h.join().unwrap_or_else(|p| std::panic::resume_unwind(p))).collect())
    })?;
    let runs: Vec<Timed> = runs.into_iter().flatten().collect();
    let start = runs.iter().map(|r| r.0).min();
    let end = runs.iter().filter_map(|r| r.1).max();
    let span = match (start, end) {
        (Some(a), Some(b)) => b.duration_since(a).as_secs_f64().max(1e-9),
        _ => f64::INFINITY,
    };
    Ok(runs.iter().map(|r| r.2).sum::<usize>() as f64 / span)
}

/// One copy's clock: its start, its last outcome's time (None with none)
/// and the outcomes between.
type Timed = (Instant, Option<Instant>, usize);

/// One copy of [`copies`]: a one-thread pipeline over `frames`, each
/// report's JSON line rendered; after its first `skip` outcomes (at least
/// one: the first frame's start-up is off every arm's clock) it says so on
/// `ready` and waits on `go`. Its clock then starts; None where `go` closed
/// unsent (another copy failed: the rest of the frames are not run).
fn timed_copy(scene: &Scene, frames: &[Frame], skip: usize, ready: Sender<()>, go: Receiver<()>) -> Option<Timed> {
    let (mut gate, mut seen, mut clock) = (Some((ready, go)), 0usize, None);
    let stopped = std::cell::Cell::new(false);
    let open = |gate: &mut Option<(Sender<()>, Receiver<()>)>| {
        let (ready, go) = gate.take()?;
        let _ = ready.send(());
        drop(ready);
        match go.recv() {
            Ok(()) => Some((Instant::now(), None, 0)),
            Err(_) => {
                stopped.set(true);
                None
            }
        }
    };
    threaded::run(scene, "bench", 1, frames.iter().take_while(|_| !stopped.get()).cloned(), |o| {
        if stopped.get() || o.reports.is_empty() && seen == frames.len() {
            return; // the final flush's outcome
        }
        render(o);
        seen += 1;
        match &mut clock {
            Some((_, last, count)) => {
                *last = Some(Instant::now());
                *count += 1;
            }
            None if seen == skip.max(1) => clock = open(&mut gate),
            None => {}
        }
    });
    clock
}

/// Renders each report's JSON line of `o`, as `process` writes them.
fn render(o: &threaded::Outcome) {
    for r in &o.reports {
        std::hint::black_box(report_json(r));
    }
}

/// Each pipeline thread's CPU time per frame (name, s/frame) over a CPU
/// window, and the frames in it.
type CpuWindow = (Vec<(String, f64)>, usize);

/// Least CPU time (s) over an arm's CPU window for its CPU time by thread
/// to be reported (/proc counts 10 ms ticks).
const MIN_CPU_S: f64 = 0.5;

/// CPU time so far (user + system, s) of the calling thread (named
/// "calling thread") and of the pipeline's stage threads ("tofwave-seg…"),
/// with their thread ids, from /proc (Linux); None where it cannot be read.
fn pipeline_cpu_s() -> Option<Vec<(u64, String, f64)>> {
    let me: u64 = std::fs::read_link("/proc/thread-self").ok()?.file_name()?.to_str()?.parse().ok()?;
    let mut out = Vec::new();
    for entry in std::fs::read_dir("/proc/self/task").ok()? {
        let Ok(entry) = entry else { continue };
        let Some(tid) = entry.file_name().to_str().and_then(|t| t.parse::<u64>().ok()) else { continue };
        // A thread that ended since the listing is skipped.
        let Ok(stat) = std::fs::read_to_string(entry.path().join("stat")) else { continue };
        let Some((name, cpu_s)) = stat_cpu_s(&stat) else { continue };
        let name = match (tid == me, name.starts_with(threaded::SEGMENT_THREAD_PREFIX)) {
            (true, _) => "calling thread".to_string(),
            (false, true) => name.to_string(),
            (false, false) => continue,
        };
        out.push((tid, name, cpu_s));
    }
    out.sort_by(|a, b| (a.1 != "calling thread", &a.1).cmp(&(b.1 != "calling thread", &b.1)));
    Some(out)
}

#[cfg(test)]
mod tests {
    /// The clock starts after both pilots where 400 outcomes follow them,
    /// else after the first where as many follow it, else at once.
    #[test]
    fn the_clock_skips_the_pilots_that_leave_400_outcomes_after_them() {
        for (frames, skip) in [(799, 0), (800, 400), (2599, 400), (2600, 2200), (6000, 2200)] {
            assert_eq!(super::pilot_skip(frames), skip, "{frames} frames");
        }
        let mut c = cost(&[], &[]);
        c.frames = 1000;
        assert!(c.markdown().contains("from the 401st outcome to the last (the first 400, the threaded pipeline's first pilot"));
        c.frames = 700;
        assert!(c.markdown().contains("each rate from the first outcome to the last"));
    }

    #[test]
    fn a_task_stat_line_gives_its_name_and_cpu_ticks() {
        // A name with a space and parentheses; utime 1234, stime 56.
        let line = "4242 (odd (name) x) S 1 2 3 4 5 6 7 8 9 10 1234 56 0 0 20 0 1 0 99 0 0";
        assert_eq!(super::stat_cpu_s(line), Some(("odd (name) x", 12.9)));
        assert_eq!(super::stat_cpu_s("4242 (short) S 1 2"), None);
        // This thread reads its own line, and names itself the calling thread.
        let me = super::pipeline_cpu_s();
        if cfg!(target_os = "linux") {
            let me = me.expect("/proc on Linux");
            assert_eq!(me.iter().filter(|t| t.1 == "calling thread").count(), 1, "{me:?}");
        }
    }

    /// A cost with the given per-thread CPU (µs/frame) on one and two threads.
    fn cost(cpu_1: &[(&str, f64)], cpu_n: &[(&str, f64)]) -> super::ThreadsCost {
        let us = |v: &[(&str, f64)]| v.iter().map(|(n, t)| (n.to_string(), t * 1e-6)).collect();
        super::ThreadsCost {
            threads: 2,
            frames: 6000,
            samples_per_frame: 2500,
            cut: "a+b (40 %) | c (60 %)".into(),
            stage_s: vec![("validate", 1e-6), ("a", 30e-6), ("c", 69e-6)],
            pilot: Some((2001, 2200)),
            steady_stage_s: vec![("validate", 1e-6), ("a", 19e-6), ("c", 80e-6)],
            cpu_1: us(cpu_1),
            cpu_n: us(cpu_n),
            cpu_tick_s: 2e-6,
            offline_1: vec![4000.0, 5000.0],
            offline_n: vec![7000.0, 7600.0],
            copies_n: vec![7600.0, 9500.0],
            service_1: vec![4000.0],
            service_n: vec![7200.0],
        }
    }

    #[test]
    fn the_report_bounds_the_speed_up_by_the_cpu_per_frame() {
        let c = cost(&[("calling thread", 200.0)], &[("calling thread", 10.0), ("tofwave-seg0", 110.0), ("tofwave-seg1", 130.0)]);
        let md = c.markdown();
        assert!(md.contains("| tofwave-seg0 | – | 110.0 |"), "{md}");
        assert!(md.contains("| calling thread | 200.0 | 10.0 |"), "{md}");
        assert!(md.contains("| all | 200.0 | 250.0 |"), "{md}");
        assert!(md.contains("+25 % CPU per frame"), "{md}");
        assert!(md.contains("at most 2 × 200.0 / 250.0 = 1.60× (that trial's: 1.52×)"), "{md}");
        assert!(md.contains("within ±2.0 µs/frame"), "{md}");
        // The ratio and the service's share to the digit that tells them from 1.8× and 80 %.
        assert!(md.contains("Offline 2 threads / 1 thread: **1.622×**; service with 2 workers / offline with 2 threads: **98.6 %**"), "{md}");
        assert!(md.contains("service with 1 worker / offline 1 thread: 88.9 %."), "{md}");
        // The machine's yardstick, over the same one-thread median, and the
        // pipeline's share of it; trial by trial against the same trial.
        assert!(md.contains("| offline, 2 independent copies of the 1-thread arm at once (the machine's yardstick) | 7600 / 9500 | 8550 |"), "{md}");
        assert!(md.contains("ran **1.900×** one alone"), "{md}");
        assert!(md.contains("it is a reference, not a bound"), "{md}");
        assert!(md.contains("The pipeline on 2 threads reached 85.4 % of it."), "{md}");
        assert!(md.contains("2 threads 1.750×, 1.520×; 2 copies 1.900×, 1.900×."), "{md}");
        // The pilot's stage times beside the steady state's, each with its share.
        assert!(md.contains("(2001–2200, whose times chose the cut)"), "{md}");
        assert!(md.contains("each rate from the 2201st outcome to the last (the first 2200, the threaded pipeline's two pilots"), "{md}");
        assert!(md.contains("| a | 30.0 | 30 % | 19.0 | 19 % |"), "{md}");
        // Without /proc (or with no stage threads) there is no CPU table, and the report says why.
        let none = cost(&[], &[]).markdown();
        assert!(!none.contains("CPU time per frame") && none.contains("| c | 69.0 | 69 % | 80.0 | 80 % |"), "{none}");
        assert!(none.contains("CPU time by thread: not measured"), "{none}");
        let pilot_only = cost(&[("calling thread", 200.0)], &[("calling thread", 190.0)]).markdown();
        assert!(pilot_only.contains("CPU time by thread: not measured"), "{pilot_only}");
    }

    /// A copy of the yardstick says it is ready after its warm-up and then
    /// waits: started, its clock counts the outcomes after the warm-up;
    /// never started (another copy failed), it gives up without a clock.
    #[test]
    fn a_copy_is_timed_from_its_start_and_gives_up_on_a_start_that_never_comes() {
        use std::sync::mpsc::channel;
        let scene = crate::scene::Scene::default_scene();
        let sim = crate::physics::Simulator::new(&scene).unwrap();
        let frames: Vec<_> = (0..20u64).map(|i| sim.frame(1, i).0).collect();
        let (ready_tx, ready_rx) = channel();
        let (go_tx, go_rx) = channel();
        go_tx.send(()).unwrap();
        let (start, last, count) = super::timed_copy(&scene, &frames, 5, ready_tx, go_rx).expect("started");
        assert!(ready_rx.recv().is_ok(), "it said it was ready");
        assert_eq!(count, 15, "the outcomes after the first 5");
        assert!(last.is_some_and(|t| t > start));
        let (ready_tx, ready_rx) = channel();
        let (go_tx, go_rx) = channel::<()>();
        drop(go_tx);
        assert!(super::timed_copy(&scene, &frames, 5, ready_tx, go_rx).is_none());
        assert!(ready_rx.recv().is_ok(), "ready before the start it waited for");
    }

    #[test]
    fn ordinals_take_the_english_suffix() {
        let got: Vec<String> = [1, 2, 3, 4, 11, 12, 13, 21, 22, 23, 101, 111, 201].into_iter().map(super::ordinal).collect();
        assert_eq!(got, ["1st", "2nd", "3rd", "4th", "11th", "12th", "13th", "21st", "22nd", "23rd", "101st", "111th", "201st"]);
    }
}
