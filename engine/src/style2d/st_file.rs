//! Safetensors files with string metadata, written byte-for-byte deterministically (the
//! `safetensors` crate writes `__metadata__` in hash-map order; the header is re-serialised
//! with sorted keys) so that re-importing the same source reproduces the same SHA-256.

use std::collections::HashMap;
use std::path::Path;

use candle_core::Tensor;

use crate::{EngineError, Result};

/// Serialises named tensors with metadata.
pub fn to_bytes(
    path: &Path,
    tensors: &[(String, Tensor)],
    meta: &[(&str, String)],
) -> Result<Vec<u8>> {
    let fail = |e: String| EngineError::artifact(path, format!("safetensors encoding failed: {e}"));
    let meta: HashMap<String, String> = meta
        .iter()
        .map(|(k, v)| (k.to_string(), v.clone()))
        .collect();
    let mut bytes =
        safetensors::serialize(tensors.iter().map(|(k, t)| (k.as_str(), t)), Some(meta))
            .map_err(|e| fail(e.to_string()))?;
    let n = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")) as usize;
    let header: serde_json::Value = serde_json::from_slice(bytes[8..8 + n].trim_ascii_end())
        .map_err(|e| fail(e.to_string()))?;
    // serde_json's default map is a BTreeMap: keys come out sorted. Same content, same length.
    let sorted = serde_json::to_vec(&header).map_err(|e| fail(e.to_string()))?;
    bytes[8..8 + sorted.len()].copy_from_slice(&sorted);
    Ok(bytes)
}

/// Writes [`to_bytes`] to `path` atomically.
pub fn save(path: &Path, tensors: &[(String, Tensor)], meta: &[(&str, String)]) -> Result<()> {
    crate::checkpoint::write_atomic(path, &to_bytes(path, tensors, meta)?)
}

/// The `__metadata__` of a safetensors buffer (empty when it has none).
pub fn metadata(path: &Path, bytes: &[u8]) -> Result<HashMap<String, String>> {
    Ok(safetensors::SafeTensors::read_metadata(bytes)
        .map_err(|e| EngineError::artifact(path, format!("bad safetensors header: {e}")))?
        .1
        .metadata()
        .clone()
        .unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn output_is_deterministic_and_readable() {
        let t = Tensor::new(&[1f32, 2., 3.], &candle_core::Device::Cpu).unwrap();
        let tensors = vec![("b".to_string(), t.clone()), ("a".to_string(), t)];
        let meta: Vec<(&str, String)> = (0..12)
            .map(|i| {
                (
                    [
                        "k0", "k1", "k2", "k3", "k4", "k5", "k6", "k7", "k8", "k9", "ka", "kb",
                    ][i],
                    i.to_string(),
                )
            })
            .collect();
        let p = Path::new("x");
        let first = to_bytes(p, &tensors, &meta).unwrap();
        for _ in 0..5 {
            assert_eq!(to_bytes(p, &tensors, &meta).unwrap(), first);
        }
        assert_eq!(metadata(p, &first).unwrap()["k7"], "7");
        let back =
            candle_core::safetensors::load_buffer(&first, &candle_core::Device::Cpu).unwrap();
        assert_eq!(back["a"].to_vec1::<f32>().unwrap(), vec![1., 2., 3.]);
    }
}
