//! The coordinator's domain vocabulary: stages, job and task states as stored in SQLite (short
//! lower-case words) and their protocol enums, task progress as stored JSON, and the clock.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use stylenerf_proto::v1 as pb;

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

/// The stages of a job: the catalogue's.
pub use stylenerf_plan::Stage;

/// Converts a stored stage name to its protocol enum value (unknown → unspecified).
pub fn stage_pb(s: &str) -> i32 {
    Stage::parse(s).map_or(pb::Stage::Unspecified, pb::Stage::from) as i32
}

/// Job states as stored.
pub mod job_state {
    pub const QUEUED: &str = "queued";
    pub const RUNNING: &str = "running";
    pub const SUCCEEDED: &str = "succeeded";
    pub const FAILED: &str = "failed";
    pub const CANCELLED: &str = "cancelled";

    pub fn is_terminal(s: &str) -> bool {
        matches!(s, SUCCEEDED | FAILED | CANCELLED)
    }
}

/// Task states as stored.
pub mod task_state {
    pub const PENDING: &str = "pending";
    pub const READY: &str = "ready";
    pub const LEASED: &str = "leased";
    pub const SUCCEEDED: &str = "succeeded";
    pub const FAILED: &str = "failed";
    pub const CANCELLED: &str = "cancelled";
}

pub fn job_state_pb(s: &str) -> i32 {
    (match s {
        job_state::QUEUED => pb::JobState::Queued,
        job_state::RUNNING => pb::JobState::Running,
        job_state::SUCCEEDED => pb::JobState::Succeeded,
        job_state::FAILED => pb::JobState::Failed,
        job_state::CANCELLED => pb::JobState::Cancelled,
        _ => pb::JobState::Unspecified,
    }) as i32
}

pub fn job_state_from_pb(v: i32) -> Option<&'static str> {
    match pb::JobState::try_from(v).ok()? {
        pb::JobState::Queued => Some(job_state::QUEUED),
        pb::JobState::Running => Some(job_state::RUNNING),
        pb::JobState::Succeeded => Some(job_state::SUCCEEDED),
        pb::JobState::Failed => Some(job_state::FAILED),
        pb::JobState::Cancelled => Some(job_state::CANCELLED),
        pb::JobState::Unspecified => None,
    }
}

pub fn task_state_pb(s: &str) -> i32 {
    (match s {
        task_state::PENDING => pb::TaskState::Pending,
        task_state::READY => pb::TaskState::Ready,
        task_state::LEASED => pb::TaskState::Leased,
        task_state::SUCCEEDED => pb::TaskState::Succeeded,
        task_state::FAILED => pb::TaskState::Failed,
        task_state::CANCELLED => pb::TaskState::Cancelled,
        _ => pb::TaskState::Unspecified,
    }) as i32
}

/// Task progress as stored in `tasks.progress` and `events.progress`.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct StoredProgress {
    pub step: u64,
    pub total: u64,
    pub loss: f64,
    pub metrics: BTreeMap<String, f64>,
    pub eta_seconds: f64,
    pub message: String,
}

impl StoredProgress {
    pub fn from_pb(p: &pb::Progress) -> Self {
        StoredProgress {
            step: p.step,
            total: p.total,
            loss: finite(p.loss),
            metrics: p
                .metrics
                .iter()
                .map(|(k, v)| (k.clone(), finite(*v)))
                .collect(),
            eta_seconds: finite(p.eta_seconds),
            message: p.message.clone(),
        }
    }

    pub fn to_pb(&self) -> pb::Progress {
        pb::Progress {
            step: self.step,
            total: self.total,
            loss: self.loss,
            metrics: self.metrics.iter().map(|(k, v)| (k.clone(), *v)).collect(),
            eta_seconds: self.eta_seconds,
            message: self.message.clone(),
        }
    }

    pub fn parse(json: &str) -> Self {
        serde_json::from_str(json).unwrap_or_default()
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string(self).unwrap_or_else(|_| "{}".into())
    }
}

/// JSON has no NaN or infinity: store them as 0 (metrics come from workers, not trusted).
fn finite(v: f64) -> f64 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}
