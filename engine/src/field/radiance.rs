//! The radiance field proper: hash-grid encoding → density network (σ and geometry features)
//! → colour network conditioned on the view direction.
//!
//! Density and colour are separate sets of variables ([`RadianceField::density_vars`],
//! [`RadianceField::colour_vars`]) so density can be frozen after pretraining, and the
//! geometry features are exposed ([`FieldSamples::geometry`]) for the stylized NeRF's style
//! module to reuse.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor, Var};
use serde::{Deserialize, Serialize};

use crate::field::hash_grid::{self, HashGrid, HashGridConfig};
use crate::field::mlp::Mlp;
use crate::field::occupancy::OccupancyGrid;
use crate::field::sh::sh16;
use crate::field::space::FieldSpace;
use crate::named::{load_vars, tensors_of};
use crate::rays::Samples;
use crate::rng::Rng;
use crate::scene::Background;
use crate::{EngineError, Result};

/// Architecture of the field.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FieldConfig {
    pub grid: HashGridConfig,
    pub density_hidden: usize,
    /// Geometry features output next to σ (fed to the colour and style networks).
    pub geometry_features: usize,
    pub colour_hidden: usize,
    pub occupancy_resolution: usize,
    /// Added to the raw density before the exponential: sets the initial density (e^bias per
    /// unit length), so a fresh field is a light haze rather than a fog.
    pub density_bias: f32,
}

/// Field-network inputs and outputs at a set of samples.
pub struct FieldSamples {
    /// Density σ [N] (≥ 0).
    pub sigma: Tensor,
    /// Geometry features [N, G].
    pub geometry: Tensor,
    /// Positions normalised to [0, 1]³ [N, 3].
    pub points01: Tensor,
    /// SH encoding of the view direction [N, 16].
    pub view_sh: Tensor,
}

pub struct RadianceField {
    pub config: FieldConfig,
    pub space: FieldSpace,
    pub grid: HashGrid,
    pub density_net: Mlp,
    pub colour_net: Mlp,
    /// The learned background: SH of the view direction → colour (only for
    /// [`Background::Learned`]).
    pub background_net: Option<Mlp>,
    pub occupancy: OccupancyGrid,
}

/// Hidden width of the learned background's network.
const BACKGROUND_HIDDEN: usize = 32;

/// Largest raw density before the exponential (keeps σ finite in f32).
const MAX_LOG_SIGMA: f64 = 15.0;

/// Points per density-network pass of the gradient-free evaluations.
const VALUE_CHUNK: usize = 65536;

/// [`RadianceField::geometry_values`]: per point, its normalised position (3 values), σ and
/// geometry features (`geometry_features` values), packed point after point.
#[derive(Debug, Clone, Default)]
pub struct GeometryValues {
    pub points01: Vec<f32>,
    pub sigma: Vec<f32>,
    pub geometry: Vec<f32>,
}

impl RadianceField {
    pub fn new(
        config: FieldConfig,
        space: FieldSpace,
        rng: &mut Rng,
        device: &Device,
    ) -> Result<Self> {
        let grid = HashGrid::new(config.grid, rng, device)?;
        let density_net = Mlp::new(
            "density",
            &[
                config.grid.output_dim(),
                config.density_hidden,
                1 + config.geometry_features,
            ],
            rng,
            DType::F32,
            device,
        )?;
        let colour_net = Mlp::new(
            "colour",
            &[
                config.geometry_features + 16,
                config.colour_hidden,
                config.colour_hidden,
                3,
            ],
            rng,
            DType::F32,
            device,
        )?;
        let background_net = match space.background {
            Background::Learned => Some(Mlp::new(
                "background",
                &[16, BACKGROUND_HIDDEN, 3],
                rng,
                DType::F32,
                device,
            )?),
            Background::Colour(_) => None,
        };
        Ok(Self {
            config,
            space,
            grid,
            density_net,
            colour_net,
            background_net,
            occupancy: OccupancyGrid::new(config.occupancy_resolution, space.aabb),
        })
    }

    pub fn device(&self) -> &Device {
        self.grid.table.device()
    }

    /// Variables that define density and geometry (frozen after pretraining).
    pub fn density_vars(&self) -> Vec<(String, Var)> {
        let mut v = vec![("grid.table".to_string(), self.grid.table.clone())];
        v.extend(self.density_net.vars());
        v
    }

    /// Variables of the view-dependent colour head and the learned background.
    pub fn colour_vars(&self) -> Vec<(String, Var)> {
        let mut v = self.colour_net.vars();
        if let Some(net) = &self.background_net {
            v.extend(net.vars());
        }
        v
    }

    pub fn vars(&self) -> Vec<(String, Var)> {
        let mut v = self.density_vars();
        v.extend(self.colour_vars());
        v
    }

    /// Normalised positions [N, 3] for packed field-space positions.
    pub fn points01(&self, positions: &[f32]) -> Result<Tensor> {
        let aabb = self.space.aabb;
        let p = hash_grid::normalise(positions, aabb.min, aabb.size());
        Ok(Tensor::from_vec(
            p,
            (positions.len() / 3, 3),
            self.device(),
        )?)
    }

