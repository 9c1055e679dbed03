//! Prewhitened matched filter in coloured (AR(1), φ = 0.9 and 0.97) Gaussian noise:
//! the false-alarm rate holds the design, and the probability of detection
//! at a fixed false-alarm probability beats the plain matched filter and
//! follows Q(Q⁻¹(p) − d_white) with d_white = A‖h ∗ s‖ from the whitened
//! template's energy. Fixed seeds; 99 % intervals from the trial counts.
//!
//! Print the numbers with
//! `cargo test --release --test suite whiten:: -- --nocapture`.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use std::sync::{Arc, Mutex};
use tofwave::detect::kernels::DetectorPlan;
use tofwave::detect::finite_gate::detection_probability;
use tofwave::math::special::{q, q_inv};
use tofwave::math::stats::clopper_pearson;
use tofwave::dsp::pulse::PulseShape;
use tofwave::frame::{Channel, ChannelRole, Frame};
use tofwave::pipeline::Pipeline;
use tofwave::scene::{RangeGateConfig, Scene, TimingMethod};

/// Marginal σ of the coloured noise, V.
const SIGMA_X: f64 = 0.0138;

/// AR(1) noise x_n = φ x_{n−1} + e_n started in its stationary distribution.
fn ar1(rng: &mut ChaCha8Rng, n: usize, phi: f64) -> Vec<f64> {
    let e = Normal::new(0.0, SIGMA_X * (1.0 - phi * phi).sqrt()).unwrap();
    let mut x = Normal::new(0.0, SIGMA_X).unwrap().sample(rng);
    (0..n)
        .map(|_| {
            let v = x;
            x = phi * x + e.sample(rng);
            v
        })
        .collect()
}

fn frame(v: Vec<f64>, pre: usize, seq: u64) -> Frame {
    Frame {
        sensor_id: "white".into(),
        sequence: seq,
        trigger_time_s: seq as f64 * 1e-3,
        sample_interval_s: 1e-9,
        first_sample_offset_s: -(pre as f64) * 1e-9,
        channels: vec![Channel::from_volts("CH2", ChannelRole::Stop, v)],
        laser_off: false,
    }
}

fn scene(whiten: bool, pfa: f64, max_m: f64) -> Scene {
    let mut s = Scene::default_scene();
    s.detector.whiten = whiten;
    s.detector.pfa = pfa;
    s.timing.method = TimingMethod::PeakParabolic;
    s.range_gate = RangeGateConfig { min_m: 0.0, max_m };
    s
}

/// Reports with a return among `frames` noise-only frames (1000 samples,
/// 300 before the trigger, a 75 m range gate), and the last report's stages.
fn false_reports(whiten: bool, pfa: f64, frames: u64, seed: u64, phi: f64) -> (u64, Vec<&'static str>) {
    let mut p = Pipeline::new(&scene(whiten, pfa, 75.0), "white");
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out = Vec::new();
    let mut hits = 0;
    let mut stages = Vec::new();
    for seq in 0..frames {
        out.clear();
        p.push(frame(ar1(&mut rng, 1000, phi), 300, seq), &mut out)
            .unwrap();
        if !out[0].returns.is_empty() {
            hits += 1;
        }
        stages = out[0].stages.clone();
    }
    (hits, stages)
}

