//! The frozen VGG encoder up to relu4_1: reflection padding, 3×3 convolutions with frozen
//! weights (input gradient only), ReLU and 2×2 max-pools, exposing relu1_1, relu2_1, relu3_1
//! and relu4_1. The source's preprocessing is folded into conv1_1, so the encoder takes RGB
//! in [0, 1] whatever the weights came from.
//!
//! Activation scale: a plain VGG's activations grow with depth (the Caffe VGG-16's relu4_1
//! averages in the hundreds), which makes the decoder's input and the style loss's layers
//! wildly different in scale, and a decoder trained from scratch on them learns noise. As in
//! Gatys et al.'s and AdaIN's `vgg_normalised`, each layer is rescaled so its mean activation
//! over a fixed set of calibration images is 1. ReLU and max-pooling commute with positive
//! scaling, so folding the scales into the weights and biases changes each feature map by a
//! constant factor and nothing else. Weights that are already normalised (AdaIN's
//! `vgg_normalised.pth`, whose decoder expects its exact scale) are left as they are.

use candle_core::{Device, Result, Tensor};

use super::arch::VggArch;
use super::conv::conv2d;
use super::images;
use super::pad::reflection_pad2d;
use super::painted;
use super::resample::max_pool2x2;
use super::weights::{ChannelOrder, ConvWeights, EncoderWeights, Preprocess};

/// The four exposed feature maps, shallow to deep: relu1_1, relu2_1, relu3_1, relu4_1.
pub type Features = [Tensor; 4];

/// How the convolutions run. `Candle` is candle's own conv2d, which also computes (and
/// discards) kernel gradients; it exists to measure what [`conv2d`] saves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvPath {
    Engine,
    Candle,
}

