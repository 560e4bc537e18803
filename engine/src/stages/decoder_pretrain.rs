//! Stage 3, `decoder_pretrain`: train the AdaIN decoder on the rendered views with the
//! content, style and geometric consistency losses, L = L_c + λ_s L_s + λ_co L_co, then train
//! the style VAE and record each style's latent distribution.
//!
//! The first `consistency_from` of the steps train plain AdaIN (λ_co = 0): that decoder is
//! kept as `adain_decoder.safetensors`, the frame-by-frame AdaIN baseline of the evaluation
//! (the paper's baseline is AdaIN without any consistency training); the remaining steps add
//! L_co, as the paper fine-tunes a pretrained AdaIN decoder. With a pretrained `--decoder`,
//! `consistency_from = 0` makes that decoder the baseline.
//!
//! Each step takes one style, a pair of neighbouring views (i, j) and a `patch`² window of
//! view i with the window of view j that shows the same part of the scene
//! ([`Window::follow`]); it stylizes both windows as one batch (AdaIN with the whole views'
//! statistics) and adds L_co = mean over the valid pixels of (O_i − M_ij · W_ij(O_j))², where W_ij
//! warps with view i's rendered depth and both cameras (see [`crate::warp`]); pixels whose
//! rendered opacity is below `min_opacity` have no depth. Views are cropped to multiples of 8.
//!
//! At the end, each decoder gets a palette per style ([`Palette`]): the affine colour map that
//! gives its output on the evaluation views the painting's chroma distribution (mean and
//! covariance) and mean luma, its strokes kept. The encoder's deep features carry little
//! colour, so without it the teacher paints the strokes in colours partly its own. One map
//! per style for all views: it moves no view against another. The evaluation's NeRF→AdaIN
//! applies the plain-AdaIN decoder's; the sheets show the final decoder's.
//!
//! Output folder: `decoder.safetensors`, `adain_decoder.safetensors`, `vae.safetensors`,
//! `styles.json` (per style: name, μ, σ, both decoders' palettes, plus how the style features
//! were computed), `sheets/style-<k>.png` (labelled rows of content | style | output with its
//! palette), `curves.png` (the loss
//! terms over the steps), `metrics.json` (written last),
//! and `ckpt/` (decoder + Adam moments + RNG, and the baseline's weights once L_co is on).

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::checkpoint::write_json_atomic;
use crate::curves::{self, Series, Term};
use crate::optim::{Adam, AdamConfig};
use crate::rng::Rng;
use crate::stages::training::Training;
use crate::stages::window::Window;
use crate::stages::{Outcome, StageControl};
use crate::style2d::adain::adain;
use crate::style2d::arch::VggArch;
use crate::style2d::decoder::{Decoder, BUNDLED_DECODER_NAME};
use crate::style2d::encoder::VggEncoder;
pub use crate::style2d::images::StyleImage;
use crate::style2d::images::{hwc_to_tensor, tensor_to_hwc};
use crate::style2d::network::{AdaInNet, StyleTarget};
use crate::style2d::palette::{ColourMoments, Palette};
use crate::style2d::style_features::{crop_vectors, CropConfig};
use crate::style2d::vae::{LatentGaussian, StyleVae, VaeConfig};
use crate::style2d::weights::EncoderWeights;
use crate::views::RenderedViews;
use crate::warp::{Warp, WarpConfig};
use crate::{EngineError, Result};
use stylenerf_plan::{Preset, Stage};

/// Where the decoder starts when the stage is not given one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DecoderStart {
    /// The general decoder bundled with the binary ([`Decoder::bundled`]) when the encoder is
    /// the one it was trained for; a fresh decoder with any other encoder.
    Bundled,
    /// A freshly initialised decoder (seeded by `seed`).
    Fresh,
}

