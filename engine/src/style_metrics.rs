//! Style fidelity measured outside the encoder the model trains with, so a method that
//! optimises the VGG style loss directly gains nothing here by doing so:
//!
//! - **colour**: the sliced Wasserstein distance (SW₂) between the CIE Lab colour distributions
//!   of the frames and of the painting — 64 fixed random directions in Lab, each distribution
//!   summarised by 128 quantiles of its projection; in Lab units (L ∈ [0, 100]);
//! - **texture**: the distance between Gabor-energy signatures — the mean magnitude of complex
//!   Gabor responses of the luminance at 4 orientations and 3 scales (a 2× pyramid, wavelength
//!   4 px at each level), as logarithms; the distance is the RMS difference of the 12 logs.
//!
//! Both are 0 for identical inputs and grow as the distributions part. The unstylized frames'
//! values are the "did nothing" floor a stylization must beat. Style images are measured at
//! the size the pipeline reads them ([`crate::stages::render_stylized::RenderStylizedConfig`]
//! `style_size`), so brush strokes have the scale the network sees.

use rayon::prelude::*;

use crate::rng::Rng;

/// CIE Lab (D65) of an sRGB colour in [0, 1].
pub fn srgb_to_lab(rgb: [f32; 3]) -> [f32; 3] {
    let lin = rgb.map(|c| {
        let c = c.clamp(0.0, 1.0);
        if c <= 0.04045 {
            c / 12.92
        } else {
            ((c + 0.055) / 1.055).powf(2.4)
        }
    });
    let [r, g, b] = lin;
    let x = (0.412_456_4 * r + 0.357_576_1 * g + 0.180_437_5 * b) / 0.950_47;
    let y = 0.212_672_9 * r + 0.715_152_2 * g + 0.072_175 * b;
    let z = (0.019_333_9 * r + 0.119_192 * g + 0.950_304_1 * b) / 1.088_83;
    let f = |t: f32| {
        if t > 0.008_856 {
            t.cbrt()
        } else {
            7.787 * t + 16.0 / 116.0
        }
    };
    let (fx, fy, fz) = (f(x), f(y), f(z));
    [116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)]
}

/// A colour distribution: Lab values of (a deterministic subsample of) some pixels.
#[derive(Debug, Clone, Default)]
pub struct Colours(Vec<[f32; 3]>);

impl Colours {
    /// At most this many pixels are kept (every k-th, in order).
    pub const MAX_PIXELS: usize = 1 << 16;

    /// The colours of images given as interleaved RGB in [0, 1], pooled.
    pub fn of(images: &[&[f32]]) -> Self {
        let total: usize = images.iter().map(|i| i.len() / 3).sum();
        let stride = total.div_ceil(Self::MAX_PIXELS).max(1);
        let lab = images
            .iter()
            .flat_map(|i| i.chunks_exact(3))
            .step_by(stride)
            .map(|p| srgb_to_lab([p[0], p[1], p[2]]))
            .collect();
        Self(lab)
    }

    /// Sliced Wasserstein-2 distance to `other`, in Lab units.
    pub fn swd(&self, other: &Colours) -> f64 {
        const DIRECTIONS: usize = 64;
        const QUANTILES: usize = 128;
        if self.0.is_empty() || other.0.is_empty() {
            return f64::NAN;
        }
        let mut rng = Rng::new(0x5eed_c0105);
        let mut total = 0.0;
        for _ in 0..DIRECTIONS {
            let d = [rng.normal(), rng.normal(), rng.normal()];
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-12);
            let d = d.map(|v| v / n);
            let qa = quantiles(&self.0, d, QUANTILES);
            let qb = quantiles(&other.0, d, QUANTILES);
            total += qa
                .iter()
                .zip(&qb)
                .map(|(a, b)| (a - b) * (a - b))
                .sum::<f64>()
                / QUANTILES as f64;
        }
        (total / DIRECTIONS as f64).sqrt()
    }
}

/// `k` quantiles (at (i + ½)/k) of the projections of `points` on `dir`, linearly interpolated.
fn quantiles(points: &[[f32; 3]], dir: [f32; 3], k: usize) -> Vec<f64> {
    let mut p: Vec<f64> = points
        .iter()
        .map(|c| (c[0] * dir[0] + c[1] * dir[1] + c[2] * dir[2]) as f64)
        .collect();
    p.sort_unstable_by(f64::total_cmp);
    let last = (p.len() - 1) as f64;
    (0..k)
        .map(|i| {
            let t = (i as f64 + 0.5) / k as f64 * last;
            let (lo, frac) = (t.floor() as usize, t.fract());
            let hi = (lo + 1).min(p.len() - 1);
            p[lo] * (1.0 - frac) + p[hi] * frac
        })
        .collect()
}

/// Orientations and pyramid levels of the Gabor bank.
const ORIENTATIONS: usize = 4;
const LEVELS: usize = 3;
const WAVELENGTH: f32 = 4.0;

