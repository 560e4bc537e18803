//! Checkpoints: named tensors in safetensors plus typed JSON metadata (step, config, RNG
//! state…), written atomically so a crash at any moment leaves either the previous checkpoint
//! or the new one, never a torn file.
//!
//! Layout of a checkpoint folder: `step-00001234.safetensors` and `step-00001234.json`. The
//! tensors are written first (temporary name, then rename) and the JSON last: a checkpoint
//! exists once its JSON exists. The JSON holds the SHA-256 of the tensors file, so a truncated
//! or altered copy (a bad disk, an interrupted transfer) is recognised; loading also refuses
//! tensors with NaN or infinite values. [`CheckpointDir::latest`] passes over such a checkpoint
//! to the newest good one.
//!
//! A stage whose state is a folder of files rather than tensors (COLMAP's database and models
//! in `poses`) checkpoints it the same way: [`CheckpointDir::save_folder`] stores each file as
//! a `u8` tensor named by its relative path, so checksums, atomic writes, pruning, the
//! worker's uploads and the newest-good restore are the same for every stage.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

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
        let tensors_sha256 = sha256_file(&tmp)?;
        std::fs::rename(&tmp, &weights).map_err(|e| EngineError::io(&weights, e))?;
        let json = serde_json::to_vec_pretty(&Stored::Checked {
            tensors_sha256,
            meta,
        })
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

    /// The newest complete checkpoint that loads, if any. Checkpoints that do not (corrupt,
    /// truncated, non-finite values) are passed over with a warning: training resumes from
    /// the newest good one, or starts afresh.
    pub fn latest<M: DeserializeOwned>(&self, device: &Device) -> Result<Option<Checkpoint<M>>> {
        for &step in self.steps()?.iter().rev() {
            match self.load(step, device) {
                Ok(checkpoint) => return Ok(Some(checkpoint)),
                Err(error @ EngineError::Artifact { .. }) => {
                    tracing::warn!(step, %error, "passing over a bad checkpoint");
                }
                Err(error) => return Err(error),
            }
        }
        Ok(None)
    }

    /// Loads the checkpoint of `step`, checking its tensors against the checksum in its
    /// metadata and that every value is finite.
    pub fn load<M: DeserializeOwned>(&self, step: u64, device: &Device) -> Result<Checkpoint<M>> {
        let stem = Self::stem(step);
        let json_path = self.dir.join(format!("{stem}.json"));
        let bytes = std::fs::read(&json_path).map_err(|e| EngineError::io(&json_path, e))?;
        let stored: Stored<M> = serde_json::from_slice(&bytes).map_err(|e| {
            EngineError::artifact(&json_path, format!("unreadable checkpoint metadata: {e}"))
        })?;
        let weights = self.dir.join(format!("{stem}.safetensors"));
        let meta = match stored {
            Stored::Checked {
                tensors_sha256,
                meta,
            } => {
                let actual = sha256_file(&weights)?;
                if actual != tensors_sha256 {
                    return Err(EngineError::artifact(
                        &weights,
                        format!(
                            "checkpoint tensors do not match their checksum (SHA-256 {actual}, \
                             expected {tensors_sha256}): truncated or corrupt"
                        ),
                    ));
                }
                meta
            }
            Stored::Unchecked(meta) => meta,
        };
        let tensors = candle_core::safetensors::load(&weights, device).map_err(|e| {
            EngineError::artifact(&weights, format!("unreadable checkpoint tensors: {e}"))
        })?;
        for (name, tensor) in &tensors {
            if !all_finite(tensor)? {
                return Err(EngineError::artifact(
                    &weights,
                    format!("checkpoint tensor {name:?} holds NaN or infinite values"),
                ));
            }
        }
        Ok(Checkpoint {
            step,
            meta,
            tensors,
        })
    }

    /// Writes a checkpoint for `step` of the files under `root` ([`files_under`], each a `u8`
    /// tensor named by its path relative to `root`) and prunes old ones.
    pub fn save_folder<M: Serialize>(&self, step: u64, root: &Path, meta: &M) -> Result<()> {
        let mut tensors = Vec::new();
        for name in files_under(root)? {
            let path = root.join(&name);
            let bytes = std::fs::read(&path).map_err(|e| EngineError::io(&path, e))?;
            let len = bytes.len();
            tensors.push((name, Tensor::from_vec(bytes, len, &Device::Cpu)?));
        }
        self.save(step, &tensors, meta)
    }

    /// Restores the newest good folder checkpoint into `root` (emptied first); returns its
    /// step and metadata, or `None` when there is none.
    pub fn restore_folder<M: DeserializeOwned>(&self, root: &Path) -> Result<Option<(u64, M)>> {
        let Some(checkpoint) = self.latest::<M>(&Device::Cpu)? else {
            return Ok(None);
        };
        match std::fs::remove_dir_all(root) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(EngineError::io(root, e))
            }
            _ => {}
        }
        for (name, tensor) in &checkpoint.tensors {
            let relative = Path::new(name);
            let safe = relative
                .components()
                .all(|c| matches!(c, std::path::Component::Normal(_)));
            if !safe || tensor.dtype() != candle_core::DType::U8 {
                return Err(EngineError::artifact(
                    &self.dir,
                    format!("checkpoint {} holds {name:?}, not a file", checkpoint.step),
                ));
            }
            let path = root.join(relative);
            if let Some(parent) = path.parent() {
                std::fs::create_dir_all(parent).map_err(|e| EngineError::io(parent, e))?;
            }
            std::fs::write(&path, tensor.to_vec1::<u8>()?)
                .map_err(|e| EngineError::io(&path, e))?;
        }
        Ok(Some((checkpoint.step, checkpoint.meta)))
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

