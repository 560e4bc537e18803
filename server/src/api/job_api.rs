//! `JobService`: uploads, job creation (validation, idempotency, input copies), queries,
//! watching with replay, cancellation, artifact listing and download, and new renders.

use crate::auth::{require, Principal, Role, CLIENT_ROLES};
use crate::config::ArtifactUrls;
use crate::errors::{internal, invalid, invalid_all, Violation};
use crate::events::{read_after, Scope};
use crate::inputs::{receive_upload, resolve_input, InputKind};
use crate::jobs::{self, NewJob};
use crate::model::{job_state, job_state_from_pb, now_ms};
use crate::state::Shared;
use crate::storage::{check_key, check_prefix};
use futures::FutureExt;
use std::pin::Pin;
use std::sync::Arc;
use stylenerf_plan::Source;
use stylenerf_proto::v1 as pb;
use stylenerf_proto::v1::job_service_server::JobService;
use tokio::sync::{broadcast, mpsc};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send + 'static>>;

/// Longest accepted JSON document in a request field.
const MAX_JSON_BYTES: usize = 64 << 10;

pub struct JobApi {
    pub shared: Arc<Shared>,
}

/// Parses an optional JSON object field (`""` = `{}`).
fn json_object(
    field: &str,
    text: &str,
    violations: &mut Vec<Violation>,
) -> serde_json::Map<String, serde_json::Value> {
    if text.trim().is_empty() {
        return serde_json::Map::new();
    }
    if text.len() > MAX_JSON_BYTES {
        violations.push(Violation::new(field, "longer than 64 KiB"));
        return serde_json::Map::new();
    }
    match serde_json::from_str::<serde_json::Value>(text) {
        Ok(serde_json::Value::Object(map)) => map,
        Ok(_) => {
            violations.push(Violation::new(field, "must be a JSON object"));
            serde_json::Map::new()
        }
        Err(e) => {
            violations.push(Violation::new(field, format!("not valid JSON: {e}")));
            serde_json::Map::new()
        }
    }
}

/// The camera paths workers render (the engine's `PathKind::NAMES`).
pub const CAMERA_PATH_KINDS: [&str; 4] = ["interpolate", "train", "orbit", "spiral"];

/// Validates a render specification and returns its part of the task configuration.
fn render_spec(
    shared: &Shared,
    camera_path: Option<&pb::CameraPath>,
    blend: &[pb::StyleWeight],
    num_styles: usize,
    violations: &mut Vec<Violation>,
) -> serde_json::Map<String, serde_json::Value> {
    let mut extra = serde_json::Map::new();
    if let Some(path) = camera_path {
        if !(path.kind.is_empty() || CAMERA_PATH_KINDS.contains(&path.kind.as_str())) {
            violations.push(Violation::new(
                "camera_path.kind",
                format!(
                    "unknown kind {:?} (one of {}, or empty for the preset's path)",
                    path.kind,
                    CAMERA_PATH_KINDS.join(", ")
                ),
            ));
        }
        let max = shared.config.limits.max_render_frames;
        if path.num_frames > max {
            violations.push(Violation::new(
                "camera_path.num_frames",
                format!("at most {max} frames"),
            ));
        }
        if !(path.fps.is_finite() && (0.0..=240.0).contains(&path.fps)) {
            violations.push(Violation::new("camera_path.fps", "must be within 0..=240"));
        }
        let params = json_object("camera_path.params_json", &path.params_json, violations);
        extra.insert(
            "camera_path".into(),
            serde_json::json!({
                "kind": path.kind,
                "num_frames": path.num_frames,
                "fps": path.fps,
                "params": params,
            }),
        );
    }
    if !blend.is_empty() {
        let mut total = 0.0;
        for (i, w) in blend.iter().enumerate() {
            if w.style_index as usize >= num_styles {
                violations.push(Violation::new(
                    format!("style_blend[{i}].style_index"),
                    format!("the job has {num_styles} styles"),
                ));
            }
            if !(w.weight.is_finite() && w.weight >= 0.0) {
                violations.push(Violation::new(
                    format!("style_blend[{i}].weight"),
                    "must be a finite non-negative number",
                ));
            } else {
                total += w.weight;
            }
        }
        if total <= 0.0 {
            violations.push(Violation::new(
                "style_blend",
                "the weights must not all be 0",
            ));
        }
        let weights: Vec<serde_json::Value> = blend
            .iter()
            .map(|w| serde_json::json!({"style_index": w.style_index, "weight": w.weight / total.max(f64::MIN_POSITIVE)}))
            .collect();
        extra.insert("style_blend".into(), weights.into());
    }
    extra
}