/// Mean Gabor magnitudes of some images (accumulated; see [`Texture::signature`]).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Texture {
    sums: [f64; ORIENTATIONS * LEVELS],
    counts: [f64; ORIENTATIONS * LEVELS],
}

impl Texture {
    /// The signature of images given as (width, height, interleaved RGB in [0, 1]).
    pub fn of(images: &[(usize, usize, &[f32])]) -> Self {
        // One image per thread, summed in the images' order: the same sums as one at a time.
        let per_image: Vec<Texture> = images
            .par_iter()
            .map(|&(w, h, rgb)| {
                let mut t = Self::default();
                t.add(w, h, rgb);
                t
            })
            .collect();
        let mut t = Self::default();
        for image in &per_image {
            for k in 0..ORIENTATIONS * LEVELS {
                t.sums[k] += image.sums[k];
                t.counts[k] += image.counts[k];
            }
        }
        t
    }

    fn add(&mut self, width: usize, height: usize, rgb: &[f32]) {
        let mut lum: Vec<f32> = rgb
            .chunks_exact(3)
            .map(|p| srgb_to_lab([p[0], p[1], p[2]])[0] / 100.0)
            .collect();
        let (mut w, mut h) = (width, height);
        let kernels = gabor_kernels();
        for level in 0..LEVELS {
            for (o, (even, odd, r)) in kernels.iter().enumerate() {
                let r = *r;
                if w <= 2 * r || h <= 2 * r {
                    continue;
                }
                let side = 2 * r + 1;
                let (mut sum, mut n) = (0.0f64, 0.0f64);
                for y in r..h - r {
                    for x in r..w - r {
                        let (mut re, mut im) = (0.0f32, 0.0f32);
                        for ky in 0..side {
                            let row = &lum[(y + ky - r) * w + x - r..][..side];
                            let (ke, ko) = (&even[ky * side..][..side], &odd[ky * side..][..side]);
                            for kx in 0..side {
                                re += row[kx] * ke[kx];
                                im += row[kx] * ko[kx];
                            }
                        }
                        sum += (re * re + im * im).sqrt() as f64;
                        n += 1.0;
                    }
                }
                self.sums[level * ORIENTATIONS + o] += sum;
                self.counts[level * ORIENTATIONS + o] += n;
            }
            // 2× box downsampling for the next level.
            let (nw, nh) = (w / 2, h / 2);
            lum = (0..nh * nw)
                .map(|i| {
                    let (x, y) = (2 * (i % nw), 2 * (i / nw));
                    0.25 * (lum[y * w + x]
                        + lum[y * w + x + 1]
                        + lum[(y + 1) * w + x]
                        + lum[(y + 1) * w + x + 1])
                })
                .collect();
            (w, h) = (nw, nh);
        }
    }

    /// ln(mean magnitude) per filter (level-major), `NaN` where no pixel was measured.
    pub fn signature(&self) -> [f64; ORIENTATIONS * LEVELS] {
        std::array::from_fn(|k| (self.sums[k] / self.counts[k] + 1e-6).ln())
    }

    /// RMS difference of the two signatures over the filters both measured.
    pub fn distance(&self, other: &Texture) -> f64 {
        let (a, b) = (self.signature(), other.signature());
        let d: Vec<f64> = a
            .iter()
            .zip(&b)
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(|(x, y)| (x - y) * (x - y))
            .collect();
        if d.is_empty() {
            return f64::NAN;
        }
        (d.iter().sum::<f64>() / d.len() as f64).sqrt()
    }
}

/// Zero-mean even and odd Gabor kernels (σ = 0.56 λ: one-octave bandwidth) per orientation,
/// with their radius.
fn gabor_kernels() -> Vec<(Vec<f32>, Vec<f32>, usize)> {
    let sigma = 0.56 * WAVELENGTH;
    let r = (2.0 * sigma).ceil() as usize;
    let side = 2 * r + 1;
    (0..ORIENTATIONS)
        .map(|o| {
            let theta = o as f32 * std::f32::consts::PI / ORIENTATIONS as f32;
            let (s, c) = theta.sin_cos();
            let (mut even, mut odd) = (vec![0f32; side * side], vec![0f32; side * side]);
            for ky in 0..side {
                for kx in 0..side {
                    let (x, y) = (kx as f32 - r as f32, ky as f32 - r as f32);
                    let u = x * c + y * s;
                    let g = (-(x * x + y * y) / (2.0 * sigma * sigma)).exp();
                    let phase = std::f32::consts::TAU * u / WAVELENGTH;
                    even[ky * side + kx] = g * phase.cos();
                    odd[ky * side + kx] = g * phase.sin();
                }
            }
            // Remove the DC response of the even kernel so flat regions respond with 0.
            let mean = even.iter().sum::<f32>() / even.len() as f32;
            even.iter_mut().for_each(|v| *v -= mean);
            (even, odd, r)
        })
        .collect()
}

/// Colour and texture of a reference image (a painting), measured once.
#[derive(Debug, Clone)]
pub struct StyleReference {
    pub colours: Colours,
    pub texture: Texture,
}

