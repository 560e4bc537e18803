//! NeRF-synthetic ("Blender") datasets: `transforms_{train,val,test}.json`, each with a
//! horizontal field of view `camera_angle_x` and frames whose `file_path` omits the `.png`
//! extension; RGBA images composited on the background. Bounds are the ones the NeRF code
//! uses for these scenes: the cube [-1.5, 1.5]³, near 2, far 6.

use std::path::Path;

use glam::Vec3;

use super::frames::{self, FrameSpec, IntrinsicsSpec, Split};
use super::json::{self, Obj};
use super::SceneFormat;
use super::{paths, require_split, Aabb, LoadOptions, Scene};
use crate::Result;

pub const TRAIN: &str = SceneFormat::Blender.marker();
pub const VAL: &str = "transforms_val.json";
pub const TEST: &str = "transforms_test.json";

const HALF_EXTENT: f32 = 1.5;
const NEAR: f32 = 2.0;
const FAR: f32 = 6.0;

/// Loads a NeRF-synthetic dataset folder. The test split is `transforms_test.json`, or
/// `transforms_val.json` when there is no test file; `test_every` = 0 skips it.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Scene> {
    opts.validate()?;
    let root = paths::canonical_root(dir)?;
    let train_file = root.join(TRAIN);
    let mut specs = split_specs(&root, &train_file)?;
    let n_train = specs.len();
    let test_file = [TEST, VAL]
        .map(|name| root.join(name))
        .into_iter()
        .find(|p| p.is_file())
        .filter(|_| opts.test_every > 0);
    if let Some(test_file) = &test_file {
        specs.extend(split_specs(&root, test_file)?);
    }
    let split = Split {
        train: (0..n_train).collect(),
        test: (n_train..specs.len()).collect(),
    }
    .capped(opts.max_frames);
    let split_file = test_file.as_deref().unwrap_or(&train_file);
    require_split(&split, opts, split_file, "frames")?;

    // NeRF-synthetic images are RGBA renders on a transparent background.
    let background = opts.background_or(None, true);
    let (frames, split) = frames::load(specs, split, opts, background.alpha_colour())?;
    Ok(Scene {
        root,
        frames,
        train: split.train,
        test: split.test,
        aabb: Aabb {
            min: Vec3::splat(-HALF_EXTENT),
            max: Vec3::splat(HALF_EXTENT),
        },
        near: NEAR,
        far: FAR,
        ndc: None,
        unbounded: false,
        background,
    })
}

/// The frames of one `transforms_<split>.json`.
fn split_specs(root: &Path, file: &Path) -> Result<Vec<FrameSpec>> {
    let doc = json::parse(file)?;
    let top = Obj::root(file, &doc)?;
    let angle = top.f32("camera_angle_x")?;
    if !(angle > 0.0 && angle < std::f32::consts::PI) {
        return Err(top.err(
            "camera_angle_x",
            format!("field of view must be in (0, π) radians, found {angle}"),
        ));
    }
    top.objects("frames")?
        .iter()
        .map(|e| {
            let frame = e.obj();
            let rel = frame.str("file_path")?;
            let name = with_extension(rel);
            let field = frame.field("file_path");
            let image = paths::resolve(root, &name, file, &field)?;
            let rows = frame.matrix("transform_matrix")?;
            let (rotation, position) =
                frames::c2w_pose(&rows).map_err(|r| frame.err("transform_matrix", r))?;
            frames::check_pose(rotation, position, |r| frame.err("transform_matrix", r))?;
            Ok(FrameSpec {
                name,
                image,
                source: file.to_path_buf(),
                field,
                rotation,
                position,
                intrinsics: IntrinsicsSpec::FovX(angle),
                depth: None,
            })
        })
        .collect()
}

/// Blender datasets name images without their extension; add `.png` unless one is there.
fn with_extension(rel: &str) -> String {
    if crate::image_io::has_image_extension(Path::new(rel)) {
        rel.to_string()
    } else {
        format!("{rel}.png")
    }
}
