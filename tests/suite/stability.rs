//! Numerical stability: every degenerate input gives a defined answer and a
//! flag, never NaN, a panic or a silent zero.

use crate::common;
use common::{rng, Synth};
use tofwave::frame::{Channel, ChannelRole, Frame, Report, Samples};
use tofwave::pipeline::{report_json, Pipeline};
use tofwave::scene::Scene;

fn frame(channels: Vec<Channel>) -> Frame {
    Frame {
        sensor_id: "s".into(),
        sequence: 0,
        trigger_time_s: 0.0,
        sample_interval_s: 1e-9,
        first_sample_offset_s: -500e-9,
        channels,
        laser_off: false,
    }
}

fn run(scene: &Scene, f: Frame) -> Report {
    let mut p = Pipeline::new(scene, "s");
    let mut out = Vec::new();
    p.push(f, &mut out).expect("accepted");
    p.flush(&mut out);
    assert_eq!(out.len(), 1);
    let r = out.pop().unwrap();
    assert_finite(&r);
    r
}

/// No number in the report is NaN or infinite (JSON would print null).
fn assert_finite(r: &Report) {
    let json = report_json(r);
    assert!(!json.contains("null"), "non-finite number in {json}");
}

fn has<T: std::fmt::Display>(flags: impl IntoIterator<Item = T>, f: &str) -> bool {
    flags.into_iter().any(|x| x.to_string().starts_with(f))
}

fn pulse_frame(scene: &Scene, amp: f64, sigma: f64, tof_s: f64) -> Frame {
    let s = Synth { returns: vec![(tof_s, amp)], noise_sigma_v: sigma, quantise_8bit: None, ..Synth::prototype() };
    s.frame(scene, 0, &mut rng(1))
}

#[test]
fn zero_sigma_gate_gives_a_flagged_finite_detection() {
    let scene = Scene::default_scene();
    let r = run(&scene, pulse_frame(&scene, 0.5, 0.0, 100e-9));
    assert!(has(&r.flags, "zero_noise"), "{:?}", r.flags);
    assert_eq!(r.returns.len(), 1);
    // Noise-free, so the only error is the constant-fraction method's own
    // bias: the half-max level comes from a parabola through the samples at
    // the top, and the crossing is linearly interpolated between samples.
    // Linear interpolation at the half-max point of a Gaussian edge of rise σ
    // (samples) is off by at most h²/8·|x''|/|x'| = 0.041/σ samples: 0.023
    // for the start pulse (σ = 1.79), 0.009 for the return (σ = 4.79); the
    // timing kernel holds a noise-free pulse within 0.05 samples
    // (detect::pulse_timing's test). Start and stop each: 0.1 sample, 1.5 cm.
    // (Measured: -0.033 ns, -4.9 mm.) One sample of error is 15 cm.
    let dt = 1e-9;
    let tof_err = r.returns[0].tof_s - 100e-9;
    assert!(tof_err.abs() < 2.0 * 0.05 * dt, "tof error {tof_err:e} s");
    let expected_m = 0.5 * scene.c_medium_m_per_s() * 100e-9;
    let tol_m = 0.5 * scene.c_medium_m_per_s() * 2.0 * 0.05 * dt;
    assert!((r.returns[0].range_m - expected_m).abs() < tol_m, "{} vs {expected_m} m", r.returns[0].range_m);
}

#[test]
fn all_equal_frame_has_no_returns() {
    let scene = Scene::default_scene();
    let r = run(&scene, frame(vec![Channel::from_volts("CH2", ChannelRole::Stop, vec![0.25; 2500])]));
    assert!(r.returns.is_empty());
    assert!(has(&r.flags, "zero_noise"));
    assert_eq!(r.noise.mean_v, 0.25);
}

#[test]
fn clipped_pulse_is_flagged_saturated() {
    let mut scene = Scene::default_scene();
    let tof = 60e-9;
    let s = Synth { returns: vec![(tof, 5.0)], quantise_8bit: Some((-1.0, 1.0)), ..Synth::prototype() };
    let f = s.frame(&scene, 0, &mut rng(2));
    let r = run(&scene, f.clone());
    assert!(!r.returns.is_empty());
    assert!(r.returns.iter().any(|x| has(&x.flags, "saturated")), "{:?}", r.returns);
    // With the full scale given in the scene the same holds.
    scene.digitiser.full_scale_low_v = -1.0;
    scene.digitiser.full_scale_high_v = 1.0 - 2.0 / 256.0;
    let r = run(&scene, f);
    assert!(r.returns.iter().any(|x| has(&x.flags, "saturated")));
}

