//! Stage 1, `nerf_pretrain`: fit the radiance field to the training photos, checkpointing as
//! it goes, then report test PSNR (and depth error when the dataset has ground truth) and
//! write the field artifact.
//!
//! Output folder: `field.safetensors` + `field.json` (see [`crate::field::saved`]),
//! `metrics.json`, `curves.png` (training loss and test PSNR, see [`crate::curves`]),
//! `test/<name>.png` (renders of the test views), `ckpt/` (checkpoints).

use std::path::Path;

use candle_core::Device;
use serde::{Deserialize, Serialize};

use crate::checkpoint::write_atomic;
use crate::curves::{self, Series};
use crate::depth_error::DepthErrors;
use crate::field::hash_grid::HashGridConfig;
use crate::field::radiance::{FieldConfig, RadianceField};
use crate::field::saved::{self, FieldMeta};
use crate::field::space::FieldSpace;
use crate::optim::{Adam, AdamConfig, LrSchedule};
use crate::per_view::per_view;
use crate::rays::{RayBatch, SamplingConfig};
use crate::render::depth_supervision::depth_supervision_loss;
use crate::render::distortion::distortion_loss;
use crate::render::{render_image, render_rays, step_size};
use crate::rng::Rng;
use crate::scene::{Background, LoadOptions, Scene};
use crate::stages::training::Training;
use crate::stages::{Outcome, Progress, StageControl};
use crate::{EngineError, Result};
use stylenerf_plan::{Preset, Stage};

/// Training configuration of the field.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NerfConfig {
    /// Working resolution: photos are shrunk so their longest side is at most this many
    /// pixels (`None`: full size). Every later stage renders at the size trained at.
    pub max_side: Option<u32>,
    pub field: FieldConfig,
    pub sampling: SamplingConfig,
    pub steps: u64,
    /// Rays in the first batch and the most rays per batch; the count then adapts so that
    /// each step evaluates about `samples_per_batch` samples (as in instant-ngp).
    pub rays_per_batch: usize,
    pub samples_per_batch: usize,
    pub lr: f64,
    pub lr_final_ratio: f64,
    pub warmup_steps: u64,
    /// Every cell counts as occupied until this step; then the occupancy grid is refreshed…
    pub occupancy_warmup: u64,
    /// …every this many steps…
    pub occupancy_every: u64,
    /// …sampling every cell until this step, then a quarter of the cells at random.
    pub occupancy_full_until: u64,
    /// A cell is occupied while one step through it would be at least this opaque.
    pub occupancy_alpha: f32,
    pub seed: u64,
    /// Rays per chunk when rendering whole images.
    pub render_chunk: usize,
    /// Weight of mip-NeRF 360's distortion loss (see [`crate::render::distortion`]): keeps each
    /// ray's weight in one short stretch instead of haze along it. Applied when the
    /// background is learned (a known colour already makes haze cost).
    pub distortion: f64,
    /// Weight of the binary entropy of each ray's opacity: pushes rays to be either opaque
    /// or empty, so a real background is left to the background model instead of haze, and a
    /// wall is not left partly to it. Applied when the background is learned.
    pub opacity_entropy: f64,
    /// Weight of DS-NeRF's depth-supervision loss (as depth-nerfacto uses it; see
    /// [`crate::render::depth_supervision`]): on each training ray whose pixel has a known
    /// depth `d` in its frame's depth map (a depth camera's, or sparse points from structure
    /// from motion; 0 = unknown), the cross-entropy between a narrow Gaussian around `d` and the
    /// ray's compositing weights, averaged over those rays. 0 (the default): the field learns
    /// from the photos alone and depth maps only grade it. Photos alone can leave a field in a
    /// wrong geometry it does not leave (a room around the cameras: BENCHMARKS.md, "The room,
    /// a fourth look"); 0.001 finds it and keeps a sky clear ("Depth supervision that leaves a
    /// sky empty").
    #[serde(default)]
    pub depth_weight: f64,
    /// Measure test PSNR every this many steps (0: only at the end); the time spent measuring
    /// is not counted as training time.
    pub eval_every: u64,
}

