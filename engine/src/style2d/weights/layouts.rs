//! Naming schemes of VGG state dicts: the project's layout (with its `__metadata__`),
//! torchvision's `features.N.*` and AdaIN's `vgg_normalised` (`N.*`, a 1×1 conv first).

use std::collections::HashMap;
use std::path::Path;

use super::{
    take_conv, take_vgg_conv, ChannelOrder, EncoderWeights, Preprocess, StateDict,
    TorchvisionPreprocess, WeightFormat, FORMAT_TAG,
};
use crate::style2d::arch::VggArch;
use crate::{EngineError, Result};

/// Indices of conv1_1 … conv4_1 in torchvision's `features` Sequential.
const TORCHVISION_VGG16: [usize; 8] = [0, 2, 5, 7, 10, 12, 14, 17];
const TORCHVISION_VGG19: [usize; 9] = [0, 2, 5, 7, 10, 12, 14, 16, 19];
/// Indices of conv1_1 … conv4_1 in AdaIN's `vgg` Sequential (index 0 is the 1×1 conv).
const VGG_NORMALISED: [usize; 9] = [2, 5, 9, 12, 16, 19, 22, 25, 29];

/// Interprets a state dict according to `format` (or its key names for `Auto`).
pub(super) fn from_state_dict(
    path: &Path,
    sd: &StateDict,
    meta: &HashMap<String, String>,
    format: WeightFormat,
    tv: TorchvisionPreprocess,
) -> Result<EncoderWeights> {
    let format = match format {
        WeightFormat::Auto | WeightFormat::Safetensors if sd.contains_key("conv1_1.weight") => {
            WeightFormat::Safetensors
        }
        WeightFormat::Auto if sd.contains_key("features.0.weight") => WeightFormat::TorchvisionPth,
        WeightFormat::Auto if sd.contains_key("0.weight") && sd.contains_key("2.weight") => {
            WeightFormat::VggNormalisedPth
        }
        WeightFormat::Auto => {
            let mut keys: Vec<&str> = sd.keys().map(String::as_str).collect();
            keys.sort_unstable();
            keys.truncate(6);
            return Err(EngineError::artifact(
                path,
                format!(
                    "unknown weight layout: expected tensors named like `conv1_1.weight` \
                     (this project), `features.0.weight` (torchvision) or `0.weight` (AdaIN \
                     vgg_normalised); found {keys:?}"
                ),
            ));
        }
        f => f,
    };
    match format {
        WeightFormat::Safetensors => project(path, sd, meta),
        WeightFormat::TorchvisionPth => torchvision(path, sd, tv),
        WeightFormat::VggNormalisedPth => vgg_normalised(path, sd),
        WeightFormat::Auto | WeightFormat::KerasH5 => unreachable!("resolved above"),
    }
}

fn project(path: &Path, sd: &StateDict, meta: &HashMap<String, String>) -> Result<EncoderWeights> {
    let field = |key: &str| -> Result<&str> {
        meta.get(key).map(String::as_str).ok_or_else(|| {
            EngineError::artifact(path, format!("safetensors metadata lacks `{key}`"))
        })
    };
    let bad = |key: &str, v: &str| {
        EngineError::artifact(path, format!("metadata `{key}`: bad value {v:?}"))
    };
    if field("format")? != FORMAT_TAG {
        return Err(bad("format", field("format")?));
    }
    let arch =
        VggArch::parse(field("arch")?).ok_or_else(|| bad("arch", field("arch").unwrap_or("")))?;
    let triple = |key: &str| -> Result<[f32; 3]> {
        let v = field(key)?;
        let parts: Vec<f32> = v
            .split(',')
            .map(|s| s.trim().parse::<f32>())
            .collect::<Result<_, _>>()
            .map_err(|_| bad(key, v))?;
        parts.try_into().map_err(|_| bad(key, v))
    };
    let channel_order = match field("channel_order")? {
        "rgb" => ChannelOrder::Rgb,
        "bgr" => ChannelOrder::Bgr,
        v => return Err(bad("channel_order", v)),
    };
    let scale_s = field("scale")?;
    let scale = scale_s.parse::<f32>().map_err(|_| bad("scale", scale_s))?;
    let conv = if sd.contains_key("preprocess.weight") {
        Some(take_conv(
            path,
            sd,
            "preprocess.weight",
            "preprocess.bias",
            ("preprocess", 3, 3, 1),
        )?)
    } else {
        None
    };
    // Files written before the `activations` key: a 1×1 preprocessing convolution marks
    // AdaIN's `vgg_normalised.pth`, whose activations are normalised.
    let normalised = match meta.get("activations").map(String::as_str) {
        Some("normalised") => true,
        Some("raw") => false,
        Some(v) => return Err(bad("activations", v)),
        None => conv.is_some(),
    };
    let convs = arch
        .convs()
        .iter()
        .map(|s| {
            take_vgg_conv(
                path,
                sd,
                &format!("{}.weight", s.name),
                &format!("{}.bias", s.name),
                s,
            )
        })
        .collect::<Result<_>>()?;
    Ok(EncoderWeights {
        arch,
        convs,
        preprocess: Preprocess {
            channel_order,
            scale,
            mean: triple("mean")?,
            std: triple("std")?,
            conv,
        },
        normalised,
        source: meta.get("source").cloned().unwrap_or_default(),
    })
}

fn torchvision(path: &Path, sd: &StateDict, tv: TorchvisionPreprocess) -> Result<EncoderWeights> {
    // VGG-19 has a conv at features.16; in VGG-16 index 16 is a max-pool.
    let (arch, idx): (_, &[usize]) = if sd.contains_key("features.16.weight") {
        (VggArch::Vgg19, &TORCHVISION_VGG19)
    } else {
        (VggArch::Vgg16, &TORCHVISION_VGG16)
    };
    let convs = arch
        .convs()
        .iter()
        .zip(idx)
        .map(|(s, i)| {
            take_vgg_conv(
                path,
                sd,
                &format!("features.{i}.weight"),
                &format!("features.{i}.bias"),
                s,
            )
        })
        .collect::<Result<_>>()?;
    let preprocess = match tv {
        TorchvisionPreprocess::Imagenet => Preprocess::imagenet(),
        TorchvisionPreprocess::Caffe => Preprocess::caffe(Preprocess::CAFFE_IMAGENET_MEAN),
    };
    Ok(EncoderWeights {
        arch,
        convs,
        preprocess,
        normalised: false,
        source: String::new(),
    })
}

fn vgg_normalised(path: &Path, sd: &StateDict) -> Result<EncoderWeights> {
    let pre = take_conv(
        path,
        sd,
        "0.weight",
        "0.bias",
        ("the 1×1 preprocessing conv", 3, 3, 1),
    )?;
    let arch = VggArch::Vgg19;
    let convs = arch
        .convs()
        .iter()
        .zip(VGG_NORMALISED)
        .map(|(s, i)| take_vgg_conv(path, sd, &format!("{i}.weight"), &format!("{i}.bias"), s))
        .collect::<Result<_>>()?;
    Ok(EncoderWeights {
        arch,
        convs,
        preprocess: Preprocess::conv1x1(pre),
        normalised: true,
        source: String::new(),
    })
}
