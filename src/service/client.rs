//! Library client: connect (optionally over TLS, with a bearer token), push
//! frames and collect acknowledgements, replay captures at a chosen pace, and
//! subscribe to reports.

use super::grpc;
use crate::frame::Frame;
use crate::wire::{frame_to_proto, proto};
use prost::Message;
use std::fmt::Display;
use std::time::Duration;
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_stream::wrappers::ReceiverStream;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};
use tonic::{Request, Status};

/// Client-side failures.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// Could not connect or set up TLS.
    #[error("connecting to {url}: {cause}")]
    Connect {
        /// Server URL.
        url: String,
        /// The transport error and its causes, each said once
        /// ([`error_chain`]: tonic's errors repeat their own cause).
        cause: String,
    },
    /// The URL or token is unusable.
    #[error("{0}")]
    Config(String),
    /// The server answered with an error status.
    #[error("server: {} ({:?})", .0.message(), .0.code())]
    Status(Status),
    /// The server ended a push stream with an error.
    #[error("push: {0}")]
    Push(PushFailed),
    /// A capture could not be read.
    #[error("reading captures: {0}")]
    Capture(String),
}

// Not `#[from]`: that would make the status a `source` too, and the message,
// which already prints it, would be followed by it again in an error chain.
impl From<Status> for ClientError {
    fn from(s: Status) -> Self {
        ClientError::Status(s)
    }
}

impl From<PushFailed> for ClientError {
    fn from(p: PushFailed) -> Self {
        ClientError::Push(p)
    }
}

/// How to reach a server.
#[derive(Debug, Clone, Default)]
pub struct ClientOptions {
    /// Bearer token sent with every call.
    pub token: Option<String>,
    /// CA certificate (PEM) to trust for `https://` URLs; system roots otherwise
    /// are not used, so a private CA must be given.
    pub ca_cert_pem: Option<Vec<u8>>,
    /// Server name to verify in the certificate (default: the URL's host).
    pub tls_domain: Option<String>,
    /// Largest message the client decodes, bytes (default 16 MiB).
    pub max_message_bytes: Option<usize>,
}

/// Adds `authorization: Bearer <token>` to every request.
#[derive(Clone)]
pub struct BearerToken(Option<MetadataValue<Ascii>>);

impl BearerToken {
    /// `None`: no header.
    pub fn new(token: Option<&str>) -> Result<BearerToken, ClientError> {
        token
            .map(|t| {
                format!("Bearer {t}")
                    .parse()
                    .map_err(|_| ClientError::Config("token: not valid in an HTTP header".into()))
            })
            .transpose()
            .map(BearerToken)
    }
}

