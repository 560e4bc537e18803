//! The `stylenerf.v1` gRPC protocol: messages and tonic clients/servers for the job, worker and
//! artifact services, generated at build time from `proto/stylenerf/v1/*.proto` (see those
//! files for the documentation of every message and RPC).

pub mod bearer;
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

/// The protocol's value of each stage of the catalogue ([`stylenerf_plan::Stage`]), matched by
/// name (`STAGE_NERF_PRETRAIN` is `nerf_pretrain`), so adding a stage to the catalogue needs
/// only its value in `common.proto`, and a test catches the two drifting apart.
impl From<stylenerf_plan::Stage> for v1::Stage {
    fn from(stage: stylenerf_plan::Stage) -> Self {
        v1::Stage::from_str_name(&format!("STAGE_{}", stage.name().to_ascii_uppercase()))
            .unwrap_or(v1::Stage::Unspecified)
    }
}

impl v1::Stage {
    /// The catalogue's stage of a protocol value (`None` for unspecified or unknown values).
    pub fn of(value: i32) -> Option<stylenerf_plan::Stage> {
        let name = v1::Stage::try_from(value).ok()?.as_str_name();
        stylenerf_plan::Stage::parse(&name.strip_prefix("STAGE_")?.to_ascii_lowercase())
    }
}

#[cfg(test)]
mod tests {
    use super::v1;
    use stylenerf_plan::Stage;

    #[test]
    fn every_stage_of_the_catalogue_has_its_protocol_value_and_back() {
        for stage in Stage::ALL {
            let value = v1::Stage::from(stage);
            assert_ne!(
                value,
                v1::Stage::Unspecified,
                "{stage} is missing in stage.proto"
            );
            assert_eq!(v1::Stage::of(value as i32), Some(stage));
        }
        assert_eq!(v1::Stage::of(v1::Stage::Unspecified as i32), None);
        assert_eq!(v1::Stage::of(999), None);
    }
}
