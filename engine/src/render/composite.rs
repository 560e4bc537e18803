//! Volume-rendering compositing over packed samples:
//! `C = Σ T_k (1 − exp(−σ_k δ_k)) c_k`, expected depth `D = Σ w_k z_k` and opacity
//! `O = Σ w_k`, with `T_k = exp(−Σ_{j<k} σ_j δ_j)`.
//!
//! Rays have different numbers of samples, so samples are packed: ray r owns samples
//! `offsets[r]..offsets[r+1]`. On CPU this is one fused `CustomOp2` (σ [S], rgb [S, 3]) →
//! [R, 5] (r, g, b, depth, opacity) with an analytic backward: with
//! `g_k = ∂L/∂C · c_k + ∂L/∂D · z_k + ∂L/∂O` and `G = Σ_j w_j g_j`,
//! `∂L/∂σ_k = δ_k (T_{k+1} g_k − (G − Σ_{j≤k} w_j g_j))` and `∂L/∂c_k = w_k ∂L/∂C`.
//! Other devices use a composed version on a padded [R, max samples] layout.
//!
//! Rendered images report each ray's median depth instead of `D / O` ([`median_depth`], from
//! the weights of [`sample_weights`]): the depth later stages warp with.

use std::sync::Arc;

use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Shape, Tensor, WithDType};
use rayon::prelude::*;

use crate::cpu_ops::contiguous_slice;
use crate::rays::PackedRays;
use crate::Result;

/// Composites σ [S] and rgb [S, 3] into [R, 5] = (rgb, depth, opacity) per ray.
pub fn composite(sigma: &Tensor, rgb: &Tensor, rays: &Arc<PackedRays>) -> Result<Tensor> {
    if sigma.device().is_cpu() {
        Ok(sigma.apply_op2(rgb, Composite { rays: rays.clone() })?)
    } else {
        composite_composed(sigma, rgb, rays)
    }
}

/// Device-agnostic compositing from candle ops (reference and non-CPU fallback).
pub fn composite_composed(sigma: &Tensor, rgb: &Tensor, rays: &PackedRays) -> Result<Tensor> {
    let r = rays.num_rays();
    let s = rays.num_samples();
    let m = rays
        .offsets
        .windows(2)
        .map(|w| (w[1] - w[0]) as usize)
        .max()
        .unwrap_or(0)
        .max(1);
    // Padding points at an extra zero sample appended at index S.
    let mut idx = vec![s as u32; r * m];
    for (ray, w) in rays.offsets.windows(2).enumerate() {
        for (k, sample) in (w[0]..w[1]).enumerate() {
            idx[ray * m + k] = sample;
        }
    }
    let dev = sigma.device();
    let dt = sigma.dtype();
    let idx = Tensor::from_vec(idx, r * m, dev)?;
    let pad = |t: &Tensor, cols: usize| -> Result<Tensor> {
        let zero = Tensor::zeros((1, cols), dt, dev)?;
        Ok(Tensor::cat(&[&t.reshape((s, cols))?, &zero], 0)?.index_select(&idx, 0)?)
    };
    let constant = |v: &[f32]| -> Result<Tensor> {
        let t = Tensor::from_slice(v, (s, 1), dev)?.to_dtype(dt)?;
        Ok(pad(&t, 1)?.reshape((r, m))?)
    };
    let sd = (pad(sigma, 1)?.reshape((r, m))? * constant(&rays.deltas)?)?;
    let alpha = (1.0 - sd.neg()?.exp()?)?;
    let exclusive = (sd.cumsum(1)? - &sd)?;
    let w = (exclusive.neg()?.exp()? * alpha)?;
    let colour = w
        .unsqueeze(2)?
        .broadcast_mul(&pad(rgb, 3)?.reshape((r, m, 3))?)?
        .sum(1)?;
    let depth = (&w * constant(&rays.depths)?)?.sum_keepdim(1)?;
    let opacity = w.sum_keepdim(1)?;
    Ok(Tensor::cat(&[colour, depth, opacity], 1)?)
}

struct Composite {
    rays: Arc<PackedRays>,
}

impl Composite {
    fn forward<T: WithDType>(&self, sigma: &[T], rgb: &[T]) -> Vec<T> {
        let rays = &self.rays;
        let mut out = vec![T::zero(); rays.num_rays() * 5];
        out.par_chunks_mut(5 * 64)
            .enumerate()
            .for_each(|(chunk, out)| {
                for (i, o) in out.chunks_exact_mut(5).enumerate() {
                    let ray = chunk * 64 + i;
                    let mut trans = 1.0f64;
                    for k in rays.offsets[ray] as usize..rays.offsets[ray + 1] as usize {
                        let decay = (-sigma[k].to_f64() * rays.deltas[k] as f64).exp();
                        let w = T::from_f64(trans * (1.0 - decay));
                        for c in 0..3 {
                            o[c] += w * rgb[3 * k + c];
                        }
                        o[3] += w * T::from_f64(rays.depths[k] as f64);
                        o[4] += w;
                        trans *= decay;
                    }
                }
            });
        out
    }
}

