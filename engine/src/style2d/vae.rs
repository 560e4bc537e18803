//! A VAE over style feature vectors (see [`super::style_features`]): each style becomes a
//! Gaussian N(μ_j, σ_j) in a small latent space, which initialises and regularises the
//! stylized NeRF's per-view latent codes.
//!
//! Architecture: inputs are standardised per dimension with the mean/std of the training
//! vectors (stored with the weights, so inference standardises identically); encoder
//! 1024 → hidden → ReLU → (μ, log σ²) of size `latent`; decoder latent → hidden → ReLU → 1024.
//! Loss: mean squared reconstruction error of the standardised vector + `kl_weight` ·
//! KL(q(z|x) ‖ N(0, I)) averaged over the batch.
//!
//! A style's distribution aggregates the posteriors of its K crops as their equal-weight
//! mixture, moment-matched to one Gaussian: μ_j = (1/K) Σ_k μ_k and
//! σ_j² = (1/K) Σ_k (σ_k² + μ_k²) − μ_j² (per latent dimension). It covers both each crop's
//! posterior spread and the spread between crops.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor, Var};
use serde::{Deserialize, Serialize};

use super::st_file;
use crate::named::{load_vars, tensors_of};
use crate::optim::{Adam, AdamConfig};
use crate::rng::Rng;
use crate::{EngineError, Result};

const FORMAT_TAG: &str = "stylenerf-style-vae/1";

/// Sizes and training weights of the VAE.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct VaeConfig {
    pub input: usize,
    pub hidden: usize,
    pub latent: usize,
    pub kl_weight: f64,
}

impl Default for VaeConfig {
    fn default() -> Self {
        Self {
            input: super::style_features::STYLE_DIM,
            hidden: 256,
            latent: 32,
            kl_weight: 1e-3,
        }
    }
}

/// A Gaussian per latent dimension.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LatentGaussian {
    pub mu: Vec<f32>,
    pub sigma: Vec<f32>,
}

#[derive(Debug, Clone)]
struct Linear {
    w: Var,
    b: Var,
}

impl Linear {
    fn new(i: usize, o: usize, rng: &mut Rng, device: &Device) -> Result<Self> {
        let bound = (6.0 / i as f32).sqrt();
        let w: Vec<f32> = (0..i * o)
            .map(|_| (rng.uniform() * 2.0 - 1.0) * bound)
            .collect();
        Ok(Self {
            w: Var::from_tensor(&Tensor::from_vec(w, (o, i), device)?)?,
            b: Var::zeros(o, DType::F32, device)?,
        })
    }

    fn forward(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        x.matmul(&self.w.as_tensor().t()?)?
            .broadcast_add(self.b.as_tensor())
    }
}

/// The style VAE.
#[derive(Debug, Clone)]
pub struct StyleVae {
    pub config: VaeConfig,
    /// Per-dimension standardisation of the inputs: `[input]` each.
    input_mean: Var,
    input_std: Var,
    enc: Linear,
    enc_mu: Linear,
    enc_logvar: Linear,
    dec: Linear,
    dec_out: Linear,
}

/// One VAE training step's losses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VaeLosses {
    pub reconstruction: f32,
    pub kl: f32,
}

impl StyleVae {
    pub fn new(config: VaeConfig, seed: u64, device: &Device) -> Result<Self> {
        let mut rng = Rng::new(seed);
        let (i, h, l) = (config.input, config.hidden, config.latent);
        Ok(Self {
            config,
            input_mean: Var::zeros(i, DType::F32, device)?,
            input_std: Var::from_tensor(&Tensor::ones(i, DType::F32, device)?)?,
            enc: Linear::new(i, h, &mut rng, device)?,
            enc_mu: Linear::new(h, l, &mut rng, device)?,
            enc_logvar: Linear::new(h, l, &mut rng, device)?,
            dec: Linear::new(l, h, &mut rng, device)?,
            dec_out: Linear::new(h, i, &mut rng, device)?,
        })
    }

