//! A resumable Adam optimiser and learning-rate schedules.
//!
//! candle-nn's AdamW cannot save its moments, so a resumed run would restart with cold moments
//! and diverge from an uninterrupted one. This Adam keeps its first and second moments as
//! tensors that go into checkpoints next to the weights. On CPU the update is two fused
//! in-place passes (moments, then parameters) instead of a dozen allocating tensor ops, which
//! matters for hash-grid tables with millions of entries; other devices use composed ops.

use candle_core::backprop::GradStore;
use candle_core::{CpuStorage, DType, Device, InplaceOp2, Layout, Tensor, Var};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::{EngineError, Result};

/// Adam hyper-parameters (plain Adam when `weight_decay` is 0; decoupled decay otherwise).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub weight_decay: f64,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: 0.0,
        }
    }
}

/// Learning-rate schedule: linear warm-up, then exponential decay from `lr` to `lr * final_ratio`
/// at `total_steps`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LrSchedule {
    pub lr: f64,
    pub warmup_steps: u64,
    pub final_ratio: f64,
    pub total_steps: u64,
}

impl LrSchedule {
    pub fn constant(lr: f64) -> Self {
        Self {
            lr,
            warmup_steps: 0,
            final_ratio: 1.0,
            total_steps: 1,
        }
    }

    /// Learning rate for the 0-based `step`.
    pub fn at(&self, step: u64) -> f64 {
        let warm = if step < self.warmup_steps {
            (step + 1) as f64 / self.warmup_steps as f64
        } else {
            1.0
        };
        let progress = (step as f64 / self.total_steps.max(1) as f64).min(1.0);
        self.lr * warm * self.final_ratio.powf(progress)
    }
}

struct Param {
    name: String,
    var: Var,
    /// First and second moments stacked: shape [2, numel].
    moments: Var,
}

/// Adam over named variables, with state that round-trips through checkpoints.
pub struct Adam {
    params: Vec<Param>,
    config: AdamConfig,
    step: u64,
}

impl Adam {
    pub fn new(vars: Vec<(String, Var)>, config: AdamConfig) -> Result<Self> {
        let params = vars
            .into_iter()
            .map(|(name, var)| {
                let moments = Var::zeros((2, var.elem_count()), var.dtype(), var.device())?;
                Ok(Param { name, var, moments })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            params,
            config,
            step: 0,
        })
    }

    /// Number of updates applied so far (restored from checkpoints).
    pub fn step_count(&self) -> u64 {
        self.step
    }

    /// Applies one update with learning rate `lr`. Variables without a gradient are left alone
    /// (their moments are not decayed either).
    pub fn step(&mut self, grads: &GradStore, lr: f64) -> Result<()> {
        self.step += 1;
        let c = self.config;
        let bias1 = 1.0 - c.beta1.powi(self.step as i32);
        let bias2 = 1.0 - c.beta2.powi(self.step as i32);
        for p in &self.params {
            let Some(grad) = grads.get(p.var.as_tensor()) else {
                continue;
            };
            let grad = grad.flatten_all()?.contiguous()?;
            let fused = matches!(p.var.device(), Device::Cpu)
                && p.var.dtype() == DType::F32
                && p.var.is_contiguous();
            if fused {
                p.moments.inplace_op2(
                    &grad,
                    &MomentUpdate {
                        beta1: c.beta1 as f32,
                        beta2: c.beta2 as f32,
                    },
                )?;
                p.var.inplace_op2(
                    p.moments.as_tensor(),
                    &ParamUpdate {
                        lr: lr as f32,
                        bias1: bias1 as f32,
                        bias2: bias2 as f32,
                        eps: c.eps as f32,
                        weight_decay: c.weight_decay as f32,
                    },
                )?;
            } else {
                composed_step(p, &grad, c, lr, bias1, bias2)?;
            }
        }
        Ok(())
    }

    /// The optimiser state as named tensors (`<name>.adam`: moments [2, numel]) for checkpoints.
    pub fn state(&self) -> Vec<(String, Tensor)> {
        self.params
            .iter()
            .map(|p| (format!("{}.adam", p.name), p.moments.as_tensor().clone()))
            .collect()
    }

