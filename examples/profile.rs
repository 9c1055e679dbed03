//! Per-frame cost of one sensor's pipeline on one core, for profiling
//! (`valgrind --tool=callgrind`, `perf record`) and quick before/after
//! timings. Not part of the acceptance: `tofwave bench` is.
//!
//! ```text
//! cargo run --release --example profile -- SCENE METHOD [FRAMES] [PASSES]
//!   SCENE:  ref | ref-learned | default | lab  (or `peer`: the numpy/scipy
//!           peer comparison of `tofwave bench` alone, markdown; or `machine`:
//!           this core's f64 FMA rate and the memory bandwidth yardstick; or
//!           `limits`: the physical-limit table of `tofwave bench` alone)
//!   METHOD: ml | peak_parabolic | constant_fraction | scene
//! ```
//!
//! Prints CPU µs/frame of the calling thread (best of PASSES passes over the same frames, frames
//! cloned before the clock starts), the same after the first 256 frames of
//! each pass (start-up off the clock) where there are more than 512, and,
//! with `PROFILE_STAGES=1`, each stage's µs/frame from the threaded
//! engine's first pilot (frames 201-400, one thread). With `PROFILE_THREADS=N`
//! it instead runs the frames once through the threaded engine on N threads,
//! as `tofwave bench --threads` runs its offline arms, and prints wall
//! µs/frame and allocations/frame (whole process) after both pilots (frame 2200).


use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use tofwave::bench::{reference_frames, reference_scene};
use tofwave::frame::Frame;
use tofwave::physics::Simulator;
use tofwave::pipeline::Pipeline;
use tofwave::pipeline::learn::{LearnOptions, learn_shapes};
use tofwave::scene::{Scene, TimingMethod};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let which = args.first().map_or("ref", String::as_str);
    if which == "machine" {
        machine();
        return;
    }
    if which == "limits" {
        // The physical-limit table of `tofwave bench` alone (reference frames, ML).
        let scene = reference_scene();
        let (frames, _) = reference_frames(&scene, 20.0, 99, 2000);
        println!("{}", tofwave::bench::measure_limits(&scene, &frames, 400).markdown());
        return;
    }
    if which == "peer" {
        // The numpy/scipy peer on the reference frames, as `tofwave bench` runs it.
        let cfg = tofwave::bench::BenchConfig::default_run();
        let root = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR"));
        match tofwave::bench::run_peer(&reference_scene(), &cfg, &root, &root) {
            tofwave::bench::PeerOutcome::Ran(c) => println!("{}", c.markdown()),
            tofwave::bench::PeerOutcome::Failed(why) => println!("peer did not run: {why}"),
        }
        return;
    }
    let method = args.get(1).map_or("scene", String::as_str);
    let count: usize = args.get(2).map_or(2000, |s| s.parse().expect("FRAMES"));
    let passes: usize = args.get(3).map_or(3, |s| s.parse().expect("PASSES"));
    let (mut scene, frames) = match which {
        "ref" | "ref-learned" => {
            let mut scene = reference_scene();
            if which == "ref-learned" {
                let (shots, _) = reference_frames(&scene, 35.0, 7, 400);
                let opts = LearnOptions { passes: 3, ..Default::default() };
                scene = learn_shapes(&scene, "bench", &shots, &opts, |_| {}, |_| {}).expect("shapes learn");
            }
            let (frames, _) = reference_frames(&scene, 20.0, 99, count);
            (scene, frames)
        }
        "default" | "lab" => {
            let scene = if which == "lab" {
                Scene::load(std::path::Path::new("replay-data/scenes/lab-table-10-20.toml")).expect("lab scene")
            } else {
                Scene::default_scene()
            };
            let sim = Simulator::new(&scene).expect("scene simulates");
            let frames: Vec<Frame> = (0..count as u64).map(|i| sim.frame(1, i).0).collect();
            (scene, frames)
        }
        other => panic!("unknown scene {other}"),
    };
    scene.timing.method = match method {
        "ml" => TimingMethod::Ml,
        "peak_parabolic" => TimingMethod::PeakParabolic,
        "constant_fraction" => TimingMethod::ConstantFraction,
        "scene" => scene.timing.method,
        other => panic!("unknown method {other}"),
    };
    if let Some(n) = std::env::var_os("PROFILE_THREADS") {
        threads_probe(&scene, &frames, n.to_str().and_then(|n| n.parse().ok()).expect("PROFILE_THREADS=N"));
        return;
    }
    // Start-up (error tables, cached per process) is not a frame's cost.
    let mut warm = Pipeline::new(&scene, "bench");
    let mut out = Vec::new();
    for f in frames.iter().take(50).cloned() {
        warm.recycle(&mut out);
        warm.push(f, &mut out).expect("valid frames");
    }
    let (mut best, mut best_steady) = (f64::INFINITY, f64::INFINITY);
    let mut returns = 0;
    for _ in 0..passes {
        let (s, steady, r) = timed_pass(&scene, &frames);
        best = best.min(s);
        best_steady = best_steady.min(steady);
        returns = r;
    }
    println!("{which} {method}: {:.1} us/frame over {} frames ({returns} returns)", best / frames.len() as f64 * 1e6, frames.len());
    if frames.len() > 2 * STEADY_AFTER {
        println!(
            "{which} {method}: {:.1} us/frame after the first {STEADY_AFTER} (start-up off the clock)",
            best_steady / (frames.len() - STEADY_AFTER) as f64 * 1e6
        );
    }
    if std::env::var_os("PROFILE_REPORT").is_some() {
        let mut p = Pipeline::new(&scene, "bench");
        let mut out = Vec::new();
        p.push(frames[0].clone(), &mut out).expect("valid frames");
        println!("{}", tofwave::pipeline::report_json(&out[0]));
    }
    let pilot = tofwave::pipeline::threaded::PILOT_FRAMES;
    if std::env::var_os("PROFILE_STAGES").is_some() && frames.len() >= pilot {
        let cut = tofwave::pipeline::threaded::run(&scene, "bench", 2, frames.iter().take(pilot).cloned(), |_| {});
        for (name, s) in &cut.stage_s {
            println!("  {name:>18}: {:7.1} us/frame", s * 1e6);
        }
    }
}

