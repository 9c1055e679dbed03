//! Compiles the wire contract under `proto/` with protox (a pure-Rust protobuf
//! compiler), so a machine with only cargo builds tofwave: no system `protoc`.

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
    tonic_prost_build::configure()
        // Sample payloads stay `bytes::Bytes`: decoding a batch does not copy them.
        .bytes(".tofwave.v1.Channel.samples")
        .compile_fds(fds)?;
    Ok(())
}
