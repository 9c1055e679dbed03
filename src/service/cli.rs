//! Command-line pieces of `tofwave serve`, `tofwave replay` and
//! `tofwave subscribe`; `main.rs` parses and calls these.

use super::client::{self, BatchLimits, ClientOptions, Rate};
use super::{ServerConfig, TlsPem};
use crate::capture;
use crate::scene::Scene;
use crate::wire::proto;
use anyhow::Context;
use std::io::Write;
use std::net::SocketAddr;
use std::path::PathBuf;

/// `tofwave serve`: run the gRPC server.
#[derive(Debug, clap::Args)]
pub struct ServeArgs {
    /// Scene TOML for sensors without their own scene [default: the embedded prototype scene].
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// Address to serve gRPC on (host:port).
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:50051")]
    pub listen: SocketAddr,
    /// Bearer token required for ingest and control (unset: open).
    #[arg(
        long,
        env = "TOFWAVE_TOKEN",
        hide_env_values = true,
        value_name = "TOKEN"
    )]
    pub token: Option<String>,
    /// Read-only bearer token: allows subscribe only.
    #[arg(
        long,
        env = "TOFWAVE_READ_TOKEN",
        hide_env_values = true,
        value_name = "TOKEN"
    )]
    pub read_token: Option<String>,
    /// TLS certificate chain (PEM); with --tls-key, serve over TLS.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// TLS private key (PEM).
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Serve Prometheus metrics on http://ADDR/metrics (host:port).
    #[arg(long, value_name = "ADDR")]
    pub metrics: Option<SocketAddr>,
    /// Serve the live dashboard (a page for the browser: range strip chart, waveform with
    /// gates, threshold and detections, noise model, false-alarm rate, sensor health) on
    /// http://ADDR/ (host:port; port 0 picks a free one, printed at start). Fed by server-sent
    /// events from the report stream; needs the read token (?token=) when one is set.
    #[arg(long, value_name = "ADDR")]
    pub dashboard: Option<SocketAddr>,
    /// With --dashboard: waveform snapshots per sensor per second at most, taken only while a
    /// dashboard page is open (0: none), snapshots/s.
    #[arg(long, value_name = "PER_S", default_value_t = super::dashboard::DEFAULT_SNAPSHOTS_PER_S)]
    pub dashboard_snapshots_per_s: f64,
    /// Persist per-sensor scenes and noise models here; reloaded at start.
    #[arg(long, value_name = "DIR")]
    pub state_dir: Option<PathBuf>,
    /// Record every accepted frame losslessly (tofwave recording format), one file per sensor.
    /// An acknowledged frame is in its recording (see --record-sync).
    #[arg(long, value_name = "DIR")]
    pub record: Option<PathBuf>,
    /// With --record, before frames are acknowledged: "flush" writes them to the operating
    /// system (they survive the server being killed, kill -9), "fsync" also syncs them to the
    /// storage device (they survive a power cut; one sync per acknowledged batch).
    #[arg(long, value_enum, value_name = "POLICY", default_value = "flush")]
    pub record_sync: super::session::RecordSync,
    /// With --state-dir, save each sensor's noise model at most this often while frames arrive
    /// (and at shutdown), seconds; written atomically (temporary file, sync, rename).
    #[arg(long, value_name = "SECONDS", default_value_t = 10.0)]
    pub persist_interval_s: f64,
    /// Largest gRPC message accepted, bytes; a bigger ingest message ends that stream with INVALID_ARGUMENT.
    #[arg(long, value_name = "BYTES", default_value_t = super::DEFAULT_MAX_MESSAGE_BYTES)]
    pub max_message_bytes: usize,
    /// Concurrent gRPC streams allowed per client connection.
    #[arg(long, value_name = "N", default_value_t = 64)]
    pub max_streams_per_connection: u32,
    /// Frames queued per sensor before ingest waits (backpressure), frames.
    #[arg(long, value_name = "FRAMES", default_value_t = 64)]
    pub queue_frames: usize,
    /// Threads each sensor's pipeline runs on, threads. A sensor's frames
    /// run on one worker thread at 1; with N > 1 its stages are cut into N
    /// consecutive segments, one thread each, cut where the times measured
    /// on one thread balance best: on its frames 201-400, and again on
    /// frames 2001-2200, once start-up has passed. Reports are identical to one
    /// thread's and in order; each frame is acknowledged once its report is
    /// out. Worth it when one sensor's frame rate exceeds what one core
    /// processes (see `tofwave bench`); more threads than stages add nothing
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub workers_per_sensor: u32,
    /// Sensors served at most (each holds a worker thread and a pipeline), sensors.
    #[arg(long, value_name = "N", default_value_t = 256)]
    pub max_sensors: usize,
    /// Longest wait after Ctrl-C/SIGTERM for clients to take their last acks and reports, seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 20.0)]
    pub drain_timeout_s: f64,
    /// Reports a subscriber may fall behind before it is told it lagged, reports.
    /// Reports go out in groups of up to 32: a buffer smaller than that can
    /// tell a subscriber that keeps up that it lagged.
    #[arg(long, value_name = "REPORTS", default_value_t = 1024)]
    pub subscriber_buffer: usize,
    /// Reports retained per sensor for subscribers resuming from a sequence number, reports.
    #[arg(long, value_name = "REPORTS", default_value_t = 1024)]
    pub history_reports: usize,
    /// Join a cluster over NATS JetStream (nats://HOST:PORT; comma-separate several servers):
    /// frames pushed to any node are stored in JetStream (an ack means stored), each sensor is
    /// processed by one node at a time, and Subscribe on any node sees every sensor's reports
    /// (also on the NATS subjects tofwave.reports.<sensor>). Without it, nothing of this runs.
    #[arg(long, value_name = "URL")]
    pub cluster: Option<String>,
    /// With --cluster: this node's id, unique in the cluster [default: the host name and process id].
    #[arg(long, value_name = "ID", requires = "cluster")]
    pub node_id: Option<String>,
    /// With --cluster: a sensor whose owner stops renewing its lease (killed, cut off) moves to
    /// another node after this long; leases are renewed every third of it, seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = super::cluster::DEFAULT_LEASE_TTL_S, requires = "cluster")]
    pub lease_ttl_s: f64,
    /// With --cluster: copies JetStream keeps of the streams and buckets this node creates
    /// (1 for one NATS server; 3 for a 3-server NATS cluster, which then survives losing one).
    #[arg(long, value_name = "N", default_value_t = 1, requires = "cluster")]
    pub cluster_replicas: usize,
}

