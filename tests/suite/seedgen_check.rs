//! Checks of the independent frame generator (`tests/common/seedgen.rs`)
//! itself: its noise, pulse shapes, truth, quantisation, determinism and
//! interference bursts. Nothing here runs the library's algorithms.
//!
//! Monte-Carlo tolerances are z = 4.5 standard errors (two-sided false-failure
//! probability 6.8e-6 per check) unless a test says otherwise; seeds are fixed.

use crate::common;

use common::seedgen::{
    EventConfig, GenConfig, PulseFamily, auto_full_scale_v, frame_with_seed, generate,
};
use tofwave::frame::{Channel, Frame, Samples};

/// Standard errors allowed in the Monte-Carlo checks (two-sided 6.8e-6).
const Z: f64 = 4.5;

fn stop(frame: &Frame) -> &Channel {
    frame.channel("CH2").expect("stop channel")
}

fn start(frame: &Frame) -> &Channel {
    frame.channel("CH1").expect("start channel")
}

/// A configuration with no noise, no quantisation and no jitter, so frames
/// can be compared with the pulse shapes sample by sample.
fn clean() -> GenConfig {
    GenConfig {
        noise_sigma_v: 0.0,
        start_noise_sigma_v: 0.0,
        bits: 0,
        ..GenConfig::default()
    }
}

/// Mean square deviation from the known mean `mu`, and the count.
fn var_about(samples: impl Iterator<Item = f64>, mu: f64) -> (f64, usize) {
    let (mut s, mut n) = (0.0, 0usize);
    for x in samples {
        s += (x - mu) * (x - mu);
        n += 1;
    }
    (s / n as f64, n)
}

#[test]
fn default_configuration_is_valid_and_quotes_the_prototype() {
    let cfg = GenConfig::default();
    cfg.validate().unwrap();
    assert!((cfg.noise_sigma_v.powi(2) - 1.916e-4).abs() < 1e-12);
    assert_eq!((cfg.samples, cfg.dt_s, cfg.bits), (2500, 1e-9, 8));
    assert_eq!(
        cfg.return_pulse,
        PulseFamily::SharpOnset {
            rise_s: 8.08e-9,
            fwhm_s: 26.04e-9
        }
    );
    assert!((cfg.speed_of_light_m_per_s - 299_792_458.0 / 1.000_273).abs() < 1e-6);
    EventConfig::default().validate().unwrap();
    // A configuration error names the field.
    let bad = GenConfig {
        bits: 17,
        ..GenConfig::default()
    };
    assert!(bad.validate().unwrap_err().contains("bits"));
    let bad = PulseFamily::SharpOnset {
        rise_s: 10e-9,
        fwhm_s: 10e-9,
    };
    assert!(bad.validate().is_err());
    let bad = PulseFamily::RaisedCosine {
        rise_s: 10e-9,
        fwhm_s: 8e-9,
    };
    assert!(bad.validate().is_err());
}

/// Laser off, default (quantised) scope settings: the stop channel's variance
/// about the configured mean is σ² plus the quantisation's Δ²/12 (Sheppard;
/// exact to e^(−2π²σ²/Δ²) ≈ 1e-17 here), within Z standard errors of a
/// variance of n Gaussian samples, σ²·sqrt(2/n); the mean within Z σ/sqrt(n).
#[test]
fn laser_off_noise_has_the_configured_mean_and_sigma() {
    let cfg = GenConfig {
        laser_off: true,
        ..GenConfig::default()
    };
    let frames = generate(&cfg, 16, 11);
    let vpc = stop(&frames[0].0).volts_per_code;
    assert!(
        cfg.noise_sigma_v / vpc > 1.0,
        "noise spans more than a code"
    );
    let expected = cfg.noise_sigma_v.powi(2) + vpc * vpc / 12.0;
    let all: Vec<f64> = frames.iter().flat_map(|(f, _)| stop(f).volts()).collect();
    let n = all.len() as f64;
    let mean = all.iter().sum::<f64>() / n;
    assert!(
        (mean - cfg.noise_mean_v).abs() < Z * (expected / n).sqrt(),
        "mean {mean} vs {}",
        cfg.noise_mean_v
    );
    let (var, _) = var_about(all.iter().copied(), cfg.noise_mean_v);
    let tol = Z * expected * (2.0 / n).sqrt();
    assert!(
        (var - expected).abs() < tol,
        "variance {var:e} vs {expected:e} ± {tol:e}"
    );
    for (f, t) in &frames {
        assert!(t.laser_off && f.laser_off && t.returns.is_empty());
        assert_eq!(t.clipped_stop, 0);
        // No start pulse either: the start channel holds its noise only.
        assert!(
            start(f)
                .volts()
                .iter()
                .all(|v| v.abs() < 10.0 * cfg.start_noise_sigma_v + 0.01)
        );
    }
}

