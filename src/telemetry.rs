//! Metric names (defined once, here), recording helpers, the Prometheus
//! recorder, and tracing set-up.
//!
//! Every metric the service emits is named by a constant below and recorded
//! through a helper, so a dashboard author can read the full list in one place.
//! Per-sensor metrics carry a `sensor` label (sensor counts are small: one
//! label value per digitiser).

use metrics::{Counter, Gauge, Histogram};
use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};
use std::sync::OnceLock;
use std::time::Duration;

/// Frames decoded from ingest messages (before validation), per sensor.
pub const FRAMES_RECEIVED: &str = "tofwave_frames_received_total";
/// Frames the pipeline processed without error, per sensor.
pub const FRAMES_PROCESSED: &str = "tofwave_frames_processed_total";
/// Frames refused, per sensor and `reason` (`invalid_frame`, `sample_rate`,
/// `samples_per_frame`, `missing_stop`, `pipeline`, `panic`, `oversize`, `sensor_limit`, `shutdown`,
/// `recording`, `fault`, `cluster`: not persisted in JetStream).
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
/// Open dashboard event streams (`serve --dashboard`).
pub const DASHBOARD_CLIENTS: &str = "tofwave_dashboard_clients";
/// Frames written to `--record` files, per sensor.
pub const FRAMES_RECORDED: &str = "tofwave_frames_recorded_total";
/// Recordings stopped by a write or sync error, per sensor.
pub const RECORDING_FAILURES: &str = "tofwave_recording_failures_total";
/// 1 for a sensor whose frames are refused because it is faulted (its
/// recording failed or its worker stopped); absent otherwise. Any faulted
/// sensor makes the gRPC health of `tofwave.v1.Ingest` NOT_SERVING.
pub const SENSOR_FAULTED: &str = "tofwave_sensor_faulted";

/// Observed false-alarm rate per noise-gate cell, cumulative over the
/// sensor's frames (the latest report's `false_alarm.rate`), per sensor.
pub const FALSE_ALARM_RATE: &str = "tofwave_false_alarm_rate";
/// Design false-alarm probability per cell the threshold holds (the latest
/// report's `detector.pfa_cell`): what [`FALSE_ALARM_RATE`] should match, per sensor.
pub const FALSE_ALARM_DESIGN_RATE: &str = "tofwave_false_alarm_design_rate";
/// Lower end of the observed rate's 95 % interval (`false_alarm.ci95[0]`), per sensor.
pub const FALSE_ALARM_CI95_LOW: &str = "tofwave_false_alarm_rate_ci95_low";
/// Upper end of the observed rate's 95 % interval (`false_alarm.ci95[1]`), per sensor.
pub const FALSE_ALARM_CI95_HIGH: &str = "tofwave_false_alarm_rate_ci95_high";

/// Cluster mode (`serve --cluster`): sensors this node holds the lease of.
pub const CLUSTER_SENSORS_OWNED: &str = "tofwave_cluster_sensors_owned";
/// Cluster mode: sensors this node claimed (took over), per sensor.
pub const CLUSTER_CLAIMS: &str = "tofwave_cluster_claims_total";
/// Cluster mode: frames replayed to rebuild a sensor's state after a claim
/// (processed without publishing), per sensor.
pub const CLUSTER_FRAMES_REPLAYED: &str = "tofwave_cluster_frames_replayed_total";

/// Every metric name above, for tests and dashboard checks. Histograms are
/// exported as `<name>_bucket`, `<name>_sum` and `<name>_count`.
pub const ALL_METRICS: [&str; 21] = [
    FRAMES_RECEIVED,
    FRAMES_PROCESSED,
    FRAMES_REJECTED,
    REPORTS,
    RETURNS,
    SEQUENCE_GAPS,
    PROCESSING_SECONDS,
    QUEUE_DEPTH,
    SUBSCRIBER_LAGGED,
    SUBSCRIBERS,
    DASHBOARD_CLIENTS,
    FRAMES_RECORDED,
    RECORDING_FAILURES,
    SENSOR_FAULTED,
    FALSE_ALARM_RATE,
    FALSE_ALARM_DESIGN_RATE,
    FALSE_ALARM_CI95_LOW,
    FALSE_ALARM_CI95_HIGH,
    CLUSTER_SENSORS_OWNED,
    CLUSTER_CLAIMS,
    CLUSTER_FRAMES_REPLAYED,
];

/// Histogram buckets for [`PROCESSING_SECONDS`]: 10 µs to 10 s, roughly x3 steps.
const PROCESSING_BUCKETS_S: &[f64] = &[
    1e-5, 3e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0, 3.0, 10.0,
];

