//! The style module: the stylized NeRF's colour head. An MLP maps a sample's frozen geometry
//! features (from the pretrained density network), a sinusoidal encoding of its position and
//! the latent code l of the (view, style) instance to an RGB colour; it replaces the
//! photoreal colour head while density stays frozen. It takes no view direction, so a style
//! is painted onto the surfaces and every view sees the same colours.
//!
//! Choice over the paper (position + latent only): the geometry features are a function of
//! position too, so consistency is unchanged, but they give the small MLP the field's learned
//! description of each surface (edges, materials), which it would otherwise have to relearn
//! from a positional encoding in a few hundred steps.
//!
//! The background (the share of each ray that hits nothing) gets its own head: the latent and
//! a sinusoidal encoding of the ray's world direction, so a style (or a blend of styles)
//! paints the backdrop as a dome around the scene — textured, and the same from every view,
//! as a background at infinity is. With `background_frequencies` 0 (modules written before
//! it existed) the head sees the latent only and paints one colour.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor, Var};
use serde::{Deserialize, Serialize};

use super::surface::SurfaceBatch;
use crate::field::mlp::Mlp;
use crate::named::load_vars;
use crate::rng::Rng;
use crate::style2d::st_file;
use crate::{EngineError, Result};

const FORMAT_TAG: &str = "stylenerf-style-module/1";

/// Shape of the style module.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StyleModuleConfig {
    pub hidden: usize,
    pub hidden_layers: usize,
    /// Octaves of the positional encoding (sin and cos of 2^k π x for k < this).
    pub frequencies: usize,
    /// Feed the field's geometry features (see the module docs).
    pub use_geometry: bool,
    /// Octaves of the direction encoding in the background head (0: one colour per latent).
    #[serde(default)]
    pub background_frequencies: usize,
}

impl Default for StyleModuleConfig {
    fn default() -> Self {
        Self {
            hidden: 64,
            hidden_layers: 3,
            frequencies: 6,
            use_geometry: true,
            background_frequencies: 4,
        }
    }
}

/// The style module's weights.
pub struct StyleModule {
    pub config: StyleModuleConfig,
    pub geometry_dim: usize,
    pub latent_dim: usize,
    colour_net: Mlp,
    background_net: Mlp,
}

impl StyleModule {
    pub fn new(
        config: StyleModuleConfig,
        geometry_dim: usize,
        latent_dim: usize,
        seed: u64,
        dtype: DType,
        device: &Device,
    ) -> Result<Self> {
        let mut rng = Rng::new(seed);
        let input = if config.use_geometry { geometry_dim } else { 0 }
            + 3 * (1 + 2 * config.frequencies)
            + latent_dim;
        let mut widths = vec![input];
        widths.extend(std::iter::repeat_n(config.hidden, config.hidden_layers));
        widths.push(3);
        let background_widths = match config.background_frequencies {
            0 => vec![latent_dim, 32, 3],
            f => vec![latent_dim + 3 * (1 + 2 * f), 64, 64, 3],
        };
        Ok(Self {
            config,
            geometry_dim,
            latent_dim,
            colour_net: Mlp::new("style.colour", &widths, &mut rng, dtype, device)?,
            background_net: Mlp::new(
                "style.background",
                &background_widths,
                &mut rng,
                dtype,
                device,
            )?,
        })
    }

    pub fn vars(&self) -> Vec<(String, Var)> {
        let mut v = self.colour_net.vars();
        v.extend(self.background_net.vars());
        v
    }

    /// Sinusoidal encoding `[N, 3 (1 + 2F)]` of points in [0, 1]³ with `f` octaves: x,
    /// sin(2^k π x), cos(2^k π x).
    fn encode(points01: &Tensor, f: usize) -> Result<Tensor> {
        let n = points01.dim(0)?;
        let scales: Vec<f32> = (0..f)
            .map(|k| std::f32::consts::PI * (1u32 << k) as f32)
            .collect();
        let scales =
            Tensor::from_vec(scales, (1, 1, f), points01.device())?.to_dtype(points01.dtype())?;
        let arg = points01.unsqueeze(2)?.broadcast_mul(&scales)?; // [N, 3, F]
        Ok(Tensor::cat(
            &[
                points01.clone(),
                arg.sin()?.reshape((n, 3 * f))?,
                arg.cos()?.reshape((n, 3 * f))?,
            ],
            1,
        )?)
    }

