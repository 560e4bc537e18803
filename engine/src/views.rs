//! The output of the `render_views` stage and the input of every later stage: rendered RGB,
//! z-depth (each ray's median termination) and opacity for a list of cameras (training poses
//! and an interpolated path).
//!
//! On disk: `cameras.json` (size and the cameras), `views.safetensors` (`rgb` [N, H, W, 3],
//! `depth` [N, H, W] in world units along the camera axis, `opacity` [N, H, W], and
//! `true_depth` [N, H, W] when the dataset has ground-truth depth), and PNG
//! previews under `rgb/` and `depth/` for people. The safetensors file is written before the
//! JSON, so a folder with `cameras.json` is complete.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::{EngineError, Result};

/// Where a rendered view's camera came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum ViewKind {
    /// A training pose; `frame` indexes the scene's frames.
    Train { frame: usize },
    /// A pose on the interpolated camera path.
    Path,
}

/// One rendered view's metadata.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewInfo {
    pub name: String,
    #[serde(flatten)]
    pub kind: ViewKind,
    pub camera: Camera,
}

#[derive(Serialize, Deserialize)]
struct CamerasFile {
    width: u32,
    height: u32,
    views: Vec<ViewInfo>,
}

/// Rendered views with depth and opacity.
#[derive(Debug, Clone)]
pub struct RenderedViews {
    pub width: u32,
    pub height: u32,
    pub views: Vec<ViewInfo>,
    /// Interleaved RGB, view after view: N·H·W·3.
    pub rgb: Vec<f32>,
    /// z-depth per pixel: N·H·W.
    pub depth: Vec<f32>,
    /// Accumulated opacity per pixel: N·H·W.
    pub opacity: Vec<f32>,
    /// The dataset's ground-truth z-depth per pixel, N·H·W (0 where unknown and on the path's
    /// views), when the dataset has it.
    pub true_depth: Option<Vec<f32>>,
}

impl RenderedViews {
    pub fn len(&self) -> usize {
        self.views.len()
    }

    pub fn is_empty(&self) -> bool {
        self.views.is_empty()
    }

    fn pixels(&self) -> usize {
        (self.width * self.height) as usize
    }

    pub fn rgb(&self, i: usize) -> &[f32] {
        let n = self.pixels() * 3;
        &self.rgb[i * n..(i + 1) * n]
    }

    pub fn depth(&self, i: usize) -> &[f32] {
        let n = self.pixels();
        &self.depth[i * n..(i + 1) * n]
    }

    pub fn opacity(&self, i: usize) -> &[f32] {
        let n = self.pixels();
        &self.opacity[i * n..(i + 1) * n]
    }

    /// View `i`'s ground-truth depth, when the dataset has it.
    pub fn true_depth(&self, i: usize) -> Option<&[f32]> {
        let n = self.pixels();
        self.true_depth.as_ref().map(|d| &d[i * n..(i + 1) * n])
    }

    /// Indices of the views rendered at training poses.
    pub fn train_indices(&self) -> Vec<usize> {
        (0..self.len())
            .filter(|&i| matches!(self.views[i].kind, ViewKind::Train { .. }))
            .collect()
    }

    /// Indices of the views on the interpolated path, in path order.
    pub fn path_indices(&self) -> Vec<usize> {
        (0..self.len())
            .filter(|&i| self.views[i].kind == ViewKind::Path)
            .collect()
    }

    /// View `i`'s RGB as a [3, H, W] tensor.
    pub fn rgb_chw(&self, i: usize, device: &Device) -> Result<Tensor> {
        let (h, w) = (self.height as usize, self.width as usize);
        Ok(Tensor::from_slice(self.rgb(i), (h, w, 3), device)?
            .permute((2, 0, 1))?
            .contiguous()?)
    }

    /// Writes the views into `dir` (created if needed).
    pub fn save(&self, dir: &Path, near: f32, far: f32) -> Result<()> {
        let (n, h, w) = (self.len(), self.height as usize, self.width as usize);
        let dev = Device::Cpu;
        let mut tensors = HashMap::from([
            (
                "rgb".to_string(),
                Tensor::from_slice(&self.rgb, (n, h, w, 3), &dev)?,
            ),
            (
                "depth".to_string(),
                Tensor::from_slice(&self.depth, (n, h, w), &dev)?,
            ),
            (
                "opacity".to_string(),
                Tensor::from_slice(&self.opacity, (n, h, w), &dev)?,
            ),
        ]);
        if let Some(truth) = &self.true_depth {
            tensors.insert(
                "true_depth".to_string(),
                Tensor::from_slice(truth, (n, h, w), &dev)?,
            );
        }
        std::fs::create_dir_all(dir.join("rgb")).map_err(|e| EngineError::io(dir, e))?;
        std::fs::create_dir_all(dir.join("depth")).map_err(|e| EngineError::io(dir, e))?;
        for (i, v) in self.views.iter().enumerate() {
            crate::image_io::save_rgb_png(
                &dir.join("rgb").join(format!("{}.png", v.name)),
                self.width,
                self.height,
                self.rgb(i),
            )?;
            let preview =
                crate::image_io::depth_preview(self.width, self.height, self.depth(i), near, far);
            crate::image_io::save_png(
                &dir.join("depth").join(format!("{}.png", v.name)),
                &preview,
            )?;
        }
        let tmp = dir.join(".views.safetensors.tmp");
        candle_core::safetensors::save(&tensors, &tmp)?;
        let path = dir.join("views.safetensors");
        std::fs::rename(&tmp, &path).map_err(|e| EngineError::io(&path, e))?;
        let json = serde_json::to_vec_pretty(&CamerasFile {
            width: self.width,
            height: self.height,
            views: self.views.clone(),
        })
        .map_err(|e| EngineError::artifact(dir, e.to_string()))?;
        crate::checkpoint::write_atomic(&dir.join("cameras.json"), &json)
    }

    /// Reads views written by [`RenderedViews::save`].
    pub fn load(dir: &Path) -> Result<Self> {
        let cam_path = dir.join("cameras.json");
        let bytes = std::fs::read(&cam_path).map_err(|e| EngineError::io(&cam_path, e))?;
        let cams: CamerasFile = serde_json::from_slice(&bytes).map_err(|e| {
            EngineError::artifact(&cam_path, format!("unreadable cameras file: {e}"))
        })?;
        let path = dir.join("views.safetensors");
        let tensors = candle_core::safetensors::load(&path, &Device::Cpu)
            .map_err(|e| EngineError::artifact(&path, format!("unreadable views: {e}")))?;
        let (n, h, w) = (cams.views.len(), cams.height as usize, cams.width as usize);
        let take = |name: &str, shape: &[usize]| {
            crate::checkpoint::f32_tensor(&tensors, &path, name, shape, "cameras.json")
        };
        Ok(Self {
            width: cams.width,
            height: cams.height,
            rgb: take("rgb", &[n, h, w, 3])?,
            depth: take("depth", &[n, h, w])?,
            opacity: take("opacity", &[n, h, w])?,
            true_depth: match tensors.contains_key("true_depth") {
                true => Some(take("true_depth", &[n, h, w])?),
                false => None,
            },
            views: cams.views,
        })
    }
}
