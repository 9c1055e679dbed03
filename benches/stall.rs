//! Does a subscriber that stops reading slow ingest down?
//!
//! Runs the gRPC server on loopback and pushes the same simulated frames
//! (the lab scene of `replay-data/scenes/lab-table-10-20.toml`, two i16
//! channels of 2500 samples) as fast as the server takes them, in
//! alternating rounds: with no subscriber, and with one subscriber that opens
//! its stream (16 KiB HTTP/2 windows) and then reads nothing. Ingest
//! throughput is the frames acknowledged per second of the push; the median
//! of the rounds is compared. After its round the stalled subscriber resumes
//! reading and must find a "lagged, N skipped" marker.
//!
//! Run: `cargo bench --bench stall` (`-- --frames N --rounds R` to change the load).

use std::time::{Duration, Instant};

use tofwave::frame::Frame;
use tofwave::physics::Simulator;
use tofwave::scene::Scene;
use tofwave::service::client::{self, ClientOptions};
use tofwave::wire::frame_to_proto;
use tofwave::wire::proto::{self, report_event::Event};
use tofwave::service::{run, ServerConfig};
use tokio::net::TcpListener;

fn arg(name: &str, default: usize) -> usize {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn frames(scene: &Scene, n: usize) -> Vec<Frame> {
    let sim = Simulator::new(scene).expect("the lab scene simulates");
    (0..n as u64)
        .map(|i| {
            let mut f = sim.frame(5, i).0;
            f.sensor_id = "bench".into();
            f
        })
        .collect()
}

struct Round {
    frames_per_s: f64,
    skipped: u64,
    delivered: u64,
}

async fn round(scene: &Scene, batches: &[proto::FrameBatch], stalled: bool) -> Round {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let config = ServerConfig { scene: scene.clone(), ..Default::default() };
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(run(listener, config, async move {
        let _ = stop_rx.await;
    }));
    let mut c = client::connect(&url, &ClientOptions::default()).await.unwrap();
    let sub = if stalled {
        let channel = tonic::transport::Endpoint::from_shared(url.clone())
            .unwrap()
            .initial_stream_window_size(16 * 1024)
            .initial_connection_window_size(16 * 1024)
            .connect()
            .await
            .unwrap();
        let mut rc = tofwave::service::grpc::reports_client::ReportsClient::new(channel);
        Some(rc.subscribe(proto::SubscribeRequest::default()).await.unwrap().into_inner())
    } else {
        None
    };
    let frames_total: usize = batches.iter().map(|b| b.frames.len()).sum();
    let t = Instant::now();
    let summary = client::push(&mut c.ingest, tokio_stream::iter(batches.to_vec()), |_| {})
        .await
        .expect("push succeeds");
    let elapsed = t.elapsed();
    assert_eq!(summary.accepted as usize, frames_total, "every frame accepted");
    // Resume the stalled reader; shutdown ends its stream after the last report.
    let reader = sub.map(|mut s| {
        tokio::spawn(async move {
            let (mut delivered, mut skipped) = (0u64, 0u64);
            while let Ok(Some(e)) = s.message().await {
                match e.event {
                    Some(Event::Report(_)) => delivered += 1,
                    Some(Event::Lagged(l)) => skipped += l.skipped,
                    None => {}
                }
            }
            (delivered, skipped)
        })
    });
    let _ = stop_tx.send(());
    let _ = tokio::time::timeout(Duration::from_secs(60), server).await;
    let (delivered, skipped) = match reader {
        Some(r) => r.await.unwrap(),
        None => (0, 0),
    };
    Round { frames_per_s: frames_total as f64 / elapsed.as_secs_f64(), skipped, delivered }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}

fn main() {
    // `cargo bench` passes `--bench`; only our own flags are read.
    let n = arg("--frames", 4000);
    let rounds = arg("--rounds", 5);
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/replay-data/scenes/lab-table-10-20.toml");
    let scene = Scene::load(std::path::Path::new(path)).expect("scene loads");
    eprintln!("simulating {n} frames of the lab scene...");
    let fs = frames(&scene, n);
    let batches: Vec<proto::FrameBatch> =
        fs.chunks(50).map(|c| proto::FrameBatch { frames: c.iter().map(frame_to_proto).collect() }).collect();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let (mut free, mut stalled) = (Vec::new(), Vec::new());
    let mut markers = Vec::new();
    // One warm-up round of each, not counted.
    rt.block_on(round(&scene, &batches, false));
    rt.block_on(round(&scene, &batches, true));
    for r in 0..rounds {
        let a = rt.block_on(round(&scene, &batches, false));
        let b = rt.block_on(round(&scene, &batches, true));
        eprintln!(
            "round {r}: no subscriber {:.0} frames/s; stalled subscriber {:.0} frames/s ({} delivered, {} skipped)",
            a.frames_per_s, b.frames_per_s, b.delivered, b.skipped
        );
        free.push(a.frames_per_s);
        stalled.push(b.frames_per_s);
        markers.push(b.skipped);
    }
    let (f, s) = (median(free), median(stalled));
    let samples = 2.0 * fs[0].channels[0].samples.len() as f64;
    println!("ingest + processing, {n} frames x {rounds} rounds, median:");
    println!("  no subscriber       {f:>9.0} frames/s  ({:.1} Msamples/s)", f * samples / 1e6);
    println!("  stalled subscriber  {s:>9.0} frames/s  ({:.1} Msamples/s)", s * samples / 1e6);
    println!("  cost of the stalled subscriber: {:+.1} % (target: less than 5 %)", 100.0 * (f - s) / f);
    println!(
        "  lag markers on resume: {} of {rounds} rounds (reports skipped per round: {markers:?})",
        markers.iter().filter(|&&m| m > 0).count()
    );
}
