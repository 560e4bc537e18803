//! Small helpers between f32 pixel buffers and image files: saving RGB previews and 16-bit
//! depth maps atomically, colour-mapping depth, and loading style/content images as linear
//! [0, 1] RGB.

use std::path::{Path, PathBuf};

use image::{EncodableLayout, ImageBuffer, Luma, PixelWithColorType, Rgb, Rgb32FImage, RgbImage};

use crate::{EngineError, Result};

/// Whether `path` names a PNG or JPEG file by its extension (in any case).
pub fn has_image_extension(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["png", "jpg", "jpeg"].contains(&e.to_ascii_lowercase().as_str()))
}

/// The PNG and JPEG files of a folder (not its subfolders), in name order.
pub fn image_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| EngineError::io(dir, e))? {
        let path = entry.map_err(|e| EngineError::io(dir, e))?.path();
        if path.is_file() && has_image_extension(&path) {
            files.push(path);
        }
    }
    files.sort();
    Ok(files)
}

/// Quantises interleaved RGB in [0, 1] to 8-bit.
pub fn to_rgb8(width: u32, height: u32, rgb: &[f32]) -> RgbImage {
    let bytes = rgb
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
        .collect();
    RgbImage::from_raw(width, height, bytes).expect("buffer length matches the image size")
}

/// Saves interleaved RGB in [0, 1] as a PNG, atomically (temporary file, then rename).
pub fn save_rgb_png(path: &Path, width: u32, height: u32, rgb: &[f32]) -> Result<()> {
    save_png(path, &to_rgb8(width, height, rgb))
}

/// Saves an 8-bit RGB image as a PNG atomically.
pub fn save_png(path: &Path, img: &RgbImage) -> Result<()> {
    save_png_of(path, img)
}

/// Saves a z-depth map (row-major, world units, 0 = unknown) as a 16-bit grayscale PNG of
/// `depth / unit`, atomically, as nerfstudio reads them (`depth_unit_scale_factor` = `unit`).
/// A known depth never rounds to 0; depths past `65535 · unit` are clipped there.
pub fn save_depth_png(
    path: &Path,
    width: u32,
    height: u32,
    depth: &[f32],
    unit: f64,
) -> Result<()> {
    let values: Vec<u16> = depth
        .iter()
        .map(|&d| match d > 0.0 {
            true => (d / unit as f32).round().clamp(1.0, f32::from(u16::MAX)) as u16,
            false => 0,
        })
        .collect();
    let img = ImageBuffer::<Luma<u16>, _>::from_raw(width, height, values)
        .expect("buffer length matches the image size");
    save_png_of(path, &img)
}

fn save_png_of<P>(path: &Path, img: &ImageBuffer<P, Vec<P::Subpixel>>) -> Result<()>
where
    P: PixelWithColorType,
    [P::Subpixel]: EncodableLayout,
{
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )
    .map_err(|e| EngineError::artifact(path, format!("PNG encoding failed: {e}")))?;
    crate::checkpoint::write_atomic(path, &bytes)
}

/// Maps depth to a perceptual-ish colour ramp between `near` and `far` (0 depth → black).
pub fn depth_preview(width: u32, height: u32, depth: &[f32], near: f32, far: f32) -> RgbImage {
    let mut img = RgbImage::new(width, height);
    for (p, &d) in img.pixels_mut().zip(depth) {
        if d <= 0.0 || !d.is_finite() {
            continue;
        }
        let t = ((d - near) / (far - near).max(1e-6)).clamp(0.0, 1.0);
        // Warm (near) to cool (far).
        let r = 1.0 - t;
        let g = 1.0 - (2.0 * t - 1.0).abs();
        let b = t;
        *p = Rgb([
            (r * 255.0) as u8,
            (g * 200.0 + 55.0 * (1.0 - t)) as u8,
            (b * 255.0) as u8,
        ]);
    }
    img
}

/// Loads any image the `image` crate decodes as RGB in [0, 1].
pub fn load_rgb(path: &Path) -> Result<Rgb32FImage> {
    let img = image::ImageReader::open(path)
        .map_err(|e| EngineError::io(path, e))?
        .with_guessed_format()
        .map_err(|e| EngineError::io(path, e))?
        .decode()
        .map_err(|e| EngineError::dataset(path, "image", format!("cannot decode image: {e}")))?;
    Ok(img.into_rgb32f())
}