/// A checkpoint's JSON: the metadata with the tensors' checksum, or (written before
/// checksums) the metadata alone.
#[derive(Serialize, Deserialize)]
#[serde(untagged)]
enum Stored<M> {
    Checked { tensors_sha256: String, meta: M },
    Unchecked(M),
}

/// Tensor `name` of the safetensors file at `path` (already loaded as `tensors`) as f32
/// values, refused with the file and tensor named unless it has `shape`, which `source` sets.
pub fn f32_tensor(
    tensors: &HashMap<String, Tensor>,
    path: &Path,
    name: &str,
    shape: &[usize],
    source: &str,
) -> Result<Vec<f32>> {
    let t = tensors
        .get(name)
        .ok_or_else(|| EngineError::artifact(path, format!("tensor `{name}` missing")))?;
    if t.dims() != shape {
        return Err(EngineError::artifact(
            path,
            format!(
                "tensor `{name}` has shape {:?}, {source} implies {shape:?}",
                t.dims()
            ),
        ));
    }
    Ok(t.flatten_all()?.to_vec1()?)
}

/// `/`-separated paths of the regular files under `dir` (recursively), sorted, leaving out
/// hidden files and folders (temporary files of atomic writes start with `.`); none when `dir`
/// does not exist. What a folder checkpoint holds, and what a worker uploads of an output folder.
pub fn files_under(dir: &Path) -> Result<Vec<String>> {
    fn walk(dir: &Path, rel: &str, out: &mut Vec<String>) -> Result<()> {
        let entries = match std::fs::read_dir(dir) {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(EngineError::io(dir, e)),
        };
        for entry in entries {
            let entry = entry.map_err(|e| EngineError::io(dir, e))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') {
                continue;
            }
            let path = rel.to_string() + &name;
            let kind = entry
                .file_type()
                .map_err(|e| EngineError::io(entry.path(), e))?;
            if kind.is_dir() {
                walk(&entry.path(), &format!("{path}/"), out)?;
            } else if kind.is_file() {
                out.push(path);
            }
        }
        Ok(())
    }
    let mut out = Vec::new();
    walk(dir, "", &mut out)?;
    out.sort();
    Ok(out)
}

fn sha256_file(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).map_err(|e| EngineError::io(path, e))?;
    Ok(crate::style2d::weights::sha256_hex(&bytes))
}

