//! The frozen VGG encoder up to relu4_1: reflection padding, 3×3 convolutions with frozen
//! weights (input gradient only), ReLU and 2×2 max-pools, exposing relu1_1, relu2_1, relu3_1
//! and relu4_1. The source's preprocessing is folded into conv1_1, so the encoder takes RGB
//! in [0, 1] whatever the weights came from.

use candle_core::{Device, Result, Tensor};

use super::arch::VggArch;
use super::frozen_conv::FrozenConv;
use super::pad::reflection_pad2d;
use super::resample::max_pool2x2;
use super::weights::EncoderWeights;

/// The four exposed feature maps, shallow to deep: relu1_1, relu2_1, relu3_1, relu4_1.
pub type Features = [Tensor; 4];

/// How the convolutions run. `Plain` is candle's conv2d, which also computes (and discards)
/// kernel gradients; it exists to measure what [`FrozenConv`] saves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvPath {
    Frozen,
    Plain,
}

#[derive(Debug, Clone)]
struct Layer {
    conv: FrozenConv,
    /// `[1, out, 1, 1]`.
    bias: Tensor,
    pool_before: bool,
    tap: bool,
}

/// A VGG encoder with frozen weights.
#[derive(Debug, Clone)]
pub struct VggEncoder {
    arch: VggArch,
    layers: Vec<Layer>,
    path: ConvPath,
    source: String,
}

impl VggEncoder {
    pub fn new(weights: &EncoderWeights, device: &Device) -> Result<Self> {
        let first = weights
            .folded_first_conv()
            .map_err(candle_core::Error::wrap)?;
        let layers = weights
            .arch
            .convs()
            .iter()
            .zip(&weights.convs)
            .enumerate()
            .map(|(i, (spec, w))| {
                let w = if i == 0 { &first } else { w };
                Ok(Layer {
                    conv: FrozenConv::new(w.weight.to_device(device)?)?,
                    bias: w.bias.to_device(device)?.reshape((1, spec.c_out, 1, 1))?,
                    pool_before: spec.pool_before,
                    tap: spec.tap,
                })
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            arch: weights.arch,
            layers,
            path: ConvPath::Frozen,
            source: weights.source.clone(),
        })
    }

    /// The same encoder running its convolutions through `path`.
    pub fn with_conv_path(mut self, path: ConvPath) -> Self {
        self.path = path;
        self
    }

    pub fn arch(&self) -> VggArch {
        self.arch
    }

    /// Where the weights came from.
    pub fn source(&self) -> &str {
        &self.source
    }

    /// Features of `x` (NCHW RGB in [0, 1]; H and W multiples of [`VggArch::STRIDE`]).
    pub fn features(&self, x: &Tensor) -> Result<Features> {
        let taps = self.run(x, 4)?;
        Ok(taps.try_into().expect("four taps"))
    }

    /// relu4_1 only.
    pub fn relu4_1(&self, x: &Tensor) -> Result<Tensor> {
        Ok(self.run(x, 4)?.pop().expect("four taps"))
    }

