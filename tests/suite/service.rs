//! End-to-end gRPC tests: a server on 127.0.0.1:0 per test, driven through the
//! library client. Report contents come from `Pipeline`; every test that
//! compares reports runs the same frames through `Pipeline` directly and
//! demands identical JSON, so the tests hold for any pipeline implementation.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use std::error::Error;
use std::time::Duration;
use tofwave::frame::{Channel, ChannelRole, Frame, Samples};
use tofwave::pipeline::report_json;
use tofwave::scene::Scene;
use tofwave::service::client::{self, BatchLimits, ClientOptions, Clients, Rate};
use tofwave::service::session::build_pipeline;
use tofwave::service::{ServerConfig, ServiceError, run};
use tofwave::wire::frame_to_proto;
use tofwave::wire::proto::{self, report_event::Event};
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;

/// Volts per ADC code of the synthetic digitiser (12-bit over +-0.5 V).
const VOLTS_PER_CODE: f64 = 1.0 / 4096.0;

struct TestServer {
    url: String,
    stop: Option<oneshot::Sender<()>>,
    task: JoinHandle<Result<(), ServiceError>>,
    metrics_url: Option<std::net::SocketAddr>,
}

impl TestServer {
    async fn start(config: ServerConfig) -> TestServer {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let metrics_url = config
            .metrics_listener
            .as_ref()
            .map(|l| l.local_addr().unwrap());
        let (tx, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(run(listener, config, async move {
            let _ = rx.await;
        }));
        TestServer {
            url: format!("http://{addr}"),
            stop: Some(tx),
            task,
            metrics_url,
        }
    }

    /// `config` with a metrics endpoint on a free port.
    async fn with_metrics(mut config: ServerConfig) -> ServerConfig {
        config.metrics_listener = Some(TcpListener::bind("127.0.0.1:0").await.unwrap());
        config
    }

    async fn connect(&self, token: Option<&str>) -> Clients {
        let opts = ClientOptions {
            token: token.map(String::from),
            ..Default::default()
        };
        client::connect(&self.url, &opts).await.unwrap()
    }

    /// Triggers shutdown and waits (bounded) for `run` to return.
    async fn shutdown(mut self) -> Result<(), ServiceError> {
        let _ = self.stop.take().unwrap().send(());
        tokio::time::timeout(Duration::from_secs(30), self.task)
            .await
            .expect("server drains within 30 s")
            .unwrap()
    }
}

/// A prototype-like frame: 2500 samples at 1 GS/s with 200 ns of pre-trigger
/// noise, a start pulse at the trigger on CH1 and a return at 10 m on CH2,
/// Gaussian noise (10 mV), 12-bit codes.
fn test_frame(sensor: &str, seq: u64, rng: &mut ChaCha8Rng) -> Frame {
    let n = 2500;
    let dt = 1e-9;
    let t0 = -200e-9;
    let noise = Normal::new(0.0, 0.010).unwrap();
    let pulse = |t: f64, at: f64, fwhm: f64, a: f64| {
        let s = fwhm / 2.354_820_045;
        a * (-0.5 * ((t - at) / s).powi(2)).exp()
    };
    let mut ch = |at: f64, fwhm: f64, a: f64| -> Vec<i16> {
        (0..n)
            .map(|i| {
                let t = t0 + i as f64 * dt;
                let v = pulse(t, at, fwhm, a) + noise.sample(rng);
                (v / VOLTS_PER_CODE).round().clamp(-2048.0, 2047.0) as i16
            })
            .collect()
    };
    let start = ch(0.0, 8e-9, 0.4);
    let stop = ch(2.0 * 10.0 / 299_792_458.0, 26e-9, 0.2);
    let chan = |name: &str, role, s| Channel {
        name: name.into(),
        role,
        samples: Samples::I16(s),
        volts_per_code: VOLTS_PER_CODE,
        offset_v: 0.0,
    };
    Frame {
        sensor_id: sensor.into(),
        sequence: seq,
        trigger_time_s: 1000.0 + seq as f64 * 1e-3,
        sample_interval_s: dt,
        first_sample_offset_s: t0,
        channels: vec![
            chan("CH1", ChannelRole::Unspecified, start),
            chan("CH2", ChannelRole::Unspecified, stop),
        ],
        laser_off: false,
    }
}

pub(crate) fn frames(sensor: &str, seqs: std::ops::Range<u64>, seed: u64) -> Vec<Frame> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    seqs.map(|s| test_frame(sensor, s, &mut rng)).collect()
}

pub(crate) fn batch(frames: &[Frame]) -> proto::FrameBatch {
    proto::FrameBatch {
        frames: frames.iter().map(frame_to_proto).collect(),
    }
}

/// Runs frames through `Pipeline` directly: the reference for server output.
pub(crate) fn direct_reports(scene: &Scene, frames: &[Frame]) -> Vec<String> {
    let mut by_sensor: Vec<(String, tofwave::pipeline::Pipeline)> = Vec::new();
    let mut out = Vec::new();
    let mut reports = Vec::new();
    for f in frames {
        let i = match by_sensor.iter().position(|(s, _)| *s == f.sensor_id) {
            Some(i) => i,
            None => {
                by_sensor.push((
                    f.sensor_id.clone(),
                    build_pipeline(scene, &f.sensor_id).unwrap(),
                ));
                by_sensor.len() - 1
            }
        };
        by_sensor[i]
            .1
            .push(f.clone(), &mut reports)
            .expect("test frames are valid");
        out.extend(reports.drain(..).map(|r| report_json(&r)));
    }
    for (_, p) in &mut by_sensor {
        p.flush(&mut reports);
        out.extend(reports.drain(..).map(|r| report_json(&r)));
    }
    sort_reports(out)
}

fn sort_reports(mut v: Vec<String>) -> Vec<String> {
    let key = |s: &String| {
        let j: serde_json::Value = serde_json::from_str(s).unwrap();
        (
            j["sensor"].as_str().unwrap().to_string(),
            j["seq_first"].as_u64().unwrap(),
        )
    };
    v.sort_by_key(key);
    v
}

async fn push_batches(
    c: &mut Clients,
    batches: Vec<proto::FrameBatch>,
) -> Result<Vec<proto::IngestAck>, tonic::Status> {
    let mut acks = Vec::new();
    client::push(&mut c.ingest, tokio_stream::iter(batches), |a| {
        acks.push(a.clone())
    })
    .await
    .map_err(|e| e.status)?;
    Ok(acks)
}

/// Reads `/metrics` and returns the value of `name` whose labels include all of `labels`.
async fn metric(addr: std::net::SocketAddr, name: &str, labels: &[(&str, &str)]) -> Option<f64> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
        .await
        .unwrap();
    let mut body = String::new();
    s.read_to_string(&mut body).await.unwrap();
    assert!(body.starts_with("HTTP/1.1 200"), "{body}");
    metric_in(&body, name, labels)
}

/// The value of `name` with all of `labels` in Prometheus text `body`.
fn metric_in(body: &str, name: &str, labels: &[(&str, &str)]) -> Option<f64> {
    body.lines().find_map(|l| {
        let (head, value) = l.rsplit_once(' ')?;
        let (n, rest) = head.split_once('{').unwrap_or((head, ""));
        (n == name
            && labels
                .iter()
                .all(|(k, v)| rest.contains(&format!("{k}=\"{v}\""))))
        .then(|| value.parse().unwrap())
    })
}

