//! Per-owner quotas (`--max-running-tasks-per-owner`, `--max-stored-gib-per-owner`, and
//! `[quotas.<name>]` in the config file). Stored bytes are an owner's uploads, open upload
//! sessions, and jobs (copied inputs plus the outputs their workers recorded); new uploads,
//! appends and jobs that would pass the quota are refused with RESOURCE_EXHAUSTED, checked at
//! each request (so concurrent requests may pass it by one request's size). The running-task
//! limit is applied where tasks are leased (`scheduler`).

use crate::errors::internal;
use crate::state::Shared;
use tonic::Status;

/// Bytes stored for `owner`.
pub async fn stored_bytes(shared: &Shared, owner: &str) -> Result<u64, Status> {
    let bytes: i64 = sqlx::query_scalar(
        "SELECT (SELECT COALESCE(SUM(size), 0) FROM uploads WHERE owner = ?1) \
         + (SELECT COALESCE(SUM(committed), 0) FROM upload_sessions \
            WHERE owner = ?1 AND upload_id IS NULL) \
         + (SELECT COALESCE(SUM(input_bytes), 0) FROM jobs WHERE owner = ?1) \
         + (SELECT COALESCE(SUM(a.size), 0) FROM artifacts a JOIN jobs j ON j.id = a.job_id \
            WHERE j.owner = ?1)",
    )
    .bind(owner)
    .fetch_one(&shared.db.read)
    .await
    .map_err(internal)?;
    Ok(bytes.max(0) as u64)
}

/// How many more bytes `owner` may store (`None`: no quota).
pub async fn storage_room(shared: &Shared, owner: &str) -> Result<Option<u64>, Status> {
    let quota = shared.config.quotas.of(owner).stored_bytes;
    if quota == 0 {
        return Ok(None);
    }
    Ok(Some(
        quota.saturating_sub(stored_bytes(shared, owner).await?),
    ))
}

/// RESOURCE_EXHAUSTED for `what` (e.g. "this upload of 5000 bytes"), which does not fit.
pub fn over_storage_quota(shared: &Shared, owner: &str, what: &str, room: u64) -> Status {
    let quota = shared.config.quotas.of(owner).stored_bytes;
    Status::resource_exhausted(format!(
        "{what} does not fit in the storage quota of {owner:?}: {} of {quota} bytes are \
         used; delete finished jobs (DeleteJob) to make room",
        quota.saturating_sub(room)
    ))
}

/// Refuses `what`, which adds `adding` bytes, if it does not fit in `owner`'s quota.
pub async fn check_storage(
    shared: &Shared,
    owner: &str,
    adding: u64,
    what: &str,
) -> Result<(), Status> {
    match storage_room(shared, owner).await? {
        Some(room) if adding > room => Err(over_storage_quota(shared, owner, what, room)),
        _ => Ok(()),
    }
}