    /// Colours `[N, 3]` of a batch's samples under latent `[1, Z]`.
    pub fn sample_colours(&self, batch: &SurfaceBatch, latent: &Tensor) -> Result<Tensor> {
        let n = batch.points01.dim(0)?;
        let mut parts = Vec::with_capacity(3);
        if self.config.use_geometry {
            parts.push(batch.geometry.to_dtype(latent.dtype())?);
        }
        parts.push(Self::encode(
            &batch.points01.to_dtype(latent.dtype())?,
            self.config.frequencies,
        )?);
        parts.push(latent.broadcast_as((n, self.latent_dim))?.contiguous()?);
        let x = Tensor::cat(&parts, 1)?;
        Ok(candle_nn::ops::sigmoid(&self.colour_net.forward(&x)?)?)
    }

    /// Background colour under latent `[1, Z]` of rays with unit `directions` `[R, 3]`:
    /// `[R, 3]`, or `[1, 3]` for every ray when the head takes no direction.
    pub fn background(&self, latent: &Tensor, directions: &Tensor) -> Result<Tensor> {
        let input = match self.config.background_frequencies {
            0 => latent.clone(),
            f => {
                let unit = ((directions.to_dtype(latent.dtype())? + 1.0)? * 0.5)?;
                let r = unit.dim(0)?;
                Tensor::cat(
                    &[
                        latent.broadcast_as((r, self.latent_dim))?.contiguous()?,
                        Self::encode(&unit, f)?,
                    ],
                    1,
                )?
            }
        };
        Ok(candle_nn::ops::sigmoid(
            &self.background_net.forward(&input)?,
        )?)
    }

    /// Stylized colour `[R, 3]` of the batch's rays under latent `[1, Z]`.
    pub fn render(&self, batch: &SurfaceBatch, latent: &Tensor) -> Result<Tensor> {
        if batch.points01.dim(0)? == 0 {
            // No ray hits anything (candle cannot slice empty tensors): all background.
            return Ok(self
                .background(latent, &batch.directions)?
                .broadcast_as((batch.num_rays, 3))?
                .contiguous()?);
        }
        let colours = self.sample_colours(batch, latent)?;
        let w = batch.weights.to_dtype(colours.dtype())?;
        let t = batch.transparency.to_dtype(colours.dtype())?;
        let batch = SurfaceBatch {
            weights: w,
            transparency: t,
            ..batch.clone()
        };
        batch.composite(&colours, &self.background(latent, &batch.directions)?)
    }

    /// Writes the weights and shape to `path` (safetensors with metadata).
    pub fn save(&self, path: &Path) -> Result<()> {
        let tensors: Vec<(String, Tensor)> = self
            .vars()
            .into_iter()
            .map(|(n, v)| (n, v.as_tensor().clone()))
            .collect();
        let config = serde_json::to_string(&self.config).expect("serialisable config");
        st_file::save(
            path,
            &tensors,
            &[
                ("format", FORMAT_TAG.into()),
                ("config", config),
                ("geometry_dim", self.geometry_dim.to_string()),
                ("latent_dim", self.latent_dim.to_string()),
            ],
        )
    }

