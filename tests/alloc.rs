//! Steady-state heap allocations of the pipeline, per configuration.
//!
//! A counting global allocator (this test binary's own) counts the
//! allocations made on the test's thread while frames go through a warmed-up
//! pipeline. Frames are prepared before counting (they are the caller's), and
//! reports are handed back with `Pipeline::recycle` (the documented way to
//! reuse their storage). Every configuration expects zero, so any new
//! allocation on the per-frame path fails here; a self-test checks that an
//! allocation made while a frame goes through is counted.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::PathBuf;

use tofwave::capture::{read_paths, ReadOptions};
use tofwave::frame::Frame;
use tofwave::physics::Simulator;
use tofwave::pipeline::threaded::{Outcome, Staged};
use tofwave::pipeline::{Observer, Pipeline};
use tofwave::scene::Scene;

struct Counting;

thread_local! {
    /// Counting is on for this thread.
    static ON: Cell<bool> = const { Cell::new(false) };
    /// Allocations (and reallocations) counted on this thread.
    static COUNT: Cell<u64> = const { Cell::new(0) };
}

fn note() {
    // `try_with`: the allocator may run while thread-locals are torn down.
    let _ = ON.try_with(|on| {
        if on.get() {
            let _ = COUNT.try_with(|c| c.set(c.get() + 1));
        }
    });
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `text` (scene TOML) with `overrides` ("section.key", TOML value) applied.
fn scene_with(text: &str, overrides: &[(&str, &str)]) -> Scene {
    let mut doc: toml::Table = text.parse().expect("scene TOML parses");
    for (key, value) in overrides {
        let parsed: toml::Table = format!("v = {value}").parse().expect("override value parses");
        let mut parts: Vec<&str> = key.split('.').collect();
        let leaf = parts.pop().expect("non-empty key");
        let mut table = &mut doc;
        for p in parts {
            table = table
                .entry(p)
                .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                .as_table_mut()
                .expect("a table");
        }
        table.insert(leaf.to_string(), parsed["v"].clone());
    }
    Scene::from_toml_str(&toml::to_string(&doc).expect("serialises"), "alloc").expect("scene is valid")
}

fn scene_file(name: &str, overrides: &[(&str, &str)]) -> Scene {
    let text = std::fs::read_to_string(root().join("replay-data/scenes").join(name)).expect("shipped scene");
    scene_with(&text, overrides)
}

fn simulated(scene: &Scene, count: u64) -> Vec<Frame> {
    let sim = Simulator::new(scene).expect("simulator builds");
    (0..count).map(|i| sim.frame(7, i).0).collect()
}

/// Frames to warm up on: past the whitener's refits at frames 1, 2, 4, …, 128
/// (the next is at 192, after the counted frames).
const WARM: usize = 130;
/// Frames counted.
const COUNTED: usize = 48;

/// Allocations while `COUNTED` frames go through a pipeline warmed on `WARM`
/// frames (`frames` repeats when shorter, with fresh sequence numbers).
fn steady_state_allocations(scene: &Scene, frames: &[Frame]) -> u64 {
    steady_state_allocations_observed(scene, frames, None)
}

/// [`steady_state_allocations`] with `observer` seeing every finished unit
/// of work (inside `push`, so what it allocates is counted).
fn steady_state_allocations_observed(scene: &Scene, frames: &[Frame], observer: Option<Observer>) -> u64 {
    let mut p = Pipeline::new(scene, "alloc");
    if let Some(o) = observer {
        p.set_observer(o);
    }
    let mut batch: Vec<Frame> = (0..WARM + COUNTED)
        .map(|i| {
            let mut f = frames[i % frames.len()].clone();
            f.sequence = i as u64;
            f
        })
        .collect();
    let counted: Vec<Frame> = batch.split_off(WARM);
    let mut out = Vec::with_capacity(8);
    let mut reports = 0;
    for f in batch {
        p.recycle(&mut out);
        p.push(f, &mut out).expect("frame accepted");
    }
    COUNT.with(|c| c.set(0));
    ON.with(|on| on.set(true));
    for f in counted {
        p.recycle(&mut out);
        let _ = p.push(f, &mut out);
        reports += out.len();
    }
    ON.with(|on| on.set(false));
    assert!(reports > 0, "the counted frames gave reports");
    let count = COUNT.with(|c| c.get());
    eprintln!("{count} allocations over {COUNTED} frames ({reports} reports)");
    count
}

fn lecroy() -> Vec<Frame> {
    read_paths(&[root().join("replay-data/lecroy_4.trc")], &ReadOptions::default()).expect("shipped capture reads")
}

fn lab(overrides: &[(&str, &str)]) -> u64 {
    let scene = scene_file("lab-table-10-20.toml", overrides);
    let frames = simulated(&scene, 32);
    steady_state_allocations(&scene, &frames)
}

fn burst(overrides: &[(&str, &str)]) -> u64 {
    let scene = scene_file("burst-1m83.toml", overrides);
    let frames = simulated(&scene, 64);
    steady_state_allocations(&scene, &frames)
}

/// Asserts each case's count equals its expected count (0 everywhere
/// today), listing every case when one differs.
fn assert_counts(cases: &[(&str, u64, u64)]) {
    let wrong: Vec<_> = cases.iter().filter(|c| c.1 != c.2).collect();
    assert!(wrong.is_empty(), "(case, allocations, expected) differ: {wrong:?}; all: {cases:?}");
}

const METHODS: [&str; 5] = ["constant_fraction", "leading_edge", "peak_parabolic", "peak_gaussian", "ml"];

#[test]
fn default_scene_on_a_shipped_capture_allocates_nothing_per_frame() {
    let frames = lecroy();
    let counts: Vec<u64> = METHODS
        .iter()
        .map(|m| {
            let scene = scene_with(&Scene::default_scene().to_toml(), &[("timing.method", &format!("\"{m}\""))]);
            steady_state_allocations(&scene, &frames)
        })
        .collect();
    let cases: Vec<(&str, u64, u64)> = METHODS.iter().zip(&counts).map(|(m, &c)| (*m, c, 0)).collect();
    assert_counts(&cases);
}

/// The default scene's own frames: 8-bit codes, interference events in the
/// gates (the cleaner counts the gate's colour on the codes) and learned
/// event templates aligned on later frames.
#[test]
fn default_scene_on_its_simulated_frames_allocates_nothing_per_frame() {
    let scene = Scene::default_scene();
    let frames = simulated(&scene, 200);
    assert_counts(&[("default scene", steady_state_allocations(&scene, &frames), 0)]);
}

/// `process --threads 1`'s engine: the staged pipeline on the calling
/// thread, each outcome's reports handed back with `Staged::recycle`.
#[test]
fn staged_pipeline_on_one_thread_with_outcomes_recycled_allocates_nothing_per_frame() {
    let scene = Scene::default_scene();
    let frames = simulated(&scene, 64);
    let mut staged = Staged::new(&scene, "alloc", 1);
    let mut out: Vec<Outcome> = Vec::with_capacity(8);
    let mut reports = 0;
    // Frames are the caller's: made before counting.
    let batch: Vec<Frame> = (0..WARM + COUNTED)
        .map(|i| {
            let mut f = frames[i % frames.len()].clone();
            f.sequence = i as u64;
            f
        })
        .collect();
    for (i, f) in batch.into_iter().enumerate() {
        if i == WARM {
            COUNT.with(|c| c.set(0));
            ON.with(|on| on.set(true));
        }
        staged.push(f, &mut out);
        for o in out.drain(..) {
            assert!(o.result.is_ok() && o.panic.is_none(), "frame {i} accepted");
            reports += o.reports.len();
            staged.recycle(o.reports);
        }
    }
    ON.with(|on| on.set(false));
    assert!(reports > 0, "the frames gave reports");
    let count = COUNT.with(|c| c.get());
    assert_counts(&[("staged, one thread", count, 0)]);
}

/// Maximum-likelihood timing resolves the lab scene's five returns jointly
/// (`detect::resolve::Resolver`, whose refit reuses its buffers).
#[test]
fn lab_scene_with_every_timing_method_allocates_nothing_per_frame() {
    let counts: Vec<u64> = METHODS.iter().map(|m| lab(&[("timing.method", &format!("\"{m}\""))])).collect();
    let cases: Vec<(&str, u64, u64)> = METHODS.iter().zip(&counts).map(|(m, &c)| (*m, c, 0)).collect();
    assert_counts(&cases);
}

/// The CFAR plan follows the per-cell probability, which follows the pooled
/// noise-colour estimate frame by frame: it is redesigned in place
/// (`CfarPlan::redesign`), keeping its buffers.
#[test]
fn lab_scene_with_whitening_cfar_and_baseline_allocates_nothing_per_frame() {
    assert_counts(&[
        ("whiten", lab(&[("detector.whiten", "true")]), 0),
        ("cfar ca", lab(&[("detector.cfar", "\"ca\"")]), 0),
        ("cfar os", lab(&[("detector.cfar", "\"os\"")]), 0),
        ("baseline", lab(&[("baseline.smoothing", "0.5")]), 0),
    ]);
}

/// At pfa 0.4 the noise gates cross the self-check's level in about every
/// other frame: the events stage judges those excursions (and the context ones
/// over what the cleaning left out) with its scratch taken once.
#[test]
fn lab_scene_with_gate_crossings_judged_by_the_events_stage_allocates_nothing_per_frame() {
    assert_counts(&[
        ("pfa 0.4", lab(&[("detector.pfa", "0.4")]), 0),
        ("pfa 0.4, cfar ca", lab(&[("detector.pfa", "0.4"), ("detector.cfar", "\"ca\"")]), 0),
    ]);
}

/// The cleaned stop channel becomes the frame's F64 samples; its storage is
/// lent to the frame (`Work::set_volts`) and comes back when the report goes
/// out, so the next frame reuses it.
#[test]
fn burst_scene_with_each_denoise_method_allocates_nothing_per_frame() {
    assert_counts(&[
        ("template", burst(&[("denoise.method", "\"template\""), ("denoise.learn_frames", "24")]), 0),
        ("notch", burst(&[("denoise.method", "\"notch\""), ("denoise.notch_frequencies_hz", "[2e6, 5e6]")]), 0),
        ("highpass", burst(&[("denoise.method", "\"highpass\"")]), 0),
    ]);
}

/// Averaging reuses its accumulators and kept frames' volts, lends the mean
/// channels' storage to the output frame, and hands the frames it averaged
/// away back to the pipeline (`Stage::consumed`), whose units keep their
/// buffers.
#[test]
fn lab_scene_with_averaging_allocates_nothing_per_frame() {
    assert_counts(&[
        ("block", lab(&[("averaging.frames", "4")]), 0),
        ("sliding", lab(&[("averaging.frames", "4"), ("averaging.mode", "\"sliding\"")]), 0),
        ("trimmed block", lab(&[("averaging.frames", "4"), ("averaging.method", "\"trimmed_mean\"")]), 0),
        (
            "median sliding",
            lab(&[("averaging.frames", "4"), ("averaging.mode", "\"sliding\""), ("averaging.method", "\"median\"")]),
            0,
        ),
        ("block, stationarity guard", lab(&[("averaging.frames", "8"), ("averaging.stationarity_block", "2")]), 0),
        (
            "template denoise, block",
            burst(&[("denoise.method", "\"template\""), ("denoise.learn_frames", "24"), ("averaging.frames", "4")]),
            0,
        ),
    ]);
}

/// The count is falsifiable: one allocation per finished frame, made while
/// the frame goes through the pipeline (by an observer), is seen, exactly.
#[test]
fn an_allocation_on_the_per_frame_path_is_counted() {
    let frames = lecroy();
    let scene = Scene::default_scene();
    let observer: Observer = Box::new(|w| {
        std::hint::black_box(vec![w.frame.sequence; 1]);
    });
    assert_eq!(steady_state_allocations_observed(&scene, &frames, Some(observer)), COUNTED as u64);
    assert_eq!(steady_state_allocations(&scene, &frames), 0);
}

/// Per-sensor metric handles, once registered, record without allocating
/// (the service records on every frame).
#[test]
fn sensor_metrics_record_without_allocating_after_first_use() {
    use tofwave::telemetry::SensorMetrics;
    let _ = tofwave::telemetry::prometheus_handle();
    let m = SensorMetrics::new("alloc-free");
    // The processing histogram is left out: the exporter stores its samples
    // in blocks it allocates as they fill, however the handle is kept.
    let record = |m: &SensorMetrics| {
        m.frame_received();
        m.frames_rejected("pipeline", 1);
        m.report_published(3);
        m.sequence_gap(1);
        m.queue_depth(2);
        m.frame_recorded();
        m.false_alarm(1e-7, [0.0, 3e-6], 1.4e-8);
    };
    record(&m); // registers the handles
    COUNT.with(|c| c.set(0));
    ON.with(|on| on.set(true));
    for _ in 0..100 {
        record(&m);
    }
    ON.with(|on| on.set(false));
    let allocations = COUNT.with(|c| c.get());
    assert_eq!(allocations, 0, "allocations while recording 100 frames");
    let text = tofwave::telemetry::prometheus_handle().render();
    let received = text.lines().find_map(|l| {
        let rest = l.strip_prefix("tofwave_frames_received_total{")?;
        rest.contains("sensor=\"alloc-free\"").then(|| l.rsplit_once(' ').unwrap().1.parse::<f64>().unwrap())
    });
    assert_eq!(received, Some(101.0));
}
