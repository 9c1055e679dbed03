//! `serve --dashboard ADDR`: a single-page dashboard in the browser, fed by
//! server-sent events (SSE) from the same report fan-out that gRPC
//! subscribers read.
//!
//! Why SSE: the dashboard only listens (one-way push), SSE is plain
//! HTTP/1.1 that a minimal responder like the metrics endpoint can serve
//! without a new dependency, and the browser's `EventSource` reconnects by
//! itself. WebSocket would need a handshake and framing for a return channel
//! nobody uses; gRPC-web would need tonic-web and a JS client library.
//!
//! Endpoints (`docs/dashboard.md` has the details):
//! - `GET /`, `/app.js`: the page and its script, embedded in the binary;
//! - `GET /events[?sensor=ID…]`: the SSE stream (`hello`, `report`,
//!   `waveform`, `sensors` once a second, `lagged`);
//! - `GET /api/sensors`: the sensor list as JSON.
//!
//! `/events` and `/api/*` need the read (or write) token when one is
//! configured, as `?token=` or `Authorization: Bearer`; the page and its
//! script are open (they hold no data).

mod snapshot;

pub use snapshot::{Decimated, MAX_POINTS, Snapshot, Snapshots, Watch, decimate};

use super::Shared;
use super::auth::{Access, Tokens};
use super::fanout::Published;
use super::metrics_http::Head;
use super::session::unix_ms;
use crate::telemetry;
use std::collections::{HashMap, HashSet};
use std::fmt::Write as _;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::broadcast;
use tokio_util::sync::CancellationToken;

/// The page, embedded: no CDN, no network at run time.
const INDEX_HTML: &str = include_str!("index.html");
/// The page's script (vanilla JS, canvas drawing).
const APP_JS: &str = include_str!("app.js");

/// Retained reports sent to a client when it connects, per sensor at most,
/// so the strip chart starts with the recent past.
const BACKLOG_PER_SENSOR: usize = 256;
/// Bytes gathered from the fan-out before one write to the client.
const WRITE_CHUNK_BYTES: usize = 256 * 1024;
/// Period of the `sensors` status event.
const STATUS_PERIOD: Duration = Duration::from_secs(1);
/// Default snapshot rate per sensor (`--dashboard-snapshots-per-s`).
pub const DEFAULT_SNAPSHOTS_PER_S: f64 = 5.0;

/// What the dashboard endpoint needs.
pub(crate) struct Dashboard {
    /// Sessions (status) and the report fan-out.
    pub(crate) shared: Arc<Shared>,
    /// Read token check, as gRPC subscribers have it.
    pub(crate) tokens: Tokens,
    /// Waveform snapshots from the sensors' pipelines.
    pub(crate) snapshots: Arc<Snapshots>,
}

/// Serves the dashboard on `listener` until `shutdown`; each connection on its own task.
pub(crate) async fn serve(
    listener: TcpListener,
    dash: Arc<Dashboard>,
    shutdown: CancellationToken,
) {
    tracing::info!(addr = ?listener.local_addr().ok(), "dashboard endpoint");
    super::metrics_http::accept_each(listener, "dashboard", shutdown, move |stream, stop| {
        let dash = dash.clone();
        async move { respond(stream, &dash, stop).await }
    })
    .await
}

/// A parsed request head: what the routes need.
#[derive(Debug, Default, PartialEq)]
struct Request {
    method: String,
    path: String,
    /// Query parameters in order, percent-decoded (repeats kept).
    query: Vec<(String, String)>,
    /// The bearer token of an `Authorization` header.
    bearer: Option<String>,
}

fn parse_request(head: &[u8]) -> Option<Request> {
    let head = std::str::from_utf8(head).ok()?;
    let mut lines = head.split("\r\n");
    let mut parts = lines.next()?.split_whitespace();
    let method = parts.next()?.to_string();
    let target = parts.next()?;
    let (path, query) = target.split_once('?').unwrap_or((target, ""));
    let query = query
        .split('&')
        .filter(|p| !p.is_empty())
        .map(|p| {
            let (k, v) = p.split_once('=').unwrap_or((p, ""));
            (percent_decode(k), percent_decode(v))
        })
        .collect();
    let bearer = lines
        .take_while(|l| !l.is_empty())
        .filter_map(|l| l.split_once(':'))
        .find(|(k, _)| k.trim().eq_ignore_ascii_case("authorization"))
        .and_then(|(_, v)| {
            let v = v.trim();
            v.strip_prefix("Bearer ")
                .or_else(|| v.strip_prefix("bearer "))
                .map(|t| t.trim().to_string())
        });
    Some(Request {
        method,
        path: path.to_string(),
        query,
        bearer,
    })
}