impl CustomOp2 for Composite {
    fn name(&self) -> &'static str {
        "composite"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        if l1.shape().elem_count() != self.rays.num_samples()
            || l2.shape().elem_count() != 3 * self.rays.num_samples()
        {
            candle_core::bail!("composite: sigma/rgb sizes do not match the packed rays");
        }
        let out = match (s1, s2) {
            (CpuStorage::F32(s), CpuStorage::F32(c)) => CpuStorage::F32(self.forward(
                contiguous_slice(s, l1, "composite: sigma")?,
                contiguous_slice(c, l2, "composite: rgb")?,
            )),
            (CpuStorage::F64(s), CpuStorage::F64(c)) => CpuStorage::F64(self.forward(
                contiguous_slice(s, l1, "composite: sigma")?,
                contiguous_slice(c, l2, "composite: rgb")?,
            )),
            _ => candle_core::bail!("composite: sigma and rgb must both be f32 or f64"),
        };
        Ok((out, Shape::from((self.rays.num_rays(), 5))))
    }

    fn bwd(
        &self,
        sigma: &Tensor,
        rgb: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let op = CompositeBackward {
            rays: self.rays.clone(),
        };
        let joint = Tensor::cat(&[res, &grad.contiguous()?], 1)?;
        let g = sigma.apply_op3_no_bwd(&rgb.contiguous()?, &joint, &op)?;
        let s = self.rays.num_samples();
        Ok((
            Some(g.narrow(1, 0, 1)?.reshape(s)?),
            Some(g.narrow(1, 1, 3)?),
        ))
    }
}

/// (σ, rgb, [result | grad] [R, 10]) → [S, 4] = (∂L/∂σ, ∂L/∂rgb).
struct CompositeBackward {
    rays: Arc<PackedRays>,
}

impl CompositeBackward {
    fn backward<T: WithDType>(&self, sigma: &[T], rgb: &[T], joint: &[T]) -> Vec<T> {
        let rays = &self.rays;
        let mut out = vec![T::zero(); rays.num_samples() * 4];
        // Split the output by ray so each task writes only its own samples.
        let mut parts: Vec<&mut [T]> = Vec::with_capacity(rays.num_rays());
        let mut rest = out.as_mut_slice();
        for w in rays.offsets.windows(2) {
            let (head, tail) = rest.split_at_mut((w[1] - w[0]) as usize * 4);
            parts.push(head);
            rest = tail;
        }
        parts
            .into_par_iter()
            .enumerate()
            .with_min_len(64)
            .for_each(|(ray, out)| {
                let j = &joint[ray * 10..ray * 10 + 10];
                let f = |t: T| t.to_f64();
                let (gc, gd, go) = ([f(j[5]), f(j[6]), f(j[7])], f(j[8]), f(j[9]));
                let total = gc[0] * f(j[0])
                    + gc[1] * f(j[1])
                    + gc[2] * f(j[2])
                    + gd * f(j[3])
                    + go * f(j[4]);
                let mut trans = 1.0f64;
                let mut prefix = 0.0f64;
                let start = rays.offsets[ray] as usize;
                for (i, o) in out.chunks_exact_mut(4).enumerate() {
                    let k = start + i;
                    let delta = rays.deltas[k] as f64;
                    let decay = (-f(sigma[k]) * delta).exp();
                    let w = trans * (1.0 - decay);
                    let c = [f(rgb[3 * k]), f(rgb[3 * k + 1]), f(rgb[3 * k + 2])];
                    let g = gc[0] * c[0]
                        + gc[1] * c[1]
                        + gc[2] * c[2]
                        + gd * rays.depths[k] as f64
                        + go;
                    prefix += w * g;
                    trans *= decay;
                    o[0] = T::from_f64(delta * (trans * g - (total - prefix)));
                    for ch in 0..3 {
                        o[1 + ch] = T::from_f64(w * gc[ch]);
                    }
                }
            });
        out
    }
}

