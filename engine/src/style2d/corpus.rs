//! Training a general-purpose AdaIN decoder once, offline, on a corpus of content photos and
//! style images (`stylenerf stylize train-decoder`): a 2D teacher that a job's
//! `decoder_pretrain` can fine-tune (its `init_decoder`) instead of starting from noise.
//!
//! Each step draws `batch` content crops and `batch` style crops, each of a random image, at a
//! random scale (a square of side between `crop` pixels and the image's shorter side, resized
//! to `crop`²), randomly mirrored; a style crop's hue is rotated by a random angle with
//! probability `hue_jitter`, so a few paintings teach many palettes with their own brushwork.
//! The loss is AdaIN's: content (relu4_1 against the AdaIN target) + λ_s · style (channel
//! mean/std at relu1_1 … relu4_1), each content crop stylized with its own style crop.
//! Training checkpoints (decoder, Adam moments, RNG) and resumes, and writes the current
//! decoder plus a preview sheet at every checkpoint.

use std::path::Path;
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use image::imageops::FilterType;
use image::{Rgb, Rgb32FImage};
use serde::{Deserialize, Serialize};

use super::images::{hwc_to_tensor, tensor_to_hwc};
use super::network::AdaInNet;
use crate::checkpoint::CheckpointDir;
use crate::optim::{Adam, AdamConfig, LrSchedule};
use crate::rng::Rng;
use crate::{EngineError, Result};

/// Hyper-parameters of [`train`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CorpusConfig {
    pub steps: u64,
    /// Content/style pairs per step.
    pub batch: usize,
    /// Side of the square training crops (a multiple of 8).
    pub crop: u32,
    pub lr: LrSchedule,
    /// λ_s.
    pub style_weight: f64,
    /// Probability that a style crop's hue is rotated by a random angle.
    pub hue_jitter: f32,
    /// Seconds between checkpoints.
    pub checkpoint_seconds: f64,
    pub seed: u64,
}

impl Default for CorpusConfig {
    fn default() -> Self {
        Self {
            steps: 4000,
            batch: 4,
            crop: 96,
            lr: LrSchedule {
                lr: 3e-4,
                warmup_steps: 50,
                final_ratio: 0.2,
                total_steps: 4000,
            },
            style_weight: 1.0,
            hue_jitter: 0.5,
            checkpoint_seconds: 120.0,
            seed: 0,
        }
    }
}

/// The images a decoder is trained on.
#[derive(Debug, Clone)]
pub struct Corpus {
    pub content: Vec<Rgb32FImage>,
    pub styles: Vec<Rgb32FImage>,
}

impl Corpus {
    /// Longest side images are kept at: crops are drawn from at most this much detail.
    pub const MAX_SIDE: u32 = 512;

    /// A corpus whose images are shrunk (never enlarged) to [`Self::MAX_SIDE`].
    pub fn new(content: Vec<Rgb32FImage>, styles: Vec<Rgb32FImage>) -> Result<Self> {
        if content.is_empty() || styles.is_empty() {
            return Err(EngineError::config(
                "corpus",
                "at least one content image and one style image are needed",
            ));
        }
        let shrink = |img: Rgb32FImage| {
            let (w, h) = img.dimensions();
            let s = Self::MAX_SIDE as f32 / w.max(h) as f32;
            if s >= 1.0 {
                img
            } else {
                let (nw, nh) = (
                    ((w as f32 * s) as u32).max(1),
                    ((h as f32 * s) as u32).max(1),
                );
                image::imageops::resize(&img, nw, nh, FilterType::Triangle)
            }
        };
        Ok(Self {
            content: content.into_iter().map(shrink).collect(),
            styles: styles.into_iter().map(shrink).collect(),
        })
    }
}

/// Loss values of one step, for progress reports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CorpusStep {
    pub step: u64,
    pub content: f32,
    pub style: f32,
    pub lr: f64,
    pub seconds: f64,
}

#[derive(Serialize, Deserialize)]
struct CheckpointMeta {
    step: u64,
    rng: Rng,
    config: CorpusConfig,
    log: Vec<CorpusStep>,
    seconds: f64,
}