    /// Restores moments saved by [`Adam::state`] and the step count.
    pub fn load_state(
        &mut self,
        tensors: &std::collections::HashMap<String, Tensor>,
        step: u64,
    ) -> Result<()> {
        for p in &self.params {
            let key = format!("{}.adam", p.name);
            let t = tensors.get(&key).ok_or_else(|| {
                EngineError::artifact(&key, "optimiser moments missing from checkpoint")
            })?;
            if t.dims() != p.moments.dims() {
                return Err(EngineError::artifact(
                    &key,
                    format!(
                        "moments have shape {:?}, expected {:?}",
                        t.dims(),
                        p.moments.dims()
                    ),
                ));
            }
            p.moments.set(
                &t.to_dtype(p.moments.dtype())?
                    .to_device(p.moments.device())?,
            )?;
        }
        self.step = step;
        Ok(())
    }
}

fn composed_step(
    p: &Param,
    grad: &Tensor,
    c: AdamConfig,
    lr: f64,
    bias1: f64,
    bias2: f64,
) -> Result<()> {
    let m = p.moments.get(0)?;
    let v = p.moments.get(1)?;
    let m = ((m * c.beta1)? + (grad * (1.0 - c.beta1))?)?;
    let v = ((v * c.beta2)? + (grad.sqr()? * (1.0 - c.beta2))?)?;
    let denom = ((&v / bias2)?.sqrt()? + c.eps)?;
    let update = ((&m / bias1)? / denom)?.reshape(p.var.shape())?;
    let decayed = (p.var.as_tensor() * (1.0 - lr * c.weight_decay))?;
    p.var.set(&(decayed - (update * lr)?)?)?;
    p.moments.set(&Tensor::stack(&[m, v], 0)?)?;
    Ok(())
}

fn cpu_slice<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> candle_core::Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(data), Some((start, end))) => Ok(&data[start..end]),
        _ => candle_core::bail!("adam: {what} must be contiguous f32"),
    }
}

fn cpu_slice_mut<'a>(
    s: &'a mut CpuStorage,
    l: &Layout,
    what: &str,
) -> candle_core::Result<&'a mut [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(data), Some((start, end))) => Ok(&mut data[start..end]),
        _ => candle_core::bail!("adam: {what} must be contiguous f32"),
    }
}

const CHUNK: usize = 1 << 14;

/// m ← β1 m + (1 − β1) g, v ← β2 v + (1 − β2) g², in place on the stacked moments.
struct MomentUpdate {
    beta1: f32,
    beta2: f32,
}

impl InplaceOp2 for MomentUpdate {
    fn name(&self) -> &'static str {
        "adam-moments"
    }

    fn cpu_fwd(
        &self,
        dst: &mut CpuStorage,
        dst_l: &Layout,
        g: &CpuStorage,
        gl: &Layout,
    ) -> candle_core::Result<()> {
        let g = cpu_slice(g, gl, "gradient")?;
        let moments = cpu_slice_mut(dst, dst_l, "moments")?;
        let (m, v) = moments.split_at_mut(g.len());
        let (b1, b2) = (self.beta1, self.beta2);
        m.par_chunks_mut(CHUNK)
            .zip(v.par_chunks_mut(CHUNK))
            .zip(g.par_chunks(CHUNK))
            .for_each(|((m, v), g)| {
                for ((m, v), &g) in m.iter_mut().zip(v.iter_mut()).zip(g) {
                    *m = b1 * *m + (1.0 - b1) * g;
                    *v = b2 * *v + (1.0 - b2) * g * g;
                }
            });
        Ok(())
    }
}

/// p ← p (1 − lr·wd) − lr · m̂ / (√v̂ + ε), in place on the parameter.
struct ParamUpdate {
    lr: f32,
    bias1: f32,
    bias2: f32,
    eps: f32,
    weight_decay: f32,
}