/// Client connection flags shared by replay and subscribe.
#[derive(Debug, clap::Args)]
pub struct ConnectArgs {
    /// CA certificate (PEM) that signed the server's certificate, for https:// URLs.
    #[arg(long, value_name = "FILE")]
    pub ca_cert: Option<PathBuf>,
    /// Server name to check in its certificate [default: the URL's host].
    #[arg(long, value_name = "NAME")]
    pub tls_domain: Option<String>,
}

/// `tofwave replay`: stream captures to a running server.
#[derive(Debug, clap::Args)]
pub struct ReplayArgs {
    /// Server URL (http://host:port or https://host:port).
    #[arg(long, value_name = "URL")]
    pub to: String,
    /// Capture files or directories (all captures inside, in name order).
    #[arg(long, value_name = "PATH", required = true, num_args = 1..)]
    pub input: Vec<PathBuf>,
    /// Pace: "realtime" (recorded trigger spacing), "max" (as fast as accepted) or a speed-up factor (2 = twice as fast).
    #[arg(long, value_name = "RATE", default_value = "realtime")]
    pub rate: Rate,
    /// Sensor id to send the frames as [default: the id in the capture, or "replay"].
    #[arg(long, value_name = "ID")]
    pub sensor: Option<String>,
    /// Capture format (auto detects).
    #[arg(long, value_name = "FORMAT", default_value = "auto")]
    pub format: String,
    /// Frames per gRPC message at most, frames.
    #[arg(long, value_name = "N", default_value_t = 64)]
    pub batch_frames: usize,
    /// Encoded bytes per gRPC message at most (keep below the server's --max-message-bytes), bytes.
    #[arg(long, value_name = "BYTES", default_value_t = 4 * 1024 * 1024)]
    pub batch_bytes: usize,
    /// Bearer token for ingest.
    #[arg(
        long,
        env = "TOFWAVE_TOKEN",
        hide_env_values = true,
        value_name = "TOKEN"
    )]
    pub token: Option<String>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// TLS options.
    #[command(flatten)]
    pub connect: ConnectArgs,
}

