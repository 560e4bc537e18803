//! Writing a sparse model as a nerfstudio dataset: the registered images at the working
//! resolution (intrinsics scaled to match) and a `transforms.json` with COLMAP's camera model
//! and distortion, camera-to-world poses in OpenGL axes.

use std::collections::BTreeMap;
use std::path::Path;

use image::imageops::FilterType;
use rayon::prelude::*;
use serde_json::{json, Map, Value};

use super::model::{ColmapCamera, SparseModel};
use crate::camera::Intrinsics;
use crate::checkpoint::{write_atomic, write_json_atomic};
use crate::scene::{working_intrinsics, LoadOptions};
use crate::{EngineError, Result};

/// Writes `model`'s registered images from `images` into `out/images/` and
/// `out/transforms.json`. `sharpness` (by image name) is recorded per frame when known.
/// Returns the written resolution of the first camera.
pub fn write(
    model: &SparseModel,
    images: &Path,
    out: &Path,
    max_side: u32,
    sharpness: &BTreeMap<String, f64>,
) -> Result<(u32, u32)> {
    let image_dir = out.join("images");
    std::fs::create_dir_all(&image_dir).map_err(|e| EngineError::io(&image_dir, e))?;
    let scaled: BTreeMap<u32, ColmapCamera> = model
        .cameras
        .iter()
        .map(|(&id, c)| (id, scale_camera(c, max_side)))
        .collect();
    let mut frames: Vec<_> = model.images.iter().collect();
    frames.sort_by(|a, b| a.name.cmp(&b.name));
    frames.par_iter().try_for_each(|img| {
        let cam = &scaled[&img.camera];
        resize_into(&images.join(&img.name), &image_dir.join(&img.name), cam)
    })?;

    let distorted = scaled
        .values()
        .any(|c| c.distortion.iter().any(|&k| k != 0.0));
    let mut top = Map::new();
    top.insert(
        "camera_model".into(),
        json!(if distorted { "OPENCV" } else { "PINHOLE" }),
    );
    let single = scaled.len() == 1;
    if single {
        intrinsics(&mut top, scaled.values().next().expect("one camera"));
    }
    let frames: Vec<Value> = frames
        .iter()
        .map(|img| {
            let mut f = Map::new();
            f.insert("file_path".into(), json!(format!("images/{}", img.name)));
            let (r, p) = (img.rotation, img.position);
            f.insert(
                "transform_matrix".into(),
                json!([
                    [r.x_axis.x, r.y_axis.x, r.z_axis.x, p.x],
                    [r.x_axis.y, r.y_axis.y, r.z_axis.y, p.y],
                    [r.x_axis.z, r.y_axis.z, r.z_axis.z, p.z],
                    [0.0, 0.0, 0.0, 1.0]
                ]),
            );
            if !single {
                intrinsics(&mut f, &scaled[&img.camera]);
            }
            if let Some(s) = sharpness.get(&img.name) {
                f.insert("sharpness".into(), json!(s));
            }
            Value::Object(f)
        })
        .collect();
    top.insert("frames".into(), Value::Array(frames));
    write_json_atomic(&out.join("transforms.json"), &Value::Object(top))?;
    let first = scaled.values().next().expect("a model has a camera");
    Ok((first.width, first.height))
}

fn intrinsics(obj: &mut Map<String, Value>, c: &ColmapCamera) {
    for (k, v) in [
        ("w", c.width as f64),
        ("h", c.height as f64),
        ("fl_x", c.fx),
        ("fl_y", c.fy),
        ("cx", c.cx),
        ("cy", c.cy),
        ("k1", c.distortion[0]),
        ("k2", c.distortion[1]),
        ("p1", c.distortion[2]),
        ("p2", c.distortion[3]),
    ] {
        obj.insert(k.into(), json!(v));
    }
}

/// The camera at the working resolution. COLMAP puts pixel centres at +0.5 as the loader does,
/// so the principal point scales with the image; distortion is in normalised coordinates and
/// does not change.
fn scale_camera(c: &ColmapCamera, max_side: u32) -> ColmapCamera {
    // The size the loader would train a frame of this camera at with this `max_side`.
    let k = Intrinsics {
        fx: c.fx as f32,
        fy: c.fy as f32,
        cx: c.cx as f32,
        cy: c.cy as f32,
        width: c.width,
        height: c.height,
    };
    let opts = LoadOptions {
        max_side: Some(max_side),
        ..LoadOptions::default()
    };
    let Intrinsics {
        width: w,
        height: h,
        ..
    } = working_intrinsics(&k, &opts);
    let (sx, sy) = (w as f64 / c.width as f64, h as f64 / c.height as f64);
    ColmapCamera {
        width: w,
        height: h,
        fx: c.fx * sx,
        fy: c.fy * sy,
        cx: c.cx * sx,
        cy: c.cy * sy,
        distortion: c.distortion,
    }
}

/// Writes `from` at the camera's size to `to` (copied when already that size), atomically.
fn resize_into(from: &Path, to: &Path, cam: &ColmapCamera) -> Result<()> {
    let img = image::open(from).map_err(|e| {
        EngineError::dataset(
            from,
            "images",
            format!("cannot decode a registered image: {e}"),
        )
    })?;
    if (img.width(), img.height()) == (cam.width, cam.height) {
        let bytes = std::fs::read(from).map_err(|e| EngineError::io(from, e))?;
        return write_atomic(to, &bytes);
    }
    let small = img.resize_exact(cam.width, cam.height, FilterType::Lanczos3);
    let format = image::ImageFormat::from_path(to).unwrap_or(image::ImageFormat::Png);
    let mut bytes = Vec::new();
    let mut cursor = std::io::Cursor::new(&mut bytes);
    let encoded =
        match format {
            image::ImageFormat::Jpeg => small.to_rgb8().write_with_encoder(
                image::codecs::jpeg::JpegEncoder::new_with_quality(&mut cursor, 95),
            ),
            _ => small.to_rgb8().write_to(&mut cursor, format),
        };
    encoded.map_err(|e| EngineError::artifact(to, format!("cannot encode: {e}")))?;
    write_atomic(to, &bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn working_size_keeps_the_aspect_and_small_images() {
        let c = ColmapCamera {
            width: 1080,
            height: 1920,
            fx: 1375.5,
            fy: 1374.5,
            cx: 554.5,
            cy: 965.3,
            distortion: [0.05, -0.08, 0.0, 0.0],
        };
        let s = scale_camera(&c, 480);
        assert_eq!((s.width, s.height), (270, 480));
        assert!((s.fx - 1375.5 / 4.0).abs() < 1e-9 && (s.cy - 965.3 / 4.0).abs() < 1e-9);
        assert_eq!(s.distortion, c.distortion);
        let small = ColmapCamera {
            width: 200,
            height: 100,
            ..c
        };
        let s = scale_camera(&small, 480);
        assert_eq!((s.width, s.height), (200, 100));
    }
}
