//! The learnable latent codes l_ij, one per (training view i, style j), and their prior
//! N(μ_j, σ_j) from the style VAE.
//!
//! Each code starts as a sample of its style's distribution and is learned with the style
//! module; L_d keeps it likely under that distribution. L_d is the proper Gaussian negative
//! log-likelihood, Σ_d [(l_d − μ_d)² / (2σ_d²) + ln σ_d] + (Z/2) ln 2π, averaged over the
//! codes in a batch. The paper prints (l − μ)² / (2πσ²): a stray π in place of the 2's
//! companion, and no ln σ term (which does not depend on l and so changes no gradient). Our
//! λ_d default is set for this definition (see `MutualConfig`).
//!
//! At inference a style is rendered with its mean μ_j and a blend with Σ_j w_j μ_j.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor, Var};

use crate::rng::Rng;
use crate::style2d::st_file;
use crate::style2d::vae::LatentGaussian;
use crate::{EngineError, Result};

const FORMAT_TAG: &str = "stylenerf-latents/1";

/// Latent codes and their per-style priors.
pub struct LatentCodes {
    pub num_views: usize,
    pub num_styles: usize,
    pub dim: usize,
    /// `[V · S, Z]`, row i · S + j.
    codes: Var,
    /// `[S, Z]`.
    mu: Tensor,
    /// `[S, Z]`.
    sigma: Tensor,
}

impl LatentCodes {
    /// Codes for `num_views` views sampled from each style's distribution.
    pub fn sample(
        styles: &[LatentGaussian],
        num_views: usize,
        rng: &mut Rng,
        device: &Device,
    ) -> Result<Self> {
        let (mu, sigma) = priors(styles, device)?;
        let dim = mu.dim(1)?;
        let mut codes = Vec::with_capacity(num_views * styles.len() * dim);
        for _ in 0..num_views {
            for s in styles {
                codes.extend(
                    s.mu.iter()
                        .zip(&s.sigma)
                        .map(|(m, sd)| m + sd * rng.normal()),
                );
            }
        }
        let codes = Tensor::from_vec(codes, (num_views * styles.len(), dim), device)?;
        Ok(Self {
            num_views,
            num_styles: styles.len(),
            dim,
            codes: Var::from_tensor(&codes)?,
            mu,
            sigma,
        })
    }

    /// One fixed code per style (its mean), shared by every view: the "no learnable latents"
    /// ablation. The returned codes are still a variable; the caller decides whether to train.
    pub fn means(styles: &[LatentGaussian], num_views: usize, device: &Device) -> Result<Self> {
        let (mu, sigma) = priors(styles, device)?;
        let codes = mu.repeat((num_views, 1))?;
        Ok(Self {
            num_views,
            num_styles: styles.len(),
            dim: mu.dim(1)?,
            codes: Var::from_tensor(&codes)?,
            mu,
            sigma,
        })
    }

    pub fn var(&self) -> (String, Var) {
        ("latents.codes".into(), self.codes.clone())
    }

    /// The codes' current values `[V · S, Z]` (for checkpoints and the saved artifact).
    pub fn codes(&self) -> &Tensor {
        self.codes.as_tensor()
    }

    /// Restores codes saved by [`LatentCodes::codes`].
    pub fn set_codes(&self, codes: &Tensor) -> Result<()> {
        if codes.dims() != self.codes.dims() {
            return Err(EngineError::config(
                "latents.codes",
                format!("shape {:?}, expected {:?}", codes.dims(), self.codes.dims()),
            ));
        }
        Ok(self.codes.set(codes)?)
    }

    /// l_ij `[1, Z]`, part of the graph.
    pub fn code(&self, view: usize, style: usize) -> Result<Tensor> {
        Ok(self
            .codes
            .as_tensor()
            .narrow(0, view * self.num_styles + style, 1)?)
    }

    /// L_d(l_ij): the Gaussian negative log-likelihood of the code under its style's prior.
    pub fn nll(&self, view: usize, style: usize) -> Result<Tensor> {
        let l = self.code(view, style)?;
        let mu = self.mu.narrow(0, style, 1)?;
        let sigma = self.sigma.narrow(0, style, 1)?;
        let z = ((l - mu)? / &sigma)?;
        let quad = (z.sqr()?.sum_all()? * 0.5)?;
        let log_norm = sigma.log()?.sum_all()?.to_scalar::<f32>()?
            + 0.5 * self.dim as f32 * (2.0 * std::f32::consts::PI).ln();
        Ok((quad + f64::from(log_norm))?)
    }

