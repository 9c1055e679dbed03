//! Ensemble averaging (issue 6): SNR gain on white noise, exact integer means,
//! the source's weak 32 m return ranged after 256 shots, start alignment,
//! robust methods and the stationarity guard.

use crate::common;

use common::{Synth, load_scene as scene_file, rng};
use rand::Rng;
use rand_distr::{Distribution, Normal};
use std::sync::{Arc, Mutex};
use tofwave::dsp::fracdelay::FractionalDelay;
use tofwave::frame::{Channel, ChannelRole, Frame, Report, Samples};
use tofwave::physics::Simulator;
use tofwave::pipeline::Pipeline;
use tofwave::calibrate::calibrate;
use tofwave::scene::{AveragingAlign, AveragingMethod, AveragingMode, CalibrationConfig, Scene};

/// A stop-only frame whose samples all lie in the pre-trigger noise gate.
fn gate_frame(seq: u64, samples: Samples) -> Frame {
    Frame {
        sensor_id: "avg".into(),
        sequence: seq,
        trigger_time_s: seq as f64 * 1e-4,
        sample_interval_s: 1e-9,
        // 20 000 samples ending 40 ns before the trigger: all noise gate.
        first_sample_offset_s: -(samples.len() as f64) * 1e-9 - 40e-9,
        channels: vec![Channel {
            name: "CH2".into(),
            role: ChannelRole::Stop,
            samples,
            volts_per_code: 1.0,
            offset_v: 0.0,
        }],
        laser_off: false,
    }
}

#[test]
fn white_noise_gain_is_sqrt_n() {
    let sigma = 0.0138;
    let len = 20_000;
    let normal = Normal::new(0.0, sigma).unwrap();
    let mut r = rng(42);
    for n in [4u32, 16, 64, 256, 1024, 4096] {
        let mut scene = Scene::default_scene();
        scene.averaging.frames = n;
        let mut p = Pipeline::new(&scene, "avg");
        let mut out = Vec::new();
        for k in 0..n {
            let v: Vec<f64> = (0..len).map(|_| normal.sample(&mut r)).collect();
            p.push(gate_frame(k as u64, Samples::F64(v)), &mut out)
                .unwrap();
        }
        assert_eq!(out.len(), 1);
        let rep = &out[0];
        assert_eq!(rep.frames_averaged, n);
        let gain = 10f64.powf(rep.snr_gain_db.expect("averaged reports carry the gain") / 20.0);
        // The noise model is re-fitted on the averaged frame: its sigma, too.
        let refit = sigma / rep.noise.sigma_v;
        let expect = (n as f64).sqrt();
        println!(
            "N = {n:5}: realised SNR gain {gain:8.3} (re-fitted sigma ratio {refit:8.3}), sqrt(N) = {expect:8.3}, error {:+.2} %",
            100.0 * (gain / expect - 1.0)
        );
        // Each sigma comes from 20 000 gate samples: relative standard error
        // 1/sqrt(2 * 20000) = 0.5 %, the ratio's 0.7 %; 5 % is > 7 standard
        // errors (false failure probability < 1e-11 per N).
        assert!((gain / expect - 1.0).abs() < 0.05, "N = {n}: gain {gain}");
        assert!(
            (refit / expect - 1.0).abs() < 0.05,
            "N = {n}: re-fitted sigma gives {refit}"
        );
    }
}

#[test]
fn integer_code_average_is_the_exact_mean() {
    let n = 1000u32;
    let len = 512;
    let mut scene = Scene::default_scene();
    scene.averaging.frames = n;
    let mut p = Pipeline::new(&scene, "avg");
    let seen: Arc<Mutex<Vec<Vec<f64>>>> = Arc::default();
    let sink = seen.clone();
    p.set_observer(Box::new(move |w| {
        sink.lock().unwrap().push(w.buffers.stop_v.clone())
    }));
    let mut r = rng(3);
    let mut sums = vec![0i64; len];
    let mut out = Vec::new();
    for k in 0..n {
        // Codes near the extremes: a float running sum would lose digits.
        let v: Vec<i16> = (0..len)
            .map(|_| r.random_range(-32768..=32767i32) as i16)
            .collect();
        v.iter()
            .zip(sums.iter_mut())
            .for_each(|(c, s)| *s += *c as i64);
        p.push(gate_frame(k as u64, Samples::I16(v)), &mut out)
            .unwrap();
    }
    assert_eq!(out.len(), 1);
    let got = &seen.lock().unwrap()[0];
    // |sum| < 2^53, so sum as f64 / n as f64 is the exact quotient rounded once.
    let mismatches = got
        .iter()
        .zip(&sums)
        .filter(|(g, s)| **g != **s as f64 / n as f64)
        .count();
    assert_eq!(
        mismatches, 0,
        "{mismatches} samples differ from the exact mean"
    );
}

