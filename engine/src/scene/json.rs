//! Reading dataset JSON files: parsing with line/column errors, and typed field access whose
//! errors name the file and the full field path (e.g. `frames[3].transform_matrix`).
//!
//! Python's `json` module writes `NaN` and `Infinity` literals, which are not JSON. They are
//! turned into strings before parsing so that the field holding them is reported as
//! non-finite instead of the whole file failing with a syntax error.

use std::path::Path;

use glam::Vec3;
use serde_json::{Map, Value};

use crate::{EngineError, Result};

/// Reads and parses a JSON document.
pub(crate) fn parse(file: &Path) -> Result<Value> {
    let text = std::fs::read_to_string(file).map_err(|e| EngineError::io(file, e))?;
    serde_json::from_str(&quote_non_finite(&text)).map_err(|e| {
        EngineError::dataset(
            file,
            "(syntax)",
            format!(
                "invalid JSON at line {}, column {}: {}",
                e.line(),
                e.column(),
                strip_position(&e.to_string())
            ),
        )
    })
}

/// serde_json appends " at line L column C" to its messages; we report the position ourselves.
fn strip_position(msg: &str) -> &str {
    msg.find(" at line ").map_or(msg, |i| &msg[..i])
}

const NON_FINITE: [&str; 3] = ["-Infinity", "Infinity", "NaN"];

/// Wraps bare `NaN`, `Infinity` and `-Infinity` tokens (outside strings) in quotes.
fn quote_non_finite(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut in_string = false;
    let mut escaped = false;
    let mut rest = text;
    while let Some(c) = rest.chars().next() {
        if in_string {
            match (escaped, c) {
                (false, '\\') => escaped = true,
                (false, '"') => in_string = false,
                _ => escaped = false,
            }
        } else if c == '"' {
            in_string = true;
        } else if let Some(token) = NON_FINITE.iter().find(|t| rest.starts_with(**t)) {
            let boundary = out
                .chars()
                .next_back()
                .is_none_or(|p| !(p.is_alphanumeric() || p == '_' || p == '.'));
            if boundary {
                out.push('"');
                out.push_str(token);
                out.push('"');
                rest = &rest[token.len()..];
                continue;
            }
        }
        out.push(c);
        rest = &rest[c.len_utf8()..];
    }
    out
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// A finite number, or the reason the value is not one.
fn finite_f32(v: &Value) -> Result<f32, String> {
    match v {
        Value::Number(n) => {
            let x = n.as_f64().unwrap_or(f64::NAN) as f32;
            if x.is_finite() {
                Ok(x)
            } else {
                Err(format!("{n} is out of range"))
            }
        }
        Value::String(s) if NON_FINITE.contains(&s.as_str()) => {
            Err(format!("non-finite value {s}"))
        }
        other => Err(format!("expected a number, found {}", kind(other))),
    }
}

/// A JSON object inside a dataset file, with the path that leads to it.
#[derive(Clone, Copy)]
pub(crate) struct Obj<'a> {
    file: &'a Path,
    prefix: &'a str,
    map: &'a Map<String, Value>,
}

/// An owned field prefix for objects found inside arrays (`frames[3]`).
pub(crate) struct Element<'a> {
    file: &'a Path,
    prefix: String,
    map: &'a Map<String, Value>,
}

impl<'a> Element<'a> {
    pub fn obj(&self) -> Obj<'_> {
        Obj {
            file: self.file,
            prefix: &self.prefix,
            map: self.map,
        }
    }
}

impl<'a> Obj<'a> {
    /// The document's top-level object.
    pub fn root(file: &'a Path, doc: &'a Value) -> Result<Self> {
        match doc {
            Value::Object(map) => Ok(Self {
                file,
                prefix: "",
                map,
            }),
            other => Err(EngineError::dataset(
                file,
                "(document)",
                format!("expected a JSON object, found {}", kind(other)),
            )),
        }
    }

