//! Task scheduling: worker registration, leasing (highest priority, then oldest ready task
//! first, matched against the worker's device, labels and free memory, and skipping owners at
//! their running-task quota), heartbeats that extend leases, completion and
//! failure under fencing tokens, promotion of dependent tasks, and requeueing of expired leases.
//! Every state change happens in one write transaction, group-committed by `writer`.

use crate::auth::Principal;
use crate::config::Quotas;
use crate::errors::{internal, invalid};
use crate::events::{EventBatch, NewEvent, JOB_STATE, TASK_PROGRESS};
use crate::jobs::{cancel_open_tasks, set_job_state, TaskRow};
use crate::model::{job_state, now_ms, task_state, Stage, StoredProgress};
use crate::state::Shared;
use crate::writer::{OpError, OpResult};
use futures::FutureExt;
use sqlx::SqliteConnection;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use stylenerf_plan::Source;
use stylenerf_proto::v1 as pb;
use tonic::Status;

/// Registers a worker (or refreshes a known id) and returns its id.
pub async fn register_worker(
    shared: &Shared,
    owner: &str,
    request: &pb::RegisterWorkerRequest,
) -> Result<String, Status> {
    let caps = request.capabilities.clone().unwrap_or_default();
    let device = if caps.device.is_empty() {
        "cpu".to_string()
    } else {
        caps.device.clone()
    };
    if let Err(e) = device.parse::<stylenerf_plan::device::DeviceName>() {
        return Err(invalid("capabilities.device", e.reason));
    }
    if request.name.len() > 200 {
        return Err(invalid("name", "longer than 200 characters"));
    }
    let id = if request.worker_id.is_empty() {
        format!("w-{}", uuid::Uuid::now_v7().simple())
    } else {
        request.worker_id.clone()
    };
    if id.len() > 100 {
        return Err(invalid("worker_id", "longer than 100 characters"));
    }
    let now = now_ms();
    // A known id is refreshed only by the principal that registered it: a worker's leases are
    // bound to its credentials.
    let stored = sqlx::query(
        "INSERT INTO workers (id, name, owner, device, memory_bytes, labels, max_tasks, \
         registered_at, last_seen_at, tools) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?) \
         ON CONFLICT (id) DO UPDATE SET name = excluded.name, \
         device = excluded.device, memory_bytes = excluded.memory_bytes, labels = excluded.labels, \
         max_tasks = excluded.max_tasks, last_seen_at = excluded.last_seen_at, \
         tools = excluded.tools \
         WHERE workers.owner = excluded.owner",
    )
    .bind(&id)
    .bind(&request.name)
    .bind(owner)
    .bind(&device)
    .bind(caps.memory_bytes.min(i64::MAX as u64) as i64)
    .bind(serde_json::to_string(&caps.labels).unwrap_or_else(|_| "[]".into()))
    .bind(caps.max_tasks.max(1) as i64)
    .bind(now)
    .bind(now)
    .bind(serde_json::to_string(&caps.tools).unwrap_or_else(|_| "[]".into()))
    .execute(&shared.db.write)
    .await
    .map_err(internal)?;
    if stored.rows_affected() == 0 {
        return Err(Status::permission_denied(format!(
            "worker id {id:?} is registered with other credentials"
        )));
    }
    shared
        .worker_owners
        .lock()
        .expect("worker owners")
        .insert(id.clone(), owner.to_string());
    Ok(id)
}

/// Checks that `worker_id` was registered by `caller`; every worker call acts on leases held
/// under that id. An unknown id is NOT_FOUND (the worker registers again).
pub async fn check_worker_owner(
    shared: &Shared,
    caller: &Principal,
    worker_id: &str,
) -> Result<(), Status> {
    let cached = shared
        .worker_owners
        .lock()
        .expect("worker owners")
        .get(worker_id)
        .cloned();
    let owner = match cached {
        Some(owner) => Some(owner),
        None => {
            let stored: Option<String> =
                sqlx::query_scalar("SELECT owner FROM workers WHERE id = ?")
                    .bind(worker_id)
                    .fetch_optional(&shared.db.read)
                    .await
                    .map_err(internal)?;
            if let Some(owner) = &stored {
                shared
                    .worker_owners
                    .lock()
                    .expect("worker owners")
                    .insert(worker_id.to_string(), owner.clone());
            }
            stored
        }
    };
    match owner {
        None => Err(Status::not_found(format!(
            "worker {worker_id:?} is not registered (call RegisterWorker)"
        ))),
        Some(owner) if owner == caller.name => Ok(()),
        Some(_) => Err(Status::permission_denied(format!(
            "worker {worker_id:?} is registered with other credentials"
        ))),
    }
}

