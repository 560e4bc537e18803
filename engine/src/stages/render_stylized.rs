//! Stage 5, `render_stylized`: render a camera path with the stylized NeRF for each requested
//! style or blend of styles, and evaluate it against the 2D baselines.
//!
//! A style is rendered with its mean latent μ_j; a blend `a:0.3,b:0.7` with Σ w_j μ_j (the 2D
//! methods blend the AdaIN targets' statistics the same way). For every style spec the stage
//! writes, under `<spec>/`: `frames/frame_NNNN.png`, `animation.gif` (and `animation.mp4` when
//! `ffmpeg` is on PATH), `sheet.png` (labelled rows of style | photoreal render | NeRF→AdaIN
//! | stylized NeRF for a few views); its entry in `metrics.json` lists the animations written
//! and says why there is no MP4 when there is none (also at the end of `eval.md`). With evaluation on (the default), it also renders the
//! path with (a) the plain-AdaIN decoder of `decoder_pretrain` (trained without L_co) frame by
//! frame (the paper's NeRF→AdaIN baseline) and (b) the mutually fine-tuned decoder, each
//! through its palette (`styles.json` and `latents.json`; the stylized NeRF's own palettes are
//! in `latents.json` too), and
//! reports for (a), (b) and (c) the stylized NeRF the warped consistency errors, the
//! style/content losses ([`crate::eval`]) and the colour/texture distances to the painting
//! measured outside the encoder ([`crate::style_metrics`]), with the unstylized frames'
//! distances as the floor: `metrics.json` and `eval.md` (written last).
//!
//! The default path is `render_views`' interpolated path, whose depth is the field's; any
//! other camera path is given as cameras and its depth comes from the frozen density.

use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::checkpoint::write_json_atomic;
use crate::eval::{fidelity, GapError, PathWarps};
use crate::field::radiance::RadianceField;
use crate::field::saved::{self, FieldMeta};
use crate::image_io;
use crate::per_view::per_view;
use crate::stages::decoder_pretrain::crop_views;
use crate::stages::mutual_learning::{read_styles_file, LatentsFile};
use crate::stages::pose_consistency::{PoseFrames, PoseScores, GAPS};
use crate::stages::{Outcome, Progress, StageControl};
use crate::style2d::adain::{adain, Stats};
use crate::style2d::arch::VggArch;
use crate::style2d::decoder::Decoder;
use crate::style2d::encoder::VggEncoder;
use crate::style2d::images::{hwc_to_tensor, tensor_to_hwc, StyleImage};
use crate::style2d::network::StyleTarget;
use crate::style2d::palette::Palette;
use crate::style2d::weights::EncoderWeights;
use crate::style_metrics::StyleReference;
use crate::stylized::latents::LatentCodes;
use crate::stylized::style_module::StyleModule;
use crate::stylized::surface::SurfaceSamples;
use crate::views::RenderedViews;
use crate::warp::WarpConfig;
use crate::{EngineError, Result};
use stylenerf_plan::Preset;

/// Configuration of the stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderStylizedConfig {
    /// Style specs: a style name (`waves`) or a blend (`mosaic:0.3,waves:0.7`). Empty: every
    /// style on its own.
    pub styles: Vec<String>,
    /// Evaluate consistency and fidelity against the 2D baselines.
    pub eval: bool,
    /// Frame gaps of the short- and long-range consistency.
    pub short_gap: usize,
    pub long_gap: usize,
    /// Pixels rendered less opaque than this have no depth for warping.
    pub min_opacity: f32,
    /// Relative depth tolerance of the warp's occlusion test.
    pub rel_tolerance: f32,
    /// Rows of the contact sheet.
    pub sheet_rows: usize,
    /// Delay between animation frames.
    pub frame_ms: u32,
    /// Longer side the style images are resized to for their statistics.
    pub style_size: u32,
    /// Style and content losses are measured on every this-many-th frame (VGG passes on every
    /// frame of every method would cost more than the rendering).
    pub fidelity_stride: usize,
    /// Training views (the first, in dataset order) at which consistency is also measured
    /// with the dataset's ground-truth depth, when it has some ([`crate::stages::pose_consistency`]); 0: off.
    #[serde(default)]
    pub truth_views: usize,
}