    /// σ and geometry features at normalised points.
    pub fn geometry(&self, points01: &Tensor) -> Result<(Tensor, Tensor)> {
        self.geometry_of_encoding(&self.grid.encode(points01)?)
    }

    /// σ and geometry features from the hash encoding of the points.
    fn geometry_of_encoding(&self, encoding: &Tensor) -> Result<(Tensor, Tensor)> {
        let h = self.density_net.forward(encoding)?;
        let raw = (h.narrow(1, 0, 1)?.squeeze(1)? + self.config.density_bias as f64)?;
        let sigma = raw.clamp(-MAX_LOG_SIGMA, MAX_LOG_SIGMA)?.exp()?;
        let geometry = h.narrow(1, 1, self.config.geometry_features)?;
        Ok((sigma, geometry))
    }

    /// The samples each ray still sees (transmittance in front of them ≥ `eps`), found front
    /// to back ([`Samples::front_to_back`]), and their normalised positions, σ and geometry
    /// features, without gradients; the arrays are indexed like `marched` and hold zeros
    /// where a sample was not evaluated.
    pub fn visible_geometry(
        &self,
        marched: &Samples,
        eps: f32,
    ) -> Result<(Vec<bool>, GeometryValues)> {
        let g = self.config.geometry_features;
        let n = marched.ray.len();
        let (mut points01, mut geometry) = (vec![0.0; 3 * n], vec![0.0; g * n]);
        let (keep, sigma) = marched.front_to_back(eps, |idx| {
            let v = self.geometry_values(&marched.positions_of(idx))?;
            for (j, &k) in idx.iter().enumerate() {
                points01[3 * k..3 * k + 3].copy_from_slice(&v.points01[3 * j..3 * j + 3]);
                geometry[g * k..g * (k + 1)].copy_from_slice(&v.geometry[g * j..g * (j + 1)]);
            }
            Ok(v.sigma)
        })?;
        let values = GeometryValues {
            points01,
            sigma,
            geometry,
        };
        Ok((keep, values))
    }

    /// σ at packed field-space positions, without gradients (occupancy updates, pruning).
    pub fn density_values(&self, positions: &[f32]) -> Result<Vec<f32>> {
        let mut out = Vec::with_capacity(positions.len() / 3);
        for chunk in positions.chunks(3 * VALUE_CHUNK) {
            let (sigma, _) = self.geometry(&self.points01(chunk)?)?;
            out.extend(sigma.detach().to_vec1::<f32>()?);
        }
        Ok(out)
    }

    /// σ at packed field-space positions without gradients, and the hash encoding it was
    /// computed from ([N · L·F]; for [`RadianceField::encoded_samples`]).
    pub fn density_and_encoding(&self, positions: &[f32]) -> Result<(Vec<f32>, Vec<f32>)> {
        let n = positions.len() / 3;
        let mut sigma = Vec::with_capacity(n);
        let mut encoding = Vec::with_capacity(n * self.config.grid.output_dim());
        for chunk in positions.chunks(3 * VALUE_CHUNK) {
            let e = self.grid.encode(&self.points01(chunk)?)?;
            let (s, _) = self.geometry_of_encoding(&e)?;
            sigma.extend(s.detach().to_vec1::<f32>()?);
            encoding.extend(e.detach().flatten_all()?.to_vec1::<f32>()?);
        }
        Ok((sigma, encoding))
    }

    /// Normalised positions, σ and geometry features at packed field-space positions, without
    /// gradients: what a cache of the frozen density keeps.
    fn geometry_values(&self, positions: &[f32]) -> Result<GeometryValues> {
        let n = positions.len() / 3;
        let mut out = GeometryValues {
            points01: Vec::with_capacity(3 * n),
            sigma: Vec::with_capacity(n),
            geometry: Vec::with_capacity(n * self.config.geometry_features),
        };
        for chunk in positions.chunks(3 * VALUE_CHUNK) {
            let points01 = self.points01(chunk)?;
            let (sigma, geometry) = self.geometry(&points01)?;
            out.points01
                .extend(points01.flatten_all()?.to_vec1::<f32>()?);
            out.sigma.extend(sigma.detach().to_vec1::<f32>()?);
            out.geometry
                .extend(geometry.detach().flatten_all()?.to_vec1::<f32>()?);
        }
        Ok(out)
    }

    /// Evaluates the geometry at `samples`, with the view directions of their rays, given the
    /// samples' hash encoding computed without gradients
    /// ([`RadianceField::density_and_encoding`]): the values and gradients of encoding them
    /// again, without looking the encoding up again.
    pub fn encoded_samples(
        &self,
        samples: &Samples,
        encoding: Vec<f32>,
        view_dirs: &[glam::Vec3],
    ) -> Result<FieldSamples> {
        let points01 = self.points01(&samples.positions)?;
        let encoding = hash_grid::encode_known(
            &self.grid.config,
            self.grid.table.as_tensor(),
            &points01,
            encoding,
        )?;
        let (sigma, geometry) = self.geometry_of_encoding(&encoding)?;
        Ok(FieldSamples {
            sigma,
            geometry,
            points01,
            view_sh: self.view_sh(samples, view_dirs)?,
        })
    }

