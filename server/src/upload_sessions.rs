//! Resumable uploads (`StartUpload`, `AppendUpload`, `GetUploadSession`, `FinishUpload`): the
//! bytes of one input arrive over any number of streams, each stored as one part object
//! `upload-sessions/<session>/<offset>` before its row commits it, so that what the
//! coordinator acknowledges survives a broken link and a coordinator restart. `FinishUpload`
//! joins the parts, checks the whole content's size and SHA-256, and validates and stores it
//! exactly as a one-stream `Upload` (`inputs`). Idle sessions are swept after
//! `--upload-session-hours`.
//!
//! An append runs in a task of its own, so that a client that hangs up mid-stream (the gRPC
//! handler is then dropped) still has the bytes that arrived committed; one append or finish
//! at a time per session (the `busy_upload_sessions` claim).

use crate::auth::Principal;
use crate::errors::{internal, invalid};
use crate::inputs::{
    check_declared_size, check_filename, size_limit, spool_file, store_upload, upload_kind,
    upload_receipt, InputKind, Received,
};
use crate::model::now_ms;
use crate::state::Shared;
use crate::storage::check_sha256;
use futures::{Stream, StreamExt};
use sha2::{Digest, Sha256};
use std::sync::Arc;
use std::time::Duration;
use stylenerf_proto::v1 as pb;
use tokio::io::AsyncWriteExt;
use tonic::Status;

/// A session's row.
#[derive(sqlx::FromRow)]
struct Session {
    id: String,
    owner: String,
    kind: String,
    filename: String,
    total_size: i64,
    committed: i64,
    upload_id: Option<String>,
    updated_at: i64,
}

impl Session {
    fn kind(&self) -> InputKind {
        // Only `start` writes the column, from an `InputKind`.
        InputKind::parse(&self.kind).unwrap_or(InputKind::Dataset)
    }

    fn to_pb(&self, ttl: Duration) -> pb::UploadSession {
        pb::UploadSession {
            session_id: self.id.clone(),
            kind: self.kind().to_pb() as i32,
            filename: self.filename.clone(),
            total_size: self.total_size as u64,
            committed_size: self.committed as u64,
            upload_id: self.upload_id.clone().unwrap_or_default(),
            expires_at_ms: self.updated_at + ttl.as_millis() as i64,
        }
    }
}

fn part_key(session: &str, offset: u64) -> String {
    // Zero-padded, so that a listing is in offset order.
    format!("upload-sessions/{session}/{offset:020}")
}

fn not_found(session: &str) -> Status {
    Status::not_found(format!("upload session {session:?} not found"))
}

/// The session `id` if `caller` may use it (another owner's is NOT_FOUND, like a missing one).
async fn load(shared: &Shared, caller: &Principal, id: &str) -> Result<Session, Status> {
    let session: Option<Session> = sqlx::query_as(
        "SELECT id, owner, kind, filename, total_size, committed, upload_id, updated_at \
         FROM upload_sessions WHERE id = ?",
    )
    .bind(id)
    .fetch_optional(&shared.db.read)
    .await
    .map_err(internal)?;
    session
        .filter(|s| caller.can_see(&s.owner))
        .ok_or_else(|| not_found(id))
}

/// The claim of one session by one call; released when dropped.
struct Claim {
    shared: Arc<Shared>,
    id: String,
}

impl Claim {
    fn take(shared: &Arc<Shared>, id: &str) -> Result<Claim, Status> {
        let mut busy = shared.busy_upload_sessions.lock().expect("not poisoned");
        if !busy.insert(id.to_string()) {
            return Err(Status::aborted(format!(
                "upload session {id:?} is being appended to or finished by another call: \
                 wait for it, then ask GetUploadSession where to resume"
            )));
        }
        Ok(Claim {
            shared: shared.clone(),
            id: id.to_string(),
        })
    }
}

impl Drop for Claim {
    fn drop(&mut self) {
        self.shared
            .busy_upload_sessions
            .lock()
            .expect("not poisoned")
            .remove(&self.id);
    }
}

