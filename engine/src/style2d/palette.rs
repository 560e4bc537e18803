//! A painting's palette as a colour map applied to a stylization's output (the 2D decoders',
//! the stylized NeRF's). The HED encoder's features carry the strokes (luma structure) well
//! and colour poorly, so an AdaIN decoder of them paints the painting's strokes in a palette
//! partly its own, and a NeRF trained on its losses and its output inherits it. The map fixes the chroma
//! and leaves the strokes: in BT.601 YCbCr it carries the output's chroma (Cb, Cr) mean and
//! covariance onto the painting's with the optimal transport map between two Gaussians
//! (`A = Σ_s^{-1/2} (Σ_s^{1/2} Σ_t Σ_s^{1/2})^{1/2} Σ_s^{-1/2}`, the map that moves colours
//! least), and shifts luma to the painting's mean without scaling it — the colour transfer of
//! Gatys et al. 2017 ("Controlling Perceptual Factors in Neural Style Transfer") in
//! optimal-transport form, restricted to chroma. As an RGB map it is affine:
//! `x ↦ matrix · x + offset`; what is shown is then brought into the gamut at constant luma
//! and hue ([`into_gamut`]).
//!
//! A job fits one map per style and per decoder or stylized NeRF, from its output on the
//! scene's views pooled to the painting's pixels, and applies it to that output wherever it
//! is shown: one map for every view, so it moves no view against another.

use candle_core::Tensor;
use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use serde::{Deserialize, Serialize};

use super::images::tensor_to_hwc;
use crate::{EngineError, Result};

/// Added to each covariance's diagonal, as a fraction of its mean variance (plus a floor): a
/// flat image has a singular covariance.
const RIDGE: f64 = 1e-3;

fn regularised(cov: &Matrix3<f64>) -> Matrix3<f64> {
    cov + Matrix3::identity() * (RIDGE * cov.trace() / 3.0 + 1e-8)
}

/// Mean and covariance of a number of RGB pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColourMoments {
    pub pixels: f64,
    pub mean: Vector3<f64>,
    pub cov: Matrix3<f64>,
}

impl ColourMoments {
    /// The moments of images given as interleaved RGB, pooled; `None` without a pixel.
    pub fn of(images: &[&[f32]]) -> Option<Self> {
        let n = images.iter().map(|i| i.len() / 3).sum::<usize>();
        if n == 0 {
            return None;
        }
        let pixels = || {
            images
                .iter()
                .flat_map(|i| i.chunks_exact(3))
                .map(|p| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64))
        };
        let mean = pixels().sum::<Vector3<f64>>() / n as f64;
        let cov = pixels()
            .map(|p| (p - mean) * (p - mean).transpose())
            .sum::<Matrix3<f64>>()
            / n as f64;
        Some(Self {
            pixels: n as f64,
            mean,
            cov,
        })
    }

    /// The moments of one image `[1, 3, H, W]` or `[3, H, W]` as seen (clamped to [0, 1]);
    /// `None` without a pixel.
    pub fn of_image(image: &Tensor) -> Result<Option<Self>> {
        Ok(Self::of(&[&tensor_to_hwc(image)?.2]))
    }

    /// The moments of several sets of pixels pooled, as if measured at once (so images can
    /// be measured one at a time); `None` without a pixel.
    pub fn pool(parts: &[ColourMoments]) -> Option<Self> {
        let n: f64 = parts.iter().map(|p| p.pixels).sum();
        if n == 0.0 {
            return None;
        }
        let mean = parts
            .iter()
            .map(|p| p.mean * p.pixels)
            .sum::<Vector3<f64>>()
            / n;
        let cov = parts
            .iter()
            .map(|p| (p.cov + (p.mean - mean) * (p.mean - mean).transpose()) * p.pixels)
            .sum::<Matrix3<f64>>()
            / n;
        Some(Self {
            pixels: n,
            mean,
            cov,
        })
    }
}

/// An affine colour map `x ↦ matrix · x + offset` on RGB.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Palette {
    pub matrix: [[f32; 3]; 3],
    pub offset: [f32; 3],
}

impl Default for Palette {
    fn default() -> Self {
        Self::IDENTITY
    }
}

