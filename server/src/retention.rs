//! Deleting user data: `DeleteJob` (a finished job's objects, then its rows) and the retention
//! loop (`--retention-days`), which deletes finished jobs and uploads by age the same way.
//!
//! Objects go first, rows last, in one transaction that checks again that the job is still
//! finished: an interrupted deletion leaves the job listed (with fewer objects) and can be
//! repeated; nothing is left in the store that no row points to.

use crate::auth::Principal;
use crate::errors::{internal, job_not_found};
use crate::model::{job_state, now_ms};
use crate::state::Shared;
use std::sync::Arc;
use std::time::Duration;
use stylenerf_proto::v1 as pb;
use tonic::Status;

/// Deletes a finished job the caller can see: its objects, then its rows.
pub async fn delete_job(
    shared: &Shared,
    caller: &Principal,
    job_id: &str,
) -> Result<pb::DeleteJobResponse, Status> {
    let job: Option<(String, String)> =
        sqlx::query_as("SELECT owner, state FROM jobs WHERE id = ?")
            .bind(job_id)
            .fetch_optional(&shared.db.read)
            .await
            .map_err(internal)?;
    let state = match job {
        Some((owner, state)) if caller.can_see(&owner) => state,
        _ => return Err(job_not_found(job_id)),
    };
    let unfinished = || {
        Status::failed_precondition(format!(
            "job {job_id:?} is {state}: cancel it first (only succeeded, failed or cancelled \
             jobs can be deleted)"
        ))
    };
    if !job_state::is_terminal(&state) {
        return Err(unfinished());
    }
    let objects = shared.storage.list(&format!("jobs/{job_id}/")).await?;
    let mut reply = pb::DeleteJobResponse::default();
    for (key, size) in &objects {
        shared.storage.delete(key).await.map_err(internal)?;
        reply.deleted_objects += 1;
        reply.deleted_bytes += size;
    }
    let mut tx = shared.db.write.begin().await.map_err(internal)?;
    let still: Option<String> = sqlx::query_scalar("SELECT state FROM jobs WHERE id = ?")
        .bind(job_id)
        .fetch_optional(&mut *tx)
        .await
        .map_err(internal)?;
    match still {
        None => return Ok(reply),
        Some(s) if !job_state::is_terminal(&s) => return Err(unfinished()),
        Some(_) => {}
    }
    for statement in [
        "DELETE FROM task_deps WHERE task_id IN (SELECT id FROM tasks WHERE job_id = ?1) \
         OR depends_on IN (SELECT id FROM tasks WHERE job_id = ?1)",
        "DELETE FROM artifacts WHERE job_id = ?1",
        "DELETE FROM events WHERE job_id = ?1",
        "DELETE FROM webhook_deliveries WHERE job_id = ?1",
        "DELETE FROM job_webhooks WHERE job_id = ?1",
        "DELETE FROM tasks WHERE job_id = ?1",
        "DELETE FROM jobs WHERE id = ?1",
    ] {
        sqlx::query(statement)
            .bind(job_id)
            .execute(&mut *tx)
            .await
            .map_err(internal)?;
    }
    tx.commit().await.map_err(internal)?;
    metrics::counter!("stylenerf_jobs_deleted_total").increment(1);
    Ok(reply)
}

/// Deletes an upload's object, then its row.
async fn delete_upload(shared: &Shared, id: &str, key: &str) -> anyhow::Result<()> {
    shared.storage.delete(key).await?;
    sqlx::query("DELETE FROM uploads WHERE id = ?")
        .bind(id)
        .execute(&shared.db.write)
        .await?;
    Ok(())
}

/// One pass: finished jobs and uploads older than `keep` are deleted. Returns (jobs, uploads).
pub async fn sweep(shared: &Shared, keep: Duration) -> anyhow::Result<(usize, usize)> {
    let before = now_ms() - keep.as_millis().min(i64::MAX as u128) as i64;
    let system = Principal {
        name: "retention".into(),
        role: crate::auth::Role::Admin,
    };
    let jobs: Vec<String> = sqlx::query_scalar(
        "SELECT id FROM jobs WHERE state IN ('succeeded', 'failed', 'cancelled') \
         AND finished_at > 0 AND finished_at < ? ORDER BY finished_at LIMIT 1000",
    )
    .bind(before)
    .fetch_all(&shared.db.read)
    .await?;
    let mut deleted_jobs = 0;
    for id in &jobs {
        // A job rendered again since it was listed is running: not deleted.
        if delete_job(shared, &system, id).await.is_ok() {
            deleted_jobs += 1;
        }
    }
    let uploads: Vec<(String, String)> = sqlx::query_as(
        "SELECT id, key FROM uploads WHERE created_at < ? ORDER BY created_at LIMIT 1000",
    )
    .bind(before)
    .fetch_all(&shared.db.read)
    .await?;
    for (id, key) in &uploads {
        delete_upload(shared, id, key).await?;
    }
    Ok((deleted_jobs, uploads.len()))
}

/// Sweeps every `every` until shutdown.
pub async fn run(shared: Arc<Shared>, keep: Duration, every: Duration) {
    shared
        .every(every, || async {
            match sweep(&shared, keep).await {
                Ok((0, 0)) => {}
                Ok((jobs, uploads)) => {
                    tracing::info!(jobs, uploads, "retention: deleted old data")
                }
                Err(e) => tracing::warn!(error = %e, "retention sweep failed"),
            }
        })
        .await
}
