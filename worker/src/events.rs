//! What a worker reports to whoever embeds it: [`WorkerEvent`]s (a task started, a task
//! ended) and [`TaskResult`], how a task ended.

use stylenerf_proto::v1 as pb;

use crate::context::Metrics;

/// What a worker did, for logs, tests and embedding programs.
#[derive(Debug, Clone, PartialEq)]
pub enum WorkerEvent {
    /// A task's inputs and checkpoint are in place and its stage starts.
    TaskStarted {
        task_id: u64,
        job_id: String,
        stage: pb::Stage,
        attempt: u32,
        /// Checkpoint step the stage resumes from (0 = fresh start).
        resumed_from: u64,
    },
    /// A task ended.
    TaskFinished {
        task_id: u64,
        job_id: String,
        stage: pb::Stage,
        result: TaskResult,
    },
}

/// How a task ended, as reported in [`crate::WorkerEvent::TaskFinished`].
#[derive(Debug, Clone, PartialEq)]
pub enum TaskResult {
    /// `CompleteTask` with this manifest (including `manifest.json`).
    Completed {
        outputs: Vec<pb::Artifact>,
        metrics: Metrics,
    },
    /// `FailTask` with this reason.
    Failed { reason: String, retryable: bool },
    /// Stopped on the coordinator's cancellation; nothing reported.
    Cancelled,
    /// Checkpointed and released on shutdown (`FailTask`, retryable, "worker shutting down").
    Released { checkpoint_step: Option<u64> },
    /// The lease was lost; nothing reported.
    LeaseLost,
}
