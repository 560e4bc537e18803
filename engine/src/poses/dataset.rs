//! Writing a sparse model as a nerfstudio dataset: the registered images at the working
//! resolution (intrinsics scaled to match), a sparse depth map per image (the z-depth of each
//! sparse point the image observes, at the pixel it observes it; 0 elsewhere, as nerfstudio's
//! `create_sfm_depth` writes them: what `nerf_pretrain.depth_weight` trains on, and what grades
//! the field's depth on test views) and a `transforms.json` with COLMAP's camera model and
//! distortion, camera-to-world poses in OpenGL axes.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use glam::DVec3;
use image::imageops::FilterType;
use rayon::prelude::*;
use serde_json::{json, Map, Value};

use super::model::{ColmapCamera, ColmapImage, SparseModel};
use crate::camera::Intrinsics;
use crate::checkpoint::{write_atomic, write_json_atomic};
use crate::image_io::save_depth_png;
use crate::scene::{working_intrinsics, LoadOptions};
use crate::{EngineError, Result};

/// Writes `model`'s registered images from `images` into `out/images/`, their sparse depth
/// maps into `out/depths/` and `out/transforms.json`. `sharpness` (by image name) is recorded
/// per frame when known. Returns the written resolution of the first camera.
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
    let positions: HashMap<u64, DVec3> = model.points.iter().map(|p| (p.id, p.position)).collect();
    let depths: Vec<Vec<f32>> = frames
        .iter()
        .map(|img| {
            sparse_depth(
                img,
                &model.cameras[&img.camera],
                &scaled[&img.camera],
                &positions,
            )
        })
        .collect();
    // One unit for every map, so the farthest point fits in 16 bits.
    let farthest = depths.iter().flatten().fold(0f32, |m, &d| m.max(d));
    let unit = (farthest as f64 / f64::from(u16::MAX)).max(1e-6);
    let depth_dir = out.join("depths");
    std::fs::create_dir_all(&depth_dir).map_err(|e| EngineError::io(&depth_dir, e))?;
    frames
        .par_iter()
        .zip(&depths)
        .try_for_each(|(img, depth)| {
            let cam = &scaled[&img.camera];
            save_depth_png(
                &out.join(depth_path(img)),
                cam.width,
                cam.height,
                depth,
                unit,
            )
        })?;

    let distorted = scaled
        .values()
        .any(|c| c.distortion.iter().any(|&k| k != 0.0));
    let mut top = Map::new();
    top.insert(
        "camera_model".into(),
        json!(if distorted { "OPENCV" } else { "PINHOLE" }),
    );
    top.insert("depth_unit_scale_factor".into(), json!(unit));
    let single = scaled.len() == 1;
    if single {
        intrinsics(&mut top, scaled.values().next().expect("one camera"));
    }
    let frames: Vec<Value> = frames
        .iter()
        .map(|img| {
            let mut f = Map::new();
            f.insert("file_path".into(), json!(format!("images/{}", img.name)));
            f.insert("depth_file_path".into(), json!(depth_path(img)));
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

/// Where an image's sparse depth map is written, relative to the dataset.
fn depth_path(img: &ColmapImage) -> String {
    format!("depths/{}.png", img.name)
}

/// The z-depth (model units) of each sparse point `img` observes, at the pixel of the
/// `scaled` camera it observes it at (the nearest point where two share a pixel; 0 where none
/// is, and for points behind the camera). `camera` is the model's camera, whose pixels the
/// observations are in.
fn sparse_depth(
    img: &ColmapImage,
    camera: &ColmapCamera,
    scaled: &ColmapCamera,
    positions: &HashMap<u64, DVec3>,
) -> Vec<f32> {
    let (w, h) = (scaled.width as usize, scaled.height as usize);
    let (sx, sy) = (
        scaled.width as f64 / camera.width as f64,
        scaled.height as f64 / camera.height as f64,
    );
    // OpenGL axes: the camera looks down its −z.
    let forward = -img.rotation.z_axis;
    let mut depth = vec![0f32; w * h];
    for o in &img.observations {
        let Some(&p) = positions.get(&o.point) else {
            continue;
        };
        let z = (p - img.position).dot(forward) as f32;
        let (x, y) = ((o.pixel[0] * sx).floor(), (o.pixel[1] * sy).floor());
        if z <= 0.0 || x < 0.0 || y < 0.0 || x >= w as f64 || y >= h as f64 {
            continue;
        }
        let d = &mut depth[y as usize * w + x as usize];
        if *d == 0.0 || z < *d {
            *d = z;
        }
    }
    depth
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

    #[test]
    fn sparse_depth_puts_each_observed_point_at_its_pixel_nearest_first() {
        use super::super::model::Observation;
        let camera = ColmapCamera {
            width: 64,
            height: 48,
            fx: 50.0,
            fy: 50.0,
            cx: 32.0,
            cy: 24.0,
            distortion: [0.0; 4],
        };
        let scaled = scale_camera(&camera, 32);
        assert_eq!((scaled.width, scaled.height), (32, 24));
        // A camera at (1, 0, 0) with OpenGL axes looking down world −z.
        let seen = |pixel, point| Observation { pixel, point };
        let img = ColmapImage {
            name: "a.jpg".into(),
            camera: 1,
            rotation: glam::DMat3::IDENTITY,
            position: DVec3::new(1.0, 0.0, 0.0),
            observations: vec![
                seen([10.5, 20.5], 1),
                seen([11.0, 21.9], 2),
                seen([40.2, 7.7], 3),
                seen([3.0, 3.0], 4),
                seen([5.0, 5.0], 99),
            ],
        };
        let positions = HashMap::from([
            (1, DVec3::new(1.2, 0.1, -3.0)),
            (2, DVec3::new(0.9, 0.0, -2.0)),
            (3, DVec3::new(5.0, 5.0, -7.5)),
            (4, DVec3::new(1.0, 0.0, 2.0)),
        ]);
        let depth = sparse_depth(&img, &camera, &scaled, &positions);
        // Points 1 and 2 share pixel (5, 10) at half size: the nearer (z = 2) is kept.
        assert_eq!(depth[10 * 32 + 5], 2.0);
        assert_eq!(depth[3 * 32 + 20], 7.5);
        // Point 4 is behind the camera and point 99 is not in the model.
        assert_eq!(depth.iter().filter(|&&d| d > 0.0).count(), 2);
    }
}
