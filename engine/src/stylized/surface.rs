//! What the stylized NeRF needs of the frozen field, computed once per view: for every pixel's
//! ray, the samples that contribute to its colour, with their compositing weights
//! w_k = T_k (1 − exp(−σ_k δ_k)), geometry features and normalised positions.
//!
//! Density is frozen after pretraining, so these weights never change: the stylized colour of
//! a ray is Σ_k w_k c_s(x_k, l) + (1 − Σ_k w_k) · background, linear in the style module's
//! colours. Caching the few samples per ray that carry weight (typically 2–8 on a surface, out
//! of the dozens a ray marches through) makes a mutual-learning step cost one small MLP pass
//! instead of a field evaluation along whole rays. Each ray also keeps its direction, which
//! the style module's background reads.

use candle_core::{Device, Tensor};

use crate::camera::Camera;
use crate::field::radiance::RadianceField;
use crate::field::saved::FieldMeta;
use crate::render::composite::median_depth;
use crate::render::march_field;
use crate::Result;

/// Samples with a compositing weight below this are dropped (their colour is invisible).
pub const MIN_WEIGHT: f32 = 1e-3;

/// At most this many samples are kept per ray (those of largest weight, rescaled to carry the
/// ray's whole kept weight), so the cache's size is bounded by the pixel count whatever the
/// field: a hazy field gives dozens of samples above `MIN_WEIGHT` per ray.
pub const MAX_SAMPLES_PER_RAY: usize = 12;

/// Rays evaluated per field pass when building the cache.
const CHUNK: usize = 8192;

/// The weighted samples of a set of rays, packed ray after ray.
#[derive(Debug, Clone, Default)]
pub struct SurfaceSamples {
    /// `offsets[r]..offsets[r + 1]` are ray r's samples; `num_rays + 1` entries.
    pub offsets: Vec<u32>,
    /// Compositing weight per sample.
    pub weights: Vec<f32>,
    /// Geometry features, `geometry_dim` per sample.
    pub geometry: Vec<f32>,
    /// Positions normalised to the field's box, 3 per sample.
    pub points01: Vec<f32>,
    /// z-depth (world units) per sample.
    pub depths: Vec<f32>,
    /// Unit world direction of each ray, 3 per ray (the background's input).
    pub directions: Vec<f32>,
    pub geometry_dim: usize,
}

/// A batch of surface samples as tensors, ready for the style module.
#[derive(Debug, Clone)]
pub struct SurfaceBatch {
    pub num_rays: usize,
    /// `[N, G]`.
    pub geometry: Tensor,
    /// `[N, 3]`.
    pub points01: Tensor,
    /// `[N, 1]`.
    pub weights: Tensor,
    /// `[N]` u32: the ray (row of the output) of each sample.
    pub ray: Tensor,
    /// `[R, 1]`: 1 − Σ weights, the background's share of each ray.
    pub transparency: Tensor,
    /// `[R, 3]`: each ray's unit world direction.
    pub directions: Tensor,
}

/// Keeps the `cap` samples of largest weight (in ray order), scaled so they carry the weight
/// of all of them: the ray's opacity, hence its background share, is unchanged.
fn cap_samples(samples: &mut Vec<(usize, f32)>, cap: usize) {
    if samples.len() <= cap {
        return;
    }
    let total: f32 = samples.iter().map(|s| s.1).sum();
    let mut by_weight = samples.clone();
    by_weight.sort_by(|a, b| b.1.total_cmp(&a.1));
    let floor = by_weight[cap - 1].1;
    let mut room = cap;
    samples.retain(|s| {
        let keep = room > 0 && s.1 >= floor;
        room -= keep as usize;
        keep
    });
    let kept: f32 = samples.iter().map(|s| s.1).sum();
    for s in samples.iter_mut() {
        s.1 *= total / kept;
    }
}