    /// Sets the input standardisation from training vectors `[N, input]`.
    pub fn fit_standardisation(&self, x: &Tensor) -> Result<()> {
        let mean = x.mean(0)?;
        let std = (x.broadcast_sub(&mean)?.sqr()?.mean(0)? + 1e-6)?.sqrt()?;
        self.input_mean.set(&mean)?;
        self.input_std.set(&std)?;
        Ok(())
    }

    fn standardise(&self, x: &Tensor) -> candle_core::Result<Tensor> {
        x.broadcast_sub(self.input_mean.as_tensor())?
            .broadcast_div(self.input_std.as_tensor())
    }

    /// Posterior mean and log-variance `[N, latent]` of style vectors `[N, input]`.
    pub fn encode(&self, x: &Tensor) -> candle_core::Result<(Tensor, Tensor)> {
        let h = self.enc.forward(&self.standardise(x)?)?.relu()?;
        Ok((self.enc_mu.forward(&h)?, self.enc_logvar.forward(&h)?))
    }

    /// Reconstructed style vectors `[N, input]` (in the original units) of latents `[N, latent]`.
    pub fn decode(&self, z: &Tensor) -> candle_core::Result<Tensor> {
        let y = self.dec_out.forward(&self.dec.forward(z)?.relu()?)?;
        y.broadcast_mul(self.input_std.as_tensor())?
            .broadcast_add(self.input_mean.as_tensor())
    }

    /// Trainable variables (not the standardisation), named.
    pub fn vars(&self) -> Vec<(String, Var)> {
        let mut v = Vec::new();
        for (name, l) in self.layers() {
            v.push((format!("vae.{name}.weight"), l.w.clone()));
            v.push((format!("vae.{name}.bias"), l.b.clone()));
        }
        v
    }

