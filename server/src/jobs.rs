//! Jobs in the database: creating a job with a task per stage of its source and their dependencies,
//! loading jobs and tasks as protocol messages, listing, cancelling, and adding renders.

use crate::auth::Principal;
use crate::errors::{internal, job_not_found};
use crate::events::{commit, EventBatch, NewEvent, JOB_CREATED, JOB_STATE};
use crate::model::{
    job_state, job_state_pb, now_ms, stage_pb, task_state, task_state_pb, Stage, StoredProgress,
};
use crate::state::Shared;
use sqlx::{SqliteConnection, SqlitePool};
use std::collections::HashMap;
use std::sync::LazyLock;
use stylenerf_plan::Source;
use stylenerf_proto::v1 as pb;
use tonic::Status;

/// A row of the `jobs` table.
#[derive(Debug, Clone, sqlx::FromRow)]
pub struct JobRow {
    pub row: i64,
    pub id: String,
    pub owner: String,
    pub name: String,
    pub state: String,
    pub preset: String,
    pub overrides: String,
    pub require_cuda: bool,
    pub labels: String,
    pub memory_bytes: i64,
    pub dataset_key: String,
    pub style_keys: String,
    pub idempotency_key: Option<String>,
    pub error: String,
    pub created_at: i64,
    pub updated_at: i64,
    pub finished_at: i64,
    /// The integrator's key-value pairs, a JSON object.
    pub metadata: String,
    pub priority: i64,
    /// Epoch ms; 0 = none.
    pub deadline_at: i64,
}

/// A row of the `tasks` table.
#[derive(Debug, Clone, sqlx::FromRow, serde::Deserialize)]
pub struct TaskRow {
    pub id: i64,
    pub job_id: String,
    pub stage: String,
    pub state: String,
    pub core: bool,
    pub config: String,
    pub memory_bytes: i64,
    pub output_prefix: String,
    pub attempt: i64,
    pub max_attempts: i64,
    pub fencing_token: i64,
    pub worker_id: String,
    pub lease_expires_at: i64,
    pub leased_at: i64,
    pub progress: String,
    pub error: String,
    pub created_at: i64,
    pub started_at: i64,
    pub finished_at: i64,
}

/// Everything needed to insert a job; inputs are already stored under `jobs/<id>/inputs/`.
#[derive(Debug)]
pub struct NewJob {
    pub id: String,
    pub owner: String,
    pub name: String,
    pub preset: String,
    pub overrides: serde_json::Value,
    pub requirements: pb::Requirements,
    pub dataset_key: String,
    pub style_keys: Vec<String>,
    pub idempotency_key: Option<String>,
    /// Extra configuration of the final render (`camera_path`, `style_blend`).
    pub render: serde_json::Map<String, serde_json::Value>,
    /// The message of the `job_created` event (what the job waits for, when it may wait long).
    pub note: String,
    /// Where the job's events are posted, if anywhere.
    pub webhook: Option<crate::webhooks::NewWebhook>,
    /// The integrator's key-value pairs.
    pub metadata: std::collections::BTreeMap<String, String>,
    /// Scheduling priority (-100..=100, higher first).
    pub priority: i32,
    /// Epoch ms by which the job must end; 0 = none.
    pub deadline_at: i64,
    /// Size of the copied inputs (counted in the owner's stored bytes).
    pub input_bytes: u64,
}

/// The job of `owner` with this idempotency key, if any.
pub async fn find_by_idempotency_key(
    pool: &SqlitePool,
    owner: &str,
    key: &str,
) -> Result<Option<JobRow>, Status> {
    sqlx::query_as("SELECT * FROM jobs WHERE owner = ? AND idempotency_key = ?")
        .bind(owner)
        .bind(key)
        .fetch_optional(pool)
        .await
        .map_err(internal)
}

/// Output prefix of a stage task.
pub fn stage_prefix(job_id: &str, stage: Stage) -> String {
    format!("jobs/{job_id}/{}/", stage.name())
}

