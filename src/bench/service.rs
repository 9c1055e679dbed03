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
}

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
        let _ = stop_tx.send(());
        let _ = tokio::time::timeout(Duration::from_secs(30), server).await;
        if got.len() < count {
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
        Ok(ServiceThroughput {
            frames: count,
            samples_per_frame,
            batch_frames: BATCH_FRAMES,
            ingest_samples_per_s: total_samples / ingest_s,
            processed_samples_per_s: total_samples / last_report_s,
            frames_per_s: count as f64 / last_report_s,
            latency_p50_s: q(0.5),
            latency_p99_s: q(0.99),
        })
    })
}