    /// The inference code of a blend of styles: Σ_j w_j μ_j `[1, Z]`. Weights need not sum to
    /// one; they are normalised.
    pub fn blend(&self, weights: &[(usize, f32)]) -> Result<Tensor> {
        let total: f32 = weights.iter().map(|(_, w)| w).sum();
        if weights.is_empty() || total <= 0.0 {
            return Err(EngineError::config(
                "style",
                "a blend needs at least one style with a positive weight",
            ));
        }
        let mut out = Tensor::zeros((1, self.dim), DType::F32, self.mu.device())?;
        for &(j, w) in weights {
            if j >= self.num_styles {
                return Err(EngineError::config(
                    "style",
                    format!("style index {j} out of range ({} styles)", self.num_styles),
                ));
            }
            out = (out + (self.mu.narrow(0, j, 1)? * f64::from(w / total))?)?;
        }
        Ok(out)
    }

    /// Writes codes, μ and σ to `path` (safetensors).
    pub fn save(&self, path: &Path) -> Result<()> {
        st_file::save(
            path,
            &[
                ("codes".into(), self.codes.as_tensor().clone()),
                ("mu".into(), self.mu.clone()),
                ("sigma".into(), self.sigma.clone()),
            ],
            &[("format", FORMAT_TAG.into())],
        )
    }

    /// Reads codes written by [`LatentCodes::save`].
    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| EngineError::io(path, e))?;
        if st_file::metadata(path, &bytes)?
            .get("format")
            .map(String::as_str)
            != Some(FORMAT_TAG)
        {
            return Err(EngineError::artifact(
                path,
                "not a stylenerf latent-code file",
            ));
        }
        let mut t: HashMap<String, Tensor> = candle_core::safetensors::load_buffer(&bytes, device)?
            .into_iter()
            .collect();
        let mut take = |k: &str| {
            t.remove(k)
                .ok_or_else(|| EngineError::artifact(path, format!("tensor `{k}` missing")))
        };
        let (codes, mu, sigma) = (take("codes")?, take("mu")?, take("sigma")?);
        let (num_styles, dim) = mu.dims2()?;
        let (rows, code_dim) = codes.dims2()?;
        if sigma.dims() != mu.dims() || code_dim != dim || num_styles == 0 || rows % num_styles != 0
        {
            return Err(EngineError::artifact(
                path,
                format!(
                    "inconsistent shapes: codes {:?}, mu {:?}, sigma {:?}",
                    codes.dims(),
                    mu.dims(),
                    sigma.dims()
                ),
            ));
        }
        Ok(Self {
            num_views: rows / num_styles,
            num_styles,
            dim,
            codes: Var::from_tensor(&codes)?,
            mu,
            sigma,
        })
    }

    /// Mean over codes of |l − μ_j| / σ_j: how far the codes moved from their prior's centre.
    pub fn mean_deviation(&self) -> Result<f32> {
        let mu = self.mu.repeat((self.num_views, 1))?;
        let sigma = self.sigma.repeat((self.num_views, 1))?;
        Ok(((self.codes.as_tensor() - mu)? / sigma)?
            .abs()?
            .mean_all()?
            .to_scalar::<f32>()?)
    }
}