/// `%XX` and `+` decoding of a query component (invalid escapes stay as they are).
fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'+' => out.push(b' '),
            b'%' if i + 2 < b.len() => {
                let hex = |c: u8| (c as char).to_digit(16);
                match (hex(b[i + 1]), hex(b[i + 2])) {
                    (Some(h), Some(l)) => {
                        out.push((h * 16 + l) as u8);
                        i += 2;
                    }
                    _ => out.push(b'%'),
                }
            }
            c => out.push(c),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

async fn respond(
    mut stream: TcpStream,
    dash: &Dashboard,
    shutdown: CancellationToken,
) -> std::io::Result<()> {
    let mut buf = Vec::with_capacity(1024);
    match super::metrics_http::read_head(&mut stream, &mut buf).await? {
        Head::Complete => {}
        Head::Closed => return Ok(()),
        Head::TooLarge => {
            return reply(
                &mut stream,
                "431 Request Header Fields Too Large",
                "text/plain",
                "request head over 8 KiB\n",
            )
            .await;
        }
    }
    let Some(req) = parse_request(&buf) else {
        return reply(
            &mut stream,
            "400 Bad Request",
            "text/plain",
            "malformed request line\n",
        )
        .await;
    };
    if req.method != "GET" {
        return reply(
            &mut stream,
            "405 Method Not Allowed",
            "text/plain",
            "only GET is served\n",
        )
        .await;
    }
    match req.path.as_str() {
        "/" | "/index.html" => {
            reply(
                &mut stream,
                "200 OK",
                "text/html; charset=utf-8",
                INDEX_HTML,
            )
            .await
        }
        "/app.js" => {
            reply(
                &mut stream,
                "200 OK",
                "text/javascript; charset=utf-8",
                APP_JS,
            )
            .await
        }
        "/events" | "/api/sensors" => {
            let token = req
                .query
                .iter()
                .find(|(k, _)| k == "token")
                .map(|(_, v)| v.clone())
                .or(req.bearer.clone());
            if let Err(status) = dash.tokens.check(Access::Read, token.as_deref()) {
                let body = format!(
                    "{}: give the read token as ?token=TOKEN or \"Authorization: Bearer TOKEN\"\n",
                    status.message()
                );
                return reply(&mut stream, "401 Unauthorized", "text/plain", &body).await;
            }
            let sensors: HashSet<String> = req
                .query
                .iter()
                .filter(|(k, _)| k == "sensor")
                .map(|(_, v)| v.clone())
                .collect();
            if req.path == "/events" {
                events(stream, dash, sensors, shutdown).await
            } else {
                let body = sensors_json(dash, &sensors, &mut HashMap::new());
                reply(&mut stream, "200 OK", "application/json", &body).await
            }
        }
        _ => {
            reply(
                &mut stream,
                "404 Not Found",
                "text/plain",
                "served: /, /app.js, /events, /api/sensors\n",
            )
            .await
        }
    }
}