/// `StartUpload`: a new, empty session of `caller`.
pub async fn start(
    shared: &Shared,
    caller: &Principal,
    request: pb::StartUploadRequest,
) -> Result<pb::UploadSession, Status> {
    let kind = upload_kind("kind", request.kind)?;
    let filename = check_filename("filename", &request.filename)?;
    check_declared_size(shared, "total_size", kind, request.total_size, true)?;
    crate::quotas::check_storage(
        shared,
        &caller.name,
        request.total_size,
        &format!("an upload of {} bytes", request.total_size),
    )
    .await?;
    let open: i64 = sqlx::query_scalar(
        "SELECT COUNT(*) FROM upload_sessions WHERE owner = ? AND upload_id IS NULL",
    )
    .bind(&caller.name)
    .fetch_one(&shared.db.read)
    .await
    .map_err(internal)?;
    let most = shared.config.limits.max_upload_sessions;
    if open as usize >= most {
        return Err(Status::resource_exhausted(format!(
            "{open} upload sessions are open (at most {most}): finish them, or they are deleted \
             after {} hours without an append",
            shared.config.upload_session_ttl.as_secs_f64() / 3600.0
        )));
    }
    let now = now_ms();
    let session = Session {
        id: format!("us-{}", uuid::Uuid::now_v7().simple()),
        owner: caller.name.clone(),
        kind: kind.as_str().to_string(),
        filename: filename.to_string(),
        total_size: request.total_size as i64,
        committed: 0,
        upload_id: None,
        updated_at: now,
    };
    sqlx::query(
        "INSERT INTO upload_sessions (id, owner, kind, filename, total_size, committed, \
         created_at, updated_at) VALUES (?, ?, ?, ?, ?, 0, ?, ?)",
    )
    .bind(&session.id)
    .bind(&session.owner)
    .bind(&session.kind)
    .bind(&session.filename)
    .bind(session.total_size)
    .bind(now)
    .bind(now)
    .execute(&shared.db.write)
    .await
    .map_err(internal)?;
    Ok(session.to_pb(shared.config.upload_session_ttl))
}

/// `GetUploadSession`.
pub async fn get(
    shared: &Shared,
    caller: &Principal,
    id: &str,
) -> Result<pb::UploadSession, Status> {
    Ok(load(shared, caller, id)
        .await?
        .to_pb(shared.config.upload_session_ttl))
}

/// `AppendUpload`: receives the stream in a task of its own (see the module comment).
pub async fn append<S>(
    shared: Arc<Shared>,
    caller: Principal,
    stream: S,
) -> Result<pb::UploadSession, Status>
where
    S: Stream<Item = Result<pb::UploadSessionChunk, Status>> + Send + Unpin + 'static,
{
    tokio::spawn(async move { receive_part(&shared, &caller, stream).await })
        .await
        .map_err(internal)?
}

