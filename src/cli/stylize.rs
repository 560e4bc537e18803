//! `stylenerf stylize image`: AdaIN style transfer of one image, a standalone use of the 2D
//! network and a visible check of it.

use std::path::PathBuf;
use std::time::Instant;

use candle_core::Device;
use clap::{Args, Subcommand};
use stylenerf_engine::image_io;
use stylenerf_engine::style2d::corpus::{self, Corpus, CorpusConfig};
use stylenerf_engine::style2d::decoder::Decoder;
use stylenerf_engine::style2d::encoder::VggEncoder;
use stylenerf_engine::style2d::fit::{fit_pair, FitConfig};
use stylenerf_engine::style2d::images::{self, StyleImage};
use stylenerf_engine::style2d::network::AdaInNet;
use stylenerf_engine::style2d::painted;
use stylenerf_engine::style2d::palette::Palette;
use stylenerf_engine::style2d::weights::EncoderWeights;
use stylenerf_engine::LrSchedule;

#[derive(Debug, Subcommand)]
pub enum StylizeCommand {
    /// Stylize one image with AdaIN.
    ///
    /// Starts from the general decoder bundled with stylenerf (trained for the bundled encoder;
    /// a fresh one with another --encoder) or from --decoder, and fine-tunes it on this one
    /// content/style pair for --train-steps Adam steps of AdaIN's content and style losses
    /// (several minutes on a CPU at the default size). The output's chroma is then mapped to
    /// the painting's, its strokes kept (the palette; --no-palette keeps the decoder's
    /// own colours, which with the bundled encoder come mostly from the fine-tuning):
    /// --train-steps 0 gives the general decoder's feed-forward strokes in the painting's
    /// palette. A decoder trained by
    /// `decoder_pretrain` for this style, or AdaIN's decoder.pth with vgg_normalised.pth as
    /// --encoder, needs no fine-tuning.
    Image(ImageArgs),
    /// Write the bundled styles (painted by code, see docs/STYLE2D.md) as PNG files.
    ExportStyles(ExportArgs),
    /// Train a general-purpose decoder on many content photos and style images (a 2D
    /// teacher to start every job's decoder_pretrain from; see docs/STYLE2D.md). Resumes from
    /// OUT/ckpt; OUT/decoder.safetensors and OUT/preview.png are updated at every checkpoint.
    TrainDecoder(TrainDecoderArgs),
}

#[derive(Debug, Args)]
pub struct TrainDecoderArgs {
    /// Content images: files, or folders whose image files are all taken (repeatable).
    #[arg(long, required = true)]
    content: Vec<PathBuf>,
    /// Style images: files, folders, or `builtin:<name>` (repeatable).
    #[arg(long, required = true)]
    style: Vec<String>,
    /// Output folder.
    #[arg(long = "out", value_name = "DIR")]
    output: PathBuf,
    /// Decoder to start from (default: a fresh one).
    #[arg(long)]
    init: Option<PathBuf>,
    /// Encoder weights (any format `weights import` reads); default: the bundled VGG-16.
    #[arg(long)]
    encoder: Option<PathBuf>,
    #[arg(long, default_value_t = CorpusConfig::default().steps)]
    steps: u64,
    /// Content/style pairs per step.
    #[arg(long, default_value_t = CorpusConfig::default().batch)]
    batch: usize,
    /// Side of the square training crops (a multiple of 8).
    #[arg(long, default_value_t = CorpusConfig::default().crop)]
    crop: u32,
    /// Peak learning rate (50 warm-up steps, then exponential decay to 0.2× at the last step).
    #[arg(long, default_value_t = CorpusConfig::default().lr.lr)]
    lr: f64,
    #[arg(long, default_value_t = CorpusConfig::default().style_weight)]
    style_weight: f64,
    /// Probability that a style crop's hue is rotated by a random angle.
    #[arg(long, default_value_t = CorpusConfig::default().hue_jitter)]
    hue_jitter: f32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Stop this run (after writing a checkpoint) once this many minutes have passed; a later
    /// run resumes.
    #[arg(long)]
    minutes: Option<f64>,
}

