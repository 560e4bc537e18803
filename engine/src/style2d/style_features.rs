//! The style feature vector the VAE models: channel mean and std (AdaIN's statistics, unbiased
//! variance + 1e-5) of the encoder's relu4_1 — 512 + 512 = 1024 values — of random square
//! crops (random position, side a random fraction of the shorter side) resized to a fixed
//! size. Training and a style's distribution use the same function, [`crop_vectors`].

use candle_core::{Device, Tensor};
use image::imageops::FilterType;
use image::Rgb32FImage;

use super::adain::stats;
use super::encoder::VggEncoder;
use super::images::hwc_to_tensor;
use crate::rng::Rng;
use crate::Result;

/// Length of the style feature vector: mean and std of relu4_1's 512 channels.
pub const STYLE_DIM: usize = 1024;

/// How crops are drawn.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CropConfig {
    /// Side (pixels) every crop is resized to before encoding; a multiple of 8.
    pub size: u32,
    /// Crop side as a fraction of the image's shorter side, drawn uniformly in [min, 1].
    pub min_scale: f32,
}

impl Default for CropConfig {
    fn default() -> Self {
        Self {
            size: 128,
            min_scale: 0.4,
        }
    }
}

/// Style vectors `[B, 1024]` of images `[B, 3, H, W]`: `[mean(relu4_1), std(relu4_1)]`.
pub fn style_vectors(encoder: &VggEncoder, images: &Tensor) -> Result<Tensor> {
    let s = stats(&encoder.relu4_1(images)?)?;
    let b = images.dim(0)?;
    Ok(Tensor::cat(
        &[s.mean.reshape((b, 512))?, s.std.reshape((b, 512))?],
        1,
    )?)
}

/// `n` random square crops of `img` with random scales, each resized to `cfg.size`:
/// `[n, 3, size, size]`.
pub fn random_crops(
    img: &Rgb32FImage,
    n: usize,
    cfg: CropConfig,
    rng: &mut Rng,
    device: &Device,
) -> Result<Tensor> {
    let (w, h) = img.dimensions();
    let short = w.min(h) as f32;
    let crops = (0..n)
        .map(|_| {
            let scale = cfg.min_scale + (1.0 - cfg.min_scale) * rng.uniform();
            let side = ((short * scale) as u32).clamp(1, w.min(h));
            let x = rng.below((w - side + 1) as usize) as u32;
            let y = rng.below((h - side + 1) as usize) as u32;
            let crop = image::imageops::crop_imm(img, x, y, side, side).to_image();
            let r = image::imageops::resize(&crop, cfg.size, cfg.size, FilterType::Triangle);
            hwc_to_tensor(r.as_raw(), cfg.size as usize, cfg.size as usize, device)
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Tensor::cat(&crops, 0)?)
}

/// Style vectors `[n, 1024]` of `n` random crops of `img`: the VAE's training data, and the
/// input of a style's distribution ([`super::vae::StyleVae::style_distribution`]).
pub fn crop_vectors(
    encoder: &VggEncoder,
    img: &Rgb32FImage,
    n: usize,
    cfg: CropConfig,
    rng: &mut Rng,
    device: &Device,
) -> Result<Tensor> {
    style_vectors(encoder, &random_crops(img, n, cfg, rng, device)?)
}
