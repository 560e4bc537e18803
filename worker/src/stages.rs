//! Running a task's stage: its configuration from the task's `config_json`, the inputs the
//! catalogue says it reads (the dataset, the styles, the output folders of its upstream
//! stages) downloaded, then the engine's one entry point
//! ([`stylenerf_engine::stages::dispatch::run`]) on a blocking thread with the task's output
//! folder and [`StageControl`]. Nothing here is written per stage.
//!
//! [`StageControl`]: stylenerf_engine::stages::StageControl

use std::collections::BTreeMap;

use stylenerf_engine::image_io;
use stylenerf_engine::stages::camera_paths::PathKind;
use stylenerf_engine::stages::dispatch::{self, PathRequest, StageConfig};
use stylenerf_engine::stages::Outcome;
use stylenerf_engine::style2d::images::StyleImage;
use stylenerf_engine::style2d::weights::EncoderWeights;
use stylenerf_plan::{Source, Stage};
use stylenerf_proto::v1 as pb;

use crate::context::{Metrics, TaskContext};
use crate::error::TaskError;

/// The snake_case name of a protocol stage value (`nerf_pretrain`, …; `unspecified` for none).
pub fn stage_name(stage: i32) -> &'static str {
    pb::Stage::of(stage).map_or("unspecified", Stage::name)
}

/// Runs the task's stage.
pub async fn run_stage(ctx: &TaskContext) -> Result<Outcome<Metrics>, TaskError> {
    let stage = pb::Stage::of(ctx.assignment.stage).ok_or_else(|| {
        TaskError::permanent(format!(
            "task {} has no (or an unknown) stage: {}",
            ctx.assignment.task_id, ctx.assignment.stage
        ))
    })?;
    let mut config = ctx.config.stage_config(stage)?;
    let request = RenderRequest::parse(&ctx.config.raw)?;
    if let StageConfig::RenderStylized(cfg) = &mut config {
        if let Some(spec) = &request.blend {
            cfg.styles = vec![spec.clone()];
        }
        if let Some(fps) = request.fps {
            cfg.frame_ms = (1000.0 / fps).round().max(1.0) as u32;
        }
    }
    let reads = stage.inputs();
    let source = Source::of_input_key(&ctx.assignment.dataset_key);
    let mut upstream = BTreeMap::new();
    for of in source.upstream(stage) {
        upstream.insert(of, ctx.upstream(of).await?);
    }
    // A job from photos reads its posed dataset from the poses stage's outputs.
    let dataset = match reads.dataset && source == Source::Dataset {
        true => Some(ctx.dataset().await?),
        false => None,
    };
    let photos = match reads.photos {
        true => Some(ctx.photos().await?),
        false => None,
    };
    let style_paths = match reads.styles {
        true => ctx.styles().await?,
        false => Vec::new(),
    };
    let encoder_path = ctx.settings.encoder.clone();
    ctx.run_engine(move |control, device, out| {
        let styles = load_styles(&style_paths)?;
        let encoder = match reads.encoder {
            true => Some(EncoderWeights::load_or_bundled(encoder_path.as_deref())?),
            false => None,
        };
        let inputs = dispatch::Inputs {
            dataset: dataset.as_deref(),
            photos: photos.as_deref(),
            upstream: &upstream,
            styles: &styles,
            encoder: encoder.as_ref(),
            init_decoder: None,
            path: request.path(),
        };
        Ok(dispatch::run(&config, &inputs, out, control, device)?.map(|r| r.metrics()))
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

    /// The requested camera path (60 interpolated frames unless it says); `None` for the
    /// default (`render_views`' path).
    fn path(&self) -> Option<PathRequest> {
        if self.kind.is_none() && self.num_frames == 0 {
            return None;
        }
        Some(PathRequest {
            kind: self.kind.unwrap_or(PathKind::Interpolate),
            frames: if self.num_frames == 0 {
                60
            } else {
                self.num_frames
            },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_render_requests() {
        assert_eq!(stage_name(pb::Stage::NerfPretrain as i32), "nerf_pretrain");
        assert_eq!(
            stage_name(pb::Stage::RenderStylized as i32),
            "render_stylized"
        );
        assert_eq!(stage_name(0), "unspecified");
        let raw = serde_json::json!({
            "camera_path": {"kind": "", "num_frames": 12, "fps": 24.0},
            "style_blend": [{"style_index": 0, "weight": 0.25}, {"style_index": 1, "weight": 0.75}]
        });
        let r = RenderRequest::parse(raw.as_object().unwrap()).unwrap();
        assert_eq!(r.blend.as_deref(), Some("style-0:0.25,style-1:0.75"));
        assert_eq!(
            r.path(),
            Some(PathRequest {
                kind: PathKind::Interpolate,
                frames: 12
            })
        );
        assert_eq!(RenderRequest::default().path(), None);
    }
}