async fn receive_part<S>(
    shared: &Arc<Shared>,
    caller: &Principal,
    mut stream: S,
) -> Result<pb::UploadSession, Status>
where
    S: Stream<Item = Result<pb::UploadSessionChunk, Status>> + Unpin,
{
    use pb::upload_session_chunk::Part;
    let resume = match stream.next().await {
        Some(Ok(pb::UploadSessionChunk {
            part: Some(Part::Resume(resume)),
        })) => resume,
        Some(Err(status)) => return Err(status),
        _ => {
            return Err(invalid(
                "resume",
                "the first message must name the session and the offset",
            ))
        }
    };
    let id = resume.session_id.as_str();
    load(shared, caller, id).await?;
    let _claim = Claim::take(shared, id)?;
    // Read again under the claim: another append may have committed in between.
    let session = load(shared, caller, id).await?;
    if let Some(upload) = &session.upload_id {
        return Err(Status::failed_precondition(format!(
            "upload session {id:?} is finished: its upload is {upload:?}"
        )));
    }
    let offset = session.committed as u64;
    if resume.offset != offset {
        return Err(Status::failed_precondition(format!(
            "resume.offset is {} but upload session {id:?} has {offset} bytes committed: \
             append from {offset}",
            resume.offset
        )));
    }
    let limit = match session.total_size {
        0 => size_limit(shared, session.kind()),
        declared => declared as u64,
    };
    let room = crate::quotas::storage_room(shared, &session.owner).await?;
    let spool = spool_file(shared)?;
    let mut file = tokio::fs::File::create(spool.path())
        .await
        .map_err(internal)?;
    let mut received = 0u64;
    // A broken stream still commits what arrived; the error is returned after.
    let mut broken = None;
    while let Some(message) = stream.next().await {
        let data = match message {
            Ok(pb::UploadSessionChunk {
                part: Some(Part::Data(data)),
            }) => data,
            Ok(_) => {
                return Err(invalid(
                    "resume",
                    "only the first message may name the session",
                ))
            }
            Err(status) => {
                broken = Some(status);
                break;
            }
        };
        if offset + received + data.len() as u64 > limit {
            let what = if session.total_size > 0 {
                "the total_size declared at StartUpload"
            } else {
                "the size limit of the input kind"
            };
            return Err(invalid(
                "data",
                format!("more than {limit} bytes, {what}: nothing of this stream was kept"),
            ));
        }
        if let Some(room) = room.filter(|room| received + data.len() as u64 > *room) {
            let what = "this append (nothing of it was kept)";
            return Err(crate::quotas::over_storage_quota(
                shared,
                &session.owner,
                what,
                room,
            ));
        }
        file.write_all(&data).await.map_err(internal)?;
        received += data.len() as u64;
    }
    file.flush().await.map_err(internal)?;
    drop(file);
    if received > 0 {
        shared
            .storage
            .put_file(&part_key(id, offset), spool.path())
            .await
            .map_err(internal)?;
        let mut tx = shared.db.write.begin().await.map_err(internal)?;
        sqlx::query("INSERT INTO upload_session_parts (session_id, offset, size) VALUES (?, ?, ?)")
            .bind(id)
            .bind(offset as i64)
            .bind(received as i64)
            .execute(&mut *tx)
            .await
            .map_err(internal)?;
        sqlx::query("UPDATE upload_sessions SET committed = ?, updated_at = ? WHERE id = ?")
            .bind((offset + received) as i64)
            .bind(now_ms())
            .bind(id)
            .execute(&mut *tx)
            .await
            .map_err(internal)?;
        tx.commit().await.map_err(internal)?;
        metrics::counter!("stylenerf_upload_session_bytes_total").increment(received);
    }
    if let Some(status) = broken {
        tracing::info!(session = id, committed = offset + received, error = %status, "upload stream broken; what arrived is committed");
        return Err(status);
    }
    Ok(load(shared, caller, id)
        .await?
        .to_pb(shared.config.upload_session_ttl))
}

