//! Stage dispatch: one match arm and one small function per stage. Each function builds the
//! stage's configuration (preset + its overrides), downloads the inputs it needs, and runs the
//! engine's stage on a blocking thread with the task's output folder and [`StageControl`].
//!
//! Adding a stage: one arm in [`run_stage`] and one function here.
//!
//! [`StageControl`]: stylenerf_engine::stages::StageControl

use serde::Serialize;
use stylenerf_engine::image_io;
use stylenerf_engine::scene::{LoadOptions, Scene};
use stylenerf_engine::stages::decoder_pretrain::{self, DecoderPretrainConfig, StyleImage};
use stylenerf_engine::stages::nerf_pretrain::{self, NerfConfig};
use stylenerf_engine::stages::render_views::{self, RenderViewsConfig};
use stylenerf_engine::stages::Outcome;
use stylenerf_engine::style2d::weights::EncoderWeights;
use stylenerf_engine::views::RenderedViews;
use stylenerf_proto::v1::Stage;

use crate::error::TaskError;
use crate::task::{Metrics, TaskContext};
use crate::task_config::STAGE_NAMES;

/// The snake_case name of a stage (`nerf_pretrain`, …; `unspecified` for none).
pub fn stage_name(stage: Stage) -> &'static str {
    match stage {
        Stage::Unspecified => "unspecified",
        s => STAGE_NAMES[s as usize - 1],
    }
}

/// Runs the task's stage.
pub async fn run_stage(ctx: &TaskContext) -> Result<Outcome<Metrics>, TaskError> {
    match Stage::try_from(ctx.assignment.stage).unwrap_or(Stage::Unspecified) {
        Stage::NerfPretrain => nerf_pretrain(ctx).await,
        Stage::RenderViews => render_views(ctx).await,
        Stage::DecoderPretrain => decoder_pretrain(ctx).await,
        stage @ (Stage::MutualLearning | Stage::RenderStylized) => {
            Err(TaskError::permanent(format!(
                "stage {} is not available in this worker build",
                stage_name(stage)
            )))
        }
        Stage::Unspecified => Err(TaskError::permanent(format!(
            "task {} has no (or an unknown) stage: {}",
            ctx.assignment.task_id, ctx.assignment.stage
        ))),
    }
}

async fn nerf_pretrain(ctx: &TaskContext) -> Result<Outcome<Metrics>, TaskError> {
    let cfg = ctx
        .config
        .stage_config("nerf_pretrain", NerfConfig::preset)?;
    let data = ctx.dataset().await?;
    ctx.run_engine(move |control, device, out| {
        let scene = Scene::load(&data, &LoadOptions::default())?;
        let outcome = nerf_pretrain::run(&scene, &cfg, out, control, device)?;
        Ok(map_done(outcome, |r| numeric_fields(&r)))
    })
    .await
}

async fn render_views(ctx: &TaskContext) -> Result<Outcome<Metrics>, TaskError> {
    let cfg = ctx
        .config
        .stage_config("render_views", RenderViewsConfig::preset)?;
    let field = ctx.upstream(Stage::NerfPretrain).await?;
    ctx.run_engine(move |control, device, out| {
        let outcome = render_views::run(&field, &cfg, out, control, device)?;
        Ok(map_done(outcome, |views| {
            Metrics::from([("views".to_string(), views.len() as f64)])
        }))
    })
    .await
}

async fn decoder_pretrain(ctx: &TaskContext) -> Result<Outcome<Metrics>, TaskError> {
    let cfg = ctx
        .config
        .stage_config("decoder_pretrain", DecoderPretrainConfig::preset)?;
    let views_dir = ctx.upstream(Stage::RenderViews).await?;
    let style_paths = ctx.styles().await?;
    let encoder_path = ctx.settings.encoder.clone();
    ctx.run_engine(move |control, device, out| {
        let views = RenderedViews::load(&views_dir)?;
        let styles = style_paths
            .iter()
            .enumerate()
            .map(|(i, path)| {
                Ok(StyleImage {
                    name: format!("style-{i}"),
                    image: image_io::load_rgb(path)?,
                })
            })
            .collect::<stylenerf_engine::Result<Vec<_>>>()?;
        let encoder = EncoderWeights::load_or_bundled(encoder_path.as_deref())?;
        let inputs = decoder_pretrain::Inputs {
            views: &views,
            styles: &styles,
            encoder: &encoder,
            init_decoder: None,
        };
        let outcome = decoder_pretrain::run(inputs, &cfg, out, control, device)?;
        Ok(map_done(outcome, |r| numeric_fields(&r)))
    })
    .await
}

fn map_done<R>(outcome: Outcome<R>, f: impl FnOnce(R) -> Metrics) -> Outcome<Metrics> {
    match outcome {
        Outcome::Done(r) => Outcome::Done(f(r)),
        Outcome::Stopped { step } => Outcome::Stopped { step },
    }
}

/// The top-level numeric fields of a stage report (PSNR, seconds, losses…) as metrics.
fn numeric_fields(report: &impl Serialize) -> Metrics {
    match serde_json::to_value(report) {
        Ok(serde_json::Value::Object(map)) => map
            .into_iter()
            .filter_map(|(k, v)| v.as_f64().map(|v| (k, v)))
            .collect(),
        _ => Metrics::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_metrics() {
        assert_eq!(stage_name(Stage::NerfPretrain), "nerf_pretrain");
        assert_eq!(stage_name(Stage::RenderStylized), "render_stylized");
        #[derive(Serialize)]
        struct R {
            psnr: f64,
            steps: u64,
            log: Vec<f64>,
            none: Option<f64>,
        }
        let m = numeric_fields(&R {
            psnr: 30.5,
            steps: 10,
            log: vec![1.0],
            none: None,
        });
        assert_eq!(m.len(), 2);
        assert_eq!(m["psnr"], 30.5);
    }
}
