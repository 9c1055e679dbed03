//! End-to-end service throughput: a load generator pushes simulated frames as
//! fast as the server takes them to a server on loopback, while a subscriber
//! times each report against the moment its frame was sent.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::net::TcpListener;
use tokio::sync::{mpsc, oneshot};
use tokio_stream::StreamExt;
use tokio_stream::wrappers::ReceiverStream;

use super::BenchError;
use super::grid::reference_frames;
use crate::scene::Scene;
use crate::service::client::{self, ClientOptions};
use crate::service::{ServerConfig, run};
use crate::wire::frame_to_proto;
use crate::wire::proto::{self, report_event::Event};

/// Frames per `FrameBatch` message of the load generator.
const BATCH_FRAMES: usize = 32;

/// Loopback gRPC throughput.
#[derive(Debug, Clone, PartialEq)]
pub struct ServiceThroughput {
    /// Frames pushed.
    pub frames: usize,
    /// Samples per channel per frame.
    pub samples_per_frame: usize,
    /// Frames per `FrameBatch`.
    pub batch_frames: usize,
    /// Samples (all channels) acknowledged by ingest per second, from the first send to the last ack.
    pub ingest_samples_per_s: f64,
    /// Samples (all channels) whose report reached the subscriber per second,
    /// from the first send to the last report.
    pub processed_samples_per_s: f64,
    /// Reports (= frames, N = 1) per second reaching the subscriber.
    pub frames_per_s: f64,
    /// Median send-to-report latency, s.
    pub latency_p50_s: f64,
    /// 99th-percentile send-to-report latency, s.
    pub latency_p99_s: f64,
    /// Send-to-report latency at offered loads below the flood's rate.
    pub latency_curve: Vec<LatencyPoint>,
}

/// Latency at one offered load: frames sent one per message on a fixed
/// schedule (open loop), each timed from its scheduled send time, so a
/// sender that falls behind shows as latency instead of hiding it.
#[derive(Debug, Clone, PartialEq)]
pub struct LatencyPoint {
    /// Offered load as a fraction of the flood's frames/s.
    pub load: f64,
    /// Offered frames/s.
    pub offered_frames_per_s: f64,
    /// Frames timed (after the warm-up).
    pub frames: usize,
    /// Latency percentiles 50, 99 and 99.9, s.
    pub p50_s: f64,
    /// 99th percentile, s.
    pub p99_s: f64,
    /// 99.9th percentile, s.
    pub p999_s: f64,
}

/// Offered loads of the latency curve, as fractions of the flood's rate.
pub const LATENCY_LOADS: [f64; 4] = [0.25, 0.5, 0.75, 0.9];
/// Frames sent per load before timing starts (a fresh sensor's start-up).
pub const LATENCY_WARMUP_FRAMES: usize = 200;

