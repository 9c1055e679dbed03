//! Whole-pipeline throughput on 2500-sample i16 frames, one core. The
//! reference frames of `tofwave bench` (64-tap template, white noise, 20 dB,
//! matched-filter Neyman–Pearson detection) per timing method and for N = 64
//! averaging; and the ML method on the physics bench scene (coloured receiver
//! noise). Run: `cargo bench --bench pipeline`.

use criterion::{BatchSize, Criterion, Throughput, criterion_group, criterion_main};

use tofwave::bench::{bench_scene, reference_frames, reference_scene, snr_scene};
use tofwave::frame::Frame;
use tofwave::physics::Simulator;
use tofwave::pipeline::Pipeline;
use tofwave::scene::{Scene, TimingMethod};

/// Distinct frames cycled through, so the branch predictor does not learn one frame.
const FRAMES: usize = 256;

fn bench_one(c: &mut Criterion, group: &str, name: &str, scene: &Scene, frames: &[Frame]) {
    let mut g = c.benchmark_group(group);
    g.throughput(Throughput::Elements(1));
    let mut p = Pipeline::new(scene, "bench");
    let mut reports = Vec::with_capacity(4);
    let mut k = 0usize;
    g.bench_function(name, |b| {
        b.iter_batched(
            || {
                k = (k + 1) % frames.len();
                frames[k].clone()
            },
            |f| {
                reports.clear();
                p.push(f, &mut reports).expect("bench frames are valid");
                reports.len()
            },
            BatchSize::SmallInput,
        )
    });
    g.finish();
}

fn pipeline(c: &mut Criterion) {
    let reference = reference_scene();
    let (frames, _) = reference_frames(&reference, 20.0, 1, FRAMES);
    for (name, method, n) in [
        ("ml", TimingMethod::Ml, 1),
        ("peak_parabolic", TimingMethod::PeakParabolic, 1),
        ("peak_gaussian", TimingMethod::PeakGaussian, 1),
        ("constant_fraction", TimingMethod::ConstantFraction, 1),
        ("leading_edge", TimingMethod::LeadingEdge, 1),
        ("ml_avg64 (per input frame)", TimingMethod::Ml, 64),
    ] {
        let mut s = reference.clone();
        s.timing.method = method;
        s.averaging.frames = n;
        bench_one(c, "pipeline_reference_2500_i16", name, &s, &frames);
    }
    let (mut physics, _) = snr_scene(&bench_scene(), 0.5, 20.0).expect("the bench scene simulates");
    physics.timing.method = TimingMethod::Ml;
    let sim = Simulator::new(&physics).expect("the bench scene simulates");
    let frames: Vec<Frame> = (0..FRAMES as u64).map(|i| sim.frame(1, i).0).collect();
    bench_one(c, "pipeline_bench_scene_2500_i16", "ml", &physics, &frames);
}

criterion_group!(benches, pipeline);
criterion_main!(benches);
