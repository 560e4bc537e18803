//! Stage 4, `mutual_learning`: the stylized NeRF and the 2D decoder learn from each other.
//!
//! Each step takes a training view i, a style j and a `patch`×`patch` window of the view:
//! - the stylized NeRF renders the window's rays with latent l_ij (frozen density, cached
//!   surface samples — see [`crate::stylized::surface`]);
//! - the decoder stylizes view i with style j (AdaIN on the whole view's relu4_1, decoded on
//!   the window's part of the feature map): C_2d, without the decoder's palette (the decoder
//!   keeps learning here, and its palette was fitted to it before; BENCHMARKS.md, "The
//!   painting's palette");
//! - L_mimic = mean ‖C_nerf − C_2d‖² over the window (C_2d clamped to [0, 1] as the NeRF's
//!   target).
//!
//! The style module and the latents minimise L_N = L_mimic + λ_d L_d + λ_sN L_s(C_nerf window)
//! (C_2d detached; the last term is ours, `nerf_style_weight`, see docs/STYLIZED.md). After the
//! first `decoder_freeze` fraction of the steps, the decoder also learns, minimising
//! L_C = λ_m L_mimic + λ_s L_s + L_c (C_nerf detached): the NeRF's multi-view-consistent colours
//! pull the decoder towards consistency while the style and content losses keep it stylizing.
//! While the decoder is frozen its outputs are cached per (view, style).
//!
//! At the end, the stylized NeRF gets a palette per style as the decoders did ([`Palette`]),
//! fitted to its own colours on every training view under the style's mean latent: its colour
//! comes from the colour-blind encoder's style loss and from a teacher in colours partly its
//! own. One map per style for every view; `render_stylized` applies it to the NeRF's colours.
//! The fine-tuned decoder's palettes are refitted the same way (on its output for every
//! training view): it changed here, and `decoder_pretrain`'s maps describe it as it was.
//!
//! Output folder: `style_module.safetensors`, `latents.safetensors` (codes, μ, σ) with
//! `latents.json` (style names, the NeRF's and the fine-tuned decoder's palettes),
//! `decoder.safetensors` (fine-tuned), `curves.png` (the loss
//! terms over the steps), `metrics.json` (written last), and `ckpt/` (style module, latents, decoder, both optimisers' moments, RNG).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::checkpoint::write_json_atomic;
use crate::curves::{self, Series, Term};
use crate::field::saved;
use crate::named::{load_vars, tensors_of};
use crate::optim::{Adam, AdamConfig};
use crate::per_view::per_view;
use crate::rng::Rng;
use crate::stages::decoder_pretrain::{crop_views, StylesFile};
use crate::stages::training::Training;
use crate::stages::window::Window;
use crate::stages::{Outcome, Progress, StageControl};
use crate::style2d::adain::adain;
use crate::style2d::arch::VggArch;
use crate::style2d::decoder::Decoder;
use crate::style2d::encoder::{Features, VggEncoder};
use crate::style2d::images::{hwc_to_tensor, StyleImage};
use crate::style2d::losses::{content_loss, mse, style_loss};
use crate::style2d::network::{AdaInNet, StyleTarget};
use crate::style2d::palette::{ColourMoments, Palette};
use crate::style2d::weights::EncoderWeights;
use crate::stylized::latents::LatentCodes;
use crate::stylized::style_module::{StyleModule, StyleModuleConfig};
use crate::stylized::surface::SurfaceSamples;
use crate::views::RenderedViews;
use crate::{EngineError, Result};
use stylenerf_plan::{Preset, Stage};

