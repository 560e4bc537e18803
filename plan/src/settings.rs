//! The override syntax: `key=value` pairs addressing any setting of a configuration by its
//! dotted JSON path (`steps=2000`, `field.grid.levels=12`), and a job's overrides, whose first
//! path segment names the stage they are for (`nerf_pretrain.steps=2000`), flat or nested
//! (`{"nerf_pretrain": {"field": {"grid.levels": 12}}}` means `nerf_pretrain.field.grid.levels`).
//!
//! [`configure`] is the one way a stage's configuration is built from its preset and a job's
//! overrides: it keeps the stage's own overrides, applies them with their types checked and
//! checks the result against the stage's [`bounds`](crate::bounds).

use serde::de::DeserializeOwned;
use serde::Serialize;
use serde_json::Value;

use crate::Stage;

/// One override: a dotted path and its value.
pub type Override = (String, Value);

/// A setting that cannot be applied: the setting (its dotted path) and why.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("config `{field}`: {reason}")]
pub struct SettingError {
    pub field: String,
    pub reason: String,
}

impl SettingError {
    pub fn new(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self {
            field: field.into(),
            reason: reason.into(),
        }
    }
}

/// Parses `key=value` (value as JSON, or as a plain string when it is not JSON).
pub fn parse_override(s: &str) -> Result<Override, SettingError> {
    let (key, value) = s
        .split_once('=')
        .ok_or_else(|| SettingError::new(s, "an override must look like key=value"))?;
    let value = serde_json::from_str(value).unwrap_or_else(|_| Value::String(value.to_string()));
    Ok((key.trim().to_string(), value))
}

/// Applies dotted-path overrides to a configuration. Unknown keys and values of the wrong type
/// are errors naming the key.
pub fn apply_overrides<T: Serialize + DeserializeOwned>(
    config: &T,
    overrides: &[Override],
) -> Result<T, SettingError> {
    let mut json =
        serde_json::to_value(config).map_err(|e| SettingError::new("config", e.to_string()))?;
    for (key, value) in overrides {
        let mut node = &mut json;
        for part in key.split('.') {
            node = node
                .as_object_mut()
                .and_then(|o| o.get_mut(part))
                .ok_or_else(|| SettingError::new(key, "no such setting"))?;
        }
        *node = value.clone();
        serde_json::from_value::<T>(json.clone())
            .map_err(|e| SettingError::new(key, format!("invalid value {value}: {e}")))?;
    }
    serde_json::from_value(json).map_err(|e| SettingError::new("config", e.to_string()))
}

/// A job's overrides object (flat, nested or both) as dotted keys and their values.
pub fn flatten_overrides(map: &serde_json::Map<String, Value>) -> Vec<Override> {
    fn walk(prefix: &str, map: &serde_json::Map<String, Value>, out: &mut Vec<Override>) {
        for (k, v) in map {
            let key = if prefix.is_empty() {
                k.clone()
            } else {
                format!("{prefix}.{k}")
            };
            match v {
                Value::Object(inner) => walk(&key, inner, out),
                leaf => out.push((key, leaf.clone())),
            }
        }
    }
    let mut out = Vec::new();
    walk("", map, &mut out);
    out
}

/// The stage a job override is for, and the path inside that stage's configuration; an error
/// when its first segment names no stage.
pub fn addressed(key: &str) -> Result<(Stage, &str), SettingError> {
    match key.split_once('.') {
        Some((stage, rest)) if !rest.is_empty() => {
            if let Some(stage) = Stage::parse(stage) {
                return Ok((stage, rest));
            }
        }
        _ => {}
    }
    Err(SettingError::new(
        key,
        format!(
            "an override must start with a stage name ({}), e.g. nerf_pretrain.steps=500",
            Stage::names().join(", ")
        ),
    ))
}

/// `stage`'s configuration: `config` (its preset) with the job overrides addressed to the stage
/// applied, within the stage's bounds. Errors name the full key (`nerf_pretrain.steps`); a key
/// naming no stage is an error for every stage.
pub fn configure<T: Serialize + DeserializeOwned>(
    config: &T,
    stage: Stage,
    overrides: &[Override],
) -> Result<T, SettingError> {
    let mut mine = Vec::new();
    for (key, value) in overrides {
        let (target, rest) = addressed(key)?;
        if target == stage {
            mine.push((rest.to_string(), value.clone()));
        }
    }
    let config = apply_overrides(config, &mine).map_err(|e| SettingError {
        field: format!("{stage}.{}", e.field),
        reason: e.reason,
    })?;
    crate::bounds::check(stage, &config)?;
    Ok(config)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

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

    const CFG: Cfg = Cfg {
        steps: 10,
        lr: 0.1,
        grid: Inner { levels: 4 },
    };

    #[test]
    fn a_stage_takes_its_own_overrides_and_refuses_keys_naming_no_stage() {
        let o = vec![
            parse_override("nerf_pretrain.steps=25").unwrap(),
            parse_override("mutual_learning.steps=7").unwrap(),
        ];
        assert_eq!(configure(&CFG, Stage::NerfPretrain, &o).unwrap().steps, 25);
        assert_eq!(configure(&CFG, Stage::RenderViews, &o).unwrap().steps, 10);
        for bad in ["steps=3", "render.steps=3", "nerf_pretrain.=3"] {
            let e = configure(&CFG, Stage::NerfPretrain, &[parse_override(bad).unwrap()])
                .unwrap_err()
                .to_string();
            assert!(e.contains("stage name"), "{bad}: {e}");
        }
        let wrong = vec![parse_override("nerf_pretrain.nope=3").unwrap()];
        let e = configure(&CFG, Stage::NerfPretrain, &wrong).unwrap_err();
        assert_eq!(e.field, "nerf_pretrain.nope");
        let far = vec![parse_override("nerf_pretrain.steps=1e12").unwrap()];
        let e = configure(&CFG, Stage::NerfPretrain, &far).unwrap_err();
        assert_eq!(e.field, "nerf_pretrain.steps", "{e}");
    }

    #[test]
    fn overrides_apply_and_errors_name_the_key() {
        let o = vec![
            parse_override("steps=25").unwrap(),
            parse_override("grid.levels=8").unwrap(),
        ];
        assert_eq!(
            apply_overrides(&CFG, &o).unwrap(),
            Cfg {
                steps: 25,
                lr: 0.1,
                grid: Inner { levels: 8 }
            }
        );
        let err = apply_overrides(&CFG, &[parse_override("grid.nope=1").unwrap()])
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("grid.nope") && err.contains("no such setting"),
            "{err}"
        );
        let err = apply_overrides(&CFG, &[parse_override("steps=fast").unwrap()])
            .unwrap_err()
            .to_string();
        assert!(err.contains("steps") && err.contains("invalid"), "{err}");
        assert!(parse_override("steps").is_err());
    }

    #[test]
    fn nested_and_flat_overrides_mean_the_same() {
        let nested: serde_json::Map<String, Value> = serde_json::from_str(
            r#"{"nerf_pretrain.steps": 7, "nerf_pretrain": {"field": {"grid.levels": 3}}}"#,
        )
        .unwrap();
        let mut flat = flatten_overrides(&nested);
        flat.sort_by(|a, b| a.0.cmp(&b.0));
        assert_eq!(
            flat,
            [
                (
                    "nerf_pretrain.field.grid.levels".to_string(),
                    Value::from(3)
                ),
                ("nerf_pretrain.steps".to_string(), Value::from(7)),
            ]
        );
    }
}
