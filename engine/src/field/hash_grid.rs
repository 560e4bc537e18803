//! Multiresolution hash-grid encoding (instant-ngp): L levels of trilinearly interpolated
//! feature grids from coarse to fine; coarse levels are stored densely, fine levels in a
//! spatially hashed table of T entries.
//!
//! On CPU the encoding is a fused candle `CustomOp2` (table, points) with an analytic backward
//! that scatters the output gradient into the table, one level per task so no two threads
//! write the same rows. Other devices (and the gradient test's reference) use the composed
//! path: `index_select` of the corner rows times the trilinear weights, whose backward
//! (`index_add`) is correct in candle. Points are positions normalised to [0, 1]³ and carry no
//! gradient.

use candle_core::{CpuStorage, CustomOp2, Device, Layout, Shape, Tensor, Var, WithDType};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::cpu_ops::contiguous_slice;
use crate::rng::Rng;
use crate::Result;

/// Shape of the encoding.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HashGridConfig {
    pub levels: usize,
    pub features_per_level: usize,
    pub log2_table_size: u32,
    pub base_resolution: f32,
    pub max_resolution: f32,
}

impl HashGridConfig {
    pub fn table_size(&self) -> usize {
        1 << self.log2_table_size
    }

    pub fn output_dim(&self) -> usize {
        self.levels * self.features_per_level
    }

    /// Grid resolution (cells per axis) of level `l`.
    pub fn resolution(&self, level: usize) -> u32 {
        if self.levels <= 1 {
            return self.base_resolution as u32;
        }
        let growth = (self.max_resolution / self.base_resolution).ln() / (self.levels - 1) as f32;
        (self.base_resolution * (growth * level as f32).exp()).floor() as u32
    }
}

/// Per-level lookup parameters, computed once per op.
#[derive(Debug, Clone, Copy)]
struct Level {
    resolution: u32,
    dense: bool,
    offset: usize,
}

fn levels(config: &HashGridConfig) -> Vec<Level> {
    let t = config.table_size();
    (0..config.levels)
        .map(|l| {
            let r = config.resolution(l);
            let verts = (r as u64 + 1).pow(3);
            Level {
                resolution: r,
                dense: verts <= t as u64,
                offset: l * t,
            }
        })
        .collect()
}

/// The 8 corner rows (absolute table rows) and trilinear weights of point `p` on `level`.
#[inline]
fn corners(level: &Level, mask: usize, p: [f32; 3]) -> [(usize, f32); 8] {
    let r = level.resolution;
    let mut base = [0u32; 3];
    let mut frac = [0f32; 3];
    for a in 0..3 {
        let x = p[a].clamp(0.0, 1.0) * r as f32;
        let i = (x.floor() as u32).min(r - 1);
        base[a] = i;
        frac[a] = x - i as f32;
    }
    let mut out = [(0usize, 0f32); 8];
    for (c, slot) in out.iter_mut().enumerate() {
        let (dx, dy, dz) = ((c & 1) as u32, ((c >> 1) & 1) as u32, ((c >> 2) & 1) as u32);
        let (x, y, z) = (base[0] + dx, base[1] + dy, base[2] + dz);
        let w = (if dx == 1 { frac[0] } else { 1.0 - frac[0] })
            * (if dy == 1 { frac[1] } else { 1.0 - frac[1] })
            * (if dz == 1 { frac[2] } else { 1.0 - frac[2] });
        let row = if level.dense {
            let n = (r + 1) as usize;
            x as usize + y as usize * n + z as usize * n * n
        } else {
            (x as usize
                ^ (y as usize).wrapping_mul(2_654_435_761)
                ^ (z as usize).wrapping_mul(805_459_861))
                & mask
        };
        *slot = (level.offset + row, w);
    }
    out
}

/// The learnable encoding: a table of shape [levels · T, features_per_level].
pub struct HashGrid {
    pub config: HashGridConfig,
    pub table: Var,
}

impl HashGrid {
    /// A table initialised uniformly in [−1e-4, 1e-4] (as in instant-ngp) from `rng`.
    pub fn new(config: HashGridConfig, rng: &mut Rng, device: &Device) -> Result<Self> {
        let rows = config.levels * config.table_size();
        let values: Vec<f32> = (0..rows * config.features_per_level)
            .map(|_| (rng.uniform() * 2.0 - 1.0) * 1e-4)
            .collect();
        let table = Var::from_tensor(&Tensor::from_vec(
            values,
            (rows, config.features_per_level),
            device,
        )?)?;
        Ok(Self { config, table })
    }

