//! `tofwave bench --cluster URL`: throughput of one node on the cluster path
//! (gRPC ingest → JetStream → owner's pipeline → reports stream → the node's
//! Subscribe) against the same node serving alone (`serve` without
//! `--cluster`), in trials alternating the two on this machine.
//!
//! Rates are steady-state: reports from the first to the last one reaching
//! the subscriber, divided by the time between them, so the cluster arm's
//! one-off start (the node noticing the new sensor and claiming it, up to a
//! poll period) is not counted as throughput. Every trial uses a fresh
//! sensor id (no history to replay) and the cluster arm forgets it afterwards.

use std::time::{Duration, Instant};

use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio_stream::wrappers::ReceiverStream;

use super::BenchError;
use super::grid::reference_frames;
use crate::scene::Scene;
use crate::service::client::{self, ClientOptions};
use crate::service::cluster::{Cluster, ClusterConfig};
use crate::service::{ServerConfig, run};
use crate::wire::frame_to_proto;
use super::service::median;
use crate::wire::proto::{self, report_event::Event};

/// Frames per `FrameBatch` of the load generator.
const BATCH_FRAMES: usize = 32;

/// Single-node against cluster-path throughput, measured in one run.
#[derive(Debug, Clone, PartialEq)]
pub struct ClusterCost {
    /// NATS URL of the cluster arm.
    pub url: String,
    /// Frames per trial (one sensor).
    pub frames_per_trial: usize,
    /// Samples per channel per frame.
    pub samples_per_frame: usize,
    /// Reports per second reaching the subscriber, single-node `serve`, per trial.
    pub single_frames_per_s: Vec<f64>,
    /// The same through the cluster path (one node joined to the cluster).
    pub cluster_frames_per_s: Vec<f64>,
    /// Seconds from the first frame sent to the first report, cluster arm, per trial
    /// (the new sensor is noticed and claimed in this time).
    pub cluster_first_report_s: Vec<f64>,
}

impl ClusterCost {
    /// Median cluster rate over median single-node rate.
    pub fn ratio(&self) -> f64 {
        median(&self.cluster_frames_per_s) / median(&self.single_frames_per_s)
    }

    /// The result as a Markdown table and a verdict line against the 70 % target.
    pub fn markdown(&self) -> String {
        let row = |name: &str, v: &[f64]| {
            let cells: Vec<String> = v.iter().map(|x| format!("{x:.0}")).collect();
            format!("| {name} | {} | {:.0} |\n", cells.join(" / "), median(v))
        };
        let mut s = format!(
            "One sensor, {} frames per trial ({} samples per channel), batches of {BATCH_FRAMES}; NATS at {}.\n\n\
             | arm | frames/s per trial | median frames/s |\n|---|---|---|\n",
            self.frames_per_trial, self.samples_per_frame, self.url
        );
        s.push_str(&row("single-node `serve`", &self.single_frames_per_s));
        s.push_str(&row("cluster path (`serve --cluster`, one node)", &self.cluster_frames_per_s));
        s.push_str(&format!(
            "\nCluster path / single node: **{:.0} %** (target >= 70 %: {}). First report after {} s (cluster arm: sensor noticed and claimed).\n",
            100.0 * self.ratio(),
            if self.ratio() >= 0.7 { "met" } else { "NOT met" },
            self.cluster_first_report_s.iter().map(|x| format!("{x:.2}")).collect::<Vec<_>>().join(" / ")
        ));
        s
    }
}

/// Runs `trials` trials of each arm, alternating, with `frames` reference
/// frames at `snr_db` per trial.
pub fn measure_cluster_cost(
    scene: &Scene,
    snr_db: f64,
    frames: usize,
    trials: usize,
    url: &str,
) -> Result<ClusterCost, BenchError> {
    let err = |e: &dyn std::fmt::Display| BenchError::Service(e.to_string());
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().map_err(|e| err(&e))?;
    let count = frames.max(2);
    let (domain, _) = reference_frames(scene, snr_db, 4242, count.min(2048));
    let samples_per_frame = domain.first().map_or(0, |f| f.len());
    let wire: Vec<proto::Frame> = (0..count)
        .map(|i| {
            let mut f = domain[i % domain.len()].clone();
            f.sequence = i as u64;
            frame_to_proto(&f)
        })
        .collect();
    drop(domain);
    let mut cost = ClusterCost {
        url: url.to_string(),
        frames_per_trial: count,
        samples_per_frame,
        single_frames_per_s: Vec::new(),
        cluster_frames_per_s: Vec::new(),
        cluster_first_report_s: Vec::new(),
    };
    rt.block_on(async {
        let node_id = format!("bench-{}", std::process::id());
        let cluster = ClusterConfig {
            url: url.to_string(),
            node_id: node_id.clone(),
            lease_ttl: Duration::from_secs(3),
            replicas: 1,
        };
        // Fails early, naming the URL, when NATS is not there.
        let admin = Cluster::connect(ClusterConfig { node_id: format!("{node_id}-admin"), ..cluster.clone() }, scene.clone())
            .await
            .map_err(|e| err(&e))?;
        let stamp = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis());
        for t in 0..trials.max(1) {
            let sensor = format!("bench-{stamp}-{t}");
            let (fps, _) = trial(scene, &wire, &format!("{sensor}-single"), None, 1, 0).await?;
            cost.single_frames_per_s.push(fps);
            let (fps, first) = trial(scene, &wire, &sensor, Some(cluster.clone()), 1, 0).await?;
            cost.cluster_frames_per_s.push(fps);
            cost.cluster_first_report_s.push(first);
            admin.forget_sensor(&sensor).await.map_err(|e| err(&e))?;
            eprintln!(
                "tofwave bench --cluster: trial {}: single {:.0} frames/s, cluster {:.0} frames/s",
                t + 1,
                cost.single_frames_per_s[t],
                fps
            );
        }
        Ok::<(), BenchError>(())
    })?;
    Ok(cost)
}