impl InplaceOp2 for ParamUpdate {
    fn name(&self) -> &'static str {
        "adam-params"
    }

    fn cpu_fwd(
        &self,
        dst: &mut CpuStorage,
        dst_l: &Layout,
        mv: &CpuStorage,
        mvl: &Layout,
    ) -> candle_core::Result<()> {
        let p = cpu_slice_mut(dst, dst_l, "parameter")?;
        let moments = cpu_slice(mv, mvl, "moments")?;
        let (m, v) = moments.split_at(p.len());
        let decay = 1.0 - self.lr * self.weight_decay;
        let (lr, b1, b2, eps) = (self.lr, self.bias1, self.bias2, self.eps);
        p.par_chunks_mut(CHUNK)
            .zip(m.par_chunks(CHUNK))
            .zip(v.par_chunks(CHUNK))
            .for_each(|((p, m), v)| {
                for ((p, &m), &v) in p.iter_mut().zip(m).zip(v) {
                    *p = *p * decay - lr * (m / b1) / ((v / b2).sqrt() + eps);
                }
            });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quadratic_run(device: &Device, dtype: DType, steps: usize) -> Vec<f64> {
        let x = Var::from_vec(vec![1.0f32, -2.0, 3.0, 0.5], 4, device).unwrap();
        let x = Var::from_tensor(&x.to_dtype(dtype).unwrap()).unwrap();
        let cfg = AdamConfig {
            weight_decay: 0.01,
            ..Default::default()
        };
        let mut adam = Adam::new(vec![("x".into(), x.clone())], cfg).unwrap();
        for _ in 0..steps {
            let loss = (x.as_tensor() - 0.25)
                .unwrap()
                .sqr()
                .unwrap()
                .sum_all()
                .unwrap();
            adam.step(&loss.backward().unwrap(), 0.05).unwrap();
        }
        x.to_dtype(DType::F64).unwrap().to_vec1().unwrap()
    }

    #[test]
    fn fused_and_composed_updates_agree() {
        // f32 on CPU takes the fused path, f64 the composed one.
        let fused = quadratic_run(&Device::Cpu, DType::F32, 50);
        let composed = quadratic_run(&Device::Cpu, DType::F64, 50);
        for (a, b) in fused.iter().zip(&composed) {
            assert!((a - b).abs() < 1e-4, "{fused:?} vs {composed:?}");
        }
        // And it actually optimises.
        let far = quadratic_run(&Device::Cpu, DType::F32, 400);
        assert!(far.iter().all(|v| (v - 0.25).abs() < 0.05), "{far:?}");
    }

    #[test]
    fn restored_state_continues_identically() {
        let dev = Device::Cpu;
        let run = |split: Option<usize>| {
            let x = Var::from_vec(vec![1.0f32, -2.0, 3.0], 3, &dev).unwrap();
            let mut adam = Adam::new(vec![("x".into(), x.clone())], AdamConfig::default()).unwrap();
            for i in 0..20 {
                if Some(i) == split {
                    let state: std::collections::HashMap<_, _> = adam.state().into_iter().collect();
                    let step = adam.step_count();
                    let state = state
                        .into_iter()
                        .map(|(k, t)| (k, t.copy().unwrap()))
                        .collect();
                    adam = Adam::new(vec![("x".into(), x.clone())], AdamConfig::default()).unwrap();
                    adam.load_state(&state, step).unwrap();
                }
                let loss = x.as_tensor().sqr().unwrap().sum_all().unwrap();
                adam.step(&loss.backward().unwrap(), 0.1).unwrap();
            }
            x.to_vec1::<f32>().unwrap()
        };
        assert_eq!(run(None), run(Some(7)));
    }

    #[test]
    fn schedule_warms_up_and_decays() {
        let s = LrSchedule {
            lr: 1.0,
            warmup_steps: 10,
            final_ratio: 0.1,
            total_steps: 100,
        };
        assert!(s.at(0) < 0.2 && (s.at(10) - 0.1f64.powf(0.1)).abs() < 1e-9);
        assert!((s.at(100) - 0.1).abs() < 1e-9);
    }
}
