//! gRPC services and the wire contract. Only this module knows prost/tonic types.

/// Conversion between the wire `Frame` and the domain `Frame`, with validation that names the field.
pub mod convert;

/// Generated wire-contract types (`proto/tofwave/v1/*.proto`).
#[allow(missing_docs, clippy::all)]
pub mod proto {
    tonic::include_proto!("tofwave.v1");

    /// Encoded file descriptor set, for gRPC reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        tonic::include_file_descriptor_set!("tofwave_descriptor");
}