/// The JSON configuration handed to the worker of one task.
fn task_config(
    stage: Stage,
    preset: &str,
    overrides: &serde_json::Value,
    num_styles: usize,
    extra: &serde_json::Map<String, serde_json::Value>,
) -> String {
    let mut config = serde_json::Map::new();
    config.insert("stage".into(), stage.name().into());
    config.insert("preset".into(), preset.into());
    config.insert("overrides".into(), overrides.clone());
    config.insert("num_styles".into(), num_styles.into());
    for (k, v) in extra {
        config.insert(k.clone(), v.clone());
    }
    serde_json::Value::Object(config).to_string()
}

/// Inserts a job, a task per stage (those without upstream stages ready, the others pending on
/// the tasks of their upstream stages) and the creation events. Returns `None` when the
/// idempotency key is already taken.
pub async fn insert_job(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    job: &NewJob,
    max_attempts: u32,
) -> Result<bool, sqlx::Error> {
    let now = now_ms();
    let inserted = sqlx::query(
        "INSERT INTO jobs (id, owner, name, state, preset, overrides, require_cuda, labels, \
         memory_bytes, dataset_key, style_keys, idempotency_key, created_at, updated_at, \
         metadata, priority, deadline_at, input_bytes) \
         VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?) \
         ON CONFLICT (owner, idempotency_key) WHERE idempotency_key IS NOT NULL DO NOTHING",
    )
    .bind(&job.id)
    .bind(&job.owner)
    .bind(&job.name)
    .bind(job_state::QUEUED)
    .bind(&job.preset)
    .bind(job.overrides.to_string())
    .bind(job.requirements.require_cuda)
    .bind(serde_json::to_string(&job.requirements.labels).unwrap_or_else(|_| "[]".into()))
    .bind(job.requirements.memory_bytes.min(i64::MAX as u64) as i64)
    .bind(&job.dataset_key)
    .bind(serde_json::to_string(&job.style_keys).unwrap_or_else(|_| "[]".into()))
    .bind(&job.idempotency_key)
    .bind(now)
    .bind(now)
    .bind(serde_json::to_string(&job.metadata).unwrap_or_else(|_| "{}".into()))
    .bind(job.priority)
    .bind(job.deadline_at)
    .bind(job.input_bytes.min(i64::MAX as u64) as i64)
    .execute(&mut *conn)
    .await?
    .rows_affected();
    if inserted == 0 {
        return Ok(false);
    }
    if let Some(webhook) = &job.webhook {
        crate::webhooks::subscribe(conn, &job.id, webhook).await?;
    }
    batch.push(NewEvent::job(
        &job.id,
        JOB_CREATED,
        job_state::QUEUED,
        &job.note,
    ));
    let no_extra = serde_json::Map::new();
    let mut ids: Vec<(Stage, i64)> = Vec::new();
    let source = Source::of_input_key(&job.dataset_key);
    for stage in source.stages() {
        let upstream = source.upstream(stage);
        let root = upstream.is_empty();
        let state = if root {
            task_state::READY
        } else {
            task_state::PENDING
        };
        let memory = match job.requirements.memory_bytes {
            0 => stage.default_memory_bytes(),
            m => m.min(i64::MAX as u64) as i64,
        };
        let extra = if stage == Stage::RenderStylized {
            &job.render
        } else {
            &no_extra
        };
        let config = task_config(
            stage,
            &job.preset,
            &job.overrides,
            job.style_keys.len(),
            extra,
        );
        let id: i64 = sqlx::query_scalar(
            "INSERT INTO tasks (job_id, stage, state, core, config, memory_bytes, output_prefix, \
             max_attempts, ready_at, created_at, priority) VALUES (?, ?, ?, 1, ?, ?, ?, ?, ?, ?, ?) \
             RETURNING id",
        )
        .bind(&job.id)
        .bind(stage.name())
        .bind(state)
        .bind(config)
        .bind(memory)
        .bind(stage_prefix(&job.id, stage))
        .bind(max_attempts as i64)
        .bind(if root { now } else { 0 })
        .bind(now)
        .bind(job.priority)
        .fetch_one(&mut *conn)
        .await?;
        // The stages come in dependency order: every upstream task is already inserted.
        for (_, dep) in ids.iter().filter(|(s, _)| upstream.contains(s)) {
            sqlx::query("INSERT INTO task_deps (task_id, depends_on) VALUES (?, ?)")
                .bind(id)
                .bind(dep)
                .execute(&mut *conn)
                .await?;
        }
        batch.push(NewEvent::task(
            &job.id,
            id,
            stage.name(),
            state,
            0,
            "task created",
        ));
        ids.push((stage, id));
    }
    Ok(true)
}