impl NerfConfig {
    /// How to load the scene for this configuration (its working resolution).
    pub fn load_options(&self) -> LoadOptions {
        LoadOptions {
            max_side: self.max_side,
            ..LoadOptions::default()
        }
    }

    pub fn preset(preset: Preset) -> Self {
        let grid = |levels, log2_table_size, base_resolution, max_resolution| HashGridConfig {
            levels,
            features_per_level: 2,
            log2_table_size,
            base_resolution,
            max_resolution,
        };
        let field = |grid, hidden, occupancy_resolution| FieldConfig {
            grid,
            density_hidden: hidden,
            geometry_features: 15,
            colour_hidden: hidden,
            occupancy_resolution,
            density_bias: -1.5,
        };
        let sampling = |steps_per_diagonal, max_samples_per_ray| SamplingConfig {
            steps_per_diagonal,
            max_samples_per_ray,
            early_stop_eps: 1e-4,
        };
        let base =
            |max_side, field, sampling, steps, rays_per_batch, samples_per_batch| NerfConfig {
                max_side: Some(max_side),
                field,
                sampling,
                steps,
                rays_per_batch,
                samples_per_batch,
                lr: 1e-2,
                lr_final_ratio: 0.05,
                warmup_steps: 20,
                occupancy_warmup: 32,
                occupancy_every: 16,
                occupancy_full_until: 256,
                occupancy_alpha: 0.01,
                seed: 0,
                render_chunk: 8192,
                // 0.002 left fox's wall a quarter transparent, painted by the background
                // model: "Opaque walls: the opacity entropy weight" in BENCHMARKS.md.
                opacity_entropy: 1e-2,
                distortion: 2e-3,
                depth_weight: 0.0,
                eval_every: 0,
            };
        match preset {
            Preset::Tiny => base(
                128,
                field(grid(8, 14, 4.0, 64.0), 32, 32),
                sampling(128, 128),
                150,
                1024,
                1 << 15,
            ),
            // 400 steps decaying to 0.05 of the learning rate stopped learning too early
            // (27.4 dB on the generated scene, the tuning scene; 30.1 dB when decaying to
            // 0.22): BENCHMARKS.md, "Learning-rate decay of the quick preset". A real capture
            // fills a 2^16-entry hash table with collisions (fox's validation split: 23.5 dB at
            // 2^16, 24.8 dB at 2^18, 24.4 dB at 2^19): "Hash table size of the quick preset".
            Preset::Quick => NerfConfig {
                lr_final_ratio: 0.22,
                ..base(
                    240,
                    field(grid(16, 18, 16.0, 512.0), 64, 64),
                    sampling(384, 512),
                    400,
                    8192,
                    1 << 17,
                )
            },
            Preset::Standard => base(
                480,
                field(grid(16, 19, 16.0, 1024.0), 64, 128),
                sampling(512, 1024),
                10_000,
                16384,
                1 << 18,
            ),
            Preset::Paper => base(
                1024,
                field(grid(16, 19, 16.0, 2048.0), 64, 128),
                sampling(1024, 1024),
                30_000,
                16384,
                1 << 18,
            ),
        }
    }
}

