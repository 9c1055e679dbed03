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
    /// Sensors served at most (each holds a worker thread and a pipeline), sensors.
    #[arg(long, value_name = "N", default_value_t = 256)]
    pub max_sensors: usize,
    /// Longest wait after Ctrl-C/SIGTERM for clients to take their last acks and reports, seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 20.0)]
    pub drain_timeout_s: f64,
    /// Reports a subscriber may fall behind before it is told it lagged, reports.
    #[arg(long, value_name = "REPORTS", default_value_t = 1024)]
    pub subscriber_buffer: usize,
    /// Reports retained per sensor for subscribers resuming from a sequence number, reports.
    #[arg(long, value_name = "REPORTS", default_value_t = 1024)]
    pub history_reports: usize,
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
        Ok(ServerConfig {
            scene,
            write_token: self.token.clone(),
            read_token: self.read_token.clone(),
            tls,
            max_message_bytes: self.max_message_bytes,
            max_streams_per_connection: self.max_streams_per_connection,
            queue_frames: self.queue_frames,
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
    if let Some(addr) = args.metrics {
        config.metrics_listener = Some(
            tokio::net::TcpListener::bind(addr)
                .await
                .with_context(|| format!("binding metrics endpoint {addr}"))?,
        );
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
    super::run(listener, config, shutdown_signal()).await?;
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

/// Replays captures; prints a progress bar (frames/s) on stderr and the ack
/// summary at the end. Fails when the server refused frames, so scripts notice.
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
    let mut clients = client::connect(&args.to, &options(&args.token, &args.connect)?).await?;
    let bar = if args.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        let bar =
            indicatif::ProgressBar::with_draw_target(None, indicatif::ProgressDrawTarget::stderr());
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} {elapsed_precise} {pos} frames acknowledged ({per_sec}) {msg}",
            )
            .expect("valid template"),
        );
        // Keeps the rate and spinner moving between acks (paced replays).
        bar.enable_steady_tick(std::time::Duration::from_millis(200));
        bar
    };
    let limits = BatchLimits {
        frames: args.batch_frames.max(1),
        bytes: args.batch_bytes.max(1),
    };
    let progress = bar.clone();
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
    bar.finish_and_clear();
    let summary = summary?;
    eprintln!("tofwave replay: {summary}");
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

/// Prints reports as JSON lines (the `tofwave process` shape) until the server
/// ends the stream or Ctrl-C; lag markers go to stderr.
pub async fn run_subscribe(args: SubscribeArgs) -> anyhow::Result<()> {
    let mut clients = client::connect(&args.from, &options(&args.token, &args.connect)?).await?;
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