/// Reports of `frames` frames of `scene`'s simulation.
fn simulate(scene: &Scene, seed: u64, frames: u64) -> (Vec<Report>, f64) {
    let sim = Simulator::new(scene).unwrap();
    let mut p = Pipeline::new(scene, "weak");
    let mut out = Vec::new();
    let mut tof = 0.0;
    for k in 0..frames {
        let (f, t) = sim.frame(seed, k);
        tof = t.returns[0].tof_s;
        p.push(f, &mut out).unwrap();
    }
    p.flush(&mut out);
    (out, tof)
}

#[test]
fn weak_far_return_is_ranged_after_256_shots_and_not_single_shot() {
    let mut scene = scene_file("weak-32m");
    let range_m = 32.1147;
    scene.detector.pfa = 1e-6;
    // The simulated receiver noise is coloured (19.5 MHz TIA); the Gaussian
    // threshold sizes the matched filter's output sigma from the noise
    // colour pooled over the gates (detect::colour), so the scene's own
    // threshold mode holds the design pfa here.
    let near = |r: &Report| {
        r.returns
            .iter()
            .find(|x| (x.range_m - range_m).abs() < 0.5)
            .map(|x| x.range_m)
    };

    scene.averaging.frames = 256;
    // Calibrate as `tofwave calibrate` does: the chain's fixed delay and the
    // method's own bias, from an independent calibration run (32 averaged
    // reports, other seed) of the target at its known range.
    scene.calibration = CalibrationConfig::default();
    let (cal, _) = simulate(&scene, 100, 256 * 32);
    let measured = calibrate(&cal, range_m, &scene, false).unwrap().file;
    scene.calibration = measured.calibration;
    println!(
        "calibration run: {} of 32 reports used, delay {:.4} ns ± {:.4} ns",
        measured.measurement.returns,
        scene.calibration.delay_s * 1e9,
        measured.measurement.delay_sem_s * 1e9
    );
    let groups = 64u64;
    let (avg, _) = simulate(&scene, 7, 256 * groups);
    assert_eq!(avg.len() as u64, groups);
    let found: Vec<f64> = avg.iter().filter_map(near).collect();
    let errs: Vec<f64> = found.iter().map(|r| r - range_m).collect();
    let rms = (errs.iter().map(|e| e * e).sum::<f64>() / errs.len().max(1) as f64).sqrt();
    let mean = errs.iter().sum::<f64>() / errs.len().max(1) as f64;
    let spurious: usize = avg
        .iter()
        .map(|r| r.returns.len() - near(r).is_some() as usize)
        .sum();
    let gain = avg.iter().filter_map(|r| r.snr_gain_db).sum::<f64>() / groups as f64;
    println!(
        "256-shot averages: detected {} of {groups}, range error mean {:+.2} cm, rms {:.2} cm, max {:.2} cm; spurious returns {spurious}; mean snr_gain_db {gain:.2} (sqrt(256) = 24.08 dB)",
        found.len(),
        mean * 100.0,
        rms * 100.0,
        errs.iter().fold(0.0f64, |m, e| m.max(e.abs())) * 100.0
    );
    assert_eq!(
        found.len() as u64,
        groups,
        "the averaged return must be detected in every report"
    );
    // 64 reports: the rms is known to ~1/sqrt(128) = 9 % (one standard error).
    assert!(rms < 0.02, "range rms error {rms} m");

    scene.averaging.frames = 1;
    let shots = 2000u64;
    let (single, _) = simulate(&scene, 8, shots);
    let hits = single.iter().filter(|r| near(r).is_some()).count();
    println!("single shot: the 20.8 mV return reported in {hits} of {shots} shots");
    // At 1.5 sigma single-shot the detector at pfa 1e-6 per report finds the
    // return in well under 1 % of shots (binomial: 20 of 2000 is > 4 standard
    // errors above a 0.3 % rate).
    assert!(
        hits * 100 <= shots as usize,
        "{hits} single-shot detections"
    );
}

