//! Rectangular windows of a view, aligned to the encoder's stride: what the 2D training steps
//! work on instead of whole views (a 64² window of a 128² view costs a quarter of the
//! decoder and encoder passes). A window of a view is itself a view: its camera is the view's
//! camera with the principal point shifted, so warps between windows need nothing new.

use candle_core::Tensor;

use crate::camera::Camera;
use crate::rng::Rng;
use crate::style2d::arch::VggArch;
use crate::Result;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Window {
    pub x: usize,
    pub y: usize,
    pub width: usize,
    pub height: usize,
}

impl Window {
    /// The whole `width`×`height` view.
    pub fn full(width: usize, height: usize) -> Self {
        Self {
            x: 0,
            y: 0,
            width,
            height,
        }
    }

    /// A random square window of side `size` (at most the view; rounded down to the stride);
    /// `size` 0 means the whole view.
    pub fn random(width: usize, height: usize, size: usize, rng: &mut Rng) -> Self {
        if size == 0 {
            return Self::full(width, height);
        }
        let s = VggArch::STRIDE;
        let size = (size.min(width).min(height) / s * s).max(s);
        let x = rng.below((width - size) / s + 1) * s;
        let y = rng.below((height - size) / s + 1) * s;
        Self {
            x,
            y,
            width: size,
            height: size,
        }
    }

    /// A window of the same size in view j showing what this window of view i shows: centred
    /// on where the window's centre (at the median valid depth of `depth_i`, the view's
    /// row-major z-depth, 0 = unknown) projects into `cam_j`, clamped to the view and aligned
    /// to the stride. Without a valid depth, the same window.
    pub fn follow(
        &self,
        cam_i: &Camera,
        depth_i: &[f32],
        view_width: usize,
        cam_j: &Camera,
    ) -> Self {
        let mut d: Vec<f32> = self
            .pixels(view_width)
            .into_iter()
            .map(|p| depth_i[p])
            .filter(|d| *d > 0.0 && d.is_finite())
            .collect();
        if d.is_empty() {
            return *self;
        }
        let mid = d.len() / 2;
        let z = *d.select_nth_unstable_by(mid, f32::total_cmp).1;
        let (cu, cv) = (
            (self.x + self.width / 2) as f32,
            (self.y + self.height / 2) as f32,
        );
        let (u, v, zj) = cam_j.project(cam_i.unproject(cu, cv, z));
        if zj <= 0.0 || !u.is_finite() || !v.is_finite() {
            return *self;
        }
        let s = VggArch::STRIDE as f32;
        let (vw, vh) = (
            cam_j.intrinsics.width as usize,
            cam_j.intrinsics.height as usize,
        );
        let place = |c: f32, size: usize, limit: usize| -> usize {
            let start = ((c - size as f32 / 2.0) / s).round().max(0.0) * s;
            (start as usize).min(limit - size)
        };
        Self {
            x: place(u, self.width, vw),
            y: place(v, self.height, vh),
            ..*self
        }
    }

    /// Row-major pixel indices of the window in a `view_width`-wide view.
    pub fn pixels(&self, view_width: usize) -> Vec<usize> {
        (self.y..self.y + self.height)
            .flat_map(|r| (self.x..self.x + self.width).map(move |c| r * view_width + c))
            .collect()
    }

    /// The window's values of a row-major per-pixel plane.
    pub fn crop_plane(&self, plane: &[f32], view_width: usize) -> Vec<f32> {
        self.pixels(view_width)
            .into_iter()
            .map(|p| plane[p])
            .collect()
    }

    /// The window of a `[B, C, H, W]` map at `1/scale` of the view's resolution.
    pub fn crop(&self, t: &Tensor, scale: usize) -> Result<Tensor> {
        Ok(t.narrow(2, self.y / scale, self.height / scale)?.narrow(
            3,
            self.x / scale,
            self.width / scale,
        )?)
    }

    /// The camera of the window: the view's camera with the principal point shifted.
    pub fn camera(&self, camera: &Camera) -> Camera {
        let mut c = *camera;
        c.intrinsics.cx -= self.x as f32;
        c.intrinsics.cy -= self.y as f32;
        c.intrinsics.width = self.width as u32;
        c.intrinsics.height = self.height as u32;
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use glam::Vec3;

    fn camera(x: f32) -> Camera {
        let k = Intrinsics {
            fx: 64.0,
            fy: 64.0,
            cx: 64.0,
            cy: 64.0,
            width: 128,
            height: 128,
        };
        Camera::look_at(k, Vec3::new(x, 0.0, 4.0), Vec3::new(x, 0.0, 0.0), Vec3::Y)
    }

    #[test]
    fn window_cameras_see_the_same_rays_and_windows_follow_the_scene() {
        let cam = camera(0.0);
        let w = Window {
            x: 40,
            y: 24,
            width: 32,
            height: 32,
        };
        let wc = w.camera(&cam);
        let (a, b) = (cam.pixel_ray(45, 30), wc.pixel_ray(5, 6));
        assert!((a.dir - b.dir).length() < 1e-6);
        // A plane at depth 4: the window moves left in a camera shifted right by 1 unit
        // (64 px per unit at depth 4 · 64 / 4 = 16 px).
        let depth = vec![4.0; 128 * 128];
        let f = w.follow(&cam, &depth, 128, &camera(1.0));
        assert_eq!((f.x, f.y, f.width), (24, 24, 32));
        // Unknown depth: the same window.
        assert_eq!(w.follow(&cam, &vec![0.0; 128 * 128], 128, &camera(1.0)), w);
        let mut rng = Rng::new(1);
        for _ in 0..50 {
            let r = Window::random(128, 96, 64, &mut rng);
            assert!(
                r.x.is_multiple_of(8) && r.y.is_multiple_of(8) && r.x + 64 <= 128 && r.y + 64 <= 96
            );
        }
        assert_eq!(Window::random(40, 32, 0, &mut rng), Window::full(40, 32));
    }
}