/// Configuration of the stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecoderPretrainConfig {
    /// The starting decoder when the stage is given none.
    pub start: DecoderStart,
    pub steps: u64,
    /// Side of the square windows trained per step (0: whole views). The window of the
    /// second view is placed where the first window's scene projects.
    pub patch: usize,
    pub lr: f64,
    /// λ_s.
    pub style_weight: f64,
    /// λ_co (0 disables the consistency loss).
    pub consistency_weight: f64,
    /// Fraction of the steps trained as plain AdaIN before L_co is switched on; the decoder
    /// at that point is the evaluation's AdaIN baseline (`adain_decoder.safetensors`).
    pub consistency_from: f64,
    /// The final evaluation pairs every `eval_stride`-th view with its nearest neighbour.
    pub eval_stride: usize,
    /// Each view is paired with one of its this many nearest views (by camera centre).
    pub neighbours: usize,
    /// Pixels rendered less opaque than this have no depth for warping.
    pub min_opacity: f32,
    pub warp: WarpTolerance,
    /// Longer side the style images are resized to for their statistics.
    pub style_size: u32,
    pub vae: VaeConfig,
    pub vae_steps: usize,
    pub vae_lr: f64,
    /// Random crops per style for the VAE (and for its per-style distribution).
    pub crops_per_style: usize,
    pub crop: CropConfig,
    /// Fit each decoder's palette for each style ([`Palette`]): the affine colour map that
    /// gives the decoder's output on the views the painting's chroma and mean luma.
    /// Off: the decoders' own colours (identity maps).
    #[serde(default = "crate::style2d::palette::fitted_by_default")]
    pub palette: bool,
    pub seed: u64,
}

/// The warp's relative depth tolerance (a serialisable copy of [`WarpConfig`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WarpTolerance {
    pub rel_tolerance: f32,
}

impl DecoderPretrainConfig {
    pub fn preset(preset: Preset) -> Self {
        let base = Self {
            start: DecoderStart::Bundled,
            steps: 300,
            patch: 64,
            // Fine-tuning the bundled decoder (a fresh one was trained at 5e-4).
            lr: 1e-4,
            style_weight: 1.0,
            consistency_weight: 1000.0,
            consistency_from: 0.5,
            eval_stride: 8,
            neighbours: 2,
            min_opacity: 0.5,
            warp: WarpTolerance {
                rel_tolerance: WarpConfig::default().rel_tolerance,
            },
            style_size: 256,
            vae: VaeConfig::default(),
            vae_steps: 500,
            vae_lr: 1e-3,
            crops_per_style: 32,
            crop: CropConfig::default(),
            palette: true,
            seed: 0,
        };
        match preset {
            Preset::Tiny => Self {
                steps: 4,
                patch: 16,
                eval_stride: 1,
                style_size: 32,
                vae: VaeConfig {
                    hidden: 32,
                    latent: 8,
                    ..VaeConfig::default()
                },
                vae_steps: 20,
                crops_per_style: 4,
                crop: CropConfig {
                    size: 32,
                    min_scale: 0.5,
                },
                ..base
            },
            Preset::Quick => base,
            Preset::Standard => Self {
                steps: 3000,
                crops_per_style: 64,
                ..base
            },
            // The paper pre-trains the decoder with L_co for 1k iterations; the first half
            // (`consistency_from` 0.5) fine-tunes the bundled decoder as plain AdaIN, the
            // evaluation's baseline.
            Preset::Paper => Self {
                steps: 2_000,
                crops_per_style: 128,
                vae_steps: 2000,
                ..base
            },
        }
    }
}

/// What `styles.json` holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StylesFile {
    /// How the VAE's input was computed (see [`crate::style2d::style_features`]): relu4_1
    /// channel mean + std of `crops_per_style` random crops resized to `crop.size`².
    pub feature: String,
    pub crop: CropConfig,
    pub styles: Vec<StyleLatent>,
}