#[test]
fn pulses_at_the_frame_edges_are_flagged() {
    use tofwave::dsp::pulse::PulseShape;
    let pulse = Scene::default_scene().return_pulse.pulse(1e-9);
    // Each range gate reaches its frame edge and leaves a noise gate at the other end.
    for (peak, min_m, max_m) in [(0usize, -100.0, 150.0), (2499, 0.0, 400.0)] {
        let scene = Scene { range_gate: tofwave::scene::RangeGateConfig { min_m, max_m }, ..Scene::default_scene() };
        use rand_distr::{Distribution, Normal};
        let mut r = rng(3);
        let n = Normal::new(0.0, 0.01).unwrap();
        let v: Vec<f64> = (0..2500)
            .map(|k| n.sample(&mut r) + pulse.value_and_slope(k as f64 - peak as f64).0)
            .collect();
        let rep = run(&scene, frame(vec![Channel::from_volts("CH2", ChannelRole::Stop, v)]));
        let t_peak = -500e-9 + peak as f64 * 1e-9;
        let ret = rep
            .returns
            .iter()
            .find(|x| (x.t_peak_s - t_peak).abs() < 5e-9)
            .unwrap_or_else(|| panic!("no return near the edge at {peak}: {:?}", rep.returns));
        assert!(has(&ret.flags, "frame_edge"), "{:?}", ret.flags);
        assert!((ret.amplitude_v - 1.0).abs() < 0.2, "{}", ret.amplitude_v);
    }
}

#[test]
fn missing_start_pulse_times_from_the_trigger() {
    let scene = Scene::default_scene();
    let s = Synth { start_amplitude_v: 0.0, returns: vec![(100e-9, 0.5)], ..Synth::prototype() };
    let r = run(&scene, s.frame(&scene, 0, &mut rng(4)));
    assert!(has(&r.flags, "no_start_pulse"), "{:?}", r.flags);
    assert_eq!(r.t_start_s, scene.channels.reference_offset_s);
    assert_eq!(r.returns.len(), 1);
}

#[test]
fn non_finite_samples_are_held_and_flagged() {
    let scene = Scene::default_scene();
    let mut f = pulse_frame(&scene, 0.5, 0.01, 100e-9);
    if let Samples::F64(v) = &mut f.channels[1].samples {
        v[100] = f64::NAN;
        v[700] = f64::INFINITY;
        v[701] = f64::NEG_INFINITY;
    }
    let r = run(&scene, f);
    assert!(has(&r.flags, "non_finite_samples:3"), "{:?}", r.flags);
    assert_eq!(r.returns.len(), 1);
}

#[test]
fn large_mean_small_sigma_has_no_cancellation() {
    let scene = Scene::default_scene();
    let mut r = rng(5);
    use rand_distr::{Distribution, Normal};
    let n = Normal::new(0.0, 1e-6).unwrap();
    let noise: Vec<f64> = (0..2500).map(|_| n.sample(&mut r)).collect();
    let m = noise.iter().sum::<f64>() / 2500.0;
    let truth_sd = (noise.iter().map(|x| (x - m).powi(2)).sum::<f64>() / 2499.0).sqrt();
    let v: Vec<f64> = noise.iter().map(|x| 1e3 + x).collect();
    let rep = run(&scene, frame(vec![Channel::from_volts("CH2", ChannelRole::Stop, v)]));
    // The gate is part of the frame; compare with the same samples' deviation within sampling error.
    assert!((rep.noise.sigma_v / truth_sd - 1.0).abs() < 0.1, "{} vs {}", rep.noise.sigma_v, truth_sd);
    assert!((rep.noise.mean_v - 1e3).abs() < 1e-6);
}

