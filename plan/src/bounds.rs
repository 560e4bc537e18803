//! Bounds on every stage setting, so that an override (from the CLI or from a job) cannot make
//! a stage allocate without limit, run for ever or overflow: the settings that size memory or
//! time have explicit ranges, every other integer is at most [`DEFAULT_MAX_INT`] (seeds
//! excepted), and every float is finite. [`crate::settings::configure`] checks every stage
//! configuration it builds, so the coordinator refuses at submission what a worker would.

use serde_json::Value;

use crate::{SettingError, Stage};

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
    ("depth_weight", 0.0, 1e3),
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

const POSES: &[Range] = &[
    ("max_side", 16.0, 16384.0),
    ("feature_max_side", 64.0, 16384.0),
    ("max_features", 64.0, 65536.0),
    ("video.fps", 0.01, 120.0),
    ("video.max_frames", 3.0, 2000.0),
    ("video.max_side", 64.0, 16384.0),
    ("min_registered", 0.0, 1.0),
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
    ("style_module.hidden", 1.0, 1024.0),
    ("style_module.hidden_layers", 1.0, 16.0),
    // 2^k π in f32 (and the encoding's resolution) ends long before 2^24.
    ("style_module.frequencies", 0.0, 16.0),
    ("style_module.background_frequencies", 0.0, 16.0),
];

const RENDER_STYLIZED: &[Range] = &[
    ("short_gap", 1.0, 10_000.0),
    ("long_gap", 1.0, 10_000.0),
    ("min_opacity", 0.0, 1.0),
    ("sheet_rows", 1.0, 100.0),
    ("frame_ms", 1.0, 60_000.0),
    ("style_size", 16.0, 4096.0),
    ("fidelity_stride", 1.0, 1e6),
    ("truth_views", 0.0, 10_000.0),
];

fn ranges(stage: Stage) -> &'static [Range] {
    match stage {
        Stage::Poses => POSES,
        Stage::NerfPretrain => NERF_PRETRAIN,
        Stage::RenderViews => RENDER_VIEWS,
        Stage::DecoderPretrain => DECODER_PRETRAIN,
        Stage::MutualLearning => MUTUAL_LEARNING,
        Stage::RenderStylized => RENDER_STYLIZED,
    }
}

/// Checks the configuration of `stage` against the bounds; errors name the setting as
/// `<stage>.<path>`.
pub fn check<T: serde::Serialize>(stage: Stage, config: &T) -> Result<(), SettingError> {
    let json =
        serde_json::to_value(config).map_err(|e| SettingError::new(stage.name(), e.to_string()))?;
    check_json(stage, &json)
}

fn check_json(stage: Stage, config: &Value) -> Result<(), SettingError> {
    let mut problems = Vec::new();
    check_leaves(stage, ranges(stage), "", config, &mut problems);
    if stage == Stage::NerfPretrain {
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
        Some((field, reason)) => Err(SettingError { field, reason }),
    }
}

fn check_leaves(
    stage: Stage,
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

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn problem(stage: Stage, config: Value) -> Option<String> {
        check(stage, &config).err().map(|e| e.field)
    }

    #[test]
    fn ranges_defaults_and_the_grid_budget() {
        let ok = json!({"steps": 10, "seed": 123_456_789_012u64, "lr": 0.01});
        assert_eq!(problem(Stage::NerfPretrain, ok), None);
        assert_eq!(
            problem(Stage::NerfPretrain, json!({"steps": 0})).as_deref(),
            Some("nerf_pretrain.steps")
        );
        // An integer without its own range is bounded by the default; a float must be finite
        // (JSON has no infinity, so serde writes it as null: nothing to check).
        assert_eq!(
            problem(Stage::RenderViews, json!({"other": 2_000_000})).as_deref(),
            Some("render_views.other")
        );
        assert_eq!(
            problem(Stage::RenderViews, json!({"list": [1, 2_000_000]})).as_deref(),
            Some("render_views.list[1]")
        );
        let grid = |log2: u32, levels: u32| {
            json!({"field": {"grid": {"levels": levels, "log2_table_size": log2,
                                      "features_per_level": 2}}})
        };
        // An octave count whose 2^k would overflow is refused, not left to the worker.
        let octaves = json!({"style_module": {"frequencies": 40}});
        assert_eq!(
            problem(Stage::MutualLearning, octaves).as_deref(),
            Some("mutual_learning.style_module.frequencies")
        );
        assert_eq!(problem(Stage::NerfPretrain, grid(19, 16)), None);
        assert_eq!(
            problem(Stage::NerfPretrain, grid(24, 32)).as_deref(),
            Some("nerf_pretrain.field.grid")
        );
    }
}
