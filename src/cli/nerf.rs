//! `stylenerf nerf …`: train a radiance field on a dataset and render its views (the first two
//! stages, run locally).

use std::path::PathBuf;

use anyhow::Context;
use clap::Subcommand;
use stylenerf_engine::scene::Scene;
use stylenerf_engine::stages::{nerf_pretrain, render_views, Outcome};
use stylenerf_plan::Stage;

use super::common::{stage_progress, TrainingArgs};

#[derive(Debug, Subcommand)]
pub enum NerfCommand {
    /// Train a radiance field on a dataset (nerf_pretrain); resumes from `OUT/ckpt` if present.
    Train {
        /// Dataset folder (nerfstudio, NeRF-synthetic/Blender or LLFF).
        #[arg(long)]
        data: PathBuf,
        /// Output folder for the field, metrics, test renders and checkpoints.
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        training: TrainingArgs,
    },
    /// Render RGB, depth and opacity at the training poses and along an interpolated path
    /// (render_views).
    Render {
        /// Folder written by `nerf train`.
        #[arg(long)]
        field: PathBuf,
        /// Output folder for the views.
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        training: TrainingArgs,
    },
}

pub fn run(cmd: NerfCommand) -> anyhow::Result<()> {
    match cmd {
        NerfCommand::Train {
            data,
            out,
            training,
        } => {
            let cfg = training.config(Stage::NerfPretrain, nerf_pretrain::NerfConfig::preset)?;
            let device = training.device()?;
            let scene = Scene::load(&data, &cfg.load_options())
                .with_context(|| format!("loading {}", data.display()))?;
            let (bar, control) = stage_progress("nerf_pretrain");
            let outcome = nerf_pretrain::run(&scene, &cfg, &out, &control, &device)?;
            bar.finish();
            if let Outcome::Done(report) = outcome {
                match report.test_psnr {
                    Some(p) => println!(
                        "test PSNR {p:.2} dB after {} steps ({:.0} s)",
                        report.steps, report.train_seconds
                    ),
                    None => println!(
                        "trained {} steps ({:.0} s); no test split",
                        report.steps, report.train_seconds
                    ),
                }
                if let Some(d) = report.depth_mae_relative {
                    println!("depth MAE {:.2}% of the scene extent", d * 100.0);
                }
                println!("field written to {}", out.display());
            }
            Ok(())
        }
        NerfCommand::Render {
            field,
            out,
            training,
        } => {
            let cfg =
                training.config(Stage::RenderViews, render_views::RenderViewsConfig::preset)?;
            let device = training.device()?;
            let (bar, control) = stage_progress("render_views");
            let outcome = render_views::run(&field, &cfg, &out, &control, &device)?;
            bar.finish();
            if let Outcome::Done(views) = outcome {
                println!("{} views written to {}", views.len(), out.display());
            }
            Ok(())
        }
    }
}
