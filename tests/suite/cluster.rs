//! `serve --cluster`: nodes joined by a real `nats-server -js` on loopback
//! (a free port, a temporary store). Reports that reach subscribers are
//! compared, JSON line for JSON line, with the same frames run through
//! `Pipeline` on one machine (`service::direct_reports`), so the tests hold
//! whatever the pipeline computes. `.ci/run` installs nats-server; without
//! it these tests fail and say so.

use super::service::{batch, direct_reports, frames};
use std::collections::{BTreeMap, BTreeSet};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tofwave::frame::Frame;
use tofwave::scene::Scene;
use tofwave::service::client::{self, ClientOptions};
use tofwave::service::cluster::{self, ClusterConfig};
use tofwave::service::{ServerConfig, ServiceError, run};
use tofwave::wire::proto::{self, report_event::Event};
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// A nats-server with JetStream on 127.0.0.1, killed when dropped.
struct Nats {
    child: Child,
    url: String,
    _store: tempfile::TempDir,
}

impl Nats {
    fn start() -> Nats {
        let store = tempfile::tempdir().unwrap();
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let child = Command::new("nats-server")
            .args(["-js", "-a", "127.0.0.1", "-p", &port.to_string(), "-sd"])
            .arg(store.path())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| {
                panic!(
                    "cannot start nats-server ({e}): the cluster tests need it on PATH. \
                     Run .ci/run (it installs nats-server), or `apt-get install nats-server`"
                )
            });
        let deadline = Instant::now() + Duration::from_secs(10);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(Instant::now() < deadline, "nats-server did not listen on 127.0.0.1:{port} within 10 s");
            std::thread::sleep(Duration::from_millis(20));
        }
        Nats { child, url: format!("nats://127.0.0.1:{port}"), _store: store }
    }
}

