//! Error type of the engine: every user-facing failure names the file, the field and the reason.

use std::path::{Path, PathBuf};

/// Errors produced by the engine. Dataset and config errors carry enough context for a user to
/// fix their input without reading the source.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    /// A dataset file is missing, malformed or inconsistent.
    #[error("{}: field `{field}`: {reason}", file.display())]
    Dataset {
        file: PathBuf,
        field: String,
        reason: String,
    },
    /// A configuration value is out of range or contradicts another.
    #[error("config `{field}`: {reason}")]
    Config { field: String, reason: String },
    /// Reading or writing a file failed.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A checkpoint or artifact could not be read back.
    #[error("{}: {reason}", path.display())]
    Artifact { path: PathBuf, reason: String },
    /// An external program (COLMAP, ffmpeg) is missing or failed.
    #[error("{tool}: {reason}")]
    Tool { tool: String, reason: String },
    /// The stage was cancelled through its control handle.
    #[error("cancelled")]
    Cancelled,
    /// A tensor operation failed (a bug, or out of memory).
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

pub type Result<T, E = EngineError> = std::result::Result<T, E>;

impl EngineError {
    /// A dataset error about `field` in `file`.
    pub fn dataset(
        file: impl AsRef<Path>,
        field: impl Into<String>,
        reason: impl Into<String>,
    ) -> Self {
        Self::Dataset {
            file: file.as_ref().to_path_buf(),
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// A configuration error about `field`.
    pub fn config(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::Config {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// An I/O error on `path`.
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Self::Io {
            path: path.as_ref().to_path_buf(),
            source,
        }
    }

    /// An unreadable or inconsistent artifact at `path`.
    pub fn artifact(path: impl AsRef<Path>, reason: impl Into<String>) -> Self {
        Self::Artifact {
            path: path.as_ref().to_path_buf(),
            reason: reason.into(),
        }
    }
}

impl From<stylenerf_plan::SettingError> for EngineError {
    fn from(e: stylenerf_plan::SettingError) -> Self {
        Self::Config {
            field: e.field,
            reason: e.reason,
        }
    }
}