/// What `nerf_pretrain` measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NerfReport {
    pub steps: u64,
    pub resumed_from: u64,
    /// Mean PSNR over the test views (dB), `None` without a test split.
    pub test_psnr: Option<f64>,
    /// Mean absolute depth error on test pixels with opacity > 0.5 (world units), when the
    /// dataset has ground-truth depth.
    pub depth_mae: Option<f64>,
    /// `depth_mae` divided by the largest side of the content box.
    pub depth_mae_relative: Option<f64>,
    /// Median of |rendered − true| / true depth over the same pixels.
    pub depth_median_relative_error: Option<f64>,
    /// Mean rendered opacity of test pixels whose ground truth sees nothing (depth 0: a
    /// background at infinity); 0 is right, haze raises it.
    pub empty_opacity: Option<f64>,
    /// Mean rendered opacity over every test pixel. With a learned background, an indoor
    /// capture should be opaque everywhere: what is missing is painted by the background,
    /// which has no parallax.
    #[serde(default)]
    pub test_opacity: Option<f64>,
    /// Mean field samples per ray while training (after occupancy and early-stop pruning).
    #[serde(default)]
    pub samples_per_ray: f64,
    /// Fraction of occupancy cells occupied at the end.
    #[serde(default)]
    pub occupied_fraction: f64,
    /// Working resolution trained at (width, height of the first frame).
    #[serde(default)]
    pub resolution: (u32, u32),
    pub train_seconds: f64,
    /// Field samples evaluated with gradients per second of training.
    pub samples_per_second: f64,
    /// Training loss every 10 steps: (step, loss).
    pub loss_log: Vec<(u64, f32)>,
    /// Test PSNR during training (`eval_every`): (step, training seconds, PSNR).
    pub psnr_curve: Vec<(u64, f64, f64)>,
}

/// What a checkpoint holds besides the weights and the optimiser's moments.
#[derive(Serialize, Deserialize)]
struct TrainingState {
    rng: Rng,
    config: NerfConfig,
    loss_log: Vec<(u64, f32)>,
    psnr_curve: Vec<(u64, f64, f64)>,
    samples: u64,
    rays: u64,
    batch_rays: usize,
}

/// All training rays of the scene, their colours, and their known depths (0 = unknown) when a
/// training frame has a depth map.
fn training_rays(scene: &Scene) -> (RayBatch, Vec<f32>, Option<Vec<f32>>) {
    let mut rays = RayBatch {
        near: scene.near,
        far: scene.far,
        ..Default::default()
    };
    let mut colours = Vec::new();
    let mut depths = Vec::new();
    let has_depth = scene.train.iter().any(|&i| scene.frames[i].depth.is_some());
    for &i in &scene.train {
        let frame = &scene.frames[i];
        rays.extend(&RayBatch::for_camera(
            &frame.camera,
            scene.ndc.as_ref(),
            scene.near,
            scene.far,
        ));
        colours.extend_from_slice(frame.image.as_raw());
        if has_depth {
            let pixels = frame.image.as_raw().len() / 3;
            match &frame.depth {
                Some(d) => depths.extend_from_slice(d),
                None => depths.resize(depths.len() + pixels, 0.0),
            }
        }
    }
    (rays, colours, has_depth.then_some(depths))
}

/// Why `cfg` cannot train on `dataset` when none of its training frames has a depth map, if it
/// cannot: the stage's refusal at its start, and the coordinator's at submission.
pub fn without_depth(cfg: &NerfConfig, dataset: &str) -> Option<EngineError> {
    (cfg.depth_weight > 0.0).then(|| {
        EngineError::config(
            "nerf_pretrain.depth_weight",
            format!(
                "is {} but no training frame of {dataset} has a depth map \
                 (frames[].depth_file_path)",
                cfg.depth_weight
            ),
        )
    })
}

/// Mean binary entropy of opacities [R] (clamped away from 0 and 1, where it has no slope).
fn opacity_entropy(opacity: &candle_core::Tensor) -> Result<candle_core::Tensor> {
    let o = opacity.clamp(1e-4, 1.0 - 1e-4)?;
    let q = (1.0 - &o)?;
    let h = ((&o * o.log()?)? + (&q * q.log()?)?)?.neg()?;
    Ok(h.mean_all()?)
}

/// Next batch size: scale the ray count so the evaluated samples approach the target.
fn adapt_batch(rays: usize, samples: usize, cfg: &NerfConfig) -> usize {
    let scaled = rays as f64 * cfg.samples_per_batch as f64 / samples.max(1) as f64;
    // Move halfway (in log space) to damp the noise of one batch.
    let next = (rays as f64 * scaled).sqrt().round() as usize;
    next.clamp(256.min(cfg.rays_per_batch), cfg.rays_per_batch)
}