/// Pushes `frames` reference frames at `snr_db` (as sensor "bench", scene `scene`) through a server on
/// 127.0.0.1 and measures ingest, processing and latency.
pub fn measure_service(
    scene: &Scene,
    snr_db: f64,
    frames: usize,
) -> Result<ServiceThroughput, BenchError> {
    let err = |e: &dyn std::fmt::Display| BenchError::Service(e.to_string());
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| err(&e))?;
    // The load generator pre-encodes its frames (a digitiser hands over ready buffers).
    let count = frames.max(1);
    let (domain, _) = reference_frames(scene, snr_db, 31337, count.min(2048));
    let samples_per_frame = domain.first().map_or(0, |f| f.len());
    let channels = domain.first().map_or(0, |f| f.channels.len());
    let wire: Vec<proto::Frame> = (0..count)
        .map(|i| {
            let mut f = domain[i % domain.len()].clone();
            f.sensor_id = "bench".into();
            f.sequence = i as u64;
            frame_to_proto(&f)
        })
        .collect();
    drop(domain);
    let wire_again: Vec<proto::Frame> = wire.iter().take(2048).cloned().collect();
    let scene = scene.clone();
    rt.block_on(async move {
        let listener = TcpListener::bind("127.0.0.1:0")
            .await
            .map_err(|e| err(&e))?;
        let url = format!("http://{}", listener.local_addr().map_err(|e| err(&e))?);
        let config = ServerConfig {
            scene,
            queue_frames: 256,
            subscriber_buffer: count + 16,
            history_reports: 16,
            ..ServerConfig::default()
        };
        let (stop_tx, stop_rx) = oneshot::channel::<()>();
        let server = tokio::spawn(run(listener, config, async move {
            let _ = stop_rx.await;
        }));
        let mut clients = client::connect(&url, &ClientOptions::default())
            .await
            .map_err(|e| err(&e))?;
        let mut events =
            client::subscribe(&mut clients.reports, proto::SubscribeRequest::default())
                .await
                .map_err(|e| err(&e))?;

        let sent_at: Arc<Mutex<Vec<Option<Instant>>>> = Arc::new(Mutex::new(vec![None; count]));
        let collector = tokio::spawn(async move {
            let mut got: Vec<(u64, Instant)> = Vec::with_capacity(count);
            while got.len() < count {
                match tokio::time::timeout(Duration::from_secs(60), events.next()).await {
                    Ok(Some(Ok(ev))) => {
                        if let Some(Event::Report(r)) = ev.event {
                            got.push((r.seq_last, Instant::now()));
                        }
                    }
                    _ => break,
                }
            }
            got
        });

        let (tx, rx) = mpsc::channel::<proto::FrameBatch>(4);
        let t0 = Instant::now();
        let stamps = sent_at.clone();
        let producer = tokio::spawn(async move {
            let mut it = wire.into_iter().enumerate().peekable();
            while it.peek().is_some() {
                let mut batch = proto::FrameBatch::default();
                let mut seqs = Vec::with_capacity(BATCH_FRAMES);
                for (i, f) in it.by_ref().take(BATCH_FRAMES) {
                    seqs.push(i);
                    batch.frames.push(f);
                }
                if tx.send(batch).await.is_err() {
                    break;
                }
                let now = Instant::now();
                let mut s = stamps.lock().expect("no panics while holding the lock");
                for i in seqs {
                    s[i] = Some(now);
                }
            }
        });
        let summary = client::push(&mut clients.ingest, ReceiverStream::new(rx), |_| {})
            .await
            .map_err(|e| err(&e))?;
        let ingest_s = t0.elapsed().as_secs_f64();
        let _ = producer.await;
        let got = collector.await.map_err(|e| err(&e))?;
        let last_report_s = got
            .last()
            .map_or(ingest_s, |(_, t)| t.duration_since(t0).as_secs_f64());
        if got.len() < count {
            let _ = stop_tx.send(());
            let _ = tokio::time::timeout(Duration::from_secs(30), server).await;
            return Err(BenchError::Service(format!(
                "{} of {count} reports arrived (ingest acknowledged {summary:?})",
                got.len()
            )));
        }
        let stamps = sent_at.lock().expect("no panics while holding the lock");
        let mut lat: Vec<f64> = got
            .iter()
            .filter_map(|(seq, t)| {
                stamps
                    .get(*seq as usize)
                    .copied()
                    .flatten()
                    .map(|s| t.saturating_duration_since(s).as_secs_f64())
            })
            .collect();
        lat.sort_by(f64::total_cmp);
        let q = |p: f64| {
            lat.get(((lat.len() as f64 - 1.0) * p).round() as usize)
                .copied()
                .unwrap_or(f64::NAN)
        };
        let total_samples = (count * samples_per_frame * channels) as f64;
        let flood_fps = count as f64 / last_report_s;
        let mut latency_curve = Vec::new();
        for (k, load) in LATENCY_LOADS.iter().enumerate() {
            let sensor = format!("latency-{k}");
            let point = latency_at(&url, &wire_again, &sensor, *load, flood_fps).await?;
            latency_curve.push(point);
        }
        let _ = stop_tx.send(());
        let _ = tokio::time::timeout(Duration::from_secs(30), server).await;
        Ok(ServiceThroughput {
            frames: count,
            samples_per_frame,
            batch_frames: BATCH_FRAMES,
            ingest_samples_per_s: total_samples / ingest_s,
            processed_samples_per_s: total_samples / last_report_s,
            frames_per_s: count as f64 / last_report_s,
            latency_p50_s: q(0.5),
            latency_p99_s: q(0.99),
            latency_curve,
        })
    })
}

