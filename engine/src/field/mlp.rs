//! Small fully connected networks (ReLU between layers, none after the last) with all
//! parameters in one flat variable.
//!
//! On CPU the whole network is one fused candle op: forward and backward call `gemm` directly
//! and fuse bias and ReLU, instead of a dozen graph nodes per layer whose gradients candle
//! accumulates with extra zero-fill and add passes (measured 5–10× slower for the field's
//! 64-wide layers on 100k samples). Both run the network on blocks of rows, one block per
//! task, so activations stay in cache from layer to layer (docs/BENCHMARKS.md, "The fused MLP
//! in blocks of rows"). Other devices, and the gradient test's reference, use the composed
//! form built from `narrow`/`matmul`/`relu`.
//!
//! Parameter layout, layer after layer: weight [in, out] row-major, then bias [out].

use candle_core::{
    CpuStorage, CustomOp2, CustomOp3, DType, Device, Layout, Shape, Tensor, Var, WithDType,
};

use rayon::prelude::*;

use crate::cpu_ops::{contiguous_slice, matmul, Threads};
use crate::rng::Rng;
use crate::Result;

pub struct Mlp {
    name: String,
    widths: Vec<usize>,
    params: Var,
}

fn param_count(widths: &[usize]) -> usize {
    widths.windows(2).map(|w| w[0] * w[1] + w[1]).sum()
}

impl Mlp {
    /// Layer widths `[in, hidden…, out]`, He-uniform initialised from `rng`, zero biases.
    pub fn new(
        name: &str,
        widths: &[usize],
        rng: &mut Rng,
        dtype: DType,
        device: &Device,
    ) -> Result<Self> {
        let mut values = Vec::with_capacity(param_count(widths));
        for w in widths.windows(2) {
            let bound = (6.0 / w[0] as f32).sqrt();
            values.extend((0..w[0] * w[1]).map(|_| (rng.uniform() * 2.0 - 1.0) * bound));
            values.extend(std::iter::repeat_n(0.0, w[1]));
        }
        let n = values.len();
        let params = Var::from_tensor(&Tensor::from_vec(values, n, device)?.to_dtype(dtype)?)?;
        Ok(Self {
            name: name.to_string(),
            widths: widths.to_vec(),
            params,
        })
    }

    /// Applies the network to `x` [N, in].
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if x.device().is_cpu() {
            Ok(x.contiguous()?.apply_op2(
                self.params.as_tensor(),
                FusedMlp {
                    widths: self.widths.clone(),
                },
            )?)
        } else {
            forward_composed(&self.widths, x, self.params.as_tensor())
        }
    }

    /// Parameters as (`<name>.params`, var).
    pub fn vars(&self) -> Vec<(String, Var)> {
        vec![(format!("{}.params", self.name), self.params.clone())]
    }
}

/// The network from candle ops (non-CPU devices; reference for the fused op).
pub fn forward_composed(widths: &[usize], x: &Tensor, params: &Tensor) -> Result<Tensor> {
    let mut h = x.clone();
    let mut offset = 0;
    let layers = widths.len() - 1;
    for (i, w) in widths.windows(2).enumerate() {
        let weight = params
            .narrow(0, offset, w[0] * w[1])?
            .reshape((w[0], w[1]))?;
        let bias = params.narrow(0, offset + w[0] * w[1], w[1])?;
        offset += w[0] * w[1] + w[1];
        h = h.matmul(&weight)?.broadcast_add(&bias)?;
        if i + 1 < layers {
            h = h.relu()?;
        }
    }
    Ok(h)
}

/// Rows per task of the fused forward and backward. Each task runs the whole network on its
/// rows with serial products, so a layer's 64-wide activations (256 KiB here) stay in the
/// core's cache for the next layer instead of streaming N rows through memory per layer.
const ROWS: usize = 1024;