/// Whether `caller` (through a worker it registered) holds a live lease on a task of `job_id`;
/// with `writing`, the task's output prefix must also contain `key`. Workers reach only the
/// objects of the jobs they are working on.
pub async fn worker_may_access(
    shared: &Shared,
    caller: &Principal,
    job_id: &str,
    key: &str,
    writing: bool,
) -> Result<bool, Status> {
    let prefixes: Vec<String> = sqlx::query_scalar(
        "SELECT t.output_prefix FROM tasks t JOIN workers w ON w.id = t.worker_id \
         WHERE t.job_id = ? AND t.state = 'leased' AND w.owner = ?",
    )
    .bind(job_id)
    .bind(&caller.name)
    .fetch_all(&shared.db.read)
    .await
    .map_err(internal)?;
    Ok(if writing {
        prefixes
            .iter()
            .any(|prefix| key.starts_with(prefix.as_str()))
    } else {
        !prefixes.is_empty()
    })
}

#[derive(sqlx::FromRow)]
struct WorkerRow {
    device: String,
    memory_bytes: i64,
    labels: String,
    tools: String,
    max_tasks: i64,
    running: i64,
    reserved: i64,
}

/// Expired leases are also looked for at lease time, at most this often (milliseconds); the
/// reaper does it every `reaper_interval` in any case.
const LEASE_TIME_EXPIRY_CHECK_MS: i64 = 100;

/// Tries once to lease a task to a worker. The group-committed write only claims the task;
/// the assignment's inputs are read afterwards from the read pool.
pub async fn try_lease(
    shared: &Shared,
    worker_id: &str,
    free_memory: u64,
) -> Result<Option<pb::TaskAssignment>, Status> {
    let now = now_ms();
    let check_expiry = shared
        .next_expiry_check
        .fetch_max(now + LEASE_TIME_EXPIRY_CHECK_MS, Ordering::Relaxed)
        <= now;
    let ttl = shared.config.lease_ttl.as_millis() as i64;
    let worker = worker_id.to_string();
    // Counted per lease only where some owner has a running-task limit.
    let quotas = Arc::new(
        shared
            .config
            .quotas
            .limits_running_tasks()
            .then(|| shared.config.quotas.clone()),
    );
    let (leased, requeued) = shared
        .writer
        .write(move |conn, batch| {
            let worker_id = worker.clone();
            let quotas = quotas.clone();
            async move {
                let quotas = quotas.as_ref().as_ref();
                lease_in(
                    conn,
                    batch,
                    &worker_id,
                    free_memory,
                    ttl,
                    check_expiry,
                    quotas,
                )
                .await
            }
            .boxed()
        })
        .await??;
    if requeued {
        shared.wake_workers();
    }
    let Some(task) = leased else {
        return Ok(None);
    };
    metrics::counter!("stylenerf_leases_total", "stage" => task.stage.clone()).increment(1);
    assignment(shared, task).await.map(Some).map_err(internal)
}

