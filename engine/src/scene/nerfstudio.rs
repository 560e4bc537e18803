//! nerfstudio (and instant-ngp) `transforms.json`: shared intrinsics at the top level with
//! per-frame overrides, camera-to-world matrices with OpenGL axes, optional explicit splits,
//! optional depth maps, and this project's optional bounds keys (`aabb`, `near`, `far`,
//! `background`). See `docs/SCENES.md` for the keys.

use std::collections::HashMap;
use std::path::Path;

use glam::Vec3;

use super::distortion::Distortion;
use super::frames::{self, DepthSpec, FrameSpec, IntrinsicsSpec, Split};
use super::json::{self, Obj};
use super::SceneFormat;
use super::{bounds, paths, require_split, Aabb, Background, LoadOptions, Scene};
use crate::camera::Intrinsics;
use crate::Result;

/// The file name nerfstudio datasets use.
pub const TRANSFORMS: &str = SceneFormat::Nerfstudio.marker();

/// Default depth scale: 16-bit depth PNGs in millimetres.
const DEFAULT_DEPTH_SCALE: f32 = 1e-3;

/// Loads a nerfstudio `transforms.json`; paths in it are relative to its folder.
pub fn load(file: &Path, opts: &LoadOptions) -> Result<Scene> {
    opts.validate()?;
    let root = paths::canonical_root(paths::parent_dir(file))?;
    let doc = json::parse(file)?;
    let top = Obj::root(file, &doc)?;

    let model = camera_model(&top)?;
    let depth_scale = top
        .opt_f32("depth_unit_scale_factor")?
        .unwrap_or(DEFAULT_DEPTH_SCALE);
    if depth_scale <= 0.0 {
        return Err(top.err("depth_unit_scale_factor", "must be positive"));
    }
    let elements = top.objects("frames")?;
    missing_images(&root, file, &elements)?;
    let specs = elements
        .iter()
        .map(|e| frame_spec(&root, &top, &e.obj(), model, depth_scale))
        .collect::<Result<Vec<_>>>()?;

    let split = split(&top, &specs, opts)?.capped(opts.max_frames);
    require_split(&split, opts, file, "frames")?;

    let poses: Vec<(Vec3, Vec3)> = specs
        .iter()
        .map(|s| (s.position, -s.rotation.z_axis))
        .collect();
    let stated_aabb = top.opt_matrix("aabb")?;
    let aabb = match &stated_aabb {
        Some(rows) => aabb(rows).map_err(|r| top.err("aabb", r))?,
        None => bounds::estimate_aabb(&poses),
    };
    let background = match top.opt_vec3("background")? {
        Some(bg) if bg.min_element() < 0.0 || bg.max_element() > 1.0 => {
            return Err(top.err("background", "components must be in [0, 1]"))
        }
        bg => {
            let first = split.train.first().map(|&i| specs[i].image.as_path());
            let alpha = first.is_some_and(super::images::has_alpha);
            opts.background_or(bg.map(|v| v.to_array()), alpha)
        }
    };
    // Photos of a real background with no stated box: the surroundings go on past any box.
    let unbounded = background == Background::Learned && stated_aabb.is_none();
    let (near_default, far_default) = if unbounded {
        bounds::near_far_unbounded(&poses, &aabb)
    } else {
        bounds::near_far(&poses, &aabb)
    };
    let near = top.opt_f32("near")?.unwrap_or(near_default);
    let far = top.opt_f32("far")?.unwrap_or(far_default);
    if near < 0.0 || far <= near {
        return Err(top.err(
            if top.has("far") { "far" } else { "near" },
            format!("need 0 ≤ near < far, found near {near}, far {far}"),
        ));
    }

    let (frames, split) = frames::load(specs, split, opts, background.alpha_colour())?;
    Ok(Scene {
        root,
        frames,
        train: split.train,
        test: split.test,
        aabb,
        near,
        far,
        ndc: None,
        unbounded,
        background,
    })
}