/// The linear part of the optimal transport map between centred Gaussians of covariances `s`
/// and `t` (both positive definite).
fn gaussian_map(s: &Matrix3<f64>, t: &Matrix3<f64>) -> Matrix3<f64> {
    let s_half = spectral(s, f64::sqrt);
    let s_inv_half = spectral(s, |l| 1.0 / l.sqrt());
    s_inv_half * spectral(&(s_half * t * s_half), f64::sqrt) * s_inv_half
}

/// RGB → BT.601 YCbCr (full range, no offsets).
fn ycbcr() -> Matrix3<f64> {
    Matrix3::new(
        0.299, 0.587, 0.114, //
        -0.168736, -0.331264, 0.5, //
        0.5, -0.418688, -0.081312,
    )
}

/// `f(S)` for a symmetric positive semi-definite `S`, applied to its eigenvalues.
fn spectral(s: &Matrix3<f64>, f: impl Fn(f64) -> f64) -> Matrix3<f64> {
    let eig = SymmetricEigen::new(*s);
    let d = Matrix3::from_diagonal(&eig.eigenvalues.map(|l| f(l.max(0.0))));
    eig.eigenvectors * d * eig.eigenvectors.transpose()
}

impl Palette {
    pub const IDENTITY: Palette = Palette {
        matrix: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        offset: [0.0; 3],
    };

    /// The map from colours with moments `from` to colours with moments `to`: the optimal
    /// transport map of the chroma (Cb, Cr of BT.601 YCbCr), with luma shifted to `to`'s mean
    /// and its contrast (the strokes) kept.
    pub fn transport(from: &ColourMoments, to: &ColourMoments) -> Palette {
        let y = ycbcr();
        let y_inv = y.try_inverse().expect("YCbCr is invertible");
        // Chroma covariance in YCbCr, luma set apart (unit variance, uncorrelated): the map
        // leaves it as it is.
        let chroma = |m: &ColourMoments| {
            let mut c = regularised(&(y * m.cov * y.transpose()));
            for k in 0..3 {
                let unit = if k == 0 { 1.0 } else { 0.0 };
                (c[(0, k)], c[(k, 0)]) = (unit, unit);
            }
            c
        };
        let a = gaussian_map(&chroma(from), &chroma(to));
        Self::affine(y_inv * a * y, y_inv * (y * to.mean - a * (y * from.mean)))
    }

    fn affine(a: Matrix3<f64>, offset: Vector3<f64>) -> Palette {
        Palette {
            matrix: std::array::from_fn(|r| std::array::from_fn(|c| a[(r, c)] as f32)),
            offset: std::array::from_fn(|r| offset[r] as f32),
        }
    }

    /// The map that gives `outputs` (images `[1, 3, H, W]` or `[3, H, W]`, pooled, as seen:
    /// clamped to [0, 1]) the chroma moments and mean luma of `painting` (one such image).
    pub fn fit(outputs: &[Tensor], painting: &Tensor) -> Result<Palette> {
        let parts = outputs
            .iter()
            .map(ColourMoments::of_image)
            .collect::<Result<Vec<_>>>()?;
        Self::fit_moments(&parts.into_iter().flatten().collect::<Vec<_>>(), painting)
    }

    /// [`Self::fit`] from the outputs' moments, measured one image at a time.
    pub fn fit_moments(outputs: &[ColourMoments], painting: &Tensor) -> Result<Palette> {
        let none = || EngineError::config("palette", "no pixels to fit a palette to");
        let from = ColourMoments::pool(outputs).ok_or_else(none)?;
        let to = ColourMoments::of_image(painting)?.ok_or_else(none)?;
        Ok(Self::transport(&from, &to))
    }

    /// The weighted mean of maps (weights normalised; a blend of styles, or a map applied
    /// with strength α as `[(map, α), (IDENTITY, 1 − α)]`).
    pub fn blend(parts: &[(Palette, f32)]) -> Palette {
        let total: f32 = parts.iter().map(|(_, w)| w).sum();
        let mut out = Palette {
            matrix: [[0.0; 3]; 3],
            offset: [0.0; 3],
        };
        for (p, w) in parts {
            let w = w / total;
            for r in 0..3 {
                out.offset[r] += w * p.offset[r];
                for c in 0..3 {
                    out.matrix[r][c] += w * p.matrix[r][c];
                }
            }
        }
        out
    }