    fn layers(&self) -> [(&'static str, &Linear); 5] {
        [
            ("enc", &self.enc),
            ("enc_mu", &self.enc_mu),
            ("enc_logvar", &self.enc_logvar),
            ("dec", &self.dec),
            ("dec_out", &self.dec_out),
        ]
    }

    /// All tensors including the standardisation.
    pub fn tensors(&self) -> Vec<(String, Tensor)> {
        tensors_of(&self.all_vars())
    }

    /// The variables and the standardisation.
    fn all_vars(&self) -> Vec<(String, Var)> {
        let mut all = self.vars();
        all.push(("vae.input_mean".into(), self.input_mean.clone()));
        all.push(("vae.input_std".into(), self.input_std.clone()));
        all
    }

    /// Restores tensors produced by [`Self::tensors`] (read from `source`).
    pub fn load_tensors(&self, tensors: &HashMap<String, Tensor>, source: &Path) -> Result<()> {
        load_vars(&self.all_vars(), tensors, source)
    }

    /// The training loss on a batch `[N, input]`; `noise` `[N, latent]` is ε ~ N(0, I) for
    /// the reparameterisation.
    pub fn loss(
        &self,
        x: &Tensor,
        noise: &Tensor,
    ) -> candle_core::Result<(Tensor, Tensor, Tensor)> {
        let (mu, logvar) = self.encode(x)?;
        let z = (&mu + (noise * (&logvar * 0.5)?.exp()?)?)?;
        let recon = self.dec_out.forward(&self.dec.forward(&z)?.relu()?)?;
        let rec = recon.sub(&self.standardise(x)?)?.sqr()?.mean_all()?;
        // KL(N(μ, σ²) ‖ N(0, 1)) = ½ Σ (μ² + σ² − log σ² − 1), averaged over the batch.
        let kl = ((mu.sqr()? + logvar.exp()? - &logvar)? - 1.0)?
            .sum(1)?
            .mean_all()?
            * 0.5;
        let kl = kl?;
        let total = (&rec + (&kl * self.config.kl_weight)?)?;
        Ok((total, rec, kl))
    }

    /// Trains on `x` `[N, input]` for `steps` full-batch Adam steps (standardisation fitted
    /// first); returns the final losses.
    pub fn train(&self, x: &Tensor, steps: usize, lr: f64, rng: &mut Rng) -> Result<VaeLosses> {
        self.fit_standardisation(x)?;
        let mut adam = Adam::new(self.vars(), AdamConfig::default())?;
        let n = x.dim(0)?;
        let mut last = VaeLosses {
            reconstruction: f32::NAN,
            kl: f32::NAN,
        };
        for _ in 0..steps {
            let eps: Vec<f32> = (0..n * self.config.latent).map(|_| rng.normal()).collect();
            let noise = Tensor::from_vec(eps, (n, self.config.latent), x.device())?;
            let (total, rec, kl) = self.loss(x, &noise)?;
            adam.step(&total.backward()?, lr)?;
            last = VaeLosses {
                reconstruction: rec.to_scalar()?,
                kl: kl.to_scalar()?,
            };
        }
        Ok(last)
    }

    /// The style's distribution from the style vectors of its crops `[K, input]`: the
    /// moment-matched mixture of the K posteriors (see the module docs).
    pub fn style_distribution(&self, crops: &Tensor) -> Result<LatentGaussian> {
        let (mu, logvar) = self.encode(crops)?;
        let m = mu.mean(0)?;
        let second = (logvar.exp()? + mu.sqr()?)?.mean(0)?;
        let var = (second - m.sqr()?)?.clamp(1e-12f32, f32::MAX)?;
        Ok(LatentGaussian {
            mu: m.to_vec1()?,
            sigma: var.sqrt()?.to_vec1()?,
        })
    }

    /// Saves weights and standardisation with the config in the metadata.
    pub fn save(&self, path: &Path) -> Result<()> {
        let cfg = serde_json::to_string(&self.config).expect("config serialises");
        st_file::save(
            path,
            &self.tensors(),
            &[("format", FORMAT_TAG.to_string()), ("config", cfg)],
        )
    }

    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| EngineError::io(path, e))?;
        let meta = st_file::metadata(path, &bytes)?;
        if meta.get("format").map(String::as_str) != Some(FORMAT_TAG) {
            return Err(EngineError::artifact(
                path,
                format!("not a style VAE: metadata `format` is not {FORMAT_TAG}"),
            ));
        }
        let config: VaeConfig = meta
            .get("config")
            .and_then(|c| serde_json::from_str(c).ok())
            .ok_or_else(|| {
                EngineError::artifact(path, "style VAE metadata lacks a valid `config`")
            })?;
        let vae = Self::new(config, 0, device)?;
        let tensors = candle_core::safetensors::load_buffer(&bytes, device)?;
        vae.load_tensors(&tensors, path)?;
        Ok(vae)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two "styles": clusters of 64-dim vectors around different centres, with spread.
    fn clusters(rng: &mut Rng) -> (Tensor, Tensor) {
        let dim = 64;
        let centre = |j: usize, d: usize| {
            ((d * 7 + j * 13) % 11) as f32 * (if j == 0 { 1.0 } else { -0.5 }) + 3.0
        };
        let sample = |j: usize, rng: &mut Rng| -> Vec<f32> {
            (0..dim)
                .map(|d| centre(j, d) + 0.1 * rng.normal())
                .collect()
        };
        let a: Vec<f32> = (0..24).flat_map(|_| sample(0, rng)).collect();
        let b: Vec<f32> = (0..24).flat_map(|_| sample(1, rng)).collect();
        (
            Tensor::from_vec(a, (24, dim), &Device::Cpu).unwrap(),
            Tensor::from_vec(b, (24, dim), &Device::Cpu).unwrap(),
        )
    }

