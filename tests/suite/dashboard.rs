//! The browser dashboard (`serve --dashboard`), in a real browser: the
//! server binary on free ports, a shipped capture replayed into it, and
//! headless Chromium driven over chromedriver's WebDriver HTTP API. The page
//! writes what it drew into data attributes of `#dash`, which the test reads;
//! a screenshot goes to `target/test-artefacts/dashboard.png`.
//!
//! Chromium and chromedriver must be installed (Debian: `apt-get install
//! chromium chromium-driver`; `.ci/run` does it): without them the test fails
//! and says so rather than skipping.

use super::common::tofwave;
use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A child process killed when the test ends, however it ends.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `tofwave serve` on free ports: (process, gRPC URL, dashboard URL).
fn serve(extra: &[&str]) -> (Killed, String, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_tofwave"))
        .args([
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--dashboard",
            "127.0.0.1:0",
        ])
        .args(extra)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("tofwave serve starts");
    let stderr = child.stderr.take().unwrap();
    let child = Killed(child);
    let mut lines = BufReader::new(stderr).lines();
    let (mut grpc, mut dash) = (None, None);
    while grpc.is_none() || dash.is_none() {
        let line = lines
            .next()
            .expect("serve announces its addresses before anything else")
            .unwrap();
        if let Some(a) = line.strip_prefix("tofwave: serving gRPC on ") {
            grpc = Some(format!("http://{}", a.trim()));
        }
        if let Some(a) = line.strip_prefix("tofwave: dashboard on ") {
            dash = Some(a.trim().to_string());
        }
    }
    // Keep draining the log so the server never blocks on a full pipe.
    std::thread::spawn(move || for _ in lines {});
    (child, grpc.unwrap(), dash.unwrap())
}

/// One HTTP/1.1 exchange on a fresh connection: (status, body).
fn http(
    addr: &str,
    method: &str,
    path: &str,
    body: Option<&Value>,
    headers: &[&str],
) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap_or_else(|e| panic!("connect {addr}: {e}"));
    s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for h in headers {
        head.push_str(h);
        head.push_str("\r\n");
    }
    if method != "GET" {
        head.push_str(&format!(
            "Content-Type: application/json\r\nContent-Length: {}\r\n",
            body.len()
        ));
    }
    head.push_str("\r\n");
    s.write_all(head.as_bytes()).unwrap();
    s.write_all(body.as_bytes()).unwrap();
    // Read the head, then the body by its length (chromedriver keeps the
    // connection open after its reply), by chunks, or to the end.
    let mut raw = Vec::new();
    let mut buf = [0u8; 16384];
    let split = loop {
        if let Some(p) = raw.windows(4).position(|w| w == b"\r\n\r\n") {
            break p;
        }
        let n = s.read(&mut buf).unwrap();
        assert!(n > 0, "{addr} closed before the response head");
        raw.extend_from_slice(&buf[..n]);
    };
    let head = String::from_utf8_lossy(&raw[..split]).to_ascii_lowercase();
    let mut body = raw[split + 4..].to_vec();
    let length = head
        .lines()
        .find_map(|l| l.strip_prefix("content-length:"))
        .map(|v| v.trim().parse::<usize>().unwrap());
    if let Some(len) = length {
        while body.len() < len {
            let n = s.read(&mut buf).unwrap();
            assert!(n > 0, "{addr} closed inside the body");
            body.extend_from_slice(&buf[..n]);
        }
    } else {
        s.read_to_end(&mut body).unwrap();
        if head.contains("transfer-encoding: chunked") {
            body = dechunk(&body);
        }
    }
    let status = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    (status, String::from_utf8(body).unwrap())
}

fn dechunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let eol = b
            .windows(2)
            .position(|w| w == b"\r\n")
            .expect("chunk size line");
        let size_hex = String::from_utf8_lossy(&b[..eol]);
        let size = usize::from_str_radix(size_hex.split(';').next().unwrap().trim(), 16).unwrap();
        if size == 0 {
            return out;
        }
        out.extend_from_slice(&b[eol + 2..eol + 2 + size]);
        b = &b[eol + 2 + size + 2..];
    }
}

fn base64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    };
    let bytes: Vec<u8> = s
        .bytes()
        .filter(|c| !c.is_ascii_whitespace() && *c != b'=')
        .collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for q in bytes.chunks(4) {
        let v: Vec<u32> = q.iter().map(|&c| val(c) as u32).collect();
        let n = v
            .iter()
            .enumerate()
            .fold(0u32, |acc, (i, x)| acc | (x << (18 - 6 * i)));
        out.extend_from_slice(&n.to_be_bytes()[1..q.len()]);
    }
    out
}

