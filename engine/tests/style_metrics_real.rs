//! Validates the measures outside the encoder on real images (ignored: it reads `../shared`,
//! which CI does not need): each painting against itself (0), against the other paintings, and
//! against photos of the fox capture, printed as the matrix in docs/BENCHMARKS.md. Only the
//! zero against itself is asserted: whether a painting is closer to other paintings than to
//! photos depends on the painting (the measures are used relative to the unstylized frames'
//! floor against the same painting, not across paintings).
//!
//! `cargo test --release -p stylenerf-engine --test style_metrics_real -- --ignored --nocapture`

use std::path::Path;

use stylenerf_engine::image_io::load_rgb;
use stylenerf_engine::style_metrics::StyleReference;

/// An image resized so its longer side is 256 (the pipeline's `style_size`), as raw RGB.
fn load(path: &Path) -> (usize, usize, Vec<f32>) {
    let img = load_rgb(path).unwrap();
    let (w, h) = img.dimensions();
    let s = 256.0 / w.max(h) as f32;
    let (nw, nh) = ((w as f32 * s) as u32, (h as f32 * s) as u32);
    let r = image::imageops::resize(&img, nw, nh, image::imageops::FilterType::Triangle);
    (nw as usize, nh as usize, r.into_raw())
}

#[test]
#[ignore = "reads ../shared/styles and ../shared/data/fox"]
fn paintings_are_closer_to_themselves_than_to_photos() {
    let shared = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared");
    let paintings = [
        "starry_night",
        "the_scream",
        "shipwreck",
        "woman-with-hat-matisse",
    ];
    let styles: Vec<_> = paintings
        .iter()
        .map(|p| load(&shared.join(format!("styles/{p}.jpg"))))
        .collect();
    let photos: Vec<_> = ["0004", "0021", "0035"]
        .iter()
        .map(|f| load(&shared.join(format!("data/fox/images/{f}.jpg"))))
        .collect();
    let photo_views: Vec<(usize, usize, &[f32])> = photos
        .iter()
        .map(|(w, h, v)| (*w, *h, v.as_slice()))
        .collect();
    println!("| painting | vs itself | vs other paintings (mean) | vs fox photos |");
    println!("|---|---|---|---|");
    for (i, (w, h, rgb)) in styles.iter().enumerate() {
        let reference = StyleReference::new(*w, *h, rgb);
        let own = reference.score(&[(*w, *h, rgb)]);
        let others: Vec<(f64, f64)> = styles
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != i)
            .map(|(_, (w, h, v))| reference.score(&[(*w, *h, v)]))
            .collect();
        let mean = |f: fn(&(f64, f64)) -> f64| others.iter().map(f).sum::<f64>() / 3.0;
        let other = (mean(|s| s.0), mean(|s| s.1));
        let photo = reference.score(&photo_views);
        println!(
            "| {} | {:.2} / {:.3} | {:.2} / {:.3} | {:.2} / {:.3} |",
            paintings[i], own.0, own.1, other.0, other.1, photo.0, photo.1
        );
        assert_eq!(own, (0.0, 0.0));
        assert!(photo.0 > 0.0 && photo.1 > 0.0);
    }
}