/// Whether a CUDA worker has been heard from within the worker timeout.
async fn cuda_worker_live(shared: &Shared) -> Result<bool, Status> {
    let since = now_ms() - shared.config.worker_timeout.as_millis() as i64;
    let live: i64 = sqlx::query_scalar(
        "SELECT COUNT(*) FROM workers WHERE device LIKE 'cuda%' AND last_seen_at >= ?",
    )
    .bind(since)
    .fetch_one(&shared.db.read)
    .await
    .map_err(internal)?;
    Ok(live > 0)
}

/// Whether a live worker advertises every one of `tools`.
async fn tools_worker_live(shared: &Shared, tools: &[&str]) -> Result<bool, Status> {
    if tools.is_empty() {
        return Ok(true);
    }
    let since = now_ms() - shared.config.worker_timeout.as_millis() as i64;
    let advertised: Vec<String> =
        sqlx::query_scalar("SELECT tools FROM workers WHERE last_seen_at >= ?")
            .bind(since)
            .fetch_all(&shared.db.read)
            .await
            .map_err(internal)?;
    Ok(advertised.iter().any(|json| {
        let have: Vec<String> = serde_json::from_str(json).unwrap_or_default();
        tools.iter().all(|t| have.iter().any(|h| h == t))
    }))
}

/// Text that other people's terminals and pages show must not carry control characters
/// (escape sequences, carriage returns, NUL).
fn no_control_characters(field: &str, value: &str, violations: &mut Vec<Violation>) {
    if value.chars().any(char::is_control) {
        violations.push(Violation::new(
            field,
            "control characters (escape, carriage return, NUL, …) are not allowed",
        ));
    }
}