impl Interceptor for BearerToken {
    fn call(&mut self, mut req: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

/// Ingest client with the bearer token attached.
pub type IngestClient = grpc::ingest_client::IngestClient<InterceptedService<Channel, BearerToken>>;
/// Reports client with the bearer token attached.
pub type ReportsClient =
    grpc::reports_client::ReportsClient<InterceptedService<Channel, BearerToken>>;
/// Control client with the bearer token attached.
pub type ControlClient =
    grpc::control_client::ControlClient<InterceptedService<Channel, BearerToken>>;

/// The three clients over one connection.
pub struct Clients {
    /// Ingest.
    pub ingest: IngestClient,
    /// Reports.
    pub reports: ReportsClient,
    /// Control.
    pub control: ControlClient,
}

/// An error and its causes as one line, each distinct message once
/// (`transport error: tcp connect error: Connection refused (os error 111)`):
/// wrappers that print their cause and also return it as `source()` would
/// otherwise say it twice.
pub fn error_chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut next = Some(e);
    while let Some(err) = next {
        let msg = err.to_string();
        // A wrapper that printed its cause already holds the cause's text.
        if !parts.iter().any(|p| p.contains(&msg)) {
            parts.push(msg);
        }
        next = err.source();
    }
    parts.join(": ")
}

/// A server address as a URL: `host:port` gets `http://`; `http://` and
/// `https://` URLs are kept; anything else with a scheme is refused.
pub fn normalize_url(url: &str) -> Result<String, ClientError> {
    let url = url.trim();
    if url.starts_with("http://") || url.starts_with("https://") {
        return Ok(url.to_string());
    }
    if let Some((scheme, _)) = url.split_once("://") {
        return Err(ClientError::Config(format!(
            "URL {url:?}: scheme {scheme:?} is not served; use http://host:port, https://host:port or host:port"
        )));
    }
    if url.is_empty() {
        return Err(ClientError::Config("URL is empty; use host:port or http://host:port".into()));
    }
    Ok(format!("http://{url}"))
}

/// Connects to `url` (`http://host:port`, `https://host:port`, or `host:port`
/// meaning `http://host:port`).
pub async fn connect(url: &str, opts: &ClientOptions) -> Result<Clients, ClientError> {
    let url = normalize_url(url)?;
    let url = url.as_str();
    let mut ep = Endpoint::from_shared(url.to_string())
        .map_err(|e| ClientError::Config(format!("URL {url:?}: {e}")))?
        .tcp_nodelay(true)
        .max_frame_size(super::MAX_H2_FRAME);
    if url.starts_with("https://") {
        let mut tls = ClientTlsConfig::new();
        if let Some(ca) = &opts.ca_cert_pem {
            tls = tls.ca_certificate(Certificate::from_pem(ca));
        }
        if let Some(d) = &opts.tls_domain {
            tls = tls.domain_name(d.clone());
        }
        ep = ep.tls_config(tls).map_err(|e| ClientError::Connect {
            url: url.into(),
            cause: error_chain(&e),
        })?;
    }
    let channel = ep.connect().await.map_err(|e| ClientError::Connect {
        url: url.into(),
        cause: error_chain(&e),
    })?;
    let token = BearerToken::new(opts.token.as_deref())?;
    let limit = opts
        .max_message_bytes
        .unwrap_or(super::DEFAULT_MAX_MESSAGE_BYTES);
    Ok(Clients {
        ingest: grpc::ingest_client::IngestClient::with_interceptor(channel.clone(), token.clone())
            .max_decoding_message_size(limit),
        reports: grpc::reports_client::ReportsClient::with_interceptor(
            channel.clone(),
            token.clone(),
        )
        .max_decoding_message_size(limit),
        control: grpc::control_client::ControlClient::with_interceptor(channel, token)
            .max_decoding_message_size(limit),
    })
}

/// What the server acknowledged over one push stream.
#[derive(Debug, Clone, Default)]
pub struct PushSummary {
    /// Batches acknowledged.
    pub batches: u64,
    /// Frames accepted (processed by the pipeline).
    pub accepted: u64,
    /// Frames rejected.
    pub rejected: u64,
    /// Every rejection, in order.
    pub rejections: Vec<proto::Rejection>,
    /// Every sequence gap reported.
    pub gaps: Vec<proto::SequenceGap>,
    /// Frames handed to the stream (sent, or queued to be sent).
    pub sent: u64,
}

impl PushSummary {
    /// Frames sent that the server neither accepted nor rejected.
    pub fn unacknowledged(&self) -> u64 {
        self.sent.saturating_sub(self.accepted + self.rejected)
    }

    fn add(&mut self, ack: &proto::IngestAck) {
        self.batches = ack.batch;
        self.accepted += ack.accepted;
        self.rejected += ack.rejected;
        self.rejections.extend(ack.rejections.iter().cloned());
        self.gaps.extend(ack.gaps.iter().cloned());
    }
}

impl Display for PushSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let missing: u64 = self.gaps.iter().map(|g| g.count).sum();
        write!(
            f,
            "{} batches acknowledged: {} frames accepted, {} rejected, {} sequence gaps ({} frames missing)",
            self.batches,
            self.accepted,
            self.rejected,
            self.gaps.len(),
            missing
        )?;
        match self.unacknowledged() {
            0 => Ok(()),
            n => write!(f, "; {n} of {} frames sent were not acknowledged", self.sent),
        }
    }
}