/// Configuration of the stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MutualConfig {
    pub steps: u64,
    /// Side of the square window trained per step (a multiple of 8).
    pub patch: usize,
    /// Learning rate of the style module and the latents.
    pub lr: f64,
    /// Learning rate of the decoder.
    pub decoder_lr: f64,
    /// λ_d, on the proper Gaussian NLL (see [`crate::stylized::latents`]).
    pub latent_weight: f64,
    /// λ_s.
    pub style_weight: f64,
    /// λ_m. The paper's 10 is relative to its loss scale; with this project's normalised
    /// encoder the style and content losses are 10–100× larger (see docs/STYLE2D.md), so the
    /// default is 100: L_mimic then weighs on the decoder as L_co does in `decoder_pretrain`.
    pub mimic_weight: f64,
    /// Weight of a style loss on the stylized NeRF's own window (0: mimicry only). L_mimic
    /// alone pulls the NeRF towards the average of the decoder's view-inconsistent outputs,
    /// which is flatter than any of them; this term keeps the NeRF's window stylized. Larger
    /// weights paint finer, more saturated texture and cost consistency (docs/STYLIZED.md).
    pub nerf_style_weight: f64,
    /// Fraction of the steps during which the decoder is frozen.
    pub decoder_freeze: f64,
    /// Fine-tune the decoder at all (off: the "no decoder fine-tuning" ablation).
    pub finetune_decoder: bool,
    /// Learn one latent per (view, style) (off: one fixed code per style, its mean).
    pub learnable_latents: bool,
    pub style_module: StyleModuleConfig,
    /// Longer side the style images are resized to for their statistics.
    pub style_size: u32,
    /// Fit the stylized NeRF's palette for each style at the end ([`Palette`], as
    /// `decoder_pretrain` does for its decoders): the chroma map that gives its colours on the
    /// training views the painting's chroma and mean luma. Off: identity maps.
    #[serde(default = "crate::style2d::palette::fitted_by_default")]
    pub palette: bool,
    pub seed: u64,
}

impl MutualConfig {
    pub fn preset(preset: Preset) -> Self {
        let base = Self {
            steps: 300,
            patch: 64,
            lr: 2e-3,
            decoder_lr: 1e-4,
            latent_weight: 1e-4,
            style_weight: 1.0,
            mimic_weight: 100.0,
            nerf_style_weight: 0.128,
            decoder_freeze: 0.4,
            finetune_decoder: true,
            learnable_latents: true,
            style_module: StyleModuleConfig::default(),
            style_size: 256,
            palette: true,
            seed: 0,
        };
        match preset {
            Preset::Tiny => Self {
                steps: 12,
                patch: 16,
                style_size: 32,
                style_module: StyleModuleConfig {
                    hidden: 16,
                    hidden_layers: 2,
                    frequencies: 2,
                    use_geometry: true,
                    background_frequencies: 2,
                },
                ..base
            },
            Preset::Quick => base,
            Preset::Standard => Self {
                steps: 3000,
                ..base
            },
            // The paper's schedule: 50k iterations, the decoder fixed for the first 20k
            // (`decoder_freeze` 0.4). docs/STYLIZED.md lists what differs from the paper.
            Preset::Paper => Self {
                steps: 50_000,
                style_module: StyleModuleConfig {
                    hidden: 128,
                    hidden_layers: 4,
                    ..StyleModuleConfig::default()
                },
                ..base
            },
        }
    }
}

/// Loss values at one step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MutualRecord {
    pub step: u64,
    pub mimic: f32,
    pub latent_nll: f32,
    /// Style loss of the NeRF's window (0 when `nerf_style_weight` is 0).
    pub nerf_style: f32,
    /// Decoder losses (0 while it is frozen).
    pub content: f32,
    pub style: f32,
}

/// The stage's metrics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MutualReport {
    pub steps: u64,
    pub resumed_from: u64,
    pub train_seconds: f64,
    pub loss_log: Vec<MutualRecord>,
    /// Mean L_mimic over the first and the last 10% of the steps.
    pub mimic_start: f32,
    pub mimic_end: f32,
    /// Relative change of the decoder's weights, ‖θ_end − θ_start‖ / ‖θ_start‖.
    pub decoder_change: f32,
    /// Mean |l − μ_j| / σ_j of the final codes.
    pub latent_deviation: f32,
}

/// What `latents.json` holds: the style names, in latent order, and the palettes of the NeRF
/// and of the fine-tuned decoder.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LatentsFile {
    pub styles: Vec<String>,
    pub num_views: usize,
    /// Per style, the colour map applied to the stylized NeRF's colours under that style
    /// (empty in files written before palettes: identity).
    #[serde(default)]
    pub palettes: Vec<Palette>,
    /// Per style, the fine-tuned decoder's palette (as `palettes`): the decoder changed here,
    /// so `decoder_pretrain`'s map for it no longer fits.
    #[serde(default)]
    pub decoder_palettes: Vec<Palette>,
}