/// One style: its latent distribution (the moment-matched mixture over its crops) and the
/// teachers' palettes for it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StyleLatent {
    pub name: String,
    #[serde(flatten)]
    pub latent: LatentGaussian,
    /// The colour map of `decoder.safetensors`' output for this style, as its sheet shows it
    /// (`mutual_learning` fits its own for the decoder it fine-tunes from this one): see
    /// [`Palette`]. Identity in files written before palettes, or with `palette` off.
    #[serde(default)]
    pub palette: Palette,
    /// The same for `adain_decoder.safetensors`.
    #[serde(default)]
    pub adain_palette: Palette,
}

/// Loss values at one step.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LossRecord {
    pub step: u64,
    pub content: f32,
    pub style: f32,
    pub consistency: f32,
}

/// The stage's metrics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DecoderPretrainReport {
    /// The decoder training started from: `bundled:…`, `fresh` or the given file.
    #[serde(default)]
    pub started_from: String,
    pub steps: u64,
    pub resumed_from: u64,
    pub train_seconds: f64,
    pub loss_log: Vec<LossRecord>,
    /// Masked MSE between each stylized view and its warped stylized neighbour (evaluation
    /// pairs: every `eval_stride`-th view with its nearest neighbour, every style).
    pub consistency_mse: f64,
    /// Mean style loss of the stylized views (style fidelity).
    pub style_loss: f64,
    pub vae_reconstruction: f32,
}

/// What a checkpoint holds besides the weights and the optimiser's moments.
#[derive(Serialize, Deserialize)]
struct TrainingState {
    rng: Rng,
    config: DecoderPretrainConfig,
    loss_log: Vec<LossRecord>,
}

/// The views cropped (top-left) to multiples of the encoder's stride.
pub(crate) fn crop_views(v: &RenderedViews) -> Result<RenderedViews> {
    let s = VggArch::STRIDE as u32;
    let (w, h) = (v.width / s * s, v.height / s * s);
    if w < 2 * s || h < 2 * s {
        return Err(EngineError::config(
            "views",
            format!("{}×{} is too small to stylize", v.width, v.height),
        ));
    }
    let mut out = RenderedViews {
        width: w,
        height: h,
        views: v.views.clone(),
        rgb: vec![],
        depth: vec![],
        opacity: vec![],
        true_depth: v.true_depth.as_ref().map(|_| vec![]),
    };
    for (i, info) in out.views.iter_mut().enumerate() {
        info.camera.intrinsics.width = w;
        info.camera.intrinsics.height = h;
        for y in 0..h as usize {
            let row = y * v.width as usize;
            out.rgb
                .extend_from_slice(&v.rgb(i)[3 * row..3 * (row + w as usize)]);
            out.depth
                .extend_from_slice(&v.depth(i)[row..row + w as usize]);
            out.opacity
                .extend_from_slice(&v.opacity(i)[row..row + w as usize]);
            if let (Some(to), Some(from)) = (&mut out.true_depth, v.true_depth(i)) {
                to.extend_from_slice(&from[row..row + w as usize]);
            }
        }
    }
    Ok(out)
}

/// For each view, the indices of its `k` nearest other views by camera centre.
fn nearest(views: &RenderedViews, k: usize) -> Vec<Vec<usize>> {
    (0..views.len())
        .map(|i| {
            let p = views.views[i].camera.position;
            let mut others: Vec<usize> = (0..views.len()).filter(|&j| j != i).collect();
            others.sort_by(|&a, &b| {
                let da = views.views[a].camera.position.distance_squared(p);
                let db = views.views[b].camera.position.distance_squared(p);
                da.total_cmp(&db)
            });
            others.truncate(k.max(1));
            others
        })
        .collect()
}

/// Per-view data the steps reuse: content tensors and relu4_1 features.
struct ViewCache<'a> {
    views: &'a RenderedViews,
    cfg: &'a DecoderPretrainConfig,
    device: Device,
    content: HashMap<usize, (Tensor, Tensor)>,
}

