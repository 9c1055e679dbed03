//! Whole-pipeline throughput on 2500-sample i16 frames (the bench scene:
//! matched-filter Neyman–Pearson detection, 14-bit digitiser), per timing
//! method and for N = 64 averaging. Run: `cargo bench --bench pipeline`.

use criterion::{BatchSize, Criterion, Throughput, criterion_group, criterion_main};

use tofwave::bench::{bench_scene, snr_scene};
use tofwave::frame::Frame;
use tofwave::physics::Simulator;
use tofwave::pipeline::Pipeline;
use tofwave::scene::TimingMethod;

/// Distinct frames cycled through, so the branch predictor does not learn one frame.
const FRAMES: usize = 256;

fn pipeline(c: &mut Criterion) {
    let (scene, _) = snr_scene(&bench_scene(), 0.5, 20.0).expect("the bench scene simulates");
    let sim = Simulator::new(&scene).expect("the bench scene simulates");
    let frames: Vec<Frame> = (0..FRAMES as u64).map(|i| sim.frame(1, i).0).collect();
    let mut group = c.benchmark_group("pipeline_2500_i16");
    group.throughput(Throughput::Elements(1));
    for (name, method, n) in [
        ("ml", TimingMethod::Ml, 1),
        ("peak_parabolic", TimingMethod::PeakParabolic, 1),
        ("constant_fraction", TimingMethod::ConstantFraction, 1),
        ("leading_edge", TimingMethod::LeadingEdge, 1),
        ("ml_avg64 (per input frame)", TimingMethod::Ml, 64),
    ] {
        let mut s = scene.clone();
        s.timing.method = method;
        s.averaging.frames = n;
        let mut p = Pipeline::new(&s, "bench");
        let mut reports = Vec::with_capacity(4);
        let mut k = 0usize;
        group.bench_function(name, |b| {
            b.iter_batched(
                || {
                    k = (k + 1) % FRAMES;
                    frames[k].clone()
                },
                |f| {
                    reports.clear();
                    p.push(f, &mut reports).expect("simulated frames are valid");
                    reports.len()
                },
                BatchSize::SmallInput,
            )
        });
    }
    group.finish();
}

criterion_group!(benches, pipeline);
criterion_main!(benches);
