//! The `stylenerf.v1` gRPC protocol: messages and tonic clients/servers for the job, worker and
//! artifact services, generated at build time from `proto/stylenerf/v1/*.proto` (see those
//! files for the documentation of every message and RPC).

pub mod chunks;

/// Generated code of the `stylenerf.v1` package.
pub mod v1 {
    tonic::include_proto!("stylenerf.v1");
    // The proto JSON mapping of every message (serde `Serialize`/`Deserialize`).
    include!(concat!(env!("OUT_DIR"), "/stylenerf.v1.serde.rs"));
}

/// The encoded `FileDescriptorSet` of the protocol, for gRPC server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/stylenerf_descriptor.bin"));

pub use v1::*;
