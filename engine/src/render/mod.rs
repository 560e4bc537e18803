//! Rendering a radiance field: ray marching through the occupancy grid, pruning samples behind
//! opaque surfaces, evaluating the field, compositing, and whole images in chunks.

pub mod composite;
pub mod depth_supervision;
pub mod distortion;
pub mod march;
pub mod weight_loss;

use std::sync::Arc;

use candle_core::Tensor;

use crate::field::radiance::{FieldSamples, RadianceField};
use crate::rays::{DepthModel, PackedRays, RayBatch, Samples, SamplingConfig};
use crate::render::composite::{composite, median_depth, sample_weights, split_with_background};
use crate::render::march::march;
use crate::rng::Rng;
use crate::Result;

/// Rendered rays.
pub struct RenderOutput {
    /// Colour over the background [R, 3].
    pub rgb: Tensor,
    /// Expected z-depth [R] (world units; weighted by opacity, so divide by it for a surface
    /// depth).
    pub depth: Tensor,
    /// Accumulated opacity [R].
    pub opacity: Tensor,
    /// Samples evaluated with gradients.
    pub num_samples: usize,
    /// σ of the evaluated samples [S] and their packing (for regularisers on the weights);
    /// `None` when no ray had a sample.
    pub samples: Option<(Tensor, Arc<PackedRays>)>,
}

/// The colour of evaluated samples: the field's own colour head, or a style module.
pub type ColourFn<'a> = dyn Fn(&FieldSamples) -> Result<Tensor> + 'a;

/// Step length for a scene box (or the NDC range).
pub fn step_size(field: &RadianceField, rays: &RayBatch, cfg: &SamplingConfig) -> f32 {
    let span = if rays
        .depth
        .first()
        .is_some_and(|d| matches!(d, DepthModel::Ndc { .. }))
    {
        rays.far - rays.near
    } else {
        field.space.aabb.size().length()
    };
    span / cfg.steps_per_diagonal as f32
}

/// Marches `rays` through `field`'s occupied cells (in its space: box, NDC or contracted) with
/// the step of `cfg`; with `rng`, sample positions are jittered (training).
pub fn march_field(
    field: &RadianceField,
    rays: &RayBatch,
    cfg: &SamplingConfig,
    rng: Option<&mut Rng>,
) -> Samples {
    march(
        rays,
        &field.occupancy,
        field.space.contraction.as_ref(),
        step_size(field, rays, cfg),
        cfg.max_samples_per_ray,
        rng,
    )
}

/// Renders `rays` through `field` with colours from `colour` over the field's background.
/// With `rng`, sample positions are jittered (training).
pub fn render_rays(
    field: &RadianceField,
    rays: &RayBatch,
    cfg: &SamplingConfig,
    colour: &ColourFn,
    rng: Option<&mut Rng>,
) -> Result<RenderOutput> {
    let marched = march_field(field, rays, cfg, rng);
    // Cheap gradient-free density passes, front to back, find where each ray becomes opaque;
    // they keep the hash encoding of what they evaluate, which the gradient pass reuses.
    let width = field.config.grid.output_dim();
    let (mut row, mut encodings) = (vec![0usize; marched.ray.len()], Vec::new());
    let (keep, _) = marched.front_to_back(cfg.early_stop_eps, |idx| {
        let (sigma, encoding) = field.density_and_encoding(&marched.positions_of(idx))?;
        for (j, &k) in idx.iter().enumerate() {
            row[k] = encodings.len() / width + j;
        }
        encodings.extend(encoding);
        Ok(sigma)
    })?;
    let samples = marched.filter(&keep);
    let evaluated = if samples.ray.is_empty() {
        None
    } else {
        // Every kept sample was evaluated (a ray keeps only samples in front of its opaque
        // point, and those are evaluated first).
        let kept: Vec<f32> = (0..keep.len())
            .filter(|&k| keep[k])
            .flat_map(|k| {
                encodings[row[k] * width..(row[k] + 1) * width]
                    .iter()
                    .copied()
            })
            .collect();
        Some(field.encoded_samples(&samples, kept, &rays.view_dirs)?)
    };
    finish(field, rays, &samples, evaluated, colour)
}

