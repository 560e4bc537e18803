//! Procedural test scenes: a small ray tracer that renders a textured table-top world (a
//! checkered floor square with spheres, boxes, a cylinder and a torus, hard shadows) on a
//! solid colour, under a sky at infinity or inside a room, from a ring of cameras or a
//! forward-facing grid, and writes it as a nerfstudio dataset with ground-truth depth (plus
//! LLFF `poses_bounds.npy` for the forward-facing kind).
//!
//! Output is a pure function of [`GenerateOptions`]: the same options give the same bytes.

mod shapes;
mod textures;
mod world;

use std::path::Path;

use glam::Vec3;
use image::RgbImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use super::npy::{self, Matrix};
use super::{bounds, Aabb};
use crate::camera::{Camera, Intrinsics};
use crate::image_io::save_depth_png;
use crate::{EngineError, Result};
pub use world::Surroundings;
use world::{View, World, BACKGROUND};

/// Where the cameras are.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraRig {
    /// 360°: a spiral over the hemisphere band between 15° and 55° elevation, every camera
    /// looking at the scene centre; consecutive frames are neighbours.
    Orbit,
    /// Forward-facing: a grid of cameras in a plane in front of the scene, all looking the
    /// same way (also written as LLFF).
    Forward,
    /// One turn around the subject with the height swaying between 20° and 40° elevation, as a
    /// phone walked once around it films: consecutive frames overlap closely (what structure
    /// from motion needs; a constant height would be a critical motion for self-calibration).
    Turntable,
}

/// What to generate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GenerateOptions {
    pub rig: CameraRig,
    /// Width and height of the images in pixels.
    pub size: u32,
    /// Number of views.
    pub views: usize,
    /// Seed of the layout, colours, patterns and light.
    pub seed: u64,
    /// What surrounds the table-top. Only `plain` states its background (and every kind but
    /// `room` its box) in the dataset, as a capture of an object on a known backdrop would.
    pub surroundings: Surroundings,
}

impl Default for GenerateOptions {
    fn default() -> Self {
        Self {
            rig: CameraRig::Orbit,
            size: 128,
            views: 48,
            seed: 7,
            surroundings: Surroundings::Plain,
        }
    }
}

/// The box all generated content lies in.
pub const AABB: Aabb = Aabb {
    min: Vec3::splat(-1.0),
    max: Vec3::splat(1.0),
};

/// Samples per pixel along each axis (3×3 supersampling; odd so the centre sample exists).
const SUPERSAMPLE: u32 = 3;
/// Where the orbit cameras look, and their distance from it.
const ORBIT_TARGET: Vec3 = Vec3::new(0.0, -0.3, 0.0);
const ORBIT_RADIUS: f32 = 2.7;
const ORBIT_FOV_X: f32 = 48.0;
const ORBIT_TURNS: f32 = 3.0;
const FORWARD_FOV_X: f32 = 55.0;

/// Generates a dataset into `out`, which must be missing or empty.
pub fn generate(opts: &GenerateOptions, out: &Path) -> Result<()> {
    if !(8..=4096).contains(&opts.size) {
        return Err(EngineError::config(
            "size",
            format!("{} is not in 8..=4096", opts.size),
        ));
    }
    if !(2..=10_000).contains(&opts.views) {
        return Err(EngineError::config(
            "views",
            format!("{} is not in 2..=10000", opts.views),
        ));
    }
    if std::fs::read_dir(out).is_ok_and(|mut entries| entries.next().is_some()) {
        return Err(EngineError::config(
            "out",
            format!("{} is not empty; choose a new folder", out.display()),
        ));
    }
    for dir in ["images", "depths"] {
        std::fs::create_dir_all(out.join(dir)).map_err(|e| EngineError::io(out.join(dir), e))?;
    }

    let world = World::new(opts.seed, opts.surroundings);
    let cameras = match opts.rig {
        CameraRig::Orbit => orbit(opts.size, opts.views),
        CameraRig::Forward => forward(opts.size, opts.views),
        CameraRig::Turntable => turntable(opts.size, opts.views),
    };
    let poses: Vec<bounds::Pose> = cameras.iter().map(|c| (c.position, c.forward())).collect();
    let (near, far) = bounds::near_far(&poses, &AABB);
    // Finest depth unit that fits every depth in 16 bits (the room's walls are farther).
    let depth_scale = if far < 6.5 && !opts.surroundings.is_room() {
        1e-4
    } else {
        1e-3
    };

    let views: Vec<View> = cameras
        .par_iter()
        .enumerate()
        .map(|(i, camera)| {
            let view = world.render(camera, SUPERSAMPLE);
            write_view(out, i, camera, &view, depth_scale)?;
            Ok(view)
        })
        .collect::<Result<_>>()?;

    let k = cameras[0].intrinsics;
    let frames: Vec<Value> = cameras
        .iter()
        .enumerate()
        .map(|(i, c)| {
            json!({
                "file_path": format!("images/{}", frame_name(i)),
                "depth_file_path": format!("depths/{}", frame_name(i)),
                "transform_matrix": c.c2w_rows().map(|row| row.map(num)),
            })
        })
        .collect();
    let mut transforms = json!({
        "camera_model": "PINHOLE",
        "fl_x": num(k.fx),
        "fl_y": num(k.fy),
        "cx": num(k.cx),
        "cy": num(k.cy),
        "w": k.width,
        "h": k.height,
        "depth_unit_scale_factor": depth_scale,
        "generator": {
            "rig": opts.rig,
            "seed": opts.seed,
            "views": opts.views,
            "size": opts.size,
            "surroundings": opts.surroundings,
        },
        "frames": frames,
    });
    let keys = transforms.as_object_mut().expect("a JSON object");
    if !opts.surroundings.is_room() {
        keys.insert(
            "aabb".into(),
            json!([AABB.min.to_array().map(num), AABB.max.to_array().map(num)]),
        );
        keys.insert("near".into(), num(near));
        keys.insert("far".into(), num(far));
    }
    if opts.surroundings == Surroundings::Plain {
        keys.insert("background".into(), json!(BACKGROUND.to_array().map(num)));
    }
    let path = out.join(super::nerfstudio::TRANSFORMS);
    let text = serde_json::to_string_pretty(&transforms).expect("JSON values serialise");
    std::fs::write(&path, text + "\n").map_err(|e| EngineError::io(&path, e))?;

    if opts.rig == CameraRig::Forward {
        write_poses_bounds(&out.join(super::llff::POSES_BOUNDS), &cameras, &views)?;
    }
    Ok(())
}