impl CustomOp3 for CompositeBackward {
    fn name(&self) -> &'static str {
        "composite-backward"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let out = match (s1, s2, s3) {
            (CpuStorage::F32(s), CpuStorage::F32(c), CpuStorage::F32(j)) => {
                CpuStorage::F32(self.backward(
                    contiguous_slice(s, l1, "composite: sigma")?,
                    contiguous_slice(c, l2, "composite: rgb")?,
                    contiguous_slice(j, l3, "composite: grad")?,
                ))
            }
            (CpuStorage::F64(s), CpuStorage::F64(c), CpuStorage::F64(j)) => {
                CpuStorage::F64(self.backward(
                    contiguous_slice(s, l1, "composite: sigma")?,
                    contiguous_slice(c, l2, "composite: rgb")?,
                    contiguous_slice(j, l3, "composite: grad")?,
                ))
            }
            _ => candle_core::bail!("composite backward: mixed dtypes"),
        };
        Ok((out, Shape::from((self.rays.num_samples(), 4))))
    }
}

/// Each sample's weight `w_k = T_k (1 − exp(−σ_k δ_k))` (σ [S] as values), as composited.
pub fn sample_weights(sigma: &[f32], rays: &PackedRays) -> Vec<f32> {
    let mut weights = Vec::with_capacity(sigma.len());
    for ray in rays.offsets.windows(2) {
        let r = ray[0] as usize..ray[1] as usize;
        let mut trans = 1.0f64;
        for (s, d) in sigma[r.clone()].iter().zip(&rays.deltas[r]) {
            let decay = (-f64::from(*s) * f64::from(*d)).exp();
            weights.push((trans * (1.0 - decay)) as f32);
            trans *= decay;
        }
    }
    weights
}

/// The median of one ray's termination: the depth of the sample at which the accumulated
/// weight reaches half of the ray's opacity (to the sample). Where a pixel sees a silhouette,
/// the expected depth `D / O` averages foreground and background into the empty space between
/// them and warps the pixel there; the median picks one surface. `None` without weight.
pub fn median_depth(weights: &[f32], depths: &[f32]) -> Option<f32> {
    let total: f32 = weights.iter().sum();
    if total <= 0.0 {
        return None;
    }
    let mut accumulated = 0.0;
    for (w, z) in weights.iter().zip(depths) {
        accumulated += w;
        if accumulated >= 0.5 * total {
            return Some(*z);
        }
    }
    depths.last().copied()
}

