//! Training curves as a picture: `curves.png` beside a training stage's `metrics.json`, one
//! panel per series (each loss term over the steps, the test PSNR), written with the contact
//! sheets' bitmap font, so that a person sees how a run went without a plotting tool. A series
//! spanning more than two decades is drawn on a log scale (said in its title).

use std::path::Path;

use image::{Rgb, RgbImage};

use crate::sheet::draw_text;
use crate::Result;

/// A named term of a loss log: its title and how to read it from a record.
pub type Term<'a, R> = (&'a str, fn(&R) -> f32);

/// One curve: a title and its (step, value) points.
pub struct Series {
    pub title: String,
    pub points: Vec<(f64, f64)>,
}

impl Series {
    pub fn new(title: &str, points: impl IntoIterator<Item = (f64, f64)>) -> Series {
        Series {
            title: title.to_string(),
            points: points
                .into_iter()
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .collect(),
        }
    }

    /// One series per named term of a loss log, over the records' steps.
    pub fn terms<R>(log: &[R], step: fn(&R) -> u64, terms: &[Term<R>]) -> Vec<Series> {
        terms
            .iter()
            .map(|(title, value)| {
                Series::new(
                    title,
                    log.iter().map(|r| (step(r) as f64, f64::from(value(r)))),
                )
            })
            .collect()
    }

    /// Worth a panel: two points or more, not all the same value (a term switched off).
    fn drawable(&self) -> bool {
        self.points.len() >= 2 && self.points.iter().any(|p| p.1 != self.points[0].1)
    }
}

const PANEL_W: u32 = 480;
const PANEL_H: u32 = 200;
/// Left margin (y labels) and bottom margin (x labels) of a panel's plot area.
const LEFT: u32 = 84;
const TOP: u32 = 24;
const BOTTOM: u32 = 18;
const BACKGROUND: Rgb<u8> = Rgb([24, 24, 24]);
const AXES: Rgb<u8> = Rgb([90, 90, 90]);
const LINE: Rgb<u8> = Rgb([100, 170, 255]);

/// A number in at most 9 characters.
fn label(v: f64) -> String {
    if v != 0.0 && (v.abs() >= 1e5 || v.abs() < 1e-2) {
        format!("{v:.2e}")
    } else {
        let text = format!("{v:.3}");
        text.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

/// Sets the pixels on the segment from `a` to `b` (Bresenham).
fn segment(img: &mut RgbImage, a: (i64, i64), b: (i64, i64), colour: Rgb<u8>) {
    let (dx, dy) = ((b.0 - a.0).abs(), -(b.1 - a.1).abs());
    let (sx, sy) = ((b.0 - a.0).signum(), (b.1 - a.1).signum());
    let (mut x, mut y, mut err) = (a.0, a.1, dx + dy);
    loop {
        if x >= 0 && y >= 0 && (x as u32) < img.width() && (y as u32) < img.height() {
            img.put_pixel(x as u32, y as u32, colour);
        }
        if (x, y) == b {
            return;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            x += sx;
        }
        if e2 <= dx {
            err += dx;
            y += sy;
        }
    }
}

/// One panel: title, value range on the left, step range below, the curve in between.
fn panel(series: &Series) -> RgbImage {
    let mut img = RgbImage::from_pixel(PANEL_W, PANEL_H, BACKGROUND);
    let (lo, hi) = series
        .points
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.1), hi.max(p.1))
        });
    let log = lo > 0.0 && hi / lo > 100.0;
    let scale = |v: f64| if log { v.log10() } else { v };
    let (y0, y1) = (scale(lo), scale(hi));
    let x0 = series.points.first().map_or(0.0, |p| p.0);
    let x1 = series.points.last().map_or(1.0, |p| p.0).max(x0 + 1e-9);
    let title = if log {
        format!("{} (log scale)", series.title)
    } else {
        series.title.clone()
    };
    draw_text(&mut img, (6, 6), PANEL_W, &title, 1);
    let (w, h) = (PANEL_W - LEFT - 8, PANEL_H - TOP - BOTTOM);
    draw_text(&mut img, (4, TOP), LEFT, &label(hi), 1);
    draw_text(&mut img, (4, TOP + h - 8), LEFT, &label(lo), 1);
    draw_text(&mut img, (LEFT, TOP + h + 6), PANEL_W, &label(x0), 1);
    let last = label(x1);
    let end = (LEFT + w).saturating_sub(8 * last.len() as u32);
    draw_text(&mut img, (end, TOP + h + 6), PANEL_W, &last, 1);
    let (left, top) = (LEFT as i64, TOP as i64);
    let (right, bottom) = (left + w as i64, top + h as i64);
    segment(&mut img, (left - 2, top), (left - 2, bottom), AXES);
    segment(&mut img, (left - 2, bottom + 2), (right, bottom + 2), AXES);
    let at = |(x, y): (f64, f64)| {
        let u = (x - x0) / (x1 - x0);
        let v = if y1 > y0 {
            (scale(y) - y0) / (y1 - y0)
        } else {
            0.5
        };
        (
            left + (u * w as f64).round() as i64,
            bottom - (v * h as f64).round() as i64,
        )
    };
    for pair in series.points.windows(2) {
        segment(&mut img, at(pair[0]), at(pair[1]), LINE);
    }
    img
}

