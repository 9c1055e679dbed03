//! Compiles the wire contract under `proto/` with protox (a pure-Rust protobuf
//! compiler), so a machine with only cargo builds tofwave: no system `protoc`.
//!
//! Two outputs, so that the layers stay apart: the messages alone (prost, no
//! tonic) for `wire::proto`, and the gRPC client and server stubs for
//! `service::grpc`, which refer to those messages by path instead of
//! generating them a second time.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let files = [
        "proto/tofwave/v1/frame.proto",
        "proto/tofwave/v1/report.proto",
        "proto/tofwave/v1/service.proto",
    ];
    for f in files {
        println!("cargo:rerun-if-changed={f}");
    }
    let fds = protox::compile(files, ["proto"])?;
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    // The encoded descriptor set feeds gRPC reflection.
    std::fs::write(
        out_dir.join("tofwave_descriptor.bin"),
        prost::Message::encode_to_vec(&fds),
    )?;
    // Messages: `OUT_DIR/wire/tofwave.v1.rs`, included by `wire::proto`.
    let wire_dir = out_dir.join("wire");
    std::fs::create_dir_all(&wire_dir)?;
    tonic_prost_build::configure()
        .out_dir(&wire_dir)
        .build_client(false)
        .build_server(false)
        // Sample payloads stay `bytes::Bytes`: decoding a batch does not copy them.
        .bytes(".tofwave.v1.Channel.samples")
        .compile_fds(fds.clone())?;
    // Services: `OUT_DIR/grpc/tofwave.v1.rs`, included by `service::grpc`.
    let grpc_dir = out_dir.join("grpc");
    std::fs::create_dir_all(&grpc_dir)?;
    tonic_prost_build::configure()
        .out_dir(&grpc_dir)
        .extern_path(".tofwave.v1", "crate::wire::proto")
        .compile_fds(fds)?;
    Ok(())
}
