//! Metric names (defined once, here), recording helpers, the Prometheus
//! recorder, and tracing set-up.
//!
//! Every metric the service emits is named by a constant below and recorded
//! through a helper, so a dashboard author can read the full list in one place.
//! Per-sensor metrics carry a `sensor` label (sensor counts are small: one
//! label value per digitiser).

use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};
use std::sync::OnceLock;
use std::time::Duration;

/// Frames decoded from ingest messages (before validation), per sensor.
pub const FRAMES_RECEIVED: &str = "tofwave_frames_received_total";
/// Frames the pipeline processed without error, per sensor.
pub const FRAMES_PROCESSED: &str = "tofwave_frames_processed_total";
/// Frames refused, per sensor and `reason` (`invalid_frame`, `sample_rate`,
/// `samples_per_frame`, `missing_stop`, `pipeline`, `panic`, `oversize`, `sensor_limit`, `shutdown`).
pub const FRAMES_REJECTED: &str = "tofwave_frames_rejected_total";
/// Reports produced, per sensor.
pub const REPORTS: &str = "tofwave_reports_total";
/// Returns (detections) in those reports, per sensor.
pub const RETURNS: &str = "tofwave_returns_total";
/// Missing sequence numbers detected, per sensor.
pub const SEQUENCE_GAPS: &str = "tofwave_sequence_missing_total";
/// Seconds from a frame entering its sensor's queue to the end of its processing.
pub const PROCESSING_SECONDS: &str = "tofwave_processing_seconds";
/// Frames waiting in a sensor's pipeline queue.
pub const QUEUE_DEPTH: &str = "tofwave_queue_depth";
/// Reports skipped for subscribers that fell behind (sum over subscribers).
pub const SUBSCRIBER_LAGGED: &str = "tofwave_subscriber_lagged_reports_total";
/// Open report subscriptions.
pub const SUBSCRIBERS: &str = "tofwave_subscribers";
/// Frames written to `--record` files, per sensor.
pub const FRAMES_RECORDED: &str = "tofwave_frames_recorded_total";

/// Histogram buckets for [`PROCESSING_SECONDS`]: 10 µs to 10 s, roughly x3 steps.
const PROCESSING_BUCKETS_S: &[f64] = &[
    1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0, 3.0, 10.0,
];

/// Installs a `tracing` subscriber writing to stderr; `RUST_LOG` filters (default `warn`).
pub fn init_tracing() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
}

/// The process-wide Prometheus recorder, installed on first call.
///
/// `metrics` allows one global recorder per process, so every server started in
/// the process (tests start several) shares it; per-sensor labels keep their
/// numbers apart. If another recorder was installed first, the handle returned
/// renders an empty registry.
pub fn prometheus_handle() -> PrometheusHandle {
    static HANDLE: OnceLock<PrometheusHandle> = OnceLock::new();
    HANDLE
        .get_or_init(|| {
            let builder = PrometheusBuilder::new()
                .set_buckets_for_metric(
                    Matcher::Full(PROCESSING_SECONDS.to_string()),
                    PROCESSING_BUCKETS_S,
                )
                .expect("bucket list is non-empty");
            let recorder = builder.build_recorder();
            let handle = recorder.handle();
            if metrics::set_global_recorder(recorder).is_err() {
                tracing::warn!("a metrics recorder was already installed; /metrics stays empty");
            }
            handle
        })
        .clone()
}

/// A frame was decoded from an ingest message.
pub fn frame_received(sensor: &str) {
    metrics::counter!(FRAMES_RECEIVED, "sensor" => sensor.to_string()).increment(1);
}

/// A frame was processed; `latency` runs from enqueue to the end of processing.
pub fn frame_processed(sensor: &str, latency: Duration) {
    metrics::counter!(FRAMES_PROCESSED, "sensor" => sensor.to_string()).increment(1);
    metrics::histogram!(PROCESSING_SECONDS, "sensor" => sensor.to_string())
        .record(latency.as_secs_f64());
}

/// `count` frames were refused for `reason` (one of the labels in [`FRAMES_REJECTED`]).
pub fn frames_rejected(sensor: &str, reason: &'static str, count: u64) {
    metrics::counter!(FRAMES_REJECTED, "sensor" => sensor.to_string(), "reason" => reason)
        .increment(count);
}

/// A report with `returns` returns was published.
pub fn report_published(sensor: &str, returns: usize) {
    metrics::counter!(REPORTS, "sensor" => sensor.to_string()).increment(1);
    metrics::counter!(RETURNS, "sensor" => sensor.to_string()).increment(returns as u64);
}

/// `missing` sequence numbers were skipped by a sensor.
pub fn sequence_gap(sensor: &str, missing: u64) {
    metrics::counter!(SEQUENCE_GAPS, "sensor" => sensor.to_string()).increment(missing);
}

/// Current depth of a sensor's pipeline queue, frames.
pub fn queue_depth(sensor: &str, depth: usize) {
    metrics::gauge!(QUEUE_DEPTH, "sensor" => sensor.to_string()).set(depth as f64);
}

/// A subscriber fell behind and `skipped` reports were dropped for it.
pub fn subscriber_lagged(skipped: u64) {
    metrics::counter!(SUBSCRIBER_LAGGED).increment(skipped);
}

/// A subscription opened (`+1`) or closed (`-1`).
pub fn subscribers_changed(delta: f64) {
    metrics::gauge!(SUBSCRIBERS).increment(delta);
}

/// A frame was written to a recording.
pub fn frame_recorded(sensor: &str) {
    metrics::counter!(FRAMES_RECORDED, "sensor" => sensor.to_string()).increment(1);
}