impl RenderStylizedConfig {
    pub fn preset(preset: Preset) -> Self {
        let base = Self {
            styles: Vec::new(),
            eval: true,
            short_gap: 1,
            long_gap: 7,
            min_opacity: 0.5,
            rel_tolerance: WarpConfig::default().rel_tolerance,
            sheet_rows: 3,
            frame_ms: 80,
            style_size: 256,
            fidelity_stride: 3,
            truth_views: 12,
        };
        match preset {
            Preset::Tiny => Self {
                long_gap: 3,
                sheet_rows: 2,
                style_size: 32,
                truth_views: 4,
                ..base
            },
            _ => base,
        }
    }
}

/// Consistency and fidelity of one method on one style spec.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MethodScores {
    pub method: String,
    pub short_range: GapError,
    pub long_range: GapError,
    pub style_loss: f64,
    pub content_loss: f64,
    /// Measured outside the encoder ([`crate::style_metrics`]), against the spec's main style.
    pub outside: OutsideScores,
}

/// Style fidelity outside the training feature space: sliced Wasserstein distance of the
/// frames' Lab colours to the painting's, and the distance of their Gabor texture signatures.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OutsideScores {
    pub colour_swd: f64,
    pub texture_distance: f64,
}

impl OutsideScores {
    fn of(reference: &StyleReference, frames: &[Tensor]) -> Result<Self> {
        let raw = frames
            .iter()
            .map(tensor_to_hwc)
            .collect::<Result<Vec<_>>>()?;
        let views: Vec<(usize, usize, &[f32])> = raw
            .iter()
            .map(|(w, h, rgb)| (*w as usize, *h as usize, rgb.as_slice()))
            .collect();
        let (colour_swd, texture_distance) = reference.score(&views);
        Ok(Self {
            colour_swd,
            texture_distance,
        })
    }
}

/// Everything measured for one style spec.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SpecReport {
    pub spec: String,
    pub folder: String,
    pub frames: usize,
    /// Empty without evaluation.
    pub methods: Vec<MethodScores>,
    /// The unstylized frames' [`OutsideScores`]: the "did nothing" floor (with evaluation).
    pub unstylized: Option<OutsideScores>,
    /// Consistency at the training poses with ground-truth depth ([`crate::stages::pose_consistency`]), per
    /// method; empty when the dataset has no depth or without evaluation.
    #[serde(default)]
    pub at_poses: Vec<PoseScores>,
    /// The animations written: `animation.gif`, and `animation.mp4` when ffmpeg made one.
    #[serde(default)]
    pub animations: Vec<String>,
    /// Why there is no `animation.mp4`, when there is none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub animation_note: Option<String>,
}

/// Consistency of the unstylized NeRF rendering along the same path: the floor that
/// resampling, occlusion edges and view-dependent colour leave for any rendering of this scene.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PhotorealScores {
    pub short_range: GapError,
    pub long_range: GapError,
}

/// The stage's metrics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderStylizedReport {
    pub specs: Vec<SpecReport>,
    /// Present with evaluation.
    pub photoreal: Option<PhotorealScores>,
    /// Training views measured at their poses with ground-truth depth (0: none).
    #[serde(default)]
    pub pose_views: usize,
    /// The unstylized renders' consistency at those poses: the floor there.
    #[serde(default)]
    pub photoreal_at_poses: Option<PoseScores>,
    pub seconds: f64,
}

/// What the stage reads.
#[derive(Debug, Clone, Copy)]
pub struct Inputs<'a> {
    pub field_dir: &'a Path,
    /// The `render_views` output (its path views are the default camera path).
    pub views: &'a RenderedViews,
    /// The `decoder_pretrain` output folder (`adain_decoder.safetensors`: the baseline).
    pub decoder_dir: &'a Path,
    /// The `mutual_learning` output folder.
    pub mutual_dir: &'a Path,
    pub styles: &'a [StyleImage],
    pub encoder: &'a EncoderWeights,
    /// A camera path to render instead of the default one.
    pub path: Option<&'a [Camera]>,
}

/// A parsed style spec: (style index, weight) pairs.
#[derive(Debug, Clone, PartialEq)]
pub struct Blend {
    pub spec: String,
    pub weights: Vec<(usize, f32)>,
}