/// Loads a job the caller may see, or NOT_FOUND.
pub async fn visible_job(
    pool: &SqlitePool,
    caller: &Principal,
    job_id: &str,
) -> Result<JobRow, Status> {
    let row: Option<JobRow> = sqlx::query_as("SELECT * FROM jobs WHERE id = ?")
        .bind(job_id)
        .fetch_optional(pool)
        .await
        .map_err(internal)?;
    match row {
        Some(job) if caller.can_see(&job.owner) => Ok(job),
        _ => Err(job_not_found(job_id)),
    }
}

/// A JSON array of the tasks of the job `job` (an SQL expression), in id order, each a
/// `TaskRow` object with `deps` (comma-separated ids it depends on) and `outputs` (its manifest
/// as `[key, size, sha256]` arrays): a job's tasks come back in one row.
fn tasks_json(job: &str) -> String {
    format!(
        "(SELECT json_group_array(json_object('id', t.id, 'job_id', t.job_id, \
         'stage', t.stage, 'state', t.state, 'core', json(CASE WHEN t.core THEN 'true' \
         ELSE 'false' END), 'config', t.config, 'memory_bytes', t.memory_bytes, \
         'output_prefix', t.output_prefix, 'attempt', t.attempt, 'max_attempts', \
         t.max_attempts, 'fencing_token', t.fencing_token, 'worker_id', t.worker_id, \
         'lease_expires_at', t.lease_expires_at, 'leased_at', t.leased_at, \
         'progress', t.progress, 'error', t.error, 'created_at', t.created_at, \
         'started_at', t.started_at, 'finished_at', t.finished_at, \
         'deps', COALESCE((SELECT group_concat(depends_on) FROM task_deps \
           WHERE task_id = t.id), ''), \
         'outputs', json((SELECT json_group_array(json_array(key, size, sha256)) FROM \
           (SELECT key, size, sha256 FROM artifacts WHERE task_id = t.id ORDER BY key))))) \
         FROM (SELECT * FROM tasks WHERE job_id = {job} ORDER BY id) t)"
    )
}

/// One element of `tasks_json`.
#[derive(serde::Deserialize)]
struct TaskJson {
    #[serde(flatten)]
    task: TaskRow,
    deps: String,
    outputs: Vec<(String, u64, String)>,
}

/// Protocol tasks from a `tasks_json` array.
fn parse_tasks(json: &str) -> Result<Vec<pb::Task>, Status> {
    let tasks: Vec<TaskJson> = serde_json::from_str(json).map_err(internal)?;
    Ok(tasks
        .into_iter()
        .map(|t| {
            let outputs = t
                .outputs
                .into_iter()
                .map(|(key, size, sha256)| pb::Artifact { key, size, sha256 })
                .collect();
            let mut depends_on: Vec<u64> =
                t.deps.split(',').filter_map(|d| d.parse().ok()).collect();
            depends_on.sort_unstable();
            task_to_pb(t.task, outputs, depends_on)
        })
        .collect())
}

/// The tasks of a job as protocol messages, with dependencies and output manifests.
pub async fn load_tasks(pool: &SqlitePool, job_id: &str) -> Result<Vec<pb::Task>, Status> {
    static QUERY: LazyLock<String> = LazyLock::new(|| format!("SELECT {}", tasks_json("?")));
    let json: String = sqlx::query_scalar(QUERY.as_str())
        .bind(job_id)
        .fetch_one(pool)
        .await
        .map_err(internal)?;
    parse_tasks(&json)
}

