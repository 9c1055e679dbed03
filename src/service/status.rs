//! The one place that maps errors to gRPC [`Status`]. Checks of a request
//! that fail in place (a bad field, shutdown begun) build their status where
//! they happen; everything that arrives as an error value is mapped here.

use super::ServiceError;
use super::session::StartError;
use crate::scene::SceneError;
use crate::telemetry;
use crate::wire::ConvertError;
use tonic::Status;

impl From<ServiceError> for Status {
    fn from(e: ServiceError) -> Status {
        match e {
            ServiceError::Scene { .. } => Status::invalid_argument(e.to_string()),
            _ => Status::internal(e.to_string()),
        }
    }
}

/// A request field the wire checks refused (the message names the field).
pub(super) fn invalid_field(e: ConvertError) -> Status {
    Status::invalid_argument(e.to_string())
}

/// A bad scene: the message names the field (dotted path or TOML key).
pub(super) fn scene(e: SceneError) -> Status {
    let msg = match &e {
        SceneError::Invalid { error, .. } => format!("toml: {error}"),
        _ => format!("toml: {e}"),
    };
    Status::invalid_argument(msg)
}

/// A scene that parsed but does not make a pipeline (`message` says why).
pub(super) fn pipeline_build(message: String) -> Status {
    Status::invalid_argument(format!("toml: {message}"))
}

/// A sensor's session that could not be started for `SetScene`.
pub(super) fn start(e: StartError) -> Status {
    match e {
        StartError::Limit(_) => Status::resource_exhausted(format!("sensor_id: {e}")),
        StartError::Build(m) => pipeline_build(m),
    }
}

/// An error that ends an ingest stream. An over-limit message fails in
/// tonic's decoder (OUT_OF_RANGE); say it as the bad-input error it is,
/// naming the limit. Other errors pass through.
pub(super) fn ingest_stream(status: Status, limit: usize) -> Status {
    if status.code() == tonic::Code::OutOfRange && status.message().contains("too large") {
        telemetry::frames_rejected("", "oversize", 1);
        Status::invalid_argument(format!(
            "FrameBatch: message exceeds the server's limit of {limit} bytes ({}); send smaller batches",
            status.message()
        ))
    } else {
        status
    }
}