/// The lease transaction's work: requeues expired leases when asked to, then claims the first
/// ready task (by priority, then age) the worker can run and whose owner is below its
/// running-task quota. Returns the claimed task and whether tasks were requeued.
async fn lease_in(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    worker_id: &str,
    free_memory: u64,
    ttl: i64,
    check_expiry: bool,
    quotas: Option<&Quotas>,
) -> OpResult<Result<(Option<TaskRow>, bool), Status>> {
    let now = now_ms();
    let requeued = check_expiry && expire_leases(conn, batch, now).await?;
    let worker: Option<WorkerRow> = sqlx::query_as(
        "UPDATE workers SET last_seen_at = ? WHERE id = ? \
         RETURNING device, memory_bytes, labels, tools, max_tasks, \
         (SELECT COUNT(*) FROM tasks WHERE worker_id = workers.id AND state = 'leased') AS running, \
         (SELECT COALESCE(SUM(memory_bytes), 0) FROM tasks \
          WHERE worker_id = workers.id AND state = 'leased') AS reserved",
    )
    .bind(now)
    .bind(worker_id)
    .fetch_optional(&mut *conn)
    .await?;
    let Some(worker) = worker else {
        return Ok(Err(Status::not_found(format!(
            "worker {worker_id:?} is not registered (call RegisterWorker)"
        ))));
    };
    if worker.running >= worker.max_tasks.max(1) {
        return Ok(Ok((None, requeued)));
    }
    let free = if free_memory > 0 {
        free_memory.min(i64::MAX as u64) as i64
    } else if worker.memory_bytes > 0 {
        worker.memory_bytes - worker.reserved
    } else {
        i64::MAX
    };
    let cuda = worker.device.starts_with("cuda");
    let labels: HashSet<String> = serde_json::from_str(&worker.labels).unwrap_or_default();
    let tools: HashSet<String> = serde_json::from_str(&worker.tools).unwrap_or_default();
    // Look at the head of the queue first; only a worker that matches none of it (labels,
    // tools) searches deeper.
    // Owners found at their running-task quota in this lease.
    let mut at_quota: HashMap<String, bool> = HashMap::new();
    for window in [8i64, 1024] {
        let candidates: Vec<Candidate> = sqlx::query_as(
            "SELECT t.id, j.labels, t.ready_at, j.require_cuda, j.owner, t.stage, j.dataset_key \
             FROM tasks t \
             JOIN jobs j ON j.id = t.job_id \
             WHERE t.state = 'ready' AND t.memory_bytes <= ? AND (j.require_cuda = 0 OR ?) \
             ORDER BY t.priority DESC, t.ready_at, t.id LIMIT ?",
        )
        .bind(free)
        .bind(cuda)
        .bind(window)
        .fetch_all(&mut *conn)
        .await?;
        let seen = candidates.len() as i64;
        let mut chosen = None;
        for (task_id, job_labels, ready_at, require_cuda, owner, stage, dataset_key) in candidates {
            let labelled = serde_json::from_str::<Vec<String>>(&job_labels)
                .unwrap_or_default()
                .iter()
                .all(|l| labels.contains(l));
            let source = Source::of_input_key(&dataset_key);
            let equipped = Stage::parse(&stage)
                .is_none_or(|s| s.tools(source).iter().all(|&t| tools.contains(t)));
            if !(labelled && equipped) {
                continue;
            }
            if let Some(quotas) = quotas {
                if !at_quota.contains_key(&owner) {
                    let full = owner_at_quota(conn, quotas, &owner).await?;
                    at_quota.insert(owner.clone(), full);
                }
                if at_quota[&owner] {
                    continue;
                }
            }
            chosen = Some((task_id, ready_at, require_cuda));
            break;
        }
        if let Some((task_id, ready_at, require_cuda)) = chosen {
            let task = claim(conn, batch, task_id, worker_id, now, ttl).await?;
            metrics::histogram!(
                "stylenerf_queue_wait_seconds",
                "stage" => task.stage.clone(),
                "device" => device_class(require_cuda),
            )
            .record((now - ready_at).max(0) as f64 / 1000.0);
            return Ok(Ok((Some(task), requeued)));
        }
        if seen < window {
            break;
        }
    }
    Ok(Ok((None, requeued)))
}

/// A ready task a worker might lease: id, the job's labels, ready time, whether the job needs
/// CUDA, its owner, the stage and the job's scene input key (which says its source).
type Candidate = (i64, String, i64, bool, String, String, String);

/// Whether `owner` has as many tasks leased as its quota allows.
async fn owner_at_quota(
    conn: &mut SqliteConnection,
    quotas: &Quotas,
    owner: &str,
) -> Result<bool, sqlx::Error> {
    let limit = quotas.of(owner).running_tasks;
    if limit == 0 {
        return Ok(false);
    }
    let running: i64 = sqlx::query_scalar(
        "SELECT COUNT(*) FROM tasks t JOIN jobs j ON j.id = t.job_id \
         WHERE t.state = 'leased' AND j.owner = ?",
    )
    .bind(owner)
    .fetch_one(&mut *conn)
    .await?;
    Ok(running >= limit as i64)
}

/// Marks a ready task leased by `worker_id` under a new fencing token. The previous attempt's
/// progress is cleared: what the task shows from now on is this attempt's.
async fn claim(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    task_id: i64,
    worker_id: &str,
    now: i64,
    ttl: i64,
) -> Result<TaskRow, sqlx::Error> {
    let task: TaskRow = sqlx::query_as(
        "UPDATE tasks SET state = 'leased', attempt = attempt + 1, \
         fencing_token = fencing_token + 1, worker_id = ?, leased_at = ?, lease_expires_at = ?, \
         progress = '{}', progress_event_at = 0, \
         started_at = CASE WHEN started_at = 0 THEN ? ELSE started_at END \
         WHERE id = ? RETURNING *",
    )
    .bind(worker_id)
    .bind(now)
    .bind(now + ttl)
    .bind(now)
    .bind(task_id)
    .fetch_one(&mut *conn)
    .await?;
    let message = format!("leased by {worker_id}");
    batch.push(NewEvent::task(
        &task.job_id,
        task.id,
        &task.stage,
        task_state::LEASED,
        task.attempt,
        &message,
    ));
    // Only a first lease can start the job (the update below finds it queued only once).
    if !(task.core && task.attempt == 1) {
        return Ok(task);
    }
    let started = sqlx::query(
        "UPDATE jobs SET state = 'running', updated_at = ? WHERE id = ? AND state = 'queued'",
    )
    .bind(now)
    .bind(&task.job_id)
    .execute(&mut *conn)
    .await?
    .rows_affected();
    if started > 0 {
        batch.push(NewEvent::job(
            &task.job_id,
            JOB_STATE,
            job_state::RUNNING,
            "",
        ));
    }
    Ok(task)
}

/// A completed upstream task and one of its outputs (none if it has no outputs).
type UpstreamRow = (
    i64,
    String,
    String,
    Option<String>,
    Option<i64>,
    Option<String>,
);

