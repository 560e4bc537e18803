//! One leased task from start to end: a scratch folder, the heartbeat loop (progress, lease
//! extension, cancellation), checkpoint restore before the stage and checkpoint upload while it
//! runs, the stage itself on a blocking thread, then the outputs and `manifest.json` (last)
//! uploaded and `CompleteTask`, or `FailTask` with the reason.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use candle_core::Device;
use stylenerf_engine::checkpoint::CheckpointDir;
use stylenerf_engine::stages::{Outcome, StageControl};
use stylenerf_proto::v1 as pb;
use tokio::sync::broadcast;

use crate::connection::Clients;
use crate::context::{latest_checkpoint, Metrics, RunSettings, TaskContext};
use crate::error::TaskError;
use crate::events::{TaskResult, WorkerEvent};
use crate::progress::ProgressTracker;
use crate::retry::with_retries;
use crate::stages;
use crate::store::Store;
use crate::task_config::TaskConfig;

/// Why a task was stopped before its stage finished.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StopReason {
    /// The worker is shutting down: checkpoint, upload, release the lease.
    Shutdown,
    /// The heartbeat reply said the job was cancelled.
    Cancelled,
    /// The coordinator no longer recognises the lease (expired, leased again).
    LeaseLost,
}

/// Stops a running task: sets the stage's cancellation flag and records why (first reason
/// wins).
#[derive(Debug)]
pub struct TaskStop {
    cancel: Arc<AtomicBool>,
    reason: Mutex<Option<StopReason>>,
}

impl TaskStop {
    pub fn stop(&self, reason: StopReason) {
        self.reason
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get_or_insert(reason);
        self.cancel.store(true, Ordering::Relaxed);
    }

    pub fn reason(&self) -> Option<StopReason> {
        *self.reason.lock().unwrap_or_else(|e| e.into_inner())
    }
}

fn checkpoint_files(step: u64) -> [String; 2] {
    // Tensors first, metadata last: the engine treats a checkpoint as complete once its JSON
    // exists, so a reader never sees a JSON without its tensors.
    [
        format!("step-{step:08}.safetensors"),
        format!("step-{step:08}.json"),
    ]
}

/// Uploads the newest local checkpoint if it is newer than `uploaded`; returns its step.
async fn upload_checkpoint(
    store: &Store,
    dir: &Path,
    prefix: &str,
    uploaded: Option<u64>,
) -> Result<Option<u64>, TaskError> {
    let Some(step) = latest_checkpoint(dir) else {
        return Ok(uploaded);
    };
    if uploaded.is_some_and(|u| u >= step) {
        return Ok(uploaded);
    }
    for file in checkpoint_files(step) {
        store
            .upload(&format!("{prefix}{file}"), &dir.join(&file))
            .await?;
    }
    tracing::info!(step, prefix, "checkpoint uploaded");
    Ok(Some(step))
}

/// Downloads the newest good checkpoint under `prefix` into `dir`; returns its step. A
/// checkpoint that does not load (truncated, corrupt, non-finite values) is removed from
/// `dir` and the next older one tried, so one bad upload costs one checkpoint interval, not
/// the task's attempts.
async fn restore_checkpoint(
    store: &Store,
    prefix: &str,
    dir: &Path,
) -> Result<Option<u64>, TaskError> {
    let objects = store.list(prefix).await?;
    let names: std::collections::HashMap<&str, &pb::Artifact> = objects
        .iter()
        .filter_map(|o| o.key.strip_prefix(prefix).map(|n| (n, o)))
        .collect();
    let mut complete: Vec<u64> = names
        .keys()
        .filter_map(|n| n.strip_prefix("step-")?.strip_suffix(".json")?.parse().ok())
        .filter(|&step: &u64| {
            checkpoint_files(step)
                .iter()
                .all(|f| names.contains_key(f.as_str()))
        })
        .collect();
    complete.sort_unstable_by(|a, b| b.cmp(a));
    for step in complete {
        for file in checkpoint_files(step) {
            let object = names[file.as_str()];
            store
                .download(&object.key, &object.sha256, &dir.join(&file))
                .await?;
        }
        let local = CheckpointDir::new(dir, usize::MAX);
        let checked = tokio::task::spawn_blocking(move || {
            local
                .load::<serde_json::Value>(step, &Device::Cpu)
                .map(drop)
        })
        .await
        .map_err(|e| TaskError::retryable(format!("checking checkpoint {step}: {e}")))?;
        match checked {
            Ok(_) => return Ok(Some(step)),
            Err(error) => {
                tracing::warn!(step, %error, "passing over a bad stored checkpoint");
                for file in checkpoint_files(step) {
                    let _ = tokio::fs::remove_file(dir.join(file)).await;
                }
            }
        }
    }
    Ok(None)
}