/// Layer outputs after bias (and ReLU for hidden layers), input first.
fn activations<T: WithDType>(widths: &[usize], x: &[T], params: &[T]) -> Vec<Vec<T>> {
    let n = x.len() / widths[0];
    let layers = widths.len() - 1;
    let mut acts = vec![x.to_vec()];
    let mut offset = 0;
    for (i, w) in widths.windows(2).enumerate() {
        let (fan_in, fan_out) = (w[0], w[1]);
        let weight = &params[offset..offset + fan_in * fan_out];
        let bias = &params[offset + fan_in * fan_out..offset + fan_in * fan_out + fan_out];
        offset += fan_in * fan_out + fan_out;
        let mut out = vec![T::zero(); n * fan_out];
        let prev = acts.last().expect("input is present");
        matmul(
            n,
            fan_out,
            fan_in,
            (&mut out, fan_out),
            (prev, fan_in as isize, 1),
            (weight, fan_out as isize, 1),
            false,
            Threads::One,
        );
        let hidden = i + 1 < layers;
        for row in out.chunks_exact_mut(fan_out) {
            for (v, b) in row.iter_mut().zip(bias) {
                *v += *b;
                if hidden && *v < T::zero() {
                    *v = T::zero();
                }
            }
        }
        acts.push(out);
    }
    acts
}

/// The network's output [N·out]: blocks of [`ROWS`] rows in parallel.
fn forward<T: WithDType>(widths: &[usize], x: &[T], params: &[T]) -> Vec<T> {
    let (n_in, n_out) = (widths[0], widths[widths.len() - 1]);
    let mut out = vec![T::zero(); x.len() / n_in * n_out];
    out.par_chunks_mut(ROWS * n_out)
        .zip(x.par_chunks(ROWS * n_in))
        .for_each(|(out, x)| {
            if let Some(y) = activations(widths, x, params).pop() {
                out.copy_from_slice(&y);
            }
        });
    out
}

/// Gradients (input [N·in], then parameters [P]) given the output gradient: blocks of
/// [`ROWS`] rows in parallel, their parameter gradients summed in block order (so the result
/// does not depend on the number of threads).
fn backward<T: WithDType>(widths: &[usize], x: &[T], params: &[T], grad: &[T]) -> Vec<T> {
    let (n_in, n_out) = (widths[0], widths[widths.len() - 1]);
    let mut out = vec![T::zero(); x.len() + param_count(widths)];
    let (dx, dparams) = out.split_at_mut(x.len());
    let blocks: Vec<Vec<T>> = dx
        .par_chunks_mut(ROWS * n_in)
        .zip(x.par_chunks(ROWS * n_in))
        .zip(grad.par_chunks(ROWS * n_out))
        .map(|((dx, x), grad)| block_backward(widths, x, params, grad, dx))
        .collect();
    for block in blocks {
        for (d, v) in dparams.iter_mut().zip(block) {
            *d += v;
        }
    }
    out
}

/// One block of rows: writes ∂L/∂x into `dx` and returns the block's ∂L/∂params.
fn block_backward<T: WithDType>(
    widths: &[usize],
    x: &[T],
    params: &[T],
    grad: &[T],
    dx: &mut [T],
) -> Vec<T> {
    let n = x.len() / widths[0];
    let acts = activations(widths, x, params);
    let mut dparams = vec![T::zero(); param_count(widths)];
    let mut g = grad.to_vec();
    let mut offset = dparams.len();
    for l in (0..widths.len() - 1).rev() {
        let (fan_in, fan_out) = (widths[l], widths[l + 1]);
        offset -= fan_in * fan_out + fan_out;
        let (dw, db) =
            dparams[offset..offset + fan_in * fan_out + fan_out].split_at_mut(fan_in * fan_out);
        let h = &acts[l];
        // dW = hᵀ g: h viewed transposed has row stride 1 and column stride fan_in.
        matmul(
            fan_in,
            fan_out,
            n,
            (dw, fan_out),
            (h, 1, fan_in as isize),
            (&g, fan_out as isize, 1),
            false,
            Threads::One,
        );
        for row in g.chunks_exact(fan_out) {
            for (d, v) in db.iter_mut().zip(row) {
                *d += *v;
            }
        }
        // g ← (g Wᵀ) ⊙ [h > 0] (the input layer has no ReLU).
        let weight = &params[offset..offset + fan_in * fan_out];
        let mut next = vec![T::zero(); if l == 0 { 0 } else { n * fan_in }];
        matmul(
            n,
            fan_in,
            fan_out,
            (if l == 0 { &mut *dx } else { &mut next }, fan_in),
            (&g, fan_out as isize, 1),
            (weight, 1, fan_out as isize),
            false,
            Threads::One,
        );
        for (v, a) in next.iter_mut().zip(h) {
            if *a <= T::zero() {
                *v = T::zero();
            }
        }
        g = next;
    }
    dparams
}