/// Installs a `tracing` subscriber writing to stderr; `RUST_LOG` filters (default `warn`).
/// Colours only on a terminal: a log file or journal gets plain text.
pub fn init_tracing() {
    use std::io::IsTerminal;
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::stderr().is_terminal())
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

/// Values of the `reason` label of [`FRAMES_REJECTED`].
pub const REJECT_REASONS: [&str; 12] = [
    "invalid_frame",
    "sample_rate",
    "samples_per_frame",
    "missing_stop",
    "pipeline",
    "panic",
    "oversize",
    "sensor_limit",
    "shutdown",
    "recording",
    "fault",
    "cluster",
];

/// One sensor's metric handles, kept by its session. Building a labelled
/// metric key allocates (the label value and the label list), so each handle
/// is registered on first use and reused after: recording allocates nothing
/// per frame. A series still appears on its first use, as it would without
/// the cache.
pub struct SensorMetrics {
    /// Value of the `sensor` label.
    sensor: String,
    /// [`FRAMES_RECEIVED`].
    frames_received: OnceLock<Counter>,
    /// [`FRAMES_PROCESSED`].
    frames_processed: OnceLock<Counter>,
    /// [`PROCESSING_SECONDS`].
    processing_seconds: OnceLock<Histogram>,
    /// [`FRAMES_REJECTED`], one per entry of [`REJECT_REASONS`].
    frames_rejected: [OnceLock<Counter>; REJECT_REASONS.len()],
    /// [`REPORTS`].
    reports: OnceLock<Counter>,
    /// [`RETURNS`].
    returns: OnceLock<Counter>,
    /// [`SEQUENCE_GAPS`].
    sequence_gaps: OnceLock<Counter>,
    /// [`QUEUE_DEPTH`].
    queue_depth: OnceLock<Gauge>,
    /// [`FRAMES_RECORDED`].
    frames_recorded: OnceLock<Counter>,
    /// [`RECORDING_FAILURES`].
    recording_failures: OnceLock<Counter>,
    /// [`FALSE_ALARM_RATE`], [`FALSE_ALARM_DESIGN_RATE`], [`FALSE_ALARM_CI95_LOW`], [`FALSE_ALARM_CI95_HIGH`].
    false_alarm: [OnceLock<Gauge>; 4],
}

impl SensorMetrics {
    /// Handles of `sensor`'s metrics (none registered yet).
    pub fn new(sensor: &str) -> Self {
        SensorMetrics {
            sensor: sensor_label(sensor),
            frames_received: OnceLock::new(),
            frames_processed: OnceLock::new(),
            processing_seconds: OnceLock::new(),
            frames_rejected: Default::default(),
            reports: OnceLock::new(),
            returns: OnceLock::new(),
            sequence_gaps: OnceLock::new(),
            queue_depth: OnceLock::new(),
            frames_recorded: OnceLock::new(),
            recording_failures: OnceLock::new(),
            false_alarm: Default::default(),
        }
    }

    /// The counter `name` of this sensor, registered on first use.
    fn counter<'a>(&self, cell: &'a OnceLock<Counter>, name: &'static str) -> &'a Counter {
        cell.get_or_init(|| metrics::counter!(name, "sensor" => self.sensor.clone()))
    }

    /// A frame was decoded from an ingest message.
    pub fn frame_received(&self) {
        self.counter(&self.frames_received, FRAMES_RECEIVED)
            .increment(1);
    }

    /// A frame was processed; `latency` runs from enqueue to the end of processing.
    pub fn frame_processed(&self, latency: Duration) {
        self.counter(&self.frames_processed, FRAMES_PROCESSED)
            .increment(1);
        self.processing_seconds
            .get_or_init(
                || metrics::histogram!(PROCESSING_SECONDS, "sensor" => self.sensor.clone()),
            )
            .record(latency.as_secs_f64());
    }

    /// `count` frames were refused for `reason` (one of [`REJECT_REASONS`]).
    pub fn frames_rejected(&self, reason: &'static str, count: u64) {
        match REJECT_REASONS.iter().position(|r| *r == reason) {
            Some(i) => self.frames_rejected[i]
                .get_or_init(|| {
                    metrics::counter!(FRAMES_REJECTED, "sensor" => self.sensor.clone(), "reason" => reason)
                })
                .increment(count),
            // Not in the list: still counted, through a fresh key.
            None => frames_rejected(&self.sensor, reason, count),
        }
    }

    /// A report with `returns` returns was published.
    pub fn report_published(&self, returns: usize) {
        self.counter(&self.reports, REPORTS).increment(1);
        self.counter(&self.returns, RETURNS)
            .increment(returns as u64);
    }

