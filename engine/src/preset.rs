//! Presets shared by every stage (`tiny` for tests, `quick` for the CPU demo, `standard` for
//! quality, `paper` for the paper's schedule on a GPU) and `key=value` overrides of any
//! configuration field, addressed by its dotted JSON path (e.g. `steps=2000`,
//! `field.grid.levels=12`).

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

use crate::{EngineError, Result};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// Seconds: unit and end-to-end tests.
    Tiny,
    /// Minutes on a 2-core CPU: the demo.
    #[default]
    Quick,
    /// Better quality, longer schedules.
    Standard,
    /// The paper's schedule (meant for a GPU).
    Paper,
}

impl std::str::FromStr for Preset {
    type Err = EngineError;

    fn from_str(s: &str) -> Result<Self> {
        match s {
            "tiny" => Ok(Preset::Tiny),
            "quick" => Ok(Preset::Quick),
            "standard" => Ok(Preset::Standard),
            "paper" => Ok(Preset::Paper),
            _ => Err(EngineError::config(
                "preset",
                format!("unknown preset `{s}` (expected tiny, quick, standard or paper)"),
            )),
        }
    }
}

impl std::fmt::Display for Preset {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Preset::Tiny => "tiny",
            Preset::Quick => "quick",
            Preset::Standard => "standard",
            Preset::Paper => "paper",
        })
    }
}

/// Parses `key=value` (value as JSON, or as a plain string when it is not JSON).
pub fn parse_override(s: &str) -> Result<(String, serde_json::Value)> {
    let (key, value) = s
        .split_once('=')
        .ok_or_else(|| EngineError::config(s, "an override must look like key=value"))?;
    let value = serde_json::from_str(value)
        .unwrap_or_else(|_| serde_json::Value::String(value.to_string()));
    Ok((key.trim().to_string(), value))
}

/// Applies dotted-path overrides to a configuration. Unknown keys and values of the wrong type
/// are errors naming the key.
pub fn apply_overrides<T: Serialize + DeserializeOwned>(
    config: &T,
    overrides: &[(String, serde_json::Value)],
) -> Result<T> {
    let mut json =
        serde_json::to_value(config).map_err(|e| EngineError::config("config", e.to_string()))?;
    for (key, value) in overrides {
        let mut node = &mut json;
        for part in key.split('.') {
            node = node
                .as_object_mut()
                .and_then(|o| o.get_mut(part))
                .ok_or_else(|| EngineError::config(key, "no such setting"))?;
        }
        *node = value.clone();
        serde_json::from_value::<T>(json.clone())
            .map_err(|e| EngineError::config(key, format!("invalid value {value}: {e}")))?;
    }
    serde_json::from_value(json).map_err(|e| EngineError::config("config", e.to_string()))
}

/// A job's overrides object (`{"nerf_pretrain.steps": 2000, "nerf_pretrain": {"field":
/// {"grid.levels": 12}}}`: flat, nested or both) as dotted keys and their values.
pub fn flatten_overrides(
    map: &serde_json::Map<String, serde_json::Value>,
) -> Vec<(String, serde_json::Value)> {
    fn walk(
        prefix: &str,
        map: &serde_json::Map<String, serde_json::Value>,
        out: &mut Vec<(String, serde_json::Value)>,
    ) {
        for (k, v) in map {
            let key = if prefix.is_empty() {
                k.clone()
            } else {
                format!("{prefix}.{k}")
            };
            match v {
                serde_json::Value::Object(inner) => walk(&key, inner, out),
                leaf => out.push((key, leaf.clone())),
            }
        }
    }
    let mut out = Vec::new();
    walk("", map, &mut out);
    out
}

/// Applies the overrides addressed to `stage` (`<stage>.<key>=…`) to its configuration and
/// checks the result against the stage's bounds ([`crate::stages::limits`]); overrides of
/// other stages are left out. A key naming no stage is an error.
pub fn stage_overrides<T: Serialize + DeserializeOwned>(
    config: &T,
    stage: &str,
    overrides: &[(String, serde_json::Value)],
) -> Result<T> {
    let mut mine = Vec::new();
    for (key, value) in overrides {
        let (prefix, rest) = key.split_once('.').unwrap_or((key, ""));
        if !crate::stages::STAGES.contains(&prefix) || rest.is_empty() {
            return Err(EngineError::config(
                key,
                format!(
                    "an override must start with a stage name ({}), e.g. nerf_pretrain.steps=500",
                    crate::stages::STAGES.join(", ")
                ),
            ));
        }
        if prefix == stage {
            mine.push((rest.to_string(), value.clone()));
        }
    }
    let config = apply_overrides(config, &mine).map_err(|e| match e {
        EngineError::Config { field, reason } => EngineError::Config {
            field: format!("{stage}.{field}"),
            reason,
        },
        e => e,
    })?;
    crate::stages::limits::check(stage, &config)?;
    Ok(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Serialize, Deserialize, PartialEq)]
    struct Inner {
        levels: usize,
    }

    #[derive(Debug, Serialize, Deserialize, PartialEq)]
    struct Cfg {
        steps: u64,
        lr: f64,
        grid: Inner,
    }

    #[test]
    fn stage_overrides_pick_their_stage_and_reject_unknown_stages() {
        let c = Cfg {
            steps: 10,
            lr: 0.1,
            grid: Inner { levels: 4 },
        };
        let o = vec![
            parse_override("nerf_pretrain.steps=25").unwrap(),
            parse_override("mutual_learning.steps=7").unwrap(),
        ];
        assert_eq!(stage_overrides(&c, "nerf_pretrain", &o).unwrap().steps, 25);
        assert_eq!(stage_overrides(&c, "render_views", &o).unwrap().steps, 10);
        let bad = vec![parse_override("steps=3").unwrap()];
        let e = stage_overrides(&c, "nerf_pretrain", &bad)
            .unwrap_err()
            .to_string();
        assert!(e.contains("stage name"), "{e}");
        let wrong = vec![parse_override("nerf_pretrain.nope=3").unwrap()];
        let e = stage_overrides(&c, "nerf_pretrain", &wrong)
            .unwrap_err()
            .to_string();
        assert!(e.contains("nerf_pretrain.nope"), "{e}");
    }

    #[test]
    fn overrides_apply_and_errors_name_the_key() {
        let c = Cfg {
            steps: 10,
            lr: 0.1,
            grid: Inner { levels: 4 },
        };
        let o = vec![
            parse_override("steps=25").unwrap(),
            parse_override("grid.levels=8").unwrap(),
        ];
        assert_eq!(
            apply_overrides(&c, &o).unwrap(),
            Cfg {
                steps: 25,
                lr: 0.1,
                grid: Inner { levels: 8 }
            }
        );
        let err = apply_overrides(&c, &[parse_override("grid.nope=1").unwrap()])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("grid.nope") && err.contains("no such setting"),
            "{err}"
        );
        let err = apply_overrides(&c, &[parse_override("steps=fast").unwrap()])
            .unwrap_err()
            .to_string();
        assert!(err.contains("steps") && err.contains("invalid"), "{err}");
        assert!("huge".parse::<Preset>().is_err());
    }
}
