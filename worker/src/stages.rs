//! Stage dispatch: one match arm and one small function per stage. Each function builds the
//! stage's configuration (preset + its overrides), downloads the inputs it needs, and runs the
//! engine's stage on a blocking thread with the task's output folder and [`StageControl`].
//!
//! Adding a stage: one arm in [`run_stage`] and one function here.
//!
//! [`StageControl`]: stylenerf_engine::stages::StageControl

use serde::Serialize;
use stylenerf_engine::camera::Camera;
use stylenerf_engine::field::saved;
use stylenerf_engine::image_io;
use stylenerf_engine::scene::Scene;
use stylenerf_engine::stages::camera_paths::{camera_path, PathKind};
use stylenerf_engine::stages::decoder_pretrain::{self, DecoderPretrainConfig, StyleImage};
use stylenerf_engine::stages::mutual_learning::{self, MutualConfig};
use stylenerf_engine::stages::nerf_pretrain::{self, NerfConfig};
use stylenerf_engine::stages::render_stylized::{self, RenderStylizedConfig};
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
        Stage::MutualLearning => mutual_learning(ctx).await,
        Stage::RenderStylized => render_stylized(ctx).await,
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
        let scene = Scene::load(&data, &cfg.load_options())?;
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
        let styles = load_styles(&style_paths)?;
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

async fn mutual_learning(ctx: &TaskContext) -> Result<Outcome<Metrics>, TaskError> {
    let cfg = ctx
        .config
        .stage_config("mutual_learning", MutualConfig::preset)?;
    let field_dir = ctx.upstream(Stage::NerfPretrain).await?;
    let views_dir = ctx.upstream(Stage::RenderViews).await?;
    let decoder_dir = ctx.upstream(Stage::DecoderPretrain).await?;
    let style_paths = ctx.styles().await?;
    let encoder_path = ctx.settings.encoder.clone();
    ctx.run_engine(move |control, device, out| {
        let views = RenderedViews::load(&views_dir)?;
        let styles = load_styles(&style_paths)?;
        let encoder = EncoderWeights::load_or_bundled(encoder_path.as_deref())?;
        let inputs = mutual_learning::Inputs {
            field_dir: &field_dir,
            views: &views,
            decoder_dir: &decoder_dir,
            styles: &styles,
            encoder: &encoder,
        };
        let outcome = mutual_learning::run(inputs, &cfg, out, control, device)?;
        Ok(map_done(outcome, |r| numeric_fields(&r)))
    })
    .await
}

async fn render_stylized(ctx: &TaskContext) -> Result<Outcome<Metrics>, TaskError> {
    let mut cfg = ctx
        .config
        .stage_config("render_stylized", RenderStylizedConfig::preset)?;
    let request = RenderRequest::parse(&ctx.config.raw)?;
    if let Some(spec) = &request.blend {
        cfg.styles = vec![spec.clone()];
    }
    if let Some(fps) = request.fps {
        cfg.frame_ms = (1000.0 / fps).round().max(1.0) as u32;
    }
    let field_dir = ctx.upstream(Stage::NerfPretrain).await?;
    let views_dir = ctx.upstream(Stage::RenderViews).await?;
    let decoder_dir = ctx.upstream(Stage::DecoderPretrain).await?;
    let mutual_dir = ctx.upstream(Stage::MutualLearning).await?;
    let style_paths = ctx.styles().await?;
    let encoder_path = ctx.settings.encoder.clone();
    ctx.run_engine(move |control, device, out| {
        let views = RenderedViews::load(&views_dir)?;
        let styles = load_styles(&style_paths)?;
        let encoder = EncoderWeights::load_or_bundled(encoder_path.as_deref())?;
        let path = request.cameras(&field_dir, device)?;
        let inputs = render_stylized::Inputs {
            field_dir: &field_dir,
            views: &views,
            decoder_dir: &decoder_dir,
            mutual_dir: &mutual_dir,
            styles: &styles,
            encoder: &encoder,
            path: path.as_deref(),
        };
        let outcome = render_stylized::run(inputs, &cfg, out, control, device)?;
        Ok(map_done(outcome, |r| {
            Metrics::from([
                ("specs".to_string(), r.specs.len() as f64),
                ("seconds".to_string(), r.seconds),
            ])
        }))
    })
    .await
}

/// The job's style images, named `style-<index>` (the names blends refer to).
fn load_styles(paths: &[std::path::PathBuf]) -> stylenerf_engine::Result<Vec<StyleImage>> {
    paths
        .iter()
        .enumerate()
        .map(|(i, path)| {
            Ok(StyleImage {
                name: format!("style-{i}"),
                image: image_io::load_rgb(path)?,
            })
        })
        .collect()
}

/// What a render request (`RenderJob`) adds to the task configuration.
#[derive(Debug, Clone, PartialEq, Default)]
struct RenderRequest {
    /// `style-0:0.3,style-1:0.7`.
    blend: Option<String>,
    /// `None`: `render_views`' path.
    kind: Option<PathKind>,
    num_frames: usize,
    fps: Option<f64>,
}

impl RenderRequest {
    fn parse(raw: &serde_json::Map<String, serde_json::Value>) -> Result<Self, TaskError> {
        let mut r = RenderRequest::default();
        if let Some(path) = raw.get("camera_path") {
            r.kind = match path["kind"].as_str().unwrap_or_default() {
                "" => None,
                kind => Some(kind.parse()?),
            };
            r.num_frames = path["num_frames"].as_u64().unwrap_or(0) as usize;
            r.fps = path["fps"].as_f64().filter(|f| *f > 0.0);
        }
        if let Some(serde_json::Value::Array(weights)) = raw.get("style_blend") {
            let parts: Vec<String> = weights
                .iter()
                .map(|w| {
                    format!(
                        "style-{}:{}",
                        w["style_index"].as_u64().unwrap_or(0),
                        w["weight"].as_f64().unwrap_or(0.0)
                    )
                })
                .collect();
            r.blend = Some(parts.join(","));
        }
        Ok(r)
    }

    /// The cameras of a requested path; `None` for the default (`render_views`' path).
    fn cameras(
        &self,
        field_dir: &std::path::Path,
        device: &candle_core::Device,
    ) -> stylenerf_engine::Result<Option<Vec<Camera>>> {
        if self.kind.is_none() && self.num_frames == 0 {
            return Ok(None);
        }
        let (_, meta) = saved::load(field_dir, device)?;
        let train = meta.train_cameras;
        let frames = if self.num_frames == 0 {
            60
        } else {
            self.num_frames
        };
        let kind = self.kind.unwrap_or(PathKind::Interpolate);
        Ok(Some(camera_path(
            kind,
            &train,
            frames,
            train.len().clamp(2, 8),
        )))
    }
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
