//! COLMAP's sparse model in its text form (`cameras.txt`, `images.txt`, `points3D.txt`, as
//! `colmap model_converter --output_type TXT` writes them), read into cameras with their
//! intrinsics and distortion, registered images with camera-to-world poses in OpenGL axes and
//! the sparse points each observes, and the sparse points.

use std::collections::BTreeMap;
use std::path::Path;

use glam::{DMat3, DQuat, DVec3};

use crate::{EngineError, Result};

/// A COLMAP camera, as the nerfstudio `transforms.json` keys describe it.
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// OpenCV distortion k1, k2, p1, p2 (zeros for the pinhole models).
    pub distortion: [f64; 4],
}

/// A registered image.
#[derive(Debug, Clone)]
pub struct ColmapImage {
    pub name: String,
    pub camera: u32,
    /// Camera-to-world rotation with OpenGL camera axes (x right, y up, looking down −z).
    pub rotation: DMat3,
    /// Camera centre in world space.
    pub position: DVec3,
    /// The sparse points this image observes, where it observes them.
    pub observations: Vec<Observation>,
}

/// A sparse point seen in an image: the pixel position of the keypoint (COLMAP's, pixel centres
/// at +0.5) and the point's `POINT3D_ID`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    pub pixel: [f64; 2],
    pub point: u64,
}

/// One sparse point with its mean reprojection error in pixels.
#[derive(Debug, Clone, Copy)]
pub struct ColmapPoint {
    pub id: u64,
    pub position: DVec3,
    pub error: f64,
}

/// A sparse model read from a folder of COLMAP text files.
#[derive(Debug, Clone)]
pub struct SparseModel {
    pub cameras: BTreeMap<u32, ColmapCamera>,
    pub images: Vec<ColmapImage>,
    pub points: Vec<ColmapPoint>,
}

impl SparseModel {
    pub fn read(dir: &Path) -> Result<Self> {
        let cameras = read_lines(&dir.join("cameras.txt"), |file, line| {
            let (id, cam) = camera(line).map_err(|r| EngineError::dataset(file, "camera", r))?;
            Ok(Some((id, cam)))
        })?
        .into_iter()
        .collect::<BTreeMap<_, _>>();
        // images.txt alternates a pose line and a line of 2D points.
        let mut pose_line = true;
        let lines = read_lines(&dir.join("images.txt"), |file, line| {
            let is_pose = pose_line;
            pose_line = !pose_line;
            match is_pose {
                true => image(line).map(ImageLine::Pose),
                false => observations(line).map(ImageLine::Points),
            }
            .map(Some)
            .map_err(|r| EngineError::dataset(file, "image", r))
        })?;
        let mut images: Vec<ColmapImage> = Vec::new();
        for line in lines {
            match (line, images.last_mut()) {
                (ImageLine::Pose(image), _) => images.push(image),
                (ImageLine::Points(points), Some(image)) => image.observations = points,
                (ImageLine::Points(_), None) => unreachable!("a points line follows a pose line"),
            }
        }
        let points = read_lines(&dir.join("points3D.txt"), |file, line| {
            point(line)
                .map(Some)
                .map_err(|r| EngineError::dataset(file, "point", r))
        })?;
        if let Some(i) = images.iter().find(|i| !cameras.contains_key(&i.camera)) {
            return Err(EngineError::dataset(
                dir.join("images.txt"),
                "CAMERA_ID",
                format!(
                    "{} refers to camera {}, not in cameras.txt",
                    i.name, i.camera
                ),
            ));
        }
        Ok(Self {
            cameras,
            images,
            points,
        })
    }

    /// Mean reprojection error over the sparse points, in pixels.
    pub fn mean_reprojection_error(&self) -> f64 {
        let n = self.points.len().max(1) as f64;
        self.points.iter().map(|p| p.error).sum::<f64>() / n
    }
}

/// A line of `images.txt`.
enum ImageLine {
    Pose(ColmapImage),
    Points(Vec<Observation>),
}

