//! Rays and their samples, the vocabulary below both the field (which evaluates samples) and
//! the renderer (which marches rays into samples and composites them): field-space ray batches
//! and how their distances map to depth, packed samples, and the sampling settings.

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, Ndc, Ray};

/// Sampling settings shared by training and rendering.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SamplingConfig {
    /// Steps across the scene box's diagonal (world scenes) or across the NDC depth range.
    pub steps_per_diagonal: usize,
    pub max_samples_per_ray: usize,
    /// Samples after the transmittance falls below this are skipped.
    pub early_stop_eps: f32,
}

/// How a distance `t` along a field-space ray maps to camera z-depth in world units.
#[derive(Debug, Clone, Copy)]
pub enum DepthModel {
    /// World-space ray with unit direction: z = t · z_per_t.
    Linear { z_per_t: f32 },
    /// NDC ray: NDC z → world z of the shared frame → distance along the original world ray
    /// (origin z `oz`, unit direction z `dz`) → z-depth.
    Ndc {
        ndc_oz: f32,
        ndc_dz: f32,
        oz: f32,
        dz: f32,
        z_per_t: f32,
        near: f32,
    },
}

impl DepthModel {
    #[inline]
    pub fn depth(&self, t: f32) -> f32 {
        match *self {
            DepthModel::Linear { z_per_t } => t * z_per_t,
            DepthModel::Ndc {
                ndc_oz,
                ndc_dz,
                oz,
                dz,
                z_per_t,
                near,
            } => {
                let z_ndc = (ndc_oz + t * ndc_dz).min(1.0 - 1e-6);
                let world_z = -2.0 * near / (1.0 - z_ndc);
                ((world_z - oz) / dz) * z_per_t
            }
        }
    }
}

/// Rays in field space.
#[derive(Debug, Clone, Default)]
pub struct RayBatch {
    pub origins: Vec<Vec3>,
    pub dirs: Vec<Vec3>,
    /// Unit world-space direction per ray (for the view-dependent colour).
    pub view_dirs: Vec<Vec3>,
    pub depth: Vec<DepthModel>,
    pub near: f32,
    pub far: f32,
}

impl RayBatch {
    pub fn len(&self) -> usize {
        self.origins.len()
    }

    pub fn is_empty(&self) -> bool {
        self.origins.is_empty()
    }

    /// Appends a world ray, converting it to NDC when the scene is forward-facing.
    pub fn push(&mut self, ray: &Ray, ndc: Option<&Ndc>) {
        match ndc {
            None => {
                self.origins.push(ray.origin);
                self.dirs.push(ray.dir);
                self.depth.push(DepthModel::Linear {
                    z_per_t: ray.z_per_t,
                });
            }
            Some(n) => {
                let (o, d) = n.ray(ray);
                self.origins.push(o);
                self.dirs.push(d);
                self.depth.push(DepthModel::Ndc {
                    ndc_oz: o.z,
                    ndc_dz: d.z,
                    oz: ray.origin.z,
                    dz: ray.dir.z,
                    z_per_t: ray.z_per_t,
                    near: n.near,
                });
            }
        }
        self.view_dirs.push(ray.dir);
    }

    /// One ray per pixel of `camera`, row-major.
    pub fn for_camera(camera: &Camera, ndc: Option<&Ndc>, near: f32, far: f32) -> RayBatch {
        let k = camera.intrinsics;
        let mut rays = RayBatch {
            near,
            far,
            ..Default::default()
        };
        for y in 0..k.height {
            for x in 0..k.width {
                rays.push(&camera.pixel_ray(x, y), ndc);
            }
        }
        rays
    }

    /// Appends all rays of `other`.
    pub fn extend(&mut self, other: &RayBatch) {
        self.origins.extend_from_slice(&other.origins);
        self.dirs.extend_from_slice(&other.dirs);
        self.view_dirs.extend_from_slice(&other.view_dirs);
        self.depth.extend_from_slice(&other.depth);
    }

    /// The rays with indices `idx`.
    pub fn select(&self, idx: &[usize]) -> RayBatch {
        RayBatch {
            origins: idx.iter().map(|&i| self.origins[i]).collect(),
            dirs: idx.iter().map(|&i| self.dirs[i]).collect(),
            view_dirs: idx.iter().map(|&i| self.view_dirs[i]).collect(),
            depth: idx.iter().map(|&i| self.depth[i]).collect(),
            near: self.near,
            far: self.far,
        }
    }
}

/// Packed samples of a batch of rays.
#[derive(Debug, Clone, Default)]
pub struct Samples {
    /// Field-space positions, 3 per sample.
    pub positions: Vec<f32>,
    /// Ray index of each sample.
    pub ray: Vec<u32>,
    pub packed: PackedRays,
}

impl Samples {
    /// Keeps the samples for which `keep` is true, preserving order and ray grouping.
    pub fn filter(&self, keep: &[bool]) -> Samples {
        let mut out = Samples {
            packed: PackedRays {
                offsets: vec![0],
                ..Default::default()
            },
            ..Default::default()
        };
        for w in self.packed.offsets.windows(2) {
            for k in (w[0] as usize..w[1] as usize).filter(|&k| keep[k]) {
                out.positions
                    .extend_from_slice(&self.positions[3 * k..3 * k + 3]);
                out.ray.push(self.ray[k]);
                out.packed.deltas.push(self.packed.deltas[k]);
                out.packed.depths.push(self.packed.depths[k]);
                out.packed.distances.push(self.packed.distances[k]);
            }
            out.packed.offsets.push(out.ray.len() as u32);
        }
        out
    }
}

/// Per-sample constants of a packed batch of rays.
#[derive(Debug, Clone, Default)]
pub struct PackedRays {
    /// Ray r owns samples `offsets[r]..offsets[r+1]`; length R + 1.
    pub offsets: Vec<u32>,
    /// Step length of each sample (in the units σ is measured in).
    pub deltas: Vec<f32>,
    /// Value averaged into the depth output (z-depth in world units).
    pub depths: Vec<f32>,
    /// Field-space distance along the ray to the start of each sample's interval (the
    /// distortion loss's coordinate; gaps where empty cells were skipped included).
    pub distances: Vec<f32>,
}

impl PackedRays {
    pub fn num_rays(&self) -> usize {
        self.offsets.len() - 1
    }

    pub fn num_samples(&self) -> usize {
        self.deltas.len()
    }
}