/// A push stream the server ended with an error, and what it had acknowledged.
#[derive(Debug, thiserror::Error)]
#[error("{} ({:?}) after {summary}", .status.message(), .status.code())]
pub struct PushFailed {
    /// Acknowledged before the failure.
    pub summary: PushSummary,
    /// The server's status.
    pub status: Status,
}

/// Streams `batches` and collects the acks; `on_ack` sees each one as it arrives.
/// Ends when the server has acknowledged everything sent, or fails with its
/// status and what had been acknowledged until then.
pub async fn push<S>(
    client: &mut IngestClient,
    batches: S,
    mut on_ack: impl FnMut(&proto::IngestAck),
) -> Result<PushSummary, PushFailed>
where
    S: tokio_stream::Stream<Item = proto::FrameBatch> + Send + 'static,
{
    let mut summary = PushSummary::default();
    let sent = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let counter = sent.clone();
    let batches = tokio_stream::StreamExt::map(batches, move |b: proto::FrameBatch| {
        counter.fetch_add(b.frames.len() as u64, std::sync::atomic::Ordering::Relaxed);
        b
    });
    let sent_now = |s: &mut PushSummary| s.sent = sent.load(std::sync::atomic::Ordering::Relaxed);
    let mut acks = match client.push(batches).await {
        Ok(r) => r.into_inner(),
        Err(status) => return Err(PushFailed { summary, status }),
    };
    loop {
        match acks.message().await {
            Ok(Some(ack)) => {
                on_ack(&ack);
                summary.add(&ack);
            }
            Ok(None) => {
                sent_now(&mut summary);
                // A stream that ends OK with frames outstanding was cut off.
                return match summary.unacknowledged() {
                    0 => Ok(summary),
                    n => Err(PushFailed {
                        status: Status::unavailable(format!("the server ended the stream with {n} frames not acknowledged")),
                        summary,
                    }),
                };
            }
            Err(status) => {
                sent_now(&mut summary);
                return Err(PushFailed { summary, status });
            }
        }
    }
}

/// Replay pace.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rate {
    /// As recorded: frames sent at their trigger-time spacing.
    Realtime,
    /// As fast as the server accepts them.
    Max,
    /// `factor` times the recorded pace (2: twice as fast).
    Factor(f64),
}

impl std::str::FromStr for Rate {
    type Err = String;
    fn from_str(s: &str) -> Result<Rate, String> {
        match s {
            "realtime" => Ok(Rate::Realtime),
            "max" => Ok(Rate::Max),
            _ => match s.parse::<f64>() {
                Ok(f) if f.is_finite() && f > 0.0 => Ok(Rate::Factor(f)),
                _ => Err(format!(
                    "{s:?}: expected realtime, max or a speed-up factor > 0"
                )),
            },
        }
    }
}

/// Limits of one replay message.
#[derive(Debug, Clone, Copy)]
pub struct BatchLimits {
    /// Frames per message at most.
    pub frames: usize,
    /// Encoded bytes per message at most (stay under the server's limit).
    pub bytes: usize,
}

impl Default for BatchLimits {
    fn default() -> Self {
        BatchLimits {
            frames: 64,
            bytes: 4 * 1024 * 1024,
        }
    }
}