/// Peak amplitude of the average of 64 noise-free frames (the weak-32m
/// pulse shapes) whose start moves by `jitter(k)` samples.
fn averaged_amplitude(align: AveragingAlign, jitter: impl Fn(u64) -> f64) -> f64 {
    let mut scene = scene_file("weak-32m");
    scene.simulation = None;
    scene.digitiser = Default::default();
    scene.averaging.frames = 64;
    scene.averaging.align = align;
    let mut synth = Synth::prototype();
    synth.noise_sigma_v = 0.0;
    synth.quantise_8bit = None;
    synth.start_amplitude_v = 0.3;
    synth.returns = vec![(214.3e-9, 0.5)];
    // A tiny noise floor so the noise model has a sigma (the detector needs one).
    let mut r = rng(5);
    let floor = Normal::new(0.0, 1e-5).unwrap();
    let mut p = Pipeline::new(&scene, "jit");
    let seen: Arc<Mutex<Vec<Vec<f64>>>> = Arc::default();
    let sink = seen.clone();
    p.set_observer(Box::new(move |w| {
        sink.lock().unwrap().push(w.buffers.stop_v.clone())
    }));
    let mut out = Vec::new();
    for k in 0..64 {
        let mut s = synth.clone();
        s.start_time_s = jitter(k) * 1e-9;
        let mut f = s.frame(&scene, k, &mut r);
        if let Samples::F64(v) = &mut f.channels[1].samples {
            v.iter_mut().for_each(|x| *x += floor.sample(&mut r));
        }
        p.push(f, &mut out).unwrap();
    }
    assert_eq!(out.len(), 1);
    // The peak of the averaged waveform itself, between samples too: the
    // band-limited waveform shifted in 1/64-sample steps (fractional delay).
    let v = seen.lock().unwrap()[0].clone();
    let k = (0..v.len()).max_by(|&a, &b| v[a].total_cmp(&v[b])).unwrap();
    let piece = &v[k - 40..k + 40];
    let mut y = vec![0.0; piece.len()];
    (0..64)
        .map(|j| {
            FractionalDelay::new(j as f64 / 64.0 - 0.5).apply(piece, &mut y);
            y[30..50].iter().copied().fold(f64::MIN, f64::max)
        })
        .fold(f64::MIN, f64::max)
}

#[test]
fn start_alignment_keeps_the_peak_under_half_sample_jitter() {
    // Start instants uniform in ±0.5 sample (a free-running sample clock);
    // the same sequence with and without alignment, against no jitter.
    let jitter = |k: u64| (k as f64 * 0.618_034).fract() - 0.5;
    let perfect = averaged_amplitude(AveragingAlign::Start, |_| 0.0);
    let aligned = averaged_amplitude(AveragingAlign::Start, jitter);
    let unaligned = averaged_amplitude(AveragingAlign::None, jitter);
    let loss = |a: f64| 20.0 * (perfect / a).log10();
    println!(
        "peak amplitude: perfect {perfect:.5} V, aligned {aligned:.5} V (loss {:.4} dB), unaligned {unaligned:.5} V (loss {:.4} dB)",
        loss(aligned),
        loss(unaligned)
    );
    // The effect is small: uniform ±0.5-sample jitter costs the unaligned
    // average ~0.03 dB (measured 0.034 dB). The only randomness is the 10 µV
    // floor, averaged over 64 frames: 1.25 µV on a 0.5 V peak, 2e-5 dB, so
    // the numbers below are the methods' own, not Monte-Carlo spread
    // (bounded here by 10 spreads = 2e-4 dB). The jitter must be visible
    // without alignment, and alignment must remove most of it: at most half
    // the unaligned loss stays (measured 0.0096 dB, the fractional-delay
    // interpolation's own loss), and it cannot gain beyond the spread.
    let spread_db = 20.0 * (1.0 + 10.0 * 1e-5 / 64f64.sqrt() / perfect).log10();
    assert!(
        loss(unaligned) > 0.01,
        "unaligned loss {} dB: the jitter has no effect to remove",
        loss(unaligned)
    );
    assert!(
        loss(aligned) > -spread_db && loss(aligned) < 0.5 * loss(unaligned),
        "aligned loss {} dB against {} dB unaligned",
        loss(aligned),
        loss(unaligned)
    );
}