/// Recorded output manifests of a job's tasks, by task id.
pub async fn load_artifacts(
    pool: &SqlitePool,
    job_id: &str,
) -> Result<HashMap<i64, Vec<pb::Artifact>>, Status> {
    let rows: Vec<(i64, String, i64, String)> = sqlx::query_as(
        "SELECT task_id, key, size, sha256 FROM artifacts WHERE job_id = ? ORDER BY key",
    )
    .bind(job_id)
    .fetch_all(pool)
    .await
    .map_err(internal)?;
    let mut out: HashMap<i64, Vec<pb::Artifact>> = HashMap::new();
    for (task, key, size, sha256) in rows {
        out.entry(task).or_default().push(pb::Artifact {
            key,
            size: size as u64,
            sha256,
        });
    }
    Ok(out)
}

pub fn task_to_pb(row: TaskRow, outputs: Vec<pb::Artifact>, depends_on: Vec<u64>) -> pb::Task {
    pb::Task {
        id: row.id as u64,
        job_id: row.job_id,
        stage: stage_pb(&row.stage),
        state: task_state_pb(&row.state),
        attempt: row.attempt as u32,
        max_attempts: row.max_attempts as u32,
        progress: Some(StoredProgress::parse(&row.progress).to_pb()),
        worker_id: row.worker_id,
        lease_expires_at_ms: row.lease_expires_at,
        created_at_ms: row.created_at,
        started_at_ms: row.started_at,
        finished_at_ms: row.finished_at,
        error: row.error,
        output_prefix: row.output_prefix,
        outputs,
        depends_on,
        config_json: row.config,
    }
}

pub fn job_to_pb(row: JobRow, tasks: Vec<pb::Task>) -> pb::Job {
    pb::Job {
        id: row.id,
        name: row.name,
        owner: row.owner,
        state: job_state_pb(&row.state),
        preset: row.preset,
        config_overrides_json: row.overrides,
        requirements: Some(pb::Requirements {
            require_cuda: row.require_cuda,
            labels: serde_json::from_str(&row.labels).unwrap_or_default(),
            memory_bytes: row.memory_bytes as u64,
        }),
        dataset_key: row.dataset_key,
        style_keys: serde_json::from_str(&row.style_keys).unwrap_or_default(),
        idempotency_key: row.idempotency_key.unwrap_or_default(),
        created_at_ms: row.created_at,
        updated_at_ms: row.updated_at,
        finished_at_ms: row.finished_at,
        error: row.error,
        tasks,
        metadata: serde_json::from_str(&row.metadata).unwrap_or_default(),
        priority: row.priority as i32,
        deadline_at_ms: row.deadline_at,
    }
}

/// A job with its tasks, if the caller may see it (one query: `GetJob` is the hot read).
pub async fn get_job(shared: &Shared, caller: &Principal, job_id: &str) -> Result<pb::Job, Status> {
    #[derive(sqlx::FromRow)]
    struct JobWithTasks {
        #[sqlx(flatten)]
        job: JobRow,
        tasks: String,
    }
    static QUERY: LazyLock<String> = LazyLock::new(|| {
        format!(
            "SELECT j.*, {} AS tasks FROM jobs j WHERE j.id = ?",
            tasks_json("j.id")
        )
    });
    let row: Option<JobWithTasks> = sqlx::query_as(QUERY.as_str())
        .bind(job_id)
        .fetch_optional(&shared.db.read)
        .await
        .map_err(internal)?;
    match row {
        Some(row) if caller.can_see(&row.job.owner) => {
            Ok(job_to_pb(row.job, parse_tasks(&row.tasks)?))
        }
        _ => Err(job_not_found(job_id)),
    }
}