/// A tool on PATH, or a failure that says how to install it.
fn require(tool: &str) -> String {
    let found = std::env::var_os("PATH").and_then(|p| {
        std::env::split_paths(&p)
            .map(|d| d.join(tool))
            .find(|f| f.is_file())
    });
    match found {
        Some(p) => p.display().to_string(),
        None => panic!(
            "the dashboard's browser test needs `{tool}` on PATH: install Chromium and its driver \
             (Debian/Ubuntu: `apt-get install -y chromium chromium-driver`; `.ci/run` does this)"
        ),
    }
}

/// A headless Chromium session behind chromedriver.
struct Browser {
    /// chromedriver's address.
    driver: String,
    /// WebDriver session id.
    session: String,
    /// Keeps chromedriver alive.
    _process: Killed,
}

impl Browser {
    fn start() -> Browser {
        let chromium = require("chromium");
        let chromedriver = require("chromedriver");
        let port = TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let process = Killed(
            Command::new(chromedriver)
                .arg(format!("--port={port}"))
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .expect("chromedriver starts"),
        );
        let driver = format!("127.0.0.1:{port}");
        let t0 = Instant::now();
        while TcpStream::connect(&driver).is_err() {
            assert!(
                t0.elapsed() < Duration::from_secs(20),
                "chromedriver did not listen on {driver}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {"binary": chromium, "args": [
                "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1400,1400", "--force-device-scale-factor=1"]}}}});
        let (status, body) = http(&driver, "POST", "/session", Some(&caps), &[]);
        assert_eq!(status, 200, "new WebDriver session: {body}");
        let v: Value = serde_json::from_str(&body).unwrap();
        let session = v["value"]["sessionId"]
            .as_str()
            .expect("session id")
            .to_string();
        Browser {
            driver,
            session,
            _process: process,
        }
    }

    fn call(&self, method: &str, what: &str, body: Option<Value>) -> Value {
        let path = format!("/session/{}/{what}", self.session);
        let (status, text) = http(&self.driver, method, &path, body.as_ref(), &[]);
        assert_eq!(status, 200, "WebDriver {method} {what}: {text}");
        serde_json::from_str::<Value>(&text).unwrap()["value"].clone()
    }

    fn script(&self, js: &str) -> Value {
        self.call(
            "POST",
            "execute/sync",
            Some(json!({"script": js, "args": []})),
        )
    }

    /// `#dash`'s data attributes.
    fn dash(&self) -> Value {
        self.script("return Object.assign({}, document.getElementById('dash').dataset);")
    }

    /// Polls `#dash` until `done` holds; fails with the last state after `limit`.
    fn wait_for(&self, limit: Duration, what: &str, done: impl Fn(&Value) -> bool) -> Value {
        let t0 = Instant::now();
        loop {
            let d = self.dash();
            if done(&d) {
                return d;
            }
            assert!(
                t0.elapsed() < limit,
                "{what} within {limit:?}; the page shows {d}"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = http(
            &self.driver,
            "DELETE",
            &format!("/session/{}", self.session),
            None,
            &[],
        );
    }
}

fn num(v: &Value, key: &str) -> f64 {
    v[key]
        .as_str()
        .and_then(|s| s.parse().ok())
        .unwrap_or(f64::NAN)
}

fn artefacts() -> std::path::PathBuf {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("target"));
    let dir = target.join("test-artefacts");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn browser_draws_replayed_returns_and_waveform() {
    let capture = super::common::replay_path("lecroy_3.trc");
    let capture = capture.to_str().unwrap();
    // What the pipeline reports for this capture, offline: the page must show the same.
    let (rc, expected, err) = tofwave(&["process", "--input", capture]);
    assert_eq!(rc, 0, "{err}");
    let expected_returns: usize = expected
        .iter()
        .map(|r| r["returns"].as_array().unwrap().len())
        .sum();
    assert!(expected_returns > 0, "the capture has returns to draw");

    let (_server, grpc, dash_url) = serve(&[]);
    let browser = Browser::start();
    browser.call("POST", "url", Some(json!({"url": dash_url})));
    browser.wait_for(
        Duration::from_secs(15),
        "the page connects to /events",
        |d| d["connected"] == "1",
    );

    let out = Command::new(env!("CARGO_BIN_EXE_tofwave"))
        .args([
            "replay", "--to", &grpc, "--input", capture, "--rate", "max", "--sensor", "lidar-a",
            "--quiet",
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "replay: {}",
        String::from_utf8_lossy(&out.stderr)
    );

    let d = browser.wait_for(
        Duration::from_secs(10),
        "every report, its returns and a waveform drawn",
        |d| {
            num(d, "reports") == expected.len() as f64
                && num(d, "returnsPlotted") == expected_returns as f64
                && d["waveformSeq"].as_str().is_some_and(|s| !s.is_empty())
                && d["health"]
                    .as_str()
                    .is_some_and(|h| h == "ok" || h == "warn")
        },
    );
    assert_eq!(d["sensor"], "lidar-a");
    // The waveform is one of the replayed reports, with its returns marked.
    let seq: u64 = d["waveformSeq"].as_str().unwrap().parse().unwrap();
    let report = expected
        .iter()
        .find(|r| r["seq_last"] == seq)
        .unwrap_or_else(|| panic!("waveform of report {seq}, which process did not make"));
    assert_eq!(
        num(&d, "waveformReturns"),
        report["returns"].as_array().unwrap().len() as f64,
        "returns marked on the waveform of report {seq}"
    );
    let points = num(&d, "waveformPoints");
    assert!(
        points > 100.0 && points <= 2.0 * 1000.0,
        "{points} waveform points (≤ 1000 per trace)"
    );
    // Returns reach the screen within 1 s of their reports (same clock: one machine).
    let delay = num(&d, "maxDelayMs");
    assert!(
        (0.0..1000.0).contains(&delay),
        "report-to-screen delay {delay} ms"
    );
    let png = base64_decode(browser.call("GET", "screenshot", None).as_str().unwrap());
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n", "screenshot is a PNG");
    let path = artefacts().join("dashboard.png");
    std::fs::write(&path, &png).unwrap();
    eprintln!("dashboard screenshot: {}", path.display());
    // The strip chart is drawn, not just counted: coloured (SNR) pixels inside its plot box.
    let coloured = browser.script(
        "const c = document.getElementById('strip'); const g = c.getContext('2d');
         const dpr = c.width / c.clientWidth;
         const img = g.getImageData(56 * dpr, 0, (c.clientWidth - 56 - 70) * dpr, c.height).data;
         let n = 0;
         for (let i = 0; i < img.length; i += 4) {
           const mx = Math.max(img[i], img[i+1], img[i+2]), mn = Math.min(img[i], img[i+1], img[i+2]);
           if (img[i+3] > 0 && mx - mn > 60) n++;
         }
         return n;",
    );
    let coloured = coloured.as_f64().unwrap();
    assert!(
        coloured >= 3.0 * expected_returns as f64,
        "{coloured} SNR-coloured pixels on the strip chart for {expected_returns} returns"
    );
}

#[test]
fn dashboard_data_needs_the_read_token() {
    let (_server, _grpc, dash_url) = serve(&["--read-token", "r3ad", "--token", "wr1te"]);
    let addr = dash_url.trim_start_matches("http://").trim_end_matches('/');
    // The page itself holds no data and is open.
    assert_eq!(http(addr, "GET", "/", None, &[]).0, 200);
    assert_eq!(http(addr, "GET", "/app.js", None, &[]).0, 200);
    let (status, body) = http(addr, "GET", "/api/sensors", None, &[]);
    assert_eq!(status, 401);
    assert!(
        body.contains("?token="),
        "the refusal says how to pass the token: {body}"
    );
    assert_eq!(
        http(addr, "GET", "/api/sensors?token=r3a", None, &[]).0,
        401
    );
    assert_eq!(http(addr, "GET", "/events?token=nope", None, &[]).0, 401);
    for ok in [
        http(addr, "GET", "/api/sensors?token=r3ad", None, &[]),
        http(addr, "GET", "/api/sensors?token=wr1te", None, &[]),
        http(
            addr,
            "GET",
            "/api/sensors",
            None,
            &["Authorization: Bearer r3ad"],
        ),
    ] {
        assert_eq!(ok.0, 200, "{}", ok.1);
        let v: Value = serde_json::from_str(&ok.1).unwrap();
        assert!(v["sensors"].is_array());
    }
    assert_eq!(http(addr, "GET", "/nothing", None, &[]).0, 404);
    assert_eq!(
        http(addr, "POST", "/events?token=r3ad", Some(&json!({})), &[]).0,
        405
    );
}

/// `tofwave bench`'s dashboard-cost row runs end to end (tiny: one trial per arm).
#[test]
fn bench_measures_ingest_with_and_without_the_dashboard() {
    let scene = tofwave::bench::reference_scene();
    let c = tofwave::bench::measure_dashboard_cost(&scene, 20.0, 128, 1).unwrap();
    assert_eq!(c.sensors, 4);
    assert_eq!((c.without_frames_per_s.len(), c.with_frames_per_s.len()), (1, 1));
    assert!(c.ratio().is_finite() && c.ratio() > 0.0, "{c:?}");
    // The dashboard client saw data, so the "with" trial measured something.
    assert!(c.waveforms > 0 && c.reports > 0, "{c:?}");
    assert!(c.check_row().contains("dashboard open on 4 sensors"));
}