impl ViewCache<'_> {
    /// View `i` as `[1, 3, H, W]` and its relu4_1.
    fn content(&mut self, net: &AdaInNet, i: usize) -> Result<(Tensor, Tensor)> {
        if let Some(c) = self.content.get(&i) {
            return Ok(c.clone());
        }
        let x = hwc_to_tensor(
            self.views.rgb(i),
            self.views.width as usize,
            self.views.height as usize,
            &self.device,
        )?;
        let f = net.encoder.relu4_1(&x)?;
        self.content.insert(i, (x.clone(), f.clone()));
        Ok((x, f))
    }

    fn depth(&self, i: usize) -> Vec<f32> {
        let min = self.cfg.min_opacity;
        self.views
            .depth(i)
            .iter()
            .zip(self.views.opacity(i))
            .map(|(&d, &o)| if o >= min { d } else { 0.0 })
            .collect()
    }

    /// The warp from window `wj` of view j into window `wi` of view i.
    fn warp(&self, (i, wi): (usize, Window), (j, wj): (usize, Window)) -> Result<Warp> {
        let width = self.views.width as usize;
        Warp::new(
            &wi.camera(&self.views.views[i].camera),
            &wi.crop_plane(&self.depth(i), width),
            &wj.camera(&self.views.views[j].camera),
            &wj.crop_plane(&self.depth(j), width),
            WarpConfig {
                rel_tolerance: self.cfg.warp.rel_tolerance,
            },
            &self.device,
        )
    }
}

/// Losses of stylizing window `wi` of view i and window `wj` (same size) of view j with one
/// style, as one batch. AdaIN uses the statistics of the whole views.
fn pair_losses(
    net: &AdaInNet,
    cache: &mut ViewCache,
    style: &StyleTarget,
    (i, wi): (usize, Window),
    (j, wj): (usize, Window),
) -> Result<(Tensor, Tensor, Tensor, Tensor)> {
    let (_, fi) = cache.content(net, i)?;
    let (_, fj) = cache.content(net, j)?;
    let t = adain(&Tensor::cat(&[&fi, &fj], 0)?, &style.stats[3], 1.0)?;
    let stride = VggArch::STRIDE;
    let target = Tensor::cat(
        &[
            wi.crop(&t.narrow(0, 0, 1)?, stride)?,
            wj.crop(&t.narrow(0, 1, 1)?, stride)?,
        ],
        0,
    )?;
    let out = net.decoder.forward(&target)?;
    let feats = net.encoder.features(&out)?;
    let content = crate::style2d::losses::content_loss(&feats[3], &target)?;
    let style_l = crate::style2d::losses::style_loss(&feats, &style.stats)?;
    let consistency = cache
        .warp((i, wi), (j, wj))?
        .consistency_loss(&out.get(0)?, &out.get(1)?)?;
    Ok((content, style_l, consistency, out))
}

/// What the stage reads.
#[derive(Debug, Clone, Copy)]
pub struct Inputs<'a> {
    /// The `render_views` output: RGB, z-depth, opacity and cameras.
    pub views: &'a RenderedViews,
    pub styles: &'a [StyleImage],
    pub encoder: &'a EncoderWeights,
    /// A decoder to start from (this project's safetensors or AdaIN's zip `decoder.pth`).
    pub init_decoder: Option<&'a Path>,
}

/// The decoder training starts from, and what it is (for the report): `init` when given, else
/// as `cfg.start` says.
fn starting_decoder(
    init: Option<&Path>,
    cfg: &DecoderPretrainConfig,
    encoder: &EncoderWeights,
    device: &Device,
) -> Result<(Decoder, String)> {
    if let Some(p) = init {
        return Ok((Decoder::load(p, device)?.0, p.display().to_string()));
    }
    if cfg.start == DecoderStart::Bundled {
        if let Some(dec) = Decoder::bundled_for(&encoder.source, device)? {
            return Ok((dec, BUNDLED_DECODER_NAME.to_string()));
        }
        tracing::warn!(
            encoder = %encoder.source,
            "the bundled decoder was trained for another encoder: starting from a fresh decoder"
        );
    }
    Ok((
        Decoder::new(encoder.arch, cfg.seed, device)?,
        "fresh".into(),
    ))
}

