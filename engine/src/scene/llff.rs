//! LLFF forward-facing datasets: `poses_bounds.npy` (N×17: a 3×5 matrix per image holding the
//! camera-to-world rotation with [down, right, back] columns, the position and (height,
//! width, focal), then the near and far scene depths) and the images in `images/`, sorted by
//! name, or in `images_<factor>/` when downscaling and that folder exists.
//!
//! As in the NeRF code: poses are converted to [right, up, back] (OpenGL) columns, the scene
//! is scaled so that the nearest depth is 1 / 0.75, poses are re-centred on their average,
//! and rays are taken to NDC with the near plane at 1, so rays span t ∈ [0, 1] and the field
//! lives in NDC space: z in [-1, 1], and x, y in [-1, 1] widened to what off-centre cameras
//! see.

use std::path::Path;

use glam::{Mat3, Vec3};

use super::distortion::Distortion;
use super::frames::{self, FrameSpec, IntrinsicsSpec, Split};
use super::SceneFormat;
use super::{npy, paths, require_split, Aabb, LoadOptions, Scene};
use crate::camera::{Camera, Intrinsics, Ndc};
use crate::{EngineError, Result};

pub const POSES_BOUNDS: &str = SceneFormat::Llff.marker();

/// NeRF's `bd_factor`: after rescaling, the nearest scene depth is 1 / 0.75.
const BD_FACTOR: f32 = 0.75;

/// One row of `poses_bounds.npy`, converted to OpenGL axes.
struct Row {
    rotation: Mat3,
    position: Vec3,
    height: f32,
    width: f32,
    focal: f32,
    near: f32,
}

/// Loads an LLFF dataset folder as an NDC scene; every `test_every`-th image is test.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Scene> {
    opts.validate()?;
    let root = paths::canonical_root(dir)?;
    let file = root.join(POSES_BOUNDS);
    let mut rows = read_rows(&file)?;
    normalise(&mut rows).map_err(|reason| EngineError::dataset(&file, "poses", reason))?;

    let factor = opts.downscale;
    let minified = format!("images_{factor}");
    let (folder, rest) = if factor > 1 && root.join(&minified).is_dir() {
        (minified, 1)
    } else {
        ("images".to_string(), factor)
    };
    let names = list_images(&root, &folder)?;
    if names.len() != rows.len() {
        return Err(EngineError::dataset(
            &file,
            "shape",
            format!(
                "{} poses but {} images in {folder}/",
                rows.len(),
                names.len()
            ),
        ));
    }
    let image_dir = root.join(&folder);
    let shrink = (folder != "images").then_some(factor);
    let (specs, intrinsics): (Vec<FrameSpec>, Vec<Intrinsics>) = rows
        .iter()
        .zip(&names)
        .enumerate()
        .map(|(i, (row, name))| frame_spec(&root, &file, &image_dir, i, row, name, shrink))
        .collect::<Result<Vec<_>>>()?
        .into_iter()
        .unzip();

    let split = Split::every_nth(specs.len(), opts.test_every).capped(opts.max_frames);
    require_split(&split, opts, &file, "shape")?;
    let first = intrinsics[0].scaled(1.0 / rest as f32);
    let ndc = Ndc {
        fx: first.fx,
        fy: first.fy,
        width: first.width,
        height: first.height,
        near: 1.0,
    };
    let aabb = ndc_aabb(
        &ndc,
        rows.iter().zip(&intrinsics).map(|(row, k)| Camera {
            intrinsics: *k,
            rotation: row.rotation,
            position: row.position,
        }),
    );
    // Forward-facing photos: NDC already reaches infinity; what no content explains is learned.
    let background = opts.background_or(None, false);
    let load_opts = LoadOptions {
        downscale: rest,
        ..opts.clone()
    };
    let (frames, split) = frames::load(specs, split, &load_opts, background.alpha_colour())?;
    Ok(Scene {
        root,
        frames,
        train: split.train,
        test: split.test,
        aabb,
        near: 0.0,
        far: 1.0,
        ndc: Some(ndc),
        unbounded: false,
        background,
    })
}

/// The NDC box every camera sees into past the nearest content: the hull of the cameras'
/// corner rays between the depth of the nearest scene bound (with a 10% margin) and infinity
/// (t = 1). It extends past [-1, 1] in x and y for cameras away from the average pose; z
/// stays [-1, 1].
fn ndc_aabb(ndc: &Ndc, cameras: impl Iterator<Item = Camera>) -> Aabb {
    let mut aabb = Aabb {
        min: Vec3::splat(-1.0),
        max: Vec3::splat(1.0),
    };
    for camera in cameras {
        let (w, h) = (
            camera.intrinsics.width as f32,
            camera.intrinsics.height as f32,
        );
        for (u, v) in [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)] {
            let (o, d) = ndc.ray(&camera.ray(u, v));
            for p in [o, o + d] {
                if p.is_finite() {
                    aabb.min = aabb.min.min(p);
                    aabb.max = aabb.max.max(p);
                }
            }
        }
    }
    aabb.min.z = -1.0;
    aabb.max.z = 1.0;
    aabb
}

