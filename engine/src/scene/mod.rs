//! Scenes: posed photos with intrinsics, bounds and a train/test split, loaded from the
//! formats users already have (nerfstudio, NeRF-synthetic/Blender, LLFF) or generated.
//!
//! Every loader produces the same [`Scene`]; the rest of the engine never looks at file
//! formats.

use std::path::PathBuf;

use glam::Vec3;
use image::Rgb32FImage;
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, Ndc};

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
    /// Linear RGB in [0, 1], already composited on the scene background where the source had
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
    /// Colour of empty space: rendered colour = Σ w c + (1 − opacity) · background.
    pub background: [f32; 3],
}
