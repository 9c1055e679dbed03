//! gRPC services over the wire contract. Only [`wire`](crate::wire) knows the
//! generated message types; only this module knows tonic (transport, stubs,
//! `Status`).
//!
//! Reading order (paths are absolute because `lib.rs` documents this module too):
//! - [`run`](crate::service::run) wires everything and owns shutdown;
//! - [`session`](crate::service::session): one sensor's pipeline on its own
//!   worker thread behind a bounded queue;
//! - [`ingest`](crate::service::ingest): frame batches in, queued frames and
//!   acknowledgements out;
//! - [`fanout`](crate::service::fanout) spreads reports to subscribers
//!   ([`subscribe`](crate::service::subscribe));
//! - [`control`](crate::service::control) reads and changes sensor state;
//! - [`auth`](crate::service::auth) checks bearer tokens;
//! - [`dashboard`](crate::service::dashboard) serves the browser dashboard
//!   (server-sent events from the same fan-out, waveform snapshots);
//! - `status` is the one place that maps errors to gRPC `Status`;
//! - [`state`](crate::service::state) persists scenes and noise models;
//! - [`cluster`](crate::service::cluster): `serve --cluster`, nodes sharing
//!   sensors over NATS JetStream (only reached when the flag is given);
//! - [`client`](crate::service::client) is the library side of `tofwave replay`
//!   and `tofwave subscribe` ([`cli`](crate::service::cli)).

/// Generated gRPC client and server stubs of `tofwave.v1` (tonic); their
/// messages are [`wire::proto`](crate::wire::proto).
#[allow(missing_docs, clippy::all)]
pub mod grpc {
    include!(concat!(env!("OUT_DIR"), "/grpc/tofwave.v1.rs"));

    /// Encoded file descriptor set, for gRPC reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        tonic::include_file_descriptor_set!("tofwave_descriptor");
}

pub mod auth;
pub mod cli;
pub mod client;
pub mod cluster;
pub mod control;
pub mod dashboard;
pub mod fanout;
pub mod ingest;
mod metrics_http;
pub mod session;
pub mod state;
mod status;
pub mod subscribe;

use crate::scene::Scene;
use std::future::Future;
use std::path::PathBuf;
use std::sync::Arc;
use tokio::net::TcpListener;
use tokio_stream::wrappers::TcpListenerStream;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tonic::transport::{Identity, Server, ServerTlsConfig};

/// Everything `run` needs besides the listener. [`ServerConfig::default`] is a
/// usable open server on the embedded default scene.
pub struct ServerConfig {
    /// Scene for sensors that have none of their own (new sensors, and `SetScene`
    /// with an empty sensor id changes it).
    pub scene: Scene,
    /// Bearer token for ingest and control; `None` leaves them open.
    pub write_token: Option<String>,
    /// Read-only bearer token: subscribe only. When either token is set,
    /// subscribing needs one of them.
    pub read_token: Option<String>,
    /// PEM certificate chain and private key: serve gRPC over TLS.
    pub tls: Option<TlsPem>,
    /// Largest gRPC message accepted, bytes. Bigger ingest messages end that
    /// stream with `INVALID_ARGUMENT` (the server and other streams stay up).
    pub max_message_bytes: usize,
    /// Concurrent HTTP/2 streams allowed per client connection.
    pub max_streams_per_connection: u32,
    /// Frames queued per sensor before ingest waits (backpressure), frames.
    pub queue_frames: usize,
    /// Threads one sensor's pipeline runs on: its stages are cut into this
    /// many consecutive segments once the first 400 frames have timed them,
    /// and cut again by the times of frames 2001-2200 (reports identical to
    /// one thread's, in order).
    pub workers_per_sensor: usize,
    /// Sensors served at most; frames of further sensor ids are refused
    /// (`RESOURCE_EXHAUSTED`), since each sensor holds a thread and a pipeline.
    pub max_sensors: usize,
    /// Reports retained per sensor for `resume_from_sequence`, reports.
    pub history_reports: usize,
    /// Reports buffered for subscribers before a slow one is told it lagged, reports.
    pub subscriber_buffer: usize,
    /// Serve Prometheus text on `GET /metrics` here.
    pub metrics_listener: Option<TcpListener>,
    /// Serve the browser dashboard (page + server-sent events) here.
    pub dashboard_listener: Option<TcpListener>,
    /// Waveform snapshots per sensor per second at most, while a dashboard
    /// client is connected (0: none).
    pub dashboard_snapshots_per_s: f64,
    /// Persist per-sensor scenes and noise models here and reload them at start.
    pub state_dir: Option<PathBuf>,
    /// Write every accepted frame losslessly to one recording per sensor here.
    pub record_dir: Option<PathBuf>,
    /// Longest wait, after shutdown begins, for clients to take their last
    /// acks and reports before `run` returns anyway.
    pub drain_timeout: std::time::Duration,
    /// What an ack promises about the recording; how often noise models are saved.
    pub durability: session::Durability,
    /// Join a cluster over NATS JetStream (`serve --cluster`): frames go to
    /// JetStream and the sensor's owner node processes them. `None`: this
    /// server processes what it receives (the default; no NATS code runs).
    pub cluster: Option<cluster::ClusterConfig>,
}

