//! The part of loading every format shares: frame descriptions (pose, intrinsics, files),
//! pose validation, the train/test split, and decoding the selected frames in parallel
//! (undistort, then downscale).

use std::path::PathBuf;

use glam::{Mat3, Vec3};
use rayon::prelude::*;

use super::distortion::Distortion;
use super::images::{self, Origin};
use super::{Frame, LoadOptions};
use crate::camera::{Camera, Intrinsics};
use crate::{EngineError, Result};

/// A frame as described by the dataset, before its image is read.
pub(crate) struct FrameSpec {
    /// Path relative to the dataset folder as written there.
    pub name: String,
    /// Resolved image file.
    pub image: PathBuf,
    /// The file describing the frame and the field naming its image, for messages.
    pub source: PathBuf,
    pub field: String,
    pub rotation: Mat3,
    pub position: Vec3,
    pub intrinsics: IntrinsicsSpec,
    pub depth: Option<DepthSpec>,
}

/// How a frame's intrinsics are known.
pub(crate) enum IntrinsicsSpec {
    /// Given in full; the image must have exactly this size. `size_field` names where the
    /// size was given, for messages.
    Known {
        k: Intrinsics,
        distortion: Distortion,
        size_field: String,
    },
    /// Only the horizontal field of view (radians); the size comes from the image, the
    /// principal point is the image centre and fy = fx.
    FovX(f32),
}

/// A ground-truth depth map: a 16-bit PNG holding depth / `scale`.
pub(crate) struct DepthSpec {
    pub path: PathBuf,
    pub field: String,
    pub scale: f32,
}

/// Checks a camera-to-world rotation and position: finite, and a proper rotation.
pub(crate) fn check_pose(
    rotation: Mat3,
    position: Vec3,
    err: impl Fn(String) -> EngineError,
) -> Result<()> {
    if !(rotation.is_finite() && position.is_finite()) {
        return Err(err("the pose contains NaN or infinite values".into()));
    }
    let off = (rotation.transpose() * rotation - Mat3::IDENTITY).abs();
    let worst = off.x_axis.max(off.y_axis).max(off.z_axis).max_element();
    if worst > 1e-2 || rotation.determinant() <= 0.0 {
        return Err(err(format!(
            "the rotation part is not a rotation (|RᵀR − I| = {worst:.3}, det = {:.3})",
            rotation.determinant()
        )));
    }
    Ok(())
}

/// Rotation and position of a row-major 3×4 or 4×4 camera-to-world matrix.
pub(crate) fn c2w_pose(rows: &[Vec<f32>]) -> Result<(Mat3, Vec3), String> {
    let shape_ok = matches!(rows.len(), 3 | 4) && rows.iter().all(|r| r.len() == 4);
    if !shape_ok {
        let cols = rows.first().map_or(0, Vec::len);
        return Err(format!(
            "expected a 4×4 or 3×4 matrix, found {}×{cols}",
            rows.len()
        ));
    }
    if let Some(last) = rows.get(3) {
        if last
            .iter()
            .zip([0.0, 0.0, 0.0, 1.0])
            .any(|(a, b)| (a - b).abs() > 1e-4)
        {
            return Err(format!("the last row must be [0, 0, 0, 1], found {last:?}"));
        }
    }
    let col = |c: usize| Vec3::new(rows[0][c], rows[1][c], rows[2][c]);
    Ok((Mat3::from_cols(col(0), col(1), col(2)), col(3)))
}

/// Train and test indices into a list of frame specs.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Split {
    pub train: Vec<usize>,
    pub test: Vec<usize>,
}

impl Split {
    /// Every `test_every`-th frame (starting with the first) is test; 0 means no test split.
    pub fn every_nth(n: usize, test_every: usize) -> Self {
        let (test, train) = (0..n).partition(|i| test_every > 0 && i % test_every == 0);
        Self { train, test }
    }

    /// Keeps at most `max` frames, shared between the splits in proportion and evenly spaced
    /// within each (each non-empty split keeps at least one frame).
    pub fn capped(self, max: Option<usize>) -> Self {
        let total = self.train.len() + self.test.len();
        let Some(max) = max.filter(|&m| m < total) else {
            return self;
        };
        let mut n_test = (max * self.test.len()).div_ceil(total).min(self.test.len());
        if n_test == max && max > 1 {
            n_test -= 1;
        }
        let pick = |idx: &[usize], k: usize| -> Vec<usize> {
            (0..k).map(|i| idx[i * idx.len() / k]).collect()
        };
        Self {
            train: pick(&self.train, max - n_test),
            test: pick(&self.test, n_test),
        }
    }
}