fn sigma_threshold(field: &RadianceField, rays: &RayBatch, cfg: &NerfConfig) -> f32 {
    -(1.0 - cfg.occupancy_alpha).ln() / step_size(field, rays, &cfg.sampling)
}

/// Trains the field on `scene` and writes the artifact into `out`. Resumes from the newest
/// checkpoint in `out/ckpt` when there is one.
pub fn run(
    scene: &Scene,
    cfg: &NerfConfig,
    out: &Path,
    control: &StageControl,
    device: &Device,
) -> Result<Outcome<NerfReport>> {
    if scene.train.is_empty() {
        return Err(EngineError::dataset(
            &scene.root,
            "train",
            "the training split is empty",
        ));
    }
    let (rays, colours, depths) = training_rays(scene);
    if depths.is_none() {
        if let Some(refusal) = without_depth(cfg, &scene.root.display().to_string()) {
            return Err(refusal);
        }
    }
    let depths = depths.filter(|_| cfg.depth_weight > 0.0);
    let mut rng = Rng::new(cfg.seed);
    let mut field = RadianceField::new(cfg.field, FieldSpace::for_scene(scene), &mut rng, device)?;
    let threshold = sigma_threshold(&field, &rays, cfg);
    let mut adam = Adam::new(
        field.vars(),
        AdamConfig {
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-15,
            weight_decay: 0.0,
        },
    )?;
    let schedule = LrSchedule {
        lr: cfg.lr,
        warmup_steps: cfg.warmup_steps,
        final_ratio: cfg.lr_final_ratio,
        total_steps: cfg.steps,
    };
    let mut training = Training::new(Stage::NerfPretrain, out, cfg.steps, control);
    let mut state = TrainingState {
        rng,
        config: cfg.clone(),
        loss_log: Vec::new(),
        psnr_curve: Vec::new(),
        samples: 0,
        rays: 0,
        batch_rays: cfg.rays_per_batch,
    };
    if let Some(resumed) = training.resume::<TrainingState>(device)? {
        field.load_tensors(&resumed.tensors, &resumed.source, threshold)?;
        adam.load_state(&resumed.tensors, training.start())?;
        state = resumed.state;
    }
    let learned = scene.background == Background::Learned;
    for step in training.steps() {
        let rng = &mut state.rng;
        if step >= cfg.occupancy_warmup && step % cfg.occupancy_every == 0 {
            let cells = if step < cfg.occupancy_full_until {
                usize::MAX
            } else {
                cfg.field.occupancy_resolution.pow(3) / 4
            };
            field.update_occupancy(rng, cells, threshold)?;
        }
        let idx: Vec<usize> = (0..state.batch_rays)
            .map(|_| rng.below(rays.len()))
            .collect();
        let batch = rays.select(&idx);
        let target: Vec<f32> = idx
            .iter()
            .flat_map(|&i| colours[3 * i..3 * i + 3].iter().copied())
            .collect();
        let target = candle_core::Tensor::from_vec(target, (idx.len(), 3), device)?;
        let out = render_rays(
            &field,
            &batch,
            &cfg.sampling,
            &|s| field.colour(s),
            Some(rng),
        )?;
        let mse = (out.rgb - target)?.sqr()?.mean_all()?;
        let mut loss = mse.clone();
        if learned && cfg.opacity_entropy > 0.0 {
            loss = (loss + (opacity_entropy(&out.opacity)? * cfg.opacity_entropy)?)?;
        }
        if let (true, Some((sigma, packed))) = (learned && cfg.distortion > 0.0, &out.samples) {
            loss = (loss + (distortion_loss(sigma, packed)? * cfg.distortion)?)?;
        }
        if let Some(depths) = &depths {
            let known: Vec<f32> = idx.iter().map(|&i| depths[i]).collect();
            let l = match &out.samples {
                Some((sigma, packed)) => depth_supervision_loss(sigma, packed, &known)?,
                None => None,
            };
            if let Some(l) = l {
                loss = (loss + (l * cfg.depth_weight)?)?;
            }
        }
        let grads = loss.backward()?;
        adam.step(&grads, schedule.at(step))?;
        state.samples += out.num_samples as u64;
        state.rays += idx.len() as u64;
        state.batch_rays = adapt_batch(state.batch_rays, out.num_samples, cfg);
        let done = step + 1;
        if cfg.eval_every > 0 && done % cfg.eval_every == 0 && done < cfg.steps {
            let seconds = training.seconds();
            let meta = field_meta(scene, cfg, threshold);
            let eval = training.untimed(|| evaluate(scene, &field, &meta, cfg, None))?;
            if let Some(psnr) = eval.psnr {
                tracing::info!(step = done, seconds, psnr, "nerf_pretrain: test PSNR");
                state.psnr_curve.push((done, seconds, psnr));
            }
        }
        if done % 10 == 0 || done == cfg.steps {
            let l = mse.to_scalar::<f32>()?;
            state.loss_log.push((done, l));
            let mut p = training.progress(done);
            p.loss = Some(l as f64);
            p.metrics.insert("psnr".into(), -10.0 * (l as f64).log10());
            p.metrics.insert("lr".into(), schedule.at(step));
            p.metrics.insert(
                "samples_per_ray".into(),
                out.num_samples as f64 / idx.len() as f64,
            );
            p.metrics.insert("rays".into(), idx.len() as f64);
            p.metrics.insert(
                "occupied".into(),
                field.occupancy.occupied_fraction() as f64,
            );
            control.report(&p);
        }
        let stopped = training.after_step(done, || {
            let mut tensors = field.tensors()?;
            tensors.extend(adam.state());
            Ok((tensors, &state))
        })?;
        if let Some(stopped) = stopped {
            return Ok(stopped);
        }
    }
    let TrainingState {
        samples: samples_total,
        rays: rays_total,
        loss_log,
        mut psnr_curve,
        ..
    } = state;
    let train_seconds = training.seconds();
    let meta = field_meta(scene, cfg, threshold);
    let eval = evaluate(scene, &field, &meta, cfg, Some(&out.join("test")))?;
    let (test_psnr, depth) = (eval.psnr, eval.depth_mae);
    if let Some(psnr) = test_psnr {
        psnr_curve.push((cfg.steps, train_seconds, psnr));
    }
    let extent = field.space.content_extent() as f64;
    let report = NerfReport {
        steps: cfg.steps,
        resumed_from: training.start(),
        test_psnr,
        depth_mae: depth,
        depth_mae_relative: depth.map(|d| d / extent),
        depth_median_relative_error: eval.depth_median_relative,
        empty_opacity: eval.empty_opacity,
        test_opacity: eval.opacity,
        samples_per_ray: samples_total as f64 / rays_total.max(1) as f64,
        occupied_fraction: field.occupancy.occupied_fraction() as f64,
        resolution: scene.resolution(),
        train_seconds,
        samples_per_second: samples_total as f64 / train_seconds.max(1e-9),
        loss_log,
        psnr_curve,
    };
    if let Some(depths) = train_depths(scene) {
        let (width, height) = scene.resolution();
        saved::save_train_depth(out, &depths, width, height)?;
    }
    saved::save(out, &field, &meta)?;
    let loss = report
        .loss_log
        .iter()
        .map(|&(s, l)| (s as f64, f64::from(l)));
    let psnr = report.psnr_curve.iter().map(|&(s, _, p)| (s as f64, p));
    curves::save(
        out,
        &[
            Series::new("training loss", loss),
            Series::new("test PSNR (dB)", psnr),
        ],
    )?;
    let json = serde_json::to_vec_pretty(&report)
        .map_err(|e| EngineError::artifact(out, e.to_string()))?;
    write_atomic(&out.join("metrics.json"), &json)?;
    control.report(&Progress {
        metrics: test_psnr
            .map(|p| ("test_psnr".to_string(), p))
            .into_iter()
            .collect(),
        ..training.progress(cfg.steps)
    });
    Ok(Outcome::Done(report))
}