    /// The false-alarm self-check of the latest report: observed rate per
    /// cell, its 95 % interval, and the design rate per cell.
    pub fn false_alarm(&self, observed: f64, ci95: [f64; 2], design: f64) {
        const NAMES: [&str; 4] = [FALSE_ALARM_RATE, FALSE_ALARM_DESIGN_RATE, FALSE_ALARM_CI95_LOW, FALSE_ALARM_CI95_HIGH];
        for ((cell, name), value) in self.false_alarm.iter().zip(NAMES).zip([observed, design, ci95[0], ci95[1]]) {
            if value.is_finite() {
                cell.get_or_init(|| metrics::gauge!(name, "sensor" => self.sensor.clone())).set(value);
            }
        }
    }

    /// `missing` sequence numbers were skipped.
    pub fn sequence_gap(&self, missing: u64) {
        self.counter(&self.sequence_gaps, SEQUENCE_GAPS)
            .increment(missing);
    }

    /// Current depth of the sensor's pipeline queue, frames.
    pub fn queue_depth(&self, depth: usize) {
        self.queue_depth
            .get_or_init(|| metrics::gauge!(QUEUE_DEPTH, "sensor" => self.sensor.clone()))
            .set(depth as f64);
    }

    /// A recording stopped on a write or sync error.
    pub fn recording_failed(&self) {
        self.counter(&self.recording_failures, RECORDING_FAILURES).increment(1);
    }

    /// A frame was written to a recording.
    pub fn frame_recorded(&self) {
        self.counter(&self.frames_recorded, FRAMES_RECORDED)
            .increment(1);
    }
}

/// The `sensor` label value of a sensor id: the id with every character the
/// Prometheus text format would have to escape (`\`, `"`) or could not show
/// (control characters) replaced by `_`, and at most 64 bytes. Ingest refuses
/// such ids anyway (`wire::check_sensor_id`); this keeps `/metrics`
/// well-formed whatever reaches it.
pub fn sensor_label(sensor: &str) -> String {
    let mut out = String::with_capacity(sensor.len().min(64));
    for c in sensor.chars() {
        if out.len() + c.len_utf8() > 64 {
            break;
        }
        out.push(if c == '\\' || c == '"' || c.is_control() { '_' } else { c });
    }
    out
}

/// A frame was decoded from an ingest message of a sensor that has no
/// session (sessions use [`SensorMetrics`]).
pub fn frame_received(sensor: &str) {
    metrics::counter!(FRAMES_RECEIVED, "sensor" => sensor_label(sensor)).increment(1);
}

/// `count` frames were refused for `reason` (one of [`REJECT_REASONS`]), for
/// a sensor without a session (sessions use [`SensorMetrics`]).
pub fn frames_rejected(sensor: &str, reason: &'static str, count: u64) {
    metrics::counter!(FRAMES_REJECTED, "sensor" => sensor_label(sensor), "reason" => reason)
        .increment(count);
}

/// `sensor` became faulted (see [`SENSOR_FAULTED`]).
pub fn sensor_faulted(sensor: &str) {
    metrics::gauge!(SENSOR_FAULTED, "sensor" => sensor_label(sensor)).set(1.0);
}

/// Cluster mode: this node claimed `sensor` (+1 owned) or let it go (-1).
pub fn cluster_sensor_owned(sensor: &str, claimed: bool) {
    if claimed {
        metrics::counter!(CLUSTER_CLAIMS, "sensor" => sensor_label(sensor)).increment(1);
    }
    metrics::gauge!(CLUSTER_SENSORS_OWNED).increment(if claimed { 1.0 } else { -1.0 });
}

/// Cluster mode: `count` frames of `sensor` replayed after a claim.
pub fn cluster_frames_replayed(sensor: &str, count: u64) {
    metrics::counter!(CLUSTER_FRAMES_REPLAYED, "sensor" => sensor_label(sensor)).increment(count);
}

/// A subscriber fell behind and `skipped` reports were dropped for it.
pub fn subscriber_lagged(skipped: u64) {
    metrics::counter!(SUBSCRIBER_LAGGED).increment(skipped);
}

/// A dashboard event stream opened (`+1`) or closed (`-1`).
pub fn dashboard_clients_changed(delta: f64) {
    metrics::gauge!(DASHBOARD_CLIENTS).increment(delta);
}

/// A subscription opened (`+1`) or closed (`-1`).
pub fn subscribers_changed(delta: f64) {
    metrics::gauge!(SUBSCRIBERS).increment(delta);
}
