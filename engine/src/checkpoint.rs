//! Checkpoints: named tensors in safetensors plus typed JSON metadata (step, config, RNG
//! state…), written atomically so a crash at any moment leaves either the previous checkpoint
//! or the new one, never a torn file.
//!
//! Layout of a checkpoint folder: `step-00001234.safetensors` and `step-00001234.json`. The
//! tensors are written first (temporary name, then rename) and the JSON last: a checkpoint
//! exists once its JSON exists.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::{EngineError, Result};

/// A checkpoint read back from disk.
pub struct Checkpoint<M> {
    pub step: u64,
    pub meta: M,
    pub tensors: HashMap<String, Tensor>,
}

/// A folder of checkpoints of one stage.
#[derive(Debug, Clone)]
pub struct CheckpointDir {
    dir: PathBuf,
    keep: usize,
}

impl CheckpointDir {
    /// Checkpoints in `dir`, keeping the newest `keep` (at least 1).
    pub fn new(dir: impl Into<PathBuf>, keep: usize) -> Self {
        Self {
            dir: dir.into(),
            keep: keep.max(1),
        }
    }

    pub fn path(&self) -> &Path {
        &self.dir
    }

    fn stem(step: u64) -> String {
        format!("step-{step:08}")
    }

    /// Writes a checkpoint for `step` and prunes old ones.
    pub fn save<M: Serialize>(
        &self,
        step: u64,
        tensors: &[(String, Tensor)],
        meta: &M,
    ) -> Result<()> {
        std::fs::create_dir_all(&self.dir).map_err(|e| EngineError::io(&self.dir, e))?;
        let stem = Self::stem(step);
        let weights = self.dir.join(format!("{stem}.safetensors"));
        let tmp = self.dir.join(format!(".{stem}.safetensors.tmp"));
        let map: HashMap<String, Tensor> = tensors.iter().cloned().collect();
        candle_core::safetensors::save(&map, &tmp)?;
        std::fs::rename(&tmp, &weights).map_err(|e| EngineError::io(&weights, e))?;
        let json = serde_json::to_vec_pretty(meta)
            .map_err(|e| EngineError::artifact(&weights, e.to_string()))?;
        write_atomic(&self.dir.join(format!("{stem}.json")), &json)?;
        self.prune()
    }

    /// Steps of the complete checkpoints present, ascending.
    pub fn steps(&self) -> Result<Vec<u64>> {
        let entries = match std::fs::read_dir(&self.dir) {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(EngineError::io(&self.dir, e)),
        };
        let mut steps: Vec<u64> = entries
            .filter_map(|e| e.ok())
            .filter_map(|e| {
                let name = e.file_name().into_string().ok()?;
                let step = name
                    .strip_prefix("step-")?
                    .strip_suffix(".json")?
                    .parse()
                    .ok()?;
                self.dir
                    .join(format!("{}.safetensors", Self::stem(step)))
                    .exists()
                    .then_some(step)
            })
            .collect();
        steps.sort_unstable();
        Ok(steps)
    }

    /// The newest complete checkpoint, if any.
    pub fn latest<M: DeserializeOwned>(&self, device: &Device) -> Result<Option<Checkpoint<M>>> {
        match self.steps()?.last() {
            Some(&step) => self.load(step, device).map(Some),
            None => Ok(None),
        }
    }

    /// Loads the checkpoint of `step`.
    pub fn load<M: DeserializeOwned>(&self, step: u64, device: &Device) -> Result<Checkpoint<M>> {
        let stem = Self::stem(step);
        let json_path = self.dir.join(format!("{stem}.json"));
        let bytes = std::fs::read(&json_path).map_err(|e| EngineError::io(&json_path, e))?;
        let meta = serde_json::from_slice(&bytes).map_err(|e| {
            EngineError::artifact(&json_path, format!("unreadable checkpoint metadata: {e}"))
        })?;
        let weights = self.dir.join(format!("{stem}.safetensors"));
        let tensors = candle_core::safetensors::load(&weights, device).map_err(|e| {
            EngineError::artifact(&weights, format!("unreadable checkpoint tensors: {e}"))
        })?;
        Ok(Checkpoint {
            step,
            meta,
            tensors,
        })
    }

    fn prune(&self) -> Result<()> {
        let steps = self.steps()?;
        for &step in steps.iter().take(steps.len().saturating_sub(self.keep)) {
            let stem = Self::stem(step);
            // The JSON goes first so a half-pruned checkpoint is never taken as complete.
            for ext in ["json", "safetensors"] {
                let p = self.dir.join(format!("{stem}.{ext}"));
                std::fs::remove_file(&p).map_err(|e| EngineError::io(&p, e))?;
            }
        }
        Ok(())
    }
}

/// Writes `bytes` to `path` through a temporary file and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| EngineError::io(dir, e))?;
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = dir.join(format!(".{name}.tmp"));
    std::fs::write(&tmp, bytes).map_err(|e| EngineError::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| EngineError::io(path, e))
}

/// Writes `value` as pretty JSON to `path`, atomically.
pub fn write_json_atomic<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let bytes = serde_json::to_vec_pretty(value)
        .map_err(|e| EngineError::artifact(path, format!("cannot serialise: {e}")))?;
    write_atomic(path, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn save_latest_prune_and_torn_checkpoint() {
        let tmp = tempfile::tempdir().unwrap();
        let ck = CheckpointDir::new(tmp.path().join("ckpt"), 2);
        let dev = Device::Cpu;
        assert!(ck.latest::<u32>(&dev).unwrap().is_none());
        for step in [10u64, 20, 30] {
            let t = Tensor::full(step as f32, (2, 2), &dev).unwrap();
            ck.save(step, &[("w".into(), t)], &(step as u32)).unwrap();
        }
        assert_eq!(ck.steps().unwrap(), vec![20, 30]);
        // Tensors without JSON (crash between the two writes) are not a checkpoint.
        candle_core::safetensors::save(
            &HashMap::from([(
                "w".to_string(),
                Tensor::zeros(1, candle_core::DType::F32, &dev).unwrap(),
            )]),
            tmp.path().join("ckpt/step-00000040.safetensors"),
        )
        .unwrap();
        let latest = ck.latest::<u32>(&dev).unwrap().unwrap();
        assert_eq!((latest.step, latest.meta), (30, 30));
        assert_eq!(
            latest.tensors["w"].to_vec2::<f32>().unwrap(),
            vec![vec![30.0; 2]; 2]
        );
    }

    #[test]
    fn corrupt_metadata_names_the_file() {
        let tmp = tempfile::tempdir().unwrap();
        let ck = CheckpointDir::new(tmp.path(), 1);
        ck.save(
            1,
            &[(
                "w".into(),
                Tensor::zeros(1, candle_core::DType::F32, &Device::Cpu).unwrap(),
            )],
            &1u32,
        )
        .unwrap();
        std::fs::write(tmp.path().join("step-00000001.json"), b"{oops").unwrap();
        let err = ck.latest::<u32>(&Device::Cpu).err().unwrap().to_string();
        assert!(
            err.contains("step-00000001.json") && err.contains("metadata"),
            "{err}"
        );
    }
}
