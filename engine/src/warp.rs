//! Differentiable depth-based warping between two rendered views, and its validity mask: the
//! W_ij and M_ij of the consistency loss L_co = ‖O_i − M_ij · W_ij(O_j)‖².
//!
//! For each pixel centre of view i with z-depth d_i: back-project with camera i to a world
//! point, project it into camera j (pixel coordinates and z-depth z_j) and sample view j there
//! bilinearly. The geometry depends only on the cameras and depths (data, not parameters), so
//! it is computed once on the CPU as four gather indices and four bilinear weights per pixel;
//! the warp itself is an `index_select` (backward: `index_add`) of image j followed by a
//! weighted sum, hence differentiable with respect to image j.
//!
//! A pixel is valid (mask 1) when its depth in view i is positive and finite, the projected
//! point lies in front of camera j with all four bilinear taps inside view j, and the point is
//! visible from j: every tap with non-zero weight has a positive depth d_j with
//! |z_j − d_j| ≤ `rel_tolerance` · z_j. Pixels whose depth is 0 count as unknown; callers mark
//! low-opacity (empty) pixels that way.

use candle_core::{Device, Tensor};

use crate::camera::Camera;
use crate::Result;

/// Settings of the visibility test.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WarpConfig {
    /// Allowed depth mismatch, relative to the depth in view j.
    pub rel_tolerance: f32,
}

impl Default for WarpConfig {
    fn default() -> Self {
        Self {
            rel_tolerance: 0.03,
        }
    }
}

/// The precomputed warp from view j into view i.
#[derive(Debug, Clone)]
pub struct Warp {
    width: usize,
    height: usize,
    /// Flattened pixel indices into view j, 4 per pixel of view i: `[H·W·4]` (u32).
    taps: Tensor,
    /// Bilinear weights `[H·W, 4]`, zero on invalid pixels.
    weights: Tensor,
    /// `[H, W]`, 1 where valid.
    mask: Tensor,
    valid: usize,
}

impl Warp {
    /// The warp from view j (camera `cam_j`, z-depth `depth_j`) into view i. Depths are
    /// row-major `H·W` in world units, 0 where unknown. Both views must have the same size.
    pub fn new(
        cam_i: &Camera,
        depth_i: &[f32],
        cam_j: &Camera,
        depth_j: &[f32],
        cfg: WarpConfig,
        device: &Device,
    ) -> Result<Self> {
        let (w, h) = (
            cam_i.intrinsics.width as usize,
            cam_i.intrinsics.height as usize,
        );
        let (wj, hj) = (
            cam_j.intrinsics.width as usize,
            cam_j.intrinsics.height as usize,
        );
        if (w, h) != (wj, hj) || depth_i.len() != w * h || depth_j.len() != w * h {
            return Err(crate::EngineError::config(
                "warp",
                format!(
                    "views must share one size: {w}×{h} (depth {}) vs {wj}×{hj} (depth {})",
                    depth_i.len(),
                    depth_j.len()
                ),
            ));
        }
        let n = w * h;
        let mut taps = vec![0u32; 4 * n];
        let mut weights = vec![0f32; 4 * n];
        let mut mask = vec![0f32; n];
        let mut valid = 0;
        for p in 0..n {
            let d = depth_i[p];
            if !(d > 0.0 && d.is_finite()) {
                continue;
            }
            let (x, y) = ((p % w) as f32 + 0.5, (p / w) as f32 + 0.5);
            let world = cam_i.unproject(x, y, d);
            let (u, v, z) = cam_j.project(world);
            if !(z > 0.0 && u.is_finite() && v.is_finite()) {
                continue;
            }
            // Continuous pixel-index coordinates (centres at integers).
            let (fx, fy) = (u - 0.5, v - 0.5);
            if fx < 0.0 || fy < 0.0 || fx > (w - 1) as f32 || fy > (h - 1) as f32 {
                continue;
            }
            let x0 = (fx.floor() as usize).min(w.saturating_sub(2));
            let y0 = (fy.floor() as usize).min(h.saturating_sub(2));
            let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
            let (ax, ay) = (fx - x0 as f32, fy - y0 as f32);
            let corner = [
                (y0 * w + x0, (1.0 - ax) * (1.0 - ay)),
                (y0 * w + x1, ax * (1.0 - ay)),
                (y1 * w + x0, (1.0 - ax) * ay),
                (y1 * w + x1, ax * ay),
            ];
            let visible = corner.iter().all(|&(q, wt)| {
                let dj = depth_j[q];
                wt == 0.0 || (dj > 0.0 && (z - dj).abs() <= cfg.rel_tolerance * dj)
            });
            if !visible {
                continue;
            }
            for (k, &(q, wt)) in corner.iter().enumerate() {
                taps[4 * p + k] = q as u32;
                weights[4 * p + k] = wt;
            }
            mask[p] = 1.0;
            valid += 1;
        }
        Ok(Self {
            width: w,
            height: h,
            taps: Tensor::from_vec(taps, 4 * n, device)?,
            weights: Tensor::from_vec(weights, (n, 4), device)?,
            mask: Tensor::from_vec(mask, (h, w), device)?,
            valid,
        })
    }