impl Blend {
    /// Parses `name` or `a:0.3,b:0.7` against the job's style names.
    pub fn parse(spec: &str, names: &[String]) -> Result<Self> {
        let bad = |reason: String| EngineError::config("style", format!("`{spec}`: {reason}"));
        let mut weights = Vec::new();
        for part in spec.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let (name, w) = match part.rsplit_once(':') {
                Some((n, w)) => (
                    n.trim(),
                    w.trim()
                        .parse::<f32>()
                        .map_err(|_| bad(format!("weight `{w}` is not a number")))?,
                ),
                None => (part, 1.0),
            };
            if !(w.is_finite() && w >= 0.0) {
                return Err(bad(format!("weight of `{name}` must be ≥ 0")));
            }
            let j = names.iter().position(|n| n == name).ok_or_else(|| {
                bad(format!(
                    "no style named `{name}` (styles: {})",
                    names.join(", ")
                ))
            })?;
            weights.push((j, w));
        }
        if weights.iter().map(|(_, w)| w).sum::<f32>() <= 0.0 {
            return Err(bad("needs a style with a positive weight".into()));
        }
        Ok(Self {
            spec: spec.to_string(),
            weights,
        })
    }

    /// A folder name for the spec.
    fn folder(&self, names: &[String]) -> String {
        if self.weights.len() == 1 {
            return names[self.weights[0].0].clone();
        }
        self.weights
            .iter()
            .map(|(j, w)| format!("{}-{w}", names[*j]))
            .collect::<Vec<_>>()
            .join("_")
    }

    /// A teacher's palette for the blend: the weighted mean of its styles' maps.
    fn palette(&self, palettes: &[Palette]) -> Palette {
        let parts: Vec<_> = self
            .weights
            .iter()
            .map(|&(j, w)| (palettes[j], w))
            .collect();
        Palette::blend(&parts)
    }

    /// The AdaIN target of the blend: weighted mean of the styles' statistics.
    fn style_target(&self, targets: &[StyleTarget]) -> Result<StyleTarget> {
        let total: f32 = self.weights.iter().map(|(_, w)| w).sum();
        let mix = |f: &dyn Fn(&Stats) -> &Tensor, k: usize| -> Result<Tensor> {
            let mut acc: Option<Tensor> = None;
            for (j, w) in &self.weights {
                let t = (f(&targets[*j].stats[k]) * f64::from(w / total))?;
                acc = Some(match acc {
                    None => t,
                    Some(a) => (a + t)?,
                });
            }
            Ok(acc.expect("non-empty blend"))
        };
        let stats: Vec<Stats> = (0..4)
            .map(|k| {
                Ok(Stats {
                    mean: mix(&|s| &s.mean, k)?,
                    std: mix(&|s| &s.std, k)?,
                })
            })
            .collect::<Result<_>>()?;
        Ok(StyleTarget {
            stats: stats.try_into().expect("four stats"),
        })
    }
}

/// The path to render: cameras, photoreal frames `[3, H, W]` and depths.
struct PathFrames {
    cameras: Vec<Camera>,
    photoreal: Vec<Tensor>,
    depths: Vec<Vec<f32>>,
    surfaces: Vec<SurfaceSamples>,
    width: usize,
    height: usize,
}