/// Builds the assignment of a freshly leased task: the job's inputs and the outputs of the
/// completed upstream stages (committed data, read from the read pool).
async fn assignment(shared: &Shared, task: TaskRow) -> Result<pb::TaskAssignment, sqlx::Error> {
    let pool = &shared.db.read;
    let (dataset_key, style_keys): (String, String) =
        sqlx::query_as("SELECT dataset_key, style_keys FROM jobs WHERE id = ?")
            .bind(&task.job_id)
            .fetch_one(pool)
            .await?;
    // The outputs of the stages this one reads.
    let upstream = Stage::parse(&task.stage).map_or(&[][..], Stage::upstream);
    let rows: Vec<UpstreamRow> = if upstream.is_empty() {
        Vec::new()
    } else {
        sqlx::query_as(
            "SELECT t.id, t.stage, t.output_prefix, a.key, a.size, a.sha256 FROM tasks t \
             LEFT JOIN artifacts a ON a.task_id = t.id \
             WHERE t.job_id = ? AND t.core = 1 AND t.state = 'succeeded' ORDER BY t.id, a.key",
        )
        .bind(&task.job_id)
        .fetch_all(pool)
        .await?
    };
    let mut inputs: Vec<pb::StageInput> = Vec::new();
    for (id, stage, prefix, key, size, sha256) in rows {
        if !Stage::parse(&stage).is_some_and(|s| upstream.contains(&s)) {
            continue;
        }
        if inputs.last().is_none_or(|i| i.task_id != id as u64) {
            inputs.push(pb::StageInput {
                stage: crate::model::stage_pb(&stage),
                task_id: id as u64,
                prefix,
                artifacts: Vec::new(),
            });
        }
        if let (Some(key), Some(size), Some(sha256), Some(input)) =
            (key, size, sha256, inputs.last_mut())
        {
            input.artifacts.push(pb::Artifact {
                key,
                size: size as u64,
                sha256,
            });
        }
    }
    Ok(pb::TaskAssignment {
        task_id: task.id as u64,
        job_id: task.job_id.clone(),
        stage: crate::model::stage_pb(&task.stage),
        attempt: task.attempt as u32,
        fencing_token: task.fencing_token as u64,
        lease_expires_at_ms: task.lease_expires_at,
        lease_ttl_ms: shared.config.lease_ttl.as_millis() as u64,
        heartbeat_interval_ms: shared.config.heartbeat_interval.as_millis() as u64,
        config_json: task.config.clone(),
        dataset_key,
        style_keys: serde_json::from_str(&style_keys).unwrap_or_default(),
        inputs,
        checkpoint_prefix: format!("{}ckpt/", task.output_prefix),
        output_prefix: task.output_prefix,
        memory_bytes: task.memory_bytes as u64,
        object_store_url: shared.storage.url().to_string(),
    })
}

/// The lease a heartbeat, completion or failure refers to.
struct HeldLease {
    task: TaskRow,
    /// The job was cancelled while the task ran.
    cancelled: bool,
}

/// Checks that `worker_id` holds the lease of `task_id` under `token`. An expired lease is
/// requeued (or failed) here and reported as lost; the caller must commit in that case.
async fn check_lease(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    worker_id: &str,
    task_id: u64,
    token: u64,
    now: i64,
) -> Result<Result<HeldLease, Status>, sqlx::Error> {
    let task: Option<TaskRow> = sqlx::query_as("SELECT * FROM tasks WHERE id = ?")
        .bind(task_id as i64)
        .fetch_optional(&mut *conn)
        .await?;
    let Some(task) = task else {
        return Ok(Err(Status::not_found(format!("task {task_id} not found"))));
    };
    if task.fencing_token as u64 != token || task.worker_id != worker_id {
        // Who holds the lease now, and under which token, is not the caller's business.
        return Ok(Err(Status::failed_precondition(format!(
            "stale lease: task {task_id} is no longer held under fencing token {token} by \
             {worker_id:?}"
        ))));
    }
    match task.state.as_str() {
        task_state::CANCELLED => Ok(Ok(HeldLease {
            task,
            cancelled: true,
        })),
        task_state::LEASED if task.lease_expires_at >= now => Ok(Ok(HeldLease {
            task,
            cancelled: false,
        })),
        task_state::LEASED => {
            expire_task(conn, batch, &task).await?;
            Ok(Err(Status::failed_precondition(format!(
                "lease of task {task_id} expired {} ms ago",
                now - task.lease_expires_at
            ))))
        }
        state => Ok(Err(Status::failed_precondition(format!(
            "lease of task {task_id} is no longer held: the task is {state}"
        )))),
    }
}

