//! Scenes: posed photos with intrinsics, bounds and a train/test split, loaded from the
//! formats users already have (nerfstudio, NeRF-synthetic/Blender, LLFF) or generated.
//!
//! Every loader produces the same [`Scene`]; the rest of the engine never looks at file
//! formats. [`Scene::load`] detects the format; `docs/SCENES.md` describes each one.

pub mod blender;
mod bounds;
mod distortion;
mod frames;
pub(crate) use frames::working_intrinsics;
pub mod generate;
mod images;
mod json;
pub mod llff;
pub mod nerfstudio;
pub mod npy;
mod paths;

use std::fmt;
use std::path::{Path, PathBuf};

use glam::Vec3;
use image::Rgb32FImage;
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, Ndc};
use crate::{EngineError, Result};

/// Axis-aligned box that contains the scene content, in the space the field works in (world
/// space, or NDC space for forward-facing scenes).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    pub fn size(&self) -> Vec3 {
        self.max - self.min
    }

    pub fn center(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }

    /// Entry and exit distances of a ray through the box, or `None` when it misses.
    pub fn intersect(&self, origin: Vec3, dir: Vec3) -> Option<(f32, f32)> {
        let inv = dir.recip();
        let t0 = (self.min - origin) * inv;
        let t1 = (self.max - origin) * inv;
        let tmin = t0.min(t1).max_element();
        let tmax = t0.max(t1).min_element();
        (tmax > tmin.max(0.0)).then_some((tmin.max(0.0), tmax))
    }
}

/// One posed photo.
#[derive(Debug, Clone)]
pub struct Frame {
    /// File name relative to the dataset root, used in messages and outputs.
    pub name: String,
    pub camera: Camera,
    /// RGB in [0, 1] as stored in the file (no gamma decoding, as in NeRF), already
    /// composited on the scene background where the source had
    /// alpha, and resized to the camera's intrinsics.
    pub image: Rgb32FImage,
    /// Ground-truth z-depth per pixel (row-major, world units; 0 where unknown), when the
    /// dataset has it (the generated scenes do).
    pub depth: Option<Vec<f32>>,
}

/// A loaded scene, ready for training.
#[derive(Debug, Clone)]
pub struct Scene {
    /// Dataset folder the scene was read from.
    pub root: PathBuf,
    pub frames: Vec<Frame>,
    /// Indices into `frames` used for training.
    pub train: Vec<usize>,
    /// Indices into `frames` held out for evaluation (may be empty only when the user asked
    /// for no test split).
    pub test: Vec<usize>,
    /// Box containing the content, in field space (world, or NDC when `ndc` is set).
    pub aabb: Aabb,
    /// Near and far distances along rays (world units; 0 and 1 in NDC).
    pub near: f32,
    pub far: f32,
    /// Set for forward-facing scenes: rays are converted to NDC before meeting the field.
    pub ndc: Option<Ndc>,
    /// Set for captures whose surroundings extend past `aabb` (photos without alpha and
    /// without a stated box): the field covers all of space, contracted into twice the box
    /// (see [`crate::field::space`]); `aabb` is then the region kept at full resolution.
    pub unbounded: bool,
    /// What rays that leave the content see: rendered colour = Σ w c + (1 − opacity) · bg.
    pub background: Background,
}

/// What lies behind the scene content.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Background {
    /// A known colour (RGBA datasets, or one the dataset or the user states): images with
    /// alpha are composited on it and empty space renders as it.
    Colour([f32; 3]),
    /// Photos of a real background: its colour is learned as a function of the view
    /// direction, so the photos need not be explained by haze in front of the content.
    Learned,
}

impl Background {
    /// The colour alpha channels are composited on (white when the background is learned: such
    /// datasets have no alpha).
    pub fn alpha_colour(&self) -> [f32; 3] {
        match self {
            Background::Colour(c) => *c,
            Background::Learned => [1.0; 3],
        }
    }
}

impl fmt::Display for Background {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Background::Colour([r, g, b]) => write!(f, "colour ({r:.3}, {g:.3}, {b:.3})"),
            Background::Learned => f.write_str("learned from the photos (view direction)"),
        }
    }
}

/// The dataset formats [`Scene::load`] understands (the catalogue's, which the coordinator
/// and the worker find uploads by).
pub use stylenerf_plan::SceneFormat;

/// The format of the dataset at `path` (a folder, or one of the marker files) and its
/// folder. A folder holding several formats is read as the first of nerfstudio, Blender,
/// LLFF.
pub fn detect(path: &Path) -> Result<(SceneFormat, PathBuf)> {
    if path.is_file() {
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default();
        let dir = paths::parent_dir(path).to_path_buf();
        return match name {
            blender::TRAIN | blender::VAL | blender::TEST => Ok((SceneFormat::Blender, dir)),
            llff::POSES_BOUNDS => Ok((SceneFormat::Llff, dir)),
            n if n.ends_with(".json") => Ok((SceneFormat::Nerfstudio, path.to_path_buf())),
            _ => Err(EngineError::dataset(
                path,
                "(format)",
                "not a dataset file: expected transforms.json, transforms_train.json or \
                 poses_bounds.npy",
            )),
        };
    }
    if !path.is_dir() {
        return Err(EngineError::dataset(
            path,
            "(path)",
            "no such file or folder",
        ));
    }
    SceneFormat::ALL
        .into_iter()
        .find(|f| path.join(f.marker()).is_file())
        .map(|f| (f, path.to_path_buf()))
        .ok_or_else(|| {
            EngineError::dataset(
                path,
                "(format)",
                "no transforms.json (nerfstudio), transforms_train.json (Blender) or \
                 poses_bounds.npy (LLFF) in this folder",
            )
        })
}