impl JobApi {
    async fn create(
        &self,
        caller: &Principal,
        req: pb::CreateJobRequest,
    ) -> Result<pb::CreateJobResponse, Status> {
        let shared = &self.shared;
        let mut violations = Vec::new();
        if req.name.chars().count() > 200 {
            violations.push(Violation::new("name", "longer than 200 characters"));
        }
        if req.idempotency_key.len() > 200 {
            violations.push(Violation::new("idempotency_key", "longer than 200 bytes"));
        }
        no_control_characters("name", &req.name, &mut violations);
        no_control_characters("idempotency_key", &req.idempotency_key, &mut violations);
        let preset = if req.preset.is_empty() {
            "quick".to_string()
        } else {
            req.preset.clone()
        };
        if !shared.config.presets.contains(&preset) {
            violations.push(Violation::new(
                "preset",
                format!(
                    "unknown preset {preset:?} (one of: {})",
                    shared.config.presets.join(", ")
                ),
            ));
        }
        if req.styles.is_empty() {
            violations.push(Violation::new(
                "styles",
                "at least one style image is needed",
            ));
        }
        if req.styles.len() > shared.config.limits.max_styles {
            violations.push(Violation::new(
                "styles",
                format!("at most {} styles", shared.config.limits.max_styles),
            ));
        }
        let overrides = json_object(
            "config_overrides_json",
            &req.config_overrides_json,
            &mut violations,
        );
        if let Some(checks) = shared
            .config
            .engine_checks
            .as_ref()
            .filter(|_| shared.config.presets.contains(&preset))
        {
            for (key, reason) in checks.settings(&preset, &overrides) {
                violations.push(Violation::new(
                    format!("config_overrides_json.{key}"),
                    reason,
                ));
            }
        }
        let requirements = req.requirements.clone().unwrap_or_default();
        for (i, label) in requirements.labels.iter().enumerate() {
            if label.is_empty() || label.len() > 100 {
                violations.push(Violation::new(
                    format!("requirements.labels[{i}]"),
                    "must be 1-100 characters",
                ));
            }
            no_control_characters(&format!("requirements.labels[{i}]"), label, &mut violations);
        }
        let render = render_spec(
            shared,
            req.camera_path.as_ref(),
            &req.style_blend,
            req.styles.len(),
            &mut violations,
        );
        check_metadata(&req.metadata, &mut violations);
        if !(-100..=100).contains(&req.priority) {
            violations.push(Violation::new(
                "priority",
                format!("{} is outside [-100, 100]", req.priority),
            ));
        }
        let now = crate::model::now_ms();
        if req.deadline_at_ms != 0
            && !(now < req.deadline_at_ms && req.deadline_at_ms <= now + 365 * 86_400_000)
        {
            violations.push(Violation::new(
                "deadline_at_ms",
                "must lie in the future, at most a year ahead (epoch milliseconds)",
            ));
        }
        let webhook = crate::webhooks::validate(
            req.webhook.as_ref(),
            shared.config.webhook_allow_private,
            &mut violations,
        )
        .await;
        if !violations.is_empty() {
            return Err(invalid_all(violations));
        }
        let idempotency_key =
            (!req.idempotency_key.is_empty()).then(|| req.idempotency_key.clone());
        if let Some(key) = &idempotency_key {
            if let Some(job) =
                jobs::find_by_idempotency_key(&shared.db.read, &caller.name, key).await?
            {
                return Ok(pb::CreateJobResponse {
                    job: Some(jobs::get_job(shared, caller, &job.id).await?),
                    created: false,
                    webhook_secret: String::new(),
                });
            }
        }
        let dataset = resolve_input(
            shared,
            caller,
            "dataset",
            &[InputKind::Dataset, InputKind::Photos],
            req.dataset.as_ref(),
        )
        .await?;
        // What a stage would refuse on this dataset (a depth loss without depth maps).
        if let (Some(checks), Some(facts)) = (&shared.config.engine_checks, &dataset.facts) {
            let refused: Vec<Violation> = checks
                .dataset_settings(&preset, &overrides, facts)
                .into_iter()
                .map(|(key, reason)| Violation::new(format!("config_overrides_json.{key}"), reason))
                .collect();
            if !refused.is_empty() {
                return Err(invalid_all(refused));
            }
        }
        let (dataset_source, dataset_extension) = (dataset.key, dataset.extension);
        let source = match (dataset.kind, dataset_extension.as_str()) {
            (InputKind::Photos, "tar") => Source::Photos,
            (InputKind::Photos, _) => Source::Video,
            _ => Source::Dataset,
        };
        let mut style_sources = Vec::new();
        for (i, style) in req.styles.iter().enumerate() {
            style_sources.push(
                resolve_input(
                    shared,
                    caller,
                    &format!("styles[{i}]"),
                    &[InputKind::Style],
                    Some(style),
                )
                .await
                .map(|style| (style.key, style.extension))?,
            );
        }
        let mut input_bytes = shared.storage.size(&dataset_source).await?;
        for (source, _) in &style_sources {
            input_bytes += shared.storage.size(source).await?;
        }
        crate::quotas::check_storage(
            shared,
            &caller.name,
            input_bytes,
            &format!("a job whose inputs take {input_bytes} bytes"),
        )
        .await?;
        let job_id = format!("j-{}", uuid::Uuid::now_v7().simple());
        let dataset_key = format!(
            "jobs/{job_id}/inputs/{}",
            source.input_name(&dataset_extension)
        );
        shared
            .storage
            .copy(&dataset_source, &dataset_key)
            .await
            .map_err(internal)?;
        let mut style_keys = Vec::new();
        for (i, (source, extension)) in style_sources.iter().enumerate() {
            let key = format!("jobs/{job_id}/inputs/styles/{i}.{extension}");
            shared.storage.copy(source, &key).await.map_err(internal)?;
            style_keys.push(key);
        }
        let tools: Vec<&str> = source
            .stages()
            .iter()
            .flat_map(|s| s.tools(source).iter().copied())
            .collect();
        let note = if requirements.require_cuda && !cuda_worker_live(shared).await? {
            "job accepted; it requires CUDA and no CUDA worker is connected: it waits until one \
             registers"
                .to_string()
        } else if !tools_worker_live(shared, &tools).await? {
            format!(
                "job accepted; its poses stage needs a worker with {} and none is connected: it \
                 waits until one registers",
                tools.join(" and ")
            )
        } else {
            "job accepted".to_string()
        };
        let new_job = NewJob {
            id: job_id.clone(),
            owner: caller.name.clone(),
            name: req.name.clone(),
            preset,
            overrides: serde_json::Value::Object(overrides),
            requirements,
            dataset_key,
            style_keys,
            idempotency_key: idempotency_key.clone(),
            render,
            note,
            webhook,
            metadata: req.metadata.clone().into_iter().collect(),
            priority: req.priority,
            deadline_at: req.deadline_at_ms,
            input_bytes,
        };
        let webhook_secret = new_job
            .webhook
            .as_ref()
            .map(|w| w.secret.clone())
            .unwrap_or_default();
        let max_attempts = shared.config.max_attempts;
        let new_job = Arc::new(new_job);
        let created = shared
            .writer
            .write(move |conn, batch| {
                let new_job = new_job.clone();
                async move { Ok(jobs::insert_job(conn, batch, &new_job, max_attempts).await?) }
                    .boxed()
            })
            .await?;
        let id = if created {
            shared.wake_workers();
            metrics::counter!("stylenerf_jobs_created_total").increment(1);
            job_id
        } else {
            // A concurrent request with the same idempotency key won.
            let key = idempotency_key.unwrap_or_default();
            jobs::find_by_idempotency_key(&shared.db.write, &caller.name, &key)
                .await?
                .map(|job| job.id)
                .ok_or_else(|| internal("idempotency key conflict without a job"))?
        };
        Ok(pb::CreateJobResponse {
            job: Some(jobs::get_job(shared, caller, &id).await?),
            created,
            webhook_secret: if created {
                webhook_secret
            } else {
                String::new()
            },
        })
    }
}

