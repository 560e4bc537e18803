//! The worker loop: register, long-poll `LeaseTask` while fewer than `max_tasks` tasks run and
//! their memory leaves room, run each task concurrently, and on shutdown stop every running
//! task (each checkpoints, uploads and releases its lease) before returning.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use backon::{BackoffBuilder, Retryable};
use stylenerf_engine::device::{device_name, parse_device};
use stylenerf_proto::v1 as pb;
use tokio::sync::{broadcast, watch};
use tokio::task::JoinSet;

use crate::config::WorkerConfig;
use crate::connection::Clients;
use crate::context::RunSettings;
use crate::events::{TaskResult, WorkerEvent};
use crate::retry;
use crate::scratch::ScratchDir;
use crate::task::{start_task, StopReason, TaskStop};

/// Controls a running [`Worker`] from elsewhere: shut it down, watch its events.
#[derive(Clone)]
pub struct WorkerHandle {
    shutdown: Arc<watch::Sender<bool>>,
    events: broadcast::Sender<WorkerEvent>,
}

impl WorkerHandle {
    /// Asks the worker to stop: running stages checkpoint, upload and release their leases;
    /// [`Worker::run`] then returns.
    pub fn shutdown(&self) {
        let _ = self.shutdown.send(true);
    }

    /// Events from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<WorkerEvent> {
        self.events.subscribe()
    }
}

/// A registered worker, ready to [`run`](Worker::run).
pub struct Worker {
    clients: Clients,
    config: WorkerConfig,
    settings: Arc<RunSettings>,
    capabilities: pb::Capabilities,
    handle: WorkerHandle,
    /// The locked scratch folder of the current worker id (see [`ScratchDir`]).
    scratch: Option<ScratchDir>,
}

/// What [`Worker::run`] did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RunSummary {
    pub completed: u64,
    pub failed: u64,
    pub cancelled: u64,
    /// Given back on shutdown or after a lost lease.
    pub released: u64,
}

impl Worker {
    /// Opens the device, connects to the coordinator and registers.
    pub async fn register(config: WorkerConfig) -> anyhow::Result<Self> {
        let device = parse_device(&config.device).context("--device")?;
        let clients = Clients::connect(
            &config.endpoint,
            config.token.as_deref(),
            config.ca_cert.as_deref(),
        )
        .await?;
        let capabilities = pb::Capabilities {
            device: device_name(&device),
            memory_bytes: config.memory_bytes,
            labels: config.labels.clone(),
            max_tasks: config.max_tasks.max(1) as u32,
            tools: advertised_tools(),
        };
        let mut worker = Self {
            clients,
            settings: Arc::new(RunSettings {
                worker_id: String::new(),
                device,
                encoder: config.encoder.clone(),
                checkpoint_every_steps: config.checkpoint_every_steps,
                checkpoint_every: config.checkpoint_every,
                checkpoint_upload_every: config.checkpoint_upload_every,
                // Set with the worker id by `register_again`.
                scratch_dir: std::path::PathBuf::new(),
                keep_scratch: config.keep_scratch,
            }),
            capabilities,
            handle: WorkerHandle {
                shutdown: Arc::new(watch::channel(false).0),
                events: broadcast::channel(256).0,
            },
            config,
            scratch: None,
        };
        worker
            .register_again(worker.config.worker_id.clone())
            .await?;
        Ok(worker)
    }