/// `tofwave subscribe`: print live reports as JSON lines.
#[derive(Debug, clap::Args)]
pub struct SubscribeArgs {
    /// Server URL (http://host:port or https://host:port).
    #[arg(long, value_name = "URL")]
    pub from: String,
    /// Only these sensors (repeatable) [default: all].
    #[arg(long = "sensor", value_name = "ID")]
    pub sensors: Vec<String>,
    /// Keep only returns with at least this SNR, dB (reports are still printed).
    #[arg(long, value_name = "DB")]
    pub min_snr_db: Option<f64>,
    /// First print retained reports from this sequence number on, then live ones.
    #[arg(long, value_name = "SEQ")]
    pub resume_from: Option<u64>,
    /// Where to write the JSON lines ("-": stdout).
    #[arg(long, value_name = "FILE", default_value = "-")]
    pub output: PathBuf,
    /// Bearer token (the read-only token suffices).
    #[arg(
        long,
        env = "TOFWAVE_READ_TOKEN",
        hide_env_values = true,
        value_name = "TOKEN"
    )]
    pub token: Option<String>,
    /// TLS options.
    #[command(flatten)]
    pub connect: ConnectArgs,
}

fn read_file(path: &PathBuf, what: &str) -> anyhow::Result<Vec<u8>> {
    std::fs::read(path).with_context(|| format!("reading {what} {}", path.display()))
}