/// The training frames' ground-truth depth maps, when every one has a map at the scene's
/// resolution (one stack of maps for the later stages' consistency with true geometry).
fn train_depths(scene: &Scene) -> Option<Vec<&[f32]>> {
    let (width, height) = scene.resolution();
    scene
        .train
        .iter()
        .map(|&i| {
            let frame = &scene.frames[i];
            let k = &frame.camera.intrinsics;
            let depth = frame.depth.as_deref()?;
            let fits =
                (k.width, k.height) == (width, height) && depth.len() == (width * height) as usize;
            fits.then_some(depth)
        })
        .collect()
}

fn field_meta(scene: &Scene, cfg: &NerfConfig, sigma_threshold: f32) -> FieldMeta {
    FieldMeta {
        config: cfg.field,
        sampling: cfg.sampling,
        space: FieldSpace::for_scene(scene),
        near: scene.near,
        far: scene.far,
        ndc: scene.ndc,
        sigma_threshold,
        train_cameras: scene
            .train
            .iter()
            .map(|&i| scene.frames[i].camera)
            .collect(),
        test_cameras: scene.test.iter().map(|&i| scene.frames[i].camera).collect(),
        steps: cfg.steps,
    }
}

/// What [`evaluate`] measures on the test views.
struct TestMetrics {
    psnr: Option<f64>,
    depth_mae: Option<f64>,
    depth_median_relative: Option<f64>,
    empty_opacity: Option<f64>,
    opacity: Option<f64>,
}

