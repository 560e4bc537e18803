//! Why a task failed, and whether running it again could help: user-data problems (a bad
//! dataset, an invalid override) are permanent; I/O, network and storage trouble is retryable.

use stylenerf_engine::EngineError;

/// A task failure to report with `FailTask`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{reason}")]
pub struct TaskError {
    /// Human-readable cause, naming the file, field or object concerned.
    pub reason: String,
    /// Whether another attempt (on this or another worker) may succeed.
    pub retryable: bool,
}

impl TaskError {
    /// A problem with the job's inputs or configuration: retrying cannot help.
    pub fn permanent(reason: impl Into<String>) -> Self {
        Self {
            reason: reason.into(),
            retryable: false,
        }
    }

    /// A transient problem (I/O, network, storage): another attempt may succeed.
    pub fn retryable(reason: impl Into<String>) -> Self {
        Self {
            reason: reason.into(),
            retryable: true,
        }
    }

    /// Prefixes the reason with what was being done, e.g. `downloading jobs/x/y`.
    pub fn context(self, what: impl std::fmt::Display) -> Self {
        Self {
            reason: format!("{what}: {}", self.reason),
            ..self
        }
    }
}

impl From<EngineError> for TaskError {
    fn from(e: EngineError) -> Self {
        match e {
            EngineError::Dataset { .. } | EngineError::Config { .. } => {
                Self::permanent(e.to_string())
            }
            _ => Self::retryable(e.to_string()),
        }
    }
}

impl From<tonic::Status> for TaskError {
    fn from(s: tonic::Status) -> Self {
        let reason = format!("coordinator: {:?}: {}", s.code(), s.message());
        match s.code() {
            tonic::Code::InvalidArgument | tonic::Code::PermissionDenied => Self::permanent(reason),
            _ => Self::retryable(reason),
        }
    }
}

impl From<std::io::Error> for TaskError {
    fn from(e: std::io::Error) -> Self {
        Self::retryable(e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn user_errors_are_permanent_and_io_is_retryable() {
        let e: TaskError = EngineError::dataset("/d/transforms.json", "frames", "empty").into();
        assert!(!e.retryable);
        assert!(e.reason.contains("transforms.json") && e.reason.contains("frames"));
        let e: TaskError = EngineError::config("steps", "must be positive").into();
        assert!(!e.retryable);
        let e: TaskError = EngineError::io("/x", std::io::Error::other("disk full")).into();
        assert!(e.retryable);
        let e: TaskError = tonic::Status::unavailable("down").into();
        assert!(e.retryable && e.reason.contains("down"));
        assert_eq!(
            TaskError::retryable("boom").context("uploading a").reason,
            "uploading a: boom"
        );
    }
}
