//! Compute devices by name: `cpu`, `cuda` or `cuda:N` (the names are parsed by
//! [`stylenerf_plan::device`], shared with the coordinator), opened for candle.

use candle_core::{Device, DeviceLocation};
use stylenerf_plan::device::DeviceName;

use crate::{EngineError, Result};

/// Opens the device named `cpu`, `cuda` (first GPU) or `cuda:N`.
pub fn parse_device(s: &str) -> Result<Device> {
    let ordinal = match s.parse::<DeviceName>()? {
        DeviceName::Cpu => return Ok(Device::Cpu),
        DeviceName::Cuda(ordinal) => ordinal,
    };
    Device::new_cuda(ordinal).map_err(|e| {
        EngineError::config(
            "device",
            format!("`{s}`: CUDA is not available (build with `--features cuda`): {e}"),
        )
    })
}

/// The canonical name of a device: `cpu`, `cuda:N` (or `metal:N`).
pub fn device_name(device: &Device) -> String {
    match device.location() {
        DeviceLocation::Cpu => "cpu".to_string(),
        DeviceLocation::Cuda { gpu_id } => format!("cuda:{gpu_id}"),
        DeviceLocation::Metal { gpu_id } => format!("metal:{gpu_id}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_names_and_explains_mistakes() {
        assert_eq!(device_name(&parse_device("cpu").unwrap()), "cpu");
        let err = parse_device("gpu").unwrap_err().to_string();
        assert!(
            err.contains("device") && err.contains("unknown device `gpu`"),
            "{err}"
        );
        let err = parse_device("cuda:x").unwrap_err().to_string();
        assert!(err.contains("cannot parse `cuda:x`"), "{err}");
    }
}