/// Whether every value of a floating-point tensor is finite (`0·x` is 0 for finite `x` and NaN
/// otherwise), on any device; integer tensors always are.
fn all_finite(tensor: &Tensor) -> Result<bool> {
    if !tensor.dtype().is_float() {
        return Ok(true);
    }
    let residue = tensor
        .affine(0.0, 0.0)?
        .to_dtype(candle_core::DType::F32)?
        .sum_all()?
        .to_scalar::<f32>()?;
    Ok(residue == 0.0)
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

    fn save_steps(ck: &CheckpointDir, steps: &[u64]) {
        for &step in steps {
            let t = Tensor::full(step as f32, (4, 4), &Device::Cpu).unwrap();
            ck.save(step, &[("w".into(), t)], &(step as u32)).unwrap();
        }
    }

    #[test]
    fn bad_checkpoints_are_passed_over_naming_the_file() {
        let tmp = tempfile::tempdir().unwrap();
        let ck = CheckpointDir::new(tmp.path(), 10);
        save_steps(&ck, &[1, 2, 3, 4]);
        // Unreadable metadata, truncated tensors, NaN tensors (with a matching checksum, as a
        // diverged run would write them).
        std::fs::write(tmp.path().join("step-00000004.json"), b"{oops").unwrap();
        let weights = tmp.path().join("step-00000003.safetensors");
        let bytes = std::fs::read(&weights).unwrap();
        std::fs::write(&weights, &bytes[..bytes.len() / 2]).unwrap();
        let nan = Tensor::full(f32::NAN, (4, 4), &Device::Cpu).unwrap();
        ck.save(2, &[("w".into(), nan)], &2u32).unwrap();

        for (step, expect) in [
            (4, "metadata"),
            (3, "do not match their checksum"),
            (2, "NaN or infinite"),
        ] {
            let err = ck
                .load::<u32>(step, &Device::Cpu)
                .err()
                .unwrap()
                .to_string();
            assert!(
                err.contains(&format!("step-{step:08}")) && err.contains(expect),
                "{err}"
            );
        }
        let latest = ck.latest::<u32>(&Device::Cpu).unwrap().unwrap();
        assert_eq!((latest.step, latest.meta), (1, 1));
        std::fs::remove_file(tmp.path().join("step-00000001.safetensors")).unwrap();
        assert!(ck.latest::<u32>(&Device::Cpu).unwrap().is_none());
    }

    #[test]
    fn checkpoints_without_a_checksum_still_load() {
        let tmp = tempfile::tempdir().unwrap();
        let ck = CheckpointDir::new(tmp.path(), 1);
        save_steps(&ck, &[7]);
        std::fs::write(tmp.path().join("step-00000007.json"), b"7").unwrap();
        let loaded = ck.load::<u32>(7, &Device::Cpu).unwrap();
        assert_eq!(loaded.meta, 7);
    }

    #[test]
    fn a_folder_comes_back_as_it_was_saved_and_a_newer_one_replaces_it() {
        let tmp = tempfile::tempdir().unwrap();
        let work = tmp.path().join("work");
        std::fs::create_dir_all(work.join("sparse/0")).unwrap();
        std::fs::write(work.join("database.db"), b"\0\x01sqlite").unwrap();
        std::fs::write(work.join("sparse/0/images.bin"), b"").unwrap();
        let ck = CheckpointDir::new(tmp.path().join("ckpt"), 1);
        ck.save_folder(2, &work, &"two").unwrap();
        std::fs::write(work.join("stale.txt"), b"after the checkpoint").unwrap();
        let (step, meta) = ck.restore_folder::<String>(&work).unwrap().unwrap();
        assert_eq!((step, meta.as_str()), (2, "two"));
        assert_eq!(
            std::fs::read(work.join("database.db")).unwrap(),
            b"\0\x01sqlite"
        );
        assert!(work.join("sparse/0/images.bin").is_file());
        assert!(!work.join("stale.txt").exists());
        ck.save_folder(3, &work, &"three").unwrap();
        assert_eq!(ck.steps().unwrap(), [3]);
        let empty = CheckpointDir::new(tmp.path().join("none"), 1);
        assert!(empty.restore_folder::<String>(&work).unwrap().is_none());
    }

    #[test]
    fn lists_files_sorted_without_hidden_ones() {
        let dir = tempfile::tempdir().unwrap();
        let dir = dir.path();
        std::fs::create_dir_all(dir.join("ckpt")).unwrap();
        for f in ["b.json", "a.bin", "ckpt/step-1.json", ".tmp", "ckpt/.x.tmp"] {
            std::fs::write(dir.join(f), b"x").unwrap();
        }
        assert_eq!(
            files_under(dir).unwrap(),
            ["a.bin", "b.json", "ckpt/step-1.json"]
        );
        assert!(files_under(&dir.join("none")).unwrap().is_empty());
    }
}
