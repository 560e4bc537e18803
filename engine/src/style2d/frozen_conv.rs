//! A 3×3 convolution with fixed weights whose backward pass computes only the gradient of its
//! input. candle's conv2d backward always also computes the kernel gradient — as expensive as
//! the input gradient — even for constant weights; the frozen VGG encoder does not need it.
//!
//! The forward is candle's conv2d (im2col + gemm). The input gradient is the full correlation
//! of the output gradient with the spatially flipped, in/out-transposed kernel: a conv2d with
//! padding k − 1, which candle runs faster than `conv_transpose2d`.

use candle_core::{CpuStorage, CustomOp1, DType, Device, Layout, Result, Shape, Tensor};

/// Convolution weights prepared for [`FrozenConv::forward`]: unpadded ("valid"), stride 1.
#[derive(Debug, Clone)]
pub struct FrozenConv {
    /// `[out, in, k, k]`.
    weight: Tensor,
    /// `weight` flipped in both spatial axes, with in and out swapped: `[in, out, k, k]`.
    weight_t: Tensor,
}

impl FrozenConv {
    pub fn new(weight: Tensor) -> Result<Self> {
        let (_, _, kh, kw) = weight.dims4()?;
        let dev = weight.device();
        let rev = |n: usize| Tensor::new((0..n as u32).rev().collect::<Vec<_>>(), dev);
        let weight_t = weight
            .transpose(0, 1)?
            .contiguous()?
            .index_select(&rev(kh)?, 2)?
            .index_select(&rev(kw)?, 3)?
            .contiguous()?;
        Ok(Self {
            weight: weight.contiguous()?,
            weight_t,
        })
    }

    pub fn weight(&self) -> &Tensor {
        &self.weight
    }

    /// Valid convolution of NCHW `x`. Gradients flow to `x` only. Off the CPU it falls back
    /// to candle's conv2d (correct, but it also pays for the unused kernel gradient).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if x.device().is_cpu() {
            x.contiguous()?.apply_op1(self.clone())
        } else {
            x.conv2d(&self.weight, 0, 1, 1, 1)
        }
    }
}

impl CustomOp1 for FrozenConv {
    fn name(&self) -> &'static str {
        "frozen-conv2d"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let Some((start, end)) = layout.contiguous_offsets() else {
            candle_core::bail!("frozen-conv2d: input must be contiguous");
        };
        let shape = layout.shape().clone();
        let x = match storage {
            CpuStorage::F32(v) => Tensor::from_slice(&v[start..end], shape, &Device::Cpu)?,
            CpuStorage::F64(v) => Tensor::from_slice(&v[start..end], shape, &Device::Cpu)?,
            _ => candle_core::bail!("frozen-conv2d: only f32 and f64 are supported"),
        };
        let y = x.conv2d(&self.weight.to_dtype(x.dtype())?, 0, 1, 1, 1)?;
        let out_shape = y.shape().clone();
        let out = match y.dtype() {
            DType::F32 => CpuStorage::F32(y.flatten_all()?.to_vec1()?),
            _ => CpuStorage::F64(y.flatten_all()?.to_vec1()?),
        };
        Ok((out, out_shape))
    }

    fn bwd(&self, _arg: &Tensor, _res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let k = self.weight.dim(2)?;
        let w = self.weight_t.to_dtype(grad_res.dtype())?;
        Ok(Some(grad_res.contiguous()?.conv2d(&w, k - 1, 1, 1, 1)?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::style2d::gradcheck;

    #[test]
    fn forward_matches_conv2d() {
        let w = gradcheck::random(&[4, 3, 3, 3], 10);
        let x = gradcheck::random(&[2, 3, 6, 5], 11);
        let a = FrozenConv::new(w.clone()).unwrap().forward(&x).unwrap();
        let b = x.conv2d(&w, 0, 1, 1, 1).unwrap();
        let d = (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f64>()
            .unwrap();
        assert!(d < 1e-12);
    }

    #[test]
    fn input_gradient_matches_finite_differences() {
        let conv = FrozenConv::new(gradcheck::random(&[4, 3, 3, 3], 12)).unwrap();
        gradcheck::check(&gradcheck::random(&[2, 3, 5, 6], 13), |x| conv.forward(x));
        let conv1 = FrozenConv::new(gradcheck::random(&[2, 3, 1, 1], 14)).unwrap();
        gradcheck::check(&gradcheck::random(&[1, 3, 3, 3], 15), |x| conv1.forward(x));
    }
}
