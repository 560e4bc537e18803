//! PyTorch `.pth` state dicts. Only the zip format (torch ≥ 1.6) is readable; a legacy pickle
//! gets an error that says how to convert it.

use std::path::Path;

use super::StateDict;
use crate::{EngineError, Result};

/// Reads every tensor of a zip-format `.pth` file (a plain state dict, or one stored under
/// the `state_dict` key).
pub(crate) fn read_state_dict(path: &Path) -> Result<StateDict> {
    let read = |key: Option<&str>| -> Result<StateDict> {
        let tensors = candle_core::pickle::read_all_with_key(path, key)
            .map_err(|e| EngineError::artifact(path, format!("cannot read PyTorch file: {e}")))?;
        Ok(tensors.into_iter().collect())
    };
    let sd = read(None)?;
    if !sd.is_empty() {
        return Ok(sd);
    }
    let sd = read(Some("state_dict")).unwrap_or_default();
    if sd.is_empty() {
        return Err(EngineError::artifact(
            path,
            "no tensors found in this PyTorch file",
        ));
    }
    Ok(sd)
}

/// The error for a pre-1.6 pickle `.pth`, with the one-line conversion.
pub(crate) fn legacy_pickle_error(path: &Path) -> EngineError {
    EngineError::artifact(
        path,
        format!(
            "this is a legacy (pre-1.6) PyTorch pickle file, which cannot be read without \
             PyTorch; convert it once to the zip format with a recent torch: python -c \
             \"import torch; torch.save(torch.load('{0}'), '{0}.zip.pth')\" and import the \
             new file",
            path.display()
        ),
    )
}