    /// [`RadianceField::encoded_samples`] without gradients and without evaluating the density
    /// again: the entries of `values` (computed at all the samples `samples` was filtered from)
    /// that `keep` marks.
    pub fn kept_samples(
        &self,
        values: &GeometryValues,
        keep: &[bool],
        samples: &Samples,
        view_dirs: &[glam::Vec3],
    ) -> Result<FieldSamples> {
        let g = self.config.geometry_features;
        let n = samples.ray.len();
        let (mut sigma, mut geometry, mut points01) = (
            Vec::with_capacity(n),
            Vec::with_capacity(n * g),
            Vec::with_capacity(3 * n),
        );
        for k in (0..keep.len()).filter(|&k| keep[k]) {
            sigma.push(values.sigma[k]);
            geometry.extend_from_slice(&values.geometry[k * g..(k + 1) * g]);
            points01.extend_from_slice(&values.points01[3 * k..3 * k + 3]);
        }
        let dev = self.device();
        Ok(FieldSamples {
            sigma: Tensor::from_vec(sigma, n, dev)?,
            geometry: Tensor::from_vec(geometry, (n, g), dev)?,
            points01: Tensor::from_vec(points01, (n, 3), dev)?,
            view_sh: self.view_sh(samples, view_dirs)?,
        })
    }

    /// SH encoding of each sample's view direction [N, 16].
    fn view_sh(&self, samples: &Samples, view_dirs: &[glam::Vec3]) -> Result<Tensor> {
        let sh: Vec<f32> = samples
            .ray
            .iter()
            .flat_map(|&r| sh16(view_dirs[r as usize].to_array()))
            .collect();
        Ok(Tensor::from_vec(
            sh,
            (samples.ray.len(), 16),
            self.device(),
        )?)
    }

    /// The photoreal colour of the field at evaluated samples [N, 3].
    pub fn colour(&self, s: &FieldSamples) -> Result<Tensor> {
        let x = Tensor::cat(&[&s.geometry, &s.view_sh], 1)?;
        Ok(candle_nn::ops::sigmoid(&self.colour_net.forward(&x)?)?)
    }

    /// What rays that leave the content see: `[1, 3]` for a known colour, `[R, 3]` per view
    /// direction for a learned background.
    pub fn background(&self, view_dirs: &[glam::Vec3]) -> Result<Tensor> {
        match &self.background_net {
            Some(net) => {
                let sh: Vec<f32> = view_dirs.iter().flat_map(|d| sh16(d.to_array())).collect();
                let x = Tensor::from_vec(sh, (view_dirs.len(), 16), self.device())?;
                Ok(candle_nn::ops::sigmoid(&net.forward(&x)?)?)
            }
            // Only a known colour has no network (see `new`).
            None => Ok(Tensor::from_slice(
                &self.space.background.alpha_colour(),
                (1, 3),
                self.device(),
            )?),
        }
    }

    /// Refreshes the occupancy grid from the current density.
    pub fn update_occupancy(
        &mut self,
        rng: &mut Rng,
        cells: usize,
        sigma_threshold: f32,
    ) -> Result<()> {
        let mut grid =
            std::mem::replace(&mut self.occupancy, OccupancyGrid::new(1, self.space.aabb));
        let res = grid.update(
            |p| self.density_values(p),
            rng,
            cells,
            0.95,
            sigma_threshold,
        );
        self.occupancy = grid;
        res
    }

    /// All tensors that define the field, occupancy included (for checkpoints and outputs).
    pub fn tensors(&self) -> Result<Vec<(String, Tensor)>> {
        let mut t = tensors_of(&self.vars());
        let occ = Tensor::from_slice(
            &self.occupancy.density,
            self.occupancy.density.len(),
            &Device::Cpu,
        )?;
        t.push(("occupancy.density".to_string(), occ));
        Ok(t)
    }

    /// Restores tensors written by [`RadianceField::tensors`].
    pub fn load_tensors(
        &mut self,
        tensors: &HashMap<String, Tensor>,
        source: &Path,
        sigma_threshold: f32,
    ) -> Result<()> {
        load_vars(&self.vars(), tensors, source)?;
        let occ = tensors
            .get("occupancy.density")
            .ok_or_else(|| EngineError::artifact(source, "tensor `occupancy.density` missing"))?;
        let density: Vec<f32> = occ.to_vec1()?;
        if density.len() != self.config.occupancy_resolution.pow(3) {
            return Err(EngineError::artifact(
                source,
                "occupancy grid size does not match the field config",
            ));
        }
        self.occupancy = OccupancyGrid::from_density(
            self.config.occupancy_resolution,
            self.space.aabb,
            density,
            sigma_threshold,
        );
        Ok(())
    }
}
