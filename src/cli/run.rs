//! `stylenerf run`: all five stages locally in one process (no server), each with its own
//! progress bar; and `stylenerf eval`: the consistency / style-fidelity evaluation of a run.
//!
//! Each stage writes into `OUT/<stage>/`. A stage whose `metrics.json` exists is complete and
//! is skipped; an interrupted stage resumes from its checkpoint. Overrides name their stage:
//! `--set mutual_learning.steps=300`.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;
use stylenerf_engine::preset::{parse_override, stage_overrides, Preset};
use stylenerf_engine::scene::Scene;
use stylenerf_engine::stages::render_stylized::{self, markdown_table, RenderStylizedConfig};
use stylenerf_engine::stages::{
    decoder_pretrain, mutual_learning, nerf_pretrain, render_views, Outcome, STAGES,
};
use stylenerf_engine::style2d::images::StyleImage;
use stylenerf_engine::style2d::weights::EncoderWeights;
use stylenerf_engine::views::RenderedViews;

use super::common::stage_progress;
use stylenerf_engine::device::parse_device;

#[derive(Debug, Args)]
pub struct RunArgs {
    /// Dataset folder (nerfstudio, NeRF-synthetic/Blender or LLFF).
    #[arg(long)]
    data: PathBuf,
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
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(STAGES))]
    until: Option<String>,
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
    overrides: Vec<(String, serde_json::Value)>,
    device: candle_core::Device,
    styles: Vec<StyleImage>,
    encoder: EncoderWeights,
    out: PathBuf,
    until: Option<String>,
}

impl Pipeline {
    fn new(
        args: &PipelineArgs,
        styles: &[String],
        out: &Path,
        until: Option<String>,
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
            out: out.to_path_buf(),
            until,
        })
    }

    fn dir(&self, stage: &str) -> PathBuf {
        self.out.join(stage)
    }

    /// The stage's configuration: its preset with the overrides addressed to it.
    fn config<T: serde::Serialize + serde::de::DeserializeOwned>(
        &self,
        stage: &str,
        preset: impl Fn(Preset) -> T,
    ) -> anyhow::Result<T> {
        Ok(stage_overrides(
            &preset(self.preset),
            stage,
            &self.overrides,
        )?)
    }

    /// Runs `f` unless the stage already finished; `false` when the pipeline should stop here
    /// (the stage stopped early, or it is the `--until` stage).
    fn stage<T>(
        &self,
        stage: &str,
        f: impl FnOnce(
            &Path,
            &stylenerf_engine::stages::StageControl,
        ) -> stylenerf_engine::Result<Outcome<T>>,
    ) -> anyhow::Result<bool> {
        let dir = self.dir(stage);
        let last = self.until.as_deref() == Some(stage);
        if dir.join("metrics.json").exists() {
            println!("{stage}: already complete in {}", dir.display());
            return Ok(!last);
        }
        let (bar, control) = stage_progress(stage);
        let outcome = f(&dir, &control).with_context(|| format!("stage {stage}"))?;
        bar.finish();
        Ok(matches!(outcome, Outcome::Done(_)) && !last)
    }

    fn render_stylized(&self, specs: &[String], out: &Path) -> anyhow::Result<()> {
        let cfg = RenderStylizedConfig {
            styles: specs.to_vec(),
            ..self.config("render_stylized", RenderStylizedConfig::preset)?
        };
        let views = RenderedViews::load(&self.dir("render_views"))?;
        let (bar, control) = stage_progress("render_stylized");
        let outcome = render_stylized::run(
            render_stylized::Inputs {
                field_dir: &self.dir("nerf_pretrain"),
                views: &views,
                decoder_dir: &self.dir("decoder_pretrain"),
                mutual_dir: &self.dir("mutual_learning"),
                styles: &self.styles,
                encoder: &self.encoder,
                path: None,
            },
            &cfg,
            out,
            &control,
            &self.device,
        )?;
        bar.finish();
        if let Outcome::Done(report) = outcome {
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
                println!("\n{}", markdown_table(&report, &cfg));
            }
        }
        Ok(())
    }
}

pub fn run(args: RunArgs) -> anyhow::Result<()> {
    let p = Pipeline::new(&args.common, &args.styles, &args.out, args.until.clone())?;
    let nerf = p.config("nerf_pretrain", nerf_pretrain::NerfConfig::preset)?;
    let scene = Scene::load(&args.data, &nerf.load_options())
        .with_context(|| format!("loading {}", args.data.display()))?;
    if !p.stage("nerf_pretrain", |out, c| {
        nerf_pretrain::run(&scene, &nerf, out, c, &p.device)
    })? {
        return Ok(());
    }
    let rv = p.config("render_views", render_views::RenderViewsConfig::preset)?;
    if !p.stage("render_views", |out, c| {
        render_views::run(&p.dir("nerf_pretrain"), &rv, out, c, &p.device)
    })? {
        return Ok(());
    }
    let views = RenderedViews::load(&p.dir("render_views"))?;
    let dp = p.config(
        "decoder_pretrain",
        decoder_pretrain::DecoderPretrainConfig::preset,
    )?;
    if !p.stage("decoder_pretrain", |out, c| {
        let inputs = decoder_pretrain::Inputs {
            views: &views,
            styles: &p.styles,
            encoder: &p.encoder,
            init_decoder: args.decoder.as_deref(),
        };
        decoder_pretrain::run(inputs, &dp, out, c, &p.device)
    })? {
        return Ok(());
    }
    let ml = p.config("mutual_learning", mutual_learning::MutualConfig::preset)?;
    if !p.stage("mutual_learning", |out, c| {
        let inputs = mutual_learning::Inputs {
            field_dir: &p.dir("nerf_pretrain"),
            views: &views,
            decoder_dir: &p.dir("decoder_pretrain"),
            styles: &p.styles,
            encoder: &p.encoder,
        };
        mutual_learning::run(inputs, &ml, out, c, &p.device)
    })? {
        return Ok(());
    }
    p.render_stylized(&args.render, &p.dir("render_stylized"))
}

pub fn eval(args: EvalArgs) -> anyhow::Result<()> {
    let p = Pipeline::new(&args.common, &args.styles, &args.run, None)?;
    p.render_stylized(&args.render, &args.run.join("eval"))
}