/// Records progress and extends the lease. Returns `(cancel, lease_expires_at_ms)`.
pub async fn heartbeat(
    shared: &Shared,
    request: &pb::HeartbeatRequest,
) -> Result<(bool, i64), Status> {
    let ttl = shared.config.lease_ttl.as_millis() as i64;
    let interval = shared.config.progress_event_interval.as_millis() as i64;
    let progress = request.progress.as_ref().map(StoredProgress::from_pb);
    let request = request.clone();
    let (outcome, checked) = shared
        .writer
        .write(move |conn, batch| {
            let (request, progress) = (request.clone(), progress.clone());
            async move {
                heartbeat_in(conn, batch, &request, progress.as_ref(), ttl, interval).await
            }
            .boxed()
        })
        .await?;
    if checked {
        // The slow path may have requeued an expired lease.
        shared.wake_workers();
    }
    outcome
}

/// The heartbeat's work. Returns the reply and whether the lease had to be checked (the slow
/// path, which may requeue an expired lease).
async fn heartbeat_in(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    request: &pb::HeartbeatRequest,
    progress: Option<&StoredProgress>,
    ttl: i64,
    interval: i64,
) -> OpResult<(Result<(bool, i64), Status>, bool)> {
    let now = now_ms();
    let expires = now + ttl;
    // The common case in one statement: the lease is held and current. Progress is always
    // kept on the row; `progress_event_at` moves (and an event is stored) at most once per
    // interval. Both assignments see the old row, so `progress_event_stored` is the decision.
    let extended: Option<(String, String, i64, bool)> = sqlx::query_as(
        "UPDATE tasks SET lease_expires_at = ?1, progress = COALESCE(?2, progress), \
         progress_event_stored = (?2 IS NOT NULL AND ?3 - progress_event_at >= ?4), \
         progress_event_at = CASE WHEN ?2 IS NOT NULL AND ?3 - progress_event_at >= ?4 \
           THEN ?3 ELSE progress_event_at END \
         WHERE id = ?5 AND fencing_token = ?6 AND worker_id = ?7 AND state = 'leased' \
         AND lease_expires_at >= ?3 RETURNING job_id, stage, attempt, progress_event_stored",
    )
    .bind(expires)
    .bind(progress.map(StoredProgress::to_json))
    .bind(now)
    .bind(interval)
    .bind(request.task_id as i64)
    .bind(request.fencing_token as i64)
    .bind(&request.worker_id)
    .fetch_optional(&mut *conn)
    .await?;
    let Some((job_id, stage, attempt, stored)) = extended else {
        // Not held: find out why (cancelled, expired, stale) for the reply.
        let held = check_lease(
            conn,
            batch,
            &request.worker_id,
            request.task_id,
            request.fencing_token,
            now,
        )
        .await?;
        let reply = held.map(|held| (held.cancelled, held.task.lease_expires_at));
        return Ok((reply, true));
    };
    if let Some(progress) = progress {
        let event = NewEvent {
            job_id: &job_id,
            kind: TASK_PROGRESS,
            task_id: request.task_id as i64,
            stage: &stage,
            task_state: task_state::LEASED,
            attempt,
            progress: Some(progress),
            ..Default::default()
        };
        if stored {
            batch.push(event);
        } else {
            batch.push_live(event);
        }
    }
    Ok((Ok((false, expires)), false))
}

/// Completes a task with its output manifest; dependents become ready and a job whose tasks
/// are all done succeeds.
pub async fn complete(shared: &Shared, request: &pb::CompleteTaskRequest) -> Result<(), Status> {
    for (i, artifact) in request.outputs.iter().enumerate() {
        crate::storage::check_key(&format!("outputs[{i}].key"), &artifact.key)?;
        crate::storage::check_sha256(&format!("outputs[{i}].sha256"), &artifact.sha256)?;
    }
    let now = now_ms();
    let metrics: std::collections::BTreeMap<&String, f64> = request
        .metrics
        .iter()
        .filter(|(_, v)| v.is_finite())
        .map(|(k, v)| (k, *v))
        .collect();
    let patch = serde_json::json!({"metrics": metrics, "eta_seconds": 0.0}).to_string();
    let request = request.clone();
    let (outcome, wake) = shared
        .writer
        .write(move |conn, batch| {
            let (request, patch) = (request.clone(), patch.clone());
            async move { complete_in(conn, batch, &request, &patch, now).await }.boxed()
        })
        .await?;
    if wake {
        shared.wake_workers();
    }
    let task = outcome?;
    let seconds = (now - task.leased_at).max(0) as f64 / 1000.0;
    metrics::histogram!("stylenerf_task_duration_seconds", "stage" => task.stage.clone())
        .record(seconds);
    metrics::counter!("stylenerf_tasks_finished_total", "stage" => task.stage, "outcome" => "succeeded")
        .increment(1);
    Ok(())
}