/// Sends `wire` (as `sensor`) one frame per message at `load` × `flood_fps`
/// on a fixed schedule and times each report from its frame's scheduled send.
async fn latency_at(url: &str, wire: &[proto::Frame], sensor: &str, load: f64, flood_fps: f64) -> Result<LatencyPoint, BenchError> {
    let err = |e: &dyn std::fmt::Display| BenchError::Service(e.to_string());
    let rate = (load * flood_fps).max(1.0);
    // About a second of frames at this rate, at least 1000 timed.
    let count = (rate as usize).max(1000) + LATENCY_WARMUP_FRAMES;
    let mut clients = client::connect(url, &ClientOptions::default()).await.map_err(|e| err(&e))?;
    let request = proto::SubscribeRequest { sensor_ids: vec![sensor.to_string()], ..Default::default() };
    let mut events = client::subscribe(&mut clients.reports, request).await.map_err(|e| err(&e))?;
    let frames: Vec<proto::Frame> = (0..count)
        .map(|i| proto::Frame { sensor_id: sensor.to_string(), sequence: i as u64, ..wire[i % wire.len()].clone() })
        .collect();
    let (tx, rx) = mpsc::channel::<proto::FrameBatch>(64);
    let t0 = tokio::time::Instant::now() + Duration::from_millis(20);
    let due = move |i: usize| t0 + Duration::from_secs_f64(i as f64 / rate);
    let producer = tokio::spawn(async move {
        for (i, f) in frames.into_iter().enumerate() {
            tokio::time::sleep_until(due(i)).await;
            if tx.send(proto::FrameBatch { frames: vec![f] }).await.is_err() {
                break;
            }
        }
    });
    let mut ingest = clients.ingest.clone();
    let pusher = tokio::spawn(async move { client::push(&mut ingest, ReceiverStream::new(rx), |_| {}).await });
    let mut lat = Vec::with_capacity(count);
    let mut got = 0usize;
    while got < count {
        match tokio::time::timeout(Duration::from_secs(60), events.next()).await {
            Ok(Some(Ok(ev))) => {
                if let Some(Event::Report(r)) = ev.event {
                    let now = tokio::time::Instant::now();
                    got += 1;
                    let i = r.seq_last as usize;
                    if i >= LATENCY_WARMUP_FRAMES {
                        lat.push(now.saturating_duration_since(due(i)).as_secs_f64());
                    }
                }
            }
            other => return Err(BenchError::Service(format!("latency at {load}: {got} of {count} reports arrived, then {other:?}"))),
        }
    }
    let _ = producer.await;
    let _ = pusher.await;
    lat.sort_by(f64::total_cmp);
    let q = |p: f64| lat.get(((lat.len() as f64 - 1.0) * p).round() as usize).copied().unwrap_or(f64::NAN);
    Ok(LatencyPoint { load, offered_frames_per_s: rate, frames: lat.len(), p50_s: q(0.5), p99_s: q(0.99), p999_s: q(0.999) })
}

/// Sensors pushing at once in the dashboard-cost measurement.
pub const DASHBOARD_SENSORS: usize = 4;

/// Ingest throughput of [`DASHBOARD_SENSORS`] sensors with and without a
/// dashboard client open on all of them, measured in one run on one server.
#[derive(Debug, Clone, PartialEq)]
pub struct DashboardCost {
    /// Sensors pushing concurrently (one gRPC connection each).
    pub sensors: usize,
    /// Frames per trial, all sensors together.
    pub frames_per_trial: usize,
    /// Samples per channel per frame.
    pub samples_per_frame: usize,
    /// Frames acknowledged per second in each trial without a dashboard client.
    pub without_frames_per_s: Vec<f64>,
    /// The same with a dashboard client reading `/events` for every sensor.
    pub with_frames_per_s: Vec<f64>,
    /// CPU time of this process (server, load generator and the dashboard
    /// client together) per frame in each trial without a dashboard, µs;
    /// empty where the platform does not say (`/proc/self/stat`).
    pub without_cpu_us_per_frame: Vec<f64>,
    /// The same with the dashboard open.
    pub with_cpu_us_per_frame: Vec<f64>,
    /// Waveform snapshots the dashboard client received, all "with" trials.
    pub waveforms: u64,
    /// Report events the dashboard client received, all "with" trials.
    pub reports: u64,
    /// Bytes of events the dashboard client received, all "with" trials.
    pub event_bytes: u64,
    /// Seconds spent in "with" trials.
    pub with_seconds: f64,
}

/// Median of `v` (NaN when empty); the bench's trial summaries share it.
pub(super) fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

