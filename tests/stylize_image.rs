//! `stylenerf stylize image` as a user runs it, feed-forward with the bundled decoder on a
//! small photo-like image written by the test: the output goes through the painting's palette
//! (its mean colour lands on the painting's), and `--no-palette` keeps the decoder's colours.

use std::path::Path;
use std::process::Command;

use stylenerf_engine::image_io::{load_rgb, save_rgb_png};
use stylenerf_engine::style2d::images::StyleImage;
use stylenerf_engine::style2d::painted;
use stylenerf_engine::style2d::palette::ColourMoments;

/// The output as (width, height, interleaved RGB).
fn stylize(dir: &Path, out: &str, extra: &[&str]) -> (u32, u32, Vec<f32>) {
    let path = dir.join(out);
    let status = Command::new(env!("CARGO_BIN_EXE_stylenerf"))
        .args(["--log", "warn", "stylize", "image", "--content"])
        .arg(dir.join("content.png"))
        .args([
            "--style",
            "builtin:waves",
            "--size",
            "32",
            "--train-steps",
            "0",
            "--out",
        ])
        .arg(&path)
        .args(extra)
        .status()
        .expect("stylenerf runs");
    assert!(status.success(), "stylize image {extra:?} failed");
    let img = load_rgb(&path).unwrap();
    (img.width(), img.height(), img.into_raw())
}

#[test]
fn the_palette_gives_the_output_the_paintings_colours() {
    let dir = tempfile::tempdir().unwrap();
    // A warm gradient with a dark disc: nothing like the waves' blues.
    let (w, h) = (32usize, 24usize);
    let rgb: Vec<f32> = (0..w * h)
        .flat_map(|i| {
            let (x, y) = ((i % w) as f32 / w as f32, (i / w) as f32 / h as f32);
            let disc = (x - 0.5).powi(2) + (y - 0.5).powi(2) < 0.04;
            let k = if disc { 0.2 } else { 1.0 };
            [k * (0.6 + 0.4 * x), k * (0.3 + 0.3 * y), k * 0.1]
        })
        .collect();
    save_rgb_png(&dir.path().join("content.png"), w as u32, h as u32, &rgb).unwrap();

    let mapped = stylize(dir.path(), "palette.png", &[]);
    let own = stylize(dir.path(), "own.png", &["--no-palette"]);
    assert_eq!((mapped.0, mapped.1), (own.0, own.1));
    // The painting as the command reads it.
    let mean = |rgb: &[f32]| ColourMoments::of(&[rgb]).unwrap().mean;
    let waves = mean(
        painted::paint("waves", StyleImage::BUILTIN_SIZE)
            .unwrap()
            .as_raw(),
    );
    let (with, without) = (mean(&mapped.2), mean(&own.2));
    assert!(
        (with - waves).norm() < 0.03 && (with - waves).norm() < (without - waves).norm(),
        "mean colours: {with:?} with the palette, {without:?} without, {waves:?} the painting"
    );
}