#[test]
fn extreme_design_pfas_give_finite_thresholds() {
    for pfa in [1e-300, 0.5] {
        let mut scene = Scene::default_scene();
        scene.detector.pfa = pfa;
        let r = run(&scene, pulse_frame(&scene, 0.5, 0.0138, 100e-9));
        assert!(r.detector.threshold.is_finite() && r.detector.threshold > 0.0);
        assert!(r.detector.pfa_cell > 0.0 && r.detector.pfa_cell <= 0.5);
        // The detector reports a return where the matched filter's output
        // exceeds Q⁻¹(pfa_cell)·σ_out. At pfa 1e-300 per report the cell
        // probability is ~1e-303, Q⁻¹ ≈ 37.2. The return: 0.5 V on 13.8 mV
        // noise is 36.2 σ per sample, and the matched filter adds the
        // template's norm (σ_rise 4.79 + σ_fall 17.3 samples: √(0.886·22.1)
        // = 4.4), ≈ 160 σ_out: far above even this threshold. So exactly the
        // one true return at its range (15.0 m; the timing sd at 31 dB is
        // ~2 cm, 10 cm is 5 sd). At 1e-300 nothing else may cross; at 0.5 a
        // noise crossing is allowed (half the reports have one by design).
        let expected_m = 0.5 * scene.c_medium_m_per_s() * 100e-9;
        let near = r.returns.iter().filter(|x| (x.range_m - expected_m).abs() < 0.1).count();
        assert_eq!(near, 1, "pfa {pfa}: {:?}", r.returns);
        if pfa == 1e-300 {
            assert_eq!(r.returns.len(), 1, "{:?}", r.returns);
            assert!(r.detector.pfa_cell < 1e-300, "{}", r.detector.pfa_cell);
        }
    }
}

#[test]
fn template_longer_than_the_frame_and_one_sample_frames() {
    let scene = Scene::default_scene();
    let short: Vec<f64> = (0..20).map(|k| if k == 10 { 1.0 } else { 0.001 * (k % 3) as f64 }).collect();
    let mut f = frame(vec![Channel::from_volts("CH2", ChannelRole::Stop, short)]);
    f.first_sample_offset_s = -10e-9;
    let r = run(&scene, f);
    assert!(has(&r.flags, "noise_gate_small") || has(&r.flags, "no_noise_estimate"), "{:?}", r.flags);
    let mut one = frame(vec![Channel::from_volts("CH2", ChannelRole::Stop, vec![0.3])]);
    one.first_sample_offset_s = 0.0;
    let r = run(&scene, one);
    assert!(has(&r.flags, "no_noise_estimate"), "{:?}", r.flags);
}

#[test]
fn empty_frames_and_bad_intervals_are_refused_by_field() {
    let scene = Scene::default_scene();
    let mut p = Pipeline::new(&scene, "s");
    let mut out = Vec::new();
    let e = p.push(frame(vec![Channel::from_volts("CH2", ChannelRole::Stop, vec![])]), &mut out).unwrap_err();
    assert!(e.to_string().contains("samples"), "{e}");
    let mut f = frame(vec![Channel::from_volts("CH2", ChannelRole::Stop, vec![0.0; 10])]);
    f.sample_interval_s = 0.0;
    let e = p.push(f, &mut out).unwrap_err();
    assert!(e.field == "sample_interval_s", "{e}");
    let f = frame(vec![Channel::from_volts("CH3", ChannelRole::Unspecified, vec![0.0; 10]), Channel::from_volts("CH4", ChannelRole::Unspecified, vec![0.0; 10])]);
    let e = p.push(f, &mut out).unwrap_err();
    assert!(e.field == "channels" && e.to_string().contains("CH2"), "{e}");
    // The pipeline carries on.
    p.push(frame(vec![Channel::from_volts("CH2", ChannelRole::Stop, vec![0.0; 100])]), &mut out).unwrap();
    assert_eq!(out.len(), 1);
}

#[test]
fn ten_million_frame_average_of_i16_codes_is_exact() {
    let mut scene = Scene::default_scene();
    let n: u32 = if cfg!(debug_assertions) { 100_000 } else { 10_000_000 };
    scene.averaging.frames = n;
    let mut p = Pipeline::new(&scene, "s");
    let mut out = Vec::new();
    // Codes near the extremes make any float accumulation lose digits.
    let codes = [i16::MAX, i16::MIN, 12345, -1, 0, 32000, -32000, 7];
    let mut template = frame(vec![Channel {
        name: "CH2".into(),
        role: ChannelRole::Stop,
        samples: Samples::I16(codes.to_vec()),
        volts_per_code: 1.0,
        offset_v: 0.0,
    }]);
    // Every sample lies in the pre-trigger noise gate, so the noise mean is the mean of the averaged frame.
    template.first_sample_offset_s = -1e-6;
    scene.noise_gate.min_samples = 2;
    let mut sums = [0i64; 8];
    for k in 0..n {
        let mut f = template.clone();
        f.sequence = k as u64;
        if let Samples::I16(v) = &mut f.channels[0].samples {
            // Alternate a +1 on odd frames so the exact mean is not a code.
            if k % 2 == 1 {
                v[3] = 0;
            }
            for (s, &c) in sums.iter_mut().zip(v.iter()) {
                *s += c as i64;
            }
        }
        p.push(f, &mut out).unwrap();
    }
    assert_eq!(out.len(), 1);
    assert_eq!(out[0].frames_averaged, n);
    // The mean the noise model saw equals the exact arithmetic mean (sum/n, rounded once).
    let exact: Vec<f64> = sums.iter().map(|&s| s as f64 / n as f64).collect();
    let exact_mean = exact.iter().sum::<f64>() / 8.0;
    assert_eq!(out[0].noise.samples, 8);
    assert!((out[0].noise.mean_v - exact_mean).abs() <= 1e-12 * exact_mean.abs().max(1.0), "{} vs {exact_mean}", out[0].noise.mean_v);
}