fn path_frames(
    (field, meta): (&RadianceField, &FieldMeta),
    views: &RenderedViews,
    path: Option<&[Camera]>,
    cfg: &RenderStylizedConfig,
    control: &StageControl,
    device: &Device,
) -> Result<PathFrames> {
    let (width, height) = (views.width as usize, views.height as usize);
    let (mut cameras, given): (Vec<Camera>, bool) = match path {
        Some(p) => (p.to_vec(), true),
        None => (
            views
                .path_indices()
                .iter()
                .map(|&i| views.views[i].camera)
                .collect(),
            false,
        ),
    };
    if cameras.is_empty() {
        return Err(EngineError::config("path", "the camera path is empty"));
    }
    let s = VggArch::STRIDE as u32;
    if given {
        for (k, cam) in cameras.iter_mut().enumerate() {
            // Crop (top-left) to the stride, as the rendered views are.
            cam.intrinsics.width = cam.intrinsics.width / s * s;
            cam.intrinsics.height = cam.intrinsics.height / s * s;
            if (
                cam.intrinsics.width as usize,
                cam.intrinsics.height as usize,
            ) != (width, height)
            {
                return Err(EngineError::config(
                    "path",
                    format!(
                        "camera {k} renders {}×{}, the views are {width}×{height}",
                        cam.intrinsics.width, cam.intrinsics.height
                    ),
                ));
            }
        }
    }
    let path_views = views.path_indices();
    let frames = per_view(
        cameras.len(),
        device,
        Some(control),
        |k| {
            let cam = &cameras[k];
            let surface = SurfaceSamples::for_camera(field, meta, cam)?;
            let (rgb, depth) = if given {
                let img = crate::render::render_image(
                    field,
                    &meta.camera_rays(cam),
                    &meta.sampling,
                    &|s| field.colour(s),
                    8192,
                )?;
                (img.rgb, surface.surface_depth(cfg.min_opacity))
            } else {
                let i = path_views[k];
                let depth = views
                    .depth(i)
                    .iter()
                    .zip(views.opacity(i))
                    .map(|(&d, &o)| if o >= cfg.min_opacity { d } else { 0.0 })
                    .collect();
                (views.rgb(i).to_vec(), depth)
            };
            let photoreal = hwc_to_tensor(&rgb, width, height, device)?.squeeze(0)?;
            Ok((photoreal, depth, surface))
        },
        |done| {
            control.report(&Progress::preparing(
                "render_stylized",
                "frames_prepared",
                done,
            ))
        },
    )?;
    let mut out = PathFrames {
        cameras,
        photoreal: Vec::new(),
        depths: Vec::new(),
        surfaces: Vec::new(),
        width,
        height,
    };
    for (photoreal, depth, surface) in frames {
        out.photoreal.push(photoreal);
        out.depths.push(depth);
        out.surfaces.push(surface);
    }
    Ok(out)
}

