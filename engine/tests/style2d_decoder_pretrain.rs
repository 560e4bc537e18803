//! A tiny `decoder_pretrain` run on views of the generated scene (ground-truth depth as the
//! rendered depth): outputs exist and are sane, a run interrupted and resumed from its
//! checkpoint ends with exactly the weights of an uninterrupted run, and each decoder's
//! palette gives its output on the views the painting's mean colour.

use std::path::Path;

use candle_core::Device;
use image::Rgb32FImage;
use stylenerf_engine::scene::generate::{generate, GenerateOptions};
use stylenerf_engine::scene::{LoadOptions, Scene};
use stylenerf_engine::stages::decoder_pretrain::{
    run, DecoderPretrainConfig, DecoderStart, Inputs, StyleImage, StyleLatent, StylesFile,
};
use stylenerf_engine::stages::{Outcome, StageControl};
use stylenerf_engine::style2d::decoder::{Decoder, BUNDLED_DECODER_NAME};
use stylenerf_engine::style2d::encoder::VggEncoder;
use stylenerf_engine::style2d::images::{hwc_to_tensor, tensor_to_hwc, to_tensor};
use stylenerf_engine::style2d::network::AdaInNet;
use stylenerf_engine::style2d::palette::{ColourMoments, Palette};
use stylenerf_engine::style2d::weights::EncoderWeights;
use stylenerf_engine::views::{RenderedViews, ViewInfo, ViewKind};
use stylenerf_engine::Preset;

fn views(dir: &Path) -> RenderedViews {
    generate(
        &GenerateOptions {
            size: 32,
            views: 6,
            ..Default::default()
        },
        dir,
    )
    .unwrap();
    let scene = Scene::load(
        dir,
        &LoadOptions {
            test_every: 0,
            ..Default::default()
        },
    )
    .unwrap();
    let mut v = RenderedViews {
        width: 32,
        height: 32,
        views: vec![],
        rgb: vec![],
        depth: vec![],
        opacity: vec![],
        true_depth: None,
    };
    for (i, f) in scene.frames.iter().enumerate() {
        v.views.push(ViewInfo {
            name: f.name.clone(),
            kind: ViewKind::Train { frame: i },
            camera: f.camera,
        });
        v.rgb.extend_from_slice(f.image.as_raw());
        let d = f.depth.clone().unwrap();
        v.opacity
            .extend(d.iter().map(|&d| if d > 0.0 { 1.0 } else { 0.0 }));
        v.depth.extend(d);
    }
    v
}

fn styles() -> Vec<StyleImage> {
    let stripes = Rgb32FImage::from_fn(40, 48, |x, y| {
        image::Rgb([((x / 4) % 2) as f32, 0.2, ((y / 6) % 2) as f32])
    });
    let dots = Rgb32FImage::from_fn(48, 40, |x, y| {
        image::Rgb([0.9, ((x * y) % 7) as f32 / 7.0, 0.1])
    });
    vec![
        StyleImage {
            name: "stripes".into(),
            image: stripes,
        },
        StyleImage {
            name: "dots".into(),
            image: dots,
        },
    ]
}

/// The views of a small generated scene (in a temporary folder), the bundled encoder and the
/// two test styles.
struct Fixture {
    tmp: tempfile::TempDir,
    views: RenderedViews,
    enc: EncoderWeights,
    styles: Vec<StyleImage>,
}

impl Fixture {
    fn new() -> Self {
        let tmp = tempfile::tempdir().unwrap();
        Self {
            views: views(&tmp.path().join("scene")),
            enc: EncoderWeights::bundled().unwrap(),
            styles: styles(),
            tmp,
        }
    }

    fn inputs(&self) -> Inputs<'_> {
        Inputs {
            views: &self.views,
            styles: &self.styles,
            encoder: &self.enc,
            init_decoder: None,
        }
    }
}