    /// Encodes points in [0, 1]³ ([N, 3], f32) into features [N, levels · F].
    pub fn encode(&self, points01: &Tensor) -> Result<Tensor> {
        encode(&self.config, self.table.as_tensor(), points01)
    }
}

/// Encodes with any table tensor (a `Var` or a detached copy).
pub fn encode(config: &HashGridConfig, table: &Tensor, points01: &Tensor) -> Result<Tensor> {
    encode_with(config, table, points01, None)
}

/// [`encode`] at points whose features were already computed from this table without
/// gradients (`known`, [N · L·F] f32): the same tensor, with the same backward into the table,
/// without looking the features up again. Other devices encode again.
pub fn encode_known(
    config: &HashGridConfig,
    table: &Tensor,
    points01: &Tensor,
    known: Vec<f32>,
) -> Result<Tensor> {
    encode_with(config, table, points01, Some(known))
}

/// The fused op on CPU (with `known` features only for an f32 table), the composed encoding
/// elsewhere.
fn encode_with(
    config: &HashGridConfig,
    table: &Tensor,
    points01: &Tensor,
    known: Option<Vec<f32>>,
) -> Result<Tensor> {
    if !table.device().is_cpu() {
        return encode_composed(config, table, points01);
    }
    let known = known.filter(|_| table.dtype() == candle_core::DType::F32);
    Ok(table.apply_op2(
        points01,
        HashEncode {
            config: *config,
            known,
        },
    )?)
}

/// Device-agnostic encoding from candle ops (the reference for the fused op).
pub fn encode_composed(
    config: &HashGridConfig,
    table: &Tensor,
    points01: &Tensor,
) -> Result<Tensor> {
    let pts: Vec<f32> = points01.to_device(&Device::Cpu)?.flatten_all()?.to_vec1()?;
    let n = pts.len() / 3;
    let lv = levels(config);
    let mask = config.table_size() - 1;
    let mut rows = Vec::with_capacity(n * lv.len() * 8);
    let mut weights = Vec::with_capacity(n * lv.len() * 8);
    for p in pts.chunks_exact(3) {
        for level in &lv {
            for (row, w) in corners(level, mask, [p[0], p[1], p[2]]) {
                rows.push(row as u32);
                weights.push(w);
            }
        }
    }
    let dev = table.device();
    let rows = Tensor::from_vec(rows, n * lv.len() * 8, dev)?;
    let weights = Tensor::from_vec(weights, (n * lv.len() * 8, 1), dev)?.to_dtype(table.dtype())?;
    let f = config.features_per_level;
    let gathered = table.index_select(&rows, 0)?.broadcast_mul(&weights)?;
    Ok(gathered
        .reshape((n, lv.len(), 8, f))?
        .sum(2)?
        .reshape((n, lv.len() * f))?)
}

fn points_slice<'a>(s: &'a CpuStorage, l: &Layout) -> candle_core::Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(d), Some((a, b))) if l.dims().len() == 2 && l.dims()[1] == 3 => {
            Ok(&d[a..b])
        }
        _ => candle_core::bail!("hash-grid: points must be a contiguous f32 [N, 3] tensor"),
    }
}

/// Fused forward: table [rows, F] × points [N, 3] → features [N, L·F] (`known`: the features,
/// already computed).
struct HashEncode {
    config: HashGridConfig,
    known: Option<Vec<f32>>,
}

impl HashEncode {
    fn forward<T: WithDType>(&self, table: &[T], pts: &[f32]) -> Vec<T> {
        let lv = levels(&self.config);
        let f = self.config.features_per_level;
        let mask = self.config.table_size() - 1;
        let width = lv.len() * f;
        let mut out = vec![T::zero(); pts.len() / 3 * width];
        out.par_chunks_mut(width * 256)
            .zip(pts.par_chunks(3 * 256))
            .for_each(|(out, pts)| {
                for (o, p) in out.chunks_exact_mut(width).zip(pts.chunks_exact(3)) {
                    for (l, level) in lv.iter().enumerate() {
                        let o = &mut o[l * f..(l + 1) * f];
                        for (row, w) in corners(level, mask, [p[0], p[1], p[2]]) {
                            let w = T::from_f64(w as f64);
                            for (k, o) in o.iter_mut().enumerate() {
                                *o += w * table[row * f + k];
                            }
                        }
                    }
                }
            });
        out
    }
}

