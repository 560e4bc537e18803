//! The bundled default styles, painted by code: no image ships with the project and nothing is
//! downloaded. Each painter is deterministic (seeded), so a style's name names one exact image.
//!
//! - `mosaic`: Voronoi tiles in a warm Mediterranean palette with dark grout lines;
//! - `waves`: brush strokes following a swirling flow field, in blues and foam white;
//! - `dots`: pointillism — small dots of broken colour over a sky, sun and hills.
//!
//! They are chosen to differ in what AdaIN transfers — colour palette, stroke orientation and
//! texture scale — so a stylization that ignores the style is easy to spot.

use image::{Rgb, Rgb32FImage};

use crate::rng::Rng;

/// Names of the bundled styles, in their default order.
pub const NAMES: [&str; 3] = ["mosaic", "waves", "dots"];

/// Paints the bundled style `name` at `size`×`size`; `None` for an unknown name.
pub fn paint(name: &str, size: u32) -> Option<Rgb32FImage> {
    match name {
        "mosaic" => Some(mosaic(size)),
        "waves" => Some(waves(size)),
        "dots" => Some(dots(size)),
        _ => None,
    }
}

fn hex(c: u32) -> [f32; 3] {
    [
        ((c >> 16) & 255) as f32 / 255.0,
        ((c >> 8) & 255) as f32 / 255.0,
        (c & 255) as f32 / 255.0,
    ]
}

fn jitter(c: [f32; 3], rng: &mut Rng, amount: f32) -> [f32; 3] {
    c.map(|v| (v + (rng.uniform() - 0.5) * amount).clamp(0.0, 1.0))
}

fn mosaic(size: u32) -> Rgb32FImage {
    let mut rng = Rng::new(11);
    let palette = [0xC8553D, 0xF2A541, 0x2E86AB, 0x1B4965, 0xF4E9CD, 0x8A9B68].map(hex);
    let cells = 10usize;
    let pitch = size as f32 / cells as f32;
    let seeds: Vec<([f32; 2], [f32; 3])> = (0..cells * cells)
        .map(|k| {
            let (cx, cy) = ((k % cells) as f32, (k / cells) as f32);
            let p = [
                (cx + 0.15 + 0.7 * rng.uniform()) * pitch,
                (cy + 0.15 + 0.7 * rng.uniform()) * pitch,
            ];
            let c = jitter(palette[rng.below(palette.len())], &mut rng, 0.12);
            (p, c)
        })
        .collect();
    let grout = hex(0x2B2118);
    let mut img = Rgb32FImage::new(size, size);
    for (x, y, px) in img.enumerate_pixels_mut() {
        let (fx, fy) = (x as f32 + 0.5, y as f32 + 0.5);
        let (mut d1, mut d2, mut best) = (f32::MAX, f32::MAX, 0);
        for (k, (p, _)) in seeds.iter().enumerate() {
            let d = ((fx - p[0]).powi(2) + (fy - p[1]).powi(2)).sqrt();
            if d < d1 {
                (d2, d1, best) = (d1, d, k);
            } else if d < d2 {
                d2 = d;
            }
        }
        let edge = d2 - d1;
        let c = if edge < pitch * 0.06 {
            grout
        } else {
            // A little shading towards the tile's edge, as on glazed tiles.
            let shade = 0.85 + 0.15 * (edge / (pitch * 0.5)).min(1.0);
            seeds[best].1.map(|v| v * shade)
        };
        *px = Rgb(c);
    }
    img
}

fn waves(size: u32) -> Rgb32FImage {
    let mut rng = Rng::new(23);
    let s = size as f32;
    let mut img = Rgb32FImage::from_pixel(size, size, Rgb(hex(0x0B2545)));
    let palette = [0x13315C, 0x134074, 0x8DA9C4, 0xEEF4ED, 0x3E7CB1].map(hex);
    let angle = |x: f32, y: f32| {
        let (u, v) = (x / s * std::f32::consts::TAU, y / s * std::f32::consts::TAU);
        (2.0 * u).sin() * 1.3 + (3.0 * v + u).cos() * 0.9 + (u - 2.0 * v).sin() * 0.5
    };
    let strokes = (s * s / 90.0) as usize;
    for _ in 0..strokes {
        let (mut x, mut y) = (rng.uniform() * s, rng.uniform() * s);
        let colour = jitter(palette[rng.below(palette.len())], &mut rng, 0.08);
        let radius = 1.0 + rng.uniform() * 2.0 * s / 256.0;
        let length = (12.0 + rng.uniform() * 28.0) * s / 256.0;
        let mut travelled = 0.0;
        while travelled < length {
            stamp(&mut img, x, y, radius, colour);
            let a = angle(x, y);
            x += a.cos();
            y += a.sin();
            travelled += 1.0;
        }
    }
    img
}