/// `FinishUpload`: joins the parts, checks size and SHA-256, validates and stores the input.
pub async fn finish(
    shared: &Arc<Shared>,
    caller: &Principal,
    request: pb::FinishUploadRequest,
) -> Result<pb::UploadReceipt, Status> {
    let id = request.session_id.as_str();
    check_sha256("sha256", &request.sha256)?;
    load(shared, caller, id).await?;
    let _claim = Claim::take(shared, id)?;
    let session = load(shared, caller, id).await?;
    if let Some(upload) = &session.upload_id {
        // A repeated finish (its first answer lost): the same receipt, for the same content.
        let receipt = upload_receipt(shared, upload).await?;
        if receipt.sha256 != request.sha256 {
            return Err(invalid(
                "sha256",
                format!(
                    "upload session {id:?} was finished with SHA-256 {}",
                    receipt.sha256
                ),
            ));
        }
        return Ok(receipt);
    }
    let committed = session.committed as u64;
    for (field, declared) in [
        ("total_size", request.total_size),
        ("the total_size of StartUpload", session.total_size as u64),
    ] {
        if declared > 0 && declared != committed {
            return Err(invalid(
                "total_size",
                format!("{field} is {declared} bytes but {committed} are committed"),
            ));
        }
    }
    if committed == 0 {
        return Err(invalid("session_id", "no data was appended"));
    }
    let parts: Vec<(i64, i64)> = sqlx::query_as(
        "SELECT offset, size FROM upload_session_parts WHERE session_id = ? ORDER BY offset",
    )
    .bind(id)
    .fetch_all(&shared.db.read)
    .await
    .map_err(internal)?;
    let spool = spool_file(shared)?;
    let mut file = tokio::fs::File::create(spool.path())
        .await
        .map_err(internal)?;
    let mut hasher = Sha256::new();
    let mut joined = 0u64;
    // One part (a stream that was never cut) is copied to the upload's key inside the store.
    let only_part = (parts.len() == 1).then(|| part_key(id, 0));
    for (offset, size) in parts {
        let key = part_key(id, offset as u64);
        let read = shared
            .storage
            .append_to(&key, &mut file, |bytes| hasher.update(bytes))
            .await?;
        if offset as u64 != joined || read != size as u64 {
            return Err(internal(format!(
                "upload session {id}: part {key} holds {read} bytes at {offset}, expected \
                 {size} at {joined}"
            )));
        }
        joined += read;
    }
    file.flush().await.map_err(internal)?;
    drop(file);
    let actual = hex::encode(hasher.finalize());
    if actual != request.sha256 {
        return Err(invalid(
            "sha256",
            format!("checksum mismatch: the {committed} bytes committed have SHA-256 {actual}"),
        ));
    }
    let stored = store_upload(
        shared,
        Received {
            kind: session.kind(),
            filename: &session.filename,
            path: spool.path(),
            size: committed,
            sha256: actual,
            stored_as: only_part,
        },
    )
    .await?;
    let mut tx = shared.db.write.begin().await.map_err(internal)?;
    let receipt = stored.insert(&session.owner, &mut *tx).await?;
    sqlx::query("UPDATE upload_sessions SET upload_id = ?, updated_at = ? WHERE id = ?")
        .bind(&receipt.upload_id)
        .bind(now_ms())
        .bind(id)
        .execute(&mut *tx)
        .await
        .map_err(internal)?;
    sqlx::query("DELETE FROM upload_session_parts WHERE session_id = ?")
        .bind(id)
        .execute(&mut *tx)
        .await
        .map_err(internal)?;
    tx.commit().await.map_err(internal)?;
    delete_parts(shared, id).await;
    Ok(receipt)
}

/// Deletes a session's part objects (a failure is logged; the sweep tries again).
async fn delete_parts(shared: &Shared, id: &str) {
    let prefix = format!("upload-sessions/{id}/");
    let result = async {
        for (key, _) in shared.storage.list(&prefix).await? {
            shared.storage.delete(&key).await.map_err(internal)?;
        }
        Ok::<_, Status>(())
    }
    .await;
    if let Err(e) = result {
        tracing::warn!(session = id, error = %e, "deleting upload session parts failed");
    }
}

/// Deletes the sessions unused for longer than the TTL (parts first, then rows); returns
/// how many. Sessions in use are skipped.
pub async fn sweep(shared: &Arc<Shared>) -> anyhow::Result<usize> {
    let ttl = shared.config.upload_session_ttl;
    let before = now_ms() - ttl.as_millis().min(i64::MAX as u128) as i64;
    let idle: Vec<String> = sqlx::query_scalar(
        "SELECT id FROM upload_sessions WHERE updated_at < ? ORDER BY updated_at LIMIT 1000",
    )
    .bind(before)
    .fetch_all(&shared.db.read)
    .await?;
    let mut deleted = 0;
    for id in &idle {
        let Ok(_claim) = Claim::take(shared, id) else {
            continue;
        };
        delete_parts(shared, id).await;
        let mut tx = shared.db.write.begin().await?;
        sqlx::query("DELETE FROM upload_session_parts WHERE session_id = ?")
            .bind(id)
            .execute(&mut *tx)
            .await?;
        sqlx::query("DELETE FROM upload_sessions WHERE id = ? AND updated_at < ?")
            .bind(id)
            .bind(before)
            .execute(&mut *tx)
            .await?;
        tx.commit().await?;
        deleted += 1;
    }
    Ok(deleted)
}

/// Sweeps idle sessions until shutdown, every tenth of the TTL (between 1 s and 10 min).
pub async fn run(shared: Arc<Shared>) {
    let every = (shared.config.upload_session_ttl / 10)
        .clamp(Duration::from_secs(1), Duration::from_secs(600));
    shared
        .every(every, || async {
            match sweep(&shared).await {
                Ok(0) => {}
                Ok(n) => tracing::info!(sessions = n, "deleted idle upload sessions"),
                Err(e) => tracing::warn!(error = %e, "sweeping upload sessions failed"),
            }
        })
        .await
}
