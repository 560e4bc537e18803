//! Compiles `stylenerf/v1/*.proto` with `protox` (pure Rust, no system `protoc`) into a
//! `FileDescriptorSet`, generates the tonic/prost code from it, and writes the encoded set
//! to `$OUT_DIR/stylenerf_descriptor.bin` for server reflection, and the messages' proto JSON
//! mapping (serde, with pbjson-build) to `$OUT_DIR/stylenerf.v1.serde.rs`.

use std::path::PathBuf;

const PROTOS: &[&str] = &[
    "stylenerf/v1/common.proto",
    "stylenerf/v1/jobs.proto",
    "stylenerf/v1/worker.proto",
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    for proto in PROTOS {
        println!("cargo:rerun-if-changed={proto}");
    }
    let fds = protox::compile(PROTOS, ["."])?;
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    let encoded = prost::Message::encode_to_vec(&fds);
    std::fs::write(out_dir.join("stylenerf_descriptor.bin"), &encoded)?;
    // Proto JSON with the .proto field names (`created_at_ms`; every proto JSON parser also
    // accepts them), defaults included so that scripts find every field.
    pbjson_build::Builder::new()
        .register_descriptors(&encoded)?
        .preserve_proto_field_names()
        .emit_fields()
        .build(&[".stylenerf"])?;
    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        .compile_fds(fds)?;
    Ok(())
}
