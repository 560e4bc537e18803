//! A task's configuration (`TaskAssignment.config_json`): `{"stage", "preset", "overrides",
//! "num_styles", ...}`, and each stage's engine configuration built from it.
//!
//! Overrides are addressed by stage: the job's `overrides` object holds, per stage, the dotted
//! paths of that stage's settings, either flat or nested (both mean the same):
//!
//! ```json
//! {"nerf_pretrain.steps": 2000, "nerf_pretrain": {"field.grid.levels": 12},
//!  "decoder_pretrain": {"style_weight": 2.0}}
//! ```
//!
//! Nested objects are flattened to dotted paths, so every leaf value sets one setting. The first
//! path segment must be a stage name; a stage sees only its own overrides.

use serde_json::Value;
use stylenerf_engine::stages::dispatch::StageConfig;
use stylenerf_plan::settings::{addressed, flatten_overrides};
use stylenerf_plan::{Override, Preset, Stage};

use crate::error::TaskError;

/// The parsed `config_json` of a task.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskConfig {
    pub preset: Preset,
    /// Every override as (full dotted path, value), e.g. `("nerf_pretrain.steps", 2000)`.
    pub overrides: Vec<Override>,
    /// The whole document, for stage-specific keys (`camera_path`, `style_blend`, …).
    pub raw: serde_json::Map<String, Value>,
}

impl TaskConfig {
    /// Parses `config_json` (empty = `{}`, preset `quick`).
    pub fn parse(config_json: &str) -> Result<Self, TaskError> {
        let bad = |why: String| TaskError::permanent(format!("task config: {why}"));
        let raw = if config_json.trim().is_empty() {
            serde_json::Map::new()
        } else {
            match serde_json::from_str(config_json) {
                Ok(Value::Object(map)) => map,
                Ok(_) => return Err(bad("must be a JSON object".into())),
                Err(e) => return Err(bad(format!("not valid JSON: {e}"))),
            }
        };
        let preset = match raw.get("preset") {
            None | Some(Value::Null) => Preset::default(),
            Some(Value::String(s)) if s.is_empty() => Preset::default(),
            Some(Value::String(s)) => s.parse().map_err(|e| bad(format!("{e}")))?,
            Some(v) => return Err(bad(format!("`preset` must be a string, not {v}"))),
        };
        let overrides = match raw.get("overrides") {
            None | Some(Value::Null) => Vec::new(),
            Some(Value::Object(map)) => flatten_overrides(map),
            Some(v) => return Err(bad(format!("`overrides` must be an object, not {v}"))),
        };
        for (key, _) in &overrides {
            addressed(key).map_err(|e| bad(format!("override `{key}`: {}", e.reason)))?;
        }
        Ok(Self {
            preset,
            overrides,
            raw,
        })
    }

    /// `stage`'s configuration: its preset with its overrides applied, within its bounds.
    /// Errors name the full key.
    pub fn stage_config(&self, stage: Stage) -> Result<StageConfig, TaskError> {
        StageConfig::new(stage, self.preset, &self.overrides)
            .map_err(|e| TaskError::permanent(format!("overrides of {stage}: {e}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flat_and_nested_overrides_reach_their_stage() {
        let c = TaskConfig::parse(
            r#"{"stage": "nerf_pretrain", "preset": "tiny", "overrides": {
                "nerf_pretrain.steps": 7, "nerf_pretrain": {"field": {"grid.levels": 3}},
                "render_views": {"path_frames": 2}}}"#,
        )
        .unwrap();
        assert_eq!(c.preset, Preset::Tiny);
        let Ok(StageConfig::NerfPretrain(cfg)) = c.stage_config(Stage::NerfPretrain) else {
            panic!("a nerf_pretrain configuration");
        };
        assert_eq!((cfg.steps, cfg.field.grid.levels), (7, 3));
        let Ok(StageConfig::RenderViews(views)) = c.stage_config(Stage::RenderViews) else {
            panic!("a render_views configuration");
        };
        assert_eq!(views.path_frames, 2);
    }

    #[test]
    fn errors_name_the_key() {
        let err = TaskConfig::parse(r#"{"overrides": {"steps": 3}}"#).unwrap_err();
        assert!(
            !err.retryable && err.reason.contains("override `steps`"),
            "{err}"
        );
        let c = TaskConfig::parse(r#"{"overrides": {"nerf_pretrain.nope": 3}}"#).unwrap();
        let err = c.stage_config(Stage::NerfPretrain).unwrap_err();
        assert!(
            err.reason.contains("nope") && err.reason.contains("no such setting"),
            "{err}"
        );
        let err = TaskConfig::parse(r#"{"preset": "huge"}"#).unwrap_err();
        assert!(err.reason.contains("huge"), "{err}");
        assert_eq!(TaskConfig::parse("").unwrap().preset, Preset::Quick);
    }
}
