//! No return is reported twice: random multi-return frames from the
//! independent generator (one to five returns, random ranges and amplitudes
//! from the detection threshold up, overlapping ones included; sharp-onset
//! pulses, 8-bit quantisation) through every timing method;
//! no two returns of a report may share a timing point (within 0.1 ns).

use crate::common;

use common::rng;
use common::seedgen::{frame_with_seed, GenConfig};
use rand::Rng;
use tofwave::frame::Report;
use tofwave::pipeline::Pipeline;
use tofwave::scene::{Scene, TimingMethod};

/// Frames per timing method, 10⁵ in all (the model fit, whose resolver
/// refits overlapping returns jointly, is the slow one and gets fewer);
/// about 50 s single-threaded.
const FRAMES: [u64; 5] = [24_000, 24_000, 24_000, 24_000, 4_000];

#[test]
fn no_report_holds_the_same_return_twice() {
    check(FRAMES, 900);
}

/// Runs `frames[m]` random multi-return frames through timing method m
/// (seeds from `seed`) and asserts no report holds a return twice.
fn check(frames: [u64; 5], seed: u64) {
    let methods = [
        TimingMethod::ConstantFraction,
        TimingMethod::LeadingEdge,
        TimingMethod::PeakParabolic,
        TimingMethod::PeakGaussian,
        TimingMethod::Ml,
    ];
    let mut duplicates = Vec::new();
    let mut returns = 0usize;
    for (m, &method) in methods.iter().enumerate() {
        let mut scene = Scene::default_scene();
        scene.timing.method = method;
        let mut p = Pipeline::new(&scene, "duplicates");
        let mut r = rng(seed + m as u64);
        let mut cfg = GenConfig::default();
        // A fixed 2.5 V vertical scale, as for a scene with returns up to ~2 V.
        cfg.full_scale_v = Some(2.5);
        let mut out: Vec<Report> = Vec::new();
        for seq in 0..frames[m] {
            let n = r.random_range(1..=5);
            cfg.targets = (0..n)
                .map(|_| {
                    // 3 to 220 m: the range gate; SNR 1.5 to 100 against 13.8 mV.
                    let range = r.random_range(3.0..220.0);
                    let amp = 0.0138 * (1.5f64.ln() + r.random::<f64>() * (100.0f64 / 1.5).ln()).exp();
                    (range, amp)
                })
                .collect();
            let (frame, _) = frame_with_seed(&cfg, seed + 200 + m as u64, seq);
            out.clear();
            p.push(frame, &mut out).expect("frame");
            for rep in &out {
                returns += rep.returns.len();
                for (i, a) in rep.returns.iter().enumerate() {
                    for b in &rep.returns[i + 1..] {
                        if (a.t_stop_s - b.t_stop_s).abs() < 0.1e-9 {
                            duplicates.push(format!(
                                "{} frame {seq}: {:.4} m ({:.3} V) and {:.4} m ({:.3} V)",
                                method.name(),
                                a.range_m,
                                a.amplitude_v,
                                b.range_m,
                                b.amplitude_v
                            ));
                        }
                    }
                }
            }
        }
    }
    let frames: u64 = frames.iter().sum();
    eprintln!("{frames} frames, {returns} returns, {} duplicates", duplicates.len());
    assert!(2 * returns as u64 > frames, "the frames hold returns: {returns}");
    assert!(duplicates.is_empty(), "{} duplicates, e.g.\n{}", duplicates.len(), duplicates.iter().take(10).cloned().collect::<Vec<_>>().join("\n"));
}
