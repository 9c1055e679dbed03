//! The `tofwave` command as a new user runs it: real captures, calibration on
//! simulated captures, noise-only captures, malformed files.

use crate::common;
use common::{replay_path, rng, tofwave, Synth};
use std::path::Path;
use std::process::Command;
use tofwave::capture::write_recording;
use tofwave::scene::Scene;

fn data(name: &str) -> String {
    replay_path(name).display().to_string()
}

#[test]
fn lecroy_4_pulse_is_reported_at_the_time_the_file_holds() {
    let (code, reports, err) = tofwave(&["process", "--input", &data("lecroy_4.trc")]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(reports.len(), 1);
    let r = &reports[0]["returns"];
    assert_eq!(r.as_array().unwrap().len(), 1, "{r}");
    let t_peak_ns = r[0]["t_peak_s"].as_f64().unwrap() * 1e9;
    let t_half_ns = r[0]["t_stop_s"].as_f64().unwrap() * 1e9;
    let amp = r[0]["amplitude_v"].as_f64().unwrap();
    // The file: peak 2.504 V at +4.25 ns, 50 % rising crossing at +0.77 ns (8 mV baseline).
    assert!((t_peak_ns - 4.25).abs() < 0.3, "{t_peak_ns}");
    assert!((t_half_ns - 0.77).abs() < 0.3, "{t_half_ns}");
    assert!((amp - 2.5).abs() < 0.1, "{amp}");
    assert!(reports[0]["flags"].as_array().unwrap().iter().any(|f| f == "no_start_channel"));
}

#[test]
fn lecroy_3_segments_give_reports_with_their_trigger_times_and_average() {
    let (code, reports, err) = tofwave(&["process", "--input", &data("lecroy_3.trc")]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(reports.len(), 20);
    let t: Vec<f64> = reports.iter().map(|r| r["time_s"].as_f64().unwrap()).collect();
    assert!((t[1] - t[0] - 7.4584e-3).abs() < 1e-6, "{}", t[1] - t[0]);
    assert!((t[2] - t[0] - 1.7308e-2).abs() < 1e-6);
    assert!(reports.iter().all(|r| r["returns"].as_array().unwrap().len() == 1));
    let (code, reports, _) = tofwave(&["process", "--input", &data("lecroy_3.trc"), "--average", "20"]);
    assert_eq!(code, 0);
    assert_eq!(reports.len(), 1);
    assert_eq!(reports[0]["frames_averaged"], 20);
    assert_eq!(reports[0]["seq_last"], 19);
    assert_eq!(reports[0]["returns"].as_array().unwrap().len(), 1);
}

/// Captures of one target: 1 GS/s, 13.8 mV rms noise, 8-bit quantisation, a
/// fixed system delay of 223.33 ns (the source's amplifier delay).
fn captures(path: &Path, range_m: f64, amp: f64, frames: u64, seed: u64) {
    let scene = Scene::default_scene();
    let delay_s = 223.33e-9;
    let tof = 2.0 * range_m / scene.c_medium_m_per_s() + delay_s;
    let s = Synth { returns: vec![(tof, amp)], ..Synth::prototype() };
    let mut r = rng(seed);
    let v: Vec<_> = (0..frames)
        .map(|k| {
            let mut st = s.clone();
            // The start pulse moves against the sample clock from shot to shot.
            st.start_time_s = (k as f64 * 0.37).fract() * 1e-9;
            st.frame(&scene, k, &mut r)
        })
        .collect();
    write_recording(path, &v).unwrap();
}

#[test]
fn calibrated_ranges_are_within_2_cm() {
    let dir = tempfile::tempdir().unwrap();
    let cal_in = dir.path().join("cal.twr");
    captures(&cal_in, 3.45, 1.0, 300, 1);
    let cal = dir.path().join("cal.toml");
    let (code, _, err) = tofwave(&[
        "calibrate", "--input", cal_in.to_str().unwrap(), "--known-range-m", "3.45", "--out", cal.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    eprintln!("{err}");
    let mut errors = Vec::new();
    // Table 10.20's targets at their measured peak voltages (>= 300 mV).
    for (i, (range_m, amp)) in [(9.5, 0.56), (15.3986, 0.505), (24.8122, 0.496), (19.6814, 0.392)].into_iter().enumerate() {
        let input = dir.path().join(format!("t{i}.twr"));
        captures(&input, range_m, amp, 200, 10 + i as u64);
        let (code, reports, err) =
            tofwave(&["process", "--input", input.to_str().unwrap(), "--calibration", cal.to_str().unwrap()]);
        assert_eq!(code, 0, "{err}");
        let ranges: Vec<f64> = reports.iter().map(|r| r["returns"][0]["range_m"].as_f64().unwrap()).collect();
        assert_eq!(ranges.len(), 200);
        let mean = ranges.iter().sum::<f64>() / ranges.len() as f64;
        let sd = (ranges.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / 199.0).sqrt();
        eprintln!("{range_m} m at {amp} V: mean {mean:.4} m (error {:+.4} m), single-shot sd {sd:.4} m", mean - range_m);
        errors.push((range_m, mean - range_m));
    }
    for (range_m, e) in errors {
        assert!(e.abs() < 0.02, "{range_m} m: error {e} m");
    }
}

#[test]
fn noise_only_captures_report_every_frame_within_the_design_pfa() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("off.twr");
    let scene = Scene::default_scene();
    let s = Synth { start_amplitude_v: 0.0, ..Synth::prototype() };
    let mut r = rng(5);
    let frames: Vec<_> = (0..400)
        .map(|k| {
            let mut f = s.frame(&scene, k, &mut r);
            f.laser_off = true;
            f
        })
        .collect();
    write_recording(&input, &frames).unwrap();
    let (code, reports, err) = tofwave(&["process", "--input", input.to_str().unwrap(), "--pfa", "0.01"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(reports.len(), 400);
    let with_returns = reports.iter().filter(|r| !r["returns"].as_array().unwrap().is_empty()).count();
    // Binomial(400, 0.01): P(X > 10) = 0.0028, so 10 is the 99.7 % upper bound.
    assert!(with_returns <= 10, "{with_returns} of 400 noise-only reports had returns at pfa 0.01");
    assert!(reports.iter().all(|r| r["flags"].as_array().unwrap().iter().any(|f| f == "no_start_pulse")));
}

#[test]
fn malformed_files_get_a_clear_error_and_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let real = std::fs::read(data("lecroy_4.trc")).unwrap();
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        ("empty.trc", vec![], "empty"),
        ("truncated.trc", real[..700].to_vec(), "byte"),
        ("magic.trc", { let mut v = real.clone(); v[11..19].copy_from_slice(b"WAVEDESX"); v }, "magic.trc"),
        ("cell.csv", b"time,CH1,CH2\n0,0.1,0.2\n1e-9,0.1,abc\n".to_vec(), "line 3"),
    ];
    for (name, bytes, needle) in cases {
        let p = dir.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        let (code, reports, err) = tofwave(&["process", "--input", p.to_str().unwrap()]);
        assert_eq!(code, 2, "{name}: {err}");
        assert!(reports.is_empty());
        assert!(err.contains(name) && err.contains(needle), "{name}: {err}");
    }
    // A stop channel the scene names but a frame lacks refuses the frame by
    // name (exit 1), not the run.
    let p = dir.path().join("two.csv");
    let rows: String = (0..200).map(|k| format!("{:e},0.01,0.02\n", k as f64 * 1e-9)).collect();
    std::fs::write(&p, format!("time,CH1,CH2\n{rows}")).unwrap();
    let mut doc: toml::Table = toml::from_str(&tofwave::scene::Scene::default_scene().to_toml()).unwrap();
    doc["channels"]["stop"] = toml::Value::String("CH3".into());
    let scene = dir.path().join("ch3.toml");
    std::fs::write(&scene, toml::to_string(&doc).unwrap()).unwrap();
    let (code, reports, err) = tofwave(&["process", "--input", p.to_str().unwrap(), "--scene", scene.to_str().unwrap()]);
    assert_eq!(code, 1, "{err}");
    assert!(reports.is_empty());
    assert!(err.contains("CH3") && err.contains("channels.stop in the scene"), "{err}");
    // Named by the flag instead, the flag is blamed and nothing runs (exit 2).
    let (code, reports, err) = tofwave(&["process", "--input", p.to_str().unwrap(), "--stop-channel", "CH3"]);
    assert_eq!(code, 2, "{err}");
    assert!(reports.is_empty());
    assert!(err.contains("--stop-channel CH3: the capture has no such channel") && err.contains("CH1, CH2"), "{err}");
}

#[test]
fn process_output_holds_every_report_a_bad_input_leaves_none_and_a_failed_write_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("reports.jsonl");
    let out_s = out.to_str().unwrap();
    // The inputs are read first: a bad one leaves no output file behind.
    let missing = dir.path().join("missing.trc");
    let (code, _, err) = tofwave(&["process", "--input", missing.to_str().unwrap(), "--output", out_s]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("missing.trc") && !out.exists(), "{err}");
    // Every report, in order, one line each, as on stdout.
    let (code, _, err) = tofwave(&["process", "--input", &data("lecroy_3.trc"), "--output", out_s]);
    assert_eq!(code, 0, "{err}");
    let (_, on_stdout, _) = tofwave(&["process", "--input", &data("lecroy_3.trc")]);
    let written: Vec<serde_json::Value> =
        std::fs::read_to_string(&out).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(written.len(), 20);
    assert_eq!(written, on_stdout);
    assert!(err.contains("20 reports"), "{err}");
    // Every frame refused (exit 1): no reports, and an empty output.
    let csv = dir.path().join("two.csv");
    let rows: String = (0..200).map(|k| format!("{:e},0.01,0.02\n", k as f64 * 1e-9)).collect();
    std::fs::write(&csv, format!("time,CH1,CH2\n{rows}")).unwrap();
    let mut doc: toml::Table = toml::from_str(&Scene::default_scene().to_toml()).unwrap();
    doc["channels"]["stop"] = toml::Value::String("CH3".into());
    let scene = dir.path().join("ch3.toml");
    std::fs::write(&scene, toml::to_string(&doc).unwrap()).unwrap();
    let none = dir.path().join("none.jsonl");
    let args = ["process", "--input", csv.to_str().unwrap(), "--scene", scene.to_str().unwrap(), "--output", none.to_str().unwrap()];
    let (code, _, err) = tofwave(&args);
    assert_eq!(code, 1, "{err}");
    assert_eq!(std::fs::read_to_string(&none).unwrap(), "", "{err}");
    // A device that takes no bytes: the write's error is the command's.
    if Path::new("/dev/full").exists() {
        let (code, _, err) = tofwave(&["process", "--input", &data("lecroy_3.trc"), "--output", "/dev/full"]);
        assert_eq!(code, 2, "{err}");
        assert!(err.contains("cannot write the reports to /dev/full"), "{err}");
    }
}

#[test]
fn every_subcommand_explains_its_flags() {
    for sub in ["process", "calibrate", "scene", "template", "simulate", "serve", "replay", "subscribe"] {
        let out = Command::new(env!("CARGO_BIN_EXE_tofwave")).args([sub, "--help"]).output().unwrap();
        assert!(out.status.success(), "{sub}");
        assert!(String::from_utf8(out.stdout).unwrap().contains("--"), "{sub}");
    }
    let out = Command::new(env!("CARGO_BIN_EXE_tofwave")).arg("scene").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    Scene::from_toml_str(&text, "printed default").expect("the printed default scene parses");
}

/// A tiny sampling period once sized the pipeline's buffers (1e-12 s: seconds
/// per frame; 1e-19 s: an allocation abort, exit 134; 1e-28 s: a capacity
/// overflow panic, exit 101). Each is now a named error within the exit-code
/// contract: 2 when the reader refuses the file, 1 when the pipeline refuses
/// the frame (its period with the scene's pulse makes a template past the
/// bound).
#[test]
fn tiny_sample_intervals_are_named_errors_not_crashes() {
    let dir = tempfile::tempdir().unwrap();
    for dt in [1e-12, 1e-14, 1e-16, 1e-19, 1e-28, 1e-30] {
        let p = dir.path().join(format!("dt{dt:e}.csv"));
        let rows: String = (0..200).map(|k| format!("{:e},{}\n", k as f64 * dt, 0.01 * ((k * 7919) % 13) as f64)).collect();
        std::fs::write(&p, format!("time,CH2\n{rows}")).unwrap();
        let (code, reports, err) = tofwave(&["process", "--input", p.to_str().unwrap()]);
        assert!(code == 1 || code == 2, "dt {dt:e}: exit {code}: {err}");
        assert!(reports.is_empty(), "dt {dt:e}");
        assert!(err.contains("sample_interval_s"), "dt {dt:e}: {err}");
        if code == 2 {
            assert!(err.contains(p.file_name().unwrap().to_str().unwrap()) && err.contains("[1e-12, 1] s"), "{err}");
        } else {
            assert!(err.contains("template taps") && err.contains("return_pulse"), "{err}");
        }
    }
    // A pulse width whose template alone outgrows any sane frame is refused
    // when the scene is loaded, by name.
    let scene = dir.path().join("wide.toml");
    let text = Scene::default_scene().to_toml();
    let mut doc: toml::Table = toml::from_str(&text).unwrap();
    doc["return_pulse"]["fwhm_s"] = toml::Value::Float(1e-3);
    std::fs::write(&scene, toml::to_string(&doc).unwrap()).unwrap();
    let p = dir.path().join("ok.csv");
    let rows: String = (0..200).map(|k| format!("{:e},0.01\n", k as f64 * 1e-9)).collect();
    std::fs::write(&p, format!("time,CH2\n{rows}")).unwrap();
    let (code, _, err) = tofwave(&["process", "--scene", scene.to_str().unwrap(), "--input", p.to_str().unwrap()]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("return_pulse.fwhm_s") && err.contains("0.001") && err.contains("(0, 1e-6] s"), "{err}");
}

/// `--token ""` used to start an open server with only a log warning.
#[test]
fn serve_refuses_an_empty_token() {
    let (code, _, err) = tofwave(&["serve", "--listen", "127.0.0.1:0", "--token", ""]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("--token") && err.contains("empty"), "{err}");
}

/// `simulate` with no scene simulates the prototype (the default scene's
/// `[simulation]`): `process` on its frames reports Table 10.20's lab targets
/// (the five above the noise; the 20.8 mV return at 32.1 m needs averaging)
/// at their ranges plus the uncalibrated chain delay (about 0.3 m), and the
/// CSV truth lists the receiver's interference events in about a third of
/// the frames: within the 99.9 % binomial interval, 300 p ± 3.29 sqrt(300
/// p (1 − p)) = 100 ± 27 for p = 1/3, each with its 0.35 V peak inside the
/// 2.5 us frame's span after its onset.
#[test]
fn simulate_without_a_scene_gives_the_lab_targets_and_the_interference_events() {
    let dir = tempfile::tempdir().unwrap();
    let (out, truth) = (dir.path().join("prototype.twr"), dir.path().join("truth.csv"));
    let (out_s, truth_s) = (out.to_str().unwrap(), truth.to_str().unwrap());
    let (code, _, err) = tofwave(&["simulate", "--frames", "300", "--out", out_s, "--truth", truth_s]);
    assert_eq!(code, 0, "{err}");
    assert!(out.is_file() && truth.is_file());
    let (code, reports, err) = tofwave(&["process", "--input", out_s]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(reports.len(), 300);
    for range_m in [3.45, 9.5, 15.3986, 19.6814, 24.8122] {
        let found = reports
            .iter()
            .filter(|r| {
                r["returns"].as_array().unwrap().iter().any(|x| (x["range_m"].as_f64().unwrap() - range_m - 0.3).abs() < 0.5)
            })
            .count();
        assert!(found >= 285, "the {range_m} m target is reported in {found} of 300 frames");
    }
    // The truth: one frame row per frame, six returns each, events with their onset and peak.
    let text = std::fs::read_to_string(&truth).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("sequence,kind,index,t_s,t_peak_s,peak_v,range_m,tof_s,flags"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    let kind = |k: &str| rows.iter().filter(|r| r[1] == k).count();
    assert_eq!(kind("frame"), 300);
    assert_eq!(kind("return"), 6 * 300);
    let events: Vec<&Vec<&str>> = rows.iter().filter(|r| r[1] == "event").collect();
    let mut frames: Vec<&str> = events.iter().map(|r| r[0]).collect();
    frames.dedup();
    assert_eq!(frames.len(), events.len(), "at most one event per frame");
    let p: f64 = 1.0 / 3.0;
    let tol = 3.29 * (300.0 * p * (1.0 - p)).sqrt();
    assert!((events.len() as f64 - 300.0 * p).abs() < tol, "{} of 300 frames hold an event", events.len());
    for e in &events {
        let (start, t_peak, peak): (f64, f64, f64) = (e[3].parse().unwrap(), e[4].parse().unwrap(), e[5].parse().unwrap());
        assert!((-250e-9..2250e-9).contains(&start), "onset {start}");
        assert!(t_peak > start && t_peak < start + 1e-6, "peak {t_peak} after onset {start}");
        assert_eq!(peak, 0.35);
    }
    // The extension chooses the format: .csv is one file (one frame), a path
    // without an extension a directory of CSVs; a .csv of many frames is refused.
    let one = dir.path().join("one.csv");
    let (code, _, err) = tofwave(&["simulate", "--frames", "1", "--out", one.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(one.is_file());
    let many = dir.path().join("many.csv");
    let (code, _, err) = tofwave(&["simulate", "--frames", "2", "--out", many.to_str().unwrap()]);
    assert_ne!(code, 0);
    assert!(err.contains("--frames 1") && !many.exists(), "{err}");
    let frames_dir = dir.path().join("frames");
    let (code, _, err) = tofwave(&["simulate", "--frames", "2", "--out", frames_dir.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(frames_dir.join("frame-00000001.csv").is_file());
}
