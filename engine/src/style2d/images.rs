//! Between images and the network's tensors: RGB in [0, 1] as `[1, 3, H, W]`, resized so both
//! sides are multiples of the encoder's stride.

use candle_core::{Device, Tensor};
use image::imageops::FilterType;
use image::Rgb32FImage;

use super::arch::VggArch;
use crate::{image_io, EngineError, Result};

/// A style image with its name.
#[derive(Debug, Clone)]
pub struct StyleImage {
    pub name: String,
    pub image: Rgb32FImage,
}

impl StyleImage {
    /// Prefix of a bundled style's spec, e.g. `builtin:waves`.
    pub const BUILTIN: &'static str = "builtin:";

    /// Side of a bundled style image.
    pub const BUILTIN_SIZE: u32 = 256;

    /// Reads a style from `spec`: `builtin:<name>` for a bundled style (see
    /// [`super::painted`]), otherwise an image file whose stem names the style.
    pub fn load(spec: &str) -> Result<Self> {
        if let Some(name) = spec.strip_prefix(Self::BUILTIN) {
            let image = super::painted::paint(name, Self::BUILTIN_SIZE).ok_or_else(|| {
                EngineError::config(
                    "style",
                    format!(
                        "unknown bundled style `{name}` (bundled: {})",
                        super::painted::NAMES.join(", ")
                    ),
                )
            })?;
            return Ok(Self {
                name: name.to_string(),
                image,
            });
        }
        let path = std::path::Path::new(spec);
        Ok(Self {
            name: path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| spec.to_string()),
            image: image_io::load_rgb(path)?,
        })
    }

    /// The bundled styles, in their default order.
    pub fn bundled() -> Vec<Self> {
        super::painted::NAMES
            .iter()
            .map(|n| Self::load(&format!("{}{n}", Self::BUILTIN)).expect("bundled style"))
            .collect()
    }
}

/// Resizes `img` so its longer side is at most `max_side` (never enlarging) and both sides are
/// multiples of [`VggArch::STRIDE`], then returns it as `[1, 3, H, W]`.
pub fn to_tensor(img: &Rgb32FImage, max_side: u32, device: &Device) -> Result<Tensor> {
    let s = VggArch::STRIDE as u32;
    let (w, h) = img.dimensions();
    let scale = (max_side as f32 / w.max(h) as f32).min(1.0);
    let round = |v: u32| (((v as f32 * scale) / s as f32).round() as u32).max(2) * s;
    let (nw, nh) = (round(w), round(h));
    let resized = if (nw, nh) == (w, h) {
        img.clone()
    } else {
        image::imageops::resize(img, nw, nh, FilterType::Triangle)
    };
    hwc_to_tensor(resized.as_raw(), nw as usize, nh as usize, device)
}

/// Interleaved RGB rows (H·W·3) → `[1, 3, H, W]`.
pub fn hwc_to_tensor(rgb: &[f32], width: usize, height: usize, device: &Device) -> Result<Tensor> {
    Ok(Tensor::from_slice(rgb, (height, width, 3), device)?
        .permute((2, 0, 1))?
        .unsqueeze(0)?
        .contiguous()?)
}

/// `[1, 3, H, W]` (or `[3, H, W]`) → (width, height, interleaved RGB clamped to [0, 1]).
pub fn tensor_to_hwc(t: &Tensor) -> Result<(u32, u32, Vec<f32>)> {
    let t = if t.rank() == 4 {
        t.squeeze(0)?
    } else {
        t.clone()
    };
    let (_, h, w) = t.dims3()?;
    let v = t
        .clamp(0f32, 1f32)?
        .permute((1, 2, 0))?
        .flatten_all()?
        .to_vec1::<f32>()?;
    Ok((w as u32, h as u32, v))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resize_to_stride_and_round_trip() {
        let img = Rgb32FImage::from_fn(50, 30, |x, y| {
            image::Rgb([x as f32 / 50.0, y as f32 / 30.0, 0.5])
        });
        let t = to_tensor(&img, 40, &Device::Cpu).unwrap();
        assert_eq!(t.dims(), &[1, 3, 24, 40]);
        let t = to_tensor(&img, 1000, &Device::Cpu).unwrap();
        assert_eq!(t.dims(), &[1, 3, 32, 48]);
        let exact = Rgb32FImage::from_fn(16, 24, |x, y| {
            image::Rgb([x as f32 / 16.0, y as f32 / 24.0, 0.25])
        });
        let t = to_tensor(&exact, 64, &Device::Cpu).unwrap();
        let (w, h, v) = tensor_to_hwc(&t).unwrap();
        assert_eq!((w, h), (16, 24));
        assert_eq!(v, exact.into_raw());
    }
}
