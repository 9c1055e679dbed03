//! The wire contract (`proto/tofwave/v1/*.proto`): the generated message
//! types and their conversion to and from the domain types of
//! [`frame`](crate::frame).
//!
//! Only this module knows the generated types' layout; it depends on
//! [`frame`](crate::frame) and nothing else in the crate, so the capture
//! formats (recordings) and the gRPC service both build on it. The gRPC
//! stubs themselves (tonic) live in [`service`](crate::service).

mod convert;
mod report;

pub use convert::{ConvertError, check_sensor_id, frame_from_proto, frame_to_proto};
pub use report::{noise_from_proto, noise_to_proto, report_from_json, report_to_proto};

/// Generated message types of `tofwave.v1` (prost only; no tonic).
#[allow(missing_docs, clippy::all)]
pub mod proto {
    include!(concat!(env!("OUT_DIR"), "/wire/tofwave.v1.rs"));
}