/// The completion's work. Returns the completed task (or why not) and whether waiting workers
/// should look again (dependents became ready, or an expired lease was requeued).
async fn complete_in(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    request: &pb::CompleteTaskRequest,
    patch: &str,
    now: i64,
) -> OpResult<(Result<TaskRow, Status>, bool)> {
    // The common case in one statement: the lease is held and current. The final metrics are
    // merged into the progress, and a known total counts as reached.
    let completed: Option<TaskRow> = sqlx::query_as(
        "UPDATE tasks SET state = 'succeeded', finished_at = ?, lease_expires_at = 0, error = '', \
         progress = json_set(json_patch(progress, ?), '$.step', \
           CASE WHEN COALESCE(json_extract(progress, '$.total'), 0) > 0 \
           THEN json_extract(progress, '$.total') \
           ELSE COALESCE(json_extract(progress, '$.step'), 0) END) \
         WHERE id = ? AND fencing_token = ? AND worker_id = ? AND state = 'leased' \
         AND lease_expires_at >= ? RETURNING *",
    )
    .bind(now)
    .bind(patch)
    .bind(request.task_id as i64)
    .bind(request.fencing_token as i64)
    .bind(&request.worker_id)
    .bind(now)
    .fetch_optional(&mut *conn)
    .await?;
    let Some(task) = completed else {
        // Not held: a cancelled task is fine, anything else is reported.
        let held = check_lease(
            conn,
            batch,
            &request.worker_id,
            request.task_id,
            request.fencing_token,
            now,
        )
        .await?;
        return Ok((held.map(|held| held.task), true));
    };
    for (i, artifact) in request.outputs.iter().enumerate() {
        if !artifact.key.starts_with(&task.output_prefix) {
            // Rolls the completion back.
            return Err(OpError::Abort(invalid(
                format!("outputs[{i}].key"),
                format!(
                    "{:?} is outside the task's output prefix {:?}",
                    artifact.key, task.output_prefix
                ),
            )));
        }
    }
    // A task completes once (fencing), so it has no earlier manifest to replace.
    for chunk in request.outputs.chunks(200) {
        let mut insert = sqlx::QueryBuilder::<sqlx::Sqlite>::new(
            "INSERT INTO artifacts (key, job_id, task_id, size, sha256) ",
        );
        insert.push_values(chunk, |mut row, a| {
            row.push_bind(a.key.clone())
                .push_bind(task.job_id.clone())
                .push_bind(task.id)
                .push_bind(a.size.min(i64::MAX as u64) as i64)
                .push_bind(a.sha256.clone());
        });
        insert.push(
            " ON CONFLICT (key) DO UPDATE SET job_id = excluded.job_id, \
             task_id = excluded.task_id, size = excluded.size, sha256 = excluded.sha256",
        );
        insert.build().execute(&mut *conn).await?;
    }
    batch.push(NewEvent::task(
        &task.job_id,
        task.id,
        &task.stage,
        task_state::SUCCEEDED,
        task.attempt,
        "",
    ));
    let promoted = promote_dependents(conn, batch, &task).await?;
    if !promoted {
        settle_job(conn, batch, &task.job_id).await?;
    }
    Ok((Ok(task), promoted))
}

/// Fails a task: retryable failures are requeued while attempts remain. Returns whether the
/// task was requeued.
pub async fn fail(shared: &Shared, request: &pb::FailTaskRequest) -> Result<bool, Status> {
    let request = request.clone();
    let (outcome, wake) = shared
        .writer
        .write(move |conn, batch| {
            let request = request.clone();
            async move { fail_in(conn, batch, &request).await }.boxed()
        })
        .await?;
    if wake {
        shared.wake_workers();
    }
    let (requeue, stage) = outcome?;
    if let Some(stage) = stage {
        metrics::counter!("stylenerf_tasks_finished_total", "stage" => stage,
            "outcome" => if requeue { "retried" } else { "failed" })
        .increment(1);
    }
    Ok(requeue)
}

/// The failure's work. Returns whether the task was requeued and its stage (none when the job
/// had been cancelled), and whether waiting workers should look again.
async fn fail_in(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    request: &pb::FailTaskRequest,
) -> OpResult<(Result<(bool, Option<String>), Status>, bool)> {
    let now = now_ms();
    let held = check_lease(
        conn,
        batch,
        &request.worker_id,
        request.task_id,
        request.fencing_token,
        now,
    )
    .await?;
    let held = match held {
        Ok(held) => held,
        Err(status) => return Ok((Err(status), true)),
    };
    if held.cancelled {
        return Ok((Ok((false, None)), false));
    }
    let task = held.task;
    let reason = if request.reason.is_empty() {
        "failed without a reason".to_string()
    } else {
        request.reason.chars().take(4000).collect()
    };
    let requeue = request.retryable && task.attempt < task.max_attempts;
    if requeue {
        requeue_task(conn, batch, &task, &reason).await?;
    } else {
        fail_task(conn, batch, &task, &reason).await?;
    }
    Ok((Ok((requeue, Some(task.stage))), requeue))
}