#[test]
fn tiny_run_writes_outputs_and_resumes_exactly() {
    let fixture = Fixture::new();
    let (tmp, inputs) = (&fixture.tmp, fixture.inputs());
    let cfg = DecoderPretrainConfig::preset(Preset::Tiny);
    let dev = Device::Cpu;

    let full = tmp.path().join("full");
    let Outcome::Done(report) = run(inputs, &cfg, &full, &StageControl::default(), &dev).unwrap()
    else {
        panic!("an uninterrupted run finishes");
    };
    assert_eq!(report.loss_log.len() as u64, cfg.steps);
    assert_eq!(report.started_from, BUNDLED_DECODER_NAME);
    assert!(report
        .loss_log
        .iter()
        .all(|l| l.content.is_finite() && l.style.is_finite() && l.consistency.is_finite()));
    assert!(report.consistency_mse.is_finite() && report.style_loss.is_finite());
    for f in [
        "decoder.safetensors",
        "adain_decoder.safetensors",
        "vae.safetensors",
        "styles.json",
        "metrics.json",
        "curves.png",
        "sheets/style-0.png",
        "sheets/style-1.png",
    ] {
        assert!(full.join(f).exists(), "{f} missing");
    }
    let styles_file: StylesFile =
        serde_json::from_slice(&std::fs::read(full.join("styles.json")).unwrap()).unwrap();
    assert_eq!(styles_file.styles.len(), 2);
    assert_eq!(styles_file.styles[0].latent.mu.len(), cfg.vae.latent);
    assert!(styles_file.styles[1].latent.sigma.iter().all(|s| *s > 0.0));

    // The plain-AdaIN baseline is the decoder before L_co switched on, not the final one.
    let read = |dir: &std::path::Path, f: &str| std::fs::read(dir.join(f)).unwrap();
    assert!(cfg.consistency_from > 0.0 && cfg.consistency_from < 1.0);
    assert_ne!(
        read(&full, "adain_decoder.safetensors"),
        read(&full, "decoder.safetensors")
    );

    // Stopped after the switch: the checkpoint must carry the baseline's weights.
    let resumed = tmp.path().join("resumed");
    let mut stop = StageControl::default();
    let switch = (cfg.steps as f64 * cfg.consistency_from).round() as u64;
    stop.stop_after_step = Some(switch + 1);
    assert_eq!(
        run(inputs, &cfg, &resumed, &stop, &dev).unwrap(),
        Outcome::Stopped { step: switch + 1 }
    );
    let Outcome::Done(r2) = run(inputs, &cfg, &resumed, &StageControl::default(), &dev).unwrap()
    else {
        panic!("the resumed run finishes");
    };
    assert_eq!(r2.resumed_from, switch + 1);
    assert_eq!(r2.loss_log, report.loss_log);
    for f in ["decoder.safetensors", "adain_decoder.safetensors"] {
        assert_eq!(
            read(&full, f),
            read(&resumed, f),
            "{f} differs after resuming"
        );
    }
}