/// Fused forward: x [N, in] × params [P] → y [N, out].
struct FusedMlp {
    widths: Vec<usize>,
}

impl CustomOp2 for FusedMlp {
    fn name(&self) -> &'static str {
        "fused-mlp"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let w = &self.widths;
        if l1.dims().len() != 2 || l1.dims()[1] != w[0] || l2.shape().elem_count() != param_count(w)
        {
            candle_core::bail!(
                "mlp: input {:?} or parameters {:?} do not match widths {w:?}",
                l1.dims(),
                l2.dims()
            );
        }
        let n = l1.dims()[0];
        let out = match (s1, s2) {
            (CpuStorage::F32(x), CpuStorage::F32(p)) => CpuStorage::F32(forward(
                w,
                contiguous_slice(x, l1, "mlp: input")?,
                contiguous_slice(p, l2, "mlp: params")?,
            )),
            (CpuStorage::F64(x), CpuStorage::F64(p)) => CpuStorage::F64(forward(
                w,
                contiguous_slice(x, l1, "mlp: input")?,
                contiguous_slice(p, l2, "mlp: params")?,
            )),
            _ => candle_core::bail!("mlp: input and parameters must both be f32 or f64"),
        };
        Ok((out, Shape::from((n, *w.last().unwrap_or(&0)))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        params: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let joint = x.apply_op3_no_bwd(
            params,
            &grad.contiguous()?,
            &FusedMlpBackward {
                widths: self.widths.clone(),
            },
        )?;
        let nx = x.elem_count();
        Ok((
            Some(joint.narrow(0, 0, nx)?.reshape(x.shape())?),
            Some(joint.narrow(0, nx, params.elem_count())?),
        ))
    }
}

/// (x, params, output gradient) → [N·in + P] = (∂L/∂x, ∂L/∂params).
struct FusedMlpBackward {
    widths: Vec<usize>,
}

impl CustomOp3 for FusedMlpBackward {
    fn name(&self) -> &'static str {
        "fused-mlp-backward"
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
        let w = &self.widths;
        let out = match (s1, s2, s3) {
            (CpuStorage::F32(x), CpuStorage::F32(p), CpuStorage::F32(g)) => {
                CpuStorage::F32(backward(
                    w,
                    contiguous_slice(x, l1, "mlp: input")?,
                    contiguous_slice(p, l2, "mlp: params")?,
                    contiguous_slice(g, l3, "mlp: grad")?,
                ))
            }
            (CpuStorage::F64(x), CpuStorage::F64(p), CpuStorage::F64(g)) => {
                CpuStorage::F64(backward(
                    w,
                    contiguous_slice(x, l1, "mlp: input")?,
                    contiguous_slice(p, l2, "mlp: params")?,
                    contiguous_slice(g, l3, "mlp: grad")?,
                ))
            }
            _ => candle_core::bail!("mlp backward: mixed dtypes"),
        };
        let len = l1.shape().elem_count() + param_count(w);
        Ok((out, Shape::from(len)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fused_matches_composed_and_finite_differences() {
        let dev = Device::Cpu;
        let widths = [5, 8, 7, 3];
        let mlp = Mlp::new("t", &widths, &mut Rng::new(3), DType::F64, &dev).unwrap();
        // Non-zero biases so every path is exercised.
        let p: Vec<f64> = mlp.params.to_vec1().unwrap();
        let p: Vec<f64> = p
            .iter()
            .enumerate()
            .map(|(i, v)| v + 0.05 * ((i % 7) as f64 - 3.0))
            .collect();
        mlp.params
            .set(&Tensor::new(p.as_slice(), &dev).unwrap())
            .unwrap();
        let x = Var::randn(0f64, 1.0, (11, 5), &dev).unwrap();
        let proj = Tensor::randn(0f64, 1.0, (11, 3), &dev).unwrap();
        let loss = |x: &Tensor, params: &Tensor, fused: bool| -> Tensor {
            let y = if fused {
                x.apply_op2(
                    params,
                    FusedMlp {
                        widths: widths.to_vec(),
                    },
                )
                .unwrap()
            } else {
                forward_composed(&widths, x, params).unwrap()
            };
            (y.sqr().unwrap() * &proj).unwrap().sum_all().unwrap()
        };
        let lf = loss(&x, &mlp.params, true);
        let lc = loss(&x, &mlp.params, false);
        assert!((lf.to_scalar::<f64>().unwrap() - lc.to_scalar::<f64>().unwrap()).abs() < 1e-10);
        let (gf, gc) = (lf.backward().unwrap(), lc.backward().unwrap());
        for v in [x.as_tensor(), mlp.params.as_tensor()] {
            let d = (gf.get(v).unwrap() - gc.get(v).unwrap())
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap();
            assert!(d.to_scalar::<f64>().unwrap() < 1e-10);
        }
        let analytic: Vec<f64> = gf.get(&mlp.params).unwrap().to_vec1().unwrap();
        for i in (0..p.len()).step_by(3) {
            let eval = |d: f64| {
                let mut q = p.clone();
                q[i] += d;
                loss(&x, &Tensor::new(q.as_slice(), &dev).unwrap(), true)
                    .to_scalar::<f64>()
                    .unwrap()
            };
            let numeric = (eval(1e-6) - eval(-1e-6)) / 2e-6;
            assert!(
                (numeric - analytic[i]).abs() < 1e-5 * (1.0 + numeric.abs()),
                "param {i}: {numeric} vs {}",
                analytic[i]
            );
        }
    }

    /// Enough rows for several blocks and a partial last one: the fused op's output and both
    /// gradients equal the composed network's.
    #[test]
    fn fused_blocks_match_composed() {
        use crate::style2d::gradcheck::max_abs;
        let dev = Device::Cpu;
        let widths = [6, 16, 16, 4];
        let mlp = Mlp::new("t", &widths, &mut Rng::new(5), DType::F64, &dev).unwrap();
        let x = Var::randn(0f64, 1.0, (2 * ROWS + 37, 6), &dev).unwrap();
        let proj = Tensor::randn(0f64, 1.0, (2 * ROWS + 37, 4), &dev).unwrap();
        let fused = mlp.forward(&x).unwrap();
        let composed = forward_composed(&widths, &x, mlp.params.as_tensor()).unwrap();
        let max_diff = |a: &Tensor, b: &Tensor| max_abs(&(a - b).unwrap());
        assert!(max_diff(&fused, &composed) < 1e-12);
        let [gf, gc] = [fused, composed].map(|y| {
            (y.sqr().unwrap() * &proj)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap()
        });
        for v in [x.as_tensor(), mlp.params.as_tensor()] {
            let (a, b) = (gf.get(v).unwrap(), gc.get(v).unwrap());
            assert!(max_diff(a, b) < 1e-9 * (1.0 + max_abs(b)));
        }
    }
}
