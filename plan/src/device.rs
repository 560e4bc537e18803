//! Compute device names, `cpu`, `cuda` (the first GPU) or `cuda:N`, as given on command lines and
//! advertised by workers: parsed here once, for the engine (which opens the device) and the
//! coordinator (which checks what a worker advertises).

use crate::SettingError;

/// A parsed device name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DeviceName {
    Cpu,
    /// A CUDA GPU by ordinal (`cuda` is `cuda:0`).
    Cuda(usize),
}

impl std::str::FromStr for DeviceName {
    type Err = SettingError;

    fn from_str(s: &str) -> Result<Self, SettingError> {
        let expected = "expected cpu, cuda or cuda:N";
        if s == "cpu" {
            return Ok(DeviceName::Cpu);
        }
        match s.strip_prefix("cuda") {
            Some("") => Ok(DeviceName::Cuda(0)),
            Some(n) => n
                .strip_prefix(':')
                .and_then(|n| n.parse().ok())
                .map(DeviceName::Cuda)
                .ok_or_else(|| {
                    SettingError::new("device", format!("cannot parse `{s}` ({expected})"))
                }),
            None => Err(SettingError::new(
                "device",
                format!("unknown device `{s}` ({expected})"),
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_and_mistakes_are_explained() {
        assert_eq!("cpu".parse(), Ok(DeviceName::Cpu));
        assert_eq!("cuda".parse(), Ok(DeviceName::Cuda(0)));
        assert_eq!("cuda:3".parse(), Ok(DeviceName::Cuda(3)));
        let e = "gpu".parse::<DeviceName>().unwrap_err();
        assert!(e.reason.contains("unknown device `gpu`"), "{e}");
        let e = "cuda:x".parse::<DeviceName>().unwrap_err();
        assert!(e.reason.contains("cannot parse `cuda:x`"), "{e}");
    }
}