/// `[S, Z]` means and standard deviations.
fn priors(styles: &[LatentGaussian], device: &Device) -> Result<(Tensor, Tensor)> {
    let dim = styles.first().map_or(0, |s| s.mu.len());
    if dim == 0
        || styles
            .iter()
            .any(|s| s.mu.len() != dim || s.sigma.len() != dim)
    {
        return Err(EngineError::config(
            "styles",
            "every style needs a latent mean and standard deviation of the same length",
        ));
    }
    let flat = |f: fn(&LatentGaussian) -> &Vec<f32>| -> Vec<f32> {
        styles.iter().flat_map(|s| f(s).iter().copied()).collect()
    };
    let mu = Tensor::from_vec(flat(|s| &s.mu), (styles.len(), dim), device)?;
    let sigma = Tensor::from_vec(flat(|s| &s.sigma), (styles.len(), dim), device)?
        .clamp(1e-4f32, f32::MAX)?;
    Ok((mu, sigma))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn styles() -> Vec<LatentGaussian> {
        vec![
            LatentGaussian {
                mu: vec![1.0, -2.0, 0.5],
                sigma: vec![0.1, 0.2, 0.3],
            },
            LatentGaussian {
                mu: vec![-1.0, 0.0, 3.0],
                sigma: vec![0.5, 0.5, 0.5],
            },
        ]
    }

    #[test]
    fn samples_follow_each_styles_distribution() {
        let dev = Device::Cpu;
        let codes = LatentCodes::sample(&styles(), 4000, &mut Rng::new(3), &dev).unwrap();
        let all: Vec<Vec<f32>> = codes.codes().to_vec2().unwrap();
        for (j, s) in styles().iter().enumerate() {
            for d in 0..3 {
                let v: Vec<f32> = all.iter().skip(j).step_by(2).map(|r| r[d]).collect();
                let mean = v.iter().sum::<f32>() / v.len() as f32;
                let sd =
                    (v.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / v.len() as f32).sqrt();
                assert!(
                    (mean - s.mu[d]).abs() < 4.0 * s.sigma[d] / 60.0,
                    "style {j} dim {d} mean {mean}"
                );
                assert!(
                    (sd / s.sigma[d] - 1.0).abs() < 0.06,
                    "style {j} dim {d} sd {sd}"
                );
            }
        }
        assert!((codes.mean_deviation().unwrap() - 0.798).abs() < 0.03);
    }

    #[test]
    fn nll_is_the_gaussian_negative_log_likelihood_and_its_gradient() {
        let dev = Device::Cpu;
        let codes = LatentCodes::means(&styles(), 2, &dev).unwrap();
        let l = [1.3f32, -2.0, 0.2];
        let row = Tensor::new(&[l], &dev).unwrap();
        let mut all: Vec<Vec<f32>> = codes.codes().to_vec2().unwrap();
        all[2] = l.to_vec(); // view 1, style 0
        codes.set_codes(&Tensor::new(all, &dev).unwrap()).unwrap();
        let s = &styles()[0];
        let expected: f32 = (0..3)
            .map(|d| {
                (l[d] - s.mu[d]).powi(2) / (2.0 * s.sigma[d].powi(2))
                    + s.sigma[d].ln()
                    + 0.5 * (2.0 * std::f32::consts::PI).ln()
            })
            .sum();
        let nll = codes.nll(1, 0).unwrap();
        assert!((nll.to_scalar::<f32>().unwrap() - expected).abs() < 1e-4);
        assert_eq!(
            codes.code(1, 0).unwrap().to_vec2::<f32>().unwrap(),
            row.to_vec2::<f32>().unwrap()
        );
        let grads = nll.backward().unwrap();
        let g: Vec<Vec<f32>> = grads.get(codes.codes()).unwrap().to_vec2().unwrap();
        for d in 0..3 {
            let want = (l[d] - s.mu[d]) / s.sigma[d].powi(2);
            assert!(
                (g[2][d] - want).abs() < 1e-3 * want.abs().max(1.0),
                "dim {d}"
            );
            assert_eq!(g[0][d], 0.0);
        }
    }

    #[test]
    fn blends_mix_the_means() {
        let codes = LatentCodes::means(&styles(), 1, &Device::Cpu).unwrap();
        let b: Vec<Vec<f32>> = codes
            .blend(&[(0, 1.0), (1, 3.0)])
            .unwrap()
            .to_vec2()
            .unwrap();
        let want = [0.25 * 1.0 - 0.75, 0.25 * -2.0, 0.25 * 0.5 + 0.75 * 3.0];
        for d in 0..3 {
            assert!((b[0][d] - want[d]).abs() < 1e-6);
        }
        assert!(codes.blend(&[]).is_err());
        assert!(codes.blend(&[(2, 1.0)]).is_err());
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("latents.safetensors");
        codes.save(&path).unwrap();
        let back = LatentCodes::load(&path, &Device::Cpu).unwrap();
        assert_eq!((back.num_views, back.num_styles, back.dim), (1, 2, 3));
        let again: Vec<Vec<f32>> = back
            .blend(&[(0, 1.0), (1, 3.0)])
            .unwrap()
            .to_vec2()
            .unwrap();
        assert_eq!(again, b);
    }
}
