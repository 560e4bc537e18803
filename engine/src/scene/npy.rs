//! Reading and writing `.npy` matrices on disk; the format itself is [`stylenerf_plan::npy`]'s,
//! shared with the coordinator's validation of uploads.

use std::path::Path;

pub use stylenerf_plan::npy::Matrix;
use stylenerf_plan::npy::{encode_matrix, parse_matrix};

use crate::{EngineError, Result};

/// Reads a 2-D `<f8`, `<f4` or `<u2` array (a trailing axis of length 1 is dropped); errors
/// name the file and the part of it that is wrong.
pub fn read_matrix(path: &Path) -> Result<Matrix> {
    let bytes = std::fs::read(path).map_err(|e| EngineError::io(path, e))?;
    parse_matrix(&bytes).map_err(|e| EngineError::dataset(path, e.field, e.reason))
}

/// Writes a 2-D `<f8` array.
pub fn write_matrix(path: &Path, m: &Matrix) -> Result<()> {
    std::fs::write(path, encode_matrix(m)).map_err(|e| EngineError::io(path, e))
}
