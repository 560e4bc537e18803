//! Camera paths to render a trained scene along: through the training cameras
//! (`interpolate`), the training cameras themselves (`train`), a circle around the point they
//! look at (`orbit`, for captures that go around an object), and a spiral about their mean
//! pose (`spiral`, for forward-facing captures, as NeRF renders LLFF scenes). Every path keeps
//! the training cameras' intrinsics and up direction.

use glam::{Mat3, Vec3};

use crate::camera::Camera;
use crate::{EngineError, Result};

/// The kinds of camera path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PathKind {
    Interpolate,
    Train,
    Orbit,
    Spiral,
}

impl PathKind {
    /// Every kind's name, as requests spell them.
    pub const NAMES: [&'static str; 4] = ["interpolate", "train", "orbit", "spiral"];
}

impl std::str::FromStr for PathKind {
    type Err = EngineError;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "interpolate" => Ok(Self::Interpolate),
            "train" => Ok(Self::Train),
            "orbit" => Ok(Self::Orbit),
            "spiral" => Ok(Self::Spiral),
            _ => Err(EngineError::config(
                "camera_path.kind",
                format!("unknown kind `{s}` (one of {})", PathKind::NAMES.join(", ")),
            )),
        }
    }
}

/// The cameras of a path of `kind` over the training cameras `cameras`, `frames` long
/// (`train` gives the training cameras whatever `frames` is); `keyframes` is the number of
/// training cameras an `interpolate` path passes through.
pub fn camera_path(
    kind: PathKind,
    cameras: &[Camera],
    frames: usize,
    keyframes: usize,
) -> Vec<Camera> {
    if cameras.is_empty() {
        return Vec::new();
    }
    match kind {
        PathKind::Train => cameras.to_vec(),
        PathKind::Interpolate => interpolated_path(cameras, keyframes, frames),
        PathKind::Orbit => orbit_path(cameras, frames),
        PathKind::Spiral => spiral_path(cameras, frames),
    }
}

/// A closed path through `keyframes` evenly spaced cameras of `cameras`, `frames` poses long.
pub fn interpolated_path(cameras: &[Camera], keyframes: usize, frames: usize) -> Vec<Camera> {
    if cameras.is_empty() || frames == 0 {
        return Vec::new();
    }
    let keys: Vec<Camera> = (0..keyframes.clamp(1, cameras.len()))
        .map(|i| cameras[i * cameras.len() / keyframes.clamp(1, cameras.len())])
        .collect();
    (0..frames)
        .map(|f| {
            let x = f as f32 * keys.len() as f32 / frames as f32;
            let i = x.floor() as usize;
            keys[i % keys.len()].interpolate(&keys[(i + 1) % keys.len()], x - i as f32)
        })
        .collect()
}

/// The training cameras' mean up direction (their y axes).
fn mean_up(cameras: &[Camera]) -> Vec3 {
    cameras
        .iter()
        .map(|c| c.rotation.y_axis)
        .sum::<Vec3>()
        .try_normalize()
        .unwrap_or(Vec3::Y)
}

fn mean_position(cameras: &[Camera]) -> Vec3 {
    cameras.iter().map(|c| c.position).sum::<Vec3>() / cameras.len() as f32
}

/// The point nearest (least squares) to every camera's optical axis: what the cameras look
/// at. `None` when the axes are (nearly) parallel, as in a forward-facing capture.
fn focus_point(cameras: &[Camera]) -> Option<Vec3> {
    let mut a = Mat3::ZERO;
    let mut b = Vec3::ZERO;
    for camera in cameras {
        let d = camera.forward();
        let projector = Mat3::IDENTITY - Mat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += projector;
        b += projector * camera.position;
    }
    // Parallel axes leave A singular along them; compare with the scale of A.
    let scale = a.col(0).length() + a.col(1).length() + a.col(2).length();
    (a.determinant().abs() > 1e-3 * scale.powi(3)).then(|| a.inverse() * b)
}

