//! Operating a real `tofwave serve` process: `replay` to `host:port`, `ctl`
//! (sensors, status, noise, scene, calibration) with the write token,
//! `subscribe`'s warning for a sensor never seen, the metrics the Grafana
//! dashboard queries, and the server's log (addresses announced, shutdown
//! announced, no ANSI colours in a file).

use crate::common::{replay_path, tofwave};
use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

const TOKEN: &str = "s3cret-write";

/// A `tofwave serve` child on free ports; its stderr lines arrive on `log`.
struct Server {
    child: Child,
    grpc: String,
    metrics: String,
    log: mpsc::Receiver<String>,
    lines: Vec<String>,
}

impl Server {
    fn start() -> Server {
        let mut child = Command::new(env!("CARGO_BIN_EXE_tofwave"))
            .args(["serve", "--listen", "127.0.0.1:0", "--metrics", "127.0.0.1:0", "--token", TOKEN])
            .env_remove("TOFWAVE_TOKEN")
            .env_remove("TOFWAVE_READ_TOKEN")
            .env("RUST_LOG", "info")
            .stderr(Stdio::piped())
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        let stderr = child.stderr.take().unwrap();
        let (tx, log) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut s = Server { child, grpc: String::new(), metrics: String::new(), log, lines: Vec::new() };
        s.grpc = s.wait_for("serving gRPC on ").trim().to_string();
        let m = s.wait_for("serving Prometheus metrics on http://");
        s.metrics = m.trim_end_matches("/metrics").to_string();
        s
    }

    /// Waits (10 s at most) for a line containing `marker`; returns what follows it.
    fn wait_for(&mut self, marker: &str) -> String {
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if let Some(l) = self.lines.iter().find(|l| l.contains(marker)) {
                return l.split_once(marker).unwrap().1.to_string();
            }
            let left = deadline.saturating_duration_since(Instant::now());
            match self.log.recv_timeout(left) {
                Ok(l) => self.lines.push(l),
                Err(_) => panic!("no {marker:?} in the server log:\n{}", self.lines.join("\n")),
            }
        }
    }

    fn scrape(&self) -> String {
        let mut s = std::net::TcpStream::connect(&self.metrics).unwrap();
        write!(s, "GET /metrics HTTP/1.1\r\nHost: {}\r\nConnection: close\r\n\r\n", self.metrics).unwrap();
        let mut text = String::new();
        s.read_to_string(&mut text).unwrap();
        text
    }

    /// SIGTERM, then the rest of the log.
    fn stop(mut self) -> Vec<String> {
        let pid = self.child.id().to_string();
        assert!(Command::new("kill").args(["-TERM", &pid]).status().unwrap().success());
        let status = self.child.wait().unwrap();
        assert!(status.success(), "server exit: {status:?}");
        while let Ok(l) = self.log.recv_timeout(Duration::from_secs(5)) {
            self.lines.push(l);
        }
        self.lines
    }
}

fn ctl(server: &Server, args: &[&str]) -> (i32, String, String) {
    let mut all = vec!["ctl", "--to", server.grpc.as_str(), "--token", TOKEN];
    all.extend_from_slice(args);
    let out = Command::new(env!("CARGO_BIN_EXE_tofwave")).args(&all).env_remove("TOFWAVE_TOKEN").output().unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8(out.stdout).unwrap(),
        String::from_utf8(out.stderr).unwrap(),
    )
}

