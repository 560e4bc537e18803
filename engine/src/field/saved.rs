//! The trained field as an artifact: `field.safetensors` (weights and occupancy) plus
//! `field.json` (architecture, bounds, sampling, cameras, metrics). The JSON is written last,
//! so a folder with `field.json` holds a complete field. When the dataset has ground-truth
//! depth for every training frame, `train_depth.safetensors` (`depth` [N, H, W], world units,
//! 0 = unknown) carries it to the later stages, which measure consistency with true geometry.

use std::path::Path;

use candle_core::Device;
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, Ndc};
use crate::checkpoint::write_atomic;
use crate::field::radiance::{FieldConfig, RadianceField};
use crate::field::space::FieldSpace;
use crate::rays::{RayBatch, SamplingConfig};
use crate::rng::Rng;
use crate::{EngineError, Result};

/// Everything besides the weights that later stages need to use a field.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FieldMeta {
    pub config: FieldConfig,
    pub sampling: SamplingConfig,
    /// The field's box, contraction and background.
    pub space: FieldSpace,
    pub near: f32,
    pub far: f32,
    pub ndc: Option<Ndc>,
    pub sigma_threshold: f32,
    /// Training cameras, in dataset order (the interpolated path follows them).
    pub train_cameras: Vec<Camera>,
    pub test_cameras: Vec<Camera>,
    /// Training steps the field was trained for.
    pub steps: u64,
}

impl FieldMeta {
    /// Rays of every pixel of `camera` in this field's space.
    pub fn camera_rays(&self, camera: &Camera) -> RayBatch {
        RayBatch::for_camera(camera, self.ndc.as_ref(), self.near, self.far)
    }
}

/// Writes a field into `dir`.
pub fn save(dir: &Path, field: &RadianceField, meta: &FieldMeta) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| EngineError::io(dir, e))?;
    let weights = dir.join("field.safetensors");
    let tmp = dir.join(".field.safetensors.tmp");
    let tensors: std::collections::HashMap<_, _> = field.tensors()?.into_iter().collect();
    candle_core::safetensors::save(&tensors, &tmp)?;
    std::fs::rename(&tmp, &weights).map_err(|e| EngineError::io(&weights, e))?;
    let json =
        serde_json::to_vec_pretty(meta).map_err(|e| EngineError::artifact(dir, e.to_string()))?;
    write_atomic(&dir.join("field.json"), &json)
}

/// The training frames' ground-truth depth: the file [`save_train_depth`] writes.
pub const TRAIN_DEPTH: &str = "train_depth.safetensors";

/// Writes the training frames' ground-truth depth (`depths[i]`: frame i's `width`×`height`
/// map) into `dir`. Call before [`save`], whose JSON marks the folder complete.
pub fn save_train_depth(dir: &Path, depths: &[&[f32]], width: u32, height: u32) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| EngineError::io(dir, e))?;
    let flat: Vec<f32> = depths.iter().flat_map(|d| d.iter().copied()).collect();
    let shape = (depths.len(), height as usize, width as usize);
    let tensor = candle_core::Tensor::from_vec(flat, shape, &Device::Cpu)?;
    let tmp = dir.join(".train_depth.safetensors.tmp");
    candle_core::safetensors::save(&std::collections::HashMap::from([("depth", tensor)]), &tmp)?;
    let path = dir.join(TRAIN_DEPTH);
    std::fs::rename(&tmp, &path).map_err(|e| EngineError::io(&path, e))
}

/// Reads the training frames' ground-truth depth of the field in `dir` as N·H·W values, `None`
/// when the dataset had none; `n`, `width` and `height` are the field's training cameras.
pub fn load_train_depth(dir: &Path, n: usize, width: u32, height: u32) -> Result<Option<Vec<f32>>> {
    let path = dir.join(TRAIN_DEPTH);
    if !path.exists() {
        return Ok(None);
    }
    let tensors = candle_core::safetensors::load(&path, &Device::Cpu)
        .map_err(|e| EngineError::artifact(&path, format!("unreadable depth: {e}")))?;
    let expected = [n, height as usize, width as usize];
    let depth = crate::checkpoint::f32_tensor(&tensors, &path, "depth", &expected, "field.json")?;
    Ok(Some(depth))
}

/// Reads the metadata of a field written by [`save`] (cameras, space, sampling), without
/// its weights.
pub fn load_meta(dir: &Path) -> Result<FieldMeta> {
    let json_path = dir.join("field.json");
    let bytes = std::fs::read(&json_path).map_err(|e| EngineError::io(&json_path, e))?;
    serde_json::from_slice(&bytes)
        .map_err(|e| EngineError::artifact(&json_path, format!("unreadable field metadata: {e}")))
}

/// Reads a field written by [`save`].
pub fn load(dir: &Path, device: &Device) -> Result<(RadianceField, FieldMeta)> {
    let meta = load_meta(dir)?;
    let weights = dir.join("field.safetensors");
    let tensors = candle_core::safetensors::load(&weights, device)
        .map_err(|e| EngineError::artifact(&weights, format!("unreadable field weights: {e}")))?;
    let mut field = RadianceField::new(meta.config, meta.space, &mut Rng::new(0), device)?;
    field.load_tensors(&tensors, &weights, meta.sigma_threshold)?;
    Ok((field, meta))
}