fn frame_name(i: usize) -> String {
    format!("frame_{i:05}.png")
}

/// A JSON number with the shortest decimal spelling of the f32.
fn num(x: f32) -> Value {
    json!(x
        .to_string()
        .parse::<f64>()
        .expect("f32 display parses as f64"))
}

fn intrinsics(size: u32, fov_x_degrees: f32) -> Intrinsics {
    let f = 0.5 * size as f32 / (0.5 * fov_x_degrees.to_radians()).tan();
    Intrinsics {
        fx: f,
        fy: f,
        cx: 0.5 * size as f32,
        cy: 0.5 * size as f32,
        width: size,
        height: size,
    }
}

fn orbit(size: u32, views: usize) -> Vec<Camera> {
    (0..views)
        .map(|i| {
            let along = i as f32 / (views - 1) as f32;
            let azimuth = std::f32::consts::TAU * ORBIT_TURNS * i as f32 / views as f32;
            orbit_camera(size, 15.0 + 40.0 * along, azimuth)
        })
        .collect()
}

fn turntable(size: u32, views: usize) -> Vec<Camera> {
    (0..views)
        .map(|i| {
            let azimuth = std::f32::consts::TAU * i as f32 / views as f32;
            orbit_camera(size, 30.0 + 10.0 * (2.0 * azimuth).sin(), azimuth)
        })
        .collect()
}

/// A camera on the orbit sphere at `elevation` degrees and `azimuth` radians, looking at the
/// orbit's target.
fn orbit_camera(size: u32, elevation: f32, azimuth: f32) -> Camera {
    let elevation = elevation.to_radians();
    let dir = Vec3::new(
        elevation.cos() * azimuth.cos(),
        elevation.sin(),
        elevation.cos() * azimuth.sin(),
    );
    let k = intrinsics(size, ORBIT_FOV_X);
    Camera::look_at(k, ORBIT_TARGET + ORBIT_RADIUS * dir, ORBIT_TARGET, Vec3::Y)
}

/// A grid of parallel cameras in the plane z = 1.9, visited row by row in serpentine order.
fn forward(size: u32, views: usize) -> Vec<Camera> {
    let k = intrinsics(size, FORWARD_FOV_X);
    let cols = ((1.5 * views as f32).sqrt().ceil() as usize).clamp(2, views);
    let rows = views.div_ceil(cols);
    let centre = Vec3::new(0.0, 0.55, 1.9);
    let look = Camera::look_at(k, centre, Vec3::new(0.0, -0.55, -0.1), Vec3::Y);
    let spread = |i: usize, n: usize| {
        if n > 1 {
            i as f32 / (n - 1) as f32 - 0.5
        } else {
            0.0
        }
    };
    (0..views)
        .map(|i| {
            let (row, mut col) = (i / cols, i % cols);
            if row % 2 == 1 {
                col = cols - 1 - col;
            }
            let offset = Vec3::new(0.7 * spread(col, cols), 0.2 * spread(row, rows), 0.0);
            Camera {
                position: centre + offset,
                ..look
            }
        })
        .collect()
}

fn write_view(out: &Path, i: usize, camera: &Camera, view: &View, depth_scale: f32) -> Result<()> {
    let (w, h) = (camera.intrinsics.width, camera.intrinsics.height);
    let bytes = view.rgb.iter().map(|v| (v * 255.0).round() as u8).collect();
    let rgb = RgbImage::from_raw(w, h, bytes).expect("buffer matches the image size");
    let rgb_path = out.join("images").join(frame_name(i));
    rgb.save(&rgb_path)
        .map_err(|e| EngineError::artifact(&rgb_path, e.to_string()))?;
    let depth_path = out.join("depths").join(frame_name(i));
    save_depth_png(&depth_path, w, h, &view.depth, f64::from(depth_scale))
}

/// LLFF `poses_bounds.npy`: [down, right, back, position, (h, w, f)] rows and per-view
/// near/far taken from the ground-truth depth.
fn write_poses_bounds(path: &Path, cameras: &[Camera], views: &[View]) -> Result<()> {
    let mut data = Vec::with_capacity(cameras.len() * 17);
    for (c, v) in cameras.iter().zip(views) {
        let r = c.rotation;
        let k = c.intrinsics;
        let cols = [-r.y_axis, r.x_axis, r.z_axis, c.position];
        let hwf = [k.height as f32, k.width as f32, k.fx];
        for i in 0..3 {
            data.extend(cols.iter().map(|col| col[i] as f64));
            data.push(hwf[i] as f64);
        }
        let hits = v.depth.iter().copied().filter(|&d| d > 0.0);
        let near = hits.clone().fold(f32::INFINITY, f32::min);
        let far = hits.fold(0.0, f32::max);
        data.extend([0.9 * near as f64, 1.1 * far as f64]);
    }
    npy::write_matrix(
        path,
        &Matrix {
            rows: cameras.len(),
            cols: 17,
            data,
        },
    )
}