    /// Reads a style module written by [`StyleModule::save`].
    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| EngineError::io(path, e))?;
        let meta = st_file::metadata(path, &bytes)?;
        let field = |k: &str| {
            meta.get(k).ok_or_else(|| {
                EngineError::artifact(path, format!("metadata `{k}` missing: not a style module"))
            })
        };
        if field("format")? != FORMAT_TAG {
            return Err(EngineError::artifact(path, "not a stylenerf style module"));
        }
        let config: StyleModuleConfig = serde_json::from_str(field("config")?)
            .map_err(|e| EngineError::artifact(path, format!("metadata `config`: {e}")))?;
        let parse = |k: &str| {
            field(k)?
                .parse::<usize>()
                .map_err(|e| EngineError::artifact(path, format!("metadata `{k}`: {e}")))
        };
        let module = Self::new(
            config,
            parse("geometry_dim")?,
            parse("latent_dim")?,
            0,
            DType::F32,
            device,
        )?;
        let tensors: HashMap<String, Tensor> =
            candle_core::safetensors::load_buffer(&bytes, device)?
                .into_iter()
                .collect();
        load_vars(&module.vars(), &tensors, path)?;
        Ok(module)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::style2d::gradcheck;
    use crate::stylized::surface::SurfaceSamples;

    fn batch(device: &Device) -> SurfaceBatch {
        // Three rays with 2, 0 and 3 samples.
        let n = 5;
        SurfaceBatch {
            num_rays: 3,
            geometry: gradcheck::random(&[n, 4], 1),
            points01: ((gradcheck::random(&[n, 3], 2) + 1.0).unwrap() * 0.5).unwrap(),
            weights: Tensor::new(&[[0.5f64], [0.3], [0.2], [0.6], [0.1]], device).unwrap(),
            ray: Tensor::new(&[0u32, 0, 2, 2, 2], device).unwrap(),
            transparency: Tensor::new(&[[0.2f64], [1.0], [0.1]], device).unwrap(),
            directions: Tensor::new(
                &[[0.6f64, 0.0, 0.8], [0.0, 1.0, 0.0], [-0.8, 0.0, 0.6]],
                device,
            )
            .unwrap(),
        }
    }

    #[test]
    fn gradients_match_finite_differences() {
        let dev = Device::Cpu;
        let cfg = StyleModuleConfig {
            hidden: 8,
            hidden_layers: 2,
            frequencies: 2,
            use_geometry: true,
            background_frequencies: 2,
        };
        let module = StyleModule::new(cfg, 4, 3, 5, DType::F64, &dev).unwrap();
        let b = batch(&dev);
        // With respect to the latent code.
        gradcheck::check(&gradcheck::random(&[1, 3], 3), |l| {
            module
                .render(&b, l)
                .map_err(|e| candle_core::Error::Msg(e.to_string()))
        });
        // With respect to the colour network's parameters.
        let latent = gradcheck::random(&[1, 3], 4);
        let params = module.colour_net.vars()[0].1.clone();
        let p0 = params.as_tensor().copy().unwrap();
        let widths = [4 + 3 * 5 + 3, 8, 8, 3];
        let x = {
            let enc = StyleModule::encode(&b.points01, 2).unwrap();
            Tensor::cat(
                &[
                    b.geometry.clone(),
                    enc,
                    latent.broadcast_as((5, 3)).unwrap(),
                ],
                1,
            )
            .unwrap()
        };
        let bg = module.background(&latent, &b.directions).unwrap().detach();
        gradcheck::check(&p0, |p| {
            let c = candle_nn::ops::sigmoid(
                &crate::field::mlp::forward_composed(&widths, &x, p)
                    .map_err(|e| candle_core::Error::Msg(e.to_string()))?,
            )?;
            b.composite(&c, &bg)
                .map_err(|e| candle_core::Error::Msg(e.to_string()))
        });
        // The fused network agrees with the composed one used above.
        let fused = module.sample_colours(&b, &latent).unwrap();
        let composed = candle_nn::ops::sigmoid(
            &crate::field::mlp::forward_composed(&widths, &x, &p0).unwrap(),
        )
        .unwrap();
        let err = (fused - composed)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        assert!(err < 1e-9, "{err}");
    }

    #[test]
    fn empty_rays_show_the_background_and_save_round_trips() {
        let dev = Device::Cpu;
        let module =
            StyleModule::new(StyleModuleConfig::default(), 4, 3, 1, DType::F32, &dev).unwrap();
        let b64 = batch(&dev);
        let b = SurfaceBatch {
            geometry: b64.geometry.to_dtype(DType::F32).unwrap(),
            points01: b64.points01.to_dtype(DType::F32).unwrap(),
            weights: b64.weights.to_dtype(DType::F32).unwrap(),
            transparency: b64.transparency.to_dtype(DType::F32).unwrap(),
            directions: b64.directions.to_dtype(DType::F32).unwrap(),
            ..b64
        };
        let l = Tensor::new(&[[0.3f32, -1.0, 2.0]], &dev).unwrap();
        let empty = SurfaceSamples {
            offsets: vec![0, 0, 0],
            directions: vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            geometry_dim: 4,
            ..Default::default()
        };
        let none = module.render(&empty.all(&dev).unwrap(), &l).unwrap();
        assert_eq!(none.dims(), &[2, 3]);
        // A background at infinity: its colour depends on the direction only.
        let bg_empty = module
            .background(&l, &empty.all(&dev).unwrap().directions)
            .unwrap();
        assert!(
            none.eq(&bg_empty)
                .unwrap()
                .min_all()
                .unwrap()
                .to_scalar::<u8>()
                .unwrap()
                == 1
        );
        let (first, second) = (none.get(0).unwrap(), none.get(1).unwrap());
        assert_ne!(
            first.to_vec1::<f32>().unwrap(),
            second.to_vec1::<f32>().unwrap()
        );
        let out = module.render(&b, &l).unwrap();
        let bg = module.background(&l, &b.directions).unwrap();
        let row1 = out.get(1).unwrap().unsqueeze(0).unwrap();
        let err = (row1 - bg.get(1).unwrap().unsqueeze(0).unwrap())
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(err < 1e-6);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("style.safetensors");
        module.save(&path).unwrap();
        let back = StyleModule::load(&path, &dev).unwrap();
        let again = back.render(&b, &l).unwrap();
        let err = (again - out)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(err < 1e-6);
    }
}