fn read_rows(file: &Path) -> Result<Vec<Row>> {
    let m = npy::read_matrix(file)?;
    if m.cols != 17 || m.rows == 0 {
        return Err(EngineError::dataset(
            file,
            "shape",
            format!(
                "expected N×17 (a 3×5 pose-and-hwf matrix and near, far per image), found {}×{}",
                m.rows, m.cols
            ),
        ));
    }
    (0..m.rows)
        .map(|r| {
            let v = m.row(r);
            let err = |what: &str, reason: String| {
                EngineError::dataset(file, format!("row {r} ({what})"), reason)
            };
            if let Some(c) = v.iter().position(|x| !x.is_finite()) {
                return Err(err("values", format!("column {c} is {}", v[c])));
            }
            let at = |i: usize, j: usize| v[i * 5 + j] as f32;
            let col = |j: usize| Vec3::new(at(0, j), at(1, j), at(2, j));
            let (height, width, focal) = (at(0, 4), at(1, 4), at(2, 4));
            if height < 1.0 || width < 1.0 || focal <= 0.0 {
                return Err(err(
                    "height, width, focal",
                    format!("must be positive, found {height}, {width}, {focal}"),
                ));
            }
            let (near, far) = (v[15] as f32, v[16] as f32);
            if near <= 0.0 || far <= near {
                return Err(err(
                    "near, far",
                    format!("need 0 < near < far, found {near}, {far}"),
                ));
            }
            // [down, right, back] → [right, up, back].
            let rotation = Mat3::from_cols(col(1), -col(0), col(2));
            let position = col(3);
            frames::check_pose(rotation, position, |reason| err("pose", reason))?;
            Ok(Row {
                rotation,
                position,
                height,
                width,
                focal,
                near,
            })
        })
        .collect()
}

/// Scales the scene so that the nearest depth is 1 / `BD_FACTOR` and re-centres the poses on
/// their average pose.
fn normalise(rows: &mut [Row]) -> Result<(), String> {
    let min_near = rows.iter().map(|r| r.near).fold(f32::INFINITY, f32::min);
    let scale = 1.0 / (min_near * BD_FACTOR);
    let n = rows.len() as f32;
    let centre = rows.iter().map(|r| r.position).sum::<Vec3>() * scale / n;
    let back = rows
        .iter()
        .map(|r| r.rotation.z_axis)
        .sum::<Vec3>()
        .normalize();
    let up = rows.iter().map(|r| r.rotation.y_axis).sum::<Vec3>();
    let right = up.cross(back).normalize();
    let avg = Mat3::from_cols(right, back.cross(right).normalize(), back);
    if !avg.is_finite() {
        return Err(
            "no average pose: the cameras' mean up and viewing directions are parallel".into(),
        );
    }
    let inv = avg.transpose();
    for r in rows {
        r.rotation = inv * r.rotation;
        r.position = inv * (r.position * scale - centre);
    }
    Ok(())
}

/// Image files of `folder`, sorted by name.
fn list_images(root: &Path, folder: &str) -> Result<Vec<String>> {
    let dir = root.join(folder);
    let entries = std::fs::read_dir(&dir).map_err(|e| {
        EngineError::dataset(&dir, "images", format!("cannot list the image folder: {e}"))
    })?;
    let mut names = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| EngineError::io(&dir, e))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if crate::image_io::has_image_extension(Path::new(&name)) {
            names.push(name);
        }
    }
    names.sort();
    Ok(names)
}

fn frame_spec(
    root: &Path,
    file: &Path,
    image_dir: &Path,
    index: usize,
    row: &Row,
    name: &str,
    shrink: Option<u32>,
) -> Result<(FrameSpec, Intrinsics)> {
    let folder = image_dir.file_name().unwrap_or_default().to_string_lossy();
    let rel = format!("{folder}/{name}");
    let image = paths::resolve(root, &rel, image_dir, name)?;
    let (w, h) = image::image_dimensions(&image).map_err(|e| {
        EngineError::dataset(image_dir, name, format!("cannot read the image: {e}"))
    })?;
    // images_<factor>/ were shrunk by other tools, which round either way.
    let (ew, eh) = match shrink {
        Some(f) => (row.width / f as f32, row.height / f as f32),
        None => (row.width, row.height),
    };
    let tolerance = if shrink.is_some() { 1.0 } else { 0.0 };
    if (w as f32 - ew).abs() > tolerance || (h as f32 - eh).abs() > tolerance {
        return Err(EngineError::dataset(
            file,
            format!("row {index} (height, width)"),
            format!("image {rel} is {w}×{h} but the pose says {ew}×{eh}"),
        ));
    }
    let k = Intrinsics {
        fx: row.focal * w as f32 / row.width,
        fy: row.focal * h as f32 / row.height,
        cx: 0.5 * w as f32,
        cy: 0.5 * h as f32,
        width: w,
        height: h,
    };
    let spec = FrameSpec {
        name: rel,
        image,
        source: image_dir.to_path_buf(),
        field: name.to_string(),
        rotation: row.rotation,
        position: row.position,
        intrinsics: IntrinsicsSpec::Known {
            k,
            distortion: Distortion::default(),
            size_field: format!("{name} (size)"),
        },
        depth: None,
    };
    Ok((spec, k))
}
