//! `WorkerService`: registration, long-polling leases, heartbeats, completion and failure.

use crate::auth::{require, WORKER_ROLES};
use crate::errors::invalid;
use crate::scheduler;
use crate::state::Shared;
use std::sync::Arc;
use std::time::Duration;
use stylenerf_proto::v1 as pb;
use stylenerf_proto::v1::worker_service_server::WorkerService;
use tonic::{Request, Response, Status};

pub struct WorkerApi {
    pub shared: Arc<Shared>,
}

#[allow(clippy::result_large_err)]
fn check_ids(worker_id: &str, task_id: u64) -> Result<(), Status> {
    if worker_id.is_empty() {
        return Err(invalid("worker_id", "missing"));
    }
    if task_id == 0 {
        return Err(invalid("task_id", "missing"));
    }
    Ok(())
}

/// Most metrics in a heartbeat's progress or a completion.
const MAX_METRICS: usize = 64;
/// Longest progress message or failure reason kept (characters).
const MAX_TEXT: usize = 1000;

/// Bounds what a worker may store with each heartbeat or completion: progress is kept on the
/// task row and in events that every watcher replays.
#[allow(clippy::result_large_err)]
fn check_metrics(
    field: &str,
    metrics: &std::collections::HashMap<String, f64>,
) -> Result<(), Status> {
    if metrics.len() > MAX_METRICS {
        return Err(invalid(field, format!("more than {MAX_METRICS} metrics")));
    }
    if metrics.keys().any(|k| k.chars().count() > 64) {
        return Err(invalid(field, "metric names are at most 64 characters"));
    }
    Ok(())
}

#[tonic::async_trait]
impl WorkerService for WorkerApi {
    async fn register_worker(
        &self,
        request: Request<pb::RegisterWorkerRequest>,
    ) -> Result<Response<pb::RegisterWorkerResponse>, Status> {
        let caller = require(&request, WORKER_ROLES)?;
        let req = request.into_inner();
        let worker_id = scheduler::register_worker(&self.shared, &caller.name, &req).await?;
        tracing::info!(worker = %worker_id, name = %req.name, "worker registered");
        let config = &self.shared.config;
        Ok(Response::new(pb::RegisterWorkerResponse {
            worker_id,
            lease_ttl_ms: config.lease_ttl.as_millis() as u64,
            heartbeat_interval_ms: config.heartbeat_interval.as_millis() as u64,
            object_store_url: self.shared.storage.url().to_string(),
        }))
    }

    async fn lease_task(
        &self,
        request: Request<pb::LeaseTaskRequest>,
    ) -> Result<Response<pb::LeaseTaskResponse>, Status> {
        let caller = require(&request, WORKER_ROLES)?;
        let req = request.into_inner();
        if req.worker_id.is_empty() {
            return Err(invalid("worker_id", "missing"));
        }
        scheduler::check_worker_owner(&self.shared, &caller, &req.worker_id).await?;
        let max_wait = self.shared.config.max_lease_wait;
        let wait = match req.wait_ms {
            0 => max_wait,
            ms => Duration::from_millis(ms).min(max_wait),
        };
        let deadline = tokio::time::Instant::now() + wait;
        let mut shutdown = self.shared.shutdown.clone();
        loop {
            // Register for wake-ups before looking, so that no notification is missed.
            let notified = self.shared.ready.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            if let Some(task) =
                scheduler::try_lease(&self.shared, &req.worker_id, req.free_memory_bytes).await?
            {
                tracing::debug!(worker = %req.worker_id, task = task.task_id, "task leased");
                return Ok(Response::new(pb::LeaseTaskResponse { task: Some(task) }));
            }
            tokio::select! {
                _ = &mut notified => {}
                _ = tokio::time::sleep_until(deadline) => break,
                _ = shutdown.changed() => break,
            }
        }
        Ok(Response::new(pb::LeaseTaskResponse { task: None }))
    }

    async fn heartbeat(
        &self,
        request: Request<pb::HeartbeatRequest>,
    ) -> Result<Response<pb::HeartbeatResponse>, Status> {
        let caller = require(&request, WORKER_ROLES)?;
        let req = request.into_inner();
        check_ids(&req.worker_id, req.task_id)?;
        scheduler::check_worker_owner(&self.shared, &caller, &req.worker_id).await?;
        if let Some(progress) = &req.progress {
            check_metrics("progress.metrics", &progress.metrics)?;
            if progress.message.chars().count() > MAX_TEXT {
                return Err(invalid(
                    "progress.message",
                    format!("longer than {MAX_TEXT} characters"),
                ));
            }
        }
        let (cancel, lease_expires_at_ms) = scheduler::heartbeat(&self.shared, &req).await?;
        Ok(Response::new(pb::HeartbeatResponse {
            cancel,
            lease_expires_at_ms,
        }))
    }

    async fn complete_task(
        &self,
        request: Request<pb::CompleteTaskRequest>,
    ) -> Result<Response<pb::CompleteTaskResponse>, Status> {
        let caller = require(&request, WORKER_ROLES)?;
        let req = request.into_inner();
        check_ids(&req.worker_id, req.task_id)?;
        scheduler::check_worker_owner(&self.shared, &caller, &req.worker_id).await?;
        check_metrics("metrics", &req.metrics)?;
        scheduler::complete(&self.shared, &req).await?;
        tracing::debug!(worker = %req.worker_id, task = req.task_id, "task completed");
        Ok(Response::new(pb::CompleteTaskResponse {}))
    }

    async fn fail_task(
        &self,
        request: Request<pb::FailTaskRequest>,
    ) -> Result<Response<pb::FailTaskResponse>, Status> {
        let caller = require(&request, WORKER_ROLES)?;
        let mut req = request.into_inner();
        check_ids(&req.worker_id, req.task_id)?;
        scheduler::check_worker_owner(&self.shared, &caller, &req.worker_id).await?;
        // A failure is recorded whatever its length: a long reason is cut, not refused.
        if let Some((cut, _)) = req.reason.char_indices().nth(MAX_TEXT) {
            req.reason.truncate(cut);
            req.reason.push('…');
        }
        let requeued = scheduler::fail(&self.shared, &req).await?;
        tracing::info!(worker = %req.worker_id, task = req.task_id, requeued, reason = %req.reason, "task failed");
        Ok(Response::new(pb::FailTaskResponse { requeued }))
    }
}