    pub fn file(&self) -> &'a Path {
        self.file
    }

    /// The full path of `key` in this object, for messages.
    pub fn field(&self, key: &str) -> String {
        if self.prefix.is_empty() {
            key.to_string()
        } else {
            format!("{}.{key}", self.prefix)
        }
    }

    /// A dataset error about `key` in this object.
    pub fn err(&self, key: &str, reason: impl Into<String>) -> EngineError {
        EngineError::dataset(self.file, self.field(key), reason)
    }

    fn get(&self, key: &str) -> Option<&'a Value> {
        self.map.get(key).filter(|v| !v.is_null())
    }

    fn required(&self, key: &str) -> Result<&'a Value> {
        self.get(key)
            .ok_or_else(|| self.err(key, "missing required field"))
    }

    pub fn has(&self, key: &str) -> bool {
        self.get(key).is_some()
    }

    pub fn opt_f32(&self, key: &str) -> Result<Option<f32>> {
        self.get(key)
            .map(|v| finite_f32(v).map_err(|r| self.err(key, r)))
            .transpose()
    }

    pub fn f32(&self, key: &str) -> Result<f32> {
        finite_f32(self.required(key)?).map_err(|r| self.err(key, r))
    }

    /// A positive integer (written as `800` or `800.0`).
    pub fn opt_dim(&self, key: &str) -> Result<Option<u32>> {
        let Some(x) = self.opt_f32(key)? else {
            return Ok(None);
        };
        let max = crate::scene::MAX_SIDE;
        if x >= 1.0 && x.fract() == 0.0 && x <= max as f32 {
            Ok(Some(x as u32))
        } else {
            Err(self.err(
                key,
                format!("expected a whole number of pixels from 1 to {max}, found {x}"),
            ))
        }
    }

    pub fn opt_str(&self, key: &str) -> Result<Option<&'a str>> {
        self.get(key)
            .map(|v| match v {
                Value::String(s) => Ok(s.as_str()),
                other => Err(self.err(key, format!("expected a string, found {}", kind(other)))),
            })
            .transpose()
    }

    pub fn str(&self, key: &str) -> Result<&'a str> {
        self.required(key)?;
        Ok(self.opt_str(key)?.unwrap_or_default())
    }

    /// A list of strings, e.g. `train_filenames`.
    pub fn opt_str_list(&self, key: &str) -> Result<Option<Vec<&'a str>>> {
        let Some(v) = self.get(key) else {
            return Ok(None);
        };
        let Value::Array(items) = v else {
            return Err(self.err(
                key,
                format!("expected a list of strings, found {}", kind(v)),
            ));
        };
        items
            .iter()
            .enumerate()
            .map(|(i, item)| match item {
                Value::String(s) => Ok(s.as_str()),
                other => Err(self.err(
                    &format!("{key}[{i}]"),
                    format!("expected a string, found {}", kind(other)),
                )),
            })
            .collect::<Result<Vec<_>>>()
            .map(Some)
    }

    /// A list of numbers of a given length, e.g. `background: [r, g, b]`.
    pub fn opt_numbers(&self, key: &str, len: usize) -> Result<Option<Vec<f32>>> {
        let Some(v) = self.get(key) else {
            return Ok(None);
        };
        let rows = numbers_2d(v).map_err(|r| self.err(key, r))?;
        match rows.as_slice() {
            [row] if row.len() == len => Ok(Some(row.clone())),
            _ => Err(self.err(key, format!("expected a list of {len} numbers"))),
        }
    }

    pub fn opt_vec3(&self, key: &str) -> Result<Option<Vec3>> {
        Ok(self
            .opt_numbers(key, 3)?
            .map(|v| Vec3::new(v[0], v[1], v[2])))
    }

    /// A matrix given as a list of rows of numbers; returns the rows.
    pub fn matrix(&self, key: &str) -> Result<Vec<Vec<f32>>> {
        numbers_2d(self.required(key)?).map_err(|r| self.err(key, r))
    }

    pub fn opt_matrix(&self, key: &str) -> Result<Option<Vec<Vec<f32>>>> {
        self.get(key)
            .map(|v| numbers_2d(v).map_err(|r| self.err(key, r)))
            .transpose()
    }

    /// The required, non-empty array of objects `key`, each with its own field prefix.
    pub fn objects(&self, key: &str) -> Result<Vec<Element<'a>>> {
        let v = self.required(key)?;
        let Value::Array(items) = v else {
            return Err(self.err(
                key,
                format!("expected a list of objects, found {}", kind(v)),
            ));
        };
        if items.is_empty() {
            return Err(self.err(key, "the list is empty"));
        }
        items
            .iter()
            .enumerate()
            .map(|(i, item)| {
                let field = self.field(&format!("{key}[{i}]"));
                match item {
                    Value::Object(map) => Ok(Element {
                        file: self.file,
                        prefix: field,
                        map,
                    }),
                    other => Err(EngineError::dataset(
                        self.file,
                        field,
                        format!("expected an object, found {}", kind(other)),
                    )),
                }
            })
            .collect()
    }
}

/// A number, a list of numbers (one row) or a list of lists of numbers, as rows.
fn numbers_2d(v: &Value) -> Result<Vec<Vec<f32>>, String> {
    let Value::Array(items) = v else {
        return Err(format!("expected a list, found {}", kind(v)));
    };
    if items.iter().all(|x| !x.is_array()) {
        return Ok(vec![items
            .iter()
            .map(finite_f32)
            .collect::<Result<_, _>>()?]);
    }
    items
        .iter()
        .enumerate()
        .map(|(r, row)| match row {
            Value::Array(cols) => cols
                .iter()
                .enumerate()
                .map(|(c, x)| finite_f32(x).map_err(|e| format!("row {r}, column {c}: {e}")))
                .collect(),
            other => Err(format!("row {r}: expected a list, found {}", kind(other))),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn non_finite_tokens_are_quoted_outside_strings_only() {
        let s = r#"{"a": NaN, "b": [-Infinity, Infinity], "c": "NaN \" NaN", "NaNx": 1}"#;
        let q = quote_non_finite(s);
        assert_eq!(
            q,
            r#"{"a": "NaN", "b": ["-Infinity", "Infinity"], "c": "NaN \" NaN", "NaNx": 1}"#
        );
    }

    #[test]
    fn fields_report_their_path() {
        let doc: Value =
            serde_json::from_str(r#"{"frames": [{"m": [[1, 2], [3, "NaN"]]}]}"#).unwrap();
        let file = Path::new("t.json");
        let root = Obj::root(file, &doc).unwrap();
        let frames = root.objects("frames").unwrap();
        let err = frames[0].obj().matrix("m").unwrap_err().to_string();
        assert!(
            err.contains("frames[0].m") && err.contains("non-finite"),
            "{err}"
        );
    }
}