    /// The affine map on planar colours `[B, 3, N]`: `matrix · x + offset`, unbounded.
    fn affine_planar(&self, planar: &Tensor) -> Result<Tensor> {
        let (b, _, _) = planar.dims3()?;
        let dev = planar.device();
        let m = Tensor::new(&self.matrix, dev)?.to_dtype(planar.dtype())?;
        let o = Tensor::new(&self.offset, dev)?
            .to_dtype(planar.dtype())?
            .reshape((1, 3, 1))?;
        Ok(m.unsqueeze(0)?
            .broadcast_as((b, 3, 3))?
            .contiguous()?
            .matmul(&planar.contiguous()?)?
            .broadcast_add(&o)?)
    }

    /// The map applied to images `[B, 3, H, W]`, as shown: in gamut (see [`into_gamut`]).
    pub fn apply(&self, images: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = images.dims4()?;
        let mapped = self.affine_planar(&images.reshape((b, c, h * w))?)?;
        Ok(into_gamut(&mapped)?.reshape((b, c, h, w))?)
    }

    /// The map applied to pixel rows `[N, 3]`, as shown: in gamut (see [`into_gamut`]).
    pub fn apply_rows(&self, rows: &Tensor) -> Result<Tensor> {
        let mapped = self.affine_planar(&rows.t()?.unsqueeze(0)?)?;
        Ok(into_gamut(&mapped)?.squeeze(0)?.t()?)
    }

    /// The affine map alone, in place on interleaved RGB (colours may leave [0, 1]): the map
    /// whose moments [`Self::transport`] matches.
    pub fn affine_rgb(&self, rgb: &mut [f32]) {
        for p in rgb.chunks_exact_mut(3) {
            let x = [p[0], p[1], p[2]];
            for (r, out) in p.iter_mut().enumerate() {
                *out = self.offset[r] + (0..3).map(|c| self.matrix[r][c] * x[c]).sum::<f32>();
            }
        }
    }
}

/// BT.601 luma weights (the first row of [`ycbcr`]); they sum to 1, so adding `t · (1, 1, 1)`
/// to a colour moves its luma by `t` and leaves its chroma.
const LUMA: [f32; 3] = [0.299, 0.587, 0.114];

/// Planar colours `[B, 3, N]` brought into [0, 1] as a chroma clip at constant luma and hue:
/// each colour keeps its luma (clamped to [0, 1]) and the direction of its chroma (Cb, Cr),
/// and loses only as much chroma as puts its furthest channel on the gamut's edge. Clamping
/// each channel instead changes luma and hue: a deep blue whose red and green the map takes
/// below zero comes out brighter and purer, and the shading inside such a patch is lost. The
/// palette's map leaves the gamut on 9–22 % of the pixels for some paintings (BENCHMARKS.md,
/// "The painting's palette").
fn into_gamut(rgb: &Tensor) -> Result<Tensor> {
    const EPS: f64 = 1e-6;
    let luma_weights = Tensor::new(&LUMA, rgb.device())?
        .to_dtype(rgb.dtype())?
        .reshape((1, 3, 1))?;
    let luma = rgb.broadcast_mul(&luma_weights)?.sum_keepdim(1)?;
    let y = luma.clamp(0f32, 1f32)?;
    // The colour is y + chroma: chroma has no luma, and scaling it keeps the hue.
    let chroma = rgb.broadcast_sub(&luma)?;
    let size = chroma.abs()?.maximum(EPS)?;
    // The largest scale of each channel's chroma that keeps it in [0, 1] (1: no limit).
    let up = (1.0 - &y)?.broadcast_div(&size)?;
    let down = y.broadcast_div(&size)?;
    let free = Tensor::ones_like(&chroma)?;
    let limit = chroma
        .gt(EPS)?
        .where_cond(&up, &chroma.lt(-EPS)?.where_cond(&down, &free)?)?;
    let scale = limit.min_keepdim(1)?.clamp(0f32, 1f32)?;
    Ok(y.broadcast_add(&chroma.broadcast_mul(&scale)?)?
        .clamp(0f32, 1f32)?)
}

