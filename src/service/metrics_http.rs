//! `GET /metrics` in Prometheus text format: a minimal HTTP/1.1 responder
//! (one request per connection), so the endpoint shares the server's runtime
//! and shutdown instead of the exporter's own listener.

use metrics_exporter_prometheus::PrometheusHandle;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_util::sync::CancellationToken;

/// Largest request head read, bytes.
pub(crate) const MAX_REQUEST_BYTES: usize = 8192;

pub(crate) async fn serve(
    listener: TcpListener,
    handle: PrometheusHandle,
    shutdown: CancellationToken,
) {
    tracing::info!(addr = ?listener.local_addr().ok(), "metrics endpoint");
    accept_each(listener, "metrics", shutdown, move |stream, _| {
        let handle = handle.clone();
        async move { respond(stream, &handle).await }
    })
    .await
}

/// Accepts connections on `listener` until `shutdown`, each handled on its
/// own task by `handle` (given the stream and the shutdown token); `what`
/// names the endpoint in the logs. Shared by `/metrics` and the dashboard.
pub(crate) async fn accept_each<F, Fut>(listener: TcpListener, what: &'static str, shutdown: CancellationToken, handle: F)
where
    F: Fn(TcpStream, CancellationToken) -> Fut,
    Fut: std::future::Future<Output = std::io::Result<()>> + Send + 'static,
{
    loop {
        let conn = tokio::select! {
            _ = shutdown.cancelled() => return,
            c = listener.accept() => c,
        };
        match conn {
            Ok((stream, _)) => {
                let work = handle(stream, shutdown.clone());
                tokio::spawn(async move {
                    if let Err(e) = work.await {
                        tracing::debug!(error = %e, endpoint = what, "request failed");
                    }
                });
            }
            Err(e) => tracing::warn!(error = %e, endpoint = what, "accept failed"),
        }
    }
}

/// How reading a request head ended.
#[derive(Debug, PartialEq)]
pub(crate) enum Head {
    /// The blank line arrived.
    Complete,
    /// [`MAX_REQUEST_BYTES`] read without it.
    TooLarge,
    /// The peer closed the connection first.
    Closed,
}

/// Reads a request head (up to the blank line, at most [`MAX_REQUEST_BYTES`]) into `buf`.
pub(crate) async fn read_head(stream: &mut TcpStream, buf: &mut Vec<u8>) -> std::io::Result<Head> {
    let mut chunk = [0u8; 1024];
    loop {
        if buf.windows(4).any(|w| w == b"\r\n\r\n") {
            return Ok(Head::Complete);
        }
        if buf.len() >= MAX_REQUEST_BYTES {
            return Ok(Head::TooLarge);
        }
        let n = stream.read(&mut chunk).await?;
        if n == 0 {
            return Ok(Head::Closed);
        }
        buf.extend_from_slice(&chunk[..n]);
    }
}

async fn respond(mut stream: TcpStream, handle: &PrometheusHandle) -> std::io::Result<()> {
    let mut buf = Vec::with_capacity(1024);
    // An incomplete head is answered from its first line, as far as it goes.
    read_head(&mut stream, &mut buf).await?;
    let line = buf.split(|&b| b == b'\n').next().unwrap_or_default();
    let line = String::from_utf8_lossy(line);
    let mut parts = line.split_whitespace();
    let (method, path) = (parts.next().unwrap_or(""), parts.next().unwrap_or(""));
    let (status, ctype, body) = if method == "GET" && (path == "/metrics" || path == "/") {
        ("200 OK", "text/plain; version=0.0.4", handle.render())
    } else {
        (
            "404 Not Found",
            "text/plain",
            "only GET /metrics is served\n".to_string(),
        )
    };
    let head = format!(
        "HTTP/1.1 {status}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    stream.write_all(head.as_bytes()).await?;
    stream.write_all(body.as_bytes()).await?;
    stream.shutdown().await
}