#[derive(Debug, Args)]
pub struct ExportArgs {
    /// Output folder; each style is written as `<name>.png`.
    #[arg(long = "out", value_name = "DIR")]
    output: PathBuf,
    /// Side of the images.
    #[arg(long, default_value_t = StyleImage::BUILTIN_SIZE)]
    size: u32,
}

#[derive(Debug, Args)]
pub struct ImageArgs {
    /// Content image.
    #[arg(long)]
    content: PathBuf,
    /// Style image, or `builtin:<name>` for a bundled style (mosaic, waves, dots).
    #[arg(long)]
    style: String,
    /// Output PNG.
    #[arg(long = "out", value_name = "FILE")]
    output: PathBuf,
    /// Style strength: 1 = full style, 0 = content features unchanged.
    #[arg(long, default_value_t = 1.0)]
    alpha: f64,
    /// Decoder to start from (this project's safetensors or AdaIN's zip-format decoder.pth);
    /// default: the bundled general decoder.
    #[arg(long)]
    decoder: Option<PathBuf>,
    /// Encoder weights (any format `weights import` reads); default: the bundled VGG-16.
    #[arg(long)]
    encoder: Option<PathBuf>,
    /// Longer side of the working resolution (rounded to a multiple of 8).
    #[arg(long, default_value_t = 256)]
    size: u32,
    /// Adam steps fine-tuning the decoder on this pair (0: feed-forward only; default 300
    /// without --decoder, 0 with it).
    #[arg(long)]
    train_steps: Option<usize>,
    /// Weight of the style loss against the content loss when training.
    #[arg(long, default_value_t = FitConfig::default().style_weight)]
    style_weight: f64,
    /// Learning rate when training.
    #[arg(long, default_value_t = FitConfig::default().lr)]
    lr: f64,
    /// Seed of the decoder's initialisation.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Keep the decoder's own colours instead of mapping its output's chroma to the painting's
    /// (the palette, applied with strength --alpha; docs/STYLE2D.md).
    #[arg(long)]
    no_palette: bool,
}

pub fn run(cmd: StylizeCommand) -> anyhow::Result<()> {
    match cmd {
        StylizeCommand::Image(args) => image(args),
        StylizeCommand::ExportStyles(args) => export_styles(args),
        StylizeCommand::TrainDecoder(args) => train_decoder(args),
    }
}