impl ServeArgs {
    /// The server configuration these flags describe (files read, listeners not bound).
    pub fn config(&self) -> anyhow::Result<ServerConfig> {
        // An empty token would read as "set" to an operator and as "open" to
        // the server: refuse it rather than serve without authentication.
        for (flag, token) in [("--token (TOFWAVE_TOKEN)", &self.token), ("--read-token (TOFWAVE_READ_TOKEN)", &self.read_token)] {
            if token.as_deref().is_some_and(|t| t.trim().is_empty()) {
                anyhow::bail!("{flag}: the token is empty; give a non-empty token, or leave the option unset to serve without one");
            }
        }
        let per_s = self.dashboard_snapshots_per_s;
        if !(per_s.is_finite() && (0.0..=60.0).contains(&per_s)) {
            anyhow::bail!("--dashboard-snapshots-per-s {per_s}: give a number of snapshots per second from 0 (none) to 60");
        }
        let scene = match &self.scene {
            Some(p) => Scene::load(p)?,
            None => Scene::default_scene(),
        };
        let tls = match (&self.tls_cert, &self.tls_key) {
            (Some(c), Some(k)) => Some(TlsPem {
                cert_pem: read_file(c, "TLS certificate")?,
                key_pem: read_file(k, "TLS key")?,
            }),
            _ => None,
        };
        let cluster = match &self.cluster {
            None => None,
            Some(url) => {
                if !(self.lease_ttl_s.is_finite() && (0.3..=3600.0).contains(&self.lease_ttl_s)) {
                    anyhow::bail!("--lease-ttl-s {}: give a number of seconds from 0.3 to 3600", self.lease_ttl_s);
                }
                let node_id = match &self.node_id {
                    Some(id) if id.trim().is_empty() => anyhow::bail!("--node-id: the id is empty"),
                    Some(id) => id.clone(),
                    None => {
                        let host = std::fs::read_to_string("/etc/hostname")
                            .ok()
                            .map(|h| h.trim().to_string())
                            .filter(|h| !h.is_empty())
                            .or_else(|| std::env::var("HOSTNAME").ok())
                            .unwrap_or_else(|| "node".into());
                        format!("{host}-{}", std::process::id())
                    }
                };
                Some(super::cluster::ClusterConfig {
                    url: url.clone(),
                    node_id,
                    lease_ttl: std::time::Duration::from_secs_f64(self.lease_ttl_s),
                    replicas: self.cluster_replicas.clamp(1, 5),
                })
            }
        };
        Ok(ServerConfig {
            cluster,
            scene,
            write_token: self.token.clone(),
            read_token: self.read_token.clone(),
            tls,
            max_message_bytes: self.max_message_bytes,
            max_streams_per_connection: self.max_streams_per_connection,
            queue_frames: self.queue_frames,
            workers_per_sensor: self.workers_per_sensor as usize,
            max_sensors: self.max_sensors,
            history_reports: self.history_reports,
            subscriber_buffer: self.subscriber_buffer,
            metrics_listener: None,
            dashboard_listener: None,
            dashboard_snapshots_per_s: per_s,
            state_dir: self.state_dir.clone(),
            record_dir: self.record.clone(),
            drain_timeout: std::time::Duration::try_from_secs_f64(self.drain_timeout_s)
                .context("--drain-timeout-s: a number of seconds >= 0")?,
            durability: super::session::Durability {
                record_sync: self.record_sync,
                persist_interval: std::time::Duration::try_from_secs_f64(self.persist_interval_s)
                    .context("--persist-interval-s: a number of seconds >= 0")?,
            },
        })
    }
}

/// Runs the server until Ctrl-C (or SIGTERM), then drains and returns.
pub async fn run_serve(args: ServeArgs) -> anyhow::Result<()> {
    let mut config = args.config()?;
    let mut metrics_addr = None;
    if let Some(addr) = args.metrics {
        let l = tokio::net::TcpListener::bind(addr)
            .await
            .with_context(|| format!("binding metrics endpoint {addr}"))?;
        metrics_addr = Some(l.local_addr()?);
        config.metrics_listener = Some(l);
    }
    if let Some(addr) = args.dashboard {
        let l = tokio::net::TcpListener::bind(addr)
            .await
            .with_context(|| format!("--dashboard {addr}: binding the dashboard endpoint"))?;
        eprintln!("tofwave: dashboard on http://{}/", l.local_addr()?);
        config.dashboard_listener = Some(l);
    }
    let listener = tokio::net::TcpListener::bind(args.listen)
        .await
        .with_context(|| format!("binding {}", args.listen))?;
    eprintln!("tofwave: serving gRPC on {}", listener.local_addr()?);
    if let Some(c) = &config.cluster {
        eprintln!("tofwave: cluster node {:?} on NATS {} (lease {:?})", c.node_id, c.url, c.lease_ttl);
    }
    match metrics_addr {
        Some(a) => eprintln!("tofwave: serving Prometheus metrics on http://{a}/metrics"),
        None => eprintln!("tofwave: no metrics endpoint (--metrics ADDR serves one)"),
    }
    let drain_s = args.drain_timeout_s;
    let signal = async move {
        shutdown_signal().await;
        eprintln!("tofwave: shutting down: draining in-flight frames (at most {drain_s} s)");
    };
    super::run(listener, config, signal).await?;
    eprintln!("tofwave: shut down");
    Ok(())
}

/// Ctrl-C, or SIGTERM on Unix (systemd and containers stop with it).
async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {},
                    _ = term.recv() => {},
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