/// The axis of a capture that goes around its subject: the normal of the plane the cameras
/// lie near (the least-variance direction of their positions), turned towards their mean up.
/// The cameras' mean up when they do not spread in a plane.
fn orbit_axis(cameras: &[Camera]) -> Vec3 {
    let up = mean_up(cameras);
    let mean = mean_position(cameras);
    let mut covariance = Mat3::ZERO;
    for camera in cameras {
        let d = camera.position - mean;
        covariance += Mat3::from_cols(d * d.x, d * d.y, d * d.z);
    }
    let trace = covariance.col(0).x + covariance.col(1).y + covariance.col(2).z;
    // Power iteration on trace·I − C finds C's least-variance direction.
    let shifted = Mat3::from_diagonal(Vec3::splat(trace)) - covariance;
    let mut normal = up;
    for _ in 0..64 {
        normal = (shifted * normal).try_normalize().unwrap_or(up);
    }
    let least = normal.dot(covariance * normal);
    let planar = least < 0.1 * (trace - least) / 2.0;
    match planar {
        true if normal.dot(up) < 0.0 => -normal,
        true => normal,
        false => up,
    }
}

/// A circle around the focus point, about the capture's axis, at the cameras' mean distance
/// from it and mean height above it, starting at the first camera's side.
fn orbit_path(cameras: &[Camera], frames: usize) -> Vec<Camera> {
    let up = orbit_axis(cameras);
    let centre = focus_point(cameras).unwrap_or_else(|| {
        mean_position(cameras) + cameras[0].forward() * spread(cameras).max(1e-3) * 2.0
    });
    let (mut radius, mut height) = (0.0, 0.0);
    for camera in cameras {
        let offset = camera.position - centre;
        height += offset.dot(up);
        radius += (offset - offset.dot(up) * up).length();
    }
    let n = cameras.len() as f32;
    let (radius, height) = (radius / n, height / n);
    let start = cameras[0].position - centre;
    let e1 = (start - start.dot(up) * up)
        .try_normalize()
        .unwrap_or_else(|| up.any_orthonormal_vector());
    let e2 = up.cross(e1);
    (0..frames)
        .map(|f| {
            let angle = std::f32::consts::TAU * f as f32 / frames as f32;
            let eye = centre + height * up + radius * (angle.cos() * e1 + angle.sin() * e2);
            Camera::look_at(cameras[0].intrinsics, eye, centre, up)
        })
        .collect()
}

/// How far the cameras are spread: their RMS distance from their mean position.
fn spread(cameras: &[Camera]) -> f32 {
    let mean = mean_position(cameras);
    (cameras
        .iter()
        .map(|c| (c.position - mean).length_squared())
        .sum::<f32>()
        / cameras.len() as f32)
        .sqrt()
}