impl Drop for Nats {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A node in this process.
struct Node {
    url: String,
    stop: Option<oneshot::Sender<()>>,
    task: JoinHandle<Result<(), ServiceError>>,
}

impl Node {
    async fn start(nats: &Nats, node_id: &str, scene: Scene) -> Node {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let config = ServerConfig {
            scene,
            subscriber_buffer: 65536,
            cluster: Some(ClusterConfig {
                url: nats.url.clone(),
                node_id: node_id.into(),
                lease_ttl: Duration::from_secs(3),
                replicas: 1,
            }),
            ..ServerConfig::default()
        };
        let (tx, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(run(listener, config, async move {
            let _ = rx.await;
        }));
        Node { url, stop: Some(tx), task }
    }

    async fn shutdown(mut self) {
        let _ = self.stop.take().unwrap().send(());
        tokio::time::timeout(Duration::from_secs(30), self.task)
            .await
            .expect("node drains within 30 s")
            .unwrap()
            .unwrap();
    }
}

/// A node as a child process (`tofwave serve --cluster`), so it can be killed with SIGKILL.
struct ChildNode {
    child: Child,
    url: String,
    /// Where its log (standard error) goes.
    log: std::path::PathBuf,
}

impl ChildNode {
    /// Its Prometheus text (`--metrics`), read with a plain HTTP/1.0 GET.
    fn metrics(&self) -> String {
        use std::io::{Read, Write};
        let text = std::fs::read_to_string(&self.log).unwrap();
        let addr = text
            .lines()
            .find_map(|l| l.strip_prefix("tofwave: serving Prometheus metrics on http://"))
            .and_then(|l| l.strip_suffix("/metrics"))
            .unwrap_or_else(|| panic!("no metrics address in the log:\n{text}"));
        let mut c = std::net::TcpStream::connect(addr).unwrap();
        c.write_all(b"GET /metrics HTTP/1.0\r\n\r\n").unwrap();
        let mut body = String::new();
        c.read_to_string(&mut body).unwrap();
        body
    }
}

impl ChildNode {
    fn start(nats: &Nats, node_id: &str, scene_file: &std::path::Path, log: &std::path::Path) -> ChildNode {
        let mut child = Command::new(env!("CARGO_BIN_EXE_tofwave"))
            .args(["serve", "--listen", "127.0.0.1:0", "--cluster", &nats.url, "--node-id", node_id])
            .args(["--subscriber-buffer", "65536", "--metrics", "127.0.0.1:0", "--scene"])
            .arg(scene_file)
            .env("RUST_LOG", "tofwave=info")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .unwrap();
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            let text = std::fs::read_to_string(log).unwrap_or_default();
            if let Some(addr) = text.lines().find_map(|l| l.strip_prefix("tofwave: serving gRPC on ")) {
                if text.contains("tofwave: serving Prometheus metrics on") {
                    return ChildNode { child, url: format!("http://{}", addr.trim()), log: log.to_path_buf() };
                }
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                let _ = child.wait();
                panic!("node {node_id} did not start within 20 s:\n{text}");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for ChildNode {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `per_sensor` frames of each sensor, interleaved 32 at a time, as batches of 64 frames.
fn interleaved(sensors: &[String], per_sensor: u64) -> (Vec<Frame>, Vec<proto::FrameBatch>) {
    let all: Vec<Vec<Frame>> = sensors
        .iter()
        .enumerate()
        .map(|(i, s)| frames(s, 0..per_sensor, 1700 + i as u64))
        .collect();
    let mut order = Vec::new();
    for chunk in 0..per_sensor.div_ceil(32) as usize {
        for f in &all {
            order.extend(f.iter().skip(chunk * 32).take(32).cloned());
        }
    }
    let batches = order.chunks(64).map(batch).collect();
    (order, batches)
}

/// Reads reports from a subscription until `want` arrived or `timeout` passes without one;
/// `on_report` sees each (sensor, seq_first, arrival).
async fn collect(
    stream: &mut tonic::Streaming<proto::ReportEvent>,
    want: usize,
    timeout: Duration,
    mut on_report: impl FnMut(&proto::Report, Instant),
) -> Vec<proto::Report> {
    let mut got = Vec::new();
    while got.len() < want {
        match tokio::time::timeout(timeout, stream.message()).await {
            Ok(Ok(Some(proto::ReportEvent { event: Some(Event::Report(r)) }))) => {
                on_report(&r, Instant::now());
                got.push(r);
            }
            Ok(Ok(Some(proto::ReportEvent { event: Some(Event::Lagged(l)) }))) => panic!("subscriber lagged by {} reports", l.skipped),
            other => panic!("{} of {want} reports, then {other:?}", got.len()),
        }
    }
    got
}

/// Per sensor: its reports' JSON in arrival order; asserts each sensor's arrive in sequence order.
fn by_sensor_in_order(reports: &[proto::Report]) -> BTreeMap<String, Vec<String>> {
    let mut out: BTreeMap<String, Vec<(u64, String)>> = BTreeMap::new();
    for r in reports {
        out.entry(r.sensor.clone()).or_default().push((r.seq_first, r.json.clone()));
    }
    out.into_iter()
        .map(|(s, v)| {
            let seqs: Vec<u64> = v.iter().map(|x| x.0).collect();
            assert!(seqs.windows(2).all(|w| w[0] < w[1]), "sensor {s}: reports out of order or repeated: {seqs:?}");
            (s, v.into_iter().map(|x| x.1).collect())
        })
        .collect()
}

fn reference_by_sensor(scene: &Scene, frames: &[Frame]) -> BTreeMap<String, Vec<String>> {
    let mut out: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for j in direct_reports(scene, frames) {
        let v: serde_json::Value = serde_json::from_str(&j).unwrap();
        out.entry(v["sensor"].as_str().unwrap().to_string()).or_default().push(j);
    }
    out
}

/// Wire reports rebuilt from JSON lines equal those built from the domain report.
#[test]
fn report_from_json_is_the_inverse_of_report_to_proto() {
    let scene = Scene::default_scene();
    let fs = frames("j", 0..20, 5);
    let mut p = tofwave::service::session::build_pipeline(&scene, "j").unwrap();
    let mut reports = Vec::new();
    for f in fs {
        p.push(f, &mut reports).unwrap();
    }
    assert_eq!(reports.len(), 20);
    for r in &reports {
        let json = tofwave::pipeline::report_json(r);
        let want = tofwave::wire::report_to_proto(r, json.clone());
        // Debug text: a NaN (written null) equals a NaN there.
        assert_eq!(format!("{:?}", tofwave::wire::report_from_json(&json).unwrap()), format!("{want:?}"), "{json}");
    }
    assert!(tofwave::wire::report_from_json("{}").unwrap_err().contains("no field"));
}

/// Two nodes, 8 sensors x 2000 frames pushed to node A, subscribed on node B:
/// every report, each sensor's in order, equal to one machine's.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn two_nodes_report_every_sensor_in_order_as_one_node_does() {
    let nats = Nats::start();
    let scene = Scene::default_scene();
    let sensors: Vec<String> = (0..8).map(|i| format!("lidar-{i}")).collect();
    let (all, batches) = interleaved(&sensors, 2000);
    let a = Node::start(&nats, "a", scene.clone()).await;
    let b = Node::start(&nats, "b", scene.clone()).await;
    let mut on_b = client::connect(&b.url, &ClientOptions::default()).await.unwrap();
    let mut events = client::subscribe(&mut on_b.reports, proto::SubscribeRequest::default()).await.unwrap();
    let mut on_a = client::connect(&a.url, &ClientOptions::default()).await.unwrap();
    let t0 = Instant::now();
    let pushed = tokio::spawn(async move {
        client::push(&mut on_a.ingest, tokio_stream::iter(batches), |_| {}).await.map_err(|e| format!("{e:?}"))
    });
    // Scenes come from the nodes' --scene in cluster mode: SetScene says so.
    // A second node with a live node's id is refused at start.
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let twin = ServerConfig {
        cluster: Some(ClusterConfig { url: nats.url.clone(), node_id: "b".into(), lease_ttl: Duration::from_secs(3), replicas: 1 }),
        ..ServerConfig::default()
    };
    let err = run(listener, twin, std::future::pending::<()>()).await.unwrap_err().to_string();
    assert!(err.contains("\"b\" is in use"), "{err}");
    let refused = on_b
        .control
        .set_scene(proto::SetSceneRequest { sensor_id: "lidar-0".into(), toml: scene.to_toml() })
        .await
        .unwrap_err();
    assert_eq!(refused.code(), tonic::Code::FailedPrecondition, "{refused:?}");
    assert!(refused.message().contains(&nats.url), "{}", refused.message());
    let got = collect(&mut events, all.len(), Duration::from_secs(60), |_, _| {}).await;
    let elapsed = t0.elapsed();
    let summary = pushed.await.unwrap().unwrap();
    assert_eq!((summary.accepted, summary.rejected), (16000, 0));
    println!("2 nodes: 16000 frames pushed to A, reported on B in {:.1} s", elapsed.as_secs_f64());
    let cluster = by_sensor_in_order(&got);
    let reference = reference_by_sensor(&scene, &all);
    assert_eq!(cluster.keys().collect::<Vec<_>>(), reference.keys().collect::<Vec<_>>());
    for (s, want) in &reference {
        assert_eq!(cluster[s].len(), want.len(), "sensor {s}");
        if let Some(i) = (0..want.len()).find(|&i| cluster[s][i] != want[i]) {
            panic!("sensor {s} report {i} differs from one node's:\ncluster: {}\none node: {}", cluster[s][i], want[i]);
        }
    }
    a.shutdown().await;
    b.shutdown().await;
}

/// Node B joins while node A holds every sensor: A hands B its share
/// (rendezvous preference) mid-stream, B rebuilds each sensor's state by
/// replay, and the reports stay exactly one machine's.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_joining_node_takes_over_its_share_and_reports_stay_exact() {
    let nats = Nats::start();
    let mut scene = Scene::default_scene();
    scene.averaging.frames = 4;
    let sensors: Vec<String> = (0..6).map(|i| format!("lidar-{i}")).collect();
    let (all, batches) = interleaved(&sensors, 800);
    let want = all.len() / 4;
    let a = Node::start(&nats, "a", scene.clone()).await;
    let mut on_a = client::connect(&a.url, &ClientOptions::default()).await.unwrap();
    let mut events = client::subscribe(&mut on_a.reports, proto::SubscribeRequest::default()).await.unwrap();
    let pushed = tokio::spawn(async move {
        client::push(&mut on_a.ingest, tokio_stream::iter(batches), |_| {}).await.map_err(|e| format!("{e:?}"))
    });
    let mut got = collect(&mut events, want / 4, Duration::from_secs(60), |_, _| {}).await;
    let b = Node::start(&nats, "b", scene.clone()).await;
    // Who holds which sensor, read from the lease bucket.
    let js = async_nats::jetstream::new(async_nats::connect(nats.url.as_str()).await.unwrap());
    let leases = js.get_key_value(cluster::LEASES_BUCKET).await.unwrap();
    let live: BTreeSet<String> = ["a".to_string(), "b".to_string()].into();
    let b_share: Vec<&String> = sensors
        .iter()
        .filter(|s| cluster::preferred_node(&cluster::sensor_token(s), &live) == Some("b"))
        .collect();
    assert!(!b_share.is_empty(), "the test's sensors all prefer node a");
    let deadline = Instant::now() + Duration::from_secs(15);
    let mut moved = BTreeSet::new();
    while moved.len() < b_share.len() {
        for s in &b_share {
            if leases.get(cluster::sensor_token(s)).await.unwrap().as_deref() == Some(b"b".as_slice()) {
                moved.insert(s.to_string());
            }
        }
        assert!(Instant::now() < deadline, "node b took {moved:?} of its share {b_share:?} within 15 s");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let rest = collect(&mut events, want - got.len(), Duration::from_secs(60), |_, _| {}).await;
    got.extend(rest);
    let summary = pushed.await.unwrap().unwrap();
    assert_eq!((summary.accepted, summary.rejected), (all.len() as u64, 0));
    println!("node b joined after {} of {want} reports and took {} of {} sensors", want / 4, moved.len(), sensors.len());
    let cluster = by_sensor_in_order(&got);
    let reference = reference_by_sensor(&scene, &all);
    for (s, want) in &reference {
        assert_eq!(cluster.get(s).map_or(0, Vec::len), want.len(), "sensor {s}");
        if let Some(i) = (0..want.len()).find(|&i| cluster[s][i] != want[i]) {
            panic!("sensor {s} report {i} differs from one node's:\ncluster: {}\none node: {}", cluster[s][i], want[i]);
        }
    }
    a.shutdown().await;
    b.shutdown().await;
}

/// A digitiser gateway publishing encoded frames straight to
/// `tofwave.frames.<sensor>` is served like gRPC ingest; a frame of another
/// sensor on that subject, or one that does not decode, is refused (no report).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_published_to_nats_by_a_gateway_are_processed() {
    use prost::Message as _;
    let nats = Nats::start();
    let scene = Scene::default_scene();
    let node = Node::start(&nats, "a", scene.clone()).await;
    let mut c = client::connect(&node.url, &ClientOptions::default()).await.unwrap();
    let mut events = client::subscribe(&mut c.reports, proto::SubscribeRequest::default()).await.unwrap();
    let js = async_nats::jetstream::new(async_nats::connect(nats.url.as_str()).await.unwrap());
    let sensor = "gate.way 1";
    let subject = cluster::frames_subject(sensor);
    assert_eq!(subject, "tofwave.frames.gate=2Eway=201");
    let fs = frames(sensor, 0..24, 77);
    for (i, f) in fs.iter().enumerate() {
        let payload = match i {
            // Another sensor's frame on this subject, and bytes that are no frame.
            5 => tofwave::wire::frame_to_proto(&Frame { sensor_id: "other".into(), ..f.clone() }).encode_to_vec(),
            9 => b"not a frame".to_vec(),
            _ => tofwave::wire::frame_to_proto(f).encode_to_vec(),
        };
        js.publish(subject.clone(), payload.into()).await.unwrap().await.unwrap();
    }
    let kept: Vec<Frame> = fs.iter().enumerate().filter(|(i, _)| *i != 5 && *i != 9).map(|(_, f)| f.clone()).collect();
    let got = collect(&mut events, kept.len(), Duration::from_secs(30), |_, _| {}).await;
    let cluster = by_sensor_in_order(&got);
    assert_eq!(cluster[sensor], reference_by_sensor(&scene, &kept)[sensor]);
    match tokio::time::timeout(Duration::from_millis(500), events.message()).await {
        Err(_) => {}
        Ok(m) => panic!("a report for a refused frame: {m:?}"),
    }
    node.shutdown().await;
}

/// An unreachable NATS server stops the server at start with an error naming the URL.
#[tokio::test]
async fn unreachable_nats_is_an_error_naming_the_url() {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let url = format!("nats://127.0.0.1:{port}");
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let config = ServerConfig {
        cluster: Some(ClusterConfig { url: url.clone(), node_id: "x".into(), lease_ttl: Duration::from_secs(3), replicas: 1 }),
        ..ServerConfig::default()
    };
    let err = tokio::time::timeout(Duration::from_secs(20), run(listener, config, std::future::pending::<()>()))
        .await
        .expect("fails within 20 s")
        .unwrap_err();
    let text = err.to_string();
    assert!(text.contains(&url) && text.contains("cannot connect"), "{text}");
}

/// Sensor names split half and half between nodes "a" and "b" by the
/// cluster's rendezvous preference (so the killed node owns half).
fn half_and_half(n: usize) -> Vec<String> {
    let live: BTreeSet<String> = ["a".to_string(), "b".to_string()].into();
    let (mut on_a, mut on_b) = (Vec::new(), Vec::new());
    for i in 0.. {
        let s = format!("lidar-{i}");
        let pref = cluster::preferred_node(&cluster::sensor_token(&s), &live).unwrap();
        let side = if pref == "a" { &mut on_a } else { &mut on_b };
        if side.len() < n / 2 {
            side.push(s);
        }
        if on_a.len() + on_b.len() == n {
            break;
        }
    }
    on_a.into_iter().chain(on_b).collect()
}

/// kill -9 of node B (owning half the sensors) midway: its sensors move to
/// A within 5 s, every acknowledged frame is reported exactly once, and the
/// reports (averages of 4 frames: groups in progress at the kill included)
/// equal one machine's.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn kill_9_of_an_owner_moves_its_sensors_and_every_acked_frame_is_reported_once() {
    let nats = Nats::start();
    let dir = tempfile::tempdir().unwrap();
    let mut scene = Scene::default_scene();
    scene.averaging.frames = 4;
    let scene_file = dir.path().join("scene.toml");
    std::fs::write(&scene_file, scene.to_toml()).unwrap();
    let sensors = half_and_half(8);
    let b_sensors: BTreeSet<String> = sensors[4..].iter().cloned().collect();
    let per_sensor = 1200u64;
    let (all, batches) = interleaved(&sensors, per_sensor);
    let want = all.len() / 4;

    let a = ChildNode::start(&nats, "a", &scene_file, &dir.path().join("a.log"));
    let mut b = ChildNode::start(&nats, "b", &scene_file, &dir.path().join("b.log"));
    let mut on_a = client::connect(&a.url, &ClientOptions::default()).await.unwrap();
    let mut events = client::subscribe(&mut on_a.reports, proto::SubscribeRequest::default()).await.unwrap();
    // Both nodes are registered once they serve; give A's poll a beat to see B.
    tokio::time::sleep(Duration::from_millis(600)).await;
    let pushed = tokio::spawn(async move {
        client::push(&mut on_a.ingest, tokio_stream::iter(batches), |_| {}).await.map_err(|e| format!("{e:?}"))
    });

    // Midway: half of B's sensors' reports arrived.
    let mut first = Vec::new();
    let mut b_reports = 0;
    while b_reports < b_sensors.len() * want / 8 / 2 {
        let r = collect(&mut events, 1, Duration::from_secs(60), |_, _| {}).await.remove(0);
        b_reports += b_sensors.contains(&r.sensor) as usize;
        first.push(r);
    }
    b.child.kill().unwrap();
    let killed = Instant::now();
    b.child.wait().unwrap();
    // What B published before it died arrives within milliseconds; after
    // 300 ms the next report of each of B's sensors is the new owner's.
    let mut last_before: BTreeMap<String, u64> = BTreeMap::new();
    let mut resumed: BTreeMap<String, Duration> = BTreeMap::new();
    let settle = Duration::from_millis(300);
    let rest = collect(&mut events, want - first.len(), Duration::from_secs(60), |r, at| {
        if !b_sensors.contains(&r.sensor) {
            return;
        }
        let since = at.duration_since(killed);
        if since < settle {
            last_before.insert(r.sensor.clone(), r.seq_first);
        } else {
            resumed.entry(r.sensor.clone()).or_insert(since);
        }
    })
    .await;
    let summary = pushed.await.unwrap().unwrap();
    assert_eq!((summary.accepted, summary.rejected), (all.len() as u64, 0), "node A acknowledged every frame");
    let takeover = resumed.values().max().copied().unwrap_or_default();
    println!(
        "kill -9 of node b (owned {} of 8 sensors) after {} of {want} reports: its sensors resumed on a after {:.2} s (per sensor: {:?})",
        b_sensors.len(),
        first.len(),
        takeover.as_secs_f64(),
        resumed.iter().map(|(s, d)| format!("{s} {:.2} s", d.as_secs_f64())).collect::<Vec<_>>()
    );
    assert_eq!(resumed.len(), b_sensors.len(), "every sensor of B resumed: {resumed:?}");
    assert!(takeover <= Duration::from_secs(5), "takeover took {takeover:?} (target <= 5 s)");

    let got: Vec<proto::Report> = first.into_iter().chain(rest).collect();
    // Exactly once: nothing more arrives.
    match tokio::time::timeout(Duration::from_millis(1500), events.message()).await {
        Err(_) => {}
        Ok(m) => panic!("a report beyond the {want} expected: {m:?}"),
    }
    let cluster = by_sensor_in_order(&got);
    let reference = reference_by_sensor(&scene, &all);
    for (s, want) in &reference {
        assert_eq!(cluster.get(s).map_or(0, Vec::len), want.len(), "sensor {s}");
        if let Some(i) = (0..want.len()).find(|&i| cluster[s][i] != want[i]) {
            panic!("sensor {s} report {i} differs from one node's:\ncluster: {}\none node: {}", cluster[s][i], want[i]);
        }
    }
    let log = std::fs::read_to_string(dir.path().join("a.log")).unwrap();
    assert!(log.contains("sensor claimed"), "{log}");
    // A claimed B's sensors and rebuilt their state by replay.
    let metrics = a.metrics();
    for s in &b_sensors {
        let claims = format!("tofwave_cluster_claims_total{{sensor=\"{s}\"}} 1");
        assert!(metrics.contains(&claims), "no {claims} in\n{metrics}");
        let replayed = metrics
            .lines()
            .find_map(|l| l.strip_prefix(&format!("tofwave_cluster_frames_replayed_total{{sensor=\"{s}\"}} ")))
            .and_then(|v| v.trim().parse::<f64>().ok())
            .unwrap_or(0.0);
        assert!(replayed >= 100.0, "{s}: {replayed} frames replayed (B had reported about half of its 1200)");
        println!("{s}: {replayed} frames replayed on a");
    }
    assert!(metrics.contains("tofwave_cluster_sensors_owned 8"), "{metrics}");
}

/// `tofwave bench --cluster`: both arms run and are timed, and the cluster
/// arm's scratch sensor is forgotten (its frames purged) afterwards.
#[test]
fn bench_cluster_measures_both_arms_and_forgets_its_sensor() {
    let nats = Nats::start();
    let scene = tofwave::bench::reference_scene();
    let cost = tofwave::bench::measure_cluster_cost(&scene, 30.0, 300, 1, &nats.url).unwrap();
    assert_eq!((cost.single_frames_per_s.len(), cost.cluster_frames_per_s.len()), (1, 1));
    for r in cost.single_frames_per_s.iter().chain(&cost.cluster_frames_per_s) {
        assert!(r.is_finite() && *r > 10.0, "{cost:?}");
    }
    assert!(cost.markdown().contains("Cluster path / single node"), "{}", cost.markdown());
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let js = async_nats::jetstream::new(async_nats::connect(nats.url.as_str()).await.unwrap());
        let info = js.get_stream(cluster::FRAMES_STREAM).await.unwrap().info().await.unwrap().clone();
        assert_eq!(info.state.messages, 0, "the bench's frames were not purged: {:?}", info.state);
    });
}