fn dots(size: u32) -> Rgb32FImage {
    let mut rng = Rng::new(37);
    let s = size as f32;
    let mut img = Rgb32FImage::from_pixel(size, size, Rgb(hex(0xF1EAD8)));
    let (sky, sky_hi, sun, hill, hill_dark) = (
        hex(0x5FA8D3),
        hex(0xCAE9FF),
        hex(0xFFB703),
        hex(0x6A994E),
        hex(0x386641),
    );
    let dots = (s * s / 6.0) as usize;
    for _ in 0..dots {
        let (x, y) = (rng.uniform() * s, rng.uniform() * s);
        let (u, v) = (x / s, y / s);
        let horizon = 0.62 + 0.08 * (u * 7.0).sin() + 0.04 * (u * 17.0).cos();
        let base = if ((u - 0.72).powi(2) + (v - 0.25).powi(2)).sqrt() < 0.11 {
            sun
        } else if v < horizon {
            if rng.uniform() < v / horizon {
                sky
            } else {
                sky_hi
            }
        } else if rng.uniform() < (v - horizon) / (1.0 - horizon) {
            hill_dark
        } else {
            hill
        };
        // Broken colour: now and then a complementary accent, as the pointillists did.
        let c = if rng.uniform() < 0.12 {
            base.map(|v| 1.0 - v * 0.8)
        } else {
            jitter(base, &mut rng, 0.15)
        };
        stamp(&mut img, x, y, (1.2 + rng.uniform()) * s / 256.0 + 0.3, c);
    }
    img
}

/// A filled disc of `colour` centred at (`x`, `y`).
fn stamp(img: &mut Rgb32FImage, x: f32, y: f32, radius: f32, colour: [f32; 3]) {
    let (w, h) = (img.width() as i64, img.height() as i64);
    let r = radius.ceil() as i64;
    for py in (y as i64 - r)..=(y as i64 + r) {
        for px in (x as i64 - r)..=(x as i64 + r) {
            let (dx, dy) = (px as f32 + 0.5 - x, py as f32 + 0.5 - y);
            if (0..w).contains(&px) && (0..h).contains(&py) && dx * dx + dy * dy <= radius * radius
            {
                img.put_pixel(px as u32, py as u32, Rgb(colour));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Mean and standard deviation of each channel.
    fn stats(img: &Rgb32FImage) -> [(f32, f32); 3] {
        let n = (img.width() * img.height()) as f32;
        [0, 1, 2].map(|c| {
            let mean = img.pixels().map(|p| p.0[c]).sum::<f32>() / n;
            let var = img.pixels().map(|p| (p.0[c] - mean).powi(2)).sum::<f32>() / n;
            (mean, var.sqrt())
        })
    }

    #[test]
    fn styles_are_deterministic_textured_and_distinct() {
        let imgs: Vec<_> = NAMES.iter().map(|n| paint(n, 64).unwrap()).collect();
        for (n, img) in NAMES.iter().zip(&imgs) {
            assert_eq!(img.as_raw(), paint(n, 64).unwrap().as_raw(), "{n}");
            assert!(stats(img).iter().all(|&(_, sd)| sd > 0.05), "{n} is flat");
        }
        // Palettes differ: the channel means of every pair differ clearly somewhere.
        for a in 0..imgs.len() {
            for b in a + 1..imgs.len() {
                let (sa, sb) = (stats(&imgs[a]), stats(&imgs[b]));
                let gap = (0..3)
                    .map(|c| (sa[c].0 - sb[c].0).abs())
                    .fold(0.0, f32::max);
                assert!(gap > 0.05, "{} and {} look alike", NAMES[a], NAMES[b]);
            }
        }
        assert!(paint("nope", 64).is_none());
    }
}
