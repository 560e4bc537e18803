//! Scene bounds for datasets that do not state them: an axis-aligned box estimated from the
//! cameras, and near/far distances that cover the box from every camera.
//!
//! The box centre is the point closest (least squares) to all optical axes: cameras of a
//! capture look at the subject. Its half-size is the median distance from the cameras to that
//! centre, which for an object-centric capture safely contains everything the cameras frame.
//! When the axes are nearly parallel (a forward-facing capture) the centre is placed one
//! median camera spread in front of the mean camera instead.

use glam::{Mat3, Vec3};

use super::Aabb;

/// A camera for bounds: its position and unit viewing direction.
pub(crate) type Pose = (Vec3, Vec3);

/// Estimates a cube containing what the cameras look at.
pub(crate) fn estimate_aabb(cameras: &[Pose]) -> Aabb {
    let centre = axes_centre(cameras).unwrap_or_else(|| {
        let mean = cameras.iter().map(|c| c.0).sum::<Vec3>() / cameras.len() as f32;
        let forward = cameras
            .iter()
            .map(|c| c.1)
            .sum::<Vec3>()
            .normalize_or_zero();
        let spread = median(cameras.iter().map(|c| (c.0 - mean).length()).collect());
        mean + forward * spread.max(1.0)
    });
    let half = median(cameras.iter().map(|c| (c.0 - centre).length()).collect()).max(1e-3);
    Aabb {
        min: centre - Vec3::splat(half),
        max: centre + Vec3::splat(half),
    }
}

/// Near and far distances covering the bounding sphere of `aabb` from every camera; near is
/// at least 1% of the box diagonal (cameras may sit inside the box).
pub(crate) fn near_far(cameras: &[Pose], aabb: &Aabb) -> (f32, f32) {
    let radius = aabb.size().length() * 0.5;
    let dist = |c: &Pose| (c.0 - aabb.center()).length();
    let closest = cameras.iter().map(dist).fold(f32::INFINITY, f32::min);
    let farthest = cameras.iter().map(dist).fold(0.0, f32::max);
    let near = (closest - radius).max(0.02 * radius);
    (near, (farthest + radius).max(near * 2.0))
}

/// Near and far for an unbounded capture: near as for [`near_far`]; far where the field's
/// contraction of space around `aabb` ends (see [`crate::field::space::Contraction`]).
pub(crate) fn near_far_unbounded(cameras: &[Pose], aabb: &Aabb) -> (f32, f32) {
    let (near, _) = near_far(cameras, aabb);
    let half = aabb.size().max_element() * 0.5;
    let farthest = cameras
        .iter()
        .map(|c| (c.0 - aabb.center()).length())
        .fold(0.0, f32::max);
    let reach = crate::field::space::Contraction::REACH * half * 3f32.sqrt();
    (near, farthest + reach)
}

/// Least-squares point nearest to all camera axes, or `None` when they are (nearly) parallel.
fn axes_centre(cameras: &[Pose]) -> Option<Vec3> {
    let mut a = Mat3::ZERO;
    let mut b = Vec3::ZERO;
    for &(position, d) in cameras {
        let p = Mat3::IDENTITY - Mat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += p;
        b += p * position;
    }
    // Parallel axes leave one direction unconstrained: the smallest eigenvalue of `a` is ~0.
    // Compare the determinant to the cube of the trace as a scale-free test.
    let trace = a.x_axis.x + a.y_axis.y + a.z_axis.z;
    (a.determinant() > 1e-3 * (trace / 3.0).powi(3)).then(|| a.inverse() * b)
}

fn median(mut v: Vec<f32>) -> f32 {
    v.sort_by(f32::total_cmp);
    v[v.len() / 2]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Intrinsics};

    fn poses(cams: &[Camera]) -> Vec<Pose> {
        cams.iter().map(|c| (c.position, c.forward())).collect()
    }

    fn k() -> Intrinsics {
        Intrinsics {
            fx: 50.0,
            fy: 50.0,
            cx: 32.0,
            cy: 32.0,
            width: 64,
            height: 64,
        }
    }

    #[test]
    fn ring_of_cameras_centres_on_the_target() {
        let target = Vec3::new(0.5, -0.2, 1.0);
        let cams: Vec<Camera> = (0..12)
            .map(|i| {
                let a = i as f32 * 0.5;
                let eye = target + Vec3::new(3.0 * a.cos(), 1.0, 3.0 * a.sin());
                Camera::look_at(k(), eye, target, Vec3::Y)
            })
            .collect();
        let b = estimate_aabb(&poses(&cams));
        assert!((b.center() - target).length() < 1e-3);
        let (near, far) = near_far(&poses(&cams), &b);
        let reach = (cams[0].position - target).length() + 0.5 * b.size().length();
        assert!(near > 0.0 && (far - reach).abs() < 1e-3);
    }

    #[test]
    fn parallel_cameras_get_a_box_in_front() {
        let cams: Vec<Camera> = (0..4)
            .map(|i| {
                let eye = Vec3::new(i as f32, 0.0, 0.0);
                Camera::look_at(k(), eye, eye - Vec3::Z, Vec3::Y)
            })
            .collect();
        let b = estimate_aabb(&poses(&cams));
        assert!(b.center().z < 0.0 && b.min.is_finite());
    }
}