/// A random square crop of `img` with a side between `crop` and the shorter side (log-uniform),
/// resized to `crop`², mirrored with probability ½.
fn random_crop(img: &Rgb32FImage, crop: u32, rng: &mut Rng) -> Rgb32FImage {
    let (w, h) = img.dimensions();
    let short = w.min(h);
    let lo = crop.min(short) as f32;
    let side = (lo * (short as f32 / lo).powf(rng.uniform())).round() as u32;
    let side = side.clamp(1, short);
    let x = rng.below((w - side + 1) as usize) as u32;
    let y = rng.below((h - side + 1) as usize) as u32;
    let mut out = image::imageops::resize(
        &image::imageops::crop_imm(img, x, y, side, side).to_image(),
        crop,
        crop,
        FilterType::Triangle,
    );
    if rng.uniform() < 0.5 {
        image::imageops::flip_horizontal_in_place(&mut out);
    }
    out
}

/// Rotates every pixel's hue by `angle` radians about the grey axis (YIQ chroma rotation),
/// keeping luma; clamped to [0, 1].
pub fn rotate_hue(img: &mut Rgb32FImage, angle: f32) {
    let (s, c) = angle.sin_cos();
    for Rgb(p) in img.pixels_mut() {
        let [r, g, b] = *p;
        let y = 0.299 * r + 0.587 * g + 0.114 * b;
        let i = 0.596 * r - 0.274 * g - 0.322 * b;
        let q = 0.211 * r - 0.523 * g + 0.312 * b;
        let (i, q) = (c * i - s * q, s * i + c * q);
        *p = [
            y + 0.956 * i + 0.621 * q,
            y - 0.272 * i - 0.647 * q,
            y - 1.106 * i + 1.703 * q,
        ]
        .map(|v| v.clamp(0.0, 1.0));
    }
}