/// Lists jobs newest first. `owner` is `None` for an admin listing everyone's jobs.
pub async fn list_jobs(
    pool: &SqlitePool,
    owner: Option<&str>,
    states: &[&str],
    metadata: &HashMap<String, String>,
    before_row: i64,
    limit: i64,
) -> Result<Vec<JobRow>, Status> {
    let mut query = sqlx::QueryBuilder::<sqlx::Sqlite>::new("SELECT * FROM jobs WHERE row < ");
    query.push_bind(before_row);
    if let Some(owner) = owner {
        query.push(" AND owner = ").push_bind(owner.to_string());
    }
    if !states.is_empty() {
        query.push(" AND state IN (");
        let mut list = query.separated(", ");
        for state in states {
            list.push_bind(state.to_string());
        }
        query.push(")");
    }
    // Keys are checked to be `[A-Za-z0-9._/-]`: safe inside the quoted JSON path.
    for (key, value) in metadata {
        query
            .push(" AND json_extract(metadata, '$.\"' || ")
            .push_bind(key.clone())
            .push(" || '\"') = ")
            .push_bind(value.clone());
    }
    query.push(" ORDER BY row DESC LIMIT ").push_bind(limit);
    query
        .build_query_as()
        .fetch_all(pool)
        .await
        .map_err(internal)
}

/// Moves a job to a terminal or running state and records the event.
pub async fn set_job_state(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    job_id: &str,
    state: &str,
    error: Option<&str>,
) -> Result<(), sqlx::Error> {
    let now = now_ms();
    let finished = if job_state::is_terminal(state) {
        now
    } else {
        0
    };
    let created_at: Option<i64> = sqlx::query_scalar(
        "UPDATE jobs SET state = ?, updated_at = ?, finished_at = ?, error = COALESCE(?, error) \
         WHERE id = ? RETURNING created_at",
    )
    .bind(state)
    .bind(now)
    .bind(finished)
    .bind(error)
    .bind(job_id)
    .fetch_optional(&mut *conn)
    .await?;
    if let Some(created_at) = created_at.filter(|_| finished > 0) {
        metrics::histogram!("stylenerf_job_duration_seconds", "outcome" => state.to_string())
            .record((now - created_at).max(0) as f64 / 1000.0);
    }
    batch.push(NewEvent::job(job_id, JOB_STATE, state, error.unwrap_or("")));
    Ok(())
}

/// Cancels every unfinished task of a job (leased ones keep their lease so that the worker
/// learns of the cancellation from its next heartbeat).
pub async fn cancel_open_tasks(
    conn: &mut SqliteConnection,
    batch: &mut EventBatch,
    job_id: &str,
    reason: &str,
) -> Result<(), sqlx::Error> {
    let cancelled: Vec<(i64, String, i64)> = sqlx::query_as(
        "UPDATE tasks SET state = 'cancelled', finished_at = ? \
         WHERE job_id = ? AND state IN ('pending', 'ready', 'leased') RETURNING id, stage, attempt",
    )
    .bind(now_ms())
    .bind(job_id)
    .fetch_all(&mut *conn)
    .await?;
    for (id, stage, attempt) in cancelled {
        batch.push(NewEvent::task(
            job_id,
            id,
            &stage,
            task_state::CANCELLED,
            attempt,
            reason,
        ));
    }
    Ok(())
}

/// Cancels a job the caller may see; a terminal job is returned unchanged.
pub async fn cancel_job(
    shared: &Shared,
    caller: &Principal,
    job_id: &str,
    reason: &str,
) -> Result<(), Status> {
    let mut tx = shared.db.write.begin().await.map_err(internal)?;
    let job: Option<(String, String)> =
        sqlx::query_as("SELECT owner, state FROM jobs WHERE id = ?")
            .bind(job_id)
            .fetch_optional(&mut *tx)
            .await
            .map_err(internal)?;
    let state = match job {
        Some((owner, state)) if caller.can_see(&owner) => state,
        _ => return Err(job_not_found(job_id)),
    };
    if job_state::is_terminal(&state) {
        return Ok(());
    }
    let reason = if reason.is_empty() {
        format!("cancelled by {}", caller.name)
    } else {
        format!("cancelled by {}: {reason}", caller.name)
    };
    let mut batch = EventBatch::default();
    cancel_open_tasks(&mut tx, &mut batch, job_id, &reason)
        .await
        .map_err(internal)?;
    set_job_state(
        &mut tx,
        &mut batch,
        job_id,
        job_state::CANCELLED,
        Some(&reason),
    )
    .await
    .map_err(internal)?;
    commit(tx, &mut batch).await.map_err(internal)?;
    shared.publish(batch);
    Ok(())
}