/// Replays `frames` (read on a blocking thread) to the server at `rate`,
/// batching frames that are due together. `sensor` overrides every frame's
/// sensor id; `on_ack` sees each ack (progress display).
pub async fn replay<I, E>(
    client: &mut IngestClient,
    frames: I,
    rate: Rate,
    sensor: Option<String>,
    limits: BatchLimits,
    on_ack: impl FnMut(&proto::IngestAck),
) -> Result<PushSummary, ClientError>
where
    I: Iterator<Item = Result<Frame, E>> + Send + 'static,
    E: Display + Send + 'static,
{
    let (frame_tx, mut frame_rx) = mpsc::channel::<Result<Frame, String>>(256);
    let reader = tokio::task::spawn_blocking(move || {
        for f in frames {
            let stop = f.is_err();
            if frame_tx
                .blocking_send(f.map_err(|e| e.to_string()))
                .is_err()
                || stop
            {
                break;
            }
        }
    });
    let (batch_tx, batch_rx) = mpsc::channel::<proto::FrameBatch>(4);
    let pacer = tokio::spawn(async move {
        let factor = match rate {
            Rate::Realtime => Some(1.0),
            Rate::Factor(f) => Some(f),
            Rate::Max => None,
        };
        let start = Instant::now();
        let mut t0: Option<f64> = None;
        let mut last_due = start;
        let mut batch = proto::FrameBatch::default();
        let mut bytes = 0usize;
        while let Some(f) = frame_rx.recv().await {
            let mut frame = f?;
            if let Some(s) = &sensor {
                frame.sensor_id = s.clone();
            }
            if let Some(factor) = factor {
                let t = frame.trigger_time_s;
                let base = *t0.get_or_insert(t);
                let offset_s = (t - base) / factor;
                let due = if offset_s.is_finite() && offset_s >= 0.0 {
                    (start + Duration::from_secs_f64(offset_s)).max(last_due)
                } else {
                    last_due
                };
                last_due = due;
                if due > Instant::now() {
                    if !batch.frames.is_empty() {
                        bytes = 0;
                        if batch_tx.send(std::mem::take(&mut batch)).await.is_err() {
                            return Ok(());
                        }
                    }
                    tokio::time::sleep_until(due).await;
                }
            }
            let msg = frame_to_proto(&frame);
            let len = msg.encoded_len() + 8;
            if !batch.frames.is_empty()
                && (batch.frames.len() >= limits.frames || bytes + len > limits.bytes)
            {
                bytes = 0;
                if batch_tx.send(std::mem::take(&mut batch)).await.is_err() {
                    return Ok(());
                }
            }
            bytes += len;
            batch.frames.push(msg);
        }
        if !batch.frames.is_empty() {
            let _ = batch_tx.send(batch).await;
        }
        Ok::<(), String>(())
    });
    let pushed = push(client, ReceiverStream::new(batch_rx), on_ack).await;
    let paced = pacer
        .await
        .map_err(|e| ClientError::Capture(e.to_string()))?;
    let _ = reader.await;
    paced.map_err(ClientError::Capture)?;
    Ok(pushed?)
}

/// Subscribes to reports.
pub async fn subscribe(
    client: &mut ReportsClient,
    request: proto::SubscribeRequest,
) -> Result<tonic::Streaming<proto::ReportEvent>, Status> {
    Ok(client.subscribe(request).await?.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_parse() {
        assert_eq!("realtime".parse(), Ok(Rate::Realtime));
        assert_eq!("max".parse(), Ok(Rate::Max));
        assert_eq!("2.5".parse(), Ok(Rate::Factor(2.5)));
        for bad in ["0", "-1", "nan", "inf", "fast", ""] {
            assert!(bad.parse::<Rate>().is_err(), "{bad}");
        }
    }

    #[test]
    fn urls_without_a_scheme_are_http() {
        assert_eq!(normalize_url("127.0.0.1:50051").unwrap(), "http://127.0.0.1:50051");
        assert_eq!(normalize_url("http://h:1").unwrap(), "http://h:1");
        assert_eq!(normalize_url("https://h:1").unwrap(), "https://h:1");
        assert!(normalize_url("nats://h:1").is_err());
        assert!(normalize_url("").is_err());
    }

    #[test]
    fn error_chains_say_each_cause_once() {
        #[derive(Debug, thiserror::Error)]
        #[error("open failed: {0}")]
        struct Wrap(#[source] std::io::Error);
        let e = Wrap(std::io::Error::from_raw_os_error(2));
        let text = error_chain(&e);
        assert_eq!(text.matches("os error 2").count(), 1, "{text}");
    }
}
