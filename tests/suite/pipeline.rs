//! The pipeline on synthetic frames with known truth.

use crate::common;
use common::{rng, Synth};
use tofwave::pipeline::Pipeline;
use tofwave::scene::{Scene, TimingMethod};

fn c_air(scene: &Scene) -> f64 {
    scene.c_medium_m_per_s()
}

#[test]
fn a_strong_return_is_ranged_by_every_timing_method() {
    let mut scene = Scene::default_scene();
    let range_m = 24.8122;
    let tof = 2.0 * range_m / c_air(&scene);
    let synth = Synth { returns: vec![(tof, 0.5)], ..Synth::prototype() };
    for method in [
        TimingMethod::ConstantFraction,
        TimingMethod::PeakParabolic,
        TimingMethod::PeakGaussian,
        TimingMethod::Ml,
    ] {
        scene.timing.method = method;
        let mut p = Pipeline::new(&scene, "t");
        let mut out = Vec::new();
        let mut r = rng(7);
        let n = 50;
        for seq in 0..n {
            p.push(synth.frame(&scene, seq, &mut r), &mut out).unwrap();
        }
        assert_eq!(out.len(), n as usize);
        let ranges: Vec<f64> = out.iter().map(|rep| {
            assert_eq!(rep.returns.len(), 1, "{method:?}: {:?}", rep.returns);
            rep.returns[0].range_m
        }).collect();
        let mean = ranges.iter().sum::<f64>() / n as f64;
        let sd = (ranges.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n as f64 - 1.0)).sqrt();
        let sigma_rep = out.iter().map(|r| r.returns[0].range_sigma_m).sum::<f64>() / n as f64;
        eprintln!("{method:?}: mean {mean:.4} m (truth {range_m}), sd {sd:.4} m, reported sigma {sigma_rep:.4} m");
        // 5 standard errors of the mean: a failure here is a bias, not bad luck.
        assert!((mean - range_m).abs() < 5.0 * sd / (n as f64).sqrt() + 0.01, "{method:?}: {mean} vs {range_m}");
    }
}
