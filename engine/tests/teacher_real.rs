//! A general 2D teacher on a real capture (ignored: it reads `../shared`, which CI does not
//! need, and a decoder trained by `stylize train-decoder`, named by `STYLENERF_TEACHER`): the
//! fox test frames (every 8th) stylized feed-forward by the bundled encoder and that decoder
//! with each painting of `../shared/styles`, scored outside the encoder (Lab colour SWD, Gabor
//! texture distance) against the unstylized frames' floor, with the decoder's own colours and
//! through the palette fitted to its output on these frames (as a job's `decoder_pretrain`
//! fits it on its views). docs/BENCHMARKS.md records which paintings the graded decoder's
//! corpus held. A labelled sheet is written to `target/teacher_real/sheet.png`.
//!
//! `STYLENERF_TEACHER=dec/decoder.safetensors cargo test --release -p stylenerf-engine \
//!     --test teacher_real -- --ignored --nocapture`

use std::path::Path;

use candle_core::{Device, Tensor};
use stylenerf_engine::image_io::{has_image_extension, load_rgb, save_png, to_rgb8};
use stylenerf_engine::style2d::decoder::Decoder;
use stylenerf_engine::style2d::encoder::VggEncoder;
use stylenerf_engine::style2d::images::{tensor_to_hwc, to_tensor};
use stylenerf_engine::style2d::network::AdaInNet;
use stylenerf_engine::style2d::palette::{ColourMoments, Palette};
use stylenerf_engine::style2d::weights::EncoderWeights;
use stylenerf_engine::style_metrics::StyleReference;

/// An image at the pipeline's style size (longer side 256, multiples of 8), as the network's
/// input tensor and as raw RGB for the measures.
fn load(path: &Path, dev: &Device) -> (Tensor, (usize, usize, Vec<f32>)) {
    let t = to_tensor(&load_rgb(path).unwrap(), 256, dev).unwrap();
    (t.clone(), raw(&t))
}

fn raw(t: &Tensor) -> (usize, usize, Vec<f32>) {
    let (w, h, rgb) = tensor_to_hwc(t).unwrap();
    (w as usize, h as usize, rgb)
}

/// How far the luma of `shown` strays from that of `source` once both means are removed (RMS):
/// the strokes the palette is meant to keep (it only shifts luma) and that clipping flattens.
fn strokes_lost(source: &[(usize, usize, Vec<f32>)], shown: &[(usize, usize, Vec<f32>)]) -> f64 {
    let luma = |rgb: &[f32]| -> Vec<f64> {
        rgb.chunks_exact(3)
            .map(|p| 0.299 * p[0] as f64 + 0.587 * p[1] as f64 + 0.114 * p[2] as f64)
            .collect()
    };
    let (mut sum, mut n) = (0.0, 0);
    for ((_, _, a), (_, _, b)) in source.iter().zip(shown) {
        let (a, b) = (luma(a), luma(b));
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let (ma, mb) = (mean(&a), mean(&b));
        sum += a
            .iter()
            .zip(&b)
            .map(|(x, y)| ((x - ma) - (y - mb)).powi(2))
            .sum::<f64>();
        n += a.len();
    }
    (sum / n as f64).sqrt()
}

fn view(v: &[(usize, usize, Vec<f32>)]) -> Vec<(usize, usize, &[f32])> {
    v.iter().map(|(w, h, x)| (*w, *h, x.as_slice())).collect()
}