/// An object key a client names for one of its jobs: well formed and under `jobs/<job_id>/`.
fn check_job_key(job_id: &str, key: &str) -> Result<(), Status> {
    check_key("key", key)?;
    if !key.starts_with(&format!("jobs/{job_id}/")) {
        return Err(invalid("key", format!("must lie under jobs/{job_id}/")));
    }
    Ok(())
}

/// Whose jobs a listing or a watch covers: `None` for all (an admin who named no owner), else
/// one owner — the caller's own unless an admin named another.
fn owner_scope(caller: &Principal, requested: &str) -> Result<Option<String>, Status> {
    match (caller.role, requested.is_empty()) {
        (Role::Admin, true) => Ok(None),
        (Role::Admin, false) => Ok(Some(requested.to_string())),
        _ if requested.is_empty() || requested == caller.name => Ok(Some(caller.name.clone())),
        _ => Err(invalid("owner", "only admins may name another owner")),
    }
}

/// Checks a job's (or a filter's) metadata: at most 32 pairs, keys of 1-63 characters
/// `[A-Za-z0-9._/-]`, values of at most 512 characters without control characters.
fn check_metadata(
    metadata: &std::collections::HashMap<String, String>,
    violations: &mut Vec<Violation>,
) {
    if metadata.len() > 32 {
        violations.push(Violation::new(
            "metadata",
            format!("{} pairs; at most 32", metadata.len()),
        ));
    }
    let mut keys: Vec<&String> = metadata.keys().collect();
    keys.sort();
    for key in keys {
        let field = format!("metadata[{:?}]", key.chars().take(63).collect::<String>());
        let valid = (1..=63).contains(&key.len())
            && key
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '/' | '-'));
        if !valid {
            violations.push(Violation::new(
                &field,
                "keys have 1-63 characters among A-Z a-z 0-9 . _ / -",
            ));
            continue;
        }
        let value = &metadata[key];
        if value.chars().count() > 512 {
            violations.push(Violation::new(&field, "longer than 512 characters"));
        }
        no_control_characters(&field, value, violations);
    }
}

