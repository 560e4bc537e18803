//! `stylenerf run`: every stage locally in one process (no server), each with its own
//! progress bar, from a posed dataset (`--data`) or from plain photos or a video (`--photos`,
//! which adds the `poses` stage); and `stylenerf eval`: the consistency / style-fidelity
//! evaluation of a run.
//!
//! Each stage writes into `OUT/<stage>/`. A stage whose `metrics.json` exists is complete and
//! is skipped; an interrupted stage resumes from its checkpoint. Overrides name their stage:
//! `--set mutual_learning.steps=300`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;
use stylenerf_engine::device::parse_device;
use stylenerf_engine::stages::dispatch::{self, StageConfig, StageReport};
use stylenerf_engine::stages::render_stylized::markdown_table;
use stylenerf_engine::stages::Outcome;
use stylenerf_engine::style2d::images::StyleImage;
use stylenerf_engine::style2d::weights::EncoderWeights;
use stylenerf_plan::settings::parse_override;
use stylenerf_plan::{Override, Preset, Source, Stage};

use super::common::stage_progress;

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Dataset folder (nerfstudio, NeRF-synthetic/Blender or LLFF).
    #[arg(long, required_unless_present = "photos", conflicts_with = "photos")]
    data: Option<PathBuf>,
    /// A folder of plain photos or a video instead of a dataset: the run starts with the
    /// `poses` stage (COLMAP and, for a video, ffmpeg from the OS packages).
    #[arg(long)]
    photos: Option<PathBuf>,
    /// Style image (repeat for several), or `builtin:<name>` (mosaic, waves, dots).
    #[arg(long = "style", required = true)]
    styles: Vec<String>,
    /// Output folder: one sub-folder per stage.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    common: PipelineArgs,
    /// Style specs to render at the end (a style name or a blend `a:0.3,b:0.7`); default:
    /// every style.
    #[arg(long = "render")]
    render: Vec<String>,
    /// Stop after this stage (e.g. `decoder_pretrain` to compare 2D settings).
    #[arg(long)]
    until: Option<Stage>,
    /// A pretrained decoder to start decoder_pretrain from (this project's safetensors, or
    /// AdaIN's `decoder.pth` together with `--encoder vgg_normalised.pth`).
    #[arg(long)]
    decoder: Option<PathBuf>,
}

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Output folder of `stylenerf run`.
    #[arg(long)]
    run: PathBuf,
    /// The run's style images, in the same order.
    #[arg(long = "style", required = true)]
    styles: Vec<String>,
    /// Style specs to evaluate; default: every style.
    #[arg(long = "render")]
    render: Vec<String>,
    #[command(flatten)]
    common: PipelineArgs,
}

/// Options shared by `run` and `eval`.
#[derive(Debug, Args)]
struct PipelineArgs {
    /// Schedule and model size: tiny (tests), quick (CPU demo), standard, paper (GPU).
    #[arg(long, default_value = "quick")]
    preset: Preset,
    /// Override a stage's setting: `--set nerf_pretrain.steps=500`.
    #[arg(long = "set", value_name = "STAGE.KEY=VALUE")]
    overrides: Vec<String>,
    /// Compute device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// Encoder weights (any format `weights import` reads); default: the bundled VGG-16.
    #[arg(long)]
    encoder: Option<PathBuf>,
}

/// What every stage needs from the command line.
struct Pipeline {
    preset: Preset,
    overrides: Vec<Override>,
    device: candle_core::Device,
    styles: Vec<StyleImage>,
    encoder: EncoderWeights,
    /// The run's folder: `<stage>/` per stage.
    run: PathBuf,
    /// What the run starts from.
    source: Source,
}

impl Pipeline {
    fn new(
        args: &PipelineArgs,
        styles: &[String],
        run: &Path,
        source: Source,
    ) -> anyhow::Result<Self> {
        let overrides = args
            .overrides
            .iter()
            .map(|o| parse_override(o))
            .collect::<Result<Vec<_>, _>>()?;
        let styles = styles
            .iter()
            .map(|s| StyleImage::load(s).with_context(|| format!("--style {s}")))
            .collect::<anyhow::Result<Vec<_>>>()?;
        Ok(Self {
            preset: args.preset,
            overrides,
            device: parse_device(&args.device)?,
            styles,
            encoder: EncoderWeights::load_or_bundled(args.encoder.as_deref())?,
            run: run.to_path_buf(),
            source,
        })
    }

