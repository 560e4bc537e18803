//! `stylenerf weights …`: convert pretrained VGG encoder weights (Keras `.h5`, AdaIN's
//! `vgg_normalised.pth`, torchvision state dicts) into the project's safetensors layout.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Subcommand, ValueEnum};
use stylenerf_engine::style2d::encoder::VggEncoder;
use stylenerf_engine::style2d::weights::{
    self, EncoderWeights, TorchvisionPreprocess, WeightFormat,
};

#[derive(Debug, Subcommand)]
pub enum WeightsCommand {
    /// Convert encoder weights into the project's safetensors layout (docs/STYLE2D.md).
    Import {
        /// The source file: Keras .h5, PyTorch .pth (zip format) or safetensors.
        #[arg(long)]
        from: PathBuf,
        /// Where to write the safetensors file.
        #[arg(long)]
        out: PathBuf,
        #[arg(long, value_enum, default_value_t = FormatArg::Auto)]
        format: FormatArg,
        /// Precision of the stored weights.
        #[arg(long, value_enum, default_value_t = DtypeArg::F16)]
        dtype: DtypeArg,
        /// Preprocessing of torchvision-layout weights (the file does not record it):
        /// `imagenet` for torchvision's own models, `caffe` for Caffe conversions (BGR, 0–255).
        #[arg(long, value_enum, default_value_t = PreprocessArg::Imagenet)]
        preprocess: PreprocessArg,
    },
    /// Print what an encoder weight file holds (the bundled one when no file is given).
    Info { file: Option<PathBuf> },
    /// Write the encoder exactly as the engine runs it: input RGB in [0, 1] (the source's
    /// preprocessing folded into conv1_1) and each layer's activations normalised. Tools
    /// outside the engine (scripts/train_decoder_gpu.py) read it to see the same features.
    Export {
        /// The encoder to export (default: the bundled one).
        #[arg(long)]
        encoder: Option<PathBuf>,
        #[arg(long)]
        out: PathBuf,
        #[arg(long, value_enum, default_value_t = DtypeArg::F32)]
        dtype: DtypeArg,
    },
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum FormatArg {
    Auto,
    KerasH5,
    VggNormalisedPth,
    TorchvisionPth,
    Safetensors,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum DtypeArg {
    F16,
    F32,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum PreprocessArg {
    Imagenet,
    Caffe,
}

pub fn run(cmd: WeightsCommand) -> anyhow::Result<()> {
    match cmd {
        WeightsCommand::Import {
            from,
            out,
            format,
            dtype,
            preprocess,
        } => {
            let format = match format {
                FormatArg::Auto => WeightFormat::Auto,
                FormatArg::KerasH5 => WeightFormat::KerasH5,
                FormatArg::VggNormalisedPth => WeightFormat::VggNormalisedPth,
                FormatArg::TorchvisionPth => WeightFormat::TorchvisionPth,
                FormatArg::Safetensors => WeightFormat::Safetensors,
            };
            let tv = match preprocess {
                PreprocessArg::Imagenet => TorchvisionPreprocess::Imagenet,
                PreprocessArg::Caffe => TorchvisionPreprocess::Caffe,
            };
            save(&weights::import(&from, format, tv)?, &out, dtype)
        }
        WeightsCommand::Info { file } => {
            print_summary(&EncoderWeights::load_or_bundled(file.as_deref())?);
            Ok(())
        }
        WeightsCommand::Export {
            encoder,
            out,
            dtype,
        } => {
            let w = EncoderWeights::load_or_bundled(encoder.as_deref())?;
            let enc = VggEncoder::new(&w, &candle_core::Device::Cpu)?;
            save(&enc.weights()?, &out, dtype)
        }
    }
}

fn save(w: &EncoderWeights, out: &std::path::Path, dtype: DtypeArg) -> anyhow::Result<()> {
    let dtype = match dtype {
        DtypeArg::F16 => candle_core::DType::F16,
        DtypeArg::F32 => candle_core::DType::F32,
    };
    w.save(out, dtype)?;
    let bytes = std::fs::read(out).with_context(|| out.display().to_string())?;
    print_summary(w);
    println!(
        "wrote {} ({} bytes, sha256 {})",
        out.display(),
        bytes.len(),
        weights::sha256_hex(&bytes)
    );
    Ok(())
}

fn print_summary(w: &EncoderWeights) {
    let p = &w.preprocess;
    println!("arch:          {}", w.arch.name());
    println!("source:        {}", w.source);
    println!(
        "preprocessing: {:?}, ×{}, mean {:?}, std {:?}{}",
        p.channel_order,
        p.scale,
        p.mean,
        p.std,
        if p.conv.is_some() {
            ", then a 1×1 conv"
        } else {
            ""
        }
    );
    println!(
        "activations:   {}",
        if w.normalised {
            "normalised (used as they are)"
        } else {
            "raw (normalised by the encoder when it loads)"
        }
    );
    for (spec, conv) in w.arch.convs().iter().zip(&w.convs) {
        println!("  {:8} {:?}", spec.name, conv.weight.dims());
    }
}
