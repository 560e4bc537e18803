//! gRPC status helpers: INVALID_ARGUMENT with `google.rpc.BadRequest` field violations, and
//! conversion of internal failures (database, storage) to INTERNAL with a log line.

use tonic::{Code, Status};
use tonic_types::{ErrorDetails, StatusExt};

/// One invalid field and what is wrong with it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Violation {
    pub field: String,
    pub description: String,
}

impl Violation {
    pub fn new(field: impl Into<String>, description: impl Into<String>) -> Self {
        Violation {
            field: field.into(),
            description: description.into(),
        }
    }
}

impl std::fmt::Display for Violation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.field, self.description)
    }
}

impl From<Violation> for Status {
    fn from(v: Violation) -> Status {
        invalid_all(vec![v])
    }
}

/// INVALID_ARGUMENT naming one field.
pub fn invalid(field: impl Into<String>, description: impl Into<String>) -> Status {
    Violation::new(field, description).into()
}

/// INVALID_ARGUMENT listing every violation (in the message and as BadRequest details).
pub fn invalid_all(violations: Vec<Violation>) -> Status {
    let message = violations
        .iter()
        .map(ToString::to_string)
        .collect::<Vec<_>>()
        .join("; ");
    let mut details = ErrorDetails::new();
    for v in &violations {
        details.add_bad_request_violation(v.field.clone(), v.description.clone());
    }
    Status::with_error_details(Code::InvalidArgument, message, details)
}

/// INTERNAL for an unexpected failure; the cause is logged and included in the message.
pub fn internal(err: impl std::fmt::Display) -> Status {
    tracing::error!(error = %err, "internal error");
    Status::internal(format!("internal error: {err}"))
}

/// NOT_FOUND for a job the caller cannot see (whether or not it exists).
pub fn job_not_found(job_id: &str) -> Status {
    Status::not_found(format!("job {job_id:?} not found"))
}