fn check_false_alarms(phi: f64, seed: u64) {
    let pfa = 1e-2;
    let frames = if cfg!(debug_assertions) { 1000 } else { 20_000 };
    let (hits, stages) = false_reports(true, pfa, frames, seed, phi);
    let (lo, hi) = clopper_pearson(hits, frames, 0.99);
    eprintln!(
        "whitened MF, AR(1) phi {phi}: {hits} of {frames} noise-only reports had a return, rate {:.4}, 99 % CP [{lo:.4}, {hi:.4}], design {pfa}; stages {stages:?}",
        hits as f64 / frames as f64
    );
    assert!(stages.iter().any(|s| *s == "whiten"), "{stages:?}");
    assert!(lo <= pfa && pfa <= hi, "design {pfa} outside [{lo}, {hi}]");
    // The plain matched filter sizes its threshold from the pooled noise
    // colour (detect::colour): near the design, but not exact once the
    // correlation outgrows the lags a gate supports (AR(1) 0.97 has a
    // correlation time of 66 samples). Whitening is what makes it exact and
    // what buys the deflection (see the Pd test).
    let plain_frames = frames / 10;
    let (plain, stages) = false_reports(false, pfa, plain_frames, seed + 1, phi);
    eprintln!(
        "plain MF in the same noise: {plain} of {plain_frames} reports had a false return (design {pfa}); stages {stages:?}"
    );
    assert!(!stages.iter().any(|s| *s == "whiten"), "{stages:?}");
    let (lo, hi) = clopper_pearson(plain, plain_frames, 0.99);
    assert!(hi >= 0.5 * pfa && lo <= 5.0 * pfa, "plain MF rate [{lo}, {hi}] far from design {pfa}");
}

#[test]
fn whitened_false_alarm_rate_matches_design_in_ar1_noise_phi_0_9() {
    check_false_alarms(0.9, 1);
}

#[test]
fn whitened_false_alarm_rate_matches_design_in_ar1_noise_phi_0_97() {
    check_false_alarms(0.97, 3);
}