impl DashboardCost {
    /// Median frames/s without a dashboard.
    pub fn without(&self) -> f64 {
        median(&self.without_frames_per_s)
    }
    /// Median frames/s with the dashboard open.
    pub fn with(&self) -> f64 {
        median(&self.with_frames_per_s)
    }
    /// Throughput with the dashboard over throughput without.
    pub fn ratio(&self) -> f64 {
        self.with() / self.without()
    }
    /// Median CPU time per frame with over without (NaN when not measured):
    /// unlike throughput, it does not move with other processes' load.
    pub fn cpu_ratio(&self) -> f64 {
        median(&self.with_cpu_us_per_frame) / median(&self.without_cpu_us_per_frame)
    }
}

/// CPU time (user + system) this process has used, s; `None` off Linux.
fn process_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    stat_cpu_s(&stat).map(|(_, s)| s)
}

/// /proc reports CPU times in USER_HZ ticks: 100 on every Linux
/// architecture tofwave builds for.
pub(super) const USER_HZ: f64 = 100.0;

/// A /proc `stat` line's command (thread) name and CPU time (user +
/// system, s): the name is in parentheses (it may hold spaces and
/// parentheses itself), utime and stime are the 14th and 15th fields of
/// the line (the 12th and 13th after the name's ')').
pub(super) fn stat_cpu_s(stat: &str) -> Option<(&str, f64)> {
    let (open, close) = (stat.find('(')?, stat.rfind(')')?);
    let f: Vec<&str> = stat.get(close + 1..)?.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some((stat.get(open + 1..close)?, ticks / USER_HZ))
}

/// A dashboard client reading `/events` (every sensor) and counting what it gets.
struct DashboardClient {
    task: tokio::task::JoinHandle<()>,
    counts: Arc<Mutex<(u64, u64, u64)>>,
}