impl SurfaceSamples {
    pub fn num_rays(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// The surface samples of every pixel of `camera`, row-major.
    pub fn for_camera(field: &RadianceField, meta: &FieldMeta, camera: &Camera) -> Result<Self> {
        let rays = meta.camera_rays(camera);
        let g = field.config.geometry_features;
        let mut out = SurfaceSamples {
            offsets: vec![0],
            geometry_dim: g,
            ..Default::default()
        };
        out.directions = rays.view_dirs.iter().flat_map(|d| d.to_array()).collect();
        let idx: Vec<usize> = (0..rays.len()).collect();
        for part in idx.chunks(CHUNK) {
            let batch = rays.select(part);
            let marched = march_field(field, &batch, &meta.sampling, None);
            // The density network, front to back until each ray is opaque, gives σ for the
            // weights and the geometry features of the samples that keep one.
            let (_, values) = field.visible_geometry(&marched, MIN_WEIGHT)?;
            let mut kept: Vec<(usize, f32)> = Vec::new();
            for w in marched.packed.offsets.windows(2) {
                let mut transmittance = 1.0f32;
                kept.clear();
                for k in w[0] as usize..w[1] as usize {
                    if transmittance < MIN_WEIGHT {
                        // Every later weight is below the transmittance, hence dropped.
                        break;
                    }
                    let alpha = 1.0 - (-values.sigma[k] * marched.packed.deltas[k]).exp();
                    let weight = transmittance * alpha;
                    transmittance *= 1.0 - alpha;
                    if weight >= MIN_WEIGHT {
                        kept.push((k, weight));
                    }
                }
                cap_samples(&mut kept, MAX_SAMPLES_PER_RAY);
                for &(k, weight) in &kept {
                    out.weights.push(weight);
                    out.geometry
                        .extend_from_slice(&values.geometry[k * g..(k + 1) * g]);
                    out.points01
                        .extend_from_slice(&values.points01[3 * k..3 * k + 3]);
                    out.depths.push(marched.packed.depths[k]);
                }
                out.offsets.push(out.weights.len() as u32);
            }
        }
        Ok(out)
    }

    /// Surface z-depth of each ray, the median of its kept samples' weights
    /// ([`median_depth`], as rendered images have it), 0 where the opacity is below `min_opacity`.
    pub fn surface_depth(&self, min_opacity: f32) -> Vec<f32> {
        self.offsets
            .windows(2)
            .map(|w| {
                let r = w[0] as usize..w[1] as usize;
                let total: f32 = self.weights[r.clone()].iter().sum();
                if total < min_opacity {
                    return 0.0;
                }
                median_depth(&self.weights[r.clone()], &self.depths[r]).unwrap_or(0.0)
            })
            .collect()
    }

    /// The samples of the rays `rays` (in that order) as tensors on `device`.
    pub fn batch(&self, rays: &[usize], device: &Device) -> Result<SurfaceBatch> {
        let g = self.geometry_dim;
        let (mut geometry, mut points01, mut weights, mut ray) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let mut transparency = Vec::with_capacity(rays.len());
        let mut directions = Vec::with_capacity(3 * rays.len());
        for (row, &r) in rays.iter().enumerate() {
            directions.extend_from_slice(&self.directions[3 * r..3 * r + 3]);
            let (a, b) = (self.offsets[r] as usize, self.offsets[r + 1] as usize);
            geometry.extend_from_slice(&self.geometry[a * g..b * g]);
            points01.extend_from_slice(&self.points01[3 * a..3 * b]);
            weights.extend_from_slice(&self.weights[a..b]);
            ray.extend(std::iter::repeat_n(row as u32, b - a));
            transparency.push(1.0 - self.weights[a..b].iter().sum::<f32>());
        }
        let n = weights.len();
        Ok(SurfaceBatch {
            num_rays: rays.len(),
            geometry: Tensor::from_vec(geometry, (n, g), device)?,
            points01: Tensor::from_vec(points01, (n, 3), device)?,
            weights: Tensor::from_vec(weights, (n, 1), device)?,
            ray: Tensor::from_vec(ray, n, device)?,
            transparency: Tensor::from_vec(transparency, (rays.len(), 1), device)?,
            directions: Tensor::from_vec(directions, (rays.len(), 3), device)?,
        })
    }

    /// All rays as one batch.
    pub fn all(&self, device: &Device) -> Result<SurfaceBatch> {
        let rays: Vec<usize> = (0..self.num_rays()).collect();
        self.batch(&rays, device)
    }
}

impl SurfaceBatch {
    /// Composites per-sample colours `[N, 3]` with per-ray background colours `[R, 3]` (or
    /// `[1, 3]`): Σ_k w_k c_k + (1 − Σ_k w_k) · background, `[R, 3]`.
    pub fn composite(&self, colours: &Tensor, background: &Tensor) -> Result<Tensor> {
        let weighted = colours.broadcast_mul(&self.weights)?;
        let rgb = Tensor::zeros((self.num_rays, 3), colours.dtype(), colours.device())?
            .index_add(&self.ray, &weighted, 0)?;
        Ok((rgb + self.transparency.broadcast_mul(background)?)?)
    }
}

#[cfg(test)]
mod tests {
    use super::cap_samples;

    #[test]
    fn capping_keeps_the_heaviest_samples_in_order_and_the_opacity() {
        let mut s: Vec<(usize, f32)> = (0..20)
            .map(|k| (k, 0.01 + 0.001 * (k % 7) as f32))
            .collect();
        let total: f32 = s.iter().map(|s| s.1).sum();
        cap_samples(&mut s, 5);
        assert_eq!(s.len(), 5);
        assert!(s.windows(2).all(|w| w[0].0 < w[1].0));
        assert!(s.iter().all(|&(k, _)| k % 7 >= 5), "{s:?}");
        let kept: f32 = s.iter().map(|s| s.1).sum();
        assert!((kept - total).abs() < 1e-5);
        let mut short = vec![(3, 0.5)];
        cap_samples(&mut short, 5);
        assert_eq!(short, vec![(3, 0.5)]);
    }
}