#[test]
fn whitened_detection_beats_the_plain_matched_filter_and_follows_theory() {
    // φ = 0.97: the noise spectrum falls by ~12x across the pulse's band, so
    // whitening gains ~1.7x in deflection. Long gates (800 samples before the
    // trigger) keep the per-frame mean error small in such slow noise.
    const PHI: f64 = 0.97;
    const N: usize = 1600;
    const PRE: usize = 800;
    const PEAK: usize = 1000;
    let sc = scene(true, 1e-2, 30.0);
    let shape = sc.return_pulse.shape(1e-9);
    let (taps, _) = shape.template();
    // True whitener of AR(1): h = (1, −φ)/σ_e; whitened template g = h ∗ s.
    let sigma_e = SIGMA_X * (1.0 - PHI * PHI).sqrt();
    let mut g = vec![0.0; taps.len() + 1];
    for (i, t) in taps.iter().enumerate() {
        g[i] += t / sigma_e;
        g[i + 1] -= PHI * t / sigma_e;
    }
    let g_norm = g.iter().map(|v| v * v).sum::<f64>().sqrt(); // d_white = A · g_norm
    // Plain MF: unit-energy taps ŝ, output σ² = Σ ŝ_j ŝ_k c(|j − k|) with c(k) = σ_x² φ^k.
    let mut mf = DetectorPlan::matched_filter(&shape, N);
    let s_norm = taps.iter().map(|v| v * v).sum::<f64>().sqrt();
    let mut var_mf = 0.0;
    for (j, a) in taps.iter().enumerate() {
        for (k, b) in taps.iter().enumerate() {
            var_mf +=
                a * b / (s_norm * s_norm) * SIGMA_X * SIGMA_X * PHI.powi(j.abs_diff(k) as i32);
        }
    }
    let sigma_mf = var_mf.sqrt();
    let d_plain_per_volt = s_norm / sigma_mf;
    eprintln!(
        "deflection per volt: whitened {g_norm:.2}, plain MF {d_plain_per_volt:.2} (gain {:.2}x)",
        g_norm / d_plain_per_volt
    );
    assert!(g_norm > d_plain_per_volt);

    // The pipeline's whitened output, threshold and deflection at the return's cell.
    type Cell = (f64, f64, f64, f64, f64);
    let seen: Arc<Mutex<Option<Cell>>> = Arc::new(Mutex::new(None));
    let mut p = Pipeline::new(&sc, "pd");
    let sink = seen.clone();
    p.set_observer(Box::new(move |w| {
        // unit-σ statistic, threshold (unit σ), Student-t threshold, kappa, nu
        *sink.lock().unwrap() = Some((
            w.buffers.detector_output[PEAK] / w.noise.sigma_v,
            w.threshold.u,
            w.threshold.t,
            w.threshold.kappa,
            w.threshold.nu,
        ));
    }));
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut out = Vec::new();
    // Warm the noise model up on 64 noise-only frames.
    for seq in 0..64 {
        out.clear();
        p.push(frame(ar1(&mut rng, N, PHI), PRE, seq), &mut out)
            .unwrap();
    }
    assert!(out[0].stages.iter().any(|s| *s == "whiten"));
    let u = q_inv(out[0].detector.pfa_cell);
    let trials = if cfg!(debug_assertions) { 300 } else { 3000 };
    for target in [0.2, 0.5, 0.9] {
        let amp = (u - q_inv(target)) / g_norm;
        let (mut white_hits, mut plain_hits, mut predicted) = (0u64, 0u64, 0.0);
        for t in 0..trials {
            let mut x = ar1(&mut rng, N, PHI);
            for (k, v) in x.iter_mut().enumerate() {
                *v += amp * shape.value_and_slope(k as f64 - PEAK as f64).0;
            }
            out.clear();
            p.push(frame(x.clone(), PRE, 100 + t as u64), &mut out)
                .unwrap();
            let (z, thr, u_t, kappa, nu) = seen.lock().unwrap().expect("observer ran");
            if z > thr {
                white_hits += 1;
            }
            predicted += detection_probability(u_t, amp * g_norm, kappa, nu);
            // Plain MF at the same per-cell pfa, with the true noise mean and
            // output σ (an oracle the pipeline does not have: its best case).
            let y = mf.run(&x, 0.0);
            if y[PEAK] / sigma_mf > u {
                plain_hits += 1;
            }
        }
        let predicted = predicted / trials as f64;
        let white = white_hits as f64 / trials as f64;
        let plain = plain_hits as f64 / trials as f64;
        let plain_theory = q(u - amp * d_plain_per_volt);
        // 99 % normal-approximation binomial half-widths for `trials` trials.
        let half = |p: f64| 2.576 * (p * (1.0 - p) / trials as f64).sqrt();
        eprintln!(
            "A = {:.2} mV: whitened Pd {white:.3} (theory Q(Q^-1(p) - d_white) {:.3}, with the gate's t correction {predicted:.3}, d_white {:.2}); plain MF Pd {plain:.3} (theory {plain_theory:.3}, d {:.2}); 99 % band +-{:.3}",
            amp * 1e3,
            q(u - amp * g_norm),
            amp * g_norm,
            amp * d_plain_per_volt,
            half(predicted)
        );
        assert!(
            (white - predicted).abs() < half(predicted),
            "whitened Pd {white} vs {predicted}"
        );
        assert!(
            (plain - plain_theory).abs() < half(plain_theory).max(3.0 / trials as f64),
            "plain Pd {plain} vs {plain_theory}"
        );
        // Two independent binomial estimates: their difference's 99 % band.
        let diff_band =
            2.576 * ((white * (1.0 - white) + plain * (1.0 - plain)) / trials as f64).sqrt();
        assert!(
            white - plain > diff_band,
            "whitening must gain: {white} vs {plain}"
        );
    }
}

#[test]
fn whitening_waits_for_a_noise_model_and_default_scene_has_no_whiten_stage() {
    let mut p = Pipeline::new(&Scene::default_scene(), "d");
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut out = Vec::new();
    p.push(frame(ar1(&mut rng, 1000, 0.9), 300, 0), &mut out)
        .unwrap();
    assert!(!out[0].stages.iter().any(|s| *s == "whiten"));
    // A frame without noise gates (no pre-trigger samples, gate beyond the frame): no model, no stage.
    let mut sc = scene(true, 1e-2, 75.0);
    sc.noise_gate.beyond_range = false;
    let mut p = Pipeline::new(&sc, "w");
    out.clear();
    p.push(frame(ar1(&mut rng, 600, 0.9), 0, 0), &mut out)
        .unwrap();
    assert!(
        !out[0].stages.iter().any(|s| *s == "whiten"),
        "{:?}",
        out[0].stages
    );
    assert!(
        out[0].flags.iter().any(|f| f == "whiten_warming_up"),
        "{:?}",
        out[0].flags
    );
}