/// A subscriber connection with 16 KiB HTTP/2 windows (the client default is
/// megabytes), so that not reading stalls the server's sends after a few reports.
async fn small_window_subscribe(url: &str) -> tonic::Streaming<proto::ReportEvent> {
    let channel = tonic::transport::Endpoint::from_shared(url.to_string())
        .unwrap()
        .initial_stream_window_size(16 * 1024)
        .initial_connection_window_size(16 * 1024)
        .connect()
        .await
        .unwrap();
    let mut c = tofwave::service::grpc::reports_client::ReportsClient::new(channel);
    c.subscribe(proto::SubscribeRequest::default())
        .await
        .unwrap()
        .into_inner()
}

async fn collect_events(mut s: tonic::Streaming<proto::ReportEvent>) -> (Vec<String>, u64) {
    let (mut reports, mut skipped) = (Vec::new(), 0);
    while let Some(e) = s.message().await.expect("subscriber stream ends cleanly") {
        match e.event.unwrap() {
            Event::Report(r) => reports.push(r.json),
            Event::Lagged(l) => skipped += l.skipped,
        }
    }
    (reports, skipped)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_frames_are_rejected_one_by_one_and_the_stream_stays_open() {
    let config = TestServer::with_metrics(ServerConfig::default()).await;
    let server = TestServer::start(config).await;
    let mut c = server.connect(None).await;
    let sensor = "malformed";
    let good = frames(sensor, 0..8, 1);
    let mut msgs: Vec<proto::Frame> = good.iter().map(frame_to_proto).collect();
    // [0] good; [1] i16 samples with an odd byte count.
    let b = &msgs[1].channels[1].samples;
    msgs[1].channels[1].samples = b.slice(..b.len() - 1);
    // [2] unknown sample format.
    msgs[2].channels[1].format = 42;
    // [3] NaN in f32 samples.
    let mut f32s: Vec<u8> = (0..2500)
        .flat_map(|i| (i as f32 * 1e-4).to_le_bytes())
        .collect();
    f32s[400..404].copy_from_slice(&f32::NAN.to_le_bytes());
    msgs[3].channels[1].format = proto::SampleFormat::F32 as i32;
    msgs[3].channels[1].samples = f32s.into();
    // [4] zero sample interval.
    msgs[4].sample_interval_s = 0.0;
    // [5] no stop channel (CH1 and CH3, no roles).
    msgs[5].channels[1].name = "CH3".into();
    // [6] good.
    let first = proto::FrameBatch {
        frames: msgs[..7].to_vec(),
    };
    let later = proto::FrameBatch {
        frames: vec![msgs[7].clone()],
    };
    let acks = push_batches(&mut c, vec![first, later]).await.unwrap();

    assert_eq!(acks.len(), 2);
    let a = &acks[0];
    assert_eq!((a.batch, a.accepted, a.rejected), (1, 2, 5), "{a:?}");
    let expect = [
        (1, "frames[1].channels[1].samples"),
        (2, "frames[2].channels[1].format"),
        // The NaN is sample 100 (bytes 400..404); the field may name the index.
        (3, "frames[3].channels[1].samples"),
        (4, "frames[4].sample_interval_s"),
        (5, "frames[5].channels: "),
    ];
    assert_eq!(a.rejections.len(), 5);
    for (r, (seq, field)) in a.rejections.iter().zip(expect) {
        assert_eq!(r.code, "INVALID_ARGUMENT");
        assert_eq!(r.sequence, seq);
        assert_eq!(r.sensor_id, sensor);
        assert!(
            r.message.starts_with(field),
            "{:?} should name {field}",
            r.message
        );
    }
    assert!(
        a.gaps.is_empty(),
        "rejected frames are not missing: {:?}",
        a.gaps
    );
    let b = &acks[1];
    assert_eq!(
        (
            b.batch,
            b.accepted,
            b.rejected,
            b.total_accepted,
            b.total_rejected
        ),
        (2, 1, 0, 3, 5)
    );

    let st = c
        .control
        .get_status(proto::SensorRequest {
            sensor_id: sensor.into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        (st.frames_received, st.frames_processed, st.frames_rejected),
        (8, 3, 5)
    );

    let m = server.metrics_url.unwrap();
    let rejected = "tofwave_frames_rejected_total";
    let invalid = metric(
        m,
        rejected,
        &[("sensor", sensor), ("reason", "invalid_frame")],
    )
    .await;
    assert_eq!(invalid, Some(4.0));
    let no_stop = metric(
        m,
        rejected,
        &[("sensor", sensor), ("reason", "missing_stop")],
    )
    .await;
    assert_eq!(no_stop, Some(1.0));
    let received = metric(m, "tofwave_frames_received_total", &[("sensor", sensor)]).await;
    assert_eq!(received, Some(8.0));
    let processed = metric(m, "tofwave_frames_processed_total", &[("sensor", sensor)]).await;
    assert_eq!(processed, Some(3.0));
    assert!(
        metric(m, "tofwave_processing_seconds_count", &[("sensor", sensor)]).await >= Some(3.0)
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sample_rate_mismatch_and_sequence_gaps_are_reported() {
    let server = TestServer::start(ServerConfig::default()).await;
    let mut c = server.connect(None).await;
    let mut scene = Scene::default_scene();
    scene.digitiser.sample_interval_s = 1e-9;
    c.control
        .set_scene(proto::SetSceneRequest {
            sensor_id: "rate".into(),
            toml: scene.to_toml(),
        })
        .await
        .unwrap();
    let mut fs = frames("rate", 0..3, 2);
    fs[1].sample_interval_s = 2e-9;
    fs[2].sequence = 10;
    let acks = push_batches(&mut c, vec![batch(&fs)]).await.unwrap();
    let a = &acks[0];
    assert_eq!((a.accepted, a.rejected), (2, 1));
    assert!(
        a.rejections[0]
            .message
            .starts_with("frames[1].sample_interval_s: 0.000000002 s does not match"),
        "{:?}",
        a.rejections
    );
    assert_eq!(a.gaps.len(), 1);
    assert_eq!((a.gaps[0].first_missing, a.gaps[0].count), (2, 8));
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversize_message_fails_that_stream_only() {
    let config = ServerConfig {
        max_message_bytes: 64 * 1024,
        ..Default::default()
    };
    let server = TestServer::start(config).await;
    let mut c = server.connect(None).await;
    // 20 frames of 2 x 5000 bytes: ~200 kB, over the 64 KiB limit.
    let big = batch(&frames("big", 0..20, 3));
    let err = push_batches(&mut c, vec![big]).await.unwrap_err();
    assert_eq!(err.code(), Code::InvalidArgument, "{err:?}");
    assert!(err.message().contains("limit of 65536 bytes"), "{err:?}");
    // The server is up, on the same connection and on a new one.
    let small = batch(&frames("big", 20..22, 4));
    let acks = push_batches(&mut c, vec![small.clone()]).await.unwrap();
    assert_eq!(acks[0].accepted, 2);
    let mut c2 = server.connect(None).await;
    assert_eq!(
        push_batches(&mut c2, vec![small]).await.unwrap()[0].accepted,
        2
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tokens_separate_write_and_read_access() {
    let config = ServerConfig {
        write_token: Some("write-secret".into()),
        read_token: Some("read-secret".into()),
        ..Default::default()
    };
    let server = TestServer::start(config).await;
    let one = || batch(&frames("auth", 0..1, 5));

    let mut none = server.connect(None).await;
    let e = push_batches(&mut none, vec![one()]).await.unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated);
    let e = client::subscribe(&mut none.reports, Default::default())
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::Unauthenticated);

    let mut wrong = server.connect(Some("guess")).await;
    assert_eq!(
        push_batches(&mut wrong, vec![one()])
            .await
            .unwrap_err()
            .code(),
        Code::Unauthenticated
    );

    let mut read = server.connect(Some("read-secret")).await;
    assert_eq!(
        push_batches(&mut read, vec![one()])
            .await
            .unwrap_err()
            .code(),
        Code::PermissionDenied
    );
    let e = read
        .control
        .list_sensors(proto::ListSensorsRequest {})
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::PermissionDenied);
    let sub = client::subscribe(&mut read.reports, Default::default())
        .await
        .unwrap();

    let mut write = server.connect(Some("write-secret")).await;
    assert_eq!(
        push_batches(&mut write, vec![one()]).await.unwrap()[0].accepted,
        1
    );
    let sensors = write
        .control
        .list_sensors(proto::ListSensorsRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(sensors.sensors.len(), 1);

    server.shutdown().await.unwrap();
    // The read-only subscription ends cleanly with the server.
    let (reports, skipped) = collect_events(sub).await;
    assert_eq!(
        reports,
        direct_reports(&Scene::default_scene(), &frames("auth", 0..1, 5))
    );
    assert_eq!(skipped, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_is_serving_and_reflection_lists_the_services() {
    use tonic_health::pb::{
        HealthCheckRequest, health_check_response::ServingStatus, health_client::HealthClient,
    };
    use tonic_reflection::pb::v1::{
        ServerReflectionRequest, server_reflection_client::ServerReflectionClient,
        server_reflection_request::MessageRequest, server_reflection_response::MessageResponse,
    };
    // Tokens on: health and reflection must stay open for probes and grpcurl.
    let config = ServerConfig {
        write_token: Some("w".into()),
        ..Default::default()
    };
    let server = TestServer::start(config).await;
    let channel = tonic::transport::Endpoint::from_shared(server.url.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = HealthClient::new(channel.clone());
    for service in [
        "",
        "tofwave.v1.Ingest",
        "tofwave.v1.Reports",
        "tofwave.v1.Control",
    ] {
        let r = health
            .check(HealthCheckRequest {
                service: service.into(),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(r.status, ServingStatus::Serving as i32, "{service:?}");
    }
    let mut refl = ServerReflectionClient::new(channel);
    let req = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut resp = refl
        .server_reflection_info(tokio_stream::iter(vec![req]))
        .await
        .unwrap()
        .into_inner();
    let Some(MessageResponse::ListServicesResponse(list)) =
        resp.message().await.unwrap().unwrap().message_response
    else {
        panic!("no service list")
    };
    let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    for want in [
        "tofwave.v1.Ingest",
        "tofwave.v1.Reports",
        "tofwave.v1.Control",
        "grpc.health.v1.Health",
    ] {
        assert!(names.iter().any(|n| n == want), "{want} not in {names:?}");
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn set_scene_validates_and_applies() {
    let server = TestServer::start(ServerConfig::default()).await;
    let mut c = server.connect(None).await;
    let sensor = "scene";
    let set = |toml: &str| proto::SetSceneRequest {
        sensor_id: sensor.into(),
        toml: toml.into(),
    };
    let e = c
        .control
        .set_scene(set("[detector]\npfa = 2.0\n"))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("detector.pfa"), "{e:?}");
    let e = c
        .control
        .set_scene(set("[detector]\nbogus = 1\n"))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("bogus"), "{e:?}");
    // Refused scenes left nothing behind.
    let e = c
        .control
        .get_scene(proto::SensorRequest {
            sensor_id: sensor.into(),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);

    let mut scene = Scene::default_scene();
    scene.name = "changed".into();
    scene.averaging.frames = 4;
    c.control.set_scene(set(&scene.to_toml())).await.unwrap();
    let got = c
        .control
        .get_scene(proto::SensorRequest {
            sensor_id: sensor.into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(Scene::from_toml_str(&got.toml, "test").unwrap(), scene);
    // The default for other sensors is unchanged.
    let d = c
        .control
        .get_scene(proto::SensorRequest {
            sensor_id: String::new(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        Scene::from_toml_str(&d.toml, "test").unwrap(),
        Scene::default_scene()
    );
    let e = c
        .control
        .get_noise_model(proto::SensorRequest {
            sensor_id: sensor.into(),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_reports_equal_running_the_pipeline_directly() {
    let server = TestServer::start(ServerConfig::default()).await;
    let mut c = server.connect(None).await;
    let sub = client::subscribe(&mut c.reports, Default::default())
        .await
        .unwrap();
    let mut all = frames("replay-a", 0..12, 6);
    all.extend(frames("replay-b", 100..110, 7));
    // Interleave the sensors the way a shared capture would.
    all.sort_by(|x, y| x.trigger_time_s.total_cmp(&y.trigger_time_s));
    let source = all
        .clone()
        .into_iter()
        .map(Ok::<_, std::convert::Infallible>);
    let limits = BatchLimits {
        frames: 5,
        bytes: 1 << 20,
    };
    let summary = client::replay(&mut c.ingest, source, Rate::Max, None, limits, |_| {})
        .await
        .unwrap();
    assert_eq!((summary.accepted, summary.rejected), (22, 0), "{summary}");
    assert_eq!(summary.batches, 5);
    server.shutdown().await.unwrap();
    let (reports, skipped) = collect_events(sub).await;
    assert_eq!(skipped, 0);
    assert_eq!(
        sort_reports(reports),
        direct_reports(&Scene::default_scene(), &all)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_paces_by_trigger_time() {
    let server = TestServer::start(ServerConfig::default()).await;
    let mut c = server.connect(None).await;
    // Ten frames 20 ms apart: 180 ms recorded, 90 ms at twice the pace.
    let mut fs = frames("pace", 0..10, 8);
    for (i, f) in fs.iter_mut().enumerate() {
        f.trigger_time_s = 5.0 + i as f64 * 0.020;
    }
    let t = std::time::Instant::now();
    let source = fs.into_iter().map(Ok::<_, std::convert::Infallible>);
    let summary = client::replay(
        &mut c.ingest,
        source,
        Rate::Factor(2.0),
        None,
        BatchLimits::default(),
        |_| {},
    )
    .await
    .unwrap();
    let elapsed = t.elapsed();
    assert_eq!(summary.accepted, 10);
    assert!(elapsed >= Duration::from_millis(90), "{elapsed:?}");
    // Paced frames go out as they fall due, not in one message (a late
    // wake-up under load may merge frames that fell due together).
    assert!(summary.batches > 1, "{summary}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_subscriber_is_told_it_lagged_and_continues() {
    // A small buffer so a few hundred reports overflow it.
    let config = ServerConfig {
        subscriber_buffer: 8,
        ..Default::default()
    };
    let server = TestServer::start(config).await;
    let mut c = server.connect(None).await;
    let slow = small_window_subscribe(&server.url).await;
    let fs = frames("lag", 0..400, 9);
    // The subscriber reads nothing while all 400 frames are processed.
    let acks = push_batches(&mut c, fs.chunks(50).map(batch).collect())
        .await
        .unwrap();
    assert_eq!(acks.iter().map(|a| a.accepted).sum::<u64>(), 400);
    // Now it resumes reading; the server's shutdown ends its stream after the
    // last report. Every report is delivered or counted as skipped, in order.
    let reader = tokio::spawn(collect_events(slow));
    server.shutdown().await.unwrap();
    let (reports, skipped) = reader.await.unwrap();
    let expected = direct_reports(&Scene::default_scene(), &fs);
    assert_eq!(reports.len() as u64 + skipped, expected.len() as u64);
    // The 16 KiB window and the server's buffers hold far fewer than 400 reports.
    if expected.len() >= 400 {
        assert!(skipped > 0, "no lag marker");
    }
    assert_eq!(
        sort_reports(reports.clone()),
        reports,
        "delivered reports keep their order"
    );
    for r in &reports {
        assert!(expected.contains(r));
    }
    let text = tofwave::telemetry::prometheus_handle().render();
    let lagged = metric_in(&text, "tofwave_subscriber_lagged_reports_total", &[]).unwrap_or(0.0);
    assert!(lagged >= skipped as f64, "{lagged} < {skipped}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_drains_in_flight_frames() {
    let config = ServerConfig {
        queue_frames: 4,
        ..Default::default()
    };
    let server = TestServer::start(config).await;
    let mut c = server.connect(None).await;
    let sub = client::subscribe(&mut c.reports, Default::default())
        .await
        .unwrap();
    let fs = frames("drain", 0..200, 10);
    let (tx, rx) = tokio::sync::mpsc::channel(64);
    for b in fs.chunks(10) {
        tx.send(batch(b)).await.unwrap();
    }
    drop(tx);
    let mut acks = c
        .ingest
        .push(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let first = acks.message().await.unwrap().unwrap();
    assert_eq!(first.accepted, 10);
    // Shut down while batches are queued behind the first one.
    let stop = tokio::spawn(server.shutdown());
    let mut accepted = first.accepted;
    loop {
        match acks.message().await {
            Ok(Some(a)) => {
                assert_eq!(a.rejected, 0);
                accepted += a.accepted;
            }
            // Clean only when every frame was acknowledged; otherwise the
            // stream says shutdown cut it off, and how many frames it left.
            Ok(None) => {
                assert_eq!(accepted, 200, "an OK end means every frame was acknowledged");
                break;
            }
            Err(e) => {
                assert_eq!(e.code(), Code::Unavailable, "{e:?}");
                assert!(e.message().contains("not acknowledged"), "{e:?}");
                break;
            }
        }
    }
    stop.await.unwrap().unwrap();
    // Every acknowledged frame was processed, and its reports reached the
    // subscriber before its stream ended.
    let (reports, skipped) = collect_events(sub).await;
    assert_eq!(skipped, 0);
    let done = &fs[..accepted as usize];
    assert_eq!(
        sort_reports(reports),
        direct_reports(&Scene::default_scene(), done)
    );
    // The endpoint is gone with the server; the process-wide registry remains.
    let text = tofwave::telemetry::prometheus_handle().render();
    let processed = metric_in(
        &text,
        "tofwave_frames_processed_total",
        &[("sensor", "drain")],
    );
    assert_eq!(processed, Some(accepted as f64));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recording_is_lossless_and_state_reloads() {
    let record = tempfile::tempdir().unwrap();
    let state = tempfile::tempdir().unwrap();
    let config = || ServerConfig {
        record_dir: Some(record.path().to_path_buf()),
        state_dir: Some(state.path().to_path_buf()),
        ..Default::default()
    };
    let server = TestServer::start(config()).await;
    let mut c = server.connect(None).await;
    let mut scene = Scene::default_scene();
    scene.name = "persisted".into();
    c.control
        .set_scene(proto::SetSceneRequest {
            sensor_id: "rec/1".into(),
            toml: scene.to_toml(),
        })
        .await
        .unwrap();
    let fs = frames("rec/1", 0..6, 11);
    let mut sent = batch(&fs);
    sent.frames[3].sample_interval_s = -1.0; // refused: not recorded
    // A sensor on the default scene: recorded, but its scene is not pinned.
    let plain = batch(&frames("plain", 0..2, 18));
    let acks = push_batches(&mut c, vec![sent, plain]).await.unwrap();
    assert_eq!((acks[0].accepted, acks[1].accepted), (5, 2));
    server.shutdown().await.unwrap();

    let all: Vec<Frame> =
        tofwave::capture::frames(&[record.path().to_path_buf()], &Default::default())
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
    assert_eq!(all.iter().filter(|f| f.sensor_id == "plain").count(), 2);
    let recorded: Vec<Frame> = all.into_iter().filter(|f| f.sensor_id == "rec/1").collect();
    let expected: Vec<Frame> = fs
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != 3)
        .map(|(_, f)| f.clone())
        .collect();
    assert_eq!(recorded, expected);

    let server = TestServer::start(config()).await;
    let mut c = server.connect(None).await;
    let got = c
        .control
        .get_scene(proto::SensorRequest {
            sensor_id: "rec/1".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(Scene::from_toml_str(&got.toml, "test").unwrap(), scene);
    let list = c
        .control
        .list_sensors(proto::ListSensorsRequest {})
        .await
        .unwrap()
        .into_inner();
    let ids: Vec<&str> = list.sensors.iter().map(|s| s.sensor_id.as_str()).collect();
    assert!(ids.contains(&"rec/1"), "{ids:?}");
    // A sensor left on the default scene comes back only through its saved
    // noise model, and still on the default scene (not pinned).
    if ids.contains(&"plain") {
        let plain = c
            .control
            .get_scene(proto::SensorRequest { sensor_id: "plain".into() })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(Scene::from_toml_str(&plain.toml, "test").unwrap(), Scene::default_scene());
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_with_token() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/tls");
    let read = |f: &str| std::fs::read(dir.join(f)).unwrap();
    let config = ServerConfig {
        tls: Some(tofwave::service::TlsPem {
            cert_pem: read("server.pem"),
            key_pem: read("server.key"),
        }),
        write_token: Some("w".into()),
        ..Default::default()
    };
    let server = TestServer::start(config).await;
    let url = server.url.replace("http://", "https://");
    let opts = ClientOptions {
        token: Some("w".into()),
        ca_cert_pem: Some(read("ca.pem")),
        tls_domain: Some("localhost".into()),
        ..Default::default()
    };
    let mut c = client::connect(&url, &opts).await.unwrap();
    let acks = push_batches(&mut c, vec![batch(&frames("tls", 0..2, 12))])
        .await
        .unwrap();
    assert_eq!(acks[0].accepted, 2);
    // Plain HTTP/2 to the TLS port fails at the transport (Unavailable,
    // Cancelled, Unknown or Internal, depending on when the server drops the
    // connection), never with an answer from a service.
    let mut plain = server.connect(Some("w")).await;
    let e = plain
        .control
        .list_sensors(proto::ListSensorsRequest {})
        .await
        .unwrap_err();
    assert!(e.source().is_some(), "a transport error: {e:?}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cli_replay_and_subscribe_round_trip() {
    use clap::Parser;
    use tofwave::service::cli::{ReplayArgs, SubscribeArgs, run_replay, run_subscribe};
    #[derive(Parser)]
    struct Replay {
        #[command(flatten)]
        args: ReplayArgs,
    }
    #[derive(Parser)]
    struct Subscribe {
        #[command(flatten)]
        args: SubscribeArgs,
    }
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("capture.twr");
    let fs = frames("cli", 0..15, 13);
    let mut w =
        tofwave::capture::RecordingWriter::new(std::fs::File::create(&capture).unwrap()).unwrap();
    for f in &fs {
        w.write_frame(f).unwrap();
    }
    let _ = w.finish();
    let server = TestServer::start(ServerConfig::default()).await;
    let out = dir.path().join("reports.jsonl");
    let sub = Subscribe::try_parse_from([
        "t",
        "--from",
        &server.url,
        "--output",
        out.to_str().unwrap(),
    ])
    .unwrap();
    let subscriber = tokio::spawn(run_subscribe(sub.args));
    // The output file exists once the subscription is registered.
    while !out.exists() {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let replay = Replay::try_parse_from([
        "t",
        "--to",
        &server.url,
        "--input",
        capture.to_str().unwrap(),
        "--rate",
        "max",
        "--quiet",
        "--batch-frames",
        "4",
    ])
    .unwrap();
    run_replay(replay.args).await.unwrap();
    server.shutdown().await.unwrap();
    subscriber.await.unwrap().unwrap();
    let lines: Vec<String> = std::fs::read_to_string(&out)
        .unwrap()
        .lines()
        .map(String::from)
        .collect();
    assert_eq!(
        sort_reports(lines),
        direct_reports(&Scene::default_scene(), &fs)
    );
    // A bad rate is refused at parse time, naming the choices.
    let e = Replay::try_parse_from(["t", "--to", "http://x", "--input", "a", "--rate", "fast"])
        .err()
        .unwrap();
    assert!(
        e.to_string().contains("realtime, max or a speed-up factor"),
        "{e}"
    );
}

#[test]
fn deploy_example_scene_is_valid() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/config/scene.toml");
    let scene = Scene::load(&path).unwrap();
    // The server's example: the default's processing sections (the default's
    // [simulation], the prototype `tofwave simulate` synthesises, is not the server's).
    let mut default = Scene::default_scene();
    default.simulation = None;
    assert_eq!(scene, default, "the example documents the default");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sensors_past_the_limit_are_refused() {
    let config = ServerConfig {
        max_sensors: 2,
        ..Default::default()
    };
    let server = TestServer::start(config).await;
    let mut c = server.connect(None).await;
    let mut fs = frames("limit-a", 0..1, 14);
    fs.extend(frames("limit-b", 0..1, 15));
    fs.extend(frames("limit-c", 0..1, 16));
    let a = &push_batches(&mut c, vec![batch(&fs)]).await.unwrap()[0];
    assert_eq!((a.accepted, a.rejected), (2, 1));
    let r = &a.rejections[0];
    assert_eq!(
        (r.sensor_id.as_str(), r.code.as_str()),
        ("limit-c", "RESOURCE_EXHAUSTED")
    );
    assert!(r.message.starts_with("frames[2].sensor_id: "), "{r:?}");
    let e = c
        .control
        .set_scene(proto::SetSceneRequest {
            sensor_id: "limit-d".into(),
            toml: String::new(),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_is_bounded_when_a_subscriber_never_reads() {
    let config = ServerConfig {
        subscriber_buffer: 8,
        drain_timeout: Duration::from_secs(1),
        ..Default::default()
    };
    let server = TestServer::start(config).await;
    let mut c = server.connect(None).await;
    // Subscribed, never read, kept open past shutdown.
    let _stuck = client::subscribe(&mut c.reports, Default::default())
        .await
        .unwrap();
    let fs = frames("stuck", 0..400, 17);
    let acks = push_batches(&mut c, fs.chunks(50).map(batch).collect())
        .await
        .unwrap();
    assert_eq!(acks.iter().map(|a| a.accepted).sum::<u64>(), 400);
    let t = std::time::Instant::now();
    server.shutdown().await.unwrap();
    // The drain deadline (1 s) plus scheduling slack.
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_streams_per_connection_are_limited() {
    let config = ServerConfig {
        max_streams_per_connection: 2,
        ..Default::default()
    };
    let server = TestServer::start(config).await;
    let mut c = server.connect(None).await;
    let first = client::subscribe(&mut c.reports, Default::default())
        .await
        .unwrap();
    let _second = client::subscribe(&mut c.reports, Default::default())
        .await
        .unwrap();
    // A third stream on the same connection waits for a free slot.
    let mut third = c.reports.clone();
    let waiting =
        tokio::spawn(async move { client::subscribe(&mut third, Default::default()).await });
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(
        !waiting.is_finished(),
        "a third concurrent stream was opened"
    );
    drop(first);
    let third = tokio::time::timeout(Duration::from_secs(5), waiting)
        .await
        .unwrap()
        .unwrap();
    assert!(third.is_ok(), "{third:?}");
    // Another connection has its own allowance.
    let mut other = server.connect(None).await;
    assert!(
        client::subscribe(&mut other.reports, Default::default())
            .await
            .is_ok()
    );
    server.shutdown().await.unwrap();
}


/// A sensor id with a NUL byte once killed the server: the worker thread was
/// named after the sensor, the OS refused the name, the session map's lock
/// was poisoned, and every later push was acknowledged with nothing. The id
/// is now refused at the wire, naming `sensor_id`, and the server carries on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sensor_id_with_nul_is_refused_and_other_sensors_continue() {
    let server = TestServer::start(ServerConfig::default()).await;
    let mut c = server.connect(None).await;
    let bad = frames("bad\0sensor", 0..1, 40);
    let acks = tokio::time::timeout(Duration::from_secs(30), push_batches(&mut c, vec![batch(&bad)]))
        .await
        .expect("the push is answered")
        .unwrap();
    assert_eq!(acks.len(), 1);
    assert_eq!((acks[0].accepted, acks[0].rejected), (0, 1), "{:?}", acks[0]);
    let r = &acks[0].rejections[0];
    assert_eq!(r.code, "INVALID_ARGUMENT", "{r:?}");
    assert!(r.message.starts_with("frames[0].sensor_id: "), "{r:?}");
    assert!(r.message.contains("control character"), "{r:?}");
    // An over-long id too, and its echo stays bounded.
    let mut long = frames("x", 0..1, 41);
    long[0].sensor_id = "L".repeat(100_000);
    let a = &push_batches(&mut c, vec![batch(&long)]).await.unwrap()[0];
    assert_eq!((a.accepted, a.rejected), (0, 1));
    assert!(a.rejections[0].message.starts_with("frames[0].sensor_id: "), "{:?}", a.rejections[0].message);
    assert!(a.rejections[0].sensor_id.len() < 100 && a.rejections[0].message.len() < 300);

    // A normal sensor, on the same connection and a new one, is processed and reported.
    let mut sub = c
        .reports
        .subscribe(proto::SubscribeRequest::default())
        .await
        .unwrap()
        .into_inner();
    let good = frames("after-nul", 0..3, 42);
    let acks = push_batches(&mut c, vec![batch(&good)]).await.unwrap();
    assert_eq!((acks[0].accepted, acks[0].rejected), (3, 0), "{:?}", acks[0]);
    let mut c2 = server.connect(None).await;
    let acks = push_batches(&mut c2, vec![batch(&frames("after-nul-2", 0..1, 43))]).await.unwrap();
    assert_eq!(acks[0].accepted, 1);
    let first = tokio::time::timeout(Duration::from_secs(30), sub.message())
        .await
        .expect("a report arrives")
        .unwrap()
        .unwrap();
    let Some(Event::Report(r)) = first.event else { panic!("a report first") };
    assert!(r.json.contains("after-nul"), "{}", r.json);
    // Control calls answer normally, and refuse a bad id by name.
    let st = c
        .control
        .get_status(proto::SensorRequest { sensor_id: "after-nul".into() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(st.frames_processed, 3);
    let e = c
        .control
        .set_scene(proto::SetSceneRequest { sensor_id: "a\0b".into(), toml: String::new() })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().starts_with("sensor_id: "), "{}", e.message());
    let e = c
        .control
        .get_status(proto::SensorRequest { sensor_id: "a\0b".into() })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    drop(sub);
    server.shutdown().await.unwrap();
}

/// Tiny sampling periods pushed over gRPC: each frame is refused by name
/// (`sample_interval_s`, at the wire or by the pipeline's resource bound),
/// never a crash, and another sensor is served normally afterwards.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiny_sample_intervals_are_refused_and_the_server_keeps_serving() {
    let server = TestServer::start(ServerConfig::default()).await;
    let mut c = server.connect(None).await;
    for (k, dt) in [1e-12, 1e-14, 1e-16, 1e-19, 1e-28, 1e-30].into_iter().enumerate() {
        let mut fs = frames("tiny-dt", k as u64..k as u64 + 1, 50 + k as u64);
        fs[0].sample_interval_s = dt;
        let acks = push_batches(&mut c, vec![batch(&fs)]).await.unwrap();
        let a = &acks[0];
        assert_eq!((a.accepted, a.rejected), (0, 1), "dt {dt:e}: {a:?}");
        let r = &a.rejections[0];
        assert_eq!(r.code, "INVALID_ARGUMENT", "dt {dt:e}: {r:?}");
        assert!(r.message.starts_with("frames[0].sample_interval_s: "), "dt {dt:e}: {r:?}");
    }
    let acks = push_batches(&mut c, vec![batch(&frames("normal-dt", 0..2, 60))]).await.unwrap();
    assert_eq!((acks[0].accepted, acks[0].rejected), (2, 0), "{:?}", acks[0]);
    // The scene refuses a pulse too wide for any template bound, by name.
    let mut doc: toml::Table = toml::from_str(&Scene::default_scene().to_toml()).unwrap();
    doc["return_pulse"]["fwhm_s"] = toml::Value::Float(1e-3);
    let toml = toml::to_string(&doc).unwrap();
    let e = c
        .control
        .set_scene(proto::SetSceneRequest { sensor_id: "normal-dt".into(), toml })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("return_pulse.fwhm_s"), "{}", e.message());
    server.shutdown().await.unwrap();
}

/// A SetScene error used to echo the whole input: a 200 KB line made a
/// 400 KB status that clients refused (RESOURCE_EXHAUSTED). The echo is
/// bounded and says how long the line was.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn set_scene_error_echo_is_bounded() {
    let server = TestServer::start(ServerConfig::default()).await;
    let mut c = server.connect(None).await;
    let toml = format!("name = {}\n", "z".repeat(200_000));
    let e = c
        .control
        .set_scene(proto::SetSceneRequest { sensor_id: "echo".into(), toml })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{}", &e.message()[..e.message().len().min(300)]);
    assert!(e.message().len() < 5000, "{} bytes", e.message().len());
    assert!(e.message().starts_with("toml: ") && e.message().contains("bytes)"), "{}", e.message());
    server.shutdown().await.unwrap();
}

/// Shutdown used to end open Push streams with OK, frames unacknowledged:
/// the stream now ends UNAVAILABLE, saying so, and the client's summary
/// counts what was sent and not acknowledged.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_ends_open_push_streams_with_unavailable() {
    let mut server = TestServer::start(ServerConfig::default()).await;
    let c = server.connect(None).await;
    let (tx, rx) = tokio::sync::mpsc::channel::<proto::FrameBatch>(4);
    let (ack_tx, mut ack_rx) = tokio::sync::mpsc::unbounded_channel();
    let mut ingest = c.ingest.clone();
    let push = tokio::spawn(async move {
        client::push(&mut ingest, ReceiverStream::new(rx), move |a| {
            let _ = ack_tx.send(a.accepted);
        })
        .await
    });
    tx.send(batch(&frames("cut", 0..3, 70))).await.unwrap();
    assert_eq!(ack_rx.recv().await, Some(3));
    // Shutdown begins with the stream open (the client still holds its sender).
    let _ = server.stop.take().unwrap().send(());
    let _ = tx.send(batch(&frames("cut", 3..5, 71))).await;
    let failed = tokio::time::timeout(Duration::from_secs(30), push)
        .await
        .expect("the stream ends")
        .unwrap()
        .expect_err("a stream cut off by shutdown is not OK");
    assert_eq!(failed.status.code(), Code::Unavailable, "{failed}");
    assert!(failed.status.message().contains("not acknowledged"), "{failed}");
    assert_eq!(failed.summary.accepted, 3, "{failed}");
    assert!(failed.summary.sent >= 3 && failed.summary.unacknowledged() == failed.summary.sent - 3, "{failed}");
    drop(tx);
    drop(c);
    tokio::time::timeout(Duration::from_secs(30), server.task)
        .await
        .expect("server drains")
        .unwrap()
        .unwrap();
}

/// A `tofwave serve` process on a free loopback port (killed on drop), its
/// gRPC URL, and its standard error collected line by line.
struct ServeProcess {
    child: std::process::Child,
    url: String,
    log: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
}

impl ServeProcess {
    fn start(args: &[&str]) -> ServeProcess {
        Self::spawn(std::process::Command::new(env!("CARGO_BIN_EXE_tofwave")), args)
    }

    /// With every file it writes limited to `blocks` × 512 bytes
    /// (`ulimit -f`, SIGXFSZ ignored): a write past the limit fails with
    /// EFBIG, as one on a full disk fails with ENOSPC.
    fn start_with_file_limit(args: &[&str], blocks: u64) -> ServeProcess {
        let mut cmd = std::process::Command::new("sh");
        cmd.args(["-c", &format!("trap '' XFSZ; ulimit -f {blocks}; exec \"$0\" \"$@\""), env!("CARGO_BIN_EXE_tofwave")]);
        Self::spawn(cmd, args)
    }

    fn spawn(mut cmd: std::process::Command, args: &[&str]) -> ServeProcess {
        use std::io::BufRead;
        let mut child = cmd
            .args(["serve", "--listen", "127.0.0.1:0"])
            .args(args)
            .env("NO_COLOR", "1")
            .env("RUST_LOG", "info")
            .stderr(std::process::Stdio::piped())
            .stdout(std::process::Stdio::null())
            .spawn()
            .expect("tofwave serve starts");
        let stderr = child.stderr.take().unwrap();
        let log: std::sync::Arc<std::sync::Mutex<Vec<String>>> = Default::default();
        let (tx, rx) = std::sync::mpsc::channel();
        let sink = log.clone();
        // Keeps draining the pipe after the address is found (a full pipe
        // would block the server's logging).
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
                if let Some(addr) = line.split("serving gRPC on ").nth(1) {
                    let _ = tx.send(addr.trim().to_string());
                }
                sink.lock().unwrap().push(line);
            }
        });
        let addr = rx.recv_timeout(Duration::from_secs(30)).unwrap_or_else(|_| panic!("no address; log: {:?}", log.lock().unwrap()));
        ServeProcess { child, url: format!("http://{addr}"), log }
    }

    /// SIGKILL: no shutdown, no flush, no save.
    fn kill_9(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

impl Drop for ServeProcess {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Frames in the recordings of `sensor` under `dir` (every file the server
/// started for it), and whether any file ended in a partial frame.
fn recorded_frames(dir: &std::path::Path, sensor: &str) -> Vec<u64> {
    let mut seqs = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().to_string();
        if !name.starts_with(&format!("{sensor}-")) {
            continue;
        }
        let file = std::fs::File::open(&path).unwrap();
        let reader = tofwave::capture::RecordingReader::new(std::io::BufReader::new(file), &path)
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        for f in reader {
            seqs.push(f.unwrap_or_else(|e| panic!("{name}: {e}")).sequence);
        }
    }
    seqs.sort_unstable();
    seqs
}

/// The durability contract: with `--record`, every frame acknowledged before
/// a kill -9 is in the recording after it (a sensor with one acknowledged
/// frame once had a 0-byte file); noise models saved within the persistence
/// period survive; the restarted server reloads the state directory.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn acknowledged_frames_survive_kill_9() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec");
    let state = dir.path().join("state");
    let args = [
        "--record",
        rec.to_str().unwrap(),
        "--state-dir",
        state.to_str().unwrap(),
        "--persist-interval-s",
        "0.1",
    ];
    let server = ServeProcess::start(&args);
    let mut c = client::connect(&server.url, &ClientOptions::default()).await.unwrap();
    // Short frames (1.2 kB) sit in the recorder's buffer: without the flush
    // before the ack they were lost (one acknowledged frame: a 0-byte file).
    let mut short = frames("one", 0..3, 1);
    for f in &mut short {
        for ch in &mut f.channels {
            if let Samples::I16(v) = &mut ch.samples {
                v.truncate(300);
            }
        }
    }
    let acks = push_batches(&mut c, vec![batch(&short[..1])]).await.unwrap();
    assert_eq!(acks.iter().map(|a| a.accepted + a.rejected).sum::<u64>(), 1);
    let many = frames("many", 0..41, 2);
    let acks = push_batches(&mut c, many[..40].chunks(8).map(batch).collect()).await.unwrap();
    assert_eq!(acks.iter().map(|a| a.accepted).sum::<u64>(), 40);
    // Past the persistence period, the next frame saves the noise model.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let acks = push_batches(&mut c, vec![batch(&many[40..])]).await.unwrap();
    assert_eq!(acks.iter().map(|a| a.accepted).sum::<u64>(), 1);
    drop(c);
    server.kill_9();
    assert_eq!(recorded_frames(&rec, "one"), vec![0]);
    assert_eq!(recorded_frames(&rec, "many"), (0..41).collect::<Vec<u64>>());
    let noise = std::fs::read(state.join("noise").join("many.pb")).expect("noise model saved before the kill");
    assert!(!noise.is_empty());
    // Restart on the same directories: the state reloads, recording goes on
    // in a new file, and the recordings of both runs read back.
    let server = ServeProcess::start(&args);
    // The reload is logged as the server starts, after it printed its address.
    // ("one" has state only if its single frame came after a persistence
    // period: not asserted.)
    let reloaded = |log: &[String]| log.iter().any(|l| l.contains("reloaded sensor state") && l.contains("sensor=many"));
    for _ in 0..100 {
        if reloaded(&server.log.lock().unwrap()) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let log = server.log.lock().unwrap().clone();
    assert!(reloaded(&log), "{log:?}");
    let mut c = client::connect(&server.url, &ClientOptions::default()).await.unwrap();
    let more = frames("many", 41..45, 3);
    let acks = push_batches(&mut c, vec![batch(&more)]).await.unwrap();
    assert_eq!(acks.iter().map(|a| a.accepted).sum::<u64>(), 4);
    drop(c);
    server.kill_9();
    assert_eq!(recorded_frames(&rec, "many"), (0..45).collect::<Vec<u64>>());
}

/// A recording that fails (here at a file-size limit, as it would on a full
/// disk) faults its sensor: its frames are refused with FAILED_PRECONDITION
/// naming the file, every acknowledged frame is in that file, health goes
/// NOT_SERVING for Ingest and for the server as a whole (Reports stays
/// SERVING), `GetStatus` says why, and the other sensors carry on.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn failed_recording_faults_its_sensor_and_health_goes_not_serving() {
    use tonic_health::pb::{HealthCheckRequest, health_check_response::ServingStatus, health_client::HealthClient};
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec");
    // 200 blocks = 100 kB per file: about nine 10 kB frames.
    let server = ServeProcess::start_with_file_limit(&["--record", rec.to_str().unwrap()], 200);
    let channel = tonic::transport::Endpoint::from_shared(server.url.clone()).unwrap().connect().await.unwrap();
    let mut health = HealthClient::new(channel);
    let status_of = |h: &mut HealthClient<tonic::transport::Channel>, service: &'static str| {
        let mut h = h.clone();
        async move {
            h.check(HealthCheckRequest { service: service.into() }).await.unwrap().into_inner().status
        }
    };
    assert_eq!(status_of(&mut health, "tofwave.v1.Ingest").await, ServingStatus::Serving as i32);
    let mut c = client::connect(&server.url, &ClientOptions::default()).await.unwrap();
    let small = frames("small", 0..4, 1);
    let acks = push_batches(&mut c, vec![batch(&small[..2])]).await.unwrap();
    assert_eq!(acks.iter().map(|a| a.accepted).sum::<u64>(), 2);

    let big = frames("big", 0..40, 2);
    // One batch at a time, so each is flushed (and acked) before the next.
    let mut acks = Vec::new();
    for chunk in big.chunks(2) {
        acks.extend(push_batches(&mut c, vec![batch(chunk)]).await.unwrap());
    }
    let accepted: u64 = acks.iter().map(|a| a.accepted).sum();
    let rejections: Vec<&proto::Rejection> = acks.iter().flat_map(|a| &a.rejections).collect();
    assert_eq!(accepted + rejections.len() as u64, 40);
    assert!((1..40).contains(&accepted), "accepted {accepted} of 40 frames");
    // The refused frames are exactly those after the last acknowledged one.
    let mut refused: Vec<u64> = rejections.iter().map(|r| r.sequence).collect();
    refused.sort_unstable();
    assert_eq!(refused, (accepted..40).collect::<Vec<u64>>());
    for r in &rejections {
        assert_eq!(r.code, "FAILED_PRECONDITION", "{r:?}");
        assert!(r.message.contains("recording") && r.message.contains("big-") && r.message.contains("not acknowledged"), "{}", r.message);
    }
    assert!(rejections.iter().any(|r| r.message.contains("File too large")), "{:?}", rejections[0].message);

    // Health follows within a moment.
    let mut ingest = ServingStatus::Serving as i32;
    for _ in 0..50 {
        ingest = status_of(&mut health, "tofwave.v1.Ingest").await;
        if ingest == ServingStatus::NotServing as i32 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(ingest, ServingStatus::NotServing as i32);
    assert_eq!(status_of(&mut health, "").await, ServingStatus::NotServing as i32);
    assert_eq!(status_of(&mut health, "tofwave.v1.Reports").await, ServingStatus::Serving as i32);
    let fault = |sensor: &str| {
        let mut control = c.control.clone();
        let sensor = sensor.to_string();
        async move {
            control.get_status(proto::SensorRequest { sensor_id: sensor }).await.unwrap().into_inner().fault
        }
    };
    let big_fault = fault("big").await;
    assert!(big_fault.contains("recording") && big_fault.contains("File too large"), "{big_fault}");
    assert_eq!(fault("small").await, "");

    // The other sensor carries on; the faulted one stays refused.
    let acks = push_batches(&mut c, vec![batch(&small[2..])]).await.unwrap();
    assert_eq!(acks.iter().map(|a| a.accepted).sum::<u64>(), 2);
    let more = frames("big", 40..41, 3);
    let acks = push_batches(&mut c, vec![batch(&more)]).await.unwrap();
    assert_eq!(acks[0].rejections.len(), 1);
    assert_eq!(acks[0].rejections[0].code, "FAILED_PRECONDITION");
    drop(c);
    server.kill_9();

    // Every acknowledged frame is in the recording (a partial frame may follow).
    let mut recorded = Vec::new();
    for entry in std::fs::read_dir(&rec).unwrap() {
        let path = entry.unwrap().path();
        if !path.file_name().unwrap().to_string_lossy().starts_with("big-") {
            continue;
        }
        let file = std::fs::File::open(&path).unwrap();
        let reader = tofwave::capture::RecordingReader::new(std::io::BufReader::new(file), &path).unwrap();
        recorded.extend(reader.map_while(Result::ok).map(|f| f.sequence));
    }
    assert!(recorded.len() as u64 >= accepted, "recorded {recorded:?}, acked 0..{accepted}");
    assert_eq!(&recorded[..accepted as usize], &(0..accepted).collect::<Vec<u64>>()[..]);
    assert_eq!(recorded_frames(&rec, "small"), vec![0, 1, 2, 3]);
}

/// `--workers-per-sensor`: one sensor's stages cut over 2 and 3 threads
/// (past both pilots, frames 201-400 and 2001-2200, with averaging groups
/// in flight and one open across the hand-back at frame 2000) report
/// exactly what the pipeline run directly does, in order.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sensor_on_several_workers_reports_what_one_thread_does() {
    let mut scene = Scene::default_scene();
    scene.averaging.frames = 3;
    let all = frames("wps", 0..2400, 9);
    let want = direct_reports(&scene, &all);
    assert_eq!(want.len(), 800);
    for workers in [2, 3] {
        let config = ServerConfig { scene: scene.clone(), workers_per_sensor: workers, queue_frames: 256, ..ServerConfig::default() };
        let server = TestServer::start(config).await;
        let mut c = server.connect(None).await;
        let sub = client::subscribe(&mut c.reports, Default::default()).await.unwrap();
        let source = all.clone().into_iter().map(Ok::<_, std::convert::Infallible>);
        let limits = BatchLimits { frames: 32, bytes: 1 << 22 };
        let summary = client::replay(&mut c.ingest, source, Rate::Max, None, limits, |_| {}).await.unwrap();
        assert_eq!((summary.accepted, summary.rejected), (2400, 0), "{workers} workers: {summary}");
        server.shutdown().await.unwrap();
        let (reports, skipped) = collect_events(sub).await;
        assert_eq!(skipped, 0);
        assert_eq!(reports.len(), want.len(), "{workers} workers");
        for (i, (a, b)) in reports.iter().zip(&want).enumerate() {
            assert_eq!(a, b, "{workers} workers: report {i} differs from the direct run");
        }
    }
}

/// A client that waits for each batch's ack before it sends the next (and
/// one that keeps two batches ahead): the worker holds verdicts and reports
/// while frames are queued, and must still release each batch's once its
/// frames are done, on one thread and with the stages on two (past the
/// pilot, frames in flight there). A hold that waited for frames that never
/// come hangs this test (each ack has 60 s).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn acks_of_a_lock_step_client_come_whatever_the_workers() {
    let all = frames("lockstep", 0..460, 4);
    let want = direct_reports(&Scene::default_scene(), &all);
    for (workers, ahead) in [(1, 1), (2, 1), (2, 2)] {
        let config = ServerConfig { workers_per_sensor: workers, ..ServerConfig::default() };
        let server = TestServer::start(config).await;
        let mut c = server.connect(None).await;
        let sub = client::subscribe(&mut c.reports, Default::default()).await.unwrap();
        // Batches of 1, 7 and 32 frames in turn.
        let mut batches = Vec::new();
        let mut rest = &all[..];
        for size in [1usize, 7, 32].into_iter().cycle() {
            if rest.is_empty() {
                break;
            }
            let (b, r) = rest.split_at(size.min(rest.len()));
            batches.push(batch(b));
            rest = r;
        }
        let sizes: Vec<u64> = batches.iter().map(|b| b.frames.len() as u64).collect();
        let (tx, rx) = tokio::sync::mpsc::channel(8);
        let mut acks = c.ingest.push(ReceiverStream::new(rx)).await.unwrap().into_inner();
        let mut to_send = batches.into_iter();
        for b in to_send.by_ref().take(ahead) {
            tx.send(b).await.unwrap();
        }
        for (k, size) in sizes.iter().enumerate() {
            let ack = tokio::time::timeout(std::time::Duration::from_secs(60), acks.message())
                .await
                .unwrap_or_else(|_| panic!("{workers} workers, {ahead} ahead: no ack for batch {k} in 60 s"))
                .unwrap()
                .unwrap();
            assert_eq!((ack.accepted, ack.rejected), (*size, 0), "{workers} workers, {ahead} ahead: batch {k}");
            if let Some(b) = to_send.next() {
                tx.send(b).await.unwrap();
            }
        }
        drop(tx);
        server.shutdown().await.unwrap();
        let (reports, skipped) = collect_events(sub).await;
        assert_eq!(skipped, 0);
        assert_eq!(reports, want, "{workers} workers, {ahead} ahead: the reports, in order");
    }
}