/// Puts a task back in the queue after a failed attempt.
async fn requeue_task(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    task: &TaskRow,
    reason: &str,
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "UPDATE tasks SET state = 'ready', ready_at = ?, lease_expires_at = 0, error = ? \
         WHERE id = ?",
    )
    .bind(now_ms())
    .bind(reason)
    .bind(task.id)
    .execute(&mut *conn)
    .await?;
    let message = format!("requeued after attempt {}: {reason}", task.attempt);
    batch.push(NewEvent::task(
        &task.job_id,
        task.id,
        &task.stage,
        task_state::READY,
        task.attempt,
        &message,
    ));
    Ok(())
}

/// Fails a task for good. A failed stage fails its job (cancelling the rest); a failed extra
/// render only settles the job.
async fn fail_task(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    task: &TaskRow,
    reason: &str,
) -> Result<(), sqlx::Error> {
    sqlx::query(
        "UPDATE tasks SET state = 'failed', finished_at = ?, lease_expires_at = 0, error = ? \
         WHERE id = ?",
    )
    .bind(now_ms())
    .bind(reason)
    .bind(task.id)
    .execute(&mut *conn)
    .await?;
    batch.push(NewEvent::task(
        &task.job_id,
        task.id,
        &task.stage,
        task_state::FAILED,
        task.attempt,
        reason,
    ));
    if task.core {
        let error = format!("{} failed: {reason}", task.stage);
        cancel_open_tasks(conn, batch, &task.job_id, &error).await?;
        set_job_state(conn, batch, &task.job_id, job_state::FAILED, Some(&error)).await
    } else {
        settle_job(conn, batch, &task.job_id).await
    }
}

/// Handles one expired lease: requeue with attempt + 1 or, out of attempts, fail.
async fn expire_task(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    task: &TaskRow,
) -> Result<(), sqlx::Error> {
    metrics::counter!("stylenerf_lease_expiries_total").increment(1);
    let reason = format!(
        "lease of worker {} expired (attempt {} of {})",
        task.worker_id, task.attempt, task.max_attempts
    );
    if task.attempt < task.max_attempts {
        requeue_task(conn, batch, task, &reason).await
    } else {
        fail_task(conn, batch, task, &reason).await
    }
}

/// Requeues or fails every task whose lease expired before `now`. Returns whether any task
/// went back to the queue.
pub async fn expire_leases(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    now: i64,
) -> Result<bool, sqlx::Error> {
    let expired: Vec<TaskRow> =
        sqlx::query_as("SELECT * FROM tasks WHERE state = 'leased' AND lease_expires_at < ?")
            .bind(now)
            .fetch_all(&mut *conn)
            .await?;
    for task in &expired {
        expire_task(conn, batch, task).await?;
    }
    Ok(!expired.is_empty())
}

/// The reaper's periodic pass.
pub async fn reap(shared: &Shared) -> Result<(), Status> {
    let requeued = shared
        .writer
        .write(|conn, batch| async move { Ok(expire_leases(conn, batch, now_ms()).await?) }.boxed())
        .await?;
    shared
        .writer
        .write(|conn, batch| {
            async move { Ok(expire_deadlines(conn, batch, now_ms()).await?) }.boxed()
        })
        .await?;
    if requeued {
        shared.wake_workers();
    }
    Ok(())
}

/// Fails the unfinished jobs whose deadline has passed; their running tasks are told to stop
/// through their workers' next heartbeat.
async fn expire_deadlines(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    now: i64,
) -> Result<(), sqlx::Error> {
    let late: Vec<String> = sqlx::query_scalar(
        "SELECT id FROM jobs WHERE deadline_at > 0 AND deadline_at < ? \
         AND state IN ('queued', 'running') LIMIT 100",
    )
    .bind(now)
    .fetch_all(&mut *conn)
    .await?;
    for job_id in &late {
        let reason = "deadline passed: the job did not finish by its deadline_at_ms";
        cancel_open_tasks(conn, batch, job_id, reason).await?;
        set_job_state(conn, batch, job_id, job_state::FAILED, Some(reason)).await?;
    }
    Ok(())
}

/// Makes the pending dependents of a succeeded task ready when all their dependencies
/// succeeded. Returns whether any became ready.
async fn promote_dependents(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    task: &TaskRow,
) -> Result<bool, sqlx::Error> {
    let promoted: Vec<(i64, String)> = sqlx::query_as(
        "UPDATE tasks SET state = 'ready', ready_at = ? WHERE state = 'pending' \
         AND id IN (SELECT task_id FROM task_deps WHERE depends_on = ?) \
         AND NOT EXISTS (SELECT 1 FROM task_deps d JOIN tasks p ON p.id = d.depends_on \
                         WHERE d.task_id = tasks.id AND p.state != 'succeeded') \
         RETURNING id, stage",
    )
    .bind(now_ms())
    .bind(task.id)
    .fetch_all(&mut *conn)
    .await?;
    for (id, stage) in &promoted {
        batch.push(NewEvent::task(
            &task.job_id,
            *id,
            stage,
            task_state::READY,
            0,
            "inputs ready",
        ));
    }
    Ok(!promoted.is_empty())
}