/// The panels of every drawable series, two per row; `None` when none is drawable.
pub fn plot(series: &[Series]) -> Option<RgbImage> {
    let panels: Vec<RgbImage> = series.iter().filter(|s| s.drawable()).map(panel).collect();
    if panels.is_empty() {
        return None;
    }
    let cols = panels.len().min(2) as u32;
    let rows = panels.len().div_ceil(2) as u32;
    let mut img = RgbImage::from_pixel(cols * PANEL_W, rows * PANEL_H, BACKGROUND);
    for (i, p) in panels.iter().enumerate() {
        let (c, r) = (i as u32 % 2, i as u32 / 2);
        image::imageops::replace(&mut img, p, (c * PANEL_W) as i64, (r * PANEL_H) as i64);
    }
    Some(img)
}

/// Writes `curves.png` into `dir` when any series is drawable.
pub fn save(dir: &Path, series: &[Series]) -> Result<()> {
    match plot(series) {
        Some(img) => crate::image_io::save_png(&dir.join("curves.png"), &img),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line_pixels(img: &RgbImage, x0: u32, x1: u32) -> usize {
        img.enumerate_pixels()
            .filter(|(x, _, p)| (x0..x1).contains(x) && **p == LINE)
            .count()
    }

    #[test]
    fn a_falling_loss_is_drawn_from_top_left_to_bottom_right() {
        let loss = Series::new(
            "loss",
            (0..50).map(|i| (i as f64 * 10.0, 1.0 / (1.0 + i as f64))),
        );
        let img = plot(&[loss]).unwrap();
        assert_eq!(img.dimensions(), (PANEL_W, PANEL_H));
        // The curve spans the plot area's width, higher on the left than on the right.
        assert!(line_pixels(&img, LEFT, PANEL_W - 8) > (PANEL_W - LEFT - 8) as usize);
        let height_at = |x: u32| {
            (0..PANEL_H)
                .find(|&y| *img.get_pixel(x, y) == LINE)
                .expect("the curve passes")
        };
        assert!(height_at(LEFT + 1) < height_at(PANEL_W - 10));
    }

    #[test]
    fn flat_short_and_broken_series_are_left_out_and_wide_ranges_go_log() {
        assert!(plot(&[Series::new("one point", [(0.0, 1.0)])]).is_none());
        assert!(plot(&[Series::new("switched off", [(0.0, 0.0), (10.0, 0.0)])]).is_none());
        let nan = Series::new("nan", [(0.0, f64::NAN), (1.0, 2.0)]);
        assert_eq!(nan.points.len(), 1, "non-finite points are dropped");
        // Three drawable panels: two per row.
        let wide = Series::new("wide", (1..40).map(|i| (i as f64, 10f64.powi(-(i % 7)))));
        let img = plot(&[
            wide,
            Series::new("a", [(0.0, 1.0), (1.0, 2.0)]),
            Series::new("b", [(0.0, 3.0), (1.0, 2.0)]),
        ])
        .unwrap();
        assert_eq!(img.dimensions(), (2 * PANEL_W, 2 * PANEL_H));
        assert_eq!(label(0.000_12), "1.20e-4");
        let log = [(10u64, 1.0f32, 4.0f32), (20, 0.5, 3.0)];
        let terms: [Term<(u64, f32, f32)>; 2] = [("a", |r| r.1), ("b", |r| r.2)];
        let series = Series::terms(&log, |r| r.0, &terms);
        assert_eq!(series[1].title, "b");
        assert_eq!(series[1].points, [(10.0, 4.0), (20.0, 3.0)]);
        assert_eq!(label(31.5), "31.5");
        assert_eq!(label(0.0), "0");
    }
}
