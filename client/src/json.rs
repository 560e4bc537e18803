//! JSON views of the protocol's messages for scripts and web backends: proto field names, enums
//! as their short names (`"state": "running"`, `"stage": "nerf_pretrain"`), JSON-valued string
//! fields (`*_json`) embedded as JSON under the name without `_json`, times in epoch ms.

use crate::download::DownloadedFile;
use crate::names;
use serde_json::{json, Value};
use stylenerf_proto::v1 as pb;

/// A `*_json` field as JSON (`""` = `{}`; text that does not parse is kept as a string).
fn embedded(text: &str) -> Value {
    if text.trim().is_empty() {
        return json!({});
    }
    serde_json::from_str(text).unwrap_or_else(|_| Value::String(text.to_string()))
}

pub fn progress(p: &pb::Progress) -> Value {
    json!({
        "step": p.step,
        "total": p.total,
        "loss": p.loss,
        "metrics": p.metrics,
        "eta_seconds": p.eta_seconds,
        "message": p.message,
    })
}

pub fn artifact(a: &pb::Artifact) -> Value {
    json!({"key": a.key, "size": a.size, "sha256": a.sha256})
}

pub fn requirements(r: &pb::Requirements) -> Value {
    json!({
        "require_cuda": r.require_cuda,
        "labels": r.labels,
        "memory_bytes": r.memory_bytes,
    })
}

pub fn task(t: &pb::Task) -> Value {
    json!({
        "id": t.id,
        "job_id": t.job_id,
        "stage": names::stage(t.stage),
        "state": names::task_state(t.state),
        "attempt": t.attempt,
        "max_attempts": t.max_attempts,
        "progress": t.progress.as_ref().map(progress),
        "worker_id": t.worker_id,
        "lease_expires_at_ms": t.lease_expires_at_ms,
        "created_at_ms": t.created_at_ms,
        "started_at_ms": t.started_at_ms,
        "finished_at_ms": t.finished_at_ms,
        "error": t.error,
        "output_prefix": t.output_prefix,
        "outputs": t.outputs.iter().map(artifact).collect::<Vec<_>>(),
        "depends_on": t.depends_on,
        "config": embedded(&t.config_json),
    })
}

pub fn job(j: &pb::Job) -> Value {
    json!({
        "id": j.id,
        "name": j.name,
        "owner": j.owner,
        "state": names::job_state(j.state),
        "preset": j.preset,
        "config_overrides": embedded(&j.config_overrides_json),
        "requirements": j.requirements.as_ref().map(requirements),
        "dataset_key": j.dataset_key,
        "style_keys": j.style_keys,
        "idempotency_key": j.idempotency_key,
        "created_at_ms": j.created_at_ms,
        "updated_at_ms": j.updated_at_ms,
        "finished_at_ms": j.finished_at_ms,
        "error": j.error,
        "tasks": j.tasks.iter().map(task).collect::<Vec<_>>(),
    })
}

pub fn event(e: &pb::Event) -> Value {
    let mut value = json!({
        "seq": e.seq,
        "job_id": e.job_id,
        "at_ms": e.at_ms,
        "kind": names::event_kind(e.kind),
    });
    let object = value.as_object_mut().expect("an object");
    let kind = pb::EventKind::try_from(e.kind).unwrap_or_default();
    if matches!(kind, pb::EventKind::JobCreated | pb::EventKind::JobState) {
        object.insert("job_state".into(), names::job_state(e.job_state).into());
    }
    if matches!(kind, pb::EventKind::TaskState | pb::EventKind::TaskProgress) {
        object.insert("task_id".into(), e.task_id.into());
        object.insert("stage".into(), names::stage(e.stage).into());
    }
    if kind == pb::EventKind::TaskState {
        object.insert("task_state".into(), names::task_state(e.task_state).into());
        object.insert("attempt".into(), e.attempt.into());
    }
    if let Some(p) = &e.progress {
        object.insert("progress".into(), progress(p));
    }
    if !e.message.is_empty() {
        object.insert("message".into(), e.message.clone().into());
    }
    value
}

pub fn receipt(r: &pb::UploadReceipt) -> Value {
    let kind = pb::UploadKind::try_from(r.kind)
        .map(|k| {
            k.as_str_name()
                .trim_start_matches("UPLOAD_KIND_")
                .to_ascii_lowercase()
        })
        .unwrap_or_default();
    json!({
        "upload_id": r.upload_id,
        "kind": kind,
        "size": r.size,
        "sha256": r.sha256,
        "summary": r.summary,
    })
}

pub fn downloaded(d: &DownloadedFile) -> Value {
    json!({
        "key": d.key,
        "path": d.path,
        "size": d.size,
        "sha256": d.sha256,
        "skipped": d.skipped,
    })
}