/// Trains the decoder and the VAE; writes the outputs into `out`. Resumes from `out/ckpt`.
pub fn run(
    inputs: Inputs,
    cfg: &DecoderPretrainConfig,
    out: &Path,
    control: &StageControl,
    device: &Device,
) -> Result<Outcome<DecoderPretrainReport>> {
    let Inputs {
        views,
        styles,
        encoder,
        init_decoder,
    } = inputs;
    if styles.is_empty() {
        return Err(EngineError::config(
            "styles",
            "at least one style image is needed",
        ));
    }
    if views.len() < 2 {
        return Err(EngineError::config(
            "views",
            "at least two rendered views are needed",
        ));
    }
    if !(0.0..=1.0).contains(&cfg.consistency_from) {
        return Err(EngineError::config(
            "decoder_pretrain.consistency_from",
            format!(
                "a fraction of the steps in [0, 1], got {}",
                cfg.consistency_from
            ),
        ));
    }
    if cfg.eval_stride == 0 {
        return Err(EngineError::config(
            "decoder_pretrain.eval_stride",
            "must be at least 1",
        ));
    }
    let views = crop_views(views)?;
    let (decoder, started_from) = starting_decoder(init_decoder, cfg, encoder, device)?;
    tracing::info!(start = %started_from, "decoder_pretrain: starting decoder");
    if decoder.arch() != encoder.arch {
        return Err(EngineError::config(
            "decoder",
            format!(
                "a {} decoder cannot decode a {} encoder",
                decoder.arch().name(),
                encoder.arch.name()
            ),
        ));
    }
    let net = AdaInNet {
        encoder: VggEncoder::new(encoder, device)?,
        decoder,
    };
    let style_tensors = styles
        .iter()
        .map(|s| crate::style2d::images::to_tensor(&s.image, cfg.style_size, device))
        .collect::<Result<Vec<_>>>()?;
    let targets = style_tensors
        .iter()
        .map(|t| Ok(net.style_target(t)?))
        .collect::<Result<Vec<_>>>()?;
    let pairs = nearest(&views, cfg.neighbours);
    let mut cache = ViewCache {
        views: &views,
        cfg,
        device: device.clone(),
        content: HashMap::new(),
    };
    let (width, height) = (views.width as usize, views.height as usize);

    let mut adam = Adam::new(net.decoder.vars(), AdamConfig::default())?;
    let mut training = Training::new(Stage::DecoderPretrain, out, cfg.steps, control);
    let mut state = TrainingState {
        rng: Rng::new(cfg.seed),
        config: cfg.clone(),
        loss_log: Vec::new(),
    };
    let switch = (cfg.steps as f64 * cfg.consistency_from).round() as u64;
    // The plain-AdaIN decoder, copied when L_co switches on (checkpointed from then on).
    let mut adain_weights: Option<HashMap<String, Tensor>> = None;
    if let Some(resumed) = training.resume::<TrainingState>(device)? {
        net.decoder
            .load_tensors(&resumed.tensors, &resumed.source)?;
        let saved: HashMap<String, Tensor> = resumed
            .tensors
            .iter()
            .filter_map(|(k, t)| Some((k.strip_prefix(ADAIN_PREFIX)?.to_string(), t.clone())))
            .collect();
        adain_weights = (!saved.is_empty()).then_some(saved);
        adam.load_state(&resumed.tensors, training.start())?;
        state = resumed.state;
    }
    for step in training.steps() {
        let rng = &mut state.rng;
        let consistency_on = step >= switch;
        if consistency_on && adain_weights.is_none() {
            adain_weights = Some(copy_weights(&net.decoder)?);
        }
        let consistency_weight = if consistency_on {
            cfg.consistency_weight
        } else {
            0.0
        };
        let s = rng.below(styles.len());
        let i = rng.below(views.len());
        let j = pairs[i][rng.below(pairs[i].len())];
        let wi = Window::random(width, height, cfg.patch, rng);
        let wj = wi.follow(
            &views.views[i].camera,
            &cache.depth(i),
            width,
            &views.views[j].camera,
        );
        let (lc, ls, lco, _) = pair_losses(&net, &mut cache, &targets[s], (i, wi), (j, wj))?;
        let total = ((&lc + (&ls * cfg.style_weight)?)? + (&lco * consistency_weight)?)?;
        adam.step(&total.backward()?, cfg.lr)?;
        let done = step + 1;
        let rec = LossRecord {
            step: done,
            content: lc.to_scalar()?,
            style: ls.to_scalar()?,
            consistency: lco.to_scalar()?,
        };
        state.loss_log.push(rec);
        let mut p = training.progress(done);
        p.loss = Some(total.to_scalar::<f32>()? as f64);
        p.metrics.insert("content".into(), rec.content as f64);
        p.metrics.insert("style".into(), rec.style as f64);
        p.metrics
            .insert("consistency".into(), rec.consistency as f64);
        control.report(&p);
        let stopped = training.after_step(done, || {
            let mut tensors = net.decoder.tensors();
            tensors.extend(adam.state());
            if let Some(w) = &adain_weights {
                tensors.extend(
                    w.iter()
                        .map(|(k, t)| (format!("{ADAIN_PREFIX}{k}"), t.clone())),
                );
            }
            Ok((tensors, &state))
        })?;
        if let Some(stopped) = stopped {
            return Ok(stopped);
        }
    }
    let TrainingState { loss_log, .. } = state;
    let train_seconds = training.seconds();
    std::fs::create_dir_all(out.join("sheets")).map_err(|e| EngineError::io(out, e))?;
    net.decoder
        .save(&out.join("decoder.safetensors"), net.encoder.source())?;
    let adain_decoder = Decoder::new(encoder.arch, cfg.seed, device)?;
    let adain_weights = match adain_weights {
        Some(w) => w,
        None => copy_weights(&net.decoder)?,
    };
    adain_decoder.load_tensors(&adain_weights, &out.join("ckpt"))?;
    adain_decoder.save(&out.join("adain_decoder.safetensors"), net.encoder.source())?;

    // Evaluation: every `eval_stride`-th view with its nearest neighbour, every style. Both
    // decoders' palettes are fitted to their outputs on the same views.
    let (mut co, mut st, mut n) = (0.0, 0.0, 0.0);
    let mut palettes = Vec::with_capacity(targets.len());
    for (k, target) in targets.iter().enumerate() {
        // Both decoders' outputs, measured one view at a time; the first three kept for the
        // sheet.
        let (mut moments, mut adain_moments, mut rows) = (Vec::new(), Vec::new(), Vec::new());
        for (i, nb) in pairs.iter().enumerate().step_by(cfg.eval_stride) {
            let full = Window::full(width, height);
            let (_, ls, lco, o) = pair_losses(&net, &mut cache, target, (i, full), (nb[0], full))?;
            co += lco.to_scalar::<f32>()? as f64;
            st += ls.to_scalar::<f32>()? as f64;
            n += 1.0;
            let output = o.get(0)?.detach();
            let (x, feat) = cache.content(&net, i)?;
            if cfg.palette {
                moments.extend(ColourMoments::of_image(&output)?);
                let t = adain(&feat, &target.stats[3], 1.0)?;
                adain_moments.extend(ColourMoments::of_image(&adain_decoder.forward(&t)?)?);
            }
            if rows.len() < 3 {
                rows.push((x, output));
            }
        }
        let fit = |moments: &[ColourMoments]| match cfg.palette {
            true => Palette::fit_moments(moments, &style_tensors[k]),
            false => Ok(Palette::IDENTITY),
        };
        let palette = fit(&moments)?;
        let rows = rows
            .into_iter()
            .map(|(x, o)| Ok((x, palette.apply(&o.unsqueeze(0)?)?.squeeze(0)?)))
            .collect::<Result<Vec<_>>>()?;
        contact_sheet(
            &out.join("sheets").join(format!("style-{k}.png")),
            &rows,
            &style_tensors[k],
        )?;
        palettes.push((palette, fit(&adain_moments)?));
    }

    // The style VAE on random crops of every style.
    let mut vae_rng = Rng::new(cfg.seed ^ 0x5eed_5eed);
    let vae = StyleVae::new(cfg.vae, cfg.seed, device)?;
    let crops = styles
        .iter()
        .map(|s| {
            crop_vectors(
                &net.encoder,
                &s.image,
                cfg.crops_per_style,
                cfg.crop,
                &mut vae_rng,
                device,
            )
        })
        .collect::<Result<Vec<_>>>()?;
    let vae_losses = vae.train(
        &Tensor::cat(&crops, 0)?,
        cfg.vae_steps,
        cfg.vae_lr,
        &mut vae_rng,
    )?;
    vae.save(&out.join("vae.safetensors"))?;
    let styles_file = StylesFile {
        feature: "relu4_1 channel mean (512) + std (512), unbiased variance + 1e-5; VAE input"
            .into(),
        crop: cfg.crop,
        styles: styles
            .iter()
            .zip(&crops)
            .zip(palettes)
            .map(|((s, c), (palette, adain_palette))| {
                Ok(StyleLatent {
                    name: s.name.clone(),
                    latent: vae.style_distribution(c)?,
                    palette,
                    adain_palette,
                })
            })
            .collect::<Result<_>>()?,
    };
    write_json_atomic(&out.join("styles.json"), &styles_file)?;
    let report = DecoderPretrainReport {
        started_from,
        steps: cfg.steps,
        resumed_from: training.start(),
        train_seconds,
        loss_log,
        consistency_mse: co / n,
        style_loss: st / n,
        vae_reconstruction: vae_losses.reconstruction,
    };
    let terms: [Term<LossRecord>; 3] = [
        ("content loss", |r| r.content),
        ("style loss", |r| r.style),
        ("consistency loss", |r| r.consistency),
    ];
    curves::save(out, &Series::terms(&report.loss_log, |r| r.step, &terms))?;
    write_json_atomic(&out.join("metrics.json"), &report)?;
    Ok(Outcome::Done(report))
}

