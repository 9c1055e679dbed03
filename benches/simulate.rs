//! Simulator speed: one frame of each shipped scene (2500 samples per channel
//! unless the scene says otherwise), on one core. Issue target: 10⁵ frames of
//! 2500 samples in under 10 s, i.e. under 100 µs per frame; the bench prints
//! the time for 10⁵ frames at the measured rate.
//!
//! Run: `cargo bench --bench simulate` (add `-- --quick` for a fast pass).

use std::hint::black_box;
use std::time::Instant;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use tofwave::physics::Simulator;
use tofwave::scene::Scene;

fn scene(name: &str) -> Scene {
    let path = format!("{}/replay-data/scenes/{name}.toml", env!("CARGO_MANIFEST_DIR"));
    Scene::load(std::path::Path::new(&path)).expect("shipped scene loads")
}

fn simulate(c: &mut Criterion) {
    let mut g = c.benchmark_group("simulate");
    g.throughput(Throughput::Elements(1));
    for name in ["lab-table-10-20", "mains-interference", "daylight", "far-150m-1mhz"] {
        let sc = scene(name);
        let sim = Simulator::new(&sc).expect("simulates");
        let mut i = 0u64;
        g.bench_function(name, |b| {
            b.iter(|| {
                i += 1;
                black_box(sim.frame(1, i))
            })
        });
    }
    g.finish();
}

/// 10⁵ frames of the lab scene, timed once end to end (what the issue asks).
fn hundred_thousand(_: &mut Criterion) {
    let sim = Simulator::new(&scene("lab-table-10-20")).expect("simulates");
    let n = if std::env::args().any(|a| a == "--quick") { 10_000 } else { 100_000 };
    let t = Instant::now();
    let mut samples = 0usize;
    for i in 0..n {
        let (f, _) = sim.frame(2, i);
        samples += f.channels.iter().map(|c| c.samples.len()).sum::<usize>();
        black_box(&f);
    }
    let s = t.elapsed().as_secs_f64();
    println!(
        "simulate lab-table-10-20: {n} frames ({} samples per frame, all channels) in {s:.2} s on one core = {:.1} us/frame; 10^5 frames: {:.2} s (target < 10 s)",
        samples / n as usize,
        s / n as f64 * 1e6,
        s / n as f64 * 1e5
    );
}

criterion_group!(benches, simulate, hundred_thousand);
criterion_main!(benches);