#[test]
#[ignore = "reads ../shared/styles, ../shared/data/fox and $STYLENERF_TEACHER"]
fn a_teacher_moves_fox_frames_toward_each_painting() {
    let shared = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared");
    let dev = Device::Cpu;
    let teacher = std::env::var("STYLENERF_TEACHER")
        .expect("STYLENERF_TEACHER: the decoder.safetensors to grade");
    let (decoder, _) = Decoder::load(Path::new(&teacher), &dev).unwrap();
    let net = AdaInNet {
        encoder: VggEncoder::new(&EncoderWeights::bundled().unwrap(), &dev).unwrap(),
        decoder,
    };
    let mut files: Vec<_> = std::fs::read_dir(shared.join("data/fox/images"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| has_image_extension(p))
        .collect();
    files.sort();
    let (inputs, frames): (Vec<_>, Vec<_>) = files.iter().step_by(8).map(|p| load(p, &dev)).unzip();
    let mut rows = Vec::new();
    println!(
        "| painting | colour SWD photo → teacher (ratio) → with palette (ratio) [clamped] | texture photo → teacher → with palette [clamped] | luma strokes lost [clamped] |"
    );
    println!("|---|---|---|---|");
    for name in [
        "starry_night",
        "shipwreck",
        "the_scream",
        "woman-with-hat-matisse",
    ] {
        let (style_input, (sw, sh, style)) = load(&shared.join(format!("styles/{name}.jpg")), &dev);
        let reference = StyleReference::new(sw, sh, &style);
        let target = net.style_target(&style_input).unwrap();
        let outs: Vec<Tensor> = inputs
            .iter()
            .map(|x| net.stylize(x, &target, 1.0).unwrap())
            .collect();
        let stylized: Vec<_> = outs.iter().map(raw).collect();
        let outputs: Vec<&[f32]> = stylized.iter().map(|s| s.2.as_slice()).collect();
        let palette = Palette::transport(
            &ColourMoments::of(&outputs).unwrap(),
            &ColourMoments::of(&[&style]).unwrap(),
        );
        // As shown (in gamut), and with each channel clamped instead (the map before it was
        // brought into gamut), for comparison.
        let mapped: Vec<_> = outs
            .iter()
            .map(|t| raw(&palette.apply(t).unwrap()))
            .collect();
        let clamped: Vec<_> = stylized
            .iter()
            .map(|(w, h, rgb)| {
                let mut rgb = rgb.clone();
                palette.affine_rgb(&mut rgb);
                rgb.iter_mut().for_each(|v| *v = v.clamp(0.0, 1.0));
                (*w, *h, rgb)
            })
            .collect();
        let floor = reference.score(&view(&frames));
        let teacher = reference.score(&view(&stylized));
        let with_palette = reference.score(&view(&mapped));
        let with_clamping = reference.score(&view(&clamped));
        println!(
            "| {name} | {:.2} → {:.2} ({:.2}×) → {:.2} ({:.2}×) [clamped: {:.2} ({:.2}×)] | {:.3} → {:.3} → {:.3} [{:.3}] | {:.4} [{:.4}] |",
            floor.0,
            teacher.0,
            teacher.0 / floor.0,
            with_palette.0,
            with_palette.0 / floor.0,
            with_clamping.0,
            with_clamping.0 / floor.0,
            floor.1,
            teacher.1,
            with_palette.1,
            with_clamping.1,
            strokes_lost(&stylized, &mapped),
            strokes_lost(&stylized, &clamped)
        );
        assert!(teacher.0.is_finite() && teacher.1.is_finite());
        assert!(
            with_palette.0 < teacher.0,
            "{name}: the palette moves the colours closer"
        );
        let (fw, fh, _) = frames[0];
        let tile = |rgb: &[f32], w: usize, h: usize| {
            let img = to_rgb8(w as u32, h as u32, rgb);
            image::imageops::resize(
                &img,
                fw as u32,
                fh as u32,
                image::imageops::FilterType::Triangle,
            )
        };
        rows.push(vec![
            tile(&style, sw, sh),
            tile(&frames[1].2, fw, fh),
            tile(&stylized[1].2, fw, fh),
            tile(&mapped[1].2, fw, fh),
            tile(&frames[3].2, fw, fh),
            tile(&stylized[3].2, fw, fh),
            tile(&mapped[3].2, fw, fh),
        ]);
    }
    let sheet = stylenerf_engine::sheet::labelled_grid(
        &[
            "style", "photo", "teacher", "palette", "photo", "teacher", "palette",
        ],
        &rows,
    )
    .unwrap();
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/teacher_real");
    std::fs::create_dir_all(&out).unwrap();
    save_png(&out.join("sheet.png"), &sheet).unwrap();
}