/// What a checkpoint holds besides the weights and the optimisers' moments.
#[derive(Serialize, Deserialize)]
struct TrainingState {
    rng: Rng,
    config: MutualConfig,
    loss_log: Vec<MutualRecord>,
    /// Steps the decoder's optimiser has taken (it starts after the freeze).
    decoder_steps: u64,
}

/// What the stage reads.
#[derive(Debug, Clone, Copy)]
pub struct Inputs<'a> {
    /// The `nerf_pretrain` output folder.
    pub field_dir: &'a Path,
    /// The `render_views` output (its training views are the training instances).
    pub views: &'a RenderedViews,
    /// The `decoder_pretrain` output folder (`decoder.safetensors`, `styles.json`).
    pub decoder_dir: &'a Path,
    pub styles: &'a [StyleImage],
    pub encoder: &'a EncoderWeights,
}

/// The training views with what every step reuses.
struct TrainingViews {
    views: RenderedViews,
    /// Index into `views` of each training view.
    indices: Vec<usize>,
    surfaces: Vec<SurfaceSamples>,
    /// relu4_1 of each training view.
    features: Vec<Tensor>,
}

impl TrainingViews {
    fn load(
        inputs: &Inputs,
        encoder: &VggEncoder,
        control: &StageControl,
        device: &Device,
    ) -> Result<Self> {
        let views = crop_views(inputs.views)?;
        let indices = views.train_indices();
        if indices.is_empty() {
            return Err(EngineError::config(
                "views",
                "the rendered views have no training views",
            ));
        }
        let (field, meta) = saved::load(inputs.field_dir, device)?;
        let prepared = per_view(
            indices.len(),
            device,
            Some(control),
            |k| {
                let i = indices[k];
                let surface = SurfaceSamples::for_camera(&field, &meta, &views.views[i].camera)?;
                let x = hwc_to_tensor(
                    views.rgb(i),
                    views.width as usize,
                    views.height as usize,
                    device,
                )?;
                Ok((surface, encoder.relu4_1(&x)?.detach()))
            },
            |done| {
                control.report(&Progress::preparing(
                    "mutual_learning",
                    "views_prepared",
                    done,
                ))
            },
        )?;
        let (surfaces, features) = prepared.into_iter().unzip();
        Ok(Self {
            views,
            indices,
            surfaces,
            features,
        })
    }

    fn width(&self) -> usize {
        self.views.width as usize
    }

    fn height(&self) -> usize {
        self.views.height as usize
    }
}

/// Per style `s`, the palette fitted to `frame(s, k)` `[3, H, W]` over every training view `k`
/// (as seen), towards the painting's colours; frames are measured one at a time, not kept.
fn fit_palettes(
    data: &TrainingViews,
    paintings: &[Tensor],
    control: &StageControl,
    device: &Device,
    frame: impl Fn(usize, usize) -> Result<Tensor> + Sync,
) -> Result<Vec<Palette>> {
    paintings
        .iter()
        .enumerate()
        .map(|(s, painting)| {
            let moments = per_view(
                data.indices.len(),
                device,
                Some(control),
                |k| ColourMoments::of_image(&frame(s, k)?),
                |_| {},
            )?;
            Palette::fit_moments(&moments.into_iter().flatten().collect::<Vec<_>>(), painting)
        })
        .collect()
}

/// `[1, 3, h, w]` → `[h · w, 3]` (pixel rows).
fn pixel_rows(img: &Tensor) -> Result<Tensor> {
    let (_, c, h, w) = img.dims4()?;
    Ok(img.squeeze(0)?.reshape((c, h * w))?.t()?.contiguous()?)
}