fn options(token: &Option<String>, c: &ConnectArgs) -> anyhow::Result<ClientOptions> {
    Ok(ClientOptions {
        token: token.clone(),
        ca_cert_pem: c
            .ca_cert
            .as_ref()
            .map(|p| read_file(p, "CA certificate"))
            .transpose()?,
        tls_domain: c.tls_domain.clone(),
        max_message_bytes: None,
    })
}

/// Prints `bar`'s state as a plain line every `every` while standard error
/// is not a terminal (a log file, CI), where indicatif draws nothing; the
/// lines stop when the returned guard is dropped.
pub fn plain_progress(bar: &indicatif::ProgressBar, what: &'static str, every: std::time::Duration) -> PlainProgress {
    use std::io::IsTerminal;
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    if std::io::stderr().is_terminal() {
        return PlainProgress { stop, thread: None };
    }
    let (bar, flag) = (bar.clone(), stop.clone());
    let start = std::time::Instant::now();
    let thread = std::thread::spawn(move || {
        let tick = std::time::Duration::from_millis(100);
        let mut next = every;
        while !flag.load(std::sync::atomic::Ordering::Relaxed) {
            std::thread::sleep(tick);
            let t = start.elapsed();
            if t < next {
                continue;
            }
            next += every;
            let pos = bar.position();
            let msg = bar.message();
            let msg = if msg.is_empty() { String::new() } else { format!(" {}", msg.trim()) };
            let total = match bar.length() {
                Some(len) if len > 0 => format!("{pos}/{len} ({:.0} %)", 100.0 * pos as f64 / len as f64),
                _ => format!("{pos}"),
            };
            eprintln!("tofwave {what}:{msg} {total} frames, {:.0} s", t.as_secs_f64());
        }
    });
    PlainProgress { stop, thread: Some(thread) }
}

/// Stops [`plain_progress`]'s lines when dropped.
pub struct PlainProgress {
    /// Set to end the printing thread.
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    /// The printing thread (none on a terminal).
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for PlainProgress {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Frames in the inputs, counted before a replay when the files hold at most
/// 1 GiB (reading them twice costs little); `None` above that.
fn count_frames(paths: &[PathBuf], opts: &capture::ReadOptions) -> Option<u64> {
    let source = capture::frames(paths, opts).ok()?;
    let size = |p: &std::path::Path| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0);
    let bytes: u64 = paths
        .iter()
        .map(|p| match std::fs::read_dir(p) {
            Ok(entries) => entries.filter_map(Result::ok).map(|e| size(&e.path())).sum(),
            Err(_) => size(p),
        })
        .sum();
    if bytes > 1 << 30 {
        return None;
    }
    let mut n = 0u64;
    for f in source {
        f.ok()?;
        n += 1;
    }
    Some(n)
}

/// Replays captures; prints a progress bar (frames acknowledged of the total,
/// percentage, frames/s) on stderr and the ack summary at the end. Fails when
/// the server refused frames, so scripts notice.
pub async fn run_replay(args: ReplayArgs) -> anyhow::Result<()> {
    let format: capture::Format = args
        .format
        .parse()
        .map_err(|e| anyhow::anyhow!("--format {}: {e}", args.format))?;
    let opts = capture::ReadOptions {
        format,
        sensor_id: args.sensor.clone().unwrap_or_else(|| "replay".to_string()),
    };
    let source = capture::frames(&args.input, &opts)?;
    for s in source.skipped() {
        eprintln!("note: {s}");
    }
    let mut clients = client::connect(&args.to, &options(&args.token, &args.connect)?).await?;
    let total = if args.quiet { None } else { count_frames(&args.input, &opts) };
    let bar = if args.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        let bar =
            indicatif::ProgressBar::with_draw_target(total, indicatif::ProgressDrawTarget::stderr());
        let template = if total.is_some() {
            "{spinner} {elapsed_precise} {bar:30} {pos}/{len} frames acknowledged ({percent} %, {per_sec}, eta {eta}) {msg}"
        } else {
            "{spinner} {elapsed_precise} {pos} frames acknowledged ({per_sec}) {msg}"
        };
        bar.set_style(indicatif::ProgressStyle::with_template(template).expect("valid template"));
        // Keeps the rate and spinner moving between acks (paced replays).
        bar.enable_steady_tick(std::time::Duration::from_millis(200));
        bar
    };
    let limits = BatchLimits {
        frames: args.batch_frames.max(1),
        bytes: args.batch_bytes.max(1),
    };
    let progress = bar.clone();
    let plain = if args.quiet {
        None
    } else {
        Some(plain_progress(&bar, "replay", std::time::Duration::from_secs(5)))
    };
    let summary = client::replay(
        &mut clients.ingest,
        source,
        args.rate,
        args.sensor.clone(),
        limits,
        move |ack| {
            progress.inc(ack.accepted + ack.rejected);
            if ack.total_rejected > 0 {
                progress.set_message(format!("{} rejected", ack.total_rejected));
            }
        },
    )
    .await;
    drop(plain);
    bar.finish_and_clear();
    let summary = summary?;
    match total {
        Some(t) if t > 0 => eprintln!(
            "tofwave replay: {} of {t} frames acknowledged ({:.0} %); {summary}",
            summary.accepted + summary.rejected,
            100.0 * (summary.accepted + summary.rejected) as f64 / t as f64
        ),
        _ => eprintln!("tofwave replay: {summary}"),
    }
    for r in summary.rejections.iter().take(10) {
        eprintln!(
            "  rejected {} #{}: {} {}",
            r.sensor_id, r.sequence, r.code, r.message
        );
    }
    if summary.rejections.len() > 10 {
        eprintln!("  ... and {} more", summary.rejections.len() - 10);
    }
    for g in summary.gaps.iter().take(10) {
        eprintln!(
            "  gap {}: {} frames missing from #{}",
            g.sensor_id, g.count, g.first_missing
        );
    }
    anyhow::ensure!(
        summary.rejected == 0,
        "{} frames were rejected",
        summary.rejected
    );
    Ok(())
}