/// Adds a `render_stylized` task to a job whose mutual learning succeeded (also when the job
/// then failed in its final render). `extra` holds the
/// render's `camera_path`/`style_blend`, `overrides` the job's overrides merged with the
/// render's.
pub async fn add_render(
    shared: &Shared,
    caller: &Principal,
    job_id: &str,
    overrides: serde_json::Value,
    extra: serde_json::Map<String, serde_json::Value>,
) -> Result<pb::Task, Status> {
    let mut tx = shared.db.write.begin().await.map_err(internal)?;
    let job: Option<JobRow> = sqlx::query_as("SELECT * FROM jobs WHERE id = ?")
        .bind(job_id)
        .fetch_optional(&mut *tx)
        .await
        .map_err(internal)?;
    let job = match job {
        Some(job) if caller.can_see(&job.owner) => job,
        _ => return Err(job_not_found(job_id)),
    };
    // A job that failed in its final render can render again: its trained models are there.
    if job.state == job_state::CANCELLED {
        return Err(Status::failed_precondition(format!(
            "job {job_id} is cancelled; only a running, succeeded or failed job can render"
        )));
    }
    let mutual: Option<(i64, String)> = sqlx::query_as(
        "SELECT id, state FROM tasks WHERE job_id = ? AND stage = 'mutual_learning' AND core = 1",
    )
    .bind(job_id)
    .fetch_optional(&mut *tx)
    .await
    .map_err(internal)?;
    let mutual_id = match mutual {
        Some((id, state)) if state == task_state::SUCCEEDED => id,
        _ => {
            return Err(Status::failed_precondition(format!(
                "job {job_id}: the mutual_learning stage has not succeeded yet"
            )))
        }
    };
    let style_count = serde_json::from_str::<Vec<String>>(&job.style_keys)
        .map(|v| v.len())
        .unwrap_or(0);
    let memory = match job.memory_bytes {
        0 => Stage::RenderStylized.default_memory_bytes(),
        m => m,
    };
    let now = now_ms();
    let config = task_config(
        Stage::RenderStylized,
        &job.preset,
        &overrides,
        style_count,
        &extra,
    );
    let id: i64 = sqlx::query_scalar(
        "INSERT INTO tasks (job_id, stage, state, core, config, memory_bytes, output_prefix, \
         max_attempts, ready_at, created_at, priority) VALUES (?, 'render_stylized', 'ready', 0, \
         ?, ?, '', ?, ?, ?, ?) RETURNING id",
    )
    .bind(job_id)
    .bind(config)
    .bind(memory)
    .bind(shared.config.max_attempts as i64)
    .bind(now)
    .bind(now)
    .bind(job.priority)
    .fetch_one(&mut *tx)
    .await
    .map_err(internal)?;
    let prefix = format!("jobs/{job_id}/render_stylized/{id}/");
    sqlx::query("UPDATE tasks SET output_prefix = ? WHERE id = ?")
        .bind(&prefix)
        .bind(id)
        .execute(&mut *tx)
        .await
        .map_err(internal)?;
    sqlx::query("INSERT INTO task_deps (task_id, depends_on) VALUES (?, ?)")
        .bind(id)
        .bind(mutual_id)
        .execute(&mut *tx)
        .await
        .map_err(internal)?;
    let mut batch = EventBatch::default();
    batch.push(NewEvent::task(
        job_id,
        id,
        Stage::RenderStylized.name(),
        task_state::READY,
        0,
        "render requested",
    ));
    if job_state::is_terminal(&job.state) {
        set_job_state(&mut tx, &mut batch, job_id, job_state::RUNNING, Some(""))
            .await
            .map_err(internal)?;
    }
    let row: TaskRow = sqlx::query_as("SELECT * FROM tasks WHERE id = ?")
        .bind(id)
        .fetch_one(&mut *tx)
        .await
        .map_err(internal)?;
    commit(tx, &mut batch).await.map_err(internal)?;
    shared.publish(batch);
    shared.wake_workers();
    Ok(task_to_pb(row, Vec::new(), vec![mutual_id as u64]))
}