    /// Registers (again) under `id` (or a new id) and points the scratch folder at it.
    /// Waits (jittered backoff, no deadline) while the coordinator cannot be reached; a refusal
    /// (a bad token, an id registered by others) is an error at once.
    async fn register_again(&mut self, id: Option<String>) -> anyhow::Result<()> {
        let request = pb::RegisterWorkerRequest {
            name: self.config.name.clone(),
            capabilities: Some(self.capabilities.clone()),
            worker_id: id.unwrap_or_default(),
        };
        let endpoint = self.config.endpoint.clone();
        let workers = self.clients.workers.clone();
        let reply = (|| {
            let mut workers = workers.clone();
            let request = request.clone();
            async move { workers.register_worker(request).await }
        })
        .retry(retry::patient())
        .when(retry::is_transient)
        .notify(|status, delay| {
            tracing::warn!(%endpoint, error = status.message(), retry_in = ?delay,
                "the coordinator is not reachable yet; waiting");
        })
        .await
        .with_context(|| format!("registering with {}", self.config.endpoint))?
        .into_inner();
        let settings = Arc::make_mut(&mut self.settings);
        settings.worker_id = reply.worker_id.clone();
        let root = self
            .config
            .scratch_dir
            .clone()
            .unwrap_or_else(|| std::env::temp_dir().join("stylenerf-worker"));
        if self.scratch.as_ref().map(|s| s.path()) != Some(&root.join(&reply.worker_id)) {
            let scratch = ScratchDir::claim(&root, &reply.worker_id)
                .with_context(|| format!("scratch folder under {}", root.display()))?;
            settings.scratch_dir = scratch.path().to_path_buf();
            self.scratch = Some(scratch);
        }
        tracing::info!(
            worker_id = %reply.worker_id,
            name = %self.config.name,
            device = %self.capabilities.device,
            memory_bytes = self.capabilities.memory_bytes,
            max_tasks = self.capabilities.max_tasks,
            lease_ttl_ms = reply.lease_ttl_ms,
            "worker registered"
        );
        Ok(())
    }

    /// The id the coordinator gave this worker.
    pub fn id(&self) -> &str {
        &self.settings.worker_id
    }

    pub fn handle(&self) -> WorkerHandle {
        self.handle.clone()
    }

    /// Leases and runs tasks until [`WorkerHandle::shutdown`]; then stops the running tasks
    /// (they checkpoint and release their leases) and returns.
    pub async fn run(mut self) -> anyhow::Result<RunSummary> {
        let mut shutdown = self.handle.shutdown.subscribe();
        let mut running: JoinSet<(pb::TaskAssignment, TaskResult)> = JoinSet::new();
        let mut stops: HashMap<u64, Arc<TaskStop>> = HashMap::new();
        let mut reserved: HashMap<u64, u64> = HashMap::new();
        let mut summary = RunSummary::default();
        // Waits after failed LeaseTask calls: jittered, growing, reset by a success.
        let mut delays = retry::patient().build();
        let budget = self.config.memory_bytes;
        let max_tasks = self.config.max_tasks.max(1);
        while !*shutdown.borrow() {
            metrics::gauge!("stylenerf_worker_tasks_running").set(running.len() as f64);
            let used: u64 = reserved.values().sum();
            let free = budget.saturating_sub(used);
            let can_lease = running.len() < max_tasks && (budget == 0 || free > 0);
            let mut workers = self.clients.workers.clone();
            let request = pb::LeaseTaskRequest {
                worker_id: self.settings.worker_id.clone(),
                wait_ms: self.config.lease_wait.as_millis() as u64,
                // 0 lets the coordinator use the registered budget minus the running tasks.
                free_memory_bytes: if budget == 0 { 0 } else { free },
            };
            let lease = async move {
                if can_lease {
                    workers.lease_task(request).await
                } else {
                    std::future::pending().await
                }
            };
            tokio::select! {
                _ = shutdown.changed() => break,
                Some(joined) = running.join_next() => {
                    self.finished(joined, &mut stops, &mut reserved, &mut summary);
                }
                reply = lease => match reply {
                    Ok(reply) => {
                        delays = retry::patient().build();
                        let Some(task) = reply.into_inner().task else { continue };
                        if budget > 0 && task.memory_bytes > free {
                            // The coordinator checks this too; never run what does not fit.
                            tracing::error!(task_id = task.task_id, memory = task.memory_bytes,
                                free, "leased a task larger than the free budget; releasing it");
                            self.release_unrun(&task, "the task does not fit the worker's memory").await;
                            continue;
                        }
                        tracing::info!(
                            task_id = task.task_id, job_id = %task.job_id,
                            stage = crate::stages::stage_name(task.stage),
                            attempt = task.attempt, "task leased"
                        );
                        let (stop, run) = start_task(
                            self.clients.clone(),
                            self.settings.clone(),
                            task.clone(),
                            self.handle.events.clone(),
                        );
                        stops.insert(task.task_id, stop);
                        reserved.insert(task.task_id, task.memory_bytes);
                        running.spawn(async move { (task, run.await) });
                    }
                    Err(s) if s.code() == tonic::Code::NotFound => {
                        tracing::warn!("the coordinator does not know this worker; registering again");
                        if let Err(e) = self.register_again(Some(self.settings.worker_id.clone())).await {
                            let backoff = delays.next().unwrap_or(Duration::from_secs(30));
                            tracing::warn!(error = %e, retry_in = ?backoff, "registering failed");
                            tokio::time::sleep(backoff).await;
                        }
                    }
                    Err(s) => {
                        let backoff = delays.next().unwrap_or(Duration::from_secs(30));
                        tracing::warn!(error = %s, retry_in = ?backoff, "LeaseTask failed");
                        tokio::select! {
                            _ = tokio::time::sleep(backoff) => {}
                            _ = shutdown.changed() => break,
                        }
                    }
                },
            }
        }
        metrics::gauge!("stylenerf_worker_draining").set(1.0);
        if !running.is_empty() {
            tracing::info!(
                tasks = running.len(),
                "shutting down: checkpointing running tasks"
            );
        }
        for stop in stops.values() {
            stop.stop(StopReason::Shutdown);
        }
        while let Some(joined) = running.join_next().await {
            self.finished(joined, &mut stops, &mut reserved, &mut summary);
        }
        tracing::info!(?summary, "worker stopped");
        Ok(summary)
    }

