//! Bounds on every stage setting, so that an override (from the CLI or from a job's
//! `config_overrides_json`) cannot make a stage allocate without limit, run for ever or
//! overflow: the settings that size memory or time have explicit ranges, every other integer
//! is at most [`DEFAULT_MAX_INT`] (seeds excepted), and every float is finite. The coordinator
//! checks a job's overrides with [`check_job_overrides`] at submission, and every stage
//! configuration built by [`crate::preset::stage_overrides`] is checked with [`check`], so a worker
//! refuses what the coordinator would have.

use serde_json::Value;

use crate::preset::{flatten_overrides, stage_overrides, Preset};
use crate::stages::{
    decoder_pretrain::DecoderPretrainConfig, mutual_learning::MutualConfig,
    nerf_pretrain::NerfConfig, render_stylized::RenderStylizedConfig,
    render_views::RenderViewsConfig, STAGES,
};
use crate::{EngineError, Result};

/// Largest value of an integer setting without its own range.
pub const DEFAULT_MAX_INT: f64 = 1_000_000.0;

/// Most hash-grid parameters (levels × table entries × features): 2²⁶ floats are 256 MiB,
/// about 1 GiB with the optimiser's moments.
pub const MAX_GRID_PARAMETERS: u64 = 1 << 26;

/// `(dotted path inside the stage's configuration, least, greatest)`.
type Range = (&'static str, f64, f64);

const NERF_PRETRAIN: &[Range] = &[
    ("max_side", 8.0, 16384.0),
    ("steps", 1.0, 1e6),
    ("rays_per_batch", 1.0, 262_144.0),
    ("samples_per_batch", 1.0, 4_194_304.0),
    ("render_chunk", 1.0, 1_048_576.0),
    ("lr", 1e-8, 10.0),
    ("lr_final_ratio", 0.0, 1.0),
    ("occupancy_every", 1.0, 1e6),
    ("occupancy_alpha", 0.0, 1.0),
    ("distortion", 0.0, 1e3),
    ("opacity_entropy", 0.0, 1e3),
    ("field.grid.levels", 1.0, 32.0),
    ("field.grid.features_per_level", 1.0, 8.0),
    ("field.grid.log2_table_size", 8.0, 24.0),
    ("field.grid.base_resolution", 1.0, 4096.0),
    ("field.grid.max_resolution", 1.0, 1_048_576.0),
    ("field.density_hidden", 1.0, 1024.0),
    ("field.geometry_features", 1.0, 256.0),
    ("field.colour_hidden", 1.0, 1024.0),
    ("field.occupancy_resolution", 8.0, 256.0),
    ("sampling.steps_per_diagonal", 1.0, 8192.0),
    ("sampling.max_samples_per_ray", 1.0, 4096.0),
    ("sampling.early_stop_eps", 0.0, 1.0),
];

const RENDER_VIEWS: &[Range] = &[
    ("path_frames", 0.0, 3600.0),
    ("path_keyframes", 0.0, 3600.0),
    ("chunk", 1.0, 1_048_576.0),
];

const DECODER_PRETRAIN: &[Range] = &[
    ("steps", 0.0, 1e6),
    ("patch", 8.0, 1024.0),
    ("lr", 0.0, 10.0),
    ("style_size", 16.0, 4096.0),
    ("eval_stride", 1.0, 1e6),
    ("neighbours", 0.0, 64.0),
    ("min_opacity", 0.0, 1.0),
    ("vae_steps", 0.0, 1e6),
    ("crops_per_style", 0.0, 100_000.0),
];

const MUTUAL_LEARNING: &[Range] = &[
    ("steps", 0.0, 1e6),
    ("patch", 8.0, 1024.0),
    ("lr", 0.0, 10.0),
    ("decoder_lr", 0.0, 10.0),
    ("decoder_freeze", 0.0, 1.0),
    ("style_size", 16.0, 4096.0),
];

const RENDER_STYLIZED: &[Range] = &[
    ("short_gap", 1.0, 10_000.0),
    ("long_gap", 1.0, 10_000.0),
    ("min_opacity", 0.0, 1.0),
    ("sheet_rows", 1.0, 100.0),
    ("frame_ms", 1.0, 60_000.0),
    ("style_size", 16.0, 4096.0),
    ("fidelity_stride", 1.0, 1e6),
];

fn ranges(stage: &str) -> &'static [Range] {
    match stage {
        "nerf_pretrain" => NERF_PRETRAIN,
        "render_views" => RENDER_VIEWS,
        "decoder_pretrain" => DECODER_PRETRAIN,
        "mutual_learning" => MUTUAL_LEARNING,
        "render_stylized" => RENDER_STYLIZED,
        _ => &[],
    }
}

/// Checks the configuration of `stage` against the bounds; errors name the setting as
/// `<stage>.<path>`.
pub fn check<T: serde::Serialize>(stage: &str, config: &T) -> Result<()> {
    let json =
        serde_json::to_value(config).map_err(|e| EngineError::config(stage, e.to_string()))?;
    check_json(stage, &json)
}

fn check_json(stage: &str, config: &Value) -> Result<()> {
    let mut problems = Vec::new();
    check_leaves(stage, ranges(stage), "", config, &mut problems);
    if stage == "nerf_pretrain" {
        let grid = |key: &str| config["field"]["grid"][key].as_f64().unwrap_or(0.0);
        let entries = 2f64.powf(grid("log2_table_size").min(64.0));
        let parameters = grid("levels") * entries * grid("features_per_level");
        if parameters > MAX_GRID_PARAMETERS as f64 {
            problems.push((
                format!("{stage}.field.grid"),
                format!(
                    "levels × 2^log2_table_size × features_per_level is {parameters:.0}, more \
                     than the limit of {MAX_GRID_PARAMETERS}"
                ),
            ));
        }
    }
    match problems.into_iter().next() {
        None => Ok(()),
        Some((field, reason)) => Err(EngineError::config(field, reason)),
    }
}