#[test]
fn returns_half_and_one_pulse_width_apart_are_resolved_and_flagged() {
    let mut scene = Scene::default_scene();
    scene.timing.method = tofwave::scene::TimingMethod::Ml;
    let fwhm_s = scene.return_pulse.fwhm_s;
    for (sep, seed) in [(1.0, 31u64), (0.5, 32)] {
        let t1 = 100e-9;
        let t2 = t1 + sep * fwhm_s;
        let s = Synth { returns: vec![(t1, 0.5), (t2, 0.4)], quantise_8bit: None, ..Synth::prototype() };
        let mut errs = Vec::new();
        for k in 0..20 {
            let r = run(&scene, s.frame(&scene, k, &mut rng(seed + 100 * k)));
            assert_eq!(r.returns.len(), 2, "separation {sep} FWHM: {:?}", r.returns);
            assert!(r.returns.iter().all(|x| has(&x.flags, "overlapping")));
            // Nearest first; t_start is the start pulse's half-max crossing.
            let tof: Vec<f64> = r.returns.iter().map(|x| x.tof_s).collect();
            errs.push(((tof[0] - t1) * 1e9, (tof[1] - t2) * 1e9));
        }
        let mean = |f: fn(&(f64, f64)) -> f64| errs.iter().map(f).sum::<f64>() / errs.len() as f64;
        let (e1, e2) = (mean(|e| e.0), mean(|e| e.1));
        eprintln!("separation {sep} FWHM: mean timing errors {e1:+.3} ns, {e2:+.3} ns");
        assert!(e1.abs() < 0.3 && e2.abs() < 0.3, "{e1} {e2}");
    }
}

/// Maximum-likelihood timing fits returns whose pulse windows do not overlap
/// separately (per cluster, `detect::resolve`): a second return far away
/// leaves the first one's range and sigma unchanged to rounding, on the same
/// noise. (The fit used to be joint over every return in the frame, at a
/// cost growing with the square of their number.)
#[test]
fn a_distant_return_does_not_change_the_ml_fit_of_another() {
    let mut scene = Scene::default_scene();
    scene.timing.method = tofwave::scene::TimingMethod::Ml;
    let t1 = 100e-9;
    let t2 = 600e-9;
    for k in 0..10u64 {
        let alone = Synth { returns: vec![(t1, 0.3)], quantise_8bit: None, ..Synth::prototype() };
        let both = Synth { returns: vec![(t1, 0.3), (t2, 0.4)], ..alone.clone() };
        let a = run(&scene, alone.frame(&scene, k, &mut rng(700 + k)));
        let b = run(&scene, both.frame(&scene, k, &mut rng(700 + k)));
        assert_eq!((a.returns.len(), b.returns.len()), (1, 2), "{:?} / {:?}", a.returns, b.returns);
        let near = b.returns.iter().min_by(|x, y| (x.tof_s - t1).abs().total_cmp(&(y.tof_s - t1).abs())).unwrap();
        let (ra, rb) = (a.returns[0].range_m, near.range_m);
        assert!((ra - rb).abs() <= 1e-9 * ra.abs().max(1.0), "frame {k}: {ra} alone, {rb} beside a distant return");
        let (sa, sb) = (a.returns[0].range_sigma_m, near.range_sigma_m);
        assert!((sa - sb).abs() <= 1e-9 * sa, "frame {k}: sigma {sa} alone, {sb} beside a distant return");
    }
}