#[test]
fn each_teachers_palette_gives_its_output_the_paintings_colours() {
    let fixture = Fixture::new();
    let (tmp, inputs) = (&fixture.tmp, fixture.inputs());
    let dev = Device::Cpu;
    let cfg = DecoderPretrainConfig {
        steps: 2,
        vae_steps: 2,
        ..DecoderPretrainConfig::preset(Preset::Tiny)
    };
    assert!(cfg.palette && cfg.eval_stride == 1, "every view is fitted");
    let read_styles = |out: &Path| -> StylesFile {
        serde_json::from_slice(&std::fs::read(out.join("styles.json")).unwrap()).unwrap()
    };
    let out = tmp.path().join("on");
    run(inputs, &cfg, &out, &StageControl::default(), &dev).unwrap();
    let file = read_styles(&out);
    let encoder = VggEncoder::new(&fixture.enc, &dev).unwrap();
    let mean = |rgb: &[Vec<f32>]| {
        let images: Vec<&[f32]> = rgb.iter().map(Vec::as_slice).collect();
        ColourMoments::of(&images).unwrap().mean
    };
    for (decoder_file, palette_of) in [
        (
            "decoder.safetensors",
            (|s: &StyleLatent| s.palette) as fn(&StyleLatent) -> Palette,
        ),
        ("adain_decoder.safetensors", |s: &StyleLatent| {
            s.adain_palette
        }),
    ] {
        let net = AdaInNet {
            encoder: encoder.clone(),
            decoder: Decoder::load(&out.join(decoder_file), &dev).unwrap().0,
        };
        for (style, latent) in fixture.styles.iter().zip(&file.styles) {
            let painting = to_tensor(&style.image, cfg.style_size, &dev).unwrap();
            let target = net.style_target(&painting).unwrap();
            let palette = palette_of(latent);
            assert_ne!(palette, Palette::IDENTITY, "{decoder_file} {}", style.name);
            // The teacher's output on every view, as seen, through the palette.
            let mapped: Vec<Vec<f32>> = (0..fixture.views.len())
                .map(|i| {
                    let x = hwc_to_tensor(fixture.views.rgb(i), 32, 32, &dev).unwrap();
                    let mut rgb = tensor_to_hwc(&net.stylize(&x, &target, 1.0).unwrap())
                        .unwrap()
                        .2;
                    palette.affine_rgb(&mut rgb);
                    rgb
                })
                .collect();
            let (got, want) = (mean(&mapped), mean(&[tensor_to_hwc(&painting).unwrap().2]));
            assert!(
                (got - want).amax() < 1e-3,
                "{decoder_file} {}: {got:?} vs {want:?}",
                style.name
            );
        }
    }

    // Off: the decoders keep their own colours.
    let off = tmp.path().join("off");
    let cfg_off = DecoderPretrainConfig {
        palette: false,
        ..cfg
    };
    run(inputs, &cfg_off, &off, &StageControl::default(), &dev).unwrap();
    for s in read_styles(&off).styles {
        assert_eq!(
            (s.palette, s.adain_palette),
            (Palette::IDENTITY, Palette::IDENTITY)
        );
    }
}

#[test]
fn the_bundled_decoder_is_the_start_only_for_its_encoder() {
    let tmp = tempfile::tempdir().unwrap();
    let views = views(&tmp.path().join("scene"));
    let styles = styles();
    let mut other = EncoderWeights::bundled().unwrap();
    other.source = "another encoder".into();
    let bundled = EncoderWeights::bundled().unwrap();
    let tiny = DecoderPretrainConfig {
        steps: 2,
        vae_steps: 2,
        ..DecoderPretrainConfig::preset(Preset::Tiny)
    };
    let fresh = DecoderPretrainConfig {
        start: DecoderStart::Fresh,
        ..tiny.clone()
    };
    for (k, (enc, cfg, want)) in [
        (&other, &tiny, "fresh"),
        (&bundled, &fresh, "fresh"),
        (&bundled, &tiny, BUNDLED_DECODER_NAME),
    ]
    .into_iter()
    .enumerate()
    {
        let inputs = Inputs {
            views: &views,
            styles: &styles,
            encoder: enc,
            init_decoder: None,
        };
        let out = tmp.path().join(format!("run-{k}"));
        let Outcome::Done(report) =
            run(inputs, cfg, &out, &StageControl::default(), &Device::Cpu).unwrap()
        else {
            panic!("finishes");
        };
        assert_eq!(report.started_from, want, "case {k}");
    }
}

#[test]
fn bad_schedule_settings_are_config_errors_naming_the_field() {
    let fixture = Fixture::new();
    let (tmp, inputs) = (&fixture.tmp, fixture.inputs());
    let base = DecoderPretrainConfig::preset(Preset::Tiny);
    for (cfg, field) in [
        (
            DecoderPretrainConfig {
                consistency_from: 1.5,
                ..base.clone()
            },
            "decoder_pretrain.consistency_from",
        ),
        (
            DecoderPretrainConfig {
                eval_stride: 0,
                ..base.clone()
            },
            "decoder_pretrain.eval_stride",
        ),
    ] {
        let out = tmp.path().join("out");
        let err = run(inputs, &cfg, &out, &StageControl::default(), &Device::Cpu).unwrap_err();
        assert!(err.to_string().contains(field), "{err}");
        assert!(!out.join("decoder.safetensors").exists());
    }
}