/// Reads the non-comment lines of `file` through `parse` (line numbers in errors).
fn read_lines<T>(
    file: &Path,
    mut parse: impl FnMut(&Path, &str) -> Result<Option<T>>,
) -> Result<Vec<T>> {
    let text = std::fs::read_to_string(file).map_err(|e| EngineError::io(file, e))?;
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        if line.starts_with('#') {
            continue;
        }
        let parsed = parse(file, line.trim()).map_err(|e| match e {
            EngineError::Dataset {
                file,
                field,
                reason,
            } => EngineError::Dataset {
                file,
                field,
                reason: format!("line {}: {reason}", n + 1),
            },
            e => e,
        })?;
        out.extend(parsed);
    }
    Ok(out)
}

fn numbers(fields: &[&str]) -> std::result::Result<Vec<f64>, String> {
    fields
        .iter()
        .map(|f| {
            f.parse::<f64>()
                .map_err(|_| format!("`{f}` is not a number"))
        })
        .collect()
}

/// `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`.
fn camera(line: &str) -> std::result::Result<(u32, ColmapCamera), String> {
    let f: Vec<&str> = line.split_whitespace().collect();
    if f.len() < 4 {
        return Err(format!(
            "expected `CAMERA_ID MODEL WIDTH HEIGHT PARAMS…`, found `{line}`"
        ));
    }
    let id = f[0]
        .parse()
        .map_err(|_| format!("bad camera id `{}`", f[0]))?;
    let width = f[2].parse().map_err(|_| format!("bad width `{}`", f[2]))?;
    let height = f[3].parse().map_err(|_| format!("bad height `{}`", f[3]))?;
    let p = numbers(&f[4..])?;
    let want = |n: usize| {
        (p.len() == n).then_some(()).ok_or_else(|| {
            format!(
                "camera model {} takes {n} parameters, found {}",
                f[1],
                p.len()
            )
        })
    };
    let (fx, fy, cx, cy, distortion) = match f[1] {
        "SIMPLE_PINHOLE" => {
            want(3)?;
            (p[0], p[0], p[1], p[2], [0.0; 4])
        }
        "PINHOLE" => {
            want(4)?;
            (p[0], p[1], p[2], p[3], [0.0; 4])
        }
        "SIMPLE_RADIAL" => {
            want(4)?;
            (p[0], p[0], p[1], p[2], [p[3], 0.0, 0.0, 0.0])
        }
        "RADIAL" => {
            want(5)?;
            (p[0], p[0], p[1], p[2], [p[3], p[4], 0.0, 0.0])
        }
        "OPENCV" => {
            want(8)?;
            (p[0], p[1], p[2], p[3], [p[4], p[5], p[6], p[7]])
        }
        other => {
            return Err(format!(
                "camera model {other} is not supported (use SIMPLE_PINHOLE, PINHOLE, \
                 SIMPLE_RADIAL, RADIAL or OPENCV)"
            ))
        }
    };
    Ok((
        id,
        ColmapCamera {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            distortion,
        },
    ))
}

/// `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`: a world-to-camera pose in OpenCV axes.
fn image(line: &str) -> std::result::Result<ColmapImage, String> {
    let f: Vec<&str> = line.splitn(10, ' ').collect();
    if f.len() < 10 {
        return Err(format!(
            "expected `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`, found `{line}`"
        ));
    }
    let v = numbers(&f[1..8])?;
    let q = DQuat::from_xyzw(v[1], v[2], v[3], v[0]);
    if (q.length() - 1.0).abs() >= 1e-3 {
        return Err(format!("the rotation quaternion of {} is not unit", f[9]));
    }
    let world_to_camera = DMat3::from_quat(q.normalize());
    let t = DVec3::new(v[4], v[5], v[6]);
    let to_world = world_to_camera.transpose();
    // OpenCV camera axes (y down, looking down +z) to OpenGL's (y up, looking down −z).
    let flip = DMat3::from_diagonal(DVec3::new(1.0, -1.0, -1.0));
    Ok(ColmapImage {
        name: f[9].to_string(),
        camera: f[8]
            .parse()
            .map_err(|_| format!("bad camera id `{}`", f[8]))?,
        rotation: to_world * flip,
        position: -(to_world * t),
        observations: Vec::new(),
    })
}

