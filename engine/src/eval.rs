//! The consistency and style-fidelity evaluation of stylized frame sequences.
//!
//! Consistency: for every pair of frames (t, t + g) along a camera path, frame t + g is warped
//! into frame t with the field's depth and both cameras ([`crate::warp`]), and the error is
//! taken over the pixels both frames see (occlusion- and frame-masked). Over all pairs of a
//! gap: RMSE = sqrt(Σ err² / n) and MAE = Σ |err| / n, n counting every valid pixel and
//! channel. A frame sequence that is a rendering of one coloured 3D scene scores ≈ 0; frame-by-
//! frame 2D stylization flickers and scores higher.
//!
//! Style fidelity: AdaIN's style loss of each frame against the style image (mean and std of
//! relu1_1 … relu4_1), and the content loss (relu4_1 MSE) against the unstylized rendering —
//! a method that is consistent only because it is flat or blurry shows up here.

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::per_view::per_view;
use crate::style2d::encoder::VggEncoder;
use crate::style2d::losses::{content_loss, style_loss};
use crate::style2d::network::StyleTarget;
use crate::warp::{Warp, WarpConfig};
use crate::Result;

/// Warped error of one frame gap.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GapError {
    pub gap: usize,
    pub rmse: f64,
    pub mae: f64,
    /// Pairs with at least one valid pixel.
    pub pairs: usize,
    /// Mean fraction of valid pixels per pair.
    pub coverage: f64,
}

/// The warps of frame t + `gap` into frame t for every pair along a camera path. They depend
/// only on the cameras and the depth, so they are built once and applied to every method's
/// frames (and every style's).
pub struct PathWarps {
    gap: usize,
    /// `(t, warp)` for the pairs with at least one valid pixel.
    warps: Vec<(usize, Warp)>,
    pixels_per_frame: usize,
}

impl PathWarps {
    /// `depths`: row-major z-depth per frame (0 where unknown/empty).
    pub fn new(
        cameras: &[Camera],
        depths: &[Vec<f32>],
        gap: usize,
        cfg: WarpConfig,
        device: &Device,
    ) -> Result<Self> {
        let mut warps = Vec::new();
        for t in 0..cameras.len().saturating_sub(gap) {
            let u = t + gap;
            let warp = Warp::new(
                &cameras[t],
                &depths[t],
                &cameras[u],
                &depths[u],
                cfg,
                device,
            )?;
            if warp.valid_pixels() > 0 {
                warps.push((t, warp));
            }
        }
        Ok(Self {
            gap,
            warps,
            pixels_per_frame: depths.first().map_or(0, Vec::len),
        })
    }

    /// Masked warped error of `frames` (`[3, H, W]` per camera, RGB in [0, 1]) over all pairs:
    /// RMSE and MAE over every valid pixel and channel.
    pub fn error(&self, frames: &[Tensor]) -> Result<GapError> {
        let (mut sq, mut abs, mut n, mut coverage) = (0.0f64, 0.0f64, 0usize, 0.0);
        for (t, warp) in &self.warps {
            let c = frames[*t].dim(0)?;
            let diff = frames[*t]
                .broadcast_mul(&warp.mask().unsqueeze(0)?)?
                .sub(&warp.apply(&frames[t + self.gap])?)?;
            sq += diff.sqr()?.sum_all()?.to_scalar::<f32>()? as f64;
            abs += diff.abs()?.sum_all()?.to_scalar::<f32>()? as f64;
            n += c * warp.valid_pixels();
            coverage += warp.valid_pixels() as f64 / self.pixels_per_frame as f64;
        }
        let pairs = self.warps.len();
        let n = n.max(1) as f64;
        Ok(GapError {
            gap: self.gap,
            rmse: (sq / n).sqrt(),
            mae: abs / n,
            pairs,
            coverage: coverage / pairs.max(1) as f64,
        })
    }
}

