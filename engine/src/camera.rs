//! Pinhole cameras: intrinsics, camera-to-world poses (OpenGL axes), ray generation,
//! projection, NDC rays for forward-facing scenes, and pose interpolation (slerp + lerp).
//!
//! Conventions used everywhere in the project:
//! - pixel (u, v) has u growing to the right and v growing downwards; pixel centres are at
//!   integer + 0.5;
//! - camera axes are OpenGL's: x right, y up, the camera looks down −z;
//! - "depth" is z-depth: the distance along the camera's viewing axis, in world units.

use glam::{Mat3, Quat, Vec3};
use serde::{Deserialize, Serialize};

/// Pinhole intrinsics in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
}

impl Intrinsics {
    /// Intrinsics scaled to an image resized by `factor` (e.g. 0.5 halves the resolution).
    pub fn scaled(&self, factor: f32) -> Self {
        let width = ((self.width as f32) * factor).round().max(1.0) as u32;
        let height = ((self.height as f32) * factor).round().max(1.0) as u32;
        let sx = width as f32 / self.width as f32;
        let sy = height as f32 / self.height as f32;
        Self {
            fx: self.fx * sx,
            fy: self.fy * sy,
            cx: self.cx * sx,
            cy: self.cy * sy,
            width,
            height,
        }
    }
}

/// A camera: intrinsics plus a camera-to-world rigid transform.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub intrinsics: Intrinsics,
    /// Camera-to-world rotation, columns are the camera's x, y, z axes in world space.
    pub rotation: Mat3,
    /// Camera centre in world space.
    pub position: Vec3,
}

/// A ray with a unit direction. `z_per_t` converts a distance `t` along the ray into z-depth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
    pub z_per_t: f32,
}

impl Camera {
    /// Builds a camera from a row-major 3×4 or 4×4 camera-to-world matrix (OpenGL axes).
    pub fn from_c2w_rows(intrinsics: Intrinsics, rows: &[[f32; 4]]) -> Self {
        let rotation = Mat3::from_cols(
            Vec3::new(rows[0][0], rows[1][0], rows[2][0]),
            Vec3::new(rows[0][1], rows[1][1], rows[2][1]),
            Vec3::new(rows[0][2], rows[1][2], rows[2][2]),
        );
        let position = Vec3::new(rows[0][3], rows[1][3], rows[2][3]);
        Self {
            intrinsics,
            rotation,
            position,
        }
    }

    /// The row-major 4×4 camera-to-world matrix (OpenGL axes), as written to JSON files.
    pub fn c2w_rows(&self) -> [[f32; 4]; 4] {
        let r = self.rotation;
        let p = self.position;
        [
            [r.x_axis.x, r.y_axis.x, r.z_axis.x, p.x],
            [r.x_axis.y, r.y_axis.y, r.z_axis.y, p.y],
            [r.x_axis.z, r.y_axis.z, r.z_axis.z, p.z],
            [0.0, 0.0, 0.0, 1.0],
        ]
    }

    /// A camera at `eye` looking at `target`, with `up` as the approximate up direction.
    pub fn look_at(intrinsics: Intrinsics, eye: Vec3, target: Vec3, up: Vec3) -> Self {
        let back = (eye - target).normalize();
        let right = up.cross(back).normalize();
        let true_up = back.cross(right);
        Self {
            intrinsics,
            rotation: Mat3::from_cols(right, true_up, back),
            position: eye,
        }
    }

    /// The viewing direction (camera −z) in world space.
    pub fn forward(&self) -> Vec3 {
        -self.rotation.z_axis
    }

    /// The ray through pixel coordinates (u, v) (continuous; pixel centres at +0.5).
    pub fn ray(&self, u: f32, v: f32) -> Ray {
        let k = &self.intrinsics;
        let d_cam = Vec3::new((u - k.cx) / k.fx, -(v - k.cy) / k.fy, -1.0);
        let len = d_cam.length();
        Ray {
            origin: self.position,
            dir: self.rotation * (d_cam / len),
            z_per_t: 1.0 / len,
        }
    }

    /// The ray through the centre of pixel (x, y).
    pub fn pixel_ray(&self, x: u32, y: u32) -> Ray {
        self.ray(x as f32 + 0.5, y as f32 + 0.5)
    }

    /// Projects a world point to continuous pixel coordinates and z-depth. Points behind the
    /// camera get a non-positive depth.
    pub fn project(&self, world: Vec3) -> (f32, f32, f32) {
        let k = &self.intrinsics;
        let local = self.rotation.transpose() * (world - self.position);
        let z = -local.z;
        let u = k.fx * local.x / z + k.cx;
        let v = -k.fy * local.y / z + k.cy;
        (u, v, z)
    }

    /// The world point seen at continuous pixel (u, v) at z-depth `z`.
    pub fn unproject(&self, u: f32, v: f32, z: f32) -> Vec3 {
        let k = &self.intrinsics;
        let local = Vec3::new((u - k.cx) / k.fx * z, -(v - k.cy) / k.fy * z, -z);
        self.rotation * local + self.position
    }