/// Unquantised, white and one-pole band-limited noise both keep σ after the
/// filter. For the AR(1) noise y[k] = a y[k−1] + …, the variance of the mean
/// square of n samples is (2σ⁴/n)(1 + a²)/(1 − a²) and the lag-1 sample
/// autocorrelation has standard error sqrt((1 − a²)/n).
#[test]
fn white_and_band_limited_noise_keep_sigma() {
    for bandwidth in [None, Some(50e6), Some(10e6)] {
        let cfg = GenConfig {
            laser_off: true,
            bits: 0,
            noise_bandwidth_hz: bandwidth,
            ..GenConfig::default()
        };
        let a = bandwidth.map_or(0.0, |b| (-2.0 * std::f64::consts::PI * b * cfg.dt_s).exp());
        let frames = generate(&cfg, 40, 5);
        let s2 = cfg.noise_sigma_v.powi(2);
        let (mut sum_sq, mut sum_lag, mut n, mut n_lag) = (0.0, 0.0, 0usize, 0usize);
        for (f, _) in &frames {
            let v: Vec<f64> = stop(f)
                .volts()
                .iter()
                .map(|x| x - cfg.noise_mean_v)
                .collect();
            sum_sq += v.iter().map(|x| x * x).sum::<f64>();
            sum_lag += v.windows(2).map(|w| w[0] * w[1]).sum::<f64>();
            n += v.len();
            n_lag += v.len() - 1;
        }
        let nf = n as f64;
        let var = sum_sq / nf;
        let tol = Z * s2 * (2.0 / nf * (1.0 + a * a) / (1.0 - a * a)).sqrt();
        assert!(
            (var - s2).abs() < tol,
            "{bandwidth:?}: variance {var:e} vs {s2:e} ± {tol:e}"
        );
        let rho = (sum_lag / n_lag as f64) / var;
        let tol = Z * ((1.0 - a * a) / nf).sqrt();
        assert!(
            (rho - a).abs() < tol,
            "{bandwidth:?}: lag-1 correlation {rho} vs {a} ± {tol}"
        );
        // The start channel's noise is white at its own σ.
        let (svar, sn) = var_about(frames.iter().flat_map(|(f, _)| start(f).volts()), 0.0);
        let s2s = cfg.start_noise_sigma_v.powi(2);
        assert!(
            (svar - s2s).abs() < Z * s2s * (2.0 / sn as f64).sqrt(),
            "start variance {svar:e}"
        );
    }
}

/// Time at which `v` (sampled every `dt` from `t0`) crosses `level`, by
/// linear interpolation: the first rising crossing after index `from`
/// (`forwards`), or the last falling crossing before it.
fn crossing(v: &[f64], t0: f64, dt: f64, level: f64, from: usize, forwards: bool) -> f64 {
    if forwards {
        let k = (from..v.len() - 1)
            .find(|&k| v[k] < level && v[k + 1] >= level)
            .expect("rising crossing");
        t0 + (k as f64 + (level - v[k]) / (v[k + 1] - v[k])) * dt
    } else {
        let k = (0..from)
            .rev()
            .find(|&k| v[k] >= level && v[k + 1] < level)
            .expect("falling crossing");
        t0 + (k as f64 + (v[k] - level) / (v[k] - v[k + 1])) * dt
    }
}

