//! `ClientError`: every way a client call can fail, with messages meant for people. gRPC
//! statuses are mapped by code: UNAVAILABLE reads "cannot reach coordinator at X", a rejected
//! token says so, INVALID_ARGUMENT carries the `google.rpc.BadRequest` field violations the
//! coordinator attaches, and local file problems name the file.

use std::path::PathBuf;
use tonic::{Code, Status};
use tonic_types::StatusExt;

/// One invalid field of a request, as reported by the coordinator (`styles[1].upload_id`,
/// `header.sha256`, `camera_path.num_frames`, ...).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FieldViolation {
    pub field: String,
    pub description: String,
}

impl std::fmt::Display for FieldViolation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.field, self.description)
    }
}

/// Why a client call failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The endpoint string is not a usable URL.
    #[error("invalid coordinator endpoint {endpoint:?}: {reason}")]
    InvalidEndpoint { endpoint: String, reason: String },
    /// TLS could not be set up (CA file unreadable or not PEM).
    #[error("TLS setup for {endpoint} failed: {reason}")]
    Tls { endpoint: String, reason: String },
    /// No connection (refused, DNS, TLS handshake, timeout) or the coordinator is shutting
    /// down. Retrying later may succeed.
    #[error("cannot reach coordinator at {endpoint}: {reason}")]
    Unreachable { endpoint: String, reason: String },
    /// No token, a malformed one, or one the coordinator does not know.
    #[error(
        "the coordinator rejected the token ({message}); give a valid token with --token or \
         STYLENERF_TOKEN"
    )]
    Unauthenticated { message: String },
    /// The token is valid but its role may not make this call (e.g. a worker token).
    #[error("permission denied: {message}")]
    PermissionDenied { message: String },
    /// Unknown job (or another owner's), upload or artifact.
    #[error("{message}")]
    NotFound { message: String },
    /// The coordinator refused the request; `violations` names each offending field.
    #[error("invalid request: {}", describe_violations(message, violations))]
    InvalidArgument {
        message: String,
        violations: Vec<FieldViolation>,
    },
    /// The request does not fit the job's state (e.g. render before training finished).
    #[error("not possible now: {message}")]
    FailedPrecondition { message: String },
    /// Any other gRPC status.
    #[error("coordinator error ({code:?}): {message}")]
    Status { code: Code, message: String },
    /// A local input is unusable (missing scene file, not a file, ...), found before uploading.
    #[error("{0}")]
    InvalidInput(String),
    /// Reading or writing a local file failed.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The coordinator sent something inconsistent (short download, checksum mismatch, a key
    /// outside the job).
    #[error("unexpected reply from the coordinator: {0}")]
    Protocol(String),
}

fn describe_violations(message: &str, violations: &[FieldViolation]) -> String {
    if violations.is_empty() {
        message.to_string()
    } else {
        violations
            .iter()
            .map(ToString::to_string)
            .collect::<Vec<_>>()
            .join("; ")
    }
}

/// The error and its sources joined with `: ` (tonic's transport errors hide the cause, e.g.
/// "Connection refused", in their source chain).
pub(crate) fn error_chain(err: &(dyn std::error::Error + 'static)) -> String {
    let mut parts = vec![err.to_string()];
    let mut source = err.source();
    while let Some(cause) = source {
        let text = cause.to_string();
        if !parts.iter().any(|p| p.contains(&text)) {
            parts.push(text);
        }
        source = cause.source();
    }
    parts.join(": ")
}

impl From<stylenerf_proto::bearer::InvalidToken> for ClientError {
    fn from(e: stylenerf_proto::bearer::InvalidToken) -> Self {
        ClientError::Unauthenticated {
            message: e.to_string(),
        }
    }
}

impl ClientError {
    /// Maps a gRPC status from the coordinator at `endpoint`.
    pub fn from_status(status: Status, endpoint: &str) -> Self {
        let message = status.message().to_string();
        match status.code() {
            Code::Unavailable => {
                let reason = match std::error::Error::source(&status) {
                    Some(source) if message.is_empty() => error_chain(source),
                    Some(source) => format!("{message}: {}", error_chain(source)),
                    None => message,
                };
                ClientError::Unreachable {
                    endpoint: endpoint.to_string(),
                    reason,
                }
            }
            Code::Unauthenticated => ClientError::Unauthenticated { message },
            Code::PermissionDenied => ClientError::PermissionDenied { message },
            Code::NotFound => ClientError::NotFound { message },
            Code::InvalidArgument => {
                let violations = status
                    .get_details_bad_request()
                    .map(|bad| {
                        bad.field_violations
                            .into_iter()
                            .map(|v| FieldViolation {
                                field: v.field,
                                description: v.description,
                            })
                            .collect()
                    })
                    .unwrap_or_default();
                ClientError::InvalidArgument {
                    message,
                    violations,
                }
            }
            Code::FailedPrecondition => ClientError::FailedPrecondition { message },
            code => ClientError::Status { code, message },
        }
    }

    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        ClientError::Io {
            path: path.into(),
            source,
        }
    }

    /// The fields named by an INVALID_ARGUMENT error (empty for other errors).
    pub fn violations(&self) -> &[FieldViolation] {
        match self {
            ClientError::InvalidArgument { violations, .. } => violations,
            _ => &[],
        }
    }

    /// Whether retrying the same call later may succeed (connection problems, shutdown).
    pub fn is_retryable(&self) -> bool {
        matches!(
            self,
            ClientError::Unreachable { .. }
                | ClientError::Status {
                    code: Code::ResourceExhausted | Code::Aborted | Code::DeadlineExceeded,
                    ..
                }
        )
    }
}

/// Result of client calls.
pub type Result<T, E = ClientError> = std::result::Result<T, E>;