/// TLS identity in PEM.
#[derive(Clone)]
pub struct TlsPem {
    /// Certificate chain, PEM.
    pub cert_pem: Vec<u8>,
    /// Private key, PEM.
    pub key_pem: Vec<u8>,
}

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            scene: Scene::default_scene(),
            write_token: None,
            read_token: None,
            tls: None,
            max_message_bytes: DEFAULT_MAX_MESSAGE_BYTES,
            max_streams_per_connection: 64,
            queue_frames: 64,
            workers_per_sensor: 1,
            max_sensors: 256,
            history_reports: 1024,
            subscriber_buffer: 1024,
            metrics_listener: None,
            dashboard_listener: None,
            dashboard_snapshots_per_s: dashboard::DEFAULT_SNAPSHOTS_PER_S,
            state_dir: None,
            record_dir: None,
            drain_timeout: std::time::Duration::from_secs(20),
            durability: session::Durability::default(),
            cluster: None,
        }
    }
}

/// Default message limit: 16 MiB holds ~1600 frames of two 2500-sample i16 channels.
pub const DEFAULT_MAX_MESSAGE_BYTES: usize = 16 * 1024 * 1024;

/// Largest HTTP/2 DATA frame a peer may send us, bytes (h2's default is
/// 16 KiB). A batch of 32 reference frames is about 330 kB: in 16 KiB frames
/// that is 20 writes by the client and as many reads here, each a syscall
/// and a trip through the TCP stack; in 1 MiB frames, one or two.
pub(crate) const MAX_H2_FRAME: u32 = 1024 * 1024;