    /// Interpolates between two poses: slerp of the rotations, lerp of the centres and of the
    /// intrinsics. `t` = 0 gives `self`, 1 gives `other`.
    pub fn interpolate(&self, other: &Camera, t: f32) -> Camera {
        let qa = Quat::from_mat3(&self.rotation).normalize();
        let mut qb = Quat::from_mat3(&other.rotation).normalize();
        if qa.dot(qb) < 0.0 {
            qb = -qb;
        }
        let a = &self.intrinsics;
        let b = &other.intrinsics;
        let lerp = |x: f32, y: f32| x + (y - x) * t;
        Camera {
            intrinsics: Intrinsics {
                fx: lerp(a.fx, b.fx),
                fy: lerp(a.fy, b.fy),
                cx: lerp(a.cx, b.cx),
                cy: lerp(a.cy, b.cy),
                width: a.width,
                height: a.height,
            },
            rotation: Mat3::from_quat(qa.slerp(qb, t)),
            position: self.position.lerp(other.position, t),
        }
    }
}

/// Parameters of the normalised-device-coordinate space used for forward-facing (LLFF)
/// scenes: rays are re-parameterised so that the near plane maps to z = −1 and infinity to
/// z = +1, as in the original NeRF code.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Ndc {
    pub fx: f32,
    pub fy: f32,
    pub width: u32,
    pub height: u32,
    /// Distance of the near plane along −z in the (shared, world) camera frame.
    pub near: f32,
}

impl Ndc {
    /// Converts a world ray (in the frame where the scene looks down −z) into an NDC ray.
    /// Returns the NDC origin and the (unnormalised) NDC direction; the NDC ray covers the
    /// scene for t in [0, 1].
    pub fn ray(&self, ray: &Ray) -> (Vec3, Vec3) {
        let (mut o, d) = (ray.origin, ray.dir);
        // Shift the origin to the near plane.
        let t = -(self.near + o.z) / d.z;
        o += t * d;
        let ax = -2.0 * self.fx / self.width as f32;
        let ay = -2.0 * self.fy / self.height as f32;
        let o_ndc = Vec3::new(ax * o.x / o.z, ay * o.y / o.z, 1.0 + 2.0 * self.near / o.z);
        let d_ndc = Vec3::new(
            ax * (d.x / d.z - o.x / o.z),
            ay * (d.y / d.z - o.y / o.z),
            -2.0 * self.near / o.z,
        );
        (o_ndc, d_ndc)
    }

    /// World-space z-depth along the camera of a point at NDC z (`z_ndc` in [−1, 1)).
    pub fn world_z(&self, z_ndc: f32) -> f32 {
        2.0 * self.near / (1.0 - z_ndc)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Camera {
        let k = Intrinsics {
            fx: 100.0,
            fy: 110.0,
            cx: 64.0,
            cy: 60.0,
            width: 128,
            height: 120,
        };
        Camera::look_at(k, Vec3::new(3.0, 1.0, 2.0), Vec3::ZERO, Vec3::Y)
    }

    #[test]
    fn project_inverts_unproject() {
        let c = cam();
        let p = c.unproject(10.5, 100.25, 2.5);
        let (u, v, z) = c.project(p);
        assert!((u - 10.5).abs() < 1e-3 && (v - 100.25).abs() < 1e-3 && (z - 2.5).abs() < 1e-4);
    }

    #[test]
    fn ray_hits_unprojected_point_at_its_depth() {
        let c = cam();
        let r = c.ray(30.0, 70.0);
        let p = c.unproject(30.0, 70.0, 1.7);
        let t = (p - r.origin).length();
        assert!((r.origin + t * r.dir - p).length() < 1e-4);
        assert!((t * r.z_per_t - 1.7).abs() < 1e-4);
    }

    #[test]
    fn look_at_centre_pixel_sees_target() {
        let c = cam();
        let (u, v, _) = c.project(Vec3::ZERO);
        assert!((u - 64.0).abs() < 1e-3 && (v - 60.0).abs() < 1e-3);
    }

    #[test]
    fn interpolation_ends_match_and_stays_rigid() {
        let a = cam();
        let b = Camera::look_at(a.intrinsics, Vec3::new(-2.0, 2.0, 1.0), Vec3::ZERO, Vec3::Y);
        let m = a.interpolate(&b, 0.5);
        assert!((a.interpolate(&b, 0.0).rotation - a.rotation).abs_diff_eq(Mat3::ZERO, 1e-5));
        assert!((a.interpolate(&b, 1.0).position - b.position).length() < 1e-5);
        let rtr = m.rotation.transpose() * m.rotation;
        assert!(rtr.abs_diff_eq(Mat3::IDENTITY, 1e-5));
    }

    #[test]
    fn c2w_rows_round_trip() {
        let c = cam();
        let rows = c.c2w_rows();
        let d = Camera::from_c2w_rows(c.intrinsics, &rows);
        assert!(d.rotation.abs_diff_eq(c.rotation, 1e-6) && d.position == c.position);
    }
}