/// [`render_rays`] for inference: no jitter and no gradients, so the density passes that
/// find where each ray becomes opaque also give the kept samples' σ and geometry features.
fn render_rays_inference(
    field: &RadianceField,
    rays: &RayBatch,
    cfg: &SamplingConfig,
    colour: &ColourFn,
) -> Result<RenderOutput> {
    let marched = march_field(field, rays, cfg, None);
    let (keep, values) = field.visible_geometry(&marched, cfg.early_stop_eps)?;
    let samples = marched.filter(&keep);
    let evaluated = if samples.ray.is_empty() {
        None
    } else {
        Some(field.kept_samples(&values, &keep, &samples, &rays.view_dirs)?)
    };
    finish(field, rays, &samples, evaluated, colour)
}

/// Colours and composites the evaluated samples of `rays` (none: every ray is background).
fn finish(
    field: &RadianceField,
    rays: &RayBatch,
    samples: &Samples,
    evaluated: Option<FieldSamples>,
    colour: &ColourFn,
) -> Result<RenderOutput> {
    let (out, sampled) = match evaluated {
        None => (
            Tensor::zeros((rays.len(), 5), candle_core::DType::F32, field.device())?,
            None,
        ),
        Some(evaluated) => {
            let rgb = colour(&evaluated)?;
            let packed = Arc::new(samples.packed.clone());
            let out = composite(&evaluated.sigma, &rgb, &packed)?;
            (out, Some((evaluated.sigma, packed)))
        }
    };
    let background = field.background(&rays.view_dirs)?;
    let (rgb, depth, opacity) = split_with_background(&out, &background)?;
    Ok(RenderOutput {
        rgb,
        depth,
        opacity,
        num_samples: samples.ray.len(),
        samples: sampled,
    })
}

/// A rendered image: interleaved RGB, z-depth (the median of each ray's termination,
/// [`median_depth`]; 0 where nothing is opaque) and opacity, row-major.
pub struct ImageOutput {
    pub rgb: Vec<f32>,
    pub depth: Vec<f32>,
    pub opacity: Vec<f32>,
}

/// Renders all `rays` in chunks without gradients (e.g. a whole image).
pub fn render_image(
    field: &RadianceField,
    rays: &RayBatch,
    cfg: &SamplingConfig,
    colour: &ColourFn,
    chunk: usize,
) -> Result<ImageOutput> {
    let mut img = ImageOutput {
        rgb: Vec::with_capacity(rays.len() * 3),
        depth: Vec::with_capacity(rays.len()),
        opacity: Vec::with_capacity(rays.len()),
    };
    let idx: Vec<usize> = (0..rays.len()).collect();
    for part in idx.chunks(chunk.max(1)) {
        let out = render_rays_inference(field, &rays.select(part), cfg, colour)?;
        img.rgb
            .extend(out.rgb.detach().flatten_all()?.to_vec1::<f32>()?);
        let opacity: Vec<f32> = out.opacity.detach().to_vec1()?;
        match &out.samples {
            Some((sigma, packed)) => {
                let weights = sample_weights(&sigma.detach().to_vec1()?, packed);
                img.depth
                    .extend(packed.offsets.windows(2).zip(&opacity).map(|(r, o)| {
                        let r = r[0] as usize..r[1] as usize;
                        if *o > 1e-3 {
                            median_depth(&weights[r.clone()], &packed.depths[r]).unwrap_or(0.0)
                        } else {
                            0.0
                        }
                    }))
            }
            None => img.depth.extend(std::iter::repeat_n(0.0, part.len())),
        }
        img.opacity.extend(opacity);
    }
    Ok(img)
}