/// Mean style loss of `frames` (`[3, H, W]`, H and W multiples of 8) against `style`, and mean
/// content loss against the relu4_1 features `[1, 512, H/8, W/8]` of the reference frames.
pub fn fidelity(
    encoder: &VggEncoder,
    frames: &[Tensor],
    reference_features: &[Tensor],
    style: &StyleTarget,
) -> Result<(f64, f64)> {
    let losses = per_view(
        frames.len().min(reference_features.len()),
        frames.first().map_or(&Device::Cpu, |f| f.device()),
        None,
        |k| {
            let feats = encoder.features(&frames[k].unsqueeze(0)?)?;
            Ok((
                style_loss(&feats, &style.stats)?.to_scalar::<f32>()? as f64,
                content_loss(&feats[3], &reference_features[k])?.to_scalar::<f32>()? as f64,
            ))
        },
        |_| {},
    )?;
    let (st, ct) = losses
        .iter()
        .fold((0.0, 0.0), |(s, c), (ds, dc)| (s + ds, c + dc));
    let n = frames.len().max(1) as f64;
    Ok((st / n, ct / n))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Intrinsics;
    use glam::{Mat3, Vec3};

    /// Cameras sliding sideways in front of a plane at z = −4 whose colour is a function of
    /// the world x: frames of one 3D scene.
    fn scene(frames: usize, size: usize) -> (Vec<Camera>, Vec<Vec<f32>>, Vec<Tensor>) {
        let k = Intrinsics {
            fx: size as f32,
            fy: size as f32,
            cx: size as f32 / 2.0,
            cy: size as f32 / 2.0,
            width: size as u32,
            height: size as u32,
        };
        let mut cams = Vec::new();
        let mut depths = Vec::new();
        let mut imgs = Vec::new();
        for f in 0..frames {
            let cam = Camera {
                intrinsics: k,
                rotation: Mat3::IDENTITY,
                position: Vec3::new(f as f32 * 0.1, 0.0, 0.0),
            };
            let mut rgb = vec![0f32; 3 * size * size];
            for y in 0..size {
                for x in 0..size {
                    let wx = cam.position.x + (x as f32 + 0.5 - k.cx) / k.fx * 4.0;
                    let v = 0.5 + 0.4 * (wx * 3.0).sin();
                    for c in 0..3 {
                        rgb[c * size * size + y * size + x] = v * (c as f32 + 1.0) / 3.0;
                    }
                }
            }
            imgs.push(Tensor::from_vec(rgb, (3, size, size), &Device::Cpu).unwrap());
            depths.push(vec![4.0; size * size]);
            cams.push(cam);
        }
        (cams, depths, imgs)
    }

    #[test]
    fn one_scene_scores_near_zero_and_flicker_scores_worse() {
        let (cams, depths, frames) = scene(6, 32);
        let dev = Device::Cpu;
        let cfg = WarpConfig::default();
        let warps = PathWarps::new(&cams, &depths, 1, cfg, &dev).unwrap();
        let good = warps.error(&frames).unwrap();
        assert_eq!(good.pairs, 5);
        assert!(good.coverage > 0.8, "{good:?}");
        // Only bilinear resampling error of a smooth pattern remains.
        assert!(good.rmse < 0.01 && good.mae <= good.rmse, "{good:?}");
        // Identical frames from identical cameras: exactly zero.
        let same_cams = vec![cams[0]; 3];
        let same_frames = vec![frames[0].clone(); 3];
        let same = PathWarps::new(&same_cams, &depths[..3], 1, cfg, &dev)
            .unwrap()
            .error(&same_frames)
            .unwrap();
        assert!(same.rmse < 1e-6, "{same:?}");
        // Flicker: every other frame brightened by 0.1 — the error is about 0.1.
        let flicker: Vec<Tensor> = frames
            .iter()
            .enumerate()
            .map(|(i, f)| {
                if i % 2 == 1 {
                    (f + 0.1).unwrap()
                } else {
                    f.clone()
                }
            })
            .collect();
        let bad = warps.error(&flicker).unwrap();
        assert!(bad.rmse > 0.09 && bad.rmse < 0.11, "{bad:?}");
        // No frame pairs at a gap longer than the sequence.
        let none = PathWarps::new(&cams, &depths, 10, cfg, &dev)
            .unwrap()
            .error(&frames)
            .unwrap();
        assert_eq!(none.pairs, 0);
    }
}