    fn finished(
        &self,
        joined: Result<(pb::TaskAssignment, TaskResult), tokio::task::JoinError>,
        stops: &mut HashMap<u64, Arc<TaskStop>>,
        reserved: &mut HashMap<u64, u64>,
        summary: &mut RunSummary,
    ) {
        let (task, result) = match joined {
            Ok(done) => done,
            Err(e) => {
                // A panic outside the stage (the stage's own panics are reported as failures).
                tracing::error!(error = %e, "a task runner panicked");
                return;
            }
        };
        stops.remove(&task.task_id);
        reserved.remove(&task.task_id);
        let outcome = match &result {
            TaskResult::Completed { .. } => {
                summary.completed += 1;
                "completed"
            }
            TaskResult::Failed { .. } => {
                summary.failed += 1;
                "failed"
            }
            TaskResult::Cancelled => {
                summary.cancelled += 1;
                "cancelled"
            }
            TaskResult::Released { .. } | TaskResult::LeaseLost => {
                summary.released += 1;
                "released"
            }
        };
        metrics::counter!(
            "stylenerf_worker_tasks_total",
            "stage" => crate::stages::stage_name(task.stage),
            "outcome" => outcome,
        )
        .increment(1);
        tracing::info!(task_id = task.task_id, ?result, "task finished");
        let _ = self.handle.events.send(WorkerEvent::TaskFinished {
            task_id: task.task_id,
            job_id: task.job_id,
            stage: pb::Stage::try_from(task.stage).unwrap_or_default(),
            result,
        });
    }

    /// Gives back a task without running it.
    async fn release_unrun(&self, task: &pb::TaskAssignment, reason: &str) {
        let request = pb::FailTaskRequest {
            worker_id: self.settings.worker_id.clone(),
            task_id: task.task_id,
            fencing_token: task.fencing_token,
            reason: reason.to_string(),
            retryable: true,
        };
        if let Err(s) = self.clients.workers.clone().fail_task(request).await {
            tracing::warn!(task_id = task.task_id, error = %s, "FailTask was refused");
        }
    }
}

/// The stages' programs found here (logged, with why a missing one is missing: such a worker
/// is not handed the stages that need it).
fn advertised_tools() -> Vec<String> {
    let mut tools = Vec::new();
    for (name, found) in stylenerf_engine::poses::installed_tools() {
        match found {
            Ok(tool) => {
                tracing::info!(tool = name, program = %tool.program.display(), "found");
                tools.push(name.to_string());
            }
            Err(e) => tracing::warn!(
                tool = name,
                "{e}; this worker will not be handed the tasks that need {name}"
            ),
        }
    }
    tools
}
