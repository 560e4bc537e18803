//! Decoding dataset images and depth maps, compositing alpha on the background, and
//! resizing both to the camera's (downscaled) intrinsics.

use std::path::Path;

use image::{DynamicImage, Rgb, Rgb32FImage};

use crate::{EngineError, Result};

/// Where an image was named, for messages: the describing file and its field.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Origin<'a> {
    pub file: &'a Path,
    pub field: &'a str,
}

impl Origin<'_> {
    pub fn err(&self, reason: impl Into<String>) -> EngineError {
        EngineError::dataset(self.file, self.field, reason)
    }
}

fn decode(path: &Path, origin: Origin) -> Result<DynamicImage> {
    image::ImageReader::open(path)
        .and_then(|r| r.with_guessed_format())
        .map_err(|e| origin.err(format!("cannot open {}: {e}", path.display())))?
        .decode()
        .map_err(|e| origin.err(format!("cannot decode {}: {e}", path.display())))
}

/// Whether the image file has an alpha channel (reads the header only); `false` when it
/// cannot be read (loading it reports why).
pub(crate) fn has_alpha(path: &Path) -> bool {
    image::ImageReader::open(path)
        .and_then(|r| r.with_guessed_format())
        .ok()
        .and_then(|r| r.into_decoder().ok())
        .is_some_and(|d| image::ImageDecoder::color_type(&d).has_alpha())
}

/// Reads an image as RGB in [0, 1] (values as stored, no gamma decoding), compositing any
/// alpha channel on `background`.
pub(crate) fn read_rgb(path: &Path, origin: Origin, background: [f32; 3]) -> Result<Rgb32FImage> {
    let img = decode(path, origin)?;
    if !img.color().has_alpha() {
        return Ok(img.into_rgb32f());
    }
    let rgba = img.into_rgba32f();
    let (w, h) = rgba.dimensions();
    Ok(Rgb32FImage::from_fn(w, h, |x, y| {
        let [r, g, b, a] = rgba.get_pixel(x, y).0;
        let mix = |c: f32, bg: f32| c * a + bg * (1.0 - a);
        Rgb([
            mix(r, background[0]),
            mix(g, background[1]),
            mix(b, background[2]),
        ])
    }))
}

/// Reads a depth map as depth in world units (`raw × scale`; 0 = unknown): a 16-bit grayscale
/// PNG, or a NumPy `.npy` array of shape (H, W) (float or uint16; NaN, infinite and negative
/// values are unknown), as nerfstudio reads them.
pub(crate) fn read_depth(path: &Path, origin: Origin, scale: f32) -> Result<(u32, u32, Vec<f32>)> {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"))
    {
        let m = super::npy::read_matrix(path)
            .map_err(|e| origin.err(format!("depth map {}: {e}", path.display())))?;
        let depth = m
            .data
            .iter()
            .map(|&d| {
                let d = d as f32 * scale;
                if d.is_finite() && d > 0.0 {
                    d
                } else {
                    0.0
                }
            })
            .collect();
        return Ok((m.cols as u32, m.rows as u32, depth));
    }
    match decode(path, origin)? {
        DynamicImage::ImageLuma16(img) => {
            let (w, h) = img.dimensions();
            Ok((
                w,
                h,
                img.into_raw()
                    .into_iter()
                    .map(|d| d as f32 * scale)
                    .collect(),
            ))
        }
        other => Err(origin.err(format!(
            "{}: expected a 16-bit grayscale depth PNG (or a .npy array), found {:?}",
            path.display(),
            other.color()
        ))),
    }
}

/// Resizes an image to `width`×`height` (area-aware triangle filter when shrinking).
pub(crate) fn resize_rgb(img: &Rgb32FImage, width: u32, height: u32) -> Rgb32FImage {
    if img.dimensions() == (width, height) {
        return img.clone();
    }
    image::imageops::resize(img, width, height, image::imageops::FilterType::Triangle)
}

/// Resizes a depth map by nearest sampling, so that no depth is invented between surfaces.
/// Where the nearest source pixel's depth is unknown (0), the smallest known depth (the nearest
/// surface) in the source block the output pixel covers is taken instead: shrinking a sparse map (points from
/// structure from motion, the `poses` stage's) by nearest sampling alone would drop most of its
/// points.
pub(crate) fn resize_depth(depth: &[f32], w: u32, h: u32, width: u32, height: u32) -> Vec<f32> {
    if (w, h) == (width, height) {
        return depth.to_vec();
    }
    // The source rows (or columns) output row `i` of `n` covers, and its centre's.
    let block = |i: u32, n: u32, src: u32| {
        let start = ((i as u64 * src as u64) / n as u64) as u32;
        let end = ((((i + 1) as u64 * src as u64) / n as u64) as u32).max(start + 1);
        let centre = (((i as f32 + 0.5) * src as f32 / n as f32) as u32).min(src - 1);
        (start..end.min(src), centre)
    };
    let mut out = Vec::with_capacity((width * height) as usize);
    for y in 0..height {
        let (rows, sy) = block(y, height, h);
        for x in 0..width {
            let (cols, sx) = block(x, width, w);
            let centre = depth[(sy * w + sx) as usize];
            if centre > 0.0 {
                out.push(centre);
                continue;
            }
            let nearest_known = rows
                .clone()
                .flat_map(|r| cols.clone().map(move |c| depth[(r * w + c) as usize]))
                .filter(|&d| d > 0.0)
                .fold(f32::INFINITY, f32::min);
            out.push(if nearest_known.is_finite() {
                nearest_known
            } else {
                0.0
            });
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shrinking_a_depth_map_samples_the_centre_and_keeps_sparse_points() {
        // 4×4 → 2×2: each output pixel covers a 2×2 block whose centre sample is its
        // bottom-right pixel.
        let dense: Vec<f32> = (1..=16).map(|v| v as f32).collect();
        assert_eq!(resize_depth(&dense, 4, 4, 2, 2), [6.0, 8.0, 14.0, 16.0]);
        // Sparse: one block holds two points off its centre (the nearer is kept), one a point
        // at its centre, one nothing.
        let mut sparse = vec![0.0; 16];
        sparse[0] = 3.0;
        sparse[4] = 2.5;
        sparse[7] = 9.0;
        sparse[15] = 4.0;
        assert_eq!(resize_depth(&sparse, 4, 4, 2, 2), [2.5, 9.0, 0.0, 4.0]);
        // Growing samples the nearest pixel, as before.
        assert_eq!(resize_depth(&[1.0, 0.0], 2, 1, 4, 1), [1.0, 1.0, 0.0, 0.0]);
    }
}