/// Renders the path; writes the outputs into `out`.
pub fn run(
    inputs: Inputs,
    cfg: &RenderStylizedConfig,
    out: &Path,
    control: &StageControl,
    device: &Device,
) -> Result<Outcome<RenderStylizedReport>> {
    let started = std::time::Instant::now();
    let latents_json = inputs.mutual_dir.join("latents.json");
    let latents_file: LatentsFile = serde_json::from_slice(
        &std::fs::read(&latents_json).map_err(|e| EngineError::io(&latents_json, e))?,
    )
    .map_err(|e| EngineError::artifact(&latents_json, format!("cannot parse: {e}")))?;
    let names = latents_file.styles;
    if names.len() != inputs.styles.len() {
        return Err(EngineError::artifact(
            &latents_json,
            format!(
                "{} styles recorded, {} given",
                names.len(),
                inputs.styles.len()
            ),
        ));
    }
    // One palette per style (none recorded: identity).
    let per_style = |recorded: Vec<Palette>, what: &str| match recorded.len() {
        0 => Ok(vec![Palette::IDENTITY; names.len()]),
        n if n == names.len() => Ok(recorded),
        n => Err(EngineError::artifact(
            &latents_json,
            format!("{n} {what} recorded for {} styles", names.len()),
        )),
    };
    let nerf_palettes = per_style(latents_file.palettes, "palettes")?;
    let finetuned_palettes = per_style(latents_file.decoder_palettes, "decoder palettes")?;
    let specs: Vec<Blend> = if cfg.styles.is_empty() {
        names
            .iter()
            .map(|n| Blend::parse(n, &names))
            .collect::<Result<_>>()?
    } else {
        cfg.styles
            .iter()
            .map(|s| Blend::parse(s, &names))
            .collect::<Result<_>>()?
    };
    let module = StyleModule::load(&inputs.mutual_dir.join("style_module.safetensors"), device)?;
    let latents = LatentCodes::load(&inputs.mutual_dir.join("latents.safetensors"), device)?;
    let baseline_palettes: Vec<Palette> = read_styles_file(inputs.decoder_dir, inputs.styles)?
        .styles
        .iter()
        .map(|s| s.adain_palette)
        .collect();
    let encoder = VggEncoder::new(inputs.encoder, device)?;
    let finetuned = Decoder::load(&inputs.mutual_dir.join("decoder.safetensors"), device)?.0;
    let baseline = Decoder::load(
        &inputs.decoder_dir.join("adain_decoder.safetensors"),
        device,
    )?
    .0;
    let style_tensors = inputs
        .styles
        .iter()
        .map(|s| crate::style2d::images::to_tensor(&s.image, cfg.style_size, device))
        .collect::<Result<Vec<_>>>()?;
    let targets = style_tensors
        .iter()
        .map(|t| {
            Ok(StyleTarget {
                stats: crate::style2d::losses::feature_stats(&encoder.features(t)?)?,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    // The painting as the network reads it, for the measures outside its feature space.
    let references = style_tensors
        .iter()
        .map(|t| {
            let (w, h, rgb) = tensor_to_hwc(t)?;
            Ok(StyleReference::new(w as usize, h as usize, &rgb))
        })
        .collect::<Result<Vec<_>>>()?;
    let (field, meta) = saved::load(inputs.field_dir, device)?;
    let views = crop_views(inputs.views)?;
    let path = path_frames((&field, &meta), &views, inputs.path, cfg, control, device)?;
    let relu4_1 = |frames: &[Tensor]| -> Result<Vec<Tensor>> {
        per_view(
            frames.len(),
            device,
            None,
            |k| Ok(encoder.relu4_1(&frames[k].unsqueeze(0)?)?),
            |_| {},
        )
    };
    let features = relu4_1(&path.photoreal)?;
    let warp_cfg = WarpConfig {
        rel_tolerance: cfg.rel_tolerance,
    };
    // The training views with ground-truth depth, their surfaces and features.
    let poses = match cfg.eval {
        true => PoseFrames::prepare(
            &views,
            cfg.truth_views,
            cfg.min_opacity,
            cfg.rel_tolerance,
            device,
        )?,
        false => None,
    };
    let pose_surfaces = match &poses {
        Some(p) => per_view(
            p.cameras.len(),
            device,
            Some(control),
            |k| SurfaceSamples::for_camera(&field, &meta, &p.cameras[k]),
            |_| {},
        )?,
        None => Vec::new(),
    };
    let pose_features = match &poses {
        Some(p) => relu4_1(&p.photoreal)?,
        None => Vec::new(),
    };
    let stylize = |surface: &SurfaceSamples,
                   (latent, palette): (&Tensor, Palette)|
     -> Result<Tensor> {
        // Detached: a frame kept with its graph would hold every activation of the
        // style module (about 100 MB per frame at 128²).
        let rgb = palette.apply_rows(&module.render(&surface.all(device)?, latent)?.detach())?;
        Ok(rgb
            .t()?
            .reshape((3, path.height, path.width))?
            .clamp(0f32, 1f32)?)
    };
    // The path's warps at both gaps, shared by every method and style.
    let warps = if cfg.eval {
        let along = |gap| PathWarps::new(&path.cameras, &path.depths, gap, warp_cfg, device);
        Some((along(cfg.short_gap)?, along(cfg.long_gap)?))
    } else {
        None
    };
    let total = (specs.len() * path.cameras.len()) as u64;
    let mut reports = Vec::new();
    for (si, blend) in specs.iter().enumerate() {
        let folder = blend.folder(&names);
        let dir = out.join(&folder);
        let latent = latents.blend(&blend.weights)?;
        // The stylized NeRF: the blend's latent and palette.
        let nerf = (&latent, blend.palette(&nerf_palettes));
        let target = blend.style_target(&targets)?;
        let finetuned = (&finetuned, blend.palette(&finetuned_palettes));
        let baseline = (&baseline, blend.palette(&baseline_palettes));
        let stylized = per_view(
            path.surfaces.len(),
            device,
            Some(control),
            |k| {
                let frame = stylize(&path.surfaces[k], nerf)?;
                save_frame(
                    &dir.join("frames").join(format!("frame_{k:04}.png")),
                    &frame,
                )?;
                Ok(frame)
            },
            |done| {
                control.report(&Progress {
                    stage: "render_stylized".into(),
                    step: (si * path.cameras.len() + done) as u64,
                    total,
                    ..Default::default()
                })
            },
        )?;
        let (animations, animation_note) = write_animation(&dir, &stylized, cfg.frame_ms)?;
        // A 2D teacher: a decoder with its palette for the blend.
        let decode =
            |(decoder, palette): (&Decoder, Palette), features: &[Tensor]| -> Result<Vec<Tensor>> {
                per_view(
                    features.len(),
                    device,
                    None,
                    |k| {
                        let out = decoder.forward(&adain(&features[k], &target.stats[3], 1.0)?)?;
                        Ok(palette
                            .apply(&out.detach())?
                            .squeeze(0)?
                            .clamp(0f32, 1f32)?)
                    },
                    |_| {},
                )
            };
        let adain_frames = decode(baseline, &features)?;
        let main_style = blend
            .weights
            .iter()
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .expect("non-empty blend")
            .0;
        contact_sheet(
            &dir.join("sheet.png"),
            &style_tensors[main_style],
            [&path.photoreal, &adain_frames, &stylized],
            cfg.sheet_rows,
        )?;
        let mut methods = Vec::new();
        let mut unstylized = None;
        if let Some((short, long)) = &warps {
            let every = |v: &[Tensor]| -> Vec<Tensor> {
                v.iter()
                    .step_by(cfg.fidelity_stride.max(1))
                    .cloned()
                    .collect()
            };
            let reference = &references[main_style];
            unstylized = Some(OutsideScores::of(reference, &every(&path.photoreal))?);
            let finetuned_frames = decode(finetuned, &features)?;
            for (method, frames) in [
                ("NeRF -> AdaIN", &adain_frames),
                ("NeRF -> fine-tuned decoder", &finetuned_frames),
                ("stylized NeRF", &stylized),
            ] {
                let (style_loss, content_loss) =
                    fidelity(&encoder, &every(frames), &every(&features), &target)?;
                methods.push(MethodScores {
                    method: method.into(),
                    short_range: short.error(frames)?,
                    long_range: long.error(frames)?,
                    style_loss,
                    content_loss,
                    outside: OutsideScores::of(reference, &every(frames))?,
                });
            }
        }
        let mut at_poses = Vec::new();
        if let Some(poses) = &poses {
            let stylized = per_view(
                pose_surfaces.len(),
                device,
                None,
                |k| stylize(&pose_surfaces[k], nerf),
                |_| {},
            )?;
            for (method, frames) in [
                ("NeRF -> AdaIN", decode(baseline, &pose_features)?),
                (
                    "NeRF -> fine-tuned decoder",
                    decode(finetuned, &pose_features)?,
                ),
                ("stylized NeRF", stylized),
            ] {
                at_poses.push(poses.score(method, &frames)?);
            }
        }
        reports.push(SpecReport {
            spec: blend.spec.clone(),
            folder,
            frames: stylized.len(),
            methods,
            unstylized,
            at_poses,
            animations,
            animation_note,
        });
    }
    let photoreal = match &warps {
        Some((short, long)) => Some(PhotorealScores {
            short_range: short.error(&path.photoreal)?,
            long_range: long.error(&path.photoreal)?,
        }),
        None => None,
    };
    let photoreal_at_poses = match &poses {
        Some(p) => Some(p.score("NeRF, unstylized (reference)", &p.photoreal)?),
        None => None,
    };
    let report = RenderStylizedReport {
        specs: reports,
        photoreal,
        pose_views: poses.as_ref().map_or(0, |p| p.views.len()),
        photoreal_at_poses,
        seconds: started.elapsed().as_secs_f64(),
    };
    if cfg.eval {
        crate::checkpoint::write_atomic(
            &out.join("eval.md"),
            markdown_table(&report, cfg).as_bytes(),
        )?;
    }
    write_json_atomic(&out.join("metrics.json"), &report)?;
    Ok(Outcome::Done(report))
}

/// The evaluation as a Markdown table in the paper's layout: one row per method and style,
/// short- and long-range consistency (RMSE, MAE), style and content loss, colour SWD and
/// texture distance, each style's unstylized floor, then the unstylized rendering's
/// consistency as a reference row.
pub fn markdown_table(report: &RenderStylizedReport, cfg: &RenderStylizedConfig) -> String {
    let mut s = format!(
        "| style | method | short-range RMSE (gap {}) | short MAE | long-range RMSE (gap {}) | long MAE | style loss | content loss | colour SWD (Lab) | texture distance |\n|---|---|---|---|---|---|---|---|---|---|\n",
        cfg.short_gap, cfg.long_gap
    );
    for spec in &report.specs {
        for m in &spec.methods {
            s += &format!(
                "| {} | {} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.2} | {:.3} |\n",
                spec.spec,
                m.method,
                m.short_range.rmse,
                m.short_range.mae,
                m.long_range.rmse,
                m.long_range.mae,
                m.style_loss,
                m.content_loss,
                m.outside.colour_swd,
                m.outside.texture_distance
            );
        }
        if let Some(u) = &spec.unstylized {
            s += &format!(
                "| {} | NeRF, unstylized (did nothing) | | | | | | | {:.2} | {:.3} |\n",
                spec.spec, u.colour_swd, u.texture_distance
            );
        }
    }
    if let Some(p) = &report.photoreal {
        s += &format!(
            "| (none) | NeRF, unstylized (reference) | {:.4} | {:.4} | {:.4} | {:.4} | | | | |\n",
            p.short_range.rmse, p.short_range.mae, p.long_range.rmse, p.long_range.mae
        );
    }
    if let Some(m) = report.specs.iter().flat_map(|s| &s.methods).next() {
        s += &format!(
            "\nThe warped errors cover the pixels whose point both views see at the field's depth \
             (the same pixels for every method): {:.1} % at gap {}, {:.1} % at gap {}.\n",
            100.0 * m.short_range.coverage,
            cfg.short_gap,
            100.0 * m.long_range.coverage,
            cfg.long_gap
        );
    }
    s += "\nColour SWD and texture distance are measured outside the encoder, against the spec's \
          main style image (lower: closer to the painting); the unstylized row is the floor a \
          method that transfers no style would score.\n";
    if let Some(floor) = &report.photoreal_at_poses {
        s += &format!(
            "\nAt the first {views} training views, in dataset order, with the dataset's \
             ground-truth depth beside the field's (same pairs, same frames; training-view gaps \
             {short} and {long}):\n\n\
             | style | method | RMSE gap {short} (true depth) | RMSE gap {short} (field depth) \
             | RMSE gap {long} (true depth) | RMSE gap {long} (field depth) |\n\
             |---|---|---|---|---|---|\n",
            views = report.pose_views,
            short = GAPS[0],
            long = GAPS[1],
        );
        let row = |style: &str, p: &PoseScores| {
            format!(
                "| {style} | {} | {:.4} | {:.4} | {:.4} | {:.4} |\n",
                p.method,
                p.true_depth[0].rmse,
                p.field_depth[0].rmse,
                p.true_depth[1].rmse,
                p.field_depth[1].rmse
            )
        };
        for spec in &report.specs {
            for p in &spec.at_poses {
                s += &row(&spec.spec, p);
            }
        }
        s += &row("(none)", floor);
    }
    for spec in &report.specs {
        s += &format!("\n{}: {}", spec.spec, spec.animations.join(", "));
        if let Some(note) = &spec.animation_note {
            s += &format!(" ({note})");
        }
    }
    s.push('\n');
    s
}

fn save_frame(path: &Path, frame: &Tensor) -> Result<()> {
    let (w, h, rgb) = tensor_to_hwc(&frame.unsqueeze(0)?)?;
    image_io::save_rgb_png(path, w, h, &rgb)
}

/// `animation.gif`, plus `animation.mp4` when `ffmpeg` is available. Returns the files
/// written, and why there is no MP4 when there is none.
fn write_animation(
    dir: &Path,
    frames: &[Tensor],
    frame_ms: u32,
) -> Result<(Vec<String>, Option<String>)> {
    let path = dir.join("animation.gif");
    let tmp = dir.join(".animation.gif.tmp");
    {
        let file = std::fs::File::create(&tmp).map_err(|e| EngineError::io(&tmp, e))?;
        let mut enc = image::codecs::gif::GifEncoder::new_with_speed(file, 10);
        enc.set_repeat(image::codecs::gif::Repeat::Infinite)
            .map_err(|e| EngineError::artifact(&path, e.to_string()))?;
        for f in frames {
            let (w, h, rgb) = tensor_to_hwc(&f.unsqueeze(0)?)?;
            let rgba = image::DynamicImage::ImageRgb8(image_io::to_rgb8(w, h, &rgb)).into_rgba8();
            let frame = image::Frame::from_parts(
                rgba,
                0,
                0,
                image::Delay::from_numer_denom_ms(frame_ms, 1),
            );
            enc.encode_frame(frame)
                .map_err(|e| EngineError::artifact(&path, e.to_string()))?;
        }
    }
    std::fs::rename(&tmp, &path).map_err(|e| EngineError::io(&path, e))?;
    let mut written = vec!["animation.gif".to_string()];
    match encode_mp4(dir, frame_ms) {
        Ok(()) => {
            written.push("animation.mp4".into());
            Ok((written, None))
        }
        Err(why) => {
            tracing::warn!("{why}; animation.gif is the only animation");
            Ok((written, Some(why)))
        }
    }
}

/// Best effort: `ffmpeg` turns the PNG frames into an H.264 MP4 (written under a temporary
/// name, then renamed); the reason when it cannot.
fn encode_mp4(dir: &Path, frame_ms: u32) -> std::result::Result<(), String> {
    let fps = (1000.0 / frame_ms.max(1) as f64).to_string();
    let mp4: PathBuf = dir.join("animation.mp4");
    let tmp: PathBuf = dir.join(".animation.tmp.mp4");
    let status = std::process::Command::new("ffmpeg")
        .args(["-loglevel", "error", "-y", "-framerate", &fps, "-i"])
        .arg(dir.join("frames").join("frame_%04d.png"))
        .args([
            "-pix_fmt",
            "yuv420p",
            "-vf",
            "scale=trunc(iw/2)*2:trunc(ih/2)*2",
        ])
        .arg(&tmp)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status();
    match status {
        Ok(s) if s.success() => {
            std::fs::rename(&tmp, &mp4)
                .map_err(|e| format!("animation.mp4 not written: renaming it failed: {e}"))?;
            tracing::info!(path = %mp4.display(), "animation.mp4 written");
            Ok(())
        }
        Ok(s) => {
            let _ = std::fs::remove_file(&tmp);
            Err(format!("animation.mp4 not written: ffmpeg failed ({s})"))
        }
        Err(_) => Err(
            "animation.mp4 not written: ffmpeg is not on PATH (the container images include it)"
                .into(),
        ),
    }
}

/// Labelled rows of style | photoreal render | NeRF→AdaIN | stylized NeRF, for `rows` views
/// spread along the path; `frames` are the last three columns' frames.
fn contact_sheet(path: &Path, style: &Tensor, frames: [&[Tensor]; 3], rows: usize) -> Result<()> {
    let n = frames[2].len();
    let (_, h, w) = frames[2][0].dims3()?;
    let rows = rows.clamp(1, n);
    let style = style.interpolate2d(h, w)?.squeeze(0)?;
    let tile = |t: &Tensor| -> Result<image::RgbImage> {
        let (tw, th, rgb) = tensor_to_hwc(t)?;
        Ok(image_io::to_rgb8(tw, th, &rgb))
    };
    let grid = (0..rows)
        .map(|r| {
            let k = r * n / rows;
            std::iter::once(&style)
                .chain(frames.iter().map(|f| &f[k]))
                .map(tile)
                .collect::<Result<Vec<_>>>()
        })
        .collect::<Result<Vec<_>>>()?;
    let labels = [
        "style",
        "photoreal render",
        "NeRF -> AdaIN",
        "stylized NeRF",
    ];
    image_io::save_png(path, &crate::sheet::labelled_grid(&labels, &grid)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blends_parse_and_errors_name_the_problem() {
        let names = vec!["mosaic".to_string(), "waves".to_string()];
        let b = Blend::parse("mosaic:0.3, waves:0.7", &names).unwrap();
        assert_eq!(b.weights, vec![(0, 0.3), (1, 0.7)]);
        assert_eq!(b.folder(&names), "mosaic-0.3_waves-0.7");
        assert_eq!(
            Blend::parse("waves", &names).unwrap().weights,
            vec![(1, 1.0)]
        );
        let e = Blend::parse("dots", &names).unwrap_err().to_string();
        assert!(
            e.contains("no style named `dots`") && e.contains("mosaic, waves"),
            "{e}"
        );
        assert!(Blend::parse("waves:x", &names)
            .unwrap_err()
            .to_string()
            .contains("not a number"));
        assert!(Blend::parse("waves:0", &names).is_err());
        assert!(Blend::parse("waves:-1", &names).is_err());
    }
}