    #[test]
    fn round_trip_separates_styles_and_reconstructs() {
        let mut rng = Rng::new(1);
        let (a, b) = clusters(&mut rng);
        let cfg = VaeConfig {
            input: 64,
            hidden: 64,
            latent: 8,
            kl_weight: 1e-3,
        };
        let vae = StyleVae::new(cfg, 2, &Device::Cpu).unwrap();
        let all = Tensor::cat(&[&a, &b], 0).unwrap();
        let losses = vae.train(&all, 300, 3e-3, &mut rng).unwrap();
        assert!(losses.reconstruction < 0.1, "{losses:?}");
        let da = vae.style_distribution(&a).unwrap();
        let db = vae.style_distribution(&b).unwrap();
        // Decoding a style's μ gives back (about) its centre; the two styles stay apart.
        let err = |d: &LatentGaussian, x: &Tensor| -> f32 {
            let z = Tensor::from_vec(d.mu.clone(), (1, 8), &Device::Cpu).unwrap();
            let rec = vae.decode(&z).unwrap();
            rec.broadcast_sub(&x.mean_keepdim(0).unwrap())
                .unwrap()
                .abs()
                .unwrap()
                .mean_all()
                .unwrap()
                .to_scalar()
                .unwrap()
        };
        assert!(
            err(&da, &a) < 0.3 && err(&db, &b) < 0.3,
            "{} {}",
            err(&da, &a),
            err(&db, &b)
        );
        let gap: f32 = da
            .mu
            .iter()
            .zip(&db.mu)
            .map(|(x, y)| (x - y).powi(2))
            .sum::<f32>()
            .sqrt();
        let spread: f32 = da.sigma.iter().chain(&db.sigma).sum::<f32>() / 16.0;
        assert!(gap > 4.0 * spread, "gap {gap}, spread {spread}");
        // Save/load reproduces the distributions exactly.
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("vae.safetensors");
        vae.save(&p).unwrap();
        let back = StyleVae::load(&p, &Device::Cpu).unwrap();
        assert_eq!(back.config, cfg);
        assert_eq!(back.style_distribution(&a).unwrap(), da);
    }

    #[test]
    fn mixture_moments() {
        // Two crops with posteriors N(0, 1) and N(2, 1) → mixture mean 1, variance 1 + 1 = 2.
        let cfg = VaeConfig {
            input: 2,
            hidden: 2,
            latent: 1,
            kl_weight: 0.0,
        };
        let vae = StyleVae::new(cfg, 0, &Device::Cpu).unwrap();
        let mut t = HashMap::new();
        let dev = Device::Cpu;
        let m = |v: &[f32], s: (usize, usize)| Tensor::from_slice(v, s, &dev).unwrap();
        t.insert(
            "vae.input_mean".to_string(),
            m(&[0., 0.], (1, 2)).squeeze(0).unwrap(),
        );
        t.insert(
            "vae.input_std".to_string(),
            m(&[1., 1.], (1, 2)).squeeze(0).unwrap(),
        );
        // Hidden = relu(x) (identity on positive inputs), μ = 2·h0, log σ² = 0.
        t.insert("vae.enc.weight".into(), m(&[1., 0., 0., 1.], (2, 2)));
        t.insert(
            "vae.enc.bias".into(),
            m(&[0., 0.], (1, 2)).squeeze(0).unwrap(),
        );
        t.insert("vae.enc_mu.weight".into(), m(&[2., 0.], (1, 2)));
        t.insert(
            "vae.enc_mu.bias".into(),
            m(&[0.], (1, 1)).squeeze(0).unwrap(),
        );
        t.insert("vae.enc_logvar.weight".into(), m(&[0., 0.], (1, 2)));
        t.insert(
            "vae.enc_logvar.bias".into(),
            m(&[0.], (1, 1)).squeeze(0).unwrap(),
        );
        for (n, s) in [("dec", (2, 1)), ("dec_out", (2, 2))] {
            t.insert(
                format!("vae.{n}.weight"),
                Tensor::zeros(s, DType::F32, &dev).unwrap(),
            );
            t.insert(
                format!("vae.{n}.bias"),
                Tensor::zeros(2, DType::F32, &dev).unwrap(),
            );
        }
        vae.load_tensors(&t, Path::new("test")).unwrap();
        let d = vae
            .style_distribution(&m(&[0., 0., 1., 0.], (2, 2)))
            .unwrap();
        assert!(
            (d.mu[0] - 1.0).abs() < 1e-6 && (d.sigma[0] - 2f32.sqrt()).abs() < 1e-5,
            "{d:?}"
        );
    }
}
