//! OpenCV lens distortion (radial k1..k4, tangential p1, p2) and undistortion of images and
//! depth maps to the ideal pinhole camera with the same intrinsics.
//!
//! Each output pixel centre is mapped through the distortion model to the place in the
//! recorded image where its light landed, and sampled there (bilinear for colour, nearest for
//! depth, whose z-value does not change with the lens). Samples outside the recorded image
//! clamp to its edge.

use image::{Rgb, Rgb32FImage};

use crate::camera::Intrinsics;

/// Distortion coefficients in the OpenCV convention (normalised image coordinates with y
/// pointing down, as nerfstudio and COLMAP write them).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Distortion {
    pub k1: f32,
    pub k2: f32,
    pub k3: f32,
    pub k4: f32,
    pub p1: f32,
    pub p2: f32,
}

impl Distortion {
    pub fn is_identity(&self) -> bool {
        *self == Self::default()
    }

    /// Where the ideal normalised point (x, y) appears in the distorted image.
    fn distort(&self, x: f32, y: f32) -> (f32, f32) {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * (self.k3 + r2 * self.k4)));
        let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        (xd, yd)
    }

    /// Continuous source pixel coordinates (pixel centres at +0.5) of each output pixel centre.
    fn source_coords(&self, k: &Intrinsics) -> impl Iterator<Item = (f32, f32)> + '_ {
        let k = *k;
        (0..k.height).flat_map(move |v| {
            (0..k.width).map(move |u| {
                let x = (u as f32 + 0.5 - k.cx) / k.fx;
                let y = (v as f32 + 0.5 - k.cy) / k.fy;
                let (xd, yd) = self.distort(x, y);
                (xd * k.fx + k.cx, yd * k.fy + k.cy)
            })
        })
    }

    /// The undistorted image (same size and intrinsics), bilinearly sampled.
    pub fn undistort_rgb(&self, img: &Rgb32FImage, k: &Intrinsics) -> Rgb32FImage {
        let (w, h) = img.dimensions();
        let at = |x: i64, y: i64| {
            img.get_pixel(
                x.clamp(0, w as i64 - 1) as u32,
                y.clamp(0, h as i64 - 1) as u32,
            )
            .0
        };
        let mut out = Rgb32FImage::new(w, h);
        for (p, (su, sv)) in out.pixels_mut().zip(self.source_coords(k)) {
            let (fx, fy) = (su - 0.5, sv - 0.5);
            let (x0, y0) = (fx.floor(), fy.floor());
            let (tx, ty) = (fx - x0, fy - y0);
            let (x0, y0) = (x0 as i64, y0 as i64);
            let (a, b, c, d) = (
                at(x0, y0),
                at(x0 + 1, y0),
                at(x0, y0 + 1),
                at(x0 + 1, y0 + 1),
            );
            *p = Rgb(std::array::from_fn(|i| {
                let top = a[i] + (b[i] - a[i]) * tx;
                let bottom = c[i] + (d[i] - c[i]) * tx;
                top + (bottom - top) * ty
            }));
        }
        out
    }

    /// The undistorted depth map (row-major, same size), nearest sampled.
    pub fn undistort_depth(&self, depth: &[f32], k: &Intrinsics) -> Vec<f32> {
        let (w, h) = (k.width as i64, k.height as i64);
        self.source_coords(k)
            .map(|(su, sv)| {
                let x = (su.floor() as i64).clamp(0, w - 1);
                let y = (sv.floor() as i64).clamp(0, h - 1);
                depth[(y * w + x) as usize]
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k() -> Intrinsics {
        Intrinsics {
            fx: 40.0,
            fy: 40.0,
            cx: 16.0,
            cy: 16.0,
            width: 32,
            height: 32,
        }
    }

    #[test]
    fn identity_distortion_keeps_the_image() {
        let img = Rgb32FImage::from_fn(32, 32, |x, y| Rgb([x as f32, y as f32, 0.0]));
        let out = Distortion::default().undistort_rgb(&img, &k());
        assert!(img.pixels().zip(out.pixels()).all(|(a, b)| a == b));
    }

    #[test]
    fn barrel_distortion_pulls_corners_inwards() {
        // With k1 < 0 a corner pixel of the ideal image was recorded closer to the centre.
        let d = Distortion {
            k1: -0.2,
            ..Default::default()
        };
        let (su, sv) = d.source_coords(&k()).next().unwrap();
        assert!(su > 0.5 && sv > 0.5, "{su} {sv}");
    }
}
