//! Golden reports: every shipped capture and every shipped scene, through
//! the pipeline with each stage and timing method switched on in turn,
//! compared byte for byte with the reports committed in `tests/data/golden/`.
//!
//! A change that is meant to leave behaviour alone (a refactor) must pass
//! this unchanged. A change that is meant to alter reports regenerates them
//! on an explicit flag and the diff is reviewed:
//!
//! ```sh
//! TOFWAVE_BLESS=1 cargo test --release --test suite golden::
//! git diff --stat tests/data/golden/
//! ```
//!
//! Only the public, stable surface is used (scene TOML, capture readers, the
//! simulator, `Pipeline`, the JSON report line), so the test survives
//! internal reorganisation.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use tofwave::capture::{read_paths, ReadOptions};
use tofwave::frame::Frame;
use tofwave::physics::Simulator;
use tofwave::pipeline::{report_json, Pipeline};
use tofwave::scene::Scene;

const TIMING_METHODS: [&str; 5] = ["constant_fraction", "leading_edge", "peak_parabolic", "peak_gaussian", "ml"];

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn golden_dir() -> PathBuf {
    root().join("tests/data/golden")
}

/// The scene from `base` TOML text with `overrides` (dotted key = TOML value) applied.
fn scene_with(base: &str, origin: &str, overrides: &[(&str, &str)]) -> Scene {
    let mut doc: toml::Table = base.parse().expect("scene TOML parses");
    for (key, value) in overrides {
        let parsed: toml::Table = format!("v = {value}").parse().expect("override value parses");
        let value = parsed["v"].clone();
        let mut parts: Vec<&str> = key.split('.').collect();
        let leaf = parts.pop().expect("non-empty key");
        let mut table = &mut doc;
        for p in parts {
            table = table
                .entry(p)
                .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                .as_table_mut()
                .expect("a table");
        }
        table.insert(leaf.to_string(), value);
    }
    Scene::from_toml_str(&toml::to_string(&doc).expect("serialises"), origin).expect("scene is valid")
}

/// Reports of `frames` through a pipeline built from `scene`, one JSON line each;
/// refused frames appear as an `error` line so that refusals are pinned too.
fn run(scene: &Scene, frames: impl IntoIterator<Item = Frame>) -> String {
    let mut pipeline = Pipeline::new(scene, "golden");
    let mut reports = Vec::new();
    let mut text = String::new();
    for frame in frames {
        reports.clear();
        if let Err(e) = pipeline.push(frame, &mut reports) {
            writeln!(text, "error: {e}").unwrap();
        }
        for r in &reports {
            writeln!(text, "{}", report_json(r)).unwrap();
        }
    }
    reports.clear();
    pipeline.flush(&mut reports);
    for r in &reports {
        writeln!(text, "{}", report_json(r)).unwrap();
    }
    text
}

fn simulated(scene: &Scene, frames: u64) -> Vec<Frame> {
    let sim = Simulator::new(scene).expect("scene simulates");
    (0..frames).map(|i| sim.frame(17, i).0).collect()
}

/// Compares `actual` with the golden file `name`, or writes it when blessing.
/// Returns a description of the mismatch, if any.
fn check(name: &str, actual: &str) -> Option<String> {
    let path = golden_dir().join(format!("{name}.jsonl"));
    if std::env::var_os("TOFWAVE_BLESS").is_some() {
        std::fs::create_dir_all(golden_dir()).unwrap();
        std::fs::write(&path, actual).unwrap();
        return None;
    }
    let expected = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) => return Some(format!("{name}: cannot read {}: {e}", path.display())),
    };
    if expected == actual {
        return None;
    }
    let (el, al): (Vec<&str>, Vec<&str>) = (expected.lines().collect(), actual.lines().collect());
    let first = el.iter().zip(&al).position(|(e, a)| e != a).unwrap_or(el.len().min(al.len()));
    Some(format!(
        "{name}: {} golden lines, {} now; first difference at line {}:\n  golden: {}\n  now:    {}",
        el.len(),
        al.len(),
        first + 1,
        el.get(first).unwrap_or(&"<none>"),
        al.get(first).unwrap_or(&"<none>"),
    ))
}

fn assert_all(cases: Vec<(String, String)>) {
    let failures: Vec<String> = cases.iter().filter_map(|(n, a)| check(n, a)).collect();
    assert!(failures.is_empty(), "{} of {} golden cases differ:\n{}", failures.len(), cases.len(), failures.join("\n"));
}

fn default_toml() -> String {
    Scene::default_scene().to_toml()
}