#[test]
fn ctl_operates_a_running_server_replayed_to_without_http() {
    let server = Server::start();
    let input = replay_path("lecroy_3.trc");
    // `host:port` without http:// is accepted; the summary has the total and percentage.
    let (code, _, err) = tofwave(&[
        "replay", "--to", &server.grpc, "--token", TOKEN, "--input", input.to_str().unwrap(), "--rate", "max", "--sensor", "lidar-1",
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("20 of 20 frames acknowledged (100 %)"), "{err}");

    let (code, out, err) = ctl(&server, &["sensors"]);
    assert_eq!(code, 0, "{err}");
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines.len(), 1, "{out}");
    assert!(lines[0].starts_with("lidar-1\tframes_received=20 frames_processed=20 frames_rejected=0 reports=20 returns="), "{out}");

    let (code, out, err) = ctl(&server, &["status", "lidar-1"]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("frames_processed: 20\n") && out.contains("last_sequence: 19\n"), "{out}");

    let (code, out, err) = ctl(&server, &["noise", "lidar-1"]);
    assert_eq!(code, 0, "{err}");
    let sigma_mv: f64 = out.lines().find_map(|l| l.strip_prefix("sigma_mv: ")).expect("sigma line").parse().unwrap();
    // lecroy_3's noise is about 30 mV (README).
    assert!((10.0..60.0).contains(&sigma_mv), "{out}");

    // An unknown sensor: a clear error naming it, said once.
    let (code, _, err) = ctl(&server, &["noise", "nosuch"]);
    assert_eq!(code, 2);
    assert!(err.contains("no sensor \"nosuch\""), "{err}");
    assert_eq!(err.matches("nosuch").count(), 1, "{err}");

    // Without the token: refused.
    let out = Command::new(env!("CARGO_BIN_EXE_tofwave"))
        .args(["ctl", "--to", &server.grpc, "sensors"])
        .env_remove("TOFWAVE_TOKEN")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));

    // Scene: set a new pfa, read it back.
    let dir = tempfile::tempdir().unwrap();
    let (code, scene_text, err) = ctl(&server, &["scene", "lidar-1"]);
    assert_eq!(code, 0, "{err}");
    let mut doc: toml::Table = scene_text.parse().unwrap();
    doc["detector"]["pfa"] = toml::Value::Float(1e-4);
    let scene_file = dir.path().join("s.toml");
    std::fs::write(&scene_file, toml::to_string(&doc).unwrap()).unwrap();
    let (code, _, err) = ctl(&server, &["scene", "lidar-1", "--set", scene_file.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let (_, back, _) = ctl(&server, &["scene", "lidar-1"]);
    let back: toml::Table = back.parse().unwrap();
    assert_eq!(back["detector"]["pfa"].as_float(), Some(1e-4));

    // Calibration: measure one from a capture, apply it, read it back.
    let cal = dir.path().join("cal.toml");
    let (code, _, err) = tofwave(&[
        "calibrate", "--input", input.to_str().unwrap(), "--known-range-m", "1.0", "--out", cal.to_str().unwrap(), "--pfa", "1e-4",
    ]);
    assert_eq!(code, 0, "{err}");
    let cal_doc: toml::Table = std::fs::read_to_string(&cal).unwrap().parse().unwrap();
    let delay = cal_doc["calibration"]["delay_s"].as_float().unwrap();
    let (code, out, err) = ctl(&server, &["calibration", "lidar-1", "--set", cal.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let (_, out2, _) = ctl(&server, &["calibration", "lidar-1"]);
    assert_eq!(out, out2);
    let got: toml::Table = out2.parse().unwrap();
    assert_eq!(got["calibration"]["delay_s"].as_float(), Some(delay), "{out2}");

    // The metrics the dashboard queries that ingest produces are on /metrics.
    let text = server.scrape();
    for name in crate::deploy::dashboard_metrics() {
        let exported = text.lines().any(|l| !l.starts_with('#') && l.starts_with(name.as_str()));
        let needs_event = ["tofwave_frames_rejected_total", "tofwave_subscriber_lagged_reports_total", "tofwave_subscribers",
            "tofwave_frames_recorded_total", "tofwave_recording_failures_total", "tofwave_sequence_missing_total"];
        if !needs_event.contains(&name.as_str()) {
            assert!(exported, "{name} queried by the dashboard, not on /metrics after a replay");
        }
    }

    let lines = server.stop();
    let log = lines.join("\n");
    assert!(log.contains("shutting down: draining") && log.contains("tofwave: shut down"), "{log}");
    assert!(!log.contains('\u{1b}'), "ANSI escape in a non-terminal log:\n{log}");
}

#[test]
fn subscribe_warns_about_a_sensor_the_server_has_never_seen() {
    let server = Server::start();
    let mut child = Command::new(env!("CARGO_BIN_EXE_tofwave"))
        .args(["subscribe", "--from", &server.grpc, "--token", TOKEN, "--sensor", "capture"])
        .env_remove("TOFWAVE_READ_TOKEN")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut line = String::new();
    stderr.read_line(&mut line).unwrap();
    child.kill().unwrap();
    let _ = child.wait();
    assert!(line.contains("warning: sensor \"capture\" has sent no frames to this server yet (sensors seen: none)"), "{line}");
    server.stop();
}