async fn reply(
    stream: &mut TcpStream,
    status: &str,
    ctype: &str,
    body: &str,
) -> std::io::Result<()> {
    let head = format!(
        "HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nCache-Control: no-store\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(head.as_bytes()).await?;
    stream.write_all(body.as_bytes()).await?;
    stream.shutdown().await
}

/// Appends one SSE event; `data` is one line (JSON never holds a raw newline).
fn push_event(buf: &mut String, event: &str, data: &str) {
    let _ = write!(buf, "event: {event}\ndata: {data}\n\n");
}

/// A report event: the subscriber's JSON line, wrapped with its publication time.
fn push_report(buf: &mut String, p: &Published) {
    let _ = write!(
        buf,
        "event: report\ndata: {{\"published_unix_ms\":{},\"report\":{}}}\n\n",
        p.published_unix_ms, p.json
    );
}

/// What one client last saw of a sensor, for frames/s.
struct Seen {
    processed: u64,
    at: Instant,
}

/// The sensor list with health counters (the `sensors` event and `/api/sensors`).
fn sensors_json(
    dash: &Dashboard,
    wanted: &HashSet<String>,
    seen: &mut HashMap<String, Seen>,
) -> String {
    let now = Instant::now();
    let now_ms = unix_ms();
    let list: Vec<serde_json::Value> = dash
        .shared
        .sessions
        .all()
        .iter()
        .filter(|s| wanted.is_empty() || wanted.contains(&s.sensor))
        .map(|s| {
            let st = &s.stats;
            let processed = st.frames_processed.load(Ordering::Relaxed);
            let fps = match seen.get(&s.sensor) {
                Some(p) if now > p.at => processed.saturating_sub(p.processed) as f64 / (now - p.at).as_secs_f64(),
                _ => 0.0,
            };
            seen.insert(s.sensor.clone(), Seen { processed, at: now });
            let last = st.last_processed_unix_ms.load(Ordering::Relaxed);
            serde_json::json!({
                "sensor": s.sensor,
                "frames_received": st.frames_received.load(Ordering::Relaxed),
                "frames_processed": processed,
                "frames_rejected": st.frames_rejected.load(Ordering::Relaxed),
                "reports": st.reports.load(Ordering::Relaxed),
                "returns": st.returns.load(Ordering::Relaxed),
                "sequence_gaps": st.sequence_gaps.load(Ordering::Relaxed),
                "queue_frames": s.queue_depth(),
                "frames_per_s": fps,
                "latency_ms": st.last_latency_us.load(Ordering::Relaxed) as f64 / 1e3,
                "idle_s": if last == 0 { serde_json::Value::Null } else { ((now_ms.saturating_sub(last)) as f64 / 1e3).into() },
                "scene": s.scene().name,
            })
        })
        .collect();
    serde_json::json!({ "server_unix_ms": now_ms, "dashboard_clients": dash.snapshots.watchers(), "sensors": list }).to_string()
}

/// Keeps the latest `per_sensor` reports of each sensor (the backlog comes
/// grouped by sensor, oldest first).
fn trim_backlog(backlog: Vec<Arc<Published>>, per_sensor: usize) -> Vec<Arc<Published>> {
    let mut count: HashMap<&str, usize> = HashMap::new();
    for p in &backlog {
        *count.entry(p.report.sensor.as_str()).or_default() += 1;
    }
    let mut skip: HashMap<String, usize> = count
        .into_iter()
        .map(|(s, n)| (s.to_string(), n.saturating_sub(per_sensor)))
        .collect();
    backlog
        .into_iter()
        .filter(|p| match skip.get_mut(&p.report.sensor) {
            Some(n) if *n > 0 => {
                *n -= 1;
                false
            }
            _ => true,
        })
        .collect()
}

/// One dashboard client's event stream, until it disconnects or the server shuts down.
async fn events(
    stream: TcpStream,
    dash: &Dashboard,
    sensors: HashSet<String>,
    shutdown: CancellationToken,
) -> std::io::Result<()> {
    let (mut rd, mut wr) = stream.into_split();
    let wanted = |s: &str| sensors.is_empty() || sensors.contains(s);
    let Some(sub) = dash.shared.hub.subscribe(Some(0), wanted) else {
        let mut s = rd.reunite(wr).expect("halves of one stream");
        return reply(
            &mut s,
            "503 Service Unavailable",
            "text/plain",
            "server is shutting down\n",
        )
        .await;
    };
    let (mut watch, latest) = dash.snapshots.watch();
    let _counted = ClientGauge::new();
    wr.write_all(
        b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\n\
          Connection: close\r\nX-Accel-Buffering: no\r\n\r\nretry: 1000\n\n",
    )
    .await?;
    let mut buf = String::new();
    let mut seen = HashMap::new();
    push_event(
        &mut buf,
        "hello",
        &serde_json::json!({
            "version": env!("CARGO_PKG_VERSION"),
            "sensors": sensors.iter().collect::<Vec<_>>(),
            "snapshot_max_points": MAX_POINTS,
        })
        .to_string(),
    );
    push_event(
        &mut buf,
        "sensors",
        &sensors_json(dash, &sensors, &mut seen),
    );
    for p in trim_backlog(sub.backlog, BACKLOG_PER_SENSOR) {
        push_report(&mut buf, &p);
    }
    for s in latest.iter().filter(|s| wanted(&s.sensor)) {
        push_event(&mut buf, "waveform", &s.json);
    }
    let mut live = sub.live;
    let mut tick =
        tokio::time::interval_at(tokio::time::Instant::now() + STATUS_PERIOD, STATUS_PERIOD);
    let mut skipped_total = 0u64;
    let mut scratch = [0u8; 256];
    loop {
        if !buf.is_empty() {
            tokio::select! {
                w = wr.write_all(buf.as_bytes()) => w?,
                _ = shutdown.cancelled() => return Ok(()),
            }
            buf.clear();
        }
        tokio::select! {
            _ = shutdown.cancelled() => return Ok(()),
            // The browser closed the connection (or sent something; ignored).
            r = rd.read(&mut scratch) => if matches!(r, Ok(0) | Err(_)) { return Ok(()) },
            r = live.recv() => {
                let mut next = Some(r);
                // Everything already waiting goes out in one write.
                while let Some(r) = next.take() {
                    match r {
                        Ok(p) => if wanted(&p.report.sensor) { push_report(&mut buf, &p) },
                        Err(broadcast::error::RecvError::Lagged(n)) => {
                            skipped_total += n;
                            telemetry::subscriber_lagged(n);
                            push_event(&mut buf, "lagged", &format!("{{\"skipped\":{n},\"skipped_total\":{skipped_total}}}"));
                        }
                        Err(broadcast::error::RecvError::Closed) => {
                            // Shutdown drained the fan-out: send what is left and end.
                            push_event(&mut buf, "closed", "{}");
                            wr.write_all(buf.as_bytes()).await?;
                            return Ok(());
                        }
                    }
                    if buf.len() < WRITE_CHUNK_BYTES {
                        next = match live.try_recv() {
                            Err(broadcast::error::TryRecvError::Empty) => None,
                            Err(broadcast::error::TryRecvError::Lagged(n)) => Some(Err(broadcast::error::RecvError::Lagged(n))),
                            Err(broadcast::error::TryRecvError::Closed) => Some(Err(broadcast::error::RecvError::Closed)),
                            Ok(p) => Some(Ok(p)),
                        };
                    }
                }
            }
            r = watch.live.recv() => match r {
                Ok(s) if wanted(&s.sensor) => push_event(&mut buf, "waveform", &s.json),
                // Skipped snapshots are superseded by the next ones anyway.
                Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => {}
                Err(broadcast::error::RecvError::Closed) => return Ok(()),
            },
            _ = tick.tick() => push_event(&mut buf, "sensors", &sensors_json(dash, &sensors, &mut seen)),
        }
    }
}

/// Counts an open event stream in the `tofwave_dashboard_clients` gauge.
struct ClientGauge;

impl ClientGauge {
    fn new() -> ClientGauge {
        telemetry::dashboard_clients_changed(1.0);
        ClientGauge
    }
}

impl Drop for ClientGauge {
    fn drop(&mut self) {
        telemetry::dashboard_clients_changed(-1.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn request_head_parses() {
        let r = parse_request(
            b"GET /events?sensor=lidar%20a&sensor=b+c&token=t%2Bk HTTP/1.1\r\nHost: x\r\nauthorization: Bearer  abc \r\n\r\n",
        )
        .unwrap();
        assert_eq!(r.method, "GET");
        assert_eq!(r.path, "/events");
        assert_eq!(
            r.query,
            vec![
                ("sensor".into(), "lidar a".into()),
                ("sensor".into(), "b c".into()),
                ("token".into(), "t+k".into())
            ]
        );
        assert_eq!(r.bearer.as_deref(), Some("abc"));
        assert_eq!(percent_decode("100%"), "100%");
        assert_eq!(percent_decode("%zz%41"), "%zzA");
        assert!(parse_request(b"\r\n\r\n").is_none());
    }

    #[test]
    fn backlog_keeps_the_latest_per_sensor() {
        let p = |s: &str, seq| {
            Arc::new(Published {
                report: crate::frame::Report {
                    sensor: s.into(),
                    seq_first: seq,
                    ..Default::default()
                },
                json: String::new(),
                published_unix_ms: 0,
                wire: None,
            })
        };
        let backlog = vec![p("a", 0), p("a", 1), p("a", 2), p("b", 0)];
        let kept: Vec<_> = trim_backlog(backlog, 2)
            .iter()
            .map(|p| (p.report.sensor.clone(), p.report.seq_first))
            .collect();
        assert_eq!(
            kept,
            vec![("a".into(), 1), ("a".into(), 2), ("b".into(), 0)]
        );
    }
}