    /// Runs until `n_taps` features have been produced; returns them.
    fn run(&self, x: &Tensor, n_taps: usize) -> Result<Vec<Tensor>> {
        let (_, c, h, w) = x.dims4()?;
        let s = VggArch::STRIDE;
        if c != 3 || h % s != 0 || w % s != 0 {
            candle_core::bail!(
                "encoder input must be [B, 3, H, W] with H, W multiples of {s}, got {:?}",
                x.dims()
            );
        }
        let mut taps = Vec::with_capacity(n_taps);
        let mut h = x.clone();
        for layer in &self.layers {
            if layer.pool_before {
                h = max_pool2x2(&h)?;
            }
            let padded = reflection_pad2d(&h, 1)?;
            let y = match self.path {
                ConvPath::Frozen => layer.conv.forward(&padded)?,
                ConvPath::Plain => padded.conv2d(layer.conv.weight(), 0, 1, 1, 1)?,
            };
            h = y.broadcast_add(&layer.bias)?.relu()?;
            if layer.tap {
                taps.push(h.clone());
                if taps.len() == n_taps {
                    break;
                }
            }
        }
        Ok(taps)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::style2d::weights::{ConvWeights, Preprocess};

    /// Small random weights for `arch`, in f64, with the given preprocessing.
    fn random_weights(arch: VggArch, preprocess: Preprocess) -> EncoderWeights {
        let convs = arch
            .convs()
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let scale = (2.0 / (9.0 * s.c_in as f64)).sqrt();
                ConvWeights {
                    weight: (crate::style2d::gradcheck::random(
                        &[s.c_out, s.c_in, 3, 3],
                        100 + i as u64,
                    ) * scale)
                        .unwrap()
                        .to_dtype(candle_core::DType::F32)
                        .unwrap(),
                    bias: (crate::style2d::gradcheck::random(&[s.c_out], 200 + i as u64) * 0.01)
                        .unwrap()
                        .to_dtype(candle_core::DType::F32)
                        .unwrap(),
                }
            })
            .collect();
        EncoderWeights {
            arch,
            convs,
            preprocess,
            source: "test".into(),
        }
    }

    #[test]
    fn preprocessing_is_folded_exactly() {
        let w = random_weights(VggArch::Vgg16, Preprocess::caffe([104.0, 117.0, 123.0]));
        let enc = VggEncoder::new(&w, &Device::Cpu).unwrap();
        let x = ((crate::style2d::gradcheck::random(&[1, 3, 16, 16], 5) + 1.0).unwrap() * 0.5)
            .unwrap()
            .to_dtype(candle_core::DType::F32)
            .unwrap();
        // Explicit: RGB → BGR, ×255, − mean, then the unfolded conv1_1.
        let bgr = x
            .index_select(&Tensor::new(&[2u32, 1, 0], &Device::Cpu).unwrap(), 1)
            .unwrap();
        let mean = Tensor::new(&[104f32, 117., 123.], &Device::Cpu)
            .unwrap()
            .reshape((1, 3, 1, 1))
            .unwrap();
        let pre = (bgr * 255.0).unwrap().broadcast_sub(&mean).unwrap();
        let c = &w.convs[0];
        let explicit = reflection_pad2d(&pre, 1)
            .unwrap()
            .conv2d(&c.weight, 0, 1, 1, 1)
            .unwrap()
            .broadcast_add(&c.bias.reshape((1, 64, 1, 1)).unwrap())
            .unwrap()
            .relu()
            .unwrap();
        let folded = enc.features(&x).unwrap()[0].clone();
        let err = (explicit - folded)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(err < 2e-3, "folded conv1_1 differs by {err}");
    }

    #[test]
    fn feature_shapes_and_paths_agree() {
        let w = random_weights(VggArch::Vgg19, Preprocess::imagenet());
        let enc = VggEncoder::new(&w, &Device::Cpu).unwrap();
        let x = crate::style2d::gradcheck::random(&[2, 3, 16, 24], 6)
            .to_dtype(candle_core::DType::F32)
            .unwrap();
        let f = enc.features(&x).unwrap();
        let dims: Vec<_> = f.iter().map(|t| t.dims().to_vec()).collect();
        assert_eq!(
            dims,
            vec![
                vec![2, 64, 16, 24],
                vec![2, 128, 8, 12],
                vec![2, 256, 4, 6],
                vec![2, 512, 2, 3]
            ]
        );
        let plain = enc
            .clone()
            .with_conv_path(ConvPath::Plain)
            .relu4_1(&x)
            .unwrap();
        let err = (&f[3] - plain)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(err < 1e-4);
        assert!(enc.features(&x.narrow(2, 0, 12).unwrap()).is_err());
    }

    #[test]
    fn encoder_block_gradient_matches_finite_differences() {
        // pad → frozen conv → bias → relu → pool → pad → conv, composed as in the encoder.
        let w1 = FrozenConv::new(crate::style2d::gradcheck::random(&[3, 2, 3, 3], 7)).unwrap();
        let w2 = FrozenConv::new(crate::style2d::gradcheck::random(&[2, 3, 3, 3], 8)).unwrap();
        let b = crate::style2d::gradcheck::random(&[1, 3, 1, 1], 9);
        crate::style2d::gradcheck::check(
            &crate::style2d::gradcheck::random(&[1, 2, 6, 4], 10),
            |x| {
                let h = w1
                    .forward(&reflection_pad2d(x, 1)?)?
                    .broadcast_add(&b)?
                    .relu()?;
                w2.forward(&reflection_pad2d(&max_pool2x2(&h)?, 1)?)
            },
        );
    }
}
