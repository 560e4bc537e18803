//! Compiles `stylenerf/v1/*.proto` with `protox` (pure Rust, no system `protoc`) into a
//! `FileDescriptorSet`, generates the tonic/prost code from it, and writes the encoded set
//! to `$OUT_DIR/stylenerf_descriptor.bin` for server reflection.

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
    std::fs::write(
        out_dir.join("stylenerf_descriptor.bin"),
        prost::Message::encode_to_vec(&fds),
    )?;
    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        .compile_fds(fds)?;
    Ok(())
}