#[derive(Debug, Clone)]
struct Layer {
    /// `[out, in, 3, 3]`, a plain tensor: no gradient is computed for it.
    weight: Tensor,
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
        Self::build(weights, !weights.normalised, device)
    }

    fn build(weights: &EncoderWeights, normalise: bool, device: &Device) -> Result<Self> {
        let first = weights
            .folded_first_conv()
            .map_err(candle_core::Error::wrap)?;
        let mut convs: Vec<(Tensor, Tensor)> = std::iter::once(&first)
            .chain(&weights.convs[1..])
            .map(|w| (w.weight.clone(), w.bias.clone()))
            .collect();
        if normalise {
            normalise_activations(weights.arch, &mut convs, &calibration_images()?)?;
        }
        let layers = weights
            .arch
            .convs()
            .iter()
            .zip(convs)
            .map(|(spec, (w, b))| {
                Ok(Layer {
                    weight: w.to_device(device)?.contiguous()?,
                    bias: b.to_device(device)?.reshape((1, spec.c_out, 1, 1))?,
                    pool_before: spec.pool_before,
                    tap: spec.tap,
                })
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            arch: weights.arch,
            layers,
            path: ConvPath::Engine,
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

    /// The weights exactly as this encoder runs them: the source's preprocessing folded into
    /// conv1_1 (the input is RGB in [0, 1]) and the activations normalised. Saved and loaded
    /// again they give the same encoder; tools outside the engine (the GPU decoder trainer in
    /// `scripts/`) read this file to see the features the engine sees.
    pub fn weights(&self) -> Result<EncoderWeights> {
        let convs = self
            .layers
            .iter()
            .map(|l| {
                Ok(ConvWeights {
                    weight: l.weight.to_device(&Device::Cpu)?,
                    bias: l.bias.flatten_all()?.to_device(&Device::Cpu)?,
                })
            })
            .collect::<Result<_>>()?;
        Ok(EncoderWeights {
            arch: self.arch,
            convs,
            preprocess: Preprocess {
                channel_order: ChannelOrder::Rgb,
                scale: 1.0,
                mean: [0.0; 3],
                std: [1.0; 3],
                conv: None,
            },
            normalised: true,
            source: self.source.clone(),
        })
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
                ConvPath::Engine => conv2d(&padded, &layer.weight)?,
                ConvPath::Candle => padded.conv2d(&layer.weight, 0, 1, 1, 1)?,
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

/// Side of the calibration images.
const CALIBRATION_SIZE: u32 = 64;

/// The calibration set of [`normalise_activations`]: the painted styles (busy textures) and a
/// smooth colour gradient (like a plain content image), `[N, 3, 64, 64]` on the CPU.
fn calibration_images() -> Result<Tensor> {
    let n = CALIBRATION_SIZE;
    let mut imgs: Vec<Tensor> = painted::NAMES
        .iter()
        .map(|name| {
            let img = painted::paint(name, n).expect("bundled style");
            images::hwc_to_tensor(img.as_raw(), n as usize, n as usize, &Device::Cpu)
                .map_err(candle_core::Error::wrap)
        })
        .collect::<Result<_>>()?;
    let gradient: Vec<f32> = (0..n * n)
        .flat_map(|k| {
            let (u, v) = ((k % n) as f32 / n as f32, (k / n) as f32 / n as f32);
            [0.2 + 0.6 * u, 0.3 + 0.4 * v, 0.8 - 0.5 * u * v]
        })
        .collect();
    imgs.push(
        images::hwc_to_tensor(&gradient, n as usize, n as usize, &Device::Cpu)
            .map_err(candle_core::Error::wrap)?,
    );
    Tensor::cat(&imgs, 0)
}

/// Rescales each `(weight, bias)` so that its layer's mean activation over `calib` is 1,
/// compensating for the previous layer's scale (see the module docs).
fn normalise_activations(
    arch: VggArch,
    convs: &mut [(Tensor, Tensor)],
    calib: &Tensor,
) -> Result<()> {
    let mut h = calib.clone();
    let mut prev_scale = 1.0f64;
    for (spec, (w, b)) in arch.convs().iter().zip(convs.iter_mut()) {
        if spec.pool_before {
            h = max_pool2x2(&h)?;
        }
        // The input is the previous layer's original activation divided by `prev_scale`.
        let w_in = (&*w * prev_scale)?;
        let a = reflection_pad2d(&h, 1)?
            .conv2d(&w_in, 0, 1, 1, 1)?
            .broadcast_add(&b.reshape((1, spec.c_out, 1, 1))?)?
            .relu()?;
        let scale = f64::from(a.mean_all()?.to_scalar::<f32>()?).max(1e-6);
        *w = (w_in / scale)?;
        *b = (&*b / scale)?;
        h = (a / scale)?;
        prev_scale = scale;
    }
    Ok(())
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
            normalised: false,
            source: "test".into(),
        }
    }

    #[test]
    fn preprocessing_is_folded_exactly() {
        let w = random_weights(VggArch::Vgg16, Preprocess::caffe([104.0, 117.0, 123.0]));
        let enc = VggEncoder::build(&w, false, &Device::Cpu).unwrap();
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
        let err = crate::style2d::gradcheck::max_abs(&(explicit - folded).unwrap());
        assert!(err < 2e-3, "folded conv1_1 differs by {err}");
    }

    #[test]
    fn normalisation_scales_each_feature_to_unit_mean() {
        let w = random_weights(VggArch::Vgg16, Preprocess::caffe([104.0, 117.0, 123.0]));
        let raw = VggEncoder::build(&w, false, &Device::Cpu).unwrap();
        let norm = VggEncoder::new(&w, &Device::Cpu).unwrap();
        let calib = calibration_images().unwrap();
        let x = ((crate::style2d::gradcheck::random(&[1, 3, 32, 32], 4) + 1.0).unwrap() * 0.5)
            .unwrap()
            .to_dtype(candle_core::DType::F32)
            .unwrap();
        let mean = |t: &Tensor| t.mean_all().unwrap().to_scalar::<f32>().unwrap();
        let (fr, fnorm) = (raw.features(&x).unwrap(), norm.features(&x).unwrap());
        for (k, f) in norm.features(&calib).unwrap().iter().enumerate() {
            assert!((mean(f) - 1.0).abs() < 1e-3, "tap {k}: mean {}", mean(f));
            // On another image the normalised feature is the raw one times a constant.
            let ratio = mean(&fnorm[k]) / mean(&fr[k]);
            let err = crate::style2d::gradcheck::max_abs(
                &((&fr[k] * f64::from(ratio)).unwrap() - &fnorm[k]).unwrap(),
            );
            assert!(
                err < 1e-3 * mean(&fnorm[k]).max(1.0) * 10.0,
                "tap {k}: {err}"
            );
        }
    }

    #[test]
    fn exported_weights_rebuild_the_same_encoder() {
        let w = random_weights(VggArch::Vgg16, Preprocess::caffe([104.0, 117.0, 123.0]));
        let enc = VggEncoder::new(&w, &Device::Cpu).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("effective.safetensors");
        enc.weights()
            .unwrap()
            .save(&p, candle_core::DType::F32)
            .unwrap();
        let back = crate::style2d::weights::import(
            &p,
            crate::style2d::weights::WeightFormat::Auto,
            Default::default(),
        )
        .unwrap();
        assert!(back.normalised);
        assert_eq!(back.source, "test");
        // A file whose `activations` says something else is refused, naming the key.
        let mut bytes = std::fs::read(&p).unwrap();
        let at = bytes.windows(10).position(|w| w == b"normalised").unwrap();
        bytes[at..at + 10].copy_from_slice(b"normalized");
        std::fs::write(&p, bytes).unwrap();
        let err = crate::style2d::weights::import(
            &p,
            crate::style2d::weights::WeightFormat::Auto,
            Default::default(),
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("`activations`") && err.contains("normalized"),
            "{err}"
        );
        let again = VggEncoder::new(&back, &Device::Cpu).unwrap();
        let x = ((crate::style2d::gradcheck::random(&[1, 3, 16, 16], 11) + 1.0).unwrap() * 0.5)
            .unwrap()
            .to_dtype(candle_core::DType::F32)
            .unwrap();
        let max_abs = crate::style2d::gradcheck::max_abs;
        for (a, b) in enc
            .features(&x)
            .unwrap()
            .iter()
            .zip(again.features(&x).unwrap())
        {
            assert!(max_abs(&(a - b).unwrap()) <= 1e-5 * max_abs(a).max(1.0));
        }
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
            .with_conv_path(ConvPath::Candle)
            .relu4_1(&x)
            .unwrap();
        let err = crate::style2d::gradcheck::max_abs(&(&f[3] - plain).unwrap());
        assert!(err < 1e-4);
        assert!(enc.features(&x.narrow(2, 0, 12).unwrap()).is_err());
    }

    #[test]
    fn encoder_block_gradient_matches_finite_differences() {
        // pad → frozen conv → bias → relu → pool → pad → conv, composed as in the encoder.
        let w1 = crate::style2d::gradcheck::random(&[3, 2, 3, 3], 7);
        let w2 = crate::style2d::gradcheck::random(&[2, 3, 3, 3], 8);
        let b = crate::style2d::gradcheck::random(&[1, 3, 1, 1], 9);
        crate::style2d::gradcheck::check(
            &crate::style2d::gradcheck::random(&[1, 2, 6, 4], 10),
            |x| {
                let h = conv2d(&reflection_pad2d(x, 1)?, &w1)?
                    .broadcast_add(&b)?
                    .relu()?;
                conv2d(&reflection_pad2d(&max_pool2x2(&h)?, 1)?, &w2)
            },
        );
    }
}