/// Sends heartbeats every `interval` until aborted; stops the task on cancellation or a lost
/// lease.
async fn heartbeat_loop(
    mut clients: Clients,
    worker_id: String,
    task_id: u64,
    fencing_token: u64,
    interval: Duration,
    tracker: Arc<ProgressTracker>,
    stop: Arc<TaskStop>,
) {
    let mut tick = tokio::time::interval(interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let request = pb::HeartbeatRequest {
            worker_id: worker_id.clone(),
            task_id,
            fencing_token,
            progress: Some(tracker.snapshot()),
        };
        match clients.workers.heartbeat(request).await {
            Ok(reply) if reply.get_ref().cancel => {
                tracing::info!(task_id, "the job was cancelled: stopping the stage");
                stop.stop(StopReason::Cancelled);
            }
            Ok(_) => {}
            Err(s)
                if matches!(
                    s.code(),
                    tonic::Code::FailedPrecondition | tonic::Code::NotFound
                ) =>
            {
                tracing::warn!(
                    task_id,
                    reason = s.message(),
                    "lease lost: stopping the stage"
                );
                stop.stop(StopReason::LeaseLost);
            }
            Err(s) => tracing::warn!(task_id, error = %s, "heartbeat failed; retrying"),
        }
    }
}

/// Prepares one leased task: returns its stop handle and the future that runs it to its end
/// and reports it. The future never fails: every problem becomes a [`TaskResult`].
pub fn start_task(
    clients: Clients,
    settings: Arc<RunSettings>,
    assignment: pb::TaskAssignment,
    events: broadcast::Sender<WorkerEvent>,
) -> (Arc<TaskStop>, impl std::future::Future<Output = TaskResult>) {
    let tracker = Arc::new(ProgressTracker::new(stages::stage_name(assignment.stage)));
    let sink = tracker.clone();
    let mut control = StageControl::default().with_sink(move |p| sink.update(p));
    control.checkpoint_every_steps = settings.checkpoint_every_steps;
    control.checkpoint_every = settings.checkpoint_every;
    let stop = Arc::new(TaskStop {
        cancel: control.cancel_flag(),
        reason: Mutex::new(None),
    });
    let run = run_task(
        clients,
        settings,
        assignment,
        events,
        control,
        tracker,
        stop.clone(),
    );
    (stop, run)
}

async fn run_task(
    clients: Clients,
    settings: Arc<RunSettings>,
    assignment: pb::TaskAssignment,
    events: broadcast::Sender<WorkerEvent>,
    control: StageControl,
    tracker: Arc<ProgressTracker>,
    stop: Arc<TaskStop>,
) -> TaskResult {
    let scratch = settings
        .scratch_dir
        .join(format!("task-{}", assignment.task_id));
    let interval = Duration::from_millis(match assignment.heartbeat_interval_ms {
        0 => 5000,
        ms => ms,
    });
    let heartbeat = tokio::spawn(heartbeat_loop(
        clients.clone(),
        settings.worker_id.clone(),
        assignment.task_id,
        assignment.fencing_token,
        interval,
        tracker.clone(),
        stop.clone(),
    ));
    let (task_id, fencing_token) = (assignment.task_id, assignment.fencing_token);
    let prefix = assignment.checkpoint_prefix.clone();
    let result = async {
        let _ = tokio::fs::remove_dir_all(&scratch).await;
        let ctx = TaskContext {
            config: TaskConfig::parse(&assignment.config_json)?,
            store: Store::new(clients.artifacts.clone()),
            settings: settings.clone(),
            control,
            tracker: tracker.clone(),
            inputs: scratch.join("inputs"),
            out: scratch.join("out"),
            assignment,
        };
        execute(&ctx, &events).await
    }
    .await;
    let store = Store::new(clients.artifacts.clone());
    let ckpt_dir = scratch.join("out").join("ckpt");
    let report = match (stop.reason(), result) {
        (Some(StopReason::LeaseLost), _) => TaskResult::LeaseLost,
        (Some(StopReason::Cancelled), _) => TaskResult::Cancelled,
        (_, Ok(Executed::Done(outputs, metrics))) => {
            let request = pb::CompleteTaskRequest {
                worker_id: settings.worker_id.clone(),
                task_id,
                fencing_token,
                outputs: outputs.clone(),
                metrics: metrics.iter().map(|(k, v)| (k.clone(), *v)).collect(),
            };
            let completed = with_retries("CompleteTask", || {
                let mut workers = clients.workers.clone();
                let request = request.clone();
                async move { workers.complete_task(request).await }
            })
            .await;
            match completed {
                Ok(_) => TaskResult::Completed { outputs, metrics },
                Err(s) => TaskResult::Failed {
                    reason: format!("CompleteTask was refused: {}", s.message()),
                    retryable: true,
                },
            }
        }
        (reason, Ok(Executed::Stopped)) | (reason @ Some(StopReason::Shutdown), Err(_)) => {
            // Interrupted by a shutdown (or a failure raced with it): keep the last checkpoint
            // and give the task back.
            let checkpoint_step = match upload_checkpoint(&store, &ckpt_dir, &prefix, None).await {
                Ok(step) => step,
                Err(e) => {
                    tracing::warn!(task_id, error = %e, "uploading the final checkpoint failed");
                    None
                }
            };
            let reason = match reason {
                Some(StopReason::Shutdown) => "worker shutting down".to_string(),
                _ => "the stage stopped before finishing".to_string(),
            };
            fail(&clients, &settings, task_id, fencing_token, &reason, true).await;
            TaskResult::Released { checkpoint_step }
        }
        (None, Err(e)) => {
            // The job's owner sees the reason: the worker's folders are none of their business.
            let reason = e
                .reason
                .replace(&settings.scratch_dir.display().to_string(), "<scratch>");
            fail(
                &clients,
                &settings,
                task_id,
                fencing_token,
                &reason,
                e.retryable,
            )
            .await;
            TaskResult::Failed {
                reason,
                retryable: e.retryable,
            }
        }
    };
    heartbeat.abort();
    if !settings.keep_scratch {
        let _ = tokio::fs::remove_dir_all(&scratch).await;
    }
    report
}