/// Streams the events of `scope` after `after_seq`, then live ones: for one job until it is
/// terminal, for an owner's (or every) job until the receiver goes or the coordinator stops.
async fn watch(
    shared: Arc<Shared>,
    scope: Scope,
    after_seq: i64,
    skip_progress: bool,
    tx: mpsc::Sender<Result<pb::Event, Status>>,
) {
    let mut live = shared.events.subscribe();
    let mut shutdown = shared.shutdown.clone();
    let mut last = after_seq;
    let wanted = |e: &pb::Event| !(skip_progress && e.kind == pb::EventKind::TaskProgress as i32);
    let is_end = |e: &pb::Event| {
        matches!(scope, Scope::Job(_))
            && e.kind == pb::EventKind::JobState as i32
            && matches!(
                pb::JobState::try_from(e.job_state),
                Ok(pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
            )
    };
    // Replays the log after `last`; returns false when the receiver is gone.
    async fn replay(
        shared: &Shared,
        scope: &Scope,
        last: &mut i64,
        wanted: &impl Fn(&pb::Event) -> bool,
        tx: &mpsc::Sender<Result<pb::Event, Status>>,
    ) -> bool {
        loop {
            let page = match read_after(&shared.db.read, scope, *last, 500).await {
                Ok(page) => page,
                Err(e) => {
                    let _ = tx.send(Err(internal(e))).await;
                    return false;
                }
            };
            let n = page.len();
            for event in page {
                *last = event.seq as i64;
                if wanted(&event) && tx.send(Ok(event)).await.is_err() {
                    return false;
                }
            }
            if n < 500 {
                return true;
            }
        }
    }
    if !replay(&shared, &scope, &mut last, &wanted, &tx).await {
        return;
    }
    if let Scope::Job(job_id) = &scope {
        let state: Option<String> = sqlx::query_scalar("SELECT state FROM jobs WHERE id = ?")
            .bind(job_id)
            .fetch_optional(&shared.db.read)
            .await
            .ok()
            .flatten();
        if state.as_deref().is_some_and(job_state::is_terminal) {
            // Anything committed between the replay and the state check.
            replay(&shared, &scope, &mut last, &wanted, &tx).await;
            return;
        }
    }
    // Whether a job is in scope, by id (an owner's jobs are looked up once each).
    let mut in_scope: std::collections::HashMap<String, bool> = Default::default();
    loop {
        tokio::select! {
            received = live.recv() => match received {
                Ok(event) => {
                    // Seq 0: a live-only progress update (not stored, so never replayed).
                    let live_only = event.seq == 0;
                    if !live_only && event.seq as i64 <= last {
                        continue;
                    }
                    let visible = match &scope {
                        Scope::Job(id) => event.job_id == *id,
                        Scope::All => true,
                        Scope::Owner(owner) => match in_scope.get(&event.job_id) {
                            Some(visible) => *visible,
                            None => {
                                let job_owner: Option<String> =
                                    sqlx::query_scalar("SELECT owner FROM jobs WHERE id = ?")
                                        .bind(&event.job_id)
                                        .fetch_optional(&shared.db.read)
                                        .await
                                        .ok()
                                        .flatten();
                                let visible = job_owner.as_deref() == Some(owner.as_str());
                                in_scope.insert(event.job_id.clone(), visible);
                                visible
                            }
                        },
                    };
                    if !visible {
                        continue;
                    }
                    if !live_only {
                        last = event.seq as i64;
                    }
                    let end = is_end(&event);
                    if wanted(&event) && tx.send(Ok(event)).await.is_err() {
                        return;
                    }
                    if end {
                        return;
                    }
                }
                Err(broadcast::error::RecvError::Lagged(_)) => {
                    if !replay(&shared, &scope, &mut last, &wanted, &tx).await {
                        return;
                    }
                }
                Err(broadcast::error::RecvError::Closed) => return,
            },
            _ = tx.closed() => return,
            _ = shutdown.changed() => {
                let _ = tx.send(Err(Status::unavailable("the coordinator is shutting down"))).await;
                return;
            }
        }
    }
}

#[tonic::async_trait]
impl JobService for JobApi {
    async fn upload(
        &self,
        request: Request<Streaming<pb::UploadChunk>>,
    ) -> Result<Response<pb::UploadReceipt>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let receipt = receive_upload(&self.shared, &caller, request.into_inner()).await?;
        tracing::info!(upload = %receipt.upload_id, owner = %caller.name, summary = %receipt.summary, "upload accepted");
        Ok(Response::new(receipt))
    }

    async fn create_job(
        &self,
        request: Request<pb::CreateJobRequest>,
    ) -> Result<Response<pb::CreateJobResponse>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let response = self.create(&caller, request.into_inner()).await?;
        if response.created {
            if let Some(job) = &response.job {
                tracing::info!(job = %job.id, owner = %caller.name, "job created");
            }
        }
        Ok(Response::new(response))
    }

    async fn get_job(
        &self,
        request: Request<pb::GetJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let job = jobs::get_job(&self.shared, &caller, &request.get_ref().job_id).await?;
        Ok(Response::new(job))
    }

    async fn list_jobs(
        &self,
        request: Request<pb::ListJobsRequest>,
    ) -> Result<Response<pb::ListJobsResponse>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let req = request.into_inner();
        let owner = owner_scope(&caller, &req.owner)?;
        let mut states = Vec::new();
        for (i, state) in req.states.iter().enumerate() {
            states.push(
                job_state_from_pb(*state)
                    .ok_or_else(|| invalid(format!("states[{i}]"), "unknown job state"))?,
            );
        }
        let page_size = match req.page_size {
            0 => 50,
            n => n.min(500),
        } as i64;
        let before = if req.page_token.is_empty() {
            i64::MAX
        } else {
            req.page_token
                .parse::<i64>()
                .map_err(|_| invalid("page_token", "not a token returned by ListJobs"))?
        };
        let mut violations = Vec::new();
        check_metadata(&req.metadata, &mut violations);
        if !violations.is_empty() {
            return Err(invalid_all(violations));
        }
        let mut rows = jobs::list_jobs(
            &self.shared.db.read,
            owner.as_deref(),
            &states,
            &req.metadata,
            before,
            page_size + 1,
        )
        .await?;
        let next_page_token = if rows.len() as i64 > page_size {
            rows.truncate(page_size as usize);
            rows.last().map(|r| r.row.to_string()).unwrap_or_default()
        } else {
            String::new()
        };
        let mut jobs_out = Vec::with_capacity(rows.len());
        for row in rows {
            let tasks = if req.include_tasks {
                jobs::load_tasks(&self.shared.db.read, &row.id).await?
            } else {
                Vec::new()
            };
            jobs_out.push(jobs::job_to_pb(row, tasks));
        }
        Ok(Response::new(pb::ListJobsResponse {
            jobs: jobs_out,
            next_page_token,
        }))
    }

    type WatchJobStream = BoxStream<pb::Event>;

    async fn watch_job(
        &self,
        request: Request<pb::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let req = request.into_inner();
        jobs::visible_job(&self.shared.db.read, &caller, &req.job_id).await?;
        let (tx, rx) = mpsc::channel(64);
        tokio::spawn(watch(
            self.shared.clone(),
            Scope::Job(req.job_id),
            req.after_seq.min(i64::MAX as u64) as i64,
            req.skip_progress,
            tx,
        ));
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    type WatchJobsStream = BoxStream<pb::Event>;

    async fn watch_jobs(
        &self,
        request: Request<pb::WatchJobsRequest>,
    ) -> Result<Response<Self::WatchJobsStream>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let req = request.into_inner();
        let scope = match owner_scope(&caller, &req.owner)? {
            None => Scope::All,
            Some(owner) => Scope::Owner(owner),
        };
        let (tx, rx) = mpsc::channel(64);
        tokio::spawn(watch(
            self.shared.clone(),
            scope,
            req.after_seq.min(i64::MAX as u64) as i64,
            req.skip_progress,
            tx,
        ));
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }

    async fn cancel_job(
        &self,
        request: Request<pb::CancelJobRequest>,
    ) -> Result<Response<pb::Job>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let req = request.into_inner();
        let mut violations = Vec::new();
        no_control_characters("reason", &req.reason, &mut violations);
        if req.reason.chars().count() > 1000 {
            violations.push(Violation::new("reason", "longer than 1000 characters"));
        }
        if !violations.is_empty() {
            return Err(invalid_all(violations));
        }
        jobs::cancel_job(&self.shared, &caller, &req.job_id, &req.reason).await?;
        tracing::info!(job = %req.job_id, by = %caller.name, "job cancelled");
        let job = jobs::get_job(&self.shared, &caller, &req.job_id).await?;
        Ok(Response::new(job))
    }

    async fn delete_job(
        &self,
        request: Request<pb::DeleteJobRequest>,
    ) -> Result<Response<pb::DeleteJobResponse>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let req = request.into_inner();
        let reply = crate::retention::delete_job(&self.shared, &caller, &req.job_id).await?;
        tracing::info!(job = %req.job_id, by = %caller.name, objects = reply.deleted_objects,
            bytes = reply.deleted_bytes, "job deleted");
        Ok(Response::new(reply))
    }

    async fn list_webhook_deliveries(
        &self,
        request: Request<pb::ListWebhookDeliveriesRequest>,
    ) -> Result<Response<pb::ListWebhookDeliveriesResponse>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let req = request.into_inner();
        jobs::visible_job(&self.shared.db.read, &caller, &req.job_id).await?;
        let deliveries = crate::webhooks::deliveries(&self.shared, &req.job_id).await?;
        Ok(Response::new(pb::ListWebhookDeliveriesResponse {
            deliveries,
        }))
    }

    async fn start_upload(
        &self,
        request: Request<pb::StartUploadRequest>,
    ) -> Result<Response<pb::UploadSession>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let session =
            crate::upload_sessions::start(&self.shared, &caller, request.into_inner()).await?;
        Ok(Response::new(session))
    }

    async fn append_upload(
        &self,
        request: Request<Streaming<pb::UploadSessionChunk>>,
    ) -> Result<Response<pb::UploadSession>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let session =
            crate::upload_sessions::append(self.shared.clone(), caller, request.into_inner())
                .await?;
        Ok(Response::new(session))
    }

    async fn get_upload_session(
        &self,
        request: Request<pb::GetUploadSessionRequest>,
    ) -> Result<Response<pb::UploadSession>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let session =
            crate::upload_sessions::get(&self.shared, &caller, &request.get_ref().session_id)
                .await?;
        Ok(Response::new(session))
    }

    async fn finish_upload(
        &self,
        request: Request<pb::FinishUploadRequest>,
    ) -> Result<Response<pb::UploadReceipt>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let receipt =
            crate::upload_sessions::finish(&self.shared, &caller, request.into_inner()).await?;
        tracing::info!(upload = %receipt.upload_id, owner = %caller.name, summary = %receipt.summary, "resumable upload accepted");
        Ok(Response::new(receipt))
    }

    async fn list_artifacts(
        &self,
        request: Request<pb::ListArtifactsRequest>,
    ) -> Result<Response<pb::ListArtifactsResponse>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let req = request.into_inner();
        jobs::visible_job(&self.shared.db.read, &caller, &req.job_id).await?;
        let prefix = format!("jobs/{}/{}", req.job_id, req.prefix);
        if !req.prefix.is_empty() {
            check_prefix("prefix", &req.prefix)?;
        }
        let known: std::collections::HashMap<String, String> =
            jobs::load_artifacts(&self.shared.db.read, &req.job_id)
                .await?
                .into_values()
                .flatten()
                .map(|a| (a.key, a.sha256))
                .collect();
        let artifacts = self
            .shared
            .storage
            .list(&prefix)
            .await?
            .into_iter()
            .map(|(key, size)| pb::Artifact {
                sha256: known.get(&key).cloned().unwrap_or_default(),
                key,
                size,
            })
            .collect();
        Ok(Response::new(pb::ListArtifactsResponse { artifacts }))
    }

    type DownloadArtifactStream = BoxStream<pb::ObjectChunk>;

    async fn download_artifact(
        &self,
        request: Request<pb::DownloadArtifactRequest>,
    ) -> Result<Response<Self::DownloadArtifactStream>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let req = request.into_inner();
        jobs::visible_job(&self.shared.db.read, &caller, &req.job_id).await?;
        check_job_key(&req.job_id, &req.key)?;
        let stream = self.shared.storage.get_stream(&req.key, req.offset).await?;
        Ok(Response::new(Box::pin(stream)))
    }

    async fn get_artifact_url(
        &self,
        request: Request<pb::GetArtifactUrlRequest>,
    ) -> Result<Response<pb::ArtifactUrl>, Status> {
        const DEFAULT_TTL: u32 = 3600;
        const MAX_TTL: u32 = 7 * 86_400;
        let caller = require(&request, CLIENT_ROLES)?;
        let req = request.into_inner();
        jobs::visible_job(&self.shared.db.read, &caller, &req.job_id).await?;
        check_job_key(&req.job_id, &req.key)?;
        if req.ttl_seconds > MAX_TTL {
            return Err(invalid(
                "ttl_seconds",
                format!("{} is more than 7 days ({MAX_TTL})", req.ttl_seconds),
            ));
        }
        let storage = &self.shared.storage;
        let by_store = match self.shared.config.artifact_urls {
            ArtifactUrls::Auto => storage.can_sign(),
            ArtifactUrls::Store => true,
            ArtifactUrls::Coordinator => false,
        };
        let size = storage.size(&req.key).await?;
        let ttl = if req.ttl_seconds == 0 {
            DEFAULT_TTL
        } else {
            req.ttl_seconds
        };
        let expires_at_ms = crate::model::now_ms() + i64::from(ttl) * 1000;
        let url = if by_store {
            storage
                .presigned_get(&req.key, std::time::Duration::from_secs(ttl.into()))
                .await
                .ok_or_else(|| internal("--artifact-urls store with a store that cannot sign"))?
                .map_err(internal)?
        } else {
            let Some(downloads) = &self.shared.downloads else {
                return Err(Status::failed_precondition(
                    "this coordinator serves no HTTP downloads (start it with --http-listen) \
                     and its store signs no URLs; use DownloadArtifact",
                ));
            };
            format!(
                "{}{}",
                downloads.public_url,
                downloads.signer.path(&req.key, expires_at_ms)
            )
        };
        Ok(Response::new(pb::ArtifactUrl {
            url,
            expires_at_ms,
            size,
        }))
    }

    async fn render_job(
        &self,
        request: Request<pb::RenderJobRequest>,
    ) -> Result<Response<pb::Task>, Status> {
        let caller = require(&request, CLIENT_ROLES)?;
        let req = request.into_inner();
        let job = jobs::visible_job(&self.shared.db.read, &caller, &req.job_id).await?;
        let num_styles = serde_json::from_str::<Vec<String>>(&job.style_keys)
            .map(|v| v.len())
            .unwrap_or(0);
        let mut violations = Vec::new();
        let mut overrides = match serde_json::from_str::<serde_json::Value>(&job.overrides) {
            Ok(serde_json::Value::Object(map)) => map,
            _ => serde_json::Map::new(),
        };
        overrides.extend(json_object(
            "config_overrides_json",
            &req.config_overrides_json,
            &mut violations,
        ));
        let extra = render_spec(
            &self.shared,
            req.camera_path.as_ref(),
            &req.style_blend,
            num_styles,
            &mut violations,
        );
        if !violations.is_empty() {
            return Err(invalid_all(violations));
        }
        let task = jobs::add_render(
            &self.shared,
            &caller,
            &req.job_id,
            serde_json::Value::Object(overrides),
            extra,
        )
        .await?;
        tracing::info!(job = %req.job_id, task = task.id, "render requested");
        Ok(Response::new(task))
    }
}