#[test]
fn median_average_rejects_sporadic_bursts() {
    // 32 frames of white noise, 3 of them with a 0.5 V step-like burst over
    // the range gate: the mean carries 3/32 of it, the median almost none.
    let mut scene = Scene::default_scene();
    scene.averaging.frames = 32;
    let normal = Normal::new(0.0, 0.01).unwrap();
    let level = |method: AveragingMethod| {
        let mut s = scene.clone();
        s.averaging.method = method;
        let mut p = Pipeline::new(&s, "burst");
        let seen: Arc<Mutex<Vec<Vec<f64>>>> = Arc::default();
        let sink = seen.clone();
        p.set_observer(Box::new(move |w| {
            sink.lock().unwrap().push(w.buffers.stop_v.clone())
        }));
        let mut r = rng(9);
        let mut out = Vec::new();
        for k in 0..32u64 {
            let v: Vec<f64> = (0..2000)
                .map(|i| normal.sample(&mut r) + if k % 11 == 3 && i > 500 { 0.5 } else { 0.0 })
                .collect();
            p.push(gate_frame(k, Samples::F64(v)), &mut out).unwrap();
        }
        assert_eq!(out[0].frames_averaged, 32);
        let v = seen.lock().unwrap()[0].clone();
        v[600..].iter().sum::<f64>() / v[600..].len() as f64
    };
    let mean = level(AveragingMethod::Mean);
    let median = level(AveragingMethod::Median);
    let trimmed = level(AveragingMethod::TrimmedMean);
    println!(
        "burst level left: mean {mean:.4} V, trimmed mean {trimmed:.4} V, median {median:.4} V"
    );
    assert!((mean - 3.0 * 0.5 / 32.0).abs() < 0.005);
    // Per-sample median of 32 N(0, 0.01) values with 3 outliers: its bias is
    // ~0.1 sigma = 1 mV.
    assert!(median.abs() < 0.003, "{median}");
    assert!(trimmed.abs() < 0.003, "{trimmed}");
}

#[test]
fn moving_target_ends_the_group_and_is_flagged() {
    let mut scene = Scene::default_scene();
    scene.averaging.frames = 64;
    scene.averaging.stationarity_block = 16;
    let mut synth = Synth::prototype();
    let mut r = rng(21);
    let mut p = Pipeline::new(&scene, "move");
    let mut out = Vec::new();
    // 40 frames at one range, then the target jumps 1.5 m (10 ns) further.
    for k in 0..128u64 {
        synth.returns = vec![(if k < 40 { 100e-9 } else { 110e-9 }, 0.3)];
        p.push(synth.frame(&scene, k, &mut r), &mut out).unwrap();
    }
    p.flush(&mut out);
    let sizes: Vec<u32> = out.iter().map(|r| r.frames_averaged).collect();
    let flagged: Vec<bool> = out
        .iter()
        .map(|r| r.flags.iter().any(|f| f == "nonstationary"))
        .collect();
    println!("groups {sizes:?} nonstationary {flagged:?}");
    // The block holding the jump (frames 32..48) is the first that differs:
    // the group of frames 0..32 ends there, flagged.
    assert_eq!(sizes[0], 32);
    assert!(flagged[0]);
    assert!(
        out.iter().all(|r| r.returns.len() == 1),
        "{:?}",
        out.iter().map(|r| r.returns.len()).collect::<Vec<_>>()
    );
    // A stationary target is averaged in full groups with no flag.
    let mut p = Pipeline::new(&scene, "still");
    let mut out = Vec::new();
    synth.returns = vec![(100e-9, 0.3)];
    for k in 0..128u64 {
        p.push(synth.frame(&scene, k, &mut r), &mut out).unwrap();
    }
    assert_eq!(
        out.iter().map(|r| r.frames_averaged).collect::<Vec<_>>(),
        vec![64, 64]
    );
    assert!(
        out.iter()
            .all(|r| !r.flags.iter().any(|f| f == "nonstationary"))
    );
}