/// A warning for each requested sensor id the server has never seen (no
/// frames, no scene set): a subscription to it waits silently, which looks
/// like a hang when the id is mistyped or the sender uses another. Empty when
/// every id is known, or when the token may not list sensors (read-only).
pub async fn unseen_sensor_warnings(control: &mut client::ControlClient, wanted: &[String]) -> Vec<String> {
    if wanted.is_empty() {
        return Vec::new();
    }
    let Ok(list) = control.list_sensors(proto::ListSensorsRequest {}).await else {
        return Vec::new();
    };
    let known: Vec<String> = list.into_inner().sensors.into_iter().map(|s| s.sensor_id).collect();
    wanted
        .iter()
        .filter(|w| !known.contains(w))
        .map(|w| {
            format!(
                "tofwave subscribe: warning: sensor {w:?} has sent no frames to this server yet (sensors seen: {}); \
                 waiting for it. `tofwave replay` sends as --sensor ID, else as \"replay\" (or the id in a recording)",
                if known.is_empty() { "none".to_string() } else { known.join(", ") }
            )
        })
        .collect()
}

/// Prints reports as JSON lines (the `tofwave process` shape) until the server
/// ends the stream or Ctrl-C; lag markers go to stderr.
pub async fn run_subscribe(args: SubscribeArgs) -> anyhow::Result<()> {
    let mut clients = client::connect(&args.from, &options(&args.token, &args.connect)?).await?;
    for w in unseen_sensor_warnings(&mut clients.control, &args.sensors).await {
        eprintln!("{w}");
    }
    let request = proto::SubscribeRequest {
        sensor_ids: args.sensors.clone(),
        min_snr_db: args.min_snr_db,
        resume_from_sequence: args.resume_from,
    };
    let mut stream = client::subscribe(&mut clients.reports, request).await?;
    let mut out: Box<dyn Write + Send> = if args.output.as_os_str() == "-" {
        Box::new(std::io::LineWriter::new(std::io::stdout()))
    } else {
        Box::new(std::io::LineWriter::new(
            std::fs::File::create(&args.output)
                .with_context(|| format!("creating {}", args.output.display()))?,
        ))
    };
    loop {
        let event = tokio::select! {
            e = stream.message() => e?,
            _ = tokio::signal::ctrl_c() => break,
        };
        match event.and_then(|e| e.event) {
            Some(proto::report_event::Event::Report(r)) => writeln!(out, "{}", r.json)?,
            Some(proto::report_event::Event::Lagged(l)) => {
                eprintln!(
                    "tofwave subscribe: fell behind, {} reports skipped",
                    l.skipped
                )
            }
            None => break,
        }
    }
    out.flush()?;
    Ok(())
}

