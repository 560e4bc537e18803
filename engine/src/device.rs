//! Compute devices by name: `cpu`, `cuda` or `cuda:N`, as given on command lines and advertised
//! by workers.

use candle_core::{Device, DeviceLocation};

use crate::{EngineError, Result};

/// Opens the device named `cpu`, `cuda` (first GPU) or `cuda:N`.
pub fn parse_device(s: &str) -> Result<Device> {
    let expected = "expected cpu, cuda or cuda:N";
    if s == "cpu" {
        return Ok(Device::Cpu);
    }
    let ordinal = match s.strip_prefix("cuda") {
        Some("") => 0,
        Some(n) => n
            .strip_prefix(':')
            .and_then(|n| n.parse().ok())
            .ok_or_else(|| {
                EngineError::config("device", format!("cannot parse `{s}` ({expected})"))
            })?,
        None => {
            return Err(EngineError::config(
                "device",
                format!("unknown device `{s}` ({expected})"),
            ))
        }
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