/// Checkpoint tensor-name prefix of the plain-AdaIN decoder's weights.
const ADAIN_PREFIX: &str = "adain.";

/// A copy of the decoder's weights (a [`candle_core::Var`] is updated in place, so the
/// tensors must not share its storage).
fn copy_weights(decoder: &Decoder) -> Result<HashMap<String, Tensor>> {
    decoder
        .tensors()
        .into_iter()
        .map(|(k, t)| Ok((k, t.copy()?)))
        .collect()
}

/// Writes labelled rows of content | style | output (each `[1, 3, H, W]` / `[3, H, W]`), the
/// style resized to the row height.
fn contact_sheet(path: &Path, rows: &[(Tensor, Tensor)], style: &Tensor) -> Result<()> {
    let (_, _, h, w) = rows[0].0.dims4()?;
    let style = style.interpolate2d(h, w)?;
    let tile = |t: &Tensor| -> Result<image::RgbImage> {
        let (tw, th, rgb) = tensor_to_hwc(t)?;
        Ok(crate::image_io::to_rgb8(tw, th, &rgb))
    };
    let grid = rows
        .iter()
        .map(|(content, output)| [content, &style, output].into_iter().map(tile).collect())
        .collect::<Result<Vec<_>>>()?;
    let sheet = crate::sheet::labelled_grid(&["content", "style", "output"], &grid)?;
    crate::image_io::save_png(path, &sheet)
}