    /// The stage's configuration (`render` replaces render_stylized's style specs when given).
    fn config(&self, stage: Stage, render: &[String]) -> anyhow::Result<StageConfig> {
        let mut config = StageConfig::new(stage, self.preset, &self.overrides)?;
        if let StageConfig::RenderStylized(cfg) = &mut config {
            if !render.is_empty() {
                cfg.styles = render.to_vec();
            }
        }
        Ok(config)
    }

    /// Runs `stage` into `out`, reading the run's upstream folders.
    fn run_stage(
        &self,
        config: &StageConfig,
        scene: Option<&Path>,
        init_decoder: Option<&Path>,
        out: &Path,
    ) -> anyhow::Result<Outcome<StageReport>> {
        let stage = config.stage();
        let upstream: BTreeMap<Stage, PathBuf> = self
            .source
            .upstream(stage)
            .into_iter()
            .map(|of| (of, self.run.join(of.name())))
            .collect();
        let (dataset, photos) = match self.source {
            Source::Dataset => (scene, None),
            Source::Photos | Source::Video => (None, scene),
        };
        let inputs = dispatch::Inputs {
            dataset,
            photos,
            upstream: &upstream,
            styles: &self.styles,
            encoder: Some(&self.encoder),
            init_decoder,
            path: None,
        };
        let (bar, control) = stage_progress(stage.name());
        let outcome = dispatch::run(config, &inputs, out, &control, &self.device)
            .with_context(|| format!("stage {stage}"))?;
        bar.finish();
        if let (
            Outcome::Done(StageReport::RenderStylized(report)),
            StageConfig::RenderStylized(cfg),
        ) = (&outcome, config)
        {
            for spec in &report.specs {
                let dir = out.join(&spec.folder);
                println!(
                    "{}: {} frames in {}, animation {}, contact sheet {}",
                    spec.spec,
                    spec.frames,
                    dir.join("frames").display(),
                    dir.join("animation.gif").display(),
                    dir.join("sheet.png").display()
                );
            }
            if cfg.eval {
                println!("\n{}", markdown_table(report, cfg));
            }
        }
        Ok(outcome)
    }
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let (scene, source, flag) = match (&args.data, &args.photos) {
        (Some(data), _) => (data, Source::Dataset, "--data"),
        (None, Some(photos)) if photos.is_dir() => (photos, Source::Photos, "--photos"),
        (None, Some(video)) => (video, Source::Video, "--photos"),
        (None, None) => anyhow::bail!("give --data (a posed dataset) or --photos"),
    };
    let p = Pipeline::new(&args.common, &args.styles, &args.out, source)?;
    // Every configuration first, so a bad override fails before any training.
    let configs = source
        .stages()
        .into_iter()
        .map(|stage| p.config(stage, &args.render))
        .collect::<anyhow::Result<Vec<_>>>()?;
    for config in &configs {
        let stage = config.stage();
        let out = args.out.join(stage.name());
        if out.join("metrics.json").exists() {
            println!("{stage}: already complete in {}", out.display());
        } else {
            let reads = stage.inputs();
            let outcome = p
                .run_stage(config, Some(scene), args.decoder.as_deref(), &out)
                .with_context(|| match reads.dataset || reads.photos {
                    true => format!("{flag} {}", scene.display()),
                    false => format!("--out {}", args.out.display()),
                })?;
            if matches!(outcome, Outcome::Stopped { .. }) {
                return Ok(());
            }
        }
        if args.until == Some(stage) {
            return Ok(());
        }
    }
    Ok(())
}

pub fn eval(args: EvalArgs) -> anyhow::Result<()> {
    let p = Pipeline::new(&args.common, &args.styles, &args.run, Source::Dataset)?;
    let config = p.config(Stage::RenderStylized, &args.render)?;
    p.run_stage(&config, None, None, &args.run.join("eval"))?;
    Ok(())
}