/// One error naming every frame whose image file is missing (published captures often list
/// frames whose images were dropped), instead of failing on the first.
fn missing_images(root: &Path, file: &Path, frames: &[json::Element]) -> Result<()> {
    let mut missing = Vec::new();
    for (i, e) in frames.iter().enumerate() {
        if let Ok(rel) = e.obj().str("file_path") {
            // Paths that leave the folder get their own error from `paths::resolve`.
            let inside = Path::new(rel).is_relative() && !rel.split('/').any(|c| c == "..");
            if inside && !rel.is_empty() && !root.join(rel).exists() {
                missing.push(format!("{rel} (frames[{i}])"));
            }
        }
    }
    match missing.len() {
        0 | 1 => Ok(()), // one missing file gets the precise per-frame error
        n => {
            const SHOWN: usize = 20;
            let more = n.saturating_sub(SHOWN);
            let mut list = missing[..n.min(SHOWN)].join(", ");
            if more > 0 {
                list.push_str(&format!(" and {more} more"));
            }
            Err(crate::EngineError::dataset(
                file,
                "frames[].file_path",
                format!(
                    "{n} of {} frames name an image that does not exist: {list}",
                    frames.len()
                ),
            ))
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Model {
    Pinhole,
    SimplePinhole,
    OpenCv,
    /// No `camera_model` key (instant-ngp files): pinhole plus any distortion given.
    Unspecified,
}

fn camera_model(top: &Obj) -> Result<Model> {
    match top.opt_str("camera_model")? {
        None => Ok(Model::Unspecified),
        Some("PINHOLE") => Ok(Model::Pinhole),
        Some("SIMPLE_PINHOLE") => Ok(Model::SimplePinhole),
        Some("OPENCV") => Ok(Model::OpenCv),
        Some(other) => Err(top.err(
            "camera_model",
            format!(
                "unsupported camera model `{other}`: supported are PINHOLE, SIMPLE_PINHOLE and \
                 OPENCV (fisheye and equirectangular cameras are not)"
            ),
        )),
    }
}

/// A value from the frame, else from the top level, with the field it came from.
fn lookup(top: &Obj, frame: &Obj, key: &str) -> Result<Option<(f32, String)>> {
    if let Some(v) = frame.opt_f32(key)? {
        return Ok(Some((v, frame.field(key))));
    }
    Ok(top.opt_f32(key)?.map(|v| (v, top.field(key))))
}

fn dim(top: &Obj, frame: &Obj, key: &str) -> Result<(u32, String)> {
    if let Some(v) = frame.opt_dim(key)? {
        return Ok((v, frame.field(key)));
    }
    match top.opt_dim(key)? {
        Some(v) => Ok((v, top.field(key))),
        None => Err(top.err(
            key,
            "missing required field (set it at the top level or in every frame)",
        )),
    }
}

fn frame_spec(
    root: &Path,
    top: &Obj,
    frame: &Obj,
    model: Model,
    depth_scale: f32,
) -> Result<FrameSpec> {
    let file = top.file();
    let rel = frame.str("file_path")?;
    let image = paths::resolve(root, rel, file, &frame.field("file_path"))?;

    let (width, w_field) = dim(top, frame, "w")?;
    let (height, h_field) = dim(top, frame, "h")?;
    let (fx, fx_field) = match lookup(top, frame, "fl_x")? {
        Some(v) => v,
        None => match lookup(top, frame, "camera_angle_x")? {
            Some((angle, field)) => (0.5 * width as f32 / (0.5 * angle).tan(), field),
            None => {
                return Err(top.err(
                    "fl_x",
                    "missing required field (set it at the top level or in every frame)",
                ))
            }
        },
    };
    let (fy, fy_field) = match lookup(top, frame, "fl_y")? {
        Some(v) if model != Model::SimplePinhole => v,
        _ => (fx, fx_field.clone()),
    };
    for (f, field) in [(fx, &fx_field), (fy, &fy_field)] {
        if f.is_nan() || f <= 0.0 {
            return Err(crate::EngineError::dataset(
                file,
                field.as_str(),
                format!("focal length must be positive, found {f}"),
            ));
        }
    }
    let cx = lookup(top, frame, "cx")?.map_or(0.5 * width as f32, |v| v.0);
    let cy = lookup(top, frame, "cy")?.map_or(0.5 * height as f32, |v| v.0);
    let distortion = distortion(top, frame, model)?;

    let rows = frame.matrix("transform_matrix")?;
    let (rotation, position) =
        frames::c2w_pose(&rows).map_err(|r| frame.err("transform_matrix", r))?;
    frames::check_pose(rotation, position, |r| frame.err("transform_matrix", r))?;

    let depth = frame
        .opt_str("depth_file_path")?
        .map(|rel| {
            let field = frame.field("depth_file_path");
            paths::resolve(root, rel, file, &field).map(|path| DepthSpec {
                path,
                field,
                scale: depth_scale,
            })
        })
        .transpose()?;

    Ok(FrameSpec {
        name: rel.to_string(),
        image,
        source: file.to_path_buf(),
        field: frame.field("file_path"),
        rotation,
        position,
        intrinsics: IntrinsicsSpec::Known {
            k: Intrinsics {
                fx,
                fy,
                cx,
                cy,
                width,
                height,
            },
            distortion,
            size_field: if frame.has("w") || frame.has("h") {
                format!("{w_field}, {h_field}")
            } else {
                "w, h".into()
            },
        },
        depth,
    })
}

fn distortion(top: &Obj, frame: &Obj, model: Model) -> Result<Distortion> {
    let get = |key| Ok::<_, crate::EngineError>(lookup(top, frame, key)?.map_or(0.0, |v| v.0));
    let d = Distortion {
        k1: get("k1")?,
        k2: get("k2")?,
        k3: get("k3")?,
        k4: get("k4")?,
        p1: get("p1")?,
        p2: get("p2")?,
    };
    if !d.is_identity() && matches!(model, Model::Pinhole | Model::SimplePinhole) {
        let key = ["k1", "k2", "k3", "k4", "p1", "p2"]
            .into_iter()
            .find(|k| get(k).is_ok_and(|v| v != 0.0))
            .unwrap_or("k1");
        let field = if frame.has(key) {
            frame.field(key)
        } else {
            top.field(key)
        };
        return Err(crate::EngineError::dataset(
            top.file(),
            field,
            "non-zero distortion with a PINHOLE camera_model: set camera_model to OPENCV to \
             have the images undistorted",
        ));
    }
    Ok(d)
}

/// The `aabb` key: `[[min x, y, z], [max x, y, z]]`.
fn aabb(rows: &[Vec<f32>]) -> Result<Aabb, String> {
    let [min, max] = rows else {
        return Err(format!(
            "expected [[min x, y, z], [max x, y, z]], found {} rows",
            rows.len()
        ));
    };
    let (min, max) = match (min.as_slice(), max.as_slice()) {
        ([a, b, c], [d, e, f]) => (Vec3::new(*a, *b, *c), Vec3::new(*d, *e, *f)),
        _ => return Err("expected [[min x, y, z], [max x, y, z]]".into()),
    };
    if min.cmpge(max).any() {
        return Err(format!("min {min} must be below max {max} on every axis"));
    }
    Ok(Aabb { min, max })
}

/// The train/test split: explicit filename lists when present (`test_filenames`, else
/// `val_filenames`; frames in no list are not loaded, and without a test list every frame not
/// in `train_filenames` is test), otherwise every `test_every`-th frame.
fn split(top: &Obj, specs: &[FrameSpec], opts: &LoadOptions) -> Result<Split> {
    let train_list = top.opt_str_list("train_filenames")?;
    let (test_key, test_list) = match top.opt_str_list("test_filenames")? {
        Some(list) => ("test_filenames", Some(list)),
        None => ("val_filenames", top.opt_str_list("val_filenames")?),
    };
    if train_list.is_none() && test_list.is_none() {
        return Ok(Split::every_nth(specs.len(), opts.test_every));
    }
    let index: HashMap<String, usize> = specs
        .iter()
        .enumerate()
        .map(|(i, s)| (paths::same_name_key(&s.name), i))
        .collect();
    let lookup = |key: &str, list: &[&str]| -> Result<Vec<usize>> {
        list.iter()
            .enumerate()
            .map(|(i, name)| {
                index
                    .get(&paths::same_name_key(name))
                    .copied()
                    .ok_or_else(|| {
                        top.err(
                            &format!("{key}[{i}]"),
                            format!("`{name}` is not the file_path of any frame"),
                        )
                    })
            })
            .collect()
    };
    let train = train_list
        .as_deref()
        .map(|l| lookup("train_filenames", l))
        .transpose()?;
    let test = test_list
        .as_deref()
        .map(|l| lookup(test_key, l))
        .transpose()?;
    let complement = |of: &[usize]| (0..specs.len()).filter(|i| !of.contains(i)).collect();
    let (train, test) = match (train, test) {
        (Some(train), Some(test)) => (train, test),
        (Some(train), None) => {
            let test = complement(&train);
            (train, test)
        }
        (None, test) => {
            let test = test.unwrap_or_default();
            (complement(&test), test)
        }
    };
    if opts.test_every == 0 {
        return Ok(Split {
            train,
            test: vec![],
        });
    }
    if train.is_empty() {
        return Err(top.err("train_filenames", "the training split is empty"));
    }
    if test.is_empty() {
        return Err(top.err(test_key, "the test split is empty"));
    }
    Ok(Split { train, test })
}