/// `tofwave ctl`: operate a running server over its Control service.
#[derive(Debug, clap::Args)]
pub struct CtlArgs {
    /// Server URL: http://host:port, https://host:port, or host:port (plain http).
    #[arg(long, value_name = "URL")]
    pub to: String,
    /// Bearer token for control (the server's --token; the read-only token is refused).
    #[arg(
        long,
        env = "TOFWAVE_TOKEN",
        hide_env_values = true,
        value_name = "TOKEN"
    )]
    pub token: Option<String>,
    /// TLS options.
    #[command(flatten)]
    pub connect: ConnectArgs,
    /// What to do.
    #[command(subcommand)]
    pub command: CtlCommand,
}

/// `tofwave ctl` subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum CtlCommand {
    /// One line per sensor: id, frames received, processed and rejected, reports, returns,
    /// missing sequence numbers, noise sigma (mV).
    Sensors,
    /// One sensor's counters and noise model, one `key: value` line each.
    Status {
        /// Sensor id.
        sensor: String,
    },
    /// Print a sensor's scene (TOML), or replace it with --set FILE. Without SENSOR: the scene
    /// new sensors start with.
    Scene {
        /// Sensor id [default: the scene new sensors start with].
        sensor: Option<String>,
        /// Scene TOML to apply: validated by the server, then applied between two frames.
        #[arg(long, value_name = "FILE")]
        set: Option<PathBuf>,
    },
    /// A sensor's noise model: mean, sigma and robust sigma (mV), skewness, excess kurtosis,
    /// normality p-value, samples.
    Noise {
        /// Sensor id.
        sensor: String,
    },
    /// Print a sensor's calibration (the [calibration] section of its scene), or apply a
    /// calibration file from `tofwave calibrate` with --set FILE (refused when the file was
    /// measured with another timing method than the sensor's scene).
    Calibration {
        /// Sensor id [default: the scene new sensors start with].
        sensor: Option<String>,
        /// Calibration TOML from `tofwave calibrate`.
        #[arg(long, value_name = "FILE")]
        set: Option<PathBuf>,
    },
}

/// One sensor's line of `tofwave ctl sensors`.
pub fn sensor_line(s: &proto::SensorStatus) -> String {
    let sigma = s
        .noise
        .as_ref()
        .map(|n| format!("{:.3}", n.sigma_v * 1e3))
        .unwrap_or_else(|| "-".into());
    format!(
        "{}\tframes_received={} frames_processed={} frames_rejected={} reports={} returns={} sequence_missing={} noise_sigma_mv={}",
        s.sensor_id,
        s.frames_received,
        s.frames_processed,
        s.frames_rejected,
        s.reports,
        s.returns,
        s.sequence_gaps,
        sigma
    )
}

fn noise_lines(n: &proto::NoiseModel) -> String {
    format!(
        "mean_mv: {:.4}\nsigma_mv: {:.4}\nrobust_sigma_mv: {:.4}\nskewness: {:.4}\nexcess_kurtosis: {:.4}\ngaussian: {}\nnormality_p_value: {:.4}\nsamples: {}\ncontaminated: {}\n",
        n.mean_v * 1e3,
        n.sigma_v * 1e3,
        n.robust_sigma_v * 1e3,
        n.skewness,
        n.excess_kurtosis,
        n.gaussian,
        n.normality_p_value,
        n.samples,
        n.contaminated
    )
}