/// Marks an active job succeeded once none of its tasks is pending, ready or leased.
async fn settle_job(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    job_id: &str,
) -> Result<(), sqlx::Error> {
    let (state, open, rendered): (String, i64, i64) = sqlx::query_as(
        "SELECT state, (SELECT COUNT(*) FROM tasks WHERE job_id = jobs.id \
         AND state IN ('pending', 'ready', 'leased')), \
         (SELECT COUNT(*) FROM tasks WHERE job_id = jobs.id AND stage = 'render_stylized' \
         AND state = 'succeeded') FROM jobs WHERE id = ?",
    )
    .bind(job_id)
    .fetch_one(&mut *conn)
    .await?;
    if open == 0 && !job_state::is_terminal(&state) {
        // A job whose final render failed and was rendered again succeeds once a render has.
        if rendered > 0 {
            set_job_state(conn, batch, job_id, job_state::SUCCEEDED, None).await?;
        } else {
            let error = "render_stylized failed: no render of the job succeeded";
            set_job_state(conn, batch, job_id, job_state::FAILED, Some(error)).await?;
        }
    }
    Ok(())
}

/// The device class of a job's tasks in metrics: `cuda` if it needs a CUDA worker, else `cpu`
/// (any worker may run it; the CPU pool is the one to scale for it).
fn device_class(require_cuda: bool) -> &'static str {
    if require_cuda {
        "cuda"
    } else {
        "cpu"
    }
}

/// A job's required worker labels as one metric label value: sorted, comma-joined.
fn label_set(labels_json: &str) -> String {
    let mut labels: Vec<String> = serde_json::from_str(labels_json).unwrap_or_default();
    labels.sort();
    labels.dedup();
    labels.join(",")
}

/// Refreshes the scheduling gauges: queue depth and running tasks per stage, device class and
/// required label set (every stage has its zero series for each class, so that an autoscaler
/// reads 0, not "no data"), and live workers.
pub async fn refresh_gauges(shared: &Shared) -> Result<(), sqlx::Error> {
    let counts: Vec<(String, String, bool, String, i64)> = sqlx::query_as(
        "SELECT t.stage, t.state, j.require_cuda, j.labels, COUNT(*) FROM tasks t \
         JOIN jobs j ON j.id = t.job_id WHERE t.state IN ('ready', 'leased') \
         GROUP BY t.stage, t.state, j.require_cuda, j.labels",
    )
    .fetch_all(&shared.db.read)
    .await?;
    // (stage, device, labels) -> (ready, leased)
    let mut series: BTreeMap<(&'static str, &'static str, String), (f64, f64)> = BTreeMap::new();
    for stage in Stage::ALL {
        for device in ["cpu", "cuda"] {
            series.insert((stage.name(), device, String::new()), (0.0, 0.0));
        }
    }
    for (stage, state, require_cuda, labels, count) in counts {
        let Some(stage) = Stage::parse(&stage) else {
            continue;
        };
        let entry = series
            .entry((stage.name(), device_class(require_cuda), label_set(&labels)))
            .or_default();
        if state == task_state::READY {
            entry.0 += count as f64;
        } else {
            entry.1 += count as f64;
        }
    }
    {
        let mut previous = shared
            .queue_series
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        for key in previous.iter() {
            series.entry(key.clone()).or_default();
        }
        for ((stage, device, labels), (ready, leased)) in &series {
            let labels = [
                ("stage", stage.to_string()),
                ("device", device.to_string()),
                ("labels", labels.clone()),
            ];
            metrics::gauge!("stylenerf_queue_depth", &labels).set(*ready);
            metrics::gauge!("stylenerf_tasks_running", &labels).set(*leased);
        }
        *previous = series
            .into_iter()
            .filter(|(_, (ready, leased))| *ready > 0.0 || *leased > 0.0)
            .map(|(key, _)| key)
            .collect();
    }
    let since = now_ms() - shared.config.worker_timeout.as_millis() as i64;
    // Live: asked for work recently, or holds a lease its heartbeats keep current.
    let live: i64 = sqlx::query_scalar(
        "SELECT COUNT(*) FROM workers w WHERE last_seen_at >= ? OR EXISTS \
         (SELECT 1 FROM tasks t WHERE t.worker_id = w.id AND t.state = 'leased' \
          AND t.lease_expires_at >= ?)",
    )
    .bind(since)
    .bind(now_ms())
    .fetch_one(&shared.db.read)
    .await?;
    metrics::gauge!("stylenerf_live_workers").set(live as f64);
    Ok(())
}