impl CustomOp2 for HashEncode {
    fn name(&self) -> &'static str {
        "hash-encode"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let pts = points_slice(s2, l2)?;
        let shape = Shape::from((pts.len() / 3, self.config.output_dim()));
        let out = match (s1, &self.known) {
            (CpuStorage::F32(_), Some(known)) if known.len() == shape.elem_count() => {
                CpuStorage::F32(known.clone())
            }
            (_, Some(_)) => candle_core::bail!("hash-grid: the known features do not match"),
            (CpuStorage::F32(t), None) => {
                CpuStorage::F32(self.forward(contiguous_slice(t, l1, "hash-grid: table")?, pts))
            }
            (CpuStorage::F64(t), None) => {
                CpuStorage::F64(self.forward(contiguous_slice(t, l1, "hash-grid: table")?, pts))
            }
            _ => candle_core::bail!("hash-grid: table must be f32 or f64"),
        };
        Ok((out, shape))
    }

    fn bwd(
        &self,
        table: &Tensor,
        points: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let rows = table.dim(0)?;
        let grad_table = grad.contiguous()?.apply_op2_no_bwd(
            points,
            &HashScatter {
                config: self.config,
                rows,
            },
        )?;
        Ok((Some(grad_table), None))
    }
}

/// Backward of [`HashEncode`]: output gradient [N, L·F] × points → table gradient [rows, F].
struct HashScatter {
    config: HashGridConfig,
    rows: usize,
}

impl HashScatter {
    fn scatter<T: WithDType>(&self, grad: &[T], pts: &[f32]) -> Vec<T> {
        let lv = levels(&self.config);
        let f = self.config.features_per_level;
        let t = self.config.table_size();
        let mask = t - 1;
        let width = lv.len() * f;
        let mut out = vec![T::zero(); self.rows * f];
        // Each level owns a disjoint slice of the table: one task per level, no races.
        out.par_chunks_mut(t * f)
            .zip(lv.par_iter())
            .enumerate()
            .for_each(|(l, (dst, level))| {
                let local = Level {
                    offset: 0,
                    ..*level
                };
                for (g, p) in grad.chunks_exact(width).zip(pts.chunks_exact(3)) {
                    let g = &g[l * f..(l + 1) * f];
                    for (row, w) in corners(&local, mask, [p[0], p[1], p[2]]) {
                        let w = T::from_f64(w as f64);
                        for (k, g) in g.iter().enumerate() {
                            dst[row * f + k] += w * *g;
                        }
                    }
                }
            });
        out
    }
}

impl CustomOp2 for HashScatter {
    fn name(&self) -> &'static str {
        "hash-scatter"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let pts = points_slice(s2, l2)?;
        let shape = Shape::from((self.rows, self.config.features_per_level));
        let out = match s1 {
            CpuStorage::F32(g) => {
                CpuStorage::F32(self.scatter(contiguous_slice(g, l1, "hash-grid: gradient")?, pts))
            }
            CpuStorage::F64(g) => {
                CpuStorage::F64(self.scatter(contiguous_slice(g, l1, "hash-grid: gradient")?, pts))
            }
            _ => candle_core::bail!("hash-grid: gradient must be f32 or f64"),
        };
        Ok((out, shape))
    }
}