async fn fail(
    clients: &Clients,
    settings: &RunSettings,
    task_id: u64,
    fencing_token: u64,
    reason: &str,
    retryable: bool,
) {
    let request = pb::FailTaskRequest {
        worker_id: settings.worker_id.clone(),
        task_id,
        fencing_token,
        reason: reason.to_string(),
        retryable,
    };
    let failed = with_retries("FailTask", || {
        let mut workers = clients.workers.clone();
        let request = request.clone();
        async move { workers.fail_task(request).await }
    })
    .await;
    if let Err(s) = failed {
        tracing::warn!(task_id, error = %s, "FailTask was refused");
    }
}

/// What [`execute`] achieved.
enum Executed {
    /// Outputs uploaded (manifest last).
    Done(Vec<pb::Artifact>, Metrics),
    /// The stage stopped early (checkpointed).
    Stopped,
}

/// Restores the checkpoint, runs the stage while uploading new checkpoints, and uploads the
/// outputs.
async fn execute(
    ctx: &TaskContext,
    events: &broadcast::Sender<WorkerEvent>,
) -> Result<Executed, TaskError> {
    let a = &ctx.assignment;
    let ckpt_dir = ctx.out.join("ckpt");
    for dir in [&ctx.inputs, &ckpt_dir] {
        tokio::fs::create_dir_all(dir)
            .await
            .map_err(|e| TaskError::retryable(format!("{}: {e}", dir.display())))?;
    }
    ctx.tracker.set_message("looking for a checkpoint");
    let restored = restore_checkpoint(&ctx.store, &a.checkpoint_prefix, &ckpt_dir).await?;
    if let Some(step) = restored {
        tracing::info!(
            task_id = a.task_id,
            attempt = a.attempt,
            step,
            "resuming from checkpoint step {step}"
        );
        ctx.tracker.set_resumed_from(step);
    }
    let _ = events.send(WorkerEvent::TaskStarted {
        task_id: a.task_id,
        job_id: a.job_id.clone(),
        stage: pb::Stage::try_from(a.stage).unwrap_or_default(),
        attempt: a.attempt,
        resumed_from: restored.unwrap_or(0),
    });

    // Upload new checkpoints while the stage runs.
    let uploader = {
        let (store, dir, prefix) = (
            ctx.store.clone(),
            ckpt_dir.clone(),
            a.checkpoint_prefix.clone(),
        );
        let every = ctx.settings.checkpoint_upload_every;
        tokio::spawn(async move {
            let mut uploaded = restored;
            loop {
                tokio::time::sleep(every).await;
                match upload_checkpoint(&store, &dir, &prefix, uploaded).await {
                    Ok(step) => uploaded = step,
                    Err(e) => tracing::warn!(error = %e, "checkpoint upload failed; retrying"),
                }
            }
        })
    };
    let outcome = stages::run_stage(ctx).await;
    uploader.abort();
    let metrics = match outcome? {
        Outcome::Done(mut metrics) => {
            metrics.insert("resumed_from".into(), restored.unwrap_or(0) as f64);
            metrics
        }
        Outcome::Stopped { .. } => return Ok(Executed::Stopped),
    };

    ctx.tracker.set_message("uploading outputs");
    let prefix = &a.output_prefix;
    let mut outputs = ctx
        .store
        .upload_dir(&ctx.out, prefix, |rel| {
            rel.starts_with("ckpt/") || rel == MANIFEST
        })
        .await?;
    let manifest = serde_json::json!({
        "task_id": a.task_id,
        "job_id": a.job_id,
        "stage": stages::stage_name(a.stage),
        "attempt": a.attempt,
        "metrics": metrics,
        "outputs": outputs.iter().map(|o| serde_json::json!({
            "key": o.key, "size": o.size, "sha256": o.sha256,
        })).collect::<Vec<_>>(),
    });
    let path = ctx.out.join(MANIFEST);
    let bytes = serde_json::to_vec_pretty(&manifest).expect("JSON of plain values");
    tokio::fs::write(&path, bytes)
        .await
        .map_err(|e| TaskError::retryable(format!("{}: {e}", path.display())))?;
    outputs.push(
        ctx.store
            .upload(&format!("{prefix}{MANIFEST}"), &path)
            .await?,
    );
    Ok(Executed::Done(outputs, metrics))
}

/// Written last under the output prefix: the list of outputs, their checksums and the metrics.
pub const MANIFEST: &str = "manifest.json";