fn check_leaves(
    stage: &str,
    ranges: &[Range],
    path: &str,
    value: &Value,
    problems: &mut Vec<(String, String)>,
) {
    match value {
        Value::Object(map) => {
            for (key, child) in map {
                let child_path = if path.is_empty() {
                    key.clone()
                } else {
                    format!("{path}.{key}")
                };
                check_leaves(stage, ranges, &child_path, child, problems);
            }
        }
        Value::Array(items) => {
            for (i, item) in items.iter().enumerate() {
                check_leaves(stage, ranges, &format!("{path}[{i}]"), item, problems);
            }
        }
        Value::Number(number) => {
            let name = path.rsplit('.').next().unwrap_or(path);
            let x = number.as_f64().unwrap_or(f64::NAN);
            let range = ranges.iter().find(|(p, _, _)| *p == path);
            let why = match range {
                _ if name == "seed" => None,
                Some((_, lo, hi)) if !(x >= *lo && x <= *hi) => {
                    Some(format!("{number} is outside [{lo}, {hi}]"))
                }
                Some(_) => None,
                None if !x.is_finite() => Some(format!("{number} is not finite")),
                None if (number.is_u64() || number.is_i64()) && x.abs() > DEFAULT_MAX_INT => Some(
                    format!("{number} is more than the limit of {DEFAULT_MAX_INT}"),
                ),
                None => None,
            };
            if let Some(why) = why {
                problems.push((format!("{stage}.{path}"), why));
            }
        }
        _ => {}
    }
}

/// Checks a job's overrides for `preset` as every stage will apply them: keys name a stage and
/// one of its settings, values have the setting's type and lie within its bounds. Returns
/// every problem as `(key, reason)`.
pub fn check_job_overrides(
    preset: &str,
    overrides: &serde_json::Map<String, Value>,
) -> Vec<(String, String)> {
    let preset: Preset = match preset.parse() {
        Ok(preset) => preset,
        Err(e) => return vec![("preset".into(), e.to_string())],
    };
    let overrides = &flatten_overrides(overrides);
    let mut problems: Vec<(String, String)> = Vec::new();
    for stage in STAGES {
        let checked = match stage {
            "nerf_pretrain" => {
                stage_overrides(&NerfConfig::preset(preset), stage, overrides).map(drop)
            }
            "render_views" => {
                stage_overrides(&RenderViewsConfig::preset(preset), stage, overrides).map(drop)
            }
            "decoder_pretrain" => {
                stage_overrides(&DecoderPretrainConfig::preset(preset), stage, overrides).map(drop)
            }
            "mutual_learning" => {
                stage_overrides(&MutualConfig::preset(preset), stage, overrides).map(drop)
            }
            "render_stylized" => {
                stage_overrides(&RenderStylizedConfig::preset(preset), stage, overrides).map(drop)
            }
            other => Err(EngineError::config(
                other,
                "a stage without a configuration",
            )),
        };
        let problem = match checked {
            Ok(()) => continue,
            Err(EngineError::Config { field, reason }) => (field, reason),
            Err(e) => ("config_overrides_json".into(), e.to_string()),
        };
        // A key that names no stage is refused by every stage: report it once.
        if !problems.contains(&problem) {
            problems.push(problem);
        }
    }
    problems
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::preset::parse_override;

    fn check(preset: &str, overrides: &[&str]) -> Vec<(String, String)> {
        let parsed = overrides
            .iter()
            .map(|o| parse_override(o).unwrap())
            .collect();
        check_job_overrides(preset, &parsed)
    }

    #[test]
    fn every_preset_is_within_bounds() {
        for preset in ["tiny", "quick", "standard", "paper"] {
            assert_eq!(check(preset, &[]), [], "{preset}");
        }
    }

    #[test]
    fn overrides_that_would_exhaust_a_worker_are_refused_naming_the_key() {
        for (overrides, key) in [
            (
                vec!["nerf_pretrain.rays_per_batch=1000000000000"],
                "nerf_pretrain.rays_per_batch",
            ),
            (
                vec!["nerf_pretrain.field.grid.levels=1000000"],
                "nerf_pretrain.field.grid.levels",
            ),
            (
                vec!["nerf_pretrain.field.grid.log2_table_size=60"],
                "nerf_pretrain.field.grid.log2_table_size",
            ),
            (
                vec![
                    "nerf_pretrain.field.grid.log2_table_size=24",
                    "nerf_pretrain.field.grid.levels=32",
                ],
                "nerf_pretrain.field.grid",
            ),
            (
                vec!["nerf_pretrain.steps=1000000000000"],
                "nerf_pretrain.steps",
            ),
            (vec!["mutual_learning.steps=-3"], "mutual_learning.steps"),
            (vec!["decoder_pretrain.lr=1e400"], "decoder_pretrain.lr"),
            (vec!["render_views.chunk=0"], "render_views.chunk"),
            (vec!["nerf_pretrain.nope=1"], "nerf_pretrain.nope"),
            (vec!["steps=3"], "steps"),
        ] {
            let problems = check("quick", &overrides);
            assert!(
                problems.iter().any(|(k, _)| k == key),
                "{overrides:?}: {problems:?}"
            );
        }
        assert_eq!(
            check(
                "quick",
                &["nerf_pretrain.steps=50", "nerf_pretrain.seed=123456789012"]
            ),
            []
        );
        assert_eq!(check("huge", &[])[0].0, "preset");
    }
}