/// Normalises world (or NDC) positions into [0, 1]³ by an axis-aligned box.
pub fn normalise(points: &[f32], min: glam::Vec3, size: glam::Vec3) -> Vec<f32> {
    points
        .chunks_exact(3)
        .flat_map(|p| {
            [
                (p[0] - min.x) / size.x,
                (p[1] - min.y) / size.y,
                (p[2] - min.z) / size.z,
            ]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> HashGridConfig {
        // Two dense levels and two hashed ones.
        HashGridConfig {
            levels: 4,
            features_per_level: 2,
            log2_table_size: 9,
            base_resolution: 3.0,
            max_resolution: 20.0,
        }
    }

    fn points(n: usize, seed: u64) -> Tensor {
        let mut rng = Rng::new(seed);
        let v: Vec<f32> = (0..n * 3).map(|_| rng.uniform()).collect();
        Tensor::from_vec(v, (n, 3), &Device::Cpu).unwrap()
    }

    #[test]
    fn levels_are_dense_then_hashed() {
        let lv = levels(&small());
        assert!(lv[0].dense && !lv[3].dense);
        assert_eq!(small().resolution(0), 3);
        assert_eq!(small().resolution(3), 20);
    }

    #[test]
    fn fused_matches_composed_forward_and_backward() {
        let cfg = small();
        let table = Var::rand(
            -1.0f64,
            1.0,
            (cfg.levels * cfg.table_size(), 2),
            &Device::Cpu,
        )
        .unwrap();
        let pts = points(300, 1);
        let proj = Tensor::rand(-1.0f64, 1.0, (300, cfg.output_dim()), &Device::Cpu).unwrap();
        let fused = encode(&cfg, table.as_tensor(), &pts).unwrap();
        let composed = encode_composed(&cfg, table.as_tensor(), &pts).unwrap();
        let diff = (&fused - &composed)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        assert!(diff < 1e-12, "forward differs by {diff}");
        let g1 = (fused * &proj)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let g2 = (composed * &proj)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let (g1, g2) = (g1.get(&table).unwrap(), g2.get(&table).unwrap());
        let diff = (g1 - g2)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        assert!(diff < 1e-12, "backward differs by {diff}");
    }

    /// Known features give the tensor and the table gradient that encoding again gives, and
    /// features that do not match the points are refused.
    #[test]
    fn known_features_act_as_the_encoding() {
        let cfg = small();
        let table = Var::rand(
            -1.0f32,
            1.0,
            (cfg.levels * cfg.table_size(), 2),
            &Device::Cpu,
        )
        .unwrap();
        let pts = points(300, 2);
        let proj = Tensor::rand(-1.0f32, 1.0, (300, cfg.output_dim()), &Device::Cpu).unwrap();
        let fresh = encode(&cfg, table.as_tensor(), &pts).unwrap();
        let features: Vec<f32> = fresh.flatten_all().unwrap().to_vec1().unwrap();
        let known = encode_known(&cfg, table.as_tensor(), &pts, features.clone()).unwrap();
        assert_eq!(
            known.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            features
        );
        let [g1, g2] = [fresh, known].map(|e| {
            let grads = (e * &proj).unwrap().sum_all().unwrap().backward().unwrap();
            grads
                .get(&table)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
        });
        assert_eq!(g1, g2);
        let short = features[..features.len() - 1].to_vec();
        assert!(encode_known(&cfg, table.as_tensor(), &pts, short).is_err());
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let cfg = small();
        let rows = cfg.levels * cfg.table_size();
        let table = Var::rand(-1.0f64, 1.0, (rows, 2), &Device::Cpu).unwrap();
        let pts = points(50, 2);
        let proj = Tensor::rand(-1.0f64, 1.0, (50, cfg.output_dim()), &Device::Cpu).unwrap();
        let loss = |t: &Tensor| -> f64 {
            let y = encode(&cfg, t, &pts).unwrap();
            (y.sqr().unwrap() * &proj)
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar()
                .unwrap()
        };
        let y = encode(&cfg, table.as_tensor(), &pts).unwrap();
        let grads = (y.sqr().unwrap() * &proj)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        let analytic: Vec<f64> = grads
            .get(&table)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap();
        let base: Vec<f64> = table.flatten_all().unwrap().to_vec1().unwrap();
        // Check the rows that were touched (non-zero gradient) plus a few untouched ones.
        let mut checked = 0;
        for i in (0..base.len()).step_by(7) {
            let eps = 1e-6;
            let mut plus = base.clone();
            plus[i] += eps;
            let mut minus = base.clone();
            minus[i] -= eps;
            let t = |v: Vec<f64>| Tensor::from_vec(v, (rows, 2), &Device::Cpu).unwrap();
            let numeric = (loss(&t(plus)) - loss(&t(minus))) / (2.0 * eps);
            assert!(
                (numeric - analytic[i]).abs() < 1e-6 * (1.0 + numeric.abs()),
                "entry {i}: {numeric} vs {}",
                analytic[i]
            );
            checked += usize::from(analytic[i] != 0.0);
        }
        assert!(checked > 20, "too few touched entries checked: {checked}");
    }
}