/// Renders the test views: mean PSNR and, with ground truth, depth errors and the opacity
/// where the truth sees nothing. With `images`, the renders are saved there as PNGs.
fn evaluate(
    scene: &Scene,
    field: &RadianceField,
    meta: &FieldMeta,
    cfg: &NerfConfig,
    images: Option<&Path>,
) -> Result<TestMetrics> {
    let rendered = per_view(
        scene.test.len(),
        field.device(),
        None,
        |t| {
            let frame = &scene.frames[scene.test[t]];
            let img = render_image(
                field,
                &meta.camera_rays(&frame.camera),
                &cfg.sampling,
                &|s| field.colour(s),
                cfg.render_chunk,
            )?;
            if let Some(dir) = images {
                let k = frame.camera.intrinsics;
                let name = Path::new(&frame.name)
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_else(|| format!("{:04}", scene.test[t]));
                crate::image_io::save_rgb_png(
                    &dir.join(format!("{name}.png")),
                    k.width,
                    k.height,
                    &img.rgb,
                )?;
                // Opacity as grey levels: haze in front of a real background shows at a glance.
                let grey: Vec<f32> = img.opacity.iter().flat_map(|&o| [o; 3]).collect();
                crate::image_io::save_rgb_png(
                    &dir.join(format!("{name}.opacity.png")),
                    k.width,
                    k.height,
                    &grey,
                )?;
            }
            Ok(img)
        },
        |_| {},
    )?;
    let mut psnrs = Vec::new();
    let mut depth = DepthErrors::default();
    let (mut opacity, mut pixels) = (0.0f64, 0usize);
    for (img, &i) in rendered.iter().zip(&scene.test) {
        let frame = &scene.frames[i];
        let mse = img
            .rgb
            .iter()
            .zip(frame.image.as_raw())
            .map(|(a, b)| ((a - b) as f64).powi(2))
            .sum::<f64>()
            / img.rgb.len() as f64;
        psnrs.push(-10.0 * mse.max(1e-12).log10());
        opacity += img.opacity.iter().map(|&o| o as f64).sum::<f64>();
        pixels += img.opacity.len();
        if let Some(truth) = &frame.depth {
            depth.add(&img.depth, &img.opacity, truth);
        }
    }
    let errors = depth.summary();
    Ok(TestMetrics {
        psnr: (!psnrs.is_empty()).then(|| psnrs.iter().sum::<f64>() / psnrs.len() as f64),
        depth_mae: errors.map(|e| e.mae),
        depth_median_relative: errors.map(|e| e.median_relative),
        empty_opacity: depth.empty_opacity(),
        opacity: (pixels > 0).then(|| opacity / pixels as f64),
    })
}