/// Loads the frames of `split`, returning them in dataset order with the split re-indexed.
pub(crate) fn load(
    specs: Vec<FrameSpec>,
    split: Split,
    opts: &LoadOptions,
    background: [f32; 3],
) -> Result<(Vec<Frame>, Split)> {
    let mut used: Vec<usize> = split.train.iter().chain(&split.test).copied().collect();
    used.sort_unstable();
    used.dedup();
    let position = |i: &usize| used.binary_search(i).expect("split index is used");
    let split = Split {
        train: split.train.iter().map(position).collect(),
        test: split.test.iter().map(position).collect(),
    };
    let mut specs: Vec<Option<FrameSpec>> = specs.into_iter().map(Some).collect();
    let selected: Vec<FrameSpec> = used.iter().filter_map(|&i| specs[i].take()).collect();
    let frames = selected
        .into_par_iter()
        .map(|spec| load_frame(spec, opts, background))
        .collect::<Result<Vec<_>>>()?;
    Ok((frames, split))
}

fn load_frame(spec: FrameSpec, opts: &LoadOptions, background: [f32; 3]) -> Result<Frame> {
    let origin = Origin {
        file: &spec.source,
        field: &spec.field,
    };
    let mut image = images::read_rgb(&spec.image, origin, background)?;
    let (w, h) = image.dimensions();
    let (k, distortion) = match spec.intrinsics {
        IntrinsicsSpec::Known {
            k,
            distortion,
            size_field,
        } => {
            if (w, h) != (k.width, k.height) {
                return Err(EngineError::dataset(
                    &spec.source,
                    size_field,
                    format!(
                        "image {} is {w}×{h} but the intrinsics say {}×{}",
                        spec.name, k.width, k.height
                    ),
                ));
            }
            (k, distortion)
        }
        IntrinsicsSpec::FovX(angle) => {
            let f = 0.5 * w as f32 / (0.5 * angle).tan();
            let k = Intrinsics {
                fx: f,
                fy: f,
                cx: 0.5 * w as f32,
                cy: 0.5 * h as f32,
                width: w,
                height: h,
            };
            (k, Distortion::default())
        }
    };
    if !distortion.is_identity() {
        image = distortion.undistort_rgb(&image, &k);
    }
    let target = working_intrinsics(&k, opts);
    let image = images::resize_rgb(&image, target.width, target.height);
    let depth = spec
        .depth
        .map(|d| {
            let origin = Origin {
                file: &spec.source,
                field: &d.field,
            };
            let (dw, dh, mut depth) = images::read_depth(&d.path, origin, d.scale)?;
            if (dw, dh) != (w, h) {
                return Err(origin.err(format!(
                    "depth map is {dw}×{dh} but its image {} is {w}×{h}",
                    spec.name
                )));
            }
            if !distortion.is_identity() {
                depth = distortion.undistort_depth(&depth, &k);
            }
            Ok(images::resize_depth(
                &depth,
                w,
                h,
                target.width,
                target.height,
            ))
        })
        .transpose()?;
    Ok(Frame {
        name: spec.name,
        camera: Camera {
            intrinsics: target,
            rotation: spec.rotation,
            position: spec.position,
        },
        image,
        depth,
    })
}

/// The intrinsics a frame is trained at: shrunk by `downscale`, then to at most `max_side`
/// pixels on its longest side (one resize, so the two never round twice).
pub(crate) fn working_intrinsics(k: &Intrinsics, opts: &LoadOptions) -> Intrinsics {
    let mut factor = 1.0 / opts.downscale.max(1) as f32;
    let longest = k.width.max(k.height) as f32;
    if let Some(side) = opts.max_side {
        factor = factor.min(side as f32 / longest);
    }
    if factor < 1.0 {
        k.scaled(factor)
    } else {
        *k
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn working_resolution_caps_the_longest_side() {
        let k = Intrinsics {
            fx: 1375.0,
            fy: 1374.0,
            cx: 554.0,
            cy: 965.0,
            width: 1080,
            height: 1920,
        };
        let opts = |downscale, max_side| LoadOptions {
            downscale,
            max_side,
            ..LoadOptions::default()
        };
        let w = working_intrinsics(&k, &opts(1, Some(240)));
        assert_eq!((w.width, w.height), (135, 240));
        assert!((w.fx - 1375.0 / 8.0).abs() < 0.01 && (w.cy - 965.0 / 8.0).abs() < 0.01);
        // The smaller of the two wins; neither enlarges.
        let w = working_intrinsics(&k, &opts(2, Some(1000)));
        assert_eq!((w.width, w.height), (540, 960));
        assert_eq!(working_intrinsics(&k, &opts(1, Some(4000))), k);
    }

    #[test]
    fn every_eighth_frame_is_test() {
        let s = Split::every_nth(17, 8);
        assert_eq!(s.test, vec![0, 8, 16]);
        assert_eq!(s.train.len(), 14);
        assert!(Split::every_nth(5, 0).test.is_empty());
    }

    #[test]
    fn capping_keeps_both_splits() {
        let s = Split::every_nth(48, 8).capped(Some(10));
        assert_eq!(s.train.len() + s.test.len(), 10);
        assert!(!s.test.is_empty() && !s.train.is_empty());
        let t = Split::every_nth(48, 8).capped(Some(2));
        assert_eq!((t.train.len(), t.test.len()), (1, 1));
    }
}