/// The `[calibration]` section of a scene, as TOML.
fn calibration_toml(scene: &Scene) -> anyhow::Result<String> {
    #[derive(serde::Serialize)]
    struct Section<'a> {
        calibration: &'a crate::scene::CalibrationConfig,
    }
    Ok(crate::scene::human_floats(&toml::to_string(&Section { calibration: &scene.calibration })?))
}

/// Runs one `tofwave ctl` command and returns what it prints on standard output.
pub async fn ctl(args: &CtlArgs) -> anyhow::Result<String> {
    let mut clients = client::connect(&args.to, &options(&args.token, &args.connect)?).await?;
    let c = &mut clients.control;
    let status = |e: tonic::Status| anyhow::anyhow!("server: {} ({:?})", e.message(), e.code());
    let sensor_req = |s: &str| proto::SensorRequest { sensor_id: s.to_string() };
    let mut out = String::new();
    match &args.command {
        CtlCommand::Sensors => {
            let r = c.list_sensors(proto::ListSensorsRequest {}).await.map_err(status)?.into_inner();
            let mut sensors = r.sensors;
            sensors.sort_by(|a, b| a.sensor_id.cmp(&b.sensor_id));
            for s in &sensors {
                out.push_str(&sensor_line(s));
                out.push('\n');
            }
        }
        CtlCommand::Status { sensor } => {
            let s = c.get_status(sensor_req(sensor)).await.map_err(status)?.into_inner();
            out.push_str(&format!(
                "sensor: {}\nframes_received: {}\nframes_processed: {}\nframes_rejected: {}\nreports: {}\nreturns: {}\nlast_sequence: {}\nsequence_missing: {}\n",
                s.sensor_id, s.frames_received, s.frames_processed, s.frames_rejected, s.reports, s.returns, s.last_sequence, s.sequence_gaps
            ));
            if let Some(n) = &s.noise {
                out.push_str(&noise_lines(n));
            }
        }
        CtlCommand::Noise { sensor } => {
            let n = c.get_noise_model(sensor_req(sensor)).await.map_err(status)?.into_inner();
            out.push_str(&noise_lines(&n));
        }
        CtlCommand::Scene { sensor, set } => {
            let sensor_id = sensor.clone().unwrap_or_default();
            let doc = match set {
                Some(path) => {
                    let toml = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
                    // Checked here first, so a typo is named against the file, not the server.
                    Scene::from_toml_str(&toml, &path.display().to_string())?;
                    c.set_scene(proto::SetSceneRequest { sensor_id, toml }).await.map_err(status)?.into_inner()
                }
                None => c.get_scene(sensor_req(&sensor_id)).await.map_err(status)?.into_inner(),
            };
            out.push_str(&doc.toml);
        }
        CtlCommand::Calibration { sensor, set } => {
            let sensor_id = sensor.clone().unwrap_or_default();
            let doc = c.get_scene(sensor_req(&sensor_id)).await.map_err(status)?.into_inner();
            let origin = format!("the scene of sensor {sensor_id:?}");
            let mut scene = Scene::from_toml_str(&doc.toml, &origin)?;
            if let Some(path) = set {
                crate::scene::CalibrationFile::load(path)?.apply(&mut scene, &path.display().to_string())?;
                c.set_scene(proto::SetSceneRequest { sensor_id, toml: scene.to_toml() })
                    .await
                    .map_err(status)?;
            }
            out.push_str(&calibration_toml(&scene)?);
        }
    }
    Ok(out)
}

/// `tofwave ctl`: runs the command and prints its output.
pub async fn run_ctl(args: CtlArgs) -> anyhow::Result<()> {
    let text = ctl(&args).await?;
    let mut stdout = std::io::stdout().lock();
    stdout.write_all(text.as_bytes())?;
    stdout.flush()?;
    Ok(())
}
