//! Noise model with exponential forgetting (`noise_gate.forgetting_frames`):
//! a step in σ between frames is followed within the stated 3·N frames, and
//! with forgetting off every report's noise model is exactly the fit on that
//! frame's own gates. Fixed seeds.
//!
//! Print the numbers with `cargo test --release --test suite forgetting:: -- --nocapture`.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use std::sync::{Arc, Mutex};
use tofwave::detect::noise_model::NoiseFitter;
use tofwave::frame::{Channel, ChannelRole, Frame, NoiseSummary};
use tofwave::pipeline::Pipeline;
use tofwave::scene::Scene;

fn noise_frame(rng: &mut ChaCha8Rng, sigma: f64, seq: u64) -> Frame {
    let g = Normal::new(0.0, sigma).unwrap();
    Frame {
        sensor_id: "f".into(),
        sequence: seq,
        trigger_time_s: seq as f64 * 1e-3,
        sample_interval_s: 1e-9,
        first_sample_offset_s: -300e-9,
        channels: vec![Channel::from_volts(
            "CH2",
            ChannelRole::Stop,
            (0..1000).map(|_| g.sample(rng)).collect(),
        )],
        laser_off: true,
    }
}

fn scene(forgetting_frames: u32) -> Scene {
    let mut s = Scene::default_scene();
    s.range_gate.max_m = 75.0;
    s.noise_gate.forgetting_frames = forgetting_frames;
    s
}

#[test]
fn sigma_step_is_tracked_within_three_time_constants() {
    const TAU: u32 = 10;
    let (s1, s2) = (0.01, 0.02);
    let mut p = Pipeline::new(&scene(TAU), "f");
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut out = Vec::new();
    for seq in 0..60 {
        p.push(noise_frame(&mut rng, s1, seq), &mut out).unwrap();
    }
    let before = out.last().unwrap().noise;
    out.clear();
    for seq in 60..60 + 4 * TAU as u64 {
        p.push(noise_frame(&mut rng, s2, seq), &mut out).unwrap();
    }
    let sig: Vec<f64> = out.iter().map(|r| r.noise.sigma_v).collect();
    // After k frames at the new level the old level keeps weight λ^k = e^(−k/N):
    // σ_k² = (1 − e^(−k/N)) σ₂² + e^(−k/N) σ₁².
    let model = |k: f64| {
        ((1.0 - (-k / TAU as f64).exp()) * s2 * s2 + (-k / TAU as f64).exp() * s1 * s1).sqrt()
    };
    for k in [1usize, TAU as usize, 3 * TAU as usize] {
        eprintln!(
            "{k} frames after the step: sigma {:.5} V (model {:.5}, new level {s2})",
            sig[k - 1],
            model(k as f64)
        );
    }
    eprintln!(
        "before the step: sigma {:.5} V from {} effective samples",
        before.sigma_v, before.samples
    );
    // The tracker's σ has relative standard error ≈ 1/√(2 n_eff); with n_eff
    // ≈ (gate samples)(1 + λ)/(1 − λ) ≈ 1e4 that is 0.7 %: 3.3 of them (99.9 %) is 2.3 %.
    let n_eff = before.samples as f64;
    assert!(n_eff > 5000.0, "effective samples {n_eff}");
    let tol = 3.3 / (2.0 * n_eff).sqrt();
    assert!(
        (before.sigma_v / s1 - 1.0).abs() < tol,
        "settled sigma {} vs {s1}",
        before.sigma_v
    );
    for (k, s) in sig.iter().enumerate() {
        let m = model((k + 1) as f64);
        assert!(
            (s / m - 1.0).abs() < tol,
            "frame {} after the step: {s} vs model {m}",
            k + 1
        );
    }
    // "Tracked within 3N frames": within 5 % of the new level.
    assert!((sig[3 * TAU as usize - 1] / s2 - 1.0).abs() < 0.05);
    // And not thrown by one frame: one frame after the step σ has moved little.
    assert!(sig[0] < 1.2 * s1, "{}", sig[0]);
}

#[test]
fn without_forgetting_each_frame_is_fitted_on_its_own_gates() {
    let sc = scene(0);
    let mut p = Pipeline::new(&sc, "f");
    type Gates = (Vec<f64>, std::ops::Range<usize>, std::ops::Range<usize>);
    let seen: Arc<Mutex<Vec<Gates>>> = Arc::default();
    let sink = seen.clone();
    p.set_observer(Box::new(move |w| {
        sink.lock().unwrap().push((
            w.buffers.stop_v.clone(),
            w.noise.gates.pre.clone(),
            w.noise.gates.beyond.clone(),
        ))
    }));
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut out = Vec::new();
    for seq in 0..20 {
        let sigma = if seq < 10 { 0.01 } else { 0.04 };
        p.push(noise_frame(&mut rng, sigma, seq), &mut out).unwrap();
    }
    let seen = seen.lock().unwrap();
    let mut fitter = NoiseFitter::default();
    for (r, (x, pre, beyond)) in out.iter().zip(seen.iter()) {
        let own: NoiseSummary = fitter.fit(
            &[&x[pre.clone()], &x[beyond.clone()]],
            sc.detector.normality_alpha,
        );
        assert_eq!(r.noise, own, "frame {}", r.seq_first);
    }
    // The step shows at once.
    assert!(out[10].noise.sigma_v > 3.5 * out[9].noise.sigma_v);
}