#[test]
fn shipped_captures_give_the_golden_reports_with_every_timing_method() {
    let captures = ["agilent_1.bin", "lecroy_2.trc", "lecroy_3.trc", "lecroy_4.trc"];
    let mut cases = Vec::new();
    for capture in captures {
        let frames = read_paths(&[root().join("replay-data").join(capture)], &ReadOptions::default())
            .unwrap_or_else(|e| panic!("{capture}: {e}"));
        for method in TIMING_METHODS {
            let scene = scene_with(&default_toml(), "default", &[("timing.method", &format!("\"{method}\""))]);
            let stem = Path::new(capture).file_stem().unwrap().to_string_lossy().to_string();
            cases.push((format!("capture-{stem}-{method}"), run(&scene, frames.clone())));
        }
    }
    assert_all(cases);
}

#[test]
fn shipped_scenes_give_the_golden_reports() {
    let dir = root().join("replay-data/scenes");
    let mut names: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "toml"))
        .collect();
    names.sort();
    assert!(names.len() >= 9, "shipped scenes: {names:?}");
    let mut cases = Vec::new();
    for path in names {
        let stem = path.file_stem().unwrap().to_string_lossy().to_string();
        let text = std::fs::read_to_string(&path).unwrap();
        let scene = scene_with(&text, &stem, &[]);
        // Enough frames for at least two reports where the scene averages.
        let frames = (2 * scene.averaging.frames as u64).max(24);
        cases.push((format!("scene-{stem}"), run(&scene, simulated(&scene, frames))));
    }
    assert_all(cases);
}

/// The lab scene (five returns) with each optional stage and detector mode
/// switched on in turn, so that every stage's output is pinned; and the
/// embedded default scene on its own simulated frames.
#[test]
fn every_stage_and_mode_gives_the_golden_reports() {
    let lab = std::fs::read_to_string(root().join("replay-data/scenes/lab-table-10-20.toml")).unwrap();
    let burst = std::fs::read_to_string(root().join("replay-data/scenes/burst-1m83.toml")).unwrap();
    let default = default_toml();
    let variants: Vec<(&str, &str, Vec<(&str, &str)>, u64)> = vec![
        // The embedded default on its own frames: 8-bit codes, an 89-tap
        // template the f64 filter would run by FFT (filtered in integers),
        // coloured noise, events in the gates and the events stage on.
        ("default-simulated", &default, vec![], 32),
        ("lab-leading_edge", &lab, vec![("timing.method", "\"leading_edge\"")], 16),
        ("lab-peak_parabolic", &lab, vec![("timing.method", "\"peak_parabolic\"")], 16),
        ("lab-peak_gaussian", &lab, vec![("timing.method", "\"peak_gaussian\"")], 16),
        ("lab-ml", &lab, vec![("timing.method", "\"ml\"")], 8),
        ("lab-threshold", &lab, vec![("detector.kind", "\"threshold\"")], 16),
        ("lab-whiten", &lab, vec![("detector.whiten", "true")], 24),
        ("lab-whiten-forgetting", &lab, vec![("detector.whiten", "true"), ("noise_gate.forgetting_frames", "8")], 24),
        ("lab-cfar-ca", &lab, vec![("detector.cfar", "\"ca\"")], 16),
        ("lab-cfar-os", &lab, vec![("detector.cfar", "\"os\"")], 16),
        ("lab-empirical", &lab, vec![("detector.threshold_mode", "\"empirical\"")], 24),
        ("lab-pfa-sample", &lab, vec![("detector.pfa_scope", "\"sample\""), ("detector.pfa", "1e-7")], 16),
        ("lab-baseline", &lab, vec![("baseline.smoothing", "0.5")], 16),
        ("lab-average-block", &lab, vec![("averaging.frames", "4")], 16),
        (
            "lab-average-sliding-median",
            &lab,
            vec![("averaging.frames", "4"), ("averaging.mode", "\"sliding\""), ("averaging.method", "\"median\"")],
            16,
        ),
        (
            "lab-average-trimmed",
            &lab,
            vec![("averaging.frames", "4"), ("averaging.method", "\"trimmed_mean\"")],
            16,
        ),
        ("burst-template", &burst, vec![("denoise.method", "\"template\""), ("denoise.learn_frames", "24")], 48),
        ("burst-notch", &burst, vec![("denoise.method", "\"notch\""), ("denoise.notch_frequencies_hz", "[2e6, 5e6]")], 16),
        ("burst-highpass", &burst, vec![("denoise.method", "\"highpass\"")], 16),
    ];
    let mut cases = Vec::new();
    for (name, base, overrides, frames) in variants {
        let scene = scene_with(base, name, &overrides);
        cases.push((format!("stage-{name}"), run(&scene, simulated(&scene, frames))));
    }
    assert_all(cases);
}
