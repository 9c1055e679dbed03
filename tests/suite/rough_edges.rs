//! The rough edges a new user hit (issue 16), one test each where a test can
//! hold it; `docs/rough-edges.md` has the before/after of every one.

use crate::common::{replay_path, tofwave};
use std::path::Path;

fn repo(p: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

#[test]
fn process_of_a_directory_skips_non_captures_with_a_note() {
    let dir = replay_path("");
    let (code, reports, err) = tofwave(&["process", "--input", dir.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("LICENSE-scope-captures.txt: skipped, text without a capture header"), "{err}");
    assert!(err.contains("README.md: skipped, not a capture file extension"), "{err}");
    // lecroy_4 (1 frame) and lecroy_3 (20 segments) are among them.
    assert!(reports.len() >= 21, "{} reports", reports.len());
    // A file named on the command line is still read, and fails loudly.
    let (code, _, err) = tofwave(&["process", "--input", replay_path("LICENSE-scope-captures.txt").to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("LICENSE-scope-captures.txt: line 1"), "{err}");
}

#[test]
fn a_channel_flag_the_capture_lacks_is_blamed_on_the_flag() {
    let input = replay_path("lecroy_4.trc");
    let (code, reports, err) = tofwave(&["process", "--input", input.to_str().unwrap(), "--stop-channel", "CH3"]);
    assert_eq!(code, 2, "{err}");
    assert!(reports.is_empty());
    assert!(err.contains("--stop-channel CH3: the capture has no such channel") && err.contains("has C2"), "{err}");
    assert!(!err.contains("channels.stop in the scene"), "{err}");
    let (code, _, err) = tofwave(&["process", "--input", input.to_str().unwrap(), "--start-channel", "CH1"]);
    assert_eq!(code, 2);
    assert!(err.contains("--start-channel CH1: the capture has no such channel"), "{err}");
    // Vendor spellings of the channel it has still match.
    let (code, _, err) = tofwave(&["process", "--input", input.to_str().unwrap(), "--stop-channel", "CH2"]);
    assert_eq!(code, 0, "{err}");
}

#[test]
fn errors_say_their_cause_once() {
    let (code, _, err) = tofwave(&["process", "--input", "no-such-file.trc"]);
    assert_eq!(code, 2);
    assert_eq!(err.matches("No such file or directory").count(), 1, "{err}");
    let (code, _, err) = tofwave(&["process", "--scene", "no-such-scene.toml", "--input", "x.trc"]);
    assert_eq!(code, 2);
    assert_eq!(err.matches("No such file or directory").count(), 1, "{err}");
    // A port nobody listens on, given without http://.
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let to = format!("127.0.0.1:{port}");
    let (code, _, err) = tofwave(&["replay", "--to", &to, "--input", replay_path("lecroy_4.trc").to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains(&format!("connecting to http://{to}")), "{err}");
    for once in ["transport error", "tcp connect error", "Connection refused"] {
        assert_eq!(err.matches(once).count(), 1, "{once}: {err}");
    }
    let (code, _, err) = tofwave(&["replay", "--to", "nats://127.0.0.1:4222", "--input", replay_path("lecroy_4.trc").to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("scheme \"nats\" is not served"), "{err}");
}

#[test]
fn calibrate_and_scene_check_print_human_numbers_and_calibrate_warns_without_a_start_channel() {
    let dir = tempfile::tempdir().unwrap();
    let cal = dir.path().join("cal.toml");
    let (code, _, err) = tofwave(&[
        "calibrate", "--input", replay_path("lecroy_4.trc").to_str().unwrap(), "--known-range-m", "3", "--out", cal.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("warning: 1 of 1 reports have no start channel"), "{err}");
    let line = err.lines().find(|l| l.contains("tofwave calibrate: delay")).expect("delay line");
    assert!(line.contains(" ns ± ") && !line.contains("0.0000000"), "{line}");
    let text = std::fs::read_to_string(&cal).unwrap();
    assert!(text.contains("Measured without a start channel"), "{text}");
    let delay_line = text.lines().find(|l| l.starts_with("delay_s = ")).unwrap();
    assert!(delay_line.contains("e-") && delay_line.contains(" ns"), "{delay_line}");
    assert!(!text.contains("0.0000000"), "{text}");
    // The file still loads and applies.
    let (code, _, err) = tofwave(&["process", "--input", replay_path("lecroy_4.trc").to_str().unwrap(), "--calibration", cal.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");

    let scene = dir.path().join("s.toml");
    std::fs::write(&scene, crate::common::tofwave_ok(&["scene"])).unwrap();
    let out = crate::common::tofwave_ok(&["scene", "--check", scene.to_str().unwrap()]);
    assert!(out.contains("rise_time_s = 8.08e-9  # 8.080 ns"), "{out}");
    assert!(!out.contains("0.0000000"), "{out}");
}

#[test]
fn simulate_csv_is_a_file_and_the_truths_tof_holds_the_system_delay() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("x.csv");
    let truth = dir.path().join("t.csv");
    let (code, _, err) = tofwave(&["simulate", "--frames", "1", "--out", csv.to_str().unwrap(), "--truth", truth.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(csv.is_file());
    let text = std::fs::read_to_string(&truth).unwrap();
    let c_air = tofwave::scene::Scene::default_scene().c_medium_m_per_s();
    let mut delays = Vec::new();
    for row in text.lines().skip(1).filter(|l| l.split(',').nth(1) == Some("return")) {
        let cells: Vec<&str> = row.split(',').collect();
        let (range_m, tof_s): (f64, f64) = (cells[6].parse().unwrap(), cells[7].parse().unwrap());
        delays.push(tof_s - 2.0 * range_m / c_air);
    }
    assert!(!delays.is_empty());
    // One delay for every target (the chain's), positive, about 2 ns: what --help says.
    let (lo, hi) = delays.iter().fold((f64::MAX, f64::MIN), |(a, b), &d| (a.min(d), b.max(d)));
    assert!(lo > 1.5e-9 && hi < 2.7e-9, "{delays:?}");
    let help = crate::common::tofwave_ok(&["simulate", "--help"]);
    assert!(help.contains("system delay") && help.contains("geometric range"), "{help}");
}

#[test]
fn every_report_flag_is_documented_in_the_flags_table() {
    let src = std::fs::read_to_string(repo("src/frame.rs")).unwrap();
    let doc = std::fs::read_to_string(repo("docs/report-flags.md")).unwrap();
    let readme = std::fs::read_to_string(repo("README.md")).unwrap();
    assert!(readme.contains("docs/report-flags.md"), "README links the flags table");
    let mut names = Vec::new();
    for line in src.lines() {
        let l = line.trim();
        if (l.starts_with("FrameFlag::") || l.starts_with("ReturnFlag::")) && l.contains("=> \"") {
            names.push(l.split('"').nth(1).unwrap().to_string());
        }
    }
    assert!(names.len() >= 29, "{names:?}");
    for n in names {
        assert!(doc.contains(&format!("| `{n}` |")), "{n} is not in docs/report-flags.md");
    }
}

#[test]
fn the_readme_sample_report_is_real_output() {
    let readme = std::fs::read_to_string(repo("README.md")).unwrap();
    let start = readme.find("The first command prints").expect("sample intro");
    let block = &readme[start..];
    let json_start = block.find("```json\n").unwrap() + 8;
    let json_end = json_start + block[json_start..].find("```").unwrap();
    let sample: serde_json::Value = serde_json::from_str(&block[json_start..json_end]).expect("the README sample is JSON");
    let (code, reports, err) = tofwave(&["process", "--input", replay_path("lecroy_4.trc").to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    fn same(a: &serde_json::Value, b: &serde_json::Value, path: &str) {
        use serde_json::Value::*;
        match (a, b) {
            (Object(x), Object(y)) => {
                let kx: Vec<_> = x.keys().collect();
                let ky: Vec<_> = y.keys().collect();
                assert_eq!(kx, ky, "keys at {path}");
                for (k, v) in x {
                    same(v, &y[k], &format!("{path}.{k}"));
                }
            }
            (Array(x), Array(y)) => {
                assert_eq!(x.len(), y.len(), "length at {path}");
                for (i, (u, v)) in x.iter().zip(y).enumerate() {
                    same(u, v, &format!("{path}[{i}]"));
                }
            }
            (Number(x), Number(y)) => {
                let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
                assert!((x - y).abs() <= 1e-3 * y.abs().max(1e-12), "{path}: README {x}, real {y}");
            }
            _ => assert_eq!(a, b, "at {path}"),
        }
    }
    same(&sample, &reports[0], "report");
}