fn batch_tensor(crops: &[Rgb32FImage], device: &Device) -> Result<Tensor> {
    let t = crops
        .iter()
        .map(|c| {
            let (w, h) = c.dimensions();
            hwc_to_tensor(c.as_raw(), w as usize, h as usize, device)
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Tensor::cat(&t, 0)?)
}

/// One step's content and style crops.
fn draw(
    corpus: &Corpus,
    cfg: &CorpusConfig,
    rng: &mut Rng,
) -> (Vec<Rgb32FImage>, Vec<Rgb32FImage>) {
    let content = (0..cfg.batch)
        .map(|_| {
            random_crop(
                &corpus.content[rng.below(corpus.content.len())],
                cfg.crop,
                rng,
            )
        })
        .collect();
    let styles = (0..cfg.batch)
        .map(|_| {
            let mut s = random_crop(
                &corpus.styles[rng.below(corpus.styles.len())],
                cfg.crop,
                rng,
            );
            if rng.uniform() < cfg.hue_jitter {
                rotate_hue(&mut s, rng.uniform() * std::f32::consts::TAU);
            }
            s
        })
        .collect();
    (content, styles)
}

/// Trains `net.decoder` on `corpus`, checkpointing into `out/ckpt` and resuming from it. At
/// every checkpoint and at the end, `out/decoder.safetensors` is the current decoder (f16) and
/// `out/preview.png` shows content | style | output for a few fixed pairs. `report` is called
/// after every step; returning `false` stops after the next checkpoint is written.
pub fn train(
    net: &AdaInNet,
    corpus: &Corpus,
    cfg: &CorpusConfig,
    out: &Path,
    device: &Device,
    mut report: impl FnMut(&CorpusStep) -> bool,
) -> Result<Vec<CorpusStep>> {
    if !cfg.crop.is_multiple_of(8) || cfg.crop < 32 || cfg.batch == 0 {
        return Err(EngineError::config(
            "train-decoder",
            format!(
                "crop must be a multiple of 8 of at least 32 and batch at least 1, \
                 got crop {} and batch {}",
                cfg.crop, cfg.batch
            ),
        ));
    }
    let ckpt = CheckpointDir::new(out.join("ckpt"), 2);
    let mut adam = Adam::new(net.decoder.vars(), AdamConfig::default())?;
    let mut rng = Rng::new(cfg.seed);
    let (mut start, mut log, mut seconds_before) = (0, Vec::new(), 0.0);
    if let Some(c) = ckpt.latest::<CheckpointMeta>(device)? {
        net.decoder.load_tensors(&c.tensors, ckpt.path())?;
        adam.load_state(&c.tensors, c.meta.step)?;
        (start, rng, log, seconds_before) = (c.meta.step, c.meta.rng, c.meta.log, c.meta.seconds);
        tracing::info!(step = start, "train-decoder: resuming from checkpoint");
    }
    // Fixed preview pairs, drawn from their own seed so they do not depend on the step.
    let preview = draw(
        corpus,
        &CorpusConfig {
            batch: 4,
            hue_jitter: 0.0,
            ..*cfg
        },
        &mut Rng::new(cfg.seed ^ 0x9e37_79b9),
    );
    let started = Instant::now();
    let mut last_ckpt = Instant::now();
    let save = |step: u64, adam: &Adam, rng: Rng, log: &[CorpusStep], seconds: f64| -> Result<()> {
        let mut tensors = net.decoder.tensors();
        tensors.extend(adam.state());
        let meta = CheckpointMeta {
            step,
            rng,
            config: *cfg,
            log: log.to_vec(),
            seconds,
        };
        ckpt.save(step, &tensors, &meta)?;
        export(net, out)?;
        preview_sheet(net, &preview, &out.join("preview.png"), device)
    };
    for step in start..cfg.steps {
        let (content, styles) = draw(corpus, cfg, &mut rng);
        let target = net.style_target(&batch_tensor(&styles, device)?)?;
        let l = net.losses(&batch_tensor(&content, device)?, &target)?;
        let total = (&l.content + (&l.style * cfg.style_weight)?)?;
        let lr = cfg.lr.at(step);
        adam.step(&total.backward()?, lr)?;
        let rec = CorpusStep {
            step: step + 1,
            content: l.content.to_scalar()?,
            style: l.style.to_scalar()?,
            lr,
            seconds: seconds_before + started.elapsed().as_secs_f64(),
        };
        if !(rec.content.is_finite() && rec.style.is_finite()) {
            return Err(EngineError::config(
                "train-decoder",
                format!(
                    "the loss diverged at step {} (lower the learning rate)",
                    rec.step
                ),
            ));
        }
        log.push(rec);
        let go_on = report(&rec);
        let due = last_ckpt.elapsed().as_secs_f64() >= cfg.checkpoint_seconds;
        if rec.step == cfg.steps || due || !go_on {
            save(rec.step, &adam, rng, &log, rec.seconds)?;
            last_ckpt = Instant::now();
        }
        if !go_on {
            break;
        }
    }
    if start >= cfg.steps {
        export(net, out)?;
    }
    Ok(log)
}

/// Writes `out/decoder.safetensors`, f16 (the form it ships in; the checkpoint keeps f32).
fn export(net: &AdaInNet, out: &Path) -> Result<()> {
    net.decoder.save_as(
        &out.join("decoder.safetensors"),
        net.encoder.source(),
        DType::F16,
    )
}

/// Rows of content | style | output for `pairs`.
fn preview_sheet(
    net: &AdaInNet,
    (content, styles): &(Vec<Rgb32FImage>, Vec<Rgb32FImage>),
    path: &Path,
    device: &Device,
) -> Result<()> {
    let target = net.style_target(&batch_tensor(styles, device)?)?;
    let out = net.stylize(&batch_tensor(content, device)?, &target, 1.0)?;
    let (w, h) = content[0].dimensions();
    let grid = (0..content.len())
        .map(|r| {
            let (_, _, o) = tensor_to_hwc(&out.get(r)?)?;
            Ok([content[r].as_raw(), styles[r].as_raw(), &o]
                .into_iter()
                .map(|rgb| crate::image_io::to_rgb8(w, h, rgb))
                .collect())
        })
        .collect::<Result<Vec<_>>>()?;
    let sheet = crate::sheet::labelled_grid(&["content", "style", "output"], &grid)?;
    crate::image_io::save_png(path, &sheet)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::style2d::arch::VggArch;
    use crate::style2d::decoder::Decoder;
    use crate::style2d::encoder::VggEncoder;
    use crate::style2d::weights::EncoderWeights;

    #[test]
    fn hue_rotation_keeps_grey_and_luma_and_turns_full_circle() {
        let mut img = Rgb32FImage::from_fn(4, 1, |x, _| match x {
            0 => Rgb([0.5, 0.5, 0.5]),
            1 => Rgb([0.6, 0.3, 0.2]),
            2 => Rgb([0.2, 0.5, 0.4]),
            _ => Rgb([0.3, 0.3, 0.6]),
        });
        let orig = img.clone();
        rotate_hue(&mut img, 2.0);
        let luma = |p: &Rgb<f32>| 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2];
        for (a, b) in orig.pixels().zip(img.pixels()) {
            assert!((luma(a) - luma(b)).abs() < 2e-3, "{a:?} {b:?}");
        }
        assert!(img.get_pixel(0, 0).0.iter().all(|v| (v - 0.5).abs() < 1e-4));
        assert!((img.get_pixel(1, 0)[0] - 0.6).abs() > 0.05, "hue changed");
        rotate_hue(&mut img, std::f32::consts::TAU - 2.0);
        for (a, b) in orig.pixels().zip(img.pixels()) {
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() < 2e-3, "{a:?} {b:?}");
            }
        }
    }

    #[test]
    fn crops_have_the_size_asked_and_stay_inside() {
        let img = Rgb32FImage::from_fn(70, 50, |x, y| Rgb([x as f32 / 70.0, y as f32 / 50.0, 0.0]));
        let mut rng = Rng::new(3);
        for _ in 0..20 {
            let c = random_crop(&img, 32, &mut rng);
            assert_eq!(c.dimensions(), (32, 32));
        }
        // Smaller than the crop: the whole image, enlarged.
        let small = Rgb32FImage::new(20, 12);
        assert_eq!(random_crop(&small, 32, &mut rng).dimensions(), (32, 32));
    }

    #[test]
    fn an_empty_corpus_or_a_bad_crop_is_refused_with_the_reason() {
        let img = || vec![Rgb32FImage::new(40, 40)];
        let e = Corpus::new(vec![], img()).unwrap_err().to_string();
        assert!(e.contains("at least one content image"), "{e}");
        assert!(Corpus::new(img(), vec![]).is_err());
        let dev = Device::Cpu;
        let net = AdaInNet {
            encoder: VggEncoder::new(&EncoderWeights::bundled().unwrap(), &dev).unwrap(),
            decoder: Decoder::new(VggArch::Vgg16, 0, &dev).unwrap(),
        };
        let corpus = Corpus::new(img(), img()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        for (crop, batch) in [(36, 2), (24, 2), (32, 0)] {
            let cfg = CorpusConfig {
                crop,
                batch,
                ..CorpusConfig::default()
            };
            let e = train(&net, &corpus, &cfg, dir.path(), &dev, |_| true)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains(&format!("got crop {crop} and batch {batch}")),
                "{e}"
            );
        }
        assert!(!dir.path().join("ckpt").exists());
    }

    #[test]
    fn training_lowers_the_loss_and_resumes_where_it_stopped() {
        let dev = Device::Cpu;
        let w = EncoderWeights::bundled().unwrap();
        let net = AdaInNet {
            encoder: VggEncoder::new(&w, &dev).unwrap(),
            decoder: Decoder::new(VggArch::Vgg16, 0, &dev).unwrap(),
        };
        let content = vec![Rgb32FImage::from_fn(48, 40, |x, y| {
            Rgb([x as f32 / 48.0, y as f32 / 40.0, 0.5])
        })];
        let styles = vec![crate::style2d::painted::paint("waves", 64).unwrap()];
        let corpus = Corpus::new(content, styles).unwrap();
        let cfg = CorpusConfig {
            steps: 12,
            batch: 2,
            crop: 32,
            lr: LrSchedule::constant(1e-3),
            checkpoint_seconds: 1e9,
            ..CorpusConfig::default()
        };
        let dir = tempfile::tempdir().unwrap();
        // Stopped after 6 steps (a checkpoint is written), then resumed to 12.
        let first = train(&net, &corpus, &cfg, dir.path(), &dev, |s| s.step < 6).unwrap();
        assert_eq!(first.len(), 6);
        assert!(dir.path().join("decoder.safetensors").exists());
        assert!(dir.path().join("preview.png").exists());
        let fresh = AdaInNet {
            decoder: Decoder::new(VggArch::Vgg16, 0, &dev).unwrap(),
            ..net.clone()
        };
        let log = train(&fresh, &corpus, &cfg, dir.path(), &dev, |_| true).unwrap();
        assert_eq!(log.len(), 12);
        assert_eq!(log[5], first[5]);
        let total = |s: &CorpusStep| s.content + s.style;
        let early: f32 = log[..3].iter().map(total).sum();
        let late: f32 = log[9..].iter().map(total).sum();
        assert!(late < early, "loss {early} → {late}");
    }
}