/// The stages' `palette` setting when a configuration does not name it (those written before
/// palettes existed): palettes are fitted.
pub(crate) fn fitted_by_default() -> bool {
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use candle_core::Device;

    /// Correlated, shifted colours: `n` pixels of `base + mix · normal`.
    fn colours(seed: u64, base: [f32; 3], mix: [[f32; 3]; 3], n: usize) -> Vec<f32> {
        let mut rng = Rng::new(seed);
        let mut out = Vec::with_capacity(3 * n);
        for _ in 0..n {
            let z = [rng.normal(), rng.normal(), rng.normal()];
            for r in 0..3 {
                out.push(base[r] + (0..3).map(|c| mix[r][c] * z[c]).sum::<f32>());
            }
        }
        out
    }

    /// Moments of the colours in YCbCr.
    fn in_ycbcr(m: &ColourMoments) -> ColourMoments {
        let y = ycbcr();
        ColourMoments {
            pixels: m.pixels,
            mean: y * m.mean,
            cov: y * m.cov * y.transpose(),
        }
    }

    #[test]
    fn the_map_carries_chroma_onto_the_targets_and_keeps_luma_contrast() {
        let from = colours(
            1,
            [0.3, 0.5, 0.2],
            [[0.1, 0.02, 0.0], [0.0, 0.05, 0.03], [0.01, 0.0, 0.08]],
            4000,
        );
        let to = colours(
            2,
            [0.7, 0.4, 0.6],
            [[0.02, 0.0, 0.0], [0.1, 0.1, 0.0], [0.0, -0.04, 0.15]],
            4000,
        );
        let (mf, mt) = (
            ColourMoments::of(&[&from]).unwrap(),
            ColourMoments::of(&[&to]).unwrap(),
        );
        let p = Palette::transport(&mf, &mt);
        let mut mapped = from.clone();
        p.affine_rgb(&mut mapped);
        let (got, want, before) = (
            in_ycbcr(&ColourMoments::of(&[&mapped]).unwrap()),
            in_ycbcr(&mt),
            in_ycbcr(&mf),
        );
        // Luma: the target's mean, the source's variance.
        assert!((got.mean[0] - want.mean[0]).abs() < 1e-5);
        assert!((got.cov[(0, 0)] - before.cov[(0, 0)]).abs() < 1e-6 * before.cov[(0, 0)].max(1.0));
        // Chroma: the target's mean and covariance, but for the ridge.
        let scale = want.cov.amax();
        for r in 1..3 {
            assert!(
                (got.mean[r] - want.mean[r]).abs() < 1e-5,
                "{got:?} vs {want:?}"
            );
            for c in 1..3 {
                let d = (got.cov[(r, c)] - want.cov[(r, c)]).abs();
                assert!(d < 10.0 * RIDGE * scale, "{got:?} vs {want:?}");
            }
        }
        // A distribution mapped onto itself stays where it is.
        let same = Palette::transport(&mf, &mf);
        for r in 0..3 {
            assert!((same.offset[r]).abs() < 1e-3, "{same:?}");
            for c in 0..3 {
                let id = if r == c { 1.0 } else { 0.0 };
                assert!((same.matrix[r][c] - id).abs() < 1e-2, "{same:?}");
            }
        }
    }

    #[test]
    fn fitting_images_and_blending_maps() {
        let dev = Device::Cpu;
        // Two flat-ish images against a painting: the fitted map takes their pooled mean to
        // the painting's.
        let image = |base: [f32; 3], seed| {
            let rgb = colours(
                seed,
                base,
                [[0.05, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, 0.0, 0.05]],
                16,
            );
            Tensor::from_vec(rgb, (16, 3), &dev)
                .unwrap()
                .t()
                .unwrap()
                .reshape((1, 3, 4, 4))
                .unwrap()
        };
        let outputs = [image([0.3, 0.3, 0.3], 5), image([0.5, 0.4, 0.3], 6)];
        let painting = image([0.8, 0.2, 0.5], 7);
        let p = Palette::fit(&outputs, &painting).unwrap();
        let rgb = |t: &Tensor| tensor_to_hwc(t).unwrap().2;
        let mut mapped: Vec<Vec<f32>> = outputs.iter().map(rgb).collect();
        for m in &mut mapped {
            p.affine_rgb(m);
        }
        // Both the luma and the chroma means move to the painting's: so does the RGB mean.
        let pooled = ColourMoments::of(&[&mapped[0], &mapped[1]]).unwrap();
        let target = ColourMoments::of(&[&rgb(&painting)]).unwrap();
        // Measured one image at a time and pooled: the same moments as measured at once.
        let parts = [0, 1].map(|k| ColourMoments::of(&[&mapped[k]]).unwrap());
        let at_once = ColourMoments::pool(&parts).unwrap();
        assert_eq!(at_once.pixels, pooled.pixels);
        assert!((at_once.mean - pooled.mean).amax() < 1e-12);
        assert!((at_once.cov - pooled.cov).amax() < 1e-12);
        assert!((pooled.mean - target.mean).amax() < 1e-4);
        // Blends: a map against itself, and halfway to the identity.
        let same = Palette::blend(&[(p, 0.3), (p, 0.7)]);
        assert!((0..3).all(|r| (same.offset[r] - p.offset[r]).abs() < 1e-6));
        let half = Palette::blend(&[(p, 1.0), (Palette::IDENTITY, 1.0)]);
        assert!((half.offset[0] - p.offset[0] / 2.0).abs() < 1e-6);
        assert!((half.matrix[1][1] - (p.matrix[1][1] + 1.0) / 2.0).abs() < 1e-6);
        // Nothing to fit is refused.
        let empty = Tensor::zeros((1, 3, 0, 4), candle_core::DType::F32, &dev).unwrap();
        assert!(Palette::fit(&[empty], &painting).is_err());
    }

    #[test]
    fn shown_colours_are_the_affine_map_brought_into_gamut() {
        let dev = Device::Cpu;
        // Spread wide enough that the map sends many colours out of [0, 1] (about half here).
        let from = colours(
            3,
            [0.5; 3],
            [[0.3, 0.0, 0.0], [0.1, 0.3, 0.0], [0.0, 0.0, 0.3]],
            256,
        );
        let to = colours(
            4,
            [0.2, 0.6, 0.4],
            [[0.05, 0.0, 0.02], [0.0, 0.4, 0.0], [0.0, 0.0, 0.05]],
            256,
        );
        let p = Palette::transport(
            &ColourMoments::of(&[&from]).unwrap(),
            &ColourMoments::of(&[&to]).unwrap(),
        );
        let mut affine = from.clone();
        p.affine_rgb(&mut affine);
        // [1, 3, 16, 16] planar from the 256 interleaved pixels, and the rows themselves.
        let rows = Tensor::from_vec(from.clone(), (256, 3), &dev).unwrap();
        let planar = rows.t().unwrap().reshape((1, 3, 16, 16)).unwrap();
        let interleaved = |t: Tensor| -> Vec<f32> { t.flatten_all().unwrap().to_vec1().unwrap() };
        let image = interleaved(
            p.apply(&planar)
                .unwrap()
                .reshape((3, 256))
                .unwrap()
                .t()
                .unwrap(),
        );
        let by_rows = interleaved(p.apply_rows(&rows).unwrap());
        let y = ycbcr().map(|v| v as f32);
        let (mut outside, mut on_edge) = (0, 0);
        for ((a, shown), other) in affine
            .chunks_exact(3)
            .zip(image.chunks_exact(3))
            .zip(by_rows.chunks_exact(3))
        {
            for k in 0..3 {
                assert!((shown[k] - other[k]).abs() < 1e-6, "{shown:?} vs {other:?}");
                assert!((0.0..=1.0).contains(&shown[k]), "{shown:?}");
            }
            let (a_ycc, s_ycc) = (
                y * Vector3::from_column_slice(a),
                y * Vector3::from_column_slice(shown),
            );
            if a.iter().all(|v| (0.0..=1.0).contains(v)) {
                // In gamut: the affine map itself.
                assert!(
                    (0..3).all(|k| (shown[k] - a[k]).abs() < 1e-5),
                    "{a:?} {shown:?}"
                );
                continue;
            }
            outside += 1;
            // Luma kept (clamped), chroma scaled down along its own direction (same hue)...
            assert!(
                (s_ycc[0] - a_ycc[0].clamp(0.0, 1.0)).abs() < 1e-5,
                "{a:?} {shown:?}"
            );
            let cross = a_ycc[1] * s_ycc[2] - a_ycc[2] * s_ycc[1];
            let dot = a_ycc[1] * s_ycc[1] + a_ycc[2] * s_ycc[2];
            let (na, ns) = (a_ycc.rows(1, 2).norm(), s_ycc.rows(1, 2).norm());
            assert!(
                cross.abs() < 1e-4 && dot >= 0.0 && ns <= na + 1e-6,
                "{a:?} {shown:?}"
            );
            // ...by no more than it must: a channel on the gamut's edge (or no chroma left).
            if shown.iter().any(|v| !(1e-5..=1.0 - 1e-5).contains(v)) || ns < 1e-5 {
                on_edge += 1;
            }
        }
        assert!(outside > 64, "{outside} of 256 left the gamut");
        assert_eq!(on_edge, outside);
    }
}