/// Reads `styles.json` of the decoder stage and checks it matches the job's styles.
pub fn read_styles_file(decoder_dir: &Path, styles: &[StyleImage]) -> Result<StylesFile> {
    let path = decoder_dir.join("styles.json");
    let bytes = std::fs::read(&path).map_err(|e| EngineError::io(&path, e))?;
    let file: StylesFile = serde_json::from_slice(&bytes)
        .map_err(|e| EngineError::artifact(&path, format!("cannot parse: {e}")))?;
    if file.styles.len() != styles.len() {
        return Err(EngineError::artifact(
            &path,
            format!(
                "{} styles recorded, the job has {}",
                file.styles.len(),
                styles.len()
            ),
        ));
    }
    Ok(file)
}

/// The decoder's weights as one flat vector (for measuring how much they changed).
fn flat_weights(decoder: &Decoder) -> Result<Tensor> {
    let parts = decoder
        .vars()
        .iter()
        .map(|(_, v)| v.as_tensor().flatten_all())
        .collect::<candle_core::Result<Vec<_>>>()?;
    Ok(Tensor::cat(&parts, 0)?)
}

/// Runs the stage; writes the outputs into `out`. Resumes from `out/ckpt`.
pub fn run(
    inputs: Inputs,
    cfg: &MutualConfig,
    out: &Path,
    control: &StageControl,
    device: &Device,
) -> Result<Outcome<MutualReport>> {
    if cfg.patch < VggArch::STRIDE {
        return Err(EngineError::config(
            "mutual_learning.patch",
            format!("must be at least {}", VggArch::STRIDE),
        ));
    }
    let styles_file = read_styles_file(inputs.decoder_dir, inputs.styles)?;
    let (decoder, _) = Decoder::load(&inputs.decoder_dir.join("decoder.safetensors"), device)?;
    let net = AdaInNet {
        encoder: VggEncoder::new(inputs.encoder, device)?,
        decoder,
    };
    let paintings = inputs
        .styles
        .iter()
        .map(|s| crate::style2d::images::to_tensor(&s.image, cfg.style_size, device))
        .collect::<Result<Vec<_>>>()?;
    let targets: Vec<StyleTarget> = paintings
        .iter()
        .map(|t| Ok(net.style_target(t)?))
        .collect::<Result<_>>()?;
    let data = TrainingViews::load(&inputs, &net.encoder, control, device)?;
    let (n_views, n_styles) = (data.indices.len(), inputs.styles.len());
    let priors: Vec<_> = styles_file
        .styles
        .iter()
        .map(|s| s.latent.clone())
        .collect();
    let mut rng = Rng::new(cfg.seed);
    let latents = if cfg.learnable_latents {
        LatentCodes::sample(&priors, n_views, &mut rng, device)?
    } else {
        LatentCodes::means(&priors, n_views, device)?
    };
    let geometry_dim = data.surfaces[0].geometry_dim;
    let module = StyleModule::new(
        cfg.style_module,
        geometry_dim,
        latents.dim,
        cfg.seed,
        DType::F32,
        device,
    )?;
    let mut nerf_vars = module.vars();
    if cfg.learnable_latents {
        nerf_vars.push(latents.var());
    }
    let mut adam_nerf = Adam::new(nerf_vars, AdamConfig::default())?;
    let mut adam_dec = Adam::new(net.decoder.vars(), AdamConfig::default())?;
    let decoder_start = flat_weights(&net.decoder)?;

    let mut training = Training::new(Stage::MutualLearning, out, cfg.steps, control);
    let mut loss_log = Vec::new();
    if let Some(resumed) = training.resume::<TrainingState>(device)? {
        let (tensors, source) = (&resumed.tensors, &resumed.source);
        load_vars(&module.vars(), tensors, source)?;
        let codes = tensors
            .get("latents.codes")
            .ok_or_else(|| EngineError::artifact(source, "checkpoint has no latent codes"))?;
        latents.set_codes(codes)?;
        net.decoder.load_tensors(tensors, source)?;
        adam_nerf.load_state(tensors, training.start())?;
        adam_dec.load_state(tensors, resumed.state.decoder_steps)?;
        (rng, loss_log) = (resumed.state.rng, resumed.state.loss_log);
    }
    let freeze_until = if cfg.finetune_decoder {
        (cfg.steps as f64 * cfg.decoder_freeze).round() as u64
    } else {
        u64::MAX
    };
    // Frozen-decoder outputs per (view, style), as pixel rows [H·W, 3].
    let mut frozen: HashMap<(usize, usize), Tensor> = HashMap::new();
    for step in training.steps() {
        let (v, s) = (rng.below(n_views), rng.below(n_styles));
        let window = Window::random(data.width(), data.height(), cfg.patch, &mut rng);
        let pixels = window.pixels(data.width());
        let pixel_idx = Tensor::from_vec(
            pixels.iter().map(|&p| p as u32).collect::<Vec<_>>(),
            pixels.len(),
            device,
        )?;
        let code = latents.code(v, s)?;
        let batch = data.surfaces[v].batch(&pixels, device)?;
        let c_nerf = module.render(&batch, &code)?;
        let train_decoder = step >= freeze_until;
        let target = adain(&data.features[v], &targets[s].stats[3], 1.0)?;
        // The decoder's window: the window's part of the AdaIN target (statistics of the whole
        // view) and its decoding, while the decoder learns.
        let decoded = if train_decoder {
            let feat = window.crop(&target, VggArch::STRIDE)?;
            let o = net.decoder.forward(&feat)?;
            Some((feat, o))
        } else {
            None
        };
        let nerf_image = if cfg.nerf_style_weight > 0.0 {
            Some(
                c_nerf
                    .reshape((1, window.height, window.width, 3))?
                    .permute((0, 3, 1, 2))?
                    .contiguous()?,
            )
        } else {
            None
        };
        // One encoder pass over the NeRF's window and the decoder's output: the same features
        // as two passes, with half the per-op overhead on these small images.
        let images: Vec<&Tensor> = nerf_image
            .iter()
            .chain(decoded.iter().map(|(_, o)| o))
            .collect();
        let features = match images.len() {
            0 => None,
            _ => Some(net.encoder.features(&Tensor::cat(&images, 0)?)?),
        };
        let features_of = |k: usize| -> Result<Features> {
            let f = features.as_ref().expect("an image was encoded");
            Ok([
                f[0].narrow(0, k, 1)?,
                f[1].narrow(0, k, 1)?,
                f[2].narrow(0, k, 1)?,
                f[3].narrow(0, k, 1)?,
            ])
        };
        let (c_2d, decoder_terms) = match &decoded {
            Some((feat, o)) => {
                let feats = features_of(usize::from(nerf_image.is_some()))?;
                let lc = content_loss(&feats[3], feat)?;
                let ls = style_loss(&feats, &targets[s].stats)?;
                (pixel_rows(o)?, Some((lc, ls)))
            }
            None => {
                let rows = match frozen.entry((v, s)) {
                    std::collections::hash_map::Entry::Occupied(e) => e.into_mut(),
                    std::collections::hash_map::Entry::Vacant(e) => {
                        e.insert(pixel_rows(&net.decoder.forward(&target)?.detach())?)
                    }
                };
                (rows.index_select(&pixel_idx, 0)?, None)
            }
        };
        let mimic_nerf = mse(&c_nerf, &c_2d.detach().clamp(0f32, 1f32)?)?;
        let nll = latents.nll(v, s)?;
        let mut total = (&mimic_nerf + (&nll * cfg.latent_weight)?)?;
        let mut nerf_style = 0.0;
        if nerf_image.is_some() {
            let ls = style_loss(&features_of(0)?, &targets[s].stats)?;
            nerf_style = ls.to_scalar::<f32>()?;
            total = (total + (ls * cfg.nerf_style_weight)?)?;
        }
        let mut rec = MutualRecord {
            step: step + 1,
            mimic: mimic_nerf.to_scalar()?,
            latent_nll: nll.to_scalar()?,
            nerf_style,
            content: 0.0,
            style: 0.0,
        };
        if let Some((lc, ls)) = &decoder_terms {
            let mimic_2d = mse(&c_2d, &c_nerf.detach())?;
            let l_c = (((mimic_2d * cfg.mimic_weight)? + (ls * cfg.style_weight)?)? + lc)?;
            total = (total + l_c)?;
            rec.content = lc.to_scalar()?;
            rec.style = ls.to_scalar()?;
        }
        let grads = total.backward()?;
        adam_nerf.step(&grads, cfg.lr)?;
        if train_decoder {
            adam_dec.step(&grads, cfg.decoder_lr)?;
        }
        let done = step + 1;
        loss_log.push(rec);
        let mut p = training.progress(done);
        p.loss = Some(rec.mimic as f64);
        p.metrics.insert("mimic".into(), rec.mimic as f64);
        p.metrics.insert("latent_nll".into(), rec.latent_nll as f64);
        if train_decoder {
            p.metrics.insert("style".into(), rec.style as f64);
            p.metrics.insert("content".into(), rec.content as f64);
        }
        control.report(&p);
        let stopped = training.after_step(done, || {
            let mut tensors = tensors_of(&module.vars());
            tensors.push(("latents.codes".into(), latents.codes().clone()));
            tensors.extend(net.decoder.tensors());
            tensors.extend(adam_nerf.state());
            tensors.extend(adam_dec.state());
            let state = TrainingState {
                rng,
                config: cfg.clone(),
                loss_log: loss_log.clone(),
                decoder_steps: adam_dec.step_count(),
            };
            Ok((tensors, state))
        })?;
        if let Some(stopped) = stopped {
            return Ok(stopped);
        }
    }
    let train_seconds = training.seconds();

    std::fs::create_dir_all(out).map_err(|e| EngineError::io(out, e))?;
    module.save(&out.join("style_module.safetensors"))?;
    latents.save(&out.join("latents.safetensors"))?;
    // The palettes: the stylized NeRF's under each style's mean latent (as rendered), and the
    // fine-tuned decoder's, on every training view.
    let (w, h) = (data.width(), data.height());
    let (palettes, decoder_palettes) = if cfg.palette {
        let means = (0..n_styles)
            .map(|s| latents.blend(&[(s, 1.0)]))
            .collect::<Result<Vec<_>>>()?;
        let nerf = fit_palettes(&data, &paintings, control, device, |s, k| {
            let rgb = module.render(&data.surfaces[k].all(device)?, &means[s])?;
            Ok(rgb.detach().t()?.reshape((3, h, w))?)
        })?;
        let decoder = fit_palettes(&data, &paintings, control, device, |s, k| {
            let target = adain(&data.features[k], &targets[s].stats[3], 1.0)?;
            Ok(net.decoder.forward(&target)?.detach().squeeze(0)?)
        })?;
        (nerf, decoder)
    } else {
        let identity = vec![Palette::IDENTITY; n_styles];
        (identity.clone(), identity)
    };
    let latents_file = LatentsFile {
        styles: inputs.styles.iter().map(|s| s.name.clone()).collect(),
        num_views: n_views,
        palettes,
        decoder_palettes,
    };
    write_json_atomic(&out.join("latents.json"), &latents_file)?;
    net.decoder
        .save(&out.join("decoder.safetensors"), net.encoder.source())?;
    let tenth = (loss_log.len() / 10).max(1);
    let mean = |r: &[MutualRecord]| r.iter().map(|r| r.mimic).sum::<f32>() / r.len().max(1) as f32;
    let decoder_end = flat_weights(&net.decoder)?;
    let report = MutualReport {
        steps: cfg.steps,
        resumed_from: training.start(),
        train_seconds,
        mimic_start: mean(&loss_log[..tenth.min(loss_log.len())]),
        mimic_end: mean(&loss_log[loss_log.len().saturating_sub(tenth)..]),
        decoder_change: ((&decoder_end - &decoder_start)?.sqr()?.sum_all()?.sqrt()?
            / decoder_start.sqr()?.sum_all()?.sqrt()?)?
        .to_scalar()?,
        latent_deviation: latents.mean_deviation()?,
        loss_log,
    };
    let terms: [Term<MutualRecord>; 5] = [
        ("mimic loss", |r| r.mimic),
        ("latent NLL", |r| r.latent_nll),
        ("NeRF style loss", |r| r.nerf_style),
        ("decoder content loss", |r| r.content),
        ("decoder style loss", |r| r.style),
    ];
    curves::save(out, &Series::terms(&report.loss_log, |r| r.step, &terms))?;
    write_json_atomic(&out.join("metrics.json"), &report)?;
    Ok(Outcome::Done(report))
}