/// One server (alone, or a cluster node), one sensor: steady-state reports/s
/// (the clock starting at report `skip` + 1; `skip` < the frames less one)
/// and seconds to the first report.
pub(super) async fn trial(
    scene: &Scene,
    wire: &[proto::Frame],
    sensor: &str,
    cluster: Option<ClusterConfig>,
    workers_per_sensor: usize,
    skip: usize,
) -> Result<(f64, f64), BenchError> {
    let err = |e: &dyn std::fmt::Display| BenchError::Service(e.to_string());
    let count = wire.len();
    let listener = TcpListener::bind("127.0.0.1:0").await.map_err(|e| err(&e))?;
    let url = format!("http://{}", listener.local_addr().map_err(|e| err(&e))?);
    let config = ServerConfig {
        scene: scene.clone(),
        queue_frames: 256,
        subscriber_buffer: count + 16,
        history_reports: 16,
        cluster,
        workers_per_sensor,
        ..ServerConfig::default()
    };
    let (stop_tx, stop_rx) = oneshot::channel::<()>();
    let server = tokio::spawn(run(listener, config, async move {
        let _ = stop_rx.await;
    }));
    let mut clients = client::connect(&url, &ClientOptions::default()).await.map_err(|e| err(&e))?;
    let request = proto::SubscribeRequest { sensor_ids: vec![sensor.to_string()], ..Default::default() };
    let mut events = client::subscribe(&mut clients.reports, request).await.map_err(|e| err(&e))?;
    let frames: Vec<proto::Frame> = wire
        .iter()
        .map(|f| proto::Frame { sensor_id: sensor.to_string(), ..f.clone() })
        .collect();
    let (tx, rx) = tokio::sync::mpsc::channel::<proto::FrameBatch>(4);
    let t0 = Instant::now();
    let producer = tokio::spawn(async move {
        for chunk in frames.chunks(BATCH_FRAMES) {
            if tx.send(proto::FrameBatch { frames: chunk.to_vec() }).await.is_err() {
                break;
            }
        }
    });
    let mut ingest = clients.ingest.clone();
    let pusher = tokio::spawn(async move { client::push(&mut ingest, ReceiverStream::new(rx), |_| {}).await });
    let skip = skip.min(count.saturating_sub(2));
    let (mut first_report, mut first, mut last, mut got) = (None, None, None, 0usize);
    while got < count {
        match tokio::time::timeout(Duration::from_secs(60), events.message()).await {
            Ok(Ok(Some(proto::ReportEvent { event: Some(Event::Report(_)) }))) => {
                let now = Instant::now();
                first_report.get_or_insert(now);
                got += 1;
                if got > skip {
                    first.get_or_insert(now);
                    last = Some(now);
                }
            }
            Ok(Ok(Some(_))) => {}
            other => return Err(BenchError::Service(format!("{got} of {count} reports arrived, then {other:?}"))),
        }
    }
    let _ = producer.await;
    let summary = pusher.await.map_err(|e| err(&e))?.map_err(|e| err(&format!("{e:?}")))?;
    let _ = stop_tx.send(());
    let _ = tokio::time::timeout(Duration::from_secs(30), server).await;
    if summary.rejected > 0 {
        return Err(BenchError::Service(format!("{} frames rejected", summary.rejected)));
    }
    let (first, last) = (first.expect("count >= 2"), last.expect("count >= 2"));
    let span = last.duration_since(first).as_secs_f64().max(1e-9);
    let first_report = first_report.expect("count >= 2");
    Ok(((count - skip - 1) as f64 / span, first_report.duration_since(t0).as_secs_f64()))
}
