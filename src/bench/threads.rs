//! `tofwave bench --threads N`: one sensor on N threads, offline
//! (`process --threads`) and in the service (`serve --workers-per-sensor`),
//! against one thread, on the same frames in trials alternating the arms.
//!
//! Rates are steady-state: outcomes (offline) or reports reaching a
//! subscriber (service) from the 401st to the last, divided by the time
//! between them, on every arm: the first 400 frames are those the threaded
//! pipeline runs on one thread to choose its cut, and those in which any
//! pipeline pays its start-up. (With fewer than 800 frames per trial the
//! clock starts at the first.)
//!
//! Every arm renders each report's JSON line: the offline arms as `process`
//! does (on its calling thread, as the frames finish), the service for its
//! subscribers (every report carries its line). Left out of the offline
//! arms, that work (a few µs per report) would count against the service
//! alone.

use std::time::Instant;

use super::BenchError;
use super::cluster::trial;
use super::service::median;
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
    /// Offline frames/s per trial, one thread.
    pub offline_1: Vec<f64>,
    /// Offline frames/s per trial, N threads.
    pub offline_n: Vec<f64>,
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
            format!("; each rate from the {} outcome to the last (the first {skip}, the threaded pipeline's pilot on one thread and every arm's start-up, off the clock)", ordinal(skip + 1))
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
        md += &row("service, 1 worker (`serve`)", &self.service_1);
        md += &row(&format!("service, {n} workers (`serve --workers-per-sensor {n}`)"), &self.service_n);
        md += &format!(
            "\nOffline {n} threads / 1 thread: **{:.2}×**; service with {n} workers / offline with {n} threads: **{:.0} %**; \
             service with 1 worker / offline 1 thread: {:.0} %. Cut: {}.\n",
            self.offline_speedup(),
            100.0 * self.service_share(),
            100.0 * median(&self.service_1) / median(&self.offline_1),
            self.cut
        );
        if !self.stage_s.is_empty() {
            let total: f64 = self.stage_s.iter().map(|s| s.1).sum();
            md += "\nStage times per frame on one thread (the pilot's timed frames):\n\n| stage | µs/frame | share |\n|---|---|---|\n";
            for (name, t) in &self.stage_s {
                md += &format!("| {name} | {:.1} | {:.0} % |\n", t * 1e6, 100.0 * t / total);
            }
        }
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
        offline_1: Vec::new(),
        offline_n: Vec::new(),
        service_1: Vec::new(),
        service_n: Vec::new(),
    };
    for t in 0..trials {
        for (n, into) in [(1, &mut cost.offline_1), (threads, &mut cost.offline_n)] {
            let (fps, cut) = offline(scene, frames, n);
            into.push(fps);
            if n == threads {
                cost.cut = cut.to_string();
                cost.stage_s = cut.stage_s;
            }
        }
        for (n, into) in [(1, &mut cost.service_1), (threads, &mut cost.service_n)] {
            let sensor = format!("threads-{t}-{n}");
            let (fps, _) = rt.block_on(trial(scene, &wire, &sensor, None, n, pilot_skip(frames.len())))?;
            into.push(fps);
        }
        progress(&format!(
            "trial {}: offline {:.0} / {:.0} frames/s, service {:.0} / {:.0} frames/s (1 / {threads} threads)",
            t + 1,
            cost.offline_1[t],
            cost.offline_n[t],
            cost.service_1[t],
            cost.service_n[t]
        ));
    }
    Ok(cost)
}

/// Outcomes left off the clock out of `frames`: [`threaded::PILOT_FRAMES`]
/// where there are at least twice as many frames, else none.
fn pilot_skip(frames: usize) -> usize {
    if frames >= 2 * threaded::PILOT_FRAMES { threaded::PILOT_FRAMES } else { 0 }
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
/// the cut: the clock runs from the outcome of frame
/// [`threaded::PILOT_FRAMES`] on, whatever the thread count (before it a
/// pipeline on several threads runs on one while it chooses its cut, and
/// every pipeline pays its start-up), unless there are too few frames for
/// that, then from the first outcome.
fn offline(scene: &Scene, frames: &[Frame], threads: usize) -> (f64, threaded::Cut) {
    let skip = pilot_skip(frames.len());
    let (mut first, mut last, mut count, mut seen) = (None, None, 0usize, 0usize);
    let cut = threaded::run(scene, "bench", threads, frames.iter().cloned(), |o| {
        if o.reports.is_empty() && seen == frames.len() {
            return; // the final flush's outcome
        }
        for r in &o.reports {
            std::hint::black_box(report_json(r));
        }
        seen += 1;
        if seen <= skip {
            return;
        }
        let now = Instant::now();
        first.get_or_insert(now);
        last = Some(now);
        count += 1;
    });
    let span = match (first, last) {
        (Some(a), Some(b)) => b.duration_since(a).as_secs_f64().max(1e-9),
        _ => f64::INFINITY,
    };
    ((count.saturating_sub(1)) as f64 / span, cut)
}

#[cfg(test)]
mod tests {
    #[test]
    fn ordinals_take_the_english_suffix() {
        let got: Vec<String> = [1, 2, 3, 4, 11, 12, 13, 21, 22, 23, 101, 111, 201].into_iter().map(super::ordinal).collect();
        assert_eq!(got, ["1st", "2nd", "3rd", "4th", "11th", "12th", "13th", "21st", "22nd", "23rd", "101st", "111th", "201st"]);
    }
}