/// Rendered noise-free at 1 ps, each shape peaks at exactly 1, is zero up
/// to its onset, and has the configured 10–90 % rise and FWHM.
#[test]
fn pulse_shapes_have_the_configured_rise_and_width() {
    let ns = 1e-9;
    let cases = [
        PulseFamily::SharpOnset {
            rise_s: 8.08 * ns,
            fwhm_s: 26.04 * ns,
        },
        PulseFamily::SharpOnset {
            rise_s: 3.02 * ns,
            fwhm_s: 8.0 * ns,
        },
        PulseFamily::SharpOnset {
            rise_s: 1.0 * ns,
            fwhm_s: 30.0 * ns,
        },
        PulseFamily::SharpOnset {
            rise_s: 20.0 * ns,
            fwhm_s: 21.0 * ns,
        },
        PulseFamily::RaisedCosine {
            rise_s: 8.08 * ns,
            fwhm_s: 26.04 * ns,
        },
        PulseFamily::RaisedCosine {
            rise_s: 0.590334 * 20.0 * ns,
            fwhm_s: 20.0 * ns,
        },
        PulseFamily::RaisedCosine {
            rise_s: 10.0 * ns,
            fwhm_s: 9.0 * ns,
        },
    ];
    let dt = 1e-12;
    for p in cases {
        p.validate().unwrap();
        let t0 = -ns;
        let span = p.peak_offset_s() + 4.0 * p.fwhm_s() - t0;
        let v = p.render(t0, dt, (span / dt) as usize);
        let onset = (-t0 / dt).round() as usize;
        assert!(
            v[..onset].iter().all(|&x| x == 0.0),
            "{p:?}: zero before the onset"
        );
        assert_eq!(p.value(0.0), 0.0, "{p:?}: zero at the onset");
        assert!(v[onset + 1] > 0.0, "{p:?}: leaves zero at the onset");
        let (k_peak, peak) = v
            .iter()
            .enumerate()
            .fold((0, 0.0), |m, (k, &x)| if x > m.1 { (k, x) } else { m });
        assert!((peak - 1.0).abs() < 1e-6, "{p:?}: peak {peak}");
        let t_peak = t0 + k_peak as f64 * dt;
        assert!(
            (t_peak - p.peak_offset_s()).abs() < 0.05 * ns,
            "{p:?}: peak at {t_peak:e}"
        );
        let t10 = crossing(&v, t0, dt, 0.1, onset, true);
        let t50 = crossing(&v, t0, dt, 0.5, onset, true);
        let t90 = crossing(&v, t0, dt, 0.9, onset, true);
        let t50_fall = crossing(&v, t0, dt, 0.5, v.len() - 1, false);
        let tol = |x: f64| 1e-4 * x + 2.0 * dt;
        assert!(
            (t90 - t10 - p.rise_s()).abs() < tol(p.rise_s()),
            "{p:?}: rise {:e}",
            t90 - t10
        );
        assert!(
            (t50_fall - t50 - p.fwhm_s()).abs() < tol(p.fwhm_s()),
            "{p:?}: FWHM {:e}",
            t50_fall - t50
        );
        assert!(
            (t50 - p.half_rise_offset_s()).abs() < 2.0 * dt,
            "{p:?}: half rise {t50:e}"
        );
        // Monotone rise to the peak, monotone fall after it.
        assert!(
            v[onset..k_peak].windows(2).all(|w| w[1] >= w[0]),
            "{p:?}: rise not monotone"
        );
        assert!(
            v[k_peak..].windows(2).all(|w| w[1] <= w[0]),
            "{p:?}: fall not monotone"
        );
        assert!(p.value(p.support_s() * 1.0001) < 1e-12, "{p:?}: support");
    }
}

/// Noise-free, unquantised frames hold exactly the configured pulses at the
/// truth's onsets: start at `t_shot_s`, returns at
/// `t_shot_s + system_delay_s + 2 range / c`.
#[test]
fn frames_hold_the_pulses_at_the_truths_onsets() {
    let cfg = GenConfig {
        targets: vec![(10.0, 0.5), (40.0, 0.2), (41.0, 0.1)],
        start_jitter_s: 1e-9,
        return_pulse: PulseFamily::RaisedCosine {
            rise_s: 6e-9,
            fwhm_s: 15e-9,
        },
        ..clean()
    };
    for (f, t) in generate(&cfg, 8, 3) {
        assert_eq!(f.first_sample_offset_s, -cfg.pretrigger_s);
        assert_eq!(t.returns.len(), 3);
        for (echo, &(r, a)) in t.returns.iter().zip(&cfg.targets) {
            assert_eq!((echo.range_m, echo.amplitude_v), (r, a));
            assert!((echo.tof_s - 2.0 * r / cfg.speed_of_light_m_per_s).abs() < 1e-20);
            assert!((echo.t_ref_s - (t.t_shot_s + cfg.system_delay_s + echo.tof_s)).abs() < 1e-18);
        }
        let got = stop(&f).volts();
        for (k, v) in got.iter().enumerate() {
            let tk = f.sample_time_s(k as f64);
            let want: f64 = cfg.noise_mean_v
                + t.returns
                    .iter()
                    .map(|e| e.amplitude_v * cfg.return_pulse.value(tk - e.t_ref_s))
                    .sum::<f64>();
            assert!((v - want).abs() < 1e-12, "stop sample {k}: {v} vs {want}");
        }
        for (k, v) in start(&f).volts().iter().enumerate() {
            let want = cfg.start_amplitude_v
                * cfg
                    .start_pulse
                    .value(f.sample_time_s(k as f64) - t.t_shot_s);
            assert!((v - want).abs() < 1e-12, "start sample {k}: {v} vs {want}");
        }
    }
}