/// Errors that stop the server (bad set-up); data-path errors never do.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The gRPC transport failed (TLS set-up, listener).
    #[error("gRPC transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    /// The state directory could not be read or written.
    #[error("state directory: {0}")]
    State(#[from] state::StateError),
    /// A recording could not be created.
    #[error("recording {path}: {message}")]
    Record {
        /// File.
        path: String,
        /// Cause.
        message: String,
    },
    /// A server task failed unexpectedly (a panic).
    #[error("internal: {0}")]
    Internal(String),
    /// The cluster could not be joined.
    #[error("cluster: {0}")]
    Cluster(#[from] cluster::ClusterError),
    /// The reflection service could not be built from the descriptors.
    #[error("gRPC reflection: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// A scene could not be applied (pipeline construction failed).
    #[error("sensor {sensor}: {message}")]
    Scene {
        /// Sensor id.
        sensor: String,
        /// Cause.
        message: String,
    },
}

/// Locks `m`, recovering from poisoning. Every mutex of the service guards
/// data that stays consistent whatever point a panic interrupts (each
/// critical section is one assignment, insert, take or push), so a panic
/// elsewhere while a guard was held must not turn every later call into a
/// panic: the lock is simply taken again.
pub(crate) fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Shared state of one server: sessions, fan-out and configuration.
pub(crate) struct Shared {
    /// Per-sensor sessions.
    pub(crate) sessions: session::Sessions,
    /// Report fan-out and history.
    pub(crate) hub: Arc<fanout::Hub>,
    /// Cancelled once, when shutdown begins: streams stop taking new work.
    pub(crate) shutdown: CancellationToken,
    /// Long-lived tasks (ingest streams, the metrics endpoint): after the
    /// drain, `run` waits until every one has ended. (A subscription is a
    /// stream gRPC polls; it ends when the hub closes, within tonic's own
    /// graceful shutdown.)
    pub(crate) tasks: TaskTracker,
    /// The cluster this server is a node of (`serve --cluster`): ingest
    /// publishes frames to JetStream instead of queueing them locally.
    pub(crate) cluster: Option<Arc<cluster::Cluster>>,
}

/// Serves Ingest, Reports and Control (plus health and reflection) on
/// `listener` until `shutdown` resolves, then drains: ingest streams finish the
/// batch in hand and end, every queued frame is processed (partial averages
/// flushed), their reports reach subscribers, subscriber streams end cleanly,
/// and noise models are saved to the state directory (scenes are saved when set).
pub async fn run(
    listener: TcpListener,
    config: ServerConfig,
    shutdown: impl Future,
) -> Result<(), ServiceError> {
    let local = listener.local_addr().ok();
    let shutdown_begun = CancellationToken::new();
    let tasks = TaskTracker::new();

    let hub = Arc::new(fanout::Hub::new(
        config.subscriber_buffer,
        config.history_reports,
    ));
    let state_dir = config.state_dir.clone().map(state::StateDir::new);
    // Snapshots exist only with a dashboard: without one, pipelines get no observer.
    let snapshots = config
        .dashboard_listener
        .as_ref()
        .map(|_| dashboard::Snapshots::new(config.dashboard_snapshots_per_s));
    let sessions = session::Sessions::new(
        config.scene.clone(),
        config.queue_frames,
        config.max_sensors,
        hub.clone(),
        state_dir,
        config.record_dir.clone(),
        config.durability,
        snapshots.clone(),
        config.workers_per_sensor,
    )?;
    // Cluster mode: join before serving, so the reports feed exists before
    // the first subscriber; the node's work runs until the drain stops it.
    let mut cluster_work = None;
    let cluster = match &config.cluster {
        None => None,
        Some(c) => {
            let node = cluster::Cluster::connect(c.clone(), config.scene.clone()).await?;
            node.start_feed(hub.clone(), shutdown_begun.clone()).await?;
            let stop = CancellationToken::new();
            cluster_work = Some((stop.clone(), tokio::spawn(node.clone().run(stop))));
            Some(node)
        }
    };
    let shared = Arc::new(Shared {
        sessions,
        hub: hub.clone(),
        shutdown: shutdown_begun.clone(),
        tasks: tasks.clone(),
        cluster,
    });

    let auth = auth::Tokens::new(config.write_token.clone(), config.read_token.clone());
    let limit = config.max_message_bytes;
    use tonic::service::interceptor::InterceptedService;
    let ingest = InterceptedService::new(
        grpc::ingest_server::IngestServer::new(ingest::IngestService::new(shared.clone(), limit))
            .max_decoding_message_size(limit),
        auth.interceptor(auth::Access::Write),
    );
    let reports = InterceptedService::new(
        grpc::reports_server::ReportsServer::new(subscribe::ReportsService::new(shared.clone()))
            .max_decoding_message_size(limit),
        auth.interceptor(auth::Access::Read),
    );
    let control = InterceptedService::new(
        grpc::control_server::ControlServer::new(control::ControlService::new(shared.clone()))
            .max_decoding_message_size(limit),
        auth.interceptor(auth::Access::Write),
    );

    let (health, health_svc) = tonic_health::server::health_reporter();
    health
        .set_serving::<grpc::ingest_server::IngestServer<ingest::IngestService>>()
        .await;
    health
        .set_serving::<grpc::reports_server::ReportsServer<subscribe::ReportsService>>()
        .await;
    health
        .set_serving::<grpc::control_server::ControlServer<control::ControlService>>()
        .await;
    // A faulted sensor (its recording failed: acks could no longer mean
    // "recorded"; or its worker stopped) makes the server unfit to take
    // frames: Ingest and the server as a whole ("") go NOT_SERVING until a
    // restart, so probes and load balancers act. Reports and Control stay
    // SERVING (subscribers keep reading; operators can inspect GetStatus).
    {
        let health = health.clone();
        let mut signal = shared.sessions.fault_signal();
        let shared = shared.clone();
        let stop = shutdown_begun.clone();
        tasks.spawn(async move {
            loop {
                tokio::select! {
                    changed = signal.changed() => if changed.is_err() { return },
                    _ = stop.cancelled() => return,
                }
                let faulted = shared.sessions.faulted();
                if faulted.is_empty() {
                    continue;
                }
                for (sensor, reason) in &faulted {
                    tracing::error!(%sensor, %reason, "health: NOT_SERVING (restart the server once the cause is fixed)");
                }
                health
                    .set_not_serving::<grpc::ingest_server::IngestServer<ingest::IngestService>>()
                    .await;
                health
                    .set_service_status("", tonic_health::ServingStatus::NotServing)
                    .await;
            }
        });
    }
    // v1 for current grpcurl/grpcui, v1alpha for older tools.
    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(grpc::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let reflection_v1 = reflection().build_v1().map_err(ServiceError::Reflection)?;
    let reflection_v1alpha = reflection()
        .build_v1alpha()
        .map_err(ServiceError::Reflection)?;

    let dashboard_task = match (config.dashboard_listener, snapshots) {
        (Some(l), Some(snapshots)) => {
            let dash = Arc::new(dashboard::Dashboard {
                shared: shared.clone(),
                tokens: auth.clone(),
                snapshots,
            });
            Some(tasks.spawn(dashboard::serve(l, dash, shutdown_begun.clone())))
        }
        _ => None,
    };
    let metrics_task = config.metrics_listener.map(|l| {
        let handle = crate::telemetry::prometheus_handle();
        tasks.spawn(metrics_http::serve(l, handle, shutdown_begun.clone()))
    });
    // Make sure the recorder exists even without an endpoint, so counters count.
    let _ = crate::telemetry::prometheus_handle();
    // Histogram samples wait in the recorder until a render or an upkeep
    // drains them into buckets: with no /metrics scrape they piled up, about
    // 8 bytes per frame without bound (found by `tofwave bench --soak`).
    {
        let handle = crate::telemetry::prometheus_handle();
        let stop = shutdown_begun.clone();
        tasks.spawn(async move {
            let mut tick = tokio::time::interval(std::time::Duration::from_secs(5));
            loop {
                tokio::select! {
                    _ = tick.tick() => handle.run_upkeep(),
                    _ = stop.cancelled() => return,
                }
            }
        });
    }

    let mut builder = Server::builder()
        .max_concurrent_streams(config.max_streams_per_connection)
        .http2_keepalive_interval(Some(std::time::Duration::from_secs(30)))
        // Batches are hundreds of kB: h2's 64 KiB default window would cost a
        // round trip per 64 KiB. 2 MiB per stream still bounds what a client
        // can push ahead of the pipeline (backpressure).
        .initial_stream_window_size(2 * 1024 * 1024)
        .initial_connection_window_size(4 * 1024 * 1024)
        .max_frame_size(MAX_H2_FRAME);
    if let Some(tls) = &config.tls {
        builder = builder.tls_config(
            ServerTlsConfig::new().identity(Identity::from_pem(&tls.cert_pem, &tls.key_pem)),
        )?;
    }
    let router = builder
        .add_service(health_svc)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(ingest)
        .add_service(reports)
        .add_service(control);

    tracing::info!(addr = ?local, tls = config.tls.is_some(), "serving");
    if config.write_token.as_deref().is_none_or(str::is_empty) {
        tracing::warn!("no write token: anyone who can connect may ingest and change scenes");
    }
    // The drainer runs once shutdown begins, concurrently with tonic's graceful
    // shutdown, which waits for the streams the drainer ends.
    let drain_shared = shared.clone();
    let drain_begun = shutdown_begun.clone();
    let drainer = tokio::spawn(async move {
        drain_begun.cancelled().await;
        drain(drain_shared, cluster_work).await
    });
    drop(shared);

    let begin = shutdown_begun.clone();
    let serve = router.serve_with_incoming_shutdown(TcpListenerStream::new(listener), async move {
        shutdown.await;
        tracing::info!("shutdown: draining");
        // Load balancers stop sending new work while the drain runs.
        health
            .set_not_serving::<grpc::ingest_server::IngestServer<ingest::IngestService>>()
            .await;
        health
            .set_not_serving::<grpc::control_server::ControlServer<control::ControlService>>()
            .await;
        begin.cancel();
    });
    tokio::pin!(serve);
    // Phase 1: serve until shutdown begins (or the transport fails).
    tokio::select! {
        served = &mut serve => {
            // The transport ended by itself: still drain what was accepted.
            shutdown_begun.cancel();
            let drained = tokio::time::timeout(config.drain_timeout, drainer).await;
            served?;
            return match drained {
                Ok(Ok(r)) => r,
                Ok(Err(e)) => Err(ServiceError::Internal(format!("drain task: {e}"))),
                Err(_) => Ok(()),
            };
        }
        _ = shutdown_begun.cancelled() => {}
    }
    // Phase 2: drain, bounded. Clients that stop reading can hold their
    // streams (and so tonic's graceful shutdown) open forever; past the
    // deadline `run` returns and leaves them to the runtime's end.
    let drain_timeout = config.drain_timeout;
    let finished = tokio::time::timeout(drain_timeout, async {
        let served = serve.await;
        let drained = drainer.await;
        // Every long-lived task has ended once this returns.
        tasks.close();
        tasks.wait().await;
        (served, drained)
    })
    .await;
    if let Some(t) = metrics_task {
        t.abort();
    }
    if let Some(t) = dashboard_task {
        t.abort();
    }
    match finished {
        Ok((served, drained)) => {
            served?;
            drained.map_err(|e| ServiceError::Internal(format!("drain task: {e}")))?
        }
        Err(_) => {
            tracing::warn!(
                ?drain_timeout,
                "shutdown: clients still connected at the drain deadline"
            );
            Ok(())
        }
    }
}

/// Shutdown order: ingest streams finish their batch and end (counted by
/// `sessions.wait_ingest_idle`), then sessions close their
/// queues and their workers process what is queued and flush, then the hub
/// closes so subscribers receive the last reports and see their streams end.
async fn drain(
    shared: Arc<Shared>,
    cluster_work: Option<(CancellationToken, tokio::task::JoinHandle<()>)>,
) -> Result<(), ServiceError> {
    shared.sessions.wait_ingest_idle().await;
    // Cluster mode: owners report the frames in hand and release their
    // sensors (other nodes take them over at once); the node leaves.
    if let Some((stop, work)) = cluster_work {
        stop.cancel();
        let _ = work.await;
    }
    let result = shared.sessions.close_all().await;
    shared.hub.close();
    tracing::info!("shutdown: drained");
    result
}