/// How to load a dataset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LoadOptions {
    /// Force a format instead of detecting it.
    pub format: Option<SceneFormat>,
    /// Integer factor to shrink images by (intrinsics follow). LLFF uses `images_<factor>/`
    /// when present.
    pub downscale: u32,
    /// Without an explicit split, every `test_every`-th frame (starting with the first) is a
    /// test frame; 0 means no test split.
    pub test_every: usize,
    /// Keep at most this many frames, shared between the splits and evenly spaced.
    pub max_frames: Option<usize>,
    /// Background colour to composite RGBA images on and to render empty space with. `None`:
    /// the dataset's own (`background` in a nerfstudio file); else white for RGBA images and
    /// a learned background for photos without alpha.
    pub background: Option<[f32; 3]>,
    /// Working resolution: shrink images (after `downscale`) so that their longest side is at
    /// most this many pixels; intrinsics follow. `None`: full size.
    pub max_side: Option<u32>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            format: None,
            downscale: 1,
            test_every: 8,
            max_frames: None,
            background: None,
            max_side: None,
        }
    }
}

impl LoadOptions {
    fn validate(&self) -> Result<()> {
        if self.downscale == 0 {
            return Err(EngineError::config("downscale", "must be at least 1"));
        }
        if self.max_frames == Some(0) {
            return Err(EngineError::config("max_frames", "must be at least 1"));
        }
        if let Some(side) = self.max_side {
            if !(MIN_SIDE..=MAX_SIDE).contains(&side) {
                return Err(EngineError::config(
                    "max_side",
                    format!("{side}: must be between {MIN_SIDE} and {MAX_SIDE} pixels"),
                ));
            }
        }
        if let Some(bg) = self.background {
            if !bg.iter().all(|c| (0.0..=1.0).contains(c)) {
                return Err(EngineError::config(
                    "background",
                    format!("{bg:?}: components must be in [0, 1]"),
                ));
            }
        }
        Ok(())
    }

    /// The background: the user's colour, else the dataset's, else learned for photos
    /// without alpha (`has_alpha`), else white.
    fn background_or(&self, dataset: Option<[f32; 3]>, has_alpha: bool) -> Background {
        match self.background.or(dataset) {
            Some(c) => Background::Colour(c),
            None if has_alpha => Background::Colour([1.0; 3]),
            None => Background::Learned,
        }
    }
}

/// Bounds of [`LoadOptions::max_side`].
pub const MIN_SIDE: u32 = 8;
pub const MAX_SIDE: u32 = 16384;

impl Scene {
    /// Loads the dataset at `path`: a folder, or a `transforms.json`,
    /// `transforms_train.json` or `poses_bounds.npy` file.
    pub fn load(path: impl AsRef<Path>, opts: &LoadOptions) -> Result<Scene> {
        let path = path.as_ref();
        let (format, found) = match opts.format {
            Some(f) if path.is_dir() => (f, path.join(f.marker())),
            Some(f) => (f, path.to_path_buf()),
            None => detect(path)?,
        };
        match format {
            SceneFormat::Nerfstudio if found.is_dir() => {
                nerfstudio::load(&found.join(nerfstudio::TRANSFORMS), opts)
            }
            SceneFormat::Nerfstudio => nerfstudio::load(&found, opts),
            SceneFormat::Blender => blender::load(dir_of(&found), opts),
            SceneFormat::Llff => llff::load(dir_of(&found), opts),
        }
    }

    /// Size of the first frame (all frames of the supported formats share it in practice).
    pub fn resolution(&self) -> (u32, u32) {
        self.frames.first().map_or((0, 0), |f| {
            (f.camera.intrinsics.width, f.camera.intrinsics.height)
        })
    }
}

/// The folder of a dataset given either as the folder or as a file in it.
fn dir_of(path: &Path) -> &Path {
    if path.is_dir() {
        path
    } else {
        paths::parent_dir(path)
    }
}

/// Errors out when a split that must not be empty is.
fn require_split(
    split: &frames::Split,
    opts: &LoadOptions,
    file: &Path,
    field: &str,
) -> Result<()> {
    if split.train.is_empty() {
        return Err(EngineError::dataset(
            file,
            field,
            "the training split is empty",
        ));
    }
    if split.test.is_empty() && opts.test_every > 0 {
        return Err(EngineError::dataset(
            file,
            field,
            "the test split is empty (set test_every to 0 to train without one)",
        ));
    }
    Ok(())
}
