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

/// Samples per ray in the first round of [`Samples::front_to_back`]; each later round doubles.
const FIRST_ROUND: usize = 16;

impl Samples {
    /// Positions of the samples at `idx`, 3 per sample.
    pub fn positions_of(&self, idx: &[usize]) -> Vec<f32> {
        idx.iter()
            .flat_map(|&k| self.positions[3 * k..3 * k + 3].iter().copied())
            .collect()
    }

    /// Which samples each ray still sees — those with a transmittance of at least `eps` in
    /// front of them — and σ, evaluated front to back: each round asks `sigma_at` for the next
    /// samples (16, then 32, 64, …) of every ray that is not yet opaque, so the samples behind
    /// the point where a ray turns opaque are never evaluated (their σ is left at 0). In a
    /// field that is opaque everywhere (an indoor capture) the occupancy grid skips nothing
    /// behind the first wall, and this is most of the marched samples.
    pub fn front_to_back(
        &self,
        eps: f32,
        mut sigma_at: impl FnMut(&[usize]) -> crate::Result<Vec<f32>>,
    ) -> crate::Result<(Vec<bool>, Vec<f32>)> {
        let n = self.ray.len();
        let (mut keep, mut sigma) = (vec![false; n], vec![0.0f32; n]);
        // (next sample, end, transmittance in front of it) of every ray still open.
        let mut open: Vec<(usize, usize, f32)> = self
            .packed
            .offsets
            .windows(2)
            .map(|w| (w[0] as usize, w[1] as usize, 1.0))
            .filter(|&(k, end, _)| k < end)
            .collect();
        let mut round = FIRST_ROUND;
        while !open.is_empty() {
            let idx: Vec<usize> = open
                .iter()
                .flat_map(|&(k, end, _)| k..end.min(k + round))
                .collect();
            for (&k, s) in idx.iter().zip(sigma_at(&idx)?) {
                sigma[k] = s;
            }
            open.retain_mut(|(k, end, trans)| {
                let stop = (*end).min(*k + round);
                while *k < stop && *trans >= eps {
                    keep[*k] = true;
                    *trans *= (-sigma[*k] * self.packed.deltas[*k]).exp();
                    *k += 1;
                }
                *k < *end && *trans >= eps
            });
            round *= 2;
        }
        Ok((keep, sigma))
    }

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

#[cfg(test)]
mod tests {
    use super::*;

    /// Rays of the given σ per sample, each sample one unit long.
    fn samples(rays: &[Vec<f32>]) -> Samples {
        let mut s = Samples {
            packed: PackedRays {
                offsets: vec![0],
                ..Default::default()
            },
            ..Default::default()
        };
        for (r, sigma) in rays.iter().enumerate() {
            for k in 0..sigma.len() {
                s.positions.extend([k as f32, 0.0, 0.0]);
                s.ray.push(r as u32);
                s.packed.deltas.push(1.0);
                s.packed.depths.push(k as f32);
                s.packed.distances.push(k as f32);
            }
            s.packed.offsets.push(s.ray.len() as u32);
        }
        s
    }

    #[test]
    fn front_to_back_keeps_samples_until_opaque_and_evaluates_no_further() {
        let mut wall = vec![0.0; 200];
        wall[20] = 50.0;
        let rays = vec![vec![0.0, 20.0, 1.0, 1.0], vec![0.01; 100], wall, vec![]];
        let s = samples(&rays);
        let sigma: Vec<f32> = rays.concat();
        let mut evaluated = Vec::new();
        let (keep, got) = s
            .front_to_back(1e-4, |idx| {
                evaluated.extend_from_slice(idx);
                Ok(idx.iter().map(|&k| sigma[k]).collect())
            })
            .unwrap();
        // The same as walking every ray with every σ known.
        let mut expected = Vec::new();
        for ray in &rays {
            let mut trans = 1.0f32;
            for &sg in ray {
                expected.push(trans >= 1e-4);
                trans *= (-sg).exp();
            }
        }
        assert_eq!(keep, expected);
        assert_eq!(&keep[..4], &[true, true, false, false]);
        assert!(
            keep[4..104].iter().all(|&k| k),
            "a thin ray is seen to its end"
        );
        let wall_start = 104;
        assert_eq!(keep[wall_start..].iter().filter(|&&k| k).count(), 21);
        // The wall's ray is evaluated in rounds of 16 and 32 samples and then left alone.
        let on_wall: Vec<usize> = evaluated
            .iter()
            .filter(|&&k| k >= wall_start)
            .copied()
            .collect();
        assert_eq!(on_wall, (wall_start..wall_start + 48).collect::<Vec<_>>());
        for &k in &evaluated {
            assert_eq!(got[k], sigma[k]);
        }
        assert_eq!(s.positions_of(&[1, 3]), vec![1.0, 0.0, 0.0, 3.0, 0.0, 0.0]);
    }
}