impl DashboardClient {
    async fn open(addr: std::net::SocketAddr) -> Result<DashboardClient, String> {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let mut s = tokio::net::TcpStream::connect(addr).await.map_err(|e| e.to_string())?;
        s.write_all(format!("GET /events HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
            .await
            .map_err(|e| e.to_string())?;
        // Wait for the hello event: from then on the server counts this client.
        let mut seen = Vec::new();
        let mut chunk = vec![0u8; 64 * 1024];
        while !seen.windows(12).any(|w| w == b"event: hello") {
            let n = tokio::time::timeout(Duration::from_secs(10), s.read(&mut chunk))
                .await
                .map_err(|_| "no hello event from /events in 10 s".to_string())?
                .map_err(|e| e.to_string())?;
            if n == 0 {
                return Err(format!("/events closed: {}", String::from_utf8_lossy(&seen)));
            }
            seen.extend_from_slice(&chunk[..n]);
        }
        let counts = Arc::new(Mutex::new((0u64, 0u64, 0u64)));
        let c = counts.clone();
        let task = tokio::spawn(async move {
            // Markers may straddle two reads: keep the tail of the last one.
            let mut tail: Vec<u8> = Vec::new();
            loop {
                let n = match s.read(&mut chunk).await {
                    Ok(0) | Err(_) => return,
                    Ok(n) => n,
                };
                tail.extend_from_slice(&chunk[..n]);
                let count = |m: &[u8]| tail.windows(m.len()).filter(|w| *w == m).count() as u64;
                let (w, r) = (count(b"event: waveform\n"), count(b"event: report\n"));
                {
                    let mut g = c.lock().expect("no panics while holding the lock");
                    g.0 += w;
                    g.1 += r;
                    g.2 += n as u64;
                }
                let keep = tail.len().min(15);
                tail.drain(..tail.len() - keep);
            }
        });
        Ok(DashboardClient { task, counts })
    }

    fn close(self) -> (u64, u64, u64) {
        self.task.abort();
        *self.counts.lock().expect("no panics while holding the lock")
    }
}

/// Dashboard clients the server counts now (`/api/sensors`).
async fn dashboard_clients(addr: std::net::SocketAddr) -> Result<u64, String> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.map_err(|e| e.to_string())?;
    s.write_all(format!("GET /api/sensors HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .map_err(|e| e.to_string())?;
    let mut body = String::new();
    s.read_to_string(&mut body).await.map_err(|e| e.to_string())?;
    let json = body.split("\r\n\r\n").nth(1).unwrap_or("");
    let v: serde_json::Value = serde_json::from_str(json).map_err(|e| format!("{e}: {body}"))?;
    v["dashboard_clients"].as_u64().ok_or_else(|| format!("no dashboard_clients in {body}"))
}

/// Measures ingest throughput (frames acknowledged per second: an ack comes
/// after the frame was processed and its report published) of
/// [`DASHBOARD_SENSORS`] sensors pushing `frames_per_trial` frames between
/// them, alternately with no dashboard client and with one reading every
/// sensor's events (reports and waveform snapshots at the default rate), in
/// the order off, on, on, off, off, on (`trials` = 3 per arm), after one
/// warm-up trial. One server serves every trial.
pub fn measure_dashboard_cost(
    scene: &Scene,
    snr_db: f64,
    frames_per_trial: usize,
    trials: usize,
) -> Result<DashboardCost, BenchError> {
    let err = |e: &dyn std::fmt::Display| BenchError::Service(format!("dashboard cost: {e}"));
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| err(&e))?;
    let sensors = DASHBOARD_SENSORS;
    let per_sensor = (frames_per_trial / sensors).max(1);
    let (domain, _) = reference_frames(scene, snr_db, 4242, per_sensor.min(1024));
    let samples_per_frame = domain.first().map_or(0, |f| f.len());
    let scene = scene.clone();
    rt.block_on(async move {
        let listener = TcpListener::bind("127.0.0.1:0").await.map_err(|e| err(&e))?;
        let dash_listener = TcpListener::bind("127.0.0.1:0").await.map_err(|e| err(&e))?;
        let dash_addr = dash_listener.local_addr().map_err(|e| err(&e))?;
        let url = format!("http://{}", listener.local_addr().map_err(|e| err(&e))?);
        let config = ServerConfig {
            scene,
            queue_frames: 256,
            history_reports: 16,
            dashboard_listener: Some(dash_listener),
            ..ServerConfig::default()
        };
        let (stop_tx, stop_rx) = oneshot::channel::<()>();
        let server = tokio::spawn(run(listener, config, async move {
            let _ = stop_rx.await;
        }));
        let mut ingest = Vec::new();
        for _ in 0..sensors {
            ingest.push(
                client::connect(&url, &ClientOptions::default())
                    .await
                    .map_err(|e| err(&e))?
                    .ingest,
            );
        }
        // Pre-encoded frames per sensor; each trial continues the sequence numbers.
        let encode = |sensor: usize, trial: usize| -> Vec<proto::FrameBatch> {
            let mut batches = Vec::new();
            let mut batch = proto::FrameBatch::default();
            for i in 0..per_sensor {
                let mut f = domain[i % domain.len()].clone();
                f.sensor_id = format!("bench-{sensor}");
                f.sequence = (trial * per_sensor + i) as u64;
                batch.frames.push(frame_to_proto(&f));
                if batch.frames.len() == BATCH_FRAMES {
                    batches.push(std::mem::take(&mut batch));
                }
            }
            if !batch.frames.is_empty() {
                batches.push(batch);
            }
            batches
        };
        // Warm-up, then off, on, on, off, off, on, ...
        let plan: Vec<bool> = std::iter::once(false)
            .chain((0..trials * 2).map(|k| matches!(k % 4, 1 | 2)))
            .collect();
        let mut out = DashboardCost {
            sensors,
            frames_per_trial: per_sensor * sensors,
            samples_per_frame,
            without_frames_per_s: Vec::new(),
            with_frames_per_s: Vec::new(),
            without_cpu_us_per_frame: Vec::new(),
            with_cpu_us_per_frame: Vec::new(),
            waveforms: 0,
            reports: 0,
            event_bytes: 0,
            with_seconds: 0.0,
        };
        for (trial, &dashboard) in plan.iter().enumerate() {
            let work: Vec<Vec<proto::FrameBatch>> = (0..sensors).map(|s| encode(s, trial)).collect();
            let client = if dashboard {
                Some(DashboardClient::open(dash_addr).await.map_err(|e| err(&e))?)
            } else {
                // The last trial's client has gone: the server counts none.
                let t0 = Instant::now();
                while dashboard_clients(dash_addr).await.map_err(|e| err(&e))? > 0 {
                    if t0.elapsed() > Duration::from_secs(10) {
                        return Err(err(&"a closed dashboard client is still counted after 10 s"));
                    }
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
                None
            };
            let t0 = Instant::now();
            let cpu0 = process_cpu_s();
            let pushes: Vec<_> = work
                .into_iter()
                .zip(ingest.iter().cloned())
                .map(|(batches, mut c)| {
                    tokio::spawn(async move {
                        client::push(&mut c, tokio_stream::iter(batches), |_| {}).await
                    })
                })
                .collect();
            let mut accepted = 0;
            for p in pushes {
                let s = p.await.map_err(|e| err(&e))?.map_err(|e| err(&e))?;
                if s.rejected > 0 {
                    return Err(err(&format!("{} frames rejected", s.rejected)));
                }
                accepted += s.accepted;
            }
            let secs = t0.elapsed().as_secs_f64();
            let fps = accepted as f64 / secs;
            let cpu_us = match (cpu0, process_cpu_s()) {
                (Some(a), Some(b)) if accepted > 0 => Some((b - a) * 1e6 / accepted as f64),
                _ => None,
            };
            if trial == 0 {
                continue;
            }
            let cpu_list = if client.is_some() { &mut out.with_cpu_us_per_frame } else { &mut out.without_cpu_us_per_frame };
            cpu_list.extend(cpu_us);
            match client {
                Some(c) => {
                    let (w, r, b) = c.close();
                    if w == 0 || r == 0 {
                        return Err(err(&format!(
                            "the dashboard client received {w} waveforms and {r} reports: it measured nothing"
                        )));
                    }
                    out.waveforms += w;
                    out.reports += r;
                    out.event_bytes += b;
                    out.with_seconds += secs;
                    out.with_frames_per_s.push(fps);
                }
                None => out.without_frames_per_s.push(fps),
            }
        }
        let _ = stop_tx.send(());
        let _ = tokio::time::timeout(Duration::from_secs(30), server).await;
        Ok(out)
    })
}

impl DashboardCost {
    /// The check row (for report.md's table of checks).
    pub fn check_row(&self) -> String {
        let r = self.ratio();
        format!(
            "| ingest with the dashboard open on {} sensors ≥ 95 % of without | {:.0} frames/s with vs {:.0} without: **{:.1} %** | {} |",
            self.sensors,
            self.with(),
            self.without(),
            100.0 * r,
            if r >= 0.95 { "met" } else { "**not met**" }
        )
    }

    /// A Markdown section: set-up, every trial, and what the dashboard client received.
    pub fn markdown(&self) -> String {
        let list = |v: &[f64]| v.iter().map(|x| format!("{x:.0}")).collect::<Vec<_>>().join(", ");
        let per_sensor_s = self.with_seconds * self.sensors as f64;
        format!(
            "{} sensors push {} frames of {} samples (2 channels, i16) per trial between them, one gRPC \
             connection each, to one server on 127.0.0.1; throughput is frames acknowledged per second \
             (an ack follows processing and publication). Trials alternate without and with a dashboard \
             client reading `/events` for every sensor (reports, and waveform snapshots at the default \
             5 per sensor per second), in the order off, on, on, off, off, on after a warm-up.\n\n\
             | | frames/s (median) | trials |\n|---|---|---|\n\
             | without a dashboard | {:.0} | {} |\n\
             | with the dashboard open on {} sensors | {:.0} | {} |\n\n\
             Ratio with / without: **{:.3}**. The dashboard client received {} waveform snapshots \
             ({:.1} per sensor per second, counting the latest snapshot each connection starts with), \
             {} report events and {:.1} MB of events.\n\n\
             CPU time of the process (server, load generator and dashboard client) per frame, which \
             other processes' load does not move: {} µs without, {} µs with (per trial); ratio of the \
             medians with / without: **{:.3}**.\n",
            self.sensors,
            self.frames_per_trial,
            self.samples_per_frame,
            self.without(),
            list(&self.without_frames_per_s),
            self.sensors,
            self.with(),
            list(&self.with_frames_per_s),
            self.ratio(),
            self.waveforms,
            if per_sensor_s > 0.0 { self.waveforms as f64 / per_sensor_s } else { 0.0 },
            self.reports,
            self.event_bytes as f64 / 1e6,
            list(&self.without_cpu_us_per_frame),
            list(&self.with_cpu_us_per_frame),
            self.cpu_ratio()
        )
    }
}