/// Two turns of a spiral about the cameras' mean pose, in its image plane, as wide as the
/// cameras spread along its right and up axes (their 90th percentile), moving in and out
/// along the view a quarter as far, always looking at the focus point (ten spreads ahead when
/// the cameras' axes do not meet).
fn spiral_path(cameras: &[Camera], frames: usize) -> Vec<Camera> {
    let centre = mean_position(cameras);
    let up = mean_up(cameras);
    let forward = cameras
        .iter()
        .map(|c| c.forward())
        .sum::<Vec3>()
        .try_normalize()
        .unwrap_or(-Vec3::Z);
    let right = forward.cross(up).try_normalize().unwrap_or(Vec3::X);
    let true_up = right.cross(forward);
    let percentile = |axis: Vec3| {
        let mut extents: Vec<f32> = cameras
            .iter()
            .map(|c| (c.position - centre).dot(axis).abs())
            .collect();
        extents.sort_by(f32::total_cmp);
        extents[((extents.len() - 1) as f32 * 0.9).round() as usize]
    };
    let (rx, ry) = (percentile(right), percentile(true_up));
    let depth = match focus_point(cameras) {
        Some(focus) if (focus - centre).dot(forward) > 0.0 => (focus - centre).dot(forward),
        _ => 10.0 * spread(cameras).max(1e-3),
    };
    let focus = centre + depth * forward;
    let rz = 0.25 * rx.max(ry);
    (0..frames)
        .map(|f| {
            let t = 2.0 * std::f32::consts::TAU * f as f32 / frames as f32;
            let eye = centre + rx * t.cos() * right + ry * t.sin() * true_up
                - rz * (0.5 * t).sin() * forward;
            Camera::look_at(cameras[0].intrinsics, eye, focus, true_up)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;

    fn intrinsics() -> Intrinsics {
        Intrinsics {
            fx: 50.0,
            fy: 50.0,
            cx: 32.0,
            cy: 24.0,
            width: 64,
            height: 48,
        }
    }

    /// Cameras on a tilted ring of radius 3, 1 above a target at (1, 2, 3), looking at it.
    fn ring() -> Vec<Camera> {
        let target = Vec3::new(1.0, 2.0, 3.0);
        (0..12)
            .map(|i| {
                let a = i as f32 * 0.5;
                let eye = target + Vec3::new(3.0 * a.cos(), 1.0, 3.0 * a.sin());
                Camera::look_at(intrinsics(), eye, target, Vec3::Y)
            })
            .collect()
    }

    #[test]
    fn an_orbit_circles_what_the_cameras_look_at() {
        let cameras = ring();
        let target = Vec3::new(1.0, 2.0, 3.0);
        assert!((focus_point(&cameras).unwrap() - target).length() < 1e-3);
        let path = camera_path(PathKind::Orbit, &cameras, 24, 0);
        assert_eq!(path.len(), 24);
        for camera in &path {
            let offset = camera.position - target;
            assert!((offset.y - 1.0).abs() < 1e-3, "{offset}");
            let across = glam::Vec2::new(offset.x, offset.z).length();
            assert!((across - 3.0).abs() < 1e-3, "{offset}");
            let towards = (target - camera.position).normalize();
            assert!(camera.forward().dot(towards) > 0.9999);
            assert_eq!(camera.intrinsics, intrinsics());
        }
        // It goes all the way round.
        let angles: Vec<f32> = path
            .iter()
            .map(|c| (c.position.z - target.z).atan2(c.position.x - target.x))
            .collect();
        let turned: f32 = angles
            .windows(2)
            .map(|w| {
                (w[1] - w[0] + 3.0 * std::f32::consts::PI) % std::f32::consts::TAU
                    - std::f32::consts::PI
            })
            .sum();
        assert!(turned.abs() > 5.5, "{turned}");
    }

    #[test]
    fn a_spiral_stays_near_a_forward_facing_rig() {
        // A 3×3 grid of parallel cameras 0.2 apart looking down −z.
        let cameras: Vec<Camera> = (0..9)
            .map(|i| {
                let eye = Vec3::new(0.2 * (i % 3) as f32 - 0.2, 0.2 * (i / 3) as f32 - 0.2, 0.0);
                Camera::look_at(intrinsics(), eye, eye - Vec3::Z, Vec3::Y)
            })
            .collect();
        assert!(
            focus_point(&cameras).is_none(),
            "parallel axes have no focus"
        );
        let path = camera_path(PathKind::Spiral, &cameras, 30, 0);
        assert_eq!(path.len(), 30);
        for camera in &path {
            assert!(camera.position.length() < 0.3, "{}", camera.position);
            assert!(camera.forward().dot(-Vec3::Z) > 0.99);
        }
        let xs: Vec<f32> = path.iter().map(|c| c.position.x).collect();
        assert!(xs.iter().cloned().fold(f32::MIN, f32::max) > 0.15);
        assert!(xs.iter().cloned().fold(f32::MAX, f32::min) < -0.15);
    }

    #[test]
    fn kinds_parse_and_train_is_the_training_cameras() {
        for name in PathKind::NAMES {
            name.parse::<PathKind>().unwrap();
        }
        let err = "zoom".parse::<PathKind>().unwrap_err().to_string();
        assert!(
            err.contains("camera_path.kind") && err.contains("orbit"),
            "{err}"
        );
        let cameras = ring();
        assert_eq!(camera_path(PathKind::Train, &cameras, 5, 0), cameras);
        assert_eq!(
            camera_path(PathKind::Interpolate, &cameras, 10, 4).len(),
            10
        );
    }
}