fn export_styles(a: ExportArgs) -> anyhow::Result<()> {
    for name in painted::NAMES {
        let img = painted::paint(name, a.size).expect("bundled style");
        let path = a.output.join(format!("{name}.png"));
        image_io::save_rgb_png(&path, a.size, a.size, img.as_raw())?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn image(a: ImageArgs) -> anyhow::Result<()> {
    let dev = Device::Cpu;
    let weights = EncoderWeights::load_or_bundled(a.encoder.as_deref())?;
    let encoder = VggEncoder::new(&weights, &dev)?;
    let content = images::to_tensor(&image_io::load_rgb(&a.content)?, a.size, &dev)?;
    let style = images::to_tensor(&StyleImage::load(&a.style)?.image, a.size, &dev)?;
    let decoder = match &a.decoder {
        Some(p) => {
            let (d, trained_with) = Decoder::load(p, &dev)?;
            if let Some(t) = trained_with.filter(|t| t != encoder.source()) {
                tracing::warn!(
                    "decoder was trained with encoder `{t}`, using `{}`",
                    encoder.source()
                );
            }
            d
        }
        None => match Decoder::bundled_for(encoder.source(), &dev)? {
            Some(d) => d,
            None => {
                tracing::info!("--encoder is not the bundled decoder's: starting from a fresh one");
                Decoder::new(weights.arch, a.seed, &dev)?
            }
        },
    };
    let net = AdaInNet { encoder, decoder };
    let target = net.style_target(&style)?;
    let steps = a.train_steps.unwrap_or(if a.decoder.is_some() {
        0
    } else {
        FitConfig::default().steps
    });
    if steps > 0 {
        let cfg = FitConfig {
            steps,
            lr: a.lr,
            style_weight: a.style_weight,
        };
        let t0 = Instant::now();
        tracing::info!(steps, "fine-tuning the decoder on this content/style pair");
        fit_pair(&net, &content, &target, cfg, |r| {
            if r.step % 25 == 0 || r.step + 1 == cfg.steps {
                tracing::info!(
                    step = r.step,
                    content = r.content,
                    style = r.style,
                    elapsed_s = t0.elapsed().as_secs_f32(),
                    "training"
                );
            }
        })?;
    }
    let mut out = net.stylize(&content, &target, a.alpha)?;
    if !a.no_palette {
        let palette = Palette::fit(std::slice::from_ref(&out), &style)?;
        let alpha = a.alpha.clamp(0.0, 1.0) as f32;
        out = Palette::blend(&[(palette, alpha), (Palette::IDENTITY, 1.0 - alpha)]).apply(&out)?;
    }
    let (w, h, rgb) = images::tensor_to_hwc(&out)?;
    image_io::save_rgb_png(&a.output, w, h, &rgb)?;
    println!("wrote {} ({w}×{h})", a.output.display());
    Ok(())
}

/// The image files a `--content`/`--style` argument names: the file itself, or a folder's
/// image files in name order.
fn image_files(path: &std::path::Path) -> anyhow::Result<Vec<PathBuf>> {
    if !path.is_dir() {
        return Ok(vec![path.to_path_buf()]);
    }
    let files = image_io::image_files(path)?;
    if files.is_empty() {
        anyhow::bail!("{}: no .png or .jpg files in this folder", path.display());
    }
    Ok(files)
}

fn train_decoder(a: TrainDecoderArgs) -> anyhow::Result<()> {
    let dev = Device::Cpu;
    let weights = EncoderWeights::load_or_bundled(a.encoder.as_deref())?;
    let encoder = VggEncoder::new(&weights, &dev)?;
    let mut content = Vec::new();
    for p in &a.content {
        for f in image_files(p)? {
            content.push(image_io::load_rgb(&f)?);
        }
    }
    let mut styles = Vec::new();
    for s in &a.style {
        if s.starts_with(StyleImage::BUILTIN) {
            styles.push(StyleImage::load(s)?.image);
            continue;
        }
        for f in image_files(std::path::Path::new(s))? {
            styles.push(image_io::load_rgb(&f)?);
        }
    }
    tracing::info!(
        content = content.len(),
        styles = styles.len(),
        "train-decoder: corpus loaded"
    );
    let corpus = Corpus::new(content, styles)?;
    let decoder = match &a.init {
        Some(p) => Decoder::load(p, &dev)?.0,
        None => Decoder::new(weights.arch, a.seed, &dev)?,
    };
    let net = AdaInNet { encoder, decoder };
    let cfg = CorpusConfig {
        steps: a.steps,
        batch: a.batch,
        crop: a.crop,
        lr: LrSchedule {
            lr: a.lr,
            total_steps: a.steps,
            ..CorpusConfig::default().lr
        },
        style_weight: a.style_weight,
        hue_jitter: a.hue_jitter,
        seed: a.seed,
        ..CorpusConfig::default()
    };
    std::fs::create_dir_all(&a.output)?;
    let t0 = Instant::now();
    let log = corpus::train(&net, &corpus, &cfg, &a.output, &dev, |s| {
        if s.step % 20 == 0 || s.step == cfg.steps {
            tracing::info!(
                step = s.step,
                content = s.content,
                style = s.style,
                lr = s.lr,
                elapsed_s = s.seconds as f32,
                "training"
            );
        }
        a.minutes
            .is_none_or(|m| t0.elapsed().as_secs_f64() < m * 60.0)
    })?;
    let log_path = a.output.join("log.json");
    stylenerf_engine::checkpoint::write_json_atomic(&log_path, &log)?;
    println!(
        "wrote {} after {} steps",
        a.output.join("decoder.safetensors").display(),
        log.last().map_or(0, |s| s.step)
    );
    Ok(())
}