    /// Image j `[C, H, W]` warped into view i, `[C, H, W]`; zero where the mask is 0.
    pub fn apply(&self, image_j: &Tensor) -> Result<Tensor> {
        let (c, h, w) = image_j.dims3()?;
        if (h, w) != (self.height, self.width) {
            return Err(crate::EngineError::config(
                "warp",
                format!("image is {w}×{h}, warp is {}×{}", self.width, self.height),
            ));
        }
        let n = h * w;
        let gathered = image_j
            .reshape((c, n))?
            .index_select(&self.taps, 1)?
            .reshape((c, n, 4))?;
        Ok(gathered
            .broadcast_mul(&self.weights.unsqueeze(0)?)?
            .sum(2)?
            .reshape((c, h, w))?)
    }

    /// `[H, W]`: 1 where view i sees a point that view j also sees.
    pub fn mask(&self) -> &Tensor {
        &self.mask
    }

    /// Number of valid pixels.
    pub fn valid_pixels(&self) -> usize {
        self.valid
    }

    /// The consistency loss Σ M (O_i − W(O_j))² / (C · #valid): the mean squared difference
    /// over the valid pixels (0 when none are valid). Differentiable in both images.
    pub fn consistency_loss(&self, o_i: &Tensor, o_j: &Tensor) -> Result<Tensor> {
        let c = o_i.dim(0)?;
        let diff = o_i
            .broadcast_mul(&self.mask.unsqueeze(0)?)?
            .sub(&self.apply(o_j)?)?;
        Ok((diff.sqr()?.sum_all()? / (c * self.valid.max(1)) as f64)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use glam::Vec3;

    fn intr(size: u32) -> Intrinsics {
        Intrinsics {
            fx: size as f32,
            fy: size as f32,
            cx: size as f32 / 2.0,
            cy: size as f32 / 2.0,
            width: size,
            height: size,
        }
    }

    /// z-depth of the scene "plane z = −4, plus a square occluder |x|, |y| < 0.5 at z = −2"
    /// seen from `cam` (cameras look down −z from z = 0, no rotation).
    fn depth_two_planes(cam: &Camera) -> Vec<f32> {
        let k = cam.intrinsics;
        let mut out = Vec::new();
        for y in 0..k.height {
            for x in 0..k.width {
                let r = cam.pixel_ray(x, y);
                let t_occ = (-2.0 - r.origin.z) / r.dir.z;
                let p = r.origin + t_occ * r.dir;
                let t = if p.x.abs() < 0.5 && p.y.abs() < 0.5 {
                    t_occ
                } else {
                    (-4.0 - r.origin.z) / r.dir.z
                };
                out.push(t * r.z_per_t);
            }
        }
        out
    }

    #[test]
    fn identity_warp_is_exact_and_gradient_flows() {
        let cam = Camera::look_at(
            intr(16),
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(0.0, 0.0, -1.0),
            Vec3::Y,
        );
        let d = depth_two_planes(&cam);
        let warp = Warp::new(&cam, &d, &cam, &d, WarpConfig::default(), &Device::Cpu).unwrap();
        assert_eq!(warp.valid_pixels(), 16 * 16);
        let img = Tensor::rand(0f32, 1.0, (3, 16, 16), &Device::Cpu).unwrap();
        let out = warp.apply(&img).unwrap();
        let err = (out - &img)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(err < 1e-5);
        // Gradient of the loss w.r.t. image j reaches it (index_select → index_add).
        let v = candle_core::Var::from_tensor(&img).unwrap();
        let other = Tensor::zeros((3, 16, 16), candle_core::DType::F32, &Device::Cpu).unwrap();
        let g = warp
            .consistency_loss(&other, v.as_tensor())
            .unwrap()
            .backward()
            .unwrap();
        let gj = g.get(v.as_tensor()).unwrap();
        let expect = (&img * (2.0 / (3.0 * 256.0))).unwrap();
        let err = (gj - expect)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(err < 1e-6);
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let cam_i = Camera::look_at(intr(6), Vec3::ZERO, Vec3::new(0.0, 0.0, -1.0), Vec3::Y);
        let cam_j = Camera::look_at(
            intr(6),
            Vec3::new(0.13, 0.07, 0.0),
            Vec3::new(0.13, 0.07, -1.0),
            Vec3::Y,
        );
        let warp = Warp::new(
            &cam_i,
            &depth_two_planes(&cam_i),
            &cam_j,
            &depth_two_planes(&cam_j),
            WarpConfig::default(),
            &Device::Cpu,
        )
        .unwrap();
        assert!(warp.valid_pixels() > 0);
        let warp64 = Warp {
            weights: warp.weights.to_dtype(candle_core::DType::F64).unwrap(),
            ..warp.clone()
        };
        crate::style2d::gradcheck::check(&crate::style2d::gradcheck::random(&[2, 6, 6], 3), |x| {
            warp64.apply(x).map_err(candle_core::Error::wrap)
        });
    }

    #[test]
    fn warping_a_generated_scene_reproduces_the_neighbouring_view() {
        use crate::scene::generate::{generate, GenerateOptions};
        use crate::scene::{LoadOptions, Scene};
        let dir = tempfile::tempdir().unwrap();
        generate(
            &GenerateOptions {
                size: 128,
                views: 48,
                ..Default::default()
            },
            dir.path(),
        )
        .unwrap();
        let scene = Scene::load(
            dir.path(),
            &LoadOptions {
                test_every: 0,
                ..Default::default()
            },
        )
        .unwrap();
        let to_chw = |f: &crate::scene::Frame| {
            let (w, h) = f.image.dimensions();
            Tensor::from_slice(f.image.as_raw(), (h as usize, w as usize, 3), &Device::Cpu)
                .unwrap()
                .permute((2, 0, 1))
                .unwrap()
        };
        // Consecutive orbit frames are 22.5° apart.
        for (i, j) in [(8, 9), (20, 21), (9, 8)] {
            let (fi, fj) = (&scene.frames[i], &scene.frames[j]);
            let (di, dj) = (fi.depth.as_ref().unwrap(), fj.depth.as_ref().unwrap());
            let warp = Warp::new(
                &fi.camera,
                di,
                &fj.camera,
                dj,
                WarpConfig::default(),
                &Device::Cpu,
            )
            .unwrap();
            let foreground = di.iter().filter(|&&d| d > 0.0).count();
            assert!(
                warp.valid_pixels() * 2 > foreground,
                "{} of {foreground} valid",
                warp.valid_pixels()
            );
            let (img_i, img_j) = (to_chw(fi), to_chw(fj));
            let mask = warp.mask().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            // Per-pixel error (max over channels) on the valid pixels.
            let errors = |a: &Tensor| -> Vec<f32> {
                let e = (a - &img_i)
                    .unwrap()
                    .abs()
                    .unwrap()
                    .max(0)
                    .unwrap()
                    .flatten_all()
                    .unwrap()
                    .to_vec1::<f32>()
                    .unwrap();
                let mut v: Vec<f32> = e
                    .into_iter()
                    .zip(&mask)
                    .filter(|(_, &m)| m > 0.0)
                    .map(|(e, _)| e)
                    .collect();
                v.sort_by(f32::total_cmp);
                v
            };
            let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
            let warped = errors(&warp.apply(&img_j).unwrap());
            // Without warping, the same pixels of view j differ far more.
            let unwarped = errors(&img_j);
            let median = warped[warped.len() / 2];
            // What remains is resampling of the checker textures at their edges.
            assert!(
                median < 0.01 && mean(&warped) < 0.04,
                "{i}←{j}: median {median}, mean {}",
                mean(&warped)
            );
            assert!(
                mean(&warped) * 3.0 < mean(&unwarped),
                "{i}←{j}: {} vs unwarped {}",
                mean(&warped),
                mean(&unwarped)
            );
        }
    }

    #[test]
    fn translation_warp_reproduces_view_and_masks_occlusion() {
        // Views of a textured two-plane scene from two camera positions; the texture is a
        // function of the world point, so the true warp is known exactly.
        let size = 48;
        let cam_i = Camera::look_at(intr(size), Vec3::ZERO, Vec3::new(0.0, 0.0, -1.0), Vec3::Y);
        let cam_j = Camera::look_at(
            intr(size),
            Vec3::new(0.4, 0.0, 0.0),
            Vec3::new(0.4, 0.0, -1.0),
            Vec3::Y,
        );
        let texture = |p: Vec3| {
            [
                (p.x * 2.0).sin() * 0.5 + 0.5,
                (p.y * 3.0).cos() * 0.5 + 0.5,
                (p.z + 3.0) * 0.5,
            ]
        };
        let render = |cam: &Camera, depth: &[f32]| -> Tensor {
            let mut rgb = vec![0f32; 3 * depth.len()];
            for (p, &d) in depth.iter().enumerate() {
                let (x, y) = (
                    (p % size as usize) as f32 + 0.5,
                    (p / size as usize) as f32 + 0.5,
                );
                let c = texture(cam.unproject(x, y, d));
                for k in 0..3 {
                    rgb[k * depth.len() + p] = c[k];
                }
            }
            Tensor::from_vec(rgb, (3, size as usize, size as usize), &Device::Cpu).unwrap()
        };
        let (di, dj) = (depth_two_planes(&cam_i), depth_two_planes(&cam_j));
        let (img_i, img_j) = (render(&cam_i, &di), render(&cam_j, &dj));
        let warp = Warp::new(
            &cam_i,
            &di,
            &cam_j,
            &dj,
            WarpConfig::default(),
            &Device::Cpu,
        )
        .unwrap();
        let mask = warp.mask().flatten_all().unwrap().to_vec1::<f32>().unwrap();
        // Known occlusions: background points of view i that are hidden behind the occluder
        // (or out of frame) from camera j must be masked.
        let mut hidden = 0;
        for (p, &d) in di.iter().enumerate() {
            let (x, y) = (
                (p % size as usize) as f32 + 0.5,
                (p / size as usize) as f32 + 0.5,
            );
            let world = cam_i.unproject(x, y, d);
            let seg = world - cam_j.position;
            let t = (-2.0 - cam_j.position.z) / seg.z;
            let q = cam_j.position + t * seg;
            let blocked = t < 1.0 - 1e-3 && q.x.abs() < 0.5 && q.y.abs() < 0.5;
            if blocked {
                hidden += 1;
                assert_eq!(mask[p], 0.0, "pixel {p} is occluded from j but valid");
            }
        }
        assert!(
            hidden > 20,
            "the test geometry must contain occlusions ({hidden})"
        );
        assert!(warp.valid_pixels() > size as usize * size as usize / 2);
        let warped = warp.apply(&img_j).unwrap();
        let m = warp.mask().unsqueeze(0).unwrap();
        let err = ((warped - img_i.broadcast_mul(&m).unwrap())
            .unwrap()
            .abs()
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap())
            / (3 * warp.valid_pixels()) as f32;
        assert!(err < 0.02, "masked warp error {err}");
    }
}