/// `POINTS2D[]` as `(X, Y, POINT3D_ID)`: the keypoints with a sparse point (an id of −1 has
/// none).
fn observations(line: &str) -> std::result::Result<Vec<Observation>, String> {
    let f: Vec<&str> = line.split_whitespace().collect();
    if !f.len().is_multiple_of(3) {
        return Err(format!(
            "expected `X Y POINT3D_ID` triples, found {} fields",
            f.len()
        ));
    }
    f.chunks_exact(3)
        .filter(|t| t[2] != "-1")
        .map(|t| {
            let xy = numbers(&t[..2])?;
            let point = t[2]
                .parse()
                .map_err(|_| format!("bad POINT3D_ID `{}`", t[2]))?;
            Ok(Observation {
                pixel: [xy[0], xy[1]],
                point,
            })
        })
        .collect()
}

/// `POINT3D_ID X Y Z R G B ERROR TRACK[]`.
fn point(line: &str) -> std::result::Result<ColmapPoint, String> {
    let f: Vec<&str> = line.split_whitespace().take(8).collect();
    if f.len() < 8 {
        return Err(format!(
            "expected `POINT3D_ID X Y Z R G B ERROR …`, found `{line}`"
        ));
    }
    let v = numbers(&f[1..8])?;
    Ok(ColmapPoint {
        id: f[0]
            .parse()
            .map_err(|_| format!("bad POINT3D_ID `{}`", f[0]))?,
        position: DVec3::new(v[0], v[1], v[2]),
        error: v[6],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_a_model_and_converts_poses_to_camera_to_world_opengl() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("cameras.txt"),
            "# Camera list\n1 OPENCV 640 480 500 510 320 240 0.1 -0.02 0.001 0.002\n",
        )
        .unwrap();
        // A camera at (0, 0, -5) looking at the origin along +z: identity world-to-camera
        // rotation, t = -R c = (0, 0, 5).
        std::fs::write(
            dir.path().join("images.txt"),
            "# Image list\n1 1 0 0 0 0 0 5 1 photo one.jpg\n10.0 20.0 -1 30.5 40.25 2\n",
        )
        .unwrap();
        std::fs::write(
            dir.path().join("points3D.txt"),
            "# points\n1 0.5 0 0 255 0 0 0.5 1 0\n2 0 0.5 0 0 255 0 1.5 1 0\n",
        )
        .unwrap();
        let m = SparseModel::read(dir.path()).unwrap();
        let cam = &m.cameras[&1];
        assert_eq!(
            (cam.width, cam.height, cam.fy, cam.distortion[3]),
            (640, 480, 510.0, 0.002)
        );
        let img = &m.images[0];
        assert_eq!(img.name, "photo one.jpg");
        assert!((img.position - DVec3::new(0.0, 0.0, -5.0)).length() < 1e-12);
        // OpenGL: the camera looks down its −z axis, which must point at the origin (+z world).
        let forward = -img.rotation.z_axis;
        assert!((forward - DVec3::Z).length() < 1e-12);
        // COLMAP's y is down; OpenGL's up is world −y here.
        assert!((img.rotation.y_axis + DVec3::Y).length() < 1e-12);
        assert!((m.mean_reprojection_error() - 1.0).abs() < 1e-12);
        // Keypoints without a sparse point are left out.
        assert_eq!(
            img.observations,
            [Observation {
                pixel: [30.5, 40.25],
                point: 2
            }]
        );
        assert_eq!(m.points[1].id, 2);
    }

    #[test]
    fn errors_name_the_file_and_line() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("cameras.txt"), "1 FISHEYE 10 10 1 2 3\n").unwrap();
        std::fs::write(dir.path().join("images.txt"), "").unwrap();
        std::fs::write(dir.path().join("points3D.txt"), "").unwrap();
        let err = SparseModel::read(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("cameras.txt") && err.contains("line 1"),
            "{err}"
        );
        assert!(err.contains("FISHEYE is not supported"), "{err}");
        // A line of 2D points that is not whole triples.
        std::fs::write(dir.path().join("cameras.txt"), "1 PINHOLE 10 10 5 5 5 5\n").unwrap();
        std::fs::write(
            dir.path().join("images.txt"),
            "1 1 0 0 0 0 0 5 1 a.jpg\n10.0 20.0 3 4.0\n",
        )
        .unwrap();
        let err = SparseModel::read(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("images.txt") && err.contains("line 2") && err.contains("triples"),
            "{err}"
        );
    }
}