/// Without jitter the shot is uniform over one sample period centred on the
/// nominal instant: Kolmogorov–Smirnov at 0.1 % (critical 1.949/sqrt(n)).
#[test]
fn shot_phase_is_uniform_against_the_sample_clock() {
    let cfg = GenConfig {
        start_jitter_s: 0.0,
        targets: vec![],
        samples: 64,
        ..clean()
    };
    let mut u: Vec<f64> = generate(&cfg, 2000, 9)
        .iter()
        .map(|(_, t)| t.t_shot_s / cfg.dt_s + 0.5)
        .collect();
    assert!(u.iter().all(|x| (0.0..1.0).contains(x)));
    u.sort_by(f64::total_cmp);
    let n = u.len() as f64;
    let d = u
        .iter()
        .enumerate()
        .map(|(i, &x)| (x - i as f64 / n).abs().max(((i + 1) as f64 / n - x).abs()))
        .fold(0.0, f64::max);
    assert!(d < 1.949 / n.sqrt(), "KS distance {d}");
}

#[test]
fn quantisation_uses_the_range_and_counts_clipping() {
    // Automatic scale: i8 codes, the 1.5 V return fills most of the range
    // above the baseline without clipping, and the noise spans codes.
    let cfg = GenConfig::default();
    let span = cfg.stop_adc_span_v();
    assert_eq!(
        span,
        auto_full_scale_v(1.5, cfg.noise_sigma_v, cfg.baseline_fraction)
    );
    for (f, t) in generate(&cfg, 8, 1) {
        for ch in [stop(&f), start(&f)] {
            let Samples::I8(codes) = &ch.samples else {
                panic!("i8 codes")
            };
            let base = ((0.0 - ch.offset_v) / ch.volts_per_code).round();
            let top = *codes.iter().max().unwrap() as f64;
            assert!(top < 127.0, "{}: no clipping", ch.name);
            assert!(
                top - base > 0.6 * (127.0 - base),
                "{}: pulse uses the range",
                ch.name
            );
            // Bottom rail: code −128 is −baseline_fraction·span.
            let rail = -128.0 * ch.volts_per_code + ch.offset_v;
            assert!((rail + cfg.baseline_fraction * ch.volts_per_code * 256.0).abs() < 1e-12);
        }
        assert_eq!(stop(&f).volts_per_code, span / 256.0);
        assert_eq!((t.clipped_stop, t.clipped_start), (0, 0));
    }

    // A fixed 1 V span under a 1.5 V return: clipped samples are exactly
    // those whose analog value rounds above the top code, they read code 127,
    // and every other sample is within half a code of the analog value.
    let fixed = GenConfig {
        full_scale_v: Some(1.0),
        bits: 8,
        ..clean()
    };
    let analog = GenConfig {
        full_scale_v: Some(1.0),
        ..clean()
    };
    for index in 0..4 {
        let (f, t) = frame_with_seed(&fixed, 2, index);
        let (fa, _) = frame_with_seed(&analog, 2, index);
        let ch = stop(&f);
        let Samples::I8(codes) = &ch.samples else {
            panic!("i8 codes")
        };
        let vpc = ch.volts_per_code;
        let top_v = 127.0 * vpc + ch.offset_v;
        let mut clipped = 0;
        for ((&code, v), x) in codes.iter().zip(ch.volts()).zip(stop(&fa).volts()) {
            if x > top_v + 0.5 * vpc {
                clipped += 1;
                assert_eq!(code, 127);
            } else {
                assert!((v - x).abs() <= 0.5 * vpc + 1e-12, "{v} vs {x}");
            }
        }
        assert!(clipped > 5, "the return clips");
        assert_eq!(t.clipped_stop, clipped);
    }

    // Wider ADCs give i16 codes inside their range.
    let (f, _) = frame_with_seed(
        &GenConfig {
            bits: 12,
            ..GenConfig::default()
        },
        4,
        0,
    );
    let Samples::I16(codes) = &stop(&f).samples else {
        panic!("i16 codes")
    };
    assert!(codes.iter().all(|c| (-2048..2048).contains(c)));

    // The receiver's swing limits the analog signal before the ADC.
    let limited = GenConfig {
        receiver_limit_v: Some(1.0),
        ..clean()
    };
    let (f, _) = frame_with_seed(&limited, 4, 0);
    let top = stop(&f).volts().into_iter().fold(f64::MIN, f64::max);
    assert!((top - 1.0).abs() < 1e-12, "limited at {top}");
}

