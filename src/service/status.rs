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

/// Longest line of a client's input echoed in an error, characters.
const ECHO_LINE_CHARS: usize = 200;
/// Longest error message built from a client's input, bytes (well inside
/// the 4 MiB clients accept for a status).
const ECHO_MESSAGE_BYTES: usize = 4096;

/// `message` with each line longer than [`ECHO_LINE_CHARS`] cut there (an
/// ellipsis and the line's byte count follow) and the whole cut at
/// [`ECHO_MESSAGE_BYTES`]: parse errors quote the offending input, which can
/// be as large as the request.
pub(super) fn bounded(message: &str) -> String {
    let mut out = String::new();
    for (i, line) in message.split('\n').enumerate() {
        if i > 0 {
            out.push('\n');
        }
        match line.char_indices().nth(ECHO_LINE_CHARS) {
            Some((cut, _)) => {
                out.push_str(&line[..cut]);
                out.push_str(&format!("... ({} bytes)", line.len()));
            }
            None => out.push_str(line),
        }
        if out.len() > ECHO_MESSAGE_BYTES {
            let cut = (0..=ECHO_MESSAGE_BYTES).rev().find(|&k| out.is_char_boundary(k)).unwrap_or(0);
            out.truncate(cut);
            out.push_str(&format!("... ({} bytes in all)", message.len()));
            break;
        }
    }
    out
}

/// A bad scene: the message names the field (dotted path or TOML key); the
/// input it quotes is bounded ([`bounded`]).
pub(super) fn scene(e: SceneError) -> Status {
    let msg = match &e {
        SceneError::Invalid { error, .. } => format!("toml: {error}"),
        _ => format!("toml: {e}"),
    };
    Status::invalid_argument(bounded(&msg))
}

/// A scene that parsed but does not make a pipeline (`message` says why).
pub(super) fn pipeline_build(message: String) -> Status {
    Status::invalid_argument(bounded(&format!("toml: {message}")))
}

/// A sensor's session that could not be started for `SetScene`.
pub(super) fn start(e: StartError) -> Status {
    match e {
        StartError::Limit(_) => Status::resource_exhausted(format!("sensor_id: {e}")),
        StartError::Build(m) => pipeline_build(m),
    }
}

/// An error that ends an ingest stream: tonic's decoder reports the client's
/// bad input with server-side codes, so they are said as what they are.
/// - an over-limit message (OUT_OF_RANGE): INVALID_ARGUMENT naming the limit;
/// - a body that is not a `FrameBatch` (prost's decode error, INTERNAL in
///   tonic): INVALID_ARGUMENT;
/// - the compressed flag without a `grpc-encoding` header (INTERNAL, as the
///   gRPC spec words it): UNIMPLEMENTED, since the server accepts no
///   compression.
///
/// Other errors pass through. Unary calls (Control) decode before any
/// handler runs, so tonic's own codes reach their clients unchanged there.
pub(super) fn ingest_stream(status: Status, limit: usize) -> Status {
    let message = status.message();
    if status.code() == tonic::Code::OutOfRange && message.contains("too large") {
        telemetry::frames_rejected("", "oversize", 1);
        Status::invalid_argument(format!(
            "FrameBatch: message exceeds the server's limit of {limit} bytes ({message}); send smaller batches"
        ))
    } else if status.code() == tonic::Code::Internal && message.contains("compressed-flag") {
        Status::unimplemented(format!(
            "FrameBatch: compressed message: this server accepts uncompressed messages only ({message})"
        ))
    } else if status.code() == tonic::Code::Internal && is_decode_error(message) {
        telemetry::frames_rejected("", "invalid_frame", 1);
        Status::invalid_argument(format!("FrameBatch: not a valid protobuf message ({})", bounded(message)))
    } else {
        status
    }
}

/// Whether an INTERNAL status from tonic's decoder is prost's
/// `DecodeError` (its text starts "failed to decode Protobuf message").
fn is_decode_error(message: &str) -> bool {
    message.starts_with("failed to decode Protobuf message")
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::Code;

    #[test]
    fn echoed_input_is_bounded() {
        let long = format!("toml: line 1\nkey = \"{}\"\n^^^", "x".repeat(200_000));
        let b = bounded(&long);
        assert!(b.len() < 600, "{}", b.len());
        assert!(b.contains("... (200008 bytes)"), "{b}");
        assert!(b.starts_with("toml: line 1\nkey = \"xxx") && b.ends_with("^^^"), "{b}");
        let many = "y\n".repeat(100_000);
        assert!(bounded(&many).len() < ECHO_MESSAGE_BYTES + 64);
        assert_eq!(bounded("short"), "short");
    }

    #[test]
    fn decoder_errors_become_client_errors() {
        // prost's DecodeError text, as tonic-prost wraps it in INTERNAL.
        let s = ingest_stream(Status::internal("failed to decode Protobuf message: invalid wire type value: 7"), 1024);
        assert_eq!(s.code(), Code::InvalidArgument, "{s:?}");
        assert!(s.message().starts_with("FrameBatch: not a valid protobuf message"), "{s:?}");
        let s = ingest_stream(
            Status::internal("protocol error: received message with compressed-flag but no grpc-encoding was specified"),
            1024,
        );
        assert_eq!(s.code(), Code::Unimplemented, "{s:?}");
        let s = ingest_stream(Status::internal("something else"), 1024);
        assert_eq!(s.code(), Code::Internal);
    }
}