#[test]
fn sliding_window_reports_every_hop() {
    let mut scene = Scene::default_scene();
    scene.averaging.frames = 16;
    scene.averaging.mode = AveragingMode::Sliding;
    scene.averaging.hop = 4;
    let synth = Synth {
        returns: vec![(100e-9, 0.3)],
        ..Synth::prototype()
    };
    let mut r = rng(4);
    let mut p = Pipeline::new(&scene, "slide");
    let mut out = Vec::new();
    for k in 0..40u64 {
        p.push(synth.frame(&scene, k, &mut r), &mut out).unwrap();
    }
    // Windows end at frames 15, 19, ..., 39: 7 reports of 16 frames.
    assert_eq!(out.len(), 7);
    assert!(
        out.iter()
            .all(|r| r.frames_averaged == 16 && r.returns.len() == 1)
    );
    assert_eq!(
        out.iter().map(|r| r.seq_first).collect::<Vec<_>>(),
        vec![0, 4, 8, 12, 16, 20, 24]
    );
}

#[test]
fn scene_keys_are_validated_by_name_and_the_default_pipeline_is_unchanged() {
    let base = tofwave::scene::DEFAULT_SCENE_TOML;
    let cases = [
        (
            format!("{base}\n[baseline]\nsmoothing = 0.0\n"),
            "baseline.smoothing",
        ),
        (format!("{base}\n[denoise]\npfa = 2.0\n"), "denoise.pfa"),
        (
            format!("{base}\n[denoise]\nmethod = \"notch\"\n"),
            "denoise.notch_frequencies_hz",
        ),
        (base.replace("hop = 1", "hop = 0"), "averaging.hop"),
        (
            base.replace("stationarity_block = 0", "stationarity_block = 5"),
            "averaging.stationarity_block",
        ),
        (
            format!("{base}\n[denoise]\nmethd = \"template\"\n"),
            "methd",
        ),
    ];
    for (text, field) in cases {
        let e = Scene::from_toml_str(&text, "x.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains(field), "{field}: {e}");
    }
    let names = Pipeline::new(&Scene::default_scene(), "d").stage_names();
    assert!(
        !names
            .iter()
            .any(|n| ["baseline", "denoise", "average"].contains(n)),
        "{names:?}"
    );
}

#[test]
fn baseline_stage_removes_a_drifting_offset() {
    let mut scene = Scene::default_scene();
    scene.baseline = Some(tofwave::scene::BaselineConfig {
        smoothing: 0.5,
        ..Default::default()
    });
    let synth = Synth {
        returns: vec![(100e-9, 0.3)],
        quantise_8bit: None,
        ..Synth::prototype()
    };
    let mut r = rng(12);
    let mut p = Pipeline::new(&scene, "base");
    let mut out = Vec::new();
    for k in 0..50u64 {
        let mut s = synth.clone();
        // 0.2 V offset drifting by 1 mV per frame.
        s.noise_mean_v = 0.2 + 1e-3 * k as f64;
        p.push(s.frame(&scene, k, &mut r), &mut out).unwrap();
    }
    assert!(out.iter().all(|r| r.stages.iter().any(|s| *s == "baseline")));
    // Steady state of the smoothed offset lags a ramp by slope (1 − α)/α = 1 mV.
    let late: Vec<f64> = out[20..].iter().map(|r| r.noise.mean_v).collect();
    let mean = late.iter().sum::<f64>() / late.len() as f64;
    println!("offset left after baseline removal: {:.3} mV", mean * 1e3);
    assert!((mean - 1e-3).abs() < 0.5e-3, "{mean}");
    // The return's amplitude is measured above the removed offset.
    let amps: Vec<Vec<f64>> = out
        .iter()
        .map(|r| r.returns.iter().map(|x| x.amplitude_v).collect())
        .collect();
    assert!(
        amps.iter()
            .all(|a| a.iter().any(|x| (x - 0.3).abs() < 0.05)),
        "{amps:?}"
    );
}