/// Adds the background where the ray is not opaque: rgb + (1 − opacity) · background.
/// `out` is the [R, 5] composite and `background` `[1, 3]` or `[R, 3]`; returns ([R, 3]
/// colour, [R] depth, [R] opacity).
pub fn split_with_background(
    out: &Tensor,
    background: &Tensor,
) -> Result<(Tensor, Tensor, Tensor)> {
    let rgb = out.narrow(1, 0, 3)?;
    let opacity = out.narrow(1, 4, 1)?;
    let bg = background.to_dtype(out.dtype())?;
    let colour = (rgb + (1.0 - &opacity)?.broadcast_mul(&bg)?)?;
    Ok((
        colour,
        out.narrow(1, 3, 1)?.squeeze(1)?,
        opacity.squeeze(1)?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use candle_core::{Device, Var};

    fn batch(rng: &mut Rng) -> Arc<PackedRays> {
        let mut rays = PackedRays {
            offsets: vec![0],
            ..Default::default()
        };
        for count in [5u32, 0, 1, 9, 3] {
            for k in 0..count {
                rays.deltas.push(0.05 + 0.1 * rng.uniform());
                rays.depths.push(1.0 + k as f32 * 0.1);
            }
            let last = *rays.offsets.last().unwrap();
            rays.offsets.push(last + count);
        }
        Arc::new(rays)
    }

    #[test]
    fn median_depth_picks_a_surface_where_the_mean_lies_between_two() {
        // A silhouette: 0.45 of the pixel on the fox at z = 1, 0.55 on the wall at z = 3.
        let (weights, depths) = ([0.3, 0.15, 0.05, 0.5], [1.0, 1.01, 2.99, 3.0]);
        let mean = weights.iter().zip(&depths).map(|(w, z)| w * z).sum::<f32>();
        assert!(
            (mean - 2.1).abs() < 0.01,
            "the mean lands in the empty space: {mean}"
        );
        assert_eq!(median_depth(&weights, &depths), Some(2.99));
        // Half the opacity, not half of one: a ray 0.4 opaque ends where 0.2 is reached.
        assert_eq!(median_depth(&[0.1, 0.1, 0.2], &[1.0, 2.0, 3.0]), Some(2.0));
        assert_eq!(median_depth(&[0.0, 0.0], &[1.0, 2.0]), None);
        assert_eq!(median_depth(&[], &[]), None);
    }

    #[test]
    fn sample_weights_are_the_composited_weights() {
        let mut rng = Rng::new(9);
        let rays = batch(&mut rng);
        let s = rays.num_samples();
        let sigma: Vec<f32> = (0..s).map(|_| 8.0 * rng.uniform()).collect();
        let weights = sample_weights(&sigma, &rays);
        let ones = Tensor::ones((s, 3), candle_core::DType::F32, &Device::Cpu).unwrap();
        let sigma_t = Tensor::from_slice(&sigma, s, &Device::Cpu).unwrap();
        let out = composite(&sigma_t, &ones, &rays)
            .unwrap()
            .to_vec2::<f32>()
            .unwrap();
        for (r, ray) in rays.offsets.windows(2).enumerate() {
            let opacity: f32 = weights[ray[0] as usize..ray[1] as usize].iter().sum();
            assert!(
                (opacity - out[r][4]).abs() < 1e-5,
                "ray {r}: {opacity} vs {}",
                out[r][4]
            );
        }
    }

    #[test]
    fn fused_matches_composed_and_finite_differences() {
        let mut rng = Rng::new(5);
        let rays = batch(&mut rng);
        let s = rays.num_samples();
        let dev = Device::Cpu;
        let sigma = Var::from_vec(
            (0..s).map(|_| 8.0 * rng.uniform() as f64).collect(),
            s,
            &dev,
        )
        .unwrap();
        let rgb = Var::from_vec(
            (0..3 * s).map(|_| rng.uniform() as f64).collect(),
            (s, 3),
            &dev,
        )
        .unwrap();
        let proj = Tensor::from_vec(
            (0..rays.num_rays() * 5)
                .map(|_| rng.uniform() as f64 - 0.5)
                .collect(),
            (rays.num_rays(), 5),
            &dev,
        )
        .unwrap();
        let loss = |sg: &Tensor, c: &Tensor, fused: bool| -> Tensor {
            let out = if fused {
                composite(sg, c, &rays).unwrap()
            } else {
                composite_composed(sg, c, &rays).unwrap()
            };
            (out.sqr().unwrap() * &proj).unwrap().sum_all().unwrap()
        };
        let lf = loss(&sigma, &rgb, true);
        let lc = loss(&sigma, &rgb, false);
        let (a, b) = (
            lf.to_scalar::<f64>().unwrap(),
            lc.to_scalar::<f64>().unwrap(),
        );
        assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        let gf = lf.backward().unwrap();
        let gc = lc.backward().unwrap();
        for v in [&sigma, &rgb] {
            let d = (gf.get(v).unwrap() - gc.get(v).unwrap())
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap();
            assert!(d.to_scalar::<f64>().unwrap() < 1e-10);
        }
        // Finite differences on every σ and colour.
        let eps = 1e-6;
        for (var, analytic) in [
            (&sigma, gf.get(&sigma).unwrap()),
            (&rgb, gf.get(&rgb).unwrap()),
        ] {
            let base: Vec<f64> = var.flatten_all().unwrap().to_vec1().unwrap();
            let analytic: Vec<f64> = analytic.flatten_all().unwrap().to_vec1().unwrap();
            for i in 0..base.len() {
                let eval = |delta: f64| {
                    let mut v = base.clone();
                    v[i] += delta;
                    let t = Tensor::from_vec(v, var.shape(), &dev).unwrap();
                    let l = if var.dims().len() == 1 {
                        loss(&t, &rgb, true)
                    } else {
                        loss(&sigma, &t, true)
                    };
                    l.to_scalar::<f64>().unwrap()
                };
                let numeric = (eval(eps) - eval(-eps)) / (2.0 * eps);
                assert!(
                    (numeric - analytic[i]).abs() < 1e-6,
                    "entry {i}: {numeric} vs {}",
                    analytic[i]
                );
            }
        }
    }

    #[test]
    fn opaque_sample_gives_its_colour_and_depth() {
        let rays = Arc::new(PackedRays {
            offsets: vec![0, 2],
            deltas: vec![1.0, 1.0],
            depths: vec![2.0, 3.0],
            distances: vec![0.0, 1.0],
        });
        let dev = Device::Cpu;
        let sigma = Tensor::new(&[1e4f32, 0.0], &dev).unwrap();
        let rgb = Tensor::new(&[[0.2f32, 0.4, 0.6], [1.0, 1.0, 1.0]], &dev).unwrap();
        let out = composite(&sigma, &rgb, &rays).unwrap();
        let bg = Tensor::new(&[[1.0f32, 0.0, 0.0]], &Device::Cpu).unwrap();
        let (c, d, o) = split_with_background(&out, &bg).unwrap();
        assert_eq!(c.to_vec2::<f32>().unwrap(), vec![vec![0.2, 0.4, 0.6]]);
        assert_eq!(
            (
                d.to_vec1::<f32>().unwrap()[0],
                o.to_vec1::<f32>().unwrap()[0]
            ),
            (2.0, 1.0)
        );
    }
}