impl StyleReference {
    pub fn new(width: usize, height: usize, rgb: &[f32]) -> Self {
        Self {
            colours: Colours::of(&[rgb]),
            texture: Texture::of(&[(width, height, rgb)]),
        }
    }

    /// (colour SWD, texture distance) of frames `(width, height, interleaved RGB)`.
    pub fn score(&self, frames: &[(usize, usize, &[f32])]) -> (f64, f64) {
        let rgb: Vec<&[f32]> = frames.iter().map(|f| f.2).collect();
        (
            Colours::of(&rgb).swd(&self.colours),
            Texture::of(frames).distance(&self.texture),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::style2d::painted;

    fn raw(name: &str, size: u32) -> Vec<f32> {
        painted::paint(name, size).unwrap().into_raw()
    }

    #[test]
    fn lab_matches_known_values() {
        let close = |a: [f32; 3], b: [f32; 3]| a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 0.1);
        assert!(close(srgb_to_lab([1.0, 1.0, 1.0]), [100.0, 0.0, 0.0]));
        assert!(close(srgb_to_lab([0.0, 0.0, 0.0]), [0.0, 0.0, 0.0]));
        // sRGB red, green and mid grey (reference values of the CIE formulas, D65).
        assert!(close(srgb_to_lab([1.0, 0.0, 0.0]), [53.24, 80.09, 67.20]));
        assert!(close(srgb_to_lab([0.0, 1.0, 0.0]), [87.73, -86.18, 83.18]));
        assert!(close(srgb_to_lab([0.5, 0.5, 0.5]), [53.39, 0.0, 0.0]));
    }

    #[test]
    fn colour_distance_is_zero_for_the_same_colours_and_grows_with_a_palette_swap() {
        let waves = raw("waves", 64);
        let a = Colours::of(&[&waves]);
        assert_eq!(a.swd(&a), 0.0);
        // The same distribution in another order and size (each pixel twice) still scores 0.
        let mut twice: Vec<f32> = waves
            .chunks(3)
            .rev()
            .flat_map(|p| [p, p].concat())
            .collect();
        assert!(a.swd(&Colours::of(&[&twice])) < 0.5);
        // A palette swap (red ↔ blue) moves the blues to oranges.
        twice.chunks_mut(3).for_each(|p| p.swap(0, 2));
        let swapped = a.swd(&Colours::of(&[&twice]));
        assert!(swapped > 20.0, "{swapped}");
        // A uniform shift of ΔL moves every projection's quantiles: SW₂ is about ΔL/√3.
        let grey = vec![0.5f32; 300];
        let lighter = vec![0.6f32; 300];
        let dl = (srgb_to_lab([0.6; 3])[0] - srgb_to_lab([0.5; 3])[0]) as f64;
        let d = Colours::of(&[&grey]).swd(&Colours::of(&[&lighter]));
        assert!((d - dl / 3f64.sqrt()).abs() < 0.25 * dl, "{d} vs {dl}");
    }

    #[test]
    fn texture_tells_brush_strokes_from_a_smooth_photo() {
        let s = 96;
        let sig = |name: &str| {
            let r = raw(name, s as u32);
            Texture::of(&[(s, s, &r)])
        };
        let (waves, mosaic, dots) = (sig("waves"), sig("mosaic"), sig("dots"));
        assert_eq!(waves.distance(&waves), 0.0);
        // A smooth "photo": a soft gradient with one blurred edge.
        let photo: Vec<f32> = (0..s * s)
            .flat_map(|i| {
                let (x, y) = ((i % s) as f32 / s as f32, (i / s) as f32 / s as f32);
                let v = 0.3 + 0.4 * x + 0.2 / (1.0 + (-(y - 0.5) * 20.0).exp());
                [v, v * 0.9, v * 0.8]
            })
            .collect();
        let photo = Texture::of(&[(s, s, &photo)]);
        let to_photo = waves.distance(&photo);
        for other in [&mosaic, &dots] {
            let between = waves.distance(other);
            assert!(between > 0.05, "paintings differ: {between}");
            assert!(to_photo > between, "photo {to_photo} vs painting {between}");
        }
        // The signature pools images: one image twice is the image.
        let r = raw("dots", s as u32);
        assert!(Texture::of(&[(s, s, &r), (s, s, &r)]).distance(&dots) < 1e-9);
        // Too small for any filter: no signature, no distance.
        let tiny = vec![0.5f32; 3 * 4 * 4];
        assert!(Texture::of(&[(4, 4, &tiny)]).distance(&dots).is_nan());
    }

    #[test]
    fn a_reference_scores_itself_zero() {
        let r = raw("mosaic", 64);
        let reference = StyleReference::new(64, 64, &r);
        assert_eq!(reference.score(&[(64, 64, &r)]), (0.0, 0.0));
        let other = raw("waves", 64);
        let (c, t) = reference.score(&[(64, 64, &other)]);
        assert!(c > 5.0 && t > 0.05, "{c} {t}");
    }
}