#[test]
fn frames_are_deterministic_per_seed_and_index() {
    let cfg = GenConfig {
        events: Some(EventConfig {
            probability: 0.5,
            ..EventConfig::default()
        }),
        ..GenConfig::default()
    };
    let batch = generate(&cfg, 6, 42);
    for (i, item) in batch.iter().enumerate() {
        assert_eq!(item, &frame_with_seed(&cfg, 42, i as u64));
        assert_eq!(item.0.sequence, i as u64);
    }
    assert_ne!(batch[0], batch[1]);
    assert_ne!(batch[0].0, frame_with_seed(&cfg, 43, 0).0);
    // Bursts that never happen change nothing else.
    let never = GenConfig {
        events: Some(EventConfig {
            probability: 0.0,
            ..EventConfig::default()
        }),
        ..GenConfig::default()
    };
    let none = GenConfig {
        events: None,
        ..GenConfig::default()
    };
    assert_eq!(
        frame_with_seed(&never, 42, 3),
        frame_with_seed(&none, 42, 3)
    );
}

/// Bursts appear in the configured fraction of frames: the count of M
/// Bernoulli(p) frames lies within Z·sqrt(M p (1 − p)) of M p (normal
/// approximation, M p (1 − p) = 315 here). Each burst starts inside its
/// frame, is absent before its onset, and peaks at `peak_v` when it fits.
#[test]
fn bursts_occur_in_the_configured_fraction_of_frames() {
    let ev = EventConfig {
        probability: 0.3,
        ..EventConfig::default()
    };
    let cfg = GenConfig {
        events: Some(ev.clone()),
        laser_off: true,
        ..clean()
    };
    let m = 1500;
    let frames = generate(&cfg, m, 17);
    let k = frames
        .iter()
        .filter(|(_, t)| t.event_at_s.is_some())
        .count() as f64;
    let (mean, sd) = (
        m as f64 * ev.probability,
        (m as f64 * ev.probability * (1.0 - ev.probability)).sqrt(),
    );
    assert!(
        (k - mean).abs() < Z * sd,
        "{k} bursts in {m} frames, expected {mean} ± {}",
        Z * sd
    );

    let mut whole = 0;
    for (f, t) in &frames {
        let v: Vec<f64> = stop(f)
            .volts()
            .iter()
            .map(|x| x - cfg.noise_mean_v)
            .collect();
        let t_first = f.sample_time_s(0.0);
        let t_end = f.sample_time_s(f.len() as f64);
        match t.event_at_s {
            None => assert!(v.iter().all(|&x| x == 0.0)),
            Some(at) => {
                assert!(at >= t_first && at < t_end);
                for (i, &x) in v.iter().enumerate() {
                    if f.sample_time_s(i as f64) <= at {
                        assert_eq!(x, 0.0);
                    }
                }
                if at + ev.duration_s() < t_end {
                    whole += 1;
                    let top = v.iter().copied().fold(f64::MIN, f64::max);
                    assert!(
                        (top - ev.peak_v).abs() < 2e-3 * ev.peak_v,
                        "burst peak {top}"
                    );
                }
            }
        }
    }
    assert!(whole > 100);
}

/// The burst's energy lies below 10 MHz, as the prototype's did (DFT of one
/// burst rendered at 1 GS/s over 4 µs: bins below 10 MHz hold > 95 % of it).
#[test]
fn burst_energy_is_below_10_mhz() {
    let ev = EventConfig::default();
    let (dt, n) = (1e-9, 4000);
    let x = ev.render(0.0, dt, n);
    let total: f64 = x.iter().map(|v| v * v).sum();
    let df = 1.0 / (n as f64 * dt);
    let mut low = 0.0;
    for j in 0..=((10e6 / df) as usize) {
        let w = 2.0 * std::f64::consts::PI * j as f64 / n as f64;
        let (re, im) = x.iter().enumerate().fold((0.0, 0.0), |(re, im), (k, &v)| {
            (re + v * (w * k as f64).cos(), im - v * (w * k as f64).sin())
        });
        // Parseval: bin j (and its mirror, except DC) carries (re² + im²)/n.
        low += (re * re + im * im) / n as f64 * if j == 0 { 1.0 } else { 2.0 };
    }
    assert!(low / total > 0.95, "below 10 MHz: {:.3}", low / total);
}