/// Frames of a pass whose time the steady-state figure leaves out (a new
/// pipeline's start-up: plans, the timing error tables, colour and nulls),
/// as `tofwave bench`'s peer comparison does.
const STEADY_AFTER: usize = 256;

/// One pass over `frames` on a fresh pipeline: (seconds, seconds after the
/// first [`STEADY_AFTER`] frames, returns). The profiler's collection can
/// be limited to this function (`--toggle-collect=profile::timed_pass`).
#[inline(never)]
fn timed_pass(scene: &Scene, frames: &[Frame]) -> (f64, f64, usize) {
    let mut p = Pipeline::new(scene, "bench");
    let owned = frames.to_vec();
    let mut out = Vec::new();
    let mut returns = 0;
    let t0 = thread_cpu_s();
    let mut t_steady = t0;
    for (i, f) in owned.into_iter().enumerate() {
        if i == STEADY_AFTER {
            t_steady = thread_cpu_s();
        }
        p.recycle(&mut out);
        p.push(f, &mut out).expect("valid frames");
        returns += out.iter().map(|r| r.returns.len()).sum::<usize>();
    }
    let t1 = thread_cpu_s();
    (t1 - t0, t1 - t_steady, returns)
}

/// CPU time of the calling thread, s: on a loaded machine wall time counts
/// the time the thread waited for a core.
fn thread_cpu_s() -> f64 {
    #[repr(C)]
    struct Timespec {
        tv_sec: i64,
        tv_nsec: i64,
    }
    unsafe extern "C" {
        fn clock_gettime(clock: i32, tp: *mut Timespec) -> i32;
    }
    const CLOCK_THREAD_CPUTIME_ID: i32 = 3;
    let mut t = Timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes one timespec through a valid pointer.
    let rc = unsafe { clock_gettime(CLOCK_THREAD_CPUTIME_ID, &mut t) };
    assert_eq!(rc, 0, "clock_gettime");
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

/// The machine's yardsticks for the physical-limit table: f64 fused
/// multiply-adds per second on one core (independent chains, the widest
/// vectors the CPU has) and the bench's copy / read bandwidth.
fn machine() {
    let fma = fma_rate();
    println!("f64 FMA, one core: {:.2e} FMA/s ({:.1} GFLOP/s)", fma, 2.0 * fma / 1e9);
    let bw = tofwave::bench::measure_bandwidth(2500, 4096);
    println!(
        "read-only {:.1} GB/s, copy {:.1} GB/s (read + write), i16 accumulate {:.1} GB/s read (stream {} MB, wall time)",
        bw.read_bytes_per_s / 1e9,
        bw.copy_bytes_per_s / 1e9,
        bw.average_bytes_per_s / 1e9,
        bw.stream_bytes / 1_000_000
    );
}

/// Best of five CPU-timed runs of 64 independent FMA chains.
fn fma_rate() -> f64 {
    const ITER: usize = 20_000_000;
    let mut best = 0.0f64;
    for _ in 0..5 {
        let t0 = thread_cpu_s();
        std::hint::black_box(tofwave::bench::fma_chains(ITER, std::hint::black_box(1.000_000_1)));
        let s = thread_cpu_s() - t0;
        best = best.max((ITER * 64) as f64 / s);
    }
    best
}

/// Counts every allocation of this process (all threads), for
/// `PROFILE_THREADS`' allocations per frame.
struct Counting;

static ALLOCATIONS: AtomicU64 = AtomicU64::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Relaxed);
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Relaxed);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// `threaded::run` on `threads` threads as `tofwave bench --threads` runs
/// its offline arms (frames cloned as they go in, each report's JSON
/// rendered): wall µs/frame from the outcome of frame
/// `threaded::SETTLED_FRAMES` on (both pilots over), and the allocations per frame over the same
/// span, whole process (the frame's clone and the JSON included).
fn threads_probe(scene: &Scene, frames: &[Frame], threads: usize) {
    let skip = tofwave::pipeline::threaded::SETTLED_FRAMES;
    let want = skip + tofwave::pipeline::threaded::PILOT_FRAMES;
    assert!(frames.len() >= want, "PROFILE_THREADS wants at least {want} frames");
    let (mut first, mut last, mut seen, mut allocations) = (None, None, 0usize, 0u64);
    let cut = tofwave::pipeline::threaded::run(scene, "bench", threads, frames.iter().cloned(), |o| {
        if o.reports.is_empty() && seen == frames.len() {
            return; // the final flush's outcome
        }
        for r in &o.reports {
            std::hint::black_box(tofwave::pipeline::report_json(r));
        }
        seen += 1;
        if seen == skip {
            first = Some(std::time::Instant::now());
            ALLOCATIONS.store(0, Relaxed);
        }
        last = Some(std::time::Instant::now());
        allocations = ALLOCATIONS.load(Relaxed);
    });
    let (Some(a), Some(b)) = (first, last) else { return };
    let (counted, allocations) = ((seen - skip) as f64, allocations as f64);
    println!(
        "{threads} threads: {:.1} us/frame wall after the first {skip}, {:.2} allocations/frame; cut {cut}",
        b.duration_since(a).as_secs_f64() / counted * 1e6,
        allocations / counted
    );
}
